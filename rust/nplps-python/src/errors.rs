//! Mapping of the core's typed errors (and any panic) onto the exceptions of `nplps.errors`.

use std::panic::{catch_unwind, AssertUnwindSafe};

use pyo3::prelude::*;

// The exceptions of `nplps.errors`, imported (and type-checked) on first use.
pyo3::import_exception!(nplps.errors, InputError);
pyo3::import_exception!(nplps.errors, RigError);
pyo3::import_exception!(nplps.errors, SolverError);
pyo3::import_exception!(nplps.errors, MemoryLimitError);

/// Converts a core error into the matching Python exception, carrying the error's fields as
/// attributes: `MemoryLimitError.what` / `.needed` / `.limit` (bytes, None when unknown) /
/// `.explicit`; `InputError.argument` (the parameter or array) with `.value` (an out-of-range
/// parameter's value), `.expected` / `.got` (a wrong size), `.index` (the first bad value) or
/// `.path` (an unreadable image); an image file that the system cannot write is an `OSError`
/// of its errno, with `filename` the file.
pub fn to_py(err: nplps::Error) -> PyErr {
    let message = err.to_string();
    let bytes = |x: f64| (x.is_finite() && x >= 0.0).then(|| x.round() as u64);
    match err {
        nplps::Error::Rig(_) => RigError::new_err(message),
        nplps::Error::Solver(_) => SolverError::new_err(message),
        nplps::Error::Memory {
            what,
            needed,
            limit,
            explicit,
        } => with_fields(MemoryLimitError::new_err(message), |e| {
            e.setattr("what", what)?;
            e.setattr("needed", bytes(needed))?;
            e.setattr("limit", bytes(limit))?;
            e.setattr("explicit", explicit)
        }),
        nplps::Error::Cancelled => {
            pyo3::exceptions::PyKeyboardInterrupt::new_err("reconstruction cancelled")
        }
        nplps::Error::Shape {
            what,
            expected,
            got,
            ..
        } => with_fields(InputError::new_err(message), |e| {
            e.setattr("argument", what)?;
            e.setattr("expected", expected)?;
            e.setattr("got", got)
        }),
        nplps::Error::NonFinite { what, index, .. } => {
            with_fields(InputError::new_err(message), |e| {
                e.setattr("argument", what)?;
                e.setattr("index", index)
            })
        }
        nplps::Error::OutOfRange { name, value, .. } => {
            with_fields(InputError::new_err(message), |e| {
                e.setattr("argument", name)?;
                e.setattr("value", value)
            })
        }
        nplps::Error::Image { path, .. } => with_fields(InputError::new_err(message), |e| {
            e.setattr("path", path.to_string_lossy().into_owned())
        }),
        // A file the system refused to write: the OSError of its errno, naming the file.
        nplps::Error::ImageWrite {
            path,
            os_error: Some(errno),
            reason,
        } => pyo3::exceptions::PyOSError::new_err((
            errno,
            reason,
            path.to_string_lossy().into_owned(),
        )),
        // Unusable (and any input error a later version adds): what the caller passed in
        // cannot be used.
        _ => InputError::new_err(message),
    }
}

/// `err` with the attributes that `set` gives its exception value (unchanged if setting fails,
/// which it does not for the classes of `nplps.errors`).
pub fn with_fields(
    err: PyErr,
    set: impl FnOnce(&Bound<'_, pyo3::exceptions::PyBaseException>) -> PyResult<()>,
) -> PyErr {
    Python::attach(|py| {
        // Setting the attributes of a fresh exception of nplps.errors cannot fail; if it ever
        // did, the exception without them is still the right one to raise.
        let _ = set(err.value(py));
    });
    err
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
