//! The camera mapping of a rig file, read strictly: the one implementation of its rules, for the
//! rig file reader ([`crate::io`], over JSON values) and for the Python bindings (over Python
//! objects). A source of values implements [`MapValue`]; [`camera_from_map`] reads the camera.
//!
//! The mapping has `model` = "orthographic" with `pixel_size` (w, h) and `origin` (x, y), or
//! "pinhole" with `K` (3 x 3) and an optional `distortion` (a flat list or OpenCV's 1 x n or
//! n x 1 matrix; see [`Camera::distortion_from`]; null or absent is none). Every value is
//! checked for its type and shape; a key that is not part of the model's form is an error
//! naming it, except keys starting with `_` (comments). Every problem is an [`Error::Rig`]
//! naming the key (`camera.distortion[2] must be a finite number, got NaN`).

use crate::error::Error;
use crate::rig::Camera;

/// A value of a mapping read by [`camera_from_map`]: a JSON value, a Python object, ...
/// Its methods fail with rig errors ([`MapValue::rig_error`]) whose messages name `what` and
/// describe the value.
pub trait MapValue: Sized {
    /// The error of this source of values ([`Error`] for JSON, the Python exception for the
    /// bindings).
    type Error;
    /// A rig error with `message` (an [`Error::Rig`], a `RigError`).
    fn rig_error(message: String) -> Self::Error;
    /// The core's error as this source's error.
    fn core_error(error: Error) -> Self::Error;
    /// A short description of the value for messages ("null", "the string \"x\"", "a list of
    /// 3 items", ...), never its full text.
    fn describe(&self) -> String;
    /// The value as a finite number, or an error naming `what`.
    fn number(&self, what: &str) -> std::result::Result<f64, Self::Error>;
    /// The items of a list (at most `max` of them), or an error naming `what`.
    fn items(&self, what: &str, max: usize) -> std::result::Result<Vec<Self>, Self::Error>;
    /// Whether the value is a list.
    fn is_list(&self) -> bool;
    /// Whether the value is null (None).
    fn is_null(&self) -> bool;
    /// The value as a string, if it is one.
    fn string(&self) -> Option<String>;
    /// The keys of a mapping, or an error naming `what` (a key that is not a string).
    fn keys(&self, what: &str) -> std::result::Result<Vec<String>, Self::Error>;
    /// The value of `key` of a mapping, if present.
    fn get(&self, key: &str) -> std::result::Result<Option<Self>, Self::Error>;
}

/// The result of reading values of the source `V`.
type Read<T, V> = std::result::Result<T, <V as MapValue>::Error>;

/// At most 40 characters of `s`, quoted, for a message.
pub(crate) fn short(s: &str) -> String {
    if s.chars().count() <= 40 {
        format!("{s:?}")
    } else {
        let head: String = s.chars().take(37).collect();
        format!("{head:?}...")
    }
}

/// Exactly `N` finite numbers.
fn numbers<const N: usize, V: MapValue>(v: &V, what: &str) -> Read<[f64; N], V> {
    let wrong = || V::rig_error(format!("{what} must be {N} numbers, got {}", v.describe()));
    let list = v.items(what, N).map_err(|_| wrong())?;
    if list.len() != N {
        return Err(wrong());
    }
    let mut out = [0.0; N];
    for (i, (o, x)) in out.iter_mut().zip(&list).enumerate() {
        *o = x.number(&format!("{what}[{i}]"))?;
    }
    Ok(out)
}

/// Fails on a key of `map` that is not in `known` and does not start with '_' (a comment).
pub(crate) fn check_keys<V: MapValue>(
    map: &V,
    what: &str,
    known: &[&str],
    usage: &str,
) -> Read<(), V> {
    for name in map.keys(what)? {
        if !(name.starts_with('_') || known.contains(&name.as_str())) {
            return Err(V::rig_error(format!(
                "{what} has an unknown key {} ({usage}; keys starting with '_' are comments)",
                short(&name)
            )));
        }
    }
    Ok(())
}

/// The value of `key`; missing is an error naming the key.
fn required<V: MapValue>(map: &V, what: &str, key: &str) -> Read<V, V> {
    map.get(key)?
        .ok_or_else(|| V::rig_error(format!("{what} is missing the key {key:?}")))
}

/// The distortion coefficients of a flat list or of OpenCV's 1 x n or n x 1 matrix (at most 14),
/// as (k1, k2, p1, p2, k3) (see [`Camera::distortion_from`]); null is none.
fn distortion<V: MapValue>(v: &V) -> Read<[f64; 5], V> {
    const WHAT: &str = "camera.distortion";
    if v.is_null() {
        return Ok([0.0; 5]);
    }
    let outer = v.items(WHAT, 14)?;
    let flat = if !outer.is_empty() && outer.iter().all(MapValue::is_list) {
        if outer.len() == 1 {
            outer[0].items(WHAT, 14)?
        } else {
            let mut column = Vec::with_capacity(outer.len());
            for row in &outer {
                let row = row.items(WHAT, 14)?;
                if row.len() != 1 {
                    return Err(V::rig_error(format!(
                        "{WHAT} must be a list of numbers or OpenCV's 1 x n or n x 1 matrix, \
                         got a {} x {} matrix",
                        outer.len(),
                        row.len()
                    )));
                }
                column.extend(row);
            }
            column
        }
    } else {
        outer
    };
    let mut c = Vec::with_capacity(flat.len());
    for (i, x) in flat.iter().enumerate() {
        c.push(x.number(&format!("{WHAT}[{i}]"))?);
    }
    Camera::distortion_from(&c).map_err(V::core_error)
}

/// Reads and validates the camera mapping `camera` of a rig file.
///
/// The mapping has `model` = "orthographic" with `pixel_size` (w, h) and `origin` (x, y), or
/// "pinhole" with `K` (3 x 3) and an optional `distortion` (a flat list or OpenCV's 1 x n or
/// n x 1 matrix; see [`Camera::distortion_from`]; null or absent is none). Every value is
/// checked for its type and shape; a key that is not part of the model's form is an error
/// naming it, except keys starting with `_` (comments). Every problem is a rig error
/// ([`MapValue::rig_error`]) naming the key (`camera.distortion[2] must be a finite number, got
/// NaN`). The one implementation of these rules, for the rig file reader (over JSON values) and
/// the Python bindings (over Python objects).
pub fn camera_from_map<V: MapValue>(camera: &V) -> Read<Camera, V> {
    let model = required(camera, "camera", "model")?;
    let Some(model) = model.string() else {
        return Err(V::rig_error(format!(
            "camera.model must be a string, got {}",
            model.describe()
        )));
    };
    let cam = match model.as_str() {
        "orthographic" => {
            check_keys(
                camera,
                "camera",
                &["model", "pixel_size", "origin"],
                "an orthographic camera has model, pixel_size and origin",
            )?;
            Camera::Orthographic {
                pixel_size: numbers(
                    &required(camera, "camera", "pixel_size")?,
                    "camera.pixel_size",
                )?,
                origin: numbers(&required(camera, "camera", "origin")?, "camera.origin")?,
            }
        }
        "pinhole" => {
            check_keys(
                camera,
                "camera",
                &["model", "K", "distortion"],
                "a pinhole camera has model, K and distortion",
            )?;
            let matrix = required(camera, "camera", "K")?;
            let wrong = || {
                V::rig_error(format!(
                    "camera.K must be a 3 x 3 matrix, got {}",
                    matrix.describe()
                ))
            };
            let rows = matrix.items("camera.K", 3).map_err(|_| wrong())?;
            if rows.len() != 3 {
                return Err(wrong());
            }
            let mut k = [[0.0; 3]; 3];
            for (i, row) in rows.iter().enumerate() {
                k[i] = numbers(row, &format!("camera.K[{i}]"))?;
            }
            let d = match camera.get("distortion")? {
                Some(v) => distortion(&v)?,
                None => [0.0; 5],
            };
            Camera::Pinhole { k, distortion: d }
        }
        _ => {
            return Err(V::rig_error(format!(
                "unknown camera model {}; supported: \"orthographic\", \"pinhole\"",
                short(&model)
            )))
        }
    };
    cam.validate().map_err(V::core_error)?;
    Ok(cam)
}
