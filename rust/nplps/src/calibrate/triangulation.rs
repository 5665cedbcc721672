//! A light from its mirror rays (step 5 of the [module documentation](super)): the
//! least-squares point closest to all its rays, `p = argmin sum_i |(I - r_i r_i^T)(p - X_i)|^2`
//! (for two rays, the midpoint of their shortest connecting segment, as in the paper). When the
//! rays agree within `parallel_tol` (RMS angle about their mean direction) the light is too far
//! to be located and is reported as a directional light along the mean direction; likewise with
//! a single ray (with a warning), or when the least-squares point lies behind a sphere
//! (diverging rays).

use nalgebra::{Matrix3, SymmetricEigen, Vector3};

use crate::rig::Ray;
use crate::vec3::{add, angle, dot, norm, not_above, scale, sub};

/// The point closest to a set of lines in the least-squares sense,
/// `argmin_p sum_i |(I - d_i d_i^T)(p - o_i)|^2`, and the RMS distance of the lines from it.
/// None when fewer than two rays are given or the rays are parallel (the normal matrix is
/// singular to working precision).
pub(crate) fn nearest_point(rays: &[Ray]) -> Option<([f64; 3], f64)> {
    if rays.len() < 2 {
        return None;
    }
    let mut a = Matrix3::<f64>::zeros();
    let mut b = Vector3::<f64>::zeros();
    for ray in rays {
        let d = Vector3::new(ray.direction[0], ray.direction[1], ray.direction[2]);
        let o = Vector3::new(ray.origin[0], ray.origin[1], ray.origin[2]);
        let proj = Matrix3::identity() - d * d.transpose();
        a += proj;
        b += proj * o;
    }
    let eig = SymmetricEigen::new(a);
    let min = eig.eigenvalues.min();
    if not_above(min, 1e-10 * rays.len() as f64) {
        return None;
    }
    let p = a.cholesky()?.solve(&b);
    let p = [p[0], p[1], p[2]];
    if !p.iter().all(|v| v.is_finite()) {
        return None;
    }
    let ms = rays.iter().map(|r| r.distance_to(p).powi(2)).sum::<f64>() / rays.len() as f64;
    Some((p, ms.sqrt()))
}

/// The normalised mean direction of the rays and the RMS angle (radians) of the rays about it.
pub(crate) fn mean_direction(rays: &[Ray]) -> Option<([f64; 3], f64)> {
    let sum = rays.iter().fold([0.0; 3], |acc, r| add(acc, r.direction));
    let n = norm(sum);
    if rays.is_empty() || not_above(n, 0.0) {
        return None;
    }
    let d = scale(sum, 1.0 / n);
    let ms = rays
        .iter()
        .map(|r| angle(r.direction, d).powi(2))
        .sum::<f64>()
        / rays.len() as f64;
    Some((d, ms.sqrt()))
}

/// A light estimated from its rays.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LightEstimate {
    /// A near light at this position.
    Point([f64; 3]),
    /// A distant light in this direction (unit, from the scene towards the light).
    Directional([f64; 3]),
    /// Not seen on any sphere.
    Missing,
}

/// The calibration of one light.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct LightReport {
    /// Position or direction.
    pub estimate: LightEstimate,
    /// RMS distance of the rays from the position (NaN for directional or missing lights).
    pub rms_miss: f64,
    /// RMS angle (degrees) between each ray and the direction from its origin to the position
    /// (point lights) or the mean direction (directional lights).
    pub rms_angle: f64,
    /// Largest angle (degrees) between two of the rays (their spread; 0 for one ray).
    pub spread: f64,
    /// Number of spheres (rays) the light was seen on.
    pub spheres: usize,
    /// Why the light is not a located point light, if it is not.
    pub warning: Option<String>,
}

/// Locates one light from its rays (see the [module documentation](super)). `parallel_tol` is
/// the RMS angle in radians about the mean direction below which the rays are taken as
/// parallel (a distant light).
pub(crate) fn locate_light(rays: &[Ray], parallel_tol: f64) -> LightReport {
    let spread = rays
        .iter()
        .enumerate()
        .flat_map(|(i, a)| {
            rays[i + 1..]
                .iter()
                .map(move |b| angle(a.direction, b.direction))
        })
        .fold(0.0f64, f64::max)
        .to_degrees();
    let Some((mean, rms_dir)) = mean_direction(rays) else {
        return LightReport {
            estimate: LightEstimate::Missing,
            rms_miss: f64::NAN,
            rms_angle: f64::NAN,
            spread: 0.0,
            spheres: 0,
            warning: Some("not seen on any sphere: no position and no direction".into()),
        };
    };
    let directional = |warning: Option<String>| LightReport {
        estimate: LightEstimate::Directional(mean),
        rms_miss: f64::NAN,
        rms_angle: rms_dir.to_degrees(),
        spread,
        spheres: rays.len(),
        warning,
    };
    if rays.len() == 1 {
        return directional(Some(
            "seen on one sphere only: no position possible from one ray; written as a directional light along the reflected ray".into(),
        ));
    }
    if rms_dir <= parallel_tol {
        return directional(None);
    }
    let Some((p, rms_miss)) = nearest_point(rays) else {
        return directional(None);
    };
    if rays
        .iter()
        .any(|r| dot(sub(p, r.origin), r.direction) <= 0.0)
    {
        return directional(Some(format!(
            "the rays diverge (their nearest point lies behind a sphere; spread {spread:.2} deg): written as a directional light"
        )));
    }
    let ms_angle = rays
        .iter()
        .map(|r| angle(r.direction, sub(p, r.origin)).powi(2))
        .sum::<f64>()
        / rays.len() as f64;
    LightReport {
        estimate: LightEstimate::Point(p),
        rms_miss,
        rms_angle: ms_angle.sqrt().to_degrees(),
        spread,
        spheres: rays.len(),
        warning: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vec3::unit;

    #[test]
    fn nearest_point_of_rays_and_parallel_rays() {
        let p = [3.0, -4.0, 5.0];
        let origins = [[0.0, 0.0, 100.0], [50.0, 10.0, 90.0], [-30.0, 40.0, 110.0]];
        let rays: Vec<Ray> = origins
            .iter()
            .map(|&o| Ray {
                origin: o,
                direction: unit(sub(p, o)),
            })
            .collect();
        let (q, rms) = nearest_point(&rays).unwrap();
        assert!(norm(sub(p, q)) < 1e-9 && rms < 1e-9);
        let report = locate_light(&rays, 0.5f64.to_radians());
        assert!(matches!(report.estimate, LightEstimate::Point(_)) && report.warning.is_none());
        // Two skew lines: the midpoint of their shortest segment.
        let a = Ray {
            origin: [0.0, 0.0, 0.0],
            direction: [1.0, 0.0, 0.0],
        };
        let b = Ray {
            origin: [0.0, 0.0, 2.0],
            direction: [0.0, 1.0, 0.0],
        };
        let (q, rms) = nearest_point(&[a, b]).unwrap();
        assert!(norm(sub(q, [0.0, 0.0, 1.0])) < 1e-12 && (rms - 1.0).abs() < 1e-12);
        // Parallel rays: no point; locate_light returns the direction.
        let d = unit([0.2, -0.1, -1.0]);
        let par: Vec<Ray> = origins
            .iter()
            .map(|&o| Ray {
                origin: o,
                direction: d,
            })
            .collect();
        assert!(nearest_point(&par).is_none());
        let report = locate_light(&par, 0.5f64.to_radians());
        match report.estimate {
            LightEstimate::Directional(e) => assert!(angle(e, d) < 1e-12),
            other => panic!("{other:?}"),
        }
        // Nearly parallel (far light, 0.1 deg apart) is directional within the tolerance.
        let far = [1e5, -3e4, -1e6];
        let rays: Vec<Ray> = origins
            .iter()
            .map(|&o| Ray {
                origin: o,
                direction: unit(sub(far, o)),
            })
            .collect();
        assert!(matches!(
            locate_light(&rays, 0.5f64.to_radians()).estimate,
            LightEstimate::Directional(_)
        ));
        // One ray: a direction with a warning; none: missing.
        let one = locate_light(&rays[..1], 0.01);
        assert!(matches!(one.estimate, LightEstimate::Directional(_)) && one.warning.is_some());
        assert!(matches!(
            locate_light(&[], 0.01).estimate,
            LightEstimate::Missing
        ));
        // Diverging rays (nearest point behind the spheres) are not a point light.
        let div = [
            Ray {
                origin: [0.0, 0.0, 0.0],
                direction: unit([0.1, 0.0, -1.0]),
            },
            Ray {
                origin: [10.0, 0.0, 0.0],
                direction: unit([0.3, 0.0, -1.0]),
            },
        ];
        let rep = locate_light(&div, 0.001);
        assert!(matches!(rep.estimate, LightEstimate::Directional(_)) && rep.warning.is_some());
    }
}
