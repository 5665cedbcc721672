"""Parsers of option values: ``--depth``, ``--exposures``, ``--lights`` and comma-separated lists."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from ..errors import InputError


def parse_depth(value: str, option: str = "--depth") -> float | np.ndarray:
    """Parse ``--depth`` (or ``option``, e.g. ``--depth-prior``).

    Accept a positive number, 'auto', or the path of a .npy depth map of real numbers.
    """
    if value == "auto" and option == "--depth":
        return value  # type: ignore[return-value]
    try:
        number = float(value)
    except ValueError:
        number = None
    if number is not None:
        if not np.isfinite(number) or number <= 0:
            raise InputError(
                f"{option} must be a positive working distance (in the rig's unit) or a .npy depth map, got {value}"
            )
        return number
    if not os.path.exists(value):
        raise InputError(
            f"{option} '{value}' is neither a number (the working distance) nor an existing .npy depth map file"
        )
    if not value.lower().endswith(".npy"):
        raise InputError(
            f"{option} '{value}' is not a .npy file: give the working distance or an (H+1, W+1) .npy depth map"
        )
    try:
        depth = np.load(value, allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:  # EOFError: an empty file
        raise InputError(f"{option}: cannot read '{value}' as a .npy array: {e}") from None
    if not isinstance(depth, np.ndarray):  # np.load also reads .npz archives
        raise InputError(f"{option}: '{value}' holds an archive, not a single .npy array")
    real = np.issubdtype(depth.dtype, np.integer) or np.issubdtype(depth.dtype, np.floating)
    if depth.ndim != 2 or not real:
        raise InputError(
            f"{option}: '{value}' holds a {depth.dtype} array of shape {depth.shape}; "
            "it must be an (H+1, W+1) map of vertex depths (real numbers)"
        )
    return depth.astype(np.float64)


def parse_exposures(text: str, k: int) -> np.ndarray:
    """Parse ``--exposures E1,E2,...``: k positive numbers (``auto`` is read by ``reconstruct`` and ``evaluate``)."""
    if text.strip().lower() == "auto":
        raise InputError(
            "--exposures auto (from camera RAW metadata) is an option of nplps reconstruct and evaluate: "
            "give one number per image here"
        )
    values = _parse_list(text, float, "--exposures", "comma-separated numbers, e.g. 1,0.5,2")
    if len(values) != k:
        raise InputError(f"--exposures has {len(values)} values but there are {k} images: give one per image")
    e = np.array(values)
    if not np.all(np.isfinite(e)) or np.any(e <= 0):
        raise InputError(f"--exposures must be positive numbers, got {text}")
    return e


def parse_lights(text: str | None, k: int) -> list[int]:
    """Parse ``--lights I,J,...``: 0-based light indices (default: all k)."""
    if text is None:
        return list(range(k))
    lights = _parse_list(text, int, "--lights", "comma-separated light indices, e.g. 0,3,5")
    bad = [i for i in lights if not 0 <= i < k]
    if bad:
        raise InputError(f"--lights: {bad[0]} is not a light of the rig (0 .. {k - 1})")
    return lights


def _parse_list(text: str, kind: Any, option: str, expected: str) -> list[Any]:
    try:
        return [kind(part) for part in text.split(",")]
    except ValueError:
        raise InputError(f"{option} must be {expected}, got '{text}'") from None
