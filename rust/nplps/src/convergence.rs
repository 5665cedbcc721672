//! What the solver's loop measures and when it stops: the depth change, the image residual and
//! the lateral size that scales the tolerance; the safeguards (the state of lowest residual
//! while the lights are refined, the surface in front of the lights, divergence, stalls).

use crate::error::{Error, Result};
use crate::geometry::Geometry;
use crate::grid::Grid;
use crate::local::FacetStat;
use crate::memory::try_copy;
use crate::problem::Problem;
use crate::reconstruction::STALL_WINDOW;
use crate::refinement::LightRefinement;
use crate::rig::Light;

/// Largest change of vertex depth between two sets of unknowns.
pub(crate) fn max_depth_change(geometry: &Geometry, a: &[f64], b: &[f64]) -> f64 {
    use rayon::prelude::*;
    a.par_iter()
        .zip(b)
        .map(|(&x, &y)| (geometry.depth(x) - geometry.depth(y)).abs())
        .reduce(|| 0.0, f64::max)
}

/// Alternations in a row after which [`Oscillation`] damps the iteration.
const OSCILLATION_FLIPS: usize = 3;

/// Damping of a two-cycle of the loop.
///
/// The map `T` of one iteration (local fits at the current surface, then the global step) can
/// settle into alternating between two surfaces instead of converging: seen on a 7-light capture
/// (queau_human1) where cast-shadow masks had left 4-5 lights to the facets at a ragged mask
/// border, whose vertices then swung by 7 mm every iteration while two iterations apart they
/// agreed to 1e-4. Detection: the unknown that moved most in one step moves back at the next
/// (opposite sign, at least half as far), with the step above the tolerance, [`OSCILLATION_FLIPS`]
/// iterations in a row. From then on the run takes the averaged (Krasnoselskii-Mann) step
/// `u <- (u + T(u)) / 2`, whose fixed points are those of `T` and which turns a two-cycle
/// `a <-> b` into a contraction towards the point between them. A loop that converges
/// monotonically never flips and runs exactly as without it.
#[derive(Debug, Default)]
pub(crate) struct Oscillation {
    /// The unknown that moved most at the last step, and its signed change.
    last: Option<(usize, f64)>,
    flips: usize,
    damped: bool,
}

impl Oscillation {
    /// Forgets the past steps (a new run).
    pub(crate) fn reset(&mut self) {
        *self = Oscillation::default();
    }

    /// Averages `next` (the image of `u` under the loop's map) with `u` when damped.
    pub(crate) fn damp(&self, u: &[f64], next: &mut [f64]) {
        use rayon::prelude::*;
        if self.damped {
            next.par_iter_mut()
                .zip(u)
                .for_each(|(n, &x)| *n = 0.5 * (*n + x));
        }
    }

    /// Records the step from `u` to `next` (as taken) and returns its largest depth change
    /// (as [`max_depth_change`], in the same pass that finds the unknown that moved most) and
    /// the smallest depth of `next` (NaN ignored; for [`check_in_front`], from the depths this
    /// pass computes anyway: a pass of its own took one `exp` per unknown again, about 0.05 s of
    /// CPU per iteration at 12 MP): an alternation counts only when that change is above the
    /// tolerance `limit`.
    pub(crate) fn record(
        &mut self,
        geometry: &Geometry,
        u: &[f64],
        next: &[f64],
        limit: f64,
    ) -> (f64, f64) {
        use rayon::prelude::*;
        // (largest depth change, (unknown that moved most, its signed change), nearest depth
        // of `next`); ties keep the first unknown, whatever the split of the reduction.
        let (moved, largest, nearest) = u
            .par_iter()
            .zip(next)
            .enumerate()
            .map(|(i, (&a, &b))| {
                let z = geometry.depth(b);
                let depth = (geometry.depth(a) - z).abs();
                (depth, (i, b - a), z)
            })
            .reduce(
                || (0.0, (0, 0.0), f64::INFINITY),
                |x, y| {
                    let largest = if y.1 .1.abs() > x.1 .1.abs() {
                        y.1
                    } else {
                        x.1
                    };
                    (x.0.max(y.0), largest, x.2.min(y.2))
                },
            );
        let back = match self.last {
            Some((j, before)) if j < u.len() => {
                let now = next[j] - u[j];
                now * before < 0.0 && now.abs() >= 0.5 * before.abs()
            }
            _ => false,
        };
        self.flips = if back && moved > limit {
            self.flips + 1
        } else {
            0
        };
        if self.flips >= OSCILLATION_FLIPS {
            self.damped = true;
        }
        self.last = Some(largest);
        (moved, nearest)
    }
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

/// RMS image residual of each region of `grid` under the facet statistics `stats`.
pub(crate) fn region_residuals(grid: &Grid, stats: &[FacetStat], channels: usize) -> Vec<f64> {
    let mut sse = vec![0.0; grid.n_regions];
    let mut count = vec![0usize; grid.n_regions];
    for (fit, ids) in stats
        .iter()
        .zip(grid.all_facet_vertices())
        .filter(|(f, _)| f.valid)
    {
        let r = grid.region_of_unknown[ids[0] as usize] as usize;
        sse[r] += fit.sse;
        count[r] += fit.used as usize * channels;
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

/// Median over each region's fitted facets of the facet's RMS image residual
/// `sqrt(sse / (used * channels))` (NaN for a region without one).
///
/// The distance search's criterion under the glossy model: there the RMS over all observations
/// is ruled by the few facets whose fit fails (a highlight explained by a wrong normal), and its
/// minimum wanders by several percent of the distance, while the median's stays at the true
/// distance (measured on the PBR renders of `benchmarks/pbr`, see docs/method.md).
pub(crate) fn region_median_residuals(
    grid: &Grid,
    stats: &[FacetStat],
    channels: usize,
) -> Vec<f64> {
    let mut per: Vec<Vec<f64>> = vec![Vec::new(); grid.n_regions];
    for (fit, ids) in stats
        .iter()
        .zip(grid.all_facet_vertices())
        .filter(|(f, _)| f.valid && f.used > 0)
    {
        let r = grid.region_of_unknown[ids[0] as usize] as usize;
        per[r].push((fit.sse / (fit.used as usize * channels) as f64).sqrt());
    }
    per.into_iter().map(|mut v| median(&mut v)).collect()
}

/// The median of `values` (reordered; the mean of the two middle ones for an even count, NaN
/// for none).
fn median(values: &mut [f64]) -> f64 {
    let n = values.len();
    if n == 0 {
        return f64::NAN;
    }
    let (low, &mut mid, _) = values.select_nth_unstable_by(n / 2, f64::total_cmp);
    if n % 2 == 1 {
        return mid;
    }
    let below = low.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    0.5 * (below + mid)
}

/// Largest absolute difference of two parameter vectors (0 when empty).
pub(crate) fn max_change(a: &[f64], b: &[f64]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max)
}

/// The smallest depth of the unknowns `u` (sequentially, NaN ignored).
pub(crate) fn nearest(geometry: &Geometry, u: &[f64]) -> f64 {
    u.iter()
        .map(|&x| geometry.depth(x))
        .fold(f64::INFINITY, f64::min)
}

/// Fails when the surface `u` has reached a point light of `lights` (the image model then no
/// longer describes it; e.g. lights nearly in one plane let the surface run off), given the
/// surface's smallest depth `nearest` (NaN ignored, as [`Oscillation::record`] finds it).
pub(crate) fn check_in_front(lights: &[Light], nearest: f64, iteration: usize) -> Result<()> {
    match crate::rig::first_behind(lights, nearest) {
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

/// Returns to the best state (with a fresh acceleration history) before the refinement is
/// stopped.
const MAX_RESTARTS: usize = 2;

/// Residual growth (over the best state's) at which the light refinement goes back to it.
const DIVERGENCE: f64 = 2.0;

/// The state of lowest residual of a run with light refinement.
struct Best {
    rms: f64,
    u: Vec<f64>,
    lights: Vec<Light>,
    /// How often the iteration went back to a best state.
    restarts: usize,
}

/// What the loop does after an iteration.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Next {
    /// Go on iterating.
    Continue,
    /// The depths and lights have converged.
    Converged,
    /// The largest depth change has not reached a new minimum for [`STALL_WINDOW`] iterations.
    Stalled,
}

/// The safeguards of one run of the loop: the state of lowest residual while the lights are
/// refined, and the progress of the depth changes.
pub(crate) struct Safeguard {
    best: Option<Best>,
    /// The residual of the last local step.
    last_rms: f64,
    smallest: f64,
    since_smallest: usize,
}

impl Safeguard {
    /// The safeguards of a new run.
    pub fn new() -> Safeguard {
        Safeguard {
            best: None,
            last_rms: f64::NAN,
            smallest: f64::INFINITY,
            since_smallest: 0,
        }
    }

    /// After the local step on `u` with residual `rms` (with the current lights): tracks the
    /// state of lowest residual while the lights are refined. The joint iteration can drift
    /// along weakly determined directions of the lights; when the residual rises above
    /// [`DIVERGENCE`] times the best one, the best state is restored and true is returned; after
    /// [`MAX_RESTARTS`] such returns the refinement stops for the rest of the run. `keep` is
    /// false for a state never to be kept as the best.
    pub fn best_state(
        &mut self,
        keep: bool,
        rms: f64,
        u: &mut [f64],
        lights: &mut LightRefinement,
    ) -> Result<bool> {
        self.last_rms = rms;
        if !keep || !lights.is_active() || !rms.is_finite() {
            return Ok(false);
        }
        Ok(match &mut self.best {
            Some(b) if rms > DIVERGENCE * b.rms => {
                u.copy_from_slice(&b.u);
                lights.set_lights(b.lights.clone());
                b.restarts += 1;
                if b.restarts > MAX_RESTARTS {
                    lights.stop();
                }
                true
            }
            Some(b) if rms >= b.rms => false,
            best => {
                let restarts = best.as_ref().map_or(0, |b| b.restarts);
                *best = Some(Best {
                    rms,
                    u: try_copy(u, "the best state")?,
                    lights: lights.lights().to_vec(),
                    restarts,
                });
                false
            }
        })
    }

    /// After iteration `iteration` moved the depths by at most `depth_change` and the lights by
    /// at most `light_change`: an error when the depths diverged, else whether the run has
    /// converged (both changes within `tol`, the depth change in units of `scale`), stalled or
    /// goes on.
    pub fn verdict(
        &mut self,
        iteration: usize,
        depth_change: f64,
        light_change: f64,
        tol: f64,
        scale: f64,
    ) -> Result<Next> {
        if !depth_change.is_finite() {
            return Err(Error::Solver(format!(
                "the depths diverged at iteration {iteration}"
            )));
        }
        if depth_change <= tol * scale && light_change <= tol {
            return Ok(Next::Converged);
        }
        if depth_change < self.smallest {
            (self.smallest, self.since_smallest) = (depth_change, 0);
        } else {
            self.since_smallest += 1;
            if self.since_smallest >= STALL_WINDOW {
                return Ok(Next::Stalled);
            }
        }
        Ok(Next::Continue)
    }

    /// At the end of a run: goes back to the best state when the last one is clearly worse (by
    /// 0.1 % in RMS residual).
    pub fn finish(self, u: &mut [f64], lights: &mut LightRefinement) {
        if let Some(b) = self.best {
            if b.rms < self.last_rms * (1.0 - 1e-3) {
                u.copy_from_slice(&b.u);
                lights.set_lights(b.lights);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_two_cycle_is_damped_to_the_point_between_and_a_monotone_run_is_not() {
        // A map that swaps a and b (T(u) = a + b - u) alternates for ever; averaged it lands on
        // (a + b) / 2 in one step.
        let (a, b) = ([1.0, 5.0, -2.0], [1.0, -3.0, 4.0]);
        let map = |u: &[f64]| -> Vec<f64> { (0..3).map(|i| a[i] + b[i] - u[i]).collect() };
        // Orthographic unknowns: the depth change is the change of the unknowns.
        let flat = Geometry::orthographic(3);
        let mut osc = Oscillation::default();
        let mut u = a.to_vec();
        let mut damped_at = None;
        for iteration in 1..=8 {
            let mut next = map(&u);
            osc.damp(&u, &mut next);
            let (moved, z) = osc.record(&flat, &u, &next, 1e-6);
            assert_eq!(moved, max_change(&u, &next));
            assert_eq!(z, nearest(&flat, &next));
            if osc.damped && damped_at.is_none() {
                damped_at = Some(iteration);
            }
            u = next;
        }
        assert_eq!(damped_at, Some(OSCILLATION_FLIPS + 1));
        for i in 0..3 {
            assert!((u[i] - 0.5 * (a[i] + b[i])).abs() < 1e-12, "{u:?}");
        }
        // A slowly converging map (u -> 0.95 u) never flips: its steps are taken as they are.
        let mut osc = Oscillation::default();
        let mut u = vec![1.0, -2.0, 3.0];
        for _ in 0..50 {
            let mut next: Vec<f64> = u.iter().map(|x| 0.95 * x).collect();
            let taken = next.clone();
            osc.damp(&u, &mut next);
            assert_eq!(next, taken);
            let (_, z) = osc.record(&flat, &u, &next, 1e-9);
            assert_eq!(z, nearest(&flat, &next));
            u = next;
        }
        assert!(!osc.damped);
        // Alternations below the tolerance do not count.
        let mut osc = Oscillation::default();
        let mut u = a.to_vec();
        for _ in 0..8 {
            let next = map(&u);
            osc.record(&flat, &u, &next, 100.0);
            u = next;
        }
        assert!(!osc.damped);
    }

    /// The median of odd and even counts, and NaN for none.
    #[test]
    fn medians() {
        assert_eq!(median(&mut [3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&mut [4.0, 1.0, 3.0, 2.0]), 2.5);
        assert_eq!(median(&mut [7.0]), 7.0);
        assert!(median(&mut []).is_nan());
    }

    /// The verdict: non-finite depths are an error, both changes within the tolerance converge,
    /// and [`STALL_WINDOW`] iterations without a new smallest depth change stall the run.
    #[test]
    fn verdicts_follow_the_stop_rules() {
        let mut guard = Safeguard::new();
        let err = guard.verdict(3, f64::NAN, 0.0, 1e-3, 10.0).unwrap_err();
        assert!(matches!(&err, Error::Solver(m) if m.contains("diverged at iteration 3")));
        assert_eq!(
            guard.verdict(1, 0.01, 0.0, 1e-3, 10.0).unwrap(),
            Next::Converged
        );
        assert_eq!(
            guard.verdict(1, 0.01, 0.1, 1e-3, 10.0).unwrap(),
            Next::Continue
        );
        let mut stalled = Safeguard::new();
        let verdicts: Vec<Next> = (1..=STALL_WINDOW + 1)
            .map(|i| stalled.verdict(i, 1.0, 0.0, 1e-3, 10.0).unwrap())
            .collect();
        assert!(verdicts[..STALL_WINDOW]
            .iter()
            .all(|&v| v == Next::Continue));
        assert_eq!(verdicts[STALL_WINDOW], Next::Stalled);
    }

    /// Without an active refinement the best state is never kept nor restored.
    #[test]
    fn without_refinement_the_best_state_is_left_alone() {
        let light = Light::Directional {
            direction: [0.0, 0.0, -1.0],
            intensity: [1.0; 3],
        };
        let mut lights = LightRefinement::new(crate::options::Refine::NONE, &[light; 4]);
        let mut guard = Safeguard::new();
        let mut u = vec![1.0, 2.0];
        assert!(!guard.best_state(true, 1.0, &mut u, &mut lights).unwrap());
        assert!(!guard.best_state(true, 10.0, &mut u, &mut lights).unwrap());
        guard.finish(&mut u, &mut lights);
        assert_eq!(u, [1.0, 2.0]);
    }

    /// The light change and the RMS residual (NaN without a valid facet).
    #[test]
    fn measures() {
        assert_eq!(max_change(&[1.0, -2.0], &[0.5, 1.0]), 3.0);
        assert_eq!(max_change(&[], &[]), 0.0);
        let stats = [
            FacetStat {
                valid: true,
                sse: 8.0,
                used: 2,
            },
            FacetStat::default(),
        ];
        assert_eq!(rms_of(&stats, 1), 2.0);
        assert!(rms_of(&stats[1..], 1).is_nan());
    }
}
