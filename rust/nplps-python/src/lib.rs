//! `nplps._core`: Python bindings of the `nplps` crate.
//!
//! The bindings only convert and delegate: arrays are borrowed from numpy without copies where
//! their layout allows, the work runs with the GIL released, core errors become the exceptions
//! of `nplps.errors`, and no panic crosses into Python. Between iterations the solver takes the
//! GIL back briefly to check for Ctrl-C and to call the progress callback.

mod convert;
mod errors;

use numpy::{PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use convert::{array, array3, camera_from, reconstruction_dict, rig_from};
use errors::{no_panic, py_error, to_py};

/// Borrows a C-contiguous array as a slice, or explains what is wrong.
fn slice<'a, T: numpy::Element, D: numpy::ndarray::Dimension>(
    py: Python<'_>,
    a: &'a numpy::PyReadonlyArray<'_, T, D>,
    name: &str,
) -> PyResult<&'a [T]> {
    a.as_slice().map_err(|_| {
        py_error(
            py,
            "InputError",
            format!("{name} must be a C-contiguous array"),
        )
    })
}

/// The starting depth: a working distance or an (H+1, W+1) map.
fn initial_depth<'a>(
    py: Python<'_>,
    distance: Option<f64>,
    map: Option<&'a PyReadonlyArray2<'_, f64>>,
) -> PyResult<nplps::InitialDepth<'a>> {
    match (distance, map) {
        (Some(d), None) => Ok(nplps::InitialDepth::Distance(d)),
        (None, Some(m)) => Ok(nplps::InitialDepth::Map(slice(py, m, "depth map")?)),
        _ => Err(py_error(
            py,
            "InputError",
            "give exactly one of a working distance or a depth map".into(),
        )),
    }
}

fn weighting(py: Python<'_>, name: &str) -> PyResult<nplps::Weighting> {
    match name {
        "image" => Ok(nplps::Weighting::Image),
        "paper" => Ok(nplps::Weighting::Paper),
        other => Err(py_error(
            py,
            "InputError",
            format!("weighting must be \"image\" or \"paper\", got {other:?}"),
        )),
    }
}

/// The borrowed input of a reconstruction: rig, (k, H, W) images, mask and starting depth.
struct Input<'a> {
    rig: nplps::Rig,
    shape: [usize; 3],
    images: &'a [f32],
    mask: Option<&'a [bool]>,
    depth: nplps::InitialDepth<'a>,
}

impl<'a> Input<'a> {
    fn new(
        py: Python<'_>,
        images: &'a PyReadonlyArray3<'_, f32>,
        camera: &Bound<'_, PyDict>,
        lights: PyReadonlyArray2<'_, f64>,
        mask: Option<&'a PyReadonlyArray2<'_, bool>>,
        distance: Option<f64>,
        depth_map: Option<&'a PyReadonlyArray2<'_, f64>>,
    ) -> PyResult<Input<'a>> {
        let shape = images.shape();
        Ok(Input {
            rig: rig_from(py, camera, lights)?,
            shape: [shape[0], shape[1], shape[2]],
            images: slice(py, images, "images")?,
            mask: mask.map(|m| slice(py, m, "mask")).transpose()?,
            depth: initial_depth(py, distance, depth_map)?,
        })
    }

    /// The validated problem (runs without the GIL).
    fn problem(&self) -> nplps::Result<nplps::Problem<'_>> {
        let [k, h, w] = self.shape;
        let stack = nplps::ImageStack::new(self.images, k, h, w)?;
        nplps::Problem::new(stack, &self.rig, self.mask, self.depth)
    }
}

/// Near-light reconstruction (see `nplps.reconstruct`). Returns a dict of arrays.
#[pyfunction]
#[pyo3(signature = (images, camera, lights, mask, distance, depth_map, iterations, tol, dark, weighting_name, threads, progress))]
#[allow(clippy::too_many_arguments)]
fn reconstruct<'py>(
    py: Python<'py>,
    images: PyReadonlyArray3<'py, f32>,
    camera: &Bound<'py, PyDict>,
    lights: PyReadonlyArray2<'py, f64>,
    mask: Option<PyReadonlyArray2<'py, bool>>,
    distance: Option<f64>,
    depth_map: Option<PyReadonlyArray2<'py, f64>>,
    iterations: usize,
    tol: f64,
    dark: f64,
    weighting_name: &str,
    threads: usize,
    progress: Option<Py<PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    let input = Input::new(
        py,
        &images,
        camera,
        lights,
        mask.as_ref(),
        distance,
        depth_map.as_ref(),
    )?;
    let options = nplps::Options {
        iterations,
        tol,
        dark,
        weighting: weighting(py, weighting_name)?,
        threads,
        ..nplps::Options::default()
    };
    let mut callback_error: Option<PyErr> = None;
    let result = py.detach(|| {
        no_panic(|| {
            let problem = input.problem()?;
            let mut on_iteration = |stats: &nplps::IterationStats| {
                Python::attach(|py| {
                    let outcome = py.check_signals().and_then(|_| match &progress {
                        Some(cb) => cb
                            .call1(
                                py,
                                (
                                    stats.iteration,
                                    stats.depth_change,
                                    stats.rms_residual,
                                    stats.elapsed.as_secs_f64(),
                                ),
                            )
                            .map(|_| ()),
                        None => Ok(()),
                    });
                    match outcome {
                        Ok(()) => nplps::Control::Continue,
                        Err(e) => {
                            callback_error = Some(e);
                            nplps::Control::Cancel
                        }
                    }
                })
            };
            nplps::reconstruct(&problem, &options, &mut on_iteration)
        })
    });
    if let Some(e) = callback_error {
        return Err(e);
    }
    reconstruction_dict(py, result.map_err(|e| to_py(py, e))?)
}

/// Parallel-light baseline (see `nplps.reconstruct_parallel`).
#[pyfunction]
#[pyo3(signature = (images, camera, lights, mask, distance, depth_map, dark, threads))]
#[allow(clippy::too_many_arguments)]
fn reconstruct_parallel<'py>(
    py: Python<'py>,
    images: PyReadonlyArray3<'py, f32>,
    camera: &Bound<'py, PyDict>,
    lights: PyReadonlyArray2<'py, f64>,
    mask: Option<PyReadonlyArray2<'py, bool>>,
    distance: Option<f64>,
    depth_map: Option<PyReadonlyArray2<'py, f64>>,
    dark: f64,
    threads: usize,
) -> PyResult<Bound<'py, PyDict>> {
    let input = Input::new(
        py,
        &images,
        camera,
        lights,
        mask.as_ref(),
        distance,
        depth_map.as_ref(),
    )?;
    let result = py.detach(|| {
        no_panic(|| {
            let problem = input.problem()?;
            nplps::reconstruct_parallel(&problem, dark, threads)
        })
    });
    reconstruction_dict(py, result.map_err(|e| to_py(py, e))?)
}

/// Images (k, H, W) of the surface `depth` (H+1, W+1) with albedo (H, W) under the rig.
#[pyfunction]
#[pyo3(signature = (depth, camera, lights, albedo, mask=None))]
fn render<'py>(
    py: Python<'py>,
    depth: PyReadonlyArray2<'py, f64>,
    camera: &Bound<'py, PyDict>,
    lights: PyReadonlyArray2<'py, f64>,
    albedo: PyReadonlyArray2<'py, f64>,
    mask: Option<PyReadonlyArray2<'py, bool>>,
) -> PyResult<Bound<'py, PyAny>> {
    let rig = rig_from(py, camera, lights)?;
    let (h, w) = (albedo.shape()[0], albedo.shape()[1]);
    let depth_s = slice(py, &depth, "depth")?;
    let albedo_s = slice(py, &albedo, "albedo")?;
    let mask = mask.as_ref().map(|m| slice(py, m, "mask")).transpose()?;
    let images = py
        .detach(|| no_panic(|| nplps::render(&rig, h, w, depth_s, albedo_s, mask)))
        .map_err(|e| to_py(py, e))?;
    array(py, images, &[rig.n_lights(), h, w])
}

/// Mesh normals (H, W, 3) of a vertex depth map (H+1, W+1).
#[pyfunction]
fn mesh_normals<'py>(
    py: Python<'py>,
    depth: PyReadonlyArray2<'py, f64>,
    camera: &Bound<'py, PyDict>,
) -> PyResult<Bound<'py, PyAny>> {
    let cam = camera_from(py, camera)?;
    let (h, w) = (depth.shape()[0] - 1, depth.shape()[1] - 1);
    let z = slice(py, &depth, "depth")?;
    let normals = py
        .detach(|| no_panic(|| nplps::mesh_normals(&cam, h, w, z)))
        .map_err(|e| to_py(py, e))?;
    array3(py, normals, &[h, w])
}

/// Vertex positions (H+1, W+1, 3) of a vertex depth map (H+1, W+1).
#[pyfunction]
fn vertices<'py>(
    py: Python<'py>,
    depth: PyReadonlyArray2<'py, f64>,
    camera: &Bound<'py, PyDict>,
) -> PyResult<Bound<'py, PyAny>> {
    let cam = camera_from(py, camera)?;
    let (h, w) = (depth.shape()[0] - 1, depth.shape()[1] - 1);
    let z = slice(py, &depth, "depth")?;
    let v = no_panic(|| nplps::vertices(&cam, h, w, z)).map_err(|e| to_py(py, e))?;
    array3(py, v, &[h + 1, w + 1])
}

/// Validates a rig (camera mapping and (k, 3) lights); raises `RigError` when it is invalid.
#[pyfunction]
fn check_rig<'py>(
    py: Python<'py>,
    camera: &Bound<'py, PyDict>,
    lights: PyReadonlyArray2<'py, f64>,
) -> PyResult<()> {
    rig_from(py, camera, lights).map(|_| ())
}

/// A synthetic scene with ground truth: dict of depth, mask, albedo, camera and lights.
#[pyfunction]
#[pyo3(signature = (name, n, size, distance, seed))]
fn synth_scene<'py>(
    py: Python<'py>,
    name: &str,
    n: usize,
    size: f64,
    distance: f64,
    seed: u64,
) -> PyResult<Bound<'py, PyDict>> {
    let scene = nplps::SceneKind::from_name(name)
        .and_then(|kind| nplps::Scene::new(kind, n, size, distance, seed))
        .map_err(|e| to_py(py, e))?;
    let d = PyDict::new(py);
    d.set_item("depth", array(py, scene.depth, &[n + 1, n + 1])?)?;
    d.set_item("mask", array(py, scene.mask, &[n, n])?)?;
    d.set_item("albedo", array(py, scene.albedo, &[n, n])?)?;
    let nplps::Camera::Orthographic { pixel_size, origin } = scene.rig.camera;
    d.set_item("pixel_size", pixel_size.to_vec())?;
    d.set_item("origin", origin.to_vec())?;
    let k = scene.rig.n_lights();
    d.set_item("lights", array3(py, scene.rig.lights, &[k])?)?;
    d.set_item("size", scene.size)?;
    Ok(d)
}

/// The compiled core of nplps.
#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_function(wrap_pyfunction!(reconstruct, m)?)?;
    m.add_function(wrap_pyfunction!(reconstruct_parallel, m)?)?;
    m.add_function(wrap_pyfunction!(render, m)?)?;
    m.add_function(wrap_pyfunction!(mesh_normals, m)?)?;
    m.add_function(wrap_pyfunction!(vertices, m)?)?;
    m.add_function(wrap_pyfunction!(synth_scene, m)?)?;
    m.add_function(wrap_pyfunction!(check_rig, m)?)?;
    Ok(())
}
