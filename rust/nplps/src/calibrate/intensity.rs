//! Intensity calibration from images of a flat diffuse board (see the
//! [module documentation](super)).
//!
//! Every masked pixel's viewing ray meets the board plane `n . X = d` at `X`, and the image
//! model is `I_i(X) = rho(X) Phi_i max(0, n . beta_i(X))` ([`Light::beta`]).
//! - Uniform board: `Phi_i rho` per light and channel is the one-parameter linear least-squares
//!   fit `Phi_c = sum I rho s / sum (rho s)^2` ([`fit_phi`]).
//! - [`BoardAlbedo::PerPixel`]: alternating least squares (a rank-one factorisation) of the
//!   intensities and the albedo per pixel and channel `rho_j = sum_i I Phi s / sum_i (Phi s)^2`,
//!   with the gauge mean albedo 1 per channel.
//! - LED shape: each point light's anisotropy `mu` (and principal direction) by
//!   Levenberg–Marquardt with the intensities eliminated (variable projection, [`fit_shape`]).
//!
//! `rho` and the exposure are not separable from `Phi`: the intensities are relative, scaled to
//! a geometric mean of 1 over all lights and channels.

use super::fits::tangent_basis;
use crate::error::{Error, Result};
use crate::light::Light;
use crate::rig::{Camera, Rig};
use crate::vec3::{add, dot, norm, scale, sub, unit};

/// A plane `normal . X = offset` in the camera frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plane {
    /// Normal (any length; normalised and turned towards the camera internally).
    pub normal: [f64; 3],
    /// Offset d.
    pub offset: f64,
}

impl Plane {
    /// The plane z = `depth` (a board facing the camera).
    pub fn at_depth(depth: f64) -> Plane {
        Plane {
            normal: [0.0, 0.0, -1.0],
            offset: -depth,
        }
    }

    /// Unit normal facing the camera (n_z < 0) and the matching offset.
    fn facing(&self) -> Result<([f64; 3], f64)> {
        let n = norm(self.normal);
        if !(n > 0.0 && n.is_finite() && self.offset.is_finite()) {
            return Err(Error::Unusable(format!(
                "the board plane needs a finite non-zero normal and a finite offset, got {self:?}"
            )));
        }
        let (mut u, mut d) = (scale(self.normal, 1.0 / n), self.offset / n);
        if u[2] > 0.0 {
            u = scale(u, -1.0);
            d = -d;
        }
        if u[2].abs() < 1e-6 {
            return Err(Error::Unusable(
                "the board plane is seen edge-on (its normal is perpendicular to the view)".into(),
            ));
        }
        Ok((u, d))
    }

    /// Where the viewing ray of (u, v) meets the plane (None behind the camera).
    pub fn intersect(&self, camera: &Camera, uv: [f64; 2]) -> Option<[f64; 3]> {
        let (n, d) = self.facing().ok()?;
        let ray = camera.ray(uv);
        let denom = dot(n, ray.direction);
        if denom == 0.0 {
            return None;
        }
        let t = (d - dot(n, ray.origin)) / denom;
        (t > 0.0 || matches!(camera, Camera::Orthographic { .. })).then(|| ray.at(t))
    }
}

/// The board's albedo model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum BoardAlbedo {
    /// One albedo for the whole board (per channel): a plain linear fit per light.
    #[default]
    Uniform,
    /// One albedo per pixel and channel, shared by all lights (absorbs texture of the board and
    /// vignetting): alternating least squares.
    PerPixel,
}

/// Options of [`calibrate_intensities`].
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub struct IntensityOptions {
    /// Fit each point light's anisotropy mu (>= 0).
    pub fit_mu: bool,
    /// Fit each point light's principal direction (with `fit_mu`).
    pub fit_axis: bool,
    /// The board's albedo model.
    pub albedo: BoardAlbedo,
    /// Observations at or below this value are left out.
    pub dark: f64,
    /// Observations at or above this value are left out.
    pub saturation: f64,
    /// Most alternations (per-pixel albedo) or Levenberg–Marquardt steps.
    pub iterations: usize,
}

impl Default for IntensityOptions {
    fn default() -> Self {
        IntensityOptions {
            fit_mu: false,
            fit_axis: false,
            albedo: BoardAlbedo::Uniform,
            dark: 0.0,
            saturation: f64::INFINITY,
            iterations: 100,
        }
    }
}

with_fields!(IntensityOptions {
    with_fit_mu: fit_mu: bool,
    with_fit_axis: fit_axis: bool,
    with_albedo: albedo: BoardAlbedo,
    with_dark: dark: f64,
    with_saturation: saturation: f64,
    with_iterations: iterations: usize,
});

/// One light's fitted parameters.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct IntensityReport {
    /// Relative intensity per channel (geometric mean 1 over all lights and channels).
    pub intensity: Vec<f64>,
    /// Anisotropy (as given unless fitted; 0 for directional lights).
    pub mu: f64,
    /// Principal direction (as given unless fitted).
    pub axis: [f64; 3],
    /// RMS residual over the light's observations, relative to their mean.
    pub rms: f64,
    /// Observations used (pixels x channels).
    pub observations: usize,
}

/// The result of [`calibrate_intensities`].
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct IntensityCalibration {
    /// The lights with fitted intensities (and mu, axes).
    pub lights: Vec<Light>,
    /// Per-light reports.
    pub reports: Vec<IntensityReport>,
    /// The common factor removed from the intensities (board albedo times exposure, per
    /// channel mean), so that `I = scale * rho_rel * Phi_rel * shading`.
    pub scale: f64,
    /// Relative board albedo per pixel and channel (H x W x C, NaN outside the mask or unused;
    /// all 1 for a uniform board).
    pub albedo: Vec<f64>,
    /// Alternations (or LM iterations) run.
    pub iterations: usize,
    /// Notes and warnings.
    pub warnings: Vec<String>,
}

/// A point light's shading function parameters during the fit.
#[derive(Debug, Clone, Copy)]
struct Shape {
    mu: f64,
    axis: [f64; 3],
}

/// Shading `max(0, n . beta(X))` of every board point under `light` (intensity excluded; see
/// [`Light::shading`]).
fn shading(light: &Light, n: [f64; 3], points: &[[f64; 3]]) -> Vec<f64> {
    points.iter().map(|&x| light.shading(n, x)).collect()
}

/// Per-channel least-squares intensities `Phi_c = sum I rho s / sum (rho s)^2` and the residual
/// sum of squares, over the valid observations.
fn fit_phi(obs: &[(usize, f32)], channels: usize, s: &[f64], rho: &[f64]) -> (Vec<f64>, f64) {
    let mut num = vec![0.0; channels];
    let mut den = vec![0.0; channels];
    for &(j, v) in obs {
        let (p, c) = (j / channels, j % channels);
        let m = rho[j] * s[p];
        num[c] += v as f64 * m;
        den[c] += m * m;
    }
    let phi: Vec<f64> = num
        .iter()
        .zip(&den)
        .map(|(n, d)| if *d > 0.0 { n / d } else { 0.0 })
        .collect();
    let rss = obs
        .iter()
        .map(|&(j, v)| {
            let (p, c) = (j / channels, j % channels);
            (v as f64 - phi[c] * rho[j] * s[p]).powi(2)
        })
        .sum();
    (phi, rss)
}

/// What the board shows of one light: the plane's unit normal `n`, the board points of the
/// pixels, the lit observations `(j, value)` with `j = pixel * channels + channel`, and the
/// albedo `rho[j]` of each pixel and channel.
struct LitBoard<'a> {
    n: [f64; 3],
    points: &'a [[f64; 3]],
    obs: &'a [(usize, f32)],
    channels: usize,
    rho: &'a [f64],
}

/// Levenberg–Marquardt over (mu, axis) of one point light with the intensities eliminated.
fn fit_shape(
    light: &Light,
    start: Shape,
    fit_axis: bool,
    board: &LitBoard<'_>,
    iterations: usize,
) -> (Shape, usize) {
    let LitBoard {
        n,
        points,
        obs,
        channels,
        rho,
    } = *board;
    // Parameters: mu and two tangent offsets of the axis.
    let np = if fit_axis { 3 } else { 1 };
    let residuals = |shape: Shape| -> Vec<f64> {
        let s = shading(&light.with_shape(shape.mu, shape.axis), n, points);
        let (phi, _) = fit_phi(obs, channels, &s, rho);
        obs.iter()
            .map(|&(j, v)| {
                let (p, c) = (j / channels, j % channels);
                v as f64 - phi[c] * rho[j] * s[p]
            })
            .collect()
    };
    let apply = |shape: Shape, delta: &[f64]| -> Shape {
        let mu = (shape.mu + delta[0]).max(0.0);
        let axis = if np == 3 {
            let a = shape.axis;
            let (e1, e2) = tangent_basis(a);
            unit(add(a, add(scale(e1, delta[1]), scale(e2, delta[2]))))
        } else {
            shape.axis
        };
        Shape { mu, axis }
    };
    let mut shape = start;
    let mut r = residuals(shape);
    let mut cost: f64 = r.iter().map(|v| v * v).sum();
    let mut lambda = 1e-3;
    let mut done = 0;
    for it in 0..iterations {
        done = it + 1;
        // Forward-difference Jacobian.
        let mut jac = vec![vec![0.0; r.len()]; np];
        for (q, col) in jac.iter_mut().enumerate() {
            let h = if q == 0 {
                1e-6 * (1.0 + shape.mu)
            } else {
                1e-7
            };
            let mut delta = vec![0.0; np];
            delta[q] = h;
            let rq = residuals(apply(shape, &delta));
            for (cv, (a, b)) in col.iter_mut().zip(rq.iter().zip(&r)) {
                *cv = (a - b) / h;
            }
        }
        let mut jtj = nalgebra::DMatrix::<f64>::zeros(np, np);
        let mut jtr = nalgebra::DVector::<f64>::zeros(np);
        for a in 0..np {
            for b in 0..np {
                jtj[(a, b)] = jac[a].iter().zip(&jac[b]).map(|(x, y)| x * y).sum();
            }
            jtr[a] = jac[a].iter().zip(&r).map(|(x, y)| x * y).sum();
        }
        let mut improved = false;
        for _ in 0..12 {
            let mut m = jtj.clone();
            for d in 0..np {
                m[(d, d)] += lambda * (jtj[(d, d)] + 1e-12);
            }
            let Some(step) = m.cholesky().map(|c| c.solve(&(-&jtr))) else {
                lambda *= 10.0;
                continue;
            };
            let trial = apply(shape, step.as_slice());
            let rt = residuals(trial);
            let ct: f64 = rt.iter().map(|v| v * v).sum();
            if ct < cost {
                let rel = (cost - ct) / cost.max(1e-300);
                shape = trial;
                r = rt;
                cost = ct;
                lambda = (lambda * 0.3).max(1e-9);
                improved = true;
                if rel < 1e-12 {
                    return (shape, done);
                }
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    (shape, done)
}

/// The board images of [`calibrate_intensities`]: k images of H x W pixels with C channels
/// (k x H x W x C, row-major, the rig's light order) and an optional H x W mask of the board's
/// pixels (`true` = board; None: all).
#[derive(Debug, Clone, Copy)]
pub struct BoardImages<'a> {
    /// The pixel values, k x H x W x C.
    pub images: &'a [f32],
    /// Number of images k (one per light).
    pub k: usize,
    /// Image height H.
    pub height: usize,
    /// Image width W.
    pub width: usize,
    /// Channels C (1 or 3).
    pub channels: usize,
    /// The board's pixels (None: every pixel).
    pub mask: Option<&'a [bool]>,
}

/// Calibrates the light intensities (and optionally LED anisotropy and axes) from k images
/// (k x H x W x C) of a flat diffuse board on `plane`; see the [module documentation](super).
/// `mask` (H x W) selects the board's pixels (None: all). Light positions come from `lights`.
pub fn calibrate_intensities(
    camera: &Camera,
    board: &BoardImages<'_>,
    plane: &Plane,
    lights: &[Light],
    options: &IntensityOptions,
) -> Result<IntensityCalibration> {
    let BoardImages {
        images,
        k,
        height,
        width,
        channels,
        mask,
    } = *board;
    camera.validate()?;
    let (n, _) = plane.facing()?;
    let npx = height * width;
    if lights.len() != k || k == 0 {
        return Err(Error::Shape {
            what: "board images",
            expected: lights.len(),
            got: k,
            message: format!(
                "{k} board images but {} lights in the rig: give one image per light",
                lights.len()
            ),
        });
    }
    if channels != 1 && channels != 3 {
        return Err(Error::OutOfRange {
            name: "channels",
            value: channels as f64,
            message: format!("channels must be 1 or 3, got {channels}"),
        });
    }
    if images.len() != k * npx * channels {
        return Err(Error::Shape {
            what: "board images",
            expected: k
                .saturating_mul(height)
                .saturating_mul(width)
                .saturating_mul(channels),
            got: images.len(),
            message: format!(
                "expected {k} images x {width} x {height} pixels x {channels} channels of values, got {}",
                images.len()
            ),
        });
    }
    if let Some(m) = mask {
        if m.len() != npx {
            return Err(Error::Shape {
                what: "mask",
                expected: height * width,
                got: m.len(),
                message: format!(
                    "the mask has {} pixels, the images {width} x {height}",
                    m.len()
                ),
            });
        }
    }
    if images.iter().any(|v| !v.is_finite()) {
        return Err(Error::Unusable(
            "the board images contain non-finite values".into(),
        ));
    }
    Rig {
        camera: *camera,
        lights: lights.to_vec(),
    }
    .validate_parameters()?;
    // Board points of the masked pixels.
    let mut pixels = Vec::new();
    let mut points = Vec::new();
    for p in 0..npx {
        if mask.is_some_and(|m| !m[p]) {
            continue;
        }
        if let Some(x) = plane.intersect(camera, [(p % width) as f64, (p / width) as f64]) {
            pixels.push(p);
            points.push(x);
        }
    }
    if pixels.is_empty() {
        return Err(Error::Unusable(
            "no board pixel: the mask is empty or the plane is behind the camera".into(),
        ));
    }
    let m = pixels.len();
    let mut warnings = Vec::new();
    // Initial shapes.
    let centroid = scale(
        points.iter().fold([0.0; 3], |a, &x| add(a, x)),
        1.0 / m as f64,
    );
    let mut shapes: Vec<Shape> = lights
        .iter()
        .map(|l| match *l {
            Light::Point {
                position, axis, mu, ..
            } => {
                let axis = if mu > 0.0 || !options.fit_axis {
                    axis
                } else {
                    unit(sub(centroid, position))
                };
                let mu = if options.fit_mu && mu == 0.0 { 1.0 } else { mu };
                Shape { mu, axis }
            }
            Light::Directional { .. } => Shape {
                mu: 0.0,
                axis: [0.0, 0.0, 1.0],
            },
        })
        .collect();
    // Valid observations per light: (index into the m x C albedo, value).
    let value = |i: usize, q: usize, c: usize| images[(i * npx + pixels[q]) * channels + c];
    let valid = |v: f32| (v as f64) > options.dark && (v as f64) < options.saturation;
    let obs: Vec<Vec<(usize, f32)>> = (0..k)
        .map(|i| {
            (0..m)
                .flat_map(|q| (0..channels).map(move |c| (q, c)))
                .filter_map(|(q, c)| {
                    let v = value(i, q, c);
                    valid(v).then_some((q * channels + c, v))
                })
                .collect()
        })
        .collect();
    let mut rho = vec![1.0; m * channels];
    let is_point = |l: &Light| matches!(l, Light::Point { .. });
    let fit_any_shape = options.fit_mu;
    let mut phi = vec![vec![0.0; channels]; k];
    let mut s_all: Vec<Vec<f64>> = (0..k)
        .map(|i| {
            shading(
                &lights[i].with_shape(shapes[i].mu, shapes[i].axis),
                n,
                &points,
            )
        })
        .collect();
    let outer = match options.albedo {
        BoardAlbedo::Uniform => 1,
        BoardAlbedo::PerPixel => options.iterations.max(1),
    };
    let mut iterations = 0;
    let mut last_rss = f64::INFINITY;
    for it in 0..outer {
        iterations = it + 1;
        let mut rss_total = 0.0;
        for i in 0..k {
            // Observations the model lights (s > 0) count.
            let lit: Vec<(usize, f32)> = obs[i]
                .iter()
                .copied()
                .filter(|&(j, _)| s_all[i][j / channels] > 0.0)
                .collect();
            if lit.len() < 3 {
                return Err(Error::Unusable(format!(
                    "light {i}: fewer than 3 usable board pixels (all dark, saturated, or facing away from the light)"
                )));
            }
            if fit_any_shape && is_point(&lights[i]) {
                let board = LitBoard {
                    n,
                    points: &points,
                    obs: &lit,
                    channels,
                    rho: &rho,
                };
                let (shape, steps) = fit_shape(
                    &lights[i],
                    shapes[i],
                    options.fit_axis,
                    &board,
                    if options.albedo == BoardAlbedo::Uniform {
                        options.iterations
                    } else {
                        3
                    },
                );
                if options.albedo == BoardAlbedo::Uniform {
                    iterations = iterations.max(steps);
                }
                shapes[i] = shape;
                s_all[i] = shading(&lights[i].with_shape(shape.mu, shape.axis), n, &points);
            }
            let (p, rss) = fit_phi(&lit, channels, &s_all[i], &rho);
            phi[i] = p;
            rss_total += rss;
        }
        if options.albedo == BoardAlbedo::Uniform {
            break;
        }
        // Albedo step: rho_j = sum_i I Phi s / sum_i (Phi s)^2 per pixel and channel.
        let mut num = vec![0.0; m * channels];
        let mut den = vec![0.0; m * channels];
        for i in 0..k {
            for &(j, v) in &obs[i] {
                let a = phi[i][j % channels] * s_all[i][j / channels];
                if a > 0.0 {
                    num[j] += v as f64 * a;
                    den[j] += a * a;
                }
            }
        }
        for j in 0..m * channels {
            rho[j] = if den[j] > 0.0 {
                num[j] / den[j]
            } else {
                f64::NAN
            };
        }
        // Fix the gauge: mean albedo 1 per channel (NaN pixels excluded from the fits).
        for c in 0..channels {
            let vals: Vec<f64> = (0..m)
                .map(|q| rho[q * channels + c])
                .filter(|v| v.is_finite())
                .collect();
            let mean = vals.iter().sum::<f64>() / vals.len().max(1) as f64;
            if mean > 0.0 {
                for q in 0..m {
                    rho[q * channels + c] /= mean;
                }
            }
        }
        for r in rho.iter_mut() {
            if !r.is_finite() {
                *r = 0.0;
            }
        }
        if (last_rss - rss_total).abs() <= 1e-12 * rss_total.max(1e-300) {
            break;
        }
        last_rss = rss_total;
    }
    // Normalise: geometric mean 1 over all lights and channels.
    let logs: Vec<f64> = phi.iter().flatten().map(|v| v.ln()).collect();
    if logs.iter().any(|v| !v.is_finite()) {
        return Err(Error::Unusable(
            "a light's fitted intensity is zero or negative: its board images are dark where the model says it is lit (wrong position or plane?)".into(),
        ));
    }
    let scale = (logs.iter().sum::<f64>() / logs.len() as f64).exp();
    let mut out_lights = Vec::with_capacity(k);
    let mut reports = Vec::with_capacity(k);
    for i in 0..k {
        let rel: Vec<f64> = phi[i].iter().map(|v| v / scale).collect();
        let intensity = if channels == 1 {
            [rel[0]; 3]
        } else {
            [rel[0], rel[1], rel[2]]
        };
        let light = match lights[i] {
            Light::Point { position, .. } => Light::Point {
                position,
                intensity,
                axis: shapes[i].axis,
                mu: shapes[i].mu,
            },
            Light::Directional { direction, .. } => Light::Directional {
                direction,
                intensity,
            },
        };
        let (mut ss, mut sv, mut count) = (0.0, 0.0, 0usize);
        for &(j, v) in &obs[i] {
            let (q, c) = (j / channels, j % channels);
            if s_all[i][q] > 0.0 {
                ss += (v as f64 - phi[i][c] * rho[j] * s_all[i][q]).powi(2);
                sv += v as f64;
                count += 1;
            }
        }
        let rms = (ss / count.max(1) as f64).sqrt() / (sv / count.max(1) as f64);
        if options.fit_mu && is_point(&lights[i]) && shapes[i].mu == 0.0 {
            warnings.push(format!(
                "light {i}: the fitted anisotropy is at its bound mu = 0 (an isotropic light)"
            ));
        }
        if count < 100 {
            warnings.push(format!(
                "light {i}: only {count} board observations are usable"
            ));
        }
        reports.push(IntensityReport {
            intensity: rel,
            mu: shapes[i].mu,
            axis: shapes[i].axis,
            rms,
            observations: count,
        });
        out_lights.push(light);
    }
    let mut albedo = vec![f64::NAN; npx * channels];
    for (q, &p) in pixels.iter().enumerate() {
        for c in 0..channels {
            albedo[p * channels + c] = rho[q * channels + c];
        }
    }
    Ok(IntensityCalibration {
        lights: out_lights,
        reports,
        scale,
        albedo,
        iterations,
        warnings,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vec3::angle;

    #[test]
    fn intensity_fit_recovers_relative_intensities_and_mu() {
        let cam = Camera::Orthographic {
            pixel_size: [2.0, 2.0],
            origin: [-40.0, -40.0],
        };
        let (h, w) = (40, 40);
        let plane = Plane::at_depth(150.0);
        let lights = vec![
            Light::Point {
                position: [30.0, 0.0, 0.0],
                intensity: [2.0; 3],
                axis: unit([-0.2, 0.0, 1.0]),
                mu: 1.5,
            },
            Light::Point {
                position: [-30.0, 10.0, 20.0],
                intensity: [0.5; 3],
                axis: unit([0.2, -0.1, 1.0]),
                mu: 0.7,
            },
            Light::Directional {
                direction: unit([0.3, 0.2, -1.0]),
                intensity: [1e-4; 3],
            },
        ];
        let rho = 3e4;
        let mut images = Vec::new();
        for l in &lights {
            for p in 0..h * w {
                let x = plane
                    .intersect(&cam, [(p % w) as f64, (p / w) as f64])
                    .unwrap();
                let s = l.shading([0.0, 0.0, -1.0], x);
                images.push((rho * l.intensity()[0] * s) as f32);
            }
        }
        let truth: Vec<f64> = lights.iter().map(|l| l.intensity()[0]).collect();
        let gm = truth.iter().map(|v| v.ln()).sum::<f64>() / 3.0;
        let start: Vec<Light> = lights
            .iter()
            .map(|l| match *l {
                Light::Point { position, .. } => Light::point(position),
                other => other,
            })
            .collect();
        let options = IntensityOptions {
            fit_mu: true,
            fit_axis: true,
            ..IntensityOptions::default()
        };
        let board = |images| BoardImages {
            images,
            k: 3,
            height: h,
            width: w,
            channels: 1,
            mask: None,
        };
        let cal = calibrate_intensities(&cam, &board(&images), &plane, &start, &options).unwrap();
        for (i, rep) in cal.reports.iter().enumerate() {
            let expected = truth[i] / gm.exp();
            assert!(
                (rep.intensity[0] / expected - 1.0).abs() < 1e-4,
                "light {i}: {rep:?}"
            );
        }
        for (rep, l) in cal.reports.iter().zip(&lights) {
            if let Light::Point { mu, axis, .. } = *l {
                assert!((rep.mu - mu).abs() < 1e-3, "{rep:?}");
                assert!(angle(rep.axis, axis) < 1e-3, "{rep:?}");
            }
        }
        // Per-pixel albedo: a textured board gives the same relative intensities.
        let texture: Vec<f64> = (0..h * w)
            .map(|p| 1.0 + 0.3 * ((p % 7) as f64 / 7.0))
            .collect();
        let textured: Vec<f32> = images
            .iter()
            .enumerate()
            .map(|(j, v)| (*v as f64 * texture[j % (h * w)]) as f32)
            .collect();
        let options = IntensityOptions {
            albedo: BoardAlbedo::PerPixel,
            iterations: 500,
            ..IntensityOptions::default()
        };
        let cal =
            calibrate_intensities(&cam, &board(&textured), &plane, &lights, &options).unwrap();
        for (i, rep) in cal.reports.iter().enumerate() {
            let expected = truth[i] / gm.exp();
            assert!(
                (rep.intensity[0] / expected - 1.0).abs() < 1e-4,
                "light {i}: {rep:?}"
            );
        }
        // Bad input is an error, not a panic.
        assert!(
            calibrate_intensities(&cam, &board(&images[..10]), &plane, &lights, &options).is_err()
        );
        let edge_on = Plane {
            normal: [1.0, 0.0, 0.0],
            offset: 0.0,
        };
        assert!(calibrate_intensities(&cam, &board(&images), &edge_on, &lights, &options).is_err());
    }
}
