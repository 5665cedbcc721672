"""``nplps batch``: a capture's own rig.json overrides --rig; --capture LAYOUT reads each folder with its loader.

The captures run on an in-process Dask cluster (quick); see tests/test_batch.py for the local
cluster of worker processes.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

import nplps
from nplps import batch
from nplps.cli import main

REASON = "nplps batch needs dask.distributed (pip install 'nplps[batch]')"
distributed = pytest.importorskip("distributed", reason=REASON)


@pytest.fixture(scope="module")
def scheduler():
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as c:
        yield c.scheduler_address


def _errors(out: Path, truth: np.ndarray, mask: np.ndarray) -> float:
    normals = np.load(out / "normals.npy")
    dot = np.clip(np.sum(normals[mask] * truth[mask], axis=-1), -1, 1)
    return float(np.degrees(np.arccos(dot)).mean())


def _rows(out: Path) -> dict[str, dict[str, str]]:
    with open(out / "batch_summary.csv", newline="") as f:
        return {r["capture"]: r for r in csv.DictReader(f)}


def test_own_rig_overrides_the_shared_rig(tmp_path: Path, scheduler: str, capsys: pytest.CaptureFixture[str]) -> None:
    # Two captures whose rigs differ (objects 100 and 160 wide: other pixel size and lights): "near"
    # keeps its rig.json, "far" has none and gets --rig (its own rig, saved elsewhere).
    near = nplps.make_scene("bumps", n=24, seed=1)
    far = nplps.make_scene("sphere", n=24, seed=2, size=160.0)
    assert not np.allclose(near.rig.positions, far.rig.positions)
    near.save(tmp_path / "caps" / "near")
    far.save(tmp_path / "caps" / "far")
    shared = tmp_path / "far_rig.json"
    (tmp_path / "caps" / "far" / "rig.json").rename(shared)
    out = tmp_path / "out"
    args = ["batch", str(tmp_path / "caps" / "*"), "--rig", str(shared), "--depth", "auto", "--out", str(out)]
    code = main([*args, "--scheduler", scheduler, "--no-report"])
    assert code == 0, capsys.readouterr()
    rows = _rows(out)
    assert rows["near"]["rig"] == str(tmp_path / "caps" / "near" / "rig.json")
    assert rows["far"]["rig"] == str(shared)
    options = json.loads((out / "near" / "summary.json").read_text())["options"]
    assert options["rig"] == str(tmp_path / "caps" / "near" / "rig.json")
    assert _errors(out / "near", near.normals, near.mask) < 0.5
    assert _errors(out / "far", far.normals, far.mask) < 0.5
    # A wrong rig.json in "near" (the lights mirrored left-right) is the one used: the result is worse.
    mirrored = near.rig.positions * np.array([-1.0, 1.0, 1.0])
    near.rig.with_positions(mirrored).with_grid(24, 24).save(tmp_path / "caps" / "near" / "rig.json")
    code = main([*args[:-1], str(tmp_path / "out2"), "--scheduler", scheduler, "--no-report"])
    assert code == 0
    own = _errors(out / "near", near.normals, near.mask)
    assert _errors(tmp_path / "out2" / "near", near.normals, near.mask) > 5 * own + 2.0


def test_no_rig_anywhere_is_refused_first(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    nplps.make_scene("saddle", n=16).save(tmp_path / "caps" / "a")
    nplps.make_scene("saddle", n=16).save(tmp_path / "caps" / "b")
    (tmp_path / "caps" / "b" / "rig.json").unlink()
    code = main(["batch", str(tmp_path / "caps" / "*"), "--depth", "200", "--out", str(tmp_path / "out")])
    assert code == 2
    err = capsys.readouterr().err
    assert "no rig for 1 capture(s) (b)" in err and "--rig" in err
    assert not (tmp_path / "out").exists()


def test_capture_layout_luces(tmp_path: Path, scheduler: str, capsys: pytest.CaptureFixture[str]) -> None:
    from test_luces import write_luces_object

    truth = {name: write_luces_object(tmp_path / "data" / name, seed=i, n=32) for i, name in enumerate(("A", "B"))}
    write_luces_object(tmp_path / "data" / "Broken", seed=3, n=16)
    params = tmp_path / "data" / "Broken" / "led_params.txt"
    params.write_text("\n".join(params.read_text().splitlines()[:-1]) + "\n")
    out = tmp_path / "out"
    common = ["batch", str(tmp_path / "data" / "*"), "--capture", "luces", "--depth", "200", "--out", str(out)]
    code = main([*common, "--scheduler", scheduler, "--no-report"])
    printed = capsys.readouterr()
    assert code == 1  # Broken failed, the others ran
    assert "capture Broken: failed: " in printed.out and "LED lines" in printed.out
    rows = _rows(out)
    assert [rows[n]["status"] for n in ("A", "B", "Broken")] == ["ok", "ok", "failed"]
    for name in ("A", "B"):
        assert rows[name]["rig"].startswith("luces calibration")
        assert _errors(out / name, truth[name]["normals"], truth[name]["mask"]) < 0.5
    summary = json.loads((out / "A" / "summary.json").read_text())
    assert summary["options"]["vignetting"] is None  # LUCES: no cos^4 by default
    # A rerun skips the two complete results.
    code = main([*common, "--scheduler", scheduler, "--no-report"])
    assert code == 1 and capsys.readouterr().out.count("skipped (complete result") == 2
    # --capture takes the rig from each folder.
    assert main([*common, "--rig", str(tmp_path / "x.json")]) == 2
    assert "not --rig" in capsys.readouterr().err


def test_layout_api_checks(tmp_path: Path) -> None:
    with pytest.raises(nplps.InputError, match="unknown capture layout"):
        batch.run(str(tmp_path / "*"), None, tmp_path / "out", depth=200.0, layout="queau_human1")
    with pytest.raises(nplps.InputError, match="give no rig"):
        batch.run(str(tmp_path / "*"), nplps.make_scene("saddle", n=8).rig, tmp_path / "out", depth=1.0, layout="luces")


def test_capture_layouts_on_real_captures(shared_capture, tmp_path: Path, scheduler: str) -> None:
    # hehe12 (near_ps layout: cos^4 by default, the ambient image subtracted) and the DiLiGenT ball
    # (directional lights, no K: no vignetting), each found by a glob of one folder.
    for layout, name, depth in (("hehe12", "hehe12", "200"), ("diligent", "diligent_ball", "1000")):
        folder = shared_capture(name)
        out = tmp_path / layout
        args = ["batch", str(folder), "--capture", layout, "--depth", depth, "--bin", "8", "--gray"]
        assert main([*args, "--out", str(out), "--scheduler", scheduler, "--no-report"]) == 0
        rows = _rows(out)
        assert rows[name]["status"] == "ok" and rows[name]["rig"].startswith(f"{layout} calibration")
        options = json.loads((out / name / "summary.json").read_text())["options"]
        assert options["vignetting"] == ("cos4" if layout == "hehe12" else None)
        if layout == "hehe12":
            assert options["ambient"].endswith("photometric_sample_raw_ambient.png")
