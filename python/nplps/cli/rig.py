"""``nplps rig convert IN OUT``: convert rig, lights and camera files between formats."""

from __future__ import annotations

import argparse
import os
from typing import Any

from .console import describe_rig

RIG_DESCRIPTION = """\
Convert between nplps rig files (JSON) and other rig, lights and camera formats: RelightLab .dome
and .lp, AliceVision lights.json (and the intrinsics of an SfMData as a camera), OpenCV camera
files (FileStorage YAML .yml/.yaml or its JSON form). The input format is found from the
extension and, for .json, the keys; the output format from the extension (a file named
lights.json is AliceVision's, any other .json a rig file) or --to.

A lights file without a camera (.dome, .lp, lights.json) needs --camera. A .dome's positions are
in the dome's frame (origin on the object plane, z up): --camera-distance places them in the
camera frame. Whatever the output format cannot hold is refused with the reason (a point-light
rig as .lp, LEDs as .dome, an orthographic camera as OpenCV YAML). Conventions and sources:
docs/formats.md.
"""

RIG_EPILOG = """\
examples:
  nplps rig convert lights.lp rig.json --camera camera.yml
  nplps rig convert dome.dome rig.json --camera camera.yml --camera-distance 400
  nplps rig convert rig.json dome.dome --camera-distance 400
  nplps rig convert rig.json camera.yml            # the camera only
  nplps rig convert lights.json rig.json --camera cameras.sfm --intrinsic 1234
"""


def add_rig_parser(sub: Any, formatter: Any) -> argparse.ArgumentParser:
    """Add the ``rig`` command (with its ``convert`` subcommand) to ``sub``; return its parser."""
    from ..rig_formats import FORMATS

    p = sub.add_parser(
        "rig",
        help="convert rig, lights and camera files (.dome, .lp, lights.json, OpenCV YAML, SfMData)",
        description=RIG_DESCRIPTION,
        epilog=RIG_EPILOG,
        formatter_class=formatter,
    )
    actions = p.add_subparsers(dest="rig_command", metavar="ACTION", title="actions")
    c = actions.add_parser(
        "convert", help="convert IN to OUT", description=RIG_DESCRIPTION, epilog=RIG_EPILOG, formatter_class=formatter
    )
    c.add_argument("input", metavar="IN", help="a rig file, .dome, .lp or lights.json")
    c.add_argument("output", metavar="OUT", help="the file to write (.json, .dome, .lp, lights.json, .yml)")
    c.add_argument("--camera", metavar="FILE", help="the camera: OpenCV YAML/JSON, a rig file or an SfMData")
    c.add_argument("--intrinsic", metavar="ID", help="the intrinsicId of an SfMData --camera with several")
    c.add_argument(
        "--camera-distance",
        type=float,
        metavar="D",
        help="distance from the camera centre to the .dome frame's origin on the object plane (rig units)",
    )
    c.add_argument(
        "--light-distance",
        type=float,
        metavar="R",
        help="read the directions of a .lp or directional .dome as point lights R from the .dome origin",
    )
    c.add_argument(
        "--scale",
        type=float,
        metavar="S",
        help="rig units per unit of a .dome's positions (default 1: the .dome's mm; 0.1 for cm)",
    )
    c.add_argument("--from", dest="fmt_in", choices=FORMATS, help="the input format (default: detected)")
    c.add_argument("--to", dest="fmt_out", choices=FORMATS, help="the output format (default: by extension)")
    c.add_argument("--drop-intensities", action="store_true", help="write a .lp although intensities are not 1")
    return p


def cmd_rig(args: argparse.Namespace) -> int:
    """Run ``nplps rig ACTION``; return the exit status."""
    from .. import rig_formats
    from ..errors import RigError

    if args.rig_command != "convert":
        raise RigError("give an action: nplps rig convert IN OUT (see nplps rig --help)")
    if os.path.isdir(args.input):
        raise RigError(f"'{args.input}' is a directory")
    rig = rig_formats.load(
        args.input,
        fmt=args.fmt_in,
        camera=args.camera,
        camera_distance=args.camera_distance,
        light_distance=args.light_distance,
        intrinsic=args.intrinsic,
        scale=args.scale,
    )
    fmt = rig_formats.save(
        rig,
        args.output,
        fmt=args.fmt_out,
        camera_distance=args.camera_distance,
        drop_intensities=args.drop_intensities,
        scale=args.scale,
    )
    what = "the camera" if fmt.startswith("opencv") else describe_rig(rig)
    print(f"wrote {args.output} ({fmt}): {what}")
    return 0
