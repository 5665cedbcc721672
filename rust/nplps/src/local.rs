//! Local step: fit each facet's normal under the near-light model and turn it into target corner
//! depths.
//!
//! For facet f with centre `c` (mean of its 4 corners) and usable lights `I_k > dark`, with
//! `a_k = p_k - c`, the scaled normal `g = rho * n` solves the 3 x 3 normal equations `T g = s`:
//! - [`Weighting::Image`] (default): `b_k = a_k / |a_k|^3`, `T = sum b_k b_k^T`,
//!   `s = sum I_k b_k`, i.e. least squares of the image model `I_k = b_k . g` in image units;
//! - [`Weighting::Paper`] (Eq. 6 of Xie et al.): `T = sum a_k a_k^T`, `s = sum |a_k|^3 I_k a_k`.
//!
//! Then `rho = |g|`, `n = g / rho`, and the facet's target is the plane through `c` with normal
//! `n`: corner j at offset `(dx_j, dy_j)` from the centre gets `p_j = c_z - (n_x dx_j + n_y dy_j)
//! / n_z'` with `n_z' = min(n_z, -NZ_MIN)`. The global step only sees the mean-subtracted target
//! `N p = -(n_x dx + n_y dy) / n_z'`. A facet with fewer than 3 usable lights, or a singular
//! system, keeps its current shape (`target = N z(f)`) and reports no albedo.

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use crate::grid::{dot, quad_centre, quad_normal, sub, Grid, CORNER_OFFSETS};
use crate::rig::Camera;

/// Largest allowed `n_z` of a fitted normal when it is turned into a plane (`-NZ_MIN`), which
/// bounds the target slopes of grazing fits.
pub const NZ_MIN: f64 = 0.01;

/// How the per-facet linear system weights the lights.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Weighting {
    /// Least squares in image units (lower normal error under image noise).
    #[default]
    Image,
    /// The paper's Eq. 6: each equation multiplied by `|a_k|^3`.
    Paper,
}

/// The local fit of one facet.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FacetFit {
    /// Mean-subtracted target corner depths (order 00, 01, 10, 11).
    pub target: [f64; 4],
    /// Fitted unit normal (the mesh normal for an invalid facet).
    pub normal: [f64; 3],
    /// Fitted albedo `rho` (NaN for an invalid facet).
    pub albedo: f64,
    /// Sum of squared image residuals `(b_k . g - I_k)^2` over the usable lights.
    pub sse: f64,
    /// Number of usable lights.
    pub used: u32,
    /// Whether the fit succeeded (>= 3 usable lights, regular system).
    pub valid: bool,
}

impl FacetFit {
    /// A placeholder before the first fit.
    pub const EMPTY: FacetFit = FacetFit {
        target: [0.0; 4],
        normal: [f64::NAN; 3],
        albedo: f64::NAN,
        sse: 0.0,
        used: 0,
        valid: false,
    };

    /// RMS image residual over the usable lights (NaN for an invalid facet).
    pub fn rms(&self) -> f64 {
        if self.valid {
            (self.sse / self.used as f64).sqrt()
        } else {
            f64::NAN
        }
    }
}

/// Per-facet observations, facet-major: `obs[f * k + i]` is facet f's intensity under light i.
pub struct Observations {
    /// Number of lights k.
    pub k: usize,
    /// Intensities, `n_facets * k`.
    pub values: Vec<f32>,
}

/// Settings of the per-facet fits.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FitSettings {
    /// Observations at or below this value (and NaN) are shadowed and left out.
    pub dark: f64,
    /// Take the residual from the normal equations instead of a second pass (see [`fit_facet`]).
    pub fast_residual: bool,
}

/// The lighting model a facet is fitted with.
#[derive(Debug, Clone, Copy)]
pub enum Model<'a> {
    /// Near point lights at these positions (the method's model).
    Near(&'a [[f64; 3]], Weighting),
    /// Parallel lights along these unit directions, no falloff (the conventional baseline).
    Parallel(&'a [[f64; 3]]),
}

impl Model<'_> {
    /// Whether every equation has weight 1 (the residual then follows from the normal equations).
    #[inline]
    fn unit_weights(&self) -> bool {
        !matches!(self, Model::Near(_, Weighting::Paper))
    }

    /// For light k seen from the point `c`: the vector `b` of the image model `I = b . g`, and
    /// the weight that multiplies the equation.
    #[inline]
    fn row(&self, k: usize, c: [f64; 3]) -> ([f64; 3], f64) {
        match *self {
            Model::Near(lights, weighting) => {
                let a = sub(lights[k], c);
                let d2 = dot(a, a);
                let d3 = d2 * d2.sqrt();
                let inv = 1.0 / d3;
                let b = [a[0] * inv, a[1] * inv, a[2] * inv];
                match weighting {
                    Weighting::Image => (b, 1.0),
                    Weighting::Paper => (b, d3),
                }
            }
            Model::Parallel(directions) => (directions[k], 1.0),
        }
    }
}

/// Runs the local step on every facet in parallel (rayon), writing `fits` (see [`fit_facet`]
/// for `fast_residual`).
pub fn local_step(
    grid: &Grid,
    camera: &Camera,
    model: Model<'_>,
    obs: &Observations,
    z: &[f64],
    settings: FitSettings,
    fits: &mut [FacetFit],
) {
    let pixel_size = camera.pixel_size();
    fits.par_iter_mut().enumerate().for_each(|(f, fit)| {
        let q = grid.facet_corners(camera, f, z);
        let intensities = &obs.values[f * obs.k..(f + 1) * obs.k];
        *fit = fit_facet(&q, model, intensities, pixel_size, settings);
    });
}

/// Fits one facet with corners `q` (see the module documentation).
///
/// The symmetric 3 x 3 system is accumulated entry by entry and solved by nalgebra's Cholesky
/// factorization (failure = singular system). With `fast_residual` and unit equation weights the
/// residual follows from the normal equations, `sum (b_k . g - I_k)^2 = sum I_k^2 - g . s`,
/// without a second pass over the lights (exact up to a cancellation of order
/// `sqrt(eps * sum I_k^2)`, fine for the per-iteration history); otherwise it is summed exactly.
pub fn fit_facet(
    q: &[[f64; 3]; 4],
    model: Model<'_>,
    intensities: &[f32],
    pixel_size: [f64; 2],
    settings: FitSettings,
) -> FacetFit {
    let FitSettings {
        dark,
        fast_residual,
    } = settings;
    let c = quad_centre(q);
    let usable = |i: f32| !(i.is_nan() || i as f64 <= dark);
    // Upper triangle of T (t00, t01, t02, t11, t12, t22), right side s, sum of I^2.
    let mut t = [0.0f64; 6];
    let mut s = [0.0f64; 3];
    let mut sum_i2 = 0.0;
    let mut used = 0u32;
    for (k, &i) in intensities.iter().enumerate() {
        if !usable(i) {
            continue;
        }
        let i = i as f64;
        let (b, w) = model.row(k, c);
        let r = [b[0] * w, b[1] * w, b[2] * w];
        let y = w * i;
        t[0] += r[0] * r[0];
        t[1] += r[0] * r[1];
        t[2] += r[0] * r[2];
        t[3] += r[1] * r[1];
        t[4] += r[1] * r[2];
        t[5] += r[2] * r[2];
        s[0] += r[0] * y;
        s[1] += r[1] * y;
        s[2] += r[2] * y;
        sum_i2 += i * i;
        used += 1;
    }
    if used < 3 {
        return keep_shape(q, used);
    }
    let tm = Matrix3::new(t[0], t[1], t[2], t[1], t[3], t[4], t[2], t[4], t[5]);
    let Some(g) = solve_spd3(&tm, &Vector3::from(s)) else {
        return keep_shape(q, used);
    };
    let rho = g.norm();
    if !(rho.is_finite() && rho > 0.0) {
        return keep_shape(q, used);
    }
    let g = [g.x, g.y, g.z];
    let sse = if fast_residual && model.unit_weights() {
        (sum_i2 - dot(g, s)).max(0.0)
    } else {
        intensities
            .iter()
            .enumerate()
            .filter(|(_, i)| usable(**i))
            .map(|(k, &i)| {
                let e = dot(model.row(k, c).0, g) - i as f64;
                e * e
            })
            .sum()
    };
    let n = [g[0] / rho, g[1] / rho, g[2] / rho];
    FacetFit {
        target: plane_target(n, pixel_size),
        normal: n,
        albedo: rho,
        sse,
        used,
        valid: true,
    }
}

/// Solves `T g = s` for a symmetric 3 x 3 `T`, or `None` when `T` is not (numerically) positive
/// definite: its determinant must exceed `1e-12` times the product of its diagonal (Hadamard's
/// bound), which rejects singular and nearly singular light configurations. nalgebra's closed-form
/// inverse keeps the dependency chain per facet short (a Cholesky factorization chains three
/// square roots and several divisions).
#[inline]
fn solve_spd3(t: &Matrix3<f64>, s: &Vector3<f64>) -> Option<Vector3<f64>> {
    let diag = t[(0, 0)] * t[(1, 1)] * t[(2, 2)];
    let det = t.determinant();
    if !(diag > 0.0 && det > 1e-12 * diag) {
        return None;
    }
    t.try_inverse().map(|inv| inv * s)
}

/// Mean-subtracted corner depths of the plane with normal `n` (n_z limited to `-NZ_MIN`).
#[inline]
pub fn plane_target(n: [f64; 3], pixel_size: [f64; 2]) -> [f64; 4] {
    let nz = n[2].min(-NZ_MIN);
    CORNER_OFFSETS.map(|[ox, oy]| -(n[0] * ox * pixel_size[0] + n[1] * oy * pixel_size[1]) / nz)
}

/// The fit of a facet that cannot be fitted: it keeps its current (mean-subtracted) shape.
fn keep_shape(q: &[[f64; 3]; 4], used: u32) -> FacetFit {
    let mean = 0.25 * (q[0][2] + q[1][2] + q[2][2] + q[3][2]);
    FacetFit {
        target: std::array::from_fn(|j| q[j][2] - mean),
        normal: quad_normal(q),
        albedo: f64::NAN,
        sse: 0.0,
        used,
        valid: false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const EXACT: FitSettings = FitSettings {
        dark: 0.0,
        fast_residual: false,
    };

    fn lights() -> Vec<[f64; 3]> {
        vec![
            [30.0, 0.0, -50.0],
            [-20.0, 25.0, -60.0],
            [-10.0, -30.0, -40.0],
            [5.0, 5.0, -80.0],
        ]
    }

    /// A tilted plane facet and its exact images.
    fn facet() -> ([[f64; 3]; 4], [f64; 3], Vec<f32>) {
        let slope = [0.3, -0.2];
        let q: [[f64; 3]; 4] = std::array::from_fn(|j| {
            let [dx, dy] = CORNER_OFFSETS[j];
            [dx, dy, 100.0 + slope[0] * dx + slope[1] * dy]
        });
        let n = crate::grid::normalize([slope[0], slope[1], -1.0]);
        let c = quad_centre(&q);
        let rho = 2.0e4;
        let images = lights()
            .iter()
            .map(|p| {
                let a = sub(*p, c);
                (rho * dot(n, a).max(0.0) / dot(a, a).powf(1.5)) as f32
            })
            .collect();
        (q, n, images)
    }

    #[test]
    fn exact_images_give_the_exact_plane() {
        let (q, n, images) = facet();
        for weighting in [Weighting::Image, Weighting::Paper] {
            let l = lights();
            let fit = fit_facet(&q, Model::Near(&l, weighting), &images, [1.0, 1.0], EXACT);
            assert!(fit.valid);
            assert_eq!(fit.used, 4);
            let err = dot(fit.normal, n).clamp(-1.0, 1.0).acos().to_degrees();
            assert!(err < 1e-4, "{weighting:?}: {err} degrees");
            assert!((fit.albedo / 2.0e4 - 1.0).abs() < 1e-5);
            let mean = 0.25 * q.iter().map(|p| p[2]).sum::<f64>();
            for (t, corner) in fit.target.iter().zip(&q) {
                assert!((t - (corner[2] - mean)).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn shadowed_facet_keeps_its_shape() {
        let (q, _, mut images) = facet();
        images[0] = 0.0;
        images[1] = -1.0;
        let l = lights();
        let fit = fit_facet(
            &q,
            Model::Near(&l, Weighting::Image),
            &images,
            [1.0, 1.0],
            EXACT,
        );
        assert!(!fit.valid);
        assert_eq!(fit.used, 2);
        assert!(fit.albedo.is_nan() && fit.rms().is_nan());
        assert!(fit.target.iter().all(|t| t.is_finite()));
        assert!((fit.target.iter().sum::<f64>()).abs() < 1e-12);
    }

    #[test]
    fn fast_residual_matches_the_exact_one_on_noisy_data() {
        let (q, _, images) = facet();
        let noisy: Vec<f32> = images
            .iter()
            .enumerate()
            .map(|(k, &v)| v * (1.0 + 0.02 * (k as f32 - 1.5)))
            .collect();
        let l = lights();
        let model = Model::Near(&l, Weighting::Image);
        let fast = fit_facet(
            &q,
            model,
            &noisy,
            [1.0, 1.0],
            FitSettings {
                fast_residual: true,
                ..EXACT
            },
        );
        let exact = fit_facet(&q, model, &noisy, [1.0, 1.0], EXACT);
        assert!(exact.rms() > 0.0);
        assert!((fast.rms() / exact.rms() - 1.0).abs() < 1e-6);
        assert_eq!(fast.normal, exact.normal);
    }
}
