//! Rendering by the image model, and geometry of a depth map (vertices, mesh normals).
//!
//! A facet with corners `q` (vertices at pixel corners) has centre `c = mean(q)` and mesh normal
//! `n = normalize((q10 - q01) x (q11 - q00))`; its image under light k in channel `ch` is
//! `I = rho_ch * Phi_{k,ch} * max(0, n . beta_k(c))` (attached shadows clipped at 0; see
//! [`Light::beta`]). Grey images use the mean of each light's channels.

use rayon::prelude::*;

use crate::error::{ensure_range, ensure_shape, Result};
use crate::geometry::{quad_centre, quad_normal, Geometry};
use crate::grid::Grid;
use crate::light::{channel_intensity, Light};
use crate::rig::{Camera, Rig};
use crate::vec3::{normalize, sub};

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
    /// the vertex positions of the depth map (see [`positions`]).
    fn vertices(&self, camera: &Camera) -> Result<Vec<[f64; 3]>> {
        let (plane, channels) = (self.height * self.width, self.channels);
        let v = positions(camera, self.height, self.width, self.depth)?;
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
        if let Some(m) = self.mask {
            ensure_shape("mask", plane, m.len(), || {
                format!("mask has {} values, expected H x W = {plane}", m.len())
            })?;
        }
        Ok(v)
    }
}

/// Vertex positions of a full (H+1) x (W+1) depth map.
fn positions(camera: &Camera, height: usize, width: usize, depth: &[f64]) -> Result<Vec<[f64; 3]>> {
    ensure_shape("depth map", (height + 1) * (width + 1), depth.len(), || {
        format!(
            "depth map has {} values, expected (W+1) x (H+1) = {} x {}",
            depth.len(),
            width + 1,
            height + 1
        )
    })?;
    crate::memory::check(
        || format!("the vertices of a depth map of {width} x {height} pixels"),
        // Grid, geometry and positions: about 100 bytes per vertex.
        100.0 * depth.len() as f64,
        None,
    )?;
    let grid = Grid::new(height, width, None)?;
    let geometry = Geometry::new(camera, &grid)?;
    // Vertices of unknown (NaN) depth need no ray: outside a reconstruction's mask, say.
    geometry.check_rays(&grid, |v| depth[v].is_finite())?;
    crate::memory::try_collect(
        depth
            .iter()
            .enumerate()
            .map(|(v, &z)| geometry.position_at_depth(v, z)),
        "the vertex positions",
    )
}

/// The 4 corners of pixel `p` from the vertex positions.
#[inline]
fn pixel_quad(vertices: &[[f64; 3]], width: usize, p: usize) -> [[f64; 3]; 4] {
    let v = (p / width) * (width + 1) + p % width;
    [
        vertices[v],
        vertices[v + 1],
        vertices[v + width + 1],
        vertices[v + width + 2],
    ]
}

/// 3-D position of every vertex of an (H+1) x (W+1) depth map.
pub fn vertices(
    camera: &Camera,
    height: usize,
    width: usize,
    depth: &[f64],
) -> Result<Vec<[f64; 3]>> {
    positions(camera, height, width, depth)
}

/// Mesh normal of every pixel of an (H+1) x (W+1) depth map (NaN where a corner is NaN).
pub fn mesh_normals(
    camera: &Camera,
    height: usize,
    width: usize,
    depth: &[f64],
) -> Result<Vec<[f64; 3]>> {
    let v = positions(camera, height, width, depth)?;
    crate::memory::try_par_collect(
        (0..height * width)
            .into_par_iter()
            .map(|p| quad_normal(&pixel_quad(&v, width, p))),
        "the mesh normals",
    )
}

/// Renders the k images (k, H, W, C) of the surface `depth` ((H+1) x (W+1)) with per-pixel
/// `albedo` (H x W x C, C = 1 or 3). Pixels outside `mask` are 0; pixels inside it with a
/// non-finite corner (an unknown depth) are NaN in every image, so that an unknown surface does
/// not pass for a shadow.
pub fn render(rig: &Rig, surface: &Surface<'_>) -> Result<Vec<f64>> {
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
    let mut images = shade_images(&rig.lights, plane, channels, albedo, |p| {
        if mask.is_some_and(|m| !m[p]) {
            return None;
        }
        let q = pixel_quad(&v, width, p);
        Some((quad_normal(&q), quad_centre(&q)))
    })?;
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

/// The k images (k, H, W, C) of pixels shaded by `lights`: `surface(p)` gives the normal and the
/// surface point of pixel p (None: 0), `albedo` its albedo per channel. Pixels with a non-finite
/// normal, point or albedo are 0. Refused with [`crate::Error::Memory`] when the images (and the
/// per-pixel geometry) would not fit in the memory available.
fn shade_images(
    lights: &[Light],
    plane: usize,
    channels: usize,
    albedo: &[f64],
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
            surface(p).filter(|(n, c)| n.iter().chain(c).chain(rho).all(|x| x.is_finite()))
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
                    shade(
                        light,
                        n,
                        c,
                        rho,
                        &mut image[p * channels..(p + 1) * channels],
                    );
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
    shade_images(&lights, plane, channels, albedo, |p| {
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
