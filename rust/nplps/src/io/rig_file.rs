//! The rig file (JSON), read strictly; the format is described in [`crate::io`].

use std::path::Path;

use serde_json::Value;

use crate::camera_map::{camera_from_map, check_keys, short, MapValue};
use crate::error::{g6, Error, Result};
use crate::rig::{Light, Rig, MAX_LIGHTS};

/// Largest rig file read (bytes).
pub const MAX_RIG_FILE_BYTES: usize = 16 << 20;

/// Deepest nesting of arrays and objects in a rig file.
pub const MAX_NESTING: usize = 64;

/// The newest rig file version (files of version 1 to this one are read).
pub const RIG_FILE_VERSION: i64 = 3;

fn rig_error(message: String) -> Error {
    Error::Rig(message)
}

/// Reads the rig file at `path` (see the format in the [`io`](crate::io) module).
pub fn read_rig(path: &Path) -> Result<Rig> {
    let name = path.display().to_string();
    let raw = read_limited(path).map_err(|e| {
        rig_error(format!(
            "cannot read rig file '{name}': {}",
            match e.kind() {
                std::io::ErrorKind::NotFound => "No such file or directory".to_string(),
                _ => e.to_string(),
            }
        ))
    })?;
    if raw.len() > MAX_RIG_FILE_BYTES {
        return Err(rig_error(format!(
            "rig file '{name}' is larger than {} MiB: not a rig file",
            MAX_RIG_FILE_BYTES >> 20
        )));
    }
    let text = std::str::from_utf8(&raw).map_err(|_| {
        rig_error(format!(
            "rig file '{name}' is not a JSON text file (not UTF-8)"
        ))
    })?;
    parse_rig(text.strip_prefix('\u{feff}').unwrap_or(text), &name)
}

/// At most [`MAX_RIG_FILE_BYTES`] + 1 bytes of the file.
fn read_limited(path: &Path) -> std::io::Result<Vec<u8>> {
    use std::io::Read;
    let mut raw = Vec::new();
    std::fs::File::open(path)?
        .take(MAX_RIG_FILE_BYTES as u64 + 1)
        .read_to_end(&mut raw)?;
    Ok(raw)
}

/// Reads the JSON text of a rig file; `source` names it in the messages.
pub fn parse_rig(text: &str, source: &str) -> Result<Rig> {
    let depth = nesting(text);
    if depth > MAX_NESTING {
        return Err(rig_error(format!(
            "rig file '{source}' is nested too deeply ({depth} levels; at most {MAX_NESTING})"
        )));
    }
    let value: Value = serde_json::from_str(text).map_err(|e| {
        let message = e.to_string();
        let message = if message.chars().count() <= 200 {
            message
        } else {
            format!("{}...", message.chars().take(200).collect::<String>())
        };
        rig_error(format!("rig file '{source}' is not valid JSON: {message}"))
    })?;
    rig_from_value(&value, source)
}

/// The deepest nesting of arrays and objects in a JSON text (brackets in strings left out).
fn nesting(text: &str) -> usize {
    let (mut depth, mut deepest, mut in_string, mut escaped) = (0usize, 0usize, false, false);
    for b in text.bytes() {
        if in_string {
            match (escaped, b) {
                (true, _) => escaped = false,
                (false, b'\\') => escaped = true,
                (false, b'"') => in_string = false,
                _ => {}
            }
            continue;
        }
        match b {
            b'"' => in_string = true,
            b'[' | b'{' => {
                depth += 1;
                deepest = deepest.max(depth);
            }
            b']' | b'}' => depth = depth.saturating_sub(1),
            _ => {}
        }
    }
    deepest
}

/// A short description of a JSON value for messages (the words of the Python reader).
fn describe(v: &Value) -> String {
    match v {
        Value::Null => "null".to_string(),
        Value::Bool(b) => format!("the boolean {b}"),
        Value::String(s) => format!("the string {}", short(s)),
        Value::Array(a) => format!(
            "a list of {} item{}",
            a.len(),
            if a.len() == 1 { "" } else { "s" }
        ),
        Value::Object(_) => "an object (mapping)".to_string(),
        Value::Number(n) => n.as_f64().map_or_else(|| n.to_string(), g6),
    }
}

/// A finite number.
fn number(v: &Value, what: &str) -> Result<f64> {
    let Some(x) = v.as_f64() else {
        return Err(rig_error(format!(
            "{what} must be a number, got {}",
            describe(v)
        )));
    };
    if !x.is_finite() {
        return Err(rig_error(format!(
            "{what} must be a finite number, got {}",
            g6(x)
        )));
    }
    Ok(x)
}

/// Exactly `N` finite numbers.
fn numbers<const N: usize>(v: &Value, what: &str) -> Result<[f64; N]> {
    match v.as_array() {
        Some(items) if items.len() == N => {
            let mut out = [0.0; N];
            for (i, (o, x)) in out.iter_mut().zip(items).enumerate() {
                *o = number(x, &format!("{what}[{i}]"))?;
            }
            Ok(out)
        }
        _ => Err(rig_error(format!(
            "{what} must be {N} numbers, got {}",
            describe(v)
        ))),
    }
}

impl MapValue for Value {
    type Error = Error;

    fn rig_error(message: String) -> Error {
        Error::Rig(message)
    }

    fn core_error(error: Error) -> Error {
        error
    }

    fn describe(&self) -> String {
        describe(self)
    }

    fn number(&self, what: &str) -> Result<f64> {
        number(self, what)
    }

    fn items(&self, what: &str, max: usize) -> Result<Vec<Value>> {
        match self.as_array() {
            Some(items) if items.len() <= max => Ok(items.clone()),
            Some(items) => Err(rig_error(format!(
                "{what} has {} items; at most {max} are allowed",
                items.len()
            ))),
            None => Err(rig_error(format!(
                "{what} must be a list, got {}",
                describe(self)
            ))),
        }
    }

    fn is_list(&self) -> bool {
        self.is_array()
    }

    fn is_null(&self) -> bool {
        self.is_null()
    }

    fn string(&self) -> Option<String> {
        self.as_str().map(str::to_string)
    }

    fn keys(&self, what: &str) -> Result<Vec<String>> {
        match self.as_object() {
            Some(map) => Ok(map.keys().cloned().collect()),
            None => Err(rig_error(format!(
                "{what} must be an object, got {}",
                describe(self)
            ))),
        }
    }

    fn get(&self, key: &str) -> Result<Option<Value>> {
        Ok(self.as_object().and_then(|map| map.get(key)).cloned())
    }
}

/// One light's intensity: a number, or three (R, G, B).
fn intensity(v: &Value, what: &str) -> Result<[f64; 3]> {
    if v.is_array() {
        numbers(v, what)
    } else {
        let x = number(v, what)?;
        Ok([x; 3])
    }
}

/// Checks a rig file's `"grid"`: `{"image_size": [W, H], "binning": n}`, whole numbers >= 1
/// (both optional). It says which images the camera belongs to; the native [`Rig`] does not keep
/// it (the Python package checks images against it).
fn check_grid(grid: &Value, place: &str) -> Result<()> {
    let Some(map) = grid.as_object() else {
        return Err(rig_error(format!(
            "{place} must be an object with image_size [W, H] and binning, got {}",
            describe(grid)
        )));
    };
    check_keys(
        grid,
        place,
        &["image_size", "binning"],
        "a grid has image_size [W, H] and binning",
    )?;
    let whole = |v: &Value, name: &str| -> Result<()> {
        match v.as_u64() {
            Some(n) if (1..=1u64 << 31).contains(&n) => Ok(()),
            _ => Err(rig_error(format!(
                "{place} {name} must be a whole number of at least 1, got {}",
                describe(v)
            ))),
        }
    };
    if let Some(size) = map.get("image_size") {
        match size.as_array() {
            Some(wh) if wh.len() == 2 => {
                whole(&wh[0], "image_size width")?;
                whole(&wh[1], "image_size height")?;
            }
            _ => {
                return Err(rig_error(format!(
                    "{place} image_size must be [width, height] in pixels, got {}",
                    describe(size)
                )))
            }
        }
    }
    if let Some(b) = map.get("binning") {
        whole(b, "binning")?;
    }
    Ok(())
}

/// The rig of a rig file's JSON value; `source` names the file in the messages.
pub(crate) fn rig_from_value(data: &Value, source: &str) -> Result<Rig> {
    let Some(top) = data.as_object() else {
        return Err(rig_error(format!(
            "{source}: a rig file holds a JSON object, got {}",
            describe(data)
        )));
    };
    const TOP: [&str; 4] = ["version", "camera", "lights", "grid"];
    check_keys(
        data,
        source,
        &TOP,
        "a rig file has version, camera, lights and optionally grid",
    )?;
    let missing: Vec<&str> = TOP[..3]
        .iter()
        .copied()
        .filter(|k| !top.contains_key(*k))
        .collect();
    if !missing.is_empty() {
        return Err(rig_error(format!(
            "{source}: missing key(s) {}",
            missing.join(", ")
        )));
    }
    let version = &top["version"];
    let Some(v) = version.as_i64() else {
        return Err(rig_error(format!(
            "{source}: 'version' must be an integer, got {}",
            describe(version)
        )));
    };
    if !(1..=RIG_FILE_VERSION).contains(&v) {
        return Err(rig_error(format!(
            "{source}: unsupported rig file version {v} (this nplps reads 1..{RIG_FILE_VERSION})"
        )));
    }
    if let Some(grid) = top.get("grid") {
        check_grid(grid, &format!("{source}: grid"))?;
    }
    let camera = &top["camera"];
    match camera.as_object() {
        Some(c) if c.contains_key("model") => {}
        _ => {
            return Err(rig_error(format!(
                "{source}: 'camera' must be an object with a 'model' key, got {}",
                describe(camera)
            )))
        }
    }
    let Some(lights) = top["lights"].as_array() else {
        return Err(rig_error(format!(
            "{source}: 'lights' must be a list of objects (one per light), got {}",
            describe(&top["lights"])
        )));
    };
    if lights.len() > MAX_LIGHTS {
        return Err(rig_error(format!(
            "{source}: the rig has {} lights; at most {MAX_LIGHTS} are supported",
            lights.len()
        )));
    }
    let lights = lights
        .iter()
        .enumerate()
        .map(|(i, light)| light_from(light, &format!("{source}: light {i}")))
        .collect::<Result<Vec<Light>>>()?;
    let prefixed = |e: Error| match e {
        Error::Rig(message) => rig_error(format!("{source}: {message}")),
        other => other,
    };
    let rig = Rig {
        camera: camera_from_map(camera).map_err(prefixed)?,
        lights,
    };
    rig.validate_parameters().map_err(prefixed)?;
    Ok(rig)
}

/// One light of a rig file.
fn light_from(value: &Value, place: &str) -> Result<Light> {
    let Some(light) = value.as_object() else {
        return Err(rig_error(format!(
            "{place} must be an object, got {}",
            describe(value)
        )));
    };
    let kind = light.get("type").map_or(Some("point"), Value::as_str);
    let (kind, known): (&str, &[&str]) = match kind {
        Some("point") => (
            "point",
            &["type", "position", "intensity", "direction", "mu"],
        ),
        Some("directional") => ("directional", &["type", "direction", "intensity"]),
        _ => {
            return Err(rig_error(format!(
                "{place} has unknown type {} (\"point\" or \"directional\")",
                describe(&light["type"])
            )))
        }
    };
    check_keys(
        value,
        place,
        known,
        &format!("a {kind} light has {}", known.join(", ")),
    )?;
    let key = if kind == "point" {
        "position"
    } else {
        "direction"
    };
    let Some(vector) = light.get(key) else {
        return Err(rig_error(format!("{place} is missing its '{key}'")));
    };
    let vector = numbers::<3>(vector, &format!("{place} {key}"))?;
    let phi = match light.get("intensity") {
        Some(v) => intensity(v, &format!("{place} intensity"))?,
        None => [1.0; 3],
    };
    if kind == "directional" {
        return Ok(Light::Directional {
            direction: vector,
            intensity: phi,
        });
    }
    let axis = light
        .get("direction")
        .map(|a| numbers::<3>(a, &format!("{place} direction")))
        .transpose()?;
    let mu = match light.get("mu") {
        Some(v) => number(v, &format!("{place} mu"))?,
        None => 0.0,
    };
    if mu > 0.0 && axis.is_none() {
        // An LED's falloff about its axis: without the axis its brightness is unknown.
        return Err(rig_error(format!(
            "{place}: an anisotropic LED (mu = {}) needs its principal 'direction'",
            g6(mu)
        )));
    }
    Ok(Light::Point {
        position: vector,
        intensity: phi,
        axis: axis.unwrap_or([0.0; 3]),
        mu,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::Camera;

    const ORTHO: &str = r#"{"version": 2, "_comment": "bench rig",
        "camera": {"model": "orthographic", "pixel_size": [0.2, 0.2], "origin": [-50, -50]},
        "lights": [{"type": "point", "position": [30, -10, -50], "intensity": 1.0},
                   {"position": [-25, 20, -40], "intensity": [1, 0.9, 0.8],
                    "direction": [0, 0, 1], "mu": 1.0},
                   {"type": "directional", "direction": [0.0, -0.6, -0.8], "intensity": 0.7}]}"#;

    #[test]
    fn reads_a_version_3_file_with_its_grid() {
        let v3 = ORTHO.replace(
            "\"version\": 2,",
            "\"version\": 3, \"grid\": {\"image_size\": [640, 480], \"binning\": 4},",
        );
        assert_eq!(parse_rig(&v3, "rig.json").unwrap().n_lights(), 3);
        for (grid, message) in [
            ("[640, 480]", "grid must be an object"),
            (
                "{\"image_size\": [640]}",
                "image_size must be [width, height]",
            ),
            (
                "{\"image_size\": [640, 0]}",
                "image_size height must be a whole number",
            ),
            ("{\"binning\": 1.5}", "binning must be a whole number"),
            ("{\"size\": 1}", "unknown key"),
        ] {
            let text = ORTHO.replace(
                "\"version\": 2,",
                &format!("\"version\": 3, \"grid\": {grid},"),
            );
            let error = parse_rig(&text, "rig.json").unwrap_err().to_string();
            assert!(error.contains(message), "{grid}: {error}");
        }
    }

    #[test]
    fn reads_a_version_2_file() {
        let rig = parse_rig(ORTHO, "rig.json").unwrap();
        assert_eq!(rig.n_lights(), 3);
        assert_eq!(
            rig.camera,
            Camera::Orthographic {
                pixel_size: [0.2, 0.2],
                origin: [-50.0, -50.0]
            }
        );
        assert!(
            matches!(rig.lights[1], Light::Point { mu, axis, .. } if mu == 1.0 && axis == [0.0, 0.0, 1.0])
        );
        assert!(matches!(rig.lights[2], Light::Directional { .. }));
    }

    #[test]
    fn refuses_what_is_not_the_format() {
        let cases = [
            (
                ORTHO.replace("\"intensity\": 1.0", "\"intensities\": 1.0"),
                "unknown key \"intensities\"",
            ),
            (
                ORTHO.replace("\"version\": 2", "\"version\": 4"),
                "unsupported rig file version 4",
            ),
            (
                ORTHO.replace("[0.2, 0.2]", "[0.2, true]"),
                "camera.pixel_size[1] must be a number, got the boolean true",
            ),
            (
                ORTHO.replace("\"mu\": 1.0", "\"mu\": \"1\""),
                "light 1 mu must be a number",
            ),
            (
                ORTHO.replace("\"model\": \"orthographic\"", "\"model\": \"fisheye\""),
                "unknown camera model \"fisheye\"",
            ),
            (
                format!("{}{}{}", "[".repeat(70), "1", "]".repeat(70)),
                "nested too deeply (70 levels; at most 64)",
            ),
        ];
        for (text, expected) in cases {
            let message = parse_rig(&text, "rig.json").unwrap_err().to_string();
            assert!(message.contains(expected), "{message}");
        }
    }

    #[test]
    fn distortion_forms() {
        let pinhole = |d: &str| {
            format!(
                r#"{{"version": 2, "camera": {{"model": "pinhole", "K": [[500, 0, 32], [0, 500, 24], [0, 0, 1]], "distortion": {d}}},
                "lights": [{{"position": [0, 0, -10]}}]}}"#
            )
        };
        let k = |text: String| match parse_rig(&text, "r").unwrap().camera {
            Camera::Pinhole { distortion, .. } => distortion,
            other => panic!("{other:?}"),
        };
        assert_eq!(
            k(pinhole("[[0.1, 0.2, 0, 0, 0.3]]")),
            [0.1, 0.2, 0.0, 0.0, 0.3]
        );
        assert_eq!(k(pinhole("[[0.1], [0.2]]")), [0.1, 0.2, 0.0, 0.0, 0.0]);
        assert_eq!(k(pinhole("null")), [0.0; 5]);
        let three = parse_rig(&pinhole("[0.1, 0.2, 0.3]"), "r").unwrap_err();
        assert!(three
            .to_string()
            .starts_with("r: camera.distortion has 3 coefficients"));
    }
}
