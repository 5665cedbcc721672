//! Rendering by the image model, and geometry of a depth map (vertices, mesh normals).
//!
//! A facet with corners `q` (vertices at pixel corners) has centre `c = mean(q)` and mesh normal
//! `n = normalize((q10 - q01) x (q11 - q00))`; its image under light k is
//! `I_k = rho * max(0, n . (p_k - c)) / |p_k - c|^3` (attached shadows clipped at 0).

use rayon::prelude::*;

use crate::error::{ensure_input, Result};
use crate::grid::{dot, quad_centre, quad_normal, sub};
use crate::rig::{Camera, Rig};

/// The 4 corners of pixel (r, c) of an (H+1) x (W+1) vertex depth map.
#[inline]
fn pixel_quad(camera: &Camera, width: usize, depth: &[f64], r: usize, c: usize) -> [[f64; 3]; 4] {
    let vw = width + 1;
    let rc = [(r, c), (r, c + 1), (r + 1, c), (r + 1, c + 1)];
    rc.map(|(rr, cc)| {
        let [x, y] = camera.vertex_xy(rr, cc);
        [x, y, depth[rr * vw + cc]]
    })
}

fn check_depth(height: usize, width: usize, depth: &[f64]) -> Result<()> {
    ensure_input(depth.len() == (height + 1) * (width + 1), || {
        format!(
            "depth map has {} values, expected (H+1) x (W+1) = {} x {}",
            depth.len(),
            height + 1,
            width + 1
        )
    })
}

/// Mesh normal of every pixel of an (H+1) x (W+1) depth map (NaN where a corner is NaN).
pub fn mesh_normals(
    camera: &Camera,
    height: usize,
    width: usize,
    depth: &[f64],
) -> Result<Vec<[f64; 3]>> {
    check_depth(height, width, depth)?;
    Ok((0..height * width)
        .into_par_iter()
        .map(|p| quad_normal(&pixel_quad(camera, width, depth, p / width, p % width)))
        .collect())
}

/// 3-D position of every vertex of an (H+1) x (W+1) depth map.
pub fn vertices(
    camera: &Camera,
    height: usize,
    width: usize,
    depth: &[f64],
) -> Result<Vec<[f64; 3]>> {
    check_depth(height, width, depth)?;
    let vw = width + 1;
    Ok(depth
        .iter()
        .enumerate()
        .map(|(v, &z)| {
            let [x, y] = camera.vertex_xy(v / vw, v % vw);
            [x, y, z]
        })
        .collect())
}

/// Renders the k images (k, H, W) of the surface `depth` ((H+1) x (W+1)) with per-pixel
/// `albedo` (H x W). Pixels outside `mask`, or with a NaN corner, are 0.
pub fn render(
    rig: &Rig,
    height: usize,
    width: usize,
    depth: &[f64],
    albedo: &[f64],
    mask: Option<&[bool]>,
) -> Result<Vec<f64>> {
    check_depth(height, width, depth)?;
    let plane = height * width;
    ensure_input(albedo.len() == plane, || {
        format!(
            "albedo has {} values, expected H x W = {plane}",
            albedo.len()
        )
    })?;
    if let Some(m) = mask {
        ensure_input(m.len() == plane, || {
            format!("mask has {} values, expected H x W = {plane}", m.len())
        })?;
    }
    let k = rig.n_lights();
    let mut out = vec![0.0; k * plane];
    // Pixel-major work, written image-major.
    let per_pixel: Vec<Vec<f64>> = (0..plane)
        .into_par_iter()
        .map(|p| {
            if mask.is_some_and(|m| !m[p]) {
                return Vec::new();
            }
            let q = pixel_quad(&rig.camera, width, depth, p / width, p % width);
            let n = quad_normal(&q);
            let c = quad_centre(&q);
            if !(n.iter().all(|v| v.is_finite())) {
                return Vec::new();
            }
            rig.lights
                .iter()
                .map(|l| {
                    let a = sub(*l, c);
                    let d2 = dot(a, a);
                    albedo[p] * dot(n, a).max(0.0) / (d2 * d2.sqrt())
                })
                .collect()
        })
        .collect();
    for (p, values) in per_pixel.iter().enumerate() {
        for (i, v) in values.iter().enumerate() {
            out[i * plane + p] = *v;
        }
    }
    Ok(out)
}
