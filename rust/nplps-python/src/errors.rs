//! Mapping of the core's typed errors (and any panic) onto the exceptions of `nplps.errors`.

use std::panic::{catch_unwind, AssertUnwindSafe};

use pyo3::prelude::*;

// The exceptions of `nplps.errors`, imported (and type-checked) on first use.
pyo3::import_exception!(nplps.errors, InputError);
pyo3::import_exception!(nplps.errors, RigError);
pyo3::import_exception!(nplps.errors, SolverError);
pyo3::import_exception!(nplps.errors, MemoryLimitError);

/// Converts a core error into the matching Python exception.
pub fn to_py(err: nplps::Error) -> PyErr {
    let message = err.to_string();
    match err {
        nplps::Error::Rig(_) => RigError::new_err(message),
        nplps::Error::Solver(_) => SolverError::new_err(message),
        nplps::Error::Memory { .. } => MemoryLimitError::new_err(message),
        nplps::Error::Cancelled => {
            pyo3::exceptions::PyKeyboardInterrupt::new_err("reconstruction cancelled")
        }
        // Shape, NonFinite, OutOfRange, Unusable: what the caller passed in cannot be used
        // (and any input error a later version adds).
        _ => InputError::new_err(message),
    }
}

/// Runs `f`, turning a panic into `nplps.Error::Solver` so that no panic reaches Python, on a
/// thread pool that works after `fork()` (see [`crate::pool`]).
pub fn no_panic<T: Send>(f: impl FnOnce() -> nplps::Result<T> + Send) -> nplps::Result<T> {
    let guarded = || crate::pool::fork_safe(f).unwrap_or_else(|why| Err(nplps::Error::Solver(why)));
    catch_unwind(AssertUnwindSafe(guarded)).unwrap_or_else(|payload| {
        let what = payload
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| payload.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "unknown panic".to_string());
        Err(nplps::Error::Solver(format!(
            "internal error (please report it): {what}"
        )))
    })
}
