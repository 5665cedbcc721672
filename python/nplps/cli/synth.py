"""The ``nplps synth`` and ``nplps demo`` commands.

``nplps synth`` (write a synthetic scene) and ``nplps demo`` (compare the near-light method with
parallel-light photometric stereo on a synthetic scene).
"""

from __future__ import annotations

import argparse
import shlex
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from .console import PROG, _warnings_to_stderr, describe_rig
from .outputs import add_output_options, output_directory, writing

SYNTH_DESCRIPTION = """\
Write a synthetic scene: 16-bit images image_XX.png (RGB with --rgb) rendered by the solver's
image model under 27 lights, rig.json, mask.png, and the ground truth (depth_gt.npy,
normals_gt.npy, albedo_gt.npy), and nplps-manifest.json (the files written). --out must be
empty unless --overwrite. Prints the command that reconstructs it.

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
reconstructions into --out (scene/, near/, baseline/); --out must be empty unless --overwrite.
"""

DEMO_EPILOG = """\
examples:
  nplps demo
  nplps demo --scene bumps --size 256 --noise 0.005 --out demo-bumps
"""


def add_synth_parser(sub: Any, formatter: Any) -> argparse.ArgumentParser:
    """Add the ``synth`` command and its options to the subparsers ``sub``; return its parser."""
    from ..synth import SCENES

    p = sub.add_parser(
        "synth",
        help="write a synthetic scene with ground truth",
        description=SYNTH_DESCRIPTION,
        epilog=SYNTH_EPILOG,
        formatter_class=formatter,
    )
    p.add_argument("scene", choices=SCENES, metavar="SCENE", help=f"one of {', '.join(SCENES)}")
    add_output_options(p)
    p.add_argument("--size", type=int, default=128, metavar="N", help="image size N x N pixels (default 128)")
    p.add_argument(
        "--noise",
        type=float,
        default=0.0,
        help="Gaussian image noise, standard deviation as a fraction of the brightest value (default 0)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the noise and of the bumps scene (default 0)")
    p.add_argument("--distance", type=float, default=200.0, help="working distance (default 200)")
    p.add_argument("--object-size", type=float, default=100.0, metavar="S", help="lateral object size (default 100)")
    p.add_argument(
        "--camera",
        choices=("orthographic", "pinhole"),
        default="orthographic",
        help="orthographic (default) or a pinhole camera at the origin viewing the object",
    )
    p.add_argument("--led", action="store_true", help="anisotropic LEDs aimed at the object, unequal RGB intensities")
    p.add_argument("--rgb", action="store_true", help="colour albedo and RGB images")
    p.add_argument("--directional", action="store_true", help="every third light is a distant (directional) light")
    return p


def add_demo_parser(sub: Any, formatter: Any) -> argparse.ArgumentParser:
    """Add the ``demo`` command and its options to the subparsers ``sub``; return its parser."""
    from ..synth import SCENES

    p = sub.add_parser(
        "demo",
        help="synthetic comparison of nplps against parallel-light photometric stereo",
        description=DEMO_DESCRIPTION,
        epilog=DEMO_EPILOG,
        formatter_class=formatter,
    )
    p.add_argument("--scene", choices=SCENES, default="sphere", help="synthetic scene (default sphere)")
    p.add_argument("--size", type=int, default=128, metavar="N", help="image size N x N pixels (default 128)")
    p.add_argument(
        "--noise", type=float, default=0.0, help="image noise as a fraction of the brightest value (default 0)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the noise and of the bumps scene (default 0)")
    add_output_options(p, default="nplps-demo")
    return p


def _check_scene_args(args: argparse.Namespace) -> None:
    if args.size < 2:
        raise InputError(f"--size must be at least 2 pixels, got {args.size}")
    if not np.isfinite(args.noise) or args.noise < 0:
        raise InputError(f"--noise must be a non-negative fraction, got {args.noise}")


def cmd_synth(args: argparse.Namespace) -> int:
    """Run ``nplps synth``; return the exit status."""
    from ..synth import make_scene

    _check_scene_args(args)
    directory = output_directory(args)
    scene = make_scene(
        args.scene,
        n=args.size,
        size=args.object_size,
        distance=args.distance,
        seed=args.seed,
        noise=args.noise,
        camera=args.camera,
        led=args.led,
        rgb=args.rgb,
        directional=args.directional,
    )
    with writing(directory):
        paths = scene.save(directory)
    out = Path(args.out)
    kind = ("RGB" if args.rgb else "grey") + (", LEDs" if args.led else "")
    print(
        f"wrote the {args.scene} scene ({args.size} x {args.size} pixels, {kind}; {describe_rig(scene.rig)}; "
        f"object size {scene.size:g}, noise {args.noise:g}) to {out}:"
    )
    n_images = sum(1 for k in paths if k.startswith("image_"))
    print(
        f"  image_00.png .. image_{n_images - 1:02d}.png, rig.json, mask.png, depth_gt.npy, normals_gt.npy, "
        "albedo_gt.npy"
    )
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


def normal_errors(normals: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Angular errors in degrees of the unit normals over the masked pixels (NaN where unfitted)."""
    dot = np.sum(normals[mask] * truth[mask], axis=-1)
    return np.degrees(np.arccos(np.clip(dot, -1.0, 1.0)))


def depth_rms(depth: np.ndarray, truth: np.ndarray) -> float:
    """RMS of the vertex depth differences over the vertices both maps define."""
    ok = np.isfinite(depth) & np.isfinite(truth)
    return float(np.sqrt(np.mean((depth[ok] - truth[ok]) ** 2))) if ok.any() else float("nan")


def cmd_demo(args: argparse.Namespace) -> int:
    """Run ``nplps demo``; return the exit status."""
    from ..api import reconstruct, reconstruct_parallel
    from ..synth import make_scene

    _check_scene_args(args)
    out = output_directory(args)
    scene = make_scene(args.scene, n=args.size, seed=args.seed, noise=args.noise)
    distance = scene.mean_depth
    print(
        f"scene: {args.scene}, {args.size} x {args.size} pixels, {scene.rig.n_lights} near point lights, "
        f"object size {scene.size:g} at mean depth {distance:.4g}, noise {args.noise:g}"
    )
    print(f"both methods start from a plane at the true mean depth {distance:.6g}\n")

    runs: list[dict[str, Any]] = []
    for label, run in (
        ("near light (nplps)", lambda: reconstruct(scene.images, scene.rig, mask=scene.mask, depth=distance)),
        ("parallel light", lambda: reconstruct_parallel(scene.images, scene.rig, mask=scene.mask, depth=distance)),
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
    with writing(out):
        scene.save(out.subdirectory("scene"))
        near["result"].save(out.subdirectory("near"))
        base["result"].save(out.subdirectory("baseline"))

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
    top = out.path
    print(f"wrote the scene to {top / 'scene'}, the reconstructions to {top / 'near'} and {top / 'baseline'}")
    return 0
