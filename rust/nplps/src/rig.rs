//! Rig: the camera model, and the rig (a camera and its lights; the light model is
//! [`crate::light`]).
//!
//! The camera frame is OpenCV's: x right (increasing column), y down (increasing row), z forward
//! into the scene; depth is z. Units are the user's (mm typical): pixel sizes and light positions
//! share them.

use crate::error::{g6, Error, Result};
use crate::light::{check_magnitude, g6_list};
pub(crate) use crate::light::{Light, MAX_MAGNITUDE, MIN_MAGNITUDE};
use crate::vec3::{add, dot, norm, scale, sub, unit};

/// Most lights a rig may have. Real rigs have tens to a few hundred; the bound keeps a malformed
/// rig file from asking for unbounded work (every light is one image of the stack).
pub const MAX_LIGHTS: usize = 10_000;

/// Camera model.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub enum Camera {
    /// Orthographic camera looking along +z. Vertex (r, c) of the mesh stands at
    /// `x = origin[0] + c * pixel_size[0]`, `y = origin[1] + r * pixel_size[1]`: `origin` is the
    /// top-left corner of pixel (0, 0), `pixel_size` = (w, h) the footprint of one pixel.
    Orthographic {
        /// Pixel footprint (w, h) in scene units.
        pixel_size: [f64; 2],
        /// Scene (x, y) of the top-left corner of pixel (0, 0).
        origin: [f64; 2],
    },
    /// Pinhole camera at the origin with intrinsics `k` in the 0-based pixel-centre convention
    /// (pixel (r, c) has its centre at (u, v) = (c, r)) and OpenCV distortion coefficients
    /// (k1, k2, p1, p2, k3). Vertex (r, c) sits on the ray through the pixel corner
    /// (u, v) = (c - 1/2, r - 1/2), scaled to z = 1, at depth z.
    Pinhole {
        /// Intrinsic matrix, row-major.
        k: [[f64; 3]; 3],
        /// Distortion (k1, k2, p1, p2, k3); zeros for none.
        distortion: [f64; 5],
    },
}

impl Camera {
    /// OpenCV's distortion coefficients as (k1, k2, p1, p2, k3): 0, 1, 2, 4 or 5 of them (a
    /// prefix of k1, k2, p1, p2, k3 that keeps p1 and p2 together; missing ones are zero), or 8,
    /// 12 or 14 (OpenCV's rational, thin-prism and tilted models) when the coefficients after k3
    /// are zero. 3 are ambiguous (OpenCV's k1, k2, p1 or a radial k1, k2, k3) and refused. The
    /// one implementation of this rule for the rig file reader (`nplps::io`) and the Python
    /// bindings.
    pub fn distortion_from(coefficients: &[f64]) -> Result<[f64; 5]> {
        const WHAT: &str = "camera.distortion";
        let c = coefficients;
        let mut d = [0.0; 5];
        match c.len() {
            0 | 1 | 2 | 4 | 5 => d[..c.len()].copy_from_slice(c),
            3 => {
                return Err(Error::Rig(format!(
                "{WHAT} has 3 coefficients, which is ambiguous (OpenCV's k1, k2, p1 or a radial \
                     k1, k2, k3): give 4 or 5 (k1, k2, p1, p2[, k3])"
            )))
            }
            n @ (8 | 12 | 14) => {
                const NAMES: [&str; 14] = [
                    "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4",
                    "tau_x", "tau_y",
                ];
                if let Some(i) = (5..n).find(|&i| c[i] != 0.0) {
                    return Err(Error::Rig(format!(
                        "{WHAT} has {n} coefficients and {} = {} is not zero: nplps models k1, k2, \
                         p1, p2, k3 only, not OpenCV's rational (k4, k5, k6), thin-prism (s1..s4) \
                         or tilt (tau_x, tau_y) terms",
                        NAMES[i],
                        crate::error::g6(c[i])
                    )));
                }
                d.copy_from_slice(&c[..5]);
            }
            n => {
                return Err(Error::Rig(format!(
                    "{WHAT} has {n} coefficients; OpenCV's models have 4, 5, 8, 12 or 14 \
                     (nplps models k1, k2, p1, p2, k3)"
                )))
            }
        }
        Ok(d)
    }

    /// Whether the global step works on log-depth (pinhole) rather than depth (orthographic).
    pub fn is_perspective(&self) -> bool {
        matches!(self, Camera::Pinhole { .. })
    }

    /// Checks that the camera's parameters are finite, the pixel size positive, and K a valid
    /// upper-triangular intrinsic matrix with positive focal lengths.
    pub fn validate(&self) -> Result<()> {
        match *self {
            Camera::Orthographic { pixel_size, origin } => {
                if !pixel_size.iter().all(|s| s.is_finite() && *s > 0.0) {
                    return Err(Error::Rig(format!(
                        "pixel size must be positive and finite, got {}",
                        g6_list(&pixel_size)
                    )));
                }
                if !origin.iter().all(|o| o.is_finite()) {
                    return Err(Error::Rig(format!(
                        "origin must be finite, got {}",
                        g6_list(&origin)
                    )));
                }
                if pixel_size.iter().any(|s| *s < MIN_MAGNITUDE) {
                    return Err(Error::Rig(format!(
                        "pixel size must be at least {}, got {}",
                        g6(MIN_MAGNITUDE),
                        g6_list(&pixel_size)
                    )));
                }
                check_magnitude("the camera's pixel_size", &pixel_size)?;
                check_magnitude("the camera's origin", &origin)
            }
            Camera::Pinhole { k, distortion } => {
                let finite = k.iter().flatten().chain(&distortion).all(|v| v.is_finite());
                let shape_ok = k[1][0] == 0.0 && k[2] == [0.0, 0.0, 1.0];
                if !(finite && shape_ok && k[0][0] > 0.0 && k[1][1] > 0.0) {
                    let rows: Vec<String> = k.iter().map(|r| g6_list(r)).collect();
                    return Err(Error::Rig(format!(
                        "K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with positive finite focal \
                         lengths (and finite distortion), got K = [{}], distortion = {}",
                        rows.join(", "),
                        g6_list(&distortion)
                    )));
                }
                if k[0][0] < MIN_MAGNITUDE || k[1][1] < MIN_MAGNITUDE {
                    return Err(Error::Rig(format!(
                        "the focal lengths fx, fy must be at least {}, got {}",
                        g6(MIN_MAGNITUDE),
                        g6_list(&[k[0][0], k[1][1]])
                    )));
                }
                check_magnitude("the camera's K", k.as_flattened())?;
                check_magnitude("the camera's distortion", &distortion)
            }
        }
    }

    /// The point at depth `z` of [`Camera::vertex_xy`]'s `xy`: `(x z, y z, z)` on a pinhole
    /// camera's ray, `(x, y, z)` for an orthographic camera (as `Geometry::position_at_depth`).
    #[inline]
    pub fn at_depth(&self, [x, y]: [f64; 2], z: f64) -> [f64; 3] {
        if self.is_perspective() {
            [x * z, y * z, z]
        } else {
            [x, y, z]
        }
    }

    /// Orthographic: the scene (x, y) of vertex (r, c). Pinhole: the ray (x, y) of vertex (r, c)
    /// at z = 1, undistorted; NaN where the distortion cannot be undone (see
    /// `undistort_checked`).
    pub fn vertex_xy(&self, r: usize, c: usize) -> [f64; 2] {
        match *self {
            Camera::Orthographic { pixel_size, origin } => [
                origin[0] + c as f64 * pixel_size[0],
                origin[1] + r as f64 * pixel_size[1],
            ],
            Camera::Pinhole { k, distortion } => {
                let uv = [c as f64 - 0.5, r as f64 - 0.5];
                undistort_checked(normalized_distorted(k, uv), distortion)
            }
        }
    }

    /// The viewing ray of the image point (u, v) in the pixel-centre convention (pixel (r, c)
    /// has its centre at (u, v) = (c, r)): orthographic, from
    /// `(ox + (u + 1/2) w, oy + (v + 1/2) h, 0)` along +z; pinhole, from the camera centre along
    /// the unit direction of `(x, y, 1)`, where `(x, y)` is the undistorted normalized point
    /// `K^-1 (u, v, 1)` (unlike [`Camera::vertex_xy`], unchecked: where the distortion folds
    /// over, the fixed-point iteration's end point). The inverse of [`Camera::project`].
    pub(crate) fn ray(&self, uv: [f64; 2]) -> Ray {
        match *self {
            Camera::Orthographic { pixel_size, origin } => Ray {
                origin: [
                    origin[0] + (uv[0] + 0.5) * pixel_size[0],
                    origin[1] + (uv[1] + 0.5) * pixel_size[1],
                    0.0,
                ],
                direction: [0.0, 0.0, 1.0],
            },
            Camera::Pinhole { k, distortion } => {
                let [x, y] = undistort(normalized_distorted(k, uv), distortion);
                Ray {
                    origin: [0.0; 3],
                    direction: unit([x, y, 1.0]),
                }
            }
        }
    }

    /// The image point (u, v) (pixel-centre convention) of the camera-frame point `p`:
    /// orthographic, `((x - ox) / w - 1/2, (y - oy) / h - 1/2)`; pinhole, `K` applied to the
    /// distorted `(x / z, y / z)`, NaN behind the camera (`z <= 0`).
    pub(crate) fn project(&self, p: [f64; 3]) -> [f64; 2] {
        match *self {
            Camera::Orthographic { pixel_size, origin } => [
                (p[0] - origin[0]) / pixel_size[0] - 0.5,
                (p[1] - origin[1]) / pixel_size[1] - 0.5,
            ],
            Camera::Pinhole { k, distortion } => {
                if p[2] <= 0.0 {
                    return [f64::NAN; 2];
                }
                let [x, y] = distort([p[0] / p[2], p[1] / p[2]], distortion);
                [k[0][0] * x + k[0][1] * y + k[0][2], k[1][1] * y + k[1][2]]
            }
        }
    }

    /// Lateral extent of one pixel at depth `z` (w, h).
    pub fn pixel_size_at(&self, z: f64) -> [f64; 2] {
        match *self {
            Camera::Orthographic { pixel_size, .. } => pixel_size,
            Camera::Pinhole { k, .. } => [z / k[0][0], z / k[1][1]],
        }
    }
}

/// `K^-1 (u, v, 1)`: the distorted normalized point of the image point (u, v), for the upper
/// triangular intrinsics `k` (`y = (v - cy) / fy`, `x = (u - cx - s y) / fx`).
fn normalized_distorted(k: [[f64; 3]; 3], uv: [f64; 2]) -> [f64; 2] {
    let yd = (uv[1] - k[1][2]) / k[1][1];
    let xd = (uv[0] - k[0][2] - k[0][1] * yd) / k[0][0];
    [xd, yd]
}

/// A ray: origin and unit direction (camera frame), such as the viewing ray of an image point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ray {
    /// Origin (camera frame).
    pub origin: [f64; 3],
    /// Unit direction.
    pub direction: [f64; 3],
}

impl Ray {
    /// The point at parameter `t`: `origin + t direction`.
    pub fn at(&self, t: f64) -> [f64; 3] {
        add(self.origin, scale(self.direction, t))
    }

    /// Distance of the point `p` from the (infinite) line of the ray:
    /// `|(p - o) - ((p - o) . d) d|`.
    pub fn distance_to(&self, p: [f64; 3]) -> f64 {
        let a = sub(p, self.origin);
        norm(sub(a, scale(self.direction, dot(a, self.direction))))
    }
}

/// The first point light (index and z) that is not strictly in front of a surface whose nearest
/// depth is `depth` (see [`Light::is_in_front_of`]).
pub(crate) fn first_behind(lights: &[Light], depth: f64) -> Option<(usize, f64)> {
    lights
        .iter()
        .enumerate()
        .find_map(|(i, light)| match *light {
            Light::Point { position, .. } if !light.is_in_front_of(depth) => Some((i, position[2])),
            _ => None,
        })
}

/// OpenCV's distortion model: the distorted normalized point of the undistorted point `p`.
pub(crate) fn distort(p: [f64; 2], dist: [f64; 5]) -> [f64; 2] {
    let [k1, k2, p1, p2, k3] = dist;
    let (x, y) = (p[0], p[1]);
    let r2 = x * x + y * y;
    let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
    [
        x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
        y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
    ]
}

/// [`undistort`], checked: NaN unless the distortion model maps the result back onto `d` (to
/// 1e-9 of its size). Far from the centre a strong distortion folds over and maps no point
/// there; the fixed-point iteration then ends anywhere, and that ray would be a lie.
pub(crate) fn undistort_checked(d: [f64; 2], dist: [f64; 5]) -> [f64; 2] {
    let x = undistort(d, dist);
    if dist.iter().all(|c| *c == 0.0) {
        return x;
    }
    let back = distort(x, dist);
    let miss = (back[0] - d[0]).hypot(back[1] - d[1]);
    if miss <= 1e-9 * (1.0 + d[0].hypot(d[1])) {
        x
    } else {
        [f64::NAN; 2]
    }
}

/// Inverts OpenCV's distortion model by fixed-point iteration (as `cv::undistortPoints` does).
pub(crate) fn undistort(d: [f64; 2], dist: [f64; 5]) -> [f64; 2] {
    if dist.iter().all(|c| *c == 0.0) {
        return d;
    }
    let [k1, k2, p1, p2, k3] = dist;
    let (mut x, mut y) = (d[0], d[1]);
    for _ in 0..30 {
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        let dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
        let dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
        x = (d[0] - dx) / radial;
        y = (d[1] - dy) / radial;
    }
    [x, y]
}

/// A calibrated rig: one camera and k lights.
#[derive(Debug, Clone, PartialEq)]
pub struct Rig {
    /// The camera.
    pub camera: Camera,
    /// The lights, in the order of the images.
    pub lights: Vec<Light>,
}

impl Rig {
    /// An orthographic rig with isotropic unit point lights at `positions`.
    pub fn orthographic(
        pixel_size: [f64; 2],
        origin: [f64; 2],
        positions: Vec<[f64; 3]>,
    ) -> Result<Rig> {
        let rig = Rig {
            camera: Camera::Orthographic { pixel_size, origin },
            lights: positions.into_iter().map(Light::point).collect(),
        };
        rig.validate()?;
        Ok(rig)
    }

    /// Number of lights k.
    pub fn n_lights(&self) -> usize {
        self.lights.len()
    }

    /// Checks the camera and the lights (at least 3).
    pub fn validate(&self) -> Result<()> {
        if self.lights.len() < 3 {
            return Err(Error::Rig(format!(
                "photometric stereo needs at least 3 lights, the rig has {}",
                self.lights.len()
            )));
        }
        self.validate_parameters()
    }

    /// Checks the camera and every light's parameters, whatever their number up to
    /// [`MAX_LIGHTS`] (rendering and prediction work with any number of lights).
    pub fn validate_parameters(&self) -> Result<()> {
        if self.lights.len() > MAX_LIGHTS {
            return Err(Error::Rig(format!(
                "the rig has {} lights; at most {MAX_LIGHTS} are supported",
                self.lights.len()
            )));
        }
        self.camera.validate()?;
        self.lights
            .iter()
            .enumerate()
            .try_for_each(|(i, l)| l.validate(i))
    }

    /// Fails when a point light is not strictly in front of the surface (its z must be smaller
    /// than the smallest surface depth `min_depth`: lights stand on the camera's side).
    pub fn check_lights_in_front(&self, min_depth: f64) -> Result<()> {
        match first_behind(&self.lights, min_depth) {
            Some((i, z)) => Err(Error::Rig(format!(
                "light {i} at z = {} is not in front of the surface (nearest depth {}); \
                 lights must have smaller z than the object (z grows away from the camera)",
                g6(z),
                g6(min_depth)
            ))),
            None => Ok(()),
        }
    }
}

/// Two cameras for tests that must hold on both kinds: a pinhole camera with skew and every
/// distortion coefficient, and an orthographic one with unequal pixel sides.
#[cfg(test)]
pub(crate) fn test_cameras() -> [Camera; 2] {
    [
        Camera::Pinhole {
            k: [[20.0, 0.3, 4.5], [0.0, 21.0, 3.2], [0.0, 0.0, 1.0]],
            distortion: [-0.2, 0.05, 0.001, -0.002, 0.01],
        },
        Camera::Orthographic {
            pixel_size: [0.3, 0.25],
            origin: [-1.0, 2.0],
        },
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lights() -> Vec<[f64; 3]> {
        vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    }

    #[test]
    fn vertex_positions_follow_the_grid() {
        let rig = Rig::orthographic([0.5, 0.25], [-1.0, 2.0], lights()).unwrap();
        assert_eq!(rig.camera.vertex_xy(0, 0), [-1.0, 2.0]);
        assert_eq!(rig.camera.vertex_xy(4, 2), [0.0, 3.0]);
    }

    #[test]
    fn pinhole_rays_go_through_pixel_corners() {
        let cam = Camera::Pinhole {
            k: [[100.0, 0.0, 10.0], [0.0, 200.0, 20.0], [0.0, 0.0, 1.0]],
            distortion: [0.0; 5],
        };
        cam.validate().unwrap();
        // Corner (r, c) = (20.5, 10.5) is the principal point.
        let [x, y] = cam.vertex_xy(0, 0);
        assert!((x + 10.5 / 100.0).abs() < 1e-15 && (y + 20.5 / 200.0).abs() < 1e-15);
    }

    #[test]
    fn viewing_rays_and_projection_invert_each_other() {
        let cameras = [
            Camera::Orthographic {
                pixel_size: [0.5, 0.25],
                origin: [-10.0, 3.0],
            },
            Camera::Pinhole {
                k: [[400.0, 2.0, 99.5], [0.0, 410.0, 95.5], [0.0, 0.0, 1.0]],
                distortion: [-0.1, 0.02, 0.001, -0.002, 0.0],
            },
        ];
        for cam in cameras {
            for uv in [[0.0, 0.0], [37.25, 120.5], [199.0, 3.75]] {
                let ray = cam.ray(uv);
                assert!((norm(ray.direction) - 1.0).abs() < 1e-15);
                let back = cam.project(ray.at(250.0));
                assert!((back[0] - uv[0]).abs() < 1e-8 && (back[1] - uv[1]).abs() < 1e-8);
            }
            // The ray through a pixel corner is the vertex ray of the mesh.
            let [x, y] = cam.vertex_xy(7, 11);
            let ray = cam.ray([10.5, 6.5]);
            if cam.is_perspective() {
                let d = ray.direction;
                assert!((d[0] / d[2] - x).abs() < 1e-12 && (d[1] / d[2] - y).abs() < 1e-12);
            } else {
                assert_eq!([ray.origin[0], ray.origin[1]], [x, y]);
            }
        }
        assert!(cameras[1].project([1.0, 1.0, 0.0])[0].is_nan());
    }

    #[test]
    fn undistortion_inverts_the_distortion_model() {
        let dist = [-0.2, 0.05, 0.001, -0.002, 0.01];
        let (x, y) = (0.3f64, -0.2f64);
        let r2 = x * x + y * y;
        let radial = 1.0 + dist[0] * r2 + dist[1] * r2 * r2 + dist[4] * r2 * r2 * r2;
        let xd = x * radial + 2.0 * dist[2] * x * y + dist[3] * (r2 + 2.0 * x * x);
        let yd = y * radial + dist[2] * (r2 + 2.0 * y * y) + 2.0 * dist[3] * x * y;
        let [ux, uy] = undistort([xd, yd], dist);
        assert!((ux - x).abs() < 1e-10 && (uy - y).abs() < 1e-10);
        assert_eq!(distort([x, y], dist), [xd, yd]);
        assert_eq!(undistort_checked([xd, yd], dist), [ux, uy]);
    }

    #[test]
    fn distortion_that_cannot_be_undone_gives_no_ray() {
        // k1 = -0.2 maps radius r to at most 0.86 (at r = 1.29): radius 1 has no preimage.
        let dist = [-0.2, 0.0, 0.0, 0.0, 0.0];
        assert!(undistort_checked([0.8, 0.6], dist)
            .iter()
            .all(|v| v.is_nan()));
        assert!(undistort_checked([0.4, 0.3], dist)
            .iter()
            .all(|v| v.is_finite()));
        let cam = Camera::Pinhole {
            k: [[10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [0.0, 0.0, 1.0]],
            distortion: dist,
        };
        assert!(cam.vertex_xy(10, 10)[0].is_nan());
        assert!(cam.vertex_xy(3, 3)[0].is_finite());
    }

    #[test]
    fn rejects_bad_rigs() {
        assert!(matches!(
            Rig::orthographic([0.0, 1.0], [0.0, 0.0], lights()),
            Err(Error::Rig(_))
        ));
        assert!(matches!(
            Rig::orthographic([1.0, 1.0], [0.0, 0.0], lights()[..2].to_vec()),
            Err(Error::Rig(_))
        ));
        let mut l = lights();
        l[1][2] = f64::NAN;
        assert!(Rig::orthographic([1.0, 1.0], [0.0, 0.0], l).is_err());
        let rig = Rig::orthographic([1.0, 1.0], [0.0, 0.0], lights()).unwrap();
        assert!(rig.check_lights_in_front(1.0).is_ok());
        assert!(rig.check_lights_in_front(0.0).is_err());
        let bad_k = Camera::Pinhole {
            k: [[0.0, 0.0, 1.0], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]],
            distortion: [0.0; 5],
        };
        assert!(bad_k.validate().is_err());
    }
}
