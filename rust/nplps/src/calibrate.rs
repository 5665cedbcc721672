//! Light calibration: light positions from the highlights on mirror (or shiny) spheres, and light
//! intensities from images of a flat diffuse board.
//!
//! # Sphere calibration (the paper's section 5)
//!
//! Every light is photographed once per *placement*: an image set of k images (one per light, in
//! the order of the rig) of one or more spheres of known radius `R`. The camera is fixed, so all
//! placements share the camera frame (OpenCV: x right, y down, z forward; pixel (r, c) has its
//! centre at (u, v) = (c, r)).
//!
//! 1. **The sphere in the image.** Boundary points come from a mask (`mask_boundary`: the
//!    midpoints of the cracks between an inside and an outside pixel, unbiased for a mask that
//!    holds the pixels whose centre sees the sphere) or from the images (`radial_edges` in the
//!    composite of the k images, each pixel's brightest value: the crossing of the half level
//!    between the outside and the inside, extrapolated to the edge, along rays from a first
//!    centre, sub-pixel by linear interpolation; `detect_spheres` finds the first circles).
//! 2. **The sphere in 3-D.**
//!    *Orthographic camera*: the boundary points, in scene units (x = ox + (u + 1/2) w,
//!    y = oy + (v + 1/2) h), are fitted with a circle (`fit_circle`: algebraic fit, then
//!    Gauss–Newton on the geometric distances with Tukey reweighting); its centre is the sphere
//!    centre's (x, y); z is given (the depth of the sphere centre: for a ball lying on a board at
//!    depth `z_b`, `z_b - R`; for a hemisphere lying flat on it, `z_b`). The fitted radius checks
//!    the pixel size (a warning when it differs from `R` by more than 3 %).
//!    *Pinhole camera*: the image of a sphere is an ellipse, the section of the tangent cone from
//!    the camera centre. Each boundary point back-projects (after undistortion) to a unit ray
//!    `b_i` on that cone: `b_i . a = cos(theta)` with `a` the unit axis, which passes through the
//!    sphere centre, and `sin(theta) = R / D`, `D` the distance of the centre. `fit_cone` solves
//!    `b_i . m = 1` linearly (`m = a / cos(theta)`), then refines `(a, cos(theta))` as the plane
//!    `b . a = c` closest to the points `b_i` (the smallest eigenvector of their covariance; the
//!    plane distance is `sin(theta)` times the angular distance to the cone, to first order), with
//!    Tukey reweighting. The centre is `C = a R / sin(theta)`, exact at any position in the image.
//!    A given centre depth, if any, replaces `D` (`C = a z / a_z`).
//! 3. **The highlight** of light i on a sphere ([`find_highlight`]): inside the sphere's image
//!    (pixels whose ray passes within 0.97 `R` of the centre), the brightest pixel and the
//!    8-connected blob above the midpoint between it and the sphere's median; a plane fitted to
//!    a ring 2-4 pixels around the blob is the local background (the diffuse shading). The
//!    position is the mean of the centroids of the regions where the bilinear interpolant
//!    exceeds the background by 1/4, 1/2 and 3/4 of the peak's excess (8 x 8 samples per
//!    pixel): sub-pixel also when the blob is saturated. A blob that is not compact (more than
//!    5 % of the sphere's image), too faint, or clipped by the limb is rejected. Each level
//!    region is a small circle of normals about the mirror normal, which the sphere's curvature
//!    and foreshortening shift towards the sphere's image centre by `A tan(t) / (2 pi R_px)`
//!    (area `A`, tilt `t` of the normal from the view, image radius `R_px`);
//!    `correct_highlight` moves it back.
//! 4. **The reflected ray.** The viewing ray `v` through the highlight meets the sphere at `X`
//!    (nearest intersection) with outward normal `n = (X - C) / R`; the light lies on the mirror
//!    ray from `X` along `r = v - 2 (v . n) n`.
//! 5. **The light** (`locate_light`): the least-squares point closest to all its rays,
//!    `p = argmin sum_i |(I - r_i r_i^T)(p - X_i)|^2` (for two rays, the midpoint of their
//!    shortest connecting segment, as in the paper). When the rays agree within `parallel_tol`
//!    (RMS angle about their mean direction) the light is too far to be located and is reported
//!    as a directional light along the mean direction; likewise with a single ray (with a
//!    warning), or when the least-squares point lies behind a sphere (diverging rays).
//! 6. **Joint refinement** (`refine_spheres`): a binary mask places a sphere's centre only to
//!    a few hundredths of a pixel, which turns all its rays by ~0.1 degree; the sphere centres
//!    and the lights are therefore refined together by least squares on the outlines and on the
//!    highlights of every light seen on two or more spheres (a small bundle adjustment), and
//!    step 5 is repeated with the refined spheres.
//!
//! # Intensity calibration
//!
//! Given the light positions (and LED axes and anisotropy, if known), images of a flat diffuse
//! board on the plane `n . X = d` (camera frame) determine each light's intensity: every masked
//! pixel's ray meets the plane at `X`, and the image model is
//! `I_i(X) = rho(X) Phi_i max(0, n . beta_i(X))` ([`Light::beta`]). With a uniform board
//! (`rho` constant) `Phi_i rho` is a one-parameter linear least-squares fit per light and
//! channel; with [`BoardAlbedo::PerPixel`] the board's albedo (which also absorbs vignetting) is
//! estimated per pixel by alternating least squares (rank-one factorisation). `rho` and the
//! exposure are not separable from `Phi`: the intensities are relative, scaled to a geometric
//! mean of 1 over all lights and channels. Optionally each LED's anisotropy `mu` and principal
//! direction are fitted too, by Levenberg–Marquardt with the intensities eliminated (variable
//! projection).

use nalgebra::{Matrix3, SymmetricEigen, Vector3, Vector4};

use crate::error::{Error, Result};
use crate::rig::{distort, Camera, Light, Rig};
use crate::vec3::{add, angle, cross, dot, norm, not_above, not_at_least, scale, sub, unit};

// -------------------------------------------------------------------------------------------
// Small numeric helpers (the 3-vector ones are in `crate::vec3`)
// -------------------------------------------------------------------------------------------

/// Tukey's biweight for the residual `r` at scale `c` (0 beyond `c`).
#[inline]
fn tukey(r: f64, c: f64) -> f64 {
    let t = r / c;
    if t.abs() >= 1.0 {
        0.0
    } else {
        (1.0 - t * t).powi(2)
    }
}

/// Median of a slice (reorders it); NaN for an empty slice.
fn median(values: &mut [f64]) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    let mid = values.len() / 2;
    values.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
    values[mid]
}

/// Robust scale of residuals: 1.4826 times their median absolute value, at least `floor`.
fn robust_scale(residuals: &[f64], floor: f64) -> f64 {
    let mut abs: Vec<f64> = residuals.iter().map(|r| r.abs()).collect();
    (1.4826 * median(&mut abs)).max(floor)
}

// -------------------------------------------------------------------------------------------
// Camera rays
// -------------------------------------------------------------------------------------------

/// A ray: origin and unit direction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ray {
    /// Origin (camera frame).
    pub origin: [f64; 3],
    /// Unit direction.
    pub direction: [f64; 3],
}

impl Ray {
    /// The point at parameter `t`.
    pub fn at(&self, t: f64) -> [f64; 3] {
        add(self.origin, scale(self.direction, t))
    }

    /// Distance of the point `p` from the (infinite) line of the ray.
    pub fn distance_to(&self, p: [f64; 3]) -> f64 {
        let a = sub(p, self.origin);
        norm(sub(a, scale(self.direction, dot(a, self.direction))))
    }
}

/// The viewing ray of the image point (u, v) (pixel (r, c) has its centre at (u, v) = (c, r)).
/// Orthographic: from (ox + (u + 1/2) w, oy + (v + 1/2) h, 0) along +z. Pinhole: from the
/// camera centre through the undistorted point.
pub(crate) fn pixel_ray(camera: &Camera, uv: [f64; 2]) -> Ray {
    match *camera {
        Camera::Orthographic { pixel_size, origin } => Ray {
            origin: [
                origin[0] + (uv[0] + 0.5) * pixel_size[0],
                origin[1] + (uv[1] + 0.5) * pixel_size[1],
                0.0,
            ],
            direction: [0.0, 0.0, 1.0],
        },
        Camera::Pinhole { k, distortion } => {
            let yd = (uv[1] - k[1][2]) / k[1][1];
            let xd = (uv[0] - k[0][2] - k[0][1] * yd) / k[0][0];
            let [x, y] = crate::rig::undistort([xd, yd], distortion);
            Ray {
                origin: [0.0; 3],
                direction: unit([x, y, 1.0]),
            }
        }
    }
}

/// The image point (u, v) of the camera-frame point `p` (pinhole: NaN behind the camera).
pub(crate) fn project(camera: &Camera, p: [f64; 3]) -> [f64; 2] {
    match *camera {
        Camera::Orthographic { pixel_size, origin } => [
            (p[0] - origin[0]) / pixel_size[0] - 0.5,
            (p[1] - origin[1]) / pixel_size[1] - 0.5,
        ],
        Camera::Pinhole { k, distortion } => {
            if p[2] <= 0.0 {
                return [f64::NAN; 2];
            }
            let [x, y] = distort([p[0] / p[2], p[1] / p[2]], distortion);
            [k[0][0] * x + k[0][1] * y + k[0][2], k[1][1] * y + k[1][2]]
        }
    }
}

/// Nearest intersection (t > 0) of a ray with the sphere of centre `c` and radius `r`.
pub(crate) fn ray_sphere(ray: &Ray, c: [f64; 3], r: f64) -> Option<[f64; 3]> {
    let oc = sub(ray.origin, c);
    let b = dot(oc, ray.direction);
    let disc = b * b - (dot(oc, oc) - r * r);
    if disc < 0.0 {
        return None;
    }
    let s = disc.sqrt();
    let t = if -b - s > 0.0 { -b - s } else { -b + s };
    (t > 0.0).then(|| ray.at(t))
}

/// Mirror reflection of the direction `v` (towards the surface) about the unit normal `n`:
/// `v - 2 (v . n) n`.
#[inline]
pub(crate) fn reflect(v: [f64; 3], n: [f64; 3]) -> [f64; 3] {
    sub(v, scale(n, 2.0 * dot(v, n)))
}

// -------------------------------------------------------------------------------------------
// Circle and cone fits
// -------------------------------------------------------------------------------------------

/// A circle fitted to 2-D points.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Circle {
    /// Centre (x, y).
    pub center: [f64; 2],
    /// Radius.
    pub radius: f64,
    /// RMS geometric distance of the inliers from the circle.
    pub rms: f64,
    /// Points kept by the robust weights (non-zero Tukey weight).
    pub inliers: usize,
}

/// Fits a circle to 2-D points: the algebraic (Kåsa) fit `x^2 + y^2 + D x + E y + F = 0` on
/// centred and scaled coordinates, then Gauss–Newton on the geometric distances
/// `|p_i - c| - r`, reweighted with Tukey's biweight at 4.685 robust standard deviations so that
/// a few wrong boundary points (an occluded or touching part of the outline) do not bend the
/// circle. Needs at least 5 points that are not on a line.
pub(crate) fn fit_circle(points: &[[f64; 2]]) -> Result<Circle> {
    let n = points.len();
    if n < 5 {
        return Err(Error::Unusable(format!(
            "a circle fit needs at least 5 boundary points, got {n}"
        )));
    }
    if points.iter().flatten().any(|v| !v.is_finite()) {
        return Err(Error::Unusable("boundary points must be finite".into()));
    }
    let mean = [
        points.iter().map(|p| p[0]).sum::<f64>() / n as f64,
        points.iter().map(|p| p[1]).sum::<f64>() / n as f64,
    ];
    let spread = (points
        .iter()
        .map(|p| (p[0] - mean[0]).powi(2) + (p[1] - mean[1]).powi(2))
        .sum::<f64>()
        / n as f64)
        .sqrt();
    if not_above(spread, 0.0) {
        return Err(Error::Unusable(
            "the boundary points of a sphere all coincide".into(),
        ));
    }
    // Algebraic fit in normalised coordinates q = (p - mean) / spread, reweighted by the
    // geometric residuals (Tukey) so that wrong points do not spoil the start.
    let mut weights = vec![1.0; n];
    let mut residuals = vec![0.0; n];
    let mut c = [0.0; 2];
    let mut r = 0.0;
    for round in 0..8 {
        let mut ata = Matrix3::<f64>::zeros();
        let mut atb = Vector3::<f64>::zeros();
        for (p, w) in points.iter().zip(&weights) {
            let x = (p[0] - mean[0]) / spread;
            let y = (p[1] - mean[1]) / spread;
            let row = Vector3::new(x, y, 1.0);
            ata += row * row.transpose() * *w;
            atb -= row * ((x * x + y * y) * *w);
        }
        let sol = ata
            .cholesky()
            .map(|c| c.solve(&atb))
            .filter(|s| s.iter().all(|v| v.is_finite()))
            .ok_or_else(|| {
                Error::Unusable("the boundary points lie on a line: no circle".into())
            })?;
        let (cx, cy) = (-0.5 * sol[0], -0.5 * sol[1]);
        let r2 = cx * cx + cy * cy - sol[2];
        if not_above(r2, 0.0) {
            return Err(Error::Unusable(
                "the boundary points do not outline a circle".into(),
            ));
        }
        c = [mean[0] + cx * spread, mean[1] + cy * spread];
        r = r2.sqrt() * spread;
        for (res, p) in residuals.iter_mut().zip(points) {
            *res = ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2)).sqrt() - r;
        }
        if round == 7 {
            break;
        }
        let s = robust_scale(&residuals, 1e-6 * r);
        for (w, res) in weights.iter_mut().zip(&residuals) {
            *w = tukey(*res, 4.685 * s);
        }
    }
    // Geometric refinement (Gauss-Newton, IRLS with Tukey weights).
    for iteration in 0..30 {
        for (res, p) in residuals.iter_mut().zip(points) {
            *res = ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2)).sqrt() - r;
        }
        let s = robust_scale(&residuals, 1e-6 * r);
        for (w, res) in weights.iter_mut().zip(&residuals) {
            *w = tukey(*res, 4.685 * s);
        }
        let mut jtj = Matrix3::<f64>::zeros();
        let mut jtr = Vector3::<f64>::zeros();
        for ((p, res), w) in points.iter().zip(&residuals).zip(&weights) {
            if *w == 0.0 {
                continue;
            }
            let d = ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2)).sqrt();
            if d == 0.0 {
                continue;
            }
            let j = Vector3::new(-(p[0] - c[0]) / d, -(p[1] - c[1]) / d, -1.0);
            jtj += j * j.transpose() * *w;
            jtr += j * (*res * *w);
        }
        let Some(step) = jtj.cholesky().map(|ch| ch.solve(&jtr)) else {
            break;
        };
        c = [c[0] - step[0], c[1] - step[1]];
        r -= step[2];
        if not_above(r, 0.0) || !c.iter().all(|v| v.is_finite()) {
            return Err(Error::Unusable(
                "the circle fit to the sphere's boundary diverged".into(),
            ));
        }
        if iteration >= 4 && step.norm() < 1e-12 * r {
            break;
        }
    }
    let (mut sum, mut count) = (0.0, 0usize);
    for (p, w) in points.iter().zip(&weights) {
        if *w > 0.0 {
            let d = ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2)).sqrt() - r;
            sum += d * d;
            count += 1;
        }
    }
    Ok(Circle {
        center: c,
        radius: r,
        rms: (sum / count.max(1) as f64).sqrt(),
        inliers: count,
    })
}

/// Fits the centre of a circle of known `radius` to 2-D points from `start`: Gauss–Newton on
/// the geometric distances `|p_i - c| - radius` with Tukey reweighting (4.685 robust standard
/// deviations). None when the fit fails.
pub(crate) fn fit_circle_radius(
    points: &[[f64; 2]],
    start: [f64; 2],
    radius: f64,
) -> Option<Circle> {
    if points.len() < 3 || not_above(radius, 0.0) {
        return None;
    }
    let mut c = start;
    let mut residuals = vec![0.0; points.len()];
    let mut weights = vec![1.0; points.len()];
    for _ in 0..50 {
        for (res, p) in residuals.iter_mut().zip(points) {
            *res = (p[0] - c[0]).hypot(p[1] - c[1]) - radius;
        }
        let s = robust_scale(&residuals, 1e-6 * radius);
        for (w, res) in weights.iter_mut().zip(&residuals) {
            *w = tukey(*res, 4.685 * s);
        }
        let (mut a, mut b) = (
            nalgebra::Matrix2::<f64>::zeros(),
            nalgebra::Vector2::<f64>::zeros(),
        );
        for ((p, res), w) in points.iter().zip(&residuals).zip(&weights) {
            let d = (p[0] - c[0]).hypot(p[1] - c[1]);
            if *w == 0.0 || d == 0.0 {
                continue;
            }
            let j = nalgebra::Vector2::new(-(p[0] - c[0]) / d, -(p[1] - c[1]) / d);
            a += j * j.transpose() * *w;
            b += j * (*res * *w);
        }
        let step = a.cholesky()?.solve(&b);
        c = [c[0] - step[0], c[1] - step[1]];
        if !c.iter().all(|v| v.is_finite()) {
            return None;
        }
        if step.norm() < 1e-12 * radius {
            break;
        }
    }
    let (mut sum, mut count) = (0.0, 0usize);
    for (p, w) in points.iter().zip(&weights) {
        if *w > 0.0 {
            sum += ((p[0] - c[0]).hypot(p[1] - c[1]) - radius).powi(2);
            count += 1;
        }
    }
    Some(Circle {
        center: c,
        radius,
        rms: (sum / count.max(1) as f64).sqrt(),
        inliers: count,
    })
}

/// A circular cone with apex at the camera centre.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Cone {
    /// Unit axis (towards the scene, z > 0).
    pub axis: [f64; 3],
    /// Half-angle in radians.
    pub half_angle: f64,
    /// RMS angular distance (radians) of the inlier rays from the cone.
    pub rms: f64,
    /// Rays kept by the robust weights.
    pub inliers: usize,
}

/// Fits the tangent cone of a sphere to unit rays through its outline (see the
/// [module documentation](self)): the linear fit `b_i . m = 1`, then the plane `b . a = c`
/// (|a| = 1) closest to the points `b_i` on the unit sphere, with Tukey reweighting of the
/// angular residuals. Needs at least 5 rays that do not lie on a great circle.
pub(crate) fn fit_cone(rays: &[[f64; 3]]) -> Result<Cone> {
    let n = rays.len();
    if n < 5 {
        return Err(Error::Unusable(format!(
            "a cone fit needs at least 5 outline rays, got {n}"
        )));
    }
    if rays.iter().flatten().any(|v| !v.is_finite()) {
        return Err(Error::Unusable("outline rays must be finite".into()));
    }
    let rays: Vec<[f64; 3]> = rays.iter().map(|&b| unit(b)).collect();
    // Linear fit: b . m = 1.
    let mut ata = Matrix3::<f64>::zeros();
    let mut atb = Vector3::<f64>::zeros();
    for b in &rays {
        let v = Vector3::new(b[0], b[1], b[2]);
        ata += v * v.transpose();
        atb += v;
    }
    let m = ata
        .cholesky()
        .map(|c| c.solve(&atb))
        .filter(|m| m.iter().all(|v| v.is_finite()) && m.norm() > 1.0)
        .ok_or_else(|| {
            Error::Unusable("the outline rays do not form a cone (degenerate outline)".into())
        })?;
    let mut axis = unit([m[0], m[1], m[2]]);
    let mut cos_t = 1.0 / m.norm();
    let mut weights = vec![1.0; n];
    let mut residuals = vec![0.0; n];
    for iteration in 0..30 {
        let half = cos_t.clamp(-1.0, 1.0).acos();
        for (res, b) in residuals.iter_mut().zip(&rays) {
            *res = angle(*b, axis) - half;
        }
        if iteration >= 1 {
            let s = robust_scale(&residuals, 1e-9 * half.max(1e-9));
            for (w, res) in weights.iter_mut().zip(&residuals) {
                *w = tukey(*res, 4.685 * s);
            }
        }
        // Weighted plane fit to the points b_i.
        let wsum: f64 = weights.iter().sum();
        if not_above(wsum, 0.0) {
            return Err(Error::Unusable(
                "no consistent outline rays for the cone fit".into(),
            ));
        }
        let mut mean = [0.0; 3];
        for (b, w) in rays.iter().zip(&weights) {
            mean = add(mean, scale(*b, *w / wsum));
        }
        let mut cov = Matrix3::<f64>::zeros();
        for (b, w) in rays.iter().zip(&weights) {
            let d = sub(*b, mean);
            let v = Vector3::new(d[0], d[1], d[2]);
            cov += v * v.transpose() * *w;
        }
        let eig = SymmetricEigen::new(cov);
        let mut order = [0usize, 1, 2];
        order.sort_by(|&i, &j| eig.eigenvalues[i].total_cmp(&eig.eigenvalues[j]));
        if not_above(eig.eigenvalues[order[1]], 1e-6 * eig.eigenvalues[order[2]]) {
            return Err(Error::Unusable(
                "the outline rays lie on a line: no cone".into(),
            ));
        }
        let e = eig.eigenvectors.column(order[0]);
        let mut new_axis = unit([e[0], e[1], e[2]]);
        if dot(new_axis, axis) < 0.0 {
            new_axis = scale(new_axis, -1.0);
        }
        let change = angle(new_axis, axis);
        axis = new_axis;
        cos_t = dot(mean, axis);
        if iteration >= 3 && change < 1e-14 {
            break;
        }
    }
    if !(cos_t > 0.0 && cos_t < 1.0) || axis[2] <= 0.0 {
        return Err(Error::Unusable(
            "the outline does not describe a sphere in front of the camera".into(),
        ));
    }
    let half = cos_t.acos();
    let (mut sum, mut count) = (0.0, 0usize);
    for (b, w) in rays.iter().zip(&weights) {
        if *w > 0.0 {
            sum += (angle(*b, axis) - half).powi(2);
            count += 1;
        }
    }
    Ok(Cone {
        axis,
        half_angle: half,
        rms: (sum / count.max(1) as f64).sqrt(),
        inliers: count,
    })
}

// -------------------------------------------------------------------------------------------
// Masks, components, detection and edges
// -------------------------------------------------------------------------------------------

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

// -------------------------------------------------------------------------------------------
// Spheres in 3-D
// -------------------------------------------------------------------------------------------

/// A sphere located in the camera frame.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct Sphere {
    /// Index of the placement (image set) that shows it.
    pub placement: usize,
    /// Centre in the camera frame.
    pub center: [f64; 3],
    /// Radius (scene units, as given).
    pub radius: f64,
    /// Image of the centre (u, v).
    pub image_center: [f64; 2],
    /// Mean image radius, pixels.
    pub image_radius: f64,
    /// RMS distance of the outline points from the fitted outline, pixels.
    pub fit_rms: f64,
    /// Outline points used (inliers) and found.
    pub outline_points: [usize; 2],
    /// Orthographic: fitted radius / given radius (checks the pixel size). Pinhole with a given
    /// centre depth: distance from the outline / distance from the given depth. Otherwise 1.
    pub scale_check: f64,
    /// How far the joint refinement moved the centre from the outline's (scene units; 0 without
    /// refinement).
    pub shift: f64,
    /// Precision of the outline's centre (pixels per coordinate) that the joint refinement
    /// assumes: `MASK_DIGITAL_SIGMA` for a separating fit to a mask, `OUTLINE_FIT_SIGMA`
    /// otherwise.
    pub outline_sigma: f64,
}

/// The sphere of radius `radius` whose outline passes through the image points `outline`
/// (pixels). Orthographic cameras need the depth of the centre (`center_depth`); for pinhole
/// cameras it is optional and, when given, replaces the distance derived from the outline.
pub(crate) fn locate_sphere(
    camera: &Camera,
    outline: &[[f64; 2]],
    radius: f64,
    center_depth: Option<f64>,
) -> Result<Sphere> {
    if !(radius > 0.0 && radius.is_finite()) {
        return Err(Error::Unusable(format!(
            "the sphere radius must be positive and finite, got {radius}"
        )));
    }
    if let Some(z) = center_depth {
        if !(z.is_finite() && z > 0.0) {
            return Err(Error::Unusable(format!(
                "the depth of a sphere centre must be positive and finite, got {z}"
            )));
        }
    }
    match *camera {
        Camera::Orthographic { pixel_size, .. } => {
            let z = center_depth.ok_or_else(|| {
                Error::Unusable(
                    "an orthographic camera needs the depth of each sphere centre (center_depth)"
                        .into(),
                )
            })?;
            let scene: Vec<[f64; 2]> = outline
                .iter()
                .map(|&uv| {
                    let o = pixel_ray(camera, uv).origin;
                    [o[0], o[1]]
                })
                .collect();
            let free = fit_circle(&scene)?;
            // The radius is known: when the free fit agrees with it (the pixel size is right),
            // the centre is fitted with the radius fixed, which rejects a part of the outline
            // that is biased inwards (a limb in the dark, where the shading fades to nothing).
            let circle = if (free.radius / radius - 1.0).abs() <= 0.03 {
                fit_circle_radius(&scene, free.center, radius).unwrap_or(free)
            } else {
                free
            };
            let px = (pixel_size[0] * pixel_size[1]).sqrt();
            let c = [circle.center[0], circle.center[1], z];
            Ok(Sphere {
                placement: 0,
                center: c,
                radius,
                image_center: project(camera, c),
                image_radius: free.radius / px,
                fit_rms: circle.rms / px,
                outline_points: [circle.inliers, outline.len()],
                scale_check: free.radius / radius,
                shift: 0.0,
                outline_sigma: OUTLINE_FIT_SIGMA,
            })
        }
        Camera::Pinhole { k, .. } => {
            let rays: Vec<[f64; 3]> = outline
                .iter()
                .map(|&uv| pixel_ray(camera, uv).direction)
                .collect();
            let cone = fit_cone(&rays)?;
            let distance = radius / cone.half_angle.sin();
            let from_outline = scale(cone.axis, distance);
            let (center, check) = match center_depth {
                Some(z) => {
                    let c = scale(cone.axis, z / cone.axis[2]);
                    (c, distance / norm(c))
                }
                None => (from_outline, 1.0),
            };
            let f = (k[0][0] * k[1][1]).sqrt();
            Ok(Sphere {
                placement: 0,
                center,
                radius,
                image_center: project(camera, center),
                image_radius: f * cone.half_angle.tan(),
                fit_rms: f * cone.rms,
                outline_points: [cone.inliers, outline.len()],
                scale_check: check,
                shift: 0.0,
                outline_sigma: OUTLINE_FIT_SIGMA,
            })
        }
    }
}

// -------------------------------------------------------------------------------------------
// Outlines from digitised masks
// -------------------------------------------------------------------------------------------

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

/// Maximises `t = z[3]` subject to `rows[i] . z <= h[i]` by the active-set (simplex) method,
/// starting from the feasible point `z` (one constraint active, `active`). Returns the optimum,
/// or None when the problem is unbounded or does not converge.
fn max_margin_lp(rows: &[[f64; 4]], h: &[f64], mut z: [f64; 4], active: usize) -> Option<[f64; 4]> {
    let c = Vector4::new(0.0, 0.0, 0.0, 1.0);
    let row = |i: usize| Vector4::new(rows[i][0], rows[i][1], rows[i][2], rows[i][3]);
    let mut work = vec![active];
    for _ in 0..(20 * rows.len() + 100) {
        // Multipliers y of the working set (least squares c ~ G_W^T y) and the projection d of c
        // onto the null space of G_W: the steepest feasible ascent along the working set.
        let k = work.len();
        let g = nalgebra::DMatrix::from_fn(k, 4, |i, j| rows[work[i]][j]);
        let y = (&g * g.transpose()).lu().solve(&(&g * c))?;
        let d = c - g.transpose() * &y;
        if d.norm() < 1e-12 {
            // A vertex or an optimal face: optimal when no multiplier is negative, otherwise
            // leave the constraint with the most negative one.
            let (j, &lambda) = y.iter().enumerate().min_by(|a, b| a.1.total_cmp(b.1))?;
            if lambda >= -1e-12 {
                return Some(z);
            }
            work.remove(j);
            continue;
        }
        // Ratio test: the first constraint the step along d meets.
        let zv = Vector4::new(z[0], z[1], z[2], z[3]);
        let mut best: Option<(usize, f64)> = None;
        for (i, hi) in h.iter().enumerate() {
            if work.contains(&i) {
                continue;
            }
            let gd = row(i).dot(&d);
            if gd > 1e-14 {
                let step = ((hi - row(i).dot(&zv)) / gd).max(0.0);
                if best.is_none_or(|(_, s)| step < s) {
                    best = Some((i, step));
                }
            }
        }
        let (i, step) = best?;
        for (zj, dj) in z.iter_mut().zip(d.iter()) {
            *zj += step * dj;
        }
        work.push(i);
    }
    None
}

/// The circle (scene units) that separates the `inside` points from the `outside` points with
/// the widest margin in the algebraic form `|p|^2 + D x + E y + F` (the Chebyshev centre of the
/// set of consistent circles, a linear programme in D, E, F), started from `start`. A mask that
/// holds the pixels whose centre sees a disc determines the disc far better this way than a
/// least-squares fit to its boundary (about 0.01 against 0.03 pixel for a 40-pixel disc). None
/// when no circle separates the points (a mask that is not such a digitisation).
pub(crate) fn separating_circle(
    inside: &[[f64; 2]],
    outside: &[[f64; 2]],
    start: &Circle,
) -> Option<Circle> {
    if inside.len() < 5 || outside.len() < 5 || not_above(start.radius, 0.0) {
        return None;
    }
    let (c0, s) = (start.center, start.radius);
    let mut rows = Vec::with_capacity(inside.len() + outside.len());
    let mut h = Vec::with_capacity(rows.capacity());
    for (points, sign) in [(inside, 1.0), (outside, -1.0)] {
        for p in points {
            let q = [(p[0] - c0[0]) / s, (p[1] - c0[1]) / s];
            let norm = (q[0] * q[0] + q[1] * q[1] + 1.0).sqrt();
            rows.push([sign * q[0] / norm, sign * q[1] / norm, sign / norm, 1.0]);
            h.push(-sign * (q[0] * q[0] + q[1] * q[1]) / norm);
        }
    }
    // The start circle (centre 0, radius 1 in normalised coordinates) with the margin that
    // makes it feasible.
    let x0 = [0.0, 0.0, -1.0];
    let (active, t0) = rows
        .iter()
        .zip(&h)
        .map(|(r, hi)| hi - (r[0] * x0[0] + r[1] * x0[1] + r[2] * x0[2]))
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(&b.1))?;
    let z = max_margin_lp(&rows, &h, [x0[0], x0[1], x0[2], t0], active)?;
    if not_above(z[3], 0.0) {
        return None;
    }
    let (cx, cy) = (-0.5 * z[0], -0.5 * z[1]);
    let r2 = cx * cx + cy * cy - z[2];
    if not_above(r2, 0.0) {
        return None;
    }
    Some(Circle {
        center: [c0[0] + s * cx, c0[1] + s * cy],
        radius: s * r2.sqrt(),
        rms: start.rms,
        inliers: inside.len() + outside.len(),
    })
}

/// The cone (apex at the camera) that separates the `inside` unit rays from the `outside` ones
/// with the widest margin: `b . m >= 1` inside and `<= 1` outside with `m = a / cos(theta)`, a
/// linear programme in `m` (coordinates scaled so that a unit step turns the axis or changes
/// the half-angle by about one radian), started from `start`. None when no cone separates them.
pub(crate) fn separating_cone(
    inside: &[[f64; 3]],
    outside: &[[f64; 3]],
    start: &Cone,
) -> Option<Cone> {
    if inside.len() < 5 || outside.len() < 5 {
        return None;
    }
    let a0 = start.axis;
    let (sin0, cos0) = start.half_angle.sin_cos();
    let m0 = scale(a0, 1.0 / cos0);
    let (e1, e2) = tangent_basis(a0);
    // m = m0 + e1 x1 + e2 x2 + a0 sin0 x3 (x3 changes the half-angle by ~x3 radians).
    let basis = [e1, e2, scale(a0, sin0)];
    let mut rows = Vec::with_capacity(inside.len() + outside.len());
    let mut h = Vec::with_capacity(rows.capacity());
    for (rays, sign) in [(inside, -1.0), (outside, 1.0)] {
        for b in rays {
            // inside: -b . m <= -1, outside: b . m <= 1.
            let g = [
                sign * dot(*b, basis[0]),
                sign * dot(*b, basis[1]),
                sign * dot(*b, basis[2]),
            ];
            let len = norm(g);
            if not_above(len, 0.0) {
                continue;
            }
            rows.push([g[0] / len, g[1] / len, g[2] / len, 1.0]);
            h.push((sign - sign * dot(*b, m0)) / len);
        }
    }
    let (active, t0) = h
        .iter()
        .copied()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(&b.1))?;
    let z = max_margin_lp(&rows, &h, [0.0, 0.0, 0.0, t0], active)?;
    if not_above(z[3], 0.0) {
        return None;
    }
    let m = add(
        m0,
        add(
            scale(basis[0], z[0]),
            add(scale(basis[1], z[1]), scale(basis[2], z[2])),
        ),
    );
    let len = norm(m);
    if not_above(len, 1.0) {
        return None;
    }
    Some(Cone {
        axis: scale(m, 1.0 / len),
        half_angle: (1.0 / len).acos(),
        rms: start.rms,
        inliers: inside.len() + outside.len(),
    })
}

/// Outline precision (pixels, per coordinate of the centre) assumed by the joint refinement
/// for a sphere located by [`separating_circle`] / [`separating_cone`] from its mask.
pub(crate) const MASK_DIGITAL_SIGMA: f64 = 0.01;

/// Outline precision (pixels) assumed for a least-squares outline fit (mask boundary or image
/// edges): the digitisation leaves ~0.03 pixel even for a 40-pixel disc.
pub(crate) const OUTLINE_FIT_SIGMA: f64 = 0.03;

/// Locates a sphere from its mask region: the least-squares fit of the crack midpoints
/// ([`locate_sphere`]), improved by the widest-margin separating circle or cone of the mask's
/// edge pixels when the mask is consistent with one. Returns the sphere and whether the
/// separating fit was used.
pub(crate) fn locate_sphere_in_mask(
    camera: &Camera,
    labels: &[u32],
    height: usize,
    width: usize,
    label: u32,
    radius: f64,
    center_depth: Option<f64>,
) -> Result<(Sphere, bool)> {
    let cracks = mask_boundary(labels, height, width, label);
    let mut sphere = locate_sphere(camera, &cracks, radius, center_depth)?;
    sphere.outline_sigma = OUTLINE_FIT_SIGMA;
    let (inside, outside) = mask_edge_pixels(labels, height, width, label);
    match *camera {
        Camera::Orthographic { pixel_size, .. } => {
            let to_scene = |uv: &[f64; 2]| {
                let o = pixel_ray(camera, *uv).origin;
                [o[0], o[1]]
            };
            let start = fit_circle(&cracks.iter().map(to_scene).collect::<Vec<_>>())?;
            let ins: Vec<[f64; 2]> = inside.iter().map(to_scene).collect();
            let outs: Vec<[f64; 2]> = outside.iter().map(to_scene).collect();
            if let Some(circle) = separating_circle(&ins, &outs, &start) {
                let px = (pixel_size[0] * pixel_size[1]).sqrt();
                sphere.center = [circle.center[0], circle.center[1], sphere.center[2]];
                sphere.image_center = project(camera, sphere.center);
                sphere.image_radius = circle.radius / px;
                sphere.scale_check = circle.radius / radius;
                sphere.outline_sigma = MASK_DIGITAL_SIGMA;
                return Ok((sphere, true));
            }
        }
        Camera::Pinhole { k, .. } => {
            let rays = |pts: &[[f64; 2]]| -> Vec<[f64; 3]> {
                pts.iter()
                    .map(|&uv| pixel_ray(camera, uv).direction)
                    .collect()
            };
            let start = fit_cone(&rays(&cracks))?;
            if let Some(cone) = separating_cone(&rays(&inside), &rays(&outside), &start) {
                let distance = radius / cone.half_angle.sin();
                let (center, check) = match center_depth {
                    Some(z) => {
                        let c = scale(cone.axis, z / cone.axis[2]);
                        (c, distance / norm(c))
                    }
                    None => (scale(cone.axis, distance), 1.0),
                };
                sphere.center = center;
                sphere.image_center = project(camera, center);
                sphere.image_radius = (k[0][0] * k[1][1]).sqrt() * cone.half_angle.tan();
                sphere.scale_check = check;
                sphere.outline_sigma = MASK_DIGITAL_SIGMA;
                return Ok((sphere, true));
            }
        }
    }
    Ok((sphere, false))
}

/// The pixels of the sphere's image whose ray passes within `margin * R` of the centre, as
/// (bounding box [r0, c0, r1, c1] inclusive, flags over the box).
fn sphere_region(
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
            let ray = pixel_ray(camera, [c as f64, r as f64]);
            let ahead = dot(sub(sphere.center, ray.origin), ray.direction) > 0.0;
            if ahead && ray.distance_to(sphere.center) < limit {
                inside[(r - r0) * bw + (c - c0)] = true;
                any = true;
            }
        }
    }
    any.then_some(([r0, c0, r1, c1], inside))
}

// -------------------------------------------------------------------------------------------
// Highlights and rays
// -------------------------------------------------------------------------------------------

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

/// Finds the highlight of one image (H x W) inside a sphere's region (see the
/// [module documentation](self)).
fn find_highlight_in(
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
/// [module documentation](self).
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
    let view = pixel_ray(camera, highlight.pixel).direction;
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

/// The mirror ray of a highlight at image point `uv` on `sphere`: the surface point, its outward
/// normal, and the ray from the surface point towards the light. None when the viewing ray
/// misses the sphere.
pub(crate) fn reflected_ray(
    camera: &Camera,
    sphere: &Sphere,
    uv: [f64; 2],
) -> Option<([f64; 3], [f64; 3], Ray)> {
    let view = pixel_ray(camera, uv);
    let x = ray_sphere(&view, sphere.center, sphere.radius)?;
    let n = scale(sub(x, sphere.center), 1.0 / sphere.radius);
    let r = unit(reflect(view.direction, n));
    Some((
        x,
        n,
        Ray {
            origin: x,
            direction: r,
        },
    ))
}

// -------------------------------------------------------------------------------------------
// Lights from rays
// -------------------------------------------------------------------------------------------

/// The point closest to a set of lines in the least-squares sense,
/// `argmin_p sum_i |(I - d_i d_i^T)(p - o_i)|^2`, and the RMS distance of the lines from it.
/// None when fewer than two rays are given or the rays are parallel (the normal matrix is
/// singular to working precision).
pub(crate) fn nearest_point(rays: &[Ray]) -> Option<([f64; 3], f64)> {
    if rays.len() < 2 {
        return None;
    }
    let mut a = Matrix3::<f64>::zeros();
    let mut b = Vector3::<f64>::zeros();
    for ray in rays {
        let d = Vector3::new(ray.direction[0], ray.direction[1], ray.direction[2]);
        let o = Vector3::new(ray.origin[0], ray.origin[1], ray.origin[2]);
        let proj = Matrix3::identity() - d * d.transpose();
        a += proj;
        b += proj * o;
    }
    let eig = SymmetricEigen::new(a);
    let min = eig.eigenvalues.min();
    if not_above(min, 1e-10 * rays.len() as f64) {
        return None;
    }
    let p = a.cholesky()?.solve(&b);
    let p = [p[0], p[1], p[2]];
    if !p.iter().all(|v| v.is_finite()) {
        return None;
    }
    let ms = rays.iter().map(|r| r.distance_to(p).powi(2)).sum::<f64>() / rays.len() as f64;
    Some((p, ms.sqrt()))
}

/// The normalised mean direction of the rays and the RMS angle (radians) of the rays about it.
pub(crate) fn mean_direction(rays: &[Ray]) -> Option<([f64; 3], f64)> {
    let sum = rays.iter().fold([0.0; 3], |acc, r| add(acc, r.direction));
    let n = norm(sum);
    if rays.is_empty() || not_above(n, 0.0) {
        return None;
    }
    let d = scale(sum, 1.0 / n);
    let ms = rays
        .iter()
        .map(|r| angle(r.direction, d).powi(2))
        .sum::<f64>()
        / rays.len() as f64;
    Some((d, ms.sqrt()))
}

/// A light estimated from its rays.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LightEstimate {
    /// A near light at this position.
    Point([f64; 3]),
    /// A distant light in this direction (unit, from the scene towards the light).
    Directional([f64; 3]),
    /// Not seen on any sphere.
    Missing,
}

/// The calibration of one light.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct LightReport {
    /// Position or direction.
    pub estimate: LightEstimate,
    /// RMS distance of the rays from the position (NaN for directional or missing lights).
    pub rms_miss: f64,
    /// RMS angle (degrees) between each ray and the direction from its origin to the position
    /// (point lights) or the mean direction (directional lights).
    pub rms_angle: f64,
    /// Largest angle (degrees) between two of the rays (their spread; 0 for one ray).
    pub spread: f64,
    /// Number of spheres (rays) the light was seen on.
    pub spheres: usize,
    /// Why the light is not a located point light, if it is not.
    pub warning: Option<String>,
}

/// Locates one light from its rays (see the [module documentation](self)). `parallel_tol` is
/// the RMS angle in radians about the mean direction below which the rays are taken as
/// parallel (a distant light).
pub(crate) fn locate_light(rays: &[Ray], parallel_tol: f64) -> LightReport {
    let spread = rays
        .iter()
        .enumerate()
        .flat_map(|(i, a)| {
            rays[i + 1..]
                .iter()
                .map(move |b| angle(a.direction, b.direction))
        })
        .fold(0.0f64, f64::max)
        .to_degrees();
    let Some((mean, rms_dir)) = mean_direction(rays) else {
        return LightReport {
            estimate: LightEstimate::Missing,
            rms_miss: f64::NAN,
            rms_angle: f64::NAN,
            spread: 0.0,
            spheres: 0,
            warning: Some("not seen on any sphere: no position and no direction".into()),
        };
    };
    let directional = |warning: Option<String>| LightReport {
        estimate: LightEstimate::Directional(mean),
        rms_miss: f64::NAN,
        rms_angle: rms_dir.to_degrees(),
        spread,
        spheres: rays.len(),
        warning,
    };
    if rays.len() == 1 {
        return directional(Some(
            "seen on one sphere only: no position possible from one ray; written as a directional light along the reflected ray".into(),
        ));
    }
    if rms_dir <= parallel_tol {
        return directional(None);
    }
    let Some((p, rms_miss)) = nearest_point(rays) else {
        return directional(None);
    };
    if rays
        .iter()
        .any(|r| dot(sub(p, r.origin), r.direction) <= 0.0)
    {
        return directional(Some(format!(
            "the rays diverge (their nearest point lies behind a sphere; spread {spread:.2} deg): written as a directional light"
        )));
    }
    let ms_angle = rays
        .iter()
        .map(|r| angle(r.direction, sub(p, r.origin)).powi(2))
        .sum::<f64>()
        / rays.len() as f64;
    LightReport {
        estimate: LightEstimate::Point(p),
        rms_miss,
        rms_angle: ms_angle.sqrt().to_degrees(),
        spread,
        spheres: rays.len(),
        warning: None,
    }
}

// -------------------------------------------------------------------------------------------
// The whole sphere calibration
// -------------------------------------------------------------------------------------------

/// Where the spheres of a placement are.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SphereSource<'a> {
    /// An H x W label image: 0 background; if every non-zero label is 1 (a binary mask), each
    /// 8-connected component is a sphere, otherwise each label is one sphere.
    Labels(&'a [u32]),
    /// Detection in the composite image (see `detect_spheres`).
    Detect(Detection),
}

/// Where the outline points of a sphere come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Outline {
    /// From the mask (crack midpoints); detection then uses the images anyway.
    #[default]
    Mask,
    /// From the composite image of the placement (each pixel's brightest value over the lights;
    /// `radial_edges`), starting from the mask's circle.
    Images,
}

/// One image set: k grey images (k x H x W, the rig's light order) of one or more spheres.
#[derive(Debug, Clone, PartialEq)]
pub struct Placement<'a> {
    /// The images, k x H x W.
    pub images: &'a [f32],
    /// Where the spheres are.
    pub spheres: SphereSource<'a>,
    /// Depth of the sphere centres: none, one for all spheres of the placement, or one per
    /// sphere (in the order of the labels or the detection). Required for an orthographic
    /// camera.
    pub center_depth: Vec<f64>,
}

/// Options of [`calibrate_spheres`].
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub struct SphereOptions {
    /// Sphere radius (scene units), the same for every sphere.
    pub radius: f64,
    /// Where the outline points come from when masks are given.
    pub outline: Outline,
    /// RMS angle (degrees) of the rays about their mean below which a light is taken as distant
    /// (directional). Default 0.5.
    pub parallel_tol: f64,
    /// Highlight search thresholds.
    pub highlight: HighlightOptions,
    /// Fewest pixels of a mask component taken as a sphere (smaller ones are ignored with a
    /// note). Default 30.
    pub min_component: usize,
    /// Refine the sphere centres and the lights jointly (step 6 of the
    /// [module documentation](self)). Default true.
    pub refine: bool,
}

impl Default for SphereOptions {
    fn default() -> Self {
        SphereOptions {
            radius: 1.0,
            outline: Outline::Mask,
            parallel_tol: 0.5,
            highlight: HighlightOptions::default(),
            min_component: 30,
            refine: true,
        }
    }
}

with_fields!(SphereOptions {
    with_radius: radius: f64,
    with_outline: outline: Outline,
    with_parallel_tol: parallel_tol: f64,
    with_highlight: highlight: HighlightOptions,
    with_min_component: min_component: usize,
    with_refine: refine: bool,
});

/// One highlight used (or rejected) for a light.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct Observation {
    /// Light (image) index.
    pub light: usize,
    /// Sphere index (into [`SphereCalibration::spheres`]).
    pub sphere: usize,
    /// The highlight, or why there is none.
    pub highlight: std::result::Result<Highlight, Rejection>,
    /// The reflected ray (None when rejected).
    pub ray: Option<Ray>,
    /// The surface normal at the highlight (NaN when rejected).
    pub normal: [f64; 3],
}

/// The result of [`calibrate_spheres`].
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct SphereCalibration {
    /// The located spheres, placement by placement.
    pub spheres: Vec<Sphere>,
    /// Every (light, sphere) pair, light-major.
    pub observations: Vec<Observation>,
    /// One report per light.
    pub lights: Vec<LightReport>,
    /// Notes and warnings (a light seen on fewer than two spheres, a pixel size that does not
    /// match the radius, ignored mask components, ...).
    pub warnings: Vec<String>,
    /// The joint refinement, if it ran.
    pub refinement: Option<Refinement>,
}

impl SphereCalibration {
    /// The calibrated rig: the camera and, per light, an isotropic point light of unit intensity
    /// at the position, or a directional light of unit intensity. Fails when a light was not
    /// seen on any sphere.
    pub fn rig(&self, camera: Camera) -> Result<Rig> {
        let mut lights = Vec::with_capacity(self.lights.len());
        for (i, l) in self.lights.iter().enumerate() {
            lights.push(match l.estimate {
                LightEstimate::Point(p) => Light::point(p),
                LightEstimate::Directional(d) => Light::Directional {
                    direction: d,
                    intensity: [1.0; 3],
                },
                LightEstimate::Missing => {
                    return Err(Error::Rig(format!(
                        "light {i} was not seen on any sphere: no rig can be written (check its image, or the highlight thresholds)"
                    )))
                }
            });
        }
        let rig = Rig { camera, lights };
        rig.validate_parameters()?;
        Ok(rig)
    }
}

/// The label image's spheres: labels as given, or the components of a binary mask.
fn sphere_labels(
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

/// Calibrates the lights from mirror-sphere images (see the [module documentation](self)).
/// Every placement holds k x H x W images (the same k and H x W for all).
pub fn calibrate_spheres(
    camera: &Camera,
    placements: &[Placement<'_>],
    height: usize,
    width: usize,
    k: usize,
    options: &SphereOptions,
) -> Result<SphereCalibration> {
    camera.validate()?;
    if placements.is_empty() {
        return Err(Error::Unusable(
            "no sphere images (no placement) given".into(),
        ));
    }
    if k == 0 || height < 3 || width < 3 {
        return Err(Error::Unusable(format!(
            "sphere images must be at least 3 x 3 pixels and at least one per light, got k = {k}, {width} x {height} pixels"
        )));
    }
    if !(options.radius > 0.0 && options.radius.is_finite()) {
        return Err(Error::OutOfRange {
            name: "radius",
            value: options.radius,
            message: format!(
                "the sphere radius must be positive and finite, got {}",
                options.radius
            ),
        });
    }
    if !(options.parallel_tol >= 0.0 && options.parallel_tol.is_finite()) {
        return Err(Error::OutOfRange {
            name: "parallel_tol",
            value: options.parallel_tol,
            message: format!(
                "parallel_tol must be a non-negative angle in degrees, got {}",
                options.parallel_tol
            ),
        });
    }
    let h = options.highlight;
    let valid = (0.0..1.0).contains(&h.min_contrast)
        && h.max_blob_fraction > 0.0
        && h.max_blob_fraction <= 1.0
        && h.limb_margin > 0.0
        && h.limb_margin <= 1.0;
    if !valid {
        return Err(Error::Unusable(format!(
            "highlight options out of range (min_contrast in [0, 1), max_blob_fraction and limb_margin in (0, 1]): {h:?}"
        )));
    }
    let plane = height * width;
    let mut warnings = Vec::new();
    let mut spheres: Vec<Sphere> = Vec::new();
    let mut regions: Vec<([usize; 4], Vec<bool>)> = Vec::new();
    for (pi, placement) in placements.iter().enumerate() {
        if placement.images.len() != k * plane {
            return Err(Error::Shape {
                what: "sphere images",
                expected: k * plane,
                got: placement.images.len(),
                message: format!(
                    "placement {pi}: expected {k} images of {width} x {height} pixels ({} values), got {} values",
                    k * plane,
                    placement.images.len()
                ),
            });
        }
        if let Some(i) = placement.images.iter().position(|v| !v.is_finite()) {
            return Err(Error::NonFinite {
                what: "sphere images",
                index: i,
                message: format!(
                    "placement {pi}: image {} has a non-finite value at pixel ({}, {})",
                    i / plane,
                    (i % plane) / width,
                    i % width
                ),
            });
        }
        // The brightest value of each pixel over the lights: every part of the limb is lit by
        // some light, so the outline stands out all around (the mean leaves the limb dark on the
        // side away from most lights).
        let mut composite = vec![f32::NEG_INFINITY; plane];
        for image in placement.images.chunks_exact(plane) {
            for (x, v) in composite.iter_mut().zip(image) {
                *x = x.max(*v);
            }
        }
        // Where each sphere's outline comes from: its mask region (label) or outline points.
        enum Source {
            Region(u32),
            Points(Vec<[f64; 2]>),
        }
        let mut region_labels: Vec<u32> = Vec::new();
        let sources: Vec<Source> = match placement.spheres {
            SphereSource::Labels(labels) => {
                if labels.len() != plane {
                    return Err(Error::Unusable(format!(
                        "placement {pi}: the mask has {} pixels, the images {width} x {height}",
                        labels.len()
                    )));
                }
                let (labels, keep) = sphere_labels(
                    labels,
                    height,
                    width,
                    options.min_component,
                    pi,
                    &mut warnings,
                );
                if keep.is_empty() {
                    return Err(Error::Unusable(format!(
                        "placement {pi}: the mask marks no sphere"
                    )));
                }
                let mut sources = Vec::new();
                for l in keep {
                    match options.outline {
                        Outline::Mask => sources.push(Source::Region(l)),
                        Outline::Images => {
                            let points = mask_boundary(&labels, height, width, l);
                            let circle = fit_circle(&points).map_err(|e| {
                                Error::Unusable(format!("placement {pi}, mask region {l}: {e}"))
                            })?;
                            match image_outline(
                                &composite,
                                height,
                                width,
                                circle.center,
                                circle.radius,
                            ) {
                                Ok(edges) if edges.len() >= points.len().min(64) => {
                                    sources.push(Source::Points(edges))
                                }
                                _ => {
                                    warnings.push(format!(
                                        "placement {pi}, mask region {l}: the sphere's outline is not visible in the images; the mask's outline is used"
                                    ));
                                    sources.push(Source::Region(l));
                                }
                            }
                        }
                    }
                }
                region_labels = labels;
                sources
            }
            SphereSource::Detect(detection) => {
                let (circles, notes) = detect_spheres(&composite, height, width, &detection)
                    .map_err(|e| Error::Unusable(format!("placement {pi}: {e}")))?;
                warnings.extend(notes.into_iter().map(|n| format!("placement {pi}: {n}")));
                let mut sources = Vec::new();
                for (centre, radius) in circles {
                    sources.push(Source::Points(
                        image_outline(&composite, height, width, centre, radius).map_err(|e| {
                            Error::Unusable(format!(
                            "placement {pi}: the sphere detected at (u, v) = ({:.0}, {:.0}): {e}",
                            centre[0], centre[1]
                        ))
                        })?,
                    ));
                }
                sources
            }
        };
        let n_here = sources.len();
        let depth_of = |j: usize| -> Result<Option<f64>> {
            match placement.center_depth.len() {
                0 => Ok(None),
                1 => Ok(Some(placement.center_depth[0])),
                n if n == n_here => Ok(Some(placement.center_depth[j])),
                n => Err(Error::Unusable(format!(
                    "placement {pi} has {n_here} sphere(s) but {n} centre depths were given (give one for all, or one per sphere)"
                ))),
            }
        };
        let mut inconsistent = 0;
        for (j, source) in sources.iter().enumerate() {
            let located = match source {
                Source::Region(l) => locate_sphere_in_mask(
                    camera,
                    &region_labels,
                    height,
                    width,
                    *l,
                    options.radius,
                    depth_of(j)?,
                )
                .map(|(sphere, digital)| {
                    inconsistent += usize::from(!digital);
                    sphere
                }),
                Source::Points(points) => {
                    locate_sphere(camera, points, options.radius, depth_of(j)?)
                }
            };
            let mut sphere =
                located.map_err(|e| Error::Unusable(format!("placement {pi}, sphere {j}: {e}")))?;
            sphere.placement = pi;
            let index = spheres.len();
            if sphere.image_radius < 5.0 {
                return Err(Error::Unusable(format!(
                    "sphere {index} (placement {pi}) is only {:.1} px in radius; highlights cannot be located on it",
                    sphere.image_radius
                )));
            }
            if (sphere.scale_check - 1.0).abs() > 0.03 {
                warnings.push(match camera {
                    Camera::Orthographic { .. } => format!(
                        "sphere {index} (placement {pi}): its outline has radius {:.4} but the given radius is {} (ratio {:.3}): check the pixel size and the radius",
                        sphere.scale_check * options.radius, options.radius, sphere.scale_check
                    ),
                    Camera::Pinhole { .. } => format!(
                        "sphere {index} (placement {pi}): the outline puts the centre at {:.1}% of the distance implied by the given centre depth: check K, the radius and the depth",
                        100.0 * sphere.scale_check
                    ),
                });
            }
            let region = sphere_region(
                camera,
                &sphere,
                height,
                width,
                options.highlight.limb_margin,
            )
            .ok_or_else(|| {
                Error::Unusable(format!(
                    "sphere {index} (placement {pi}) is not inside the image"
                ))
            })?;
            spheres.push(sphere);
            regions.push(region);
        }
        if inconsistent > 0 {
            warnings.push(format!(
                "placement {pi}: {inconsistent} mask region(s) are not the pixel sampling of a circle (hand-drawn or smoothed masks?); their outlines were fitted by least squares, which is less exact"
            ));
        }
    }
    // Highlights, light by light and sphere by sphere.
    let ns = spheres.len();
    let mut highlights = Vec::with_capacity(k * ns);
    for i in 0..k {
        for (s, sphere) in spheres.iter().enumerate() {
            let image = &placements[sphere.placement].images[i * plane..(i + 1) * plane];
            let (bbox, inside) = &regions[s];
            let highlight =
                find_highlight_in(image, height, width, *bbox, inside, &options.highlight)
                    .and_then(|h| correct_highlight(camera, sphere, h).ok_or(Rejection::Miss));
            highlights.push(highlight);
        }
    }
    let tol = options.parallel_tol.to_radians();
    let locate_all =
        |spheres: &[Sphere], highlights: &[std::result::Result<Highlight, Rejection>]| {
            (0..k)
                .map(|i| {
                    let rays: Vec<Ray> = (0..ns)
                        .filter_map(|s| {
                            let hl = highlights[i * ns + s].as_ref().ok()?;
                            reflected_ray(camera, &spheres[s], hl.pixel).map(|(_, _, r)| r)
                        })
                        .collect();
                    locate_light(&rays, tol)
                })
                .collect::<Vec<_>>()
        };
    let mut lights = locate_all(&spheres, &highlights);
    let mut refinement = None;
    if options.refine {
        let obs: Vec<HighlightPixel> = (0..k * ns)
            .filter_map(|j| {
                highlights[j]
                    .as_ref()
                    .ok()
                    .map(|h| (j / ns, j % ns, h.pixel))
            })
            .collect();
        let estimates: Vec<LightEstimate> = lights.iter().map(|l| l.estimate).collect();
        let useful = estimates
            .iter()
            .enumerate()
            .filter(|(i, _)| obs.iter().filter(|o| o.0 == *i).count() >= 2)
            .count();
        if useful > 0 {
            let (report, dropped) = refine_spheres(camera, &mut spheres, &obs, &estimates)?;
            for j in dropped {
                let (i, s, _) = obs[j];
                highlights[i * ns + s] = Err(Rejection::Inconsistent);
                warnings.push(format!(
                    "light {i}: its highlight on sphere {s} is inconsistent with its other spheres and was left out"
                ));
            }
            lights = locate_all(&spheres, &highlights);
            refinement = Some(report);
        }
    }
    let mut observations = Vec::with_capacity(k * ns);
    for (j, highlight) in highlights.into_iter().enumerate() {
        let (i, s) = (j / ns, j % ns);
        let (ray, normal) = match highlight
            .as_ref()
            .ok()
            .and_then(|h| reflected_ray(camera, &spheres[s], h.pixel))
        {
            Some((_, n, r)) => (Some(r), n),
            None => (None, [f64::NAN; 3]),
        };
        observations.push(Observation {
            light: i,
            sphere: s,
            highlight,
            ray,
            normal,
        });
    }
    for (i, report) in lights.iter().enumerate() {
        if let Some(w) = &report.warning {
            warnings.push(format!("light {i}: {w}"));
        }
    }
    Ok(SphereCalibration {
        spheres,
        observations,
        lights,
        warnings,
        refinement,
    })
}

// -------------------------------------------------------------------------------------------
// Joint refinement of the spheres and the lights
// -------------------------------------------------------------------------------------------

/// What the joint refinement did.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct Refinement {
    /// Levenberg–Marquardt iterations (all rounds).
    pub iterations: usize,
    /// Highlights used (each light seen on at least two spheres).
    pub highlights: usize,
    /// Highlights dropped as inconsistent.
    pub dropped: usize,
    /// RMS highlight residual before and after, pixel-equivalent (ray angle times half the
    /// sphere's image radius).
    pub highlight_rms: [f64; 2],
    /// RMS move of the sphere centres' images (and image radii, pinhole) away from the
    /// outlines' estimates, pixels.
    pub outline_shift: f64,
    /// The highlight noise level used to weight the highlights against the outlines, pixels.
    pub highlight_sigma: f64,
}

/// A light's parameters in the refinement.
#[derive(Debug, Clone, Copy)]
enum LightParam {
    Point,
    /// A direction near `d0`, moved in the tangent basis (e1, e2).
    Directional {
        d0: [f64; 3],
        e1: [f64; 3],
        e2: [f64; 3],
    },
}

/// Two unit vectors orthogonal to the unit vector `a` and to each other.
fn tangent_basis(a: [f64; 3]) -> ([f64; 3], [f64; 3]) {
    let helper = if a[0].abs() < 0.9 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    let e1 = unit(cross(a, helper));
    (e1, cross(a, e1))
}

/// The least-squares problem of [`refine_spheres`].
struct Bundle {
    radius: f64,
    perspective: bool,
    /// Orthographic: the given centre depths.
    depths: Vec<f64>,
    /// Per sphere: the outline's centre (the prior).
    prior: Vec<[f64; 3]>,
    /// Per sphere: pixels per scene unit (orthographic) or per radian (pinhole), divided by the
    /// outline's sigma (pixels).
    prior_weight: Vec<f64>,
    /// Per sphere: the outline's sigma (pixels).
    sigma_o: Vec<f64>,
    /// Per sphere: pixel-equivalent of one radian of ray angle (half the image radius).
    ray_scale: Vec<f64>,
    /// Observations: (light slot, sphere, viewing ray through the highlight).
    obs: Vec<(usize, usize, Ray)>,
    lights: Vec<LightParam>,
    sigma_h: f64,
}

impl Bundle {
    fn sphere_params(&self) -> usize {
        if self.perspective {
            3
        } else {
            2
        }
    }

    fn center(&self, theta: &[f64], s: usize) -> [f64; 3] {
        if self.perspective {
            [theta[3 * s], theta[3 * s + 1], theta[3 * s + 2]]
        } else {
            [theta[2 * s], theta[2 * s + 1], self.depths[s]]
        }
    }

    /// Light slot `l`: Ok(position) or Err(direction).
    fn light(
        &self,
        theta: &[f64],
        offsets: &[usize],
        l: usize,
    ) -> std::result::Result<[f64; 3], [f64; 3]> {
        let o = offsets[l];
        match self.lights[l] {
            LightParam::Point => Ok([theta[o], theta[o + 1], theta[o + 2]]),
            LightParam::Directional { d0, e1, e2 } => Err(unit(add(
                d0,
                add(scale(e1, theta[o]), scale(e2, theta[o + 1])),
            ))),
        }
    }

    fn offsets(&self) -> (Vec<usize>, usize) {
        let mut o = self.sphere_params() * self.prior.len();
        let mut offsets = Vec::with_capacity(self.lights.len());
        for l in &self.lights {
            offsets.push(o);
            o += match l {
                LightParam::Point => 3,
                LightParam::Directional { .. } => 2,
            };
        }
        (offsets, o)
    }

    /// The reflected ray of an observation for the sphere centre `c` (the viewing ray meets the
    /// sphere, or its closest approach is pushed onto it).
    fn ray(&self, view: &Ray, c: [f64; 3]) -> Ray {
        let oc = sub(view.origin, c);
        let b = dot(oc, view.direction);
        let disc = (b * b - (dot(oc, oc) - self.radius * self.radius)).max(0.0);
        let x = view.at(-b - disc.sqrt());
        let n = scale(sub(x, c), 1.0 / self.radius);
        Ray {
            origin: x,
            direction: unit(reflect(view.direction, n)),
        }
    }

    /// Outline (prior) residuals of the spheres, in units of their sigma: orthographic, the
    /// centre's (x, y) move; pinhole, the move of the centre's direction and of the half-angle
    /// of the tangent cone (which sets the distance).
    fn prior_residuals(&self, theta: &[f64], out: &mut Vec<f64>) {
        for (s, c0) in self.prior.iter().enumerate() {
            let c = self.center(theta, s);
            let w = self.prior_weight[s];
            if self.perspective {
                let (a0, a) = (unit(*c0), unit(c));
                let (e1, e2) = tangent_basis(a0);
                let half = |p: [f64; 3]| (self.radius / norm(p)).clamp(-1.0, 1.0).asin();
                out.extend([dot(a, e1) * w, dot(a, e2) * w, (half(c) - half(*c0)) * w]);
            } else {
                out.extend([(c[0] - c0[0]) * w, (c[1] - c0[1]) * w]);
            }
        }
    }

    /// Prior residuals, then highlight residuals (3 per observation, weighted).
    fn residuals(&self, theta: &[f64], offsets: &[usize], out: &mut Vec<f64>) {
        out.clear();
        self.prior_residuals(theta, out);
        for &(l, s, view) in &self.obs {
            let ray = self.ray(&view, self.center(theta, s));
            let target = match self.light(theta, offsets, l) {
                Ok(p) => unit(sub(p, ray.origin)),
                Err(d) => d,
            };
            let e = sub(target, scale(ray.direction, dot(target, ray.direction)));
            let w = self.ray_scale[s] / self.sigma_h;
            out.extend([e[0] * w, e[1] * w, e[2] * w]);
        }
    }

    /// Levenberg–Marquardt from `theta`; returns the iterations run.
    fn solve(&self, theta: &mut [f64], max_iterations: usize) -> usize {
        let (offsets, n) = self.offsets();
        let mut r = Vec::new();
        self.residuals(theta, &offsets, &mut r);
        let mut cost: f64 = r.iter().map(|v| v * v).sum();
        let mut lambda = 1e-4;
        let mut rp = Vec::new();
        let mut done = 0;
        for it in 0..max_iterations {
            done = it + 1;
            // Forward-difference Jacobian, column by column.
            let mut jac = vec![0.0; n * r.len()];
            for j in 0..n {
                let h = 1e-7 * theta[j].abs().max(1.0);
                let keep = theta[j];
                theta[j] = keep + h;
                self.residuals(theta, &offsets, &mut rp);
                theta[j] = keep;
                for (q, (a, b)) in rp.iter().zip(&r).enumerate() {
                    jac[j * r.len() + q] = (a - b) / h;
                }
            }
            let mut jtj = nalgebra::DMatrix::<f64>::zeros(n, n);
            let mut jtr = nalgebra::DVector::<f64>::zeros(n);
            for a in 0..n {
                let ca = &jac[a * r.len()..(a + 1) * r.len()];
                jtr[a] = ca.iter().zip(&r).map(|(x, y)| x * y).sum();
                for b in a..n {
                    let cb = &jac[b * r.len()..(b + 1) * r.len()];
                    let v: f64 = ca.iter().zip(cb).map(|(x, y)| x * y).sum();
                    jtj[(a, b)] = v;
                    jtj[(b, a)] = v;
                }
            }
            let mut improved = false;
            for _ in 0..10 {
                let mut m = jtj.clone();
                for d in 0..n {
                    m[(d, d)] += lambda * jtj[(d, d)].max(1e-12);
                }
                let Some(step) = m.cholesky().map(|c| c.solve(&(-&jtr))) else {
                    lambda *= 10.0;
                    continue;
                };
                let trial: Vec<f64> = theta.iter().zip(step.iter()).map(|(t, d)| t + d).collect();
                self.residuals(&trial, &offsets, &mut rp);
                let c: f64 = rp.iter().map(|v| v * v).sum();
                if c.is_finite() && c < cost {
                    let rel = (cost - c) / cost.max(1e-300);
                    theta.copy_from_slice(&trial);
                    std::mem::swap(&mut r, &mut rp);
                    cost = c;
                    lambda = (lambda * 0.2).max(1e-12);
                    improved = true;
                    if rel < 1e-10 {
                        return done;
                    }
                    break;
                }
                lambda *= 10.0;
            }
            if !improved {
                break;
            }
        }
        done
    }

    /// RMS outline move (pixels) and per-observation highlight residual norms (pixels).
    fn report(&self, theta: &[f64]) -> (f64, Vec<f64>) {
        let (offsets, _) = self.offsets();
        let mut r = Vec::new();
        self.residuals(theta, &offsets, &mut r);
        let per_sphere = if self.perspective { 3 } else { 2 };
        let n_prior = per_sphere * self.prior.len();
        let shift = r[..n_prior]
            .iter()
            .enumerate()
            .map(|(q, v)| {
                (v / self.prior_weight[q / per_sphere] * self.px_scale(q / per_sphere)).powi(2)
            })
            .sum::<f64>()
            / self.prior.len().max(1) as f64;
        let per_obs: Vec<f64> = r[n_prior..]
            .chunks_exact(3)
            .map(|e| (e[0] * e[0] + e[1] * e[1] + e[2] * e[2]).sqrt() * self.sigma_h)
            .collect();
        (shift.sqrt(), per_obs)
    }

    /// Pixels per prior unit of sphere `s` (the prior weight times the outline sigma).
    fn px_scale(&self, s: usize) -> f64 {
        self.prior_weight[s] * self.sigma_o[s]
    }
}

/// A located highlight: (light index, sphere index, its (u, v) pixel position).
pub(crate) type HighlightPixel = (usize, usize, [f64; 2]);

/// Refines the sphere centres and the lights jointly (a small bundle adjustment): minimises
/// the highlight residuals of every light seen on at least two spheres — the angle between the
/// mirror ray through the observed highlight and the direction to the light, expressed in
/// pixels (times half the sphere's image radius: the image shift of a highlight that turns the
/// ray by that angle) and weighted by the highlight noise level — plus, per sphere, the move of
/// its centre from the outline's estimate (orthographic: x and y in pixels; pinhole: the
/// direction of the centre and the half-angle of its tangent cone, in pixels), weighted by the
/// outline's precision ([`Sphere::outline_sigma`]). The highlights pin the sphere centres in
/// most directions better than a binary mask; the outline keeps the modes the highlights cannot
/// see (a common shift of all spheres and lights, and a stretch of the spheres' separation,
/// which turns every ray within its own plane through the baseline). The highlight noise is
/// estimated from the residuals (two rounds), and highlights more than 5 robust standard
/// deviations off are dropped. Orthographic cameras keep the given centre depths. Returns the
/// report and the dropped observations (indices into `obs`).
pub(crate) fn refine_spheres(
    camera: &Camera,
    spheres: &mut [Sphere],
    obs: &[HighlightPixel],
    lights: &[LightEstimate],
) -> Result<(Refinement, Vec<usize>)> {
    let perspective = camera.is_perspective();
    let radius = spheres.first().map_or(1.0, |s| s.radius);
    // Light slots: the lights seen on at least two spheres.
    let mut seen = vec![0usize; lights.len()];
    for &(l, _, _) in obs {
        seen[l] += 1;
    }
    let mut slot = vec![usize::MAX; lights.len()];
    let mut params = Vec::new();
    let mut init_lights = Vec::new();
    for (l, est) in lights.iter().enumerate() {
        if seen[l] < 2 {
            continue;
        }
        match *est {
            LightEstimate::Point(p) => {
                slot[l] = params.len();
                params.push(LightParam::Point);
                init_lights.extend(p);
            }
            LightEstimate::Directional(d) => {
                slot[l] = params.len();
                let (e1, e2) = tangent_basis(d);
                params.push(LightParam::Directional { d0: d, e1, e2 });
                init_lights.extend([0.0, 0.0]);
            }
            LightEstimate::Missing => {}
        }
    }
    let used: Vec<usize> = (0..obs.len())
        .filter(|&j| slot[obs[j].0] != usize::MAX)
        .collect();
    let px_per = match *camera {
        Camera::Orthographic { pixel_size, .. } => 1.0 / (pixel_size[0] * pixel_size[1]).sqrt(),
        Camera::Pinhole { k, .. } => (k[0][0] * k[1][1]).sqrt(),
    };
    let sigma_o: Vec<f64> = spheres.iter().map(|s| s.outline_sigma.max(1e-4)).collect();
    let mut bundle = Bundle {
        radius,
        perspective,
        depths: spheres.iter().map(|s| s.center[2]).collect(),
        prior: spheres.iter().map(|s| s.center).collect(),
        prior_weight: sigma_o.iter().map(|s| px_per / s).collect(),
        sigma_o,
        ray_scale: spheres.iter().map(|s| 0.5 * s.image_radius).collect(),
        obs: used
            .iter()
            .map(|&j| (slot[obs[j].0], obs[j].1, pixel_ray(camera, obs[j].2)))
            .collect(),
        lights: params,
        sigma_h: 0.05,
    };
    let mut theta: Vec<f64> = Vec::new();
    for s in spheres.iter() {
        if perspective {
            theta.extend(s.center);
        } else {
            theta.extend([s.center[0], s.center[1]]);
        }
    }
    theta.extend(init_lights);
    let (_, h_before) = bundle.report(&theta);
    let rms = |v: &[f64]| (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt();
    let highlight_before = rms(&h_before);
    let mut iterations = 0;
    let mut dropped = Vec::new();
    for round in 0..3 {
        iterations += bundle.solve(&mut theta, 50);
        let (_, per_obs) = bundle.report(&theta);
        // Noise level of the highlights, with the light parameters' share removed.
        let n_obs = per_obs.len() as f64;
        let n_light: f64 = bundle
            .lights
            .iter()
            .map(|l| match l {
                LightParam::Point => 3.0,
                LightParam::Directional { .. } => 2.0,
            })
            .sum();
        let dof = (2.0 * n_obs - n_light).max(1.0);
        let sigma = (per_obs.iter().map(|e| e * e).sum::<f64>() / dof)
            .sqrt()
            .max(0.005);
        if round == 2 {
            break;
        }
        // Drop gross outliers once (highlights far off their light's other rays).
        if round == 0 {
            let mut abs = per_obs.clone();
            let robust = (1.4826 * median(&mut abs) * std::f64::consts::SQRT_2).max(0.005);
            let limit = 5.0 * robust;
            let bad: Vec<usize> = (0..per_obs.len()).filter(|&q| per_obs[q] > limit).collect();
            if !bad.is_empty() {
                let mut keep = Vec::new();
                for (q, o) in bundle.obs.iter().enumerate() {
                    if bad.contains(&q) {
                        dropped.push(used[q]);
                    } else {
                        keep.push(*o);
                    }
                }
                bundle.obs = keep;
            }
        }
        bundle.sigma_h = sigma;
    }
    let (outline_shift, h_after) = bundle.report(&theta);
    if !theta.iter().all(|v| v.is_finite()) {
        return Err(Error::Unusable(
            "the joint refinement of spheres and lights diverged".into(),
        ));
    }
    for (s, sphere) in spheres.iter_mut().enumerate() {
        let c = bundle.center(&theta, s);
        sphere.shift = norm(sub(c, sphere.center));
        sphere.center = c;
        sphere.image_center = project(camera, c);
    }
    Ok((
        Refinement {
            iterations,
            highlights: bundle.obs.len(),
            dropped: dropped.len(),
            highlight_rms: [highlight_before, rms(&h_after)],
            outline_shift,
            highlight_sigma: bundle.sigma_h,
        },
        dropped,
    ))
}

/// The outline of a sphere in the composite image from a rough image circle: radial edges in a
/// window of a quarter radius (at least 4 pixels), a circle fit, and radial edges again in a
/// window of 8 % of the radius (at least 3 pixels) about that circle.
fn image_outline(
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

// -------------------------------------------------------------------------------------------
// Intensity calibration
// -------------------------------------------------------------------------------------------

/// A plane `normal . X = offset` in the camera frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plane {
    /// Normal (any length; normalised and turned towards the camera internally).
    pub normal: [f64; 3],
    /// Offset d.
    pub offset: f64,
}

impl Plane {
    /// The plane z = `depth` (a board facing the camera).
    pub fn at_depth(depth: f64) -> Plane {
        Plane {
            normal: [0.0, 0.0, -1.0],
            offset: -depth,
        }
    }

    /// Unit normal facing the camera (n_z < 0) and the matching offset.
    fn facing(&self) -> Result<([f64; 3], f64)> {
        let n = norm(self.normal);
        if !(n > 0.0 && n.is_finite() && self.offset.is_finite()) {
            return Err(Error::Unusable(format!(
                "the board plane needs a finite non-zero normal and a finite offset, got {self:?}"
            )));
        }
        let (mut u, mut d) = (scale(self.normal, 1.0 / n), self.offset / n);
        if u[2] > 0.0 {
            u = scale(u, -1.0);
            d = -d;
        }
        if u[2].abs() < 1e-6 {
            return Err(Error::Unusable(
                "the board plane is seen edge-on (its normal is perpendicular to the view)".into(),
            ));
        }
        Ok((u, d))
    }

    /// Where the viewing ray of (u, v) meets the plane (None behind the camera).
    pub fn intersect(&self, camera: &Camera, uv: [f64; 2]) -> Option<[f64; 3]> {
        let (n, d) = self.facing().ok()?;
        let ray = pixel_ray(camera, uv);
        let denom = dot(n, ray.direction);
        if denom == 0.0 {
            return None;
        }
        let t = (d - dot(n, ray.origin)) / denom;
        (t > 0.0 || matches!(camera, Camera::Orthographic { .. })).then(|| ray.at(t))
    }
}

/// The board's albedo model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum BoardAlbedo {
    /// One albedo for the whole board (per channel): a plain linear fit per light.
    #[default]
    Uniform,
    /// One albedo per pixel and channel, shared by all lights (absorbs texture of the board and
    /// vignetting): alternating least squares.
    PerPixel,
}

/// Options of [`calibrate_intensities`].
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub struct IntensityOptions {
    /// Fit each point light's anisotropy mu (>= 0).
    pub fit_mu: bool,
    /// Fit each point light's principal direction (with `fit_mu`).
    pub fit_axis: bool,
    /// The board's albedo model.
    pub albedo: BoardAlbedo,
    /// Observations at or below this value are left out.
    pub dark: f64,
    /// Observations at or above this value are left out.
    pub saturation: f64,
    /// Most alternations (per-pixel albedo) or Levenberg–Marquardt steps.
    pub iterations: usize,
}

impl Default for IntensityOptions {
    fn default() -> Self {
        IntensityOptions {
            fit_mu: false,
            fit_axis: false,
            albedo: BoardAlbedo::Uniform,
            dark: 0.0,
            saturation: f64::INFINITY,
            iterations: 100,
        }
    }
}

with_fields!(IntensityOptions {
    with_fit_mu: fit_mu: bool,
    with_fit_axis: fit_axis: bool,
    with_albedo: albedo: BoardAlbedo,
    with_dark: dark: f64,
    with_saturation: saturation: f64,
    with_iterations: iterations: usize,
});

/// One light's fitted parameters.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct IntensityReport {
    /// Relative intensity per channel (geometric mean 1 over all lights and channels).
    pub intensity: Vec<f64>,
    /// Anisotropy (as given unless fitted; 0 for directional lights).
    pub mu: f64,
    /// Principal direction (as given unless fitted).
    pub axis: [f64; 3],
    /// RMS residual over the light's observations, relative to their mean.
    pub rms: f64,
    /// Observations used (pixels x channels).
    pub observations: usize,
}

/// The result of [`calibrate_intensities`].
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct IntensityCalibration {
    /// The lights with fitted intensities (and mu, axes).
    pub lights: Vec<Light>,
    /// Per-light reports.
    pub reports: Vec<IntensityReport>,
    /// The common factor removed from the intensities (board albedo times exposure, per
    /// channel mean), so that `I = scale * rho_rel * Phi_rel * shading`.
    pub scale: f64,
    /// Relative board albedo per pixel and channel (H x W x C, NaN outside the mask or unused;
    /// all 1 for a uniform board).
    pub albedo: Vec<f64>,
    /// Alternations (or LM iterations) run.
    pub iterations: usize,
    /// Notes and warnings.
    pub warnings: Vec<String>,
}

/// A point light's shading function parameters during the fit.
#[derive(Debug, Clone, Copy)]
struct Shape {
    mu: f64,
    axis: [f64; 3],
}

fn with_shape(light: &Light, shape: Shape) -> Light {
    match *light {
        Light::Point {
            position,
            intensity,
            ..
        } => Light::Point {
            position,
            intensity,
            axis: shape.axis,
            mu: shape.mu,
        },
        other => other,
    }
}

/// Shading `max(0, n . beta(X))` of every board point under `light` (intensity excluded).
fn shading(light: &Light, n: [f64; 3], points: &[[f64; 3]]) -> Vec<f64> {
    points
        .iter()
        .map(|&x| dot(n, light.beta(x).0).max(0.0))
        .collect()
}

/// Per-channel least-squares intensities `Phi_c = sum I rho s / sum (rho s)^2` and the residual
/// sum of squares, over the valid observations.
fn fit_phi(obs: &[(usize, f32)], channels: usize, s: &[f64], rho: &[f64]) -> (Vec<f64>, f64) {
    let mut num = vec![0.0; channels];
    let mut den = vec![0.0; channels];
    for &(j, v) in obs {
        let (p, c) = (j / channels, j % channels);
        let m = rho[j] * s[p];
        num[c] += v as f64 * m;
        den[c] += m * m;
    }
    let phi: Vec<f64> = num
        .iter()
        .zip(&den)
        .map(|(n, d)| if *d > 0.0 { n / d } else { 0.0 })
        .collect();
    let rss = obs
        .iter()
        .map(|&(j, v)| {
            let (p, c) = (j / channels, j % channels);
            (v as f64 - phi[c] * rho[j] * s[p]).powi(2)
        })
        .sum();
    (phi, rss)
}

/// What the board shows of one light: the plane's unit normal `n`, the board points of the
/// pixels, the lit observations `(j, value)` with `j = pixel * channels + channel`, and the
/// albedo `rho[j]` of each pixel and channel.
struct LitBoard<'a> {
    n: [f64; 3],
    points: &'a [[f64; 3]],
    obs: &'a [(usize, f32)],
    channels: usize,
    rho: &'a [f64],
}

/// Levenberg–Marquardt over (mu, axis) of one point light with the intensities eliminated.
fn fit_shape(
    light: &Light,
    start: Shape,
    fit_axis: bool,
    board: &LitBoard<'_>,
    iterations: usize,
) -> (Shape, usize) {
    let LitBoard {
        n,
        points,
        obs,
        channels,
        rho,
    } = *board;
    // Parameters: mu and two tangent offsets of the axis.
    let np = if fit_axis { 3 } else { 1 };
    let residuals = |shape: Shape| -> Vec<f64> {
        let s = shading(&with_shape(light, shape), n, points);
        let (phi, _) = fit_phi(obs, channels, &s, rho);
        obs.iter()
            .map(|&(j, v)| {
                let (p, c) = (j / channels, j % channels);
                v as f64 - phi[c] * rho[j] * s[p]
            })
            .collect()
    };
    let apply = |shape: Shape, delta: &[f64]| -> Shape {
        let mu = (shape.mu + delta[0]).max(0.0);
        let axis = if np == 3 {
            let a = shape.axis;
            let helper = if a[0].abs() < 0.9 {
                [1.0, 0.0, 0.0]
            } else {
                [0.0, 1.0, 0.0]
            };
            let e1 = unit(cross(a, helper));
            let e2 = cross(a, e1);
            unit(add(a, add(scale(e1, delta[1]), scale(e2, delta[2]))))
        } else {
            shape.axis
        };
        Shape { mu, axis }
    };
    let mut shape = start;
    let mut r = residuals(shape);
    let mut cost: f64 = r.iter().map(|v| v * v).sum();
    let mut lambda = 1e-3;
    let mut done = 0;
    for it in 0..iterations {
        done = it + 1;
        // Forward-difference Jacobian.
        let mut jac = vec![vec![0.0; r.len()]; np];
        for (q, col) in jac.iter_mut().enumerate() {
            let h = if q == 0 {
                1e-6 * (1.0 + shape.mu)
            } else {
                1e-7
            };
            let mut delta = vec![0.0; np];
            delta[q] = h;
            let rq = residuals(apply(shape, &delta));
            for (cv, (a, b)) in col.iter_mut().zip(rq.iter().zip(&r)) {
                *cv = (a - b) / h;
            }
        }
        let mut jtj = nalgebra::DMatrix::<f64>::zeros(np, np);
        let mut jtr = nalgebra::DVector::<f64>::zeros(np);
        for a in 0..np {
            for b in 0..np {
                jtj[(a, b)] = jac[a].iter().zip(&jac[b]).map(|(x, y)| x * y).sum();
            }
            jtr[a] = jac[a].iter().zip(&r).map(|(x, y)| x * y).sum();
        }
        let mut improved = false;
        for _ in 0..12 {
            let mut m = jtj.clone();
            for d in 0..np {
                m[(d, d)] += lambda * (jtj[(d, d)] + 1e-12);
            }
            let Some(step) = m.cholesky().map(|c| c.solve(&(-&jtr))) else {
                lambda *= 10.0;
                continue;
            };
            let trial = apply(shape, step.as_slice());
            let rt = residuals(trial);
            let ct: f64 = rt.iter().map(|v| v * v).sum();
            if ct < cost {
                let rel = (cost - ct) / cost.max(1e-300);
                shape = trial;
                r = rt;
                cost = ct;
                lambda = (lambda * 0.3).max(1e-9);
                improved = true;
                if rel < 1e-12 {
                    return (shape, done);
                }
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    (shape, done)
}

/// The board images of [`calibrate_intensities`]: k images of H x W pixels with C channels
/// (k x H x W x C, row-major, the rig's light order) and an optional H x W mask of the board's
/// pixels (`true` = board; None: all).
#[derive(Debug, Clone, Copy)]
pub struct BoardImages<'a> {
    /// The pixel values, k x H x W x C.
    pub images: &'a [f32],
    /// Number of images k (one per light).
    pub k: usize,
    /// Image height H.
    pub height: usize,
    /// Image width W.
    pub width: usize,
    /// Channels C (1 or 3).
    pub channels: usize,
    /// The board's pixels (None: every pixel).
    pub mask: Option<&'a [bool]>,
}

/// Calibrates the light intensities (and optionally LED anisotropy and axes) from k images
/// (k x H x W x C) of a flat diffuse board on `plane`; see the [module documentation](self).
/// `mask` (H x W) selects the board's pixels (None: all). Light positions come from `lights`.
pub fn calibrate_intensities(
    camera: &Camera,
    board: &BoardImages<'_>,
    plane: &Plane,
    lights: &[Light],
    options: &IntensityOptions,
) -> Result<IntensityCalibration> {
    let BoardImages {
        images,
        k,
        height,
        width,
        channels,
        mask,
    } = *board;
    camera.validate()?;
    let (n, _) = plane.facing()?;
    let npx = height * width;
    if lights.len() != k || k == 0 {
        return Err(Error::Shape {
            what: "board images",
            expected: lights.len(),
            got: k,
            message: format!(
                "{k} board images but {} lights in the rig: give one image per light",
                lights.len()
            ),
        });
    }
    if channels != 1 && channels != 3 {
        return Err(Error::OutOfRange {
            name: "channels",
            value: channels as f64,
            message: format!("channels must be 1 or 3, got {channels}"),
        });
    }
    if images.len() != k * npx * channels {
        return Err(Error::Shape {
            what: "board images",
            expected: k
                .saturating_mul(height)
                .saturating_mul(width)
                .saturating_mul(channels),
            got: images.len(),
            message: format!(
                "expected {k} images x {width} x {height} pixels x {channels} channels of values, got {}",
                images.len()
            ),
        });
    }
    if let Some(m) = mask {
        if m.len() != npx {
            return Err(Error::Shape {
                what: "mask",
                expected: height * width,
                got: m.len(),
                message: format!(
                    "the mask has {} pixels, the images {width} x {height}",
                    m.len()
                ),
            });
        }
    }
    if images.iter().any(|v| !v.is_finite()) {
        return Err(Error::Unusable(
            "the board images contain non-finite values".into(),
        ));
    }
    Rig {
        camera: *camera,
        lights: lights.to_vec(),
    }
    .validate_parameters()?;
    // Board points of the masked pixels.
    let mut pixels = Vec::new();
    let mut points = Vec::new();
    for p in 0..npx {
        if mask.is_some_and(|m| !m[p]) {
            continue;
        }
        if let Some(x) = plane.intersect(camera, [(p % width) as f64, (p / width) as f64]) {
            pixels.push(p);
            points.push(x);
        }
    }
    if pixels.is_empty() {
        return Err(Error::Unusable(
            "no board pixel: the mask is empty or the plane is behind the camera".into(),
        ));
    }
    let m = pixels.len();
    let mut warnings = Vec::new();
    // Initial shapes.
    let centroid = scale(
        points.iter().fold([0.0; 3], |a, &x| add(a, x)),
        1.0 / m as f64,
    );
    let mut shapes: Vec<Shape> = lights
        .iter()
        .map(|l| match *l {
            Light::Point {
                position, axis, mu, ..
            } => {
                let axis = if mu > 0.0 || !options.fit_axis {
                    axis
                } else {
                    unit(sub(centroid, position))
                };
                let mu = if options.fit_mu && mu == 0.0 { 1.0 } else { mu };
                Shape { mu, axis }
            }
            Light::Directional { .. } => Shape {
                mu: 0.0,
                axis: [0.0, 0.0, 1.0],
            },
        })
        .collect();
    // Valid observations per light: (index into the m x C albedo, value).
    let value = |i: usize, q: usize, c: usize| images[(i * npx + pixels[q]) * channels + c];
    let valid = |v: f32| (v as f64) > options.dark && (v as f64) < options.saturation;
    let obs: Vec<Vec<(usize, f32)>> = (0..k)
        .map(|i| {
            (0..m)
                .flat_map(|q| (0..channels).map(move |c| (q, c)))
                .filter_map(|(q, c)| {
                    let v = value(i, q, c);
                    valid(v).then_some((q * channels + c, v))
                })
                .collect()
        })
        .collect();
    let mut rho = vec![1.0; m * channels];
    let is_point = |l: &Light| matches!(l, Light::Point { .. });
    let fit_any_shape = options.fit_mu;
    let mut phi = vec![vec![0.0; channels]; k];
    let mut s_all: Vec<Vec<f64>> = (0..k)
        .map(|i| shading(&with_shape(&lights[i], shapes[i]), n, &points))
        .collect();
    let outer = match options.albedo {
        BoardAlbedo::Uniform => 1,
        BoardAlbedo::PerPixel => options.iterations.max(1),
    };
    let mut iterations = 0;
    let mut last_rss = f64::INFINITY;
    for it in 0..outer {
        iterations = it + 1;
        let mut rss_total = 0.0;
        for i in 0..k {
            // Observations the model lights (s > 0) count.
            let lit: Vec<(usize, f32)> = obs[i]
                .iter()
                .copied()
                .filter(|&(j, _)| s_all[i][j / channels] > 0.0)
                .collect();
            if lit.len() < 3 {
                return Err(Error::Unusable(format!(
                    "light {i}: fewer than 3 usable board pixels (all dark, saturated, or facing away from the light)"
                )));
            }
            if fit_any_shape && is_point(&lights[i]) {
                let board = LitBoard {
                    n,
                    points: &points,
                    obs: &lit,
                    channels,
                    rho: &rho,
                };
                let (shape, steps) = fit_shape(
                    &lights[i],
                    shapes[i],
                    options.fit_axis,
                    &board,
                    if options.albedo == BoardAlbedo::Uniform {
                        options.iterations
                    } else {
                        3
                    },
                );
                if options.albedo == BoardAlbedo::Uniform {
                    iterations = iterations.max(steps);
                }
                shapes[i] = shape;
                s_all[i] = shading(&with_shape(&lights[i], shape), n, &points);
            }
            let (p, rss) = fit_phi(&lit, channels, &s_all[i], &rho);
            phi[i] = p;
            rss_total += rss;
        }
        if options.albedo == BoardAlbedo::Uniform {
            break;
        }
        // Albedo step: rho_j = sum_i I Phi s / sum_i (Phi s)^2 per pixel and channel.
        let mut num = vec![0.0; m * channels];
        let mut den = vec![0.0; m * channels];
        for i in 0..k {
            for &(j, v) in &obs[i] {
                let a = phi[i][j % channels] * s_all[i][j / channels];
                if a > 0.0 {
                    num[j] += v as f64 * a;
                    den[j] += a * a;
                }
            }
        }
        for j in 0..m * channels {
            rho[j] = if den[j] > 0.0 {
                num[j] / den[j]
            } else {
                f64::NAN
            };
        }
        // Fix the gauge: mean albedo 1 per channel (NaN pixels excluded from the fits).
        for c in 0..channels {
            let vals: Vec<f64> = (0..m)
                .map(|q| rho[q * channels + c])
                .filter(|v| v.is_finite())
                .collect();
            let mean = vals.iter().sum::<f64>() / vals.len().max(1) as f64;
            if mean > 0.0 {
                for q in 0..m {
                    rho[q * channels + c] /= mean;
                }
            }
        }
        for r in rho.iter_mut() {
            if !r.is_finite() {
                *r = 0.0;
            }
        }
        if (last_rss - rss_total).abs() <= 1e-12 * rss_total.max(1e-300) {
            break;
        }
        last_rss = rss_total;
    }
    // Normalise: geometric mean 1 over all lights and channels.
    let logs: Vec<f64> = phi.iter().flatten().map(|v| v.ln()).collect();
    if logs.iter().any(|v| !v.is_finite()) {
        return Err(Error::Unusable(
            "a light's fitted intensity is zero or negative: its board images are dark where the model says it is lit (wrong position or plane?)".into(),
        ));
    }
    let scale = (logs.iter().sum::<f64>() / logs.len() as f64).exp();
    let mut out_lights = Vec::with_capacity(k);
    let mut reports = Vec::with_capacity(k);
    for i in 0..k {
        let rel: Vec<f64> = phi[i].iter().map(|v| v / scale).collect();
        let intensity = if channels == 1 {
            [rel[0]; 3]
        } else {
            [rel[0], rel[1], rel[2]]
        };
        let light = match lights[i] {
            Light::Point { position, .. } => Light::Point {
                position,
                intensity,
                axis: shapes[i].axis,
                mu: shapes[i].mu,
            },
            Light::Directional { direction, .. } => Light::Directional {
                direction,
                intensity,
            },
        };
        let (mut ss, mut sv, mut count) = (0.0, 0.0, 0usize);
        for &(j, v) in &obs[i] {
            let (q, c) = (j / channels, j % channels);
            if s_all[i][q] > 0.0 {
                ss += (v as f64 - phi[i][c] * rho[j] * s_all[i][q]).powi(2);
                sv += v as f64;
                count += 1;
            }
        }
        let rms = (ss / count.max(1) as f64).sqrt() / (sv / count.max(1) as f64);
        if options.fit_mu && is_point(&lights[i]) && shapes[i].mu == 0.0 {
            warnings.push(format!(
                "light {i}: the fitted anisotropy is at its bound mu = 0 (an isotropic light)"
            ));
        }
        if count < 100 {
            warnings.push(format!(
                "light {i}: only {count} board observations are usable"
            ));
        }
        reports.push(IntensityReport {
            intensity: rel,
            mu: shapes[i].mu,
            axis: shapes[i].axis,
            rms,
            observations: count,
        });
        out_lights.push(light);
    }
    let mut albedo = vec![f64::NAN; npx * channels];
    for (q, &p) in pixels.iter().enumerate() {
        for c in 0..channels {
            albedo[p * channels + c] = rho[q * channels + c];
        }
    }
    Ok(IntensityCalibration {
        lights: out_lights,
        reports,
        scale,
        albedo,
        iterations,
        warnings,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pinhole() -> Camera {
        Camera::Pinhole {
            k: [[400.0, 0.0, 99.5], [0.0, 410.0, 95.5], [0.0, 0.0, 1.0]],
            distortion: [0.0; 5],
        }
    }

    /// Pixel-centre-sampled disc mask (label 1) of an ellipse-free circle.
    fn disc(h: usize, w: usize, c: [f64; 2], r: f64) -> Vec<u32> {
        (0..h * w)
            .map(|p| {
                let (u, v) = ((p % w) as f64, (p / w) as f64);
                u32::from((u - c[0]).powi(2) + (v - c[1]).powi(2) <= r * r)
            })
            .collect()
    }

    #[test]
    fn circle_fit_is_exact_on_a_circle_and_robust_to_outliers() {
        let mut pts: Vec<[f64; 2]> = (0..60)
            .map(|i| {
                let a = i as f64 * 0.1;
                [3.0 + 7.0 * a.cos(), -2.0 + 7.0 * a.sin()]
            })
            .collect();
        let c = fit_circle(&pts).unwrap();
        assert!((c.center[0] - 3.0).abs() < 1e-10 && (c.center[1] + 2.0).abs() < 1e-10);
        assert!((c.radius - 7.0).abs() < 1e-10 && c.rms < 1e-9);
        // Five wild points do not move it.
        pts.extend([
            [30.0, 30.0],
            [3.0, -2.0],
            [4.0, 0.0],
            [20.0, -2.0],
            [0.0, 0.0],
        ]);
        let c = fit_circle(&pts).unwrap();
        assert!((c.radius - 7.0).abs() < 1e-6, "{c:?}");
        assert_eq!(c.inliers, 60);
        assert!(fit_circle(&[[0.0, 0.0], [1.0, 1.0], [2.0, 2.0], [3.0, 3.0], [4.0, 4.0]]).is_err());
        assert!(fit_circle(&pts[..3]).is_err());
    }

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
    fn separating_fits_locate_pixel_sampled_discs_and_spheres() {
        // Orthographic: discs at random sub-pixel positions; the widest separating circle is
        // about three times more precise than the least-squares fit to the crack midpoints.
        let (h, w) = (110, 110);
        let mut state = 7u64;
        let mut uniform = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let (mut ls, mut lp) = (0.0, 0.0);
        let n = 40;
        for _ in 0..n {
            let c = [55.0 + 2.0 * uniform() - 1.0, 55.0 + 2.0 * uniform() - 1.0];
            let r = 40.0 + 2.0 * uniform() - 1.0;
            let labels = disc(h, w, c, r);
            let start = fit_circle(&mask_boundary(&labels, h, w, 1)).unwrap();
            let (ins, outs) = mask_edge_pixels(&labels, h, w, 1);
            let best = separating_circle(&ins, &outs, &start).unwrap();
            ls += (start.center[0] - c[0]).powi(2) + (start.center[1] - c[1]).powi(2);
            lp += (best.center[0] - c[0]).powi(2) + (best.center[1] - c[1]).powi(2);
            assert!((best.radius - r).abs() < 0.05);
        }
        let (ls, lp) = ((ls / n as f64).sqrt(), (lp / n as f64).sqrt());
        assert!(
            lp < 0.02 && lp < 0.5 * ls,
            "centre RMS: least squares {ls} px, separating {lp} px"
        );
        // A notched mask is no pixel sampling of a circle: no separating circle.
        let mut notched = disc(h, w, [55.3, 54.8], 40.0);
        notched[55 * w + 20] = 0;
        notched[55 * w + 21] = 0;
        notched[54 * w + 20] = 0;
        let start = fit_circle(&mask_boundary(&notched, h, w, 1)).unwrap();
        let (ins, outs) = mask_edge_pixels(&notched, h, w, 1);
        assert!(separating_circle(&ins, &outs, &start).is_none());
        // Pinhole (30-pixel images): the widest separating cone of the mask's edge pixels puts the
        // centre within 0.12 % of its distance, better than the least-squares cone on average.
        let cam = pinhole();
        let (mut worst, mut sum_lp, mut sum_ls) = (0.0f64, 0.0, 0.0);
        for i in 0..6 {
            let centre = [
                -30.0 + 12.0 * i as f64 + uniform(),
                20.0 * uniform() - 10.0,
                250.0 + 20.0 * uniform(),
            ];
            let mut labels = vec![0u32; 200 * 200];
            for (p, l) in labels.iter_mut().enumerate() {
                let ray = pixel_ray(&cam, [(p % 200) as f64, (p / 200) as f64]);
                *l = u32::from(ray.distance_to(centre) <= 20.0);
            }
            let (sphere, digital) =
                locate_sphere_in_mask(&cam, &labels, 200, 200, 1, 20.0, None).unwrap();
            let lsq =
                locate_sphere(&cam, &mask_boundary(&labels, 200, 200, 1), 20.0, None).unwrap();
            assert!(digital);
            let err = norm(sub(sphere.center, centre)) / norm(centre);
            worst = worst.max(err);
            sum_lp += err;
            sum_ls += norm(sub(lsq.center, centre)) / norm(centre);
        }
        assert!(worst < 1.2e-3 && sum_lp < 0.5 * sum_ls, "relative centre errors: worst {worst}, sums {sum_lp} (separating), {sum_ls} (least squares)");
    }

    #[test]
    fn cone_fit_locates_an_off_axis_sphere_exactly() {
        let cam = pinhole();
        let (centre, radius) = ([45.0, -30.0, 260.0], 20.0);
        // Exact outline: rays tangent to the sphere.
        let d = norm(centre);
        let a = unit(centre);
        let half = (radius / d).asin();
        let e1 = unit(cross(a, [0.0, 1.0, 0.0]));
        let e2 = cross(a, e1);
        let outline: Vec<[f64; 2]> = (0..100)
            .map(|i| {
                let phi = i as f64 * 0.0628;
                let dir = add(
                    scale(a, half.cos()),
                    scale(add(scale(e1, phi.cos()), scale(e2, phi.sin())), half.sin()),
                );
                project(&cam, dir)
            })
            .collect();
        let s = locate_sphere(&cam, &outline, radius, None).unwrap();
        assert!(norm(sub(s.center, centre)) < 1e-8, "{:?}", s.center);
        assert!(s.fit_rms < 1e-6);
        // With a given depth the centre moves along the axis to it.
        let s = locate_sphere(&cam, &outline, radius, Some(300.0)).unwrap();
        assert!((s.center[2] - 300.0).abs() < 1e-9 && s.scale_check < 1.0);
        // A pixel-sampled mask of the exact image (an ellipse) gives the centre within 0.05 %.
        let (h, w) = (200, 200);
        let mut labels = vec![0u32; h * w];
        for (p, l) in labels.iter_mut().enumerate() {
            let ray = pixel_ray(&cam, [(p % w) as f64, (p / w) as f64]);
            *l = u32::from(ray.distance_to(centre) <= radius);
        }
        let s = locate_sphere(&cam, &mask_boundary(&labels, h, w, 1), radius, None).unwrap();
        let err = norm(sub(s.center, centre)) / d;
        assert!(err < 5e-4, "relative centre error {err}");
    }

    #[test]
    fn reflection_and_ray_sphere() {
        let n = unit([0.0, -1.0, -1.0]);
        let r = reflect([0.0, 0.0, 1.0], n);
        assert!(norm(sub(r, [0.0, -1.0, 0.0])) < 1e-15);
        let ray = Ray {
            origin: [0.0; 3],
            direction: [0.0, 0.0, 1.0],
        };
        let x = ray_sphere(&ray, [0.0, 0.0, 10.0], 2.0).unwrap();
        assert!((x[2] - 8.0).abs() < 1e-12);
        assert!(ray_sphere(&ray, [5.0, 0.0, 10.0], 2.0).is_none());
        // The mirror ray from a sphere point towards a light comes back to it.
        let cam = Camera::Orthographic {
            pixel_size: [0.5, 0.5],
            origin: [-20.0, -20.0],
        };
        let sphere = Sphere {
            placement: 0,
            center: [1.0, 2.0, 100.0],
            radius: 10.0,
            image_center: project(&cam, [1.0, 2.0, 100.0]),
            image_radius: 20.0,
            fit_rms: 0.0,
            outline_points: [0, 0],
            scale_check: 1.0,
            shift: 0.0,
            outline_sigma: OUTLINE_FIT_SIGMA,
        };
        let light = [30.0, -40.0, 20.0];
        // The surface point whose normal bisects the view (-z) and the light direction.
        let mut n = [0.0, 0.0, -1.0];
        for _ in 0..50 {
            let x = add(sphere.center, scale(n, sphere.radius));
            n = unit(add([0.0, 0.0, -1.0], unit(sub(light, x))));
        }
        let x = add(sphere.center, scale(n, sphere.radius));
        let (_, _, ray) = reflected_ray(&cam, &sphere, project(&cam, x)).unwrap();
        assert!(ray.distance_to(light) < 1e-9);
    }

    #[test]
    fn nearest_point_of_rays_and_parallel_rays() {
        let p = [3.0, -4.0, 5.0];
        let origins = [[0.0, 0.0, 100.0], [50.0, 10.0, 90.0], [-30.0, 40.0, 110.0]];
        let rays: Vec<Ray> = origins
            .iter()
            .map(|&o| Ray {
                origin: o,
                direction: unit(sub(p, o)),
            })
            .collect();
        let (q, rms) = nearest_point(&rays).unwrap();
        assert!(norm(sub(p, q)) < 1e-9 && rms < 1e-9);
        let report = locate_light(&rays, 0.5f64.to_radians());
        assert!(matches!(report.estimate, LightEstimate::Point(_)) && report.warning.is_none());
        // Two skew lines: the midpoint of their shortest segment.
        let a = Ray {
            origin: [0.0, 0.0, 0.0],
            direction: [1.0, 0.0, 0.0],
        };
        let b = Ray {
            origin: [0.0, 0.0, 2.0],
            direction: [0.0, 1.0, 0.0],
        };
        let (q, rms) = nearest_point(&[a, b]).unwrap();
        assert!(norm(sub(q, [0.0, 0.0, 1.0])) < 1e-12 && (rms - 1.0).abs() < 1e-12);
        // Parallel rays: no point; locate_light returns the direction.
        let d = unit([0.2, -0.1, -1.0]);
        let par: Vec<Ray> = origins
            .iter()
            .map(|&o| Ray {
                origin: o,
                direction: d,
            })
            .collect();
        assert!(nearest_point(&par).is_none());
        let report = locate_light(&par, 0.5f64.to_radians());
        match report.estimate {
            LightEstimate::Directional(e) => assert!(angle(e, d) < 1e-12),
            other => panic!("{other:?}"),
        }
        // Nearly parallel (far light, 0.1 deg apart) is directional within the tolerance.
        let far = [1e5, -3e4, -1e6];
        let rays: Vec<Ray> = origins
            .iter()
            .map(|&o| Ray {
                origin: o,
                direction: unit(sub(far, o)),
            })
            .collect();
        assert!(matches!(
            locate_light(&rays, 0.5f64.to_radians()).estimate,
            LightEstimate::Directional(_)
        ));
        // One ray: a direction with a warning; none: missing.
        let one = locate_light(&rays[..1], 0.01);
        assert!(matches!(one.estimate, LightEstimate::Directional(_)) && one.warning.is_some());
        assert!(matches!(
            locate_light(&[], 0.01).estimate,
            LightEstimate::Missing
        ));
        // Diverging rays (nearest point behind the spheres) are not a point light.
        let div = [
            Ray {
                origin: [0.0, 0.0, 0.0],
                direction: unit([0.1, 0.0, -1.0]),
            },
            Ray {
                origin: [10.0, 0.0, 0.0],
                direction: unit([0.3, 0.0, -1.0]),
            },
        ];
        let rep = locate_light(&div, 0.001);
        assert!(matches!(rep.estimate, LightEstimate::Directional(_)) && rep.warning.is_some());
    }

    #[test]
    fn components_and_highlight_centroid() {
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
                            let ray = pixel_ray(&camera, uv);
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
                    let ray = pixel_ray(&camera, [(p % w) as f64, (p / w) as f64]);
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
            sphere.image_center = project(&camera, center);
            let truth = project(&camera, add(center, scale(n_m, radius)));
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

    #[test]
    fn intensity_fit_recovers_relative_intensities_and_mu() {
        let cam = Camera::Orthographic {
            pixel_size: [2.0, 2.0],
            origin: [-40.0, -40.0],
        };
        let (h, w) = (40, 40);
        let plane = Plane::at_depth(150.0);
        let lights = vec![
            Light::Point {
                position: [30.0, 0.0, 0.0],
                intensity: [2.0; 3],
                axis: unit([-0.2, 0.0, 1.0]),
                mu: 1.5,
            },
            Light::Point {
                position: [-30.0, 10.0, 20.0],
                intensity: [0.5; 3],
                axis: unit([0.2, -0.1, 1.0]),
                mu: 0.7,
            },
            Light::Directional {
                direction: unit([0.3, 0.2, -1.0]),
                intensity: [1e-4; 3],
            },
        ];
        let rho = 3e4;
        let mut images = Vec::new();
        for l in &lights {
            for p in 0..h * w {
                let x = plane
                    .intersect(&cam, [(p % w) as f64, (p / w) as f64])
                    .unwrap();
                let s = dot([0.0, 0.0, -1.0], l.beta(x).0).max(0.0);
                images.push((rho * l.intensity()[0] * s) as f32);
            }
        }
        let truth: Vec<f64> = lights.iter().map(|l| l.intensity()[0]).collect();
        let gm = truth.iter().map(|v| v.ln()).sum::<f64>() / 3.0;
        let start: Vec<Light> = lights
            .iter()
            .map(|l| match *l {
                Light::Point { position, .. } => Light::point(position),
                other => other,
            })
            .collect();
        let options = IntensityOptions {
            fit_mu: true,
            fit_axis: true,
            ..IntensityOptions::default()
        };
        let board = |images| BoardImages {
            images,
            k: 3,
            height: h,
            width: w,
            channels: 1,
            mask: None,
        };
        let cal = calibrate_intensities(&cam, &board(&images), &plane, &start, &options).unwrap();
        for (i, rep) in cal.reports.iter().enumerate() {
            let expected = truth[i] / gm.exp();
            assert!(
                (rep.intensity[0] / expected - 1.0).abs() < 1e-4,
                "light {i}: {rep:?}"
            );
        }
        for (rep, l) in cal.reports.iter().zip(&lights) {
            if let Light::Point { mu, axis, .. } = *l {
                assert!((rep.mu - mu).abs() < 1e-3, "{rep:?}");
                assert!(angle(rep.axis, axis) < 1e-3, "{rep:?}");
            }
        }
        // Per-pixel albedo: a textured board gives the same relative intensities.
        let texture: Vec<f64> = (0..h * w)
            .map(|p| 1.0 + 0.3 * ((p % 7) as f64 / 7.0))
            .collect();
        let textured: Vec<f32> = images
            .iter()
            .enumerate()
            .map(|(j, v)| (*v as f64 * texture[j % (h * w)]) as f32)
            .collect();
        let options = IntensityOptions {
            albedo: BoardAlbedo::PerPixel,
            iterations: 500,
            ..IntensityOptions::default()
        };
        let cal =
            calibrate_intensities(&cam, &board(&textured), &plane, &lights, &options).unwrap();
        for (i, rep) in cal.reports.iter().enumerate() {
            let expected = truth[i] / gm.exp();
            assert!(
                (rep.intensity[0] / expected - 1.0).abs() < 1e-4,
                "light {i}: {rep:?}"
            );
        }
        // Bad input is an error, not a panic.
        assert!(
            calibrate_intensities(&cam, &board(&images[..10]), &plane, &lights, &options).is_err()
        );
        let edge_on = Plane {
            normal: [1.0, 0.0, 0.0],
            offset: 0.0,
        };
        assert!(calibrate_intensities(&cam, &board(&images), &edge_on, &lights, &options).is_err());
    }
}
