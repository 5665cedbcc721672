"""The streamed PLY writer (``_core.write_ply``, issue 23) writes the bytes of the array-based one.

``write_ply`` and ``Reconstruction.save`` stream the PLY file from the vertex grids in blocks of
rows, without whole position, normal and face arrays; these tests compare its files byte for
byte with the writer built on ``_core.mesh_arrays`` (``_build_mesh`` then ``_write_ply_mesh``).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

import nplps
from nplps import _core, export
from nplps.errors import InputError


def _array_ply(path: Path, vertices, mask, normals, albedo, opengl: bool) -> bytes:
    """The bytes of the array-based writer (the mesh arrays, then the record blocks)."""
    export._write_ply_mesh(path, export._build_mesh(vertices, mask, normals, albedo, opengl))
    return path.read_bytes()


def _streamed_ply(path: Path, vertices, mask, normals, albedo, opengl: bool) -> bytes:
    export.write_ply(path, vertices, mask, normals=normals, albedo=albedo, opengl=opengl)
    return path.read_bytes()


def _grids(seed: int, h: int, w: int, rgb: bool) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    depth = rng.uniform(5.0, 50.0, size=(h + 1, w + 1))  # at the vertices
    depth[rng.random((h + 1, w + 1)) < 0.05] = np.nan  # holes
    k = [[40.0, 0.0, w / 2], [0.0, 42.0, h / 2], [0.0, 0.0, 1.0]]
    camera = {"model": "pinhole", "K": k, "distortion": [0.01, -0.001, 0.0, 0.0, 0.0]}
    if seed % 2:
        camera = {"model": "orthographic", "pixel_size": [0.1, 0.12], "origin": [-1.0, 2.0]}
    rig = nplps.Rig(camera=camera, lights=np.array([[0.0, 0.0, -100.0]]))
    vertices = _core.vertices(depth, rig.camera)
    normals = _core.vertex_means(rng.normal(size=(h, w, 3)), True)
    normals[rng.random((h + 1, w + 1)) < 0.02] = np.nan
    shape = (h, w, 3) if rgb else (h, w, 1)
    albedo = _core.vertex_means(rng.uniform(0.0, 2.0, size=shape), False)
    albedo[rng.random(albedo.shape) < 0.03] = np.nan
    if not rgb:
        albedo = albedo[..., 0]
    mask = rng.random((h, w)) < 0.8
    _CAMERAS[seed, h, w] = depth, rig.camera
    return vertices, mask, normals, albedo


#: The vertex depths and camera of each ``_grids`` case.
_CAMERAS: dict[tuple[int, int, int], tuple[np.ndarray, dict]] = {}


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("opengl", [False, True])
def test_streamed_ply_is_the_array_writers_bytes(tmp_path: Path, seed: int, opengl: bool) -> None:
    h, w = [(7, 9), (40, 33), (130, 70), (1, 5), (66, 1), (65, 64)][seed]
    vertices, mask, normals, albedo = _grids(seed, h, w, rgb=seed % 3 == 2)
    for n, a in [(normals, albedo), (None, albedo), (normals, None), (None, None)]:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            try:
                expected = _array_ply(tmp_path / "a.ply", vertices, mask, n, a, opengl)
            except InputError:
                with pytest.raises(InputError, match="no facet"):
                    _streamed_ply(tmp_path / "b.ply", vertices, mask, n, a, opengl)
                continue
            assert _streamed_ply(tmp_path / "b.ply", vertices, mask, n, a, opengl) == expected


def test_a_reconstructions_saved_ply_is_the_array_writers_bytes(tmp_path: Path) -> None:
    scene = nplps.make_scene("bumps", n=24)
    r = nplps.reconstruct(scene.images, scene.rig, mask=scene.mask, depth=scene.mean_depth)
    r.save(tmp_path / "out")
    for opengl in (False, True):
        expected = _array_ply(tmp_path / "a.ply", r.vertices, r.mask, r.vertex_normals(), r.vertex_albedo(), opengl)
        r.save_ply(tmp_path / "b.ply", opengl=opengl)
        assert (tmp_path / "b.ply").read_bytes() == expected
    assert (tmp_path / "out" / "mesh.ply").read_bytes() == _array_ply(
        tmp_path / "a.ply", r.vertices, r.mask, r.vertex_normals(), r.vertex_albedo(), False
    )


def test_streamed_ply_warns_and_refuses_as_before(tmp_path: Path) -> None:
    vertices, _, normals, _ = _grids(0, 6, 6, rgb=False)
    vertices[2, 2] = np.nan
    with pytest.warns(RuntimeWarning, match=r"skipped \d+ masked facet"):
        export.write_ply(tmp_path / "a.ply", vertices, np.ones((6, 6), bool), normals=normals)
    with pytest.raises(InputError, match="no facet"):
        export.write_ply(tmp_path / "b.ply", vertices, np.zeros((6, 6), bool))
    assert not (tmp_path / "b.ply").exists()
    vertices[0, 0] = 1e300  # finite, beyond float32
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        with pytest.raises(InputError, match=r"1 vertex position.*float32 range"):
            export.write_ply(tmp_path / "c.ply", vertices, np.ones((6, 6), bool))
    assert not (tmp_path / "c.ply").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["a.ply"]  # no temporary file left


@pytest.mark.parametrize("seed", range(4))
def test_per_pixel_maps_give_the_vertex_grids_bytes(tmp_path: Path, seed: int) -> None:
    # save streams from the per-pixel normals and albedo: their vertex means are made per vertex.
    rng = np.random.default_rng(seed)
    h, w = [(9, 7), (50, 61), (1, 3), (70, 66)][seed]
    vertices, mask, _, _ = _grids(seed, h, w, rgb=False)
    normals = rng.normal(size=(h, w, 3))
    normals[rng.random((h, w)) < 0.05] = np.nan
    albedo = rng.uniform(0.0, 3.0, size=(h, w, 3) if seed % 2 else (h, w))
    albedo[rng.random(albedo.shape) < 0.05] = np.nan
    vertex_albedo = _core.vertex_means(albedo if albedo.ndim == 3 else albedo[..., None], False)
    if albedo.ndim == 2:
        vertex_albedo = vertex_albedo[..., 0]
    vertex_normals = _core.vertex_means(normals, True)
    for opengl in (False, True):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            expected = _array_ply(tmp_path / "a.ply", vertices, mask, vertex_normals, vertex_albedo, opengl)
            export._stream_ply(tmp_path / "b.ply", vertices, mask, normals, albedo, opengl, per_pixel=True)
            assert (tmp_path / "b.ply").read_bytes() == expected
            # The positions made from the camera and the vertex depths (as save writes them).
            depth, camera = _CAMERAS[seed, h, w]
            export._stream_ply(tmp_path / "c.ply", depth, mask, normals, albedo, opengl, per_pixel=True, camera=camera)
            assert (tmp_path / "c.ply").read_bytes() == expected
