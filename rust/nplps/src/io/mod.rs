//! Files of a native application (cargo feature `io`, on by default): the rig file (JSON,
//! [`read_rig`]) and PNG images ([`read_png`], [`read_pngs`], [`write_png`], [`write_pngs`]; 8
//! and 16 bits, grey or colour).
//! The Python bindings decode PNG files with this code, and read camera mappings by the same
//! rules as the rig file reader ([`crate::camera_from_map`]).
//!
//! ## The rig file
//!
//! JSON, read strictly: versions 1 and 2, the format of `python/nplps/rig.py`.
//!
//! ```json
//! {"version": 2,
//!  "camera": {"model": "orthographic", "pixel_size": [0.2, 0.2], "origin": [-50.0, -50.0]},
//!  "lights": [{"type": "point", "position": [30.0, -10.0, 50.0], "intensity": 1.0},
//!             {"type": "point", "position": [0.0, -30.0, 60.0], "intensity": [1.0, 0.9, 0.8],
//!              "direction": [0.0, 0.4, 0.9], "mu": 1.0},
//!             {"type": "directional", "direction": [0.0, -0.6, -0.8], "intensity": 0.7}]}
//! ```
//!
//! A pinhole camera is `{"model": "pinhole", "K": [[fx, s, cx], [0, fy, cy], [0, 0, 1]],
//! "distortion": [k1, k2, p1, p2, k3]}` (K in the 0-based pixel-centre convention; OpenCV's
//! distortion, also as its 1 x n or n x 1 matrix; see [`Camera::distortion_from`](crate::Camera::distortion_from)). A point
//! light at `position` p with `intensity` Φ (a number, or R, G, B), principal `direction` d and
//! anisotropy `mu` lights a surface point x with normal n as
//! `I = ρ Φ ((x − p)·d / |x − p|)^mu max(0, n·(p − x)) / |p − x|³`; a directional light with unit
//! `direction` l as `I = ρ Φ max(0, n·l)`.
//!
//! Every value must have its type and shape: numbers are JSON numbers (never booleans, strings
//! or null) and finite; a key that is not part of the format is an error naming it, except keys
//! starting with `_`, which are comments at every level. A file is at most [`MAX_RIG_FILE_BYTES`]
//! of UTF-8 (a byte order mark is allowed), nested at most [`MAX_NESTING`] levels, with at most
//! [`MAX_LIGHTS`](crate::MAX_LIGHTS) lights. Every problem is an
//! [`Error::Rig`](crate::Error::Rig) whose message names the file and the key, in the words of
//! the Python reader.

mod png;
mod rig_file;

pub use self::png::{
    read_png, read_pngs, write_png, write_pngs, Decoded, Image, Pixels, PngCompression, PngFilter,
    PngOptions, Samples,
};
pub use self::rig_file::{
    parse_rig, read_rig, RigFile, RigGrid, MAX_NESTING, MAX_RIG_FILE_BYTES, RIG_FILE_VERSION,
};
