//! # nplps — photometric stereo with near point lighting
//!
//! Recovers a metric mesh, normals and albedo from k images of a still object, each lit by one
//! point light close to it, by the mesh-deformation method of Xie, Dai & Wang, "Photometric
//! Stereo with Near Point Lighting: A Solution by Mesh Deformation" (CVPR 2015).
//!
//! Each pixel is a quad facet whose corners are shared mesh vertices with unknown depth. A
//! [local step](local) fits every facet's normal under the near-light image model
//! `I_k = rho * max(0, n . (p_k - x)) / |p_k - x|^3` and turns it into target corner depths; a
//! [global step](global) glues the facets back together with one sparse least-squares system,
//! factored once per mask; the [solver] alternates the two until the depths converge. Pinhole
//! cameras ([geometry]: log-depth unknowns), LEDs and directional lights ([rig]), colour and
//! robust fits ([local]), depth priors ([global]) and the estimation of the working distance from
//! the images ([distance]) extend the paper's setting. At camera resolution the global system is
//! solved by conjugate gradients with a [multigrid] preconditioner (linear time and memory in the
//! pixels; [`GlobalSolver`]), and the solver runs coarse-to-fine over an image [pyramid]
//! ([`Options::levels`]).
//!
//! The lower modules build on each other bottom up, each using only those listed before it (and
//! [`error`]):
//! `vec3` (the crate's 3-vector helpers: `sub`, `dot`, `cross`, `normalize`, ...); [`rig`] (the
//! camera and the lights) and [`grid`] (the mesh's connectivity: which pixel corners are unknowns,
//! the regions), which do not use each other; [`geometry`] (where the vertices are under the
//! camera, and the facets' corners, normals and centres); then [`local`] (the per-facet fits),
//! on which the solver's modules build.
//!
//! Camera frame as in OpenCV: x right (increasing column), y down (increasing row), z forward;
//! depth = z; normals face the camera (n_z < 0). Units are the user's.
//!
//! ```
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
