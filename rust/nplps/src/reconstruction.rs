//! What a reconstruction returns: the [`Reconstruction`] with its [`Status`], [`Timings`] and
//! [`RefinementReport`]; what a progress callback sees ([`IterationStats`], [`SearchProgress`])
//! and answers ([`Control`]); and how a result is assembled from the final fits and judged
//! ([`Reconstruction::assess`]).

use std::time::Duration;

use crate::error::Result;
use crate::local::{FacetFit, LobeCheck};
use crate::memory::{try_par_vec, try_zeros, Spare};
use crate::options::Refine;
use crate::parallel::{scatter, PixelMaps};
use crate::problem::Problem;
use crate::refine::Conditioning;
use crate::reflectance::{Lobe, Reflectance};
use crate::rig::Light;
use crate::shadow::ShadowMask;

/// What one iteration did.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
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
    /// Largest relative change of a light parameter in this iteration's light step (0 without
    /// refinement): `|delta Phi_i| / Phi_i` or `|delta p_i| / D`.
    pub light_change: f64,
    /// The candidate of the working-distance search this iteration evaluates (None for the
    /// reconstruction's own iterations, which are the ones in [`Reconstruction::history`]).
    pub search: Option<SearchProgress>,
}

/// Where the working-distance search ([`crate::reconstruct_auto`]) is, reported with each of
/// the iterations that evaluate a candidate distance. With several regions, distances and
/// residuals are the means over the regions.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub struct SearchProgress {
    /// 1-based number of the candidate being evaluated.
    pub candidate: usize,
    /// How many candidates the search evaluates (the scan and the refinement's steps).
    pub candidates: usize,
    /// The candidate's distance (depth units).
    pub distance: f64,
    /// The candidate's RMS photometric residual: set on the candidate's last iteration, NaN on
    /// the others.
    pub residual: f64,
    /// The evaluated candidate of lowest residual so far, including this one once its residual
    /// is set (NaN before the first).
    pub best_distance: f64,
    /// The residual of `best_distance`.
    pub best_residual: f64,
}

/// Answer of a progress callback.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Control {
    /// Go on iterating.
    Continue,
    /// Stop now: the solver returns [`Error::Cancelled`](crate::Error::Cancelled).
    Cancel,
}

/// Wall-clock time spent in each part.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
#[non_exhaustive]
pub struct Timings {
    /// Assembly, analysis and factorization of the global system.
    pub factorization: Duration,
    /// All local steps.
    pub local: Duration,
    /// All global solves (right sides, back-substitution, gauge).
    pub solve: Duration,
    /// Building the coarse-to-fine pyramid (its levels' own work is counted above).
    pub pyramid: Duration,
    /// Light refinement steps.
    pub lights: Duration,
    /// The cast-shadow marches (with [`Options::shadows`](crate::Options::shadows)).
    pub shadows: Duration,
    /// Gathering the indirect light (with
    /// [`Options::interreflections`](crate::Options::interreflections)): binning, the light
    /// exchange and its passes.
    pub indirect: Duration,
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
        self.lights += other.lights;
        self.shadows += other.shadows;
        self.indirect += other.indirect;
    }
}

/// How a reconstruction ended; the result's `status_reason` gives the numbers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum Status {
    /// The largest depth change of the last iteration was at most `tol` times the lateral size.
    Converged,
    /// The iteration stopped without converging: at the iteration limit, or because the depth
    /// change found no new minimum for 50 iterations. The surface may be usable;
    /// the history says how far it was from converging.
    Stalled,
    /// The depth changes grew (the last at least 10 times the smallest one of
    /// the final level): the surface is moving away.
    Diverged,
    /// More than half of the masked pixels could not be fitted (fewer than 3
    /// usable observations): they kept the starting shape, which says nothing about the object.
    Degenerate,
}

impl Status {
    /// The status as a lowercase word ("converged", "stalled", "diverged", "degenerate").
    pub fn name(&self) -> &'static str {
        match self {
            Status::Converged => "converged",
            Status::Stalled => "stalled",
            Status::Diverged => "diverged",
            Status::Degenerate => "degenerate",
        }
    }
}

/// An iteration stops as [`Status::Stalled`] when its largest depth change has not reached a new
/// minimum for this many iterations (so `tol = 0` with a huge iteration count cannot run forever).
pub const STALL_WINDOW: usize = 50;

/// The depth changes of the final level have grown by this factor over their minimum:
/// [`Status::Diverged`].
pub const DIVERGENCE_GROWTH: f64 = 10.0;

/// Share of unfitted masked pixels above which a result is [`Status::Degenerate`].
pub const DEGENERATE_SHARE: f64 = 0.5;

/// The result of a reconstruction. Per-pixel arrays are (H, W) row-major, per-vertex arrays
/// (H+1, W+1); NaN (or 0 for counts) outside the mask.
#[derive(Debug, Clone)]
#[non_exhaustive]
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
    /// Fitted albedo, `channels` values per pixel (row-major, the channels of a pixel
    /// together: `albedo[p * channels + c]`; one value a pixel for grey images, not three);
    /// NaN where a facet could not be fitted.
    pub albedo: Vec<f64>,
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
    /// Whether the tolerance was reached (exactly when `status` is [`Status::Converged`]).
    pub converged: bool,
    /// How the run ended (see [`Status`]).
    pub status: Status,
    /// One sentence saying why, with the numbers.
    pub status_reason: String,
    /// Number of negative observations inside the mask (treated as unlit).
    pub negative_observations: usize,
    /// Where the time went.
    pub timings: Timings,
    /// The lights of the final fit: the rig's, or the refined ones (see [`Options::refine`](crate::Options::refine)).
    pub lights: Vec<Light>,
    /// What the light refinement did (None without refinement).
    pub refinement: Option<RefinementReport>,
    /// The shared lobe of the glossy model (None under the Lambertian model).
    pub lobe: Option<Lobe>,
    /// With the glossy model and its lobe to estimate: the lobe found when it was too rough to
    /// be a highlight (see [`MATTE_ROUGHNESS`](crate::MATTE_ROUGHNESS)); the result
    /// is then the Lambertian model's (`lobe` None). None otherwise.
    pub matte_lobe: Option<Lobe>,
    /// With the glossy model and its lobe to estimate: the last held-out comparison of the
    /// glossy and Lambertian models (see [`LobeCheck`]); the glossy model was dropped (and
    /// `matte_lobe` set) where it did not predict better. None otherwise.
    pub lobe_check: Option<LobeCheck>,
    /// Specular albedo of each pixel under the glossy model (NaN where a facet could not be
    /// fitted); empty under the Lambertian model.
    pub specular: Vec<f64>,
    /// The cast shadows of the final mesh's level, as the last local steps used them (with
    /// [`Options::shadows`](crate::Options::shadows); None without).
    pub shadows: Option<ShadowMask>,
    /// How far to trust the result without ground truth: the normals' predicted uncertainty,
    /// the leave-one-light-out re-rendering error and per-light residuals, from the Lambertian
    /// fit at the final mesh (see [`Trust`](crate::Trust)); None for the parallel baseline.
    pub trust: Option<crate::local::Trust>,
}

/// What the self-calibration of the lights did.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct RefinementReport {
    /// What was refined.
    pub refine: Refine,
    /// Whether the refinement was dropped because it did not lower the photometric residual of
    /// a run without it (on the first pyramid level); the rig's lights were then kept.
    pub fell_back: bool,
    /// Whether the refinement was stopped early because the photometric residual rose (the
    /// joint iteration drifted along weakly determined light parameters): the state of lowest
    /// residual was restored and the lights kept from then on.
    pub stopped: bool,
    /// RMS residual, on the first level, without refinement.
    pub residual_without: f64,
    /// RMS residual, on the first level, with refinement.
    pub residual_with: f64,
    /// How well the images determine the refined parameters at the final mesh.
    pub conditioning: Option<Conditioning>,
}

/// The per-pixel results of the final local step (NaN, or 0 for counts, outside the mask).
pub(crate) struct FitOutputs {
    normals: Vec<[f64; 3]>,
    /// `channels` values a pixel.
    albedo: Vec<f64>,
    residual: Vec<f64>,
    lights_used: Vec<u32>,
    /// Empty unless `glossy`.
    specular: Vec<f64>,
}

impl FitOutputs {
    /// Empty outputs for `problem`'s image size (with a specular albedo map when `glossy`),
    /// filled in parallel (about 40 bytes a pixel: 0.5 GB at 12 MP).
    pub(crate) fn new(problem: &Problem<'_>, glossy: bool) -> Result<FitOutputs> {
        let n = problem.grid.height * problem.grid.width;
        Ok(FitOutputs {
            specular: try_par_vec(
                if glossy { n } else { 0 },
                f64::NAN,
                "the specular albedo map",
            )?,
            normals: try_par_vec(n, [f64::NAN; 3], "the normal map")?,
            albedo: try_par_vec(n * problem.obs.channels, f64::NAN, "the albedo map")?,
            residual: try_par_vec(n, f64::NAN, "the residual map")?,
            lights_used: try_par_vec(n, 0, "the map of lights used")?,
        })
    }

    /// Outputs of the Lambertian model for `problem`'s image size, allocated but not written:
    /// the normal, albedo and residual maps on the memory of `spare`'s buffers where they are
    /// large enough (pages already touched, see [`triples_on`] and [`values_on`]), the others
    /// zero pages until touched; for a final pass that writes every pixel, masked or not
    /// ([`FinalView::write`]), so that each is written once.
    ///
    /// [`triples_on`]: crate::memory::triples_on
    /// [`values_on`]: crate::memory::values_on
    pub(crate) fn unwritten(problem: &Problem<'_>, spare: Spare) -> Result<FitOutputs> {
        use crate::memory::{triples_on, values_on};
        let n = problem.grid.height * problem.grid.width;
        let Spare { quads, mut values } = spare;
        Ok(FitOutputs {
            specular: Vec::new(),
            normals: triples_on(quads, n, "the normal map")?,
            albedo: values_on(&mut values, n * problem.obs.channels, "the albedo map")?,
            residual: values_on(&mut values, n, "the residual map")?,
            lights_used: try_zeros(n, "the map of lights used")?,
        })
    }

    /// All the maps, for writing.
    fn view(&mut self, channels: usize) -> OutputView<'_> {
        OutputView {
            channels,
            normals: &mut self.normals,
            albedo: &mut self.albedo,
            residual: &mut self.residual,
            lights_used: &mut self.lights_used,
            specular: &mut self.specular,
        }
    }

    /// Writes the fits of facets `first..first + fits.len()` onto their pixels, pieces of the
    /// facets in parallel (each piece writes its own pixels: a grid's facets are in increasing
    /// pixel order, so the pieces' pixel ranges do not overlap).
    pub(crate) fn scatter(&mut self, problem: &Problem<'_>, first: usize, fits: &[FacetFit]) {
        let facets = &problem.grid.facets[first..first + fits.len()];
        let view = self.view(problem.obs.channels);
        scatter(view, 0, facets, fits, SCATTER_PIECE, &|view, p, fit| {
            view.put(p, fit)
        });
    }
}

impl OutputView<'_> {
    /// Writes `fit` onto pixel `p` (counted from the view's first pixel).
    #[inline]
    fn put(&mut self, p: usize, fit: &FacetFit) {
        let channels = self.channels;
        self.normals[p] = fit.normal;
        self.albedo[p * channels..(p + 1) * channels].copy_from_slice(&fit.albedo[..channels]);
        self.residual[p] = fit.rms(channels);
        self.lights_used[p] = fit.used;
        if let Some(s) = self.specular.get_mut(p) {
            *s = fit.specular;
        }
    }

    /// Writes pixel `p` as outside the mask: NaN, no lights used (the values of
    /// [`FitOutputs::new`]).
    #[inline]
    fn put_outside(&mut self, p: usize) {
        let channels = self.channels;
        self.normals[p] = [f64::NAN; 3];
        self.albedo[p * channels..(p + 1) * channels].fill(f64::NAN);
        self.residual[p] = f64::NAN;
        self.lights_used[p] = 0;
        if let Some(s) = self.specular.get_mut(p) {
            *s = f64::NAN;
        }
    }
}

/// A range of pixels of the final pass's maps: the outputs (None: the trust maps alone) and
/// the trust maps' `[normal sigma, held-out]`, from pixel `base` on.
pub(crate) struct FinalView<'a> {
    base: usize,
    outputs: Option<OutputView<'a>>,
    trust: (&'a mut [f32], &'a mut [f32]),
}

impl<'a> FinalView<'a> {
    /// The maps of every pixel, cut at the first pixel of every chunk of facets but the first
    /// (`chunks` of `chunk` facets each, the last one shorter): one view per chunk, whose
    /// pixels no other chunk's facets lie on.
    pub(crate) fn split(
        grid: &crate::grid::Grid,
        outputs: Option<&'a mut FitOutputs>,
        channels: usize,
        trust: (&'a mut [f32], &'a mut [f32]),
        chunks: usize,
        chunk: usize,
    ) -> Vec<FinalView<'a>> {
        let mut rest = FinalView {
            base: 0,
            outputs: outputs.map(|o| o.view(channels)),
            trust,
        };
        let mut views = Vec::with_capacity(chunks);
        for c in 1..chunks {
            let at = grid.facets[c * chunk] as usize;
            let m = at - rest.base;
            let (left, right) = rest.split_at(m);
            views.push(left);
            rest = right;
        }
        views.push(rest);
        views
    }

    /// Writes the fits (empty: the trust maps alone) and trust values of the facets at
    /// `pixels` (increasing, within the view) onto their pixels, and every other pixel of the
    /// view as outside the mask (NaN, no lights used): each pixel of the view once.
    pub(crate) fn write(mut self, pixels: &[u32], fits: &[FacetFit], trust: &[[f32; 2]]) {
        debug_assert!(fits.is_empty() || fits.len() == trust.len());
        let base = self.base;
        let end = self.trust.0.len();
        let mut next = 0;
        for (i, (&pixel, value)) in pixels.iter().zip(trust).enumerate() {
            let p = pixel as usize - base;
            self.outside(next..p);
            self.trust.0[p] = value[0];
            self.trust.1[p] = value[1];
            if let (Some(outputs), Some(fit)) = (self.outputs.as_mut(), fits.get(i)) {
                outputs.put(p, fit);
            }
            next = p + 1;
        }
        self.outside(next..end);
    }

    /// Writes the view's pixels `range` as outside the mask.
    fn outside(&mut self, range: std::ops::Range<usize>) {
        self.trust.0[range.clone()].fill(f32::NAN);
        self.trust.1[range.clone()].fill(f32::NAN);
        if let Some(outputs) = self.outputs.as_mut() {
            range.for_each(|p| outputs.put_outside(p));
        }
    }
}

impl PixelMaps for FinalView<'_> {
    fn split_at(self, m: usize) -> (Self, Self) {
        let (outputs0, outputs1) = match self.outputs.map(|o| o.split_at(m)) {
            Some((a, b)) => (Some(a), Some(b)),
            None => (None, None),
        };
        let (trust0, trust1) = self.trust.split_at(m);
        let view = |base, outputs, trust| FinalView {
            base,
            outputs,
            trust,
        };
        (
            view(self.base, outputs0, trust0),
            view(self.base + m, outputs1, trust1),
        )
    }
}

/// Facets a piece of [`FitOutputs::scatter`] writes on one thread.
const SCATTER_PIECE: usize = 1 << 14;

/// The maps of [`FitOutputs`] from some pixel on (the specular map: empty, or as the others).
struct OutputView<'a> {
    channels: usize,
    normals: &'a mut [[f64; 3]],
    albedo: &'a mut [f64],
    residual: &'a mut [f64],
    lights_used: &'a mut [u32],
    specular: &'a mut [f64],
}

impl PixelMaps for OutputView<'_> {
    fn split_at(self, m: usize) -> (Self, Self) {
        let channels = self.channels;
        let (n0, n1) = self.normals.split_at_mut(m);
        let (a0, a1) = self.albedo.split_at_mut(m * channels);
        let (r0, r1) = self.residual.split_at_mut(m);
        let (u0, u1) = self.lights_used.split_at_mut(m);
        let (s0, s1) = self.specular.split_at_mut(m.min(self.specular.len()));
        let view = |normals, albedo, residual, lights_used, specular| OutputView {
            channels,
            normals,
            albedo,
            residual,
            lights_used,
            specular,
        };
        (view(n0, a0, r0, u0, s0), view(n1, a1, r1, u1, s1))
    }
}

impl Reconstruction {
    /// The reflectance model the result was fitted with: the glossy model with its lobe (given
    /// or estimated), or the Lambertian model (asked for, or the glossy model dropped for a lobe
    /// too rough to be a highlight). Options with it make a later run on the same images (such
    /// as [`check_distance`](crate::check_distance)) fit under the same model without
    /// estimating the lobe again.
    pub fn reflectance(&self) -> Reflectance {
        match self.lobe {
            Some(lobe) => Reflectance::Glossy(Some(lobe)),
            None => Reflectance::Lambertian,
        }
    }

    /// Whether light positions were refined and the refinement was kept because it lowered the
    /// photometric residual: then growing depth changes follow the moving lights (the surface
    /// is still settling at the iteration limit), they are not a divergence.
    fn refinement_helped(&self) -> bool {
        self.refinement.as_ref().is_some_and(|r| {
            r.refine.position && !r.fell_back && r.residual_with < r.residual_without
        })
    }

    /// Sets `status`, `status_reason` and `converged` from the outcome: `tol_depth` is the
    /// depth-change tolerance in depth units (`tol` times the lateral size; infinite for a
    /// non-iterative result), `stalled` whether the iteration stopped for lack of progress,
    /// `settled` the residual share by which it stopped because the glossy fits settled (see
    /// [`GLOSSY_RESIDUAL_FACTOR`](crate::solver::GLOSSY_RESIDUAL_FACTOR)), if it did.
    pub(crate) fn assess(&mut self, tol_depth: f64, stalled: bool, settled: Option<f64>) {
        use crate::error::g6;
        let masked = self.regions.iter().filter(|&&r| r >= 0).count();
        let unfitted = self
            .regions
            .iter()
            .zip(&self.lights_used)
            .filter(|(&r, &n)| r >= 0 && n < 3)
            .count();
        let level = self.history.last().map_or(0, |s| s.level);
        // The run whose surface is returned, on the last level: with position refinement the
        // first level runs twice (without, then with refinement, each from iteration 1); the
        // refined run's changes must not be judged against the converged plain run's, and when
        // the refinement fell back the plain run is the one returned.
        let starts: Vec<usize> = (0..self.history.len())
            .filter(|&i| self.history[i].level == level && self.history[i].iteration == 1)
            .collect();
        let fell_back = self.refinement.as_ref().is_some_and(|r| r.fell_back);
        let (start, end) = match starts.as_slice() {
            [.., plain, refined] if fell_back => (*plain, *refined),
            [.., last] => (*last, self.history.len()),
            [] => (0, self.history.len()),
        };
        let changes: Vec<f64> = self.history[start..end]
            .iter()
            .filter(|s| s.level == level)
            .map(|s| s.depth_change)
            .collect();
        let last = changes.last().copied().unwrap_or(f64::NAN);
        let smallest = changes.iter().copied().fold(f64::INFINITY, f64::min);
        let iterations = changes.len();
        let (status, reason) = if masked > 0 && unfitted as f64 > DEGENERATE_SHARE * masked as f64 {
            (
                Status::Degenerate,
                format!(
                    "{unfitted} of {masked} masked pixels ({:.0} %) had fewer than 3 usable \
                     observations and kept the starting shape; check dark, saturation, valid, \
                     the mask and the lights",
                    100.0 * unfitted as f64 / masked as f64
                ),
            )
        } else if self.converged {
            if let (Some(share), true) = (settled, last > tol_depth) {
                (
                    Status::Converged,
                    format!(
                        "the RMS image residual changed by at most {} of it in the last local \
                         step: the glossy fits have settled (the largest depth change of \
                         iteration {iterations}, {}, is within their precision, above the depth \
                         tolerance {})",
                        g6(share),
                        g6(last),
                        g6(tol_depth)
                    ),
                )
            } else if tol_depth.is_finite() && last > tol_depth && iterations >= 2 {
                // Stopped by the projected rule (crate::solver::projected_converged).
                (
                    Status::Converged,
                    format!(
                        "the depth changes of iterations {} and {iterations} ({} and {}) \
                         contract so fast that the changes still to come are projected \
                         within the tolerance ({})",
                        iterations - 1,
                        g6(changes[iterations - 2]),
                        g6(last),
                        g6(tol_depth)
                    ),
                )
            } else if tol_depth.is_finite() {
                (
                    Status::Converged,
                    format!(
                        "the largest depth change of iteration {iterations} ({}) is within the \
                         tolerance ({})",
                        g6(last),
                        g6(tol_depth)
                    ),
                )
            } else {
                (
                    Status::Converged,
                    "a direct (non-iterative) solution".to_string(),
                )
            }
        } else if iterations >= 2
            && last > DIVERGENCE_GROWTH * smallest
            && last > tol_depth
            && !self.refinement_helped()
        {
            (
                Status::Diverged,
                format!(
                    "the depth changes grew from {} to {} at iteration {iterations}: the surface \
                     is moving away (check the rig, the starting depth and the thresholds)",
                    g6(smallest),
                    g6(last)
                ),
            )
        } else if stalled {
            (
                Status::Stalled,
                format!(
                    "no progress in the last {STALL_WINDOW} of {iterations} iterations: the \
                     largest depth change stays at {} (smallest {}), above the tolerance ({})",
                    g6(last),
                    g6(smallest),
                    g6(tol_depth)
                ),
            )
        } else {
            (
                Status::Stalled,
                format!(
                    "stopped at the iteration limit ({iterations}) with a largest depth change \
                     of {}, above the tolerance ({}); more iterations may help",
                    g6(last),
                    g6(tol_depth)
                ),
            )
        };
        self.status = status;
        self.status_reason = reason;
        self.converged = status == Status::Converged;
    }
}

/// Assembles the result: the per-pixel `outputs` and the depths of the unknowns `z` scattered
/// onto the vertex grid. `depths`, when the caller has them, are those depths (the camera's
/// `depth` of each unknown, as computed here otherwise): they are scattered instead, or, when
/// every vertex is an unknown (the unknowns are numbered in vertex order), are the depth map
/// itself.
pub(crate) fn assemble(
    problem: &Problem<'_>,
    z: &[f64],
    depths: Option<Vec<f64>>,
    outputs: FitOutputs,
    history: Vec<IterationStats>,
    converged: bool,
    timings: Timings,
) -> Result<Reconstruction> {
    let grid = &problem.grid;
    let depth = match depths {
        Some(d) if grid.active.len() == grid.vertex_unknown.len() && d.len() == z.len() => d,
        Some(d) => grid.scatter_vertices_with(&d, |d| d)?,
        None => grid.scatter_vertices_with(z, |u| problem.geometry.depth(u))?,
    };
    Ok(Reconstruction {
        height: grid.height,
        width: grid.width,
        channels: problem.obs.channels,
        depth,
        normals: outputs.normals,
        albedo: outputs.albedo,
        residual: outputs.residual,
        lights_used: outputs.lights_used,
        regions: grid.pixel_regions()?,
        gauge: problem
            .gauge
            .iter()
            .map(|&g| problem.geometry.depth(g))
            .collect(),
        history,
        converged,
        status: if converged {
            Status::Converged
        } else {
            Status::Stalled
        },
        status_reason: String::new(),
        negative_observations: problem.negative_observations,
        timings,
        lights: problem.rig.lights.clone(),
        refinement: None,
        lobe: None,
        matte_lobe: None,
        lobe_check: None,
        specular: outputs.specular,
        shadows: None,
        trust: None,
    })
}
