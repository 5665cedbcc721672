//! A sphere in 3-D from its outline (step 2 of the [module documentation](super)).
//!
//! - *Orthographic camera*: the outline points in scene units (the origins of their viewing
//!   rays, `x = ox + (u + 1/2) w`, `y = oy + (v + 1/2) h`) are fitted with a circle whose centre
//!   is the sphere centre's (x, y); z is given (for a ball lying on a board at depth `z_b`,
//!   `z_b - R`; for a hemisphere lying flat on it, `z_b`). When the free fit's radius agrees with
//!   `R` within 3 % the centre is refitted with the radius fixed; the ratio checks the pixel size.
//! - *Pinhole camera*: the image of a sphere is an ellipse, the section of the tangent cone from
//!   the camera centre; the cone fitted to the outline rays gives the centre
//!   `C = a R / sin(theta)`, exact at any position in the image. A given centre depth `z`, if
//!   any, replaces the distance: `C = a z / a_z`.
//!
//! From a mask, the widest-margin separating circle or cone of the mask's edge pixels improves
//! on the least-squares fit when the mask is the pixel sampling of a disc (about 0.01 against
//! 0.03 pixel for a 40-pixel disc); the precision assumed by the joint refinement
//! ([`Sphere::outline_sigma`]) says which fit was used.

use super::fits::{fit_circle, fit_circle_radius, fit_cone, separating_circle, separating_cone};
use super::outline::{mask_boundary, mask_edge_pixels};
use crate::error::{Error, Result};
use crate::rig::Camera;
use crate::vec3::{norm, scale};

/// A sphere located in the camera frame.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct Sphere {
    /// Index of the placement (image set) that shows it.
    pub placement: usize,
    /// Centre in the camera frame.
    pub center: [f64; 3],
    /// Radius (scene units, as given).
    pub radius: f64,
    /// Image of the centre (u, v).
    pub image_center: [f64; 2],
    /// Mean image radius, pixels.
    pub image_radius: f64,
    /// RMS distance of the outline points from the fitted outline, pixels.
    pub fit_rms: f64,
    /// Outline points used (inliers) and found.
    pub outline_points: [usize; 2],
    /// Orthographic: fitted radius / given radius (checks the pixel size). Pinhole with a given
    /// centre depth: distance from the outline / distance from the given depth. Otherwise 1.
    pub scale_check: f64,
    /// How far the joint refinement moved the centre from the outline's (scene units; 0 without
    /// refinement).
    pub shift: f64,
    /// Precision of the outline's centre (pixels per coordinate) that the joint refinement
    /// assumes: `MASK_DIGITAL_SIGMA` for a separating fit to a mask, `OUTLINE_FIT_SIGMA`
    /// otherwise.
    pub outline_sigma: f64,
}

/// The sphere of radius `radius` whose outline passes through the image points `outline`
/// (pixels). Orthographic cameras need the depth of the centre (`center_depth`); for pinhole
/// cameras it is optional and, when given, replaces the distance derived from the outline.
pub(crate) fn locate_sphere(
    camera: &Camera,
    outline: &[[f64; 2]],
    radius: f64,
    center_depth: Option<f64>,
) -> Result<Sphere> {
    if !(radius > 0.0 && radius.is_finite()) {
        return Err(Error::Unusable(format!(
            "the sphere radius must be positive and finite, got {radius}"
        )));
    }
    if let Some(z) = center_depth {
        if !(z.is_finite() && z > 0.0) {
            return Err(Error::Unusable(format!(
                "the depth of a sphere centre must be positive and finite, got {z}"
            )));
        }
    }
    match *camera {
        Camera::Orthographic { pixel_size, .. } => {
            let z = center_depth.ok_or_else(|| {
                Error::Unusable(
                    "an orthographic camera needs the depth of each sphere centre (center_depth)"
                        .into(),
                )
            })?;
            let scene: Vec<[f64; 2]> = outline
                .iter()
                .map(|&uv| {
                    let o = camera.ray(uv).origin;
                    [o[0], o[1]]
                })
                .collect();
            let free = fit_circle(&scene)?;
            // The radius is known: when the free fit agrees with it (the pixel size is right),
            // the centre is fitted with the radius fixed, which rejects a part of the outline
            // that is biased inwards (a limb in the dark, where the shading fades to nothing).
            let circle = if (free.radius / radius - 1.0).abs() <= 0.03 {
                fit_circle_radius(&scene, free.center, radius).unwrap_or(free)
            } else {
                free
            };
            let px = (pixel_size[0] * pixel_size[1]).sqrt();
            let c = [circle.center[0], circle.center[1], z];
            Ok(Sphere {
                placement: 0,
                center: c,
                radius,
                image_center: camera.project(c),
                image_radius: free.radius / px,
                fit_rms: circle.rms / px,
                outline_points: [circle.inliers, outline.len()],
                scale_check: free.radius / radius,
                shift: 0.0,
                outline_sigma: OUTLINE_FIT_SIGMA,
            })
        }
        Camera::Pinhole { k, .. } => {
            let rays: Vec<[f64; 3]> = outline.iter().map(|&uv| camera.ray(uv).direction).collect();
            let cone = fit_cone(&rays)?;
            let distance = radius / cone.half_angle.sin();
            let from_outline = scale(cone.axis, distance);
            let (center, check) = match center_depth {
                Some(z) => {
                    let c = scale(cone.axis, z / cone.axis[2]);
                    (c, distance / norm(c))
                }
                None => (from_outline, 1.0),
            };
            let f = (k[0][0] * k[1][1]).sqrt();
            Ok(Sphere {
                placement: 0,
                center,
                radius,
                image_center: camera.project(center),
                image_radius: f * cone.half_angle.tan(),
                fit_rms: f * cone.rms,
                outline_points: [cone.inliers, outline.len()],
                scale_check: check,
                shift: 0.0,
                outline_sigma: OUTLINE_FIT_SIGMA,
            })
        }
    }
}

/// Outline precision (pixels, per coordinate of the centre) assumed by the joint refinement
/// for a sphere located by [`separating_circle`] / [`separating_cone`] from its mask.
pub(crate) const MASK_DIGITAL_SIGMA: f64 = 0.01;

/// Outline precision (pixels) assumed for a least-squares outline fit (mask boundary or image
/// edges): the digitisation leaves ~0.03 pixel even for a 40-pixel disc.
pub(crate) const OUTLINE_FIT_SIGMA: f64 = 0.03;

/// Locates a sphere from its mask region: the least-squares fit of the crack midpoints
/// ([`locate_sphere`]), improved by the widest-margin separating circle or cone of the mask's
/// edge pixels when the mask is consistent with one. Returns the sphere and whether the
/// separating fit was used.
pub(crate) fn locate_sphere_in_mask(
    camera: &Camera,
    labels: &[u32],
    height: usize,
    width: usize,
    label: u32,
    radius: f64,
    center_depth: Option<f64>,
) -> Result<(Sphere, bool)> {
    let cracks = mask_boundary(labels, height, width, label);
    let mut sphere = locate_sphere(camera, &cracks, radius, center_depth)?;
    sphere.outline_sigma = OUTLINE_FIT_SIGMA;
    let (inside, outside) = mask_edge_pixels(labels, height, width, label);
    match *camera {
        Camera::Orthographic { pixel_size, .. } => {
            let to_scene = |uv: &[f64; 2]| {
                let o = camera.ray(*uv).origin;
                [o[0], o[1]]
            };
            let start = fit_circle(&cracks.iter().map(to_scene).collect::<Vec<_>>())?;
            let ins: Vec<[f64; 2]> = inside.iter().map(to_scene).collect();
            let outs: Vec<[f64; 2]> = outside.iter().map(to_scene).collect();
            if let Some(circle) = separating_circle(&ins, &outs, &start) {
                let px = (pixel_size[0] * pixel_size[1]).sqrt();
                sphere.center = [circle.center[0], circle.center[1], sphere.center[2]];
                sphere.image_center = camera.project(sphere.center);
                sphere.image_radius = circle.radius / px;
                sphere.scale_check = circle.radius / radius;
                sphere.outline_sigma = MASK_DIGITAL_SIGMA;
                return Ok((sphere, true));
            }
        }
        Camera::Pinhole { k, .. } => {
            let rays = |pts: &[[f64; 2]]| -> Vec<[f64; 3]> {
                pts.iter().map(|&uv| camera.ray(uv).direction).collect()
            };
            let start = fit_cone(&rays(&cracks))?;
            if let Some(cone) = separating_cone(&rays(&inside), &rays(&outside), &start) {
                let distance = radius / cone.half_angle.sin();
                let (center, check) = match center_depth {
                    Some(z) => {
                        let c = scale(cone.axis, z / cone.axis[2]);
                        (c, distance / norm(c))
                    }
                    None => (scale(cone.axis, distance), 1.0),
                };
                sphere.center = center;
                sphere.image_center = camera.project(center);
                sphere.image_radius = (k[0][0] * k[1][1]).sqrt() * cone.half_angle.tan();
                sphere.scale_check = check;
                sphere.outline_sigma = MASK_DIGITAL_SIGMA;
                return Ok((sphere, true));
            }
        }
    }
    Ok((sphere, false))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calibrate::fits::{fit_circle, separating_circle};
    use crate::calibrate::testing::{disc, pinhole};
    use crate::vec3::{add, cross, sub, unit};

    #[test]
    fn separating_fits_locate_pixel_sampled_discs_and_spheres() {
        // Orthographic: discs at random sub-pixel positions; the widest separating circle is
        // about three times more precise than the least-squares fit to the crack midpoints.
        let (h, w) = (110, 110);
        let mut state = 7u64;
        let mut uniform = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let (mut ls, mut lp) = (0.0, 0.0);
        let n = 40;
        for _ in 0..n {
            let c = [55.0 + 2.0 * uniform() - 1.0, 55.0 + 2.0 * uniform() - 1.0];
            let r = 40.0 + 2.0 * uniform() - 1.0;
            let labels = disc(h, w, c, r);
            let start = fit_circle(&mask_boundary(&labels, h, w, 1)).unwrap();
            let (ins, outs) = mask_edge_pixels(&labels, h, w, 1);
            let best = separating_circle(&ins, &outs, &start).unwrap();
            ls += (start.center[0] - c[0]).powi(2) + (start.center[1] - c[1]).powi(2);
            lp += (best.center[0] - c[0]).powi(2) + (best.center[1] - c[1]).powi(2);
            assert!((best.radius - r).abs() < 0.05);
        }
        let (ls, lp) = ((ls / n as f64).sqrt(), (lp / n as f64).sqrt());
        assert!(
            lp < 0.02 && lp < 0.5 * ls,
            "centre RMS: least squares {ls} px, separating {lp} px"
        );
        // A notched mask is no pixel sampling of a circle: no separating circle.
        let mut notched = disc(h, w, [55.3, 54.8], 40.0);
        notched[55 * w + 20] = 0;
        notched[55 * w + 21] = 0;
        notched[54 * w + 20] = 0;
        let start = fit_circle(&mask_boundary(&notched, h, w, 1)).unwrap();
        let (ins, outs) = mask_edge_pixels(&notched, h, w, 1);
        assert!(separating_circle(&ins, &outs, &start).is_none());
        // Pinhole (30-pixel images): the widest separating cone of the mask's edge pixels puts the
        // centre within 0.12 % of its distance, better than the least-squares cone on average.
        let cam = pinhole();
        let (mut worst, mut sum_lp, mut sum_ls) = (0.0f64, 0.0, 0.0);
        for i in 0..6 {
            let centre = [
                -30.0 + 12.0 * i as f64 + uniform(),
                20.0 * uniform() - 10.0,
                250.0 + 20.0 * uniform(),
            ];
            let mut labels = vec![0u32; 200 * 200];
            for (p, l) in labels.iter_mut().enumerate() {
                let ray = cam.ray([(p % 200) as f64, (p / 200) as f64]);
                *l = u32::from(ray.distance_to(centre) <= 20.0);
            }
            let (sphere, digital) =
                locate_sphere_in_mask(&cam, &labels, 200, 200, 1, 20.0, None).unwrap();
            let lsq =
                locate_sphere(&cam, &mask_boundary(&labels, 200, 200, 1), 20.0, None).unwrap();
            assert!(digital);
            let err = norm(sub(sphere.center, centre)) / norm(centre);
            worst = worst.max(err);
            sum_lp += err;
            sum_ls += norm(sub(lsq.center, centre)) / norm(centre);
        }
        assert!(worst < 1.2e-3 && sum_lp < 0.5 * sum_ls, "relative centre errors: worst {worst}, sums {sum_lp} (separating), {sum_ls} (least squares)");
    }

    #[test]
    fn cone_fit_locates_an_off_axis_sphere_exactly() {
        let cam = pinhole();
        let (centre, radius) = ([45.0, -30.0, 260.0], 20.0);
        // Exact outline: rays tangent to the sphere.
        let d = norm(centre);
        let a = unit(centre);
        let half = (radius / d).asin();
        let e1 = unit(cross(a, [0.0, 1.0, 0.0]));
        let e2 = cross(a, e1);
        let outline: Vec<[f64; 2]> = (0..100)
            .map(|i| {
                let phi = i as f64 * 0.0628;
                let dir = add(
                    scale(a, half.cos()),
                    scale(add(scale(e1, phi.cos()), scale(e2, phi.sin())), half.sin()),
                );
                cam.project(dir)
            })
            .collect();
        let s = locate_sphere(&cam, &outline, radius, None).unwrap();
        assert!(norm(sub(s.center, centre)) < 1e-8, "{:?}", s.center);
        assert!(s.fit_rms < 1e-6);
        // With a given depth the centre moves along the axis to it.
        let s = locate_sphere(&cam, &outline, radius, Some(300.0)).unwrap();
        assert!((s.center[2] - 300.0).abs() < 1e-9 && s.scale_check < 1.0);
        // A pixel-sampled mask of the exact image (an ellipse) gives the centre within 0.05 %.
        let (h, w) = (200, 200);
        let mut labels = vec![0u32; h * w];
        for (p, l) in labels.iter_mut().enumerate() {
            let ray = cam.ray([(p % w) as f64, (p / w) as f64]);
            *l = u32::from(ray.distance_to(centre) <= radius);
        }
        let s = locate_sphere(&cam, &mask_boundary(&labels, h, w, 1), radius, None).unwrap();
        let err = norm(sub(s.center, centre)) / d;
        assert!(err < 5e-4, "relative centre error {err}");
    }
}
