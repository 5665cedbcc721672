//! The trust figures of a result's `summary.json`, from the per-pixel trust maps in a few
//! streaming passes, with no copy of the selected values.
//!
//! The pixels counted are those inside the mask where both maps are finite, in raster order:
//! `s_0, ..., s_(n-1)` (the normal's standard deviation) and `h_0, ..., h_(n-1)` (the held-out
//! error). The figures are, in float64 (the values widened exactly):
//! - `rms(s) = sqrt(S(s_i^2) / n)` and `mean(h) = S(h_i) / n`, where `S` is numpy's pairwise sum
//!   of a contiguous float64 array ([`pairwise_sums`]), so that they equal numpy's
//!   `np.sqrt(np.mean(s.astype(float64) ** 2))` and `np.mean(h.astype(float64))` bit for bit;
//! - the median and the 90th percentile of each map, from the order statistics `x_(0) <= ... <=
//!   x_(n-1)`: the median is `x_(n/2)` for odd `n` and `(x_(n/2-1) + x_(n/2)) / 2` for even `n`;
//!   the percentile ("linear", numpy's default) has the virtual index `v = (n - 1) 0.9`,
//!   `i = floor(v)`, `g = v - i`, `d = x_(i+1) - x_i`, and is `x_i + d g` when `g < 1/2`,
//!   `x_(i+1) - d (1 - g)` otherwise (numpy's `_lerp`), or `x_(n-1)` when `v >= n - 1`
//!   (`np.median`, `np.percentile(.., 90)`).
//!
//! The order statistics are found by a radix selection on an order-preserving integer key of each
//! value ([`TrustValue::key`]), 16 bits a pass: a histogram of the key's top 16 bits tells in which
//! bucket each wanted rank lies and its rank inside it; the next pass counts the next 16 bits of
//! the values in those buckets only; after `bits / 16` passes the key, hence the value, of each
//! rank is known exactly. Keys order `-0` before `+0`: where both zeros sit at a wanted rank the
//! sign of a zero figure may differ from numpy's (whose selection leaves their order open).

use crate::error::{ensure_shape, Result};

/// A trust map's value type (float32 or float64): widening to float64 and an integer key with
/// the same order as the (finite) values.
pub trait TrustValue: Copy + Send + Sync {
    /// Bits of the key (a multiple of 16).
    const BITS: u32;
    /// The value as float64 (exact).
    fn wide(self) -> f64;
    /// Whether the value is finite.
    fn finite(self) -> bool;
    /// The key: the bits with the sign bit flipped for positive values and all bits flipped for
    /// negative ones, so that `a < b` implies `key(a) < key(b)` (and `-0` before `+0`).
    fn key(self) -> u64;
    /// The value of a key (the inverse of [`TrustValue::key`]).
    fn of_key(key: u64) -> Self;
}

impl TrustValue for f32 {
    const BITS: u32 = 32;
    fn wide(self) -> f64 {
        f64::from(self)
    }
    fn finite(self) -> bool {
        self.is_finite()
    }
    fn key(self) -> u64 {
        let b = self.to_bits();
        u64::from(if b >> 31 == 1 { !b } else { b | 1 << 31 })
    }
    fn of_key(key: u64) -> Self {
        let k = key as u32;
        f32::from_bits(if k >> 31 == 1 { k & !(1 << 31) } else { !k })
    }
}

impl TrustValue for f64 {
    const BITS: u32 = 64;
    fn wide(self) -> f64 {
        self
    }
    fn finite(self) -> bool {
        self.is_finite()
    }
    fn key(self) -> u64 {
        let b = self.to_bits();
        if b >> 63 == 1 {
            !b
        } else {
            b | 1 << 63
        }
    }
    fn of_key(key: u64) -> Self {
        f64::from_bits(if key >> 63 == 1 {
            key & !(1 << 63)
        } else {
            !key
        })
    }
}

/// The trust figures of [`trust_figures`] (see the module documentation); with no pixel
/// (`pixels == 0`) the others are NaN.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrustFigures {
    /// The pixels inside the mask where both maps are finite.
    pub pixels: usize,
    /// Median of the normal's standard deviation.
    pub sigma_median: f64,
    /// 90th percentile of the normal's standard deviation.
    pub sigma_p90: f64,
    /// Root mean square of the normal's standard deviation.
    pub sigma_rms: f64,
    /// Mean of the held-out error.
    pub held_mean: f64,
    /// Median of the held-out error.
    pub held_median: f64,
    /// 90th percentile of the held-out error.
    pub held_p90: f64,
}

/// numpy's block of its pairwise sum: below it the values are summed with 8 accumulators.
const BLOCK: usize = 128;

/// Pairwise sums of the next `n` pairs of `values`, the recursion of numpy's pairwise sum of a
/// contiguous float64 array (both sums share it): fewer than 8 values are added one by one to 0;
/// up to [`BLOCK`], 8 running sums `r_j` over the values `j, j + 8, ...` of the first
/// `n - n mod 8`, combined as `((r_0 + r_1) + (r_2 + r_3)) + ((r_4 + r_5) + (r_6 + r_7))`, then
/// the last `n mod 8` added one by one; above, the sum of the first `m = floor(n / 2)` rounded
/// down to a multiple of 8 plus the sum of the other `n - m`.
fn pairwise_sums(n: usize, values: &mut impl Iterator<Item = (f64, f64)>) -> (f64, f64) {
    if n < 8 {
        let mut sum = (0.0, 0.0);
        for (a, b) in values.take(n) {
            sum.0 += a;
            sum.1 += b;
        }
        sum
    } else if n <= BLOCK {
        let mut block = [(0.0, 0.0); BLOCK];
        for (slot, v) in block.iter_mut().zip(values.take(n)) {
            *slot = v;
        }
        let mut r = [(0.0, 0.0); 8];
        r.copy_from_slice(&block[..8]);
        let whole = n - n % 8;
        for eight in block[8..whole].chunks_exact(8) {
            for (r, v) in r.iter_mut().zip(eight) {
                r.0 += v.0;
                r.1 += v.1;
            }
        }
        let combine = |f: fn(&(f64, f64)) -> f64| {
            ((f(&r[0]) + f(&r[1])) + (f(&r[2]) + f(&r[3])))
                + ((f(&r[4]) + f(&r[5])) + (f(&r[6]) + f(&r[7])))
        };
        let mut sum = (combine(|v| v.0), combine(|v| v.1));
        for v in &block[whole..n] {
            sum.0 += v.0;
            sum.1 += v.1;
        }
        sum
    } else {
        let half = n / 2;
        let first = half - half % 8;
        let a = pairwise_sums(first, values);
        let b = pairwise_sums(n - first, values);
        (a.0 + b.0, a.1 + b.1)
    }
}

/// A radix selection of some order statistics of a stream of keys, 16 bits a pass (see the module
/// documentation).
struct Selection {
    /// The wanted ranks' rank inside the bucket their key's known prefix names.
    rank: Vec<usize>,
    /// The wanted ranks' known key prefix (the top `16 level` bits).
    prefix: Vec<u64>,
    /// The distinct prefixes of this pass, with the histogram of the next 16 bits of the keys
    /// under each.
    groups: Vec<(u64, Vec<u64>)>,
    /// The bits below the 16 this pass counts.
    shift: u32,
}

impl Selection {
    /// A selection whose first pass counts the top 16 bits of every key (the ranks are set later,
    /// by [`Selection::resolve`], once the number of values is known).
    fn new(bits: u32) -> Self {
        Self {
            rank: Vec::new(),
            prefix: Vec::new(),
            groups: vec![(0, vec![0; 1 << 16])],
            shift: bits - 16,
        }
    }

    /// Counts one key.
    #[inline]
    fn count(&mut self, key: u64) {
        let digit = ((key >> self.shift) & 0xffff) as usize;
        let above = key.checked_shr(self.shift + 16).unwrap_or(0);
        for (prefix, histogram) in &mut self.groups {
            if *prefix == above {
                histogram[digit] += 1;
            }
        }
    }

    /// After a pass: the next 16 bits of each wanted rank's key (`ranks` on the first call), and
    /// the groups of the next pass; true when the keys are complete.
    fn resolve(&mut self, ranks: Option<&[usize]>) -> bool {
        if let Some(ranks) = ranks {
            self.rank = ranks.to_vec();
            self.prefix = vec![0; ranks.len()];
        }
        for (rank, prefix) in self.rank.iter_mut().zip(&mut self.prefix) {
            let (_, histogram) = self
                .groups
                .iter()
                .find(|(p, _)| p == prefix)
                .expect("each rank's prefix has its group");
            let mut below = 0;
            let digit = histogram
                .iter()
                .position(|&count| {
                    below += count;
                    below > *rank as u64
                })
                .expect("a rank below the number of values");
            *rank -= (below - histogram[digit]) as usize;
            *prefix = (*prefix << 16) | digit as u64;
        }
        if self.shift == 0 {
            return true;
        }
        self.shift -= 16;
        let mut prefixes = self.prefix.clone();
        prefixes.sort_unstable();
        prefixes.dedup();
        self.groups = prefixes
            .into_iter()
            .map(|p| (p, vec![0; 1 << 16]))
            .collect();
        false
    }
}

/// The ranks read by the median and the 90th percentile of `n > 0` values: the median's one or
/// two, the percentile's `i` and `min(i + 1, n - 1)`, and the virtual index `v`.
fn wanted_ranks(n: usize) -> ([usize; 4], f64) {
    let half = n / 2;
    let virtual_index = (n - 1) as f64 * 0.9;
    let low = if virtual_index >= (n - 1) as f64 {
        n - 1
    } else {
        virtual_index.floor() as usize
    };
    let high = (low + 1).min(n - 1);
    let median_low = if n % 2 == 1 { half } else { half - 1 };
    ([median_low, half, low, high], virtual_index)
}

/// The median and the 90th percentile from the values at [`wanted_ranks`] (in their order).
fn median_p90(n: usize, at: [f64; 4], virtual_index: f64) -> (f64, f64) {
    let median = if n % 2 == 1 {
        at[1]
    } else {
        (at[0] + at[1]) / 2.0
    };
    let (a, b) = (at[2], at[3]);
    let low = if virtual_index >= (n - 1) as f64 {
        n - 1
    } else {
        virtual_index.floor() as usize
    };
    let p90 = if low == n - 1 {
        b
    } else {
        let gamma = virtual_index - low as f64;
        let diff = b - a;
        if gamma >= 0.5 {
            b - diff * (1.0 - gamma)
        } else {
            a + diff * gamma
        }
    };
    (median, p90)
}

/// The trust figures (see the module documentation) of the normal's standard deviation `sigma`
/// and the held-out error `held` (H x W each, row-major) over the pixels of `mask` where both
/// are finite. Reads the maps `1 + bits / 16` times (float32: 3) and copies none of them.
pub fn trust_figures<T: TrustValue>(
    mask: &[bool],
    sigma: &[T],
    held: &[T],
) -> Result<TrustFigures> {
    let plane = mask.len();
    ensure_shape("normal_sigma", plane, sigma.len(), || {
        format!(
            "normal_sigma has {} values, expected H x W = {plane}",
            sigma.len()
        )
    })?;
    ensure_shape("held_out_error", plane, held.len(), || {
        format!(
            "held_out_error has {} values, expected H x W = {plane}",
            held.len()
        )
    })?;
    let inside = || {
        mask.iter()
            .zip(sigma.iter().zip(held))
            .filter(|(&m, (s, h))| m && s.finite() && h.finite())
            .map(|(_, (&s, &h))| (s, h))
    };
    let mut selections = [Selection::new(T::BITS), Selection::new(T::BITS)];
    let mut n = 0;
    for (s, h) in inside() {
        n += 1;
        selections[0].count(s.key());
        selections[1].count(h.key());
    }
    if n == 0 {
        let nan = f64::NAN;
        return Ok(TrustFigures {
            pixels: 0,
            sigma_median: nan,
            sigma_p90: nan,
            sigma_rms: nan,
            held_mean: nan,
            held_median: nan,
            held_p90: nan,
        });
    }
    let (ranks, virtual_index) = wanted_ranks(n);
    let mut done = false;
    for selection in &mut selections {
        done = selection.resolve(Some(&ranks));
    }
    // The sums on the second pass, with the selection's next 16 bits.
    let mut pairs = inside().map(|(s, h)| {
        if !done {
            selections[0].count(s.key());
            selections[1].count(h.key());
        }
        let s = s.wide();
        (s * s, h.wide())
    });
    let (squares, errors) = pairwise_sums(n, &mut pairs);
    debug_assert!(pairs.next().is_none());
    drop(pairs);
    while !done {
        for selection in &mut selections {
            done = selection.resolve(None);
        }
        if !done {
            for (s, h) in inside() {
                selections[0].count(s.key());
                selections[1].count(h.key());
            }
        }
    }
    let [sigma_at, held_at] = selections
        .each_ref()
        .map(|s| std::array::from_fn(|j| T::of_key(s.prefix[j]).wide()));
    let (sigma_median, sigma_p90) = median_p90(n, sigma_at, virtual_index);
    let (held_median, held_p90) = median_p90(n, held_at, virtual_index);
    // numpy's sum reduction starts from its identity, +0.
    let count = n as f64;
    Ok(TrustFigures {
        pixels: n,
        sigma_median,
        sigma_p90,
        sigma_rms: ((0.0 + squares) / count).sqrt(),
        held_mean: (0.0 + errors) / count,
        held_median,
        held_p90,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small deterministic generator (xorshift64*), values in [0, 1).
    fn uniform(state: &mut u64) -> f64 {
        *state ^= *state >> 12;
        *state ^= *state << 25;
        *state ^= *state >> 27;
        (state.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64
    }

    /// The order statistics by sorting a copy (the reference of the selection).
    fn sorted_figures(values: &[f64]) -> (f64, f64) {
        let mut v = values.to_vec();
        v.sort_by(f64::total_cmp);
        let n = v.len();
        let (ranks, virtual_index) = wanted_ranks(n);
        median_p90(n, ranks.map(|r| v[r]), virtual_index)
    }

    #[test]
    fn keys_keep_the_order_and_invert() {
        let values = [
            f32::MIN,
            -3.5,
            -1e-30,
            -0.0,
            0.0,
            1e-40,
            1e-30,
            2.0,
            7.25,
            f32::MAX,
        ];
        for pair in values.windows(2) {
            assert!(pair[0].key() < pair[1].key(), "{pair:?}");
        }
        for v in values {
            assert_eq!(f32::of_key(v.key()).to_bits(), v.to_bits());
            let w = f64::from(v);
            assert_eq!(f64::of_key(w.key()).to_bits(), w.to_bits());
        }
    }

    #[test]
    fn the_selection_finds_the_sorted_order_statistics() {
        // Several seeds and sizes, with ties (values on a coarse grid) and negative values.
        for seed in 1..=6u64 {
            let mut state = seed * 0x9e37_79b9_7f4a_7c15;
            for n in [1usize, 2, 3, 7, 8, 9, 10, 11, 127, 128, 129, 1000, 4099] {
                let coarse = seed % 2 == 0;
                let sigma: Vec<f32> = (0..n)
                    .map(|_| {
                        let u = uniform(&mut state);
                        if coarse {
                            (u * 8.0).floor() as f32 - 3.0
                        } else {
                            (u * 40.0 - 5.0) as f32
                        }
                    })
                    .collect();
                let held: Vec<f32> = (0..n).map(|_| uniform(&mut state) as f32).collect();
                let mask = vec![true; n];
                let t = trust_figures(&mask, &sigma, &held).unwrap();
                assert_eq!(t.pixels, n);
                let s: Vec<f64> = sigma.iter().map(|&v| f64::from(v)).collect();
                let h: Vec<f64> = held.iter().map(|&v| f64::from(v)).collect();
                assert_eq!((t.sigma_median, t.sigma_p90), sorted_figures(&s), "n {n}");
                assert_eq!((t.held_median, t.held_p90), sorted_figures(&h), "n {n}");
                // float64 maps: four passes of the selection, the same figures.
                let t64 = trust_figures(&mask, &s, &h).unwrap();
                assert_eq!(t64, t);
            }
        }
    }

    #[test]
    fn the_mask_and_non_finite_values_leave_pixels_out() {
        let sigma = [1.0f32, f32::NAN, 3.0, 4.0, 5.0, f32::INFINITY];
        let held = [0.5f32, 0.5, f32::NEG_INFINITY, 0.25, 0.125, 1.0];
        let mask = [true, true, true, false, true, true];
        let t = trust_figures(&mask, &sigma, &held).unwrap();
        // Pixels 0 and 4: sigma 1 and 5, held 0.5 and 0.125.
        assert_eq!(t.pixels, 2);
        assert_eq!((t.sigma_median, t.held_median), (3.0, 0.3125));
        assert_eq!(t.sigma_rms, 13f64.sqrt());
        assert_eq!(t.held_mean, 0.3125);
        assert_eq!(t.sigma_p90, 1.0 + 4.0 * 0.9);
        let none = trust_figures(&[false; 6], &sigma, &held).unwrap();
        assert_eq!(none.pixels, 0);
        assert!(none.sigma_median.is_nan() && none.held_mean.is_nan());
        assert!(trust_figures(&mask[..5], &sigma, &held).is_err());
    }

    #[test]
    fn the_pairwise_sums_follow_the_recursion() {
        // Against a direct transcription of the recursion on a slice, for sizes around the
        // block and the halving's rounding.
        fn reference(v: &[f64]) -> f64 {
            let n = v.len();
            if n < 8 {
                v.iter().fold(0.0, |s, &x| s + x)
            } else if n <= BLOCK {
                let mut r: [f64; 8] = std::array::from_fn(|j| v[j]);
                let whole = n - n % 8;
                let mut i = 8;
                while i < whole {
                    for j in 0..8 {
                        r[j] += v[i + j];
                    }
                    i += 8;
                }
                let mut s = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
                for &x in &v[whole..] {
                    s += x;
                }
                s
            } else {
                let m = n / 2 - (n / 2) % 8;
                reference(&v[..m]) + reference(&v[m..])
            }
        }
        let mut state = 7u64;
        for n in [
            0usize, 1, 5, 8, 15, 16, 127, 128, 129, 136, 255, 256, 257, 1000, 5003,
        ] {
            let v: Vec<f64> = (0..n).map(|_| uniform(&mut state) * 1e3 - 1.0).collect();
            let (a, b) = pairwise_sums(n, &mut v.iter().map(|&x| (x, -x)));
            assert_eq!(a, reference(&v));
            assert_eq!(b, -reference(&v));
        }
    }
}
