"""Reconstruct the renders of ``benchmarks/pbr/render.py`` and print the errors against the truth.

    python benchmarks/pbr/run.py /work/pbr-data/256/*.npz
    python benchmarks/pbr/run.py /work/pbr-data/256/*.npz --opt robust=tukey --auto --json tukey.json
    python benchmarks/pbr/run.py /work/pbr-data/256/*.npz --opt reflectance=glossy --opt robust=tukey

``--opt key=value`` (repeatable) passes any keyword option to ``nplps.reconstruct``; the value is
read as JSON when it parses (numbers, true/false/null, lists), else as a string. Per file, a
markdown row: the mean and median normal error (degrees; the result's mesh normals against the
true facet normals inside the mask) and the depth RMS (mm, after the gauge: the result scaled so
that its geometric mean over the vertices the mask uses is the truth's) at the true distance;
with ``--auto`` also ``depth="auto"``: its mean normal error and the error of the distance it
found in percent; and the wall seconds of each run.

``--noise S`` adds Gaussian noise of S times each file's maximum (clipped at 0, as
``make_scene``), ``--seed`` its seed, ``--dark-sigmas K`` sets ``dark`` to K noise sigmas.
``--lights N`` uses the first N lights of each render (``render.py --lights 32`` renders hold
the 16- and 24-light rigs as their first lights, image for image). ``--oracle-shadows`` drops
the observations of pixels that lie partly or wholly in a true cast shadow (the renders'
``shadow`` array, as ``valid``): what a perfect shadow detection would give.

``--check`` compares the diffuse controls with ``nplps.render`` of the true surface (albedo
0.5): the median and 95th percentile of the relative difference over the lit observations, the
number of observations more than 5 % off (partial cast shadows within a pixel, the terminator),
and the mean normal error with those set to 0 (dropped as dark).
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from typing import Any

import numpy as np

import nplps


def angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Return the angles in degrees between unit vectors (..., 3)."""
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))


def used_vertices(mask: np.ndarray) -> np.ndarray:
    """Return the vertices (H+1, W+1) the mask's pixels use."""
    h, w = mask.shape
    used = np.zeros((h + 1, w + 1), dtype=bool)
    for dr in (0, 1):
        for dc in (0, 1):
            used[dr : dr + h, dc : dc + w] |= mask
    return used


def depth_rms(depth: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    """Return the RMS depth error after the pinhole gauge (geometric mean) is matched."""
    used = used_vertices(mask) & np.isfinite(depth)
    scale = np.exp(np.log(truth[used]).mean() - np.log(depth[used]).mean())
    return float(np.sqrt(np.mean((scale * depth[used] - truth[used]) ** 2)))


def parse_options(pairs: list[str]) -> dict[str, Any]:
    """Return the ``key=value`` pairs as keyword options (values as JSON when they parse)."""
    options: dict[str, Any] = {}
    for pair in pairs:
        key, sep, text = pair.partition("=")
        if not sep or not key:
            raise SystemExit(f"--opt takes key=value, got {pair!r}")
        try:
            options[key] = json.loads(text)
        except json.JSONDecodeError:
            options[key] = text
    return options


def reconstruct(data: Any, rig: nplps.Rig, depth: Any, options: dict[str, Any]) -> tuple[Any, float]:
    """Run ``nplps.reconstruct`` and return the result and the wall seconds."""
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = nplps.reconstruct(data["images"], rig, depth=depth, mask=data["mask"], **options)
    return result, time.perf_counter() - start


def lobe_of(result: Any) -> list[float] | None:
    """Return the result's glossy lobe ``[roughness, eta, retro]`` (None under the Lambertian model;
    ``retro`` 1 with the retro-reflective diffuse term, 0 with the transmitted one)."""
    lobe = getattr(result, "lobe", None)
    if lobe is None:
        return None
    return [float(lobe.roughness), float(lobe.eta), float(getattr(lobe, "diffuse", "") == "retro")]


def lobe_text(lobe: list[float] | None) -> str:
    """Return a lobe as ``roughness/eta``, ``roughness/eta/r`` with the retro-reflective diffuse
    term (``-`` without one)."""
    if lobe is None:
        return "-"
    return f"{lobe[0]:.3g}/{lobe[1]:.3g}" + ("/r" if len(lobe) > 2 and lobe[2] else "")


def prepare(data: dict[str, Any], args: argparse.Namespace, options: dict[str, Any]) -> dict[str, Any]:
    """Return the options with the true cast shadows as ``valid`` (if asked) and noisy images in `data`."""
    images = data["images"].astype(np.float32)
    if args.noise > 0:
        sigma = args.noise * float(images.max())
        rng = np.random.default_rng(args.seed)
        images = np.clip(images + rng.normal(0.0, sigma, images.shape), 0.0, None).astype(np.float32)
        if args.dark_sigmas is not None:
            options = {**options, "dark": args.dark_sigmas * sigma}
    data["images"] = images
    oracle = args.oracle_shadows
    if oracle:
        if "shadow" not in data:
            raise SystemExit("--oracle-shadows needs renders with the 'shadow' array")
        options = {**options, "valid": data["shadow"] == 0}
    return options


def check(data: Any, rig: nplps.Rig, options: dict[str, Any]) -> dict[str, float]:
    """Compare a diffuse render with ``nplps.render`` of the true surface (see the module doc)."""
    mask, images = data["mask"], data["images"].astype(np.float64)
    reference = nplps.render(data["depth"], rig, 0.5, mask=mask)
    lit = mask[None] & (reference > 1e-3 * reference.max()) & (images > 0)
    relative = images[lit] / reference[lit] - 1
    off = mask[None] & (np.abs(images - reference) > 0.05 * reference) & (images > 0)
    result, _ = reconstruct({**data, "images": np.where(off, 0.0, images)}, rig, float(data["distance"]), options)
    return {
        "median_relative": float(np.median(relative)),
        "p95_relative": float(np.percentile(np.abs(relative), 95)),
        "off_5pc": int(off.sum()),
        "observations": int(lit.sum()),
        "normals_mean_without_off": float(angles(result.normals[mask], data["normals"][mask]).mean()),
    }


def main() -> None:
    """Reconstruct every file and print the table."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("files", nargs="+")
    parser.add_argument("--opt", action="append", default=[], help="key=value, an option of nplps.reconstruct")
    parser.add_argument("--auto", action="store_true", help='also run depth="auto"')
    parser.add_argument("--check", action="store_true", help="compare diffuse controls with nplps.render")
    parser.add_argument("--noise", type=float, default=0.0, help="Gaussian noise, a fraction of the maximum")
    parser.add_argument("--seed", type=int, default=0, help="of the noise")
    parser.add_argument("--dark-sigmas", type=float, help="with --noise: dark = this many noise sigmas")
    parser.add_argument(
        "--oracle-shadows", action="store_true", help="drop the observations in a true cast shadow (valid=)"
    )
    parser.add_argument(
        "--lights",
        type=int,
        help="use the first N lights of each render (16 or 24 of a 32-light one: its first rings)",
    )
    parser.add_argument("--json", help="write the numbers to this file")
    args = parser.parse_args()
    shared = parse_options(args.opt)
    extra = f", noise {args.noise}" if args.noise else ""
    extra += f", dark {args.dark_sigmas} sigmas" if args.noise and args.dark_sigmas is not None else ""
    extra += ", true cast shadows dropped" if args.oracle_shadows else ""
    print(f"options: {shared or 'defaults'}{extra}\n")
    header = "| scene | material | size | mean (deg) | median (deg) | depth RMS (mm) | lobe | s |"
    if args.auto:
        header += " auto mean (deg) | auto distance error | auto lobe | auto s |"
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    rows = []
    for path in args.files:
        with np.load(path) as f:
            data = dict(f)
        rig = nplps.Rig.from_dict(json.loads(str(data["rig"])))
        if args.lights is not None:
            if not 0 < args.lights <= len(rig.lights):
                raise SystemExit(f"--lights {args.lights}: {path} has {len(rig.lights)} lights")
            rig = rig.subset(list(range(args.lights)))
            for key in ("images", "shadow"):
                if key in data:
                    data[key] = data[key][: args.lights]
        options = prepare(data, args, shared)
        mask, truth = data["mask"], data["normals"]
        distance = float(data["distance"])
        known, seconds = reconstruct(data, rig, distance, options)
        error = angles(known.normals[mask], truth[mask])
        row: dict[str, Any] = {
            "file": path,
            "shape": str(data.get("shape", "?")),
            "material": str(data["material"]),
            "size": int(mask.shape[0]),
            "pixels": int(mask.sum()),
            "options": {key: value for key, value in options.items() if key != "valid"},
            "lights": len(rig.lights),
            "noise": args.noise,
            "dark": options.get("dark"),
            "oracle_shadows": args.oracle_shadows,
            "mean_deg": float(error.mean()),
            "median_deg": float(np.median(error)),
            "depth_rms_mm": depth_rms(known.depth, data["depth"], mask),
            "seconds": seconds,
            "status": str(known.status),
            "lobe": lobe_of(known),
        }
        line = (
            f"| {row['shape']} | {row['material']} | {row['size']} | {row['mean_deg']:.3f} | "
            f"{row['median_deg']:.3f} | {row['depth_rms_mm']:.3f} | {lobe_text(row['lobe'])} | {seconds:.1f} |"
        )
        if args.auto:
            auto, auto_seconds = reconstruct(data, rig, "auto", options)
            found = float(auto.distance.distance[0]) if auto.distance is not None else float("nan")
            row.update(
                auto_mean_deg=float(angles(auto.normals[mask], truth[mask]).mean()),
                auto_distance=found,
                auto_distance_error_pc=100 * (found / distance - 1),
                auto_seconds=auto_seconds,
                auto_lobe=lobe_of(auto),
            )
            line += (
                f" {row['auto_mean_deg']:.3f} | {row['auto_distance_error_pc']:+.2f} % | "
                f"{lobe_text(row['auto_lobe'])} | {auto_seconds:.1f} |"
            )
        print(line, flush=True)
        if args.check and row["material"] == "diffuse":
            row["check"] = check(data, rig, options)
        rows.append(row)
    checks = [row for row in rows if "check" in row]
    if checks:
        print("\n| control | vs nplps.render: median | p95 abs | obs > 5 % off | mean (deg) without them |")
        print("|---|---|---|---|---|")
        for row in checks:
            c = row["check"]
            print(
                f"| {row['shape']} {row['size']} | {c['median_relative']:+.1e} | {c['p95_relative']:.1e} | "
                f"{c['off_5pc']} of {c['observations']} | {c['normals_mean_without_off']:.3f} |"
            )
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
