//! The vectorized local step: the grey, unit-weight normal equations and residuals of
//! [`LANES`] facets at once, one SIMD lane per facet, with the lane form of the light model
//! (`LaneLight`). Per lane the sums are those of the scalar code (`Facet::accumulate_grey`,
//! `Facet::sq_residual`), the same operations in the same order, so the fits agree bit for bit.
//! The kernels run compiled for AVX-512 (8 f64 lanes in one register) or AVX2 when the processor
//! has it (`simd_dispatch!`, its `wide` form): the same operations per lane, so the same bits.

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use super::trust::{add_sums, trust_values, LightSums, CHUNK};
use super::{
    facet_scratch, invert_spd3, keep_shape, solve_sums, u16_value, usable_count, FacetFit,
    LocalStep, Model, Observations, Robust, Stored, Sums, Weighting, SCRATCH,
};
use crate::error::Result;
use crate::geometry::quad_centre;
use crate::light::LaneLight;
use crate::memory::try_vec;
use crate::reflectance::Packed;
use crate::vec3::dot;

impl Observations<'_> {
    /// For grey observations: the values of the facets at `pixels`, light-major and
    /// interleaved (`out[k][lane]`); returns false (and writes nothing) for colour.
    #[inline]
    pub(crate) fn gather_lanes<const N: usize>(
        &self,
        pixels: &[usize; N],
        out: &mut [[f32; N]],
    ) -> bool {
        if self.channels != 1 {
            return false;
        }
        match &self.data {
            Stored::F32(d) => gather_interleaved(&d[..], self.k, self.plane, pixels, out, |v| v),
            Stored::U16(d) => gather_interleaved(d, self.k, self.plane, pixels, out, u16_value),
        }
        true
    }
}

/// `out[k][lane] = value(data[k * plane + pixels[lane]])` for the `k` lights, prefetching each
/// image ahead of the last pixel.
#[inline(always)]
fn gather_interleaved<T: Copy, const N: usize>(
    data: &[T],
    k: usize,
    plane: usize,
    pixels: &[usize; N],
    out: &mut [[f32; N]],
    value: impl Fn(T) -> f32,
) {
    // The facets of a batch are usually neighbours in one image row: then each light's values
    // are one contiguous run of N samples, read (and converted) as a block.
    let first = pixels[0];
    if (1..N).all(|l| pixels[l] == first + l) {
        for (i, slot) in out[..k].iter_mut().enumerate() {
            let base = i * plane + first;
            let run: &[T; N] = data[base..base + N].try_into().expect("a run of N samples");
            *slot = run.map(&value);
            prefetch(data, base + N - 1 + PREFETCH_AHEAD);
        }
        return;
    }
    for (i, slot) in out[..k].iter_mut().enumerate() {
        let base = i * plane;
        for (v, &p) in slot.iter_mut().zip(pixels) {
            *v = value(data[base + p]);
        }
        prefetch(data, base + pixels[N - 1] + PREFETCH_AHEAD);
    }
}

/// A thread's scratch space of the vectorized accumulation: one facet's `per` observations and
/// the `k` lights' observations of [`LANES`] facets interleaved.
pub(super) fn lane_scratch(per: usize, k: usize) -> Result<(Vec<f32>, Vec<[f32; LANES]>)> {
    Ok((facet_scratch(per)?.0, try_vec(k, [0.0f32; LANES], SCRATCH)?))
}

/// How far ahead (in pixels) the gather of observations prefetches each image: the local step
/// reads the k images as k streams, more than the hardware prefetchers follow.
const PREFETCH_AHEAD: usize = 512;

/// Hints the processor to load `data[i]` into the cache (nothing when `i` is out of range or
/// on other architectures).
#[inline(always)]
fn prefetch<T>(data: &[T], i: usize) {
    #[cfg(target_arch = "x86_64")]
    if i < data.len() {
        // SAFETY: the address lies inside `data`; a prefetch never faults and changes no state
        // visible to the program.
        unsafe {
            use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
            _mm_prefetch::<_MM_HINT_T0>(data.as_ptr().add(i).cast());
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (data, i);
}

/// Facets whose normal equations are accumulated together (one SIMD lane each).
pub(super) const LANES: usize = 8;

impl LocalStep<'_> {
    /// The lights of the vectorized accumulation, when it applies: grey images, unit weights,
    /// no robust fit, and only lights with a lane form ([`LaneLight::from_light`]: isotropic
    /// point lights or LEDs with `mu = 1`). It computes the same sums in the same order as
    /// [`Facet::accumulate_grey`](super::Facet::accumulate_grey).
    pub(super) fn lane_lights(&self) -> Option<Vec<LaneLight>> {
        let s = self.settings;
        let eligible = self.obs.channels == 1
            && s.weighting == Weighting::Image
            && s.robust == Robust::None
            && s.lobe.is_none()
            && self.indirect.is_none();
        let Model::Near(lights) = self.model else {
            return None;
        };
        if !eligible {
            return None;
        }
        lights.iter().map(LaneLight::from_light).collect()
    }

    /// Fits facets `first..first + LANES` with the vectorized accumulation.
    pub(super) fn fit_lanes(
        &self,
        lights: &[LaneLight],
        first: usize,
        u: &[f64],
        buf: &mut [f32],
        interleaved: &mut [[f32; LANES]],
        trust: Option<LaneTrust<'_>>,
    ) -> [FacetFit; LANES] {
        let (grid, geometry, obs) = (self.grid, self.geometry, self.obs);
        let pixels: [usize; LANES] = std::array::from_fn(|l| grid.facets[first + l] as usize);
        let batch = self.batch_corners(first, &pixels, u);
        let quads = &batch.quads;
        let centres: [[f64; 3]; LANES] = std::array::from_fn(|l| quad_centre(&quads[l]));
        if !obs.gather_lanes(&pixels, interleaved) {
            for l in 0..LANES {
                let f = first + l;
                let values = obs.facet(grid.facets[f] as usize, buf);
                for (slot, &v) in interleaved.iter_mut().zip(values) {
                    slot[l] = v;
                }
            }
        }
        if let Some(shadows) = self.shadows {
            // One channel: light k is row k of the interleaved values.
            for (l, &pixel) in pixels.iter().enumerate() {
                for k in shadows.lights_at(pixel) {
                    interleaved[k][l] = f32::NAN;
                }
            }
        }
        let thresholds = (self.settings.dark, self.settings.saturation);
        let mut trust = trust;
        let sums = accumulate_lanes_dispatch(
            lights,
            &centres,
            interleaved,
            thresholds,
            trust.as_mut().map(|t| &mut t.rows[..]),
        );
        let mut fitted: [Option<FacetFit>; LANES] = std::array::from_fn(|l| grey_fit(&sums[l]));
        if let Some(trust) = trust {
            // One pass over the stored rows for the exact residuals and the trust values.
            let normals = fitted.map(|f| f.map_or([0.0; 3], |f| f.normal));
            let albedo = fitted.map(|f| f.map_or(0.0, |f| f.albedo[0]));
            let fits = LaneFits { normals, albedo };
            let solved = LaneSolved::new(&sums);
            let out = final_residuals_dispatch(
                lights,
                trust.rows,
                interleaved,
                thresholds,
                &fits,
                &solved,
                trust.sums,
            );
            for l in 0..LANES {
                if let (false, Some(fit)) = (self.settings.fast_residual, &mut fitted[l]) {
                    fit.sse = out[0][l];
                }
                trust.out[l] = match solved.active[l] {
                    true => trust_values(
                        &[out[1][l], 0.0, 0.0],
                        &[solved.inverse(l), Matrix3::zeros(), Matrix3::zeros()],
                        Vector3::zeros() + Vector3::from(solved.g[l]),
                        sums[l].used as usize,
                        1,
                        out[2][l],
                        out[3][l] as usize,
                    ),
                    false => [f32::NAN; 2],
                };
            }
        } else if !self.settings.fast_residual {
            // The exact residual, a second pass over the lights (as the scalar code does).
            let normals = fitted.map(|f| f.map_or([0.0; 3], |f| f.normal));
            let albedo = fitted.map(|f| f.map_or(0.0, |f| f.albedo[0]));
            let sse = residual_lanes_dispatch(
                lights,
                &centres,
                interleaved,
                (self.settings.dark, self.settings.saturation),
                &normals,
                &albedo,
            );
            for (fit, sse) in fitted.iter_mut().zip(sse) {
                if let Some(fit) = fit {
                    fit.sse = sse;
                }
            }
        }
        std::array::from_fn(|l| {
            let f = first + l;
            let ids = batch.ids[l];
            match fitted[l] {
                Some(fitted) => FacetFit {
                    target: geometry.plane_target_at(batch.base[l], fitted.normal, centres[l]),
                    ..fitted
                },
                None => {
                    let values = self.facet_values(f, buf);
                    keep_shape(
                        &quads[l],
                        ids.map(|i| u[i as usize]),
                        usable_count(values, 1, self.settings),
                    )
                }
            }
        })
    }
}

/// The corners of [`LANES`] facets: their unknowns (as [`Grid::facet_vertices`]), the
/// [`Geometry::base`] of each corner and the corner positions (as [`LocalStep::corners`]).
///
/// [`Grid::facet_vertices`]: crate::grid::Grid::facet_vertices
/// [`Geometry::base`]: crate::geometry::Geometry::base
struct BatchCorners {
    ids: [[u32; 4]; LANES],
    base: [[[f64; 2]; 4]; LANES],
    quads: [[[f64; 3]; 4]; LANES],
}

impl LocalStep<'_> {
    /// The depth of unknown `i` (as [`LocalStep::corners`] finds it).
    #[inline(always)]
    fn depth_of(&self, i: u32, u: &[f64]) -> f64 {
        let i = i as usize;
        match self.depths {
            Some(z) => z[i],
            None => self.geometry.depth(u[i]),
        }
    }

    /// The corners of facets `first..first + LANES` (at pixels `pixels`). When the facets are
    /// [`LANES`] neighbours in one image row (the usual case), their corners are the
    /// `LANES + 1` vertices of two grid rows: each is looked up and placed once, with one
    /// division for the batch instead of one per corner and facet; the same values.
    #[inline(always)]
    fn batch_corners(&self, first: usize, pixels: &[usize; LANES], u: &[f64]) -> BatchCorners {
        let (grid, geometry) = (self.grid, self.geometry);
        let (w, p0) = (grid.width, pixels[0]);
        let (row, col) = (p0 / w, p0 % w);
        if col + LANES <= w && (1..LANES).all(|l| pixels[l] == p0 + l) {
            let vw = w + 1;
            let v0 = row * vw + col;
            let line = |r: usize, v: usize| -> ([u32; LANES + 1], [[f64; 2]; LANES + 1]) {
                let ids: [u32; LANES + 1] = std::array::from_fn(|j| grid.vertex_unknown[v + j]);
                let base = std::array::from_fn(|j| {
                    geometry.base_at_vertex(ids[j] as usize, r, col + j)
                });
                (ids, base)
            };
            let (top, top_base) = line(row, v0);
            let (bottom, bottom_base) = line(row + 1, v0 + vw);
            let place = |ids: &[u32; LANES + 1], base: &[[f64; 2]; LANES + 1]| {
                let z: [f64; LANES + 1] = std::array::from_fn(|j| self.depth_of(ids[j], u));
                let p: [[f64; 3]; LANES + 1] =
                    std::array::from_fn(|j| geometry.position_from_base(base[j], z[j]));
                p
            };
            let (tp, bp) = (place(&top, &top_base), place(&bottom, &bottom_base));
            return BatchCorners {
                ids: std::array::from_fn(|l| [top[l], top[l + 1], bottom[l], bottom[l + 1]]),
                base: std::array::from_fn(|l| {
                    [top_base[l], top_base[l + 1], bottom_base[l], bottom_base[l + 1]]
                }),
                quads: std::array::from_fn(|l| [tp[l], tp[l + 1], bp[l], bp[l + 1]]),
            };
        }
        let ids: [[u32; 4]; LANES] = std::array::from_fn(|l| grid.facet_vertices(first + l));
        let base: [[[f64; 2]; 4]; LANES] =
            std::array::from_fn(|l| ids[l].map(|i| geometry.base(i as usize)));
        let quads = std::array::from_fn(|l| {
            let (ids, base) = (&ids[l], &base[l]);
            let at = |j: usize| geometry.position_from_base(base[j], self.depth_of(ids[j], u));
            [at(0), at(1), at(2), at(3)]
        });
        BatchCorners { ids, base, quads }
    }
}

/// The fit of grey, unit-weight, plain sums with the residual from the normal equations (as
/// [`fit_facet`](super::fit_facet) computes it for those settings); the target is left at zero.
#[inline(always)]
fn grey_fit(sums: &Sums) -> Option<FacetFit> {
    if sums.used < 3 {
        return None;
    }
    let (normal, albedo, g) = solve_sums(sums, 1)?;
    Some(FacetFit {
        target: [0.0; 4],
        normal,
        albedo,
        specular: 0.0,
        sse: (sums.sum_i2 - dot(g, sums.s[0])).max(0.0),
        used: sums.used,
        valid: true,
    })
}

simd_dispatch! {
    wide
    /// [`accumulate_lanes`] with AVX-512 or AVX2 when the processor has it (same arithmetic, wider
    /// registers).
    fn accumulate_lanes_dispatch => accumulate_lanes(
        lights: &[LaneLight],
        centres: &[[f64; 3]; LANES],
        values: &[[f32; LANES]],
        thresholds: (f64, f64),
        rows: Option<&mut [[[f64; LANES]; 3]]>,
    ) -> [Sums; LANES];
}

/// The observations of one light in [`LANES`] facets as f64, and whether each is usable
/// (strictly between `dark` and `saturation`, not NaN).
#[inline(always)]
fn lane_values(v: &[f32; LANES], dark: f64, saturation: f64) -> ([f64; LANES], [bool; LANES]) {
    let i: [f64; LANES] = std::array::from_fn(|l| v[l] as f64);
    let ok: [bool; LANES] = std::array::from_fn(|l| i[l] > dark && i[l] < saturation);
    (i, ok)
}

/// The grey unit-weight normal equations of [`LANES`] facets at once (`values[k][lane]`): per
/// lane the same operations in the same order as
/// [`Facet::accumulate_grey`](super::Facet::accumulate_grey), written so that the compiler keeps
/// the lanes in SIMD registers. With `rows`, each light's `beta` of the lanes is stored in its
/// row (for [`final_residuals`]).
#[inline(always)]
fn accumulate_lanes(
    lights: &[LaneLight],
    centres: &[[f64; 3]; LANES],
    values: &[[f32; LANES]],
    (dark, saturation): (f64, f64),
    mut rows: Option<&mut [[[f64; LANES]; 3]]>,
) -> [Sums; LANES] {
    let mut t = [[0.0f64; LANES]; 6];
    let mut s = [[0.0f64; LANES]; 3];
    let mut sum_i2 = [0.0f64; LANES];
    let mut used = [0u32; LANES];
    for (k, (light, v)) in lights.iter().zip(values).enumerate() {
        let p = light.grey;
        let (i, ok) = lane_values(v, dark, saturation);
        let ([a0, a1, a2], f) = light.beta(centres);
        let b0: [f64; LANES] = std::array::from_fn(|l| a0[l] * f[l]);
        let b1: [f64; LANES] = std::array::from_fn(|l| a1[l] * f[l]);
        let b2: [f64; LANES] = std::array::from_fn(|l| a2[l] * f[l]);
        if let Some(rows) = rows.as_mut() {
            rows[k] = [b0, b1, b2];
        }
        let r0: [f64; LANES] = std::array::from_fn(|l| b0[l] * p);
        let r1: [f64; LANES] = std::array::from_fn(|l| b1[l] * p);
        let r2: [f64; LANES] = std::array::from_fn(|l| b2[l] * p);
        let pick = |l: usize, x: f64| if ok[l] { x } else { 0.0 };
        for l in 0..LANES {
            t[0][l] += pick(l, r0[l] * r0[l]);
            t[1][l] += pick(l, r0[l] * r1[l]);
            t[2][l] += pick(l, r0[l] * r2[l]);
            t[3][l] += pick(l, r1[l] * r1[l]);
            t[4][l] += pick(l, r1[l] * r2[l]);
            t[5][l] += pick(l, r2[l] * r2[l]);
            s[0][l] += pick(l, r0[l] * i[l]);
            s[1][l] += pick(l, r1[l] * i[l]);
            s[2][l] += pick(l, r2[l] * i[l]);
            sum_i2[l] += pick(l, i[l] * i[l]);
            used[l] += u32::from(ok[l]);
        }
    }
    std::array::from_fn(|l| Sums {
        t: [
            [t[0][l], t[1][l], t[2][l], t[3][l], t[4][l], t[5][l]],
            [0.0; 6],
            [0.0; 6],
        ],
        s: [[s[0][l], s[1][l], s[2][l]], [0.0; 3], [0.0; 3]],
        sum_i2: sum_i2[l],
        used: used[l],
        // The lanes run without indirect light: every used observation is lit.
        lit: used[l],
    })
}

simd_dispatch! {
    wide
    /// [`residual_lanes`] with AVX-512 or AVX2 when the processor has it (same arithmetic, wider
    /// registers).
    fn residual_lanes_dispatch => residual_lanes(
        lights: &[LaneLight],
        centres: &[[f64; 3]; LANES],
        values: &[[f32; LANES]],
        thresholds: (f64, f64),
        normals: &[[f64; 3]; LANES],
        albedo: &[f64; LANES],
    ) -> [f64; LANES];
}

/// The summed squared image residuals of [`LANES`] grey fits `(normals, albedo)` over their
/// usable observations: per lane the operations of
/// [`Facet::sq_residual`](super::Facet::sq_residual), in its order.
#[inline(always)]
fn residual_lanes(
    lights: &[LaneLight],
    centres: &[[f64; 3]; LANES],
    values: &[[f32; LANES]],
    (dark, saturation): (f64, f64),
    normals: &[[f64; 3]; LANES],
    albedo: &[f64; LANES],
) -> [f64; LANES] {
    let mut sse = [0.0f64; LANES];
    for (light, v) in lights.iter().zip(values) {
        let p = light.grey;
        let (i, ok) = lane_values(v, dark, saturation);
        let ([a0, a1, a2], f) = light.beta(centres);
        let nb: [f64; LANES] = std::array::from_fn(|l| {
            let n = normals[l];
            n[0] * (a0[l] * f[l]) + n[1] * (a1[l] * f[l]) + n[2] * (a2[l] * f[l])
        });
        for l in 0..LANES {
            let e = albedo[l] * p * nb[l] - i[l];
            sse[l] += if ok[l] { e * e } else { 0.0 };
        }
    }
    sse
}

/// The trust part of a final pass over [`LANES`] facets (see [`LocalStep::final_lanes`]): scratch
/// rows (`beta` of each light, per lane), the facets' `[normal sigma, held-out]` and the
/// per-light sums they add to.
pub(super) struct LaneTrust<'a> {
    rows: &'a mut [[[f64; LANES]; 3]],
    out: &'a mut [[f32; 2]],
    sums: &'a mut [[f64; 4]],
}

/// The grey fits of [`LANES`] facets: unit normals and albedo (0 where a fit failed).
struct LaneFits {
    normals: [[f64; 3]; LANES],
    albedo: [f64; LANES],
}

/// The trust's solution of [`LANES`] facets' normal equations (see the `trust` module):
/// `T^-1` (row-major), `g = T^-1 s`, and whether the facet has a trust value (at least 4 usable
/// lights, `T` regular).
struct LaneSolved {
    inverse: [[[f64; 3]; 3]; LANES],
    g: [[f64; 3]; LANES],
    active: [bool; LANES],
}

impl LaneSolved {
    /// From the sums, with the operations of `LocalStep::facet_trust`.
    fn new(sums: &[Sums; LANES]) -> LaneSolved {
        let mut solved = LaneSolved {
            inverse: [[[0.0; 3]; 3]; LANES],
            g: [[0.0; 3]; LANES],
            active: [false; LANES],
        };
        for (l, sums) in sums.iter().enumerate() {
            if sums.used < 4 {
                continue;
            }
            let t = &sums.t[0];
            let tm = Matrix3::new(t[0], t[1], t[2], t[1], t[3], t[4], t[2], t[4], t[5]);
            let Some(inv) = invert_spd3(&tm) else {
                continue;
            };
            let g = inv * Vector3::from(sums.s[0]);
            solved.inverse[l] = std::array::from_fn(|i| std::array::from_fn(|j| inv[(i, j)]));
            solved.g[l] = [g.x, g.y, g.z];
            solved.active[l] = true;
        }
        solved
    }

    /// `T^-1` of lane `l`.
    fn inverse(&self, l: usize) -> Matrix3<f64> {
        let m = &self.inverse[l];
        Matrix3::new(
            m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2], m[2][0], m[2][1], m[2][2],
        )
    }
}

simd_dispatch! {
    wide
    /// [`final_residuals`] with AVX-512 or AVX2 when the processor has it (same arithmetic, wider
    /// registers).
    fn final_residuals_dispatch => final_residuals(
        lights: &[LaneLight],
        rows: &[[[f64; LANES]; 3]],
        values: &[[f32; LANES]],
        thresholds: (f64, f64),
        fits: &LaneFits,
        solved: &LaneSolved,
        sums: &mut [[f64; 4]],
    ) -> [[f64; LANES]; 4];
}

/// One pass over the lights of [`LANES`] facets, their rows `beta` stored by
/// [`accumulate_lanes`]: the exact squared residuals of the fits `fits` (the operations of
/// [`residual_lanes`]), and for the facets with a trust value (`solved`) the trust's residual
/// `e = I - r . g`, leverage `h = r . T^-1 r` and leave-one-out residual `e / (1 - h)` (the
/// operations of `LocalStep::facet_trust`, in its order), adding each light's to `sums` facet
/// after facet. Returns per lane the fit's squared residual, the trust's, the sum of the finite
/// `|e / (1 - h)|` and their count.
#[inline(always)]
fn final_residuals(
    lights: &[LaneLight],
    rows: &[[[f64; LANES]; 3]],
    values: &[[f32; LANES]],
    (dark, saturation): (f64, f64),
    fits: &LaneFits,
    solved: &LaneSolved,
    sums: &mut [[f64; 4]],
) -> [[f64; LANES]; 4] {
    let mut sse = [0.0f64; LANES];
    let mut trust_sse = [0.0f64; LANES];
    let mut loo_sum = [0.0f64; LANES];
    let mut loo_count = [0.0f64; LANES];
    let (inv, g) = (&solved.inverse, &solved.g);
    for (((light, v), row), sum) in lights.iter().zip(values).zip(rows).zip(sums) {
        let p = light.grey;
        let (i, ok) = lane_values(v, dark, saturation);
        let [b0, b1, b2] = *row;
        let nb: [f64; LANES] = std::array::from_fn(|l| {
            let n = fits.normals[l];
            n[0] * b0[l] + n[1] * b1[l] + n[2] * b2[l]
        });
        for l in 0..LANES {
            let e = fits.albedo[l] * p * nb[l] - i[l];
            sse[l] += if ok[l] { e * e } else { 0.0 };
        }
        let r0: [f64; LANES] = std::array::from_fn(|l| b0[l] * p);
        let r1: [f64; LANES] = std::array::from_fn(|l| b1[l] * p);
        let r2: [f64; LANES] = std::array::from_fn(|l| b2[l] * p);
        let e: [f64; LANES] =
            std::array::from_fn(|l| i[l] - (r0[l] * g[l][0] + r1[l] * g[l][1] + r2[l] * g[l][2]));
        let ir: [[f64; LANES]; 3] = std::array::from_fn(|j| {
            std::array::from_fn(|l| {
                let m = inv[l][j];
                m[0] * r0[l] + m[1] * r1[l] + m[2] * r2[l]
            })
        });
        let h: [f64; LANES] =
            std::array::from_fn(|l| r0[l] * ir[0][l] + r1[l] * ir[1][l] + r2[l] * ir[2][l]);
        let loo: [f64; LANES] = std::array::from_fn(|l| e[l] / (1.0 - h[l]));
        for l in 0..LANES {
            if !(ok[l] && solved.active[l]) {
                continue;
            }
            trust_sse[l] += e[l] * e[l];
            if loo[l].is_finite() {
                loo_sum[l] += loo[l].abs();
                loo_count[l] += 1.0;
                sum[1] += loo[l] * loo[l];
            }
            sum[0] += e[l] * e[l];
            sum[2] += i[l];
            sum[3] += 1.0;
        }
    }
    [sse, trust_sse, loo_sum, loo_count]
}

impl LocalStep<'_> {
    /// [`LocalStep::try_run_final`] with the vectorized accumulation (`lights` from
    /// [`LocalStep::lane_lights`]): each batch of [`LANES`] facets is fitted and its trust values
    /// computed from one evaluation of the lights' `beta`, with the fits of
    /// [`LocalStep::try_run`] and the trust values of the `trust` module (same operations, same
    /// order). Returns the per-light sums.
    pub(super) fn final_lanes(
        &self,
        lights: &[LaneLight],
        u: &[f64],
        first: usize,
        fits: &mut [FacetFit],
        trust: &mut [[f32; 2]],
    ) -> Result<LightSums> {
        let (per, k) = (self.obs.per_facet(), self.obs.k);
        let scratch = || -> Result<_> {
            let (buf, interleaved) = lane_scratch(per, k)?;
            let rows = try_vec(k, [[0.0f64; LANES]; 3], SCRATCH)?;
            let trust_rows = try_vec(per, [0.0f64; 4], SCRATCH)?;
            Ok((buf, interleaved, rows, trust_rows))
        };
        fits.par_chunks_mut(CHUNK)
            .zip(trust.par_chunks_mut(CHUNK))
            .enumerate()
            .map_init(scratch, |scratch, (chunk, (fits, trust))| {
                let (buf, interleaved, rows, trust_rows) =
                    scratch.as_mut().map_err(|e| e.clone())?;
                let mut sums = vec![[0.0f64; 4]; k];
                let start = first + chunk * CHUNK;
                let batches = fits.chunks_mut(LANES).zip(trust.chunks_mut(LANES));
                for (b, (fits, out)) in batches.enumerate() {
                    if self.cancel.is_cancelled() {
                        break;
                    }
                    let at = start + b * LANES;
                    if fits.len() == LANES {
                        let lane_trust = LaneTrust {
                            rows,
                            out,
                            sums: &mut sums,
                        };
                        let lanes =
                            self.fit_lanes(lights, at, u, buf, interleaved, Some(lane_trust));
                        fits.copy_from_slice(&lanes);
                    } else {
                        for (i, (fit, out)) in fits.iter_mut().zip(out).enumerate() {
                            *fit = self.fit(at + i, u, buf, &mut Packed::new(), None);
                            *out = self.facet_trust(at + i, u, buf, trust_rows, &mut sums);
                        }
                    }
                }
                Ok(sums)
            })
            .try_reduce(|| vec![[0.0; 4]; k], |a, b| Ok(add_sums(a, b)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Geometry;
    use crate::grid::Grid;
    use crate::light::Light;
    use crate::local::{FacetStat, FitSettings, TrustMaps};
    use crate::reflectance::Packed;
    use crate::vec3::normalize;

    /// On full rows (batches of neighbours in one image row, whose corners
    /// `LocalStep::batch_corners` takes from two grid rows, and batches across a row end),
    /// pinhole and orthographic, with and without precomputed depths, and a mask with a hole:
    /// the fits of the lanes are those of the scalar code bit for bit.
    #[test]
    fn lanes_on_full_rows_match_the_scalar_fits_exactly() {
        use crate::rig::Camera;
        let (h, w) = (5, 19);
        let cameras = [
            Camera::Pinhole {
                k: [[60.0, 0.0, 9.0], [0.0, 55.0, 2.0], [0.0, 0.0, 1.0]],
                distortion: [0.0; 5],
            },
            Camera::Pinhole {
                k: [[60.0, 0.5, 9.0], [0.0, 55.0, 2.0], [0.0, 0.0, 1.0]],
                distortion: [0.01, 0.0, 0.0, 0.0, 0.0],
            },
            Camera::Orthographic {
                pixel_size: [1.5, 1.5],
                origin: [-5.0, -7.0],
            },
        ];
        let hole: Vec<bool> = (0..h * w).map(|p| p != 2 * w + 12).collect();
        let lights = crate::local::tests::lights();
        let k = lights.len();
        let data: Vec<f32> = (0..k * h * w)
            .map(|i| 1e-4 * (1.0 + ((i * 31) % 13) as f32))
            .collect();
        let obs = Observations::from_stack(&data, k, h * w, 1);
        let mut fast_batches = 0;
        for camera in &cameras {
            for mask in [None, Some(&hole[..])] {
                let grid = Grid::new(h, w, mask).unwrap();
                let geometry = Geometry::new(camera, &grid).unwrap();
                let u: Vec<f64> = (0..grid.n_unknowns())
                    .map(|i| geometry.unknown(100.0 + 0.3 * (i % 8) as f64 - 0.02 * i as f64))
                    .collect();
                let z: Vec<f64> = u.iter().map(|&x| geometry.depth(x)).collect();
                for depths in [None, Some(&z[..])] {
                    let step = LocalStep {
                        grid: &grid,
                        geometry: &geometry,
                        model: Model::Near(&lights),
                        obs: &obs,
                        settings: FitSettings::default(),
                        depths,
                        cancel: crate::Cancel::never(),
                        warm: None,
                        shadows: None,
                        indirect: None,
                    };
                    let n = grid.n_facets();
                    let mut fits = vec![FacetFit::EMPTY; n];
                    step.run(&u, 0, &mut fits);
                    let mut buf = vec![0.0f32; k];
                    for (f, lane_fit) in fits.iter().enumerate() {
                        let fit = step.fit(f, &u, &mut buf, &mut Packed::new(), None);
                        assert_eq!(&fit, lane_fit, "facet {f}");
                    }
                    fast_batches += (0..n / LANES)
                        .filter(|b| {
                            let p0 = grid.facets[b * LANES] as usize;
                            grid.facets[b * LANES + LANES - 1] as usize == p0 + LANES - 1
                                && p0 % w + LANES <= w
                        })
                        .count();
                }
            }
        }
        assert!(fast_batches > 10, "{fast_batches}");
    }

    /// The vectorized accumulation gives bit for bit the fits of the scalar code (isotropic
    /// lights and LEDs with mu = 1, shadowed and missing observations, a partial last batch).
    #[test]
    fn lanes_match_the_scalar_fits_exactly() {
        use crate::rig::{Camera, Rig};
        let (h, w) = (9, 7);
        let mask: Vec<bool> = (0..h * w).map(|p| p % 5 != 2).collect();
        let grid = Grid::new(h, w, Some(&mask)).unwrap();
        let camera = Camera::Orthographic {
            pixel_size: [1.5, 1.5],
            origin: [-5.0, -7.0],
        };
        let geometry = Geometry::new(&camera, &grid).unwrap();
        let mut lights: Vec<Light> = crate::local::tests::lights();
        lights.push(Light::Point {
            position: [12.0, -8.0, 30.0],
            intensity: [2.0, 3.0, 4.0],
            axis: normalize([-0.2, 0.1, 1.0]),
            mu: 1.0,
        });
        let _ = Rig {
            camera,
            lights: lights.clone(),
        };
        let k = lights.len();
        let u: Vec<f64> = grid
            .active
            .iter()
            .map(|&v| {
                100.0 + 0.3 * (v % 8) as f64 - 0.2 * (v / 8) as f64 + 0.05 * ((v * 7) % 5) as f64
            })
            .collect();
        let mut data = vec![0.0f32; k * h * w];
        for (i, x) in data.iter_mut().enumerate() {
            *x = match i % 17 {
                0 => 0.0,
                3 => f32::NAN,
                _ => 1e-4 * (1.0 + ((i * 31) % 13) as f32),
            };
        }
        let obs = Observations::from_stack(&data, k, h * w, 1);
        let step = LocalStep {
            grid: &grid,
            geometry: &geometry,
            model: Model::Near(&lights),
            obs: &obs,
            settings: FitSettings {
                fast_residual: true,
                ..FitSettings::default()
            },
            depths: None,
            cancel: crate::Cancel::never(),
            warm: None,
            shadows: None,
            indirect: None,
        };
        assert!(step.lane_lights().is_some());
        let n = grid.n_facets();
        assert!(!n.is_multiple_of(LANES));
        let mut targets = vec![[0.0; 4]; n];
        let mut stats = vec![FacetStat::default(); n];
        step.run_targets(&u, &mut targets, &mut stats);
        let mut buf = vec![0.0f32; k];
        for f in 0..n {
            let fit = step.fit(f, &u, &mut buf, &mut Packed::new(), None);
            assert_eq!(fit.target, targets[f], "facet {f}");
            assert_eq!(FacetStat::from(&fit), stats[f], "facet {f}");
        }
        assert!(stats.iter().any(|s| s.valid) && stats.iter().any(|s| s.used < k as u32));
        // The final pass: exact residuals.
        let exact = LocalStep {
            settings: FitSettings::default(),
            ..step
        };
        let mut fits = vec![FacetFit::EMPTY; n];
        exact.run(&u, 0, &mut fits);
        for (f, lane_fit) in fits.iter().enumerate() {
            let fit = exact.fit(f, &u, &mut buf, &mut Packed::new(), None);
            assert_eq!(fit.target, lane_fit.target, "facet {f}");
            assert_eq!(fit.normal, lane_fit.normal, "facet {f}");
            assert_eq!(fit.albedo[0], lane_fit.albedo[0], "facet {f}");
            assert_eq!(fit.sse, lane_fit.sse, "facet {f}");
            assert_eq!(fit.used, lane_fit.used, "facet {f}");
        }
        // The fused final pass: the same fits, and the trust maps of `trust` bit for bit (the
        // per-light sums up to the order of the parallel reduction), in two chunks.
        assert!(exact.lane_lights().is_some());
        let expected = exact.trust(&u).unwrap();
        let mut maps = TrustMaps::new(&grid, k, 1).unwrap();
        let mut final_fits = vec![FacetFit::EMPTY; n];
        let mut values = vec![[f32::NAN; 2]; n];
        let split = 8;
        for (first, end) in [(0, split), (split, n)] {
            let (fits, values) = (&mut final_fits[first..end], &mut values[first..end]);
            exact
                .try_run_final(&u, first, fits, values, &mut maps)
                .unwrap();
            maps.scatter(&grid, first, values);
        }
        assert_eq!(final_fits, fits);
        let trust = maps.finish();
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&trust.normal_sigma), bits(&expected.normal_sigma));
        assert_eq!(bits(&trust.held_out), bits(&expected.held_out));
        assert!(trust.normal_sigma.iter().any(|v| v.is_finite()));
        for (a, b) in trust.lights.iter().zip(&expected.lights) {
            assert_eq!(a.facets, b.facets);
            for (x, y) in [
                (a.residual, b.residual),
                (a.held_out, b.held_out),
                (a.mean_intensity, b.mean_intensity),
            ] {
                assert!((x - y).abs() <= 1e-12 * y.abs(), "{a:?} {b:?}");
            }
        }
    }
}
