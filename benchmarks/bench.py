"""Benchmark: nplps (Rust core) against the pure-numpy/scipy reference, same scenes, same run.

Usage::

    python benchmarks/bench.py [--sizes 128 256 512] [--repeats 5] [--reference-repeats 1]
                               [--threads N] [--json results.json]

Each size reconstructs the synthetic ``bumps`` scene (27 lights, 10 iterations, tol 0 so that
every run does exactly 10 iterations) and reports the median wall time of the Rust core split into
factorization, local steps and solves, the reference's median, and the speed-up; then the time of
``depth="auto"`` (working-distance search) against a run given the distance. Timings are
medians of repeated runs in one process; machines are shared and noisy, so compare ratios
measured in the same run rather than absolute numbers across runs.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

import nplps

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import reference


def time_rust(scene: nplps.Scene, images: np.ndarray, repeats: int, threads: int | None) -> dict[str, float]:
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        r = nplps.reconstruct(
            images, scene.rig, mask=scene.mask, depth=scene.mean_depth, iterations=10, tol=0.0, threads=threads
        )
        wall = time.perf_counter() - t0
        runs.append({**r.timings, "wall": wall})
    return {k: statistics.median(run[k] for run in runs) for k in runs[0]}


def time_reference(scene: nplps.Scene, images: np.ndarray, repeats: int) -> dict[str, float]:
    cam = scene.rig.camera
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = reference.reconstruct(
            images.astype(np.float64),
            scene.rig.positions,
            cam["pixel_size"],
            cam["origin"],
            mask=scene.mask,
            depth=scene.mean_depth,
            iterations=10,
            tol=0.0,
        )
        wall = time.perf_counter() - t0
        runs.append(
            {
                "factorization": out["timings"]["factor"],
                "local": out["timings"]["local"],
                "solve": out["timings"]["solve"],
                "total": out["timings"]["total"],
                "wall": wall,
            }
        )
    return {k: statistics.median(run[k] for run in runs) for k in runs[0]}


def _wall(run) -> float:
    t0 = time.perf_counter()
    run()
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512])
    parser.add_argument("--repeats", type=int, default=5, help="runs of the Rust core per size (median reported)")
    parser.add_argument("--reference-repeats", type=int, default=1, help="runs of the numpy reference per size")
    parser.add_argument(
        "--threads", type=int, default=None, help="worker threads of the Rust core (default: all cores)"
    )
    parser.add_argument("--auto-size", type=int, default=256, help="image size of the depth='auto' timing")
    parser.add_argument("--json", help="also write the results to this JSON file")
    args = parser.parse_args()

    results = []
    header = f"{'size':>9} {'factor':>8} {'local':>8} {'solve':>8} {'total':>8} | {'numpy':>8} {'speed-up':>8}"
    print(f"nplps {nplps.__version__}: bumps scene, 27 lights, 10 iterations; seconds, medians")
    print(header)
    print("-" * len(header))
    for n in args.sizes:
        scene = nplps.make_scene("bumps", n=n)
        images = scene.images.astype(np.float32)
        nplps.reconstruct(images, scene.rig, mask=scene.mask, depth=scene.mean_depth, iterations=1)  # warm-up
        rust = time_rust(scene, images, args.repeats, args.threads)
        ref = time_reference(scene, images, args.reference_repeats)
        speedup = ref["wall"] / rust["wall"]
        print(
            f"{n:>4}x{n:<4} {rust['factorization']:8.3f} {rust['local']:8.3f} {rust['solve']:8.3f} {rust['wall']:8.3f}"
            f" | {ref['wall']:8.3f} {speedup:7.1f}x"
        )
        results.append({"size": n, "rust": rust, "numpy_reference": ref, "speedup": speedup})
    # The working-distance search (depth="auto") against a run given the distance.
    scene = nplps.make_scene("bumps", n=args.auto_size, camera="pinhole", led=True, noise=0.01)
    images = scene.images.astype(np.float32)
    known = statistics.median(
        _wall(lambda: nplps.reconstruct(images, scene.rig, mask=scene.mask, depth=scene.mean_depth))
        for _ in range(args.repeats)
    )
    auto = statistics.median(
        _wall(lambda: nplps.reconstruct(images, scene.rig, mask=scene.mask, depth="auto")) for _ in range(args.repeats)
    )
    print(
        f"\ndepth='auto' on a {args.auto_size}^2 pinhole LED scene: {auto:.3f} s"
        f", {auto / known:.1f}x a run given the distance ({known:.3f} s)"
    )
    results.append({"auto_size": args.auto_size, "auto": auto, "known": known, "ratio": auto / known})
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(results, f, indent=2)


if __name__ == "__main__":
    main()
