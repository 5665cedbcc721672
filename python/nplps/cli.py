"""The ``nplps`` command line: reconstruct from image files, make synthetic scenes, run a demo.

Run ``nplps --help`` (or ``python -m nplps --help``) for the overview and ``nplps COMMAND --help``
for each command. :func:`main` is the entry point; it returns the exit status instead of exiting,
so it can be called from Python and from tests.
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import sys
import textwrap
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from . import __version__
from .errors import InputError, NplpsError

PROG = "nplps"

#: File name endings taken as images when IMAGES is a directory.
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".pnm", ".webp")

CONVENTIONS = (
    "Conventions: camera frame as in OpenCV (x right, y down, z forward into the scene, depth = z); "
    "the rig file gives the pixel footprint, the image origin and the light positions in one length "
    "unit (mm typical), and depths are in that unit too."
)

MAIN_DESCRIPTION = f"""\
nplps: photometric stereo with near point lighting (Xie, Dai & Wang, CVPR 2015).

From k photographs of a still object, each lit by one small light (LED) close to the object,
nplps recovers a metric 3-D mesh, per-pixel normals and albedo. The positions of the lights
relative to the camera come from a rig file (JSON, see below), and the object's approximate
distance from the camera (the working distance) must be given.

{textwrap.fill(CONVENTIONS, 95)}

Rig file (JSON, version 1):
  {{"version": 1,
   "camera": {{"model": "orthographic", "pixel_size": [w, h], "origin": [x0, y0]}},
   "lights": [{{"position": [x, y, z]}}, ...]}}
  pixel_size: footprint of one pixel on the object; origin: scene (x, y) of the top-left
  corner of pixel (0, 0); lights in the same order as the images.
"""

MAIN_EPILOG = """\
examples:
  nplps demo                                    # synthetic sphere: near-light vs parallel-light
  nplps synth sphere --out scene                # write a synthetic scene (images, rig, mask)
  nplps reconstruct scene --rig scene/rig.json --mask scene/mask.png --depth 180 --out result
  nplps reconstruct --help                      # all options of a command

exit status: 0 success, 2 invalid input or usage, 1 output could not be written,
130 interrupted.
"""

RECONSTRUCT_DESCRIPTION = f"""\
Reconstruct a surface from k images taken under the k near point lights of a rig.

Writes into --out: mesh.ply and mesh.obj (the masked surface, vertex normals, albedo as grey),
normals.png (normal map), albedo.png (16-bit), depth.npy / depth.tiff (vertex depths,
(H+1, W+1), NaN where no masked pixel), normals.npy, residual.npy and summary.json.

{textwrap.fill(CONVENTIONS, 95)}
"""

RECONSTRUCT_EPILOG = """\
examples:
  # all images of a folder (sorted by name; files with 'mask' in the name are skipped):
  nplps reconstruct shots/ --rig rig.json --mask shots/mask.png --depth 250 --out result
  # explicit files, in the rig's light order, initial depth map from a previous run:
  nplps reconstruct a.png b.png c.png d.png --rig rig.json --depth result/depth.npy --out refined
  # compare with conventional (parallel-light) photometric stereo, written to result/baseline:
  nplps reconstruct shots/ --rig rig.json --depth 250 --out result --baseline
"""

SYNTH_DESCRIPTION = """\
Write a synthetic scene: 16-bit images image_XX.png rendered by the solver's image model
under 27 near point lights, rig.json, mask.png, and the ground truth (depth_gt.npy,
normals_gt.npy, albedo_gt.npy). Prints the command that reconstructs it.

Scenes: saddle; sphere (a sphere cap in a disc mask); cube (two faces of a turned cube);
bumps (random smooth bumps, see --seed).
"""

SYNTH_EPILOG = """\
examples:
  nplps synth sphere --out scene
  nplps synth bumps --size 256 --noise 0.01 --seed 3 --out bumps
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
    from .synth import SCENES

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
    p.add_argument(
        "images",
        nargs="+",
        metavar="IMAGES",
        help="one image file per light, in the rig's light order; or one directory "
        "(all its image files sorted by name, except those with 'mask' in the name)",
    )
    p.add_argument("--rig", required=True, metavar="RIG.json", help="rig file: camera and light positions")
    p.add_argument(
        "--depth",
        required=True,
        metavar="D",
        help="working distance (the object's mean depth, in the rig's unit), or a .npy file "
        "with an (H+1, W+1) initial vertex depth map (NaN allowed outside the mask)",
    )
    p.add_argument("--mask", metavar="M", help="mask image, non-zero = reconstruct (default: every pixel)")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (created if needed)")
    p.add_argument("--iterations", type=int, default=10, metavar="N", help="maximum iterations (default 10)")
    p.add_argument(
        "--tol",
        type=float,
        default=1e-6,
        help="stop when the largest depth change is at most tol x the image footprint (default 1e-6)",
    )
    p.add_argument(
        "--dark",
        type=float,
        default=0.0,
        help="pixel values (0..1 scale) at or below this count as shadowed and are ignored (default 0)",
    )
    p.add_argument(
        "--weighting",
        choices=("image", "paper"),
        default="image",
        help="local fit: least squares in image units (image, default) or the paper's Eq. 6 (paper)",
    )
    p.add_argument("--threads", type=int, metavar="N", help="worker threads (default: all cores)")
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
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=cmd_reconstruct)

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
    p.set_defaults(func=cmd_synth)

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
    return parser


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
# reconstruct
# --------------------------------------------------------------------------------------------------


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from .api import reconstruct, reconstruct_parallel
    from .io import load_images

    if args.iterations < 1:
        raise InputError(f"--iterations must be at least 1, got {args.iterations}")
    if args.threads is not None and args.threads < 1:
        raise InputError(f"--threads must be at least 1, got {args.threads}")
    if not np.isfinite(args.tol) or args.tol < 0:
        raise InputError(f"--tol must be a non-negative number, got {args.tol}")
    rig = load_rig(args.rig)
    depth = parse_depth(args.depth)
    if args.mask is not None and not os.path.isfile(args.mask):
        raise InputError(f"mask file '{args.mask}' not found")
    files = resolve_images(args.images, args.mask, quiet=args.quiet)
    if len(files) != rig.n_lights:
        source = f"found in '{args.images[0]}'" if _is_dir_input(args.images) else "given"
        raise InputError(
            f"{len(files)} images {source} but the rig file '{args.rig}' has {rig.n_lights} lights: "
            "there must be exactly one image per light, in the rig's light order"
        )
    stack = load_images(files)
    if not args.quiet:
        _note(f"{stack.shape[0]} images of {stack.shape[2]} x {stack.shape[1]} pixels, {rig.n_lights} lights")

    progress = not args.quiet
    common = dict(mask=args.mask, depth=depth, dark=args.dark, threads=args.threads)
    start = time.perf_counter()
    with _warnings_to_stderr():
        result = reconstruct(
            stack, rig, iterations=args.iterations, tol=args.tol, weighting=args.weighting, progress=progress, **common
        )
    wall = time.perf_counter() - start
    paths = result.save(args.out, opengl=args.opengl)
    _print_summary("near-light reconstruction (nplps)", result, wall, paths, args.iterations)

    if args.baseline:
        start = time.perf_counter()
        with _warnings_to_stderr():
            base = reconstruct_parallel(stack, rig, **common)
        wall = time.perf_counter() - start
        base_paths = base.save(Path(args.out) / "baseline", opengl=args.opengl)
        print()
        _print_summary("parallel-light baseline", base, wall, base_paths, None)
    return 0


def load_rig(path: str) -> Any:
    """Reads the rig file; every failure becomes a :class:`~nplps.RigError` naming the file."""
    from .errors import RigError
    from .rig import Rig

    if os.path.isdir(path):
        raise RigError(f"rig file '{path}' is a directory")
    return Rig.load(path)


def resolve_images(items: Sequence[str], mask: str | None = None, quiet: bool = False) -> list[str]:
    """The image files named by the IMAGES arguments: the files themselves, or the image files of
    a single directory sorted by name (numbers in names compare by value; names containing
    ``mask`` are skipped). Announces on stderr which files a directory gave."""
    if not _is_dir_input(items):
        dirs = [i for i in items if os.path.isdir(i)]
        if dirs:
            raise InputError(
                f"'{dirs[0]}' is a directory: give either one directory or a list of image files, not both"
            )
        missing = [i for i in items if not os.path.exists(i)]
        if missing:
            more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
            raise InputError(f"image file '{missing[0]}' not found{more}")
        return list(items)

    folder = items[0]
    names = sorted(
        (
            n
            for n in os.listdir(folder)
            if n.lower().endswith(IMAGE_SUFFIXES)
            and not n.startswith(".")
            and "mask" not in n.lower()
            and os.path.isfile(os.path.join(folder, n))
        ),
        key=_natural_key,
    )
    if not names:
        raise InputError(
            f"no image files in directory '{folder}' (looked for {', '.join(IMAGE_SUFFIXES)}; "
            "names containing 'mask' are skipped)"
        )
    if not quiet:
        listing = textwrap.fill(
            ", ".join(names), width=95, initial_indent="  ", subsequent_indent="  ", break_on_hyphens=False
        )
        _note(f"using {len(names)} images from '{folder}' in this order (light 0 first):\n{listing}")
        skipped = sorted(n for n in os.listdir(folder) if "mask" in n.lower() and n.lower().endswith(IMAGE_SUFFIXES))
        if mask is None and skipped:
            _note(f"note: {', '.join(skipped)} in '{folder}' was not used as the mask; pass --mask to use it")
    return [os.path.join(folder, n) for n in names]


def _is_dir_input(items: Sequence[str]) -> bool:
    return len(items) == 1 and os.path.isdir(items[0])


def _natural_key(name: str) -> list[Any]:
    return [(0, int(part), part) if part.isdigit() else (1, 0, part.lower()) for part in re.split(r"(\d+)", name) if part]


def parse_depth(value: str) -> float | np.ndarray:
    """``--depth``: a positive number, or the path of a .npy depth map."""
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


def _print_summary(title: str, result: Any, wall: float, paths: dict[str, Path], max_iterations: int | None) -> None:
    s = result.summary()
    h, w = s["shape"]
    print(f"{title}:")
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
    print(f"  time            {wall:.2f} s (solver {s['timings'].get('total', float('nan')):.2f} s)")
    files = sorted({str(p.parent) for p in paths.values()})
    print(f"  files written   in {', '.join(files)}: {', '.join(p.name for p in paths.values())}")


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
    scene = make_scene(args.scene, args.size, args.object_size, args.distance, args.seed, args.noise)
    paths = scene.save(args.out)
    out = Path(args.out)
    print(
        f"wrote the {args.scene} scene ({args.size} x {args.size} pixels, {scene.rig.n_lights} lights, "
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
