//! PNG decoding for `nplps.io`: the bindings of `nplps::io::read_pngs` (several files in
//! parallel, with the GIL released); the decoder and its rules are in the core's `io` module.

use std::path::PathBuf;

use nplps::io::{Decoded, Pixels};
use numpy::ndarray::{ArrayD, IxDyn};
use numpy::IntoPyArray;
use pyo3::prelude::*;
use pyo3::types::PyList;

use crate::errors::InputError;

/// Decodes the PNG files `paths` (in parallel) into a list of `uint8` / `uint16` arrays of shape
/// `(H, W)` or `(H, W, 3)`, in the order of `paths`.
///
/// Raises `nplps.errors.InputError` naming the first file (in the order of `paths`) that is
/// missing, is not a valid PNG, or declares more than `max_pixels` pixels.
#[pyfunction]
pub fn read_pngs<'py>(
    py: Python<'py>,
    paths: Vec<PathBuf>,
    max_pixels: u64,
) -> PyResult<Bound<'py, PyList>> {
    let decoded: Vec<nplps::Result<Decoded>> = py.detach(|| {
        crate::pool::fork_safe(|| nplps::io::read_pngs(&paths, max_pixels)).unwrap_or_else(|why| {
            paths
                .iter()
                .map(|path| {
                    Err(nplps::Error::Image {
                        path: path.clone(),
                        reason: why.clone(),
                    })
                })
                .collect()
        })
    });
    let mut arrays = Vec::with_capacity(decoded.len());
    for (path, image) in paths.iter().zip(decoded) {
        let image = image.map_err(|e| InputError::new_err(e.to_string()))?;
        let fail = |reason: String| {
            InputError::new_err(format!("cannot read image '{}': {reason}", path.display()))
        };
        let shape = IxDyn(&image.shape);
        let array = match image.pixels {
            Pixels::U8(v) => {
                ArrayD::from_shape_vec(shape, v).map(|a| a.into_pyarray(py).into_any())
            }
            Pixels::U16(v) => {
                ArrayD::from_shape_vec(shape, v).map(|a| a.into_pyarray(py).into_any())
            }
            _ => return Err(fail("an unsupported sample type".to_string())),
        }
        .map_err(|e| fail(format!("internal error (please report it): {e}")))?;
        arrays.push(array);
    }
    PyList::new(py, arrays)
}
