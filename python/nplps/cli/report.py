"""``nplps report RESULT_DIR``: re-make ``report.html`` from the files of a result directory."""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from typing import Any

from .console import _warnings_to_stderr

REPORT_DESCRIPTION = """\
Make report.html in a result directory (written by nplps reconstruct or Reconstruction.save)
from the files there: one self-contained HTML file (every picture embedded, no network, no
script) with the capture's facts, the input thumbnails (inputs.png, if the run wrote it), the
mask, normal map and albedo, the residual and depth maps with colour bars, the unfitted pixels,
three oblique shaded renders of the mesh, the convergence history, the distance curve (--depth
auto), the held-out table (held_out.json, if present), the timings and all options. A section
without data says so. nplps reconstruct writes the report by default (--no-report skips it).
"""

REPORT_EPILOG = """\
examples:
  nplps report result/                    # (re)writes result/report.html
  nplps report result/ --out /tmp/r.html  # somewhere else
"""


def add_report_parser(sub: Any, formatter: Any) -> argparse.ArgumentParser:
    """Add the ``report`` command to the subparsers ``sub``; return its parser."""
    p = sub.add_parser(
        "report",
        help="make report.html (one self-contained page) from a result directory",
        description=REPORT_DESCRIPTION,
        epilog=REPORT_EPILOG,
        formatter_class=formatter,
    )
    p.add_argument(
        "result", metavar="RESULT_DIR", help="a directory written by nplps reconstruct or Reconstruction.save"
    )
    p.add_argument(
        "--out",
        metavar="FILE",
        default=None,
        help="write the report here instead of RESULT_DIR/report.html ('-': standard output)",
    )
    return p


def cmd_report(args: argparse.Namespace) -> int:
    """Run ``nplps report``; return the exit status."""
    from ..report import write_report

    start = time.perf_counter()
    if args.out == "-":  # the page on standard output, not a file named "-"
        with tempfile.TemporaryDirectory(prefix="nplps-report-") as tmp:
            with _warnings_to_stderr():
                page = write_report(args.result, path=os.path.join(tmp, "report.html"))
            sys.stdout.write(page.read_text(encoding="utf-8"))
            sys.stdout.flush()
        return 0
    with _warnings_to_stderr():
        path = write_report(args.result, path=args.out)
    print(f"wrote {path} ({path.stat().st_size / 1024:.0f} KiB, {time.perf_counter() - start:.1f} s)")
    return 0
