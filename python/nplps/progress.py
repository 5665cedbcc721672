"""Progress displays: one bar per stage on a terminal, a few plain lines elsewhere.

A run goes through stages -- load (images decoded), preprocess (the steps of
:mod:`nplps.pipeline`), distance search (``depth="auto"``: one candidate distance after the
other), iterations (the reconstruction itself, per pyramid level) and export. Each stage gets
one :class:`Bar`:

* on a terminal (the stream's ``isatty()``), a single line redrawn in place with a carriage
  return (at most 10 times a second), replaced by the stage's summary line when it ends;
* elsewhere (a pipe, a CI log, a file), a plain line at each fifth of the stage and at most
  every 10 seconds in between, then the summary line: a handful of lines per stage, never one
  per iteration.

:class:`ReconstructionProgress` turns the core's :class:`~nplps.Iteration` reports into these
bars (``nplps.reconstruct(..., progress=True)`` and the command line use it);
:class:`PipelineProgress` does the same for the loading and pre-processing reports of
:func:`nplps.pipeline.prepare`. Both write to ``sys.stderr`` by default. This module only
renders: it is plain Python without dependencies (no tqdm), so that the output is the same in
every environment and testable with any stream.
"""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any, Protocol, TextIO

if TYPE_CHECKING:
    from .reconstruction import Iteration, Reconstruction

__all__ = ["CTRL_C_HINT", "Bar", "PipelineProgress", "ReconstructionProgress", "aborting", "format_duration"]

#: The hint printed once at the start of long work. It is what happens: Ctrl-C raises
#: KeyboardInterrupt within a fraction of a second (also inside an iteration; a direct sparse
#: factorization finishes first), an output folder is left complete or marked unfinished (its
#: manifest says "in progress", never complete), and every file is written
#: under a temporary name and renamed when complete (the command exits with status 130).
CTRL_C_HINT = "Ctrl-C stops cleanly: no half-written file; an output folder is left complete or marked unfinished"

#: Seconds between two redraws of a terminal bar.
_REDRAW = 0.1
#: Seconds after which a plain (non-terminal) display prints a line even between milestones.
_KEEPALIVE = 10.0
#: Plain displays print a line each time a stage passes another 1/_MILESTONES of its total.
_MILESTONES = 5
_BAR_WIDTH = 10


def format_duration(seconds: float) -> str:
    """Return a short duration: ``0.42 s``, ``12 s``, ``3 min 5 s``, ``1 h 2 min``."""
    if not math.isfinite(seconds) or seconds < 0:
        return "?"
    if seconds < 10:
        return f"{seconds:.2f} s"
    if seconds < 60:
        return f"{seconds:.0f} s"
    minutes, secs = divmod(round(seconds), 60)
    if minutes < 60:
        return f"{minutes} min {secs} s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes} min"


class _Display(Protocol):
    def abort(self) -> None: ...


@contextmanager
def aborting(display: _Display | None) -> Iterator[None]:
    """End ``display``'s open lines if the block raises (an error or Ctrl-C), then re-raise.

    Parameters
    ----------
    display : Bar, ReconstructionProgress, PipelineProgress or None
        The display of the work in the block (None: nothing shown, nothing to end).
    """
    try:
        yield
    except BaseException:
        if display is not None:
            display.abort()
        raise


def _isatty(stream: TextIO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


def _columns(stream: TextIO) -> int:
    """Return the width of the terminal behind ``stream`` (80 when unknown)."""
    try:
        return max(20, os.get_terminal_size(stream.fileno()).columns)
    except (AttributeError, ValueError, OSError):
        return 80


class Bar:
    """The progress display of one stage.

    Parameters
    ----------
    label : str
        The stage's name, at the start of each line (``"load"``, ``"distance search"``, ...).
    total : int, optional
        How many units the stage has (0: unknown; then no bar, only the count and the detail).
    stream : text stream, optional
        Where to write (default ``sys.stderr``, looked up when the bar is made).
    tty : bool, optional
        Draw in place (a terminal) or print plain lines; default: ``stream.isatty()``.
    clock : callable, optional
        Seconds as a float (default :func:`time.monotonic`); tests pass a fake clock.
    start : float, optional
        When the stage began, on ``clock`` (default: now).
    """

    def __init__(
        self,
        label: str,
        *,
        total: int = 0,
        stream: TextIO | None = None,
        tty: bool | None = None,
        clock: Callable[[], float] = time.monotonic,
        start: float | None = None,
    ) -> None:
        self.label = label
        self.total = int(total)
        self.stream = sys.stderr if stream is None else stream
        self.tty = _isatty(self.stream) if tty is None else bool(tty)
        self._clock = clock
        self.start = clock() if start is None else start
        self.done = 0
        self.closed = False
        self._drawn = -math.inf
        self._printed = self.start
        self._milestone = 0
        self._shown = 0

    @property
    def elapsed(self) -> float:
        """Seconds since the bar was made."""
        return self._clock() - self.start

    def update(self, done: int, detail: str = "", *, total: int | None = None) -> None:
        """Show that ``done`` units are done, with a detail text (rate-limited)."""
        if self.closed:
            return
        if total is not None:
            self.total = int(total)
        self.done = int(done)
        now = self._clock()
        if self.tty:
            if now - self._drawn < _REDRAW:
                return
            self._drawn = now
            self._draw(self._text(detail, bar=True))
            return
        milestone = self.done * _MILESTONES // self.total if self.total > 0 else 0
        finished = self.total > 0 and self.done >= self.total  # the summary line follows
        if (milestone > self._milestone or now - self._printed >= _KEEPALIVE) and not finished:
            self._milestone = max(milestone, self._milestone)
            self._printed = now
            self._write(self._text(detail, bar=False) + "\n")

    def close(self, summary: str) -> None:
        """End the stage with its summary line ``label: summary``."""
        if self.closed:
            return
        self.closed = True
        line = f"{self.label}: {summary}"
        if self.tty:
            self._draw(line)
            self._write("\n")
        else:
            self._write(line + "\n")

    def abort(self) -> None:
        """End a terminal bar's line without a summary (before an error message), once."""
        if not self.closed:
            self.closed = True
            if self.tty and self._shown:
                self._write("\n")

    def _text(self, detail: str, *, bar: bool) -> str:
        count = f"{self.done}/{self.total}" if self.total > 0 else ""
        if bar and self.total > 0:
            filled = min(_BAR_WIDTH, _BAR_WIDTH * self.done // self.total)
            head = f"{self.label} [{'#' * filled}{'.' * (_BAR_WIDTH - filled)}] {count}"
        else:
            head = f"{self.label}: {count}" if count else f"{self.label}:"
        return f"{head} {detail}".rstrip()

    def _draw(self, text: str) -> None:
        text = text[: _columns(self.stream) - 1]
        pad = max(0, self._shown - len(text))
        self._write("\r" + text + " " * pad)
        self._shown = len(text)

    def _write(self, text: str) -> None:
        self.stream.write(text)
        self.stream.flush()


class ReconstructionProgress:
    """The bars of a reconstruction: the distance search and the iterations of each level.

    Call it with every :class:`~nplps.Iteration` the core reports (it is the ``progress``
    callback of ``nplps.reconstruct(..., progress=True)``), then :meth:`finish` with the result.

    Parameters
    ----------
    iterations : int
        The iteration limit (per pyramid level).
    stream, tty, clock
        As in :class:`Bar`.
    """

    def __init__(
        self,
        iterations: int,
        *,
        stream: TextIO | None = None,
        tty: bool | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.iterations = int(iterations)
        self._bar_options: dict[str, Any] = {"stream": stream, "tty": tty, "clock": clock}
        self.search: Bar | None = None
        self.solve: Bar | None = None
        self._level = -1
        self._level_start = 0.0
        self._last: Iteration | None = None
        self._best = (math.nan, math.nan)
        self._candidates = 0
        self._search_seconds = 0.0
        self._solve_iterations = 0

    def __call__(self, it: Iteration) -> None:
        """Show one iteration's report."""
        if it.candidate > 0:
            self._search(it)
        else:
            self._iteration(it)
        self._last = it

    def _search(self, it: Iteration) -> None:
        if self.search is None:
            self.search = Bar("distance search", total=it.candidates, **self._bar_options)
        evaluated = it.candidate if math.isfinite(it.candidate_residual) else it.candidate - 1
        if math.isfinite(it.best_distance):
            self._best = (it.best_distance, it.best_residual)
        self._candidates = max(self._candidates, evaluated)
        self._search_seconds = it.elapsed
        # The most useful first: a terminal line is cut at the terminal's width.
        parts = []
        if evaluated > 0:
            parts.append(f"~{format_duration((it.candidates - evaluated) * it.elapsed / evaluated)} left")
        if math.isfinite(self._best[0]):
            parts.append(f"best {self._best[0]:.5g}")
        if math.isfinite(it.candidate_residual):
            parts.append(f"candidate {it.distance:.5g}: residual {it.candidate_residual:.2e}")
        else:
            parts.append(f"candidate {it.distance:.5g}: iteration {it.iteration}")
        self.search.update(evaluated, ", ".join(parts), total=max(it.candidates, it.candidate))

    def _close_search(self) -> None:
        if self.search is not None and not self.search.closed:
            self.search.close(self.search_summary())

    def search_summary(self) -> str:
        """Return ``9 candidates, best 412.3 (residual 1.2e-03), 2.1 s`` (empty before a search)."""
        if self.search is None:
            return ""
        best = f"best {self._best[0]:.5g} (residual {self._best[1]:.3e})" if math.isfinite(self._best[0]) else "no best"
        return f"{self._candidates} candidates, {best}, {format_duration(self._search_seconds)}"

    def _iteration(self, it: Iteration) -> None:
        self._close_search()
        if it.level != self._level or self.solve is None or (self._last is not None and it.iteration == 1):
            self._close_solve()
            self._level = it.level
            self._level_start = self._last.elapsed if self._last is not None else 0.0
            label = f"iterations (level {it.level})" if it.level else "iterations"
            self.solve = Bar(label, total=self.iterations, **self._bar_options)
        self._solve_iterations = it.iteration
        per = (it.elapsed - self._level_start) / it.iteration
        left = (self.iterations - it.iteration) * per
        detail = f"depth change {it.depth_change:.2e}"
        if it.iteration < self.iterations:
            detail += f", at most ~{format_duration(left)} left"
        self.solve.update(it.iteration, f"{detail}, rms residual {it.rms_residual:.2e}")

    def _close_solve(self, status: str = "") -> None:
        if self.solve is None or self.solve.closed or self._last is None:
            return
        last = self._last
        text = f"{self._solve_iterations} iteration{'s' if self._solve_iterations != 1 else ''}"
        text += f", last depth change {last.depth_change:.2e}"
        if status:
            text += f", {status}"
        self.solve.close(f"{text}, {format_duration(last.elapsed - self._level_start)}")

    def finish(self, result: Reconstruction | None = None) -> None:
        """Close the open bars; the last one's summary names the result's status."""
        self._close_search()
        self._close_solve(result.status if result is not None else "")

    def abort(self) -> None:
        """End the open bars' lines (an error or Ctrl-C follows)."""
        for bar in (self.search, self.solve):
            if bar is not None:
                bar.abort()


class PipelineProgress:
    """The load and preprocess bars of :func:`nplps.pipeline.prepare` (its ``progress`` callback).

    It is called ``(stage, done, total, name)``: ``("load", i, k, file name)`` after each image
    is decoded, ``("preprocess", i, 0, step)`` before each pre-processing step. Call
    :meth:`finish` when the pipeline has returned.

    Parameters
    ----------
    stream, tty, clock
        As in :class:`Bar`.
    """

    def __init__(
        self,
        *,
        stream: TextIO | None = None,
        tty: bool | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._bar_options: dict[str, Any] = {"stream": stream, "tty": tty, "clock": clock}
        self._clock = clock
        self._start = clock()
        self.load: Bar | None = None
        self.preprocess: Bar | None = None
        self.steps: list[str] = []

    def __call__(self, stage: str, done: int, total: int, name: str) -> None:
        """Show one report of the pipeline."""
        if stage == "load":
            if self.load is None:  # loading began when the display was made
                self.load = Bar("load", total=total, start=self._start, **self._bar_options)
            self.load.update(done, f"{name}", total=total)
        elif stage == "preprocess":
            self._close_load()
            if self.preprocess is None:
                self.preprocess = Bar("preprocess", **self._bar_options)
            self.steps.append(name)
            self.preprocess.update(len(self.steps), f"{name} ({len(self.steps)})")

    def _close_load(self) -> None:
        if self.load is not None and not self.load.closed:
            n = self.load.done
            self.load.close(f"{n} image{'s' if n != 1 else ''} read in {format_duration(self.load.elapsed)}")

    def finish(self) -> None:
        """Close the open bars with their summaries."""
        self._close_load()
        if self.preprocess is not None and not self.preprocess.closed:
            self.preprocess.close(f"{', '.join(self.steps)} in {format_duration(self.preprocess.elapsed)}")

    def abort(self) -> None:
        """End the open bars' lines (an error or Ctrl-C follows)."""
        for bar in (self.load, self.preprocess):
            if bar is not None:
                bar.abort()
