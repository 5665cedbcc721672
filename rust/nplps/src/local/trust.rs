//! How far to trust a result without ground truth: per facet, from the Lambertian linear fit at
//! the final mesh, the normal's predicted angular uncertainty and the leave-one-light-out
//! re-rendering error; per light, its in-sample and held-out residuals.
//!
//! At facet f (centre `c`), channel `ch`, the scaled normal `g_ch` solves the weighted least
//! squares `min sum_k w_k (I_k - r_k . g)^2` over the usable lights (`r_k = Phi_k beta_k(c)`, the
//! rows of the local step; `w_k` its weighting times, with a robust estimator, the robust weights
//! at the facet's robust fit, which leave out the lights of weight 0), `T_ch = sum w r r^T`.
//! With `m` usable lights and the residual variance `s2_ch = sum w e^2 / (m - 3)`, the
//! covariance of `g_ch` is `s2_ch T_ch^-1`; the normal `n = b / |b|` of `b = sum_ch g_ch` has,
//! to first order, `Cov(n) = P Cov(b) P / |b|^2` with `P = I - n n^T`. The reported
//! uncertainty is `sqrt(trace Cov(n))` in degrees: the RMS angle between the fitted and the true
//! normal the image noise alone would give (the two tangent-plane standard deviations added in
//! quadrature). It needs `m >= 4` (NaN otherwise).
//!
//! The leave-one-out residual of light k is `e_k / (1 - h_k)` with the hat-matrix diagonal
//! `h_k = w_k r_k^T T^-1 r_k`: the error of predicting light k's observation from a fit of the
//! other lights, without refitting. The per-pixel map is its mean absolute value over the usable
//! lights and channels (image units).
//!
//! Under the glossy model the same Lambertian fit is used (at the glossy result's mesh): its
//! uncertainty describes the Lambertian normal of the facet, and its held-out error what the
//! Lambertian model predicts. With interreflections, the indirect light is left out of the rows.

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use super::{
    channel_intensity, fit_facet, usable, Facet, FacetFit, FitSettings, LocalStep, Robust, Row,
    Weighting,
};
use crate::error::Result;
use crate::geometry::quad_centre;
use crate::memory::{try_par_vec, try_zeros};
use crate::parallel::scatter;
use crate::vec3::norm;

/// The trust maps and per-light figures of a result (see the module's documentation).
#[derive(Debug, Clone, PartialEq, Default)]
#[non_exhaustive]
pub struct Trust {
    /// Predicted RMS angular error of each pixel's (Lambertian) fitted normal from the image
    /// noise, degrees (NaN outside the mask and where fewer than 4 lights were usable).
    pub normal_sigma: Vec<f32>,
    /// Mean absolute leave-one-light-out re-rendering error of each pixel, image units (NaN
    /// outside the mask and where fewer than 4 lights were usable).
    pub held_out: Vec<f32>,
    /// Per light: the in-sample and held-out residuals over the facets that used it.
    pub lights: Vec<LightTrust>,
}

#[cfg(test)]
impl Trust {
    /// Test helper: the per-facet maps of a final pass equal `expected`'s bit for bit and its
    /// per-light figures within 1e-12 (relative; their sums add in another order); returns how
    /// many facets have a finite normal sigma.
    pub(crate) fn assert_matches(&self, expected: &Trust) -> usize {
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&self.normal_sigma), bits(&expected.normal_sigma));
        assert_eq!(bits(&self.held_out), bits(&expected.held_out));
        for (a, b) in self.lights.iter().zip(&expected.lights) {
            assert_eq!(a.facets, b.facets);
            for (x, y) in [
                (a.residual, b.residual),
                (a.held_out, b.held_out),
                (a.mean_intensity, b.mean_intensity),
            ] {
                assert!((x - y).abs() <= 1e-12 * y.abs(), "{a:?} {b:?}");
            }
        }
        self.normal_sigma.iter().filter(|v| v.is_finite()).count()
    }
}

/// One light's residuals over the facets that used it (and had at least 4 usable lights).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[non_exhaustive]
pub struct LightTrust {
    /// RMS residual of its observations under the fits with it (image units).
    pub residual: f64,
    /// RMS leave-one-out residual: of its observations predicted by fits without it.
    pub held_out: f64,
    /// Mean of its usable observations (image units).
    pub mean_intensity: f64,
    /// Number of facets whose fit used it.
    pub facets: usize,
}

/// Per-light sums: squared residual, squared held-out residual, observation, count.
pub(crate) type LightSums = Vec<[f64; 4]>;

/// Facets per parallel chunk.
pub(super) const CHUNK: usize = 4096;

/// `a += b`, light by light.
pub(super) fn add_sums(mut a: LightSums, b: LightSums) -> LightSums {
    for (x, y) in a.iter_mut().zip(&b) {
        for j in 0..4 {
            x[j] += y[j];
        }
    }
    a
}

/// The trust maps of a result while they are filled, chunk by chunk of facets (see
/// [`LocalStep::try_run_final_lanes`] and [`LocalStep::try_run_final`]), and its per-light
/// sums.
#[derive(Debug)]
pub struct TrustMaps {
    normal_sigma: Vec<f32>,
    held_out: Vec<f32>,
    sums: LightSums,
    channels: usize,
}

/// Facets a piece of [`TrustMaps::scatter`] writes on one thread.
const SCATTER_PIECE: usize = 1 << 15;

impl TrustMaps {
    /// Empty maps (NaN) of the grid's image for `k` lights of `channels` channels.
    pub fn new(grid: &crate::grid::Grid, k: usize, channels: usize) -> Result<TrustMaps> {
        let pixels = grid.height * grid.width;
        Ok(TrustMaps {
            normal_sigma: try_par_vec(pixels, f32::NAN, "the normal uncertainty map")?,
            held_out: try_par_vec(pixels, f32::NAN, "the held-out error map")?,
            sums: vec![[0.0; 4]; k],
            channels,
        })
    }

    /// As [`TrustMaps::new`], the maps allocated but not written (zero pages until touched):
    /// for a final pass that writes every pixel, masked or not ([`TrustMaps::maps`]).
    pub(crate) fn unwritten(
        grid: &crate::grid::Grid,
        k: usize,
        channels: usize,
    ) -> Result<TrustMaps> {
        let pixels = grid.height * grid.width;
        Ok(TrustMaps {
            normal_sigma: try_zeros(pixels, "the normal uncertainty map")?,
            held_out: try_zeros(pixels, "the held-out error map")?,
            sums: vec![[0.0; 4]; k],
            channels,
        })
    }

    /// The normal uncertainty and held-out error maps, for writing.
    pub(crate) fn maps(&mut self) -> (&mut [f32], &mut [f32]) {
        (&mut self.normal_sigma, &mut self.held_out)
    }

    /// Writes the values of facets `first..first + per_facet.len()` into the maps, pieces of
    /// the facets in parallel (a grid's facets are in increasing pixel order, so the pieces'
    /// pixels do not overlap).
    pub fn scatter(&mut self, grid: &crate::grid::Grid, first: usize, per_facet: &[[f32; 2]]) {
        let facets = &grid.facets[first..first + per_facet.len()];
        let maps = (&mut self.normal_sigma[..], &mut self.held_out[..]);
        scatter(
            maps,
            0,
            facets,
            per_facet,
            SCATTER_PIECE,
            &|(sigma, held), p, v| {
                sigma[p] = v[0];
                held[p] = v[1];
            },
        );
    }

    /// Adds per-light sums.
    pub(crate) fn add(&mut self, sums: LightSums) {
        self.sums = add_sums(std::mem::take(&mut self.sums), sums);
    }

    /// The trust maps and per-light figures.
    pub fn finish(self) -> Trust {
        let channels = self.channels;
        let lights = self
            .sums
            .iter()
            .map(|s| {
                let m = s[3] * channels as f64;
                LightTrust {
                    residual: (s[0] / m).sqrt(),
                    held_out: (s[1] / m).sqrt(),
                    mean_intensity: s[2] / m,
                    facets: s[3] as usize,
                }
            })
            .collect();
        Trust {
            normal_sigma: self.normal_sigma,
            held_out: self.held_out,
            lights,
        }
    }
}

thread_local! {
    static LIGHT_ROWS: std::cell::Cell<Vec<Row>> = const { std::cell::Cell::new(Vec::new()) };
}

/// A thread's buffer of one facet's light rows ([`Model::row`](super::Model) of each light),
/// taken from the thread and given back when dropped, so that the trust of a robust fit
/// allocates nothing once the buffer has grown.
struct LightRows(Vec<Row>);

impl LightRows {
    fn take() -> LightRows {
        LightRows(LIGHT_ROWS.take())
    }
}

impl Drop for LightRows {
    fn drop(&mut self) {
        LIGHT_ROWS.set(std::mem::take(&mut self.0));
    }
}

impl LocalStep<'_> {
    /// The trust maps of every facet at the unknowns `u` (see the module's documentation), as
    /// per-pixel maps of the grid's image (the reconstruction computes them with its final fits,
    /// [`LocalStep::try_run_final_lanes`] or [`LocalStep::try_run_final`]).
    #[cfg(test)]
    pub fn trust(&self, u: &[f64]) -> Result<Trust> {
        let grid = self.grid;
        let mut maps = TrustMaps::new(grid, self.obs.k, self.obs.channels)?;
        let mut per_facet =
            crate::memory::try_vec(grid.n_facets(), [f32::NAN; 2], "the trust maps")?;
        let sums = self.trust_range(u, 0, &mut per_facet, None);
        maps.add(sums);
        maps.scatter(grid, 0, &per_facet);
        Ok(maps.finish())
    }

    /// The trust values of facets `first..first + out.len()` (`[normal sigma, held-out]`, see
    /// [`LocalStep::facet_trust`]) and their per-light sums, with the scalar fits; with a
    /// robust estimator, from the robust fits of these facets (`fits`, one per entry of `out`)
    /// when the caller has them: this step's own fits, without a lobe or indirect light, which
    /// are those [`LocalStep::facet_trust`] would compute (the same bits), so they are not
    /// computed twice; None: fitted here.
    pub(super) fn trust_range(
        &self,
        u: &[f64],
        first: usize,
        out: &mut [[f32; 2]],
        fits: Option<&[FacetFit]>,
    ) -> LightSums {
        debug_assert!(fits.is_none_or(|f| f.len() == out.len()));
        let (k, channels) = (self.obs.k, self.obs.channels);
        out.par_chunks_mut(CHUNK)
            .enumerate()
            .map(|(chunk, out)| {
                let mut buf = vec![0.0f32; k * channels];
                let mut rows = vec![[0.0f64; 4]; k * channels];
                let mut sums = vec![[0.0f64; 4]; k];
                for (i, o) in out.iter_mut().enumerate() {
                    if self.cancel.is_cancelled() {
                        break;
                    }
                    let j = chunk * CHUNK + i;
                    let fitted = fits.map(|fits| &fits[j]);
                    *o = self.facet_trust(first + j, u, &mut buf, &mut rows, &mut sums, fitted);
                }
                sums
            })
            .reduce(|| vec![[0.0; 4]; k], add_sums)
    }

    /// `[normal sigma (degrees), mean |leave-one-out residual|]` of facet `f`, adding its
    /// lights' residuals to `sums`; `buf` and `rows` are scratch (k * channels each). With a
    /// robust estimator, `fitted` is the facet's robust fit when the caller has it (see
    /// [`LocalStep::trust_range`]; an invalid fit is the failed fit); None: fitted here.
    pub(super) fn facet_trust(
        &self,
        f: usize,
        u: &[f64],
        buf: &mut [f32],
        rows: &mut [[f64; 4]],
        sums: &mut LightSums,
        fitted: Option<&FacetFit>,
    ) -> [f32; 2] {
        let none = [f32::NAN; 2];
        let channels = self.obs.channels;
        let q = self.corners(f, u);
        let c = quad_centre(&q);
        let values = self.facet_values(f, buf);
        // With a robust estimator each light's row is computed once, for the weights and the
        // sums below (the same values as where they are used).
        let mut light_rows = LightRows::take();
        light_rows.0.clear();
        // With a robust estimator: its weights at the robust fit (0 leaves a light out).
        let robust = match self.settings.robust {
            Robust::None => None,
            _ => {
                let k = values.len() / channels;
                light_rows.0.extend((0..k).map(|k| self.model.row(k, c)));
                let settings = FitSettings {
                    lobe: None,
                    ..self.settings
                };
                let fit = match fitted {
                    Some(fit) => fit.valid.then_some(*fit),
                    None => fit_facet(c, self.model, values, channels, settings),
                };
                let Some(fit) = fit else {
                    return none;
                };
                let facet = Facet {
                    c,
                    model: self.model,
                    values,
                    channels,
                    settings,
                    indirect: None,
                    rows: Some(&light_rows.0),
                };
                match facet.robust_weights(fit.normal, fit.albedo, &mut Vec::new()) {
                    Some(weights) => Some(weights),
                    None => return none,
                }
            }
        };
        // Rows (r, w) of the usable observations, light-major; w = 0 marks an unusable one.
        let mut t = [Matrix3::<f64>::zeros(); 3];
        let mut s = [Vector3::<f64>::zeros(); 3];
        let mut used = 0usize;
        for (k, o) in values.chunks_exact(channels).enumerate() {
            let rw = robust.as_ref().map_or(1.0, |w| w[k]);
            let ok = usable(o, &self.settings) && rw > 0.0;
            let (b, pw, phi) = match light_rows.0.get(k) {
                Some(&row) => row,
                None => self.model.row(k, c),
            };
            used += ok as usize;
            for (ch, &i) in o.iter().enumerate() {
                let row = &mut rows[k * channels + ch];
                if !ok {
                    row[3] = 0.0;
                    continue;
                }
                let p = channel_intensity(phi, channels, ch);
                let r = Vector3::new(b[0] * p, b[1] * p, b[2] * p);
                let w = rw
                    * match self.settings.weighting {
                        Weighting::Image => 1.0,
                        Weighting::Paper => (pw / p) * (pw / p),
                    };
                *row = [r.x, r.y, r.z, w];
                t[ch] += w * r * r.transpose();
                s[ch] += w * i as f64 * r;
            }
        }
        if used < 4 {
            return none;
        }
        let mut inv = [Matrix3::<f64>::zeros(); 3];
        let mut b = Vector3::<f64>::zeros();
        let mut g = [Vector3::<f64>::zeros(); 3];
        for ch in 0..channels {
            let Some(ti) = super::invert_spd3(&t[ch]) else {
                return none;
            };
            inv[ch] = ti;
            g[ch] = ti * s[ch];
            b += g[ch];
        }
        // Residuals, leave-one-out residuals and the residual variance per channel.
        let mut sse = [0.0f64; 3];
        let mut loo_sum = 0.0f64;
        let mut loo_count = 0usize;
        for (k, o) in values.chunks_exact(channels).enumerate() {
            for (ch, &i) in o.iter().enumerate() {
                let row = rows[k * channels + ch];
                if row[3] == 0.0 {
                    continue;
                }
                let r = Vector3::new(row[0], row[1], row[2]);
                let w = row[3];
                let i = i as f64;
                let e = i - r.dot(&g[ch]);
                let h = w * r.dot(&(inv[ch] * r));
                let loo = e / (1.0 - h);
                sse[ch] += w * e * e;
                let sum = &mut sums[k];
                if loo.is_finite() {
                    loo_sum += loo.abs();
                    loo_count += 1;
                    sum[1] += loo * loo;
                }
                sum[0] += e * e;
                sum[2] += i;
            }
            if rows[k * channels][3] != 0.0 {
                sums[k][3] += 1.0;
            }
        }
        trust_values(&sse, &inv, b, used, channels, loo_sum, loo_count)
    }
}

/// `[normal sigma (degrees), mean |leave-one-out residual|]` of a facet from its per-channel
/// weighted squared residuals `sse`, inverse normal matrices `inv`, summed scaled normal `b`,
/// `used` (>= 4) usable lights and the sum and count of its finite leave-one-out residuals.
#[inline]
pub(super) fn trust_values(
    sse: &[f64; 3],
    inv: &[Matrix3<f64>; 3],
    b: Vector3<f64>,
    used: usize,
    channels: usize,
    loo_sum: f64,
    loo_count: usize,
) -> [f32; 2] {
    let dof = (used - 3) as f64;
    let mut cov = Matrix3::<f64>::zeros();
    for ch in 0..channels {
        cov += (sse[ch] / dof) * inv[ch];
    }
    let len = norm([b.x, b.y, b.z]);
    if !(len.is_finite() && len > 0.0) {
        return [f32::NAN; 2];
    }
    let n = b / len;
    // trace(P C P) = trace(C) - n^T C n for P = I - n n^T.
    let var = ((cov.trace() - n.dot(&(cov * n))) / (len * len)).max(0.0);
    let held_out = if loo_count > 0 {
        loo_sum / loo_count as f64
    } else {
        f64::NAN
    };
    [var.sqrt().to_degrees() as f32, held_out as f32]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Geometry;
    use crate::grid::Grid;
    use crate::light::Light;
    use crate::local::{FitSettings, Model, Observations};
    use crate::rig::Camera;
    use crate::vec3::{dot, normalize};

    /// A flat tilted 24 x 24 patch 100 mm away under 12 LEDs, its images with Gaussian noise of
    /// `sigma` (seeded), and the true normal.
    fn patch(sigma: f64, seed: u64) -> (Grid, Geometry, Vec<Light>, Vec<f32>, Vec<f64>, [f64; 3]) {
        let (h, w) = (24, 24);
        let grid = Grid::new(h, w, None).unwrap();
        let camera = Camera::Orthographic {
            pixel_size: [1.0, 1.0],
            origin: [-12.0, -12.0],
        };
        let geometry = Geometry::new(&camera, &grid).unwrap();
        let n = normalize([0.2, -0.1, -1.0]);
        // Plane n . x = n . (0, 0, 100): z = (d - n_x x - n_y y) / n_z.
        let d = n[2] * 100.0;
        let u: Vec<f64> = (0..grid.n_unknowns())
            .map(|i| {
                let x = geometry.position_at_depth(i, 100.0);
                (d - n[0] * x[0] - n[1] * x[1]) / n[2]
            })
            .collect();
        let lights: Vec<Light> = (0..12)
            .map(|i| {
                let a = i as f64 * std::f64::consts::TAU / 12.0;
                let r = if i % 2 == 0 { 60.0 } else { 35.0 };
                Light::point([r * a.cos(), r * a.sin(), 10.0 + 3.0 * i as f64])
            })
            .map(|l| match l {
                Light::Point {
                    position, axis, mu, ..
                } => Light::Point {
                    position,
                    intensity: [2000.0; 3],
                    axis,
                    mu,
                },
                other => other,
            })
            .collect();
        // Gaussian noise: Box-Muller on a splitmix64 stream.
        let mut state = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15);
        let mut uniform = move || {
            state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = state;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut rng = move || {
            let (a, b) = (uniform().max(1e-300), uniform());
            (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
        };
        let mut images = vec![0.0f32; lights.len() * h * w];
        for f in 0..grid.n_facets() {
            let q = geometry.facet_corners(&grid, f, &u);
            let c = quad_centre(&q);
            for (k, l) in lights.iter().enumerate() {
                let (b, _) = l.beta(c);
                let v = 0.7 * 2000.0 * dot(n, b).max(0.0);
                images[k * h * w + grid.facets[f] as usize] = (v + sigma * rng()) as f32;
            }
        }
        (grid, geometry, lights, images, u, n)
    }

    /// Over several seeds, the RMS angle between the fitted and the true normal matches the
    /// RMS predicted sigma within 0.8 .. 1.25, and the held-out error is about
    /// sqrt(2 / pi) sigma times a leverage factor above 1.
    #[test]
    fn predicted_sigma_matches_the_observed_error() {
        for (seed, sigma) in [(1, 0.01), (2, 0.003), (3, 0.02), (4, 0.01)] {
            let (grid, geometry, lights, images, u, n_true) = patch(sigma, seed);
            let k = lights.len();
            let obs = Observations::from_stack(&images, k, grid.height * grid.width, 1);
            let step = LocalStep::new(
                &grid,
                &geometry,
                Model::Near(&lights),
                &obs,
                FitSettings {
                    dark: -1.0,
                    ..FitSettings::default()
                },
            );
            let trust = step.trust(&u).unwrap();
            let mut fits = vec![crate::local::FacetFit::EMPTY; grid.n_facets()];
            step.run(&u, 0, &mut fits);
            let (mut observed, mut predicted) = (0.0, 0.0);
            for (f, fit) in fits.iter().enumerate() {
                let angle = dot(fit.normal, n_true).clamp(-1.0, 1.0).acos().to_degrees();
                observed += angle * angle;
                let s = trust.normal_sigma[grid.facets[f] as usize] as f64;
                predicted += s * s;
            }
            let ratio = (observed / predicted).sqrt();
            assert!((0.8..1.25).contains(&ratio), "seed {seed}: ratio {ratio}");
            let mean_loo =
                trust.held_out.iter().map(|&v| v as f64).sum::<f64>() / trust.held_out.len() as f64;
            let expected = (2.0 / std::f64::consts::PI).sqrt() * sigma;
            assert!(
                (1.0..1.6).contains(&(mean_loo / expected)),
                "seed {seed}: held-out {mean_loo} vs {expected}"
            );
            for l in &trust.lights {
                assert_eq!(l.facets, grid.n_facets());
                assert!((l.residual / sigma - 0.85).abs() < 0.2, "{l:?}");
                assert!(l.held_out > l.residual);
            }
        }
    }
}
