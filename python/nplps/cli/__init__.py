"""The ``nplps`` command line.

It can reconstruct from image files or capture folders, evaluate with held-out lights, make
synthetic scenes, run a demo.

Run ``nplps --help`` (or ``python -m nplps --help``) for the overview and ``nplps COMMAND --help``
for each command. :func:`main` is the entry point; it returns the exit status instead of exiting,
so it can be called from Python and from tests.

The package holds :func:`main`, the top-level parser and the error handling; the commands are in
:mod:`~nplps.cli.reconstruct`, :mod:`~nplps.cli.evaluate` and :mod:`~nplps.cli.synth` (``synth``
and ``demo``), their shared input options in :mod:`~nplps.cli.inputs` (with
:mod:`~nplps.cli.imagefiles` and :mod:`~nplps.cli.parsers`), the ``--out``/``--overwrite``
options in :mod:`~nplps.cli.outputs`, and the stderr notes in :mod:`~nplps.cli.console`. The
package is argparse and printing only: what the input options do to the images is
:func:`nplps.pipeline.prepare`.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import textwrap
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any

from .. import __version__
from .._atomic import is_write_error
from .._text import printable
from ..errors import NplpsError
from .batch import add_batch_parser, cmd_batch
from .benchmark import add_benchmark_parser, cmd_benchmark
from .calibrate import add_calibrate_parser, add_synth_calibration_parser, cmd_calibrate, cmd_synth_calibration
from .console import PROG, describe_rig
from .evaluate import EVALUATE_COLUMNS, add_evaluate_parser, cmd_evaluate
from .imagefiles import IMAGE_SUFFIXES, SKIPPED_WORDS, resolve_images
from .inputs import (
    CAPTURE_LAYOUTS,
    CONVENTIONS,
    Inputs,
    add_input_options,
    build_inputs,
    check_input_args,
    load_rig,
    near_options,
)
from .meshroom import add_meshroom_parser, cmd_meshroom
from .parsers import parse_depth, parse_exposures, parse_lights
from .reconstruct import add_reconstruct_parser, cmd_reconstruct
from .report import add_report_parser, cmd_report
from .rig import add_rig_parser, cmd_rig
from .synth import add_demo_parser, add_synth_parser, cmd_demo, cmd_synth, depth_rms, normal_errors
from .view import add_view_parser, cmd_view

__all__ = [
    "CAPTURE_LAYOUTS",
    "CONVENTIONS",
    "EVALUATE_COLUMNS",
    "IMAGE_SUFFIXES",
    "PROG",
    "SKIPPED_WORDS",
    "Inputs",
    "add_input_options",
    "build_inputs",
    "build_parser",
    "check_input_args",
    "cmd_batch",
    "cmd_benchmark",
    "cmd_calibrate",
    "cmd_demo",
    "cmd_evaluate",
    "cmd_meshroom",
    "cmd_reconstruct",
    "cmd_report",
    "cmd_rig",
    "cmd_synth",
    "cmd_synth_calibration",
    "cmd_view",
    "depth_rms",
    "describe_rig",
    "load_rig",
    "main",
    "near_options",
    "normal_errors",
    "parse_depth",
    "parse_exposures",
    "parse_lights",
    "resolve_images",
]

MAIN_DESCRIPTION = f"""\
nplps: photometric stereo with near point lighting (Xie, Dai & Wang, CVPR 2015).

From k photographs of a still object, each lit by one small light (LED) close to the object,
nplps recovers a metric 3-D mesh, per-pixel normals and albedo. The camera and the lights come
from a rig file (JSON, see below), and the object's approximate distance from the camera (the
working distance) must be given.

{textwrap.fill(CONVENTIONS, 95)}

Rig file (JSON, version 2; version 1 files are read too):
  {{"version": 2,
   "camera": {{"model": "orthographic", "pixel_size": [w, h], "origin": [x0, y0]}},
   "lights": [{{"type": "point", "position": [x, y, z], "intensity": 1.0}}, ...]}}
  pixel_size: footprint of one pixel on the object; origin: scene (x, y) of the top-left
  corner of pixel (0, 0); lights in the same order as the images. A pinhole camera is
  {{"model": "pinhole", "K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]}} (0-based pixel centres);
  LEDs add "direction" and "mu", distant lights are {{"type": "directional", "direction": ...}}.
  See README.md, section "Rig file".
"""

MAIN_EPILOG = """\
examples:
  nplps demo                                    # synthetic sphere: near-light vs parallel-light
  nplps synth sphere --out scene                # write a synthetic scene (images, rig, mask)
  nplps reconstruct scene --rig scene/rig.json --mask scene/mask.png --depth 180 --out result
  nplps evaluate scene --rig scene/rig.json --mask scene/mask.png --depth 180 --lights 0,9,18
  nplps synth-calibration --out calib          # synthetic shiny spheres and a board
  nplps calibrate spheres calib/placement_0 calib/placement_1 --camera calib/camera.json \
      --radius 20 --center-depth 180 --out rig.json   # light positions from the highlights
  nplps view result                             # the mesh in 3-D: an offline page in the browser
  nplps report result                           # (re)make result/report.html
  nplps benchmark luces LUCES/data --bin 4      # per-object errors against LUCES's ground truth
  nplps reconstruct --help                      # all options of a command

results: a command with --out DIR writes only into a new or empty directory unless --overwrite
is given; then files of the same names are replaced, the files of an earlier nplps result there
that this run does not write (listed in its nplps-manifest.json) are removed, and every other
file is kept. Every file is written under a temporary name and renamed when complete: an error
or Ctrl-C never leaves a truncated file.

exit status: 0 success, 2 invalid input or usage (also: --out DIR not empty without
--overwrite), 1 output could not be written (the message names the file), 130 interrupted
(Ctrl-C), 143 terminated (SIGTERM).
"""


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of the ``nplps`` command."""
    formatter = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(
        prog=PROG, description=MAIN_DESCRIPTION, epilog=MAIN_EPILOG, formatter_class=formatter
    )
    parser.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", title="commands")
    # The commands are looked up here, in this module, each time the parser is built, so that
    # replacing nplps.cli.cmd_demo (and the others) takes effect.
    add_reconstruct_parser(sub, formatter).set_defaults(func=cmd_reconstruct)
    add_evaluate_parser(sub, formatter).set_defaults(func=cmd_evaluate)
    add_synth_parser(sub, formatter).set_defaults(func=cmd_synth)
    add_demo_parser(sub, formatter).set_defaults(func=cmd_demo)
    add_calibrate_parser(sub, formatter).set_defaults(func=cmd_calibrate)
    add_synth_calibration_parser(sub, formatter).set_defaults(func=cmd_synth_calibration)
    add_batch_parser(sub, formatter).set_defaults(func=cmd_batch)
    add_benchmark_parser(sub, formatter).set_defaults(func=cmd_benchmark)
    add_view_parser(sub, formatter).set_defaults(func=cmd_view)
    add_report_parser(sub, formatter).set_defaults(func=cmd_report)
    add_rig_parser(sub, formatter).set_defaults(func=cmd_rig)
    add_meshroom_parser(sub, formatter).set_defaults(func=cmd_meshroom)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``nplps`` command with ``argv`` (default ``sys.argv[1:]``); return the exit status.

    While it runs, SIGTERM (if not handled otherwise) raises an exception like Ctrl-C does, so that
    the solver stops and no temporary file is left behind; the exit status is then 143.
    """
    with _sigterm_raises():
        return _main(argv)


def _main(argv: Sequence[str] | None) -> int:
    parser = build_parser()
    try:
        try:
            args = parser.parse_args(None if argv is None else list(argv))
        except SystemExit as e:  # --help, --version, usage errors
            return _exit_code(e.code)
        if args.command is None:
            parser.print_help(sys.stderr)
            return 2
        return int(args.func(args) or 0)
    except NplpsError as e:
        _error(str(e))
        return 2
    except BrokenPipeError:  # output piped into e.g. `head`: stop quietly
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        except (OSError, ValueError, AttributeError):
            pass
        return 1
    except OSError as e:
        _error(_os_message(e))
        return 1
    except MemoryError as e:  # numpy (or Python) could not allocate: one line, as the core's errors
        detail = f" ({e})" if str(e) else ""
        _error(f"out of memory{detail}: free memory, or use --bin or a smaller --mask to need less")
        return 2
    except _Terminated:
        print("terminated", file=sys.stderr, flush=True)
        return 128 + signal.SIGTERM
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr, flush=True)
        return 130


class _Terminated(KeyboardInterrupt):
    """Raised by SIGTERM while :func:`main` runs.

    It is a KeyboardInterrupt: code that cleans up after Ctrl-C cleans up after it too.
    """


@contextmanager
def _sigterm_raises() -> Iterator[None]:
    """Make SIGTERM raise :class:`_Terminated` inside the block.

    Only if SIGTERM has its default action and this is the main thread; the previous handler is
    restored afterwards.
    """
    previous = None
    try:
        if signal.getsignal(signal.SIGTERM) == signal.SIG_DFL:
            previous = signal.signal(signal.SIGTERM, _raise_terminated)
    except ValueError:  # not the main thread
        pass
    try:
        yield
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _raise_terminated(signum: int, frame: Any) -> None:
    raise _Terminated()


def _exit_code(code: Any) -> int:
    if code is None:
        return 0
    if isinstance(code, int):
        return code
    print(code, file=sys.stderr)
    return 1


def _error(message: str) -> None:
    message = printable(" ".join(str(message).split())) or "unknown error"
    print(f"{PROG}: error: {message}", file=sys.stderr, flush=True)


def _os_message(e: OSError) -> str:
    what = e.strerror or str(e)
    if e.filename is not None:
        where = f"'{os.fspath(e.filename)}'"
        return f"cannot write {where}: {what}" if is_write_error(e) else f"{where}: {what}"
    return what
