"""Which normals to hand users: the local fits (``result.fit_normals``) or the mesh's own
(``result.normals``)? Issue 10's measurement, which made the mesh's the default ``normals``.

    python benchmarks/normals.py [--quick] [--seeds 5] [--no-ball] [--json out.json]

For every case it reconstructs with the default options of :func:`nplps.reconstruct` at the true
gauge (``scene.mean_depth``) and measures, against the ground truth, the angular error (degrees)
of

- local: ``result.fit_normals``, each pixel's own least-squares fit of the final local step;
- mesh: ``result.normals``, the facet normals of the integrated depth (cross product of the
  quad's diagonals),

over the fitted masked pixels (masked, at least 3 usable lights, both normals and the truth
finite). Synthetic ground truth is ``scene.normals``: the true mesh's facet normals, which are
also the normals the renderer shades with.

Cases (synthetic; means over seeds 0..N-1, the worst seed's mean alongside):

- noise: scenes saddle, sphere, bumps and cube (two faces meeting at a sharp edge that lies on a
  pixel line, so the true mesh holds it exactly), 128 x 128, orthographic and pinhole cameras,
  Gaussian image noise 0, 0.5, 1 and 2 % of the maximum intensity, exact lights;
- lights: the same with every point light moved by a seeded random offset of 5 % of the working
  distance (RMS length; the rig handed to the reconstruction is wrong, the images are not);
- size: bumps, 256 x 256, pinhole, 1 % noise, exact and wrong lights;
- led: anisotropic LEDs with unequal RGB intensities and colour albedo, pinhole, 1 % noise;
- where: for the orthographic cases at noise 0 and 1 %, exact and wrong lights, the errors split
  into interior pixels, the boundary band (within 2 pixels of the mask's edge or the image's)
  and bend pixels (whose true normal differs from a 4-neighbour's by more than 5 degrees: the
  cube's edge, the bumps' steep flanks, the ball's rim; band and bends may overlap, the interior
  is neither);
- ball: DiLiGenT's ball (directional lights, 96 RGB images, ``Normal_gt.mat``) from
  ``../shared/data/diligent_ball`` (skipped with a message when absent or scipy is missing), at a
  distance of 1000 pixel units (immaterial for directional lights), with all 96 lights and with
  every 7th (14 lights).

Each table row is one case group; the verdict counts the groups where one kind of normals has the
lower mean error (averaged over seeds; differences under 0.005 degrees are ties) and by how much,
over all groups and separately with and without image noise and on real data. ``--quick`` runs
2 seeds, noise 0 and 1 % and leaves out the size and LED groups.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

import nplps

#: make_scene's default working distance (its lights are placed for it).
DISTANCE = 200.0
SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SCENES = ("saddle", "sphere", "bumps", "cube")
CAMERAS = ("orthographic", "pinhole")
#: Differences of mean error below this (degrees) count as ties in the verdict.
TIE = 0.005


def angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles in degrees between the rows of a and b (any lengths)."""
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))


def wrong_lights(rig: nplps.Rig, seed: int, fraction: float) -> nplps.Rig:
    """The rig with every point light moved by a random offset of RMS length ``fraction * DISTANCE``
    (as in benchmarks/refine_lights.py); directional lights are left alone."""
    rng = np.random.default_rng(1000 + seed)
    shift = rng.normal(size=rig.positions.shape) * fraction * DISTANCE / np.sqrt(3.0)
    return rig.with_positions(rig.positions + shift)  # NaN rows (directional lights) stay NaN


def boundary_band(mask: np.ndarray, width: int = 2) -> np.ndarray:
    """Masked pixels within ``width`` pixels (chessboard distance) of an unmasked pixel or the
    image's edge."""
    inside = np.pad(mask, width, constant_values=False)
    h, w = mask.shape
    core = np.ones_like(mask)
    for dr in range(-width, width + 1):
        for dc in range(-width, width + 1):
            core &= inside[width + dr : width + dr + h, width + dc : width + dc + w]
    return mask & ~core


def bends(truth: np.ndarray, mask: np.ndarray, degrees: float = 5.0) -> np.ndarray:
    """Masked pixels whose true normal differs from a masked 4-neighbour's by more than
    ``degrees``."""
    out = np.zeros_like(mask)
    for axis in (0, 1):
        a = [slice(None), slice(None)]
        b = [slice(None), slice(None)]
        a[axis], b[axis] = slice(None, -1), slice(1, None)
        a, b = tuple(a), tuple(b)
        both = mask[a] & mask[b]
        with np.errstate(invalid="ignore"):
            bent = both & (angles(truth[a], truth[b]) > degrees)
        out[a] |= bent
        out[b] |= bent
    return out


def measure(result: nplps.Reconstruction, truth: np.ndarray, mask: np.ndarray) -> dict[str, Any]:
    """Mean and median errors of the local and the mesh normals over the fitted masked pixels,
    and the mean errors on the interior, the boundary band and the bend pixels."""
    local, mesh = result.fit_normals, result.normals
    fitted = (
        mask
        & (result.lights_used >= 3)
        & np.isfinite(local).all(-1)
        & np.isfinite(mesh).all(-1)
        & np.isfinite(truth).all(-1)
        & (np.linalg.norm(np.nan_to_num(truth), axis=-1) > 0)
    )
    err = {"local": angles(local, truth), "mesh": angles(mesh, truth)}
    band = boundary_band(mask)
    bend = bends(truth, mask)
    parts = {"interior": fitted & ~band & ~bend, "boundary": fitted & band, "bend": fitted & bend}
    out: dict[str, Any] = {"pixels": int(fitted.sum()), "masked": int(mask.sum()), "status": result.status}
    for kind, e in err.items():
        out[kind] = {"mean": float(e[fitted].mean()), "median": float(np.median(e[fitted]))}
        for part, sel in parts.items():
            out[kind][part] = float(e[sel].mean()) if sel.any() else None
        out[kind]["pixels"] = {part: int(sel.sum()) for part, sel in parts.items()}
    return out


def synthetic_case(
    name: str,
    camera: str,
    noise: float,
    light_error: float,
    seeds: range,
    n: int = 128,
    led: bool = False,
    rgb: bool = False,
) -> dict[str, Any]:
    runs = []
    for seed in seeds:
        scene = nplps.make_scene(name, n=n, seed=seed, noise=noise, camera=camera, led=led, rgb=rgb)
        rig = wrong_lights(scene.rig, seed, light_error) if light_error > 0 else scene.rig
        result = nplps.reconstruct(scene.images, rig, mask=scene.mask, depth=scene.mean_depth)
        runs.append({"seed": seed, **measure(result, scene.normals, scene.mask)})
    return {
        "scene": name,
        "camera": camera,
        "n": n,
        "noise": noise,
        "light_error": light_error,
        "led": led,
        "rgb": rgb,
        "runs": runs,
        **summarize(runs),
    }


def summarize(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Means over the runs, and the worst run's mean error, of each kind of normals."""
    out: dict[str, Any] = {}
    for kind in ("local", "mesh"):
        means = [r[kind]["mean"] for r in runs]
        out[kind] = {
            "mean": float(np.mean(means)),
            "median": float(np.mean([r[kind]["median"] for r in runs])),
            "worst": float(np.max(means)),
            "worst_seed": runs[int(np.argmax(means))].get("seed"),
        }
        for part in ("interior", "boundary", "bend"):
            values = [r[kind][part] for r in runs if r[kind][part] is not None]
            out[kind][part] = float(np.mean(values)) if values else None
    out["mesh_minus_local"] = out["mesh"]["mean"] - out["local"]["mean"]
    out["not_converged"] = sum(r["status"] != "converged" for r in runs)
    return out


def ball_cases() -> list[dict[str, Any]]:
    """DiLiGenT's ball with all 96 lights and with every 7th (14 lights: less averaging per
    pixel; every 8th would leave the lights nearly in one plane)."""
    folder = SHARED / "diligent_ball"
    if not folder.is_dir():
        print(f"\n(DiLiGenT ball skipped: {folder} not found)")
        return []
    try:
        import scipy  # noqa: F401  (Normal_gt.mat)
    except ImportError:
        print("\n(DiLiGenT ball skipped: scipy is needed to read Normal_gt.mat)")
        return []
    ball = nplps.captures.load_diligent(folder, load=True)
    if ball.normals_gt is None or ball.mask is None:
        print("\n(DiLiGenT ball skipped: no Normal_gt.mat or mask.png)")
        return []
    cases = []
    for capture in (ball, ball.select(range(0, ball.num_images, 7))):
        result = nplps.reconstruct(capture.images, capture.rig(), mask=capture.mask, depth=1000.0)
        run = measure(result, capture.normals_gt, capture.mask)
        cases.append(
            {
                "scene": f"DiLiGenT ball, {capture.num_images} lights",
                "camera": "orthographic",
                "n": list(capture.mask.shape),
                "noise": None,
                "light_error": 0.0,
                "runs": [run],
                **summarize([run]),
            }
        )
    return cases


# -- printing --------------------------------------------------------------------------------------
def label(case: dict[str, Any]) -> str:
    parts = [case["scene"]]
    if isinstance(case["n"], int) and case["n"] != 128:
        parts.append(f"{case['n']}²")
    if case.get("led"):
        parts.append("LED RGB")
    return " ".join(parts)


def fmt(v: float | None, digits: int = 2) -> str:
    return "–" if v is None else f"{v:.{digits}f}"


def table(title: str, cases: list[dict[str, Any]]) -> None:
    print(f"\n## {title}\n")
    print(
        "| case | camera | noise | lights off | local mean | local median | local worst | "
        "mesh mean | mesh median | mesh worst | mesh − local | better |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for c in cases:
        lo, me, d = c["local"], c["mesh"], c["mesh_minus_local"]
        better = "tie" if abs(d) < TIE else ("mesh" if d < 0 else "local")
        noise = "–" if c["noise"] is None else f"{100 * c['noise']:g} %"
        flag = f" ({c['not_converged']} not converged)" if c["not_converged"] else ""
        print(
            f"| {label(c)}{flag} | {c['camera'][:5]} | {noise} | {100 * c['light_error']:g} % | "
            f"{fmt(lo['mean'])} | {fmt(lo['median'])} | {fmt(lo['worst'])} | "
            f"{fmt(me['mean'])} | {fmt(me['median'])} | {fmt(me['worst'])} | {d:+.2f} | {better} |"
        )


def where_table(cases: list[dict[str, Any]]) -> None:
    print("\n## Where the errors are (mean error in degrees, means over seeds; local / mesh)\n")
    print(
        "| case | camera | noise | lights off | interior | boundary band (2 px) | bend (> 5° to a neighbour) | "
        "pixels interior / band / bend |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for c in cases:
        lo, me = c["local"], c["mesh"]
        px = c["runs"][0]["local"]["pixels"]
        cells = [f"{fmt(lo[p])} / {fmt(me[p])}" for p in ("interior", "boundary", "bend")]
        noise = "–" if c["noise"] is None else f"{100 * c['noise']:g} %"
        print(
            f"| {label(c)} | {c['camera'][:5]} | {noise} | {100 * c['light_error']:g} % | "
            f"{' | '.join(cells)} | {px['interior']} / {px['boundary']} / {px['bend']} |"
        )


def case_name(c: dict[str, Any]) -> str:
    noise = "" if c["noise"] is None else f" noise {100 * c['noise']:g} %"
    return f"{label(c)} {c['camera'][:5]}{noise} lights {100 * c['light_error']:g} %"


def spread(v: np.ndarray, digits: int = 2) -> str:
    """ "a" for one value, else "min to max (median m)"."""
    if len(v) == 1:
        return f"{v[0]:.{digits}f}"
    return f"{v.min():.{digits}f} to {v.max():.{digits}f} (median {np.median(v):.{digits}f})"


def verdict(cases: list[dict[str, Any]], title: str, list_local: bool = True) -> list[str]:
    """Lines saying in how many of ``cases`` each kind of normals has the lower mean error, and by
    how much (degrees, and the ratio mesh error / local error)."""
    if not cases:
        return []
    d = np.array([c["mesh_minus_local"] for c in cases])
    ratio = np.array([c["mesh"]["mean"] / max(c["local"]["mean"], 1e-300) for c in cases])
    mesh, local = d < -TIE, d > TIE
    medians = np.array([c["mesh"]["median"] - c["local"]["median"] for c in cases])
    lines = [f"{title}: {len(cases)} case group{'s' if len(cases) > 1 else ''}"]
    if mesh.any():
        lines.append(
            f"  mesh normals more accurate in {mesh.sum()}: by {spread(-d[mesh])} degrees; "
            f"error ratio mesh/local {spread(ratio[mesh])}"
        )
    if local.any():
        worse = [case_name(c) for c, w in zip(cases, local, strict=False) if w]
        lines.append(
            f"  local normals more accurate in {local.sum()}: by {spread(d[local], 3)} degrees; "
            f"error ratio mesh/local {spread(ratio[local])}" + (" — " + "; ".join(worse) if list_local else "")
        )
    ties = len(cases) - mesh.sum() - local.sum()
    if ties:
        lines.append(f"  ties (|difference| < {TIE} degrees): {ties}")
    lines.append(f"  by median error: mesh better in {(medians < -TIE).sum()}, local better in {(medians > TIE).sum()}")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="2 seeds, noise 0 and 1 %%, no size or LED groups")
    parser.add_argument("--seeds", type=int, default=None, help="number of seeds (default 5; 2 with --quick)")
    parser.add_argument("--json", type=Path, default=None, help="write every case and run to this file")
    parser.add_argument("--no-ball", action="store_true", help="skip the DiLiGenT ball")
    args = parser.parse_args(argv)
    seeds = range(args.seeds if args.seeds is not None else (2 if args.quick else 5))
    if len(seeds) < 1:
        parser.error("--seeds must be at least 1")
    noises = (0.0, 0.01) if args.quick else (0.0, 0.005, 0.01, 0.02)

    groups: dict[str, list[dict[str, Any]]] = {}

    def run(group: str, *a: Any, **kw: Any) -> None:
        groups.setdefault(group, []).append(synthetic_case(*a, seeds=seeds, **kw))
        print(".", end="", file=sys.stderr, flush=True)

    for camera in CAMERAS:
        for name in SCENES:
            for noise in noises:
                run("noise", name, camera, noise, 0.0)
    for camera in CAMERAS:
        for name in SCENES:
            for noise in noises:
                run("lights", name, camera, noise, 0.05)
    if not args.quick:
        for light_error in (0.0, 0.05):
            run("size", "bumps", "pinhole", 0.01, light_error, n=256)
        for name in SCENES:
            run("led", name, "pinhole", 0.01, 0.0, led=True, rgb=True)
    print(file=sys.stderr)

    titles = {
        "noise": "Exact lights, 128 x 128: noise sweep",
        "lights": "Point lights off by 5 % of the working distance (RMS), 128 x 128",
        "size": "Bumps, 256 x 256, pinhole, 1 % noise",
        "led": "Anisotropic LEDs, unequal RGB intensities, colour albedo, pinhole, 1 % noise, 128 x 128",
    }
    print(
        f"Angular error of the normals against ground truth, degrees; seeds 0..{len(seeds) - 1} "
        "(mean = average over seeds of each run's mean; worst = the largest run mean)."
    )
    for key, title in titles.items():
        if key in groups:
            table(title, groups[key])
    where_table(
        [
            c
            for key in ("noise", "lights")
            for c in groups[key]
            if c["camera"] == "orthographic" and c["noise"] in (0.0, 0.01)
        ]
    )
    ball = [] if args.no_ball else ball_cases()
    if ball:
        groups["ball"] = ball
        table("DiLiGenT ball (directional lights, RGB, default options)", ball)
        where_table(ball)

    cases = [c for group in groups.values() for c in group]
    synthetic = [c for c in cases if c["noise"] is not None]
    print("\n## Verdict (mean angular error, averaged over seeds)\n")
    lines = verdict(cases, "All", list_local=False)
    lines += verdict([c for c in synthetic if c["noise"] > 0], "Synthetic with image noise")
    lines += verdict([c for c in synthetic if c["noise"] == 0], "Synthetic without noise")
    lines += verdict([c for c in cases if c["noise"] is None], "Real (DiLiGenT ball)")
    print("\n".join(lines))
    if args.json is not None:
        args.json.write_text(json.dumps({"seeds": len(seeds), "groups": groups}, indent=1))
        print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
