//! The working distance from the images.
//!
//! Under near lighting the lighting of a surface point depends on where it is, so the absolute
//! distance of the object is observable: with the wrong gauge (each region's mean depth, or
//! geometric mean depth for a pinhole camera) no surface explains the images as well as with the
//! right one. [`estimate_distance`] scans the photometric residual of the reconstruction over a
//! log-spaced range of gauges and refines each region's minimum by successive parabolic
//! interpolation ([`Parabolic`]); every evaluation is a few warm-started iterations that reuse
//! the one factorization. On a level larger than [`SEARCH_SIDE`] pixels the scan runs on a
//! coarser level, and the level itself only refines the distance in a narrow window (see
//! [`search_stages`]). Regions are independent in the global step, so all of them are searched
//! at once.
//!
//! With 3 lights the fit is exact at every distance, and directional lights do not depend on
//! the distance: such rigs are rejected.

use std::sync::{Arc, Mutex};
use std::time::Instant;

use crate::error::{Error, Result};
use crate::grid::Grid;
use crate::local::RETRO_ETA;
use crate::memory::try_copy;
use crate::options::{Options, Refine};
use crate::parallel::with_threads;
use crate::problem::Problem;
use crate::reconstruction::{Control, IterationStats, Reconstruction, SearchProgress};
use crate::reflectance::Lobe;
use crate::rig::Light;
use crate::shadow::ShadowMask;
use crate::solver::{coarse_to_fine, Solver};
use crate::vec3::{norm, sub};

/// Iterations per evaluation when the search runs on the coarsest level of a pyramid, where
/// they are cheap: evaluations closer to convergence make the residual curve smoother.
const COARSE_INNER: usize = 15;

/// How to search for the working distance.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub struct DistanceSearch {
    /// Search range (near, far) in depth units. None: from `guess`, else from the rig.
    pub range: Option<(f64, f64)>,
    /// A rough distance; the range is then `(guess / 2, guess * 2)`.
    pub guess: Option<f64>,
    /// Candidates of the coarse, log-spaced scan.
    pub scan: usize,
    /// Local/global iterations per evaluation (warm-started).
    pub inner: usize,
    /// Relative precision of the refinement.
    pub precision: f64,
}

impl Default for DistanceSearch {
    fn default() -> Self {
        DistanceSearch {
            range: None,
            guess: None,
            scan: 12,
            inner: 5,
            precision: 1e-3,
        }
    }
}

with_fields!(DistanceSearch {
    with_range: range: Option<(f64, f64)>,
    with_guess: guess: Option<f64>,
    with_scan: scan: usize,
    with_inner: inner: usize,
    with_precision: precision: f64,
});

/// The estimated gauge of every region and the residual curve it came from.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct DistanceEstimate {
    /// Estimated distance of each region (arithmetic mean depth, or geometric mean depth for a
    /// pinhole camera).
    pub distance: Vec<f64>,
    /// Per region, every evaluated `(distance, residual)`, sorted by distance: the RMS image
    /// residual, or under the glossy model the median of the facets' RMS residuals (the
    /// search's criterion, see `search_with`); a search in a window (glossy, or after a scan
    /// on a coarser level) keeps its window's candidates and the wide scan's outside it, the
    /// latter scaled to the window's residuals where they meet when they come from a coarser
    /// level.
    pub curve: Vec<Vec<(f64, f64)>>,
    /// The search range used.
    pub range: (f64, f64),
}

/// Fails when the rig cannot reveal the distance.
fn check_observable(problem: &Problem<'_>) -> Result<()> {
    let lights = &problem.rig.lights;
    if !lights.iter().any(|l| matches!(l, Light::Point { .. })) {
        return Err(Error::Unusable(
            "the working distance cannot be estimated with directional lights only: they light every \
             distance alike; give depth explicitly"
                .into(),
        ));
    }
    if lights.len() <= 3 {
        return Err(Error::Unusable(format!(
            "the working distance cannot be estimated from {} lights: with 3 lights every distance fits \
             the images exactly; use at least 4 lights or give depth explicitly",
            lights.len()
        )));
    }
    Ok(())
}

/// The search range: given, around the guess, or from the rig (just beyond the farthest point
/// light to 20 light-spreads beyond it).
fn search_range(problem: &Problem<'_>, search: &DistanceSearch) -> Result<(f64, f64)> {
    let points: Vec<[f64; 3]> = problem
        .rig
        .lights
        .iter()
        .filter_map(|l| match l {
            Light::Point { position, .. } => Some(*position),
            Light::Directional { .. } => None,
        })
        .collect();
    let front = points
        .iter()
        .map(|p| p[2])
        .fold(f64::NEG_INFINITY, f64::max);
    let (near, far) = match (search.range, search.guess) {
        (Some(r), _) => r,
        (None, Some(g)) => (g / 2.0, g * 2.0),
        (None, None) => {
            let spread = points
                .iter()
                .flat_map(|a| points.iter().map(move |b| norm(sub(*a, *b))))
                .fold(0.0, f64::max)
                .max(1e-9);
            (
                front.max(0.0) + 0.05 * spread,
                front.max(0.0) + 20.0 * spread,
            )
        }
    };
    let near = near.max(front + 1e-6 * (far - front).abs());
    if !(near.is_finite() && far.is_finite() && near > 0.0 && far > near * (1.0 + 1e-6)) {
        return Err(Error::OutOfRange {
            name: "depth_range",
            value: near,
            message: format!(
                "the distance search range ({near}, {far}) is empty: it must lie beyond the point lights (z > {front})"
            ),
        });
    }
    Ok((near, far))
}

/// Evaluates the per-region residual at per-region distances `d`, warm-starting from `u`.
struct Evaluator<'s, 'p> {
    solver: &'s mut Solver<'p>,
    u: Vec<f64>,
    inner: usize,
    curve: Vec<Vec<(f64, f64)>>,
    /// The light refinement of every evaluation.
    refine: Refine,
    /// Candidates evaluated so far, and how many the search plans.
    candidate: usize,
    candidates: usize,
    /// The (mean) distance and residual of the best candidate so far (NaN before the first).
    best: (f64, f64),
    /// Candidates evaluated afresh under a held lobe (see [`Fresh`]), or warm-started.
    fresh: Option<Fresh>,
}

impl<'s, 'p> Evaluator<'s, 'p> {
    /// An evaluator of candidates on `solver`'s level (of `regions` regions) from the depths
    /// `u`, `inner` iterations each (warm-started) or afresh (`fresh`); its candidates numbered
    /// from `candidate` of `candidates` planned.
    fn new(
        (solver, regions): (&'s mut Solver<'p>, usize),
        u: Vec<f64>,
        inner: usize,
        (candidate, candidates): (usize, usize),
        fresh: Option<Fresh>,
    ) -> Self {
        Evaluator {
            refine: solver.lights.refine(),
            solver,
            u,
            inner,
            curve: vec![Vec::new(); regions],
            candidate,
            candidates,
            best: (f64::NAN, f64::NAN),
            fresh,
        }
    }
}

/// A candidate evaluated afresh: a new solver on the level (`options`), the search's settings
/// ([`begin_search`]) but the continuation of sharp lobes' fits and the user's cast-shadow
/// policy, as in a run of its own, and `lobe` held, from one surface for all candidates
/// (`start`: that of the run that estimated the lobe at the profile's distance, see
/// [`fresh_stages`]) gauged at the candidate, run to the level's convergence
/// (`options.iterations`, `options.tol`). Its criterion is then a function of the level, the
/// distance and the lobe alone.
#[derive(Debug, Clone)]
struct Fresh {
    options: Options,
    lobe: Lobe,
    /// The surface every candidate starts from and its cast shadows.
    start: Arc<FreshStart>,
    /// The candidates evaluated under `lobe` so far: one evaluated again (the scans of
    /// [`fresh_stages`]' first pass, the end a window moved to) is looked up, not run again.
    memo: Arc<Mutex<Vec<Memo>>>,
}

/// A candidate of [`Fresh`]: its distances, residuals and surface.
#[derive(Debug)]
struct Memo {
    distance: Vec<f64>,
    residuals: Vec<f64>,
    surface: Vec<f64>,
}

impl Fresh {
    /// A candidate evaluated before at `d` (the same bits), if any.
    fn recall(&self, d: &[f64]) -> Option<(Vec<f64>, Vec<f64>)> {
        let memo = self.memo.lock().ok()?;
        memo.iter()
            .find(|m| {
                m.distance
                    .iter()
                    .map(|x| x.to_bits())
                    .eq(d.iter().map(|x| x.to_bits()))
            })
            .map(|m| (m.residuals.clone(), m.surface.clone()))
    }

    fn remember(&self, d: &[f64], residuals: &[f64], surface: &[f64]) -> Result<()> {
        let memo = Memo {
            distance: d.to_vec(),
            residuals: residuals.to_vec(),
            surface: try_copy(surface, "the distance search's surfaces")?,
        };
        if let Ok(mut all) = self.memo.lock() {
            all.push(memo);
        }
        Ok(())
    }
}

/// Where the candidates of [`Fresh`] start.
#[derive(Debug)]
struct FreshStart {
    /// The unknowns of the surface, gauged at each candidate's distance.
    surface: Vec<f64>,
    /// Its cast shadows under the user's policy (see [`Solver::start_from_shadows`]).
    shadows: Option<ShadowMask>,
}

impl Evaluator<'_, '_> {
    /// Evaluates one candidate. Its iterations are reported with a [`SearchProgress`]; the last
    /// one is held back until the candidate's residual is known, so that it carries it.
    fn eval(
        &mut self,
        d: &[f64],
        progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
    ) -> Result<Vec<f64>> {
        if let Some((residuals, surface)) = self.fresh.as_ref().and_then(|f| f.recall(d)) {
            self.u = surface;
            self.record(d, &residuals);
            return Ok(residuals);
        }
        let problem = self.solver.problem();
        let (iterations, tol) = match &self.fresh {
            Some(fresh) => {
                let start = self.solver.start;
                *self.solver = Solver::new(problem, &fresh.options)?;
                self.solver.start = start;
                // The search's settings, but the cast shadows of the user's policy: with them
                // (shadows "auto") the 64² PBR block with 0.5 % noise had its lowest criterion
                // under the retro lobe near the truth; with none, under the transmitted ones
                // 0.5-1.5 % long (docs/shiny.md, stop 54). It starts from its start's.
                let (_, shadows) = begin_search(self.solver);
                self.solver.restore_shadows(shadows);
                self.solver.start_from_shadows(fresh.start.shadows.clone());
                // A run of its own, as one given the distance and the lobe: with the
                // continuation of sharp lobes' fits (see `Solver::continuation`).
                self.solver.continuation = true;
                self.solver.lobe = Some(fresh.lobe);
                self.solver.hold_lobe = true;
                self.u.clone_from(&fresh.start.surface);
                (fresh.options.iterations, fresh.options.tol)
            }
            None => (self.inner, 0.0),
        };
        let gauge: Vec<f64> = d.iter().map(|&x| problem.geometry.unknown(x)).collect();
        problem.grid.apply_gauge(&mut self.u, &gauge);
        // Every candidate starts from the rig's lights: the residual curve must not depend on
        // the order of the evaluations.
        self.solver.lights.restart(self.refine);
        // Its glossy fits go on from the normals of the last candidate, as its surface does.
        if self.candidate > 0 && self.fresh.is_none() {
            self.solver.keep_glossy_normals();
        }
        self.candidate += 1;
        self.candidates = self.candidates.max(self.candidate);
        let info = SearchProgress {
            candidate: self.candidate,
            candidates: self.candidates,
            distance: mean(d),
            residual: f64::NAN,
            best_distance: self.best.0,
            best_residual: self.best.1,
        };
        let mut pending: Option<IterationStats> = None;
        {
            let mut deferred = |stats: &IterationStats| {
                let stats = IterationStats {
                    search: Some(info),
                    ..*stats
                };
                match pending.replace(stats) {
                    Some(previous) => progress(&previous),
                    None => Control::Continue,
                }
            };
            self.solver
                .iterate(&mut self.u, &gauge, iterations, tol, &mut deferred)?;
        }
        self.solver.local(&self.u)?;
        let residuals = self.solver.search_residuals();
        if let Some(fresh) = &self.fresh {
            fresh.remember(d, &residuals, &self.u)?;
        }
        let residual = self.record(d, &residuals);
        if let Some(last) = pending {
            let stats = IterationStats {
                search: Some(SearchProgress {
                    residual,
                    best_distance: self.best.0,
                    best_residual: self.best.1,
                    ..info
                }),
                ..last
            };
            if progress(&stats) == Control::Cancel {
                return Err(Error::Cancelled);
            }
        }
        Ok(residuals)
    }

    /// Adds a candidate's residuals to the curves and the best so far; returns their mean.
    fn record(&mut self, d: &[f64], residuals: &[f64]) -> f64 {
        for ((curve, &x), &r) in self.curve.iter_mut().zip(d).zip(residuals) {
            curve.push((x, r));
        }
        let residual = mean(residuals);
        if residual.is_finite() && (self.best.1.is_nan() || residual < self.best.1) {
            self.best = (mean(d), residual);
        }
        residual
    }
}

/// The lower of two criteria, NaN counting as none.
fn lower(a: f64, b: f64) -> f64 {
    match (a.is_nan(), b.is_nan()) {
        (true, _) => b,
        (_, true) => a,
        _ => a.min(b),
    }
}

/// The mean of `values` (NaN for none).
fn mean(values: &[f64]) -> f64 {
    values.iter().sum::<f64>() / values.len() as f64
}

/// How many candidates a search is announced to evaluate: the scan and the refinement steps it
/// usually takes ([`PLANNED_REFINEMENTS`]); the announcement grows when a search needs more,
/// and a search may end sooner.
fn planned_candidates(scan: usize) -> usize {
    scan + PLANNED_REFINEMENTS
}

/// The refinement steps announced after a scan (see [`planned_candidates`]).
const PLANNED_REFINEMENTS: usize = 5;

/// Estimates each region's working distance (see the module documentation).
pub fn estimate_distance(
    problem: &Problem<'_>,
    options: &Options,
    search: &DistanceSearch,
    progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
) -> Result<DistanceEstimate> {
    options.validate()?;
    check_observable(problem)?;
    problem.check_memory(options)?;
    let range = search_range(problem, search)?;
    with_threads(options.threads, || {
        let mut solver = Solver::new(problem, options)?;
        search_with(&mut solver, problem, options, search, range, progress)
            .map(|(estimate, _)| estimate)
    })?
}

/// The search itself; also returns the warm state at the estimate.
///
/// Under the glossy model with a lobe to estimate, the lobe and the distance trade off (a
/// stronger Fresnel rise or another roughness explains the highlights of a surface placed too
/// near or too far), so candidates compared under one lobe estimated away from the truth give a
/// biased minimum (by up to 12 % on the PBR renders). The wide search therefore only brackets
/// the distance under a held lobe ([`hold_lobe`]); it is then refined in a window
/// [`PROFILE_WIDTH`] either side of the distance found with the lobe estimated for every
/// candidate (the residual minimised over lobes, [`search_window`]), which brackets it, and
/// refined under each lobe of a grid held in turn, every candidate evaluated afresh
/// ([`fresh_stages`]). The stages are [`search_stages`]'s.
fn search_with(
    solver: &mut Solver<'_>,
    problem: &Problem<'_>,
    options: &Options,
    search: &DistanceSearch,
    range: (f64, f64),
    progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
) -> Result<(DistanceEstimate, Vec<f64>)> {
    let saved = begin_search(solver);
    let found = search_stages(solver, problem, options, search, range, progress);
    end_search(solver, saved);
    found
}

/// Sets `solver` up for comparing candidates; returns what [`end_search`] restores.
fn begin_search(solver: &mut Solver<'_>) -> (Refine, crate::shadow::Shadows) {
    // During the search only intensities are refined: positions trade against the distance.
    let refine = solver.lights.refine();
    solver.lights.set_refine(Refine {
        position: false,
        ..refine
    });
    // A candidate far from the truth may pull the surface through a light: that is a high
    // residual for the search, not an error.
    solver.check_lights = false;
    // Candidates are compared under one model: a lobe too rough for a highlight, estimated at a
    // candidate, does not drop the glossy model (the run at the distance found decides).
    solver.keep_glossy = true;
    // ... and without the glossy fits' continuation (`Solver::continuation`).
    solver.continuation = false;
    // Candidates are compared under `Shadows::in_search`; the run at the distance found uses the
    // user's policy again.
    (refine, solver.search_shadows())
}

/// Undoes [`begin_search`].
fn end_search(solver: &mut Solver<'_>, (refine, shadows): (Refine, crate::shadow::Shadows)) {
    solver.hold_lobe = false;
    solver.lobe_once = false;
    solver.keep_glossy = false;
    solver.continuation = true;
    solver.restore_shadows(shadows);
    solver.check_lights = true;
    solver.lights.restart(refine);
}

/// The longest side, in pixels, of the level on which the wide part of a search (the scan and
/// its refinement to [`WIDE_PRECISION`]) runs when the search's level is larger: a candidate
/// there costs a quarter or less of one on the pyramid's coarsest level (128 pixels or more).
/// The search's own level then only refines the distance in a window around that estimate
/// (see [`search_stages`]).
pub const SEARCH_SIDE: usize = 64;

/// Local/global iterations per candidate of the wide search on the [`SEARCH_SIDE`] level: it
/// need only bracket the distance for the window on the search's own level.
const WIDE_INNER: usize = 8;

/// The precision (in log-distance) of a wide search on the [`SEARCH_SIDE`] level that a window
/// on the search's own level refines.
const WIDE_PRECISION: f64 = 0.01;

/// The half-width, as a factor of the distance, of the window in which the search's own level
/// refines the estimate of the [`SEARCH_SIDE`] level (Lambertian model, or a lobe given).
const NARROW_WIDTH: f64 = 1.03;

/// Candidates of that window's first scan (its ends and its middle).
const NARROW_SCAN: usize = 3;

/// How many times that window may move to an end where the residual keeps falling.
const NARROW_MOVES: usize = 6;

/// Local/global iterations per candidate of that window (at most the search's): its candidates
/// start from surfaces converged nearby (the coarser level's, carried up and iterated at its
/// distance with the search's iterations, then the nearest candidate's).
const WINDOW_INNER: usize = 5;

/// The stages of a search (see [`search_with`]).
///
/// On a level larger than [`SEARCH_SIDE`] the wide search (log-spaced scan, then successive
/// parabolic interpolation to [`WIDE_PRECISION`], or [`BRACKET_PRECISION`] before a glossy
/// window) runs on a coarser level of at most `SEARCH_SIDE` pixels a side, whose surface then
/// starts the search's level; there a window [`NARROW_WIDTH`] either side of the estimate
/// gives the distance to `search.precision` (glossy with the lobe estimated: the window
/// [`PROFILE_WIDTH`] with the lobe estimated per candidate, to [`BRACKET_PRECISION`], on the
/// coarser level too, see [`search_coarser`]; then [`fresh_stages`] on a level of at most
/// `SEARCH_SIDE` pixels a side).
fn search_stages(
    solver: &mut Solver<'_>,
    problem: &Problem<'_>,
    options: &Options,
    search: &DistanceSearch,
    range: (f64, f64),
    progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
) -> Result<(DistanceEstimate, Vec<f64>)> {
    let profile = solver.estimates_lobe();
    let scan = search.scan.max(3);
    let tolerance = search.precision.max(1e-9);
    let halvings = halvings_to(problem.grid.height, problem.grid.width, SEARCH_SIDE);
    let bracket = match (profile, halvings > 0) {
        (true, _) => tolerance.max(BRACKET_PRECISION),
        (false, true) => tolerance.max(WIDE_PRECISION),
        (false, false) => tolerance,
    };
    let mut count = Count {
        lowest: f64::NAN,
        beat: f64::NAN,
        done: 0,
        planned: planned_candidates(scan)
            + match (profile, halvings > 0) {
                (true, _) => planned_candidates(PROFILE_SCAN),
                (false, true) => planned_candidates(NARROW_SCAN),
                (false, false) => 0,
            },
    };
    // Before a window, the wide search need only bracket the distance.
    let wide = DistanceSearch {
        precision: bracket,
        ..*search
    };
    let found = if halvings > 0 {
        search_coarser(
            solver, problem, options, &wide, range, halvings, &mut count, progress,
        )
    } else {
        hold_lobe(solver, problem, (range.0 * range.1).sqrt(), search.inner)
            .and_then(|()| {
                let u = problem.u0.to_vec("the depths")?;
                search_refined(
                    solver,
                    problem,
                    &wide,
                    range,
                    u,
                    (false, None),
                    &mut count,
                    progress,
                )
            })
            .and_then(|searched| searched.found(range))
    };
    match found {
        // The run at the distance found then starts afresh (the starting surface, no lobe), as
        // a run given that distance does: continuing from the last candidate's surface, whose
        // glossy fits went through many distances and lobes, ended 1.0-1.2° worse on the block
        // with cast shadows of the PBR renders (1.46° at +0.14 %, 0.42° from the start).
        Ok(wide) if profile => {
            let window = Window {
                scan: PROFILE_SCAN,
                width: PROFILE_WIDTH,
                moves: PROFILE_MOVES,
                lobe: true,
                coarser: halvings > 0,
                grow: 1.0,
                vee: false,
                fresh: None,
            };
            // The profile's scan only brackets the distance (its candidates are 5 % apart);
            // the stages under held lobes refine it.
            let bracket = DistanceSearch {
                precision: tolerance.max(BRACKET_PRECISION),
                ..*search
            };
            // Criteria are compared on this level only.
            count.lowest = f64::NAN;
            // On a level larger than `SEARCH_SIDE` the profile window ran on the coarser level
            // already (see [`search_coarser`]).
            let profiled = if halvings > 0 {
                Ok(wide)
            } else {
                search_window(
                    solver, problem, &bracket, range, wide, window, &mut count, progress,
                )
            };
            profiled
                .and_then(|(profiled, _)| {
                    fresh_stages(
                        solver, problem, options, search, range, halvings, profiled, &mut count,
                        progress,
                    )
                })
                .and_then(|estimate| {
                    solver.lobe = None;
                    solver.hold_lobe = false;
                    Ok((estimate, problem.u0.to_vec("the depths")?))
                })
        }
        Ok((wide, mut u)) if halvings > 0 => {
            // The coarser level's surface converges at its distance on this level first; the
            // window's candidates then start near convergence and take fewer iterations.
            let gauge: Vec<f64> = wide
                .distance
                .iter()
                .map(|&d| problem.geometry.unknown(d))
                .collect();
            problem.grid.apply_gauge(&mut u, &gauge);
            solver.lights.restart(solver.lights.refine());
            solver.iterate(&mut u, &gauge, search.inner, 0.0, &mut |_| {
                Control::Continue
            })?;
            let window = Window {
                scan: NARROW_SCAN,
                width: NARROW_WIDTH,
                moves: NARROW_MOVES,
                lobe: false,
                coarser: true,
                grow: 1.0,
                vee: false,
                fresh: None,
            };
            let narrow = DistanceSearch {
                inner: search.inner.min(WINDOW_INNER),
                ..*search
            };
            search_window(
                solver,
                problem,
                &narrow,
                range,
                (wide, u),
                window,
                &mut count,
                progress,
            )
        }
        other => other,
    }
}

/// How many halvings bring a `height` x `width` level to at most `side` pixels a side.
fn halvings_to(height: usize, width: usize, side: usize) -> usize {
    let (mut h, mut w, mut n) = (height, width, 0);
    while h.max(w) > side && h > 1 && w > 1 {
        h = h.div_ceil(2);
        w = w.div_ceil(2);
        n += 1;
    }
    n
}

/// The wide search on the level `halvings` below `problem`'s (see [`search_stages`]): its
/// estimate per region of `problem` (that of the coarse region holding the region's pinned
/// vertex) and its surface carried up to `problem` (not gauged). Under the glossy model with
/// the lobe estimated, the profile window ([`PROFILE_WIDTH`], the lobe estimated per candidate)
/// refines the wide estimate on this level too, and the estimate carried up is the window's.
///
/// Why the profile window runs here: it only brackets the distance (its candidates are 5 %
/// apart) for the stages of [`fresh_stages`], which refine it to the search's precision. A
/// candidate of 15 iterations, two lobe estimates among them (until stop 57; now
/// [`PROFILE_INNER`] and one), costs a quarter as much on the
/// 64² level as on the 128² one (the glossy bumps at 256²: 0.35 against
/// 0.75 CPU s), and its criterion there brackets the same distance (the bumps' 7 candidates:
/// residuals within 5 % of the 128² level's, the same lowest candidate). Until stop 49 the
/// window ran on the search's level, 40 % of the search's cost.
#[allow(clippy::too_many_arguments)]
fn search_coarser(
    solver: &mut Solver<'_>,
    problem: &Problem<'_>,
    options: &Options,
    wide: &DistanceSearch,
    range: (f64, f64),
    halvings: usize,
    count: &mut Count,
    progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
) -> Result<(DistanceEstimate, Vec<f64>)> {
    let options = one_level(options);
    let rigs = crate::pyramid::coarse_rigs(problem.rig, halvings + 1);
    let coarse = crate::pyramid::coarse_problems(problem, &rigs, &options.fit_settings(true))?;
    let level = coarse.last().unwrap_or(problem);
    let mut sub = Solver::new(level, &options)?;
    sub.start = solver.start;
    let saved = begin_search(&mut sub);
    let profile = sub.estimates_lobe();
    let found = hold_lobe(&mut sub, level, (range.0 * range.1).sqrt(), wide.inner)
        .and_then(|()| {
            let u = level.u0.to_vec("the depths")?;
            let wide = DistanceSearch {
                inner: WIDE_INNER,
                ..*wide
            };
            search_refined(
                &mut sub,
                level,
                &wide,
                range,
                u,
                (false, None),
                count,
                progress,
            )
        })
        .and_then(|searched| searched.found(range))
        .and_then(|found| {
            if !profile {
                return Ok(found);
            }
            // The glossy profile window on this level too (see [`search_coarser`]); its
            // criteria are compared among themselves.
            count.lowest = f64::NAN;
            let window = Window {
                scan: PROFILE_SCAN,
                width: PROFILE_WIDTH,
                moves: PROFILE_MOVES,
                lobe: true,
                coarser: false,
                grow: 1.0,
                vee: false,
                fresh: None,
            };
            search_window(&mut sub, level, wide, range, found, window, count, progress)
        });
    end_search(&mut sub, saved);
    let (estimate, u) = found?;
    drop(sub);
    Ok((
        on_finer(&problem.grid, &level.grid, halvings, estimate),
        carry_up(problem, &coarse, u)?,
    ))
}

/// The options of a search's runs on one level of a pyramid.
fn one_level(options: &Options) -> Options {
    Options {
        levels: 1,
        ..*options
    }
}

/// The unknowns `u` of the last of the `coarse` levels below `problem` (see
/// [`crate::pyramid::coarse_problems`]), upsampled level by level to `problem` (not gauged).
fn carry_up(problem: &Problem<'_>, coarse: &[Problem<'_>], mut u: Vec<f64>) -> Result<Vec<f64>> {
    for i in (0..coarse.len()).rev() {
        let finer = match i {
            0 => &problem.grid,
            _ => &coarse[i - 1].grid,
        };
        u = crate::pyramid::upsample(&coarse[i].grid, &u, finer)?;
    }
    Ok(u)
}

/// An estimate of the regions of `coarse` (`halvings` levels below `grid`) as one of the
/// regions of `grid`: each takes the distance and curve of the coarse region holding its
/// pinned vertex ([`coarse_regions`]).
fn on_finer(
    grid: &Grid,
    coarse: &Grid,
    halvings: usize,
    estimate: DistanceEstimate,
) -> DistanceEstimate {
    let regions = coarse_regions(grid, coarse, halvings as u32);
    DistanceEstimate {
        distance: regions.iter().map(|&r| estimate.distance[r]).collect(),
        curve: regions.iter().map(|&r| estimate.curve[r].clone()).collect(),
        range: estimate.range,
    }
}

/// The other way (see [`on_finer`]): per region of `coarse`, the geometric mean of the
/// distances of the regions of `grid` it holds (of all of them where it holds none) and the
/// curve of the first of them.
fn on_coarser(
    grid: &Grid,
    coarse: &Grid,
    halvings: usize,
    estimate: &DistanceEstimate,
) -> DistanceEstimate {
    let regions = coarse_regions(grid, coarse, halvings as u32);
    let log_mean = |d: &mut dyn Iterator<Item = f64>| {
        let (sum, n) = d.fold((0.0, 0usize), |(s, n), d| (s + d.ln(), n + 1));
        (n > 0).then(|| (sum / n as f64).exp())
    };
    let all = log_mean(&mut estimate.distance.iter().copied()).unwrap_or(f64::NAN);
    let held = |r: usize| regions.iter().enumerate().filter(move |&(_, &q)| q == r);
    DistanceEstimate {
        distance: (0..coarse.n_regions)
            .map(|r| log_mean(&mut held(r).map(|(i, _)| estimate.distance[i])).unwrap_or(all))
            .collect(),
        curve: (0..coarse.n_regions)
            .map(|r| {
                held(r)
                    .next()
                    .map_or_else(Vec::new, |(i, _)| estimate.curve[i].clone())
            })
            .collect(),
        range: estimate.range,
    }
}

/// For each region of `grid`, the region of `coarse` (`halvings` levels below) holding its
/// pinned vertex (region 0 where that vertex is inactive there).
fn coarse_regions(grid: &Grid, coarse: &Grid, halvings: u32) -> Vec<usize> {
    let scale = 1usize << halvings;
    grid.pins
        .iter()
        .map(|&p| {
            let v = grid.active[p as usize] as usize;
            let (r, c) = (v / (grid.width + 1) / scale, v % (grid.width + 1) / scale);
            let cv = r.min(coarse.height) * (coarse.width + 1) + c.min(coarse.width);
            let u = coarse.vertex_unknown[cv];
            let region = if u == crate::grid::INACTIVE {
                0
            } else {
                coarse.region_of_unknown[u as usize] as usize
            };
            region.min(coarse.n_regions.saturating_sub(1))
        })
        .collect()
}

/// The half-width, as a factor of the distance, of the window in which a glossy search is
/// refined with the lobe estimated per candidate (the wide search under one lobe missed by up to
/// 12 % on the PBR renders; the window moves when that is not enough).
const PROFILE_WIDTH: f64 = 1.15;

/// The precision (in log-distance) of a wide search that a window refines: its estimate lies
/// within 2.5 % of its minimum, well inside the window.
const BRACKET_PRECISION: f64 = 0.05;

/// Candidates of the window's scan (5 % apart).
const PROFILE_SCAN: usize = 7;

/// How many times the window may move to an end where the residual keeps falling.
const PROFILE_MOVES: usize = 3;

/// Local/global iterations per candidate of the profile window (at most the search's): each
/// candidate estimates the lobe once ([`Solver::lobe_once`]), over the whole grids at its
/// iteration [`LOBE_AT`](crate::solver::LOBE_AT)`[0]` (3), and keeps that lobe to the end.
///
/// Until stop 57 a candidate ran 15 iterations and estimated the lobe at iterations 3 (the whole
/// grids) and 5 (near the first), after a run at the wide estimate that estimated the window's
/// first lobe (15 iterations, three estimates); the window was 1.6 of the 5.6 CPU s of the 256²
/// glossy bumps of `bench.py --ratios`, and is 41 % cheaper now (docs/performance.md, stop 57).
/// The estimates must search the whole grids: on a matte object under the glossy model the
/// roughness criterion has two minima (about 0.19 and 0.85), and estimates near the last one
/// drift along it from candidate to candidate (stop 56's variant, reverted: the 256² matte
/// sphere and torus went +0.88 % and +1.35 %).
const PROFILE_INNER: usize = 8;

/// The half-width, as a factor of the distance, of the first window of a stage of
/// [`fresh_stages`], around the profile's estimate; it widens by [`FRESH_GROWTH`] at each of
/// at most [`FRESH_MOVES`] moves towards an end where the criterion keeps falling (a reach of
/// `1.015^(1 + 1.5 + 2.25 + 3.375) = 1.13`, within the profile's own window [`PROFILE_WIDTH`]).
const FRESH_WIDTH: f64 = 1.015;

/// See [`FRESH_WIDTH`].
const FRESH_MOVES: usize = 3;

/// See [`FRESH_WIDTH`].
const FRESH_GROWTH: f64 = 1.5;

/// The indices of the transmitted lobes of [`fresh_stages`]: the lobe search's grid
/// ([`ETAS`](crate::local::ETAS)) without its first index, 1.
///
/// At the index 1 the model is not the end of the index line but another model: its Fresnel
/// shape `F(v.h) / F(1)` is taken as 1 (nothing is reflected to shape), while as `eta -> 1+` the
/// shape tends to its steepest rise, `(1 + (2c^2 - 1)^2) / (2c^4)` at `c = v.h` (2.1 at
/// `c = 0.7`, 9.9 at `c = 0.5`; at the index 1.15 1.6 and 4.7); only the transmittance (`T = 1`,
/// the Lambertian diffuse term) joins the line continuously. On the 64² rough plastic 0.3
/// block of tests/data/pbr (16 lights, true distance 210.95) the lowest criterion of the stages
/// with the index 1 among them was under it, at -2.65 %, as it was for stop 45's index walk
/// over the whole grid. It competes where the lobe estimated at the profile's distance has it
/// (matte surfaces: without it the 256² matte bumps of the PBR renders under the glossy model
/// went to +1.49 %, index 1.05, and kept the glossy model), and the lobe search of the run at the
/// distance found may choose it.
const FRESH_ETAS: [f64; 6] = {
    let e = crate::local::ETAS;
    [e[1], e[2], e[3], e[4], e[5], e[6]]
};

/// Refines the estimate of a glossy profile window ([`search_window`] with `lobe`): the lobe
/// (its roughness `alpha`) is estimated once, by a run at the profile's distance on the search's
/// level (at most [`SEARCH_SIDE`] pixels a side); then, under each lobe held in turn, that one,
/// the retro-reflective one (index [`RETRO_ETA`]) and the transmitted one at each index of
/// [`FRESH_ETAS`], all at `alpha`, the distance
/// is searched in a window around the profile's estimate with every candidate evaluated afresh
/// ([`Fresh`]: a new solver from the starting surface, run to convergence under the lobe). The
/// estimate is that of the lobe whose lowest criterion `R` (the median of the facets' RMS
/// residuals) is the lowest; the profile's when no lobe finds a minimum in its windows. Its
/// distance on `problem` is the gauge there of that candidate's surface carried up: the gauge of
/// a curved surface (its geometric mean depth) differs between levels whose masks differ, and
/// the level's own distance left the 256² PBR spheres and tori 0.2-0.4 % long.
///
/// The lobes' first windows are scanned first (3 candidates each); their searches then run
/// from the lobe whose scan went lowest, and each stops as soon as the V floor of its least
/// points ([`Parabolic::floor`]) lies above the lowest criterion found so far (by more than
/// [`BEAT_MARGIN`]): such a lobe would not win. A search's candidates evaluated before (its
/// scan, the end its window moved to) are looked up, not run again ([`Fresh`]'s memo). This
/// leaves the winner and its candidates as they were (stop 56: the same bits on 62 runs,
/// docs/performance.md) and saves about a third of the stages' candidates.
///
/// So `R(d, L)` is a function of the level's images, the distance and the lobe alone, and the
/// search is the minimum over a grid of lobes of a minimum over the distance: the estimate
/// moves continuously with the images, except where two lobes' minima tie.
///
/// Why (stop 54): until then the stages after the profile (an alternation between the lobe
/// estimated at the distance found and a search under it held, a walk along the index, a last
/// stage under the retro-reflective shape) evaluated each candidate by 5 iterations from the
/// last candidate's surface and glossy normals: a stage's minimum stayed near the distance it
/// started from, and its criterion depended on the order of all the candidates before it, so
/// that stages did not compare. The 256² principled 0.3 block with cast shadows of the PBR
/// renders ended at -0.31 / -0.15 / -0.76 / -1.72 / -0.98 / -0.74 % under Gaussian noise of
/// `1e-6` (seeds 0-5), and its 64² render with noise of 0.5 % of the maximum missed 1 % in 5 of 8
/// seeds (-0.55 to -2.23 %). Converged runs from the starting surface, at given distances under
/// the retro-reflective lobe (0.09), had their minimum at -0.5 % in every seed, and the lowest
/// criterion of all the lobes (docs/shiny.md, stop 54). The index trades against the distance
/// along a valley (a lower index explains the fall-off of a nearer surface: on the 256² rough
/// plastic 0.1 block the minima under the indices 1 / 1.15 / 1.45 / 1.8 / 2.1 lie at -2.1 / -1.4
/// / -0.4 / -0.1 / -0.2 %), and the lowest criterion lies near the truth, under the index 1.8.
#[allow(clippy::too_many_arguments)]
fn fresh_stages(
    solver: &mut Solver<'_>,
    problem: &Problem<'_>,
    options: &Options,
    search: &DistanceSearch,
    range: (f64, f64),
    halvings: usize,
    profiled: DistanceEstimate,
    count: &mut Count,
    progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
) -> Result<DistanceEstimate> {
    let options = one_level(options);
    let rigs = crate::pyramid::coarse_rigs(problem.rig, halvings + 1);
    let coarse = crate::pyramid::coarse_problems(problem, &rigs, &options.fit_settings(true))?;
    let level = coarse.last().unwrap_or(problem);
    // The profile's curve stays outside the stages' windows (see [`search_window`]).
    let start = on_coarser(&problem.grid, &level.grid, halvings, &profiled);
    let mut sub = Solver::new(level, &options)?;
    sub.start = solver.start;
    let saved = begin_search(&mut sub);
    let found = (|| {
        // The lobe is estimated by a run at the profile's distance that marches the cast shadows
        // of the user's policy; its surface and that surface's cast shadows start every
        // candidate (see [`Fresh`]).
        sub.restore_shadows(saved.1);
        let surface = lobe_run(&mut sub, level, mean(&start.distance), search.inner)?;
        let shadows = sub.shadows_under(&surface, saved.1)?;
        let fresh_start = Arc::new(FreshStart { surface, shadows });
        sub.search_shadows();
        let Some(estimated) = sub.lobe else {
            return Ok(None);
        };
        let alpha = estimated.alpha;
        let grid = std::iter::once(Lobe::retro(alpha, RETRO_ETA))
            .chain(FRESH_ETAS.iter().map(|&eta| Lobe::new(alpha, eta)));
        let lobes: Vec<Lobe> = std::iter::once(estimated)
            .chain(grid.filter(|&l| l != estimated))
            .collect();
        let fresh: Vec<Fresh> = lobes
            .iter()
            .map(|&lobe| Fresh {
                options,
                lobe,
                start: fresh_start.clone(),
                memo: Arc::default(),
            })
            .collect();
        // First the scan of every lobe's first window; then the lobes' searches from the one
        // whose scan went lowest, each stopped once it cannot come below the lowest criterion
        // so far (`count.beat`). The scans are looked up again, not run (see [`Fresh`]).
        let bounds = first_bounds(&start.distance, FRESH_WIDTH, range);
        let mut lowest = Vec::with_capacity(fresh.len());
        for f in &fresh {
            count.planned += NARROW_SCAN;
            let mut ev = Evaluator::new(
                (&mut sub, level.grid.n_regions),
                Vec::new(),
                1,
                (count.done, count.planned),
                Some(f.clone()),
            );
            let scan = log_scan(bounds, NARROW_SCAN);
            for i in (0..NARROW_SCAN).rev() {
                let d = scan_distance(scan, i).exp();
                ev.eval(&vec![d; level.grid.n_regions], progress)?;
            }
            count.done = ev.candidate;
            lowest.push(ev.best.1);
        }
        let mut order: Vec<usize> = (0..fresh.len()).collect();
        order.sort_by(|&a, &b| {
            let (fa, fb) = (lowest[a], lowest[b]);
            fa.is_nan().cmp(&fb.is_nan()).then(fa.total_cmp(&fb))
        });
        let mut best: Option<(f64, DistanceEstimate, Fresh)> = None;
        for f in order.into_iter().map(|i| fresh[i].clone()) {
            let window = Window {
                scan: NARROW_SCAN,
                width: FRESH_WIDTH,
                moves: FRESH_MOVES,
                lobe: false,
                coarser: false,
                grow: FRESH_GROWTH,
                vee: true,
                fresh: Some(f.clone()),
            };
            count.planned += PLANNED_REFINEMENTS;
            count.lowest = f64::NAN;
            count.beat = best.as_ref().map_or(f64::NAN, |b| b.0);
            // (Fresh candidates start from `fresh_start`, not from the window's surface.)
            let u = Vec::new();
            match search_window(
                &mut sub,
                level,
                search,
                range,
                (start.clone(), u),
                window,
                count,
                progress,
            ) {
                Ok((estimate, _)) => {
                    if best.as_ref().is_none_or(|b| count.lowest < b.0) {
                        best = Some((count.lowest, estimate, f));
                    }
                }
                // The criterion under this lobe keeps falling out of the windows.
                Err(Error::Unusable(_)) => {}
                Err(e) => return Err(e),
            }
        }
        count.beat = f64::NAN;
        let Some((_, estimate, fresh)) = best else {
            return Ok(None);
        };
        // The best candidate once more, for its surface: carried up to `problem`, its gauge
        // there is the distance found (as in [`fine_estimate`]).
        let mut ev = Evaluator::new(
            (&mut sub, level.grid.n_regions),
            Vec::new(),
            1,
            (count.done, count.planned + 1),
            Some(fresh),
        );
        ev.eval(&estimate.distance, progress)?;
        count.done = ev.candidate;
        let u = carry_up(problem, &coarse, std::mem::take(&mut ev.u))?;
        let gauge = problem.grid.region_means(&u);
        Ok(Some(DistanceEstimate {
            distance: gauge.iter().map(|&g| problem.geometry.depth(g)).collect(),
            ..on_finer(&problem.grid, &level.grid, halvings, estimate)
        }))
    })();
    end_search(&mut sub, saved);
    Ok(found?.unwrap_or(profiled))
}

/// Candidates evaluated so far and planned, over the stages of a search (for its progress).
struct Count {
    done: usize,
    planned: usize,
    /// The lowest (mean) criterion of a candidate since it was last reset (NaN: none; see
    /// [`fresh_stages`]).
    lowest: f64,
    /// The criterion a search must come below to matter (NaN: none): once a lower bound of
    /// its minimum ([`Parabolic::floor`]) is above it, the search stops (see [`fresh_stages`]).
    beat: f64,
}

/// The window in which [`search_window`] refines a wide estimate.
#[derive(Debug, Clone)]
struct Window {
    /// Candidates of its scan.
    scan: usize,
    /// Its half-width, as a factor of the distance.
    width: f64,
    /// How many times it may move to an end where the residual keeps falling.
    moves: usize,
    /// Whether the glossy lobe is estimated afresh at the wide estimate and for every candidate
    /// (a glossy search, see [`search_with`]).
    lobe: bool,
    /// Whether the wide estimate came from a coarser level (see [`search_stages`]): its curve is
    /// then scaled to this level's residuals where the two meet.
    coarser: bool,
    /// The factor on its log half-width at each move (1: it moves at its width; see
    /// [`FRESH_GROWTH`]).
    grow: f64,
    /// Whether its refinement steps to the vertex of a V rather than a parabola (see
    /// [`vee_minimum`]).
    vee: bool,
    /// Whether its candidates are evaluated afresh (see [`Fresh`]).
    fresh: Option<Fresh>,
}

/// Refines the `wide` estimate of a search (see [`search_with`]) in a window `window.width`
/// either side of it, which moves towards an end where the residual keeps falling. With
/// `window.lobe` every candidate estimates the lobe (once, see [`PROFILE_INNER`]), the first
/// starting under the lobe the wide search held. The curve keeps the wide search's candidates
/// outside the last window.
#[allow(clippy::too_many_arguments)]
fn search_window(
    solver: &mut Solver<'_>,
    problem: &Problem<'_>,
    search: &DistanceSearch,
    range: (f64, f64),
    wide: (DistanceEstimate, Vec<f64>),
    window: Window,
    count: &mut Count,
    progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
) -> Result<(DistanceEstimate, Vec<f64>)> {
    if window.lobe {
        // The first candidate starts under the lobe the wide search held (a run at the wide
        // estimate only where it had none): its own estimate at iteration 3 replaces it. (Until
        // stop 57 a run at the wide estimate estimated the window's first lobe: 0.2 CPU s of
        // the 256² glossy bumps' search, with the same PBR table within its noise.)
        hold_lobe(solver, problem, mean(&wide.0.distance), search.inner)?;
        solver.hold_lobe = false;
    }
    // (Back to false where the window ends; on an error [`end_search`] resets it.)
    solver.lobe_once = window.lobe;
    let window_search = DistanceSearch {
        scan: window.scan,
        inner: match window.lobe {
            true => search.inner.min(PROFILE_INNER),
            false => search.inner,
        },
        ..*search
    };
    let (wide, u) = wide;
    let clip = |(lo, hi): (f64, f64)| (lo.max(range.0), hi.min(range.1));
    let mut width = window.width;
    let mut bounds = first_bounds(&wide.distance, width, range);
    let mut moves = 0;
    loop {
        let start = try_copy(&u, "the depths")?;
        let searched = search_refined(
            solver,
            problem,
            &window_search,
            bounds,
            start,
            (window.vee, window.fresh.clone()),
            count,
            progress,
        )?;
        if let Searched::Edge { near, .. } = searched {
            let end = if near { bounds.0 } else { bounds.1 };
            let inside = if near { end > range.0 } else { end < range.1 };
            if inside && moves < window.moves {
                moves += 1;
                if window.grow != 1.0 {
                    width = width.powf(window.grow);
                }
                bounds = clip((end / width, end * width));
                continue;
            }
        }
        let (mut estimate, u) = searched.found(bounds)?;
        for ((curve, before), &centre) in estimate
            .curve
            .iter_mut()
            .zip(wide.curve)
            .zip(&wide.distance)
        {
            let scale = match window.coarser {
                true => level_ratio(curve, &before, centre),
                false => 1.0,
            };
            curve.extend(
                before
                    .into_iter()
                    .filter(|&(d, _)| d < bounds.0 || d > bounds.1)
                    .map(|(d, r)| (d, r * scale)),
            );
            curve.sort_by(|a, b| a.0.total_cmp(&b.0));
        }
        estimate.range = range;
        solver.lobe_once = false;
        return Ok((estimate, u));
    }
}

/// The first bounds of a [`search_window`] of half-width `width` around `distance` (per region),
/// within `range`.
fn first_bounds(distance: &[f64], width: f64, range: (f64, f64)) -> (f64, f64) {
    let near = distance.iter().copied().fold(f64::INFINITY, f64::min);
    let far = distance.iter().copied().fold(0.0, f64::max);
    ((near / width).max(range.0), (far * width).min(range.1))
}

/// The log-distance of the nearest candidate of a scan of `scan` candidates over `range` and
/// the step between them (see [`scan_distance`]).
fn log_scan(range: (f64, f64), scan: usize) -> (f64, f64) {
    let (ln_near, ln_far) = (range.0.ln(), range.1.ln());
    (ln_near, (ln_far - ln_near) / (scan - 1) as f64)
}

/// The log-distance of the `i`-th candidate (from the near end) of a scan (see [`log_scan`]).
fn scan_distance((ln_near, step): (f64, f64), i: usize) -> f64 {
    ln_near + step * i as f64
}

/// The ratio of a window's residual to a coarser level's where they meet: at the window's
/// candidate nearest to `centre`, against the coarser curve `wide` interpolated linearly in
/// log-distance there (1 when either is missing).
fn level_ratio(window: &[(f64, f64)], wide: &[(f64, f64)], centre: f64) -> f64 {
    let Some(&(d, r)) = window.iter().min_by(|a, b| {
        (a.0 / centre)
            .ln()
            .abs()
            .total_cmp(&(b.0 / centre).ln().abs())
    }) else {
        return 1.0;
    };
    let at = wide.partition_point(|&(x, _)| x < d);
    let coarse = match (at.checked_sub(1).map(|i| wide[i]), wide.get(at)) {
        (Some((x0, r0)), Some(&(x1, r1))) if x1 > x0 => {
            let t = (d / x0).ln() / (x1 / x0).ln();
            r0 + t * (r1 - r0)
        }
        (Some((_, r0)), _) => r0,
        (None, Some(&(_, r1))) => r1,
        (None, None) => f64::NAN,
    };
    let ratio = r / coarse;
    match ratio.is_finite() && ratio > 0.0 {
        true => ratio,
        false => 1.0,
    }
}

/// Under the glossy model with a lobe to estimate, the candidates are compared under one lobe
/// (the caller releases it): the one estimated by a run at `distance` (the middle of the
/// search's range, or the distance checked) with at least `inner` iterations. The final run
/// of a search estimates it again at the distance found.
///
/// (Stop 49: with `LOBE_AT[1]` iterations for the search's runs, the lobe being estimated at
/// the iterations `LOBE_AT` and the run's surface dropped, the candidates after agreed with
/// those of 15 iterations to 1e-7 in their residuals on the glossy bumps, but the PBR shadows
/// principled 0.3 block's search ended at +1.45 % instead of -0.28 %: not kept.)
fn hold_lobe(
    solver: &mut Solver<'_>,
    problem: &Problem<'_>,
    distance: f64,
    inner: usize,
) -> Result<()> {
    if !solver.estimates_lobe() {
        return Ok(());
    }
    if solver.lobe.is_none() {
        lobe_run(solver, problem, distance, inner)?;
    }
    solver.hold_lobe = true;
    Ok(())
}

/// [`hold_lobe`] with a lobe to estimate (`solver.lobe` unset): the lobe is estimated by a run
/// from the starting surface at `distance` and held; returns that run's surface.
fn lobe_run(
    solver: &mut Solver<'_>,
    problem: &Problem<'_>,
    distance: f64,
    inner: usize,
) -> Result<Vec<f64>> {
    let gauge = vec![problem.geometry.unknown(distance); problem.grid.n_regions];
    let mut u = problem.u0.to_vec("the depths")?;
    problem.grid.apply_gauge(&mut u, &gauge);
    if solver.estimates_lobe() && solver.lobe.is_none() {
        let iterations = inner.max(crate::solver::LOBE_AT[1]);
        solver.iterate(&mut u, &gauge, iterations, 0.0, &mut |_| Control::Continue)?;
        solver.hold_lobe = true;
    }
    Ok(u)
}

/// The outcome of a scan and its refinement.
enum Searched {
    /// The estimate and the warm state at it.
    Found(DistanceEstimate, Vec<f64>),
    /// The residual of `region` keeps falling towards the near (`near`) or far end of the range.
    Edge { region: usize, near: bool },
}

impl Searched {
    /// The estimate, or the error that the distance lies outside `range`.
    fn found(self, range: (f64, f64)) -> Result<(DistanceEstimate, Vec<f64>)> {
        match self {
            Searched::Found(estimate, u) => Ok((estimate, u)),
            Searched::Edge { region, near } => {
                let side = if near { "near" } else { "far" };
                Err(Error::Unusable(format!(
                    "the photometric residual of region {region} keeps falling towards the {side} end of the distance \
                     search range ({:.4}, {:.4}): the distance lies outside it or cannot be observed; \
                     widen depth_range",
                    range.0, range.1
                )))
            }
        }
    }
}

/// The scan of `range` (log-spaced, far to near) and the golden-section refinement of each
/// region's minimum, warm-starting from the depths `u` (with `vee`, see [`Parabolic`]).
#[allow(clippy::too_many_arguments)]
fn search_refined(
    solver: &mut Solver<'_>,
    problem: &Problem<'_>,
    search: &DistanceSearch,
    range: (f64, f64),
    u: Vec<f64>,
    (vee, fresh): (bool, Option<Fresh>),
    count: &mut Count,
    progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
) -> Result<Searched> {
    let regions = problem.grid.n_regions;
    let scan = search.scan.max(3);
    let (ln_near, step) = log_scan(range, scan);
    let tolerance = search.precision.max(1e-9);
    let mut ev = Evaluator::new(
        (solver, regions),
        u,
        search.inner.max(1),
        (count.done, count.planned),
        fresh,
    );
    let searched = refine_scan(
        &mut ev,
        regions,
        scan,
        (ln_near, step),
        tolerance,
        (vee, count.beat),
        progress,
    );
    count.done = ev.candidate;
    count.planned = count.planned.max(ev.candidates);
    count.lowest = lower(count.lowest, ev.best.1);
    let distance = match searched? {
        Ok(distance) => distance,
        Err((region, near)) => return Ok(Searched::Edge { region, near }),
    };
    for curve in &mut ev.curve {
        curve.sort_by(|a, b| a.0.total_cmp(&b.0));
    }
    let estimate = DistanceEstimate {
        distance,
        curve: ev.curve,
        range,
    };
    Ok(Searched::Found(estimate, ev.u))
}

/// The candidates of [`search_refined`]: each region's distance, or the first region whose
/// residual keeps falling towards the near (true) or far end of the scan. With a criterion to
/// `beat` (not NaN), the refinement stops at the least points once the mean of the regions'
/// lower bounds ([`Parabolic::floor`]) is above it by more than [`BEAT_MARGIN`]: none of its
/// candidates would then come below it.
#[allow(clippy::type_complexity)]
fn refine_scan(
    ev: &mut Evaluator<'_, '_>,
    regions: usize,
    scan: usize,
    (ln_near, step): (f64, f64),
    tolerance: f64,
    (vee, beat): (bool, f64),
    progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
) -> Result<std::result::Result<Vec<f64>, (usize, bool)>> {
    // Coarse scan from far to near (surfaces start flat; far is the gentlest start).
    let mut surfaces = Surfaces::default();
    let mut scanned: Vec<(f64, Vec<f64>)> = Vec::with_capacity(scan);
    for i in (0..scan).rev() {
        let x = scan_distance((ln_near, step), i);
        let d = x.exp();
        scanned.push((d, ev.eval(&vec![d; regions], progress)?));
        surfaces.add(vec![x; regions], &ev.u)?;
        let points: Vec<Vec<(f64, f64)>> = (0..regions)
            .map(|r| {
                scanned
                    .iter()
                    .zip((0..scan).rev())
                    .map(|((_, f), i)| (scan_distance((ln_near, step), i), f[r]))
                    .collect()
            })
            .collect();
        surfaces.prune(&points);
    }
    scanned.reverse();
    // Per region, the scan's minimum must lie inside it.
    let mut points: Vec<Vec<(f64, f64)>> = Vec::with_capacity(regions);
    for r in 0..regions {
        let best = (0..scan)
            .min_by(|&a, &b| scanned[a].1[r].total_cmp(&scanned[b].1[r]))
            .unwrap_or(0);
        if best == 0 || best == scan - 1 {
            return Ok(Err((r, best == 0)));
        }
        points.push(
            (0..scan)
                .map(|i| (scan_distance((ln_near, step), i), scanned[i].1[r]))
                .collect(),
        );
    }
    let mut state: Vec<Parabolic> = points
        .into_iter()
        .map(|p| Parabolic {
            vee,
            ..Parabolic::new(p)
        })
        .collect();
    for _ in 0..MAX_REFINEMENTS {
        let floor = mean(&state.iter().map(Parabolic::floor).collect::<Vec<_>>());
        if floor > beat * (1.0 + BEAT_MARGIN) {
            break;
        }
        let trial: Vec<Option<f64>> = state.iter_mut().map(|s| s.next(tolerance)).collect();
        if trial.iter().all(Option::is_none) {
            break;
        }
        // A region that is done is evaluated at its estimate (not recorded).
        let x: Vec<f64> = trial
            .iter()
            .zip(&state)
            .map(|(t, s)| t.unwrap_or_else(|| s.estimate()))
            .collect();
        // Each region starts from the surface evaluated nearest to its candidate.
        surfaces.start(&x, &ev.solver.problem().grid.region_of_unknown, &mut ev.u);
        let d: Vec<f64> = x.iter().map(|x| x.exp()).collect();
        let f = ev.eval(&d, progress)?;
        for ((s, t), &f) in state.iter_mut().zip(&trial).zip(&f) {
            if let Some(x) = *t {
                s.insert(x, f);
            }
        }
        surfaces.add(x, &ev.u)?;
        let points: Vec<Vec<(f64, f64)>> = state.iter().map(|s| s.points.clone()).collect();
        surfaces.prune(&points);
    }
    Ok(Ok(state.iter().map(|s| s.estimate().exp()).collect()))
}

/// The surfaces of the candidates that bracket some region's minimum, which start the
/// refinement's candidates: a candidate started from the last one evaluated, often far away
/// (the scan ends at the near end of the range), is not converged after a few iterations and
/// its residual is too high (seen as outliers of 5-10 times the curve on noise-free scenes).
#[derive(Default)]
struct Surfaces {
    /// Per surface, its log-distance per region and its unknowns.
    kept: Vec<(Vec<f64>, Vec<f64>)>,
}

impl Surfaces {
    fn add(&mut self, x: Vec<f64>, u: &[f64]) -> Result<()> {
        self.kept
            .push((x, try_copy(u, "the distance search's surfaces")?));
        Ok(())
    }

    /// Keeps the surfaces of the least point of some region's `points` (`(x, residual)`) and of
    /// its neighbours.
    fn prune(&mut self, points: &[Vec<(f64, f64)>]) {
        let mut keep: Vec<Vec<f64>> = vec![Vec::new(); points.len()];
        for (r, p) in points.iter().enumerate() {
            let mut sorted = p.clone();
            sorted.sort_by(|a, b| a.0.total_cmp(&b.0));
            let best = (0..sorted.len())
                .min_by(|&a, &b| sorted[a].1.total_cmp(&sorted[b].1))
                .unwrap_or(0);
            keep[r] = (best.saturating_sub(1)..(best + 2).min(sorted.len()))
                .map(|i| sorted[i].0)
                .collect();
        }
        self.kept
            .retain(|(x, _)| x.iter().zip(&keep).any(|(x, k)| k.contains(x)));
    }

    /// Sets `u` to the surface evaluated nearest to `x` in each region (unchanged without any).
    fn start(&self, x: &[f64], region_of_unknown: &[u32], u: &mut [f64]) {
        let nearest: Vec<Option<usize>> = (0..x.len())
            .map(|r| {
                (0..self.kept.len()).min_by(|&a, &b| {
                    let da = (self.kept[a].0[r] - x[r]).abs();
                    let db = (self.kept[b].0[r] - x[r]).abs();
                    da.total_cmp(&db)
                })
            })
            .collect();
        for ((value, &region), i) in u.iter_mut().zip(region_of_unknown).zip(0..) {
            if let Some(Some(k)) = nearest.get(region as usize) {
                *value = self.kept[*k].1[i];
            }
        }
    }
}

/// The margin (relative) by which a lower bound must be above the criterion to beat before a
/// search stops (see [`refine_scan`]): the bound of [`Parabolic::floor`] assumes a V of equal
/// slopes, and the criterion's minimum may be rounded or lopsided (stop 56, on the traces of 62
/// runs: 77 of 2360 floors were above their lobe's lowest criterion, 58 by at most 0.2 %, 19 on
/// noise-free renders by up to 8.5 times; no winner changed, as those lobes won by far or were
/// searched first: docs/performance.md).
const BEAT_MARGIN: f64 = 2e-3;

/// At most this many refinement steps follow a scan (golden-section search from the scan's
/// bracket to 1e-3 takes 15 with the default scan; successive parabolic interpolation takes
/// 3-6 on smooth residual curves).
const MAX_REFINEMENTS: usize = 20;

/// One region's refinement of a scan's minimum by safeguarded successive parabolic
/// interpolation in log-distance `x` (Brent's method without derivatives).
///
/// The evaluated points bracket the minimum: the least one is never at an end. The next
/// candidate is the vertex of the parabola through the least point and its neighbours,
///
/// `x* = b - ((b - a)² (f_b - f_c) - (b - c)² (f_b - f_a)) / (2 ((b - a)(f_b - f_c) - (b - c)(f_b - f_a)))`,
///
/// unless that step is longer than half the step before the last one, or it falls outside the
/// bracket: then a golden-section step into the larger side of the bracket. A candidate keeps
/// at least `tolerance` from the least point (into the larger side of the bracket when the
/// vertex is nearer), so that the bracket keeps shrinking. The
/// refinement is done when the bracket is at most `2 tolerance` wide; the estimate is then the
/// vertex through its three points. With `vee` the vertex is a V's ([`vee_minimum`]) instead,
/// under the same safeguards.
struct Parabolic {
    /// The evaluated `(x, residual)`, sorted by `x`.
    points: Vec<(f64, f64)>,
    /// The last two steps (for the safeguard).
    steps: [f64; 2],
    /// The estimate once done.
    done: Option<f64>,
    /// Whether the vertex is a V's ([`vee_minimum`]) rather than a parabola's.
    vee: bool,
}

impl Parabolic {
    fn new(mut points: Vec<(f64, f64)>) -> Parabolic {
        points.sort_by(|a, b| a.0.total_cmp(&b.0));
        let width = points.last().map_or(0.0, |p| p.0) - points.first().map_or(0.0, |p| p.0);
        Parabolic {
            points,
            steps: [width, width],
            done: None,
            vee: false,
        }
    }

    /// The index of the least point (NaN residuals last).
    fn best(&self) -> usize {
        (0..self.points.len())
            .min_by(|&a, &b| {
                let (fa, fb) = (self.points[a].1, self.points[b].1);
                fa.is_nan().cmp(&fb.is_nan()).then(fa.total_cmp(&fb))
            })
            .unwrap_or(0)
    }

    /// The estimate: once done, its value; before, the least point.
    fn estimate(&self) -> f64 {
        self.done.unwrap_or_else(|| self.points[self.best()].0)
    }

    /// The next candidate, or None once done.
    fn next(&mut self, tolerance: f64) -> Option<f64> {
        if self.done.is_some() {
            return None;
        }
        let b = self.best();
        if b == 0 || b + 1 >= self.points.len() {
            self.done = Some(self.points[b].0);
            return None;
        }
        let [(a, fa), (m, fm), (c, fc)] = [self.points[b - 1], self.points[b], self.points[b + 1]];
        let vertex = match self.vee {
            true => vee_minimum([a, m, c], [fa, fm, fc]),
            false => parabola_minimum([a, m, c], [fa, fm, fc]),
        };
        if c - a <= 2.0 * tolerance * (1.0 + 1e-9) {
            self.done = Some(vertex);
            return None;
        }
        let step = vertex - m;
        let golden = 0.5 * (3.0 - 5f64.sqrt());
        let parabolic = step.abs() < 0.5 * self.steps[0] && vertex > a && vertex < c;
        let mut x = match parabolic {
            true => vertex,
            false if m - a > c - m => m - golden * (m - a),
            false => m + golden * (c - m),
        };
        // At least `tolerance` from the least point, into the larger side of the bracket, so
        // that the bracket shrinks to `2 tolerance` around a vertex that stays put.
        if (x - m).abs() < tolerance {
            x = if m - a > c - m {
                m - tolerance
            } else {
                m + tolerance
            };
        }
        let gap = 0.5 * tolerance;
        x = x.clamp(a + gap.min(0.5 * (m - a)), c - gap.min(0.5 * (c - m)));
        self.steps = [self.steps[1], (x - m).abs()];
        Some(x)
    }

    /// A lower bound of the least residual: the bottom of the V of equal slopes (the steeper of
    /// the least point's two chords) through the least point and its neighbours, as
    /// [`vee_minimum`] places it; minus infinity without a bracket. Exact for a V whose slopes
    /// are equal, low for a convex curve that is symmetric about its minimum; it can be high
    /// for a rounded bottom or unequal slopes (see [`BEAT_MARGIN`]).
    fn floor(&self) -> f64 {
        let b = self.best();
        if b == 0 || b + 1 >= self.points.len() {
            return f64::NEG_INFINITY;
        }
        let [(a, fa), (m, fm), (c, fc)] = [self.points[b - 1], self.points[b], self.points[b + 1]];
        let slope = ((fa - fm) / (m - a)).max((fc - fm) / (c - m));
        if !(slope > 0.0 && slope.is_finite()) {
            return f64::NEG_INFINITY;
        }
        fm - slope * (vee_minimum([a, m, c], [fa, fm, fc]) - m).abs()
    }

    /// Records the residual `f` at `x`.
    fn insert(&mut self, x: f64, f: f64) {
        let at = self.points.partition_point(|p| p.0 < x);
        self.points.insert(at, (x, f));
    }
}

/// A solver failure after the distance search, with the distance it found (`found`) in the
/// message: a far-off estimate (seen on glossy objects, see docs/method.md) can pull the surface
/// through a light, and the user should then give the distance.
fn after_search(error: Error, found: Option<f64>) -> Error {
    match (error, found) {
        (Error::Solver(message), Some(d)) => Error::Solver(format!(
            "{message} (after depth=\"auto\" found a working distance of {}: if that is far from \
             the truth, give the distance, or a depth_range that brackets it)",
            crate::error::g6(d)
        )),
        (error, _) => error,
    }
}

/// Estimates the working distance of every region, then reconstructs at it (warm-started).
///
/// With a coarse-to-fine pyramid ([`Options::levels`](crate::Options::levels)) the search runs on the coarsest level
/// only; the finer levels start from its surface and keep its gauge, so the full resolution
/// costs about what a run with a known distance costs.
///
/// A glossy run whose model is dropped after the search (an estimated lobe as broad as the
/// diffuse part, [`crate::solver::MATTE_ROUGHNESS`], or fits without some lights predicting
/// them worse than the Lambertian ones, see [`crate::LobeCheck`]) searched under a model the
/// images do not support: the search is then made again under the Lambertian model, and the
/// result is that of `depth="auto"` with the Lambertian model, bit for bit, as at a known
/// distance, with the glossy run's verdict (`matte_lobe`, `lobe_check`) and its time added.
/// Stop 51: hehe12 (8 LEDs, skin) with the glossy model had found 259.3 mm where the
/// Lambertian search finds 199.6 mm, then dropped the model and kept that distance (its
/// held-out RMS 1.01 against 0.056).
pub fn reconstruct_auto(
    problem: &Problem<'_>,
    options: &Options,
    search: &DistanceSearch,
    progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
) -> Result<(Reconstruction, DistanceEstimate)> {
    let (result, estimate) = reconstruct_auto_once(problem, options, search, progress)?;
    if !options.reflectance.is_glossy() || result.matte_lobe.is_none() {
        return Ok((result, estimate));
    }
    let lambertian = Options {
        reflectance: crate::Reflectance::Lambertian,
        ..*options
    };
    let (mut again, estimate) = reconstruct_auto_once(problem, &lambertian, search, progress)?;
    again.matte_lobe = result.matte_lobe;
    again.lobe_check = result.lobe_check;
    again.timings.add(&result.timings);
    again.timings.total += result.timings.total;
    Ok((again, estimate))
}

/// [`reconstruct_auto`] under the model of `options` to the end.
fn reconstruct_auto_once(
    problem: &Problem<'_>,
    options: &Options,
    search: &DistanceSearch,
    progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
) -> Result<(Reconstruction, DistanceEstimate)> {
    options.validate()?;
    check_observable(problem)?;
    problem.check_memory(options)?;
    crate::refine::check_refinable(&options.refine, problem.rig.n_lights())?;
    crate::problem::check_fittable(problem, &options.fit_settings(false))?;
    let range = search_range(problem, search)?;
    with_threads(options.threads, || {
        let start = Instant::now();
        // The working distance is estimated with the rig's scale: a common scale of the light
        // positions would trade against it (see [`crate::refine`]).
        let options = &Options {
            refine: Refine {
                fix_scale: true,
                ..options.refine
            },
            ..*options
        };
        let mut coarse_estimate: Option<(DistanceEstimate, Grid)> = None;
        let mut at_coarsest = |solver: &mut Solver<'_>,
                               u: &mut Vec<f64>,
                               progress: &mut (dyn FnMut(&IterationStats) -> Control + Send)|
         -> Result<Vec<f64>> {
            let coarse = solver.problem();
            let coarse_search = DistanceSearch {
                inner: search.inner.max(COARSE_INNER),
                ..*search
            };
            let (estimate, warm) =
                search_with(solver, coarse, options, &coarse_search, range, progress)?;
            *u = warm;
            let gauge = estimate
                .distance
                .iter()
                .map(|&d| coarse.geometry.unknown(d))
                .collect();
            coarse_estimate = Some((estimate, coarse.grid.clone()));
            Ok(gauge)
        };
        let mut u = problem.u0.to_vec("the depths")?;
        let coarse = coarse_to_fine(
            problem,
            options,
            &mut u,
            start,
            progress,
            Some(&mut at_coarsest),
            None,
        );
        let found = coarse_estimate.as_ref().map(|(e, _)| mean(&e.distance));
        let coarse = coarse.map_err(|e| after_search(e, found))?;
        let carried = coarse.carried;
        let mut solver = Solver::new(problem, options)?;
        solver.start = start;
        let mut history = solver.carry(coarse)?;
        let (estimate, gauge) = if carried {
            let (coarse, coarse_grid) = coarse_estimate.expect("the coarsest level ran the search");
            let gauge = problem.grid.region_means(&u);
            let estimate = fine_estimate(problem, &coarse_grid, coarse, &gauge);
            (estimate, gauge)
        } else {
            let (estimate, warm) =
                search_with(&mut solver, problem, options, search, range, progress)?;
            u = warm;
            let gauge: Vec<f64> = estimate
                .distance
                .iter()
                .map(|&d| problem.geometry.unknown(d))
                .collect();
            problem.grid.apply_gauge(&mut u, &gauge);
            (estimate, gauge)
        };
        // The lights seen from the surface at the estimated distance.
        crate::problem::check_light_geometry(problem.rig, &problem.geometry, &u)?;
        let (fine, converged) = if carried {
            solver.iterate(&mut u, &gauge, options.iterations, options.tol, progress)
        } else {
            solver.iterate_first(&mut u, &gauge, progress)
        }
        .map_err(|e| after_search(e, Some(mean(&estimate.distance))))?;
        history.extend(fine);
        let (rounds, converged) = solver
            .interreflect(&mut u, &gauge, converged, progress)
            .map_err(|e| after_search(e, Some(mean(&estimate.distance))))?;
        history.extend(rounds);
        Ok((solver.finish(&u, history, converged)?, estimate))
    })?
}

/// The estimate per full-resolution region from the coarsest level's: the distance is the
/// region's gauge after carrying the coarse surface up; the curve is that of the coarse region
/// holding the region's pinned vertex.
fn fine_estimate(
    problem: &Problem<'_>,
    coarse_grid: &Grid,
    coarse: DistanceEstimate,
    gauge: &[f64],
) -> DistanceEstimate {
    let curve = coarse_regions(
        &problem.grid,
        coarse_grid,
        levels_below(&problem.grid, coarse_grid),
    )
    .into_iter()
    .map(|region| coarse.curve[region.min(coarse.curve.len() - 1)].clone())
    .collect();
    DistanceEstimate {
        distance: gauge.iter().map(|&g| problem.geometry.depth(g)).collect(),
        curve,
        range: coarse.range,
    }
}

/// How many halvings lead from `fine` to `coarse`.
fn levels_below(fine: &Grid, coarse: &Grid) -> u32 {
    let (mut h, mut w, mut n) = (fine.height, fine.width, 0);
    while (h, w) != (coarse.height, coarse.width) && h > 1 {
        h = h.div_ceil(2);
        w = w.div_ceil(2);
        n += 1;
    }
    n
}

/// The longest side, in pixels, of the level on which [`check_distance`] compares distances.
pub const CHECK_SIDE: usize = 32;

/// The factors of the given distance that [`check_distance`] evaluates (log-spaced from 1/2 to
/// 2, the given distance among them).
const CHECK_FACTORS: [f64; 9] = [0.5, 0.63, 0.79, 0.89, 1.0, 1.12, 1.26, 1.59, 2.0];

/// Local/global iterations per evaluation of [`check_distance`] (warm-started from the previous
/// candidate's surface, far to near).
const CHECK_INNER: usize = 10;

/// [`CHECK_INNER`] under the glossy model, whose fits cost several times the Lambertian ones
/// (the check's were a third of a glossy run at 256²). Each candidate's fits go on from the
/// glossy normals of the candidate before. With 5 iterations instead of 10 the check's found
/// distance moved by at most 0.1 % and its residual ratio by at most 7 % on the synthetic
/// glossy bumps (128², 0.5 % noise, at 0.75, 1 and 1.25 times their distance) and four Mitsuba
/// renders of `benchmarks/pbr` (at 0.8, 1 and 1.25 times), ratios 1.34 to 76 off the distance
/// and 1 at it, and no verdict changed. With 3 instead of 5 (stop 46; the same scenes, the
/// synthetic ones over seeds 0-2, four renders: principled 0.3 bumps, rough plastic 0.3 bumps,
/// principled 0.5 sphere, rough plastic 0.1 torus) the found distance moved by at most 0.06 %
/// (0.44 % on the sphere at its distance: 1.0055 -> 1.0010 times it), the ratio by at most
/// 2.5 % (1.81 to 11.1 off the distance, 1 at it), no verdict changed, and the check's CPU
/// time on the glossy 256² bumps fell by a sixth to a quarter (0.21 -> 0.18 s; its coarse
/// levels and each candidate's local step do not shrink).
/// Five candidates instead of nine (1/2, 0.79, 1, 1.26, 2) kept the verdicts too but moved the
/// found distance by up to 5 % (the parabola through coarser points), so the nine stay.
const CHECK_INNER_GLOSSY: usize = 3;

/// A given working distance compared with the ones around it on a coarse level.
///
/// Every candidate is evaluated the same way on the same coarse level (a few warm-started
/// iterations at that distance): `residual_given` at the given gauge, `residual_found` at the
/// best candidate, `found` the minimum of a parabola in log-distance through the best candidate
/// and its neighbours. See [`DistanceCheck::looks_wrong`].
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub struct DistanceCheck {
    /// The given distance (the mean of the regions' gauges, as depths).
    pub given: f64,
    /// The distance the images fit best on the coarse level (the mean over regions); at an end
    /// of the range (half or twice the given distance) when the residual keeps falling there.
    pub found: f64,
    /// The search's criterion (see [`DistanceEstimate::curve`]) on the coarse level at the given
    /// distance.
    pub residual_given: f64,
    /// The same at the best candidate.
    pub residual_found: f64,
    /// Pixels of the coarse level's longer side.
    pub side: usize,
}

/// The residual ratio above which, together with [`WRONG_DISTANCE_OFFSET`], a given distance
/// looks wrong (chosen by measurement: see `benchmarks/distance_check.py`). On synthetic scenes
/// the ratio is exactly 1 within 5 % of the true distance (the given candidate is the best) and
/// 1.7 to 13 beyond 10 %; on real captures, whose residual is mostly model error, it is only 1.05
/// to 1.2 at 20-25 % off, hence the low threshold; the offset guard keeps it from firing on a
/// slightly biased minimum.
pub const WRONG_DISTANCE_RATIO: f64 = 1.02;

/// The relative offset `|given / found - 1|` above which, together with
/// [`WRONG_DISTANCE_RATIO`], a given distance looks wrong.
pub const WRONG_DISTANCE_OFFSET: f64 = 0.1;

impl DistanceCheck {
    /// `residual_given / residual_found`.
    pub fn ratio(&self) -> f64 {
        self.residual_given / self.residual_found
    }

    /// `given / found - 1`.
    pub fn offset(&self) -> f64 {
        self.given / self.found - 1.0
    }

    /// Whether the images fit another distance clearly better: the residual at the given
    /// distance is more than `WRONG_DISTANCE_RATIO` times the best one, and the distances differ
    /// by more than `WRONG_DISTANCE_OFFSET`.
    pub fn looks_wrong(&self) -> bool {
        self.ratio() > WRONG_DISTANCE_RATIO && self.offset().abs() > WRONG_DISTANCE_OFFSET
    }
}

/// Checks the working distance `problem` was given (its gauge): on a coarse level (longer side
/// at most [`CHECK_SIDE`] pixels) the residual at the given distance is compared with those at
/// 1/2 to 2 times it.
///
/// Returns None when the rig cannot reveal the distance (directional lights only, or 3 lights
/// or fewer). The cost, 90 local/global iterations on at most `CHECK_SIDE`² pixels (27 under
/// the glossy model), does not grow with the image size. Under the glossy model with a lobe to
/// estimate, a run at the given distance estimates it first; options with the lobe of a
/// reconstruction at that distance ([`Reconstruction::reflectance`](crate::Reconstruction::reflectance))
/// compare the candidates under it instead.
pub fn check_distance(problem: &Problem<'_>, options: &Options) -> Result<Option<DistanceCheck>> {
    check_distance_on(problem, options, None)
}

/// [`check_distance`] and then [`reconstruct`](crate::reconstruct) under the Lambertian
/// model, on one pyramid: the check's coarse levels (down to [`CHECK_SIDE`]
/// pixels a side) are the reconstruction's coarse levels and more (the same rigs, the same
/// settings: `coarsen` reads only `dark` and `saturation`), so they are made once instead of
/// twice (at 12 MP x 16 lights the level at 3 MP alone reads the whole stack). Same bits as
/// the two calls. Under the glossy model the check compares distances under the lobe of the
/// result: then this is the two calls, the check after the reconstruction.
pub fn reconstruct_checked(
    problem: &Problem<'_>,
    options: &Options,
    progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
) -> Result<(Reconstruction, Option<DistanceCheck>)> {
    if options.reflectance.is_glossy() {
        let r = crate::solver::reconstruct(problem, options, progress)?;
        let options = options.with_reflectance(r.reflectance());
        let checked = check_distance(problem, &options)?;
        return Ok((r, checked));
    }
    options.validate()?;
    problem.check_memory(options)?;
    let (h, w) = problem.shape();
    let levels = crate::pyramid::levels_for(h, w, options.levels).max(check_levels(problem).0);
    let t = Instant::now();
    let rigs = crate::pyramid::coarse_rigs(problem.rig, levels);
    let coarse = with_threads(options.threads, || {
        crate::pyramid::coarse_problems(problem, &rigs, &options.fit_settings(true))
    })??;
    let made = t.elapsed();
    crate::memory::trace("checked: coarse problems made");
    let checked = check_distance_on(problem, options, Some(&coarse))?;
    crate::memory::trace("checked: distance checked");
    let mut r = crate::solver::reconstruct_on(problem, options, progress, Some(coarse))?;
    // The levels were made before the run's clock started: their time counts as its pyramid's
    // (as when the run makes them), the check's own iterations still outside the timings.
    r.timings.pyramid += made;
    r.timings.total += made;
    Ok((r, checked))
}

/// The pyramid levels of [`check_distance`] (the full resolution counted): down to a longer
/// side of at most [`CHECK_SIDE`] pixels; and that longer side of the coarsest level.
pub(crate) fn check_levels(problem: &Problem<'_>) -> (usize, usize) {
    let mut levels = 1;
    let (mut h, mut w) = (problem.grid.height, problem.grid.width);
    while h.max(w) > CHECK_SIDE {
        h = h.div_ceil(2);
        w = w.div_ceil(2);
        levels += 1;
    }
    (levels, h.max(w))
}

/// [`check_distance`] on the coarse levels `pyramid` when the caller has made them
/// ([`crate::pyramid::coarse_problems`] with at least [`check_levels`] levels, see
/// [`reconstruct_checked`]); made here otherwise.
pub(crate) fn check_distance_on(
    problem: &Problem<'_>,
    options: &Options,
    pyramid: Option<&[Problem<'_>]>,
) -> Result<Option<DistanceCheck>> {
    options.validate()?;
    if check_observable(problem).is_err() {
        return Ok(None);
    }
    let (levels, side) = check_levels(problem);
    let options = Options {
        levels: 1,
        refine: Refine {
            position: false,
            fix_scale: true,
            ..options.refine
        },
        shadows: options.shadows.in_search(),
        ..*options
    };
    with_threads(options.threads, || {
        let (rigs, made);
        let coarse = match pyramid {
            Some(coarse) if coarse.len() + 1 >= levels => &coarse[..levels - 1],
            _ => {
                rigs = crate::pyramid::coarse_rigs(problem.rig, levels);
                made =
                    crate::pyramid::coarse_problems(problem, &rigs, &options.fit_settings(true))?;
                &made[..]
            }
        };
        let level = coarse.last().unwrap_or(problem);
        let given: Vec<f64> = level
            .gauge
            .iter()
            .map(|&g| level.geometry.depth(g))
            .collect();
        let mut solver = check_solver(level, &options)?;
        let inner = match options.reflectance.is_glossy() {
            true => CHECK_INNER_GLOSSY,
            false => CHECK_INNER,
        };
        hold_lobe(&mut solver, level, mean(&given), inner)?;
        let mut ev = Evaluator::new(
            (&mut solver, level.grid.n_regions),
            level.u0.to_vec("the depths")?,
            inner,
            (0, CHECK_FACTORS.len()),
            None,
        );
        let mut quiet = |_: &IterationStats| Control::Continue;
        let mut residuals = [f64::NAN; CHECK_FACTORS.len()];
        for (i, f) in CHECK_FACTORS.iter().enumerate().rev() {
            let d: Vec<f64> = given.iter().map(|g| g * f).collect();
            residuals[i] = mean(&ev.eval(&d, &mut quiet)?);
        }
        let given_at = CHECK_FACTORS.iter().position(|&f| f == 1.0).unwrap_or(0);
        let best = (0..residuals.len())
            .filter(|&i| residuals[i].is_finite())
            .min_by(|&a, &b| residuals[a].total_cmp(&residuals[b]))
            .unwrap_or(given_at);
        let factor = if best == 0 || best + 1 == residuals.len() {
            CHECK_FACTORS[best]
        } else {
            let x = [best - 1, best, best + 1].map(|i| CHECK_FACTORS[i].ln());
            let y = [best - 1, best, best + 1].map(|i| residuals[i]);
            parabola_minimum(x, y).exp()
        };
        Ok(Some(DistanceCheck {
            given: mean(&given),
            found: mean(&given) * factor,
            residual_given: residuals[given_at],
            residual_found: residuals[best],
            side,
        }))
    })?
}

/// The solver of [`check_distance_on`] on its coarse `level`: the lights as given, the glossy
/// fits without the continuation (as in the search, `begin_search`) and, unlike the search's, in
/// `f32` lanes (see [`Solver::precise_lanes`]).
fn check_solver<'a>(level: &'a Problem<'a>, options: &Options) -> Result<Solver<'a>> {
    let mut solver = Solver::new(level, options)?;
    solver.check_lights = false;
    solver.continuation = false;
    solver.precise_lanes = false;
    Ok(solver)
}

/// The corner of the V of equal slopes `±s` through three points `a < m < c` whose middle one
/// is the least: the side whose two points do not straddle the corner has the steeper slope,
/// `s = max((f_a - f_m) / (m - a), (f_c - f_m) / (c - m))`; with the corner `x0` right of `m`
/// (the left side steeper) `f_c - f_m = s (c + m - 2 x0)`, so
/// `x0 = (m + c) / 2 - (f_c - f_m) / (2 s)`, and left of it
/// `x0 = (a + m) / 2 + (f_a - f_m) / (2 s)`; clamped to that side (the middle point where no
/// slope is positive).
///
/// Why: the criterion of a held stage (the median of the facets' RMS residuals) is, on
/// noise-free images, linear in the distance error either side of its minimum, about equally
/// steep both sides (on the glossy bumps at 256²: 4e-5 at the minimum, 2.2e-4 and 2.9e-4
/// 0.07 % below and 0.1 % above, 6.3e-4 0.22 % below). A parabola's vertex through a V's points
/// lies between the corner and the middle point, so parabolic steps crawl: the alternation's
/// stage there took 7 refinement steps (198.75 / 197.06 / 197.98 / 197.78 / 198.21 / 198.41 /
/// 198.08); the V's corner took 3. The stages of [`fresh_stages`] use it (until stop 54 the
/// stages under a given lobe did; with the alternation's stages, whose lobe was estimated, on it
/// too, the 256² PBR shadows rough plastic 0.1 block with 0.05 % image noise, seed 2, had its
/// lobe estimates turn to the retro shape and stay there, at -3.65 %). On a V whose sides
/// differ (slopes 1 and 3, the unit tests)
/// the corner is not exact and the refinement takes about as many steps as parabolic
/// interpolation (9-10 against 8); on noisy images the criterion's bottom is rounded
/// (`sqrt(s0^2 + k^2 x^2)`), where the safeguards of [`Parabolic`] and its tolerance step keep
/// the refinement to the bracket's tolerance (the unit tests).
fn vee_minimum([a, m, c]: [f64; 3], [fa, fm, fc]: [f64; 3]) -> f64 {
    let left = (fa - fm) / (m - a);
    let right = (fc - fm) / (c - m);
    let slope = left.max(right);
    if !(slope > 0.0 && slope.is_finite()) {
        return m;
    }
    if left >= right {
        (0.5 * (m + c) - 0.5 * (fc - fm) / slope).clamp(m, c)
    } else {
        (0.5 * (a + m) + 0.5 * (fa - fm) / slope).clamp(a, m)
    }
}

/// The abscissa of the minimum of the parabola through three points with `y[1]` the least (the
/// middle abscissa when the points are collinear).
fn parabola_minimum(x: [f64; 3], y: [f64; 3]) -> f64 {
    let (d0, d2) = (x[0] - x[1], x[2] - x[1]);
    let (e0, e2) = (y[0] - y[1], y[2] - y[1]);
    let denominator = d0 * e2 - d2 * e0;
    let numerator = d0 * d0 * e2 - d2 * d2 * e0;
    if denominator.abs() < f64::MIN_POSITIVE {
        return x[1];
    }
    (x[1] + 0.5 * numerator / denominator).clamp(x[0], x[2])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Runs [`Parabolic`] on `f` from a scan of `scan` points over `[lo, hi]`; returns the
    /// estimate and the number of refinement steps.
    fn refine(f: impl Fn(f64) -> f64, range: (f64, f64), scan: usize, tol: f64) -> (f64, usize) {
        refine_with(f, range, scan, tol, false)
    }

    /// [`refine`], stepping to a V's vertex with `vee` (see [`vee_minimum`]).
    fn refine_with(
        f: impl Fn(f64) -> f64,
        (lo, hi): (f64, f64),
        scan: usize,
        tol: f64,
        vee: bool,
    ) -> (f64, usize) {
        let points = (0..scan)
            .map(|i| lo + (hi - lo) * i as f64 / (scan - 1) as f64)
            .map(|x| (x, f(x)))
            .collect();
        let mut p = Parabolic {
            vee,
            ..Parabolic::new(points)
        };
        let mut steps = 0;
        while let Some(x) = p.next(tol) {
            p.insert(x, f(x));
            steps += 1;
            assert!(steps <= MAX_REFINEMENTS, "no convergence");
        }
        (p.estimate(), steps)
    }

    /// Smooth minima are found to the tolerance in a few steps, and V-shaped ones (the residual
    /// of noise-free images, linear in the distance error) and lopsided ones within it too,
    /// in fewer steps than golden-section search (15 from the default scan's bracket to 1e-3).
    #[test]
    fn parabolic_refinement_finds_minima_to_the_tolerance() {
        let tol = 1e-3;
        type Case = (&'static str, Box<dyn Fn(f64) -> f64>, f64);
        let cases: [Case; 4] = [
            ("quadratic", Box::new(|x: f64| (x - 0.123).powi(2)), 0.123),
            ("v", Box::new(|x: f64| (x + 0.31).abs()), -0.31),
            (
                "lopsided",
                Box::new(|x: f64| (x - 0.05).exp() - (x - 0.05)),
                0.05,
            ),
            ("flat bottom", Box::new(|x: f64| (x - 0.4).powi(4)), 0.4),
        ];
        for (name, f, truth) in cases {
            let (x, steps) = refine(f, (-3.0, 3.0), 12, tol);
            assert!((x - truth).abs() <= 1.5 * tol, "{name}: {x} vs {truth}");
            assert!(steps <= 15, "{name}: {steps} steps");
        }
        // A narrow window of three points (the search's own level after a coarser scan).
        let (x, steps) = refine(|x: f64| (x - 0.012).powi(2), (-0.03, 0.03), 3, tol);
        assert!((x - 0.012).abs() <= tol && steps <= 6, "{x} {steps}");
    }

    /// The V's corner: exact on a V of equal slopes from any three points bracketing it
    /// (either side of the middle one); inside the bracket otherwise.
    #[test]
    fn the_vee_vertex_is_the_corner_of_a_vee() {
        for corner in [-0.7, -0.2, 0.0, 0.05, 0.3, 0.69] {
            for (a, m, c) in [(-1.0, 0.0, 0.7), (-0.8, 0.1, 1.0), (-1.0, -0.5, 0.75)] {
                let f = |x: f64| 3.0 * (x - corner).abs() + 0.2;
                let (fa, fm, fc) = (f(a), f(m), f(c));
                if fm > fa.min(fc) {
                    continue;
                }
                let x = vee_minimum([a, m, c], [fa, fm, fc]);
                assert!((x - corner).abs() < 1e-12, "{corner} from {a} {m} {c}: {x}");
            }
        }
        // A flat triple: its middle. A parabola `(x - 1)^2` through 0, 1, 3: the V's corner
        // falls short of the vertex, towards the shallower side (`0.5 + 1 / 4`); a V of
        // unequal sides (0.7 left, 0.9 right, corner 0): past the corner into the shallower
        // side, by `(0.9 - 0.7) / 1.8`.
        assert_eq!(vee_minimum([0.0, 1.0, 2.0], [1.0, 1.0, 1.0]), 1.0);
        let x = vee_minimum([0.0, 1.0, 3.0], [1.0, 0.0, 4.0]);
        assert!((x - 0.75).abs() < 1e-12, "{x}");
        let x = vee_minimum([-1.0, 0.0, 1.0], [0.7, 0.0, 0.9]);
        assert!((x + 0.2 / 1.8).abs() < 1e-12, "{x}");
    }

    /// [`Parabolic::floor`]: the bottom of a V of equal slopes, at every step of its
    /// refinement; below the minimum of smooth curves from a scan's three points (not at every
    /// step: once the points crowd on one side of a rounded bottom, the floor of a parabola
    /// `4 (x - 0.05)^2 + 0.5` reaches 0.504); none without a bracket.
    #[test]
    fn the_floor_bounds_the_least_residual() {
        type Curve = fn(f64, f64) -> f64;
        let curves: [(&str, Curve, f64); 3] = [
            ("vee", |x, c| 3.0 * (x - c).abs() + 0.2, 0.2),
            ("parabola", |x, c| 4.0 * (x - c).powi(2) + 0.5, 0.5),
            ("quartic", |x, c| (x - c).powi(4) + 0.1, 0.1),
        ];
        for (name, f, least) in curves {
            for corner in [-0.7, -0.2, 0.0, 0.05, 0.3, 0.69] {
                let points: Vec<(f64, f64)> = [-1.0, corner + 0.1, 1.0]
                    .map(|x| (x, f(x, corner)))
                    .to_vec();
                let mut p = Parabolic {
                    vee: true,
                    ..Parabolic::new(points)
                };
                // A scan's three points: below the least for the smooth curves too.
                let floor = p.floor();
                assert!(floor <= least + 1e-12, "{name} {corner}: {floor}");
                assert!(floor > least - 3.0, "{name} {corner}: {floor}");
                let mut steps = 0;
                loop {
                    let floor = p.floor();
                    if name == "vee" {
                        assert!((floor - least).abs() < 1e-12, "{corner}: {floor}");
                    }
                    let Some(x) = p.next(1e-4) else { break };
                    p.insert(x, f(x, corner));
                    steps += 1;
                }
                assert!(steps > 0);
            }
        }
        let edge = Parabolic::new(vec![(0.0, 1.0), (1.0, 2.0), (2.0, 3.0)]);
        assert_eq!(edge.floor(), f64::NEG_INFINITY);
        let flat = Parabolic::new(vec![(0.0, 1.0), (1.0, 1.0), (2.0, 1.0)]);
        assert_eq!(flat.floor(), f64::NEG_INFINITY);
    }

    /// Stepping to a V's corner from a window of three points (a held stage's): V-shaped minima
    /// (noise-free residuals) in fewer steps than parabolas take, rounded ones (residuals with
    /// noise, `sqrt(s^2 + k^2 x^2)`), lopsided ones and Vs of unequal sides still to the
    /// tolerance, in at most 3 steps more than parabolas take.
    #[test]
    fn vee_refinement_finds_minima_to_the_tolerance() {
        let tol = 1e-3;
        type Case = (&'static str, Box<dyn Fn(f64) -> f64>, f64);
        let cases: [Case; 6] = [
            ("v", Box::new(|x: f64| (x + 0.0123).abs()), -0.0123),
            (
                "unequal v",
                Box::new(|x: f64| {
                    if x < 0.007 {
                        0.007 - x
                    } else {
                        3.0 * (x - 0.007)
                    }
                }),
                0.007,
            ),
            (
                "rounded",
                Box::new(|x: f64| (1e-6 + (x - 0.0042).powi(2)).sqrt()),
                0.0042,
            ),
            ("quadratic", Box::new(|x: f64| (x - 0.0123).powi(2)), 0.0123),
            (
                "lopsided",
                Box::new(|x: f64| (20.0 * (x - 0.005)).exp() - 20.0 * (x - 0.005)),
                0.005,
            ),
            ("flat bottom", Box::new(|x: f64| (x - 0.004).powi(4)), 0.004),
        ];
        for (name, f, truth) in cases {
            let (x, vee) = refine_with(&f, (-0.03, 0.03), 3, tol, true);
            let (_, parabola) = refine_with(&f, (-0.03, 0.03), 3, tol, false);
            assert!((x - truth).abs() <= 1.5 * tol, "{name}: {x} vs {truth}");
            assert!(vee <= MAX_REFINEMENTS, "{name}: {vee} steps");
            match name {
                // Exact on a V: the corner, then the tolerance steps.
                "v" => assert!(
                    vee <= 3 && vee < parabola,
                    "{name}: {vee} / {parabola} steps"
                ),
                // Not exact where the sides differ: about as many steps as parabolas take.
                _ => assert!(vee <= parabola + 3, "{name}: {vee} / {parabola} steps"),
            }
        }
    }

    /// Levels are halved down to the search side; the ratio of two levels' curves is taken
    /// where they meet.
    #[test]
    fn coarser_levels_and_their_curves() {
        assert_eq!(halvings_to(48, 48, SEARCH_SIDE), 0);
        assert_eq!(halvings_to(128, 100, SEARCH_SIDE), 1);
        assert_eq!(halvings_to(1024, 768, SEARCH_SIDE), 4);
        let wide = [(1.0, 2.0), (2.0, 4.0), (4.0, 8.0)];
        let window = [(1.9, 30.0), (2.0, 20.0), (2.1, 10.0)];
        assert!((level_ratio(&window, &wide, 2.0) - 5.0).abs() < 1e-12);
        // Between two coarse points: interpolated in log-distance.
        let r = level_ratio(&[(2.0f64.sqrt(), 9.0)], &[(1.0, 2.0), (2.0, 4.0)], 1.4);
        assert!((r - 3.0).abs() < 1e-12, "{r}");
        assert_eq!(level_ratio(&[], &wide, 2.0), 1.0);
    }

    /// A window of log half-width `h` that may move `m` times to an end, its half-width growing
    /// by `g` at each move, reaches `h (1 + g + ... + g^m)` either side of its start (each move
    /// centres it on the last window's end). The stages of [`fresh_stages`] start at the
    /// profile's estimate, which lies within [`BRACKET_PRECISION`] of the profile's minimum,
    /// and the minima under the lobes of the grid lie within a few percent of each other: their
    /// windows reach twice that precision, and no farther than the profile's own window.
    #[test]
    fn the_fresh_window_reaches_past_the_profile_bracket() {
        let reach =
            |w: f64, m: usize, g: f64| w.ln() * (0..=m).map(|k| g.powi(k as i32)).sum::<f64>();
        let fresh = reach(FRESH_WIDTH, FRESH_MOVES, FRESH_GROWTH);
        assert!(fresh >= 2.0 * BRACKET_PRECISION, "{fresh}");
        assert!(fresh <= PROFILE_WIDTH.ln(), "{fresh}");
        assert!((reach(1.01, 3, 1.0) - 4.0 * 1.01f64.ln()).abs() < 1e-12);
        // Its lobes: the lobe search's indices but the index 1.
        assert_eq!(FRESH_ETAS[..], crate::local::ETAS[1..]);
        assert!(FRESH_ETAS.iter().all(|&e| e > 1.0));
    }

    /// A solver failure after the search names the distance found; other errors and failures
    /// without a search are kept as they are.
    #[test]
    fn failures_after_the_search_name_the_distance_found() {
        let e = after_search(
            Error::Solver("the surface reached light 8".into()),
            Some(118.074),
        );
        let Error::Solver(message) = e else {
            panic!("not a solver error")
        };
        assert!(
            message.starts_with("the surface reached light 8"),
            "{message}"
        );
        assert!(message.contains("118.074") && message.contains("give the distance"));
        let kept = after_search(Error::Solver("x".into()), None);
        assert!(matches!(kept, Error::Solver(m) if m == "x"));
        let other = after_search(Error::Cancelled, Some(1.0));
        assert!(matches!(other, Error::Cancelled));
    }
}

#[cfg(all(test, feature = "synth"))]
mod search_state_tests {
    use super::*;
    use crate::problem::{ImageStack, InitialDepth};
    use crate::synth::{Scene, SceneKind};

    /// A 16 x 16 spherical cap at 200 and its (Lambertian) images.
    fn cap() -> (Scene, Vec<f32>) {
        let scene = Scene::new(SceneKind::SphereCap, 16, 100.0, 200.0, 0).unwrap();
        let images = scene.render().unwrap().iter().map(|&v| v as f32).collect();
        (scene, images)
    }

    /// The problem of [`cap`]'s images, started at the scene's mean depth.
    fn cap_problem<'a>(scene: &'a Scene, images: &'a [f32]) -> Problem<'a> {
        let stack = ImageStack::new(images, scene.rig.n_lights(), 16, 16).unwrap();
        let start = InitialDepth::Distance(scene.mean_depth());
        Problem::new(stack, &scene.rig, Some(&scene.mask), start).unwrap()
    }

    /// The search compares its candidates without the glossy fits' continuation (their
    /// residual curve moved with it), with its glossy fits in `f64` lanes, and gives both back
    /// to the run at the distance found.
    #[test]
    fn the_search_turns_the_continuation_off_and_back_on() {
        let (scene, images) = cap();
        let problem = cap_problem(&scene, &images);
        let options = Options {
            levels: 1,
            ..Options::default()
        };
        let mut solver = Solver::new(&problem, &options).unwrap();
        assert!(solver.continuation);
        let saved = begin_search(&mut solver);
        assert!(!solver.continuation && !solver.check_lights);
        assert!(!solver.local_step(false, None).settings.continuation);
        // ... and its glossy fits without the step tolerance (`STEP_TOLERANCE`).
        assert_eq!(solver.local_step(false, None).settings.step_tolerance, 0.0);
        assert!(solver.local_step(false, None).settings.precise);
        end_search(&mut solver, saved);
        assert!(solver.continuation && solver.check_lights);
        assert!(solver.local_step(false, None).settings.step_tolerance > 0.0);
        assert!(!solver.local_step(false, None).settings.precise);
    }

    /// The check compares its candidates without the glossy fits' continuation, as the search
    /// does, but with its glossy fits in `f32` lanes (its verdict is a ratio and an offset, not
    /// a distance to 1 %), and without the step tolerance.
    #[test]
    fn the_check_fits_in_single_lanes() {
        let (scene, images) = cap();
        let problem = cap_problem(&scene, &images);
        let options = Options {
            levels: 1,
            ..Options::default()
        };
        let solver = check_solver(&problem, &options).unwrap();
        assert!(!solver.continuation && !solver.check_lights);
        let settings = solver.local_step(false, None).settings;
        assert!(!settings.continuation && !settings.precise);
        assert_eq!(settings.step_tolerance, 0.0);
        // The search's solver keeps them in `f64` lanes.
        let mut solver = Solver::new(&problem, &options).unwrap();
        let _saved = begin_search(&mut solver);
        assert!(solver.local_step(false, None).settings.precise);
    }

    /// A candidate evaluated afresh ([`Fresh`]) is a function of its distance and lobe alone:
    /// the same residuals, bit for bit, whatever was evaluated before it; warm-started
    /// candidates under the same held lobe depend on what came before.
    #[test]
    fn fresh_candidates_do_not_depend_on_their_order() {
        let (scene, images) = cap();
        let problem = cap_problem(&scene, &images);
        let options = Options {
            levels: 1,
            reflectance: crate::Reflectance::Glossy(None),
            shadows: crate::shadow::Shadows::On,
            ..Options::default()
        };
        let lobe = Lobe::new(0.3, 1.5);
        // The candidates start from one surface and its cast shadows (marched: `On`).
        let origin = problem.u0.to_vec("the depths").unwrap();
        let shadows = Solver::new(&problem, &options)
            .unwrap()
            .shadows_under(&origin, crate::shadow::Shadows::On)
            .unwrap();
        assert!(shadows.is_some());
        let start = Arc::new(FreshStart {
            surface: origin.clone(),
            shadows,
        });
        let evaluate = |order: &[f64], fresh: bool| -> Vec<Vec<f64>> {
            let mut solver = Solver::new(&problem, &options).unwrap();
            let _ = begin_search(&mut solver);
            solver.lobe = Some(lobe);
            solver.hold_lobe = true;
            let fresh = fresh.then(|| Fresh {
                options,
                lobe,
                start: start.clone(),
                memo: Arc::default(),
            });
            let regions = problem.grid.n_regions;
            let mut ev = Evaluator::new(
                (&mut solver, regions),
                origin.clone(),
                5,
                (0, order.len()),
                fresh,
            );
            let mut quiet = |_: &IterationStats| Control::Continue;
            order
                .iter()
                .map(|&d| ev.eval(&[d], &mut quiet).unwrap())
                .collect()
        };
        let alone = evaluate(&[200.0], true);
        let after = evaluate(&[180.0, 215.0, 200.0], true);
        let before = evaluate(&[200.0, 180.0], true);
        assert!(alone[0][0].is_finite() && alone[0][0] > 0.0);
        assert_eq!(after[2], alone[0]);
        assert_eq!(before[0], alone[0]);
        assert_eq!(evaluate(&[180.0], true)[0], after[0]);
        assert_eq!(before[1], after[0]);
        let warm_alone = evaluate(&[200.0], false);
        let warm_after = evaluate(&[180.0, 215.0, 200.0], false);
        assert_ne!(warm_after[2], warm_alone[0]);
    }

    /// A search given a criterion to beat stops once its floor is above it (by more than
    /// [`BEAT_MARGIN`]), and refines as before when it is not.
    #[test]
    fn a_search_that_cannot_beat_the_best_stops() {
        let (scene, images) = cap();
        let problem = cap_problem(&scene, &images);
        let options = Options {
            levels: 1,
            ..Options::default()
        };
        let search = |beat: f64| {
            let mut solver = Solver::new(&problem, &options).unwrap();
            let _ = begin_search(&mut solver);
            let mut count = Count {
                done: 0,
                planned: 0,
                lowest: f64::NAN,
                beat,
            };
            let u = problem.u0.to_vec("the depths").unwrap();
            let window = DistanceSearch {
                scan: 3,
                ..DistanceSearch::default()
            };
            let mut quiet = |_: &IterationStats| Control::Continue;
            let searched = search_refined(
                &mut solver,
                &problem,
                &window,
                (scene.mean_depth() / 1.05, scene.mean_depth() * 1.05),
                u,
                (true, None),
                &mut count,
                &mut quiet,
            )
            .unwrap();
            let Searched::Found(estimate, _) = searched else {
                panic!("no bracket");
            };
            (count.done, count.lowest, estimate.distance[0])
        };
        let (all, lowest, found) = search(f64::NAN);
        assert!(all > 3, "{all}");
        // A criterion to beat above this search's lowest: refined as before, to the bit.
        assert_eq!(search(lowest * (1.0 + BEAT_MARGIN)), (all, lowest, found));
        assert_eq!(search(2.0 * lowest), (all, lowest, found));
        // Far below it: stopped before the refinement's end, at the least point so far.
        let (fewer, above, _) = search(0.01 * lowest);
        assert!((3..all).contains(&fewer), "{fewer} of {all}");
        assert!(above >= lowest);
    }
}
