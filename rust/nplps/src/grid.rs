//! The mesh: one quad facet per masked pixel, vertices at pixel corners.
//!
//! Facet (r, c) is pixel (r, c). Its corners, always in this order, are
//! `00 = (r, c)`, `01 = (r, c+1)`, `10 = (r+1, c)`, `11 = (r+1, c+1)` on the
//! (H+1) x (W+1) vertex grid. A vertex is *active* (an unknown of the global step) when a masked
//! facet uses it. Regions are the connected components of facets that share a vertex
//! (8-connectivity of pixels); each region's depth offset is fixed by the gauge.

use rayon::prelude::*;

use crate::error::{ensure_shape, ensure_usable, Result};
use crate::memory::{try_collect, try_par_collect, try_vec, try_with_capacity};

/// Sentinel for a vertex that no masked facet uses.
pub const INACTIVE: u32 = u32::MAX;

/// Connectivity of the masked mesh.
#[derive(Debug, Clone)]
pub struct Grid {
    /// Image height H (facet rows).
    pub height: usize,
    /// Image width W (facet columns).
    pub width: usize,
    /// Pixel index `r * W + c` of each masked facet, in row-major order (`u32`: 4 bytes a
    /// facet; a grid has fewer than 2^32 vertices).
    pub facets: Vec<u32>,
    /// For each grid vertex `r * (W+1) + c`: its unknown index, or [`INACTIVE`].
    pub vertex_unknown: Vec<u32>,
    /// Grid vertex index of each unknown (row-major, increasing; `u32`, as `facets`).
    pub active: Vec<u32>,
    /// Region label of each unknown, 0..n_regions, numbered by first appearance.
    pub region_of_unknown: Vec<u32>,
    /// Number of regions.
    pub n_regions: usize,
    /// The lowest-index unknown of each region (pinned in the global step).
    pub pins: Vec<u32>,
    /// For each pixel `r * W + c`: its facet index, or [`INACTIVE`] outside the mask; empty
    /// when every pixel is a facet (then facet `p` is pixel `p`: 4 bytes a pixel less). Read
    /// through [`Grid::facet_of_pixel`].
    facet_index: Vec<u32>,
}

impl Grid {
    /// Builds the mesh of a mask of (H, W) pixels (`None`: every pixel). Fails on an empty mask or
    /// a mask of the wrong length.
    pub fn new(height: usize, width: usize, mask: Option<&[bool]>) -> Result<Grid> {
        ensure_usable(height > 0 && width > 0, || {
            format!("images must not be empty, got {width} x {height} pixels")
        })?;
        if let Some(m) = mask {
            ensure_shape("mask", height * width, m.len(), || {
                format!(
                    "mask has {} pixels, the images have {width} x {height} = {}",
                    m.len(),
                    height * width
                )
            })?;
        }
        // Vertex, pixel and unknown numbers are u32, with u32::MAX for none.
        ensure_usable(
            (height + 1)
                .checked_mul(width + 1)
                .is_some_and(|n| n < INACTIVE as usize),
            || {
                format!(
                    "images of {width} x {height} pixels have 2^32 or more mesh vertices: too large"
                )
            },
        )?;
        let masked_count = mask.map_or(height * width, |m| m.par_iter().filter(|&&b| b).count());
        let mut facets: Vec<u32> = try_with_capacity(masked_count, "the mesh's facets")?;
        facets.extend(
            (0..height * width)
                .filter(|&p| mask.is_none_or(|m| m[p]))
                .map(|p| p as u32),
        );
        ensure_usable(!facets.is_empty(), || {
            "mask is empty: no pixel is selected for reconstruction".to_string()
        })?;

        let vw = width + 1;
        let n_vertices = (height + 1) * vw;
        let corners = |p: usize| {
            let (r, c) = (p / width, p % width);
            let v = r * vw + c;
            [v, v + 1, v + vw, v + vw + 1]
        };
        // A vertex is used when one of its (up to 4) pixels is masked.
        let masked =
            |r: usize, c: usize| r < height && c < width && mask.is_none_or(|m| m[r * width + c]);
        let used: Vec<bool> = try_par_collect(
            (0..n_vertices).into_par_iter().map(|v| {
                let (r, c) = (v / vw, v % vw);
                let (ru, cl) = (r.wrapping_sub(1), c.wrapping_sub(1));
                masked(ru, cl) || masked(ru, c) || masked(r, cl) || masked(r, c)
            }),
            "the mesh's vertices",
        )?;
        let mut vertex_unknown = try_vec(n_vertices, INACTIVE, "the mesh's vertex numbers")?;
        let mut active = try_with_capacity(
            used.par_iter().filter(|&&u| u).count(),
            "the mesh's unknowns",
        )?;
        for (v, _) in used.iter().enumerate().filter(|(_, u)| **u) {
            vertex_unknown[v] = active.len() as u32;
            active.push(v as u32);
        }
        drop(used);

        let (region_of_unknown, n_regions) = if facets.len() == height * width {
            // Every pixel: one connected region.
            (try_vec(active.len(), 0, "the mesh's regions")?, 1)
        } else {
            label_regions(
                active.len(),
                facets
                    .iter()
                    .map(|&p| corners(p as usize).map(|v| vertex_unknown[v])),
            )?
        };
        let mut pins = vec![u32::MAX; n_regions];
        for (u, &reg) in region_of_unknown.iter().enumerate() {
            if pins[reg as usize] == u32::MAX {
                pins[reg as usize] = u as u32;
            }
        }
        let facet_index = if facets.len() == height * width {
            Vec::new()
        } else {
            let mut index = try_vec(height * width, INACTIVE, "the mesh's pixel numbers")?;
            for (f, &p) in facets.iter().enumerate() {
                index[p as usize] = f as u32;
            }
            index
        };
        Ok(Grid {
            height,
            width,
            facet_index,
            facets,
            vertex_unknown,
            active,
            region_of_unknown,
            n_regions,
            pins,
        })
    }

    /// The facet of pixel `p` (`r * W + c`), or [`INACTIVE`] outside the mask.
    #[inline]
    pub fn facet_of_pixel(&self, p: usize) -> u32 {
        match self.facet_index.is_empty() {
            true => p as u32,
            false => self.facet_index[p],
        }
    }

    /// Number of unknowns (active vertices).
    pub fn n_unknowns(&self) -> usize {
        self.active.len()
    }

    /// Number of masked facets.
    pub fn n_facets(&self) -> usize {
        self.facets.len()
    }

    /// The unknowns of the 4 corners of facet `f`, in the order 00, 01, 10, 11 (top-left,
    /// top-right, bottom-left, bottom-right): for its pixel `p = (r, c)` the vertices
    /// `v = r (W + 1) + c`, `v + 1`, `v + W + 1`, `v + W + 2` through [`Grid::vertex_unknown`].
    /// Computed, not stored (16 bytes a facet less: 1.6 GB at 100 MP).
    #[inline]
    pub fn facet_vertices(&self, f: usize) -> [u32; 4] {
        let p = self.facets[f] as usize;
        let vw = self.width + 1;
        let v = p / self.width * vw + p % self.width;
        [
            self.vertex_unknown[v],
            self.vertex_unknown[v + 1],
            self.vertex_unknown[v + vw],
            self.vertex_unknown[v + vw + 1],
        ]
    }

    /// [`Grid::facet_vertices`] of every facet, in facet order.
    pub fn all_facet_vertices(&self) -> impl ExactSizeIterator<Item = [u32; 4]> + '_ {
        (0..self.facets.len()).map(|f| self.facet_vertices(f))
    }

    /// Region label of every pixel (-1 outside the mask), row-major (H, W).
    pub fn pixel_regions(&self) -> Result<Vec<i32>> {
        // Pixel by pixel in parallel (the same values as a pass over the facets).
        try_par_collect(
            (0..self.height * self.width)
                .into_par_iter()
                .map(|p| match self.facet_of_pixel(p) {
                    INACTIVE => -1,
                    f => self.region_of_unknown[self.facet_vertices(f as usize)[0] as usize] as i32,
                }),
            "the region map",
        )
    }

    /// Scatters `f` of the per-unknown `values` onto the full (H+1) x (W+1) vertex grid, NaN
    /// where inactive, without a vector of the mapped values (`f`: the depth of an unknown, for
    /// the result's depth map).
    pub fn scatter_vertices_with(
        &self,
        values: &[f64],
        f: impl Fn(f64) -> f64 + Sync,
    ) -> Result<Vec<f64>> {
        // Vertex by vertex in parallel (`f` is an `exp` per vertex for a pinhole camera).
        try_par_collect(
            self.vertex_unknown.par_iter().map(|&u| match u {
                INACTIVE => f64::NAN,
                u => f(values[u as usize]),
            }),
            "a vertex map",
        )
    }

    /// Gathers the unknowns' values from a full (H+1) x (W+1) vertex grid.
    pub fn gather_vertices(&self, full: &[f64]) -> Result<Vec<f64>> {
        try_collect(
            self.active.iter().map(|&v| full[v as usize]),
            "the values at the unknowns",
        )
    }

    /// Arithmetic mean of `values` (one per unknown) over each region. With few regions the
    /// sums run in parallel over fixed chunks added in order, so the result does not depend on
    /// the number of threads.
    pub fn region_means(&self, values: &[f64]) -> Vec<f64> {
        let regions = self.n_regions;
        let (sum, count) = if regions <= PARALLEL_REGIONS {
            let partial: Vec<(Vec<f64>, Vec<usize>)> = self
                .region_of_unknown
                .par_chunks(CHUNK)
                .zip(values.par_chunks(CHUNK))
                .map(|(reg, val)| region_sums(regions, reg, val))
                .collect();
            let mut sum = vec![0.0; regions];
            let mut count = vec![0usize; regions];
            for (s, c) in &partial {
                for r in 0..regions {
                    sum[r] += s[r];
                    count[r] += c[r];
                }
            }
            (sum, count)
        } else {
            region_sums(regions, &self.region_of_unknown, values)
        };
        sum.iter().zip(&count).map(|(s, &n)| s / n as f64).collect()
    }

    /// Shifts each region by a constant so that its arithmetic mean equals `gauge[region]`.
    pub fn apply_gauge(&self, values: &mut [f64], gauge: &[f64]) {
        let means = self.region_means(values);
        let shift: Vec<f64> = gauge.iter().zip(&means).map(|(g, m)| g - m).collect();
        values
            .par_iter_mut()
            .zip(self.region_of_unknown.par_iter())
            .for_each(|(v, &reg)| *v += shift[reg as usize]);
    }

    /// `sum_f S_f^T t_f` at grid vertex `v` (row `r`, column `c`): the targets of its (up to 4)
    /// facets, in the order NW, NE, SW, SE.
    #[inline]
    pub(crate) fn gather_targets(&self, targets: &[[f64; 4]], r: usize, c: usize) -> f64 {
        let w = self.width;
        let mut sum = 0.0;
        let mut add = |pr: usize, pc: usize, corner: usize| {
            if pr < self.height && pc < w {
                let f = self.facet_of_pixel(pr * w + pc);
                if f != INACTIVE {
                    sum += targets[f as usize][corner];
                }
            }
        };
        add(r.wrapping_sub(1), c.wrapping_sub(1), 3);
        add(r.wrapping_sub(1), c, 2);
        add(r, c.wrapping_sub(1), 1);
        add(r, c, 0);
        sum
    }
}

/// Regions up to which [`Grid::region_means`] sums in parallel.
const PARALLEL_REGIONS: usize = 64;

/// Elements per chunk of the deterministic parallel sums.
const CHUNK: usize = 1 << 15;

/// Per-region sums and counts of `values` labelled by `regions`.
fn region_sums(n: usize, regions: &[u32], values: &[f64]) -> (Vec<f64>, Vec<usize>) {
    let mut sum = vec![0.0; n];
    let mut count = vec![0usize; n];
    for (&reg, &v) in regions.iter().zip(values) {
        sum[reg as usize] += v;
        count[reg as usize] += 1;
    }
    (sum, count)
}

/// Connected components of the unknowns where the 4 corners of a facet are connected
/// (union-find). Labels are numbered by first appearance in unknown order.
fn label_regions(
    n: usize,
    facet_vertices: impl Iterator<Item = [u32; 4]>,
) -> Result<(Vec<u32>, usize)> {
    let mut parent: Vec<u32> = try_collect(0..n as u32, "the mesh's region labels")?;
    fn find(parent: &mut [u32], mut x: u32) -> u32 {
        while parent[x as usize] != x {
            let up = parent[parent[x as usize] as usize];
            parent[x as usize] = up;
            x = up;
        }
        x
    }
    for fv in facet_vertices {
        let root = find(&mut parent, fv[0]);
        for &v in &fv[1..] {
            let other = find(&mut parent, v);
            if other != root {
                let (lo, hi) = if other < root {
                    (other, root)
                } else {
                    (root, other)
                };
                parent[hi as usize] = lo;
            }
        }
    }
    let mut label = try_vec(n, u32::MAX, "the mesh's region labels")?;
    let mut region = try_vec(n, 0u32, "the mesh's regions")?;
    let mut n_regions = 0u32;
    for (u, reg) in region.iter_mut().enumerate() {
        let root = find(&mut parent, u as u32) as usize;
        if label[root] == u32::MAX {
            label[root] = n_regions;
            n_regions += 1;
        }
        *reg = label[root];
    }
    Ok((region, n_regions as usize))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn full_mask_has_all_vertices_and_one_region() {
        let g = Grid::new(3, 4, None).unwrap();
        assert_eq!(g.n_facets(), 12);
        assert_eq!(g.n_unknowns(), 20);
        assert_eq!(g.n_regions, 1);
        assert_eq!(g.pins, vec![0]);
        assert_eq!(g.facet_vertices(5), [6, 7, 11, 12]);
    }

    /// The region and vertex maps, made pixel by pixel and vertex by vertex in parallel, hold
    /// what a pass over the facets and the unknowns writes (holed mask: -1 and NaN outside).
    #[test]
    fn region_and_vertex_maps_match_a_pass_over_the_facets() {
        let (h, w) = (23, 31);
        let mask: Vec<bool> = (0..h * w).map(|p| (p * 7919) % 11 != 0).collect();
        let g = Grid::new(h, w, Some(&mask)).unwrap();
        let mut regions = vec![-1; h * w];
        for (f, p) in g.facets.iter().map(|&p| p as usize).enumerate() {
            regions[p] = g.region_of_unknown[g.facet_vertices(f)[0] as usize] as i32;
        }
        assert_eq!(g.pixel_regions().unwrap(), regions);
        let values: Vec<f64> = (0..g.n_unknowns()).map(|u| u as f64 * 0.37 - 3.0).collect();
        let mut vertices = vec![f64::NAN; (h + 1) * (w + 1)];
        for (u, v) in g.active.iter().map(|&v| v as usize).enumerate() {
            vertices[v] = values[u].exp();
        }
        let made = g.scatter_vertices_with(&values, f64::exp).unwrap();
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&made), bits(&vertices));
    }

    #[test]
    fn diagonal_neighbours_share_a_region_and_islands_do_not() {
        // Pixels (0,0) and (1,1) touch at one vertex: one region. Pixel (0,3) is an island.
        #[rustfmt::skip]
        let mask = [
            true, false, false, true,
            false, true, false, false,
        ];
        let g = Grid::new(2, 4, Some(&mask)).unwrap();
        assert_eq!(g.n_regions, 2);
        let regions = g.pixel_regions().unwrap();
        assert_eq!(regions[0], regions[5]);
        assert_ne!(regions[0], regions[3]);
        assert_eq!(g.pins.len(), 2);
        for (reg, &pin) in g.pins.iter().enumerate() {
            assert_eq!(g.region_of_unknown[pin as usize] as usize, reg);
            assert!(g.region_of_unknown[..pin as usize]
                .iter()
                .all(|&r| r as usize != reg));
        }
    }

    #[test]
    fn empty_and_mismatched_masks_are_errors() {
        assert!(Grid::new(2, 2, Some(&[false; 4])).is_err());
        assert!(Grid::new(2, 2, Some(&[true; 3])).is_err());
    }

    #[test]
    fn gauge_sets_region_means() {
        let g = Grid::new(2, 2, None).unwrap();
        let mut z: Vec<f64> = (0..9).map(|i| i as f64).collect();
        g.apply_gauge(&mut z, &[10.0]);
        assert!((g.region_means(&z)[0] - 10.0).abs() < 1e-12);
        assert!((z[1] - z[0] - 1.0).abs() < 1e-12);
    }
}
