"""The ``--out DIR`` / ``--overwrite`` pair of the commands that write a result directory.

These commands are ``reconstruct``, ``synth``, ``demo`` and ``synth-calibration``; see
:mod:`nplps._outdir`.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Iterator
from contextlib import contextmanager

from .._outdir import MANIFEST, ResultDirectory
from .console import _note

OVERWRITE_HELP = (
    "write into a non-empty --out directory: files of the same names are replaced, the files of an "
    f"earlier nplps result there that this run does not write (listed in its {MANIFEST}) are "
    "removed, other files are kept"
)


def add_output_options(parser: argparse.ArgumentParser, default: str | None = None) -> None:
    """Add ``--out DIR`` (required unless ``default``) and ``--overwrite``."""
    where = f"default {default}; " if default else ""
    parser.add_argument(
        "--out",
        required=default is None,
        default=default,
        metavar="DIR",
        help=f"output directory ({where}created if needed; must be empty unless --overwrite)",
    )
    parser.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)


def parse_formats(text: str) -> list[str]:
    """Parse ``--formats``: comma-separated names of :data:`nplps.export.FORMATS`.

    Raises :class:`argparse.ArgumentTypeError` (a usage error) for an unknown name.
    """
    from ..export import FORMATS

    names = list(dict.fromkeys(word.strip() for word in text.split(",") if word.strip()))
    unknown = [name for name in names if name not in FORMATS]
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown format(s) {', '.join(unknown)}; choose from {', '.join(FORMATS)}")
    return names


def output_directory(args: argparse.Namespace) -> ResultDirectory:
    """Return the ``--out`` directory of a command, checked now (before any work).

    Raises :class:`~nplps.errors.OutputExistsError` (exit status 2) if it is not empty and
    ``--overwrite`` was not given. Use it as a context manager around the writing.
    """
    return ResultDirectory(args.out, overwrite=args.overwrite, option="--overwrite")


@contextmanager
def writing(out: ResultDirectory) -> Iterator[ResultDirectory]:
    """Write a result into ``out`` (a ``with`` block); on an error or Ctrl-C, say what the folder holds.

    Either nothing was written (no trace of the run is left), or the folder is marked unfinished:
    its manifest says "in progress", so that it is never taken for a complete result (``nplps
    batch`` redoes it; ``--overwrite`` replaces it).
    """
    try:
        with out:
            yield out
    except BaseException:
        where = os.fspath(out.path)
        if out.written and os.path.exists(os.path.join(where, MANIFEST)):
            _note(
                f'the result in {where} is unfinished: its {MANIFEST} says "in progress" '
                "(run again with --overwrite to redo it)"
            )
        else:
            _note(f"nothing was written into {where}")
        raise
