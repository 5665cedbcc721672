//! `nplps._core`: Python bindings of the `nplps` crate.
//!
//! The bindings only convert and delegate: arrays are borrowed from numpy without copies where
//! their layout allows, the work runs with the GIL released, core errors become the exceptions
//! of `nplps.errors`, and no panic crosses into Python. Reconstructions run on a worker thread
//! while the calling thread watches for Ctrl-C (see `interrupt`); the worker takes the GIL back
//! briefly after each iteration only to call the progress callback.

mod calibrate;
mod convert;
mod decode;
mod encode;
mod errors;
mod interrupt;
mod pool;
mod records;
mod rig;

use numpy::{PyReadonlyArray2, PyReadonlyArray3, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use convert::{array, array3, camera_dict, camera_from, check_options, lighting_from, option};
use errors::{no_panic, to_py, with_fields, InputError, RigError};
use interrupt::interruptible;
use records::reconstruction_dict;

/// Borrows a C-contiguous array as a slice, or explains what is wrong.
fn slice<'a, T: numpy::Element, D: numpy::ndarray::Dimension>(
    a: &'a numpy::PyReadonlyArray<'_, T, D>,
    name: &str,
) -> PyResult<&'a [T]> {
    a.as_slice()
        .map_err(|_| InputError::new_err(format!("{name} must be a C-contiguous array")))
}

/// The image size (H, W) of an (H+1, W+1) vertex depth map, and its values.
fn depth_grid<'a>(depth: &'a PyReadonlyArray2<'_, f64>) -> PyResult<(usize, usize, &'a [f64])> {
    let shape = depth.shape();
    if shape[0] < 2 || shape[1] < 2 {
        return Err(InputError::new_err(format!(
            "depth must be an (H+1, W+1) vertex map, got shape {shape:?}"
        )));
    }
    Ok((shape[0] - 1, shape[1] - 1, slice(depth, "depth")?))
}

/// Channels of an (H, W) or (H, W, C) albedo.
fn albedo_channels(albedo: &PyReadonlyArrayDyn<'_, f64>) -> PyResult<usize> {
    match albedo.shape() {
        [_, _] => Ok(1),
        [_, _, c] => Ok(*c),
        s => Err(InputError::new_err(format!(
            "albedo must be (H, W) or (H, W, 3), got shape {s:?}"
        ))),
    }
}

/// Images as a (k, H, W) array for one channel, (k, H, W, C) otherwise.
fn image_stack<'py>(
    py: Python<'py>,
    images: Vec<f64>,
    [k, h, w, c]: [usize; 4],
) -> PyResult<Bound<'py, PyAny>> {
    if c == 1 {
        array(py, images, &[k, h, w])
    } else {
        array(py, images, &[k, h, w, c])
    }
}

/// The starting depth: a working distance or an (H+1, W+1) vertex depth map.
#[derive(FromPyObject)]
enum Depth<'py> {
    /// An (H+1, W+1) map (tried first: a float never extracts as an array).
    Map(PyReadonlyArray2<'py, f64>),
    /// A working distance.
    Distance(f64),
}

/// The starting depth: a working distance or an (H+1, W+1) map.
fn initial_depth<'a>(
    distance: Option<f64>,
    map: Option<&'a PyReadonlyArray2<'_, f64>>,
) -> PyResult<nplps::InitialDepth<'a>> {
    match (distance, map) {
        (Some(d), None) => Ok(nplps::InitialDepth::Distance(d)),
        (None, Some(m)) => Ok(nplps::InitialDepth::Map(slice(m, "depth map")?)),
        _ => Err(InputError::new_err(
            "give exactly one of a working distance or a depth map",
        )),
    }
}

/// The keys of the options mapping of `reconstruct_parallel` (those of [`options_from`]).
const SOLVER_KEYS: [&str; 17] = [
    "dark",
    "eta",
    "interreflections",
    "iterations",
    "levels",
    "light_prior_weight",
    "max_memory",
    "refine_lights",
    "reflectance",
    "robust",
    "roughness",
    "saturation",
    "shadows",
    "solver",
    "threads",
    "tol",
    "weighting",
];

/// The keys of the options mapping of `reconstruct` besides the solver's ([`SOLVER_KEYS`]): those
/// of the distance search and the depth prior.
const SEARCH_AND_PRIOR_KEYS: [&str; 6] = [
    "auto",
    "check_distance",
    "depth_guess",
    "depth_range",
    "prior",
    "prior_weight",
];

/// The keys of the options mapping of `reconstruct`, sorted (for the message of an unknown key).
fn reconstruct_keys() -> Vec<&'static str> {
    let mut keys: Vec<&str> = SOLVER_KEYS
        .iter()
        .chain(&SEARCH_AND_PRIOR_KEYS)
        .copied()
        .collect();
    keys.sort_unstable();
    keys
}

/// The value of a string option among `choices` (the first is the default, for a missing key or
/// None); another string is an `InputError` "`expected`, got ...".
fn choice<T: Copy>(
    d: &Bound<'_, PyDict>,
    key: &str,
    choices: &[(&str, T)],
    expected: &str,
) -> PyResult<T> {
    let name: String = option(d, key, choices[0].0.to_string())?;
    match choices.iter().find(|(n, _)| *n == name) {
        Some(&(_, value)) => Ok(value),
        None => {
            let err = InputError::new_err(format!("{expected}, got {name:?}"));
            Err(with_fields(err, |x| {
                x.setattr("argument", key)?;
                x.setattr("value", &name)
            }))
        }
    }
}

/// Solver options from the options mapping (keys as in `nplps.reconstruct`).
fn options_from(d: &Bound<'_, PyDict>) -> PyResult<nplps::Options> {
    let defaults = nplps::Options::default();
    let weighting = choice(
        d,
        "weighting",
        &[
            ("image", nplps::Weighting::Image),
            ("paper", nplps::Weighting::Paper),
        ],
        "weighting must be \"image\" or \"paper\"",
    )?;
    let robust = choice(
        d,
        "robust",
        &[
            ("none", nplps::Robust::None),
            ("cauchy", nplps::Robust::Cauchy),
            ("tukey", nplps::Robust::Tukey),
        ],
        "robust must be None, \"cauchy\" or \"tukey\"",
    )?;
    let solver = choice(
        d,
        "solver",
        &[
            ("auto", nplps::GlobalSolver::Auto),
            ("direct", nplps::GlobalSolver::Direct),
            ("multigrid", nplps::GlobalSolver::Multigrid),
        ],
        "solver must be \"auto\", \"direct\" or \"multigrid\"",
    )?;
    let (intensity, position) = choice(
        d,
        "refine_lights",
        &[
            ("none", (false, false)),
            ("intensity", (true, false)),
            ("position", (false, true)),
            ("both", (true, true)),
        ],
        "refine_lights must be None, \"intensity\", \"position\" or \"both\"",
    )?;
    let glossy = choice(
        d,
        "reflectance",
        &[("lambertian", false), ("glossy", true)],
        "reflectance must be \"lambertian\" or \"glossy\"",
    )?;
    let roughness: Option<f64> = option(d, "roughness", None)?;
    let eta: Option<f64> = option(d, "eta", None)?;
    let reflectance = match (glossy, roughness, eta) {
        (false, None, None) => nplps::Reflectance::Lambertian,
        (false, ..) => {
            return Err(InputError::new_err(
                "roughness and eta are options of reflectance=\"glossy\"",
            ))
        }
        (true, None, None) => nplps::Reflectance::Glossy(None),
        (true, Some(alpha), Some(eta)) => {
            nplps::Reflectance::Glossy(Some(nplps::Lobe::new(alpha, eta)))
        }
        (true, ..) => return Err(InputError::new_err(
            "give both roughness and eta (a fixed lobe), or neither (estimated from the images)",
        )),
    };
    let refine = defaults
        .refine
        .with_intensity(intensity)
        .with_position(position)
        .with_prior_weight(option(
            d,
            "light_prior_weight",
            defaults.refine.prior_weight,
        )?)
        .with_fix_scale(false);
    Ok(defaults
        .with_solver(solver)
        .with_refine(refine)
        .with_levels(option(d, "levels", defaults.levels)?)
        .with_iterations(option(d, "iterations", defaults.iterations)?)
        .with_tol(option(d, "tol", defaults.tol)?)
        .with_dark(option(d, "dark", defaults.dark)?)
        .with_saturation(option(d, "saturation", defaults.saturation)?)
        .with_weighting(weighting)
        .with_robust(robust)
        .with_reflectance(reflectance)
        .with_shadows(choice(
            d,
            "shadows",
            &[
                ("auto", nplps::Shadows::Auto),
                ("on", nplps::Shadows::On),
                ("off", nplps::Shadows::Off),
            ],
            "shadows must be \"auto\", True or False",
        )?)
        .with_interreflections(option(d, "interreflections", defaults.interreflections)?)
        .with_threads(option(d, "threads", defaults.threads)?)
        .with_max_memory(option(d, "max_memory", defaults.max_memory)?))
}

/// A (k, H, W[, C]) image stack as passed from Python: float32, or uint16 read in place (the
/// local step converts each value, `v / 65535`, as `nplps.io.load_stack` does).
#[derive(FromPyObject)]
enum Stack<'py> {
    F32(PyReadonlyArrayDyn<'py, f32>),
    U16(PyReadonlyArrayDyn<'py, u16>),
}

impl Stack<'_> {
    fn shape(&self) -> &[usize] {
        match self {
            Stack::F32(a) => a.shape(),
            Stack::U16(a) => a.shape(),
        }
    }

    /// The borrowed values, or what is wrong with the array.
    fn samples(&self) -> PyResult<nplps::Samples<'_>> {
        Ok(match self {
            Stack::F32(a) => nplps::Samples::F32(slice(a, "images")?),
            Stack::U16(a) => nplps::Samples::U16(slice(a, "images")?),
        })
    }
}

/// The borrowed input of a reconstruction: rig, (k, H, W[, 3]) images, mask and starting depth.
struct Input<'a> {
    rig: &'a nplps::Rig,
    shape: [usize; 4],
    images: nplps::Samples<'a>,
    mask: Option<&'a [bool]>,
    depth: nplps::InitialDepth<'a>,
}

impl<'a> Input<'a> {
    fn new(
        images: &'a Stack<'_>,
        rig: &'a nplps::Rig,
        mask: Option<&'a PyReadonlyArray2<'_, bool>>,
        depth: nplps::InitialDepth<'a>,
    ) -> PyResult<Input<'a>> {
        let s = images.shape();
        let shape = match *s {
            [k, h, w] => [k, h, w, 1],
            [k, h, w, c] => [k, h, w, c],
            _ => {
                return Err(InputError::new_err(format!(
                    "images must be (k, H, W) or (k, H, W, 3), got shape {s:?}"
                )))
            }
        };
        Ok(Input {
            rig,
            shape,
            images: images.samples()?,
            mask: mask.map(|m| slice(m, "mask")).transpose()?,
            depth,
        })
    }

    /// The validated problem (runs without the GIL), refused before any large allocation when
    /// reconstructing it with `options` would exceed their memory limit.
    fn problem(
        &self,
        options: &nplps::Options,
        cancel: &nplps::Cancel,
    ) -> nplps::Result<nplps::Problem<'_>> {
        let [k, h, w, c] = self.shape;
        nplps::check_memory(self.shape, self.mask, options)?;
        let stack = nplps::ImageStack::from_samples(self.images, k, h, w, c)?;
        nplps::Problem::with_cancel(stack, self.rig, self.mask, self.depth, cancel.clone())
    }
}

/// The distance search of the options mapping (`auto`, `depth_range`, `depth_guess`), if asked.
fn search_from(d: &Bound<'_, PyDict>) -> PyResult<Option<nplps::DistanceSearch>> {
    if !option(d, "auto", false)? {
        return Ok(None);
    }
    Ok(Some(
        nplps::DistanceSearch::default()
            .with_range(option(d, "depth_range", None)?)
            .with_guess(option(d, "depth_guess", None)?),
    ))
}

/// Near-light reconstruction (see `nplps.reconstruct`): `depth` is the working distance or an
/// (H+1, W+1) starting depth map; `options` may hold a depth prior (`prior`, (H+1, W+1), with
/// `prior_weight`). Returns a dict of arrays; its `lights` is the rig with the final (refined)
/// lights, of the kinds of `rig`'s.
#[pyfunction]
#[pyo3(signature = (images, rig, mask, depth, options, progress))]
fn reconstruct<'py>(
    images: Stack<'py>,
    rig: &Bound<'py, rig::Rig>,
    mask: Option<PyReadonlyArray2<'py, bool>>,
    depth: Depth<'py>,
    options: &Bound<'py, PyDict>,
    progress: Option<Py<PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    let py = rig.py();
    check_options(options, &reconstruct_keys())?;
    let rig = rig.get();
    let depth = match &depth {
        Depth::Distance(d) => nplps::InitialDepth::Distance(*d),
        Depth::Map(m) => nplps::InitialDepth::Map(slice(m, "depth map")?),
    };
    let input = Input::new(&images, &rig.rig, mask.as_ref(), depth)?;
    let search = search_from(options)?;
    let check = search.is_none() && option(options, "check_distance", false)?;
    let prior_weight: f64 = option(options, "prior_weight", 1.0)?;
    let prior: Option<PyReadonlyArray2<'py, f64>> = option(options, "prior", None)?;
    let prior = prior
        .as_ref()
        .map(|p| slice(p, "depth prior"))
        .transpose()?;
    let options = options_from(options)?;
    let mut callback_error: Option<PyErr> = None;
    let cancel = nplps::Cancel::new();
    let result = interruptible(py, &cancel, || {
        no_panic(|| {
            nplps::memtrace("bindings: before problem");
            let mut problem = input.problem(&options, &cancel)?;
            nplps::memtrace("bindings: problem made");
            if let Some(map) = prior {
                problem.set_prior(map, prior_weight)?;
            }
            // Ctrl-C is watched by the calling thread (see `interrupt`); this closure runs on
            // the worker thread and only calls the progress callback, if there is one.
            let mut on_iteration = |stats: &nplps::IterationStats| {
                let Some(cb) = &progress else {
                    return nplps::Control::Continue;
                };
                let args = (records::IterationStats::from(stats),);
                match Python::attach(|py| cb.call1(py, args).map(|_| ())) {
                    Ok(()) => nplps::Control::Continue,
                    Err(e) => {
                        callback_error = Some(e);
                        nplps::Control::Cancel
                    }
                }
            };
            match &search {
                Some(search) => {
                    nplps::reconstruct_auto(&problem, &options, search, &mut on_iteration)
                        .map(|(r, estimate)| (r, Some(estimate), None))
                }
                // The check compares distances under the model of the result (its lobe: no
                // second estimate of it on the coarse level). Under the Lambertian model that
                // is the options' own, so it runs first, on the coarse levels that the
                // reconstruction then uses (made once; see `reconstruct_checked`).
                None if check => nplps::reconstruct_checked(&problem, &options, &mut on_iteration)
                    .map(|(r, checked)| (r, None, checked)),
                None => nplps::reconstruct(&problem, &options, &mut on_iteration)
                    .map(|r| (r, None, None)),
            }
        })
    });
    if let Some(e) = callback_error {
        return Err(e);
    }
    let (result, estimate, checked) = result?;
    nplps::memtrace("bindings: solved (problem dropped)");
    let d = reconstruction_dict(py, result, rig)?;
    nplps::memtrace("bindings: dict made");
    if let Some(c) = checked {
        let e = PyDict::new(py);
        e.set_item("given", c.given)?;
        e.set_item("found", c.found)?;
        e.set_item("residual_given", c.residual_given)?;
        e.set_item("residual_found", c.residual_found)?;
        e.set_item("side", c.side)?;
        e.set_item("looks_wrong", c.looks_wrong())?;
        d.set_item("distance_check", e)?;
    }
    if let Some(estimate) = estimate {
        let e = PyDict::new(py);
        e.set_item("distance", estimate.distance)?;
        e.set_item("curve", estimate.curve)?;
        e.set_item("range", estimate.range)?;
        d.set_item("distance_estimate", e)?;
    }
    Ok(d)
}

/// Parallel-light baseline (see `nplps.reconstruct_parallel`).
#[pyfunction]
#[pyo3(signature = (images, rig, mask, distance, depth_map, options))]
fn reconstruct_parallel<'py>(
    images: Stack<'py>,
    rig: &Bound<'py, rig::Rig>,
    mask: Option<PyReadonlyArray2<'py, bool>>,
    distance: Option<f64>,
    depth_map: Option<PyReadonlyArray2<'py, f64>>,
    options: &Bound<'py, PyDict>,
) -> PyResult<Bound<'py, PyDict>> {
    let py = rig.py();
    check_options(options, &SOLVER_KEYS)?;
    let rig = rig.get();
    let depth = initial_depth(distance, depth_map.as_ref())?;
    let input = Input::new(&images, &rig.rig, mask.as_ref(), depth)?;
    let options = options_from(options)?;
    let cancel = nplps::Cancel::new();
    let result = interruptible(py, &cancel, || {
        no_panic(|| {
            let problem = input.problem(&options, &cancel)?;
            nplps::reconstruct_parallel(&problem, &options)
        })
    })?;
    reconstruction_dict(py, result, rig)
}

/// The specular albedo map (H x W) of `specular`: a number (the same everywhere) or an (H, W)
/// array of floats.
fn specular_map(specular: &Bound<'_, PyAny>, h: usize, w: usize) -> PyResult<Vec<f64>> {
    if let Ok(value) = specular.extract::<f64>() {
        return Ok(vec![value; h * w]);
    }
    let map: PyReadonlyArrayDyn<'_, f64> = specular.extract().map_err(|_| {
        InputError::new_err("specular must be None, a number or an (H, W) array of floats")
    })?;
    if map.shape() != [h, w] {
        return Err(InputError::new_err(format!(
            "specular must be a number or an (H, W) = ({h}, {w}) map, got shape {:?}",
            map.shape()
        )));
    }
    Ok(slice(&map, "specular")?.to_vec())
}

/// The shape of the glossy model's diffuse term named `name`: "transmitted" or "retro".
fn diffuse_of(name: &str) -> PyResult<nplps::reflectance::Diffuse> {
    match name {
        "transmitted" => Ok(nplps::reflectance::Diffuse::Transmitted),
        "retro" => Ok(nplps::reflectance::Diffuse::Retro),
        _ => Err(InputError::new_err(format!(
            "diffuse must be \"transmitted\" or \"retro\", got {name:?}"
        ))),
    }
}

/// Images (k, H, W) or (k, H, W, 3) of the surface `depth` (H+1, W+1) with albedo (H, W) or
/// (H, W, 3) under the rig; with `specular` (a number or an (H, W) map) the glossy model of
/// roughness `roughness`, index `eta` and diffuse shape `diffuse`; with `shadows`, cast
/// shadows are 0.
#[pyfunction]
#[pyo3(signature = (depth, rig, albedo, mask=None, *, specular=None, roughness=0.3, eta=1.5, shadows=false, diffuse="transmitted"))]
#[allow(clippy::too_many_arguments)]
fn render<'py>(
    py: Python<'py>,
    depth: PyReadonlyArray2<'py, f64>,
    rig: &Bound<'py, rig::Rig>,
    albedo: PyReadonlyArrayDyn<'py, f64>,
    mask: Option<PyReadonlyArray2<'py, bool>>,
    specular: Option<&Bound<'py, PyAny>>,
    roughness: f64,
    eta: f64,
    shadows: bool,
    diffuse: &str,
) -> PyResult<Bound<'py, PyAny>> {
    let rig = &rig.get().rig;
    let shape = diffuse_of(diffuse)?;
    let (h, w, depth_s) = depth_grid(&depth)?;
    let channels = albedo_channels(&albedo)?;
    let albedo_s = slice(&albedo, "albedo")?;
    let mask = mask.as_ref().map(|m| slice(m, "mask")).transpose()?;
    let specular = specular
        .filter(|s| !s.is_none())
        .map(|s| specular_map(s, h, w))
        .transpose()?;
    let surface = nplps::Surface {
        height: h,
        width: w,
        depth: depth_s,
        albedo: albedo_s,
        channels,
        mask,
    };
    let options = nplps::RenderOptions::default()
        .with_specular(specular.as_deref().map(|albedo| nplps::Specular {
            albedo,
            lobe: nplps::reflectance::Lobe {
                diffuse: shape,
                ..nplps::reflectance::Lobe::new(roughness, eta)
            },
        }))
        .with_cast_shadows(shadows);
    let images = py
        .detach(|| no_panic(|| nplps::render_with(rig, &surface, &options)))
        .map_err(to_py)?;
    image_stack(py, images, [rig.n_lights(), h, w, channels])
}

/// Cast shadows (k, H, W) bool of the surface `depth` (H+1, W+1) under the rig's lights (see
/// `nplps::shadow`): True where the segment from the pixel's facet to the light passes behind
/// the surface.
#[pyfunction]
#[pyo3(signature = (depth, rig, mask=None, *, max_steps=None))]
fn cast_shadows<'py>(
    py: Python<'py>,
    depth: PyReadonlyArray2<'py, f64>,
    rig: &Bound<'py, rig::Rig>,
    mask: Option<PyReadonlyArray2<'py, bool>>,
    max_steps: Option<usize>,
) -> PyResult<Bound<'py, PyAny>> {
    let rig = &rig.get().rig;
    let (h, w, depth_s) = depth_grid(&depth)?;
    let mask = mask.as_ref().map(|m| slice(m, "mask")).transpose()?;
    let bools = py
        .detach(|| {
            no_panic(|| {
                nplps::cast_shadows(rig, h, w, depth_s, mask, max_steps).and_then(|s| s.to_bools())
            })
        })
        .map_err(to_py)?;
    array(py, bools, &[rig.n_lights(), h, w])
}

/// Standard deviation of the image noise of a (k, H, W[, C]) float32 or uint16 stack inside `mask`
/// (see `nplps::noise`); 0 for noise-free images.
#[pyfunction]
#[pyo3(signature = (images, mask=None))]
fn estimate_noise<'py>(
    py: Python<'py>,
    images: Stack<'py>,
    mask: Option<PyReadonlyArray2<'py, bool>>,
) -> PyResult<f64> {
    let shape = match *images.shape() {
        [k, h, w] => [k, h, w, 1],
        [k, h, w, c] => [k, h, w, c],
        ref s => {
            return Err(InputError::new_err(format!(
                "images must be (k, H, W) or (k, H, W, C), got shape {s:?}"
            )))
        }
    };
    let data = images.samples()?;
    let mask = mask.as_ref().map(|m| slice(m, "mask")).transpose()?;
    let [k, h, w, c] = shape;
    py.detach(|| {
        no_panic(|| {
            let stack = nplps::ImageStack::from_samples(data, k, h, w, c)?;
            nplps::estimate_noise(&stack, mask)
        })
    })
    .map_err(to_py)
}

/// Predicted images of a reconstruction (see `Reconstruction.predict`).
#[pyfunction]
#[pyo3(signature = (depth, normals, albedo, camera, lights, mask, parallel, specular=None, lobe=None, diffuse="transmitted"))]
#[allow(clippy::too_many_arguments)]
fn predict<'py>(
    depth: PyReadonlyArray2<'py, f64>,
    normals: PyReadonlyArrayDyn<'py, f64>,
    albedo: PyReadonlyArrayDyn<'py, f64>,
    camera: &Bound<'py, PyDict>,
    lights: &Bound<'py, PyDict>,
    mask: Option<PyReadonlyArray2<'py, bool>>,
    parallel: bool,
    specular: Option<&Bound<'py, PyAny>>,
    lobe: Option<(f64, f64)>,
    diffuse: &str,
) -> PyResult<Bound<'py, PyAny>> {
    let py = depth.py();
    let shape = diffuse_of(diffuse)?;
    let rig = lighting_from(camera, lights)?;
    let (h, w, z) = depth_grid(&depth)?;
    let specular =
        match (specular, lobe) {
            (Some(s), Some(lobe)) => Some((specular_map(s, h, w)?, lobe)),
            (None, None) => None,
            _ => return Err(InputError::new_err(
                "give the specular albedo and the lobe together (a glossy result's), or neither",
            )),
        };
    let channels = albedo_channels(&albedo)?;
    let n: Vec<[f64; 3]> = slice(&normals, "normals")?
        .chunks_exact(3)
        .map(|c| [c[0], c[1], c[2]])
        .collect();
    let a = slice(&albedo, "albedo")?;
    let mask = mask.as_ref().map(|m| slice(m, "mask")).transpose()?;
    let surface = nplps::Surface {
        height: h,
        width: w,
        depth: z,
        albedo: a,
        channels,
        mask,
    };
    let images = py
        .detach(|| {
            no_panic(|| {
                let layer = specular
                    .as_ref()
                    .map(|(albedo, (alpha, eta))| nplps::Specular {
                        albedo,
                        lobe: nplps::reflectance::Lobe {
                            diffuse: shape,
                            ..nplps::reflectance::Lobe::new(*alpha, *eta)
                        },
                    });
                nplps::predict_with(&rig, &surface, &n, parallel, layer)
            })
        })
        .map_err(to_py)?;
    image_stack(py, images, [rig.n_lights(), h, w, channels])
}

/// Mesh normals (H, W, 3) of a vertex depth map (H+1, W+1); NaN outside `mask` (H, W) if given.
#[pyfunction]
#[pyo3(signature = (depth, camera, mask=None))]
fn mesh_normals<'py>(
    py: Python<'py>,
    depth: PyReadonlyArray2<'py, f64>,
    camera: &Bound<'py, PyDict>,
    mask: Option<PyReadonlyArray2<'py, bool>>,
) -> PyResult<Bound<'py, PyAny>> {
    let cam = camera_from(camera)?;
    let (h, w, z) = depth_grid(&depth)?;
    let mask = mask.as_ref().map(|m| slice(m, "mask")).transpose()?;
    // The GIL released: `save` makes its PNG images on another thread meanwhile.
    let normals = py
        .detach(|| no_panic(|| nplps::mesh_normals_masked(&cam, h, w, z, mask)))
        .map_err(to_py)?;
    array3(py, normals, &[h, w])
}

/// The trust figures of `summary.json` (see `nplps::trust_figures`) of the maps `sigma` and
/// `held` (H, W; both float32 or both float64) inside `mask` (H, W): `(pixels, sigma_median,
/// sigma_p90, sigma_rms, held_mean, held_median, held_p90)`, NaN figures without a pixel.
#[pyfunction]
fn trust_figures<'py>(
    py: Python<'py>,
    mask: PyReadonlyArray2<'py, bool>,
    sigma: &Bound<'py, PyAny>,
    held: &Bound<'py, PyAny>,
) -> PyResult<(usize, f64, f64, f64, f64, f64, f64)> {
    let mask = slice(&mask, "mask")?;
    let figures = if let (Ok(s), Ok(e)) = (
        sigma.extract::<PyReadonlyArray2<'py, f32>>(),
        held.extract::<PyReadonlyArray2<'py, f32>>(),
    ) {
        let (s, e) = (slice(&s, "normal_sigma")?, slice(&e, "held_out_error")?);
        py.detach(|| no_panic(|| nplps::trust_figures(mask, s, e)))
    } else {
        let wrong = |_| {
            InputError::new_err(
                "normal_sigma and held_out_error must be 2-D float32 or float64 arrays",
            )
        };
        let s: PyReadonlyArray2<'py, f64> = sigma.extract().map_err(wrong)?;
        let e: PyReadonlyArray2<'py, f64> = held.extract().map_err(wrong)?;
        let (s, e) = (slice(&s, "normal_sigma")?, slice(&e, "held_out_error")?);
        py.detach(|| no_panic(|| nplps::trust_figures(mask, s, e)))
    }
    .map_err(to_py)?;
    Ok((
        figures.pixels,
        figures.sigma_median,
        figures.sigma_p90,
        figures.sigma_rms,
        figures.held_mean,
        figures.held_median,
        figures.held_p90,
    ))
}

/// The 8-bit grey pixels (uint8, the shape of `image`) of an image of values in [0, 1] (see
/// `nplps::grey_pixels`): `round(clip(x, 0, 1) 255)`, NaN as 0.
#[pyfunction]
fn grey_pixels<'py>(
    py: Python<'py>,
    image: PyReadonlyArray2<'py, f64>,
) -> PyResult<Bound<'py, PyAny>> {
    let shape = image.shape().to_vec();
    let values = slice(&image, "image")?;
    let pixels = py.detach(|| nplps::grey_pixels(values));
    array(py, pixels, &shape)
}

/// The pixels (H, W, 3) of the normal map of `normals` (H, W, 3) in the frame of the signs
/// `flip` with `bits` (8: uint8, 16: uint16) per channel, black outside `mask` and where a
/// component is not finite (see `nplps::normal_map_pixels`).
#[pyfunction]
#[pyo3(signature = (normals, mask, flip, bits))]
fn normal_map_pixels<'py>(
    py: Python<'py>,
    normals: PyReadonlyArray3<'py, f64>,
    mask: Option<PyReadonlyArray2<'py, bool>>,
    flip: [f64; 3],
    bits: u32,
) -> PyResult<Bound<'py, PyAny>> {
    let shape = normals.shape().to_vec();
    if shape[2] != 3 {
        return Err(InputError::new_err(format!(
            "normals must have shape (H, W, 3), got {shape:?}"
        )));
    }
    let values = slice(&normals, "normals")?;
    let mask = mask.as_ref().map(|m| slice(m, "mask")).transpose()?;
    let pixels = py
        .detach(|| no_panic(|| nplps::normal_map_pixels(values, mask, flip, bits)))
        .map_err(to_py)?;
    if bits == 8 {
        let bytes: Vec<u8> = pixels.into_iter().map(|v| v as u8).collect();
        array(py, bytes, &shape)
    } else {
        array(py, pixels, &shape)
    }
}

/// Vertex positions (H+1, W+1, 3) of a vertex depth map (H+1, W+1).
#[pyfunction]
fn vertices<'py>(
    py: Python<'py>,
    depth: PyReadonlyArray2<'py, f64>,
    camera: &Bound<'py, PyDict>,
) -> PyResult<Bound<'py, PyAny>> {
    let cam = camera_from(camera)?;
    let (h, w, z) = depth_grid(&depth)?;
    // The GIL released: `save` makes its PNG images on another thread meanwhile.
    let v = py
        .detach(|| no_panic(|| nplps::vertices(&cam, h, w, z)))
        .map_err(to_py)?;
    array3(py, v, &[h + 1, w + 1])
}

/// The mean of the finite values of the (up to 4) pixels around each vertex: an (H, W, C) map
/// to (H+1, W+1, C), each mean scaled to unit length with `normalize` (`nplps::vertex_means`).
#[pyfunction]
fn vertex_means<'py>(
    py: Python<'py>,
    values: PyReadonlyArray3<'py, f64>,
    normalize: bool,
) -> PyResult<Bound<'py, PyAny>> {
    let shape = values.shape().to_vec();
    let (h, w, c) = (shape[0], shape[1], shape[2]);
    let data = slice(&values, "values")?;
    let means = py
        .detach(|| no_panic(|| nplps::vertex_means(data, h, w, c, normalize)))
        .map_err(to_py)?;
    array(py, means, &[h + 1, w + 1, c])
}

/// Streams the PLY file of the masked facets with finite corners to `path` (`nplps::ply_plan`,
/// then `nplps::write_ply_records` through a buffered writer), the GIL released. `normals` and
/// `albedo` (C = 1 or 3 channels; quantized to colours) are per-vertex grids (H+1, W+1, C), or
/// with `per_pixel` the per-pixel maps (H, W, C) whose vertex means (normalized for the normals)
/// are written, computed as the file is written. `scale`: the colours' (None: 255 over the 99th
/// percentile of the written vertices' finite albedo). Returns `(vertices, facets, skipped,
/// overflow)`; nothing is written (the file is not created) when there is no facet or a
/// written position is beyond the float32 range. With `camera`, `vertices` is the (H+1, W+1)
/// vertex depth map and the positions are those of `vertices(depth, camera)`, made vertex by
/// vertex.
#[pyfunction]
#[pyo3(signature = (path, vertices, mask, normals, albedo, per_pixel, opengl, scale=None, camera=None))]
#[allow(clippy::too_many_arguments)]
fn write_ply<'py>(
    py: Python<'py>,
    path: std::path::PathBuf,
    vertices: PyReadonlyArrayDyn<'py, f64>,
    mask: PyReadonlyArray2<'py, bool>,
    normals: Option<PyReadonlyArray3<'py, f64>>,
    albedo: Option<PyReadonlyArray3<'py, f64>>,
    per_pixel: bool,
    opengl: bool,
    scale: Option<f64>,
    camera: Option<&Bound<'py, PyDict>>,
) -> PyResult<(usize, usize, usize, usize)> {
    let shape = vertices.shape().to_vec();
    let dims = if camera.is_some() { 2 } else { 3 };
    if shape.len() != dims || shape[0] < 2 || shape[1] < 2 || (dims == 3 && shape[2] != 3) {
        return Err(InputError::new_err(if camera.is_some() {
            format!("the vertex depths must have shape (H + 1, W + 1), got {shape:?}")
        } else {
            format!("vertices must have shape (H + 1, W + 1, 3), got {shape:?}")
        }));
    }
    let (h, w) = (shape[0] - 1, shape[1] - 1);
    let cam = camera.map(camera_from).transpose()?;
    let values = slice(&vertices, "vertices")?;
    let positions = match &cam {
        Some(camera) => nplps::Positions::Camera {
            camera,
            depth: values,
        },
        None => nplps::Positions::Grid(values),
    };
    let v = &positions;
    let m = slice(&mask, "mask")?;
    fn map(values: &[f64], per_pixel: bool) -> nplps::VertexMap<'_> {
        if per_pixel {
            nplps::VertexMap::Pixels(values)
        } else {
            nplps::VertexMap::Vertices(values)
        }
    }
    let n = match &normals {
        Some(n) => Some(map(slice(n, "normals")?, per_pixel)),
        None => None,
    };
    let colors = match &albedo {
        Some(a) => Some(nplps::PlyColors {
            albedo: map(slice(a, "albedo")?, per_pixel),
            channels: a.shape()[2],
            scale,
        }),
        None => None,
    };
    type Counts = (usize, usize, usize, usize);
    let written = py.detach(|| {
        no_panic(|| -> nplps::Result<std::io::Result<Counts>> {
            let plan = nplps::ply_plan(v, n.as_ref(), colors.as_ref(), m, h, w)?;
            let counts = (plan.vertices, plan.facets, plan.skipped, plan.overflow);
            if plan.facets == 0 || plan.overflow > 0 {
                return Ok(Ok(counts));
            }
            let file = match std::fs::File::create(&path) {
                Ok(f) => f,
                Err(e) => return Ok(Err(e)),
            };
            let mut out = std::io::BufWriter::with_capacity(1 << 20, file);
            let done = nplps::write_ply_records(
                &mut out,
                &plan,
                v,
                n.as_ref(),
                colors.as_ref(),
                m,
                h,
                w,
                opengl,
            )?;
            Ok(done
                .and_then(|()| out.into_inner().map_err(|e| e.into_error()).map(drop))
                .map(|()| counts))
        })
    });
    match written.map_err(to_py)? {
        Ok(counts) => Ok(counts),
        Err(e) => Err(match e.raw_os_error() {
            Some(errno) => pyo3::exceptions::PyOSError::new_err((
                errno,
                e.to_string(),
                path.to_string_lossy().into_owned(),
            )),
            None => pyo3::exceptions::PyOSError::new_err(format!("{e}: {}", path.display())),
        }),
    }
}

/// The mesh of the masked facets with finite corners (`nplps::mesh_arrays`): `(used, points,
/// normals, faces, skipped)` with the used vertices' flat indices (int64), their positions and
/// normals (float32, (n, 3); normals None without `normals`), the triangles (int32, (m, 3)) and
/// the number of masked facets left out.
#[pyfunction]
#[pyo3(signature = (vertices, mask, normals, opengl))]
#[allow(clippy::type_complexity)]
fn mesh_arrays<'py>(
    py: Python<'py>,
    vertices: PyReadonlyArray3<'py, f64>,
    mask: PyReadonlyArray2<'py, bool>,
    normals: Option<PyReadonlyArray3<'py, f64>>,
    opengl: bool,
) -> PyResult<(
    Bound<'py, PyAny>,
    Bound<'py, PyAny>,
    Option<Bound<'py, PyAny>>,
    Bound<'py, PyAny>,
    usize,
)> {
    let shape = vertices.shape().to_vec();
    if shape[0] < 2 || shape[1] < 2 || shape[2] != 3 {
        return Err(InputError::new_err(format!(
            "vertices must have shape (H + 1, W + 1, 3), got {shape:?}"
        )));
    }
    let (h, w) = (shape[0] - 1, shape[1] - 1);
    let v = slice(&vertices, "vertices")?;
    let m = slice(&mask, "mask")?;
    let n = normals.as_ref().map(|n| slice(n, "normals")).transpose()?;
    let mesh = py
        .detach(|| no_panic(|| nplps::mesh_arrays(v, n, m, h, w, opengl)))
        .map_err(to_py)?;
    let used = mesh.used;
    let count = used.len();
    let points = array(py, mesh.points.into_flattened(), &[count, 3])?;
    let normals = match normals {
        Some(_) => Some(array(py, mesh.normals.into_flattened(), &[count, 3])?),
        None => None,
    };
    let faces = mesh.faces.len();
    Ok((
        array(py, used, &[count])?,
        points,
        normals,
        array(py, mesh.faces.into_flattened(), &[faces, 3])?,
        mesh.skipped,
    ))
}

/// Validates a rig (camera and lights mappings, any number of lights: rendering, prediction and
/// calibration take one or two; reconstruction checks for 3 itself); raises `RigError` when it
/// is invalid.
#[pyfunction]
fn check_rig<'py>(camera: &Bound<'py, PyDict>, lights: &Bound<'py, PyDict>) -> PyResult<()> {
    let rig = lighting_from(camera, lights)?;
    if rig.lights.is_empty() {
        return Err(RigError::new_err(
            "a rig needs at least one light, it has 0 lights",
        ));
    }
    Ok(())
}

/// The camera mapping checked and in its canonical form (floats; a pinhole camera's distortion
/// as the 5 coefficients k1, k2, p1, p2, k3; comment keys dropped); raises `RigError`.
#[pyfunction]
fn normalize_camera<'py>(
    py: Python<'py>,
    camera: &Bound<'py, PyDict>,
) -> PyResult<Bound<'py, PyDict>> {
    camera_dict(py, &camera_from(camera)?)
}

/// A synthetic scene with ground truth: dict of depth, mask, albedo, camera and lights.
/// `options` are the keyword flags `pinhole`, `led`, `rgb` and `directional` (all false by
/// default; see `nplps::SceneOptions`).
#[pyfunction]
#[pyo3(signature = (name, n, size, distance, seed, **options))]
fn synth_scene<'py>(
    py: Python<'py>,
    name: &str,
    n: usize,
    size: f64,
    distance: f64,
    seed: u64,
    options: Option<&Bound<'py, PyDict>>,
) -> PyResult<Bound<'py, PyDict>> {
    let flags = match options {
        Some(d) => {
            check_options(d, &["directional", "led", "pinhole", "rgb"])?;
            d.clone()
        }
        None => PyDict::new(py),
    };
    let options = nplps::SceneOptions::default()
        .with_pinhole(option(&flags, "pinhole", false)?)
        .with_led(option(&flags, "led", false)?)
        .with_rgb(option(&flags, "rgb", false)?)
        .with_directional(option(&flags, "directional", false)?);
    let scene = no_panic(|| {
        nplps::SceneKind::from_name(name)
            .and_then(|kind| nplps::Scene::with_options(kind, n, size, distance, seed, options))
    })
    .map_err(to_py)?;
    let d = PyDict::new(py);
    d.set_item("depth", array(py, scene.depth, &[n + 1, n + 1])?)?;
    d.set_item("mask", array(py, scene.mask, &[n, n])?)?;
    let albedo_shape: &[usize] = if scene.channels == 1 {
        &[n, n]
    } else {
        &[n, n, 3]
    };
    d.set_item("albedo", array(py, scene.albedo, albedo_shape)?)?;
    d.set_item("rig", rig::Rig::of(scene.rig, None))?;
    d.set_item("size", scene.size)?;
    Ok(d)
}

/// The compiled core of nplps.
#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    pool::remember_process();
    // Load numpy's C API now: loading it runs Python code, and a Ctrl-C arriving during that
    // first load inside a call would surface as a panic of the numpy crate instead of a
    // KeyboardInterrupt.
    let _ = numpy::PyArray1::<f64>::zeros(m.py(), [0], false);
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("MULTIGRID_MAX_ITERATIONS", nplps::MULTIGRID_MAX_ITERATIONS)?;
    m.add_class::<records::IterationStats>()?;
    m.add_class::<records::SearchProgress>()?;
    m.add_class::<rig::Rig>()?;
    m.add_function(wrap_pyfunction!(rig::read_rig, m)?)?;
    m.add_function(wrap_pyfunction!(rig::parse_rig, m)?)?;
    m.add_function(wrap_pyfunction!(reconstruct, m)?)?;
    m.add_function(wrap_pyfunction!(reconstruct_parallel, m)?)?;
    m.add_function(wrap_pyfunction!(render, m)?)?;
    m.add_function(wrap_pyfunction!(cast_shadows, m)?)?;
    m.add_function(wrap_pyfunction!(estimate_noise, m)?)?;
    m.add_function(wrap_pyfunction!(predict, m)?)?;
    m.add_function(wrap_pyfunction!(mesh_normals, m)?)?;
    m.add_function(wrap_pyfunction!(trust_figures, m)?)?;
    m.add_function(wrap_pyfunction!(grey_pixels, m)?)?;
    m.add_function(wrap_pyfunction!(normal_map_pixels, m)?)?;
    m.add_function(wrap_pyfunction!(vertices, m)?)?;
    m.add_function(wrap_pyfunction!(vertex_means, m)?)?;
    m.add_function(wrap_pyfunction!(mesh_arrays, m)?)?;
    m.add_function(wrap_pyfunction!(write_ply, m)?)?;
    m.add_function(wrap_pyfunction!(check_rig, m)?)?;
    m.add_function(wrap_pyfunction!(normalize_camera, m)?)?;
    m.add("MAX_LIGHTS", nplps::MAX_LIGHTS)?;
    m.add_function(wrap_pyfunction!(synth_scene, m)?)?;
    m.add_function(wrap_pyfunction!(decode::read_pngs, m)?)?;
    m.add_function(wrap_pyfunction!(encode::write_pngs, m)?)?;
    m.add_function(wrap_pyfunction!(calibrate::calibrate_spheres, m)?)?;
    m.add_function(wrap_pyfunction!(calibrate::calibrate_intensities, m)?)?;
    m.add_function(wrap_pyfunction!(calibrate::synth_spheres, m)?)?;
    m.add_function(wrap_pyfunction!(calibrate::synth_board, m)?)?;
    Ok(())
}
