//! PNG decoding: one file, or several in parallel.
//!
//! Each image comes back exactly as the file holds it: 8 or 16 bits per sample (all 16 bits, no
//! scaling, `sBIT` ignored), `[H, W]` for grey and `[H, W, 3]` for colour. Alpha is dropped;
//! palette images are expanded to RGB, and to grey when every pixel's colour is grey; grey
//! images of 1, 2 or 4 bits are scaled to 8 bits (0..255). An image whose header declares more
//! than `max_pixels` pixels is refused before anything is allocated (a small file can declare a
//! huge image). The chunks' CRCs and the zlib stream's Adler-32 are verified: a corrupted file is
//! an error, not an image with a few wrong pixels.

use std::fs::File;
use std::io::{BufReader, ErrorKind};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};

use png::{BitDepth, ColorType, Transformations};
use rayon::prelude::*;

use crate::error::{Error, Result};

/// Read buffer of the file reader; larger than the default 8 KiB to cut system calls.
const READ_BUFFER: usize = 1 << 16;

/// The samples of one decoded image, as the file stores them.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum Pixels {
    /// 8-bit samples (0..255).
    U8(Vec<u8>),
    /// 16-bit samples (0..65535), all 16 bits.
    U16(Vec<u16>),
}

/// One decoded image: samples in row-major order and their shape, `[H, W]` (grey) or
/// `[H, W, 3]` (colour).
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct Decoded {
    /// The samples.
    pub pixels: Pixels,
    /// `[H, W]` or `[H, W, 3]`.
    pub shape: Vec<usize>,
}

impl Decoded {
    /// The samples scaled to [0, 1] (divided by 255 or 65535), in the same layout.
    pub fn to_unit(&self) -> Vec<f32> {
        match &self.pixels {
            Pixels::U8(v) => v.iter().map(|&x| f32::from(x) / 255.0).collect(),
            Pixels::U16(v) => v.iter().map(|&x| f32::from(x) / 65535.0).collect(),
        }
    }
}

/// Decodes the PNG file `path`; fails with [`Error::Image`] naming the file when it is missing,
/// is not a valid PNG, or declares more than `max_pixels` pixels, and with [`Error::Memory`]
/// when its samples cannot be allocated.
pub fn read_png(path: &Path, max_pixels: u64) -> Result<Decoded> {
    decode_guarded(path, max_pixels).map_err(|failure| match failure {
        Failure::Reason(reason) => Error::Image {
            path: path.to_path_buf(),
            reason,
        },
        Failure::Memory(bytes) => {
            crate::memory::allocation_failed(&format!("decoding image '{}'", path.display()), bytes)
        }
    })
}

/// Why a file cannot be decoded.
enum Failure {
    /// Missing, invalid, too large: the message.
    Reason(String),
    /// The samples (this many bytes) cannot be allocated.
    Memory(f64),
}

impl From<String> for Failure {
    fn from(reason: String) -> Failure {
        Failure::Reason(reason)
    }
}

impl From<&str> for Failure {
    fn from(reason: &str) -> Failure {
        Failure::Reason(reason.to_string())
    }
}

/// A vector of `len` default values, or [`Failure::Memory`].
fn try_buffer<T: Copy + Default>(len: usize) -> std::result::Result<Vec<T>, Failure> {
    let mut v = Vec::new();
    v.try_reserve_exact(len)
        .map_err(|_| Failure::Memory(len as f64 * std::mem::size_of::<T>() as f64))?;
    v.resize(len, T::default());
    Ok(v)
}

/// Decodes the PNG files `paths` in parallel (on the current rayon pool), each as
/// [`read_png`] does, in the order of `paths`.
pub fn read_pngs(paths: &[PathBuf], max_pixels: u64) -> Vec<Result<Decoded>> {
    paths
        .par_iter()
        .map(|path| read_png(path, max_pixels))
        .collect()
}

/// [`decode`], with a panic turned into an error message.
fn decode_guarded(path: &Path, max_pixels: u64) -> std::result::Result<Decoded, Failure> {
    catch_unwind(AssertUnwindSafe(|| decode(path, max_pixels))).unwrap_or_else(|payload| {
        let what = payload
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| payload.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "unknown panic".to_string());
        Err(Failure::Reason(format!(
            "internal error (please report it): {what}"
        )))
    })
}

/// Decodes one PNG file.
fn decode(path: &Path, max_pixels: u64) -> std::result::Result<Decoded, Failure> {
    let file = File::open(path).map_err(|e| match e.kind() {
        ErrorKind::NotFound => "file not found".to_string(),
        _ => e.to_string(),
    })?;
    let mut decoder = png::Decoder::new(BufReader::with_capacity(READ_BUFFER, file));
    // Verify the chunks' CRCs and the zlib stream's Adler-32 (the crate skips the latter by
    // default): a corrupted file is an error, not an image with a few wrong pixels.
    decoder.ignore_checksums(false);
    let header = decoder.read_header_info().map_err(|e| e.to_string())?;
    let (width, height) = (header.width, header.height);
    if u64::from(width) * u64::from(height) > max_pixels {
        return Err(Failure::Reason(format!(
            "{width} x {height} pixels is more than the limit of {max_pixels} pixels \
             (max_pixels; raise it if the image is genuine)"
        )));
    }
    let palette = header.color_type == ColorType::Indexed;
    // Palette to RGB(A), grey below 8 bits to 8 bits (scaled to 0..255), tRNS to alpha.
    decoder.set_transformations(Transformations::EXPAND);
    let mut reader = decoder.read_info().map_err(|e| e.to_string())?;
    let (colour, depth) = reader.output_color_type();
    let samples = colour.samples();
    let channels = if samples >= 3 { 3 } else { 1 };
    let (h, w) = (height as usize, width as usize);
    let shape = if channels == 1 {
        vec![h, w]
    } else {
        vec![h, w, 3]
    };
    let pixels = match depth {
        BitDepth::Eight => {
            let mut out = read_rows(&mut reader, h, w * channels, |src, dst| {
                copy_row_u8(src, dst, samples, channels)
            })?;
            if palette && channels == 3 && is_grey(&out) {
                out = rgb_to_grey(out);
                return Ok(Decoded {
                    pixels: Pixels::U8(out),
                    shape: vec![h, w],
                });
            }
            Pixels::U8(out)
        }
        BitDepth::Sixteen => Pixels::U16(read_rows(&mut reader, h, w * channels, |src, dst| {
            copy_row_u16(src, dst, samples, channels)
        })?),
        other => {
            return Err(Failure::Reason(format!(
                "unexpected bit depth {other:?} after expansion"
            )))
        }
    };
    Ok(Decoded { pixels, shape })
}

/// Decodes the image data into `h` rows of `row_len` samples, each converted from the decoder's
/// row by `convert`.
fn read_rows<T: Copy + Default, R: std::io::BufRead + std::io::Seek>(
    reader: &mut png::Reader<R>,
    h: usize,
    row_len: usize,
    convert: impl Fn(&[u8], &mut [T]),
) -> std::result::Result<Vec<T>, Failure> {
    let mut out = try_buffer(h * row_len)?;
    if row_len == 0 {
        return Ok(out);
    }
    read_frame(reader, row_len, &mut out, convert)?;
    // Read to the end of the image data, so that its CRC and Adler-32 are verified.
    reader
        .finish()
        .map_err(|e| format!("the image data is corrupt ({e})"))?;
    Ok(out)
}

/// [`read_rows`] into `out`.
fn read_frame<T: Copy + Default, R: std::io::BufRead + std::io::Seek>(
    reader: &mut png::Reader<R>,
    row_len: usize,
    out: &mut [T],
    convert: impl Fn(&[u8], &mut [T]),
) -> std::result::Result<(), Failure> {
    if reader.info().interlaced {
        // Adam7 rows arrive pass by pass: decode the whole frame, then convert it.
        let size = reader
            .output_buffer_size()
            .ok_or("the image is too large for this machine")?;
        let mut frame: Vec<u8> = try_buffer(size)?;
        let info = reader.next_frame(&mut frame).map_err(|e| e.to_string())?;
        for (src, dst) in frame
            .chunks_exact(info.line_size)
            .zip(out.chunks_exact_mut(row_len))
        {
            convert(src, dst);
        }
    } else {
        for dst in out.chunks_exact_mut(row_len) {
            let row = reader
                .next_row()
                .map_err(|e| e.to_string())?
                .ok_or("the image data ends early")?;
            convert(row.data(), dst);
        }
    }
    Ok(())
}

/// Copies the first `channels` of every pixel's `samples` 8-bit samples.
fn copy_row_u8(src: &[u8], dst: &mut [u8], samples: usize, channels: usize) {
    if samples == channels {
        dst.copy_from_slice(&src[..dst.len()]);
    } else {
        for (d, s) in dst
            .chunks_exact_mut(channels)
            .zip(src.chunks_exact(samples))
        {
            d.copy_from_slice(&s[..channels]);
        }
    }
}

/// Copies the first `channels` of every pixel's `samples` 16-bit big-endian samples.
fn copy_row_u16(src: &[u8], dst: &mut [u16], samples: usize, channels: usize) {
    if samples == channels {
        for (d, s) in dst.iter_mut().zip(src.chunks_exact(2)) {
            *d = u16::from_be_bytes([s[0], s[1]]);
        }
    } else {
        for (d, s) in dst
            .chunks_exact_mut(channels)
            .zip(src.chunks_exact(2 * samples))
        {
            for (v, b) in d.iter_mut().zip(s.chunks_exact(2)) {
                *v = u16::from_be_bytes([b[0], b[1]]);
            }
        }
    }
}

/// True when every RGB pixel has equal channels.
fn is_grey(rgb: &[u8]) -> bool {
    rgb.chunks_exact(3).all(|p| p[0] == p[1] && p[1] == p[2])
}

/// The first channel of an RGB image, in place.
fn rgb_to_grey(mut rgb: Vec<u8>) -> Vec<u8> {
    let n = rgb.len() / 3;
    for i in 0..n {
        rgb[i] = rgb[3 * i];
    }
    rgb.truncate(n);
    rgb.shrink_to_fit();
    rgb
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_drop_alpha_and_swap_bytes() {
        let mut grey = [0u16; 2];
        copy_row_u16(&[1, 2, 9, 9, 3, 4, 9, 9], &mut grey, 2, 1);
        assert_eq!(grey, [0x0102, 0x0304]);
        let mut rgb = [0u8; 3];
        copy_row_u8(&[1, 2, 3, 4], &mut rgb, 4, 3);
        assert_eq!(rgb, [1, 2, 3]);
    }

    #[test]
    fn grey_palette_reduction() {
        assert!(is_grey(&[5, 5, 5, 7, 7, 7]));
        assert!(!is_grey(&[5, 5, 5, 7, 7, 8]));
        assert_eq!(rgb_to_grey(vec![5, 5, 5, 7, 7, 7]), vec![5, 7]);
    }
}
