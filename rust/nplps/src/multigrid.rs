//! The global step at linear cost: conjugate gradients preconditioned by a geometric multigrid
//! V-cycle on the masked vertex grid.
//!
//! The global system `A u = b` (see [`crate::global`]) is a sum of one 4 x 4 element per facet,
//! `N = I_4 - ones/4` on the facet's 4 corners, plus diagonal terms (the pinned vertex of each
//! region, the depth prior). On the vertex grid it is a 9-point stencil that depends only on the
//! mask.
//!
//! **Hierarchy.** Level `l + 1` has the nodes of the even rows and columns of level `l`
//! (`rows / 2 + 1` of them along each axis); the prolongation `P` is bilinear interpolation,
//! restricted to the active nodes of the finer level (an inactive node gets nothing), and the
//! restriction is `P^T`. Coarse operators are Galerkin products `A_{l+1} = P^T A_l P`, computed
//! element by element: the 2 x 2 fine cells `(2R + a, 2C + b)` all interpolate from the 4
//! corners of coarse cell `(R, C)` through a fixed invertible 4 x 4 matrix `Q_ab`, so the coarse
//! element is `sum_ab Q_ab^T E_child Q_ab` and every level is again a 9-point stencil. Because
//! each `Q_ab` is invertible, `P` has full column rank on the active coarse nodes and every
//! `A_l` is symmetric positive definite when `A` is; constants (the near-null space of each
//! region) are interpolated exactly. The coarsest level (a few thousand nodes) is factored by
//! faer's sparse Cholesky.
//!
//! **Smoother.** Gauss-Seidel over horizontal bands of [`BAND`] rows: bands of even index are
//! swept in parallel, then bands of odd index (a band reads only its neighbours' boundary rows,
//! which the other phase writes). The pre-smoother sweeps forward, the post-smoother backward in
//! the reverse band order, so the V-cycle is a symmetric preconditioner. The band height is
//! fixed, so results do not depend on the number of threads.
//!
//! **Solve.** Each global step runs preconditioned conjugate gradients from the current depths
//! (a warm start: the right side changes little between outer iterations) until
//! `|b - A u| <= rtol |b_t|`, with `b_t` the facet part of the right side, or, when the caller
//! asks (`MultigridSystem::relative_stop`, the first step of the full resolution), once the
//! residual has fallen by a given factor from the warm start's. Cost and memory are
//! linear in the number of vertices.
//!
//! **Limits.** Strips of the mask separated by gaps of a pixel or two (a comb, a grille) are
//! joined by the coarse levels, which then cannot represent their independent bending: such
//! masks need hundreds of iterations ([`MAX_ITERATIONS`] at most). The automatic choice of
//! [`crate::global::GlobalStep`] switches those systems to the direct solver when they are small
//! enough (see [`crate::global::FALLBACK_ITERATIONS`]).

use crate::memory::{try_vec, try_with_capacity, try_zeros, Zeroable};
use faer::sparse::linalg::cholesky::SymmetricOrdering;
use faer::sparse::{SparseColMat, Triplet};
use faer::Par;
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::grid::{Grid, INACTIVE};
use crate::system::{faer_error, pinned_unknowns, prior_right_side, right_side, Cholesky, Prior};

/// Rows per Gauss-Seidel band.
pub const BAND: usize = 16;

/// Most conjugate-gradient iterations of one multigrid global step. Compact masks need 0 to 10; thin one-pixel strips
/// joined across gaps by the coarsening (a comb, a grid of lines) can need hundreds.
pub const MAX_ITERATIONS: usize = 500;

/// Largest number of active nodes of the coarsest level (factored directly).
pub const COARSEST_NODES: usize = 4096;

/// Elements per chunk of the deterministic parallel reductions.
const CHUNK: usize = 1 << 14;

/// Stencil offsets `(dr, dc)` in the order of a stencil's 9 coefficients (row-major over the
/// 3 x 3 neighbourhood).
const OFFSETS: [(isize, isize); 9] = [
    (-1, -1),
    (-1, 0),
    (-1, 1),
    (0, -1),
    (0, 0),
    (0, 1),
    (1, -1),
    (1, 0),
    (1, 1),
];

/// Index of the diagonal in a stencil.
const CENTRE: usize = 4;

/// Index of the inverse of the diagonal (0 for an inactive node), kept with the stencil so that
/// Gauss-Seidel multiplies instead of dividing.
const INVERSE: usize = 9;

/// The 9 coefficients of a node's row over its 3 x 3 neighbourhood (row-major), then the
/// inverse of the diagonal.
type Stencil = [f64; 10];

/// A coarse stencil as stored, in single precision (half the memory of the coarse levels):
/// the 8 neighbour coefficients in their places, at [`CENTRE`] the row sum `e = sum_k s_k`
/// (what the pins and the prior add to the diagonal; 0 up to rounding elsewhere) and at
/// [`INVERSE`] the inverse diagonal. The diagonal is recomputed as `e - sum_{k != centre}
/// s_k` from the rounded neighbours ([`unpack`]), so the stored operator stays symmetric
/// (both ends of an edge round the same value) and keeps constants in its null space away
/// from the pins exactly as the double-precision one does. The coarse levels only
/// precondition the conjugate gradients, which run in double precision: the rounding (a
/// relative 6e-8 per coefficient) changes how fast they converge, not what they converge to.
type Packed = [f32; 10];

/// The single-precision form of a coarse stencil (see [`Packed`]).
fn pack(s: &Stencil) -> Packed {
    let mut p = [0.0f32; 10];
    let mut sum = 0.0;
    for k in 0..9 {
        sum += s[k];
        if k != CENTRE {
            p[k] = s[k] as f32;
        }
    }
    p[CENTRE] = sum as f32;
    let centre = unpack(&p)[CENTRE];
    p[INVERSE] = if centre > 0.0 {
        (1.0 / centre) as f32
    } else {
        0.0
    };
    p
}

/// The double-precision stencil of a stored coarse stencil (see [`Packed`]).
#[inline(always)]
fn unpack(p: &Packed) -> Stencil {
    let mut s = [0.0; 10];
    let mut neighbours = 0.0;
    for k in 0..9 {
        if k != CENTRE {
            s[k] = f64::from(p[k]);
            neighbours += s[k];
        }
    }
    s[CENTRE] = f64::from(p[CENTRE]) - neighbours;
    s[INVERSE] = f64::from(p[INVERSE]);
    s
}

/// Sets a stencil's inverse diagonal from its diagonal.
fn with_inverse(mut s: Stencil) -> Stencil {
    s[INVERSE] = if s[CENTRE] > 0.0 {
        1.0 / s[CENTRE]
    } else {
        0.0
    };
    s
}

// SAFETY: zero bytes are arrays of 0.0.
unsafe impl Zeroable for Packed {
    const ZERO: Self = [0.0; 10];
}
// SAFETY: as above.
unsafe impl Zeroable for Element {
    const ZERO: Self = [[0.0; 4]; 4];
}

/// Corner offsets `(row, column)` of a cell in the order 00, 01, 10, 11.
const CORNERS: [(usize, usize); 4] = [(0, 0), (0, 1), (1, 0), (1, 1)];

/// Flag bits of a fine vertex: which of its 4 facets are masked, whether it is pinned, whether
/// it carries a prior.
const NW: u8 = 1;
const NE: u8 = 2;
const SW: u8 = 4;
const SE: u8 = 8;
const PINNED: u8 = 16;
const PRIOR: u8 = 32;

/// A node grid of `rows x cols` stored with a border of zeros (one row/column before, two
/// after), so that stencils and transfers never index out of range.
#[derive(Debug, Clone, Copy)]
struct Layout {
    rows: usize,
    cols: usize,
    stride: usize,
}

impl Layout {
    fn new(rows: usize, cols: usize) -> Layout {
        Layout {
            rows,
            cols,
            stride: cols + 3,
        }
    }

    /// Length of a padded vector.
    fn len(&self) -> usize {
        (self.rows + 3) * self.stride
    }

    /// Padded index of node (r, c).
    #[inline]
    fn index(&self, r: usize, c: usize) -> usize {
        (r + 1) * self.stride + c + 1
    }

    /// The level below: the nodes of the even rows and columns.
    fn coarser(&self) -> Layout {
        Layout::new(self.rows / 2 + 1, self.cols / 2 + 1)
    }
}

/// A symmetric 4 x 4 cell element.
type Element = [[f64; 4]; 4];

/// `Q_ab[j][i]`: the weight of coarse corner i at fine corner j of child cell (a, b).
fn interpolation(a: usize, b: usize) -> Element {
    let w = |x: usize, i: usize| match (x, i) {
        (0, 0) | (2, 1) => 1.0,
        (1, _) => 0.5,
        _ => 0.0,
    };
    let mut q = [[0.0; 4]; 4];
    for (j, &(jr, jc)) in CORNERS.iter().enumerate() {
        for (i, &(ir, ic)) in CORNERS.iter().enumerate() {
            q[j][i] = w(a + jr, ir) * w(b + jc, ic);
        }
    }
    q
}

/// `Q^T E Q`.
fn congruence(q: &Element, e: &Element) -> Element {
    let mut eq = [[0.0; 4]; 4];
    for j in 0..4 {
        for i in 0..4 {
            eq[j][i] = (0..4).map(|m| e[j][m] * q[m][i]).sum();
        }
    }
    let mut out = [[0.0; 4]; 4];
    for i in 0..4 {
        for k in 0..4 {
            out[i][k] = (0..4).map(|j| q[j][i] * eq[j][k]).sum();
        }
    }
    out
}

fn add_element(acc: &mut Element, e: &Element) {
    for (a, b) in acc.iter_mut().zip(e) {
        for (x, y) in a.iter_mut().zip(b) {
            *x += y;
        }
    }
}

/// The 9-point stencil of a fine vertex with flags `f` and prior weight `w`.
fn fine_stencil(f: u8, w: f64) -> Stencil {
    let b = |bit: u8| if f & bit != 0 { 1.0 } else { 0.0 };
    let (nw, ne, sw, se) = (b(NW), b(NE), b(SW), b(SE));
    with_inverse([
        -0.25 * nw,
        -0.25 * (nw + ne),
        -0.25 * ne,
        -0.25 * (nw + sw),
        0.75 * (nw + ne + sw + se) + b(PINNED) + w * b(PRIOR),
        -0.25 * (ne + se),
        -0.25 * sw,
        -0.25 * (sw + se),
        -0.25 * se,
        0.0,
    ])
}

/// The operator of one level: fine (stencils looked up from vertex flags) or coarse (stored).
enum Stencils {
    /// Flags of every vertex (row-major, unpadded) and the 64 stencils they select.
    Fine {
        flags: Vec<u8>,
        table: Box<[Stencil; 64]>,
    },
    /// The stencils of a coarse level (see [`CoarseStencils`]).
    Coarse(CoarseStencils),
}

impl Stencils {
    #[inline]
    fn get(&self, node: usize) -> Stencil {
        match self {
            Stencils::Fine { flags, table } => table[flags[node] as usize],
            Stencils::Coarse(s) => s.get(node),
        }
    }

    /// Whether `node` is active (its diagonal is positive).
    #[inline]
    fn active(&self, node: usize) -> bool {
        match self {
            Stencils::Fine { flags, table } => table[flags[node] as usize][INVERSE] > 0.0,
            Stencils::Coarse(s) => s.index[node] != INACTIVE_NODE,
        }
    }
}

/// [`CoarseStencils::index`] of an inactive node (its stencil is zero).
const INACTIVE_NODE: u32 = 0;

/// [`CoarseStencils::index`] of a node whose stencil is the level's interior stencil.
const PLAIN_NODE: u32 = 1;

/// The stencils of a coarse level in single precision (see [`Packed`]), stored once per kind:
/// away from the mask's border, the pins and the prior, the Galerkin products of identical
/// children are computed by the same operations on the same values, so every interior node
/// has bit for bit the same stencil (the level's `plain` one, computed from an interior cell);
/// only the other active nodes keep a stencil of their own. A V-cycle then
/// reads 4 bytes a coarse node (its index) instead of 40 (its stencil): the coarse levels
/// cost a fraction of what they did and take a tenth of the memory, with the same values.
struct CoarseStencils {
    /// Per node (row-major, unpadded): [`INACTIVE_NODE`], [`PLAIN_NODE`], or `2 + k` for the
    /// node's stencil `general[k]`.
    index: Vec<u32>,
    /// The stencils of the active nodes that are not plain, in node order.
    general: Vec<Packed>,
    /// The interior stencil (unpacked).
    plain: Stencil,
}

impl CoarseStencils {
    /// The stencil of `node` (zero for an inactive node).
    #[inline(always)]
    fn get(&self, node: usize) -> Stencil {
        match self.index[node] {
            INACTIVE_NODE => [0.0; 10],
            PLAIN_NODE => self.plain,
            k => unpack(&self.general[k as usize - 2]),
        }
    }
}

/// Classifies the packed stencils `stencils` of consecutive nodes into `index` (one entry a
/// node): inactive, bit for bit equal to `plain`, or general (pushed onto `general`, indexed
/// from 2 within this part: [`join_parts`] offsets them).
fn classify(
    stencils: impl Iterator<Item = Packed>,
    plain: &Packed,
    index: &mut [u32],
    general: &mut Vec<Packed>,
) {
    for (slot, p) in index.iter_mut().zip(stencils) {
        let active = p[INVERSE] > 0.0;
        *slot = if !active {
            INACTIVE_NODE
        } else if p.iter().zip(plain).all(|(a, b)| a.to_bits() == b.to_bits()) {
            PLAIN_NODE
        } else {
            general.push(p);
            2 + (general.len() - 1) as u32
        };
    }
}

/// The coarse stencils from the parts made by [`classify`] over consecutive chunks of
/// `chunk` nodes of `index`: the general stencils are joined in order and the indices offset.
fn join_parts(
    mut index: Vec<u32>,
    chunk: usize,
    parts: Vec<Vec<Packed>>,
    plain: &Packed,
) -> Result<CoarseStencils> {
    let total = parts.iter().map(Vec::len).sum();
    let mut general = try_with_capacity(total, "the multigrid levels")?;
    let mut offsets = Vec::with_capacity(parts.len());
    for part in parts {
        offsets.push(general.len() as u32);
        general.extend_from_slice(&part);
    }
    index
        .par_chunks_mut(chunk.max(1))
        .zip(offsets.par_iter())
        .for_each(|(index, &offset)| {
            for k in index.iter_mut().filter(|k| **k > PLAIN_NODE) {
                *k += offset;
            }
        });
    Ok(CoarseStencils {
        index,
        general,
        plain: unpack(plain),
    })
}

/// One level of the hierarchy: its node grid and operator.
struct Level {
    layout: Layout,
    stencils: Stencils,
    /// A padded row of zeros (see [`gauss_seidel`]).
    zeros: Vec<f64>,
}

impl Level {
    fn new(layout: Layout, stencils: Stencils) -> Result<Level> {
        Ok(Level {
            layout,
            stencils,
            zeros: try_zeros(layout.stride, "the multigrid levels")?,
        })
    }
}

impl Level {
    fn active_nodes(&self) -> usize {
        (0..self.layout.rows * self.layout.cols)
            .filter(|&n| self.stencils.active(n))
            .count()
    }
}

/// Work vectors of one level (padded): solution and right side (its residual is restricted
/// as it is computed, see [`restrict_residual`]).
struct Work {
    x: Vec<f64>,
    b: Vec<f64>,
}

impl Work {
    fn new(layout: Layout) -> Result<Work> {
        let n = layout.len();
        Ok(Work {
            x: try_zeros(n, "the multigrid levels")?,
            b: try_zeros(n, "the multigrid levels")?,
        })
    }
}

/// Calls `f` with the level's stencil lookup (node index -> stencil), monomorphized per kind.
/// `plain(n)` tells whether node n has the interior stencil of [`plain_apply`] (a fine vertex
/// whose 4 facets are all masked, neither pinned nor under a prior).
macro_rules! with_stencils {
    ($level:expr, |$get:ident, $plain:ident| $body:expr) => {
        match &$level.stencils {
            Stencils::Fine { flags, table } => {
                let $get = |n: usize| -> Stencil { table[flags[n] as usize] };
                let $plain = |n: usize| flags[n] == NW | NE | SW | SE;
                $body
            }
            Stencils::Coarse(stencils) => {
                let $get = |n: usize| -> Stencil { stencils.get(n) };
                let $plain = |_: usize| false;
                $body
            }
        }
    };
}

/// The interior fine stencil `3 x - (edge neighbours) / 2 - (diagonal neighbours) / 4` (four
/// masked facets) at padded column `j`, with the weights as constants.
#[inline(always)]
fn plain_apply(above: &[f64], here: &[f64], below: &[f64], j: usize) -> f64 {
    3.0 * here[j]
        - 0.5 * (above[j] + below[j] + here[j - 1] + here[j + 1])
        - 0.25 * (above[j - 1] + above[j + 1] + below[j - 1] + below[j + 1])
}

/// `s . x` over the 3 x 3 neighbourhood of padded column `j` in rows `above`, `here`, `below`.
#[inline(always)]
fn apply_stencil(s: &Stencil, above: &[f64], here: &[f64], below: &[f64], j: usize) -> f64 {
    s[0] * above[j - 1]
        + s[1] * above[j]
        + s[2] * above[j + 1]
        + s[3] * here[j - 1]
        + s[4] * here[j]
        + s[5] * here[j + 1]
        + s[6] * below[j - 1]
        + s[7] * below[j]
        + s[8] * below[j + 1]
}

/// `out = b - A x` (or `A x` when `b` is None) at the active nodes, 0 elsewhere. Returns
/// `x . out` (summed per row, rows in order: deterministic), which the conjugate gradients need
/// after `q = A p`.
fn residual(level: &Level, x: &[f64], b: Option<&[f64]>, out: &mut [f64]) -> f64 {
    let l = level.layout;
    with_stencils!(level, |get, plain| {
        let partial: Vec<f64> = out
            .par_chunks_mut(l.stride)
            .enumerate()
            .map(|(pr, row)| residual_row(&get, &plain, l, x, b, pr, row))
            .collect();
        partial.iter().sum()
    })
}

/// Padded row `pr` of [`residual`] into `row` (its nodes only: the padding is left as it is);
/// returns the row's part of `x . out` (0 for a padding row).
#[inline(always)]
fn residual_row(
    get: &impl Fn(usize) -> Stencil,
    plain: &impl Fn(usize) -> bool,
    l: Layout,
    x: &[f64],
    b: Option<&[f64]>,
    pr: usize,
    row: &mut [f64],
) -> f64 {
    if pr == 0 || pr > l.rows {
        return 0.0;
    }
    let stride = l.stride;
    let r = pr - 1;
    let above = &x[(pr - 1) * stride..pr * stride];
    let here = &x[pr * stride..(pr + 1) * stride];
    let below = &x[(pr + 1) * stride..(pr + 2) * stride];
    let base = r * l.cols;
    let row = &mut row[1..l.cols + 1];
    match b {
        Some(b) => {
            let b = &b[pr * stride + 1..pr * stride + 1 + l.cols];
            for (c, (o, &bc)) in row.iter_mut().zip(b).enumerate() {
                *o = if plain(base + c) {
                    bc - plain_apply(above, here, below, c + 1)
                } else {
                    let s = get(base + c);
                    let ax = apply_stencil(&s, above, here, below, c + 1);
                    if s[INVERSE] > 0.0 {
                        bc - ax
                    } else {
                        0.0
                    }
                };
            }
        }
        None => {
            for (c, o) in row.iter_mut().enumerate() {
                *o = if plain(base + c) {
                    plain_apply(above, here, below, c + 1)
                } else {
                    let s = get(base + c);
                    let ax = apply_stencil(&s, above, here, below, c + 1);
                    if s[INVERSE] > 0.0 {
                        ax
                    } else {
                        0.0
                    }
                };
            }
        }
    }
    row.iter().zip(&here[1..]).map(|(o, x)| o * x).sum::<f64>()
}

/// Coarse rows per task of [`restrict_residual`].
const RESTRICT_ROWS: usize = 8;

thread_local! {
    /// The fine residual rows of one task of [`restrict_residual`] (kept per thread, so that
    /// V-cycles do not allocate).
    static RESTRICT_BUFFER: std::cell::RefCell<Vec<f64>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// `b_coarse = P^T (b - A x)` at the active coarse nodes (the residual of `fine`, restricted)
/// without storing the fine residual: each task of [`RESTRICT_ROWS`] coarse rows computes the
/// `2 RESTRICT_ROWS + 1` fine residual rows they read into a buffer of its own (a row shared
/// by two tasks is computed by both, so the fine level needs no residual vector).
fn restrict_residual(fine: &Level, coarse: &Level, x: &[f64], b: &[f64], b_coarse: &mut [f64]) {
    let (lf, lc) = (fine.layout, coarse.layout);
    with_stencils!(fine, |get, plain| {
        b_coarse
            .par_chunks_mut(lc.stride * RESTRICT_ROWS)
            .enumerate()
            .for_each(|(task, rows)| {
                // Fine padded rows 2 pr_c - 2 .. 2 pr_c for coarse padded row pr_c (node row
                // pr_c - 1 sits on fine node row 2 pr_c - 2, padded 2 pr_c - 1).
                let first_c = task * RESTRICT_ROWS;
                let first_f = (2 * first_c).saturating_sub(2);
                RESTRICT_BUFFER.with_borrow_mut(|buffer| {
                    buffer.clear();
                    buffer.resize((2 * RESTRICT_ROWS + 1) * lf.stride, 0.0);
                    for (t, out) in buffer.chunks_exact_mut(lf.stride).enumerate() {
                        residual_row(&get, &plain, lf, x, Some(b), first_f + t, out);
                    }
                    for (t, row) in rows.chunks_exact_mut(lc.stride).enumerate() {
                        let pr = first_c + t;
                        if pr == 0 || pr > lc.rows {
                            continue;
                        }
                        let rr = pr - 1;
                        // Fine padded rows 2 rr, 2 rr + 1, 2 rr + 2 around the centre.
                        let top = 2 * rr - first_f;
                        for cc in 0..lc.cols {
                            row[cc + 1] = if coarse.stencils.active(rr * lc.cols + cc) {
                                let centre = 2 * cc + 1;
                                let mut sum = 0.0;
                                for (dr, wr) in [(0, 0.5), (1, 1.0), (2, 0.5)] {
                                    let f = &buffer[(top + dr) * lf.stride..];
                                    sum += wr
                                        * (0.5 * f[centre - 1] + f[centre] + 0.5 * f[centre + 1]);
                                }
                                sum
                            } else {
                                0.0
                            };
                        }
                    }
                })
            })
    });
}

/// A raw pointer shared by the Gauss-Seidel bands.
#[derive(Clone, Copy)]
struct Shared(*mut f64);
// SAFETY: the bands that run at the same time write disjoint rows and read only rows that no
// concurrent band writes (see `gauss_seidel`).
unsafe impl Send for Shared {}
unsafe impl Sync for Shared {}

/// One Gauss-Seidel sweep on `A x = b` over bands of [`BAND`] rows (see the module
/// documentation); `FORWARD` selects the direction and the order of the two band phases.
///
/// With `FROM_ZERO` (a forward sweep only), the sweep starts from `x = 0` whatever `x` holds:
/// the values it has not updated yet (the east neighbour, the row below within the band, and
/// the rows of the bands of the other phase before that phase) are read from a row of zeros,
/// and inactive nodes are set to zero. It computes what a forward sweep of a zeroed `x` does,
/// operation for operation, without the pass that zeroes it.
fn gauss_seidel<const FORWARD: bool, const FROM_ZERO: bool>(
    level: &Level,
    x: &mut [f64],
    b: &[f64],
) {
    const { assert!(FORWARD || !FROM_ZERO) };
    let (forward, from_zero) = (FORWARD, FROM_ZERO);
    let l = level.layout;
    let zeros = &level.zeros[..];
    assert_eq!(x.len(), l.len());
    assert_eq!(b.len(), l.len());
    let stride = l.stride;
    let bands = l.rows.div_ceil(BAND);
    let ptr = Shared(x.as_mut_ptr());
    let phases: [usize; 2] = if forward { [0, 1] } else { [1, 0] };
    with_stencils!(level, |get, plain| {
        for phase in phases {
            (0..bands)
                .into_par_iter()
                .filter(|band| band % 2 == phase)
                .for_each(|band| {
                    let p = ptr;
                    let rows = band * BAND..((band + 1) * BAND).min(l.rows);
                    let sweep_row = |r: usize| {
                        let pr = r + 1;
                        // SAFETY: rows pr - 1, pr, pr + 1 lie in the padded vector (one border
                        // row before the nodes, two after). Row pr belongs to this band, which
                        // only this thread writes; rows pr +- 1 belong to this band or to a
                        // band of the other phase, which no thread writes during this phase.
                        // The three rows are disjoint, and `here` is the only one written.
                        let (above, here, below) = unsafe {
                            (
                                std::slice::from_raw_parts(p.0.add((pr - 1) * stride), stride),
                                std::slice::from_raw_parts_mut(p.0.add(pr * stride), stride),
                                std::slice::from_raw_parts(p.0.add((pr + 1) * stride), stride),
                            )
                        };
                        let (above, below) = if from_zero {
                            // Rows of this band after `r`, and of the other phase's bands
                            // before that phase runs (phase 0 runs first), are not updated.
                            let first = r == rows.start && phase == 0;
                            let last = r + 1 == rows.end && phase == 1;
                            (
                                if first { zeros } else { above },
                                if last { below } else { zeros },
                            )
                        } else {
                            (above, below)
                        };
                        let b = &b[pr * stride..(pr + 1) * stride];
                        let base = r * l.cols;
                        // The neighbour along the sweep is the only term that depends on the
                        // previous update: it is added last, from a register, so that the
                        // dependency chain between nodes is one multiply-subtract-multiply.
                        // Forward sweeps take the west neighbour from the register and read the
                        // east one; backward sweeps the other way round.
                        let (behind, ahead) = if forward { (3, 5) } else { (5, 3) };
                        let mut previous = if forward { here[0] } else { here[l.cols + 1] };
                        for t in 0..l.cols {
                            let c = if forward { t } else { l.cols - 1 - t };
                            let j = c + 1;
                            let next = match (forward, from_zero) {
                                (_, true) => 0.0,
                                (true, false) => here[j + 1],
                                (false, _) => here[j - 1],
                            };
                            if plain(base + c) {
                                let rest = 0.5 * (above[j] + below[j] + next)
                                    + 0.25
                                        * (above[j - 1]
                                            + above[j + 1]
                                            + below[j - 1]
                                            + below[j + 1]);
                                here[j] = (b[j] + rest + 0.5 * previous) * (1.0 / 3.0);
                            } else {
                                let s = get(base + c);
                                if s[INVERSE] > 0.0 {
                                    let rest = s[0] * above[j - 1]
                                        + s[1] * above[j]
                                        + s[2] * above[j + 1]
                                        + s[ahead] * next
                                        + s[6] * below[j - 1]
                                        + s[7] * below[j]
                                        + s[8] * below[j + 1];
                                    here[j] = (b[j] - rest - s[behind] * previous) * s[INVERSE];
                                } else if from_zero {
                                    here[j] = 0.0;
                                }
                            }
                            previous = here[j];
                        }
                    };
                    if forward {
                        rows.clone().for_each(sweep_row);
                    } else {
                        rows.clone().rev().for_each(sweep_row);
                    }
                })
        }
    });
}

/// `x_fine += P x_coarse` at the active fine nodes. A fine node on an even row and column takes
/// its coarse node's value, one between two coarse nodes their mean, one between four the
/// quarter of their sum (added in the order of the rows, then the columns).
fn prolongate_add(fine: &Level, coarse: &Level, x_coarse: &[f64], x_fine: &mut [f64]) {
    let (lf, lc) = (fine.layout, coarse.layout);
    x_fine
        .par_chunks_mut(lf.stride)
        .enumerate()
        .for_each(|(pr, row)| {
            if pr == 0 || pr > lf.rows {
                return;
            }
            let r = pr - 1;
            let top = &x_coarse[lc.index(r / 2, 0)..][..lc.cols + 1];
            let bottom = &x_coarse[lc.index(r / 2 + r % 2, 0)..][..lc.cols + 1];
            let base = r * lf.cols;
            let row = &mut row[1..lf.cols + 1];
            let active = |c: usize| fine.stencils.active(base + c);
            if r % 2 == 0 {
                for (c, x) in row.iter_mut().enumerate() {
                    let (k, odd) = (c / 2, c % 2 == 1);
                    if active(c) {
                        *x += if odd {
                            0.5 * top[k] + 0.5 * top[k + 1]
                        } else {
                            top[k]
                        };
                    }
                }
            } else {
                for (c, x) in row.iter_mut().enumerate() {
                    let (k, odd) = (c / 2, c % 2 == 1);
                    if active(c) {
                        *x += if odd {
                            0.25 * top[k]
                                + 0.25 * top[k + 1]
                                + 0.25 * bottom[k]
                                + 0.25 * bottom[k + 1]
                        } else {
                            0.5 * top[k] + 0.5 * bottom[k]
                        };
                    }
                }
            }
        });
}

/// Deterministic parallel dot product (fixed chunks, summed in order).
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let partial: Vec<f64> = a
        .par_chunks(CHUNK)
        .zip(b.par_chunks(CHUNK))
        .map(|(x, y)| x.iter().zip(y).map(|(p, q)| p * q).sum())
        .collect();
    partial.iter().sum()
}

/// Writes per-unknown `values` onto the padded grid `out` (0 at inactive nodes and padding).
fn to_grid(layout: Layout, grid: &Grid, values: &[f64], out: &mut [f64]) {
    let vw = grid.width + 1;
    out.par_chunks_mut(layout.stride)
        .enumerate()
        .for_each(|(pr, row)| {
            if pr == 0 || pr > layout.rows {
                row.fill(0.0);
                return;
            }
            let r = pr - 1;
            row[0] = 0.0;
            for (c, o) in row[1..].iter_mut().enumerate() {
                *o = if c < layout.cols {
                    let u = grid.vertex_unknown[r * vw + c];
                    if u == INACTIVE {
                        0.0
                    } else {
                        values[u as usize]
                    }
                } else {
                    0.0
                };
            }
        });
}

/// Reads the per-unknown `values` off the padded grid `x` (the inverse of [`to_grid`]). The
/// padded index of each unknown is computed from its vertex, not stored: one division per
/// chunk of unknowns, then row by row (the unknowns' vertices increase).
fn from_grid(layout: Layout, grid: &Grid, x: &[f64], values: &mut [f64]) {
    let vw = grid.width + 1;
    values
        .par_chunks_mut(CHUNK)
        .zip(grid.active.par_chunks(CHUNK))
        .for_each(|(values, vertices)| {
            let Some(&first) = vertices.first() else {
                return;
            };
            let mut row = first as usize / vw;
            let mut row_start = row * vw;
            for (o, &v) in values.iter_mut().zip(vertices) {
                let v = v as usize;
                while v >= row_start + vw {
                    row += 1;
                    row_start += vw;
                }
                *o = x[layout.index(row, v - row_start)];
            }
        });
}

/// The conjugate-gradient step `x += alpha p`, `r -= alpha q` in one pass; returns `r . r`
/// (deterministic: fixed chunks summed in order).
fn step_and_norm(alpha: f64, p: &[f64], q: &[f64], x: &mut [f64], r: &mut [f64]) -> f64 {
    let partial: Vec<f64> = x
        .par_chunks_mut(CHUNK)
        .zip(r.par_chunks_mut(CHUNK))
        .zip(p.par_chunks(CHUNK).zip(q.par_chunks(CHUNK)))
        .map(|((x, r), (p, q))| {
            let mut rr = 0.0;
            for (((x, r), p), q) in x.iter_mut().zip(r.iter_mut()).zip(p).zip(q) {
                *x += alpha * p;
                *r -= alpha * q;
                rr += *r * *r;
            }
            rr
        })
        .collect();
    partial.iter().sum()
}

/// The coarsest level, factored directly.
struct Coarsest {
    chol: Cholesky,
    /// Padded index of each active node (the unknowns of the factored matrix).
    nodes: Vec<usize>,
    rhs: Vec<f64>,
}

impl Coarsest {
    fn new(level: &Level) -> Result<Coarsest> {
        // The coarsest level is small, except when the image has at most 3 rows or columns and
        // the fine level is also the coarsest: O(pixels), so allocated fallibly.
        const WHAT: &str = "the coarsest multigrid level";
        let l = level.layout;
        let mut number = try_vec(l.rows * l.cols, u32::MAX, WHAT)?;
        let active = (0..l.rows * l.cols)
            .filter(|&n| level.stencils.active(n))
            .count();
        let mut nodes = try_with_capacity(active, WHAT)?;
        for (n, slot) in number.iter_mut().enumerate() {
            if level.stencils.active(n) {
                *slot = nodes.len() as u32;
                nodes.push(l.index(n / l.cols, n % l.cols));
            }
        }
        // At most the centre and half of the neighbours of each node in the lower triangle.
        let mut triplets = try_with_capacity(active * OFFSETS.len().div_ceil(2), WHAT)?;
        for n in 0..l.rows * l.cols {
            let s = level.stencils.get(n);
            if s[CENTRE] <= 0.0 {
                continue;
            }
            let (r, c) = ((n / l.cols) as isize, (n % l.cols) as isize);
            for (k, &(dr, dc)) in OFFSETS.iter().enumerate() {
                let (rr, cc) = (r + dr, c + dc);
                if s[k] == 0.0 || rr < 0 || cc < 0 || rr >= l.rows as isize || cc >= l.cols as isize
                {
                    continue;
                }
                let m = number[rr as usize * l.cols + cc as usize];
                let i = number[n];
                if m != u32::MAX && m <= i {
                    triplets.push(Triplet::new(i as usize, m as usize, s[k]));
                }
            }
        }
        let n = nodes.len();
        let lower = SparseColMat::try_new_from_triplets(n, n, &triplets).map_err(|e| match e {
            faer::sparse::CreationError::Generic(e) => {
                faer_error(e, WHAT, "cannot assemble the coarsest multigrid level")
            }
            e => Error::Solver(format!(
                "cannot assemble the coarsest multigrid level: {e:?}"
            )),
        })?;
        drop(triplets);
        let chol = Cholesky::new(lower, SymmetricOrdering::Amd, Par::Seq)?;
        Ok(Coarsest {
            chol,
            rhs: try_vec(n, 0.0, WHAT)?,
            nodes,
        })
    }

    /// `x = A^-1 b` at the active nodes.
    fn solve(&mut self, b: &[f64], x: &mut [f64]) {
        for (v, &i) in self.rhs.iter_mut().zip(&self.nodes) {
            *v = b[i];
        }
        self.chol.solve_in_place(&mut self.rhs);
        for (&v, &i) in self.rhs.iter().zip(&self.nodes) {
            x[i] = v;
        }
    }
}

/// Vectors of the conjugate gradients on the fine padded grid: `x`, and `r`, `p` and `w` side by
/// side in one buffer, which may be memory the solver lent between its local steps (its
/// targets, see [`MultigridSystem::lend`]). `w` holds the preconditioned residual `z = M r` until
/// the search direction `p` is updated from it, then `q = A p` until the next preconditioning:
/// the two are never needed at the same time.
#[derive(Default)]
struct Krylov {
    x: Vec<f64>,
    /// `r`, `p` and `w`, a padded vector each, or empty; `r` and `w` trade places at the start
    /// of each solve (`swapped`).
    rpw: Vec<f64>,
    swapped: bool,
    /// Whether `rpw` is lent (see [`MultigridSystem::lend`]), to be given back.
    lent: bool,
    /// Whether `rpw` holds the lender's values (until the next solve zeroes its `w`).
    unzeroed: bool,
}

impl Krylov {
    /// Zeroed vectors of `n` values.
    fn new(n: usize) -> Result<Krylov> {
        Ok(Krylov {
            x: try_zeros(n, "the conjugate gradients' vectors")?,
            rpw: try_zeros(3 * n, "the conjugate gradients' vectors")?,
            ..Krylov::default()
        })
    }

    /// `(x, r, p, w)`.
    fn parts(&mut self) -> (&mut [f64], &mut [f64], &mut [f64], &mut [f64]) {
        let n = self.x.len();
        let (a, rest) = self.rpw[..3 * n].split_at_mut(n);
        let (p, b) = rest.split_at_mut(n);
        let (r, w) = if self.swapped { (b, a) } else { (a, b) };
        (&mut self.x, r, p, w)
    }
}

/// The multigrid-preconditioned global system of one mask (see the module documentation).
pub struct MultigridSystem {
    levels: Vec<Level>,
    /// Work vectors of the levels below the fine one (`work[l - 1]` for level l).
    work: Vec<Work>,
    coarsest: Coarsest,
    krylov: Krylov,
    pins: Vec<u32>,
    prior_rhs: Option<Vec<f64>>,
    /// Stop when `|b - A u| <= rtol |b_t|`.
    pub rtol: f64,
    /// Most conjugate-gradient iterations per solve.
    pub max_iterations: usize,
    /// Also stop when `|b - A u| <= relative_stop |b - A u_0|`, `u_0` the warm start (0: only
    /// by `rtol`): for a step whose targets the next local step replaces anyway (see
    /// `solver::FIRST_STEP_REDUCTION`).
    pub relative_stop: f64,
    /// Checked at every conjugate-gradient iteration: once cancelled, the solve stops early
    /// (the caller checks the token and discards the step).
    pub cancel: crate::Cancel,
}

impl MultigridSystem {
    /// Builds the hierarchy of `grid`'s system (with its pins and optional prior) and factors
    /// the coarsest level.
    pub fn new(grid: &Grid, prior: Option<&Prior>) -> Result<MultigridSystem> {
        MultigridSystem::with_coarsest(grid, prior, COARSEST_NODES)
    }

    /// As [`MultigridSystem::new`], coarsening until a level has at most `coarsest_nodes`
    /// active nodes (or fewer than 4 rows or columns).
    pub fn with_coarsest(
        grid: &Grid,
        prior: Option<&Prior>,
        coarsest_nodes: usize,
    ) -> Result<MultigridSystem> {
        let pins = pinned_unknowns(grid, prior)?;
        let layout = Layout::new(grid.height + 1, grid.width + 1);
        let vw = grid.width + 1;
        let mut flags: Vec<u8> =
            try_zeros(layout.rows * layout.cols, "the multigrid's fine level")?;
        // Row by row of vertices in parallel: vertex (r, c) is the NW corner (flag SE) of facet
        // (r, c), the NE corner (SW) of (r, c - 1), the SW corner (NE) of (r - 1, c) and the SE
        // corner (NW) of (r - 1, c - 1), where those pixels are facets.
        let (h, w) = (grid.height, grid.width);
        let facet =
            |r: usize, c: usize| r < h && c < w && grid.facet_of_pixel(r * w + c) != INACTIVE;
        flags.par_chunks_mut(vw).enumerate().for_each(|(r, row)| {
            for (c, f) in row.iter_mut().enumerate() {
                let (up, left) = (r.wrapping_sub(1), c.wrapping_sub(1));
                let bit = |on: bool, flag: u8| if on { flag } else { 0 };
                *f = bit(facet(r, c), SE)
                    | bit(facet(r, left), SW)
                    | bit(facet(up, c), NE)
                    | bit(facet(up, left), NW);
            }
        });
        for &p in &pins {
            flags[grid.active[p as usize] as usize] |= PINNED;
        }
        let mut weight = 0.0;
        if let Some(prior) = prior {
            weight = prior.weight;
            for (u, v) in prior.values.iter().enumerate() {
                if v.is_finite() {
                    flags[grid.active[u] as usize] |= PRIOR;
                }
            }
        }
        let table: Box<[Stencil; 64]> =
            Box::new(std::array::from_fn(|f| fine_stencil(f as u8, weight)));

        let mut levels = vec![Level::new(layout, Stencils::Fine { flags, table })?];
        let mut cells: Option<Vec<Element>> = None;
        // The interior cell of the last level made (see [`CoarseStencils`]).
        let mut interior = FineCells::new(&levels[0], weight).interior();
        loop {
            let last = levels.last().expect("at least the fine level");
            let l = last.layout;
            if l.rows <= 3 || l.cols <= 3 || last.active_nodes() <= coarsest_nodes {
                break;
            }
            let layout = l.coarser();
            // `cells`: the cells of the new level (after level 1), whose stencils they give,
            // and from which the cells of the level below it are made.
            let coarser = layout.rows > 3 && layout.cols > 3;
            let (stencils, next) = match cells.take() {
                // Level 1 straight from the fine flags, with the level-2 cells.
                None if levels.len() == 1 => first_coarse_level(last, weight, coarser)?,
                None => break,
                Some(c) => {
                    interior = coarser_interior(&interior);
                    let stencils = stencils_of(layout, &c, &plain_stencil(&interior))?;
                    let next = match coarser {
                        true => Some(coarsen_cells(layout, &c)?),
                        false => None,
                    };
                    (stencils, next)
                }
            };
            levels.push(Level::new(layout, Stencils::Coarse(stencils))?);
            cells = next;
        }
        drop(cells);
        let coarsest = Coarsest::new(levels.last().expect("at least the fine level"))?;
        let work = levels[1..]
            .iter()
            .map(|l| Work::new(l.layout))
            .collect::<Result<Vec<Work>>>()?;
        Ok(MultigridSystem {
            levels,
            work,
            coarsest,
            krylov: Krylov::new(layout.len())?,
            pins,
            prior_rhs: prior_right_side(prior)?,
            rtol: 1e-6,
            max_iterations: MAX_ITERATIONS,
            relative_stop: 0.0,
            cancel: crate::Cancel::default(),
        })
    }

    /// Gives back the work vectors: the conjugate gradients' four on the fine padded grid and
    /// the two of each coarser level (`8 (4 + 2/4 + 2/16 + ...)`, about 37 bytes a vertex).
    /// [`MultigridSystem::reserve_work`] allocates them again (zero pages, touched as the solve
    /// runs); no solve reads what a previous one left in them. The solver gives them back
    /// between its global steps, so that they and the local step's buffers are never held at
    /// once (see [`crate::global::GlobalStep::release_work`]). Lent memory must have been
    /// taken back first ([`MultigridSystem::take_back`]).
    pub fn release_work(&mut self) {
        debug_assert!(!self.krylov.lent);
        self.krylov = Krylov::default();
        for w in &mut self.work {
            *w = Work {
                x: Vec::new(),
                b: Vec::new(),
            };
        }
    }

    /// Takes `buffer` (memory the caller does not need until [`MultigridSystem::take_back`];
    /// its values are not read) as the conjugate gradients' `r`, `p` and `w`, in place of the
    /// system's own, when it can hold them (three padded vectors) and none is lent already;
    /// returns whether it did (else the buffer is left as it is). The solver lends its targets, dead from the right side
    /// ([`MultigridSystem::right_side`]) to the next local step: those three vectors are then
    /// never allocated, and a run holds 24 bytes a vertex less at its peak (the first global
    /// step of the full resolution: about 0.28 GB at 12 MP) and touches no fresh page for them.
    pub fn lend(&mut self, buffer: &mut Vec<f64>) -> bool {
        let values = 3 * self.levels[0].layout.len();
        if self.krylov.lent || buffer.capacity() < values {
            return false;
        }
        let mut rpw = std::mem::take(buffer);
        // (within the capacity: truncates, or writes zeros after the old values)
        rpw.resize(values, 0.0);
        // (the system's own, if any, is freed: its pages untouched since `new`, or released)
        self.krylov.rpw = rpw;
        self.krylov.swapped = false;
        self.krylov.lent = true;
        self.krylov.unzeroed = true;
        true
    }

    /// Gives back the buffer taken by [`MultigridSystem::lend`] (None if none was), its
    /// length as lent or shorter, its values the solve's.
    pub fn take_back(&mut self) -> Option<Vec<f64>> {
        if !std::mem::take(&mut self.krylov.lent) {
            return None;
        }
        Some(std::mem::take(&mut self.krylov.rpw))
    }

    /// The conjugate gradients' vectors (empty when given back, see
    /// [`MultigridSystem::release_work`]), the rest of the system freed: buffers of at least
    /// the padded node count (more than the grid's vertices), for maps written whole once the
    /// solves are done (see [`crate::memory::values_on`]).
    pub(crate) fn into_spare(self) -> Vec<Vec<f64>> {
        let Krylov { x, rpw, .. } = self.krylov;
        vec![rpw, x]
    }

    /// Allocates the work vectors given back by [`MultigridSystem::release_work`] (those not
    /// there, or lent); `MultigridSystem::solve` (tests) needs them.
    pub fn reserve_work(&mut self) -> Result<()> {
        let n = self.levels[0].layout.len();
        if self.krylov.x.is_empty() {
            self.krylov.x = try_zeros(n, "the conjugate gradients' vectors")?;
        }
        if self.krylov.rpw.is_empty() {
            self.krylov.rpw = try_zeros(3 * n, "the conjugate gradients' vectors")?;
            self.krylov.swapped = false;
        }
        for (w, level) in self.work.iter_mut().zip(&self.levels[1..]) {
            if w.x.is_empty() {
                *w = Work::new(level.layout)?;
            }
        }
        Ok(())
    }

    /// Number of levels (the fine level included).
    #[cfg(test)]
    pub fn n_levels(&self) -> usize {
        self.levels.len()
    }

    /// `z ~ A^-1 r` by one V-cycle from a zero start, into `w`.
    fn precondition(&mut self) {
        let (_, r, _, w) = self.krylov.parts();
        vcycle(&self.levels, &mut self.work, &mut self.coarsest, 0, w, r);
    }

    /// One global step (as [`crate::global::GlobalSystem::solve`]): solves the pinned system
    /// for the facets' `targets` from the warm start `z_current`, writing `z_out`. Returns the
    /// number of conjugate-gradient iterations. The work vectors must be there (after
    /// [`MultigridSystem::release_work`], [`MultigridSystem::reserve_work`] first).
    #[cfg(test)]
    pub fn solve(
        &mut self,
        grid: &Grid,
        targets: &[[f64; 4]],
        z_current: &[f64],
        z_out: &mut [f64],
    ) -> usize {
        let target_norm = self.right_side(grid, targets, z_current, z_out);
        self.solve_from(grid, target_norm, z_current, z_out)
    }

    /// The right side of `MultigridSystem::solve` (tests) per unknown into `out`; returns the norm of
    /// its target part (see [`right_side`]).
    pub fn right_side(
        &self,
        grid: &Grid,
        targets: &[[f64; 4]],
        z_current: &[f64],
        out: &mut [f64],
    ) -> f64 {
        let prior = self.prior_rhs.as_deref();
        right_side(grid, targets, &self.pins, prior, z_current, out)
    }

    /// `MultigridSystem::solve` (tests) from its right side in `z` ([`MultigridSystem::right_side`],
    /// whose norm is `target_norm`), which the solution then replaces: the targets are not
    /// read, so the caller may give them back before the work vectors are reserved.
    pub fn solve_from(
        &mut self,
        grid: &Grid,
        target_norm: f64,
        z_current: &[f64],
        z_out: &mut [f64],
    ) -> usize {
        let fine = &self.levels[0];
        // Lent memory holds other values: `w` gets only the residual's nodes below, and its
        // padding (and inactive nodes) must be zero, as fresh vectors and every solve leave it.
        if std::mem::take(&mut self.krylov.unzeroed) {
            let (_, _, _, w) = self.krylov.parts();
            w.par_chunks_mut(CHUNK).for_each(|w| w.fill(0.0));
        }
        let (x, r, _, w) = self.krylov.parts();
        to_grid(fine.layout, grid, z_out, r);
        let scale = if target_norm > 0.0 {
            target_norm
        } else {
            dot(r, r).sqrt()
        };
        let tol = self.rtol * scale;
        to_grid(fine.layout, grid, z_current, x);
        // r = b - A x into `w`, then swapped: the residual writes the nodes only, and the
        // padding of both vectors is zero (`to_grid` wrote it in `r`, nothing writes it in `w`).
        residual(fine, x, Some(r), w);
        self.krylov.swapped = !self.krylov.swapped;
        let mut iterations = 0;
        let (_, r, _, _) = self.krylov.parts();
        let start = dot(r, r).sqrt();
        let tol = tol.max(self.relative_stop * start);
        if start > tol {
            self.precondition();
            let (_, r, p, w) = self.krylov.parts();
            p.copy_from_slice(w);
            let mut rz = dot(r, w);
            while iterations < self.max_iterations && !self.cancel.is_cancelled() {
                iterations += 1;
                let (x, r, p, w) = self.krylov.parts();
                let pq = residual(&self.levels[0], p, None, w);
                if pq.is_nan() || pq <= 0.0 {
                    break;
                }
                let alpha = rz / pq;
                if step_and_norm(alpha, p, w, x, r).sqrt() <= tol {
                    break;
                }
                self.precondition();
                let (_, r, p, w) = self.krylov.parts();
                let rz_new = dot(r, w);
                let beta = rz_new / rz;
                rz = rz_new;
                p.par_chunks_mut(CHUNK)
                    .zip(w.par_chunks(CHUNK))
                    .for_each(|(p, z)| p.iter_mut().zip(z).for_each(|(p, z)| *p = z + beta * *p));
            }
        }
        from_grid(self.levels[0].layout, grid, &self.krylov.x, z_out);
        iterations
    }
}

/// One V-cycle on level `l` from a zero start: `x ~ A_l^-1 b`; `work` holds the work vectors
/// of the levels below it.
fn vcycle(
    levels: &[Level],
    work: &mut [Work],
    coarsest: &mut Coarsest,
    l: usize,
    x: &mut [f64],
    b: &[f64],
) {
    if l + 1 == levels.len() {
        x.fill(0.0);
        coarsest.solve(b, x);
        return;
    }
    let (fine, coarse) = (&levels[l], &levels[l + 1]);
    gauss_seidel::<true, true>(fine, x, b);
    let (here, below) = work.split_first_mut().expect("a coarser level");
    restrict_residual(fine, coarse, x, b, &mut here.b);
    vcycle(levels, below, coarsest, l + 1, &mut here.x, &here.b);
    prolongate_add(fine, coarse, &here.x, x);
    gauss_seidel::<false, false>(fine, x, b);
}

/// The 4 x 4 interpolation matrices of the 4 child cells, indexed `2 a + b`.
fn interpolations() -> [Element; 4] {
    std::array::from_fn(|ab| interpolation(ab / 2, ab % 2))
}

/// What the level-1 cells are made from: the fine vertex flags, the interpolation matrices, the
/// facet element seen from the coarse corners per child position, and the prior's weight.
struct FineCells<'a> {
    flags: &'a [u8],
    layout: Layout,
    q: [Element; 4],
    facet: [Element; 4],
    weight: f64,
}

impl FineCells<'_> {
    fn new(fine: &Level, weight: f64) -> FineCells<'_> {
        let Stencils::Fine { flags, .. } = &fine.stencils else {
            unreachable!("the level-1 cells come from the fine level")
        };
        let q = interpolations();
        // The facet element N = I - ones/4 seen from the coarse corners, per child position.
        let mut facet = [[[0.0; 4]; 4]; 4];
        let n: Element = std::array::from_fn(|i| std::array::from_fn(|j| f64::from(i == j) - 0.25));
        for (ab, g) in facet.iter_mut().enumerate() {
            *g = congruence(&q[ab], &n);
        }
        FineCells {
            flags,
            layout: fine.layout,
            q,
            facet,
            weight,
        }
    }

    /// The level-1 cell of four masked facets without pins or prior, made as [`FineCells::cell`]
    /// makes it.
    fn interior(&self) -> Element {
        let mut cell: Element = [[0.0; 4]; 4];
        for facet in &self.facet {
            add_element(&mut cell, facet);
        }
        cell
    }

    /// The Galerkin element of level-1 cell (cr, cc) from its (up to 4) fine facets, with the
    /// pins' and the prior's diagonal terms folded into one facet of each vertex: the first
    /// masked one among its NW, NE, SW, SE facets.
    #[inline]
    fn cell(&self, cr: usize, cc: usize) -> Element {
        let (l, flags) = (self.layout, self.flags);
        let (h, w) = (l.rows - 1, l.cols - 1);
        // Which facet bit of corner j's vertex facet (r, c) is (corner 00 sees it as SE, ...).
        let bit_of_corner = [SE, SW, NE, NW];
        let mut cell: Element = [[0.0; 4]; 4];
        for (ab, qab) in self.q.iter().enumerate() {
            let (r, c) = (2 * cr + ab / 2, 2 * cc + ab % 2);
            if r >= h || c >= w || flags[r * l.cols + c] & SE == 0 {
                continue;
            }
            add_element(&mut cell, &self.facet[ab]);
            for (j, &(jr, jc)) in CORNERS.iter().enumerate() {
                let f = flags[(r + jr) * l.cols + c + jc];
                let extra = f64::from(f & PINNED != 0) + self.weight * f64::from(f & PRIOR != 0);
                let first = 1u8 << (f & 15).trailing_zeros();
                if extra != 0.0 && first == bit_of_corner[j] {
                    for i in 0..4 {
                        for k in 0..4 {
                            cell[i][k] += extra * qab[j][i] * qab[j][k];
                        }
                    }
                }
            }
        }
        cell
    }
}

/// Level-1 rows per task of [`first_coarse_level`] (even: a task makes whole level-2 rows).
const SETUP_ROWS: usize = 32;

/// The stencils of level 1 and, when `coarser` (level 1 has a coarser level), the Galerkin
/// elements of the level-2 cells, without storing the level-1 cells (32 bytes a fine pixel,
/// the largest transient of the set-up): each task of [`SETUP_ROWS`] level-1 node rows computes
/// the level-1 cells they touch (a row of cells shared with the task above is computed by both)
/// and makes its stencils and the level-2 cells over its rows from them.
fn first_coarse_level(
    fine: &Level,
    weight: f64,
    coarser: bool,
) -> Result<(CoarseStencils, Option<Vec<Element>>)> {
    let cells = FineCells::new(fine, weight);
    let plain = plain_stencil(&cells.interior());
    let layout = fine.layout.coarser();
    let (h, w) = (layout.rows - 1, layout.cols - 1);
    let mut index = try_vec(layout.rows * layout.cols, 0u32, "the multigrid levels")?;
    let below = layout.coarser();
    let (h2, w2) = (below.rows - 1, below.cols - 1);
    let mut next = match coarser {
        true => Some(try_zeros(h2 * w2, "the multigrid levels")?),
        false => None,
    };
    let q = interpolations();
    let mut next_chunks = next
        .as_mut()
        .map(|n| n.chunks_mut((SETUP_ROWS / 2) * w2.max(1)));
    let chunk = SETUP_ROWS * layout.cols;
    let tasks: Vec<(&mut [u32], Option<&mut [Element]>)> = index
        .chunks_mut(chunk)
        .map(|s| (s, next_chunks.as_mut().and_then(|c| c.next())))
        .collect();
    let parts: Vec<Vec<Packed>> = tasks
        .into_par_iter()
        .enumerate()
        .map(|(task, (index_rows, next_rows))| {
            let first = task * SETUP_ROWS;
            let rows = index_rows.len() / layout.cols;
            // Level-1 cell rows first - 1 .. first + rows (within 0..h).
            let top = first.saturating_sub(1);
            let end = (first + rows).min(h);
            let mut local = Vec::with_capacity((end.saturating_sub(top)) * w);
            for cr in top..end {
                for cc in 0..w {
                    local.push(cells.cell(cr, cc));
                }
            }
            let cell = |r: usize, c: usize| -> Option<&Element> {
                (r >= top && r < end && c < w).then(|| &local[(r - top) * w + c])
            };
            let mut general = Vec::new();
            let stencils = (0..rows * layout.cols)
                .map(|n| pack(&stencil_at(first + n / layout.cols, n % layout.cols, &cell)));
            classify(stencils, &plain, index_rows, &mut general);
            if let Some(next_rows) = next_rows {
                for (t, out) in next_rows.chunks_exact_mut(w2).enumerate() {
                    let r2 = first / 2 + t;
                    for (c2, out) in out.iter_mut().enumerate() {
                        *out = coarse_cell(r2, c2, &q, &cell);
                    }
                }
            }
            general
        })
        .collect();
    Ok((join_parts(index, chunk, parts, &plain)?, next))
}

/// The packed stencil of a node whose 4 cells are all `cell` (made as [`stencil_at`] makes
/// every node's, so that the interior nodes' stencils equal it bit for bit).
fn plain_stencil(cell: &Element) -> Packed {
    pack(&stencil_at(1, 1, &|_, _| Some(cell)))
}

/// The interior cell of the level below that of the interior cell `cell` (made as
/// [`coarse_cell`] makes every cell's).
fn coarser_interior(cell: &Element) -> Element {
    coarse_cell(0, 0, &interpolations(), &|_, _| Some(cell))
}

/// The Galerkin element of cell (cr, cc) of the next level from the cells of this one
/// (`cell(r, c)`: None outside the level).
#[inline]
fn coarse_cell<'e>(
    cr: usize,
    cc: usize,
    q: &[Element; 4],
    cell: &impl Fn(usize, usize) -> Option<&'e Element>,
) -> Element {
    let mut out: Element = [[0.0; 4]; 4];
    for (ab, qab) in q.iter().enumerate() {
        let (r, c) = (2 * cr + ab / 2, 2 * cc + ab % 2);
        let Some(child) = cell(r, c) else {
            continue;
        };
        if child[0][0] == 0.0 && child[3][3] == 0.0 && child[1][1] == 0.0 {
            continue;
        }
        add_element(&mut out, &congruence(qab, child));
    }
    out
}

/// Galerkin elements of the next level's cells from the cells of a level with `layout`.
fn coarsen_cells(layout: Layout, cells: &[Element]) -> Result<Vec<Element>> {
    let (h, w) = (layout.rows - 1, layout.cols - 1);
    let coarse = layout.coarser();
    let (ch, cw) = (coarse.rows - 1, coarse.cols - 1);
    let q = interpolations();
    let cell = |r: usize, c: usize| (r < h && c < w).then(|| &cells[r * w + c]);
    let mut out = try_zeros(ch * cw, "the multigrid levels")?;
    out.par_chunks_mut(cw).enumerate().for_each(|(cr, row)| {
        for (cc, out) in row.iter_mut().enumerate() {
            *out = coarse_cell(cr, cc, &q, &cell);
        }
    });
    Ok(out)
}

/// The nodal 9-point stencil of node (r, c) from the cells around it (`cell(r, c)`: None
/// outside the level).
#[inline]
fn stencil_at<'e>(
    r: usize,
    c: usize,
    cell: &impl Fn(usize, usize) -> Option<&'e Element>,
) -> Stencil {
    let mut s: Stencil = [0.0; 10];
    // Cell (r - 1 + jr', c - 1 + jc') holds this node as its corner (1 - jr', 1 - jc').
    for (cell_r, cell_c, j) in [
        (r.wrapping_sub(1), c.wrapping_sub(1), 3),
        (r.wrapping_sub(1), c, 2),
        (r, c.wrapping_sub(1), 1),
        (r, c, 0),
    ] {
        let Some(e) = cell(cell_r, cell_c) else {
            continue;
        };
        let (jr, jc) = CORNERS[j];
        for (m, &(mr, mc)) in CORNERS.iter().enumerate() {
            let k = (mr + 1 - jr) * 3 + (mc + 1 - jc);
            s[k] += e[j][m];
        }
    }
    s
}

/// The nodal 9-point stencils of a level with `layout` from its cell elements, `plain` being
/// the stencil of its interior nodes (see [`CoarseStencils`]).
fn stencils_of(layout: Layout, cells: &[Element], plain: &Packed) -> Result<CoarseStencils> {
    let (rows, cols) = (layout.rows, layout.cols);
    let (h, w) = (rows - 1, cols - 1);
    let cell = |r: usize, c: usize| (r < h && c < w).then(|| &cells[r * w + c]);
    let mut index = try_vec(rows * cols, 0u32, "the multigrid levels")?;
    let parts: Vec<Vec<Packed>> = index
        .par_chunks_mut(cols)
        .enumerate()
        .map(|(r, row)| {
            let mut general = Vec::new();
            let stencils = (0..cols).map(|c| pack(&stencil_at(r, c, &cell)));
            classify(stencils, plain, row, &mut general);
            general
        })
        .collect();
    join_parts(index, cols, parts, plain)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// Deterministic pseudo-random numbers in [0, 1).
    pub(crate) fn lcg(seed: u64) -> impl FnMut() -> f64 {
        let mut s = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        move || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    /// Random targets (mean-subtracted per facet) and a random current state.
    pub(crate) fn problem_data(grid: &Grid, seed: u64) -> (Vec<[f64; 4]>, Vec<f64>) {
        let mut rand = lcg(seed);
        let targets = grid
            .all_facet_vertices()
            .map(|_| {
                let t: [f64; 4] = std::array::from_fn(|_| rand() - 0.5);
                let m = t.iter().sum::<f64>() / 4.0;
                t.map(|v| v - m)
            })
            .collect();
        let current = (0..grid.n_unknowns()).map(|_| 100.0 + rand()).collect();
        (targets, current)
    }

    /// Masks that stress the hierarchy: holes, thin strips, many islands, single pixels.
    pub(crate) fn masks(h: usize, w: usize) -> Vec<(&'static str, Vec<bool>)> {
        let full = vec![true; h * w];
        let disc: Vec<bool> = (0..h * w)
            .map(|p| {
                let (r, c) = (
                    (p / w) as f64 - h as f64 / 2.0,
                    (p % w) as f64 - w as f64 / 2.0,
                );
                let d = (r * r + c * c).sqrt();
                d < 0.45 * h.min(w) as f64 && d > 0.15 * h.min(w) as f64
            })
            .collect();
        let strips: Vec<bool> = (0..h * w)
            .map(|p| (p / w).is_multiple_of(4) || p % w == 3)
            .collect();
        let islands: Vec<bool> = (0..h * w)
            .map(|p| {
                let (r, c) = (p / w, p % w);
                (r % 5 < 2 && c % 7 < 3) || (r % 9 == 4 && c % 11 == 6)
            })
            .collect();
        let speckle: Vec<bool> = {
            let mut rand = lcg(7);
            (0..h * w).map(|_| rand() < 0.6).collect()
        };
        vec![
            ("full", full),
            ("ring", disc),
            ("strips", strips),
            ("islands", islands),
            ("speckle", speckle),
        ]
    }

    pub(crate) fn max_diff(a: &[f64], b: &[f64]) -> f64 {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max)
    }

    /// From the exact solution as warm start, no iteration is needed.
    #[test]
    fn warm_start_at_the_solution_needs_no_iteration() {
        let grid = Grid::new(64, 64, None).unwrap();
        let (targets, current) = problem_data(&grid, 3);
        let mut mg = MultigridSystem::new(&grid, None).unwrap();
        let mut a = vec![0.0; grid.n_unknowns()];
        mg.rtol = 1e-10;
        mg.solve(&grid, &targets, &current, &mut a);
        // The pinned vertex keeps its value: starting from the solution changes nothing.
        let mut b = vec![0.0; grid.n_unknowns()];
        mg.rtol = 1e-8;
        let iterations = mg.solve(&grid, &targets, &a, &mut b);
        assert_eq!(iterations, 0);
        assert!(max_diff(&a, &b) == 0.0);
    }

    /// Solves on lent memory (filled with NaN, as the solver's targets could hold anything)
    /// give the bits of solves on the system's own zeroed vectors, on every mask; the buffer
    /// comes back (the same allocation), and one too small to hold three vectors is refused
    /// and left as it was.
    #[test]
    fn solves_on_lent_memory_are_the_same_bits() {
        for (name, mask) in masks(40, 56) {
            let grid = Grid::new(40, 56, Some(&mask)).unwrap();
            if grid.n_unknowns() == 0 {
                continue;
            }
            let n = grid.n_unknowns();
            let mut own = MultigridSystem::new(&grid, None).unwrap();
            let mut lent = MultigridSystem::new(&grid, None).unwrap();
            let padded = lent.levels[0].layout.len();
            let mut small = vec![f64::NAN; 3 * padded - 1];
            lent.release_work();
            assert!(!lent.lend(&mut small), "{name}");
            assert_eq!(small.len(), 3 * padded - 1);
            for seed in 0..3 {
                let (targets, current) = problem_data(&grid, seed);
                let mut a = vec![0.0; n];
                let ia = own.solve(&grid, &targets, &current, &mut a);
                let mut buffer = vec![f64::NAN; 4 * padded];
                let at = buffer.as_ptr();
                assert!(lent.lend(&mut buffer) && buffer.is_empty(), "{name}");
                lent.reserve_work().unwrap();
                let mut b = vec![0.0; n];
                let ib = lent.solve(&grid, &targets, &current, &mut b);
                let back = lent.take_back().expect("the lent buffer");
                assert!(back.as_ptr() == at && back.len() == 3 * padded, "{name}");
                assert!(lent.take_back().is_none());
                lent.release_work();
                assert_eq!(ia, ib, "{name} seed {seed}");
                assert!(
                    a.iter().zip(&b).all(|(a, b)| a.to_bits() == b.to_bits()),
                    "{name} seed {seed}"
                );
            }
        }
    }

    /// A relative stop ends the conjugate gradients earlier, once the residual has fallen by
    /// that factor (the solution then within a small part of the start's distance from the
    /// exact one); a relative stop of 0 changes no bit.
    #[test]
    fn a_relative_stop_ends_the_solve_early() {
        let grid = Grid::new(96, 80, None).unwrap();
        let (targets, current) = problem_data(&grid, 5);
        let n = grid.n_unknowns();
        let mut mg = MultigridSystem::new(&grid, None).unwrap();
        let mut exact = vec![0.0; n];
        let full = mg.solve(&grid, &targets, &current, &mut exact);
        mg.relative_stop = 0.0;
        let mut again = vec![0.0; n];
        assert_eq!(mg.solve(&grid, &targets, &current, &mut again), full);
        assert!(exact
            .iter()
            .zip(&again)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
        mg.relative_stop = 1e-3;
        let mut rough = vec![0.0; n];
        let early = mg.solve(&grid, &targets, &current, &mut rough);
        assert!(early >= 1 && early < full, "{early} vs {full}");
        let start = max_diff(&current, &exact);
        assert!(
            max_diff(&rough, &exact) <= 1e-2 * start,
            "{}",
            max_diff(&rough, &exact)
        );
    }

    /// Level 1 and the level-2 cells made band by band from the fine flags are those of the
    /// whole level-1 cells.
    #[test]
    fn level_one_by_bands_matches_the_whole_cells() {
        for (h, w) in [(120, 130), (75, 41), (200, 9)] {
            for (name, mask) in masks(h, w) {
                let grid = Grid::new(h, w, Some(&mask)).unwrap();
                let prior = Prior {
                    values: (0..grid.n_unknowns())
                        .map(|i| if i % 5 == 0 { 1.0 } else { f64::NAN })
                        .collect(),
                    weight: 0.3,
                };
                let mg = MultigridSystem::with_coarsest(&grid, Some(&prior), 1).unwrap();
                let fine = &mg.levels[0];
                let l1 = fine.layout.coarser();
                let cells = FineCells::new(fine, 0.3);
                let whole: Vec<Element> = (0..(l1.rows - 1) * (l1.cols - 1))
                    .map(|i| cells.cell(i / (l1.cols - 1), i % (l1.cols - 1)))
                    .collect();
                let (stencils, next) = first_coarse_level(fine, 0.3, true).unwrap();
                let plain = plain_stencil(&cells.interior());
                let from_whole = stencils_of(l1, &whole, &plain).unwrap();
                let (h1, w1) = (l1.rows - 1, l1.cols - 1);
                let cell = |r: usize, c: usize| (r < h1 && c < w1).then(|| &whole[r * w1 + c]);
                for n in 0..l1.rows * l1.cols {
                    // What the level stored before the interior stencils were shared.
                    let own = unpack(&pack(&stencil_at(n / l1.cols, n % l1.cols, &cell)));
                    let bits = |s: Stencil| s.map(f64::to_bits);
                    assert_eq!(bits(stencils.get(n)), bits(own), "{name} node {n}");
                    assert_eq!(bits(from_whole.get(n)), bits(own), "{name} node {n}");
                }
                assert_eq!(stencils.index, from_whole.index, "{name}");
                assert_eq!(next.unwrap(), coarsen_cells(l1, &whole).unwrap(), "{name}");
            }
        }
    }

    /// A forward sweep from zero over whatever the vector holds is the sweep of the zeroed
    /// vector, bit for bit, on every level of masks with holes, over several bands.
    #[test]
    fn sweep_from_zero_is_the_sweep_of_zeros() {
        let (h, w) = (5 * BAND + 3, 70);
        for (name, mask) in masks(h, w) {
            let grid = Grid::new(h, w, Some(&mask)).unwrap();
            let mg = MultigridSystem::with_coarsest(&grid, None, 20).unwrap();
            for level in &mg.levels[..mg.n_levels() - 1] {
                let l = level.layout;
                let mut rand = lcg(l.len() as u64);
                let mut b: Vec<f64> = (0..l.len()).map(|_| rand() - 0.5).collect();
                // The padding of a right side is zero (its nodes are what the sweeps read).
                for (i, v) in b.iter_mut().enumerate() {
                    let (pr, pc) = (i / l.stride, i % l.stride);
                    if pr == 0 || pr > l.rows || pc == 0 || pc > l.cols {
                        *v = 0.0;
                    }
                }
                let mut zeroed = vec![0.0; l.len()];
                gauss_seidel::<true, false>(level, &mut zeroed, &b);
                // Garbage at the nodes; the padding stays zero, as in the solver's vectors.
                let mut garbage: Vec<f64> = b
                    .iter()
                    .map(|v| if *v == 0.0 { 0.0 } else { 7.0 + rand() })
                    .collect();
                gauss_seidel::<true, true>(level, &mut garbage, &b);
                let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(
                    bits(&garbage),
                    bits(&zeroed),
                    "{name} {} x {}",
                    l.rows,
                    l.cols
                );
            }
        }
    }

    /// On a full mask every coarse level shares one interior stencil: only the nodes near the
    /// border and the pin keep their own, and the shared one is each interior node's own, bit
    /// for bit (what the level-1 test above checks node by node for all masks).
    #[test]
    fn interior_nodes_share_one_stencil() {
        let grid = Grid::new(250, 260, None).unwrap();
        let mg = MultigridSystem::with_coarsest(&grid, None, 50).unwrap();
        assert!(mg.n_levels() >= 4);
        for level in &mg.levels[1..] {
            let Stencils::Coarse(s) = &level.stencils else {
                panic!("coarse level expected")
            };
            let l = level.layout;
            let plain = s.index.iter().filter(|&&k| k == PLAIN_NODE).count();
            // The two outermost rings of nodes are not interior.
            let border = 2 * (l.rows + l.cols) * 2;
            println!(
                "{} x {}: {plain} plain, {} own",
                l.rows,
                l.cols,
                s.general.len()
            );
            assert!(s.general.len() <= border + 9, "{}", s.general.len());
            assert_eq!(plain + s.general.len(), l.rows * l.cols);
        }
    }

    /// The fine level's vertex flags, made row by row in parallel, are those of a pass over the
    /// facets setting each facet's four corners (full, holed and ragged masks, the pins).
    #[test]
    fn fine_flags_are_the_facets_corners() {
        for (h, w) in [(37, 53), (64, 64), (5, 3)] {
            for (_, mask) in masks(h, w) {
                let Ok(grid) = Grid::new(h, w, Some(&mask)) else {
                    continue;
                };
                let mg = MultigridSystem::with_coarsest(&grid, None, 50).unwrap();
                let Stencils::Fine { flags, .. } = &mg.levels[0].stencils else {
                    panic!("fine level expected")
                };
                let vw = w + 1;
                let mut expected = vec![0u8; (h + 1) * vw];
                for p in grid.facets.iter().map(|&p| p as usize) {
                    let v = (p / w) * vw + p % w;
                    expected[v] |= SE;
                    expected[v + 1] |= SW;
                    expected[v + vw] |= NE;
                    expected[v + vw + 1] |= NW;
                }
                for &p in &mg.pins {
                    expected[grid.active[p as usize] as usize] |= PINNED;
                }
                assert_eq!(flags, &expected, "{h} x {w}");
            }
        }
    }

    /// The Galerkin coarse operators are symmetric and have constants in their null space away
    /// from the pins (the stencil of every unpinned row sums to zero).
    #[test]
    fn coarse_stencils_are_symmetric_and_conservative() {
        let mask: Vec<bool> = masks(120, 130).remove(1).1;
        let grid = Grid::new(120, 130, Some(&mask)).unwrap();
        let mg = MultigridSystem::with_coarsest(&grid, None, 50).unwrap();
        assert!(mg.n_levels() >= 3);
        for level in &mg.levels[1..] {
            let Stencils::Coarse(s) = &level.stencils else {
                panic!("coarse level expected")
            };
            let l = level.layout;
            let mut checked = 0;
            for r in 1..l.rows - 1 {
                for c in 1..l.cols - 1 {
                    let st = s.get(r * l.cols + c);
                    for (k, &(dr, dc)) in OFFSETS.iter().enumerate() {
                        let other =
                            s.get((r as isize + dr) as usize * l.cols + (c as isize + dc) as usize);
                        assert!((st[k] - other[8 - k]).abs() <= 1e-12 * st[CENTRE].max(1.0));
                    }
                    let sum: f64 = st[..9].iter().sum();
                    if sum.abs() > 1e-9 * st[CENTRE] {
                        checked += 1;
                    }
                }
            }
            // Only the (one) pinned region's neighbourhood carries the pin.
            assert!(checked <= 9, "{checked} rows do not sum to zero");
        }
    }
}
