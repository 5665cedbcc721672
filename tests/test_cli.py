"""Tests of the ``nplps`` command line (nplps.cli)."""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys

import numpy as np
import pytest

import nplps
from nplps import cli
from nplps.export import read_ply

SIZE = 40

SUMMARY_KEYS = {
    "method",
    "shape",
    "pixels",
    "regions",
    "gauge",
    "iterations",
    "converged",
    "last_depth_change",
    "rms_residual",
    "unfitted_pixels",
    "depth_range",
    "timings",
}

OUTPUT_FILES = (
    "mesh.ply",
    "mesh.obj",
    "normals.png",
    "albedo.png",
    "depth.npy",
    "depth.tiff",
    "normals.npy",
    "residual.npy",
    "summary.json",
)


def angular_errors(normals: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    dot = np.clip(np.sum(normals[mask] * truth[mask], axis=-1), -1.0, 1.0)
    return np.degrees(np.arccos(dot))


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    """A synthetic scene written by ``nplps synth``, and the reconstruct command it printed."""
    out = tmp_path_factory.mktemp("scene") / "bumps"
    import io
    from contextlib import redirect_stdout

    buf = io.StringIO()
    with redirect_stdout(buf):
        rc = cli.main(["synth", "bumps", "--size", str(SIZE), "--seed", "1", "--out", str(out)])
    assert rc == 0
    text = buf.getvalue()
    line = next(line for line in text.splitlines() if line.strip().startswith("nplps reconstruct"))
    return out, shlex.split(line.strip())


def run(capsys, *argv):
    rc = cli.main([str(a) for a in argv])
    captured = capsys.readouterr()
    return rc, captured.out, captured.err


# --------------------------------------------------------------------------------------------------
# synth + reconstruct
# --------------------------------------------------------------------------------------------------


def test_synth_writes_scene(scene_dir):
    out, command = scene_dir
    assert len(sorted(out.glob("image_*.png"))) == 27
    for name in ("rig.json", "mask.png", "depth_gt.npy", "normals_gt.npy", "albedo_gt.npy"):
        assert (out / name).is_file(), name
    assert command[:3] == ["nplps", "reconstruct", str(out)]
    depth = float(command[command.index("--depth") + 1])
    scene = nplps.make_scene("bumps", SIZE, seed=1)
    assert depth == pytest.approx(scene.mean_depth, rel=1e-9)


def test_reconstruct_printed_command_recovers_truth(scene_dir, tmp_path, capsys):
    out, command = scene_dir
    argv = command[1:]
    argv[argv.index("--out") + 1] = str(tmp_path / "result")
    rc, stdout, stderr = run(capsys, *argv)
    assert rc == 0, stderr

    # the directory listing says which files were taken, in order, and skipped the mask
    assert "using 27 images" in stderr
    assert "image_00.png" in stderr and "image_26.png" in stderr
    assert stderr.index("image_00.png") < stderr.index("image_09.png") < stderr.index("image_26.png")
    # progress: one line per iteration
    iteration_lines = [line for line in stderr.splitlines() if line.startswith("iteration")]
    assert iteration_lines and re.match(r"iteration\s+1/10: depth change .*, rms residual .*, .* s", iteration_lines[0])
    # summary
    for word in ("pixels", "regions", "iterations", "converged", "rms residual", "unfitted pixels", "time", "files written"):
        assert word in stdout, word

    result = tmp_path / "result"
    for name in OUTPUT_FILES:
        assert (result / name).is_file(), name
    summary = json.loads((result / "summary.json").read_text())
    assert SUMMARY_KEYS <= set(summary)
    assert summary["converged"] is True
    assert len(iteration_lines) == summary["iterations"]

    truth = np.load(out / "normals_gt.npy")
    mask = np.isfinite(truth).all(axis=-1)
    normals = np.load(result / "normals.npy")
    errors = angular_errors(normals, truth, mask)
    assert np.isfinite(errors).all()
    assert errors.mean() < 0.1

    ply = read_ply(result / "mesh.ply")
    assert ply["vertices"].shape[1] == 3 and len(ply["vertices"]) > 0
    assert ply["faces"].shape == (2 * int(mask.sum()), 3)
    assert not (result / "baseline").exists()


def test_reconstruct_files_baseline_depth_map_and_quiet(scene_dir, tmp_path, capsys):
    out, _ = scene_dir
    images = [str(p) for p in sorted(out.glob("image_*.png"))]
    depth_gt = np.load(out / "depth_gt.npy")
    rc, stdout, stderr = run(
        capsys,
        "reconstruct",
        *images,
        "--rig",
        out / "rig.json",
        "--mask",
        out / "mask.png",
        "--depth",
        out / "depth_gt.npy",
        "--out",
        tmp_path / "r",
        "--baseline",
        "--iterations",
        "3",
        "--threads",
        "2",
        "-q",
    )
    assert rc == 0, stderr
    assert stderr == ""
    assert "parallel-light baseline" in stdout
    for name in OUTPUT_FILES:
        assert (tmp_path / "r" / name).is_file()
        assert (tmp_path / "r" / "baseline" / name).is_file()
    assert json.loads((tmp_path / "r" / "summary.json").read_text())["method"] == "near"
    assert json.loads((tmp_path / "r" / "baseline" / "summary.json").read_text())["method"] == "parallel"
    depth = np.load(tmp_path / "r" / "depth.npy")
    assert depth.shape == depth_gt.shape
    # started from the true surface: the result stays close to it
    ok = np.isfinite(depth)
    assert np.sqrt(np.mean((depth[ok] - depth_gt[ok]) ** 2)) < 0.05


# --------------------------------------------------------------------------------------------------
# demo
# --------------------------------------------------------------------------------------------------


def test_demo_compares_methods(tmp_path, capsys):
    rc, stdout, stderr = run(capsys, "demo", "--size", "32", "--out", tmp_path / "demo")
    assert rc == 0, stderr
    rows = {}
    for line in stdout.splitlines():
        m = re.match(r"(mean normal error|median normal error|RMS depth error)\D*\]\s+(\S+)\s+(\S+)$", line)
        if m:
            rows[m.group(1)] = (float(m.group(2)), float(m.group(3)))
    assert set(rows) == {"mean normal error", "median normal error", "RMS depth error"}, stdout
    for near, parallel in rows.values():
        assert near < parallel
    assert rows["mean normal error"][0] < 0.1
    assert "time" in stdout
    for sub in ("scene", "near", "baseline"):
        assert (tmp_path / "demo" / sub).is_dir()
    assert (tmp_path / "demo" / "near" / "mesh.ply").is_file()


# --------------------------------------------------------------------------------------------------
# errors
# --------------------------------------------------------------------------------------------------


def assert_one_line_error(rc, stderr, *words):
    assert rc == 2
    assert "Traceback" not in stderr
    lines = [line for line in stderr.splitlines() if line.startswith("nplps: error:")]
    assert len(lines) == 1, stderr
    for word in words:
        assert word in lines[0], (word, lines[0])


def test_error_missing_rig(scene_dir, tmp_path, capsys):
    out, _ = scene_dir
    missing = tmp_path / "no_such_rig.json"
    rc, _, stderr = run(capsys, "reconstruct", out, "--rig", missing, "--depth", "200", "--out", tmp_path / "r")
    assert_one_line_error(rc, stderr, "rig file", "no_such_rig.json")
    assert not (tmp_path / "r").exists()


def test_error_rig_not_json(scene_dir, tmp_path, capsys):
    out, _ = scene_dir
    rc, _, stderr = run(capsys, "reconstruct", out, "--rig", out / "image_00.png", "--depth", "200", "--out", tmp_path / "r")
    assert_one_line_error(rc, stderr, "rig file", "image_00.png")


def test_error_image_count_mismatch(scene_dir, tmp_path, capsys):
    out, _ = scene_dir
    images = sorted(out.glob("image_*.png"))[:5]
    rc, _, stderr = run(capsys, "reconstruct", *images, "--rig", out / "rig.json", "--depth", "200", "--out", tmp_path / "r")
    assert_one_line_error(rc, stderr, "5 images", "27 lights")


@pytest.mark.parametrize(
    "depth, words",
    [
        ("abc", ["--depth", "abc", "number"]),
        ("-5", ["--depth", "positive"]),
        ("nan", ["--depth", "positive"]),
        ("rig.json", ["--depth", ".npy"]),
        ("normals_gt.npy", ["--depth", "(H+1, W+1)"]),
        ("bad_shape.npy", ["depth map", "(H+1, W+1)"]),
    ],
)
def test_error_bad_depth(scene_dir, tmp_path, capsys, depth, words):
    out, _ = scene_dir
    np.save(out / "bad_shape.npy", np.full((SIZE, SIZE), 200.0))
    value = str(out / depth) if depth.endswith((".json", ".npy")) else depth
    rc, _, stderr = run(capsys, "reconstruct", out, "--rig", out / "rig.json", "--mask", out / "mask.png", "--depth", value, "--out", tmp_path / "r")
    assert_one_line_error(rc, stderr, *words)


def test_error_missing_image_and_mask(scene_dir, tmp_path, capsys):
    out, _ = scene_dir
    images = [str(p) for p in sorted(out.glob("image_*.png"))]
    images[3] = str(tmp_path / "gone.png")
    rc, _, stderr = run(capsys, "reconstruct", *images, "--rig", out / "rig.json", "--depth", "200", "--out", tmp_path / "r")
    assert_one_line_error(rc, stderr, "gone.png")
    rc, _, stderr = run(capsys, "reconstruct", out, "--rig", out / "rig.json", "--mask", tmp_path / "m.png", "--depth", "200", "--out", tmp_path / "r")
    assert_one_line_error(rc, stderr, "mask", "m.png")


def test_error_empty_directory(tmp_path, capsys, scene_dir):
    out, _ = scene_dir
    (tmp_path / "empty").mkdir()
    rc, _, stderr = run(capsys, "reconstruct", tmp_path / "empty", "--rig", out / "rig.json", "--depth", "200", "--out", tmp_path / "r")
    assert_one_line_error(rc, stderr, "no image files", "empty")


def test_error_synth_options(tmp_path, capsys):
    rc, _, stderr = run(capsys, "synth", "sphere", "--size", "1", "--out", tmp_path / "s")
    assert_one_line_error(rc, stderr, "--size")
    rc, _, stderr = run(capsys, "synth", "sphere", "--noise", "-0.1", "--out", tmp_path / "s")
    assert_one_line_error(rc, stderr, "--noise")
    rc, _, stderr = run(capsys, "synth", "teapot", "--out", tmp_path / "s")
    assert rc == 2 and "invalid choice" in stderr


def test_usage_errors(capsys):
    rc, _, stderr = run(capsys)
    assert rc == 2 and "usage" in stderr
    rc, _, stderr = run(capsys, "reconstruct", "a.png")
    assert rc == 2 and "required" in stderr


def test_keyboard_interrupt(monkeypatch, capsys):
    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "cmd_demo", interrupted)
    rc, _, stderr = run(capsys, "demo")
    assert rc == 130
    assert stderr.strip() == "interrupted"


# --------------------------------------------------------------------------------------------------
# help, version, helpers
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("command", [[], ["reconstruct"], ["synth"], ["demo"]])
def test_help(capsys, command):
    rc, stdout, _ = run(capsys, *command, "--help")
    assert rc == 0
    assert "usage: nplps" in stdout
    assert "example" in stdout
    if not command:
        assert "OpenCV" in stdout and "reconstruct" in stdout and "synth" in stdout and "demo" in stdout


def test_version_subprocess(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "nplps", "--version"], capture_output=True, text=True, cwd=tmp_path, timeout=60
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == f"nplps {nplps.__version__}"


def test_subprocess_error_exit_code(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "nplps", "reconstruct", "x.png", "--rig", "missing.json", "--depth", "1", "--out", "o"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=60,
    )
    assert proc.returncode == 2
    assert proc.stderr.startswith("nplps: error:") and "missing.json" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_resolve_images_natural_order(tmp_path, capsys):
    for name in ("img10.png", "img2.png", "img1.png", "Mask.png", "notes.txt", ".hidden.png"):
        (tmp_path / name).write_bytes(b"")
    (tmp_path / "sub.png").mkdir()
    files = cli.resolve_images([str(tmp_path)])
    assert [p.rsplit("/", 1)[-1] for p in files] == ["img1.png", "img2.png", "img10.png"]
    err = capsys.readouterr().err
    assert "using 3 images" in err and "Mask.png" in err and "--mask" in err
