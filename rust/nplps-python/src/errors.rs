//! Mapping of the core's typed errors (and any panic) onto the exceptions of `nplps.errors`.

use std::panic::{catch_unwind, AssertUnwindSafe};

use pyo3::prelude::*;
use pyo3::types::PyType;

/// Raises `nplps.errors.<class_name>(message)`.
pub fn py_error(py: Python<'_>, class_name: &str, message: String) -> PyErr {
    let class = py
        .import("nplps.errors")
        .and_then(|m| m.getattr(class_name))
        .and_then(|c| c.cast_into::<PyType>().map_err(PyErr::from));
    match class {
        Ok(class) => PyErr::from_type(class, message),
        Err(e) => e,
    }
}

/// Converts a core error into the matching Python exception.
pub fn to_py(py: Python<'_>, err: nplps::Error) -> PyErr {
    let class = match &err {
        nplps::Error::Input(_) => "InputError",
        nplps::Error::Rig(_) => "RigError",
        nplps::Error::Solver(_) => "SolverError",
        nplps::Error::Memory { .. } => "MemoryLimitError",
        nplps::Error::Cancelled => {
            return pyo3::exceptions::PyKeyboardInterrupt::new_err("reconstruction cancelled")
        }
    };
    py_error(py, class, err.to_string())
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
