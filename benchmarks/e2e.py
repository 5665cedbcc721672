"""End-to-end timing of the command line at camera resolution: decode, solve, write mesh and maps.

Usage::

    python benchmarks/e2e.py [--size 4000x3000] [--lights 16] [--camera orthographic|pinhole]
                             [--repeats 1] [--solver S] [--levels N] [--threads N]
                             [--cli-args "--iterations 10"] [--workdir DIR] [--keep]
                             [--limit 40] [--json results.json]

Writes the scene of ``benchmarks/scale.py`` (a tilted plane with bumps, ``--lights`` point
lights on a ring) once into a directory: sixteen 16-bit grey PNG images, ``rig.json`` and a
full-frame ``mask.png`` (``--workdir DIR`` keeps them there and reuses them on the next run).
Then it times, as a subprocess::

    nplps reconstruct DIR --rig DIR/rig.json --mask DIR/mask.png --depth D --out OUT

(D is the true working distance): wall time and peak RSS (from ``/usr/bin/time -v`` when it
exists, else ``getrusage(RUSAGE_CHILDREN)``), the solver time the command reports, the files it
wrote with their sizes, and the accuracy of the written normals and depths against the ground
truth. The acceptance asks for at most ``--limit`` (40) seconds for decode + solve + PLY + maps
at 12 MP; note that ``reconstruct`` also writes the OBJ, which is included in the wall time.
``--solver`` / ``--levels`` are passed only if ``nplps reconstruct --help`` lists them.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import types
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import nplps
import scale
from nplps import export


def nplps_command() -> list[str]:
    """The ``nplps`` console script of this Python, or ``python -m nplps``."""
    script = Path(sys.executable).parent / "nplps"
    return [str(script)] if script.exists() else [sys.executable, "-m", "nplps"]


def cli_options() -> str:
    """The help text of ``nplps reconstruct`` (to see which options it has)."""
    return subprocess.run(
        [*nplps_command(), "reconstruct", "--help"], capture_output=True, text=True, check=True
    ).stdout


def write_inputs(directory: Path, camera: str, w: int, h: int, k: int) -> dict[str, Any]:
    """Writes the images, rig.json, mask.png and the ground truth once; reuses them if a previous
    run wrote the same case."""
    spec = {"camera": camera, "width": w, "height": h, "lights": k, "scene": "scale.py v1"}
    spec_path = directory / "scene.json"
    if spec_path.exists() and json.loads(spec_path.read_text(encoding="utf-8")).get("spec") == spec:
        print(f"reusing the inputs in {directory}", file=sys.stderr)
        return json.loads(spec_path.read_text(encoding="utf-8"))
    directory.mkdir(parents=True, exist_ok=True)
    print(
        f"writing {k} {w} x {h} 16-bit PNG images, rig.json and mask.png into {directory} ...",
        file=sys.stderr,
        flush=True,
    )
    t0 = time.perf_counter()
    rig = scale.make_rig(camera, w, h, scale.ring_lights(k))
    depth = scale.surface_depth(rig, w, h)
    scratch = directory / "render-scratch.npy"  # used above 2 GB of float32 images (50 MP, 100 MP)
    images = scale.render_uint16(depth, rig, scale.albedo_map(rig, w, h), scratch=scratch)
    scratch.unlink(missing_ok=True)
    for i, image in enumerate(images):
        export.write_png16(directory / f"image_{i:02d}.png", image)
    del images
    rig.save(directory / "rig.json")
    export.save_grey_png(directory / "mask.png", np.ones((h, w)))
    np.save(directory / "depth_gt.npy", depth)
    info = {"spec": spec, "gauge": scale.true_gauge(depth, rig), "write_s": time.perf_counter() - t0}
    spec_path.write_text(json.dumps(info, indent=2), encoding="utf-8")
    return info


def make_inputs(directory: Path, camera: str, w: int, h: int, k: int) -> dict[str, Any]:
    """:func:`write_inputs` in a process of its own: rendering 12 MP images takes GB, and on Linux
    a child's ru_maxrss starts from its parent's peak."""
    subprocess.run(
        [
            sys.executable,
            os.path.abspath(__file__),
            "--make",
            str(directory),
            "--camera",
            camera,
            "--size",
            f"{w}x{h}",
            "--lights",
            str(k),
        ],
        check=True,
    )
    return json.loads((directory / "scene.json").read_text(encoding="utf-8"))


def run_once(command: list[str]) -> dict[str, Any]:
    """Runs ``command``; wall time, peak RSS (MB) and its output."""
    gnu_time = Path("/usr/bin/time")
    use_time = gnu_time.exists() and os.access(gnu_time, os.X_OK)
    full = [str(gnu_time), "-v", *command] if use_time else command
    t0 = time.perf_counter()
    proc = subprocess.run(full, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    stderr = proc.stderr
    rss_mb = cpu_s = None
    if use_time:
        match = re.search(r"Maximum resident set size \(kbytes\): (\d+)", stderr)
        rss_mb = int(match.group(1)) / 1024 if match else None
        user = re.search(r"User time \(seconds\): ([0-9.]+)", stderr)
        system = re.search(r"System time \(seconds\): ([0-9.]+)", stderr)
        cpu_s = float(user.group(1)) + float(system.group(1)) if user and system else None
        stderr = stderr.split("\tCommand being timed:")[0]
    if rss_mb is None:  # the largest child so far
        rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
        rss_mb = rss / (1024 * 1024) if sys.platform == "darwin" else rss / 1024
    return {
        "wall_s": wall,
        "cpu_s": cpu_s,
        "load_average": os.getloadavg(),
        "rss_mb": rss_mb,
        "rss_source": "/usr/bin/time -v" if use_time else "getrusage(RUSAGE_CHILDREN)",
        "returncode": proc.returncode,
        "stdout": proc.stdout,
        "stderr": stderr,
    }


def reported_seconds(stdout: str) -> tuple[float | None, float | None]:
    """The reconstruction call's wall time and the solver time of the command's summary line
    ``time  W s (solver S s)``."""
    match = re.search(r"time\s+([0-9.]+) s \(solver ([0-9.]+) s\)", stdout)
    return (float(match.group(1)), float(match.group(2))) if match else (None, None)


def stage_seconds(stderr: str) -> tuple[float | None, float | None]:
    """The decoding and export times of the command's progress lines ``load: k images read in
    T s`` and ``export: n files written in T s`` (T as ``format_duration`` writes it: s or m s)."""

    def seconds(pattern: str) -> float | None:
        found = re.search(pattern + r" (?:(\d+) min )?([0-9.]+) s", stderr)
        return None if found is None else 60.0 * float(found.group(1) or 0) + float(found.group(2))

    return seconds(r"images read in"), seconds(r"files written in")


def check_output(out: Path, directory: Path, rig: nplps.Rig, mask: np.ndarray) -> dict[str, float]:
    """Normal and depth errors of the written normals.npy / depth.npy against the ground truth
    (``scale.accuracy``, in bands of rows: 100 MP arrays are read memory-mapped)."""
    written = types.SimpleNamespace(
        normals=np.load(out / "normals.npy", mmap_mode="r"), depth=np.load(out / "depth.npy", mmap_mode="r"), mask=mask
    )
    return scale.accuracy(written, np.load(directory / "depth_gt.npy"), rig)  # type: ignore[arg-type]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=scale.parse_size, default=(4000, 3000), help="N or WxH (default 4000x3000)")
    parser.add_argument("--lights", type=int, default=16, help="number of images / point lights (default 16)")
    parser.add_argument("--camera", choices=("orthographic", "pinhole"), default="orthographic")
    parser.add_argument("--repeats", type=int, default=1, help="runs of the command (median wall time, largest RSS)")
    parser.add_argument("--solver", help="--solver of nplps reconstruct, if it has one")
    parser.add_argument("--levels", type=int, help="--levels of nplps reconstruct, if it has one")
    parser.add_argument("--threads", type=int, help="--threads of nplps reconstruct")
    parser.add_argument("--cli-args", default="", help="further options for nplps reconstruct, as one string")
    parser.add_argument("--workdir", help="directory for the inputs (kept and reused; default: a temporary one)")
    parser.add_argument("--keep", action="store_true", help="keep the output directory of the last run")
    parser.add_argument("--limit", type=float, default=40.0, help="acceptance limit in seconds (default 40)")
    parser.add_argument("--json", help="also write the results to this JSON file")
    parser.add_argument("--make", help=argparse.SUPPRESS)
    args = parser.parse_args()
    w, h = args.size
    if args.make:
        write_inputs(Path(args.make), args.camera, w, h, args.lights)
        return

    temporary = args.workdir is None
    directory = Path(args.workdir or tempfile.mkdtemp(prefix="nplps-e2e-"))
    try:
        info = make_inputs(directory, args.camera, w, h, args.lights)
        help_text = cli_options()
        extra: list[str] = []
        skipped = []
        for option, value in (("--solver", args.solver), ("--levels", args.levels)):
            if value is None:
                continue
            if re.search(rf"{option}\b", help_text):
                extra += [option, str(value)]
            else:
                skipped.append(option)
        if skipped:
            print(f"note: nplps reconstruct has no {', '.join(skipped)} option; ignored", file=sys.stderr)
        if args.threads is not None:
            extra += ["--threads", str(args.threads)]
        extra += shlex.split(args.cli_args)
        out = directory / "out"
        command = [
            *nplps_command(),
            "reconstruct",
            str(directory),
            "--rig",
            str(directory / "rig.json"),
            "--mask",
            str(directory / "mask.png"),
            "--depth",
            repr(info["gauge"]),
            "--out",
            str(out),
            *extra,
        ]
        print("$ " + " ".join(shlex.quote(c) for c in command), file=sys.stderr, flush=True)
        runs = []
        for i in range(args.repeats):
            shutil.rmtree(out, ignore_errors=True)
            run = run_once(command)
            if run["returncode"] != 0:
                sys.stderr.write(run["stderr"])
                sys.exit(f"nplps reconstruct failed with exit code {run['returncode']}")
            run["reconstruct_s"], run["solver_s"] = reported_seconds(run["stdout"])
            run["decode_s"], run["export_s"] = stage_seconds(run["stderr"])
            runs.append(run)
            print(
                f"run {i + 1}: {run['wall_s']:.1f} s wall, peak RSS {run['rss_mb']:.0f} MB", file=sys.stderr, flush=True
            )
        files = {p.name: p.stat().st_size for p in sorted(out.iterdir()) if p.is_file()}
        rig = nplps.Rig.load(directory / "rig.json")
        accuracy = check_output(out, directory, rig, np.ones((h, w), dtype=bool))
        if not args.keep:
            shutil.rmtree(out, ignore_errors=True)
    finally:
        if temporary and not args.keep:
            shutil.rmtree(directory, ignore_errors=True)

    wall = statistics.median(r["wall_s"] for r in runs)
    solver = [r["solver_s"] for r in runs if r["solver_s"] is not None]
    call = [r["reconstruct_s"] for r in runs if r["reconstruct_s"] is not None]
    rss = max(r["rss_mb"] for r in runs)
    verdict = "PASS" if wall <= args.limit else "FAIL"
    print(runs[-1]["stdout"].rstrip())
    print(f"\n## nplps reconstruct, {w} x {h} ({w * h / 1e6:.1f} MP), {args.lights} 16-bit PNG images, {args.camera}\n")
    print("| measure | value |\n|---|---|")
    print(f"| wall time (median of {len(runs)}) | {wall:.2f} s ({verdict}: limit {args.limit:g} s) |")
    cpu = [r["cpu_s"] for r in runs if r["cpu_s"] is not None]
    if cpu:
        print(f"| CPU time, user + system (median) | {statistics.median(cpu):.2f} s |")
    print(f"| load average at the end (1 / 5 / 15 min) | {' / '.join(f'{x:.2f}' for x in runs[-1]['load_average'])} |")
    if call and solver:
        print(
            f"| reconstruct call (reported) | {statistics.median(call):.2f} s"
            f", of which solver {statistics.median(solver):.2f} s |"
        )
        print(f"| start-up + decode + export (wall − reconstruct call) | {wall - statistics.median(call):.2f} s |")
    decode = [r["decode_s"] for r in runs if r["decode_s"] is not None]
    export_s = [r["export_s"] for r in runs if r["export_s"] is not None]
    if decode and export_s:
        print(
            f"| of which decode / export (reported) | {statistics.median(decode):.2f} s"
            f" / {statistics.median(export_s):.2f} s |"
        )
    print(f"| peak RSS ({runs[-1]['rss_source']}) | {rss:.0f} MB ({rss * 1024 * 1024 / (w * h):.0f} bytes/pixel) |")
    print(
        f"| normal error mean / median | {accuracy['normal_error_mean_deg']:.3f}°"
        f" / {accuracy['normal_error_median_deg']:.3f}° |"
    )
    print(
        f"| depth error max / RMS | {accuracy['depth_error_max_pct']:.3f} %"
        f" / {accuracy['depth_error_rms_pct']:.3f} % of the depth range |"
    )
    print("\n| file | size |\n|---|---|")
    for name, size in files.items():
        print(f"| {name} | {size / 1e6:.1f} MB |")
    print(f"| total | {sum(files.values()) / 1e6:.1f} MB |")
    if args.json:
        payload = {
            "nplps": nplps.__version__,
            "cpus": os.cpu_count(),
            "command": command,
            "size": [w, h],
            "lights": args.lights,
            "camera": args.camera,
            "wall_s": wall,
            "cpu_s": statistics.median(cpu) if cpu else None,
            "load_average": runs[-1]["load_average"],
            "progress": runs[-1]["stderr"],  # the command's progress lines (stage times)
            "reconstruct_s": statistics.median(call) if call else None,
            "solver_s": statistics.median(solver) if solver else None,
            "decode_s": statistics.median(decode) if decode else None,
            "export_s": statistics.median(export_s) if export_s else None,
            "rss_mb": rss,
            "limit_s": args.limit,
            "verdict": verdict,
            "files": files,
            "accuracy": accuracy,
            "skipped_options": skipped,
            "runs": [{k: v for k, v in r.items() if k not in ("stdout", "stderr")} for r in runs],
            "input_write_s": info.get("write_s"),
        }
        Path(args.json).write_text(json.dumps(payload, indent=2) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
