//! The pieces of the global system that the direct solver ([`crate::global`]) and the multigrid
//! solver ([`crate::multigrid`]) share: the depth prior, the pinned unknowns, the right side, and
//! the sparse Cholesky factor (the direct solver's, and the multigrid's coarsest level).
//!
//! The direct and multigrid global steps both build on this module; neither uses the other's
//! internals (the global step chooses between them, see [`crate::global::GlobalStep`]).

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, LltRef, SymbolicCholesky,
    SymmetricOrdering,
};
use faer::sparse::SparseColMat;
use faer::{Conj, MatMut, Par, Side};

use crate::error::{Error, Result};
use crate::grid::Grid;
use crate::memory::{try_collect, try_copy, try_vec, try_with_capacity};

/// A prior on the unknowns (depth, or log-depth for a pinhole camera) fused in the global step:
/// the energy gains `weight * sum_v (u_v - prior_v)^2` over the unknowns whose prior is finite.
/// A region the prior covers needs no pinned vertex.
#[derive(Debug, Clone, PartialEq)]
pub struct Prior {
    /// Prior value of each unknown (NaN: none).
    pub values: Vec<f64>,
    /// Weight of the prior term relative to the facet terms.
    pub weight: f64,
}

/// Relative residual above which a factorization is considered wrong.
const RESIDUAL_LIMIT: f64 = 1e-6;

/// Whether a check residual passes (NaN does not).
fn accurate(residual: f64) -> bool {
    residual <= RESIDUAL_LIMIT
}

/// A sparse symmetric positive definite matrix, stored as its lower triangle, factored as
/// `L L^T` by faer (used by the direct global step and by the coarsest level of the multigrid).
pub(crate) struct Cholesky {
    lower: SparseColMat<usize, f64>,
    symbolic: SymbolicCholesky<usize>,
    l_values: Vec<f64>,
    par: Par,
    scratch: MemBuffer,
    /// Relative residual of the check solve after factorization.
    pub check_residual: f64,
}

impl Cholesky {
    /// Analyses (with `ordering`) and factors `lower`, checking the factor by the relative
    /// residual of a test solve (redone sequentially when a parallel factorization fails it).
    pub fn new(
        lower: SparseColMat<usize, f64>,
        ordering: SymmetricOrdering<'_, usize>,
        par: Par,
    ) -> Result<Cholesky> {
        let n = lower.nrows();
        let symbolic = factorize_symbolic_cholesky(
            lower.symbolic(),
            Side::Lower,
            ordering,
            CholeskySymbolicParams::default(),
        )
        .map_err(|e| {
            faer_error(
                e,
                "the analysis of the global step's sparse system",
                "symbolic analysis failed",
            )
        })?;
        let mut chol = Cholesky {
            l_values: crate::memory::try_filled(
                symbolic.len_val(),
                0.0,
                "the sparse Cholesky factor of the global step",
            )?,
            symbolic,
            lower,
            par,
            scratch: MemBuffer::new(faer::dyn_stack::StackReq::empty()),
            check_residual: f64::NAN,
        };
        chol.factor()?;
        chol.check_residual = chol.check()?;
        if !accurate(chol.check_residual) && !matches!(par, Par::Seq) {
            chol.par = Par::Seq;
            chol.factor()?;
            chol.check_residual = chol.check()?;
        }
        if !accurate(chol.check_residual) {
            return Err(Error::Solver(format!(
                "the factorization of the {n} x {n} system is inaccurate (relative residual {:e})",
                chol.check_residual
            )));
        }
        Ok(chol)
    }

    /// Number of nonzeros of the factor.
    #[cfg(test)]
    pub fn factor_nnz(&self) -> usize {
        self.symbolic.len_val()
    }

    fn factor(&mut self) -> Result<()> {
        let req = self
            .symbolic
            .factorize_numeric_llt_scratch::<f64>(self.par, Default::default())
            .or(self.symbolic.solve_in_place_scratch::<f64>(1, self.par));
        self.scratch = MemBuffer::try_new(req).map_err(|_| {
            crate::memory::allocation_failed(
                "the sparse Cholesky factorization's scratch space",
                req.size_bytes() as f64,
            )
        })?;
        self.symbolic
            .factorize_numeric_llt(
                &mut self.l_values,
                self.lower.as_ref(),
                Side::Lower,
                Default::default(),
                self.par,
                MemStack::new(&mut self.scratch),
                Default::default(),
            )
            .map_err(|e| {
                Error::Solver(format!("the normal matrix is not positive definite: {e:?}"))
            })?;
        Ok(())
    }

    /// Solves `A x = rhs` in place.
    pub fn solve_in_place(&mut self, rhs: &mut [f64]) {
        let n = rhs.len();
        let llt = LltRef::new(&self.symbolic, &self.l_values);
        llt.solve_in_place_with_conj(
            Conj::No,
            MatMut::from_column_major_slice_mut(rhs, n, 1),
            self.par,
            MemStack::new(&mut self.scratch),
        );
    }

    /// Relative residual `|A x - b| / |b|` of a solve with a deterministic right side.
    fn check(&mut self) -> Result<f64> {
        const WHAT: &str = "the check of the sparse Cholesky factor";
        let n = self.lower.nrows();
        let b = try_collect((0..n).map(|i| ((i as f64) * 0.618).sin() + 0.5), WHAT)?;
        let mut x = try_copy(&b, WHAT)?;
        self.solve_in_place(&mut x);
        let ax = self.mul(&x)?;
        let num: f64 = ax.iter().zip(&b).map(|(a, b)| (a - b) * (a - b)).sum();
        let den: f64 = b.iter().map(|b| b * b).sum();
        Ok((num / den).sqrt())
    }

    /// `A x` with `A` stored as its lower triangle.
    fn mul(&self, x: &[f64]) -> Result<Vec<f64>> {
        let a = self.lower.as_ref();
        let mut y = try_vec(x.len(), 0.0, "the check of the sparse Cholesky factor")?;
        for j in 0..a.ncols() {
            for (i, v) in a.row_idx_of_col(j).zip(a.val_of_col(j)) {
                y[i] += v * x[j];
                if i != j {
                    y[j] += v * x[i];
                }
            }
        }
        Ok(y)
    }
}

/// The pinned unknowns: the lowest-index unknown of each region that the prior does not cover.
pub(crate) fn pinned_unknowns(grid: &Grid, prior: Option<&Prior>) -> Result<Vec<u32>> {
    // One per region: up to one per few unknowns for a speckled mask.
    let mut anchored = try_vec(grid.n_regions, false, "the pinned unknowns")?;
    if let Some(prior) = prior {
        for (u, value) in prior.values.iter().enumerate() {
            if value.is_finite() {
                anchored[grid.region_of_unknown[u] as usize] = true;
            }
        }
    }
    let mut pins = try_with_capacity(
        anchored.iter().filter(|a| !**a).count(),
        "the pinned unknowns",
    )?;
    pins.extend(
        grid.pins
            .iter()
            .zip(&anchored)
            .filter(|(_, a)| !**a)
            .map(|(p, _)| *p),
    );
    Ok(pins)
}

/// `weight * prior` per unknown (0 where there is none).
pub(crate) fn prior_right_side(prior: Option<&Prior>) -> Result<Option<Vec<f64>>> {
    prior
        .map(|p| {
            crate::memory::try_collect(
                p.values
                    .iter()
                    .map(|v| if v.is_finite() { p.weight * v } else { 0.0 }),
                "the depth prior's right side",
            )
        })
        .transpose()
}

/// A faer error as the crate's: [`Error::Memory`] when an allocation for `what` failed, else
/// [`Error::Solver`] starting with `context`.
pub(crate) fn faer_error(e: faer::sparse::FaerError, what: &str, context: &str) -> Error {
    match e {
        faer::sparse::FaerError::OutOfMemory => crate::memory::allocation_failed(what, f64::NAN),
        e => Error::Solver(format!("{context}: {e:?}")),
    }
}

/// The right side `b = sum_f S_f^T t_f + pins * z_current + weight * prior` of the unknowns,
/// written to `out` (one per unknown; each gathers the targets of its facets, in parallel).
/// Returns the norm of the facet part `sum_f S_f^T t_f`.
pub(crate) fn right_side(
    grid: &Grid,
    targets: &[[f64; 4]],
    pins: &[u32],
    prior_rhs: Option<&[f64]>,
    z_current: &[f64],
    out: &mut [f64],
) -> f64 {
    use rayon::prelude::*;
    const CHUNK: usize = 1 << 15;
    let vw = grid.width + 1;
    // One pass: each chunk of unknowns finds the row of its first vertex by one division and
    // follows the rows from there (the vertices increase), and sums its squares in order.
    let partial: Vec<f64> = out
        .par_chunks_mut(CHUNK)
        .zip(grid.active.par_chunks(CHUNK))
        .map(|(out, vertices)| {
            let Some(&first) = vertices.first() else {
                return 0.0;
            };
            let mut row = first as usize / vw;
            let mut row_start = row * vw;
            let mut squares = 0.0;
            for (o, &v) in out.iter_mut().zip(vertices) {
                let v = v as usize;
                while v >= row_start + vw {
                    row += 1;
                    row_start += vw;
                }
                *o = grid.gather_targets(targets, row, v - row_start);
                squares += *o * *o;
            }
            squares
        })
        .collect();
    let norm = partial.iter().sum::<f64>().sqrt();
    for &p in pins {
        out[p as usize] += z_current[p as usize];
    }
    if let Some(rhs) = prior_rhs {
        out.par_iter_mut().zip(rhs).for_each(|(o, r)| *o += r);
    }
    norm
}
