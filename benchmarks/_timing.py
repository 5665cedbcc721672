"""The time of each file a ``save`` writes (used by ``save.py`` and ``scale.py``).

:func:`file_timer` records when each file written through :mod:`nplps._atomic` starts and ends;
:func:`covered` is the wall time a set of such intervals covers (files are written in parallel).
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any


@contextmanager
def file_timer(record: list[tuple[str, float, float]]) -> Iterator[None]:
    """Record (file name, start, end) of every file written through :mod:`nplps._atomic` in the block.

    A PNG file encoded by the Rust extension (``nplps._core.write_pngs``, several at once) ends
    when its encoding does: its rename waits for the meshes, which is not its own time.
    """
    from nplps import _atomic, _core, export

    original = _atomic.atomic_path
    encoder = getattr(_core, "write_pngs", None)
    encoded: dict[str, float] = {}

    @contextmanager
    def timed(path: Any) -> Iterator[str]:
        start = time.perf_counter()
        with original(path) as temporary:
            yield temporary
        end = min(time.perf_counter(), encoded.pop(temporary, float("inf")))
        record.append((os.path.basename(os.fspath(path)), start, end))

    def timed_encoder(jobs: Any, *args: Any) -> None:
        assert encoder is not None
        encoder(jobs, *args)
        encoded.update((path, time.perf_counter()) for path, _ in jobs)

    _atomic.atomic_path = timed  # type: ignore[assignment]
    saved = export.atomic_path
    export.atomic_path = timed  # type: ignore[assignment]
    if encoder is not None:
        _core.write_pngs = timed_encoder
    try:
        yield
    finally:
        _atomic.atomic_path = original  # type: ignore[assignment]
        export.atomic_path = saved  # type: ignore[assignment]
        if encoder is not None:
            _core.write_pngs = encoder


def covered(intervals: list[tuple[float, float]]) -> float:
    """Total length of the union of ``intervals``."""
    total, end = 0.0, -float("inf")
    for a, b in sorted(intervals):
        if b > end:
            total += b - max(a, end)
            end = b
    return total
