//! The conventional baseline the paper compares against: parallel-light photometric stereo
//! followed by integration with the same global step.
//!
//! Each point light becomes one direction `l_k = (p_k - x0) / |p_k - x0|` from the centroid `x0`
//! of the initial surface, with no falloff (its intensity is kept); directional lights keep their
//! direction. Each facet's `g` is the least-squares fit of `I_k = Phi_k l_k . g` over its usable
//! lights, and the normals are integrated by one global step (the targets do not depend on the
//! depths, so one solve is exact).

use std::time::Instant;

use crate::error::Result;
use crate::global::GlobalStep;
use crate::grid::{normalize, sub};
use crate::local::{local_step, FacetFit, FacetStat, Model, Weighting};
use crate::problem::Problem;
use crate::rig::Light;
use crate::solver::{
    assemble, max_depth_change, rms_of, sparse_par, with_threads, FitOutputs, IterationStats,
    Options, Reconstruction, Timings,
};

/// `(direction, intensity)` of each light in the parallel-light model, seen from the centroid of
/// the initial surface.
pub fn parallel_lights(problem: &Problem<'_>) -> Vec<([f64; 3], [f64; 3])> {
    let grid = &problem.grid;
    let mut centroid = [0.0; 3];
    for (i, &u) in problem.u0.iter().enumerate() {
        let x = problem.geometry.position(i, u);
        for (acc, val) in centroid.iter_mut().zip(x) {
            *acc += val;
        }
    }
    let centroid = centroid.map(|s| s / grid.n_unknowns() as f64);
    problem
        .rig
        .lights
        .iter()
        .map(|light| match *light {
            Light::Point {
                position,
                intensity,
                ..
            } => (normalize(sub(position, centroid)), intensity),
            Light::Directional {
                direction,
                intensity,
            } => (direction, intensity),
        })
        .collect()
}

/// Runs the parallel-light baseline on `problem` (`options` give the thresholds, the robust
/// estimator and the threads; the weighting is always in image units).
pub fn reconstruct_parallel(problem: &Problem<'_>, options: &Options) -> Result<Reconstruction> {
    options.validate()?;
    with_threads(options.threads, || {
        let start = Instant::now();
        let grid = &problem.grid;
        let mut timings = Timings::default();
        let t = Instant::now();
        let mut system = GlobalStep::new(
            grid,
            options.solver,
            sparse_par(options.parallel_sparse),
            None,
        )?;
        timings.factorization = t.elapsed();

        let lights = parallel_lights(problem);
        let mut fits: Vec<FacetFit> = vec![FacetFit::EMPTY; grid.n_facets()];
        let settings = Options {
            weighting: Weighting::Image,
            ..*options
        }
        .fit_settings(false);
        let t = Instant::now();
        local_step(
            grid,
            &problem.geometry,
            Model::Parallel(&lights),
            &problem.obs,
            &problem.u0,
            settings,
            &mut fits,
        );
        timings.local = t.elapsed();

        let t = Instant::now();
        let targets: Vec<[f64; 4]> = fits.iter().map(|f| f.target).collect();
        let mut u = vec![0.0; grid.n_unknowns()];
        let inner_iterations = system.solve(grid, &targets, &problem.u0, &mut u)?;
        grid.apply_gauge(&mut u, &problem.gauge);
        timings.solve = t.elapsed();
        timings.total = start.elapsed();
        let history = vec![IterationStats {
            iteration: 1,
            depth_change: max_depth_change(&problem.geometry, &u, &problem.u0),
            rms_residual: rms_of(
                &fits.iter().map(FacetStat::from).collect::<Vec<_>>(),
                problem.obs.channels,
            ),
            elapsed: timings.total,
            level: 0,
            inner_iterations,
        }];
        let mut outputs = FitOutputs::new(problem);
        outputs.scatter(problem, 0, &fits);
        Ok(assemble(problem, &u, outputs, history, true, timings))
    })?
}
