"""The interreflection baseline (issue 21): indirect light in the GI renders and today's errors on them.

    python benchmarks/pbr/render.py --gi --size 256 --spp 256 --out-dir /work/pbr-data/gi
    python benchmarks/pbr/indirect.py /work/pbr-data/gi            # every *-gi-*.npz with its twin
    python benchmarks/pbr/indirect.py /work/pbr-data/gi --json indirect.json --opt robust=tukey
    python benchmarks/pbr/indirect.py /work/pbr-data/gi --cost --repeats 2 --synthetic 1024 --memory

For each pair of renders of ``render.py --gi`` (``SHAPE-MATERIAL-gi-SIZE.npz``, path traced with
global illumination, and its direct-only twin ``SHAPE-MATERIAL-direct-SIZE.npz``: the same
surface, rig, material and spp, ``max_depth`` 2) a markdown row:

- the indirect share of the lit observations: (GI - direct) / GI per observation, its mean and
  90th percentile, and the share of the total energy, sum(GI - direct) / sum(GI). Lit: inside
  the mask and the direct render above 1e-3 of its maximum (attached and cast shadows left out:
  there the share is 1, and ``dark=0`` keeps them anyway);
- ``nplps.reconstruct`` with the default options (or ``--opt key=value``, as ``run.py``) at the
  true distance, on the GI render and on its direct twin (the control): the mean and median
  normal error in degrees (``run.py``'s measure: the result's mesh normals against the true
  facet normals inside the mask) and the albedo error, the median of albedo / true albedo - 1 in
  percent (the true albedo is the material's diffuse reflectance);
- the shadowed observations: the share of the mask's observations that the direct twin leaves
  unlit (attached and cast shadows, at most 1e-3 of its maximum) but that indirect light makes
  brighter than that in the GI render, so that ``dark=0`` keeps them; and the GI mean normal
  error with those left out (``valid=``, an oracle: the twin's shadows are not known in a real
  capture) — the error that remains comes from the indirect light in the lit observations;
- ``depth="auto"`` on the GI render: the mean normal error and the error of the distance it found
  in percent.

The errors are those of ``run.py`` (its helpers are imported, not copied).

``--cost`` measures instead what ``interreflections=True`` costs (issue 21's acceptance: at most
4x a default run at 256² and at 1 MP, peak memory at most +30 %): on every GI render, and on a
synthetic bowl of ``--synthetic N`` pixels a side (``render.py``'s bowl surface and 16-light rig,
rendered by ``nplps.render`` with its cast shadows, plus the indirect light of the 256² GI bowl
render, ``GI - direct``, upsampled, when the pair is among the paths), ``--repeats`` runs of each
configuration alternating in one process (wall seconds: medians; the ratio is of the medians),
with the seconds the solver spent on the indirect light (``timings["indirect"]``); ``--memory``
adds the peak RSS of one run of each in a fresh process (on Linux from the call on: the peak is
reset after the case is loaded or made).
"""

from __future__ import annotations

import argparse
import json
import re
import resource
import subprocess
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from render import bowl_surface, facet_normals, make_rig, mean_depth, reflectance  # benchmarks/pbr/render.py
from run import angles, depth_rms, parse_options, reconstruct  # benchmarks/pbr/run.py

import nplps

NAME = re.compile(r"(?P<scene>.+)-gi-(?P<size>\d+)\.npz$")


def load(path: Path) -> tuple[dict[str, Any], nplps.Rig]:
    """Return the arrays of a render (images as float32) and its rig."""
    with np.load(path) as f:
        data = dict(f)
    data["images"] = data["images"].astype(np.float32)
    return data, nplps.Rig.from_dict(json.loads(str(data["rig"])))


def true_albedo(data: dict[str, Any]) -> float:
    """Return the true albedo of a render: its stored reflectance, else its material's."""
    return float(data["reflectance"]) if "reflectance" in data else reflectance(str(data["material"]))


def lit(direct: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Return the observations (k, H, W) the direct twin lights: inside the mask, above 1e-3 of its maximum."""
    return mask[None] & (direct > 1e-3 * direct.max())


def indirect_share(gi: np.ndarray, direct: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """Return the share of indirect light in the lit observations and the shadowed ones it lights (module doc)."""
    on = lit(direct, mask)
    g, d = gi[on].astype(np.float64), direct[on].astype(np.float64)
    share = (g - d) / np.maximum(g, 1e-12)
    shadowed = mask[None] & ~on & (gi > 1e-3 * direct.max())
    return {
        "share_mean": float(share.mean()),
        "share_p90": float(np.percentile(share, 90)),
        "share_energy": float((g - d).sum() / g.sum()),
        "lit_observations": int(on.sum()),
        "shadowed_lit_by_gi": float(shadowed.sum() / (mask.sum() * len(gi))),
    }


def errors(data: dict[str, Any], rig: nplps.Rig, depth: Any, options: dict[str, Any]) -> dict[str, float]:
    """Return the normal, albedo and depth errors of one reconstruction (and the distance it used)."""
    mask = data["mask"]
    result, seconds = reconstruct(data, rig, depth, options)
    error = angles(result.normals[mask], data["normals"][mask])
    albedo = np.asarray(result.albedo)[mask] / true_albedo(data) - 1
    out = {
        "mean_deg": float(error.mean()),
        "median_deg": float(np.median(error)),
        "albedo_pc": float(100 * np.median(albedo)),
        "depth_rms_mm": depth_rms(result.depth, data["depth"], mask),
        "seconds": seconds,
        "status": str(result.status),
    }
    if result.distance is not None:
        found = float(result.distance.distance[0])
        out.update(distance=found, distance_error_pc=100 * (found / float(data["distance"]) - 1))
    return out


def gi_files(paths: list[Path]) -> list[Path]:
    """Return the GI renders among the given files or directories."""
    files: list[Path] = []
    for path in paths:
        files.extend(sorted(path.glob("*-gi-*.npz")) if path.is_dir() else [path])
    return [f for f in files if NAME.search(f.name)]


def pairs(paths: list[Path]) -> list[tuple[Path, Path]]:
    """Return the (GI, direct twin) pairs among the given files or directories."""
    found = []
    for gi in gi_files(paths):
        match = NAME.search(gi.name)
        if not match:
            continue
        twin = gi.with_name(f"{match['scene']}-direct-{match['size']}.npz")
        if not twin.exists():
            raise SystemExit(f"{gi}: its direct twin {twin.name} is missing")
        found.append((gi, twin))
    if not found:
        raise SystemExit("no SHAPE-MATERIAL-gi-SIZE.npz among the given paths")
    return found


def synthetic_bowl(n: int, paths: list[Path]) -> dict[str, Any]:
    """Return a synthetic GI bowl of n x n pixels (see the module doc) as a render's arrays."""
    depth, mask = bowl_surface(n)
    rig = make_rig(n)
    images = nplps.render(depth, rig, 0.5, mask=mask, shadows=True).astype(np.float32)
    indirect = "none"
    for gi_path in gi_files(paths):
        direct_path = gi_path.with_name(gi_path.name.replace("-gi-", "-direct-"))
        if gi_path.name == "bowl-diffuse-gi-256.npz" and n % 256 == 0 and direct_path.exists():
            gi, _ = load(gi_path)
            direct, _ = load(direct_path)
            extra = np.clip(gi["images"] - direct["images"], 0.0, None) * gi["mask"][None]
            f = n // 256
            images += np.repeat(np.repeat(extra, f, axis=1), f, axis=2) * mask[None]
            indirect = gi_path.name
    return {
        "images": images,
        "mask": mask,
        "rig": json.dumps(rig.to_dict()),
        "distance": mean_depth(depth, mask),
        "normals": facet_normals(depth, n),
        "name": f"synthetic bowl {n}² (indirect: {indirect})",
    }


def cost_cases(args: argparse.Namespace) -> list[tuple[str, dict[str, Any], nplps.Rig]]:
    """Return the cases of ``--cost``: (name, arrays, rig); with ``--child``, only that one is loaded."""
    cases: list[tuple[str, dict[str, Any], nplps.Rig]] = []
    empty: tuple[dict[str, Any], nplps.Rig] = ({}, make_rig(2))

    def wanted(i: int) -> bool:
        return args.child is None or i == args.child

    files = gi_files(args.paths)
    for i, gi_path in enumerate(files):
        data, rig = load(gi_path) if wanted(i) else empty
        cases.append((gi_path.name, data, rig))
    for i, n in enumerate(args.synthetic, start=len(files)):
        if wanted(i):
            data = synthetic_bowl(n, args.paths)
            cases.append((data["name"], data, nplps.Rig.from_dict(json.loads(data["rig"]))))
        else:
            cases.append(("", *empty))
    return cases


def timed(data: dict[str, Any], rig: nplps.Rig, options: dict[str, Any]) -> tuple[float, float, int, float, float]:
    """Return the wall seconds, the seconds on the indirect light, the iterations, the CPU seconds and the error."""
    start, cpu = time.perf_counter(), time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = nplps.reconstruct(data["images"], rig, depth=float(data["distance"]), mask=data["mask"], **options)
    seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
    error = float("nan")
    if "normals" in data:
        mask = data["mask"]
        error = float(angles(result.normals[mask], data["normals"][mask]).mean())
    return seconds, float(result.timings["indirect"]), len(result.history), cpu, error


def child_peak(args: argparse.Namespace, case: int, options: dict[str, Any]) -> float:
    """Return the peak RSS (MB) of one run of cost case `case` in a fresh process."""
    command = [sys.executable, __file__, *map(str, args.paths), "--cost", "--child", str(case)]
    command += [f"--synthetic={n}" for n in args.synthetic]
    command += [f"--opt={k}={json.dumps(v)}" for k, v in options.items()]
    out = subprocess.run(command, check=True, capture_output=True, text=True).stdout
    return float(out.split()[-1])


def cost(args: argparse.Namespace, options: dict[str, Any]) -> None:
    """Print the cost table of ``--cost`` (see the module doc)."""
    cases = cost_cases(args)
    if args.child is not None:
        _, data, rig = cases[args.child]
        clear = Path("/proc/self/clear_refs")
        if clear.exists():  # Linux: the peak RSS from here on (the scene's making left out)
            clear.write_text("5")
        timed(data, rig, options)
        status = Path("/proc/self/status")
        peaks = [line for line in status.read_text().splitlines() if line.startswith("VmHWM")] if clear.exists() else []
        if peaks:
            print(float(peaks[0].split()[1]) / 1024)
        else:
            print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
        return
    on = {**options, "interreflections": True}
    header = (
        "| case | default (s) | with (s) | ratio | CPU default (s) | CPU with (s) | CPU ratio | indirect (s) | "
        "iterations | mean error default / with (deg) | runs |"
    )
    if args.memory:
        header += " peak default (MB) | peak with (MB) | peak growth |"
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    rows = []
    for index, (name, data, rig) in enumerate(cases):
        plain, with_ = [], []
        for _ in range(args.repeats):
            plain.append(timed(data, rig, options))
            with_.append(timed(data, rig, on))
        a = float(np.median([t[0] for t in plain]))
        b = float(np.median([t[0] for t in with_]))
        ca = float(np.median([t[3] for t in plain]))
        cb = float(np.median([t[3] for t in with_]))
        row: dict[str, Any] = {
            "case": name,
            "default_s": [t[0] for t in plain],
            "with_s": [t[0] for t in with_],
            "indirect_s": [t[1] for t in with_],
            "default_cpu_s": [t[3] for t in plain],
            "with_cpu_s": [t[3] for t in with_],
            "errors_deg": (plain[0][4], with_[0][4]),
            "iterations": (plain[0][2], with_[0][2]),
            "ratio": b / a,
        }
        line = (
            f"| {name} | {a:.2f} | {b:.2f} | {b / a:.2f}x | {ca:.2f} | {cb:.2f} | {cb / ca:.2f}x | "
            f"{np.median(row['indirect_s']):.2f} | {plain[0][2]} / {with_[0][2]} | "
            f"{plain[0][4]:.3f} / {with_[0][4]:.3f} | {args.repeats} |"
        )
        if args.memory:
            row["peak_default_mb"] = child_peak(args, index, options)
            row["peak_with_mb"] = child_peak(args, index, on)
            growth = row["peak_with_mb"] / row["peak_default_mb"] - 1
            line += f" {row['peak_default_mb']:.0f} | {row['peak_with_mb']:.0f} | {100 * growth:+.1f} % |"
        print(line, flush=True)
        rows.append(row)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


def main() -> None:
    """Print the table of every pair."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", nargs="*", type=Path, help="directories or *-gi-*.npz files")
    parser.add_argument("--opt", action="append", default=[], help="key=value, an option of nplps.reconstruct")
    parser.add_argument("--no-auto", action="store_true", help='skip depth="auto"')
    parser.add_argument("--json", help="write the numbers to this file")
    parser.add_argument("--cost", action="store_true", help="the cost of interreflections=True instead (module doc)")
    parser.add_argument("--repeats", type=int, default=2, help="--cost: runs of each configuration (default 2)")
    parser.add_argument(
        "--synthetic", type=int, action="append", default=[], help="--cost: also a synthetic bowl of N² pixels"
    )
    parser.add_argument("--memory", action="store_true", help="--cost: the peak RSS of each in a fresh process")
    parser.add_argument("--child", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    options = parse_options(args.opt)
    if args.cost:
        return cost(args, options)
    if not args.paths:
        parser.error("the GI renders (paths) are needed without --cost")
    print(f"options: {options or 'defaults'}\n")
    header = (
        "| scene | size | max depth | spp | indirect share mean | p90 | energy | "
        "GI mean (deg) | GI median | GI albedo | direct mean (deg) | direct median | direct albedo | "
        "shadowed obs | GI mean, twin's shadows dropped |"
    )
    if not args.no_auto:
        header += " auto mean (deg) | auto distance error |"
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    rows = []
    for gi_path, direct_path in pairs(args.paths):
        gi, rig = load(gi_path)
        direct, direct_rig = load(direct_path)
        if not (
            np.array_equal(gi["mask"], direct["mask"])
            and np.array_equal(gi["depth"], direct["depth"])
            and gi_path.name.replace("-gi-", "-") == direct_path.name.replace("-direct-", "-")
            and str(gi["material"]) == str(direct["material"])
            and int(direct["max_depth"]) == 2
            and int(gi["max_depth"]) > 2
        ):
            raise SystemExit(f"{gi_path.name} and {direct_path.name} are not twins")
        scene = f"{gi['shape']} {gi['material']}"
        row: dict[str, Any] = {
            "gi": str(gi_path),
            "direct": str(direct_path),
            "scene": scene,
            "size": int(gi["mask"].shape[0]),
            "max_depth": int(gi["max_depth"]),
            "spp": int(gi["spp"]),
            "albedo": true_albedo(gi),
            "render_seconds_gi": float(gi["seconds"]),
            "render_seconds_direct": float(direct["seconds"]),
            "options": options,
            **indirect_share(gi["images"], direct["images"], gi["mask"]),
        }
        distance = float(gi["distance"])
        row["gi_errors"] = errors(gi, rig, distance, options)
        row["direct_errors"] = errors(direct, direct_rig, distance, options)
        row["gi_errors_twin_shadows_dropped"] = errors(
            gi, rig, distance, {**options, "valid": lit(direct["images"], gi["mask"])}
        )
        g, d, o = row["gi_errors"], row["direct_errors"], row["gi_errors_twin_shadows_dropped"]
        line = (
            f"| {scene} | {row['size']} | {row['max_depth']} | {row['spp']} | {100 * row['share_mean']:.1f} % | "
            f"{100 * row['share_p90']:.1f} % | {100 * row['share_energy']:.1f} % | "
            f"{g['mean_deg']:.3f} | {g['median_deg']:.3f} | {g['albedo_pc']:+.2f} % | "
            f"{d['mean_deg']:.3f} | {d['median_deg']:.3f} | {d['albedo_pc']:+.2f} % | "
            f"{100 * row['shadowed_lit_by_gi']:.1f} % | {o['mean_deg']:.3f} |"
        )
        if not args.no_auto:
            row["gi_auto"] = errors(gi, rig, "auto", options)
            a = row["gi_auto"]
            line += f" {a['mean_deg']:.3f} | {a.get('distance_error_pc', float('nan')):+.2f} % |"
        print(line, flush=True)
        rows.append(row)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
