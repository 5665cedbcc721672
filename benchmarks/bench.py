"""Benchmark: nplps (Rust core) against the pure-numpy/scipy reference, same scenes, same run.

Usage::

    python benchmarks/bench.py [--sizes 128 256 512] [--repeats 5] [--reference-repeats 1]
                               [--threads N] [--json results.json]
    python benchmarks/bench.py --ratios [--ratio-sizes 256 512 1024] [--repeats 3]

Each size reconstructs the synthetic ``bumps`` scene (27 lights, 10 iterations, tol 0 so that
every run does exactly 10 iterations) and reports the median wall time of the Rust core split into
factorization, local steps and solves, the reference's median, and the speed-up; then the time of
``depth="auto"`` (working-distance search) against a run given the distance. Timings are
medians of repeated runs in one process, wall time and the process's CPU time (``time.process_time``,
all threads; the numpy reference's CPU ratio says how much work each does, its wall ratio what a
user waits); machines are shared and noisy, so compare ratios
measured in the same run rather than absolute numbers across runs.

``--ratios`` measures only the cost ratios of issue 23 (item 4), medians in one process: ``depth="auto"``
over a run given the distance (pinhole bumps, 27 lights, 1 % noise) at each ``--ratio-sizes`` with robust
none / tukey and reflectance lambertian / glossy, with the found distance's error; and light refinement
over none at 256² and the largest size, each mode given the rig it is for: "intensity" a rig whose
intensities are off by up to 20 % (positions right), "position" one whose positions are off by 2 mm
(intensities right: refining positions against wrong intensities makes the positions absorb the
intensity error, a misuse), "both" both errors; "none" runs on the "both" rig. With the mean normal
error against the true normals and the refined lights' errors (intensities relative to their
geometric mean, positions in mm).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np

import nplps

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import reference


def time_rust(
    scene: nplps.Scene, images: np.ndarray, repeats: int, threads: int | None, levels: int | None = None
) -> dict[str, float]:
    """Median timings of ``nplps.reconstruct`` with 10 iterations (per level) and tol 0. ``levels=1``
    is the reference's work exactly (10 local and 10 global steps at full resolution); the default
    pyramid does 10 iterations on every level and the trust maps on top."""
    runs = []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        r = nplps.reconstruct(
            images,
            scene.rig,
            mask=scene.mask,
            depth=scene.mean_depth,
            iterations=10,
            tol=0.0,
            threads=threads,
            levels=levels,
        )
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        runs.append({**r.timings, "wall": wall, "cpu": cpu})
    return {k: statistics.median(run[k] for run in runs) for k in runs[0]}


def time_reference(scene: nplps.Scene, images: np.ndarray, repeats: int) -> dict[str, float]:
    cam = scene.rig.camera
    runs = []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
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
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        runs.append(
            {
                "factorization": out["timings"]["factor"],
                "local": out["timings"]["local"],
                "solve": out["timings"]["solve"],
                "total": out["timings"]["total"],
                "wall": wall,
                "cpu": cpu,
            }
        )
    return {k: statistics.median(run[k] for run in runs) for k in runs[0]}


def _wall(run) -> float:
    t0 = time.perf_counter()
    run()
    return time.perf_counter() - t0


CASES = ("none/lambertian", "tukey/lambertian", "none/glossy")


def _timed(reps: int, *args: object, **kw: object) -> tuple[float, float, nplps.Reconstruction]:
    """Median wall and CPU time (the process's, all threads) of ``reps`` runs of
    ``nplps.reconstruct(*args, **kw)`` and the first result."""
    results: list[nplps.Reconstruction] = []
    times, cpus = [], []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for _ in range(reps):
            t0, c0 = time.perf_counter(), time.process_time()
            results.append(nplps.reconstruct(*args, **kw))  # type: ignore[arg-type]
            times.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
    return statistics.median(times), statistics.median(cpus), results[0]


def ratios(
    sizes: list[int], repeats: int, cases: list[str], largest: int | None, refine_sizes: list[int] | None
) -> list[dict[str, object]]:
    """Print and return the cost ratios of ``depth="auto"`` and of light refinement (see the module docstring)."""
    out: list[dict[str, object]] = []
    print("## depth='auto' over a known distance (bumps, pinhole, 27 lights, 1 % noise; medians)")
    print(
        f"{'size':>9} {'robust':>6} {'reflectance':>11} | {'known s':>8} {'auto s':>8} {'ratio':>6}"
        f" | {'CPU known':>9} {'CPU auto':>8} {'ratio':>6} | distance error"
    )
    for n in sizes:
        reps = repeats if n <= 512 else max(1, (repeats + 1) // 2)
        for case in cases if largest is None or n <= largest else cases[:1]:
            name, reflectance = case.split("/")
            robust = None if name == "none" else name
            glossy = reflectance == "glossy"
            s = nplps.make_scene(
                "bumps", n=n, camera="pinhole", led=not glossy, noise=0.01, specular=0.5 if glossy else 0.0
            )
            images = s.images.astype(np.float32)
            kw = {"mask": s.mask, "robust": robust, "reflectance": reflectance}
            known, known_cpu, _ = _timed(reps, images, s.rig, depth=s.mean_depth, **kw)
            auto, auto_cpu, found = _timed(reps, images, s.rig, depth="auto", **kw)
            assert found.distance is not None
            error = found.distance.distance[0] / s.mean_depth - 1
            print(
                f"{n:>4}x{n:<4} {name:>6} {reflectance:>11} | {known:8.3f} {auto:8.3f} {auto / known:6.2f}"
                f" | {known_cpu:9.3f} {auto_cpu:8.3f} {auto_cpu / known_cpu:6.2f} | {100 * error:+.3f} %",
                flush=True,
            )
            out.append(
                {
                    "size": n,
                    "robust": robust,
                    "reflectance": reflectance,
                    "known": known,
                    "auto": auto,
                    "known_cpu": known_cpu,
                    "auto_cpu": auto_cpu,
                    "error": error,
                }
            )
    if not refine_sizes:
        return out
    print(
        "\n## Light refinement over none (bumps, pinhole LEDs; intensity: intensities off by up to 20 %,"
        " position: positions off by 2 mm, both: both, none: the both rig; medians)"
    )
    print(
        f"{'size':>9} {'refine':>9} | {'time s':>8} {'ratio':>6} | {'CPU s':>8} {'ratio':>6}"
        " | normals (deg) | intensity % | position mm"
    )
    for n in refine_sizes:
        reps = repeats if n <= 512 else max(1, (repeats + 1) // 2)
        s = nplps.make_scene("bumps", n=n, camera="pinhole", led=True, noise=0.01)
        rigs = refinement_rigs(s.rig)
        images = s.images.astype(np.float32)
        base = base_cpu = None
        for mode in (None, "intensity", "position", "both"):
            rig = rigs[mode or "both"]
            t, cpu, r = _timed(reps, images, rig, depth=s.mean_depth, mask=s.mask, refine_lights=mode)
            base, base_cpu = base or t, base_cpu or cpu
            cos = np.clip((r.normals * s.normals).sum(-1), -1.0, 1.0)
            error = float(np.degrees(np.arccos(cos))[s.mask].mean())
            phi, pos = light_errors(r.rig, s.rig)
            print(
                f"{n:>4}x{n:<4} {mode or 'none':>9} | {t:8.3f} {t / base:6.2f} | {cpu:8.3f} {cpu / base_cpu:6.2f}"
                f" | {error:13.3f} | {phi:11.3f}"
                f" | {pos:11.3f}",
                flush=True,
            )
            out.append(
                {
                    "size": n,
                    "refine": mode,
                    "time": t,
                    "ratio": t / base,
                    "cpu": cpu,
                    "cpu_ratio": cpu / base_cpu,
                    "normals": error,
                    "intensity_error": phi,
                    "position_error": pos,
                }
            )
    return out


def refinement_rigs(rig: nplps.Rig) -> dict[str, nplps.Rig]:
    """The rigs of the light-refinement rows: ``rig`` with its intensities off by up to 20 % ("intensity"),
    its positions off by 2 mm in random directions ("position"), and both ("both"); fixed seeds."""
    factors = 1 + np.random.default_rng(1).uniform(-0.2, 0.2, rig.n_lights)
    step = np.random.default_rng(2).normal(size=(rig.n_lights, 3))
    moved = rig.positions + 2.0 * step / np.linalg.norm(step, axis=1, keepdims=True)
    intensity = rig.with_intensities(rig.intensities * factors[:, None])
    return {"intensity": intensity, "position": rig.with_positions(moved), "both": intensity.with_positions(moved)}


def light_errors(found: nplps.Rig, truth: nplps.Rig) -> tuple[float, float]:
    """The largest intensity error of ``found`` (percent, each rig's intensities relative to their geometric
    mean) and its mean position error (scene units, mm)."""

    def relative(phi: np.ndarray) -> np.ndarray:
        return phi / np.exp(np.log(phi).mean())

    phi = relative(found.intensities[:, 0]) / relative(truth.intensities[:, 0]) - 1
    pos = np.linalg.norm(found.positions - truth.positions, axis=1)
    return float(100 * np.abs(phi).max()), float(pos.mean())


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
    parser.add_argument("--ratios", action="store_true", help="only the auto and light-refinement cost ratios")
    parser.add_argument("--ratio-sizes", type=int, nargs="*", default=[256, 512, 1024])
    parser.add_argument(
        "--ratio-cases", nargs="+", default=list(CASES), help="robust/reflectance pairs of the auto ratios"
    )
    parser.add_argument("--refine-sizes", type=int, nargs="*", default=[256, 1024], help="light-refinement sizes")
    parser.add_argument("--ratio-max", type=int, default=None, help="sizes above this: the first case only")
    args = parser.parse_args()
    if args.ratios:
        results = ratios(args.ratio_sizes, args.repeats, args.ratio_cases, args.ratio_max, args.refine_sizes)
        if args.json:
            with open(args.json, "w", encoding="utf-8") as f:
                json.dump(results, f, indent=2)
        return

    results = []
    header = (
        f"{'size':>9} {'factor':>8} {'local':>8} {'solve':>8} {'total':>8} | {'numpy':>8} {'speed-up':>8}"
        f" | {'levels=1':>8} {'speed-up':>8} | {'CPU':>6} {'numpy CPU':>9} {'ratio':>6}"
    )
    print(
        f"nplps {nplps.__version__}: bumps scene, 27 lights, 10 iterations (per level: the default pyramid; "
        "levels=1: the reference's work); seconds, medians"
    )
    print(header)
    print("-" * len(header))
    for n in args.sizes:
        scene = nplps.make_scene("bumps", n=n)
        images = scene.images.astype(np.float32)
        nplps.reconstruct(images, scene.rig, mask=scene.mask, depth=scene.mean_depth, iterations=1)  # warm-up
        rust = time_rust(scene, images, args.repeats, args.threads)
        single = time_rust(scene, images, args.repeats, args.threads, levels=1)
        ref = time_reference(scene, images, args.reference_repeats)
        speedup = ref["wall"] / rust["wall"]
        same_work = ref["wall"] / single["wall"]
        print(
            f"{n:>4}x{n:<4} {rust['factorization']:8.3f} {rust['local']:8.3f} {rust['solve']:8.3f} {rust['wall']:8.3f}"
            f" | {ref['wall']:8.3f} {speedup:7.1f}x | {single['wall']:8.3f} {same_work:7.1f}x"
            f" | {rust['cpu']:6.3f} {ref['cpu']:9.3f} {ref['cpu'] / rust['cpu']:5.1f}x"
        )
        results.append(
            {
                "size": n,
                "rust": rust,
                "rust_levels_1": single,
                "numpy_reference": ref,
                "speedup": speedup,
                "speedup_same_work": same_work,
            }
        )
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
