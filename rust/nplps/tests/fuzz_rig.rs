//! Property tests (fuzzing) of the rig checks and of the problem builder: whatever the camera,
//! the lights, the images, the mask and the starting depth (NaN, infinities, zeros, negative or
//! huge values, wrong sizes), building and solving never panics, and every error is a typed
//! [`nplps::Error`] with a short message.
//!
//! Each property runs 64 cases by default (CI); `PROPTEST_CASES=100000 cargo test --release
//! --test fuzz_rig` runs a long fuzzing session.

use nplps::{
    mesh_normals, reconstruct, render, vertices, Camera, Control, Error, ImageStack, InitialDepth,
    Light, Options, Problem, Reconstruction, Rig, Surface,
};
use proptest::prelude::*;
use proptest::test_runner::Config;

/// 64 cases per property unless `PROPTEST_CASES` asks for another number.
fn config() -> Config {
    let cases = std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(64);
    Config {
        cases,
        failure_persistence: None,
        ..Config::default()
    }
}

/// Any number, with the troublesome ones (NaN, infinities, zeros, tiny, huge) often.
fn wild() -> impl Strategy<Value = f64> {
    prop_oneof![
        3 => -100.0..100.0f64,
        1 => Just(f64::NAN),
        1 => Just(f64::INFINITY),
        1 => Just(f64::NEG_INFINITY),
        1 => Just(0.0),
        1 => Just(-0.0),
        1 => Just(1e300),
        1 => Just(-1e300),
        1 => Just(f64::MIN_POSITIVE),
        1 => Just(5e-324),
        1 => any::<f64>(),
    ]
}

/// Mostly a sensible value from `sane`, sometimes a wild one.
fn mostly(sane: impl Strategy<Value = f64> + 'static) -> BoxedStrategy<f64> {
    prop_oneof![6 => sane, 1 => wild()].boxed()
}

fn camera() -> impl Strategy<Value = Camera> {
    let orthographic = (
        [mostly(0.1..5.0), mostly(0.1..5.0)],
        [mostly(-50.0..50.0), mostly(-50.0..50.0)],
    )
        .prop_map(|(pixel_size, origin)| Camera::Orthographic { pixel_size, origin });
    let pinhole = (
        [mostly(10.0..2000.0), mostly(-5.0..5.0), mostly(-10.0..10.0)],
        [
            mostly(0.0..0.0001),
            mostly(10.0..2000.0),
            mostly(-10.0..10.0),
        ],
        prop_oneof![4 => Just([0.0, 0.0, 1.0]), 1 => [wild(), wild(), wild()]],
        [
            mostly(-0.5..0.5),
            mostly(-0.2..0.2),
            mostly(-0.01..0.01),
            mostly(-0.01..0.01),
            mostly(-0.1..0.1),
        ],
    )
        .prop_map(|(r0, r1, r2, distortion)| Camera::Pinhole {
            k: [
                r0,
                [if r1[0] < 0.00005 { 0.0 } else { r1[0] }, r1[1], r1[2]],
                r2,
            ],
            distortion,
        });
    prop_oneof![orthographic, pinhole]
}

fn light() -> impl Strategy<Value = Light> {
    let point = (
        [
            mostly(-60.0..60.0),
            mostly(-60.0..60.0),
            mostly(-80.0..10.0),
        ],
        [mostly(0.1..3.0), mostly(0.1..3.0), mostly(0.1..3.0)],
        [mostly(-1.0..1.0), mostly(-1.0..1.0), mostly(0.2..1.0)],
        prop_oneof![3 => Just(0.0), 2 => mostly(0.0..3.0)],
        any::<bool>(),
    )
        .prop_map(|(position, intensity, axis, mu, normalize)| {
            let n = (axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]).sqrt();
            let axis = if normalize && n > 0.0 {
                axis.map(|a| a / n)
            } else {
                axis
            };
            Light::Point {
                position,
                intensity,
                axis,
                mu,
            }
        });
    let directional = (
        [mostly(-1.0..1.0), mostly(-1.0..1.0), mostly(-1.0..-0.2)],
        [mostly(0.1..3.0), mostly(0.1..3.0), mostly(0.1..3.0)],
        any::<bool>(),
    )
        .prop_map(|(direction, intensity, normalize)| {
            let n = direction.iter().map(|d| d * d).sum::<f64>().sqrt();
            let direction = if normalize && n > 0.0 {
                direction.map(|d| d / n)
            } else {
                direction
            };
            Light::Directional {
                direction,
                intensity,
            }
        });
    prop_oneof![4 => point, 1 => directional]
}

/// Rigs with anything in them (most are invalid).
fn wild_rig() -> impl Strategy<Value = Rig> {
    (camera(), prop::collection::vec(light(), 0..8))
        .prop_map(|(camera, lights)| Rig { camera, lights })
}

/// A valid rig of 3 to 8 lights in front of surfaces at depth 80 and more.
fn sane_rig() -> impl Strategy<Value = Rig> {
    let camera = prop_oneof![
        ([0.1..5.0f64, 0.1..5.0], [-50.0..50.0f64, -50.0..50.0])
            .prop_map(|(pixel_size, origin)| Camera::Orthographic { pixel_size, origin }),
        (
            [20.0..2000.0f64, 20.0..2000.0],
            [-5.0..5.0f64, -10.0..10.0, -10.0..10.0],
            [
                -0.3..0.3f64,
                -0.1..0.1,
                -0.01..0.01,
                -0.01..0.01,
                -0.05..0.05
            ],
            any::<bool>(),
        )
            .prop_map(|(f, [s, cx, cy], d, distorted)| Camera::Pinhole {
                k: [[f[0], s, cx], [0.0, f[1], cy], [0.0, 0.0, 1.0]],
                distortion: if distorted { d } else { [0.0; 5] },
            }),
    ];
    let light = (
        [-60.0..60.0f64, -60.0..60.0, -80.0..10.0],
        [0.1..3.0f64, 0.1..3.0, 0.1..3.0],
        [-0.5..0.5f64, -0.5..0.5, 0.2..1.0],
        prop_oneof![Just(0.0), 0.0..3.0f64],
        0usize..6,
    )
        .prop_map(|(p, intensity, a, mu, kind)| {
            let n = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
            if kind == 0 {
                Light::Directional {
                    direction: [a[0] / n, a[1] / n, -a[2] / n],
                    intensity,
                }
            } else {
                Light::Point {
                    position: p,
                    intensity,
                    axis: a.map(|v| v / n),
                    mu,
                }
            }
        });
    (camera, prop::collection::vec(light, 3..9)).prop_map(|(camera, lights)| Rig { camera, lights })
}

/// A valid rig, or one with one parameter replaced by a wild value.
fn rig() -> impl Strategy<Value = Rig> {
    (sane_rig(), any::<bool>(), 0usize..100, wild()).prop_map(|(mut rig, corrupt, which, value)| {
        if corrupt {
            corrupt_one(&mut rig, which, value);
        }
        rig
    })
}

/// Sets one number of the rig (chosen by `which`) to `value`.
fn corrupt_one(rig: &mut Rig, which: usize, value: f64) {
    let mut slots: Vec<&mut f64> = Vec::new();
    match &mut rig.camera {
        Camera::Orthographic { pixel_size, origin } => {
            slots.extend(pixel_size.iter_mut().chain(origin.iter_mut()))
        }
        Camera::Pinhole { k, distortion } => {
            slots.extend(k.iter_mut().flatten().chain(distortion.iter_mut()))
        }
        other => panic!("a camera model this test does not know: {other:?}"),
    }
    for light in &mut rig.lights {
        match light {
            Light::Point {
                position,
                intensity,
                axis,
                mu,
            } => {
                slots.extend(
                    position
                        .iter_mut()
                        .chain(intensity.iter_mut())
                        .chain(axis.iter_mut()),
                );
                slots.push(mu);
            }
            Light::Directional {
                direction,
                intensity,
            } => slots.extend(direction.iter_mut().chain(intensity.iter_mut())),
            other => panic!("a light model this test does not know: {other:?}"),
        }
    }
    let n = slots.len();
    *slots[which % n] = value;
}

/// An error message is short and prints no number with hundreds of digits.
fn check_message(e: &Error) -> Result<(), TestCaseError> {
    let text = e.to_string();
    prop_assert!(
        text.len() < 1500,
        "message of {} characters: {text}",
        text.len()
    );
    let mut run = 0;
    for c in text.chars() {
        run = if c.is_ascii_digit() { run + 1 } else { 0 };
        prop_assert!(run <= 20, "a number with more than 20 digits: {text}");
    }
    Ok(())
}

/// A validated rig holds finite values only, positive intensities and unit directions where
/// they are used.
fn check_valid(rig: &Rig) -> Result<(), TestCaseError> {
    let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
    match rig.camera {
        Camera::Orthographic { pixel_size, origin } => {
            prop_assert!(finite(&pixel_size) && finite(&origin));
            prop_assert!(pixel_size.iter().all(|&s| s > 0.0));
        }
        Camera::Pinhole { k, distortion } => {
            prop_assert!(k.iter().all(|r| finite(r)) && finite(&distortion));
            prop_assert!(k[0][0] > 0.0 && k[1][1] > 0.0);
        }
        other => prop_assert!(false, "a camera model this test does not know: {other:?}"),
    }
    for light in &rig.lights {
        prop_assert!(light.intensity().iter().all(|&p| p.is_finite() && p > 0.0));
        match *light {
            Light::Point {
                position, axis, mu, ..
            } => {
                prop_assert!(finite(&position) && finite(&axis) && mu.is_finite() && mu >= 0.0);
            }
            Light::Directional { direction, .. } => {
                let n = direction.iter().map(|d| d * d).sum::<f64>().sqrt();
                prop_assert!((n - 1.0).abs() < 1e-6);
            }
            other => prop_assert!(false, "a light model this test does not know: {other:?}"),
        }
    }
    Ok(())
}

/// Inside the mask a reconstruction is finite: depths at the pixels' corners and unit normals
/// (a reconstruction does not report NaN as a result).
fn check_result(r: &Reconstruction, h: usize, w: usize) -> Result<(), TestCaseError> {
    prop_assert_eq!(r.depth.len(), (h + 1) * (w + 1));
    prop_assert_eq!(r.normals.len(), h * w);
    for p in (0..h * w).filter(|&p| r.regions[p] >= 0) {
        let n = r.normals[p];
        let norm = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        prop_assert!((norm - 1.0).abs() < 1e-6, "normal {}: {:?}", p, n);
        let (row, col) = (p / w, p % w);
        for v in [row * (w + 1) + col, (row + 1) * (w + 1) + col + 1] {
            prop_assert!(r.depth[v].is_finite(), "depth {}: {}", v, r.depth[v]);
        }
    }
    Ok(())
}

/// The size of the images and the values of a stack of `k` of them.
fn images(k: usize) -> impl Strategy<Value = (usize, usize, usize, Vec<f32>)> {
    (
        1usize..6,
        1usize..6,
        prop_oneof![4 => Just(1usize), 1 => Just(3usize)],
    )
        .prop_flat_map(move |(h, w, c)| {
            let value = prop_oneof![
                400 => 0.0f32..2.0,
                1 => Just(f32::NAN),
                1 => Just(f32::INFINITY),
                2 => Just(-1.0f32),
                4 => Just(0.0f32),
                1 => Just(f32::MAX),
                1 => Just(f32::MIN_POSITIVE),
            ];
            // Sometimes one value too few or too many.
            let n = k * h * w * c;
            let len = prop_oneof![30 => Just(n), 1 => Just(n.saturating_sub(1)), 1 => Just(n + 1)];
            (
                Just(h),
                Just(w),
                Just(c),
                len.prop_flat_map(move |n| prop::collection::vec(value.clone(), n)),
            )
        })
}

proptest! {
    #![proptest_config(config())]

    /// Checking a rig never panics; an accepted rig is sane; a refused one says why briefly.
    #[test]
    fn rig_checks_never_panic(rig in prop_oneof![wild_rig(), rig()]) {
        match rig.validate_parameters() {
            Ok(()) => check_valid(&rig)?,
            Err(e) => {
                prop_assert!(matches!(e, Error::Rig(_)), "{e:?}");
                check_message(&e)?;
            }
        }
        if let Err(e) = rig.validate() {
            check_message(&e)?;
        }
        for depth in [f64::NAN, -1.0, 0.0, 1e300, 100.0] {
            if let Err(e) = rig.check_lights_in_front(depth) {
                check_message(&e)?;
            }
        }
    }

    /// The geometry of a depth map under a valid camera never panics, whatever the depths.
    #[test]
    fn geometry_never_panics(
        camera in camera(),
        (h, w) in (1usize..5, 1usize..5),
        depth in prop::collection::vec(mostly(50.0..200.0), 0..40),
        albedo in prop::collection::vec(mostly(0.0..1.0), 0..40),
        lights in prop::collection::vec(light(), 0..5),
    ) {
        if camera.validate().is_err() {
            return Ok(());
        }
        for result in [vertices(&camera, h, w, &depth), mesh_normals(&camera, h, w, &depth)] {
            if let Err(e) = result {
                check_message(&e)?;
            }
        }
        let rig = Rig { camera, lights };
        if rig.validate_parameters().is_ok() {
            for channels in [1, 3] {
                let surface = Surface { height: h, width: w, depth: &depth, albedo: &albedo, channels, mask: None };
                if let Err(e) = render(&rig, &surface) {
                    check_message(&e)?;
                }
            }
        }
    }

    /// Building a problem from anything never panics, and nor does a short reconstruction of an
    /// accepted problem; errors are typed and short.
    #[test]
    fn problem_builder_never_panics(
        (rig, (h, w, c, data)) in rig().prop_flat_map(|rig| {
            let k = rig.n_lights();
            (Just(rig), images(k))
        }),
        mask_kind in prop_oneof![4 => Just(0usize), 4 => Just(1), 1 => Just(2), 1 => Just(3)],
        mask_bits in prop::collection::vec(any::<bool>(), 36),
        depth_kind in prop_oneof![4 => Just(0usize), 1 => Just(1), 4 => Just(2)],
        distance in prop_oneof![20 => 80.0..150.0f64, 1 => wild()],
        depth_map in prop::collection::vec(prop_oneof![30 => 80.0..150.0f64, 1 => wild()], 1..50),
        iterations in 1usize..3,
    ) {
        let Ok(stack) = ImageStack::with_channels(&data, rig.n_lights(), h, w, c) else {
            return Ok(());
        };
        let mask: Option<Vec<bool>> = match mask_kind {
            0 => None,
            1 => Some(mask_bits[..h * w].to_vec()),
            2 => Some(vec![true; h * w]),
            _ => Some(mask_bits[..(h * w).saturating_sub(1)].to_vec()),
        };
        // A map of the right size, or (depth_kind 1) of a wrong one.
        let n = if depth_kind == 2 { (h + 1) * (w + 1) } else { depth_map.len().min(7) };
        let map: Vec<f64> = depth_map.iter().copied().cycle().take(n).collect();
        let depth = match depth_kind {
            0 => InitialDepth::Distance(distance),
            _ => InitialDepth::Map(&map),
        };
        match Problem::new(stack, &rig, mask.as_deref(), depth) {
            Err(e) => check_message(&e)?,
            Ok(problem) => {
                check_valid(&rig)?;
                let options = Options::default().with_iterations(iterations).with_levels(1);
                match reconstruct(&problem, &options, &mut |_| Control::Continue) {
                    Err(e) => {
                        prop_assert!(!matches!(e, Error::Cancelled));
                        check_message(&e)?;
                    }
                    Ok(r) => check_result(&r, h, w)?,
                }
            }
        }
    }
}

/// Image sizes whose product overflows are an error, not a wrapped length.
#[test]
fn image_stack_sizes_that_overflow_are_errors() {
    let data: Vec<f32> = Vec::new();
    let huge = 1usize << (usize::BITS - 2);
    for (k, h, w) in [
        (huge, 4, 1),
        (4, huge, 4),
        (1, usize::MAX, 1),
        (3, 1, usize::MAX),
    ] {
        assert!(
            matches!(
                ImageStack::with_channels(&data, k, h, w, 1),
                Err(Error::Shape { .. })
            ),
            "{k} x {h} x {w}"
        );
    }
}

/// More lights than [`nplps::MAX_LIGHTS`] are refused.
#[test]
fn too_many_lights_are_refused() {
    let lights = vec![Light::point([0.0, 0.0, -10.0]); nplps::MAX_LIGHTS + 1];
    let rig = Rig {
        camera: Camera::Orthographic {
            pixel_size: [1.0, 1.0],
            origin: [0.0, 0.0],
        },
        lights,
    };
    let e = rig.validate().unwrap_err();
    assert!(e.to_string().contains("at most 10000"), "{e}");
}

/// Numbers in the rig's messages have 6 significant digits, never hundreds.
#[test]
fn rig_messages_print_short_numbers() {
    let rig = Rig {
        camera: Camera::Orthographic {
            pixel_size: [1.0, 1.0],
            origin: [0.0, 0.0],
        },
        lights: vec![Light::point([0.0, 0.0, 1e300]); 3],
    };
    let e = rig.check_lights_in_front(1e300).unwrap_err().to_string();
    assert!(e.contains("z = 1.00000e300") && e.len() < 300, "{e}");
    let led = Light::Point {
        position: [0.0; 3],
        intensity: [1.0; 3],
        axis: [0.0, 0.0, 1.0],
        mu: -1e300,
    };
    let rig = Rig {
        lights: vec![led; 3],
        ..rig
    };
    let e = rig.validate().unwrap_err().to_string();
    assert!(e.contains("mu = -1.00000e300") && e.len() < 300, "{e}");
}
