//! The input of a reconstruction: images, rig, mask and initial depth, validated once.

use rayon::prelude::*;

use crate::error::{ensure_input, Error, Result};
use crate::grid::Grid;
use crate::local::Observations;
use crate::rig::Rig;

/// A borrowed stack of k grey images, laid out (k, H, W) row-major.
#[derive(Debug, Clone, Copy)]
pub struct ImageStack<'a> {
    /// Pixel values, `k * height * width` of them.
    pub data: &'a [f32],
    /// Number of images k.
    pub k: usize,
    /// Image height H.
    pub height: usize,
    /// Image width W.
    pub width: usize,
}

impl<'a> ImageStack<'a> {
    /// Wraps `data` as k images of H x W pixels; fails when the length does not match.
    pub fn new(data: &'a [f32], k: usize, height: usize, width: usize) -> Result<Self> {
        ensure_input(data.len() == k * height * width, || {
            format!(
                "image data has {} values, expected k * H * W = {k} * {height} * {width}",
                data.len()
            )
        })?;
        Ok(ImageStack {
            data,
            k,
            height,
            width,
        })
    }
}

/// The starting surface and the gauge.
#[derive(Debug, Clone, Copy)]
pub enum InitialDepth<'a> {
    /// Working distance: a fronto-parallel plane at this depth; every region's mean vertex depth
    /// stays at it.
    Distance(f64),
    /// An (H+1) x (W+1) vertex depth map, row-major; each region's mean vertex depth stays at the
    /// region's mean of this map.
    Map(&'a [f64]),
}

/// A validated reconstruction problem.
pub struct Problem<'a> {
    /// The rig.
    pub rig: &'a Rig,
    /// Mesh connectivity of the mask.
    pub grid: Grid,
    /// Per-facet observations (facet-major).
    pub obs: Observations,
    /// Initial depth of each unknown, already gauged.
    pub z0: Vec<f64>,
    /// Gauge value of each region (its mean vertex depth).
    pub gauge: Vec<f64>,
    /// Number of negative observations inside the mask (treated as unlit).
    pub negative_observations: usize,
}

impl<'a> Problem<'a> {
    /// Validates the input and prepares the per-facet observations.
    pub fn new(
        images: ImageStack<'_>,
        rig: &'a Rig,
        mask: Option<&[bool]>,
        depth: InitialDepth<'_>,
    ) -> Result<Problem<'a>> {
        rig.validate()?;
        ensure_input(images.k == rig.n_lights(), || {
            format!(
                "{} images were given for {} lights: there must be one image per light",
                images.k,
                rig.n_lights()
            )
        })?;
        if let Some(i) = images.data.iter().position(|v| !v.is_finite()) {
            let plane = images.height * images.width;
            return Err(Error::Input(format!(
                "image {} has a non-finite value (NaN or inf) at row {}, column {}",
                i / plane,
                (i % plane) / images.width,
                i % images.width
            )));
        }
        let grid = Grid::new(images.height, images.width, mask)?;
        let (z0, gauge) = initial_depth(&grid, depth)?;
        let min_depth = z0.iter().copied().fold(f64::INFINITY, f64::min);
        rig.check_lights_in_front(min_depth)?;
        let obs = gather_observations(&grid, &images);
        let negative_observations = obs.values.par_iter().filter(|v| **v < 0.0).count();
        Ok(Problem {
            rig,
            grid,
            obs,
            z0,
            gauge,
            negative_observations,
        })
    }
}

fn initial_depth(grid: &Grid, depth: InitialDepth<'_>) -> Result<(Vec<f64>, Vec<f64>)> {
    match depth {
        InitialDepth::Distance(d) => {
            ensure_input(d.is_finite(), || {
                format!("the working distance must be finite, got {d}")
            })?;
            Ok((vec![d; grid.n_unknowns()], vec![d; grid.n_regions]))
        }
        InitialDepth::Map(map) => {
            let (h, w) = (grid.height + 1, grid.width + 1);
            ensure_input(map.len() == h * w, || {
                format!(
                    "the initial depth map has {} values; it must have one per vertex, \
                     (H+1) x (W+1) = {h} x {w}",
                    map.len()
                )
            })?;
            let z0 = grid.gather_vertices(map);
            if let Some(u) = z0.iter().position(|z| !z.is_finite()) {
                let v = grid.active[u];
                return Err(Error::Input(format!(
                    "the initial depth map is not finite at vertex (row {}, column {}) used by the mask",
                    v / w,
                    v % w
                )));
            }
            let gauge = grid.region_means(&z0);
            Ok((z0, gauge))
        }
    }
}

/// Transposes the masked pixels of a (k, H, W) stack to facet-major order.
fn gather_observations(grid: &Grid, images: &ImageStack<'_>) -> Observations {
    let k = images.k;
    let plane = images.height * images.width;
    let mut values = vec![0.0f32; grid.n_facets() * k];
    values
        .par_chunks_mut(k)
        .zip(grid.facets.par_iter())
        .for_each(|(out, &p)| {
            for (i, o) in out.iter_mut().enumerate() {
                *o = images.data[i * plane + p];
            }
        });
    Observations { k, values }
}
