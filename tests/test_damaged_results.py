"""Regression tests: ``nplps report`` / ``nplps view`` on damaged result folders (issue 18, Why 9).

Each case of the issue's "30 tracebacks" class gets one test: the command exits with status 2 and
exactly one stderr line ``nplps: error: ...`` naming the damaged file and the problem. Also the
viewer template filled in one pass (a title with ``@SCRIPT@`` / ``@DATA@``) and STL/GLB refusing a
vertex beyond float32 instead of writing ``inf``.
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import nplps
from nplps.cli import main

_BASE: dict[str, Path] = {}


@pytest.fixture
def result(tmp_path_factory: pytest.TempPathFactory, tmp_path: Path) -> Path:
    if "dir" not in _BASE:
        scene = nplps.make_scene("sphere", n=12, seed=0)
        r = nplps.reconstruct(scene.images, scene.rig, depth=scene.mean_depth, mask=scene.mask)
        base = tmp_path_factory.mktemp("base")
        r.save(base, overwrite=True)
        _BASE["dir"] = base
    shutil.copytree(_BASE["dir"], tmp_path / "r")
    return tmp_path / "r"


def run(*argv: str) -> tuple[int, list[str]]:
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        status = main(list(argv))
    return status, err.getvalue().splitlines()


def assert_one_line(argv: list[str], file: str, *words: str) -> str:
    status, lines = run(*argv)
    assert status == 2, (status, lines)
    assert len(lines) == 1 and lines[0].startswith("nplps: error: damaged result file "), lines
    assert file in lines[0], lines[0]
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


def edit_summary(d: Path, **fields: object) -> None:
    doc = json.loads((d / "summary.json").read_text())
    doc.update(fields)
    (d / "summary.json").write_text(json.dumps(doc))


def test_undamaged_result_gives_status_0(result: Path) -> None:
    assert run("report", str(result)) == (0, [])
    assert run("view", str(result), "--no-open") == (0, [])


@pytest.mark.parametrize("value", [[1, 2], "text", 3, None])
def test_summary_not_an_object(result: Path, value: object) -> None:
    (result / "summary.json").write_text(json.dumps(value))
    assert_one_line(["report", str(result)], "summary.json", "not a JSON object")


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("shape", "12x12"),
        ("shape", [12]),
        ("timings", "fast"),
        ("timings", {"total": "1 s"}),
        ("estimated_distance", ["far"]),
        ("options", [1]),
        ("iterations", "5"),
        ("converged", "yes"),
    ],
)
def test_summary_field_of_the_wrong_type(result: Path, field: str, value: object) -> None:
    edit_summary(result, **{field: value})
    assert_one_line(["report", str(result)], "summary.json", f'"{field}"')


@pytest.mark.parametrize("command", [["report"], ["view", "--no-open"]])
def test_truncated_depth_npy(result: Path, command: list[str]) -> None:
    p = result / "depth.npy"
    p.write_bytes(p.read_bytes()[:600])
    assert_one_line([command[0], str(result), *command[1:]], "depth.npy", "truncated")


@pytest.mark.parametrize("command", [["report"], ["view", "--no-open"]])
def test_npy_header_claiming_a_huge_shape(result: Path, command: list[str]) -> None:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "<f8", "fortran_order": False, "shape": (100000, 100000)})
    (result / "depth.npy").write_bytes(buf.getvalue())
    assert len(buf.getvalue()) <= 128
    assert_one_line([command[0], str(result), *command[1:]], "depth.npy", "(100000, 100000)")


@pytest.mark.parametrize("name", ["residual.npy", "lights_used.npy", "normals.npy"])
def test_npy_of_another_shape(result: Path, name: str) -> None:
    if name == "normals.npy":  # read for the mask when mask.png is missing
        (result / "mask.png").unlink()
    np.save(result / name, np.zeros((5, 7, 3) if name == "normals.npy" else (5, 7), dtype=np.load(result / name).dtype))
    assert_one_line(["report", str(result)], name, "expected")


@pytest.mark.parametrize("name", ["mask.png", "normals.png", "albedo.png"])
def test_map_of_another_size(result: Path, name: str) -> None:
    nplps.export.write_png(result / name, np.full((8, 5), 200, dtype=np.uint8))
    assert_one_line(["report", str(result)], name, "5 x 8", "expected 12 x 12")


def test_history_with_two_columns(result: Path) -> None:
    (result / "history.csv").write_text("level,iteration\n0,1\n0,2\n")
    assert_one_line(["report", str(result)], "history.csv", "columns")


def test_history_row_with_two_columns(result: Path) -> None:
    p = result / "history.csv"
    p.write_text(p.read_text() + "0,9\n")
    assert_one_line(["report", str(result)], "history.csv", "2 column(s)")


@pytest.mark.parametrize("count", ["1e30", "1000000000000000000000000000000"])
def test_ply_declaring_1e30_vertices(result: Path, count: str) -> None:
    p = result / "mesh.ply"
    raw = p.read_bytes()
    n = int(raw.split(b"element vertex ")[1].split(b"\n")[0])
    p.write_bytes(raw.replace(f"element vertex {n}\n".encode(), f"element vertex {count}\n".encode(), 1))
    assert_one_line(["view", str(result), "--no-open"], "mesh.ply", count)


def test_ply_face_index_past_the_vertices(result: Path) -> None:
    p = result / "mesh.ply"
    raw = bytearray(p.read_bytes())
    raw[-4:] = np.int32(100000).tobytes()  # the last corner of the last face
    p.write_bytes(bytes(raw))
    assert_one_line(["view", str(result), "--no-open"], "mesh.ply", "vertex 100000")


@pytest.mark.parametrize("title", ["@SCRIPT@", "@DATA@", "a @TITLE@ b", "</script><b>x"])
def test_viewer_title_fills_the_template_once(result: Path, title: str) -> None:
    out = result / "v.html"
    assert run("view", str(result), "--no-open", "--out", str(out), "--title", title)[0] == 0
    text = out.read_text()
    assert text.count('<script id="nplps-mesh"') == 1
    assert text.count('"use strict"') == 1
    assert "</script><b>x" not in text
    assert nplps.viewer.read_viewer(out)["meta"]["title"] == title


@pytest.mark.parametrize("writer", ["write_stl", "write_glb"])
def test_stl_glb_refuse_a_vertex_beyond_float32(tmp_path: Path, writer: str) -> None:
    v = np.zeros((3, 3, 3))
    v[..., 0], v[..., 1], v[..., 2] = np.arange(3)[None, :], np.arange(3)[:, None], 100.0
    v[1, 1, 2] = 1e39
    with pytest.raises(nplps.InputError, match="float32"):
        getattr(nplps.export, writer)(tmp_path / "m", v, np.ones((2, 2), dtype=bool))
    assert not (tmp_path / "m").exists()
