//! The light model: the one place where the irradiance of a light source is written.
//!
//! A surface point `x` with unit normal `n` and albedo `rho` is imaged under a light of
//! intensity `Phi` (per channel; grey images use the mean of the channels,
//! [`channel_intensity`]) as
//!
//! ```text
//! I = rho * Phi * max(0, n . beta(x))
//! ```
//!
//! with the irradiance factor `beta` of the light:
//! - a point light (an LED) at `p` with unit principal direction `axis` and anisotropy `mu >= 0`
//!   (Quéau et al. 2018): with `a = p - x`,
//!   `beta(x) = aniso(x) a / |a|^3`, `aniso(x) = max(0, t)^mu`, `t = -a . axis / |a|` (the
//!   cosine between the axis and the direction from the LED to `x`); `mu = 0` is an isotropic
//!   point light (`aniso = 1`, the axis unused);
//! - a directional light: `beta = direction` (unit, from the surface towards the light).
//!
//! What this module provides, each written once:
//! - [`Light::beta`]: `beta(x)` and the paper's weighting factor `|a|^3 / aniso`;
//!   [`Light::shading`]: `max(0, n . beta(x))`;
//! - [`Light::beta_gradient`] and [`Light::beta_gradient_at`]: the gradient of `beta(x) . g`
//!   with respect to the light position and to the surface point, from the position
//!   derivative's terms [`Gradient`]; [`derivatives`]: the derivatives of a prediction
//!   `Phi beta . g` with respect to the refined light parameters (log-intensity, position), the
//!   one function of the light step (whose terms come from the lanes) and of the tests;
//! - [`Light::with_shape`]: the LED shape `(mu, axis)` that calibration fits (it differentiates
//!   the shape by finite differences of [`Light::beta`], so no analytic shape derivative exists);
//! - [`LaneLight`] and [`LaneLight::beta`]: the lane (SIMD) form of `beta` for several surface
//!   points at once, with its eligibility rule ([`LaneLight::from_light`]: every point light),
//!   the same operations in the same order as [`Light::beta`]; [`LaneLight::step_terms`]: the
//!   light refinement's terms (`beta` and the position derivative's factors) in lanes, bit for
//!   bit those of [`Light::beta_anisotropy`] and of the scalar [`Gradient`];
//! - [`anisotropy`] and [`power_lanes`]: the LED anisotropy `t^mu` without libm, in lanes
//!   (a libm call per facet and light was a third of an LED rig's reconstruction, and kept LED
//!   rigs with `mu` other than 0 or 1 out of the lane form).
//!
//! Adding a light model means a new [`Light`] variant here, its entry in the rig file reader and
//! the bindings, and its Python value class.
//!
//! All arithmetic is written out in a fixed order: the reconstruction's results depend on it to
//! the bit, and the lane form must agree with the scalar one exactly.

use crate::error::{g6, Error, Result};
use crate::vec3::{dot, norm, sub};

/// Largest magnitude of a length or pixel coordinate of a rig (camera values, light positions)
/// and of a depth; pixel sizes, focal lengths and pinhole depths are at least [`MIN_MAGNITUDE`].
/// No real rig comes near either bound, and values beyond them overflow or underflow the
/// geometry (cubes of distances, cross products of vertex offsets) into NaN results.
pub const MAX_MAGNITUDE: f64 = 1e12;
/// Smallest pixel size, focal length and pinhole depth (see [`MAX_MAGNITUDE`]).
pub const MIN_MAGNITUDE: f64 = 1e-12;

/// The position derivative's terms of a point light at a surface point `x`: `v = p - x`, the
/// fall-off `f = t^mu / |v|^3` of `beta = f v` and its gradient `grad f` with respect to `p`
/// (see [`Light::falloff_gradient`]; in lanes, [`LaneLight::step_terms`]). All zero where the
/// gradient vanishes (a directional light, an LED's outside).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct Gradient {
    pub v: [f64; 3],
    pub f: f64,
    pub grad_f: [f64; 3],
}

impl Gradient {
    /// The gradient of `beta . g` with respect to the light's position: `d(f v . g)/dp =
    /// f g + (v . g) grad f` (`dv/dp` is the identity).
    #[inline(always)]
    pub fn along(&self, g: [f64; 3]) -> [f64; 3] {
        let vg = dot(self.v, g);
        crate::lanes(|j| self.f * g[j] + vg * self.grad_f[j])
    }
}

/// `d(a . g)/d theta` of a light with row `a = phi beta(c)` (`phi` its intensity in the
/// channel) at a surface point `c` with scaled normal `g`: the log-intensity derivative `a . g`
/// first (if `intensity`), then the position's `phi d(beta . g)/dp = phi (f g + (v . g) grad f)`
/// from the light's terms `grad` at `c` (if `position`; zero without them: a directional light,
/// an LED's outside); unused entries 0. The one form of the light step's derivatives (its
/// terms from [`LaneLight::step_terms`], the tests' from [`Light::falloff_gradient`]).
#[inline(always)]
pub(crate) fn derivatives(
    a: [f64; 3],
    g: [f64; 3],
    phi: f64,
    (intensity, position): (bool, bool),
    grad: Option<&Gradient>,
) -> [f64; 4] {
    let mut d = [0.0; 4];
    let mut k = 0;
    if intensity {
        d[0] = dot(a, g);
        k = 1;
    }
    if let Some(t) = grad.filter(|_| position) {
        let along = t.along(g);
        for j in 0..3 {
            d[k + j] = phi * along[j];
        }
    }
    d
}

/// Fails when a value of `values` (named `what`) is beyond [`MAX_MAGNITUDE`].
pub(crate) fn check_magnitude(what: &str, values: &[f64]) -> Result<()> {
    match values.iter().find(|v| v.abs() > MAX_MAGNITUDE) {
        Some(v) => Err(Error::Rig(format!(
            "{what} has the value {}, beyond {} in magnitude: no rig has such values, and they \
             overflow the geometry",
            g6(*v),
            g6(MAX_MAGNITUDE)
        ))),
        None => Ok(()),
    }
}

/// Numbers for messages, each with 6 significant digits: `[1, 0.5, 1.00000e300]`.
pub(crate) fn g6_list(values: &[f64]) -> String {
    let items: Vec<String> = values.iter().map(|&v| g6(v)).collect();
    format!("[{}]", items.join(", "))
}

/// The intensity `Phi` of a light with channel intensities `phi` in channel `ch` of images with
/// `channels` channels: grey images (1 channel) use the mean of the three.
#[inline]
pub(crate) fn channel_intensity(phi: [f64; 3], channels: usize, ch: usize) -> f64 {
    if channels == 1 {
        (phi[0] + phi[1] + phi[2]) / 3.0
    } else {
        phi[ch]
    }
}

/// A light source. Image model at surface point `x` with unit normal `n`, albedo `rho`, in
/// channel `ch`: `I = rho * intensity[ch] * max(0, n . beta(x))` (grey images use the mean of
/// the channels), with `beta` as given for each kind.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub enum Light {
    /// A near point light (an LED) at `position`, emitting around the unit `axis` with
    /// anisotropy `mu` (Quéau et al. 2018): `beta(x) = max(0, (x - p) . axis / |x - p|)^mu *
    /// (p - x) / |p - x|^3`; `mu = 0` is an isotropic point light (the axis is then unused).
    Point {
        /// Position p in the camera frame.
        position: [f64; 3],
        /// Intensity per channel (R, G, B; grey images use the mean).
        intensity: [f64; 3],
        /// Unit principal direction, from the LED towards the scene.
        axis: [f64; 3],
        /// Anisotropy mu >= 0.
        mu: f64,
    },
    /// A distant light: `beta = direction` (unit, from the surface towards the light).
    Directional {
        /// Unit direction from the surface towards the light.
        direction: [f64; 3],
        /// Intensity per channel.
        intensity: [f64; 3],
    },
}

impl Light {
    /// An isotropic point light of unit intensity.
    pub fn point(position: [f64; 3]) -> Light {
        Light::Point {
            position,
            intensity: [1.0; 3],
            axis: [0.0, 0.0, 1.0],
            mu: 0.0,
        }
    }

    /// Intensity per channel.
    pub fn intensity(&self) -> [f64; 3] {
        match *self {
            Light::Point { intensity, .. } | Light::Directional { intensity, .. } => intensity,
        }
    }

    /// This light with the LED shape `mu`, `axis` (a point light; a directional light is
    /// returned unchanged): the parameters that intensity calibration fits.
    pub(crate) fn with_shape(&self, mu: f64, axis: [f64; 3]) -> Light {
        match *self {
            Light::Point {
                position,
                intensity,
                ..
            } => Light::Point {
                position,
                intensity,
                axis,
                mu,
            },
            other => other,
        }
    }

    /// `beta(x)` (see [`Light`]) and the factor `|p - x|^3 / aniso` that turns the paper's
    /// Eq. 6 weighting into equation weights (1 for directional lights).
    #[inline]
    pub fn beta(&self, x: [f64; 3]) -> ([f64; 3], f64) {
        let (b, d3, aniso) = self.beta_parts(x);
        (b, d3 / aniso)
    }

    /// `beta(x)` and the anisotropy factor `t^mu` (1 for an isotropic or directional light, 0
    /// outside an LED's cone): the one power of the model, which
    /// [`Light::falloff_gradient`] can take instead of computing it again.
    /// The scalar reference of [`LaneLight::step_terms`] (the light step uses the lane form).
    #[cfg_attr(not(test), allow(dead_code))]
    #[inline]
    pub(crate) fn beta_anisotropy(&self, x: [f64; 3]) -> ([f64; 3], f64) {
        let (b, _, aniso) = self.beta_parts(x);
        (b, aniso)
    }

    /// `beta(x)`, `|p - x|^3` and `t^mu` (directional: the direction, 1, 1).
    #[inline]
    fn beta_parts(&self, x: [f64; 3]) -> ([f64; 3], f64, f64) {
        match *self {
            Light::Point {
                position, axis, mu, ..
            } => {
                let a = sub(position, x);
                let d2 = dot(a, a);
                let d = d2.sqrt();
                let d3 = d2 * d;
                let aniso = anisotropy((-dot(a, axis) / d).max(0.0), mu);
                let f = aniso / d3;
                ([a[0] * f, a[1] * f, a[2] * f], d3, aniso)
            }
            Light::Directional { direction, .. } => (direction, 1.0, 1.0),
        }
    }

    /// The shading `max(0, n . beta(x))` of a surface point `x` with unit normal `n` (attached
    /// shadows clipped at 0; the image is `rho * Phi` times it).
    #[inline]
    pub(crate) fn shading(&self, n: [f64; 3], x: [f64; 3]) -> f64 {
        dot(n, self.beta(x).0).max(0.0)
    }

    /// For a point light at `p` and the surface point `x`: `v = p - x`, the factor
    /// `f = aniso / |v|^3` with `beta = f v`, and its gradient with respect to `p`,
    ///
    /// ```text
    /// grad f = mu t^(mu-1) (-axis / |v| + (v . axis) v / |v|^3) / |v|^3 - 3 t^mu v / |v|^5
    /// ```
    ///
    /// (for `mu = 0`, `-3 v / |v|^5`). None for a directional light and for an LED outside its
    /// cone (`t <= 0`), where `beta` and its gradient vanish. With `aniso = t^mu` given (from
    /// [`Light::beta_anisotropy`] at the same `x`) no power is computed: `t^(mu-1) = t^mu / t`
    /// (equal to `powf(mu - 1)` up to rounding).
    #[inline]
    pub(crate) fn falloff_gradient(&self, x: [f64; 3], aniso: Option<f64>) -> Option<Gradient> {
        let Light::Point {
            position: p,
            axis,
            mu,
            ..
        } = *self
        else {
            return None;
        };
        let v = sub(p, x);
        let d2 = dot(v, v);
        let len = d2.sqrt();
        let inv3 = 1.0 / (d2 * len);
        let inv5 = inv3 / d2;
        if mu == 0.0 {
            return Some(Gradient {
                v,
                f: inv3,
                grad_f: v.map(|x| -3.0 * x * inv5),
            });
        }
        let va = dot(v, axis);
        let t = -va / len;
        if t <= 0.0 {
            return None;
        }
        let (tm, tm1) = match aniso {
            Some(tm) => (tm, tm / t),
            None => (anisotropy(t, mu), anisotropy(t, mu - 1.0)),
        };
        let dt: [f64; 3] = crate::lanes(|j| -axis[j] / len + va * v[j] * inv3);
        let dm = mu * tm1 * inv3;
        Some(Gradient {
            v,
            f: tm * inv3,
            grad_f: crate::lanes(|j| dm * dt[j] - 3.0 * tm * v[j] * inv5),
        })
    }

    /// The gradient of `beta(x) . g` with respect to the light's position `p`: with
    /// `beta = f(v) v`, `v = p - x`, it is `f g + (v . g) grad f` (see
    /// [`Light::falloff_gradient`]). None for a directional light (no position) and where
    /// `beta` vanishes (an LED's outside, `t <= 0`: the gradient is zero).
    #[inline]
    pub(crate) fn beta_gradient(&self, x: [f64; 3], g: [f64; 3]) -> Option<[f64; 3]> {
        self.beta_gradient_with(x, g, None)
    }

    /// [`Light::beta_gradient`] with `t^mu` at `x` given (see [`Light::falloff_gradient`]).
    #[inline]
    fn beta_gradient_with(&self, x: [f64; 3], g: [f64; 3], aniso: Option<f64>) -> Option<[f64; 3]> {
        Some(self.falloff_gradient(x, aniso)?.along(g))
    }

    /// The gradient of `beta(x) . g` with respect to the surface point `x`: `beta` depends on
    /// `p - x` only, so it is minus [`Light::beta_gradient`] for a point light, and zero for a
    /// directional light (None, as where an LED's `beta` vanishes).
    #[cfg_attr(not(test), allow(dead_code))]
    #[inline]
    pub(crate) fn beta_gradient_at(&self, x: [f64; 3], g: [f64; 3]) -> Option<[f64; 3]> {
        self.beta_gradient(x, g).map(|d| d.map(|v| -v))
    }

    /// Whether the light stands strictly in front of a surface whose nearest depth is `depth`
    /// (a point light's z below it; a NaN depth is in front of nothing). Directional lights are
    /// always in front.
    #[inline]
    pub fn is_in_front_of(&self, depth: f64) -> bool {
        match *self {
            Light::Point { position, .. } => position[2] < depth,
            Light::Directional { .. } => true,
        }
    }

    /// Checks light `i`'s parameters: finite, within [`MAX_MAGNITUDE`], positive intensities,
    /// `mu >= 0`, a unit axis for an anisotropic LED and a unit direction.
    pub(crate) fn validate(&self, i: usize) -> Result<()> {
        let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
        let (vector, name, intensity, axis, mu) = match *self {
            Light::Point {
                position,
                intensity,
                axis,
                mu,
            } => (position, "position", intensity, axis, mu),
            Light::Directional {
                direction,
                intensity,
            } => (direction, "direction", intensity, [0.0, 0.0, 1.0], 0.0),
        };
        if !finite(&vector) {
            return Err(Error::Rig(format!(
                "light {i} has a non-finite {name} {}",
                g6_list(&vector)
            )));
        }
        check_magnitude(&format!("light {i}'s {name}"), &vector)?;
        if !finite(&intensity) {
            return Err(Error::Rig(format!(
                "light {i} has a non-finite intensity {}",
                g6_list(&intensity)
            )));
        }
        if !finite(&axis) || !mu.is_finite() {
            return Err(Error::Rig(format!(
                "light {i} has a non-finite principal direction {} or anisotropy mu = {}",
                g6_list(&axis),
                g6(mu)
            )));
        }
        if !intensity.iter().all(|v| *v > 0.0) {
            return Err(Error::Rig(format!(
                "light {i} must have positive intensities, got {}",
                g6_list(&intensity)
            )));
        }
        if mu < 0.0 {
            return Err(Error::Rig(format!(
                "light {i} has anisotropy mu = {}; it must be >= 0",
                g6(mu)
            )));
        }
        let unit = |v: [f64; 3]| (norm(v) - 1.0).abs() < 1e-6;
        match *self {
            Light::Point { axis, mu, .. } if mu > 0.0 && !unit(axis) => Err(Error::Rig(format!(
                "light {i}: the principal direction of an anisotropic LED must be a unit vector, got {}",
                g6_list(&axis)
            ))),
            Light::Directional { direction, .. } if !unit(direction) => Err(Error::Rig(format!(
                "light {i}: a directional light needs a unit direction, got {}",
                g6_list(&direction)
            ))),
            _ => Ok(()),
        }
    }
}

/// `ln 2` split so that `k * LN2_HI` is exact for integers `|k| < 2^21` (its last 21 bits zero).
const LN2_HI: f64 = f64::from_bits(0x3FE6_2E42_FEE0_0000);
/// `ln 2 - LN2_HI` (to double precision).
const LN2_LO: f64 = 1.908_214_929_270_587_7e-10;
/// Adding and subtracting it rounds a float below `2^51` in magnitude to the nearest integer
/// (and its bits then hold that integer in their low part).
const ROUND: f64 = 6_755_399_441_055_744.0; // 1.5 * 2^52

/// `base^exponent` for `N` bases at once with one exponent, for the LED anisotropy `t^mu`
/// (`t = max(0, cos)` in `[0, 1]`): straight-line code over the lanes (no call into libm, no
/// branch per lane), so that it runs in SIMD registers inside the lane form of the model, and
/// the one power of the scalar model too ([`anisotropy`], one lane), so that both agree bit for bit.
///
/// With `b = m 2^e`, `m` in `[sqrt(1/2), sqrt(2))` (subnormal bases scaled by `2^54` first),
/// `ln b = e ln 2 + 2 atanh(s)`, `s = (m - 1) / (m + 1)`, `|s| <= 0.172`, the series
/// `atanh(s) = s (1 + s^2/3 + ... + s^22/23)` (remainder below `1e-19` relative); then `y =
/// exponent * ln b = k ln 2 + r` with `k` the nearest integer of `y / ln 2` (`ln 2` in two parts,
/// Cody-Waite) and `|r| <= ln 2 / 2`, `exp(r)` by its Taylor series to `r^14/14!` (remainder
/// below `5e-18`) and the result `exp(r) 2^k`, the power of two built in two halves so that
/// results down to the subnormals and up to infinity come out right. `ln b` is good to about
/// one unit in the last place, and the product `y` carries that to the result: its relative
/// error is about `(1 + |y|) 2^-52` (libm's `powf` is correctly rounded); measured in
/// `power_matches_libm` below. Special values as
/// `powf` for non-negative bases: `0^e` is 0 for `e > 0`, 1 for `e = 0`, infinity for `e < 0`;
/// `b^0 = 1` and `1^e = 1` exactly. A base of NaN or below 0 is not for this function.
#[inline(always)]
pub(crate) fn power_lanes<const N: usize>(base: &[f64; N], exponent: f64) -> [f64; N] {
    const SCALE: f64 = 18_014_398_509_481_984.0; // 2^54
    let tiny: [bool; N] = crate::lanes(|l| base[l] < f64::MIN_POSITIVE);
    let b: [f64; N] = crate::lanes(|l| if tiny[l] { base[l] * SCALE } else { base[l] });
    let bits: [u64; N] = crate::lanes(|l| b[l].to_bits());
    // The mantissa in [1, 2), halved when above sqrt(2) (its exponent then one more).
    let high: [bool; N] =
        crate::lanes(|l| (bits[l] & 0x000F_FFFF_FFFF_FFFF) > 0x0006_A09E_667F_3BCC);
    let m: [f64; N] = crate::lanes(|l| {
        let exponent_bits = if high[l] {
            0x3FE0_0000_0000_0000
        } else {
            0x3FF0_0000_0000_0000
        };
        f64::from_bits((bits[l] & 0x000F_FFFF_FFFF_FFFF) | exponent_bits)
    });
    let e: [f64; N] = crate::lanes(|l| {
        let biased = ((bits[l] >> 52) & 0x7FF) as i64 + i64::from(high[l]);
        let scaled = if tiny[l] { 54 } else { 0 };
        (biased - 1023 - scaled) as f64
    });
    let s: [f64; N] = crate::lanes(|l| (m[l] - 1.0) / (m[l] + 1.0));
    let z: [f64; N] = crate::lanes(|l| s[l] * s[l]);
    let series: [f64; N] = crate::lanes(|l| {
        let z = z[l];
        let mut p = 1.0 / 23.0;
        p = p * z + 1.0 / 21.0;
        p = p * z + 1.0 / 19.0;
        p = p * z + 1.0 / 17.0;
        p = p * z + 1.0 / 15.0;
        p = p * z + 1.0 / 13.0;
        p = p * z + 1.0 / 11.0;
        p = p * z + 1.0 / 9.0;
        p = p * z + 1.0 / 7.0;
        p = p * z + 1.0 / 5.0;
        p = p * z + 1.0 / 3.0;
        p * z
    });
    // ln b = e LN2_HI + (e LN2_LO + 2 s + 2 s z series): the large part exact. Clamped to where
    // the result is 0 or infinity anyway (keeps k and 2^k in range).
    let y: [f64; N] = crate::lanes(|l| {
        let ln_b = e[l] * LN2_HI + (e[l] * LN2_LO + (2.0 * s[l] + 2.0 * s[l] * series[l]));
        (exponent * ln_b).clamp(-746.0, 710.0)
    });
    let rounded: [f64; N] = crate::lanes(|l| y[l] * std::f64::consts::LOG2_E + ROUND);
    let k: [f64; N] = crate::lanes(|l| rounded[l] - ROUND);
    // r = y - k ln 2, ln 2 in two parts (k LN2_HI exact).
    let r: [f64; N] = crate::lanes(|l| y[l] - k[l] * LN2_HI - k[l] * LN2_LO);
    let p: [f64; N] = crate::lanes(|l| {
        let r = r[l];
        let mut p = 1.0 / 87_178_291_200.0; // 1/14!
        p = p * r + 1.0 / 6_227_020_800.0;
        p = p * r + 1.0 / 479_001_600.0;
        p = p * r + 1.0 / 39_916_800.0;
        p = p * r + 1.0 / 3_628_800.0;
        p = p * r + 1.0 / 362_880.0;
        p = p * r + 1.0 / 40_320.0;
        p = p * r + 1.0 / 5_040.0;
        p = p * r + 1.0 / 720.0;
        p = p * r + 1.0 / 120.0;
        p = p * r + 1.0 / 24.0;
        p = p * r + 1.0 / 6.0;
        p = p * r + 0.5;
        p = p * r + 1.0;
        p * r + 1.0
    });
    crate::lanes(|l| {
        let k = rounded[l].to_bits() as i64 - ROUND.to_bits() as i64;
        let half = k >> 1;
        let two_a = f64::from_bits(((half + 1023) as u64) << 52);
        let two_b = f64::from_bits(((k - half + 1023) as u64) << 52);
        let value = p[l] * two_a * two_b;
        if base[l] > 0.0 {
            value
        } else if exponent > 0.0 {
            0.0
        } else if exponent == 0.0 {
            1.0
        } else {
            f64::INFINITY
        }
    })
}

/// The LED anisotropy `t^mu` of a clipped cosine `t >= 0`: [`anisotropy_lanes`] with one lane.
#[inline]
pub(crate) fn anisotropy(t: f64, mu: f64) -> f64 {
    anisotropy_lanes(&[t], mu)[0]
}

/// The LED anisotropy `t^mu` of `N` clipped cosines `t >= 0`: 1 for `mu = 0` (an isotropic
/// point light, whatever `t`), `t` itself for `mu = 1`, else [`power_lanes`].
#[inline(always)]
fn anisotropy_lanes<const N: usize>(t: &[f64; N], mu: f64) -> [f64; N] {
    if mu == 0.0 {
        [1.0; N]
    } else if mu == 1.0 {
        *t
    } else {
        power_lanes(t, mu)
    }
}

/// Whether `light` lights the front of each of `N` facets (centres `c`, normals `n`):
/// `n . beta(c) > 0`, with the values of [`Light::beta`] (`not_above(n . beta, 0)` false). A
/// point light's `beta` in lanes (`lane`, its [`LaneLight`]: the scalar operations in their
/// order per lane, so the same bits), a directional light's (`lane` None) one facet at a time.
/// The cast-shadow marches' facing test and the indirect field's lights behind a facet (its
/// negation) both take it.
#[inline(always)]
pub(crate) fn faced_lanes<const N: usize>(
    light: &Light,
    lane: Option<&LaneLight>,
    c: &[[f64; 3]; N],
    n: &[[f64; 3]; N],
) -> [bool; N] {
    match lane {
        Some(lane) => {
            let (a, f) = lane.beta(c);
            crate::lanes(|l| {
                let b = [a[0][l] * f[l], a[1][l] * f[l], a[2][l] * f[l]];
                !crate::vec3::not_above(dot(n[l], b), 0.0)
            })
        }
        None => crate::lanes(|l| !crate::vec3::not_above(dot(n[l], light.beta(c[l]).0), 0.0)),
    }
}

/// A light in the lane (SIMD) form of the model, which evaluates `beta` at several surface
/// points at once: a point light (isotropic, or an LED of any anisotropy `mu`, its power by
/// [`power_lanes`]), with its grey intensity.
#[derive(Debug, Clone, Copy)]
pub(crate) struct LaneLight {
    position: [f64; 3],
    axis: [f64; 3],
    /// The anisotropy `mu` (0: isotropic).
    mu: f64,
    /// Grey intensity, the mean of the channels ([`channel_intensity`] of one channel).
    pub grey: f64,
}

impl LaneLight {
    /// The lane form of `light`, when it has one: any point light (None for a directional
    /// light).
    pub fn from_light(light: &Light) -> Option<LaneLight> {
        match *light {
            Light::Point {
                position,
                intensity,
                axis,
                mu,
            } => Some(LaneLight {
                position,
                axis,
                mu,
                grey: channel_intensity(intensity, 1, 0),
            }),
            Light::Directional { .. } => None,
        }
    }

    /// For `N` surface points `x`: `a = p - x` and the factor `f` with `beta = a * f` (see
    /// [`Light::beta`]), computed per lane with the operations of the scalar code in its order
    /// (the anisotropy by [`anisotropy_lanes`], whose one lane is the scalar [`anisotropy`]; for
    /// `mu = 0` no cosine is computed: the factor is `1 / |a|^3`). Straight-line code over the lanes, one
    /// operation at a time, so that the compiler turns each line into one vector instruction.
    #[inline(always)]
    pub fn beta<const N: usize>(&self, x: &[[f64; 3]; N]) -> ([[f64; N]; 3], [f64; N]) {
        let [px, py, pz] = self.position;
        let [ax, ay, az] = self.axis;
        let a0: [f64; N] = crate::lanes(|l| px - x[l][0]);
        let a1: [f64; N] = crate::lanes(|l| py - x[l][1]);
        let a2: [f64; N] = crate::lanes(|l| pz - x[l][2]);
        let d2: [f64; N] = crate::lanes(|l| a0[l] * a0[l] + a1[l] * a1[l] + a2[l] * a2[l]);
        let d: [f64; N] = crate::lanes(|l| d2[l].sqrt());
        let d3: [f64; N] = crate::lanes(|l| d2[l] * d[l]);
        let f: [f64; N] = if self.mu == 0.0 {
            crate::lanes(|l| 1.0 / d3[l])
        } else {
            let t: [f64; N] =
                crate::lanes(|l| (-(a0[l] * ax + a1[l] * ay + a2[l] * az) / d[l]).max(0.0));
            let aniso = anisotropy_lanes(&t, self.mu);
            crate::lanes(|l| aniso[l] / d3[l])
        };
        ([a0, a1, a2], f)
    }

    /// The light step's terms of this light at `N` surface points `x` (see [`LaneTerms`]): per
    /// lane the numbers of the scalar [`Light::beta_anisotropy`] and, if `gradient`, of
    /// [`Light::falloff_gradient`] with `t^mu` given, bit for bit (the same operations in the
    /// same order; one power per lane, [`anisotropy_lanes`]). Outside an LED's cone (`t <= 0`,
    /// where the scalar gradient is None) `f` and `grad f` are 0, so that the derivative
    /// `f g + (v . g) grad f` is zero as the scalar one.
    #[allow(clippy::needless_range_loop)] // lane code: one index per lane, as the vector instructions
    #[inline(always)]
    pub fn step_terms<const N: usize>(&self, x: &[[f64; 3]; N], gradient: bool) -> LaneTerms<N> {
        // Loops over the lanes (not `array::from_fn`, whose closures need not be inlined into
        // the caller's SIMD target features).
        let axis = self.axis;
        let mut v = [[0.0; N]; 3];
        for j in 0..3 {
            for l in 0..N {
                v[j][l] = self.position[j] - x[l][j];
            }
        }
        let (mut d2, mut d, mut d3) = ([0.0; N], [0.0; N], [0.0; N]);
        for l in 0..N {
            d2[l] = v[0][l] * v[0][l] + v[1][l] * v[1][l] + v[2][l] * v[2][l];
            d[l] = d2[l].sqrt();
            d3[l] = d2[l] * d[l];
        }
        // v . axis and the clipped cosine t (only an LED needs them).
        let (mut va, mut t) = ([0.0; N], [0.0; N]);
        if self.mu != 0.0 {
            for l in 0..N {
                va[l] = v[0][l] * axis[0] + v[1][l] * axis[1] + v[2][l] * axis[2];
                t[l] = (-va[l] / d[l]).max(0.0);
            }
        }
        let aniso = anisotropy_lanes(&t, self.mu);
        let mut out = LaneTerms {
            beta: [[0.0; N]; 3],
            v,
            f: [0.0; N],
            grad_f: [[0.0; N]; 3],
        };
        let mut fb = [0.0; N];
        for l in 0..N {
            fb[l] = aniso[l] / d3[l];
        }
        for j in 0..3 {
            for l in 0..N {
                out.beta[j][l] = v[j][l] * fb[l];
            }
        }
        if !gradient {
            return out;
        }
        let (mut inv3, mut inv5) = ([0.0; N], [0.0; N]);
        for l in 0..N {
            inv3[l] = 1.0 / (d2[l] * d[l]);
            inv5[l] = inv3[l] / d2[l];
        }
        if self.mu == 0.0 {
            out.f = inv3;
            for j in 0..3 {
                for l in 0..N {
                    out.grad_f[j][l] = -3.0 * v[j][l] * inv5[l];
                }
            }
            return out;
        }
        let mut dm = [0.0; N];
        for l in 0..N {
            let tm1 = aniso[l] / t[l];
            dm[l] = self.mu * tm1 * inv3[l];
            out.f[l] = if t[l] > 0.0 { aniso[l] * inv3[l] } else { 0.0 };
        }
        for j in 0..3 {
            for l in 0..N {
                let dt = -axis[j] / d[l] + va[l] * v[j][l] * inv3[l];
                let g = dm[l] * dt - 3.0 * aniso[l] * v[j][l] * inv5[l];
                out.grad_f[j][l] = if t[l] > 0.0 { g } else { 0.0 };
            }
        }
        out
    }
}

/// A point light's terms in the light step ([`crate::refine`]) at `N` surface points, one lane
/// each ([`LaneLight::step_terms`]): `beta = f_b v` with `v = p - x` and `f_b = t^mu / |v|^3`,
/// and for the position derivative `d(beta . g)/dp = f g + (v . g) grad f` the factor
/// `f = t^mu / |v|^3` (written `t^mu (1 / |v|^3)`, as [`Light::falloff_gradient`]) and its
/// gradient `grad f` with respect to `p` (zero when not asked for).
#[derive(Debug, Clone, Copy)]
pub(crate) struct LaneTerms<const N: usize> {
    /// `beta`, per coordinate.
    pub beta: [[f64; N]; 3],
    /// `v = p - x`, per coordinate.
    pub v: [[f64; N]; 3],
    /// `f` of the position derivative (0 outside an LED's cone).
    pub f: [f64; N],
    /// `grad f` with respect to `p`, per coordinate (0 outside an LED's cone).
    pub grad_f: [[f64; N]; 3],
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vec3::normalize;

    fn led(mu: f64) -> Light {
        Light::Point {
            position: [40.0, 10.0, 5.0],
            intensity: [2.0; 3],
            axis: normalize([-0.3, -0.1, 1.0]),
            mu,
        }
    }

    #[test]
    fn led_beta_follows_the_anisotropic_model() {
        let led = Light::Point {
            position: [0.0, 0.0, 0.0],
            intensity: [1.0; 3],
            axis: [0.0, 0.0, 1.0],
            mu: 2.0,
        };
        // On the axis at distance 2: beta = (p - x) / 8; off axis at 45 degrees the factor is 1/2.
        let (b, w) = led.beta([0.0, 0.0, 2.0]);
        assert!((b[2] + 0.25).abs() < 1e-15 && (w - 8.0).abs() < 1e-12);
        let (b, _) = led.beta([1.0, 0.0, 1.0]);
        let expected = 0.5 / 2f64.powf(1.5);
        assert!((b[0] + expected).abs() < 1e-12);
        // Behind the LED (t < 0) it lights nothing.
        assert_eq!(led.beta([0.0, 0.0, -2.0]).0, [0.0; 3]);
        assert!((led.shading([0.0, 0.0, -1.0], [1.0, 0.0, 1.0]) - expected).abs() < 1e-12);
        assert_eq!(led.shading([0.0, 0.0, 1.0], [1.0, 0.0, 1.0]), 0.0);
    }

    /// Finite-difference check of the position and intensity derivatives, isotropic and LED.
    #[test]
    fn derivatives_match_finite_differences() {
        let c = [3.0, -2.0, 100.0];
        let g = [0.2, -0.1, -0.9];
        for mu in [0.0, 1.0, 2.5] {
            let light = led(mu);
            let pred = |l: &Light| {
                let (b, _) = l.beta(c);
                2.0 * dot(b, g)
            };
            let (b, _) = light.beta(c);
            let a = b.map(|x| 2.0 * x);
            let d = derivatives(
                a,
                g,
                2.0,
                (true, true),
                light.falloff_gradient(c, None).as_ref(),
            );
            assert!((d[0] - pred(&light)).abs() < 1e-15);
            for j in 0..3 {
                let h = 1e-4;
                let mut plus = light;
                let mut minus = light;
                if let (Light::Point { position: p, .. }, Light::Point { position: m, .. }) =
                    (&mut plus, &mut minus)
                {
                    p[j] += h;
                    m[j] -= h;
                }
                let fd = (pred(&plus) - pred(&minus)) / (2.0 * h);
                assert!(
                    (fd - d[1 + j]).abs() < 1e-6 * fd.abs().max(1e-9),
                    "mu {mu} axis {j}: {fd} vs {}",
                    d[1 + j]
                );
            }
        }
    }

    /// With `t^mu` given (from `beta_anisotropy`, bit-identical to `beta`'s), the derivatives
    /// are those computed with the powers, up to rounding; outside the cone both are zero.
    #[test]
    fn derivatives_with_the_anisotropy_given_match() {
        let g = [0.2, -0.1, -0.9];
        for mu in [0.0, 0.5, 1.0, 1.5, 2.0, 2.5] {
            let light = led(mu);
            for c in [[3.0, -2.0, 100.0], [-30.0, 12.0, 60.0], [0.0, 0.0, -100.0]] {
                let (b, aniso) = light.beta_anisotropy(c);
                assert_eq!(b, light.beta(c).0);
                let a = b.map(|x| 2.0 * x);
                let with = light.falloff_gradient(c, Some(aniso));
                let without = light.falloff_gradient(c, None);
                assert_eq!(with.is_some(), without.is_some());
                let with = derivatives(a, g, 2.0, (true, true), with.as_ref());
                let without = derivatives(a, g, 2.0, (true, true), without.as_ref());
                let scale = without.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                for (x, y) in with.iter().zip(&without) {
                    assert!(
                        (x - y).abs() <= 1e-14 * scale,
                        "mu {mu}: {with:?} vs {without:?}"
                    );
                }
            }
        }
        let sun = Light::Directional {
            direction: [0.0, 0.0, -1.0],
            intensity: [1.0; 3],
        };
        assert_eq!(
            sun.beta_anisotropy([1.0, 2.0, 3.0]),
            ([0.0, 0.0, -1.0], 1.0)
        );
    }

    /// The gradient with respect to the surface point, by finite differences; none for a
    /// directional light or outside an LED's cone.
    #[test]
    fn surface_point_gradient_matches_finite_differences() {
        let c = [3.0, -2.0, 100.0];
        let g = [0.2, -0.1, -0.9];
        for mu in [0.0, 1.0, 2.5] {
            let light = led(mu);
            let grad = light.beta_gradient_at(c, g).unwrap();
            for j in 0..3 {
                let h = 1e-4;
                let (mut plus, mut minus) = (c, c);
                plus[j] += h;
                minus[j] -= h;
                let fd = (dot(light.beta(plus).0, g) - dot(light.beta(minus).0, g)) / (2.0 * h);
                assert!(
                    (fd - grad[j]).abs() < 1e-6 * fd.abs().max(1e-9),
                    "mu {mu} axis {j}: {fd} vs {}",
                    grad[j]
                );
            }
        }
        let sun = Light::Directional {
            direction: [0.0, 0.0, -1.0],
            intensity: [1.0; 3],
        };
        assert!(sun.beta_gradient_at(c, g).is_none());
        assert!(sun.falloff_gradient(c, None).is_none());
        assert_eq!(derivatives([0.0; 3], g, 1.0, (false, true), None), [0.0; 4]);
        assert!(led(1.0).beta_gradient([0.0, 0.0, -100.0], g).is_none());
    }

    /// The lane form gives bit for bit the scalar `beta`, for the lights it accepts.
    #[test]
    fn lane_beta_matches_the_scalar_beta_exactly() {
        let x = [
            [3.0, -2.0, 100.0],
            [-7.5, 4.25, 80.0],
            [0.1, 0.2, 30.0],
            [200.0, 0.0, 6.0],
        ];
        for mu in [0.0, 1.0, 2.5, 0.5, 1.7] {
            let light = led(mu);
            let lane = LaneLight::from_light(&light).unwrap();
            assert_eq!(lane.grey, 2.0);
            let (a, f) = lane.beta(&x);
            for l in 0..4 {
                let b = light.beta(x[l]).0;
                assert_eq!(
                    [a[0][l] * f[l], a[1][l] * f[l], a[2][l] * f[l]],
                    b,
                    "mu {mu}"
                );
            }
        }
        let sun = Light::Directional {
            direction: [0.0, 0.0, -1.0],
            intensity: [1.0; 3],
        };
        assert!(LaneLight::from_light(&sun).is_none());
    }

    /// The light step's lane terms give bit for bit the scalar `beta_anisotropy` and the
    /// position derivative of `derivatives` with the anisotropy given, over LEDs of several
    /// `mu` and points inside and outside the cone (where the derivative is zero).
    #[test]
    fn lane_step_terms_match_the_scalar_derivatives_exactly() {
        let x = [
            [3.0, -2.0, 100.0],
            [-7.5, 4.25, 80.0],
            [0.1, 0.2, 30.0],
            [200.0, 0.0, 6.0],
            [0.0, 0.0, -100.0],
            [40.0, 10.0, -3.0],
            [-30.0, 12.0, 60.0],
            [1e-3, -5.0, 1e4],
        ];
        let g = [0.2, -0.1, -0.9];
        for mu in [0.0, 1.0, 2.5, 0.5, 1.7] {
            let light = led(mu);
            let lane = LaneLight::from_light(&light).unwrap();
            let with = lane.step_terms(&x, true);
            let without = lane.step_terms(&x, false);
            for (l, &x) in x.iter().enumerate() {
                let (b, aniso) = light.beta_anisotropy(x);
                let ours = [0, 1, 2].map(|j| with.beta[j][l]);
                assert_eq!(ours, b, "mu {mu} lane {l}");
                assert_eq!([0, 1, 2].map(|j| without.beta[j][l]), b);
                let ours = Gradient {
                    v: [0, 1, 2].map(|j| with.v[j][l]),
                    f: with.f[l],
                    grad_f: [0, 1, 2].map(|j| with.grad_f[j][l]),
                };
                let scalar = light.falloff_gradient(x, Some(aniso));
                if let Some(scalar) = scalar {
                    assert_eq!(ours, scalar, "mu {mu} lane {l}");
                }
                let d = derivatives([0.0; 3], g, 2.0, (false, true), Some(&ours));
                let scalar = derivatives([0.0; 3], g, 2.0, (false, true), scalar.as_ref());
                assert_eq!(d, scalar, "mu {mu} lane {l}");
            }
        }
    }

    #[test]
    fn with_shape_sets_the_led_shape_only() {
        let l = led(0.0).with_shape(1.5, [0.0, 0.0, 1.0]);
        assert_eq!(
            l,
            Light::Point {
                position: [40.0, 10.0, 5.0],
                intensity: [2.0; 3],
                axis: [0.0, 0.0, 1.0],
                mu: 1.5,
            }
        );
        let sun = Light::Directional {
            direction: [0.0, 0.0, -1.0],
            intensity: [1.0; 3],
        };
        assert_eq!(sun.with_shape(2.0, [1.0, 0.0, 0.0]), sun);
    }

    /// The power without libm agrees with libm's (correctly rounded) `powf` within a few units
    /// in the last place over the bases and exponents of LEDs, and its special values are
    /// `powf`'s.
    #[test]
    fn power_matches_libm() {
        let power = |t: f64, mu: f64| power_lanes(&[t], mu)[0];
        // The relative error over (1 + |y|) ulp, y = mu ln t.
        let mut worst = 0.0f64;
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        let mut uniform = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        for _ in 0..200_000 {
            let t = 10f64.powf(-6.0 * uniform());
            let mu = -2.0 + 14.0 * uniform();
            let (ours, libm) = (power(t, mu), t.powf(mu));
            let y = (mu * t.ln()).abs();
            worst = worst.max((ours - libm).abs() / libm / (1.0 + y) / f64::EPSILON);
        }
        eprintln!("power: worst error {worst:.3} (1 + |y|) ulp");
        assert!(worst < 2.0, "worst error {worst:e} (1 + |y|) ulp");
        for mu in [0.5, 1.3, 2.0, 7.25] {
            for t in [
                1.0,
                0.5,
                0.25,
                1e-3,
                0.999_999,
                f64::MIN_POSITIVE,
                1e-310,
                5e-324,
            ] {
                let (ours, libm) = (power(t, mu), t.powf(mu));
                let bound = 2.0 * (1.0 + (mu * t.ln()).abs()) * f64::EPSILON * libm;
                assert!(
                    ours == libm || (ours - libm).abs() <= bound,
                    "{t:e}^{mu}: {ours:e} vs {libm:e}"
                );
            }
        }
        assert_eq!(power(1.0, 3.3), 1.0);
        assert_eq!(power(0.3, 0.0), 1.0);
        assert_eq!(power(0.0, 2.0), 0.0);
        assert_eq!(power(0.0, 0.0), 1.0);
        assert_eq!(power(0.0, -1.0), f64::INFINITY);
        assert_eq!(power(1e-200, 2.0), 0.0);
        assert_eq!(power(1e-200, -2.0), f64::INFINITY);
        let lanes = power_lanes(&[0.2, 0.0, 1.0, 1e-310], 1.5);
        assert_eq!(lanes, [0.2, 0.0, 1.0, 1e-310].map(|t| power(t, 1.5)));
    }
}
