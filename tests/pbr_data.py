"""The committed Mitsuba 3 renders of benchmarks/pbr (tests/data/pbr) and the angle measure their tests share."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

import nplps

DATA = Path(__file__).parent / "data" / "pbr"


def load(name: str) -> tuple[dict[str, np.ndarray], nplps.Rig]:
    """Return the arrays of a committed render and its rig."""
    with np.load(DATA / f"{name}-64.npz") as f:
        data = dict(f)
    return data, nplps.Rig.from_dict(json.loads(str(data["rig"])))


def angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles in degrees between unit vectors (..., 3)."""
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))
