//! The conventional baseline the paper compares against: parallel-light photometric stereo
//! followed by integration with the same global step.
//!
//! Each point light becomes one direction `l_k = (p_k - x0) / |p_k - x0|` from the centroid `x0`
//! of the initial surface, with no falloff (its intensity is kept); directional lights keep their
//! direction. Each facet's `g` is the least-squares fit of `I_k = Phi_k l_k . g` over its usable
//! lights, and the normals are integrated by one global step (the targets do not depend on the
//! depths, so one solve is exact).
//!
//! Under the glossy model ([`Reflectance::Glossy`](crate::Reflectance)) each facet's fit is the
//! glossy one of [`crate::local`] with the parallel lights and the view vector at the initial
//! surface; a lobe that is not given is estimated once from those fits (on the initial surface,
//! with the rig's intensities), before the intensities are refined. The intensities are refined
//! by the Lambertian light step (see [`refine_intensities`]).

use std::time::Instant;

/// The baseline's local step under the parallel `lights`.
fn parallel_step<'a>(
    problem: &'a Problem<'a>,
    lights: &'a [([f64; 3], [f64; 3])],
    settings: FitSettings,
) -> LocalStep<'a> {
    LocalStep {
        cancel: &problem.cancel,
        ..LocalStep::new(
            &problem.grid,
            &problem.geometry,
            Model::Parallel(lights),
            &problem.obs,
            settings,
        )
    }
}

/// Further passes of the baseline's glossy fits, each warm-started from the last (its one local
/// step would otherwise stop the fits after their first few Gauss-Newton steps).
const BASELINE_GLOSSY_PASSES: usize = 4;

use crate::convergence::{max_depth_change, rms_of};
use crate::error::Result;
use crate::global::GlobalStep;
use crate::local::{
    estimate_lobe, glossy_normal, FacetFit, FacetStat, FitSettings, LocalStep, Model, Weighting,
};
use crate::options::{Options, Refine};
use crate::parallel::{sparse_par, with_threads};
use crate::problem::Problem;
use crate::reconstruction::{
    assemble, FitOutputs, IterationStats, Reconstruction, RefinementReport, Timings,
};
use crate::refine::{LightData, Refiner};
use crate::rig::Light;
use crate::vec3::{normalize, sub};

/// `(direction, intensity)` of each light in the parallel-light model, seen from the centroid of
/// the initial surface.
pub fn parallel_lights(problem: &Problem<'_>) -> Vec<([f64; 3], [f64; 3])> {
    let grid = &problem.grid;
    let mut centroid = [0.0; 3];
    for i in 0..grid.n_unknowns() {
        let x = problem.geometry.position(i, problem.u0.at(i));
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

/// Steps of the baseline's intensity refinement (its model does not depend on the depths, so
/// the light step is iterated to convergence once).
const REFINE_STEPS: usize = 100;

/// With `options.refine.intensity`: refines the parallel lights' intensities in place by the
/// (Lambertian) light step of [`crate::refine`] with the thresholds of `settings` (positions are
/// not refined: the model has none) at the starting unknowns `u0` and returns each light's factor.
fn refine_intensities(
    problem: &Problem<'_>,
    options: &Options,
    settings: FitSettings,
    u0: &[f64],
    lights: &mut [([f64; 3], [f64; 3])],
) -> Result<Option<Vec<f64>>> {
    if !options.refine.intensity {
        return Ok(None);
    }
    let refine = Refine {
        intensity: true,
        position: false,
        ..options.refine
    };
    let mut directional: Vec<Light> = lights
        .iter()
        .map(|&(direction, intensity)| Light::Directional {
            direction,
            intensity,
        })
        .collect();
    // Without the facets' glossy normals the light step is the Lambertian one, also under the
    // glossy model: alternating it with glossy fits (as the solver does) failed here (intensity
    // errors of 20 % from 30 % on glossy directional-light scenes, where the Lambertian step
    // leaves 0.6-1 %).
    let data = LightData::of(problem, settings);
    let mut refiner = Refiner::new(refine, directional.clone());
    for _ in 0..REFINE_STEPS {
        let outcome = refiner.try_step(&data, &mut directional, u0)?;
        if !outcome.accepted || outcome.change < 1e-10 {
            break;
        }
    }
    let factors = lights
        .iter_mut()
        .zip(&directional)
        .map(|((_, intensity), refined)| {
            let f = refined.intensity()[0] / intensity[0];
            *intensity = refined.intensity();
            f
        })
        .collect();
    Ok(Some(factors))
}

/// Runs the parallel-light baseline on `problem` (`options` give the thresholds, the robust
/// estimator and the threads; the weighting is always in image units).
pub fn reconstruct_parallel(problem: &Problem<'_>, options: &Options) -> Result<Reconstruction> {
    options.validate()?;
    if options.interreflections {
        return Err(crate::Error::Unusable(
            "interreflections are not supported by the parallel-light baseline (its lights have \
             no position to light the mesh from): use reconstruct"
                .to_string(),
        ));
    }
    problem.check_memory(options)?;
    crate::refine::check_refinable(&options.refine, problem.rig.n_lights())?;
    crate::problem::check_fittable(problem, &options.fit_settings(false))?;
    let u0 = problem.u0.values()?;
    crate::problem::check_light_geometry(problem.rig, &problem.geometry, &u0[..])?;
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

        let mut lights = parallel_lights(problem);
        let mut settings = Options {
            weighting: Weighting::Image,
            ..*options
        }
        .fit_settings(false);
        let t = Instant::now();
        if options.reflectance.is_glossy() && settings.lobe.is_none() {
            let step = parallel_step(problem, &lights, settings);
            settings.lobe = estimate_lobe(&step, &u0[..], None)?;
        }
        timings.local = t.elapsed();
        let t = Instant::now();
        let factors = refine_intensities(problem, options, settings, &u0[..], &mut lights)?;
        timings.lights = t.elapsed();
        let mut fits: Vec<FacetFit> =
            crate::memory::try_vec(grid.n_facets(), FacetFit::EMPTY, "the per-facet fits")?;
        let t = Instant::now();
        let step = parallel_step(problem, &lights, settings);
        step.try_run(&u0[..], 0, &mut fits)?;
        if settings.lobe.is_some() {
            // The baseline has one local step: its glossy fits continue from their own normals
            // for a few more passes, as the solver's iterations would.
            for _ in 0..BASELINE_GLOSSY_PASSES {
                problem.cancel.check()?;
                let warm: Vec<[f32; 3]> = crate::memory::try_collect(
                    fits.iter().map(glossy_normal),
                    "the glossy normals",
                )?;
                let warm_step = LocalStep {
                    warm: Some(&warm),
                    ..step
                };
                warm_step.try_run(&u0[..], 0, &mut fits)?;
            }
        }
        problem.cancel.check()?;
        timings.local += t.elapsed();

        let t = Instant::now();
        let targets: Vec<[f64; 4]> =
            crate::memory::try_collect(fits.iter().map(|f| f.target), "the per-facet targets")?;
        let mut u = crate::memory::try_vec(grid.n_unknowns(), 0.0, "the depths")?;
        let inner_iterations = system.solve(grid, &targets, &u0[..], &mut u)?;
        grid.apply_gauge(&mut u, &problem.gauge);
        timings.solve = t.elapsed();
        timings.total = start.elapsed();
        let history = vec![IterationStats {
            iteration: 1,
            depth_change: max_depth_change(&problem.geometry, &u, &u0[..]),
            rms_residual: rms_of(
                &crate::memory::try_collect(
                    fits.iter().map(FacetStat::from),
                    "the per-facet statistics",
                )?,
                problem.obs.channels,
            ),
            elapsed: timings.total,
            level: 0,
            inner_iterations,
            light_change: 0.0,
            search: None,
        }];
        let mut outputs = FitOutputs::new(problem, settings.lobe.is_some())?;
        outputs.scatter(problem, 0, &fits);
        let mut result = assemble(problem, &u, None, outputs, history, true, timings)?;
        result.assess(f64::INFINITY, false, None);
        result.lobe = settings.lobe;
        if let Some(factors) = factors {
            for (light, f) in result.lights.iter_mut().zip(factors) {
                match light {
                    Light::Point { intensity, .. } | Light::Directional { intensity, .. } => {
                        *intensity = intensity.map(|v| v * f);
                    }
                }
            }
            result.refinement = Some(RefinementReport {
                refine: options.refine,
                fell_back: false,
                stopped: false,
                residual_without: f64::NAN,
                residual_with: f64::NAN,
                conditioning: None,
            });
        }
        Ok(result)
    })?
}
