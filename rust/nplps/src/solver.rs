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

use std::time::{Duration, Instant};

use faer::Par;

use crate::error::{Error, Result};
use crate::geometry::Geometry;
use crate::global::{GlobalSolver, GlobalStep};
use crate::local::{FacetFit, FacetStat, FitSettings, LocalStep, Model, Robust, Weighting};
use crate::problem::Problem;

/// Options of the iteration.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Options {
    /// Maximum number of local/global iterations.
    pub iterations: usize,
    /// Stop when the largest vertex depth change of an iteration is at most `tol` times the
    /// lateral size of the grid.
    pub tol: f64,
    /// Observations at or below this value are treated as shadowed and left out of the fits.
    pub dark: f64,
    /// Observations at or above this value are treated as saturated and left out of the fits.
    pub saturation: f64,
    /// Weighting of the per-facet systems.
    pub weighting: Weighting,
    /// Robust estimator of the per-facet fits.
    pub robust: Robust,
    /// Worker threads (0: rayon's default, all cores).
    pub threads: usize,
    /// Run faer's sparse factorization and solves on the worker threads too. Off by default:
    /// on 512 x 512 images with 2 cores the parallel paths measured 20-30% slower than the
    /// sequential ones (see faer issue 211), while the local step uses every thread.
    pub parallel_sparse: bool,
    /// How the global step's linear system is solved.
    pub solver: GlobalSolver,
    /// Coarse-to-fine pyramid levels (1: the full resolution only; 0: automatic, see
    /// [`crate::pyramid`]).
    pub levels: usize,
}

impl Options {
    /// Checks the options: `tol >= 0`, `dark` finite, `saturation > dark`.
    pub fn validate(&self) -> Result<()> {
        if self.tol.is_nan() || self.tol < 0.0 {
            return Err(Error::Input(format!("tol must be >= 0, got {}", self.tol)));
        }
        check_thresholds(self.dark, self.saturation)
    }

    /// The per-facet fit settings of these options.
    pub fn fit_settings(&self, fast_residual: bool) -> FitSettings {
        FitSettings {
            dark: self.dark,
            saturation: self.saturation,
            weighting: self.weighting,
            robust: self.robust,
            fast_residual,
        }
    }
}

/// The shadow threshold must be a finite number below the saturation threshold.
pub(crate) fn check_thresholds(dark: f64, saturation: f64) -> Result<()> {
    if !dark.is_finite() {
        return Err(Error::Input(format!(
            "dark (the shadow threshold) must be a finite number, got {dark}"
        )));
    }
    if saturation.is_nan() || saturation <= dark {
        return Err(Error::Input(format!(
            "saturation must be above dark (= {dark}), got {saturation}"
        )));
    }
    Ok(())
}

impl Default for Options {
    fn default() -> Self {
        Options {
            iterations: 10,
            tol: 1e-6,
            dark: 0.0,
            saturation: f64::INFINITY,
            weighting: Weighting::Image,
            robust: Robust::None,
            threads: 0,
            parallel_sparse: false,
            solver: GlobalSolver::Auto,
            levels: 0,
        }
    }
}

/// What one iteration did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IterationStats {
    /// 1-based iteration number.
    pub iteration: usize,
    /// Largest vertex depth change of this iteration.
    pub depth_change: f64,
    /// RMS image residual over all usable observations of this iteration's local step.
    pub rms_residual: f64,
    /// Time since the solver started.
    pub elapsed: Duration,
    /// Pyramid level (0: full resolution; level l has 2^l times fewer pixels per side).
    pub level: usize,
    /// Conjugate-gradient iterations of the global step (0 for the direct solver).
    pub inner_iterations: usize,
}

/// Answer of a progress callback.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Control {
    /// Go on iterating.
    Continue,
    /// Stop now: the solver returns [`Error::Cancelled`].
    Cancel,
}

/// Wall-clock time spent in each part.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Timings {
    /// Assembly, analysis and factorization of the global system.
    pub factorization: Duration,
    /// All local steps.
    pub local: Duration,
    /// All global solves (right sides, back-substitution, gauge).
    pub solve: Duration,
    /// Building the coarse-to-fine pyramid (its levels' own work is counted above).
    pub pyramid: Duration,
    /// Everything.
    pub total: Duration,
}

impl Timings {
    /// Adds the parts of `other` (not its total).
    pub fn add(&mut self, other: &Timings) {
        self.factorization += other.factorization;
        self.local += other.local;
        self.solve += other.solve;
        self.pyramid += other.pyramid;
    }
}

/// The result of a reconstruction. Per-pixel arrays are (H, W) row-major, per-vertex arrays
/// (H+1, W+1); NaN (or 0 for counts) outside the mask.
#[derive(Debug, Clone)]
pub struct Reconstruction {
    /// Image height H.
    pub height: usize,
    /// Image width W.
    pub width: usize,
    /// Vertex depths z.
    pub depth: Vec<f64>,
    /// Local-fit unit normals (the mesh normal where a facet could not be fitted).
    pub normals: Vec<[f64; 3]>,
    /// Channels of the images (1 or 3): the albedo has as many meaningful entries.
    pub channels: usize,
    /// Fitted albedo per channel (grey: three equal values; NaN where a facet could not be
    /// fitted).
    pub albedo: Vec<[f64; 3]>,
    /// RMS image residual of each facet's fit.
    pub residual: Vec<f64>,
    /// Number of usable lights of each facet.
    pub lights_used: Vec<u32>,
    /// Region label of each pixel (-1 outside the mask).
    pub regions: Vec<i32>,
    /// Gauge of each region: its arithmetic mean vertex depth (orthographic) or geometric mean
    /// vertex depth (pinhole).
    pub gauge: Vec<f64>,
    /// One entry per iteration run.
    pub history: Vec<IterationStats>,
    /// Whether the tolerance was reached.
    pub converged: bool,
    /// Number of negative observations inside the mask (treated as unlit).
    pub negative_observations: usize,
    /// Where the time went.
    pub timings: Timings,
}

/// Runs `f` on a rayon pool of `threads` workers (0: the global pool).
pub(crate) fn with_threads<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> Result<T> {
    if threads == 0 {
        return Ok(f());
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| Error::Input(format!("cannot start {threads} worker threads: {e}")))?;
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
    with_threads(options.threads, || {
        let start = Instant::now();
        let mut u = problem.u0.clone();
        let (mut history, coarse_timings, carried) =
            coarse_to_fine(problem, options, &mut u, start, progress, None)?;
        if carried {
            problem.grid.apply_gauge(&mut u, &problem.gauge);
        }
        let mut solver = Solver::new(problem, options)?;
        solver.timings.add(&coarse_timings);
        let (fine, converged) = solver.iterate(
            &mut u,
            &problem.gauge,
            options.iterations,
            options.tol,
            start,
            progress,
        )?;
        history.extend(fine);
        Ok(solver.finish(&u, history, converged, start))
    })?
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
/// history and timings, and whether there were coarse levels.
pub(crate) fn coarse_to_fine(
    problem: &Problem<'_>,
    options: &Options,
    u: &mut Vec<f64>,
    start: Instant,
    progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
    mut at_coarsest: Option<AtCoarsest<'_>>,
) -> Result<(Vec<IterationStats>, Timings, bool)> {
    let levels =
        crate::pyramid::levels_for(problem.grid.height, problem.grid.width, options.levels);
    let mut timings = Timings::default();
    let mut history = Vec::new();
    if levels <= 1 {
        return Ok((history, timings, false));
    }
    let t = Instant::now();
    let rigs = crate::pyramid::coarse_rigs(problem.rig, levels);
    let coarse = crate::pyramid::coarse_problems(problem, &rigs, &options.fit_settings(true))?;
    timings.pyramid = t.elapsed();
    let mut current: Vec<f64> = Vec::new();
    for (i, p) in coarse.iter().enumerate().rev() {
        let mut solver = Solver::new(p, options)?;
        solver.set_level(i + 1);
        let gauge = if i + 1 == coarse.len() {
            current = p.u0.clone();
            match at_coarsest.as_mut() {
                Some(hook) => hook(&mut solver, &mut current, progress)?,
                None => p.gauge.clone(),
            }
        } else {
            current = crate::pyramid::upsample(&coarse[i + 1].grid, &current, &p.grid);
            p.grid.region_means(&current)
        };
        p.grid.apply_gauge(&mut current, &gauge);
        let (h, _) = solver.iterate(
            &mut current,
            &gauge,
            options.iterations,
            options.tol,
            start,
            progress,
        )?;
        history.extend(h);
        timings.add(&solver.timings);
    }
    let t = Instant::now();
    *u = crate::pyramid::upsample(&coarse[0].grid, &current, &problem.grid);
    timings.pyramid += t.elapsed();
    Ok((history, timings, true))
}

/// The iteration machinery of one problem: the factored global system and the per-facet
/// buffers, reusable for several runs (warm starts, other gauges).
pub struct Solver<'p> {
    problem: &'p Problem<'p>,
    options: Options,
    /// The global system (None once [`Solver::finish`] has freed it).
    system: Option<GlobalStep>,
    level: usize,
    targets: Vec<[f64; 4]>,
    stats: Vec<FacetStat>,
    next: Vec<f64>,
    /// Time spent so far.
    pub timings: Timings,
}

impl<'p> Solver<'p> {
    /// Factors the global system of `problem` (with its prior, if any).
    pub fn new(problem: &'p Problem<'p>, options: &Options) -> Result<Solver<'p>> {
        let t = Instant::now();
        let system = GlobalStep::new(
            &problem.grid,
            options.solver,
            sparse_par(options.parallel_sparse),
            problem.prior.as_ref(),
        )?;
        let n = problem.grid.n_facets();
        Ok(Solver {
            problem,
            options: *options,
            system: Some(system),
            level: 0,
            targets: vec![[0.0; 4]; n],
            stats: vec![FacetStat::default(); n],
            next: vec![0.0; problem.grid.n_unknowns()],
            timings: Timings {
                factorization: t.elapsed(),
                ..Timings::default()
            },
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

    /// The local step of this problem with the given residual mode, on unknowns whose depths
    /// are `depths` (if computed).
    fn step<'a>(&'a self, fast_residual: bool, depths: Option<&'a [f64]>) -> LocalStep<'a> {
        let p = self.problem;
        LocalStep {
            grid: &p.grid,
            geometry: &p.geometry,
            model: Model::Near(&p.rig.lights),
            obs: &p.obs,
            settings: self.options.fit_settings(fast_residual),
            depths,
        }
    }

    /// The depth of every unknown for a pinhole camera (log-depth unknowns), computed once per
    /// local step instead of once per facet corner; None for an orthographic camera.
    fn depths(&self, u: &[f64]) -> Option<Vec<f64>> {
        use rayon::prelude::*;
        let geometry = &self.problem.geometry;
        geometry
            .is_perspective()
            .then(|| u.par_iter().map(|&x| geometry.depth(x)).collect())
    }

    /// The local step on `u` (with fast residuals): the facets' targets and statistics.
    pub fn local(&mut self, u: &[f64]) {
        let t = Instant::now();
        let (mut targets, mut stats) = (
            std::mem::take(&mut self.targets),
            std::mem::take(&mut self.stats),
        );
        let depths = self.depths(u);
        self.step(true, depths.as_deref())
            .run_targets(u, &mut targets, &mut stats);
        (self.targets, self.stats) = (targets, stats);
        self.timings.local += t.elapsed();
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
        start: Instant,
        progress: &mut (dyn FnMut(&IterationStats) -> Control + Send),
    ) -> Result<(Vec<IterationStats>, bool)> {
        let p = self.problem;
        let scale = lateral_size(p);
        let mut history = Vec::new();
        for iteration in 1..=iterations {
            self.local(u);
            let t = Instant::now();
            let system = self.system.as_mut().expect("the solver has not finished");
            let inner_iterations = system.solve(&p.grid, &self.targets, u, &mut self.next)?;
            p.grid.apply_gauge(&mut self.next, gauge);
            let depth_change = max_depth_change(&p.geometry, u, &self.next);
            std::mem::swap(u, &mut self.next);
            self.timings.solve += t.elapsed();

            let stats = IterationStats {
                iteration,
                depth_change,
                rms_residual: rms_of(&self.stats, p.obs.channels),
                elapsed: start.elapsed(),
                level: self.level,
                inner_iterations,
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
            if depth_change <= tol * scale {
                return Ok((history, true));
            }
        }
        Ok((history, false))
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
        start: Instant,
    ) -> Reconstruction {
        let t = Instant::now();
        drop(std::mem::take(&mut self.targets));
        drop(std::mem::take(&mut self.stats));
        drop(std::mem::take(&mut self.next));
        drop(self.system.take());
        let problem = self.problem;
        let mut outputs = FitOutputs::new(problem);
        let depths = self.depths(u);
        let step = self.step(false, depths.as_deref());
        let n = problem.grid.n_facets();
        let mut fits = vec![FacetFit::EMPTY; n.min(FINAL_CHUNK)];
        for first in (0..n).step_by(FINAL_CHUNK) {
            let chunk = &mut fits[..(n - first).min(FINAL_CHUNK)];
            step.run(u, first, chunk);
            outputs.scatter(problem, first, chunk);
        }
        drop(fits);
        self.timings.local += t.elapsed();
        self.timings.total = start.elapsed();
        let mut result = assemble(problem, u, outputs, history, converged, self.timings);
        result.gauge = self
            .problem
            .grid
            .region_means(u)
            .iter()
            .map(|&g| self.problem.geometry.depth(g))
            .collect();
        result
    }
}

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

/// The per-pixel results of the final local step (NaN, or 0 for counts, outside the mask).
pub(crate) struct FitOutputs {
    normals: Vec<[f64; 3]>,
    albedo: Vec<[f64; 3]>,
    residual: Vec<f64>,
    lights_used: Vec<u32>,
}

impl FitOutputs {
    /// Empty outputs for `problem`'s image size.
    pub(crate) fn new(problem: &Problem<'_>) -> FitOutputs {
        let n = problem.grid.height * problem.grid.width;
        FitOutputs {
            normals: vec![[f64::NAN; 3]; n],
            albedo: vec![[f64::NAN; 3]; n],
            residual: vec![f64::NAN; n],
            lights_used: vec![0; n],
        }
    }

    /// Writes the fits of facets `first..first + fits.len()` onto their pixels.
    pub(crate) fn scatter(&mut self, problem: &Problem<'_>, first: usize, fits: &[FacetFit]) {
        let channels = problem.obs.channels;
        for (fit, &p) in fits.iter().zip(&problem.grid.facets[first..]) {
            self.normals[p] = fit.normal;
            self.albedo[p] = fit.albedo;
            self.residual[p] = fit.rms(channels);
            self.lights_used[p] = fit.used;
        }
    }
}

/// Assembles the result: the per-pixel `outputs` and the unknowns `z` scattered onto the
/// vertex grid.
pub(crate) fn assemble(
    problem: &Problem<'_>,
    z: &[f64],
    outputs: FitOutputs,
    history: Vec<IterationStats>,
    converged: bool,
    timings: Timings,
) -> Reconstruction {
    let grid = &problem.grid;
    Reconstruction {
        height: grid.height,
        width: grid.width,
        channels: problem.obs.channels,
        depth: grid.scatter_vertices(
            &z.iter()
                .map(|&u| problem.geometry.depth(u))
                .collect::<Vec<_>>(),
        ),
        normals: outputs.normals,
        albedo: outputs.albedo,
        residual: outputs.residual,
        lights_used: outputs.lights_used,
        regions: grid.pixel_regions(),
        gauge: problem
            .gauge
            .iter()
            .map(|&g| problem.geometry.depth(g))
            .collect(),
        history,
        converged,
        negative_observations: problem.negative_observations,
        timings,
    }
}
