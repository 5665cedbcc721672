"""``nplps view``: write a result directory's 3-D viewer page and open it (:mod:`nplps.viewer`)."""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import webbrowser
from pathlib import Path
from typing import Any

from ..errors import InputError
from ..viewer import DEFAULT_MAX_TRIANGLES, VIEWER_FILE, write_result_viewer
from .console import _warnings_to_stderr

__all__ = ["add_view_parser", "can_open_browser", "cmd_view"]

VIEW_DESCRIPTION = f"""\
Show a result's mesh in 3-D in the web browser.

Writes one self-contained HTML page (default RESULT_DIR/{VIEWER_FILE}) that draws the mesh with
WebGL: no library, no network access, the mesh embedded in the page, so it opens offline from
disk and can be sent as one file. RESULT_DIR is what 'nplps reconstruct --out' writes (mesh.ply
and depth.npy are read). The page is then opened in the default browser, unless --no-open is
given or there is no display (CI=true, or no DISPLAY / WAYLAND_DISPLAY on Linux): then the
command prints the path to open.

In the page: drag to rotate, wheel or pinch to zoom, right-drag or shift-drag to pan, alt-drag
or the sliders to move the light (it moves with the eye), keys 1 2 3 colour by albedo, shaded
grey or normals, R resets the view. The object is upright as the camera saw it; the initial view
is oblique. A URL hash sets the view, e.g. {VIEWER_FILE}#azimuth=-40&elevation=10&zoom=1.5&mode=shaded
(also light_azimuth, light_elevation; all in degrees, azimuth = elevation = 0 is the camera's
viewpoint). Meshes of more than --max-triangles triangles are decimated on a regular grid, and
the page says so.
"""

VIEW_EPILOG = """\
examples:
  nplps view result                        # writes result/viewer.html and opens it
  nplps view result --out ball.html --no-open
  nplps view result --max-triangles 500000 # a smaller page for a large capture
"""


def add_view_parser(sub: Any, formatter: Any) -> argparse.ArgumentParser:
    """Add the ``view`` command and its options to the subparsers ``sub``; return its parser."""
    p = sub.add_parser(
        "view",
        help="show a result's mesh in 3-D: an offline WebGL page, opened in the browser",
        description=VIEW_DESCRIPTION,
        epilog=VIEW_EPILOG,
        formatter_class=formatter,
    )
    p.add_argument("result", metavar="RESULT_DIR", help="a result directory (from 'nplps reconstruct --out')")
    p.add_argument(
        "--out",
        metavar="FILE",
        help=f"the page to write (default RESULT_DIR/{VIEWER_FILE}; replaced; '-': standard output)",
    )
    p.add_argument("--no-open", action="store_true", help="only write the page and print its path")
    p.add_argument(
        "--max-triangles",
        type=int,
        default=DEFAULT_MAX_TRIANGLES,
        metavar="N",
        help=f"decimate larger meshes on a regular grid (default {DEFAULT_MAX_TRIANGLES:,}, about 50 MB of page)",
    )
    p.add_argument(
        "--units",
        metavar="UNIT",
        help="length unit shown with the extent and the scale bar, e.g. mm (default: the result's "
        "--units, else 'rig units')",
    )
    p.add_argument("--title", metavar="TEXT", help="title of the page (default: the directory's name)")
    return p


def can_open_browser() -> bool:
    """Tell whether a browser window can be opened here: not on CI, and with a display on Linux."""
    if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
        return False
    if sys.platform.startswith("linux"):
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


def cmd_view(args: argparse.Namespace) -> int:
    """Run ``nplps view``; return the exit status."""
    if args.max_triangles < 2:
        raise InputError(f"--max-triangles must be at least 2, got {args.max_triangles}")
    if args.out == "-":  # the page on standard output, not a file named "-"
        with tempfile.TemporaryDirectory(prefix="nplps-view-") as tmp:
            with _warnings_to_stderr():
                info = write_result_viewer(
                    args.result,
                    os.path.join(tmp, "viewer.html"),
                    title=args.title,
                    units=args.units,
                    max_triangles=args.max_triangles,
                )
            sys.stdout.write(Path(info.path).read_text(encoding="utf-8"))
            sys.stdout.flush()
        return 0
    with _warnings_to_stderr():
        info = write_result_viewer(
            args.result, args.out, title=args.title, units=args.units, max_triangles=args.max_triangles
        )
    size = f"{info.size_bytes / 1e6:.1f} MB"
    what = f"{info.triangles:,} triangles"
    if info.stride > 1:
        what += f", decimated on a grid of stride {info.stride} from {info.full_triangles:,}"
    print(f"viewer written: {info.path} ({what}; {size})", flush=True)
    url = Path(os.path.abspath(info.path)).as_uri()
    if not args.no_open and can_open_browser():
        try:
            opened = webbrowser.open(url)
        except webbrowser.Error:
            opened = False
        if opened:
            return 0
    print(f"open it in a web browser (works offline): {url}", flush=True)
    return 0
