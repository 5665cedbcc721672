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

/// `x` with 6 significant digits, like C's `%g`: plain between 1e-4 and 1e6, else scientific
/// (messages never print a number with hundreds of digits).
pub fn g6(x: f64) -> String {
    if !x.is_finite() || x == 0.0 {
        return format!("{x}");
    }
    let exponent = x.abs().log10().floor() as i32;
    if (-4..6).contains(&exponent) {
        let decimals = (5 - exponent).max(0) as usize;
        let text = format!("{x:.decimals$}");
        if text.contains('.') {
            text.trim_end_matches('0').trim_end_matches('.').to_string()
        } else {
            text
        }
    } else {
        format!("{x:.5e}")
    }
}

#[cfg(test)]
mod tests {
    use super::g6;

    #[test]
    fn numbers_print_like_percent_g() {
        assert_eq!(g6(200.0), "200");
        assert_eq!(g6(0.000123456789), "0.000123457");
        assert_eq!(g6(-1.23456789), "-1.23457");
        assert_eq!(g6(1e300), "1.00000e300");
        assert_eq!(g6(f64::NAN), "NaN");
    }
}
