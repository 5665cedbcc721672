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
//! of at most [`LOBE_SAMPLE`](super::glossy::LOBE_SAMPLE) facets, a few lines of the lobe
//! search's.

use rayon::prelude::*;

use super::glossy::{held_out_sse, refine, GLOSSY_STEPS, LOBE_SAMPLE};
use super::{channel_intensity, fit_facet, usable, FacetFit, FitSettings, LocalStep, Model};
use crate::error::Result;
use crate::geometry::{quad_centre, quad_normal};
use crate::reflectance::{Lobe, Packed};
use crate::vec3::dot;

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
}

impl LobeCheck {
    /// Whether the glossy model predicted the held-out observations better.
    pub fn glossy_wins(&self) -> bool {
        self.glossy < self.lambertian
    }
}

/// The observations `values` (`channels` per light) with the lights of fold `j` of `folds`
/// hidden (NaN, which no fit uses).
fn without_fold(values: &[f32], channels: usize, folds: usize, j: usize) -> Vec<f32> {
    let mut kept = values.to_vec();
    for (k, o) in kept.chunks_exact_mut(channels).enumerate() {
        if k % folds == j {
            o.fill(f32::NAN);
        }
    }
    kept
}

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
    let scored: Vec<(f64, f64, usize)> = (0..n)
        .into_par_iter()
        .step_by(stride)
        .map_init(
            || (vec![0.0f32; per], Packed::new()),
            |(buf, scratch), f| {
                let q = step.corners(f, u);
                let c = quad_centre(&q);
                let v = step.geometry.view(c);
                let values = step.facet_values(f, buf);
                let warm = step.warm.and_then(|w| super::warm_normal(&w[f]));
                let mut total = (0.0, 0.0, 0);
                for j in 0..folds {
                    let seen = without_fold(values, channels, folds, j);
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
                        Some(g) => held_out_sse(
                            c,
                            v,
                            step.model,
                            values,
                            channels,
                            &lambertian,
                            lobe,
                            &g,
                            held,
                        ),
                        None => l,
                    };
                    total = (total.0 + g, total.1 + l, total.2 + count);
                }
                total
            },
        )
        .collect();
    step.cancel.check()?;
    // Summed in the facets' order (deterministic, see `estimate_lobe`).
    let (g, l, count) = scored
        .iter()
        .fold((0.0, 0.0, 0), |t, s| (t.0 + s.0, t.1 + s.1, t.2 + s.2));
    if count == 0 {
        return Ok(None);
    }
    Ok(Some(LobeCheck {
        glossy: (g / count as f64).sqrt(),
        lambertian: (l / count as f64).sqrt(),
        observations: count,
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
        let kept = without_fold(&values, 2, 3, 1);
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
}
