"""``nplps batch``: a capture's own rig.json overrides --rig; --capture LAYOUT reads each folder with its loader.

The captures run on an in-process Dask cluster (quick); see tests/test_batch.py for the local
cluster of worker processes.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import nplps
from nplps import batch, export
from nplps.cli import main
from nplps.io import read_image

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


# --------------------------------------------------------------------------------------------------
# The output and camera RAW options of nplps reconstruct, in nplps batch
# --------------------------------------------------------------------------------------------------


def _reconstruct(folder: Path, out: Path, *extra: str) -> None:
    argv = ["reconstruct", str(folder), "--rig", str(folder / "rig.json"), "--mask", str(folder / "mask.png")]
    assert main([*argv, "--depth", "200", "--out", str(out), "--quiet", *extra]) == 0


def _dng_capture(tmp_path: Path, seed: int, shutters: tuple[tuple[int, int], ...] = ((1, 125),)) -> tuple[Any, Path]:
    """Make ``caps/dng`` (DNG files) and ``caps/png`` (PNG files) of one scene; return the scene and ``caps/dng``.

    The DNGs' half-size decoding is the scene's images quantised to the 14-bit-like sensor of
    tests/test_raw.py (decoded value 5 q); image i says the shutter time ``shutters[i % len]``.
    """
    pytest.importorskip("rawpy")
    from test_raw import BLACK, superpixels, write_dng

    scene = nplps.make_scene("bumps", n=32, seed=seed)
    scene.save(tmp_path / "png" / "obj")
    dng = tmp_path / "caps" / "dng"
    dng.mkdir(parents=True)
    for name in ("rig.json", "mask.png"):
        (dng / name).write_bytes((tmp_path / "png" / "obj" / name).read_bytes())
    for i, image in enumerate(sorted((tmp_path / "png" / "obj").glob("image_*.png"))):
        q = np.rint(read_image(image).astype(np.float64) / 5).astype(np.int64)
        shutter = shutters[i % len(shutters)]
        write_dng(dng / f"image_{i:02d}.dng", (BLACK + superpixels(q)).astype(np.uint16), shutter=shutter)
    scene.save(tmp_path / "caps" / "png")
    return scene, dng


def _files(out: Path) -> set[str]:
    return {p.name for p in out.iterdir()}


def test_help_shows_the_options_of_reconstruct(capsys: pytest.CaptureFixture[str]) -> None:
    from nplps.cli.options import OPTIONS

    assert main(["batch", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    for flag in ("--normal-map", "--exr", "--units", "--raw-wb", "--raw-half-size"):
        assert flag in text
        o = OPTIONS[flag]
        assert " ".join((o.batch_help or o.help).split()) in text  # the help of one place
    assert "camera RAW files (as for 'nplps reconstruct')" in text and "output of each capture" in text


def test_output_options_write_what_reconstruct_writes(
    tmp_path: Path, scheduler: str, capsys: pytest.CaptureFixture[str]
) -> None:
    nplps.make_scene("bumps", n=24, seed=4).save(tmp_path / "caps" / "obj")
    nplps.make_scene("sphere", n=24, seed=5).save(tmp_path / "caps" / "other")
    folder = tmp_path / "caps" / "obj"
    flags = ["--normal-map", "directx", "--units", "mm", "--threads", "1"]
    out = tmp_path / "out"
    common = ["batch", str(tmp_path / "caps" / "*"), "--rig", str(folder / "rig.json"), "--depth", "200"]
    common += ["--out", str(out), "--scheduler", scheduler]
    assert main([*common, *flags]) == 0, capsys.readouterr()
    _reconstruct(folder, tmp_path / "single", *flags)
    got, want = out / "obj", tmp_path / "single"
    assert _files(got) == _files(want)  # the same files (reports included)
    # The same result (one image model, the same input): maps bit for bit, the same conventions recorded.
    for name in ("depth.npy", "normals.npy", "albedo.png", "normals.png"):
        assert (got / name).read_bytes() == (want / name).read_bytes(), name
    a, b = (json.loads((d / "summary.json").read_text()) for d in (got, want))
    assert a["normal_map"] == b["normal_map"] and a["normal_map"]["frame"] == "directx"
    assert a["units"] == b["units"] == "mm"
    decoded = export.read_normal_map(got / "normals.png", frame="directx")
    normals = np.load(got / "normals.npy")
    inside = np.isfinite(normals[..., 0])
    assert np.degrees(np.arccos(np.clip(np.sum(decoded[inside] * normals[inside], -1), -1, 1))).max() < 0.01

    # Resumed with other output options: redone (the line says which), not mixed with the earlier results.
    capsys.readouterr()
    assert main([*common, "--normal-map", "opengl", "--units", "mm", "--threads", "1"]) == 0
    printed = capsys.readouterr().out
    assert printed.count("redone: the earlier result was made from other option normal_map") == 2
    assert json.loads((got / "summary.json").read_text())["normal_map"]["frame"] == "opengl"
    # ... and again with the same options (the defaults spelled out or left out alike): skipped.
    assert main([*common, "--units", "mm"]) == 0
    assert capsys.readouterr().out.count("skipped (complete result") == 2
    assert main([*common]) == 0  # without --units: redone
    assert capsys.readouterr().out.count("from other option units") == 2
    # From Python, too: the defaults given are the same as left out (also for results made before).
    api = {"pattern": str(tmp_path / "caps" / "*"), "rig": folder / "rig.json", "out": tmp_path / "api"}
    assert [i.status for i in batch.run(**api, depth=200.0, scheduler=scheduler)] == ["ok", "ok"]
    defaults = {"normal_map": "opengl", "formats": [], "units": None, "white_balance": "none", "half_size": False}
    items = batch.run(**api, depth=200.0, scheduler=scheduler, **defaults)
    assert [i.status for i in items] == ["skipped", "skipped"]


def test_exr_option(tmp_path: Path, scheduler: str, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("OpenEXR")
    nplps.make_scene("saddle", n=24, seed=6).save(tmp_path / "caps" / "obj")
    folder = tmp_path / "caps" / "obj"
    out = tmp_path / "out"
    args = ["batch", str(folder), "--rig", str(folder / "rig.json"), "--depth", "200", "--out", str(out)]
    assert main([*args, "--scheduler", scheduler, "--exr", "--normal-map", "opencv", "--no-report"]) == 0
    _reconstruct(folder, tmp_path / "single", "--exr", "--normal-map", "opencv", "--no-report")
    assert {"depth.exr", "normals.exr", "albedo.exr"} <= _files(out / "obj")
    assert _files(out / "obj") == _files(tmp_path / "single")
    for name in ("depth.exr", "normals.exr", "albedo.exr"):
        mine, theirs = (export.read_exr(d / name)[0] for d in (out / "obj", tmp_path / "single"))
        assert mine.keys() == theirs.keys()
        for channel in mine:
            assert np.array_equal(mine[channel], theirs[channel], equal_nan=True), (name, channel)
    assert json.loads((out / "obj" / "summary.json").read_text())["options"]["formats"] == ["exr"]
    # Resumed without --exr: redone, and the .exr files of the earlier result are removed.
    capsys.readouterr()
    assert main([*args, "--scheduler", scheduler, "--normal-map", "opencv", "--no-report"]) == 0
    assert "from other option formats" in capsys.readouterr().out
    assert not {"depth.exr", "normals.exr", "albedo.exr"} & _files(out / "obj")


def test_exr_without_openexr_is_refused_first(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import sys

    nplps.make_scene("saddle", n=16).save(tmp_path / "caps" / "a")
    monkeypatch.setitem(sys.modules, "OpenEXR", None)  # import OpenEXR now raises ImportError
    rig = str(tmp_path / "caps" / "a" / "rig.json")
    out = tmp_path / "out"
    code = main(["batch", str(tmp_path / "caps" / "*"), "--rig", rig, "--depth", "200", "--out", str(out), "--exr"])
    assert code == 2
    assert 'pip install "nplps[exr]"' in capsys.readouterr().err and not out.exists()
    with pytest.raises(nplps.InputError, match="OpenEXR"):
        batch.run(str(tmp_path / "caps" / "*"), rig, out, depth=200.0, formats=["exr"])
    with pytest.raises(nplps.InputError, match="normal_map"):
        batch.run(str(tmp_path / "caps" / "*"), rig, out, depth=200.0, normal_map="y-up")
    with pytest.raises(nplps.InputError, match="white balance"):
        batch.run(str(tmp_path / "caps" / "*"), rig, out, depth=200.0, white_balance="auto")
    args = ["batch", str(tmp_path / "caps" / "*"), "--rig", rig, "--depth", "1", "--out", str(out)]
    code = main([*args, "--units", " "])
    assert code == 2
    assert "--units must not be empty" in capsys.readouterr().err and not out.exists()


def test_raw_options_reach_the_decoder(tmp_path: Path, scheduler: str, capsys: pytest.CaptureFixture[str]) -> None:
    # A DNG capture whose half-size decoding is the scene's images, beside a PNG capture.
    _, dng = _dng_capture(tmp_path, seed=7)
    out = tmp_path / "out"
    common = ["batch", str(tmp_path / "caps" / "*"), "--depth", "200", "--out", str(out), "--scheduler", scheduler]
    common += ["--no-report", "--gray"]

    # Decoded at full size, the DNGs are twice the rig's grid: that capture fails, naming the size.
    assert main(common) == 1
    printed = capsys.readouterr().out
    assert "capture dng: failed: " in printed and "capture png: ok" in printed
    # At half size it runs, as nplps reconstruct --raw-half-size does: the same result, and the
    # default thresholds are one level of the sensor (white - black = 13107), not of 16 bits.
    assert main([*common, "--raw-half-size"]) == 0
    printed = capsys.readouterr().out
    assert "capture dng: ok" in printed and "capture png: skipped" in printed  # no RAW file: nothing changed
    _reconstruct(dng, tmp_path / "single", "--raw-half-size", "--gray", "--no-report")
    for name in ("depth.npy", "normals.npy", "albedo.png"):
        assert (out / "dng" / name).read_bytes() == (tmp_path / "single" / name).read_bytes(), name
    options = json.loads((out / "dng" / "summary.json").read_text())["options"]
    assert options["half_size"] is True and options["white_balance"] == "none"
    assert options["dark"] == pytest.approx(1 / 13107)
    # Another white balance: the RAW capture is redone (the line says why), the PNG one skipped.
    assert main([*common, "--raw-half-size", "--raw-wb", "camera"]) == 0
    printed = capsys.readouterr().out
    assert "capture dng: ok" in printed and "from other option white_balance" in printed
    assert "capture png: skipped" in printed
    assert json.loads((out / "dng" / "summary.json").read_text())["options"]["white_balance"] == "camera"


def test_mesh_and_normal_map_options_write_what_reconstruct_writes(
    tmp_path: Path, scheduler: str, capsys: pytest.CaptureFixture[str]
) -> None:
    nplps.make_scene("bumps", n=24, seed=8).save(tmp_path / "caps" / "obj")
    folder = tmp_path / "caps" / "obj"
    flags = ["--opengl", "--formats", "stl,points", "--normal-map-bits", "8", "--obj", "--no-report", "--threads", "1"]
    out = tmp_path / "out"
    common = ["batch", str(folder), "--rig", str(folder / "rig.json"), "--depth", "200", "--out", str(out)]
    common += ["--scheduler", scheduler]
    assert main([*common, *flags]) == 0, capsys.readouterr()
    _reconstruct(folder, tmp_path / "single", *flags)
    got, want = out / "obj", tmp_path / "single"
    assert {"mesh.stl", "points.ply", "mesh.obj", "mesh.ply"} <= _files(got)
    assert _files(got) == _files(want)
    for name in ("mesh.ply", "mesh.stl", "points.ply", "mesh.obj", "normals.png", "depth.npy"):
        assert (got / name).read_bytes() == (want / name).read_bytes(), name
    summary = json.loads((got / "summary.json").read_text())
    assert summary["normal_map"]["bits"] == 8
    assert summary["options"]["opengl"] is True and summary["options"]["formats"] == ["stl", "points", "obj"]
    # The OpenGL frame: y up, so the meshes differ from the camera frame's.
    _reconstruct(folder, tmp_path / "camera", "--formats", "stl", "--no-report", "--threads", "1")
    assert (tmp_path / "camera" / "mesh.stl").read_bytes() != (got / "mesh.stl").read_bytes()

    # Resumed with other output options: redone, naming the option; the same ones: skipped.
    capsys.readouterr()
    assert main([*common, *[f for f in flags if f not in ("--obj",)], "--formats", "stl,points,obj"]) == 0
    assert "skipped (complete result" in capsys.readouterr().out  # --obj is --formats obj
    assert main([*common, "--opengl", "--formats", "stl,points,obj", "--no-report", "--threads", "1"]) == 0
    assert "from other option normal_map_bits" in capsys.readouterr().out
    assert json.loads((got / "summary.json").read_text())["normal_map"]["bits"] == 16
    api = {"pattern": str(folder), "rig": folder / "rig.json", "out": tmp_path / "api", "report": False}
    assert [i.status for i in batch.run(**api, depth=200.0, scheduler=scheduler)] == ["ok"]
    items = batch.run(**api, depth=200.0, scheduler=scheduler, opengl=False, normal_map_bits=16)
    assert [i.status for i in items] == ["skipped"]  # the defaults given are the same as left out
    with pytest.raises(nplps.InputError, match="normal_map_bits must be 8 or 16"):
        batch.run(**api, depth=200.0, normal_map_bits=12)
    with pytest.raises(nplps.InputError, match="opengl must be True or False"):
        batch.run(**api, depth=200.0, opengl="yes")


def test_exposures_auto_reads_each_capture_s_raw_metadata(
    tmp_path: Path, scheduler: str, capsys: pytest.CaptureFixture[str]
) -> None:
    # A DNG capture whose files say two shutter times (1/50 s and 1/100 s), beside a PNG capture,
    # which has no exposure metadata. The batch must divide by what each capture's files say, as
    # nplps reconstruct --exposures auto does.
    scene, dng = _dng_capture(tmp_path, seed=9, shutters=((1, 50), (1, 100), (1, 100)))
    out = tmp_path / "out"
    common = ["batch", str(tmp_path / "caps" / "*"), "--depth", "200", "--out", str(out), "--scheduler", scheduler]
    common += ["--no-report", "--gray", "--raw-half-size", "--exposures", "auto"]
    assert main(common) == 1
    printed = capsys.readouterr().out
    assert "capture dng: ok" in printed
    assert "capture png: failed: " in printed and "is not a camera RAW file" in printed
    _reconstruct(dng, tmp_path / "single", "--raw-half-size", "--gray", "--no-report", "--exposures", "auto")
    for name in ("depth.npy", "normals.npy", "albedo.png"):
        assert (out / "dng" / name).read_bytes() == (tmp_path / "single" / name).read_bytes(), name
    recorded = json.loads((out / "dng" / "summary.json").read_text())["options"]["exposures"]
    assert recorded == [1.0 if i % 3 == 0 else 0.5 for i in range(scene.images.shape[0])]
    with pytest.raises(nplps.InputError, match="exposures must be numbers, one per light, or 'auto'"):
        batch.run(str(tmp_path / "caps" / "*"), None, out, depth=200.0, exposures="metadata")
