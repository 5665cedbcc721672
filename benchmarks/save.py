"""Save benchmark: the time of each file that ``Reconstruction.save`` writes, at camera resolution.

Usage::

    python benchmarks/save.py [--size 4000x3000] [--lights 16] [--repeats 3] [--formats obj ...]
                              [--baseline DIR [--baseline-core FILE]] [--workdir DIR] [--json results.json]

A result of the requested size is made without reconstructing (so that it takes seconds): the
scene of ``benchmarks/scale.py`` (a tilted plane with bumps, its albedo pattern), its true vertex
depths as the result's depth, the mesh normals as the fitted normals, a small residual, every
light used and random float32 trust maps (normal sigma, held-out error). ``result.save`` then
writes it ``--repeats`` times into a fresh directory, in a fresh
Python process per variant, and the time of every file is recorded: from the creation of its
temporary file to its rename into place (:mod:`nplps._atomic`), computing its content included.
Files written in parallel overlap (the PNG images are made and encoded together on a thread of
their own while the meshes and arrays are written: each PNG row is that batch's encoding, and
the computation of their pixels overlaps the other files); "other" is the time of ``save`` outside every
file (the mesh and vertex arrays built before the first mesh file, the checks, the manifest's
hashes).

``--baseline DIR`` also runs the ``nplps`` package found in ``DIR`` (a ``python`` folder of
another checkout, e.g. ``git worktree add /tmp/base BASE`` or ``git archive BASE python | tar -x
-C /tmp/base``; the compiled ``_core`` of this checkout is used for both unless ``--baseline-core
FILE`` gives the baseline's own, e.g. a copy of its ``python/nplps/_core.abi3.so``), so that the before and
after columns come from one run on one machine. Medians of the repeats; the processor time of
the save (user + system, all threads: less sensitive than wall time to a busy machine); peak
RSS of each process.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from _timing import covered, file_timer  # benchmarks/_timing.py

HERE = Path(__file__).resolve().parent


def parse_size(text: str) -> tuple[int, int]:
    """``N`` or ``WxH`` as (W, H)."""
    w, _, h = text.lower().partition("x")
    return int(w), int(h or w)


def synthetic_result(w: int, h: int, k: int) -> Any:
    """A ``Reconstruction`` of the scale benchmark's scene at W x H pixels (no reconstruction run)."""
    import numpy as np

    import nplps
    from nplps.reconstruction import Reconstruction

    sys.path.insert(0, str(HERE))
    import scale

    rig = scale.make_rig("orthographic", w, h, scale.ring_lights(k))
    depth = scale.surface_depth(rig, w, h)
    mask = np.ones((h, w), dtype=bool)
    result = Reconstruction(
        depth=depth,
        fit_normals=np.zeros((h, w, 3)),
        albedo=scale.albedo_map(rig, w, h),
        residual=np.full((h, w), 1e-3),
        lights_used=np.full((h, w), k, dtype=np.int64),
        regions=np.zeros((h, w), dtype=np.int64),
        gauge=np.array([float(depth.mean())]),
        history=[],
        converged=True,
        mask=mask,
        rig=rig,
        timings={"total": 0.0},
    )
    result.fit_normals = np.ascontiguousarray(result.normals)  # the mesh normals, as fits would be
    # Trust maps (float32, as a reconstruction makes them) so that summary.json's trust figures
    # and the two map TIFF files are part of the save, as after a reconstruction.
    rng = np.random.default_rng(0)
    result.normal_sigma = (rng.standard_exponential((h, w), dtype=np.float32) * np.float32(0.5)).astype(np.float32)
    result.held_out_error = (rng.standard_exponential((h, w), dtype=np.float32) * np.float32(1e-3)).astype(np.float32)
    assert isinstance(result, nplps.Reconstruction)
    return result


def run_child(spec: dict[str, Any]) -> dict[str, Any]:
    """Save one synthetic result ``repeats`` times; per-file medians, sizes and peak RSS."""
    import nplps

    w, h = spec["size"]
    t0 = time.perf_counter()
    result = synthetic_result(w, h, spec["lights"])
    _ = result.normals, result.vertices  # cached / computed once, as after a reconstruction
    make_s = time.perf_counter() - t0
    runs: list[dict[str, float]] = []
    sizes: dict[str, int] = {}
    for i in range(spec["repeats"]):
        out = Path(spec["workdir"]) / f"out{i}"
        record: list[tuple[str, float, float]] = []
        kwargs: dict[str, Any] = {"formats": spec["formats"]} if spec["formats"] else {}
        with file_timer(record):
            cpu0 = resource.getrusage(resource.RUSAGE_SELF)
            t0 = time.perf_counter()
            paths = result.save(out, **kwargs)
            total = time.perf_counter() - t0
            cpu1 = resource.getrusage(resource.RUSAGE_SELF)
        times = {name: b - a for name, a, b in record}
        times["other"] = total - covered([(a, b) for _, a, b in record])
        times["total"] = total
        # Processor time of all threads (user + system): less sensitive to a busy machine.
        times["cpu (user + system)"] = cpu1.ru_utime - cpu0.ru_utime + cpu1.ru_stime - cpu0.ru_stime
        runs.append(times)
        sizes = {p.name: p.stat().st_size for p in out.iterdir()}
        del paths
        shutil.rmtree(out)
    names = sorted({n for r in runs for n in r}, key=lambda n: (n in ("other", "total", "cpu (user + system)"), n))
    return {
        "nplps": os.path.dirname(nplps.__file__),
        "make_s": make_s,
        "seconds": {n: statistics.median(r.get(n, 0.0) for r in runs) for n in names},
        "bytes": sizes,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }


def _variant(args: argparse.Namespace, label: str, python_path: str | None, workdir: Path) -> dict[str, Any]:
    spec = {
        "size": list(args.size),
        "lights": args.lights,
        "repeats": args.repeats,
        "formats": args.formats,
        "workdir": str(workdir),
    }
    spec_path = workdir / f"{label}.json"
    spec_path.write_text(json.dumps(spec), encoding="utf-8")
    env = dict(os.environ)
    if python_path:
        from nplps import _core

        core = Path(_core.__file__ or "")  # this checkout's extension, unless --baseline-core
        shutil.copy(args.baseline_core or core, Path(python_path) / "nplps" / core.name)
        env["PYTHONPATH"] = os.pathsep.join([python_path, env.get("PYTHONPATH", "")])
    out = workdir / f"{label}.out.json"
    subprocess.run([sys.executable, __file__, "--child", str(spec_path), "--out", str(out)], check=True, env=env)
    return json.loads(out.read_text(encoding="utf-8"))


def table(results: dict[str, dict[str, Any]]) -> str:
    """Markdown table: one row per file, seconds and MB of each variant."""
    labels = list(results)
    names: list[str] = []
    for r in results.values():
        names += [n for n in r["seconds"] if n not in names]
    names.sort(key=lambda n: (n.startswith("cpu"), n == "total", n == "other", n))
    head = "| file | " + " | ".join(f"{label} s | {label} MB" for label in labels) + " |"
    rows = [head, "|---" * (1 + 2 * len(labels)) + "|"]
    for n in names:
        cells = []
        for label in labels:
            r = results[label]
            s = r["seconds"].get(n)
            size = r["bytes"].get(n)
            cells += ["—" if s is None else f"{s:.3f}", "" if size is None else f"{size / 1e6:.1f}"]
        rows.append(f"| {n} | " + " | ".join(cells) + " |")
    rows.append("| peak RSS MB | " + " | ".join(f"{results[label]['peak_rss_mb']:.0f} | " for label in labels) + "|")
    return "\n".join(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=parse_size, default=(4000, 3000), help="N or WxH (default 4000x3000)")
    parser.add_argument("--lights", type=int, default=16, help="lights of the rig (default 16)")
    parser.add_argument("--repeats", type=int, default=3, help="saves per variant; medians (default 3)")
    parser.add_argument("--formats", nargs="*", default=[], help="passed to save(formats=...)")
    parser.add_argument("--baseline", help="a python/ folder holding another nplps package to compare with")
    parser.add_argument(
        "--baseline-core", help="the compiled nplps._core for --baseline (default: this checkout's, copied there)"
    )
    parser.add_argument("--workdir", help="where the files are written (default: a temporary directory)")
    parser.add_argument("--json", help="also write the results to this JSON file")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--out", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        result = run_child(json.loads(Path(args.child).read_text(encoding="utf-8")))
        Path(args.out).write_text(json.dumps(result), encoding="utf-8")
        return
    workdir = Path(tempfile.mkdtemp(prefix="nplps-save-", dir=args.workdir))
    try:
        results = {}
        if args.baseline:
            results["before"] = _variant(args, "before", args.baseline, workdir)
        results["after" if args.baseline else "save"] = _variant(args, "after", None, workdir)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    w, h = args.size
    print(
        f"\nReconstruction.save of {w} x {h} ({w * h / 1e6:.1f} MP), medians of {args.repeats}; {os.cpu_count()} CPUs\n"
    )
    print(table(results))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
