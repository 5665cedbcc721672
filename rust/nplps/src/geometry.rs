//! Where the mesh vertices are, and what the global step solves for.
//!
//! Every unknown of the global step is one scalar `u` per active vertex:
//! - orthographic camera: `u = z`, the vertex at `(x, y, z)` with `(x, y)` fixed by the grid;
//! - pinhole camera: `u = log z`, the vertex at `z * r` on the ray `r = (x, y, 1)` through its
//!   pixel corner.
//!
//! The local step's plane through the facet centre `c` with normal `n` becomes mean-subtracted
//! targets for the 4 corners:
//! - orthographic: `z_j = c_z - (n_x dx_j + n_y dy_j) / n_z` (dx, dy: corner offsets from `c`);
//! - pinhole: the plane meets ray `r_j` at `z_j = (n . c) / (n . r_j)`, so
//!   `log z_j = log(-n . c) - log(-n . r_j)` and the mean-subtracted target
//!   `-log(-n . r_j) + mean_j log(-n . r_j)` does not depend on the plane's offset.
//!
//! Grazing fits are limited: `n_z <= -NZ_MIN` (orthographic), `-n . r_j >= NZ_MIN |r_j|`
//! (pinhole). The gauge is the arithmetic mean of `u` per region: the arithmetic mean depth
//! (orthographic) or the geometric mean depth (pinhole).
//!
//! A facet's 4 corner positions ([`Geometry::facet_corners`], in the corner order of
//! [`crate::grid`]) give its normal ([`quad_normal`]) and centre ([`quad_centre`]).

use rayon::prelude::*;

use crate::error::{ensure_shape, Error, Result};
use crate::grid::Grid;
use crate::rig::{Camera, MAX_MAGNITUDE};
use crate::vec3::{cross, normalize, sub};

/// Largest allowed `n_z` (orthographic), or smallest `-n . r / |r|` (pinhole), when a fitted
/// normal is turned into a plane; bounds the target slopes of grazing fits.
pub const NZ_MIN: f64 = 0.01;

/// `NZ_MIN^2` enlarged by a relative margin of 1e-9 (see [`Geometry::plane_target`]).
const NZ_MIN_SQ_SAFE: f64 = NZ_MIN * NZ_MIN * (1.0 + 1e-9);

/// Vertex positions of the active vertices of a grid under a camera.
#[derive(Debug, Clone)]
pub struct Geometry {
    perspective: bool,
    /// Per unknown: the fixed (x, y) (orthographic) or the ray's (x, y) at z = 1 (pinhole).
    base: Base,
}

/// Where [`Geometry`] finds the `(x, y)` of an unknown.
///
/// A camera whose `(x, y)` at vertex `(r, c)` is `(xs[c], ys[r])` (orthographic, or a pinhole
/// without distortion and skew: `x = (c - 1/2 - c_x) / f_x`, `y = (r - 1/2 - c_y) / f_y`) keeps
/// one value per column and per row, the same values [`Camera::vertex_xy`] gives, bit for bit:
/// `O(H + W)` memory instead of 16 bytes per vertex (1.6 GB at 100 MP). The vertex of unknown
/// `i` is `i` itself when every vertex is active (a full mask), else a copy of
/// [`Grid::active`] (4 bytes per unknown). Other cameras keep the table.
#[derive(Debug, Clone)]
enum Base {
    Separable {
        /// `x` per vertex column.
        xs: Vec<f64>,
        /// `y` per vertex row.
        ys: Vec<f64>,
        /// Vertices per row (`W + 1`).
        columns: usize,
        /// The vertex of each unknown (None: unknown `i` is vertex `i`).
        vertex: Option<Vec<u32>>,
    },
    Table(Vec<[f64; 2]>),
}

impl Base {
    #[inline]
    fn get(&self, i: usize) -> [f64; 2] {
        match self {
            Base::Separable {
                xs,
                ys,
                columns,
                vertex,
            } => {
                let v = match vertex {
                    Some(vertex) => vertex[i] as usize,
                    None => i,
                };
                [xs[v % columns], ys[v / columns]]
            }
            Base::Table(t) => t[i],
        }
    }

    fn len(&self) -> usize {
        match self {
            Base::Separable { xs, ys, vertex, .. } => match vertex {
                Some(vertex) => vertex.len(),
                None => xs.len() * ys.len(),
            },
            Base::Table(t) => t.len(),
        }
    }
}

impl Geometry {
    /// The geometry of `grid`'s active vertices under `camera`.
    pub fn new(camera: &Camera, grid: &Grid) -> Result<Geometry> {
        let vw = grid.width + 1;
        let separable = match *camera {
            Camera::Orthographic { .. } => true,
            Camera::Pinhole { k, distortion } => k[0][1] == 0.0 && distortion == [0.0; 5],
        };
        let base = if separable {
            let full = grid.active.len() == vw * (grid.height + 1);
            Base::Separable {
                xs: (0..vw).map(|c| camera.vertex_xy(0, c)[0]).collect(),
                ys: (0..=grid.height)
                    .map(|r| camera.vertex_xy(r, 0)[1])
                    .collect(),
                columns: vw,
                vertex: match full {
                    true => None,
                    false => Some(crate::memory::try_copy(
                        &grid.active,
                        "the vertices of the unknowns",
                    )?),
                },
            }
        } else {
            Base::Table(crate::memory::try_par_collect(
                grid.active
                    .par_iter()
                    .map(|&v| camera.vertex_xy(v as usize / vw, v as usize % vw)),
                "the vertex positions",
            )?)
        };
        Ok(Geometry {
            perspective: camera.is_perspective(),
            base,
        })
    }

    /// An orthographic geometry of `n` unknowns at (0, 0) (tests that only need depths).
    #[cfg(test)]
    pub(crate) fn orthographic(n: usize) -> Geometry {
        Geometry {
            perspective: false,
            base: Base::Table(vec![[0.0; 2]; n]),
        }
    }

    /// Fails when a vertex of `grid` (the grid this geometry was made for) has no finite
    /// position or ray, or one beyond [`MAX_MAGNITUDE`]: a pinhole camera whose distortion
    /// cannot be undone there (see `undistort_checked`) or whose rays are nearly
    /// parallel to the image plane, or an orthographic grid too large. Only the unknowns `i`
    /// with `used(i)` are checked.
    pub fn check_rays(&self, grid: &Grid, used: impl Fn(usize) -> bool + Sync) -> Result<()> {
        let Some(i) = (0..self.base.len()).into_par_iter().position_first(|i| {
            let b = self.base.get(i);
            used(i) && !(b[0].abs() <= MAX_MAGNITUDE && b[1].abs() <= MAX_MAGNITUDE)
        }) else {
            return Ok(());
        };
        let v = grid.active[i] as usize;
        let (r, c) = (v / (grid.width + 1), v % (grid.width + 1));
        Err(Error::Rig(if self.perspective {
            format!(
                "the camera has no ray at pixel corner (row {r}, column {c}): its distortion \
                 cannot be undone there (OpenCV's model maps no ray there: distortion too strong \
                 for this image size, or K and distortion for another image size?) or K puts \
                 it at a right angle to the optical axis"
            )
        } else {
            format!(
                "the orthographic camera's grid reaches beyond {} at pixel corner (row {r}, \
                 column {c}) (pixel_size and origin too large)",
                crate::error::g6(MAX_MAGNITUDE)
            )
        }))
    }

    /// Whether the unknowns are log-depths.
    #[inline]
    pub fn is_perspective(&self) -> bool {
        self.perspective
    }

    /// The unit vector from the surface point `x` towards the camera: `-x / |x|` for a pinhole
    /// camera (its centre is the origin), `(0, 0, -1)` for an orthographic one.
    #[inline]
    pub fn view(&self, x: [f64; 3]) -> [f64; 3] {
        if self.perspective {
            normalize([-x[0], -x[1], -x[2]])
        } else {
            [0.0, 0.0, -1.0]
        }
    }

    /// The unknown of a depth.
    #[inline]
    pub fn unknown(&self, z: f64) -> f64 {
        if self.perspective {
            z.ln()
        } else {
            z
        }
    }

    /// The depth of an unknown.
    #[inline]
    pub fn depth(&self, u: f64) -> f64 {
        if self.perspective {
            u.exp()
        } else {
            u
        }
    }

    /// Position of unknown `i` with unknown value `u`.
    #[inline]
    pub fn position(&self, i: usize, u: f64) -> [f64; 3] {
        self.position_at_depth(i, self.depth(u))
    }

    /// Position of unknown `i` at depth `z`.
    #[inline]
    pub fn position_at_depth(&self, i: usize, z: f64) -> [f64; 3] {
        self.position_from_base(self.base.get(i), z)
    }

    /// The position at depth `z` of the unknown whose fixed `(x, y)` (orthographic) or ray
    /// `(x, y, 1)` (pinhole) is `base` (see [`Geometry::base`]).
    #[inline(always)]
    pub(crate) fn position_from_base(&self, [x, y]: [f64; 2], z: f64) -> [f64; 3] {
        if self.perspective {
            [x * z, y * z, z]
        } else {
            [x, y, z]
        }
    }

    /// The fixed `(x, y)` (orthographic) or the ray's `(x, y)` at `z = 1` (pinhole) of unknown
    /// `i`.
    #[inline]
    pub(crate) fn base(&self, i: usize) -> [f64; 2] {
        self.base.get(i)
    }

    /// [`Geometry::base`] of unknown `i` when the caller knows its grid vertex `(row, col)`:
    /// the same values, without the division that finds the vertex of an unknown.
    #[inline(always)]
    pub(crate) fn base_at_vertex(&self, i: usize, row: usize, col: usize) -> [f64; 2] {
        match &self.base {
            Base::Separable { xs, ys, .. } => [xs[col], ys[row]],
            Base::Table(t) => t[i],
        }
    }

    /// The 4 corners of facet `f` of `grid` (the grid this geometry was made for), in the order
    /// 00, 01, 10, 11, given the unknowns `u`.
    #[inline]
    pub fn facet_corners(&self, grid: &Grid, f: usize, u: &[f64]) -> [[f64; 3]; 4] {
        grid.facet_vertices(f)
            .map(|i| self.position(i as usize, u[i as usize]))
    }

    /// Mean-subtracted targets of the corners `ids` for the plane through `centre` with unit
    /// normal `n` (see the module documentation). Inlined into the local step's loops (a call
    /// returning the 4 targets through memory stalled the loads that follow).
    #[inline(always)]
    pub fn plane_target(&self, n: [f64; 3], ids: [u32; 4], centre: [f64; 3]) -> [f64; 4] {
        // (Array literals rather than `map`: its calls, returning arrays through memory, were
        // not inlined into the local step.)
        let at = |j: usize| self.base.get(ids[j] as usize);
        self.plane_target_at([at(0), at(1), at(2), at(3)], n, centre)
    }

    /// [`Geometry::plane_target`] of the corners whose [`Geometry::base`] values are `base`.
    #[inline(always)]
    pub(crate) fn plane_target_at(
        &self,
        base: [[f64; 2]; 4],
        n: [f64; 3],
        centre: [f64; 3],
    ) -> [f64; 4] {
        let raw: [f64; 4] = if self.perspective {
            let s = |[x, y]: [f64; 2]| {
                // `max(t, NZ_MIN |r|)` without the square root where `t` clearly exceeds the
                // bound (`t^2 >= NZ_MIN^2 |r|^2 (1 + 1e-9)`, a margin far above the rounding of
                // either side): then it is `t`, the same bits as with the root.
                let t = -(n[0] * x + n[1] * y + n[2]);
                let r2 = x * x + y * y + 1.0;
                if t > 0.0 && t * t >= NZ_MIN_SQ_SAFE * r2 {
                    t
                } else {
                    t.max(NZ_MIN * r2.sqrt())
                }
            };
            log_ratios([s(base[0]), s(base[1]), s(base[2]), s(base[3])])
        } else {
            let nz = n[2].min(-NZ_MIN);
            let z = |[x, y]: [f64; 2]| -(n[0] * (x - centre[0]) + n[1] * (y - centre[1])) / nz;
            [z(base[0]), z(base[1]), z(base[2]), z(base[3])]
        };
        let mean = 0.25 * (raw[0] + raw[1] + raw[2] + raw[3]);
        [raw[0] - mean, raw[1] - mean, raw[2] - mean, raw[3] - mean]
    }
}

impl Geometry {
    /// [`Geometry::plane_target_at`] of `N` facets at once, one lane each (corner bases
    /// `base`, unit normals `n` as their 3 components over the lanes, centres `centre`): per
    /// lane the same operations in the same order, so the same bits, written as plain loops
    /// over the lanes for the local step's vectorised kernels. Lanes whose log-ratios leave the
    /// series' range take the logarithms, as [`log_ratios`] does.
    #[inline(always)]
    pub(crate) fn plane_targets<const N: usize>(
        &self,
        base: &[[[f64; 2]; 4]; N],
        n: &[[f64; N]; 3],
        centre: &[[f64; 3]; N],
    ) -> [[f64; 4]; N] {
        let mut raw = [[0.0f64; N]; 4];
        if self.perspective {
            let mut s = [[0.0f64; N]; 4];
            for (j, s) in s.iter_mut().enumerate() {
                for l in 0..N {
                    let [x, y] = base[l][j];
                    let t = -(n[0][l] * x + n[1][l] * y + n[2][l]);
                    let r2 = x * x + y * y + 1.0;
                    let clear = t > 0.0 && t * t >= NZ_MIN_SQ_SAFE * r2;
                    let bound = t.max(NZ_MIN * r2.sqrt());
                    s[l] = if clear { t } else { bound };
                }
            }
            let mut series = [true; N];
            for l in 0..N {
                let inv = 1.0 / s[0][l];
                for j in 1..4 {
                    let x = (s[j][l] - s[0][l]) * inv;
                    series[l] &= x.abs() <= LN1P_SERIES_MAX;
                    raw[j][l] = -ln1p_series(x);
                }
            }
            for l in 0..N {
                if !series[l] {
                    for j in 0..4 {
                        raw[j][l] = -s[j][l].ln();
                    }
                }
            }
        } else {
            for (j, raw) in raw.iter_mut().enumerate() {
                for l in 0..N {
                    let [x, y] = base[l][j];
                    let nz = n[2][l].min(-NZ_MIN);
                    raw[l] = -(n[0][l] * (x - centre[l][0]) + n[1][l] * (y - centre[l][1])) / nz;
                }
            }
        }
        let mut out = [[0.0f64; 4]; N];
        for (l, out) in out.iter_mut().enumerate() {
            let mean = 0.25 * (raw[0][l] + raw[1][l] + raw[2][l] + raw[3][l]);
            *out = [
                raw[0][l] - mean,
                raw[1][l] - mean,
                raw[2][l] - mean,
                raw[3][l] - mean,
            ];
        }
        out
    }
}

/// Largest `|x|` for which [`ln1p_series`] is used (`2^-7`: its first omitted term, `x^10 / 10`,
/// is below `1e-22`).
const LN1P_SERIES_MAX: f64 = 1.0 / 128.0;

/// `ln(1 + x)` for `|x| <= LN1P_SERIES_MAX` by its Taylor series to `x^9` (Estrin's scheme): no
/// call into libm, and within a few units of rounding of `x` of the exact value.
#[inline(always)]
fn ln1p_series(x: f64) -> f64 {
    const C: [f64; 9] = [
        1.0,
        -1.0 / 2.0,
        1.0 / 3.0,
        -1.0 / 4.0,
        1.0 / 5.0,
        -1.0 / 6.0,
        1.0 / 7.0,
        -1.0 / 8.0,
        1.0 / 9.0,
    ];
    // Estrin's scheme: pairs, then powers of x^2, for a short dependency chain.
    let x2 = x * x;
    let x4 = x2 * x2;
    let p01 = C[0] + C[1] * x;
    let p23 = C[2] + C[3] * x;
    let p45 = C[4] + C[5] * x;
    let p67 = C[6] + C[7] * x;
    let p0123 = p01 + p23 * x2;
    let p4567 = p45 + p67 * x2;
    let p = p0123 + (p4567 + C[8] * x4) * x4;
    p * x
}

/// The pinhole targets' `-log s_j` of the 4 corners up to a common constant (which the mean
/// subtraction removes): `-log(s_j / s_0)`. Neighbouring rays make `s_j / s_0 = 1 + x_j` with
/// `|x_j|` of the order of a pixel's angle times the slope, so the logarithm is [`ln1p_series`]
/// of `x_j` (no libm call, and more accurate than the difference of two logarithms); beyond
/// [`LN1P_SERIES_MAX`] (grazing fits, very coarse pyramid levels), or for a NaN, `-ln s_j`.
#[inline(always)]
fn log_ratios(s: [f64; 4]) -> [f64; 4] {
    let inv = 1.0 / s[0];
    let x = [
        0.0,
        (s[1] - s[0]) * inv,
        (s[2] - s[0]) * inv,
        (s[3] - s[0]) * inv,
    ];
    let small = |v: f64| v.abs() <= LN1P_SERIES_MAX;
    if small(x[1]) && small(x[2]) && small(x[3]) {
        [
            0.0,
            -ln1p_series(x[1]),
            -ln1p_series(x[2]),
            -ln1p_series(x[3]),
        ]
    } else {
        [-s[0].ln(), -s[1].ln(), -s[2].ln(), -s[3].ln()]
    }
}

/// Geometric normal of a quad: `normalize((v10 - v01) x (v11 - v00))`, facing the camera
/// (n_z < 0) for a visible facet. It is the normal of the plane spanned by the two diagonals, i.e.
/// the averaged finite-difference slope of the quad.
#[inline]
pub fn quad_normal(q: &[[f64; 3]; 4]) -> [f64; 3] {
    let d1 = sub(q[2], q[1]);
    let d2 = sub(q[3], q[0]);
    normalize(cross(d1, d2))
}

/// Mean of the 4 corners.
#[inline]
pub fn quad_centre(q: &[[f64; 3]; 4]) -> [f64; 3] {
    std::array::from_fn(|i| 0.25 * (q[0][i] + q[1][i] + q[2][i] + q[3][i]))
}

/// Checks that `depth` has the (H+1) x (W+1) values of a vertex depth map.
fn ensure_depth_map(height: usize, width: usize, depth: &[f64]) -> Result<()> {
    ensure_shape("depth map", (height + 1) * (width + 1), depth.len(), || {
        format!(
            "depth map has {} values, expected (W+1) x (H+1) = {} x {}",
            depth.len(),
            width + 1,
            height + 1
        )
    })
}

/// Whether a vertex of depth `z` whose [`Camera::vertex_xy`] is `xy` lacks a camera ray that
/// it needs (vertices of unknown, NaN, depth need none: outside a reconstruction's mask, say).
#[inline]
fn lacks_ray([x, y]: [f64; 2], z: f64) -> bool {
    z.is_finite() && !(x.abs() <= MAX_MAGNITUDE && y.abs() <= MAX_MAGNITUDE)
}

/// The error naming the first vertex of finite depth without a ray (the geometry's own check),
/// once [`lacks_ray`] found one.
fn missing_ray(camera: &Camera, height: usize, width: usize, depth: &[f64]) -> Result<()> {
    let grid = Grid::new(height, width, None)?;
    Geometry::new(camera, &grid)?.check_rays(&grid, |v| depth[v].is_finite())
}

/// 3-D position of every vertex of an (H+1) x (W+1) depth map (row-major); an error where a vertex
/// of finite depth has no camera ray.
pub fn vertices(
    camera: &Camera,
    height: usize,
    width: usize,
    depth: &[f64],
) -> Result<Vec<[f64; 3]>> {
    ensure_depth_map(height, width, depth)?;
    crate::memory::check(
        || format!("the vertices of a depth map of {width} x {height} pixels"),
        // The positions, 24 bytes per vertex, twice for room (the grid and geometry of the
        // error path of a missing ray allocate fallibly). It was 100, from when the positions
        // came from a grid and its geometry, and refused a 100 MP result's mesh at the end of
        // the run (issue 23).
        48.0 * depth.len() as f64,
        None,
    )?;
    // Each vertex's ray straight from the camera (no grid or geometry: 24 bytes per vertex
    // instead of about 100, which at 12 MP is a gigabyte of pages less to fault in; issue 23),
    // with the arithmetic of `Geometry::position_at_depth`.
    let vw = width + 1;
    let no_ray = std::sync::atomic::AtomicBool::new(false);
    let positions = crate::memory::try_par_collect(
        depth.par_iter().enumerate().map(|(v, &z)| {
            let (position, lacking) = vertex_position(camera, vw, v, z);
            if lacking {
                no_ray.store(true, std::sync::atomic::Ordering::Relaxed);
            }
            position
        }),
        "the vertex positions",
    )?;
    if no_ray.into_inner() {
        missing_ray(camera, height, width, depth)?;
    }
    Ok(positions)
}

/// The position of vertex `v` (row-major, `vw` vertices a row) at depth `z`, and whether a
/// finite depth lacks a camera ray there ([`vertices`]' error).
fn vertex_position(camera: &Camera, vw: usize, v: usize, z: f64) -> ([f64; 3], bool) {
    let xy = camera.vertex_xy(v / vw, v % vw);
    (camera.at_depth(xy, z), lacks_ray(xy, z))
}

/// The corners (top-left, top-right, bottom-left, bottom-right) of pixel `p` of an image
/// `width` pixels wide, from its (H+1) x (W+1) `vertices` (row-major).
#[inline]
pub(crate) fn pixel_quad(vertices: &[[f64; 3]], width: usize, p: usize) -> [[f64; 3]; 4] {
    let v = (p / width) * (width + 1) + p % width;
    [
        vertices[v],
        vertices[v + 1],
        vertices[v + width + 1],
        vertices[v + width + 2],
    ]
}

/// Pixel rows a task of [`facet_normals`] makes (it computes their `rows + 1` vertex rows).
const NORMAL_BAND: usize = 16;

/// The mesh normal [`quad_normal`] of every pixel of an (H+1) x (W+1) depth map (H x W,
/// row-major), NaN outside `mask` (None: every pixel); an error where a vertex of finite depth has
/// no camera ray (as [`vertices`]).
///
/// The same normals, bit for bit, as [`quad_normal`] of the quads of [`vertices`]' positions,
/// without the whole (H+1) x (W+1) position grid: each parallel task takes a band of
/// `NORMAL_BAND` pixel rows, computes the positions of its `NORMAL_BAND + 1` vertex rows into a
/// buffer of its own (the vertex rows between two bands twice) and writes the band's normals, so
/// that the only large allocation is the result (24 bytes a pixel instead of 24 a vertex more).
pub(crate) fn facet_normals(
    camera: &Camera,
    height: usize,
    width: usize,
    depth: &[f64],
    mask: Option<&[bool]>,
) -> Result<Vec<[f64; 3]>> {
    ensure_depth_map(height, width, depth)?;
    crate::error::ensure_mask(mask, height * width)?;
    let mut normals = crate::memory::try_zeros::<[f64; 3]>(height * width, "the mesh normals")?;
    let vw = width + 1;
    let no_ray = std::sync::atomic::AtomicBool::new(false);
    normals
        .par_chunks_mut((NORMAL_BAND * width).max(1))
        .enumerate()
        .for_each(|(band, out)| {
            let top = band * NORMAL_BAND;
            let rows = out.len() / width;
            let mut positions = Vec::with_capacity((rows + 1) * vw);
            let mut lacking = false;
            let first = top * vw;
            for (v, &z) in (first..).zip(&depth[first..(top + rows + 1) * vw]) {
                let (position, lacks) = vertex_position(camera, vw, v, z);
                lacking |= lacks;
                positions.push(position);
            }
            if lacking {
                no_ray.store(true, std::sync::atomic::Ordering::Relaxed);
            }
            for (i, n) in out.iter_mut().enumerate() {
                let (r, c) = (i / width, i % width);
                if mask.is_some_and(|m| !m[(top + r) * width + c]) {
                    *n = [f64::NAN; 3];
                    continue;
                }
                *n = quad_normal(&pixel_quad(&positions, width, i));
            }
        });
    if no_ray.into_inner() {
        missing_ray(camera, height, width, depth)?;
    }
    Ok(normals)
}

/// Checks that every vertex of finite depth of an (H+1) x (W+1) depth map has a camera ray,
/// with the error of [`vertices`], without making the positions (the PLY writer computes them
/// vertex by vertex: `crate::mesh::Positions::Camera`).
pub fn check_vertex_rays(
    camera: &Camera,
    height: usize,
    width: usize,
    depth: &[f64],
) -> Result<()> {
    ensure_depth_map(height, width, depth)?;
    let vw = width + 1;
    let no_ray = depth
        .par_iter()
        .enumerate()
        .any(|(v, &z)| lacks_ray(camera.vertex_xy(v / vw, v % vw), z));
    if no_ray {
        missing_ray(camera, height, width, depth)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vertices_are_the_geometrys_positions() {
        // The direct rays of `vertices` against the grid-and-geometry path they replaced, bit
        // for bit, on a distorted pinhole camera and an orthographic one, with unknown depths.
        let (h, w) = (7, 9);
        let cameras = crate::rig::test_cameras();
        let mut depth: Vec<f64> = (0..(h + 1) * (w + 1))
            .map(|v| 50.0 + (v as f64).sin())
            .collect();
        depth[5] = f64::NAN;
        for camera in &cameras {
            let got = vertices(camera, h, w, &depth).unwrap();
            let grid = Grid::new(h, w, None).unwrap();
            let geometry = Geometry::new(camera, &grid).unwrap();
            for (v, p) in got.iter().enumerate() {
                let want = geometry.position_at_depth(v, depth[v]);
                for k in 0..3 {
                    assert_eq!(p[k].to_bits(), want[k].to_bits(), "vertex {v}");
                }
            }
        }
    }

    /// The series agrees with `ln_1p` to a few units of rounding over its range, and the
    /// targets of `log_ratios` with those of 4 logarithms once mean-subtracted.
    #[test]
    fn log_ratios_match_the_logarithms() {
        let mut worst = 0.0f64;
        for i in 0..=2000 {
            let x = LN1P_SERIES_MAX * (i as f64 / 1000.0 - 1.0);
            let err = (ln1p_series(x) - x.ln_1p()).abs();
            worst = worst.max(err / (x.abs() * f64::EPSILON).max(f64::MIN_POSITIVE));
        }
        assert!(worst <= 4.0, "{worst} ulps of x");
        let centred = |r: [f64; 4]| {
            let m = 0.25 * (r[0] + r[1] + r[2] + r[3]);
            r.map(|t| t - m)
        };
        for (s, series) in [
            ([0.7, 0.7002, 0.6999, 0.70015], true),
            ([0.02, 0.0201, 0.0199, 0.02], true),
            ([0.02, 0.03, 0.0199, 0.02], false),
            ([f64::NAN, 0.5, 0.5, 0.5], false),
        ] {
            let x = s.map(|v| (v - s[0]) / s[0]);
            assert_eq!(x.iter().all(|v| v.abs() <= LN1P_SERIES_MAX), series);
            let got = centred(log_ratios(s));
            let want = centred(s.map(|v| -v.ln()));
            for (g, w) in got.iter().zip(want) {
                assert!(
                    (g - w).abs() <= 1e-15 || (g.is_nan() && w.is_nan()),
                    "{got:?} {want:?}"
                );
            }
        }
    }

    #[test]
    fn quad_normal_faces_the_camera() {
        let q = [
            [0.0, 0.0, 5.0],
            [1.0, 0.0, 5.0],
            [0.0, 1.0, 5.0],
            [1.0, 1.0, 5.0],
        ];
        let n = quad_normal(&q);
        assert!((n[2] + 1.0).abs() < 1e-15);
        // z = 5 + 0.5 x: the normal is (0.5, 0, -1) normalized.
        let q = q.map(|p| [p[0], p[1], p[2] + 0.5 * p[0]]);
        let n = quad_normal(&q);
        let s = (1.25f64).sqrt();
        assert!((n[0] - 0.5 / s).abs() < 1e-12 && (n[2] + 1.0 / s).abs() < 1e-12);
    }
}
