"""What the command line prints besides its results.

The program name, notes on stderr, the Ctrl-C hint, library warnings as ``nplps: warning:``
lines, a one-line description of a rig, and image sizes (the progress bars are
:mod:`nplps.progress`'s). Sizes are printed width first, as the README writes them:
"W x H pixels" (a 480-row, 300-column image is "300 x 480 pixels").
"""

from __future__ import annotations

import sys
import warnings
from typing import Any

import numpy as np

from .._text import printable
from ..progress import CTRL_C_HINT

PROG = "nplps"


def _note(message: str) -> None:
    print(printable(message, keep_newlines=True), file=sys.stderr, flush=True)


def _hint_ctrl_c(args: Any) -> None:
    """Print the Ctrl-C hint on stderr at the start of a long command (not with --quiet)."""
    if not getattr(args, "quiet", False):
        _note(f"({CTRL_C_HINT})")


class _warnings_to_stderr:
    """Context manager that shows library warnings as ``nplps: warning: ...`` lines instead of Python's format."""

    def __enter__(self) -> None:
        self._ctx = warnings.catch_warnings(record=True)
        self._caught = self._ctx.__enter__()
        warnings.simplefilter("always")

    def __exit__(self, *exc: Any) -> None:
        caught = list(self._caught)
        self._ctx.__exit__(*exc)
        for w in caught:
            _note(f"{PROG}: warning: {w.message}")


def describe_size(shape: tuple[int, ...]) -> str:
    """'W x H pixels' for an image shape (H, W[, ...]): the order every printed size uses."""
    return f"{shape[1]} x {shape[0]} pixels"


def describe_rig(rig: Any) -> str:
    """'pinhole camera, 18 point lights, 9 directional lights' and the like."""
    far = int(np.count_nonzero(rig.directional))
    near = rig.n_lights - far
    counts = ((near, "point"), (far, "directional"))
    lights = [f"{count} {kind} light{'s' if count != 1 else ''}" for count, kind in counts if count]
    return f"{rig.camera.get('model', '?')} camera, {', '.join(lights) or 'no lights'}"
