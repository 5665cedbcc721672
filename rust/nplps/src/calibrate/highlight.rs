//! The highlight of a light on a sphere (step 3 of the [module documentation](super)).
//!
//! Inside the sphere's image (pixels whose viewing ray passes within `limb_margin` (0.97) `R` of
//! the centre), the brightest pixel and the 8-connected blob above the midpoint between it and
//! the sphere's median; a plane fitted to a ring 2-4 pixels (Chebyshev) around the blob is the
//! local background (the diffuse shading). The position is the mean of the centroids of the
//! regions where the bilinear interpolant exceeds the background by 1/4, 1/2 and 3/4 of the
//! peak's excess (8 x 8 samples per pixel): sub-pixel also when the blob is saturated. A blob
//! that is not compact (more than `max_blob_fraction`, 5 %, of the sphere's image), too faint,
//! or clipped by the limb is rejected.
//!
//! Each level region is a small circle of normals about the mirror normal, which the sphere's
//! curvature and foreshortening shift towards the sphere's image centre by
//! `A tan(t) / (2 pi R_px)` (area `A`, tilt `t` of the normal from the view, image radius
//! `R_px`); [`correct_highlight`] moves it back.

use nalgebra::{Matrix3, Vector3};

use super::fits::median;
use super::rays::reflected_ray;
use super::sphere::Sphere;
use crate::rig::Camera;
use crate::vec3::{dot, not_above, not_at_least, sub};

/// Thresholds of the highlight search.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub struct HighlightOptions {
    /// The highlight must stand out: `peak - background >= min_contrast * peak` (default 0.3).
    pub min_contrast: f64,
    /// Largest blob, as a fraction of the sphere's image (default 0.05).
    pub max_blob_fraction: f64,
    /// Pixels whose ray passes within this fraction of the radius from the centre are searched
    /// (default 0.97: keeps away from the limb).
    pub limb_margin: f64,
}

impl Default for HighlightOptions {
    fn default() -> Self {
        HighlightOptions {
            min_contrast: 0.3,
            max_blob_fraction: 0.05,
            limb_margin: 0.97,
        }
    }
}

with_fields!(HighlightOptions {
    with_min_contrast: min_contrast: f64,
    with_max_blob_fraction: max_blob_fraction: f64,
    with_limb_margin: limb_margin: f64,
});

/// A highlight in one image on one sphere.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Highlight {
    /// Sub-pixel image position (u, v), corrected for the sphere's curvature (see
    /// `correct_highlight`).
    pub pixel: [f64; 2],
    /// The mean area (pixels) of the level regions whose centroids make the position.
    pub level_area: f64,
    /// The curvature correction applied (pixels, outwards from the sphere's image centre).
    pub correction: f64,
    /// Brightest value.
    pub peak: f64,
    /// Local background level at the peak (a plane fitted around the blob).
    pub background: f64,
    /// Pixels of the blob above the midpoint between background and peak.
    pub area: usize,
    /// Pixels of the blob at the peak value (saturated, for clipped images).
    pub saturated: usize,
}

/// Why no highlight was taken from a sphere in an image.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Rejection {
    /// The brightest value does not stand out from the sphere's background.
    Faint,
    /// The bright blob is too large to be a highlight.
    Large,
    /// The blob reaches the limb (clipped, unreliable).
    Limb,
    /// The highlight's viewing ray misses the sphere.
    Miss,
    /// The joint refinement found the highlight inconsistent with the other observations of its
    /// light (more than 5 robust standard deviations off).
    Inconsistent,
}

impl Rejection {
    /// Short description.
    pub fn describe(&self) -> &'static str {
        match self {
            Rejection::Faint => "no highlight (too faint)",
            Rejection::Large => "bright region too large for a highlight",
            Rejection::Limb => "highlight at the limb",
            Rejection::Miss => "highlight off the sphere",
            Rejection::Inconsistent => "highlight inconsistent with the other spheres",
        }
    }
}

/// The levels, as fractions of the way from the background to the peak, whose sub-pixel region
/// centroids are averaged into the highlight position.
const HIGHLIGHT_LEVELS: [f64; 3] = [0.25, 0.5, 0.75];

/// Sub-samples per pixel and axis of the bilinear interpolant in the highlight centroid.
const HIGHLIGHT_SUBSAMPLES: usize = 8;

/// The pixels of the sphere's image whose ray passes within `margin * R` of the centre, as
/// (bounding box [r0, c0, r1, c1] inclusive, flags over the box).
pub(super) fn sphere_region(
    camera: &Camera,
    sphere: &Sphere,
    height: usize,
    width: usize,
    margin: f64,
) -> Option<([usize; 4], Vec<bool>)> {
    // Bounding box from the image circle, generously (exact test below).
    let reach = 1.5 * sphere.image_radius + 3.0;
    let [cu, cv] = sphere.image_center;
    if !(cu.is_finite() && cv.is_finite()) {
        return None;
    }
    let clamp = |x: f64, n: usize| x.max(0.0).min((n - 1) as f64) as usize;
    let (r0, r1) = (
        clamp((cv - reach).floor(), height),
        clamp((cv + reach).ceil(), height),
    );
    let (c0, c1) = (
        clamp((cu - reach).floor(), width),
        clamp((cu + reach).ceil(), width),
    );
    let bw = c1 - c0 + 1;
    let limit = margin * sphere.radius;
    let mut inside = vec![false; (r1 - r0 + 1) * bw];
    let mut any = false;
    for r in r0..=r1 {
        for c in c0..=c1 {
            let ray = camera.ray([c as f64, r as f64]);
            let ahead = dot(sub(sphere.center, ray.origin), ray.direction) > 0.0;
            if ahead && ray.distance_to(sphere.center) < limit {
                inside[(r - r0) * bw + (c - c0)] = true;
                any = true;
            }
        }
    }
    any.then_some(([r0, c0, r1, c1], inside))
}

/// Finds the highlight of one image (H x W) inside a sphere's region (see the
/// [module documentation](self)).
pub(super) fn find_highlight_in(
    image: &[f32],
    height: usize,
    width: usize,
    bbox: [usize; 4],
    inside: &[bool],
    options: &HighlightOptions,
) -> std::result::Result<Highlight, Rejection> {
    let [r0, c0, r1, c1] = bbox;
    let bw = c1 - c0 + 1;
    let bh = r1 - r0 + 1;
    let value = |i: usize| image[(r0 + i / bw) * width + c0 + i % bw] as f64;
    let mut values = Vec::with_capacity(inside.len());
    let (mut peak, mut at) = (f64::NEG_INFINITY, 0usize);
    for (i, &ins) in inside.iter().enumerate() {
        if ins {
            let v = value(i);
            values.push(v);
            if v > peak {
                peak = v;
                at = i;
            }
        }
    }
    let region = values.len();
    let background = median(&mut values);
    if not_at_least(peak - background, options.min_contrast * peak.abs())
        || not_above(peak, background)
    {
        return Err(Rejection::Faint);
    }
    // 8-connected blob of the region's pixels where `above(value, pixel)` holds, from the peak;
    // the pixels (box indices) and the number above `count_above`.
    let flood = |above: &dyn Fn(f64, usize) -> bool,
                 count_above: &dyn Fn(f64, usize) -> bool|
     -> std::result::Result<(Vec<usize>, usize, usize), Rejection> {
        let mut blob = vec![false; inside.len()];
        let mut stack = vec![at];
        blob[at] = true;
        let (mut members, mut area, mut saturated) = (Vec::new(), 0usize, 0usize);
        let mut touches_limb = false;
        while let Some(i) = stack.pop() {
            let v = value(i);
            let (br, bc) = (i / bw, i % bw);
            members.push(i);
            if count_above(v, i) {
                area += 1;
            }
            if v >= peak {
                saturated += 1;
            }
            for dr in -1isize..=1 {
                for dc in -1isize..=1 {
                    let (rr, cc) = (br as isize + dr, bc as isize + dc);
                    if rr < 0 || cc < 0 || rr >= bh as isize || cc >= bw as isize {
                        touches_limb = true;
                        continue;
                    }
                    let j = rr as usize * bw + cc as usize;
                    if !inside[j] {
                        touches_limb = true;
                        continue;
                    }
                    if !blob[j] && above(value(j), j) {
                        blob[j] = true;
                        stack.push(j);
                    }
                }
            }
            if area as f64 > options.max_blob_fraction * region as f64 {
                return Err(Rejection::Large);
            }
        }
        if touches_limb {
            return Err(Rejection::Limb);
        }
        Ok((members, area, saturated))
    };
    // First blob: above the midpoint of the sphere's median and the peak.
    let mid0 = background + 0.5 * (peak - background);
    let (first, _, _) = flood(&|v, _| v > mid0, &|v, _| v > mid0)?;
    // Local background: a plane fitted to the ring 2..4 pixels (Chebyshev) around the blob.
    let mut near = vec![u8::MAX; inside.len()];
    for &i in &first {
        let (br, bc) = ((i / bw) as isize, (i % bw) as isize);
        for dr in -4isize..=4 {
            for dc in -4isize..=4 {
                let (rr, cc) = (br + dr, bc + dc);
                if rr < 0 || cc < 0 || rr >= bh as isize || cc >= bw as isize {
                    continue;
                }
                let j = rr as usize * bw + cc as usize;
                near[j] = near[j].min(dr.unsigned_abs().max(dc.unsigned_abs()) as u8);
            }
        }
    }
    let mut ata = Matrix3::<f64>::zeros();
    let mut atb = Vector3::<f64>::zeros();
    let mut ring = 0usize;
    for (j, &d) in near.iter().enumerate() {
        if (2..=4).contains(&d) && inside[j] {
            let row = Vector3::new(1.0, (j % bw) as f64, (j / bw) as f64);
            ata += row * row.transpose();
            atb += row * value(j);
            ring += 1;
        }
    }
    let plane = (ring >= 12)
        .then(|| ata.cholesky().map(|c| c.solve(&atb)))
        .flatten()
        .filter(|p| p.iter().all(|v| v.is_finite()))
        .unwrap_or_else(|| Vector3::new(background, 0.0, 0.0));
    // Background at box pixel (row, column) offsets, continuous.
    let base = |bu: f64, bv: f64| plane[0] + plane[1] * bu + plane[2] * bv;
    let excess = |v: f64, i: usize| v - base((i % bw) as f64, (i / bw) as f64);
    let top = excess(peak, at);
    if not_above(top, 0.0) || top < options.min_contrast * peak.abs() {
        return Err(Rejection::Faint);
    }
    let low = HIGHLIGHT_LEVELS[0] * top;
    let (members, area, saturated) =
        flood(&|v, i| excess(v, i) > low, &|v, i| excess(v, i) > 0.5 * top)?;
    // The blob dilated by one pixel, in image coordinates, bounds the sub-pixel regions.
    let (mut rmin, mut rmax, mut cmin, mut cmax) = (usize::MAX, 0, usize::MAX, 0);
    for &i in &members {
        let (r, c) = (r0 + i / bw, c0 + i % bw);
        rmin = rmin.min(r);
        rmax = rmax.max(r);
        cmin = cmin.min(c);
        cmax = cmax.max(c);
    }
    let (wr0, wc0) = (rmin.saturating_sub(1), cmin.saturating_sub(1));
    let (wr1, wc1) = ((rmax + 1).min(height - 1), (cmax + 1).min(width - 1));
    let ww = wc1 - wc0 + 1;
    let mut allowed = vec![false; (wr1 - wr0 + 1) * ww];
    for &i in &members {
        let (r, c) = (r0 + i / bw, c0 + i % bw);
        for rr in r.saturating_sub(1)..=(r + 1).min(wr1) {
            for cc in c.saturating_sub(1)..=(c + 1).min(wc1) {
                allowed[(rr - wr0) * ww + (cc - wc0)] = true;
            }
        }
    }
    // Centroid of {bilinear interpolant - local plane > level}, sub-sampled, per level;
    // averaged. (The plane is linear: the interpolant of the excess is the excess of the
    // interpolant.)
    let s = HIGHLIGHT_SUBSAMPLES;
    let at_px = |r: usize, c: usize| image[r * width + c] as f64;
    let mut sums = [[0.0f64; 3]; HIGHLIGHT_LEVELS.len()];
    for r in wr0..wr1 {
        for c in wc0..wc1 {
            let (q00, q01, q10, q11) = (
                at_px(r, c),
                at_px(r, c + 1),
                at_px(r + 1, c),
                at_px(r + 1, c + 1),
            );
            for a in 0..s {
                let fv = (a as f64 + 0.5) / s as f64;
                let nr = r + usize::from(fv >= 0.5);
                for b in 0..s {
                    let fu = (b as f64 + 0.5) / s as f64;
                    let nc = c + usize::from(fu >= 0.5);
                    if !allowed[(nr - wr0) * ww + (nc - wc0)] {
                        continue;
                    }
                    let (u, v) = (c as f64 + fu, r as f64 + fv);
                    let e = (1.0 - fv) * ((1.0 - fu) * q00 + fu * q01)
                        + fv * ((1.0 - fu) * q10 + fu * q11)
                        - base(u - c0 as f64, v - r0 as f64);
                    for (sum, f) in sums.iter_mut().zip(HIGHLIGHT_LEVELS) {
                        if e > f * top {
                            sum[0] += u;
                            sum[1] += v;
                            sum[2] += 1.0;
                        }
                    }
                }
            }
        }
    }
    let used: Vec<[f64; 3]> = sums
        .iter()
        .filter(|s| s[2] > 0.0)
        .map(|s| {
            [
                s[0] / s[2],
                s[1] / s[2],
                s[2] / (HIGHLIGHT_SUBSAMPLES * HIGHLIGHT_SUBSAMPLES) as f64,
            ]
        })
        .collect();
    if used.is_empty() {
        return Err(Rejection::Faint);
    }
    let n = used.len() as f64;
    Ok(Highlight {
        pixel: [
            used.iter().map(|p| p[0]).sum::<f64>() / n,
            used.iter().map(|p| p[1]).sum::<f64>() / n,
        ],
        level_area: used.iter().map(|p| p[2]).sum::<f64>() / n,
        correction: 0.0,
        peak,
        background: base((at % bw) as f64, (at / bw) as f64),
        area,
        saturated,
    })
}

/// Finds the highlight of one image (H x W, grey) on a located sphere; see the
/// [module documentation](super).
pub fn find_highlight(
    camera: &Camera,
    image: &[f32],
    height: usize,
    width: usize,
    sphere: &Sphere,
    options: &HighlightOptions,
) -> std::result::Result<Highlight, Rejection> {
    let (bbox, inside) =
        sphere_region(camera, sphere, height, width, options.limb_margin).ok_or(Rejection::Miss)?;
    find_highlight_in(image, height, width, bbox, &inside, options)
        .and_then(|h| correct_highlight(camera, sphere, h).ok_or(Rejection::Miss))
}

/// Corrects a highlight's centroid for the curvature of the sphere. The source's angular
/// profile is symmetric about the mirror direction, so each level region of the highlight is
/// (to second order) a small circle of normals about the mirror normal `n_m`, of angular radius
/// `g`. Projected onto the image, such a region's area centroid lies `R_px sin(t) g^2 / 2`
/// closer to the sphere's image centre than the image of `n_m` (half from the curvature of the
/// cap, half from its foreshortening), where `t` is the angle between `n_m` and the viewing
/// direction and `R_px` the sphere's image radius; with the region's area
/// `A = pi g^2 R_px^2 cos(t)` the shift is `A tan(t) / (2 pi R_px)`. The correction moves the
/// centroid back by that amount, away from the image of the sphere's centre. (For sources that
/// are wider across the plane of incidence than along it, such as a Phong lobe at incidence
/// `i`, the factor changes by `cos(i) (3 + 1 / cos^2(i)) / 4`: 2 % at 17 degrees.) None when
/// the viewing ray misses the sphere.
pub(crate) fn correct_highlight(
    camera: &Camera,
    sphere: &Sphere,
    highlight: Highlight,
) -> Option<Highlight> {
    let (_, n, _) = reflected_ray(camera, sphere, highlight.pixel)?;
    let view = camera.ray(highlight.pixel).direction;
    let cos_t = (-dot(n, view)).clamp(1e-6, 1.0);
    let tan_t = (1.0 - cos_t * cos_t).sqrt() / cos_t;
    let d = [
        highlight.pixel[0] - sphere.image_center[0],
        highlight.pixel[1] - sphere.image_center[1],
    ];
    let len = d[0].hypot(d[1]);
    if not_above(len, 1e-9) || not_above(sphere.image_radius, 0.0) {
        return Some(highlight);
    }
    let shift = highlight.level_area * tan_t / (2.0 * std::f64::consts::PI * sphere.image_radius);
    let pixel = [
        highlight.pixel[0] + shift * d[0] / len,
        highlight.pixel[1] + shift * d[1] / len,
    ];
    reflected_ray(camera, sphere, pixel)?;
    Some(Highlight {
        pixel,
        correction: shift,
        ..highlight
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calibrate::outline::mask_boundary;
    use crate::calibrate::rays::ray_sphere;
    use crate::calibrate::sphere::{locate_sphere, OUTLINE_FIT_SIGMA};
    use crate::vec3::{add, angle, scale, unit};

    #[test]
    fn highlight_centroid_is_sub_pixel_also_when_saturated() {
        let (h, w) = (40, 60);
        // A saturated Gaussian blob at a sub-pixel position: its centroid is found to 0.02 px.
        let cam = Camera::Orthographic {
            pixel_size: [1.0, 1.0],
            origin: [-0.5, -0.5],
        };
        let sphere = Sphere {
            placement: 0,
            center: [30.0, 20.0, 100.0],
            radius: 15.0,
            image_center: [30.0, 20.0],
            image_radius: 15.0,
            fit_rms: 0.0,
            outline_points: [0, 0],
            scale_check: 1.0,
            shift: 0.0,
            outline_sigma: OUTLINE_FIT_SIGMA,
        };
        let truth = [33.37, 18.71];
        let image: Vec<f32> = (0..h * w)
            .map(|p| {
                let (u, v) = ((p % w) as f64, (p / w) as f64);
                let g = 4.0
                    * (-((u - truth[0]).powi(2) + (v - truth[1]).powi(2)) / (2.0 * 1.5f64.powi(2)))
                        .exp();
                (0.2 + g).min(1.0) as f32
            })
            .collect();
        // (Image-space symmetric: the centroid before the sphere-curvature correction.)
        let options = HighlightOptions::default();
        let (bbox, inside) = sphere_region(&cam, &sphere, h, w, options.limb_margin).unwrap();
        let hl = find_highlight_in(&image, h, w, bbox, &inside, &options).unwrap();
        assert!(
            (hl.pixel[0] - truth[0]).abs() < 0.02 && (hl.pixel[1] - truth[1]).abs() < 0.02,
            "{hl:?}"
        );
        assert!(hl.saturated > 5);
        // A flat image has no highlight.
        let flat = vec![0.3f32; h * w];
        assert_eq!(
            find_highlight(&cam, &flat, h, w, &sphere, &HighlightOptions::default()),
            Err(Rejection::Faint)
        );
    }

    #[test]
    fn highlight_symmetric_about_the_mirror_normal_lands_on_the_mirror_point() {
        // A saturated source profile that is a function of the angle between the surface
        // normal and the mirror normal, rendered with 4 x 4 samples per pixel.
        for camera in [
            Camera::Orthographic {
                pixel_size: [0.5, 0.5],
                origin: [-30.0, -30.0],
            },
            Camera::Pinhole {
                k: [[480.0, 0.0, 59.5], [0.0, 480.0, 59.5], [0.0, 0.0, 1.0]],
                distortion: [0.0; 5],
            },
        ] {
            let (h, w) = (120, 120);
            let center = [3.0, -2.0, 240.0];
            let radius = 20.0;
            let tilt = 28f64.to_radians();
            let n_m = unit([tilt.sin() * 0.6, -tilt.sin() * 0.8, -tilt.cos()]);
            let image: Vec<f32> = (0..h * w)
                .map(|p| {
                    let (u, v) = ((p % w) as f64, (p / w) as f64);
                    let mut acc = 0.0;
                    for a in 0..4 {
                        for b in 0..4 {
                            let uv = [
                                u + (a as f64 + 0.5) / 4.0 - 0.5,
                                v + (b as f64 + 0.5) / 4.0 - 0.5,
                            ];
                            let ray = camera.ray(uv);
                            acc += match ray_sphere(&ray, center, radius) {
                                Some(x) => {
                                    let n = scale(sub(x, center), 1.0 / radius);
                                    let g = angle(n, n_m);
                                    0.3 + 6.0 * (-g * g / (2.0 * 0.04f64.powi(2))).exp()
                                }
                                None => 0.02,
                            } / 16.0;
                        }
                    }
                    acc.min(1.0) as f32
                })
                .collect();
            let labels: Vec<u32> = (0..h * w)
                .map(|p| {
                    let ray = camera.ray([(p % w) as f64, (p / w) as f64]);
                    u32::from(ray_sphere(&ray, center, radius).is_some())
                })
                .collect();
            let mut sphere = locate_sphere(
                &camera,
                &mask_boundary(&labels, h, w, 1),
                radius,
                Some(center[2]),
            )
            .unwrap();
            // Exact geometry: the test is about the highlight, not the outline.
            sphere.center = center;
            sphere.image_center = camera.project(center);
            let truth = camera.project(add(center, scale(n_m, radius)));
            let hl = find_highlight(&camera, &image, h, w, &sphere, &HighlightOptions::default())
                .unwrap();
            // Radial (towards the sphere's image centre) and total errors before and after.
            let d = [
                truth[0] - sphere.image_center[0],
                truth[1] - sphere.image_center[1],
            ];
            let len = d[0].hypot(d[1]);
            let radial = |p: [f64; 2]| ((p[0] - truth[0]) * d[0] + (p[1] - truth[1]) * d[1]) / len;
            let before = radial(hl.pixel) - hl.correction;
            let after = radial(hl.pixel);
            let err = (hl.pixel[0] - truth[0]).hypot(hl.pixel[1] - truth[1]);
            assert!(
                before < -0.05 && after.abs() < 0.2 * before.abs() && err < 0.03,
                "{camera:?}: radial error {before} px before, {after} after the correction; {err} px in all ({hl:?})"
            );
        }
    }
}
