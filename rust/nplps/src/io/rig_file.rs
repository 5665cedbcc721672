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
    read_rig_file(path).map(|file| file.rig)
}

/// Reads the JSON text of a rig file; `source` names it in the messages.
pub fn parse_rig(text: &str, source: &str) -> Result<Rig> {
    parse_rig_file(text, source).map(|file| file.rig)
}

/// The image grid a rig file's camera belongs to (its optional `"grid"`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RigGrid {
    /// Width and height of the images in pixels, if the file says.
    pub image_size: Option<[u64; 2]>,
    /// Pixels of the original calibration grid one pixel averages along each axis (default 1).
    pub binning: u64,
}

/// A rig file as read: the rig, and what the file says besides it.
#[derive(Debug, Clone, PartialEq)]
pub struct RigFile {
    /// The rig (LED axes scaled to unit length, directional directions as written).
    pub rig: Rig,
    /// Per light, whether it is an LED: a point light with a principal `"direction"`, even with
    /// `mu` = 0 (the Python package keeps such a light an LED).
    pub leds: Vec<bool>,
    /// The file's `"grid"`, if it has one.
    pub grid: Option<RigGrid>,
    /// The top-level comments (keys starting with `_`), in the order of the file.
    pub comments: Vec<(String, Value)>,
}

impl Rig {
    /// Reads the rig file at `path` with its grid, LED flags and comments (see [`read_rig`]).
    pub fn read_file(path: &Path) -> Result<RigFile> {
        read_rig_file(path)
    }

    /// Reads the JSON text of a rig file with its grid, LED flags and comments (see
    /// [`parse_rig`]); `source` names it in the messages.
    pub fn parse_file(text: &str, source: &str) -> Result<RigFile> {
        parse_rig_file(text, source)
    }
}

/// The message of an I/O error without Rust's " (os error N)" suffix (the words of `strerror`).
fn io_message(e: &std::io::Error) -> String {
    let text = e.to_string();
    match text.rfind(" (os error ") {
        Some(i) if text.ends_with(')') => text[..i].to_string(),
        _ => text,
    }
}

fn read_rig_file(path: &Path) -> Result<RigFile> {
    let name = path.display().to_string();
    let raw = read_limited(path).map_err(|e| {
        rig_error(format!(
            "cannot read rig file '{name}': {}",
            match e.kind() {
                std::io::ErrorKind::NotFound => "No such file or directory".to_string(),
                _ => io_message(&e),
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
    parse_rig_file(text.strip_prefix('\u{feff}').unwrap_or(text), &name)
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

fn parse_rig_file(text: &str, source: &str) -> Result<RigFile> {
    let depth = nesting(text);
    if depth > MAX_NESTING {
        return Err(rig_error(format!(
            "rig file '{source}' is nested too deeply ({depth} levels; at most {MAX_NESTING})"
        )));
    }
    let value: Value = match serde_json::from_str(text) {
        Ok(value) => value,
        // NaN, infinities and numbers beyond a double (which Python's json reads) become marks
        // that the number readers name as non-finite, naming the key.
        Err(e) => match with_non_finite_marked(text).and_then(|t| serde_json::from_str(&t).ok()) {
            Some(value) => value,
            None => {
                let message = e.to_string();
                let message = if message.chars().count() <= 200 {
                    message
                } else {
                    format!("{}...", message.chars().take(200).collect::<String>())
                };
                return Err(rig_error(format!(
                    "rig file '{source}' is not valid JSON: {message}"
                )));
            }
        },
    };
    let mut file = rig_from_value(&value, source)?;
    if file.comments.len() > 1 {
        // `Value`'s objects are sorted by key: the file's order comes from its text.
        let keys = top_level_keys(text);
        file.comments
            .sort_by_key(|(k, _)| keys.iter().position(|o| o == k));
    }
    Ok(file)
}

/// The top-level keys of the JSON object `text` (valid JSON) in the order of the text, each
/// where it first appears (as Python's `json.loads` orders them).
fn top_level_keys(text: &str) -> Vec<String> {
    let bytes = text.as_bytes();
    let (mut keys, mut depth, mut i) = (Vec::<String>::new(), 0usize, 0usize);
    while i < bytes.len() {
        match bytes[i] {
            b'"' => {
                let start = i;
                i += 1;
                while i < bytes.len() && bytes[i] != b'"' {
                    i += if bytes[i] == b'\\' { 2 } else { 1 };
                }
                let end = (i + 1).min(bytes.len());
                let rest = text[end..].trim_start();
                if depth == 1 && rest.starts_with(':') {
                    if let Ok(key) = serde_json::from_str::<String>(&text[start..end]) {
                        if !keys.contains(&key) {
                            keys.push(key);
                        }
                    }
                }
            }
            b'[' | b'{' => depth += 1,
            b']' | b'}' => depth = depth.saturating_sub(1),
            _ => {}
        }
        i += 1;
    }
    keys
}

/// The start of a string that stands for a number JSON cannot hold (see [`non_finite`]).
const MARK: &str = "\u{0}nplps-non-finite:";

/// `text` with its tokens `NaN`, `Infinity`, `-Infinity` and numbers beyond a double replaced
/// by marked strings (`MARK` + `NaN`, `inf`, `-inf` or `integer`), or None when it has none.
fn with_non_finite_marked(text: &str) -> Option<String> {
    let bytes = text.as_bytes();
    let (mut out, mut i, mut last, mut marked) = (String::new(), 0usize, 0usize, false);
    let mark = |out: &mut String, what: &str| {
        out.push('"');
        out.push_str(&MARK.replace('\u{0}', "\\u0000"));
        out.push_str(what);
        out.push('"');
    };
    while i < bytes.len() {
        let b = bytes[i];
        if b == b'"' {
            i += 1;
            while i < bytes.len() && bytes[i] != b'"' {
                i += if bytes[i] == b'\\' { 2 } else { 1 };
            }
            i += 1;
            continue;
        }
        let rest = &text[i..];
        let word = ["-Infinity", "Infinity", "NaN"]
            .into_iter()
            .find(|w| rest.starts_with(w));
        if let Some(w) = word {
            out.push_str(&text[last..i]);
            mark(
                &mut out,
                if w == "NaN" {
                    "NaN"
                } else if w.starts_with('-') {
                    "-inf"
                } else {
                    "inf"
                },
            );
            i += w.len();
            last = i;
            marked = true;
            continue;
        }
        if b == b'-' || b.is_ascii_digit() {
            let end = rest
                .find(|c: char| !(c.is_ascii_digit() || "+-.eE".contains(c)))
                .map_or(bytes.len(), |n| i + n);
            let token = &text[i..end];
            if token.parse::<f64>().is_ok_and(|x| x.is_infinite()) {
                out.push_str(&text[last..i]);
                let integer = !token.contains(['.', 'e', 'E']);
                let sign = if token.starts_with('-') { "-" } else { "" };
                mark(
                    &mut out,
                    &if integer {
                        "integer".to_string()
                    } else {
                        format!("{sign}inf")
                    },
                );
                last = end;
                marked = true;
            }
            i = end.max(i + 1);
            continue;
        }
        i += 1;
    }
    out.push_str(&text[last..]);
    marked.then_some(out)
}

/// What a marked string of [`with_non_finite_marked`] stands for: `NaN`, `inf`, `-inf` or
/// `integer` (an integer too large for a double).
fn non_finite(v: &Value) -> Option<&str> {
    v.as_str().and_then(|s| s.strip_prefix(MARK))
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
    if let Some(what) = non_finite(v) {
        return match what {
            "integer" => "an integer too large for a floating-point number".to_string(),
            other => other.to_string(),
        };
    }
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
    match non_finite(v) {
        Some("integer") => {
            return Err(rig_error(format!(
                "{what} is an integer too large for a floating-point number"
            )))
        }
        Some(x) => {
            return Err(rig_error(format!(
                "{what} must be a finite number, got {x}"
            )))
        }
        None => {}
    }
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

/// Reads a rig file's `"grid"`: `{"image_size": [W, H], "binning": n}`, whole numbers >= 1
/// (both optional). It says which images the camera belongs to; the native [`Rig`] does not keep
/// it (the Python package checks images against it).
fn read_grid(grid: &Value, place: &str) -> Result<RigGrid> {
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
    let whole = |v: &Value, name: &str| -> Result<u64> {
        match v.as_u64() {
            Some(n) if (1..=1u64 << 31).contains(&n) => Ok(n),
            _ => Err(rig_error(format!(
                "{place} {name} must be a whole number of at least 1, got {}",
                describe(v)
            ))),
        }
    };
    let mut out = RigGrid {
        image_size: None,
        binning: 1,
    };
    if let Some(size) = map.get("image_size") {
        match size.as_array() {
            Some(wh) if wh.len() == 2 => {
                out.image_size = Some([
                    whole(&wh[0], "image_size width")?,
                    whole(&wh[1], "image_size height")?,
                ]);
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
        out.binning = whole(b, "binning")?;
    }
    Ok(out)
}

/// The rig of a rig file's JSON value; `source` names the file in the messages.
fn rig_from_value(data: &Value, source: &str) -> Result<RigFile> {
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
    let grid = top
        .get("grid")
        .map(|grid| read_grid(grid, &format!("{source}: grid")))
        .transpose()?;
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
    let (lights, leds): (Vec<Light>, Vec<bool>) = lights
        .iter()
        .enumerate()
        .map(|(i, light)| light_from(light, &format!("{source}: light {i}")))
        .collect::<Result<Vec<(Light, bool)>>>()?
        .into_iter()
        .unzip();
    let prefixed = |e: Error| match e {
        Error::Rig(message) => rig_error(format!("{source}: {message}")),
        other => other,
    };
    let rig = Rig {
        camera: camera_from_map(camera).map_err(prefixed)?,
        lights,
    };
    rig.validate_parameters().map_err(prefixed)?;
    let comments = top
        .iter()
        .filter(|(k, _)| k.starts_with('_'))
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect();
    Ok(RigFile {
        rig,
        leds,
        grid,
        comments,
    })
}

/// `v` scaled to unit length (by its largest component first, so that the norm of a huge vector
/// does not overflow), by the operations of the Python package (the same bits); zero stays zero.
pub(crate) fn unit_axis(v: [f64; 3]) -> [f64; 3] {
    let largest = v.iter().fold(0.0f64, |m, x| m.max(x.abs())).max(1e-300);
    let a = v.map(|x| x / largest);
    let n = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    if n.is_nan() || n <= 0.0 {
        return [0.0; 3];
    }
    a.map(|x| x / n)
}

/// One light of a rig file, and whether it is an LED (a point light with a principal direction).
fn light_from(value: &Value, place: &str) -> Result<(Light, bool)> {
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
        // Kept as written (checked to be a unit vector): a file reads back as it was saved.
        let length = vector.iter().map(|x| x * x).sum::<f64>().sqrt();
        if length.is_nan() || (length - 1.0).abs() > 1e-6 {
            return Err(rig_error(format!(
                "{place}: a directional light needs a unit direction (from the surface towards \
                 the light), got [{}]",
                vector.map(g6).join(", ")
            )));
        }
        let light = Light::Directional {
            direction: vector,
            intensity: phi,
        };
        return Ok((light, false));
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
    if mu < 0.0 {
        return Err(rig_error(format!(
            "{place} has anisotropy mu = {}; it must be >= 0",
            g6(mu)
        )));
    }
    // An LED's axis is scaled to unit length; a zero axis stands for +z where it is unused.
    let axis = match axis.map(unit_axis) {
        Some([0.0, 0.0, 0.0]) if mu > 0.0 => {
            return Err(rig_error(format!(
                "{place}: an anisotropic LED (mu = {}) needs a non-zero axis",
                g6(mu)
            )))
        }
        Some([0.0, 0.0, 0.0]) | None => [0.0, 0.0, 1.0],
        Some(a) => a,
    };
    let led = light.contains_key("direction");
    let light = Light::Point {
        position: vector,
        intensity: phi,
        axis,
        mu,
    };
    Ok((light, led))
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
