//! End-to-end accuracy on synthetic scenes rendered by the model.

use nplps::{
    mesh_normals, reconstruct, reconstruct_parallel, Control, ImageStack, InitialDepth, Options,
    Problem, Reconstruction, Scene, SceneKind, SceneOptions,
};

fn angle_deg(a: [f64; 3], b: [f64; 3]) -> f64 {
    (a[0] * b[0] + a[1] * b[1] + a[2] * b[2])
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

/// Mean angular error (degrees) of `normals` against the scene's true mesh normals, inside the mask.
fn mean_normal_error(scene: &Scene, normals: &[[f64; 3]]) -> f64 {
    let truth = mesh_normals(&scene.rig.camera, scene.height, scene.width, &scene.depth).unwrap();
    let errs: Vec<f64> = (0..truth.len())
        .filter(|&p| scene.mask[p])
        .map(|p| angle_deg(truth[p], normals[p]))
        .collect();
    errs.iter().sum::<f64>() / errs.len() as f64
}

fn max_depth_error(scene: &Scene, result: &Reconstruction) -> f64 {
    result
        .depth
        .iter()
        .zip(&scene.depth)
        .filter(|(a, _)| a.is_finite())
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max)
}

/// The scene's problem with its mask, started at the true working distance.
fn problem<'a>(scene: &'a Scene, images: &'a [f32]) -> Problem<'a> {
    let stack = ImageStack::with_channels(
        images,
        scene.rig.n_lights(),
        scene.height,
        scene.width,
        scene.channels,
    )
    .unwrap();
    let depth = InitialDepth::Distance(scene.mean_depth());
    Problem::new(stack, &scene.rig, Some(&scene.mask), depth).unwrap()
}

fn solve(scene: &Scene, images: &[f32], options: &Options) -> Reconstruction {
    reconstruct(&problem(scene, images), options, &mut |_| Control::Continue).unwrap()
}

fn exact_images(scene: &Scene) -> Vec<f32> {
    scene.render().unwrap().iter().map(|&v| v as f32).collect()
}

/// Reconstructs a scene with options from its exact images (any channels) at the true gauge.
fn solve_scene(scene: &Scene, options: &Options) -> Reconstruction {
    solve(scene, &exact_images(scene), options)
}

#[test]
fn real_rig_variations_are_recovered_exactly() {
    let options = Options::default().with_iterations(100).with_tol(1e-10);
    let variations = [
        ("pinhole", SceneOptions::default().with_pinhole(true)),
        (
            "pinhole + LEDs",
            SceneOptions::default().with_pinhole(true).with_led(true),
        ),
        (
            "orthographic + LEDs",
            SceneOptions::default().with_led(true),
        ),
        ("RGB", SceneOptions::default().with_rgb(true).with_led(true)),
        (
            "directional",
            SceneOptions::default()
                .with_directional(true)
                .with_pinhole(true),
        ),
    ];
    for (name, variation) in variations {
        for kind in [SceneKind::Saddle, SceneKind::SphereCap] {
            let scene = Scene::with_options(kind, 40, 100.0, 200.0, 3, variation).unwrap();
            let result = solve_scene(&scene, &options);
            let normal_err = mean_normal_error(&scene, &result.normals);
            let depth_err = max_depth_error(&scene, &result) / scene.size;
            println!(
                "{name:>20} {:>7}: normal error {normal_err:.2e} deg, depth error {depth_err:.2e}",
                kind.name()
            );
            assert!(
                normal_err < 0.01,
                "{name} {}: {normal_err} degrees",
                kind.name()
            );
            assert!(
                depth_err < 1e-3,
                "{name} {}: depth error {depth_err}",
                kind.name()
            );
            if scene.channels == 3 {
                let p = scene.mask.iter().position(|m| *m).unwrap();
                for ch in 0..3 {
                    let rel = result.albedo[p * 3 + ch] / scene.albedo[p * 3 + ch] - 1.0;
                    assert!(rel.abs() < 1e-3, "{name}: albedo channel {ch} off by {rel}");
                }
            }
        }
    }
}

#[test]
fn pinhole_gauge_is_the_geometric_mean_depth() {
    let scene = Scene::with_options(
        SceneKind::Bumps,
        32,
        100.0,
        300.0,
        5,
        SceneOptions::default().with_pinhole(true),
    )
    .unwrap();
    let result = solve_scene(&scene, &Options::default());
    let finite: Vec<f64> = result
        .depth
        .iter()
        .copied()
        .filter(|z| z.is_finite())
        .collect();
    let geometric = (finite.iter().map(|z| z.ln()).sum::<f64>() / finite.len() as f64).exp();
    assert!((geometric / scene.mean_depth() - 1.0).abs() < 1e-12);
    assert!((result.gauge[0] / scene.mean_depth() - 1.0).abs() < 1e-12);
}

#[test]
fn exact_model_recovers_every_scene() {
    let options = Options::default().with_iterations(200).with_tol(1e-9);
    // The block's walls are one-pixel cliffs: a scene for the forward model (cast shadows),
    // not one the smooth-surface solver is held to.
    for kind in SceneKind::ALL
        .into_iter()
        .filter(|k| *k != SceneKind::Block)
    {
        let scene = Scene::new(kind, 48, 100.0, 200.0, 7).unwrap();
        let result = solve(&scene, &exact_images(&scene), &options);
        let normal_err = mean_normal_error(&scene, &result.normals);
        let depth_err = max_depth_error(&scene, &result) / scene.size;
        println!(
            "{:>7}: {} iterations, normal error {normal_err:.2e} deg, depth error {depth_err:.2e} of size",
            kind.name(),
            result.history.len()
        );
        assert!(normal_err < 0.01, "{}: {normal_err} degrees", kind.name());
        assert!(depth_err < 1e-3, "{}: depth error {depth_err}", kind.name());
    }
}

#[test]
fn near_light_model_beats_the_parallel_baseline() {
    let scene = Scene::new(SceneKind::SphereCap, 40, 100.0, 200.0, 0).unwrap();
    let images = exact_images(&scene);
    let problem = problem(&scene, &images);
    let near = reconstruct(&problem, &Options::default(), &mut |_| Control::Continue).unwrap();
    let parallel = reconstruct_parallel(&problem, &Options::default()).unwrap();
    let (e_near, e_par) = (
        mean_normal_error(&scene, &near.normals),
        mean_normal_error(&scene, &parallel.normals),
    );
    println!("sphere: near {e_near:.2e} deg, parallel baseline {e_par:.2} deg");
    assert!(e_near < 0.01 && e_par > 1.0);
}

#[test]
fn cancelling_stops_the_solver() {
    let scene = Scene::new(SceneKind::Saddle, 16, 100.0, 200.0, 0).unwrap();
    let images = exact_images(&scene);
    let problem = problem(&scene, &images);
    let mut calls = 0;
    let result = reconstruct(&problem, &Options::default(), &mut |_| {
        calls += 1;
        Control::Cancel
    });
    assert_eq!(result.unwrap_err(), nplps::Error::Cancelled);
    assert_eq!(calls, 1);
}

#[test]
fn a_cancel_token_stops_the_solver_from_another_thread() {
    // 256^2 with 1000 iterations and tol 0 runs for seconds; a token cancelled from another
    // thread after the first iteration stops it inside the next local or global step.
    let scene = Scene::new(SceneKind::Bumps, 256, 100.0, 200.0, 0).unwrap();
    let images = exact_images(&scene);
    let stack = ImageStack::new(&images, scene.rig.n_lights(), 256, 256).unwrap();
    let cancel = nplps::Cancel::new();
    let problem = Problem::with_cancel(
        stack,
        &scene.rig,
        Some(&scene.mask),
        InitialDepth::Distance(scene.mean_depth()),
        cancel.clone(),
    )
    .unwrap();
    let options = Options::default()
        .with_iterations(1000)
        .with_tol(0.0)
        .with_levels(1);
    let mut calls = 0;
    let result = std::thread::scope(|s| {
        let (first, seen) = std::sync::mpsc::channel();
        let canceller = s.spawn(move || {
            seen.recv().unwrap();
            cancel.cancel();
        });
        let result = reconstruct(&problem, &options, &mut |_| {
            calls += 1;
            if calls == 1 {
                first.send(()).unwrap();
            }
            Control::Continue
        });
        canceller.join().unwrap();
        result
    });
    assert_eq!(result.unwrap_err(), nplps::Error::Cancelled);
    assert!(calls < 50, "{calls} iterations ran after the cancellation");

    // A token cancelled before the start stops the problem's preparation.
    let stopped = nplps::Cancel::new();
    stopped.cancel();
    let stack = ImageStack::new(&images, scene.rig.n_lights(), 256, 256).unwrap();
    let refused = Problem::with_cancel(
        stack,
        &scene.rig,
        None,
        InitialDepth::Distance(200.0),
        stopped,
    );
    assert_eq!(refused.err(), Some(nplps::Error::Cancelled));
}

#[test]
fn working_distance_is_found_from_the_images() {
    use nplps::{reconstruct_auto, DistanceSearch};
    for pinhole in [false, true] {
        let variation = SceneOptions::default().with_pinhole(pinhole);
        let scene = Scene::with_options(SceneKind::Bumps, 40, 100.0, 200.0, 2, variation).unwrap();
        let truth = scene.mean_depth();
        let images = exact_images(&scene);
        let stack = ImageStack::new(&images, scene.rig.n_lights(), 40, 40).unwrap();
        for factor in [0.7, 1.3] {
            let problem = Problem::new(
                stack,
                &scene.rig,
                Some(&scene.mask),
                InitialDepth::Distance(truth * factor),
            )
            .unwrap();
            let search = DistanceSearch::default().with_guess(Some(truth * factor));
            let t = std::time::Instant::now();
            let (result, estimate) =
                reconstruct_auto(&problem, &Options::default(), &search, &mut |_| {
                    Control::Continue
                })
                .unwrap();
            let rel = estimate.distance[0] / truth - 1.0;
            println!(
                "pinhole {pinhole}, guess x{factor}: estimate {:.3} (true {truth:.3}, {rel:+.2e}), {} evaluations, {:?}",
                estimate.distance[0],
                estimate.curve[0].len(),
                t.elapsed()
            );
            assert!(rel.abs() < 0.01);
            assert!(mean_normal_error(&scene, &result.normals) < 0.05);
        }
    }
}

/// A glossy `depth="auto"` run whose model is dropped (Lambertian images: the estimated lobe is
/// matte) is the Lambertian `depth="auto"` run, bit for bit, as at a known distance: its
/// distance comes from a search under the Lambertian model, not from the glossy model's.
#[test]
fn a_glossy_auto_run_that_drops_the_model_is_the_lambertian_auto_run() {
    use nplps::{reconstruct_auto, DistanceSearch, Reflectance};
    let variation = SceneOptions::default().with_pinhole(true);
    let scene = Scene::with_options(SceneKind::Bumps, 40, 100.0, 200.0, 2, variation).unwrap();
    let truth = scene.mean_depth();
    let images = exact_images(&scene);
    let stack = ImageStack::new(&images, scene.rig.n_lights(), 40, 40).unwrap();
    let problem = Problem::new(
        stack,
        &scene.rig,
        Some(&scene.mask),
        InitialDepth::Distance(truth * 1.2),
    )
    .unwrap();
    let search = DistanceSearch::default().with_guess(Some(truth * 1.2));
    let run = |reflectance: Reflectance| {
        let mut options = Options::default();
        options.reflectance = reflectance;
        reconstruct_auto(&problem, &options, &search, &mut |_| Control::Continue).unwrap()
    };
    let (lambertian, plain) = run(Reflectance::Lambertian);
    let (glossy, estimate) = run(Reflectance::Glossy(None));
    assert!(glossy.matte_lobe.is_some(), "the glossy model was kept");
    assert!(lambertian.matte_lobe.is_none());
    assert_eq!(estimate.distance, plain.distance);
    let bits = |v: &[[f64; 3]]| v.iter().map(|n| n.map(f64::to_bits)).collect::<Vec<_>>();
    assert!(bits(&glossy.normals) == bits(&lambertian.normals));
    assert!(glossy
        .depth
        .iter()
        .zip(&lambertian.depth)
        .all(|(a, b)| a.to_bits() == b.to_bits()));
    assert!(glossy.timings.total > lambertian.timings.total / 2);
}

#[test]
fn the_distance_search_reports_its_candidates() {
    use nplps::{reconstruct_auto, DistanceSearch, IterationStats};
    let scene = Scene::new(SceneKind::Bumps, 24, 100.0, 200.0, 2).unwrap();
    let images = exact_images(&scene);
    let problem = problem(&scene, &images);
    let search = DistanceSearch::default().with_guess(Some(scene.mean_depth()));
    let mut seen: Vec<IterationStats> = Vec::new();
    let (result, estimate) = reconstruct_auto(&problem, &Options::default(), &search, &mut |s| {
        seen.push(*s);
        Control::Continue
    })
    .unwrap();
    let searched: Vec<_> = seen.iter().filter_map(|s| s.search).collect();
    // Every evaluation is one candidate, numbered 1..=n; a plan is announced, which grows when
    // the search needs more candidates (and the search may end sooner).
    let n = searched.last().unwrap().candidate;
    assert_eq!(n, estimate.curve[0].len());
    assert!(searched.iter().all(|s| s.candidates >= s.candidate));
    assert!(searched
        .windows(2)
        .all(|w| w[1].candidate >= w[0].candidate && w[1].candidates >= w[0].candidates));
    // The residual is set on each candidate's last iteration only, and the best follows it.
    let finished: Vec<_> = searched.iter().filter(|s| s.residual.is_finite()).collect();
    assert_eq!(finished.len(), n);
    let lowest = finished
        .iter()
        .min_by(|a, b| a.residual.total_cmp(&b.residual))
        .unwrap();
    let last = finished.last().unwrap();
    assert_eq!(
        (last.best_distance, last.best_residual),
        (lowest.distance, lowest.residual)
    );
    // The search comes first; the reconstruction's own iterations are the history.
    let solve: Vec<_> = seen.iter().filter(|s| s.search.is_none()).collect();
    assert_eq!(seen.len(), searched.len() + solve.len());
    assert!(seen[..searched.len()].iter().all(|s| s.search.is_some()));
    assert_eq!(solve.len(), result.history.len());
}
