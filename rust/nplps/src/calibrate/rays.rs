//! Mirror rays (step 4 of the [module documentation](super)): the viewing ray `v` through a
//! highlight meets the sphere at `X` (nearest intersection, [`ray_sphere`]) with outward normal
//! `n = (X - C) / R`; the light lies on the mirror ray from `X` along `r = v - 2 (v . n) n`
//! ([`reflect`], [`reflected_ray`]). The viewing rays themselves are [`Camera::ray`].

use super::sphere::Sphere;
use crate::rig::{Camera, Ray};
use crate::vec3::{dot, scale, sub, unit};

/// Nearest intersection (t > 0) of a ray with the sphere of centre `c` and radius `r`.
pub(crate) fn ray_sphere(ray: &Ray, c: [f64; 3], r: f64) -> Option<[f64; 3]> {
    let oc = sub(ray.origin, c);
    let b = dot(oc, ray.direction);
    let disc = b * b - (dot(oc, oc) - r * r);
    if disc < 0.0 {
        return None;
    }
    let s = disc.sqrt();
    let t = if -b - s > 0.0 { -b - s } else { -b + s };
    (t > 0.0).then(|| ray.at(t))
}

/// Mirror reflection of the direction `v` (towards the surface) about the unit normal `n`:
/// `v - 2 (v . n) n`.
#[inline]
pub(crate) fn reflect(v: [f64; 3], n: [f64; 3]) -> [f64; 3] {
    sub(v, scale(n, 2.0 * dot(v, n)))
}

/// The mirror ray of a highlight at image point `uv` on `sphere`: the surface point, its outward
/// normal, and the ray from the surface point towards the light. None when the viewing ray
/// misses the sphere.
pub(crate) fn reflected_ray(
    camera: &Camera,
    sphere: &Sphere,
    uv: [f64; 2],
) -> Option<([f64; 3], [f64; 3], Ray)> {
    let view = camera.ray(uv);
    let x = ray_sphere(&view, sphere.center, sphere.radius)?;
    let n = scale(sub(x, sphere.center), 1.0 / sphere.radius);
    let r = unit(reflect(view.direction, n));
    Some((
        x,
        n,
        Ray {
            origin: x,
            direction: r,
        },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calibrate::sphere::OUTLINE_FIT_SIGMA;
    use crate::vec3::{add, norm};

    #[test]
    fn reflection_and_ray_sphere() {
        let n = unit([0.0, -1.0, -1.0]);
        let r = reflect([0.0, 0.0, 1.0], n);
        assert!(norm(sub(r, [0.0, -1.0, 0.0])) < 1e-15);
        let ray = Ray {
            origin: [0.0; 3],
            direction: [0.0, 0.0, 1.0],
        };
        let x = ray_sphere(&ray, [0.0, 0.0, 10.0], 2.0).unwrap();
        assert!((x[2] - 8.0).abs() < 1e-12);
        assert!(ray_sphere(&ray, [5.0, 0.0, 10.0], 2.0).is_none());
        // The mirror ray from a sphere point towards a light comes back to it.
        let cam = Camera::Orthographic {
            pixel_size: [0.5, 0.5],
            origin: [-20.0, -20.0],
        };
        let sphere = Sphere {
            placement: 0,
            center: [1.0, 2.0, 100.0],
            radius: 10.0,
            image_center: cam.project([1.0, 2.0, 100.0]),
            image_radius: 20.0,
            fit_rms: 0.0,
            outline_points: [0, 0],
            scale_check: 1.0,
            shift: 0.0,
            outline_sigma: OUTLINE_FIT_SIGMA,
        };
        let light = [30.0, -40.0, 20.0];
        // The surface point whose normal bisects the view (-z) and the light direction.
        let mut n = [0.0, 0.0, -1.0];
        for _ in 0..50 {
            let x = add(sphere.center, scale(n, sphere.radius));
            n = unit(add([0.0, 0.0, -1.0], unit(sub(light, x))));
        }
        let x = add(sphere.center, scale(n, sphere.radius));
        let (_, _, ray) = reflected_ray(&cam, &sphere, cam.project(x)).unwrap();
        assert!(ray.distance_to(light) < 1e-9);
    }
}
