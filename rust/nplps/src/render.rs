//! Rendering by the image model, and geometry of a depth map (vertices, mesh normals).
//!
//! A facet with corners `q` (vertices at pixel corners) has centre `c = mean(q)` and mesh normal
//! `n = normalize((q10 - q01) x (q11 - q00))`; its image under light k in channel `ch` is
//! `I = rho_ch * Phi_{k,ch} * max(0, n . beta_k(c))` (attached shadows clipped at 0; see
//! [`Light::beta`]). Grey images use the mean of each light's channels.
//!
//! [`render_with`] adds, on request ([`RenderOptions`]):
//! - the glossy model of [`crate::reflectance`]: with a grey specular albedo `rho_s` per pixel
//!   and a [`Lobe`], `I = Phi_{k,ch} a (rho_ch D(n) + rho_s S(n))` with `a = |beta_k(c)|` and
//!   `l = beta_k(c) / a` (so that `Phi a l = Phi beta`: the same light as the Lambertian
//!   model), `D`, `S` of [`Lobe::shade`] with the view vector `v` from `c` to the camera
//!   (pinhole: `-c / |c|`; orthographic: `(0, 0, -1)`). Facets turned away from the light or
//!   the camera are 0. At `eta = 1` and `rho_s = 0`, `a D(n) = max(0, n . beta)`: the
//!   Lambertian image, to rounding;
//! - cast shadows ([`crate::shadow`]): an observation whose segment to the light passes behind
//!   the surface is 0.

use rayon::prelude::*;

use crate::error::{ensure_mask, ensure_range, ensure_shape, Result};
use crate::geometry::{pixel_quad, quad_centre, quad_normal, vertices};
use crate::light::{channel_intensity, Light};
use crate::reflectance::Lobe;
use crate::rig::{Camera, Rig};
use crate::vec3::{norm, normalize, not_above, scale, sub};

/// A surface to shade: an (H+1) x (W+1) vertex depth map (row-major) with a per-pixel albedo
/// (H x W x C, C = 1 or 3) and an optional H x W mask (`true` = shade the pixel).
#[derive(Debug, Clone, Copy)]
pub struct Surface<'a> {
    /// Image height H (pixels).
    pub height: usize,
    /// Image width W (pixels).
    pub width: usize,
    /// Vertex depths, (H+1) x (W+1).
    pub depth: &'a [f64],
    /// Per-pixel albedo, H x W x C.
    pub albedo: &'a [f64],
    /// Channels C of the albedo and of the images (1 or 3).
    pub channels: usize,
    /// Pixels to shade (None: all).
    pub mask: Option<&'a [bool]>,
}

impl Surface<'_> {
    /// Checks the channels and the lengths of the albedo and the mask against H x W, and returns
    /// the vertex positions of the depth map (see [`vertices`]).
    fn vertices(&self, camera: &Camera) -> Result<Vec<[f64; 3]>> {
        let (plane, channels) = (self.height * self.width, self.channels);
        let v = vertices(camera, self.height, self.width, self.depth)?;
        ensure_range(
            channels == 1 || channels == 3,
            "channels",
            channels as f64,
            || format!("channels must be 1 or 3, got {channels}"),
        )?;
        ensure_shape("albedo", plane * channels, self.albedo.len(), || {
            format!(
                "albedo has {} values, expected H x W x C = {}",
                self.albedo.len(),
                plane * channels
            )
        })?;
        ensure_mask(self.mask, plane)?;
        Ok(v)
    }
}

/// A specular layer for [`render_with`]: a grey specular albedo per pixel (H x W, the same for
/// every channel) and the lobe shared by the surface.
#[derive(Debug, Clone, Copy)]
pub struct Specular<'a> {
    /// Specular albedo `rho_s` per pixel, H x W (non-finite: the pixel is 0).
    pub albedo: &'a [f64],
    /// The GGX lobe and the index of refraction (`0 < alpha <= 1`, `eta >= 1`).
    pub lobe: Lobe,
}

/// What [`render_with`] adds to the Lambertian model of [`render`]; the default adds nothing.
#[derive(Debug, Clone, Copy, Default)]
#[non_exhaustive]
pub struct RenderOptions<'a> {
    /// The glossy model with this specular layer (None: Lambertian).
    pub specular: Option<Specular<'a>>,
    /// Observations in a cast shadow ([`crate::shadow`]) are 0.
    pub cast_shadows: bool,
    /// The bound of the shadow march in pixels (None: `2 max(H, W)`; see
    /// [`crate::shadow::cast_shadows`]).
    pub max_steps: Option<usize>,
}

impl<'a> RenderOptions<'a> {
    /// These options with the glossy model of this specular layer (None: Lambertian).
    #[must_use]
    pub fn with_specular(mut self, specular: Option<Specular<'a>>) -> Self {
        self.specular = specular;
        self
    }

    /// These options with cast shadows on or off.
    #[must_use]
    pub fn with_cast_shadows(mut self, cast_shadows: bool) -> Self {
        self.cast_shadows = cast_shadows;
        self
    }

    /// These options with the bound of the shadow march (None: the default).
    #[must_use]
    pub fn with_max_steps(mut self, max_steps: Option<usize>) -> Self {
        self.max_steps = max_steps;
        self
    }
}

impl Specular<'_> {
    /// Checks the map's length against H x W and the lobe's parameters.
    fn check(&self, plane: usize) -> Result<()> {
        ensure_shape("specular albedo", plane, self.albedo.len(), || {
            format!(
                "the specular albedo has {} values, expected H x W = {plane}",
                self.albedo.len()
            )
        })?;
        let Lobe { alpha, eta, .. } = self.lobe;
        ensure_range(alpha > 0.0 && alpha <= 1.0, "roughness", alpha, || {
            format!(
                "roughness (GGX alpha) must be in (0, 1], got {}",
                crate::error::g6(alpha)
            )
        })?;
        ensure_range(eta.is_finite() && eta >= 1.0, "eta", eta, || {
            format!(
                "eta (the relative index of refraction) must be finite and at least 1, got {}",
                crate::error::g6(eta)
            )
        })
    }
}

/// The reflectance model [`shade_images`] applies.
#[derive(Clone, Copy)]
enum Model<'a> {
    /// `rho Phi max(0, n . beta)`.
    Lambert,
    /// The glossy model; `perspective`: the view vector is `-c / |c|` (else `(0, 0, -1)`).
    Glossy {
        specular: &'a [f64],
        lobe: Lobe,
        perspective: bool,
    },
}

impl<'a> Model<'a> {
    /// The glossy model of `specular` (checked against `plane` = H x W pixels) seen by `camera`,
    /// or the Lambertian model without it.
    fn of(specular: Option<Specular<'a>>, camera: &Camera, plane: usize) -> Result<Model<'a>> {
        Ok(match specular {
            Some(specular) => {
                specular.check(plane)?;
                Model::Glossy {
                    specular: specular.albedo,
                    lobe: specular.lobe,
                    perspective: camera.is_perspective(),
                }
            }
            None => Model::Lambert,
        })
    }
}

/// Mesh normal of every pixel of an (H+1) x (W+1) depth map (NaN where a corner is NaN).
pub fn mesh_normals(
    camera: &Camera,
    height: usize,
    width: usize,
    depth: &[f64],
) -> Result<Vec<[f64; 3]>> {
    mesh_normals_masked(camera, height, width, depth, None)
}

/// [`mesh_normals`] inside `mask` (H x W; None: everywhere), NaN outside it: a result's
/// normals. Made band by band of pixel rows from the depths, with no whole vertex grid (the same
/// bits as the normals of [`crate::vertices`]' quads).
pub fn mesh_normals_masked(
    camera: &Camera,
    height: usize,
    width: usize,
    depth: &[f64],
    mask: Option<&[bool]>,
) -> Result<Vec<[f64; 3]>> {
    crate::geometry::facet_normals(camera, height, width, depth, mask)
}

/// Renders the k images (k, H, W, C) of the surface `depth` ((H+1) x (W+1)) with per-pixel
/// `albedo` (H x W x C, C = 1 or 3). Pixels outside `mask` are 0; pixels inside it with a
/// non-finite corner (an unknown depth) are NaN in every image, so that an unknown surface does
/// not pass for a shadow.
pub fn render(rig: &Rig, surface: &Surface<'_>) -> Result<Vec<f64>> {
    render_with(rig, surface, &RenderOptions::default())
}

/// As [`render`], with the glossy model and cast shadows of `options` (see the module
/// documentation); `RenderOptions::default()` gives [`render`]'s images bit for bit.
pub fn render_with(
    rig: &Rig,
    surface: &Surface<'_>,
    options: &RenderOptions<'_>,
) -> Result<Vec<f64>> {
    let v = surface.vertices(&rig.camera)?;
    let Surface {
        height,
        width,
        albedo,
        channels,
        mask,
        ..
    } = *surface;
    let plane = height * width;
    let model = Model::of(options.specular, &rig.camera, plane)?;
    let shadows = if options.cast_shadows {
        Some(crate::shadow::shadows_of_vertices(
            rig,
            height,
            width,
            &v,
            mask,
            options.max_steps,
        )?)
    } else {
        None
    };
    let mut images = shade_images(&rig.lights, plane, channels, albedo, model, |p| {
        if mask.is_some_and(|m| !m[p]) {
            return None;
        }
        let q = pixel_quad(&v, width, p);
        Some((quad_normal(&q), quad_centre(&q)))
    })?;
    if let Some(shadows) = shadows.filter(|s| s.count() > 0) {
        let stride = plane * channels;
        images
            .par_chunks_mut(stride.max(1))
            .enumerate()
            .for_each(|(k, image)| {
                for p in 0..plane {
                    if shadows.is_shadowed(p, k) {
                        image[p * channels..(p + 1) * channels].fill(0.0);
                    }
                }
            });
    }
    let unknown: Vec<usize> = (0..plane)
        .into_par_iter()
        .filter(|&p| {
            mask.is_none_or(|m| m[p])
                && pixel_quad(&v, width, p)
                    .iter()
                    .flatten()
                    .any(|x| !x.is_finite())
        })
        .collect();
    if !unknown.is_empty() {
        for image in images.chunks_exact_mut(plane * channels) {
            for &p in &unknown {
                image[p * channels..(p + 1) * channels].fill(f64::NAN);
            }
        }
    }
    Ok(images)
}

/// The k images (k, H, W, C) of pixels shaded by `lights` under `model`: `surface(p)` gives the
/// normal and the surface point of pixel p (None: 0), `albedo` its albedo per channel. Pixels
/// with a non-finite normal, point, albedo (or specular albedo) are 0. Refused with
/// [`crate::Error::Memory`] when the images (and the per-pixel geometry) would not fit in the
/// memory available.
fn shade_images(
    lights: &[Light],
    plane: usize,
    channels: usize,
    albedo: &[f64],
    model: Model<'_>,
    surface: impl Fn(usize) -> Option<([f64; 3], [f64; 3])> + Sync,
) -> Result<Vec<f64>> {
    let stride = plane * channels;
    let values = lights.len() as f64 * stride as f64;
    // The f64 images, the per-pixel geometry, and a copy when they are handed on.
    let needed = 2.0 * 8.0 * values + 56.0 * plane as f64;
    crate::memory::check(
        || format!("rendering {} images of {plane} pixels", lights.len()),
        needed,
        None,
    )?;
    let geometry: Vec<Option<([f64; 3], [f64; 3])>> = crate::memory::try_par_collect(
        (0..plane).into_par_iter().map(|p| {
            let rho = &albedo[p * channels..(p + 1) * channels];
            let specular = match model {
                Model::Lambert => 0.0,
                Model::Glossy { specular, .. } => specular[p],
            };
            surface(p).filter(|(n, c)| {
                n.iter().chain(c).chain(rho).all(|x| x.is_finite()) && specular.is_finite()
            })
        }),
        "the rendered surface",
    )?;
    let mut out = crate::memory::try_filled(lights.len() * stride, 0.0, "the rendered images")?;
    if stride == 0 {
        return Ok(out);
    }
    out.par_chunks_mut(stride)
        .zip(lights.par_iter())
        .for_each(|(image, light)| {
            for (p, g) in geometry.iter().enumerate() {
                if let Some((n, c)) = *g {
                    let rho = &albedo[p * channels..(p + 1) * channels];
                    let out = &mut image[p * channels..(p + 1) * channels];
                    match model {
                        Model::Lambert => shade(light, n, c, rho, out),
                        Model::Glossy {
                            specular,
                            lobe,
                            perspective,
                        } => {
                            let v = if perspective {
                                scale(c, -1.0 / norm(c))
                            } else {
                                [0.0, 0.0, -1.0]
                            };
                            shade_glossy(light, &lobe, n, c, v, rho, specular[p], out);
                        }
                    }
                }
            }
        });
    Ok(out)
}

/// Predicts the k images (k, H, W, C) of a reconstruction: each pixel shaded with its own
/// (local-fit) `normals` (H x W) and `albedo` (H x W x C) at the centre of its quad on `depth`.
/// With `parallel`, each point light is replaced by a parallel light along the direction from
/// the centroid of the surface to the light (the baseline's model). Pixels outside `mask` or
/// with a NaN are 0.
pub fn predict(
    rig: &Rig,
    surface: &Surface<'_>,
    normals: &[[f64; 3]],
    parallel: bool,
) -> Result<Vec<f64>> {
    predict_with(rig, surface, normals, parallel, None)
}

/// As [`predict`], under the glossy model with the specular layer `specular` of a glossy
/// reconstruction (its specular albedo map and lobe; `surface.albedo` is then the diffuse
/// albedo); None: the Lambertian model, as [`predict`].
pub fn predict_with(
    rig: &Rig,
    surface: &Surface<'_>,
    normals: &[[f64; 3]],
    parallel: bool,
    specular: Option<Specular<'_>>,
) -> Result<Vec<f64>> {
    let v = surface.vertices(&rig.camera)?;
    let Surface {
        height,
        width,
        albedo,
        channels,
        mask,
        ..
    } = *surface;
    let plane = height * width;
    ensure_shape("normals", plane, normals.len(), || {
        format!(
            "normals has {} values, expected H x W = {plane}",
            normals.len()
        )
    })?;
    let inside = |p: usize| mask.is_none_or(|m| m[p]);
    let lights: Vec<Light> = if parallel {
        let finite: Vec<[f64; 3]> = v
            .iter()
            .copied()
            .filter(|x| x.iter().all(|c| c.is_finite()))
            .collect();
        let centroid: [f64; 3] =
            std::array::from_fn(|i| finite.iter().map(|x| x[i]).sum::<f64>() / finite.len() as f64);
        rig.lights
            .iter()
            .map(|l| match *l {
                Light::Point {
                    position,
                    intensity,
                    ..
                } => Light::Directional {
                    direction: normalize(sub(position, centroid)),
                    intensity,
                },
                other => other,
            })
            .collect()
    } else {
        rig.lights.clone()
    };
    let model = Model::of(specular, &rig.camera, plane)?;
    shade_images(&lights, plane, channels, albedo, model, |p| {
        inside(p).then(|| (normals[p], quad_centre(&pixel_quad(&v, width, p))))
    })
}

/// Writes the image values (one per channel of `rho`) of a facet with normal `n` and centre `c`
/// into `out`.
fn shade(light: &Light, n: [f64; 3], c: [f64; 3], rho: &[f64], out: &mut [f64]) {
    let shading = light.shading(n, c);
    let phi = light.intensity();
    for (ch, (r, o)) in rho.iter().zip(out.iter_mut()).enumerate() {
        *o = r * channel_intensity(phi, rho.len(), ch) * shading;
    }
}

/// Writes the image values under the glossy model (see the module documentation) of a facet
/// with normal `n`, centre `c`, view vector `v`, albedo `rho` (per channel) and specular albedo
/// `rho_s` into `out` (left at 0 where the facet turns away from the light or the camera, or
/// the light does not reach it).
#[allow(clippy::too_many_arguments)]
fn shade_glossy(
    light: &Light,
    lobe: &Lobe,
    n: [f64; 3],
    c: [f64; 3],
    v: [f64; 3],
    rho: &[f64],
    rho_s: f64,
    out: &mut [f64],
) {
    let beta = light.beta(c).0;
    let a = norm(beta);
    if not_above(a, 0.0) {
        return;
    }
    let Some(shade) = lobe.shade(n, scale(beta, 1.0 / a), v) else {
        return;
    };
    let phi = light.intensity();
    for (ch, (r, o)) in rho.iter().zip(out.iter_mut()).enumerate() {
        *o = channel_intensity(phi, rho.len(), ch)
            * a
            * (r * shade.diffuse + rho_s * shade.specular);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 2 x 3 surface at depth 10 (vertices 3 x 4) with unit albedo of C channels.
    fn surface<'a>(
        depth: &'a [f64],
        albedo: &'a [f64],
        channels: usize,
        mask: Option<&'a [bool]>,
    ) -> Surface<'a> {
        Surface {
            height: 2,
            width: 3,
            depth,
            albedo,
            channels,
            mask,
        }
    }

    #[test]
    fn render_and_predict_check_the_surface_alike() {
        let lights = vec![[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 5.0, 0.0]];
        let rig = Rig::orthographic([1.0, 1.0], [0.0, 0.0], lights).unwrap();
        let (depth, albedo, normals) = (vec![10.0; 12], vec![1.0; 6], [[0.0, 0.0, -1.0]; 6]);
        let short_mask = [true; 5];
        // A short mask (which predict used to index past), 2 channels, an albedo too short for 3.
        for bad in [
            surface(&depth, &albedo, 1, Some(&short_mask)),
            surface(&depth, &albedo, 2, None),
            surface(&depth, &albedo, 3, None),
        ] {
            let rendered = render(&rig, &bad).unwrap_err();
            assert_eq!(predict(&rig, &bad, &normals, false).unwrap_err(), rendered);
        }
        let good = surface(&depth, &albedo, 1, None);
        assert!(render(&rig, &good).is_ok());
        assert!(predict(&rig, &good, &normals, false).is_ok());
        let err = predict(&rig, &good, &normals[..5], false).unwrap_err();
        assert!(err.to_string().contains("normals has 5 values"), "{err}");
    }
}

#[cfg(test)]
mod forward_tests {
    use super::*;
    use crate::shadow::cast_shadows;

    const N: usize = 16;

    /// A bowl-and-bump surface at about 100 (smooth, every facet facing the camera).
    fn bumpy() -> Vec<f64> {
        (0..(N + 1) * (N + 1))
            .map(|v| {
                let (r, c) = ((v / (N + 1)) as f64 - 8.0, (v % (N + 1)) as f64 - 8.0);
                100.0 + 0.02 * (r * r - 0.5 * c * c) + 1.5 * (-(r * r + c * c) / 8.0).exp()
            })
            .collect()
    }

    fn rigs() -> Vec<Rig> {
        let lights = vec![
            Light::point([10.0, 5.0, 40.0]),
            Light::point([-20.0, 15.0, 20.0]),
            Light::Directional {
                direction: normalize([0.3, -0.2, -1.0]),
                intensity: [0.5, 1.0, 2.0],
            },
        ];
        let c = (N as f64 - 1.0) / 2.0;
        vec![
            Rig {
                camera: Camera::Orthographic {
                    pixel_size: [1.0, 1.0],
                    origin: [-8.0, -8.0],
                },
                lights: lights.clone(),
            },
            Rig {
                camera: Camera::Pinhole {
                    k: [[200.0, 0.0, c], [0.0, 200.0, c], [0.0, 0.0, 1.0]],
                    distortion: [0.0; 5],
                },
                lights,
            },
        ]
    }

    fn surface<'a>(depth: &'a [f64], albedo: &'a [f64], channels: usize) -> Surface<'a> {
        Surface {
            height: N,
            width: N,
            depth,
            albedo,
            channels,
            mask: None,
        }
    }

    #[test]
    fn the_glossy_model_at_eta_one_without_specular_is_lambertian() {
        let depth = bumpy();
        let zeros = vec![0.0; N * N];
        for channels in [1, 3] {
            let albedo: Vec<f64> = (0..N * N * channels)
                .map(|i| 0.5 + 0.01 * (i % 7) as f64)
                .collect();
            for rig in rigs() {
                let s = surface(&depth, &albedo, channels);
                let lambert = render(&rig, &s).unwrap();
                assert_eq!(
                    render_with(&rig, &s, &RenderOptions::default()).unwrap(),
                    lambert
                );
                let glossy = RenderOptions::default().with_specular(Some(Specular {
                    albedo: &zeros,
                    lobe: Lobe::new(0.3, 1.0),
                }));
                let images = render_with(&rig, &s, &glossy).unwrap();
                let peak = lambert.iter().fold(0.0f64, |m, v| m.max(*v));
                assert!(peak > 0.0);
                for (a, b) in images.iter().zip(&lambert) {
                    assert!((a - b).abs() <= 1e-12 * peak, "{a} vs {b}");
                }
            }
        }
    }

    #[test]
    fn specular_adds_light_near_the_mirror_direction_only() {
        // A plane at 100 under an overhead light at the image centre: the mirror direction is
        // the centre pixel; far from it the lobe adds (almost) nothing.
        let depth = vec![100.0; (N + 1) * (N + 1)];
        let (albedo, rho_s, zeros) = (vec![1.0; N * N], vec![1.0; N * N], vec![0.0; N * N]);
        let mut rig = rigs().remove(0);
        rig.lights = vec![Light::point([0.0, 0.0, 90.0])];
        let s = surface(&depth, &albedo, 1);
        let lobe = Lobe::new(0.05, 1.5);
        let matte = RenderOptions::default().with_specular(Some(Specular {
            albedo: &zeros,
            lobe,
        }));
        let shiny = RenderOptions::default().with_specular(Some(Specular {
            albedo: &rho_s,
            lobe,
        }));
        let (m, g) = (
            render_with(&rig, &s, &matte).unwrap(),
            render_with(&rig, &s, &shiny).unwrap(),
        );
        let centre = 8 * N + 8;
        assert!(
            g[centre] > 2.0 * m[centre],
            "{} vs {}",
            g[centre],
            m[centre]
        );
        assert!(g.iter().zip(&m).all(|(a, b)| a >= b));
        // At the corner (46 degrees off the mirror direction) it adds under 2 %.
        assert!(g[0] - m[0] < 0.02 * m[0], "{} vs {}", g[0], m[0]);
        // A bad lobe or map is refused.
        for (alpha, eta) in [(0.0, 1.5), (1.5, 1.5), (0.3, 0.9), (0.3, f64::NAN)] {
            let bad = RenderOptions::default().with_specular(Some(Specular {
                albedo: &rho_s,
                lobe: Lobe::new(alpha, eta),
            }));
            assert!(matches!(
                render_with(&rig, &s, &bad),
                Err(crate::Error::OutOfRange { .. })
            ));
        }
        let short = RenderOptions::default().with_specular(Some(Specular {
            albedo: &rho_s[1..],
            lobe,
        }));
        assert!(matches!(
            render_with(&rig, &s, &short),
            Err(crate::Error::Shape { .. })
        ));
    }

    #[test]
    fn cast_shadows_zero_exactly_the_shadowed_observations() {
        // A block on a plane under low lights.
        let depth: Vec<f64> = (0..(N + 1) * (N + 1))
            .map(|v| {
                let (r, c) = (v / (N + 1), v % (N + 1));
                if (6..=10).contains(&r) && (6..=10).contains(&c) {
                    96.0
                } else {
                    100.0
                }
            })
            .collect();
        let albedo = vec![1.0; N * N * 3];
        for mut rig in rigs() {
            rig.lights = vec![
                Light::point([60.0, 0.0, 60.0]),
                Light::point([0.0, -60.0, 70.0]),
                Light::point([0.0, 0.0, 0.0]),
            ];
            let s = surface(&depth, &albedo, 3);
            let plain = render(&rig, &s).unwrap();
            let shaded =
                render_with(&rig, &s, &RenderOptions::default().with_cast_shadows(true)).unwrap();
            let mask = cast_shadows(&rig, N, N, &depth, None, None).unwrap();
            assert!(mask.count() > 0);
            for k in 0..3 {
                for p in 0..N * N {
                    for ch in 0..3 {
                        let i = (k * N * N + p) * 3 + ch;
                        let expected = if mask.is_shadowed(p, k) {
                            0.0
                        } else {
                            plain[i]
                        };
                        assert_eq!(shaded[i], expected);
                    }
                }
            }
        }
    }

    #[test]
    fn masked_normals_are_the_vertex_grids_quad_normals_bit_for_bit() {
        // Band edges (heights around 16 and 32), one column, distortion, NaN depths and masks:
        // the banded normals against `quad_normal` of `vertices`' quads, NaN outside the mask.
        let cameras = [
            Camera::Orthographic {
                pixel_size: [0.7, 1.1],
                origin: [-3.0, 2.0],
            },
            Camera::Pinhole {
                k: [[90.0, 0.5, 20.0], [0.0, 95.0, 15.0], [0.0, 0.0, 1.0]],
                distortion: [-0.1, 0.02, 0.001, -0.002, 0.0],
            },
        ];
        for (seed, camera) in cameras.iter().enumerate() {
            for (height, width) in [(1, 1), (15, 1), (16, 7), (17, 40), (33, 29)] {
                let vw = width + 1;
                let depth: Vec<f64> = (0..(height + 1) * vw)
                    .map(|v| {
                        let (r, c) = ((v / vw) as f64, (v % vw) as f64);
                        if (v + seed) % 23 == 5 {
                            f64::NAN
                        } else {
                            10.0 + 0.3 * (0.7 * r + seed as f64).sin() + 0.2 * (1.3 * c).cos()
                        }
                    })
                    .collect();
                let mask: Vec<bool> = (0..height * width)
                    .map(|p| (p * 7 + seed) % 5 != 0)
                    .collect();
                let grid = crate::geometry::vertices(camera, height, width, &depth).unwrap();
                let all = mesh_normals(camera, height, width, &depth).unwrap();
                let masked =
                    mesh_normals_masked(camera, height, width, &depth, Some(&mask)).unwrap();
                for p in 0..height * width {
                    let want = quad_normal(&pixel_quad(&grid, width, p));
                    assert_eq!(
                        all[p].map(f64::to_bits),
                        want.map(f64::to_bits),
                        "{height}x{width} {p}"
                    );
                    if mask[p] {
                        assert_eq!(masked[p].map(f64::to_bits), want.map(f64::to_bits));
                    } else {
                        assert!(masked[p].iter().all(|x| x.is_nan()));
                    }
                }
                assert!(
                    mesh_normals_masked(camera, height, width, &depth, Some(&mask[1..])).is_err()
                );
            }
        }
    }
}
