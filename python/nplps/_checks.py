"""Checks of the public API's arguments, shared by its modules.

Each check returns the argument in the form the compiled core takes, or raises
:class:`~nplps.InputError` with a short message naming the argument (never a huge repr).
"""

from __future__ import annotations

import math
from typing import Any, Literal, cast

import numpy as np

from .errors import InputError
from .rig import Rig
from .types import RefineLights, Solver

#: Most worker threads (``threads``). Far more than any machine's cores: a larger number is a
#: mistake, and merely starting a million threads takes many seconds before anything is computed.
MAX_THREADS = 1024


def _check_rig(rig: Any) -> None:
    if not isinstance(rig, Rig):
        raise InputError(f"rig must be an nplps.Rig, got {type(rig).__name__}")


def _refine_choice(mode: str | None) -> RefineLights | Literal["none"]:
    """Check ``refine_lights``: None, "intensity", "position" or "both"."""
    if mode is None or mode is False:
        return "none"
    if mode not in ("intensity", "position", "both"):
        raise InputError(f'refine_lights must be None, "intensity", "position" or "both", got {mode!r}')
    return cast(RefineLights, str(mode))


def _short(value: Any) -> str:
    """Return a short description of ``value`` for messages.

    Never a huge repr (a long string, an integer of thousands of digits, a large array).
    """
    if isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_)):
        bits = int(value).bit_length()
        return str(int(value)) if bits <= 64 else f"an integer of about {int(bits * math.log10(2)) + 1} digits"
    if isinstance(value, (float, np.floating, complex, np.complexfloating)):
        return f"{value:.6g}"
    if isinstance(value, (str, bytes)):
        return repr(value) if len(value) <= 40 else repr(value[:37]) + "..."
    if isinstance(value, np.ndarray):
        return f"an array of dtype {value.dtype} and shape {value.shape}"
    if isinstance(value, (bool, np.bool_)) or value is None:
        return repr(value)
    return f"a value of type {type(value).__name__}"


def _real(value: Any, name: str) -> float:
    """``value`` as a float (a real number, not a string, bool or complex), or InputError."""
    if isinstance(value, (bool, np.bool_, str, bytes)) or np.iscomplexobj(value):
        raise InputError(f"{name} must be a real number, got {_short(value)}")
    try:
        return float(value)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{name} must be a real number, got {_short(value)}") from None


def _light_indices(lights: Any, k: int, name: str = "lights", negative: bool = True) -> list[int]:
    """Return ``lights`` as a list of indices of ``k`` lights, or raise InputError.

    Indices run from -k with ``negative``, else from 0.
    """
    try:
        flat = not isinstance(lights, (str, bytes)) and np.ndim(lights) == 1
    except ValueError:  # a ragged nested sequence
        flat = False
    if not flat:
        raise InputError(f"{name} must be a list of light indices, got {_short(lights)}")
    low = -k if negative else 0
    for i in lights:
        if isinstance(i, (bool, np.bool_)) or not isinstance(i, (int, np.integer)) or not low <= i < k:
            kind = "" if isinstance(i, (int, np.integer)) else f" ({type(i).__name__})"
            raise InputError(
                f"{name} must be whole-number indices of the rig's {k} lights ({low} .. {k - 1}), got {_short(i)}{kind}"
            )
    return [int(i) for i in lights]


def _real_array(value: Any, name: str) -> np.ndarray:
    """Return ``value`` as a contiguous float64 array, or raise InputError.

    The values must be integers or floats: not bools, strings, complex numbers or objects.
    """
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError):  # ragged nested sequences
        raise InputError(f"{name} must be an array of real numbers, got {_short(value)}") from None
    if not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        got = _short(value if arr.ndim == 0 and not isinstance(value, np.ndarray) else arr)
        raise InputError(f"{name} must be an array of real numbers, got {got}")
    return np.ascontiguousarray(arr, dtype=np.float64)


def _positive(value: Any, name: str) -> float:
    """``value`` as a positive finite float, or InputError."""
    v = _real(value, name)
    if not (np.isfinite(v) and v > 0):
        raise InputError(f"{name} must be a positive finite number, got {v:.6g}")
    return v


_UNITS = {
    "": 1,
    "b": 1,
    "k": 1e3,
    "kb": 1e3,
    "m": 1e6,
    "mb": 1e6,
    "g": 1e9,
    "gb": 1e9,
    "t": 1e12,
    "tb": 1e12,
    "kib": 2**10,
    "mib": 2**20,
    "gib": 2**30,
    "tib": 2**40,
}


def _memory_limit(value: Any, name: str = "max_memory") -> float | None:
    """Return a memory limit in bytes from a number or a string like "8 GB" / "512MiB" (None: the default)."""
    if value is None:
        return None
    if isinstance(value, str):
        text = value.strip().lower().replace(" ", "")
        number = text.rstrip("abcdefghijklmnopqrstuvwxyz")
        unit = text[len(number) :]
        if unit not in _UNITS or not number:
            raise InputError(f'{name} must be a number of bytes or a size such as "8 GB" or "512 MiB", got {value!r}')
        v = _real(_float_text(number, value, name), name) * _UNITS[unit]
    else:
        v = _real(value, name)
    if not v > 0:
        raise InputError(f"{name} must be a positive number of bytes, got {v:.6g}")
    return v


def _float_text(text: str, original: str, name: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise InputError(
            f'{name} must be a number of bytes or a size such as "8 GB" or "512 MiB", got {original!r}'
        ) from None


def _whole(value: Any, name: str, minimum: int) -> int:
    """``value`` as an int of at least ``minimum`` (integral floats accepted), or InputError."""
    if isinstance(value, (bool, np.bool_)):
        raise InputError(f"{name} must be a whole number, got {value!r}")
    if isinstance(value, (int, np.integer)):
        v = int(value)
    else:
        try:
            f = _real(value, name)
        except InputError:
            raise InputError(f"{name} must be a whole number, got {_short(value)}") from None
        if not (np.isfinite(f) and f == int(f)):
            raise InputError(f"{name} must be a whole number, got {_short(value)}")
        v = int(f)
    if v < minimum:
        raise InputError(f"{name} must be at least {minimum}, got {_short(v)}")
    return v


def _depth_range(value: Any) -> tuple[float, float] | None:
    """``depth_range`` as (near, far) with 0 < near < far, both finite, or InputError."""
    if value is None:
        return None
    if isinstance(value, (str, bytes)) or np.ndim(value) != 1 or len(value) != 2:
        raise InputError(f"depth_range must be a pair (near, far) of numbers, got {value!r}")
    near, far = (_positive(v, "depth_range") for v in value)
    if not near < far:
        raise InputError(f"depth_range must have near < far, got ({near:.6g}, {far:.6g})")
    return near, far


def _flag(value: Any, name: str) -> bool:
    """Return a bool option (numpy bools too); anything else is an InputError."""
    if not isinstance(value, (bool, np.bool_)):
        raise InputError(f"{name} must be True or False, got {_short(value)}")
    return bool(value)


def _shadows(value: Any) -> Literal["auto", "on", "off"]:
    """Return the cast-shadow policy of ``shadows=`` (True, False or "auto") by its core name; else InputError."""
    if isinstance(value, str) and value == "auto":
        return "auto"
    if isinstance(value, (bool, np.bool_)):
        return "on" if value else "off"
    raise InputError(f'shadows must be "auto", True or False, got {_short(value)}')


def _finite_number(value: Any, name: str) -> float:
    """``value`` as a finite float >= 0, or InputError."""
    v = _real(value, name)
    if not (np.isfinite(v) and v >= 0):
        raise InputError(f"{name} must be a finite number >= 0, got {v:.6g}")
    return v


def _solver_choice(solver: str) -> Solver:
    if solver not in ("auto", "direct", "multigrid"):
        raise InputError(f'solver must be "auto", "direct" or "multigrid", got {solver!r}')
    return cast(Solver, solver)


def _levels(levels: int | None) -> int:
    if levels is None:
        return 0
    if isinstance(levels, bool) or not isinstance(levels, (int, np.integer)) or int(levels) < 1:
        raise InputError(f"levels must be a whole number of at least 1 (or None for automatic), got {levels!r}")
    return int(levels)


def _threads(threads: int | None) -> int:
    """``threads`` as a whole number from 1 to :data:`MAX_THREADS`, 0 for None (all cores)."""
    if threads is None:
        return 0
    n = _whole(threads, "threads", 1)
    if n > MAX_THREADS:
        raise InputError(f"threads must be at most {MAX_THREADS} (or None for all cores), got {_short(n)}")
    return n
