"""The ``nplps calibrate`` and ``nplps synth-calibration`` commands.

``nplps calibrate spheres`` (light positions from shiny-sphere images),
``nplps calibrate intensity`` (light intensities from images of a flat board) and
``nplps synth-calibration`` (a synthetic calibration scene).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import stat
from collections.abc import Sequence
from typing import Any

import numpy as np

from .._atomic import write_text
from ..errors import InputError, OutputExistsError
from .console import PROG, _note, _warnings_to_stderr, describe_rig
from .imagefiles import resolve_images
from .outputs import add_output_options, output_directory, writing

CALIBRATE_DESCRIPTION = """\
Calibrate the lights of a rig.

  spheres    light positions (or directions of distant lights) from images of shiny spheres
  intensity  light intensities (and optionally LED anisotropy and directions) from images of a
             flat diffuse board

Run 'nplps calibrate spheres --help' or 'nplps calibrate intensity --help' for the options, and
see docs/calibration.md for what to photograph.
"""

CALIBRATE_EPILOG = """\
examples:
  nplps synth-calibration --out calib           # a synthetic scene to try it on
  nplps calibrate spheres calib/placement_0 calib/placement_1 --camera calib/camera.json \\
      --radius 20 --center-depth 180 --out calib/rig_spheres.json
  nplps calibrate intensity calib/board --rig calib/rig_spheres.json --plane-depth 200 \\
      --out calib/rig.json
"""

SPHERES_DESCRIPTION = """\
Locate each light from its highlights on shiny spheres of known radius (the paper's section 5).

Photograph one or more shiny balls (chrome or glossy, radius R) once per light, in the light
order of the rig, with the camera of the rig; move the balls and photograph again for more
placements. Each PLACEMENT is a directory of the k images (natural order; names containing
'mask' or 'ambient' are skipped); a list of image files is one placement. Each sphere is
located from its outline (a mask per placement: each connected region one sphere, or an
integer label image; or --detect), the highlight of each image gives the mirror ray towards the
light, and the light is the point nearest to its rays (rays that agree within --parallel-tol
make a distant light). A light needs two spheres (one placement with two balls, or two
placements) for a position. Sphere centres and lights are then refined jointly.

Orthographic cameras need the depth of the sphere centres (--center-depth: for a ball on a
board at depth z it is z - R, for a hemisphere lying flat on it z); pinhole cameras get it from
the outline (a given depth overrides it).

Prints one row per light: the position (or the direction towards a distant light), the number
of spheres it was seen on, the RMS distance of its rays from the position (scene units), the
RMS angle of the rays about it and their spread. Writes the rig with unit intensities; run
'nplps calibrate intensity' next for the intensities.
"""

SPHERES_EPILOG = """\
examples:
  nplps calibrate spheres balls_1/ balls_2/ --camera camera.json --radius 12.7 --out rig.json
  nplps calibrate spheres balls_1/ balls_2/ --camera camera.json --radius 12.7 \\
      --mask balls_1/mask.png --mask balls_2/mask.png --center-depth 187.3 --out rig.json
  nplps calibrate spheres shots/ --camera camera.json --radius 20 --detect 30 80 --count 2 --out rig.json
"""

INTENSITY_DESCRIPTION = """\
Fit each light's intensity from images of a flat diffuse board (white paper or card) on a
known plane, one image per light in the rig's order, with the light positions of the rig
(e.g. from 'nplps calibrate spheres'). The model is I = rho * Phi * max(0, n . beta(X)) at the
board point X of each pixel; the board's albedo and the exposure cannot be told apart from the
intensities, so they are relative: scaled to a geometric mean of 1. --fit-mu fits each LED's
anisotropy mu, --fit-direction also its principal direction; --albedo per_pixel estimates the
board's albedo per pixel (absorbs texture and vignetting). Writes the rig with the intensities
and prints one row per light: intensity, mu, RMS residual (% of the mean) and observations.
"""

INTENSITY_EPILOG = """\
examples:
  nplps calibrate intensity board/ --rig rig.json --plane-depth 200 --out rig_phi.json
  nplps calibrate intensity board/ --rig rig.json --plane 0 0.1 -1 -195 --fit-mu --fit-direction \\
      --mask board/mask.png --out rig_phi.json
"""

SYNTH_CALIBRATION_DESCRIPTION = """\
Write a synthetic calibration scene for the rig of 'nplps synth' (same camera and lights):
shiny spheres (Lambertian plus a Phong lobe, highlights saturating) on a dark board at two
placements (placement_0/, placement_1/: 8-bit images image_XX.png and mask.png), a flat white
board under the same lights (board/: images and board.json), camera.json (the camera without
lights), rig_true.json and scene.json (radius, centre depths), and nplps-manifest.json (the files
written). --out must be empty unless --overwrite (rig files written there later by
'nplps calibrate' are kept). Prints the commands that calibrate it.
"""

SYNTH_CALIBRATION_EPILOG = """\
examples:
  nplps synth-calibration --out calib
  nplps synth-calibration --camera pinhole --lights 8 --directional --spheres 2 --out calib
"""


FILE_OVERWRITE_HELP = "replace --out (and --report) if the file exists (default: refuse)"


def _refuse_existing(args: argparse.Namespace, *options: str) -> None:
    """Refuse an existing file as the target of ``options`` (e.g. "--out") unless ``--overwrite``.

    Devices and pipes (``/dev/stdout``, a FIFO) are written in place, not replaced: they are
    accepted. Raises :class:`~nplps.errors.OutputExistsError` (exit status 2) naming the option
    and the file, before any work is done; a directory or two options naming one file are an
    :class:`~nplps.errors.InputError`.
    """
    targets = [(option, getattr(args, option.lstrip("-").replace("-", "_"))) for option in options]
    targets = [(option, target) for option, target in targets if target is not None]
    if len(targets) == 2 and os.path.abspath(targets[0][1]) == os.path.abspath(targets[1][1]):
        raise InputError(f"{targets[0][0]} and {targets[1][0]} name the same file '{targets[0][1]}'")
    for option, target in targets:
        if os.path.isdir(target):
            raise InputError(f"{option} '{target}' is a directory; give the file to write")
        if args.overwrite:
            continue
        try:
            mode = os.stat(target).st_mode
        except FileNotFoundError:
            if not os.path.islink(target):
                continue
            mode = stat.S_IFLNK  # a dangling link: it would be replaced
        except OSError:
            continue  # not reachable (e.g. no such directory): writing names the problem
        if stat.S_ISCHR(mode) or stat.S_ISFIFO(mode) or stat.S_ISSOCK(mode):
            continue
        raise OutputExistsError(f"{option} '{target}' exists; pass --overwrite to replace it", target)


def _add_spheres_parser(sub: Any, formatter: Any) -> None:
    p = sub.add_parser(
        "spheres",
        help="light positions from images of shiny spheres",
        description=SPHERES_DESCRIPTION,
        epilog=SPHERES_EPILOG,
        formatter_class=formatter,
    )
    p.add_argument(
        "placements", nargs="+", metavar="PLACEMENT", help="a directory of k images per placement, or k image files"
    )
    p.add_argument("--camera", required=True, metavar="RIG", help="rig file with the camera (its lights are ignored)")
    p.add_argument("--radius", required=True, type=float, metavar="R", help="sphere radius, in the rig's unit")
    p.add_argument(
        "--mask",
        action="append",
        metavar="FILE",
        help="mask of the spheres, once per placement in order (default: mask.png in each placement directory)",
    )
    p.add_argument(
        "--detect",
        nargs=2,
        type=float,
        metavar=("MIN", "MAX"),
        help="find the spheres: their image radius range in pixels",
    )
    p.add_argument("--count", type=int, help="with --detect: spheres per placement (default: all found)")
    p.add_argument(
        "--center-depth",
        action="append",
        metavar="Z[,Z...]",
        help="depth of the sphere centres: once for all placements, or once per placement (one value, or one per "
        "sphere)",
    )
    p.add_argument(
        "--outline", choices=("mask", "images"), default="mask", help="outline from the mask (default) or the images"
    )
    p.add_argument(
        "--parallel-tol",
        type=float,
        default=0.5,
        metavar="DEG",
        help="rays within this RMS angle make a distant light (default 0.5)",
    )
    p.add_argument("--min-contrast", type=float, default=0.3, help="highlight contrast threshold (default 0.3)")
    p.add_argument("--no-refine", action="store_true", help="skip the joint refinement of spheres and lights")
    p.add_argument("--out", "-o", required=True, metavar="RIG", help="the calibrated rig file to write")
    p.add_argument("--report", metavar="JSON", help="also write the per-light and per-sphere report as JSON")
    p.add_argument("--reference", metavar="RIG", help=REFERENCE_HELP)
    p.add_argument(
        "--working-distance",
        type=float,
        metavar="D",
        help="with --reference: the distance the position errors are a percentage of (default: the mean depth "
        "of the sphere centres)",
    )
    p.add_argument("--overwrite", action="store_true", help=FILE_OVERWRITE_HELP)
    p.add_argument("--quiet", "-q", action="store_true", help="no notes on stderr")


REFERENCE_HELP = (
    "a rig file with the true lights (e.g. rig_true.json of nplps synth-calibration): print and report "
    "each light's error against it (positions in scene units and %% of the working distance, directions, "
    "relative intensities)"
)


def _add_intensity_parser(sub: Any, formatter: Any) -> None:
    p = sub.add_parser(
        "intensity",
        help="light intensities from images of a flat board",
        description=INTENSITY_DESCRIPTION,
        epilog=INTENSITY_EPILOG,
        formatter_class=formatter,
    )
    p.add_argument("images", nargs="+", metavar="IMAGES", help="a directory of k board images, or k image files")
    p.add_argument("--rig", required=True, metavar="RIG", help="rig file with the camera and the light positions")
    plane = p.add_mutually_exclusive_group(required=True)
    plane.add_argument("--plane-depth", type=float, metavar="Z", help="the board faces the camera at depth Z")
    plane.add_argument(
        "--plane",
        nargs=4,
        type=float,
        metavar=("NX", "NY", "NZ", "D"),
        help="the board plane NX x + NY y + NZ z = D (camera frame)",
    )
    p.add_argument("--mask", metavar="FILE", help="the board's pixels (default: all)")
    p.add_argument("--fit-mu", action="store_true", help="fit each LED's anisotropy mu")
    p.add_argument("--fit-direction", action="store_true", help="with --fit-mu: fit each LED's principal direction")
    p.add_argument(
        "--albedo", choices=("uniform", "per_pixel"), default="uniform", help="board albedo model (default uniform)"
    )
    p.add_argument("--color", action="store_true", help="fit R, G, B intensities of colour images (a white board)")
    p.add_argument("--out", "-o", required=True, metavar="RIG", help="the calibrated rig file to write")
    p.add_argument("--report", metavar="JSON", help="also write the per-light report as JSON")
    p.add_argument("--reference", metavar="RIG", help=REFERENCE_HELP)
    p.add_argument("--overwrite", action="store_true", help=FILE_OVERWRITE_HELP)
    p.add_argument("--quiet", "-q", action="store_true", help="no notes on stderr")


def add_calibrate_parser(sub: Any, formatter: Any) -> argparse.ArgumentParser:
    """Add the ``calibrate`` command (``spheres``, ``intensity``) to the subparsers ``sub``."""
    p = sub.add_parser(
        "calibrate",
        help="calibrate light positions (shiny spheres) and intensities (flat board)",
        description=CALIBRATE_DESCRIPTION,
        epilog=CALIBRATE_EPILOG,
        formatter_class=formatter,
    )
    kinds = p.add_subparsers(dest="calibration", metavar="KIND", title="kinds")
    _add_spheres_parser(kinds, formatter)
    _add_intensity_parser(kinds, formatter)
    return p


def add_synth_calibration_parser(sub: Any, formatter: Any) -> argparse.ArgumentParser:
    """Add the ``synth-calibration`` command to the subparsers ``sub``."""
    p = sub.add_parser(
        "synth-calibration",
        help="write a synthetic light-calibration scene (shiny spheres and a board)",
        description=SYNTH_CALIBRATION_DESCRIPTION,
        epilog=SYNTH_CALIBRATION_EPILOG,
        formatter_class=formatter,
    )
    add_output_options(p)
    p.add_argument("--camera", choices=("orthographic", "pinhole"), default="orthographic")
    p.add_argument("--lights", type=int, choices=(8, 27), default=27, help="8 or the 27 standard lights (default 27)")
    p.add_argument("--directional", action="store_true", help="every third standard light is a distant light")
    p.add_argument("--led", action="store_true", help="anisotropic LEDs with unequal intensities")
    p.add_argument("--size", type=int, default=200, metavar="N", help="image size N x N (default 200)")
    p.add_argument("--radius", type=float, default=20.0, help="sphere radius (default 20: 40 px at the default size)")
    p.add_argument("--spheres", type=int, choices=(1, 2), default=1, help="spheres per placement (default 1)")
    p.add_argument(
        "--noise", type=float, default=0.01, help="Gaussian noise, fraction of the full scale (default 0.01)"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-board", action="store_true", help="skip the board images")
    return p


# --------------------------------------------------------------------------------------------------
# commands
# --------------------------------------------------------------------------------------------------


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Run ``nplps calibrate spheres`` or ``nplps calibrate intensity``."""
    if getattr(args, "calibration", None) == "spheres":
        return _cmd_spheres(args)
    if getattr(args, "calibration", None) == "intensity":
        return _cmd_intensity(args)
    raise InputError("say what to calibrate: 'nplps calibrate spheres ...' or 'nplps calibrate intensity ...'")


def _placement_dirs(items: Sequence[str]) -> bool:
    """Whether the PLACEMENT arguments are directories (one placement each) or files (one)."""
    for item in items:
        if not os.path.exists(item):
            raise InputError(
                f"placement '{item}' not found: give a directory of images per placement, or the image files of one"
            )
    dirs = [os.path.isdir(i) for i in items]
    if any(dirs) and not all(dirs):
        raise InputError("give either directories (one per placement) or the image files of one placement, not both")
    return all(dirs)


def _parse_depths(values: Sequence[str] | None, n: int) -> Any:
    if not values:
        return None
    try:
        parsed = [[float(v) for v in item.split(",") if v.strip()] for item in values]
    except ValueError:
        raise InputError(f"--center-depth takes numbers (Z or Z1,Z2,...), got {' '.join(values)}") from None
    if any(not p for p in parsed):
        raise InputError("--center-depth needs a value")
    if len(parsed) == 1 and len(parsed[0]) == 1:
        return parsed[0][0]
    if len(parsed) != n:
        raise InputError(f"give --center-depth once for all placements or once per placement ({n}), got {len(parsed)}")
    return [p[0] if len(p) == 1 else p for p in parsed]


def _cmd_spheres(args: argparse.Namespace) -> int:
    from ..calibrate import calibrate_spheres, load_camera

    if not (np.isfinite(args.radius) and args.radius > 0):
        raise InputError(f"--radius must be positive, got {args.radius}")
    if args.count is not None and args.count < 1:
        raise InputError(f"--count must be at least 1 (spheres per placement), got {args.count}")
    _refuse_existing(args, "--out", "--report")
    if args.working_distance is not None and not (np.isfinite(args.working_distance) and args.working_distance > 0):
        raise InputError(f"--working-distance must be positive, got {args.working_distance}")
    if os.path.isdir(args.camera):
        raise InputError(f"--camera '{args.camera}' is a directory, not a rig file")
    rig = load_camera(args.camera)
    reference = _load_reference(args)
    dirs = _placement_dirs(args.placements)
    n = len(args.placements) if dirs else 1
    masks: list[Any] | None = None
    if args.mask:
        if len(args.mask) != n:
            raise InputError(f"give --mask once per placement: {n} placement(s), {len(args.mask)} mask(s)")
        masks = list(args.mask)
    elif args.detect is None:
        found = [os.path.join(p, "mask.png") for p in args.placements] if dirs else []
        if found and all(os.path.isfile(f) for f in found):
            masks = found
        else:
            raise InputError(
                "give the spheres' masks (--mask, once per placement, or mask.png in each placement directory) "
                "or --detect MIN MAX"
            )
    if dirs:
        placements = [
            resolve_images([d], mask=None if masks is None else masks[i], quiet=args.quiet)
            for i, d in enumerate(args.placements)
        ]
    else:
        placements = [resolve_images(list(args.placements), quiet=args.quiet)]
    if masks is not None and not args.mask and not args.quiet:
        _note(f"masks: {', '.join(masks)}")
    if args.count is not None and args.detect is None:
        raise InputError("--count goes with --detect")
    depth = _parse_depths(args.center_depth, len(placements))
    with _warnings_to_stderr():
        result = calibrate_spheres(
            placements,
            rig,
            args.radius,
            masks=masks,
            detect=None if args.detect is None else (args.detect[0], args.detect[1]),
            count=args.count,
            center_depth=depth,
            outline=args.outline,
            parallel_tol=args.parallel_tol,
            min_contrast=args.min_contrast,
            refine=not args.no_refine,
        )
    k = len(result.lights)
    print(f"{len(result.spheres)} sphere(s) in {len(placements)} placement(s), {k} lights")
    for s in result.spheres:
        c = ", ".join(f"{v:.3f}" for v in s.center)
        print(
            f"  sphere {s.index} (placement {s.placement}): centre ({c}), image radius {s.image_radius:.1f} px, "
            f"outline RMS {s.fit_rms:.3f} px" + (f", refined by {s.shift:.3g}" if s.shift else "")
        )
    if result.refinement:
        r = result.refinement
        print(
            f"  joint refinement: {r['highlights']} highlights, highlight RMS {r['highlight_rms'][0]:.4f} -> "
            f"{r['highlight_rms'][1]:.4f} px, spheres moved {r['outline_shift']:.3f} px RMS from their outlines"
            + (f", {r['dropped']} inconsistent highlight(s) left out" if r["dropped"] else "")
        )
    print()
    print(result.table())
    print(
        "  (se: standard error of the position, scene units, or of the direction, degrees, from the scatter "
        "of the light's rays; the spheres' own errors are not in it)"
    )
    comparison = None
    if reference is not None:
        if args.working_distance is not None:
            distance, what = float(args.working_distance), "given"
        else:
            distance, what = float(np.mean([sp.center[2] for sp in result.spheres])), "the spheres' mean depth"
        comparison = _compare(args.reference, reference, result.rig_or_none(), distance, what, intensities=False)
    for w in result.warnings:
        _note(f"{PROG}: warning: {w}")
    if args.report:
        _write_report(args.report, result, comparison)
    out_rig = result.rig  # raises RigError when a light was not seen
    out_rig.save(args.out)
    print(f"\nwrote {args.out} ({describe_rig(out_rig)}, unit intensities)")
    return 0


def _load_reference(args: argparse.Namespace) -> Any:
    """Return the ``--reference`` rig (read before any work, so that a bad file fails first), or None."""
    from .inputs import load_rig

    return None if args.reference is None else load_rig(args.reference)


def _compare(
    path: str, reference: Any, calibrated: Any, distance: float, what: str, intensities: bool = True
) -> dict[str, Any] | None:
    """Print the calibrated lights' errors against the `reference` rig (file `path`); return them for the report.

    Without `intensities` (the sphere calibration writes unit intensities) the intensity errors
    are left out.
    """
    from ..calibrate import compare_lights, reference_summary

    if calibrated is None:
        _note(f"{PROG}: warning: no comparison with {path}: a light was not located")
        return None
    rows = compare_lights(calibrated, reference, distance)
    if not intensities:
        for row in rows:
            row["intensity_error_percent"] = None
    summary = reference_summary(rows)
    print(f"\nagainst the reference {path} (working distance D = {distance:.4g}, {what}):")
    head = f"{'light':>5}  {'kind':<11} {'position error':>14} {'% of D':>7} {'direction °':>11}"
    print(head + (f" {'intensity %':>11}" if intensities else ""))

    def cell(v: Any, width: int, digits: int) -> str:
        return f"{'-':>{width}}" if v is None else f"{v:>{width}.{digits}f}"

    for r in rows:
        print(
            f"{r['light']:>5}  {r['kind']:<11} {cell(r['position_error'], 14, 3)} "
            f"{cell(r['position_error_percent'], 7, 3)} {cell(r['direction_error'], 11, 3)}"
            + (f" {cell(r['intensity_error_percent'], 11, 3)}" if intensities else "")
        )
    parts = []
    if summary["position_error_rms"] is not None:
        parts.append(
            f"positions RMS {summary['position_error_rms']:.3f} ({summary['position_error_percent_rms']:.3f} % of D), "
            f"max {summary['position_error_max']:.3f} ({summary['position_error_percent_max']:.3f} %)"
        )
    if summary["direction_error_rms"] is not None:
        parts.append(f"directions max {summary['direction_error_max']:.3f}°")
    if summary["intensity_error_percent_rms"] is not None:
        parts.append(
            f"intensities RMS {summary['intensity_error_percent_rms']:.3f} %, "
            f"max {summary['intensity_error_percent_max']:.3f} %"
        )
    print("  " + "; ".join(parts))
    return {"reference": os.fspath(path), "distance": distance, "lights": rows, "summary": summary}


def _board_distance(plane: Any) -> float:
    """Return the board's distance along the optical axis: its depth, or ``offset / n_z`` of ``(normal, offset)``."""
    if isinstance(plane, tuple):
        normal, offset = plane
        nz = float(normal[2])
        return abs(float(offset) / nz) if nz != 0 else float("nan")
    return float(plane)


def _finite(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def _write_report(path: str, result: Any, comparison: dict[str, Any] | None = None) -> None:
    def vec(v: Any) -> Any:
        return None if v is None else [float(x) for x in v]

    report = {
        "spheres": [
            {
                "placement": s.placement,
                "center": vec(s.center),
                "image_center": vec(s.image_center),
                "image_radius": s.image_radius,
                "fit_rms": s.fit_rms,
                "shift": s.shift,
            }
            for s in result.spheres
        ],
        "lights": [
            {
                "kind": light.kind,
                "position": vec(light.position),
                "direction": vec(light.direction),
                "rms_miss": None if not np.isfinite(light.rms_miss) else light.rms_miss,
                "rms_angle": None if not np.isfinite(light.rms_angle) else light.rms_angle,
                "spread": light.spread,
                "spheres": light.spheres,
                "warning": light.warning,
                "standard_error": None if light.standard_error is None else vec(light.standard_error),
                "direction_se": _finite(light.direction_se),
            }
            for light in result.lights
        ],
        "highlights": [[vec(h) if np.all(np.isfinite(h)) else None for h in row] for row in result.highlights],
        "status": result.status,
        "refinement": result.refinement,
        "warnings": result.warnings,
        "reference": comparison,
    }
    write_text(path, json.dumps(report, indent=2) + "\n")


def _cmd_intensity(args: argparse.Namespace) -> int:
    from ..calibrate import calibrate_intensities
    from .inputs import load_rig

    _refuse_existing(args, "--out", "--report")
    rig = load_rig(args.rig)
    reference = _load_reference(args)
    if reference is not None and reference.n_lights != rig.n_lights:
        raise InputError(
            f"--reference '{args.reference}' has {reference.n_lights} lights but --rig {rig.n_lights}: "
            "give the reference of the same lights, in the same order"
        )
    files = resolve_images(args.images, mask=args.mask, quiet=args.quiet)
    if args.fit_direction and not args.fit_mu:
        raise InputError("--fit-direction needs --fit-mu")
    plane: Any = args.plane_depth if args.plane is None else (args.plane[:3], args.plane[3])
    with _warnings_to_stderr():
        result = calibrate_intensities(
            files,
            rig,
            plane,
            mask=args.mask,
            fit_mu=args.fit_mu,
            fit_direction=args.fit_direction,
            albedo=args.albedo,
            color=args.color,
        )
    print(f"{rig.n_lights} lights, board scale (albedo x exposure) {result.scale:.6g}")
    print()
    print(result.table())
    print(
        "  (se %: relative standard error of the intensity from its residual and observations; the error of "
        "the light positions, which the intensities absorb, is not in it)"
    )
    comparison = None
    if reference is not None:
        distance = _board_distance(plane)
        comparison = _compare(args.reference, reference, result.rig, distance, "the board's distance along the axis")
    for w in result.warnings:
        _note(f"{PROG}: warning: {w}")
    if args.report:
        se = result.standard_errors
        record = {
            "scale": result.scale,
            "lights": [
                {
                    "intensity": [float(v) for v in result.intensities[i]],
                    "mu": float(result.mu[i]),
                    "rms": _finite(float(result.rms[i])),
                    "standard_error": _finite(float(se[i])),
                    "observations": int(result.observations[i]),
                }
                for i in range(len(result.rms))
            ],
            "warnings": result.warnings,
            "reference": comparison,
        }
        write_text(args.report, json.dumps(record, indent=2) + "\n")
    result.rig.save(args.out)
    print(f"\nwrote {args.out} ({describe_rig(result.rig)}, relative intensities)")
    return 0


def cmd_synth_calibration(args: argparse.Namespace) -> int:
    """Run ``nplps synth-calibration``."""
    from ..synth_calibration import make_board_scene, make_sphere_scene

    if args.size < 32:
        raise InputError(f"--size must be at least 32 pixels, got {args.size}")
    if not (np.isfinite(args.noise) and args.noise >= 0):
        raise InputError(f"--noise must be a non-negative fraction, got {args.noise}")
    directory = output_directory(args)
    out = directory.path
    scene = make_sphere_scene(
        args.camera,
        n=args.size,
        lights=args.lights,
        directional=args.directional,
        led=args.led,
        radius=args.radius,
        spheres=args.spheres,
        noise=args.noise,
        seed=args.seed,
    )
    with writing(directory):
        scene.save(directory)
        if not args.no_board:
            board = make_board_scene(
                scene.rig, n=args.size, noise=args.noise, seed=args.seed + 1, distance=scene.distance
            )
            board.save(directory.subdirectory("board"))
    print(
        f"wrote a sphere-calibration scene ({args.size} x {args.size} pixels, {describe_rig(scene.rig)}, "
        f"{len(scene.centers)} placements of {args.spheres} sphere(s) of radius {scene.radius:g}, "
        f"noise {args.noise:g}) to {out}"
    )
    placements = [str(out / f"placement_{i}") for i in range(len(scene.centers))]
    command = [
        PROG,
        "calibrate",
        "spheres",
        *placements,
        "--camera",
        str(out / "camera.json"),
        "--radius",
        f"{scene.radius:g}",
    ]
    if args.camera == "orthographic":
        for depths in scene.center_depths:
            command += ["--center-depth", ",".join(f"{z:g}" for z in depths)]
    command += ["--out", str(out / "rig_spheres.json")]
    print("calibrate the light positions with:")
    print("  " + " ".join(shlex.quote(c) for c in command))
    if not args.no_board:
        extra = ["--fit-mu", "--fit-direction"] if args.led else []
        command = [
            PROG,
            "calibrate",
            "intensity",
            str(out / "board"),
            "--rig",
            str(out / "rig_spheres.json"),
            "--plane-depth",
            f"{scene.distance:g}",
            *extra,
            "--out",
            str(out / "rig.json"),
        ]
        print(f"wrote the board images (plane z = {scene.distance:g}) to {out / 'board'}; then the intensities with:")
        print("  " + " ".join(shlex.quote(c) for c in command))
    return 0
