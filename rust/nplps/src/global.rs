//! Global step: glue the facets back into one mesh with a pre-factored sparse system.
//!
//! Minimizes `sum_f |N z(f) - t_f|^2` over the unknown vertex depths, with `N = I_4 - ones/4`
//! and `t_f` the local step's mean-subtracted targets. The normal equations are `A z = b` with
//! `A = sum_f S_f^T N S_f` (a 9-point stencil that depends only on the mask) and
//! `b = sum_f S_f^T t_f`.
//!
//! `A` has one constant per region in its null space. The lowest-index unknown of each region is
//! pinned (`A[p, p] += 1`, `b[p] += z_current[p]`): since the energy is exactly invariant to a
//! constant shift per region, the pinned system's solution is an exact minimizer (no bias), and
//! `A` becomes strictly positive definite. The gauge (a shift per region) is applied afterwards.
//!
//! `A` is analysed (AMD ordering) and factored (`L L^T`, faer) once; each iteration only
//! back-substitutes. faer's parallel dense kernels have had wrong results in some versions, so
//! the factorization is checked by the relative residual of a test solve and redone sequentially
//! when that check fails.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::perm::PermRef;
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, LltRef, SymbolicCholesky,
    SymmetricOrdering,
};
use faer::sparse::{SparseColMat, Triplet};
use faer::{Conj, MatMut, Par, Side};

use crate::error::{Error, Result};
use crate::grid::Grid;
use crate::memory::{try_collect, try_copy, try_vec, try_with_capacity};
use crate::ordering::nested_dissection;

/// Fill-reducing ordering of the sparse Cholesky factorization.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FillOrdering {
    /// Geometric nested dissection of the vertex grid (default; see [`crate::ordering`]).
    #[default]
    NestedDissection,
    /// faer's approximate minimum degree (compared with nested dissection by the tests).
    #[cfg(test)]
    Amd,
}

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
    let vw = grid.width + 1;
    out.par_iter_mut()
        .zip(grid.active.par_iter())
        .for_each(|(o, &v)| *o = grid.gather_targets(targets, v / vw, v % vw));
    let partial: Vec<f64> = out
        .par_chunks(1 << 15)
        .map(|c| c.iter().map(|v| v * v).sum())
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

/// The factored global system of one mask.
pub struct GlobalSystem {
    chol: Cholesky,
    pins: Vec<u32>,
    /// `weight * prior` per unknown (0 where there is no prior), added to every right side.
    prior_rhs: Option<Vec<f64>>,
    /// Relative residual of the check solve after factorization.
    #[cfg(test)]
    check_residual: f64,
}

impl GlobalSystem {
    /// Assembles, analyses and factors the system of `grid` with the nested-dissection
    /// ordering, using `par` for faer's kernels.
    #[cfg(test)]
    pub fn new(grid: &Grid, par: Par) -> Result<GlobalSystem> {
        GlobalSystem::with_ordering(grid, par, FillOrdering::NestedDissection, None)
    }

    /// As [`GlobalSystem::new`], with a chosen fill-reducing ordering and an optional prior
    /// (see [`Prior`]).
    pub fn with_ordering(
        grid: &Grid,
        par: Par,
        ordering: FillOrdering,
        prior: Option<&Prior>,
    ) -> Result<GlobalSystem> {
        let n = grid.n_unknowns();
        let pins = pinned_unknowns(grid, prior)?;
        let lower = assemble_lower(grid, &pins, prior)?;
        let (fwd, inv) = nested_dissection(grid)?;
        let ord = match ordering {
            #[cfg(test)]
            FillOrdering::Amd => SymmetricOrdering::Amd,
            FillOrdering::NestedDissection => {
                SymmetricOrdering::Custom(PermRef::new_checked(&fwd, &inv, n))
            }
        };
        let chol = Cholesky::new(lower, ord, par)?;
        Ok(GlobalSystem {
            #[cfg(test)]
            check_residual: chol.check_residual,
            chol,
            pins,
            prior_rhs: prior_right_side(prior)?,
        })
    }

    /// Number of nonzeros of the Cholesky factor.
    #[cfg(test)]
    pub fn factor_nnz(&self) -> usize {
        self.chol.factor_nnz()
    }

    /// One global step: the depths that best glue the facets' targets `targets`, with each
    /// region's constant taken from `z_current` at its pinned vertex. Writes `z_out`.
    pub fn solve(
        &mut self,
        grid: &Grid,
        targets: &[[f64; 4]],
        z_current: &[f64],
        z_out: &mut [f64],
    ) {
        right_side(
            grid,
            targets,
            &self.pins,
            self.prior_rhs.as_deref(),
            z_current,
            z_out,
        );
        self.chol.solve_in_place(z_out);
    }
}

/// How the global step's linear system is solved.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum GlobalSolver {
    /// Direct below 40 000 unknowns (about 200 x 200 pixels), multigrid above.
    #[default]
    Auto,
    /// Sparse Cholesky factorization (nested dissection), factored once: exact, but its fill
    /// grows faster than the pixels (about 7.5 GB at 2048 x 2048).
    Direct,
    /// Conjugate gradients with a multigrid preconditioner: linear cost
    /// and memory in the pixels.
    Multigrid,
}

/// Unknowns above which [`GlobalSolver::Auto`] takes the multigrid solver.
pub const AUTO_MULTIGRID_UNKNOWNS: usize = 40_000;

/// With [`GlobalSolver::Auto`], a multigrid solve that needs more than this many
/// conjugate-gradient iterations (masks of thin strips joined across gaps by the coarsening,
/// such as combs) switches the system to the direct solver, when it has at most
/// [`FALLBACK_MAX_UNKNOWNS`] unknowns.
pub const FALLBACK_ITERATIONS: usize = 100;

/// Most unknowns for which [`GlobalSolver::Auto`] falls back to the direct solver (its factor
/// then takes about 3 GB).
pub const FALLBACK_MAX_UNKNOWNS: usize = 1_500_000;

/// The global system of one mask, solved directly or by multigrid.
pub enum GlobalStep {
    /// Sparse Cholesky.
    Direct(Box<GlobalSystem>),
    /// Multigrid-preconditioned conjugate gradients.
    Multigrid {
        /// The multigrid system.
        system: Box<crate::multigrid::MultigridSystem>,
        /// What a switch to the direct solver needs (see [`FALLBACK_ITERATIONS`]); None when
        /// the multigrid solver was asked for, or the system is too large.
        fallback: Option<Box<(Par, Option<Prior>)>>,
    },
}

impl GlobalStep {
    /// Sets up the solver of `grid`'s system (with an optional prior) as `choice` says.
    pub fn new(
        grid: &Grid,
        choice: GlobalSolver,
        par: Par,
        prior: Option<&Prior>,
    ) -> Result<GlobalStep> {
        let n = grid.n_unknowns();
        let multigrid = match choice {
            GlobalSolver::Auto => n > AUTO_MULTIGRID_UNKNOWNS,
            GlobalSolver::Direct => false,
            GlobalSolver::Multigrid => true,
        };
        Ok(if multigrid {
            let fallback = (choice == GlobalSolver::Auto && n <= FALLBACK_MAX_UNKNOWNS)
                .then(|| Box::new((par, prior.cloned())));
            GlobalStep::Multigrid {
                system: Box::new(crate::multigrid::MultigridSystem::new(grid, prior)?),
                fallback,
            }
        } else {
            GlobalStep::Direct(Box::new(GlobalSystem::with_ordering(
                grid,
                par,
                FillOrdering::NestedDissection,
                prior,
            )?))
        })
    }

    /// Makes the conjugate gradients stop early once `cancel` is cancelled (the direct solver's
    /// factorization and solves are single library calls and run to their end).
    pub fn set_cancel(&mut self, cancel: &crate::Cancel) {
        if let GlobalStep::Multigrid { system, .. } = self {
            system.cancel = cancel.clone();
        }
    }

    /// One global step (see [`GlobalSystem::solve`]); returns the conjugate-gradient iterations
    /// (0 for the direct solver). A multigrid solve that needed more than
    /// [`FALLBACK_ITERATIONS`] is redone, and the system kept, with the direct solver when the
    /// fallback is allowed (see [`GlobalStep::Multigrid`]).
    pub fn solve(
        &mut self,
        grid: &Grid,
        targets: &[[f64; 4]],
        z_current: &[f64],
        z_out: &mut [f64],
    ) -> Result<usize> {
        match self {
            GlobalStep::Direct(system) => {
                system.solve(grid, targets, z_current, z_out);
                Ok(0)
            }
            GlobalStep::Multigrid { system, fallback } => {
                // With a fallback, stop the conjugate gradients as soon as they are too slow.
                let limit = system.max_iterations;
                if fallback.is_some() {
                    system.max_iterations = limit.min(FALLBACK_ITERATIONS + 1);
                }
                let iterations = system.solve(grid, targets, z_current, z_out);
                system.max_iterations = limit;
                if iterations > FALLBACK_ITERATIONS && !system.cancel.is_cancelled() {
                    if let Some(parts) = fallback.take() {
                        let (par, prior) = *parts;
                        let mut direct = GlobalSystem::with_ordering(
                            grid,
                            par,
                            FillOrdering::NestedDissection,
                            prior.as_ref(),
                        )?;
                        direct.solve(grid, targets, z_current, z_out);
                        *self = GlobalStep::Direct(Box::new(direct));
                    }
                }
                Ok(iterations)
            }
        }
    }
}

/// Lower triangle of `A = sum_f S_f^T N S_f`, plus 1 on each pinned diagonal entry and the
/// prior's weight on each diagonal entry it covers.
fn assemble_lower(
    grid: &Grid,
    pins: &[u32],
    prior: Option<&Prior>,
) -> Result<SparseColMat<usize, f64>> {
    let n = grid.n_unknowns();
    let priors = prior.map_or(0, |p| p.values.iter().filter(|v| v.is_finite()).count());
    let mut triplets = crate::memory::try_with_capacity(
        grid.n_facets() * 10 + pins.len() + priors,
        "the global step's sparse system",
    )?;
    for ids in &grid.facet_vertices {
        for a in 0..4 {
            for b in 0..4 {
                let (i, j) = (ids[a] as usize, ids[b] as usize);
                if i == j {
                    triplets.push(Triplet::new(i, j, 0.75));
                } else if i > j {
                    triplets.push(Triplet::new(i, j, -0.25));
                }
            }
        }
    }
    for &p in pins {
        triplets.push(Triplet::new(p as usize, p as usize, 1.0));
    }
    if let Some(prior) = prior {
        for (u, value) in prior.values.iter().enumerate() {
            if value.is_finite() {
                triplets.push(Triplet::new(u, u, prior.weight));
            }
        }
    }
    SparseColMat::try_new_from_triplets(n, n, &triplets).map_err(|e| match e {
        faer::sparse::CreationError::Generic(e) => faer_error(
            e,
            "the global step's sparse system",
            "cannot assemble the normal matrix",
        ),
        e => Error::Solver(format!("cannot assemble the normal matrix: {e:?}")),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Targets of a known surface are reproduced exactly (planes are in the range of the
    /// facet-wise mean subtraction), with the pinned vertex fixing the constant.
    #[test]
    fn recovers_a_plane_from_its_targets() {
        let mask: Vec<bool> = (0..30).map(|p| p != 7 && p != 8).collect();
        let grid = Grid::new(5, 6, Some(&mask)).unwrap();
        let truth: Vec<f64> = grid
            .active
            .iter()
            .map(|&v| 3.0 + 0.2 * (v % 7) as f64 - 0.1 * (v / 7) as f64)
            .collect();
        let targets: Vec<[f64; 4]> = grid
            .facet_vertices
            .iter()
            .map(|ids| {
                let m = ids.iter().map(|&i| truth[i as usize]).sum::<f64>() / 4.0;
                ids.map(|i| truth[i as usize] - m)
            })
            .collect();
        for par in [Par::Seq, Par::rayon(2)] {
            let mut sys = GlobalSystem::new(&grid, par).unwrap();
            assert!(sys.check_residual < 1e-10);
            let mut z = vec![0.0; grid.n_unknowns()];
            sys.solve(&grid, &targets, &truth, &mut z);
            for (a, b) in z.iter().zip(&truth) {
                assert!((a - b).abs() < 1e-9, "{a} vs {b}");
            }
        }
    }

    /// A grid large enough for the supernodal path factorizes accurately with both orderings,
    /// and nested dissection fills in less than AMD.
    #[test]
    fn large_grid_factorizes_accurately() {
        let grid = Grid::new(120, 130, None).unwrap();
        let nd = GlobalSystem::new(&grid, Par::rayon(2)).unwrap();
        let amd =
            GlobalSystem::with_ordering(&grid, Par::rayon(2), FillOrdering::Amd, None).unwrap();
        assert!(nd.check_residual < 1e-9 && amd.check_residual < 1e-9);
        println!(
            "factor nonzeros: nested dissection {}, AMD {}",
            nd.factor_nnz(),
            amd.factor_nnz()
        );
        assert!(nd.factor_nnz() < amd.factor_nnz());
    }

    /// A comb (3-pixel teeth, 2-pixel gaps) defeats the multigrid coarsening; `Auto` then
    /// switches to the direct solver and gives its exact solution; `Multigrid` keeps iterating.
    #[test]
    fn auto_falls_back_to_direct_on_a_comb() {
        let n = 256;
        let mask: Vec<bool> = (0..n * n).map(|p| p % n % 5 < 3 || p / n < 10).collect();
        let grid = Grid::new(n, n, Some(&mask)).unwrap();
        assert!(grid.n_unknowns() > AUTO_MULTIGRID_UNKNOWNS);
        let targets: Vec<[f64; 4]> = (0..grid.n_facets())
            .map(|f| {
                let x = ((f * 7919) % 101) as f64 * 1e-3;
                [x, -x, 0.5 * x, -0.5 * x]
            })
            .collect();
        let current = vec![100.0; grid.n_unknowns()];
        let mut exact = vec![0.0; grid.n_unknowns()];
        GlobalSystem::new(&grid, Par::Seq)
            .unwrap()
            .solve(&grid, &targets, &current, &mut exact);
        let mut auto = GlobalStep::new(&grid, GlobalSolver::Auto, Par::Seq, None).unwrap();
        assert!(matches!(auto, GlobalStep::Multigrid { .. }));
        let mut z = vec![0.0; grid.n_unknowns()];
        let iterations = auto.solve(&grid, &targets, &current, &mut z).unwrap();
        assert!(iterations > FALLBACK_ITERATIONS, "{iterations}");
        assert!(matches!(auto, GlobalStep::Direct(_)));
        for (a, b) in z.iter().zip(&exact) {
            assert!((a - b).abs() < 1e-9, "{a} vs {b}");
        }
        let mut forced = GlobalStep::new(&grid, GlobalSolver::Multigrid, Par::Seq, None).unwrap();
        forced.solve(&grid, &targets, &current, &mut z).unwrap();
        assert!(matches!(forced, GlobalStep::Multigrid { .. }));
    }

    /// A prior on every unknown anchors the system without pins and pulls the solution towards
    /// the prior where the targets say nothing (here: flat targets, prior = a tilted plane).
    #[test]
    fn prior_pulls_towards_its_values() {
        let grid = Grid::new(6, 7, None).unwrap();
        let values: Vec<f64> = grid
            .active
            .iter()
            .map(|&v| 10.0 + 0.1 * (v % 8) as f64)
            .collect();
        let prior = Prior {
            values: values.clone(),
            weight: 1e6,
        };
        let mut sys = GlobalSystem::with_ordering(
            &grid,
            Par::Seq,
            FillOrdering::NestedDissection,
            Some(&prior),
        )
        .unwrap();
        assert!(sys.pins.is_empty());
        let targets = vec![[0.0; 4]; grid.n_facets()];
        let mut z = vec![0.0; grid.n_unknowns()];
        sys.solve(&grid, &targets, &values, &mut z);
        for (a, b) in z.iter().zip(&values) {
            assert!((a - b).abs() < 1e-3, "{a} vs {b}");
        }
    }
}
