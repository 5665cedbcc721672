"""The default shadow threshold: ``dark=0`` against 3 sigma of the noise estimate (issue 20, item 3).

    python benchmarks/dark.py [--seeds 5] [--n 96]

For each case and seed it renders ``nplps.make_scene(scene, n=n, camera="pinhole", noise=noise,
seed=s)`` (the block with ``shadows=True``: its cast shadows are zeros before the noise), then
reconstructs at the true gauge (``scene.mean_depth``) with ``dark=0`` and with the default
(``dark=None``: 3 sigma of :func:`nplps.estimate_noise`), and prints the medians over the seeds of

- sigma: the estimate over the true noise (``noise * max`` of the clean render), 0 for noise-free
  scenes;
- dark: the default threshold, as a fraction of the image maximum;
- err0 / err: the mean angle (degrees) between ``result.normals[mask]`` and ``scene.normals[mask]``
  with ``dark=0`` and with the default.

Noise-free scenes must estimate exactly 0 and give results bit-identical to ``dark=0`` (the column
"same"); the script exits with status 1 otherwise.
"""

from __future__ import annotations

import argparse
import sys
import warnings

import numpy as np

import nplps

CASES = [
    ("block", 0.005),
    ("block", 0.01),
    ("block", 0.002),
    ("sphere", 0.005),
    ("bumps", 0.005),
    ("sphere", 0.0),
    ("bumps", 0.0),
    ("block", 0.0),
]


def angle(a: np.ndarray, b: np.ndarray) -> float:
    """Mean angle in degrees between two arrays of unit vectors (N, 3)."""
    cos = np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)).mean())


def run(name: str, noise: float, seed: int, n: int) -> dict[str, float]:
    shadows = name == "block"
    scene = nplps.make_scene(name, n=n, camera="pinhole", noise=noise, seed=seed, shadows=shadows)
    clean = nplps.make_scene(name, n=n, camera="pinhole", seed=seed, shadows=shadows).images
    kw = {"depth": scene.mean_depth, "mask": scene.mask, "progress": False}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r0 = nplps.reconstruct(scene.images, scene.rig, dark=0.0, **kw)
        r1 = nplps.reconstruct(scene.images, scene.rig, **kw)
    m = scene.mask
    truth = scene.normals[m]
    top = float(clean.max())
    sigma = float(r1.noise or 0.0)
    return {
        "sigma": sigma / (noise * top) if noise else sigma,
        "dark": float(r1.dark or 0.0) / float(scene.images.max()),
        "err0": angle(r0.normals[m], truth),
        "err": angle(r1.normals[m], truth),
        "same": float(
            np.array_equal(r0.depth, r1.depth, equal_nan=True)
            and np.array_equal(r0.normals, r1.normals, equal_nan=True)
        ),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--n", type=int, default=96)
    args = parser.parse_args(argv)
    print(f"pinhole, n={args.n}, medians over seeds 0..{args.seeds - 1}; errors in degrees")
    header = (
        f"{'scene':8} {'noise':>6} {'sigma/true':>10} {'dark/max':>9} {'err dark=0':>11} "
        f"{'err default':>12} {'gain':>7} {'same':>5}"
    )
    print(header)
    print("-" * len(header))
    ok = True
    for name, noise in CASES:
        rows = [run(name, noise, s, args.n) for s in range(args.seeds)]
        med = {k: float(np.median([r[k] for r in rows])) for k in rows[0]}
        same = all(r["same"] == 1.0 for r in rows)
        if noise == 0 and not (same and all(r["sigma"] == 0 for r in rows)):
            ok = False
        print(
            f"{name:8} {noise:6.3f} {med['sigma']:10.3f} {med['dark']:9.4f} {med['err0']:11.3f} "
            f"{med['err']:12.3f} {med['err0'] - med['err']:7.3f} {('yes' if same else 'no'):>5}"
        )
    if not ok:
        print("noise-free scenes did not keep dark = 0 and the same result", file=sys.stderr)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
