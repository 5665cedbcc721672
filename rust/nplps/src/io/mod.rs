//! Files of a native application (cargo feature `io`, on by default): the rig file (JSON,
//! [`read_rig`]) and PNG images ([`read_png`], [`read_pngs`]; 8 and 16 bits, grey or colour).
//! The Python bindings decode PNG files with this code, and share the camera distortion rule
//! ([`crate::Camera::distortion_from`]) with the rig file reader.

mod png;
mod rig_file;

pub use self::png::{read_png, read_pngs, Decoded, Pixels};
pub use self::rig_file::{parse_rig, read_rig, MAX_NESTING, MAX_RIG_FILE_BYTES, RIG_FILE_VERSION};
