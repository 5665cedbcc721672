//! What a run says about itself, tested from Rust: the status of light refinements (the start is
//! never returned as the iterated result; a fallen-back refinement is judged on the run it
//! returns) and the check of a given working distance.

use nplps::{
    check_distance, reconstruct, Control, ImageStack, InitialDepth, Light, Options, Problem,
    Refine, Rig, Scene, SceneKind, Status,
};

fn exact_images(scene: &Scene) -> Vec<f32> {
    scene.render().unwrap().iter().map(|&v| v as f32).collect()
}

fn problem<'a>(scene: &'a Scene, rig: &'a Rig, images: &'a [f32], depth: f64) -> Problem<'a> {
    let stack = ImageStack::new(images, rig.n_lights(), scene.height, scene.width).unwrap();
    Problem::new(stack, rig, Some(&scene.mask), InitialDepth::Distance(depth)).unwrap()
}

/// A deterministic normal deviate stream (Box-Muller on a 64-bit LCG).
struct Normal(u64);

impl Normal {
    fn uniform(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }

    fn next(&mut self) -> f64 {
        let (a, b) = (self.uniform(), self.uniform());
        (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
    }
}

/// The scene's rig with every point light moved by N(0, sd) per coordinate.
fn perturbed(rig: &Rig, sd: f64, seed: u64) -> Rig {
    let mut normal = Normal(seed);
    let lights = rig
        .lights
        .iter()
        .map(|l| match *l {
            Light::Point { position, .. } => Light::point([
                position[0] + sd * normal.next(),
                position[1] + sd * normal.next(),
                position[2] + sd * normal.next(),
            ]),
            other => other,
        })
        .collect();
    Rig {
        camera: rig.camera,
        lights,
    }
}

fn std_dev(values: &[f64]) -> f64 {
    let v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    let mean = v.iter().sum::<f64>() / v.len() as f64;
    (v.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / v.len() as f64).sqrt()
}

fn position_refinement(prior_weight: f64) -> Options {
    Options::default().with_refine(
        Refine::NONE
            .with_position(true)
            .with_prior_weight(prior_weight),
    )
}

#[test]
fn a_stiff_prior_does_not_return_the_flat_start() {
    for seed in 0..3 {
        let scene = Scene::new(SceneKind::Bumps, 48, 100.0, 200.0, seed).unwrap();
        let images = exact_images(&scene);
        let rig = perturbed(&scene.rig, 6.0, 10 + seed);
        let p = problem(&scene, &rig, &images, scene.mean_depth());
        let r = reconstruct(&p, &position_refinement(1e9), &mut |_| Control::Continue).unwrap();
        // The start is a plane (std about 1e-14); the bumps are several millimetres high.
        assert!(
            std_dev(&r.depth) > 0.3 * std_dev(&scene.depth),
            "seed {seed}: depth std {} against the truth's {}",
            std_dev(&r.depth),
            std_dev(&scene.depth)
        );
    }
}

#[test]
fn a_fallen_back_refinement_is_judged_on_the_plain_run() {
    for seed in 0..3 {
        let scene = Scene::new(SceneKind::Bumps, 32, 100.0, 200.0, seed).unwrap();
        let images = exact_images(&scene);
        let p = problem(&scene, &scene.rig, &images, scene.mean_depth());
        let options = position_refinement(1e3).with_levels(1);
        let r = reconstruct(&p, &options, &mut |_| Control::Continue).unwrap();
        let report = r.refinement.as_ref().expect("refinement report");
        // With the exact lights nothing is gained: the plain run is returned.
        assert!(report.fell_back, "seed {seed}");
        let starts: Vec<usize> = (0..r.history.len())
            .filter(|&i| r.history[i].iteration == 1)
            .collect();
        assert_eq!(
            starts.len(),
            2,
            "seed {seed}: the plain and the refined run"
        );
        let plain = &r.history[..starts[1]];
        assert_eq!(r.status, Status::Converged, "seed {seed}");
        let quoted = format!("iteration {} (", plain.len());
        assert!(
            r.status_reason.contains(&quoted),
            "seed {seed}: {}",
            r.status_reason
        );
    }
}

#[test]
fn a_given_distance_is_checked_against_the_images() {
    for seed in 0..3 {
        let scene = Scene::new(SceneKind::Bumps, 64, 100.0, 200.0, seed).unwrap();
        let images = exact_images(&scene);
        let truth = scene.mean_depth();
        for factor in [0.75, 0.97, 1.0, 1.03, 1.25] {
            let p = problem(&scene, &scene.rig, &images, truth * factor);
            let check = check_distance(&p, &Options::default())
                .unwrap()
                .expect("27 point lights reveal the distance");
            let wrong = (factor - 1.0f64).abs() > 0.1;
            assert_eq!(
                check.looks_wrong(),
                wrong,
                "seed {seed}, x{factor}: {check:?}"
            );
            assert!((check.given / (truth * factor) - 1.0).abs() < 1e-9);
            assert!(
                (check.found / truth - 1.0).abs() < 0.03,
                "seed {seed}, x{factor}: found {} for {truth}",
                check.found
            );
            assert!(check.side <= nplps::CHECK_SIDE);
        }
    }
}

#[test]
fn no_check_where_the_rig_cannot_reveal_the_distance() {
    let scene = Scene::new(SceneKind::Bumps, 32, 100.0, 200.0, 0).unwrap();
    let all = exact_images(&scene);
    let keep = [2usize, 5, 8];
    let n = scene.height * scene.width;
    let images: Vec<f32> = keep
        .iter()
        .flat_map(|&i| all[i * n..(i + 1) * n].iter().copied())
        .collect();
    let rig = Rig {
        camera: scene.rig.camera,
        lights: keep.iter().map(|&i| scene.rig.lights[i]).collect(),
    };
    let p = problem(&scene, &rig, &images, scene.mean_depth());
    assert!(check_distance(&p, &Options::default()).unwrap().is_none());
}
