"""``nplps meshroom SFMDATA --output DIR``: reconstruct each pose of a Meshroom/AliceVision SfMData."""

from __future__ import annotations

import argparse
from typing import Any

from .console import _note, _warnings_to_stderr

MESHROOM_DESCRIPTION = """\
Reconstruct each pose of an AliceVision SfMData (what Meshroom's nodes pass on): the views sharing
a poseId are the images of one pose, one per light, sorted by path. The camera comes from the
SfMData's pinhole intrinsics, the lights from --lights (AliceVision lights.json, matched by viewId
when it has them; .lp, .dome or an nplps rig file, in the order of the images) or lights.json
beside the SfMData. Per pose it writes DIR/<poseId>_normals.png (16-bit RGB normals, OpenGL or
OpenCV frame: v = 2 p / 65535 - 1) and DIR/<poseId>/ with the full nplps result (mesh.ply,
mesh.obj, albedo.png, depth.tiff, depth.npy, normals.npy, summary.json, ...).

The Meshroom node (nplpsNodes/NplpsPhotometricStereo) runs this command: add the folder that
--plugin-path prints to MESHROOM_PLUGINS_PATH.
"""

MESHROOM_EPILOG = """\
examples:
  nplps meshroom cameras.sfm --output out --lights lights.json --depth 300
  nplps meshroom cameras.sfm --output out --lights dome.dome --camera-distance 400 --normal-frame opencv
  export MESHROOM_PLUGINS_PATH=$(nplps meshroom --plugin-path):$MESHROOM_PLUGINS_PATH
"""


def add_meshroom_parser(sub: Any, formatter: Any) -> argparse.ArgumentParser:
    """Add the ``meshroom`` command to the subparsers ``sub``; return its parser."""
    p = sub.add_parser(
        "meshroom",
        help="reconstruct each pose of a Meshroom/AliceVision SfMData (and the Meshroom node's plugin path)",
        description=MESHROOM_DESCRIPTION,
        epilog=MESHROOM_EPILOG,
        formatter_class=formatter,
    )
    p.add_argument("sfmdata", metavar="SFMDATA", nargs="?", help="the SfMData (.sfm or .json)")
    p.add_argument("--output", metavar="DIR", help="the output folder (created if needed)")
    p.add_argument("--plugin-path", action="store_true", help="print the Meshroom plugin folder and exit")
    p.add_argument(
        "--lights",
        metavar="FILE",
        nargs="?",
        const="",
        default="",
        help="lights.json, .lp, .dome or rig file (default: lights.json beside SFMDATA)",
    )
    p.add_argument("--depth", default="auto", help="working distance in the lights' unit, or 'auto' (default)")
    p.add_argument("--normal-frame", choices=("opengl", "opencv"), default="opengl", help="frame of the normal maps")
    p.add_argument(
        "--camera-distance",
        type=float,
        metavar="D",
        help="for a .dome/.lp: distance from the camera to the .dome frame's origin (0: none)",
    )
    p.add_argument("--light-distance", type=float, metavar="R", help="read .lp directions as point lights at R")
    p.add_argument("--mask-folder", metavar="DIR", nargs="?", const="", default="", help="folder of <poseId>.png masks")
    p.add_argument("--poses", metavar="IDS", help="comma-separated poseIds to reconstruct (default: all)")
    p.add_argument("--overwrite", action="store_true", help="replace the results of an earlier run")
    return p


def cmd_meshroom(args: argparse.Namespace) -> int:
    """Run ``nplps meshroom``; return the exit status."""
    from ..errors import InputError
    from ..meshroom import PLUGIN_PATH, run

    if args.plugin_path:
        print(PLUGIN_PATH)
        return 0
    if not args.sfmdata or not args.output:
        raise InputError("give SFMDATA and --output DIR (or --plugin-path)")
    depth: Any = args.depth
    if depth != "auto":
        try:
            depth = float(depth)
        except ValueError:
            raise InputError(f"--depth must be a number or 'auto', got {args.depth!r}") from None
    distance = args.camera_distance if args.camera_distance else None
    poses = [p.strip() for p in args.poses.split(",") if p.strip()] if args.poses else None
    with _warnings_to_stderr():
        results = run(
            args.sfmdata,
            args.output,
            lights=args.lights or None,
            depth=depth,
            normal_frame=args.normal_frame,
            camera_distance=distance,
            light_distance=args.light_distance,
            mask_folder=args.mask_folder or None,
            poses=poses,
            overwrite=args.overwrite,
        )
    for r in results:
        _note(f"pose {r.pose_id}: {len(r.images)} images, {r.status}; wrote {r.normals} and {r.folder}/")
    return 0
