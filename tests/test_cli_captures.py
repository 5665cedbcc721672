"""Tests of the command line's light selection, grid padding, capture presets and early checks."""

from __future__ import annotations

import re

import numpy as np
import pytest

import nplps
import nplps.io
import nplps.pipeline
from nplps import cli

SIZE = 24


def run(capsys, *argv):
    rc = cli.main([str(a) for a in argv])
    captured = capsys.readouterr()
    return rc, captured.out, captured.err


def assert_one_line_error(rc, stderr, *words):
    assert rc == 2
    assert "Traceback" not in stderr
    lines = [line for line in stderr.splitlines() if line.startswith("nplps: error:")]
    assert len(lines) == 1, stderr
    for word in words:
        assert word in lines[0], (word, lines[0])


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    """A 27-light synthetic scene written by ``nplps synth`` (image_00.png ... image_26.png)."""
    out = tmp_path_factory.mktemp("scene") / "bumps"
    assert cli.main(["synth", "bumps", "--size", str(SIZE), "--out", str(out)]) == 0
    return out


@pytest.fixture
def no_image_reads(monkeypatch):
    """Make any reading of the image stack fail the test."""

    def fail(*args, **kwargs):
        raise AssertionError("the images were read")

    monkeypatch.setattr(nplps.pipeline, "load_images", fail)
    monkeypatch.setattr(nplps.io, "load_stack", fail)


def images(folder, rows):
    return [folder / f"image_{i:02d}.png" for i in rows]


# -- --lights -----------------------------------------------------------------------------------------


def test_lights_select_rows_of_the_rig(scene_dir, tmp_path, capsys):
    rows = [0, 3, 5, 9, 12, 20, 26]
    rc, stdout, stderr = run(
        capsys,
        "reconstruct",
        *images(scene_dir, rows),
        "--rig",
        scene_dir / "rig.json",
        "--mask",
        scene_dir / "mask.png",
        "--lights",
        ",".join(map(str, rows)),
        "--depth",
        "200",
        "--out",
        tmp_path / "r",
        "-q",
    )
    assert rc == 0, stderr
    assert "orthographic camera, 7 point lights" in stdout
    assert re.search(r"status\s+converged", stdout)
    # the same as the API on the rig's subset
    rig = nplps.Rig.load(scene_dir / "rig.json").subset(rows)
    ref = nplps.reconstruct(
        [str(p) for p in images(scene_dir, rows)], rig, depth=200.0, mask=str(scene_dir / "mask.png"), progress=False
    )
    assert np.allclose(np.load(tmp_path / "r" / "depth.npy"), ref.depth, equal_nan=True, atol=1e-9)


@pytest.mark.parametrize(
    "lights, words",
    [
        ("0,1,27", ["--lights", "27", "0 .. 26"]),
        ("0,1,1", ["--lights", "1", "twice"]),
        ("0,x,2", ["--lights", "0,x,2"]),
        ("0,-1,2", ["--lights", "-1", "negative"]),
        ("0,1", ["2 images", "3 lights selected by --lights"]),
    ],
)
def test_lights_errors(scene_dir, tmp_path, capsys, no_image_reads, lights, words):
    rc, _, stderr = run(
        capsys,
        "reconstruct",
        *images(scene_dir, [0, 1]) if lights == "0,1" else images(scene_dir, [0, 1, 2]),
        "--rig",
        scene_dir / "rig.json",
        "--lights",
        "0,1,2" if lights == "0,1" else lights,
        "--depth",
        "200",
        "--out",
        tmp_path / "r",
    )
    assert_one_line_error(rc, stderr, *words)
    assert not (tmp_path / "r").exists()


def test_evaluate_use_lights(scene_dir, capsys):
    rows = [0, 4, 8, 13, 17, 22]
    rc, stdout, stderr = run(
        capsys,
        "evaluate",
        *images(scene_dir, rows),
        "--rig",
        scene_dir / "rig.json",
        "--use-lights",
        ",".join(map(str, rows)),
        "--lights",
        "2",
        "--depth",
        "200",
        "-q",
    )
    assert rc == 0, stderr
    assert "from the other 5 lights" in stdout


# -- --grid-shape ---------------------------------------------------------------------------------------


def test_grid_shape_pads_and_crops(scene_dir, tmp_path, capsys):
    common = ["reconstruct", scene_dir, "--rig", scene_dir / "rig.json", "--depth", "200", "-q"]
    rc, _, stderr = run(capsys, *common, "--grid-shape", f"{SIZE + 4},{SIZE + 2}", "--out", tmp_path / "pad")
    assert rc == 0, stderr
    assert np.load(tmp_path / "pad" / "depth.npy").shape == (SIZE + 5, SIZE + 3)
    rc, _, stderr = run(
        capsys,
        *common,
        "--grid-shape",
        f"{SIZE - 4},{SIZE}",
        "--out",
        tmp_path / "crop",
    )
    assert rc == 0, stderr
    assert np.load(tmp_path / "crop" / "depth.npy").shape == (SIZE - 3, SIZE + 1)


@pytest.mark.parametrize("shape", ["24", "a,b", "0,5", "1,2,3"])
def test_grid_shape_errors(scene_dir, tmp_path, capsys, no_image_reads, shape):
    rc, _, stderr = run(
        capsys,
        "reconstruct",
        scene_dir,
        "--rig",
        scene_dir / "rig.json",
        "--grid-shape",
        shape,
        "--depth",
        "200",
        "--out",
        tmp_path / "r",
    )
    assert_one_line_error(rc, stderr, "--grid-shape", shape)


def test_grid_shape_mask_must_be_on_the_grid(scene_dir, tmp_path, capsys):
    rc, _, stderr = run(
        capsys,
        "reconstruct",
        scene_dir,
        "--rig",
        scene_dir / "rig.json",
        "--mask",
        scene_dir / "mask.png",
        "--grid-shape",
        f"{SIZE + 2},{SIZE}",
        "--depth",
        "200",
        "--out",
        tmp_path / "r",
    )
    assert_one_line_error(rc, stderr, "mask")


# -- checks before the images are read -------------------------------------------------------------------


def test_auto_depth_with_directional_lights_fails_before_reading(scene_dir, tmp_path, capsys, no_image_reads):
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(27, 3)) * [0.5, 0.5, 0.0] + [0.0, 0.0, -1.0]
    rig = nplps.Rig.orthographic(1.0, directions=dirs / np.linalg.norm(dirs, axis=1, keepdims=True))
    rig.save(tmp_path / "rig.json")
    rc, _, stderr = run(
        capsys, "reconstruct", scene_dir, "--rig", tmp_path / "rig.json", "--depth", "auto", "--out", tmp_path / "r"
    )
    assert_one_line_error(rc, stderr, "--depth auto", "directional")


def test_auto_depth_with_three_lights_and_cos4_fail_before_reading(scene_dir, tmp_path, capsys, no_image_reads):
    common = ["reconstruct", *images(scene_dir, [0, 1, 2]), "--rig", scene_dir / "rig.json", "--lights", "0,1,2"]
    rc, _, stderr = run(capsys, *common, "--depth", "auto", "--out", tmp_path / "r")
    assert_one_line_error(rc, stderr, "--depth auto", "3 lights")
    rc, _, stderr = run(capsys, *common, "--depth", "200", "--vignetting", "cos4", "--out", tmp_path / "r")
    assert_one_line_error(rc, stderr, "cos4", "pinhole", "orthographic")


def test_preset_option_errors(tmp_path, capsys):
    rc, _, stderr = run(
        capsys, "reconstruct", "--capture", "hehe12", tmp_path, "x*.png", "--depth", "200", "--out", tmp_path / "r"
    )
    assert_one_line_error(rc, stderr, "--capture hehe12", "folder")
    rc, _, stderr = run(
        capsys,
        "reconstruct",
        "--capture",
        "queau_human1",
        tmp_path,
        "--srgb",
        "--depth",
        "700",
        "--out",
        tmp_path / "r",
    )
    assert_one_line_error(rc, stderr, "--capture queau_human1", "--srgb")
    rc, _, stderr = run(
        capsys,
        "reconstruct",
        "--capture",
        "queau_human1",
        tmp_path,
        "--grid-shape",
        "10,10",
        "--depth",
        "700",
        "--out",
        tmp_path / "r",
    )
    assert_one_line_error(rc, stderr, "--capture queau_human1", "--grid-shape")


# -- the presets on the shared captures -----------------------------------------------------------------


def run_preset(capsys, tmp_path, *argv):
    out = tmp_path / "r"
    rc, stdout, stderr = run(capsys, "reconstruct", "--capture", *argv, "--out", out, "-q")
    assert rc == 0, stderr
    for name in ("mesh.ply", "normals.png", "depth.npy", "summary.json", "nplps-manifest.json"):
        assert (out / name).is_file(), name
    assert re.search(r"^\s*status\s+(converged|stalled): ", stdout, re.M), stdout
    return stdout, np.load(out / "depth.npy")


def test_preset_hehe12(tmp_path, capsys, shared_capture):
    stdout, depth = run_preset(capsys, tmp_path, "hehe12", shared_capture("hehe12"), "--depth", "200", "--bin", "16")
    assert "pinhole camera, 8 point lights" in stdout
    assert depth.shape == (1200 // 16 + 1, 1920 // 16 + 1)
    assert 150 < np.nanmedian(depth) < 250


def test_preset_hehe12_lights_and_auto_depth_check(tmp_path, capsys, shared_capture, no_image_reads):
    rc, _, stderr = run(
        capsys,
        "reconstruct",
        "--capture",
        "hehe12",
        shared_capture("hehe12"),
        "--lights",
        "0,3,9",
        "--depth",
        "200",
        "--out",
        tmp_path / "r",
    )
    assert_one_line_error(rc, stderr, "LED row(s) [9]")
    rc, _, stderr = run(
        capsys,
        "reconstruct",
        "--capture",
        "hehe12",
        shared_capture("hehe12"),
        "--lights",
        "0,3,5",
        "--depth",
        "auto",
        "--out",
        tmp_path / "r",
    )
    assert_one_line_error(rc, stderr, "--depth auto", "3 lights")


def test_preset_queau_human1(tmp_path, capsys, shared_capture):
    stdout, depth = run_preset(
        capsys, tmp_path, "queau_human1", shared_capture("queau_human1"), "--depth", "700", "--bin", "16"
    )
    assert "pinhole camera, 7 point lights" in stdout
    assert depth.shape == (1732 // 16 + 1, 2601 // 16 + 1)  # the RAW grid of camera.mat
    assert 600 < np.nanmedian(depth) < 800


def test_preset_diligent_ball(tmp_path, capsys, shared_capture):
    stdout, depth = run_preset(
        capsys, tmp_path, "diligent", shared_capture("diligent_ball"), "--depth", "1000", "--gray", "--bin", "4"
    )
    assert "orthographic camera, 96 directional lights" in stdout
    assert depth.shape == (512 // 4 + 1, 612 // 4 + 1)


def test_preset_diligent_auto_depth_fails_before_reading(tmp_path, capsys, shared_capture, no_image_reads):
    rc, _, stderr = run(
        capsys,
        "reconstruct",
        "--capture",
        "diligent",
        shared_capture("diligent_ball"),
        "--depth",
        "auto",
        "--out",
        tmp_path / "r",
    )
    assert_one_line_error(rc, stderr, "--depth auto", "directional")
