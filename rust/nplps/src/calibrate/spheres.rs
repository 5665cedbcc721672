//! The whole sphere calibration, steps 1 to 6 of the [module documentation](super) in order:
//! per placement the composite image, the spheres (labels or detection), their outlines and 3-D
//! positions; per light and sphere the highlight; per light the position from its mirror rays;
//! then, optionally, the joint refinement and the lights again from the refined spheres.

use super::bundle::{refine_spheres, HighlightPixel, Refinement};
use super::detection::{detect_spheres, sphere_labels, Detection};
use super::fits::fit_circle;
use super::highlight::{
    correct_highlight, find_highlight_in, sphere_region, Highlight, HighlightOptions, Rejection,
};
use super::outline::{image_outline, mask_boundary};
use super::rays::reflected_ray;
use super::sphere::{locate_sphere, locate_sphere_in_mask, Sphere};
use super::triangulation::{locate_light, LightEstimate, LightReport};
use crate::error::{Error, Result};
use crate::rig::{Camera, Light, Ray, Rig};

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
    /// [module documentation](super)). Default true.
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

/// Calibrates the lights from mirror-sphere images (see the [module documentation](super)).
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
