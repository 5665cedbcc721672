//! The glossy reflectance model: a diffuse term (transmitted through a rough interface, or
//! Burley's retro-reflective one) plus a GGX specular lobe, and the per-facet fit of a normal, a
//! diffuse and a specular albedo under it.
//!
//! ## The model
//!
//! A facet with unit normal `n` at point `x`, seen along the unit view vector `v` (towards the
//! camera) and lit by light k from the unit direction `l` (towards the light) with attenuation
//! `a` (for a point light `a = aniso / |p - x|^2`, so that `a l = beta(x)` of the light model),
//! has the image
//!
//! ```text
//! I = Phi a (rho_d D(n) + rho_s S(n)),
//! D(n) = (n.l) T(n.l) T(n.v) / T(1)^2,
//! S(n) = F(v.h) / F(1) * G(n.h) * G1(n.l) G1(n.v) / (4 n.v),      h = normalize(l + v),
//! ```
//!
//! - `T(mu)` is the transmittance of the rough interface of the lobe's own roughness and index
//!   ([`rough_transmittance`]: over the GGX normals visible from the direction of cosine `mu`,
//!   the Fresnel-transmitted share times Smith's masking of the refracted ray): light that
//!   enters the surface, scatters below it and leaves again is attenuated twice, more at grazing
//!   angles, and less so the rougher the interface (Mitsuba's `roughplastic` weighs its diffuse
//!   part so). It is tabulated once per lobe and interpolated (`Transmittance`). `D(n) / (n.l)`
//!   is 1 at normal incidence and at most 1 elsewhere, and `eta = 1` gives `T = 1`: the
//!   Lambertian model exactly. (Before, `T` was the smooth interface's `1 - F`: on the
//!   rough plastic renders no index of it matched, see docs/method.md.)
//! - With [`Diffuse::Retro`] the diffuse term is instead Burley's (Disney's principled BRDF, the
//!   diffuse part of Mitsuba's `principled`, read and re-derived):
//!   `D(n) = (n.l) (1 + k F5(n.l)) (1 + k F5(n.v))`, `F5(c) = (1 - c)^5` (Schlick's weight),
//!   `k = F_D90 - 1 = 2 R (l.h)^2 - 1/2` with Disney's roughness `R = sqrt(alpha)` (its GGX alpha
//!   is `R^2`). It is 1 at normal incidence too, falls to half towards grazing angles where
//!   `k = -1/2` (a smooth surface, or light far from the camera), and rises above `n.l` there
//!   where `2 R (l.h)^2 > 1/2`: retro-reflection, a rough surface lit from near the camera
//!   (`l.h` near 1). `l.h` does not depend on `n`: `(l.h)^2` is computed per observation
//!   like the Fresnel factor, and the roughness stays the lobe's (no new unknown). No `(1 - F)`
//!   weighting: Disney's diffuse and specular parts are simply added. Mitsuba's principled
//!   renders (roughness 0.5) are fitted by it at the true points per pixel to 0.017 degrees
//!   against 1.27 with the transmitted term and 0.35 with Lambert's (docs/method.md).
//! - The lobe is the GGX (Trowbridge-Reitz) normal distribution
//!   `G(c) = alpha^2 / (pi (c^2 (alpha^2 - 1) + 1)^2)` with Smith's separable masking
//!   `G1(c) = 2c / (c + sqrt(alpha^2 + (1 - alpha^2) c^2))`; `alpha` is the roughness.
//! - `F(v.h) / F(1)` is the shape of the Fresnel reflectance over the half angle (its scale is in
//!   `rho_s`); at `eta = 1` (no reflection) the shape is taken as 1.
//! - `alpha`, `eta` and the diffuse shape are shared by the whole object (a [`Lobe`]); `n`,
//!   `rho_d` and `rho_s` are per facet. Observations with `n.l <= 0` (attached shadow) or `n.v <= 0` carry no light.
//!
//! ## Evaluation
//!
//! `h` and `F(v.h) / F(1)` do not depend on `n`: an [`Observation`] carries them, computed once
//! per facet. `T(n.v)` and `G1(n.v)` are shared by all lights: they are computed once per normal
//! (a `View`; with the retro-reflective term `F5(n.v)`, and per light `1 + k F5(n.v)`: one
//! multiply-add). Per light and normal there remain `T(n.l)` (a table look-up, or `F5(n.l)`: three
//! multiplications), `G(n.h)` and
//! `G1(n.l)`: one square root and two divisions (each function's reciprocals from one division, see
//! [`Lobe::fresnel`]).
//!
//! ## The fit
//!
//! Per facet the unknowns are `b = rho_d n` (3) and `s = rho_s`, and the model
//! `m_k = Phi_k a_k (|b| D_k(n) + s S_k(n))` with `n = b / |b|`. [`fit`] runs damped
//! Gauss-Newton (Levenberg-Marquardt) on the 4 unknowns from a start (the Lambertian fit, `s = 0`):
//! `d m / d b = Phi a (D n + P grad D + (s / |b|) P grad S)` with `P = I - n n^T`, and
//! `d m / d s = Phi a S` (analytic derivatives). A step is kept only if it lowers the squared
//! residual; `s` is kept non-negative. [`fit_packed_within`] also stops before trying a step
//! shorter than a tolerance of the unknowns ([`STEP_TOLERANCE`] in a reconstruction's local
//! steps).
//!
//! ## Cost
//!
//! [`fit_packed`] holds a facet's observations as a structure of arrays in groups of lights
//! ([`Packed`]) and computes the factors, their gradients and the sums of the normal equations a
//! group at a time, one SIMD lane per light (compiled for AVX-512 or AVX2 where the processor
//! has it): per light one square root, one division (the reciprocals of the GGX and Smith
//! denominators from one division of their product) and the transmittance's table look-up.
//! [`Packed::prepare`] computes the point lights' directions and scales, the half vectors and
//! the Fresnel factors in lanes too. The trial after the last step is evaluated without
//! derivatives. The lanes are `f32` (16 lights to a group; the lane sums, the solves and the
//! unknowns `f64`), or `f64` (8 lights) for a [`Packed::precise`] (the lobe search's fits): one
//! text of the kernels compiled in both precisions. The sums are accumulated per lane, so the
//! results differ from a light-by-light `f64` evaluation ([`Lobe::shade`]) by the lanes'
//! rounding: in the last bits in `f64`, about `1e-6` relative in the factors in `f32`.

use std::cell::RefCell;
use std::sync::{Arc, Mutex, OnceLock};

use rayon::prelude::*;

use nalgebra::{Matrix4, Vector4};

use crate::light::power_lanes;
use crate::vec3::{dot, norm, normalize, scale};

/// The reflectance model the local step fits (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum Reflectance {
    /// `I = rho Phi max(0, n . beta)`: the method's model, the default.
    #[default]
    Lambertian,
    /// Diffuse with Fresnel transmittance plus a GGX lobe: the given shared [`Lobe`], or, with
    /// None, the lobe estimated from the images (see `crate::local::estimate_lobe`).
    Glossy(Option<Lobe>),
}

impl Reflectance {
    /// Whether the model is the glossy one.
    pub fn is_glossy(&self) -> bool {
        matches!(self, Reflectance::Glossy(_))
    }

    /// Name of the model: "lambertian" or "glossy".
    pub fn name(&self) -> &'static str {
        match self {
            Reflectance::Lambertian => "lambertian",
            Reflectance::Glossy(_) => "glossy",
        }
    }
}

/// The shape of the glossy model's diffuse term (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Diffuse {
    /// `D = (n.l) T(n.l) T(n.v) / T(1)^2`: transmitted twice through the rough interface of the
    /// lobe (Mitsuba's `roughplastic`); `eta = 1` is the Lambertian term.
    #[default]
    Transmitted,
    /// `D = (n.l) (1 + k F5(n.l)) (1 + k F5(n.v))`, `F5(c) = (1 - c)^5`,
    /// `k = 2 sqrt(alpha) (l.h)^2 - 1/2`: Burley's diffuse with retro-reflection (Disney's
    /// principled BRDF, Mitsuba's `principled`), its roughness `sqrt(alpha)` the lobe's.
    Retro,
}

impl Diffuse {
    /// Name of the shape: "transmitted" or "retro".
    pub fn name(&self) -> &'static str {
        match self {
            Diffuse::Transmitted => "transmitted",
            Diffuse::Retro => "retro",
        }
    }
}

/// The shared parameters of the glossy model: GGX roughness `alpha`, relative index `eta` and
/// the shape of the diffuse term.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lobe {
    /// GGX roughness (0 < alpha <= 1; about 0.05 polished, 0.3 satin, 0.6 rough).
    pub alpha: f64,
    /// Relative index of refraction of the surface layer (1 <= eta; 1.5 for most plastics).
    pub eta: f64,
    /// The shape of the diffuse term.
    pub diffuse: Diffuse,
}

impl Lobe {
    /// A lobe of roughness `alpha` and index `eta` with the transmitted diffuse term.
    pub fn new(alpha: f64, eta: f64) -> Lobe {
        Lobe {
            alpha,
            eta,
            diffuse: Diffuse::Transmitted,
        }
    }

    /// A lobe of roughness `alpha` and index `eta` with the retro-reflective diffuse term.
    pub fn retro(alpha: f64, eta: f64) -> Lobe {
        Lobe {
            alpha,
            eta,
            diffuse: Diffuse::Retro,
        }
    }

    /// This lobe with the roughness `alpha` (the same index and diffuse shape).
    pub fn with_alpha(&self, alpha: f64) -> Lobe {
        Lobe { alpha, ..*self }
    }

    /// `2 R` of the retro-reflective diffuse term (`R = sqrt(alpha)`, Disney's roughness), or 0
    /// with the transmitted one.
    #[inline]
    fn retro_weight(&self) -> f64 {
        match self.diffuse {
            Diffuse::Retro => 2.0 * self.alpha.sqrt(),
            Diffuse::Transmitted => 0.0,
        }
    }

    /// Checks `0 < alpha <= 1` and `1 <= eta <= 3` (finite).
    pub fn validate(&self) -> crate::Result<()> {
        let bad = |name: &'static str, value: f64, range: &str| crate::Error::OutOfRange {
            name,
            value,
            message: format!(
                "{name} must be a number {range}, got {}",
                crate::error::g6(value)
            ),
        };
        if !(self.alpha > 0.0 && self.alpha <= 1.0) {
            return Err(bad("roughness", self.alpha, "in (0, 1]"));
        }
        if !(self.eta >= 1.0 && self.eta <= 3.0) {
            return Err(bad("eta", self.eta, "from 1 to 3"));
        }
        Ok(())
    }

    /// Unpolarised Fresnel reflectance of a dielectric of index `eta` at incidence cosine `c`
    /// (0 < c <= 1), and its derivative with respect to `c`:
    /// `F = (rs^2 + rp^2) / 2`, `rs = (c - eta t) / (c + eta t)`, `rp = (eta c - t) / (eta c + t)`,
    /// `t = sqrt(1 - (1 - c^2) / eta^2)` the cosine of the refracted ray. With
    /// `eta^2 t^2 = eta^2 - 1 + c^2`, `t - c dt/dc = (eta^2 - 1) / (eta^2 t)`, so that
    /// `d rs / dc = 2 (eta^2 - 1) / (eta t (c + eta t)^2)` and
    /// `d rp / dc = 2 (eta^2 - 1) / (eta t (eta c + t)^2)` (0 at `eta = 1`, where `t = c`); the
    /// three reciprocals come from one division.
    pub fn fresnel(&self, c: f64) -> (f64, f64) {
        let eta = self.eta;
        let e2 = eta * eta;
        let t = (1.0 - (1.0 - c * c) / e2).max(0.0).sqrt();
        let (ds, dp) = (c + eta * t, eta * c + t);
        if t.is_nan() || t <= 0.0 {
            let (rs, rp) = ((c - eta * t) / ds, (eta * c - t) / dp);
            return (0.5 * (rs * rs + rp * rp), 0.0);
        }
        let q = 1.0 / (ds * dp * t);
        let (ids, idp) = (dp * t * q, ds * t * q);
        let rs = (c - eta * t) * ids;
        let rp = (eta * c - t) * idp;
        // 2 (eta^2 - 1) / (eta t) = 2 (eta - 1 / eta) / t
        let w = 2.0 * (eta - 1.0 / eta) * (ds * dp * q);
        (
            0.5 * (rs * rs + rp * rp),
            w * (rs * ids * ids + rp * idp * idp),
        )
    }

    /// `F(1) = ((eta - 1) / (eta + 1))^2`, the reflectance at normal incidence.
    #[inline]
    fn normal_reflectance(&self) -> f64 {
        let r = (self.eta - 1.0) / (self.eta + 1.0);
        r * r
    }

    /// The diffuse and specular factors `D(n)`, `S(n)` of one observation (see the module
    /// documentation) and their gradients with respect to `n` (with `l`, `v` held), or None
    /// where the facet turns away from the light or the camera.
    pub fn shade(&self, n: [f64; 3], l: [f64; 3], v: [f64; 3]) -> Option<Shade> {
        let o = Observation::new(0.0, 1.0, l, v, self);
        with_kernel(self, |k| k.shade(n, &k.view(n, v)?, &o))
    }

    /// [`Lobe::shade`] at the normal `n` seen from `v`, for many lights: the lobe's constants
    /// (its transmittance table) and the terms of `n` and `v` that every light shares are
    /// computed here, once; None where `n.v <= 0` (where [`Lobe::shade`] is None for every
    /// light). [`Shader::shade`] of a light gives [`Lobe::shade`]'s bits.
    pub fn shader(&self, n: [f64; 3], v: [f64; 3]) -> Option<Shader> {
        let kernel = Kernel::new(self);
        let view = kernel.view(n, v)?;
        Some(Shader {
            lobe: *self,
            kernel,
            view,
            n,
            v,
        })
    }
}

/// [`Lobe::shade`] at one normal and view vector, for many lights (see [`Lobe::shader`]).
#[derive(Debug, Clone)]
pub struct Shader {
    lobe: Lobe,
    kernel: Kernel,
    view: View,
    n: [f64; 3],
    v: [f64; 3],
}

impl Shader {
    /// [`Lobe::shade`] of the light from the unit direction `l` (the same bits).
    #[inline]
    pub fn shade(&self, l: [f64; 3]) -> Option<Shade> {
        let o = Observation::new(0.0, 1.0, l, self.v, &self.lobe);
        self.kernel.shade(self.n, &self.view, &o)
    }

    /// The factors `D(n)`, `S(n)` of [`Shader::shade`] (without their gradients) of
    /// [`SHADE_LANES`] lights at once, from their unit directions: `lit[i]` where
    /// [`Shader::shade`] of light `i` is Some, and then `diffuse[i]`, `specular[i]` its factors'
    /// bits (the same operations in the same order, lane by lane; the other lanes' values are
    /// not meaningful). For predictions at a fitted normal (the lobe search's held-out score):
    /// [`Shader::shade`] made the half vector, the Fresnel factor and the factors' gradients of
    /// one light at a time.
    #[inline]
    pub fn values(&self, lights: &[[f64; 3]; SHADE_LANES]) -> ShadeValues {
        values_dispatch(self, lights)
    }
}

/// Lights per call of [`Shader::values`]: one AVX-512 vector of `f64` (two AVX2 vectors).
pub const SHADE_LANES: usize = 8;

/// The factors of [`SHADE_LANES`] lights at one normal (see [`Shader::values`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShadeValues {
    /// Whether the light carries light ([`Shader::shade`] is Some).
    pub lit: [bool; SHADE_LANES],
    /// `D(n)` where `lit`.
    pub diffuse: [f64; SHADE_LANES],
    /// `S(n)` where `lit`.
    pub specular: [f64; SHADE_LANES],
}

simd_dispatch! {
    wide
    /// [`shade_values`] with AVX-512 or AVX2 when the processor has it.
    fn values_dispatch => shade_values(
        shader: &Shader, lights: &[[f64; 3]; SHADE_LANES],
    ) -> ShadeValues;
}

/// [`Shader::values`]: [`Observation::new`]'s half vector and Fresnel factor, and
/// [`Kernel::shade`]'s factors (not their gradients), written lane by lane with the scalar
/// code's operations in its order (so its bits); where the scalar Fresnel factor takes its
/// other branch (no refracted ray, by rounding or at a NaN cosine), that lane calls it.
// (Loops over the lanes by index: the form the compiler turns into vector instructions.)
#[allow(clippy::needless_range_loop)]
#[inline(always)]
fn shade_values(shader: &Shader, l: &[[f64; 3]; SHADE_LANES]) -> ShadeValues {
    const N: usize = SHADE_LANES;
    type L = [f64; N];
    let (n, v, lobe, kernel, w) = (
        shader.n,
        shader.v,
        &shader.lobe,
        &shader.kernel,
        &shader.view,
    );
    // `Observation::new`: h = normalize(l + v), F(v.h) / F(1), (l.h)^2.
    let mut a = [[0.0; N]; 3];
    for j in 0..3 {
        for i in 0..N {
            a[j][i] = l[i][j] + v[j];
        }
    }
    let mut len: L = [0.0; N];
    for i in 0..N {
        len[i] = (a[0][i] * a[0][i] + a[1][i] * a[1][i] + a[2][i] * a[2][i]).sqrt();
    }
    let mut h = [[0.0; N]; 3];
    for j in 0..3 {
        for i in 0..N {
            h[j][i] = a[j][i] / len[i];
        }
    }
    let f1 = lobe.normal_reflectance();
    let mut fresnel: L = [1.0; N];
    if f1 > 1e-12 {
        // `Lobe::fresnel(v.h).0`, its branch with a refracted ray (`t > 0`).
        let eta = lobe.eta;
        let e2 = eta * eta;
        let mut c: L = [0.0; N];
        let mut t: L = [0.0; N];
        for i in 0..N {
            c[i] = v[0] * h[0][i] + v[1] * h[1][i] + v[2] * h[2][i];
            t[i] = (1.0 - (1.0 - c[i] * c[i]) / e2).max(0.0).sqrt();
        }
        for i in 0..N {
            let (ds, dp) = (c[i] + eta * t[i], eta * c[i] + t[i]);
            let q = 1.0 / (ds * dp * t[i]);
            let (ids, idp) = (dp * t[i] * q, ds * t[i] * q);
            let rs = (c[i] - eta * t[i]) * ids;
            let rp = (eta * c[i] - t[i]) * idp;
            fresnel[i] = 0.5 * (rs * rs + rp * rp) / f1;
        }
        for i in 0..N {
            if t[i].is_nan() || t[i] <= 0.0 {
                fresnel[i] = lobe.fresnel(c[i]).0 / f1;
            }
        }
    }
    // `Kernel::shade`'s factors.
    let mut cl: L = [0.0; N];
    let mut ch: L = [0.0; N];
    for i in 0..N {
        cl[i] = n[0] * l[i][0] + n[1] * l[i][1] + n[2] * l[i][2];
        ch[i] = n[0] * h[0][i] + n[1] * h[1][i] + n[2] * h[2][i];
    }
    let lit: [bool; N] = std::array::from_fn(|i| !(cl[i] <= 0.0 || w.cv <= 0.0));
    let mut diffuse: L = [0.0; N];
    if kernel.retro > 0.0 {
        for i in 0..N {
            let cd = l[i][0] * h[0][i] + l[i][1] * h[1][i] + l[i][2] * h[2][i];
            let k = kernel.retro * (cd * cd) - 0.5;
            let u = 1.0 - cl[i];
            let u4 = (u * u) * (u * u);
            let (x, y) = (1.0 + k * (u4 * u), 1.0 + k * w.tv);
            diffuse[i] = cl[i] * x * y;
        }
    } else {
        let tl = match &kernel.table {
            None => [1.0; N],
            Some(t) => t.at_lanes(&cl).0,
        };
        for i in 0..N {
            diffuse[i] = cl[i] * tl[i] * w.tv;
        }
    }
    let a2 = kernel.a2;
    let mut specular: L = [0.0; N];
    for i in 0..N {
        let c = ch[i];
        let iq = 1.0 / (c * c * (a2 - 1.0) + 1.0);
        let d = a2 * std::f64::consts::FRAC_1_PI * iq * iq;
        let c = cl[i];
        let r = (a2 + (1.0 - a2) * c * c).sqrt();
        let q = 1.0 / (c * r * (c + r));
        let g = 2.0 * c * c * r * q;
        let s = fresnel[i] * d * g * w.gv;
        specular[i] = if ch[i] > 0.0 { s } else { 0.0 };
    }
    ShadeValues {
        lit,
        diffuse,
        specular,
    }
}

thread_local! {
    /// The kernel of the lobe a thread last shaded with [`Lobe::shade`], with its
    /// [`kernel_key`] (see [`with_kernel`]).
    static LAST_KERNEL: RefCell<Option<(KernelKey, Kernel)>> = const { RefCell::new(None) };
}

/// `f` of the kernel of `lobe`, the thread's last one where its key is the same: a scalar
/// evaluation per light ([`Lobe::shade`]) then looks the transmittance table up (a thread-local
/// search and a reference count shared by all threads) once per lobe, not once per call. The
/// same kernel, so the same bits.
fn with_kernel<T>(lobe: &Lobe, f: impl FnOnce(&Kernel) -> T) -> T {
    let key = kernel_key(lobe);
    LAST_KERNEL.with(|cell| {
        let mut last = cell.borrow_mut();
        if !matches!(&*last, Some((kept, _)) if *kept == key) {
            *last = Some((key, Kernel::new(lobe)));
        }
        let (_, k) = last.as_ref().expect("a kernel was kept");
        f(k)
    })
}

/// The constants of a [`Lobe`] that every evaluation uses.
#[derive(Debug, Clone)]
struct Kernel {
    /// `alpha^2`.
    a2: f64,
    /// The diffuse transmittance `T(c) / T(1)` of the lobe; None where `eta = 1` (`T = 1`, the
    /// Lambertian diffuse term) or the diffuse term is the retro-reflective one.
    table: Option<Arc<Transmittance>>,
    /// `2 R` of the retro-reflective diffuse term (see [`Diffuse::Retro`]), 0 without it.
    retro: f64,
}

/// The terms of a normal `n` that every light shares (see [`Kernel::view`]).
#[derive(Debug, Clone, Copy)]
struct View {
    /// `n.v`.
    cv: f64,
    /// `T(n.v) / T(1)` and its derivative; with the retro-reflective diffuse term
    /// `F5(n.v) = (1 - n.v)^5` and its derivative instead.
    tv: f64,
    dtv: f64,
    /// `G1(n.v) / (4 n.v)`.
    gv: f64,
    /// `d ln(G1(c) / c) / dc` at `c = n.v`.
    dgv: f64,
}

impl Kernel {
    fn new(lobe: &Lobe) -> Kernel {
        let retro = lobe.retro_weight();
        Kernel {
            a2: lobe.alpha * lobe.alpha,
            table: (lobe.eta != 1.0 && retro == 0.0).then(|| Transmittance::cached(lobe)),
            retro,
        }
    }

    /// `F5(c) = (1 - c)^5` and its derivative, the weight of the retro-reflective diffuse term's
    /// factors.
    #[inline(always)]
    fn schlick(c: f64) -> (f64, f64) {
        let u = 1.0 - c;
        let u4 = (u * u) * (u * u);
        (u4 * u, -5.0 * u4)
    }

    /// `T(c) / T(1)` and its derivative (1 and 0 for `eta = 1`).
    #[inline(always)]
    fn transmittance(&self, c: f64) -> (f64, f64) {
        match &self.table {
            None => (1.0, 0.0),
            Some(t) => t.at(c),
        }
    }

    /// GGX distribution `G(c)` of the half-vector cosine `c` and `G'(c) / G(c)`.
    #[inline]
    fn ggx(&self, c: f64) -> (f64, f64) {
        let iq = 1.0 / (c * c * (self.a2 - 1.0) + 1.0);
        (
            self.a2 * std::f64::consts::FRAC_1_PI * iq * iq,
            -4.0 * c * (self.a2 - 1.0) * iq,
        )
    }

    /// Smith masking `G1(c)` and `G1'(c) / G1(c)`: with `r = sqrt(alpha^2 + (1 - alpha^2) c^2)`,
    /// `G1 = 2c / (c + r)` and `G1' / G1 = alpha^2 / (c r (c + r))`.
    #[inline(always)]
    fn smith(&self, c: f64) -> (f64, f64) {
        let r = (self.a2 + (1.0 - self.a2) * c * c).sqrt();
        let w = 1.0 / (c * r * (c + r));
        (2.0 * c * c * r * w, self.a2 * w)
    }

    /// The terms of the normal `n` that every light shares, or None where `n.v <= 0`.
    #[inline(always)]
    fn view(&self, n: [f64; 3], v: [f64; 3]) -> Option<View> {
        let cv = dot(n, v);
        if cv <= 0.0 {
            return None;
        }
        let (tv, dtv) = match self.retro > 0.0 {
            true => Kernel::schlick(cv),
            false => self.transmittance(cv),
        };
        let (g, dg) = self.smith(cv);
        let icv = 1.0 / cv;
        Some(View {
            cv,
            tv,
            dtv,
            gv: 0.25 * g * icv,
            dgv: dg - icv,
        })
    }

    /// [`Lobe::shade`] of observation `o` at the normal `n` with its shared terms `w`.
    #[inline]
    fn shade(&self, n: [f64; 3], w: &View, o: &Observation) -> Option<Shade> {
        let (l, h) = (o.light, o.half);
        let cl = dot(n, l);
        if cl <= 0.0 || w.cv <= 0.0 {
            return None;
        }
        let (diffuse, wl, wv) = if self.retro > 0.0 {
            // D = c A B, A = 1 + k F5(c), B = 1 + k F5(n.v), k = 2 R (l.h)^2 - 1/2.
            let k = self.retro * o.retro - 0.5;
            let (fl, dfl) = Kernel::schlick(cl);
            let (a, b) = (1.0 + k * fl, 1.0 + k * w.tv);
            (cl * a * b, (a + cl * k * dfl) * b, cl * a * k * w.dtv)
        } else {
            let (tl, dtl) = self.transmittance(cl);
            (cl * tl * w.tv, (tl + cl * dtl) * w.tv, cl * tl * w.dtv)
        };
        let ch = dot(n, h);
        let (specular, sh, sl, sv) = if ch > 0.0 {
            let (d, dd) = self.ggx(ch);
            let (gl, dgl) = self.smith(cl);
            let s = o.fresnel * d * gl * w.gv;
            (s, s * dd, s * dgl, s * w.dgv)
        } else {
            (0.0, 0.0, 0.0, 0.0)
        };
        Some(Shade {
            diffuse,
            specular,
            d_diffuse: std::array::from_fn(|j| wl * l[j] + wv * o.view[j]),
            d_specular: std::array::from_fn(|j| sh * h[j] + sl * l[j] + sv * o.view[j]),
        })
    }
}

/// The factors of one observation under the glossy model (see [`Lobe::shade`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Shade {
    /// `D(n)`.
    pub diffuse: f64,
    /// `S(n)`.
    pub specular: f64,
    /// `grad_n D`.
    pub d_diffuse: [f64; 3],
    /// `grad_n S`.
    pub d_specular: [f64; 3],
}

/// One observation of a facet: the image value, the light's scale `Phi a` and its unit direction,
/// with the terms that do not depend on the normal for one view vector and lobe (see
/// [`Observation::new`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Observation {
    /// The image value.
    pub value: f64,
    /// `Phi a`: the light's intensity times its attenuation at the facet.
    pub scale: f64,
    /// Unit vector from the facet towards the light.
    pub light: [f64; 3],
    /// Unit vector from the facet towards the camera.
    view: [f64; 3],
    /// `h = normalize(l + v)`.
    half: [f64; 3],
    /// `F(v.h) / F(1)` of the lobe (1 where `F(1)` vanishes).
    fresnel: f64,
    /// `(l.h)^2`, of which the retro-reflective diffuse term's `k` (see [`Diffuse::Retro`]).
    retro: f64,
}

impl Observation {
    /// The observation of image value `value` under a light of scale `Phi a` from the unit
    /// direction `light`, seen from the unit direction `view`, for fits under `lobe`.
    pub fn new(value: f64, scale: f64, light: [f64; 3], view: [f64; 3], lobe: &Lobe) -> Self {
        let half = normalize([light[0] + view[0], light[1] + view[1], light[2] + view[2]]);
        let f1 = lobe.normal_reflectance();
        let fresnel = if f1 > 1e-12 {
            lobe.fresnel(dot(view, half)).0 / f1
        } else {
            1.0
        };
        let cd = dot(light, half);
        Observation {
            value,
            scale,
            light,
            view,
            half,
            fresnel,
            retro: cd * cd,
        }
    }
}

/// Intervals of the diffuse transmittance's table over the cosine: nodes at `mu = i /
/// TABLE_STEPS` (Mitsuba tabulates the same function at 64 cosines and interpolates linearly).
const TABLE_STEPS: usize = 256;

/// Gauss-Legendre nodes per dimension of the integral of [`rough_transmittance`] (the
/// integrand is smooth over the visible normals but for the cut where the refracted ray turns
/// back: 24 nodes agree with 48 within 5e-4 on the lobe search's grids).
const TABLE_QUADRATURE: usize = 24;

/// Lobes whose tables each thread keeps, and all threads share (see [`Transmittance::cached`]):
/// more than a run's lobe searches try. A search from scratch tries 28 lobes (its first line the
/// same 10 every time), a search near a lobe about 8, and a reconstruction with the lobe
/// estimated searches twice from scratch and once or twice near: with 16 the second search
/// computed its first line's tables again (69 tables at 256², now 58). A table is 8 KiB.
const TABLE_CACHE: usize = 64;

/// The Gauss-Legendre nodes and weights of `n` points on `[0, 1]` (Newton's iteration on the
/// Legendre polynomial from the usual start; the weights sum to 1).
fn gauss_legendre(n: usize) -> Vec<(f64, f64)> {
    (0..n)
        .map(|i| {
            let mut x = (std::f64::consts::PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
            let mut dp = 1.0;
            for _ in 0..100 {
                // p_n(x) and p_n'(x) by the three-term recurrence.
                let (mut p0, mut p1) = (1.0, x);
                for k in 2..=n {
                    let k = k as f64;
                    (p0, p1) = (p1, ((2.0 * k - 1.0) * x * p1 - (k - 1.0) * p0) / k);
                }
                dp = n as f64 * (x * p1 - p0) / (x * x - 1.0);
                let dx = p1 / dp;
                x -= dx;
                if dx.abs() < 1e-15 {
                    break;
                }
            }
            let w = 2.0 / ((1.0 - x * x) * dp * dp);
            (0.5 * (1.0 - x), 0.5 * w)
        })
        .collect()
}

/// A GGX visible normal of roughness `alpha` for the direction `(sin, 0, mu)` (normal `z`) from
/// the point `(u1, u2)` of the unit square, by Heitz's construction (2018): the direction
/// stretched to roughness 1, a point of the unit disc (radius `sqrt(u1)`, angle `2 pi u2`)
/// warped onto the visible half of the projected hemisphere, lifted onto it and unstretched.
#[cfg(test)]
fn visible_normal(alpha: f64, mu: f64, (r_cos, r_sin): (f64, f64)) -> [f64; 3] {
    let node = Node::new((r_cos, r_sin), 1.0);
    VisibleFrame::new(alpha, mu).normal(&node)
}

/// A node of the unit square for `visible_normal` (tests) with its weight: the point of the unit disc
/// `(sqrt(u1) cos(2 pi u2), sqrt(u1) sin(2 pi u2))` and `sqrt(1 - (sqrt(u1) cos(2 pi u2))^2)`,
/// which does not depend on the direction (computed once per node, not once per node and
/// cosine: the same operations, the same bits).
#[derive(Debug, Clone, Copy)]
struct Node {
    r_cos: f64,
    r_sin: f64,
    /// `sqrt(1 - r_cos^2)`.
    r_rest: f64,
    weight: f64,
}

impl Node {
    fn new((r_cos, r_sin): (f64, f64), weight: f64) -> Node {
        Node {
            r_cos,
            r_sin,
            r_rest: (1.0 - r_cos * r_cos).sqrt(),
            weight,
        }
    }
}

/// The terms of `visible_normal` (tests) that depend on the direction alone (once per cosine of a
/// table, not once per node): the stretched direction `vh`, its frame `(t1, t2, vh)` and the
/// warp's weight `s = (1 + vh_z) / 2`.
struct VisibleFrame {
    alpha: f64,
    vh: [f64; 3],
    t1: [f64; 3],
    t2: [f64; 3],
    s: f64,
}

impl VisibleFrame {
    fn new(alpha: f64, mu: f64) -> VisibleFrame {
        let sin = (1.0 - mu * mu).max(0.0).sqrt();
        let vh = normalize([alpha * sin, 0.0, mu]);
        // An orthonormal frame (t1, t2, vh) with t1 = (0, 1, 0) (x at normal incidence).
        let (t1, t2) = if vh[0] > 0.0 {
            ([0.0, 1.0, 0.0], [-vh[2], 0.0, vh[0]])
        } else {
            ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
        };
        VisibleFrame {
            alpha,
            vh,
            t1,
            t2,
            s: 0.5 * (1.0 + vh[2]),
        }
    }

    /// The visible normal of `node` (see `visible_normal`, tests).
    #[inline(always)]
    fn normal(&self, node: &Node) -> [f64; 3] {
        let (s, vh, t1, t2) = (self.s, self.vh, self.t1, self.t2);
        let (p1, p2) = (node.r_cos, (1.0 - s) * node.r_rest + s * node.r_sin);
        let p3 = (1.0 - p1 * p1 - p2 * p2).max(0.0).sqrt();
        let nh = [
            p1 * t1[0] + p2 * t2[0] + p3 * vh[0],
            p1 * t1[1] + p2 * t2[1] + p3 * vh[1],
            p1 * t1[2] + p2 * t2[2] + p3 * vh[2],
        ];
        let alpha = self.alpha;
        normalize([alpha * nh[0], alpha * nh[1], nh[2].max(1e-9)])
    }
}

/// The light a GGX dielectric interface of roughness `alpha` and index `eta > 1` transmits into
/// the body from the direction of cosine `mu`, in the single-scattering microfacet model: the
/// expectation over the visible normals `m` of the direction `w` (distribution
/// `G1(w, m) max(0, w.m) D(m) / (w.n)`) of the transmitted share `1 - F(w.m)` times Smith's
/// masking `G1(t, m)` of the refracted ray `t`,
///
/// ```text
/// T(mu) = E_{m ~ D_w} [(1 - F(w.m)) G1(t, m)],    t = -w / eta + (w.m / eta - c_t) m,
/// ```
///
/// `c_t = sqrt(1 - (1 - (w.m)^2) / eta^2)`, integrated with `TABLE_QUADRATURE^2`
/// Gauss-Legendre nodes over the square of `visible_normal`. By reciprocity the same factor
/// weighs the light leaving the body towards the camera. This is what Mitsuba's `roughplastic`
/// weighs its diffuse part by; it falls towards grazing light less than the smooth interface's
/// `1 - F(mu)` (at `alpha = 0.3`, `eta = 1.5`: 0.81 of `T(1)` at `mu = 0.2` against 0.69), as the
/// visible facets turn towards the light. At `eta = 1` no light is reflected but the refracted
/// ray is still masked: the model's `eta = 1` is the Lambertian term instead.
pub fn rough_transmittance(alpha: f64, eta: f64, mu: f64) -> f64 {
    transmittance_dispatch(
        alpha,
        eta,
        mu,
        &square_nodes(&gauss_legendre(TABLE_QUADRATURE)),
    )
}

/// The nodes of the unit square for `visible_normal` (tests; `sqrt(u1) cos(2 pi u2)`,
/// `sqrt(u1) sin(2 pi u2)`) with their weights.
fn square_nodes(nodes: &[(f64, f64)]) -> Vec<Node> {
    let mut out = Vec::with_capacity(nodes.len() * nodes.len());
    for &(u1, w1) in nodes {
        for &(u2, w2) in nodes {
            let (s, c) = (2.0 * std::f64::consts::PI * u2).sin_cos();
            out.push(Node::new((u1.sqrt() * c, u1.sqrt() * s), w1 * w2));
        }
    }
    out
}

/// Nodes of the transmittance integral per lane group ([`transmittance_lanes`]): 8 `f64`, one
/// AVX-512 vector. (The kernels' lanes are [`single::W`] and [`double::W`].)
const W: usize = 8;

/// One `f64` per node of a group of the integral.
type Lanes = [f64; W];

/// `W` lanes computed by `f` (see [`crate::lanes`]).
#[inline(always)]
fn lanes(f: impl FnMut(usize) -> f64) -> Lanes {
    crate::lanes(f)
}

simd_dispatch! {
    /// [`transmittance_lanes`] with AVX2 when the processor has it.
    fn transmittance_dispatch => transmittance_lanes(
        alpha: f64, eta: f64, mu: f64, nodes: &[Node],
    ) -> f64;
}

/// [`rough_transmittance`]'s integral over the given nodes ([`transmittance_from`]) with the
/// integrand of `W` nodes at a time in lanes: the same operations in the same order on each node
/// (the visible normal, `F(min(w.m, 1))` as [`Lobe::fresnel`], the refracted ray's cosine and
/// masking), and the terms summed one node at a time in the nodes' order, so the same bits. The
/// refracted cosine that `Lobe::fresnel` computes is the one the masking uses (`w.m <= 1`): made
/// once, not twice. The square roots and divisions, most of a table's cost, are then made `W`
/// at a time.
#[inline(always)]
fn transmittance_lanes(alpha: f64, eta: f64, mu: f64, nodes: &[Node]) -> f64 {
    let mu = mu.clamp(1e-6, 1.0);
    let w = [(1.0 - mu * mu).max(0.0).sqrt(), 0.0, mu];
    let lobe = Lobe::new(alpha, eta);
    let frame = VisibleFrame::new(alpha, mu);
    let (s, vh, t1, t2) = (frame.s, frame.vh, frame.t1, frame.t2);
    let a2 = alpha * alpha;
    let e2 = eta * eta;
    let mut sum = 0.0;
    let mut chunks = nodes.chunks_exact(W);
    for chunk in &mut chunks {
        // `VisibleFrame::normal`, lane by lane.
        let p1 = lanes(|i| chunk[i].r_cos);
        let p2 = lanes(|i| (1.0 - s) * chunk[i].r_rest + s * chunk[i].r_sin);
        let p3 = lanes(|i| (1.0 - p1[i] * p1[i] - p2[i] * p2[i]).max(0.0).sqrt());
        let nh: [Lanes; 3] =
            std::array::from_fn(|j| lanes(|i| p1[i] * t1[j] + p2[i] * t2[j] + p3[i] * vh[j]));
        let u = [
            lanes(|i| alpha * nh[0][i]),
            lanes(|i| alpha * nh[1][i]),
            lanes(|i| nh[2][i].max(1e-9)),
        ];
        let len = lanes(|i| (u[0][i] * u[0][i] + u[1][i] * u[1][i] + u[2][i] * u[2][i]).sqrt());
        let m: [Lanes; 3] = std::array::from_fn(|j| lanes(|i| u[j][i] / len[i]));
        let c = lanes(|i| w[0] * m[0][i] + w[1] * m[1][i] + w[2] * m[2][i]);
        // The refracted ray's cosine, and `Lobe::fresnel(min(c, 1)).0` from it where `c <= 1`
        // and the ray exists (`t > 0`; `Lobe::fresnel` computes the same `t` there).
        let t = lanes(|i| (1.0 - (1.0 - c[i] * c[i]) / e2).max(0.0).sqrt());
        let ds = lanes(|i| c[i] + eta * t[i]);
        let dp = lanes(|i| eta * c[i] + t[i]);
        let q = lanes(|i| 1.0 / (ds[i] * dp[i] * t[i]));
        let f = lanes(|i| {
            let rs = (c[i] - eta * t[i]) * (dp[i] * t[i] * q[i]);
            let rp = (eta * c[i] - t[i]) * (ds[i] * t[i] * q[i]);
            0.5 * (rs * rs + rp * rp)
        });
        let tz = lanes(|i| -w[2] / eta + (c[i] / eta - t[i]) * m[2][i]);
        let cz = lanes(|i| -tz[i]);
        let g1 = lanes(|i| 2.0 * cz[i] / (cz[i] + (a2 + (1.0 - a2) * cz[i] * cz[i]).sqrt()));
        for i in 0..W {
            if c[i] <= 0.0 || tz[i] >= 0.0 {
                continue;
            }
            let f = if c[i] <= 1.0 && t[i] > 0.0 {
                f[i]
            } else {
                // A cosine above 1 by rounding, or no refracted ray (none for eta > 1 but by
                // rounding): as the node-by-node integral.
                lobe.fresnel(c[i].min(1.0)).0
            };
            sum += chunk[i].weight * (1.0 - f) * g1[i];
        }
    }
    transmittance_from(alpha, eta, mu, chunks.remainder(), sum)
}

/// [`rough_transmittance`] over the given nodes, one node at a time.
#[cfg(test)]
fn transmittance_integral(alpha: f64, eta: f64, mu: f64, nodes: &[Node]) -> f64 {
    transmittance_from(alpha, eta, mu, nodes, 0.0)
}

/// `sum` plus the terms of [`rough_transmittance`]'s integral of the given nodes, one node at a
/// time.
fn transmittance_from(alpha: f64, eta: f64, mu: f64, nodes: &[Node], sum: f64) -> f64 {
    let mu = mu.clamp(1e-6, 1.0);
    let w = [(1.0 - mu * mu).max(0.0).sqrt(), 0.0, mu];
    let lobe = Lobe::new(alpha, eta);
    let frame = VisibleFrame::new(alpha, mu);
    let a2 = alpha * alpha;
    let e2 = eta * eta;
    let mut sum = sum;
    for node in nodes {
        let m = frame.normal(node);
        let c = dot(w, m);
        if c <= 0.0 {
            continue;
        }
        let (f, _) = lobe.fresnel(c.min(1.0));
        let ct = (1.0 - (1.0 - c * c) / e2).max(0.0).sqrt();
        let tz = -w[2] / eta + (c / eta - ct) * m[2];
        if tz >= 0.0 {
            continue;
        }
        // Smith's G1 of the refracted ray (below the surface: its cosine with -n).
        let cz = -tz;
        let g1 = 2.0 * cz / (cz + (a2 + (1.0 - a2) * cz * cz).sqrt());
        sum += node.weight * (1.0 - f) * g1;
    }
    sum
}

/// The `TABLE_QUADRATURE^2` nodes of the tables, computed once.
fn table_nodes() -> &'static [Node] {
    static NODES: OnceLock<Vec<Node>> = OnceLock::new();
    NODES.get_or_init(|| square_nodes(&gauss_legendre(TABLE_QUADRATURE)))
}

/// [`rough_transmittance`] of a lobe relative to its value at normal incidence, `T(c) / T(1)`,
/// tabulated at `TABLE_STEPS + 1` cosines and interpolated by a cubic Hermite spline with the
/// central differences of the table as slopes (Catmull-Rom; one-sided at the ends): continuous
/// with its derivative, which [`Transmittance::at`] returns exactly (the derivative of the
/// interpolant, so that the fits' gradients are those of the values they use).
#[derive(Debug)]
struct Transmittance {
    /// Per interval `i` (`mu` from `i / N` to `(i + 1) / N`), the cubic's coefficients in
    /// `t = N mu - i`: `T = c0 + c1 t + c2 t^2 + c3 t^3`.
    cubic: [[f64; 4]; TABLE_STEPS],
    /// `cubic` rounded to `f32`, for the lanes of the fits ([`Transmittance::at_lanes_f32`]).
    cubic32: [[f32; 4]; TABLE_STEPS],
}

/// A lobe's table with its key, the bits of `(alpha, eta)`.
type Keyed = ((u64, u64), Arc<Transmittance>);

/// The tables of the lobes all threads used last (see [`Transmittance::cached`]).
static SHARED_TABLES: Mutex<Vec<Keyed>> = Mutex::new(Vec::new());

thread_local! {
    /// The tables of the lobes a thread used last (see [`Transmittance::cached`]).
    static TABLES: RefCell<Vec<Keyed>> =
        const { RefCell::new(Vec::new()) };
}

/// The body of [`Transmittance::at_lanes`] (`f64`, `cubic`) and
/// [`Transmittance::at_lanes_f32`] (`f32`, `cubic32`): one text for both lane types, the lanes
/// `$c` of type `$f` and the coefficients of field `$table` of `$t`. (Loops over the lanes by
/// index: the form the compiler turns into vector instructions.)
macro_rules! table_lanes {
    ($t:ident, $c:ident, $f:ty, $table:ident) => {{
        let steps = TABLE_STEPS as $f;
        let mut u = [0.0; N];
        // The interval in `i32` lanes (`u` is in `[0, N]` or NaN, where both conversions give
        // the same integer, 0 for NaN): the conversion to `usize` was made lane by lane.
        let mut index = [0i32; N];
        let mut t = [0.0; N];
        for i in 0..N {
            u[i] = $c[i].clamp(0.0, 1.0) * steps;
            // (`max` and `min` send NaN to 0: the conversion of a value in range, in lanes.)
            let at = u[i].max(0.0).min(steps - 1.0);
            // SAFETY: `at` is finite and in `[0, TABLE_STEPS - 1]`, within `i32`.
            index[i] = unsafe { at.to_int_unchecked::<i32>() };
            t[i] = u[i] - index[i] as $f;
        }
        // The coefficients by lane, from the flat table (an index at most `4 TABLE_STEPS - 1`).
        let flat = $t.$table.as_flattened();
        let mut k = [[0.0; N]; 4];
        for j in 0..4 {
            for i in 0..N {
                k[j][i] = flat[4 * index[i] as usize + j];
            }
        }
        let mut value = [0.0; N];
        let mut slope = [0.0; N];
        for i in 0..N {
            value[i] = k[0][i] + t[i] * (k[1][i] + t[i] * (k[2][i] + t[i] * k[3][i]));
            slope[i] = steps * (k[1][i] + t[i] * (2.0 * k[2][i] + t[i] * 3.0 * k[3][i]));
        }
        (value, slope)
    }};
}

impl Transmittance {
    /// The table of a lobe (`alpha > 0`, `eta > 1`).
    fn new(lobe: &Lobe) -> Transmittance {
        let nodes = table_nodes();
        let v: Vec<f64> = (0..=TABLE_STEPS)
            .map(|i| {
                let mu = i as f64 / TABLE_STEPS as f64;
                transmittance_dispatch(lobe.alpha, lobe.eta, mu, nodes)
            })
            .collect();
        let t1 = v[TABLE_STEPS];
        let v: Vec<f64> = v.iter().map(|x| x / t1).collect();
        let slope = |i: usize| match i {
            0 => v[1] - v[0],
            i if i == TABLE_STEPS => v[i] - v[i - 1],
            i => 0.5 * (v[i + 1] - v[i - 1]),
        };
        let cubic: [[f64; 4]; TABLE_STEPS] = std::array::from_fn(|i| {
            let (p0, p1, m0, m1) = (v[i], v[i + 1], slope(i), slope(i + 1));
            [
                p0,
                m0,
                3.0 * (p1 - p0) - 2.0 * m0 - m1,
                2.0 * (p0 - p1) + m0 + m1,
            ]
        });
        Transmittance {
            cubic,
            cubic32: cubic.map(|row| row.map(|x| x as f32)),
        }
    }

    /// The table of `lobe`, computed once for the last [`TABLE_CACHE`] lobes: each thread looks
    /// in its own list first (no lock), then in the list all threads share, where a missing
    /// table is computed under the lock (about 2 ms; the other threads that need it wait instead
    /// of computing it again: the lobe search's threads all move to the same lobe at once, which
    /// is why [`prepare_tables`] computes the tables of a line of the search beforehand).
    fn cached(lobe: &Lobe) -> Arc<Transmittance> {
        let key = table_key(lobe);
        if let Some(table) = TABLES.with(|t| find_table(&t.borrow(), key)) {
            return table;
        }
        let table = {
            let mut shared = SHARED_TABLES.lock().unwrap_or_else(|e| e.into_inner());
            match find_table(&shared, key) {
                Some(table) => table,
                None => {
                    let table = Arc::new(Transmittance::new(lobe));
                    keep_table(&mut shared, key, &table);
                    table
                }
            }
        };
        TABLES.with(|t| keep_table(&mut t.borrow_mut(), key, &table));
        table
    }

    /// `T(c) / T(1)` and its derivative at `0 <= c <= 1`: [`Transmittance::at_lanes`] with one
    /// lane.
    #[inline(always)]
    fn at(&self, c: f64) -> (f64, f64) {
        let (value, slope) = self.at_lanes(&[c]);
        (value[0], slope[0])
    }

    /// [`Transmittance::at`] of `N` cosines at once: the same operations on each lane (so the
    /// same bits), written as loops over the lanes so that they are inlined into the vector
    /// code of their caller (`std::array::from_fn` over [`Transmittance::at`] was compiled as a
    /// separate, non-vector function call per group: 7 % of a 256² glossy profile).
    #[allow(clippy::needless_range_loop)]
    #[inline(always)]
    fn at_lanes<const N: usize>(&self, c: &[f64; N]) -> ([f64; N], [f64; N]) {
        table_lanes!(self, c, f64, cubic)
    }

    /// [`Transmittance::at_lanes`] in `f32` lanes from the rounded coefficients: the value and
    /// slope to about `1e-6` (the coefficients' and `t`'s rounding).
    #[allow(clippy::needless_range_loop)]
    #[inline(always)]
    fn at_lanes_f32<const N: usize>(&self, c: &[f32; N]) -> ([f32; N], [f32; N]) {
        table_lanes!(self, c, f32, cubic32)
    }
}

/// The key of a lobe's table: the bits of `(alpha, eta)`.
fn table_key(lobe: &Lobe) -> (u64, u64) {
    (lobe.alpha.to_bits(), lobe.eta.to_bits())
}

/// The table of `key` in `tables`, looked for from the last one kept (the lobe of the last fits,
/// or of the search's line).
fn find_table(tables: &[Keyed], key: (u64, u64)) -> Option<Arc<Transmittance>> {
    let mut newest = tables.iter().rev();
    newest.find(|t| t.0 == key).map(|t| Arc::clone(&t.1))
}

/// Keeps `table` in `tables`, dropping the oldest one kept beyond [`TABLE_CACHE`].
fn keep_table(tables: &mut Vec<Keyed>, key: (u64, u64), table: &Arc<Transmittance>) {
    if tables.len() >= TABLE_CACHE {
        tables.remove(0);
    }
    tables.push((key, Arc::clone(table)));
}

/// Computes the diffuse transmittance tables of `lobes` that all threads share (see
/// `Transmittance::cached`) and are missing, in parallel, a lobe a task: the lobes of a line of
/// the lobe search, before its fits ask for them one at a time (each then computed by one thread
/// while the others wait for it). The same tables, bit for bit, as computed on demand.
pub fn prepare_tables(lobes: &[Lobe]) {
    let mut missing: Vec<Lobe> = {
        let shared = SHARED_TABLES.lock().unwrap_or_else(|e| e.into_inner());
        lobes
            .iter()
            .filter(|l| {
                l.eta != 1.0
                    && l.diffuse == Diffuse::Transmitted
                    && find_table(&shared, table_key(l)).is_none()
            })
            .copied()
            .collect()
    };
    missing.dedup_by_key(|l| table_key(l));
    if missing.len() < 2 {
        return;
    }
    let built: Vec<(Lobe, Arc<Transmittance>)> = missing
        .into_par_iter()
        .map(|l| (l, Arc::new(Transmittance::new(&l))))
        .collect();
    let mut shared = SHARED_TABLES.lock().unwrap_or_else(|e| e.into_inner());
    for (lobe, table) in &built {
        if find_table(&shared, table_key(lobe)).is_none() {
            keep_table(&mut shared, table_key(lobe), table);
        }
    }
}

/// [`fit`] stops once a step lowers the squared residual by less than this fraction of it. Near
/// the minimum the remaining decrease is of the order of the last one, and with `m` noisy
/// observations a residual `(1 + e)` times the least lies about `sqrt(e (m - 4))` standard
/// deviations of the fit from it: 0.004 for 16 lights, far below the noise.
pub const CONVERGED: f64 = 1e-6;

/// The step tolerance of the fits in a reconstruction's local steps ([`fit_packed_within`]): a
/// fit stops, without trying it, at a Gauss-Newton step `(db, ds)` with `|(db, ds)| <=
/// STEP_TOLERANCE (|b| + s)`. The step is the linearised model's estimate of the way left to the
/// minimum, so the fit then ends within about this fraction of it: the normal within about
/// `1e-5` rad (0.0006°), the residual above its minimum by about `STEP_TOLERANCE^2` of the
/// facet's image energy. A facet whose surface has converged is fitted again from its normal of
/// the step before (the warm start) in every local step: on the synthetic glossy bumps at 512²
/// the fits of the last local steps then end after one evaluation of the model instead of four
/// (the first step from the warm normal shorter than `1e-7` rad for 85 % of the facets). Not
/// used where residuals are compared across candidates (the distance search, the lobe search):
/// an earlier use there moved the glossy distance search on the PBR renders by up to 2 %.
pub const STEP_TOLERANCE: f64 = 1e-5;

/// With a step tolerance (see [`STEP_TOLERANCE`]) a glossy fit also stops, without trying it,
/// at a Gauss-Newton step whose promised decrease of the squared residual, `dx . J^T r` (the
/// decrease of the linearised model, `dx^T J^T J dx` undamped), is at most this many times the
/// variance `sigma^2` of an observation's noise ([`Packed::noise`], measured in the images by
/// [`estimate_noise`](crate::noise::estimate_noise); 0 on noise-free images: no change). The
/// step `dx` is then within about one standard error of the noise, `dx^T (J^T J / sigma^2) dx
/// <= 1` (the covariance of the least-squares unknowns is `sigma^2 (J^T J)^-1`): the minimum
/// it would reach differs from the fit where it stops by less than the noise lets the data tell
/// apart. Such a fit counts as converged ([`GlossyFit::converged`]). The local steps use it only
/// for fits from a glossy start (the previous step's or a coarser level's normal): from a
/// Lambertian fit, whose normals the highlights tilt alike on neighbouring facets (a bias the
/// mesh does not average away as it does the noise), `glossy::refine` fits with noise 0.
///
/// Stop 49 (issue 20): the fits of a finer level start from the coarser level's normals, which
/// average four facets' data and so carry a quarter of the noise; without this stop every fit
/// of the first local steps ran its Gauss-Newton steps toward its own noisy minimum, and the
/// normals came out *worse* the longer they ran (stop 48). On the glossy bumps at 1 MP with 0.5
/// % noise, lobe given: share 0 / 0.3 / 1 / 3: mean normal error 1.019 / 0.924 / 0.748 / 0.424
/// degrees, CPU 11.9 / 7.0 / 6.1 / 5.3 s. 1 is a standard error, the least that stands for a
/// statistical statement; larger shares smooth more (they keep the coarser level's normal
/// wherever the data do not move it by more than `sqrt(share)` standard errors). At 128² and
/// 192², where one glossy level starts from the Lambertian fits, the same scene came out 0.015°
/// worse on average (3 seeds; 0.03-0.04° before the Lambertian starts were left out).
pub const NOISE_STOP: f64 = 1.0;

/// A fit with a step tolerance ([`fit_packed_within`]) takes a step without evaluating the
/// model at its end when the step before it *settled* (the residual fell by the decrease the
/// linearised model predicted for it, within [`SETTLED_MATCH`] of it), this step is at most
/// this fraction of that one's length `q`, and the step after it, predicted `q` times as long,
/// would be within the step tolerance ([`STEP_TOLERANCE`]). The fit then counts as converged
/// and reports the residual the linearised model predicts at the step's end, `|r - J dx|^2`
/// ([`GlossyFit::sse`]; in a unit test within `1e-3` of the model's there). The noise stop
/// ([`NOISE_STOP`]) was tried as a second reason (the next step promising `q^2` times this one's
/// decrease, within the noise): such a step may still lower the residual by several `sigma^2`,
/// and the prediction then came out up to `0.08 sigma^2` below the least residual. Near its minimum a Gauss-Newton fit converges at least
/// linearly, quadratically where the residual is small: the prediction is conservative there.
///
/// Stop 56 (issue 20): the warm fits of a reconstruction's local steps took a second step and
/// then evaluated the model at its end only to find the third step within the tolerance (77 %
/// of the first fine local step's fits at 1 MP); that evaluation with its derivatives was a
/// third of a fit's.
pub const SETTLED_RATIO: f64 = 0.5;

/// How close a step's decrease of the residual must come to the linearised model's prediction
/// (relatively) for the step to have settled (see [`SETTLED_RATIO`]).
pub const SETTLED_MATCH: f64 = 0.1;

/// The glossy fit of one facet.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GlossyFit {
    /// Unit normal.
    pub normal: [f64; 3],
    /// Diffuse albedo `rho_d`.
    pub diffuse: f64,
    /// Specular albedo `rho_s`.
    pub specular: f64,
    /// Sum of squared residuals over the observations that carry light (where the fit's last
    /// step was taken unevaluated, see [`SETTLED_RATIO`], the linearised model's).
    pub sse: f64,
    /// How many observations carry light at the final normal.
    pub used: u32,
    /// Whether the fit ended at its minimum (a step within the tolerance or the convergence
    /// test, or none that lowers the residual) rather than by taking its last allowed step.
    pub converged: bool,
    /// How far (radians) the light and view vectors may turn, and the lights' falloff change
    /// (relatively) by twice as much, before the fit, stopped within the noise, may no longer
    /// stand for one made again (see [`latitude`]); 0 where it did not stop within the noise.
    pub latitude: f64,
}

/// How far the light and view vectors of a fit stopped within the noise may turn (radians)
/// before a fit made again would take a step: 0 unless `noise > 0` and the fit stopped at a
/// step whose promised decrease `promise` is known.
///
/// The fit stopped where the next Gauss-Newton step promised `p = dx . J^T r <= NOISE_STOP
/// sigma^2`, i.e. where `|P r| = sqrt(p)` for the projection `P = J (J^T J)^-1 J^T` onto the
/// model's tangent space (undamped; the damping only shortens the step). Move the facet's
/// centre so that its light and view vectors turn by at most `t` radians and each light's
/// falloff `1 / |p - c|^2` changes by a factor within `1 +- 2 t`. To first order the model's
/// predictions change by `dm = dm_turn + dm_fall`:
/// - turning the vectors by `t` changes the predictions as turning the normal by about `t`
///   does (shading depends on the angles between the normal, the light and the view), the
///   change of `b = rho_d n` by `|db| <= rho_d t`: `|P dm_turn| <= |J_b db| <= rho_d t
///   sqrt(lambda_max(J_b^T J_b)) <= rho_d t sqrt(tr J_b^T J_b)`;
/// - the falloff scales every prediction by `1 + 2 t` at most: `m = J x` exactly for the unknowns
///   `x = (b, rho_s)` (the diffuse term is homogeneous of degree 1 in `b`, the specular of degree
///   0 in `b` and 1 in `rho_s`), so `|P dm_fall| <= 2 t |J x| = 2 t sqrt(x^T J^T J x)`.
///
/// The step a fit made again would promise is then at most `(sqrt(p) + t G)^2` with `G = rho_d
/// sqrt(tr J_b^T J_b) + 2 sqrt(x^T J^T J x)`, within the noise stop while `t <= (sqrt(NOISE_STOP
/// sigma^2) - sqrt(p)) / G`: that `t` is returned. The turns and the falloff are first order in
/// the move; an LED's anisotropy `mu` adds `mu t tan(angle off its axis)` to the falloff's
/// change (the caller allows for it, see `local::KeptFits`).
pub fn latitude(jtj: &Matrix4<f64>, b: [f64; 3], s: f64, promise: f64, noise: f64) -> f64 {
    if noise <= 0.0 || !promise.is_finite() {
        return 0.0;
    }
    let room = (NOISE_STOP * noise).sqrt() - promise.max(0.0).sqrt();
    let x = Vector4::new(b[0], b[1], b[2], s);
    let g = norm(b) * (jtj[(0, 0)] + jtj[(1, 1)] + jtj[(2, 2)]).sqrt()
        + 2.0 * x.dot(&(jtj * x)).max(0.0).sqrt();
    match room > 0.0 && g > 0.0 {
        true => room / g,
        false => 0.0,
    }
}

/// `[e(0), e(1), e(2)]` of the expression `e` in `j`, written out: the coordinates of a vector
/// of lanes. (`crate::lanes` over a closure that itself builds lanes was left out of line in
/// the `f32` kernels, as baseline SSE code called per coordinate: 5 % of their profile.)
macro_rules! coords {
    (|$j:ident| $e:expr) => {
        [
            {
                let $j = 0;
                $e
            },
            {
                let $j = 1;
                $e
            },
            {
                let $j = 2;
                $e
            },
        ]
    };
}

/// The glossy kernels in lanes, written once (the text of `reflectance/kernels.rs`) and compiled in two
/// precisions: [`single`] (`f32`, 16 lanes), which the local steps' fits use, and [`double`]
/// (`f64`, 8 lanes), which [`Packed::precise`] selects (the lobe search's fits). In both the
/// per-observation shading (the half vectors, the Fresnel factors, GGX, Smith, the transmittance
/// look-up, the Jacobian rows) and the per-lane sums of the normal equations are computed in the
/// lanes' type `F`; the lanes are summed in `f64` (`Accumulator::finish`), and the steps, their
/// solves and the unknowns stay in `f64`. The point lights' directions and scales are computed
/// in `f64` (`Wide`, from positions of hundreds of millimetres) and then rounded.
///
/// `f32` lanes hold 16 observations to an AVX-512 vector, twice as many per instruction as
/// `f64` lanes (docs/shiny.md, stops 46 and 51). Their rounding (relative `6e-8` per operation)
/// is far below the image noise and the fits' step tolerance ([`STEP_TOLERANCE`]), but not below
/// the differences between the lobes the lobe search compares on a sharp lobe: on DiLiGenT's
/// ball, whose criterion is flat in the index, the search's fits in `f32` moved its index from
/// 2.09 to 1.90 (stop 51); in `f64` it is the index of the scalar `f64` kernels.
pub(crate) mod single {
    use super::*;

    /// The lanes' floating-point type.
    pub(super) type F = f32;

    /// Observations per group (one SIMD lane each, see [`Packed`]): one AVX-512 vector of `f32`
    /// (two AVX2 vectors). The kernels are dispatched as the Lambertian ones (`simd_dispatch!`
    /// `wide`). A rig of 16 lights fills one group; the lanes of a last group that is not full
    /// carry no light and cost as much as the others.
    pub(super) const W: usize = 16;

    /// `T(c) / T(1)` and its derivative in lanes: from the table's coefficients rounded to `f32`.
    #[inline(always)]
    fn table_lanes(t: &Transmittance, c: &Lanes) -> (Lanes, Lanes) {
        t.at_lanes_f32(c)
    }

    /// The GGX denominator as a sum of two positive terms (see `shade_group`): in `f32` the
    /// form `(n.h)^2 (alpha^2 - 1) + 1` cancels near the peak.
    const GGX_SUM: bool = true;

    /// The least cosine `n.l` of a lit lane in `shade_group` (lit lanes below it are evaluated
    /// at it: their factors change by less than `1e-10`): it keeps the product of the GGX and
    /// Smith denominators (at least `c alpha^4` about) above the least normal `f32` for
    /// roughnesses down to `1e-7`.
    const LEAST_COSINE: F = 1e-10;

    /// The fits' starting albedos from sums in `f64` lanes (`albedo_sums`).
    const LANE_ALBEDO_SUMS: bool = true;

    /// The lanes of the normal equations summed inside the kernels (`Accumulator::finish`): out
    /// of line, the conversions and sums of 15 vectors of 16 lanes took 17 % of the `f32`
    /// kernels' perf samples in a glossy `depth="auto"` run (stop 53).
    const FINISH_OUT_OF_LINE: bool = false;

    include!("reflectance/kernels.rs");
}

/// The kernels of [`single`] in `f64` lanes (see there).
// (The text is the same as `single`'s: its casts to `F` and conversions from `F` are identities
// here.)
#[allow(clippy::unnecessary_cast, clippy::useless_conversion)]
pub(crate) mod double {
    use super::*;

    /// The lanes' floating-point type.
    pub(super) type F = f64;

    /// Observations per group: one AVX-512 vector of `f64` (two AVX2 vectors).
    pub(super) const W: usize = 8;

    /// `T(c) / T(1)` and its derivative in lanes: [`Transmittance::at_lanes`] (the scalar
    /// look-up's bits).
    #[inline(always)]
    fn table_lanes(t: &Transmittance, c: &Lanes) -> (Lanes, Lanes) {
        t.at_lanes(c)
    }

    // The forms of the `f64` kernels that the `f32` lanes replaced (stop 51), so that these
    // lanes give their bits: the distance search, which runs in them, hangs on the last bits
    // of its fits (docs/shiny.md, stop 52), and these forms are also the cheaper ones.

    /// The GGX denominator as `(n.h)^2 (alpha^2 - 1) + 1` (its cancellation near the peak costs
    /// `1e-16 / alpha^2` relative in `f64`).
    const GGX_SUM: bool = false;

    /// The least cosine `n.l` of a lit lane in `shade_group` (lit lanes below it are evaluated
    /// at it).
    const LEAST_COSINE: F = 1e-100;

    /// The fits' starting albedos from sums one observation after another
    /// (`albedo_sums_in_order`).
    const LANE_ALBEDO_SUMS: bool = false;

    /// The lanes of the normal equations summed out of line (`Accumulator::finish`), as scalar
    /// code: inlined into the dispatched kernels, the compiler summed the 15 vectors at once by
    /// transposing them, with shuffles and spills (perf samples of a glossy `depth="auto"` run
    /// on bumps rough plastic 0.3, stop 53: `accumulate` 298 inlined, 84 plus `finish` 139
    /// out of line, shared with `equations`).
    const FINISH_OUT_OF_LINE: bool = true;

    include!("reflectance/kernels.rs");
}

/// The observations of one facet packed for [`fit_packed`]: groups of lights, one SIMD lane
/// each, with the terms that do not depend on the normal (as [`Observation`]) computed for all
/// lights at once by [`Packed::prepare`]. Reusable from facet to facet ([`Packed::clear`]). Its
/// fits run the kernels in `f32` lanes (`single`), or, made by [`Packed::precise`], in `f64`
/// lanes (`double`).
#[derive(Debug, Clone, Default)]
pub struct Packed {
    view: [f64; 3],
    /// Whether the kernels run in `f64` lanes (`double`) rather than `f32` lanes (`single`).
    precise: bool,
    single: single::Store,
    double: double::Store,
    /// The kernel of the lobe last fitted, with its [`kernel_key`]: the next fits under the same
    /// lobe reuse it instead of looking its transmittance table up again (a thread-local search
    /// and a reference count shared by all threads, per fit).
    kernel: Option<(KernelKey, Kernel)>,
    /// Whether the glossy fit of these observations that their user kept ended at its minimum
    /// ([`GlossyFit::converged`]; `glossy::refine` sets it, [`Packed::clear`] clears it).
    pub converged: bool,
    /// That fit's [`GlossyFit::latitude`] (set and cleared with `converged`).
    pub latitude: f64,
    /// The variance of an observation's noise (its value's: the sum of its channels), which
    /// ends the fits with a step tolerance within the noise (see [`NOISE_STOP`]; 0: none).
    pub noise: f64,
}

/// What a [`Kernel`] is made of: the bits of `alpha`, `eta` and the retro-reflective weight.
type KernelKey = (u64, u64, u64);

/// The [`KernelKey`] of `lobe`.
fn kernel_key(lobe: &Lobe) -> KernelKey {
    (
        lobe.alpha.to_bits(),
        lobe.eta.to_bits(),
        lobe.retro_weight().to_bits(),
    )
}

impl Packed {
    /// No observations; its fits in `f32` lanes.
    pub fn new() -> Packed {
        Packed::default()
    }

    /// No observations; its fits in `f64` lanes (the lobe search's, see `reflectance::double`).
    pub fn precise() -> Packed {
        Packed {
            precise: true,
            ..Packed::default()
        }
    }

    /// Starts over for a facet seen along the unit vector `view` (towards the camera).
    pub fn clear(&mut self, view: [f64; 3]) {
        self.view = view;
        self.single.clear();
        self.double.clear();
        self.converged = false;
        self.latitude = 0.0;
    }

    /// How many observations it holds.
    pub fn len(&self) -> usize {
        match self.precise {
            true => self.double.len,
            false => self.single.len,
        }
    }

    /// Whether it holds no observation.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Adds the observation of image value `value` under a light of scale `Phi a` from the unit
    /// direction `light` ([`Packed::prepare`] then computes its half vector and Fresnel factor).
    #[inline]
    pub fn push(&mut self, value: f64, scale: f64, light: [f64; 3]) {
        match self.precise {
            true => self.double.push(value, scale, light),
            false => self.single.push(value, scale, light),
        }
    }

    /// Adds the observation of image value `value` under a point light at `position` with axis
    /// `axis`, anisotropy `mu` (0: isotropic, else an LED, `t^mu`) and intensity `phi`:
    /// [`Packed::prepare`] computes its direction and scale `Phi a` at the facet (see
    /// [`crate::Light`]). An LED that does not light the facet never carries light.
    #[inline]
    pub fn push_point(
        &mut self,
        value: f64,
        phi: f64,
        position: [f64; 3],
        axis: [f64; 3],
        mu: f64,
    ) {
        match self.precise {
            true => self.double.push_point(value, phi, position, axis, mu),
            false => self.single.push_point(value, phi, position, axis, mu),
        }
    }

    /// Adds `o` as it is (with its half vector and Fresnel factor; made for this view vector).
    #[inline]
    pub fn push_observation(&mut self, o: &Observation) {
        match self.precise {
            true => self.double.push_observation(o),
            false => self.single.push_observation(o),
        }
    }

    /// Computes, for the facet with centre `x`, the directions and scales of the observations
    /// [`Packed::push_point`]ed, and the half vectors and `F(v.h) / F(1)` of all the
    /// observations pushed, under `lobe` (as [`Observation::new`], for all lights at once), with
    /// the retro-reflective diffuse term also `(l.h)^2` (then valid for any lobe of that term and
    /// index, whatever its roughness).
    pub fn prepare(&mut self, lobe: &Lobe, x: [f64; 3]) {
        let retro = lobe.diffuse == Diffuse::Retro;
        match self.precise {
            true => self.double.prepare(self.view, x, lobe.eta, retro),
            false => self.single.prepare(self.view, x, lobe.eta, retro),
        }
    }
}

/// The solution `x` of `A x = r` for a symmetric positive definite 4x4 `A` (its lower triangle
/// is read), by the factorization `A = L D L^T` (`L` unit lower triangular, `D` diagonal):
///
/// ```text
/// d_j = a_jj - sum_{k<j} l_jk^2 d_k,   l_ij = (a_ij - sum_{k<j} l_ik l_jk d_k) / d_j   (i > j),
/// L y = r,   z = D^-1 y,   L^T x = z,
/// ```
///
/// with the products `l_ik d_k` kept (`t_ik`) and each pivot inverted once: 4 divisions and no
/// square root, where the Cholesky factor `A = G G^T` takes 4 square roots and 14 divisions
/// (6 in the factor, 8 in the two substitutions), all in one chain of dependent operations. In
/// exact arithmetic the same `x` (`G = L D^(1/2)`), and `A` is positive definite exactly when
/// every pivot `d_j > 0`, the test the Cholesky factor makes on its squared diagonal: None
/// where one is not (or is NaN), as the Cholesky factor fails. Both are backward stable on
/// positive definite matrices; rounding differs in the last bits.
#[inline(always)]
fn solve_spd4(a: &Matrix4<f64>, r: &Vector4<f64>) -> Option<Vector4<f64>> {
    let pivot = |d: f64| (d > 0.0).then(|| 1.0 / d);
    // Column 0.
    let d0 = a[(0, 0)];
    let i0 = pivot(d0)?;
    let (t10, t20, t30) = (a[(1, 0)], a[(2, 0)], a[(3, 0)]);
    let (l10, l20, l30) = (t10 * i0, t20 * i0, t30 * i0);
    // Column 1.
    let d1 = a[(1, 1)] - l10 * t10;
    let i1 = pivot(d1)?;
    let t21 = a[(2, 1)] - l20 * t10;
    let t31 = a[(3, 1)] - l30 * t10;
    let (l21, l31) = (t21 * i1, t31 * i1);
    // Column 2.
    let d2 = a[(2, 2)] - l20 * t20 - l21 * t21;
    let i2 = pivot(d2)?;
    let t32 = a[(3, 2)] - l30 * t20 - l31 * t21;
    let l32 = t32 * i2;
    // Column 3.
    let d3 = a[(3, 3)] - l30 * t30 - l31 * t31 - l32 * t32;
    let i3 = pivot(d3)?;
    // L y = r, then L^T x = D^-1 y.
    let y0 = r[0];
    let y1 = r[1] - l10 * y0;
    let y2 = r[2] - l20 * y0 - l21 * y1;
    let y3 = r[3] - l30 * y0 - l31 * y1 - l32 * y2;
    let x3 = y3 * i3;
    let x2 = y2 * i2 - l32 * x3;
    let x1 = y1 * i1 - l21 * x2 - l31 * x3;
    let x0 = y0 * i0 - l10 * x1 - l20 * x2 - l30 * x3;
    Some(Vector4::new(x0, x1, x2, x3))
}

/// Fits `(n, rho_d, rho_s)` of one facet from the normal of `start = rho_d n` (e.g. the
/// Lambertian fit) with the least-squares albedos there, by at most `steps` damped
/// Gauss-Newton steps (see the module documentation). `v` is the unit vector from the facet to
/// the camera, and `obs` were made for it and `lobe` ([`Observation::new`]). None if the start
/// is not a finite, non-zero vector or fewer than 4 observations carry light. (The
/// observations packed, then [`fit_packed`].)
pub fn fit(
    lobe: &Lobe,
    obs: &[Observation],
    v: [f64; 3],
    start: [f64; 3],
    steps: usize,
) -> Option<GlossyFit> {
    let mut packed = Packed::new();
    packed.clear(v);
    for o in obs {
        packed.push_observation(o);
    }
    fit_packed(lobe, &mut packed, start, steps)
}

/// [`fit`] on packed observations (prepared for `lobe`, see [`Packed::prepare`]): the same
/// steps, each light's factors and the sums of the normal equations computed `W` lights at a
/// time. The residual after the last step is evaluated without the derivatives (no step
/// follows it).
pub fn fit_packed(
    lobe: &Lobe,
    obs: &mut Packed,
    start: [f64; 3],
    steps: usize,
) -> Option<GlossyFit> {
    fit_packed_within(lobe, obs, start, steps, 0.0)
}

/// [`fit_packed`] that stops, without trying it, at a step shorter than `tolerance` of the
/// unknowns (`|(db, ds)| <= tolerance (|b| + s)`, see [`STEP_TOLERANCE`]); 0: [`fit_packed`].
pub fn fit_packed_within(
    lobe: &Lobe,
    obs: &mut Packed,
    start: [f64; 3],
    steps: usize,
    tolerance: f64,
) -> Option<GlossyFit> {
    if !start.iter().all(|x| x.is_finite()) || norm(start) == 0.0 {
        return None;
    }
    fit_from(lobe, obs, normalize(start), Some(start), steps, tolerance)
}

/// [`fit_packed`] from the unit normal `normal` with the least-squares albedos there alone: None
/// where they cannot be found (no light, or a diffuse albedo that is not positive).
pub fn fit_packed_at(
    lobe: &Lobe,
    obs: &mut Packed,
    normal: [f64; 3],
    steps: usize,
) -> Option<GlossyFit> {
    fit_packed_at_within(lobe, obs, normal, steps, 0.0)
}

/// [`fit_packed_at`] with a step tolerance (see [`fit_packed_within`]).
pub fn fit_packed_at_within(
    lobe: &Lobe,
    obs: &mut Packed,
    normal: [f64; 3],
    steps: usize,
    tolerance: f64,
) -> Option<GlossyFit> {
    if !normal.iter().all(|x| x.is_finite()) || norm(normal) == 0.0 {
        return None;
    }
    fit_from(lobe, obs, normalize(normal), None, steps, tolerance)
}

/// The fit from the unit normal `n0` with its least-squares albedos, or, where they cannot be
/// found, from `fallback` (None: no fit), with at most `steps` steps and the step tolerance
/// `tolerance` (see [`fit_packed_within`]).
fn fit_from(
    lobe: &Lobe,
    obs: &mut Packed,
    n0: [f64; 3],
    fallback: Option<[f64; 3]>,
    steps: usize,
    tolerance: f64,
) -> Option<GlossyFit> {
    let key = kernel_key(lobe);
    let k = match obs.kernel.take() {
        Some((kept, k)) if kept == key => k,
        _ => Kernel::new(lobe),
    };
    let (v, noise) = (obs.view, obs.noise);
    let fit = match obs.precise {
        true => double::fit_with(
            &k,
            &mut obs.double,
            v,
            noise,
            n0,
            fallback,
            steps,
            tolerance,
        ),
        false => single::fit_with(
            &k,
            &mut obs.single,
            v,
            noise,
            n0,
            fallback,
            steps,
            tolerance,
        ),
    };
    obs.kernel = Some((key, k));
    fit
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vec3::sub;

    fn lights() -> Vec<[f64; 3]> {
        // 16 lights on two rings around the camera, 200 mm in front of the object.
        (0..16)
            .map(|i| {
                let t = i as f64 * std::f64::consts::PI / 4.0 + if i >= 8 { 0.4 } else { 0.0 };
                let r = if i >= 8 { 120.0 } else { 60.0 };
                [r * t.cos(), r * t.sin(), 0.0]
            })
            .collect()
    }

    fn observe(lobe: &Lobe, x: [f64; 3], n: [f64; 3], rho_d: f64, rho_s: f64) -> Vec<Observation> {
        lights()
            .iter()
            .map(|&p| {
                let a = sub(p, x);
                let d2 = dot(a, a);
                let l = normalize(a);
                let v = normalize(scale(x, -1.0));
                let scale = 4.0e4 / d2;
                let value = lobe
                    .shade(n, l, v)
                    .map_or(0.0, |s| scale * (rho_d * s.diffuse + rho_s * s.specular));
                Observation::new(value, scale, l, v, lobe)
            })
            .collect()
    }

    fn gradient_matches(f: impl Fn([f64; 3]) -> f64, grad: [f64; 3], n: [f64; 3]) {
        for j in 0..3 {
            let mut p = n;
            let mut m = n;
            p[j] += 1e-6;
            m[j] -= 1e-6;
            let fd = (f(p) - f(m)) / 2e-6;
            assert!(
                (fd - grad[j]).abs() < 1e-5 * (1.0 + fd.abs()),
                "{j}: {fd} vs {}",
                grad[j]
            );
        }
    }

    /// Random numbers in [-1, 1) (xorshift64*; the tests need no statistics, only spread).
    fn uniform(state: &mut u64) -> f64 {
        *state ^= *state >> 12;
        *state ^= *state << 25;
        *state ^= *state >> 27;
        let x = state.wrapping_mul(0x2545_f491_4f6c_dd1d);
        (x >> 11) as f64 / (1u64 << 52) as f64 - 1.0
    }

    #[test]
    fn the_ldlt_solve_is_the_cholesky_solve() {
        // J^T J of random Jacobians (8-32 rows) with columns of different scales, damped as
        // the fit damps them or not, over several seeds: both solves agree to the conditioning
        // (relative residual and difference), and both reject the same singular and
        // indefinite matrices.
        for seed in 1..=5u64 {
            let mut state = seed * 0x9e37_79b9_7f4a_7c15;
            for case in 0..400usize {
                let rows = 8 + case % 25;
                let scales = [1.0, 0.5, 2.0, 10f64.powf(3.0 * uniform(&mut state))];
                let mut jtj = Matrix4::zeros();
                let mut jtr = Vector4::zeros();
                for _ in 0..rows {
                    let j = Vector4::from_fn(|i, _| scales[i] * uniform(&mut state));
                    jtj += j * j.transpose();
                    jtr += j * uniform(&mut state);
                }
                if case % 2 == 0 {
                    let lambda = 1e-3 * 10f64.powi((case % 7) as i32);
                    for i in 0..4 {
                        jtj[(i, i)] += lambda * jtj[(i, i)];
                    }
                }
                let ours = solve_spd4(&jtj, &jtr).expect("positive definite");
                let theirs = jtj.cholesky().expect("positive definite").solve(&jtr);
                let cond = jtj.symmetric_eigenvalues().max() / jtj.symmetric_eigenvalues().min();
                let tol = 1e-14 * cond;
                assert!(
                    (jtj * ours - jtr).norm() <= tol * jtr.norm() * 10.0,
                    "{seed} {case}"
                );
                assert!(
                    (ours - theirs).norm() <= tol * theirs.norm(),
                    "{seed} {case}"
                );
            }
            // Singular (a zero pivot), indefinite (a negative one), NaN, zero: no solution
            // from either.
            let mut singular = Matrix4::identity();
            singular[(3, 3)] = 0.0;
            let r = Vector4::new(1.0, 2.0, 3.0, 4.0);
            let mut indefinite = Matrix4::identity() * 2.0;
            indefinite[(1, 0)] = 3.0;
            indefinite[(0, 1)] = 3.0;
            let mut nan = Matrix4::identity();
            nan[(2, 2)] = f64::NAN;
            for bad in [singular, indefinite, nan, Matrix4::zeros()] {
                assert!(solve_spd4(&bad, &r).is_none());
                assert_eq!(solve_spd4(&bad, &r).is_none(), bad.cholesky().is_none());
            }
        }
    }

    #[test]
    fn eta_one_is_lambertian_and_fresnel_is_exact_at_normal_incidence() {
        let lobe = Lobe::new(0.3, 1.0);
        let n = normalize([0.2, -0.1, -1.0]);
        let l = normalize([0.5, 0.3, -1.0]);
        let v = [0.0, 0.0, -1.0];
        let s = lobe.shade(n, l, v).unwrap();
        assert!((s.diffuse - dot(n, l)).abs() < 1e-15);
        let glass = Lobe::new(0.3, 1.5);
        assert!((glass.fresnel(1.0).0 - 0.04).abs() < 1e-12);
        // Grazing light is transmitted less.
        let k = Kernel::new(&glass);
        assert!(k.transmittance(0.2).0 < 0.9 && (k.transmittance(1.0).0 - 1.0).abs() < 1e-15);
    }

    /// The specular albedo of the lobe from the direction of cosine `mu`: the expectation over the
    /// visible normals of `F(w.m) G1(r, m)`, `r` the reflected ray (as [`rough_transmittance`]).
    fn specular_albedo(alpha: f64, eta: f64, mu: f64) -> f64 {
        let nodes = square_nodes(&gauss_legendre(TABLE_QUADRATURE));
        let w = [(1.0 - mu * mu).sqrt(), 0.0, mu];
        let a2 = alpha * alpha;
        let mut sum = 0.0;
        for node in &nodes {
            let (p, weight) = ((node.r_cos, node.r_sin), node.weight);
            let m = visible_normal(alpha, mu, p);
            let c = dot(w, m);
            let rz = 2.0 * c * m[2] - w[2];
            if c > 0.0 && rz > 0.0 {
                let g1 = 2.0 * rz / (rz + (a2 + (1.0 - a2) * rz * rz).sqrt());
                sum += weight * Lobe::new(alpha, eta).fresnel(c.min(1.0)).0 * g1;
            }
        }
        sum
    }

    /// [`transmittance_integral`] as it was before the direction's frame and the nodes'
    /// `sqrt(1 - r_cos^2)` were hoisted out of the loop over the nodes (stop 40).
    fn transmittance_integral_per_node(alpha: f64, eta: f64, mu: f64, nodes: &[Node]) -> f64 {
        let visible = |mu: f64, (r_cos, r_sin): (f64, f64)| -> [f64; 3] {
            let sin = (1.0 - mu * mu).max(0.0).sqrt();
            let vh = normalize([alpha * sin, 0.0, mu]);
            let (t1, t2) = if vh[0] > 0.0 {
                ([0.0, 1.0, 0.0], [-vh[2], 0.0, vh[0]])
            } else {
                ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
            };
            let s = 0.5 * (1.0 + vh[2]);
            let (p1, p2) = (r_cos, (1.0 - s) * (1.0 - r_cos * r_cos).sqrt() + s * r_sin);
            let p3 = (1.0 - p1 * p1 - p2 * p2).max(0.0).sqrt();
            let nh: [f64; 3] = std::array::from_fn(|j| p1 * t1[j] + p2 * t2[j] + p3 * vh[j]);
            normalize([alpha * nh[0], alpha * nh[1], nh[2].max(1e-9)])
        };
        let mu = mu.clamp(1e-6, 1.0);
        let w = [(1.0 - mu * mu).max(0.0).sqrt(), 0.0, mu];
        let lobe = Lobe::new(alpha, eta);
        let a2 = alpha * alpha;
        let mut sum = 0.0;
        for node in nodes {
            let m = visible(mu, (node.r_cos, node.r_sin));
            let c = dot(w, m);
            if c <= 0.0 {
                continue;
            }
            let (f, _) = lobe.fresnel(c.min(1.0));
            let ct = (1.0 - (1.0 - c * c) / (eta * eta)).max(0.0).sqrt();
            let tz = -w[2] / eta + (c / eta - ct) * m[2];
            if tz >= 0.0 {
                continue;
            }
            let cz = -tz;
            let g1 = 2.0 * cz / (cz + (a2 + (1.0 - a2) * cz * cz).sqrt());
            sum += node.weight * (1.0 - f) * g1;
        }
        sum
    }

    /// Hoisting the direction's frame and the nodes' terms out of the loop changes no bit of the
    /// integral (the same operations on the same operands), on the lobe search's grids.
    #[test]
    fn the_hoisted_integral_is_the_per_node_one_bit_for_bit() {
        let nodes = square_nodes(&gauss_legendre(TABLE_QUADRATURE));
        for &alpha in &[0.04, 0.09, 0.2, 0.3, 0.6, 0.85] {
            for &eta in &[1.02, 1.15, 1.5, 2.1] {
                for i in 0..=TABLE_STEPS / 8 {
                    let mu = (8 * i) as f64 / TABLE_STEPS as f64;
                    let a = transmittance_integral(alpha, eta, mu, &nodes);
                    let b = transmittance_integral_per_node(alpha, eta, mu, &nodes);
                    assert_eq!(a.to_bits(), b.to_bits(), "{alpha} {eta} {mu}: {a} vs {b}");
                }
            }
        }
    }

    /// The integral in lanes (with AVX2 where the processor has it, and without) is the one made
    /// node by node, bit for bit: on the lobe search's grids, near `eta = 1`, at the ends of the
    /// cosines, and with node counts that leave a remainder of fewer than `W` nodes.
    #[test]
    fn the_integral_in_lanes_is_the_scalar_one_bit_for_bit() {
        for q in [TABLE_QUADRATURE, 5, 7] {
            let nodes = square_nodes(&gauss_legendre(q));
            for &alpha in &[0.04, 0.09, 0.2, 0.3, 0.6, 0.85, 1.0] {
                for &eta in &[1.0 + 1e-9, 1.02, 1.15, 1.5, 2.1, 3.0] {
                    for i in 0..=TABLE_STEPS / 4 {
                        let mu = (4 * i) as f64 / TABLE_STEPS as f64;
                        let a = transmittance_integral(alpha, eta, mu, &nodes);
                        let b = transmittance_dispatch(alpha, eta, mu, &nodes);
                        let c = transmittance_lanes(alpha, eta, mu, &nodes);
                        assert_eq!(
                            a.to_bits(),
                            b.to_bits(),
                            "{q} {alpha} {eta} {mu}: {a} vs {b}"
                        );
                        assert_eq!(
                            a.to_bits(),
                            c.to_bits(),
                            "{q} {alpha} {eta} {mu}: {a} vs {c}"
                        );
                    }
                }
            }
        }
    }

    /// The tables [`prepare_tables`] computes in parallel are those computed on demand, bit for
    /// bit (a lobe with `eta = 1` has none).
    #[test]
    fn prepared_tables_are_the_tables_computed_on_demand() {
        let lobes = [
            Lobe::new(0.123, 1.37),
            Lobe::new(0.321, 1.37),
            Lobe::new(0.123, 1.37),
            Lobe::new(0.123, 1.0),
        ];
        prepare_tables(&lobes);
        for lobe in &lobes[..2] {
            let kept = Transmittance::cached(lobe);
            let fresh = Transmittance::new(lobe);
            let bits = |t: &Transmittance| -> Vec<u64> {
                t.cubic.iter().flatten().map(|x| x.to_bits()).collect()
            };
            assert_eq!(bits(&kept), bits(&fresh));
        }
    }

    #[test]
    fn gauss_legendre_integrates_polynomials_exactly() {
        let nodes = gauss_legendre(TABLE_QUADRATURE);
        for k in 0..2 * TABLE_QUADRATURE {
            let sum: f64 = nodes.iter().map(|&(x, w)| w * x.powi(k as i32)).sum();
            assert!((sum - 1.0 / (k as f64 + 1.0)).abs() < 1e-14, "{k} {sum}");
        }
    }

    /// The rough transmittance conserves energy (with the light the lobe reflects, at most 1),
    /// is greatest at normal incidence (so `D(n) <= n.l`, the Lambertian term), tends to the
    /// smooth interface's `1 - F` as the roughness vanishes, and its quadrature has converged.
    #[test]
    fn rough_transmittance_is_physical() {
        for &alpha in &[0.04, 0.1, 0.3, 0.85] {
            for &eta in &[1.15, 1.5, 2.1] {
                let normal = rough_transmittance(alpha, eta, 1.0);
                for i in 0..=20 {
                    let mu = (i as f64 / 20.0).max(1e-3);
                    let t = rough_transmittance(alpha, eta, mu);
                    let e = specular_albedo(alpha, eta, mu);
                    assert!(
                        t > 0.0 && t + e <= 1.0 + 1e-9,
                        "{alpha} {eta} {mu}: {t} + {e}"
                    );
                    assert!(t <= normal + 1e-9, "{alpha} {eta} {mu}: {t} > {normal}");
                    let fine = square_nodes(&gauss_legendre(2 * TABLE_QUADRATURE));
                    let t2 = transmittance_integral(alpha, eta, mu, &fine);
                    let tol = 5e-4;
                    assert!((t - t2).abs() < tol, "{alpha} {eta} {mu}: {t} vs {t2}");
                }
            }
        }
        let smooth = Lobe::new(0.3, 1.5);
        for mu in [0.3, 0.5, 0.8, 1.0] {
            let t = rough_transmittance(0.005, 1.5, mu);
            assert!((t - (1.0 - smooth.fresnel(mu).0)).abs() < 2e-3, "{mu}: {t}");
        }
    }

    /// The table's spline matches the integral between its nodes, and its derivative is the
    /// spline's (finite differences); it is 1 at normal incidence and at most 1 below.
    #[test]
    fn the_transmittance_table_interpolates_the_integral() {
        for &(alpha, eta) in &[(0.04, 1.5), (0.3, 1.5), (0.85, 2.1), (0.1, 1.15)] {
            let lobe = Lobe::new(alpha, eta);
            let k = Kernel::new(&lobe);
            let t1 = rough_transmittance(alpha, eta, 1.0);
            assert!((k.transmittance(1.0).0 - 1.0).abs() < 1e-15);
            for i in 0..97 {
                let c = (i as f64 + 0.37) / 97.0;
                let (t, dt) = k.transmittance(c);
                let exact = rough_transmittance(alpha, eta, c) / t1;
                // Steepest at grazing light, where the diffuse term `c T` is least.
                let tol = if c < 0.05 { 1e-5 / c } else { 2e-5 };
                assert!((t - exact).abs() < tol, "{alpha} {eta} {c}: {t} vs {exact}");
                assert!(t <= 1.0 + 1e-9);
                let h = 1e-7;
                let fd = (k.transmittance(c + h).0 - k.transmittance(c - h).0) / (2.0 * h);
                assert!(
                    (fd - dt).abs() < 1e-5 * (1.0 + dt.abs()),
                    "{c}: {fd} vs {dt}"
                );
            }
        }
    }

    #[test]
    fn the_table_in_lanes_is_the_scalar_lookup_bit_for_bit() {
        let table = Transmittance::new(&Lobe::new(0.3, 1.5));
        // Interior cosines, the nodes themselves, the ends and values outside [0, 1] (clamped).
        let mut cosines: Vec<f64> = (0..=1000).map(|i| i as f64 / 1000.0).collect();
        cosines.extend((0..=TABLE_STEPS).map(|i| i as f64 / TABLE_STEPS as f64));
        cosines.extend([
            1e-100,
            f64::MIN_POSITIVE,
            1.0 + 1e-15,
            1.5,
            -0.25,
            0.999_999_999,
        ]);
        for chunk in cosines.chunks(W) {
            let c: Lanes = std::array::from_fn(|i| chunk[i % chunk.len()]);
            let (value, slope) = table.at_lanes(&c);
            let (value32, slope32) = table.at_lanes_f32(&c.map(|x| x as f32));
            for i in 0..W {
                let (v, s) = table.at(c[i]);
                assert_eq!(value[i].to_bits(), v.to_bits(), "{}", c[i]);
                assert_eq!(slope[i].to_bits(), s.to_bits(), "{}", c[i]);
                // In f32: the value to 1e-6 (it is at most 1), the slope to 1e-6 of the
                // table's steepest slope (T(c) / T(1) is of order 1 over c in [0, 1]).
                assert!((f64::from(value32[i]) - v).abs() < 1e-6, "{} {v}", c[i]);
                assert!(
                    (f64::from(slope32[i]) - s).abs() < 1e-6 * (1.0 + s.abs()) + 1e-4,
                    "{}",
                    c[i]
                );
            }
        }
    }

    /// `D(n)` and `S(n)` straight from the formulas of the module documentation.
    fn reference(lobe: &Lobe, n: [f64; 3], l: [f64; 3], v: [f64; 3]) -> (f64, f64) {
        let fresnel = |c: f64| {
            let e = lobe.eta;
            let t = (1.0 - (1.0 - c * c) / (e * e)).sqrt();
            let rs = (c - e * t) / (c + e * t);
            let rp = (e * c - t) / (e * c + t);
            (rs * rs + rp * rp) / 2.0
        };
        let a2 = lobe.alpha * lobe.alpha;
        let g1 = |c: f64| 2.0 * c / (c + (a2 + (1.0 - a2) * c * c).sqrt());
        let rough = |c: f64| rough_transmittance(lobe.alpha, lobe.eta, c);
        let t = |c: f64| match lobe.eta == 1.0 {
            true => 1.0,
            false => rough(c) / rough(1.0),
        };
        let h = normalize([l[0] + v[0], l[1] + v[1], l[2] + v[2]]);
        let (cl, cv, ch) = (dot(n, l), dot(n, v), dot(n, h));
        // Burley's: (n.l) (1 + (F_D90 - 1) (1 - n.l)^5) (1 + (F_D90 - 1) (1 - n.v)^5),
        // F_D90 = 1/2 + 2 R (l.h)^2, R = sqrt(alpha).
        let fd90 = 0.5 + 2.0 * lobe.alpha.sqrt() * dot(l, h).powi(2);
        let diffuse = match lobe.diffuse {
            Diffuse::Transmitted => cl * t(cl) * t(cv),
            Diffuse::Retro => {
                cl * (1.0 + (fd90 - 1.0) * (1.0 - cl).powi(5))
                    * (1.0 + (fd90 - 1.0) * (1.0 - cv).powi(5))
            }
        };
        let q = ch * ch * (a2 - 1.0) + 1.0;
        let ggx = a2 / (std::f64::consts::PI * q * q);
        let shape = if lobe.eta == 1.0 {
            1.0
        } else {
            fresnel(dot(v, h)) / fresnel(1.0)
        };
        (diffuse, shape * ggx * g1(cl) * g1(cv) / (4.0 * cv))
    }

    /// The lobes the factors' tests try: both diffuse shapes.
    fn test_lobes() -> Vec<Lobe> {
        let pairs = [(0.05, 1.5), (0.3, 1.3), (0.6, 1.0), (1.0, 2.5)];
        let transmitted = pairs.iter().map(|&(a, e)| Lobe::new(a, e));
        transmitted
            .chain(pairs.iter().map(|&(a, e)| Lobe::retro(a, e)))
            .collect()
    }

    /// The retro-reflective diffuse term is `n.l` where the light and the camera look along
    /// the normal, and where `k = 0`; towards grazing angles it is brighter than `n.l` under a
    /// rough lobe with the light beside the camera (retro-reflection) and darker under a
    /// smooth one. Burley's term does not conserve energy: its directional albedo reaches 1.38 of
    /// a Lambertian surface's at `alpha = 1` seen at 84 degrees (below 1.2 for `alpha <= 0.25`).
    #[test]
    fn the_retro_diffuse_term_is_burleys() {
        let v = [0.0, 0.0, -1.0];
        for alpha in [0.01, 0.09, 0.25, 1.0] {
            let lobe = Lobe::retro(alpha, 1.5);
            let s = lobe.shade(v, v, v).unwrap();
            assert!((s.diffuse - 1.0).abs() < 1e-15, "{s:?}");
            // k = 0 where (l.h)^2 = 1 / (4 R): h halfway between l and v (l within 83 degrees
            // of v for the facet below to face it).
            let cd = (0.25 / alpha.sqrt()).sqrt();
            if cd > 0.75 && cd < 1.0 {
                let theta = 2.0 * cd.acos();
                let l = [theta.sin(), 0.0, -theta.cos()];
                let n = normalize([0.3, 0.2, -1.0]);
                let s = lobe.shade(n, l, v).unwrap();
                assert!((s.diffuse - dot(n, l)).abs() < 1e-12, "{alpha}: {s:?}");
            }
            // Light beside the camera, grazing facet.
            let n = normalize([3.0, 0.0, -1.0]);
            let l = normalize([0.05, 0.0, -1.0]);
            let ratio = lobe.shade(n, l, v).unwrap().diffuse / dot(n, l);
            match alpha >= 0.09 {
                true => assert!(ratio > 1.0, "{alpha}: {ratio}"),
                false => assert!(ratio < 1.0, "{alpha}: {ratio}"),
            }
            // Directional albedo of D / pi (midpoint rule over the hemisphere of the light).
            for mu in [1.0, 0.5, 0.1] {
                let n = [(1.0f64 - mu * mu).sqrt(), 0.0, -mu];
                let steps = 200;
                let mut albedo = 0.0;
                for i in 0..steps {
                    let ct = (i as f64 + 0.5) / steps as f64;
                    for j in 0..steps {
                        let phi = 2.0 * std::f64::consts::PI * (j as f64 + 0.5) / steps as f64;
                        let st = (1.0 - ct * ct).sqrt();
                        // A frame with n as its pole.
                        let (a, b) = ([0.0, 1.0, 0.0], normalize([mu, 0.0, n[0]]));
                        let l: [f64; 3] = std::array::from_fn(|k| {
                            st * phi.cos() * a[k] + st * phi.sin() * b[k] + ct * n[k]
                        });
                        if let Some(s) = lobe.shade(n, l, v) {
                            albedo += s.diffuse / std::f64::consts::PI
                                * (2.0 * std::f64::consts::PI)
                                / (steps * steps) as f64;
                        }
                    }
                }
                let most = if alpha <= 0.25 { 1.2 } else { 1.4 };
                assert!(albedo > 0.5 && albedo < most, "{alpha} {mu}: {albedo}");
            }
        }
    }

    #[test]
    fn factors_match_the_formulas() {
        let v = normalize([0.05, 0.02, -1.0]);
        for lobe in test_lobes() {
            for i in 0..50 {
                let t = i as f64;
                let n = normalize([0.6 * (t * 0.37).sin(), 0.6 * (t * 0.73).cos(), -1.0]);
                let l = normalize([0.8 * (t * 0.21).cos(), 0.8 * (t * 0.53).sin(), -1.0]);
                let Some(sh) = lobe.shade(n, l, v) else {
                    assert!(dot(n, l) <= 0.0);
                    continue;
                };
                let (d, s) = reference(&lobe, n, l, v);
                // The diffuse factor's transmittance is interpolated in a table.
                assert!((sh.diffuse - d).abs() <= 1e-4 * d.abs(), "{sh:?} {d}");
                assert!((sh.specular - s).abs() <= 1e-13 * s.abs(), "{sh:?} {s}");
            }
        }
    }

    #[test]
    fn gradients_match_finite_differences() {
        let v = normalize([0.05, 0.02, -1.0]);
        let l = normalize([0.3, 0.2, -1.0]);
        let pairs = [(0.1, 1.5), (0.3, 1.3), (0.6, 1.0)];
        let lobes = pairs
            .iter()
            .flat_map(|&(a, e)| [Lobe::new(a, e), Lobe::retro(a, e)]);
        for lobe in lobes {
            let (f, df) = lobe.fresnel(0.7);
            let fd = (lobe.fresnel(0.7 + 1e-7).0 - lobe.fresnel(0.7 - 1e-7).0) / 2e-7;
            assert!((fd - df).abs() < 1e-6, "{f} {df} {fd}");
            let normals = [
                normalize([0.1, 0.1, -1.0]),
                normalize([0.4, -0.2, -1.0]),
                normalize([1.5, 0.2, -1.0]),
            ];
            for n in normals {
                let sh = lobe.shade(n, l, v).unwrap();
                gradient_matches(|m| lobe.shade(m, l, v).unwrap().diffuse, sh.d_diffuse, n);
                gradient_matches(|m| lobe.shade(m, l, v).unwrap().specular, sh.d_specular, n);
            }
        }
    }

    /// The factors of every observation of `packed` at the normal `n` (shared terms `w`) by its
    /// kernels (`f32` or `f64` lanes), in `f64`: whether lit, `D`, `S`, grad `D`, grad `S`; and
    /// whether the padding lanes of its last group are all unlit.
    #[allow(clippy::type_complexity)]
    fn packed_factors(
        k: &Kernel,
        packed: &Packed,
        n: [f64; 3],
        w: &View,
    ) -> (Vec<(bool, f64, f64, [f64; 3], [f64; 3])>, bool) {
        let v = packed.view;
        macro_rules! read {
            ($m:ident, $store:expr) => {{
                let groups = $store.groups();
                let mut f = vec![$m::Factors::default(); groups.len()];
                $m::factors_of(k, groups, n, w, v, &mut f);
                let one = |j: usize| {
                    let (g, lane) = (&f[j / $m::W], j % $m::W);
                    let x = |a: $m::F| f64::from(a);
                    (
                        g.lit[lane],
                        x(g.diffuse[lane]),
                        x(g.specular[lane]),
                        std::array::from_fn(|c| x(g.d_diffuse[c][lane])),
                        std::array::from_fn(|c| x(g.d_specular[c][lane])),
                    )
                };
                let last = f.last().unwrap();
                let padding = ($store.len % $m::W..$m::W).all(|lane| !last.lit[lane]);
                ((0..$store.len).map(one).collect(), padding)
            }};
        }
        match packed.precise {
            true => read!(double, packed.double),
            false => read!(single, packed.single),
        }
    }

    /// The packed factors of `shade_group` are those of [`Lobe::shade`] (a partial last group,
    /// unlit lights and padding lanes never lit), in `f32` lanes to `4e-6` of the factor's scale
    /// (the gradients to that of the gradient's length: their coordinates may cancel), in `f64`
    /// lanes to `1e-12`.
    #[test]
    fn packed_factors_match_the_scalar_ones() {
        let v = normalize([0.05, 0.02, -1.0]);
        let ls: Vec<[f64; 3]> = (0..11)
            .map(|i| {
                let t = i as f64;
                normalize([1.2 * (t * 0.21).cos(), 1.2 * (t * 0.53).sin(), -1.0])
            })
            .collect();
        for (precise, tolerance) in [(false, 4e-6), (true, 1e-12)] {
            for lobe in test_lobes() {
                let k = Kernel::new(&lobe);
                let mut packed = if precise {
                    Packed::precise()
                } else {
                    Packed::new()
                };
                packed.clear(v);
                for &l in &ls {
                    packed.push(1.0, 1.0, l);
                }
                packed.prepare(&lobe, [0.0; 3]);
                let mut lit = 0;
                for i in 0..30 {
                    let t = i as f64;
                    let n = normalize([0.9 * (t * 0.37).sin(), 0.9 * (t * 0.73).cos(), -1.0]);
                    let w = k.view(n, v).unwrap();
                    let (f, padding) = packed_factors(&k, &packed, n, &w);
                    assert!(padding);
                    for (j, &l) in ls.iter().enumerate() {
                        let (on, d, s, dd, ds) = f[j];
                        match lobe.shade(n, l, v) {
                            None => assert!(!on),
                            Some(sh) => {
                                lit += 1;
                                assert!(on);
                                let near = |a: f64, b: f64, scale: f64| {
                                    let e = (a - b).abs();
                                    assert!(
                                        e <= tolerance * scale.max(1e-3),
                                        "{a} vs {b} ({lobe:?}, precise {precise})"
                                    );
                                };
                                near(sh.diffuse, d, sh.diffuse);
                                near(sh.specular, s, sh.specular);
                                for c in 0..3 {
                                    near(sh.d_diffuse[c], dd[c], norm(sh.d_diffuse));
                                    near(sh.d_specular[c], ds[c], norm(sh.d_specular));
                                }
                            }
                        }
                    }
                }
                assert!(lit > 200 && lit < 30 * ls.len(), "{lit}");
            }
        }
    }

    /// The point lights' directions, scales, half vectors and Fresnel factors of
    /// [`Packed::prepare`] are those of [`Observation::new`] from [`crate::Light::beta`].
    #[test]
    fn packed_point_lights_match_the_observations() {
        for lobe in [Lobe::new(0.3, 1.5), Lobe::retro(0.3, 1.5)] {
            point_lights_match(&lobe);
        }
    }

    fn point_lights_match(lobe: &Lobe) {
        use crate::Light;
        let x = [3.0, -2.0, 150.0];
        // Isotropic lights, LEDs of mu = 1 and of other exponents (two in one group), and two
        // LEDs that point away from the facet (mu = 1 and 1.7).
        let mus = [0.0, 1.0, 1.7, 0.0, 3.0, 1.0, 1.7, 1.7, 0.0, 1.0, 0.5];
        let lights: Vec<Light> = (0..mus.len())
            .map(|i| {
                let t = i as f64;
                let position = [60.0 * t.cos(), 60.0 * t.sin(), 10.0 * t];
                let axis = match i {
                    5 | 7 => normalize([0.0, 0.0, -1.0]),
                    _ => normalize([0.1 * t, -0.05, 1.0]),
                };
                Light::Point {
                    position,
                    intensity: [1.0 + t, 2.0, 3.0],
                    axis,
                    mu: mus[i],
                }
            })
            .collect();
        for (precise, tolerance) in [(false, 4e-7), (true, 1e-14)] {
            point_lights_match_in(lobe, &lights, x, precise, tolerance);
        }
    }

    /// The prepared lanes of every observation of `packed`, in `f64`: scale, `l`, `h`, Fresnel
    /// factor, `(l.h)^2`.
    #[allow(clippy::type_complexity)]
    fn packed_lanes(packed: &Packed) -> Vec<(f64, [f64; 3], [f64; 3], f64, f64)> {
        macro_rules! read {
            ($m:ident, $store:expr) => {{
                let one = |j: usize| {
                    let (g, lane) = (&$store.groups()[j / $m::W], j % $m::W);
                    let x = |a: $m::F| f64::from(a);
                    (
                        x(g.scale[lane]),
                        std::array::from_fn(|c| x(g.l[c][lane])),
                        std::array::from_fn(|c| x(g.h[c][lane])),
                        x(g.fresnel[lane]),
                        x(g.retro[lane]),
                    )
                };
                (0..$store.len).map(one).collect()
            }};
        }
        match packed.precise {
            true => read!(double, packed.double),
            false => read!(single, packed.single),
        }
    }

    /// [`point_lights_match`] in one precision (`precise`: `f64` lanes), to `tolerance`
    /// relative.
    fn point_lights_match_in(
        lobe: &Lobe,
        lights: &[crate::Light],
        x: [f64; 3],
        precise: bool,
        tolerance: f64,
    ) {
        use crate::Light;
        let v = normalize(scale(x, -1.0));
        let mut packed = match precise {
            true => Packed::precise(),
            false => Packed::new(),
        };
        packed.clear(v);
        for light in lights {
            let Light::Point {
                position,
                intensity,
                axis,
                mu,
            } = *light
            else {
                unreachable!()
            };
            packed.push_point(0.5, intensity[0], position, axis, mu);
        }
        packed.prepare(lobe, x);
        let prepared = packed_lanes(&packed);
        let mut unlit = 0;
        for (j, light) in lights.iter().enumerate() {
            let (scale_j, l, h, fresnel, retro) = prepared[j];
            let (b, _) = light.beta(x);
            let a = norm(b);
            if a == 0.0 {
                assert_eq!(l, [0.0; 3]);
                unlit += 1;
                continue;
            }
            let o = Observation::new(0.5, light.intensity()[0] * a, scale(b, 1.0 / a), v, lobe);
            // Rounded to f32: to a few units of its last place; in f64 to rounding.
            let near = |a: f64, b: f64| {
                assert!(
                    (a - b).abs() <= tolerance * a.abs().max(1.0),
                    "{a} vs {b} (precise {precise})"
                );
            };
            near(o.scale, scale_j);
            for c in 0..3 {
                near(o.light[c], l[c]);
                near(o.half[c], h[c]);
            }
            near(o.fresnel, fresnel);
            if lobe.diffuse == Diffuse::Retro {
                near(o.retro, retro);
            }
        }
        assert_eq!(unlit, 2);
    }

    /// A rig of LEDs with `mu = 1.7` fits the same in the lane form ([`Packed::push_point`],
    /// the anisotropy by `power_lanes` in [`Packed::prepare`]) as from the directions and scales
    /// of [`crate::Light::beta`] (the path such rigs took before): over 40 facets and three
    /// lobes, normals within 1e-5 degrees, albedos within 1e-6 relative.
    #[test]
    fn an_led_rig_of_any_mu_fits_as_from_its_beta() {
        use crate::Light;
        let lights: Vec<Light> = lights()
            .iter()
            .enumerate()
            .map(|(i, &p)| Light::Point {
                position: p,
                intensity: [3.0e4 * (1.0 + 0.05 * i as f64); 3],
                axis: normalize([-0.1 * p[0] / 120.0, -0.1 * p[1] / 120.0, 1.0]),
                mu: 1.7,
            })
            .collect();
        let mut worst: f64 = 0.0;
        for lobe in [
            Lobe::new(0.15, 1.5),
            Lobe::new(0.4, 1.3),
            Lobe::retro(0.25, 1.5),
        ] {
            for i in 0..40 {
                let t = i as f64;
                let n = normalize([0.5 * (t * 0.37).sin(), 0.5 * (t * 0.73).cos(), -1.0]);
                let x = [10.0 * (t * 0.11).sin(), 10.0 * (t * 0.29).cos(), 200.0];
                let v = normalize(scale(x, -1.0));
                let (mut lane, mut scalar) = (Packed::new(), Packed::new());
                lane.clear(v);
                scalar.clear(v);
                for light in &lights {
                    let (b, _) = light.beta(x);
                    let a = norm(b);
                    let phi = light.intensity()[0];
                    let l = scale(b, 1.0 / a);
                    let value = lobe
                        .shade(n, l, v)
                        .map_or(0.0, |s| phi * a * (0.6 * s.diffuse + 0.4 * s.specular));
                    let Light::Point {
                        position, axis, mu, ..
                    } = *light
                    else {
                        unreachable!()
                    };
                    lane.push_point(value, phi, position, axis, mu);
                    scalar.push(value, phi * a, l);
                }
                lane.prepare(&lobe, x);
                scalar.prepare(&lobe, x);
                let start = scale(normalize([n[0] + 0.05, n[1] - 0.04, n[2]]), 0.7);
                let a = fit_packed(&lobe, &mut lane, start, 30).expect("a fit");
                let b = fit_packed(&lobe, &mut scalar, start, 30).expect("a fit");
                let angle = dot(a.normal, b.normal).clamp(-1.0, 1.0).acos().to_degrees();
                worst = worst.max(angle);
                assert!(
                    (a.diffuse - b.diffuse).abs() < 1e-6 * b.diffuse,
                    "{a:?} {b:?}"
                );
                assert!((a.specular - b.specular).abs() < 1e-5 * b.specular + 1e-7);
                // And both find the truth.
                assert!(dot(a.normal, n) > (1e-3f64).to_radians().cos(), "{a:?}");
            }
        }
        assert!(worst < 1e-5, "{worst} deg");
    }

    #[test]
    fn fit_recovers_normal_and_albedos_from_the_lambertian_start() {
        let lobes = [
            Lobe::new(0.15, 1.5),
            Lobe::new(0.3, 1.4),
            Lobe::new(0.5, 1.6),
            Lobe::retro(0.09, 1.5),
            Lobe::retro(0.25, 1.5),
        ];
        for (seed, lobe) in lobes.into_iter().enumerate() {
            let alpha = lobe.alpha;
            let mut worst: f64 = 0.0;
            for i in 0..200 {
                let t = (seed * 200 + i) as f64;
                let n = normalize([0.5 * (t * 0.37).sin(), 0.5 * (t * 0.73).cos(), -1.0]);
                let x = [10.0 * (t * 0.11).sin(), 10.0 * (t * 0.29).cos(), 200.0];
                let obs = observe(&lobe, x, n, 0.6, 0.4);
                let v = normalize(scale(x, -1.0));
                // A Lambertian-like start: off by a few degrees and in albedo.
                let start = scale(normalize([n[0] + 0.05, n[1] - 0.04, n[2]]), 0.7);
                let f = fit(&lobe, &obs, v, start, 30).expect("a fit");
                let angle = dot(f.normal, n).clamp(-1.0, 1.0).acos().to_degrees();
                worst = worst.max(angle);
                assert!(
                    (f.diffuse - 0.6).abs() < 1e-4 && (f.specular - 0.4).abs() < 1e-3,
                    "{f:?}"
                );
            }
            assert!(worst < 1e-3, "alpha {alpha}: worst {worst} deg");
        }
    }

    /// A [`Packed`] reused under other lobes (it keeps the kernel of the last one, see
    /// [`kernel_key`]) fits as a fresh one, bit for bit: lobes that differ in the roughness
    /// alone, the index alone, the shape of the diffuse term alone, and the same lobe again.
    #[test]
    fn a_reused_packed_fits_as_a_fresh_one() {
        let lobes = [
            Lobe::new(0.3, 1.5),
            Lobe::new(0.2, 1.5),
            Lobe::new(0.2, 1.3),
            Lobe::retro(0.2, 1.3),
            Lobe::new(0.2, 1.0),
            Lobe::new(0.2, 1.0),
            Lobe::new(0.3, 1.5),
        ];
        let truth = Lobe::new(0.25, 1.4);
        let mut kept = Packed::new();
        for i in 0..10 {
            let t = i as f64;
            let n = normalize([0.4 * (t * 0.37).sin(), 0.4 * (t * 0.73).cos(), -1.0]);
            let x = [10.0 * (t * 0.11).sin(), 10.0 * (t * 0.29).cos(), 200.0];
            let v = normalize(scale(x, -1.0));
            let start = scale(normalize([n[0] + 0.05, n[1] - 0.04, n[2]]), 0.7);
            for lobe in &lobes {
                // Observations of the truth's lobe fitted under `lobe`: the fits differ by lobe.
                let obs: Vec<Observation> = observe(&truth, x, n, 0.6, 0.4)
                    .iter()
                    .map(|o| Observation::new(o.value, o.scale, o.light, v, lobe))
                    .collect();
                let mut fresh = Packed::new();
                for p in [&mut kept, &mut fresh] {
                    p.clear(v);
                    for o in &obs {
                        p.push_observation(o);
                    }
                }
                let a = fit_packed(lobe, &mut kept, start, 6).expect("a fit");
                let b = fit_packed(lobe, &mut fresh, start, 6).expect("a fit");
                assert_eq!(a, b, "{lobe:?}");
            }
        }
    }

    /// A fit's squared residual, as the scalar `f64` model ([`Lobe::shade`]) gives it at the
    /// fit's unknowns, and the fit's own (`GlossyFit::sse`): in `f64` lanes
    /// ([`Packed::precise`]) they agree to `1e-12` of the observations' squared sum, in `f32`
    /// lanes only to about `1e-7` of it (the rounding of the model, which moved a flat lobe
    /// search, stop 51). The two precisions' normals differ by up to 0.003 degrees here (the
    /// fits stop by tests on the rounded residual; bound 0.01) and they fit. 4 lobes
    /// (one sharp, one retro-reflective) x 30 noisy facets (2 % of the largest value, 3 seeds).
    #[test]
    fn precise_fits_carry_the_scalar_models_residual() {
        let lobes = [
            Lobe::new(0.3, 1.5),
            Lobe::new(0.05, 2.1),
            Lobe::retro(0.2, 1.5),
            Lobe::new(0.15, 1.0),
        ];
        let (mut worst_single, mut worst_double, mut worst_angle) = (0.0f64, 0.0f64, 0.0f64);
        for seed in 0..3u64 {
            let mut uniform = crate::multigrid::tests::lcg(seed);
            for lobe in &lobes {
                for i in 0..10 {
                    let t = i as f64 + 10.0 * seed as f64;
                    let n = normalize([0.4 * (t * 0.37).sin(), 0.4 * (t * 0.73).cos(), -1.0]);
                    let x = [10.0 * (t * 0.11).sin(), 10.0 * (t * 0.29).cos(), 200.0];
                    let v = normalize(scale(x, -1.0));
                    let mut obs = observe(lobe, x, n, 0.6, 0.4);
                    let top = obs.iter().map(|o| o.value).fold(0.0, f64::max);
                    for o in &mut obs {
                        o.value += 0.02 * top * (2.0 * uniform() - 1.0);
                    }
                    let total: f64 = obs.iter().map(|o| o.value * o.value).sum();
                    let start = scale(normalize([n[0] + 0.05, n[1] - 0.04, n[2]]), 0.7);
                    let mut fits = Vec::new();
                    for mut packed in [Packed::new(), Packed::precise()] {
                        packed.clear(v);
                        for o in &obs {
                            packed.push_observation(o);
                        }
                        let fit = fit_packed(lobe, &mut packed, start, 30).expect("a fit");
                        // The scalar model's squared residual at the fit's unknowns.
                        let sse: f64 = obs
                            .iter()
                            .map(|o| {
                                // (Lights that do not reach the facet are not used.)
                                lobe.shade(fit.normal, o.light, v).map_or(0.0, |sh| {
                                    let m = o.scale
                                        * (fit.diffuse * sh.diffuse + fit.specular * sh.specular);
                                    (o.value - m) * (o.value - m)
                                })
                            })
                            .sum();
                        let error = (fit.sse - sse).abs() / total;
                        match packed.precise {
                            true => worst_double = worst_double.max(error),
                            false => worst_single = worst_single.max(error),
                        }
                        fits.push(fit);
                    }
                    let angle = dot(fits[0].normal, fits[1].normal)
                        .min(1.0)
                        .acos()
                        .to_degrees();
                    worst_angle = worst_angle.max(angle);
                }
            }
        }
        eprintln!("residual: f32 {worst_single:e}, f64 {worst_double:e}; {worst_angle} degrees");
        assert!(worst_double <= 1e-12, "{worst_double}");
        assert!(worst_single <= 1e-5, "{worst_single}");
        // The f32 lanes' residual is rounded (not a bound that could not fail).
        assert!(
            worst_single > 100.0 * worst_double,
            "{worst_single} {worst_double}"
        );
        assert!(worst_angle <= 0.01, "{worst_angle}");
    }

    /// With the step tolerance a fit ends within about the tolerance of the exact fit (from a
    /// far start and from a warm one), and a fit started at the exact fit's normal stops there
    /// at once with its albedos; with tolerance 0 it is the exact fit, bit for bit.
    #[test]
    fn the_step_tolerance_ends_near_the_exact_fit() {
        let lobe = Lobe::new(0.3, 1.5);
        let mut worst: f64 = 0.0;
        for i in 0..100 {
            let t = i as f64;
            let n = normalize([0.5 * (t * 0.37).sin(), 0.5 * (t * 0.73).cos(), -1.0]);
            let x = [10.0 * (t * 0.11).sin(), 10.0 * (t * 0.29).cos(), 200.0];
            let v = normalize(scale(x, -1.0));
            let mut packed = Packed::new();
            packed.clear(v);
            for o in observe(&lobe, x, n, 0.6, 0.4) {
                packed.push_observation(&o);
            }
            let start = scale(normalize([n[0] + 0.05, n[1] - 0.04, n[2]]), 0.7);
            let exact = fit_packed(&lobe, &mut packed, start, 30).unwrap();
            let zero = fit_packed_within(&lobe, &mut packed, start, 30, 0.0).unwrap();
            assert_eq!(exact, zero);
            let within = fit_packed_within(&lobe, &mut packed, start, 30, STEP_TOLERANCE).unwrap();
            let angle = |a: [f64; 3], b: [f64; 3]| dot(a, b).clamp(-1.0, 1.0).acos();
            worst = worst.max(angle(within.normal, exact.normal));
            assert!(
                (within.diffuse - exact.diffuse).abs() < 10.0 * STEP_TOLERANCE,
                "{within:?}"
            );
            assert!((within.specular - exact.specular).abs() < 10.0 * STEP_TOLERANCE);
            // A warm start near the fit: at most a few steps, and as close.
            let near = normalize([exact.normal[0] + 1e-4, exact.normal[1], exact.normal[2]]);
            let warm = fit_packed_at_within(&lobe, &mut packed, near, 3, STEP_TOLERANCE).unwrap();
            worst = worst.max(angle(warm.normal, exact.normal));
            // At the fit's own normal: it stays there.
            let there = fit_packed_at_within(&lobe, &mut packed, exact.normal, 3, STEP_TOLERANCE);
            assert!(dot(there.unwrap().normal, exact.normal) > 1.0 - 1e-15);
        }
        assert!(worst < 10.0 * STEP_TOLERANCE, "{worst} rad");
    }

    /// Fits from warm starts near their minimum, on noisy observations: with the step
    /// tolerance, a fit whose last step settled takes the next one without evaluating the model
    /// at its end (see [`SETTLED_RATIO`]). Such fits end as near the minimum as the step tolerance
    /// says, report that they converged, and report the residual of the model at their unknowns
    /// (or the one before their last step, as near). With two steps allowed, a fit that needs
    /// both ends converged only by taking its second step unevaluated: some do.
    #[test]
    fn a_settled_fit_takes_its_last_step_unevaluated() {
        let lobe = Lobe::new(0.3, 1.5);
        let angle = |a: [f64; 3], b: [f64; 3]| dot(a, b).clamp(-1.0, 1.0).acos();
        let mut state = 7u64;
        let (mut worst, mut converged_in_two) = (0.0f64, 0);
        for i in 0..100 {
            let t = i as f64;
            let n = normalize([0.5 * (t * 0.37).sin(), 0.5 * (t * 0.73).cos(), -1.0]);
            let x = [10.0 * (t * 0.11).sin(), 10.0 * (t * 0.29).cos(), 200.0];
            let v = normalize(scale(x, -1.0));
            let mut obs = observe(&lobe, x, n, 0.6, 0.4);
            for o in &mut obs {
                o.value += 0.005 * uniform(&mut state);
            }
            let mut packed = Packed::new();
            packed.clear(v);
            for o in &obs {
                packed.push_observation(o);
            }
            let exact = fit_packed(&lobe, &mut packed, scale(n, 0.6), 30).unwrap();
            let start = normalize([n[0] + 0.006, n[1] - 0.004, n[2]]);
            let fit = fit_packed_at_within(&lobe, &mut packed, start, 30, STEP_TOLERANCE).unwrap();
            assert!(fit.converged, "{i}: {fit:?}");
            worst = worst.max(angle(fit.normal, exact.normal));
            // The residual of the scalar model at the fit's unknowns.
            let sse: f64 = obs
                .iter()
                .filter_map(|o| {
                    let s = lobe.shade(fit.normal, o.light, v)?;
                    let e =
                        o.value - o.scale * (fit.diffuse * s.diffuse + fit.specular * s.specular);
                    Some(e * e)
                })
                .sum();
            assert!(
                (fit.sse - sse).abs() <= 1e-3 * sse,
                "{i}: {} against {sse}",
                fit.sse
            );
            let two = fit_packed_at_within(&lobe, &mut packed, start, 2, STEP_TOLERANCE).unwrap();
            converged_in_two += usize::from(two.converged);
        }
        assert!(worst < 10.0 * STEP_TOLERANCE, "{worst} rad");
        assert!(converged_in_two >= 10, "{converged_in_two} of 100");
    }

    /// A fit cut off by its last allowed step reports that it did not converge; one that ends
    /// by its step tolerance, or at its minimum, reports that it did (the flag the local steps
    /// keep fits by). Over 50 facets from a far start.
    #[test]
    fn a_fit_reports_whether_it_converged() {
        let lobe = Lobe::new(0.3, 1.5);
        for i in 0..50 {
            let t = i as f64;
            let n = normalize([0.5 * (t * 0.37).sin(), 0.5 * (t * 0.73).cos(), -1.0]);
            let x = [10.0 * (t * 0.11).sin(), 10.0 * (t * 0.29).cos(), 200.0];
            let mut packed = Packed::new();
            packed.clear(normalize(scale(x, -1.0)));
            for o in observe(&lobe, x, n, 0.6, 0.4) {
                packed.push_observation(&o);
            }
            let start = scale(normalize([n[0] + 0.05, n[1] - 0.04, n[2]]), 0.7);
            let one = fit_packed_within(&lobe, &mut packed, start, 1, STEP_TOLERANCE).unwrap();
            assert!(!one.converged, "{one:?}");
            for tolerance in [0.0, STEP_TOLERANCE] {
                let full = fit_packed_within(&lobe, &mut packed, start, 30, tolerance).unwrap();
                assert!(full.converged, "{full:?}");
            }
            // From the fit's normal (with the albedos there) three steps are allowed: the
            // tolerance ends the fit before the last.
            let full = fit_packed_within(&lobe, &mut packed, start, 30, STEP_TOLERANCE).unwrap();
            let there = fit_packed_at_within(&lobe, &mut packed, full.normal, 3, STEP_TOLERANCE);
            assert!(there.unwrap().converged);
        }
    }

    /// With the noise's variance given, a fit with a step tolerance stops where the decrease
    /// left is within the noise: its squared residual is above that of the fit run to its
    /// minimum by at most about [`NOISE_STOP`] `sigma^2` (the linearised model's promise; here
    /// within 3 `sigma^2`), it reports converged, and over the facets its normals are on average
    /// no farther from the truth than the minima's (from a start 2.9 degrees off). Without the
    /// noise (0) the fit is the one without the rule, bit for bit. 5 seeds x 40 facets with
    /// Gaussian noise of 0.5 % and 2 % of the largest value; more than 50 of the 200 fits stop
    /// short of their minimum.
    #[test]
    fn fits_stop_once_the_decrease_left_is_within_the_noise() {
        let lobe = Lobe::new(0.3, 1.5);
        let mut stopped_early = 0;
        // The mean angle to the truth of the fits that stop and of those run to the minimum,
        // at each noise level (100 facets each).
        let mut errors = [[0.0f64; 2]; 2];
        for seed in 0..5u64 {
            let mut uniform = crate::multigrid::tests::lcg(seed);
            let mut gauss = move || {
                let (a, b) = (uniform().max(1e-300), uniform());
                (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
            };
            for (i, level) in [0.005, 0.02].into_iter().cycle().take(40).enumerate() {
                let t = (i as f64) + 13.0 * seed as f64;
                let n = normalize([0.4 * (t * 0.37).sin(), 0.4 * (t * 0.73).cos(), -1.0]);
                let x = [10.0 * (t * 0.11).sin(), 10.0 * (t * 0.29).cos(), 200.0];
                let mut obs = observe(&lobe, x, n, 0.6, 0.3);
                let top = obs.iter().map(|o| o.value).fold(0.0, f64::max);
                let sigma = level * top;
                for o in &mut obs {
                    o.value += sigma * gauss();
                }
                let mut packed = Packed::new();
                packed.clear(normalize(scale(x, -1.0)));
                for o in &obs {
                    packed.push_observation(o);
                }
                // A start a few degrees off, as a coarser level's normal.
                let start = scale(normalize([n[0] + 0.04, n[1] - 0.03, n[2]]), 0.6);
                let plain = fit_packed_within(&lobe, &mut packed, start, 30, STEP_TOLERANCE);
                let best = fit_packed_within(&lobe, &mut packed, start, 30, 0.0).unwrap();
                packed.noise = 0.0;
                let none = fit_packed_within(&lobe, &mut packed, start, 30, STEP_TOLERANCE);
                assert_eq!(none, plain);
                packed.noise = sigma * sigma;
                let fit = fit_packed_within(&lobe, &mut packed, start, 30, STEP_TOLERANCE).unwrap();
                assert!(fit.converged, "{fit:?}");
                // (A fit whose last step was taken unevaluated reports the linearised model's
                // residual, which may lie a little below the least: see `SETTLED_RATIO`.)
                let excess = (fit.sse - best.sse) / (sigma * sigma);
                assert!(
                    (-1e-2..=3.0 * NOISE_STOP).contains(&excess),
                    "seed {seed} facet {i}: {excess} {fit:?} {best:?}"
                );
                let error = |g: &GlossyFit| dot(g.normal, n).min(1.0).acos();
                errors[i % 2][0] += error(&fit) / 100.0;
                errors[i % 2][1] += error(&best) / 100.0;
                stopped_early += (fit.sse > best.sse + 1e-12 * best.sse) as usize;
            }
        }
        // Against the truth the fits that stop are not worse than those run to the minimum.
        for [stopped, least] in errors {
            eprintln!("mean error stopped {stopped} least {least}");
            assert!(stopped <= 1.02 * least, "{stopped} {least}");
        }
        // The rule does stop fits short of their minimum (not a test that cannot fail).
        assert!(stopped_early > 50, "{stopped_early}");
    }

    /// A fit stopped within the noise keeps standing for a fit made again once its centre moved
    /// by up to its [`GlossyFit::latitude`] of its reach (the same observed values seen along
    /// the moved centre's light and view vectors, with their falloff): made again from its
    /// normal, every such fit stops at once (the same normal), while moves of 30 times as much
    /// make most of them take a step (the latitude is not a bound that could not fail). Without
    /// noise the latitude is 0. 5 seeds x 20 facets, Gaussian noise of 0.5 % and 2 % of the
    /// largest value, moves in random directions.
    #[test]
    fn a_fit_stands_while_its_centre_moves_within_its_latitude() {
        let lobe = Lobe::new(0.3, 1.5);
        let at = |x: [f64; 3], values: &[f64]| {
            let mut packed = Packed::new();
            packed.clear(normalize(scale(x, -1.0)));
            for (&p, &value) in lights().iter().zip(values) {
                let a = sub(p, x);
                let l = normalize(a);
                let o = Observation::new(value, 4.0e4 / dot(a, a), l, packed.view, &lobe);
                packed.push_observation(&o);
            }
            packed
        };
        let (mut total, mut stepped_far, mut latitudes) = (0, 0, Vec::new());
        for seed in 0..5u64 {
            let mut uniform = crate::multigrid::tests::lcg(seed);
            let mut gauss = move || {
                let (a, b) = (uniform().max(1e-300), uniform());
                (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
            };
            let mut direction = crate::multigrid::tests::lcg(100 + seed);
            for (i, level) in [0.005, 0.02].into_iter().cycle().take(20).enumerate() {
                let t = (i as f64) + 13.0 * seed as f64;
                let n = normalize([0.4 * (t * 0.37).sin(), 0.4 * (t * 0.73).cos(), -1.0]);
                let x = [10.0 * (t * 0.11).sin(), 10.0 * (t * 0.29).cos(), 200.0];
                let obs = observe(&lobe, x, n, 0.6, 0.3);
                let top = obs.iter().map(|o| o.value).fold(0.0, f64::max);
                let sigma = level * top;
                let values: Vec<f64> = obs.iter().map(|o| o.value + sigma * gauss()).collect();
                let mut packed = at(x, &values);
                let start = scale(normalize([n[0] + 0.04, n[1] - 0.03, n[2]]), 0.6);
                let quiet = fit_packed_within(&lobe, &mut packed, start, 30, STEP_TOLERANCE);
                assert_eq!(quiet.unwrap().latitude, 0.0);
                packed.noise = sigma * sigma;
                let fit = fit_packed_within(&lobe, &mut packed, start, 30, STEP_TOLERANCE).unwrap();
                assert!(fit.converged && fit.latitude > 0.0, "{fit:?}");
                latitudes.push(fit.latitude);
                let reach = lights()
                    .iter()
                    .map(|&p| norm(sub(p, x)))
                    .fold(norm(x), f64::min);
                for (factor, near) in [(0.9, true), (30.0, false)] {
                    let d = normalize([direction() - 0.5, direction() - 0.5, direction() - 0.5]);
                    let moved =
                        std::array::from_fn(|j| x[j] + factor * fit.latitude * reach * d[j]);
                    let mut packed = at(moved, &values);
                    packed.noise = sigma * sigma;
                    let again =
                        fit_packed_at_within(&lobe, &mut packed, fit.normal, 30, STEP_TOLERANCE)
                            .unwrap();
                    let same = dot(again.normal, fit.normal) >= 1.0 - 1e-12;
                    match near {
                        true => assert!(same, "seed {seed} facet {i}: {fit:?} {again:?}"),
                        false => stepped_far += !same as usize,
                    }
                }
                total += 1;
            }
        }
        latitudes.sort_by(f64::total_cmp);
        eprintln!(
            "latitudes {:?}; {stepped_far} of {total} stepped",
            latitudes
        );
        assert!(stepped_far > total / 2, "{stepped_far} of {total}");
    }

    #[test]
    fn matte_facets_get_no_specular_albedo() {
        let lobe = Lobe::new(0.3, 1.5);
        let n = normalize([0.2, 0.1, -1.0]);
        let x = [5.0, -3.0, 200.0];
        let obs = observe(&lobe, x, n, 0.5, 0.0);
        let f = fit(&lobe, &obs, normalize(scale(x, -1.0)), scale(n, 0.5), 20).unwrap();
        assert!(f.specular < 1e-6 && dot(f.normal, n) > 1.0 - 1e-10, "{f:?}");
    }
}
