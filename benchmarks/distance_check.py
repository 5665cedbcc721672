"""The check of a given working distance (``reconstruct(check_distance=True)``): issue 18, item 8.

    python benchmarks/distance_check.py [--seeds 5] [--sections rates,cost,real]

- rates: synthetic scenes (sphere, bumps, saddle, cube; orthographic and pinhole; 0.5 % and 2 %
  noise; plain and tukey fits), reconstructed at the true distance times 0.7 ... 1.3, seeds
  0..N-1: how often the check says "looks wrong" at each offset. Offsets within 5 % must not
  warn (false alarms); offsets of 15 % or more should (detections).
- cost: the time of a run with the check over one without (medians of 3 runs in this process;
  machines are shared and noisy: compare the ratios).
- real: the shared captures at their documented distances and at 0.8 / 1.25 times them
  (needs ../shared/data).
"""

from __future__ import annotations

import argparse
import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np

import nplps
from refine_lights import _median_time  # same folder: the benchmarks' one timing helper

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
OFFSETS = (0.7, 0.8, 0.85, 0.9, 0.95, 0.98, 1.0, 1.02, 1.05, 1.1, 1.15, 1.2, 1.3)


def check(images, rig, mask, depth, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return nplps.reconstruct(images, rig, depth=depth, mask=mask, **kw).distance_check


def rates(seeds: int, n: int) -> None:
    print(f"## Warnings by offset of the given distance ({n} x {n}, 27 lights, seeds 0..{seeds - 1})")
    warned: dict[tuple[str, float], list[bool]] = defaultdict(list)
    ratios: dict[float, list[float]] = defaultdict(list)
    found: list[float] = []
    for name in ("sphere", "bumps", "saddle", "cube"):
        for camera in ("orthographic", "pinhole"):
            for noise in (0.005, 0.02):
                for robust in (None, "tukey"):
                    group = f"{name}/{camera[:5]}/{noise:g}/{robust or 'plain'}"
                    for seed in range(seeds):
                        s = nplps.make_scene(name, n=n, seed=seed, noise=noise, camera=camera)
                        for f in OFFSETS:
                            c = check(s.images, s.rig, s.mask, s.mean_depth * f, robust=robust)
                            assert c is not None
                            warned[(group, f)].append(c.looks_wrong)
                            ratios[f].append(c.ratio)
                            if f == 1.0:
                                found.append(c.found / s.mean_depth - 1.0)
    groups = sorted({g for g, _ in warned})
    print("group                        | " + " ".join(f"{f:5.2f}" for f in OFFSETS))
    for g in groups:
        print(f"{g:28} | " + " ".join(f"{np.mean(warned[(g, f)]):5.2f}" for f in OFFSETS))
    total = {f: np.mean([w for (g, ff), ws in warned.items() if ff == f for w in ws]) for f in OFFSETS}
    print(f"{'all (share warned)':28} | " + " ".join(f"{total[f]:5.2f}" for f in OFFSETS))
    print(f"{'median residual ratio':28} | " + " ".join(f"{np.median(ratios[f]):5.2f}" for f in OFFSETS))
    near = [w for (g, f), ws in warned.items() if abs(f - 1) <= 0.05 + 1e-9 for w in ws]
    far = [w for (g, f), ws in warned.items() if abs(f - 1) >= 0.15 - 1e-9 for w in ws]
    print(
        f"false alarms (|offset| <= 5 %): {sum(near)} of {len(near)}; "
        f"detections (|offset| >= 15 %): {sum(far)} of {len(far)}"
    )
    fa = np.abs(found)
    print(f"found distance at the true one: |error| median {100 * np.median(fa):.2f} %, max {100 * fa.max():.2f} %")


def cost() -> None:
    print("\n## Cost of the check (bumps, 27 lights, 1 % noise; medians of 3 runs)")
    print("size  | without (s) | with (s) | ratio")
    for n in (128, 256, 512, 1024):
        s = nplps.make_scene("bumps", n=n, seed=0, noise=0.01)

        def run(check: bool, s: nplps.Scene = s) -> None:
            nplps.reconstruct(s.images, s.rig, depth=s.mean_depth, mask=s.mask, check_distance=check)

        off = _median_time(lambda: run(False), 3)
        on = _median_time(lambda: run(True), 3)
        print(f"{n:5} | {off:11.3f} | {on:8.3f} | {on / off:5.2f}")


def real() -> None:
    from nplps import captures

    if not SHARED.is_dir():
        print(f"\n(real captures skipped: {SHARED} not found)")
        return
    print("\n## Real captures at their documented distances and at 0.8 / 1.25 times them")
    cases = [
        ("hehe12 (bin 4)", captures.prepare(captures.load_hehe12(SHARED / "hehe12"), bin_factor=4), 200.0),
        (
            "queau_human1 (bin 8)",
            captures.prepare(captures.load_queau_human1(SHARED / "queau_human1"), bin_factor=8),
            700.0,
        ),
    ]
    for label, cap, d in cases:
        for f in (1.0, 0.8, 1.25):
            try:
                c = check(cap.images, cap.rig(), cap.mask, d * f)
            except nplps.SolverError as e:
                print(f"{label} at {d * f:g}: the run fails: {str(e)[:90]}...")
                continue
            text = "no check (rig cannot reveal the distance)" if c is None else c.message
            print(f"{label} at {d * f:g}: {text}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--size", type=int, default=96)
    parser.add_argument("--sections", default="rates,cost,real")
    args = parser.parse_args()
    sections = args.sections.split(",")
    if "rates" in sections:
        rates(args.seeds, args.size)
    if "cost" in sections:
        cost()
    if "real" in sections:
        real()


if __name__ == "__main__":
    main()
