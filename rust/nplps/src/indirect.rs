//! Interreflections: the indirect irradiance that the facets of a height-field mesh send to each
//! other, gathered from the observed images (issue 21). [`Exchange`] is the light exchange of a
//! mesh; [`IndirectField`] is what the solver uses with
//! [`Options::interreflections`](crate::Options::interreflections): the exchange of its current
//! mesh on a coarse grid, looked up per fine facet.
//!
//! ## The model
//!
//! The image model of the crate (see [`crate::Light`]) is `I = rho * Phi * max(0, n . beta(x))`:
//! with `E = Phi n . beta(x)` the irradiance that the light sends to the surface point, an image
//! value is `I = rho E`, the albedo times the irradiance. For a Lambertian surface of reflectance
//! `rho` the exitance (radiosity) is `B = rho E` and the radiance is `L = B / pi`, the same in
//! every direction: the image value is the exitance, and the radiance of facet `j` under light
//! `k` is `L_jk = I_jk / pi`.
//!
//! A small facet `j` (centre `x_j`, unit normal `n_j`, area `A_j`) of radiance `L_j` gives the
//! point `x_i` with normal `n_i` the irradiance
//!
//! ```text
//! dE_ij = L_j A_j cos_i cos_j / r^2 = n_i . (L_j A_j cos_j / r^2 d_ij),
//! d_ij = (x_j - x_i) / r,  r = |x_j - x_i|,  cos_i = n_i . d_ij,  cos_j = -n_j . d_ij,
//! ```
//!
//! when both face each other (`cos_i > 0`, `cos_j > 0`) and the segment between them is not
//! blocked by the surface (`vis_ij`). Summed over the facets, the irradiance at facet `i` under
//! light `k` is `n_i . (Phi_k beta_k(x_i) + V_ik)`, and the image model with indirect light
//! stays linear in the scaled normal `b = rho n`:
//!
//! ```text
//! I_ik = b_i . (s_ik + V_ik),   s_ik = Phi_k beta_k(x_i),
//! V_ik = sum_j I_jk w_ij,       w_ij = vis_ij A_j cos_j / (pi r_ij^2) d_ij,
//! ```
//!
//! the *irradiance vector* `V_ik` of facet `i` (the same units as `s_ik`). `n_i . w_ij` is the
//! point-to-facet form factor `F_ij = A_j cos_i cos_j / (pi r^2)`, and the reciprocity
//! `A_i F_ij = A_j F_ji` holds for every pair. Gathering the **observed** images `I_jk`, which
//! hold all the light that facet `j` sends (its direct light and its own indirect light), gives
//! all the bounces at once, with no iteration over bounces; it assumes Lambertian emitters (with a
//! glossy model, emit the modelled diffuse part instead) and misses the light of surfaces that
//! the image does not show (outside the mask, or hidden from the camera). Where the surface
//! reaches the image border, [`IndirectField`] continues its coarse mesh past it by linear
//! prediction and lets that margin emit what the image model predicts for it (its albedo from
//! the border facet, its direct light from the rig, cut by the cast shadows on the extended
//! mesh, and its own gathered light): see `IndirectField::of_mesh`.
//!
//! `V` is linear in the observations and assumes the rig's intensities in the units that make the
//! albedo the reflectance (a white facet facing a unit light at unit distance images to 1). When
//! the fitted albedo is `g` times the reflectance (intensities known up to a factor), the
//! indirect term of the model is `V / g`: pass the observations divided by `g`.
//!
//! ## Near pairs
//!
//! The point formula is accurate when the facets are small beside their distance; next to a
//! crease it is not (a facet and its neighbour across a 90-degree groove: +4 %). For pairs nearer
//! than [`NEAR`] facet sizes (`r^2 < NEAR^2 max(A_i, A_j)`), `w_ij` is instead the mean, over
//! [`SUBDIVISIONS`]² points `y_a` of the receiver (the centres of its bilinear sub-facets), of the
//! emitter's exact vector
//!
//! ```text
//! (1 / pi) int_{A_j} cos_j d / r^2 dA = (1 / (2 pi)) sum_e theta_e g_e
//! ```
//!
//! (Lambert's formula for a polygon, Arvo 1994: `theta_e` the angle that edge `e` of the quad
//! subtends at `y_a`, `g_e` the unit normal of the plane through `y_a` and the edge, oriented
//! towards the quad; exact for any surface spanned by the quad's 4 straight edges, e.g. its
//! bilinear patch, seen wholly from the front). Points `y_a` behind the emitter's plane get
//! nothing. The two directions of a pair are two quadratures of one double integral,
//! `A_i F_ij` and `A_j F_ji` (they differ by 0.2 % in the median on a bowl, more for twisted
//! quads): both are set to their mean `m`, which keeps the reciprocity exact, by the smallest
//! change of each vector that does it, along its receiver's normal:
//!
//! ```text
//! w_ij <- w_ij + n_i (m - A_i n_i . w_ij) / A_i,   m = (A_i n_i . w_ij + A_j n_j . w_ji) / 2,
//! ```
//!
//! so that `|w_ij| <= 1 + A_j / (2 A_i)` (`|w_ij| <= 1` before: the vector of a solid angle
//! within a hemisphere). Scaling the vector by `m / (A_i n_i . w_ij)` instead (before issue 21's
//! third helper) blew up the pairs whose receiver sees the emitter nearly edge-on: on the
//! corrugated sheet's coarse mesh, `A_i n_i . w_ij` a few hundredths of `m`, vectors 10-60 times
//! the bound along the receiver's surface, and the fitted normals of those facets followed them
//! (the "pits": a two-cycle of the iteration, see `Solver::interreflect`). A near pair with a
//! form factor that is not positive in either direction is dropped.
//!
//! ## Visibility
//!
//! The facets are the pixels of an (H+1) x (W+1) vertex mesh seen by the camera (a height field:
//! every point of space nearer the camera than the surface along its camera ray is free). Facets
//! `i` and `j` see each other when they face each other at their centres
//! (`n_i . (x_j - x_i) > COS_MIN r` and `n_j . (x_i - x_j) > COS_MIN r`, [`COS_MIN`]) and the
//! segment between the centres stays in front of the surface: sampled half a pixel apart in the
//! image as the shadow march of [`crate::shadow`] does (the perspective-correct point of image
//! parameter `s`, projected with the camera's distortion; without distortion the image point is
//! interpolated on the line between the projected ends and the depth is `1 / ((1 - s) / z_i +
//! s / z_j)`, pinhole, or linear, orthographic), it is blocked at the first sample
//! where the bilinear surface depth is nearer than the segment's,
//! `z_surface < z(s) - (1e-6 |z(s)| + 1e-3 sqrt(max(A_i, A_j)))`. Samples in the two end pixels
//! are not tested (a planar facet does not hide what it faces), and samples over pixels outside
//! the mask or with a non-finite corner neither block nor end the march (the surface there is
//! unknown). Visibility is symmetric: each unordered pair is marched once. Without distortion
//! the march computes the image points and hiding depths of 8 samples at a time in SIMD lanes
//! (`clearance_lanes`: the same operations, the same values) and tests them in turn (with a
//! one-pass marking of the last gathering, the benchmark's corrugated sheet with
//! `interreflections=True` took about 13 % less processor time; docs/concave.md, stop 46).
//!
//! A blocked pair's march ends at its first blocking sample. Every exchange marches all its
//! facing pairs afresh: up to stop 54 the solver's rounds kept each pair's verdict for the next
//! round's exchange (with the clearance that bounded how far the mesh could move before it
//! changed), but after their over-relaxed step the meshes moved too far for most of them and
//! keeping them cost more than it saved (docs/concave.md, stops 54 and 55).
//!
//! ## Cost and memory
//!
//! With `F` masked facets (e.g. `F <= 64^2` on a coarse level of the pyramid), building tests
//! the `F (F - 1) / 2` unordered pairs (facing test: a few flops each) and marches the facing
//! ones, `O(D)` samples each (`D` the image diagonal in pixels): `O(F^2 D)` time in the worst
//! case, `O(F^2)` on surfaces where few pairs face each other, parallel over the facets. Near
//! pairs cost `2 S^2` = 32 evaluations of the edge formula each (4 edge angles each: the
//! receiver's sub-points run in SIMD lanes with a branch-free `atan`, see `near_weight`),
//! `O(F NEAR^2)` of them. It is
//! computed once per geometry.
//!
//! The pairs are stored sparsely, by receiver (compressed rows): a `u32` source facet and the
//! weight vector as 3 `f32`, [`BYTES_PER_PAIR`] = 16 bytes per directed pair (each facing, visible
//! unordered pair gives two), plus 8 bytes per pixel of row offsets and 56 bytes per pixel of
//! facet geometry. While building, the unordered pairs are also held in per-row lists
//! (28 bytes each, 14 per directed pair): the peak is about 30 bytes per directed pair. The dense
//! worst case at 64² facets is `F (F - 1)` = 16.8 M directed pairs (268 MB); the count is capped
//! (`max_pairs`, default [`DEFAULT_MAX_PAIRS`] = 4 M directed pairs, 67 MB) and building fails
//! with an error that names the cap beyond it (use a coarser grid, or raise the cap). The
//! march reads the cells' corner depths from one array (32 bytes per pixel).
//!
//! The pass over the lights ([`Exchange::irradiance`]) costs `O(P k C)` multiply-adds for `P`
//! directed pairs, `k` lights and `C` channels, parallel over the receivers; it holds the
//! observations transposed to facet-major order (`4 F k C` bytes) and the result (`24 H W k C`
//! bytes, and as much again while it is reordered).
//!
//! Measured (test `timings`, 2 busy cores, release): the benchmark's bowl at 64² pixels, 1492
//! facets in its mask, all of which see each other: 2.2 M directed pairs (36 MB), built in
//! 0.9-1.2 s (the march is 3/4 of it); a pass of 16 lights 0.03 s. At 32² (356 facets): 126 k
//! pairs, 0.07-0.1 s, 0.002 s.

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use rayon::prelude::*;

use crate::error::{ensure_mask, ensure_shape, ensure_usable, Error, Result};
use crate::rig::Camera;
use crate::shadow::{hiding_depth, segment_point, March};
use crate::vec3::{cross, dot, norm, not_above, sub};

/// Pairs nearer than `NEAR` facet sizes (`r^2 < NEAR^2 max(A_i, A_j)`) get the subdivided
/// (area-averaged) weight instead of the point formula.
pub const NEAR: f64 = 4.0;

/// Receiver points per side of a facet in the weight of a near pair (`SUBDIVISIONS`² points).
pub const SUBDIVISIONS: usize = 4;

/// Smallest cosine at both centres for a pair to count as facing.
pub const COS_MIN: f64 = 1e-6;

/// Bytes of one stored directed pair: a `u32` source facet and 3 `f32` weights.
pub const BYTES_PER_PAIR: usize = 16;

/// Default cap on the stored directed pairs (4 M, 67 MB).
pub const DEFAULT_MAX_PAIRS: usize = 1 << 22;

/// The geometry of a facet: centre, unit normal, area, corners.
#[derive(Debug, Clone, Copy)]
struct Facet {
    centre: [f64; 3],
    normal: [f64; 3],
    area: f64,
    corners: [[f64; 3]; 4],
}

/// The exchange of light between the facets of a mesh: per receiver facet, the facets it sees
/// and their weight vectors `w_ij` (see the module documentation), stored by receiver.
#[derive(Debug, Clone)]
pub struct Exchange {
    height: usize,
    width: usize,
    /// Per pixel `p`: its pairs are `offsets[p]..offsets[p + 1]`.
    offsets: Vec<usize>,
    /// The source (emitter) pixel of each pair, increasing within a row.
    sources: Vec<u32>,
    /// The weight vector `w_ij` of each pair.
    weights: Vec<[f32; 3]>,
    /// Per pixel: centre, unit normal and area (NaN outside the mask or the finite vertices).
    facets: Vec<([f64; 3], [f64; 3], f64)>,
    /// Facing pairs (unordered) whose visibility was marched while it was built.
    marched: usize,
}

impl Exchange {
    /// The exchange between the facets (pixels) of `mask` (H x W; None: all) of the mesh with
    /// the vertex positions `vertices` ((H+1) x (W+1), camera frame, as [`crate::vertices`]
    /// makes them; facets with a non-finite corner take no part), seen by `camera`. At most
    /// `max_pairs` directed pairs (None: [`DEFAULT_MAX_PAIRS`]); more is an error that names
    /// the cap.
    pub fn new(
        camera: &Camera,
        height: usize,
        width: usize,
        vertices: &[[f64; 3]],
        mask: Option<&[bool]>,
        max_pairs: Option<usize>,
    ) -> Result<Exchange> {
        let plane = height * width;
        ensure_usable(plane > 0, || "the mesh has no facets".to_string())?;
        ensure_shape(
            "vertices",
            (height + 1) * (width + 1),
            vertices.len(),
            || {
                format!(
                    "vertices has {} positions, expected (W+1) x (H+1) = {} x {}",
                    vertices.len(),
                    width + 1,
                    height + 1
                )
            },
        )?;
        ensure_mask(mask, plane)?;
        let max_pairs = max_pairs.unwrap_or(DEFAULT_MAX_PAIRS);
        let march = March {
            camera,
            height,
            width,
            vertices: crate::shadow::Vertices::Positions(vertices),
            mask,
            z_min: f64::NEG_INFINITY,
            max_steps: usize::MAX / 4,
            pyramid: None,
        };
        let geometry: Vec<Option<Facet>> = crate::memory::try_par_collect(
            (0..plane).into_par_iter().map(|p| {
                let (centre, normal, _) = march.facet(p)?;
                let q = march.quad(p / width, p % width);
                let area = 0.5 * norm(cross(sub(q[2], q[1]), sub(q[3], q[0])));
                (area > 0.0 && normal.iter().all(|x| x.is_finite())).then_some(Facet {
                    centre,
                    normal,
                    area,
                    corners: q,
                })
            }),
            "the facets of the light exchange",
        )?;
        let projected: Vec<[f64; 2]> = crate::memory::try_par_collect(
            geometry.par_iter().map(|f| match f {
                Some(f) => camera.project(f.centre),
                None => [f64::NAN; 2],
            }),
            "the facets of the light exchange",
        )?;

        let depths = CellDepths::new(&march)?;
        // The unordered pairs (i < j) per row i: (j, w_ij, w_ji).
        let (count, marched) = (AtomicUsize::new(0), AtomicUsize::new(0));
        let over = AtomicBool::new(false);
        type Row = Vec<(u32, [f32; 3], [f32; 3])>;
        let rows: Vec<Row> = (0..plane)
            .into_par_iter()
            .with_max_len(1)
            .map(|i| {
                let mut row = Row::new();
                if over.load(Ordering::Relaxed) {
                    return row;
                }
                let Some(fi) = geometry[i] else {
                    return row;
                };
                let mut facing = 0;
                for (j, fj) in geometry.iter().enumerate().skip(i + 1) {
                    let Some(fj) = fj else { continue };
                    let d = sub(fj.centre, fi.centre);
                    let r = norm(d);
                    if !(dot(fi.normal, d) > COS_MIN * r && -dot(fj.normal, d) > COS_MIN * r) {
                        continue;
                    }
                    let tol = 1e-3 * fi.area.max(fj.area).sqrt();
                    let ceiling = march_length(projected[i], projected[j]);
                    facing += 1;
                    let (a, b) = ((i, &fi, projected[i]), (j, fj, projected[j]));
                    if clearance(&march, &depths, a, b, ceiling, tol) < 0.0 {
                        continue;
                    }
                    let Some((wij, wji)) = pair_weights(&fi, fj) else {
                        continue;
                    };
                    row.push((j as u32, wij.map(|x| x as f32), wji.map(|x| x as f32)));
                }
                marched.fetch_add(facing, Ordering::Relaxed);
                if count.fetch_add(2 * row.len(), Ordering::Relaxed) + 2 * row.len() > max_pairs {
                    over.store(true, Ordering::Relaxed);
                }
                row
            })
            .collect();
        let total = count.load(Ordering::Relaxed);
        if over.load(Ordering::Relaxed) {
            return Err(Error::Unusable(format!(
                "the light exchange of {} facets has more than max_pairs = {max_pairs} directed \
                 pairs of facets that see each other ({} bytes each): use a coarser grid or raise \
                 the cap",
                geometry.iter().flatten().count(),
                BYTES_PER_PAIR
            )));
        }
        crate::memory::check(
            || format!("the light exchange of {total} pairs of facets"),
            (BYTES_PER_PAIR * total + 8 * (plane + 1)) as f64,
            None,
        )?;

        // Compressed rows by receiver: row p holds the pairs of earlier rows (i < p, in order),
        // then its own (j > p, in order).
        let mut offsets = crate::memory::try_vec(plane + 1, 0usize, "the light exchange")?;
        for (i, row) in rows.iter().enumerate() {
            offsets[i + 1] += row.len();
            for &(j, _, _) in row {
                offsets[j as usize + 1] += 1;
            }
        }
        for p in 0..plane {
            offsets[p + 1] += offsets[p];
        }
        let mut sources = crate::memory::try_vec(total, 0u32, "the light exchange")?;
        let mut weights = crate::memory::try_vec(total, [0f32; 3], "the light exchange")?;
        let mut next: Vec<usize> = offsets[..plane].to_vec();
        for (i, row) in rows.into_iter().enumerate() {
            for (j, wij, wji) in row {
                let j = j as usize;
                sources[next[i]] = j as u32;
                weights[next[i]] = wij;
                next[i] += 1;
                sources[next[j]] = i as u32;
                weights[next[j]] = wji;
                next[j] += 1;
            }
        }
        let facets = geometry
            .iter()
            .map(|f| match f {
                Some(f) => (f.centre, f.normal, f.area),
                None => ([f64::NAN; 3], [f64::NAN; 3], f64::NAN),
            })
            .collect();
        Ok(Exchange {
            height,
            width,
            offsets,
            sources,
            weights,
            facets,
            marched: marched.load(Ordering::Relaxed),
        })
    }

    /// Image height H (facet rows).
    pub fn height(&self) -> usize {
        self.height
    }

    /// Image width W (facet columns).
    pub fn width(&self) -> usize {
        self.width
    }

    /// Facing pairs (unordered) whose visibility was marched while it was built (all of them).
    pub fn marched(&self) -> usize {
        self.marched
    }

    /// Number of stored directed pairs.
    pub fn pairs(&self) -> usize {
        self.sources.len()
    }

    /// Bytes held: [`BYTES_PER_PAIR`] per pair, the row offsets and the facet geometry.
    pub fn bytes(&self) -> usize {
        BYTES_PER_PAIR * self.pairs()
            + std::mem::size_of::<usize>() * self.offsets.len()
            + std::mem::size_of::<([f64; 3], [f64; 3], f64)>() * self.facets.len()
    }

    /// The pairs of receiver pixel `p`: (source pixel `j`, weight vector `w_pj`), by increasing
    /// `j`.
    pub fn pairs_of(&self, p: usize) -> impl Iterator<Item = (usize, [f32; 3])> + '_ {
        let range = self.offsets[p]..self.offsets[p + 1];
        self.sources[range.clone()]
            .iter()
            .zip(&self.weights[range])
            .map(|(&j, &w)| (j as usize, w))
    }

    /// Centre, unit normal and area of facet (pixel) `p` (NaN where it takes no part).
    pub fn facet(&self, p: usize) -> ([f64; 3], [f64; 3], f64) {
        self.facets[p]
    }

    /// The indirect irradiance vectors `V_ik = sum_j I_jk w_ij` of every pixel under every light
    /// from the observations `observed`, (k, H, W, C) with `C = channels` (the layout of an
    /// image stack). Non-finite observations emit nothing. The result has the same layout,
    /// one vector per value: (k, H, W, C); zero at pixels that see no other facet.
    pub fn irradiance(
        &self,
        observed: &[f32],
        lights: usize,
        channels: usize,
    ) -> Result<Vec<[f64; 3]>> {
        let plane = self.height * self.width;
        let kc = lights * channels;
        ensure_shape("observations", plane * kc, observed.len(), || {
            format!(
                "observations has {} values, expected k x H x W x C = {lights} x {} x {} x \
                 {channels}",
                observed.len(),
                self.height,
                self.width
            )
        })?;
        crate::memory::check(
            || format!("the indirect light of {lights} lights on {plane} facets"),
            (plane * kc) as f64 * (4.0 + 24.0 + 24.0),
            None,
        )?;
        // Facet-major observations: (H W, k C).
        let mut emit = crate::memory::try_vec(plane * kc, 0f32, "the emitted light")?;
        if kc > 0 {
            emit.par_chunks_mut(kc).enumerate().for_each(|(p, row)| {
                for k in 0..lights {
                    for ch in 0..channels {
                        let v = observed[(k * plane + p) * channels + ch];
                        row[k * channels + ch] = if v.is_finite() { v } else { 0.0 };
                    }
                }
            });
        }
        let mut gathered = crate::memory::try_vec(plane * kc, [0f64; 3], "the indirect light")?;
        if kc > 0 {
            gathered
                .par_chunks_mut(kc)
                .enumerate()
                .for_each(|(p, acc)| {
                    for (j, w) in self.pairs_of(p) {
                        let w = w.map(f64::from);
                        for (a, &e) in acc.iter_mut().zip(&emit[j * kc..(j + 1) * kc]) {
                            let e = f64::from(e);
                            a[0] += e * w[0];
                            a[1] += e * w[1];
                            a[2] += e * w[2];
                        }
                    }
                });
        }
        drop(emit);
        let mut out = crate::memory::try_vec(plane * kc, [0f64; 3], "the indirect light")?;
        if kc > 0 {
            out.par_chunks_mut(plane * channels)
                .enumerate()
                .for_each(|(k, image)| {
                    for (p, values) in image.chunks_mut(channels).enumerate() {
                        let src = &gathered[p * kc + k * channels..p * kc + (k + 1) * channels];
                        values.copy_from_slice(src);
                    }
                });
        }
        Ok(out)
    }
}

/// `ceil(2 |mb - ma|)` with the length `hypot(dx, dy)` (NaN or infinite with it), where the
/// visibility march counts its samples: from `sqrt(dx² + dy²)` when twice that is more than 1
/// and further than `1e-9` (relative) from an integer, else from `hypot`. The two lengths
/// differ by a few units in the last place (relative `1e-15`: the rounded squares, their
/// rounded sum and its rounded root against `hypot`'s ulp) when the squares neither overflow
/// nor underflow (then `2 sqrt` is infinite or at most 1, and `hypot` decides), so their
/// ceilings are the same; `hypot` took 2 % of the processor time of the benchmark's sheet with
/// interreflections (once for the count, once again in the march).
#[inline]
fn march_length(ma: [f64; 2], mb: [f64; 2]) -> f64 {
    let (dx, dy) = (mb[0] - ma[0], mb[1] - ma[1]);
    let quick = 2.0 * (dx * dx + dy * dy).sqrt();
    let up = quick.ceil();
    let clear = 1e-9 * up;
    if quick > 1.0 && up < 1e300 && up - quick > clear && quick - (up - 1.0) > clear {
        return up;
    }
    (2.0 * dx.hypot(dy)).ceil()
}

/// Whether the segment between the centres of facets `a` and `b` (pixel, facet, projected
/// centre) stays in front of the surface (see the module documentation), as its *clearance*:
/// blocked, the amount (negative) by which the surface passes in front of the segment's
/// hiding depth at the first sample that blocks it, where the march ends; visible, the
/// smallest margin (>= 0) of the surface behind the segment over the samples tested (+inf
/// when none is), `min_s z_surface(s) - hiding_depth(z(s), tol)`. (Only its sign is used.)
fn clearance(
    march: &March<'_>,
    depths: &CellDepths,
    (pa, fa, ma): (usize, &Facet, [f64; 2]),
    (pb, fb, mb): (usize, &Facet, [f64; 2]),
    ceiling: f64,
    tol: f64,
) -> f64 {
    let (c, e) = (fa.centre, fb.centre);
    if !ceiling.is_finite() {
        return f64::INFINITY;
    }
    let total = ceiling.max(1.0);
    let undistorted = match *march.camera {
        Camera::Pinhole { distortion, .. } => distortion == [0.0; 5],
        Camera::Orthographic { .. } => true,
    };
    let perspective = march.camera.is_perspective();
    if undistorted {
        let segment = Segment {
            ends: (pa, pb),
            image: [ma, mb],
            depth: [c[2], e[2]],
            perspective,
            total,
            tol,
        };
        return clearance_dispatch(depths, &segment);
    }
    let steps = total as usize;
    let d = sub(e, c);
    let mut verdict = Verdict::new();
    for i in 1..steps {
        let s = i as f64 / total;
        // With distortion: the segment's point, projected.
        let x = segment_point(c, e, d, s, perspective);
        let [u, v] = march.camera.project(x);
        if verdict.sample(depths, (pa, pb), u + 0.5, v + 0.5, hiding_depth(x[2], tol)) {
            break;
        }
    }
    verdict.clearance()
}

/// An undistorted segment of [`clearance`]: its two cells, projected centres and depths, the
/// camera's kind, its sample count and tolerance.
struct Segment {
    ends: (usize, usize),
    image: [[f64; 2]; 2],
    depth: [f64; 2],
    perspective: bool,
    total: f64,
    tol: f64,
}

/// Samples of [`clearance_lanes`] computed together.
const MARCH_LANES: usize = 8;

simd_dispatch! {
    wide
    /// [`clearance_lanes`] with AVX-512 or AVX2 when the processor has it (same arithmetic).
    fn clearance_dispatch => clearance_lanes(depths: &CellDepths, segment: &Segment) -> f64;
}

/// [`clearance`] of an undistorted segment: the image point of sample `s` is on the line
/// between the projected ends and its depth is harmonic (pinhole) or linear in `s`. Each
/// block of [`MARCH_LANES`] samples computes their image points and hiding depths in SIMD
/// lanes (the scalar march's operations, in its order: the same values), then tests them
/// against the surface in turn ([`Verdict::sample`]).
#[inline(always)]
fn clearance_lanes(depths: &CellDepths, segment: &Segment) -> f64 {
    let Segment {
        ends,
        image: [ma, mb],
        depth: [cz, ez],
        perspective,
        total,
        tol,
    } = *segment;
    let steps = total as usize;
    let mut verdict = Verdict::new();
    let mut from = 1;
    while from < steps {
        let s: [f64; MARCH_LANES] = crate::lanes(|t| (from + t) as f64 / total);
        let z: [f64; MARCH_LANES] = match perspective {
            true => crate::lanes(|t| 1.0 / ((1.0 - s[t]) / cz + s[t] / ez)),
            false => crate::lanes(|t| cz + s[t] * (ez - cz)),
        };
        let gx: [f64; MARCH_LANES] = crate::lanes(|t| ma[0] + s[t] * (mb[0] - ma[0]) + 0.5);
        let gy: [f64; MARCH_LANES] = crate::lanes(|t| ma[1] + s[t] * (mb[1] - ma[1]) + 0.5);
        let reach: [f64; MARCH_LANES] = crate::lanes(|t| hiding_depth(z[t], tol));
        for t in 0..MARCH_LANES.min(steps - from) {
            if verdict.sample(depths, ends, gx[t], gy[t], reach[t]) {
                return verdict.clearance();
            }
        }
        from += MARCH_LANES;
    }
    verdict.clearance()
}

/// The state of a march of [`clearance`] along its samples.
struct Verdict {
    /// The smallest margin of the surface behind the segment so far; blocked, the cut at the
    /// blocking sample (negative).
    clearance: f64,
}

impl Verdict {
    fn new() -> Verdict {
        Verdict {
            clearance: f64::INFINITY,
        }
    }

    /// Tests the sample at the image point `(gx, gy)` (pixel corners at integers) with the
    /// hiding depth `reach`; samples over the end cells `ends` or where the surface is unknown
    /// are not tested. True when the march is over: the sample blocks the segment.
    #[inline(always)]
    fn sample(
        &mut self,
        depths: &CellDepths,
        (pa, pb): (usize, usize),
        gx: f64,
        gy: f64,
        reach: f64,
    ) -> bool {
        if !(gx >= 0.0 && gy >= 0.0) {
            return false;
        }
        let (row, col) = (
            (gy as usize).min(depths.height.saturating_sub(1)),
            (gx as usize).min(depths.width.saturating_sub(1)),
        );
        let cell = row * depths.width + col;
        if cell == pa || cell == pb {
            return false;
        }
        let Some(z_surface) = depths.surface_depth_in(gx, gy, row, col) else {
            return false;
        };
        if z_surface < reach {
            // (negative: z_surface < reach, and finite values differ by a nonzero amount)
            self.clearance = (z_surface - reach).min(-f64::MIN_POSITIVE);
            return true;
        }
        self.clearance = self.clearance.min(z_surface - reach);
        false
    }

    /// Blocked, the cut at the blocking sample; else the smallest margin (+inf when no sample
    /// was tested).
    fn clearance(&self) -> f64 {
        self.clearance
    }
}

/// The depths of the 4 corners of every cell (pixel) of an exchange's mesh, in one array for
/// its visibility march (NaN outside the mask or with a non-finite corner).
struct CellDepths {
    height: usize,
    width: usize,
    corners: Vec<[f64; 4]>,
}

impl CellDepths {
    fn new(march: &March<'_>) -> Result<CellDepths> {
        let (height, width) = (march.height, march.width);
        let corners = crate::memory::try_par_collect(
            (0..height * width).into_par_iter().map(|p| {
                let q = march.quad(p / width, p % width);
                match march.mask.is_none_or(|m| m[p]) {
                    true => [q[0][2], q[1][2], q[2][2], q[3][2]],
                    false => [f64::NAN; 4],
                }
            }),
            "the depths of the light exchange",
        )?;
        Ok(CellDepths {
            height,
            width,
            corners,
        })
    }

    /// [`March::surface_depth`] from the corners, at `(gx, gy)` in its cell `(row, col)` (the
    /// cell that holds it, clamped to the grid: `(min(gy, H - 1), min(gx, W - 1))` rounded
    /// down): the same value (None outside the image, the mask or the finite vertices).
    #[inline(always)]
    fn surface_depth_in(&self, gx: f64, gy: f64, row: usize, col: usize) -> Option<f64> {
        let (w, h) = (self.width as f64, self.height as f64);
        if !(gx >= 0.0 && gx <= w && gy >= 0.0 && gy <= h) {
            return None;
        }
        let q = &self.corners[row * self.width + col];
        let (fx, fy) = (gx - col as f64, gy - row as f64);
        let z = (1.0 - fy) * ((1.0 - fx) * q[0] + fx * q[1]) + fy * ((1.0 - fx) * q[2] + fx * q[3]);
        z.is_finite().then_some(z)
    }
}

/// The weight vectors `(w_ij, w_ji)` of a facing pair (see the module documentation): the point
/// formula, or for a near pair the two quadratures made reciprocal (each corrected along its
/// receiver's normal); None when a near pair's form factor is not positive.
fn pair_weights(fi: &Facet, fj: &Facet) -> Option<([f64; 3], [f64; 3])> {
    let (wij, wji) = raw_pair_weights(fi, fj);
    if !is_near(fi, fj) {
        return Some((wij, wji));
    }
    // A_i F_ij and A_j F_ji: two estimates of the same double integral; both take their mean,
    // by the least change of each vector (along its receiver's normal, where the form factor
    // reads it).
    let (a, b) = (fi.area * dot(fi.normal, wij), fj.area * dot(fj.normal, wji));
    if !(a > 0.0 && b > 0.0) {
        return None;
    }
    let mean = 0.5 * (a + b);
    let towards = |w: [f64; 3], f: &Facet, own: f64| -> [f64; 3] {
        let t = (mean - own) / f.area;
        std::array::from_fn(|c| w[c] + t * f.normal[c])
    };
    Some((towards(wij, fi, a), towards(wji, fj, b)))
}

/// Whether a pair is near: `r^2 < NEAR^2 max(A_i, A_j)`.
fn is_near(fi: &Facet, fj: &Facet) -> bool {
    let d = sub(fj.centre, fi.centre);
    dot(d, d) < NEAR * NEAR * fi.area.max(fj.area)
}

/// The weight vectors before the near pairs are made reciprocal.
fn raw_pair_weights(fi: &Facet, fj: &Facet) -> ([f64; 3], [f64; 3]) {
    if !is_near(fi, fj) {
        let (wij, wji) = point_kernel(fi.centre, fi.normal, fj.centre, fj.normal);
        (wij.map(|x| x * fj.area), wji.map(|x| x * fi.area))
    } else {
        (near_weight(fi, fj), near_weight(fj, fi))
    }
}

/// `w_ij` of a near pair: the mean over the receiver's sub-points `y_a` (in front of the
/// emitter's plane) of the emitter quad's vector `(1 / pi) int d dw` by Lambert's edge formula
/// (see `polygon_vector`, tests). The [`SUBDIVISIONS`]² sub-points run in SIMD lanes
/// ([`near_weight_lanes`]): the operations of `polygon_vector` per sub-point, in its order,
/// with the edge angles of [`angle_of`] instead of `atan2` (within 2 ulp of it: the weights,
/// stored as `f32`, come out the same but where an `f64` value falls within that of an `f32`
/// rounding boundary).
fn near_weight(receiver: &Facet, emitter: &Facet) -> [f64; 3] {
    near_weight_dispatch(
        &receiver.corners,
        emitter.normal,
        emitter.centre,
        &emitter.corners,
    )
}

simd_dispatch! {
    wide
    /// [`near_weight_lanes`] with AVX-512 or AVX2 when the processor has it (same arithmetic).
    fn near_weight_dispatch => near_weight_lanes(
        receiver: &[[f64; 3]; 4],
        normal: [f64; 3],
        centre: [f64; 3],
        emitter: &[[f64; 3]; 4],
    ) -> [f64; 3];
}

/// Sub-points of a receiver in [`near_weight`].
const SUB: usize = SUBDIVISIONS * SUBDIVISIONS;

/// [`near_weight`] of the receiver quad `receiver` and the emitter quad `emitter` (unit normal
/// `normal`, centre `centre`), one lane per sub-point.
#[inline(always)]
fn near_weight_lanes(
    receiver: &[[f64; 3]; 4],
    normal: [f64; 3],
    centre: [f64; 3],
    emitter: &[[f64; 3]; 4],
) -> [f64; 3] {
    let y = sub_points(receiver);
    let p = [emitter[0], emitter[1], emitter[3], emitter[2]];
    let lane = |f: &dyn Fn(usize) -> f64| -> [f64; SUB] { crate::lanes(f) };
    // Per corner e and component c: v_e = p_e - y (each sub-point).
    let v: [[[f64; SUB]; 3]; 4] = crate::lanes(|e| crate::lanes(|c| lane(&|t| p[e][c] - y[t][c])));
    let mut sum = [[0.0f64; SUB]; 3];
    for e in 0..4 {
        let (a, b) = (&v[e], &v[(e + 1) % 4]);
        for t in 0..SUB {
            let g = [
                a[1][t] * b[2][t] - a[2][t] * b[1][t],
                a[2][t] * b[0][t] - a[0][t] * b[2][t],
                a[0][t] * b[1][t] - a[1][t] * b[0][t],
            ];
            let len = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt();
            let d = a[0][t] * b[0][t] + a[1][t] * b[1][t] + a[2][t] * b[2][t];
            let theta = angle_of(len, d);
            let used = !not_above(len, 0.0);
            for c in 0..3 {
                sum[c][t] += if used { theta * g[c] / len } else { 0.0 };
            }
        }
    }
    let mut w = [0.0; 3];
    for t in 0..SUB {
        let towards: [f64; 3] =
            std::array::from_fn(|c| 0.0 + v[0][c][t] + v[1][c][t] + v[2][c][t] + v[3][c][t]);
        let s = [sum[0][t], sum[1][t], sum[2][t]];
        let sign = if dot(s, towards) < 0.0 { -1.0 } else { 1.0 };
        let front = !not_above(dot(normal, sub(y[t], centre)), 0.0);
        for c in 0..3 {
            w[c] += if front {
                sign * s[c] / (2.0 * std::f64::consts::PI)
            } else {
                0.0
            };
        }
    }
    w.map(|x| x / SUB as f64)
}

/// The angle `atan2(len, d)` in `[0, pi]` for `len >= 0` (the angle between two vectors from
/// the length of their cross product and their dot product), without a branch per value (so
/// that lanes of it vectorize): Cephes' `atan` (Moshier: the rational approximation of degree
/// 4 / 5 on `[0, 0.66]`, the reductions `pi / 4 + atan((x - 1) / (x + 1))` and
/// `pi / 2 - atan(1 / x)`) of `x = len / |d|`, then `pi - atan(x)` for `d < 0`. Within 2 ulp of
/// `f64::atan2` (test `angle_of_is_atan2`).
#[inline(always)]
fn angle_of(len: f64, d: f64) -> f64 {
    const P: [f64; 5] = [
        -8.750_608_600_031_904e-1,
        -1.615_753_718_733_365e1,
        -7.500_855_792_314_705e1,
        -1.228_866_684_490_136_2e2,
        -6.485_021_904_942_025e1,
    ];
    const Q: [f64; 5] = [
        2.485_846_490_142_306_4e1,
        1.650_270_098_316_988_6e2,
        4.328_810_604_912_903e2,
        4.853_903_996_359_137e2,
        1.945_506_571_482_614e2,
    ];
    const T3P8: f64 = 2.414_213_562_373_095;
    const MOREBITS: f64 = 6.123_233_995_736_766e-17;
    use std::f64::consts::{FRAC_PI_2, FRAC_PI_4, PI};
    let x = len / d.abs();
    let (far, mid) = (x > T3P8, x > 0.66);
    let r = match (far, mid) {
        (true, _) => -1.0 / x,
        (false, true) => (x - 1.0) / (x + 1.0),
        _ => x,
    };
    let (base, more) = match (far, mid) {
        (true, _) => (FRAC_PI_2, MOREBITS),
        (false, true) => (FRAC_PI_4, 0.5 * MOREBITS),
        _ => (0.0, 0.0),
    };
    let z = r * r;
    let num = (((P[0] * z + P[1]) * z + P[2]) * z + P[3]) * z + P[4];
    let den = ((((z + Q[0]) * z + Q[1]) * z + Q[2]) * z + Q[3]) * z + Q[4];
    let a = base + (r * (z * num / den) + r + more);
    if d < 0.0 {
        PI - a
    } else {
        a
    }
}

/// `(1 / pi) int d dw` over the solid angle of the closed polygon `p` (straight edges) seen
/// from `y`, `d` the unit direction: Lambert's formula `1 / (2 pi) sum_e theta_e g_e`, with
/// `theta_e` the angle that edge `e` subtends at `y` and `g_e` the unit normal of the plane
/// through `y` and the edge, oriented towards the polygon (Arvo 1994). Exact for any surface
/// spanned by the polygon that stays in front of `y`. (The reference of [`near_weight_lanes`],
/// which computes it per sub-point in lanes.)
#[cfg(test)]
fn polygon_vector(y: [f64; 3], p: [[f64; 3]; 4]) -> [f64; 3] {
    let v = p.map(|x| sub(x, y));
    let mut sum = [0.0; 3];
    for e in 0..4 {
        let (a, b) = (v[e], v[(e + 1) % 4]);
        let g = cross(a, b);
        let len = norm(g);
        if not_above(len, 0.0) {
            continue;
        }
        // (crate::vec3::angle(a, b), from the cross product at hand: the same bits)
        let theta = len.atan2(dot(a, b));
        for c in 0..3 {
            sum[c] += theta * g[c] / len;
        }
    }
    // The winding decides the sign: the vector points towards the polygon.
    let towards = v.iter().fold([0.0; 3], |acc, x| crate::vec3::add(acc, *x));
    let sign = if dot(sum, towards) < 0.0 { -1.0 } else { 1.0 };
    sum.map(|x| sign * x / (2.0 * std::f64::consts::PI))
}

/// [`near_weight`] one sub-point at a time with `atan2` (the code before the lanes; the
/// reference of the tests).
#[cfg(test)]
fn near_weight_reference(receiver: &Facet, emitter: &Facet) -> [f64; 3] {
    let q = emitter.corners;
    let mut w = [0.0; 3];
    for y in sub_points(&receiver.corners) {
        if not_above(dot(emitter.normal, sub(y, emitter.centre)), 0.0) {
            continue;
        }
        let v = polygon_vector(y, [q[0], q[1], q[3], q[2]]);
        for c in 0..3 {
            w[c] += v[c];
        }
    }
    let s = (SUBDIVISIONS * SUBDIVISIONS) as f64;
    w.map(|x| x / s)
}

/// Per unit emitter area, between the points `a` (normal `na`) and `b` (normal `nb`): the
/// irradiance vectors `max(0, cos_b) d / (pi r^2)` at `a` from `b` and `max(0, cos_a) (-d) /
/// (pi r^2)` at `b` from `a` (`d = (b - a) / r`), each zero when the receiver turns away.
#[inline]
fn point_kernel(a: [f64; 3], na: [f64; 3], b: [f64; 3], nb: [f64; 3]) -> ([f64; 3], [f64; 3]) {
    let d = sub(b, a);
    let r2 = dot(d, d);
    let (ca, cb) = (dot(na, d), -dot(nb, d));
    if !(ca > 0.0 && cb > 0.0 && r2 > 0.0) {
        return ([0.0; 3], [0.0; 3]);
    }
    // cos_b / r * d / r / (pi r^2) = cb d / (pi r^4).
    let f = 1.0 / (std::f64::consts::PI * r2 * r2);
    (d.map(|x| x * cb * f), d.map(|x| -x * ca * f))
}

/// The centres of the `SUBDIVISIONS`² bilinear sub-facets of a quad (corners 00, 01, 10, 11).
fn sub_points(q: &[[f64; 3]; 4]) -> [[f64; 3]; SUBDIVISIONS * SUBDIVISIONS] {
    std::array::from_fn(|t| {
        let (a, b) = (t / SUBDIVISIONS, t % SUBDIVISIONS);
        let fy = (a as f64 + 0.5) / SUBDIVISIONS as f64;
        let fx = (b as f64 + 0.5) / SUBDIVISIONS as f64;
        std::array::from_fn(|c| {
            (1.0 - fy) * ((1.0 - fx) * q[0][c] + fx * q[1][c])
                + fy * ((1.0 - fx) * q[2][c] + fx * q[3][c])
        })
    })
}

/// Longest side, in facets, of the coarse grid on which the solver gathers the indirect light
/// (`IndirectField::of_mesh`): the issue's prototype measured that 32² to 128² facets change
/// the normals by at most 0.13° on the benchmark's concave scenes.
pub const FIELD_SIDE: usize = 64;

/// The coarse grid's longest side is at most `max(FIELD_SIDE_SMALL, min(FIELD_SIDE, longest /
/// 8))` facets, so that a small image gets a small exchange: 256² images are gathered on 32²
/// facets, 512² and more on 64² (measured on the benchmark's GI renders at 256²: 32² instead of
/// 64² changed the mean normal errors by -0.03 to +0.21°, and cut the exchange's cost from about
/// 1 s to 0.1 s a round on one core, where a default run takes 0.1-0.3 s).
pub const FIELD_SIDE_SMALL: usize = 32;

/// The first round of `Solver::interreflect` gathers on a grid of `1 / FIRST_ROUND_COARSER`
/// as many facets a side as the rounds after it (16² instead of 32² for a 256² image: a
/// quarter of the facets, about 1/16 of the pairs to march): the converged surface without
/// indirect light is far from the rounds' fixed point (on the benchmark's sheet the first
/// round moves the depths by 1.8, the fourth by 0.2), so its field need only be about right.
/// The second round gathers on the rounds' own grid afresh (not at the first's factor).
/// Measured on the benchmark's GI renders (docs/concave.md, stop 47): the mean normal errors
/// moved by -0.01 to +0.02° (all under 1°), the sheet's option about 10 % less processor time.
pub const FIRST_ROUND_COARSER: usize = 2;

/// The indirect irradiance of a solver's current mesh under each light, gathered on a coarse
/// grid (the image binned by a power of two to at most [`FIELD_SIDE`] facets a side) from the
/// binned observations, and looked up per fine facet by bilinear interpolation
/// ([`IndirectField::at`]).
///
/// Cost: binning `O(H W k C)`; the [`Exchange`] of the `F <= FIELD_SIDE^2` coarse facets
/// `O(F^2 D)` (`D` the coarse image diagonal), independent of the image size beyond the binning;
/// its pass `O(P k C)` for `P` pairs; each local step then adds `O(k C)` per fine facet (the
/// lookup, and the field's rows in the fits: in SIMD lanes for grey images, see
/// `local::lanes::field`; colour images take the scalar fits). Memory: the exchange (at most
/// `max_pairs` pairs, [`BYTES_PER_PAIR`] each) while it is built, then `12 k C` bytes per coarse
/// facet.
#[derive(Debug, Clone)]
pub struct IndirectField {
    /// Fine pixels per coarse facet side.
    factor: usize,
    height: usize,
    width: usize,
    /// Values per coarse facet: `k C`.
    per: usize,
    /// Per coarse facet, light-major then channel: `V` (facet-major, (Hc Wc, k C)).
    vectors: Vec<[f32; 3]>,
    /// Whether each coarse facet took part in the exchange (else its vectors are not used).
    valid: Vec<bool>,
    /// Directed pairs of the exchange it came from.
    pairs: usize,
    /// Per fine pixel, `words` bits: the lights behind its facet on the mesh the field was made
    /// for (see [`IndirectField::with_unlit`]); empty: none.
    unlit: Vec<u64>,
    /// Per fine pixel, `words` bits: the lights of `unlit` that the margin hides (see
    /// [`IndirectField::with_unlit`]), kept for the field of the next round; empty: none.
    hidden: Vec<u64>,
    words: usize,
    /// The coarse mesh continued past the image border (see [`IndirectField::with_unlit`],
    /// also for a finer level's field, [`IndirectField::finer`]); None without a margin.
    margin: Option<MarginMesh>,
}

impl crate::local::IndirectLight for IndirectField {
    fn is_unlit(&self, p: usize, k: usize) -> bool {
        IndirectField::is_unlit(self, p, k)
    }

    fn at_into(&self, p: usize, width: usize, out: &mut Vec<[f64; 3]>) {
        IndirectField::at_into(self, p, width, out)
    }

    /// In one pass: each value is interpolated straight into its lane (the sums of
    /// [`IndirectField::at_into`], in its order: the same values) and the unlit lights read
    /// from their bits, without the per-pixel vectors and a call per light.
    fn lane_into(&self, p: usize, width: usize, lane: usize, rows: &mut [crate::local::FieldRow]) {
        let (cells, used, total) = self.cells(p, width);
        let cells = &cells[..used];
        for (j, row) in rows.iter_mut().enumerate().take(self.per) {
            for c in 0..3 {
                let mut x = 0.0;
                for &(pc, weight) in cells {
                    x += weight * f64::from(self.vectors[pc * self.per + j][c]);
                }
                row.v[c][lane] = if total != 1.0 { x / total } else { x };
            }
            row.direct[lane] = !self.is_unlit(p, j);
        }
    }
}

impl IndirectField {
    /// The field of the mesh with unknowns `u` on `grid` / `geometry` seen by `camera` (the
    /// fine grid's), from the observations `obs` (the fine stack: the observed images are the
    /// emitters; non-finite values emit nothing). The grid is binned by the smallest power of
    /// two that brings both sides to at most [`FIELD_SIDE_SMALL`] to [`FIELD_SIDE`] facets (see
    /// [`FIELD_SIDE_SMALL`]), at least `min_factor` (the factor of the field of the same
    /// solver the round before, so that a grid over the cap is built once), or further while
    /// the exchange has more than `max_pairs` pairs (None: [`DEFAULT_MAX_PAIRS`]).
    ///
    /// A coarse vertex is the fine vertex it stands on when that is active, else the mean depth
    /// of the active fine vertices within half a bin of it, on its own ray; a coarse facet takes
    /// part when its corners are known and one of its fine pixels is in the mask, and emits the
    /// mean of the finite observations of its masked fine pixels.
    ///
    /// With `lights` (the rig's; empty: no margin), where the surface reaches the image border
    /// the coarse mesh is continued past it by a margin of `ceil(MARGIN_FRACTION * longest
    /// coarse side)` facets ([`extend_depths`], [`MARGIN_FRACTION`]): the margin's facets take
    /// part in the exchange (they block, receive and emit), emit the light the image model
    /// predicts for them ([`Margin`]: their direct light cut by the cast shadows marched on the
    /// extended mesh), and hide lights from the image's facets ([`IndirectField::with_unlit`]).
    /// Surface outside the mask that does not reach the border, and surface hidden from the
    /// camera, still emit nothing: their light is missing (see the module documentation).
    ///
    /// On a grid of `1 / coarser` as many facets a side (`coarser` a power of two; 1: the
    /// grid's side limit, see [`FIELD_SIDE_SMALL`]; 2: the first round of `Solver::interreflect`,
    /// see [`FIRST_ROUND_COARSER`]).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn of_mesh(
        camera: &Camera,
        grid: &crate::grid::Grid,
        geometry: &crate::geometry::Geometry,
        u: &[f64],
        obs: &crate::local::Observations<'_>,
        lights: &[crate::Light],
        min_factor: usize,
        max_pairs: Option<usize>,
        coarser: usize,
    ) -> Result<IndirectField> {
        let (h, w) = (grid.height, grid.width);
        // Fine vertex depths ((H+1) x (W+1), NaN where inactive) and the fine mask.
        let mut depth = crate::memory::try_vec((h + 1) * (w + 1), f64::NAN, "the vertex depths")?;
        for (i, v) in grid.active.iter().map(|&v| v as usize).enumerate() {
            depth[v] = geometry.depth(u[i]);
        }
        let mut factor = 1;
        let mut coarse = *camera;
        let side = (h.max(w) / 8).clamp(FIELD_SIDE_SMALL, FIELD_SIDE) / coarser.max(1);
        while factor < min_factor || h.div_ceil(factor) > side || w.div_ceil(factor) > side {
            factor *= 2;
            coarse = crate::pyramid::coarser_camera(&coarse);
        }
        loop {
            match Self::at_factor(&coarse, factor, grid, &depth, obs, lights, max_pairs) {
                Err(Error::Unusable(m))
                    if m.contains("max_pairs")
                        && h.div_ceil(factor) > 4
                        && w.div_ceil(factor) > 4 =>
                {
                    factor *= 2;
                    coarse = crate::pyramid::coarser_camera(&coarse);
                }
                other => return other,
            }
        }
    }

    /// [`IndirectField::of_mesh`] at one binning `factor` (`coarse`: the camera of that grid).
    fn at_factor(
        coarse: &Camera,
        factor: usize,
        grid: &crate::grid::Grid,
        depth: &[f64],
        obs: &crate::local::Observations<'_>,
        lights: &[crate::Light],
        max_pairs: Option<usize>,
    ) -> Result<IndirectField> {
        let (h, w) = (grid.height, grid.width);
        let (hc, wc) = (h.div_ceil(factor), w.div_ceil(factor));
        let fw = w + 1;
        let half = factor / 2;
        let depths: Vec<f64> = crate::memory::try_collect(
            (0..(hc + 1) * (wc + 1)).map(|v| {
                let (r, c) = (v / (wc + 1) * factor, v % (wc + 1) * factor);
                let z = match r <= h && c <= w {
                    true => depth[r * fw + c],
                    false => f64::NAN,
                };
                if z.is_finite() {
                    return z;
                }
                let (mut sum, mut n) = (0.0, 0usize);
                for rr in r.saturating_sub(half)..=(r + half).min(h) {
                    for cc in c.saturating_sub(half)..=(c + half).min(w) {
                        let d = depth[rr * fw + cc];
                        if d.is_finite() {
                            sum += d;
                            n += 1;
                        }
                    }
                }
                if n > 0 {
                    sum / n as f64
                } else {
                    f64::NAN
                }
            }),
            "the coarse vertices of the light exchange",
        )?;
        let (k, channels) = (obs.k, obs.channels);
        let per = k * channels;
        let plane = hc * wc;
        // The coarse mask and the binned observations, (k, Hc, Wc, C).
        let mut mask = crate::memory::try_vec(plane, false, "the coarse mask")?;
        for p in grid.facets.iter().map(|&p| p as usize) {
            mask[(p / w / factor) * wc + p % w / factor] = true;
        }
        let mut binned = crate::memory::try_vec(plane * per, f32::NAN, "the binned images")?;
        let mut sum = vec![0f64; per];
        let mut count = vec![0u32; per];
        for (pc, &inside) in mask.iter().enumerate() {
            if !inside {
                continue;
            }
            sum.fill(0.0);
            count.fill(0);
            let (rc, cc) = (pc / wc, pc % wc);
            for r in rc * factor..((rc + 1) * factor).min(h) {
                for c in cc * factor..((cc + 1) * factor).min(w) {
                    let p = r * w + c;
                    if grid.facet_of_pixel(p) == crate::grid::INACTIVE {
                        continue;
                    }
                    for light in 0..k {
                        for (ch, &v) in obs.at(light, p).iter().enumerate() {
                            if v.is_finite() {
                                sum[light * channels + ch] += f64::from(v);
                                count[light * channels + ch] += 1;
                            }
                        }
                    }
                }
            }
            for light in 0..k {
                for ch in 0..channels {
                    let i = light * channels + ch;
                    if count[i] > 0 {
                        binned[(light * plane + pc) * channels + ch] =
                            (sum[i] / f64::from(count[i])) as f32;
                    }
                }
            }
        }
        // The grid extended by the margin past the image border (see [`MARGIN_FRACTION`]):
        // (hc + 2 m) x (wc + 2 m) facets, the image's at offset (m, m).
        let m = if lights.is_empty() {
            0
        } else {
            margin_cells(hc, wc)
        };
        let (he, we) = (hc + 2 * m, wc + 2 * m);
        let extended = he * we;
        let ext_depths = extend_depths(&depths, hc, wc, m)?;
        drop(depths);
        let camera = shifted_camera(coarse, m);
        let inner = |pc: usize| (pc / wc + m) * we + pc % wc + m;
        let in_view = |pe: usize| {
            let (r, c) = (pe / we, pe % we);
            r >= m && r < m + hc && c >= m && c < m + wc
        };
        let mut mask_e = crate::memory::try_vec(extended, false, "the coarse mask")?;
        for (pe, inside) in mask_e.iter_mut().enumerate() {
            *inside = if in_view(pe) {
                mask[(pe / we - m) * wc + pe % we - m]
            } else {
                let v = (pe / we) * (we + 1) + pe % we;
                [v, v + 1, v + we + 1, v + we + 2]
                    .iter()
                    .all(|&i| ext_depths[i].is_finite())
            };
        }
        let vertices: Vec<[f64; 3]> = crate::memory::try_collect(
            ext_depths.iter().enumerate().map(|(v, &z)| {
                let [x, y] = camera.vertex_xy(v / (we + 1), v % (we + 1));
                match camera.is_perspective() {
                    true => [x * z, y * z, z],
                    false => [x, y, z],
                }
            }),
            "the coarse vertices of the light exchange",
        )?;
        let exchange = Exchange::new(&camera, he, we, &vertices, Some(&mask_e), max_pairs)?;
        // The emitters, (k, He, We, C): the binned observations in the image, the model in the
        // margin (NaN, emitting nothing, until it is set).
        let mut emit = crate::memory::try_vec(extended * per, f32::NAN, "the emitted light")?;
        for light in 0..k {
            for pc in 0..plane {
                let (from, to) = (light * plane + pc, light * extended + inner(pc));
                emit[to * channels..(to + 1) * channels]
                    .copy_from_slice(&binned[from * channels..(from + 1) * channels]);
            }
        }
        drop(binned);
        let mut v = exchange.irradiance(&emit, k, channels)?;
        let margin_takes_part = (0..extended).any(|pe| !in_view(pe) && mask_e[pe]);
        if margin_takes_part {
            let shadows = crate::shadow::march_all(
                &camera,
                lights,
                he,
                we,
                crate::shadow::Vertices::Positions(&vertices),
                Some(&mask_e),
                None,
                true,
                1,
            )?;
            let margin = Margin {
                exchange: &exchange,
                shadows: &shadows,
                lights,
                channels,
                image: (m, hc, wc),
                mask: &mask_e,
            };
            for _ in 0..MARGIN_PASSES {
                margin.emit(&v, &mut emit);
                v = exchange.irradiance(&emit, k, channels)?;
            }
        }
        drop(emit);
        let margin = margin_takes_part.then(|| MarginMesh {
            z_min: vertices
                .iter()
                .map(|v| v[2])
                .filter(|z| z.is_finite())
                .fold(f64::INFINITY, f64::min),
            camera,
            height: he,
            width: we,
            image: (m, hc, wc),
            vertices,
            mask: mask_e,
        });
        let mut vectors = crate::memory::try_vec(plane * per, [0f32; 3], "the indirect light")?;
        for light in 0..k {
            for pc in 0..plane {
                for ch in 0..channels {
                    vectors[pc * per + light * channels + ch] =
                        v[(light * extended + inner(pc)) * channels + ch].map(|x| x as f32);
                }
            }
        }
        let valid = (0..plane)
            .map(|pc| mask[pc] && exchange.facet(inner(pc)).2.is_finite())
            .collect();
        Ok(IndirectField {
            factor,
            height: hc,
            width: wc,
            per,
            vectors,
            valid,
            pairs: exchange.pairs(),
            unlit: Vec::new(),
            hidden: Vec::new(),
            words: 0,
            margin,
        })
    }

    /// The field with the lights behind each facet of the mesh `u` (`n . beta_k(c) <= 0` for
    /// its mesh normal `n` and centre `c`), and those that the margin past the image border
    /// hides from its centre (`MarginMesh::hides`: cast shadows of surface the image does not
    /// show; only when at least [`MIN_LIT`] lights are left), marked, whose direct light the fits
    /// then leave out (see [`crate::local::Indirect`]). Decided once per field rather than at
    /// every local step: a facet whose mesh normal crosses a light's terminator from one
    /// iteration to the next made the iteration alternate between two surfaces (on the
    /// benchmark's sheet).
    ///
    /// `kept`: the lights that the margin hid in the field of the round before
    /// ([`IndirectField::take_hidden`]), hidden again (while [`MIN_LIT`] allows). The margin is
    /// continued from the border facets, whose fits change when a light is left out: on the
    /// benchmark's sheet a light that the surface past the left border shadows (the direct-only
    /// render is black there) was hidden in one round and not in the next, for good (a
    /// two-cycle of the rounds, 0.25 mm at the border, the residual alternating by 0.6 %).
    /// Once hidden, a light stays hidden: the hidden sets only grow, so they settle after
    /// finitely many rounds, and the rounds can converge.
    pub(crate) fn with_unlit(
        self,
        grid: &crate::grid::Grid,
        geometry: &crate::geometry::Geometry,
        u: &[f64],
        lights: &[crate::Light],
        kept: Option<Vec<u64>>,
    ) -> Result<IndirectField> {
        self.marked(grid, geometry, u, lights, kept)
    }

    /// [`IndirectField::with_unlit`]: per facet (in parallel, into one flat buffer: 16 bytes a
    /// facet at up to 64 lights) the lights behind it, then those its margin hides (with
    /// `kept` and the [`MIN_LIT`] rule). The lights behind [`MARK_LANES`] facets at a time
    /// (a point light's `beta` in lanes: the same values as `Light::beta`), and each centre
    /// projected once for the margin's tests of all its lights (the sheet's option: this took
    /// 72 ms a run at stop 52, 42 of them in the margin's tests; docs/concave.md, stop 53).
    fn marked(
        mut self,
        grid: &crate::grid::Grid,
        geometry: &crate::geometry::Geometry,
        u: &[f64],
        lights: &[crate::Light],
        kept: Option<Vec<u64>>,
    ) -> Result<IndirectField> {
        let words = lights.len().div_ceil(64);
        let kept = kept.filter(|k| k.len() == grid.height * grid.width * words);
        let mut unlit = crate::memory::try_vec(
            grid.height * grid.width * words,
            0u64,
            "the unlit lights of the indirect light",
        )?;
        let margin = self.margin.as_ref();
        // Per facet, in one flat buffer (`2 words` values a facet: its unlit lights, then the
        // lights the margin hides): 16 bytes a facet at up to 64 lights, where a pair of
        // vectors a facet took about 100 (two headers and two heap blocks), 100 MB at 1 MP.
        let mut bits = crate::memory::try_vec(
            grid.facets.len() * 2 * words,
            0u64,
            "the unlit lights of the indirect light",
        )?;
        // (no lights: an empty buffer, and chunks of 1 so that the chunking is defined)
        let per = (2 * words).max(1);
        // The point lights' lane forms: the lights behind [`MARK_LANES`] facets at a time
        // (those the facets do not face, `crate::light::faced_lanes`: the values of
        // `Light::beta`).
        let lanes: Vec<Option<crate::light::LaneLight>> = lights
            .iter()
            .map(crate::light::LaneLight::from_light)
            .collect();
        bits.par_chunks_mut(per * MARK_LANES)
            .enumerate()
            .for_each(|(chunk, outs)| {
                let first = chunk * MARK_LANES;
                let count = outs.len() / per;
                // The facets' centres and normals (the chunk's last facet repeated past its
                // end, whose lanes are not read).
                let mut centres = [[0.0; 3]; MARK_LANES];
                let mut normals = [[0.0; 3]; MARK_LANES];
                for l in 0..MARK_LANES {
                    let q = geometry.facet_corners(grid, first + l.min(count - 1), u);
                    centres[l] = crate::geometry::quad_centre(&q);
                    normals[l] = crate::geometry::quad_normal(&q);
                }
                for (k, (light, lane)) in lights.iter().zip(&lanes).enumerate() {
                    let (w, bit) = (k / 64, 1u64 << (k % 64));
                    let faced = crate::light::faced_lanes(light, lane.as_ref(), &centres, &normals);
                    for (l, out) in outs.chunks_exact_mut(per).enumerate() {
                        if !faced[l] {
                            out[w] |= bit;
                        }
                    }
                }
                for (l, out) in outs.chunks_exact_mut(per).enumerate() {
                    if let Some(kept) = kept.as_ref() {
                        let p = grid.facets[first + l] as usize;
                        out[words..].copy_from_slice(&kept[p * words..(p + 1) * words]);
                    }
                }
                if let Some(m) = margin {
                    // The lights the margin hides (each centre projected once for all the
                    // lights; a point light's segments whose ends both project inside the
                    // image, where `hides` is false without a march, found in lanes).
                    let images: [[f64; 2]; MARK_LANES] =
                        crate::lanes(|l| m.camera.project(centres[l]));
                    for (k, light) in lights.iter().enumerate() {
                        let (w, bit) = (k / 64, 1u64 << (k % 64));
                        let may = match *light {
                            crate::Light::Point { position, .. } => {
                                m.may_hide_lanes(&centres, &images, position)
                            }
                            crate::Light::Directional { .. } => [true; MARK_LANES],
                        };
                        for (l, out) in outs.chunks_exact_mut(per).enumerate() {
                            // (a light kept hidden is not marched again: the result is the
                            // same)
                            if may[l]
                                && (out[w] | out[words + w]) & bit == 0
                                && m.hides(centres[l], images[l], light)
                            {
                                out[words + w] |= bit;
                            }
                        }
                    }
                }
                for out in outs.chunks_exact_mut(per) {
                    let (bits, hidden) = out.split_at_mut(words);
                    // The margin is a guess: it may not leave fewer than MIN_LIT lights.
                    let unlit: u32 = bits
                        .iter()
                        .zip(hidden.iter())
                        .map(|(a, b)| (a | b).count_ones())
                        .sum();
                    let applied = lights.len().saturating_sub(unlit as usize) >= MIN_LIT;
                    if applied {
                        for (a, b) in bits.iter_mut().zip(hidden.iter()) {
                            *a |= b;
                        }
                    } else {
                        hidden.fill(0);
                    }
                }
            });
        drop(kept);
        let mut hidden = crate::memory::try_vec(
            grid.height * grid.width * words,
            0u64,
            "the hidden lights of the indirect light",
        )?;
        let facets = grid.facets.iter().map(|&p| p as usize);
        for (p, out) in facets.zip(bits.chunks_exact(per)) {
            unlit[p * words..(p + 1) * words].copy_from_slice(&out[..words]);
            hidden[p * words..(p + 1) * words].copy_from_slice(&out[words..]);
        }
        drop(bits);
        self.hidden = hidden;
        self.unlit = unlit;
        self.words = words;
        Ok(self)
    }

    /// The field for the next finer level of a pyramid (the grid `grid`, about twice as many
    /// pixels a side as the field's level: `ceil(H / 2) = h` rows and columns, see
    /// [`crate::pyramid::levels_for`]) with the mesh `u`: the same coarse vectors looked up with
    /// twice the factor `f` (the centre of a finer pixel `r`, at `(r + 1/2) / 2` coarser
    /// pixels, is at `(r + 1/2) / (2 f) - 1/2` cells either way: the bilinear interpolation of
    /// the same field at finer points), and the lights behind each facet of
    /// `u` marked again ([`IndirectField::with_unlit`]), with the lights that the margin hid
    /// from the coarser pixel under each fine one kept hidden.
    pub(crate) fn finer(
        mut self,
        grid: &crate::grid::Grid,
        geometry: &crate::geometry::Geometry,
        u: &[f64],
        lights: &[crate::Light],
    ) -> Result<IndirectField> {
        let kept = self.carry_to_finer(grid)?;
        self.with_unlit(grid, geometry, u, lights, kept)
    }

    /// The field on the next finer level's grid `grid` (see [`IndirectField::finer`]) before
    /// its lights are marked: twice the factor, no unlit lights; returns the lights that the
    /// margin hid from the coarser pixel under each fine one (None: none were kept).
    fn carry_to_finer(&mut self, grid: &crate::grid::Grid) -> Result<Option<Vec<u64>>> {
        let (h, w) = (grid.height, grid.width);
        let (hc, wc) = (h.div_ceil(2), w.div_ceil(2));
        let words = self.words;
        let kept = match self.hidden.len() == hc * wc * words && words > 0 {
            true => {
                let mut kept = crate::memory::try_vec(h * w * words, 0u64, "the hidden lights")?;
                for (p, bits) in kept.chunks_exact_mut(words).enumerate() {
                    let q = (p / w / 2) * wc + p % w / 2;
                    bits.copy_from_slice(&self.hidden[q * words..(q + 1) * words]);
                }
                Some(kept)
            }
            false => None,
        };
        self.factor *= 2;
        self.unlit = Vec::new();
        self.hidden = Vec::new();
        Ok(kept)
    }

    /// The lights that the margin hid from each fine pixel (see
    /// [`IndirectField::with_unlit`]), taken out of the field for the next round's; None when
    /// there were none.
    pub(crate) fn take_hidden(&mut self) -> Option<Vec<u64>> {
        let hidden = std::mem::take(&mut self.hidden);
        hidden.iter().any(|&b| b != 0).then_some(hidden)
    }

    /// Whether light `k` is behind the facet of fine pixel `p` (see
    /// `IndirectField::with_unlit`; false without it).
    pub fn is_unlit(&self, p: usize, k: usize) -> bool {
        self.words > 0 && self.unlit[p * self.words + k / 64] & (1 << (k % 64)) != 0
    }

    /// Fine pixels per coarse facet side.
    pub fn factor(&self) -> usize {
        self.factor
    }

    /// Directed pairs of facets of the exchange the field came from.
    pub fn pairs(&self) -> usize {
        self.pairs
    }

    /// The vectors `V` of fine pixel `p` (of an image `width` wide), `k C` of them, light-major:
    /// the bilinear interpolation of the coarse facets' around its centre, over those that took
    /// part (weights renormalised); where none of the four did, those of the nearest coarse
    /// facet within two that did; else zero.
    pub fn at(&self, p: usize, width: usize) -> Vec<[f64; 3]> {
        let mut out = Vec::new();
        self.at_into(p, width, &mut out);
        out
    }

    /// [`IndirectField::at`] into `out` (resized to `k C`).
    pub fn at_into(&self, p: usize, width: usize, out: &mut Vec<[f64; 3]>) {
        out.clear();
        out.resize(self.per, [0.0; 3]);
        // Per value, `(0 + w_a v_a + w_b v_b + ...) / total` in the cells' order: one pass over
        // a cell's contiguous values at a time (which vectorises; the same sums in the same
        // order as a pass over the cells per value, so the same bits), the division skipped
        // where the weights sum to exactly 1, as they do inside the grid for a power-of-two
        // factor (the same bits).
        let (cells, used, total) = self.cells(p, width);
        for &(pc, weight) in &cells[..used] {
            self.add(pc, weight, out);
        }
        if total != 1.0 {
            for o in out.iter_mut() {
                *o = o.map(|x| x / total);
            }
        }
    }

    /// The coarse facets whose vectors [`IndirectField::at`] sums for fine pixel `p`, with
    /// their weights, in the order it sums them (the first `used`), and the divisor of the sums
    /// (`total`): the bilinear weights of those that took part and their sum; else the nearest
    /// within two that did, weight 1; else none.
    fn cells(&self, p: usize, width: usize) -> ([(usize, f64); 4], usize, f64) {
        let f = self.factor as f64;
        let y = ((p / width) as f64 + 0.5) / f - 0.5;
        let x = ((p % width) as f64 + 0.5) / f - 0.5;
        let (y0, x0) = (y.floor(), x.floor());
        let (ty, tx) = (y - y0, x - x0);
        let mut total = 0.0;
        // The cells that take part, in the order their weights are summed.
        let (mut cells, mut used) = ([(0usize, 0.0f64); 4], 0);
        for (dy, wy) in [(0, 1.0 - ty), (1, ty)] {
            for (dx, wx) in [(0, 1.0 - tx), (1, tx)] {
                let (r, c) = (y0 as i64 + dy, x0 as i64 + dx);
                let weight = wy * wx;
                if let Some(pc) = self.cell(r, c).filter(|_| weight > 0.0) {
                    cells[used] = (pc, weight);
                    used += 1;
                    total += weight;
                }
            }
        }
        if total > 0.0 {
            return (cells, used, total);
        }
        let (r, c) = (
            (p / width / self.factor) as i64,
            (p % width / self.factor) as i64,
        );
        let nearest = (-2i64..=2)
            .flat_map(|dr| (-2i64..=2).map(move |dc| (dr, dc)))
            .filter_map(|(dr, dc)| self.cell(r + dr, c + dc).map(|pc| (dr * dr + dc * dc, pc)))
            .min_by_key(|&(d, _)| d);
        match nearest {
            Some((_, pc)) => ([(pc, 1.0); 4], 1, 1.0),
            None => (cells, 0, 1.0),
        }
    }

    /// The coarse facet at (r, c) when it is in the grid and took part.
    fn cell(&self, r: i64, c: i64) -> Option<usize> {
        let inside = r >= 0 && c >= 0 && (r as usize) < self.height && (c as usize) < self.width;
        let pc = inside.then(|| r as usize * self.width + c as usize)?;
        self.valid[pc].then_some(pc)
    }

    /// Adds `weight` times the vectors of coarse facet `pc` to `out`.
    fn add(&self, pc: usize, weight: f64, out: &mut [[f64; 3]]) {
        for (o, v) in out
            .iter_mut()
            .zip(&self.vectors[pc * self.per..(pc + 1) * self.per])
        {
            for c in 0..3 {
                o[c] += weight * f64::from(v[c]);
            }
        }
    }
}

/// The margin past the image border, in coarse facets a side: `ceil(MARGIN_FRACTION * longest
/// coarse side)` (4 on the 32² grid of a 256² image).
pub const MARGIN_FRACTION: f64 = 0.125;

/// The lights that the margin past the image border hides from a facet are left out only when
/// at least `MIN_LIT` lights still reach it (a facet with fewer rows of direct light cannot be
/// fitted; the margin is a guess).
pub const MIN_LIT: usize = 3;

/// Facets whose unlit lights [`IndirectField::with_unlit`] marks together, in SIMD lanes.
const MARK_LANES: usize = 8;

/// Passes of "model the margin's light, gather again" (see `Margin::emit`).
pub const MARGIN_PASSES: usize = 2;

/// Order `P` of the linear prediction that continues the mesh past the image border
/// (`continue_line`).
pub const PREDICTION_ORDER: usize = 3;

/// At most this many coarse vertices nearest the border (a row or column's run of known ones)
/// fit the linear prediction (`continue_line`).
pub const PREDICTION_SAMPLES: usize = 16;

/// The margin width in coarse facets of a coarse grid of `hc` x `wc` facets.
fn margin_cells(hc: usize, wc: usize) -> usize {
    (MARGIN_FRACTION * hc.max(wc) as f64).ceil() as usize
}

/// The camera of a grid extended by `m` facets on every side: vertex `(r + m, c + m)` of the
/// extended grid stands on the ray of vertex `(r, c)` of `camera`'s (a pinhole's principal point
/// moves by `m` pixels, an orthographic origin by `-m` pixels).
fn shifted_camera(camera: &Camera, m: usize) -> Camera {
    let m = m as f64;
    match *camera {
        Camera::Orthographic { pixel_size, origin } => Camera::Orthographic {
            pixel_size,
            origin: [origin[0] - m * pixel_size[0], origin[1] - m * pixel_size[1]],
        },
        Camera::Pinhole { mut k, distortion } => {
            k[0][2] += m;
            k[1][2] += m;
            Camera::Pinhole { k, distortion }
        }
    }
}

/// The coarse vertex depths `depths` ((hc+1) x (wc+1), NaN where unknown) extended by `m`
/// facets past every side of the image: ((hc+1+2m) x (wc+1+2m)). Where a row of the image's
/// vertices reaches the left or right border with a known depth, [`continue_line`] continues it
/// past that border from its run of known vertices ending there; then every column (the margin
/// columns too, which fills the corners) is continued past the top and bottom alike. Elsewhere
/// the margin stays unknown (NaN): surface that ends inside the image (a mask's edge) is not
/// continued.
fn extend_depths(depths: &[f64], hc: usize, wc: usize, m: usize) -> Result<Vec<f64>> {
    let (rows, cols) = (hc + 1 + 2 * m, wc + 1 + 2 * m);
    let mut ext = crate::memory::try_vec(rows * cols, f64::NAN, "the extended coarse vertices")?;
    for r in 0..=hc {
        ext[(r + m) * cols + m..(r + m) * cols + m + wc + 1]
            .copy_from_slice(&depths[r * (wc + 1)..(r + 1) * (wc + 1)]);
    }
    if m == 0 {
        return Ok(ext);
    }
    let mut line = Vec::new();
    let mut out = vec![0.0; m];
    // Along rows (index i -> ext[r * cols + i]) and then columns.
    for (outer, stride, step, inner) in [(rows, cols, 1, (m, m + wc)), (cols, 1, cols, (m, m + hc))]
    {
        let lines: Vec<usize> = if stride == cols {
            (m..=m + hc).collect()
        } else {
            (0..outer).collect()
        };
        for l in lines {
            let at = |i: usize| l * stride + i * step;
            for forward in [true, false] {
                // The run of known vertices ending at the border, ordered towards it.
                line.clear();
                let indices: Vec<usize> = if forward {
                    (inner.0..=inner.1).rev().collect()
                } else {
                    (inner.0..=inner.1).collect()
                };
                for &i in &indices {
                    let z = ext[at(i)];
                    if !z.is_finite() || line.len() == PREDICTION_SAMPLES {
                        break;
                    }
                    line.push(z);
                }
                if line.is_empty() {
                    continue;
                }
                line.reverse();
                continue_line(&line, &mut out);
                for (t, &z) in out.iter().enumerate() {
                    let i = if forward {
                        inner.1 + 1 + t
                    } else {
                        inner.0 - 1 - t
                    };
                    ext[at(i)] = z;
                }
            }
        }
    }
    Ok(ext)
}

/// Continues the depths `samples` (equally spaced, ordered towards the end that is continued)
/// by `out.len()` more, each clamped to the samples' range `[min, max]` (the continuation stays
/// within the depths the border shows).
///
/// Linear prediction of order `P` = [`PREDICTION_ORDER`] with a constant: `z_t = a_0 +
/// sum_{i=1..P} a_i z_{t-i}`, the coefficients fitted by least squares to the samples (the
/// predictions `t = P..n-1` from their `P` predecessors, with a ridge of `1e-6` times the mean
/// diagonal), run forward from the last `P` samples, each prediction clamped before it is used
/// for the next. Such a recurrence continues exactly a polynomial of degree < `P + 1` and a sine
/// on a line (e.g. a corrugation on a tilted plane) as long as it stays in the range. With
/// fewer than `2 P + 2` samples (or a singular fit) the samples' least-squares line is
/// continued (clamped alike); one sample is continued flat. The clamp turns a plane that slopes
/// towards the border into a flat shelf past it.
fn continue_line(samples: &[f64], out: &mut [f64]) {
    let n = samples.len();
    // The line: t in 0..n, centred at t_mean.
    let t_mean = (n as f64 - 1.0) / 2.0;
    let z_mean = samples.iter().sum::<f64>() / n as f64;
    let (mut stt, mut stz) = (0.0, 0.0);
    for (t, &z) in samples.iter().enumerate() {
        let dt = t as f64 - t_mean;
        stt += dt * dt;
        stz += dt * (z - z_mean);
    }
    let gamma = if stt > 0.0 { stz / stt } else { 0.0 };
    let line = |t: f64| z_mean + gamma * (t - t_mean);
    let (lo, hi) = (
        samples.iter().copied().fold(f64::INFINITY, f64::min),
        samples.iter().copied().fold(f64::NEG_INFINITY, f64::max),
    );
    let clamp = |_: usize, z: f64| z.clamp(lo, hi);
    let linear = |out: &mut [f64]| {
        for (i, o) in out.iter_mut().enumerate() {
            *o = clamp(n + i, line((n + i) as f64));
        }
    };
    const P: usize = PREDICTION_ORDER;
    if n < 2 * P + 2 {
        return linear(out);
    }
    let z: Vec<f64> = samples.iter().map(|&s| s - z_mean).collect();
    let mut a = nalgebra::SMatrix::<f64, { P + 1 }, { P + 1 }>::zeros();
    let mut b = nalgebra::SVector::<f64, { P + 1 }>::zeros();
    for t in P..n {
        let row = nalgebra::SVector::<f64, { P + 1 }>::from_fn(|i, _| match i {
            0 => 1.0,
            i => z[t - i],
        });
        a += row * row.transpose();
        b += row * z[t];
    }
    let ridge = 1e-6 * a.trace() / (P + 1) as f64 + f64::MIN_POSITIVE;
    for i in 0..=P {
        a[(i, i)] += ridge;
    }
    let Some(x) = a.cholesky().map(|c| c.solve(&b)) else {
        return linear(out);
    };
    if !x.iter().all(|v| v.is_finite()) {
        return linear(out);
    }
    let mut history: Vec<f64> = z[n - P..].to_vec();
    for (i, o) in out.iter_mut().enumerate() {
        let k = history.len();
        let mut p = x[0];
        for j in 1..=P {
            p += x[j] * history[k - j];
        }
        let p = clamp(n + i, p + z_mean);
        *o = p;
        history.push(p - z_mean);
    }
}

/// The coarse mesh extended past the image border ([`extend_depths`]), kept while a field is
/// made to find the lights that the margin hides from the image's facets.
#[derive(Debug, Clone)]
struct MarginMesh {
    camera: Camera,
    height: usize,
    width: usize,
    /// The margin `m` and the image's coarse facets `hc` x `wc`.
    image: (usize, usize, usize),
    vertices: Vec<[f64; 3]>,
    mask: Vec<bool>,
    /// The smallest vertex depth: a segment nearer the camera than it is not hidden.
    z_min: f64,
}

impl MarginMesh {
    /// The far end of the segment of [`MarginMesh::hides`] from the point `x` towards `light`:
    /// the light's position, or the point where the segment comes nearer the camera than
    /// `z_min` (along a directional light's direction, which always ends there); None for a
    /// directional light whose segment never does (nothing to march).
    #[inline(always)]
    fn segment_end(&self, x: [f64; 3], light: &crate::Light) -> Option<[f64; 3]> {
        match *light {
            crate::Light::Point { position, .. } => Some(self.point_end(x, position)),
            crate::Light::Directional { direction, .. } => {
                if !(direction[2] < 0.0 && x[2] > self.z_min) {
                    return None;
                }
                let t = (x[2] - self.z_min) / -direction[2];
                Some(std::array::from_fn(|i| x[i] + t * direction[i]))
            }
        }
    }

    /// [`MarginMesh::segment_end`] of a point light at `position`.
    #[inline(always)]
    fn point_end(&self, x: [f64; 3], position: [f64; 3]) -> [f64; 3] {
        if position[2] < self.z_min && x[2] > self.z_min {
            let t = (x[2] - self.z_min) / (x[2] - position[2]);
            std::array::from_fn(|i| x[i] + t * (position[i] - x[i]))
        } else {
            position
        }
    }

    /// Whether the image point `uv` (of the extended grid) is over the image's facets (their
    /// grid points, corners included).
    #[inline(always)]
    fn inside(&self, [u, v]: [f64; 2]) -> bool {
        let (m, hc, wc) = self.image;
        let (gx, gy) = (u + 0.5 - m as f64, v + 0.5 - m as f64);
        gx >= 0.0 && gy >= 0.0 && gx <= wc as f64 && gy <= hc as f64
    }

    /// Per lane, whether [`MarginMesh::hides`] of the point `x[l]` (image point `a[l]`) and the
    /// point light at `position` may be true: false where the segment's two ends project, finite,
    /// inside the image (where `hides` returns false before it marches), for a camera without
    /// distortion, whose projection is computed here in lanes (`Camera::project`'s operations
    /// less the distortion's, which with zero coefficients multiplies by 1 and adds 0: the same
    /// values where they are finite); true otherwise (with distortion: every lane).
    #[inline(always)]
    fn may_hide_lanes<const N: usize>(
        &self,
        x: &[[f64; 3]; N],
        a: &[[f64; 2]; N],
        position: [f64; 3],
    ) -> [bool; N] {
        let end: [[f64; 3]; N] = crate::lanes(|l| self.point_end(x[l], position));
        let b: [[f64; 2]; N] = match self.camera {
            Camera::Orthographic { pixel_size, origin } => crate::lanes(|l| {
                [
                    (end[l][0] - origin[0]) / pixel_size[0] - 0.5,
                    (end[l][1] - origin[1]) / pixel_size[1] - 0.5,
                ]
            }),
            Camera::Pinhole { k, distortion } if distortion == [0.0; 5] => crate::lanes(|l| {
                let p = end[l];
                let (x, y) = (p[0] / p[2], p[1] / p[2]);
                match p[2] <= 0.0 {
                    true => [f64::NAN; 2],
                    false => [k[0][0] * x + k[0][1] * y + k[0][2], k[1][1] * y + k[1][2]],
                }
            }),
            Camera::Pinhole { .. } => return [true; N],
        };
        crate::lanes(|l| {
            let finite = a[l].iter().chain(&b[l]).all(|v| v.is_finite());
            !(finite && self.inside(a[l]) && self.inside(b[l]))
        })
    }

    /// Whether the margin's surface hides `light` from the point `x` (a fine facet's centre):
    /// the segment from `x` towards the light (its position, or along its direction), cut where
    /// it comes nearer the camera than the nearest vertex, is marched half a coarse pixel at a
    /// time in the extended image as [`Exchange`]'s visibility march does, testing only the
    /// samples over the margin (the image's own surface is the cast-shadow march's business,
    /// `shadows=True`): hidden where the bilinear surface depth there is nearer than the
    /// segment's by more than `1e-6 |z| + 1e-3` coarse facet sizes. Segments whose cut ends
    /// both project inside the image are not marched.
    ///
    /// `a` is the image point of `x`, `self.camera.project(x)` (a facet's centre is projected
    /// once for all its lights).
    fn hides(&self, x: [f64; 3], a: [f64; 2], light: &crate::Light) -> bool {
        let Some(end) = self.segment_end(x, light) else {
            return false;
        };
        let (m, hc, wc) = self.image;
        let inside = |uv: [f64; 2]| self.inside(uv);
        let b = self.camera.project(end);
        if !(a.iter().chain(&b).all(|v| v.is_finite())) || (inside(a) && inside(b)) {
            return false;
        }
        let march = March {
            camera: &self.camera,
            height: self.height,
            width: self.width,
            vertices: crate::shadow::Vertices::Positions(&self.vertices),
            mask: Some(&self.mask),
            z_min: f64::NEG_INFINITY,
            max_steps: usize::MAX / 4,
            pyramid: None,
        };
        let size = {
            let q = march.quad(m, m);
            norm(sub(q[1], q[0]))
        };
        let tol = 1e-3 * if size.is_finite() { size } else { 0.0 };
        let length = (b[0] - a[0]).hypot(b[1] - a[1]);
        let total = (2.0 * length).ceil().max(1.0);
        let d = sub(end, x);
        let perspective = self.camera.is_perspective();
        // Without distortion the image point of sample s is a + s (b - a) (the segment's points
        // are perspective-correct): the samples over the image before it leaves the image are
        // skipped (they are not tested), from two samples before its exit on.
        let undistorted = match self.camera {
            Camera::Pinhole { distortion, .. } => distortion == [0.0; 5],
            Camera::Orthographic { .. } => true,
        };
        let first = match undistorted && inside(a) {
            true => {
                let exit = |from: f64, to: f64, size: usize| {
                    let (g, step) = (from + 0.5 - m as f64, to - from);
                    match step {
                        s if s > 0.0 => (size as f64 - g) / s,
                        s if s < 0.0 => -g / s,
                        _ => f64::INFINITY,
                    }
                };
                let leaves = exit(a[0], b[0], wc).min(exit(a[1], b[1], hc));
                ((leaves * total).floor() - 2.0).clamp(1.0, total) as usize
            }
            false => 1,
        };
        for i in first..=total as usize {
            let s = i as f64 / total;
            let p = segment_point(x, end, d, s, perspective);
            let uv = self.camera.project(p);
            let (gx, gy) = (uv[0] + 0.5, uv[1] + 0.5);
            if !(gx >= 0.0 && gy >= 0.0 && gx <= self.width as f64 && gy <= self.height as f64) {
                break;
            }
            if inside(uv) {
                continue;
            }
            let Some(z_surface) = march.surface_depth(gx, gy) else {
                continue;
            };
            if z_surface < hiding_depth(p[2], tol) {
                return true;
            }
        }
        false
    }
}

/// The model of the light that the margin's facets (surface continued past the image border,
/// [`extend_depths`]) send: they are not observed, so each emits what the image model predicts
/// for it, `I_mk = rho_s (Phi_k max(0, n_m . beta_k(c_m)) + n_m . V_mk)` per channel (its direct
/// light, unshadowed, and the indirect light it gathers), with the albedo `rho_s` of the image's
/// facet `s` nearest it on its row or column (the border facet it was continued from; the corner
/// facet for the corners), fitted to that facet's binned observations by least squares over
/// the lights that reach it under the same model:
///
/// ```text
/// rho_s = sum_k I_sk a_sk / sum_k a_sk^2,   a_sk = Phi_k max(0, n_s . beta_k(c_s)) + n_s . V_sk
/// ```
///
/// (the sums over the lights with a finite observation and `a_sk > 0`).
struct Margin<'a> {
    exchange: &'a Exchange,
    /// The cast shadows on the extended grid's mesh: a shadowed facet gets no direct light.
    shadows: &'a crate::shadow::ShadowMask,
    lights: &'a [crate::Light],
    channels: usize,
    /// The margin `m` and the image's coarse facets `hc` x `wc`.
    image: (usize, usize, usize),
    /// The extended grid's facets that take part.
    mask: &'a [bool],
}

impl Margin<'_> {
    /// The model's irradiance `a` of facet `p` of the extended grid under light `k`, channel
    /// `ch`, with the indirect vectors `v` ((k, He, We, C)).
    fn shading(&self, v: &[[f64; 3]], p: usize, k: usize, ch: usize) -> f64 {
        let (centre, normal, _) = self.exchange.facet(p);
        let light = &self.lights[k];
        let plane = self.exchange.height() * self.exchange.width();
        let phi = crate::light::channel_intensity(light.intensity(), self.channels, ch);
        let shadowed = self.shadows.is_shadowed(p, k);
        let direct = match shadowed {
            true => 0.0,
            false => phi * dot(normal, light.beta(centre).0).max(0.0),
        };
        direct + dot(normal, v[(k * plane + p) * self.channels + ch])
    }

    /// Sets the margin's emission in `emit` ((k, He, We, C)) from the model with the indirect
    /// vectors `v` of the last gather.
    fn emit(&self, v: &[[f64; 3]], emit: &mut [f32]) {
        let (m, hc, wc) = self.image;
        let we = self.exchange.width();
        let plane = self.exchange.height() * we;
        let k = self.lights.len();
        let channels = self.channels;
        let mut rho = vec![[f64::NAN; 3]; plane];
        for pe in 0..plane {
            let (r, c) = (pe / we, pe % we);
            if (r >= m && r < m + hc && c >= m && c < m + wc) || !self.mask[pe] {
                continue;
            }
            let s = r.clamp(m, m + hc - 1) * we + c.clamp(m, m + wc - 1);
            if !self.mask[s] || !self.exchange.facet(s).2.is_finite() {
                continue;
            }
            if rho[s][0].is_nan() {
                for ch in 0..channels {
                    let (mut num, mut den) = (0.0, 0.0);
                    for light in 0..k {
                        let i = f64::from(emit[(light * plane + s) * channels + ch]);
                        let a = self.shading(v, s, light, ch);
                        if i.is_finite() && a > 0.0 {
                            num += i * a;
                            den += a * a;
                        }
                    }
                    rho[s][ch] = if den > 0.0 { num / den } else { 0.0 };
                }
            }
            for light in 0..k {
                for ch in 0..channels {
                    let a = self.shading(v, pe, light, ch).max(0.0);
                    emit[(light * plane + pe) * channels + ch] = (rho[s][ch] * a) as f32;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::Camera;

    fn ortho() -> Camera {
        Camera::Orthographic {
            pixel_size: [1.0, 1.0],
            origin: [0.0, 0.0],
        }
    }

    fn pinhole(n: usize, f: f64) -> Camera {
        let c = (n as f64 - 1.0) / 2.0;
        Camera::Pinhole {
            k: [[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]],
            distortion: [0.0; 5],
        }
    }

    /// Vertex depths (n+1) x (n+1) from a function of the vertex (row, column).
    /// Facet `p` of the exchange `x` of an n x n mesh with vertices `v`, as the pair weights
    /// take it (its corners from the vertices).
    fn facets_of<'a>(
        x: &'a Exchange,
        camera: &'a Camera,
        n: usize,
        v: &'a [[f64; 3]],
    ) -> impl Fn(usize) -> Facet + 'a {
        let march = March {
            camera,
            height: n,
            width: n,
            vertices: crate::shadow::Vertices::Positions(v),
            mask: None,
            z_min: f64::NEG_INFINITY,
            max_steps: 1,
            pyramid: None,
        };
        move |p| {
            let (centre, normal, area) = x.facet(p);
            Facet {
                centre,
                normal,
                area,
                corners: march.quad(p / n, p % n),
            }
        }
    }

    fn depths(n: usize, f: impl Fn(f64, f64) -> f64) -> Vec<f64> {
        (0..(n + 1) * (n + 1))
            .map(|v| f((v / (n + 1)) as f64, (v % (n + 1)) as f64))
            .collect()
    }

    /// An orthographic mesh of `n`² pixels of side `pixel` whose vertex depths follow the
    /// profile `depth(x)` across the rows (`x` the vertex column times `pixel`): its camera,
    /// grid, geometry and unknowns.
    fn profile_mesh(
        n: usize,
        pixel: f64,
        depth: impl Fn(f64) -> f64,
    ) -> (
        Camera,
        crate::grid::Grid,
        crate::geometry::Geometry,
        Vec<f64>,
    ) {
        let camera = Camera::Orthographic {
            pixel_size: [pixel, pixel],
            origin: [0.0, 0.0],
        };
        let depth = depths(n, |_, c| depth(c * pixel));
        let grid = crate::grid::Grid::new(n, n, None).unwrap();
        let geometry = crate::geometry::Geometry::new(&camera, &grid).unwrap();
        let u = grid.gather_vertices(&depth).unwrap();
        (camera, grid, geometry, u)
    }

    /// A V-groove along the rows, orthographic 1-unit pixels: depth `z0 + slope (m - |c - m|)`
    /// (deepest at vertex column m = n / 2), the walls at `atan(slope)` from the image plane.
    fn groove(n: usize, slope: f64) -> Vec<f64> {
        let m = (n / 2) as f64;
        depths(n, |_, c| 100.0 + slope * (m - (c - m).abs()))
    }

    /// The march of stop 45 (one sample at a time, as the distorted path still does, with the
    /// undistorted image point and depth): the reference of [`clearance_lanes`].
    fn clearance_one_by_one(
        march: &March<'_>,
        depths: &CellDepths,
        (pa, fa, ma): (usize, &Facet, [f64; 2]),
        (pb, fb, mb): (usize, &Facet, [f64; 2]),
        tol: f64,
    ) -> f64 {
        let (c, e) = (fa.centre, fb.centre);
        let length = (mb[0] - ma[0]).hypot(mb[1] - ma[1]);
        if !length.is_finite() {
            return f64::INFINITY;
        }
        let total = (2.0 * length).ceil().max(1.0);
        let d = sub(e, c);
        let mut verdict = Verdict::new();
        for i in 1..total as usize {
            let s = i as f64 / total;
            let z = match march.camera.is_perspective() {
                true => 1.0 / ((1.0 - s) / c[2] + s / e[2]),
                false => c[2] + s * d[2],
            };
            let (u, v) = (ma[0] + s * (mb[0] - ma[0]), ma[1] + s * (mb[1] - ma[1]));
            if verdict.sample(depths, (pa, pb), u + 0.5, v + 0.5, hiding_depth(z, tol)) {
                break;
            }
        }
        verdict.clearance()
    }

    /// The march in lanes ([`clearance_lanes`]) gives every pair the clearance of the march one
    /// sample at a time, bit for bit: every pair of facets (facing or not, visible or blocked,
    /// segments of 1 to about 90 samples: all the block remainders) of rough meshes under a
    /// pinhole and an orthographic camera, with a mask.
    #[test]
    fn the_march_in_lanes_is_the_march_one_sample_at_a_time() {
        let n = 32;
        let mask: Vec<bool> = (0..n * n).map(|p| (p * 7919) % 13 != 0).collect();
        let (mut blocked, mut visible) = (0, 0);
        for (seed, camera) in [
            (0.0, pinhole(n, 40.0)),
            (1.0, ortho()),
            (2.0, pinhole(n, 25.0)),
        ] {
            let z = depths(n, |r, c| {
                30.0 + 3.0 * (0.7 * c + seed).sin() * (0.4 * r).cos() + 0.5 * (1.3 * r * c).sin()
            });
            let vertices = crate::geometry::vertices(&camera, n, n, &z).unwrap();
            let march = March {
                camera: &camera,
                height: n,
                width: n,
                vertices: crate::shadow::Vertices::Positions(&vertices),
                mask: Some(&mask),
                z_min: f64::NEG_INFINITY,
                max_steps: usize::MAX / 4,
                pyramid: None,
            };
            let cells = CellDepths::new(&march).unwrap();
            let facet = |p: usize| {
                let (centre, normal, _) = march.facet(p)?;
                let q = march.quad(p / n, p % n);
                let area = 0.5 * norm(cross(sub(q[2], q[1]), sub(q[3], q[0])));
                Some(Facet {
                    centre,
                    normal,
                    area,
                    corners: q,
                })
            };
            let facets: Vec<Option<Facet>> = (0..n * n).map(facet).collect();
            for i in 0..n * n {
                let Some(fi) = facets[i].as_ref() else {
                    continue;
                };
                for (j, fj) in facets.iter().enumerate().skip(i + 1) {
                    let Some(fj) = fj.as_ref() else { continue };
                    let tol = 1e-3 * fi.area.max(fj.area).sqrt();
                    let a = (i, fi, camera.project(fi.centre));
                    let b = (j, fj, camera.project(fj.centre));
                    let ceiling = march_length(a.2, b.2);
                    let lanes = clearance(&march, &cells, a, b, ceiling, tol);
                    let one = clearance_one_by_one(&march, &cells, a, b, tol);
                    assert_eq!(lanes.to_bits(), one.to_bits(), "pair {i}, {j}");
                    match lanes < 0.0 {
                        true => blocked += 1,
                        false => visible += 1,
                    }
                }
            }
        }
        // Both verdicts are common on these meshes.
        assert!(blocked > 10_000 && visible > 10_000, "{blocked} {visible}");
    }

    /// [`march_length`] (the square root of the sum of squares, away from integers) is the
    /// ceiling of twice `hypot`, bit for bit: random offsets over 12 decades (several seeds),
    /// offsets whose doubled length is an integer (axis-aligned halves, 3-4-5 triangles) and
    /// their neighbours a few ulps away, zero, tiny, huge and non-finite ones.
    #[test]
    fn the_march_length_is_the_ceiling_of_twice_hypot() {
        let reference =
            |ma: [f64; 2], mb: [f64; 2]| (2.0 * (mb[0] - ma[0]).hypot(mb[1] - ma[1])).ceil();
        let check = |ma: [f64; 2], mb: [f64; 2]| {
            let (got, want) = (march_length(ma, mb), reference(ma, mb));
            assert!(
                got.to_bits() == want.to_bits() || (got.is_nan() && want.is_nan()),
                "{ma:?} {mb:?}: {got} against {want}"
            );
        };
        let mut quick = 0;
        for seed in [1, 7, 23] {
            let mut next = crate::multigrid::tests::lcg(seed);
            for _ in 0..20_000 {
                let scale = 10f64.powf(12.0 * next() - 6.0);
                let ma = [40.0 * next(), 40.0 * next()];
                let mb = [
                    ma[0] + scale * (next() - 0.5),
                    ma[1] + scale * (next() - 0.5),
                ];
                check(ma, mb);
                let (dx, dy) = (mb[0] - ma[0], mb[1] - ma[1]);
                quick += usize::from(2.0 * (dx * dx + dy * dy).sqrt() > 1.0);
            }
        }
        // Most offsets take the quick path.
        assert!(quick > 20_000, "{quick}");
        for k in 0..200 {
            let half = f64::from(k) / 2.0;
            for (dx, dy) in [(half, 0.0), (0.0, half), (0.3 * half, 0.4 * half)] {
                let (mut x, mut y) = (dx, dy);
                for _ in 0..4 {
                    check([1.25, 3.5], [1.25 + x, 3.5 + y]);
                    check([0.0, 0.0], [x, y]);
                    check([0.0, 0.0], [-x, -y]);
                    (x, y) = (x.next_up(), y.next_down());
                }
                let (mut x, mut y) = (dx, dy);
                for _ in 0..4 {
                    check([0.0, 0.0], [x, y]);
                    (x, y) = (x.next_down(), y.next_up());
                }
            }
        }
        for d in [
            0.0,
            1e-310,
            1e-160,
            0.5,
            1e160,
            1e300,
            f64::MAX,
            f64::INFINITY,
            f64::NAN,
        ] {
            check([0.0, 0.0], [d, d]);
            check([0.0, 0.0], [d, 0.0]);
            check([-d, 0.0], [d, 1.0]);
        }
    }

    /// A field carried to the next finer level ([`IndirectField::finer`]: twice the factor) is
    /// the field that level gathers itself on the same coarse grid: a V-groove seen at 64² and
    /// at 128² pixels (orthographic, half the pixel size; the same surface), every facet lit
    /// alike, the 128² image binned 4 x 4 to the same 32² facets. Every fine pixel looks up the
    /// same vectors, bit for bit.
    #[test]
    fn a_field_carried_to_a_finer_level_is_the_one_gathered_there() {
        let field_of = |n: usize, pixel: f64, previous: Option<IndirectField>, carry: bool| {
            // The groove along the rows, deepest at x = 32, walls at 45 degrees.
            let (camera, grid, geometry, u) =
                profile_mesh(n, pixel, |x| 100.0 + (32.0 - (x - 32.0).abs()));
            let images = vec![1.0f32; 2 * n * n];
            let obs = crate::local::Observations::from_stack(&images, 2, n * n, 1);
            match (carry, previous) {
                (true, Some(f)) => f.finer(&grid, &geometry, &u, &[]).unwrap(),
                (_, previous) => IndirectField::of_mesh(
                    &camera,
                    &grid,
                    &geometry,
                    &u,
                    &obs,
                    &[],
                    previous.map_or(1, |f| f.factor()),
                    None,
                    1,
                )
                .unwrap(),
            }
        };
        let coarse = field_of(64, 1.0, None, false);
        assert_eq!(coarse.factor(), 2);
        let carried = field_of(128, 0.5, Some(coarse.clone()), true);
        let gathered = field_of(128, 0.5, Some(coarse), false);
        assert_eq!((carried.factor(), gathered.factor()), (4, 4));
        let mut lit = 0;
        for p in 0..128 * 128 {
            let (a, b) = (carried.at(p, 128), gathered.at(p, 128));
            assert_eq!(a, b, "pixel {p}");
            lit += usize::from(a[0][0] != 0.0);
        }
        // The walls light each other (the facets at the groove's rim see little).
        assert!(lit > 128 * 100, "{lit}");
    }

    /// The first round's grid ([`IndirectField::of_mesh`] with [`FIRST_ROUND_COARSER`]):
    /// half the facets a side of its grid with `coarser` 1 (twice the factor), and the field
    /// the grid of that factor gives by itself: a V-groove at 128² pixels, 32² facets of 4
    /// pixels by default, 16² of 8 for the first round, its vectors those of the 64² image of
    /// the same groove binned 4 x 4 (the same coarse mesh and emitters), bit for bit.
    #[test]
    fn the_first_round_gathers_on_half_the_side() {
        let setup =
            |n: usize, pixel: f64| profile_mesh(n, pixel, |x| 100.0 + (32.0 - (x - 32.0).abs()));
        let images = vec![1.0f32; 2 * 128 * 128];
        let obs = crate::local::Observations::from_stack(&images, 2, 128 * 128, 1);
        let (camera, grid, geometry, u) = setup(128, 0.5);
        let of = |coarser: usize| {
            IndirectField::of_mesh(&camera, &grid, &geometry, &u, &obs, &[], 1, None, coarser)
                .unwrap()
        };
        let (rounds, first) = (of(1), of(FIRST_ROUND_COARSER));
        assert_eq!((rounds.factor(), first.factor()), (4, 8));
        assert_eq!((first.height, first.width), (16, 16));
        assert!(
            first.pairs() * 8 < rounds.pairs(),
            "{} {}",
            first.pairs(),
            rounds.pairs()
        );
        // The 64² image of the same groove gathers on 16² facets of 4 of its pixels by itself
        // only with a cap that its side rule would not reach: compare with its own field at
        // the factor 4 (`coarser` 2 on 64² pixels: a side limit of 16).
        let small = vec![1.0f32; 2 * 64 * 64];
        let small_obs = crate::local::Observations::from_stack(&small, 2, 64 * 64, 1);
        let (camera, grid, geometry, u) = setup(64, 1.0);
        let own =
            IndirectField::of_mesh(&camera, &grid, &geometry, &u, &small_obs, &[], 1, None, 2)
                .unwrap();
        assert_eq!((own.factor(), own.height, own.width), (4, 16, 16));
        assert_eq!(own.valid, first.valid);
        let bits = |f: &IndirectField| -> Vec<u32> {
            f.vectors.iter().flatten().map(|x| x.to_bits()).collect()
        };
        assert_eq!(bits(&own), bits(&first));
        assert!(first.vectors.iter().any(|v| v[0] != 0.0));
    }

    /// The solver's field of a V-groove, 64² pixels binned 2 x 2 (32² facets), every facet lit
    /// alike: the coarse vectors are those of the exchange of the groove's own 32² mesh (the
    /// even vertices), and a fine pixel on the boundary of two coarse facets gets their mean.
    #[test]
    fn the_field_of_a_groove_bins_and_interpolates() {
        let n = 64;
        let camera = ortho();
        let depth = groove(n, 1.0);
        let grid = crate::grid::Grid::new(n, n, None).unwrap();
        let geometry = crate::geometry::Geometry::new(&camera, &grid).unwrap();
        let u = grid.gather_vertices(&depth).unwrap();
        let images = vec![1.0f32; 2 * n * n];
        let obs = crate::local::Observations::from_stack(&images, 2, n * n, 1);
        let field =
            IndirectField::of_mesh(&camera, &grid, &geometry, &u, &obs, &[], 1, None, 1).unwrap();
        assert_eq!(field.factor(), 2);
        let m = n / 2;
        let coarse_camera = crate::pyramid::coarser_camera(&camera);
        let coarse_depth = depths(m, |r, c| depth[(2 * r as usize) * (n + 1) + 2 * c as usize]);
        let v = crate::geometry::vertices(&coarse_camera, m, m, &coarse_depth).unwrap();
        let x = Exchange::new(&coarse_camera, m, m, &v, None, None).unwrap();
        assert_eq!(field.pairs(), x.pairs());
        let own = x.irradiance(&vec![1.0f32; m * m], 1, 1).unwrap();
        let close = |a: [f64; 3], b: [f64; 3]| (0..3).all(|c| (a[c] - b[c]).abs() < 1e-6);
        // Pixel (33, 17) is the lower right quarter of coarse facet (16, 8): its centre is a
        // quarter of a coarse facet from that facet's centre towards (17, 9).
        let at = field.at(33 * n + 17, n);
        assert_eq!(at.len(), 2);
        assert_eq!(at[0], at[1]);
        let w = |r: usize, c: usize| own[r * m + c];
        let expected: [f64; 3] = std::array::from_fn(|c| {
            0.5625 * w(16, 8)[c]
                + 0.1875 * w(16, 9)[c]
                + 0.1875 * w(17, 8)[c]
                + 0.0625 * w(17, 9)[c]
        });
        assert!(close(at[0], expected), "{at:?} {expected:?}");
        // Pixel (32, 16) is on coarse facet (16, 8) too, a quarter towards (15, 7).
        let at = field.at(32 * n + 16, n);
        let expected: [f64; 3] = std::array::from_fn(|c| {
            0.5625 * w(16, 8)[c]
                + 0.1875 * w(16, 7)[c]
                + 0.1875 * w(15, 8)[c]
                + 0.0625 * w(15, 7)[c]
        });
        assert!(close(at[0], expected), "{at:?} {expected:?}");
        assert!(expected[0].abs() > 0.01);
        lanes_are_the_lookups(&field, n, n * n);
    }

    /// `IndirectLight::lane_into` of every fine pixel (in lane `p % LANES`, over what the pixel
    /// before left there) gives `at_into` and `is_unlit`, bit for bit.
    fn lanes_are_the_lookups(field: &IndirectField, width: usize, pixels: usize) {
        use crate::local::IndirectLight;
        let mut rows = vec![crate::local::FieldRow::EMPTY; field.per];
        let lanes = rows[0].direct.len();
        let mut vectors = Vec::new();
        for p in 0..pixels {
            let lane = p % lanes;
            field.lane_into(p, width, lane, &mut rows);
            field.at_into(p, width, &mut vectors);
            for (j, (row, v)) in rows.iter().zip(&vectors).enumerate() {
                for (c, x) in v.iter().enumerate() {
                    assert_eq!(row.v[c][lane].to_bits(), x.to_bits(), "{p} {j} {c}");
                }
                assert_eq!(row.direct[lane], !field.is_unlit(p, j), "{p} {j}");
            }
        }
    }

    /// `angle_of` is `atan2` for non-negative first arguments, within 2 ulp: every range of
    /// its reduction, both signs of the second argument, zeros and infinities of the ratio.
    #[test]
    fn angle_of_is_atan2() {
        let mut next = crate::multigrid::tests::lcg(11);
        let mut worst = 0.0f64;
        let mut cases = vec![
            (1.0, 0.0),
            (1.0, -0.0),
            (0.0, 1.0),
            (0.0, -1.0),
            (1e-300, 1.0),
        ];
        for _ in 0..200_000 {
            let len = (20.0 * next() - 10.0).exp2() * next();
            let d = (20.0 * next() - 10.0).exp2() * (next() - 0.5);
            cases.push((len, d));
        }
        for (len, d) in cases {
            let (a, b) = (angle_of(len, d), len.atan2(d));
            let ulp = (b.abs() * f64::EPSILON).max(f64::MIN_POSITIVE);
            let err = (a - b).abs() / ulp;
            worst = worst.max(err);
            assert!(err <= 2.0, "atan2({len}, {d}): {a} against {b}");
        }
        assert!(worst > 0.0);
    }

    /// The near weights in lanes are the reference's (one sub-point at a time, `atan2`) within
    /// 1e-14 of their size and 1e-16 (the sub-points' terms are at most 1 and may cancel), on quads of random shape and tilt, near and touching, facing and
    /// partly behind each other's planes; stored as `f32` they are the same bits.
    #[test]
    fn near_weights_in_lanes_match_the_reference() {
        let mut next = crate::multigrid::tests::lcg(5);
        let quad = |next: &mut dyn FnMut() -> f64, origin: [f64; 3], tilt: f64| -> Facet {
            let corners: [[f64; 3]; 4] = std::array::from_fn(|k| {
                let (x, y) = ((k % 2) as f64, (k / 2) as f64);
                [
                    origin[0] + x + 0.2 * (next() - 0.5),
                    origin[1] + y + 0.2 * (next() - 0.5),
                    origin[2] + tilt * (x - 0.5) + 0.3 * (next() - 0.5),
                ]
            });
            let centre: [f64; 3] =
                std::array::from_fn(|c| 0.25 * corners.iter().map(|q| q[c]).sum::<f64>());
            let n = cross(sub(corners[2], corners[1]), sub(corners[3], corners[0]));
            let normal = n.map(|x| -x / norm(n));
            let area = 0.5 * norm(n);
            Facet {
                centre,
                normal,
                area,
                corners,
            }
        };
        let (mut same, mut total) = (0, 0);
        for _ in 0..3000 {
            let tilt = 4.0 * (next() - 0.5);
            let a = quad(&mut next, [0.0; 3], tilt);
            let offset = [
                3.0 * (next() - 0.5),
                3.0 * (next() - 0.5),
                2.0 * (next() - 0.5),
            ];
            let tilt = 4.0 * (next() - 0.5);
            let b = quad(&mut next, offset, tilt);
            for (r, e) in [(&a, &b), (&b, &a)] {
                let (w, reference) = (near_weight(r, e), near_weight_reference(r, e));
                let size = norm(reference).max(1e-300);
                for c in 0..3 {
                    assert!(
                        (w[c] - reference[c]).abs() <= 1e-16 + 1e-14 * size,
                        "{w:?} against {reference:?}"
                    );
                    same += usize::from((w[c] as f32).to_bits() == (reference[c] as f32).to_bits());
                    total += 1;
                }
            }
        }
        assert!(same as f64 >= 0.999 * total as f64, "{same} of {total}");
    }

    #[test]
    fn a_plane_exchanges_nothing() {
        let n = 24;
        for (camera, depth) in [
            (ortho(), depths(n, |_, _| 100.0)),
            (ortho(), depths(n, |r, c| 100.0 + 0.3 * c - 0.2 * r)),
            (pinhole(n, 40.0), depths(n, |_, _| 500.0)),
        ] {
            let v = crate::geometry::vertices(&camera, n, n, &depth).unwrap();
            let x = Exchange::new(&camera, n, n, &v, None, None).unwrap();
            assert_eq!(x.pairs(), 0);
            let obs = vec![1.0f32; 3 * n * n];
            let vi = x.irradiance(&obs, 3, 1).unwrap();
            assert!(vi.iter().all(|w| *w == [0.0; 3]));
        }
    }

    /// Two far facets on the walls of a groove (the only ones in the mask): the weight is the
    /// point-to-point formula, `n_i . w_ij = A_j cos_i cos_j / (pi r^2)`, its direction towards
    /// the emitter, and V is the observation times it.
    #[test]
    fn two_facing_facets_give_the_point_form_factor() {
        let n = 32;
        let slope = 1.5;
        let depth = groove(n, slope);
        let camera = ortho();
        let v = crate::geometry::vertices(&camera, n, n, &depth).unwrap();
        let (pi, pj) = (10 * n + 2, 14 * n + 29);
        let mut mask = vec![false; n * n];
        mask[pi] = true;
        mask[pj] = true;
        let x = Exchange::new(&camera, n, n, &v, Some(&mask), None).unwrap();
        assert_eq!(x.pairs(), 2);
        let (ci, ni, ai) = x.facet(pi);
        let (cj, nj, aj) = x.facet(pj);
        // The walls: normals (+-slope, 0, -1) / |.|, areas sqrt(1 + slope^2).
        let s = (1.0 + slope * slope).sqrt();
        assert!((ai - s).abs() < 1e-12 && (aj - s).abs() < 1e-12);
        assert!((ni[0] - slope / s).abs() < 1e-12 && (nj[0] + slope / s).abs() < 1e-12);
        let d = sub(cj, ci);
        let r = norm(d);
        let (cos_i, cos_j) = (dot(ni, d) / r, -dot(nj, d) / r);
        let f_ij = aj * cos_i * cos_j / (std::f64::consts::PI * r * r);
        let f_ji = ai * cos_i * cos_j / (std::f64::consts::PI * r * r);
        let (j, w) = x.pairs_of(pi).next().unwrap();
        assert_eq!(j, pj);
        let w = w.map(f64::from);
        assert!(
            (dot(ni, w) / f_ij - 1.0).abs() < 1e-6,
            "{} {f_ij}",
            dot(ni, w)
        );
        assert!((norm(w) * r / dot(w, d) - 1.0).abs() < 1e-6);
        let (i, w) = x.pairs_of(pj).next().unwrap();
        assert_eq!(i, pi);
        assert!((dot(nj, w.map(f64::from)) / f_ji - 1.0).abs() < 1e-6);
        // V at pi under 2 lights: 3 and 5 times the weight; nothing at pixels without pairs.
        let mut obs = vec![0f32; 2 * n * n];
        obs[pj] = 3.0;
        obs[n * n + pj] = 5.0;
        let vi = x.irradiance(&obs, 2, 1).unwrap();
        let (j, w) = x.pairs_of(pi).next().unwrap();
        assert_eq!(j, pj);
        for (k, e) in [(0, 3.0), (1, 5.0)] {
            for c in 0..3 {
                assert!((vi[k * n * n + pi][c] - e * f64::from(w[c])).abs() < 1e-12);
            }
        }
        assert!(vi[pj] == [0.0; 3] && vi[n * n + 5] == [0.0; 3]);
    }

    /// Colour: V has the layout of the stack, (k, H, W, C), each channel gathered from the
    /// same channel; non-finite observations emit nothing.
    #[test]
    fn channels_keep_the_stack_layout() {
        let n = 16;
        let camera = ortho();
        let v = crate::geometry::vertices(&camera, n, n, &groove(n, 1.0)).unwrap();
        let x = Exchange::new(&camera, n, n, &v, None, None).unwrap();
        let (lights, channels) = (2, 3);
        let value = |k: usize, p: usize, ch: usize| (1 + k * 7 + ch * 3) as f32 + p as f32 / 100.0;
        let mut obs = vec![0f32; lights * n * n * channels];
        for k in 0..lights {
            for p in 0..n * n {
                for ch in 0..channels {
                    obs[(k * n * n + p) * channels + ch] = value(k, p, ch);
                }
            }
        }
        obs[(n * n + 8 * n + 9) * channels + 2] = f32::NAN;
        let vi = x.irradiance(&obs, lights, channels).unwrap();
        for p in [8 * n + 4, 3 * n + 12] {
            for k in 0..lights {
                for ch in 0..channels {
                    let mut expected = [0.0; 3];
                    for (j, w) in x.pairs_of(p) {
                        let e = if (k, j, ch) == (1, 8 * n + 9, 2) {
                            0.0
                        } else {
                            f64::from(value(k, j, ch))
                        };
                        for c in 0..3 {
                            expected[c] += e * f64::from(w[c]);
                        }
                    }
                    let got = vi[(k * n * n + p) * channels + ch];
                    assert!(norm(expected) > 0.0);
                    assert!(
                        norm(sub(got, expected)) < 1e-9 * norm(expected),
                        "{p} {k} {ch}"
                    );
                }
            }
        }
    }

    /// Brute-force irradiance vector at the point `y` with normal `ny` from the planar wall
    /// `origin + s a + t b` (`0 <= s, t <= 1`, normal `nw`) of uniform radiance 1 / pi (an image
    /// value of 1): `q x q` midpoint samples.
    fn wall_irradiance(
        y: [f64; 3],
        ny: [f64; 3],
        (origin, a, b, nw): ([f64; 3], [f64; 3], [f64; 3], [f64; 3]),
        q: usize,
    ) -> [f64; 3] {
        let area = norm(cross(a, b)) / (q * q) as f64;
        let mut e = [0.0; 3];
        for u in 0..q {
            for v in 0..q {
                let (s, t) = ((u as f64 + 0.5) / q as f64, (v as f64 + 0.5) / q as f64);
                let z: [f64; 3] = std::array::from_fn(|c| origin[c] + s * a[c] + t * b[c]);
                let (w, _) = point_kernel(y, ny, z, nw);
                for c in 0..3 {
                    e[c] += area * w[c];
                }
            }
        }
        e
    }

    /// A V-groove lit uniformly (every facet an image value of 1): V at facets of the left
    /// wall equals the irradiance vector of the right wall (a planar rectangle of uniform
    /// radiance 1 / pi), integrated by brute force and averaged over the receiver facet.
    #[test]
    fn a_groove_matches_the_integrated_irradiance_of_the_opposite_wall() {
        let n = 32;
        let half = n / 2;
        for slope in [1.0, 2.0] {
            let depth = groove(n, slope);
            let camera = ortho();
            let v = crate::geometry::vertices(&camera, n, n, &depth).unwrap();
            let x = Exchange::new(&camera, n, n, &v, None, None).unwrap();
            let vi = x.irradiance(&vec![1f32; n * n], 1, 1).unwrap();
            // The right wall: vertex columns m..n, rows 0..n.
            let at = |r: usize, c: usize| v[r * (n + 1) + c];
            let origin = at(0, half);
            let a = sub(at(0, n), origin);
            let b = sub(at(n, half), origin);
            let nw = crate::vec3::normalize(cross(b, a));
            assert!(nw[2] < 0.0 && nw[0] < 0.0);
            let mut worst: f64 = 0.0;
            for (r, c) in [
                (16, 15),
                (16, 14),
                (16, 12),
                (16, 8),
                (16, 1),
                (2, 10),
                (0, 15),
            ] {
                let p = r * n + c;
                let (_, ni, _) = x.facet(p);
                // The reference averaged over the receiver facet (8 x 8 points).
                let q = [at(r, c), at(r, c + 1), at(r + 1, c), at(r + 1, c + 1)];
                let mut reference = [0.0; 3];
                let m = 8;
                for u in 0..m {
                    for w in 0..m {
                        let (fy, fx) = ((u as f64 + 0.5) / m as f64, (w as f64 + 0.5) / m as f64);
                        let y: [f64; 3] = std::array::from_fn(|k| {
                            (1.0 - fy) * ((1.0 - fx) * q[0][k] + fx * q[1][k])
                                + fy * ((1.0 - fx) * q[2][k] + fx * q[3][k])
                        });
                        let e = wall_irradiance(y, ni, (origin, a, b, nw), 256);
                        for k in 0..3 {
                            reference[k] += e[k] / (m * m) as f64;
                        }
                    }
                }
                let (e, e_ref) = (dot(ni, vi[p]), dot(ni, reference));
                let rel = (e / e_ref - 1.0).abs();
                let angle = crate::vec3::angle(vi[p], reference);
                println!(
                    "groove slope {slope} facet ({r}, {c}): n.V {e:.5} reference {e_ref:.5} \
                     ({:+.2} %), angle {:.3} deg",
                    100.0 * (e / e_ref - 1.0),
                    angle.to_degrees()
                );
                worst = worst.max(rel);
                assert!(
                    rel < 0.025,
                    "slope {slope} facet ({r}, {c}): {e} vs {e_ref}"
                );
                assert!(angle.to_degrees() < 1.0, "{angle}");
            }
            assert!(worst > 0.0);
        }
    }

    /// The continuation past the border: a sampled sine on a tilted line (a corrugation's
    /// profile) is continued exactly while it stays in the samples' range, and clamped to it
    /// beyond; a line sloping towards the border becomes a flat shelf at its last depth; a
    /// short run continues its line, one sample stays flat.
    #[test]
    fn the_mesh_is_continued_past_the_border() {
        let f = |t: f64| 200.0 + 0.2 * t + 5.0 * (2.0 * std::f64::consts::PI * t / 6.4 + 0.3).sin();
        let samples: Vec<f64> = (0..16).map(|t| f(t as f64)).collect();
        let (lo, hi) = (
            samples.iter().copied().fold(f64::INFINITY, f64::min),
            samples.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        );
        let mut out = [0.0; 4];
        continue_line(&samples, &mut out);
        for (i, &z) in out.iter().enumerate() {
            let truth = f((16 + i) as f64).clamp(lo, hi);
            // Within 0.2 % of the amplitude (the fit's ridge).
            assert!((z - truth).abs() < 0.01, "{i}: {z} vs {truth}");
        }
        assert!(out.iter().any(|&z| z < hi - 1.0), "{out:?}");
        let ramp: Vec<f64> = (0..16).map(|t| 100.0 + t as f64).collect();
        continue_line(&ramp, &mut out);
        assert!(out.iter().all(|&z| (z - 115.0).abs() < 1e-9), "{out:?}");
        continue_line(&[3.0, 2.0, 1.0], &mut out);
        assert!(out.iter().all(|&z| (z - 1.0).abs() < 1e-12), "{out:?}");
        continue_line(&[7.0], &mut out);
        assert_eq!(out, [7.0; 4]);
    }

    /// The extended vertex grid: rows that reach the left and right borders are continued past
    /// them, then every column past the top and bottom (the corners too); a surface that ends
    /// inside the image (unknown border vertices) is not continued.
    #[test]
    fn the_margin_continues_only_surface_that_reaches_the_border() {
        let (hc, wc, m) = (10, 12, 3);
        let z = |r: f64, c: f64| 50.0 + 0.5 * r + 2.0 * (c / 2.0).sin();
        let depths: Vec<f64> = (0..(hc + 1) * (wc + 1))
            .map(|v| z((v / (wc + 1)) as f64, (v % (wc + 1)) as f64))
            .collect();
        let ext = extend_depths(&depths, hc, wc, m).unwrap();
        let cols = wc + 1 + 2 * m;
        assert_eq!(ext.len(), (hc + 1 + 2 * m) * cols);
        assert!(ext.iter().all(|z| z.is_finite()));
        for r in 0..=hc {
            for c in 0..=wc {
                assert_eq!(ext[(r + m) * cols + c + m], depths[r * (wc + 1) + c]);
            }
        }
        // A surface inside the image only: the border vertices unknown, no margin.
        let inner: Vec<f64> = (0..(hc + 1) * (wc + 1))
            .map(|v| {
                let (r, c) = (v / (wc + 1), v % (wc + 1));
                let border = r == 0 || c == 0 || r == hc || c == wc;
                if border {
                    f64::NAN
                } else {
                    depths[v]
                }
            })
            .collect();
        let ext = extend_depths(&inner, hc, wc, m).unwrap();
        for (v, z) in ext.iter().enumerate() {
            let (r, c) = (v / cols, v % cols);
            let in_view = r >= m && r <= m + hc && c >= m && c <= m + wc;
            assert_eq!(
                z.is_finite(),
                in_view && inner[(r - m) * (wc + 1) + c - m].is_finite()
            );
        }
    }

    /// The field of a corrugated surface that fills the image (orthographic, lit by one point
    /// light): with the lights given, the margin past the border sends light to the border
    /// facets that face it (their `V` grows) and much less to the centre; without lights (no
    /// margin) the field is the image's alone.
    #[test]
    fn the_margin_lights_the_border() {
        let n = 64;
        let camera = ortho();
        let depth = depths(n, |_, c| {
            100.0 - 6.0 * (2.0 * std::f64::consts::PI * c / 40.0).sin()
        });
        let grid = crate::grid::Grid::new(n, n, None).unwrap();
        let geometry = crate::geometry::Geometry::new(&camera, &grid).unwrap();
        let u = grid.gather_vertices(&depth).unwrap();
        let images = vec![0.3f32; n * n];
        let obs = crate::local::Observations::from_stack(&images, 1, n * n, 1);
        let lights = [crate::Light::point([32.0, 32.0, 0.0])];
        let plain =
            IndirectField::of_mesh(&camera, &grid, &geometry, &u, &obs, &[], 1, None, 1).unwrap();
        let field =
            IndirectField::of_mesh(&camera, &grid, &geometry, &u, &obs, &lights, 1, None, 1)
                .unwrap();
        assert!(field.pairs() > plain.pairs());
        let energy = |f: &IndirectField, p: usize| norm(f.at(p, n)[0]);
        // Column 1 faces the margin past the left border (the surface rises from the left
        // border towards its crest at column 10: its facets turn to the left).
        let (border, centre) = (32 * n + 1, 32 * n + 32);
        println!(
            "border {} -> {}, centre {} -> {}",
            energy(&plain, border),
            energy(&field, border),
            energy(&plain, centre),
            energy(&field, centre)
        );
        let gain = |p: usize| energy(&field, p) / energy(&plain, p) - 1.0;
        assert!(gain(border) > 0.2 && gain(border) > 2.0 * gain(centre).abs());
    }

    /// A wall raised at the bottom of a groove blocks two facets on opposite walls from each
    /// other; facets high on the walls see over it. Orthographic and pinhole.
    #[test]
    fn a_wall_blocks_the_exchange() {
        let n = 32;
        let m = (n / 2) as f64;
        for pinhole_camera in [false, true] {
            let scale = if pinhole_camera { 10.0 } else { 1.0 };
            let camera = if pinhole_camera {
                pinhole(n, 100.0)
            } else {
                ortho()
            };
            let shape = |wall: f64| {
                depths(n, move |_, c| {
                    let z = 100.0 + 1.0 * (m - (c - m).abs());
                    let raised = if (c - m).abs() <= 1.0 { wall } else { 0.0 };
                    scale * (z - raised)
                })
            };
            // Facets 5 columns either side of the bottom (depth about 111), and 14 columns
            // out (depth about 102).
            let row = 16;
            let (low_l, low_r) = (row * n + 10, row * n + 21);
            let (high_l, high_r) = (row * n + 1, row * n + 30);
            let pair = |x: &Exchange, a: usize, b: usize| x.pairs_of(a).any(|(j, _)| j == b);
            for (wall, blocked) in [(0.0, false), (12.0, true)] {
                let v = crate::geometry::vertices(&camera, n, n, &shape(wall)).unwrap();
                let x = Exchange::new(&camera, n, n, &v, None, None).unwrap();
                assert_eq!(
                    pair(&x, low_l, low_r),
                    !blocked,
                    "wall {wall} {pinhole_camera}"
                );
                assert_eq!(
                    pair(&x, low_r, low_l),
                    !blocked,
                    "wall {wall} {pinhole_camera}"
                );
                assert!(pair(&x, high_l, high_r), "wall {wall} {pinhole_camera}");
            }
        }
    }

    /// Reciprocity `A_i F_ij = A_j F_ji` (with `F_ij = n_i . w_ij`) for every pair, far and
    /// near, on a bowl seen by a pinhole camera; the pairs come in both directions. Far pairs
    /// are reciprocal by the formula, near pairs by construction (the two quadratures before it
    /// are printed).
    #[test]
    fn reciprocity_holds_for_every_pair() {
        let n = 24;
        let camera = pinhole(n, 30.0);
        let c = n as f64 / 2.0;
        let depth = depths(n, |r, col| {
            let q = ((r - c).powi(2) + (col - c).powi(2)) / (c * c);
            500.0 + 150.0 * (1.0 - q).max(0.0)
        });
        let v = crate::geometry::vertices(&camera, n, n, &depth).unwrap();
        let mask: Vec<bool> = (0..n * n).map(|p| p % 7 != 3).collect();
        let x = Exchange::new(&camera, n, n, &v, Some(&mask), None).unwrap();
        assert!(x.pairs() > 10_000, "{}", x.pairs());
        let facet = facets_of(&x, &camera, n, &v);
        let (mut checked, mut raw) = (0, Vec::new());
        for i in 0..n * n {
            let (_, ni, ai) = x.facet(i);
            for (j, w) in x.pairs_of(i) {
                let (_, nj, aj) = x.facet(j);
                let (_, back) = x
                    .pairs_of(j)
                    .find(|&(k, _)| k == i)
                    .expect("the reverse pair");
                let (w, back) = (w.map(f64::from), back.map(f64::from));
                let a = ai * dot(ni, w);
                let b = aj * dot(nj, back);
                assert!(a > 0.0 && b > 0.0, "{i} {j}: {a} {b}");
                // f32 weights: the error is relative to |w|, not to n . w.
                let scale = ai * norm(w) + aj * norm(back);
                assert!((a - b).abs() <= 1e-6 * scale, "{i} {j}: {a} {b}");
                let (fi, fj) = (facet(i), facet(j));
                if is_near(&fi, &fj) && i < j {
                    let (u, v) = raw_pair_weights(&fi, &fj);
                    let (a, b) = (ai * dot(ni, u), aj * dot(nj, v));
                    raw.push((a - b).abs() / (0.5 * (a + b)));
                }
                checked += 1;
                assert!(mask[i] && mask[j]);
            }
        }
        assert_eq!(checked, x.pairs());
        // Conservation: the form factors of a receiver sum to at most 1 (its whole hemisphere).
        let sums: Vec<f64> = (0..n * n)
            .map(|i| {
                let (_, ni, _) = x.facet(i);
                x.pairs_of(i).map(|(_, w)| dot(ni, w.map(f64::from))).sum()
            })
            .collect();
        let most = sums.iter().copied().fold(0.0, f64::max);
        println!("the largest sum of form factors of a receiver: {most:.4}");
        assert!(most > 0.2 && most < 1.0, "{most}");
        raw.sort_by(f64::total_cmp);
        println!(
            "near pairs: {} of {}; before the mean, |A_i F_ij - A_j F_ji| / mean: median {:.2e}, \
             90 % {:.2e}, max {:.2e}",
            raw.len(),
            checked / 2,
            raw[raw.len() / 2],
            raw[raw.len() * 9 / 10],
            raw[raw.len() - 1]
        );
        assert!(raw.len() > 100);
    }

    /// The near pairs' vectors stay within `|w_ij| <= 1 + A_j / (2 A_i)` (the vector of a solid
    /// angle within a hemisphere, `<= 1`, plus the correction to the mean form factor) on a
    /// steep corrugated sheet seen by a pinhole camera, where some receivers see a near emitter
    /// nearly edge-on: scaling those vectors to the mean form factor (the rule before) exceeds
    /// the bound there (the pairs that made the benchmark sheet's pits).
    #[test]
    fn near_pairs_seen_edge_on_stay_bounded() {
        let n = 32;
        let camera = pinhole(n, 30.0);
        let depth = depths(n, |r, col| {
            200.0 + 9.0 * (2.0 * std::f64::consts::PI * (col + 0.3 * r) / 7.0).sin()
        });
        let v = crate::geometry::vertices(&camera, n, n, &depth).unwrap();
        let x = Exchange::new(&camera, n, n, &v, None, None).unwrap();
        let facet = facets_of(&x, &camera, n, &v);
        let (mut near, mut scaled_over) = (0, 0);
        for i in 0..n * n {
            let (_, ni, ai) = x.facet(i);
            for (j, w) in x.pairs_of(i) {
                let (_, nj, aj) = x.facet(j);
                let w = w.map(f64::from);
                let bound = 1.0 + aj / (2.0 * ai);
                assert!(norm(w) <= bound * (1.0 + 1e-6), "{i} {j}: {w:?} {bound}");
                let (fi, fj) = (facet(i), facet(j));
                if !is_near(&fi, &fj) {
                    continue;
                }
                near += 1;
                let (u, back) = raw_pair_weights(&fi, &fj);
                let (a, b) = (ai * dot(ni, u), aj * dot(nj, back));
                assert!(norm(u) <= 1.0 + 1e-9, "{i} {j}: {u:?}");
                if norm(u) * 0.5 * (a + b) / a > bound {
                    scaled_over += 1;
                }
            }
        }
        println!("near pairs: {near}; scaled to the mean, over the bound: {scaled_over}");
        assert!(near > 1000 && scaled_over > 0, "{near} {scaled_over}");
    }

    /// A light that the margin hid in the round before stays hidden (`kept`), while at least
    /// `MIN_LIT` lights are left; without `kept` the same field leaves it lit.
    #[test]
    fn hidden_lights_are_kept_for_the_next_round() {
        let n = 32;
        let camera = ortho();
        let depth = depths(n, |_, c| {
            100.0 - 6.0 * (2.0 * std::f64::consts::PI * c / 20.0).sin()
        });
        let grid = crate::grid::Grid::new(n, n, None).unwrap();
        let geometry = crate::geometry::Geometry::new(&camera, &grid).unwrap();
        let u = grid.gather_vertices(&depth).unwrap();
        let images = vec![0.3f32; 4 * n * n];
        let obs = crate::local::Observations::from_stack(&images, 4, n * n, 1);
        let lights: Vec<crate::Light> = [[-20.0, 0.0], [52.0, 0.0], [16.0, -20.0], [16.0, 52.0]]
            .iter()
            .map(|&[x, y]| crate::Light::point([x, y, 0.0]))
            .collect();
        let field = |kept: Option<Vec<u64>>| {
            IndirectField::of_mesh(&camera, &grid, &geometry, &u, &obs, &lights, 1, None, 1)
                .unwrap()
                .with_unlit(&grid, &geometry, &u, &lights, kept)
                .unwrap()
        };
        let mut first = field(None);
        let before = first.take_hidden().unwrap_or_else(|| vec![0; n * n]);
        // A facet in the middle, every light in front of it and none hidden.
        let p = 16 * n + 16;
        assert!((0..4).all(|k| !first.is_unlit(p, k)));
        let mut kept = before.clone();
        kept[p] |= 1 << 2;
        let again = field(Some(kept));
        assert!(again.is_unlit(p, 2) && !again.is_unlit(p, 1));
        // What was hidden before is still hidden.
        for (q, &bits) in before.iter().enumerate() {
            for k in 0..4 {
                if bits & (1 << k) != 0 {
                    assert!(again.is_unlit(q, k), "{q} {k}");
                }
            }
        }
    }

    /// The lights behind each facet and those the margin hides ([`IndirectField::with_unlit`]:
    /// the point lights' `beta` in lanes of [`MARK_LANES`] facets, the centre projected once
    /// per facet) are those of the scalar rule facet by facet (`n . beta_k(c) <= 0` with
    /// `Light::beta`, then `MarginMesh::hides` with the centre projected for each light and the
    /// [`MIN_LIT`] rule): on a sheet of ridges that reaches the border, with isotropic and
    /// anisotropic point lights and a directional one, 30² facets (a last chunk of 4), both
    /// cameras.
    #[test]
    fn the_unlit_lights_in_lanes_are_those_of_the_scalar_rule() {
        let n = 30;
        let depth = depths(n, |r, c| 100.0 - 6.0 * (0.45 * c + 0.1 * r).sin());
        let led = |p: [f64; 3], axis: [f64; 3], mu: f64| crate::Light::Point {
            position: p,
            intensity: [1.0; 3],
            axis,
            mu,
        };
        let lights = vec![
            crate::Light::point([-20.0, 0.0, 0.0]),
            crate::Light::point([52.0, 10.0, 0.0]),
            led([16.0, -20.0, 0.0], [0.0, 0.2, 1.0], 1.5),
            led([16.0, 52.0, 10.0], [0.1, -0.3, 0.9], 0.7),
            crate::Light::Directional {
                direction: [0.6, 0.0, -0.8],
                intensity: [1.0; 3],
            },
            crate::Light::point([5.0, 5.0, 60.0]),
        ];
        let pinhole = Camera::Pinhole {
            k: [[40.0, 0.0, 14.5], [0.0, 40.0, 14.5], [0.0, 0.0, 1.0]],
            distortion: [0.0; 5],
        };
        let mut hidden_any = 0;
        for camera in [ortho(), pinhole] {
            let grid = crate::grid::Grid::new(n, n, None).unwrap();
            let geometry = crate::geometry::Geometry::new(&camera, &grid).unwrap();
            let u = grid.gather_vertices(&depth).unwrap();
            let images = vec![0.3f32; lights.len() * n * n];
            let obs = crate::local::Observations::from_stack(&images, lights.len(), n * n, 1);
            let field =
                IndirectField::of_mesh(&camera, &grid, &geometry, &u, &obs, &lights, 1, None, 1)
                    .unwrap();
            let margin = field.margin.clone().expect("a margin");
            let field = field
                .with_unlit(&grid, &geometry, &u, &lights, None)
                .unwrap();
            for (f, &p) in grid.facets.iter().enumerate() {
                let q = geometry.facet_corners(&grid, f, &u);
                let (c, nrm) = (
                    crate::geometry::quad_centre(&q),
                    crate::geometry::quad_normal(&q),
                );
                let behind: Vec<bool> = lights
                    .iter()
                    .map(|l| not_above(dot(nrm, l.beta(c).0), 0.0))
                    .collect();
                let hidden: Vec<bool> = lights
                    .iter()
                    .zip(&behind)
                    .map(|(l, &b)| !b && margin.hides(c, margin.camera.project(c), l))
                    .collect();
                let unlit = behind.iter().chain(&hidden).filter(|&&x| x).count();
                let applied = lights.len().saturating_sub(unlit) >= MIN_LIT;
                hidden_any += usize::from(applied && hidden.iter().any(|&h| h));
                for k in 0..lights.len() {
                    let expected = behind[k] || (applied && hidden[k]);
                    assert_eq!(field.is_unlit(p as usize, k), expected, "{p} {k}");
                }
            }
            lanes_are_the_lookups(&field, n, n * n);
        }
        assert!(
            hidden_any > 0,
            "the margin hides no light: the test tests nothing of it"
        );
    }

    #[test]
    fn the_cap_and_the_shapes_are_checked() {
        let n = 16;
        let camera = ortho();
        let v = crate::geometry::vertices(&camera, n, n, &groove(n, 1.0)).unwrap();
        let err = Exchange::new(&camera, n, n, &v, None, Some(100)).unwrap_err();
        assert!(err.to_string().contains("max_pairs = 100"), "{err}");
        assert!(Exchange::new(&camera, n, n, &v[1..], None, None).is_err());
        assert!(Exchange::new(&camera, n, n, &v, Some(&[true; 3]), None).is_err());
        let x = Exchange::new(&camera, n, n, &v, None, None).unwrap();
        assert!(x.irradiance(&[1.0; 7], 1, 1).is_err());
        assert_eq!(x.bytes(), 16 * x.pairs() + 8 * (n * n + 1) + 56 * n * n);
    }

    /// The benchmark's bowl (benchmarks/pbr/render.py, `bowl_surface`) at n x n pixels: the
    /// inside of a spherical cap, rim of radius 35 mm at 200 mm, 20 mm deep, pinhole camera
    /// with f = 2 n; the mask is the pixels inside the rim facing the camera (cosine > 0.4).
    fn benchmark_bowl(n: usize) -> (Camera, Vec<[f64; 3]>, Vec<bool>) {
        let f = 2.0 * n as f64;
        let c = (n as f64 - 1.0) / 2.0;
        let camera = pinhole(n, f);
        let (rim, radius_rim, depth_bowl) = (200.0, 35.0, 20.0);
        let radius = (radius_rim * radius_rim + depth_bowl * depth_bowl) / (2.0 * depth_bowl);
        let centre = [0.0, 0.0, rim + depth_bowl - radius];
        let mut inside = vec![false; (n + 1) * (n + 1)];
        let depth = depths(n, |r, col| {
            let d = crate::vec3::normalize([(col - 0.5 - c) / f, (r - 0.5 - c) / f, 1.0]);
            let b = dot(d, centre);
            let disc = b * b - dot(centre, centre) + radius * radius;
            let z = (b + disc.max(0.0).sqrt()) * d[2];
            if disc > 0.0 && z >= rim {
                z
            } else {
                rim
            }
        });
        for (v, z) in depth.iter().enumerate() {
            inside[v] = *z > rim;
        }
        let v = crate::geometry::vertices(&camera, n, n, &depth).unwrap();
        let mask = (0..n * n)
            .map(|p| {
                let w = (p / n) * (n + 1) + p % n;
                let corners = [w, w + 1, w + n + 1, w + n + 2];
                let q = corners.map(|i| v[i]);
                let centre = crate::geometry::quad_centre(&q);
                let normal = crate::geometry::quad_normal(&q);
                corners.iter().all(|&i| inside[i])
                    && -dot(normal, crate::vec3::normalize(centre)) > 0.4
            })
            .collect();
        (camera, v, mask)
    }

    /// Inside a sphere of radius R the form factor from a point to a surface element is
    /// `dA / (4 pi R^2)` (both cosines are `r / (2 R)`): on the benchmark's bowl (a spherical
    /// cap, every facet seeing every other), each receiver's form factors sum to the area of
    /// the other facets over `4 pi R^2`, and each pair's is `A_j / (4 pi R^2)`.
    #[test]
    fn a_spherical_bowl_gives_the_sphere_form_factors() {
        let n = 48;
        let (camera, v, mask) = benchmark_bowl(n);
        let x = Exchange::new(&camera, n, n, &v, Some(&mask), None).unwrap();
        let facets = mask.iter().filter(|&&m| m).count();
        assert_eq!(x.pairs(), facets * (facets - 1));
        let radius = (35.0f64 * 35.0 + 20.0 * 20.0) / 40.0;
        let sphere = 4.0 * std::f64::consts::PI * radius * radius;
        let total: f64 = (0..n * n).filter(|&p| mask[p]).map(|p| x.facet(p).2).sum();
        let (mut worst_sum, mut far, mut near): (f64, f64, Vec<f64>) = (0.0, 0.0, Vec::new());
        for i in (0..n * n).filter(|&p| mask[p]) {
            let (ci, ni, ai) = x.facet(i);
            let mut sum = 0.0;
            for (j, w) in x.pairs_of(i) {
                let (cj, _, aj) = x.facet(j);
                let f = dot(ni, w.map(f64::from));
                let error = (f / (aj / sphere) - 1.0).abs();
                let d = sub(cj, ci);
                if dot(d, d) < NEAR * NEAR * ai.max(aj) {
                    near.push(error);
                } else {
                    far = far.max(error);
                }
                sum += f;
            }
            worst_sum = worst_sum.max((sum / ((total - ai) / sphere) - 1.0).abs());
        }
        near.sort_by(f64::total_cmp);
        println!(
            "spherical bowl {n}x{n}, {facets} facets: sum of form factors within {:.3} %; each \
             pair's against A_j / (4 pi R^2): far pairs within {:.2} %, near pairs median {:.2} \
             %, max {:.2} %",
            100.0 * worst_sum,
            100.0 * far,
            100.0 * near[near.len() / 2],
            100.0 * near[near.len() - 1]
        );
        assert!(worst_sum < 0.005 && far < 0.05, "{worst_sum} {far}");
        assert!(near[near.len() / 2] < 0.05, "{near:?}");
    }

    /// Timings at 64 x 64 facets, 16 lights, on the benchmark's bowl (pinhole):
    /// `cargo test -p nplps --release --lib indirect::tests::timings -- --ignored --nocapture`.
    #[test]
    #[ignore = "timings"]
    fn timings() {
        for n in [32, 64] {
            let (camera, v, mask) = benchmark_bowl(n);
            let facets = mask.iter().filter(|&&m| m).count();
            let lights = 16;
            let obs: Vec<f32> = (0..lights * n * n)
                .map(|i| (i % 97) as f32 / 97.0)
                .collect();
            let default = Exchange::new(&camera, n, n, &v, Some(&mask), None);
            println!(
                "indirect timing: {n}x{n} bowl, {facets} facets; default cap: {}",
                match &default {
                    Ok(x) => format!("{} pairs", x.pairs()),
                    Err(e) => e.to_string(),
                }
            );
            for _ in 0..2 {
                let start = std::time::Instant::now();
                let x = Exchange::new(&camera, n, n, &v, Some(&mask), Some(1 << 26)).unwrap();
                let build = start.elapsed().as_secs_f64();
                let mut pass = Vec::new();
                for _ in 0..5 {
                    let start = std::time::Instant::now();
                    let vi = x.irradiance(&obs, lights, 1).unwrap();
                    pass.push(start.elapsed().as_secs_f64());
                    assert_eq!(vi.len(), lights * n * n);
                }
                pass.sort_by(f64::total_cmp);
                println!(
                    "indirect timing: {n}x{n} bowl, {facets} facets, {} threads: build {build:.3} \
                     s, {} pairs ({:.1} % of F (F - 1), {:.1} MB), pass of {lights} lights \
                     median {:.4} s (min {:.4})",
                    rayon::current_num_threads(),
                    x.pairs(),
                    100.0 * x.pairs() as f64 / (facets * (facets - 1)) as f64,
                    x.bytes() as f64 / 1e6,
                    pass[2],
                    pass[0]
                );
            }
        }
    }
}
