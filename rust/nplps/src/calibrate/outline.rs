//! The outline points of a sphere's image, in pixels (u, v) (pixel (r, c) has its centre at
//! (u, v) = (c, r)).
//!
//! - From a mask ([`mask_boundary`]): the midpoints of the cracks between an inside and an
//!   outside 4-neighbour. For a mask holding the pixels whose centre sees the sphere the true
//!   outline crosses each such crack at a uniformly distributed place: the midpoints are
//!   unbiased to within a small fraction of a pixel on average. [`mask_edge_pixels`] gives the
//!   pixel centres on both sides, for the separating fits of [`super::fits`].
//! - From the images ([`radial_edges`], [`image_outline`]): in the composite of the k images
//!   (each pixel's brightest value), along rays from a first centre, the crossing of the half
//!   level between the outside and the inside (extrapolated linearly to the edge), sub-pixel by
//!   linear interpolation of the bilinearly interpolated profile.

use super::fits::fit_circle;
use crate::error::Result;

/// Sub-pixel boundary points (u, v) of the pixels labelled `label`: the midpoint of every crack
/// between 4-neighbours of which exactly one has the label (pixels beyond the image border are
/// unknown and give no point). For a mask holding the pixels whose centre sees the object the
/// true outline crosses each such segment, at a uniformly distributed place: the midpoints are
/// unbiased to within a small fraction of a pixel on average.
pub(crate) fn mask_boundary(
    labels: &[u32],
    height: usize,
    width: usize,
    label: u32,
) -> Vec<[f64; 2]> {
    let mut points = Vec::new();
    for r in 0..height {
        for c in 0..width {
            let here = labels[r * width + c] == label;
            if c + 1 < width && here != (labels[r * width + c + 1] == label) {
                points.push([c as f64 + 0.5, r as f64]);
            }
            if r + 1 < height && here != (labels[(r + 1) * width + c] == label) {
                points.push([c as f64, r as f64 + 0.5]);
            }
        }
    }
    points
}

/// Bilinear interpolation of an H x W image at (u, v); None outside the pixel centres' hull.
fn bilinear(image: &[f32], height: usize, width: usize, u: f64, v: f64) -> Option<f64> {
    if !(u >= 0.0 && v >= 0.0 && u <= (width - 1) as f64 && v <= (height - 1) as f64) {
        return None;
    }
    let (c0, r0) = (
        (u.floor() as usize).min(width - 2),
        (v.floor() as usize).min(height - 2),
    );
    let (fu, fv) = (u - c0 as f64, v - r0 as f64);
    let at = |r: usize, c: usize| image[r * width + c] as f64;
    Some(
        (1.0 - fv) * ((1.0 - fu) * at(r0, c0) + fu * at(r0, c0 + 1))
            + fv * ((1.0 - fu) * at(r0 + 1, c0) + fu * at(r0 + 1, c0 + 1)),
    )
}

/// Sub-pixel outline points (u, v) of a roughly circular blob in `image` around the image
/// circle (`center`, `radius`, pixels): along `max(90, 2 pi radius)` rays from the centre, the
/// profile (bilinear, steps of 1/8 pixel) within `radius +- window` gives a first edge at its
/// steepest descent (the blob must be brighter or darker than its surroundings all around; the
/// polarity is that of the whole profile); the edge is then the crossing, nearest to it, of the
/// level halfway between the profile 2 pixels outside and the inside profile (1.5 and 2.5
/// pixels inside) extrapolated linearly to the edge, by linear interpolation.
/// Rays with a contrast below `min_contrast` are skipped.
pub(crate) fn radial_edges(
    image: &[f32],
    height: usize,
    width: usize,
    center: [f64; 2],
    radius: f64,
    window: f64,
    min_contrast: f64,
) -> Vec<[f64; 2]> {
    let n_rays = ((2.0 * std::f64::consts::PI * radius).ceil() as usize).max(90);
    let step = 0.125;
    let lo = (radius - window).max(1.0);
    let hi = radius + window;
    let n_samples = ((hi - lo) / step).floor() as usize + 1;
    let mut points = Vec::with_capacity(n_rays);
    let mut profile = Vec::with_capacity(n_samples);
    for j in 0..n_rays {
        let a = 2.0 * std::f64::consts::PI * j as f64 / n_rays as f64;
        let (ca, sa) = (a.cos(), a.sin());
        let sample = |rho: f64| {
            bilinear(
                image,
                height,
                width,
                center[0] + rho * ca,
                center[1] + rho * sa,
            )
        };
        profile.clear();
        let mut complete = true;
        for s in 0..n_samples {
            match sample(lo + s as f64 * step) {
                Some(v) => profile.push(v),
                None => {
                    complete = false;
                    break;
                }
            }
        }
        if !complete || profile.len() < 16 {
            continue;
        }
        let first = profile[..4].iter().sum::<f64>() / 4.0;
        let last = profile[profile.len() - 4..].iter().sum::<f64>() / 4.0;
        let sign = if first >= last { 1.0 } else { -1.0 };
        if (first - last).abs() < min_contrast {
            continue;
        }
        // Steepest descent (inside to outside) over a one-pixel baseline.
        let span = (1.0 / step) as usize;
        let mut best = (0usize, f64::NEG_INFINITY);
        for s in 0..profile.len() - span {
            let drop = sign * (profile[s] - profile[s + span]);
            if drop > best.1 {
                best = (s, drop);
            }
        }
        let rough = lo + (best.0 as f64 + 0.5 * span as f64) * step;
        // The inside level: the profile 1.5 and 2.5 pixels inside (clear of the edge pixel),
        // extrapolated linearly to the edge (shading often falls towards the limb; the level
        // inside would put the half level too high and the edge too far inside).
        let (Some(i1), Some(i2), Some(outside)) = (
            sample(rough - 1.5),
            sample(rough - 2.5),
            sample(rough + 2.0),
        ) else {
            continue;
        };
        let inside = i1 + 1.5 * (i1 - i2);
        if sign * (inside - outside) < min_contrast {
            continue;
        }
        let level = 0.5 * (inside + outside);
        // The crossing of `level` nearest to the rough edge.
        let mut found: Option<f64> = None;
        for s in 0..profile.len() - 1 {
            let (a0, a1) = (profile[s] - level, profile[s + 1] - level);
            if (a0 > 0.0) != (a1 > 0.0) || a0 == 0.0 {
                let t = if a0 == a1 { 0.0 } else { a0 / (a0 - a1) };
                let rho = lo + (s as f64 + t) * step;
                if found.is_none_or(|f| (rho - rough).abs() < (f - rough).abs()) {
                    found = Some(rho);
                }
            }
        }
        if let Some(rho) = found {
            if (rho - rough).abs() <= 1.5 {
                points.push([center[0] + rho * ca, center[1] + rho * sa]);
            }
        }
    }
    points
}

/// The centres of the pixels just inside and just outside the region labelled `label` (those
/// with a 4-neighbour on the other side), (u, v).
pub(crate) fn mask_edge_pixels(
    labels: &[u32],
    height: usize,
    width: usize,
    label: u32,
) -> (Vec<[f64; 2]>, Vec<[f64; 2]>) {
    let (mut inside, mut outside) = (Vec::new(), Vec::new());
    for r in 0..height {
        for c in 0..width {
            let here = labels[r * width + c] == label;
            let differs = |rr: usize, cc: usize| (labels[rr * width + cc] == label) != here;
            let edge = (c > 0 && differs(r, c - 1))
                || (c + 1 < width && differs(r, c + 1))
                || (r > 0 && differs(r - 1, c))
                || (r + 1 < height && differs(r + 1, c));
            if edge {
                if here {
                    inside.push([c as f64, r as f64]);
                } else {
                    outside.push([c as f64, r as f64]);
                }
            }
        }
    }
    (inside, outside)
}

/// The outline of a sphere in the composite image from a rough image circle: radial edges in a
/// window of a quarter radius (at least 4 pixels), a circle fit, and radial edges again in a
/// window of 8 % of the radius (at least 3 pixels) about that circle.
pub(super) fn image_outline(
    composite: &[f32],
    height: usize,
    width: usize,
    center: [f64; 2],
    radius: f64,
) -> Result<Vec<[f64; 2]>> {
    let floor = contrast_floor(composite);
    let first = radial_edges(
        composite,
        height,
        width,
        center,
        radius,
        (0.25 * radius).max(4.0),
        floor,
    );
    let circle = fit_circle(&first)?;
    Ok(radial_edges(
        composite,
        height,
        width,
        circle.center,
        circle.radius,
        (0.08 * circle.radius).max(3.0),
        floor,
    ))
}

/// Smallest edge contrast taken as an outline: 5 % of the image's range.
fn contrast_floor(image: &[f32]) -> f64 {
    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
    for &v in image {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    0.05 * (hi - lo).max(0.0) as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calibrate::detection::{detect_spheres, Detection};
    use crate::calibrate::fits::fit_circle;
    use crate::calibrate::testing::disc;

    #[test]
    fn mask_outline_gives_sub_pixel_circles() {
        // Random centres and radii: the crack midpoints give centre and radius to ~0.02 px.
        let mut worst = [0.0f64; 2];
        for t in 0..20 {
            let c = [50.0 + 0.37 * t as f64, 48.0 + 0.61 * t as f64 % 1.0];
            let r = 30.0 + 0.73 * t as f64;
            let labels = disc(110, 110, c, r);
            let fit = fit_circle(&mask_boundary(&labels, 110, 110, 1)).unwrap();
            worst[0] = worst[0].max((fit.center[0] - c[0]).hypot(fit.center[1] - c[1]));
            worst[1] = worst[1].max((fit.radius - r).abs());
        }
        assert!(
            worst[0] < 0.1 && worst[1] < 0.06,
            "centre, radius errors {worst:?} px"
        );
    }

    #[test]
    fn radial_edges_follow_an_antialiased_disc() {
        let (h, w) = (120, 120);
        let (c, r) = ([60.3, 58.8], 40.0);
        // 8 x 8 supersampled disc, inside 0.8, outside 0.1.
        let image: Vec<f32> = (0..h * w)
            .map(|p| {
                let (u, v) = ((p % w) as f64, (p / w) as f64);
                let mut cover = 0.0;
                for i in 0..8 {
                    for j in 0..8 {
                        let (du, dv) = ((i as f64 + 0.5) / 8.0 - 0.5, (j as f64 + 0.5) / 8.0 - 0.5);
                        if (u + du - c[0]).powi(2) + (v + dv - c[1]).powi(2) <= r * r {
                            cover += 1.0 / 64.0;
                        }
                    }
                }
                (0.1 + 0.7 * cover) as f32
            })
            .collect();
        let pts = radial_edges(&image, h, w, [61.0, 58.0], 39.0, 5.0, 0.05);
        let fit = fit_circle(&pts).unwrap();
        assert!(
            (fit.center[0] - c[0]).abs() < 0.02 && (fit.center[1] - c[1]).abs() < 0.02,
            "{fit:?}"
        );
        assert!((fit.radius - r).abs() < 0.03, "{fit:?}");
        let (circles, _) = detect_spheres(
            &image,
            h,
            w,
            &Detection {
                radius_range: [30.0, 50.0],
                count: Some(1),
            },
        )
        .unwrap();
        assert!((circles[0].1 - r).abs() < 1.0);
        assert!(detect_spheres(
            &image,
            h,
            w,
            &Detection {
                radius_range: [5.0, 10.0],
                count: None
            }
        )
        .is_err());
    }
}
