//! Self-calibration of the lights inside the reconstruction: per-light intensities and point-light
//! positions refined from the images themselves.
//!
//! # The light step
//! With the facet centres `c_f` fixed (the current mesh), facet f and channel ch predict
//! `I_{i,f} = a_{i,f} . g_f` with `a_{i,f} = Phi_{i,ch} beta_i(c_f; theta_i)` (see
//! [`Light::beta`]) and a free scaled normal `g_f = rho_f n_f` per facet and channel. The light
//! parameters `theta` (per light: the log-intensity factor `s_i`, `Phi_i <- e^{s_i} Phi_i`, and/or
//! the position `p_i`) minimise
//!
//! ```text
//! E(theta) = 1/2 sum_f min_g sum_i (I_{i,f} - a_{i,f}(theta) . g)^2 / sigma^2
//!          + 1/2 w sum_i |p_i - p_i^0|^2 / D^2
//! ```
//!
//! over the usable observations: a Gaussian likelihood with the noise variance `sigma^2`
//! estimated from the residual of the fits (at least [`NOISE_FLOOR`] of the RMS observation) and
//! a Gaussian prior of standard deviation `D / sqrt(w)` on every coordinate of a light position
//! (`D` is the mean depth of the surface; `p^0` the rig's positions; `w` the prior weight, default
//! 1000: about 3 % of the working distance). The
//! normals are eliminated per facet (variable projection): the Gauss-Newton matrix of the full
//! problem in `(theta, g_1..g_F)` has 3 x 3 blocks `T_f = sum_i a_i a_i^T` for the normals, and its
//! Schur complement on `theta` is
//!
//! ```text
//! H = sum_f sum_{i,i'} d_i d_{i'}^T (delta_{ii'} - a_i^T T_f^{-1} a_{i'}),   d_i = d(a_i . g_f)/d theta_i
//! ```
//!
//! with gradient `sum_f sum_i -d_i r_i` (the normals' gradient vanishes at their least-squares
//! fit). `d(a.g)/ds_i = a_i . g`; for a point light `beta = f(v) v`, `v = p - c`,
//! `f = t^mu / |v|^3`, `t = -v . axis / |v|`, so `d(beta . g)/dp = f g + (v . g) grad f` with
//! `grad f = mu t^(mu-1) (-axis / |v| + (v . axis) v / |v|^3) / |v|^3 - 3 t^mu v / |v|^5`.
//!
//! One damped (Levenberg-Marquardt) step `(H + lambda diag H) delta = -grad` is taken per
//! iteration of the solver, accepted only when it lowers `E` at the current mesh (else `lambda`
//! grows and the step is retried). Because the normals are free in this step, the lights feel the
//! mesh only through the facet positions, a weak coupling: this is not the slow alternation that
//! fits the lights to the mesh's own normals.
//!
//! # Under the glossy model
//! With the glossy model's lobe in the settings ([`FitSettings::lobe`]) and the facets' normals of
//! the last glossy local step ([`LightData::normals`]), the light step stays the Lambertian one
//! above, on corrected observations: each facet predicts its image from its glossy normal `n`
//! (held in the step) under the step's current lights,
//! `I_i = Phi_i a_i (rho_d D_i(n) + rho_s S_i(n))` (see [`crate::reflectance`]), with the
//! least-squares albedos `rho_d`, `rho_s >= 0` at `n`; an observation enters as
//! `(I_i - Phi_i a_i rho_s S_i(n)) (n . l_i) / D_i(n)`: its predicted specular part subtracted
//! and its diffuse part turned Lambertian (the Fresnel transmittance divided out), so that
//! `a_i . g` fits it. Observations whose predicted specular share `rho_s S_i / (rho_d D_i +
//! rho_s S_i)` exceeds [`MAX_SPECULAR_SHARE`] are left out: there a small error of the normal is
//! a large error of the prediction. The corrections are held during a step (its trial lights
//! compare the same observations). A facet without a glossy normal (the first iteration of a
//! run, a failed glossy fit) enters uncorrected: the first step of a run is the Lambertian one,
//! which takes the lights most of the way (waiting for the glossy normals instead measured
//! worse: 0.04-0.07 % intensity error on bumps, and 6-8 degrees on a sphere). The glossy normals
//! are the per-facet fits, which depend on the mesh only through the facet positions; the mesh's
//! own normals, tried first, failed on a sphere started from a plane (no intensity refined at
//! all). Without this the highlights and the
//! non-Lambertian diffuse fall-off bend the lights: see the CHANGELOG and the tests
//! (`tests/test_glossy_lights.py`) for the measurements.
//!
//! # With interreflections
//! With a field of indirect light (the local steps' one, see [`crate::indirect`]), each light's
//! row at a facet is its direct row plus the facet's indirect irradiance vector of that light and
//! channel, `a_{i,f} = Phi_{i,ch} beta_i(c_f; theta_i) + V_{i,f,ch}`, as in the local step's fits.
//! The field is gathered from the observed images (they emit), not from the light model, so it is
//! a constant of the step: the derivatives `d(a . g)/d theta` are those of the direct part alone
//! (`d(a . g)/ds_i = Phi_i beta_i . g`), while the normals' elimination (`T_f`, the residuals)
//! uses the whole rows. Observations of lights behind the facet (see
//! [`crate::local::IndirectLight::is_unlit`]), which carry no direct light, are left out. Without
//! the field the indirect light the images hold bends the lights (the lights brighten where the
//! surface looks at itself).
//!
//! # What the images determine
//! - A common factor of all intensities is the albedo's: the step keeps `sum_i s_i = 0`, i.e. the
//!   geometric mean of the rig's intensities (a linear constraint of the step). With indirect
//!   light the images do tell the common factor (it scales the direct light against the
//!   indirect, which the observed images emit), weakly where the indirect share is small; the
//!   step still holds it at the rig's: the interreflection model takes the rig's intensities
//!   as calibrated.
//! - A common scale of all light positions about the camera centre trades against the working
//!   distance (scaling the whole scene by `k` scales every image by `1/k^2`, absorbed by the
//!   albedo). With a given distance the gauge fixes it; with an estimated distance
//!   ([`Refine::fix_scale`]) the step keeps `sum_i p_i^0 . (p_i - p_i^0) = 0`: the rig's scale.
//! - With only directional lights, intensities need 4 or more lights in general position;
//!   directional lights have no position to refine.
//!
//! # The pass over the facets
//! A pass sums the objective, the gradient and the Gauss-Newton matrix over a regular subsample
//! of the facets ([`MAX_FACETS`]). The lights' `beta` vectors and the position derivatives'
//! terms of `LANES` (8) facets are computed at once, one SIMD lane per facet
//! ([`crate::light::LaneLight::step_terms`], bit for bit the scalar model's). With grey
//! images, the Lambertian model and no indirect light the rest of a facet (its normal's fit,
//! residuals, Jacobian rows and, for the facets of the Gauss-Newton matrix, the Cholesky
//! rows) runs in lanes too (`fit_lanes_kernel`: the scalar operations per lane, the matrix
//! the same bits), the residuals' and gradient's sums kept per lane through a chunk;
//! otherwise it is scalar. The facets are summed in fixed chunks, one thread each, and the
//! chunks' sums added in order, so that a pass gives the same bits whatever the threads do
//! (`MAX_CHUNKS`).
//!
//! [`conditioning`] reports the singular values of the light block after the normals are
//! eliminated and the standard error of every parameter.

use nalgebra::{DMatrix, DVector, Matrix3, Vector3};
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::geometry::quad_centre;
use crate::geometry::Geometry;
use crate::grid::Grid;
use crate::light::{derivatives, Gradient, LaneLight};
use crate::local::{
    channel_intensity, invert_spd3, usable, FitSettings, IndirectLight, Observations,
};
use crate::memory::{try_vec, try_with_capacity};
use crate::options::Refine;
use crate::problem::Problem;
use crate::reflectance::Lobe;
use crate::rig::Light;
use crate::vec3::{dot, norm, sub};

/// At most this many facets (a regular subsample) enter a light step: the light parameters are
/// few (at 1 % image noise and 27 lights, 32 768 facets determine each intensity to about
/// 0.05 %), and this bounds the step's cost at camera resolution.
pub const MAX_FACETS: usize = 1 << 15;

/// At most this many facets (a regular subsample of those of a pass) enter the Gauss-Newton
/// matrix, whose cost per facet grows with the square of the light parameters; the gradient and
/// the objective use every facet of the pass, so the fixed point is exact.
pub const MAX_MATRIX_FACETS: usize = 4096;

/// Smallest noise level assumed by the prior, relative to the RMS observation: with exact
/// images the prior still holds the weak directions of the lights.
pub const NOISE_FLOOR: f64 = 1e-3;

/// Under the glossy model, observations whose predicted specular share (of the predicted
/// image) is above this are left out of the light step (see the module documentation).
pub const MAX_SPECULAR_SHARE: f64 = 0.1;

/// At most this many `beta` vectors (facets of a pass times lights, 24 bytes each: 24 MB) are
/// kept through a light step that does not move the lights (intensities only): its passes
/// (the Gauss-Newton one and the trial ones) then evaluate `beta` once per facet and light
/// instead of once per pass, facet, channel and use. Above it each pass evaluates them again.
pub const MAX_CACHED_BETAS: usize = 1 << 20;

/// Fails when `refine` is active with fewer than 4 lights: 3 observations per pixel fit any
/// lights exactly, so the images say nothing about them.
pub fn check_refinable(refine: &Refine, lights: usize) -> Result<()> {
    if refine.is_active() && lights < 4 {
        return Err(Error::Unusable(format!(
            "refining the lights needs at least 4 lights: with {lights}, every light configuration fits \
             the images exactly"
        )));
    }
    Ok(())
}

/// Where each light's parameters sit in the parameter vector.
#[derive(Debug, Clone)]
struct Layout {
    /// Index of light i's intensity parameter.
    intensity: Vec<Option<usize>>,
    /// Index of light i's first position parameter (x, y, z follow).
    position: Vec<Option<usize>>,
    n: usize,
}

impl Layout {
    fn new(lights: &[Light], refine: &Refine) -> Layout {
        let mut n = 0;
        let mut intensity = Vec::with_capacity(lights.len());
        let mut position = Vec::with_capacity(lights.len());
        for light in lights {
            intensity.push(refine.intensity.then(|| {
                n += 1;
                n - 1
            }));
            let point = matches!(light, Light::Point { .. });
            position.push((refine.position && point).then(|| {
                n += 3;
                n - 3
            }));
        }
        Layout {
            intensity,
            position,
            n,
        }
    }

    /// First index and number of light i's parameters (they are contiguous).
    fn span(&self, i: usize) -> (usize, usize) {
        let first = self.intensity[i].or(self.position[i]).unwrap_or(0);
        let m = self.intensity[i].is_some() as usize + 3 * self.position[i].is_some() as usize;
        (first, m)
    }

    /// The linear constraints of a step, as columns: the intensity gauge and, if asked, the
    /// common scale of the positions about the camera centre, `sum_i p_i^0 . delta p_i = 0` with
    /// the `reference` (rig's) positions: fixed coefficients, so every step and every affine
    /// combination of iterates keeps `sum_i p_i^0 . (p_i - p_i^0) = 0`.
    fn constraints(&self, lights: &[Light], fix_scale: bool) -> Vec<DVector<f64>> {
        let mut out = Vec::new();
        if self.intensity.iter().any(Option::is_some) {
            let mut c = DVector::zeros(self.n);
            for j in self.intensity.iter().flatten() {
                c[*j] = 1.0;
            }
            out.push(c);
        }
        if fix_scale && self.position.iter().any(Option::is_some) {
            let mut c = DVector::zeros(self.n);
            for (light, j) in lights.iter().zip(&self.position) {
                if let (Light::Point { position, .. }, Some(j)) = (light, j) {
                    for a in 0..3 {
                        c[j + a] = position[a];
                    }
                }
            }
            out.push(c);
        }
        out
    }
}

/// The observations and mesh a light step works on.
#[derive(Clone, Copy)]
pub struct LightData<'a> {
    /// The mesh.
    pub grid: &'a Grid,
    /// Vertex positions.
    pub geometry: &'a Geometry,
    /// The images.
    pub obs: &'a Observations<'a>,
    /// Shadow and saturation thresholds.
    pub settings: FitSettings,
    /// Under the glossy model (`settings.lobe`), each facet's normal of the last glossy fit
    /// (NaN: none), from which its specular part is predicted; a facet without one (or all,
    /// without these) enters with its observations as they are (the Lambertian light step).
    pub normals: Option<&'a [[f32; 3]]>,
    /// The cast shadows the local steps use (see [`crate::Options::shadows`]): shadowed
    /// observations are left out of the light step too.
    pub shadows: Option<&'a crate::shadow::ShadowMask>,
    /// The field of indirect light the local steps use (see the module documentation, "With
    /// interreflections"; Lambertian model only): added to each light's row.
    pub indirect: Option<&'a dyn IndirectLight>,
}

/// The lights of a pass and where their parameters sit.
#[derive(Clone, Copy)]
struct Model<'a> {
    lights: &'a [Light],
    layout: &'a Layout,
    /// The lights that predict the specular part under the glossy model (the step's current
    /// lights: one step's passes compare the same corrected observations).
    shading: &'a [Light],
    /// Whether `shading` has the positions of `lights` (then its `beta` vectors are theirs).
    same_positions: bool,
}

/// The `beta` vector of each light at a facet's centre (see [`Light::beta`]): the only part
/// of the model that costs a power per observation (LEDs), computed once per facet of a pass
/// and shared by its channels and the glossy correction.
type Betas = [[f64; 3]];

/// Sums of one pass over the facets.
#[derive(Debug, Clone)]
struct Pass {
    /// Gauss-Newton matrix (upper triangle filled during the pass), n x n row-major.
    h: Vec<f64>,
    grad: Vec<f64>,
    sse: f64,
    sum_i2: f64,
    /// Usable observations (lights x channels) of fitted facets.
    count: usize,
    /// Facet-channel fits (each has 3 unknowns).
    fits: usize,
    sum_z: f64,
    min_z: f64,
    facets: usize,
}

/// What the pass's buffers are for, in the message of a failed allocation.
const PASS: &str = "the light refinement's Gauss-Newton sums";

impl Pass {
    /// Empty sums (without the matrix and the gradient unless `with_h`).
    fn try_new(n: usize, with_h: bool) -> Result<Pass> {
        let mut pass = Pass::empty();
        if with_h {
            pass.h = try_vec(n * n, 0.0, PASS)?;
            pass.grad = try_vec(n, 0.0, PASS)?;
        }
        Ok(pass)
    }

    /// Empty sums without the matrix and the gradient (the identity of [`Pass::merge`]).
    fn empty() -> Pass {
        Pass {
            h: Vec::new(),
            grad: Vec::new(),
            sse: 0.0,
            sum_i2: 0.0,
            count: 0,
            fits: 0,
            sum_z: 0.0,
            min_z: f64::INFINITY,
            facets: 0,
        }
    }

    /// The sums of both passes (an [`Pass::empty`] one adds nothing and has no matrix).
    fn merge(mut self, mut other: Pass) -> Pass {
        if self.h.len() < other.h.len() {
            std::mem::swap(&mut self.h, &mut other.h);
        }
        if self.grad.len() < other.grad.len() {
            std::mem::swap(&mut self.grad, &mut other.grad);
        }
        for (a, b) in self.h.iter_mut().zip(&other.h) {
            *a += b;
        }
        for (a, b) in self.grad.iter_mut().zip(&other.grad) {
            *a += b;
        }
        self.sse += other.sse;
        self.sum_i2 += other.sum_i2;
        self.count += other.count;
        self.fits += other.fits;
        self.sum_z += other.sum_z;
        self.min_z = self.min_z.min(other.min_z);
        self.facets += other.facets;
        self
    }
}

/// `(Phi a D, Phi a S, (n . l) / D, I)` of an observation under the glossy model (see
/// [`LightData::glossy`]).
type GlossyTerms = (f64, f64, f64, f64);

/// Per-thread scratch of a pass.
struct Scratch {
    values: Vec<f32>,
    used: Vec<usize>,
    rows: Vec<[f64; 3]>,
    obs: Vec<f64>,
    /// Under the glossy model, per light: the observation's correction `(offset, factor)`
    /// (`I' = (I - offset) * factor`), None where it is left out (see [`LightData::glossy`]).
    glossy: Vec<Option<(f64, f64)>>,
    /// Under the glossy model, per light: the terms of [`LightData::glossy`].
    terms: Vec<Option<GlossyTerms>>,
    /// With a field of indirect light: the facet's vectors `V`, one per light and channel
    /// (light-major; see [`LightData::indirect`]).
    indirect: Vec<[f64; 3]>,
    /// Rows of `B^T` (see [`LightData::facet`]) of the last facets, three per facet, folded
    /// into the pass by one matrix product every [`BATCH`] facets.
    bt: DMatrix<f64>,
    /// `B B^T` of a flush (n x n; empty without the matrix).
    product: DMatrix<f64>,
    pending: usize,
    /// Whether the current facet adds to the Gauss-Newton matrix.
    want_h: bool,
}

/// Up to this many rows of `B^T` (nalgebra's `SMALL_DIM`), [`Scratch::flush`] multiplies by
/// plain sums instead of nalgebra's `gemm`.
const SMALL_PRODUCT: usize = 5;

/// Facet channels whose normals' parts are subtracted from the Gauss-Newton matrix at once.
const BATCH: usize = 64;

/// Facets whose lights' terms ([`terms_kernel`]) are computed at once, one SIMD lane each.
const LANES: usize = 8;

/// A pass is split into at most this many chunks of consecutive facets (fewer when a chunk
/// would hold less than [`MIN_CHUNK`] facets), each summed in order by one thread and the
/// chunks' sums added in order: the chunks depend on the number of facets only, so a pass's
/// sums are the same bits whatever the threads do (rayon's fold and reduce split by thread
/// timing, and runs differed by 2.5e-12). Each chunk holds its own Gauss-Newton matrix.
const MAX_CHUNKS: usize = 32;

/// The fewest facets of a chunk (see [`MAX_CHUNKS`]).
const MIN_CHUNK: usize = 256;

/// The chunks of a pass over `count` facets (see [`MAX_CHUNKS`]): their number and size (a
/// multiple of [`LANES`]; the last one may be shorter).
fn chunking(count: usize) -> (usize, usize) {
    let size = count
        .div_ceil(MAX_CHUNKS)
        .max(MIN_CHUNK)
        .next_multiple_of(LANES);
    (count.div_ceil(size), size)
}

/// The `beta` vectors of `lights` at [`LANES`] facet centres into `betas`, facet-major
/// (entry `l k + i`: light i at the l-th centre), and, when `grads` is not empty, their
/// position derivatives' terms into it (same layout); `lanes` holds the lights' lane forms
/// (None: a directional light, whose `beta` is its direction and which has no position). Per
/// facet and light the numbers of the scalar [`Light::beta_anisotropy`] and
/// [`Light::falloff_gradient`] ([`Gradient`]), bit for bit (see [`LaneLight::step_terms`]), for a light's
/// [`LANES`] facets in SIMD registers: the LED power, one per facet and light, was a fifth of
/// a refined run. Returns the number of lights in lane form.
#[inline(always)]
fn terms_kernel(
    lights: &[Light],
    lanes: &[Option<LaneLight>],
    centres: &[[f64; 3]; LANES],
    betas: &mut [[f64; 3]],
    grads: &mut [Gradient],
) -> usize {
    let k = lights.len();
    let gradient = !grads.is_empty();
    let mut in_lanes = 0;
    for (i, (light, lane)) in lights.iter().zip(lanes).enumerate() {
        match lane {
            Some(lane) => {
                in_lanes += 1;
                let t = lane.step_terms(centres, gradient);
                for l in 0..LANES {
                    betas[l * k + i] = [t.beta[0][l], t.beta[1][l], t.beta[2][l]];
                }
                if gradient {
                    for l in 0..LANES {
                        grads[l * k + i] = Gradient {
                            v: [t.v[0][l], t.v[1][l], t.v[2][l]],
                            f: t.f[l],
                            grad_f: [t.grad_f[0][l], t.grad_f[1][l], t.grad_f[2][l]],
                        };
                    }
                }
            }
            None => {
                let b = light.beta(centres[0]).0;
                for l in 0..LANES {
                    betas[l * k + i] = b;
                    if gradient {
                        grads[l * k + i] = Gradient::default();
                    }
                }
            }
        }
    }
    in_lanes
}

simd_dispatch! {
    wide
    /// [`terms_kernel`] with AVX-512 or AVX2 when the processor has it (same arithmetic).
    fn terms_dispatch => terms_kernel(
        lights: &[Light],
        lanes: &[Option<LaneLight>],
        centres: &[[f64; 3]; LANES],
        betas: &mut [[f64; 3]],
        grads: &mut [Gradient],
    ) -> usize;
}

/// A thread's buffers of the light pass's facets in lanes ([`fit_lanes_kernel`]): per light,
/// the observations of [`LANES`] facets (`values`), their rows `a` and observations as used
/// (zero where unusable), and the outputs: per light the squared residual and squared
/// observation of each lane (zero where unusable or the fit failed), and per parameter each
/// lane's term `d r` of the gradient (zero where unusable; empty without the gradient).
struct LaneScratch {
    values: Vec<[f32; LANES]>,
    rows: Vec<[[f64; LANES]; 3]>,
    obs: Vec<[f64; LANES]>,
    ok: Vec<[bool; LANES]>,
    sq_residual: Vec<[f64; LANES]>,
    sq_obs: Vec<[f64; LANES]>,
    grad: Vec<[f64; LANES]>,
    /// With the gradient: per parameter each lane's derivative `d` (zero where unusable).
    d: Vec<[f64; LANES]>,
    /// With the gradient, per light: `w = L^-1 a` of each lane (`T = L L^T`, see [`Scratch`]).
    w: Vec<[[f64; LANES]; 3]>,
    /// The chunk's sums per lane so far: of the squared residuals, of the squared observations
    /// and (with the gradient) of each parameter's terms `d r`; folded into the pass's sums at
    /// the chunk's end ([`LaneScratch::fold`]).
    sum_sse: [f64; LANES],
    sum_i2: [f64; LANES],
    sum_grad: Vec<[f64; LANES]>,
}

impl LaneScratch {
    /// The buffers for `k` lights and `n` parameters (the gradient's when `with_grad`).
    fn try_new(k: usize, n: usize, with_grad: bool) -> Result<LaneScratch> {
        let z = [0.0; LANES];
        Ok(LaneScratch {
            values: try_vec(k, [0.0f32; LANES], PASS)?,
            rows: try_vec(k, [z; 3], PASS)?,
            obs: try_vec(k, z, PASS)?,
            ok: try_vec(k, [false; LANES], PASS)?,
            sq_residual: try_vec(k, z, PASS)?,
            sq_obs: try_vec(k, z, PASS)?,
            grad: try_vec(if with_grad { n } else { 0 }, z, PASS)?,
            d: try_vec(if with_grad { n } else { 0 }, z, PASS)?,
            w: try_vec(if with_grad { k } else { 0 }, [z; 3], PASS)?,
            sum_sse: z,
            sum_i2: z,
            sum_grad: try_vec(if with_grad { n } else { 0 }, z, PASS)?,
        })
    }

    /// Adds the lanes' sums to `acc` (the lanes in order) and clears them.
    fn fold(&mut self, acc: &mut Pass) {
        acc.sse += self.sum_sse.iter().sum::<f64>();
        acc.sum_i2 += self.sum_i2.iter().sum::<f64>();
        for (gr, d) in acc.grad.iter_mut().zip(&mut self.sum_grad) {
            *gr -= d.iter().sum::<f64>();
            *d = [0.0; LANES];
        }
        self.sum_sse = [0.0; LANES];
        self.sum_i2 = [0.0; LANES];
    }
}

/// The fits of [`LANES`] facets of a light pass, one SIMD lane per facet (grey images, no
/// glossy correction, no indirect light): per lane the numbers of the scalar
/// [`LightData::facet`] without the Gauss-Newton matrix, the same operations in the same order,
/// so the same bits. Per light i with intensity `phi_i` (`phis`) and `beta` vectors `betas`
/// (facet-major, `m` facets, entry `l k + i`; lanes from `m` on repeat the last facet), an
/// observation `I` of `s.values` is usable when `dark < I < saturation` (`thresholds`); the
/// row `a_i = phi_i beta_i` (zero where unusable) enters `T = sum_i a_i a_i^T` (its 6 distinct
/// entries) and `s = sum_i a_i I_i`; a lane with at least 4 usable observations and `T` regular
/// by [`invert_spd3`]'s test has the scaled normal `g = T^-1 s`
/// ([`solve_spd3_lanes`](crate::local::solve_spd3_lanes)), the residuals `r_i = I_i - a_i . g`, and with the gradient (`s.grad`
/// not empty) the terms `d r` of each parameter ([`derivatives`]: `d = a_i . g` for the
/// log-intensity, `phi_i (f g + (v . g) grad f)` for the position from the lights' `grads`,
/// zero without them). With the gradient also the Gauss-Newton matrix's terms of each lane
/// (used by the lanes that enter it): the derivatives `d` and `w_i = L^-1 a_i` with the
/// Cholesky factor `T = L L^T` (nalgebra's `cholesky` and `solve_lower_triangular` written
/// out: `L00 = sqrt(T00)`, `L10 = T10 / L00`, `L20 = T20 / L00`, `L11 = sqrt(T11 - L10 L10)`,
/// `L21 = (T21 - L10 L20) / L11`, `L22 = sqrt((T22 - L20 L20) - L21 L21)`, failing where a
/// square root's argument is not positive; forward substitution). Returns which lanes are
/// fitted, their usable observations and whether their Cholesky factor exists; the caller
/// adds the lanes' terms to its sums per lane ([`LightData::lanes_into`]).
#[allow(clippy::needless_range_loop)] // lane code: one index per lane, as the vector instructions
#[inline(always)]
fn fit_lanes_kernel(
    phis: &[f64],
    layout: &Layout,
    thresholds: (f64, f64),
    betas: &[[f64; 3]],
    grads: &[Gradient],
    m: usize,
    s: &mut LaneScratch,
) -> LaneFits {
    let k = phis.len();
    let (dark, saturation) = thresholds;
    let z = [0.0f64; LANES];
    let facet = |l: usize| l.min(m - 1) * k;
    // T = [[t0 t1 t2] [t1 t3 t4] [t2 t4 t5]] and s, summed over the lights in order.
    let mut t = [z; 6];
    let mut sv = [z; 3];
    let mut used = [0usize; LANES];
    for i in 0..k {
        let phi = phis[i];
        let (mut a, mut v, mut ok) = ([z; 3], z, [false; LANES]);
        for l in 0..LANES {
            let x = s.values[i][l] as f64;
            ok[l] = x > dark && x < saturation;
            let b = betas[facet(l) + i];
            for c in 0..3 {
                a[c][l] = if ok[l] { b[c] * phi } else { 0.0 };
            }
            v[l] = if ok[l] { x } else { 0.0 };
            used[l] += ok[l] as usize;
        }
        for l in 0..LANES {
            t[0][l] += a[0][l] * a[0][l];
            t[1][l] += a[0][l] * a[1][l];
            t[2][l] += a[0][l] * a[2][l];
            t[3][l] += a[1][l] * a[1][l];
            t[4][l] += a[1][l] * a[2][l];
            t[5][l] += a[2][l] * a[2][l];
            for c in 0..3 {
                sv[c][l] += a[c][l] * v[l];
            }
        }
        s.rows[i] = a;
        s.obs[i] = v;
        s.ok[i] = ok;
    }
    // invert_spd3's test and g = T^-1 s per lane.
    let (regular, _, g) = crate::local::solve_spd3_lanes(&t, &sv);
    let valid: [bool; LANES] = crate::lanes(|l| l < m && used[l] >= 4 && regular[l]);
    let with_grad = !s.grad.is_empty();
    // T = L L^T per lane (for the lanes of the Gauss-Newton matrix).
    let (mut chol, mut factored) = ([z; 6], [false; LANES]);
    if with_grad {
        for l in 0..LANES {
            let l00 = t[0][l].sqrt();
            let (l10, l20) = (t[1][l] / l00, t[2][l] / l00);
            let p11 = t[3][l] - l10 * l10;
            let l11 = p11.sqrt();
            let l21 = (t[4][l] - l10 * l20) / l11;
            let p22 = (t[5][l] - l20 * l20) - l21 * l21;
            let l22 = p22.sqrt();
            factored[l] = t[0][l] > 0.0 && p11 > 0.0 && p22 > 0.0;
            for (c, x) in chol.iter_mut().zip([l00, l10, l20, l11, l21, l22]) {
                c[l] = x;
            }
        }
    }
    let [l00, l10, l20, l11, l21, l22] = &chol;
    for i in 0..k {
        let a = &s.rows[i];
        let mut r = z;
        let mut keep = [false; LANES];
        for l in 0..LANES {
            keep[l] = s.ok[i][l] && valid[l];
            let prediction = a[0][l] * g[0][l] + a[1][l] * g[1][l] + a[2][l] * g[2][l];
            r[l] = s.obs[i][l] - prediction;
            s.sq_residual[i][l] = if keep[l] { r[l] * r[l] } else { 0.0 };
            s.sq_obs[i][l] = if keep[l] {
                s.obs[i][l] * s.obs[i][l]
            } else {
                0.0
            };
        }
        if !with_grad {
            continue;
        }
        for l in 0..LANES {
            let w0 = a[0][l] / l00[l];
            let w1 = (a[1][l] - w0 * l10[l]) / l11[l];
            let w2 = ((a[2][l] - w0 * l20[l]) - w1 * l21[l]) / l22[l];
            s.w[i][0][l] = w0;
            s.w[i][1][l] = w1;
            s.w[i][2][l] = w2;
        }
        if let Some(j) = layout.intensity[i] {
            for l in 0..LANES {
                let d = a[0][l] * g[0][l] + a[1][l] * g[1][l] + a[2][l] * g[2][l];
                s.d[j][l] = if keep[l] { d } else { 0.0 };
                s.grad[j][l] = if keep[l] { d * r[l] } else { 0.0 };
            }
        }
        if let Some(j) = layout.position[i] {
            let phi = phis[i];
            for l in 0..LANES {
                let gl = [g[0][l], g[1][l], g[2][l]];
                let d = match grads.get(facet(l) + i) {
                    Some(t) => t.along(gl).map(|x| phi * x),
                    None => [0.0; 3],
                };
                for c in 0..3 {
                    s.d[j + c][l] = if keep[l] { d[c] } else { 0.0 };
                    s.grad[j + c][l] = if keep[l] { d[c] * r[l] } else { 0.0 };
                }
            }
        }
    }
    LaneFits {
        valid,
        used,
        factored,
    }
}

/// `sum += terms[0] + terms[1] + ...` in the lanes where `keep` holds.
#[inline(always)]
fn add_lanes(sum: &mut [f64; LANES], terms: &[[f64; LANES]], keep: [bool; LANES]) {
    for t in terms {
        for l in 0..LANES {
            sum[l] += if keep[l] { t[l] } else { 0.0 };
        }
    }
}

/// What [`fit_lanes_kernel`] returns per lane: whether the facet is fitted, its usable
/// observations and whether its `T` has a Cholesky factor.
struct LaneFits {
    valid: [bool; LANES],
    used: [usize; LANES],
    factored: [bool; LANES],
}

simd_dispatch! {
    wide
    /// [`fit_lanes_kernel`] with AVX-512 or AVX2 when the processor has it (same arithmetic).
    fn fit_lanes_dispatch => fit_lanes_kernel(
        phis: &[f64],
        layout: &Layout,
        thresholds: (f64, f64),
        betas: &[[f64; 3]],
        grads: &[Gradient],
        m: usize,
        s: &mut LaneScratch,
    ) -> LaneFits;
}

/// The centres of the pass's facets `first..first + m` (`m <= LANES`; the last repeated to fill
/// the lanes) at unknowns `u`.
fn centres(
    (grid, geometry): (&Grid, &Geometry),
    (first, m, stride): (usize, usize, usize),
    u: &[f64],
) -> [[f64; 3]; LANES] {
    let mut out = [[0.0; 3]; LANES];
    for (l, c) in out.iter_mut().enumerate() {
        let j = first + l.min(m - 1);
        *c = quad_centre(&geometry.facet_corners(grid, j * stride, u));
    }
    out
}

impl Scratch {
    /// A thread's scratch for `k` lights and `n` parameters (`per` values per facet).
    fn try_new(per: usize, k: usize, n: usize, with_h: bool) -> Result<Scratch> {
        let rows = if with_h { 3 * BATCH } else { 0 };
        Ok(Scratch {
            values: try_vec(per, 0.0, PASS)?,
            used: try_with_capacity(k, PASS)?,
            rows: try_with_capacity(k, PASS)?,
            obs: try_with_capacity(k, PASS)?,
            glossy: try_with_capacity(k, PASS)?,
            terms: try_with_capacity(k, PASS)?,
            indirect: Vec::new(),
            bt: DMatrix::from_vec(rows, n, try_vec(rows * n, 0.0, PASS)?),
            product: match with_h {
                true => DMatrix::from_vec(n, n, try_vec(n * n, 0.0, PASS)?),
                false => DMatrix::zeros(0, 0),
            },
            pending: 0,
            want_h: true,
        })
    }

    /// Subtracts `B B^T` of the pending facets from `acc.h` (its upper triangle), the product
    /// by one matrix multiplication (nalgebra's `gemm`, packed and blocked by the
    /// `matrixmultiply` crate) instead of a dot product per pair of columns.
    fn flush(&mut self, acc: &mut Pass) {
        if self.pending == 0 || acc.h.is_empty() {
            return;
        }
        let n = self.bt.ncols();
        let rows = 3 * self.pending;
        let stride = self.bt.nrows();
        // B (n x rows): B^T's first `rows` rows read transposed, in place.
        let b =
            nalgebra::DMatrixView::from_slice_with_strides(self.bt.as_slice(), n, rows, stride, 1);
        let bt = self.bt.rows(0, rows);
        if rows > SMALL_PRODUCT {
            self.product.gemm(1.0, &b, &bt, 0.0);
        } else {
            // nalgebra's `gemm` multiplies this few rows by its own loops, which read the
            // transposed view out of its bounds (one facet pending at a chunk's end: undefined
            // behaviour, a crash in the tests): the product by plain sums.
            for i in 0..n {
                for j in i..n {
                    let mut sum = 0.0;
                    for r in 0..rows {
                        sum += bt[(r, i)] * bt[(r, j)];
                    }
                    self.product[(i, j)] = sum;
                }
            }
        }
        for i in 0..n {
            let h = &mut acc.h[i * n..(i + 1) * n];
            for (j, hj) in h.iter_mut().enumerate().skip(i) {
                *hj -= self.product[(i, j)];
            }
        }
        self.pending = 0;
    }
}

impl<'a> LightData<'a> {
    /// The mesh and images of `problem`, with the thresholds of `settings`.
    pub fn of(problem: &'a Problem<'_>, settings: FitSettings) -> LightData<'a> {
        LightData {
            grid: &problem.grid,
            geometry: &problem.geometry,
            obs: &problem.obs,
            settings,
            normals: None,
            shadows: None,
            indirect: None,
        }
    }

    /// These data with the facets' glossy `normals` (see [`LightData::normals`]).
    pub fn with_normals(self, normals: Option<&'a [[f32; 3]]>) -> LightData<'a> {
        LightData { normals, ..self }
    }

    /// These data with the cast `shadows` of the local steps (see [`LightData::shadows`]).
    pub fn with_shadows(self, shadows: Option<&'a crate::shadow::ShadowMask>) -> LightData<'a> {
        LightData { shadows, ..self }
    }

    /// These data with the local steps' field of `indirect` light (see [`LightData::indirect`]).
    pub fn with_indirect(self, indirect: Option<&'a dyn IndirectLight>) -> LightData<'a> {
        LightData { indirect, ..self }
    }
}

impl LightData<'_> {
    /// The facets of a pass: a regular subsample of at most [`MAX_FACETS`], and its stride.
    fn subsample(&self) -> (usize, usize) {
        let n = self.grid.n_facets();
        let stride = n.div_ceil(MAX_FACETS).max(1);
        (n.div_ceil(stride), stride)
    }

    /// The `beta` vectors of `lights` at the centres of the facets of a pass at unknowns `u`,
    /// facet-major (entry `j k + i`: light i at the pass's j-th facet), for the passes of a step
    /// that keeps the light positions; None above [`MAX_CACHED_BETAS`] (each pass then
    /// computes them). The same numbers as a pass computes: the passes are unchanged.
    fn betas(&self, lights: &[Light], u: &[f64]) -> Result<Option<Vec<[f64; 3]>>> {
        let (count, stride) = self.subsample();
        let k = lights.len();
        if k == 0 || count * k > MAX_CACHED_BETAS {
            return Ok(None);
        }
        let mut out = try_vec(count * k, [0.0; 3], "the light step's beta vectors")?;
        let lanes: Vec<Option<LaneLight>> = lights.iter().map(LaneLight::from_light).collect();
        let mesh = (self.grid, self.geometry);
        out.par_chunks_mut(k * LANES)
            .with_min_len(32)
            .enumerate()
            .for_each(|(b, block)| {
                let m = block.len() / k;
                let centres = centres(mesh, (b * LANES, m, stride), u);
                if m == LANES {
                    terms_dispatch(lights, &lanes, &centres, block, &mut []);
                } else {
                    let mut full = [[0.0; 3]; LANES].repeat(k);
                    terms_dispatch(lights, &lanes, &centres, &mut full, &mut []);
                    block.copy_from_slice(&full[..block.len()]);
                }
            });
        Ok(Some(out))
    }

    /// One pass over the (subsampled) facets at unknowns `u` under `lights`, with the `beta`
    /// vectors of `cached` (see [`LightData::betas`]; computed per facet without);
    /// [`Error::Memory`] when a thread's sums or scratch cannot be allocated.
    fn pass(
        &self,
        lights: (&[Light], &[Light]),
        layout: &Layout,
        u: &[f64],
        with_h: bool,
        cached: Option<&Betas>,
    ) -> Result<Pass> {
        let in_lanes = self.lanes_apply();
        self.pass_in(lights, layout, u, (with_h, in_lanes), cached)
    }

    /// Whether a pass fits its facets in lanes ([`fit_lanes_kernel`]): grey images without
    /// the glossy correction and without indirect light (else every facet is fitted by the
    /// scalar [`LightData::facet`]).
    fn lanes_apply(&self) -> bool {
        self.obs.channels == 1 && self.settings.lobe.is_none() && self.indirect.is_none()
    }

    /// [`LightData::pass`], its facets fitted in lanes when `in_lanes` (which needs
    /// [`LightData::lanes_apply`]; [`LightData::lanes_into`]), else each by the scalar
    /// [`LightData::facet`]: the same bits either way.
    fn pass_in(
        &self,
        (lights, shading): (&[Light], &[Light]),
        layout: &Layout,
        u: &[f64],
        (with_h, in_lanes): (bool, bool),
        cached: Option<&Betas>,
    ) -> Result<Pass> {
        debug_assert!(!in_lanes || self.lanes_apply());
        let (count, stride) = self.subsample();
        let (grid, geometry, obs) = (self.grid, self.geometry, self.obs);
        let k = obs.k;
        let channels = obs.channels;
        let n = layout.n;
        let h_every = count.div_ceil(MAX_MATRIX_FACETS).max(1);
        // The position derivatives' terms: for the Gauss-Newton pass of a step moving lights.
        let gradient = with_h && layout.position.iter().any(Option::is_some);
        let lanes: Vec<Option<LaneLight>> = lights.iter().map(LaneLight::from_light).collect();
        let phis: Vec<f64> = lights
            .iter()
            .map(|light| channel_intensity(light.intensity(), channels, 0))
            .collect();
        let model = Model {
            lights,
            layout,
            shading,
            same_positions: cached.is_some() || std::ptr::eq(lights, shading),
        };
        let (chunks, size) = chunking(count);
        // Each chunk's sums, in order (see MAX_CHUNKS).
        let parts = (0..chunks)
            .into_par_iter()
            .map(|chunk| -> Result<Pass> {
                let (lo, hi) = (chunk * size, ((chunk + 1) * size).min(count));
                let mut acc = Pass::try_new(n, with_h)?;
                let mut s = Scratch::try_new(obs.per_facet(), k, n, with_h)?;
                let mut own = try_vec(LANES * k, [0.0; 3], PASS)?;
                let mut grads = try_vec(
                    if gradient { LANES * k } else { 0 },
                    Gradient::default(),
                    PASS,
                )?;
                let mut values = std::mem::take(&mut s.values);
                let mut ls = match in_lanes {
                    true => Some(LaneScratch::try_new(k, n, with_h)?),
                    false => None,
                };
                for first in (lo..hi).step_by(LANES) {
                    let m = (hi - first).min(LANES);
                    let centres = centres((grid, geometry), (first, m, stride), u);
                    if cached.is_none() {
                        terms_dispatch(lights, &lanes, &centres, &mut own, &mut grads);
                    }
                    if let Some(ls) = ls.as_mut() {
                        let facets = (first, m, stride);
                        let terms = (cached, &own[..], &grads[..]);
                        let (mesh, pass) = ((model, &phis[..]), (&mut acc, &mut s));
                        self.lanes_into(mesh, facets, (centres, h_every), terms, ls, pass);
                        continue;
                    }
                    for (l, &c) in centres.iter().enumerate().take(m) {
                        let j = first + l;
                        let f = j * stride;
                        let n = self
                            .normals
                            .and_then(|w| w.get(f))
                            .filter(|w| w.iter().all(|x| x.is_finite()))
                            .map(|w| w.map(f64::from));
                        acc.sum_z += c[2];
                        acc.min_z = acc.min_z.min(c[2]);
                        acc.facets += 1;
                        s.want_h = j % h_every == 0;
                        let pixel = grid.facets[f] as usize;
                        obs.facet(pixel, &mut values);
                        if let Some(shadows) = self.shadows {
                            for k in shadows.lights_at(pixel) {
                                values[k * channels..(k + 1) * channels].fill(f32::NAN);
                            }
                        }
                        if let Some(field) = self.indirect {
                            field.at_into(pixel, grid.width, &mut s.indirect);
                            for light in (0..k).filter(|&light| field.is_unlit(pixel, light)) {
                                values[light * channels..(light + 1) * channels].fill(f32::NAN);
                            }
                        }
                        let betas: &Betas = match cached {
                            Some(b) => &b[j * k..(j + 1) * k],
                            None => &own[l * k..(l + 1) * k],
                        };
                        let grads = grads.get(l * k..(l + 1) * k).unwrap_or(&[]);
                        for ch in 0..channels {
                            let terms = (betas, grads);
                            self.facet(model, (c, n), (&values, ch), terms, &mut acc, &mut s);
                        }
                    }
                }
                if let Some(ls) = ls.as_mut() {
                    ls.fold(&mut acc);
                }
                s.flush(&mut acc);
                Ok(acc)
            })
            .collect::<Result<Vec<Pass>>>()?;
        let mut pass = parts.into_iter().fold(Pass::empty(), Pass::merge);
        if with_h && pass.h.is_empty() {
            // No facet at all: the sums are zero.
            pass = Pass::try_new(n, with_h)?;
        }
        // The matrix from every `h_every`-th facet stands for all of them.
        pass.h.iter_mut().for_each(|v| *v *= h_every as f64);
        Ok(pass)
    }

    /// Adds the pass's facets `first..first + m` (every `stride`-th facet of the mesh, centres
    /// `centres`; grey images: see [`LightData::lanes_apply`]), fitted in lanes by
    /// [`fit_lanes_kernel`], to the pass: their counts to `acc`, their squared residuals,
    /// squared observations and gradient terms to the per-lane sums of `ls` (which
    /// [`LaneScratch::fold`] adds to `acc` at the chunk's end: the scalar pass's terms, summed
    /// in another order); those entering the Gauss-Newton matrix (every `h_every`-th of a pass
    /// with it) also add their rows of `B^T` and their block-diagonal terms facet after facet,
    /// as the scalar [`LightData::facet`] does (the same bits). `betas` are the `cached` ones
    /// or the block's `own`, `grads` the position derivatives' terms (or empty).
    #[inline]
    fn lanes_into(
        &self,
        (model, phis): (Model<'_>, &[f64]),
        (first, m, stride): (usize, usize, usize),
        (centres, h_every): ([[f64; 3]; LANES], usize),
        (cached, own, grads): (Option<&Betas>, &Betas, &[Gradient]),
        ls: &mut LaneScratch,
        (acc, s): (&mut Pass, &mut Scratch),
    ) {
        let (grid, obs) = (self.grid, self.obs);
        let k = obs.k;
        let pixels: [usize; LANES] =
            crate::lanes(|l| grid.facets[(first + l.min(m - 1)) * stride] as usize);
        let grey = obs.gather_lanes(&pixels, &mut ls.values);
        debug_assert!(grey);
        if let Some(shadows) = self.shadows {
            for (l, &pixel) in pixels.iter().enumerate().take(m) {
                for light in shadows.lights_at(pixel) {
                    ls.values[light][l] = f32::NAN;
                }
            }
        }
        let betas: &Betas = match cached {
            Some(b) => &b[first * k..(first + m) * k],
            None => own,
        };
        let thresholds = (self.settings.dark, self.settings.saturation);
        let layout = model.layout;
        let fits = fit_lanes_dispatch(phis, layout, thresholds, betas, grads, m, ls);
        let with_h = !acc.h.is_empty();
        let n = layout.n;
        let mut keep = [false; LANES];
        for (l, &c) in centres.iter().enumerate().take(m) {
            let j = first + l;
            acc.sum_z += c[2];
            acc.min_z = acc.min_z.min(c[2]);
            acc.facets += 1;
            if !fits.valid[l] {
                continue;
            }
            acc.fits += 1;
            // A facet of the Gauss-Newton matrix adds nothing without its Cholesky factor.
            let in_h = with_h && j % h_every == 0;
            if in_h && !fits.factored[l] {
                continue;
            }
            keep[l] = true;
            acc.count += fits.used[l];
            if !in_h {
                continue;
            }
            // B^T's rows d_ij w_i and the block-diagonal part sum_i d_i d_i^T.
            let row = 3 * s.pending;
            s.bt.rows_mut(row, 3).fill(0.0);
            for i in (0..k).filter(|&i| ls.ok[i][l]) {
                let (first, m) = layout.span(i);
                for a in 0..m {
                    let col = first + a;
                    let d = ls.d[col][l];
                    for c in 0..3 {
                        s.bt[(row + c, col)] = d * ls.w[i][c][l];
                    }
                    let h = &mut acc.h[col * n..];
                    for bb in a..m {
                        h[first + bb] += d * ls.d[first + bb][l];
                    }
                }
            }
            s.pending += 1;
            if s.pending == BATCH {
                s.flush(acc);
            }
        }
        add_lanes(&mut ls.sum_sse, &ls.sq_residual, keep);
        add_lanes(&mut ls.sum_i2, &ls.sq_obs, keep);
        for (sum, d) in ls.sum_grad.iter_mut().zip(&ls.grad) {
            add_lanes(sum, std::slice::from_ref(d), keep);
        }
    }

    /// Under the glossy model (`lobe`), the correction `(offset, factor)` of each observation of
    /// channel `ch` of the facet with centre `c` and glossy normal `n` under the `shading` lights
    /// into `out` (see the module documentation): None for an unusable one, one unlit at `n`, and
    /// one whose predicted specular share exceeds [`MAX_SPECULAR_SHARE`].
    /// `betas` are those of the `shading` lights at `c` when given (else computed).
    fn glossy(
        &self,
        lobe: &Lobe,
        (shading, betas): (&[Light], Option<&Betas>),
        (c, n): ([f64; 3], [f64; 3]),
        (values, ch): (&[f32], usize),
        terms_out: &mut Vec<Option<GlossyTerms>>,
        out: &mut Vec<Option<(f64, f64)>>,
    ) {
        let channels = self.obs.channels;
        let view = self.geometry.view(c);
        out.clear();
        // (Phi a D, Phi a S, (n . l) / D, I) of each usable observation lit at the normal.
        let terms = |i: usize, light: &Light| -> Option<GlossyTerms> {
            let o = &values[i * channels..(i + 1) * channels];
            if !usable(o, &self.settings) {
                return None;
            }
            let b = betas.map_or_else(|| light.beta(c).0, |b| b[i]);
            let a = norm(b);
            if !(a > 0.0 && a.is_finite()) {
                return None;
            }
            let l = b.map(|x| x / a);
            let sh = lobe.shade(n, l, view)?;
            let pa = channel_intensity(light.intensity(), channels, ch) * a;
            let lambert = dot(n, l) / sh.diffuse;
            Some((pa * sh.diffuse, pa * sh.specular, lambert, o[ch] as f64))
        };
        terms_out.clear();
        terms_out.extend(shading.iter().enumerate().map(|(i, light)| terms(i, light)));
        // The least-squares albedos (rho_d, rho_s >= 0) at the normal.
        let (mut dd, mut ds, mut ss, mut di, mut si) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for &(d, s, _, v) in terms_out.iter().flatten() {
            dd += d * d;
            ds += d * s;
            ss += s * s;
            di += d * v;
            si += s * v;
        }
        let det = dd * ss - ds * ds;
        let (rho_d, rho_s) = if det > 1e-12 * dd * ss && dd * si - ds * di > 0.0 {
            ((ss * di - ds * si) / det, (dd * si - ds * di) / det)
        } else if dd > 0.0 {
            (di / dd, 0.0)
        } else {
            (0.0, 0.0)
        };
        for t in terms_out.iter() {
            out.push(t.and_then(|(d, s, lambert, _)| {
                let (spec, diffuse) = (rho_s * s, rho_d * d);
                (spec <= MAX_SPECULAR_SHARE * (spec + diffuse)).then_some((spec, lambert))
            }));
        }
    }

    /// Adds channel `ch` of the facet with centre `c`, glossy normal `n` (if any),
    /// observations `values` and the lights' `betas` at `c` (with their position derivatives'
    /// terms for a Gauss-Newton pass moving the lights, else empty) to the pass.
    #[inline]
    fn facet(
        &self,
        model: Model<'_>,
        (c, n): ([f64; 3], Option<[f64; 3]>),
        (values, ch): (&[f32], usize),
        (betas, grads): (&Betas, &[Gradient]),
        acc: &mut Pass,
        s: &mut Scratch,
    ) {
        let Model {
            lights,
            layout,
            shading,
            same_positions,
        } = model;
        let channels = self.obs.channels;
        s.used.clear();
        s.rows.clear();
        s.obs.clear();
        let glossy = self.settings.lobe.zip(n);
        if let Some((lobe, n)) = &glossy {
            let shading = (shading, same_positions.then_some(betas));
            let (terms, out) = (&mut s.terms, &mut s.glossy);
            self.glossy(lobe, shading, (c, *n), (values, ch), terms, out);
        }
        let mut t = Matrix3::zeros();
        let mut sv = Vector3::zeros();
        for (i, light) in lights.iter().enumerate() {
            let o = &values[i * channels..(i + 1) * channels];
            if !usable(o, &self.settings) {
                continue;
            }
            let mut v = o[ch] as f64;
            if glossy.is_some() {
                let Some((offset, factor)) = s.glossy[i] else {
                    continue;
                };
                v = (v - offset) * factor;
            }
            let phi = channel_intensity(light.intensity(), channels, ch);
            let b = betas[i];
            let mut a = Vector3::new(b[0] * phi, b[1] * phi, b[2] * phi);
            if self.indirect.is_some() {
                a += Vector3::from(s.indirect[i * channels + ch]);
            }
            t += a * a.transpose();
            sv += a * v;
            s.used.push(i);
            s.rows.push([a.x, a.y, a.z]);
            s.obs.push(v);
        }
        // Three observations fit any lights exactly: only the fourth and later carry
        // information about them.
        if s.used.len() < 4 {
            return;
        }
        let Some(tinv) = invert_spd3(&t) else {
            return;
        };
        let g = tinv * sv;
        let g = [g.x, g.y, g.z];
        acc.fits += 1;
        let with_h = s.want_h && !acc.h.is_empty();
        let with_grad = !acc.grad.is_empty();
        // T = L L^T; a_i^T T^-1 a_j = w_i . w_j with w = L^-1 a.
        let chol = if with_h {
            match t.cholesky() {
                Some(c) => Some(c.l()),
                None => return,
            }
        } else {
            None
        };
        let n = layout.n;
        if with_h {
            s.bt.rows_mut(3 * s.pending, 3).fill(0.0);
        }
        for (idx, (&i, row)) in s.used.iter().zip(&s.rows).enumerate() {
            let v = s.obs[idx];
            let r = v - dot(*row, g);
            acc.sse += r * r;
            acc.sum_i2 += v * v;
            acc.count += 1;
            if !with_grad {
                continue;
            }
            let (first, m) = layout.span(i);
            if m == 0 {
                continue;
            }
            let phi = channel_intensity(lights[i].intensity(), channels, ch);
            let refined = (layout.intensity[i].is_some(), layout.position[i].is_some());
            // With indirect light the row's direct part alone depends on the lights.
            let direct = match self.indirect {
                Some(_) => betas[i].map(|b| b * phi),
                None => *row,
            };
            let d = derivatives(direct, g, phi, refined, grads.get(i));
            for (gr, da) in acc.grad[first..first + m].iter_mut().zip(&d) {
                *gr -= da * r;
            }
            let Some(l) = chol.as_ref() else {
                continue;
            };
            let w = l
                .solve_lower_triangular(&Vector3::from(*row))
                .unwrap_or_else(Vector3::zeros);
            for a in 0..m {
                let col = first + a;
                s.bt[(3 * s.pending, col)] = d[a] * w.x;
                s.bt[(3 * s.pending + 1, col)] = d[a] * w.y;
                s.bt[(3 * s.pending + 2, col)] = d[a] * w.z;
                // The block-diagonal part, sum_i d_i d_i^T.
                let h = &mut acc.h[(first + a) * n..];
                for bb in a..m {
                    h[first + bb] += d[a] * d[bb];
                }
            }
        }
        if !with_h {
            return;
        }
        // Minus the normals' part, B B^T with the rows of B = d_ij w_i, in batches.
        s.pending += 1;
        if s.pending == BATCH {
            s.flush(acc);
        }
    }
}

/// The symmetric matrix of a pass (its upper triangle mirrored).
fn symmetric(h: &[f64], n: usize) -> DMatrix<f64> {
    DMatrix::from_fn(
        n,
        n,
        |i, j| if i <= j { h[i * n + j] } else { h[j * n + i] },
    )
}

/// What a light step did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepOutcome {
    /// Largest change: `|delta s_i|` or `|delta p_i| / D` (0 when the step was rejected).
    pub change: f64,
    /// The objective `E` before the step (at the current mesh).
    pub objective: f64,
    /// Whether a step was accepted.
    pub accepted: bool,
}

/// The state of the light refinement across the iterations of a solver.
#[derive(Debug, Clone)]
pub struct Refiner {
    /// What is refined.
    pub refine: Refine,
    /// The rig's lights (the prior's centre and the intensity gauge's reference).
    pub reference: Vec<Light>,
    lambda: f64,
    /// Whether the last step's decrease of `E` matched the Gauss-Newton model's prediction
    /// (then the next step is taken without a trial evaluation; the one after is checked).
    trusted: bool,
    /// The Gauss-Newton pass of the last step, when that step left the lights as they were
    /// (see [`SettledPass`]).
    settled: Option<SettledPass>,
}

/// The Gauss-Newton pass of a light step that left the lights as they were (found nothing to
/// improve), with those lights and the pass's subsampling stride: the light step's matrix at
/// the lights the run keeps, from which [`SettledPass::conditioning`] reports the conditioning
/// without a pass of its own (issue 23: at 256² the report's pass over 32 k facets was a
/// tenth of a refined run's extra CPU).
#[derive(Debug, Clone)]
pub struct SettledPass {
    pass: Pass,
    lights: Vec<Light>,
    stride: usize,
}

impl SettledPass {
    /// The conditioning of `refine`'s parameters of `lights` from this pass (see
    /// [`conditioning`]); None when `lights` are not the pass's or `refine` lays out other
    /// parameters.
    ///
    /// The pass is at the mesh of the step that settled the lights, not at the final one: the
    /// step's fits free each facet's normal, so the mesh enters only through the facet
    /// centres, which the iterations after a settled step move by at most their depth change.
    pub fn conditioning(&self, lights: &[Light], refine: &Refine) -> Option<Result<Conditioning>> {
        let layout = Layout::new(lights, refine);
        (self.lights == lights && self.pass.grad.len() == layout.n && layout.n > 0)
            .then(|| conditioning_of(&self.pass, self.stride, lights, &layout, refine))
    }
}

/// A light step whose undamped Gauss-Newton step predicts a decrease of the objective `E` of
/// at most this ends the light steps of the run ([`StepOutcome::accepted`] false). `E` is half
/// a chi-square (the data in units of the estimated noise variance, the subsample standing for
/// all facets), so the step `delta` it skips has `delta^T H delta = 2 x 0.01`: it would move the
/// lights by 0.14 standard errors (Mahalanobis length), far within what the images determine.
/// Only with images noisier than [`NOISE_FLOOR`] (with exact images `E`'s unit is the floor,
/// not a noise the images have, and the steps go on to the old stop rule).
/// Measured (bumps, 256², 1 % noise): the last 2-3 light steps of each level fall below it,
/// where each cost a pass over the facets and the joint iteration crept on (issue 23, item 4).
pub const SETTLED_DECREASE: f64 = 0.01;

/// A light step whose undamped Gauss-Newton step predicts a decrease of `E` of at most this
/// share of `E` itself also ends the light steps of the run (with noise above the floor, as
/// [`SETTLED_DECREASE`]): the step would lower the residual's sum of squares by 0.01 %, its RMS
/// by 0.005 %, 16-36 times less than `E`'s own statistical spread between noise draws
/// (`sqrt(2 / dof)`: 0.16 % at 256² with 27 lights, 0.36 % at 80²). With many facets the
/// chi-square unit of [`SETTLED_DECREASE`] is far below what the mesh's discretisation error
/// moves (the noise estimate does not see it), and the lights crept on fitting it: measured on
/// bumps at 256² with 1 % noise and 27 LEDs (issue 23), the finest level's last 4-6 light steps
/// each predicted 0.2-50 chi-square units, 7e-5 of `E` and less, moved the positions by
/// 0.05-0.7 % of the distance with the residual flat to 1e-6, and cost a pass over the facets
/// and an iteration each; stopping them left the normal and light errors as they were or
/// lowered them (see the CHANGELOG).
pub const SETTLED_RELATIVE: f64 = 1e-4;

/// Largest number of damping increases in one step.
const MAX_TRIES: usize = 8;

impl Refiner {
    /// A refiner of `refine` around the rig's `reference` lights.
    pub fn new(refine: Refine, reference: Vec<Light>) -> Refiner {
        Refiner {
            refine,
            reference,
            lambda: 1e-3,
            trusted: false,
            settled: None,
        }
    }

    /// The pass of the last step when it left the lights as they were (see [`SettledPass`]).
    pub fn settled_pass(&self) -> Option<&SettledPass> {
        self.settled.as_ref()
    }

    /// Forgets the last step's pass (a new run starts: its mesh is another).
    pub fn forget_settled(&mut self) {
        self.settled = None;
    }

    /// The refined parameters of `lights` as a vector in the step's layout: `ln(Phi_i / Phi_i^0)`
    /// (relative to the rig's intensity) and `p_i / D`.
    pub fn encode(&self, lights: &[Light], distance: f64) -> Vec<f64> {
        let layout = Layout::new(lights, &self.refine);
        let mut x = vec![0.0; layout.n];
        for (i, (light, reference)) in lights.iter().zip(&self.reference).enumerate() {
            if let Some(j) = layout.intensity[i] {
                x[j] = intensity_ratio(light, reference).ln();
            }
            if let (Some(j), Light::Point { position, .. }) = (layout.position[i], light) {
                for a in 0..3 {
                    x[j + a] = position[a] / distance;
                }
            }
        }
        x
    }

    /// The lights whose refined parameters are `x` (see [`Refiner::encode`]).
    pub fn decode(&self, lights: &[Light], x: &[f64], distance: f64) -> Vec<Light> {
        let layout = Layout::new(lights, &self.refine);
        lights
            .iter()
            .zip(&self.reference)
            .enumerate()
            .map(|(i, (light, reference))| {
                let mut light = *light;
                if let Some(j) = layout.intensity[i] {
                    let phi = reference.intensity().map(|v| v * x[j].exp());
                    match &mut light {
                        Light::Point { intensity, .. } | Light::Directional { intensity, .. } => {
                            *intensity = phi;
                        }
                    }
                }
                if let (Some(j), Light::Point { position, .. }) = (layout.position[i], &mut light) {
                    for a in 0..3 {
                        position[a] = x[j + a] * distance;
                    }
                }
                light
            })
            .collect()
    }

    /// The objective of `lights` from a pass (data) and the prior.
    fn objective(&self, pass: &Pass, nu: f64, lights: &[Light], distance: f64) -> f64 {
        0.5 * pass.sse / nu + self.prior(lights, distance)
    }

    fn prior(&self, lights: &[Light], distance: f64) -> f64 {
        if !self.refine.position {
            return 0.0;
        }
        let w = self.refine.prior_weight / (distance * distance);
        0.5 * w
            * lights
                .iter()
                .zip(&self.reference)
                .map(|(a, b)| match (a, b) {
                    (Light::Point { position: p, .. }, Light::Point { position: q, .. }) => {
                        let d = sub(*p, *q);
                        dot(d, d)
                    }
                    _ => 0.0,
                })
                .sum::<f64>()
    }

    /// One damped Gauss-Newton step on `lights` at unknowns `u` (see the module docs).
    ///
    /// Panics when the sums of the step cannot be allocated: prefer [`Refiner::try_step`],
    /// which reports it as [`Error::Memory`].
    #[cfg(all(test, feature = "synth"))]
    pub fn step(&mut self, data: &LightData<'_>, lights: &mut [Light], u: &[f64]) -> StepOutcome {
        match self.try_step(data, lights, u) {
            Ok(outcome) => outcome,
            Err(e) => panic!("{e}"),
        }
    }

    /// As `Refiner::step` (tests), with [`Error::Memory`] (and `lights` unchanged) when the sums of
    /// the step or a thread's scratch cannot be allocated.
    pub fn try_step(
        &mut self,
        data: &LightData<'_>,
        lights: &mut [Light],
        u: &[f64],
    ) -> Result<StepOutcome> {
        self.settled = None;
        let layout = Layout::new(lights, &self.refine);
        let n = layout.n;
        let none = StepOutcome {
            change: 0.0,
            objective: f64::NAN,
            accepted: false,
        };
        if n == 0 {
            return Ok(none);
        }
        // Intensities only: the positions, hence the beta vectors, stay through the step.
        let cached = match self.refine.position {
            true => None,
            false => data.betas(lights, u)?,
        };
        let pass = data.pass((lights, lights), &layout, u, true, cached.as_deref())?;
        if pass.fits == 0 || pass.sum_i2 <= 0.0 {
            return Ok(none);
        }
        // The data term in units of the noise variance, estimated from the residual of the fits
        // (the subsample stands for all facets): the prior then reads as a Gaussian prior with
        // standard deviation D / sqrt(w) on each coordinate of a light.
        let (_, stride) = data.subsample();
        let dof = (pass.count as f64 - 3.0 * pass.fits as f64).max(1.0);
        let floor = NOISE_FLOOR * NOISE_FLOOR * pass.sum_i2 / pass.count.max(1) as f64;
        let noisy = pass.sse / dof > floor;
        let nu = (pass.sse / dof).max(floor) / stride as f64;
        let distance = (pass.sum_z / pass.facets as f64)
            .abs()
            .max(f64::MIN_POSITIVE);
        let e0 = self.objective(&pass, nu, lights, distance);
        let mut h = symmetric(&pass.h, n) / nu;
        let mut grad = DVector::from_vec(pass.grad.clone()) / nu;
        let w = self.refine.prior_weight / (distance * distance);
        for (light, (j, reference)) in lights
            .iter()
            .zip(layout.position.iter().zip(&self.reference))
        {
            if let (Some(j), Light::Point { position: p, .. }, Light::Point { position: q, .. }) =
                (j, light, reference)
            {
                for a in 0..3 {
                    h[(j + a, j + a)] += w;
                    grad[j + a] += w * (p[a] - q[a]);
                }
            }
        }
        let constraints = layout.constraints(&self.reference, self.refine.fix_scale);
        let scale = h.diagonal().max().max(f64::MIN_POSITIVE);
        // The undamped Gauss-Newton step's predicted decrease, 1/2 g^T H^-1 g (on the
        // constraints): below SETTLED_DECREASE the lights are as good as the images tell, below
        // SETTLED_RELATIVE of E they would only fit the mesh's discretisation (with noise above
        // the floor only: at the floor E's unit is not the images' noise).
        let mut a = h.clone();
        for i in 0..n {
            a[(i, i)] += 1e-12 * scale;
        }
        let undamped = noisy
            .then(|| solve_constrained(&a, &grad, &constraints))
            .flatten();
        if let Some(delta) = undamped {
            let full = -grad.dot(&delta) - 0.5 * delta.dot(&(&h * &delta));
            if full <= SETTLED_DECREASE.max(SETTLED_RELATIVE * e0) {
                self.keep_settled(pass, lights, stride);
                return Ok(StepOutcome {
                    objective: e0,
                    ..none
                });
            }
        }
        for _ in 0..MAX_TRIES {
            let mut a = h.clone();
            for i in 0..n {
                a[(i, i)] += self.lambda * h[(i, i)] + 1e-12 * scale;
            }
            let Some(delta) = solve_constrained(&a, &grad, &constraints) else {
                self.lambda *= 10.0;
                continue;
            };
            let (trial, change) = apply(lights, &layout, &delta, distance);
            // Decrease predicted by the Gauss-Newton model: when it is at the rounding level of
            // E, the lights have converged and a trial evaluation could not tell.
            let predicted = -grad.dot(&delta) - 0.5 * delta.dot(&(&h * &delta));
            if predicted <= 1e-13 * e0 {
                self.keep_settled(pass, lights, stride);
                return Ok(StepOutcome {
                    objective: e0,
                    ..none
                });
            }
            let in_front = trial.iter().all(|l| l.is_in_front_of(pass.min_z));
            if in_front && self.trusted {
                // The model predicted the last decrease well: take this step unchecked (the
                // solver's safeguard watches the residual), and check the next one.
                self.trusted = false;
                lights.copy_from_slice(&trial);
                return Ok(StepOutcome {
                    change,
                    objective: e0,
                    accepted: true,
                });
            }
            let e1 = if in_front {
                let p = data.pass((&trial, lights), &layout, u, false, cached.as_deref())?;
                self.objective(&p, nu, &trial, distance)
            } else {
                f64::INFINITY
            };
            if e1 < e0 {
                let ratio = (e0 - e1) / predicted;
                self.trusted = (0.5..=2.0).contains(&ratio);
                lights.copy_from_slice(&trial);
                self.lambda = (self.lambda / 3.0).max(1e-9);
                return Ok(StepOutcome {
                    change,
                    objective: e0,
                    accepted: true,
                });
            }
            self.lambda *= 5.0;
            self.trusted = false;
        }
        self.keep_settled(pass, lights, stride);
        Ok(StepOutcome {
            objective: e0,
            ..none
        })
    }

    /// Keeps `pass` of a step that left `lights` as they were (see [`SettledPass`]).
    fn keep_settled(&mut self, pass: Pass, lights: &[Light], stride: usize) {
        self.settled = Some(SettledPass {
            pass,
            lights: lights.to_vec(),
            stride,
        });
    }
}

/// `Phi / Phi^0` of a light whose intensity is a multiple of the reference's (its largest channel).
fn intensity_ratio(light: &Light, reference: &Light) -> f64 {
    let (phi, phi0) = (light.intensity(), reference.intensity());
    let c = (0..3).fold(0, |best, c| if phi0[c] > phi0[best] { c } else { best });
    phi[c] / phi0[c]
}

/// Solves `A x = -grad` subject to `C^T x = 0` (KKT system), or None if it is singular.
fn solve_constrained(
    a: &DMatrix<f64>,
    grad: &DVector<f64>,
    constraints: &[DVector<f64>],
) -> Option<DVector<f64>> {
    let n = a.nrows();
    let m = constraints.len();
    let mut k = DMatrix::zeros(n + m, n + m);
    k.view_mut((0, 0), (n, n)).copy_from(a);
    let mut rhs = DVector::zeros(n + m);
    for i in 0..n {
        rhs[i] = -grad[i];
    }
    for (j, c) in constraints.iter().enumerate() {
        let norm = c.norm().max(f64::MIN_POSITIVE);
        for i in 0..n {
            k[(i, n + j)] = c[i] / norm;
            k[(n + j, i)] = c[i] / norm;
        }
    }
    let x = k.lu().solve(&rhs)?;
    x.iter()
        .all(|v| v.is_finite())
        .then(|| x.rows(0, n).into_owned())
}

/// Largest change of an intensity factor per step (the step is retried when it does not help).
const MAX_LOG_STEP: f64 = 1.0;

/// `lights` moved by `delta`, and the largest relative change.
fn apply(
    lights: &[Light],
    layout: &Layout,
    delta: &DVector<f64>,
    distance: f64,
) -> (Vec<Light>, f64) {
    let mut change: f64 = 0.0;
    let out = lights
        .iter()
        .enumerate()
        .map(|(i, light)| {
            let mut light = *light;
            if let Some(j) = layout.intensity[i] {
                let ds = delta[j].clamp(-MAX_LOG_STEP, MAX_LOG_STEP);
                change = change.max(ds.abs());
                let factor = ds.exp();
                match &mut light {
                    Light::Point { intensity, .. } | Light::Directional { intensity, .. } => {
                        *intensity = intensity.map(|v| v * factor);
                    }
                }
            }
            if let (Some(j), Light::Point { position, .. }) = (layout.position[i], &mut light) {
                let d = [delta[j], delta[j + 1], delta[j + 2]];
                change = change.max(norm(d) / distance);
                for a in 0..3 {
                    position[a] += d[a];
                }
            }
            light
        })
        .collect();
    (out, change)
}

/// How well the images determine the light parameters at a mesh.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct Conditioning {
    /// Singular values of the light block of the (relative) Jacobian after the normals are
    /// eliminated, positions measured in units of the working distance, largest first; the
    /// directions removed by the gauge constraints are left out.
    pub singular_values: Vec<f64>,
    /// Per light: standard error of the intensity factor (relative) and of the position
    /// (x, y, z, in scene units) from the residual's variance; NaN where not refined.
    pub standard_errors: Vec<[f64; 4]>,
    /// RMS residual of the light step's fits (image units).
    pub rms_residual: f64,
    /// The working distance `D` used to scale positions.
    pub distance: f64,
}

/// The conditioning of `refine`'s light parameters for `lights` at unknowns `u` (see
/// [`Conditioning`]). The Gauss-Newton matrix is that of the light step, scaled up from its
/// subsample of facets; it leaves out integrability, so it bounds from below what the whole
/// reconstruction knows.
pub fn conditioning(
    data: &LightData<'_>,
    lights: &[Light],
    u: &[f64],
    refine: &Refine,
) -> Result<Conditioning> {
    let layout = Layout::new(lights, refine);
    let n = layout.n;
    if n == 0 {
        return Err(Error::Unusable(
            "nothing to analyse: no light parameter is refined".into(),
        ));
    }
    let pass = data.pass((lights, lights), &layout, u, true, None)?;
    let (_, stride) = data.subsample();
    conditioning_of(&pass, stride, lights, &layout, refine)
}

/// [`conditioning`] from a Gauss-Newton `pass` of `lights` in `layout` (`refine`'s) over a
/// subsample of every `stride`-th facet.
fn conditioning_of(
    pass: &Pass,
    stride: usize,
    lights: &[Light],
    layout: &Layout,
    refine: &Refine,
) -> Result<Conditioning> {
    let n = layout.n;
    let dof = pass.count as f64 - 3.0 * pass.fits as f64 - n as f64;
    if pass.fits == 0 || dof <= 0.0 {
        return Err(Error::Unusable(
            "too few usable observations to analyse the lights (each fitted facet needs 4 or more lit images)"
                .into(),
        ));
    }
    let distance = (pass.sum_z / pass.facets as f64).abs();
    let sigma2 = pass.sse / dof;
    // Full-data J^T J, estimated from the subsample.
    let h = symmetric(&pass.h, n) * stride as f64;
    // Scaled parameters: positions in units of D, data relative to sum I^2.
    let mut scale = DVector::from_element(n, 1.0);
    for j in layout.position.iter().flatten() {
        for a in 0..3 {
            scale[j + a] = distance;
        }
    }
    let nu = pass.sum_i2 * stride as f64;
    let hs = DMatrix::from_fn(n, n, |i, j| h[(i, j)] * scale[i] * scale[j] / nu);
    let constraints = layout.constraints(lights, refine.fix_scale);
    // Project out the gauge directions (in scaled coordinates).
    let mut basis: Vec<DVector<f64>> = Vec::new();
    for c in &constraints {
        let mut v = c.component_mul(&scale.map(|s| 1.0 / s));
        for b in &basis {
            let proj = b.dot(&v);
            v -= b * proj;
        }
        let norm = v.norm();
        if norm > 0.0 {
            basis.push(v / norm);
        }
    }
    let mut projector = DMatrix::identity(n, n);
    for b in &basis {
        projector -= b * b.transpose();
    }
    let reduced = &projector * &hs * &projector;
    let mut eig: Vec<f64> = reduced
        .symmetric_eigenvalues()
        .iter()
        .map(|&e| e.max(0.0).sqrt())
        .collect();
    eig.sort_by(|a, b| b.total_cmp(a));
    eig.truncate(n - basis.len());
    // Covariance: sigma^2 (J^T J)^+ on the constrained subspace.
    let mut kkt = DMatrix::zeros(n + basis.len(), n + basis.len());
    kkt.view_mut((0, 0), (n, n)).copy_from(&h);
    for (j, b) in basis.iter().enumerate() {
        let c = b.component_mul(&scale.map(|s| 1.0 / s));
        for i in 0..n {
            kkt[(i, n + j)] = c[i];
            kkt[(n + j, i)] = c[i];
        }
    }
    let inverse = kkt.try_inverse();
    let se = |j: usize| -> f64 {
        inverse
            .as_ref()
            .map_or(f64::INFINITY, |inv| (sigma2 * inv[(j, j)]).max(0.0).sqrt())
    };
    let standard_errors = (0..lights.len())
        .map(|i| {
            let mut out = [f64::NAN; 4];
            if let Some(j) = layout.intensity[i] {
                out[0] = se(j);
            }
            if let Some(j) = layout.position[i] {
                for a in 0..3 {
                    out[1 + a] = se(j + a);
                }
            }
            out
        })
        .collect();
    Ok(Conditioning {
        singular_values: eig,
        standard_errors,
        rms_residual: (pass.sse / pass.count.max(1) as f64).sqrt(),
        distance,
    })
}

// The tests reconstruct synthetic scenes (cargo feature `synth`).
#[cfg(all(test, feature = "synth"))]
mod tests {
    use super::*;
    use crate::problem::{ImageStack, InitialDepth};
    use crate::synth::{Scene, SceneKind};

    fn scene_problem(scene: &Scene, images: &[f32]) -> Problem<'static> {
        let stack = ImageStack::new(
            Box::leak(images.to_vec().into_boxed_slice()),
            scene.rig.n_lights(),
            scene.height,
            scene.width,
        )
        .unwrap();
        let rig = Box::leak(Box::new(scene.rig.clone()));
        let depth = Box::leak(scene.depth.clone().into_boxed_slice());
        Problem::new(stack, rig, Some(&scene.mask), InitialDepth::Map(depth)).unwrap()
    }

    /// The facets' normals of the problem's starting mesh (the true one in these tests, as the
    /// renderer's).
    fn true_normals(problem: &Problem<'_>) -> Vec<[f32; 3]> {
        (0..problem.grid.n_facets())
            .map(|f| {
                let q =
                    problem
                        .geometry
                        .facet_corners(&problem.grid, f, &problem.u0.values().unwrap());
                crate::geometry::quad_normal(&q).map(|x| x as f32)
            })
            .collect()
    }

    /// `lights` with the point lights' intensities off by up to 35 % (a fixed pattern).
    fn off_intensities(lights: &[Light]) -> Vec<Light> {
        let mut lights = lights.to_vec();
        for (i, l) in lights.iter_mut().enumerate() {
            if let Light::Point { intensity, .. } = l {
                let f = 1.0 + 0.35 * ((i as f64 * 2.1).sin());
                *intensity = intensity.map(|v| v * f);
            }
        }
        lights
    }

    /// On the true mesh, intensity steps recover intensities that are off by up to 35 %.
    #[test]
    fn intensity_steps_recover_the_truth_on_the_true_mesh() {
        let scene = Scene::new(SceneKind::SphereCap, 24, 100.0, 200.0, 0).unwrap();
        let images: Vec<f32> = scene.render().unwrap().iter().map(|&v| v as f32).collect();
        let problem = scene_problem(&scene, &images);
        let mut lights = off_intensities(&scene.rig.lights);
        let refine = Refine {
            intensity: true,
            ..Refine::NONE
        };
        let data = LightData::of(&problem, FitSettings::default());
        let mut refiner = Refiner::new(refine, lights.clone());
        for _ in 0..15 {
            refiner.step(&data, &mut lights, &problem.u0.values().unwrap());
        }
        // Relative intensities: ratios to the geometric mean.
        let ratio = |ls: &[Light]| -> Vec<f64> {
            let v: Vec<f64> = ls.iter().map(|l| l.intensity()[0]).collect();
            let g = (v.iter().map(|x| x.ln()).sum::<f64>() / v.len() as f64).exp();
            v.iter().map(|x| x / g).collect()
        };
        for (a, b) in ratio(&lights).iter().zip(ratio(&scene.rig.lights)) {
            assert!((a / b - 1.0).abs() < 1e-6, "{a} vs {b}");
        }
    }

    /// A field of indirect light that does not change: `k` vectors per pixel, none unlit.
    struct FixedField {
        vectors: Vec<[f64; 3]>,
        k: usize,
    }

    impl IndirectLight for FixedField {
        fn is_unlit(&self, _p: usize, _k: usize) -> bool {
            false
        }
        fn at_into(&self, p: usize, _width: usize, out: &mut Vec<[f64; 3]>) {
            out.clear();
            out.extend_from_slice(&self.vectors[p * self.k..(p + 1) * self.k]);
        }
    }

    /// With a field of indirect light in the images (`I = (Phi beta + V) . g`, on the true
    /// mesh): intensity steps given the field recover intensities that are off by up to 35 %;
    /// without it the indirect light biases them.
    #[test]
    fn intensity_steps_with_indirect_light_recover_the_truth() {
        let scene = Scene::new(SceneKind::SphereCap, 24, 100.0, 200.0, 0).unwrap();
        let direct = scene.render().unwrap();
        let (k, plane) = (scene.rig.n_lights(), scene.height * scene.width);
        let start = Problem::new(
            ImageStack::new(
                Box::leak(vec![0.0f32; k * plane].into_boxed_slice()),
                k,
                scene.height,
                scene.width,
            )
            .unwrap(),
            Box::leak(Box::new(scene.rig.clone())),
            Some(&scene.mask),
            InitialDepth::Map(Box::leak(scene.depth.clone().into_boxed_slice())),
        )
        .unwrap();
        let u = start.u0.values().unwrap();
        // V of light i: a fifth of its direct row's length, along a direction of the pixel's
        // own (not the light's), so that it is no change of the intensities.
        let mut vectors = vec![[0.0; 3]; plane * k];
        let mut images: Vec<f32> = direct.iter().map(|&v| v as f32).collect();
        for f in 0..start.grid.n_facets() {
            let p = start.grid.facets[f] as usize;
            let q = start.geometry.facet_corners(&start.grid, f, &u);
            let c = quad_centre(&q);
            // The renderer's scaled normal: the least-squares fit of the lit direct images.
            let (mut t, mut b) = (Matrix3::zeros(), Vector3::zeros());
            for (i, light) in scene.rig.lights.iter().enumerate() {
                if direct[i * plane + p] > 0.0 {
                    let a = Vector3::from(light.beta(c).0) * light.intensity()[0];
                    t += a * a.transpose();
                    b += a * direct[i * plane + p];
                }
            }
            let g = invert_spd3(&t).unwrap() * b;
            let g = [g.x, g.y, g.z];
            let t = p as f64 * 0.7;
            let w = [t.sin(), t.cos(), 1.5];
            for (i, light) in scene.rig.lights.iter().enumerate() {
                let size = 0.2 * norm(light.beta(c).0) * light.intensity()[0] / norm(w);
                let v = w.map(|x| x * size);
                vectors[p * k + i] = v;
                if direct[i * plane + p] > 0.0 {
                    images[i * plane + p] = (direct[i * plane + p] + dot(v, g)) as f32;
                }
            }
        }
        let problem = scene_problem(&scene, &images);
        let field = FixedField { vectors, k };
        let refine = Refine {
            intensity: true,
            ..Refine::NONE
        };
        let ratio = |ls: &[Light]| -> Vec<f64> {
            let v: Vec<f64> = ls.iter().map(|l| l.intensity()[0]).collect();
            let g = (v.iter().map(|x| x.ln()).sum::<f64>() / v.len() as f64).exp();
            v.iter().map(|x| x / g).collect()
        };
        let ratio_to_truth = |ls: &[Light]| -> Vec<f64> {
            ls.iter()
                .zip(&scene.rig.lights)
                .map(|(a, b)| a.intensity()[0] / b.intensity()[0])
                .collect()
        };
        let worst = |indirect: Option<&dyn IndirectLight>| -> f64 {
            let data = LightData::of(&problem, FitSettings::default()).with_indirect(indirect);
            // Off by up to 35 %, their geometric mean kept: with indirect light the images
            // determine the intensities' common factor too (it scales the direct light against
            // the indirect), which the step's gauge holds at the rig's (see the module docs).
            let mut lights = off_intensities(&scene.rig.lights);
            let mean =
                (ratio_to_truth(&lights).iter().map(|x| x.ln()).sum::<f64>() / k as f64).exp();
            for l in &mut lights {
                if let Light::Point { intensity, .. } = l {
                    *intensity = intensity.map(|v| v / mean);
                }
            }
            let mut refiner = Refiner::new(refine, lights.clone());
            for _ in 0..15 {
                refiner.step(&data, &mut lights, &u);
            }
            ratio(&lights)
                .iter()
                .zip(ratio(&scene.rig.lights))
                .map(|(a, b)| (a / b - 1.0).abs())
                .fold(0.0, f64::max)
        };
        let without = worst(None);
        let with = worst(Some(&field));
        assert!(with < 1e-6, "{with}");
        assert!(without > 1e-3, "{without}");
    }

    /// Under the glossy model, on the true mesh: intensity steps with the lobe recover
    /// intensities that are off by up to 35 % (the highlights corrected), the Lambertian light
    /// step does not (its bias is what the correction removes).
    #[test]
    fn glossy_intensity_steps_recover_the_truth_on_the_true_mesh() {
        let scene = Scene::new(SceneKind::Bumps, 32, 100.0, 200.0, 1).unwrap();
        let lobe = Lobe::new(0.3, 1.5);
        let specular: Vec<f64> = scene.albedo.iter().map(|a| 0.2 * a).collect();
        let options =
            crate::render::RenderOptions::default().with_specular(Some(crate::render::Specular {
                albedo: &specular,
                lobe,
            }));
        let images: Vec<f32> = crate::render::render_with(&scene.rig, &scene.surface(), &options)
            .unwrap()
            .iter()
            .map(|&v| v as f32)
            .collect();
        let problem = scene_problem(&scene, &images);
        // The facets' normals: those of the true mesh (as the renderer's).
        let normals = true_normals(&problem);
        let ratio = |ls: &[Light]| -> Vec<f64> {
            let v: Vec<f64> = ls.iter().map(|l| l.intensity()[0]).collect();
            let g = (v.iter().map(|x| x.ln()).sum::<f64>() / v.len() as f64).exp();
            v.iter().map(|x| x / g).collect()
        };
        let worst = |lobe: Option<Lobe>| -> f64 {
            let mut lights = off_intensities(&scene.rig.lights);
            let refine = Refine {
                intensity: true,
                ..Refine::NONE
            };
            let settings = FitSettings {
                lobe,
                ..FitSettings::default()
            };
            let data = LightData::of(&problem, settings).with_normals(Some(&normals));
            let mut refiner = Refiner::new(refine, lights.clone());
            for _ in 0..15 {
                refiner.step(&data, &mut lights, &problem.u0.values().unwrap());
            }
            ratio(&lights)
                .iter()
                .zip(ratio(&scene.rig.lights))
                .map(|(a, b)| (a / b - 1.0).abs())
                .fold(0.0, f64::max)
        };
        let glossy = worst(Some(lobe));
        let lambertian = worst(None);
        assert!(glossy < 1e-4, "glossy light step: {glossy}");
        assert!(lambertian > 10.0 * glossy, "{lambertian} vs {glossy}");
    }

    /// A pass that fits its facets in lanes gives the scalar pass's Gauss-Newton matrix bit for
    /// bit and its other sums to rounding (summed per lane, then the lanes): intensity,
    /// position and both, with and without the Gauss-Newton matrix and cached `beta` vectors,
    /// with LEDs, isotropic and directional lights, unusable observations (NaN, dark,
    /// saturated), facets left with 3 usable ones (not fitted) and 4, and a pass whose facets
    /// are not a multiple of the lanes; every facet in the Gauss-Newton matrix (41²) or every
    /// other (80²).
    #[test]
    fn lane_pass_matches_the_scalar_pass() {
        for size in [41, 80] {
            lane_pass_matches_at(size);
        }
    }

    fn lane_pass_matches_at(size: usize) {
        let scene = Scene::new(SceneKind::Bumps, size, 100.0, 200.0, 3).unwrap();
        let mut images: Vec<f32> = scene.render().unwrap().iter().map(|&v| v as f32).collect();
        let k = scene.rig.n_lights();
        let plane = scene.width * scene.height;
        let peak = images.iter().fold(0.0f32, |m, v| m.max(*v));
        for (idx, v) in images.iter_mut().enumerate() {
            let (light, pixel) = (idx / plane, idx % plane);
            if (idx * 7919) % 97 == 0 {
                *v = f32::NAN;
            } else if (pixel % 53 == 0 && light + 3 < k) || (pixel % 59 == 0 && light + 4 < k) {
                // Most lights of a few pixels dark: 3 usable observations (not fitted) or 4.
                *v = 0.0;
            }
        }
        let problem = scene_problem(&scene, &images);
        let mut lights = off_intensities(&scene.rig.lights);
        for (i, light) in lights.iter_mut().enumerate() {
            if let Light::Point { axis, mu, .. } = light {
                if i % 2 == 0 {
                    *axis = [0.0, 0.0, 1.0];
                    *mu = 0.5 + 0.3 * i as f64;
                }
            }
        }
        lights[1] = Light::Directional {
            direction: [0.1, -0.2, -1.0],
            intensity: [0.3; 3],
        };
        let u = problem.u0.values().unwrap();
        let settings = FitSettings {
            saturation: 0.8 * peak as f64,
            ..FitSettings::default()
        };
        let data = LightData::of(&problem, settings);
        let count = data.subsample().0;
        assert!(data.lanes_apply() && (size > 64 || !count.is_multiple_of(LANES)));
        assert_eq!(
            count.div_ceil(MAX_MATRIX_FACETS),
            if size > 64 { 2 } else { 1 }
        );
        let trial: Vec<Light> = scene.rig.lights.clone();
        let cache = data.betas(&lights, &u).unwrap().unwrap();
        for refine in [
            Refine::NONE.with_intensity(true),
            Refine::NONE.with_position(true),
            Refine::NONE.with_intensity(true).with_position(true),
        ] {
            let layout = Layout::new(&lights, &refine);
            for (with_h, pair) in [(true, (&lights, &lights)), (false, (&trial, &lights))] {
                let pair = (&pair.0[..], &pair.1[..]);
                let cached = match refine.position {
                    false => vec![None, Some(&cache[..])],
                    true => vec![None],
                };
                for cached in cached.into_iter().filter(|c| c.is_none() || with_h) {
                    let run = |lanes: bool| {
                        data.pass_in(pair, &layout, &u, (with_h, lanes), cached)
                            .unwrap()
                    };
                    let (scalar, lanes) = (run(false), run(true));
                    let what = format!("{refine:?} with_h {with_h} cached {}", cached.is_some());
                    assert!(scalar.fits > 0 && scalar.count > 4 * scalar.fits, "{what}");
                    assert!(scalar.fits < scalar.facets, "{what}: some facets unfitted");
                    assert_eq!(
                        (scalar.count, scalar.fits),
                        (lanes.count, lanes.fits),
                        "{what}"
                    );
                    // The sums per lane: the same terms, added in another order.
                    let close = |a: f64, b: f64| (a - b).abs() <= 1e-12 * a.abs().max(b.abs());
                    assert!(close(scalar.sse, lanes.sse), "{what}");
                    assert!(close(scalar.sum_i2, lanes.sum_i2), "{what}");
                    assert_eq!((scalar.sum_z, scalar.facets), (lanes.sum_z, lanes.facets));
                    let largest = scalar.grad.iter().fold(0.0f64, |m, g| m.max(g.abs()));
                    for (a, b) in scalar.grad.iter().zip(&lanes.grad) {
                        assert!((a - b).abs() <= 1e-11 * largest, "{what}: {a} vs {b}");
                    }
                    assert_eq!(scalar.h, lanes.h, "{what}");
                    assert_eq!(with_h, scalar.grad.iter().any(|g| *g != 0.0), "{what}");
                }
            }
        }
    }

    /// A pass with the step's cached `beta` vectors has the sums of one that computes them
    /// per facet (Lambertian and glossy, grey and colour): the cache changes no number.
    #[test]
    fn cached_betas_leave_the_pass_unchanged() {
        for rgb in [false, true] {
            let scene = Scene::new(SceneKind::Bumps, 24, 100.0, 200.0, 2).unwrap();
            let grey: Vec<f32> = scene.render().unwrap().iter().map(|&v| v as f32).collect();
            let mut problem = scene_problem(&scene, &grey);
            // A colour stack: the grey image scaled per channel (k x H x W x 3).
            if rgb {
                let images: Vec<f32> = grey.iter().flat_map(|&v| [v, 0.8 * v, 1.1 * v]).collect();
                let k = scene.rig.n_lights();
                let images = Box::leak(images.into_boxed_slice());
                let stack =
                    ImageStack::with_channels(images, k, scene.height, scene.width, 3).unwrap();
                problem = Problem::new(
                    stack,
                    Box::leak(Box::new(scene.rig.clone())),
                    Some(&scene.mask),
                    InitialDepth::Map(Box::leak(scene.depth.clone().into_boxed_slice())),
                )
                .unwrap();
            }
            let lights = off_intensities(&scene.rig.lights);
            let layout = Layout::new(&lights, &Refine::NONE.with_intensity(true));
            let normals = true_normals(&problem);
            for lobe in [None, Some(Lobe::new(0.3, 1.5))] {
                let settings = FitSettings {
                    lobe,
                    ..FitSettings::default()
                };
                let data = LightData::of(&problem, settings).with_normals(Some(&normals));
                let cache = data
                    .betas(&lights, &problem.u0.values().unwrap())
                    .unwrap()
                    .unwrap();
                let u = &problem.u0.values().unwrap();
                let trial: Vec<Light> = scene.rig.lights.clone();
                for (with_h, pair) in [(true, (&lights, &lights)), (false, (&trial, &lights))] {
                    let pair = (&pair.0[..], &pair.1[..]);
                    let plain = data.pass(pair, &layout, u, with_h, None).unwrap();
                    let cached = data.pass(pair, &layout, u, with_h, Some(&cache)).unwrap();
                    assert_eq!((plain.count, plain.fits), (cached.count, cached.fits));
                    let close = |a: f64, b: f64| (a - b).abs() <= 1e-12 * a.abs().max(b.abs());
                    assert!(
                        close(plain.sse, cached.sse),
                        "{} vs {}",
                        plain.sse,
                        cached.sse
                    );
                    for (a, b) in plain
                        .h
                        .iter()
                        .zip(&cached.h)
                        .chain(plain.grad.iter().zip(&cached.grad))
                    {
                        assert!(close(*a, *b) || (a - b).abs() < 1e-300, "{a} vs {b}");
                    }
                }
            }
        }
    }

    /// A pass's sums are the same bits whatever the number of threads (fixed chunks added in
    /// order), for intensity and position refinement, with the facets of a pass not a multiple
    /// of the lanes or of a chunk; and the chunks cover every facet once.
    #[test]
    fn pass_sums_do_not_depend_on_the_threads() {
        for (n, count) in [(0usize, 0usize), (7, 7), (300, 300), (100_000, 100_000)] {
            let (chunks, size) = chunking(count);
            assert_eq!(size % LANES, 0);
            assert!(chunks <= MAX_CHUNKS && chunks * size >= count);
            assert!(count == 0 || (chunks - 1) * size < count, "{n}");
        }
        let scene = Scene::new(SceneKind::Bumps, 41, 100.0, 200.0, 3).unwrap();
        let images: Vec<f32> = scene.render().unwrap().iter().map(|&v| v as f32).collect();
        let problem = scene_problem(&scene, &images);
        let lights = off_intensities(&scene.rig.lights);
        let u = problem.u0.values().unwrap();
        let data = LightData::of(&problem, FitSettings::default());
        assert!(!data.subsample().0.is_multiple_of(LANES) && chunking(data.subsample().0).0 > 1);
        for refine in [
            Refine::NONE.with_intensity(true),
            Refine::NONE.with_intensity(true).with_position(true),
        ] {
            let layout = Layout::new(&lights, &refine);
            let run = |threads: usize| {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                pool.install(|| {
                    data.pass((&lights, &lights), &layout, &u, true, None)
                        .unwrap()
                })
            };
            let one = run(1);
            assert_eq!(one.facets, data.subsample().0);
            assert!(one.fits > 0 && one.h.iter().any(|v| *v != 0.0));
            for threads in [2, 3] {
                let other = run(threads);
                assert_eq!(one.h, other.h, "{threads} threads");
                assert_eq!(one.grad, other.grad);
                assert_eq!(
                    (one.sse, one.sum_i2, one.sum_z),
                    (other.sse, other.sum_i2, other.sum_z)
                );
                assert_eq!((one.count, one.fits), (other.count, other.fits));
            }
        }
    }

    /// With noisy images the light steps end once a step would move the lights by a small
    /// fraction of their standard errors ([`SETTLED_DECREASE`]) or lower `E` by less than
    /// [`SETTLED_RELATIVE`] of it, with the intensities as
    /// close to the truth as the noise allows. The step that ends them keeps its pass
    /// ([`SettledPass`]), whose conditioning is that of a pass of its own at the same mesh, bit
    /// for bit, and which serves only those lights and that layout.
    #[test]
    fn noisy_light_steps_settle_near_the_truth() {
        let scene = Scene::new(SceneKind::SphereCap, 32, 100.0, 200.0, 0).unwrap();
        let mut images: Vec<f32> = scene.render().unwrap().iter().map(|&v| v as f32).collect();
        let peak = images.iter().fold(0.0f32, |m, v| m.max(*v));
        // 1 % noise from a fixed pseudo-random sequence.
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        for v in images.iter_mut() {
            let mut sum = 0.0;
            for _ in 0..12 {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                sum += (state >> 11) as f64 / (1u64 << 53) as f64;
            }
            *v += (0.01 * peak as f64 * (sum - 6.0)) as f32;
        }
        let problem = scene_problem(&scene, &images);
        let mut lights = off_intensities(&scene.rig.lights);
        let data = LightData::of(&problem, FitSettings::default());
        let mut refiner = Refiner::new(Refine::NONE.with_intensity(true), lights.clone());
        let mut steps = 0;
        while refiner
            .step(&data, &mut lights, &problem.u0.values().unwrap())
            .accepted
        {
            steps += 1;
            assert!(steps < 30, "the light steps did not settle");
        }
        let ratio = |ls: &[Light]| -> Vec<f64> {
            let v: Vec<f64> = ls.iter().map(|l| l.intensity()[0]).collect();
            let g = (v.iter().map(|x| x.ln()).sum::<f64>() / v.len() as f64).exp();
            v.iter().map(|x| x / g).collect()
        };
        let c = conditioning(
            &data,
            &lights,
            &problem.u0.values().unwrap(),
            &Refine::NONE.with_intensity(true),
        )
        .unwrap();
        for ((a, b), se) in ratio(&lights)
            .iter()
            .zip(ratio(&scene.rig.lights))
            .zip(&c.standard_errors)
        {
            // Within 4 standard errors of the truth (the noise's), as a converged fit.
            assert!(
                (a / b - 1.0).abs() < 4.0 * se[0],
                "{a} vs {b} (se {})",
                se[0]
            );
        }
        let intensity = Refine::NONE.with_intensity(true);
        let kept = refiner.settled_pass().expect("the settling step's pass");
        let bits = |c: &Conditioning| -> Vec<u64> {
            let errors = c.standard_errors.iter().flatten();
            let values = c.singular_values.iter().chain(errors);
            values
                .chain([&c.rms_residual, &c.distance])
                .map(|v| v.to_bits())
                .collect()
        };
        let from_kept = kept.conditioning(&lights, &intensity).unwrap().unwrap();
        assert_eq!(bits(&from_kept), bits(&c));
        // Other lights, or another layout of the parameters: not this pass's.
        let moved = off_intensities(&lights);
        assert!(kept.conditioning(&moved, &intensity).is_none());
        let both = intensity.with_position(true);
        assert!(kept.conditioning(&lights, &both).is_none());
        // An accepted step keeps none.
        let mut again = Refiner::new(intensity, lights.clone());
        let mut off = off_intensities(&lights);
        assert!(
            again
                .step(&data, &mut off, &problem.u0.values().unwrap())
                .accepted
        );
        assert!(again.settled_pass().is_none());
    }

    /// On the true mesh, position steps recover positions off by 5 % of the distance.
    #[test]
    fn position_steps_recover_the_truth_on_the_true_mesh() {
        let scene = Scene::new(SceneKind::SphereCap, 32, 100.0, 200.0, 0).unwrap();
        let images: Vec<f32> = scene.render().unwrap().iter().map(|&v| v as f32).collect();
        let problem = scene_problem(&scene, &images);
        let mut lights = scene.rig.lights.clone();
        for (i, l) in lights.iter_mut().enumerate() {
            if let Light::Point { position, .. } = l {
                position[i % 3] += 10.0 * if i % 2 == 0 { 1.0 } else { -1.0 };
            }
        }
        let refine = Refine {
            position: true,
            prior_weight: 0.0,
            ..Refine::NONE
        };
        let data = LightData::of(&problem, FitSettings::default());
        let mut refiner = Refiner::new(refine, lights.clone());
        for _ in 0..40 {
            refiner.step(&data, &mut lights, &problem.u0.values().unwrap());
        }
        for (a, b) in lights.iter().zip(&scene.rig.lights) {
            if let (Light::Point { position: p, .. }, Light::Point { position: q, .. }) = (a, b) {
                let d = sub(*p, *q);
                assert!(norm(d) < 0.01, "{p:?} vs {q:?}");
            }
        }
        let c = conditioning(&data, &lights, &problem.u0.values().unwrap(), &refine).unwrap();
        assert_eq!(c.singular_values.len(), 3 * lights.len());
        assert!(c.singular_values.iter().all(|s| s.is_finite() && *s > 0.0));
    }
}
