//! Joint refinement of the spheres and the lights (step 6 of the
//! [module documentation](super)), a small bundle adjustment.
//!
//! Unknowns: per sphere its centre (orthographic: x, y at the given depth; pinhole: x, y, z),
//! per light seen on two or more spheres its position (or, for a directional light, two
//! tangent offsets of its direction). Residuals, minimised by Levenberg–Marquardt with a
//! forward-difference Jacobian:
//! - per highlight, the component of the unit direction to the light orthogonal to the mirror
//!   ray through the observed highlight (about the angle between them), times half the
//!   sphere's image radius (the image shift of a highlight that turns the ray by that angle),
//!   divided by the highlight noise level `sigma_h` (pixels);
//! - per sphere, the move of its centre from the outline's estimate (orthographic: x and y in
//!   pixels; pinhole: the direction of the centre and the half-angle `asin(R / |C|)` of its
//!   tangent cone, in pixels), divided by the outline's precision.
//!
//! `sigma_h` is estimated from the residuals (`sqrt(sum e^2 / (2 n_obs - n_light))`, at least
//! 0.005 pixel, two rounds), and highlights more than 5 robust standard deviations off are
//! dropped once.

use super::fits::{median, tangent_basis};
use super::rays::reflect;
use super::sphere::Sphere;
use super::triangulation::LightEstimate;
use crate::error::{Error, Result};
use crate::rig::{Camera, Ray};
use crate::vec3::{add, dot, norm, scale, sub, unit};

/// What the joint refinement did.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct Refinement {
    /// Levenberg–Marquardt iterations (all rounds).
    pub iterations: usize,
    /// Highlights used (each light seen on at least two spheres).
    pub highlights: usize,
    /// Highlights dropped as inconsistent.
    pub dropped: usize,
    /// RMS highlight residual before and after, pixel-equivalent (ray angle times half the
    /// sphere's image radius).
    pub highlight_rms: [f64; 2],
    /// RMS move of the sphere centres' images (and image radii, pinhole) away from the
    /// outlines' estimates, pixels.
    pub outline_shift: f64,
    /// The highlight noise level used to weight the highlights against the outlines, pixels.
    pub highlight_sigma: f64,
}

/// A light's parameters in the refinement.
#[derive(Debug, Clone, Copy)]
enum LightParam {
    Point,
    /// A direction near `d0`, moved in the tangent basis (e1, e2).
    Directional {
        d0: [f64; 3],
        e1: [f64; 3],
        e2: [f64; 3],
    },
}

/// The least-squares problem of [`refine_spheres`].
struct Bundle {
    radius: f64,
    perspective: bool,
    /// Orthographic: the given centre depths.
    depths: Vec<f64>,
    /// Per sphere: the outline's centre (the prior).
    prior: Vec<[f64; 3]>,
    /// Per sphere: pixels per scene unit (orthographic) or per radian (pinhole), divided by the
    /// outline's sigma (pixels).
    prior_weight: Vec<f64>,
    /// Per sphere: the outline's sigma (pixels).
    sigma_o: Vec<f64>,
    /// Per sphere: pixel-equivalent of one radian of ray angle (half the image radius).
    ray_scale: Vec<f64>,
    /// Observations: (light slot, sphere, viewing ray through the highlight).
    obs: Vec<(usize, usize, Ray)>,
    lights: Vec<LightParam>,
    sigma_h: f64,
}

impl Bundle {
    fn sphere_params(&self) -> usize {
        if self.perspective {
            3
        } else {
            2
        }
    }

    fn center(&self, theta: &[f64], s: usize) -> [f64; 3] {
        if self.perspective {
            [theta[3 * s], theta[3 * s + 1], theta[3 * s + 2]]
        } else {
            [theta[2 * s], theta[2 * s + 1], self.depths[s]]
        }
    }

    /// Light slot `l`: Ok(position) or Err(direction).
    fn light(
        &self,
        theta: &[f64],
        offsets: &[usize],
        l: usize,
    ) -> std::result::Result<[f64; 3], [f64; 3]> {
        let o = offsets[l];
        match self.lights[l] {
            LightParam::Point => Ok([theta[o], theta[o + 1], theta[o + 2]]),
            LightParam::Directional { d0, e1, e2 } => Err(unit(add(
                d0,
                add(scale(e1, theta[o]), scale(e2, theta[o + 1])),
            ))),
        }
    }

    fn offsets(&self) -> (Vec<usize>, usize) {
        let mut o = self.sphere_params() * self.prior.len();
        let mut offsets = Vec::with_capacity(self.lights.len());
        for l in &self.lights {
            offsets.push(o);
            o += match l {
                LightParam::Point => 3,
                LightParam::Directional { .. } => 2,
            };
        }
        (offsets, o)
    }

    /// The reflected ray of an observation for the sphere centre `c` (the viewing ray meets the
    /// sphere, or its closest approach is pushed onto it).
    fn ray(&self, view: &Ray, c: [f64; 3]) -> Ray {
        let oc = sub(view.origin, c);
        let b = dot(oc, view.direction);
        let disc = (b * b - (dot(oc, oc) - self.radius * self.radius)).max(0.0);
        let x = view.at(-b - disc.sqrt());
        let n = scale(sub(x, c), 1.0 / self.radius);
        Ray {
            origin: x,
            direction: unit(reflect(view.direction, n)),
        }
    }

    /// Outline (prior) residuals of the spheres, in units of their sigma: orthographic, the
    /// centre's (x, y) move; pinhole, the move of the centre's direction and of the half-angle
    /// of the tangent cone (which sets the distance).
    fn prior_residuals(&self, theta: &[f64], out: &mut Vec<f64>) {
        for (s, c0) in self.prior.iter().enumerate() {
            let c = self.center(theta, s);
            let w = self.prior_weight[s];
            if self.perspective {
                let (a0, a) = (unit(*c0), unit(c));
                let (e1, e2) = tangent_basis(a0);
                let half = |p: [f64; 3]| (self.radius / norm(p)).clamp(-1.0, 1.0).asin();
                out.extend([dot(a, e1) * w, dot(a, e2) * w, (half(c) - half(*c0)) * w]);
            } else {
                out.extend([(c[0] - c0[0]) * w, (c[1] - c0[1]) * w]);
            }
        }
    }

    /// Prior residuals, then highlight residuals (3 per observation, weighted).
    fn residuals(&self, theta: &[f64], offsets: &[usize], out: &mut Vec<f64>) {
        out.clear();
        self.prior_residuals(theta, out);
        for &(l, s, view) in &self.obs {
            let ray = self.ray(&view, self.center(theta, s));
            let target = match self.light(theta, offsets, l) {
                Ok(p) => unit(sub(p, ray.origin)),
                Err(d) => d,
            };
            let e = sub(target, scale(ray.direction, dot(target, ray.direction)));
            let w = self.ray_scale[s] / self.sigma_h;
            out.extend([e[0] * w, e[1] * w, e[2] * w]);
        }
    }

    /// Levenberg–Marquardt from `theta`; returns the iterations run.
    fn solve(&self, theta: &mut [f64], max_iterations: usize) -> usize {
        let (offsets, n) = self.offsets();
        let mut r = Vec::new();
        self.residuals(theta, &offsets, &mut r);
        let mut cost: f64 = r.iter().map(|v| v * v).sum();
        let mut lambda = 1e-4;
        let mut rp = Vec::new();
        let mut done = 0;
        for it in 0..max_iterations {
            done = it + 1;
            // Forward-difference Jacobian, column by column.
            let mut jac = vec![0.0; n * r.len()];
            for j in 0..n {
                let h = 1e-7 * theta[j].abs().max(1.0);
                let keep = theta[j];
                theta[j] = keep + h;
                self.residuals(theta, &offsets, &mut rp);
                theta[j] = keep;
                for (q, (a, b)) in rp.iter().zip(&r).enumerate() {
                    jac[j * r.len() + q] = (a - b) / h;
                }
            }
            let mut jtj = nalgebra::DMatrix::<f64>::zeros(n, n);
            let mut jtr = nalgebra::DVector::<f64>::zeros(n);
            for a in 0..n {
                let ca = &jac[a * r.len()..(a + 1) * r.len()];
                jtr[a] = ca.iter().zip(&r).map(|(x, y)| x * y).sum();
                for b in a..n {
                    let cb = &jac[b * r.len()..(b + 1) * r.len()];
                    let v: f64 = ca.iter().zip(cb).map(|(x, y)| x * y).sum();
                    jtj[(a, b)] = v;
                    jtj[(b, a)] = v;
                }
            }
            let mut improved = false;
            for _ in 0..10 {
                let mut m = jtj.clone();
                for d in 0..n {
                    m[(d, d)] += lambda * jtj[(d, d)].max(1e-12);
                }
                let Some(step) = m.cholesky().map(|c| c.solve(&(-&jtr))) else {
                    lambda *= 10.0;
                    continue;
                };
                let trial: Vec<f64> = theta.iter().zip(step.iter()).map(|(t, d)| t + d).collect();
                self.residuals(&trial, &offsets, &mut rp);
                let c: f64 = rp.iter().map(|v| v * v).sum();
                if c.is_finite() && c < cost {
                    let rel = (cost - c) / cost.max(1e-300);
                    theta.copy_from_slice(&trial);
                    std::mem::swap(&mut r, &mut rp);
                    cost = c;
                    lambda = (lambda * 0.2).max(1e-12);
                    improved = true;
                    if rel < 1e-10 {
                        return done;
                    }
                    break;
                }
                lambda *= 10.0;
            }
            if !improved {
                break;
            }
        }
        done
    }

    /// RMS outline move (pixels) and per-observation highlight residual norms (pixels).
    fn report(&self, theta: &[f64]) -> (f64, Vec<f64>) {
        let (offsets, _) = self.offsets();
        let mut r = Vec::new();
        self.residuals(theta, &offsets, &mut r);
        let per_sphere = if self.perspective { 3 } else { 2 };
        let n_prior = per_sphere * self.prior.len();
        let shift = r[..n_prior]
            .iter()
            .enumerate()
            .map(|(q, v)| {
                (v / self.prior_weight[q / per_sphere] * self.px_scale(q / per_sphere)).powi(2)
            })
            .sum::<f64>()
            / self.prior.len().max(1) as f64;
        let per_obs: Vec<f64> = r[n_prior..]
            .chunks_exact(3)
            .map(|e| (e[0] * e[0] + e[1] * e[1] + e[2] * e[2]).sqrt() * self.sigma_h)
            .collect();
        (shift.sqrt(), per_obs)
    }

    /// Pixels per prior unit of sphere `s` (the prior weight times the outline sigma).
    fn px_scale(&self, s: usize) -> f64 {
        self.prior_weight[s] * self.sigma_o[s]
    }
}

/// A located highlight: (light index, sphere index, its (u, v) pixel position).
pub(crate) type HighlightPixel = (usize, usize, [f64; 2]);

/// Refines the sphere centres and the lights jointly (a small bundle adjustment): minimises
/// the highlight residuals of every light seen on at least two spheres — the angle between the
/// mirror ray through the observed highlight and the direction to the light, expressed in
/// pixels (times half the sphere's image radius: the image shift of a highlight that turns the
/// ray by that angle) and weighted by the highlight noise level — plus, per sphere, the move of
/// its centre from the outline's estimate (orthographic: x and y in pixels; pinhole: the
/// direction of the centre and the half-angle of its tangent cone, in pixels), weighted by the
/// outline's precision ([`Sphere::outline_sigma`]). The highlights pin the sphere centres in
/// most directions better than a binary mask; the outline keeps the modes the highlights cannot
/// see (a common shift of all spheres and lights, and a stretch of the spheres' separation,
/// which turns every ray within its own plane through the baseline). The highlight noise is
/// estimated from the residuals (two rounds), and highlights more than 5 robust standard
/// deviations off are dropped. Orthographic cameras keep the given centre depths. Returns the
/// report and the dropped observations (indices into `obs`).
pub(crate) fn refine_spheres(
    camera: &Camera,
    spheres: &mut [Sphere],
    obs: &[HighlightPixel],
    lights: &[LightEstimate],
) -> Result<(Refinement, Vec<usize>)> {
    let perspective = camera.is_perspective();
    let radius = spheres.first().map_or(1.0, |s| s.radius);
    // Light slots: the lights seen on at least two spheres.
    let mut seen = vec![0usize; lights.len()];
    for &(l, _, _) in obs {
        seen[l] += 1;
    }
    let mut slot = vec![usize::MAX; lights.len()];
    let mut params = Vec::new();
    let mut init_lights = Vec::new();
    for (l, est) in lights.iter().enumerate() {
        if seen[l] < 2 {
            continue;
        }
        match *est {
            LightEstimate::Point(p) => {
                slot[l] = params.len();
                params.push(LightParam::Point);
                init_lights.extend(p);
            }
            LightEstimate::Directional(d) => {
                slot[l] = params.len();
                let (e1, e2) = tangent_basis(d);
                params.push(LightParam::Directional { d0: d, e1, e2 });
                init_lights.extend([0.0, 0.0]);
            }
            LightEstimate::Missing => {}
        }
    }
    let used: Vec<usize> = (0..obs.len())
        .filter(|&j| slot[obs[j].0] != usize::MAX)
        .collect();
    let px_per = match *camera {
        Camera::Orthographic { pixel_size, .. } => 1.0 / (pixel_size[0] * pixel_size[1]).sqrt(),
        Camera::Pinhole { k, .. } => (k[0][0] * k[1][1]).sqrt(),
    };
    let sigma_o: Vec<f64> = spheres.iter().map(|s| s.outline_sigma.max(1e-4)).collect();
    let mut bundle = Bundle {
        radius,
        perspective,
        depths: spheres.iter().map(|s| s.center[2]).collect(),
        prior: spheres.iter().map(|s| s.center).collect(),
        prior_weight: sigma_o.iter().map(|s| px_per / s).collect(),
        sigma_o,
        ray_scale: spheres.iter().map(|s| 0.5 * s.image_radius).collect(),
        obs: used
            .iter()
            .map(|&j| (slot[obs[j].0], obs[j].1, camera.ray(obs[j].2)))
            .collect(),
        lights: params,
        sigma_h: 0.05,
    };
    let mut theta: Vec<f64> = Vec::new();
    for s in spheres.iter() {
        if perspective {
            theta.extend(s.center);
        } else {
            theta.extend([s.center[0], s.center[1]]);
        }
    }
    theta.extend(init_lights);
    let (_, h_before) = bundle.report(&theta);
    let rms = |v: &[f64]| (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt();
    let highlight_before = rms(&h_before);
    let mut iterations = 0;
    let mut dropped = Vec::new();
    for round in 0..3 {
        iterations += bundle.solve(&mut theta, 50);
        let (_, per_obs) = bundle.report(&theta);
        // Noise level of the highlights, with the light parameters' share removed.
        let n_obs = per_obs.len() as f64;
        let n_light: f64 = bundle
            .lights
            .iter()
            .map(|l| match l {
                LightParam::Point => 3.0,
                LightParam::Directional { .. } => 2.0,
            })
            .sum();
        let dof = (2.0 * n_obs - n_light).max(1.0);
        let sigma = (per_obs.iter().map(|e| e * e).sum::<f64>() / dof)
            .sqrt()
            .max(0.005);
        if round == 2 {
            break;
        }
        // Drop gross outliers once (highlights far off their light's other rays).
        if round == 0 {
            let mut abs = per_obs.clone();
            let robust = (1.4826 * median(&mut abs) * std::f64::consts::SQRT_2).max(0.005);
            let limit = 5.0 * robust;
            let bad: Vec<usize> = (0..per_obs.len()).filter(|&q| per_obs[q] > limit).collect();
            if !bad.is_empty() {
                let mut keep = Vec::new();
                for (q, o) in bundle.obs.iter().enumerate() {
                    if bad.contains(&q) {
                        dropped.push(used[q]);
                    } else {
                        keep.push(*o);
                    }
                }
                bundle.obs = keep;
            }
        }
        bundle.sigma_h = sigma;
    }
    let (outline_shift, h_after) = bundle.report(&theta);
    if !theta.iter().all(|v| v.is_finite()) {
        return Err(Error::Unusable(
            "the joint refinement of spheres and lights diverged".into(),
        ));
    }
    for (s, sphere) in spheres.iter_mut().enumerate() {
        let c = bundle.center(&theta, s);
        sphere.shift = norm(sub(c, sphere.center));
        sphere.center = c;
        sphere.image_center = camera.project(c);
    }
    Ok((
        Refinement {
            iterations,
            highlights: bundle.obs.len(),
            dropped: dropped.len(),
            highlight_rms: [highlight_before, rms(&h_after)],
            outline_shift,
            highlight_sigma: bundle.sigma_h,
        },
        dropped,
    ))
}
