"""Shared fixtures and helpers of the tests (synthetic scenes, angles, the real captures).

Helpers are handed out as fixtures (``angular_error``, ``active_vertices``, ...) so that test
modules never import this file directly. Synthetic scenes are cached for the whole session: they
are read-only inputs, and building them once keeps the suite fast.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

import nplps


def _angular_error(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Per-pixel angle in degrees between the unit normals ``a`` and ``b`` (``(H, W, 3)``).

    Returns the 1-D array of the angles at the pixels of ``mask`` (every pixel if None). The
    angle is computed with atan2(|a x b|, a . b), which stays accurate for tiny angles (arccos of
    a dot product loses everything below ~1e-6 deg).
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if mask is not None:
        a, b = a[mask], b[mask]
    else:
        a, b = a.reshape(-1, 3), b.reshape(-1, 3)
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    dot = np.sum(a * b, axis=-1)
    return np.degrees(np.arctan2(cross, dot))


def _active_vertices(mask: np.ndarray) -> np.ndarray:
    """(H+1, W+1) bool: the vertices used by at least one masked pixel."""
    mask = np.asarray(mask, dtype=bool)
    h, w = mask.shape
    used = np.zeros((h + 1, w + 1), dtype=bool)
    for dr in (0, 1):
        for dc in (0, 1):
            used[dr : dr + h, dc : dc + w] |= mask
    return used


#: Real captures made by other people, beside the repository (see ../shared/data/README.md).
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_capture() -> Callable[[str], Path]:
    """The folder of a real capture in ../shared/data; skips the test when it is absent."""

    def folder(name: str) -> Path:
        path = SHARED_DATA / name
        if not path.is_dir():
            pytest.skip(f"real capture {name!r} not available: {path} does not exist")
        return path

    return folder


@pytest.fixture(scope="session")
def angular_error() -> Callable[..., np.ndarray]:
    """``angular_error(a, b, mask=None)`` -> per-pixel angles (degrees) between unit normals."""
    return _angular_error


@pytest.fixture(scope="session")
def active_vertices() -> Callable[[np.ndarray], np.ndarray]:
    """``active_vertices(mask)`` -> (H+1, W+1) bool of the vertices the mask uses."""
    return _active_vertices


_SCENES: dict[tuple, nplps.Scene] = {}


@pytest.fixture(scope="session")
def scene() -> Callable[..., nplps.Scene]:
    """``scene(name, n=48, seed=0, noise=0.0)`` -> a cached :func:`nplps.make_scene` result.

    Object size 100 at working distance 200 (the defaults of make_scene). Do not modify the
    arrays of a cached scene; copy them first.
    """

    def get(name: str, n: int = 48, seed: int = 0, noise: float = 0.0) -> nplps.Scene:
        key = (name, int(n), int(seed), float(noise))
        if key not in _SCENES:
            s = nplps.make_scene(name, n=n, seed=seed, noise=noise)
            for arr in (s.depth, s.mask, s.albedo, s.images):
                arr.setflags(write=False)
            _SCENES[key] = s
        return _SCENES[key]

    return get


@pytest.fixture(scope="module")
def auto_result() -> tuple[nplps.Scene, nplps.Reconstruction]:
    """A small synthetic scene and its ``depth="auto"`` reconstruction."""
    s = nplps.make_scene("bumps", n=24, seed=1)
    return s, nplps.reconstruct(s.images, s.rig, mask=s.mask, depth="auto")
