//! Coarse-to-fine: an image pyramid whose coarse levels give the finer ones their starting
//! surface.
//!
//! Level `l + 1` halves level `l` in each direction (an owned image stack, built image by image
//! and row by row): coarse pixel (R, C) averages the usable observations of its masked
//! children `(2R + a, 2C + b)` (a child observation is usable when
//! every channel is finite and strictly between `dark` and `saturation`; none usable: missing),
//! and it is masked when any child is. The camera follows exactly, as binning does:
//! orthographic pixels double in size with the same origin; a pinhole K becomes
//! `fx / 2, fy / 2, s / 2, cx' = (cx - 1/2) / 2, cy' = (cy - 1/2) / 2`. Either way coarse vertex
//! (R, C) lies on the same ray as fine vertex (2R, 2C), so a coarse surface is carried to the
//! finer level by bilinear interpolation of its unknowns (depth, or log-depth for a pinhole
//! camera), and then shifted to the finer level's gauge.
//!
//! The coarsest level converges from the starting plane, where low-frequency shape is cheap; each
//! finer level then needs only the few iterations that its detail asks for (the usual `tol`
//! rule stops it). The default number of levels halves the image while the coarser level keeps
//! at least [`COARSEST_SIDE`] pixels along its longer side.

use crate::memory::{try_collect, try_par_collect, try_par_vec, try_vec};
use rayon::prelude::*;

use crate::error::Result;
use crate::geometry::Geometry;
use crate::grid::{Grid, INACTIVE};
use crate::local::{u16_value, usable, FitSettings, Observations, Stored};
use crate::problem::Problem;
use crate::rig::{Camera, Rig};
use crate::system::Prior;

/// The automatic pyramid stops before the longer side of a level drops below this.
pub const COARSEST_SIDE: usize = 128;

/// Most pyramid levels.
pub const MAX_LEVELS: usize = 12;

/// Number of levels for an H x W image: `requested` if it is not 0, else automatic (see the
/// module documentation). Never more than the image can be halved.
pub fn levels_for(height: usize, width: usize, requested: usize) -> usize {
    let mut possible = 1;
    let (mut h, mut w) = (height, width);
    while possible < MAX_LEVELS && h > 1 && w > 1 {
        h = h.div_ceil(2);
        w = w.div_ceil(2);
        possible += 1;
    }
    if requested > 0 {
        return requested.min(possible);
    }
    let mut levels = 1;
    let (mut h, mut w) = (height, width);
    while levels < possible && h.max(w).div_ceil(2) >= COARSEST_SIDE {
        h = h.div_ceil(2);
        w = w.div_ceil(2);
        levels += 1;
    }
    levels
}

/// The camera of the level below (see the module documentation).
pub fn coarser_camera(camera: &Camera) -> Camera {
    match *camera {
        Camera::Orthographic { pixel_size, origin } => Camera::Orthographic {
            pixel_size: [2.0 * pixel_size[0], 2.0 * pixel_size[1]],
            origin,
        },
        Camera::Pinhole { k, distortion } => Camera::Pinhole {
            k: [
                [k[0][0] / 2.0, k[0][1] / 2.0, (k[0][2] - 0.5) / 2.0],
                [0.0, k[1][1] / 2.0, (k[1][2] - 0.5) / 2.0],
                [0.0, 0.0, 1.0],
            ],
            distortion,
        },
    }
}

/// The data of the level below a problem, owned (the rig is built separately, since the
/// coarse problem borrows it).
pub struct Coarsened {
    /// The coarse observations, an owned (k, H, W, C) stack.
    pub obs: Observations<'static>,
    /// The coarse starting unknowns (one per coarse unknown) and the coarse grid.
    pub grid: Grid,
    /// Starting unknowns of the coarse grid.
    pub u0: Vec<f64>,
    /// The prior on the coarse unknowns, if the problem has one.
    pub prior: Option<Prior>,
}

/// Builds the level below `problem` (see the module documentation).
pub fn coarsen(problem: &Problem<'_>, settings: &FitSettings) -> Result<Coarsened> {
    let grid = &problem.grid;
    let (h, w) = (grid.height, grid.width);
    let (ch, cw) = (h.div_ceil(2), w.div_ceil(2));
    // Which of its 4 children (bits 0..3: (0,0), (0,1), (1,0), (1,1)) each coarse pixel has.
    let children: Vec<u8> = try_par_collect(
        (0..ch * cw).into_par_iter().map(|cp| {
            let (cr, cc) = (cp / cw, cp % cw);
            let mut bits = 0u8;
            for (bit, (a, b)) in [(0, 0), (0, 1), (1, 0), (1, 1)].into_iter().enumerate() {
                let (r, c) = (2 * cr + a, 2 * cc + b);
                if r < h && c < w && grid.facet_of_pixel(r * w + c) != crate::grid::INACTIVE {
                    bits |= 1 << bit;
                }
            }
            bits
        }),
        "the coarse mask",
    )?;
    // A coarse pixel is masked when any of its children is.
    let mask: Vec<bool> = try_collect(children.iter().map(|&bits| bits != 0), "the coarse mask")?;
    problem.cancel.check()?;
    let coarse_grid = Grid::new(ch, cw, Some(&mask))?;
    problem.cancel.check()?;
    let (k, channels) = (problem.obs.k, problem.obs.channels);
    let obs = &problem.obs;
    // Image by image, coarse row by coarse row (streams through the finer stack: each output
    // row reads its two finer rows as slices); coarse pixels outside the coarse mask stay NaN.
    // (filled in parallel: 4 bytes a coarse pixel and light, 190 MB under a 12 MP stack of 16)
    let mut values = try_par_vec(k * ch * cw * channels, f32::NAN, "the coarse images")?;
    let shape = RowShape {
        h,
        w,
        ch,
        cw,
        channels,
        plane: obs.plane,
    };
    match &obs.data {
        Stored::F32(d) => coarsen_rows(
            &d[..],
            shape,
            &children,
            settings,
            &mut values,
            problem,
            |v| v,
        ),
        Stored::U16(d) => coarsen_rows(
            d,
            shape,
            &children,
            settings,
            &mut values,
            problem,
            u16_value,
        ),
    }
    problem.cancel.check()?;
    // (read in place: a constant start is not written out as a vector of every fine unknown,
    // 96 MB of fresh pages at 12 MP, to read a quarter of it)
    let u0 = subsample(grid, |i| problem.u0.at(i), &coarse_grid, f64::NAN)?;
    let u0 = fill_missing(&coarse_grid, u0, &problem.gauge)?;
    let prior = match problem.prior.as_ref() {
        Some(p) => Some(Prior {
            values: subsample(grid, |i| p.values[i], &coarse_grid, f64::NAN)?,
            weight: p.weight,
        }),
        None => None,
    };
    Ok(Coarsened {
        obs: Observations::owned_stack(values, k, ch * cw, channels),
        grid: coarse_grid,
        u0,
        prior,
    })
}

/// The shape of a finer stack and of its coarse rows (see [`coarsen_rows`]).
#[derive(Clone, Copy)]
struct RowShape {
    /// Finer rows and columns.
    h: usize,
    w: usize,
    /// Coarse rows and columns.
    ch: usize,
    cw: usize,
    channels: usize,
    /// Values per finer image.
    plane: usize,
}

/// The coarse images (rows of `values`, image-major) from the finer stack `data`, whose
/// samples read as `value(v)`: monomorphised per sample type, so that the inner loop reads
/// plain slices (the same arithmetic as [`Observations::at`] and [`usable`], so the result is
/// the same to the bit whatever the storage).
fn coarsen_rows<T: Copy + Sync>(
    data: &[T],
    shape: RowShape,
    children: &[u8],
    settings: &FitSettings,
    values: &mut [f32],
    problem: &Problem<'_>,
    value: impl Fn(T) -> f32 + Sync,
) {
    let RowShape {
        h,
        w,
        ch,
        cw,
        channels,
        plane,
    } = shape;
    let row_len = cw * channels;
    let fine_row = w * channels;
    values
        .par_chunks_mut(row_len)
        .enumerate()
        .for_each(|(j, out)| {
            if problem.cancel.is_cancelled() {
                return;
            }
            let (i, cr) = (j / ch, j % ch);
            let image = &data[i * plane..(i + 1) * plane];
            let top = &image[2 * cr * fine_row..(2 * cr + 1) * fine_row];
            let bottom = if 2 * cr + 1 < h {
                &image[(2 * cr + 1) * fine_row..(2 * cr + 2) * fine_row]
            } else {
                &image[..0]
            };
            let children = &children[cr * cw..(cr + 1) * cw];
            if channels == 1 && bottom.len() == w {
                coarse_row_grey(top, bottom, children, settings, out, &value);
                return;
            }
            let mut sum = [0.0f64; 3];
            let mut o = [0.0f32; 3];
            for (cc, &bits) in children.iter().enumerate() {
                if bits == 0 {
                    continue;
                }
                let mut n = 0u32;
                sum[..channels].fill(0.0);
                for bit in 0..4 {
                    if bits & (1 << bit) == 0 {
                        continue;
                    }
                    let row = if bit < 2 { top } else { bottom };
                    let at = (2 * cc + (bit & 1)) * channels;
                    for (o, &v) in o[..channels].iter_mut().zip(&row[at..at + channels]) {
                        *o = value(v);
                    }
                    if usable(&o[..channels], settings) {
                        n += 1;
                        for (s, &v) in sum.iter_mut().zip(&o[..channels]) {
                            *s += v as f64;
                        }
                    }
                }
                if n > 0 {
                    for ch in 0..channels {
                        out[cc * channels + ch] = (sum[ch] / n as f64) as f32;
                    }
                }
            }
        });
}

/// One coarse row of a grey stack from its two finer rows `top` and `bottom` (both present):
/// the operations of the general loop of [`coarsen_rows`] in its order (children (0,0), (0,1),
/// (1,0), (1,1); each usable value added in f64, the sum divided by their count), written without
/// branches for the common case of 4 children (an unusable child adds `+0.0`, which leaves the
/// sum unchanged to the bit: it starts at `+0.0` and never becomes `-0.0`), so the same bits.
#[inline(always)]
fn coarse_row_grey<T: Copy>(
    top: &[T],
    bottom: &[T],
    children: &[u8],
    settings: &FitSettings,
    out: &mut [f32],
    value: &impl Fn(T) -> f32,
) {
    let (dark, saturation) = (settings.dark, settings.saturation);
    let take = |v: T| {
        let x = value(v) as f64;
        let ok = x > dark && x < saturation;
        (if ok { x } else { 0.0 }, u32::from(ok))
    };
    for (cc, (&bits, o)) in children.iter().zip(out.iter_mut()).enumerate() {
        if bits == 0 {
            continue;
        }
        let at = 2 * cc;
        let mut sum = 0.0f64;
        let mut n = 0u32;
        if bits == 0b1111 {
            for v in [top[at], top[at + 1], bottom[at], bottom[at + 1]] {
                let (x, ok) = take(v);
                sum += x;
                n += ok;
            }
        } else {
            for bit in 0..4 {
                if bits & (1 << bit) != 0 {
                    let row = if bit < 2 { top } else { bottom };
                    let (x, ok) = take(row[at + (bit & 1)]);
                    sum += x;
                    n += ok;
                }
            }
        }
        if n > 0 {
            *o = (sum / n as f64) as f32;
        }
    }
}

/// Values of the coarse unknowns taken from the fine vertex on the same ray (`value(i)` of its
/// fine unknown `i`; `missing` where that fine vertex is not an unknown).
fn subsample(
    fine: &Grid,
    value: impl Fn(usize) -> f64,
    coarse: &Grid,
    missing: f64,
) -> Result<Vec<f64>> {
    let (fw, cw) = (fine.width + 1, coarse.width + 1);
    try_collect(
        coarse.active.iter().map(|&v| {
            let v = v as usize;
            let (r, c) = (2 * (v / cw), 2 * (v % cw));
            if r <= fine.height && c <= fine.width {
                let u = fine.vertex_unknown[r * fw + c];
                if u != INACTIVE {
                    return value(u as usize);
                }
            }
            missing
        }),
        "the coarse depths",
    )
}

/// Replaces NaN starting unknowns by the mean of the finite ones of their region (or of the
/// fine gauges when a region has none).
fn fill_missing(grid: &Grid, mut u: Vec<f64>, fine_gauge: &[f64]) -> Result<Vec<f64>> {
    // One per region: up to one per few unknowns for a speckled mask.
    let mut sum = try_vec(grid.n_regions, 0.0, "the coarse depths")?;
    let mut count = try_vec(grid.n_regions, 0usize, "the coarse depths")?;
    for (v, &r) in u.iter().zip(&grid.region_of_unknown) {
        if v.is_finite() {
            sum[r as usize] += v;
            count[r as usize] += 1;
        }
    }
    let fallback = fine_gauge.iter().sum::<f64>() / fine_gauge.len() as f64;
    for (v, &r) in u.iter_mut().zip(&grid.region_of_unknown) {
        if !v.is_finite() {
            let r = r as usize;
            *v = if count[r] > 0 {
                sum[r] / count[r] as f64
            } else {
                fallback
            };
        }
    }
    Ok(u)
}

/// The coarse problem of `data` under `rig` (the coarse rig).
pub fn coarse_problem(data: Coarsened, rig: &Rig) -> Result<Problem<'_>> {
    let geometry = Geometry::new(&rig.camera, &data.grid)?;
    let gauge = data.grid.region_means(&data.u0);
    Ok(Problem {
        rig,
        geometry,
        gauge,
        grid: data.grid,
        obs: data.obs,
        u0: crate::problem::Start::Values(data.u0),
        negative_observations: 0,
        prior: data.prior,
        cancel: crate::Cancel::default(),
    })
}

/// The coarse levels 1..levels of `problem` (level 1 first) under `rigs` (the coarse rigs, level
/// 1 first, see [`coarse_rigs`]).
pub fn coarse_problems<'r>(
    problem: &Problem<'_>,
    rigs: &'r [Rig],
    settings: &FitSettings,
) -> Result<Vec<Problem<'r>>> {
    let mut out: Vec<Problem<'r>> = Vec::with_capacity(rigs.len());
    for rig in rigs {
        problem.cancel.check()?;
        let data = match out.last() {
            None => coarsen(problem, settings)?,
            Some(p) => coarsen(p, settings)?,
        };
        let mut coarse = coarse_problem(data, rig)?;
        coarse.cancel = problem.cancel.clone();
        out.push(coarse);
    }
    Ok(out)
}

/// The rigs of levels 1..levels (level 1 first).
pub fn coarse_rigs(rig: &Rig, levels: usize) -> Vec<Rig> {
    let mut out: Vec<Rig> = Vec::with_capacity(levels.saturating_sub(1));
    for _ in 1..levels {
        let camera = coarser_camera(&out.last().unwrap_or(rig).camera);
        out.push(Rig {
            camera,
            lights: rig.lights.clone(),
        });
    }
    out
}

/// Carries the unknowns `u` of `coarse` to the unknowns of `fine` (one level up) by bilinear
/// interpolation on the shared rays.
pub fn upsample(coarse: &Grid, u: &[f64], fine: &Grid) -> Result<Vec<f64>> {
    let (fw, cw) = (fine.width + 1, coarse.width + 1);
    let value = |r: usize, c: usize| -> Option<f64> {
        if r > coarse.height || c > coarse.width {
            return None;
        }
        let i = coarse.vertex_unknown[r * cw + c];
        (i != INACTIVE).then(|| u[i as usize])
    };
    let mean = u.iter().sum::<f64>() / u.len().max(1) as f64;
    try_par_collect(
        fine.active.par_iter().map(|&v| {
            let v = v as usize;
            let (r, c) = (v / fw, v % fw);
            let rows: &[(usize, f64)] = if r % 2 == 0 {
                &[(r / 2, 1.0)]
            } else {
                &[(r / 2, 0.5), (r / 2 + 1, 0.5)]
            };
            let cols: &[(usize, f64)] = if c % 2 == 0 {
                &[(c / 2, 1.0)]
            } else {
                &[(c / 2, 0.5), (c / 2 + 1, 0.5)]
            };
            let (mut sum, mut weight) = (0.0, 0.0);
            for &(rr, wr) in rows {
                for &(cc, wc) in cols {
                    if let Some(x) = value(rr, cc) {
                        sum += wr * wc * x;
                        weight += wr * wc;
                    }
                }
            }
            if weight > 0.0 {
                sum / weight
            } else {
                mean
            }
        }),
        "the carried depths",
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The grey row kernel gives the general loop's bits: every child pattern, unusable
    /// (dark, saturated, NaN) children, an odd width.
    #[test]
    fn grey_rows_match_the_general_average() {
        let settings = FitSettings {
            dark: 0.05,
            saturation: 0.95,
            ..FitSettings::default()
        };
        let w: usize = 33;
        let cw = w.div_ceil(2);
        let sample = |i: usize| match i % 11 {
            0 => 0.01,
            1 => 0.99,
            2 => f32::NAN,
            _ => 0.1 + 0.8 * ((i * 7919) % 1000) as f32 / 1000.0,
        };
        for seed in 0..16 {
            let top: Vec<f32> = (0..w).map(|c| sample(seed * 131 + c)).collect();
            let bottom: Vec<f32> = (0..w).map(|c| sample(seed * 131 + 61 + 3 * c)).collect();
            let children: Vec<u8> = (0..cw)
                .map(|cc| {
                    let bits = ((cc * 5 + seed * 3) % 16) as u8;
                    let bits = if seed % 2 == 0 { 0b1111 } else { bits };
                    if 2 * cc + 1 < w {
                        bits
                    } else {
                        bits & 0b0101
                    }
                })
                .collect();
            let mut out = vec![f32::NAN; cw];
            coarse_row_grey(&top, &bottom, &children, &settings, &mut out, &|v: f32| v);
            for (cc, &bits) in children.iter().enumerate() {
                let (mut sum, mut n) = (0.0f64, 0u32);
                for bit in 0..4 {
                    if bits & (1 << bit) != 0 {
                        let row = if bit < 2 { &top } else { &bottom };
                        let v = row[2 * cc + (bit & 1)];
                        if usable(&[v], &settings) {
                            sum += v as f64;
                            n += 1;
                        }
                    }
                }
                let want = if n > 0 {
                    (sum / n as f64) as f32
                } else {
                    f32::NAN
                };
                assert_eq!(out[cc].to_bits(), want.to_bits(), "seed {seed} column {cc}");
            }
        }
    }

    #[test]
    fn automatic_levels_keep_the_coarsest_side_at_least_128() {
        assert_eq!(levels_for(100, 100, 0), 1);
        assert_eq!(levels_for(256, 256, 0), 2);
        assert_eq!(levels_for(512, 512, 0), 3);
        assert_eq!(levels_for(3000, 4000, 0), 5);
        assert_eq!(levels_for(512, 512, 2), 2);
        assert_eq!(levels_for(4, 4, 10), 3);
    }

    /// A coarse vertex lies on the same ray as the fine vertex (2R, 2C).
    #[test]
    fn coarse_cameras_share_the_rays_of_even_vertices() {
        let cameras = [
            Camera::Orthographic {
                pixel_size: [0.3, 0.2],
                origin: [-5.0, 7.0],
            },
            Camera::Pinhole {
                k: [[800.0, 1.5, 330.0], [0.0, 790.0, 240.0], [0.0, 0.0, 1.0]],
                distortion: [0.1, -0.05, 0.001, 0.002, 0.01],
            },
        ];
        for camera in cameras {
            let mut fine = camera;
            let mut scale = 1;
            for _ in 0..3 {
                let coarse = coarser_camera(&fine);
                scale *= 2;
                for (r, c) in [(0, 0), (3, 5), (17, 2)] {
                    let a = coarse.vertex_xy(r, c);
                    let b = camera.vertex_xy(scale * r, scale * c);
                    assert!((a[0] - b[0]).abs() < 1e-12 && (a[1] - b[1]).abs() < 1e-12);
                }
                fine = coarse;
            }
        }
    }

    /// A plane's unknowns are carried up exactly.
    #[test]
    fn upsampling_reproduces_planes() {
        let mask: Vec<bool> = (0..9 * 11).map(|p| p % 7 != 3).collect();
        let fine = Grid::new(9, 11, Some(&mask)).unwrap();
        let mut cmask = vec![false; 5 * 6];
        for p in fine.facets.iter().map(|&p| p as usize) {
            cmask[(p / 11 / 2) * 6 + (p % 11) / 2] = true;
        }
        let coarse = Grid::new(5, 6, Some(&cmask)).unwrap();
        let plane = |r: usize, c: usize| 3.0 + 0.5 * r as f64 - 0.25 * c as f64;
        let u: Vec<f64> = coarse
            .active
            .iter()
            .map(|&v| plane(2 * (v as usize / 7), 2 * (v as usize % 7)))
            .collect();
        let up = upsample(&coarse, &u, &fine).unwrap();
        for (&v, x) in fine.active.iter().zip(&up) {
            assert!((x - plane(v as usize / 12, v as usize % 12)).abs() < 1e-12);
        }
    }
}
