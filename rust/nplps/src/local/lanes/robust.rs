//! The robust local fits (iteratively reweighted least squares, [`Robust::Cauchy`] and
//! [`Robust::Tukey`]) of [`LANES`] facets at once, one SIMD lane per facet, grey and colour:
//! the fits of the scalar `Facet::fit` with a robust estimator, bit for bit.
//!
//! Per facet (one lane) the fit is that of the scalar code. With `b_k = beta_k(c)` (the lane
//! form of the light, [`LaneLight::beta`]), `p_kc` the light's intensity in channel `c` and
//! `r_kc = p_kc b_k`, the weighted normal equations of channel `c` are
//!
//! ```text
//! T_c = sum_k w_k r_kc r_kc^T,   s_c = sum_k w_k I_kc r_kc
//! ```
//!
//! over the usable lights (every channel strictly between `dark` and `saturation`, not NaN),
//! each term added as `(w r_i) r_j` and `(w r_i) I` in light order. The first fit has `w = 1`;
//! its solve is `solve_sums`'s (grey: `g = T^-1 s`, `n = g / |g|`, `rho = |g|`; colour: the
//! three solves, `n = normalize(g_0 + g_1 + g_2)`, `rho_c = (n . s_c) / (n . T_c n)`, the
//! product `T_c n` summed column after column and the dots as `(a + b) + c`, as nalgebra does).
//! Then, [`IRLS_ITERATIONS`] times at most, each lane takes the RMS residual of every usable
//! light, `e_k = sqrt(sum_c (rho_c p_kc (n . b_k) - I_kc)^2 / C)`, its scale
//! `sigma = max(1.4826 median_k e_k, 1e-9 max I, MIN_POSITIVE)` (the median of the facet's own
//! usable residuals, chosen per lane: the per-facet scale stays per facet) and the weights
//! `w_k = robust_weight(e_k, sigma)` (0 for unusable lights); a lane stops when fewer than 3
//! lights keep a positive weight, or when the reweighted system fails to solve (it keeps its
//! previous fit), as the scalar loop breaks. The fit's residual is `sum_k sum_c e_kc^2` at the
//! final fit.
//!
//! Why the bits agree: each lane's sums run over the lights in the scalar order, one term per
//! light and channel; a term the scalar code skips (an unusable light, a zero weight) is added
//! as `+0.0`, which changes no sum (the sums start at `+0.0` and never become `-0.0` under
//! round-to-nearest); the median is an order statistic, the same value whichever selection
//! finds it; the solves and targets are the shared lane forms ([`solve_spd3_lanes`],
//! [`Geometry::plane_targets`]) whose lanes are the scalar code's bits. The test
//! `robust_lanes_match_the_scalar_fits_exactly` checks it over random facets.
//!
//! Applies with a robust estimator, unit (image) weights, the Lambertian model without indirect
//! light and lights with a lane form ([`LaneLight::from_light`]); the paper weighting, the
//! glossy model, interreflections and parallel lights keep the scalar fits.
//!
//! [`solve_spd3_lanes`]: crate::local::solve_spd3_lanes

use super::{lane_values, LANES, SCRATCH};
use crate::error::Result;
use crate::geometry::{quad_centre, Geometry};
use crate::light::{channel_intensity, LaneLight};
use crate::local::{
    keep_shape, robust_weight, solve_spd3_lanes, FacetFit, LocalStep, Model, Robust, Weighting,
    IRLS_ITERATIONS,
};
use crate::memory::try_vec;

/// The lights of the robust lanes: their lane forms and, per light, the intensity `p_kc` in each
/// of the images' channels ([`channel_intensity`]; grey images: the mean, in the first entry).
pub(in crate::local) struct RobustLights {
    lights: Vec<LaneLight>,
    intensity: Vec<[f64; 3]>,
}

/// A thread's scratch space of the robust lanes, sized for `k` lights and `channels` channels.
pub(in crate::local) struct RobustScratch {
    /// One facet's observations (for the scalar fits of a partial batch and failed lanes).
    pub(in crate::local) buf: Vec<f32>,
    /// The observations of the batch, `values[k * channels + c][lane]`.
    values: Vec<[f32; LANES]>,
    /// The batch's working arrays, one entry per light.
    work: Vec<LightLanes>,
    /// One lane's usable residuals, for its median.
    sorted: Vec<f64>,
}

/// One light's numbers in the [`LANES`] facets of a batch.
#[derive(Clone, Copy, Default)]
struct LightLanes {
    /// `beta_k(c)` per lane.
    beta: [[f64; LANES]; 3],
    /// Whether the observation is usable (every channel).
    usable: [bool; LANES],
    /// The RMS residual over the channels of the current fit (any value where unusable).
    rms: [f64; LANES],
    /// The robust weight (0 where unusable).
    weight: [f64; LANES],
}

impl RobustScratch {
    /// The scratch space of a step with `k` lights and `channels` channels per observation.
    pub(in crate::local) fn new(k: usize, channels: usize) -> Result<RobustScratch> {
        Ok(RobustScratch {
            buf: try_vec(k * channels, 0.0f32, SCRATCH)?,
            values: try_vec(k * channels, [0.0f32; LANES], SCRATCH)?,
            work: try_vec(k, LightLanes::default(), SCRATCH)?,
            sorted: try_vec(k, 0.0f64, SCRATCH)?,
        })
    }
}

impl LocalStep<'_> {
    /// The lights of the robust lanes, when they apply: a robust estimator, unit weights, the
    /// Lambertian model of the rig's lights without indirect light, grey or colour images, and
    /// lights with a lane form.
    pub(in crate::local) fn robust_lane_lights(&self) -> Option<RobustLights> {
        let s = self.settings;
        let channels = self.obs.channels;
        let eligible = s.robust != Robust::None
            && s.weighting == Weighting::Image
            && s.lobe.is_none()
            && self.indirect.is_none()
            && matches!(channels, 1 | 3);
        let Model::Near(lights) = self.model else {
            return None;
        };
        if !eligible {
            return None;
        }
        let lanes: Option<Vec<LaneLight>> = lights.iter().map(LaneLight::from_light).collect();
        let intensity = lights
            .iter()
            .map(|light| {
                let phi = light.intensity();
                crate::lanes(|c| match c < channels {
                    true => channel_intensity(phi, channels, c),
                    false => 0.0,
                })
            })
            .collect();
        Some(RobustLights {
            lights: lanes?,
            intensity,
        })
    }

    /// The robust fits of facets `first..first + fits.len()` (at most [`LANES`]): a full batch
    /// in the lanes, a partial one with the scalar fits (the same bits).
    pub(in crate::local) fn fit_robust_batch(
        &self,
        lights: &RobustLights,
        first: usize,
        u: &[f64],
        scratch: &mut RobustScratch,
        fits: &mut [FacetFit],
    ) {
        if fits.len() == LANES {
            let lanes = self.fit_robust_lanes(lights, first, u, scratch);
            fits.copy_from_slice(&lanes);
        } else {
            for (i, fit) in fits.iter_mut().enumerate() {
                let glossy = &mut self.settings.packed();
                *fit = self.fit(first + i, u, &mut scratch.buf, glossy, None);
            }
        }
    }

    /// The robust fits of facets `first..first + LANES` in the lanes (see the module
    /// documentation).
    fn fit_robust_lanes(
        &self,
        lights: &RobustLights,
        first: usize,
        u: &[f64],
        scratch: &mut RobustScratch,
    ) -> [FacetFit; LANES] {
        let (grid, geometry, obs) = (self.grid, self.geometry, self.obs);
        let channels = obs.channels;
        let pixels: [usize; LANES] = crate::lanes(|l| grid.facets[first + l] as usize);
        let batch = self.batch_corners(first, &pixels, u);
        let quads = &batch.quads;
        let centres: [[f64; 3]; LANES] = crate::lanes(|l| quad_centre(&quads[l]));
        let values = &mut scratch.values;
        if !obs.gather_lanes(&pixels, values) {
            for (l, &pixel) in pixels.iter().enumerate() {
                let facet = obs.facet(pixel, &mut scratch.buf);
                for (slot, &v) in values.iter_mut().zip(facet) {
                    slot[l] = v;
                }
            }
        }
        if let Some(shadows) = self.shadows {
            for (l, &pixel) in pixels.iter().enumerate() {
                for k in shadows.lights_at(pixel) {
                    for slot in &mut values[k * channels..(k + 1) * channels] {
                        slot[l] = f32::NAN;
                    }
                }
            }
        }
        let input = RobustInput {
            lights: &lights.lights,
            intensity: &lights.intensity,
            robust: self.settings.robust,
            thresholds: (self.settings.dark, self.settings.saturation),
            centres: &centres,
            base: &batch.base,
            geometry,
        };
        let (values, work, sorted) = (&scratch.values[..], &mut scratch.work, &mut scratch.sorted);
        let out = match channels {
            1 => robust_grey_dispatch(&input, values, work, sorted),
            _ => robust_colour_dispatch(&input, values, work, sorted),
        };
        std::array::from_fn(|l| match out.valid[l] {
            true => FacetFit {
                target: out.target[l],
                normal: [out.normal[0][l], out.normal[1][l], out.normal[2][l]],
                albedo: match channels {
                    1 => [out.albedo[0][l]; 3],
                    _ => [out.albedo[0][l], out.albedo[1][l], out.albedo[2][l]],
                },
                specular: 0.0,
                sse: out.sse[l],
                used: out.used[l],
                valid: true,
            },
            false => keep_shape(&quads[l], batch.ids[l].map(|i| u[i as usize]), out.used[l]),
        })
    }
}

/// What the robust kernel reads of a batch besides the observations.
struct RobustInput<'a> {
    lights: &'a [LaneLight],
    intensity: &'a [[f64; 3]],
    robust: Robust,
    thresholds: (f64, f64),
    centres: &'a [[f64; 3]; LANES],
    base: &'a [[[f64; 2]; 4]; LANES],
    geometry: &'a Geometry,
}

/// The robust fits of [`LANES`] facets (0 or NaN in the lanes that are not `valid`).
struct RobustOut {
    normal: [[f64; LANES]; 3],
    /// Per channel (grey: the first row).
    albedo: [[f64; LANES]; 3],
    sse: [f64; LANES],
    used: [u32; LANES],
    valid: [bool; LANES],
    target: [[f64; 4]; LANES],
}

simd_dispatch! {
    wide
    /// [`robust_lanes`] of grey images with AVX-512 or AVX2 when the processor has it (same
    /// arithmetic, wider registers).
    fn robust_grey_dispatch => robust_grey(
        input: &RobustInput<'_>,
        values: &[[f32; LANES]],
        work: &mut [LightLanes],
        sorted: &mut Vec<f64>,
    ) -> RobustOut;
}

simd_dispatch! {
    wide
    /// [`robust_lanes`] of colour images with AVX-512 or AVX2 when the processor has it.
    fn robust_colour_dispatch => robust_colour(
        input: &RobustInput<'_>,
        values: &[[f32; LANES]],
        work: &mut [LightLanes],
        sorted: &mut Vec<f64>,
    ) -> RobustOut;
}

/// [`robust_lanes`] with one channel.
#[inline(always)]
fn robust_grey(
    input: &RobustInput<'_>,
    values: &[[f32; LANES]],
    work: &mut [LightLanes],
    sorted: &mut Vec<f64>,
) -> RobustOut {
    robust_lanes::<1>(input, values, work, sorted)
}

/// [`robust_lanes`] with three channels.
#[inline(always)]
fn robust_colour(
    input: &RobustInput<'_>,
    values: &[[f32; LANES]],
    work: &mut [LightLanes],
    sorted: &mut Vec<f64>,
) -> RobustOut {
    robust_lanes::<3>(input, values, work, sorted)
}

/// The current fit of [`LANES`] facets: unit normal and albedo per channel.
#[derive(Clone, Copy)]
struct LaneFit {
    normal: [[f64; LANES]; 3],
    albedo: [[f64; LANES]; C_MAX],
}

/// The most channels of an observation.
const C_MAX: usize = 3;

/// The robust fits of [`LANES`] facets with `C` channels (`values[k * C + c][lane]`; see the
/// module documentation), with `work` (one entry per light) and `sorted` as scratch.
#[inline(always)]
fn robust_lanes<const C: usize>(
    input: &RobustInput<'_>,
    values: &[[f32; LANES]],
    work: &mut [LightLanes],
    sorted: &mut Vec<f64>,
) -> RobustOut {
    let (dark, saturation) = input.thresholds;
    let k = input.lights.len();
    let work = &mut work[..k];
    // The rows, the usable lights and each lane's largest observation (NaN ignored, the floor
    // of its scale), once per batch.
    let mut used = [0u32; LANES];
    for (j, (light, w)) in input.lights.iter().zip(work.iter_mut()).enumerate() {
        let ([a0, a1, a2], f) = light.beta(input.centres);
        w.beta = [
            crate::lanes(|l| a0[l] * f[l]),
            crate::lanes(|l| a1[l] * f[l]),
            crate::lanes(|l| a2[l] * f[l]),
        ];
        let mut usable = [true; LANES];
        for v in &values[j * C..(j + 1) * C] {
            let (_, ok) = lane_values(v, dark, saturation);
            for l in 0..LANES {
                usable[l] &= ok[l];
            }
        }
        w.usable = usable;
        w.weight = [1.0; LANES];
        for l in 0..LANES {
            used[l] += u32::from(usable[l]);
        }
    }
    let mut max_i = [0.0f32; LANES];
    for v in &values[..k * C] {
        for l in 0..LANES {
            max_i[l] = max_i[l].max(v[l]);
        }
    }
    let (mut fit, solved) = solve_robust::<C>(&accumulate_robust::<C>(input, values, work));
    let valid: [bool; LANES] = crate::lanes(|l| used[l] >= 3 && solved[l]);
    let mut live = valid;
    for _ in 0..IRLS_ITERATIONS {
        if !live.iter().any(|&x| x) {
            break;
        }
        residuals::<C>(input, values, work, &fit);
        // The scale of each live lane: the median of its usable residuals.
        let median = medians(work, &live, sorted);
        let mut sigma = [1.0f64; LANES];
        for l in 0..LANES {
            let floor = 1e-9 * max_i[l] as f64;
            sigma[l] = (1.4826 * median[l]).max(floor).max(f64::MIN_POSITIVE);
        }
        let positive = weights(input.robust, work, &sigma);
        for l in 0..LANES {
            live[l] &= positive[l] >= 3;
        }
        if !live.iter().any(|&x| x) {
            break;
        }
        let (next, solved) = solve_robust::<C>(&accumulate_robust::<C>(input, values, work));
        for l in 0..LANES {
            live[l] &= solved[l];
            if live[l] {
                for j in 0..3 {
                    fit.normal[j][l] = next.normal[j][l];
                }
                for c in 0..C {
                    fit.albedo[c][l] = next.albedo[c][l];
                }
            }
        }
    }
    let sse = residuals::<C>(input, values, work, &fit);
    let target = input
        .geometry
        .plane_targets(input.base, &fit.normal, input.centres);
    RobustOut {
        normal: fit.normal,
        albedo: fit.albedo,
        sse,
        used,
        valid,
        target,
    }
}

/// The normal equations of [`LANES`] facets with `C` channels: per channel `T_c` (its entries
/// `t00 t01 t02 t11 t12 t22`) and `s_c`, one lane each.
type Systems<const C: usize> = ([[[f64; LANES]; 6]; C], [[[f64; LANES]; 3]; C]);

/// The weighted normal equations of [`LANES`] facets with `C` channels: `T_c` (its entries
/// `t00 t01 t02 t11 t12 t22`) and `s_c` per channel, the terms of each usable light with a
/// nonzero weight added in light order, as `Facet::accumulate` adds them (`(w r_i) r_j`,
/// `(w r_i) I`; a skipped term is `+0.0`).
#[inline(always)]
fn accumulate_robust<const C: usize>(
    input: &RobustInput<'_>,
    values: &[[f32; LANES]],
    work: &[LightLanes],
) -> Systems<C> {
    let (dark, saturation) = input.thresholds;
    let mut t = [[[0.0f64; LANES]; 6]; C];
    let mut s = [[[0.0f64; LANES]; 3]; C];
    for (j, (w, p)) in work.iter().zip(input.intensity).enumerate() {
        let [b0, b1, b2] = &w.beta;
        let take: [bool; LANES] = crate::lanes(|l| w.usable[l] && w.weight[l] != 0.0);
        for c in 0..C {
            let (i, _) = lane_values(&values[j * C + c], dark, saturation);
            let p = p[c];
            let (t, s) = (&mut t[c], &mut s[c]);
            for l in 0..LANES {
                let r = [b0[l] * p, b1[l] * p, b2[l] * p];
                let wr = [w.weight[l] * r[0], w.weight[l] * r[1], w.weight[l] * r[2]];
                let pick = |x: f64| if take[l] { x } else { 0.0 };
                t[0][l] += pick(wr[0] * r[0]);
                t[1][l] += pick(wr[0] * r[1]);
                t[2][l] += pick(wr[0] * r[2]);
                t[3][l] += pick(wr[1] * r[1]);
                t[4][l] += pick(wr[1] * r[2]);
                t[5][l] += pick(wr[2] * r[2]);
                s[0][l] += pick(wr[0] * i[l]);
                s[1][l] += pick(wr[1] * i[l]);
                s[2][l] += pick(wr[2] * i[l]);
            }
        }
    }
    (t, s)
}

/// The fits of [`LANES`] facets' normal equations `(T_c, s_c)`, as `solve_sums` computes them
/// (see the module documentation), and whether each succeeded (every `T_c` regular, the
/// normal's length and the albedos finite and, for grey images, the albedo positive).
#[inline(always)]
fn solve_robust<const C: usize>((t, s): &Systems<C>) -> (LaneFit, [bool; LANES]) {
    let z = [0.0f64; LANES];
    let mut ok = [true; LANES];
    let mut g = [[z; 3]; C];
    for c in 0..C {
        let (regular, _, gc) = solve_spd3_lanes(&t[c], &s[c]);
        g[c] = gc;
        for l in 0..LANES {
            ok[l] &= regular[l];
        }
    }
    let mut fit = LaneFit {
        normal: [z; 3],
        albedo: [z; C_MAX],
    };
    if C == 1 {
        let g = &g[0];
        let mut rho = z;
        for l in 0..LANES {
            rho[l] = (g[0][l] * g[0][l] + g[1][l] * g[1][l] + g[2][l] * g[2][l]).sqrt();
            ok[l] &= rho[l].is_finite() && rho[l] > 0.0;
        }
        for (n, g) in fit.normal.iter_mut().zip(g) {
            for l in 0..LANES {
                n[l] = g[l] / rho[l];
            }
        }
        fit.albedo[0] = rho;
        return (fit, ok);
    }
    let mut sum = [z; 3];
    for (i, sum) in sum.iter_mut().enumerate() {
        for l in 0..LANES {
            sum[l] = g[0][i][l] + g[1 % C][i][l] + g[2 % C][i][l];
        }
    }
    let mut len = z;
    for l in 0..LANES {
        len[l] = (sum[0][l] * sum[0][l] + sum[1][l] * sum[1][l] + sum[2][l] * sum[2][l]).sqrt();
        ok[l] &= len[l].is_finite() && len[l] > 0.0;
    }
    for (n, sum) in fit.normal.iter_mut().zip(&sum) {
        for l in 0..LANES {
            n[l] = sum[l] / len[l];
        }
    }
    let n = &fit.normal;
    for c in 0..C {
        let [m11, m12, m13, m22, m23, m33] = &t[c];
        let s = &s[c];
        for l in 0..LANES {
            // `T_c n` column after column, then `n . (T_c n)` and `n . s_c`.
            let tn = [
                m11[l] * n[0][l] + m12[l] * n[1][l] + m13[l] * n[2][l],
                m12[l] * n[0][l] + m22[l] * n[1][l] + m23[l] * n[2][l],
                m13[l] * n[0][l] + m23[l] * n[1][l] + m33[l] * n[2][l],
            ];
            let den = n[0][l] * tn[0] + n[1][l] * tn[1] + n[2][l] * tn[2];
            let ns = n[0][l] * s[0][l] + n[1][l] * s[1][l] + n[2][l] * s[2][l];
            let a = ns / den;
            fit.albedo[c][l] = a;
            ok[l] &= a.is_finite();
        }
    }
    (fit, ok)
}

/// The residuals of the fits `fit` of [`LANES`] facets: each light's RMS over the channels
/// into its `rms` (the operations of `Facet::sq_residual`, `e = (rho_c p_kc) (n . b_k) - I_kc`,
/// `e^2` summed over the channels, divided by `C` and rooted); returns per lane the sum of the
/// usable lights' squared residuals (before the division), in light order.
#[inline(always)]
fn residuals<const C: usize>(
    input: &RobustInput<'_>,
    values: &[[f32; LANES]],
    work: &mut [LightLanes],
    fit: &LaneFit,
) -> [f64; LANES] {
    let (dark, saturation) = input.thresholds;
    let n = &fit.normal;
    let mut sse = [0.0f64; LANES];
    for (j, (w, p)) in work.iter_mut().zip(input.intensity).enumerate() {
        let [b0, b1, b2] = &w.beta;
        let nb: [f64; LANES] =
            crate::lanes(|l| n[0][l] * b0[l] + n[1][l] * b1[l] + n[2][l] * b2[l]);
        let mut sq = [0.0f64; LANES];
        for c in 0..C {
            let (i, _) = lane_values(&values[j * C + c], dark, saturation);
            for l in 0..LANES {
                let e = fit.albedo[c][l] * p[c] * nb[l] - i[l];
                sq[l] += e * e;
            }
        }
        for l in 0..LANES {
            w.rms[l] = (sq[l] / C as f64).sqrt();
            sse[l] += if w.usable[l] { sq[l] } else { 0.0 };
        }
    }
    sse
}

/// Per lane in `live`, the median of the usable lights' residuals `rms`: the element of rank
/// `m / 2` (from 0) of the `m` usable ones in [`f64::total_cmp`]'s order, selected as the
/// scalar code selects it (0 without a usable light, and in the lanes not `live`, where it
/// is not used). A selection per lane: ranks computed in the lanes (every pair of lights
/// compared, 8 lanes at a time) measured 5x slower for 27 lights and worse beyond.
#[inline(always)]
fn medians(work: &[LightLanes], live: &[bool; LANES], sorted: &mut Vec<f64>) -> [f64; LANES] {
    let mut median = [0.0f64; LANES];
    for l in (0..LANES).filter(|&l| live[l]) {
        sorted.clear();
        sorted.extend(work.iter().filter(|w| w.usable[l]).map(|w| w.rms[l]));
        if !sorted.is_empty() {
            let mid = sorted.len() / 2;
            median[l] = *sorted.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1;
        }
    }
    median
}

/// The robust weights of every light from its RMS residual and the lanes' scales `sigma`
/// ([`robust_weight`], 0 for the unusable lights); returns per lane the count of positive
/// weights.
#[inline(always)]
fn weights(robust: Robust, work: &mut [LightLanes], sigma: &[f64; LANES]) -> [u32; LANES] {
    // (one loop per estimator, so that the estimator is a constant of the loop)
    match robust {
        Robust::None => weights_with(work, sigma, |e, s| robust_weight(Robust::None, e, s)),
        Robust::Cauchy => weights_with(work, sigma, |e, s| robust_weight(Robust::Cauchy, e, s)),
        Robust::Tukey => weights_with(work, sigma, |e, s| robust_weight(Robust::Tukey, e, s)),
    }
}

/// [`weights`] with the estimator's weight function `weight(e, sigma)`.
#[inline(always)]
fn weights_with(
    work: &mut [LightLanes],
    sigma: &[f64; LANES],
    weight: impl Fn(f64, f64) -> f64,
) -> [u32; LANES] {
    let mut positive = [0u32; LANES];
    for w in work.iter_mut() {
        for l in 0..LANES {
            let x = weight(w.rms[l], sigma[l]);
            let x = if w.usable[l] { x } else { 0.0 };
            w.weight[l] = x;
            positive[l] += u32::from(x > 0.0);
        }
    }
    positive
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Grid;
    use crate::light::Light;
    use crate::local::{FacetStat, FitSettings, Observations};
    use crate::reflectance::Packed;
    use crate::rig::Camera;
    use crate::shadow::ShadowMask;
    use crate::vec3::normalize;

    /// The bits of a fit, NaN included.
    fn bits(fit: &FacetFit) -> Vec<u64> {
        let mut out: Vec<u64> = fit.target.iter().map(|x| x.to_bits()).collect();
        out.extend(fit.normal.map(f64::to_bits));
        out.extend(fit.albedo.map(f64::to_bits));
        out.extend([fit.specular.to_bits(), fit.sse.to_bits()]);
        out.extend([u64::from(fit.used), u64::from(fit.valid)]);
        out
    }

    /// The robust lanes give the scalar robust fits bit for bit (targets, normals, albedos,
    /// residuals, usable counts, validity), for both estimators, grey and colour, over random
    /// facets of several seeds: a Lambertian image of random normals and albedos with noise,
    /// highlights, dark (0), missing (NaN) and saturated observations and cast shadows left
    /// out, facets with few usable lights (where the reweighting stops early or the fit fails),
    /// isotropic lights and LEDs; pinhole and orthographic cameras, a mask with holes (batches
    /// across row ends and holes), full and partial batches, through both entry points
    /// (`try_run`, `try_run_targets`).
    #[test]
    fn robust_lanes_match_the_scalar_fits_exactly() {
        let (h, w) = (7, 21);
        let cameras = [
            Camera::Pinhole {
                k: [[60.0, 0.0, 10.0], [0.0, 55.0, 3.0], [0.0, 0.0, 1.0]],
                distortion: [0.0; 5],
            },
            Camera::Orthographic {
                pixel_size: [1.5, 1.5],
                origin: [-15.0, -5.0],
            },
        ];
        let mut lights: Vec<Light> = crate::local::tests::lights();
        for (j, p) in [[12.0, -8.0, 30.0], [-9.0, 14.0, 25.0], [20.0, 20.0, 40.0]]
            .into_iter()
            .enumerate()
        {
            lights.push(Light::Point {
                position: p,
                intensity: [2.0, 3.0 + j as f64, 4.0],
                axis: normalize([-0.2, 0.1 * j as f64, 1.0]),
                mu: [1.0, 2.3, 0.5][j],
            });
        }
        lights.extend([[-30.0, -10.0, 35.0], [8.0, 30.0, 55.0]].map(Light::point));
        let k = lights.len();
        let mut counts = [0usize; 4];
        for seed in 0..4u64 {
            let mut next = crate::multigrid::tests::lcg(100 + seed);
            let hole: Vec<bool> = (0..h * w).map(|_| next() > 0.08).collect();
            let shadows = ShadowMask::from_fn(h, w, k, |p, j| (p * 7 + j * 3) % 23 == 0);
            for channels in [1, 3] {
                // Per pixel a random normal and albedo; per pixel a usable-light budget (a few
                // pixels keep only 2-4 lights).
                let mut data = vec![0.0f32; k * h * w * channels];
                for p in 0..h * w {
                    let n = normalize([0.6 * next() - 0.3, 0.6 * next() - 0.3, -1.0]);
                    let rho = 2.0e4 * (0.5 + next());
                    let few = next() < 0.1;
                    let x = [(p % w) as f64 - 10.0, (p / w) as f64 - 3.0, 100.0];
                    for (j, light) in lights.iter().enumerate() {
                        let shade = light.shading(n, x);
                        let drop = few && next() < 0.7;
                        let kind = next();
                        for c in 0..channels {
                            let phi = channel_intensity(light.intensity(), channels, c);
                            let mut v = rho * (1.0 + 0.2 * c as f64) * phi * shade;
                            v *= 1.0 + 0.02 * (2.0 * next() - 1.0);
                            if kind < 0.08 {
                                v *= 3.0; // a highlight
                            } else if kind < 0.11 {
                                v = 0.0; // dark
                            } else if kind < 0.13 {
                                v = f64::NAN; // missing
                            } else if kind < 0.15 {
                                v = 1e9; // saturated
                            }
                            if drop {
                                v = f64::NAN;
                            }
                            data[(j * h * w + p) * channels + c] = v as f32;
                        }
                    }
                }
                let obs = Observations::from_stack(&data, k, h * w, channels);
                for camera in &cameras {
                    let grid = Grid::new(h, w, Some(&hole)).unwrap();
                    let geometry = crate::geometry::Geometry::new(camera, &grid).unwrap();
                    let u: Vec<f64> = (0..grid.n_unknowns())
                        .map(|i| geometry.unknown(100.0 + 0.3 * (i % 8) as f64 + next()))
                        .collect();
                    for robust in [Robust::Cauchy, Robust::Tukey] {
                        for shadowed in [None, Some(&shadows)] {
                            let settings = FitSettings {
                                robust,
                                dark: 1e-3,
                                saturation: 1e8,
                                ..FitSettings::default()
                            };
                            let step = LocalStep {
                                shadows: shadowed,
                                ..LocalStep::new(
                                    &grid,
                                    &geometry,
                                    Model::Near(&lights),
                                    &obs,
                                    settings,
                                )
                            };
                            assert!(step.robust_lane_lights().is_some());
                            let n = grid.n_facets();
                            let mut fits = vec![FacetFit::EMPTY; n];
                            step.run(&u, 0, &mut fits);
                            let mut targets = vec![[0.0; 4]; n];
                            let mut stats = vec![FacetStat::default(); n];
                            step.run_targets(&u, &mut targets, &mut stats);
                            let plain = LocalStep {
                                settings: FitSettings {
                                    robust: Robust::None,
                                    ..settings
                                },
                                ..step
                            };
                            let mut buf = vec![0.0f32; k * channels];
                            for f in 0..n {
                                let fit = step.fit(f, &u, &mut buf, &mut Packed::new(), None);
                                let case = format!("{seed} {channels} {robust:?} facet {f}");
                                assert_eq!(bits(&fit), bits(&fits[f]), "{case}");
                                assert_eq!(fit.target, targets[f], "{case}");
                                assert_eq!(FacetStat::from(&fit), stats[f], "{case}");
                                let p = plain.fit(f, &u, &mut buf, &mut Packed::new(), None);
                                counts[0] += usize::from(fit.valid);
                                counts[1] += usize::from(!fit.valid);
                                counts[2] += usize::from(fit.valid && fit.normal != p.normal);
                            }
                            counts[3] += n / LANES;
                        }
                    }
                }
            }
        }
        // Fitted and failed facets, robust fits away from the plain ones, full batches.
        assert!(counts[0] > 5000 && counts[1] > 100, "{counts:?}");
        assert!(counts[2] > counts[0] / 2, "{counts:?}");
        assert!(counts[3] > 500, "{counts:?}");
    }

    /// The final pass of a robust step (`try_run_final`, in two ranges, one not a multiple of
    /// the lanes) gives the fits of `try_run` and, from them, the trust maps of the scalar
    /// `trust` (which fits every facet again): the per-facet values bit for bit, the per-light
    /// sums up to the order of their additions; grey and colour, both estimators, with shadows.
    #[test]
    fn a_robust_final_pass_reuses_its_fits_for_the_trust_maps() {
        use crate::local::TrustMaps;
        let (grid, _, geometry) = crate::local::tests::small_masked_mesh();
        let (h, w) = (grid.height, grid.width);
        let lights = crate::local::tests::lights();
        let k = lights.len();
        let u: Vec<f64> = (0..grid.n_unknowns())
            .map(|v| 100.0 + 0.3 * (v % 8) as f64 - 0.2 * (v / 8) as f64)
            .collect();
        let shadows = ShadowMask::from_fn(h, w, k, |p, j| (p + 2 * j) % 11 == 0);
        let n = grid.n_facets();
        let mut checked = 0;
        for channels in [1, 3] {
            let mut next = crate::multigrid::tests::lcg(5 + channels as u64);
            let data: Vec<f32> = (0..k * h * w * channels)
                .map(|i| match i % 19 {
                    0 => 0.0,
                    5 => f32::NAN,
                    _ => (1e-3 * (1.0 + next()) * if next() < 0.1 { 3.0 } else { 1.0 }) as f32,
                })
                .collect();
            let obs = Observations::from_stack(&data, k, h * w, channels);
            for robust in [Robust::Cauchy, Robust::Tukey] {
                let settings = FitSettings {
                    robust,
                    ..FitSettings::default()
                };
                let step = LocalStep {
                    shadows: Some(&shadows),
                    ..LocalStep::new(&grid, &geometry, Model::Near(&lights), &obs, settings)
                };
                let mut fits = vec![FacetFit::EMPTY; n];
                step.run(&u, 0, &mut fits);
                let expected = step.trust(&u).unwrap();
                let mut maps = TrustMaps::new(&grid, k, channels).unwrap();
                let mut final_fits = vec![FacetFit::EMPTY; n];
                let mut values = vec![[f32::NAN; 2]; n];
                for (first, end) in [(0, 13), (13, n)] {
                    let (fits, values) = (&mut final_fits[first..end], &mut values[first..end]);
                    step.try_run_final(&u, first, fits, values, &mut maps, None)
                        .unwrap();
                    maps.scatter(&grid, first, values);
                }
                let fit_bits = |f: &[FacetFit]| f.iter().map(bits).collect::<Vec<_>>();
                assert_eq!(fit_bits(&final_fits), fit_bits(&fits));
                checked += maps.finish().assert_matches(&expected);
            }
        }
        assert!(checked > 4 * n / 2, "{checked} of {n}");
    }

    /// Only the settings the lanes implement take them: a robust estimator with unit weights
    /// and the Lambertian model of point lights.
    #[test]
    fn robust_lanes_apply_where_they_are_exact() {
        let (grid, _, geometry) = crate::local::tests::small_masked_mesh();
        let lights = crate::local::tests::lights();
        let k = lights.len();
        let data = vec![1e-3f32; k * grid.height * grid.width];
        let obs = Observations::from_stack(&data, k, grid.height * grid.width, 1);
        let step = |settings: FitSettings| {
            LocalStep::new(&grid, &geometry, Model::Near(&lights), &obs, settings)
                .robust_lane_lights()
                .is_some()
        };
        let tukey = FitSettings {
            robust: Robust::Tukey,
            ..FitSettings::default()
        };
        assert!(step(tukey));
        assert!(!step(FitSettings::default()));
        assert!(!step(FitSettings {
            weighting: Weighting::Paper,
            ..tukey
        }));
        assert!(!step(FitSettings {
            lobe: Some(crate::reflectance::Lobe::new(0.3, 1.5)),
            ..tukey
        }));
        let parallel = [([0.0, 0.0, -1.0], [1.0; 3]); 5];
        let step = LocalStep::new(&grid, &geometry, Model::Parallel(&parallel), &obs, tukey);
        assert!(step.robust_lane_lights().is_none());
    }
}
