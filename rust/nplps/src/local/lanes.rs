//! The vectorized local step: the grey, unit-weight normal equations and residuals of
//! [`LANES`] facets at once, one SIMD lane per facet, with the lane form of the light model
//! (`LaneLight`). Per lane the sums are those of the scalar code (`Facet::accumulate_grey`,
//! `Facet::sq_residual`), the same operations in the same order, so the fits agree bit for bit;
//! so are the solves of the 3 x 3 systems, the normals and the plane targets (`solve_lanes`,
//! nalgebra's closed-form inverse written out per lane, `Geometry::plane_targets`), which run in
//! the lanes too, right after the sums. A batch of neighbours in one image row takes its corners
//! from two grid rows (`LocalStep::batch_corners`). The kernels run compiled for AVX-512 (8 f64 lanes in one register) or AVX2 when the processor
//! has it (`simd_dispatch!`, its `wide` form): the same operations per lane, so the same bits.

#[cfg(test)]
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use super::trust::{add_sums, LightSums, CHUNK};
use super::{
    keep_shape, u16_value, usable_count, FacetFit, FacetStat, LocalStep, Model, Observations,
    Robust, Stored, Weighting, SCRATCH,
};
use crate::error::Result;
use crate::geometry::{quad_centre, Geometry};
use crate::light::LaneLight;
use crate::memory::try_vec;

mod field;
pub(crate) use field::FieldRow;
mod robust;

pub(super) use robust::RobustScratch;

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
    Ok((
        try_vec(per, 0.0f32, SCRATCH)?,
        try_vec(k, [0.0f32; LANES], SCRATCH)?,
    ))
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
    /// no robust fit, and only lights with a lane form ([`LaneLight::from_light`]: point
    /// lights, isotropic or LEDs). It computes the same sums in the same order as
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
        if let Some(field) = self.indirect {
            // (with a field the lights come from `field_lane_lights`; no trust pass uses them)
            debug_assert!(trust.is_none());
            return self.fit_field_lanes(lights, first, u, buf, interleaved, field);
        }
        let geometry = self.geometry;
        let (batch, centres) = self.gather_batch(first, u, buf, interleaved);
        let thresholds = (self.settings.dark, self.settings.saturation);
        let mut trust = trust;
        let (sums, solved) = fit_lanes_dispatch(
            lights,
            &centres,
            interleaved,
            thresholds,
            trust.as_mut().map(|t| &mut t.rows[..]),
            &batch.base,
            geometry,
        );
        let mut fitted: [Option<FacetFit>; LANES] = crate::lanes(|l| {
            let n = &solved.normal;
            solved.valid[l].then_some(FacetFit {
                target: solved.target[l],
                normal: [n[0][l], n[1][l], n[2][l]],
                albedo: [solved.rho[l]; 3],
                specular: 0.0,
                sse: solved.sse[l],
                used: sums.used[l],
                valid: true,
            })
        });
        if let Some(trust) = trust {
            // One pass over the stored rows for the exact residuals and the trust values.
            let normals = fitted.map(|f| f.map_or([0.0; 3], |f| f.normal));
            let albedo = fitted.map(|f| f.map_or(0.0, |f| f.albedo[0]));
            let fits = LaneFits { normals, albedo };
            let solved = LaneSolved::new(&sums, &solved);
            let out = final_residuals_dispatch(
                lights,
                trust.rows,
                interleaved,
                thresholds,
                &fits,
                &solved,
                trust.sums,
            );
            let values = trust_lanes_dispatch(&out, &solved, &sums.used);
            for l in 0..LANES {
                if let (false, Some(fit)) = (self.settings.fast_residual, &mut fitted[l]) {
                    fit.sse = out[0][l];
                }
            }
            trust.out.copy_from_slice(&values);
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
        std::array::from_fn(|l| match fitted[l] {
            Some(fitted) => fitted,
            None => self.unsolved_fit(&batch, l, first, u, buf),
        })
    }

    /// The fit of lane `l` of `batch` (facet `first + l`) where the lane solve found none: the
    /// facet keeps its shape ([`keep_shape`]), with its count of usable lights.
    fn unsolved_fit(
        &self,
        batch: &BatchCorners,
        l: usize,
        first: usize,
        u: &[f64],
        buf: &mut [f32],
    ) -> FacetFit {
        let values = self.facet_values(first + l, buf);
        keep_shape(
            &batch.quads[l],
            batch.ids[l].map(|i| u[i as usize]),
            usable_count(values, 1, self.settings),
        )
    }
}

impl LocalStep<'_> {
    /// The targets and statistics of [`LocalStep::fit_lanes`]'s fits of facets
    /// `first..first + LANES` (`targets` and `stats` of [`LANES`] entries), written from the
    /// kernel's solution without the fits' normals and albedos: with the fast residual and
    /// without indirect light (the solver's iterations); otherwise from the whole fits.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn fit_lanes_targets(
        &self,
        lights: &[LaneLight],
        first: usize,
        u: &[f64],
        buf: &mut [f32],
        interleaved: &mut [[f32; LANES]],
        targets: &mut [[f64; 4]],
        stats: &mut [FacetStat],
    ) {
        if self.indirect.is_some() || !self.settings.fast_residual {
            let fits = self.fit_lanes(lights, first, u, buf, interleaved, None);
            for ((target, stat), fit) in targets.iter_mut().zip(stats).zip(&fits) {
                *target = fit.target;
                *stat = FacetStat::from(fit);
            }
            return;
        }
        let (batch, centres) = self.gather_batch(first, u, buf, interleaved);
        let thresholds = (self.settings.dark, self.settings.saturation);
        let (sums, solved) = fit_lanes_dispatch(
            lights,
            &centres,
            interleaved,
            thresholds,
            None,
            &batch.base,
            self.geometry,
        );
        for (l, (target, stat)) in targets.iter_mut().zip(stats).enumerate() {
            if solved.valid[l] {
                *target = solved.target[l];
                *stat = FacetStat {
                    sse: solved.sse[l],
                    used: sums.used[l],
                    valid: true,
                };
            } else {
                let fit = self.unsolved_fit(&batch, l, first, u, buf);
                *target = fit.target;
                *stat = FacetStat::from(&fit);
            }
        }
    }
}

impl LocalStep<'_> {
    /// The corners and centres of facets `first..first + LANES` on `u`, and their observations
    /// gathered into `interleaved` (`interleaved[k][lane]`, those in a cast shadow NaN; `buf`
    /// is scratch for one facet's).
    #[inline(always)]
    fn gather_batch(
        &self,
        first: usize,
        u: &[f64],
        buf: &mut [f32],
        interleaved: &mut [[f32; LANES]],
    ) -> (BatchCorners, [[f64; 3]; LANES]) {
        let (grid, obs) = (self.grid, self.obs);
        let pixels: [usize; LANES] = crate::lanes(|l| grid.facets[first + l] as usize);
        let batch = self.batch_corners(first, &pixels, u);
        let centres: [[f64; 3]; LANES] = crate::lanes(|l| quad_centre(&batch.quads[l]));
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
        (batch, centres)
    }

    /// The trust values alone of facets `first..first + LANES` (see [`LocalStep::fit_lanes`]
    /// with a [`LaneTrust`], whose values and sums these are, bit for bit): the sums and the
    /// solve of the trust's normal equations, and one pass over the stored rows, without the
    /// fits' normals, albedos, targets and residuals.
    fn trust_batch(
        &self,
        lights: &[LaneLight],
        first: usize,
        u: &[f64],
        buf: &mut [f32],
        interleaved: &mut [[f32; LANES]],
        trust: LaneTrust<'_>,
    ) {
        let (_, centres) = self.gather_batch(first, u, buf, interleaved);
        let thresholds = (self.settings.dark, self.settings.saturation);
        let (used, solved) =
            trust_kernel_dispatch(lights, &centres, interleaved, thresholds, trust.rows);
        let out = trust_residuals_dispatch(
            lights,
            trust.rows,
            interleaved,
            thresholds,
            &solved,
            trust.sums,
        );
        trust
            .out
            .copy_from_slice(&trust_lanes_dispatch(&out, &solved, &used));
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
                let ids: [u32; LANES + 1] = crate::lanes(|j| grid.vertex_unknown[v + j]);
                let base = crate::lanes(|j| geometry.base_at_vertex(ids[j] as usize, r, col + j));
                (ids, base)
            };
            let (top, top_base) = line(row, v0);
            let (bottom, bottom_base) = line(row + 1, v0 + vw);
            let place = |ids: &[u32; LANES + 1], base: &[[f64; 2]; LANES + 1]| {
                let z: [f64; LANES + 1] = crate::lanes(|j| self.depth_of(ids[j], u));
                let p: [[f64; 3]; LANES + 1] =
                    crate::lanes(|j| geometry.position_from_base(base[j], z[j]));
                p
            };
            let (tp, bp) = (place(&top, &top_base), place(&bottom, &bottom_base));
            return BatchCorners {
                ids: crate::lanes(|l| [top[l], top[l + 1], bottom[l], bottom[l + 1]]),
                base: crate::lanes(|l| {
                    [
                        top_base[l],
                        top_base[l + 1],
                        bottom_base[l],
                        bottom_base[l + 1],
                    ]
                }),
                quads: crate::lanes(|l| [tp[l], tp[l + 1], bp[l], bp[l + 1]]),
            };
        }
        let ids: [[u32; 4]; LANES] = crate::lanes(|l| grid.facet_vertices(first + l));
        let base: [[[f64; 2]; 4]; LANES] =
            crate::lanes(|l| ids[l].map(|i| geometry.base(i as usize)));
        let quads = crate::lanes(|l| {
            let (ids, base) = (&ids[l], &base[l]);
            let at = |j: usize| geometry.position_from_base(base[j], self.depth_of(ids[j], u));
            [at(0), at(1), at(2), at(3)]
        });
        BatchCorners { ids, base, quads }
    }
}

/// The grey unit-weight normal equations of [`LANES`] facets, one lane each (the sums of
/// [`Facet::accumulate_grey`](super::Facet::accumulate_grey)): `T` as its 6 entries
/// `t00 t01 t02 t11 t12 t22`, `s`, `sum I^2` and the usable lights.
struct LaneSums {
    t: [[f64; LANES]; 6],
    s: [[f64; LANES]; 3],
    sum_i2: [f64; LANES],
    used: [u32; LANES],
}

/// The solutions of [`LANES`] facets' grey, unit-weight normal equations `T g = s` (see
/// [`solve_lanes`]), one lane each.
struct LaneSolution {
    /// `T^-1`, its entries row-major.
    inverse: [[f64; LANES]; 9],
    /// Whether `T` passes the test of [`invert_spd3`](super::invert_spd3).
    regular: [bool; LANES],
    /// `g = T^-1 s`.
    g: [[f64; LANES]; 3],
    /// The unit normal `g / |g|`.
    normal: [[f64; LANES]; 3],
    /// The albedo `rho = |g|`.
    rho: [f64; LANES],
    /// The residual from the normal equations, `max(0, sum I^2 - g . s)`.
    sse: [f64; LANES],
    /// Whether the fit succeeded: at least 3 usable lights, `T` regular, `rho` finite and
    /// positive.
    valid: [bool; LANES],
    /// The corner targets of the plane through the facet's centre with that normal (see
    /// [`Geometry::plane_target`]).
    target: [[f64; 4]; LANES],
}

simd_dispatch! {
    wide
    /// [`accumulate_lanes`] and [`solve_lanes`] with AVX-512 or AVX2 when the processor has it
    /// (same arithmetic, wider registers): the sums stay in registers for the solve.
    fn fit_lanes_dispatch => fit_kernel(
        lights: &[LaneLight],
        centres: &[[f64; 3]; LANES],
        values: &[[f32; LANES]],
        thresholds: (f64, f64),
        rows: Option<&mut [[[f64; LANES]; 3]]>,
        base: &[[[f64; 2]; 4]; LANES],
        geometry: &Geometry,
    ) -> (LaneSums, LaneSolution);
}

simd_dispatch! {
    wide
    #[cfg(test)]
    /// [`solve_lanes`] alone, dispatched as [`fit_lanes_dispatch`] (for the tests).
    fn solve_lanes_dispatch => solve_lanes(
        sums: &LaneSums,
        centres: &[[f64; 3]; LANES],
        base: &[[[f64; 2]; 4]; LANES],
        geometry: &Geometry,
    ) -> LaneSolution;
}

/// [`accumulate_lanes`], then [`solve_lanes`].
#[inline(always)]
fn fit_kernel(
    lights: &[LaneLight],
    centres: &[[f64; 3]; LANES],
    values: &[[f32; LANES]],
    thresholds: (f64, f64),
    rows: Option<&mut [[[f64; LANES]; 3]]>,
    base: &[[[f64; 2]; 4]; LANES],
    geometry: &Geometry,
) -> (LaneSums, LaneSolution) {
    let sums = accumulate_lanes(lights, centres, values, thresholds, rows);
    let solution = solve_lanes(&sums, centres, base, geometry);
    (sums, solution)
}

simd_dispatch! {
    wide
    /// [`trust_kernel`] with AVX-512 or AVX2 when the processor has it (same arithmetic, wider
    /// registers).
    fn trust_kernel_dispatch => trust_kernel(
        lights: &[LaneLight],
        centres: &[[f64; 3]; LANES],
        values: &[[f32; LANES]],
        thresholds: (f64, f64),
        rows: &mut [[[f64; LANES]; 3]],
    ) -> ([u32; LANES], LaneSolved);
}

/// [`accumulate_lanes`] with the rows stored, and the trust's solution of the sums (the solve
/// of [`solve_lanes`], without the normals, albedos, residuals and targets of the fits): the
/// usable lights and the [`LaneSolved`] of [`LaneSolved::new`], the same bits.
#[inline(always)]
fn trust_kernel(
    lights: &[LaneLight],
    centres: &[[f64; 3]; LANES],
    values: &[[f32; LANES]],
    thresholds: (f64, f64),
    rows: &mut [[[f64; LANES]; 3]],
) -> ([u32; LANES], LaneSolved) {
    let sums = accumulate_lanes(lights, centres, values, thresholds, Some(rows));
    let (regular, inverse, g) = super::solve_spd3_lanes(&sums.t, &sums.s);
    (
        sums.used,
        LaneSolved::of(&sums.used, &regular, &inverse, &g),
    )
}

/// The fits of [`LANES`] facets' grey, unit-weight sums, one lane each, with the operations of
/// the scalar code in its order, so that they agree bit for bit: the test, closed-form
/// inverse and `g = T^-1 s` of [`solve_spd3_lanes`](super::solve_spd3_lanes), the normal and albedo of
/// [`solve_sums`](super::solve_sums) with one channel, the fast residual of
/// [`fit_facet`](super::fit_facet), and the targets of [`Geometry::plane_target`]. Every lane
/// is computed (a failed fit's values are not used), with plain loops over the lanes that the
/// compiler turns into vector instructions: the 12 divisions and the root of a facet run 8
/// lanes to an instruction.
#[inline(always)]
fn solve_lanes(
    sums: &LaneSums,
    centres: &[[f64; 3]; LANES],
    base: &[[[f64; 2]; 4]; LANES],
    geometry: &Geometry,
) -> LaneSolution {
    let z = [0.0f64; LANES];
    let s = &sums.s;
    let (regular, inverse, g) = super::solve_spd3_lanes(&sums.t, s);
    let (mut rho, mut sse, mut valid) = (z, z, [false; LANES]);
    let mut normal = [z; 3];
    for l in 0..LANES {
        rho[l] = (g[0][l] * g[0][l] + g[1][l] * g[1][l] + g[2][l] * g[2][l]).sqrt();
        let gs = g[0][l] * s[0][l] + g[1][l] * s[1][l] + g[2][l] * s[2][l];
        sse[l] = (sums.sum_i2[l] - gs).max(0.0);
        valid[l] = sums.used[l] >= 3 && regular[l] && rho[l].is_finite() && rho[l] > 0.0;
    }
    for (n, g) in normal.iter_mut().zip(&g) {
        for l in 0..LANES {
            n[l] = g[l] / rho[l];
        }
    }
    let target = geometry.plane_targets(base, &normal, centres);
    LaneSolution {
        inverse,
        regular,
        g,
        normal,
        rho,
        sse,
        valid,
        target,
    }
}

/// The observations of one light in [`LANES`] facets as f64, and whether each is usable
/// (strictly between `dark` and `saturation`, not NaN).
#[inline(always)]
fn lane_values(v: &[f32; LANES], dark: f64, saturation: f64) -> ([f64; LANES], [bool; LANES]) {
    let i: [f64; LANES] = crate::lanes(|l| v[l] as f64);
    let ok: [bool; LANES] = crate::lanes(|l| i[l] > dark && i[l] < saturation);
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
) -> LaneSums {
    let mut t = [[0.0f64; LANES]; 6];
    let mut s = [[0.0f64; LANES]; 3];
    let mut sum_i2 = [0.0f64; LANES];
    let mut used = [0u32; LANES];
    for (k, (light, v)) in lights.iter().zip(values).enumerate() {
        let p = light.grey;
        let (i, ok) = lane_values(v, dark, saturation);
        let ([a0, a1, a2], f) = light.beta(centres);
        let b0: [f64; LANES] = crate::lanes(|l| a0[l] * f[l]);
        let b1: [f64; LANES] = crate::lanes(|l| a1[l] * f[l]);
        let b2: [f64; LANES] = crate::lanes(|l| a2[l] * f[l]);
        if let Some(rows) = rows.as_mut() {
            rows[k] = [b0, b1, b2];
        }
        let r0: [f64; LANES] = crate::lanes(|l| b0[l] * p);
        let r1: [f64; LANES] = crate::lanes(|l| b1[l] * p);
        let r2: [f64; LANES] = crate::lanes(|l| b2[l] * p);
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
    LaneSums { t, s, sum_i2, used }
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
        let nb: [f64; LANES] = crate::lanes(|l| {
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

/// The trust part of a final pass over [`LANES`] facets (see [`LocalStep::final_lanes_into`]): scratch
/// rows (`beta` of each light, per lane), the facets' `[normal sigma, held-out]` and the
/// per-light sums they add to, per lane (see [`LaneLightSums`]).
pub(super) struct LaneTrust<'a> {
    rows: &'a mut [[[f64; LANES]; 3]],
    out: &'a mut [[f32; 2]],
    sums: &'a mut [LaneLightSums],
}

/// One light's trust sums (see [`LightSums`]) of the batches of a chunk, one running sum per
/// lane: [`final_residuals`] adds each batch's terms lane by lane (vector additions), and
/// [`LocalStep::final_lanes_into`] sums the lanes ([`lane_total`]) once at the end of the chunk.
type LaneLightSums = [[f64; LANES]; 4];

/// The grey fits of [`LANES`] facets: unit normals and albedo (0 where a fit failed).
struct LaneFits {
    normals: [[f64; 3]; LANES],
    albedo: [f64; LANES],
}

/// The trust's solution of [`LANES`] facets' normal equations (see the `trust` module):
/// `T^-1` (its entries row-major, one lane each), `g = T^-1 s`, and whether the facet has a
/// trust value (at least 4 usable lights, `T` regular).
struct LaneSolved {
    inverse: [[f64; LANES]; 9],
    g: [[f64; LANES]; 3],
    active: [bool; LANES],
}

impl LaneSolved {
    /// From the sums and their lane solution, as `LocalStep::facet_trust` solves them (the
    /// inverse of [`invert_spd3`](super::invert_spd3) and `g = T^-1 s`, which
    /// [`solve_lanes`] computes with the same operations): active where at least 4 lights are
    /// usable and `T` is regular (elsewhere the inverse and `g` are 0).
    fn new(sums: &LaneSums, solution: &LaneSolution) -> LaneSolved {
        LaneSolved::of(
            &sums.used,
            &solution.regular,
            &solution.inverse,
            &solution.g,
        )
    }

    /// From the usable lights, and the test, inverse and `g` of
    /// [`solve_spd3_lanes`](super::solve_spd3_lanes) (see [`LaneSolved::new`]).
    #[inline(always)]
    fn of(
        used: &[u32; LANES],
        regular: &[bool; LANES],
        inverse: &[[f64; LANES]; 9],
        g: &[[f64; LANES]; 3],
    ) -> LaneSolved {
        let active: [bool; LANES] = crate::lanes(|l| used[l] >= 4 && regular[l]);
        let keep = |x: &[f64; LANES]| -> [f64; LANES] {
            crate::lanes(|l| if active[l] { x[l] } else { 0.0 })
        };
        LaneSolved {
            inverse: inverse.each_ref().map(keep),
            g: g.each_ref().map(keep),
            active,
        }
    }

    /// `T^-1` of lane `l`.
    #[cfg(test)]
    fn inverse(&self, l: usize) -> Matrix3<f64> {
        let m = &self.inverse;
        Matrix3::new(
            m[0][l], m[1][l], m[2][l], m[3][l], m[4][l], m[5][l], m[6][l], m[7][l], m[8][l],
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
        sums: &mut [LaneLightSums],
    ) -> [[f64; LANES]; 4];
}

/// One pass over the lights of [`LANES`] facets, their rows `beta` stored by
/// [`accumulate_lanes`]: the exact squared residuals of the fits `fits` (the operations of
/// [`residual_lanes`]), and for the facets with a trust value (`solved`) the trust's residual
/// `e = I - r . g`, leverage `h = r . T^-1 r` and leave-one-out residual `e / (1 - h)` (the
/// operations of `LocalStep::facet_trust`, in its order), adding each light's terms to its
/// running sums `sums`, lane by lane (the lanes are summed once per chunk, see
/// [`LaneLightSums`]: the per-light sums differ from the scalar code's facet-after-facet order
/// in the last bits, as they do with the order of the parallel reduction; the per-facet values
/// are the scalar code's bits). Returns per lane the fit's squared residual, the trust's, the sum of the finite
/// `|e / (1 - h)|` and their count.
#[inline(always)]
fn final_residuals(
    lights: &[LaneLight],
    rows: &[[[f64; LANES]; 3]],
    values: &[[f32; LANES]],
    thresholds: (f64, f64),
    fits: &LaneFits,
    solved: &LaneSolved,
    sums: &mut [LaneLightSums],
) -> [[f64; LANES]; 4] {
    residual_terms::<true>(lights, rows, values, thresholds, fits, solved, sums)
}

simd_dispatch! {
    wide
    /// [`trust_residuals`] with AVX-512 or AVX2 when the processor has it (same arithmetic,
    /// wider registers).
    fn trust_residuals_dispatch => trust_residuals(
        lights: &[LaneLight],
        rows: &[[[f64; LANES]; 3]],
        values: &[[f32; LANES]],
        thresholds: (f64, f64),
        solved: &LaneSolved,
        sums: &mut [LaneLightSums],
    ) -> [[f64; LANES]; 4];
}

/// [`final_residuals`] without fits: the trust's terms alone (the fits' squared residuals,
/// row 0, are 0), the same bits.
#[inline(always)]
fn trust_residuals(
    lights: &[LaneLight],
    rows: &[[[f64; LANES]; 3]],
    values: &[[f32; LANES]],
    thresholds: (f64, f64),
    solved: &LaneSolved,
    sums: &mut [LaneLightSums],
) -> [[f64; LANES]; 4] {
    let fits = LaneFits {
        normals: [[0.0; 3]; LANES],
        albedo: [0.0; LANES],
    };
    residual_terms::<false>(lights, rows, values, thresholds, &fits, solved, sums)
}

/// [`final_residuals`], with the fits' squared residuals when `FIT` (else 0).
#[inline(always)]
fn residual_terms<const FIT: bool>(
    lights: &[LaneLight],
    rows: &[[[f64; LANES]; 3]],
    values: &[[f32; LANES]],
    (dark, saturation): (f64, f64),
    fits: &LaneFits,
    solved: &LaneSolved,
    sums: &mut [LaneLightSums],
) -> [[f64; LANES]; 4] {
    let mut sse = [0.0f64; LANES];
    let mut trust_sse = [0.0f64; LANES];
    let mut loo_sum = [0.0f64; LANES];
    let mut loo_count = [0.0f64; LANES];
    let (inv, g, active) = (&solved.inverse, &solved.g, &solved.active);
    // The normals one row per component (the lanes of a component side by side).
    let normals: [[f64; LANES]; 3] = crate::lanes(|j| crate::lanes(|l| fits.normals[l][j]));
    let albedo = &fits.albedo;
    for (((light, v), row), sum) in lights.iter().zip(values).zip(rows).zip(sums) {
        let p = light.grey;
        let [b0, b1, b2] = row;
        // The light's running sums in locals, written back whole; the conditions combined with
        // `&` (no short circuit) and the terms chosen by `select_unpredictable`, not by `if`:
        // branches that the compiler turned into pairs of masked stores, with the sums on the
        // stack, whose loads the next light's additions waited for (most of the time of this
        // function).
        let mut s = *sum;
        let pick = |c: bool, x: f64| std::hint::select_unpredictable(c, x, 0.0);
        for l in 0..LANES {
            let i = v[l] as f64;
            let ok = (i > dark) & (i < saturation);
            if FIT {
                let nb = normals[0][l] * b0[l] + normals[1][l] * b1[l] + normals[2][l] * b2[l];
                let fit_e = albedo[l] * p * nb - i;
                sse[l] += pick(ok, fit_e * fit_e);
            }
            let (r0, r1, r2) = (b0[l] * p, b1[l] * p, b2[l] * p);
            let e = i - (r0 * g[0][l] + r1 * g[1][l] + r2 * g[2][l]);
            let ir0 = inv[0][l] * r0 + inv[1][l] * r1 + inv[2][l] * r2;
            let ir1 = inv[3][l] * r0 + inv[4][l] * r1 + inv[5][l] * r2;
            let ir2 = inv[6][l] * r0 + inv[7][l] * r1 + inv[8][l] * r2;
            let h = r0 * ir0 + r1 * ir1 + r2 * ir2;
            let loo = e / (1.0 - h);
            // Per lane the facet's sums as the scalar code adds them (adding 0 to a sum of
            // non-negative terms changes no bit); the light's terms are added to its running
            // sums lane by lane (no horizontal sum per batch).
            let used = ok & active[l];
            let finite = used & loo.is_finite();
            let ee = e * e;
            trust_sse[l] += pick(used, ee);
            loo_sum[l] += pick(finite, loo.abs());
            loo_count[l] += pick(finite, 1.0);
            s[0][l] += pick(used, ee);
            s[1][l] += pick(finite, loo * loo);
            s[2][l] += pick(used, i);
            s[3][l] += pick(used, 1.0);
        }
        *sum = s;
    }
    [sse, trust_sse, loo_sum, loo_count]
}

simd_dispatch! {
    wide
    /// [`trust_lanes`] with AVX-512 or AVX2 when the processor has it (same arithmetic, wider
    /// registers).
    fn trust_lanes_dispatch => trust_lanes(
        residuals: &[[f64; LANES]; 4],
        solved: &LaneSolved,
        used: &[u32; LANES],
    ) -> [[f32; 2]; LANES];
}

/// The trust values `[normal sigma, held-out]` of [`LANES`] grey facets, one lane each, from
/// [`final_residuals`]'s `residuals` (the trust's squared residual, the sum and count of the
/// finite leave-one-out residuals in rows 1-3), their trust solution `solved` and usable
/// lights `used`: per lane the operations of [`trust_values`](super::trust::trust_values) with one channel, in its order,
/// so the same bits: `cov = 0 + (sse / (used - 3)) T^-1` entry by entry, `b = 0 + g`,
/// `len = |b|`, `n = b / len`, the trace summed from 0 (nalgebra's `trace`), `C n` column after
/// column (nalgebra's matrix-vector product), `n . (C n)` as `(a + b) + c` (nalgebra's 3-vector
/// `dot`), `sigma = sqrt(max(0, (trace - n . C n) / len²))` in degrees and the mean
/// leave-one-out residual (NaN without one). NaN for the facets without a trust value
/// (`solved.active` false) or whose `|g|` is not finite and positive, as there. Written as plain
/// loops over the lanes, so the 7 divisions and 2 roots of a facet run 8 lanes to an
/// instruction (the scalar function took about a sixth of the final step).
#[inline(always)]
fn trust_lanes(
    residuals: &[[f64; LANES]; 4],
    solved: &LaneSolved,
    used: &[u32; LANES],
) -> [[f32; 2]; LANES] {
    let (inv, g) = (&solved.inverse, &solved.g);
    let [_, sse, loo_sum, loo_count] = residuals;
    let mut out = [[f32::NAN; 2]; LANES];
    for l in 0..LANES {
        // (an inactive lane's values are computed and not used; its `used` may be below 3)
        let dof = used[l].wrapping_sub(3) as usize as f64;
        let c = sse[l] / dof;
        let cov: [f64; 9] = crate::lanes(|j| 0.0 + c * inv[j][l]);
        let b = [0.0 + g[0][l], 0.0 + g[1][l], 0.0 + g[2][l]];
        let len = (b[0] * b[0] + b[1] * b[1] + b[2] * b[2]).sqrt();
        let n = [b[0] / len, b[1] / len, b[2] / len];
        let trace = ((0.0 + cov[0]) + cov[4]) + cov[8];
        let cn: [f64; 3] =
            crate::lanes(|i| cov[3 * i] * n[0] + cov[3 * i + 1] * n[1] + cov[3 * i + 2] * n[2]);
        let ncn = (n[0] * cn[0] + n[1] * cn[1]) + n[2] * cn[2];
        let var = ((trace - ncn) / (len * len)).max(0.0);
        let held_out = match loo_count[l] > 0.0 {
            true => loo_sum[l] / loo_count[l],
            false => f64::NAN,
        };
        let ok = solved.active[l] && len.is_finite() && len > 0.0;
        out[l] = match ok {
            true => [var.sqrt().to_degrees() as f32, held_out as f32],
            false => [f32::NAN; 2],
        };
    }
    out
}

/// The sum of the [`LANES`] values `a`, in pairs: `((a0 + a1) + (a2 + a3)) + ((a4 + a5) +
/// (a6 + a7))`.
#[inline(always)]
fn lane_total(a: &[f64; LANES]) -> f64 {
    let pairs: [f64; 4] = crate::lanes(|j| a[2 * j] + a[2 * j + 1]);
    (pairs[0] + pairs[1]) + (pairs[2] + pairs[3])
}

impl LocalStep<'_> {
    /// The final pass with the vectorized accumulation (`lights` from
    /// [`LocalStep::lane_lights`]) over every facet: each batch of [`LANES`]
    /// facets is fitted and its trust values computed from one evaluation of the lights'
    /// `beta`, with the fits of [`LocalStep::try_run`] and the trust values of the `trust`
    /// module (same operations, same order); with `fitted` false the trust values alone (see
    /// [`LocalStep::trust_batch`]; the fits handed on are then empty). The facets run in chunks
    /// of [`CHUNK`] (the last one shorter; one empty chunk without facets), in parallel, each
    /// on one thread, which hands its fits and trust values to `write` with the chunk's entry
    /// of `views` (one per chunk) and its first facet, straight from its own buffers. Returns
    /// the per-light sums (see [`LaneLightSums`]). Once cancelled, the remaining chunks are not
    /// written (the caller must then check the token and discard the maps).
    pub(super) fn final_lanes_into<V: Send>(
        &self,
        lights: &[LaneLight],
        u: &[f64],
        fitted: bool,
        views: Vec<V>,
        write: &(impl Fn(V, usize, &[FacetFit], &[[f32; 2]]) + Sync),
    ) -> Result<LightSums> {
        let len = self.grid.n_facets();
        debug_assert_eq!(views.len(), final_chunks(len));
        let (per, k) = (self.obs.per_facet(), self.obs.k);
        let scratch = || -> Result<_> {
            let (buf, interleaved) = lane_scratch(per, k)?;
            let rows = try_vec(k, [[0.0f64; LANES]; 3], SCRATCH)?;
            let trust_rows = try_vec(per, [0.0f64; 4], SCRATCH)?;
            let fits = try_vec(if fitted { CHUNK } else { 0 }, FacetFit::EMPTY, SCRATCH)?;
            let trust = try_vec(CHUNK, [f32::NAN; 2], SCRATCH)?;
            Ok((buf, interleaved, rows, trust_rows, fits, trust))
        };
        views
            .into_par_iter()
            .enumerate()
            .map_init(scratch, |scratch, (chunk, view)| {
                let (buf, interleaved, rows, trust_rows, fits, trust) =
                    scratch.as_mut().map_err(|e| e.clone())?;
                let start = chunk * CHUNK;
                let n = len.saturating_sub(chunk * CHUNK).min(CHUNK);
                let (fits, trust) = (&mut fits[..if fitted { n } else { 0 }], &mut trust[..n]);
                let mut sums = vec![[0.0f64; 4]; k];
                let mut lane_sums = vec![[[0.0f64; LANES]; 4]; k];
                for (b, out) in trust.chunks_mut(LANES).enumerate() {
                    if self.cancel.is_cancelled() {
                        return Ok(sums);
                    }
                    let at = start + b * LANES;
                    let batch = b * LANES..b * LANES + out.len();
                    if out.len() == LANES {
                        let lane_trust = LaneTrust {
                            rows,
                            out,
                            sums: &mut lane_sums,
                        };
                        if fitted {
                            let lanes =
                                self.fit_lanes(lights, at, u, buf, interleaved, Some(lane_trust));
                            fits[batch].copy_from_slice(&lanes);
                        } else {
                            self.trust_batch(lights, at, u, buf, interleaved, lane_trust);
                        }
                    } else {
                        for (i, out) in out.iter_mut().enumerate() {
                            if fitted {
                                let fit =
                                    self.fit(at + i, u, buf, &mut self.settings.packed(), None);
                                fits[batch.start + i] = fit;
                            }
                            *out = self.facet_trust(at + i, u, buf, trust_rows, &mut sums, None);
                        }
                    }
                }
                for (sum, lanes) in sums.iter_mut().zip(&lane_sums) {
                    for (sum, lanes) in sum.iter_mut().zip(lanes) {
                        *sum += lane_total(lanes);
                    }
                }
                write(view, start, fits, trust);
                Ok(sums)
            })
            .try_reduce(|| vec![[0.0; 4]; k], |a, b| Ok(add_sums(a, b)))
    }
}

/// The chunks of [`LocalStep::final_lanes_into`] over `len` facets: one per [`CHUNK`] facets
/// or part of one, and at least one.
pub(crate) fn final_chunks(len: usize) -> usize {
    len.div_ceil(CHUNK).max(1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Geometry;
    use crate::grid::Grid;
    use crate::light::Light;
    use crate::local::{FacetStat, FitSettings};
    use crate::reflectance::Packed;
    use crate::vec3::normalize;

    /// The lane solve gives the scalar code's solve bit for bit: regular, nearly singular,
    /// singular, indefinite and non-finite systems, fewer than 3 lights; the normal, albedo,
    /// fast residual, validity, inverse and `g`, and the targets (pinhole, with grazing normals
    /// and the logarithm's fallback, and orthographic).
    #[test]
    fn lane_solve_matches_the_scalar_solve_exactly() {
        use crate::local::Sums;
        use crate::rig::Camera;
        let mut next = crate::multigrid::tests::lcg(7);
        let grid = Grid::new(3, 3, None).unwrap();
        let cameras = [
            Camera::Pinhole {
                k: [[3.0, 0.0, 1.5], [0.0, 3.0, 1.5], [0.0, 0.0, 1.0]],
                distortion: [0.0; 5],
            },
            Camera::Orthographic {
                pixel_size: [1.0, 1.0],
                origin: [0.0, 0.0],
            },
        ];
        let mut checked = [0usize; 3];
        for round in 0..400 {
            let scalar: [Sums; LANES] = std::array::from_fn(|l| {
                let r: [[f64; 3]; 5] = crate::lanes(|_| crate::lanes(|_| next() - 0.5));
                let mut t = [0.0; 6];
                let mut s = [0.0; 3];
                let lights = match (round + l) % 9 {
                    0 => 2,
                    1 => 3,
                    _ => 5,
                };
                for (k, r) in r.iter().take(lights).enumerate() {
                    let i = 0.5 + next();
                    let idx = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)];
                    for (slot, (a, b)) in t.iter_mut().zip(idx) {
                        *slot += r[a] * r[b];
                    }
                    for (slot, x) in s.iter_mut().zip(r) {
                        *slot += x * i * (1.0 + 0.1 * k as f64);
                    }
                }
                match (round * 3 + l) % 11 {
                    0 => t = [1.0, 1.0, 0.0, 1.0, 0.0, 1.0], // singular
                    1 => t[5] = -t[5],                       // indefinite
                    2 => t[4] = f64::NAN,
                    3 => t = [1.0, 1.0 - 1e-7, 0.0, 1.0, 0.0, 1.0], // nearly singular
                    4 => s = [0.0; 3],
                    _ => {}
                }
                Sums {
                    t: [t, [0.0; 6], [0.0; 6]],
                    s: [s, [0.0; 3], [0.0; 3]],
                    sum_i2: 3.0 * next(),
                    used: lights as u32,
                    lit: lights as u32,
                }
            });
            let lane =
                |f: &dyn Fn(&Sums) -> f64| -> [f64; LANES] { crate::lanes(|l| f(&scalar[l])) };
            let sums = LaneSums {
                t: crate::lanes(|i| lane(&|x| x.t[0][i])),
                s: crate::lanes(|i| lane(&|x| x.s[0][i])),
                sum_i2: lane(&|x| x.sum_i2),
                used: crate::lanes(|l| scalar[l].used),
            };
            let centres: [[f64; 3]; LANES] =
                crate::lanes(|_| [next() - 0.5, next() - 0.5, 5.0 + next()]);
            let base: [[[f64; 2]; 4]; LANES] = crate::lanes(|_| {
                let spread = if next() < 0.2 { 3.0 } else { 0.01 };
                let x = [next() - 0.5, next() - 0.5];
                crate::lanes(|_| [x[0] + spread * next(), x[1] + spread * next()])
            });
            let geometry = Geometry::new(&cameras[round % 2], &grid).unwrap();
            let lanes = solve_lanes_dispatch(&sums, &centres, &base, &geometry);
            let plain = solve_lanes(&sums, &centres, &base, &geometry);
            for l in 0..LANES {
                let sums = &scalar[l];
                let t = &sums.t[0];
                let tm = Matrix3::new(t[0], t[1], t[2], t[1], t[3], t[4], t[2], t[4], t[5]);
                let inverse = super::super::invert_spd3(&tm);
                assert_eq!(lanes.regular[l], inverse.is_some(), "{round} {l}");
                assert_eq!(plain.regular[l], lanes.regular[l]);
                if let Some(inv) = inverse {
                    let g = inv * Vector3::from(sums.s[0]);
                    let m: [[f64; 3]; 3] = crate::lanes(|i| crate::lanes(|j| inv[(i, j)]));
                    let lane_inverse: [[f64; 3]; 3] =
                        crate::lanes(|i| crate::lanes(|j| lanes.inverse[3 * i + j][l]));
                    let bits = |m: [[f64; 3]; 3]| m.map(|r| r.map(f64::to_bits));
                    assert_eq!(bits(lane_inverse), bits(m));
                    let lane_g = [lanes.g[0][l], lanes.g[1][l], lanes.g[2][l]];
                    assert_eq!(lane_g.map(f64::to_bits), [g.x, g.y, g.z].map(f64::to_bits));
                    checked[0] += 1;
                }
                let fit = (sums.used >= 3)
                    .then(|| super::super::solve_sums(sums, 1))
                    .flatten();
                assert_eq!(lanes.valid[l], fit.is_some(), "{round} {l}");
                if let Some((normal, albedo, g)) = fit {
                    let sse = (sums.sum_i2 - crate::vec3::dot(g, sums.s[0])).max(0.0);
                    let lane_normal = [lanes.normal[0][l], lanes.normal[1][l], lanes.normal[2][l]];
                    assert_eq!(lane_normal.map(f64::to_bits), normal.map(f64::to_bits));
                    assert_eq!(lanes.rho[l].to_bits(), albedo[0].to_bits());
                    assert_eq!(lanes.sse[l].to_bits(), sse.to_bits());
                    let target = geometry.plane_target_at(base[l], normal, centres[l]);
                    assert_eq!(lanes.target[l].map(f64::to_bits), target.map(f64::to_bits));
                    assert_eq!(plain.target[l].map(f64::to_bits), target.map(f64::to_bits));
                    checked[1] += 1;
                    if round % 2 == 0 && normal[2] > -0.3 {
                        checked[2] += 1;
                    }
                }
            }
        }
        assert!(checked.iter().all(|&c| c > 100), "{checked:?}");
    }

    /// The lane trust values are `trust_values`' bits, lane by lane: random symmetric inverses
    /// (also indefinite ones, whose variance is clipped at 0), zero and non-finite `g`, no
    /// finite leave-one-out residual, inactive lanes (NaN), 3 to 20 usable lights.
    #[test]
    fn lane_trust_values_match_the_scalar_ones_exactly() {
        use super::super::trust::trust_values;
        let mut next = crate::multigrid::tests::lcg(11);
        let mut checked = 0;
        for round in 0..500 {
            let mut residuals = [[0.0f64; LANES]; 4];
            let mut inverse = [[0.0f64; LANES]; 9];
            let mut g = [[0.0f64; LANES]; 3];
            let mut used = [0u32; LANES];
            let mut active = [false; LANES];
            for l in 0..LANES {
                let m: [f64; 6] = crate::lanes(|_| next() - 0.3);
                let sym = [m[0], m[1], m[2], m[1], m[3], m[4], m[2], m[4], m[5]];
                for (j, v) in sym.iter().enumerate() {
                    inverse[j][l] = *v;
                }
                for gi in g.iter_mut() {
                    gi[l] = 2.0 * next() - 1.0;
                }
                match (round + l) % 9 {
                    0 => g.iter_mut().for_each(|gi| gi[l] = 0.0),
                    1 => g[1][l] = f64::NAN,
                    2 => g[0][l] = -0.0,
                    _ => {}
                }
                used[l] = 3 + (next() * 18.0) as u32;
                active[l] = used[l] >= 4 && next() < 0.9;
                residuals[1][l] = if l % 5 == 0 { 0.0 } else { next() };
                residuals[3][l] = (next() * used[l] as f64).floor();
                residuals[2][l] = residuals[3][l] * next();
            }
            let solved = LaneSolved { inverse, g, active };
            let lanes = trust_lanes_dispatch(&residuals, &solved, &used);
            let plain = trust_lanes(&residuals, &solved, &used);
            for l in 0..LANES {
                let scalar = match active[l] {
                    true => trust_values(
                        &[residuals[1][l], 0.0, 0.0],
                        &[solved.inverse(l), Matrix3::zeros(), Matrix3::zeros()],
                        Vector3::zeros() + Vector3::new(g[0][l], g[1][l], g[2][l]),
                        used[l] as usize,
                        1,
                        residuals[2][l],
                        residuals[3][l] as usize,
                    ),
                    false => [f32::NAN; 2],
                };
                for got in [lanes[l], plain[l]] {
                    assert_eq!(
                        got.map(f32::to_bits),
                        scalar.map(f32::to_bits),
                        "{round} {l}"
                    );
                }
                checked += usize::from(scalar[0].is_finite());
            }
        }
        assert!(checked > 1000, "{checked}");
    }

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
                        depths,
                        ..LocalStep::new(
                            &grid,
                            &geometry,
                            Model::Near(&lights),
                            &obs,
                            FitSettings::default(),
                        )
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

    /// Timings of the final pass against a plain local step at 1024 x 1024 facets (pinhole
    /// bumps, 16 of the scene's lights, depths given as the solver gives them):
    /// `cargo test -p nplps --release --features synth --lib final_pass_timings -- --ignored
    /// --nocapture`.
    #[cfg(all(feature = "synth", unix))]
    #[test]
    #[ignore = "timings"]
    fn final_pass_timings() {
        use crate::problem::{ImageStack, InitialDepth, Problem};
        use crate::synth::{Scene, SceneKind, SceneOptions};
        let n = 1024;
        let options = SceneOptions::default().with_pinhole(true);
        let mut scene = Scene::with_options(SceneKind::Bumps, n, 100.0, 200.0, 0, options).unwrap();
        scene.rig.lights.truncate(16);
        let images: Vec<f32> = scene.render().unwrap().iter().map(|&v| v as f32).collect();
        let k = scene.rig.lights.len();
        let stack = ImageStack::new(&images, k, n, n).unwrap();
        let start = InitialDepth::Distance(scene.mean_depth());
        let problem = Problem::new(stack, &scene.rig, Some(&scene.mask), start).unwrap();
        let u = problem.u0.to_vec("u").unwrap();
        let depths: Vec<f64> = u.iter().map(|&x| problem.geometry.depth(x)).collect();
        let step = LocalStep {
            depths: Some(&depths),
            ..LocalStep::new(
                &problem.grid,
                &problem.geometry,
                Model::Near(&scene.rig.lights),
                &problem.obs,
                FitSettings::default(),
            )
        };
        let facets = problem.grid.n_facets();
        let chunk = 1 << 18;
        let mut fits = vec![FacetFit::EMPTY; chunk.min(facets)];
        // CPU time of the process (all threads): steadier than wall time on a shared machine.
        let cpu = || {
            let mut t = libc::timespec {
                tv_sec: 0,
                tv_nsec: 0,
            };
            // SAFETY: clock_gettime only writes the struct we pass.
            unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut t) };
            t.tv_sec as f64 * 1e9 + t.tv_nsec as f64
        };
        let time = |f: &mut dyn FnMut()| {
            let mut t: Vec<f64> = (0..7)
                .map(|_| {
                    let start = cpu();
                    f();
                    (cpu() - start) / facets as f64
                })
                .collect();
            t.sort_by(f64::total_cmp);
            (t[3], t[0])
        };
        let plain = time(&mut || {
            for first in (0..facets).step_by(chunk) {
                let len = (facets - first).min(chunk);
                step.try_run(&u, first, &mut fits[..len]).unwrap();
            }
        });
        // The final pass as the solver runs it (its facet-long fits and trust buffers
        // allocated in each sample: the solver writes onto its outputs instead).
        let last = time(&mut || {
            crate::local::tests::lane_final_pass(&step, &u, None);
        });
        println!(
            "final pass timing: {facets} facets, {k} lights, {} threads: plain exact step \
             {:.1} CPU ns a facet (min {:.1}), final pass {:.1} (min {:.1})",
            rayon::current_num_threads(),
            plain.0,
            plain.1,
            last.0,
            last.1
        );
    }

    /// The vectorized accumulation gives bit for bit the fits of the scalar code (isotropic
    /// lights and LEDs with mu = 1 and 2.3, shadowed and missing observations, a partial last
    /// batch).
    #[test]
    fn lanes_match_the_scalar_fits_exactly() {
        use crate::rig::Rig;
        let (grid, camera, geometry) = crate::local::tests::small_masked_mesh();
        let (h, w) = (grid.height, grid.width);
        let mut lights: Vec<Light> = crate::local::tests::lights();
        lights.push(Light::Point {
            position: [12.0, -8.0, 30.0],
            intensity: [2.0, 3.0, 4.0],
            axis: normalize([-0.2, 0.1, 1.0]),
            mu: 1.0,
        });
        lights.push(Light::Point {
            position: [-9.0, 14.0, 25.0],
            intensity: [3.0, 2.0, 2.5],
            axis: normalize([0.3, -0.2, 1.0]),
            mu: 2.3,
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
        let step = LocalStep::new(
            &grid,
            &geometry,
            Model::Near(&lights),
            &obs,
            FitSettings {
                fast_residual: true,
                ..FitSettings::default()
            },
        );
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
        // per-light sums up to the order of the parallel reduction).
        assert!(exact.lane_lights().is_some());
        let expected = exact.trust(&u).unwrap();
        let (final_fits, maps) = crate::local::tests::lane_final_pass(&exact, &u, None);
        assert_eq!(final_fits, fits);
        assert!(maps.finish().assert_matches(&expected) > 0);
    }
}
