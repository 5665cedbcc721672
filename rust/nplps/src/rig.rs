//! Rig: the camera model and the light sources.
//!
//! The camera frame is OpenCV's: x right (increasing column), y down (increasing row), z forward
//! into the scene; depth is z. Units are the user's (mm typical): pixel sizes and light positions
//! share them.

use crate::error::{Error, Result};

/// Camera model. Only the paper's orthographic camera exists for now; pinhole cameras extend this
/// enum.
#[derive(Debug, Clone, Copy, PartialEq)]
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
}

impl Camera {
    /// Scene (x, y) of vertex (r, c) (a pixel corner).
    #[inline]
    pub fn vertex_xy(&self, r: usize, c: usize) -> [f64; 2] {
        match *self {
            Camera::Orthographic { pixel_size, origin } => [
                origin[0] + c as f64 * pixel_size[0],
                origin[1] + r as f64 * pixel_size[1],
            ],
        }
    }

    /// Pixel footprint (w, h).
    #[inline]
    pub fn pixel_size(&self) -> [f64; 2] {
        match *self {
            Camera::Orthographic { pixel_size, .. } => pixel_size,
        }
    }

    /// Checks that the camera's parameters are finite and its pixel size positive.
    pub fn validate(&self) -> Result<()> {
        match *self {
            Camera::Orthographic { pixel_size, origin } => {
                if !pixel_size.iter().all(|s| s.is_finite() && *s > 0.0) {
                    return Err(Error::Rig(format!(
                        "pixel size must be positive and finite, got {pixel_size:?}"
                    )));
                }
                if !origin.iter().all(|o| o.is_finite()) {
                    return Err(Error::Rig(format!("origin must be finite, got {origin:?}")));
                }
                Ok(())
            }
        }
    }
}

/// A calibrated rig: one camera and k isotropic point lights.
///
/// Image model at a surface point `x` with unit normal `n` and albedo `rho`:
/// `I_k = rho * max(0, n . (p_k - x)) / |p_k - x|^3`.
#[derive(Debug, Clone, PartialEq)]
pub struct Rig {
    /// The camera.
    pub camera: Camera,
    /// Light positions `p_k` in the camera frame.
    pub lights: Vec<[f64; 3]>,
}

impl Rig {
    /// An orthographic rig; fails on non-positive pixel sizes, non-finite values or fewer than
    /// three lights.
    pub fn orthographic(
        pixel_size: [f64; 2],
        origin: [f64; 2],
        lights: Vec<[f64; 3]>,
    ) -> Result<Rig> {
        let rig = Rig {
            camera: Camera::Orthographic { pixel_size, origin },
            lights,
        };
        rig.validate()?;
        Ok(rig)
    }

    /// Number of lights k.
    pub fn n_lights(&self) -> usize {
        self.lights.len()
    }

    /// Checks the camera and the lights.
    pub fn validate(&self) -> Result<()> {
        self.camera.validate()?;
        if self.lights.len() < 3 {
            return Err(Error::Rig(format!(
                "photometric stereo needs at least 3 lights, the rig has {}",
                self.lights.len()
            )));
        }
        if let Some(i) = self
            .lights
            .iter()
            .position(|p| !p.iter().all(|v| v.is_finite()))
        {
            return Err(Error::Rig(format!(
                "light {i} has a non-finite position {:?}",
                self.lights[i]
            )));
        }
        Ok(())
    }

    /// Fails when a light is not strictly in front of the surface (its z must be smaller than
    /// the smallest surface depth `min_depth`: lights stand between the camera side and the
    /// object).
    pub fn check_lights_in_front(&self, min_depth: f64) -> Result<()> {
        if let Some(i) = self.lights.iter().position(|p| p[2] >= min_depth) {
            return Err(Error::Rig(format!(
                "light {i} at z = {} is not in front of the surface (nearest depth {min_depth}); \
                 lights must have smaller z than the object (z grows away from the camera)",
                self.lights[i][2]
            )));
        }
        Ok(())
    }
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
    }
}
