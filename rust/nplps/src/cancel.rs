//! Cooperative cancellation of a running computation (for example on Ctrl-C).
//!
//! A [`Cancel`] token is shared by the caller and the computation (it travels in
//! [`crate::Problem::cancel`]). The caller may call [`Cancel::cancel`] from any thread; the
//! computation checks the token every few facets of a local step, at every conjugate-gradient
//! iteration of the global step and between stages, and returns [`Error::Cancelled`]. A check
//! is one relaxed atomic load, so a computation stops within a few milliseconds of the request
//! (the exceptions are single library calls such as the direct solver's sparse factorization).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use crate::error::{Error, Result};

/// A cancellation flag shared between threads; the default token is never cancelled.
#[derive(Debug, Clone, Default)]
pub struct Cancel(Option<Arc<AtomicBool>>);

/// A token that is never cancelled, for callers that need a `&'static Cancel`.
static NEVER: Cancel = Cancel(None);

impl Cancel {
    /// A new token, not cancelled yet.
    pub fn new() -> Cancel {
        Cancel(Some(Arc::new(AtomicBool::new(false))))
    }

    /// A token that is never cancelled.
    pub fn never() -> &'static Cancel {
        &NEVER
    }

    /// Asks every computation holding this token (or a clone) to stop.
    pub fn cancel(&self) {
        if let Some(flag) = &self.0 {
            flag.store(true, Ordering::Relaxed);
        }
    }

    /// Whether [`Cancel::cancel`] was called.
    #[inline]
    pub fn is_cancelled(&self) -> bool {
        self.0.as_ref().is_some_and(|f| f.load(Ordering::Relaxed))
    }

    /// `Err(Error::Cancelled)` once the token is cancelled.
    #[inline]
    pub fn check(&self) -> Result<()> {
        if self.is_cancelled() {
            Err(Error::Cancelled)
        } else {
            Ok(())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clones_share_the_flag() {
        let token = Cancel::new();
        let clone = token.clone();
        assert!(clone.check().is_ok());
        token.cancel();
        assert!(clone.is_cancelled());
        assert_eq!(clone.check(), Err(Error::Cancelled));
        Cancel::never().cancel();
        assert!(!Cancel::never().is_cancelled());
    }
}
