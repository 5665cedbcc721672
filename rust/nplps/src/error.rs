//! Typed errors of the crate.

use thiserror::Error;

/// Everything that can go wrong in nplps, with a message that names the problem.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum Error {
    /// The input images, mask, depth or options are invalid.
    #[error("{0}")]
    Input(String),
    /// The rig (camera or lights) is invalid.
    #[error("{0}")]
    Rig(String),
    /// The sparse factorization or solve failed.
    #[error("solver failed: {0}")]
    Solver(String),
    /// The caller asked the iteration to stop (for example on Ctrl-C).
    #[error("reconstruction cancelled")]
    Cancelled,
}

/// Result alias used across the crate.
pub type Result<T> = std::result::Result<T, Error>;

/// Returns `Err(Error::Input(msg))` unless `cond` holds.
pub(crate) fn ensure_input(cond: bool, msg: impl FnOnce() -> String) -> Result<()> {
    if cond {
        Ok(())
    } else {
        Err(Error::Input(msg()))
    }
}
