//! The worker threads of a run: a rayon pool of the requested size, faer's parallelism, and the
//! parallel scatter of per-facet values onto per-pixel maps.

use faer::Par;

use crate::error::{Error, Result};

/// Runs `f` on a rayon pool of `threads` workers (0: the global pool).
pub(crate) fn with_threads<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> Result<T> {
    if threads == 0 {
        return Ok(f());
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| Error::Unusable(format!("cannot start {threads} worker threads: {e}")))?;
    Ok(pool.install(f))
}

/// faer parallelism: sequential, or the current rayon pool when `parallel` is set.
pub(crate) fn sparse_par(parallel: bool) -> Par {
    match rayon::current_num_threads() {
        n if parallel && n > 1 => Par::rayon(n),
        _ => Par::Seq,
    }
}

/// Per-pixel maps that can be cut at a pixel, so that threads write disjoint pixel ranges
/// (see [`scatter`]).
pub(crate) trait PixelMaps: Send + Sized {
    /// The maps' pixels before `at` (counted from the maps' first pixel) and those from `at` on.
    fn split_at(self, at: usize) -> (Self, Self);
}

/// Two maps of one value a pixel.
impl<A: Send, B: Send> PixelMaps for (&mut [A], &mut [B]) {
    fn split_at(self, at: usize) -> (Self, Self) {
        let (a0, a1) = self.0.split_at_mut(at);
        let (b0, b1) = self.1.split_at_mut(at);
        ((a0, b0), (a1, b1))
    }
}

/// Writes `values[i]` onto pixel `pixels[i]` of `maps`, whose first pixel is `base`, as
/// `write(maps, pixels[i] - base, values[i])`. `pixels` increases (a grid's facets are in
/// increasing pixel order) and starts at `base` or later, so the halves of `values` write
/// disjoint pixel ranges: above `piece` values the two halves run in parallel
/// (`rayon::join`), each on its part of the maps.
pub(crate) fn scatter<M: PixelMaps, T: Sync>(
    maps: M,
    base: usize,
    pixels: &[u32],
    values: &[T],
    piece: usize,
    write: &(impl Fn(&mut M, usize, &T) + Sync),
) {
    debug_assert_eq!(pixels.len(), values.len());
    if values.len() > piece.max(1) {
        let mid = values.len() / 2;
        debug_assert!(pixels.windows(2).all(|w| w[0] < w[1]));
        let at = pixels[mid] as usize;
        let (left, right) = maps.split_at(at - base);
        rayon::join(
            || scatter(left, base, &pixels[..mid], &values[..mid], piece, write),
            || scatter(right, at, &pixels[mid..], &values[mid..], piece, write),
        );
        return;
    }
    let mut maps = maps;
    for (value, &p) in values.iter().zip(pixels) {
        write(&mut maps, p as usize - base, value);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scatter_writes_every_value_onto_its_pixel() {
        // Every third pixel of 10 000, in pieces of 7 values: many splits, each at a pixel that
        // is not a piece boundary of the maps.
        let pixels: Vec<u32> = (0..10_000).filter(|p| p % 3 == 1).collect();
        let values: Vec<f32> = pixels.iter().map(|&p| p as f32 * 0.5).collect();
        let (mut a, mut b) = (vec![f32::NAN; 10_000], vec![0u32; 10_000]);
        scatter(
            (&mut a[..], &mut b[..]),
            0,
            &pixels,
            &values,
            7,
            &|(a, b): &mut (&mut [f32], &mut [u32]), p, &v| {
                a[p] = v;
                b[p] = 1;
            },
        );
        for p in 0..10_000 {
            if p % 3 == 1 {
                assert_eq!((a[p], b[p]), (p as f32 * 0.5, 1), "pixel {p}");
            } else {
                assert!(a[p].is_nan() && b[p] == 0, "pixel {p}");
            }
        }
    }
}
