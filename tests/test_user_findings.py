"""Valid inputs a user gave that were refused, misleading readings and silent results.

Rigs of fewer than 3 lights for prediction and calibration, sphere calibration of a placement
given twice or of small spheres, the held-out reading against its own numbers, calibrate
writing over existing files, DiLiGenT's filenames.txt in another encoding, bad --count and
--scheduler values, the report of a preset's pre-processing, and meshes beyond float32 in PLY
and OBJ.
"""

from __future__ import annotations

import contextlib
import io
import json
import re
from pathlib import Path

import numpy as np
import pytest

import nplps
import nplps.calibrate as cal
import nplps.export
from nplps import synth_calibration as scenes
from nplps.captures import load_diligent
from nplps.cli import main
from nplps.evaluation import reading


def run(*argv: object) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main([str(a) for a in argv])
    return status, out.getvalue(), err.getvalue()


def assert_one_line_error(status: int, stderr: str, *words: str) -> str:
    assert status == 2, stderr
    assert "Traceback" not in stderr
    lines = [line for line in stderr.splitlines() if line.startswith("nplps: error:")]
    assert len(lines) == 1, stderr
    for word in words:
        assert word in lines[0], (word, lines[0])
    return lines[0]


# --------------------------------------------------------------------------------------------------
# Rigs of 1 and 2 lights: prediction, calibration
# --------------------------------------------------------------------------------------------------


def test_predict_under_a_two_light_rig() -> None:
    scene = nplps.make_scene("bumps", n=32, seed=0)
    result = nplps.reconstruct(scene.images, scene.rig, depth=scene.mean_depth, mask=scene.mask)
    two = scene.rig.subset([0, 9])
    predicted = result.predict(two)
    assert predicted.shape == (2, 32, 32)
    inside = np.isfinite(predicted)
    assert inside[:, scene.mask].mean() > 0.9
    # The same images as predicted under the full rig for those lights.
    np.testing.assert_allclose(predicted, result.predict(scene.rig, lights=[0, 9]), equal_nan=True)
    with pytest.raises(nplps.RigError, match="at least 3 lights"):
        nplps.reconstruct(scene.images[[0, 9]], two, depth=scene.mean_depth, mask=scene.mask)


def test_one_light_calibration_spheres_then_board(tmp_path: Path) -> None:
    scene = scenes.make_sphere_scene("orthographic", n=160, lights=[3], radius=25, seed=0)
    spheres = cal.calibrate_spheres(
        scene.images, scene.rig, scene.radius, masks=scene.masks, center_depth=scene.center_depths
    )
    rig = spheres.rig
    assert rig.n_lights == 1 and spheres.lights[0].kind == "point"
    error = np.linalg.norm(rig.positions[0] - scene.rig.positions[0])
    assert error < 0.03 * np.linalg.norm(scene.rig.positions[0]), error
    spheres.save(tmp_path / "rig.json")
    assert nplps.Rig.load(tmp_path / "rig.json").n_lights == 1
    board = scenes.make_board_scene(rig, n=160, distance=scene.distance)
    intensities = cal.calibrate_intensities(board.images, rig, board.plane)
    # One light: the relative intensity is 1 (geometric mean 1), the fit is exact.
    np.testing.assert_allclose(intensities.intensities, [[1.0]])
    assert intensities.rms[0] < 0.05


# --------------------------------------------------------------------------------------------------
# Sphere calibration: a placement given twice, small spheres
# --------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def spheres_40px() -> scenes.SphereScene:
    # radius 25 at 160 pixels for 100 units: 40 px, the size the docs ask for.
    return scenes.make_sphere_scene("orthographic", n=160, lights=8, radius=25, seed=0)


def test_placement_given_twice_is_named_in_a_warning(spheres_40px: scenes.SphereScene) -> None:
    s = spheres_40px
    twice = cal.calibrate_spheres(
        [s.images[0], s.images[0]], s.rig, s.radius, masks=[s.masks[0]] * 2, center_depth=[s.center_depths[0]] * 2
    )
    assert all(light.kind == "directional" for light in twice.lights)  # what the user got silently
    same = [w for w in twice.warnings if "placements 0 and 1" in w]
    assert len(same) == 1, twice.warnings
    assert "same place" in same[0] and "given twice" in same[0]
    # Two real placements: no such warning (and no small-sphere warning at 40 px).
    moved = cal.calibrate_spheres(s.images, s.rig, s.radius, masks=s.masks, center_depth=s.center_depths)
    assert not [w for w in moved.warnings if "same place" in w or "pixels in radius" in w], moved.warnings
    assert all(light.kind == "point" for light in moved.lights)


def test_small_spheres_are_named_with_their_measured_radius() -> None:
    # radius 15 at 160 pixels: 24 px in the images.
    s = scenes.make_sphere_scene("orthographic", n=160, lights=8, radius=15, seed=0)
    result = cal.calibrate_spheres(s.images, s.rig, s.radius, masks=s.masks, center_depth=s.center_depths)
    small = [w for w in result.warnings if "pixels in radius" in w]
    assert len(small) == 1, result.warnings
    for sphere in result.spheres:
        assert abs(sphere.image_radius - 24.0) < 0.5
        assert f"sphere {sphere.index} (placement {sphere.placement}) {sphere.image_radius:.1f} px" in small[0]
    assert "40" in small[0]


def test_cli_prints_the_placement_warning(tmp_path: Path, spheres_40px: scenes.SphereScene) -> None:
    spheres_40px.save(tmp_path / "cal")
    p0 = tmp_path / "cal" / "placement_0"
    depth = ",".join(f"{z:g}" for z in spheres_40px.center_depths[0])
    status, _, stderr = run(
        "calibrate", "spheres", p0, p0, "--camera", tmp_path / "cal" / "camera.json", "--radius", "25",
        "--center-depth", depth, "--out", tmp_path / "rig.json", "-q",
    )  # fmt: skip
    assert status == 0, stderr
    assert re.search(r"nplps: warning: placements 0 and 1 put a sphere at the same place", stderr), stderr


# --------------------------------------------------------------------------------------------------
# The held-out reading follows its numbers
# --------------------------------------------------------------------------------------------------


def _check_reading(text: str, near: tuple[float, float], parallel: tuple[float, float]) -> None:
    """The reading may call a model better only if neither mean error says the opposite (lower is better)."""
    names = {"the near-light model (nplps)": near, "the parallel-light baseline": parallel}
    m = re.match(r"reading: (.+?) predicts the held-out images better than (.+?):", text)
    if m:
        (b_rel, b_shape), (w_rel, w_shape) = names[m.group(1)], names[m.group(2)]
        assert b_shape < w_shape, text
        assert b_rel <= 1.05 * w_rel, text  # the relative error does not clearly say the opposite


@pytest.mark.parametrize(
    ("near", "parallel"),
    [((0.2699, 0.04739), (0.1904, 0.05843)), ((0.19, 0.08), (0.334, 0.05)), ((0.5, 0.01), (0.1, 0.0101))],
)
def test_reading_says_mixed_when_the_errors_disagree(near: tuple[float, float], parallel: tuple[float, float]) -> None:
    text = reading(near, parallel)
    _check_reading(text, near, parallel)
    assert "\n" not in text
    lower_rel = "near-light" if near[0] < parallel[0] else "parallel-light"
    # The model with the lower relative error is named as having it, with both numbers.
    assert re.search(rf"{lower_rel} (model \(nplps\)|baseline) (has )?the lower mean relative error", text), text
    assert f"{min(near[0], parallel[0]):.3g} vs {max(near[0], parallel[0]):.3g}" in text, text


def test_reading_when_the_errors_agree_is_unchanged() -> None:
    text = reading((0.02, 0.01), (0.05, 0.04))
    assert text.startswith("reading: the near-light model (nplps) predicts the held-out images better")
    assert "mixed" not in reading((0.05, 0.06), (0.0502, 0.03))  # relative errors a tie: shape decides


def test_evaluate_hehe12_refine_lights_reading_follows_the_table(shared_capture) -> None:
    folder = shared_capture("hehe12")
    status, stdout, stderr = run(
        "evaluate", "--capture", "hehe12", folder, "--depth", "200", "--bin", "16", "--refine-lights", "both", "-q"
    )
    assert status == 0, stderr
    lines = stdout.rstrip("\n").splitlines()
    mean = [float(v) for v in lines[-3].split()[1:]]
    assert lines[-3].split()[0] == "mean" and len(mean) == 4
    _check_reading(lines[-1], (mean[0], mean[1]), (mean[2], mean[3]))


# --------------------------------------------------------------------------------------------------
# calibrate --out / --report do not replace files silently; --count
# --------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def calibration_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("cal") / "cal"
    status, _, stderr = run("synth-calibration", "--out", out, "--lights", "8", "--size", "120", "--radius", "34")
    assert status == 0, stderr
    return out


def _spheres(folder: Path, *extra: object) -> tuple[int, str, str]:
    return run(
        "calibrate", "spheres", folder / "placement_0", folder / "placement_1", "--camera", folder / "camera.json",
        "--radius", "34", "--center-depth", "166", "-q", *extra,
    )  # fmt: skip


def test_calibrate_spheres_refuses_existing_out_and_report(tmp_path: Path, calibration_folder: Path) -> None:
    rig, report = tmp_path / "rig.json", tmp_path / "report.json"
    rig.write_text("mine")
    status, _, stderr = _spheres(calibration_folder, "--out", rig)
    assert_one_line_error(status, stderr, "--out", str(rig), "--overwrite")
    assert rig.read_text() == "mine"
    report.write_text("mine too")
    status, _, stderr = _spheres(calibration_folder, "--out", tmp_path / "new.json", "--report", report)
    assert_one_line_error(status, stderr, "--report", str(report), "--overwrite")
    assert report.read_text() == "mine too" and not (tmp_path / "new.json").exists()
    status, _, stderr = _spheres(calibration_folder, "--out", rig, "--report", report, "--overwrite")
    assert status == 0, stderr
    assert nplps.Rig.load(rig).n_lights == 8 and "lights" in json.loads(report.read_text())
    status, _, stderr = _spheres(calibration_folder, "--out", tmp_path)
    assert_one_line_error(status, stderr, "--out", "directory")


def test_calibrate_intensity_refuses_an_existing_out(tmp_path: Path, calibration_folder: Path) -> None:
    target = tmp_path / "rig.json"
    target.write_text("mine")
    argv = ["calibrate", "intensity", calibration_folder / "board", "--rig", calibration_folder / "rig_true.json"]
    argv += ["--plane-depth", "200", "--out", target, "-q"]
    status, _, stderr = run(*argv)
    assert_one_line_error(status, stderr, "--out", str(target), "--overwrite")
    assert target.read_text() == "mine"
    status, _, stderr = run(*argv, "--overwrite")
    assert status == 0, stderr
    assert nplps.Rig.load(target).n_lights == 8


@pytest.mark.parametrize("count", ["-1", "0"])
def test_calibrate_count_below_one(tmp_path: Path, calibration_folder: Path, count: str) -> None:
    status, _, stderr = _spheres(calibration_folder, "--detect", "20", "60", "--count", count, "--out", tmp_path / "r")
    assert_one_line_error(status, stderr, "--count", count)
    with pytest.raises(nplps.InputError, match="count"):
        cal.calibrate_spheres(np.zeros((3, 40, 40)), nplps.make_scene("sphere", n=8).rig, 5.0, detect=(5, 9), count=-1)


# --------------------------------------------------------------------------------------------------
# nplps batch --scheduler
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("address", ["not a url", "tcp://host:99999", "http://x:8786", ":8786", "inproc://"])
def test_batch_scheduler_that_is_not_an_address(tmp_path: Path, address: str) -> None:
    pytest.importorskip("distributed")
    scene = tmp_path / "caps" / "c1"
    assert run("synth", "sphere", "--size", "16", "--out", scene)[0] == 0
    status, _, stderr = run(
        "batch", f"{tmp_path}/caps/*", "--rig", scene / "rig.json", "--depth", "200", "--scheduler", address,
        "--out", tmp_path / "out",
    )  # fmt: skip
    assert_one_line_error(status, stderr, "--scheduler", address)
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------------------------------
# DiLiGenT filenames.txt
# --------------------------------------------------------------------------------------------------


def _diligent(root: Path, names: bytes) -> Path:
    obj = root / "toyPNG"
    obj.mkdir(parents=True)
    (obj / "filenames.txt").write_bytes(names)
    np.savetxt(obj / "light_directions.txt", [[0.0, 0.0, 1.0], [0.3, 0.0, 0.95], [0.0, 0.3, 0.95]])
    np.savetxt(obj / "light_intensities.txt", np.ones((3, 3)))
    return obj


def test_diligent_filenames_not_utf8(tmp_path: Path) -> None:
    obj = _diligent(tmp_path, "bild_ä1.png\nbild_ä2.png\nbild_ä3.png\n".encode("latin-1"))
    with pytest.raises(nplps.InputError, match=r"filenames\.txt.*not UTF-8"):
        load_diligent(obj)
    status, _, stderr = run("reconstruct", "--capture", "diligent", obj, "--depth", "100", "--out", tmp_path / "r")
    assert_one_line_error(status, stderr, "filenames.txt", "UTF-8")
    (obj / "filenames.txt").write_bytes(b"001.png\n\x00\x00\n003.png\n")
    with pytest.raises(nplps.InputError, match=r"filenames\.txt.*NUL"):
        load_diligent(obj)


def test_diligent_filenames_utf8_with_bom(tmp_path: Path) -> None:
    obj = _diligent(tmp_path, "\ufeffbild_ä1.png\r\nb2.png\r\nb3.png\r\n".encode())
    for name in ("bild_ä1.png", "b2.png", "b3.png"):
        (obj / name).write_bytes(b"")  # the names are only resolved here, not read
    capture = load_diligent(obj, normals=False)
    assert [p.name for p in capture.images] == ["bild_ä1.png", "b2.png", "b3.png"]


# --------------------------------------------------------------------------------------------------
# The report shows the pre-processing applied
# --------------------------------------------------------------------------------------------------


def _report_rows(page: str) -> dict[str, str]:
    return dict(re.findall(r"<tr><th>([^<]*)</th><td>([^<]*)</td></tr>", page))


def test_report_shows_the_preprocessing_steps(tmp_path: Path) -> None:
    scene = nplps.make_scene("sphere", n=12, seed=0)
    result = nplps.reconstruct(scene.images, scene.rig, depth=scene.mean_depth, mask=scene.mask)
    steps = ["sRGB decoded", "ambient 'dark.png' subtracted", "divided by the cos^4 vignetting map"]
    options = {"capture": "near_ps", "srgb": False, "ambient": None, "vignetting": None, "preprocessing": steps}
    result.save(tmp_path / "r", options=options)
    assert run("report", tmp_path / "r", "--out", tmp_path / "r.html")[0] == 0
    page = (tmp_path / "r.html").read_text()
    rows = _report_rows(page)
    assert rows["pre-processing"] == "; ".join(steps).replace("'", "&#x27;")
    # The flags as typed (false / null) are not shown as if they described what was done.
    assert not {"srgb", "ambient", "vignetting"} & set(rows), sorted(rows)
    # A result without recorded steps shows its options as recorded, and no pre-processing row.
    result.save(tmp_path / "old", options={"srgb": True})
    assert run("report", tmp_path / "old", "--out", tmp_path / "old.html")[0] == 0
    rows = _report_rows((tmp_path / "old.html").read_text())
    assert rows["srgb"] == "true" and "pre-processing" not in rows


def test_report_of_a_hehe12_preset(tmp_path: Path, shared_capture) -> None:
    folder = shared_capture("hehe12")
    status, _, stderr = run(
        "reconstruct", "--capture", "hehe12", folder, "--depth", "200", "--bin", "16", "--out", tmp_path / "r", "-q"
    )
    assert status == 0, stderr
    rows = _report_rows((tmp_path / "r" / "report.html").read_text())
    assert "subtracted" in rows["pre-processing"] and "vignetting" in rows["pre-processing"]
    assert "binned 16 x 16" in rows["pre-processing"]
    assert "ambient" not in rows and "vignetting" not in rows


# --------------------------------------------------------------------------------------------------
# PLY / OBJ beyond float32
# --------------------------------------------------------------------------------------------------


def _far_grid() -> tuple[np.ndarray, np.ndarray]:
    v = np.zeros((3, 3, 3))
    v[..., 0], v[..., 1], v[..., 2] = np.arange(3)[None, :], np.arange(3)[:, None], 100.0
    v[1, 1, 2] = 1e39  # beyond float32 (3.4e38)
    return v, np.ones((2, 2), dtype=bool)


@pytest.mark.parametrize("writer", ["write_ply", "write_point_cloud"])
def test_ply_refuses_a_vertex_beyond_float32(tmp_path: Path, writer: str) -> None:
    v, mask = _far_grid()
    with pytest.raises(nplps.InputError, match=r"PLY file .*m\.ply.*float32"):
        getattr(nplps.export, writer)(tmp_path / "m.ply", v, mask)
    assert not (tmp_path / "m.ply").exists()


def test_write_meshes_writes_nothing_when_ply_refuses(tmp_path: Path) -> None:
    v, mask = _far_grid()
    with pytest.raises(nplps.InputError, match="PLY"):
        nplps.export.write_meshes(tmp_path / "m.ply", tmp_path / "m.obj", v, mask)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("opengl", [False, True])
def test_obj_writes_a_vertex_beyond_float32_exactly(tmp_path: Path, opengl: bool) -> None:
    v, mask = _far_grid()
    nplps.export.write_obj(tmp_path / "m.obj", v, mask, albedo=np.full((3, 3), 0.5), opengl=opengl)
    text = (tmp_path / "m.obj").read_text()
    assert "inf" not in text
    rows = [line.split()[1:] for line in text.splitlines() if line.startswith("v ")]
    points = np.array([[float(x) for x in row[:3]] for row in rows])
    flip = np.array([1.0, -1.0, -1.0]) if opengl else np.ones(3)
    np.testing.assert_array_equal(points, v.reshape(-1, 3) * flip)
    assert all(len(row) == 6 for row in rows)  # the colours are kept on the widened line too


def test_an_ignored_depth_range_does_not_fail_the_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--depth-range without --depth auto is ignored with a warning: even a reversed one must not
    then fail the run (it did, in every capture of a batch)."""
    from nplps.cli import main

    s = nplps.make_scene("bumps", n=24, seed=0)
    s.save(tmp_path / "scene")
    sc = str(tmp_path / "scene")
    argv = ["reconstruct", sc, "--rig", f"{sc}/rig.json", "--mask", f"{sc}/mask.png"]
    argv += ["--depth", f"{s.mean_depth:.6g}", "--depth-range", "400,100", "--out", str(tmp_path / "out"), "-q"]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "--depth-range has no effect without --depth auto" in err
