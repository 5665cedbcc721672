//! Local step: fit each facet's normal under the lighting model and turn it into target corner
//! values for the global step.
//!
//! For facet f with centre `c` (mean of its 4 corners), light k contributes the image model
//! `I_{k,ch} = rho_ch * n . r_{k,ch}` with `r_{k,ch} = Phi_{k,ch} * beta_k(c)` (see
//! [`Light::beta`]; `Phi` is the light's intensity in channel `ch`, grey images use the mean of
//! its channels). Per channel, the scaled normal `g_ch = rho_ch * n` solves the weighted normal
//! equations `T_ch g_ch = s_ch`, `T_ch = sum w r r^T`, `s_ch = sum w I r`, over the usable lights
//! (`dark < I < saturation` in every channel, not NaN), with weights
//! - [`Weighting::Image`] (default): `w = 1`, least squares in image units;
//! - [`Weighting::Paper`] (Eq. 6 of Xie et al., generalized): `w = (|p - c|^3 / (Phi aniso))^2`,
//!   i.e. each equation multiplied by `|a_k|^3` for isotropic unit lights;
//!
//! times the robust weights of the optional IRLS ([`Robust`]). Grey images give `n = g / |g|`,
//! `rho = |g|`. Colour images give `n = normalize(sum_ch g_ch)` and, for that `n`, the
//! least-squares albedo `rho_ch = n . s_ch / (n^T T_ch n)`. The target for the global step is the
//! plane through `c` with normal `n` (see [`Geometry::plane_target`]). A facet with fewer than 3
//! usable lights, or a singular system, keeps its current shape and reports no albedo.

use std::borrow::Cow;

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use crate::error::Result;
use crate::geometry::{quad_centre, quad_normal, Geometry};
use crate::grid::Grid;
pub(crate) use crate::light::channel_intensity;
use crate::light::Light;
use crate::memory::try_vec;
use crate::reflectance::{Lobe, Packed};
use crate::shadow::ShadowMask;
use crate::vec3::{dot, norm, scale};

mod check;
mod glossy;
mod glossy_indirect;
mod lanes;
mod trust;

pub(crate) use check::check_lobe;
pub use check::{LobeCheck, CHECK_BELOW_LIGHTS, CHECK_FOLDS};
pub(crate) use glossy::{
    estimate_lobe, estimate_starting_lobe, ETAS, GLOSSY_STEPS, GLOSSY_WARM_STEPS, RETRO_ETA,
};
pub(crate) use glossy_indirect::GlossyState;
pub(crate) use lanes::{final_chunks, FieldRow};
use lanes::{lane_scratch, RobustScratch, LANES};
/// Facets per chunk of the final pass's vectorized accumulation (see
/// [`LocalStep::try_run_final_lanes`]).
pub(crate) const FINAL_LANE_CHUNK: usize = trust::CHUNK;
pub use trust::{LightTrust, Trust, TrustMaps};

/// How the per-facet linear system weights the lights.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Weighting {
    /// Least squares in image units (lower normal error under image noise).
    #[default]
    Image,
    /// The paper's Eq. 6: each equation multiplied by `|a_k|^3`.
    Paper,
}

/// Optional robust estimator (iteratively reweighted least squares) that keeps highlights and
/// cast shadows from bending the normals. Residuals `e_k` (RMS over channels) are scaled by
/// `sigma = 1.4826 * median |e|`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Robust {
    /// Plain least squares.
    #[default]
    None,
    /// Cauchy weights `1 / (1 + (e / (2.385 sigma))^2)`.
    Cauchy,
    /// Tukey's biweight `(1 - (e / (4.685 sigma))^2)^2`, 0 beyond `4.685 sigma`.
    Tukey,
}

/// Reweighting rounds of the robust estimator.
pub const IRLS_ITERATIONS: usize = 8;

/// Settings of the per-facet fits.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FitSettings {
    /// Observations at or below this value (and NaN) are shadowed and left out.
    pub dark: f64,
    /// Observations at or above this value are saturated and left out.
    pub saturation: f64,
    /// Weighting of the equations.
    pub weighting: Weighting,
    /// Robust estimator.
    pub robust: Robust,
    /// Take the residual of grey, unit-weight fits from the normal equations,
    /// `sum (r . g - I)^2 = sum I^2 - g . s`, instead of a second pass over the lights (exact up
    /// to a cancellation of order `sqrt(eps * sum I^2)`; used for the per-iteration history).
    pub fast_residual: bool,
    /// The shared lobe of the glossy model: each facet's Lambertian fit is then refined under
    /// it (see the `glossy` module); None: the Lambertian model.
    pub lobe: Option<Lobe>,
    /// Under a sharp lobe, also fit each facet from its Lambertian start by continuation from a
    /// rough lobe (see `glossy::CONTINUE_BELOW`). The distance search compares its candidates
    /// without it (their residual curve moved with it: see `Solver::continuation`).
    pub continuation: bool,
    /// The glossy fits stop before trying a Gauss-Newton step shorter than this fraction of
    /// their unknowns (see [`STEP_TOLERANCE`](crate::reflectance::STEP_TOLERANCE)); 0: they go
    /// on until a step no longer lowers the residual noticeably. The solver sets it where no
    /// residuals are compared across candidates (see `Solver::local_step`).
    pub step_tolerance: f64,
    /// The variance of the noise of an observation (the sum of its channels), which with a
    /// step tolerance also ends the glossy fits (see
    /// [`NOISE_STOP`](crate::reflectance::NOISE_STOP)); 0: none known.
    pub noise: f64,
    /// The glossy fits run their kernels in `f64` lanes ([`Packed::precise`]) instead of
    /// `f32` ones. The solver sets it where residuals are compared across candidates (the
    /// distance search and check, see `Solver::local_step`): their criteria are flat, and the
    /// `f32` lanes' rounding moved the distances found (stop 51, docs/shiny.md).
    pub precise: bool,
}

impl Default for FitSettings {
    fn default() -> Self {
        FitSettings {
            dark: 0.0,
            saturation: f64::INFINITY,
            weighting: Weighting::Image,
            robust: Robust::None,
            fast_residual: false,
            lobe: None,
            continuation: true,
            step_tolerance: 0.0,
            noise: 0.0,
            precise: false,
        }
    }
}

impl FitSettings {
    /// A glossy fit's scratch space in the lanes' precision of these settings (see
    /// [`FitSettings::precise`]).
    pub(crate) fn packed(&self) -> Packed {
        match self.precise {
            true => Packed::precise(),
            false => Packed::new(),
        }
    }
}

/// The local fit of one facet.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FacetFit {
    /// Mean-subtracted target corner values (order 00, 01, 10, 11).
    pub target: [f64; 4],
    /// Fitted unit normal (the mesh normal for an invalid facet).
    pub normal: [f64; 3],
    /// Fitted albedo per channel (grey: all three equal; NaN for an invalid facet); the diffuse
    /// albedo under the glossy model.
    pub albedo: [f64; 3],
    /// Specular albedo of the glossy model (0 under the Lambertian model, NaN for an invalid
    /// facet).
    pub specular: f64,
    /// Sum of squared image residuals over the usable observations (lights x channels).
    pub sse: f64,
    /// Number of usable lights.
    pub used: u32,
    /// Whether the fit succeeded (>= 3 usable lights, regular system).
    pub valid: bool,
}

impl FacetFit {
    /// A placeholder before the first fit.
    pub const EMPTY: FacetFit = FacetFit {
        target: [0.0; 4],
        normal: [f64::NAN; 3],
        albedo: [f64::NAN; 3],
        specular: f64::NAN,
        sse: 0.0,
        used: 0,
        valid: false,
    };

    /// RMS image residual per usable observation (NaN for an invalid facet).
    pub fn rms(&self, channels: usize) -> f64 {
        if self.valid {
            (self.sse / (self.used as usize * channels) as f64).sqrt()
        } else {
            f64::NAN
        }
    }
}

/// The divisor of 16-bit samples: a `u16` value `v` reads as `v as f32 / 65535.0` (the float32
/// division that `nplps.io.load_stack` applies to 16-bit images, so both give the same bits).
pub const U16_SCALE: f32 = 65535.0;

/// The value of a 16-bit sample on the `[0, 1]` scale of the float stacks (see [`U16_SCALE`]).
#[inline(always)]
pub fn u16_value(v: u16) -> f32 {
    f32::from(v) / U16_SCALE
}

/// The sample values of a borrowed image stack: float32 (NaN marks a missing observation), or
/// 16-bit integers kept as they are read, 2 bytes per value instead of 4, and converted where
/// they are used ([`u16_value`]; a 16-bit stack has no missing observation).
#[derive(Debug, Clone, Copy)]
pub enum Samples<'a> {
    /// Float32 values.
    F32(&'a [f32]),
    /// 16-bit values `v`, read as `v / 65535`.
    U16(&'a [u16]),
}

impl Samples<'_> {
    /// Number of values.
    #[inline]
    pub fn len(&self) -> usize {
        match self {
            Samples::F32(d) => d.len(),
            Samples::U16(d) => d.len(),
        }
    }

    /// Whether there is no value.
    #[inline]
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Value `i` on the float scale.
    #[inline(always)]
    pub fn get(&self, i: usize) -> f32 {
        match self {
            Samples::F32(d) => d[i],
            Samples::U16(d) => u16_value(d[i]),
        }
    }

    /// Bytes per value (4 or 2).
    pub fn bytes_per_value(&self) -> usize {
        match self {
            Samples::F32(_) => 4,
            Samples::U16(_) => 2,
        }
    }
}

/// The values of the stack an [`Observations`] reads: float32, borrowed or owned (the coarse
/// levels of a pyramid), or borrowed 16-bit integers read as `v / 65535` where they are used
/// ([`u16_value`]).
#[derive(Debug, Clone)]
pub(crate) enum Stored<'a> {
    /// Float32 values; NaN marks a missing observation.
    F32(Cow<'a, [f32]>),
    /// 16-bit values.
    U16(&'a [u16]),
}

/// The (at most 3) channel values of one observation, by value (a 16-bit stack has no float
/// slice to borrow); dereferences to the `channels` values.
#[derive(Debug, Clone, Copy)]
pub struct Sample {
    values: [f32; 3],
    channels: usize,
}

impl std::ops::Deref for Sample {
    type Target = [f32];
    #[inline]
    fn deref(&self) -> &[f32] {
        &self.values[..self.channels]
    }
}

/// The observations of the masked facets: a (k, H, W, C) image stack, borrowed from the
/// caller without a copy (float32 or 16-bit), or owned (the coarse levels of a pyramid). NaN
/// marks a missing observation.
#[derive(Debug, Clone)]
pub struct Observations<'a> {
    /// Number of lights k.
    pub k: usize,
    /// Channels per observation (1 or 3).
    pub channels: usize,
    /// The stack, row-major (k, H, W, C).
    pub(crate) data: Stored<'a>,
    /// Values per image, H * W * C.
    pub(crate) plane: usize,
}

impl<'a> Observations<'a> {
    /// Borrows a float32 (k, H, W, C) stack with `pixels` = H * W pixels per image.
    #[cfg(test)]
    pub fn from_stack(data: &'a [f32], k: usize, pixels: usize, channels: usize) -> Self {
        Self::from_samples(Samples::F32(data), k, pixels, channels)
    }

    /// Borrows a (k, H, W, C) stack of float32 or 16-bit samples with `pixels` = H * W pixels
    /// per image.
    pub fn from_samples(data: Samples<'a>, k: usize, pixels: usize, channels: usize) -> Self {
        debug_assert_eq!(data.len(), k * pixels * channels);
        Observations {
            k,
            channels,
            data: match data {
                Samples::F32(d) => Stored::F32(Cow::Borrowed(d)),
                Samples::U16(d) => Stored::U16(d),
            },
            plane: pixels * channels,
        }
    }

    /// Owns a (k, H, W, C) stack with `pixels` = H * W pixels per image.
    pub fn owned_stack(
        data: Vec<f32>,
        k: usize,
        pixels: usize,
        channels: usize,
    ) -> Observations<'static> {
        debug_assert_eq!(data.len(), k * pixels * channels);
        Observations {
            k,
            channels,
            data: Stored::F32(Cow::Owned(data)),
            plane: pixels * channels,
        }
    }

    /// Values per facet, `k * channels`.
    #[inline]
    pub fn per_facet(&self) -> usize {
        self.k * self.channels
    }

    /// The `channels` values of light `i` at pixel index `pixel`.
    #[inline]
    pub fn at(&self, i: usize, pixel: usize) -> Sample {
        let start = i * self.plane + pixel * self.channels;
        let mut values = [0.0f32; 3];
        let c = self.channels;
        match &self.data {
            Stored::F32(d) => values[..c].copy_from_slice(&d[start..start + c]),
            Stored::U16(d) => {
                for (o, &v) in values[..c].iter_mut().zip(&d[start..start + c]) {
                    *o = u16_value(v);
                }
            }
        }
        Sample {
            values,
            channels: c,
        }
    }

    /// The `k * channels` values of the facet at pixel index `pixel` (row-major, `r * W + c`),
    /// light-major, gathered into `buf` (of at least that length).
    #[inline]
    pub fn facet<'b>(&self, pixel: usize, buf: &'b mut [f32]) -> &'b [f32] {
        match &self.data {
            Stored::F32(d) => self.gather_facet(&d[..], pixel, buf, |v| v),
            Stored::U16(d) => self.gather_facet(d, pixel, buf, u16_value),
        }
    }

    #[inline(always)]
    fn gather_facet<'b, T: Copy>(
        &self,
        data: &[T],
        pixel: usize,
        buf: &'b mut [f32],
        value: impl Fn(T) -> f32,
    ) -> &'b [f32] {
        let per = self.per_facet();
        let plane = self.plane;
        let c = self.channels;
        let start = pixel * c;
        if c == 1 {
            // One value per light: plain loads (a slice copy per light would be a call).
            for (i, out) in buf[..per].iter_mut().enumerate() {
                *out = value(data[i * plane + start]);
            }
        } else {
            for (i, out) in buf[..per].chunks_exact_mut(c).enumerate() {
                let at = i * plane + start;
                for (o, &v) in out.iter_mut().zip(&data[at..at + c]) {
                    *o = value(v);
                }
            }
        }
        &buf[..per]
    }
}

/// The lighting model a facet is fitted with.
#[derive(Debug, Clone, Copy)]
pub enum Model<'a> {
    /// The rig's lights (the method's model).
    Near(&'a [Light]),
    /// Parallel lights `(direction, intensity)`, no falloff (the conventional baseline).
    Parallel(&'a [([f64; 3], [f64; 3])]),
}

impl Model<'_> {
    /// `beta_k(c)`, the paper-weighting factor and the intensity of light k.
    #[inline]
    fn row(&self, k: usize, c: [f64; 3]) -> ([f64; 3], f64, [f64; 3]) {
        match *self {
            Model::Near(lights) => {
                let (b, w) = lights[k].beta(c);
                (b, w, lights[k].intensity())
            }
            Model::Parallel(lights) => (lights[k].0, 1.0, lights[k].1),
        }
    }

    /// Light k at `c` as the glossy model uses it: `(a, l, phi)` with `a = |beta_k(c)|`, the
    /// unit direction `l = (1 / a) beta_k(c)` and the intensity `phi`; `None` unless `a` is
    /// positive and finite.
    #[inline]
    fn light(&self, k: usize, c: [f64; 3]) -> Option<(f64, [f64; 3], [f64; 3])> {
        let (b, _, phi) = self.row(k, c);
        let a = norm(b);
        (a > 0.0 && a.is_finite()).then(|| (a, scale(b, 1.0 / a), phi))
    }
}

/// The indirect light that a local step adds to its Lambertian fits: what the fits ask of
/// [`crate::indirect::IndirectField`], which implements it (the local step sits below the
/// interreflection model and knows it only through these two questions).
pub trait IndirectLight: Sync {
    /// Whether light `k` is behind the facet of pixel `p` on the mesh the field was made for
    /// (its observation then keeps its indirect light only).
    fn is_unlit(&self, p: usize, k: usize) -> bool;
    /// The indirect irradiance vectors `V` of pixel `p` (of an image `width` pixels wide), one
    /// per light and channel, into `out` (resized to them).
    fn at_into(&self, p: usize, width: usize, out: &mut Vec<[f64; 3]>);
    /// [`IndirectLight::at_into`] and [`IndirectLight::is_unlit`] of pixel `p` for lane `lane`
    /// of the fits in lanes (grey images): `rows[j].v[c][lane]` is component `c` of its vector
    /// `j` and `rows[j].direct[lane]` whether light `j`'s direct light reaches it (not
    /// `is_unlit`), for the first `rows.len()` vectors. The same values as those two; a field
    /// may find them in one pass (the default goes through them).
    fn lane_into(&self, p: usize, width: usize, lane: usize, rows: &mut [FieldRow]) {
        let mut vectors = Vec::new();
        self.at_into(p, width, &mut vectors);
        for (j, (row, v)) in rows.iter_mut().zip(&vectors).enumerate() {
            for (c, &x) in v.iter().enumerate() {
                row.v[c][lane] = x;
            }
            row.direct[lane] = !self.is_unlit(p, j);
        }
    }
}

/// What the iterations keep of a facet's fit besides its target.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FacetStat {
    /// Sum of squared image residuals over the usable observations.
    pub sse: f64,
    /// Number of usable lights.
    pub used: u32,
    /// Whether the fit succeeded.
    pub valid: bool,
}

// SAFETY: zero bytes are 0.0, 0 and false (the padding bytes are never read).
unsafe impl crate::memory::Zeroable for FacetStat {
    const ZERO: Self = FacetStat {
        sse: 0.0,
        used: 0,
        valid: false,
    };
}

impl From<&FacetFit> for FacetStat {
    fn from(fit: &FacetFit) -> FacetStat {
        FacetStat {
            sse: fit.sse,
            used: fit.used,
            valid: fit.valid,
        }
    }
}

/// The inputs of a local step.
#[derive(Clone, Copy)]
pub struct LocalStep<'s> {
    /// The mesh.
    pub grid: &'s Grid,
    /// Vertex positions.
    pub geometry: &'s Geometry,
    /// The lighting model.
    pub model: Model<'s>,
    /// The observations.
    pub obs: &'s Observations<'s>,
    /// Fit settings.
    pub settings: FitSettings,
    /// The depth of every unknown, when the caller has it (a pinhole camera's unknowns are
    /// log-depths: this saves an `exp` per facet corner); None: from the unknowns.
    pub depths: Option<&'s [f64]>,
    /// Checked every few facets: once cancelled, the remaining facets are skipped (the caller
    /// must then check the token and discard the step).
    pub cancel: &'s crate::Cancel,
    /// Under the glossy model, each facet's glossy normal of an earlier local step (NaN: none),
    /// which starts its glossy fit in [`LocalStep::try_run`] (see [`LocalStep::fit`]).
    pub warm: Option<&'s [[f32; 3]]>,
    /// The cast shadows of the current mesh (per pixel of the grid's image and light): the
    /// observations in a cast shadow are left out of every fit as if missing (NaN); None: all
    /// observations are used.
    pub shadows: Option<&'s ShadowMask>,
    /// The indirect irradiance of each facet under each light (with
    /// [`Options::interreflections`](crate::Options::interreflections), see
    /// [`crate::indirect::IndirectField`]): added to the light's row of the fits,
    /// `I = b . (s + V)`; None: the direct light only. The Lambertian fits use it (grey images
    /// in the vectorised lanes, `lanes::field`, colour in the scalar fits; the glossy model is
    /// refused).
    pub indirect: Option<&'s dyn IndirectLight>,
}

impl<'s> LocalStep<'s> {
    /// A local step of the direct light alone: depths from the unknowns, never cancelled, no
    /// warm start, no shadow mask, no indirect light (set those fields by struct update).
    pub fn new(
        grid: &'s Grid,
        geometry: &'s Geometry,
        model: Model<'s>,
        obs: &'s Observations<'s>,
        settings: FitSettings,
    ) -> Self {
        LocalStep {
            grid,
            geometry,
            model,
            obs,
            settings,
            depths: None,
            cancel: crate::Cancel::never(),
            warm: None,
            shadows: None,
            indirect: None,
        }
    }
}

impl LocalStep<'_> {
    /// The 4 corners of facet `f` (see [`Geometry::facet_corners`]).
    #[inline]
    fn corners(&self, f: usize, u: &[f64]) -> [[f64; 3]; 4] {
        match self.depths {
            Some(z) => {
                // (an array literal rather than `map`, whose call was not inlined)
                let ids = self.grid.facet_vertices(f);
                let at = |j: usize| {
                    let i = ids[j] as usize;
                    self.geometry.position_at_depth(i, z[i])
                };
                [at(0), at(1), at(2), at(3)]
            }
            None => self.geometry.facet_corners(self.grid, f, u),
        }
    }

    /// The observations of facet `f` gathered into `buf`, those in a cast shadow (see
    /// [`LocalStep::shadows`]) set to NaN.
    #[inline]
    pub(super) fn facet_values<'b>(&self, f: usize, buf: &'b mut [f32]) -> &'b [f32] {
        let pixel = self.grid.facets[f] as usize;
        let per = self.obs.facet(pixel, buf).len();
        if let Some(shadows) = self.shadows {
            let c = self.obs.channels;
            for k in shadows.lights_at(pixel) {
                buf[k * c..(k + 1) * c].fill(f32::NAN);
            }
        }
        &buf[..per]
    }

    /// The fit of facet `f` on the unknowns `u`, with `buf` as scratch for its observations
    /// (and `glossy` for the glossy model's). Under the glossy model a `warm` normal (the
    /// facet's glossy normal of the previous local step) starts the glossy fit, with
    /// [`GLOSSY_WARM_STEPS`] steps; without one the fit starts from the Lambertian normal; the
    /// mesh normal is the second start (see `glossy::refine`).
    #[inline]
    fn fit(
        &self,
        f: usize,
        u: &[f64],
        buf: &mut [f32],
        glossy: &mut Packed,
        warm: Option<[f64; 3]>,
    ) -> FacetFit {
        self.fit_corners(f, u, self.corners(f, u), buf, glossy, warm)
    }

    /// [`LocalStep::fit`] of facet `f` whose corners `q` are already known.
    #[inline]
    fn fit_corners(
        &self,
        f: usize,
        u: &[f64],
        q: [[f64; 3]; 4],
        buf: &mut [f32],
        glossy: &mut Packed,
        warm: Option<[f64; 3]>,
    ) -> FacetFit {
        let (grid, geometry, obs) = (self.grid, self.geometry, self.obs);
        let ids = grid.facet_vertices(f);
        let c = quad_centre(&q);
        if let Some(field) = self.indirect {
            return self.fit_indirect(f, u, buf, field, &q, c);
        }
        let values = self.facet_values(f, buf);
        let lambertian = || fit_facet(c, self.model, values, obs.channels, self.settings);
        let fitted = match self.settings.lobe {
            None => lambertian(),
            Some(lobe) => {
                let mut refine = |start: Option<&FacetFit>, first: [f64; 3], steps: usize| {
                    glossy::refine(
                        c,
                        geometry.view(c),
                        self.model,
                        values,
                        obs.channels,
                        &self.settings,
                        &lobe,
                        start,
                        [Some(first), Some(quad_normal(&q))],
                        steps,
                        glossy,
                    )
                };
                // From a warm normal the Lambertian fit is needed only where the glossy fit
                // fails: it then starts it again, or is kept.
                let from_warm = warm.and_then(|n| refine(None, n, GLOSSY_WARM_STEPS));
                from_warm.or_else(|| {
                    lambertian().map(|fit| {
                        let (n, steps) = match warm {
                            Some(n) => (n, GLOSSY_WARM_STEPS),
                            None => (fit.normal, GLOSSY_STEPS),
                        };
                        refine(Some(&fit), n, steps).unwrap_or(fit)
                    })
                })
            }
        };
        match fitted {
            Some(fitted) => FacetFit {
                target: geometry.plane_target(fitted.normal, ids, c),
                ..fitted
            },
            None => keep_shape(
                &q,
                ids.map(|i| u[i as usize]),
                usable_count(values, obs.channels, self.settings),
            ),
        }
    }

    /// [`LocalStep::fit`] with the indirect light of `field` (Lambertian model): the
    /// observations in a cast shadow (and those of the lights behind the facet, see
    /// [`IndirectField::with_unlit`](crate::indirect::IndirectField::with_unlit)) keep their
    /// indirect light, as rows `V` alone. The vectors and flags live in a per-thread scratch.
    fn fit_indirect(
        &self,
        f: usize,
        u: &[f64],
        buf: &mut [f32],
        field: &dyn IndirectLight,
        q: &[[f64; 3]; 4],
        c: [f64; 3],
    ) -> FacetFit {
        thread_local! {
            static SCRATCH: std::cell::RefCell<(Vec<[f64; 3]>, Vec<bool>)> =
                const { std::cell::RefCell::new((Vec::new(), Vec::new())) };
        }
        let (grid, obs) = (self.grid, self.obs);
        let pixel = grid.facets[f] as usize;
        let ids = grid.facet_vertices(f);
        SCRATCH.with_borrow_mut(|(vectors, direct)| {
            direct.clear();
            direct.extend((0..obs.k).map(|k| !field.is_unlit(pixel, k)));
            if let Some(shadows) = self.shadows {
                for k in shadows.lights_at(pixel) {
                    direct[k] = false;
                }
            }
            field.at_into(pixel, grid.width, vectors);
            let values = obs.facet(pixel, buf);
            let indirect = Indirect { vectors, direct };
            match fit_facet_with(
                c,
                self.model,
                values,
                obs.channels,
                self.settings,
                Some(indirect),
            ) {
                Some(fitted) => FacetFit {
                    target: self.geometry.plane_target(fitted.normal, ids, c),
                    ..fitted
                },
                None => keep_shape(
                    q,
                    ids.map(|i| u[i as usize]),
                    usable_count(values, obs.channels, self.settings),
                ),
            }
        })
    }

    /// Fits facets `first..first + fits.len()` on `u` in parallel (rayon), writing `fits`.
    ///
    /// Panics when a thread's scratch space cannot be allocated: prefer [`LocalStep::try_run`],
    /// which reports it as [`Error::Memory`](crate::Error::Memory).
    #[cfg(test)]
    pub fn run(&self, u: &[f64], first: usize, fits: &mut [FacetFit]) {
        if let Err(e) = self.try_run(u, first, fits) {
            panic!("{e}");
        }
    }

    /// As `LocalStep::run` (tests), with [`Error::Memory`](crate::Error::Memory) when a thread's scratch space (one facet's
    /// observations) cannot be allocated.
    pub fn try_run(&self, u: &[f64], first: usize, fits: &mut [FacetFit]) -> Result<()> {
        let per = self.obs.per_facet();
        if let Some(lights) = self.batch_lights() {
            let lights = &lights[..];
            return fits.par_chunks_mut(LANES).enumerate().try_for_each_init(
                || lane_scratch(per, self.obs.k),
                |scratch, (chunk, fits)| {
                    let (buf, interleaved) = scratch.as_mut().map_err(|e| e.clone())?;
                    if self.cancel.is_cancelled() {
                        return Ok(());
                    }
                    let start = first + chunk * LANES;
                    if fits.len() == LANES {
                        let lanes = self.fit_lanes(lights, start, u, buf, interleaved, None);
                        fits.copy_from_slice(&lanes);
                    } else {
                        for (i, fit) in fits.iter_mut().enumerate() {
                            // (no glossy observations: the lanes fit the Lambertian model)
                            *fit = self.fit(start + i, u, buf, &mut Packed::new(), None);
                        }
                    }
                    Ok(())
                },
            );
        }
        if let Some(lights) = self.robust_lane_lights() {
            let (k, channels) = (self.obs.k, self.obs.channels);
            return fits.par_chunks_mut(LANES).enumerate().try_for_each_init(
                || RobustScratch::new(k, channels),
                |scratch, (chunk, fits)| {
                    let scratch = scratch.as_mut().map_err(|e| e.clone())?;
                    if !self.cancel.is_cancelled() {
                        let start = first + chunk * LANES;
                        self.fit_robust_batch(&lights, start, u, scratch, fits);
                    }
                    Ok(())
                },
            );
        }
        fits.par_iter_mut().enumerate().try_for_each_init(
            || facet_scratch(per, &self.settings),
            |scratch, (i, fit)| {
                let (buf, glossy) = scratch.as_mut().map_err(|e| e.clone())?;
                if !self.cancel.is_cancelled() {
                    let warm = self.warm.and_then(|w| warm_normal(&w[first + i]));
                    *fit = self.fit(first + i, u, buf, glossy, warm);
                }
                Ok(())
            },
        )
    }

    /// The final pass over facets `first..first + fits.len()` on `u` where the vectorized
    /// accumulation does not give the trust values (colour, a robust estimator, indirect
    /// light, the paper's weighting, parallel lights: [`LocalStep::final_lane_lights`] is
    /// None; the solver takes [`LocalStep::try_run_final_lanes`] otherwise): their fits, as
    /// [`LocalStep::try_run`], then their trust values `[normal sigma, held-out]` into `trust`
    /// (same length), as the `trust` module defines them, whose per-light sums it adds to
    /// `maps` (the caller scatters `trust` into `maps`).
    ///
    /// Under the glossy model the trust values are still those of the Lambertian fit at the
    /// final mesh (the `trust` module's, which leave the lobe out), and with `kept` the facets
    /// that did not move since their last converged glossy fit keep it (see
    /// [`LocalStep::try_run_kept`]); returns how many did.
    pub fn try_run_final(
        &self,
        u: &[f64],
        first: usize,
        fits: &mut [FacetFit],
        trust: &mut [[f32; 2]],
        maps: &mut TrustMaps,
        kept: Option<&KeptFits>,
    ) -> Result<usize> {
        debug_assert_eq!(fits.len(), trust.len());
        let done = self.try_run_kept(u, first, fits, kept)?;
        // A robust step's fits (without a lobe or indirect light) are those its trust values
        // start from: passed on, not fitted again.
        let s = self.settings;
        let own = s.robust != Robust::None && s.lobe.is_none() && self.indirect.is_none();
        maps.add(self.trust_range(u, first, trust, own.then_some(&*fits)));
        Ok(done)
    }

    /// This step without its lobe: the Lambertian model's fits under the same settings.
    pub(crate) fn lambertian(&self) -> LocalStep<'_> {
        LocalStep {
            settings: FitSettings {
                lobe: None,
                ..self.settings
            },
            ..*self
        }
    }

    /// Where the final pass takes its trust values (and, under the Lambertian model, its fits)
    /// from the vectorized accumulation: the lights of [`LocalStep::lane_lights`] of the
    /// Lambertian model under this step's settings, and whether the lanes' fits are the
    /// pass's fits (the Lambertian model) or only its trust values are (the glossy model, whose
    /// own fits are then made by [`LocalStep::try_run_kept`]). None: the scalar trust values
    /// (colour, a robust estimator, indirect light, the paper's weighting, parallel lights).
    pub(crate) fn final_lane_lights(&self) -> Option<(Vec<crate::light::LaneLight>, bool)> {
        let lights = self.lambertian().lane_lights()?;
        Some((lights, self.settings.lobe.is_none()))
    }

    /// The final pass of the vectorized accumulation over every facet (`lights` and `fitted`
    /// from [`LocalStep::final_lane_lights`]): in chunks of [`FINAL_LANE_CHUNK`] facets run in
    /// parallel, each handing its fits (with `fitted`; else none) and trust values to `write`
    /// with its entry of `views` (one per chunk, [`final_chunks`] of them) and its first
    /// facet (see `LocalStep::final_lanes_into`). Returns the per-light trust sums (for
    /// [`TrustMaps::add`]).
    pub(crate) fn try_run_final_lanes<V: Send>(
        &self,
        lights: &[crate::light::LaneLight],
        u: &[f64],
        fitted: bool,
        views: Vec<V>,
        write: &(impl Fn(V, usize, &[FacetFit], &[[f32; 2]]) + Sync),
    ) -> Result<trust::LightSums> {
        self.lambertian()
            .final_lanes_into(lights, u, fitted, views, write)
    }

    /// [`LocalStep::try_run`] where, under the glossy model with grey images, each facet whose
    /// record in `kept` holds (its last glossy fit converged, and its centre moved by at most
    /// [`SKIP_MOVE`] of its reach since, see [`KeptFits`]) keeps that fit: its warm normal,
    /// diffuse and specular albedos, residual and count of lights, with the plane through its
    /// current centre as target. Returns how many facets kept their fits.
    pub fn try_run_kept(
        &self,
        u: &[f64],
        first: usize,
        fits: &mut [FacetFit],
        kept: Option<&KeptFits>,
    ) -> Result<usize> {
        let (Some(kept), Some(key), Some(warm)) = (kept, self.kept_key(), self.warm) else {
            return self.try_run(u, first, fits).map(|()| 0);
        };
        if self.obs.channels != 1 || !kept.trusts(&key, self.grid.n_facets()) {
            return self.try_run(u, first, fits).map(|()| 0);
        }
        let (records, lights) = (&kept.facets[first..][..fits.len()], key.1);
        let per = self.obs.per_facet();
        fits.par_iter_mut()
            .zip(records)
            .enumerate()
            .map_init(
                || facet_scratch(per, &self.settings),
                |scratch, (i, (fit, record))| -> Result<usize> {
                    let (buf, glossy) = scratch.as_mut().map_err(|e| e.clone())?;
                    if self.cancel.is_cancelled() {
                        return Ok(0);
                    }
                    let f = first + i;
                    let q = self.corners(f, u);
                    let start = warm_normal(&warm[f]);
                    let c = quad_centre(&q);
                    if let Some(n) = start.filter(|_| record.holds(c, lights)) {
                        let n = scale(n, 1.0 / norm(n));
                        *fit = FacetFit {
                            target: self
                                .geometry
                                .plane_target(n, self.grid.facet_vertices(f), c),
                            normal: n,
                            albedo: [record.diffuse as f64; 3],
                            specular: record.specular as f64,
                            sse: record.sse as f64,
                            used: record.used,
                            valid: true,
                        };
                        return Ok(1);
                    }
                    *fit = self.fit_corners(f, u, q, buf, glossy, start);
                    Ok(0)
                },
            )
            .try_reduce(|| 0, |a, b| Ok(a + b))
    }

    /// The settings and lights under which this step may keep fits of [`KeptFits`]: None where
    /// it keeps none (the Lambertian model, fits that run to their minimum for a comparison
    /// (`step_tolerance` 0), cast shadows, indirect light, parallel lights). The fits'
    /// residual mode is left out (the glossy fits do not use it).
    fn kept_key(&self) -> Option<(FitSettings, &[Light])> {
        match self.model {
            Model::Near(lights)
                if self.settings.lobe.is_some()
                    && self.settings.step_tolerance > 0.0
                    && self.shadows.is_none()
                    && self.indirect.is_none() =>
            {
                let settings = FitSettings {
                    fast_residual: false,
                    ..self.settings
                };
                Some((settings, lights))
            }
            _ => None,
        }
    }

    /// Fits every facet on `u` in parallel, keeping only the targets and the statistics.
    ///
    /// Panics when a thread's scratch space cannot be allocated: prefer
    /// [`LocalStep::try_run_targets`], which reports it as [`Error::Memory`](crate::Error::Memory).
    #[cfg(test)]
    pub fn run_targets(&self, u: &[f64], targets: &mut [[f64; 4]], stats: &mut [FacetStat]) {
        if let Err(e) = self.try_run_targets(u, targets, stats) {
            panic!("{e}");
        }
    }

    /// As `LocalStep::run_targets` (tests), with [`Error::Memory`](crate::Error::Memory) when a thread's scratch space
    /// cannot be allocated.
    pub fn try_run_targets(
        &self,
        u: &[f64],
        targets: &mut [[f64; 4]],
        stats: &mut [FacetStat],
    ) -> Result<()> {
        self.try_run_targets_at(0, u, targets, stats)
    }

    /// As [`LocalStep::try_run_targets`] for the facets `start..start + targets.len()` only
    /// (`start` a multiple of the lane count, so the facets are batched as in a whole run and
    /// the results are the same bits).
    pub fn try_run_targets_at(
        &self,
        start: usize,
        u: &[f64],
        targets: &mut [[f64; 4]],
        stats: &mut [FacetStat],
    ) -> Result<()> {
        debug_assert_eq!(start % LANES, 0);
        let per = self.obs.per_facet();
        if let Some(lights) = self.batch_lights() {
            let lights = &lights[..];
            return targets
                .par_chunks_mut(LANES)
                .zip(stats.par_chunks_mut(LANES))
                .enumerate()
                .try_for_each_init(
                    || lane_scratch(per, self.obs.k),
                    |scratch, (chunk, (targets, stats))| {
                        let (buf, interleaved) = scratch.as_mut().map_err(|e| e.clone())?;
                        if self.cancel.is_cancelled() {
                            return Ok(());
                        }
                        let first = start + chunk * LANES;
                        if targets.len() == LANES {
                            self.fit_lanes_targets(
                                lights,
                                first,
                                u,
                                buf,
                                interleaved,
                                targets,
                                stats,
                            );
                        } else {
                            for (i, (target, stat)) in targets.iter_mut().zip(stats).enumerate() {
                                let fit = self.fit(first + i, u, buf, &mut Packed::new(), None);
                                *target = fit.target;
                                *stat = FacetStat::from(&fit);
                            }
                        }
                        Ok(())
                    },
                );
        }
        if let Some(lights) = self.robust_lane_lights() {
            let (k, channels) = (self.obs.k, self.obs.channels);
            return targets
                .par_chunks_mut(LANES)
                .zip(stats.par_chunks_mut(LANES))
                .enumerate()
                .try_for_each_init(
                    || RobustScratch::new(k, channels),
                    |scratch, (chunk, (targets, stats))| {
                        let scratch = scratch.as_mut().map_err(|e| e.clone())?;
                        if self.cancel.is_cancelled() {
                            return Ok(());
                        }
                        let mut fits = [FacetFit::EMPTY; LANES];
                        let fits = &mut fits[..targets.len()];
                        let first = start + chunk * LANES;
                        self.fit_robust_batch(&lights, first, u, scratch, fits);
                        for ((target, stat), fit) in targets.iter_mut().zip(stats).zip(&*fits) {
                            *target = fit.target;
                            *stat = FacetStat::from(fit);
                        }
                        Ok(())
                    },
                );
        }
        targets
            .par_iter_mut()
            .zip(stats.par_iter_mut())
            .enumerate()
            .try_for_each_init(
                || facet_scratch(per, &self.settings),
                |scratch, (f, (target, stat))| {
                    let (buf, glossy) = scratch.as_mut().map_err(|e| e.clone())?;
                    if self.cancel.is_cancelled() {
                        return Ok(());
                    }
                    let fit = self.fit(start + f, u, buf, glossy, None);
                    *target = fit.target;
                    *stat = FacetStat::from(&fit);
                    Ok(())
                },
            )
    }

    /// As [`LocalStep::try_run_targets`] under the glossy model (`settings.lobe` set), with the
    /// facets' glossy normals of the previous local step in `warm` (NaN: none), which start
    /// their fits and are replaced by this step's.
    ///
    /// With `kept` (see [`KeptFits`]), a facet whose last glossy fit converged (ended at its
    /// minimum, not by its last allowed step) and whose centre has moved by at most [`SKIP_MOVE`] of its reach since that fit keeps it: its
    /// target is the plane of its warm normal through its current centre, its statistics those
    /// of that fit, and it is not fitted again. Returns how many facets kept their fits.
    pub fn try_run_glossy_targets(
        &self,
        u: &[f64],
        targets: &mut [[f64; 4]],
        stats: &mut [FacetStat],
        warm: &mut [[f32; 3]],
        kept: Option<&mut KeptFits>,
    ) -> Result<usize> {
        let per = self.obs.per_facet();
        let kept = match (kept, self.kept_key()) {
            (Some(kept), Some(key)) => Some((kept, key)),
            (Some(kept), None) => {
                kept.clear();
                None
            }
            (None, _) => None,
        };
        let Some((kept, key)) = kept else {
            return targets
                .par_iter_mut()
                .zip(stats.par_iter_mut())
                .zip(warm.par_iter_mut())
                .enumerate()
                .try_for_each_init(
                    || facet_scratch(per, &self.settings),
                    |scratch, (f, ((target, stat), warm))| {
                        let (buf, glossy) = scratch.as_mut().map_err(|e| e.clone())?;
                        if self.cancel.is_cancelled() {
                            return Ok(());
                        }
                        self.glossy_target(f, u, buf, glossy, target, stat, warm, None);
                        Ok(())
                    },
                )
                .map(|()| 0);
        };
        let reuse = kept.trusts(&key, targets.len());
        let (settings, lights) = key;
        if kept.facets.len() != targets.len() {
            kept.facets = Vec::new();
            kept.facets = try_vec(targets.len(), KeptFit::NONE, "the kept glossy fits")?;
        }
        // Until this step has written every facet's record, none is trusted.
        kept.under = None;
        let skip = reuse.then_some(lights);
        let done = targets
            .par_iter_mut()
            .zip(stats.par_iter_mut())
            .zip(warm.par_iter_mut())
            .zip(kept.facets.par_iter_mut())
            .enumerate()
            .map_init(
                || facet_scratch(per, &self.settings),
                |scratch, (f, (((target, stat), warm), record))| -> Result<usize> {
                    let (buf, glossy) = scratch.as_mut().map_err(|e| e.clone())?;
                    if self.cancel.is_cancelled() {
                        return Ok(0);
                    }
                    let kept = (record, skip);
                    Ok(
                        self.glossy_target(f, u, buf, glossy, target, stat, warm, Some(kept))
                            as usize,
                    )
                },
            )
            .try_reduce(|| 0, |a, b| Ok(a + b))?;
        if !self.cancel.is_cancelled() {
            kept.under = Some((settings, lights.to_vec()));
        }
        Ok(done)
    }

    /// One facet of [`LocalStep::try_run_glossy_targets`]: its target, statistics and warm
    /// normal, from its fit, or from its `kept` record where the facet keeps its last fit (the
    /// lights given: the record is trusted); the record is then replaced by this fit's. Returns
    /// whether the facet kept its fit.
    #[allow(clippy::too_many_arguments)]
    #[inline]
    fn glossy_target(
        &self,
        f: usize,
        u: &[f64],
        buf: &mut [f32],
        glossy: &mut Packed,
        target: &mut [f64; 4],
        stat: &mut FacetStat,
        warm: &mut [f32; 3],
        kept: Option<(&mut KeptFit, Option<&[Light]>)>,
    ) -> bool {
        let q = self.corners(f, u);
        let start = warm_normal(warm);
        let Some((record, skip)) = kept else {
            let fit = self.fit_corners(f, u, q, buf, glossy, start);
            *target = fit.target;
            *stat = FacetStat::from(&fit);
            *warm = glossy_normal(&fit);
            return false;
        };
        let c = quad_centre(&q);
        if let (Some(lights), Some(n)) = (skip, start) {
            if record.holds(c, lights) {
                *target = self
                    .geometry
                    .plane_target(n, self.grid.facet_vertices(f), c);
                *stat = FacetStat {
                    sse: record.sse as f64,
                    used: record.used,
                    valid: true,
                };
                return true;
            }
        }
        glossy.converged = false;
        glossy.latitude = 0.0;
        let fit = self.fit_corners(f, u, q, buf, glossy, start);
        *target = fit.target;
        *stat = FacetStat::from(&fit);
        *warm = glossy_normal(&fit);
        *record = KeptFit::of(&fit, glossy.converged, glossy.latitude, c);
        false
    }
}

/// How far a facet's centre may move, as a fraction of its reach (the distance to the camera's
/// centre or to the nearest point light, whichever is less), before its glossy fit is made
/// again (see [`LocalStep::try_run_glossy_targets`]). A fit sees the facet's centre only
/// through its light and view vectors: a move `d` turns a vector by at most `d / reach`
/// radians and changes a light's falloff by about `2 d / reach` (`(2 + mu) d / reach` for an
/// LED of anisotropy `mu`), so a kept fit's normal is about `SKIP_MOVE` radians from the fit
/// it stands for, the size of the fits' own stop ([`STEP_TOLERANCE`](crate::reflectance::STEP_TOLERANCE)).
///
/// A fit that stopped within the image noise ([`NOISE_STOP`](crate::reflectance::NOISE_STOP))
/// may move farther: by its [`latitude`](crate::reflectance::latitude) of its reach (times `2 /
/// (2 + mu)` for LEDs of anisotropy up to `mu`), the turn of its light and view vectors within
/// which a fit made again would still stop at once, at its normal (stop 50: the unit test's
/// fits with 0.5-2 % noise have latitudes 4-200 times this; on the glossy bumps at 1 MP with
/// 0.5 % noise the second local step of the finest level kept 88 % of the fits instead of 11 %).
pub const SKIP_MOVE: f64 = 1e-5;

/// What the glossy local steps of a solver keep of each facet's last glossy fit, so that a
/// facet which did not move keeps its fit instead of fitting it again (see
/// [`LocalStep::try_run_glossy_targets`]): per facet its centre at the fit, its residual and
/// its count of usable lights, its diffuse and specular albedos and its latitude (32 bytes; its normal is the solver's warm normal), and for all
/// the settings and lights the fits were made under. Only a step under the same settings and
/// lights (and the same count of facets) trusts the records. The caller clears them whenever
/// the warm normals change otherwise than by these steps (a coarser level's carried in, the
/// glossy model dropped) or the observations do.
#[derive(Debug, Default)]
pub struct KeptFits {
    /// The settings and lights of the fits; None: no record is trusted.
    under: Option<(FitSettings, Vec<Light>)>,
    /// One record a facet.
    facets: Vec<KeptFit>,
}

impl KeptFits {
    /// Forgets every record (keeps their memory).
    pub fn clear(&mut self) {
        self.under = None;
    }

    /// Whether the records stand for fits under `key` (see [`LocalStep::kept_key`]) of `n`
    /// facets.
    fn trusts(&self, key: &(FitSettings, &[Light]), n: usize) -> bool {
        self.facets.len() == n
            && self
                .under
                .as_ref()
                .is_some_and(|(settings, lights)| *settings == key.0 && lights[..] == *key.1)
    }
}

/// A facet's record in [`KeptFits`].
#[derive(Debug, Clone, Copy)]
struct KeptFit {
    /// The facet's centre at its last fit (NaN: no fit to keep).
    centre: [f32; 3],
    /// That fit's sum of squared residuals.
    sse: f32,
    /// That fit's count of usable lights.
    used: u32,
    /// That fit's diffuse albedo (grey images; the mean of the channels' otherwise).
    diffuse: f32,
    /// That fit's specular albedo.
    specular: f32,
    /// That fit's [`GlossyFit::latitude`](crate::reflectance::GlossyFit::latitude) (radians;
    /// 0: [`SKIP_MOVE`] alone).
    latitude: f32,
}

impl KeptFit {
    /// No fit to keep.
    const NONE: KeptFit = KeptFit {
        centre: [f32::NAN; 3],
        sse: f32::NAN,
        used: 0,
        diffuse: f32::NAN,
        specular: f32::NAN,
        latitude: 0.0,
    };

    /// The record of `fit`, made at centre `c`: NONE unless it is a valid glossy fit that
    /// `converged` (see [`GlossyFit::converged`](crate::reflectance::GlossyFit::converged)).
    fn of(fit: &FacetFit, converged: bool, latitude: f64, c: [f64; 3]) -> KeptFit {
        match converged && fit.valid && fit.specular.is_finite() {
            true => KeptFit {
                centre: c.map(|x| x as f32),
                sse: fit.sse as f32,
                used: fit.used,
                diffuse: (fit.albedo.iter().sum::<f64>() / 3.0) as f32,
                specular: fit.specular as f32,
                latitude: latitude as f32,
            },
            false => KeptFit::NONE,
        }
    }

    /// Whether the fit may be kept at centre `c` under `lights`: the centre moved by at most
    /// [`SKIP_MOVE`] of its reach, or by its latitude of it where that is more (times `2 / (2 +
    /// mu)` for the largest anisotropy `mu` of the lights: the falloff's change, `2 t` for a
    /// turn `t`, is then up to `(2 + mu) t` for lights within 45 degrees of their axes); false
    /// without a record (NaN).
    #[inline]
    fn holds(&self, c: [f64; 3], lights: &[Light]) -> bool {
        let d = [0, 1, 2].map(|i| c[i] - self.centre[i] as f64);
        let moved = dot(d, d);
        let mut reach = dot(c, c);
        let mut mu: f64 = 0.0;
        for light in lights {
            if let Light::Point {
                position: p, mu: m, ..
            } = light
            {
                let e = [0, 1, 2].map(|i| c[i] - p[i]);
                reach = reach.min(dot(e, e));
                mu = mu.max(*m);
            }
        }
        let turn = SKIP_MOVE.max(self.latitude as f64 * 2.0 / (2.0 + mu));
        moved <= turn * turn * reach
    }
}

/// The glossy normal of a fit to store as the next step's start (NaN where the facet has none:
/// an invalid fit, or one left Lambertian).
#[inline]
pub(crate) fn glossy_normal(fit: &FacetFit) -> [f32; 3] {
    match fit.valid && fit.specular.is_finite() {
        true => fit.normal.map(|x| x as f32),
        false => [f32::NAN; 3],
    }
}

/// A stored glossy normal as a start (None where none is stored: NaN).
#[inline]
fn warm_normal(w: &[f32; 3]) -> Option<[f64; 3]> {
    w.iter().all(|x| x.is_finite()).then(|| w.map(f64::from))
}

/// What a thread's scratch space is for, in the message of a failed allocation.
const SCRATCH: &str = "the local step's per-thread scratch space";

/// A thread's scratch space for one facet's `per` observations (and, filled on demand, its
/// observations under the glossy model).
fn facet_scratch(per: usize, settings: &FitSettings) -> Result<(Vec<f32>, Packed)> {
    Ok((try_vec(per, 0.0f32, SCRATCH)?, settings.packed()))
}

/// Whether an observation (all its channels) can be used.
#[inline]
pub(crate) fn usable(obs: &[f32], settings: &FitSettings) -> bool {
    obs.iter().all(|&v| {
        let v = v as f64;
        v > settings.dark && v < settings.saturation
    })
}

/// The observations `values` (`channels` per light) with the lights `k` for which `hide(k)`
/// holds hidden: NaN, which no fit uses ([`usable`] is false for them). The held-out checks
/// (`check`) and the lobe search's folds (`glossy`) fit without some lights this way.
pub(crate) fn hide_lights(
    values: &[f32],
    channels: usize,
    hide: impl Fn(usize) -> bool,
) -> Vec<f32> {
    let mut kept = values.to_vec();
    for (k, o) in kept.chunks_exact_mut(channels).enumerate() {
        if hide(k) {
            o.fill(f32::NAN);
        }
    }
    kept
}

fn usable_count(values: &[f32], channels: usize, settings: FitSettings) -> u32 {
    values
        .chunks_exact(channels)
        .filter(|o| usable(o, &settings))
        .count() as u32
}

/// Normal equations of one facet, per channel.
#[derive(Default)]
struct Sums {
    t: [[f64; 6]; 3],
    s: [[f64; 3]; 3],
    sum_i2: f64,
    used: u32,
    /// Of the `used` observations, those the direct light reaches (all of them without
    /// indirect light, see [`Indirect`]).
    lit: u32,
}

/// The indirect light of one facet (see [`crate::indirect`]): the model of light k becomes
/// `I = rho n . (d_k Phi_k beta_k(c) + V_k)`, `d_k` = 1 where the direct light reaches the facet
/// and 0 where it does not (a cast shadow, or the light behind the facet), so that observations
/// lit only by the surface's own light still count.
#[derive(Debug, Clone, Copy)]
pub struct Indirect<'a> {
    /// The irradiance vector `V` of each light and channel (`k * channels`, light-major).
    pub vectors: &'a [[f64; 3]],
    /// Per light: whether its direct light reaches the facet.
    pub direct: &'a [bool],
}

/// One facet's data during its fit.
struct Facet<'a> {
    c: [f64; 3],
    model: Model<'a>,
    values: &'a [f32],
    channels: usize,
    settings: FitSettings,
    /// The indirect light, added to the rows; None: none.
    indirect: Option<Indirect<'a>>,
    /// Each light's [`Model::row`] at `c`, computed once for the robust fits (their weight
    /// passes would recompute them: the near model's powers and square roots); None: computed
    /// where they are used.
    rows: Option<&'a [Row]>,
}

/// What [`Model::row`] gives for a light: `beta(c)`, its paper weight, and the intensity.
type Row = ([f64; 3], f64, [f64; 3]);

impl Facet<'_> {
    /// Light `k`'s [`Model::row`] at the facet's centre (the cached one where there is one: the
    /// same values).
    #[inline]
    fn row(&self, k: usize) -> Row {
        match self.rows {
            Some(rows) => rows[k],
            None => self.model.row(k, self.c),
        }
    }

    /// Observations per light (chunks of `channels` values).
    fn observations(&self) -> impl Iterator<Item = (usize, &[f32])> {
        self.values.chunks_exact(self.channels).enumerate()
    }

    /// [`Facet::accumulate`] for the common case, specialized: grey images, unit weights, the
    /// near-light model (the same sums, without the per-light dispatch on channels and
    /// weighting).
    #[inline]
    fn accumulate_grey(&self, lights: &[Light]) -> Sums {
        let (dark, saturation) = (self.settings.dark, self.settings.saturation);
        let mut t = [0.0f64; 6];
        let mut s = [0.0f64; 3];
        let (mut sum_i2, mut used) = (0.0, 0u32);
        for (light, &v) in lights.iter().zip(self.values) {
            let i = v as f64;
            if !(i > dark && i < saturation) {
                continue;
            }
            used += 1;
            let (b, _) = light.beta(self.c);
            let phi = light.intensity();
            let p = channel_intensity(phi, 1, 0);
            let r = [b[0] * p, b[1] * p, b[2] * p];
            t[0] += r[0] * r[0];
            t[1] += r[0] * r[1];
            t[2] += r[0] * r[2];
            t[3] += r[1] * r[1];
            t[4] += r[1] * r[2];
            t[5] += r[2] * r[2];
            s[0] += r[0] * i;
            s[1] += r[1] * i;
            s[2] += r[2] * i;
            sum_i2 += i * i;
        }
        Sums {
            t: [t, [0.0; 6], [0.0; 6]],
            s: [s, [0.0; 3], [0.0; 3]],
            sum_i2,
            used,
            lit: used,
        }
    }

    /// Accumulates the weighted normal equations with robust weights `rw(k)`.
    fn accumulate(&self, rw: impl Fn(usize) -> f64) -> Sums {
        let mut sums = Sums::default();
        for (k, o) in self.observations() {
            if !usable(o, &self.settings) {
                continue;
            }
            sums.used += 1;
            if self.indirect.is_none_or(|x| x.direct[k]) {
                sums.lit += 1;
            }
            let robust = rw(k);
            if robust == 0.0 {
                continue;
            }
            let (mut b, pw, phi) = self.row(k);
            if self.indirect.is_some_and(|x| !x.direct[k]) {
                b = [0.0; 3];
            }
            for (ch, &i) in o.iter().enumerate() {
                let i = i as f64;
                let p = channel_intensity(phi, self.channels, ch);
                let mut r = [b[0] * p, b[1] * p, b[2] * p];
                if let Some(x) = self.indirect {
                    let v = x.vectors[k * self.channels + ch];
                    r = [r[0] + v[0], r[1] + v[1], r[2] + v[2]];
                }
                let w = robust
                    * match self.settings.weighting {
                        Weighting::Image => 1.0,
                        Weighting::Paper => (pw / p) * (pw / p),
                    };
                let (t, s) = (&mut sums.t[ch], &mut sums.s[ch]);
                t[0] += w * r[0] * r[0];
                t[1] += w * r[0] * r[1];
                t[2] += w * r[0] * r[2];
                t[3] += w * r[1] * r[1];
                t[4] += w * r[1] * r[2];
                t[5] += w * r[2] * r[2];
                s[0] += w * r[0] * i;
                s[1] += w * r[1] * i;
                s[2] += w * r[2] * i;
                sums.sum_i2 += i * i;
            }
        }
        sums
    }

    /// Squared residual of light k's observation `o` (summed over channels) under the fit
    /// `(n, albedo)`, or `None` when the observation is not usable.
    fn sq_residual(&self, k: usize, o: &[f32], n: [f64; 3], albedo: [f64; 3]) -> Option<f64> {
        if !usable(o, &self.settings) {
            return None;
        }
        let (b, _, phi) = self.row(k);
        let nb = match self.indirect {
            Some(x) if !x.direct[k] => 0.0,
            _ => dot(n, b),
        };
        Some(
            o.iter()
                .enumerate()
                .map(|(ch, &i)| {
                    let p = channel_intensity(phi, self.channels, ch);
                    // (without indirect light, the operations of the vectorised lanes)
                    let e = match self.indirect {
                        None => albedo[ch] * p * nb - i as f64,
                        Some(x) => {
                            albedo[ch] * (p * nb + dot(n, x.vectors[k * self.channels + ch]))
                                - i as f64
                        }
                    };
                    e * e
                })
                .sum(),
        )
    }

    /// Robust weights (per light) of the fit `(n, albedo)`; `None` when fewer than 3 lights keep
    /// a positive weight (see [`Facet::robust_weights_into`]; this one allocates its result).
    fn robust_weights(
        &self,
        n: [f64; 3],
        albedo: [f64; 3],
        scratch: &mut Vec<f64>,
    ) -> Option<Vec<f64>> {
        let mut irls = Irls {
            sorted: std::mem::take(scratch),
            ..Irls::default()
        };
        let ok = self.robust_weights_into(n, albedo, self.max_observation(), &mut irls);
        *scratch = irls.sorted;
        ok.then_some(irls.weights)
    }

    /// The largest observation (NaN ignored), which floors the robust scale: a constant of the
    /// facet, taken once per fit.
    fn max_observation(&self) -> f64 {
        self.values.iter().fold(0.0f32, |m, v| m.max(*v)) as f64
    }

    /// Robust weights (per light) of the fit `(n, albedo)` into `irls.weights`; false when fewer
    /// than 3 lights keep a positive weight. With `e_k` the RMS residual over the channels of
    /// each usable light (`irls.rms`), the scale is `sigma = max(1.4826 median_k e_k,
    /// 1e-9 max_i, MIN_POSITIVE)` (`max_i`: [`Facet::max_observation`]) and the weight
    /// [`robust_weight`]`(e_k, sigma)`; unusable lights weigh 0. No allocation once the buffers
    /// have grown to the facet's lights.
    fn robust_weights_into(
        &self,
        n: [f64; 3],
        albedo: [f64; 3],
        max_i: f64,
        irls: &mut Irls,
    ) -> bool {
        let channels = self.channels as f64;
        let Irls {
            rms,
            sorted,
            weights,
        } = irls;
        rms.clear();
        rms.extend(self.observations().map(|(k, o)| {
            self.sq_residual(k, o, n, albedo)
                .map(|e| (e / channels).sqrt())
        }));
        sorted.clear();
        sorted.extend(rms.iter().flatten());
        let mid = sorted.len() / 2;
        let median = *sorted.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1;
        let sigma = (1.4826 * median).max(1e-9 * max_i).max(f64::MIN_POSITIVE);
        weights.clear();
        let mut positive = 0usize;
        weights.extend(rms.iter().map(|e| {
            let w = e.map_or(0.0, |e| robust_weight(self.settings.robust, e, sigma));
            positive += (w > 0.0) as usize;
            w
        }));
        positive >= 3
    }
}

/// Buffers of the robust reweighting ([`Facet::robust_weights_into`]), kept per thread across
/// facets so that the reweighting rounds allocate nothing.
#[derive(Default)]
struct Irls {
    /// RMS residual of each light (None: not usable).
    rms: Vec<Option<f64>>,
    /// The usable residuals, for the median.
    sorted: Vec<f64>,
    /// Robust weight of each light.
    weights: Vec<f64>,
}

/// Solves the accumulated system for the normal and the albedo per channel. Inlined: the
/// vectorized step calls it per lane with `channels = 1`, and a call returning its arrays through
/// memory stalled the loads that follow (store forwarding).
#[inline(always)]
fn solve_sums(sums: &Sums, channels: usize) -> Option<([f64; 3], [f64; 3], [f64; 3])> {
    let mut gs = [[0.0; 3]; 3];
    let mut tms = [Matrix3::zeros(); 3];
    for ch in 0..channels {
        let t = &sums.t[ch];
        tms[ch] = Matrix3::new(t[0], t[1], t[2], t[1], t[3], t[4], t[2], t[4], t[5]);
        let g = solve_spd3(&tms[ch], &Vector3::from(sums.s[ch]))?;
        gs[ch] = [g.x, g.y, g.z];
    }
    if channels == 1 {
        let g = gs[0];
        let rho = norm(g);
        if !(rho.is_finite() && rho > 0.0) {
            return None;
        }
        return Some(([g[0] / rho, g[1] / rho, g[2] / rho], [rho; 3], g));
    }
    let sum: [f64; 3] = std::array::from_fn(|i| gs[0][i] + gs[1][i] + gs[2][i]);
    let norm = norm(sum);
    if !(norm.is_finite() && norm > 0.0) {
        return None;
    }
    let n = sum.map(|v| v / norm);
    let nv = Vector3::from(n);
    let albedo: [f64; 3] = std::array::from_fn(|ch| {
        let den = nv.dot(&(tms[ch] * nv));
        dot(n, sums.s[ch]) / den
    });
    if !albedo.iter().all(|a| a.is_finite()) {
        return None;
    }
    Some((n, albedo, sum))
}

/// Robust weight of a residual `e` with scale `sigma` (inlined into the robust lanes,
/// `lanes::robust`, where the estimator is a constant of the loop).
#[inline(always)]
fn robust_weight(robust: Robust, e: f64, sigma: f64) -> f64 {
    match robust {
        Robust::None => 1.0,
        Robust::Cauchy => {
            let x = e / (2.385 * sigma);
            1.0 / (1.0 + x * x)
        }
        Robust::Tukey => {
            let x = e / (4.685 * sigma);
            if x < 1.0 {
                (1.0 - x * x) * (1.0 - x * x)
            } else {
                0.0
            }
        }
    }
}

/// Fits one facet with centre `c` to its observations `values` (k lights x `channels`); `None`
/// when it cannot be fitted. The target is left at zero (the caller sets it).
pub fn fit_facet(
    c: [f64; 3],
    model: Model<'_>,
    values: &[f32],
    channels: usize,
    settings: FitSettings,
) -> Option<FacetFit> {
    fit_facet_with(c, model, values, channels, settings, None)
}

/// [`fit_facet`] with the indirect light `indirect` added to the rows: the model
/// `I = rho n . (d Phi beta(c) + V)` (see [`Indirect`] and [`crate::indirect`]). None: exactly
/// [`fit_facet`].
pub fn fit_facet_with(
    c: [f64; 3],
    model: Model<'_>,
    values: &[f32],
    channels: usize,
    settings: FitSettings,
    indirect: Option<Indirect<'_>>,
) -> Option<FacetFit> {
    let facet = Facet {
        c,
        model,
        values,
        channels,
        settings,
        indirect,
        rows: None,
    };
    if settings.robust == Robust::None {
        return facet.fit();
    }
    thread_local! {
        static ROWS: std::cell::RefCell<Vec<Row>> = const { std::cell::RefCell::new(Vec::new()) };
    }
    ROWS.with_borrow_mut(|rows| {
        rows.clear();
        rows.extend((0..values.len() / channels).map(|k| model.row(k, c)));
        Facet {
            rows: Some(rows),
            ..facet
        }
        .fit()
    })
}

impl Facet<'_> {
    /// The fit of [`fit_facet_with`] (its rows cached or computed where used: the same bits).
    fn fit(&self) -> Option<FacetFit> {
        let (channels, settings) = (self.channels, self.settings);
        let sums = match self.model {
            Model::Near(lights)
                if self.indirect.is_none()
                    && channels == 1
                    && settings.weighting == Weighting::Image
                    && settings.robust == Robust::None =>
            {
                self.accumulate_grey(lights)
            }
            _ => self.accumulate(|_| 1.0),
        };
        // Rows of indirect light alone do not determine a facet: their vectors are small (a tenth of
        // the direct light or less), so with fewer than 3 directly lit observations the fit would
        // follow their noise to an albedo orders of magnitude off (a face of queau_human1, whose
        // dark threshold is 0, predicted held-out images 10^4 times too bright). Without indirect
        // light every used observation is lit.
        if sums.lit < 3 {
            return None;
        }
        let (mut n, mut albedo, g) = solve_sums(&sums, channels)?;
        if settings.robust != Robust::None {
            thread_local! {
                static IRLS: std::cell::RefCell<Irls> = std::cell::RefCell::default();
            }
            let max_i = self.max_observation();
            let mut rounds = |irls: &mut Irls| {
                for _ in 0..IRLS_ITERATIONS {
                    if !self.robust_weights_into(n, albedo, max_i, irls) {
                        break;
                    }
                    let weights = &irls.weights;
                    match solve_sums(&self.accumulate(|k| weights[k]), channels) {
                        Some((n2, a2, _)) => (n, albedo) = (n2, a2),
                        None => break,
                    }
                }
            };
            IRLS.with(|cell| match cell.try_borrow_mut() {
                Ok(mut irls) => rounds(&mut irls),
                // (not reached: no fit runs inside another on one thread)
                Err(_) => rounds(&mut Irls::default()),
            });
        }
        let unit_weights =
            settings.weighting == Weighting::Image && settings.robust == Robust::None;
        let sse = if settings.fast_residual && unit_weights && channels == 1 {
            (sums.sum_i2 - dot(g, sums.s[0])).max(0.0)
        } else {
            self.observations()
                .filter_map(|(k, o)| self.sq_residual(k, o, n, albedo))
                .sum()
        };
        Some(FacetFit {
            target: [0.0; 4],
            normal: n,
            albedo,
            specular: 0.0,
            sse,
            used: sums.used,
            valid: true,
        })
    }
}

/// Solves `T g = s` for a symmetric 3 x 3 `T`, or `None` when `T` is not (numerically) positive
/// definite: its determinant must exceed `1e-12` times the product of its diagonal (Hadamard's
/// bound), which rejects singular and nearly singular light configurations. nalgebra's closed-form
/// inverse keeps the dependency chain per facet short.
#[inline]
fn solve_spd3(t: &Matrix3<f64>, s: &Vector3<f64>) -> Option<Vector3<f64>> {
    invert_spd3(t).map(|inv| inv * s)
}

/// The inverse of a symmetric 3 x 3 `T` under the test of [`solve_spd3`].
#[inline]
pub(crate) fn invert_spd3(t: &Matrix3<f64>) -> Option<Matrix3<f64>> {
    let diag = t[(0, 0)] * t[(1, 1)] * t[(2, 2)];
    let det = t.determinant();
    if !(diag > 0.0 && det > 1e-12 * diag) {
        return None;
    }
    t.try_inverse()
}

/// [`solve_spd3`] in lanes, every lane computed: per lane of `t`, the six distinct entries of
/// `T = [[t0 t1 t2] [t1 t3 t4] [t2 t4 t5]]`, whether it passes [`invert_spd3`]'s test, its
/// inverse (row-major) and `g = T^-1 s`, with the operations of the scalar code in its order, so
/// that they agree bit for bit: nalgebra 0.34's `determinant` and `try_inverse` of a 3 x 3 matrix
/// written out (minors `M1 = m22 m33 - m32 m23`, `M2 = m21 m33 - m31 m23`, `M3 = m21 m32 - m31
/// m22`, the determinant `m11 M1 - m12 M2 + m13 M3`, each entry of the adjugate divided by it),
/// and the matrix-vector product as nalgebra sums it (column after column). Plain loops over
/// the lanes that the compiler turns into vector instructions (inlined into the SIMD kernels
/// of the local step, `lanes::solve_lanes`, and of the light pass, `refine::fit_lanes_kernel`).
#[inline(always)]
pub(crate) fn solve_spd3_lanes<const N: usize>(
    t: &[[f64; N]; 6],
    s: &[[f64; N]; 3],
) -> ([bool; N], [[f64; N]; 9], [[f64; N]; 3]) {
    let z = [0.0f64; N];
    let [m11, m12, m13, m22, m23, m33] = t;
    let (m21, m31, m32) = (m12, m13, m23);
    let (mut det, mut regular) = (z, [false; N]);
    // The adjugate, row-major (the first column holds the minors M1, -M2, M3).
    let mut adj = [z; 9];
    for l in 0..N {
        let diag = m11[l] * m22[l] * m33[l];
        let minor1 = m22[l] * m33[l] - m32[l] * m23[l];
        let minor2 = m21[l] * m33[l] - m31[l] * m23[l];
        let minor3 = m21[l] * m32[l] - m31[l] * m22[l];
        det[l] = m11[l] * minor1 - m12[l] * minor2 + m13[l] * minor3;
        regular[l] = diag > 0.0 && det[l] > 1e-12 * diag;
        adj[0][l] = minor1;
        adj[1][l] = m13[l] * m32[l] - m33[l] * m12[l];
        adj[2][l] = m12[l] * m23[l] - m22[l] * m13[l];
        adj[3][l] = -minor2;
        adj[4][l] = m11[l] * m33[l] - m31[l] * m13[l];
        adj[5][l] = m13[l] * m21[l] - m23[l] * m11[l];
        adj[6][l] = minor3;
        adj[7][l] = m12[l] * m31[l] - m32[l] * m11[l];
        adj[8][l] = m11[l] * m22[l] - m21[l] * m12[l];
    }
    let mut inverse = [z; 9];
    for (inv, adj) in inverse.iter_mut().zip(&adj) {
        for l in 0..N {
            inv[l] = adj[l] / det[l];
        }
    }
    let mut g = [z; 3];
    for (i, g) in g.iter_mut().enumerate() {
        let row = &inverse[3 * i..3 * i + 3];
        for l in 0..N {
            g[l] = row[0][l] * s[0][l] + row[1][l] * s[1][l] + row[2][l] * s[2][l];
        }
    }
    (regular, inverse, g)
}

/// The fit of a facet that cannot be fitted: it keeps its current (mean-subtracted) unknowns.
fn keep_shape(q: &[[f64; 3]; 4], u: [f64; 4], used: u32) -> FacetFit {
    let mean = 0.25 * (u[0] + u[1] + u[2] + u[3]);
    FacetFit {
        target: u.map(|v| v - mean),
        normal: quad_normal(q),
        albedo: [f64::NAN; 3],
        specular: f64::NAN,
        sse: 0.0,
        used,
        valid: false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vec3::normalize;

    /// Five isotropic unit point lights in front of a surface about 100 away.
    /// A glossy step with [`KeptFits`] keeps the fits of the facets that did not move once they
    /// converged, with the targets and statistics of fitting them again (to about the fits' own
    /// step tolerance); a move beyond [`SKIP_MOVE`], other settings or other lights make every
    /// facet fit again; the final pass keeps them too, with normals and albedos as fitted.
    #[test]
    fn glossy_steps_keep_the_fits_of_facets_that_did_not_move() {
        use crate::reflectance::{Lobe, STEP_TOLERANCE};
        type Pass = (Vec<[f64; 4]>, Vec<FacetStat>, usize);
        fn pass(
            step: &LocalStep,
            u: &[f64],
            warm: &mut [[f32; 3]],
            kept: Option<&mut KeptFits>,
        ) -> Pass {
            let n = step.grid.n_facets();
            let (mut targets, mut stats) = (vec![[0.0; 4]; n], vec![FacetStat::default(); n]);
            let skipped = step
                .try_run_glossy_targets(u, &mut targets, &mut stats, warm, kept)
                .unwrap();
            (targets, stats, skipped)
        }
        let (grid, _, geometry) = small_masked_mesh();
        let (h, w) = (grid.height, grid.width);
        let lobe = Lobe::new(0.3, 1.5);
        let normal = crate::vec3::normalize([0.1, -0.05, -1.0]);
        let lights = lights();
        let k = lights.len();
        let u: Vec<f64> = (0..grid.n_unknowns())
            .map(|v| 100.0 - 0.1 * (v % 7) as f64 + 0.05 * (v / 7) as f64)
            .collect();
        let angle = |a: [f64; 3], b: [f64; 3]| dot(a, b).clamp(-1.0, 1.0).acos();
        for seed in 0..3usize {
            // The glossy model's image of a tilted plane near `u`, with a little noise.
            let mut data = vec![f32::NAN; k * h * w];
            for p in 0..h * w {
                let x = [
                    -5.0 + 1.5 * (p % w) as f64,
                    -7.0 + 1.5 * (p / w) as f64,
                    100.0,
                ];
                for (j, light) in lights.iter().enumerate() {
                    let Light::Point { position, .. } = light else {
                        unreachable!()
                    };
                    let a = crate::vec3::sub(*position, x);
                    let d2 = dot(a, a);
                    let l = scale(a, 1.0 / d2.sqrt());
                    let noise = (((p * 31 + j * 17 + seed * 7) % 13) as f64 - 6.0) * 2e-5;
                    data[j * h * w + p] = lobe
                        .shade(normal, l, geometry.view(x))
                        .map_or(f32::NAN, |sh| {
                            ((0.6 * sh.diffuse + 0.3 * sh.specular) * 1e3 / d2 + noise) as f32
                        });
                }
            }
            let obs = Observations::from_stack(&data, k, h * w, 1);
            let n = grid.n_facets();
            let settings = FitSettings {
                lobe: Some(lobe),
                step_tolerance: STEP_TOLERANCE,
                ..FitSettings::default()
            };
            let step = LocalStep::new(&grid, &geometry, Model::Near(&lights), &obs, settings);
            let settle = |kept: &mut KeptFits| {
                let mut warm = vec![[f32::NAN; 3]; n];
                // The first pass keeps nothing (no converged fit yet).
                assert_eq!(pass(&step, &u, &mut warm, Some(kept)).2, 0);
                for _ in 0..3 {
                    pass(&step, &u, &mut warm, Some(kept));
                }
                warm
            };
            let mut kept = KeptFits::default();
            let mut warm = settle(&mut kept);
            // The same surface: the fits are kept, as fitting them again would find them.
            let refit = pass(&step, &u, &mut warm.clone(), None);
            let same = pass(&step, &u, &mut warm, Some(&mut kept));
            assert!(same.2 > n / 2, "{} of {n}", same.2);
            for f in 0..n {
                let (a, b) = (same.0[f], refit.0[f]);
                let size = 1.0 + b.iter().map(|x| x.abs()).fold(0.0, f64::max);
                assert!(
                    (0..4).all(|j| (a[j] - b[j]).abs() <= 1e-4 * size),
                    "{a:?} {b:?}"
                );
                let (s, t) = (same.1[f], refit.1[f]);
                assert_eq!((s.valid, s.used), (t.valid, t.used));
                assert!((s.sse - t.sse).abs() <= 1e-3 * t.sse + 1e-12, "{s:?} {t:?}");
            }
            // A move far below SKIP_MOVE keeps them; one far above fits every facet again.
            let moved = |d: f64| u.iter().map(|x| x + d).collect::<Vec<_>>();
            let small = pass(
                &step,
                &moved(1e-3 * SKIP_MOVE),
                &mut warm.clone(),
                Some(&mut kept),
            );
            assert_eq!(small.2, same.2);
            let far = pass(
                &step,
                &moved(1e4 * SKIP_MOVE),
                &mut warm.clone(),
                Some(&mut kept),
            );
            assert_eq!(far.2, 0);
            // The final pass keeps them too, with the normals and albedos of fitting again.
            let mut kept = KeptFits::default();
            let warm = settle(&mut kept);
            let final_step = LocalStep {
                warm: Some(&warm),
                ..step
            };
            let mut fits = vec![FacetFit::EMPTY; n];
            let mut refits = vec![FacetFit::EMPTY; n];
            let mut maps = TrustMaps::new(&grid, k, 1).unwrap();
            let mut values = vec![[f32::NAN; 2]; n];
            let kept_final = final_step
                .try_run_final(&u, 0, &mut fits, &mut values, &mut maps, Some(&kept))
                .unwrap();
            assert!(kept_final > n / 2, "{kept_final} of {n}");
            final_step.run(&u, 0, &mut refits);
            for (a, b) in fits.iter().zip(&refits) {
                assert_eq!(a.valid, b.valid);
                if a.valid {
                    assert!(
                        angle(a.normal, b.normal) < 10.0 * STEP_TOLERANCE,
                        "{a:?} {b:?}"
                    );
                    assert!((a.albedo[0] - b.albedo[0]).abs() < 1e-3 * b.albedo[0]);
                    assert!((a.specular - b.specular).abs() < 1e-3 * b.specular + 1e-6);
                }
            }
            // Other settings (another lobe, fits to their minimum) or other lights: nothing is
            // kept.
            let other_lobe = FitSettings {
                lobe: Some(Lobe::new(0.4, 1.5)),
                ..settings
            };
            let rough = LocalStep::new(&grid, &geometry, Model::Near(&lights), &obs, other_lobe);
            assert_eq!(pass(&rough, &u, &mut warm.clone(), Some(&mut kept)).2, 0);
            let mut kept = KeptFits::default();
            let warm = settle(&mut kept);
            let exact = LocalStep {
                settings: FitSettings {
                    step_tolerance: 0.0,
                    ..settings
                },
                ..step
            };
            assert!(exact.kept_key().is_none());
            let mut moved_light = lights.clone();
            moved_light[0] = Light::point([31.0, 0.0, 50.0]);
            let other = LocalStep::new(&grid, &geometry, Model::Near(&moved_light), &obs, settings);
            assert!(kept.trusts(&step.kept_key().unwrap(), n));
            assert_eq!(pass(&other, &u, &mut warm.clone(), Some(&mut kept)).2, 0);
        }
    }

    pub(crate) fn lights() -> Vec<Light> {
        [
            [30.0, 0.0, 50.0],
            [-20.0, 25.0, 40.0],
            [-10.0, -30.0, 60.0],
            [5.0, 5.0, 20.0],
            [0.0, -40.0, 45.0],
        ]
        .into_iter()
        .map(Light::point)
        .collect()
    }

    /// The final pass of the vectorized accumulation over every facet of `step` (which must
    /// take it: [`LocalStep::final_lane_lights`]), as the solver runs it
    /// ([`LocalStep::try_run_final_lanes`] with each chunk copied into its part of two
    /// facet-long buffers; under the glossy model the fits of [`LocalStep::try_run_kept`]
    /// follow): the fits and the trust maps.
    pub(crate) fn lane_final_pass(
        step: &LocalStep<'_>,
        u: &[f64],
        kept: Option<&KeptFits>,
    ) -> (Vec<FacetFit>, TrustMaps) {
        let (lights, fitted) = step.final_lane_lights().unwrap();
        let n = step.grid.n_facets();
        let mut fits = vec![FacetFit::EMPTY; n];
        let mut trust = vec![[f32::NAN; 2]; n];
        let views: Vec<_> = fits
            .chunks_mut(FINAL_LANE_CHUNK)
            .zip(trust.chunks_mut(FINAL_LANE_CHUNK))
            .collect();
        assert_eq!(views.len(), lanes::final_chunks(n));
        let write = |(fits, trust): (&mut [FacetFit], &mut [[f32; 2]]),
                     _: usize,
                     chunk_fits: &[FacetFit],
                     chunk_trust: &[[f32; 2]]| {
            if fitted {
                fits.copy_from_slice(chunk_fits);
            }
            trust.copy_from_slice(chunk_trust);
        };
        let sums = step
            .try_run_final_lanes(&lights, u, fitted, views, &write)
            .unwrap();
        let mut maps = TrustMaps::new(step.grid, step.obs.k, step.obs.channels).unwrap();
        maps.add(sums);
        maps.scatter(step.grid, 0, &trust);
        if !fitted {
            step.try_run_kept(u, 0, &mut fits, kept).unwrap();
        }
        (fits, maps)
    }

    /// A 9 x 7 grid without every fifth pixel (from the third) under an orthographic camera,
    /// and its geometry: the small mesh on which lane and scalar paths are compared.
    pub(crate) fn small_masked_mesh() -> (Grid, crate::rig::Camera, Geometry) {
        let (h, w) = (9, 7);
        let mask: Vec<bool> = (0..h * w).map(|p| p % 5 != 2).collect();
        let grid = Grid::new(h, w, Some(&mask)).unwrap();
        let camera = crate::rig::Camera::Orthographic {
            pixel_size: [1.5, 1.5],
            origin: [-5.0, -7.0],
        };
        let geometry = Geometry::new(&camera, &grid).unwrap();
        (grid, camera, geometry)
    }

    /// A tilted facet centre 100 away and its exact images for albedo (2e4, 1e4, 5e3).
    fn facet(channels: usize) -> ([f64; 3], [f64; 3], Vec<f32>) {
        let c = [1.0, -2.0, 100.0];
        let n = normalize([0.3, -0.2, -1.0]);
        let rho = [2.0e4, 1.0e4, 5.0e3];
        let mut images = Vec::new();
        for l in lights() {
            let (b, _) = l.beta(c);
            for r in &rho[..channels] {
                images.push((r * dot(n, b).max(0.0)) as f32);
            }
        }
        (c, n, images)
    }

    fn angle(a: [f64; 3], b: [f64; 3]) -> f64 {
        dot(a, b).clamp(-1.0, 1.0).acos().to_degrees()
    }

    /// Under the glossy model the final pass takes its trust maps from the Lambertian lanes
    /// ([`LocalStep::try_run_final_lanes`]): its fits are the glossy fits of
    /// [`LocalStep::run`] (from warm normals where the facets have them), its per-facet trust
    /// values those of the scalar [`LocalStep::trust`] bit for bit and its per-light sums the
    /// same up to their order; with a robust estimator (no lanes) the scalar path
    /// ([`LocalStep::try_run_final`], in two chunks, one not a multiple of the lanes) gives
    /// the same.
    #[test]
    fn a_glossy_final_pass_takes_the_trust_maps_from_the_lanes() {
        use crate::reflectance::Lobe;
        let (grid, _, geometry) = small_masked_mesh();
        let (h, w) = (grid.height, grid.width);
        let lights = lights();
        let k = lights.len();
        let u: Vec<f64> = (0..grid.n_unknowns())
            .map(|v| 100.0 + 0.3 * (v % 8) as f64 - 0.2 * (v / 8) as f64)
            .collect();
        // A diffuse part and a highlight where a light mirrors into the view, then dark, missing
        // and saturated observations here and there.
        let mut data = vec![0.0f32; k * h * w];
        for (i, x) in data.iter_mut().enumerate() {
            *x = match i % 23 {
                0 => 0.0,
                7 => f32::NAN,
                11 => f32::INFINITY,
                j => 1e-4 * (1.0 + (j % 5) as f32) + if i % 29 == 3 { 5e-3 } else { 0.0 },
            };
        }
        let obs = Observations::from_stack(&data, k, h * w, 1);
        let n = grid.n_facets();
        let warm: Vec<[f32; 3]> = (0..n)
            .map(|f| match f % 3 {
                0 => [f32::NAN; 3],
                _ => [0.05 * (f % 4) as f32, -0.1, -1.0],
            })
            .collect();
        for robust in [Robust::None, Robust::Tukey] {
            let step = LocalStep {
                warm: Some(&warm),
                ..LocalStep::new(
                    &grid,
                    &geometry,
                    Model::Near(&lights),
                    &obs,
                    FitSettings {
                        lobe: Some(Lobe::new(0.3, 1.5)),
                        robust,
                        ..FitSettings::default()
                    },
                )
            };
            assert!(step.lane_lights().is_none());
            let lambertian = LocalStep {
                settings: FitSettings {
                    lobe: None,
                    ..step.settings
                },
                ..step
            };
            assert_eq!(lambertian.lane_lights().is_some(), robust == Robust::None);
            let mut fits = vec![FacetFit::EMPTY; n];
            step.run(&u, 0, &mut fits);
            assert!(fits.iter().filter(|f| f.valid && f.specular > 0.0).count() > n / 4);
            let expected = step.trust(&u).unwrap();
            assert_eq!(step.final_lane_lights().is_some(), robust == Robust::None);
            let (final_fits, maps) = match step.final_lane_lights() {
                Some(_) => lane_final_pass(&step, &u, None),
                None => {
                    let mut maps = TrustMaps::new(&grid, k, 1).unwrap();
                    let mut final_fits = vec![FacetFit::EMPTY; n];
                    let mut values = vec![[f32::NAN; 2]; n];
                    let split = 13;
                    for (first, end) in [(0, split), (split, n)] {
                        let (fits, values) = (&mut final_fits[first..end], &mut values[first..end]);
                        step.try_run_final(&u, first, fits, values, &mut maps, None)
                            .unwrap();
                        maps.scatter(&grid, first, values);
                    }
                    (final_fits, maps)
                }
            };
            assert_eq!(final_fits, fits);
            let trust = maps.finish();
            trust.assert_matches(&expected);
            assert!(trust.held_out.iter().filter(|v| v.is_finite()).count() > n / 2);
        }
    }

    /// Precomputed depths (pinhole: log-depth unknowns) give the same fits as the unknowns.
    #[test]
    fn precomputed_depths_change_nothing() {
        use crate::rig::Camera;
        let (h, w) = (6, 9);
        let grid = Grid::new(h, w, None).unwrap();
        let camera = Camera::Pinhole {
            k: [[50.0, 0.0, 4.0], [0.0, 50.0, 3.0], [0.0, 0.0, 1.0]],
            distortion: [0.0; 5],
        };
        let geometry = Geometry::new(&camera, &grid).unwrap();
        let lights = lights();
        let k = lights.len();
        let u: Vec<f64> = (0..grid.n_unknowns())
            .map(|i| (100.0 + 0.1 * (i % 7) as f64).ln())
            .collect();
        let data: Vec<f32> = (0..k * h * w)
            .map(|i| 1e-4 * (1.0 + ((i * 13) % 7) as f32))
            .collect();
        let obs = Observations::from_stack(&data, k, h * w, 1);
        let z: Vec<f64> = u.iter().map(|&x| geometry.depth(x)).collect();
        let n = grid.n_facets();
        let mut results = Vec::new();
        for depths in [None, Some(&z[..])] {
            let step = LocalStep {
                depths,
                ..LocalStep::new(
                    &grid,
                    &geometry,
                    Model::Near(&lights),
                    &obs,
                    FitSettings {
                        fast_residual: true,
                        ..FitSettings::default()
                    },
                )
            };
            let mut targets = vec![[0.0; 4]; n];
            let mut stats = vec![FacetStat::default(); n];
            step.run_targets(&u, &mut targets, &mut stats);
            results.push((targets, stats));
        }
        assert_eq!(results[0], results[1]);
    }

    #[test]
    fn exact_images_give_the_exact_normal() {
        let l = lights();
        for channels in [1, 3] {
            let (c, n, images) = facet(channels);
            for weighting in [Weighting::Image, Weighting::Paper] {
                for robust in [Robust::None, Robust::Cauchy, Robust::Tukey] {
                    let settings = FitSettings {
                        weighting,
                        robust,
                        ..FitSettings::default()
                    };
                    let fit = fit_facet(c, Model::Near(&l), &images, channels, settings).unwrap();
                    assert_eq!(fit.used, 5);
                    assert!(
                        angle(fit.normal, n) < 1e-4,
                        "{channels} {weighting:?} {robust:?}"
                    );
                    assert!((fit.albedo[0] / 2.0e4 - 1.0).abs() < 1e-5);
                    if channels == 3 {
                        assert!((fit.albedo[2] / 5.0e3 - 1.0).abs() < 1e-5);
                    }
                }
            }
        }
    }

    #[test]
    fn robust_fit_ignores_a_highlight() {
        let l = lights();
        let mut more = l.clone();
        more.extend(
            [[15.0, 15.0, 30.0], [-25.0, -5.0, 35.0], [10.0, -20.0, 25.0]].map(Light::point),
        );
        let c = [1.0, -2.0, 100.0];
        let n = normalize([0.3, -0.2, -1.0]);
        let mut images: Vec<f32> = more
            .iter()
            .map(|l| (2.0e4 * dot(n, l.beta(c).0)) as f32)
            .collect();
        images[3] *= 3.0;
        let plain = fit_facet(c, Model::Near(&more), &images, 1, FitSettings::default()).unwrap();
        let robust = FitSettings {
            robust: Robust::Tukey,
            ..FitSettings::default()
        };
        let fixed = fit_facet(c, Model::Near(&more), &images, 1, robust).unwrap();
        assert!(angle(plain.normal, n) > 1.0);
        assert!(angle(fixed.normal, n) < 1e-3, "{}", angle(fixed.normal, n));
    }

    #[test]
    fn robust_fits_with_rows_computed_once_are_the_same_bits() {
        // The robust fits take each light's row from a per-facet cache; computed where used,
        // as before, they give the same fit bit for bit (colour, paper weights, a highlight).
        let mut l = lights();
        l.extend([[15.0, 15.0, 30.0], [-25.0, -5.0, 35.0]].map(Light::point));
        let c = [1.0, -2.0, 100.0];
        let n = normalize([0.3, -0.2, -1.0]);
        for channels in [1, 3] {
            let mut images: Vec<f32> = l
                .iter()
                .flat_map(|l| {
                    let v = 2.0e4 * dot(n, l.beta(c).0);
                    (0..channels).map(move |ch| (v * (1.0 + 0.1 * ch as f64)) as f32)
                })
                .collect();
            images[3 * channels] *= 2.5;
            images[1] *= 1.1;
            for weighting in [Weighting::Image, Weighting::Paper] {
                for robust in [Robust::Cauchy, Robust::Tukey] {
                    let settings = FitSettings {
                        weighting,
                        robust,
                        ..FitSettings::default()
                    };
                    let model = Model::Near(&l);
                    let cached = fit_facet(c, model, &images, channels, settings).unwrap();
                    let each = Facet {
                        c,
                        model,
                        values: &images,
                        channels,
                        settings,
                        indirect: None,
                        rows: None,
                    }
                    .fit()
                    .unwrap();
                    assert_eq!(
                        cached.normal.map(f64::to_bits),
                        each.normal.map(f64::to_bits)
                    );
                    assert_eq!(
                        cached.albedo.map(f64::to_bits),
                        each.albedo.map(f64::to_bits)
                    );
                    assert_eq!(cached.sse.to_bits(), each.sse.to_bits());
                }
            }
        }
    }

    /// The robust fit as it was before its buffers were kept per thread: every round's
    /// weights freshly allocated, the scale's floor taken each round, then the residual.
    fn robust_fit_allocating(facet: &Facet) -> Option<([f64; 3], [f64; 3], f64)> {
        let sums = facet.accumulate(|_| 1.0);
        if sums.lit < 3 {
            return None;
        }
        let (mut n, mut albedo, _) = solve_sums(&sums, facet.channels)?;
        for _ in 0..IRLS_ITERATIONS {
            let Some(w) = facet.robust_weights(n, albedo, &mut Vec::new()) else {
                break;
            };
            let Some((n2, a2, _)) = solve_sums(&facet.accumulate(|k| w[k]), facet.channels) else {
                break;
            };
            (n, albedo) = (n2, a2);
        }
        let sse = facet
            .observations()
            .filter_map(|(k, o)| facet.sq_residual(k, o, n, albedo))
            .sum();
        Some((n, albedo, sse))
    }

    #[test]
    fn robust_fits_with_buffers_kept_per_thread_are_the_same_bits() {
        // The robust rounds reuse one thread's buffers from facet to facet; fitted in sequence
        // on one thread, with the number of lights going up and down (so that a longer facet's
        // leftovers sit in the buffers), noisy, with a highlight and a shadow, grey and colour,
        // both weightings and both estimators, they give the bits of fresh buffers.
        let mut l = lights();
        l.extend([[15.0, 15.0, 30.0], [-25.0, -5.0, 35.0], [5.0, -30.0, 25.0]].map(Light::point));
        let c = [1.0, -2.0, 100.0];
        let mut uniform = crate::multigrid::tests::lcg(0x2545_f491_4f6c_dd1d);
        let mut cases = 0;
        for seed in 0..12 {
            let lights = &l[..[l.len(), 5, l.len() - 1][seed % 3]];
            let n = normalize([0.3 - 0.05 * seed as f64, -0.2, -1.0]);
            let noise = [0.0, 1e-3, 1e-2][(seed / 3) % 3];
            for channels in [1, 3] {
                let mut images: Vec<f32> = lights
                    .iter()
                    .flat_map(|l| {
                        let v = 2.0e4 * dot(n, l.beta(c).0);
                        (0..channels)
                            .map(|ch| v * (1.0 + 0.1 * ch as f64))
                            .collect::<Vec<_>>()
                    })
                    .map(|v| (v * (1.0 + noise * (2.0 * uniform() - 1.0))) as f32)
                    .collect();
                images[(seed % lights.len()) * channels] *= 2.5;
                images[((seed + 3) % lights.len()) * channels] = 0.0;
                for weighting in [Weighting::Image, Weighting::Paper] {
                    for robust in [Robust::Cauchy, Robust::Tukey] {
                        let settings = FitSettings {
                            weighting,
                            robust,
                            ..FitSettings::default()
                        };
                        let model = Model::Near(lights);
                        let fit = fit_facet(c, model, &images, channels, settings);
                        let facet = Facet {
                            c,
                            model,
                            values: &images,
                            channels,
                            settings,
                            indirect: None,
                            rows: None,
                        };
                        let case = format!("{seed} {channels} {weighting:?} {robust:?}");
                        let Some((n, albedo, sse)) = robust_fit_allocating(&facet) else {
                            assert!(fit.is_none(), "{case}");
                            continue;
                        };
                        let fit = fit.unwrap();
                        assert_eq!(fit.normal.map(f64::to_bits), n.map(f64::to_bits), "{case}");
                        assert_eq!(
                            fit.albedo.map(f64::to_bits),
                            albedo.map(f64::to_bits),
                            "{case}"
                        );
                        assert_eq!(fit.sse.to_bits(), sse.to_bits(), "{case}");
                        cases += 1;
                    }
                }
            }
        }
        assert!(cases >= 90, "{cases} fitted");
    }

    #[test]
    fn shadowed_and_saturated_observations_are_left_out() {
        let l = lights();
        let (c, _, mut images) = facet(1);
        images[0] = 0.0;
        images[1] = -1.0;
        images[2] = f32::NAN;
        assert!(fit_facet(c, Model::Near(&l), &images, 1, FitSettings::default()).is_none());
        assert_eq!(usable_count(&images, 1, FitSettings::default()), 2);
        let (c, _, images) = facet(1);
        let saturation = FitSettings {
            saturation: images[2] as f64,
            ..FitSettings::default()
        };
        let fit = fit_facet(c, Model::Near(&l), &images, 1, saturation).unwrap();
        assert_eq!(fit.used, 4);
    }

    #[test]
    fn fast_residual_matches_the_exact_one_on_noisy_data() {
        let l = lights();
        let (c, _, images) = facet(1);
        let noisy: Vec<f32> = images
            .iter()
            .enumerate()
            .map(|(k, &v)| v * (1.0 + 0.02 * (k as f32 - 1.5)))
            .collect();
        let fast = FitSettings {
            fast_residual: true,
            ..FitSettings::default()
        };
        let a = fit_facet(c, Model::Near(&l), &noisy, 1, fast).unwrap();
        let b = fit_facet(c, Model::Near(&l), &noisy, 1, FitSettings::default()).unwrap();
        assert!(b.sse > 0.0 && (a.sse / b.sse - 1.0).abs() < 1e-6);
    }

    #[test]
    fn invalid_facets_keep_their_shape() {
        let q = [
            [0.0, 0.0, 1.0],
            [1.0, 0.0, 2.0],
            [0.0, 1.0, 3.0],
            [1.0, 1.0, 5.0],
        ];
        let fit = keep_shape(&q, [1.0, 2.0, 3.0, 5.0], 2);
        assert!(!fit.valid && fit.albedo[0].is_nan() && fit.rms(1).is_nan());
        assert_eq!(fit.target, [-1.75, -0.75, 0.25, 2.25]);
    }
}
