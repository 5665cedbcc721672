//! Conversions between Python objects and the core's types.

use numpy::{IntoPyArray, PyArray1, PyArrayMethods, PyReadonlyArray2};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyDictMethods};

use crate::errors::{py_error, to_py};

/// Builds a core [`nplps::Camera`] from the rig file's `camera` mapping.
pub fn camera_from(py: Python<'_>, camera: &Bound<'_, PyDict>) -> PyResult<nplps::Camera> {
    let model: String = get(py, camera, "model")?;
    let cam = match model.as_str() {
        "orthographic" => nplps::Camera::Orthographic {
            pixel_size: get(py, camera, "pixel_size")?,
            origin: get(py, camera, "origin")?,
        },
        other => {
            return Err(py_error(
                py,
                "RigError",
                format!("unknown camera model {other:?}; supported: \"orthographic\""),
            ))
        }
    };
    cam.validate().map_err(|e| to_py(py, e))?;
    Ok(cam)
}

/// Builds a core [`nplps::Rig`] from the `camera` mapping and a (k, 3) light array.
pub fn rig_from(
    py: Python<'_>,
    camera: &Bound<'_, PyDict>,
    lights: PyReadonlyArray2<'_, f64>,
) -> PyResult<nplps::Rig> {
    let lights_view = lights.as_array();
    if lights_view.ncols() != 3 {
        return Err(py_error(
            py,
            "RigError",
            format!(
                "lights must be a (k, 3) array, got shape {:?}",
                lights_view.shape()
            ),
        ));
    }
    let rig = nplps::Rig {
        camera: camera_from(py, camera)?,
        lights: lights_view
            .rows()
            .into_iter()
            .map(|r| [r[0], r[1], r[2]])
            .collect(),
    };
    rig.validate().map_err(|e| to_py(py, e))?;
    Ok(rig)
}

fn get<'py, T: FromPyObjectOwned<'py>>(
    py: Python<'py>,
    dict: &Bound<'py, PyDict>,
    key: &str,
) -> PyResult<T> {
    let value = dict
        .get_item(key)?
        .ok_or_else(|| py_error(py, "RigError", format!("camera is missing the key {key:?}")))?;
    value.extract::<T>().map_err(|e| {
        let e: PyErr = e.into();
        py_error(
            py,
            "RigError",
            format!("camera key {key:?} is invalid: {e}"),
        )
    })
}

/// A flat vector as a numpy array of the given shape.
pub fn array<'py, T: numpy::Element>(
    py: Python<'py>,
    data: Vec<T>,
    shape: &[usize],
) -> PyResult<Bound<'py, PyAny>> {
    Ok(data.into_pyarray(py).reshape(shape)?.into_any())
}

/// Vectors of 3 as an array of shape `shape + [3]`.
pub fn array3<'py>(
    py: Python<'py>,
    data: Vec<[f64; 3]>,
    shape: &[usize],
) -> PyResult<Bound<'py, PyAny>> {
    let flat: Vec<f64> = data.into_iter().flatten().collect();
    let mut full = shape.to_vec();
    full.push(3);
    array(py, flat, &full)
}

/// The reconstruction as a dict of numpy arrays and plain values.
pub fn reconstruction_dict<'py>(
    py: Python<'py>,
    r: nplps::Reconstruction,
) -> PyResult<Bound<'py, PyDict>> {
    let (h, w) = (r.height, r.width);
    let d = PyDict::new(py);
    d.set_item("depth", array(py, r.depth, &[h + 1, w + 1])?)?;
    d.set_item("normals", array3(py, r.normals, &[h, w])?)?;
    d.set_item("albedo", array(py, r.albedo, &[h, w])?)?;
    d.set_item("residual", array(py, r.residual, &[h, w])?)?;
    d.set_item("lights_used", array(py, r.lights_used, &[h, w])?)?;
    d.set_item("regions", array(py, r.regions, &[h, w])?)?;
    d.set_item("gauge", PyArray1::from_vec(py, r.gauge))?;
    let history: Vec<(usize, f64, f64, f64)> = r
        .history
        .iter()
        .map(|s| {
            (
                s.iteration,
                s.depth_change,
                s.rms_residual,
                s.elapsed.as_secs_f64(),
            )
        })
        .collect();
    d.set_item("history", history)?;
    d.set_item("converged", r.converged)?;
    d.set_item("negative_observations", r.negative_observations)?;
    let t = PyDict::new(py);
    t.set_item("factorization", r.timings.factorization.as_secs_f64())?;
    t.set_item("local", r.timings.local.as_secs_f64())?;
    t.set_item("solve", r.timings.solve.as_secs_f64())?;
    t.set_item("total", r.timings.total.as_secs_f64())?;
    d.set_item("timings", t)?;
    Ok(d)
}
