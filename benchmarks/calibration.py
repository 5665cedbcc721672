"""Accuracy of the light calibration on synthetic scenes (prints the acceptance table).

For each camera (orthographic, pinhole), light set (8 or 27 of the standard lights; all near, or
every third one distant) and sphere layout (two placements of one or of two spheres, moved with
the seed), and each seed:

1. renders the sphere scene (shiny spheres of radius 20 = 40 px orthographic, 44 px pinhole, on
   a dark board; 1 % noise, 8-bit, highlights saturated) and calibrates the lights
   (``nplps.calibrate.calibrate_spheres`` with the scene's masks; orthographic: the given
   centre depths);
2. renders a flat white board at the working distance under the true lights (1 % noise, 8-bit)
   and calibrates the intensities with the calibrated positions
   (``calibrate_intensities``);
3. reconstructs ``make_scene("bumps")`` (128 x 128, its true images) with the calibrated rig and
   with the true rig.

Columns: light-position error (RMS over the point lights, and the largest, in % of the
working distance 200), direction error of the distant lights (largest, degrees), intensity
error (relative intensities, both scaled to geometric mean 1: RMS and largest, %), mean normal
error against the ground truth with the true and with the calibrated rig, and the mean angle
between the two normal maps (degrees). The last row of each block gives the mean and the worst
over the seeds. A second table gives the intensity calibration alone, with the true positions
(isotropic lights, and LEDs with mu and directions fitted).

Usage: ``python benchmarks/calibration.py`` (seeds 0-9, about 80 s on 2 cores);
``--seeds 3`` for a quick run; ``--refine off`` to see the effect of the joint refinement;
``--outline images`` to use the image outlines instead of the masks, ``--outline detect`` to
detect the spheres (no masks).
"""

from __future__ import annotations

import argparse
import itertools
import time

import numpy as np

import nplps
from nplps import calibrate as cal
from nplps import synth_calibration as scenes

WORKING_DISTANCE = 200.0


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles in degrees between rows of unit vectors."""
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    return np.degrees(np.arctan2(cross, np.sum(a * b, axis=-1)))


def run_case(
    camera: str, lights: int, spheres: int, directional: bool, seed: int, refine: bool, outline: str, recon_n: int
) -> dict[str, float]:
    """One calibration + reconstruction; returns the measured errors."""
    scene = scenes.make_sphere_scene(
        camera, n=200, lights=lights, directional=directional, spheres=spheres, noise=0.01, seed=seed
    )
    t0 = time.perf_counter()
    depth = scene.center_depths if camera == "orthographic" else None
    if outline == "detect":
        res = cal.calibrate_spheres(
            scene.images, scene.rig, scene.radius, detect=(30.0, 60.0), count=spheres, center_depth=depth, refine=refine
        )
    else:
        res = cal.calibrate_spheres(
            scene.images,
            scene.rig,
            scene.radius,
            masks=scene.labels,
            center_depth=depth,
            refine=refine,
            outline=outline,
        )
    t_spheres = time.perf_counter() - t0
    truth = scene.rig
    missing = sum(light.kind == "missing" for light in res.lights)
    if missing:
        # No rig can be written (a light was seen on no sphere): count it as a failure.
        nan = float("nan")
        return {key: nan for _, key, _ in COLUMNS} | {"wrong_kind": missing, "seen_min": 0, "failed": 1}
    pos, dirs, wrong_kind = [], [], 0
    for light in res.lights:
        if truth.directional[light.index]:
            if light.kind == "directional":
                dirs.append(float(angle_deg(light.direction, truth.directions[light.index])))
            else:
                wrong_kind += 1
        else:
            if light.kind == "point":
                pos.append(float(np.linalg.norm(light.position - truth.positions[light.index])))
            else:
                wrong_kind += 1
    pos_a = np.array(pos)
    # Intensities from a board under the true lights, with the calibrated positions.
    board = scenes.make_board_scene(truth, n=200, noise=0.01, seed=seed + 1000, distance=WORKING_DISTANCE)
    t0 = time.perf_counter()
    icl = cal.calibrate_intensities(board.images, res.rig, WORKING_DISTANCE)
    t_board = time.perf_counter() - t0
    true_phi = truth.intensities.mean(axis=1)
    true_phi = true_phi / np.exp(np.mean(np.log(true_phi)))
    phi_err = 100.0 * (icl.intensities[:, 0] / true_phi - 1.0)
    # Reconstruction with the true and with the calibrated rig.
    obj = nplps.make_scene("bumps", n=recon_n, camera=camera, directional=directional, seed=seed)
    idx = scene.light_indices
    images = obj.images[idx]
    true_rig = obj.rig.subset(idx)
    cal_rig = nplps.Rig(camera=dict(obj.rig.camera), lights=icl.rig.lights)  # the reconstruction's own image size
    depth0 = obj.mean_depth
    r_true = nplps.reconstruct(images, true_rig, mask=obj.mask, depth=depth0, iterations=30, tol=1e-8)
    r_cal = nplps.reconstruct(images, cal_rig, mask=obj.mask, depth=depth0, iterations=30, tol=1e-8)
    m = obj.mask
    gt = obj.normals
    e_true = float(np.nanmean(angle_deg(r_true.normals[m], gt[m])))
    e_cal = float(np.nanmean(angle_deg(r_cal.normals[m], gt[m])))
    e_pair = float(np.nanmean(angle_deg(r_cal.normals[m], r_true.normals[m])))
    return {
        "pos_rms": 100.0 * float(np.sqrt(np.mean(pos_a**2))) / WORKING_DISTANCE if pos else float("nan"),
        "pos_max": 100.0 * float(pos_a.max()) / WORKING_DISTANCE if pos else float("nan"),
        "dir_max": max(dirs) if dirs else float("nan"),
        "wrong_kind": wrong_kind,
        "phi_rms": float(np.sqrt(np.mean(phi_err**2))),
        "phi_max": float(np.abs(phi_err).max()),
        "n_true": e_true,
        "n_cal": e_cal,
        "n_diff": e_cal - e_true,
        "n_pair": e_pair,
        "seen_min": min(light.spheres for light in res.lights),
        "t_spheres": t_spheres,
        "t_board": t_board,
        "failed": 0,
    }


def run_intensity(camera: str, led: bool, seed: int) -> dict[str, float]:
    """Intensity calibration alone, with the true light positions: a tilted white board at the
    working distance, 1 % noise, 8-bit; isotropic lights with intensities drawn in [0.65, 1.35]
    (and every third light distant), or LEDs (mu 0.5-2, unequal RGB intensities) with mu and
    directions fitted."""
    rig = scenes.standard_rig(camera, n=200, lights=27, directional=True, led=led)
    if not led:
        phi = np.random.default_rng(seed).uniform(0.65, 1.35, rig.n_lights)
        rig = rig.with_intensities(rig.intensities * phi[:, None])
    plane = ([0.05, -0.1, -1.0], -WORKING_DISTANCE)
    board = scenes.make_board_scene(rig, n=200, plane=plane, noise=0.01, seed=seed)
    start = nplps.Rig.from_arrays(rig.camera, rig.positions, directions=rig.directions)
    t0 = time.perf_counter()
    res = cal.calibrate_intensities(board.images, start, plane, fit_mu=led, fit_direction=led)
    elapsed = time.perf_counter() - t0
    truth = rig.intensities.mean(axis=1)
    truth = truth / np.exp(np.mean(np.log(truth)))
    err = 100.0 * (res.intensities[:, 0] / truth - 1.0)
    point = ~rig.directional
    return {
        "phi_rms": float(np.sqrt(np.mean(err**2))),
        "phi_max": float(np.abs(err).max()),
        "mu_max": float(np.abs(res.mu[point] - rig.mu[point]).max()) if led else float("nan"),
        "dir_max": float(angle_deg(res.axes[point], rig.axes[point]).max()) if led else float("nan"),
        "time": elapsed,
    }


COLUMNS = [
    ("pos RMS %WD", "pos_rms", "{:.3f}"),
    ("pos max %WD", "pos_max", "{:.3f}"),
    ("dir max °", "dir_max", "{:.3f}"),
    ("Φ RMS %", "phi_rms", "{:.3f}"),
    ("Φ max %", "phi_max", "{:.3f}"),
    ("normals true °", "n_true", "{:.3f}"),
    ("normals cal °", "n_cal", "{:.3f}"),
    ("cal − true °", "n_diff", "{:+.3f}"),
    ("cal vs true °", "n_pair", "{:.3f}"),
    ("min spheres", "seen_min", "{:.0f}"),
    ("wrong kind", "wrong_kind", "{:.0f}"),
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=10, help="seeds 0..N-1 (default 10)")
    parser.add_argument("--refine", choices=("on", "off"), default="on")
    parser.add_argument(
        "--outline",
        choices=("mask", "images", "detect"),
        default="mask",
        help="outline from the masks, the images (from the masks' circles), or detection",
    )
    parser.add_argument("--recon-n", type=int, default=128, help="reconstruction image size (default 128)")
    parser.add_argument("--cameras", nargs="+", default=["orthographic", "pinhole"])
    parser.add_argument("--lights", nargs="+", type=int, default=[8, 27])
    parser.add_argument("--spheres", nargs="+", type=int, default=[1, 2], help="spheres per placement")
    parser.add_argument(
        "--directional",
        nargs="+",
        choices=("no", "yes"),
        default=["no", "yes"],
        help="every third standard light distant (yes) or all point lights (no); default both",
    )
    args = parser.parse_args()
    print(
        f"nplps light calibration, seeds 0-{args.seeds - 1}, 200 x 200 px, sphere radius 20 (40 px), "
        f"1 % noise, 8-bit, two placements, joint refinement {args.refine}, outline from {args.outline}"
    )
    header = "| camera | lights | distant | spheres | seed | " + " | ".join(c[0] for c in COLUMNS) + " |"
    print()
    print(header)
    print("|" + "---|" * (5 + len(COLUMNS)))
    start = time.perf_counter()
    summary = []
    for camera, lights, far, spheres in itertools.product(args.cameras, args.lights, args.directional, args.spheres):
        rows = []
        distant = "1/3" if far == "yes" else "0"
        for seed in range(args.seeds):
            r = run_case(camera, lights, spheres, far == "yes", seed, args.refine == "on", args.outline, args.recon_n)
            rows.append(r)
            cells = " | ".join(fmt.format(r[key]) for _, key, fmt in COLUMNS)
            print(f"| {camera} | {lights} | {distant} | 2 x {spheres} | {seed} | {cells} |", flush=True)

        def stat(key: str, worst: bool, rows: list[dict] = rows) -> float:
            values = np.array([r[key] for r in rows], dtype=float)
            values = values[np.isfinite(values)]
            if values.size == 0:
                return float("nan")
            if not worst:
                return float(values.mean())
            return float(values.min() if key == "seen_min" else values.max())

        cells = " | ".join(
            f"{stat(k, False):.3f} / {fmt.format(stat(k, True))}"
            if ".0f" not in fmt
            else f"{stat(k, False):.1f} / {fmt.format(stat(k, True))}"
            for _, k, fmt in COLUMNS
        )
        failed = sum(r["failed"] for r in rows)
        note = f" ({failed} failed: a light seen on no sphere)" if failed else ""
        line = f"| **{camera}** | **{lights}** | **{distant}** | **2 x {spheres}** | **mean / worst{note}** | {cells} |"
        print(line, flush=True)
        summary.append(line)
    print()
    print("Intensity calibration alone (true positions; 200 x 200 tilted board, 1 % noise, 8-bit), mean / worst:")
    print("| camera | lights | Φ RMS % | Φ max % | μ max error | direction max ° | time s |")
    print("|---|---|---|---|---|---|---|")
    for camera in args.cameras:
        for led in (False, True):
            rows = [run_intensity(camera, led, seed) for seed in range(args.seeds)]

            def cell(k: str, f: str, rows: list[dict] = rows) -> str:
                return f"{np.mean([r[k] for r in rows]):{f}} / {np.max([r[k] for r in rows]):{f}}"

            kind = "LEDs (μ, directions fitted)" if led else "isotropic, 1/3 distant"
            print(
                f"| {camera} | {kind} | {cell('phi_rms', '.3f')} | {cell('phi_max', '.3f')} | "
                f"{cell('mu_max', '.3f')} | {cell('dir_max', '.2f')} | {cell('time', '.2f')} |",
                flush=True,
            )
    print()
    print("Summary (mean / worst over the seeds):")
    print(header)
    print("|" + "---|" * (5 + len(COLUMNS)))
    for line in summary:
        print(line)
    print(f"\nwall time {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
