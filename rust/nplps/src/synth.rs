//! Synthetic scenes with ground truth, for tests, the demo and the benchmark.
//!
//! Every scene is an object of lateral size `size` (the grid spans `[-size/2, size/2]^2` with
//! the orthographic camera; a pinhole camera sees the same extent at the working distance) whose
//! mean vertex depth is about `distance`, seen by
//! [`standard_lights`]: 27 point lights in three layers 1.5, 2.25 and 3 object sizes in front of
//! the object, spread over about the object's size. Albedo is `distance^2 * (0.6 + 0.4 * s)`
//! with a smooth pattern `s` in [0, 1], so intensities are of order 1.

use std::f64::consts::PI;

use crate::error::{Error, Result};
use crate::rig::{Camera, Light, Rig};
use crate::vec3::{dot, normalize, sub};

/// The kinds of synthetic scene.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SceneKind {
    /// `z = d + 0.5 (x^2 - y^2) / size`: slopes up to 0.5.
    Saddle,
    /// A sphere of radius 0.6 size seen inside a disc mask of radius 0.45 size (slopes to ~49
    /// degrees).
    SphereCap,
    /// Two faces of a cube turned about the vertical axis (40 and 50 degrees), its sharp edge on
    /// the middle vertex column.
    Cube,
    /// A plane with 12 random Gaussian bumps and dents (seeded).
    Bumps,
    /// A square block (0.4 size wide, 0.2 size tall, sharp walls one pixel wide) standing on a
    /// plane: the lights cast its shadow on the plane (the scene with cast shadows; see
    /// [`crate::shadow`]).
    Block,
}

impl SceneKind {
    /// All kinds, in a fixed order.
    pub const ALL: [SceneKind; 5] = [
        SceneKind::Saddle,
        SceneKind::SphereCap,
        SceneKind::Cube,
        SceneKind::Bumps,
        SceneKind::Block,
    ];

    /// Lower-case name (`saddle`, `sphere`, `cube`, `bumps`, `block`).
    pub fn name(&self) -> &'static str {
        match self {
            SceneKind::Saddle => "saddle",
            SceneKind::SphereCap => "sphere",
            SceneKind::Cube => "cube",
            SceneKind::Bumps => "bumps",
            SceneKind::Block => "block",
        }
    }

    /// Parses a name given by [`SceneKind::name`].
    pub fn from_name(name: &str) -> Result<SceneKind> {
        SceneKind::ALL
            .into_iter()
            .find(|k| k.name() == name)
            .ok_or_else(|| {
                let names: Vec<_> = SceneKind::ALL.iter().map(|k| k.name()).collect();
                Error::Unusable(format!(
                    "unknown scene {name:?}; choose one of {}",
                    names.join(", ")
                ))
            })
    }
}

/// Variations of the rig and images of a synthetic scene.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[non_exhaustive]
pub struct SceneOptions {
    /// A pinhole camera at the origin (focal length so that the object spans the image) instead
    /// of the orthographic one; the surface is then `z = surface(D x_r, D y_r)` on each ray.
    pub pinhole: bool,
    /// Anisotropic LEDs aimed at the object (mu from 0.5 to 2) with unequal RGB intensities.
    pub led: bool,
    /// Colour albedo (3 channels).
    pub rgb: bool,
    /// Every third light is a distant, directional light.
    pub directional: bool,
}

with_fields!(SceneOptions {
    with_pinhole: pinhole: bool,
    with_led: led: bool,
    with_rgb: rgb: bool,
    with_directional: directional: bool,
});

/// A synthetic scene: true surface, mask, albedo and rig.
#[derive(Debug, Clone)]
#[non_exhaustive]
pub struct Scene {
    /// Image height H.
    pub height: usize,
    /// Image width W.
    pub width: usize,
    /// True vertex depths, (H+1) x (W+1).
    pub depth: Vec<f64>,
    /// Mask, H x W.
    pub mask: Vec<bool>,
    /// Channels of the albedo and the images (1 or 3).
    pub channels: usize,
    /// True albedo, H x W x channels.
    pub albedo: Vec<f64>,
    /// The rig (27 lights).
    pub rig: Rig,
    /// Lateral object size.
    pub size: f64,
}

impl Scene {
    /// Builds a scene of `n` x `n` pixels, lateral size `size` and working distance `distance`
    /// with an orthographic camera and isotropic unit point lights; `seed` drives the random
    /// bumps.
    pub fn new(kind: SceneKind, n: usize, size: f64, distance: f64, seed: u64) -> Result<Scene> {
        Scene::with_options(kind, n, size, distance, seed, SceneOptions::default())
    }

    /// As [`Scene::new`] with the variations in `options`.
    pub fn with_options(
        kind: SceneKind,
        n: usize,
        size: f64,
        distance: f64,
        seed: u64,
        options: SceneOptions,
    ) -> Result<Scene> {
        if n < 2 || size.is_nan() || size <= 0.0 || distance.is_nan() || distance <= 0.0 {
            return Err(Error::Unusable(format!(
                "a scene needs n >= 2 pixels and positive size and distance, got n = {n}, size = {size}, distance = {distance}"
            )));
        }
        let side = n as f64 + 1.0;
        crate::memory::check(
            || format!("a {n} x {n} synthetic scene"),
            // Depth, lateral positions, albedo, mask and the mean-depth grid: ~100 B per vertex.
            100.0 * side * side,
            None,
        )?;
        let camera = if options.pinhole {
            let f = n as f64 * distance / size;
            let c = (n as f64 - 1.0) / 2.0;
            Camera::Pinhole {
                k: [[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]],
                distortion: [0.0; 5],
            }
        } else {
            let pixel = size / n as f64;
            Camera::Orthographic {
                pixel_size: [pixel, pixel],
                origin: [-0.5 * size, -0.5 * size],
            }
        };
        let rig = Rig {
            camera,
            lights: scene_lights(size, distance, options),
        };
        rig.validate()?;
        let bumps = random_bumps(size, seed);
        let surface = |x: f64, y: f64| -> f64 {
            match kind {
                SceneKind::Saddle => distance + 0.5 * (x * x - y * y) / size,
                SceneKind::SphereCap => {
                    let r = 0.6 * size;
                    distance - (r * r - x * x - y * y).max(0.0).sqrt() + 0.5 * r
                }
                SceneKind::Cube => {
                    let t = if x < 0.0 {
                        -(40f64.to_radians().tan())
                    } else {
                        50f64.to_radians().tan()
                    };
                    distance - 0.25 * size + t * x
                }
                SceneKind::Bumps => {
                    distance
                        + bumps
                            .iter()
                            .map(|b| {
                                b.amplitude
                                    * (-((x - b.x).powi(2) + (y - b.y).powi(2))
                                        / (2.0 * b.sigma * b.sigma))
                                        .exp()
                            })
                            .sum::<f64>()
                }
                SceneKind::Block => {
                    let inside = x.abs() <= 0.2 * size && y.abs() <= 0.2 * size;
                    distance + 0.05 * size - if inside { 0.2 * size } else { 0.0 }
                }
            }
        };
        // Lateral coordinates of each vertex: the grid (orthographic) or the ray at the working
        // distance (pinhole).
        let vw = n + 1;
        let lateral: Vec<[f64; 2]> = (0..vw * vw)
            .map(|v| {
                let [x, y] = camera.vertex_xy(v / vw, v % vw);
                if options.pinhole {
                    [x * distance, y * distance]
                } else {
                    [x, y]
                }
            })
            .collect();
        let depth: Vec<f64> = lateral.iter().map(|&[x, y]| surface(x, y)).collect();
        let centre = |p: usize| {
            let v = (p / n) * vw + p % n;
            let corners = [
                lateral[v],
                lateral[v + 1],
                lateral[v + vw],
                lateral[v + vw + 1],
            ];
            (
                corners.iter().map(|c| c[0]).sum::<f64>() / 4.0,
                corners.iter().map(|c| c[1]).sum::<f64>() / 4.0,
            )
        };
        let mask: Vec<bool> = (0..n * n)
            .map(|p| {
                let (x, y) = centre(p);
                kind != SceneKind::SphereCap || x * x + y * y <= (0.45 * size).powi(2)
            })
            .collect();
        let channels = if options.rgb { 3 } else { 1 };
        let tints = [[1.0, 0.0], [0.8, 0.2], [0.6, 0.4]];
        let albedo: Vec<f64> = (0..n * n)
            .flat_map(|p| {
                let (x, y) = centre(p);
                let s =
                    0.5 + 0.25 * (2.0 * PI * x / size).sin() + 0.25 * (3.0 * PI * y / size).cos();
                let s2 = 0.5 + 0.5 * (PI * (x + y) / size).cos();
                let base = distance * distance * (0.6 + 0.4 * s);
                tints[..channels]
                    .iter()
                    .map(move |[a, b]| base * (a + b * s2))
                    .collect::<Vec<_>>()
            })
            .collect();
        Ok(Scene {
            height: n,
            width: n,
            depth,
            mask,
            channels,
            albedo,
            rig,
            size,
        })
    }

    /// The scene's true surface (depths, albedo, mask) as the renderer takes it.
    pub fn surface(&self) -> crate::render::Surface<'_> {
        crate::render::Surface {
            height: self.height,
            width: self.width,
            depth: &self.depth,
            albedo: &self.albedo,
            channels: self.channels,
            mask: Some(&self.mask),
        }
    }

    /// The scene's images (k, H, W, C), rendered by the model.
    pub fn render(&self) -> Result<Vec<f64>> {
        crate::render::render(&self.rig, &self.surface())
    }

    /// Mean of the true vertex depths used by the mask: arithmetic (orthographic) or geometric
    /// (pinhole) — the true gauge.
    pub fn mean_depth(&self) -> f64 {
        let grid = crate::grid::Grid::new(self.height, self.width, Some(&self.mask))
            .expect("scene mask is valid");
        let z = grid
            .gather_vertices(&self.depth)
            .expect("the scene's depths fit in memory");
        if self.rig.camera.is_perspective() {
            (z.iter().map(|v| v.ln()).sum::<f64>() / z.len() as f64).exp()
        } else {
            z.iter().sum::<f64>() / z.len() as f64
        }
    }
}

/// The scene's lights: [`standard_lights`] as isotropic unit point lights, or with the LED and
/// directional variations of `options`.
fn scene_lights(size: f64, distance: f64, options: SceneOptions) -> Vec<Light> {
    let target = [0.0, 0.0, distance];
    standard_lights(size, distance)
        .into_iter()
        .enumerate()
        .map(|(i, position)| {
            let t = i as f64;
            let intensity = if options.led {
                let base = 0.8 + 0.4 * (0.5 + 0.5 * (1.7 * t).sin());
                [
                    base,
                    base * (0.9 + 0.1 * (0.9 * t).cos()),
                    base * (0.85 + 0.1 * (1.3 * t).sin()),
                ]
            } else {
                [1.0; 3]
            };
            if options.directional && i % 3 == 2 {
                let to_light = sub(position, target);
                let d2 = dot(to_light, to_light);
                return Light::Directional {
                    direction: normalize(to_light),
                    intensity: intensity.map(|v| v / d2),
                };
            }
            let (axis, mu) = if options.led {
                (normalize(sub(target, position)), 0.5 + 0.5 * (i % 4) as f64)
            } else {
                ([0.0, 0.0, 1.0], 0.0)
            };
            Light::Point {
                position,
                intensity,
                axis,
                mu,
            }
        })
        .collect()
}

/// 27 point lights: three layers at `distance - {1.5, 2.25, 3} * size`, each 9 lights on circles
/// of radius 0.3, 0.4 and 0.5 times `size`, turned from layer to layer so that no two lights are
/// aligned with the object's centre.
pub fn standard_lights(size: f64, distance: f64) -> Vec<[f64; 3]> {
    let mut lights = Vec::with_capacity(27);
    for (layer, stand_off) in [1.5, 2.25, 3.0].into_iter().enumerate() {
        for i in 0..9 {
            let angle = 2.0 * PI * (i as f64 + layer as f64 / 3.0) / 9.0;
            let radius = size * (0.3 + 0.1 * (i % 3) as f64);
            lights.push([
                radius * angle.cos(),
                radius * angle.sin(),
                distance - stand_off * size,
            ]);
        }
    }
    lights
}

struct Bump {
    x: f64,
    y: f64,
    sigma: f64,
    amplitude: f64,
}

/// 12 Gaussian bumps with centres inside the object, widths 0.06..0.15 size and heights
/// +-0.03..0.08 size, from a splitmix64 stream.
fn random_bumps(size: f64, seed: u64) -> Vec<Bump> {
    let mut state = seed;
    let mut uniform = move || {
        state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    };
    (0..12)
        .map(|_| {
            let x = (uniform() - 0.5) * 0.8 * size;
            let y = (uniform() - 0.5) * 0.8 * size;
            let sigma = (0.06 + 0.09 * uniform()) * size;
            let sign = if uniform() < 0.5 { -1.0 } else { 1.0 };
            let amplitude = sign * (0.03 + 0.05 * uniform()) * size;
            Bump {
                x,
                y,
                sigma,
                amplitude,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Of the scenes, at the default rig, only the block casts shadows (the others' slopes stay
    /// below the lights' angles); the block shadows a fair share of the plane.
    #[test]
    fn the_block_scene_casts_shadows() {
        for kind in SceneKind::ALL {
            for pinhole in [false, true] {
                let options = SceneOptions::default().with_pinhole(pinhole);
                let scene = Scene::with_options(kind, 48, 100.0, 200.0, 0, options).unwrap();
                let shadows = crate::shadow::cast_shadows(
                    &scene.rig,
                    48,
                    48,
                    &scene.depth,
                    Some(&scene.mask),
                    None,
                )
                .unwrap();
                let share = shadows.count() as f64 / (48.0 * 48.0 * 27.0);
                println!("{} pinhole {pinhole}: {share:.4}", kind.name());
                if kind == SceneKind::Block {
                    assert!(share > 0.005, "{share}");
                }
            }
        }
        assert_eq!(SceneKind::from_name("block").unwrap(), SceneKind::Block);
    }
}
