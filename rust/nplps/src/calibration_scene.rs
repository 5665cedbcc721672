//! Synthetic calibration scenes: shiny spheres on a dark board (for [`crate::calibrate`]'s
//! sphere calibration) and a flat diffuse board (for its intensity calibration).
//!
//! The spheres are rendered by ray tracing: every pixel averages `supersample^2` viewing rays
//! (anti-aliased outlines); a ray that meets a sphere at `X` with outward normal `n` and viewing
//! direction `v` gets, per light with `beta(X)` ([`Light::beta`]) of magnitude `b` and direction
//! `l = beta / b`,
//!
//! `Phi (kd b max(0, n . l) + ks b max(0, r . l)^e)`, `r = v - 2 (v . n) n`
//!
//! (Lambertian plus a Phong lobe about the mirror direction, with the lights' inverse-square
//! falloff and LED anisotropy; `Phi` is the mean of the light's channels). The lobe peaks exactly
//! at the mirror point, so the highlight's centre is where a mirror sphere would show the light;
//! its width in pixels is about `r_px / (2 sqrt(e))` for a sphere of `r_px` pixels. A ray that
//! misses the spheres meets the board (albedo `kb`, Lambertian) or stays black. Points in the
//! shadow of a sphere get no light from it. Labels mark the pixels whose centre ray meets a sphere
//! (1 + the sphere's index), the ideal mask. Exposure, noise and quantisation are left to the
//! caller.

use rayon::prelude::*;

use crate::calibrate::{ray_sphere, reflect, Plane, Ray};
use crate::error::{Error, Result};
use crate::light::Light;
use crate::rig::{Camera, Rig};
use crate::vec3::{dot, norm, not_above, sub};

/// Reflectance of the spheres and of the board behind them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SphereMaterial {
    /// Lambertian albedo of the spheres, kd.
    pub diffuse: f64,
    /// Strength of the Phong lobe, ks.
    pub specular: f64,
    /// Phong exponent e (larger: smaller highlights).
    pub exponent: f64,
    /// Lambertian albedo of the board, kb.
    pub background: f64,
}

impl Default for SphereMaterial {
    fn default() -> Self {
        SphereMaterial {
            diffuse: 1.0,
            specular: 20.0,
            exponent: 200.0,
            background: 0.05,
        }
    }
}

/// Rendered sphere images.
#[derive(Debug, Clone, PartialEq)]
pub struct SphereImages {
    /// Radiance, k x H x W (linear, not clipped).
    pub images: Vec<f64>,
    /// H x W: 0 where the pixel centre's ray misses the spheres, 1 + the sphere index otherwise.
    pub labels: Vec<u32>,
}

/// Nearest sphere hit along a ray: (sphere index, point).
fn hit(ray: &Ray, centers: &[[f64; 3]], radius: f64) -> Option<(usize, [f64; 3])> {
    centers
        .iter()
        .enumerate()
        .filter_map(|(s, &c)| ray_sphere(ray, c, radius).map(|x| (s, x)))
        .min_by(|a, b| {
            let da = dot(sub(a.1, ray.origin), ray.direction);
            let db = dot(sub(b.1, ray.origin), ray.direction);
            da.total_cmp(&db)
        })
}

/// Whether the segment from `x` towards the light (`l` unit, `reach` its length; infinite for a
/// distant light) meets a sphere other than `skip`.
fn shadowed(
    x: [f64; 3],
    l: [f64; 3],
    reach: f64,
    centers: &[[f64; 3]],
    radius: f64,
    skip: Option<usize>,
) -> bool {
    let ray = Ray {
        origin: x,
        direction: l,
    };
    centers.iter().enumerate().any(|(s, &c)| {
        if Some(s) == skip {
            return false;
        }
        ray_sphere(&ray, c, radius).is_some_and(|p| dot(sub(p, x), l) < reach)
    })
}

/// Direction, magnitude and distance of a light's `beta` at `x` (None when it does not light x).
fn incident(light: &Light, x: [f64; 3]) -> Option<([f64; 3], f64, f64)> {
    let (beta, _) = light.beta(x);
    let b = norm(beta);
    if !(b > 0.0 && b.is_finite()) {
        return None;
    }
    let l = [beta[0] / b, beta[1] / b, beta[2] / b];
    let reach = match *light {
        Light::Point { position, .. } => {
            let d = sub(position, x);
            norm(d)
        }
        Light::Directional { .. } => f64::INFINITY,
    };
    Some((l, b, reach))
}

/// What a sphere scene shows: an H x W image of spheres of one `radius` at `centers` (camera
/// frame), in front of an optional board plane.
#[derive(Debug, Clone, Copy)]
pub struct SphereLayout<'a> {
    /// Image height H (pixels).
    pub height: usize,
    /// Image width W (pixels).
    pub width: usize,
    /// The sphere centres.
    pub centers: &'a [[f64; 3]],
    /// The spheres' radius (scene units).
    pub radius: f64,
    /// The board behind the spheres, if any.
    pub board: Option<Plane>,
}

/// Renders k images (one per light of `rig`) of spheres of radius `radius` at `centers` in
/// front of an optional board plane; see the [module documentation](self).
pub fn render_spheres(
    rig: &Rig,
    layout: &SphereLayout<'_>,
    material: &SphereMaterial,
    supersample: usize,
) -> Result<SphereImages> {
    let SphereLayout {
        height,
        width,
        centers,
        radius,
        board,
    } = *layout;
    rig.validate_parameters()?;
    if height == 0 || width == 0 || supersample == 0 || supersample > 16 {
        return Err(Error::Unusable(format!(
            "a sphere scene needs a non-empty image and 1..=16 subsamples, got {width} x {height} pixels, {supersample}"
        )));
    }
    if !(radius > 0.0 && radius.is_finite()) || centers.iter().flatten().any(|v| !v.is_finite()) {
        return Err(Error::Unusable(format!(
            "sphere radius must be positive and centres finite, got radius {radius}"
        )));
    }
    let m = *material;
    if ![m.diffuse, m.specular, m.exponent, m.background]
        .iter()
        .all(|v| v.is_finite() && *v >= 0.0)
    {
        return Err(Error::Unusable(format!(
            "sphere material parameters must be finite and non-negative, got {m:?}"
        )));
    }
    let board = board
        .map(|p| {
            let n = p.normal;
            let len = norm(n);
            if not_above(len, 0.0) {
                return Err(Error::Unusable(
                    "the board plane needs a non-zero normal".into(),
                ));
            }
            let (mut u, mut d) = ([n[0] / len, n[1] / len, n[2] / len], p.offset / len);
            if u[2] > 0.0 {
                u = [-u[0], -u[1], -u[2]];
                d = -d;
            }
            Ok((u, d))
        })
        .transpose()?;
    let camera: Camera = rig.camera;
    let lights = &rig.lights;
    let k = lights.len();
    let phi: Vec<f64> = lights
        .iter()
        .map(|l| l.intensity().iter().sum::<f64>() / 3.0)
        .collect();
    let s = supersample;
    let weight = 1.0 / (s * s) as f64;
    let shade_ray = |ray: &Ray, out: &mut [f64]| {
        if let Some((index, x)) = hit(ray, centers, radius) {
            let c = centers[index];
            let n = [
                (x[0] - c[0]) / radius,
                (x[1] - c[1]) / radius,
                (x[2] - c[2]) / radius,
            ];
            let r = reflect(ray.direction, n);
            for (i, light) in lights.iter().enumerate() {
                let Some((l, b, reach)) = incident(light, x) else {
                    continue;
                };
                let nl = dot(n, l);
                if nl <= 0.0 || shadowed(x, l, reach, centers, radius, Some(index)) {
                    continue;
                }
                let spec = dot(r, l).max(0.0).powf(m.exponent);
                out[i] += weight * phi[i] * b * (m.diffuse * nl + m.specular * spec);
            }
        } else if let Some((nb, d)) = board {
            let denom = dot(nb, ray.direction);
            if denom == 0.0 {
                return;
            }
            let t = (d - dot(nb, ray.origin)) / denom;
            if t <= 0.0 && camera.is_perspective() {
                return;
            }
            let x = ray.at(t);
            for (i, light) in lights.iter().enumerate() {
                let Some((l, b, reach)) = incident(light, x) else {
                    continue;
                };
                let nl = dot(nb, l);
                if nl <= 0.0 || shadowed(x, l, reach, centers, radius, None) {
                    continue;
                }
                out[i] += weight * phi[i] * b * m.background * nl;
            }
        }
    };
    let plane = height * width;
    let per_pixel: Vec<(Vec<f64>, u32)> = (0..plane)
        .into_par_iter()
        .map(|p| {
            let (u, v) = ((p % width) as f64, (p / width) as f64);
            let mut values = vec![0.0; k];
            for a in 0..s {
                for b in 0..s {
                    let du = (a as f64 + 0.5) / s as f64 - 0.5;
                    let dv = (b as f64 + 0.5) / s as f64 - 0.5;
                    shade_ray(&camera.ray([u + du, v + dv]), &mut values);
                }
            }
            let label = hit(&camera.ray([u, v]), centers, radius).map_or(0, |(i, _)| i as u32 + 1);
            (values, label)
        })
        .collect();
    let mut images = vec![0.0; k * plane];
    let mut labels = vec![0u32; plane];
    for (p, (values, label)) in per_pixel.into_iter().enumerate() {
        for (i, v) in values.into_iter().enumerate() {
            images[i * plane + p] = v;
        }
        labels[p] = label;
    }
    Ok(SphereImages { images, labels })
}

/// Vertex depths ((H+1) x (W+1)) of the plane `plane` seen by `camera`.
pub(crate) fn plane_depth(
    camera: &Camera,
    height: usize,
    width: usize,
    plane: &Plane,
) -> Result<Vec<f64>> {
    let n = plane.normal;
    let len = norm(n);
    if !(len > 0.0 && len.is_finite() && plane.offset.is_finite()) {
        return Err(Error::Unusable(format!(
            "the board plane needs a finite non-zero normal and offset, got {plane:?}"
        )));
    }
    let (u, d) = ([n[0] / len, n[1] / len, n[2] / len], plane.offset / len);
    let vw = width + 1;
    let depth: Vec<f64> = (0..(height + 1) * vw)
        .map(|v| {
            let [x, y] = camera.vertex_xy(v / vw, v % vw);
            if camera.is_perspective() {
                d / (u[0] * x + u[1] * y + u[2])
            } else {
                (d - u[0] * x - u[1] * y) / u[2]
            }
        })
        .collect();
    if depth.iter().any(|z| !(z.is_finite() && *z > 0.0)) {
        return Err(Error::Unusable(
            "the board plane is not in front of the camera over the whole image".into(),
        ));
    }
    Ok(depth)
}

/// Renders k images (k x H x W x C) of a flat Lambertian board on `plane` with per-pixel
/// `albedo` (H x W x C) by the image model ([`crate::render()`]).
pub fn render_board(
    rig: &Rig,
    height: usize,
    width: usize,
    plane: &Plane,
    albedo: &[f64],
    channels: usize,
) -> Result<Vec<f64>> {
    rig.validate_parameters()?;
    let depth = plane_depth(&rig.camera, height, width, plane)?;
    let surface = crate::render::Surface {
        height,
        width,
        depth: &depth,
        albedo,
        channels,
        mask: None,
    };
    crate::render::render(rig, &surface)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calibrate::{
        calibrate_spheres, LightEstimate, Placement, SphereOptions, SphereSource,
    };

    #[test]
    fn rendered_spheres_calibrate_back_to_their_lights() {
        let cam = Camera::Orthographic {
            pixel_size: [0.5, 0.5],
            origin: [-40.0, -40.0],
        };
        let positions = vec![
            [40.0, 10.0, 20.0],
            [-30.0, 35.0, -10.0],
            [5.0, -45.0, 40.0],
            [-20.0, -20.0, 0.0],
        ];
        let rig = Rig::orthographic([0.5, 0.5], [-40.0, -40.0], positions.clone()).unwrap();
        let radius = 20.0;
        let centers = [[-18.0, -12.0, 150.0], [18.0, 14.0, 150.0]];
        let material = SphereMaterial {
            exponent: (40.0f64 / 3.0).powi(2),
            ..SphereMaterial::default()
        };
        let layout = SphereLayout {
            height: 160,
            width: 160,
            centers: &centers,
            radius,
            board: Some(Plane::at_depth(170.0)),
        };
        let scene = render_spheres(&rig, &layout, &material, 4).unwrap();
        let peak = scene.images.iter().copied().fold(0.0, f64::max);
        // Exposure: the diffuse maximum near 0.5, highlights clipped at 1 (8-bit).
        let diffuse_max = {
            let mut v: Vec<f64> = scene.images.clone();
            v.sort_by(f64::total_cmp);
            v[(0.995 * v.len() as f64) as usize]
        };
        assert!(peak > 4.0 * diffuse_max);
        let images: Vec<f32> = scene
            .images
            .iter()
            .map(|v| ((v * 0.5 / diffuse_max).min(1.0) * 255.0).round() as f32 / 255.0)
            .collect();
        let placement = Placement {
            images: &images,
            spheres: SphereSource::Labels(&scene.labels),
            center_depth: vec![150.0],
        };
        let options = SphereOptions {
            radius,
            ..SphereOptions::default()
        };
        let cal = calibrate_spheres(&cam, &[placement], 160, 160, 4, &options).unwrap();
        assert_eq!(cal.spheres.len(), 2);
        for (report, truth) in cal.lights.iter().zip(&positions) {
            let LightEstimate::Point(p) = report.estimate else {
                panic!("{report:?}");
            };
            let err =
                ((p[0] - truth[0]).powi(2) + (p[1] - truth[1]).powi(2) + (p[2] - truth[2]).powi(2))
                    .sqrt();
            assert!(err < 1.5, "light at {truth:?} found at {p:?} ({err} off)");
        }
    }

    #[test]
    fn board_depth_follows_a_tilted_plane() {
        let cam = Camera::Pinhole {
            k: [[100.0, 0.0, 15.5], [0.0, 100.0, 15.5], [0.0, 0.0, 1.0]],
            distortion: [0.0; 5],
        };
        let plane = Plane {
            normal: [0.1, -0.2, -1.0],
            offset: -200.0,
        };
        let z = plane_depth(&cam, 32, 32, &plane).unwrap();
        for (v, &depth) in z.iter().enumerate() {
            let [x, y] = cam.vertex_xy(v / 33, v % 33);
            let p = [x * depth, y * depth, depth];
            assert!((dot(plane.normal, p) - plane.offset).abs() < 1e-9);
        }
        let behind = Plane {
            normal: [0.0, 0.0, 1.0],
            offset: -5.0,
        };
        assert!(plane_depth(&cam, 32, 32, &behind).is_err());
    }
}
