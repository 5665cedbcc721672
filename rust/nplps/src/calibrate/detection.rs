//! Where the spheres are in the image: the regions of a label image or mask
//! ([`sphere_labels`], [`label_components`]), or the bright round blobs of the composite image
//! ([`detect_spheres`]: Otsu's threshold, 8-connected components that do not touch the border,
//! equivalent radius `sqrt(area / pi)` in the expected range and farthest pixel within 1.3
//! equivalent radii of the centroid).

use crate::error::{Error, Result};
use crate::vec3::not_above;

/// 8-connected components of a mask: labels 1..=count (0 outside), numbered in raster order of
/// their first pixel, and the count.
pub(crate) fn label_components(mask: &[bool], height: usize, width: usize) -> (Vec<u32>, usize) {
    let mut labels = vec![0u32; mask.len()];
    let mut count = 0u32;
    let mut stack = Vec::new();
    for start in 0..mask.len() {
        if !mask[start] || labels[start] != 0 {
            continue;
        }
        count += 1;
        labels[start] = count;
        stack.push(start);
        while let Some(p) = stack.pop() {
            let (r, c) = ((p / width) as isize, (p % width) as isize);
            for dr in -1..=1 {
                for dc in -1..=1 {
                    let (rr, cc) = (r + dr, c + dc);
                    if rr < 0 || cc < 0 || rr >= height as isize || cc >= width as isize {
                        continue;
                    }
                    let q = rr as usize * width + cc as usize;
                    if mask[q] && labels[q] == 0 {
                        labels[q] = count;
                        stack.push(q);
                    }
                }
            }
        }
    }
    (labels, count as usize)
}

/// Otsu's threshold of the finite values of an image (256 bins between its min and max).
fn otsu(values: &[f32]) -> Option<f64> {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for &v in values {
        lo = lo.min(v as f64);
        hi = hi.max(v as f64);
    }
    if not_above(hi, lo) {
        return None;
    }
    let bins = 256usize;
    let mut hist = vec![0f64; bins];
    for &v in values {
        let b = (((v as f64 - lo) / (hi - lo)) * (bins as f64 - 1.0)).round() as usize;
        hist[b.min(bins - 1)] += 1.0;
    }
    let total: f64 = hist.iter().sum();
    let sum_all: f64 = hist.iter().enumerate().map(|(i, h)| i as f64 * h).sum();
    let (mut w0, mut sum0, mut best, mut best_t) = (0.0, 0.0, -1.0, 0usize);
    for (t, h) in hist.iter().enumerate() {
        w0 += h;
        sum0 += t as f64 * h;
        let w1 = total - w0;
        if w0 == 0.0 || w1 == 0.0 {
            continue;
        }
        let m0 = sum0 / w0;
        let m1 = (sum_all - sum0) / w1;
        let between = w0 * w1 * (m0 - m1).powi(2);
        if between > best {
            best = between;
            best_t = t;
        }
    }
    Some(lo + (best_t as f64 + 0.5) / (bins as f64 - 1.0) * (hi - lo))
}

/// An image circle: centre (u, v) and radius, pixels.
pub(crate) type ImageCircle = ([f64; 2], f64);

/// Sphere detection: the expected image radius range in pixels and, optionally, how many
/// spheres each image set shows.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Detection {
    /// Smallest and largest image radius of a sphere, pixels.
    pub radius_range: [f64; 2],
    /// How many spheres to keep (the largest ones); None keeps every candidate.
    pub count: Option<usize>,
}

/// Finds spheres in the composite image of a placement (each pixel's brightest value over the
/// lights): Otsu's threshold splits it into bright and
/// dark, and the bright 8-connected components that do not touch the image border, whose
/// equivalent radius `sqrt(area / pi)` lies in the range (+-20 %) and that are round (farthest
/// pixel within 1.3 equivalent radii of the centroid), are the spheres. Returns their rough
/// image circles (centre (u, v), radius) ordered by row then column of the centre, and notes
/// about rejected candidates. (The spheres must stand out brighter than the background in the
/// composite, e.g. shiny balls with a diffuse part on a dark cloth; otherwise give masks.)
pub(crate) fn detect_spheres(
    mean_image: &[f32],
    height: usize,
    width: usize,
    detection: &Detection,
) -> Result<(Vec<ImageCircle>, Vec<String>)> {
    let [rmin, rmax] = detection.radius_range;
    if !(rmin > 0.0 && rmax >= rmin && rmax.is_finite()) {
        return Err(Error::Unusable(format!(
            "the sphere radius range must be 0 < min <= max (pixels), got [{rmin}, {rmax}]"
        )));
    }
    let threshold = otsu(mean_image)
        .ok_or_else(|| Error::Unusable("the images are uniform: no sphere to detect".into()))?;
    let mask: Vec<bool> = mean_image.iter().map(|&v| v as f64 > threshold).collect();
    let (labels, count) = label_components(&mask, height, width);
    let mut stats = vec![(0usize, 0.0f64, 0.0f64, false); count];
    for (p, &l) in labels.iter().enumerate() {
        if l == 0 {
            continue;
        }
        let (r, c) = (p / width, p % width);
        let s = &mut stats[l as usize - 1];
        s.0 += 1;
        s.1 += c as f64;
        s.2 += r as f64;
        if r == 0 || c == 0 || r + 1 == height || c + 1 == width {
            s.3 = true;
        }
    }
    let mut far = vec![0.0f64; count];
    for (p, &l) in labels.iter().enumerate() {
        if l == 0 {
            continue;
        }
        let s = &stats[l as usize - 1];
        let (cu, cv) = (s.1 / s.0 as f64, s.2 / s.0 as f64);
        let d = ((((p % width) as f64) - cu).powi(2) + (((p / width) as f64) - cv).powi(2)).sqrt();
        far[l as usize - 1] = far[l as usize - 1].max(d);
    }
    let mut notes = Vec::new();
    let mut found: Vec<(usize, [f64; 2], f64)> = Vec::new();
    for (i, s) in stats.iter().enumerate() {
        let req = (s.0 as f64 / std::f64::consts::PI).sqrt();
        let centre = [s.1 / s.0 as f64, s.2 / s.0 as f64];
        if req < 0.8 * rmin || req > 1.2 * rmax {
            if req >= 0.5 * rmin {
                notes.push(format!(
                    "a bright region at (u, v) = ({:.0}, {:.0}) with radius {req:.1} px is outside the radius range [{rmin}, {rmax}]",
                    centre[0], centre[1]
                ));
            }
            continue;
        }
        if s.3 {
            notes.push(format!(
                "a candidate sphere at (u, v) = ({:.0}, {:.0}) touches the image border and is skipped",
                centre[0], centre[1]
            ));
            continue;
        }
        if far[i] > 1.3 * req + 1.5 {
            notes.push(format!(
                "a candidate at (u, v) = ({:.0}, {:.0}) is not round (farthest pixel {:.1} px, equivalent radius {req:.1} px)",
                centre[0], centre[1], far[i]
            ));
            continue;
        }
        found.push((s.0, centre, req));
    }
    found.sort_by_key(|f| std::cmp::Reverse(f.0));
    if let Some(n) = detection.count {
        if found.len() < n {
            return Err(Error::Unusable(format!(
                "found {} sphere(s) but {n} were expected (radius range [{rmin}, {rmax}] px){}",
                found.len(),
                if notes.is_empty() {
                    String::new()
                } else {
                    format!("; {}", notes.join("; "))
                }
            )));
        }
        found.truncate(n);
    }
    if found.is_empty() {
        return Err(Error::Unusable(format!(
            "no sphere found in the radius range [{rmin}, {rmax}] px (the spheres must be brighter than the background under the lights; otherwise give masks){}",
            if notes.is_empty() {
                String::new()
            } else {
                format!("; {}", notes.join("; "))
            }
        )));
    }
    let mut circles: Vec<([f64; 2], f64)> = found.into_iter().map(|(_, c, r)| (c, r)).collect();
    circles.sort_by(|a, b| {
        (a.0[1].round(), a.0[0])
            .partial_cmp(&(b.0[1].round(), b.0[0]))
            .unwrap_or(std::cmp::Ordering::Equal)
    });
    Ok((circles, notes))
}

/// The label image's spheres: labels as given, or the components of a binary mask.
pub(super) fn sphere_labels(
    labels: &[u32],
    height: usize,
    width: usize,
    min_component: usize,
    placement: usize,
    warnings: &mut Vec<String>,
) -> (Vec<u32>, Vec<u32>) {
    let binary = labels.iter().all(|&l| l <= 1);
    let labels: Vec<u32> = if binary {
        let mask: Vec<bool> = labels.iter().map(|&l| l != 0).collect();
        label_components(&mask, height, width).0
    } else {
        labels.to_vec()
    };
    let mut counts = std::collections::BTreeMap::<u32, usize>::new();
    for &l in &labels {
        if l != 0 {
            *counts.entry(l).or_default() += 1;
        }
    }
    let mut keep = Vec::new();
    for (l, n) in counts {
        if n < min_component {
            warnings.push(format!(
                "placement {placement}: a mask region of {n} pixel(s) is too small for a sphere and is ignored"
            ));
        } else {
            keep.push(l);
        }
    }
    (labels, keep)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn components_are_8_connected_and_numbered_in_raster_order() {
        let (h, w) = (40, 60);
        let mut mask = vec![false; h * w];
        for r in 5..15 {
            for c in 5..15 {
                mask[r * w + c] = true;
                mask[(r + 20) * w + c + 30] = true;
            }
        }
        let (labels, n) = label_components(&mask, h, w);
        assert_eq!(n, 2);
        assert_eq!(labels[5 * w + 5], 1);
        assert_eq!(labels[25 * w + 35], 2);
    }
}
