//! # nplps — photometric stereo with near point lighting
//!
//! Recovers a metric mesh, normals and albedo from k images of a still object, each lit by one
//! point light close to it, by the mesh-deformation method of Xie, Dai & Wang, "Photometric
//! Stereo with Near Point Lighting: A Solution by Mesh Deformation" (CVPR 2015).
//!
//! Each pixel is a quad facet whose corners are shared mesh vertices with unknown depth. A local
//! step fits every facet's normal under the near-light image model
//! `I_k = rho * max(0, n . (p_k - x)) / |p_k - x|^3` and turns it into target corner depths; a
//! global step glues the facets back together with one sparse least-squares system, factored
//! once per mask; [`reconstruct`] alternates the two until the depths converge. Pinhole cameras
//! (log-depth unknowns), LEDs and directional lights ([`Light`]), colour and robust fits
//! ([`Robust`]), depth priors ([`Problem::set_prior`]) and the estimation of the working distance
//! from the images ([`reconstruct_auto`]) extend the paper's setting. At camera resolution the
//! global system is solved by conjugate gradients with a multigrid preconditioner (linear time
//! and memory in the pixels; [`GlobalSolver`]), and the solver runs coarse-to-fine over an image
//! pyramid ([`Options::levels`]).
//!
//! ## The public surface
//!
//! - Input: [`Rig`] ([`Camera`], [`Light`]), [`ImageStack`], [`InitialDepth`], [`Problem`]
//!   (validated once; [`Problem::with_cancel`] takes a [`Cancel`] token), [`Options`] (built from
//!   [`Options::default`] with `with_*` methods, or by setting its public fields).
//! - Running: [`reconstruct`], [`reconstruct_auto`] (with a [`DistanceSearch`]),
//!   [`reconstruct_parallel`] (the parallel-light baseline); a progress callback gets
//!   [`IterationStats`] and returns [`Control`].
//! - Output: [`Reconstruction`] with its [`Status`], [`Timings`] and, when the lights are refined
//!   ([`Refine`]), a [`RefinementReport`]; [`DistanceEstimate`].
//! - The image model: [`render`], [`predict`] (of a [`Surface`]), [`vertices`], [`mesh_normals`].
//! - Light calibration from sphere and board images: the [`calibrate`] module.
//! - Errors: [`Error`] (non-exhaustive; input errors say which array or parameter is wrong),
//!   [`Result`]; memory is checked before the large allocations ([`check_memory`]).
//! - Cargo features: `synth` (off by default) adds synthetic scenes with ground truth (`Scene`,
//!   `SceneKind`, `SceneOptions`, and the `calibration_scene` module).
//!
//! Inside, the modules build on each other bottom up: the 3-vector helpers; the rig and the
//! mesh connectivity (which pixel corners are unknowns, the regions), which do not use each
//! other; the geometry (where the vertices are under the camera, and the facets' corners, normals
//! and centres); the per-facet fits; then the global step, the solver, the pyramid, the light
//! refinement and the distance search. All of them are private to the crate.
//!
//! Camera frame as in OpenCV: x right (increasing column), y down (increasing row), z forward;
//! depth = z; normals face the camera (n_z < 0). Units are the user's.
//!
//! ```
//! # #[cfg(feature = "synth")] {
//! use nplps::{reconstruct, ImageStack, InitialDepth, Options, Problem, Scene, SceneKind};
//!
//! // A synthetic saddle, 32 x 32 pixels, 100 mm wide, 200 mm away, 27 lights.
//! let scene = Scene::new(SceneKind::Saddle, 32, 100.0, 200.0, 0).unwrap();
//! let images: Vec<f32> = scene.render().unwrap().iter().map(|&v| v as f32).collect();
//! let stack = ImageStack::new(&images, scene.rig.n_lights(), 32, 32).unwrap();
//! let problem = Problem::new(stack, &scene.rig, None, InitialDepth::Distance(scene.mean_depth())).unwrap();
//! let options = Options::default().with_iterations(50).with_tol(1e-9);
//! let result = reconstruct(&problem, &options, &mut |_| nplps::Control::Continue).unwrap();
//! let err = result.depth.iter().zip(&scene.depth).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
//! assert!(err < 0.1, "max depth error {err} mm");
//! # }
//! ```

#![warn(missing_docs)]

/// `with_FIELD(value)` builder methods on a `#[non_exhaustive]` options struct (which other crates
/// cannot build with a struct literal): `Options::default().with_iterations(50)`.
macro_rules! with_fields {
    ($t:ty { $($method:ident: $field:ident: $ty:ty),* $(,)? }) => {
        impl $t {
            $(
                #[doc = concat!("These options with [`", stringify!($field), "`](Self::", stringify!($field), ") set to `value`.")]
                #[must_use]
                pub fn $method(mut self, value: $ty) -> Self {
                    self.$field = value;
                    self
                }
            )*
        }
    };
}

mod anderson;
mod baseline;
pub mod calibrate;
#[cfg(feature = "synth")]
pub mod calibration_scene;
mod cancel;
mod distance;
mod error;
mod geometry;
mod global;
mod grid;
mod local;
mod memory;
mod multigrid;
mod ordering;
mod problem;
mod pyramid;
mod refine;
mod render;
mod rig;
mod solver;
#[cfg(feature = "synth")]
mod synth;
mod vec3;

pub use baseline::reconstruct_parallel;
pub use cancel::Cancel;
pub use distance::{estimate_distance, reconstruct_auto, DistanceEstimate, DistanceSearch};
pub use error::{g6, Error, Result};
pub use global::GlobalSolver;
pub use local::{Robust, Weighting};
pub use memory::check_memory;
pub use multigrid::MAX_ITERATIONS as MULTIGRID_MAX_ITERATIONS;
pub use problem::{ImageStack, InitialDepth, Problem};
pub use refine::{Conditioning, Refine};
pub use render::{mesh_normals, predict, render, vertices, Surface};
pub use rig::{Camera, Light, Rig, MAX_LIGHTS};
pub use solver::{
    reconstruct, Control, IterationStats, Options, Reconstruction, RefinementReport, Status,
    Timings,
};
#[cfg(feature = "synth")]
pub use synth::{Scene, SceneKind, SceneOptions};
