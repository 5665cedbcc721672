//! The options of a reconstruction ([`Options`], with the light refinement's [`Refine`]), their
//! checks, and the estimate of a reconstruction's peak memory under them ([`check_memory`]).
//!
//! The per-pixel constants of [`reconstruction`] are peak resident memory measured above the
//! input image stack (`VmHWM`, 512² to 2048², 4 to 27 lights, orthographic and pinhole, grey and
//! RGB): about 216 bytes per pixel with the multigrid global step (it does not grow with the
//! number of lights: the stack is read in place), +170 with light refinement, and about 1 kB per
//! pixel with the direct sparse Cholesky, whose fill grows slowly with the size. The estimate
//! rounds them up; it is a guard against aborts, not an accountant.

use crate::error::{Error, Result};
use crate::global::GlobalSolver;
use crate::local::{FitSettings, Robust, Weighting};
use crate::memory::check;
use crate::reflectance::Reflectance;
use crate::shadow::Shadows;

/// Options of the iteration.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
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
    /// The reflectance model of the per-facet fits (Lambertian by default).
    pub reflectance: Reflectance,
    /// Cast shadows predicted from the current mesh (see [`crate::shadow`]): the observations a
    /// facet's own surface hides from a light are left out of its fits. The masks are computed
    /// at a few iterations of each pyramid level (`solver::SHADOWS_AT`); by default
    /// ([`Shadows::Auto`]) only where the coarsest level finds the object shadowing itself.
    pub shadows: Shadows,
    /// Interreflections (see [`crate::indirect`]): after the full-resolution level converges,
    /// the indirect irradiance `V` of every facet under every light is gathered from the
    /// observed images over the current mesh (on a grid of at most
    /// [`FIELD_SIDE`](crate::indirect::FIELD_SIDE)² facets), added to the lights' rows of the
    /// local fits (`I = b . (s + V)`), and the iteration runs again, up to
    /// `INDIRECT_ROUNDS` rounds. Under the glossy model the modelled diffuse part of the images
    /// emits and the glossy fits see the observations less the indirect light they receive as a
    /// Lambertian surface (see `local::glossy_indirect`), the rounds at full resolution. Without
    /// light refinement (refused).
    pub interreflections: bool,
    /// Worker threads (0: rayon's default, all cores).
    pub threads: usize,
    /// Run faer's sparse factorization and solves on the worker threads too. Off by default:
    /// on 512 x 512 images with 2 cores the parallel paths measured 20-30% slower than the
    /// sequential ones (see faer issue 211), while the local step uses every thread.
    pub parallel_sparse: bool,
    /// How the global step's linear system is solved.
    pub solver: GlobalSolver,
    /// Coarse-to-fine pyramid levels (1: the full resolution only; 0: automatic, see
    /// the images are halved while the longer side keeps at least 128 pixels).
    pub levels: usize,
    /// Self-calibration of the lights (off by default).
    pub refine: Refine,
    /// Memory limit in bytes: a reconstruction whose estimated peak memory exceeds it is refused
    /// with [`Error::Memory`] before the large allocations. `None`: a share of the memory the
    /// machine has available (see [`crate::check_memory`]); `Some(f64::INFINITY)`: no limit.
    pub max_memory: Option<f64>,
}

impl Options {
    /// Checks the options: `tol >= 0`, `dark` finite, `saturation > dark`.
    pub fn validate(&self) -> Result<()> {
        if self.tol.is_nan() || self.tol < 0.0 {
            return Err(Error::OutOfRange {
                name: "tol",
                value: self.tol,
                message: format!("tol must be >= 0, got {}", self.tol),
            });
        }
        self.refine.validate()?;
        if self.interreflections && self.refine.is_active() && self.reflectance.is_glossy() {
            return Err(Error::Unusable(
                "interreflections with refine_lights are not supported under the glossy model \
                 yet (its light step does not model the indirect light)"
                    .to_string(),
            ));
        }
        if let Reflectance::Glossy(Some(lobe)) = self.reflectance {
            lobe.validate()?;
        }
        if let Some(m) = self.max_memory {
            if m.is_nan() || m <= 0.0 {
                return Err(Error::OutOfRange {
                    name: "max_memory",
                    value: m,
                    message: format!(
                        "max_memory must be a positive number of bytes, got {}",
                        crate::error::g6(m)
                    ),
                });
            }
        }
        check_thresholds(self.dark, self.saturation)
    }

    /// The per-facet fit settings of these options: with the glossy model, its lobe when it is
    /// given (an estimated lobe is the solver's to set).
    pub(crate) fn fit_settings(&self, fast_residual: bool) -> FitSettings {
        FitSettings {
            dark: self.dark,
            saturation: self.saturation,
            weighting: self.weighting,
            robust: self.robust,
            fast_residual,
            lobe: match self.reflectance {
                Reflectance::Glossy(lobe) => lobe,
                Reflectance::Lambertian => None,
            },
            continuation: true,
            step_tolerance: 0.0,
            noise: 0.0,
            precise: false,
        }
    }
}

with_fields!(Options {
    with_iterations: iterations: usize,
    with_tol: tol: f64,
    with_dark: dark: f64,
    with_saturation: saturation: f64,
    with_weighting: weighting: Weighting,
    with_robust: robust: Robust,
    with_reflectance: reflectance: Reflectance,
    with_shadows: shadows: Shadows,
    with_interreflections: interreflections: bool,
    with_threads: threads: usize,
    with_parallel_sparse: parallel_sparse: bool,
    with_solver: solver: GlobalSolver,
    with_levels: levels: usize,
    with_refine: refine: Refine,
    with_max_memory: max_memory: Option<f64>,
});

/// The shadow threshold must be a finite number below the saturation threshold.
pub(crate) fn check_thresholds(dark: f64, saturation: f64) -> Result<()> {
    if !dark.is_finite() {
        return Err(Error::OutOfRange {
            name: "dark",
            value: dark,
            message: format!("dark (the shadow threshold) must be a finite number, got {dark}"),
        });
    }
    if saturation.is_nan() || saturation <= dark {
        return Err(Error::OutOfRange {
            name: "saturation",
            value: saturation,
            message: format!("saturation must be above dark (= {dark}), got {saturation}"),
        });
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
            reflectance: Reflectance::Lambertian,
            shadows: Shadows::Auto,
            interreflections: false,
            threads: 0,
            parallel_sparse: false,
            solver: GlobalSolver::Auto,
            levels: 0,
            refine: Refine::NONE,
            max_memory: None,
        }
    }
}

/// Default weight of the prior that holds light positions to the rig's (see the module docs).
pub const DEFAULT_PRIOR_WEIGHT: f64 = 1e3;

/// Which light parameters the reconstruction refines.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub struct Refine {
    /// Refine each light's intensity (a common factor per light, all channels).
    pub intensity: bool,
    /// Refine each point light's position.
    pub position: bool,
    /// Weight `w` of the prior toward the rig's positions.
    pub prior_weight: f64,
    /// Keep the common scale of the light positions (set when the distance is estimated).
    pub fix_scale: bool,
}

impl Default for Refine {
    fn default() -> Self {
        Refine::NONE
    }
}

impl Refine {
    /// No refinement.
    pub const NONE: Refine = Refine {
        intensity: false,
        position: false,
        prior_weight: DEFAULT_PRIOR_WEIGHT,
        fix_scale: false,
    };

    /// The same settings with nothing refined (the prior weight and scale rule are kept).
    pub fn off(self) -> Refine {
        Refine {
            intensity: false,
            position: false,
            ..self
        }
    }

    /// Whether anything is refined.
    pub fn is_active(&self) -> bool {
        self.intensity || self.position
    }

    /// Checks the prior weight.
    pub fn validate(&self) -> Result<()> {
        if !(self.prior_weight.is_finite() && self.prior_weight >= 0.0) {
            return Err(Error::OutOfRange {
                name: "light_prior_weight",
                value: self.prior_weight,
                message: format!(
                    "light_prior_weight must be a finite number >= 0, got {}",
                    self.prior_weight
                ),
            });
        }
        Ok(())
    }

    /// Name of the mode: "none", "intensity", "position" or "both".
    pub fn name(&self) -> &'static str {
        match (self.intensity, self.position) {
            (false, false) => "none",
            (true, false) => "intensity",
            (false, true) => "position",
            (true, true) => "both",
        }
    }
}

with_fields!(Refine {
    with_intensity: intensity: bool,
    with_position: position: bool,
    with_prior_weight: prior_weight: f64,
    with_fix_scale: fix_scale: bool,
});

/// Fixed overhead of a reconstruction (thread pools, small systems, the coarsest level).
const FIXED: f64 = 64e6;
/// Bytes per frame pixel: the larger of the frame-sized buffers of the iterations (the
/// multigrid's padded vertex grid: four f64 conjugate-gradient vectors, the coarse levels'
/// stencils and work vectors, the vertex flags, about 40 since the coarse levels' interior nodes
/// share one stencil (2.5 bytes a pixel for the stencils, 13 before); the vertex numbers, 4) and
/// of the end (the result's maps: normals 24, albedo 8, residual 8, depth 8, trust maps 8, lights
/// used and regions 8, vertex numbers 4: 68), with 15 % to spare (see [`PER_FACET`]).
const PER_PIXEL: f64 = 78.0;
/// Extra bytes per frame pixel and colour channel beyond the first.
const PER_CHANNEL: f64 = 16.0;
/// Bytes per masked facet beyond [`PER_PIXEL`]: the mesh's facet, unknown and region numbers
/// (12), the current depths (8) and, through the iterations, the solver's next depths (8): 28,
/// 30 with the spare of the measurement below. The solver's targets (32) are held only while the multigrid's
/// work vectors are given back (the local step, whose statistics are summed a chunk at a time)
/// and the work vectors only while the targets are (the global step reads them into its right
/// side first); the shadow march's transients (about 22 a pixel) only while neither is; a
/// constant starting depth is not stored. At a full mask the iterations' peak (the frame-sized
/// buffers of [`PER_PIXEL`] then hold the targets and the multigrid's vectors) and the end's
/// (the result's maps) were about equal; since the coarse stencils shrank the end sets the peak.
/// Measured with 16 grey lights, a full mask and the default options at 12 MP (issue 23,
/// given-back buffers forced by a `max_memory` below [`keeps_buffers`]'s share; `NPLPS_MEMTRACE`
/// over the stack and the interpreter): 91 bytes a pixel beyond the stack at the end, 76 through
/// the iterations (92-94 at the iterations' peak before the shared stencils, 128-131 before that,
/// 204 and 271 before that), which this and [`PER_PIXEL`] bound with 19 % to spare (108 a pixel;
/// kept at the 15 % of the old measurement). At 1 MP: 100 MB beyond the stack, against an
/// estimate of 177 MB. Kept buffers (the default where they fit): 109 bytes a pixel through the
/// iterations at 12 MP, 91 at the end.
const PER_FACET: f64 = 30.0;
/// Extra bytes per facet with light refinement (light-step sensitivities and snapshots).
const PER_FACET_REFINE: f64 = 192.0;
/// Extra bytes per facet with the direct sparse Cholesky at one megapixel (its fill grows
/// like `n log n`: see [`reconstruction`]).
const PER_FACET_DIRECT: f64 = 900.0;

/// Extra bytes per facet under the glossy model: the solver's warm glossy normals (three `f32`),
/// the converged fits a step may keep ([`crate::local::KeptFits`], 32 bytes since stop 50's
/// latitude, 28 before) and the result's specular albedo. Measured at stop 48: the 1 MP glossy
/// bumps (lobe given, full mask) peaked at 563 MB against the Lambertian run's 521 MB, 40 bytes
/// a facet; 48 left 20 % to spare, 52 with the records' 4 bytes more (stop 50: 583 MB against
/// main's 578 MB).
const PER_FACET_GLOSSY: f64 = 52.0;

/// Extra bytes per facet of the interreflection rounds under the glossy model: each facet's
/// glossy state of the round's start (normal, diffuse albedo, specular albedo: seven `f32`).
const PER_FACET_GLOSSY_ROUNDS: f64 = 28.0;

/// Estimated peak memory in bytes of reconstructing an `height` x `width` frame with `facets`
/// masked pixels, `channels` colour channels and `lights` lights, beyond the input images
/// themselves.
///
/// `bytes = 64 MB + (78 + 16 (C - 1) + 8 k C [glossy rounds]) H W
///          + (30 + 192 [refine] + 900 f(n) [direct] + 52 [glossy] + 28 [glossy rounds]) n`,
/// with `f(n) = 1 + 0.15 log2(n / 2^20)` (at least 1) for the fill of the direct factor. "Glossy
/// rounds" are interreflections under the glossy model: a round holds two more `f32` stacks of
/// the images' size (the emitters, the observations less the received light) and the fits'
/// states. The arithmetic is in floating point, so absurd sizes give huge estimates instead of
/// overflowing.
pub fn reconstruction(
    height: usize,
    width: usize,
    facets: usize,
    channels: usize,
    lights: usize,
    options: &Options,
) -> f64 {
    let frame = height as f64 * width as f64;
    let n = facets as f64;
    let mut per_facet = PER_FACET;
    if options.refine.intensity || options.refine.position {
        per_facet += PER_FACET_REFINE;
    }
    if options.solver == GlobalSolver::Direct {
        let growth = 1.0 + 0.15 * (n / (1u64 << 20) as f64).log2().max(0.0);
        per_facet += PER_FACET_DIRECT * growth;
    }
    let channels = channels.max(1) as f64;
    let mut per_pixel = PER_PIXEL + PER_CHANNEL * (channels - 1.0);
    if options.reflectance.is_glossy() {
        per_facet += PER_FACET_GLOSSY;
    }
    if options.interreflections && options.reflectance.is_glossy() {
        per_pixel += 2.0 * 4.0 * lights as f64 * channels;
        per_facet += PER_FACET_GLOSSY_ROUNDS;
    }
    FIXED + per_pixel * frame + per_facet * n
}

/// Extra bytes per facet of a run that keeps its iteration buffers from one step to the next
/// (the multigrid's work vectors, about 37 a vertex, through the local step; the targets, 32,
/// through the global step): the larger, with 15 % to spare.
const PER_FACET_KEPT: f64 = 43.0;

/// Share of the memory limit within which a run keeps its iteration buffers (see
/// [`keeps_buffers`]): comfortably within it, the rest left to what follows the solve (the
/// export holds the result's maps).
const KEEP_SHARE: f64 = 0.5;

/// Whether reconstructing `problem` with `options` keeps the solver's iteration buffers from
/// one step to the next ([`crate::solver`]'s `keep_buffers`): when its estimate
/// ([`reconstruction`]) plus [`PER_FACET_KEPT`] a facet is within [`KEEP_SHARE`] of the memory
/// limit (see [`crate::memory::limit`]) and of the memory available now (see
/// [`crate::memory::available`], which also sees an address-space cap; neither known: kept).
/// Otherwise they are given back between the
/// steps, which lowers the peak for the cost of touching fresh zero pages each iteration. The
/// results are the same bits either way.
pub(crate) fn keeps_buffers(problem: &crate::Problem<'_>, options: &Options) -> bool {
    let (h, w) = problem.shape();
    let facets = problem.grid.n_facets();
    let needed = reconstruction(h, w, facets, problem.obs.channels, problem.obs.k, options)
        + PER_FACET_KEPT * facets as f64;
    let available = crate::memory::available().map(|a| a as f64);
    let room = match (crate::memory::limit(options.max_memory), available) {
        (Some(l), Some(a)) => Some(l.min(a)),
        (l, a) => l.or(a),
    };
    room.is_none_or(|room| needed <= KEEP_SHARE * room)
}

/// Checks the memory of a reconstruction (see [`reconstruction`]) against `options.max_memory`.
pub fn check_reconstruction(
    height: usize,
    width: usize,
    facets: usize,
    channels: usize,
    lights: usize,
    options: &Options,
) -> Result<()> {
    let needed = reconstruction(height, width, facets, channels, lights, options);
    check(
        || {
            format!(
                "reconstructing {width} x {height} pixels ({facets} in the mask) with {lights} lights"
            )
        },
        needed,
        options.max_memory,
    )
}

/// Refuses with [`Error::Memory`] when reconstructing `shape` = (k, H, W, C) images under
/// `mask` (H x W, `true` = reconstruct; `None` = every pixel) with `options` would need more
/// memory than `options.max_memory` allows. Call it before [`crate::Problem::new`] to refuse
/// before the problem's own allocations.
pub fn check_memory(shape: [usize; 4], mask: Option<&[bool]>, options: &Options) -> Result<()> {
    let [k, h, w, c] = shape;
    let facets = match mask {
        Some(m) => m.iter().filter(|&&inside| inside).count(),
        None => h.saturating_mul(w),
    };
    check_reconstruction(h, w, facets, c, k, options)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_estimate_grows_with_the_pixels_and_the_options() {
        let plain = Options::default();
        let small = reconstruction(512, 512, 512 * 512, 1, 16, &plain);
        let large = reconstruction(2048, 2048, 2048 * 2048, 1, 16, &plain);
        // Linear in the pixels beyond the fixed part; measured 91 B/px beyond the stack at
        // 4000 x 3000 (16 lights, full mask, buffers given back between the steps; issue 23,
        // the end's maps; 76 through the iterations): the estimate bounds it with 19 % to spare.
        assert!((large - FIXED) / (small - FIXED) > 15.9);
        let per_pixel = (large - FIXED) / (2048.0 * 2048.0);
        assert!((104.0..110.0).contains(&per_pixel), "{per_pixel}");
        let refine = Options {
            refine: Refine {
                intensity: true,
                ..Refine::NONE
            },
            ..plain
        };
        assert!(reconstruction(2048, 2048, 2048 * 2048, 1, 16, &refine) > large);
        let direct = Options {
            solver: GlobalSolver::Direct,
            ..plain
        };
        assert!(reconstruction(2048, 2048, 2048 * 2048, 1, 16, &direct) > 4.0 * large);
        // The glossy model holds its warm normals and kept fits; interreflections under it two
        // more f32 stacks (16 lights: 128 bytes a pixel) and the fits' states; under the
        // Lambertian model they add nothing here.
        let alone = Options {
            reflectance: Reflectance::Glossy(None),
            ..plain
        };
        let extra =
            (reconstruction(2048, 2048, 2048 * 2048, 1, 16, &alone) - large) / (2048.0 * 2048.0);
        assert!((extra - 52.0).abs() < 1e-9, "{extra}");
        let rounds = |reflectance| Options {
            interreflections: true,
            reflectance,
            ..plain
        };
        let lambertian = reconstruction(
            2048,
            2048,
            2048 * 2048,
            1,
            16,
            &rounds(Reflectance::Lambertian),
        );
        assert_eq!(lambertian, large);
        let glossy = reconstruction(
            2048,
            2048,
            2048 * 2048,
            1,
            16,
            &rounds(Reflectance::Glossy(None)),
        );
        let extra = (glossy - large) / (2048.0 * 2048.0);
        assert!((extra - (128.0 + 52.0 + 28.0)).abs() < 1e-9, "{extra}");
        // Absurd sizes give a huge number, not an overflow.
        let absurd = reconstruction(usize::MAX, usize::MAX, usize::MAX, 3, usize::MAX, &plain);
        assert!(absurd.is_finite() && absurd > 1e40);
    }
}
