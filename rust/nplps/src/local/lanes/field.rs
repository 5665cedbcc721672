//! The vectorized local step with a field of indirect light (issue 21): the fits of
//! [`LocalStep::fit_indirect`](super::super::LocalStep) for [`LANES`] facets at once, one SIMD
//! lane per facet, bit for bit.
//!
//! With the indirect irradiance vectors `V_k` of a facet (see [`crate::indirect`]) the model of
//! light `k` stays linear in the scaled normal `b = rho n`:
//!
//! ```text
//! I_k = b . (d_k s_k + V_k),   s_k = Phi_k beta_k(c),
//! ```
//!
//! `d_k = 1` where the direct light reaches the facet, 0 where it does not (a cast shadow of
//! the mask, or a light behind the facet or hidden by the margin, [`IndirectLight::is_unlit`]);
//! such observations are kept, with their indirect light alone. The normal equations are those
//! of the Lambertian lanes with the row `r_k = d_k s_k + V_k` instead of `s_k`:
//! `T = sum r_k r_k^T`, `t = sum r_k I_k` over the usable observations; the fit needs at
//! least 3 directly lit ones (`sum d_k >= 3`). Per lane these are the operations of the scalar
//! code (`Facet::accumulate` with unit weights and one channel, `Facet::sq_residual`,
//! `solve_sums`) in its order, so the fits agree bit for bit (test
//! `field_lanes_match_the_scalar_fits_exactly`); the lights' `beta` (the powers and roots of
//! the near-light model) run in the lanes, the field's lookup stays per facet.
//!
//! Applies where the Lambertian lanes do (grey images, unit weights, no robust fit, lights with
//! a lane form) and a field is set; colour images keep the scalar fits.

use std::cell::RefCell;

use super::{lane_values, solve_lanes, LaneSums, LANES};
use crate::geometry::{quad_centre, Geometry};
use crate::light::LaneLight;
use crate::local::{keep_shape, FacetFit, IndirectLight, LocalStep, Model, Robust, Weighting};

/// One light's field in [`LANES`] facets: the vector `V` of each lane (components, lanes) and
/// whether its direct light reaches the lane's facet.
#[derive(Debug, Clone, Copy)]
pub(crate) struct FieldRow {
    pub(crate) v: [[f64; LANES]; 3],
    pub(crate) direct: [bool; LANES],
}

impl FieldRow {
    /// Zero vectors, no direct light.
    pub(crate) const EMPTY: FieldRow = FieldRow {
        v: [[0.0; LANES]; 3],
        direct: [false; LANES],
    };
}

impl LocalStep<'_> {
    /// The lights of the vectorized fits with a field of indirect light
    /// ([`LocalStep::fit_field_lanes`]): as [`LocalStep::lane_lights`] (grey images, unit
    /// weights, no robust fit, no lobe, lights with a lane form) where a field is set; None
    /// without one.
    pub(in crate::local) fn field_lane_lights(&self) -> Option<Vec<LaneLight>> {
        let s = self.settings;
        let eligible = self.indirect.is_some()
            && self.obs.channels == 1
            && s.weighting == Weighting::Image
            && s.robust == Robust::None
            && s.lobe.is_none();
        let Model::Near(lights) = self.model else {
            return None;
        };
        if !eligible {
            return None;
        }
        lights.iter().map(LaneLight::from_light).collect()
    }

    /// The lights of the vectorized fits of this step, with or without a field (see
    /// [`LocalStep::lane_lights`], [`LocalStep::field_lane_lights`]).
    pub(in crate::local) fn batch_lights(&self) -> Option<Vec<LaneLight>> {
        self.lane_lights().or_else(|| self.field_lane_lights())
    }

    /// Fits facets `first..first + LANES` with the field `field` in the lanes: the fits of
    /// the scalar `LocalStep::fit_indirect`, bit for bit (see the module documentation).
    pub(in crate::local) fn fit_field_lanes(
        &self,
        lights: &[LaneLight],
        first: usize,
        u: &[f64],
        buf: &mut [f32],
        interleaved: &mut [[f32; LANES]],
        field: &dyn IndirectLight,
    ) -> [FacetFit; LANES] {
        thread_local! {
            static SCRATCH: RefCell<Vec<FieldRow>> = const { RefCell::new(Vec::new()) };
        }
        let (grid, geometry, obs) = (self.grid, self.geometry, self.obs);
        let k = obs.k;
        let pixels: [usize; LANES] = crate::lanes(|l| grid.facets[first + l] as usize);
        let batch = self.batch_corners(first, &pixels, u);
        let quads = &batch.quads;
        let centres: [[f64; 3]; LANES] = crate::lanes(|l| quad_centre(&quads[l]));
        // The observations as they are (those in a cast shadow keep their indirect light).
        if !obs.gather_lanes(&pixels, interleaved) {
            for (l, &pixel) in pixels.iter().enumerate() {
                let values = obs.facet(pixel, buf);
                for (slot, &v) in interleaved.iter_mut().zip(values) {
                    slot[l] = v;
                }
            }
        }
        SCRATCH.with_borrow_mut(|rows| {
            rows.clear();
            rows.resize(k, FieldRow::EMPTY);
            for (l, &pixel) in pixels.iter().enumerate() {
                field.lane_into(pixel, grid.width, l, rows);
                if let Some(shadows) = self.shadows {
                    for j in shadows.lights_at(pixel) {
                        rows[j].direct[l] = false;
                    }
                }
            }
            let thresholds = (self.settings.dark, self.settings.saturation);
            let (sums, lit) =
                accumulate_field_dispatch(lights, &centres, interleaved, rows, thresholds);
            let solved = solve_field_dispatch(&sums, &centres, &batch.base, geometry);
            let valid: [bool; LANES] = crate::lanes(|l| solved.valid[l] && lit[l] >= 3);
            let mut sse = solved.sse;
            if !self.settings.fast_residual {
                let normals: [[f64; 3]; LANES] = crate::lanes(|l| match valid[l] {
                    true => [
                        solved.normal[0][l],
                        solved.normal[1][l],
                        solved.normal[2][l],
                    ],
                    false => [0.0; 3],
                });
                let albedo: [f64; LANES] =
                    crate::lanes(|l| if valid[l] { solved.rho[l] } else { 0.0 });
                sse = residual_field_dispatch(
                    lights,
                    &centres,
                    interleaved,
                    rows,
                    thresholds,
                    &normals,
                    &albedo,
                );
            }
            std::array::from_fn(|l| match valid[l] {
                true => FacetFit {
                    target: solved.target[l],
                    normal: [
                        solved.normal[0][l],
                        solved.normal[1][l],
                        solved.normal[2][l],
                    ],
                    albedo: [solved.rho[l]; 3],
                    specular: 0.0,
                    sse: sse[l],
                    used: sums.used[l],
                    valid: true,
                },
                false => keep_shape(&quads[l], batch.ids[l].map(|i| u[i as usize]), sums.used[l]),
            })
        })
    }
}

simd_dispatch! {
    wide
    /// [`accumulate_field`] with AVX-512 or AVX2 when the processor has it (same arithmetic).
    fn accumulate_field_dispatch => accumulate_field(
        lights: &[LaneLight],
        centres: &[[f64; 3]; LANES],
        values: &[[f32; LANES]],
        field: &[FieldRow],
        thresholds: (f64, f64),
    ) -> (LaneSums, [u32; LANES]);
}

simd_dispatch! {
    wide
    /// [`solve_lanes`] dispatched for the field's fits.
    fn solve_field_dispatch => solve_lanes(
        sums: &LaneSums,
        centres: &[[f64; 3]; LANES],
        base: &[[[f64; 2]; 4]; LANES],
        geometry: &Geometry,
    ) -> super::LaneSolution;
}

/// The normal equations of [`LANES`] facets with their field (see the module documentation):
/// per lane the operations of `Facet::accumulate` with one channel and unit weights, in its
/// order (`r = (d b) p + V`, `T += (1 r) r`, `t += (1 r) I`). Returns the sums and, per lane,
/// the usable observations that the direct light reaches.
#[inline(always)]
fn accumulate_field(
    lights: &[LaneLight],
    centres: &[[f64; 3]; LANES],
    values: &[[f32; LANES]],
    field: &[FieldRow],
    (dark, saturation): (f64, f64),
) -> (LaneSums, [u32; LANES]) {
    let mut t = [[0.0f64; LANES]; 6];
    let mut s = [[0.0f64; LANES]; 3];
    let mut sum_i2 = [0.0f64; LANES];
    let mut used = [0u32; LANES];
    let mut lit = [0u32; LANES];
    for ((light, v), row) in lights.iter().zip(values).zip(field) {
        let p = light.grey;
        let (i, ok) = lane_values(v, dark, saturation);
        let ([a0, a1, a2], f) = light.beta(centres);
        let d = &row.direct;
        let b = |a: &[f64; LANES], l: usize| if d[l] { a[l] * f[l] } else { 0.0 };
        let r0: [f64; LANES] = crate::lanes(|l| b(&a0, l) * p + row.v[0][l]);
        let r1: [f64; LANES] = crate::lanes(|l| b(&a1, l) * p + row.v[1][l]);
        let r2: [f64; LANES] = crate::lanes(|l| b(&a2, l) * p + row.v[2][l]);
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
            lit[l] += u32::from(ok[l] && d[l]);
        }
    }
    (LaneSums { t, s, sum_i2, used }, lit)
}

simd_dispatch! {
    wide
    /// [`residual_field`] with AVX-512 or AVX2 when the processor has it (same arithmetic).
    fn residual_field_dispatch => residual_field(
        lights: &[LaneLight],
        centres: &[[f64; 3]; LANES],
        values: &[[f32; LANES]],
        field: &[FieldRow],
        thresholds: (f64, f64),
        normals: &[[f64; 3]; LANES],
        albedo: &[f64; LANES],
    ) -> [f64; LANES];
}

/// The summed squared image residuals of [`LANES`] fits `(normals, albedo)` with their field
/// over their usable observations: per lane the operations of `Facet::sq_residual`
/// (`e = rho (p (n . d b) + n . V) - I`), in its order.
#[inline(always)]
fn residual_field(
    lights: &[LaneLight],
    centres: &[[f64; 3]; LANES],
    values: &[[f32; LANES]],
    field: &[FieldRow],
    (dark, saturation): (f64, f64),
    normals: &[[f64; 3]; LANES],
    albedo: &[f64; LANES],
) -> [f64; LANES] {
    let mut sse = [0.0f64; LANES];
    for ((light, v), row) in lights.iter().zip(values).zip(field) {
        let p = light.grey;
        let (i, ok) = lane_values(v, dark, saturation);
        let ([a0, a1, a2], f) = light.beta(centres);
        for l in 0..LANES {
            let n = normals[l];
            let nb = match row.direct[l] {
                true => n[0] * (a0[l] * f[l]) + n[1] * (a1[l] * f[l]) + n[2] * (a2[l] * f[l]),
                false => 0.0,
            };
            let nv = n[0] * row.v[0][l] + n[1] * row.v[1][l] + n[2] * row.v[2][l];
            let e = albedo[l] * (p * nb + nv) - i[l];
            sse[l] += if ok[l] { e * e } else { 0.0 };
        }
    }
    sse
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Grid;
    use crate::light::Light;
    use crate::local::{FacetStat, FitSettings, Observations};
    use crate::reflectance::Packed;
    use crate::rig::Camera;
    use crate::shadow::ShadowMask;
    use crate::vec3::normalize;

    /// A field of made-up vectors: some zero, some along the facets, some against them, and
    /// lights behind some facets.
    struct Field {
        k: usize,
    }

    impl IndirectLight for Field {
        fn is_unlit(&self, p: usize, k: usize) -> bool {
            (3 * p + k).is_multiple_of(7)
        }

        fn at_into(&self, p: usize, _width: usize, out: &mut Vec<[f64; 3]>) {
            out.clear();
            out.extend((0..self.k).map(|k| match (p + 2 * k) % 5 {
                0 => [0.0; 3],
                1 => [-0.3e-6, 0.2e-6, -(p as f64) * 1e-7],
                _ => [1e-6 * k as f64, -2e-7 * (p % 3) as f64, 3e-6],
            }));
        }
    }

    /// With a field of indirect light (lights behind facets, a cast-shadow mask whose
    /// observations keep their indirect light, dark and missing observations, facets left with
    /// fewer than 3 directly lit observations, a partial last batch), pinhole and orthographic,
    /// the fast and the exact residual: the lanes give the scalar fits bit for bit.
    #[test]
    fn field_lanes_match_the_scalar_fits_exactly() {
        let (h, w) = (9, 19);
        let mask: Vec<bool> = (0..h * w).map(|p| p % 11 != 4).collect();
        let cameras = [
            Camera::Orthographic {
                pixel_size: [1.5, 1.5],
                origin: [-5.0, -7.0],
            },
            Camera::Pinhole {
                k: [[60.0, 0.0, 9.0], [0.0, 55.0, 2.0], [0.0, 0.0, 1.0]],
                distortion: [0.0; 5],
            },
        ];
        let mut lights: Vec<Light> = crate::local::tests::lights();
        lights.push(Light::Point {
            position: [12.0, -8.0, 30.0],
            intensity: [2.0, 3.0, 4.0],
            axis: normalize([-0.2, 0.1, 1.0]),
            mu: 1.0,
        });
        let k = lights.len();
        let mut data = vec![0.0f32; k * h * w];
        for (i, x) in data.iter_mut().enumerate() {
            *x = match i % 17 {
                0 => 0.0,
                3 => f32::NAN,
                _ => 1e-4 * (1.0 + ((i * 31) % 13) as f32),
            };
        }
        let obs = Observations::from_stack(&data, k, h * w, 1);
        let shadows = ShadowMask::from_fn(h, w, k, |p, j| (p + 5 * j).is_multiple_of(4));
        let field = Field { k };
        let (mut valid, mut invalid) = (0, 0);
        for camera in &cameras {
            let grid = Grid::new(h, w, Some(&mask)).unwrap();
            let geometry = Geometry::new(camera, &grid).unwrap();
            let u: Vec<f64> = grid
                .active
                .iter()
                .map(|&v| {
                    let z = 100.0 + 0.3 * (v % 8) as f64 - 0.2 * (v / 8) as f64
                        + 0.05 * ((v * 7) % 5) as f64;
                    geometry.unknown(z)
                })
                .collect();
            for (fast_residual, shadowed) in [(true, true), (false, true), (false, false)] {
                let step = LocalStep {
                    shadows: shadowed.then_some(&shadows),
                    indirect: Some(&field),
                    ..LocalStep::new(
                        &grid,
                        &geometry,
                        Model::Near(&lights),
                        &obs,
                        FitSettings {
                            fast_residual,
                            ..FitSettings::default()
                        },
                    )
                };
                assert!(step.lane_lights().is_none());
                assert!(step.field_lane_lights().is_some());
                let n = grid.n_facets();
                assert!(!n.is_multiple_of(LANES));
                let mut fits = vec![FacetFit::EMPTY; n];
                step.run(&u, 0, &mut fits);
                let mut targets = vec![[0.0; 4]; n];
                let mut stats = vec![FacetStat::default(); n];
                step.run_targets(&u, &mut targets, &mut stats);
                let mut buf = vec![0.0f32; k];
                for f in 0..n {
                    let fit = step.fit(f, &u, &mut buf, &mut Packed::new(), None);
                    let bits = |x: &FacetFit| {
                        (
                            x.target.map(f64::to_bits),
                            x.normal.map(f64::to_bits),
                            x.albedo.map(f64::to_bits),
                            x.sse.to_bits(),
                            x.used,
                            x.valid,
                        )
                    };
                    assert_eq!(bits(&fit), bits(&fits[f]), "facet {f}");
                    assert_eq!(fit.target, targets[f], "facet {f}");
                    assert_eq!(FacetStat::from(&fit), stats[f], "facet {f}");
                    match fit.valid {
                        true => valid += 1,
                        false => invalid += 1,
                    }
                }
                // The field changes the fits (it is used).
                let plain = LocalStep {
                    indirect: None,
                    ..step
                };
                let mut plain_fits = vec![FacetFit::EMPTY; n];
                plain.run(&u, 0, &mut plain_fits);
                assert_ne!(plain_fits, fits);
            }
        }
        assert!(valid > 100 && invalid > 0, "{valid} {invalid}");
    }
}
