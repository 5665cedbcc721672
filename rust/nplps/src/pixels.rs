//! The integer pixels of a result's PNG pictures, made from its float64 maps in one parallel pass
//! (no full-size float temporaries).
//!
//! - A grey picture of values in [0, 1]: `round(clip(x, 0, 1) 255)` as `u8`, NaN as 0 (+inf as
//!   255, -inf as 0), rounding half to even ([`grey_pixels`]).
//! - A normal map: each channel `round(((clip(n_c f_c, -1, 1) + 1) / 2) top)` with the frame's
//!   signs `f_c = +-1` and `top = 2^bits - 1`, all three 0 where a component is not finite or
//!   outside the mask ([`normal_map_pixels`]).
//!
//! Both with numpy's arithmetic (`nplps.export`'s `_grey_pixels` and `normal_map_pixels`):
//! the same float64 operations in the same order, rounding half to even as `np.rint`, so the
//! same bytes.

use rayon::prelude::*;

use crate::error::{ensure_mask, ensure_shape, Result};

/// Values a task of the parallel loops converts.
const CHUNK: usize = 1 << 16;

/// The 8-bit grey pixels of `image` (see the module documentation).
pub fn grey_pixels(image: &[f64]) -> Vec<u8> {
    let mut out = vec![0u8; image.len()];
    out.par_chunks_mut(CHUNK)
        .zip(image.par_chunks(CHUNK))
        .for_each(|(out, image)| {
            for (o, &x) in out.iter_mut().zip(image) {
                *o = if x.is_nan() {
                    0
                } else {
                    (x.clamp(0.0, 1.0) * 255.0).round_ties_even() as u8
                };
            }
        });
    out
}

/// The normal-map pixels (H x W x 3, row-major) of the unit `normals` (H x W x 3, row-major,
/// camera frame) in the frame of the signs `flip`, with `bits` (8 or 16) per channel, as `u16`
/// values (below 256 for 8 bits); black outside `mask` (H x W; None: everywhere) and where a
/// component is not finite.
pub fn normal_map_pixels(
    normals: &[f64],
    mask: Option<&[bool]>,
    flip: [f64; 3],
    bits: u32,
) -> Result<Vec<u16>> {
    ensure_shape("normals", 0, normals.len() % 3, || {
        format!("normals has {} values, not a multiple of 3", normals.len())
    })?;
    let plane = normals.len() / 3;
    ensure_mask(mask, plane)?;
    ensure_shape("bits", 1, usize::from(bits == 8 || bits == 16), || {
        format!("bits must be 8 or 16, got {bits}")
    })?;
    let top = f64::from((1u32 << bits) - 1);
    let mut out = vec![0u16; normals.len()];
    out.par_chunks_mut(3 * CHUNK)
        .enumerate()
        .for_each(|(chunk, out)| {
            let first = chunk * CHUNK;
            for (i, o) in out.chunks_exact_mut(3).enumerate() {
                let p = first + i;
                let n = &normals[3 * p..3 * p + 3];
                if mask.is_some_and(|m| !m[p]) || !n.iter().all(|x| x.is_finite()) {
                    continue; // black (the buffer's zeros)
                }
                for c in 0..3 {
                    let f = (n[c] * flip[c]).clamp(-1.0, 1.0);
                    o[c] = ((f + 1.0) / 2.0 * top).round_ties_even() as u16;
                }
            }
        });
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grey_pixels_round_half_to_even_and_clip() {
        // 0.5 255 = 127.5 rounds to 128 (even), 0.25 255 = 63.75 to 64, 2^-9 255 = 0.498.. to 0,
        // 3 2^-9 255 = 1.494.. to 1; NaN and below 0 to 0, above 1 and +inf to 255.
        let image = [
            f64::NAN,
            -0.5,
            0.0,
            0.5,
            0.25,
            1.0 / 512.0,
            3.0 / 512.0,
            1.0,
            3.0,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ];
        assert_eq!(
            grey_pixels(&image),
            [0, 0, 0, 128, 64, 0, 1, 255, 255, 255, 0]
        );
    }

    #[test]
    fn normal_map_pixels_encode_the_frame_and_blacken_the_rest() {
        let normals = [
            0.0,
            0.0,
            -1.0,
            1.0,
            0.0,
            0.0,
            f64::NAN,
            0.0,
            -1.0,
            0.6,
            -0.8,
            0.0,
            2.0,
            -2.0,
            0.0,
        ];
        let mask = [true, true, true, false, true];
        let px = normal_map_pixels(&normals, Some(&mask), [1.0, -1.0, -1.0], 16).unwrap();
        // (0, 0, -1) -> (0, 0, 1) in OpenGL: (32768, 32768, 65535) (32767.5 rounds to even).
        assert_eq!(px[0..3], [32768, 32768, 65535]);
        assert_eq!(px[3..6], [65535, 32768, 32768]);
        assert_eq!(px[6..9], [0, 0, 0]); // a NaN component
        assert_eq!(px[9..12], [0, 0, 0]); // outside the mask
        assert_eq!(px[12..15], [65535, 65535, 32768]); // clipped to [-1, 1]
        let px8 = normal_map_pixels(&normals, None, [1.0, 1.0, 1.0], 8).unwrap();
        assert_eq!(px8[0..3], [128, 128, 0]);
        assert_eq!(px8[9..12], [204, 25, 128]);
        assert!(normal_map_pixels(&normals, Some(&mask[1..]), [1.0; 3], 8).is_err());
        assert!(normal_map_pixels(&normals, None, [1.0; 3], 12).is_err());
        assert!(normal_map_pixels(&normals[1..], None, [1.0; 3], 8).is_err());
    }
}
