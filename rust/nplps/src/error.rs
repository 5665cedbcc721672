//! Typed errors of the crate.

use thiserror::Error;

/// Everything that can go wrong in nplps, with a message that names the problem.
///
/// The input errors carry what they are about (which array, which value, which parameter) as
/// fields, and the full message that [`Display`](std::fmt::Display) prints as `message`.
#[derive(Debug, Error, Clone, PartialEq)]
#[non_exhaustive]
pub enum Error {
    /// An array or buffer does not have the number of values (or channels) it must have.
    #[error("{message}")]
    Shape {
        /// Which array ("images", "mask", "depth map", ...).
        what: &'static str,
        /// The number it must have (of values, pixels or channels, as the message says).
        expected: usize,
        /// The number it has.
        got: usize,
        /// The message.
        message: String,
    },
    /// A value that must be finite (or in the valid range of its array) is not.
    #[error("{message}")]
    NonFinite {
        /// Which array ("images", "initial depth map", ...).
        what: &'static str,
        /// The index of the first bad value in the array (row-major).
        index: usize,
        /// The message.
        message: String,
    },
    /// A numeric parameter is outside its valid range (the message gives the range).
    #[error("{message}")]
    OutOfRange {
        /// The parameter ("tol", "max_memory", "working distance", ...).
        name: &'static str,
        /// Its value.
        value: f64,
        /// The message.
        message: String,
    },
    /// The input is well-formed but cannot support the computation: an empty mask, too few
    /// usable observations or lights, an unknown name, no sphere found in calibration images,
    /// a degenerate fit.
    #[error("{0}")]
    Unusable(String),
    /// An image file cannot be read: missing, not a valid image, or above the pixel limit.
    #[error("cannot read image '{}': {reason}", path.display())]
    Image {
        /// The file.
        path: std::path::PathBuf,
        /// Why it cannot be read.
        reason: String,
    },
    /// An image file cannot be written: its directory is missing, the disk is full, or the
    /// image is not one a PNG file can hold.
    #[error("cannot write image '{}': {reason}", path.display())]
    ImageWrite {
        /// The file.
        path: std::path::PathBuf,
        /// The operating system's error number, when the system refused the write.
        os_error: Option<i32>,
        /// Why it cannot be written.
        reason: String,
    },
    /// The rig (camera or lights) is invalid.
    #[error("{0}")]
    Rig(String),
    /// The sparse factorization or solve failed.
    #[error("solver failed: {0}")]
    Solver(String),
    /// The computation would need more memory than the limit allows (checked before the large
    /// allocations; see [`crate::check_memory`]), or a large allocation failed.
    #[error("{}", memory_message(what, *needed, *limit, *explicit))]
    Memory {
        /// What was being computed ("reconstructing 4000 x 3000 pixels ...").
        what: String,
        /// Estimated (or requested) bytes.
        needed: f64,
        /// The limit in bytes (NaN when only the allocation failed).
        limit: f64,
        /// Whether the limit was the caller's `max_memory` (else the default share of the
        /// available memory).
        explicit: bool,
    },
    /// The caller asked the iteration to stop (for example on Ctrl-C).
    #[error("reconstruction cancelled")]
    Cancelled,
}

/// The share of the available memory that a computation may use when no `max_memory` is given
/// (the memory module's default limit; here for the message of [`Error::Memory`]).
pub(crate) const DEFAULT_MEMORY_FRACTION: f64 = 0.8;

fn memory_message(what: &str, needed: f64, limit: f64, explicit: bool) -> String {
    if limit.is_nan() {
        let size = if needed.is_finite() {
            format!("allocating {}", format_bytes(needed))
        } else {
            "an allocation".to_string()
        };
        return format!(
            "{what}: {size} failed (out of memory: the process cannot get that much from the \
             machine or its memory limit); use smaller images (bin or crop them) or free memory"
        );
    }
    let source = if explicit {
        "the max_memory given".to_string()
    } else {
        format!(
            "max_memory, by default {:.0}% of the memory available",
            DEFAULT_MEMORY_FRACTION * 100.0
        )
    };
    format!(
        "{what} needs about {} of memory, above the limit of {} ({source}); \
         use smaller images (bin or crop them) or raise max_memory",
        format_bytes(needed),
        format_bytes(limit)
    )
}

/// Human-readable bytes with three significant digits: "512 MB", "1.25 GB".
pub(crate) fn format_bytes(bytes: f64) -> String {
    if !bytes.is_finite() {
        return "unknown".to_string();
    }
    const UNITS: [&str; 6] = ["B", "kB", "MB", "GB", "TB", "PB"];
    let mut value = bytes.max(0.0);
    let mut unit = 0;
    while value >= 1000.0 && unit + 1 < UNITS.len() {
        value /= 1000.0;
        unit += 1;
    }
    if unit == 0 || value >= 100.0 {
        format!("{value:.0} {}", UNITS[unit])
    } else if value >= 10.0 {
        format!("{value:.1} {}", UNITS[unit])
    } else {
        format!("{value:.2} {}", UNITS[unit])
    }
}

/// Result alias used across the crate.
pub type Result<T> = std::result::Result<T, Error>;

/// Returns [`Error::Shape`] unless `expected == got`.
pub(crate) fn ensure_shape(
    what: &'static str,
    expected: usize,
    got: usize,
    message: impl FnOnce() -> String,
) -> Result<()> {
    if expected == got {
        Ok(())
    } else {
        Err(Error::Shape {
            what,
            expected,
            got,
            message: message(),
        })
    }
}

/// Checks that an optional per-pixel `mask` has `plane` (H x W) values.
pub(crate) fn ensure_mask(mask: Option<&[bool]>, plane: usize) -> Result<()> {
    match mask {
        Some(m) => ensure_shape("mask", plane, m.len(), || {
            format!("mask has {} values, expected H x W = {plane}", m.len())
        }),
        None => Ok(()),
    }
}

/// Returns [`Error::OutOfRange`] for the parameter `name` unless `cond` holds.
pub(crate) fn ensure_range(
    cond: bool,
    name: &'static str,
    value: f64,
    message: impl FnOnce() -> String,
) -> Result<()> {
    if cond {
        Ok(())
    } else {
        Err(Error::OutOfRange {
            name,
            value,
            message: message(),
        })
    }
}

/// Returns [`Error::Unusable`] unless `cond` holds.
pub(crate) fn ensure_usable(cond: bool, message: impl FnOnce() -> String) -> Result<()> {
    if cond {
        Ok(())
    } else {
        Err(Error::Unusable(message()))
    }
}

/// `x` with 6 significant digits, like C's `%g`: plain between 1e-4 and 1e6, else scientific
/// (messages never print a number with hundreds of digits).
pub fn g6(x: f64) -> String {
    if !x.is_finite() || x == 0.0 {
        return format!("{x}");
    }
    let exponent = x.abs().log10().floor() as i32;
    if (-4..6).contains(&exponent) {
        let decimals = (5 - exponent).max(0) as usize;
        let text = format!("{x:.decimals$}");
        if text.contains('.') {
            text.trim_end_matches('0').trim_end_matches('.').to_string()
        } else {
            text
        }
    } else {
        format!("{x:.5e}")
    }
}

#[cfg(test)]
mod tests {
    use super::g6;

    #[test]
    fn numbers_print_like_percent_g() {
        assert_eq!(g6(200.0), "200");
        assert_eq!(g6(0.000123456789), "0.000123457");
        assert_eq!(g6(-1.23456789), "-1.23457");
        assert_eq!(g6(1e300), "1.00000e300");
        assert_eq!(g6(f64::NAN), "NaN");
    }
}
