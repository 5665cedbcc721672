"""The ``nplps`` command line: reconstruct from image files or capture folders, evaluate with
held-out lights, make synthetic scenes, run a demo.

Run ``nplps --help`` (or ``python -m nplps --help``) for the overview and ``nplps COMMAND --help``
for each command. :func:`main` is the entry point; it returns the exit status instead of exiting,
so it can be called from Python and from tests.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import re
import shlex
import sys
import textwrap
import time
import warnings
from pathlib import Path
from typing import Any, NamedTuple, Sequence

import numpy as np

from . import __version__
from .errors import InputError, NplpsError

PROG = "nplps"

#: File name endings taken as images when IMAGES is a directory.
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".pnm", ".webp")

#: Words that keep a file of an IMAGES directory out of the image list.
SKIPPED_WORDS = ("mask", "ambient")

#: Capture folder layouts of ``--capture``.
CAPTURE_LAYOUTS = ("near_ps", "diligent")

CONVENTIONS = (
    "Conventions: camera frame as in OpenCV (x right, y down, z forward into the scene, depth = z); "
    "the rig file gives the camera (orthographic pixel footprint, or pinhole K) and the lights in "
    "one length unit (mm typical), and depths are in that unit too."
)

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
  nplps reconstruct --help                      # all options of a command

exit status: 0 success, 2 invalid input or usage, 1 output could not be written,
130 interrupted.
"""

INPUT_NOTES = """\
Input: IMAGES (one file per light in the rig's order, or one directory) and --rig; or a capture
folder: --capture near_ps FOLDER (camera.mat, light.mat, the images, a mask and an ambient image
found by name; the ambient image is subtracted and cos^4 vignetting compensated by default) or
--capture diligent FOLDER (a DiLiGenT object folder with filenames.txt: directional lights,
orthographic camera with 1-unit pixels). A .npy --depth map must match the images after --bin.

Thresholds: by default, for integer images, observations at the top level (raw values, before
any pre-processing) are saturated and left out, and values at or below one level above black
are shadowed (0 after pre-processing, whose subtractions and scalings move the levels).
"""

RECONSTRUCT_DESCRIPTION = f"""\
Reconstruct a surface from k images taken under the k lights of a rig.

Writes into --out: mesh.ply and mesh.obj (the masked surface, vertex normals, albedo as
colour), normals.png (normal map), shaded.png (the mesh lit from the camera), albedo.png
(16-bit), depth.npy / depth.tiff (vertex depths, (H+1, W+1), NaN where no masked pixel),
normals.npy, residual.npy and summary.json. RGB images give an RGB albedo unless --gray.

{INPUT_NOTES}
{textwrap.fill(CONVENTIONS, 95)}
"""

RECONSTRUCT_EPILOG = """\
examples:
  # all images of a folder (sorted by name; files with 'mask' or 'ambient' in the name are skipped):
  nplps reconstruct shots/ --rig rig.json --mask shots/mask.png --depth 250 --out result
  # explicit files, in the rig's light order, initial depth map from a previous run:
  nplps reconstruct a.png b.png c.png d.png --rig rig.json --depth result/depth.npy --out refined
  # compare with conventional (parallel-light) photometric stereo, written to result/baseline:
  nplps reconstruct shots/ --rig rig.json --depth 250 --out result --baseline
  # camera JPEGs from a pinhole rig: decode sRGB, subtract the ambient shot, cos^4, 4 x 4 bins:
  nplps reconstruct shots/ --rig rig.json --depth 200 --srgb --ambient shots/ambient.jpg \\
      --vignetting cos4 --bin 4 --robust tukey --out result
  # a near_ps capture folder (a glob pattern after the folder picks its images if needed):
  nplps reconstruct --capture near_ps hehe12/ 'photometric_sample_raw_[0-9]*.png' \\
      --depth 200 --bin 4 --out hehe12-result
  # a DiLiGenT object, grey:
  nplps reconstruct --capture diligent ballPNG/ --depth 1000 --gray --out ball
"""

EVALUATE_DESCRIPTION = f"""\
Check a rig and its reconstruction without ground truth: leave each light out in turn,
reconstruct from the others, predict the left-out image and compare it with the captured one.
Runs the near-light method (nplps) and the parallel-light baseline and prints, per light:
the relative error |prediction - image| / |image| over the masked, usable pixels, and the
shape error (the same after the best gain, free of the light's intensity calibration), plus
the means. Lower is better; a better light model predicts better. RGB images are averaged
to grey.

{INPUT_NOTES}"""

EVALUATE_EPILOG = """\
examples:
  nplps evaluate shots/ --rig rig.json --mask shots/mask.png --depth 250
  nplps evaluate --capture near_ps hehe12/ 'photometric_sample_raw_[0-9]*.png' --depth 200 \\
      --bin 8 --lights 0,3,5
"""

SYNTH_DESCRIPTION = """\
Write a synthetic scene: 16-bit images image_XX.png (RGB with --rgb) rendered by the solver's
image model under 27 lights, rig.json, mask.png, and the ground truth (depth_gt.npy,
normals_gt.npy, albedo_gt.npy). Prints the command that reconstructs it.

Scenes: saddle; sphere (a sphere cap in a disc mask); cube (two faces of a turned cube);
bumps (random smooth bumps, see --seed).
"""

SYNTH_EPILOG = """\
examples:
  nplps synth sphere --out scene
  nplps synth bumps --size 256 --noise 0.01 --seed 3 --out bumps
  nplps synth bumps --camera pinhole --led --rgb --directional --out real-like
"""

DEMO_DESCRIPTION = """\
Synthesize a scene, reconstruct it with the near-light method (nplps) and with conventional
parallel-light photometric stereo, and compare both against the ground truth: angular error
of the normals and RMS depth error (in % of the object size). Writes the scene and both
reconstructions into --out (scene/, near/, baseline/).
"""

DEMO_EPILOG = """\
examples:
  nplps demo
  nplps demo --scene bumps --size 256 --noise 0.005 --out demo-bumps
"""


# --------------------------------------------------------------------------------------------------
# Parser
# --------------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``nplps`` command."""
    formatter = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(
        prog=PROG, description=MAIN_DESCRIPTION, epilog=MAIN_EPILOG, formatter_class=formatter
    )
    parser.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", title="commands")

    p = sub.add_parser(
        "reconstruct",
        help="reconstruct a mesh, normals and albedo from images and a rig file",
        description=RECONSTRUCT_DESCRIPTION,
        epilog=RECONSTRUCT_EPILOG,
        formatter_class=formatter,
    )
    add_input_options(p)
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (created if needed)")
    p.add_argument(
        "--opengl",
        action="store_true",
        help="write meshes in the OpenGL frame (x right, y up, z towards the viewer)",
    )
    p.add_argument(
        "--baseline",
        action="store_true",
        help="also run parallel-light photometric stereo and write it to DIR/baseline",
    )
    p.set_defaults(func=cmd_reconstruct)

    p = sub.add_parser(
        "evaluate",
        help="held-out-light errors of the near-light method and of the parallel-light baseline",
        description=EVALUATE_DESCRIPTION,
        epilog=EVALUATE_EPILOG,
        formatter_class=formatter,
    )
    add_input_options(p)
    p.add_argument(
        "--lights", metavar="I,J,...", help="the lights to leave out, 0-based, e.g. 0,3,5 (default: all)"
    )
    p.set_defaults(func=cmd_evaluate)

    _add_synth_parser(sub, formatter)
    _add_demo_parser(sub, formatter)
    return parser


def add_input_options(p: argparse.ArgumentParser) -> None:
    """The options ``reconstruct`` and ``evaluate`` share: input, thresholds, pre-processing,
    solver (read back by :func:`build_inputs` and :func:`near_options`)."""
    p.add_argument(
        "images",
        nargs="*",
        metavar="IMAGES",
        help="one image file per light, in the rig's light order; or one directory (all its image "
        "files sorted by name, except those with 'mask' or 'ambient' in the name); with --capture: "
        "the capture folder [and, for near_ps, a glob pattern of its image files]",
    )
    p.add_argument("--rig", metavar="RIG.json", help="rig file: camera and lights (required unless --capture)")
    p.add_argument(
        "--capture",
        choices=CAPTURE_LAYOUTS,
        help="read IMAGES as one capture folder in this layout instead of image files + --rig",
    )
    p.add_argument(
        "--depth",
        required=True,
        metavar="D",
        help="working distance (the object's mean depth, in the rig's unit), a .npy file "
        "with an (H+1, W+1) initial vertex depth map (NaN allowed outside the mask), or 'auto' to "
        "estimate it from the images (needs 4+ lights, some of them point lights)",
    )
    p.add_argument(
        "--depth-range",
        metavar="NEAR,FAR",
        help="with --depth auto: where to search (default: derived from the light positions)",
    )
    p.add_argument(
        "--depth-prior",
        metavar="PRIOR.npy",
        help="(H+1, W+1) prior depth map (e.g. from a coarse scan; NaN where unknown) fused in the global step",
    )
    p.add_argument(
        "--prior-weight",
        type=float,
        default=1.0,
        metavar="W",
        help="weight of --depth-prior relative to the facet terms (default 1)",
    )
    p.add_argument(
        "--mask",
        metavar="M",
        help="mask image, non-zero = reconstruct (default: every pixel, or the capture's mask)",
    )

    g = p.add_argument_group("shadows, saturation, colour")
    g.add_argument(
        "--dark",
        type=float,
        metavar="X",
        help="values (0..1 scale, after pre-processing) at or below X count as shadowed and are "
        "left out (default: one level above black for integer images, 0 after pre-processing)",
    )
    g.add_argument(
        "--saturation",
        type=float,
        metavar="X",
        help="raw values (0..1 scale, before pre-processing; any channel) at or above X count as "
        "saturated and are left out (default: the top level of integer images, none for float)",
    )
    g.add_argument(
        "--robust",
        choices=("cauchy", "tukey"),
        help="reweight each pixel's fit so that highlights and cast shadows do not bend the normals",
    )
    g.add_argument("--gray", "--grey", action="store_true", help="average RGB images to grey (default: keep colour)")

    g = p.add_argument_group("pre-processing (applied in this order)")
    g.add_argument("--srgb", action="store_true", help="decode sRGB to linear (camera JPEGs); also --ambient/--flat")
    g.add_argument("--ambient", metavar="FILE", help="subtract this image taken with every light off (clip at 0)")
    g.add_argument("--exposures", metavar="E1,E2,...", help="divide image i by Ei (exposure times, gains)")
    v = g.add_mutually_exclusive_group()
    v.add_argument(
        "--vignetting",
        choices=("cos4", "none"),
        help="cos4: divide by the cos^4 fall-off map of the pinhole K (default: none; cos4 for "
        "--capture near_ps)",
    )
    v.add_argument("--flat", metavar="FILE", help="divide by this flat-field image, normalized to maximum 1")
    g.add_argument(
        "--bin",
        type=int,
        default=1,
        metavar="N",
        help="average N x N pixel blocks (mask: whole blocks only; K or the pixel size adjusted)",
    )

    g = p.add_argument_group("solver")
    g.add_argument("--iterations", type=int, default=10, metavar="N", help="maximum iterations (default 10)")
    g.add_argument(
        "--tol",
        type=float,
        default=1e-6,
        help="stop when the largest depth change is at most tol x the image footprint (default 1e-6)",
    )
    g.add_argument(
        "--weighting",
        choices=("image", "paper"),
        default="image",
        help="local fit: least squares in image units (image, default) or the paper's Eq. 6 (paper)",
    )
    g.add_argument("--threads", type=int, metavar="N", help="worker threads (default: all cores)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")


def _add_synth_parser(sub: Any, formatter: Any) -> None:
    from .synth import SCENES

    p = sub.add_parser(
        "synth",
        help="write a synthetic scene with ground truth",
        description=SYNTH_DESCRIPTION,
        epilog=SYNTH_EPILOG,
        formatter_class=formatter,
    )
    p.add_argument("scene", choices=SCENES, metavar="SCENE", help=f"one of {', '.join(SCENES)}")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (created if needed)")
    p.add_argument("--size", type=int, default=128, metavar="N", help="image size N x N pixels (default 128)")
    p.add_argument(
        "--noise",
        type=float,
        default=0.0,
        help="Gaussian image noise, standard deviation as a fraction of the brightest value (default 0)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the noise and of the bumps scene (default 0)")
    p.add_argument("--distance", type=float, default=200.0, help="working distance (default 200)")
    p.add_argument(
        "--object-size", type=float, default=100.0, metavar="S", help="lateral object size (default 100)"
    )
    p.add_argument(
        "--camera",
        choices=("orthographic", "pinhole"),
        default="orthographic",
        help="orthographic (default) or a pinhole camera at the origin viewing the object",
    )
    p.add_argument("--led", action="store_true", help="anisotropic LEDs aimed at the object, unequal RGB intensities")
    p.add_argument("--rgb", action="store_true", help="colour albedo and RGB images")
    p.add_argument("--directional", action="store_true", help="every third light is a distant (directional) light")
    p.set_defaults(func=cmd_synth)


def _add_demo_parser(sub: Any, formatter: Any) -> None:
    from .synth import SCENES

    p = sub.add_parser(
        "demo",
        help="synthetic comparison of nplps against parallel-light photometric stereo",
        description=DEMO_DESCRIPTION,
        epilog=DEMO_EPILOG,
        formatter_class=formatter,
    )
    p.add_argument("--scene", choices=SCENES, default="sphere", help="synthetic scene (default sphere)")
    p.add_argument("--size", type=int, default=128, metavar="N", help="image size N x N pixels (default 128)")
    p.add_argument("--noise", type=float, default=0.0, help="image noise as a fraction of the brightest value (default 0)")
    p.add_argument("--seed", type=int, default=0, help="seed of the noise and of the bumps scene (default 0)")
    p.add_argument("--out", default="nplps-demo", metavar="DIR", help="output directory (default nplps-demo)")
    p.set_defaults(func=cmd_demo)


# --------------------------------------------------------------------------------------------------
# Entry point
# --------------------------------------------------------------------------------------------------


def main(argv: Sequence[str] | None = None) -> int:
    """Runs the ``nplps`` command with ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
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
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr, flush=True)
        return 130


def _exit_code(code: Any) -> int:
    if code is None:
        return 0
    if isinstance(code, int):
        return code
    print(code, file=sys.stderr)
    return 1


def _error(message: str) -> None:
    message = " ".join(str(message).split()) or "unknown error"
    print(f"{PROG}: error: {message}", file=sys.stderr, flush=True)


def _os_message(e: OSError) -> str:
    what = e.strerror or str(e)
    if e.filename is not None:
        return f"'{os.fspath(e.filename)}': {what}"
    return what


def _note(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------------------------------
# Input: images, rig, mask, pre-processing (shared by reconstruct and evaluate)
# --------------------------------------------------------------------------------------------------


class Inputs(NamedTuple):
    """What :func:`build_inputs` makes of the input options."""

    #: Pre-processed float32 images (k, H, W) or (k, H, W, 3).
    images: np.ndarray
    #: The rig (camera adjusted to --bin).
    rig: Any
    #: (H, W) bool mask, or None for every pixel.
    mask: np.ndarray | None
    #: (k, H, W) bool, False where an observation is saturated; None if none is.
    valid: np.ndarray | None
    #: Keyword arguments for reconstruct, reconstruct_parallel and held_out: depth, dark, robust, threads.
    options: dict[str, Any]


class _Loaded(NamedTuple):
    """Images, rig and mask as read, before binning."""

    images: np.ndarray
    rig: Any
    mask: np.ndarray | None
    valid: np.ndarray | None
    levels: int | None
    steps: list[str]


def build_inputs(args: argparse.Namespace) -> Inputs:
    """Reads and pre-processes the input that :func:`add_input_options` describes."""
    check_input_args(args)
    depth = parse_depth(args.depth)
    loaded = _load_capture(args) if args.capture else _load_files(args)
    images, rig, mask, valid = loaded.images, loaded.rig, loaded.mask, loaded.valid
    steps = list(loaded.steps)
    if args.bin > 1:
        images, rig, mask, valid = bin_inputs(images, rig, mask, valid, args.bin)
        steps.append(f"binned {args.bin} x {args.bin} to {images.shape[2]} x {images.shape[1]} pixels")
    dark = args.dark
    if dark is None:
        dark = 1.0 / loaded.levels if loaded.levels and not steps else 0.0
    if not args.quiet:
        _note_inputs(images, rig, valid, steps, dark, loaded.levels)
    options = {"depth": depth, "dark": dark, "robust": args.robust, "threads": args.threads}
    return Inputs(np.ascontiguousarray(images, dtype=np.float32), rig, mask, valid, options)


def near_options(args: argparse.Namespace) -> dict[str, Any]:
    """The options of the near-light solver only (not of the parallel-light baseline)."""
    options: dict[str, Any] = {"iterations": args.iterations, "tol": args.tol, "weighting": args.weighting}
    if args.depth_range is not None:
        near_far = _parse_list(args.depth_range, float, "--depth-range", "NEAR,FAR, e.g. 150,400")
        if len(near_far) != 2:
            raise InputError(f"--depth-range needs two numbers NEAR,FAR, got {args.depth_range}")
        options["depth_range"] = tuple(near_far)
    if args.depth_prior is not None:
        options["depth_prior"] = parse_depth(args.depth_prior)
        options["prior_weight"] = args.prior_weight
    return options


def _estimated(result: Any, options: dict[str, Any]) -> dict[str, Any]:
    """The options with ``depth="auto"`` replaced by the depth map that ``result`` estimated."""
    if not isinstance(options.get("depth"), str):
        return options
    return dict(options, depth=result.depth)


def check_input_args(args: argparse.Namespace) -> None:
    """Checks the input options before anything is read: numbers, which options go together,
    and that the named side files exist."""
    _check_numbers(args)
    if args.capture:
        given = [f"--{name}" for name in ("rig", "ambient", "exposures") if getattr(args, name)]
        given += ["--srgb"] if args.srgb else []
        if given:
            raise InputError(
                f"--capture {args.capture} takes the rig and the ambient image from the folder: "
                f"{', '.join(given)} cannot be combined with it"
            )
    elif not args.images:
        raise InputError("no input: give IMAGES (image files or one directory) and --rig, or --capture LAYOUT FOLDER")
    elif args.rig is None:
        raise InputError("--rig is required with IMAGES (or read a capture folder with --capture LAYOUT FOLDER)")
    for option in ("mask", "ambient", "flat"):
        path = getattr(args, option)
        if path is not None and not os.path.isfile(path):
            raise InputError(f"--{option} file '{path}' not found")


def _check_numbers(args: argparse.Namespace) -> None:
    if args.iterations < 1:
        raise InputError(f"--iterations must be at least 1, got {args.iterations}")
    if args.threads is not None and args.threads < 1:
        raise InputError(f"--threads must be at least 1, got {args.threads}")
    if not np.isfinite(args.tol) or args.tol < 0:
        raise InputError(f"--tol must be a non-negative number, got {args.tol}")
    if args.bin < 1:
        raise InputError(f"--bin must be a positive integer (the block size in pixels), got {args.bin}")
    if args.dark is not None and not np.isfinite(args.dark):
        raise InputError(f"--dark must be a finite number, got {args.dark}")
    if args.saturation is not None and not (np.isfinite(args.saturation) and args.saturation > 0):
        raise InputError(f"--saturation must be a positive number (0..1 scale), got {args.saturation}")


def _load_files(args: argparse.Namespace) -> _Loaded:
    """IMAGES + --rig: read the images, the mask and the rig; sRGB, ambient, exposures, vignetting."""
    rig = load_rig(args.rig)
    exclude = [f for f in (args.ambient, args.flat) if f]
    files = resolve_images(args.images, args.mask, quiet=args.quiet, exclude=exclude, ambient=args.ambient)
    if len(files) != rig.n_lights:
        source = f"found in '{args.images[0]}'" if _is_dir_input(args.images) else "given"
        raise InputError(
            f"{len(files)} images {source} but the rig file '{args.rig}' has {rig.n_lights} lights: "
            "there must be exactly one image per light, in the rig's light order"
        )
    raw, levels = load_raw(files)
    mask = None if args.mask is None else _mask(args.mask, raw.shape[1:3])
    images = _to_gray(raw) if args.gray else raw
    images, steps = preprocess_images(images, args, rig.K)
    return _Loaded(images, rig, mask, saturation_valid(raw, levels, args.saturation), levels, steps)


def _load_capture(args: argparse.Namespace) -> _Loaded:
    """--capture LAYOUT FOLDER [PATTERN]: the capture's images, mask, ambient image and rig."""
    from . import captures

    capture = _read_capture(args)
    raw, levels = load_raw(capture.files)
    mask = capture.mask if args.mask is None else _mask(args.mask, raw.shape[1:3])
    images = _to_gray(raw) if args.gray else raw
    vmap, vstep = vignetting_map(args, capture.K, images, default="cos4" if capture.K is not None else "none")
    capture = dataclasses.replace(capture, images=images, mask=mask)
    prepared = captures.prepare(capture, bin_factor=1, ambient=True, vignetting=vmap, gray=args.gray)
    steps = ([f"ambient '{Path(capture.ambient).name}' subtracted"] if capture.ambient is not None else [])
    steps += [vstep] if vstep else []
    valid = saturation_valid(raw, levels, args.saturation)
    return _Loaded(prepared.images, prepared.rig(), prepared.mask, valid, levels, steps)


def _read_capture(args: argparse.Namespace) -> Any:
    from . import captures

    items = args.images
    if not 1 <= len(items) <= (2 if args.capture == "near_ps" else 1) or not os.path.isdir(items[0]):
        what = "the object folder"
        if args.capture == "near_ps":
            what = "the capture folder and optionally a glob pattern of its images"
        raise InputError(f"--capture {args.capture} takes {what}, got {' '.join(items) or 'nothing'}")
    if args.capture == "diligent":
        capture = captures.load_diligent(items[0], normals=False)
    else:
        try:
            capture = captures.load_near_ps(items[0], items[1] if len(items) > 1 else None)
        except InputError as e:
            if "lights selected" not in str(e):
                raise
            head = str(e).split(": pass images=")[0]
            hint = "give a glob pattern of the image files after the folder, e.g. 'img_[0-9]*.png'"
            raise InputError(f"{head}: {hint}") from None
    if not args.quiet:
        _note(f"capture '{capture.name}' ({args.capture}): {capture.num_images} images")
    return capture


def load_raw(files: Sequence[Any]) -> tuple[np.ndarray, int | None]:
    """The images as float32 (k, H, W[, 3]) on the 0..1 scale, colour kept, and their levels."""
    from .io import load_stack

    return load_stack([os.fspath(f) for f in files], color=True)


def _to_gray(images: np.ndarray) -> np.ndarray:
    return images.mean(axis=3, dtype=np.float32) if images.ndim == 4 else images


def _mask(path: str, shape: tuple[int, int]) -> np.ndarray:
    from .io import load_mask

    return load_mask(path, shape)


def saturation_valid(raw: np.ndarray, levels: int | None, saturation: float | None) -> np.ndarray | None:
    """(k, H, W) flags, False where a raw value (any channel) is at or above the saturation level
    (--saturation, or the top level of integer images); None when nothing is saturated."""
    if saturation is None:
        if levels is None:
            return None
        saturation = 1.0 - 0.5 / levels
    bad = raw >= saturation
    if bad.ndim == 4:
        bad = bad.any(axis=3)
    return ~bad if bad.any() else None


def preprocess_images(images: np.ndarray, args: argparse.Namespace, K: np.ndarray | None) -> tuple[np.ndarray, list[str]]:
    """--srgb, --ambient, --exposures, --vignetting / --flat, in this order; returns the images
    and the list of the steps done."""
    from . import preprocess

    steps = []
    if args.srgb:
        images = preprocess.srgb_to_linear(images)
        steps.append("sRGB decoded")
    if args.ambient:
        ambient = _side_image(args.ambient, "--ambient", images, args.srgb)
        images = preprocess.subtract_ambient(images, ambient[..., None] if images.ndim > ambient.ndim + 1 else ambient)
        steps.append(f"ambient '{args.ambient}' subtracted")
    if args.exposures:
        images = preprocess.scale_exposure(images, parse_exposures(args.exposures, images.shape[0]))
        steps.append("divided by the exposures")
    vmap, vstep = vignetting_map(args, K, images, default="none")
    if vmap is not None:
        images = preprocess.compensate_vignetting(images, vmap)
        steps.append(vstep)
    return images, steps


def vignetting_map(
    args: argparse.Namespace, K: np.ndarray | None, images: np.ndarray, default: str
) -> tuple[np.ndarray | None, str]:
    """The map to divide by (--flat, or cos^4 from K), or None; and what it is."""
    from . import preprocess

    if args.flat:
        flat = preprocess.flat_field_map(_side_image(args.flat, "--flat", images, args.srgb))
        return flat, f"divided by the flat field '{args.flat}'"
    if (args.vignetting or default) != "cos4":
        return None, ""
    if K is None:
        raise InputError(
            "--vignetting cos4 needs a pinhole camera (K), but the rig's camera is orthographic: "
            "use --flat FILE or --vignetting none"
        )
    return preprocess.vignetting_cos4(images.shape[1:3], K), "divided by the cos^4 vignetting map"


def _side_image(path: str, option: str, images: np.ndarray, srgb: bool) -> np.ndarray:
    """An --ambient or --flat image on the 0..1 scale (sRGB decoded with --srgb), grey for grey images."""
    from . import preprocess
    from .io import read_image, to_float

    image = to_float(read_image(path))
    if srgb:
        image = preprocess.srgb_to_linear(image)
    if image.shape[:2] != images.shape[1:3]:
        raise InputError(
            f"{option} '{path}' is {image.shape[1]} x {image.shape[0]} pixels but the images are "
            f"{images.shape[2]} x {images.shape[1]}"
        )
    return _to_gray(image[None])[0] if images.ndim == 3 else image


def parse_exposures(text: str, k: int) -> np.ndarray:
    """--exposures E1,E2,...: k positive numbers."""
    values = _parse_list(text, float, "--exposures", "comma-separated numbers, e.g. 1,0.5,2")
    if len(values) != k:
        raise InputError(f"--exposures has {len(values)} values but there are {k} images: give one per image")
    e = np.array(values)
    if not np.all(np.isfinite(e)) or np.any(e <= 0):
        raise InputError(f"--exposures must be positive numbers, got {text}")
    return e


def _parse_list(text: str, kind: Any, option: str, expected: str) -> list[Any]:
    try:
        return [kind(part) for part in text.split(",")]
    except ValueError:
        raise InputError(f"{option} must be {expected}, got '{text}'") from None


def bin_inputs(
    images: np.ndarray, rig: Any, mask: np.ndarray | None, valid: np.ndarray | None, n: int
) -> tuple[np.ndarray, Any, np.ndarray | None, np.ndarray | None]:
    """--bin N: images averaged over N x N blocks; mask and valid flags kept where the whole block
    is; the rig's K (pinhole) or pixel size (orthographic) adjusted."""
    from . import preprocess

    h, w = images.shape[1:3]
    if n > min(h, w):
        raise InputError(f"--bin {n}: the images ({w} x {h} pixels) are smaller than one {n} x {n} block")
    images = preprocess.bin_images(images, n)
    mask = None if mask is None else preprocess.bin_mask(mask, n)
    if mask is not None and not mask.any():
        raise InputError(f"--bin {n}: no {n} x {n} block lies wholly inside the mask")
    valid = None if valid is None else np.stack([preprocess.bin_mask(v, n) for v in valid])
    return images, bin_rig(rig, n), mask, valid


def bin_rig(rig: Any, n: int) -> Any:
    """The rig of images binned by n: K by :func:`nplps.preprocess.bin_intrinsics` (pinhole), or
    the pixel size times n with the origin kept at the top-left corner (orthographic)."""
    from . import preprocess

    camera = dict(rig.camera)
    if rig.is_pinhole:
        camera["K"] = preprocess.bin_intrinsics(rig.K, n).tolist()
    else:
        camera["pixel_size"] = [float(v) * n for v in camera["pixel_size"]]
    return dataclasses.replace(rig, camera=camera)


def describe_rig(rig: Any) -> str:
    """'pinhole camera, 18 point lights, 9 directional lights' and the like."""
    far = int(np.count_nonzero(rig.directional))
    near = rig.n_lights - far
    counts = ((near, "point"), (far, "directional"))
    lights = [f"{count} {kind} light{'s' if count != 1 else ''}" for count, kind in counts if count]
    return f"{rig.camera.get('model', '?')} camera, {', '.join(lights) or 'no lights'}"


def _note_inputs(
    images: np.ndarray, rig: Any, valid: np.ndarray | None, steps: list[str], dark: float, levels: int | None
) -> None:
    k, h, w = images.shape[:3]
    depth = f", {levels.bit_length()}-bit" if levels else ""
    colour = "RGB" if images.ndim == 4 else "grey"
    _note(f"{k} images of {w} x {h} pixels ({colour}{depth}); rig: {describe_rig(rig)}")
    if steps:
        _note(f"pre-processing: {', '.join(steps)}")
    saturated = 0 if valid is None else int(np.count_nonzero(~valid))
    _note(f"left out: observations at or below {dark:.4g} (shadow), {saturated} saturated")


def _is_dir_input(items: Sequence[str]) -> bool:
    return len(items) == 1 and os.path.isdir(items[0])


def load_rig(path: str) -> Any:
    """Reads the rig file; every failure becomes a :class:`~nplps.RigError` naming the file."""
    from .errors import RigError
    from .rig import Rig

    if os.path.isdir(path):
        raise RigError(f"rig file '{path}' is a directory")
    return Rig.load(path)


def resolve_images(
    items: Sequence[str],
    mask: str | None = None,
    quiet: bool = False,
    exclude: Sequence[str] = (),
    ambient: str | None = None,
) -> list[str]:
    """The image files named by the IMAGES arguments: the files themselves, or the image files of
    a single directory sorted by name (numbers in names compare by value; names containing
    ``mask`` or ``ambient`` and the files ``exclude`` are skipped). Announces on stderr which
    files a directory gave."""
    if not _is_dir_input(items):
        return _check_files(items)
    folder = items[0]
    skip = {os.path.realpath(f) for f in exclude}
    names = sorted(
        (
            n
            for n in os.listdir(folder)
            if _is_image_name(n)
            and not any(word in n.lower() for word in SKIPPED_WORDS)
            and os.path.isfile(os.path.join(folder, n))
            and os.path.realpath(os.path.join(folder, n)) not in skip
        ),
        key=_natural_key,
    )
    if not names:
        raise InputError(
            f"no image files in directory '{folder}' (looked for {', '.join(IMAGE_SUFFIXES)}; "
            "names containing 'mask' or 'ambient' are skipped)"
        )
    if not quiet:
        _note_directory(folder, names, mask, ambient)
    return [os.path.join(folder, n) for n in names]


def _is_image_name(name: str) -> bool:
    return name.lower().endswith(IMAGE_SUFFIXES) and not name.startswith(".")


def _check_files(items: Sequence[str]) -> list[str]:
    dirs = [i for i in items if os.path.isdir(i)]
    if dirs:
        raise InputError(f"'{dirs[0]}' is a directory: give either one directory or a list of image files, not both")
    missing = [i for i in items if not os.path.exists(i)]
    if missing:
        more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
        raise InputError(f"image file '{missing[0]}' not found{more}")
    return list(items)


def _note_directory(folder: str, names: list[str], mask: str | None, ambient: str | None) -> None:
    listing = textwrap.fill(", ".join(names), width=95, initial_indent="  ", subsequent_indent="  ", break_on_hyphens=False)
    _note(f"using {len(names)} images from '{folder}' in this order (light 0 first):\n{listing}")
    for word, given, option in (("mask", mask, "--mask"), ("ambient", ambient, "--ambient")):
        skipped = sorted(n for n in os.listdir(folder) if word in n.lower() and _is_image_name(n))
        if given is None and skipped:
            _note(f"note: {', '.join(skipped)} in '{folder}' was skipped; pass {option} to use it")


def _natural_key(name: str) -> list[Any]:
    return [(0, int(part), part) if part.isdigit() else (1, 0, part.lower()) for part in re.split(r"(\d+)", name) if part]


def parse_depth(value: str) -> float | np.ndarray:
    """``--depth``: a positive number, 'auto', or the path of a .npy depth map."""
    if value == "auto":
        return value  # type: ignore[return-value]
    try:
        number = float(value)
    except ValueError:
        number = None
    if number is not None:
        if not np.isfinite(number) or number <= 0:
            raise InputError(
                f"--depth must be a positive working distance (in the rig's unit) or a .npy depth map, got {value}"
            )
        return number
    if not os.path.exists(value):
        raise InputError(
            f"--depth '{value}' is neither a number (the working distance) nor an existing .npy depth map file"
        )
    if not value.lower().endswith(".npy"):
        raise InputError(f"--depth '{value}' is not a .npy file: give the working distance or an (H+1, W+1) .npy depth map")
    try:
        depth = np.load(value, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise InputError(f"--depth: cannot read '{value}' as a .npy array: {e}") from None
    if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.number):
        raise InputError(
            f"--depth: '{value}' holds a {depth.dtype} array of shape {depth.shape}; "
            "it must be an (H+1, W+1) map of vertex depths"
        )
    return depth.astype(np.float64)


class _warnings_to_stderr:
    """Shows library warnings as ``nplps: warning: ...`` lines instead of Python's format."""

    def __enter__(self) -> None:
        self._ctx = warnings.catch_warnings(record=True)
        self._caught = self._ctx.__enter__()
        warnings.simplefilter("always")

    def __exit__(self, *exc: Any) -> None:
        caught = list(self._caught)
        self._ctx.__exit__(*exc)
        for w in caught:
            _note(f"{PROG}: warning: {w.message}")


# --------------------------------------------------------------------------------------------------
# reconstruct
# --------------------------------------------------------------------------------------------------


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from .api import reconstruct, reconstruct_parallel

    inputs = build_inputs(args)
    common = dict(inputs.options, valid=inputs.valid)
    start = time.perf_counter()
    with _warnings_to_stderr():
        result = reconstruct(inputs.images, inputs.rig, inputs.mask, progress=not args.quiet, **near_options(args), **common)
    wall = time.perf_counter() - start
    paths = result.save(args.out, opengl=args.opengl)
    _print_summary("near-light reconstruction (nplps)", result, wall, paths, args.iterations)

    if args.baseline:
        start = time.perf_counter()
        with _warnings_to_stderr():
            base = reconstruct_parallel(inputs.images, inputs.rig, inputs.mask, **_estimated(result, common))
        wall = time.perf_counter() - start
        base_paths = base.save(Path(args.out) / "baseline", opengl=args.opengl)
        print()
        _print_summary("parallel-light baseline", base, wall, base_paths, None)
    return 0


def _print_summary(title: str, result: Any, wall: float, paths: dict[str, Path], max_iterations: int | None) -> None:
    s = result.summary()
    h, w = s["shape"]
    print(f"{title}:")
    print(f"  rig             {describe_rig(result.rig)}")
    print(f"  pixels          {s['pixels']} of {h} x {w}")
    print(f"  regions         {s['regions']}")
    if max_iterations is not None:
        state = "yes" if s["converged"] else f"no (iteration limit {max_iterations} reached; try --iterations)"
        print(f"  iterations      {s['iterations']}")
        print(f"  converged       {state}")
    if s["rms_residual"] is not None:
        print(f"  rms residual    {s['rms_residual']:.3e} (image units, 0..1)")
    print(f"  unfitted pixels {s['unfitted_pixels']} (fewer than 3 lit images)")
    lo, hi = s["depth_range"]
    print(f"  depth range     {lo:.6g} .. {hi:.6g}")
    if s.get("estimated_distance"):
        estimates = ", ".join(f"{d:.6g}" for d in s["estimated_distance"])
        print(f"  distance        {estimates} (estimated; residual curve in distance_curve.csv / .svg)")
    print(f"  time            {wall:.2f} s (solver {s['timings'].get('total', float('nan')):.2f} s)")
    files = sorted({str(p.parent) for p in paths.values()})
    print(f"  files written   in {', '.join(files)}: {', '.join(p.name for p in paths.values())}")


# --------------------------------------------------------------------------------------------------
# evaluate
# --------------------------------------------------------------------------------------------------

EVALUATE_COLUMNS = ("light", "near rel. error", "near shape error", "parallel rel. error", "parallel shape error")


def cmd_evaluate(args: argparse.Namespace) -> int:
    from .evaluation import held_out

    inputs = build_inputs(args)
    lights = parse_lights(args.lights, inputs.rig.n_lights)
    if inputs.options["depth"] == "auto":
        from .api import reconstruct

        with _warnings_to_stderr():
            estimate = reconstruct(inputs.images, inputs.rig, inputs.mask, valid=inputs.valid, **inputs.options, **near_options(args))
        distances = ", ".join(f"{d:.6g}" for d in estimate.distance.distance)
        _note(f"estimated working distance (all lights): {distances}")
        inputs = inputs._replace(options=_estimated(estimate, inputs.options))
    rows = []
    for done, light in enumerate(lights):
        start = time.perf_counter()
        row = [light]
        for method in ("near", "parallel"):
            with _warnings_to_stderr():
                (h,) = held_out(
                    inputs.images, inputs.rig, inputs.mask, method=method, lights=[light],
                    valid=inputs.valid, **inputs.options, **near_options(args),
                )
            row += [h.relative_error, h.shape_error]
        rows.append(row)
        if not args.quiet:
            _note(f"light {light} left out ({done + 1}/{len(lights)}): {time.perf_counter() - start:.2f} s")
    _print_evaluation(rows, inputs.rig.n_lights)
    return 0


def parse_lights(text: str | None, k: int) -> list[int]:
    """--lights I,J,...: 0-based light indices (default: all k)."""
    if text is None:
        return list(range(k))
    lights = _parse_list(text, int, "--lights", "comma-separated light indices, e.g. 0,3,5")
    bad = [i for i in lights if not 0 <= i < k]
    if bad:
        raise InputError(f"--lights: {bad[0]} is not a light of the rig (0 .. {k - 1})")
    return lights


def _print_evaluation(rows: list[list[Any]], k: int) -> None:
    print(f"held-out lights: each reconstructed from the other {k - 1} lights and predicted")
    print("relative error = |prediction - image| / |image|; shape error: the same after the best gain\n")
    widths = [5] + [len(c) + 2 for c in EVALUATE_COLUMNS[1:]]
    print("".join(f"{c:>{w}}" for c, w in zip(EVALUATE_COLUMNS, widths)))
    for row in rows:
        print(f"{row[0]:>{widths[0]}}" + "".join(f"{v:>{w}.4g}" for v, w in zip(row[1:], widths[1:])))
    means = np.nanmean(np.array([r[1:] for r in rows], dtype=float), axis=0)
    print(f"{'mean':>{widths[0]}}" + "".join(f"{v:>{w}.4g}" for v, w in zip(means, widths[1:])))


# --------------------------------------------------------------------------------------------------
# synth
# --------------------------------------------------------------------------------------------------


def _check_scene_args(args: argparse.Namespace) -> None:
    if args.size < 2:
        raise InputError(f"--size must be at least 2 pixels, got {args.size}")
    if not np.isfinite(args.noise) or args.noise < 0:
        raise InputError(f"--noise must be a non-negative fraction, got {args.noise}")


def cmd_synth(args: argparse.Namespace) -> int:
    from .synth import make_scene

    _check_scene_args(args)
    scene = make_scene(
        args.scene, args.size, args.object_size, args.distance, args.seed, args.noise,
        camera=args.camera, led=args.led, rgb=args.rgb, directional=args.directional,
    )
    paths = scene.save(args.out)
    out = Path(args.out)
    kind = ("RGB" if args.rgb else "grey") + (", LEDs" if args.led else "")
    print(
        f"wrote the {args.scene} scene ({args.size} x {args.size} pixels, {kind}; {describe_rig(scene.rig)}; "
        f"object size {scene.size:g}, noise {args.noise:g}) to {out}:"
    )
    n_images = sum(1 for k in paths if k.startswith("image_"))
    print(f"  image_00.png .. image_{n_images - 1:02d}.png, rig.json, mask.png, depth_gt.npy, normals_gt.npy, albedo_gt.npy")
    print(f"true mean depth {scene.mean_depth:.10g}; reconstruct with:")
    command = [
        PROG,
        "reconstruct",
        str(out),
        "--rig",
        str(out / "rig.json"),
        "--mask",
        str(out / "mask.png"),
        "--depth",
        f"{scene.mean_depth:.10g}",
        "--out",
        str(out / "reconstruction"),
    ]
    print("  " + " ".join(shlex.quote(c) for c in command))
    return 0


# --------------------------------------------------------------------------------------------------
# demo
# --------------------------------------------------------------------------------------------------


def normal_errors(normals: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Angular errors in degrees of the unit normals over the masked pixels (NaN where unfitted)."""
    dot = np.sum(normals[mask] * truth[mask], axis=-1)
    return np.degrees(np.arccos(np.clip(dot, -1.0, 1.0)))


def depth_rms(depth: np.ndarray, truth: np.ndarray) -> float:
    """RMS of the vertex depth differences over the vertices both maps define."""
    ok = np.isfinite(depth) & np.isfinite(truth)
    return float(np.sqrt(np.mean((depth[ok] - truth[ok]) ** 2))) if ok.any() else float("nan")


def cmd_demo(args: argparse.Namespace) -> int:
    from .api import reconstruct, reconstruct_parallel
    from .synth import make_scene

    _check_scene_args(args)
    out = Path(args.out)
    scene = make_scene(args.scene, args.size, seed=args.seed, noise=args.noise)
    scene.save(out / "scene")
    distance = scene.mean_depth
    print(
        f"scene: {args.scene}, {args.size} x {args.size} pixels, {scene.rig.n_lights} near point lights, "
        f"object size {scene.size:g} at mean depth {distance:.4g}, noise {args.noise:g}"
    )
    print(f"both methods start from a plane at the true mean depth {distance:.6g}\n")

    runs = []
    for label, run in (
        ("near light (nplps)", lambda: reconstruct(scene.images, scene.rig, scene.mask, depth=distance)),
        ("parallel light", lambda: reconstruct_parallel(scene.images, scene.rig, scene.mask, depth=distance)),
    ):
        start = time.perf_counter()
        with _warnings_to_stderr():
            result = run()
        wall = time.perf_counter() - start
        errors = normal_errors(result.normals, scene.normals, scene.mask)
        runs.append(
            {
                "label": label,
                "result": result,
                "mean": float(np.nanmean(errors)),
                "median": float(np.nanmedian(errors)),
                "depth": 100.0 * depth_rms(result.depth, scene.depth) / scene.size,
                "time": wall,
            }
        )
    near, base = runs
    near["result"].save(out / "near")
    base["result"].save(out / "baseline")

    rows = [
        ("mean normal error [deg]", "mean", "{:.4g}"),
        ("median normal error [deg]", "median", "{:.4g}"),
        ("RMS depth error [% of size]", "depth", "{:.4g}"),
        ("time [s]", "time", "{:.3f}"),
    ]
    print(f"{'':28}{near['label']:>20}{base['label']:>20}")
    for name, key, fmt in rows:
        print(f"{name:28}{fmt.format(near[key]):>20}{fmt.format(base[key]):>20}")
    its = near["result"].history
    print(f"{'iterations':28}{len(its):>20}{'1 (direct)':>20}")
    print()
    print(f"wrote the scene to {out / 'scene'}, the reconstructions to {out / 'near'} and {out / 'baseline'}")
    return 0
