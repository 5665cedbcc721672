//! Interreflections under the glossy model (issue 21, "What to build" item 3): what the rounds
//! of [`Solver::interreflect`](crate::solver) need of the glossy fits, kept apart from the
//! glossy kernel ([`crate::reflectance`]) and the glossy fit ([`super::glossy`]), which do not
//! change.
//!
//! Under the Lambertian model a facet's fit takes the indirect light into its rows,
//! `I = b . (s + V)` (see [`crate::indirect`]), and the observed images are the emitters. Under
//! the glossy model
//!
//! ```text
//! I_k = Phi_k a_k (rho_d D_k(n) + rho_s S_k(n)) + rho_d n . V_k
//! ```
//!
//! (the indirect light received as by a Lambertian surface of albedo `rho_d`), and a round of
//! interreflections from the glossy fits `(n', rho_d', rho_s')` of every facet on the mesh
//! it starts from does two things:
//!
//! - **Emitters** ([`LocalStep::glossy_emitted`]): the field `V` is gathered from the modelled
//!   diffuse part of the images, the observations minus their modelled specular part,
//!   `E_k = I_k - Phi_k a_k rho_s' S_k(n')` (0 where that is negative; the observation as it is
//!   where the light is in a cast shadow or behind the facet, which has no specular part), not
//!   from the observed images with their highlights: a highlight is reflected towards the
//!   camera, not into the rest of the surface as a Lambertian emitter would send it. `E` keeps
//!   the indirect light each facet received (all the bounces, as with the observed images).
//! - **Receivers** ([`LocalStep::glossy_received`]): the glossy fits of the next iterations see
//!   the observations minus the indirect light the fits of the round's start predict,
//!   `I_k - rho_d' n' . V_k` (per channel), a constant per round: no new unknowns, and the
//!   glossy fit is the one without interreflections.
//!
//! What this ignores: the indirect light is received as by a Lambertian surface, without the
//! glossy model's diffuse shape (the transmittances `T(n . l) T(n . v)` of the index `eta`
//! along each incoming direction, and Burley's retro-reflective factor) and without its
//! specular reflection (the glossy reflection of the rest of the surface, e.g. the mirror image
//! of a bright wall in a glazed bowl); the emitters send their diffuse part as Lambertian ones
//! (the glossy model's diffuse shape on the emitting side is ignored too), and their specular
//! part, reflected into the rest of the surface, is missing. An observation that the correction
//! brings to the dark threshold or below is left out (mostly indirect light, which the glossy
//! model cannot explain); one that was unusable (dark, saturated or missing) stays unusable.

use rayon::prelude::*;

use super::{usable, FacetFit, IndirectLight, LocalStep, Observations};
use crate::error::Result;
use crate::geometry::quad_centre;
use crate::light::channel_intensity;
use crate::memory::try_vec;
use crate::reflectance::Lobe;
use crate::vec3::{dot, norm, scale};

/// Facets per chunk of [`LocalStep::glossy_state`] (bounds the full fits held at once).
const CHUNK: usize = 1 << 16;

/// A facet's glossy fit as the rounds use it: normal, diffuse albedo per channel, specular
/// albedo (NaN: no usable fit, the facet's observations are kept as they are).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct GlossyState {
    /// The fitted unit normal.
    pub normal: [f32; 3],
    /// The diffuse albedo per channel.
    pub diffuse: [f32; 3],
    /// The specular albedo.
    pub specular: f32,
}

impl GlossyState {
    /// No usable fit.
    const NONE: GlossyState = GlossyState {
        normal: [f32::NAN; 3],
        diffuse: [f32::NAN; 3],
        specular: f32::NAN,
    };

    /// The state of a fit (none for an invalid one, or one without finite albedos).
    fn of(fit: &FacetFit) -> GlossyState {
        let finite = fit.valid
            && fit.specular.is_finite()
            && fit.albedo.iter().all(|a| a.is_finite())
            && fit.normal.iter().all(|a| a.is_finite());
        match finite {
            true => GlossyState {
                normal: fit.normal.map(|x| x as f32),
                diffuse: fit.albedo.map(|x| x as f32),
                specular: fit.specular as f32,
            },
            false => GlossyState::NONE,
        }
    }

    /// Whether the facet has a usable fit.
    fn is_some(&self) -> bool {
        self.specular.is_finite()
    }

    fn normal(&self) -> [f64; 3] {
        self.normal.map(f64::from)
    }
}

impl LocalStep<'_> {
    /// The glossy fits of every facet on `u` (this step's observations, warm start and
    /// settings; the step must have a lobe), a chunk of [`CHUNK`] facets at a time.
    pub(crate) fn glossy_state(&self, u: &[f64]) -> Result<Vec<GlossyState>> {
        debug_assert!(self.settings.lobe.is_some());
        let n = self.grid.n_facets();
        let mut state = try_vec(n, GlossyState::NONE, "the glossy fits of the rounds")?;
        let mut fits = try_vec(
            n.min(CHUNK),
            FacetFit::EMPTY,
            "the glossy fits of the rounds",
        )?;
        for first in (0..n).step_by(CHUNK) {
            let len = (n - first).min(CHUNK);
            self.try_run(u, first, &mut fits[..len])?;
            for (s, fit) in state[first..first + len].iter_mut().zip(&fits) {
                *s = GlossyState::of(fit);
            }
        }
        Ok(state)
    }

    /// The emitters of a round under the glossy model (see the module documentation): the
    /// observations `raw` (the problem's, (k, H, W, C)) minus the specular part that the fits
    /// `state` (one per facet, see [`LocalStep::glossy_state`]) model under `lobe` on the mesh
    /// `u`, clamped at 0; the observation as it is where the light is in one of this step's
    /// cast shadows or gives no specular part, and at the facets without a fit. Pixels
    /// outside the mesh are NaN (they emit nothing).
    pub(crate) fn glossy_emitted(
        &self,
        u: &[f64],
        raw: &Observations<'_>,
        state: &[GlossyState],
        lobe: &Lobe,
    ) -> Result<Vec<f32>> {
        let channels = raw.channels;
        self.restack(raw, |f, pixel, values| {
            let s = state[f];
            if !s.is_some() || s.specular == 0.0 {
                return;
            }
            let c = quad_centre(&self.corners(f, u));
            let v = self.geometry.view(c);
            let n = s.normal();
            let mut shadowed = vec![false; raw.k];
            if let Some(shadows) = self.shadows {
                for k in shadows.lights_at(pixel) {
                    shadowed[k] = true;
                }
            }
            for (k, o) in values.chunks_exact_mut(channels).enumerate() {
                if shadowed[k] {
                    continue;
                }
                let (b, _, phi) = self.model.row(k, c);
                let a = norm(b);
                if !(a > 0.0 && a.is_finite()) {
                    continue;
                }
                let Some(sh) = lobe.shade(n, scale(b, 1.0 / a), v) else {
                    continue;
                };
                for (ch, i) in o.iter_mut().enumerate() {
                    let specular = channel_intensity(phi, channels, ch) * a * sh.specular;
                    let e = f64::from(*i) - f64::from(s.specular) * specular;
                    // (NaN stays NaN: a missing observation emits nothing)
                    *i = if e < 0.0 { 0.0 } else { e as f32 };
                }
            }
        })
    }

    /// The observations the glossy fits of a round see (see the module documentation): `raw`
    /// (the problem's, (k, H, W, C)) minus the indirect light `rho_d n . V` of the field
    /// `field` received by the fits `state` (one per facet, see [`LocalStep::glossy_state`]).
    /// Observations unusable in `raw` (under this step's settings) are NaN, so that the
    /// correction cannot make a saturated one usable; facets without a fit keep theirs as they
    /// are. Pixels outside the mesh are NaN.
    pub(crate) fn glossy_received(
        &self,
        raw: &Observations<'_>,
        state: &[GlossyState],
        field: &dyn IndirectLight,
    ) -> Result<Vec<f32>> {
        let (channels, width) = (raw.channels, self.grid.width);
        self.restack(raw, |f, pixel, values| {
            let s = state[f];
            let mut vectors = Vec::new();
            if s.is_some() {
                field.at_into(pixel, width, &mut vectors);
            }
            let n = s.normal();
            for (k, o) in values.chunks_exact_mut(channels).enumerate() {
                if !usable(o, &self.settings) {
                    o.fill(f32::NAN);
                    continue;
                }
                if !s.is_some() {
                    continue;
                }
                for (ch, i) in o.iter_mut().enumerate() {
                    let received = f64::from(s.diffuse[ch]) * dot(n, vectors[k * channels + ch]);
                    *i = (f64::from(*i) - received) as f32;
                }
            }
        })
    }

    /// A (k, H, W, C) stack from the observations `raw` of every facet, each facet's
    /// `k * C` values (light-major) changed by `change(facet, pixel, values)` (in parallel);
    /// NaN at the pixels outside the mesh.
    fn restack(
        &self,
        raw: &Observations<'_>,
        change: impl Fn(usize, usize, &mut [f32]) + Sync,
    ) -> Result<Vec<f32>> {
        let (k, channels, per) = (raw.k, raw.channels, raw.per_facet());
        let plane = self.grid.height * self.grid.width;
        let n = self.grid.n_facets();
        let mut stack = try_vec(k * plane * channels, f32::NAN, "the rounds' observations")?;
        let mut facets = try_vec(n.min(CHUNK) * per, 0.0f32, "the rounds' observations")?;
        for first in (0..n).step_by(CHUNK) {
            let len = (n - first).min(CHUNK);
            facets[..len * per]
                .par_chunks_mut(per)
                .enumerate()
                .for_each(|(i, values)| {
                    let f = first + i;
                    let pixel = self.grid.facets[f] as usize;
                    raw.facet(pixel, values);
                    change(f, pixel, values);
                });
            for (i, values) in facets[..len * per].chunks_exact(per).enumerate() {
                let pixel = self.grid.facets[first + i] as usize;
                for (light, o) in values.chunks_exact(channels).enumerate() {
                    let at = (light * plane + pixel) * channels;
                    stack[at..at + channels].copy_from_slice(o);
                }
            }
        }
        Ok(stack)
    }
}
