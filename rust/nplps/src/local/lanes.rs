//! The vectorized local step: the grey, unit-weight normal equations and residuals of
//! [`LANES`] facets at once, one SIMD lane per facet, with the lane form of the light model
//! (`LaneLight`). Per lane the sums are those of the scalar code (`Facet::accumulate_grey`,
//! `Facet::sq_residual`), the same operations in the same order, so the fits agree bit for bit.
//! The kernels run compiled for AVX2 when the processor has it (`simd_dispatch!`).

use super::{
    facet_scratch, keep_shape, solve_sums, u16_value, usable_count, FacetFit, LocalStep, Model,
    Observations, Robust, Stored, Sums, Weighting, SCRATCH,
};
use crate::error::Result;
use crate::geometry::quad_centre;
use crate::light::LaneLight;
use crate::memory::try_vec;
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
pub(super) const LANES: usize = 4;

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
    ) -> [FacetFit; LANES] {
        let (grid, geometry, obs) = (self.grid, self.geometry, self.obs);
        let quads: [[[f64; 3]; 4]; LANES] = std::array::from_fn(|l| self.corners(first + l, u));
        let centres: [[f64; 3]; LANES] = std::array::from_fn(|l| quad_centre(&quads[l]));
        let pixels: [usize; LANES] = std::array::from_fn(|l| grid.facets[first + l] as usize);
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
        let sums = accumulate_lanes_dispatch(
            lights,
            &centres,
            interleaved,
            self.settings.dark,
            self.settings.saturation,
        );
        let mut fitted: [Option<FacetFit>; LANES] = std::array::from_fn(|l| grey_fit(&sums[l]));
        if !self.settings.fast_residual {
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
            let ids = grid.facet_vertices[f];
            match fitted[l] {
                Some(fitted) => FacetFit {
                    target: geometry.plane_target(fitted.normal, ids, centres[l]),
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

/// The fit of grey, unit-weight, plain sums with the residual from the normal equations (as
/// [`fit_facet`](super::fit_facet) computes it for those settings); the target is left at zero.
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
    /// [`accumulate_lanes`] with AVX2 when the processor has it (same arithmetic, wider lanes).
    fn accumulate_lanes_dispatch => accumulate_lanes(
        lights: &[LaneLight],
        centres: &[[f64; 3]; LANES],
        values: &[[f32; LANES]],
        dark: f64,
        saturation: f64,
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
/// the lanes in SIMD registers.
#[inline(always)]
fn accumulate_lanes(
    lights: &[LaneLight],
    centres: &[[f64; 3]; LANES],
    values: &[[f32; LANES]],
    dark: f64,
    saturation: f64,
) -> [Sums; LANES] {
    let mut t = [[0.0f64; LANES]; 6];
    let mut s = [[0.0f64; LANES]; 3];
    let mut sum_i2 = [0.0f64; LANES];
    let mut used = [0u32; LANES];
    for (light, v) in lights.iter().zip(values) {
        let p = light.grey;
        let (i, ok) = lane_values(v, dark, saturation);
        let ([a0, a1, a2], f) = light.beta(centres);
        let r0: [f64; LANES] = std::array::from_fn(|l| a0[l] * f[l] * p);
        let r1: [f64; LANES] = std::array::from_fn(|l| a1[l] * f[l] * p);
        let r2: [f64; LANES] = std::array::from_fn(|l| a2[l] * f[l] * p);
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
    /// [`residual_lanes`] with AVX2 when the processor has it (same arithmetic, wider lanes).
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Geometry;
    use crate::grid::Grid;
    use crate::light::Light;
    use crate::local::{FacetStat, FitSettings};
    use crate::reflectance::Packed;
    use crate::vec3::normalize;

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
        assert!(n % LANES != 0);
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
    }
}
