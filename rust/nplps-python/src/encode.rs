//! PNG encoding for `nplps.export`: the binding of `nplps::io::write_pngs` (several files in
//! parallel on a pool of threads of their own, with the GIL released); the encoder and its rules are in the core's `io` module.

use std::path::PathBuf;

use nplps::io::{Image, PngCompression, PngFilter, PngOptions, Samples};
use numpy::{PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;

use crate::errors::InputError;

/// The samples of one array to write: 8- or 16-bit, borrowed from Python.
enum Array<'py> {
    U8(PyReadonlyArrayDyn<'py, u8>),
    U16(PyReadonlyArrayDyn<'py, u16>),
}

/// Writes the images `jobs` (file, `uint8` / `uint16` array of shape `(H, W)` or `(H, W, 3)`)
/// as PNG files of the arrays' bit depth, in parallel.
///
/// `compression` is "none", "fast", "balanced" or "high"; `filter` is "adaptive", "none",
/// "sub", "up" or "paeth". Raises `OSError` (with `filename`) for the first file, in the order
/// of `jobs`, that the system cannot write, and `InputError` for an array that is not an image
/// of 8 or 16 bits (checked before anything is written).
#[pyfunction]
pub fn write_pngs(
    py: Python<'_>,
    jobs: Vec<(PathBuf, Bound<'_, PyAny>)>,
    compression: &str,
    filter: &str,
) -> PyResult<()> {
    let compression = match compression {
        "none" => PngCompression::None,
        "fast" => PngCompression::Fast,
        "balanced" => PngCompression::Balanced,
        "high" => PngCompression::High,
        other => {
            return Err(InputError::new_err(format!(
                "compression must be none, fast, balanced or high, got '{other}'"
            )))
        }
    };
    let filter = match filter {
        "adaptive" => PngFilter::Adaptive,
        "none" => PngFilter::None,
        "sub" => PngFilter::Sub,
        "up" => PngFilter::Up,
        "paeth" => PngFilter::Paeth,
        other => {
            return Err(InputError::new_err(format!(
                "filter must be adaptive, none, sub, up or paeth, got '{other}'"
            )))
        }
    };
    let mut arrays = Vec::with_capacity(jobs.len());
    for (path, array) in &jobs {
        let fail = |what: &str| {
            InputError::new_err(format!("cannot write image '{}': {what}", path.display()))
        };
        let array = if let Ok(a) = array.extract::<PyReadonlyArrayDyn<'_, u8>>() {
            Array::U8(a)
        } else if let Ok(a) = array.extract::<PyReadonlyArrayDyn<'_, u16>>() {
            Array::U16(a)
        } else {
            return Err(fail("not a uint8 or uint16 array"));
        };
        let shape = match &array {
            Array::U8(a) => a.shape().to_vec(),
            Array::U16(a) => a.shape().to_vec(),
        };
        let contiguous = match &array {
            Array::U8(a) => a.is_c_contiguous(),
            Array::U16(a) => a.is_c_contiguous(),
        };
        if !(shape.len() == 2 || (shape.len() == 3 && shape[2] == 3)) {
            return Err(fail(&format!(
                "an image has shape (H, W) or (H, W, 3), got {shape:?}"
            )));
        }
        if !contiguous {
            return Err(fail("the array is not C-contiguous"));
        }
        arrays.push((path.clone(), shape, array));
    }
    let mut images: Vec<(PathBuf, Image<'_>)> = Vec::with_capacity(arrays.len());
    for (path, shape, array) in &arrays {
        let samples = match array {
            Array::U8(a) => Samples::U8(a.as_slice()?),
            Array::U16(a) => Samples::U16(a.as_slice()?),
        };
        let channels = if shape.len() == 3 { 3 } else { 1 };
        images.push((
            path.clone(),
            Image::new(samples, shape[0], shape[1], channels),
        ));
    }
    let options = PngOptions::new(compression, filter);
    // On a pool of its own: `save` encodes its images on one thread while another builds the
    // meshes with rayon's global pool, whose work would otherwise wait behind whole encodings.
    let results = py.detach(|| {
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads.min(images.len().max(1)))
            .thread_name(|i| format!("nplps-png-{i}"))
            .build()
            .map(|pool| pool.install(|| nplps::io::write_pngs(&images, options)))
            .map_err(|e| {
                nplps::Error::Unusable(format!("cannot start the PNG encoding threads: {e}"))
            })
    });
    for result in results.map_err(crate::errors::to_py)? {
        result.map_err(crate::errors::to_py)?;
    }
    Ok(())
}
