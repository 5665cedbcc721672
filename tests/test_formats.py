"""Tests of the optional output formats (issue 11): STL, glTF binary, point cloud, float normal map."""

from __future__ import annotations

import hashlib
import json
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import tifffile

import nplps
from nplps import cli, export
from nplps.errors import InputError
from nplps.export import read_ply

_OPENGL = np.array([1.0, -1.0, -1.0], dtype=np.float32)


@pytest.fixture(scope="module")
def result() -> nplps.Reconstruction:
    """A small reconstruction with a mask that has holes (so not every vertex is used)."""
    scene = nplps.make_scene("bumps", n=24)
    mask = scene.mask.copy()
    mask[5:8, 6:9] = False
    return nplps.reconstruct(scene.images, scene.rig, mask=mask, depth=scene.mean_depth, iterations=3)


def _read_stl(path: Path) -> tuple[bytes, np.ndarray, np.ndarray]:
    """Header, facet normals (m, 3) and corners (m, 3, 3) of a binary STL file, parsed by hand."""
    data = path.read_bytes()
    (count,) = struct.unpack_from("<I", data, 80)
    assert len(data) == 84 + 50 * count
    records = np.frombuffer(
        data, dtype=[("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("a", "<u2")], count=count, offset=84
    )
    assert not records["a"].any()
    return data[:80], records["n"], records["v"]


_COMPONENTS = {5126: "<f4", 5125: "<u4", 5121: "u1"}
_WIDTH = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}


def _read_glb(path: Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The JSON document and the primitive's arrays of a GLB file, parsed from its chunks by hand."""
    data = path.read_bytes()
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert (magic, version, length) == (b"glTF", 2, len(data))
    json_length, json_type = struct.unpack_from("<I4s", data, 12)
    assert json_type == b"JSON" and json_length % 4 == 0
    document = json.loads(data[20 : 20 + json_length])
    bin_start = 20 + json_length
    bin_length, bin_type = struct.unpack_from("<I4s", data, bin_start)
    assert bin_type == b"BIN\x00" and bin_length % 4 == 0
    assert bin_start + 8 + bin_length == len(data)
    binary = data[bin_start + 8 :]
    assert document["asset"]["version"] == "2.0"
    assert document["buffers"] == [{"byteLength": bin_length}]
    primitive = document["meshes"][0]["primitives"][0]
    assert primitive["mode"] == 4
    arrays = {}
    for name, index in [*primitive["attributes"].items(), ("indices", primitive["indices"])]:
        accessor = document["accessors"][index]
        view = document["bufferViews"][accessor["bufferView"]]
        start = view["byteOffset"] + accessor["byteOffset"]
        assert start % 4 == 0
        width = _WIDTH[accessor["type"]]
        dtype = np.dtype(_COMPONENTS[accessor["componentType"]])
        assert view["byteLength"] == accessor["count"] * width * dtype.itemsize
        assert start + view["byteLength"] <= bin_length
        values = np.frombuffer(binary, dtype=dtype, count=accessor["count"] * width, offset=start)
        arrays[name] = values.reshape(accessor["count"], width) if width > 1 else values
    return document, arrays


def test_stl_is_the_mesh(result: nplps.Reconstruction, tmp_path: Path) -> None:
    result.save_ply(tmp_path / "mesh.ply")
    result.save_stl(tmp_path / "mesh.stl")
    ply = read_ply(tmp_path / "mesh.ply")
    header, normals, corners = _read_stl(tmp_path / "mesh.stl")

    assert header.startswith(b"nplps binary STL, frame opencv") and not header.startswith(b"solid")
    assert len(corners) == 2 * int(result.mask.sum())
    np.testing.assert_array_equal(corners, ply["vertices"][ply["faces"]])
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, rtol=1e-6)
    a, b, c = (corners[:, i].astype(np.float64) for i in range(3))
    cross = np.cross(b - a, c - a)
    np.testing.assert_allclose(normals, cross / np.linalg.norm(cross, axis=1, keepdims=True), atol=1e-6)
    assert (normals[:, 2] < 0).all()  # facing the camera


def test_stl_in_chunks_is_one_pass(result: nplps.Reconstruction, tmp_path: Path, monkeypatch: Any) -> None:
    result.save_stl(tmp_path / "one.stl")
    monkeypatch.setattr(export, "_GATHER_CHUNK", 7)
    result.save_stl(tmp_path / "chunks.stl")
    assert (tmp_path / "one.stl").read_bytes() == (tmp_path / "chunks.stl").read_bytes()


def test_glb_is_the_mesh(result: nplps.Reconstruction, tmp_path: Path) -> None:
    result.save_ply(tmp_path / "mesh.ply")
    result.save_glb(tmp_path / "mesh.glb")
    ply = read_ply(tmp_path / "mesh.ply")
    document, arrays = _read_glb(tmp_path / "mesh.glb")

    n = len(ply["vertices"])
    primitive = document["meshes"][0]["primitives"][0]
    position = document["accessors"][primitive["attributes"]["POSITION"]]
    assert position["count"] == n and position["type"] == "VEC3"
    assert position["min"] == [float(v) for v in ply["vertices"].min(axis=0)]
    assert position["max"] == [float(v) for v in ply["vertices"].max(axis=0)]
    assert document["accessors"][primitive["indices"]]["count"] == 3 * len(ply["faces"])
    assert document["accessors"][primitive["attributes"]["COLOR_0"]]["normalized"] is True
    assert document["asset"]["extras"]["frame"] == "opencv"
    np.testing.assert_array_equal(arrays["POSITION"], ply["vertices"])
    np.testing.assert_array_equal(arrays["NORMAL"], ply["normals"])
    np.testing.assert_allclose(np.linalg.norm(arrays["NORMAL"], axis=1), 1.0, rtol=1e-6)
    np.testing.assert_array_equal(arrays["COLOR_0"][:, :3], ply["colors"])
    assert (arrays["COLOR_0"][:, 3] == 255).all()
    np.testing.assert_array_equal(arrays["indices"].reshape(-1, 3), ply["faces"])
    assert arrays["indices"].max() == n - 1


def test_glb_without_normals_and_colours(tmp_path: Path) -> None:
    rows, cols = np.mgrid[0:4, 0:5].astype(np.float64)
    vertices = np.stack([cols, rows, np.full_like(rows, 2.0)], axis=2)
    export.write_glb(tmp_path / "plain.glb", vertices, np.ones((3, 4), dtype=bool))

    document, arrays = _read_glb(tmp_path / "plain.glb")

    assert set(document["meshes"][0]["primitives"][0]["attributes"]) == {"POSITION"}
    assert len(arrays["POSITION"]) == 20 and len(arrays["indices"]) == 3 * 2 * 12


def test_point_cloud_is_the_mesh_vertices(result: nplps.Reconstruction, tmp_path: Path, active_vertices: Any) -> None:
    result.save_ply(tmp_path / "mesh.ply")
    result.save_points(tmp_path / "points.ply")
    ply = read_ply(tmp_path / "mesh.ply")
    points = read_ply(tmp_path / "points.ply")

    assert b"element face" not in (tmp_path / "points.ply").read_bytes()[:1000]
    assert len(points["faces"]) == 0
    used = active_vertices(result.mask) & np.isfinite(result.vertices).all(axis=2)
    assert len(points["vertices"]) == int(used.sum())
    for key in ("vertices", "normals", "colors"):
        np.testing.assert_array_equal(points[key], ply[key])


def test_normals_tiff_round_trip(result: nplps.Reconstruction, tmp_path: Path) -> None:
    result.save_normals_tiff(tmp_path / "normals.tiff")

    loaded = tifffile.imread(tmp_path / "normals.tiff")

    assert loaded.dtype == np.float32 and loaded.shape == (*result.shape, 3)
    np.testing.assert_array_equal(loaded, result.normals.astype(np.float32))  # NaN outside the mask too
    with pytest.raises(InputError, match="shape"):
        export.save_normals_tiff(tmp_path / "bad.tiff", np.zeros((3, 4)))


def test_opengl_flip_applies_to_every_format(result: nplps.Reconstruction, tmp_path: Path) -> None:
    for frame in ("cv", "gl"):
        opengl = frame == "gl"
        result.save_stl(tmp_path / f"{frame}.stl", opengl=opengl)
        result.save_glb(tmp_path / f"{frame}.glb", opengl=opengl)
        result.save_points(tmp_path / f"{frame}.ply", opengl=opengl)

    header, normals_gl, corners_gl = _read_stl(tmp_path / "gl.stl")
    _, normals_cv, corners_cv = _read_stl(tmp_path / "cv.stl")
    assert b"frame opengl" in header
    np.testing.assert_array_equal(corners_gl, corners_cv * _OPENGL)
    np.testing.assert_allclose(normals_gl, normals_cv * _OPENGL, atol=1e-6)
    assert (normals_gl[:, 2] > 0).all()  # still facing the viewer

    doc_gl, gl = _read_glb(tmp_path / "gl.glb")
    _, cv = _read_glb(tmp_path / "cv.glb")
    assert doc_gl["asset"]["extras"]["frame"] == "opengl"
    np.testing.assert_array_equal(gl["POSITION"], cv["POSITION"] * _OPENGL)
    np.testing.assert_array_equal(gl["NORMAL"], cv["NORMAL"] * _OPENGL)
    np.testing.assert_array_equal(gl["indices"], cv["indices"])

    points_gl, points_cv = read_ply(tmp_path / "gl.ply"), read_ply(tmp_path / "cv.ply")
    assert "frame opengl" in points_gl["comments"]
    np.testing.assert_array_equal(points_gl["vertices"], points_cv["vertices"] * _OPENGL)
    np.testing.assert_array_equal(points_gl["normals"], points_cv["normals"] * _OPENGL)


def _digests(directory: Path) -> dict[str, str]:
    files = {}
    for path in sorted(directory.rglob("*")):
        if path.is_file() and path.name not in ("summary.json", "nplps-manifest.json"):  # timings, file list
            files[str(path.relative_to(directory))] = hashlib.sha256(path.read_bytes()).hexdigest()
    return files


def test_save_formats_adds_exactly_those_files(result: nplps.Reconstruction, tmp_path: Path) -> None:
    plain = result.save(tmp_path / "plain")
    extra = result.save(tmp_path / "extra", formats=("glb", "stl", "points", "normals_tiff", "stl"))

    assert set(extra) - set(plain) == {"glb", "stl", "points", "normals_tiff"}
    names = {p.name for p in extra.values()} - {p.name for p in plain.values()}
    assert names == {"mesh.glb", "mesh.stl", "points.ply", "normals.tiff"}
    manifest = json.loads((tmp_path / "extra" / "nplps-manifest.json").read_text())["files"]
    assert set(manifest) == {p.name for p in extra.values()}
    before, after = _digests(tmp_path / "plain"), _digests(tmp_path / "extra")
    assert {k: after[k] for k in before} == before  # the default files are unchanged
    assert result.save(tmp_path / "stem", stem="surface", formats=["glb"])["glb"].name == "surface.glb"


def test_save_rejects_unknown_formats_before_writing(result: nplps.Reconstruction, tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"'obj2'.*choose from stl, glb, points, normals_tiff"):
        result.save(tmp_path / "out", formats=["stl", "obj2"])
    assert not (tmp_path / "out").exists()


def test_cli_formats_option(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    scene = tmp_path / "scene"
    assert cli.main(["synth", "sphere", "--size", "24", "--out", str(scene)]) == 0
    common = ["reconstruct", str(scene), "--rig", str(scene / "rig.json"), "--mask", str(scene / "mask.png")]
    common += ["--depth", "200", "--iterations", "2", "-q"]
    assert cli.main([*common, "--out", str(tmp_path / "plain")]) == 0
    assert cli.main([*common, "--formats", "glb,stl", "--opengl", "--out", str(tmp_path / "extra")]) == 0
    capsys.readouterr()

    plain = set(_digests(tmp_path / "plain"))
    extra = set(_digests(tmp_path / "extra"))
    assert extra - plain == {"mesh.glb", "mesh.stl"}
    document, _ = _read_glb(tmp_path / "extra" / "mesh.glb")
    assert document["asset"]["extras"]["frame"] == "opengl"

    assert cli.main([*common, "--formats", "glb,usdz", "--out", str(tmp_path / "bad")]) == 2
    assert "unknown format(s) usdz" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def test_obj_is_opt_in_above_the_size_rule(
    tmp_path: Path, result: nplps.Reconstruction, monkeypatch: pytest.MonkeyPatch
) -> None:
    facets = int(result.mask.sum())
    small = result.save(tmp_path / "small")  # at most OBJ_MAX_FACETS: written by default
    assert "obj" in small and "skipped" not in json.loads((tmp_path / "small" / "summary.json").read_text())

    monkeypatch.setattr(export, "OBJ_MAX_FACETS", facets - 1)
    paths = result.save(tmp_path / "large")
    assert "obj" not in paths and not (tmp_path / "large" / "mesh.obj").exists()
    summary = json.loads((tmp_path / "large" / "summary.json").read_text())
    assert summary["skipped"] == {"mesh.obj": export.obj_skipped_note(facets)}
    assert 'formats=["obj"]' in summary["skipped"]["mesh.obj"] and "--obj" in summary["skipped"]["mesh.obj"]
    assert "mesh.obj" not in json.loads((tmp_path / "large" / "nplps-manifest.json").read_text())["files"]
    assert set(_digests(tmp_path / "small")) - set(_digests(tmp_path / "large")) == {"mesh.obj"}

    asked = result.save(tmp_path / "asked", formats=["obj"])
    assert (tmp_path / "asked" / "mesh.obj").read_bytes() == (tmp_path / "small" / "mesh.obj").read_bytes()
    assert asked["obj"] == tmp_path / "asked" / "mesh.obj"
    assert "skipped" not in json.loads((tmp_path / "asked" / "summary.json").read_text())


def test_cli_obj_option(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    scene = tmp_path / "scene"
    assert cli.main(["synth", "sphere", "--size", "24", "--out", str(scene)]) == 0
    common = ["reconstruct", str(scene), "--rig", str(scene / "rig.json"), "--mask", str(scene / "mask.png")]
    common += ["--depth", "200", "--iterations", "2", "-q", "--no-report"]
    monkeypatch.setattr(export, "OBJ_MAX_FACETS", 10)
    assert cli.main([*common, "--out", str(tmp_path / "plain")]) == 0
    assert cli.main([*common, "--obj", "--out", str(tmp_path / "obj")]) == 0
    assert cli.main([*common, "--formats", "obj", "--out", str(tmp_path / "formats")]) == 0
    capsys.readouterr()
    assert not (tmp_path / "plain" / "mesh.obj").exists()
    assert (tmp_path / "obj" / "mesh.obj").read_bytes() == (tmp_path / "formats" / "mesh.obj").read_bytes()
