//! PNG decoding and encoding: one file, or several in parallel.
//!
//! ## Reading
//!
//! Each image comes back exactly as the file holds it: 8 or 16 bits per sample (all 16 bits, no
//! scaling, `sBIT` ignored), `[H, W]` for grey and `[H, W, 3]` for colour. Alpha is dropped;
//! palette images are expanded to RGB, and to grey when every pixel's colour is grey; grey
//! images of 1, 2 or 4 bits are scaled to 8 bits (0..255). An image whose header declares more
//! than `max_pixels` pixels is refused before anything is allocated (a small file can declare a
//! huge image). The chunks' CRCs and the zlib stream's Adler-32 are verified: a corrupted file is
//! an error, not an image with a few wrong pixels.
//!
//! ## Writing
//!
//! [`write_png`] stores 8- or 16-bit samples, grey `[H, W]` or RGB `[H, W, 3]`, as a
//! non-interlaced PNG of the same bit depth and colour type (16-bit samples big-endian, as the
//! format requires), row by row: no copy of the whole image is made. [`PngOptions`] choose the
//! DEFLATE effort and the row filter; the default (fast DEFLATE, adaptive filter) writes a 12 MP
//! 16-bit RGB normal map in a fraction of a second. [`write_pngs`] writes several files in
//! parallel. Any reader of standard PNG files reads them back; [`read_png`] returns the samples
//! written, bit for bit.

use std::fs::File;
use std::io::{BufReader, BufWriter, ErrorKind, Write};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};

use png::{BitDepth, ColorType, Transformations};
use rayon::prelude::*;

use crate::error::{Error, Result};

/// Read buffer of the file reader; larger than the default 8 KiB to cut system calls.
const READ_BUFFER: usize = 1 << 16;

/// Write buffer of the file writer.
const WRITE_BUFFER: usize = 1 << 20;

/// Bytes of compressed data per IDAT chunk of the files written.
const IDAT_CHUNK: usize = 1 << 18;

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

/// How hard the PNG writer compresses (DEFLATE effort); the file is valid PNG in every case.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[non_exhaustive]
pub enum PngCompression {
    /// Stored (uncompressed) DEFLATE blocks: the fastest, the largest files.
    None,
    /// A fast DEFLATE made for PNG rows (the `fdeflate` encoder): several hundred MB/s of
    /// samples, files typically 10-30 % larger than `Balanced`.
    #[default]
    Fast,
    /// zlib's default level (6).
    Balanced,
    /// zlib's best level (9): the smallest files, the slowest.
    High,
}

/// The PNG row filter: how each row is predicted from its neighbours before DEFLATE.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[non_exhaustive]
pub enum PngFilter {
    /// Per row, the filter whose output has the smallest sum of absolute values.
    #[default]
    Adaptive,
    /// No prediction.
    None,
    /// Each sample minus the one to its left.
    Sub,
    /// Each sample minus the one above.
    Up,
    /// The Paeth predictor of the left, upper and upper-left samples.
    Paeth,
}

/// The settings of [`write_png`] and [`write_pngs`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[non_exhaustive]
pub struct PngOptions {
    /// DEFLATE effort.
    pub compression: PngCompression,
    /// Row filter.
    pub filter: PngFilter,
}

impl PngOptions {
    /// Options with the given compression and filter.
    pub fn new(compression: PngCompression, filter: PngFilter) -> PngOptions {
        PngOptions {
            compression,
            filter,
        }
    }
}

/// The samples of an image to write, borrowed, in row-major order.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub enum Samples<'a> {
    /// 8-bit samples.
    U8(&'a [u8]),
    /// 16-bit samples (all 16 bits are stored).
    U16(&'a [u16]),
}

impl Samples<'_> {
    fn len(&self) -> usize {
        match self {
            Samples::U8(v) => v.len(),
            Samples::U16(v) => v.len(),
        }
    }
}

/// An image to write: `height` rows of `width` pixels of `channels` samples (1: grey, 3: RGB).
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub struct Image<'a> {
    /// The samples, `height * width * channels` of them.
    pub samples: Samples<'a>,
    /// Rows.
    pub height: usize,
    /// Pixels per row.
    pub width: usize,
    /// Samples per pixel: 1 (grey) or 3 (RGB).
    pub channels: usize,
}

impl<'a> Image<'a> {
    /// An image of `height` x `width` pixels of `channels` samples.
    pub fn new(samples: Samples<'a>, height: usize, width: usize, channels: usize) -> Image<'a> {
        Image {
            samples,
            height,
            width,
            channels,
        }
    }
}

/// Writes `image` to the file `path` (created or truncated) as a PNG of the samples' bit depth,
/// grey for one channel and RGB for three; fails with [`Error::ImageWrite`] naming the file when
/// the image cannot be stored (no pixels, a side above 2^31 - 1, a channel count other than 1 or
/// 3, too few or too many samples) or the file cannot be written.
pub fn write_png(path: &Path, image: &Image<'_>, options: PngOptions) -> Result<()> {
    let fail = |os_error: Option<i32>, reason: String| Error::ImageWrite {
        path: path.to_path_buf(),
        os_error,
        reason,
    };
    let (w, h) = check_image(image).map_err(|reason| fail(None, reason))?;
    let guarded = catch_unwind(AssertUnwindSafe(|| encode(path, image, w, h, options)));
    match guarded {
        Ok(Ok(())) => Ok(()),
        Ok(Err(png::EncodingError::IoError(e))) => Err(fail(e.raw_os_error(), e.to_string())),
        Ok(Err(e)) => Err(fail(None, e.to_string())),
        Err(_) => Err(fail(None, "internal error (please report it)".to_string())),
    }
}

/// Writes the images `jobs` (file, image) in parallel (on the current rayon pool), each as
/// [`write_png`] does; the results in the order of `jobs`.
pub fn write_pngs(jobs: &[(PathBuf, Image<'_>)], options: PngOptions) -> Vec<Result<()>> {
    jobs.par_iter()
        .map(|(path, image)| write_png(path, image, options))
        .collect()
}

/// The image's width and height as PNG stores them, or why it cannot be stored.
fn check_image(image: &Image<'_>) -> std::result::Result<(u32, u32), String> {
    if image.channels != 1 && image.channels != 3 {
        return Err(format!(
            "{} channels: a PNG image here is grey (1) or RGB (3)",
            image.channels
        ));
    }
    let side = |n: usize| u32::try_from(n).ok().filter(|&v| v > 0 && v < (1 << 31));
    let (Some(w), Some(h)) = (side(image.width), side(image.height)) else {
        return Err(format!(
            "{} x {} pixels: each side must be 1 to 2^31 - 1 pixels",
            image.width, image.height
        ));
    };
    let expected = image
        .height
        .checked_mul(image.width)
        .and_then(|n| n.checked_mul(image.channels));
    if expected != Some(image.samples.len()) {
        return Err(format!(
            "{} samples for {} x {} pixels of {} channels",
            image.samples.len(),
            image.height,
            image.width,
            image.channels
        ));
    }
    Ok((w, h))
}

/// Encodes `image` (checked: `w` x `h` pixels) into the file `path`, row by row.
fn encode(
    path: &Path,
    image: &Image<'_>,
    w: u32,
    h: u32,
    options: PngOptions,
) -> std::result::Result<(), png::EncodingError> {
    let file = BufWriter::with_capacity(WRITE_BUFFER, File::create(path)?);
    let mut encoder = png::Encoder::new(file, w, h);
    encoder.set_color(if image.channels == 1 {
        ColorType::Grayscale
    } else {
        ColorType::Rgb
    });
    encoder.set_depth(match image.samples {
        Samples::U8(_) => BitDepth::Eight,
        Samples::U16(_) => BitDepth::Sixteen,
    });
    encoder.set_compression(match options.compression {
        PngCompression::None => png::Compression::NoCompression,
        PngCompression::Fast => png::Compression::Fast,
        PngCompression::Balanced => png::Compression::Balanced,
        PngCompression::High => png::Compression::High,
    });
    encoder.set_filter(match options.filter {
        PngFilter::Adaptive => png::Filter::Adaptive,
        PngFilter::None => png::Filter::NoFilter,
        PngFilter::Sub => png::Filter::Sub,
        PngFilter::Up => png::Filter::Up,
        PngFilter::Paeth => png::Filter::Paeth,
    });
    let row_len = image.width * image.channels;
    let mut writer = encoder.write_header()?;
    let mut stream = writer.stream_writer_with_size(IDAT_CHUNK)?;
    match image.samples {
        Samples::U8(v) => stream.write_all(v)?,
        Samples::U16(v) => {
            // Big-endian, one row at a time (the stream writer buffers a row itself).
            let mut row = vec![0u8; 2 * row_len];
            for samples in v.chunks_exact(row_len) {
                for (bytes, &x) in row.chunks_exact_mut(2).zip(samples) {
                    bytes.copy_from_slice(&x.to_be_bytes());
                }
                stream.write_all(&row)?;
            }
        }
    }
    stream.finish()?;
    // The end chunk, and the file flushed here, not on drop: a failed write (a full disk) must
    // be an error.
    writer.finish()?;
    Ok(())
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

    fn grey_and_rgb(dir: &Path) -> Vec<(PathBuf, Vec<u16>, usize)> {
        let grey: Vec<u16> = (0..7 * 5).map(|i| (i * 1871 % 65536) as u16).collect();
        let rgb: Vec<u16> = (0..7 * 5 * 3).map(|i| (i * 40503 % 65536) as u16).collect();
        vec![(dir.join("g.png"), grey, 1), (dir.join("c.png"), rgb, 3)]
    }

    #[test]
    fn written_images_read_back_bit_for_bit() {
        let dir = std::env::temp_dir().join(format!("nplps-png-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let cases = grey_and_rgb(&dir);
        for compression in [
            PngCompression::None,
            PngCompression::Fast,
            PngCompression::Balanced,
            PngCompression::High,
        ] {
            for filter in [
                PngFilter::Adaptive,
                PngFilter::None,
                PngFilter::Sub,
                PngFilter::Up,
                PngFilter::Paeth,
            ] {
                let options = PngOptions::new(compression, filter);
                // 16 bits, in parallel.
                let jobs: Vec<(PathBuf, Image<'_>)> = cases
                    .iter()
                    .map(|(p, v, c)| (p.clone(), Image::new(Samples::U16(v), 5, 7, *c)))
                    .collect();
                assert!(write_pngs(&jobs, options).iter().all(|r| r.is_ok()));
                for (path, v, c) in &cases {
                    let back = read_png(path, 1 << 20).unwrap();
                    assert_eq!(back.pixels, Pixels::U16(v.clone()));
                    let shape = if *c == 1 { vec![5, 7] } else { vec![5, 7, 3] };
                    assert_eq!(back.shape, shape);
                }
                // 8 bits.
                for (path, v, c) in &cases {
                    let bytes: Vec<u8> = v.iter().map(|&x| (x >> 8) as u8).collect();
                    write_png(path, &Image::new(Samples::U8(&bytes), 5, 7, *c), options).unwrap();
                    assert_eq!(read_png(path, 1 << 20).unwrap().pixels, Pixels::U8(bytes));
                }
            }
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn unwritable_images_are_errors_naming_the_file() {
        let path = Path::new("/nonexistent-nplps-dir/x.png");
        let samples = [0u8; 6];
        let image = Image::new(Samples::U8(&samples), 1, 2, 3);
        match write_png(path, &image, PngOptions::default()) {
            Err(Error::ImageWrite {
                path: p, os_error, ..
            }) => {
                assert_eq!(p, path);
                assert!(os_error.is_some());
            }
            other => panic!("{other:?}"),
        }
        for (h, w, c) in [(1, 2, 2), (0, 3, 1), (1, 3, 3), (2, 2, 1)] {
            let image = Image::new(Samples::U8(&samples), h, w, c);
            let err = write_png(path, &image, PngOptions::default()).unwrap_err();
            assert!(
                matches!(err, Error::ImageWrite { os_error: None, .. }),
                "{err}"
            );
            assert!(err.to_string().contains("x.png"));
        }
    }
}
