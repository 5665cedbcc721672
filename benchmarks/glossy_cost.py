"""Cost of the glossy reflectance model against the Lambertian default (issue 20).

Usage::

    python benchmarks/glossy_cost.py [--sizes 256 1024] [--repeats 3]
                                     [--pbr /work/pbr-data/256/bumps-roughplastic-0.3-256.npz]
                                     [--modes lambertian given estimated] [--json out.json]
                                     [--noise 0 0.005]
                                     [--baseline DIR]

Scenes: ``nplps.make_scene("bumps", camera="pinhole", specular=0.2, roughness=0.3)`` (rendered
by the glossy model itself, lobe alpha 0.3, eta 1.5) at each size and ``--noise`` level (noise-free by
default; real captures have 0.2-1 %, where the glossy run's iterations differ), and the PBR render given by
``--pbr`` (its own size; pass ``--pbr ''`` to skip it). Modes: ``lambertian`` (the default),
``given`` (``reflectance="glossy"`` with the true lobe; for a PBR render the roughness of its
material name (squared for principled) and eta 1.5) and ``estimated`` (``reflectance="glossy"``, lobe estimated), each
with the true distance and the default ``check_distance``.

Every run is one fresh Python process (its peak RSS, ``ru_maxrss``, is its own and includes the
images and the scene's rendering), and the modes of a repeat run one after the other, so that
the ratios compare runs under the same machine load. Per scene and mode the table has the
median wall seconds of ``nplps.reconstruct`` over the repeats, its ratio to the Lambertian
median, the median CPU seconds of the process during it (user + system, all threads; steadier
than the wall time on a loaded machine) and their ratio, the median peak RSS, the outer
iterations (``len(result.history)``, all levels), the mean normal error against the truth
(degrees, mesh normals) and the lobe found.

``--baseline DIR`` runs every mode also with another build of nplps, imported from ``DIR`` (e.g. a
wheel of the main branch unpacked there, or a copy of its ``python/`` directory with its
``_core`` library), alternating with this build run by run; its rows are marked ``(baseline)``
and its ratios are to its own Lambertian median. An A/B measured in one run
sees the same machine load.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import statistics
import subprocess
import sys
import time
import warnings
from typing import Any

import numpy as np

MODES = ("lambertian", "given", "estimated")


def angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Return the angles in degrees between unit vectors (..., 3)."""
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))


def load(scene: str) -> tuple[Any, Any, np.ndarray, np.ndarray, float, tuple[float, float]]:
    """Return images, rig, mask, true normals, true distance and the true lobe of `scene`.

    `scene` is ``bumps-N`` (the synthetic glossy bumps, N x N), ``bumps-N-noiseS`` (the same with
    Gaussian noise of standard deviation S, see ``--noise``) or the path of a PBR ``.npz``.
    """
    import nplps

    if scene.startswith("bumps-"):
        n, _, noise = scene.removeprefix("bumps-").partition("-noise")
        s = nplps.make_scene(
            "bumps", n=int(n), camera="pinhole", specular=0.2, roughness=0.3, eta=1.5, noise=float(noise or 0.0)
        )
        return s.images, s.rig, s.mask, s.normals, s.mean_depth, (0.3, 1.5)
    with np.load(scene) as f:
        data = dict(f)
    rig = nplps.Rig.from_dict(json.loads(str(data["rig"])))
    material = str(data["material"])
    found = re.search(r"-(0\.\d+)", material)
    alpha = float(found.group(1)) if found else 0.3
    if material.startswith("principled"):
        alpha = alpha**2  # Mitsuba's principled BSDF: GGX alpha = roughness^2
    return data["images"], rig, data["mask"], data["normals"], float(data["distance"]), (alpha, 1.5)


def worker(scene: str, mode: str) -> dict[str, Any]:
    """Run one reconstruction of `scene` in `mode` and return its numbers (this process's)."""
    import nplps

    images, rig, mask, normals, distance, (alpha, eta) = load(scene)
    options: dict[str, Any] = {}
    if mode == "given":
        options = {"reflectance": "glossy", "roughness": alpha, "eta": eta}
    elif mode == "estimated":
        options = {"reflectance": "glossy"}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cpu0 = resource.getrusage(resource.RUSAGE_SELF)
        start = time.perf_counter()
        result = nplps.reconstruct(images, rig, depth=distance, mask=mask, **options)
        seconds = time.perf_counter() - start
        cpu1 = resource.getrusage(resource.RUSAGE_SELF)
    lobe = None if result.lobe is None else (result.lobe.roughness, result.lobe.eta)
    return {
        "seconds": seconds,
        "cpu_seconds": cpu1.ru_utime - cpu0.ru_utime + cpu1.ru_stime - cpu0.ru_stime,
        "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "iterations": len(result.history),
        "error": float(angles(result.normals[mask], normals[mask]).mean()),
        "lobe": lobe,
        "solver_seconds": result.timings.get("total", float("nan")),
    }


def run(scene: str, mode: str, baseline: str | None = None) -> dict[str, Any]:
    """Run `worker` in a fresh process (importing nplps from `baseline` if given) and return its numbers."""
    env = dict(os.environ)
    if baseline:
        env["PYTHONPATH"] = os.pathsep.join([baseline, env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    out = subprocess.run(
        [sys.executable, os.path.abspath(__file__), "--worker", scene, mode],
        check=True,
        capture_output=True,
        text=True,
        env=env,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    """Time every scene and mode and print the table."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="*", default=[256, 1024])
    parser.add_argument("--pbr", default="/work/pbr-data/256/bumps-roughplastic-0.3-256.npz")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--noise",
        type=float,
        nargs="*",
        default=[0.0],
        help="noise levels of the synthetic bumps (make_scene's noise, e.g. 0 0.005): one scene per size and level",
    )
    parser.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    parser.add_argument("--json", help="write the numbers to this file")
    parser.add_argument("--baseline", help="also run the nplps importable from this directory (A/B)")
    parser.add_argument("--worker", nargs=2, metavar=("SCENE", "MODE"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(worker(*args.worker)))
        return
    scenes = [f"bumps-{n}" + (f"-noise{e:g}" if e else "") for n in args.sizes for e in args.noise]
    scenes += [args.pbr] if args.pbr else []
    header = (
        "| scene | mode | s (median) | x Lambertian | CPU s | x Lambertian (CPU) | peak RSS (MB) | iterations "
        "| mean error (deg) | lobe |"
    )
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    table: dict[str, dict[str, list[dict[str, Any]]]] = {}
    builds = [""] + ([" (baseline)"] if args.baseline else [])
    for scene in scenes:
        runs: dict[str, list[dict[str, Any]]] = {m + b: [] for b in builds for m in args.modes}
        for _ in range(args.repeats):
            for mode in args.modes:
                for b in builds:
                    runs[mode + b].append(run(scene, mode, args.baseline if b else None))
        table[scene] = runs
        cpu_bases = {
            b: statistics.median(r["cpu_seconds"] for r in runs["lambertian" + b])
            for b in builds
            if "lambertian" + b in runs
        }
        bases = {
            b: statistics.median(r["seconds"] for r in runs["lambertian" + b])
            for b in builds
            if "lambertian" + b in runs
        }
        name = os.path.basename(scene).removesuffix(".npz")
        for mode, rs in runs.items():
            seconds = statistics.median(r["seconds"] for r in rs)
            rss = statistics.median(r["rss_mb"] for r in rs)
            last = rs[-1]
            lobe = "" if last["lobe"] is None else f"{last['lobe'][0]:.3f}, {last['lobe'][1]:.2f}"
            build = " (baseline)" if mode.endswith(" (baseline)") else ""
            base, cpu_base = bases.get(build, float("nan")), cpu_bases.get(build, float("nan"))
            cpu = statistics.median(r["cpu_seconds"] for r in rs)
            print(
                f"| {name} | {mode} | {seconds:.2f} | {seconds / base:.2f} | {cpu:.2f} | {cpu / cpu_base:.2f} "
                f"| {rss:.0f} | {last['iterations']} "
                f"| {last['error']:.3f} | {lobe} |",
                flush=True,
            )
    if args.json:
        with open(args.json, "w") as f:
            json.dump(table, f, indent=1)


if __name__ == "__main__":
    main()
