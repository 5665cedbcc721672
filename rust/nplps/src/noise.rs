//! Estimate of the image noise: the standard deviation of additive sensor noise in a stack.
//!
//! # The maths
//!
//! Each image plane (one light, one channel) is filtered with the 3 x 3 high-pass kernel
//!
//! ```text
//!            [ 1 -2  1]
//! K = 1/6 *  [-2  4 -2]  =  1/6 * d2x (x) d2y,   d2 = [1, -2, 1],
//!            [ 1 -2  1]
//! ```
//!
//! the product of the second differences along the rows and along the columns. It annihilates
//! every polynomial `x^a y^b` with `a < 2` or `b < 2` (all polynomials up to degree 3 but
//! `x^2 y^2`), so a smooth shading leaves a residual of the order of its fourth derivatives:
//! about 1e-8 to 1e-6 of the image maximum on the synthetic renders, where the 4-neighbour
//! Laplacian leaves 1e-4. White noise of standard deviation `sigma` passes with the variance
//! `sigma^2 * sum K^2 = sigma^2 * 36 / 36 = sigma^2`: the residual `r` of a window is `N(0,
//! sigma^2)` plus the small signal leak. Edges (of the mask, of albedo, of cast shadows) and
//! specks (highlights) give large residuals in some windows, which the lower quartile of the
//! absolute residuals ignores as long as they are fewer than 3 in 4 (a speck in 10 % of the
//! observations touches 61 % of the 3 x 3 windows, which would carry the median away):
//!
//! `sigma = q_1/4(|r|) / Phi^-1(5/8)`, with `Phi^-1(5/8) = 0.3186` (the lower quartile of
//! `|N(0, 1)|`).
//!
//! Windows are used only when all 9 values are inside the mask, finite (NaN marks a missing
//! observation) and positive: images clipped at black have no Gaussian noise where the signal is
//! 0, and a window touching a clipped value would shrink the residual.
//!
//! Two passes restrict the estimate to the darkest observations, where it matters for the shadow
//! threshold (shot noise grows with the signal, and so does the high-pass leak of the shading):
//! the first pass takes all windows (`sigma_0`); the second the windows whose mean is at least
//! `4 sigma_0` (clipping at black is then negligible, `Phi(-4) = 3e-5`) and at most the lower
//! quartile of those means. With fewer than [`MIN_WINDOWS`] such windows the first pass stands.
//!
//! Medians and quartiles are found by selection, so the estimate takes time linear in the
//! observations; at most [`MAX_WINDOWS`] evenly strided windows are measured, which bounds the
//! memory to 8 MiB (the estimate's relative standard error is about `1.25 / sqrt(n)`, 0.1 % there).
//!
//! An estimate below [`ZERO_BELOW`] times the largest value is returned as exactly 0: noise-free
//! renders (whose high-pass leak is 1e-8 to 1e-5 of the maximum from 48 x 48 pixels up, 8e-5 for
//! the bumps at 32 x 32) then keep a shadow threshold of exactly 0. Noise that small does not
//! matter for the threshold (3 sigma = 3e-4 of the range: 20 levels of a 16-bit image, 0.08 of
//! an 8-bit level); real sensors are noisier.

use rayon::prelude::*;

use crate::error::{ensure_shape, Result};
use crate::grid::Grid;
use crate::local::{Observations, Stored};
use crate::memory::{try_vec, try_with_capacity};
use crate::problem::{u16_value, ImageStack, Samples};

/// `Phi^-1(5/8)`: the lower quartile of `|N(0, 1)|`.
const QUARTILE_SCALE: f64 = 0.318_639_363_964_375_4;

/// Estimates below this fraction of the largest value in the mask are returned as 0.
pub const ZERO_BELOW: f64 = 1e-4;

/// The second pass is used when at least this many windows qualify.
pub const MIN_WINDOWS: usize = 256;

/// At most this many windows are measured (evenly strided over the stack).
pub const MAX_WINDOWS: usize = 1 << 20;

/// The standard deviation of the additive noise of `images` (on their scale), measured inside
/// `mask` (H * W flags, row-major; None: everywhere); see the [module documentation](self).
///
/// NaN values are missing observations and left out. Returns 0 when no 3 x 3 window of positive
/// values fits inside the mask, and when the estimate is below [`ZERO_BELOW`] of the largest
/// value (noise-free images).
///
/// # Errors
///
/// [`crate::Error::Shape`] when `mask` does not have H * W values; [`crate::Error::Memory`]
/// when its buffers (at most 16 MiB) cannot be allocated.
pub fn estimate_noise(images: &ImageStack<'_>, mask: Option<&[bool]>) -> Result<f64> {
    let (h, w, c) = (images.height, images.width, images.channels);
    if let Some(m) = mask {
        ensure_shape("mask", h * w, m.len(), || {
            format!(
                "the mask has {} values, expected H * W = {h} * {w} = {}",
                m.len(),
                h * w
            )
        })?;
    }
    let inside = |p: usize| mask.is_none_or(|m| m[p]);
    let data = images.data;
    let planes = images.k * c;
    let value = |plane: usize, p: usize| {
        let (i, ch) = (plane / c, plane % c);
        data.get((i * h * w + p) * c + ch)
    };
    let top = largest(&data, h * w, c, mask) as f64;
    if h < 3 || w < 3 || top <= 0.0 {
        return Ok(0.0);
    }
    // Window centres: (h - 2) * (w - 2) per plane, numbered plane by plane; every stride-th of
    // them is measured, at most MAX_WINDOWS in all. NaN marks a window that cannot be used.
    let centres = (h - 2) * (w - 2);
    let total = centres.saturating_mul(planes);
    let stride = total.div_ceil(MAX_WINDOWS).max(1);
    let what = "estimating the image noise";
    let mut windows: Vec<(f32, f32)> = try_vec(total.div_ceil(stride), (f32::NAN, 0.0), what)?;
    windows.par_iter_mut().enumerate().for_each(|(t, slot)| {
        let g = t * stride;
        let (plane, j) = (g / centres, g % centres);
        let (y, x) = (j / (w - 2) + 1, j % (w - 2) + 1);
        let mut r = 0.0f64;
        let mut sum = 0.0f64;
        for (dy, ky) in [(0usize, 1.0f64), (1, -2.0), (2, 1.0)] {
            for (dx, kx) in [(0usize, 1.0f64), (1, -2.0), (2, 1.0)] {
                let p = (y + dy - 1) * w + (x + dx - 1);
                if !inside(p) {
                    return;
                }
                let v = value(plane, p);
                // Also false for NaN.
                if !(v > 0.0 && v.is_finite()) {
                    return;
                }
                r += ky * kx * v as f64;
                sum += v as f64;
            }
        }
        *slot = ((r / 6.0).abs() as f32, (sum / 9.0) as f32);
    });
    let used = windows.iter().filter(|(r, _)| !r.is_nan()).count();
    if used == 0 {
        return Ok(0.0);
    }
    let mut residuals: Vec<f32> = try_with_capacity(used, what)?;
    residuals.extend(windows.iter().map(|&(r, _)| r).filter(|r| !r.is_nan()));
    let sigma0 = quantile(&mut residuals, 0.25) as f64 / QUARTILE_SCALE;
    let floor = (4.0 * sigma0) as f32;
    let bright = |&&(r, m): &&(f32, f32)| !r.is_nan() && m >= floor;
    // The residuals' buffer is reused for the means, then for the darkest windows' residuals.
    residuals.clear();
    residuals.extend(windows.iter().filter(bright).map(|&(_, m)| m));
    let mut sigma = sigma0;
    if residuals.len() >= MIN_WINDOWS {
        let quartile = quantile(&mut residuals, 0.25);
        residuals.clear();
        residuals.extend(
            windows
                .iter()
                .filter(bright)
                .filter(|&&(_, m)| m <= quartile)
                .map(|&(r, _)| r),
        );
        if residuals.len() >= MIN_WINDOWS {
            sigma = quantile(&mut residuals, 0.25) as f64 / QUARTILE_SCALE;
        }
    }
    Ok(if sigma < ZERO_BELOW * top { 0.0 } else { sigma })
}

/// About this many 3 x 3 windows measure the noise of a level's images for the glossy fits
/// (see [`observation_variance`]): all its images cost 0.1 CPU s at 1 MP with 16 lights
/// (1 M windows, the estimator's cap), a noticeable share of a noise-free glossy run.
pub(crate) const NOISE_WINDOWS: usize = 1 << 18;

/// The variance of the additive noise of an observation of `obs` (the sum of its channels: `C
/// sigma^2`), with `sigma` measured by [`estimate_noise`] in the first images (enough for about
/// [`NOISE_WINDOWS`] of its windows) inside `grid`'s facets (exactly 0 on noise-free renders,
/// and where it cannot be measured or its buffers cannot be allocated).
pub(crate) fn observation_variance(obs: &Observations<'_>, grid: &Grid) -> f64 {
    let (height, width) = (grid.height, grid.width);
    if obs.plane != height * width * obs.channels {
        return 0.0;
    }
    // The first images only, about `NOISE_WINDOWS` windows (all of them below): the
    // estimate's relative standard error is then about 0.25 %, and its cost a few ms.
    let k = obs.k.min((NOISE_WINDOWS / (height * width).max(1)).max(1));
    let data = match &obs.data {
        Stored::F32(d) => Samples::F32(&d[..k * obs.plane]),
        Stored::U16(d) => Samples::U16(&d[..k * obs.plane]),
    };
    let stack = ImageStack {
        data,
        k,
        height,
        width,
        channels: obs.channels,
    };
    let Ok(mut mask) = try_vec(height * width, false, "the noise estimate's mask") else {
        return 0.0;
    };
    for &p in &grid.facets {
        mask[p as usize] = true;
    }
    match estimate_noise(&stack, Some(&mask)) {
        Ok(sigma) if sigma.is_finite() => obs.channels as f64 * sigma * sigma,
        _ => 0.0,
    }
}

/// Values per block of [`largest`]: one running maximum per position in the block, so that the
/// comparisons of a block run in vector lanes.
const BLOCK: usize = 16;

/// The largest finite value of `data` (planes of `hw` pixels with `channels` interleaved
/// values each) at the pixels inside `mask`, or 0 when none is positive: `max(0, max v)` over
/// those values. The maximum of a set does not depend on the order it is taken in (ties are
/// equal values), so the planes are split over the threads and each is scanned in blocks of
/// [`BLOCK`] with one running maximum per position; a 16-bit stack takes the largest integer
/// and converts it once (`v -> v / 65535` is increasing, so the largest value is the value of
/// the largest integer). NaN marks missing observations and is never larger.
fn largest(data: &Samples<'_>, hw: usize, channels: usize, mask: Option<&[bool]>) -> f32 {
    let planes = data.len() / hw.max(1);
    (0..planes)
        .into_par_iter()
        .map(|plane| {
            let (image, channel) = (plane / channels, plane % channels);
            let start = image * hw * channels;
            let end = start + hw * channels;
            match *data {
                Samples::F32(d) => {
                    plane_max(&d[start..end], channels, channel, mask, 0.0, |x, m| {
                        if x.is_finite() && x > m {
                            x
                        } else {
                            m
                        }
                    })
                }
                Samples::U16(d) => u16_value(plane_max(
                    &d[start..end],
                    channels,
                    channel,
                    mask,
                    0,
                    u16::max,
                )),
            }
        })
        .reduce(|| 0.0, f32::max)
}

/// `max_with(... max_with(x_0, zero) ..., m)` over the values `x_p = image[p * channels +
/// channel]` of one image's pixels `p` inside `mask`. `max_with(x, m)` is a maximum, so the
/// order does not matter: a grey image is taken in blocks of [`BLOCK`] pixels with one running
/// value per position in the block (vector lanes, no bounds checks), combined at the end.
#[inline(always)]
fn plane_max<T: Copy>(
    image: &[T],
    channels: usize,
    channel: usize,
    mask: Option<&[bool]>,
    zero: T,
    max_with: impl Fn(T, T) -> T + Copy,
) -> T {
    if channels != 1 {
        let values = image.iter().skip(channel).step_by(channels);
        return match mask {
            None => values.fold(zero, |m, &x| max_with(x, m)),
            Some(mask) => values.zip(mask).fold(
                zero,
                |m, (&x, &inside)| if inside { max_with(x, m) } else { m },
            ),
        };
    }
    let mut run = [zero; BLOCK];
    let blocks = image.chunks_exact(BLOCK);
    let rest = blocks.remainder();
    let mut m = zero;
    match mask {
        None => {
            for block in blocks {
                for (r, &x) in run.iter_mut().zip(block) {
                    *r = max_with(x, *r);
                }
            }
            m = rest.iter().fold(m, |m, &x| max_with(x, m));
        }
        Some(mask) => {
            let inside = mask.chunks_exact(BLOCK);
            let rest_inside = inside.remainder();
            for (block, inside) in blocks.zip(inside) {
                for ((r, &x), &inside) in run.iter_mut().zip(block).zip(inside) {
                    let y = max_with(x, *r);
                    *r = if inside { y } else { *r };
                }
            }
            for (&x, &inside) in rest.iter().zip(rest_inside) {
                m = if inside { max_with(x, m) } else { m };
            }
        }
    }
    run.into_iter().fold(m, |a, b| max_with(b, a))
}

/// The `q` quantile (lower) of `values` by selection (reorders them); `values` is not empty.
fn quantile(values: &mut [f32], q: f64) -> f32 {
    let i = ((values.len() - 1) as f64 * q).round() as usize;
    *values.select_nth_unstable_by(i, f32::total_cmp).1
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A deterministic Gaussian generator (xorshift64* and Box-Muller).
    struct Gauss(u64);

    impl Gauss {
        fn uniform(&mut self) -> f64 {
            self.0 ^= self.0 >> 12;
            self.0 ^= self.0 << 25;
            self.0 ^= self.0 >> 27;
            let x = self.0.wrapping_mul(0x2545_f491_4f6c_dd1d);
            ((x >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        }
        fn normal(&mut self) -> f64 {
            let (u, v) = (self.uniform(), self.uniform());
            (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
        }
    }

    /// k smooth shaded images (a lit dome, a dark quarter clipped at black, an albedo edge),
    /// with noise of `sigma` times the maximum, clipped at 0 as a sensor does.
    fn shaded(k: usize, n: usize, sigma: f64, seed: u64) -> (Vec<f32>, Vec<bool>) {
        let mut rng = Gauss(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1);
        let mut images = Vec::with_capacity(k * n * n);
        for i in 0..k {
            let a = i as f64 / k as f64 * std::f64::consts::TAU;
            let (lx, ly) = (0.6 * a.cos(), 0.6 * a.sin());
            for y in 0..n {
                for x in 0..n {
                    let (u, v) = (x as f64 / n as f64 - 0.5, y as f64 / n as f64 - 0.5);
                    let nz = (1.0 - 1.5 * (u * u + v * v)).max(0.0).sqrt();
                    let shade = (u * lx + v * ly + 0.8 * nz).max(0.0);
                    let albedo = if x < n / 3 { 0.5 } else { 0.9 };
                    let signal = if u > 0.25 && v > 0.25 {
                        0.0
                    } else {
                        albedo * shade
                    };
                    images.push((signal + sigma * rng.normal()).max(0.0) as f32);
                }
            }
        }
        let mask = (0..n * n).map(|p| p % n != 0).collect();
        (images, mask)
    }

    fn estimate(images: &[f32], k: usize, n: usize, mask: Option<&[bool]>) -> f64 {
        let stack = ImageStack::new(images, k, n, n).unwrap();
        estimate_noise(&stack, mask).unwrap()
    }

    #[test]
    fn noise_free_images_give_exactly_zero() {
        for seed in 0..3 {
            let (images, mask) = shaded(8, 64, 0.0, seed);
            assert_eq!(estimate(&images, 8, 64, Some(&mask)), 0.0);
            assert_eq!(estimate(&images, 8, 64, None), 0.0);
        }
    }

    #[test]
    fn gaussian_noise_is_measured_within_ten_percent() {
        for seed in 0..5 {
            for sigma in [0.002, 0.005, 0.01, 0.02] {
                let (images, mask) = shaded(8, 64, sigma, seed);
                let top = images.iter().copied().fold(0.0f32, f32::max) as f64;
                // The signal's maximum is below 1; sigma is relative to the signal's scale.
                assert!(top > 0.5);
                let got = estimate(&images, 8, 64, Some(&mask));
                assert!(
                    (got / sigma - 1.0).abs() < 0.1,
                    "seed {seed}, sigma {sigma}: estimated {got}"
                );
            }
        }
    }

    #[test]
    fn nan_values_are_left_out() {
        let (mut images, mask) = shaded(6, 48, 0.01, 7);
        for v in images.iter_mut().step_by(17) {
            *v = f32::NAN;
        }
        let got = estimate(&images, 6, 48, Some(&mask));
        assert!((got / 0.01 - 1.0).abs() < 0.15, "estimated {got}");
    }

    #[test]
    fn colour_channels_are_planes() {
        let (grey, _) = shaded(6, 48, 0.01, 3);
        let rgb: Vec<f32> = grey.iter().flat_map(|&v| [v, v, v]).collect();
        let stack = ImageStack::with_channels(&rgb, 6, 48, 48, 3).unwrap();
        let got = estimate_noise(&stack, None).unwrap();
        assert!((got - estimate(&grey, 6, 48, None)).abs() < 1e-4, "{got}");
    }

    #[test]
    fn tiny_or_empty_inputs_give_zero_and_a_wrong_mask_is_refused() {
        let images = vec![0.5f32; 2 * 2 * 2];
        assert_eq!(estimate(&images, 2, 2, None), 0.0);
        let (images, _) = shaded(2, 16, 0.01, 1);
        assert_eq!(estimate(&images, 2, 16, Some(&[false; 256])), 0.0);
        let stack = ImageStack::new(&images, 2, 16, 16).unwrap();
        let err = estimate_noise(&stack, Some(&[true; 10])).unwrap_err();
        assert!(matches!(err, crate::Error::Shape { what: "mask", .. }));
    }

    #[test]
    fn large_stacks_are_strided() {
        // 20 * 254 * 254 = 1.29 M windows: every second one is measured.
        let (images, mask) = shaded(20, 256, 0.01, 4);
        let got = estimate(&images, 20, 256, Some(&mask));
        assert!((got / 0.01 - 1.0).abs() < 0.05, "estimated {got}");
    }

    #[test]
    fn specks_in_a_tenth_of_the_observations_are_ignored() {
        for seed in 0..3 {
            for sigma in [0.0, 0.005] {
                let (mut images, mask) = shaded(8, 64, sigma, seed);
                let mut rng = Gauss(seed + 100);
                for v in images.iter_mut() {
                    if rng.uniform() < 0.1 {
                        *v += 0.4;
                    }
                }
                let got = estimate(&images, 8, 64, Some(&mask));
                if sigma == 0.0 {
                    assert_eq!(got, 0.0, "seed {seed}");
                } else {
                    // 61 % of the windows touch a speck: the quartile is the clean residuals'
                    // 64th percentile, about 2.9 times their lower quartile.
                    assert!(got > sigma && got < 3.5 * sigma, "seed {seed}: {got}");
                }
            }
        }
    }

    /// The plain maximum [`largest`] replaces: `max(0, max v)` over the finite values inside the
    /// mask, pixel after pixel.
    fn plain_largest(data: &Samples<'_>, hw: usize, c: usize, mask: Option<&[bool]>) -> f32 {
        (0..data.len())
            .filter(|&i| mask.is_none_or(|m| m[(i / c) % hw]))
            .map(|i| data.get(i))
            .filter(|v| v.is_finite())
            .fold(0.0f32, f32::max)
    }

    #[test]
    fn largest_is_the_plain_maximum_bit_for_bit() {
        // Sizes around the block length, one and three channels, with and without a mask,
        // negative, infinite and NaN values (float32) and 16-bit values; several seeds.
        for seed in 0..6u64 {
            let mut rng = Gauss(seed * 7919 + 1);
            for (h, w) in [(1, 1), (3, 5), (4, 4), (7, 9), (16, 17), (31, 33)] {
                let hw = h * w;
                for c in [1, 3] {
                    let k = 1 + (seed as usize % 4);
                    let n = k * hw * c;
                    let f: Vec<f32> = (0..n)
                        .map(|_| match (rng.uniform() * 20.0) as u32 {
                            0 => f32::NAN,
                            1 => f32::INFINITY,
                            2 => f32::NEG_INFINITY,
                            3 => -0.0,
                            _ => (rng.normal() * 0.3) as f32,
                        })
                        .collect();
                    let u: Vec<u16> = (0..n).map(|_| (rng.uniform() * 65536.0) as u16).collect();
                    let m: Vec<bool> = (0..hw).map(|_| rng.uniform() < 0.7).collect();
                    let none = vec![false; hw];
                    for data in [Samples::F32(&f), Samples::U16(&u)] {
                        for mask in [None, Some(&m[..]), Some(&none[..])] {
                            let got = largest(&data, hw, c, mask);
                            let want = plain_largest(&data, hw, c, mask);
                            // Equal values; a maximum of 0 may be either zero.
                            assert!(
                                got.to_bits() == want.to_bits() || (got == 0.0 && want == 0.0),
                                "seed {seed} {h}x{w}x{c}: {got} vs {want}"
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn quantile_by_selection() {
        assert_eq!(quantile(&mut [4.0f32, 1.0, 3.0, 2.0, 5.0], 0.25), 2.0);
    }

    /// The synthetic scenes (cast shadows on for the block), noise-free and with Gaussian noise of
    /// 0.2 to 2 % of the maximum, clipped at 0 as `nplps.make_scene(..., noise=...)` does.
    #[cfg(feature = "synth")]
    #[test]
    fn synthetic_scenes_noise_free_and_noisy() {
        use crate::{RenderOptions, Scene, SceneKind, SceneOptions};
        for kind in SceneKind::ALL {
            for seed in 0..3u64 {
                let options = SceneOptions::default().with_pinhole(seed % 2 == 1);
                let scene = Scene::with_options(kind, 64, 100.0, 200.0, seed, options).unwrap();
                let shadows = RenderOptions::default().with_cast_shadows(kind == SceneKind::Block);
                let clean = crate::render_with(&scene.rig, &scene.surface(), &shadows).unwrap();
                let k = scene.rig.n_lights();
                let top = clean.iter().copied().fold(0.0, f64::max);
                let f32s: Vec<f32> = clean.iter().map(|&v| v as f32).collect();
                let got = estimate(&f32s, k, 64, Some(&scene.mask));
                assert_eq!(got, 0.0, "{kind:?} seed {seed}: noise-free estimate {got}");
                let mut rng = Gauss(seed + 11);
                for noise in [0.002, 0.005, 0.02] {
                    let sigma = noise * top;
                    let noisy: Vec<f32> = clean
                        .iter()
                        .map(|&v| (v + sigma * rng.normal()).max(0.0) as f32)
                        .collect();
                    let got = estimate(&noisy, k, 64, Some(&scene.mask));
                    assert!(
                        (got / sigma - 1.0).abs() < 0.15,
                        "{kind:?} seed {seed} noise {noise}: {got} for {sigma}"
                    );
                }
            }
        }
    }
}
