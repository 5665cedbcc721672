//! What the mesh files of a result hold: per-vertex means of per-pixel maps
//! ([`vertex_means`]) and the masked facets as triangles over the vertices they use
//! ([`mesh_arrays`]). `nplps.export` writes OBJ, STL and glTF files from these arrays; PLY files
//! are streamed in blocks of rows ([`ply_plan`], [`write_ply_records`]) without them.
//!
//! Vertex `(r, c)` of the `(H + 1) x (W + 1)` grid is the top-left corner of pixel `(r, c)`;
//! pixel `(r, c)` is the quad facet with corners `00 = (r, c)`, `01 = (r, c + 1)`,
//! `10 = (r + 1, c)` and `11 = (r + 1, c + 1)`, written as the triangles `(00, 10, 11)` and
//! `(00, 11, 01)` (counter-clockwise as seen from the camera).
//!
//! The arithmetic is that of the numpy code it replaces, operation for operation, so that the
//! files are the same bytes: a mean is `((((0 + a) + b) + c) + d) / count` over the pixels
//! `(r, c)`, `(r, c - 1)`, `(r - 1, c)`, `(r - 1, c - 1)` in this order (a pixel with a
//! non-finite value adds 0 and does not count), and a length is `sqrt((x² + y²) + z²)`.

use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::memory::{try_vec, try_with_capacity};

/// The mean of the finite values of the (up to 4) pixels around each vertex: `values` is an
/// `H x W x C` map (row-major, C values per pixel), the result `(H + 1) x (W + 1) x C`.
///
/// A pixel counts when all its C values are finite. A vertex without such a pixel is NaN. With
/// `normalize`, each mean is then divided by its length `sqrt(Σ v_i²)` (C = 3: a unit normal;
/// NaN for a zero mean).
pub fn vertex_means(
    values: &[f64],
    height: usize,
    width: usize,
    channels: usize,
    normalize: bool,
) -> Result<Vec<f64>> {
    let expected = height * width * channels;
    if values.len() != expected || channels == 0 {
        return Err(Error::Shape {
            what: "per-pixel map",
            expected,
            got: values.len(),
            message: format!(
                "a per-pixel map of {height} x {width} x {channels} must have {expected} values, \
                 got {}",
                values.len()
            ),
        });
    }
    let mut out = try_vec(
        (height + 1) * (width + 1) * channels,
        0.0,
        "the per-vertex map",
    )?;
    match channels {
        1 => means::<1>(values, height, width, normalize, &mut out),
        3 => means::<3>(values, height, width, normalize, &mut out),
        c => {
            // Any other number of channels, one at a time (none of nplps's maps has them).
            let mut one = try_vec((height + 1) * (width + 1), 0.0, "the per-vertex map")?;
            for k in 0..c {
                let column: Vec<f64> = (0..height * width)
                    .map(|p| {
                        let px = &values[p * c..(p + 1) * c];
                        if px.iter().all(|v| v.is_finite()) {
                            px[k]
                        } else {
                            f64::NAN
                        }
                    })
                    .collect();
                means::<1>(&column, height, width, false, &mut one);
                for (o, v) in out.iter_mut().skip(k).step_by(c).zip(&one) {
                    *o = *v;
                }
            }
            if normalize {
                for cell in out.chunks_exact_mut(c) {
                    let length = cell.iter().map(|v| v * v).fold(0.0, |a, b| a + b).sqrt();
                    cell.iter_mut().for_each(|v| *v /= length);
                }
            }
        }
    }
    Ok(out)
}

/// [`vertex_means`] of `N` channels into `out` ((H + 1) x (W + 1) x N), row by row in parallel.
fn means<const N: usize>(
    values: &[f64],
    height: usize,
    width: usize,
    normalize: bool,
    out: &mut [f64],
) {
    out.par_chunks_mut((width + 1) * N)
        .enumerate()
        .for_each(|(r, line)| {
            for col in 0..=width {
                let mean = vertex_mean::<N>(values, height, width, r, col, normalize);
                line[col * N..col * N + N].copy_from_slice(&mean);
            }
        });
}

/// The [`vertex_means`] value of vertex `(r, col)` of an `H x W x N` per-pixel map.
#[inline]
fn vertex_mean<const N: usize>(
    values: &[f64],
    height: usize,
    width: usize,
    r: usize,
    col: usize,
    normalize: bool,
) -> [f64; N] {
    let row = width * N;
    // Pixel row r lies below vertex row r, pixel row r - 1 above it.
    let below = (r < height).then(|| &values[r * row..(r + 1) * row]);
    let above = (r > 0).then(|| &values[(r - 1) * row..r * row]);
    let mut acc = [0.0f64; N];
    let mut count = 0.0f64;
    // The order of the numpy sum: (r, c), (r, c - 1), (r - 1, c), (r - 1, c - 1).
    for pixels in [below, above].into_iter().flatten() {
        for c in [col, col.wrapping_sub(1)] {
            if c >= width {
                continue;
            }
            let px: &[f64] = &pixels[c * N..c * N + N];
            if px.iter().all(|v| v.is_finite()) {
                for k in 0..N {
                    acc[k] += px[k];
                }
                count += 1.0;
            } else {
                for a in acc.iter_mut() {
                    *a += 0.0;
                }
            }
        }
    }
    let mut cell = [f64::NAN; N];
    if count == 0.0 {
        return cell;
    }
    for k in 0..N {
        cell[k] = acc[k] / count;
    }
    if normalize {
        let mut squares = cell[0] * cell[0];
        for v in &cell[1..] {
            squares += v * v;
        }
        let length = squares.sqrt();
        cell.iter_mut().for_each(|v| *v /= length);
    }
    cell
}

/// A triangle mesh of the masked facets, as [`mesh_arrays`] returns it.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct MeshArrays {
    /// Row-major flat indices (into the vertex grid) of the vertices the facets use, increasing.
    pub used: Vec<i64>,
    /// Their positions as `f32`, multiplied by the frame's flip (values beyond the `f32` range
    /// are infinite).
    pub points: Vec<[f32; 3]>,
    /// Their normals as `f32` in the same frame (empty without normals).
    pub normals: Vec<[f32; 3]>,
    /// Two triangles `(00, 10, 11)`, `(00, 11, 01)` per facet, in row-major facet order, as
    /// indices into `points`.
    pub faces: Vec<[i32; 3]>,
    /// Masked facets left out because a corner's position (or normal) is not finite.
    pub skipped: usize,
}

/// The mesh of the masked facets of a vertex grid whose four corners have finite positions (and
/// finite normals, when given): `vertices` and `normals` are `(H + 1) x (W + 1) x 3` grids
/// (row-major, flat), `mask` is `H x W`. With `opengl`, positions and normals are written in the OpenGL frame
/// `(x, -y, -z)` (a rotation: the triangles keep facing the viewer).
pub fn mesh_arrays(
    vertices: &[f64],
    normals: Option<&[f64]>,
    mask: &[bool],
    height: usize,
    width: usize,
    opengl: bool,
) -> Result<MeshArrays> {
    let grid = (height + 1) * (width + 1);
    let shape = |what: &'static str, expected: usize, got: usize| Error::Shape {
        what,
        expected,
        got,
        message: format!(
            "the {what} of a {height} x {width} mesh must have {expected} values, got {got}"
        ),
    };
    if vertices.len() != 3 * grid {
        return Err(shape("vertex grid", 3 * grid, vertices.len()));
    }
    if let Some(n) = normals {
        if n.len() != 3 * grid {
            return Err(shape("vertex normals", 3 * grid, n.len()));
        }
    }
    if mask.len() != height * width {
        return Err(shape("mask", height * width, mask.len()));
    }
    let finite: Vec<bool> = {
        let mut f = try_vec(grid, false, "the finite vertices")?;
        f.par_iter_mut().enumerate().for_each(|(i, f)| {
            *f = vertices[3 * i..3 * i + 3].iter().all(|v| v.is_finite())
                && normals.is_none_or(|n| n[3 * i..3 * i + 3].iter().all(|v| v.is_finite()))
        });
        f
    };
    let w1 = width + 1;
    // Whether pixel (r, c) is a facet of the mesh; v00 = r (W + 1) + c is its top-left vertex.
    let facet = |p: usize, v00: usize| {
        mask[p] && finite[v00] && finite[v00 + 1] && finite[v00 + w1] && finite[v00 + w1 + 1]
    };
    let pixels =
        || (0..height).flat_map(move |r| (0..width).map(move |c| (r * width + c, r * w1 + c)));
    // -1: not used; else the vertex's index among the used ones.
    let mut index = try_vec(grid, -1i32, "the vertex indices")?;
    let (mut masked, mut facets) = (0usize, 0usize);
    for (p, v00) in pixels() {
        if !mask[p] {
            continue;
        }
        masked += 1;
        if facet(p, v00) {
            facets += 1;
            for v in [v00, v00 + 1, v00 + w1, v00 + w1 + 1] {
                index[v] = 0;
            }
        }
    }
    let count = index.iter().filter(|&&i| i == 0).count();
    if count > i32::MAX as usize {
        return Err(Error::Unusable(format!(
            "a mesh of {count} vertices cannot be indexed with 32-bit integers (at most {})",
            i32::MAX
        )));
    }
    let mut used = try_with_capacity(count, "the used vertices")?;
    for (v, i) in index.iter_mut().enumerate() {
        if *i == 0 {
            *i = used.len() as i32;
            used.push(v as i64);
        }
    }
    let flip: [f32; 3] = if opengl { [1.0, -1.0, -1.0] } else { [1.0; 3] };
    let gather = |grid: &[f64]| -> Result<Vec<[f32; 3]>> {
        let mut out = try_vec(used.len(), [0.0f32; 3], "the mesh vertices")?;
        out.par_iter_mut().zip(used.par_iter()).for_each(|(o, &v)| {
            let v = v as usize;
            let g = &grid[3 * v..3 * v + 3];
            // f64 -> f32 rounds to nearest (beyond the f32 range: infinite), then the flip.
            *o = [
                g[0] as f32 * flip[0],
                g[1] as f32 * flip[1],
                g[2] as f32 * flip[2],
            ];
        });
        Ok(out)
    };
    let points = gather(vertices)?;
    let normals = match normals {
        Some(n) => gather(n)?,
        None => Vec::new(),
    };
    let mut faces = try_with_capacity(2 * facets, "the mesh faces")?;
    for (p, v00) in pixels() {
        if facet(p, v00) {
            let (i00, i01) = (index[v00], index[v00 + 1]);
            let (i10, i11) = (index[v00 + w1], index[v00 + w1 + 1]);
            faces.push([i00, i10, i11]);
            faces.push([i00, i11, i01]);
        }
    }
    Ok(MeshArrays {
        used,
        points,
        normals,
        faces,
        skipped: masked - facets,
    })
}

/// A per-vertex map of a PLY file: given at the vertices, or as the per-pixel map whose
/// [`vertex_means`] it is (computed vertex by vertex as the file is written: no whole grid).
#[derive(Debug, Clone, Copy)]
pub enum VertexMap<'a> {
    /// `(H + 1) x (W + 1) x C` values (row-major, flat).
    Vertices(&'a [f64]),
    /// `H x W x C` per-pixel values (row-major, flat).
    Pixels(&'a [f64]),
}

impl VertexMap<'_> {
    /// The `N` values of vertex `v = r (W + 1) + c` (the normalized mean with `normalize`, for
    /// a per-pixel map).
    #[inline]
    fn at<const N: usize>(
        &self,
        height: usize,
        width: usize,
        v: usize,
        normalize: bool,
    ) -> [f64; N] {
        match self {
            VertexMap::Vertices(values) => {
                let mut out = [0.0; N];
                out.copy_from_slice(&values[N * v..N * v + N]);
                out
            }
            VertexMap::Pixels(values) => vertex_mean::<N>(
                values,
                height,
                width,
                v / (width + 1),
                v % (width + 1),
                normalize,
            ),
        }
    }

    /// The number of values it must have for C channels.
    fn expected(&self, height: usize, width: usize, channels: usize) -> (usize, usize) {
        match self {
            VertexMap::Vertices(values) => (channels * (height + 1) * (width + 1), values.len()),
            VertexMap::Pixels(values) => (channels * height * width, values.len()),
        }
    }
}

/// The vertex positions of a PLY file: a vertex grid, or the camera and the vertex depths (the
/// positions of [`crate::vertices`], computed vertex by vertex as the file is written).
#[derive(Debug, Clone, Copy)]
pub enum Positions<'a> {
    /// `(H + 1) x (W + 1) x 3` positions (row-major, flat).
    Grid(&'a [f64]),
    /// The camera and the `(H + 1) x (W + 1)` vertex depths.
    Camera {
        /// The camera.
        camera: &'a crate::rig::Camera,
        /// The depth (z) of each vertex.
        depth: &'a [f64],
    },
}

impl Positions<'_> {
    /// The position of vertex `v = r (W + 1) + c`.
    #[inline]
    fn at(&self, width: usize, v: usize) -> [f64; 3] {
        match self {
            Positions::Grid(values) => [values[3 * v], values[3 * v + 1], values[3 * v + 2]],
            Positions::Camera { camera, depth } => {
                camera.at_depth(camera.vertex_xy(v / (width + 1), v % (width + 1)), depth[v])
            }
        }
    }

    /// The number of values it must have, and has.
    fn expected(&self, height: usize, width: usize) -> (usize, usize) {
        let grid = (height + 1) * (width + 1);
        match self {
            Positions::Grid(values) => (3 * grid, values.len()),
            Positions::Camera { depth, .. } => (grid, depth.len()),
        }
    }
}

/// The vertex colours of a PLY file: a per-vertex albedo quantized to `u8`.
#[derive(Debug, Clone, Copy)]
pub struct PlyColors<'a> {
    /// The per-vertex albedo (the mean of the pixels' albedo, not normalized).
    pub albedo: VertexMap<'a>,
    /// 1 (grey, written as three equal bytes) or 3 (RGB).
    pub channels: usize,
    /// The colour of a value `a` is `round_half_even(clamp(a * scale, 0, 255))`, 0 when `a`
    /// is not finite; None: `255 / p99` with `p99` the 99th percentile (numpy's "linear"
    /// percentile) of the finite albedo values of the written vertices (scale 1 when it is not
    /// positive), computed by [`ply_plan`].
    pub scale: Option<f64>,
}

/// What a PLY file of the masked facets holds, counted by [`ply_plan`] before anything is
/// written; [`write_ply_records`] then writes it.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct PlyPlan {
    /// `(H + 1) x (W + 1)`: the index of each vertex among the written ones, `u32::MAX` for a
    /// vertex no facet uses.
    pub index: Vec<u32>,
    /// The number of written vertices (used by a facet).
    pub vertices: usize,
    /// The number of facets written (two triangles each).
    pub facets: usize,
    /// Masked facets left out because a corner's position (or normal) is not finite.
    pub skipped: usize,
    /// Written vertices whose position is beyond the `f32` range (a PLY file cannot hold them).
    pub overflow: usize,
    /// The colours' scale (see [`PlyColors::scale`]; 1 without colours).
    pub scale: f64,
}

/// Checks the shapes of the grids of [`ply_plan`] and [`write_ply_records`].
fn check_grids(
    vertices: &Positions<'_>,
    normals: Option<&VertexMap<'_>>,
    colors: Option<&PlyColors<'_>>,
    mask: &[bool],
    height: usize,
    width: usize,
) -> Result<()> {
    let shape = |what: &'static str, (expected, got): (usize, usize)| Error::Shape {
        what,
        expected,
        got,
        message: format!(
            "the {what} of a {height} x {width} mesh must have {expected} values, got {got}"
        ),
    };
    let (expected, got) = vertices.expected(height, width);
    if expected != got {
        return Err(shape("vertex positions", (expected, got)));
    }
    if let Positions::Camera { camera, depth } = vertices {
        crate::geometry::check_vertex_rays(camera, height, width, depth)?;
    }
    if let Some(n) = normals {
        let (expected, got) = n.expected(height, width, 3);
        if expected != got {
            return Err(shape("normals", (expected, got)));
        }
    }
    if let Some(c) = colors {
        let (expected, got) = c.albedo.expected(height, width, c.channels);
        if !matches!(c.channels, 1 | 3) || expected != got {
            return Err(shape("albedo", (expected, got)));
        }
    }
    if mask.len() != height * width {
        return Err(shape("mask", (height * width, mask.len())));
    }
    Ok(())
}

/// numpy's `percentile(values, q)` with its default ("linear") method, bit for bit: the
/// virtual index `i = (n - 1) (q / 100)`, `a`, `b` the values of ranks `floor(i)` and
/// `floor(i) + 1`, `t = i - floor(i)`, then `a + (b - a) t` for `t < 0.5` and `b - (b - a) (1 -
/// t)` otherwise. `values` is reordered; None when empty.
fn percentile(values: &mut [f64], q: f64) -> Option<f64> {
    let n = values.len();
    if n == 0 {
        return None;
    }
    let index = (n - 1) as f64 * (q / 100.0);
    let by = |a: &f64, b: &f64| a.total_cmp(b);
    if index >= (n - 1) as f64 {
        return values.iter().copied().max_by(by);
    }
    if index < 0.0 {
        return values.iter().copied().min_by(by);
    }
    let below = index.floor();
    let rank = below as usize;
    let (_, a, right) = values.select_nth_unstable_by(rank, by);
    let a = *a;
    let b = right.iter().copied().min_by(by).unwrap_or(a);
    let t = index - below;
    let diff = b - a;
    Some(if t >= 0.5 {
        b - diff * (1.0 - t)
    } else {
        a + diff * t
    })
}

/// The first pass of a streamed PLY file: which masked facets have four corners with finite
/// positions (and normals), which vertices they use and their numbers in row-major order —
/// the same facets, vertices and order as [`mesh_arrays`], with 5 bytes per vertex instead of
/// whole position, normal and face arrays — and the colours' scale.
pub fn ply_plan(
    vertices: &Positions<'_>,
    normals: Option<&VertexMap<'_>>,
    colors: Option<&PlyColors<'_>>,
    mask: &[bool],
    height: usize,
    width: usize,
) -> Result<PlyPlan> {
    check_grids(vertices, normals, colors, mask, height, width)?;
    let w1 = width + 1;
    let grid = (height + 1) * w1;
    // Per vertex (1 byte, row by row in parallel): 0 when its position (or normal) is not
    // finite, 2 when its position is finite but beyond the f32 range, else 1.
    let mut finite = try_vec(grid, 0u8, "the finite vertices")?;
    finite.par_chunks_mut(w1).enumerate().for_each(|(r, line)| {
        for (c, f) in line.iter_mut().enumerate() {
            let v = r * w1 + c;
            let p = vertices.at(width, v);
            let ok = p.iter().all(|x| x.is_finite())
                && normals.is_none_or(|n| {
                    n.at::<3>(height, width, v, true)
                        .iter()
                        .all(|x| x.is_finite())
                });
            *f = match (ok, p.iter().all(|&x| (x as f32).is_finite())) {
                (false, _) => 0,
                (true, true) => 1,
                (true, false) => 2,
            };
        }
    });
    // Whether each pixel is a written facet (1 byte per pixel).
    let mut facet = try_vec(height * width, false, "the mesh facets")?;
    if width > 0 {
        facet
            .par_chunks_mut(width)
            .enumerate()
            .for_each(|(r, line)| {
                for (c, f) in line.iter_mut().enumerate() {
                    let v00 = r * w1 + c;
                    *f = mask[r * width + c]
                        && finite[v00] != 0
                        && finite[v00 + 1] != 0
                        && finite[v00 + w1] != 0
                        && finite[v00 + w1 + 1] != 0;
                }
            });
    }
    let masked = mask.iter().filter(|&&m| m).count();
    let facets = facet.iter().filter(|&&f| f).count();
    // A vertex is used when one of its (up to 4) pixels is a facet.
    let mut index = try_vec(grid, u32::MAX, "the vertex indices")?;
    index.par_chunks_mut(w1).enumerate().for_each(|(r, line)| {
        for (c, i) in line.iter_mut().enumerate() {
            let mut used = false;
            for pr in [r.wrapping_sub(1), r] {
                for pc in [c.wrapping_sub(1), c] {
                    used |= pr < height && pc < width && facet[pr * width + pc];
                }
            }
            if used {
                *i = 0;
            }
        }
    });
    drop(facet);
    let mut count = 0usize;
    let mut overflow = 0usize;
    for (v, i) in index.iter_mut().enumerate() {
        if *i == 0 {
            if count >= i32::MAX as usize {
                return Err(Error::Unusable(format!(
                    "a mesh of more than {} vertices cannot be indexed with 32-bit integers",
                    i32::MAX
                )));
            }
            *i = count as u32;
            count += 1;
            if finite[v] == 2 {
                overflow += 1;
            }
        }
    }
    drop(finite);
    let scale = match colors {
        Some(PlyColors { scale: Some(s), .. }) => *s,
        Some(c) => color_scale(c, &index, height, width)?,
        None => 1.0,
    };
    Ok(PlyPlan {
        index,
        vertices: count,
        facets,
        skipped: masked - facets,
        overflow,
        scale,
    })
}

/// `255 / p99` of the finite albedo values of the used vertices (see [`PlyColors::scale`]).
fn color_scale(colors: &PlyColors<'_>, index: &[u32], height: usize, width: usize) -> Result<f64> {
    let used = index.iter().filter(|&&i| i != u32::MAX).count();
    let mut values: Vec<f64> = try_with_capacity(used * colors.channels, "the vertex albedo")?;
    for (v, _) in index.iter().enumerate().filter(|(_, &i)| i != u32::MAX) {
        match colors.channels {
            1 => values.extend(colors.albedo.at::<1>(height, width, v, false)),
            _ => values.extend(colors.albedo.at::<3>(height, width, v, false)),
        }
    }
    values.retain(|a| a.is_finite());
    let reference = percentile(&mut values, COLOR_PERCENTILE).unwrap_or(0.0);
    Ok(if reference > 0.0 {
        255.0 / reference
    } else {
        1.0
    })
}

/// The percentile of the albedo that becomes colour 255 (`nplps.export`'s `_COLOR_PERCENTILE`).
const COLOR_PERCENTILE: f64 = 99.0;

/// The ASCII header of the binary little-endian PLY file of [`write_ply_records`] (`frame`:
/// `"opencv"` or `"opengl"`): the same text as `nplps.export`'s.
pub fn ply_header(plan: &PlyPlan, normals: bool, colors: bool, frame: &str) -> String {
    let mut lines = vec![
        "ply".to_string(),
        "format binary_little_endian 1.0".to_string(),
        "comment nplps".to_string(),
        format!("comment frame {frame}"),
        format!("element vertex {}", plan.vertices),
    ];
    let mut properties = |kind: &str, names: [&str; 3]| {
        for name in names {
            lines.push(format!("property {kind} {name}"));
        }
    };
    properties("float", ["x", "y", "z"]);
    if normals {
        properties("float", ["nx", "ny", "nz"]);
    }
    if colors {
        properties("uchar", ["red", "green", "blue"]);
    }
    lines.push(format!("element face {}", 2 * plan.facets));
    lines.push("property list uchar int vertex_indices".to_string());
    lines.push("end_header\n".to_string());
    lines.join("\n")
}

/// Vertex rows per block of [`write_ply_records`].
const PLY_BLOCK_ROWS: usize = 64;

/// The colour byte of an albedo value (see [`PlyColors`]): numpy's `rint(clip(a * scale, 0,
/// 255))`, 0 for a non-finite `a`.
fn color_byte(a: f64, scale: f64) -> u8 {
    if !a.is_finite() {
        return 0;
    }
    (a * scale).clamp(0.0, 255.0).round_ties_even() as u8
}

/// The second pass: writes the header, the vertex records (`x y z` float, `nx ny nz` float,
/// `red green blue` uchar) and the face records (`3` as uchar and three int indices: the
/// triangles `(00, 10, 11)` and `(00, 11, 01)` of each facet in row-major order) of the
/// mesh that `plan` ([`ply_plan`] of the same grids) describes, in blocks of rows made in
/// parallel while a writer thread writes the previous blocks; the bytes are those of `nplps.export.write_ply`. With `opengl`, positions and
/// normals are `(x, -y, -z)`.
#[allow(clippy::too_many_arguments)]
pub fn write_ply_records<W: std::io::Write + Send>(
    out: &mut W,
    plan: &PlyPlan,
    vertices: &Positions<'_>,
    normals: Option<&VertexMap<'_>>,
    colors: Option<&PlyColors<'_>>,
    mask: &[bool],
    height: usize,
    width: usize,
    opengl: bool,
) -> Result<std::io::Result<()>> {
    check_grids(vertices, normals, colors, mask, height, width)?;
    let w1 = width + 1;
    if plan.index.len() != (height + 1) * w1 {
        return Err(Error::Shape {
            what: "vertex indices",
            expected: (height + 1) * w1,
            got: plan.index.len(),
            message: "the PLY plan is not that of this grid".to_string(),
        });
    }
    let index = &plan.index;
    let frame = if opengl { "opengl" } else { "opencv" };
    let header = ply_header(plan, normals.is_some(), colors.is_some(), frame);
    let flip: [f32; 3] = if opengl { [1.0, -1.0, -1.0] } else { [1.0; 3] };
    let record = 12 + if normals.is_some() { 12 } else { 0 } + if colors.is_some() { 3 } else { 0 };
    let put3 = |bytes: &mut Vec<u8>, g: &[f64; 3]| {
        for k in 0..3 {
            bytes.extend_from_slice(&((g[k] as f32) * flip[k]).to_le_bytes());
        }
    };
    // One vertex row's records.
    let vertex_row = |r: usize| -> Vec<u8> {
        let line = &index[r * w1..(r + 1) * w1];
        let n = line.iter().filter(|&&i| i != u32::MAX).count();
        let mut bytes = Vec::with_capacity(n * record);
        for (c, &i) in line.iter().enumerate() {
            if i == u32::MAX {
                continue;
            }
            let v = r * w1 + c;
            put3(&mut bytes, &vertices.at(width, v));
            if let Some(n) = normals {
                put3(&mut bytes, &n.at::<3>(height, width, v, true));
            }
            if let Some(colors) = colors {
                let a = match colors.channels {
                    1 => [colors.albedo.at::<1>(height, width, v, false)[0]; 3],
                    _ => colors.albedo.at::<3>(height, width, v, false),
                };
                for value in a {
                    bytes.push(color_byte(value, plan.scale));
                }
            }
        }
        bytes
    };
    // One pixel row's face records.
    let face_row = |r: usize| -> Vec<u8> {
        let mut bytes = Vec::new();
        for c in 0..width {
            let v00 = r * w1 + c;
            let (i00, i01) = (index[v00], index[v00 + 1]);
            let (i10, i11) = (index[v00 + w1], index[v00 + w1 + 1]);
            let facet = mask[r * width + c]
                && i00 != u32::MAX
                && i01 != u32::MAX
                && i10 != u32::MAX
                && i11 != u32::MAX;
            // Used corners are finite: the pixel is a facet of the first pass.
            if facet {
                for tri in [[i00, i10, i11], [i00, i11, i01]] {
                    bytes.push(3);
                    for i in tri {
                        bytes.extend_from_slice(&(i as i32).to_le_bytes());
                    }
                }
            }
        }
        bytes
    };
    // The blocks are made on rayon's pool while a writer thread writes the previous batch: the
    // encoding and the write overlap (one batch in flight, so memory stays two batches).
    let result = std::thread::scope(|scope| -> std::io::Result<()> {
        let (send, receive) = std::sync::mpsc::sync_channel::<Vec<Vec<u8>>>(1);
        let writer = scope.spawn(move || -> std::io::Result<()> {
            out.write_all(header.as_bytes())?;
            for blocks in receive {
                for b in &blocks {
                    out.write_all(b)?;
                }
            }
            out.flush()
        });
        let vertex_batches = (0..=height)
            .step_by(PLY_BLOCK_ROWS)
            .map(|start| (start, (start + PLY_BLOCK_ROWS).min(height + 1), true));
        let face_batches = (0..height)
            .step_by(PLY_BLOCK_ROWS)
            .map(|start| (start, (start + PLY_BLOCK_ROWS).min(height), false));
        for (start, end, vertex) in vertex_batches.chain(face_batches) {
            let blocks: Vec<Vec<u8>> = if vertex {
                (start..end).into_par_iter().map(vertex_row).collect()
            } else {
                (start..end).into_par_iter().map(face_row).collect()
            };
            if send.send(blocks).is_err() {
                // The writer stopped on an error: it is returned below.
                break;
            }
        }
        drop(send);
        writer
            .join()
            .unwrap_or_else(|_| Err(std::io::Error::other("the PLY writer thread panicked")))
    });
    Ok(result)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn means_skip_non_finite_pixels_and_normalize() {
        // 1 x 2 pixels, 3 channels: the right pixel is NaN.
        let values = [0.0, 0.0, -2.0, f64::NAN, 1.0, 1.0];
        let m = vertex_means(&values, 1, 2, 3, false).unwrap();
        assert_eq!(m.len(), 2 * 3 * 3);
        assert_eq!(&m[0..3], &[0.0, 0.0, -2.0]);
        assert_eq!(&m[3..6], &[0.0, 0.0, -2.0]); // the NaN pixel does not count
        assert!(m[6..9].iter().all(|v| v.is_nan())); // only the NaN pixel
        let n = vertex_means(&values, 1, 2, 3, true).unwrap();
        assert_eq!(&n[0..3], &[0.0, 0.0, -1.0]);
        // The mean of four pixels, in the documented order.
        let grey = [1.0, 2.0, 3.0, 4.0];
        let g = vertex_means(&grey, 2, 2, 1, false).unwrap();
        assert_eq!(g[4], 2.5); // the centre vertex
        assert_eq!(g[0], 1.0);
        assert_eq!(g[8], 4.0);
        assert!(vertex_means(&grey, 2, 3, 1, false).is_err());
    }

    /// 2 x 2 pixels, all masked but (0, 1), vertex i at (i, 0.5, 1) except vertex (2, 2), whose
    /// z is not finite (so facet (1, 1) is skipped): the vertex grid and the mask.
    fn two_by_two() -> (Vec<f64>, [bool; 4]) {
        let mut v = vec![0.0f64; 27];
        for i in 0..9 {
            v[3 * i..3 * i + 3].copy_from_slice(&[i as f64, 0.5, 1.0]);
        }
        v[26] = f64::NAN;
        (v, [true, false, true, true])
    }

    #[test]
    fn facets_become_two_triangles_over_the_used_vertices() {
        // 2 x 2 pixels, all masked but (0, 1); vertex (2, 2) not finite: facet (1, 1) skipped.
        let (h, w) = (2, 2);
        let (v, mask) = two_by_two();
        let m = mesh_arrays(&v, None, &mask, h, w, true).unwrap();
        assert_eq!(m.skipped, 1);
        assert_eq!(m.used, vec![0, 1, 3, 4, 6, 7]);
        assert_eq!(m.faces, vec![[0, 2, 3], [0, 3, 1], [2, 4, 5], [2, 5, 3]]);
        assert_eq!(m.points[1], [1.0, -0.5, -1.0]);
        assert!(m.normals.is_empty());
        assert!(mesh_arrays(&v, None, &mask[..3], h, w, false).is_err());
    }

    #[test]
    fn streamed_ply_holds_the_mesh_arrays() {
        // The facets, vertices and triangles of mesh_arrays, as PLY records.
        let (h, w) = (2, 2);
        let (mut v, mask) = two_by_two();
        let albedo = [0.5; 9];
        let colors = PlyColors {
            albedo: VertexMap::Vertices(&albedo),
            channels: 1,
            scale: Some(255.0),
        };
        let plan = ply_plan(&Positions::Grid(&v), None, Some(&colors), &mask, h, w).unwrap();
        assert_eq!(
            (plan.vertices, plan.facets, plan.skipped, plan.overflow),
            (6, 2, 1, 0)
        );
        let mut bytes = Vec::new();
        write_ply_records(
            &mut bytes,
            &plan,
            &Positions::Grid(&v),
            None,
            Some(&colors),
            &mask,
            h,
            w,
            true,
        )
        .unwrap()
        .unwrap();
        let header = ply_header(&plan, false, true, "opengl");
        assert!(header.contains("element vertex 6\n") && header.contains("element face 4\n"));
        let body = &bytes[header.len()..];
        assert_eq!(body.len(), 6 * 15 + 4 * 13);
        // Vertex 1 (grid vertex 1): (1, -0.5, -1) and the colour round(127.5) = 128.
        let second = &body[15..30];
        assert_eq!(&second[0..4], &1.0f32.to_le_bytes());
        assert_eq!(&second[4..8], &(-0.5f32).to_le_bytes());
        assert_eq!(&second[12..15], &[128, 128, 128]);
        let arrays = mesh_arrays(&v, None, &mask, h, w, true).unwrap();
        let faces = &body[6 * 15..];
        for (k, tri) in arrays.faces.iter().enumerate() {
            let rec = &faces[13 * k..13 * k + 13];
            assert_eq!(rec[0], 3);
            for j in 0..3 {
                assert_eq!(&rec[1 + 4 * j..5 + 4 * j], &tri[j].to_le_bytes());
            }
        }
        // A position beyond the f32 range is counted.
        v[0] = 1e300;
        assert_eq!(
            ply_plan(&Positions::Grid(&v), None, None, &mask, h, w)
                .unwrap()
                .overflow,
            1
        );
    }

    #[test]
    fn camera_positions_are_those_of_vertices() {
        let (h, w) = (5, 7);
        let depth: Vec<f64> = (0..(h + 1) * (w + 1))
            .map(|i| {
                if i == 9 {
                    f64::NAN
                } else {
                    10.0 + (i % 5) as f64
                }
            })
            .collect();
        for camera in crate::rig::test_cameras() {
            let grid = crate::vertices(&camera, h, w, &depth).unwrap();
            let positions = Positions::Camera {
                camera: &camera,
                depth: &depth,
            };
            for (v, p) in grid.iter().enumerate() {
                let q = positions.at(w, v);
                for k in 0..3 {
                    assert_eq!(p[k].to_bits(), q[k].to_bits(), "vertex {v}");
                }
            }
            // The same file from the grid and from the camera.
            let flat: Vec<f64> = grid.iter().flatten().copied().collect();
            let mask = vec![true; h * w];
            let mut files = Vec::new();
            for p in [Positions::Grid(&flat), positions] {
                let plan = ply_plan(&p, None, None, &mask, h, w).unwrap();
                let mut bytes = Vec::new();
                write_ply_records(&mut bytes, &plan, &p, None, None, &mask, h, w, false)
                    .unwrap()
                    .unwrap();
                files.push(bytes);
            }
            assert_eq!(files[0], files[1]);
        }
    }

    #[test]
    fn percentile_is_numpys_linear_one() {
        // numpy.percentile([3, 1, 2, 10], 99) = 2 + ... : index 2.97 between 3 and 10.
        let mut v = [3.0, 1.0, 2.0, 10.0];
        let i: f64 = 3.0 * 0.99;
        let t = i - 2.0;
        assert_eq!(percentile(&mut v, 99.0), Some(10.0 - 7.0 * (1.0 - t)));
        assert_eq!(percentile(&mut [5.0], 99.0), Some(5.0));
        assert_eq!(percentile(&mut [], 99.0), None);
    }
}
