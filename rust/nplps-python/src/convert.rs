//! Conversions between Python objects and the core's types.
//!
//! The camera is the rig file's `camera` mapping (`model` = "orthographic" with `pixel_size`
//! and `origin`, or "pinhole" with `K` and optional `distortion`). The lights are a mapping of
//! per-light lists: `vectors` (k x 3: positions of point lights, unit directions towards the light
//! of directional lights), `directional` (k booleans), `intensities` (k x 3), `axes` (k x 3, LED
//! principal directions) and `mu` (k anisotropies).

use numpy::{IntoPyArray, PyArray1, PyArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyDictMethods};

use crate::errors::{py_error, to_py};

/// Reads `key` of `dict`; a missing or malformed value is a `RigError` naming the key.
fn get<'py, T: FromPyObjectOwned<'py>>(
    py: Python<'py>,
    dict: &Bound<'py, PyDict>,
    what: &str,
    key: &str,
) -> PyResult<T> {
    let value = dict
        .get_item(key)?
        .ok_or_else(|| py_error(py, "RigError", format!("{what} is missing the key {key:?}")))?;
    value.extract::<T>().map_err(|e| {
        let e: PyErr = e.into();
        py_error(
            py,
            "RigError",
            format!("{what} key {key:?} is invalid: {e}"),
        )
    })
}

/// Reads an optional option of an options mapping (`InputError` when malformed).
pub fn option<'py, T: FromPyObjectOwned<'py>>(
    py: Python<'py>,
    dict: &Bound<'py, PyDict>,
    key: &str,
    default: T,
) -> PyResult<T> {
    match dict.get_item(key)? {
        None => Ok(default),
        Some(v) if v.is_none() => Ok(default),
        Some(v) => v.extract::<T>().map_err(|e| {
            let e: PyErr = e.into();
            py_error(py, "InputError", format!("option {key:?} is invalid: {e}"))
        }),
    }
}

/// Builds a core [`nplps::Camera`] from the rig file's `camera` mapping.
pub fn camera_from(py: Python<'_>, camera: &Bound<'_, PyDict>) -> PyResult<nplps::Camera> {
    let model: String = get(py, camera, "camera", "model")?;
    let cam = match model.as_str() {
        "orthographic" => nplps::Camera::Orthographic {
            pixel_size: get(py, camera, "camera", "pixel_size")?,
            origin: get(py, camera, "camera", "origin")?,
        },
        "pinhole" => {
            let k: [[f64; 3]; 3] = get(py, camera, "camera", "K")?;
            let distortion: Option<Vec<f64>> = get(py, camera, "camera", "distortion").ok();
            let mut d = [0.0; 5];
            if let Some(v) = distortion {
                if v.len() > 5 {
                    return Err(py_error(
                        py,
                        "RigError",
                        format!(
                            "distortion has {} coefficients; at most 5 (k1, k2, p1, p2, k3)",
                            v.len()
                        ),
                    ));
                }
                d[..v.len()].copy_from_slice(&v);
            }
            nplps::Camera::Pinhole { k, distortion: d }
        }
        other => {
            return Err(py_error(
                py,
                "RigError",
                format!("unknown camera model {other:?}; supported: \"orthographic\", \"pinhole\""),
            ))
        }
    };
    cam.validate().map_err(|e| to_py(py, e))?;
    Ok(cam)
}

/// The camera as the rig file's mapping.
pub fn camera_dict<'py>(py: Python<'py>, camera: &nplps::Camera) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    match *camera {
        nplps::Camera::Orthographic { pixel_size, origin } => {
            d.set_item("model", "orthographic")?;
            d.set_item("pixel_size", pixel_size.to_vec())?;
            d.set_item("origin", origin.to_vec())?;
        }
        nplps::Camera::Pinhole { k, distortion } => {
            d.set_item("model", "pinhole")?;
            d.set_item("K", k.iter().map(|r| r.to_vec()).collect::<Vec<_>>())?;
            d.set_item("distortion", distortion.to_vec())?;
        }
    }
    Ok(d)
}

/// Builds the core's lights from the lights mapping (see the module documentation).
pub fn lights_from(py: Python<'_>, lights: &Bound<'_, PyDict>) -> PyResult<Vec<nplps::Light>> {
    let what = "lights";
    let vectors: Vec<[f64; 3]> = get(py, lights, what, "vectors")?;
    let directional: Vec<bool> = get(py, lights, what, "directional")?;
    let intensities: Vec<[f64; 3]> = get(py, lights, what, "intensities")?;
    let axes: Vec<[f64; 3]> = get(py, lights, what, "axes")?;
    let mu: Vec<f64> = get(py, lights, what, "mu")?;
    let k = vectors.len();
    if [directional.len(), intensities.len(), axes.len(), mu.len()]
        .iter()
        .any(|&n| n != k)
    {
        return Err(py_error(
            py,
            "RigError",
            format!("every light needs all its parameters ({k} lights)"),
        ));
    }
    Ok((0..k)
        .map(|i| {
            if directional[i] {
                nplps::Light::Directional {
                    direction: vectors[i],
                    intensity: intensities[i],
                }
            } else {
                nplps::Light::Point {
                    position: vectors[i],
                    intensity: intensities[i],
                    axis: axes[i],
                    mu: mu[i],
                }
            }
        })
        .collect())
}

/// The light refinement's report as a dict.
fn refinement_dict<'py>(
    py: Python<'py>,
    report: &nplps::RefinementReport,
) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("mode", report.refine.name())?;
    d.set_item("prior_weight", report.refine.prior_weight)?;
    d.set_item("fell_back", report.fell_back)?;
    d.set_item("stopped", report.stopped)?;
    d.set_item("residual_without", report.residual_without)?;
    d.set_item("residual_with", report.residual_with)?;
    if let Some(c) = &report.conditioning {
        let cd = PyDict::new(py);
        cd.set_item("singular_values", c.singular_values.clone())?;
        cd.set_item(
            "standard_errors",
            c.standard_errors
                .iter()
                .map(|s| s.to_vec())
                .collect::<Vec<_>>(),
        )?;
        cd.set_item("rms_residual", c.rms_residual)?;
        cd.set_item("distance", c.distance)?;
        d.set_item("conditioning", cd)?;
    }
    Ok(d)
}

/// The lights as the lights mapping.
pub fn lights_dict<'py>(py: Python<'py>, lights: &[nplps::Light]) -> PyResult<Bound<'py, PyDict>> {
    let (mut vectors, mut directional, mut intensities, mut axes, mut mu) =
        (vec![], vec![], vec![], vec![], vec![]);
    for light in lights {
        let (v, dir, phi, axis, m) = match *light {
            nplps::Light::Point {
                position,
                intensity,
                axis,
                mu,
            } => (position, false, intensity, axis, mu),
            nplps::Light::Directional {
                direction,
                intensity,
            } => (direction, true, intensity, [0.0, 0.0, 1.0], 0.0),
        };
        vectors.push(v.to_vec());
        directional.push(dir);
        intensities.push(phi.to_vec());
        axes.push(axis.to_vec());
        mu.push(m);
    }
    let d = PyDict::new(py);
    d.set_item("vectors", vectors)?;
    d.set_item("directional", directional)?;
    d.set_item("intensities", intensities)?;
    d.set_item("axes", axes)?;
    d.set_item("mu", mu)?;
    Ok(d)
}

/// Builds and validates a core [`nplps::Rig`] for reconstruction (at least 3 lights).
pub fn rig_from(
    py: Python<'_>,
    camera: &Bound<'_, PyDict>,
    lights: &Bound<'_, PyDict>,
) -> PyResult<nplps::Rig> {
    let rig = lighting_from(py, camera, lights)?;
    rig.validate().map_err(|e| to_py(py, e))?;
    Ok(rig)
}

/// Builds a core [`nplps::Rig`] for rendering: any number of lights, each one valid.
pub fn lighting_from(
    py: Python<'_>,
    camera: &Bound<'_, PyDict>,
    lights: &Bound<'_, PyDict>,
) -> PyResult<nplps::Rig> {
    let rig = nplps::Rig {
        camera: camera_from(py, camera)?,
        lights: lights_from(py, lights)?,
    };
    rig.validate_parameters().map_err(|e| to_py(py, e))?;
    Ok(rig)
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
    let flat: Vec<f64> = data.into_flattened();
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
    let albedo = if r.channels == 1 {
        array(py, r.albedo.iter().map(|a| a[0]).collect(), &[h, w])?
    } else {
        array3(py, r.albedo, &[h, w])?
    };
    d.set_item("albedo", albedo)?;
    d.set_item("residual", array(py, r.residual, &[h, w])?)?;
    d.set_item("lights_used", array(py, r.lights_used, &[h, w])?)?;
    d.set_item("regions", array(py, r.regions, &[h, w])?)?;
    d.set_item("gauge", PyArray1::from_vec(py, r.gauge))?;
    let history: Vec<(usize, f64, f64, f64, usize, usize, f64)> = r
        .history
        .iter()
        .map(|s| {
            (
                s.iteration,
                s.depth_change,
                s.rms_residual,
                s.elapsed.as_secs_f64(),
                s.level,
                s.inner_iterations,
                s.light_change,
            )
        })
        .collect();
    d.set_item("history", history)?;
    d.set_item("converged", r.converged)?;
    d.set_item("status", r.status.name())?;
    d.set_item("status_reason", &r.status_reason)?;
    d.set_item("negative_observations", r.negative_observations)?;
    let t = PyDict::new(py);
    t.set_item("factorization", r.timings.factorization.as_secs_f64())?;
    t.set_item("local", r.timings.local.as_secs_f64())?;
    t.set_item("solve", r.timings.solve.as_secs_f64())?;
    t.set_item("pyramid", r.timings.pyramid.as_secs_f64())?;
    t.set_item("lights", r.timings.lights.as_secs_f64())?;
    t.set_item("total", r.timings.total.as_secs_f64())?;
    d.set_item("timings", t)?;
    d.set_item("lights", lights_dict(py, &r.lights)?)?;
    if let Some(report) = &r.refinement {
        d.set_item("refinement", refinement_dict(py, report)?)?;
    }
    Ok(d)
}
