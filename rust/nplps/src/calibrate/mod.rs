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
//! `I_i(X) = rho(X) Phi_i max(0, n . beta_i(X))` ([`Light::beta`](crate::Light::beta)). With a uniform board
//! (`rho` constant) `Phi_i rho` is a one-parameter linear least-squares fit per light and
//! channel; with [`BoardAlbedo::PerPixel`] the board's albedo (which also absorbs vignetting) is
//! estimated per pixel by alternating least squares (rank-one factorisation). `rho` and the
//! exposure are not separable from `Phi`: the intensities are relative, scaled to a geometric
//! mean of 1 over all lights and channels. Optionally each LED's anisotropy `mu` and principal
//! direction are fitted too, by Levenberg–Marquardt with the intensities eliminated (variable
//! projection).
//!
//! # Where the code is
//!
//! One private module per concept, each with the maths it implements in its own documentation:
//! `fits` (robust circle and cone fits, widest-margin separating fits), `outline` (outline
//! points from masks and images), `detection` (the spheres in a label image or the composite),
//! `sphere` (step 2), `highlight` (step 3), `rays` (step 4), `triangulation` (step 5), `bundle`
//! (step 6), `spheres` ([`calibrate_spheres`], the steps in order) and `intensity`
//! ([`calibrate_intensities`]). The viewing rays and the projection are the camera's
//! (`Camera::ray`, `Camera::project` in `crate::rig`).

mod bundle;
mod detection;
mod fits;
mod highlight;
mod intensity;
mod outline;
mod rays;
mod sphere;
mod spheres;
mod triangulation;

pub use crate::rig::Ray;
pub use bundle::Refinement;
pub use detection::Detection;
pub use highlight::{find_highlight, Highlight, HighlightOptions, Rejection};
pub use intensity::{
    calibrate_intensities, BoardAlbedo, BoardImages, IntensityCalibration, IntensityOptions,
    IntensityReport, Plane,
};
#[cfg(feature = "synth")]
pub(crate) use rays::{ray_sphere, reflect};
pub use sphere::Sphere;
pub use spheres::{
    calibrate_spheres, Observation, Outline, Placement, SphereCalibration, SphereOptions,
    SphereSource,
};
pub use triangulation::{LightEstimate, LightReport};

/// Shared test fixtures of the calibration modules.
#[cfg(test)]
mod testing {
    use crate::rig::Camera;

    /// A 200 x 200 pinhole camera with different focal lengths and an off-centre principal point.
    pub(super) fn pinhole() -> Camera {
        Camera::Pinhole {
            k: [[400.0, 0.0, 99.5], [0.0, 410.0, 95.5], [0.0, 0.0, 1.0]],
            distortion: [0.0; 5],
        }
    }

    /// Pixel-centre-sampled disc mask (label 1) of an ellipse-free circle.
    pub(super) fn disc(h: usize, w: usize, c: [f64; 2], r: f64) -> Vec<u32> {
        (0..h * w)
            .map(|p| {
                let (u, v) = ((p % w) as f64, (p / w) as f64);
                u32::from((u - c[0]).powi(2) + (v - c[1]).powi(2) <= r * r)
            })
            .collect()
    }
}
