//! The conventional baseline the paper compares against: parallel-light photometric stereo
//! followed by integration with the same global step.
//!
//! Each light becomes one direction `l_k = (p_k - x0) / |p_k - x0|` from the centroid `x0` of
//! the initial surface, with no falloff; each facet's `g` solves
//! `min sum_k (l_k . g - I_k)^2` over its usable lights, and the normals are integrated by one
//! global step (orthographic targets do not depend on the depths, so one solve is exact).

use std::time::Instant;

use crate::error::Result;
use crate::global::GlobalSystem;
use crate::grid::{normalize, sub};
use crate::local::{local_step, FacetFit, FitSettings, Model};
use crate::problem::Problem;
use crate::solver::{
    assemble, check_dark, rms_of, sparse_par, with_threads, IterationStats, Reconstruction, Timings,
};

/// Light directions of the parallel-light model, seen from the centroid of the initial surface.
pub fn parallel_directions(problem: &Problem<'_>) -> Vec<[f64; 3]> {
    let grid = &problem.grid;
    let mut centroid = [0.0; 3];
    for (u, &v) in grid.active.iter().enumerate() {
        let [x, y] = problem
            .rig
            .camera
            .vertex_xy(v / (grid.width + 1), v % (grid.width + 1));
        for (acc, val) in centroid.iter_mut().zip([x, y, problem.z0[u]]) {
            *acc += val;
        }
    }
    let centroid = centroid.map(|s| s / grid.n_unknowns() as f64);
    problem
        .rig
        .lights
        .iter()
        .map(|p| normalize(sub(*p, centroid)))
        .collect()
}

/// Runs the parallel-light baseline on `problem` (`dark` as in the solver options).
pub fn reconstruct_parallel(
    problem: &Problem<'_>,
    dark: f64,
    threads: usize,
) -> Result<Reconstruction> {
    check_dark(dark)?;
    with_threads(threads, || {
        let start = Instant::now();
        let grid = &problem.grid;
        let mut timings = Timings::default();
        let t = Instant::now();
        let mut system = GlobalSystem::new(grid, sparse_par(false))?;
        timings.factorization = t.elapsed();

        let directions = parallel_directions(problem);
        let camera = &problem.rig.camera;
        let mut fits: Vec<FacetFit> = vec![FacetFit::EMPTY; grid.n_facets()];
        let t = Instant::now();
        local_step(
            grid,
            camera,
            Model::Parallel(&directions),
            &problem.obs,
            &problem.z0,
            FitSettings {
                dark,
                fast_residual: false,
            },
            &mut fits,
        );
        timings.local = t.elapsed();

        let t = Instant::now();
        let targets: Vec<[f64; 4]> = fits.iter().map(|f| f.target).collect();
        let mut z = vec![0.0; grid.n_unknowns()];
        system.solve(grid, &targets, &problem.z0, &mut z);
        grid.apply_gauge(&mut z, &problem.gauge);
        timings.solve = t.elapsed();
        let depth_change = z
            .iter()
            .zip(&problem.z0)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        timings.total = start.elapsed();
        let history = vec![IterationStats {
            iteration: 1,
            depth_change,
            rms_residual: rms_of(&fits),
            elapsed: timings.total,
        }];
        Ok(assemble(problem, &z, &fits, history, true, timings))
    })?
}
