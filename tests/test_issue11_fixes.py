"""Small fixes of issue 11: the distance curve CSV, the capture docs, repr, sizes, the evaluate reading."""

from __future__ import annotations

import dataclasses
import inspect
import re
import textwrap
from pathlib import Path

import numpy as np
import pytest

import nplps
import nplps.preprocess
from nplps import captures, cli
from nplps.cli.console import describe_size
from nplps.evaluation import reading

SIZE = 24


@pytest.fixture(scope="module")
def auto_result() -> tuple[nplps.Scene, nplps.Reconstruction]:
    """A small synthetic scene and its ``depth="auto"`` reconstruction."""
    s = nplps.make_scene("bumps", n=SIZE, seed=1)
    return s, nplps.reconstruct(s.images, s.rig, mask=s.mask, depth="auto")


def _four_lights() -> np.ndarray:
    return np.array([[0.0, 0.0, -100.0], [50.0, 0.0, -100.0], [0.0, 50.0, -100.0], [-50.0, -50.0, -100.0]])


def run(capsys, *argv):
    rc = cli.main([str(a) for a in argv])
    captured = capsys.readouterr()
    return rc, captured.out, captured.err


def _check_curve_csv(path, curves: list[np.ndarray]) -> None:
    text = path.read_text()
    assert text.splitlines()[0] == "region,distance,rms_residual"
    assert "np." not in text and "float64" not in text
    table = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    expected = np.concatenate([np.column_stack([np.full(len(c), r), c]) for r, c in enumerate(curves)])
    # Full precision: the numbers read back are the numbers of the result, bit for bit.
    np.testing.assert_array_equal(table, expected)


# --------------------------------------------------------------------------------------------------
# 1. distance_curve.csv holds plain numbers
# --------------------------------------------------------------------------------------------------


def test_save_curve_is_plain_csv(auto_result, tmp_path):
    _s, r = auto_result
    assert r.distance is not None and len(r.distance.curve[0]) > 5
    r.distance.save_curve(tmp_path / "curve.csv")
    _check_curve_csv(tmp_path / "curve.csv", r.distance.curve)


def test_cli_distance_curve_csv_parses(tmp_path, capsys):
    scene = tmp_path / "scene"
    rc, _, stderr = run(capsys, "synth", "bumps", "--size", SIZE, "--seed", "1", "--out", scene)
    assert rc == 0, stderr
    out = tmp_path / "result"
    argv = ["reconstruct", scene, "--rig", scene / "rig.json", "--mask", scene / "mask.png"]
    rc, _, stderr = run(capsys, *argv, "--depth", "auto", "--out", out, "-q")
    assert rc == 0, stderr
    table = np.loadtxt(out / "distance_curve.csv", delimiter=",", skiprows=1, ndmin=2)
    assert table.shape[1] == 3 and len(table) > 5
    assert np.all(table[:, 0] == 0) and np.all(np.isfinite(table[:, 1:]))
    assert np.all(np.diff(table[:, 1]) >= 0)
    assert "np." not in (out / "distance_curve.csv").read_text()


# --------------------------------------------------------------------------------------------------
# 2. the documented use of a capture (intensities in the rig, images not divided)
# --------------------------------------------------------------------------------------------------


def _docstring_example() -> str:
    """The code of the Examples section of ``nplps.captures``' module docstring."""
    doc = inspect.getdoc(captures) or ""
    after = doc.split("Examples\n--------\n", 1)[1]
    block = after.split("::\n", 1)[1]
    lines = []
    for line in block.splitlines():
        if line and not line.startswith("    "):
            break
        lines.append(line)
    return textwrap.dedent("\n".join(lines)).strip()


def test_capture_docs_do_not_divide_by_the_intensities():
    code = _docstring_example()
    assert "ball.rig()" in code and "intensities" not in code
    # The README's captures section shows the same code.
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    section = readme.split("## Real captures", 1)[1].split("\n## ", 1)[0]
    assert textwrap.indent(code, "  ") in section
    diligent_doc = inspect.getdoc(captures.load_diligent) or ""
    assert "divide image" not in diligent_doc.lower()


def test_documented_capture_example_on_the_ball(shared_capture, monkeypatch, angular_error):
    folder = shared_capture("diligent_ball")
    monkeypatch.chdir(folder.parent)
    namespace: dict[str, object] = {}
    exec(_docstring_example(), namespace)  # the documented example, exactly as written
    ball, result = namespace["ball"], namespace["result"]
    error = angular_error(result.normals, ball.normals_gt, ball.mask).mean()
    print(f"documented example on DiLiGenT's ball: mean normal error {error:.2f} deg")
    assert 3.5 < error < 4.6  # about 4.1 deg; dividing the images by the intensities too gave 16


# --------------------------------------------------------------------------------------------------
# 3. repr is one line; _repr_html_ a compact table
# --------------------------------------------------------------------------------------------------


def test_repr_is_one_line(auto_result):
    s, r = auto_result
    text = repr(r)
    assert "\n" not in text and "array" not in text and len(text) < 200
    lo, hi = np.nanmin(r.depth), np.nanmax(r.depth)
    h, w = r.shape
    assert text.startswith(f"<Reconstruction {w} x {h} pixels, ")
    for part in (
        "method='near'",
        f"status={r.status!r}",
        f"iterations={len(r.history)}",
        f"depth {lo:.6g} .. {hi:.6g}",
        f"mask {int(s.mask.sum())} pixels",
    ):
        assert part in text
    assert str(r) == text


def test_repr_of_a_non_square_parallel_result(scene):
    s = scene("sphere", n=24)
    r = nplps.reconstruct_parallel(s.images[:, :, :16], s.rig, mask=s.mask[:, :16], depth=s.mean_depth)
    assert repr(r).startswith("<Reconstruction 16 x 24 pixels, method='parallel', ")
    assert f"mask {int(s.mask[:, :16].sum())} pixels>" in repr(r)


def test_repr_html_is_a_compact_table(auto_result):
    _s, r = auto_result
    page = r._repr_html_()
    # The facts, then a small normal map and albedo (item 2: compact, embedded; see test_report.py).
    assert page.startswith("<div><table") and page.endswith("</div>")
    assert page.count("<img") == 2 and len(page) < 100_000
    for label in ("Size (W x H)", "Method", "Status", "Iterations", "Depth range", "Mask", "Estimated distance"):
        assert f">{label}</th>" in page
    h, w = r.shape
    assert f"{w} x {h} pixels" in page and f">{len(r.history)}</td>" in page
    assert f"{r.distance.distance[0]:.6g}" in page
    # The status reason is escaped text.
    r2 = dataclasses.replace(r, status_reason="a < b & c")
    assert "a &lt; b &amp; c" in r2._repr_html_()


# --------------------------------------------------------------------------------------------------
# 4. image sizes are printed width first, "W x H pixels"
# --------------------------------------------------------------------------------------------------


def test_cli_prints_sizes_width_first(tmp_path, capsys):
    """A 24-row, 16-column capture is "16 x 24 pixels" in the input note and in the summary."""
    import imageio.v3 as iio

    s = nplps.make_scene("bumps", n=24, seed=2)
    images, mask = s.images[:, :, :16], s.mask[:, :16]
    folder = tmp_path / "capture"
    folder.mkdir()
    for i, image in enumerate(images):
        iio.imwrite(folder / f"image_{i:02d}.png", np.round(np.clip(image, 0, 1) * 65535).astype(np.uint16))
    iio.imwrite(tmp_path / "mask.png", mask.astype(np.uint8) * 255)
    s.rig.save(tmp_path / "rig.json")
    argv = ["reconstruct", folder, "--rig", tmp_path / "rig.json", "--mask", tmp_path / "mask.png"]
    rc, stdout, stderr = run(capsys, *argv, "--depth", s.mean_depth, "--out", tmp_path / "out")
    assert rc == 0, stderr
    assert f"{len(images)} images of 16 x 24 pixels" in stderr
    assert re.search(rf"pixels +{int(mask.sum())} of 16 x 24 pixels\n", stdout)
    assert "24 x 16" not in stdout + stderr
    assert describe_size((24, 16)) == "16 x 24 pixels" == describe_size((24, 16, 3))


def test_library_messages_give_sizes_width_first():
    with pytest.raises(nplps.InputError, match=r"for images of 16 x 24 pixels"):
        rig = nplps.Rig.orthographic(1.0, lights=_four_lights())
        nplps.reconstruct(np.ones((4, 24, 16)), rig, depth=np.ones((3, 3)))
    with pytest.raises(nplps.InputError, match=r"3 x 2 pixels is smaller than one 4 x 4 block"):
        nplps.preprocess.bin_images(np.ones((1, 2, 3)), 4)


# --------------------------------------------------------------------------------------------------
# 5. nplps evaluate reads its table in one line
# --------------------------------------------------------------------------------------------------


def test_reading_names_the_better_model_and_by_how_much():
    text = reading((0.02, 0.01), (0.05, 0.04))
    assert "\n" not in text
    assert text.startswith("reading: the near-light model (nplps) predicts the held-out images better")
    assert "mean shape error 0.01 vs 0.04 (4.0x lower)" in text and "mean relative error 0.02 vs 0.05" in text
    text = reading((0.05, 0.06), (0.05, 0.03))
    assert text.startswith("reading: the parallel-light baseline predicts") and "(2.0x lower)" in text
    assert "(25x lower)" in reading((0.1, 0.002), (0.1, 0.05))
    assert "about equally well" in reading((0.05, 0.0410), (0.05, 0.0400))
    assert "no comparison" in reading((float("nan"), 0.01), (0.05, 0.04))


def test_cli_evaluate_prints_a_reading(tmp_path, capsys):
    scene = tmp_path / "scene"
    rc, _, stderr = run(
        capsys, "synth", "bumps", "--size", SIZE, "--camera", "pinhole", "--led", "--noise", "0.002", "--out", scene
    )
    assert rc == 0, stderr
    depth = nplps.make_scene("bumps", n=SIZE, camera="pinhole", led=True).mean_depth
    argv = ["evaluate", scene, "--rig", scene / "rig.json", "--mask", scene / "mask.png", "--depth", depth]
    rc, stdout, stderr = run(capsys, *argv, "--lights", "0,13", "-q")
    assert rc == 0, stderr
    lines = stdout.rstrip("\n").splitlines()
    mean = [float(v) for v in lines[-3].split()[1:]]
    assert lines[-3].split()[0] == "mean" and lines[-2] == ""
    # The reading is the last line, and its numbers are the table's means.
    assert lines[-1].startswith("reading: the near-light model (nplps) predicts the held-out images better")
    m = re.search(
        r"mean shape error (\S+) vs (\S+) \((\d+(?:\.\d)?)x lower\); mean relative error (\S+) vs (\S+)\.$", lines[-1]
    )
    assert m, lines[-1]
    near_shape, par_shape, factor, near_rel, par_rel = (float(v) for v in m.groups())
    assert near_rel == pytest.approx(mean[0], rel=5e-3) and near_shape == pytest.approx(mean[1], rel=5e-3)
    assert par_rel == pytest.approx(mean[2], rel=5e-3) and par_shape == pytest.approx(mean[3], rel=5e-3)
    assert factor == pytest.approx(mean[3] / mean[1], rel=0.02, abs=0.06)


def test_shaded_picture_shows_relief_not_a_silhouette() -> None:
    # shaded.png used to be lit from the camera: a surface facing it was a white silhouette.
    scene = nplps.make_scene("sphere", n=48)
    result = nplps.reconstruct(scene.images, scene.rig, depth=scene.mean_depth, mask=scene.mask)
    default, camera = result.shaded(), result.shaded("camera")
    inside = scene.mask
    h, w = inside.shape
    upper_left = inside & (np.arange(h)[:, None] < h // 2) & (np.arange(w)[None, :] < w // 2)
    lower_right = inside & (np.arange(h)[:, None] >= h // 2) & (np.arange(w)[None, :] >= w // 2)
    # Lit from the upper left: that side is brighter; from the camera the two are alike.
    assert default[upper_left].mean() > default[lower_right].mean() + 0.2
    assert abs(camera[upper_left].mean() - camera[lower_right].mean()) < 0.05
    # The centre faces the camera: about cos 50 deg, not white.
    assert 0.5 < default[h // 2, w // 2] < 0.8 and camera[h // 2, w // 2] > 0.95
    np.testing.assert_allclose(result.shaded((0, 0, -1)), camera, atol=0.05)  # near-orthographic view
    assert np.all(default[~inside] == 0)
    for bad in ("sun", (0, 0, 0), (1, 2), (np.nan, 0, 1)):
        with pytest.raises(nplps.InputError, match="light must be"):
            result.shaded(bad)
