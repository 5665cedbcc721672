"""Small fixes of issue 11: the distance curve CSV, the capture docs, repr, sizes, the evaluate reading."""

from __future__ import annotations

import numpy as np
import pytest

import nplps
from nplps import cli

SIZE = 24


@pytest.fixture(scope="module")
def auto_result() -> tuple[nplps.Scene, nplps.Reconstruction]:
    """A small synthetic scene and its ``depth="auto"`` reconstruction."""
    s = nplps.make_scene("bumps", n=SIZE, seed=1)
    return s, nplps.reconstruct(s.images, s.rig, mask=s.mask, depth="auto")


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
