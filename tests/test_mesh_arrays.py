"""The Rust mesh builders of ``save`` (``_core.vertex_means``, ``_core.mesh_arrays``) against numpy.

They replaced numpy code operation for operation so that the files stay the same bytes: these
tests compare them bit for bit with that numpy arithmetic, on grids with NaN and infinite values.
"""

from __future__ import annotations

import numpy as np
import pytest

from nplps import _core


def _numpy_vertex_means(values: np.ndarray, normalize: bool) -> np.ndarray:
    """The numpy arithmetic of ``Reconstruction._to_vertices`` before it moved to Rust (issue 23)."""
    h, w, c = values.shape
    finite = np.isfinite(values).all(axis=-1)[..., None]
    v = np.where(finite, values, 0.0)
    total = np.zeros((h + 1, w + 1, c))
    count = np.zeros((h + 1, w + 1, 1))
    for dr in (0, 1):
        for dc in (0, 1):  # the order of the sum: (r, c), (r, c - 1), (r - 1, c), (r - 1, c - 1)
            total[dr : dr + h, dc : dc + w] += v
            count[dr : dr + h, dc : dc + w] += finite
    total /= np.maximum(count, 1)
    total[count[..., 0] == 0] = np.nan
    if normalize:
        with np.errstate(invalid="ignore", divide="ignore"):
            total /= np.linalg.norm(total, axis=-1, keepdims=True)
    return total


def _noisy(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    values = rng.normal(size=shape) * rng.uniform(0.01, 100.0, size=shape[:2] + (1,) * (len(shape) - 2))
    values[rng.random(shape) < 0.05] = np.nan
    values[rng.random(shape) < 0.01] = np.inf
    values[rng.random(shape) < 0.02] = -0.0
    return values


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize(("channels", "normalize"), [(3, True), (3, False), (1, False)])
def test_vertex_means_are_numpys_bit_for_bit(seed: int, channels: int, normalize: bool) -> None:
    rng = np.random.default_rng(seed)
    h, w = rng.integers(1, 40, size=2)
    values = _noisy(rng, (int(h), int(w), channels))
    got = _core.vertex_means(values, normalize)
    expected = _numpy_vertex_means(values, normalize)
    assert got.shape == expected.shape and got.dtype == np.float64
    assert got.tobytes() == expected.tobytes()


def _numpy_mesh(vertices: np.ndarray, mask: np.ndarray, normals: np.ndarray | None, opengl: bool) -> tuple:
    """The numpy mesh of ``export._build_mesh`` before it moved to Rust (issue 23)."""
    finite = np.isfinite(vertices).all(axis=-1)
    if normals is not None:
        finite &= np.isfinite(normals).all(axis=-1)
    facets = mask & finite[:-1, :-1] & finite[:-1, 1:] & finite[1:, :-1] & finite[1:, 1:]
    used_grid = np.zeros(finite.shape, dtype=bool)
    for dr in (0, 1):
        for dc in (0, 1):
            used_grid[dr : dr + mask.shape[0], dc : dc + mask.shape[1]] |= facets
    used = np.flatnonzero(used_grid)
    index = np.full(finite.size, -1, dtype=np.int32)
    index[used] = np.arange(len(used), dtype=np.int32)
    flip = np.array([1.0, -1.0, -1.0], dtype=np.float32) if opengl else np.ones(3, dtype=np.float32)
    with np.errstate(over="ignore"):
        points = vertices.reshape(-1, 3)[used].astype(np.float32) * flip
        vertex_normals = None if normals is None else normals.reshape(-1, 3)[used].astype(np.float32) * flip
    flat = np.flatnonzero(facets)
    v00 = flat + flat // mask.shape[1]
    w1 = mask.shape[1] + 1
    i00, i01, i10, i11 = index[v00], index[v00 + 1], index[v00 + w1], index[v00 + w1 + 1]
    faces = np.stack([np.stack([i00, i10, i11], -1), np.stack([i00, i11, i01], -1)], 1).reshape(-1, 3)
    return used, points, vertex_normals, faces, int(mask.sum() - facets.sum())


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("opengl", [False, True])
@pytest.mark.parametrize("with_normals", [False, True])
def test_mesh_arrays_are_numpys(seed: int, opengl: bool, with_normals: bool) -> None:
    rng = np.random.default_rng(seed)
    h, w = (int(n) for n in rng.integers(1, 30, size=2))
    vertices = _noisy(rng, (h + 1, w + 1, 3))
    vertices[0, 0] = [1e39, -2.0, 3.0]  # beyond float32: infinite there
    normals = _noisy(rng, (h + 1, w + 1, 3)) if with_normals else None
    mask = rng.random((h, w)) < 0.7
    got = _core.mesh_arrays(vertices, mask, normals, opengl)
    expected = _numpy_mesh(vertices, mask, normals, opengl)
    for a, b in zip(got[:4], expected[:4], strict=True):
        if b is None:
            assert a is None
            continue
        assert a.dtype == b.dtype and a.shape == b.shape
        assert a.tobytes() == b.tobytes()
    assert got[4] == expected[4]


def test_mesh_arrays_refuse_wrong_shapes() -> None:
    vertices = np.zeros((4, 5, 3))
    with pytest.raises(Exception, match="mask"):
        _core.mesh_arrays(vertices, np.ones((3, 3), dtype=bool), None, False)
    with pytest.raises(Exception, match="shape"):
        _core.mesh_arrays(np.zeros((4, 5, 2)), np.ones((3, 4), dtype=bool), None, False)
