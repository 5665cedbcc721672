"""Tests of the light calibration (nplps.calibrate): sphere calibration and intensity calibration
on synthetic scenes (accuracy over several seeds), reconstruction with the calibrated rig, the
synthetic generators, bad input, and the command line.

The accuracy claims are those of docs/calibration.md (measured over seeds 0-9 by
benchmarks/calibration.py); here they are checked on seeds 0-4 with the default scene: a 200 x
200 image, shiny spheres of radius 20 (40 px orthographic, 44 px pinhole) at two placements,
1 % noise, 8-bit images with saturated highlights, every third standard light distant.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

import nplps
from nplps import calibrate as cal
from nplps import synth_calibration as scenes
from nplps.cli import main

WD = 200.0  # working distance of the standard scenes
SEEDS = range(5)


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    return np.degrees(np.arctan2(cross, np.sum(a * b, axis=-1)))


def _errors(result: cal.SphereCalibration, truth: nplps.Rig) -> tuple[np.ndarray, np.ndarray]:
    """Position errors of the point lights and direction errors (deg) of the distant lights;
    fails if a light has the wrong kind."""
    pos, dirs = [], []
    for light in result.lights:
        if truth.directional[light.index]:
            assert light.kind == "directional", f"light {light.index} is distant but came out {light.kind}"
            dirs.append(float(_angle(light.direction, truth.directions[light.index])))
        else:
            assert light.kind == "point", (
                f"light {light.index} is a point light but came out {light.kind}: {light.warning}"
            )
            pos.append(float(np.linalg.norm(light.position - truth.positions[light.index])))
    return np.array(pos), np.array(dirs)


def _calibrate(scene: scenes.SphereScene, **kw) -> cal.SphereCalibration:
    depth = scene.center_depths if not scene.rig.is_pinhole else None
    return cal.calibrate_spheres(scene.images, scene.rig, scene.radius, masks=scene.labels, center_depth=depth, **kw)


# ------------------------------------------------------------------------------------------------
# sphere calibration: accuracy
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("camera", ["orthographic", "pinhole"])
@pytest.mark.parametrize("lights", [8, 27])
@pytest.mark.parametrize("distant", [False, True], ids=["near", "third-distant"])
def test_light_positions_and_directions_over_seeds(camera, lights, distant):
    """Two placements of two spheres: light positions within 0.5 % of the working distance
    (RMS over the lights, averaged over seeds 0-4; no seed above 1 %) and distant lights within
    0.2 degrees on every seed. (With one sphere per placement the mean is 0.27-0.56 %:
    docs/calibration.md.)"""
    rms, worst_dir = [], []
    for seed in SEEDS:
        scene = scenes.make_sphere_scene(camera, lights=lights, directional=distant, spheres=2, noise=0.01, seed=seed)
        result = _calibrate(scene)
        assert all(light.spheres == 4 for light in result.lights)
        assert all(s.outline_sigma == 0.01 for s in result.spheres)  # the separating fits
        pos, dirs = _errors(result, scene.rig)
        rms.append(100.0 * np.sqrt(np.mean(pos**2)) / WD)
        worst_dir.append(dirs.max() if dirs.size else 0.0)
        assert result.refinement is not None and result.refinement["dropped"] == 0
    assert np.mean(rms) <= 0.5 and max(rms) <= 1.0, (
        f"position RMS, % of the working distance, per seed: {np.round(rms, 3)}"
    )
    assert max(worst_dir) <= 0.2, f"largest direction error per seed (deg): {np.round(worst_dir, 3)}"


def test_joint_refinement_corrects_image_outlines():
    """Outlines found in the images (not masks) put the spheres a little off; the joint
    refinement with the highlights brings the lights back (pinhole, 27 lights, a third distant,
    seeds 0-4; benchmark: 1.83 % -> 0.40 % of the working distance)."""
    before, after = [], []
    for seed in SEEDS:
        scene = scenes.make_sphere_scene("pinhole", lights=27, directional=True, noise=0.01, seed=seed)
        for refine, out in ((False, before), (True, after)):
            pos, _ = _errors(_calibrate(scene, refine=refine, outline="images"), scene.rig)
            out.append(100.0 * np.sqrt(np.mean(pos**2)) / WD)
    assert np.mean(after) < 0.5 * np.mean(before), (before, after)
    assert np.mean(after) < 0.5, after


def test_sphere_centres_from_masks():
    """From a mask that is the pixel sampling of the sphere (before any refinement): the widest
    separating circle puts the centre's x, y within 0.08 px (orthographic; typically 0.01 px),
    the widest separating cone puts the centre within 0.1 % of its distance (pinhole)."""
    for camera in ("orthographic", "pinhole"):
        scene = scenes.make_sphere_scene(camera, lights=8, noise=0.01, seed=0)
        result = _calibrate(scene, refine=False)
        pixel = 100.0 / 200.0
        for s, c in zip(result.spheres, np.concatenate(scene.centers), strict=False):
            if camera == "orthographic":
                assert np.linalg.norm(s.center[:2] - c[:2]) < 0.08 * pixel
                assert abs(s.scale_check - 1.0) < 0.005
            else:
                assert np.linalg.norm(s.center - c) < 1e-3 * np.linalg.norm(c)
            assert s.fit_rms < 0.35 and s.outline_sigma == 0.01


def test_detection_finds_the_spheres():
    """Without masks the spheres are found in the images. Detected outlines are less exact than
    masks (docs/calibration.md: about 0.03 px orthographic and 0.2 % of the distance pinhole
    with these lights, but 0.2 px orthographic when all 27 lights are near, which leaves the
    far lights' depths several % off): here, 27 lights of which a third distant, centres within
    0.1 px laterally (orthographic) or 0.3 % of their distance (pinhole), lights within 1 % of
    the working distance."""
    for camera in ("orthographic", "pinhole"):
        for seed in range(3):
            scene = scenes.make_sphere_scene(camera, lights=27, directional=True, spheres=2, noise=0.01, seed=seed)
            depth = scene.center_depths if camera == "orthographic" else None
            result = cal.calibrate_spheres(
                scene.images, scene.rig, scene.radius, detect=(30, 60), count=2, center_depth=depth
            )
            truth = np.concatenate(scene.centers)
            assert len(result.spheres) == 4
            for s in result.spheres:
                err = np.linalg.norm(truth - s.center, axis=1).min()
                assert err < (0.05 if camera == "orthographic" else 3e-3 * 180.0), (camera, seed, s.center, err)
            pos, dirs = _errors(result, scene.rig)
            assert 100.0 * np.sqrt(np.mean(pos**2)) / WD < 1.0
            assert dirs.max() < 0.2


# ------------------------------------------------------------------------------------------------
# the whole pipeline: spheres, board, reconstruction
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("camera", ["orthographic", "pinhole"])
def test_reconstruction_with_the_calibrated_rig(camera):
    """Spheres (positions) then a board (intensities, with the calibrated positions) give a rig
    whose reconstruction is within 0.2 degrees (mean normal error) of the true rig's, on seeds
    0-2 (27 lights, a third of them distant)."""
    for seed in range(3):
        scene = scenes.make_sphere_scene(camera, lights=27, directional=True, noise=0.01, seed=seed)
        positions = _calibrate(scene)
        board = scenes.make_board_scene(scene.rig, noise=0.01, seed=seed + 100)
        rig = cal.calibrate_intensities(board.images, positions.rig, WD).rig
        obj = nplps.make_scene("bumps", n=96, camera=camera, directional=True, seed=seed)
        calibrated = nplps.Rig(camera=obj.rig.camera, lights=rig.lights)  # the lights with their intensities
        depth = obj.mean_depth
        r_true = nplps.reconstruct(obj.images, obj.rig, mask=obj.mask, depth=depth, iterations=30, tol=1e-8)
        r_cal = nplps.reconstruct(obj.images, calibrated, mask=obj.mask, depth=depth, iterations=30, tol=1e-8)
        m, gt = obj.mask, obj.normals
        e_true = np.mean(_angle(r_true.normals[m], gt[m]))
        e_cal = np.mean(_angle(r_cal.normals[m], gt[m]))
        between = np.mean(_angle(r_cal.normals[m], r_true.normals[m]))
        assert e_cal - e_true <= 0.2 and between <= 0.2, (seed, e_true, e_cal, between)


# ------------------------------------------------------------------------------------------------
# intensity calibration
# ------------------------------------------------------------------------------------------------
def _relative(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.exp(np.mean(np.log(v)))


def _positions_only(rig: nplps.Rig) -> nplps.Rig:
    return nplps.Rig.from_arrays(rig.camera, rig.positions, directions=rig.directions)


@pytest.mark.parametrize("camera", ["orthographic", "pinhole"])
def test_intensities_of_isotropic_lights(camera):
    """Relative intensities within 1 % (1 % noise, 8-bit) on seeds 0-4; a tilted board."""
    plane = ([0.05, -0.1, -1.0], -1.0 * WD)
    for seed in SEEDS:
        rig = scenes.standard_rig(camera, n=160, lights=27, directional=True)
        phi = np.random.default_rng(seed).uniform(0.65, 1.35, rig.n_lights)
        rig = rig.with_intensities(rig.intensities * phi[:, None])
        board = scenes.make_board_scene(rig, n=160, plane=plane, noise=0.01, seed=seed)
        start = _positions_only(rig)
        result = cal.calibrate_intensities(board.images, start, plane)
        err = np.abs(result.intensities[:, 0] / _relative(rig.intensities[:, 0]) - 1.0)
        assert err.max() < 0.01, (seed, err.max())
        np.testing.assert_allclose(np.exp(np.mean(np.log(result.intensities))), 1.0, rtol=1e-12)
        np.testing.assert_array_equal(result.rig.positions, start.positions)
        np.testing.assert_array_equal(result.rig.directions, start.directions)


def test_intensities_mu_and_directions_of_leds():
    """LEDs (mu 0.5-2, unequal intensities): with fit_mu and fit_direction the intensities come
    back within 1 %, mu within 0.2 and the directions within 2 degrees (seeds 0-4)."""
    for seed in SEEDS:
        rig = scenes.standard_rig("pinhole", n=160, lights=27, directional=True, led=True)
        board = scenes.make_board_scene(rig, n=160, noise=0.01, seed=seed)
        result = cal.calibrate_intensities(board.images, _positions_only(rig), WD, fit_mu=True, fit_direction=True)
        truth = _relative(rig.intensities.mean(axis=1))
        assert np.abs(result.intensities[:, 0] / truth - 1.0).max() < 0.01
        point = ~rig.directional
        assert np.abs(result.mu[point] - rig.mu[point]).max() < 0.2
        assert _angle(result.axes[point], rig.axes[point]).max() < 2.0


def test_intensities_with_a_textured_board_and_vignetting():
    """albedo="per_pixel" absorbs a board texture and a cos^4-like falloff shared by all lights."""
    rig = scenes.standard_rig("orthographic", n=120, lights=8)
    phi = np.linspace(0.7, 1.3, rig.n_lights)
    rig = rig.with_intensities(phi)
    yy, xx = np.mgrid[:120, :120] / 119.0 - 0.5
    albedo = (0.7 + 0.2 * np.sin(9 * xx) * np.cos(7 * yy)) * (1 - 0.6 * (xx**2 + yy**2))
    board = scenes.make_board_scene(rig, n=120, albedo=albedo, noise=0.005, seed=1)
    uniform = cal.calibrate_intensities(board.images, _positions_only(rig), WD)
    per_pixel = cal.calibrate_intensities(board.images, _positions_only(rig), WD, albedo="per_pixel")
    err_u = np.abs(uniform.intensities[:, 0] / _relative(phi) - 1).max()
    err_p = np.abs(per_pixel.intensities[:, 0] / _relative(phi) - 1).max()
    assert err_p < 0.01 and err_p < err_u
    assert np.nanstd(per_pixel.albedo) > 0.05


def test_colour_intensities():
    """RGB board images give per-channel intensities (colour ratios kept)."""
    rig = scenes.standard_rig("orthographic", n=100, lights=8, led=True)
    board = scenes.make_board_scene(rig, n=100, noise=0.0, bits=0)
    rgb = np.repeat(board.images[..., None], 3, axis=3).astype(np.float32)
    # Tint each light's channels by its own RGB intensity ratios.
    ratio = rig.intensities / rig.intensities.mean(axis=1, keepdims=True)
    rgb *= ratio[:, None, None, :].astype(np.float32)
    result = cal.calibrate_intensities(rgb, rig, WD, color=True)  # the rig's LED mu and axes
    assert result.intensities.shape == (8, 3)
    np.testing.assert_allclose(result.intensities / _relative(rig.intensities), 1.0, atol=0.01)


# ------------------------------------------------------------------------------------------------
# reports, warnings and errors
# ------------------------------------------------------------------------------------------------
def test_single_sphere_gives_directions_with_warnings(tmp_path):
    scene = scenes.make_sphere_scene("orthographic", n=160, lights=8, radius=16, noise=0.0, seed=0)
    result = cal.calibrate_spheres(
        scene.images[:1], scene.rig, scene.radius, masks=scene.labels[:1], center_depth=scene.center_depths[0]
    )
    assert all(
        light.kind == "directional" and light.spheres == 1 and "one sphere" in light.warning for light in result.lights
    )
    assert sum("one sphere" in w for w in result.warnings) == 8
    assert any("smaller than 40 pixels" in w and "25.6 px" in w for w in result.warnings)
    table = result.table()
    assert "directional" in table and "one sphere" in table
    result.save(tmp_path / "rig.json")
    loaded = nplps.Rig.load(tmp_path / "rig.json")
    assert loaded.directional.all() and np.allclose(np.linalg.norm(loaded.directions, axis=1), 1.0)


def test_rig_file_and_report(tmp_path):
    scene = scenes.make_sphere_scene("pinhole", n=160, lights=8, radius=16, noise=0.0, seed=0)
    result = _calibrate(scene)
    assert result.highlights.shape == (8, 2, 2) and np.isfinite(result.highlights).all()
    assert result.status == [["ok", "ok"]] * 8
    result.save(tmp_path / "rig.json")
    data = json.loads((tmp_path / "rig.json").read_text())
    assert data["version"] == nplps.rig.RIG_FILE_VERSION and data["camera"]["model"] == "pinhole"
    assert all(light["intensity"] == 1.0 for light in data["lights"])
    loaded = nplps.Rig.load(tmp_path / "rig.json")
    expected = np.array([light.position if light.kind == "point" else light.direction for light in result.lights])
    np.testing.assert_allclose(np.where(loaded.directional[:, None], loaded.directions, loaded.positions), expected)
    assert "spheres" in result.table().splitlines()[0]


def test_a_light_seen_nowhere_blocks_the_rig():
    scene = scenes.make_sphere_scene("orthographic", n=160, lights=8, radius=16, noise=0.0, seed=0)
    images = [im.copy() for im in scene.images]
    for im in images:
        im[3] = 20  # light 3: no highlight (a flat dark image)
    result = cal.calibrate_spheres(
        images, scene.rig, scene.radius, masks=scene.labels, center_depth=scene.center_depths
    )
    assert result.lights[3].kind == "missing" and result.lights[3].spheres == 0
    assert result.status[3] == ["no highlight (too faint)"] * 2
    with pytest.raises(nplps.RigError, match=r"light.*3.*not seen"):
        _ = result.rig


def test_bad_input_is_reported():
    scene = scenes.make_sphere_scene("orthographic", n=120, lights=8, radius=12, noise=0.0, seed=0)
    cam = scene.rig
    with pytest.raises(nplps.InputError, match="orthographic camera needs the depth"):
        cal.calibrate_spheres(scene.images, cam, scene.radius, masks=scene.labels)
    with pytest.raises(nplps.InputError, match=r"one mask .* per placement"):
        cal.calibrate_spheres(scene.images, cam, scene.radius, masks=scene.labels[:1], center_depth=180)
    with pytest.raises(nplps.InputError, match="has no mask"):
        cal.calibrate_spheres(scene.images, cam, scene.radius, center_depth=180)
    with pytest.raises(nplps.InputError, match="mask is empty"):
        cal.calibrate_spheres(scene.images, cam, scene.radius, masks=[np.zeros((120, 120), bool)] * 2, center_depth=180)
    with pytest.raises(nplps.InputError, match="placement 1 has 7 images"):
        cal.calibrate_spheres(
            [scene.images[0], scene.images[1][:7]], cam, scene.radius, masks=scene.labels, center_depth=180
        )
    with pytest.raises(nplps.InputError, match="radius must be positive"):
        cal.calibrate_spheres(scene.images, cam, -1.0, masks=scene.labels, center_depth=180)
    with pytest.raises(nplps.InputError, match="parallel_tol"):
        cal.calibrate_spheres(scene.images, cam, scene.radius, masks=scene.labels, center_depth=180, parallel_tol=-1)
    with pytest.raises(nplps.InputError, match="centre depths"):
        cal.calibrate_spheres(scene.images, cam, scene.radius, masks=scene.labels, center_depth=[[180, 180], 180])
    with pytest.raises(nplps.InputError, match="no sphere found"):
        cal.calibrate_spheres(scene.images, cam, scene.radius, detect=(2, 4), center_depth=180)
    with pytest.raises(nplps.RigError):
        cal.calibrate_spheres(scene.images, {"model": "fisheye"}, scene.radius, masks=scene.labels, center_depth=180)
    board = scenes.make_board_scene(cam, n=120, noise=0.0)
    with pytest.raises(nplps.InputError, match="board images but the rig has"):
        cal.calibrate_intensities(board.images[:5], cam, WD)
    with pytest.raises(nplps.InputError, match="edge-on"):
        cal.calibrate_intensities(board.images, cam, ([1.0, 0.0, 0.0], 0.0))
    with pytest.raises(nplps.InputError, match="fit_direction needs fit_mu"):
        cal.calibrate_intensities(board.images, cam, WD, fit_direction=True)
    with pytest.raises(nplps.InputError, match="albedo must be"):
        cal.calibrate_intensities(board.images, cam, WD, albedo="textured")


def test_scene_generators():
    scene = scenes.make_sphere_scene("orthographic", n=160, lights=8, radius=16, noise=0.01, seed=3, spheres=2)
    assert len(scene.images) == 2 and scene.images[0].shape == (8, 160, 160) and scene.images[0].dtype == np.uint8
    for stack, labels in zip(scene.images, scene.labels, strict=False):
        assert set(np.unique(labels)) == {0, 1, 2}
        saturated = [(im[labels > 0] == 255).sum() for im in stack]
        assert min(saturated) >= 3, "every highlight saturates"
        assert np.median(stack[:, labels > 0]) < 200, "the diffuse part does not"
    assert scene.rig.n_lights == 8 and scene.light_indices == list(scenes.LIGHTS_8)
    np.testing.assert_allclose(
        scene.rig.positions, nplps.make_scene("saddle", n=8).rig.positions[list(scenes.LIGHTS_8)]
    )
    board = scenes.make_board_scene(scene.rig, n=160, noise=0.0, bits=16)
    assert board.images.dtype == np.uint16 and board.images.max() <= 65535 * 0.9 + 1


# ------------------------------------------------------------------------------------------------
# command line
# ------------------------------------------------------------------------------------------------
def test_command_line_end_to_end(tmp_path, capsys):
    out = tmp_path / "calib"
    assert main(["synth-calibration", "--out", str(out), "--lights", "8", "--directional"]) == 0
    printed = capsys.readouterr().out
    assert "nplps calibrate spheres" in printed and "nplps calibrate intensity" in printed
    scene = json.loads((out / "scene.json").read_text())
    args = [
        "calibrate",
        "spheres",
        str(out / "placement_0"),
        str(out / "placement_1"),
        "--camera",
        str(out / "camera.json"),
        "--radius",
        "20",
        "--out",
        str(out / "rig_spheres.json"),
        "--report",
        str(out / "report.json"),
        "-q",
    ]
    assert main(args) == 2  # orthographic: the centre depth is missing
    assert "needs the depth of the sphere centres" in capsys.readouterr().err
    depths = [str(d[0]) for d in scene["center_depths"]]
    assert main([*args, "--center-depth", depths[0], "--center-depth", depths[1]]) == 0
    printed = capsys.readouterr().out
    assert "joint refinement" in printed and "rms miss" in printed
    rig = nplps.Rig.load(out / "rig_spheres.json")
    truth = nplps.Rig.load(out / "rig_true.json")
    assert rig.n_lights == 8 and (rig.directional == truth.directional).all()
    point = ~truth.directional
    assert np.sqrt(np.mean(np.sum((rig.positions[point] - truth.positions[point]) ** 2, axis=1))) < 0.005 * WD
    report = json.loads((out / "report.json").read_text())
    assert len(report["lights"]) == 8 and len(report["spheres"]) == 2
    assert (
        main(
            [
                "calibrate",
                "intensity",
                str(out / "board"),
                "--rig",
                str(out / "rig_spheres.json"),
                "--plane-depth",
                "200",
                "--out",
                str(out / "rig.json"),
                "-q",
            ]
        )
        == 0
    )
    assert "intensity" in capsys.readouterr().out
    final = nplps.Rig.load(out / "rig.json")
    phi = final.intensities[:, 0] / _relative(truth.intensities[:, 0])
    assert np.abs(phi / np.exp(np.mean(np.log(phi))) - 1).max() < 0.02


def test_command_line_errors(tmp_path, capsys):
    assert main(["calibrate"]) == 2
    assert "spheres" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    cam = tmp_path / "camera.json"
    cal.save_camera(cam, scenes.standard_rig("pinhole", n=64, lights=8))
    assert (
        main(
            [
                "calibrate",
                "spheres",
                str(empty),
                "--camera",
                str(cam),
                "--radius",
                "10",
                "--detect",
                "5",
                "9",
                "--out",
                str(tmp_path / "r.json"),
            ]
        )
        == 2
    )
    assert "no image files" in capsys.readouterr().err
    assert (
        main(
            [
                "calibrate",
                "spheres",
                str(empty),
                "--camera",
                str(cam),
                "--radius",
                "10",
                "--out",
                str(tmp_path / "r.json"),
            ]
        )
        == 2
    )
    assert "masks" in capsys.readouterr().err
    assert (
        main(
            [
                "calibrate",
                "intensity",
                str(empty),
                "--rig",
                str(cam),
                "--plane-depth",
                "100",
                "--out",
                str(tmp_path / "r.json"),
            ]
        )
        == 2
    )
    capsys.readouterr()


@pytest.mark.parametrize(
    "command", [["calibrate"], ["calibrate", "spheres"], ["calibrate", "intensity"], ["synth-calibration"]]
)
def test_command_line_help(capsys, command):
    with pytest.raises(SystemExit) as exit_info:
        from nplps.cli import build_parser

        build_parser().parse_args([*command, "--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert "usage: nplps" in out and "example" in out
