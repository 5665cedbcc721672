//! Named records that cross the boundary: the statistics of one iteration and the distance
//! search's progress (read by name in Python, never by position).

use pyo3::prelude::*;

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
