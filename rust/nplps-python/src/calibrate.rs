//! Bindings of the light calibration (`nplps::calibrate`) and of the synthetic calibration scenes
//! (`nplps::calibration_scene`): convert, delegate with the GIL released, map the errors.

use numpy::{PyReadonlyArray2, PyReadonlyArray3, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

use crate::convert::{array, camera_from, check_options, option};
use crate::errors::{no_panic, to_py, InputError};
use crate::rig::Rig;
use nplps::calibrate::{
    BoardAlbedo, BoardImages, Detection, HighlightOptions, LightEstimate, Outline, Placement,
    Plane, SphereOptions, SphereSource,
};

fn input_error(message: String) -> PyErr {
    InputError::new_err(message)
}

/// Sphere calibration (see `nplps.calibrate.calibrate_spheres`). Each placement i has the
/// (k, H, W) float32 `images[i]`, a (H, W) uint32 label image `labels[i]` or a detection
/// `detect[i]` = (min radius, max radius, count or None) in pixels, and `center_depth[i]` (empty,
/// one value, or one per sphere). Returns a dict with `spheres`, `lights`, `observations` and
/// `warnings`.
#[pyfunction]
#[pyo3(signature = (images, labels, detect, center_depth, camera, radius, options))]
pub fn calibrate_spheres<'py>(
    images: Vec<PyReadonlyArray3<'py, f32>>,
    labels: Vec<Option<PyReadonlyArray2<'py, u32>>>,
    detect: Vec<Option<(f64, f64, Option<usize>)>>,
    center_depth: Vec<Vec<f64>>,
    camera: &Bound<'py, PyDict>,
    radius: f64,
    options: &Bound<'py, PyDict>,
) -> PyResult<Bound<'py, PyDict>> {
    let py = camera.py();
    check_options(
        options,
        &[
            "limb_margin",
            "max_blob_fraction",
            "min_component",
            "min_contrast",
            "outline",
            "parallel_tol",
            "refine",
        ],
    )?;
    let cam = camera_from(camera)?;
    let n = images.len();
    if labels.len() != n || detect.len() != n || center_depth.len() != n {
        return Err(input_error(
            "every placement needs its images, a mask or a detection, and its centre depths".into(),
        ));
    }
    let Some(first) = images.first() else {
        return Err(input_error("no sphere images (no placement) given".into()));
    };
    let [k, h, w] = [first.shape()[0], first.shape()[1], first.shape()[2]];
    let mut placements = Vec::with_capacity(n);
    for i in 0..n {
        let s = images[i].shape();
        if s != [k, h, w] {
            return Err(input_error(format!(
                    "placement {i} has images of shape {s:?} but placement 0 has {:?}: every placement needs one image per light, all of one size",
                    [k, h, w]
                ),
            ));
        }
        let imgs = images[i]
            .as_slice()
            .map_err(|_| input_error(format!("placement {i}: images must be C-contiguous")))?;
        let spheres = match (&labels[i], detect[i]) {
            (Some(l), None) => {
                if l.shape() != [h, w] {
                    return Err(input_error(format!(
                        "placement {i}: the mask is {} x {} pixels but the images are {w} x {h}",
                        l.shape()[1],
                        l.shape()[0]
                    )));
                }
                SphereSource::Labels(l.as_slice().map_err(|_| {
                    input_error(format!("placement {i}: the mask must be C-contiguous"))
                })?)
            }
            (None, Some((lo, hi, count))) => SphereSource::Detect(Detection {
                radius_range: [lo, hi],
                count,
            }),
            _ => {
                return Err(input_error(format!(
                    "placement {i}: give exactly one of a mask or a detection radius range"
                )))
            }
        };
        placements.push(Placement {
            images: imgs,
            spheres,
            center_depth: center_depth[i].clone(),
        });
    }
    let defaults = SphereOptions::default();
    let outline = match option(options, "outline", "mask".to_string())?.as_str() {
        "mask" => Outline::Mask,
        "images" => Outline::Images,
        other => {
            return Err(input_error(format!(
                "outline must be \"mask\" or \"images\", got {other:?}"
            )))
        }
    };
    let hd = HighlightOptions::default();
    let highlight = hd
        .with_min_contrast(option(options, "min_contrast", hd.min_contrast)?)
        .with_max_blob_fraction(option(options, "max_blob_fraction", hd.max_blob_fraction)?)
        .with_limb_margin(option(options, "limb_margin", hd.limb_margin)?);
    let opts = defaults
        .with_radius(radius)
        .with_outline(outline)
        .with_parallel_tol(option(options, "parallel_tol", defaults.parallel_tol)?)
        .with_highlight(highlight)
        .with_min_component(option(options, "min_component", defaults.min_component)?)
        .with_refine(option(options, "refine", defaults.refine)?);
    let result = py
        .detach(|| {
            no_panic(|| nplps::calibrate::calibrate_spheres(&cam, &placements, h, w, k, &opts))
        })
        .map_err(to_py)?;

    let out = PyDict::new(py);
    let spheres = PyList::empty(py);
    for s in &result.spheres {
        let d = PyDict::new(py);
        d.set_item("placement", s.placement)?;
        d.set_item("center", s.center.to_vec())?;
        d.set_item("radius", s.radius)?;
        d.set_item("image_center", s.image_center.to_vec())?;
        d.set_item("image_radius", s.image_radius)?;
        d.set_item("fit_rms", s.fit_rms)?;
        d.set_item("outline_points", s.outline_points.to_vec())?;
        d.set_item("scale_check", s.scale_check)?;
        d.set_item("shift", s.shift)?;
        d.set_item("outline_sigma", s.outline_sigma)?;
        spheres.append(d)?;
    }
    out.set_item("spheres", spheres)?;
    let lights = PyList::empty(py);
    for l in &result.lights {
        let d = PyDict::new(py);
        let (kind, vector) = match l.estimate {
            LightEstimate::Point(p) => ("point", Some(p.to_vec())),
            LightEstimate::Directional(v) => ("directional", Some(v.to_vec())),
            LightEstimate::Missing => ("missing", None),
        };
        d.set_item("kind", kind)?;
        d.set_item("vector", vector)?;
        d.set_item("rms_miss", l.rms_miss)?;
        d.set_item("rms_angle", l.rms_angle)?;
        d.set_item("spread", l.spread)?;
        d.set_item("spheres", l.spheres)?;
        d.set_item("warning", l.warning.clone())?;
        lights.append(d)?;
    }
    out.set_item("lights", lights)?;
    let (ns, nl) = (result.spheres.len(), k);
    let mut pixel = vec![f64::NAN; nl * ns * 2];
    let mut peak = vec![f64::NAN; nl * ns];
    let mut area = vec![0u64; nl * ns];
    let mut saturated = vec![0u64; nl * ns];
    let mut correction = vec![f64::NAN; nl * ns];
    let mut origin = vec![f64::NAN; nl * ns * 3];
    let mut direction = vec![f64::NAN; nl * ns * 3];
    let mut status = Vec::with_capacity(nl * ns);
    for o in &result.observations {
        let j = o.light * ns + o.sphere;
        match o.highlight {
            Ok(hl) => {
                pixel[2 * j..2 * j + 2].copy_from_slice(&hl.pixel);
                peak[j] = hl.peak;
                area[j] = hl.area as u64;
                saturated[j] = hl.saturated as u64;
                correction[j] = hl.correction;
                status.push("ok");
            }
            Err(r) => status.push(r.describe()),
        }
        if let Some(ray) = o.ray {
            origin[3 * j..3 * j + 3].copy_from_slice(&ray.origin);
            direction[3 * j..3 * j + 3].copy_from_slice(&ray.direction);
        }
    }
    let obs = PyDict::new(py);
    obs.set_item("pixel", array(py, pixel, &[nl, ns, 2])?)?;
    obs.set_item("peak", array(py, peak, &[nl, ns])?)?;
    obs.set_item("area", array(py, area, &[nl, ns])?)?;
    obs.set_item("saturated", array(py, saturated, &[nl, ns])?)?;
    obs.set_item("correction", array(py, correction, &[nl, ns])?)?;
    obs.set_item("origin", array(py, origin, &[nl, ns, 3])?)?;
    obs.set_item("direction", array(py, direction, &[nl, ns, 3])?)?;
    obs.set_item("status", status)?;
    out.set_item("observations", obs)?;
    out.set_item("warnings", result.warnings)?;
    if let Some(r) = &result.refinement {
        let d = PyDict::new(py);
        d.set_item("iterations", r.iterations)?;
        d.set_item("highlights", r.highlights)?;
        d.set_item("dropped", r.dropped)?;
        d.set_item("highlight_rms", r.highlight_rms.to_vec())?;
        d.set_item("outline_shift", r.outline_shift)?;
        d.set_item("highlight_sigma", r.highlight_sigma)?;
        out.set_item("refinement", d)?;
    }
    Ok(out)
}

/// Intensity calibration from board images (see `nplps.calibrate.calibrate_intensities`):
/// float32 (k, H, W) or (k, H, W, 3) images, a (H, W) mask or None, the rig, the plane
/// (normal, offset) with `normal . X = offset`.
#[pyfunction]
#[pyo3(signature = (images, mask, rig, normal, offset, options))]
pub fn calibrate_intensities<'py>(
    images: PyReadonlyArrayDyn<'py, f32>,
    mask: Option<PyReadonlyArray2<'py, bool>>,
    rig: &Bound<'py, Rig>,
    normal: [f64; 3],
    offset: f64,
    options: &Bound<'py, PyDict>,
) -> PyResult<Bound<'py, PyDict>> {
    let py = images.py();
    check_options(
        options,
        &[
            "albedo",
            "dark",
            "fit_direction",
            "fit_mu",
            "iterations",
            "saturation",
        ],
    )?;
    let input = rig.get();
    let rig = &input.rig;
    let [k, h, w, c] = match *images.shape() {
        [k, h, w] => [k, h, w, 1],
        [k, h, w, c] => [k, h, w, c],
        ref s => {
            return Err(input_error(format!(
                "board images must be (k, H, W) or (k, H, W, 3), got shape {s:?}"
            )))
        }
    };
    let data = images
        .as_slice()
        .map_err(|_| input_error("board images must be C-contiguous".into()))?;
    let mask_s = match &mask {
        Some(m) => {
            if m.shape() != [h, w] {
                return Err(input_error(format!(
                    "the mask is {} x {} pixels but the images are {w} x {h}",
                    m.shape()[1],
                    m.shape()[0]
                )));
            }
            Some(
                m.as_slice()
                    .map_err(|_| input_error("the mask must be C-contiguous".into()))?,
            )
        }
        None => None,
    };
    let defaults = nplps::calibrate::IntensityOptions::default();
    let albedo = match option(options, "albedo", "uniform".to_string())?.as_str() {
        "uniform" => BoardAlbedo::Uniform,
        "per_pixel" => BoardAlbedo::PerPixel,
        other => {
            return Err(input_error(format!(
                "albedo must be \"uniform\" or \"per_pixel\", got {other:?}"
            )))
        }
    };
    let opts = defaults
        .with_fit_mu(option(options, "fit_mu", defaults.fit_mu)?)
        .with_fit_axis(option(options, "fit_direction", defaults.fit_axis)?)
        .with_albedo(albedo)
        .with_dark(option(options, "dark", defaults.dark)?)
        .with_saturation(option(options, "saturation", defaults.saturation)?)
        .with_iterations(option(options, "iterations", defaults.iterations)?);
    let plane = Plane { normal, offset };
    let result = py
        .detach(|| {
            no_panic(|| {
                let board = BoardImages {
                    images: data,
                    k,
                    height: h,
                    width: w,
                    channels: c,
                    mask: mask_s,
                };
                nplps::calibrate::calibrate_intensities(
                    &rig.camera,
                    &board,
                    &plane,
                    &rig.lights,
                    &opts,
                )
            })
        })
        .map_err(to_py)?;
    let out = PyDict::new(py);
    out.set_item("lights", input.with_lights(result.lights))?;
    let intensity: Vec<f64> = result
        .reports
        .iter()
        .flat_map(|r| r.intensity.clone())
        .collect();
    out.set_item("intensity", array(py, intensity, &[k, c])?)?;
    out.set_item(
        "mu",
        result.reports.iter().map(|r| r.mu).collect::<Vec<_>>(),
    )?;
    out.set_item(
        "axes",
        result
            .reports
            .iter()
            .map(|r| r.axis.to_vec())
            .collect::<Vec<_>>(),
    )?;
    out.set_item(
        "rms",
        result.reports.iter().map(|r| r.rms).collect::<Vec<_>>(),
    )?;
    out.set_item(
        "observations",
        result
            .reports
            .iter()
            .map(|r| r.observations)
            .collect::<Vec<_>>(),
    )?;
    out.set_item("scale", result.scale)?;
    let albedo_shape: &[usize] = if c == 1 { &[h, w] } else { &[h, w, c] };
    out.set_item("albedo", array(py, result.albedo, albedo_shape)?)?;
    out.set_item("iterations", result.iterations)?;
    out.set_item("warnings", result.warnings)?;
    Ok(out)
}

/// Renders k images (k, H, W) of spheres (radiance, unclipped) and their (H, W) uint32 labels
/// (see `nplps.calibrate.make_sphere_scene`). `shape` is (H, W); `options` holds the material
/// (`diffuse`, `specular`, `exponent`, `background`) and `supersample` (rays per pixel and
/// side, default 1).
#[pyfunction]
#[pyo3(signature = (rig, shape, centers, radius, board, options))]
pub fn synth_spheres<'py>(
    rig: &Bound<'py, Rig>,
    shape: (usize, usize),
    centers: Vec<[f64; 3]>,
    radius: f64,
    board: Option<([f64; 3], f64)>,
    options: &Bound<'py, PyDict>,
) -> PyResult<Bound<'py, PyDict>> {
    let py = rig.py();
    let (height, width) = shape;
    check_options(
        options,
        &[
            "background",
            "diffuse",
            "exponent",
            "specular",
            "supersample",
        ],
    )?;
    let rig = &rig.get().rig;
    let d = nplps::calibration_scene::SphereMaterial::default();
    let m = nplps::calibration_scene::SphereMaterial {
        diffuse: option(options, "diffuse", d.diffuse)?,
        specular: option(options, "specular", d.specular)?,
        exponent: option(options, "exponent", d.exponent)?,
        background: option(options, "background", d.background)?,
    };
    let supersample: usize = option(options, "supersample", 1)?;
    let board = board.map(|(normal, offset)| Plane { normal, offset });
    let scene = py
        .detach(|| {
            no_panic(|| {
                let layout = nplps::calibration_scene::SphereLayout {
                    height,
                    width,
                    centers: &centers,
                    radius,
                    board,
                };
                nplps::calibration_scene::render_spheres(rig, &layout, &m, supersample)
            })
        })
        .map_err(to_py)?;
    let out = PyDict::new(py);
    out.set_item(
        "images",
        array(py, scene.images, &[rig.n_lights(), height, width])?,
    )?;
    out.set_item("labels", array(py, scene.labels, &[height, width])?)?;
    Ok(out)
}

/// Renders k images (k, H, W[, 3]) of a flat board `normal . X = offset` with albedo (H, W) or
/// (H, W, 3) by the image model.
#[pyfunction]
#[pyo3(signature = (rig, normal, offset, albedo))]
pub fn synth_board<'py>(
    py: Python<'py>,
    rig: &Bound<'py, Rig>,
    normal: [f64; 3],
    offset: f64,
    albedo: PyReadonlyArrayDyn<'py, f64>,
) -> PyResult<Bound<'py, PyAny>> {
    let rig = &rig.get().rig;
    let (h, w, c) = match *albedo.shape() {
        [h, w] => (h, w, 1),
        [h, w, c] => (h, w, c),
        ref s => {
            return Err(input_error(format!(
                "albedo must be (H, W) or (H, W, 3), got shape {s:?}"
            )))
        }
    };
    let a = albedo
        .as_slice()
        .map_err(|_| input_error("albedo must be C-contiguous".into()))?;
    let plane = Plane { normal, offset };
    let images = py
        .detach(|| no_panic(|| nplps::calibration_scene::render_board(rig, h, w, &plane, a, c)))
        .map_err(to_py)?;
    let k = rig.n_lights();
    if c == 1 {
        array(py, images, &[k, h, w])
    } else {
        array(py, images, &[k, h, w, c])
    }
}
