//! The input of a reconstruction: images, rig, mask and initial depth, validated once.

use rayon::prelude::*;

use crate::error::{ensure_range, ensure_shape, ensure_usable, Error, Result};
use crate::geometry::Geometry;
use crate::grid::Grid;
pub use crate::local::{u16_value, Samples, U16_SCALE};
use crate::local::{usable, FitSettings, Observations, Stored};
use crate::memory::try_vec;
use crate::options::Options;
use crate::rig::Rig;
use crate::system::Prior;
use crate::vec3::{add, sub};

/// A borrowed stack of k images, laid out (k, H, W, C) row-major with C = 1 (grey) or 3 (RGB).
/// NaN marks a missing observation (left out of the fits); infinities are errors.
#[derive(Debug, Clone, Copy)]
pub struct ImageStack<'a> {
    /// Pixel values, `k * height * width * channels` of them.
    pub data: Samples<'a>,
    /// Number of images k.
    pub k: usize,
    /// Image height H.
    pub height: usize,
    /// Image width W.
    pub width: usize,
    /// Channels per pixel C (1 or 3).
    pub channels: usize,
}

impl<'a> ImageStack<'a> {
    /// Wraps `data` as k grey images of H x W pixels; fails when the length does not match.
    pub fn new(data: &'a [f32], k: usize, height: usize, width: usize) -> Result<Self> {
        Self::with_channels(data, k, height, width, 1)
    }

    /// Wraps `data` as k images of H x W pixels with `channels` (1 or 3) values each.
    pub fn with_channels(
        data: &'a [f32],
        k: usize,
        height: usize,
        width: usize,
        channels: usize,
    ) -> Result<Self> {
        Self::from_samples(Samples::F32(data), k, height, width, channels)
    }

    /// Wraps 16-bit `data` (read as `v / 65535`, see [`u16_value`]) as k images of H x W pixels
    /// with `channels` (1 or 3) values each, without a copy or a conversion.
    pub fn with_channels_u16(
        data: &'a [u16],
        k: usize,
        height: usize,
        width: usize,
        channels: usize,
    ) -> Result<Self> {
        Self::from_samples(Samples::U16(data), k, height, width, channels)
    }

    /// Wraps `data` as k images of H x W pixels with `channels` (1 or 3) values each.
    pub fn from_samples(
        data: Samples<'a>,
        k: usize,
        height: usize,
        width: usize,
        channels: usize,
    ) -> Result<Self> {
        ensure_range(
            channels == 1 || channels == 3,
            "channels",
            channels as f64,
            || format!("images must have 1 (grey) or 3 (RGB) channels, got {channels}"),
        )?;
        let expected = k
            .checked_mul(height)
            .and_then(|n| n.checked_mul(width))
            .and_then(|n| n.checked_mul(channels));
        ensure_shape("images", expected.unwrap_or(usize::MAX), data.len(), || {
            format!(
                "image data has {} values, expected k * H * W * C = {k} * {height} * {width} * {channels}",
                data.len()
            )
        })?;
        Ok(ImageStack {
            data,
            k,
            height,
            width,
            channels,
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

/// A validated reconstruction problem. It borrows the rig and the image stack (no copy of the
/// images is made).
pub struct Problem<'a> {
    /// The rig.
    pub(crate) rig: &'a Rig,
    /// Mesh connectivity of the mask.
    pub(crate) grid: Grid,
    /// Vertex positions and unknowns (depth or log-depth) under the rig's camera.
    pub(crate) geometry: Geometry,
    /// Per-facet observations.
    pub(crate) obs: Observations<'a>,
    /// Initial unknown of each active vertex (depth, or log-depth for a pinhole camera).
    pub(crate) u0: Start,
    /// Gauge of each region: the mean of its unknowns (arithmetic mean depth, or log of the
    /// geometric mean depth).
    pub(crate) gauge: Vec<f64>,
    /// Number of negative observations inside the mask (treated as unlit).
    pub(crate) negative_observations: usize,
    /// Optional depth prior fused in the global step.
    pub(crate) prior: Option<Prior>,
    /// Cancellation token checked while the problem is solved (never cancelled by default).
    pub(crate) cancel: crate::Cancel,
}

impl<'a> Problem<'a> {
    /// The rig.
    pub fn rig(&self) -> &'a Rig {
        self.rig
    }

    /// Image height H and width W.
    pub fn shape(&self) -> (usize, usize) {
        (self.grid.height, self.grid.width)
    }

    /// Number of negative observations inside the mask (treated as unlit).
    pub fn negative_observations(&self) -> usize {
        self.negative_observations
    }

    /// The cancellation token checked while the problem is solved.
    pub fn cancel(&self) -> &crate::Cancel {
        &self.cancel
    }

    /// Refuses with [`crate::Error::Memory`] when reconstructing this problem with `options`
    /// would need more memory than `options.max_memory` allows (see [`crate::check_memory`]).
    pub fn check_memory(&self, options: &Options) -> Result<()> {
        crate::options::check_reconstruction(
            self.grid.height,
            self.grid.width,
            self.grid.facets.len(),
            self.obs.channels,
            self.obs.k,
            options,
        )
    }

    /// Validates the input and prepares the per-facet observations.
    pub fn new(
        images: ImageStack<'a>,
        rig: &'a Rig,
        mask: Option<&[bool]>,
        depth: InitialDepth<'_>,
    ) -> Result<Problem<'a>> {
        Problem::with_cancel(images, rig, mask, depth, crate::Cancel::default())
    }

    /// As [`Problem::new`], checking `cancel` between the stages of the preparation; the
    /// problem keeps it (see [`Problem::cancel`]).
    pub fn with_cancel(
        images: ImageStack<'a>,
        rig: &'a Rig,
        mask: Option<&[bool]>,
        depth: InitialDepth<'_>,
        cancel: crate::Cancel,
    ) -> Result<Problem<'a>> {
        rig.validate()?;
        ensure_shape("images", rig.n_lights(), images.k, || {
            format!(
                "{} images were given for {} lights: there must be one image per light",
                images.k,
                rig.n_lights()
            )
        })?;
        const CHUNK: usize = 1 << 16;
        // 16-bit samples are always finite.
        let infinite = match images.data {
            Samples::F32(data) => data
                .par_chunks(CHUNK)
                .position_first(|c| c.iter().any(|v| v.is_infinite()))
                .map(|chunk| {
                    let start = chunk * CHUNK;
                    let within = data[start..].iter().position(|v| v.is_infinite());
                    start + within.unwrap_or(0)
                }),
            Samples::U16(_) => None,
        };
        if let Some(i) = infinite {
            let plane = images.height * images.width * images.channels;
            let pixel = (i % plane) / images.channels;
            return Err(Error::NonFinite {
                what: "images",
                index: i,
                message: format!(
                    "image {} has an infinite value at row {}, column {}",
                    i / plane,
                    pixel / images.width,
                    pixel % images.width
                ),
            });
        }
        cancel.check()?;
        let grid = Grid::new(images.height, images.width, mask)?;
        cancel.check()?;
        let geometry = Geometry::new(&rig.camera, &grid)?;
        geometry.check_rays(&grid, |_| true)?;
        cancel.check()?;
        let (u0, gauge) = initial_unknowns(&grid, &geometry, depth)?;
        let min_depth = match &u0 {
            Start::Constant { value, .. } => geometry.depth(*value),
            Start::Values(u0) => u0
                .iter()
                .map(|&u| geometry.depth(u))
                .fold(f64::INFINITY, f64::min),
        };
        rig.check_lights_in_front(min_depth)?;
        let obs = Observations::from_samples(
            images.data,
            images.k,
            images.height * images.width,
            images.channels,
        );
        cancel.check()?;
        let negative_observations = count_negative(&grid, &obs);
        cancel.check()?;
        Ok(Problem {
            rig,
            grid,
            geometry,
            obs,
            u0,
            gauge,
            negative_observations,
            prior: None,
            cancel,
        })
    }
}

impl Problem<'_> {
    /// Adds a per-vertex prior depth map ((H+1) x (W+1); NaN where there is none) with `weight`
    /// relative to the facet terms: the global step's energy gains
    /// `weight * sum_v (u_v - prior_v)^2` over the vertices whose prior is finite, with `u` the
    /// depth (for a pinhole camera the log-depth, and the prior's log). A region the prior
    /// covers keeps no fixed gauge.
    pub fn set_prior(&mut self, map: &[f64], weight: f64) -> Result<()> {
        let (h, w) = (self.grid.height + 1, self.grid.width + 1);
        ensure_shape("depth prior", h * w, map.len(), || {
            format!(
                "the depth prior has {} values; it must have (W+1) x (H+1) = {w} x {h}",
                map.len()
            )
        })?;
        ensure_range(
            weight.is_finite() && weight > 0.0,
            "prior_weight",
            weight,
            || {
                format!(
                    "the prior weight must be positive and finite, got {}",
                    crate::error::g6(weight)
                )
            },
        )?;
        let mut values: Vec<f64> = self.grid.gather_vertices(map)?;
        for z in values.iter_mut() {
            *z = if z.is_finite() && *z > 0.0 {
                self.geometry.unknown(*z)
            } else {
                f64::NAN
            };
        }
        ensure_usable(values.iter().any(|v| v.is_finite()), || {
            "the depth prior has no finite positive value inside the mask".to_string()
        })?;
        self.prior = Some(Prior { values, weight });
        Ok(())
    }
}

/// The starting unknowns of a problem: one value for all of them (a working distance; computed
/// where they are read, so that the problem does not hold 8 bytes an unknown through the run),
/// or one each (a depth map, a coarse level's).
#[derive(Debug, Clone)]
pub(crate) enum Start {
    /// Every one of the `len` unknowns starts at `value`.
    Constant { value: f64, len: usize },
    /// Each unknown's own.
    Values(Vec<f64>),
}

impl Start {
    /// The starting unknowns (allocated for a constant start, or [`crate::Error::Memory`]).
    pub(crate) fn values(&self) -> Result<std::borrow::Cow<'_, [f64]>> {
        Ok(match self {
            Start::Constant { .. } => std::borrow::Cow::Owned(self.to_vec("the starting depths")?),
            Start::Values(v) => std::borrow::Cow::Borrowed(v),
        })
    }

    /// The starting unknown of unknown `i`.
    pub(crate) fn at(&self, i: usize) -> f64 {
        match self {
            &Start::Constant { value, .. } => value,
            Start::Values(v) => v[i],
        }
    }

    /// A copy of the starting unknowns (`what` names it in [`crate::Error::Memory`]).
    pub(crate) fn to_vec(&self, what: &str) -> Result<Vec<f64>> {
        match self {
            &Start::Constant { value, len } => try_vec(len, value, what),
            Start::Values(v) => crate::memory::try_copy(v, what),
        }
    }
}

fn initial_unknowns(
    grid: &Grid,
    geometry: &Geometry,
    depth: InitialDepth<'_>,
) -> Result<(Start, Vec<f64>)> {
    let positive = geometry.is_perspective();
    // Depths beyond the rig's bounds overflow (or, for a pinhole camera, collapse) the mesh.
    let valid = |z: f64| {
        z.abs() <= crate::rig::MAX_MAGNITUDE && (!positive || z >= crate::rig::MIN_MAGNITUDE)
    };
    match depth {
        InitialDepth::Distance(d) => {
            ensure_range(valid(d), "working distance", d, || {
                format!(
                    "the working distance must be finite (and positive for a pinhole camera) and \
                     within [1e-12, 1e12] in magnitude, got {}",
                    crate::error::g6(d)
                )
            })?;
            let u = geometry.unknown(d);
            let len = grid.n_unknowns();
            Ok((Start::Constant { value: u, len }, vec![u; grid.n_regions]))
        }
        InitialDepth::Map(map) => {
            let (h, w) = (grid.height + 1, grid.width + 1);
            ensure_shape("initial depth map", h * w, map.len(), || {
                format!(
                    "the initial depth map has {} values; it must have one per vertex, \
                     (W+1) x (H+1) = {w} x {h}",
                    map.len()
                )
            })?;
            let z0 = grid.gather_vertices(map)?;
            if let Some(i) = z0.iter().position(|z| !valid(*z)) {
                let v = grid.active[i] as usize;
                return Err(Error::NonFinite {
                    what: "initial depth map",
                    index: v,
                    message: format!(
                    "the initial depth map is {} at vertex (row {}, column {}) used by the mask",
                    if !z0[i].is_finite() {
                        "not finite"
                    } else if z0[i].abs() > crate::rig::MAX_MAGNITUDE {
                        "beyond 1e12 in magnitude"
                    } else {
                        "not positive (at least 1e-12)"
                    },
                    v / w,
                    v % w
                ),
                });
            }
            let mut u0 = z0;
            for z in u0.iter_mut() {
                *z = geometry.unknown(*z);
            }
            let gauge = grid.region_means(&u0);
            Ok((Start::Values(u0), gauge))
        }
    }
}

/// Number of negative observations of the masked facets.
/// Fails when the lights, seen from the starting surface's centroid, do not span three
/// directions (collinear, coincident or very distant lights): then no pixel's normal is
/// determined. The test is on the Gram matrix `sum_k l_k l_k^T` of the unit light directions:
/// its smallest eigenvalue must exceed 1e-6 of its largest. (Not part of [`Problem::new`]: with
/// an estimated distance the starting plane is arbitrary, so the search checks its result.)
pub(crate) fn check_light_geometry(rig: &Rig, geometry: &Geometry, u0: &[f64]) -> Result<()> {
    let sum = u0
        .par_iter()
        .enumerate()
        .map(|(i, &u)| geometry.position(i, u))
        .reduce(|| [0.0; 3], add);
    let n = u0.len().max(1) as f64;
    let centroid = sum.map(|v| v / n);
    let mut gram = nalgebra::Matrix3::zeros();
    for light in &rig.lights {
        let d = match *light {
            crate::rig::Light::Point { position, .. } => sub(position, centroid),
            crate::rig::Light::Directional { direction, .. } => direction,
        };
        let v = nalgebra::Vector3::from(d);
        let norm = v.norm();
        if norm > 0.0 && norm.is_finite() {
            let l = v / norm;
            gram += l * l.transpose();
        }
    }
    let mut eig: Vec<f64> = gram.symmetric_eigenvalues().iter().copied().collect();
    eig.sort_by(|a, b| b.total_cmp(a));
    if eig[2].is_nan() || eig[2] <= 1e-6 * eig[0] {
        let spread: Vec<String> = eig
            .iter()
            .map(|e| format!("{:.3e}", e.max(0.0).sqrt()))
            .collect();
        return Err(Error::Rig(format!(
            "the lights cannot determine the normals: seen from the object (centroid at \
             ({}, {}, {})) their directions do not span three dimensions (singular \
             values {}); collinear, coincident or very distant lights? Photometric stereo needs \
             lights in at least three directions that do not lie in one plane",
            crate::error::g6(centroid[0]),
            crate::error::g6(centroid[1]),
            crate::error::g6(centroid[2]),
            spread.join(", ")
        )));
    }
    Ok(())
}

/// The number of negative samples of the masked pixels (the warning that dark-frame
/// subtraction went below zero).
///
/// A 16-bit stack has none (its samples read as `v / 65535`), so it is not read at all. A float
/// stack is read image by image over chunks of the masked pixels (each image's values of a
/// chunk lie in one stretch of memory), not by gathering the `k` values of each facet from `k`
/// places: the same count (the test `negative_observations_are_counted_per_masked_sample`). At
/// 12 MP x 16 the gather was a pass of 0.2-0.3 s of CPU over the whole 16-bit stack to count
/// nothing.
fn count_negative(grid: &Grid, obs: &Observations<'_>) -> usize {
    const CHUNK: usize = 1 << 14;
    let Stored::F32(data) = &obs.data else {
        return 0;
    };
    let (c, plane) = (obs.channels, obs.plane);
    grid.facets
        .par_chunks(CHUNK)
        .map(|pixels| {
            let mut n = 0;
            for image in data.chunks_exact(plane) {
                for &p in pixels {
                    let p = p as usize * c;
                    n += image[p..p + c].iter().filter(|v| **v < 0.0).count();
                }
            }
            n
        })
        .sum()
}

/// Fails when no masked pixel has 3 usable observations: nothing could be fitted, and the
/// result would be the starting surface.
pub(crate) fn check_fittable(problem: &Problem<'_>, settings: &FitSettings) -> Result<()> {
    use rayon::prelude::*;
    let obs = &problem.obs;
    let fittable = problem.grid.facets.par_iter().any(|&pixel| {
        (0..obs.k)
            .filter(|&i| usable(&obs.at(i, pixel as usize), settings))
            .take(3)
            .count()
            >= 3
    });
    if fittable {
        return Ok(());
    }
    Err(Error::Unusable(format!(
        "no masked pixel has 3 or more usable observations (above dark = {} and below saturation = \
         {}, not NaN, not left out by valid): the images are black, saturated or excluded, so \
         nothing can be reconstructed",
        crate::error::g6(settings.dark),
        crate::error::g6(settings.saturation)
    )))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::local::Observations;

    #[test]
    fn a_16_bit_stack_reads_as_the_float_stack_of_load_stack() {
        // k = 3 images of 2 x 3 pixels with 3 channels; values across the whole 16-bit range.
        let (k, h, w, c) = (3, 2, 3, 3);
        let raw: Vec<u16> = (0..k * h * w * c)
            .map(|i| ((i * 7919) % 65536) as u16)
            .chain([0, 1, 65534, 65535])
            .take(k * h * w * c)
            .collect();
        // nplps.io.load_stack: float32(v) / float32(65535), correctly rounded.
        let float: Vec<f32> = raw.iter().map(|&v| v as f32 / 65535.0).collect();
        assert_eq!(u16_value(65535), 1.0);
        assert_eq!(u16_value(0), 0.0);
        let a = ImageStack::with_channels_u16(&raw, k, h, w, c).unwrap();
        let b = ImageStack::with_channels(&float, k, h, w, c).unwrap();
        assert_eq!(a.data.bytes_per_value(), 2);
        assert_eq!(b.data.bytes_per_value(), 4);
        for i in 0..raw.len() {
            assert_eq!(a.data.get(i).to_bits(), b.data.get(i).to_bits());
        }
        let (oa, ob) = (
            Observations::from_samples(a.data, k, h * w, c),
            Observations::from_samples(b.data, k, h * w, c),
        );
        let (mut ba, mut bb) = (vec![0.0f32; k * c], vec![0.0f32; k * c]);
        for p in 0..h * w {
            assert_eq!(oa.facet(p, &mut ba), ob.facet(p, &mut bb));
            for i in 0..k {
                assert_eq!(&*oa.at(i, p), &*ob.at(i, p));
            }
        }
        // Grey: the interleaved gather of the vectorized local step.
        let grey_raw = &raw[..k * h * w];
        let grey: Vec<f32> = grey_raw.iter().map(|&v| u16_value(v)).collect();
        let (ga, gb) = (
            Observations::from_samples(Samples::U16(grey_raw), k, h * w, 1),
            Observations::from_samples(Samples::F32(&grey), k, h * w, 1),
        );
        let pixels = [0, 2, 3, 5];
        let (mut ia, mut ib) = (vec![[0.0f32; 4]; k], vec![[0.0f32; 4]; k]);
        assert!(ga.gather_lanes(&pixels, &mut ia) && gb.gather_lanes(&pixels, &mut ib));
        assert_eq!(ia, ib);
        // A wrong length is a shape error, as for float stacks.
        assert!(ImageStack::with_channels_u16(&raw[1..], k, h, w, c).is_err());
    }

    /// The count read image by image is the per-facet count of the negative samples of the
    /// masked pixels (grey and colour, with and without a mask, NaN not counted, more pixels than
    /// a chunk); a 16-bit stack has none.
    #[test]
    fn negative_observations_are_counted_per_masked_sample() {
        let (k, h, w) = (5, 150, 130);
        let mut next = crate::multigrid::tests::lcg(0x9e37_79b9_7f4a_7c15);
        let holes: Vec<bool> = (0..h * w).map(|_| next() > 0.3).collect();
        for c in [1, 3] {
            let data: Vec<f32> = (0..k * h * w * c)
                .map(|_| match next() {
                    x if x < 0.1 => -x as f32,
                    x if x < 0.15 => f32::NAN,
                    x => x as f32,
                })
                .collect();
            for mask in [None, Some(&holes[..])] {
                let grid = Grid::new(h, w, mask).unwrap();
                let obs = Observations::from_samples(Samples::F32(&data), k, h * w, c);
                let mut buf = vec![0.0f32; k * c];
                let expected: usize = grid
                    .facets
                    .iter()
                    .map(|&p| {
                        let values = obs.facet(p as usize, &mut buf);
                        values.iter().filter(|v| **v < 0.0).count()
                    })
                    .sum();
                assert!(expected > 1000);
                assert_eq!(count_negative(&grid, &obs), expected);
            }
        }
        let raw = vec![0u16; k * h * w];
        let grid = Grid::new(h, w, None).unwrap();
        let obs = Observations::from_samples(Samples::U16(&raw), k, h * w, 1);
        assert_eq!(count_negative(&grid, &obs), 0);
    }
}
