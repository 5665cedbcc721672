//! The solver loop: alternate local and global steps until the depths converge.
//!
//! ```text
//! z = initial depths (gauged per region)
//! for it in 1..=iterations:
//!     local step on z  -> targets, normals, albedo, residuals
//!     global step      -> z_new, shifted so each region's mean depth is its gauge
//!     dz = max |z_new - z|;  z = z_new
//!     stop when dz <= tol * L   (L = max(W*w, H*h), the lateral size of the grid)
//! final local step on z -> reported normals, albedo, residuals
//! ```

use std::time::Instant;

use faer::Par;

use crate::anderson::Anderson;
use crate::error::{Error, Result};
use crate::geometry::Geometry;
use crate::global::GlobalStep;
use crate::local::{FacetFit, FacetStat, LocalStep, Model};
use crate::memory::{try_copy, try_vec};
use crate::options::{Options, Refine};
use crate::problem::{check_fittable, Problem};
use crate::reconstruction::{
    assemble, Control, FitOutputs, IterationStats, Reconstruction, RefinementReport, Timings,
    STALL_WINDOW,
};
use crate::refine::{LightData, Refiner, StepOutcome};
use crate::rig::Light;

/// Runs `f` on a rayon pool of `threads` workers (0: the global pool).
pub(crate) fn with_threads<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> Result<T> {
    if threads == 0 {
        return Ok(f());
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| Error::Unusable(format!("cannot start {threads} worker threads: {e}")))?;
    Ok(pool.install(f))
}

/// faer parallelism: sequential, or the current rayon pool when `parallel` is set.
pub(crate) fn sparse_par(parallel: bool) -> Par {
    match rayon::current_num_threads() {
        n if parallel && n > 1 => Par::rayon(n),
        _ => Par::Seq,
    }
}

/// Reconstructs the surface of `problem`. `progress` is called after every iteration; returning
/// [`Control::Cancel`] stops the solver with [`Error::Cancelled`].
pub fn reconstruct(
    problem: &Problem<'_>,
    options: &Options,
    progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
) -> Result<Reconstruction> {
    options.validate()?;
    problem.check_memory(options)?;
    crate::refine::check_refinable(&options.refine, problem.rig.n_lights())?;
    problem.cancel.check()?;
    check_fittable(problem, &options.fit_settings(false))?;
    problem.cancel.check()?;
    crate::problem::check_light_geometry(problem.rig, &problem.geometry, &problem.u0)?;
    problem.cancel.check()?;
    with_threads(options.threads, || {
        let start = Instant::now();
        let mut u = try_copy(&problem.u0, "the depths")?;
        let coarse = coarse_to_fine(problem, options, &mut u, start, progress, None)?;
        let mut solver = Solver::new(problem, options)?;
        solver.start = start;
        let mut history = solver.carry(coarse);
        let (fine, converged) = if solver.carried {
            problem.grid.apply_gauge(&mut u, &problem.gauge);
            solver.iterate(
                &mut u,
                &problem.gauge,
                options.iterations,
                options.tol,
                progress,
            )?
        } else {
            solver.iterate_first(&mut u, &problem.gauge, progress)?
        };
        history.extend(fine);
        solver.finish(&u, history, converged)
    })?
}

/// What the coarse levels of a pyramid hand to the next level.
pub(crate) struct Carried {
    history: Vec<IterationStats>,
    timings: Timings,
    /// Whether there were coarse levels.
    pub(crate) carried: bool,
    lights: Vec<Light>,
    refine: Refine,
    monitor: Option<Monitor>,
    diverged: bool,
}

/// The residuals of the first level's runs without and with light refinement.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Monitor {
    without: f64,
    with: f64,
    fell_back: bool,
}

/// What the coarsest level of a pyramid does before the iterations: given its solver and its
/// starting unknowns, returns the gauge to iterate with (the distance search uses this).
pub(crate) type AtCoarsest<'h> = &'h mut dyn FnMut(
    &mut Solver<'_>,
    &mut Vec<f64>,
    &mut (dyn FnMut(&IterationStats) -> Control + Send),
) -> Result<Vec<f64>>;

/// Runs the coarse levels of `problem`'s pyramid (coarsest first, each to convergence) and
/// carries the result to the full resolution in `u` (not yet gauged). With one level it does
/// nothing (`u` keeps its value and `at_coarsest` is not called). Returns the coarse levels'
/// history, timings and lights, and whether there were coarse levels.
pub(crate) fn coarse_to_fine(
    problem: &Problem<'_>,
    options: &Options,
    u: &mut Vec<f64>,
    start: Instant,
    progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
    mut at_coarsest: Option<AtCoarsest<'_>>,
) -> Result<Carried> {
    let levels =
        crate::pyramid::levels_for(problem.grid.height, problem.grid.width, options.levels);
    let mut carried = Carried {
        history: Vec::new(),
        timings: Timings::default(),
        carried: false,
        lights: problem.rig.lights.clone(),
        refine: options.refine,
        monitor: None,
        diverged: false,
    };
    if levels <= 1 {
        return Ok(carried);
    }
    let mut timings = Timings::default();
    let mut history = Vec::new();
    let t = Instant::now();
    let rigs = crate::pyramid::coarse_rigs(problem.rig, levels);
    let coarse = crate::pyramid::coarse_problems(problem, &rigs, &options.fit_settings(true))?;
    timings.pyramid = t.elapsed();
    let mut current: Vec<f64> = Vec::new();
    for (i, p) in coarse.iter().enumerate().rev() {
        let mut solver = Solver::new(p, options)?;
        solver.start = start;
        solver.set_level(i + 1);
        let h = if i + 1 == coarse.len() {
            current = try_copy(&p.u0, "the depths")?;
            let gauge = match at_coarsest.as_mut() {
                Some(hook) => hook(&mut solver, &mut current, progress)?,
                None => p.gauge.clone(),
            };
            p.grid.apply_gauge(&mut current, &gauge);
            solver.iterate_first(&mut current, &gauge, progress)?.0
        } else {
            solver.set_lights(carried.lights.clone());
            solver.set_refine(refine_on_level(carried.refine, p));
            current = crate::pyramid::upsample(&coarse[i + 1].grid, &current, &p.grid)?;
            let gauge = p.grid.region_means(&current);
            p.grid.apply_gauge(&mut current, &gauge);
            solver
                .iterate(
                    &mut current,
                    &gauge,
                    options.iterations,
                    options.tol,
                    progress,
                )?
                .0
        };
        history.extend(h);
        timings.add(&solver.timings);
        carried.lights = solver.lights.clone();
        // A level above the refinement's size limit does not stop it for good; a fallback or a
        // stop does.
        if refine_on_level(carried.refine, p) == carried.refine {
            carried.refine = solver.refine();
        }
        carried.monitor = carried.monitor.or(solver.monitor);
        carried.diverged |= solver.diverged;
    }
    let t = Instant::now();
    *u = crate::pyramid::upsample(&coarse[0].grid, &current, &problem.grid)?;
    timings.pyramid += t.elapsed();
    carried.history = history;
    carried.timings = timings;
    carried.carried = true;
    Ok(carried)
}

/// The iteration machinery of one problem: the factored global system and the per-facet
/// buffers, reusable for several runs (warm starts, other gauges).
pub(crate) struct Solver<'p> {
    problem: &'p Problem<'p>,
    options: Options,
    /// The global system (None once [`Solver::finish`] has freed it).
    system: Option<GlobalStep>,
    level: usize,
    targets: Vec<[f64; 4]>,
    stats: Vec<FacetStat>,
    next: Vec<f64>,
    /// The current lights (the rig's, or refined).
    lights: Vec<Light>,
    /// The light refinement, when active.
    refiner: Option<Refiner>,
    /// The first level's comparison of runs without and with refinement.
    monitor: Option<Monitor>,
    /// Whether coarse levels ran before this solver's (see [`Solver::carry`]).
    carried: bool,
    /// Whether the refinement was stopped because the residual rose (see `Solver::safeguard`).
    diverged: bool,
    /// Whether the last `iterate` stopped for lack of progress (see 50).
    stalled: bool,
    /// Whether every iteration checks that the surface stays in front of the point lights (off
    /// while the distance search tries candidates, where a bad one is just a high residual).
    pub(crate) check_lights: bool,
    /// Time spent so far.
    pub(crate) timings: Timings,
    /// When the run started (by default when the solver was made; the levels of a pyramid share
    /// the run's start): the iteration statistics' `elapsed` is measured from it.
    pub(crate) start: Instant,
}

impl<'p> Solver<'p> {
    /// Factors the global system of `problem` (with its prior, if any).
    pub fn new(problem: &'p Problem<'p>, options: &Options) -> Result<Solver<'p>> {
        problem.cancel.check()?;
        let t = Instant::now();
        let mut system = GlobalStep::new(
            &problem.grid,
            options.solver,
            sparse_par(options.parallel_sparse),
            problem.prior.as_ref(),
        )?;
        system.set_cancel(&problem.cancel);
        problem.cancel.check()?;
        let n = problem.grid.n_facets();
        Ok(Solver {
            problem,
            options: *options,
            system: Some(system),
            level: 0,
            targets: try_vec(n, [0.0; 4], "the solver's per-facet targets")?,
            stats: try_vec(n, FacetStat::default(), "the solver's per-facet statistics")?,
            next: try_vec(problem.grid.n_unknowns(), 0.0, "the solver's depths")?,
            lights: problem.rig.lights.clone(),
            refiner: options
                .refine
                .is_active()
                .then(|| Refiner::new(options.refine, problem.rig.lights.clone())),
            monitor: None,
            carried: false,
            diverged: false,
            stalled: false,
            check_lights: true,
            timings: Timings {
                factorization: t.elapsed(),
                ..Timings::default()
            },
            start: t,
        })
    }

    /// Sets the pyramid level reported in the iteration statistics.
    pub fn set_level(&mut self, level: usize) {
        self.level = level;
    }

    /// The problem this solver works on.
    pub fn problem(&self) -> &'p Problem<'p> {
        self.problem
    }

    /// Replaces the current lights (the prior's centre stays the rig's).
    pub fn set_lights(&mut self, lights: Vec<Light>) {
        debug_assert_eq!(lights.len(), self.lights.len());
        self.lights = lights;
    }

    /// Goes back to the rig's lights.
    pub fn reset_lights(&mut self) {
        self.lights = self.problem.rig.lights.clone();
    }

    /// What is refined now.
    pub fn refine(&self) -> Refine {
        self.refiner
            .as_ref()
            .map_or(self.options.refine.off(), |r| r.refine)
    }

    /// Changes what is refined from now on.
    pub fn set_refine(&mut self, refine: Refine) {
        self.refiner = refine
            .is_active()
            .then(|| Refiner::new(refine, self.problem.rig.lights.clone()));
    }

    /// Starts the lights over: the rig's lights, `refine` from now on, no record of an earlier
    /// run's drift (each evaluation of the distance search starts this way).
    pub fn restart_lights(&mut self, refine: Refine) {
        self.reset_lights();
        self.set_refine(refine);
        self.diverged = false;
    }

    /// Takes over what the coarse levels carried (lights, refinement, history, timings).
    pub(crate) fn carry(&mut self, coarse: Carried) -> Vec<IterationStats> {
        self.timings.add(&coarse.timings);
        self.carried = coarse.carried;
        if coarse.carried {
            self.lights = coarse.lights;
            self.set_refine(refine_on_level(coarse.refine, self.problem));
            self.monitor = coarse.monitor;
            self.diverged = coarse.diverged;
        }
        coarse.history
    }

    /// Anderson acceleration of the joint iteration over the unknowns and the light parameters
    /// (when refining): the light step with the normals eliminated and the mesh deformation
    /// are each stable, but coupled they are not (a tilt of a nearly flat surface trades
    /// against a smooth pattern of intensities), so the plain alternation can drift.
    fn acceleration(&self, unknowns: usize, scale: f64, distance: f64) -> Result<Option<Anderson>> {
        let Some(refiner) = self.refiner.as_ref() else {
            return Ok(None);
        };
        let parameters = refiner.encode(&self.lights, distance).len();
        // Unknowns in units of the lateral size (log-depths: times the distance).
        let unit = if self.problem.geometry.is_perspective() {
            distance / scale
        } else {
            1.0 / scale
        };
        let mut weights = try_vec(unknowns + parameters, 1.0, "the acceleration weights")?;
        weights[..unknowns].fill(unit * unit);
        Ok(Some(Anderson::new(ANDERSON_DEPTH, weights)))
    }

    /// Mixes the iterate `(u, before)` and its image `(self.next, current lights)`; writes the
    /// accelerated unknowns to `self.next` and lights to `self.lights`. Returns the largest
    /// change of a light parameter.
    fn accelerate(
        &mut self,
        accel: &mut Anderson,
        u: &[f64],
        before: &[f64],
        distance: f64,
    ) -> Result<f64> {
        let Some(refiner) = self.refiner.as_ref() else {
            return Ok(0.0);
        };
        let after = refiner.encode(&self.lights, distance);
        let n = u.len();
        let mut z = crate::memory::try_with_capacity(n + before.len(), "the acceleration")?;
        z.extend_from_slice(u);
        z.extend_from_slice(before);
        let mut g = crate::memory::try_with_capacity(n + after.len(), "the acceleration")?;
        g.extend_from_slice(&self.next);
        g.extend_from_slice(&after);
        let plain = try_copy(&g, "the acceleration")?;
        accel.try_mix(&z, &mut g)?;
        // Trust region: the extrapolation may move the lights at most twice as far as the
        // light step itself did (and no more than 1 % of a parameter's scale beyond it).
        let step = after
            .iter()
            .zip(before)
            .map(|(a, b)| (a - b) * (a - b))
            .sum::<f64>()
            .sqrt();
        let extra = g[n..]
            .iter()
            .zip(&plain[n..])
            .map(|(a, b)| (a - b) * (a - b))
            .sum::<f64>()
            .sqrt();
        let limit = 2.0 * step + 1e-2;
        if extra > limit {
            let t = limit / extra;
            for (x, p) in g.iter_mut().zip(&plain) {
                *x = p + t * (*x - p);
            }
        }
        let lights = refiner.decode(&self.lights, &g[n..], distance);
        let min_depth = g[..n]
            .iter()
            .map(|&x| self.problem.geometry.depth(x))
            .fold(f64::INFINITY, f64::min);
        let in_front = lights.iter().all(|l| l.is_in_front_of(min_depth));
        if !(in_front && g.iter().all(|v| v.is_finite())) {
            accel.restart();
            return Ok(after
                .iter()
                .zip(before)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max));
        }
        self.next.copy_from_slice(&g[..n]);
        self.lights = lights;
        Ok(g[n..]
            .iter()
            .zip(before)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max))
    }

    /// One light step at `u` (when refining): returns the largest relative change.
    fn refine_lights(&mut self, u: &[f64]) -> Result<StepOutcome> {
        let Some(refiner) = self.refiner.as_mut() else {
            return Ok(StepOutcome {
                change: 0.0,
                objective: f64::NAN,
                accepted: false,
            });
        };
        let t = Instant::now();
        let p = self.problem;
        let data = LightData::of(p, self.options.fit_settings(false));
        let outcome = refiner.try_step(&data, &mut self.lights, u);
        self.timings.lights += t.elapsed();
        outcome
    }

    /// The iterations of the first (coarsest) level, from `u` with `gauge`. When light
    /// positions are refined, the level also runs without refinement (from the same start) and
    /// keeps the refinement only if it lowers the photometric residual; otherwise the rig's
    /// lights are kept and refinement stops (recorded in the report).
    pub fn iterate_first(
        &mut self,
        u: &mut Vec<f64>,
        gauge: &[f64],
        progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
    ) -> Result<(Vec<IterationStats>, bool)> {
        let (iterations, tol) = (self.options.iterations, self.options.tol);
        let refine = self.options.refine;
        self.reset_lights();
        self.set_refine(refine);
        if !refine.position {
            return self.iterate(u, gauge, iterations, tol, progress);
        }
        let mut plain = try_copy(u, "the depths")?;
        self.set_refine(Refine::NONE);
        let (mut history, plain_converged) =
            self.iterate(&mut plain, gauge, iterations, tol, progress)?;
        self.local(&plain)?;
        let without = rms_of(&self.stats, self.problem.obs.channels);
        self.set_refine(refine);
        let (refined, converged) = self.iterate(u, gauge, iterations, tol, progress)?;
        history.extend(refined);
        self.local(u)?;
        let with = rms_of(&self.stats, self.problem.obs.channels);
        let fell_back = with.is_nan() || with >= without;
        self.monitor = Some(Monitor {
            without,
            with,
            fell_back,
        });
        if fell_back {
            *u = plain;
            self.reset_lights();
            self.set_refine(Refine::NONE);
            return Ok((history, plain_converged));
        }
        Ok((history, converged))
    }

    /// The local step of this problem with the given residual mode, on unknowns whose depths
    /// are `depths` (if computed).
    fn step<'a>(&'a self, fast_residual: bool, depths: Option<&'a [f64]>) -> LocalStep<'a> {
        let p = self.problem;
        LocalStep {
            grid: &p.grid,
            geometry: &p.geometry,
            model: Model::Near(&self.lights),
            obs: &p.obs,
            settings: self.options.fit_settings(fast_residual),
            depths,
            cancel: &p.cancel,
        }
    }

    /// The depth of every unknown for a pinhole camera (log-depth unknowns), computed once per
    /// local step instead of once per facet corner; None for an orthographic camera.
    fn depths(&self, u: &[f64]) -> Result<Option<Vec<f64>>> {
        use rayon::prelude::*;
        let geometry = &self.problem.geometry;
        if !geometry.is_perspective() {
            return Ok(None);
        }
        crate::memory::try_par_collect(
            u.par_iter().map(|&x| geometry.depth(x)),
            "the vertex depths",
        )
        .map(Some)
    }

    /// The local step on `u` (with fast residuals): the facets' targets and statistics.
    pub fn local(&mut self, u: &[f64]) -> Result<()> {
        let t = Instant::now();
        let depths = self.depths(u)?;
        let (mut targets, mut stats) = (
            std::mem::take(&mut self.targets),
            std::mem::take(&mut self.stats),
        );
        let done = self
            .step(true, depths.as_deref())
            .try_run_targets(u, &mut targets, &mut stats);
        (self.targets, self.stats) = (targets, stats);
        done?;
        self.timings.local += t.elapsed();
        Ok(())
    }

    /// Runs up to `iterations` local/global iterations from `u` (updated in place) with the
    /// per-region `gauge` (in unknowns), stopping when the largest depth change is at most
    /// `tol` times the lateral size. Returns the history and whether it converged.
    pub fn iterate(
        &mut self,
        u: &mut Vec<f64>,
        gauge: &[f64],
        iterations: usize,
        tol: f64,
        progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
    ) -> Result<(Vec<IterationStats>, bool)> {
        let p = self.problem;
        let scale = lateral_size(p);
        let mut history = Vec::new();
        let distance = p
            .geometry
            .depth(gauge.iter().sum::<f64>() / gauge.len().max(1) as f64);
        let mut accel = self.acceleration(u.len(), scale, distance)?;
        // With refinement: the state of lowest residual so far (see `Solver::safeguard`).
        let mut best: Option<Best> = None;
        let mut last_rms = f64::NAN;
        let mut lights_converged = false;
        let (mut smallest, mut since_smallest) = (f64::INFINITY, 0usize);
        self.stalled = false;
        for iteration in 1..=iterations {
            // Once a light step finds nothing to improve, the lights stay for the rest of the
            // run (the mesh then converges as with known lights).
            let before = match (&self.refiner, lights_converged) {
                (Some(r), false) => Some(r.encode(&self.lights, distance)),
                _ => None,
            };
            let mut light_change = 0.0;
            if before.is_some() {
                let outcome = self.refine_lights(u)?;
                light_change = outcome.change;
                if !outcome.accepted {
                    lights_converged = true;
                    accel = None;
                }
            }
            self.local(u)?;
            p.cancel.check()?;
            last_rms = rms_of(&self.stats, p.obs.channels);
            // With position refinement the state before the first global step is the start:
            // never kept as the "best" (restoring it would return the unrefined start, e.g. the
            // starting plane under a stiff prior, while history and status describe the
            // iterated run).
            if (iteration > 1 || !self.options.refine.position)
                && self.safeguard(&mut best, last_rms, u)?
            {
                // The residual rose well above the best state's: back to it, with a fresh
                // acceleration history (or, after MAX_RESTARTS, with the lights frozen).
                accel = self.acceleration(u.len(), scale, distance)?;
                continue;
            }
            let t = Instant::now();
            let system = self.system.as_mut().expect("the solver has not finished");
            let inner_iterations = system.solve(&p.grid, &self.targets, u, &mut self.next)?;
            p.cancel.check()?;
            p.grid.apply_gauge(&mut self.next, gauge);
            if let (Some(accel), Some(before)) = (accel.as_mut(), before) {
                light_change = self.accelerate(accel, u, &before, distance)?;
            }
            let depth_change = max_depth_change(&p.geometry, u, &self.next);
            self.check_in_front(&self.next, iteration)?;
            std::mem::swap(u, &mut self.next);
            self.timings.solve += t.elapsed();

            let stats = IterationStats {
                iteration,
                depth_change,
                rms_residual: rms_of(&self.stats, p.obs.channels),
                elapsed: self.start.elapsed(),
                level: self.level,
                inner_iterations,
                light_change,
                search: None,
            };
            history.push(stats);
            if progress(&stats) == Control::Cancel {
                return Err(Error::Cancelled);
            }
            if !depth_change.is_finite() {
                return Err(Error::Solver(format!(
                    "the depths diverged at iteration {iteration}"
                )));
            }
            if depth_change <= tol * scale && light_change <= tol {
                self.restore_best(best, last_rms, u);
                return Ok((history, true));
            }
            if depth_change < smallest {
                (smallest, since_smallest) = (depth_change, 0);
            } else {
                since_smallest += 1;
                if since_smallest >= STALL_WINDOW {
                    self.stalled = true;
                    break;
                }
            }
        }
        self.restore_best(best, last_rms, u);
        Ok((history, false))
    }

    /// Fails when the surface `u` has reached a point light (the image model then no longer
    /// describes it; e.g. lights nearly in one plane let the surface run off).
    fn check_in_front(&self, u: &[f64], iteration: usize) -> Result<()> {
        use rayon::prelude::*;
        if !self.check_lights {
            return Ok(());
        }
        let geometry = &self.problem.geometry;
        let nearest = u
            .par_iter()
            .map(|&x| geometry.depth(x))
            .reduce(|| f64::INFINITY, f64::min);
        match crate::rig::first_behind(&self.lights, nearest) {
            Some((i, z)) => Err(Error::Solver(format!(
                "at iteration {iteration} the surface reached light {i} (light z = {}, nearest \
                 surface depth {}): the images and the rig do not hold a surface in front of the \
                 lights; check the light positions (units, sign of z), the starting depth and \
                 whether the lights nearly lie in one plane",
                crate::error::g6(z),
                crate::error::g6(nearest)
            ))),
            None => Ok(()),
        }
    }

    /// Tracks the state of lowest photometric residual while the lights are refined (`rms` is
    /// that of the local step on `u` with the current lights). The joint iteration can drift
    /// along weakly determined directions of the lights; when the residual rises above
    /// [`DIVERGENCE`] times the best one, the best state is restored and true is returned; after
    /// [`MAX_RESTARTS`] such returns the refinement stops for the rest of the run.
    fn safeguard(&mut self, best: &mut Option<Best>, rms: f64, u: &mut [f64]) -> Result<bool> {
        if self.refiner.is_none() || !rms.is_finite() {
            return Ok(false);
        }
        Ok(match best {
            Some(b) if rms > DIVERGENCE * b.rms => {
                u.copy_from_slice(&b.u);
                self.lights = b.lights.clone();
                b.restarts += 1;
                if b.restarts > MAX_RESTARTS {
                    self.refiner = None;
                    self.diverged = true;
                }
                true
            }
            Some(b) if rms >= b.rms => false,
            _ => {
                let restarts = best.as_ref().map_or(0, |b| b.restarts);
                *best = Some(Best {
                    rms,
                    u: try_copy(u, "the best state")?,
                    lights: self.lights.clone(),
                    restarts,
                });
                false
            }
        })
    }

    /// At the end of a run with refinement: goes back to the best state when the last one is
    /// clearly worse (by 0.1 % in RMS residual).
    fn restore_best(&mut self, best: Option<Best>, last_rms: f64, u: &mut [f64]) {
        if let Some(b) = best {
            if b.rms < last_rms * (1.0 - 1e-3) {
                u.copy_from_slice(&b.u);
                self.lights = b.lights;
            }
        }
    }

    /// RMS image residual of each region under the last local step.
    pub fn region_residuals(&self) -> Vec<f64> {
        let grid = &self.problem.grid;
        let mut sse = vec![0.0; grid.n_regions];
        let mut count = vec![0usize; grid.n_regions];
        for (fit, ids) in self
            .stats
            .iter()
            .zip(&grid.facet_vertices)
            .filter(|(f, _)| f.valid)
        {
            let r = grid.region_of_unknown[ids[0] as usize] as usize;
            sse[r] += fit.sse;
            count[r] += fit.used as usize * self.problem.obs.channels;
        }
        sse.iter()
            .zip(&count)
            .map(|(s, &n)| {
                if n == 0 {
                    f64::NAN
                } else {
                    (s / n as f64).sqrt()
                }
            })
            .collect()
    }

    /// The final (exact) local step on `u` and the assembled result. The global system and the
    /// iteration buffers are freed first, so that the outputs do not add to their memory.
    pub fn finish(
        mut self,
        u: &[f64],
        history: Vec<IterationStats>,
        converged: bool,
    ) -> Result<Reconstruction> {
        let t = Instant::now();
        drop(std::mem::take(&mut self.targets));
        drop(std::mem::take(&mut self.stats));
        drop(std::mem::take(&mut self.next));
        drop(self.system.take());
        let problem = self.problem;
        let mut outputs = FitOutputs::new(problem)?;
        let depths = self.depths(u)?;
        let step = self.step(false, depths.as_deref());
        let n = problem.grid.n_facets();
        let mut fits = try_vec(n.min(FINAL_CHUNK), FacetFit::EMPTY, "the final fits")?;
        for first in (0..n).step_by(FINAL_CHUNK) {
            let chunk = &mut fits[..(n - first).min(FINAL_CHUNK)];
            step.try_run(u, first, chunk)?;
            problem.cancel.check()?;
            outputs.scatter(problem, first, chunk);
        }
        drop(fits);
        self.timings.local += t.elapsed();
        self.timings.total = self.start.elapsed();
        let refinement = self.report(u);
        let mut result = assemble(problem, u, outputs, history, converged, self.timings)?;
        result.refinement = refinement;
        result.assess(self.options.tol * lateral_size(problem), self.stalled);
        result.lights = std::mem::take(&mut self.lights);
        result.gauge = self
            .problem
            .grid
            .region_means(u)
            .iter()
            .map(|&g| self.problem.geometry.depth(g))
            .collect();
        Ok(result)
    }
}

impl Solver<'_> {
    /// The refinement report at the final unknowns `u` (None without refinement).
    fn report(&self, u: &[f64]) -> Option<RefinementReport> {
        let refine = self.options.refine;
        if !refine.is_active() {
            return None;
        }
        let p = self.problem;
        let data = LightData::of(p, self.options.fit_settings(false));
        let monitor = self.monitor;
        let fell_back = monitor.is_some_and(|m| m.fell_back);
        Some(RefinementReport {
            refine,
            fell_back,
            stopped: self.diverged,
            residual_without: monitor.map_or(f64::NAN, |m| m.without),
            residual_with: monitor.map_or(f64::NAN, |m| m.with),
            conditioning: crate::refine::conditioning(&data, &self.lights, u, &refine).ok(),
        })
    }
}

/// Levels of a pyramid with more unknowns than this keep the lights refined on the coarser
/// levels: a few dozen light parameters are determined by a million pixels as well as by ten,
/// and the refinement's memory (the Anderson history, a few copies of the unknowns) stays
/// bounded at camera resolution. A problem without coarser levels is refined whatever its size.
pub const MAX_REFINE_UNKNOWNS: usize = 1 << 21;

/// The refinement on a finer level of a pyramid: none above [`MAX_REFINE_UNKNOWNS`].
fn refine_on_level(refine: Refine, problem: &Problem<'_>) -> Refine {
    if problem.grid.n_unknowns() > MAX_REFINE_UNKNOWNS {
        refine.off()
    } else {
        refine
    }
}

/// The state of lowest residual of a run with light refinement.
struct Best {
    rms: f64,
    u: Vec<f64>,
    lights: Vec<Light>,
    /// How often the iteration went back to a best state.
    restarts: usize,
}

/// Returns to the best state (with a fresh Anderson history) before the refinement is stopped.
const MAX_RESTARTS: usize = 2;

/// Residual growth (over the best state's) at which the light refinement is stopped.
const DIVERGENCE: f64 = 2.0;

/// Memory of the Anderson acceleration of the light refinement.
const ANDERSON_DEPTH: usize = 5;

/// Largest change of vertex depth between two sets of unknowns.
pub(crate) fn max_depth_change(geometry: &Geometry, a: &[f64], b: &[f64]) -> f64 {
    use rayon::prelude::*;
    a.par_iter()
        .zip(b)
        .map(|(&x, &y)| (geometry.depth(x) - geometry.depth(y)).abs())
        .reduce(|| 0.0, f64::max)
}

/// Lateral size of the image footprint, `max(W * w, H * h)`, with the pixel size taken at the
/// mean gauge depth for a pinhole camera.
pub(crate) fn lateral_size(problem: &Problem<'_>) -> f64 {
    let grid = &problem.grid;
    let mean_gauge = problem.gauge.iter().sum::<f64>() / problem.gauge.len() as f64;
    let [w, h] = problem
        .rig
        .camera
        .pixel_size_at(problem.geometry.depth(mean_gauge));
    (grid.width as f64 * w).max(grid.height as f64 * h)
}

/// Facets per chunk of the final, exact local step (bounds its scratch memory).
const FINAL_CHUNK: usize = 1 << 18;

/// RMS image residual over all usable observations of valid facets.
pub(crate) fn rms_of(fits: &[FacetStat], channels: usize) -> f64 {
    let (sse, n) = fits
        .iter()
        .filter(|f| f.valid)
        .fold((0.0, 0u64), |(s, n), f| {
            (s + f.sse, n + (f.used as usize * channels) as u64)
        });
    if n == 0 {
        f64::NAN
    } else {
        (sse / n as f64).sqrt()
    }
}

// The tests reconstruct synthetic scenes (cargo feature `synth`).
#[cfg(all(test, feature = "synth"))]
mod tests {
    use super::*;
    use crate::problem::{ImageStack, InitialDepth};
    use crate::synth::{Scene, SceneKind};
    use crate::vec3::dot;

    /// The surface is checked against the point lights at every iteration, not only at the
    /// start: a light the surface has reached stops the solver with a clear error.
    #[test]
    fn a_surface_that_reaches_a_light_is_an_error() {
        let scene = Scene::new(SceneKind::SphereCap, 16, 100.0, 200.0, 0).unwrap();
        let images: Vec<f32> = scene.render().unwrap().iter().map(|&v| v as f32).collect();
        let stack = ImageStack::new(&images, scene.rig.n_lights(), 16, 16).unwrap();
        let problem = Problem::new(
            stack,
            &scene.rig,
            Some(&scene.mask),
            InitialDepth::Distance(scene.mean_depth()),
        )
        .unwrap();
        let options = Options {
            levels: 1,
            ..Options::default()
        };
        let mut solver = Solver::new(&problem, &options).unwrap();
        let mut lights = scene.rig.lights.clone();
        if let Light::Point { position, .. } = &mut lights[3] {
            position[2] = scene.mean_depth();
        }
        solver.set_lights(lights);
        let mut u = problem.u0.clone();
        let err = solver
            .iterate(&mut u, &problem.gauge, 5, 0.0, &mut |_| Control::Continue)
            .unwrap_err();
        assert!(
            matches!(&err, Error::Solver(m) if m.contains("reached light 3")),
            "{err}"
        );
    }

    /// Light refinement ([`crate::refine`]) through the whole solver: intensities off by up to 35 % are recovered from a flat start,
    /// the normals match a run with the true lights, and the report is filled.
    #[test]
    fn reconstruct_refines_intensities() {
        let scene = Scene::new(SceneKind::SphereCap, 40, 100.0, 200.0, 0).unwrap();
        let images: Vec<f32> = scene.render().unwrap().iter().map(|&v| v as f32).collect();
        let mut bad = scene.rig.clone();
        for (i, l) in bad.lights.iter_mut().enumerate() {
            if let Light::Point { intensity, .. } = l {
                *intensity = intensity.map(|v| v * (1.0 + 0.35 * (i as f64 * 1.7).cos()));
            }
        }
        let d = scene.mean_depth();
        let run = |rig: &crate::rig::Rig, refine: Refine| {
            let stack = ImageStack::new(&images, rig.n_lights(), 40, 40).unwrap();
            let problem =
                Problem::new(stack, rig, Some(&scene.mask), InitialDepth::Distance(d)).unwrap();
            let options = Options {
                iterations: 50,
                tol: 1e-8,
                refine,
                ..Options::default()
            };
            reconstruct(&problem, &options, &mut |_| Control::Continue).unwrap()
        };
        let truth = run(&scene.rig, Refine::NONE);
        let refined = run(
            &bad,
            Refine {
                intensity: true,
                ..Refine::NONE
            },
        );
        let report = refined.refinement.as_ref().unwrap();
        assert!(!report.fell_back && !report.stopped);
        assert_eq!(
            report.conditioning.as_ref().unwrap().singular_values.len(),
            26
        );
        let ratio: Vec<f64> = refined
            .lights
            .iter()
            .zip(&scene.rig.lights)
            .map(|(a, b)| a.intensity()[0] / b.intensity()[0])
            .collect();
        let mean = (ratio.iter().map(|r| r.ln()).sum::<f64>() / ratio.len() as f64).exp();
        assert!(
            ratio.iter().all(|r| (r / mean - 1.0).abs() < 1e-4),
            "{ratio:?}"
        );
        let worst = truth
            .normals
            .iter()
            .zip(&refined.normals)
            .filter(|(a, _)| a[0].is_finite())
            .map(|(a, b)| dot(*a, *b).min(1.0).acos().to_degrees())
            .fold(0.0, f64::max);
        assert!(worst < 0.01, "largest normal difference {worst} degrees");
    }
}
