//! Cast shadows of a height field: which facets does the surface itself hide from which light.
//!
//! ## The test
//!
//! The surface is the mesh of an (H+1) x (W+1) vertex depth map (vertices at pixel corners,
//! positions from the camera, see [`crate::vertices`]). Facet (pixel) `p` with centre `c` (the
//! mean of its 4 corners) sees light k along the segment
//!
//! ```text
//! x(t) = c + t (e - c),   0 <= t <= 1,
//! ```
//!
//! where `e` is the light's position (point light) or a far point `c + T d` along its direction
//! `d` (directional light). The segment is cut where it comes nearer to the camera than the
//! nearest vertex of the map (`z(t) < z_min`): beyond that point nothing can block it. The
//! facet is in a cast shadow of light k when some point of the (cut) segment lies behind the
//! surface seen along the camera ray through it:
//!
//! ```text
//! z_surface(project(x(t))) < z(t) - tol,    tol = 1e-6 |z(t)| + 1/4 (max - min of the facet's corner depths),
//! ```
//!
//! where `z_surface(u, v)` interpolates the vertex depths bilinearly in the image cell that
//! contains the image point `(u, v)` (vertex (r, c) stands at `(u, v) = (c - 1/2, r - 1/2)`,
//! for both cameras). The relative term absorbs rounding; the facet term keeps a facet from
//! shadowing itself where the bilinear surface bends away from its plane.
//!
//! ## The march
//!
//! The segment is sampled half a pixel apart in the image (so that a sharp edge, a wall one
//! pixel wide, is not stepped over): its image is a straight line in the undistorted image
//! plane (`m(x) = (x / w, y / h)` orthographic, `m(x) = K (x / z, y / z)` pinhole, in pixels),
//! of length `L` pixels; sample `i` (1, 2, ...) is at `s = i / ceil(2 L)` along it, which is
//! the 3-D point `c + w (e - c)` with the perspective-correct
//! `w = s z_c / ((1 - s) z_e + s z_c)` (pinhole; `w = s` orthographic), projected with the
//! camera's distortion to find its cell. The march stops (unblocked) when the sample leaves the
//! image, enters a pixel outside the mask or a cell with a non-finite corner, or after
//! `max_steps` pixels (`2 max_steps` samples); it stops (blocked) at the first sample behind the
//! surface.
//!
//! Facets that turn away from the light (`n . beta(c) <= 0`, an attached shadow, already dark
//! in the image model) and facets outside the mask or with a non-finite corner are never
//! marked.
//!
//! ## Cost
//!
//! At most `min(2 max_steps, ceil(2 L))` samples per facet and light, each a projection and a
//! bilinear interpolation: `O(H W k min(max_steps, D))` with `D` the image diagonal, parallel
//! over pixels. The default `max_steps = 2 max(H, W)` exceeds every path inside the image
//! (its diagonal is at most `sqrt(2) max(H, W)`), so it never truncates a march that stays in
//! the image. Flat regions cost nothing: a segment from a facet at `z_min` is cut at once.
//!
//! Without lens distortion (samples evenly spaced in pixels) the march skips samples that
//! cannot be blocked, with a min-depth pyramid (quadtree) over the pixels: level `l` holds the
//! nearest vertex depth of each cell of `2^l` x `2^l` pixels (`-inf` where a pixel is outside
//! the mask or has a non-finite corner). After each sample it looks, from one level above the
//! last jump's down to level 0, for the coarsest cell that holds the sample and the next ones
//! (strictly inside, with margins of 1e-9 pixels and 1e-6 samples for rounding) and that the
//! segment passes in front of over them (`z - tol <= min - 1e-12 |min|`, with `z` the segment's farthest depth
//! over them, at one end since `z` is monotone along it); it then jumps to the first sample
//! past the cell. The skipped samples could not stop the march (the bilinear depth is never
//! nearer than the cell's nearest corner, and the cell is inside the image and the mask), so
//! the result is the plain march's, bit for bit; each evaluated sample is computed exactly as
//! in the plain march. Over open ground the jumps double in length from level to level, so a
//! march evaluates `O(log L)` samples plus those near the surface it grazes, instead of `2 L`.
//! The pyramid costs `O(H W)` to build (4/3 of a value a pixel). Pixels go in blocks of
//! 32 x 32, light after light inside a block, so that successive marches read nearby cells.
//!
//! With interreflections the solver marches the corrected mesh with `mesh_shadows_refined`:
//! the facets of a lattice of stride `s` march (`s = 2`, the odd rows and columns, up to 511
//! pixels a side; 4 at 1 MP, 8 from 2048: at least `REFINED_LATTICE` = 256 lattice facets
//! across), the others copy the verdicts of their lattice neighbours where those agree and
//! march where they do not (a shadow's edge, a terminator): `1 / s²` of the marches plus the
//! edges', at the price of shadows (or lit gaps) narrower than `s` pixels that no lattice facet
//! around sees. Without interreflections it does so from `LATTICE_SIDE` = 1024 pixels a side
//! with `s = 2` (see `solver_stride`), and marches every facet below. A level that iterates
//! with a coarser level's field and starts from its mask marches once, with `march_guided`:
//! the carried mask's verdicts stand in for the lattice's, and only the facets within
//! `GUIDE_RADIUS` pixels of its edges (or next to a terminator or a hole) march.

use rayon::prelude::*;

use crate::error::{ensure_mask, ensure_range, Result};
use crate::geometry::{quad_centre, quad_normal};
use crate::light::{faced_lanes, LaneLight, Light};
use crate::rig::{Camera, Rig};
use crate::vec3::{dot, not_above, sub};

/// The mesh vertices ((H+1) x (W+1), row-major) a march reads: stored positions, or the
/// positions of a solver's unknowns computed where they are read (no copy: 24 bytes a vertex
/// less while the march runs). Both give the same values: `Geometry::position` of the unknown,
/// NaN for a vertex without one.
#[derive(Clone, Copy)]
pub(crate) enum Vertices<'a> {
    /// Stored positions (NaN where there is no vertex).
    Positions(&'a [[f64; 3]]),
    /// The unknowns `u` of `grid`'s active vertices under `geometry`.
    Mesh {
        grid: &'a crate::grid::Grid,
        geometry: &'a crate::geometry::Geometry,
        u: &'a [f64],
    },
}

impl Vertices<'_> {
    /// Position of vertex `v`.
    #[inline]
    pub(crate) fn at(&self, v: usize) -> [f64; 3] {
        match *self {
            Vertices::Positions(p) => p[v],
            Vertices::Mesh { grid, geometry, u } => {
                let i = grid.vertex_unknown[v];
                if i == crate::grid::INACTIVE {
                    [f64::NAN; 3]
                } else {
                    geometry.position(i as usize, u[i as usize])
                }
            }
        }
    }

    /// Number of vertices.
    fn len(&self) -> usize {
        match *self {
            Vertices::Positions(p) => p.len(),
            Vertices::Mesh { grid, .. } => grid.vertex_unknown.len(),
        }
    }

    /// The smallest finite vertex depth (infinite when there is none).
    fn min_depth(&self) -> f64 {
        match *self {
            Vertices::Positions(p) => p
                .iter()
                .map(|v| v[2])
                .filter(|z| z.is_finite())
                .fold(f64::INFINITY, f64::min),
            // In parallel (a depth is an `exp` per vertex under a pinhole camera); the minimum
            // does not depend on the order.
            Vertices::Mesh { geometry, u, .. } => (0..u.len())
                .into_par_iter()
                .map(|i| geometry.position(i, u[i])[2])
                .filter(|z| z.is_finite())
                .reduce(|| f64::INFINITY, f64::min),
        }
    }
}

/// When the solver predicts cast shadows from its mesh ([`crate::Options::shadows`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Shadows {
    /// Never: only the `dark` threshold and attached shadows (`n . l <= 0`) leave observations
    /// out.
    Off,
    /// Where the object shadows itself: at the iterations `solver::SHADOWS_AT` a
    /// solver without a mask first marches from a lattice of about
    /// `solver::PROBE_FACETS` facets, and from all of them only when at least
    /// [`AUTO_SHARE`] of the lattice's observations are in a cast shadow; a mask is used only
    /// when it holds that share. On an object that does not shadow itself this costs the probes
    /// and changes nothing else (the fits are those of `Off`, bit for bit); on one that does,
    /// it works as `On` once a probe has found the shadows.
    #[default]
    Auto,
    /// Always: the masks of every march are used, at every level.
    On,
}

impl Shadows {
    /// Whether the solver marches at all.
    pub fn is_active(self) -> bool {
        self != Shadows::Off
    }

    /// The policy of the working-distance search and check: candidates are compared without
    /// cast shadows unless they are asked for (`On`): on the PBR block with cast shadows,
    /// marching in the search found -0.68 % instead of -0.20 % at 3.6x the time.
    pub(crate) fn in_search(self) -> Shadows {
        match self {
            Shadows::On => Shadows::On,
            _ => Shadows::Off,
        }
    }
}

impl From<bool> for Shadows {
    fn from(on: bool) -> Self {
        if on {
            Shadows::On
        } else {
            Shadows::Off
        }
    }
}

/// With [`Shadows::Auto`], a mask is used when at least this share of the facets' observations
/// (facets x lights) are in a cast shadow. Measured with `shadows=True` at the true distance
/// (256², 16-27 lights): a block on a plane 1.3 % (synthetic) and 2.2-4.0 % (path-traced, four
/// materials); bumpy height fields 0.01-0.10 % and a torus 0.05-0.13 % (a few facets in its hole,
/// where the masks changed the normal error by at most 0.004°); spheres and bowls 0. Below the
/// share the few hidden observations are left to the `dark` threshold.
pub const AUTO_SHARE: f64 = 0.005;

/// Which facet is in a cast shadow of which light: `k` bits per pixel, bit-packed in
/// `words_per_pixel = ceil(k / 64)` words per pixel (pixel-major, row-major pixels).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ShadowMask {
    height: usize,
    width: usize,
    lights: usize,
    words: usize,
    bits: Vec<u64>,
}

impl ShadowMask {
    /// Image height H.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Image width W.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Number of lights k.
    pub fn lights(&self) -> usize {
        self.lights
    }

    /// Words (u64) per pixel, `ceil(k / 64)`.
    pub fn words_per_pixel(&self) -> usize {
        self.words
    }

    /// Whether pixel `pixel` (row-major index) is in a cast shadow of light `light`.
    ///
    /// # Panics
    /// When `pixel >= H W` or `light >= k`.
    #[inline]
    pub fn is_shadowed(&self, pixel: usize, light: usize) -> bool {
        assert!(
            pixel < self.height * self.width && light < self.lights,
            "pixel or light out of range"
        );
        self.bits[pixel * self.words + light / 64] >> (light % 64) & 1 == 1
    }

    /// The `words_per_pixel` words of pixel `pixel`: bit `k % 64` of word `k / 64` is light k.
    #[inline]
    pub fn pixel_bits(&self, pixel: usize) -> &[u64] {
        &self.bits[pixel * self.words..(pixel + 1) * self.words]
    }

    /// The lights in whose cast shadow pixel `pixel` lies, in increasing order.
    #[inline]
    pub fn lights_at(&self, pixel: usize) -> impl Iterator<Item = usize> + '_ {
        self.pixel_bits(pixel)
            .iter()
            .enumerate()
            .flat_map(|(w, &word)| {
                let mut bits = word;
                std::iter::from_fn(move || {
                    (bits != 0).then(|| {
                        let k = 64 * w + bits.trailing_zeros() as usize;
                        bits &= bits - 1;
                        k
                    })
                })
            })
    }

    /// All words, pixel-major ((H, W, words_per_pixel), row-major).
    pub fn bits(&self) -> &[u64] {
        &self.bits
    }

    /// The mask of an image of `height` x `width` pixels twice as fine: pixel (r, c) takes the
    /// bits of pixel (r / 2, c / 2) (clamped to this image).
    pub fn upsample(&self, height: usize, width: usize) -> Result<ShadowMask> {
        let words = self.words;
        let mut bits = crate::memory::try_vec(height * width * words, 0u64, "the shadow mask")?;
        if self.height > 0 && self.width > 0 && words > 0 {
            bits.par_chunks_mut(width * words)
                .enumerate()
                .for_each(|(r, row)| {
                    let rc = (r / 2).min(self.height - 1);
                    for (c, out) in row.chunks_exact_mut(words).enumerate() {
                        let p = rc * self.width + (c / 2).min(self.width - 1);
                        out.copy_from_slice(self.pixel_bits(p));
                    }
                });
        }
        Ok(ShadowMask {
            height,
            width,
            lights: self.lights,
            words,
            bits,
        })
    }

    /// The mask of an image of `height` x `width` pixels and `lights` lights where
    /// `shadowed(pixel, light)` (for tests of the code that reads masks).
    #[cfg(test)]
    pub(crate) fn from_fn(
        height: usize,
        width: usize,
        lights: usize,
        shadowed: impl Fn(usize, usize) -> bool,
    ) -> ShadowMask {
        let words = lights.div_ceil(64);
        let mut bits = vec![0u64; height * width * words];
        for p in 0..height * width {
            for k in (0..lights).filter(|&k| shadowed(p, k)) {
                bits[p * words + k / 64] |= 1 << (k % 64);
            }
        }
        ShadowMask {
            height,
            width,
            lights,
            words,
            bits,
        }
    }

    /// Number of (pixel, light) pairs in a cast shadow.
    pub fn count(&self) -> usize {
        self.bits.iter().map(|w| w.count_ones() as usize).sum()
    }

    /// The mask as booleans in the layout of an image stack, (k, H, W).
    pub fn to_bools(&self) -> Result<Vec<bool>> {
        let plane = self.height * self.width;
        let mut out = crate::memory::try_vec(self.lights * plane, false, "the shadow mask")?;
        if plane > 0 {
            out.par_chunks_mut(plane)
                .enumerate()
                .for_each(|(k, image)| {
                    for (p, o) in image.iter_mut().enumerate() {
                        *o = self.bits[p * self.words + k / 64] >> (k % 64) & 1 == 1;
                    }
                });
        }
        Ok(out)
    }
}

/// The cast shadows of the surface `depth` ((H+1) x (W+1) vertex depths, row-major) under the
/// rig's lights, for the pixels of `mask` (H x W; None: all), marching at most `max_steps`
/// pixels per facet and light (None: `2 max(H, W)`, more than any path inside the image). See
/// the module documentation.
pub fn cast_shadows(
    rig: &Rig,
    height: usize,
    width: usize,
    depth: &[f64],
    mask: Option<&[bool]>,
    max_steps: Option<usize>,
) -> Result<ShadowMask> {
    let plane = height * width;
    ensure_mask(mask, plane)?;
    let vertices = crate::geometry::vertices(&rig.camera, height, width, depth)?;
    shadows_of_vertices(rig, height, width, &vertices, mask, max_steps)
}

/// [`cast_shadows`] from the vertex positions ((H+1) x (W+1)); the mask's length is checked
/// by the caller.
pub(crate) fn shadows_of_vertices(
    rig: &Rig,
    height: usize,
    width: usize,
    vertices: &[[f64; 3]],
    mask: Option<&[bool]>,
    max_steps: Option<usize>,
) -> Result<ShadowMask> {
    march_all(
        &rig.camera,
        &rig.lights,
        height,
        width,
        Vertices::Positions(vertices),
        mask,
        max_steps,
        true,
        1,
    )
}

/// The cast shadows of the current mesh of a solver: the surface of the unknowns `u` on `grid`
/// (its facets are the mask; vertices without an unknown are missing) under `lights`, marching
/// at most `max_steps` pixels (None: the default of [`cast_shadows`]), from the facets whose row
/// and column are both `stride / 2` modulo `stride` (1: every facet; a larger stride probes a
/// lattice of them, `1 / stride²` of the cost, for an estimate of the shadowed share).
pub(crate) fn mesh_shadows(
    camera: &Camera,
    lights: &[Light],
    grid: &crate::grid::Grid,
    geometry: &crate::geometry::Geometry,
    u: &[f64],
    max_steps: Option<usize>,
    stride: usize,
) -> Result<ShadowMask> {
    let (height, width) = (grid.height, grid.width);
    let vertices = Vertices::Mesh { grid, geometry, u };
    // Every pixel a facet: no mask (the same marches), not a pass over the facets to make one.
    let mask = match grid.n_facets() == height * width {
        true => None,
        false => Some(facet_mask(grid)?),
    };
    march_all(
        camera,
        lights,
        height,
        width,
        vertices,
        mask.as_deref(),
        max_steps,
        true,
        stride,
    )
}

/// The pixels of `grid`'s image that are facets: the mask of a march over its mesh.
fn facet_mask(grid: &crate::grid::Grid) -> Result<Vec<bool>> {
    let plane = grid.height * grid.width;
    let mut mask = crate::memory::try_vec(plane, false, "the mask of the shadow march")?;
    for p in grid.facets.iter().map(|&p| p as usize) {
        mask[p] = true;
    }
    Ok(mask)
}

/// Whether row or column `i` is on the probe lattice of `stride` (see [`mesh_shadows`]).
pub(crate) fn on_lattice(i: usize, stride: usize) -> bool {
    i % stride == stride / 2
}

/// [`shadows_of_vertices`], skipping through the cells of a [`Pyramid`] when `skip`; the result is
/// the same either way. Only the facets on the lattice of `stride` (see [`mesh_shadows`]) march.
#[allow(clippy::too_many_arguments)]
pub(crate) fn march_all(
    camera: &Camera,
    lights: &[Light],
    height: usize,
    width: usize,
    vertices: Vertices<'_>,
    mask: Option<&[bool]>,
    max_steps: Option<usize>,
    skip: bool,
    stride: usize,
) -> Result<ShadowMask> {
    let stride = stride.max(1);
    let on_lattice = |i: usize| on_lattice(i, stride);
    let max_steps = max_steps.unwrap_or(2 * height.max(width));
    ensure_range(max_steps >= 1, "max_steps", max_steps as f64, || {
        "max_steps must be at least 1".to_string()
    })?;
    let plane = height * width;
    let rig_lights = lights;
    let lights = rig_lights.len();
    let words = lights.div_ceil(64);
    crate::memory::check(
        || format!("the cast shadows of {lights} lights on {plane} pixels"),
        8.0 * (plane * words) as f64,
        None,
    )?;
    let mut bits = crate::memory::try_vec(plane * words, 0u64, "the shadow mask")?;
    let undistorted = match *camera {
        Camera::Pinhole { distortion, .. } => distortion == [0.0; 5],
        _ => true,
    };
    let pyramid = match words > 0 && skip && undistorted {
        true => Some(Pyramid::new(height, width, vertices, mask)?),
        false => None,
    };
    // The pyramid's vertex depths are those of every vertex: their smallest finite one is
    // `min_depth`'s (a minimum, whatever the order), without computing each depth again.
    let z_min = match &pyramid {
        Some(pyramid) => pyramid
            .z
            .par_iter()
            .copied()
            .filter(|z| z.is_finite())
            .reduce(|| f64::INFINITY, f64::min),
        None => vertices.min_depth(),
    };
    if words > 0 && z_min.is_finite() {
        let march = March {
            camera,
            height,
            width,
            vertices,
            mask,
            z_min,
            max_steps,
            pyramid,
        };
        // Bands of BAND rows in parallel, blocks of BAND x BLOCK pixels in each, one light after
        // the other in each block: the marches of a block under a light cross nearby cells.
        bits.par_chunks_mut(words * width * BAND)
            .enumerate()
            .for_each(|(b, out)| {
                let rows = out.len() / (words * width);
                let mut facets = Vec::with_capacity(BAND * BLOCK);
                for c0 in (0..width).step_by(BLOCK) {
                    facets.clear();
                    for r in (b * BAND..b * BAND + rows).filter(|&r| on_lattice(r)) {
                        for col in (c0..(c0 + BLOCK).min(width)).filter(|&c| on_lattice(c)) {
                            let p = r * width + col;
                            if let Some(f) = march.facet(p) {
                                facets.push((p - b * BAND * width, f));
                            }
                        }
                    }
                    for (k, light) in rig_lights.iter().enumerate() {
                        for &(p, (c, n, slack)) in &facets {
                            let beta = light.beta(c).0;
                            if not_above(dot(n, beta), 0.0) {
                                continue;
                            }
                            if march.blocked(c, light, slack) {
                                out[p * words + k / 64] |= 1 << (k % 64);
                            }
                        }
                    }
                }
            });
    }
    Ok(ShadowMask {
        height,
        width,
        lights,
        words,
        bits,
    })
}

/// `march_refined` marches every facet (as `march_all`) when more than this share of the mask's
/// pixels are on its border (next to a pixel outside it, within the image): a solid object's
/// mask at 256² has about 2 % (a disc of radius r: 2 / r), one with a 1-pixel hole every 23
/// pixels about 17 %.
pub const MAX_BORDER_SHARE: f64 = 0.1;

/// The lattice of the refined march (`mesh_shadows_refined`, see the module documentation)
/// keeps at least this many facets across the larger side of the image: its stride is 2 up to
/// 511 pixels a side (every facet of a 256² level is within a pixel of the lattice), 4 from
/// 1024, 8 from 2048.
pub const REFINED_LATTICE: usize = 256;

/// The stride of the lattice of [`mesh_shadows_refined`] on an image of `height` x `width`
/// pixels: the largest power of two `s >= 2` with `max(height, width) / s >= REFINED_LATTICE`
/// ([`REFINED_LATTICE`]), 2 when there is none. A march of every facet costs `H W k`
/// marches; the lattice `H W k / s²` plus the facets near a shadow's edge, whose band is about
/// `s` pixels wide: `O(s E k)` for edges `E` pixels long. At 1 MP (`s = 4`) the lattice is 1/16
/// of the facets instead of 1/4, and a shadow it can miss is at most 4 pixels wide, 1/256 of
/// the image, as 2 pixels are at 512².
pub(crate) fn refined_stride(height: usize, width: usize) -> usize {
    let side = height.max(width);
    let mut s = 2;
    while side / (2 * s) >= REFINED_LATTICE {
        s *= 2;
    }
    s
}

/// From this many pixels on the larger side of the image, the solver's cast shadows without
/// interreflections come from the lattice of stride 2 (`mesh_shadows_refined`) instead of a
/// march of every facet, whose cost grows as `H W k` times the march's length (about the
/// image's side): measured on the synthetic block with cast shadows, 0.2 % noise, 27 lights,
/// `shadows=True`, the run's CPU time fell from 8.2 to 5.0-5.4 s at 1024² and from 33.3 to
/// 21.0 s at 2048², the mean normal error the same to 1e-4 degrees; the lattice missed 9-11 %
/// of the marked observations there (shadow slivers narrower than 2 pixels; the largest
/// change of a normal 0.17-0.24°). The lattice of `refined_stride` (4 at 1 MP, 8 from 2048)
/// missed 41-86 % of them (a normal moved by up to 36°), so this path keeps stride 2. Below
/// this size every facet marches (the march costs little there, and the benchmarks' scenes
/// are validated with it).
pub const LATTICE_SIDE: usize = 1024;

/// The stride of the lattice from which the solver computes the cast shadows of an image of
/// `height` x `width` pixels: with `indirect` light (the rounds of interreflections and the
/// run after them) [`refined_stride`]; without, 2 from [`LATTICE_SIDE`] pixels on the larger
/// side, and None (every facet marches, [`mesh_shadows`]) below it.
pub(crate) fn solver_stride(height: usize, width: usize, indirect: bool) -> Option<usize> {
    match (indirect, height.max(width) >= LATTICE_SIDE) {
        (true, _) => Some(refined_stride(height, width)),
        (false, true) => Some(2),
        (false, false) => None,
    }
}

/// [`mesh_shadows`] (every facet, `stride` 1) from fewer marches: the facets of the lattice of
/// stride `s` (at least 2; the solver's from [`solver_stride`]) (rows and columns `s / 2`
/// modulo `s`, as [`on_lattice`]; for
/// `s = 2` the odd rows and columns, a quarter of the facets) march every light; each other
/// facet takes, for a light it faces, the verdict of the 1, 2 or 4 lattice facets nearest it
/// (the lattice rows and columns on either side of its own) when they all face that light and
/// agree, and marches that light itself otherwise (at a shadow's edge, next to a terminator, or
/// where a neighbour is missing: outside the image, the mask or the finite vertices). Cast
/// shadows are smooth over the image but for their edges: the marches are `1 / s²` plus the
/// share of edge pixels. Unlike [`mesh_shadows`] it can miss a shadow (or a lit gap) narrower
/// than the lattice, `s` pixels, that none of the lattice facets around a facet sees, and a
/// march that ends at a hole of the mask (unblocked) where its neighbours' do not: on synthetic
/// scenes with low lights 0-0.2 % of the shadowed observations differ at `s = 2` (test
/// `the_refined_march_agrees_with_the_full_one`); a mask with a long border is marched in full
/// ([`MAX_BORDER_SHARE`]). The marches it makes are the same as [`mesh_shadows`]'.
pub(crate) fn mesh_shadows_refined(
    camera: &Camera,
    lights: &[Light],
    grid: &crate::grid::Grid,
    geometry: &crate::geometry::Geometry,
    u: &[f64],
    stride: usize,
) -> Result<ShadowMask> {
    let (height, width) = (grid.height, grid.width);
    let vertices = Vertices::Mesh { grid, geometry, u };
    let mask = facet_mask(grid)?;
    march_refined(camera, lights, height, width, vertices, &mask, stride)
}

/// [`mesh_shadows_refined`] of the mesh `vertices` ((H+1) x (W+1)) over the pixels of `mask`
/// (H x W) with a lattice of `stride` (at least 2), as [`march_all`] without a stride and with
/// the default `max_steps`.
pub(crate) fn march_refined(
    camera: &Camera,
    lights: &[Light],
    height: usize,
    width: usize,
    vertices: Vertices<'_>,
    mask: &[bool],
    stride: usize,
) -> Result<ShadowMask> {
    let stride = stride.max(2);
    let plane = height * width;
    ensure_mask(Some(mask), plane)?;
    // A mask with a long border (many holes, each of which ends the marches that enter it) is
    // not smooth at the scale of the lattice: marched in full.
    let in_full = long_border(height, width, mask);
    let start = start_partial(camera, lights, height, width, vertices, mask, in_full, 24.0)?;
    let (mut bits, march) = match start {
        Ok(start) => start,
        Err(done) => return Ok(done),
    };
    let words = lights.len().div_ceil(64);
    let lattice = |i: usize| on_lattice(i, stride);
    // The lattice: per pixel, the lights it is shadowed from and the lights it faces (both
    // zero off the lattice and where it is not a facet).
    let mut known = crate::memory::try_vec(plane * words, 0u64, "the shadow mask")?;
    let mut facing = crate::memory::try_vec(plane * words, 0u64, "the shadow mask")?;
    let lanes: Vec<Option<LaneLight>> = lights.iter().map(LaneLight::from_light).collect();
    known
        .par_chunks_mut(words * width)
        .zip(facing.par_chunks_mut(words * width))
        .enumerate()
        .filter(|(r, _)| lattice(*r))
        .for_each(|(r, (out, faces))| {
            // The lights each lattice facet of the row faces (in lanes), then its marches.
            let mut batch = FacingBatch::new(lights, &lanes);
            for col in (0..width).filter(|&c| lattice(c)) {
                if let Some((c, n, _)) = march.facet(r * width + col) {
                    batch.push(col, c, n, faces, words);
                }
            }
            batch.flush(faces, words);
            for col in (0..width).filter(|&c| lattice(c)) {
                let f = &faces[col * words..(col + 1) * words];
                if f.iter().all(|&b| b == 0) {
                    continue;
                }
                let Some((c, _, slack)) = march.facet(r * width + col) else {
                    continue;
                };
                for (k, light) in lights.iter().enumerate() {
                    if f[k / 64] & (1 << (k % 64)) != 0 && march.blocked(c, light, slack) {
                        out[col * words + k / 64] |= 1 << (k % 64);
                    }
                }
            }
        });
    // The lattice rows (columns) on either side of row (column) `i` of `size`: itself on the
    // lattice, else the one before and the one after that exist.
    let near = |i: usize, size: usize| -> ([usize; 2], usize) {
        if lattice(i) {
            return ([i, i], 1);
        }
        let o = stride / 2;
        let before = (i >= o).then(|| i - (i - o) % stride);
        let after = before.map_or(o, |b| b + stride);
        match (before, after < size) {
            (Some(b), true) => ([b, after], 2),
            (Some(b), false) => ([b, b], 1),
            (None, true) => ([after, after], 1),
            (None, false) => ([0, 0], 0),
        }
    };
    bits.par_chunks_mut(words * width)
        .enumerate()
        .for_each(|(r, out)| {
            let (rows, nr) = near(r, height);
            // The lights each facet of the row off the lattice faces (in lanes).
            let mut own = vec![0u64; width * words];
            let mut batch = FacingBatch::new(lights, &lanes);
            for col in (0..width).filter(|&c| !(lattice(r) && lattice(c))) {
                if let Some((c, n, _)) = march.facet(r * width + col) {
                    batch.push(col, c, n, &mut own, words);
                }
            }
            batch.flush(&mut own, words);
            for col in 0..width {
                let p = r * width + col;
                let o = &mut out[col * words..(col + 1) * words];
                if lattice(r) && lattice(col) {
                    o.copy_from_slice(&known[p * words..(p + 1) * words]);
                    continue;
                }
                let faces = &own[col * words..(col + 1) * words];
                if faces.iter().all(|&b| b == 0) {
                    continue;
                }
                let Some((c, _, slack)) = march.facet(p) else {
                    continue;
                };
                let (cols, nc) = near(col, width);
                let mut around = [0usize; 4];
                let mut count = 0;
                for &rr in &rows[..nr] {
                    for &cc in &cols[..nc] {
                        around[count] = rr * width + cc;
                        count += 1;
                    }
                }
                let around = &around[..count];
                let complete = count > 0 && around.iter().all(|&q| mask[q]);
                for (k, light) in lights.iter().enumerate() {
                    let (w, bit) = (k / 64, 1u64 << (k % 64));
                    if faces[w] & bit == 0 {
                        continue;
                    }
                    let faced =
                        complete && around.iter().all(|&q| facing[q * words + w] & bit != 0);
                    let shadowed = around
                        .iter()
                        .filter(|&&q| known[q * words + w] & bit != 0)
                        .count();
                    let verdict = match (faced, shadowed) {
                        (true, 0) => false,
                        (true, s) if s == count => true,
                        _ => march.blocked(c, light, slack),
                    };
                    if verdict {
                        o[w] |= bit;
                    }
                }
            }
        });
    Ok(ShadowMask {
        height,
        width,
        lights: lights.len(),
        words,
        bits,
    })
}

/// The start of a march that takes verdicts from elsewhere ([`march_refined`], [`march_guided`])
/// over the pixels of `mask` (H x W): `Err` with the result where nothing is left to do
/// ([`march_all`]'s where `in_full`, the empty mask where no light or no vertex with a finite
/// depth is marched), else `Ok` with the mask's bits (all zero) and the march (see
/// [`March::masked`]). `bytes` is what a word of the mask costs the caller in all, checked
/// against the memory limit.
#[allow(clippy::too_many_arguments)]
fn start_partial<'a>(
    camera: &'a Camera,
    lights: &[Light],
    height: usize,
    width: usize,
    vertices: Vertices<'a>,
    mask: &'a [bool],
    in_full: bool,
    bytes: f64,
) -> Result<std::result::Result<(Vec<u64>, March<'a>), ShadowMask>> {
    if in_full {
        let all = march_all(
            camera,
            lights,
            height,
            width,
            vertices,
            Some(mask),
            None,
            true,
            1,
        )?;
        return Ok(Err(all));
    }
    let plane = height * width;
    let words = lights.len().div_ceil(64);
    crate::memory::check(
        || {
            format!(
                "the cast shadows of {} lights on {plane} pixels",
                lights.len()
            )
        },
        bytes * (plane * words) as f64,
        None,
    )?;
    let bits = crate::memory::try_vec(plane * words, 0u64, "the shadow mask")?;
    let march = match words > 0 && plane > 0 {
        true => March::masked(camera, height, width, vertices, mask)?,
        false => None,
    };
    Ok(match march {
        Some(march) => Ok((bits, march)),
        None => Err(ShadowMask {
            height,
            width,
            lights: lights.len(),
            words,
            bits,
        }),
    })
}

/// Whether more than [`MAX_BORDER_SHARE`] of the pixels of `mask` (H x W) are on its border
/// (next to a pixel outside it, within the image): such a mask (many holes, each of which ends
/// the marches that enter it) is not smooth at the scale of a lattice, and is marched in full.
fn long_border(height: usize, width: usize, mask: &[bool]) -> bool {
    let border = (0..height * width)
        .filter(|&p| {
            let (r, c) = (p / width, p % width);
            mask[p]
                && ((r > 0 && !mask[p - width])
                    || (r + 1 < height && !mask[p + width])
                    || (c > 0 && !mask[p - 1])
                    || (c + 1 < width && !mask[p + 1]))
        })
        .count();
    let inside = mask.iter().filter(|&&m| m).count();
    border as f64 > MAX_BORDER_SHARE * inside as f64
}

/// The pixels around a pixel whose verdicts the solver's `march_guided` compares: those
/// within this many rows and columns of it (its 5 x 5 neighbourhood). Measured on the GI
/// renders at 256² with the coarser level's mask as the prior (docs/concave.md, stop 52; mean
/// normal errors against the lattice's march): radius 1 moved the bowls by +0.009 and
/// +0.014° and the blocks by +0.014° (the shadows' edges moved by more than a pixel between
/// the two meshes), 2 by at most +0.003°, 3 by at most +0.001°; the sheet marched 22 600,
/// 41 700 and 57 600 times against the lattice's 261 000. Radius 3 up to stop 54; 2 since
/// stop 55 (with the coarse level's last run also guided, see `Solver::interreflect_with`:
/// the GI renders within +0.003° of radius 3, the sheet's CPU with the option about -6 %).
pub const GUIDE_RADIUS: usize = 2;

/// [`mesh_shadows`] (every facet) of the mesh `u` guided by `prior`, a mask of the same image
/// from a mesh near it (the coarser level's mask, upsampled, that the level started with; see
/// [`march_guided`]).
#[allow(clippy::too_many_arguments)]
pub(crate) fn mesh_shadows_guided(
    camera: &Camera,
    lights: &[Light],
    grid: &crate::grid::Grid,
    geometry: &crate::geometry::Geometry,
    u: &[f64],
    prior: &ShadowMask,
    radius: usize,
) -> Result<ShadowMask> {
    let (height, width) = (grid.height, grid.width);
    let vertices = Vertices::Mesh { grid, geometry, u };
    let mask = facet_mask(grid)?;
    march_guided(
        camera, lights, height, width, vertices, &mask, prior, radius,
    )
}

/// The cast shadows of the mesh `vertices` ((H+1) x (W+1)) over the pixels of `mask` (H x W),
/// as [`march_all`] with the default `max_steps`, marching only where `prior` (a mask of the
/// same image and lights from a mesh near this one) has an edge. A facet `p` that faces light
/// `k` takes the verdict that `prior` gives every pixel `q` of its neighbourhood `N(p)` (the
/// pixels of the image within `radius` rows and columns of it) when
///
/// ```text
/// every q in N(p) is a facet that faces k on this mesh, and
/// prior(q, k) is the same for every q in N(p),
/// ```
///
/// and marches light `k` itself otherwise: at an edge of the prior's shadows (within `radius`
/// pixels of one), next to a terminator of this mesh, or next to a pixel outside the mask or
/// the finite vertices. This is [`march_refined`]'s rule with the prior's verdicts in place of
/// those of a lattice marched on this mesh: none of the lattice's `H W k / s²` marches, only
/// the edges'. It can miss where the shadows moved, between the prior's mesh and this one, by
/// more than `radius` pixels away from the prior's edges, and a shadow (or a lit gap) the prior
/// did not have and that touches none of its edges; the prior of a coarser level (each pixel
/// the verdict of the coarse pixel under it) resolves shadows as a lattice of stride 2 does.
/// The marches it makes are the same as [`march_all`]'s; a mask with a long border
/// ([`MAX_BORDER_SHARE`]) or a prior of another size is marched in full.
#[allow(clippy::too_many_arguments)]
pub(crate) fn march_guided(
    camera: &Camera,
    lights: &[Light],
    height: usize,
    width: usize,
    vertices: Vertices<'_>,
    mask: &[bool],
    prior: &ShadowMask,
    radius: usize,
) -> Result<ShadowMask> {
    let plane = height * width;
    ensure_mask(Some(mask), plane)?;
    let words = lights.len().div_ceil(64);
    let matches = prior.height == height
        && prior.width == width
        && prior.lights == lights.len()
        && prior.words == words;
    let in_full = !matches || long_border(height, width, mask);
    let start = start_partial(camera, lights, height, width, vertices, mask, in_full, 16.0)?;
    let (mut bits, march) = match start {
        Ok(start) => start,
        Err(done) => return Ok(done),
    };
    // Per pixel, the lights it faces on this mesh (zero where it is not a facet), the point
    // lights in lanes of FACE_LANES facets of a row.
    let mut facing = crate::memory::try_vec(plane * words, 0u64, "the shadow mask")?;
    let lanes: Vec<Option<LaneLight>> = lights.iter().map(LaneLight::from_light).collect();
    facing
        .par_chunks_mut(words * width)
        .enumerate()
        .for_each(|(r, faces)| {
            let mut batch = FacingBatch::new(lights, &lanes);
            for col in 0..width {
                if let Some((c, n, _)) = march.facet(r * width + col) {
                    batch.push(col, c, n, faces, words);
                }
            }
            batch.flush(faces, words);
        });
    let span = |i: usize, size: usize| i.saturating_sub(radius)..(i + radius + 1).min(size);
    bits.par_chunks_mut(words * width)
        .enumerate()
        .for_each(|(r, out)| {
            // The neighbourhood's AND and OR in two passes (they do not depend on the order):
            // per column over the rows of `span(r)`, then per pixel over the columns of its
            // span (2 (2 radius + 1) words a pixel instead of (2 radius + 1)²).
            let mut column_face = vec![!0u64; width * words];
            let mut column_all = vec![!0u64; width * words];
            let mut column_any = vec![0u64; width * words];
            for rr in span(r, height) {
                let row = rr * width * words..(rr + 1) * width * words;
                let (f, s) = (&facing[row.clone()], &prior.bits[row]);
                for i in 0..width * words {
                    column_face[i] &= f[i];
                    column_all[i] &= s[i];
                    column_any[i] |= s[i];
                }
            }
            let mut all_face = vec![0u64; words];
            let mut all_shadowed = vec![0u64; words];
            let mut any_shadowed = vec![0u64; words];
            for col in 0..width {
                let p = r * width + col;
                let faces = &facing[p * words..(p + 1) * words];
                if faces.iter().all(|&f| f == 0) {
                    continue;
                }
                all_face.fill(!0);
                all_shadowed.fill(!0);
                any_shadowed.fill(0);
                for cc in span(col, width) {
                    let i = cc * words;
                    for w in 0..words {
                        all_face[w] &= column_face[i + w];
                        all_shadowed[w] &= column_all[i + w];
                        any_shadowed[w] |= column_any[i + w];
                    }
                }
                // The lights this facet faces whose neighbourhood agrees: the shadowed ones
                // take the verdict; the others (`open`) march.
                let o = &mut out[col * words..(col + 1) * words];
                let mut open = false;
                for w in 0..words {
                    let agreed = all_face[w] & (all_shadowed[w] | !any_shadowed[w]);
                    o[w] = faces[w] & agreed & all_shadowed[w];
                    open |= faces[w] & !agreed != 0;
                }
                if !open {
                    continue;
                }
                // The facet's centre only where a light marches.
                let Some((c, _, slack)) = march.facet(p) else {
                    o.fill(0);
                    continue;
                };
                for (k, light) in lights.iter().enumerate() {
                    let (w, bit) = (k / 64, 1u64 << (k % 64));
                    let agreed = all_face[w] & (all_shadowed[w] | !any_shadowed[w]);
                    if faces[w] & !agreed & bit != 0 && march.blocked(c, light, slack) {
                        o[w] |= bit;
                    }
                }
            }
        });
    Ok(ShadowMask {
        height,
        width,
        lights: lights.len(),
        words,
        bits,
    })
}

/// Facets whose faced lights [`FacingBatch`] finds together, in SIMD lanes.
const FACE_LANES: usize = 8;

/// The lights that facets face, `n . beta_k(c) > 0` with the values of [`Light::beta`]
/// (`not_above(n . beta, 0)` false), [`FACE_LANES`] facets at a time: a point light's `beta` in
/// lanes ([`LaneLight::beta`], the scalar operations in their order per lane: the same values,
/// so the same bits), a directional light's one facet at a time.
struct FacingBatch<'a> {
    lights: &'a [Light],
    lanes: &'a [Option<LaneLight>],
    cols: [usize; FACE_LANES],
    centres: [[f64; 3]; FACE_LANES],
    normals: [[f64; 3]; FACE_LANES],
    count: usize,
}

impl<'a> FacingBatch<'a> {
    fn new(lights: &'a [Light], lanes: &'a [Option<LaneLight>]) -> FacingBatch<'a> {
        FacingBatch {
            lights,
            lanes,
            cols: [0; FACE_LANES],
            centres: [[0.0; 3]; FACE_LANES],
            normals: [[0.0; 3]; FACE_LANES],
            count: 0,
        }
    }

    /// Adds the facet of column `col` (centre `c`, normal `n`); a full batch sets its bits in
    /// `faces` (`words` a column).
    fn push(&mut self, col: usize, c: [f64; 3], n: [f64; 3], faces: &mut [u64], words: usize) {
        let l = self.count;
        (self.cols[l], self.centres[l], self.normals[l]) = (col, c, n);
        self.count += 1;
        if self.count == FACE_LANES {
            self.flush(faces, words);
        }
    }

    /// Sets the bits of the facets added since the last flush (the unused lanes repeat the
    /// first facet and are not read).
    fn flush(&mut self, faces: &mut [u64], words: usize) {
        let count = std::mem::take(&mut self.count);
        if count == 0 {
            return;
        }
        for l in count..FACE_LANES {
            (self.centres[l], self.normals[l]) = (self.centres[0], self.normals[0]);
        }
        let (centres, normals) = (&self.centres, &self.normals);
        for (k, (light, lane)) in self.lights.iter().zip(self.lanes).enumerate() {
            let faced = faced_lanes(light, lane.as_ref(), centres, normals);
            for (l, &col) in self.cols[..count].iter().enumerate() {
                if faced[l] {
                    faces[col * words + k / 64] |= 1 << (k % 64);
                }
            }
        }
    }
}

/// Rows of a band and columns of a block of the pixels' order (see [`march_all`]).
const BAND: usize = 32;
const BLOCK: usize = 32;

/// The nearest vertex depth of the cells of a quadtree over the pixels: level `l` has cells of
/// `2^l` x `2^l` pixels, level 0 one cell a pixel (the nearest of its 4 corners), level `l + 1`
/// the nearest of the 4 cells of level `l` under each of its cells; `-inf` where a pixel of the
/// cell is outside the mask or has a non-finite corner. A march whose samples stay within a cell
/// and above its nearest depth (`z - tol <= min`) cannot be blocked there and skips to the
/// cell's edge: the coarsest such cell gives the longest jump. Only for cameras without
/// distortion, whose samples are evenly spaced in pixels. Skipping changes no result: it passes
/// over only samples that could not stop the march.
pub(crate) struct Pyramid {
    /// Per level: its columns and its minima (row-major), in single precision rounded down
    /// ([`round_down`]: a cell's minimum is never above its nearest depth, so a skip stays
    /// safe and the result is still the plain march's; half the memory of double precision).
    levels: Vec<(usize, Vec<f32>)>,
    /// The vertex depths, (H+1) x (W+1): a third of the memory of the positions, for the
    /// march's bilinear depths.
    z: Vec<f64>,
}

impl Pyramid {
    fn new(
        height: usize,
        width: usize,
        vertices: Vertices<'_>,
        mask: Option<&[bool]>,
    ) -> Result<Pyramid> {
        crate::memory::check(
            || format!("the depth pyramid of a {height} x {width} image"),
            // Levels 0, 1, ...: 1 + 1/4 + 1/16 + ... < 4/3 values (f32) a pixel.
            // and the vertex depths.
            4.0 * 1.34 * (height * width) as f64 + 8.0 * ((height + 1) * (width + 1)) as f64,
            None,
        )?;
        let vw = width + 1;
        let z = crate::memory::try_par_collect(
            (0..vertices.len())
                .into_par_iter()
                .map(|v| vertices.at(v)[2]),
            "the depths of the shadow march",
        )?;
        let base = crate::memory::try_par_collect(
            (0..height * width).into_par_iter().map(|p| {
                if mask.is_some_and(|m| !m[p]) {
                    return f32::NEG_INFINITY;
                }
                let v = (p / width) * vw + p % width;
                let mut lo = f64::INFINITY;
                // (the depths just computed: `z[v]` is `vertices.at(v)[2]`)
                for z in [v, v + 1, v + vw, v + vw + 1].map(|v| z[v]) {
                    if !z.is_finite() {
                        return f32::NEG_INFINITY;
                    }
                    lo = lo.min(z);
                }
                round_down(lo)
            }),
            "the depth pyramid",
        )?;
        let mut levels = vec![(width, base)];
        let (mut rows, mut cols) = (height, width);
        while rows > 1 || cols > 1 {
            let (r2, c2) = (rows.div_ceil(2), cols.div_ceil(2));
            let below = &levels.last().expect("level 0").1;
            let next = crate::memory::try_par_collect(
                (0..r2 * c2).into_par_iter().map(|t| {
                    let (r, c) = (2 * (t / c2), 2 * (t % c2));
                    let mut lo = f32::INFINITY;
                    for rr in r..(r + 2).min(rows) {
                        for cc in c..(c + 2).min(cols) {
                            lo = lo.min(below[rr * cols + cc]);
                        }
                    }
                    lo
                }),
                "the depth pyramid",
            )?;
            levels.push((c2, next));
            (rows, cols) = (r2, c2);
        }
        Ok(Pyramid { levels, z })
    }
}

/// The largest single-precision value not above `x` (for the pyramid's minima): `x` itself
/// when it is one, infinities as they are.
#[inline]
fn round_down(x: f64) -> f32 {
    let f = x as f32;
    if f64::from(f) <= x {
        f
    } else if f == 0.0 {
        -f32::from_bits(1)
    } else if f > 0.0 {
        // The next value towards zero (`f32::next_down`, newer than the crate's MSRV).
        f32::from_bits(f.to_bits() - 1)
    } else {
        f32::from_bits(f.to_bits() + 1)
    }
}

/// The point of the segment from `c` to `e` (with `d = e - c`) whose image lies at the share
/// `s` of the way between the images of its ends: `c + s d` for an orthographic camera, and
/// for a pinhole camera `c + w d` with `w = s c_z / ((1 - s) e_z + s c_z)` (depth is harmonic,
/// not linear, along the image of a segment). Exact without distortion.
#[inline]
pub(crate) fn segment_point(
    c: [f64; 3],
    e: [f64; 3],
    d: [f64; 3],
    s: f64,
    perspective: bool,
) -> [f64; 3] {
    let w = if perspective {
        s * c[2] / ((1.0 - s) * e[2] + s * c[2])
    } else {
        s
    };
    [c[0] + w * d[0], c[1] + w * d[1], c[2] + w * d[2]]
}

/// The depth a surface must come nearer than to hide a point at depth `z` of a march: `z`
/// less a relative rounding margin and the march's own `slack`.
#[inline]
pub(crate) fn hiding_depth(z: f64, slack: f64) -> f64 {
    z - (1e-6 * z.abs() + slack)
}

/// What one march needs: the camera, the mesh, the mask and the bounds.
pub(crate) struct March<'a> {
    pub(crate) camera: &'a Camera,
    pub(crate) height: usize,
    pub(crate) width: usize,
    pub(crate) vertices: Vertices<'a>,
    pub(crate) mask: Option<&'a [bool]>,
    pub(crate) z_min: f64,
    pub(crate) max_steps: usize,
    pub(crate) pyramid: Option<Pyramid>,
}

impl<'a> March<'a> {
    /// The march of [`march_refined`] and [`march_guided`] over the pixels of `mask`: the
    /// default `max_steps` (twice the larger side), the min-depth pyramid where the camera has
    /// no distortion; None when no vertex has a finite depth (nothing to march).
    fn masked(
        camera: &'a Camera,
        height: usize,
        width: usize,
        vertices: Vertices<'a>,
        mask: &'a [bool],
    ) -> Result<Option<March<'a>>> {
        let z_min = vertices.min_depth();
        if !z_min.is_finite() {
            return Ok(None);
        }
        let undistorted = match *camera {
            Camera::Pinhole { distortion, .. } => distortion == [0.0; 5],
            _ => true,
        };
        let pyramid = match undistorted {
            true => Some(Pyramid::new(height, width, vertices, Some(mask))?),
            false => None,
        };
        Ok(Some(March {
            camera,
            height,
            width,
            vertices,
            mask: Some(mask),
            z_min,
            max_steps: 2 * height.max(width),
            pyramid,
        }))
    }
}

impl March<'_> {
    /// The 4 corners of pixel (row, col): (r, c), (r, c+1), (r+1, c), (r+1, c+1).
    #[inline]
    pub(crate) fn quad(&self, row: usize, col: usize) -> [[f64; 3]; 4] {
        let v = row * (self.width + 1) + col;
        let w = self.width + 1;
        [
            self.vertices.at(v),
            self.vertices.at(v + 1),
            self.vertices.at(v + w),
            self.vertices.at(v + w + 1),
        ]
    }

    /// The centre, normal and self-shadow slack (a quarter of the spread of its corner
    /// depths) of facet `p`, or None outside the mask or with a non-finite corner.
    pub(crate) fn facet(&self, p: usize) -> Option<([f64; 3], [f64; 3], f64)> {
        if self.mask.is_some_and(|m| !m[p]) {
            return None;
        }
        let q = self.quad(p / self.width, p % self.width);
        if !q.iter().flatten().all(|x| x.is_finite()) {
            return None;
        }
        let (c, n) = (quad_centre(&q), quad_normal(&q));
        let (lo, hi) = q
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), x| {
                (lo.min(x[2]), hi.max(x[2]))
            });
        Some((c, n, 0.25 * (hi - lo)))
    }

    /// The undistorted image-plane point of `x` in pixels (see the module documentation).
    #[inline]
    fn plane_point(&self, x: [f64; 3]) -> [f64; 2] {
        match *self.camera {
            Camera::Orthographic { pixel_size, .. } => [x[0] / pixel_size[0], x[1] / pixel_size[1]],
            Camera::Pinhole { k, .. } => {
                let (a, b) = (x[0] / x[2], x[1] / x[2]);
                [k[0][0] * a + k[0][1] * b, k[1][1] * b]
            }
        }
    }

    /// Whether the segment from `c` towards `light` passes behind the surface.
    fn blocked(&self, c: [f64; 3], light: &Light, slack: f64) -> bool {
        let perspective = self.camera.is_perspective();
        // The far end e of the segment, before the cut at z_min.
        let (dir, t_end) = match *light {
            Light::Point { position, .. } => (sub(position, c), 1.0),
            Light::Directional { direction, .. } => {
                // Far enough that the image of c + T d is many image sizes away (or at the
                // vanishing point, for a pinhole camera).
                let reach = (self.height + self.width) as f64 * 1e3;
                let scale = if perspective {
                    c[2].abs()
                } else {
                    let [u, v] = self.plane_point(direction);
                    1.0 / u.hypot(v).max(1e-300)
                };
                (direction, (reach * scale).min(1e300))
            }
        };
        // Cut where the segment comes nearer than z_min.
        let t_cut = if dir[2] < 0.0 {
            ((self.z_min - c[2]) / dir[2]).max(0.0)
        } else {
            f64::INFINITY
        };
        let t = t_end.min(t_cut);
        if not_above(t, 0.0) {
            return false;
        }
        let e = [c[0] + t * dir[0], c[1] + t * dir[1], c[2] + t * dir[2]];
        let (m0, m1) = (self.plane_point(c), self.plane_point(e));
        let length = (m1[0] - m0[0]).hypot(m1[1] - m0[1]);
        if !length.is_finite() {
            return false;
        }
        // Samples half a pixel apart, at most 2 max_steps of them (max_steps pixels).
        let total = (2.0 * length).ceil().max(1.0);
        let steps = (total as usize).min(2 * self.max_steps);
        let d = sub(e, c);
        let point = |i: usize| segment_point(c, e, d, i as f64 / total, perspective);
        // Blocked where the surface is nearer than `z - tol(z)`, which grows with z.
        let reach = |z: f64| hiding_depth(z, slack);
        // The image step of one sample, in pixels (exact without distortion).
        let step = [(m1[0] - m0[0]) / total, (m1[1] - m0[1]) / total];
        // Without a pyramid: the plain march, every sample.
        let Some(pyramid) = &self.pyramid else {
            for i in 1..=steps {
                let x = point(i);
                let [u, v] = self.camera.project(x);
                let Some(z_surface) = self.surface_depth(u + 0.5, v + 0.5) else {
                    return false;
                };
                if z_surface < reach(x[2]) {
                    return true;
                }
            }
            return false;
        };
        let top = pyramid.levels.len() - 1;
        let inverse = [1.0 / step[0], 1.0 / step[1]];
        // z is monotone along the segment: its largest value over a run of samples is at the
        // run's start (the segment comes nearer the camera) or its end.
        let rising = d[2] > 0.0;
        let mut level = 0;
        let mut i = 1;
        while i <= steps {
            let x = point(i);
            let [u, v] = self.project_undistorted(x);
            let (gx, gy) = (u + 0.5, v + 0.5);
            let Some(z_surface) = self.pyramid_depth(pyramid, gx, gy) else {
                return false;
            };
            if z_surface < reach(x[2]) {
                return true;
            }
            // The coarsest cell (from one level above the last jump's, down) that the next
            // samples stay in and pass in front of: jump over them.
            let (row, col) = self.cell(gx, gy);
            let mut l = (level + 1).min(top);
            loop {
                let k = self.samples_in_cell(l, row, col, gx, gy, step, inverse);
                if k > 0 {
                    let j = (i + k).min(steps);
                    let z = if rising { point(j)[2].max(x[2]) } else { x[2] };
                    let (cols, min) = &pyramid.levels[l];
                    let m = f64::from(min[(row >> l) * cols + (col >> l)]);
                    // A margin for the rounding of the bilinear depth and of z.
                    if reach(z) <= m - 1e-12 * m.abs() {
                        i = j + 1;
                        level = l;
                        break;
                    }
                }
                if l == 0 {
                    i += 1;
                    level = 0;
                    break;
                }
                l -= 1;
            }
        }
        false
    }

    /// The cell (row, col) of the grid point (gx, gy) inside the image.
    #[inline]
    fn cell(&self, gx: f64, gy: f64) -> (usize, usize) {
        (
            (gy as usize).min(self.height - 1),
            (gx as usize).min(self.width - 1),
        )
    }

    /// How many of the next samples, `step` pixels apart (`inverse` their inverses), stay
    /// strictly inside the cell of level `level` of the pyramid that holds pixel (row, col),
    /// from the grid point (gx, gy). Rounding moves the samples by far less than the margins of
    /// 1e-9 pixels and 1e-6 samples.
    #[allow(clippy::too_many_arguments)]
    #[inline]
    fn samples_in_cell(
        &self,
        level: usize,
        row: usize,
        col: usize,
        gx: f64,
        gy: f64,
        step: [f64; 2],
        inverse: [f64; 2],
    ) -> usize {
        // The distance to the cell's edge less 1e-9 pixels (far more than the rounding of the
        // samples' positions), in samples.
        let along = |g: f64, d: f64, inv: f64, lo: usize, size: usize| {
            if d > 0.0 {
                ((lo + (1 << level)).min(size) as f64 - g - 1e-9) * inv
            } else if d < 0.0 {
                (lo as f64 - g + 1e-9) * inv
            } else {
                f64::INFINITY
            }
        };
        let room = along(gx, step[0], inverse[0], (col >> level) << level, self.width).min(along(
            gy,
            step[1],
            inverse[1],
            (row >> level) << level,
            self.height,
        ));
        // The samples m >= 1 with m < room - 1e-6: ceil(room - 1e-6) - 1 of them.
        let r = room - 1e-6;
        if not_above(r, 0.0) {
            return 0;
        }
        if r >= (2 * self.max_steps) as f64 {
            return 2 * self.max_steps;
        }
        let f = r as usize;
        if f as f64 == r {
            f - 1
        } else {
            f
        }
    }

    /// [`Camera::project`] for a camera without distortion, inlined: the same values (the
    /// distortion of zero coefficients multiplies by 1 and adds 0).
    #[inline(always)]
    fn project_undistorted(&self, p: [f64; 3]) -> [f64; 2] {
        match *self.camera {
            Camera::Orthographic { pixel_size, origin } => [
                (p[0] - origin[0]) / pixel_size[0] - 0.5,
                (p[1] - origin[1]) / pixel_size[1] - 0.5,
            ],
            Camera::Pinhole { k, .. } => {
                if p[2] <= 0.0 {
                    return [f64::NAN; 2];
                }
                let (x, y) = (p[0] / p[2], p[1] / p[2]);
                [k[0][0] * x + k[0][1] * y + k[0][2], k[1][1] * y + k[1][2]]
            }
        }
    }

    /// [`March::surface_depth`] from the pyramid's depths and cells (a cell at `-inf` is
    /// outside the mask or has a non-finite corner): the same value.
    #[inline]
    fn pyramid_depth(&self, pyramid: &Pyramid, gx: f64, gy: f64) -> Option<f64> {
        let (w, h) = (self.width as f64, self.height as f64);
        if !(gx >= 0.0 && gx <= w && gy >= 0.0 && gy <= h) {
            return None;
        }
        let (row, col) = self.cell(gx, gy);
        if pyramid.levels[0].1[row * self.width + col] == f32::NEG_INFINITY {
            return None;
        }
        let v = row * (self.width + 1) + col;
        let z = &pyramid.z[v..v + self.width + 3];
        let (fx, fy) = (gx - col as f64, gy - row as f64);
        let z = (1.0 - fy) * ((1.0 - fx) * z[0] + fx * z[1])
            + fy * ((1.0 - fx) * z[self.width + 1] + fx * z[self.width + 2]);
        z.is_finite().then_some(z)
    }

    /// The bilinear surface depth at the grid point (gx, gy) (the image point plus 1/2), or
    /// None outside the image, the mask or the finite vertices.
    #[inline]
    pub(crate) fn surface_depth(&self, gx: f64, gy: f64) -> Option<f64> {
        let (w, h) = (self.width as f64, self.height as f64);
        if !(gx >= 0.0 && gx <= w && gy >= 0.0 && gy <= h) {
            return None;
        }
        let (row, col) = self.cell(gx, gy);
        if self.mask.is_some_and(|m| !m[row * self.width + col]) {
            return None;
        }
        let q = self.quad(row, col);
        let (fx, fy) = (gx - col as f64, gy - row as f64);
        let z = (1.0 - fy) * ((1.0 - fx) * q[0][2] + fx * q[1][2])
            + fy * ((1.0 - fx) * q[2][2] + fx * q[3][2]);
        z.is_finite().then_some(z)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vec3::normalize;

    const N: usize = 40;

    /// A plane at depth `z0` with a square block (vertex columns and rows `lo..=hi`) raised by
    /// `h` towards the camera.
    fn block(z0: f64, h: f64, lo: usize, hi: usize) -> Vec<f64> {
        (0..(N + 1) * (N + 1))
            .map(|v| {
                let (r, c) = (v / (N + 1), v % (N + 1));
                if (lo..=hi).contains(&r) && (lo..=hi).contains(&c) {
                    z0 - h
                } else {
                    z0
                }
            })
            .collect()
    }

    fn ortho(lights: Vec<Light>) -> Rig {
        Rig {
            camera: Camera::Orthographic {
                pixel_size: [1.0, 1.0],
                origin: [0.0, 0.0],
            },
            lights,
        }
    }

    fn pinhole(lights: Vec<Light>) -> Rig {
        let cx = (N as f64 - 1.0) / 2.0;
        Rig {
            camera: Camera::Pinhole {
                k: [[100.0, 0.0, cx], [0.0, 100.0, cx], [0.0, 0.0, 1.0]],
                distortion: [0.0; 5],
            },
            lights,
        }
    }

    fn sun(direction: [f64; 3]) -> Light {
        Light::Directional {
            direction: normalize(direction),
            intensity: [1.0; 3],
        }
    }

    /// The shadowed columns of row `row` for light `k`.
    fn shadowed_columns(s: &ShadowMask, row: usize, k: usize) -> Vec<usize> {
        (0..N).filter(|&c| s.is_shadowed(row * N + c, k)).collect()
    }

    #[test]
    fn a_plane_casts_no_shadows() {
        let lights = vec![
            Light::point([5.0, 30.0, 10.0]),
            Light::point([-50.0, 20.0, 60.0]),
            sun([1.0, 0.3, -0.5]),
            sun([0.0, 0.0, -1.0]),
        ];
        // Flat and tilted planes, orthographic.
        for slope in [0.0, 0.4] {
            let depth: Vec<f64> = (0..(N + 1) * (N + 1))
                .map(|v| 100.0 + slope * (v % (N + 1)) as f64)
                .collect();
            let s = cast_shadows(&ortho(lights.clone()), N, N, &depth, None, None).unwrap();
            assert_eq!(s.count(), 0, "slope {slope}");
        }
        // A plane seen by a pinhole camera, lights in front of it.
        let lights = vec![
            Light::point([50.0, 30.0, 100.0]),
            Light::point([-300.0, 20.0, 400.0]),
            sun([1.0, 0.3, -0.5]),
        ];
        let s = cast_shadows(
            &pinhole(lights),
            N,
            N,
            &vec![1000.0; (N + 1) * (N + 1)],
            None,
            None,
        )
        .unwrap();
        assert_eq!(s.count(), 0);
    }

    /// A block of height 10 on a plane at 100, orthographic, 1-unit pixels: a light at 45
    /// degrees on the +x side shadows the plane 10 units to the block's -x side (the wall is
    /// the facet between vertex columns 19 and 20, the top edge at x = 20); an overhead light
    /// shadows nothing.
    #[test]
    fn a_block_shadows_the_plane_on_the_far_side_of_a_low_light() {
        let depth = block(100.0, 10.0, 20, 30);
        let (rig_low, rig_high) = (
            ortho(vec![
                sun([1.0, 0.0, -1.0]),
                Light::point([125.0, 25.0, 0.0]),
            ]),
            ortho(vec![Light::point([25.0, 25.0, 0.0]), sun([0.0, 0.0, -1.0])]),
        );
        let s = cast_shadows(&rig_low, N, N, &depth, None, None).unwrap();
        // Directional at 45 degrees: plane pixels with centre x0 in (10, 19) are shadowed
        // (analytic shadow [10, 20], less the wall pixel 19), the first within a pixel.
        let cols = shadowed_columns(&s, 25, 0);
        assert!((cols[0] as f64 + 0.5 - 10.0).abs() <= 1.0, "{cols:?}");
        assert_eq!(cols.last().copied(), Some(18), "{cols:?}");
        assert!((cols.len() as f64 - 9.0).abs() <= 1.0, "{cols:?}");
        // Rows outside the block's span see the light.
        assert!(shadowed_columns(&s, 5, 0).is_empty());
        // Point light at x = 125, z = 0: from the plane at x0 the segment passes behind the
        // edge (x = 20, z = 90) when 100 (20 - x0) / (125 - x0) < 10, i.e.
        // x0 > 20 - 10 (125 - 20) / 90.
        // The shadow on the plane runs from there to the wall's foot (x = 19): its length in
        // pixels within a pixel of the analytic one.
        let cols = shadowed_columns(&s, 25, 1);
        let analytic = 19.0 - (20.0 - 10.0 * (125.0 - 20.0) / 90.0);
        assert_eq!(cols.last().copied(), Some(18), "{cols:?}");
        assert!(
            (cols.len() as f64 - analytic).abs() <= 1.0,
            "{cols:?} vs {analytic}"
        );
        let high = cast_shadows(&rig_high, N, N, &depth, None, None).unwrap();
        assert_eq!(high.count(), 0);
    }

    #[test]
    fn a_block_under_a_pinhole_camera() {
        // Plane at 1000, block 100 taller; f = 100 px, centre pixel 19.5: the top edge (vertex
        // column 20, u = 19.5) stands at x = 0; a 45-degree light from +x shadows the plane from
        // x = -100, i.e. u = -100 / 10 + 19.5 = 9.5, to the wall's foot (vertex column 19).
        let depth = block(1000.0, 100.0, 20, 30);
        let s = cast_shadows(
            &pinhole(vec![sun([1.0, 0.0, -1.0])]),
            N,
            N,
            &depth,
            None,
            None,
        )
        .unwrap();
        let cols = shadowed_columns(&s, 25, 0);
        assert!(
            (cols[0] as f64 - 9.5).abs() <= 1.0 && cols.last() == Some(&18),
            "{cols:?}"
        );
        // A point light high over the block's centre (u = v = 25 at z = 900: x = y = 49.5),
        // at z = 100: the segments from the plane rise more steeply than the walls, nothing.
        let s = cast_shadows(
            &pinhole(vec![Light::point([49.5, 49.5, 100.0])]),
            N,
            N,
            &depth,
            None,
            None,
        )
        .unwrap();
        assert_eq!(s.count(), 0);
    }

    #[test]
    fn max_steps_bounds_the_march_and_the_mask_stops_it() {
        let depth = block(100.0, 10.0, 20, 30);
        let rig = ortho(vec![sun([1.0, 0.0, -1.0])]);
        let s = cast_shadows(&rig, N, N, &depth, None, Some(3)).unwrap();
        // Only pixels whose blocker is within 3 pixels are found.
        let cols = shadowed_columns(&s, 25, 0);
        assert!(
            !cols.is_empty() && cols.len() <= 3 && cols[0] >= 15,
            "{cols:?}"
        );
        // Masking the block out: the march stops at its edge, no shadow.
        let mask: Vec<bool> = (0..N * N).map(|p| p % N < 19).collect();
        let s = cast_shadows(&rig, N, N, &depth, Some(&mask), None).unwrap();
        assert_eq!(s.count(), 0);
        let err = cast_shadows(&rig, N, N, &depth, Some(&mask[1..]), None).unwrap_err();
        assert!(err.to_string().contains("mask has"), "{err}");
        assert!(cast_shadows(&rig, N, N, &depth, None, Some(0)).is_err());
    }

    /// Skipping through the pyramid's cells changes no result: bumps and a block, both cameras, with a mask.
    /// The pyramid's single-precision minima never lie above the depths they bound.
    #[test]
    fn minima_round_down() {
        for x in [
            0.0,
            1.0,
            0.1,
            -0.1,
            123.456789,
            -7.3e-5,
            1e30,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ] {
            let f = round_down(x);
            assert!(f64::from(f) <= x, "{x}");
            assert!(x.is_infinite() || x - f64::from(f) <= 1.2e-7 * x.abs().max(1e-30));
        }
        assert_eq!(round_down(0.5), 0.5);
        assert_eq!(round_down(1e300), f32::MAX);
        assert!(round_down(-1e-50) < 0.0);
    }

    #[test]
    fn the_pyramid_changes_nothing() {
        let bumpy: Vec<f64> = (0..(N + 1) * (N + 1))
            .map(|v| {
                let (r, c) = ((v / (N + 1)) as f64, (v % (N + 1)) as f64);
                100.0
                    - 6.0 * (-((r - 12.0).powi(2) + (c - 25.0).powi(2)) / 20.0).exp()
                    - 4.0 * (-((r - 30.0).powi(2) + (c - 10.0).powi(2)) / 8.0).exp()
            })
            .collect();
        let mask: Vec<bool> = (0..N * N).map(|p| (p / N + p % N) % 17 != 3).collect();
        let lights = vec![
            sun([1.0, 0.2, -1.0]),
            sun([-0.4, -1.0, -0.8]),
            Light::point([60.0, 10.0, 60.0]),
            Light::point([-20.0, 50.0, 80.0]),
        ];
        let mut found = 0;
        for depth in [bumpy, block(100.0, 10.0, 20, 30)] {
            let depth_pinhole: Vec<f64> = depth.iter().map(|z| 10.0 * z).collect();
            for (rig, z) in [
                (ortho(lights.clone()), &depth),
                (pinhole(lights.clone()), &depth_pinhole),
            ] {
                let v = crate::geometry::vertices(&rig.camera, N, N, z).unwrap();
                for m in [None, Some(&mask[..])] {
                    let fast = march_all(
                        &rig.camera,
                        &rig.lights,
                        N,
                        N,
                        Vertices::Positions(&v),
                        m,
                        None,
                        true,
                        1,
                    )
                    .unwrap();
                    let slow = march_all(
                        &rig.camera,
                        &rig.lights,
                        N,
                        N,
                        Vertices::Positions(&v),
                        m,
                        None,
                        false,
                        1,
                    )
                    .unwrap();
                    assert_eq!(fast, slow);
                    found += fast.count();
                }
            }
        }
        assert!(found > 100, "{found}");
    }

    /// The synthetic scenes of the march tests (kind, seed).
    #[cfg(feature = "synth")]
    const LOW_LIGHT_SCENES: [(crate::synth::SceneKind, u64); 5] = [
        (crate::synth::SceneKind::Block, 0),
        (crate::synth::SceneKind::Bumps, 1),
        (crate::synth::SceneKind::Bumps, 7),
        (crate::synth::SceneKind::Cube, 0),
        (crate::synth::SceneKind::SphereCap, 3),
    ];

    /// A synthetic scene of `n` x `n` pixels with point and directional lights, moved low over
    /// it so that the bumps cast shadows too.
    #[cfg(feature = "synth")]
    fn low_light_scene(
        kind: crate::synth::SceneKind,
        seed: u64,
        pinhole: bool,
        n: usize,
    ) -> crate::synth::Scene {
        use crate::synth::{Scene, SceneOptions};
        let options = SceneOptions::default()
            .with_pinhole(pinhole)
            .with_directional(true);
        let mut scene = Scene::with_options(kind, n, 100.0, 200.0, seed, options).unwrap();
        for (i, light) in scene.rig.lights.iter_mut().enumerate() {
            let a = i as f64 * 0.7;
            match light {
                Light::Point { position, .. } if i % 2 == 1 => {
                    *position = [150.0 * a.cos(), 150.0 * a.sin(), 180.0];
                }
                Light::Directional { direction, .. } => {
                    *direction = normalize([a.cos(), a.sin(), -0.4]);
                }
                _ => {}
            }
        }
        scene
    }

    /// The pyramid's march equals the plain one on synthetic scenes: block and bumps (several
    /// seeds), orthographic and pinhole, point and directional lights, with and without a mask
    /// and a hole of unknown depths, and a short `max_steps`.
    #[cfg(feature = "synth")]
    #[test]
    fn the_pyramid_changes_nothing_on_synthetic_scenes() {
        let n = 72;
        let mut found = 0;
        for (kind, seed) in LOW_LIGHT_SCENES {
            for pinhole in [false, true] {
                let scene = low_light_scene(kind, seed, pinhole, n);
                let mut depth = scene.depth.clone();
                if seed == 7 {
                    for r in 30..34 {
                        for c in 40..45 {
                            depth[r * (n + 1) + c] = f64::NAN;
                        }
                    }
                }
                let rig = &scene.rig;
                let v = crate::geometry::vertices(&rig.camera, n, n, &depth).unwrap();
                let holes: Vec<bool> = (0..n * n).map(|p| (p / n * 7 + p % n) % 23 != 5).collect();
                for (m, steps) in [
                    (Some(&scene.mask[..]), None),
                    (None, None),
                    (Some(&holes[..]), None),
                    (None, Some(5)),
                ] {
                    let fast = march_all(
                        &rig.camera,
                        &rig.lights,
                        n,
                        n,
                        Vertices::Positions(&v),
                        m,
                        steps,
                        true,
                        1,
                    )
                    .unwrap();
                    let slow = march_all(
                        &rig.camera,
                        &rig.lights,
                        n,
                        n,
                        Vertices::Positions(&v),
                        m,
                        steps,
                        false,
                        1,
                    )
                    .unwrap();
                    assert_eq!(fast, slow, "{} seed {seed} pinhole {pinhole}", kind.name());
                    found += fast.count();
                }
            }
        }
        assert!(found > 10_000, "{found}");
    }

    /// The refined march ([`march_refined`]) against the march of every facet on the synthetic
    /// scenes of `the_pyramid_changes_nothing_on_synthetic_scenes` (lights low over them),
    /// orthographic and pinhole, with the scene's mask and with a mask full of holes: the
    /// verdicts it copies from the lattice are the march's but for shadows (or lit gaps)
    /// narrower than the lattice: measured 72 of 133 233 shadowed observations differ (at most
    /// 0.2 % in a case); at most 0.5 % allowed.
    #[cfg(feature = "synth")]
    #[test]
    fn the_refined_march_agrees_with_the_full_one() {
        use crate::synth::{Scene, SceneKind};
        let n = 72;
        // The share of a march's shadowed observations allowed to differ, strides 2 and 4.
        const ALLOWED: [f64; 2] = [0.005, 0.03];
        let (mut total, mut differ) = ([0; 2], [0; 2]);
        for (kind, seed) in LOW_LIGHT_SCENES {
            for pinhole in [false, true] {
                let scene = low_light_scene(kind, seed, pinhole, n);
                let rig = &scene.rig;
                let v = crate::geometry::vertices(&rig.camera, n, n, &scene.depth).unwrap();
                // A hole of 8 x 8 pixels (a march that enters it ends unblocked).
                let hole: Vec<bool> = (0..n * n)
                    .map(|p| {
                        scene.mask[p]
                            && !((30..38).contains(&(p / n)) && (40..48).contains(&(p % n)))
                    })
                    .collect();
                for (m, stride) in [&scene.mask[..], &hole[..]]
                    .into_iter()
                    .flat_map(|m| [(m, 2), (m, 4)])
                {
                    let vertices = Vertices::Positions(&v);
                    let full = march_all(
                        &rig.camera,
                        &rig.lights,
                        n,
                        n,
                        vertices,
                        Some(m),
                        None,
                        true,
                        1,
                    )
                    .unwrap();
                    let refined =
                        march_refined(&rig.camera, &rig.lights, n, n, vertices, m, stride).unwrap();
                    let d: usize = full
                        .bits()
                        .iter()
                        .zip(refined.bits())
                        .map(|(a, b)| (a ^ b).count_ones() as usize)
                        .sum();
                    eprintln!(
                        "{} seed {seed} pinhole {pinhole} stride {stride}: {d} of {}",
                        kind.name(),
                        full.count()
                    );
                    assert!(
                        d as f64 <= ALLOWED[stride / 4] * full.count() as f64,
                        "{} seed {seed} pinhole {pinhole} stride {stride}: {d} of {}",
                        kind.name(),
                        full.count()
                    );
                    total[stride / 4] += full.count();
                    differ[stride / 4] += d;
                }
            }
        }
        assert!(total[0] > 10_000, "{total:?}");
        eprintln!(
            "refined march (strides 2, 4): {differ:?} of {total:?} shadowed observations differ"
        );
        // A mask riddled with holes (1 pixel in 23, about 17 % of its pixels on its border) is
        // marched in full: the same mask.
        let scene = Scene::new(SceneKind::Bumps, n, 100.0, 200.0, 1).unwrap();
        let rig = &scene.rig;
        let v = crate::geometry::vertices(&rig.camera, n, n, &scene.depth).unwrap();
        let holes: Vec<bool> = (0..n * n).map(|p| (p / n * 7 + p % n) % 23 != 5).collect();
        let vertices = Vertices::Positions(&v);
        let full = march_all(
            &rig.camera,
            &rig.lights,
            n,
            n,
            vertices,
            Some(&holes),
            None,
            true,
            1,
        )
        .unwrap();
        for stride in [2, 4] {
            let refined =
                march_refined(&rig.camera, &rig.lights, n, n, vertices, &holes, stride).unwrap();
            assert_eq!(full, refined);
        }
    }

    /// The guided march: with a prior that is this mesh's own full march it is that march, bit
    /// for bit (a facet whose neighbourhood agrees takes the verdict its march gives; the
    /// others march); with the full march of the mesh at half the resolution (every other
    /// vertex, the coarser camera), upsampled, it agrees with the full march but for a small
    /// share of the shadowed observations, far fewer than the upsampled prior alone misses; a
    /// prior of another size, and a mask with a long border, are marched in full.
    #[cfg(feature = "synth")]
    #[test]
    fn the_guided_march_agrees_with_the_full_one() {
        let n = 72;
        let h = n / 2;
        let (mut total, mut guided_off, mut prior_off) = (0, 0, 0);
        for (kind, seed) in LOW_LIGHT_SCENES {
            for pinhole in [false, true] {
                let scene = low_light_scene(kind, seed, pinhole, n);
                let rig = &scene.rig;
                let v = crate::geometry::vertices(&rig.camera, n, n, &scene.depth).unwrap();
                let vertices = Vertices::Positions(&v);
                let hole: Vec<bool> = (0..n * n)
                    .map(|p| {
                        scene.mask[p]
                            && !((30..38).contains(&(p / n)) && (40..48).contains(&(p % n)))
                    })
                    .collect();
                // The coarse mesh: every other vertex; a coarse pixel is in the mask when its
                // four fine pixels are.
                let cv: Vec<[f64; 3]> = (0..(h + 1) * (h + 1))
                    .map(|i| v[(i / (h + 1)) * 2 * (n + 1) + (i % (h + 1)) * 2])
                    .collect();
                let coarse_camera = crate::pyramid::coarser_camera(&rig.camera);
                for m in [&scene.mask[..], &hole[..]] {
                    let full = march_all(
                        &rig.camera,
                        &rig.lights,
                        n,
                        n,
                        vertices,
                        Some(m),
                        None,
                        true,
                        1,
                    )
                    .unwrap();
                    let exact = march_guided(&rig.camera, &rig.lights, n, n, vertices, m, &full, 3)
                        .unwrap();
                    assert_eq!(exact, full, "{} seed {seed} pinhole {pinhole}", kind.name());
                    let cm: Vec<bool> = (0..h * h)
                        .map(|q| {
                            let (r, c) = (2 * (q / h), 2 * (q % h));
                            m[r * n + c]
                                && m[r * n + c + 1]
                                && m[(r + 1) * n + c]
                                && m[(r + 1) * n + c + 1]
                        })
                        .collect();
                    let coarse = march_all(
                        &coarse_camera,
                        &rig.lights,
                        h,
                        h,
                        Vertices::Positions(&cv),
                        Some(&cm),
                        None,
                        true,
                        1,
                    )
                    .unwrap();
                    let prior = coarse.upsample(n, n).unwrap();
                    let differ = |a: &ShadowMask, b: &ShadowMask| -> usize {
                        a.bits()
                            .iter()
                            .zip(b.bits())
                            .map(|(x, y)| (x ^ y).count_ones() as usize)
                            .sum()
                    };
                    let guided =
                        march_guided(&rig.camera, &rig.lights, n, n, vertices, m, &prior, 3)
                            .unwrap();
                    let (d, p) = (differ(&guided, &full), differ(&prior, &full));
                    eprintln!(
                        "{} seed {seed} pinhole {pinhole}: guided {d}, prior {p} of {}",
                        kind.name(),
                        full.count()
                    );
                    assert!(
                        d as f64 <= 0.005 * full.count() as f64,
                        "{} seed {seed} pinhole {pinhole}: {d} of {}",
                        kind.name(),
                        full.count()
                    );
                    total += full.count();
                    guided_off += d;
                    prior_off += p;
                }
                // A prior of another size: the full march.
                let other = ShadowMask::from_fn(n, n - 1, rig.lights.len(), |_, _| true);
                let m = &scene.mask[..];
                let full = march_all(
                    &rig.camera,
                    &rig.lights,
                    n,
                    n,
                    vertices,
                    Some(m),
                    None,
                    true,
                    1,
                )
                .unwrap();
                let guided =
                    march_guided(&rig.camera, &rig.lights, n, n, vertices, m, &other, 3).unwrap();
                assert_eq!(guided, full);
            }
        }
        eprintln!("guided march: {guided_off} of {total} shadowed observations differ (prior alone {prior_off})");
        assert!(total > 10_000, "{total}");
        assert!(5 * guided_off < prior_off, "{guided_off} {prior_off}");
    }

    /// The lattice of the refined march keeps at least [`REFINED_LATTICE`] facets across: 2 at
    /// 256² and 512² (the GI renders' march unchanged), 4 at 1 MP, 8 at 12 MP.
    #[test]
    fn the_refined_lattice_grows_with_the_image() {
        for (side, stride) in [(1, 2), (72, 2), (256, 2), (511, 2), (512, 2), (1023, 2)] {
            assert_eq!(refined_stride(side, side / 2 + 1), stride, "{side}");
        }
        for (side, stride) in [(1024, 4), (2047, 4), (2048, 8), (4000, 8), (4096, 16)] {
            assert_eq!(refined_stride(side / 3, side), stride, "{side}");
        }
    }

    /// The solver's shadows: with interreflections the lattice of [`refined_stride`] at every
    /// size; without, every facet marches below [`LATTICE_SIDE`] pixels on the larger side
    /// (the benchmarks' 256² and 512² scenes) and the lattice of stride 2 from it.
    #[test]
    fn the_solver_marches_a_lattice_on_large_images() {
        for (h, w) in [(1, 1), (256, 256), (512, 300), (1023, 1023), (40, 1023)] {
            assert_eq!(solver_stride(h, w, false), None, "{h} x {w}");
            assert_eq!(solver_stride(h, w, true), Some(2), "{h} x {w}");
        }
        for (h, w, indirect) in [
            (1024, 1024, 4),
            (3000, 4000, 8),
            (10, 1024, 4),
            (2048, 9, 8),
        ] {
            assert_eq!(solver_stride(h, w, false), Some(2), "{h} x {w}");
            assert_eq!(solver_stride(h, w, true), Some(indirect), "{h} x {w}");
        }
    }

    #[test]
    fn the_mask_packs_many_lights() {
        let depth = block(100.0, 10.0, 20, 30);
        let lights: Vec<Light> = (0..70)
            .map(|i| {
                if i % 2 == 0 {
                    sun([1.0, 0.0, -1.0])
                } else {
                    sun([0.0, 0.0, -1.0])
                }
            })
            .collect();
        let s = cast_shadows(&ortho(lights), N, N, &depth, None, None).unwrap();
        assert_eq!(s.words_per_pixel(), 2);
        let bools = s.to_bools().unwrap();
        assert_eq!(bools.len(), 70 * N * N);
        assert_eq!(bools.iter().filter(|&&b| b).count(), s.count());
        for k in [0, 1, 64, 65, 69] {
            let p = 25 * N + 12;
            assert_eq!(s.is_shadowed(p, k), k % 2 == 0);
            assert_eq!(bools[k * N * N + p], k % 2 == 0);
        }
        // lights_at lists exactly the set bits, across both words.
        for p in [0, 25 * N + 12, N * N - 1] {
            let listed: Vec<usize> = s.lights_at(p).collect();
            let set: Vec<usize> = (0..70).filter(|&k| s.is_shadowed(p, k)).collect();
            assert_eq!(listed, set, "pixel {p}");
        }
        assert!(s.lights_at(25 * N + 12).any(|k| k >= 64));
    }

    /// Timings of [`cast_shadows`] on the block and bumps scenes with 16 lights (medians of 3):
    /// `cargo test -p nplps --release --features synth --lib shadow -- --ignored --nocapture`.
    /// `NPLPS_SHADOW_SIZES` (comma-separated, default `256,1024`) picks the sizes.
    #[cfg(feature = "synth")]
    #[test]
    #[ignore = "timings"]
    fn timings() {
        use crate::synth::{Scene, SceneKind, SceneOptions};
        let sizes: Vec<usize> = std::env::var("NPLPS_SHADOW_SIZES")
            .unwrap_or_else(|_| "256,1024".to_string())
            .split(',')
            .map(|s| s.trim().parse().unwrap())
            .collect();
        for n in sizes {
            for kind in [SceneKind::Block, SceneKind::Bumps] {
                for pinhole in [false, true] {
                    let options = SceneOptions::default().with_pinhole(pinhole);
                    let mut scene = Scene::with_options(kind, n, 100.0, 200.0, 0, options).unwrap();
                    scene.rig.lights.truncate(16);
                    let mut times = Vec::new();
                    let mut count = 0;
                    for _ in 0..3 {
                        let start = std::time::Instant::now();
                        let s =
                            cast_shadows(&scene.rig, n, n, &scene.depth, Some(&scene.mask), None)
                                .unwrap();
                        times.push(start.elapsed().as_secs_f64());
                        count = s.count();
                    }
                    times.sort_by(f64::total_cmp);
                    println!(
                        "shadow timing: {n}x{n} {} {} 16 lights: median {:.3} s (min {:.3}), {count} shadowed",
                        kind.name(),
                        if pinhole { "pinhole" } else { "ortho" },
                        times[1],
                        times[0]
                    );
                }
            }
        }
    }
}
