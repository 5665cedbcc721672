//! `_core.Rig`: the core's rig, built and validated once, then passed by reference to every
//! function of the bindings that takes a rig.
//!
//! Each light keeps its kind ("point", "led" or "directional"): an LED with `mu` = 0 emits like a
//! point light but stays an LED, so that lights refined by a reconstruction come back as the
//! kinds they went in as.

use pyo3::prelude::*;
use pyo3::types::{PyDict, PyDictMethods, PyList, PyString, PyTuple};

use crate::convert::{camera_dict, camera_from, lights_dict, lights_from};
use crate::errors::{to_py, RigError};

/// The kind of a light as the Python package sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    Point,
    Led,
    Directional,
}

impl Kind {
    pub fn name(self) -> &'static str {
        match self {
            Kind::Point => "point",
            Kind::Led => "led",
            Kind::Directional => "directional",
        }
    }

    /// The kind of a core light that has no other word on it: an LED when its `mu` > 0.
    pub fn of(light: &nplps::Light) -> Kind {
        match *light {
            nplps::Light::Directional { .. } => Kind::Directional,
            nplps::Light::Point { mu, .. } if mu > 0.0 => Kind::Led,
            _ => Kind::Point,
        }
    }
}

/// What `__reduce__` gives: the class and its arguments (camera and lights mappings).
type Reduced<'py> = (Bound<'py, PyAny>, (Bound<'py, PyDict>, Bound<'py, PyDict>));

/// A validated rig (camera and lights, each light with its kind).
#[pyclass(frozen, module = "nplps._core", name = "Rig")]
pub struct Rig {
    pub rig: nplps::Rig,
    pub kinds: Vec<Kind>,
}

impl Rig {
    /// A rig of core values, its kinds given or (None) read from the lights.
    pub fn of(rig: nplps::Rig, kinds: Option<Vec<Kind>>) -> Rig {
        let kinds = kinds.unwrap_or_else(|| rig.lights.iter().map(Kind::of).collect());
        Rig { rig, kinds }
    }

    /// The rig with other values of its lights (refined by a reconstruction, calibrated), each
    /// of its kind; a point light that got an anisotropy (`mu` > 0) becomes an LED.
    pub fn with_lights(&self, lights: Vec<nplps::Light>) -> Rig {
        let kinds = self
            .kinds
            .iter()
            .zip(&lights)
            .map(|(&kind, light)| match (kind, Kind::of(light)) {
                (Kind::Point, Kind::Led) => Kind::Led,
                _ => kind,
            })
            .collect();
        Rig {
            rig: nplps::Rig {
                camera: self.rig.camera,
                lights,
            },
            kinds,
        }
    }
}

/// The kinds of the lights mapping's optional `kind` list (else read from the lights).
fn kinds_from(lights: &Bound<'_, PyDict>, core: &[nplps::Light]) -> PyResult<Vec<Kind>> {
    let Some(list) = lights.get_item("kind")? else {
        return Ok(core.iter().map(Kind::of).collect());
    };
    let items: Vec<Bound<'_, PyAny>> =
        if list.is_instance_of::<PyList>() || list.is_instance_of::<PyTuple>() {
            list.try_iter()?.collect::<PyResult<_>>()?
        } else {
            return Err(RigError::new_err("lights.kind must be a list of strings"));
        };
    if items.len() != core.len() {
        return Err(RigError::new_err(format!(
            "every light needs all its parameters ({} lights)",
            core.len()
        )));
    }
    items
        .iter()
        .zip(core)
        .enumerate()
        .map(|(i, (item, light))| {
            let name = item
                .cast::<PyString>()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default();
            let kind = match name.as_str() {
                "point" => Kind::Point,
                "led" => Kind::Led,
                "directional" => Kind::Directional,
                _ => {
                    return Err(RigError::new_err(format!(
                        "lights.kind[{i}] must be \"point\", \"led\" or \"directional\""
                    )))
                }
            };
            let directional = matches!(light, nplps::Light::Directional { .. });
            if directional != (kind == Kind::Directional) {
                return Err(RigError::new_err(format!(
                    "lights.kind[{i}] is {name:?} but lights.directional[{i}] is {directional}"
                )));
            }
            Ok(kind)
        })
        .collect()
}

#[pymethods]
impl Rig {
    /// Builds and validates a rig from the rig file's camera mapping and the lights mapping
    /// (`vectors`, `directional`, `intensities`, `axes`, `mu` and optionally `kind`); at least
    /// one light. Raises `RigError`.
    #[new]
    fn new(camera: &Bound<'_, PyDict>, lights: &Bound<'_, PyDict>) -> PyResult<Rig> {
        let rig = nplps::Rig {
            camera: camera_from(camera)?,
            lights: lights_from(lights)?,
        };
        rig.validate_parameters().map_err(to_py)?;
        if rig.lights.is_empty() {
            return Err(RigError::new_err(
                "a rig needs at least one light, it has 0 lights",
            ));
        }
        let kinds = kinds_from(lights, &rig.lights)?;
        Ok(Rig::of(rig, Some(kinds)))
    }

    /// The camera mapping in its canonical form.
    #[getter]
    fn camera<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        camera_dict(py, &self.rig.camera)
    }

    /// The lights mapping, with each light's `kind`.
    #[getter]
    fn lights<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = lights_dict(py, &self.rig.lights)?;
        let kinds: Vec<&str> = self.kinds.iter().map(|k| k.name()).collect();
        d.set_item("kind", kinds)?;
        Ok(d)
    }

    /// Number of lights.
    #[getter]
    fn n_lights(&self) -> usize {
        self.rig.n_lights()
    }

    /// The rig with the lights `indices` (already checked), in that order.
    fn subset(&self, indices: Vec<usize>) -> PyResult<Rig> {
        let k = self.rig.n_lights();
        if let Some(&i) = indices.iter().find(|&&i| i >= k) {
            return Err(RigError::new_err(format!(
                "light {i} is not a light of the rig (it has {k})"
            )));
        }
        Ok(Rig {
            rig: nplps::Rig {
                camera: self.rig.camera,
                lights: indices.iter().map(|&i| self.rig.lights[i]).collect(),
            },
            kinds: indices.iter().map(|&i| self.kinds[i]).collect(),
        })
    }

    fn __reduce__<'py>(slf: &Bound<'py, Self>) -> PyResult<Reduced<'py>> {
        let py = slf.py();
        let this = slf.get();
        Ok((
            slf.get_type().into_any(),
            (this.camera(py)?, this.lights(py)?),
        ))
    }

    fn __repr__(&self) -> String {
        format!("<nplps._core.Rig with {} lights>", self.rig.n_lights())
    }
}

/// A rig file read by the core: the rig, its grid (`None` or `(image_size or None, binning)`)
/// and its top-level comments (keys starting with `_`) as `(key, JSON text of the value)` in
/// the order of the file.
type RigFile = (
    Rig,
    Option<(Option<(u64, u64)>, u64)>,
    Vec<(String, String)>,
);

/// The Python form of a [`nplps::Rig::read_file`] result.
macro_rules! rig_file {
    ($file:expr, $source:expr) => {{
        let file = $file;
        if file.rig.lights.is_empty() {
            return Err(RigError::new_err(format!(
                "{}: a rig needs at least one light, it has 0 lights",
                $source
            )));
        }
        let kinds = file
            .rig
            .lights
            .iter()
            .zip(&file.leds)
            .map(|(light, &led)| match Kind::of(light) {
                Kind::Point if led => Kind::Led,
                kind => kind,
            })
            .collect();
        let grid = file
            .grid
            .map(|g| (g.image_size.map(|[w, h]| (w, h)), g.binning));
        let comments = file
            .comments
            .iter()
            .map(|(k, v)| (k.clone(), v.to_string()))
            .collect();
        (Rig::of(file.rig, Some(kinds)), grid, comments)
    }};
}

/// Reads a rig file (the core's reader, `nplps::io`); raises `RigError` naming the file and
/// the key.
#[pyfunction]
pub fn read_rig(py: Python<'_>, path: std::path::PathBuf) -> PyResult<RigFile> {
    let file = py.detach(|| nplps::Rig::read_file(&path)).map_err(to_py)?;
    Ok(rig_file!(file, path.display()))
}

/// Reads the JSON text of a rig file; `source` names it in the messages.
#[pyfunction]
pub fn parse_rig(text: &str, source: &str) -> PyResult<RigFile> {
    let file = nplps::Rig::parse_file(text, source).map_err(to_py)?;
    Ok(rig_file!(file, source))
}
