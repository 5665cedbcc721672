//! Conversions between Python objects and the core's types.
//!
//! The camera is the rig file's `camera` mapping (`model` = "orthographic" with `pixel_size`
//! and `origin`, or "pinhole" with `K` and optional `distortion`). The lights are a mapping of
//! per-light lists: `vectors` (k x 3: positions of point lights, unit directions towards the light
//! of directional lights), `directional` (k booleans), `intensities` (k x 3), `axes` (k x 3, LED
//! principal directions) and `mu` (k anisotropies).

use numpy::{IntoPyArray, PyArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{
    PyBool, PyBytes, PyDict, PyDictMethods, PyFloat, PyInt, PyList, PyString, PyTuple,
};

use nplps::g6;

use crate::errors::{to_py, with_fields, InputError, RigError};

// ------------------------------------------------------------------------------------------------
// Strict reading of the rig mappings. Every key of the camera and lights mappings is checked for
// its type and shape here, in one place for every function of the bindings: a malformed value is
// a `RigError` naming it (`camera.distortion[2]`), never dropped; numbers are ints or floats
// (numpy scalars too), never booleans or strings, and finite; lists are lists, tuples or numpy
// arrays; keys starting with '_' are comments, any other unknown key is an error (a misspelt
// key must not silently fall back to a default).
// ------------------------------------------------------------------------------------------------

fn rig_error(message: String) -> PyErr {
    RigError::new_err(message)
}

/// At most 40 characters of `s` for a message.
fn short(s: &str) -> String {
    if s.chars().count() <= 40 {
        format!("{s:?}")
    } else {
        let head: String = s.chars().take(37).collect();
        format!("{head:?}...")
    }
}

/// The type name of `v` (`float`, `ndarray`, ...).
fn type_name(v: &Bound<'_, PyAny>) -> String {
    v.get_type()
        .name()
        .map(|n| n.to_string())
        .unwrap_or_else(|_| "object".to_string())
}

/// Whether `v` is a boolean (Python's or numpy's).
fn is_bool(v: &Bound<'_, PyAny>) -> bool {
    v.is_instance_of::<PyBool>() || matches!(type_name(v).as_str(), "bool" | "bool_")
}

/// Whether `v` is an array with at least one dimension (numpy).
fn is_array(v: &Bound<'_, PyAny>) -> bool {
    v.getattr("ndim")
        .and_then(|n| n.extract::<usize>())
        .is_ok_and(|n| n >= 1)
        && v.hasattr("tolist").unwrap_or(false)
}

/// A short description of a value for messages: never its full repr, which may be huge or
/// nested too deeply to print.
fn describe(v: &Bound<'_, PyAny>) -> String {
    if v.is_none() {
        return "null".to_string();
    }
    if is_bool(v) {
        return format!("the boolean {}", v.is_truthy().unwrap_or(false));
    }
    if let Ok(s) = v.cast::<PyString>() {
        return format!("the string {}", short(&s.to_string_lossy()));
    }
    let count = |n: usize| format!("{n} item{}", if n == 1 { "" } else { "s" });
    if let Ok(l) = v.cast::<PyList>() {
        return format!("a list of {}", count(l.len()));
    }
    if let Ok(t) = v.cast::<PyTuple>() {
        return format!("a tuple of {}", count(t.len()));
    }
    if v.is_instance_of::<PyDict>() {
        return "an object (mapping)".to_string();
    }
    if is_array(v) {
        let shape = v
            .getattr("shape")
            .and_then(|s| s.extract::<Vec<usize>>())
            .unwrap_or_default();
        return format!("an array of shape {shape:?}");
    }
    if v.is_instance_of::<PyInt>()
        || v.is_instance_of::<PyFloat>()
        || v.hasattr("__float__").unwrap_or(false)
    {
        if let Ok(x) = v.extract::<f64>() {
            return g6(x);
        }
        if v.is_instance_of::<PyInt>() {
            return "an integer too large for a floating-point number".to_string();
        }
    }
    format!("a value of type {}", short(&type_name(v)))
}

/// A finite number: an int or a float (numpy scalars included), not a boolean or a string.
fn number(v: &Bound<'_, PyAny>, what: &str) -> PyResult<f64> {
    let x = value(v, what)?;
    if !x.is_finite() {
        return Err(rig_error(format!(
            "{what} must be a finite number, got {}",
            g6(x)
        )));
    }
    Ok(x)
}

/// A number, perhaps not finite (for the lights mapping, whose values the core checks naming
/// the light and the parameter).
fn value(v: &Bound<'_, PyAny>, what: &str) -> PyResult<f64> {
    let bad = || rig_error(format!("{what} must be a number, got {}", describe(v)));
    let excluded = v.is_none()
        || is_bool(v)
        || v.is_instance_of::<PyString>()
        || v.is_instance_of::<PyBytes>()
        || v.is_instance_of::<PyList>()
        || v.is_instance_of::<PyTuple>()
        || v.is_instance_of::<PyDict>()
        || is_array(v);
    if excluded {
        return Err(bad());
    }
    let x: f64 = match v.extract() {
        Ok(x) => x,
        Err(_) if v.is_instance_of::<PyInt>() => {
            return Err(rig_error(format!(
                "{what} is an integer too large for a floating-point number"
            )))
        }
        Err(_) => return Err(bad()),
    };
    Ok(x)
}

/// The items of a list (a list, a tuple or a numpy array with at least one dimension), at most
/// `max` of them.
fn items<'py>(v: &Bound<'py, PyAny>, what: &str, max: usize) -> PyResult<Vec<Bound<'py, PyAny>>> {
    let list = if v.is_instance_of::<PyList>() || v.is_instance_of::<PyTuple>() {
        v.clone()
    } else if is_array(v) {
        let size: usize = v.getattr("size")?.extract()?;
        if size > max.saturating_mul(16) {
            return Err(rig_error(format!(
                "{what} has {size} values; at most {max} items are expected"
            )));
        }
        v.call_method0("tolist")?
    } else {
        return Err(rig_error(format!(
            "{what} must be a list, got {}",
            describe(v)
        )));
    };
    let n = list.len()?;
    if n > max {
        return Err(rig_error(format!(
            "{what} has {n} items; at most {max} are allowed"
        )));
    }
    list.try_iter()?.collect()
}

/// Exactly `N` numbers, finite ones when `finite` (else see [`value`]).
fn numbers<const N: usize>(v: &Bound<'_, PyAny>, what: &str, finite: bool) -> PyResult<[f64; N]> {
    let wrong = || rig_error(format!("{what} must be {N} numbers, got {}", describe(v)));
    let list = items(v, what, N).map_err(|_| wrong())?;
    if list.len() != N {
        return Err(wrong());
    }
    let mut out = [0.0; N];
    for (i, (o, x)) in out.iter_mut().zip(&list).enumerate() {
        let what = format!("{what}[{i}]");
        *o = if finite {
            number(x, &what)?
        } else {
            value(x, &what)?
        };
    }
    Ok(out)
}

/// Fails on a key of `dict` that is not in `known` and does not start with '_' (a comment).
fn check_keys(dict: &Bound<'_, PyDict>, what: &str, known: &[&str], usage: &str) -> PyResult<()> {
    for (key, _) in dict.iter() {
        let Ok(name) = key.cast::<PyString>() else {
            return Err(rig_error(format!(
                "{what} has a key that is not a string ({})",
                describe(&key)
            )));
        };
        let name = name.to_string_lossy();
        if !(name.starts_with('_') || known.contains(&name.as_ref())) {
            return Err(rig_error(format!(
                "{what} has an unknown key {} ({usage}; keys starting with '_' are comments)",
                short(&name)
            )));
        }
    }
    Ok(())
}

/// The value of `key` of `dict`; missing is a `RigError` naming the key.
fn required<'py>(dict: &Bound<'py, PyDict>, what: &str, key: &str) -> PyResult<Bound<'py, PyAny>> {
    dict.get_item(key)?
        .ok_or_else(|| rig_error(format!("{what} is missing the key {key:?}")))
}

/// Fails with an `InputError` naming a key of the options mapping `options` that is not one of
/// `known` (sorted), and listing the valid ones: a misspelt option must not silently fall back
/// to its default.
pub fn check_options(options: &Bound<'_, PyDict>, known: &[&str]) -> PyResult<()> {
    for (key, _) in options.iter() {
        let name = match key.cast::<PyString>() {
            Ok(name) => name.to_string_lossy().into_owned(),
            Err(_) => {
                return Err(InputError::new_err(format!(
                    "option keys must be strings, got {}",
                    describe(&key)
                )))
            }
        };
        if !known.contains(&name.as_str()) {
            let err = InputError::new_err(format!(
                "unknown option {}; the options are {}",
                short(&name),
                known.join(", ")
            ));
            return Err(with_fields(err, |x| x.setattr("argument", &name)));
        }
    }
    Ok(())
}

/// Reads an optional option of an options mapping (`InputError` when malformed).
pub fn option<'py, T: FromPyObjectOwned<'py>>(
    dict: &Bound<'py, PyDict>,
    key: &str,
    default: T,
) -> PyResult<T> {
    match dict.get_item(key)? {
        None => Ok(default),
        Some(v) if v.is_none() => Ok(default),
        Some(v) => v.extract::<T>().map_err(|e| {
            let e: PyErr = e.into();
            let err = InputError::new_err(format!("option {key:?} is invalid: {e}"));
            with_fields(err, |x| {
                x.setattr("argument", key)?;
                x.setattr("value", &v)
            })
        }),
    }
}

/// A Python value read by the core's camera-mapping rules ([`nplps::camera_from_map`]): lists
/// are lists, tuples or numpy arrays, numbers ints or floats (numpy scalars too), mappings dicts.
struct PyValue<'py>(Bound<'py, PyAny>);

impl<'py> nplps::MapValue for PyValue<'py> {
    type Error = PyErr;

    fn rig_error(message: String) -> PyErr {
        rig_error(message)
    }

    fn core_error(error: nplps::Error) -> PyErr {
        to_py(error)
    }

    fn describe(&self) -> String {
        describe(&self.0)
    }

    fn number(&self, what: &str) -> PyResult<f64> {
        number(&self.0, what)
    }

    fn items(&self, what: &str, max: usize) -> PyResult<Vec<PyValue<'py>>> {
        Ok(items(&self.0, what, max)?
            .into_iter()
            .map(PyValue)
            .collect())
    }

    fn is_list(&self) -> bool {
        self.0.is_instance_of::<PyList>() || self.0.is_instance_of::<PyTuple>() || is_array(&self.0)
    }

    fn is_null(&self) -> bool {
        self.0.is_none()
    }

    fn string(&self) -> Option<String> {
        self.0
            .cast::<PyString>()
            .ok()
            .map(|s| s.to_string_lossy().into_owned())
    }

    fn keys(&self, what: &str) -> PyResult<Vec<String>> {
        let dict = self.0.cast::<PyDict>()?;
        let mut names = Vec::with_capacity(dict.len());
        for (key, _) in dict.iter() {
            let Ok(name) = key.cast::<PyString>() else {
                return Err(rig_error(format!(
                    "{what} has a key that is not a string ({})",
                    describe(&key)
                )));
            };
            names.push(name.to_string_lossy().into_owned());
        }
        Ok(names)
    }

    fn get(&self, key: &str) -> PyResult<Option<PyValue<'py>>> {
        Ok(self.0.cast::<PyDict>()?.get_item(key)?.map(PyValue))
    }
}

/// Builds a core [`nplps::Camera`] from the rig file's `camera` mapping, by the core's rules
/// ([`nplps::camera_from_map`], shared with the rig file reader of `nplps::io`).
pub fn camera_from(camera: &Bound<'_, PyDict>) -> PyResult<nplps::Camera> {
    nplps::camera_from_map(&PyValue(camera.clone().into_any()))
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
        ref other => {
            return Err(rig_error(format!(
                "camera model {other:?} has no rig file form in this version"
            )))
        }
    }
    Ok(d)
}

/// Builds the core's lights from the lights mapping (see the module documentation): the keys
/// `vectors`, `directional`, `intensities`, `axes` and `mu`, each with one item per light (at
/// most [`nplps::MAX_LIGHTS`]), every value checked (see above).
pub fn lights_from(lights: &Bound<'_, PyDict>) -> PyResult<Vec<nplps::Light>> {
    const KEYS: [&str; 5] = ["vectors", "directional", "intensities", "axes", "mu"];
    check_keys(
        lights,
        "lights",
        &[
            "vectors",
            "directional",
            "intensities",
            "axes",
            "mu",
            "kind",
        ],
        "the lights mapping has vectors, directional, intensities, axes, mu and optionally kind",
    )?;
    let max = nplps::MAX_LIGHTS;
    let list = |key: &str| -> PyResult<Vec<Bound<'_, PyAny>>> {
        let value = required(lights, "lights", key)?;
        items(&value, &format!("lights.{key}"), max).map_err(|e| {
            if value.len().is_ok_and(|n| n > max) {
                rig_error(format!(
                    "the rig has more than {max} lights, the most nplps supports"
                ))
            } else {
                e
            }
        })
    };
    let [vectors, directional, intensities, axes, mu] = [
        list(KEYS[0])?,
        list(KEYS[1])?,
        list(KEYS[2])?,
        list(KEYS[3])?,
        list(KEYS[4])?,
    ];
    let k = vectors.len();
    if [directional.len(), intensities.len(), axes.len(), mu.len()]
        .iter()
        .any(|&n| n != k)
    {
        return Err(rig_error(format!(
            "every light needs all its parameters ({k} lights)"
        )));
    }
    (0..k)
        .map(|i| {
            let flag = &directional[i];
            if !is_bool(flag) {
                return Err(rig_error(format!(
                    "lights.directional[{i}] must be a boolean, got {}",
                    describe(flag)
                )));
            }
            let vector = numbers(&vectors[i], &format!("lights.vectors[{i}]"), false)?;
            let intensity = numbers(&intensities[i], &format!("lights.intensities[{i}]"), false)?;
            let axis = numbers(&axes[i], &format!("lights.axes[{i}]"), false)?;
            let mu = value(&mu[i], &format!("lights.mu[{i}]"))?;
            Ok(if flag.is_truthy()? {
                nplps::Light::Directional {
                    direction: vector,
                    intensity,
                }
            } else {
                nplps::Light::Point {
                    position: vector,
                    intensity,
                    axis,
                    mu,
                }
            })
        })
        .collect()
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
            ref other => {
                return Err(rig_error(format!(
                    "light {other:?} has no form in the lights mapping of this version"
                )))
            }
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

/// Builds a core [`nplps::Rig`] for rendering: any number of lights, each one valid.
pub fn lighting_from(
    camera: &Bound<'_, PyDict>,
    lights: &Bound<'_, PyDict>,
) -> PyResult<nplps::Rig> {
    let rig = nplps::Rig {
        camera: camera_from(camera)?,
        lights: lights_from(lights)?,
    };
    rig.validate_parameters().map_err(to_py)?;
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
