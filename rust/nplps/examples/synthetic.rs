//! Reconstructs a synthetic scene and prints accuracy and timings.
//!
//! `cargo run --release -p nplps --features synth --example synthetic -- [scene] [n] [iterations]`
//! (scene: saddle, sphere, cube or bumps; defaults: bumps 256 10).

use nplps::{
    mesh_normals, reconstruct, Control, ImageStack, InitialDepth, Options, Problem, Scene,
    SceneKind,
};

fn main() -> nplps::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let kind = SceneKind::from_name(args.get(1).map_or("bumps", |s| s.as_str()))?;
    let n: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(256);
    let iterations: usize = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(10);

    let scene = Scene::new(kind, n, 100.0, 200.0, 1)?;
    let images: Vec<f32> = scene.render()?.iter().map(|&v| v as f32).collect();
    let stack = ImageStack::new(&images, scene.rig.n_lights(), n, n)?;
    let problem = Problem::new(
        stack,
        &scene.rig,
        Some(&scene.mask),
        InitialDepth::Distance(scene.mean_depth()),
    )?;
    let options = Options::default().with_iterations(iterations).with_tol(0.0);
    let result = reconstruct(&problem, &options, &mut |s| {
        eprintln!(
            "iteration {:>3}: depth change {:.3e}, rms residual {:.3e}",
            s.iteration, s.depth_change, s.rms_residual
        );
        Control::Continue
    })?;

    let truth = mesh_normals(&scene.rig.camera, n, n, &scene.depth)?;
    let (sum, count) = (0..n * n)
        .filter(|&p| scene.mask[p])
        .fold((0.0, 0usize), |(s, c), p| {
            let d: f64 = (0..3).map(|i| truth[p][i] * result.normals[p][i]).sum();
            (s + d.clamp(-1.0, 1.0).acos().to_degrees(), c + 1)
        });
    let t = result.timings;
    println!(
        "{} {n}x{n}, {} lights: mean normal error {:.2e} degrees",
        kind.name(),
        scene.rig.n_lights(),
        sum / count as f64
    );
    println!(
        "factorization {:.3} s, local {:.3} s, solve {:.3} s, total {:.3} s",
        t.factorization.as_secs_f64(),
        t.local.as_secs_f64(),
        t.solve.as_secs_f64(),
        t.total.as_secs_f64()
    );
    Ok(())
}
