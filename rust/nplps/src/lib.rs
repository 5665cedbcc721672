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
//!   [`IterationStats`] (with [`SearchProgress`] while the distance search evaluates a
//!   candidate) and returns [`Control`].
//! - Output: [`Reconstruction`] with its [`Status`], [`Timings`], its [`Trust`] (per-pixel normal
//!   uncertainty and leave-one-light-out error, per-light residuals: [`LightTrust`]) and, when
//!   the lights are refined ([`Refine`]), a [`RefinementReport`]; [`DistanceEstimate`].
//! - The image model: [`render`](fn@render), [`predict`] (of a [`Surface`]), [`vertices`], [`mesh_normals`].
//! - Light calibration from sphere and board images: the [`calibrate`] module.
//! - Files (feature `io`, on by default): the `io` module reads rig files and PNG images.
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
//! ## A native application
//!
//! With the `io` feature (on by default) an application reads a rig file and PNG images and
//! reconstructs. Here the files are made first: 16-bit images of a dome rendered by the model.
//!
//! ```
//! # #[cfg(feature = "io")] {
//! use std::path::PathBuf;
//! use nplps::{io, reconstruct, Control, ImageStack, InitialDepth, Options, Problem, Surface};
//!
//! let dir = std::env::temp_dir().join(format!("nplps-doc-{}", std::process::id()));
//! std::fs::create_dir_all(&dir).unwrap();
//! // The rig file: an orthographic camera (1 mm pixels) and 8 LEDs 100 mm in front of the object.
//! let lights: Vec<String> = (0..8)
//!     .map(|i| {
//!         let a = i as f64 * std::f64::consts::FRAC_PI_4;
//!         format!(r#"{{"type": "point", "position": [{}, {}, 0], "intensity": 8000}}"#,
//!                 60.0 * a.cos(), 60.0 * a.sin())
//!     })
//!     .collect();
//! let rig_file = dir.join("rig.json");
//! std::fs::write(&rig_file, format!(
//!     r#"{{"version": 2, "camera": {{"model": "orthographic", "pixel_size": [1, 1],
//!          "origin": [-16, -16]}}, "lights": [{}]}}"#, lights.join(", "))).unwrap();
//!
//! // The images: a dome 100 mm away, rendered and written as 16-bit PNG files.
//! let (h, w) = (32, 32);
//! let truth: Vec<f64> = (0..(h + 1) * (w + 1))
//!     .map(|v| {
//!         let (x, y) = ((v % (w + 1)) as f64 - 16.0, (v / (w + 1)) as f64 - 16.0);
//!         100.0 - 8.0 + (x * x + y * y) / 64.0
//!     })
//!     .collect();
//! let rig = io::read_rig(&rig_file).unwrap();
//! let albedo = vec![0.8; h * w];
//! let surface = Surface { height: h, width: w, depth: &truth, albedo: &albedo, channels: 1, mask: None };
//! let rendered = nplps::render(&rig, &surface).unwrap();
//! let mut paths: Vec<PathBuf> = Vec::new();
//! for (i, image) in rendered.chunks(h * w).enumerate() {
//!     let path = dir.join(format!("led{i}.png"));
//!     let mut encoder = png::Encoder::new(std::fs::File::create(&path).unwrap(), w as u32, h as u32);
//!     encoder.set_color(png::ColorType::Grayscale);
//!     encoder.set_depth(png::BitDepth::Sixteen);
//!     let bytes: Vec<u8> = image
//!         .iter()
//!         .flat_map(|&v| ((v.clamp(0.0, 1.0) * 65535.0).round() as u16).to_be_bytes())
//!         .collect();
//!     encoder.write_header().unwrap().write_image_data(&bytes).unwrap();
//!     paths.push(path);
//! }
//!
//! // The application: read the rig and the images, reconstruct.
//! let rig = io::read_rig(&rig_file).unwrap();
//! let mut images: Vec<f32> = Vec::new();
//! for image in io::read_pngs(&paths, 1 << 26) {
//!     images.extend(image.unwrap().to_unit());
//! }
//! let stack = ImageStack::new(&images, rig.n_lights(), h, w).unwrap();
//! let mean = truth.iter().sum::<f64>() / truth.len() as f64;
//! let problem = Problem::new(stack, &rig, None, InitialDepth::Distance(mean)).unwrap();
//! let options = Options::default().with_iterations(100).with_tol(1e-7);
//! let result = reconstruct(&problem, &options, &mut |_| Control::Continue).unwrap();
//! let err = result.depth.iter().zip(&truth).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
//! assert!(err < 0.05, "max depth error {err} mm");
//! std::fs::remove_dir_all(&dir).unwrap();
//! # }
//! ```
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

/// `[f(0), f(1), .., f(N - 1)]`, always inlined: the lane kernels build their lanes with it.
/// `std::array::from_fn` computes the same, but above a few lanes the compiler may leave it out
/// of line, as a separate baseline (SSE2) function called from the AVX2 / AVX-512 kernels of
/// `simd_dispatch!` (below) once per use.
#[inline(always)]
pub(crate) fn lanes<T: Copy + Default, const N: usize>(mut f: impl FnMut(usize) -> T) -> [T; N] {
    let mut out = [T::default(); N];
    for (i, x) in out.iter_mut().enumerate() {
        *x = f(i);
    }
    out
}

/// Defines `$name`, which runs the (`#[inline(always)]`) kernel `$kernel` compiled for AVX2 when
/// the processor has it and as compiled for the baseline otherwise. The AVX2 copy enables no
/// FMA: its results are those of the baseline code, with wider lanes. The `wide` form (kernels
/// over 8 f64 lanes, see `local::lanes`) first tries AVX-512 (F, VL, DQ: one 512-bit register per
/// 8-lane operation), again without FMA (Rust never contracts `a * b + c` on its own), so that all
/// three copies give the same bits.
macro_rules! simd_dispatch {
    // The body both forms end with: the AVX2 copy when the processor has AVX2, else the baseline.
    (@avx2 $kernel:ident($($arg:ident: $ty:ty),*) -> $ret:ty) => {{
        #[cfg(target_arch = "x86_64")]
        {
            #[target_feature(enable = "avx2")]
            unsafe fn avx2($($arg: $ty),*) -> $ret {
                $kernel($($arg),*)
            }
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the processor supports AVX2, checked just above.
                return unsafe { avx2($($arg),*) };
            }
        }
        $kernel($($arg),*)
    }};
    (
        $(#[$meta:meta])*
        fn $name:ident => $kernel:ident($($arg:ident: $ty:ty),* $(,)?) -> $ret:ty;
    ) => {
        $(#[$meta])*
        fn $name($($arg: $ty),*) -> $ret {
            simd_dispatch!(@avx2 $kernel($($arg: $ty),*) -> $ret)
        }
    };
    (
        wide
        $(#[$meta:meta])*
        fn $name:ident => $kernel:ident($($arg:ident: $ty:ty),* $(,)?) -> $ret:ty;
    ) => {
        $(#[$meta])*
        fn $name($($arg: $ty),*) -> $ret {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f,avx512vl,avx512dq")]
                unsafe fn avx512($($arg: $ty),*) -> $ret {
                    $kernel($($arg),*)
                }
                if std::arch::is_x86_feature_detected!("avx512f")
                    && std::arch::is_x86_feature_detected!("avx512vl")
                    && std::arch::is_x86_feature_detected!("avx512dq")
                {
                    // SAFETY: the processor supports these AVX-512 subsets, checked just above.
                    return unsafe { avx512($($arg),*) };
                }
            }
            simd_dispatch!(@avx2 $kernel($($arg: $ty),*) -> $ret)
        }
    };
}

mod anderson;
mod baseline;
pub mod calibrate;
#[cfg(feature = "synth")]
pub mod calibration_scene;
mod camera_map;
mod cancel;
mod convergence;
mod distance;
mod error;
mod geometry;
mod global;
mod grid;
pub mod indirect;
#[cfg(feature = "io")]
pub mod io;
mod light;
mod local;
mod memory;
mod mesh;
mod multigrid;
pub mod noise;
mod options;
mod ordering;
mod parallel;
mod pixels;
mod problem;
mod pyramid;
mod reconstruction;
mod refine;
mod refinement;
pub mod reflectance;
mod render;
mod rig;
pub mod shadow;
mod solver;
#[cfg(feature = "synth")]
mod synth;
mod system;
mod trust_figures;
mod vec3;

pub use baseline::reconstruct_parallel;
pub use camera_map::{camera_from_map, MapValue};
pub use cancel::Cancel;
pub use distance::{
    check_distance, estimate_distance, reconstruct_auto, reconstruct_checked, DistanceCheck,
    DistanceEstimate, DistanceSearch, CHECK_SIDE,
};
pub use error::{g6, Error, Result};
pub use geometry::vertices;
pub use global::GlobalSolver;
pub use light::Light;
pub use local::{LightTrust, LobeCheck, Robust, Trust, Weighting, CHECK_BELOW_LIGHTS, CHECK_FOLDS};
#[doc(hidden)]
pub use memory::trace as memtrace;
pub use mesh::{
    mesh_arrays, ply_header, ply_plan, vertex_means, write_ply_records, MeshArrays, PlyColors,
    PlyPlan, Positions, VertexMap,
};
pub use multigrid::MAX_ITERATIONS as MULTIGRID_MAX_ITERATIONS;
pub use noise::estimate_noise;
pub use options::{check_memory, Options, Refine};
pub use pixels::{grey_pixels, normal_map_pixels};
pub use problem::{u16_value, ImageStack, InitialDepth, Problem, Samples, U16_SCALE};
pub use reconstruction::{
    Control, IterationStats, Reconstruction, RefinementReport, SearchProgress, Status, Timings,
};
pub use refine::Conditioning;
pub use reflectance::{Lobe, Reflectance};
pub use render::{
    mesh_normals, mesh_normals_masked, predict, predict_with, render, render_with, RenderOptions,
    Specular, Surface,
};
pub use rig::{Camera, Rig, MAX_LIGHTS};
pub use shadow::{cast_shadows, ShadowMask, Shadows};
pub use solver::{reconstruct, MATTE_ROUGHNESS};
#[cfg(feature = "synth")]
pub use synth::{Scene, SceneKind, SceneOptions};
pub use trust_figures::{trust_figures, TrustFigures, TrustValue};
