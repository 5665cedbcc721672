//! Named records that cross the boundary: the statistics of one iteration, the distance
//! search's progress (read by name in Python, never by position), and the reconstruction as a
//! dict (its arrays, records and lights, the lights as the kinds of the rig they came from).

use numpy::PyArray1;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyDictMethods};

use crate::convert::{array, array3};
use crate::rig::Rig;

/// Where the distance search is, with each of its iterations.
#[pyclass(frozen, get_all, module = "nplps._core")]
#[derive(Clone)]
pub struct SearchProgress {
    /// The candidate distance being evaluated (1-based).
    pub candidate: usize,
    /// How many candidates the search evaluates.
    pub candidates: usize,
    /// The candidate's distance.
    pub distance: f64,
    /// The candidate's residual (NaN until its last iteration).
    pub residual: f64,
    /// The best distance so far (NaN before the first candidate ends).
    pub best_distance: f64,
    /// Its residual.
    pub best_residual: f64,
}

/// What one local/global iteration did (`nplps::IterationStats`).
#[pyclass(frozen, get_all, module = "nplps._core")]
#[derive(Clone)]
pub struct IterationStats {
    /// The iteration's number (from 1, per pyramid level).
    pub iteration: usize,
    /// Largest vertex depth change.
    pub depth_change: f64,
    /// RMS image residual.
    pub rms_residual: f64,
    /// Seconds since the solver started.
    pub elapsed: f64,
    /// Pyramid level (0: full resolution).
    pub level: usize,
    /// Conjugate-gradient iterations of the global step.
    pub inner_iterations: usize,
    /// Largest relative light change of the iteration's light step.
    pub light_change: f64,
    /// The distance search's progress (None outside the search).
    pub search: Option<SearchProgress>,
}

impl From<&nplps::IterationStats> for IterationStats {
    fn from(s: &nplps::IterationStats) -> IterationStats {
        IterationStats {
            iteration: s.iteration,
            depth_change: s.depth_change,
            rms_residual: s.rms_residual,
            elapsed: s.elapsed.as_secs_f64(),
            level: s.level,
            inner_iterations: s.inner_iterations,
            light_change: s.light_change,
            search: s.search.map(|p| SearchProgress {
                candidate: p.candidate,
                candidates: p.candidates,
                distance: p.distance,
                residual: p.residual,
                best_distance: p.best_distance,
                best_residual: p.best_residual,
            }),
        }
    }
}

/// The light refinement's report as a dict.
fn refinement_dict<'py>(
    py: Python<'py>,
    report: &nplps::RefinementReport,
) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("mode", report.refine.name())?;
    d.set_item("prior_weight", report.refine.prior_weight)?;
    d.set_item("fell_back", report.fell_back)?;
    d.set_item("stopped", report.stopped)?;
    d.set_item("residual_without", report.residual_without)?;
    d.set_item("residual_with", report.residual_with)?;
    if let Some(c) = &report.conditioning {
        let cd = PyDict::new(py);
        cd.set_item("singular_values", c.singular_values.clone())?;
        cd.set_item(
            "standard_errors",
            c.standard_errors
                .iter()
                .map(|s| s.to_vec())
                .collect::<Vec<_>>(),
        )?;
        cd.set_item("rms_residual", c.rms_residual)?;
        cd.set_item("distance", c.distance)?;
        d.set_item("conditioning", cd)?;
    }
    Ok(d)
}

/// The reconstruction as a dict of numpy arrays and plain values.
pub fn reconstruction_dict<'py>(
    py: Python<'py>,
    r: nplps::Reconstruction,
    rig: &Rig,
) -> PyResult<Bound<'py, PyDict>> {
    let (h, w) = (r.height, r.width);
    let d = PyDict::new(py);
    d.set_item("depth", array(py, r.depth, &[h + 1, w + 1])?)?;
    d.set_item("normals", array3(py, r.normals, &[h, w])?)?;
    // One value a pixel for grey images (the core keeps no three equal values).
    let albedo = if r.channels == 1 {
        array(py, r.albedo, &[h, w])?
    } else {
        array(py, r.albedo, &[h, w, r.channels])?
    };
    d.set_item("albedo", albedo)?;
    d.set_item("residual", array(py, r.residual, &[h, w])?)?;
    d.set_item("lights_used", array(py, r.lights_used, &[h, w])?)?;
    d.set_item("regions", array(py, r.regions, &[h, w])?)?;
    d.set_item("gauge", PyArray1::from_vec(py, r.gauge))?;
    let history: Vec<IterationStats> = r.history.iter().map(IterationStats::from).collect();
    d.set_item("history", history)?;
    d.set_item("converged", r.converged)?;
    d.set_item("status", r.status.name())?;
    d.set_item("status_reason", &r.status_reason)?;
    d.set_item("negative_observations", r.negative_observations)?;
    let t = PyDict::new(py);
    t.set_item("factorization", r.timings.factorization.as_secs_f64())?;
    t.set_item("local", r.timings.local.as_secs_f64())?;
    t.set_item("solve", r.timings.solve.as_secs_f64())?;
    t.set_item("pyramid", r.timings.pyramid.as_secs_f64())?;
    t.set_item("lights", r.timings.lights.as_secs_f64())?;
    t.set_item("shadows", r.timings.shadows.as_secs_f64())?;
    t.set_item("indirect", r.timings.indirect.as_secs_f64())?;
    t.set_item("total", r.timings.total.as_secs_f64())?;
    d.set_item("timings", t)?;
    d.set_item("lights", rig.with_lights(r.lights))?;
    if let Some(report) = &r.refinement {
        d.set_item("refinement", refinement_dict(py, report)?)?;
    }
    if let Some(shadows) = &r.shadows {
        // Bit-packed: bit k % 64 of word k / 64 of pixel (r, c) is light k (unpacked on demand
        // in Python).
        let words = shadows.words_per_pixel();
        d.set_item(
            "shadow_bits",
            array(py, shadows.bits().to_vec(), &[h, w, words])?,
        )?;
    }
    if let Some(trust) = r.trust {
        d.set_item("normal_sigma", array(py, trust.normal_sigma, &[h, w])?)?;
        d.set_item("held_out_error", array(py, trust.held_out, &[h, w])?)?;
        let lights = PyDict::new(py);
        let column = |f: fn(&nplps::LightTrust) -> f64| trust.lights.iter().map(f).collect();
        lights.set_item("residual", PyArray1::from_vec(py, column(|l| l.residual)))?;
        lights.set_item("held_out", PyArray1::from_vec(py, column(|l| l.held_out)))?;
        lights.set_item(
            "mean_intensity",
            PyArray1::from_vec(py, column(|l| l.mean_intensity)),
        )?;
        lights.set_item(
            "facets",
            PyArray1::from_vec(py, column(|l| l.facets as f64)),
        )?;
        d.set_item("light_trust", lights)?;
    }
    if let Some(lobe) = r.matte_lobe {
        d.set_item("matte_lobe", (lobe.alpha, lobe.eta))?;
    }
    if let Some(check) = r.lobe_check {
        let c = PyDict::new(py);
        c.set_item("glossy", check.glossy)?;
        c.set_item("lambertian", check.lambertian)?;
        c.set_item("observations", check.observations)?;
        c.set_item("seen", check.seen)?;
        c.set_item("highlight", check.highlight)?;
        c.set_item("highlight_confirmed", check.highlight_confirmed())?;
        d.set_item("lobe_check", c)?;
    }
    if let Some(lobe) = r.lobe {
        d.set_item("lobe", (lobe.alpha, lobe.eta))?;
        d.set_item("lobe_diffuse", lobe.diffuse.name())?;
        d.set_item("specular", array(py, r.specular, &[h, w])?)?;
    }
    Ok(d)
}
