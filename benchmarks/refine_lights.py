"""Self-calibration of the lights (``refine_lights=``): the tables of issue 8.

    python benchmarks/refine_lights.py [--seeds 10] [--sections intensity,cost,position,real]
    python benchmarks/refine_lights.py --sections ratios [--ratio-sizes 128 256 1024] [--repeats 3]

- intensity: per-light intensity errors of +-35 % on synthetic scenes, exact and with 1 % noise:
  the recovered relative intensities, the normals against a run with the true intensities, and
  what refinement changes when the rig is right;
- cost: time of a run with intensity refinement over one without, medians of repeated runs
  measured in this process (machines are shared and noisy: compare the ratios, not the times);
- ratios: the cost ratios of issue 23 (item 4), refined over known lights, at 128², 256² and
  1 MP (``--ratio-sizes``): pinhole bumps, 27 LEDs, 1 % noise, intensity refinement (intensities
  off by up to 20 %) and position refinement (positions off by 2 % of the distance), Lambertian
  and glossy (specular albedo 0.5 of the diffuse) reflectance, with the errors of each run (mean
  normal error against the truth, RMS relative intensity error, RMS position error);
- convergence: the residual and the light change per iteration of one run of each kind;
- position: the paper's test, light positions off by 5 % of the working distance (RMS), seeds
  0..N-1, exact and with 1 % noise: light-position and normal errors before and after, the
  fallback/stop flags and the conditioning of the light block;
- real: hehe12's held-out protocol with calibrated intensities (each model refines its own),
  and queau_human1 / diligent_ball with and without refinement (needs ../shared/data).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import nplps
from nplps.evaluation import held_out

KW = dict(iterations=50, tol=1e-7)
SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))


def relative(phi: np.ndarray) -> np.ndarray:
    return phi / np.exp(np.mean(np.log(phi)))


def wrong_intensities(rig: nplps.Rig, seed: int, amount: float = 0.35) -> nplps.Rig:
    rng = np.random.default_rng(100 + seed)
    factors = 1.0 + rng.uniform(-amount, amount, rig.n_lights)
    return rig.with_intensities(rig.intensities * factors[:, None])


def wrong_positions(rig: nplps.Rig, seed: int, distance: float, fraction: float = 0.05) -> nplps.Rig:
    rng = np.random.default_rng(1000 + seed)
    shift = rng.normal(size=rig.positions.shape) * fraction * distance / np.sqrt(3.0)
    return rig.with_positions(rig.positions + shift)


def intensity_table(seeds: int) -> None:
    print("## Intensity refinement: +-35 % intensity errors (bumps and sphere, 80 x 80, 27 lights)")
    print(
        "scene  noise seed | rel. intensity err % | normals vs true-intensity run (deg)"
        " | unrefined (deg) | at 0 % error (deg)"
    )
    for name in ("bumps", "sphere"):
        for noise in (0.0, 0.01):
            for seed in range(seeds):
                scene = nplps.make_scene(name, n=80, seed=seed, noise=noise)
                d, m = scene.mean_depth, scene.mask
                truth = nplps.reconstruct(scene.images, scene.rig, mask=m, depth=d, **KW)
                same = nplps.reconstruct(scene.images, scene.rig, mask=m, depth=d, refine_lights="intensity", **KW)
                bad = wrong_intensities(scene.rig, seed)
                plain = nplps.reconstruct(scene.images, bad, mask=m, depth=d, **KW)
                refined = nplps.reconstruct(scene.images, bad, mask=m, depth=d, refine_lights="intensity", **KW)
                phi = relative(refined.rig.intensities[:, 0]) / relative(scene.rig.intensities[:, 0])
                print(
                    f"{name:6} {noise:5.2f} {seed:4} | {100 * np.abs(phi - 1).max():20.3f} | "
                    f"{angles(refined.normals, truth.normals)[m].mean():35.4f} | "
                    f"{angles(plain.normals, truth.normals)[m].mean():15.2f} | "
                    f"{angles(same.normals, truth.normals)[m].mean():18.4f}"
                )


def _median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def cost_table() -> None:
    print("\n## Cost of intensity refinement (bumps, 27 lights, +-35 % errors; medians, same process)")
    print("size      | plain (s) | refined (s) | ratio | iterations plain / refined")
    for n, repeats in ((80, 15), (256, 7), (1024, 3)):
        scene = nplps.make_scene("bumps", n=n, seed=0)
        bad = wrong_intensities(scene.rig, 0)
        d = scene.mean_depth
        args = (scene.images.astype(np.float32), bad)
        kw = {**KW, "mask": scene.mask, "depth": d}
        plain = _median_time(lambda args=args, kw=kw: nplps.reconstruct(*args, **kw), repeats)
        refined = _median_time(
            lambda args=args, kw=kw: nplps.reconstruct(*args, refine_lights="intensity", **kw), repeats
        )
        its = (
            len(nplps.reconstruct(*args, **kw).history),
            len(nplps.reconstruct(*args, refine_lights="intensity", **kw).history),
        )
        print(f"{n:4} x {n:<4}| {plain:9.3f} | {refined:11.3f} | {refined / plain:5.2f} | {its[0]} / {its[1]}")


def ratio_table(sizes: list[int], repeats: int, reflectances: list[str]) -> None:
    print("\n## Light refinement over known lights (bumps, pinhole, 27 LEDs, 1 % noise; medians in this process)")
    print(
        f"{'size':>9} {'reflectance':>11} {'refine':>9} | {'time s':>8} {'ratio':>6} {'its':>4} | "
        "normals deg | intensity err % | position err mm"
    )
    for n in sizes:
        reps = repeats if n <= 512 else max(2, (repeats + 1) // 2)
        for reflectance in reflectances:
            glossy = reflectance == "glossy"
            s = nplps.make_scene("bumps", n=n, camera="pinhole", led=True, noise=0.01, specular=0.5 if glossy else 0.0)
            rng = np.random.default_rng(1)
            d = s.mean_depth
            bad_phi = s.rig.with_intensities(s.rig.intensities * (1 + rng.uniform(-0.2, 0.2, s.rig.n_lights))[:, None])
            bad_pos = wrong_positions(s.rig, 1, d, fraction=0.02)
            images = s.images.astype(np.float32)
            kw = {"mask": s.mask, "depth": d, "reflectance": reflectance}  # default iterations and tol
            base = None
            for mode, rig in ((None, s.rig), ("intensity", bad_phi), ("position", bad_pos)):
                runs = []
                for _ in range(reps):
                    t = time.perf_counter()
                    r = nplps.reconstruct(images, rig, refine_lights=mode, **kw)
                    runs.append(time.perf_counter() - t)
                t = float(np.median(runs))
                base = base or t
                normals = angles(r.normals, s.normals)[s.mask].mean()
                phi = relative(r.rig.intensities[:, 0]) / relative(s.rig.intensities[:, 0])
                pos = np.sqrt(np.mean(np.sum((r.rig.positions - s.rig.positions) ** 2, axis=1)))
                print(
                    f"{n:>4}x{n:<4} {reflectance:>11} {mode or 'none':>9} | {t:8.3f} {t / base:6.2f} "
                    f"{len(r.history):4} | {normals:11.4f} | {100 * np.sqrt(np.mean((phi - 1) ** 2)):15.4f} | "
                    f"{pos:15.3f}",
                    flush=True,
                )


def convergence_traces() -> None:
    print("\n## Convergence per iteration (bumps 80 x 80, seed 0; one light step per iteration)")
    scene = nplps.make_scene("bumps", n=80, seed=0)
    d, m = scene.mean_depth, scene.mask
    for mode, bad in (
        ("intensity", wrong_intensities(scene.rig, 0)),
        ("position", wrong_positions(scene.rig, 0, d)),
    ):
        r = nplps.reconstruct(scene.images, bad, mask=m, depth=d, refine_lights=mode, **KW)
        print(f"{mode}: iteration, rms residual, largest light change (relative), depth change")
        for h in r.history:
            print(f"  {h.iteration:3} {h.rms_residual:10.3e} {h.light_change:10.3e} {h.depth_change:10.3e}")


def position_table(seeds: int) -> None:
    print("\n## Position refinement: the paper's test, light positions off by 5 % of the distance (RMS)")
    print("bumps, 80 x 80, 27 lights, refine_lights='position', default prior (w = 1000)")
    print(
        "noise seed | light RMS err mm before -> after"
        " | normals deg: true rig / before / after | fell back | stopped | cond"
    )
    for noise in (0.0, 0.01):
        rows = []
        for seed in range(seeds):
            scene = nplps.make_scene("bumps", n=80, seed=seed, noise=noise)
            d, m = scene.mean_depth, scene.mask
            bad = wrong_positions(scene.rig, seed, d)
            truth = nplps.reconstruct(scene.images, scene.rig, mask=m, depth=d, **KW)
            plain = nplps.reconstruct(scene.images, bad, mask=m, depth=d, **KW)
            refined = nplps.reconstruct(scene.images, bad, mask=m, depth=d, refine_lights="position", **KW)
            err = [angles(r.normals, scene.normals)[m].mean() for r in (truth, plain, refined)]
            before = np.sqrt(np.mean(np.sum((bad.positions - scene.rig.positions) ** 2, axis=1)))
            after = np.sqrt(np.mean(np.sum((refined.rig.positions - scene.rig.positions) ** 2, axis=1)))
            ref = refined.refinement
            rows.append(err)
            print(
                f"{noise:5.2f} {seed:4} | {before:14.2f} -> {after:6.2f}        | "
                f"{err[0]:8.3f} / {err[1]:6.3f} / {err[2]:6.3f}       | {ref.fell_back!s:9} | "
                f"{ref.stopped!s:7} | {ref.condition_number:.3g}"
            )
        rows_a = np.array(rows)
        print(
            f"  noise {noise}: after refinement max {rows_a[:, 2].max():.3f} deg (no refinement "
            f"{rows_a[:, 1].min():.2f}..{rows_a[:, 1].max():.2f}); excess over the true rig max "
            f"{(rows_a[:, 2] - rows_a[:, 0]).max():.3f} deg; never worse than no refinement: "
            f"{bool((rows_a[:, 2] <= rows_a[:, 1]).all())}"
        )


def calibrated_held_out(cap, d: float, mode: str | None):
    """Each model refines its own intensities (with ``mode``) on all images, then every light is
    left out in turn with that rig fixed. Returns both results and the mean raw and gain-free
    held-out errors of near and parallel."""
    rig = cap.rig()
    near = nplps.reconstruct(cap.images, rig, mask=cap.mask, depth=d, iterations=20, refine_lights=mode)
    par = nplps.reconstruct_parallel(cap.images, rig, mask=cap.mask, depth=d, refine_lights=mode)
    hn = held_out(cap.images, near.rig, mask=cap.mask, depth=d, method="near", iterations=20)
    hp = held_out(cap.images, par.rig, mask=cap.mask, depth=d, method="parallel")
    errors = {
        f"{field}_{model}": float(np.mean([getattr(h, f"{field}_error") for h in hs]))
        for model, hs in (("near", hn), ("parallel", hp))
        for field in ("relative", "shape")
    }
    return near, par, errors


def real_table() -> None:
    from nplps import captures

    if not SHARED.is_dir():
        print(f"\n(real captures skipped: {SHARED} not found)")
        return
    print(
        "\n## hehe12 (binned 4 x 4, distance 200 mm): calibrate intensities on all 8 images, then leave-one-light-out"
    )
    cap = captures.prepare(captures.load_hehe12(SHARED / "hehe12"), bin_factor=4)
    rig, d = cap.rig(), 200.0
    for mode in (None, "intensity"):
        near, par, e = calibrated_held_out(cap, d, mode)
        label = "light.mat intensities" if mode is None else "calibrated intensities"
        print(
            f"{label:23}: photometric RMS near {near.history[-1].rms_residual:.4f}, parallel "
            f"{par.history[-1].rms_residual:.4f}; held-out raw near {e['relative_near']:.4f}, "
            f"parallel {e['relative_parallel']:.4f} (gain-free shape: near "
            f"{e['shape_near']:.4f}, parallel {e['shape_parallel']:.4f})"
        )
        if mode:
            print(
                "  near-light intensities / light.mat's (both normalised to geometric mean 1):",
                np.round(relative(near.rig.intensities[:, 0]) / relative(rig.intensities[:, 0]), 3),
            )
            print(
                "  parallel-model intensities / light.mat's:",
                np.round(relative(par.rig.intensities[:, 0]) / relative(rig.intensities[:, 0]), 3),
            )
            se = near.refinement.standard_errors[:, 0]
            print(
                f"  standard errors of the near-light factors: {100 * se.min():.2f}..{100 * se.max():.2f} %; "
                f"singular values {np.round(near.refinement.singular_values, 4)}"
            )

    print("\n## queau_human1 (binned 8 x 8, 700 mm) and diligent_ball: with and without intensity refinement")
    cap = captures.prepare(captures.load_queau_human1(SHARED / "queau_human1"), bin_factor=8)
    for mode in (None, "intensity"):
        _, _, e = calibrated_held_out(cap, 700.0, mode)
        print(
            f"queau_human1 {mode!s:9}: held-out raw near {e['relative_near']:.4f}, "
            f"parallel {e['relative_parallel']:.4f}; shape near "
            f"{e['shape_near']:.4f}, parallel {e['shape_parallel']:.4f}"
        )
    ball = captures.load_diligent(SHARED / "diligent_ball", load=True)
    for mode in (None, "intensity"):
        r = nplps.reconstruct(ball.images, ball.rig(), mask=ball.mask, depth=1000.0, iterations=1, refine_lights=mode)
        err = angles(r.normals[ball.mask], ball.normals_gt[ball.mask]).mean()
        print(f"diligent_ball {mode!s:9}: mean normal error {err:.3f} deg")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--sections", default="intensity,cost,convergence,position,real")
    parser.add_argument("--ratio-sizes", type=int, nargs="+", default=[128, 256, 1024])
    parser.add_argument("--repeats", type=int, default=3, help="runs per case of the ratios (median)")
    parser.add_argument("--reflectances", nargs="+", default=["lambertian", "glossy"])
    args = parser.parse_args()
    sections = args.sections.split(",")
    if "intensity" in sections:
        intensity_table(min(args.seeds, 5))
    if "cost" in sections:
        cost_table()
    if "ratios" in sections:
        ratio_table(args.ratio_sizes, args.repeats, args.reflectances)
    if "convergence" in sections:
        convergence_traces()
    if "position" in sections:
        position_table(args.seeds)
    if "real" in sections:
        real_table()


if __name__ == "__main__":
    main()
