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

use std::time::Instant;

use crate::error::{Error, Result};
use crate::grid::Grid;
use crate::local::RETRO_ETA;
use crate::memory::try_copy;
use crate::options::{Options, Refine};
use crate::parallel::with_threads;
use crate::problem::Problem;
use crate::reconstruction::{Control, IterationStats, Reconstruction, SearchProgress};
use crate::reflectance::{Diffuse, Lobe};
use crate::rig::Light;
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
}

impl Evaluator<'_, '_> {
    /// Evaluates one candidate. Its iterations are reported with a [`SearchProgress`]; the last
    /// one is held back until the candidate's residual is known, so that it carries it.
    fn eval(
        &mut self,
        d: &[f64],
        progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
    ) -> Result<Vec<f64>> {
        let problem = self.solver.problem();
        let gauge: Vec<f64> = d.iter().map(|&x| problem.geometry.unknown(x)).collect();
        problem.grid.apply_gauge(&mut self.u, &gauge);
        // Every candidate starts from the rig's lights: the residual curve must not depend on
        // the order of the evaluations.
        self.solver.lights.restart(self.refine);
        // Its glossy fits go on from the normals of the last candidate, as its surface does.
        if self.candidate > 0 {
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
                .iterate(&mut self.u, &gauge, self.inner, 0.0, &mut deferred)?;
        }
        self.solver.local(&self.u)?;
        let residuals = self.solver.search_residuals();
        for ((curve, &x), &r) in self.curve.iter_mut().zip(d).zip(&residuals) {
            curve.push((x, r));
        }
        let residual = mean(&residuals);
        if residual.is_finite() && (self.best.1.is_nan() || residual < self.best.1) {
            self.best = (info.distance, residual);
        }
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
/// refined by alternating between the lobe estimated at the distance found and a search under
/// it held ([`alternate`]), then by a walk along the index under the transmitted shape
/// ([`index_walk`]), with a last stage under the retro-reflective diffuse shape held
/// ([`retro_stage`]). The stages are [`search_stages`]'s.
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
/// coarser level too, see [`search_coarser`]; then [`alternate`] on the search's level).
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
                    solver, problem, &wide, range, u, false, &mut count, progress,
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
            };
            // The profile's scan only brackets the distance (its candidates are 5 % apart);
            // the alternation under held lobes refines it.
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
                .and_then(|profiled| {
                    alternate(
                        solver, problem, search, range, profiled, &mut count, progress,
                    )
                })
                .and_then(|(estimate, _)| {
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
/// apart) for the held stages of [`alternate`] on the search's own level, which refine it to
/// the search's precision. A candidate of 15 iterations, two lobe estimates among them, costs a
/// quarter as much on the 64² level as on the 128² one (the glossy bumps at 256²: 0.35 against
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
    let options = Options {
        levels: 1,
        ..*options
    };
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
            search_refined(&mut sub, level, &wide, range, u, false, count, progress)
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
            };
            search_window(&mut sub, level, wide, range, found, window, count, progress)
        });
    end_search(&mut sub, saved);
    let (estimate, mut u) = found?;
    drop(sub);
    for i in (0..coarse.len()).rev() {
        let finer = match i {
            0 => &problem.grid,
            _ => &coarse[i - 1].grid,
        };
        u = crate::pyramid::upsample(&coarse[i].grid, &u, finer)?;
    }
    let regions = coarse_regions(&problem.grid, &level.grid, halvings as u32);
    Ok((
        DistanceEstimate {
            distance: regions.iter().map(|&r| estimate.distance[r]).collect(),
            curve: regions.iter().map(|&r| estimate.curve[r].clone()).collect(),
            range,
        },
        u,
    ))
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

/// How many times [`alternate`] estimates the lobe at the distance found and searches again
/// under it, at most.
const ALTERNATIONS: usize = 3;

/// [`alternate`] stops when a stage moves the distance by at most this (in log-distance): a
/// fifth of the 1 % the search is meant to reach, and what the stages' residual curves resolve.
const ALTERNATION_PRECISION: f64 = 2e-3;

/// How many times a window of [`alternate`] may move to an end where the residual keeps
/// falling: once, so that a stage searches within about a factor 1.06 of the profile's estimate,
/// the profile's own bracket (its candidates are 5 % apart). A stage whose minimum lies beyond
/// contradicts the profile and brings nothing: on hehe12 (8 LEDs) a held lobe's criterion kept
/// falling through six moves of the window to the far end of the range, and a stage that
/// moved 11 % there took the distance from 209 to 233 (the authors give 200-230).
const ALTERNATION_MOVES: usize = 1;

/// The half-width, as a factor of the distance, of the first window of a held stage under a
/// lobe given to it (the index walk's and the retro stage's, see [`held_stage`]): the search's
/// default precision (`1e-3` in log-distance), so that three candidates (the start and
/// `1.001^±1`) bracket a minimum that stayed put to `2e-3`, which ends the refinement at once.
/// Where the criterion keeps falling towards an end, the window moves there and widens
/// ([`GIVEN_LOBE_GROWTH`]), at most [`GIVEN_LOBE_MOVES`] times.
///
/// Why: such a stage starts from the distance of the best stage so far, a minimum under a
/// neighbouring lobe to within the search's precision; the walk's steps moved the distance by
/// 0.05-0.5 % on the PBR renders (see [`index_walk`]). Until stop 50 the window was 1 % either
/// side: on the glossy bumps at 256² the walk's three stages each scanned 200.21 / 198.23 /
/// 196.27 and refined back to 198.23 with three more candidates (6 a stage), their minima
/// within 0.005 % of each other; with this window a stage takes 3.
const GIVEN_LOBE_WIDTH: f64 = 1.001;

/// How many times the window of [`GIVEN_LOBE_WIDTH`] may move to an end where the residual
/// keeps falling.
const GIVEN_LOBE_MOVES: usize = 3;

/// The factor on the log half-width of the window of [`GIVEN_LOBE_WIDTH`] at each move: a
/// window of log half-width `h` that moves `m` times, growing by `g` each time, reaches
/// `h (1 + g + ... + g^m)` from its start (each move centres it on the last window's end):
/// with `1e-3`, 3 and 3 moves `0.040` (`1.0408`), the reach of stop 49's window (1 % moving
/// at its width, `1.01^4 = 1.0406`; its doc gave `1.01^7`, counting each move as a whole
/// window). A minimum 4 % away costs either window four scans of 3 candidates; one that stayed
/// put costs this one 3 candidates, that one 6.
const GIVEN_LOBE_GROWTH: f64 = 3.0;

/// Refines the estimate of a glossy profile window ([`search_window`] with `lobe`) by
/// alternation between lobe and distance: a stage estimates the lobe afresh by a run at the
/// distance found (from the surface and glossy normals found there), holds it, and searches the
/// distance again under it in a narrow window ([`NARROW_WIDTH`], moving as needed). It ends
/// when a stage moves the distance by at most [`ALTERNATION_PRECISION`], or after
/// [`ALTERNATIONS`] stages; then the index walk ([`index_walk`]) and the retro stage
/// ([`retro_stage`]). The estimate returned is that of the held stage whose lowest criterion `R`
/// (the median of the facets' RMS residuals, on the search's level) is the lowest (the
/// profile's when no stage finds a minimum).
///
/// Why: with the lobe estimated afresh for every candidate, the criterion is a profile
/// `R(d, L(d))`; each estimate is a search of its own (line searches on grids of roughness and
/// index, from scratch), so that curve is noisy at the scale of a refinement: on the PBR renders
/// neighbouring candidates 0.1-0.5 % apart differed by 10-35 % in residual, and the
/// refinement's bracket closed on a noisy point (principled 0.3 bumps at +1.6 % while the
/// residual near the truth was a tenth of that point's). Under a held lobe `R(d, L)` is smooth
/// in `d` (a given lobe's candidates near the minimum differed by 0.01 %), so each stage's
/// minimum is well defined, and a fixed point of the alternation is a stationary point of `R`
/// over distance and lobe together when `L(d)` minimises `R` at `d`. It does not quite: the
/// lobe estimate minimises the summed squared residual of a facet subsample, not the median,
/// so a stage can end at a higher `R` than a candidate before it (on the principled 0.3 block,
/// index 1.2 estimated at +0.7 % holds the minimum at +0.9 % with `R` 3.3e-4, while the profile
/// window's candidate at +0.4 % had 2.2e-4); keeping the stage of the lowest `R` makes the
/// alternation never end worse, by the search's own criterion, than its first stage. Until stop
/// 45 the profile competed too (its lowest candidate's `R`); see [`index_walk`] for why it no
/// longer does.
#[allow(clippy::too_many_arguments)]
fn alternate(
    solver: &mut Solver<'_>,
    problem: &Problem<'_>,
    search: &DistanceSearch,
    range: (f64, f64),
    profiled: (DistanceEstimate, Vec<f64>),
    count: &mut Count,
    progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
) -> Result<(DistanceEstimate, Vec<f64>)> {
    // The estimate of the held stage with the lowest criterion so far, that criterion, and the
    // lobe the stage held: the profile's estimate (a parabola's vertex between candidates under
    // lobes of their own) only starts them, kept when no stage finds a minimum (see
    // [`index_walk`] for why its criterion does not compete).
    let mut best: (f64, DistanceEstimate, Option<Lobe>) = (f64::NAN, profiled.0.clone(), None);
    // The same for the stages under the transmitted diffuse shape alone: where the index walk
    // starts (the retro stage may win over them and the walk then still runs, see
    // [`index_walk`]).
    let mut transmitted: Option<(f64, DistanceEstimate, Lobe)> = None;
    let (_, mut u) = alternation(profiled, |estimate, u| {
        // The lobe is estimated afresh (from the whole grids of roughness and index) by a run
        // at the distance found from the surface and glossy normals found there, then held.
        let next = held_stage(
            solver, problem, search, range, estimate, u, None, count, progress,
        )?;
        if let Some(next) = &next {
            if best.0.is_nan() || count.lowest < best.0 {
                best = (count.lowest, next.0.clone(), solver.lobe);
            }
            if let Some(l) = solver.lobe.filter(|l| l.diffuse == Diffuse::Transmitted) {
                if transmitted.as_ref().is_none_or(|t| count.lowest < t.0) {
                    transmitted = Some((count.lowest, next.0.clone(), l));
                }
            }
        }
        Ok(next)
    })?;
    // The index walk along the transmitted shape (see [`index_walk`]), then the
    // retro-reflective diffuse shape's stage (see [`retro_stage`]).
    let line = match transmitted {
        Some(line) => line,
        // No stage found a minimum (the first stage's criterion kept falling out of its
        // windows): the walk starts from the profile's estimate under the transmitted lobe that
        // stage estimated, its first stage that finds one taken (the 256² rough plastic 0.1
        // block with 0.1 % image noise, seed 0: the profile's -1.58 % was returned, the walk
        // never ran).
        None if best.0.is_nan() => {
            match solver.lobe.filter(|l| l.diffuse == Diffuse::Transmitted) {
                Some(l) => (f64::INFINITY, best.1.clone(), l),
                None => return Ok((best.1, u)),
            }
        }
        None => return Ok((best.1, u)),
    };
    let l = index_walk(
        solver, problem, search, range, line, &mut best, &mut u, count, progress,
    )?;
    retro_stage(
        solver, problem, search, range, l.alpha, &mut best, &mut u, count, progress,
    )?;
    Ok((best.1, u))
}

/// The index grid of [`index_walk`]: the lobe search's index grid without its first index, 1.
///
/// At the index 1 the model is not the end of the index line but another model: its Fresnel
/// shape `F(v.h) / F(1)` is taken as 1 (nothing is reflected to shape), while as `eta -> 1+` the
/// shape tends to its steepest rise, `(1 + (2c^2 - 1)^2) / (2c^4)` at `c = v.h` (2.1 at
/// `c = 0.7`, 9.9 at `c = 0.5`; at the index 1.15 1.6 and 4.7, at 1.5 1.3 and 2.2); only the
/// transmittance (`T = 1`, the Lambertian diffuse term) joins the line continuously. A step from
/// 1.15 to 1 jumps from the steepest rise to none. On the 64² rough plastic 0.3 block of
/// tests/data/pbr (16 lights, true distance 210.95) a walk on the whole grid went from the
/// alternation's index 1.5 (+0.42 %, `R` 2.77e-4) down through 1.45 / 1.3 / 1.15 (+0.38 / +0.17 /
/// -0.15 %, `R` 2.75 / 2.66 / 2.64e-4), each step moving the distance by 0.05-0.3 %, then to 1:
/// `R` 2.29e-4 at -2.65 %, 2.5 % in one step (the stop-45 merge's failing test). Without the
/// index 1 the walk ends at 1.15 (-0.15 %). The index 1 still competes where the alternation's
/// lobe search chooses it (its stages), and a walk may start there (the 256² rough plastic 0.1
/// block: from 1 at -2.1 % up to 2.1 at -0.38 %).
const WALK_ETAS: [f64; 6] = [1.15, 1.3, 1.45, 1.6, 1.8, 2.1];

/// [`alternate`] ends with a walk along the index: from the lobe of the best stage under the
/// transmitted shape, held stages under the indices of [`WALK_ETAS`] next to it (the same
/// roughness), first upwards, stepping on while a stage's lowest criterion `R` falls below the
/// best so far, then (if the first step up brought nothing) downwards alike ([`walk_indices`]).
/// The stage of the lowest `R` is the estimate.
///
/// Why: under the glossy model the index and the distance trade along a diagonal valley of
/// `R(d, eta)`: a lower index explains the fall-off of a nearer surface. On the 16-light rough
/// plastic 0.1 block (true distance 210.94; held stages of 5 iterations on the 128² level,
/// roughness 0.092) the minimum over the distance under each held index was at -2.5 / -2.0 /
/// -1.25 / -0.5 / -0.5 / -0.5 % with `R` 1.26 / 1.09 / 0.91 / 0.75 / 0.74 / 0.71e-3 for the indices
/// 1 / 1.1 / 1.25 / 1.5 / 1.8 / 2.2: the joint minimum lies within 0.5 % of the truth. The
/// alternation is a coordinate descent in which the lobe is estimated by the summed squared
/// residual of a facet subsample, not by `R`: at the profile's vertex (-2.0 %) it chose the
/// retro shape, then the index 1.0, and the stages stopped at -2.4 % (`R` 9.7e-4), at a fixed point
/// in the valley's low end. The profile window's lowest candidate (-1.7 %, index 1.22 estimated
/// there, `R` 7.8e-4) beat every stage, so the search returned the profile's vertex (-1.99 %); its
/// `R` is not comparable with a held stage's (its lobe was estimated by a run of its own, with
/// more iterations), and the vertex is not that candidate, so it no longer competes. The walk
/// then went 1.15 / 1.3 / 1.45 (`R` 7.5 / 6.5 / 6.1e-4, the minimum at -0.64 %) and stopped at
/// 1.6 (6.2e-4). (Stop 46's build, whose alternation ends there under the index 1 at -2.10 %,
/// `R` 1.01e-3: 1.15 / 1.3 / 1.45 / 1.6 / 1.8 / 2.1 at -1.67 / -1.15 / -0.67 / -0.41 / -0.38 /
/// -0.38 %, `R` 7.31 / 6.13 / 5.84 / 5.53 / 5.52 / 5.51e-4.)
///
/// The walk starts from the best stage under the transmitted shape, `line` (its `R`, estimate
/// and lobe), and steps on while it lowers that line's `R`; each of its stages also competes
/// with `best`, which the retro stage may hold. (Stop 45: with the walk run only where the best
/// stage was a transmitted one, the merged build of that stop ended the same block under the
/// retro stage at -3.78 %, a stage the walk never got to compete with; with the walk from the
/// best transmitted stage and the retro stage before it, 0.1 % added noise (seed 0) still ended
/// there under the retro shape at -3.99 %. So the walk comes first and the retro stage after
/// it, [`retro_stage`]; until stop 52 that stage ran only where the walk's line ended at an index
/// of at most 1.25.) Returns the lobe of the line's lowest stage.
#[allow(clippy::too_many_arguments)]
fn index_walk(
    solver: &mut Solver<'_>,
    problem: &Problem<'_>,
    search: &DistanceSearch,
    range: (f64, f64),
    line: (f64, DistanceEstimate, Lobe),
    best: &mut (f64, DistanceEstimate, Option<Lobe>),
    u: &mut Vec<f64>,
    count: &mut Count,
    progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
) -> Result<Lobe> {
    let (mut lowest, mut estimate, start) = line;
    let mut found = start;
    walk_indices(start.eta, &WALK_ETAS, |eta| {
        let lobe = Lobe::new(start.alpha, eta);
        let next = held_stage(
            solver,
            problem,
            search,
            range,
            &estimate.clone(),
            u,
            Some(lobe),
            count,
            progress,
        )?;
        Ok(match next {
            Some(next) if count.lowest < lowest => {
                lowest = count.lowest;
                estimate = next.0;
                found = lobe;
                if best.0.is_nan() || lowest < best.0 {
                    *best = (lowest, estimate.clone(), Some(lobe));
                    *u = next.1;
                }
                true
            }
            _ => false,
        })
    })?;
    Ok(found)
}

/// The walk of [`index_walk`] from the index `start` over `grid` (ascending): `lower(eta)` tries
/// a stage under `eta` and tells whether it lowered the best criterion. Upwards from the first
/// index above `start` while it does; then, if the first step up did not, downwards from the
/// first index below `start` alike. It never leaves `grid` (with [`WALK_ETAS`]: never to the
/// index 1).
fn walk_indices(
    start: f64,
    grid: &[f64],
    mut lower: impl FnMut(f64) -> Result<bool>,
) -> Result<()> {
    let above = grid.iter().copied().filter(|&e| e > start * (1.0 + 1e-9));
    let below = grid
        .iter()
        .rev()
        .copied()
        .filter(|&e| e < start * (1.0 - 1e-9));
    let mut moved = false;
    for eta in above {
        if !lower(eta)? {
            break;
        }
        moved = true;
    }
    if !moved {
        for eta in below {
            if !lower(eta)? {
                break;
            }
        }
    }
    Ok(())
}

/// One stage of [`alternate`]: the surface `u` gauged at `estimate`'s distances, the lobe held
/// (`lobe`, or with `None` estimated afresh there by a run of at least
/// [`LOBE_AT`](crate::solver::LOBE_AT)`[1]` iterations from the surface and glossy normals found
/// there), and the distance searched again under it in a window [`NARROW_WIDTH`] either side,
/// moving at most [`ALTERNATION_MOVES`] times (under a given lobe: [`GIVEN_LOBE_WIDTH`],
/// widening as it moves, and refining by stepping to a V's corner, [`vee_minimum`]). `None`
/// when the criterion under the lobe keeps falling out of the windows (the stage brings nothing); `count.lowest` is then the stage's
/// lowest criterion.
#[allow(clippy::too_many_arguments)]
fn held_stage(
    solver: &mut Solver<'_>,
    problem: &Problem<'_>,
    search: &DistanceSearch,
    range: (f64, f64),
    estimate: &DistanceEstimate,
    u: &mut Vec<f64>,
    lobe: Option<Lobe>,
    count: &mut Count,
    progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
) -> Result<Option<(DistanceEstimate, Vec<f64>)>> {
    let window = match lobe {
        None => Window {
            scan: NARROW_SCAN,
            width: NARROW_WIDTH,
            moves: ALTERNATION_MOVES,
            lobe: false,
            coarser: false,
            grow: 1.0,
            vee: false,
        },
        Some(_) => Window {
            scan: NARROW_SCAN,
            width: GIVEN_LOBE_WIDTH,
            moves: GIVEN_LOBE_MOVES,
            lobe: false,
            coarser: false,
            grow: GIVEN_LOBE_GROWTH,
            vee: true,
        },
    };
    let narrow = DistanceSearch {
        inner: search.inner.min(WINDOW_INNER),
        ..*search
    };
    let gauge: Vec<f64> = estimate
        .distance
        .iter()
        .map(|&d| problem.geometry.unknown(d))
        .collect();
    problem.grid.apply_gauge(u, &gauge);
    solver.lobe = lobe;
    solver.hold_lobe = lobe.is_some();
    solver.lights.restart(solver.lights.refine());
    if lobe.is_none() {
        solver.keep_glossy_normals();
        let iterations = search.inner.max(crate::solver::LOBE_AT[1]);
        solver.iterate(u, &gauge, iterations, 0.0, &mut |_| Control::Continue)?;
        solver.hold_lobe = true;
    }
    count.planned += planned_candidates(NARROW_SCAN);
    count.lowest = f64::NAN;
    let start = try_copy(u, "the depths")?;
    match search_window(
        solver,
        problem,
        &narrow,
        range,
        (estimate.clone(), start),
        window,
        count,
        progress,
    ) {
        Ok(next) => Ok(Some(next)),
        // The criterion under this lobe keeps falling out of the windows (see
        // [`ALTERNATION_MOVES`]): the stage brings nothing.
        Err(Error::Unusable(_)) => Ok(None),
        Err(e) => Err(e),
    }
}

/// [`alternate`] ends with one more stage under the retro-reflective diffuse shape
/// ([`Diffuse::Retro`] at the roughness of the index walk's line, index [`RETRO_ETA`]) held,
/// kept when its lowest criterion is below the stages' before (the retro stage).
///
/// Why: the transmitted shape is brightest at grazing angles with the index 1 (Lambertian), so
/// a surface brighter still (Burley's retro-reflection, the principled renders) pulls its index
/// towards an end of the range, and the distance with it (principled 0.5 at 256²: bumps and
/// block index 1.05 / 1.02 at +1.67 / +1.68 % without this stage, -0.15 / -0.16 % with it; the
/// 64² bumps of tests/data/pbr index 1.15 at +1.68 %, -0.14 % with it). The lobe search chooses
/// the shape too, but the profile's candidates (5 % apart) fall outside the retro shape's narrow
/// minimum (it lost to the transmitted shape 0.8 % from the true distance).
///
/// Until stop 51 the stage ran only where the line ended at an index of at most 1.25, which
/// saved its window (3-5 candidates) elsewhere. Stop 52 found that on the 256² principled 0.3
/// block with cast shadows (the PBR renders) the search's outcome hung on the last bits of its
/// fits: main's build chose the retro shape in the alternation (-0.28 %), but the same images
/// with Gaussian noise of `1e-6` added (seeds 0-5, below any sensor's quantization) ended at
/// +1.55 / +1.77 / +1.32 / -1.72 / -0.98 / +0.67 %, the line mostly at the top of the index range
/// (2.0-2.3), where the stage did not run; run there, it won with a criterion 1.6-10 times
/// lower: -0.31 / -0.15 / -0.76 / -1.72 / -0.98 / -0.74 % (seed 3's line ended at the index 1 and
/// its retro stage lost, as before). Where the transmitted shape fits (rough plastic), the
/// retro stage's criterion is the higher one and the estimate stays: every row of the PBR
/// renders' `depth="auto"` table came out the same (at the true distance of the rough plastic
/// 0.3 bumps the retro shape's residual was 364 times the transmitted shape's).
#[allow(clippy::too_many_arguments)]
fn retro_stage(
    solver: &mut Solver<'_>,
    problem: &Problem<'_>,
    search: &DistanceSearch,
    range: (f64, f64),
    alpha: f64,
    best: &mut (f64, DistanceEstimate, Option<Lobe>),
    u: &mut Vec<f64>,
    count: &mut Count,
    progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
) -> Result<()> {
    let retro = Lobe::retro(alpha, RETRO_ETA);
    let estimate = best.1.clone();
    if let Some(next) = held_stage(
        solver,
        problem,
        search,
        range,
        &estimate,
        u,
        Some(retro),
        count,
        progress,
    )? {
        if best.0.is_nan() || count.lowest < best.0 {
            *best = (count.lowest, next.0, Some(retro));
            *u = next.1;
        }
    }
    Ok(())
}

/// The loop of [`alternate`]: `stage` maps an estimate (and its warm state, which it may use up)
/// to the next, until it has none (the stage found no minimum), or one moves no region's
/// distance by more than [`ALTERNATION_PRECISION`] in log-distance, or after [`ALTERNATIONS`]
/// stages.
fn alternation(
    mut current: (DistanceEstimate, Vec<f64>),
    mut stage: impl FnMut(
        &DistanceEstimate,
        &mut Vec<f64>,
    ) -> Result<Option<(DistanceEstimate, Vec<f64>)>>,
) -> Result<(DistanceEstimate, Vec<f64>)> {
    for _ in 0..ALTERNATIONS {
        let Some(next) = stage(&current.0, &mut current.1)? else {
            break;
        };
        let moved = next
            .0
            .distance
            .iter()
            .zip(&current.0.distance)
            .map(|(a, b)| (a / b).ln().abs())
            .fold(0.0, f64::max);
        current = next;
        if moved <= ALTERNATION_PRECISION {
            break;
        }
    }
    Ok(current)
}

/// Candidates evaluated so far and planned, over the stages of a search (for its progress).
struct Count {
    done: usize,
    planned: usize,
    /// The lowest (mean) criterion of a candidate since it was last reset (NaN: none; see
    /// [`alternate`]).
    lowest: f64,
}

/// The window in which [`search_window`] refines a wide estimate.
#[derive(Debug, Clone, Copy)]
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
    /// [`GIVEN_LOBE_GROWTH`]).
    grow: f64,
    /// Whether its refinement steps to the vertex of a V rather than a parabola (see
    /// [`vee_minimum`]).
    vee: bool,
}

/// Refines the `wide` estimate of a search (see [`search_with`]) in a window `window.width`
/// either side of it, which moves towards an end where the residual keeps falling. With
/// `window.lobe` the lobe is estimated afresh at the distance found, then again for every
/// candidate. The curve keeps the wide search's candidates outside the last window.
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
    let (wide, u) = wide;
    let near = wide.distance.iter().copied().fold(f64::INFINITY, f64::min);
    let far = wide.distance.iter().copied().fold(0.0, f64::max);
    if window.lobe {
        solver.lobe = None;
        solver.hold_lobe = false;
        hold_lobe(solver, problem, mean(&wide.distance), search.inner)?;
        solver.hold_lobe = false;
    }
    let window_search = DistanceSearch {
        scan: window.scan,
        ..*search
    };
    let clip = |(lo, hi): (f64, f64)| (lo.max(range.0), hi.min(range.1));
    let mut width = window.width;
    let mut bounds = clip((near / width, far * width));
    let mut moves = 0;
    loop {
        let start = try_copy(&u, "the depths")?;
        let searched = search_refined(
            solver,
            problem,
            &window_search,
            bounds,
            start,
            window.vee,
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
        return Ok((estimate, u));
    }
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
        let gauge = vec![problem.geometry.unknown(distance); problem.grid.n_regions];
        let mut u = problem.u0.to_vec("the depths")?;
        problem.grid.apply_gauge(&mut u, &gauge);
        let iterations = inner.max(crate::solver::LOBE_AT[1]);
        solver.iterate(&mut u, &gauge, iterations, 0.0, &mut |_| Control::Continue)?;
    }
    solver.hold_lobe = true;
    Ok(())
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
    vee: bool,
    count: &mut Count,
    progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
) -> Result<Searched> {
    let regions = problem.grid.n_regions;
    let scan = search.scan.max(3);
    let (ln_near, ln_far) = (range.0.ln(), range.1.ln());
    let step = (ln_far - ln_near) / (scan - 1) as f64;
    let refine = solver.lights.refine();
    let tolerance = search.precision.max(1e-9);
    let mut ev = Evaluator {
        refine,
        solver,
        u,
        inner: search.inner.max(1),
        curve: vec![Vec::new(); regions],
        candidate: count.done,
        candidates: count.planned,
        best: (f64::NAN, f64::NAN),
    };
    let searched = refine_scan(
        &mut ev,
        regions,
        scan,
        (ln_near, step),
        tolerance,
        vee,
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
/// residual keeps falling towards the near (true) or far end of the scan.
#[allow(clippy::type_complexity)]
fn refine_scan(
    ev: &mut Evaluator<'_, '_>,
    regions: usize,
    scan: usize,
    (ln_near, step): (f64, f64),
    tolerance: f64,
    vee: bool,
    progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
) -> Result<std::result::Result<Vec<f64>, (usize, bool)>> {
    // Coarse scan from far to near (surfaces start flat; far is the gentlest start).
    let mut surfaces = Surfaces::default();
    let mut scanned: Vec<(f64, Vec<f64>)> = Vec::with_capacity(scan);
    for i in (0..scan).rev() {
        let x = ln_near + step * i as f64;
        let d = x.exp();
        scanned.push((d, ev.eval(&vec![d; regions], progress)?));
        surfaces.add(vec![x; regions], &ev.u)?;
        let points: Vec<Vec<(f64, f64)>> = (0..regions)
            .map(|r| {
                scanned
                    .iter()
                    .zip((0..scan).rev())
                    .map(|((_, f), i)| (ln_near + step * i as f64, f[r]))
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
                .map(|i| (ln_near + step * i as f64, scanned[i].1[r]))
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
        let mut solver = Solver::new(level, &options)?;
        solver.check_lights = false;
        solver.continuation = false; // as in the search (`begin_search`)
        let inner = match options.reflectance.is_glossy() {
            true => CHECK_INNER_GLOSSY,
            false => CHECK_INNER,
        };
        hold_lobe(&mut solver, level, mean(&given), inner)?;
        let mut ev = Evaluator {
            refine: solver.lights.refine(),
            solver: &mut solver,
            u: level.u0.to_vec("the depths")?,
            inner,
            curve: vec![Vec::new(); level.grid.n_regions],
            candidate: 0,
            candidates: CHECK_FACTORS.len(),
            best: (f64::NAN, f64::NAN),
        };
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
/// 198.08); the V's corner took 3. Only the stages under a given lobe use it (see
/// [`held_stage`]): with the alternation's stages on it too, the 256² PBR shadows rough plastic
/// 0.1 block with 0.05 % image noise (seed 2) had its alternation's lobe estimates turn to the
/// retro shape and stay there, at -3.65 % (main: -0.23 %, its third stage transmitted and the
/// index walk from it). On a V whose sides differ (slopes 1 and 3, the unit tests)
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

    /// The alternation of [`alternate`] on a criterion coupled in distance and lobe,
    /// `R(d, L) = (d - L)² + (L - 1)²` (log-distance `d`, a lobe parameter `L`): the lobe
    /// estimated at `d` is `(d + 1) / 2` and the distance under a held `L` is `L`, so each stage
    /// halves the distance's error towards the joint minimum `d = L = 1`; it stops once a stage
    /// moves the distance by at most [`ALTERNATION_PRECISION`], else after [`ALTERNATIONS`].
    #[test]
    fn the_alternation_goes_to_the_joint_minimum_and_stops() {
        let at = |d: f64| {
            let estimate = DistanceEstimate {
                distance: vec![d.exp()],
                curve: vec![Vec::new()],
                range: (0.1, 10.0),
            };
            (estimate, Vec::new())
        };
        let run = |start: f64| {
            let mut stages = 0;
            let (estimate, _) = alternation(at(start), |e, _| {
                stages += 1;
                let d = e.distance[0].ln();
                let lobe = (d + 1.0) / 2.0;
                Ok(Some(at(lobe)))
            })
            .unwrap();
            (estimate.distance[0].ln(), stages)
        };
        // 4 % off: 2, 1, 0.5 % after the three stages (the last still moved by 0.5 %).
        let (d, stages) = run(1.04);
        assert_eq!(stages, ALTERNATIONS);
        assert!((d - 1.005).abs() < 1e-12, "{d}");
        // 0.3 % off: the first stage moves by 0.15 % and is the last.
        let (d, stages) = run(1.003);
        assert_eq!(stages, 1);
        assert!((d - 1.0015).abs() < 1e-12, "{d}");
        // A stage without a minimum ends it where it is.
        let (kept, _) = alternation(at(1.04), |_, _| Ok(None)).unwrap();
        assert_eq!(kept.distance[0], 1.04f64.exp());
        // A failing stage fails the search.
        let failed = alternation(at(1.0), |_, _| Err(Error::Cancelled));
        assert!(matches!(failed, Err(Error::Cancelled)));
        // The lowest criterion of a stage: NaN counts as none.
        assert_eq!(lower(f64::NAN, 2.0), 2.0);
        assert_eq!(lower(2.0, f64::NAN), 2.0);
        assert_eq!(lower(2.0, 1.0), 1.0);
        assert!(lower(f64::NAN, f64::NAN).is_nan());
    }

    /// A window of log half-width `h` that may move `m` times to an end, its half-width growing
    /// by `g` at each move, reaches `h (1 + g + ... + g^m)` either side of its start (each move
    /// centres it on the last window's end). The held stages under a given lobe
    /// ([`GIVEN_LOBE_WIDTH`], [`GIVEN_LOBE_MOVES`], [`GIVEN_LOBE_GROWTH`]) reach as far as stop
    /// 49's window (1 %, 3 moves at its width) and at most as far as the alternation's stages
    /// ([`NARROW_WIDTH`], [`ALTERNATION_MOVES`]), which the hehe12 capture bounds (see
    /// [`ALTERNATION_MOVES`]); their first window is the search's default precision, so that
    /// its three candidates end the refinement.
    #[test]
    fn the_given_lobe_window_reaches_as_far_as_before() {
        let reach = |w: f64, m: usize, g: f64| {
            (w.ln() * (0..=m).map(|k| g.powi(k as i32)).sum::<f64>()).exp()
        };
        let given = reach(GIVEN_LOBE_WIDTH, GIVEN_LOBE_MOVES, GIVEN_LOBE_GROWTH);
        let before = reach(1.01, 3, 1.0);
        let alternation = reach(NARROW_WIDTH, ALTERNATION_MOVES, 1.0);
        assert!((before - 1.01f64.powi(4)).abs() < 1e-12);
        assert!(given >= before, "{given} {before}");
        assert!(given <= alternation, "{given} {alternation}");
        // Its first window: the ends and the middle, within the default precision, so that the
        // scan's bracket is the refinement's end.
        let precision = DistanceSearch::default().precision;
        const { assert!(NARROW_SCAN == 3) };
        assert!(2.0 * GIVEN_LOBE_WIDTH.ln() <= 2.0 * precision * (1.0 + 1e-9));
        let points = [-1.0, 0.0, 1.0].map(|k: f64| (k * GIVEN_LOBE_WIDTH.ln(), k.abs()));
        let mut p = Parabolic::new(points.to_vec());
        assert_eq!(p.next(precision), None);
    }

    /// The index walk steps on while a stage lowers the criterion, upwards first, downwards
    /// only when the first step up brings nothing, and passes on a stage's failure.
    #[test]
    fn the_index_walk_follows_the_criterion_downhill() {
        // A criterion along the index with its least value at `m`; a stage "lowers" when its
        // value is below the best so far (that of the start).
        let run = |start: f64, m: f64| {
            let cost = |e: f64| (e - m).powi(2);
            let mut best = cost(start);
            let mut tried = Vec::new();
            walk_indices(start, &WALK_ETAS, |e| {
                tried.push(e);
                let lowered = cost(e) < best;
                best = best.min(cost(e));
                Ok(lowered)
            })
            .unwrap();
            tried
        };
        // From the low end up to the least grid index (and one past it, which fails).
        assert_eq!(run(1.0, 1.5), vec![1.15, 1.3, 1.45, 1.6]);
        // Down only after the first step up failed; an index between grid values (1.22); not
        // to the index 1, which is not on the walk's grid (see `WALK_ETAS`).
        assert_eq!(run(1.22, 1.0), vec![1.3, 1.15]);
        assert_eq!(run(1.5, 1.0), vec![1.6, 1.45, 1.3, 1.15]);
        assert!(WALK_ETAS.iter().all(|&e| e > 1.0));
        assert!(WALK_ETAS.windows(2).all(|w| w[0] < w[1]));
        // At the least value: its two neighbours only.
        assert_eq!(run(1.45, 1.45), vec![1.6, 1.3]);
        // At the top of the grid: downwards only.
        assert_eq!(run(2.1, 1.75), vec![1.8, 1.6]);
        // A failing stage fails the walk.
        let failed = walk_indices(1.0, &WALK_ETAS, |_| Err(Error::Cancelled));
        assert!(matches!(failed, Err(Error::Cancelled)));
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

    /// The search compares its candidates without the glossy fits' continuation (their
    /// residual curve moved with it), with its glossy fits in `f64` lanes, and gives both back
    /// to the run at the distance found.
    #[test]
    fn the_search_turns_the_continuation_off_and_back_on() {
        let scene = Scene::new(SceneKind::SphereCap, 16, 100.0, 200.0, 0).unwrap();
        let images: Vec<f32> = scene.render().unwrap().iter().map(|&v| v as f32).collect();
        let stack = ImageStack::new(&images, scene.rig.n_lights(), 16, 16).unwrap();
        let start = InitialDepth::Distance(scene.mean_depth());
        let problem = Problem::new(stack, &scene.rig, Some(&scene.mask), start).unwrap();
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
}
