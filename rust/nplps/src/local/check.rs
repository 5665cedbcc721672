//! Whether the glossy model earns its unknowns: held-out prediction against the Lambertian model.
//!
//! The glossy fit gives each facet one more unknown than the Lambertian one (the specular albedo)
//! and the object a lobe. Where the images hold highlights it explains them; where they hold
//! none, or too few lights see each facet to pin the lobe down (hehe12's 8 LEDs, the 7 lights of
//! queau_human1's face, whose skin scatters below its surface), the glossy fit lowers the
//! residual by bending the normals and albedos to what is not a highlight, and it predicts the
//! images of other lights worse than the Lambertian model does (`nplps evaluate`, leave one light
//! out, mean shape error: hehe12 0.164 against 0.049, queau_human1 0.92 against 0.27).
//!
//! [`check_lobe`] asks the images which model predicts better. The lights are split into
//! `F = min(k, CHECK_FOLDS)` folds (light `k` in fold `k mod F`); each facet of the lobe search's
//! subsample is fitted without the lights of fold `j`, by the Lambertian model and by the glossy
//! model under the lobe (from that Lambertian fit, as a local step does), and each fit predicts
//! the observations of fold `j`:
//!
//! ```text
//! E_model = sum_facets sum_j sum_{k in fold j, ch} (I_{k,ch} - m_{k,ch}(fit without fold j))^2,
//! ```
//!
//! `m` being the model's prediction (0 where the facet turns away from the light). Both models
//! are scored on the same observations: those of the facet-folds whose Lambertian fit exists.
//! The solver keeps the glossy model when `E_glossy < E_lambertian` and otherwise goes on with
//! the Lambertian one, as it does after a lobe too rough to be a highlight
//! ([`MATTE_ROUGHNESS`](crate::MATTE_ROUGHNESS)). The cost is `F` Lambertian and `F` glossy fits
//! of at most [`LOBE_SAMPLE`] facets, a few lines of the lobe
//! search's.
//!
//! ## The highlight where a light shows it
//!
//! The held-out error cannot judge a lobe whose highlight none of the lights shows: each fold
//! then sees only the lobe's far tail, and so do the lights it predicts, while a light that falls
//! into the lobe is predicted far brighter than anything the fits saw. Under GGX light `k`
//! samples the share
//!
//! ```text
//! D(n.h_k) / D(1) = (alpha^2 / ((n.h_k)^2 (alpha^2 - 1) + 1))^2,   h_k = normalize(l_k + v),
//! ```
//!
//! of the lobe's peak at a facet of normal `n`: 1 in the mirror direction, 1/2 about
//! `0.64 alpha` radians from it (the half maximum). A glossy fit *sees the lobe* when one of the
//! lit lights (`n.l > 0`) it was fitted with has `D(n.h_k) >= D(1) / 2` ([`SEES_PEAK`]). On a
//! surface with the highlight the lobe models (one material), the fits that see the lobe find
//! the specular albedo the others find from its tail; where the glossy fits bend the tail to
//! what is not a highlight, the fits that could see the highlight find none. So the check also
//! measures
//!
//! ```text
//! highlight = median(rho_s of the fits that see the lobe) / median(rho_s of all glossy fits)
//! ```
//!
//! (0 when no fit sees the lobe), and the glossy model wins only when it predicts the held-out
//! observations better **and** `highlight >=` [`HIGHLIGHT_CONFIRMS`]. On hehe12 without LED 4
//! (7 LEDs) the lobe search ended at roughness 0.024, no fit saw it (the nearest fitted half
//! vector 5-13 degrees from each facet's normal), the glossy normals lay 8 degrees from the
//! Lambertian ones, and LED 4, within 2-4 degrees of some facets' half vectors, was predicted up
//! to 270 times brighter than its image (`nplps evaluate` shape error 0.81 against 0.022
//! Lambertian) although the model predicted the 7 LEDs' held-out images better (RMS 0.045 against
//! 0.057).

use rayon::prelude::*;

use super::glossy::{held_out_sse, refine, GLOSSY_STEPS, LOBE_SAMPLE};
use super::{
    channel_intensity, fit_facet, hide_lights, usable, FacetFit, FitSettings, LocalStep, Model,
};
use crate::error::Result;
use crate::geometry::{quad_centre, quad_normal};
use crate::reflectance::Lobe;
use crate::vec3::{add, dot, norm};

/// The solver compares the models with fewer lights than this only (the glossy fits'
/// `CONTINUE_LIGHTS`). With many lights the held-out squared
/// error is no judge of a sharp lobe: a highlight predicted a degree off its place costs more
/// than no highlight at all. On DiLiGenT's ball (96 lights, roughness 0.03) the glossy model
/// predicted held-out lights worse at the full resolution (summed squared error 438 against 94,
/// better on 37 % of the facets) while its normals are 2.6 times better (1.53 against 3.99
/// degrees); on the 16-light PBR renders it won by 10-100 times. With hehe12's 8 LEDs and
/// queau_human1's 7 lights it lost (RMS 0.105 against 0.054, and 0.007-0.039 against
/// 0.0007-0.0035), as it did in `nplps evaluate`.
pub const CHECK_BELOW_LIGHTS: usize = 12;

/// The most folds of the lights in the solver's held-out check (with fewer lights, one light a fold: leave
/// one out).
pub const CHECK_FOLDS: usize = 8;

/// The least `highlight` (see the module documentation: the median specular albedo of the
/// check's glossy fits that see the lobe over that of all of them) with which the glossy model
/// is kept. Measured at the check (`LobeCheck::highlight`): hehe12's leave-one-out runs (7 of
/// its 8 LEDs each) 0.0010-0.0043 in six runs, 0 (no fit sees the lobe) without LED 4, 0.13
/// without LED 0 (whose fits' specular albedos are all near 0; its held-out error drops it: RMS
/// 0.66 against 0.056); the whole hehe12 capture 0.0012, queau_human1 0 (both also dropped by
/// their held-out error); the solver's own glossy scenes (sphere and bumps, roughness 0.08, 0.15
/// and 0.3, 8 and 10 of their 27 lights, 3 seeds, one with 0.5 % noise) 0.023-1.8, the lowest
/// with the sharpest lobe (0.08, estimated 0.03-0.08). The threshold is near the geometric mean
/// of the gap's ends (0.0043 and 0.023). A wrong distance can refute the model too: the glossy
/// sphere (roughness 0.15, 8 lights) fitted 5 % and 11 % too far gave 0.0012 and 0.010.
pub const HIGHLIGHT_CONFIRMS: f64 = 0.01;

/// A fit sees the lobe where `D(n.h_k) / D(1)` reaches this for one of its lights: the lobe's
/// half maximum (see the module documentation).
pub const SEES_PEAK: f64 = 0.5;

/// The held-out prediction errors of the two models (see the module documentation): RMS over
/// the `observations` scored.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LobeCheck {
    /// The glossy model's, under the lobe checked.
    pub glossy: f64,
    /// The Lambertian model's.
    pub lambertian: f64,
    /// The observations (lights x channels of the facets of the subsample) predicted.
    pub observations: usize,
    /// How many of the glossy fits (facets of the subsample, each without each fold) see the
    /// lobe (see the module documentation).
    pub seen: usize,
    /// The median specular albedo of the fits that see the lobe over that of all the glossy
    /// fits (0 when none sees it; see the module documentation).
    pub highlight: f64,
}

impl LobeCheck {
    /// Whether the fits that see the lobe confirm its highlight (`highlight >=`
    /// `HIGHLIGHT_CONFIRMS`, 0.01: see the module documentation of `local::check`).
    pub fn highlight_confirmed(&self) -> bool {
        self.highlight >= HIGHLIGHT_CONFIRMS
    }

    /// Whether the glossy model keeps its place: it predicted the held-out observations better,
    /// and the fits that see the lobe confirm its highlight.
    pub fn glossy_wins(&self) -> bool {
        self.glossy < self.lambertian && self.highlight_confirmed()
    }
}

/// The largest share of the lobe's peak `D(n.h_k) / D(1)` (see the module documentation) that
/// the usable observations of `values` selected by `fitted` (by light) sample at the facet of
/// centre `c`, view vector `v` and unit normal `n`; 0 where none is lit (`n.l > 0`) or the facet
/// turns away from the camera.
#[allow(clippy::too_many_arguments)]
fn lobe_coverage(
    c: [f64; 3],
    v: [f64; 3],
    model: Model<'_>,
    values: &[f32],
    channels: usize,
    settings: &FitSettings,
    lobe: &Lobe,
    n: [f64; 3],
    fitted: impl Fn(usize) -> bool,
) -> f64 {
    if dot(n, v) <= 0.0 {
        return 0.0;
    }
    let a2 = lobe.alpha * lobe.alpha;
    let mut best = 0.0f64;
    for (k, o) in values.chunks_exact(channels).enumerate() {
        if !fitted(k) || !usable(o, settings) {
            continue;
        }
        let Some((_, l, _)) = model.light(k, c) else {
            continue;
        };
        let h = add(l, v);
        let hn = norm(h);
        if dot(n, l) <= 0.0 || hn == 0.0 {
            continue;
        }
        let ch = dot(n, h) / hn;
        let q = a2 / (ch * ch * (a2 - 1.0) + 1.0);
        best = best.max(q * q);
    }
    best
}

/// The median of `x` (the upper one of an even count; NaN when empty), reordering it.
fn median(x: &mut [f64]) -> f64 {
    if x.is_empty() {
        return f64::NAN;
    }
    let mid = x.len() / 2;
    *x.select_nth_unstable_by(mid, f64::total_cmp).1
}

/// `highlight` of the module documentation from the glossy fits' `(sees the lobe, rho_s)`: 0
/// when none sees it; 1 when the specular albedos' median is 0 (no specular part to confirm).
fn highlight_of(fits: &[(bool, f64)]) -> f64 {
    let mut seen: Vec<f64> = fits.iter().filter(|f| f.0).map(|f| f.1).collect();
    if seen.is_empty() {
        return 0.0;
    }
    let mut all: Vec<f64> = fits.iter().map(|f| f.1).collect();
    let typical = median(&mut all);
    match typical > 0.0 {
        true => median(&mut seen) / typical,
        false => 1.0,
    }
}

/// A facet's summed squared held-out errors of the glossy and Lambertian models and the
/// observations they sum.
type Scores = (f64, f64, usize);

/// The squared error of the Lambertian prediction of `fit` for the usable observations of
/// `values` that `held` selects (by light): `sum (I_{k,ch} - rho_ch Phi_{k,ch} max(0, n.beta_k))^2`,
/// and how many observations that sums.
fn lambertian_sse(
    c: [f64; 3],
    model: Model<'_>,
    values: &[f32],
    channels: usize,
    settings: &FitSettings,
    fit: &FacetFit,
    held: impl Fn(usize) -> bool,
) -> (f64, usize) {
    let (mut sse, mut count) = (0.0, 0);
    for (k, o) in values.chunks_exact(channels).enumerate() {
        if !held(k) || !usable(o, settings) {
            continue;
        }
        let (b, _, phi) = model.row(k, c);
        let shade = dot(fit.normal, b).max(0.0);
        for (ch, &i) in o.iter().enumerate() {
            let e = i as f64 - fit.albedo[ch] * channel_intensity(phi, channels, ch) * shade;
            sse += e * e;
            count += 1;
        }
    }
    (sse, count)
}

/// Compares the held-out predictions of the glossy model under `lobe` and of the Lambertian
/// model on the facets of `step` on the unknowns `u` (see the module documentation); `None`
/// when no observation could be scored (no facet of the subsample fitted without a fold).
pub fn check_lobe(step: &LocalStep<'_>, u: &[f64], lobe: &Lobe) -> Result<Option<LobeCheck>> {
    let n = step.grid.n_facets();
    let stride = n.div_ceil(LOBE_SAMPLE).max(1);
    let per = step.obs.per_facet();
    let channels = step.obs.channels;
    let lights = per / channels;
    let folds = lights.min(CHECK_FOLDS);
    if folds < 2 {
        return Ok(None);
    }
    let lambertian = FitSettings {
        lobe: None,
        ..step.settings
    };
    let scored: Vec<(Scores, Vec<(bool, f64)>)> = (0..n)
        .into_par_iter()
        .step_by(stride)
        .map_init(
            || (vec![0.0f32; per], step.settings.packed()),
            |(buf, scratch), f| {
                let q = step.corners(f, u);
                let c = quad_centre(&q);
                let v = step.geometry.view(c);
                let values = step.facet_values(f, buf);
                let warm = step.warm.and_then(|w| super::warm_normal(&w[f]));
                // (glossy SSE, Lambertian SSE, observations), and each glossy fit's (sees the
                // lobe, rho_s)
                let mut total = (0.0, 0.0, 0);
                let mut fits = Vec::with_capacity(folds);
                for j in 0..folds {
                    let seen = hide_lights(values, channels, |k| k % folds == j);
                    let Some(start) = fit_facet(c, step.model, &seen, channels, lambertian) else {
                        continue;
                    };
                    let starts = [warm.or(Some(start.normal)), Some(quad_normal(&q))];
                    let glossy = refine(
                        c,
                        v,
                        step.model,
                        &seen,
                        channels,
                        &lambertian,
                        lobe,
                        Some(&start),
                        starts,
                        GLOSSY_STEPS,
                        scratch,
                    );
                    let held = |k: usize| k % folds == j;
                    let (l, count) =
                        lambertian_sse(c, step.model, values, channels, &lambertian, &start, held);
                    // A facet whose glossy fit fails keeps its Lambertian fit (as in a local step).
                    let g = match glossy {
                        Some(g) => {
                            let sees = lobe_coverage(
                                c,
                                v,
                                step.model,
                                &seen,
                                channels,
                                &lambertian,
                                lobe,
                                g.normal,
                                |k| !held(k),
                            ) >= SEES_PEAK;
                            fits.push((sees, g.specular));
                            held_out_sse(
                                c,
                                v,
                                step.model,
                                values,
                                channels,
                                &lambertian,
                                lobe,
                                &g,
                                held,
                            )
                        }
                        None => l,
                    };
                    total = (total.0 + g, total.1 + l, total.2 + count);
                }
                (total, fits)
            },
        )
        .collect();
    step.cancel.check()?;
    // Summed in the facets' order (deterministic, see `estimate_lobe`).
    let (g, l, count) = scored
        .iter()
        .fold((0.0, 0.0, 0), |t, (s, _)| (t.0 + s.0, t.1 + s.1, t.2 + s.2));
    if count == 0 {
        return Ok(None);
    }
    let fits: Vec<(bool, f64)> = scored.into_iter().flat_map(|(_, f)| f).collect();
    let highlight = highlight_of(&fits);
    Ok(Some(LobeCheck {
        glossy: (g / count as f64).sqrt(),
        lambertian: (l / count as f64).sqrt(),
        observations: count,
        seen: fits.iter().filter(|f| f.0).count(),
        highlight,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::light::Light;

    #[test]
    fn a_fold_hides_its_own_lights_only() {
        let values: Vec<f32> = (0..10).map(|x| x as f32).collect();
        // 5 lights x 2 channels, 3 folds: fold 1 holds lights 1 and 4.
        let kept = hide_lights(&values, 2, |k| k % 3 == 1);
        for (k, o) in kept.chunks_exact(2).enumerate() {
            match k % 3 == 1 {
                true => assert!(o.iter().all(|x| x.is_nan()), "{k}"),
                false => assert_eq!(o, &values[2 * k..2 * k + 2], "{k}"),
            }
        }
    }

    #[test]
    fn the_lambertian_prediction_of_the_truth_is_exact() {
        let lights: Vec<Light> = [
            [40.0, 0.0, -60.0],
            [-30.0, 20.0, -50.0],
            [0.0, -40.0, -70.0],
        ]
        .iter()
        .map(|&position| Light::Point {
            position,
            intensity: [2.0e4; 3],
            axis: [0.0, 0.0, 1.0],
            mu: 0.0,
        })
        .collect();
        let c = [1.0, 2.0, 100.0];
        let n = [0.1, -0.2, -(1.0f64 - 0.05).sqrt()];
        let model = Model::Near(&lights);
        let albedo = 0.6;
        let values: Vec<f32> = (0..3)
            .map(|k| {
                let (b, _, phi) = model.row(k, c);
                (albedo * phi[0] * dot(n, b).max(0.0)) as f32
            })
            .collect();
        let fit = FacetFit {
            normal: n,
            albedo: [albedo; 3],
            specular: 0.0,
            valid: true,
            ..FacetFit::EMPTY
        };
        let settings = FitSettings::default();
        let (sse, count) = lambertian_sse(c, model, &values, 1, &settings, &fit, |k| k != 1);
        assert_eq!(count, 2);
        // (the observations are f32: exact to their rounding)
        assert!(sse.sqrt() < 1e-6 * values[0] as f64, "{sse}");
        // A wrong albedo is charged on the held lights only.
        let off = FacetFit {
            albedo: [0.5; 3],
            ..fit
        };
        let (sse, _) = lambertian_sse(c, model, &values, 1, &settings, &off, |k| k == 0);
        let (b, _, phi) = model.row(0, c);
        let expected = (0.1 * phi[0] * dot(n, b)).powi(2);
        assert!((sse - expected).abs() < 1e-6 * expected, "{sse} {expected}");
    }

    /// A light in the mirror direction samples the whole peak, one at the half-maximum angle
    /// `atan(alpha sqrt(sqrt(2) - 1))` half of it (to the `cos^4` of that angle, see below); a
    /// light the fit did not use, one turned away, or an unusable observation, none.
    #[test]
    fn the_coverage_is_the_share_of_the_peak_the_fitted_lights_sample() {
        let lobe = Lobe::new(0.1, 1.5);
        let v = [0.0, 0.0, -1.0];
        let n = [0.0, 0.0, -1.0];
        let c = [0.0, 0.0, 100.0];
        let settings = FitSettings::default();
        // Directional lights: h = normalize(l + v) makes the angle t/2 with n for l tilted by t.
        let tilted = |t: f64| [t.sin(), 0.0, -t.cos()];
        let half = (lobe.alpha * (2f64.sqrt() - 1.0).sqrt()).atan();
        let lights = [
            (tilted(0.0), [1.0; 3]),
            (tilted(2.0 * half), [1.0; 3]),
            (tilted(1.2), [1.0; 3]),
            (tilted(2.0), [1.0; 3]), // behind the facet: n.l < 0
        ];
        let model = Model::Parallel(&lights);
        let values = [1.0f32; 4];
        let cover = |fitted: &dyn Fn(usize) -> bool| {
            lobe_coverage(c, v, model, &values, 1, &settings, &lobe, n, fitted)
        };
        assert!((cover(&|k| k == 0) - 1.0).abs() < 1e-12);
        // D(c) / D(1) = (a^2 / (c^2 (a^2 - 1) + 1))^2 = 1 / (cos^4 (1 + tan^2 / a^2)^2): 1/2
        // at the half-maximum angle but for the cos^4 of that angle.
        let at_half = cover(&|k| k == 1);
        let expected = 0.5 / half.cos().powi(4);
        assert!((at_half - expected).abs() < 1e-9, "{at_half} {expected}");
        assert!(cover(&|k| k == 2) < 2e-3);
        assert_eq!(cover(&|k| k == 3), 0.0);
        assert_eq!(cover(&|k| k >= 1), at_half);
        let dark = [0.0f32, 1.0, 1.0, 1.0];
        let unusable = lobe_coverage(c, v, model, &dark, 1, &settings, &lobe, n, |k| k == 0);
        assert_eq!(unusable, 0.0);
    }

    /// `highlight`: the median specular albedo of the fits that see the lobe over that of all.
    #[test]
    fn the_highlight_is_the_seen_fits_median_over_all() {
        // A glossy surface: the fits that see the lobe find the others' specular albedo.
        let glossy: Vec<(bool, f64)> = (0..20)
            .map(|i| (i % 4 == 0, 0.2 + 0.001 * i as f64))
            .collect();
        assert!((highlight_of(&glossy) - 1.0).abs() < 0.05);
        // hehe12's kind: where a light shows the lobe's peak the images hold no highlight.
        let tail: Vec<(bool, f64)> = (0..20)
            .map(|i| match i < 3 {
                true => (true, 1e-5),
                false => (false, 0.02),
            })
            .collect();
        assert!(highlight_of(&tail) < 1e-3);
        // No fit sees the lobe: nothing confirms it.
        let unseen: Vec<(bool, f64)> = (0..20).map(|_| (false, 0.02)).collect();
        assert_eq!(highlight_of(&unseen), 0.0);
        // No specular part at all: nothing to confirm, nothing refuted.
        let matte: Vec<(bool, f64)> = (0..20).map(|i| (i < 5, 0.0)).collect();
        assert_eq!(highlight_of(&matte), 1.0);
        let mut x = [3.0, 1.0, 2.0];
        assert_eq!(median(&mut x), 2.0);
        assert!(median(&mut []).is_nan());
    }

    #[test]
    fn the_glossy_model_wins_only_with_its_highlight_confirmed() {
        let check = |glossy: f64, highlight: f64| LobeCheck {
            glossy,
            lambertian: 1.0,
            observations: 100,
            seen: 10,
            highlight,
        };
        assert!(check(0.5, 1.0).glossy_wins());
        assert!(!check(1.5, 1.0).glossy_wins());
        assert!(!check(0.5, 0.5 * HIGHLIGHT_CONFIRMS).glossy_wins());
        assert!(check(0.5, HIGHLIGHT_CONFIRMS).highlight_confirmed());
    }
}
