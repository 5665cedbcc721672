"""``nplps batch`` / ``nplps.batch``: many captures on a Dask LocalCluster, resumable, failures per capture."""

from __future__ import annotations

import csv
import json
import os
import shutil

import numpy as np
import pytest

import nplps
from nplps import batch
from nplps.cli import main

KINDS = ("sphere", "saddle", "bumps", "cube")


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """8 synthetic 24 x 24 captures c0..c7 sharing one rig; c5 has a truncated PNG."""
    root = tmp_path_factory.mktemp("captures")
    for i in range(8):
        nplps.make_scene(KINDS[i % 4], n=24, seed=i).save(root / f"c{i}")
    shutil.copy(root / "c5" / "image_03.png", root / "c5" / "good_image_03.png.bak")
    _break(root)
    return root


def _break(captures):
    data = (captures / "c5" / "good_image_03.png.bak").read_bytes()
    (captures / "c5" / "image_03.png").write_bytes(data[: len(data) // 2])


def _run(captures, out, capsys, *extra):
    code = main(
        [
            "batch",
            str(captures / "c*"),
            "--rig",
            str(captures / "c0" / "rig.json"),
            "--depth",
            "200",
            "--out",
            str(out),
            "--workers",
            "2",
            *extra,
        ]
    )
    return code, capsys.readouterr()


def test_batch_local_cluster_failures_resume_summary(captures, tmp_path, capsys):
    pytest.importorskip("distributed", reason="nplps batch needs dask.distributed (pip install 'nplps[batch]')")
    out = tmp_path / "results"

    # First run: 7 results, one clear failure line, exit status 1. (A LocalCluster of 2 worker
    # processes, as the command starts by default.)
    code, io = _run(captures, out, capsys)
    assert code == 1, io.err
    lines = io.out.splitlines()
    failures = [line for line in lines if ": failed: " in line]
    assert len(failures) == 1, io.out
    assert "capture c5: failed: " in failures[0] and "image_03.png" in failures[0]
    assert sum(": ok, " in line for line in lines) == 7
    assert "[8/8, 1 failed]" in io.out
    assert "7 ok, 1 failed, 0 skipped" in lines[-1]
    for i in range(8):
        assert batch.is_complete(out / f"c{i}") == (i != 5)
    assert not (out / "c5").exists()

    # The summary parses with csv and numpy, 8 rows.
    with open(out / "batch_summary.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["capture"] for r in rows] == [f"c{i}" for i in range(8)]
    assert tuple(rows[0]) == batch.SUMMARY_COLUMNS
    assert [r["status"] for r in rows].count("ok") == 7
    assert rows[5]["status"] == "failed" and "image_03.png" in rows[5]["error"]
    table = np.loadtxt(out / "batch_summary.csv", delimiter=",", skiprows=1, dtype=str)
    assert table.shape == (8, len(batch.SUMMARY_COLUMNS))
    numbers = np.loadtxt(out / "batch_summary.csv", delimiter=",", skiprows=1, usecols=(2, 4, 5))
    assert numbers.shape == (8, 3)
    ok = table[:, 1] == "ok"
    assert np.all(numbers[ok, 0] >= 1) and np.all(np.isfinite(numbers[ok, 1])) and np.all(numbers[ok, 2] > 0)
    assert np.isnan(numbers[5, 0])
    page = (out / "batch_summary.html").read_text()
    assert page.startswith("<!DOCTYPE html>") and page.count("<tr style=") == 8 and "7 ok, 1 failed" in page
    # Each result has its report (with the input thumbnails and the options), linked from the summary.
    for i in (0, 7):
        report = (out / f"c{i}" / "report.html").read_text()
        assert "data:image/png;base64," in report and (out / f"c{i}" / "inputs.png").is_file()
        assert json.loads((out / f"c{i}" / "summary.json").read_text())["options"]["capture"].endswith(f"c{i}")
    assert 'href="./c0/report.html"' in page and 'href="./c5/' not in page

    # Rerun: the 7 are skipped (their files untouched), the failed one is tried again.
    stamp = (out / "c0" / "summary.json").stat().st_mtime_ns
    code, io = _run(captures, out, capsys)
    assert code == 1
    assert sum(": skipped (complete result" in line for line in io.out.splitlines()) == 7
    assert io.out.count("capture c5: failed: ") == 1
    assert (out / "c0" / "summary.json").stat().st_mtime_ns == stamp
    rows = list(csv.DictReader(open(out / "batch_summary.csv", newline="")))
    assert [r["status"] for r in rows] == ["skipped"] * 5 + ["failed"] + ["skipped"] * 2
    summary = json.loads((out / "c0" / "summary.json").read_text())
    assert rows[0]["iterations"] == str(summary["iterations"]) and rows[0]["solver_status"] == summary["status"]

    # Repaired, the third run does only c5 and succeeds.
    shutil.copy(captures / "c5" / "good_image_03.png.bak", captures / "c5" / "image_03.png")
    try:
        code, io = _run(captures, out, capsys)
    finally:
        _break(captures)
    assert code == 0, io.out
    assert "capture c5: ok, " in io.out and "1 ok, 0 failed, 7 skipped" in io.out
    assert batch.is_complete(out / "c5")


def test_api_run_items(captures, tmp_path):
    pytest.importorskip("distributed", reason="nplps batch needs dask.distributed (pip install 'nplps[batch]')")
    seen = []
    items = batch.run(
        str(captures / "c[0-2]"),
        captures / "c0" / "rig.json",
        tmp_path / "out",
        depth=200.0,
        workers=1,
        iterations=3,
        progress=lambda item, done, total, failed: seen.append((item.name, done, total, failed)),
    )
    assert [i.name for i in items] == ["c0", "c1", "c2"]
    assert all(i.status == "ok" and 1 <= (i.iterations or 0) <= 3 for i in items)
    assert sorted(s[1] for s in seen) == [1, 2, 3] and {s[2] for s in seen} == {3}


def test_unknown_option_and_bad_pattern(captures, tmp_path):
    with pytest.raises(TypeError, match="iteration"):
        batch.run(str(captures / "c*"), captures / "c0" / "rig.json", tmp_path, depth=200.0, iteration=3)
    with pytest.raises(nplps.InputError, match="no capture directory"):
        batch.find_captures(str(tmp_path / "nothing*"))


def test_find_captures_skips_out_and_refuses_same_names(tmp_path):
    for d in ("a/x", "b/x", "a/y", "a/results"):
        (tmp_path / d).mkdir(parents=True)
    (tmp_path / "a" / "file.png").write_bytes(b"")
    found = batch.find_captures(str(tmp_path / "a" / "*"), out=tmp_path / "a" / "results")
    assert [p.name for p in found] == ["x", "y"]
    with pytest.raises(nplps.InputError, match="two captures are named 'x'"):
        batch.find_captures(str(tmp_path / "*" / "x"))


def test_is_complete(tmp_path):
    d = tmp_path / "r"
    assert not batch.is_complete(d)
    d.mkdir()
    (d / "mesh.ply").write_bytes(b"ply")

    def manifest(files, state="complete", folder=None):
        records = {name: {"size": size, "sha256": "0" * 64} for name, size in files.items()}
        data = {"nplps": "x", "manifest": 2, "state": state, "folder": folder or os.path.realpath(d), "files": records}
        (d / "nplps-manifest.json").write_text(json.dumps(data))

    manifest({"mesh.ply": 3})
    assert not batch.is_complete(d)  # a failed run's manifest: no summary.json
    manifest({"mesh.ply": 3, "summary.json": 2})
    assert not batch.is_complete(d)  # summary.json listed but missing
    (d / "summary.json").write_text("{}")
    assert batch.is_complete(d)
    manifest({"mesh.ply": 3, "summary.json": 2}, state="in progress")
    assert not batch.is_complete(d)  # not completed: an interrupted (over)write
    manifest({"mesh.ply": 3, "summary.json": 2}, folder="/elsewhere")
    assert not batch.is_complete(d)  # copied in from another folder: not this folder's
    manifest({"mesh.ply": 4, "summary.json": 2})
    assert not batch.is_complete(d)  # a file of another size
    (d / "nplps-manifest.json").write_text(json.dumps({"nplps": "x", "files": ["mesh.ply", "summary.json"]}))
    assert not batch.is_complete(d)  # format 1 (no sizes): not trusted


def test_summary_fields_need_no_quoting(tmp_path):
    item = batch.BatchItem("a,b", "f", "o", status="failed", error='bad "x", line\nnext')
    csv_path, html_path = batch.write_summary([item], tmp_path)
    text = csv_path.read_text()
    assert '"' not in text and text.count("\n") == 2
    row = np.loadtxt(csv_path, delimiter=",", skiprows=1, dtype=str, ndmin=2)[0]
    assert row[0] == "a;b" and row[-1] == "bad 'x'; line next"
    assert "&quot;x&quot;" in html_path.read_text() or "&#x27;" in html_path.read_text()


def test_existing_scheduler(captures, tmp_path, capsys):
    distributed = pytest.importorskip(
        "distributed", reason="nplps batch needs dask.distributed (pip install 'nplps[batch]')"
    )
    # An existing cluster (in-process workers, for speed), reached by its address.
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as c:
        code, io = _run(captures, tmp_path / "out", capsys, "--scheduler", c.scheduler_address)
    assert code == 1
    assert io.out.count(": ok, ") == 7 and io.out.count("capture c5: failed: ") == 1
    assert len(list((tmp_path / "out").glob("c*/nplps-manifest.json"))) == 7


def test_foreign_files_and_interrupt(captures, tmp_path):
    pytest.importorskip("distributed", reason="nplps batch needs dask.distributed (pip install 'nplps[batch]')")
    out = tmp_path / "out"
    (out / "c1").mkdir(parents=True)
    (out / "c1" / "notes.txt").write_text("mine")
    items = batch.run(str(captures / "c[0-1]"), captures / "c0" / "rig.json", out, depth=200.0, workers=1)
    assert [i.status for i in items] == ["ok", "failed"]
    assert "not empty" in (items[1].error or "") and "--overwrite" in (items[1].error or "")
    assert (out / "c1" / "notes.txt").read_text() == "mine" and not (out / "c1" / "summary.json").exists()

    # Ctrl-C while the captures run (here: raised from the progress callback): the summary is
    # written with the unfinished captures as "interrupted", and a rerun does the rest.
    def stop(item, done, total, failed):
        raise KeyboardInterrupt

    out = tmp_path / "out2"
    with pytest.raises(KeyboardInterrupt):
        batch.run(str(captures / "c[0-3]"), captures / "c0" / "rig.json", out, depth=200.0, workers=1, progress=stop)
    rows = list(csv.DictReader(open(out / "batch_summary.csv", newline="")))
    assert len(rows) == 4 and sum(r["error"] == "interrupted" for r in rows) >= 1
    items = batch.run(str(captures / "c[0-3]"), captures / "c0" / "rig.json", out, depth=200.0, workers=2)
    assert all(i.status in ("ok", "skipped") for i in items) and any(i.status == "skipped" for i in items)


def test_cli_exposures_flat_and_light_refinement(captures, tmp_path, capsys):
    pytest.importorskip("distributed", reason="nplps batch needs dask.distributed (pip install 'nplps[batch]')")
    k = nplps.Rig.load(captures / "c0" / "rig.json").n_lights
    common = ["batch", str(captures / "c0"), "--rig", str(captures / "c0" / "rig.json"), "--depth", "200"]
    common += ["--workers", "1", "--no-report"]
    assert main([*common, "--out", str(tmp_path / "plain")]) == 0
    # Every image divided by 2 (the dark threshold with it): the same shape.
    assert main([*common, "--out", str(tmp_path / "half"), "--exposures", ",".join(["2"] * k)]) == 0
    plain, half = (np.load(tmp_path / d / "c0" / "depth.npy") for d in ("plain", "half"))
    np.testing.assert_allclose(half, plain, rtol=1e-4, equal_nan=True)
    options = json.loads((tmp_path / "half" / "c0" / "summary.json").read_text())["options"]
    assert options["exposures"] == [2.0] * k
    # The lights refined per capture: each result has its refined rig.
    assert main([*common, "--out", str(tmp_path / "refined"), "--refine-lights", "intensity"]) == 0
    assert (tmp_path / "refined" / "c0" / "rig_refined.json").is_file()
    summary = json.loads((tmp_path / "refined" / "c0" / "summary.json").read_text())
    assert summary["options"]["refine_lights"] == "intensity"
    capsys.readouterr()
    # Checked before any work: a wrong count of exposures and a missing flat field.
    assert main([*common, "--out", str(tmp_path / "x"), "--exposures", "1,2"]) == 2
    assert "--exposures has 2 values" in capsys.readouterr().err
    assert main([*common, "--out", str(tmp_path / "x"), "--flat", str(tmp_path / "none.png")]) == 2
    assert "--flat" in capsys.readouterr().err and not (tmp_path / "x").exists()
