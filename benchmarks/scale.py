"""Scaling benchmark: time and memory of nplps from 256 x 256 up to camera resolution (12 MP).

Usage::

    python benchmarks/scale.py [--sizes 256 512 1024 2048 4096 4000x3000] [--lights 16]
                               [--cameras orthographic pinhole] [--solver auto|direct|multigrid]
                               [--levels N] [--noise 0] [--iterations 10] [--tol 1e-6] [--repeats 1]
                               [--threads N] [--no-files] [--stack uint16|float32] [--no-obj-alone]
                               [--workdir DIR] [--keep] [--json results.json]

Every size (N for N x N, or WxH) and camera makes the same physical scene: a tilted plane with a
few Gaussian bumps and dents, 100 units across (the longer side) at working distance 200, lit by
``--lights`` point lights on a ring 150 units in front of it; the images are rendered by
``nplps.render`` and quantized to 16 bits. They are written once per case as 16-bit PNG files
(or, with ``--no-files``, as one uint16 .npy stack that is passed as an array). Each
(size, camera) then runs in a fresh Python process, so that its peak RSS is its own, which times:

* load: ``nplps.io.load_stack`` of the PNG files (``--no-files``: ``np.load`` + ``load_stack``
  of the array), kept as ``uint16`` (``--stack float32``: converted to float32, as before);
* reconstruct: wall time of ``nplps.reconstruct``, the process's CPU time over it
  (``time.process_time``: all threads, user + system; on a shared machine the figure to
  compare) and its ``result.timings`` split;
* export: ``result.save`` (PLY + OBJ up to 4 MP + maps) into a temporary directory (wall and
  CPU time), the time of
  each file it writes (printed as the "Save, seconds per file" table; see ``benchmarks/save.py``,
  which times ``save`` alone at camera resolution without reconstructing), and the mesh writers
  alone (``write_ply``, ``write_obj``) on precomputed vertex arrays;
* iterations per pyramid level (``result.history``, grouped by ``level`` when entries have one);
* peak RSS after the reconstruction and after the export, also minus the RSS before loading;
* accuracy against the ground truth: mean / median angle between ``result.normals`` and the
  true mesh normals, and the largest and RMS vertex depth errors in percent of the true depth
  range (so that a faster setting cannot hide a worse result).

``--solver`` and ``--levels`` are passed to ``nplps.reconstruct`` only if its signature has
them (otherwise they are reported as unsupported and ignored). Timings are medians over
``--repeats`` runs in the child process. The results are printed as Markdown tables, followed
by the growth of time / pixel and RSS / pixel relative to the smallest size of at least 1 MP
(the acceptance asks that from 1 MP to 12 MP they stay within 1.5 x of linear), and written to
``--json``. The machine should be otherwise idle: 12 MP cases take minutes and several GB.
"""

from __future__ import annotations

import argparse
import inspect
import json
import math
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

import nplps
from nplps import export

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _timing  # benchmarks/_timing.py: the per-file timer

#: Lateral size of the object (its longer side), working distance, light stand-off.
OBJECT_SIZE = 100.0
DISTANCE = 200.0
STAND_OFF = 1.5 * OBJECT_SIZE
#: Bumps: (x, y, amplitude, sigma) in units of the object size.
BUMPS = (
    (-0.20, -0.15, 0.08, 0.12),
    (0.25, 0.10, -0.06, 0.10),
    (0.05, 0.30, 0.05, 0.08),
    (-0.30, 0.25, 0.04, 0.15),
    (0.30, -0.30, 0.06, 0.10),
    (0.00, 0.00, 0.03, 0.25),
)
TILT = (0.08, -0.05)  # dz/dx, dz/dy of the plane
#: 16-bit thresholds, reconstruct's defaults for 16-bit images (given, for the float32 stack of --stack float32).
LEVELS_16 = 65535
DARK_16 = 1.0 / LEVELS_16
SATURATION_16 = 1.0 - 0.5 / LEVELS_16
MEGAPIXEL = 1_000_000
#: A float32 render stack larger than this is a memory-mapped scratch file (50 MP and 100 MP cases).
SCRATCH_BYTES = 2 << 30
#: Images are rendered in bands of rows of at most this many pixels (the renderer needs ~30 B per
#: pixel and image: 100 MP x 4 images would be 12 GB at once).
BAND_PIXELS = 8 << 20


# --------------------------------------------------------------------------------------------------
# The synthetic scene
# --------------------------------------------------------------------------------------------------


def parse_size(text: str) -> tuple[int, int]:
    """``"512"`` -> (512, 512); ``"4000x3000"`` -> (4000, 3000) as (W, H)."""
    parts = text.lower().split("x")
    try:
        w, h = (int(parts[0]), int(parts[0])) if len(parts) == 1 else (int(parts[0]), int(parts[1]))
    except (ValueError, IndexError):
        raise argparse.ArgumentTypeError(f"a size is N or WxH, got {text!r}") from None
    if len(parts) > 2 or w < 8 or h < 8:
        raise argparse.ArgumentTypeError(f"a size is N or WxH with at least 8 pixels a side, got {text!r}")
    return w, h


def parse_option(text: str) -> tuple[str, Any]:
    """``NAME=VALUE`` of ``--option``: the value as JSON (numbers, true/false) or else as text."""
    name, sep, value = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {text!r}")
    try:
        return name, json.loads(value)
    except json.JSONDecodeError:
        return name, value


def size_label(w: int, h: int) -> str:
    return f"{w}x{h}"


def ring_lights(k: int) -> np.ndarray:
    """``k`` point lights on a ring (alternating radius 0.35 and 0.5 object sizes) in the plane
    ``STAND_OFF`` in front of the object's mean depth."""
    angles = 2.0 * np.pi * np.arange(k) / k
    radius = OBJECT_SIZE * np.where(np.arange(k) % 2 == 0, 0.5, 0.35)
    return np.stack([radius * np.cos(angles), radius * np.sin(angles), np.full(k, DISTANCE - STAND_OFF)], axis=1)


def make_rig(camera: str, w: int, h: int, lights: np.ndarray) -> nplps.Rig:
    """The camera sees the object's longer side across the image's longer side."""
    pixel = OBJECT_SIZE / max(w, h)
    if camera == "orthographic":
        return nplps.Rig.orthographic(pixel, origin=(-0.5 * w * pixel, -0.5 * h * pixel), lights=lights)
    f = DISTANCE / pixel
    K = [[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]]
    return nplps.Rig.pinhole(K, lights=lights)


def _lateral(rig: nplps.Rig, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lateral scene coordinates of image points (row, col) in pixel units, where vertex (r, c) is
    the corner (r, c): the orthographic footprint, or the ray at the working distance."""
    cam = rig.camera
    if cam["model"] == "orthographic":
        (pw, ph), (ox, oy) = cam["pixel_size"], cam["origin"]
        return ox + cols * pw, oy + rows * ph
    K = np.asarray(cam["K"])
    u, v = cols - 0.5, rows - 0.5
    return DISTANCE * (u - K[0, 2]) / K[0, 0], DISTANCE * (v - K[1, 2]) / K[1, 1]


def surface_depth(rig: nplps.Rig, w: int, h: int) -> np.ndarray:
    """True vertex depths (H+1, W+1): a tilted plane plus bumps, the same physical surface at any
    resolution."""
    x, y = _lateral(rig, np.arange(h + 1, dtype=np.float64)[:, None], np.arange(w + 1, dtype=np.float64)[None, :])
    z = DISTANCE + TILT[0] * x + TILT[1] * y
    for bx, by, amplitude, sigma in BUMPS:
        s = sigma * OBJECT_SIZE
        gx = np.exp(-((x - bx * OBJECT_SIZE) ** 2) / (2 * s * s))  # separable: (1, W+1) x (H+1, 1)
        gy = np.exp(-((y - by * OBJECT_SIZE) ** 2) / (2 * s * s))
        z = z + amplitude * OBJECT_SIZE * (gy * gx)
    return np.ascontiguousarray(np.broadcast_to(z, (h + 1, w + 1)), dtype=np.float64)


def albedo_map(rig: nplps.Rig, w: int, h: int) -> np.ndarray:
    """A smooth albedo pattern in [0.6, 1] at the pixel centres."""
    x, y = _lateral(rig, np.arange(h, dtype=np.float64)[:, None] + 0.5, np.arange(w, dtype=np.float64)[None, :] + 0.5)
    s = 0.5 + 0.25 * np.sin(2 * np.pi * x / OBJECT_SIZE) + 0.25 * np.cos(3 * np.pi * y / OBJECT_SIZE)
    return np.ascontiguousarray(np.broadcast_to(0.6 + 0.4 * s, (h, w)), dtype=np.float64)


def _band_rig(rig: nplps.Rig, r0: int) -> nplps.Rig:
    """The rig whose image row 0 is row ``r0`` of ``rig``'s image (``rig`` itself for ``r0 = 0``)."""
    if r0 == 0:
        return rig
    cam = rig.camera
    if cam["model"] == "orthographic":
        (pw, ph), (ox, oy) = cam["pixel_size"], cam["origin"]
        return nplps.Rig.orthographic((pw, ph), origin=(ox, oy + r0 * ph), lights=rig.lights)
    K = np.array(cam["K"], dtype=np.float64)
    K[1, 2] -= r0
    return nplps.Rig.pinhole(K, lights=rig.lights)


def render_uint16(
    depth: np.ndarray,
    rig: nplps.Rig,
    albedo: np.ndarray,
    noise: float = 0.0,
    seed: int = 0,
    scratch: Path | None = None,
) -> np.ndarray:
    """The images (k, H, W) as uint16, scaled so that the brightest value is 65535, with Gaussian
    noise of standard deviation ``noise`` times that. Rendered a few lights at a time into a
    float32 stack (a float64 stack of 12 MP x 16 is 1.5 GB); above ``SCRATCH_BYTES`` that stack is
    a memory-mapped file ``scratch`` (deleted by the caller)."""
    k = rig.n_lights
    h, w = albedo.shape
    stack: np.ndarray
    if scratch is not None and k * h * w * 4 > SCRATCH_BYTES:  # 100 MP x 16: 6.4 GB on disk, not in memory
        stack = np.lib.format.open_memmap(scratch, mode="w+", dtype=np.float32, shape=(k, h, w))
    else:
        stack = np.empty((k, h, w), dtype=np.float32)
    # Bands of rows of at most BAND_PIXELS (the model is per pixel without cast shadows, so a band
    # rendered with the camera shifted to its first row is exactly those rows of the whole image).
    band = max(1, min(h, BAND_PIXELS // w))
    for r0 in range(0, h, band):
        r1 = min(h, r0 + band)
        band_rig = _band_rig(rig, r0)
        for start in range(0, k, 4):
            stop = min(start + 4, k)
            group = list(range(min(start, max(0, stop - 3)), stop))  # a rig needs 3 lights
            images = nplps.render(depth[r0 : r1 + 1], band_rig.subset(group), albedo[r0:r1])
            for j, light in enumerate(group):
                if light >= start:
                    stack[light, r0:r1] = images[j]
            del images
    scale = np.float32(LEVELS_16 / float(stack.max()))
    rng = np.random.default_rng(seed)
    out = np.empty((k, h, w), dtype=np.uint16)
    for i in range(k):
        image = stack[i] * scale
        if noise > 0:
            image += rng.standard_normal(image.shape, dtype=np.float32) * np.float32(noise * LEVELS_16)
        out[i] = np.rint(np.clip(image, 0, LEVELS_16))
        del image
    del stack
    return out


def true_gauge(depth: np.ndarray, rig: nplps.Rig) -> float:
    """The reconstruction's gauge for the full mask: arithmetic (orthographic) or geometric
    (pinhole) mean vertex depth."""
    return float(np.exp(np.log(depth).mean())) if rig.is_pinhole else float(depth.mean())


def write_case(directory: Path, camera: str, w: int, h: int, k: int, files: bool, noise: float = 0.0) -> dict[str, Any]:
    """Renders the scene and writes its inputs and ground truth into ``directory``."""
    directory.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rig = make_rig(camera, w, h, ring_lights(k))
    depth = surface_depth(rig, w, h)
    scratch = directory / "render-scratch.npy"
    images = render_uint16(depth, rig, albedo_map(rig, w, h), noise, scratch=scratch)
    scratch.unlink(missing_ok=True)
    render_time = time.perf_counter() - t0
    rig.save(directory / "rig.json")
    np.save(directory / "depth_gt.npy", depth)
    t0 = time.perf_counter()
    if files:
        paths = [directory / f"image_{i:02d}.png" for i in range(k)]
        for path, image in zip(paths, images, strict=False):
            export.write_png16(path, image)
        inputs = [str(p) for p in paths]
        input_bytes = sum(p.stat().st_size for p in paths)
    else:
        np.save(directory / "images.npy", images)
        inputs = str(directory / "images.npy")
        input_bytes = (directory / "images.npy").stat().st_size
    return {
        "inputs": inputs,
        "input_bytes": input_bytes,
        "gauge": true_gauge(depth, rig),
        "render_s": render_time,
        "write_s": time.perf_counter() - t0,
    }


# --------------------------------------------------------------------------------------------------
# The child process: one (size, camera) case
# --------------------------------------------------------------------------------------------------


def peak_rss_mb() -> float:
    """Peak resident set size of this process in MB: ``getrusage(RUSAGE_SELF).ru_maxrss`` (kB on
    Linux, bytes on macOS). On Linux it also counts the parent's peak at the fork, which is why
    the parent keeps no images (they are made in a process of their own)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / (1024 * 1024) if sys.platform == "darwin" else rss / 1024


def hwm_mb() -> float | None:
    """Linux's VmHWM (peak RSS of this process's own memory since exec), in MB, or None."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return None


def supported_options(options: dict[str, Any]) -> tuple[dict[str, Any], list[str]]:
    """The options of ``options`` (None = not asked for) that nplps.reconstruct accepts, and the
    names of those it does not."""
    params = inspect.signature(nplps.reconstruct).parameters
    asked = {k: v for k, v in options.items() if v is not None}
    return {k: v for k, v in asked.items() if k in params}, sorted(k for k in asked if k not in params)


def iterations_per_level(history: list[Any]) -> dict[str, dict[str, int]]:
    """Per pyramid level (coarsest first; "0" is full resolution, and the only level of entries
    without one): the outer iterations and, if recorded, the inner (CG) iterations."""
    levels: dict[int, dict[str, int]] = {}
    for entry in history:
        level = int(getattr(entry, "level", 0))
        stats = levels.setdefault(level, {"iterations": 0})
        stats["iterations"] += 1
        inner = getattr(entry, "inner_iterations", None)
        if inner is not None:
            stats["inner_iterations"] = stats.get("inner_iterations", 0) + int(inner)
    return {str(level): levels[level] for level in sorted(levels, reverse=True)}


def accuracy(result: nplps.Reconstruction, depth_gt: np.ndarray, rig: nplps.Rig) -> dict[str, float]:
    """Normal and depth errors against the ground truth, over the reconstructed pixels."""
    scene = nplps.Scene("scale", depth_gt, result.mask, np.ones(result.mask.shape), rig, OBJECT_SIZE, np.empty(0))
    truth = scene.normals
    errors = np.empty(result.mask.shape, dtype=np.float64)  # row by row bands: bounded memory
    band = max(1, 4_000_000 // (3 * result.mask.shape[1]))
    for r in range(0, errors.shape[0], band):
        dot = np.einsum("ijk,ijk->ij", result.normals[r : r + band], truth[r : r + band])
        errors[r : r + band] = np.degrees(np.arccos(np.clip(dot, -1.0, 1.0)))
    errors = errors[result.mask]
    ok = np.isfinite(result.depth) & np.isfinite(depth_gt)
    diff = np.abs(result.depth[ok] - depth_gt[ok])
    depth_range = float(depth_gt[ok].max() - depth_gt[ok].min())
    return {
        "normal_error_mean_deg": float(np.nanmean(errors)),
        "normal_error_median_deg": float(np.nanmedian(errors)),
        "normal_error_p99_deg": float(np.nanpercentile(errors, 99)),
        "unfitted_pixels": int(np.count_nonzero(~np.isfinite(errors))),
        "depth_error_max_pct": 100.0 * float(diff.max()) / depth_range,
        "depth_error_rms_pct": 100.0 * float(np.sqrt(np.mean(diff**2))) / depth_range,
        "depth_range": depth_range,
    }


def _median_dict(runs: list[dict[str, float]]) -> dict[str, float]:
    keys = [k for k in runs[0] if all(k in r for r in runs)]
    return {k: statistics.median(r[k] for r in runs) for k in keys}


def run_child(spec_path: str) -> None:
    """Runs one case described by the JSON file ``spec_path``; writes ``result.json`` next to it."""
    spec = json.loads(Path(spec_path).read_text(encoding="utf-8"))
    directory = Path(spec["directory"])
    base_rss, base_hwm = peak_rss_mb(), hwm_mb()
    load_average_start = os.getloadavg()
    rig = nplps.Rig.load(directory / "rig.json")
    options, unsupported = supported_options(
        {"solver": spec["solver"], "levels": spec["levels"], **spec.get("options", {})}
    )
    h, w = spec["height"], spec["width"]
    mask = np.ones((h, w), dtype=bool)
    out_dir = directory / "out"
    runs, exports = [], []
    save_runs: list[dict[str, float]] = []
    rss_after_reconstruct = rss_after_export = 0.0
    hwm_after_reconstruct = hwm_after_export = None
    result = None
    for _ in range(spec["repeats"]):
        result = None  # free the previous run first
        t0 = time.perf_counter()
        uint16 = spec.get("stack", "uint16") == "uint16"
        if isinstance(spec["inputs"], list):
            stack, levels = nplps.io.load_stack(spec["inputs"], uint16=uint16)
        else:
            stack, levels = nplps.io.load_stack(np.load(spec["inputs"]), uint16=uint16)
        load_s = time.perf_counter() - t0
        assert levels in (None, LEVELS_16), levels
        t0, c0 = time.perf_counter(), time.process_time()
        keywords = {
            "mask": mask,
            "depth": spec["gauge"],
            "iterations": spec["iterations"],
            "tol": spec["tol"],
            "dark": DARK_16,
            "saturation": SATURATION_16,
            "threads": spec["threads"],
            **options,  # --option may replace any of them (e.g. depth=auto)
        }
        result = nplps.reconstruct(stack, rig, **keywords)
        reconstruct_s, reconstruct_cpu = time.perf_counter() - t0, time.process_time() - c0
        del stack
        rss_after_reconstruct = max(rss_after_reconstruct, peak_rss_mb())
        hwm_after_reconstruct = hwm_mb()
        runs.append(
            {
                "load": load_s,
                "reconstruct": reconstruct_s,
                "reconstruct_cpu": reconstruct_cpu,
                **{f"timings.{k}": float(v) for k, v in result.timings.items()},
            }
        )
        record: list[tuple[str, float, float]] = []
        with _timing.file_timer(record):  # the time of each file (_timing.file_timer)
            t0, c0 = time.perf_counter(), time.process_time()
            paths = result.save(out_dir)
            save_s, save_cpu = time.perf_counter() - t0, time.process_time() - c0
        save_files = {name: b - a for name, a, b in record}
        save_files["other"] = save_s - _timing.covered([(a, b) for _, a, b in record])
        save_runs.append(save_files)
        files = {p.name: p.stat().st_size for p in paths.values()}
        rss_after_export = max(rss_after_export, peak_rss_mb())
        hwm_after_export = hwm_mb()
        shutil.rmtree(out_dir)
        # The mesh writers alone, on precomputed vertex arrays.
        arrays = (result.vertices, result.mask)
        vertex_data = {"normals": result.vertex_normals(), "albedo": result.vertex_albedo()}
        t0 = time.perf_counter()
        export.write_ply(out_dir.with_suffix(".ply"), *arrays, **vertex_data)
        ply_s = time.perf_counter() - t0
        out_dir.with_suffix(".ply").unlink()
        timing = {"save": save_s, "save_cpu": save_cpu, "write_ply": ply_s}
        if spec["obj_alone"]:
            t0 = time.perf_counter()
            export.write_obj(out_dir.with_suffix(".obj"), *arrays, **vertex_data)
            timing["write_obj"] = time.perf_counter() - t0
            out_dir.with_suffix(".obj").unlink()
        del arrays, vertex_data
        exports.append(timing)
    assert result is not None
    report = {
        "timings": _median_dict(runs),
        "export": _median_dict(exports),
        "export_files": files,
        "save_files": _median_dict(save_runs),
        "iterations": len(result.history),
        "converged": bool(result.converged),
        "levels": iterations_per_level(result.history),
        "rss_base_mb": base_rss,
        "rss_reconstruct_mb": rss_after_reconstruct,
        "rss_export_mb": rss_after_export,
        "vmhwm_base_mb": base_hwm,
        "vmhwm_reconstruct_mb": hwm_after_reconstruct,
        "vmhwm_export_mb": hwm_after_export,
        "load_average": [load_average_start, os.getloadavg()],  # 1, 5, 15 min; at the start and the end
        "options": options,
        "unsupported_options": unsupported,
        "accuracy": accuracy(result, np.load(directory / "depth_gt.npy"), rig),
    }
    (directory / "result.json").write_text(json.dumps(report, indent=2), encoding="utf-8")


# --------------------------------------------------------------------------------------------------
# The parent: cases, tables, ratios
# --------------------------------------------------------------------------------------------------


def run_make(spec_path: str) -> None:
    """Renders and writes the inputs of the case described by ``spec_path`` (in a process of its
    own, so that the parent, whose peak RSS its children inherit, stays small)."""
    spec = json.loads(Path(spec_path).read_text(encoding="utf-8"))
    inputs = write_case(
        Path(spec["directory"]),
        spec["camera"],
        spec["width"],
        spec["height"],
        spec["lights"],
        spec["files"],
        spec["noise"],
    )
    Path(spec_path).write_text(json.dumps({**spec, **inputs}), encoding="utf-8")


def run_case(args: argparse.Namespace, workdir: Path, camera: str, w: int, h: int) -> dict[str, Any]:
    directory = workdir / f"{size_label(w, h)}-{camera}"
    directory.mkdir(parents=True, exist_ok=True)
    spec_path = directory / "spec.json"
    spec = {
        "directory": str(directory),
        "camera": camera,
        "width": w,
        "height": h,
        "lights": args.lights,
        "files": not args.no_files,
        "stack": args.stack,
        "noise": args.noise,
        "solver": args.solver,
        "levels": args.levels,
        "options": dict(args.option),
        "iterations": args.iterations,
        "tol": args.tol,
        "threads": args.threads,
        "repeats": args.repeats,
        "obj_alone": not args.no_obj_alone,
    }
    spec_path.write_text(json.dumps(spec), encoding="utf-8")
    print(f"[{size_label(w, h)} {camera}] rendering {args.lights} images ...", file=sys.stderr, flush=True)
    subprocess.run([sys.executable, os.path.abspath(__file__), "--make", str(spec_path)], check=True)
    inputs = json.loads(spec_path.read_text(encoding="utf-8"))
    print(
        f"[{size_label(w, h)} {camera}] rendered in {inputs['render_s']:.1f} s, written in {inputs['write_s']:.1f} s; "
        f"reconstructing in a fresh process ...",
        file=sys.stderr,
        flush=True,
    )
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", str(spec_path)])
    child_s = time.perf_counter() - t0
    case: dict[str, Any] = {
        "size": size_label(w, h),
        "width": w,
        "height": h,
        "pixels": w * h,
        "camera": camera,
        "lights": args.lights,
        "input_bytes": inputs["input_bytes"],
        "child_wall_s": child_s,
        "returncode": proc.returncode,
    }
    if proc.returncode == 0:
        case.update(json.loads((directory / "result.json").read_text(encoding="utf-8")))
    else:
        print(f"[{size_label(w, h)} {camera}] FAILED (exit code {proc.returncode})", file=sys.stderr, flush=True)
    if not args.keep:
        shutil.rmtree(directory, ignore_errors=True)
    return case


def _fmt(value: float | None, digits: int = 2) -> str:
    return "–" if value is None or (isinstance(value, float) and not math.isfinite(value)) else f"{value:.{digits}f}"


def _levels_text(levels: dict[str, dict[str, int]]) -> str:
    parts = []
    for level, stats in levels.items():
        inner = f"/{stats['inner_iterations']}" if stats.get("inner_iterations") else ""
        parts.append(f"L{level}:{stats['iterations']}{inner}")
    return " ".join(parts)


def markdown_tables(cases: list[dict[str, Any]]) -> str:
    ok = [c for c in cases if c["returncode"] == 0]
    split_keys = sorted({k for c in ok for k in c["timings"] if k.startswith("timings.") and k != "timings.total"})
    split_names = [k.split(".", 1)[1] for k in split_keys]
    head = [
        "size",
        "camera",
        "MP",
        "load s",
        "reconstruct s",
        "reconstruct CPU s",
        *[f"{n} s" for n in split_names],
        "save s",
        "save CPU s",
        "PLY s",
        "OBJ s",
        "iterations (level:outer/inner)",
        "peak RSS MB",
        "RSS − base MB",
        "normal err ° (mean/median)",
        "depth err % (max/RMS)",
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    for c in cases:
        if c["returncode"] != 0:
            lines.append(
                f"| {c['size']} | {c['camera']} | {c['pixels'] / MEGAPIXEL:.2f} | failed (exit {c['returncode']}) |"
            )
            continue
        t, e, a = c["timings"], c["export"], c["accuracy"]
        row = [
            c["size"],
            c["camera"],
            f"{c['pixels'] / MEGAPIXEL:.2f}",
            _fmt(t["load"]),
            _fmt(t["reconstruct"]),
            _fmt(t.get("reconstruct_cpu")),
            *[_fmt(t.get(k)) for k in split_keys],
            _fmt(e["save"]),
            _fmt(e.get("save_cpu")),
            _fmt(e["write_ply"]),
            _fmt(e.get("write_obj")),
            _levels_text(c["levels"]),
            f"{c['rss_export_mb']:.0f}",
            f"{c['rss_export_mb'] - c['rss_base_mb']:.0f}",
            f"{a['normal_error_mean_deg']:.3f} / {a['normal_error_median_deg']:.3f}",
            f"{a['depth_error_max_pct']:.3f} / {a['depth_error_rms_pct']:.3f}",
        ]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n\n" + save_table(ok)


def save_table(cases: list[dict[str, Any]]) -> str:
    """The save breakdown: seconds of each file ``result.save`` wrote, one column per case.

    From the creation of a file's temporary name to its rename (content computed included);
    the PNG images are encoded together in parallel while the other files are written, so their
    spans overlap the others'. "other" is the time of ``save`` outside every file.
    """
    names = sorted({n for c in cases for n in c.get("save_files", {})}, key=lambda n: (n == "other", n))
    head = ["file", *(f"{c['size']} {c['camera']}" for c in cases)]
    lines = ["Save, seconds per file:", "", "| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    for n in names:
        lines.append("| " + " | ".join([n, *(_fmt(c.get("save_files", {}).get(n), 3) for c in cases)]) + " |")
    return "\n".join(lines)


def growth(cases: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per camera: time / pixel and RSS / pixel of every size relative to the reference size (the
    smallest of at least 1 MP, else the smallest), for the reconstruction, load + reconstruction
    + export, and peak RSS minus the base RSS."""
    rows = []
    for camera in sorted({c["camera"] for c in cases}):
        runs = sorted((c for c in cases if c["camera"] == camera and c["returncode"] == 0), key=lambda c: c["pixels"])
        if not runs:
            continue
        big = [c for c in runs if c["pixels"] >= MEGAPIXEL]
        ref = big[0] if big else runs[0]

        def per_pixel(c: dict[str, Any]) -> dict[str, float]:
            t = c["timings"]
            return {
                "reconstruct": t["reconstruct"] / c["pixels"],
                "end_to_end": (t["load"] + t["reconstruct"] + c["export"]["save"]) / c["pixels"],
                "rss": (c["rss_export_mb"] - c["rss_base_mb"]) / c["pixels"],
            }

        base = per_pixel(ref)
        for c in runs:
            p = per_pixel(c)
            rows.append(
                {
                    "camera": camera,
                    "size": c["size"],
                    "reference": ref["size"],
                    "pixels": c["pixels"],
                    "us_per_pixel_reconstruct": 1e6 * p["reconstruct"],
                    "us_per_pixel_end_to_end": 1e6 * p["end_to_end"],
                    "bytes_per_pixel_rss": p["rss"] * 1024 * 1024,
                    **{f"growth_{k}": p[k] / base[k] for k in p},
                }
            )
    return rows


def growth_table(rows: list[dict[str, Any]], limit: float) -> str:
    head = [
        "camera",
        "size",
        "µs/pixel reconstruct",
        "µs/pixel load+reconstruct+save",
        "RSS bytes/pixel",
        "growth reconstruct",
        "growth end-to-end",
        "growth RSS",
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    for r in rows:
        marks = {
            k: ("" if r[f"growth_{k}"] <= limit or r["pixels"] < MEGAPIXEL else " ⚠")
            for k in ("reconstruct", "end_to_end", "rss")
        }
        lines.append(
            "| "
            + " | ".join(
                [
                    r["camera"],
                    r["size"],
                    f"{r['us_per_pixel_reconstruct']:.3f}",
                    f"{r['us_per_pixel_end_to_end']:.3f}",
                    f"{r['bytes_per_pixel_rss']:.0f}",
                    f"{r['growth_reconstruct']:.2f}{marks['reconstruct']}",
                    f"{r['growth_end_to_end']:.2f}{marks['end_to_end']}",
                    f"{r['growth_rss']:.2f}{marks['rss']}",
                ]
            )
            + " |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--sizes",
        type=parse_size,
        nargs="+",
        default=[parse_size(s) for s in "256 512 1024 2048 4096 4000x3000".split()],
        help="N (N x N) or WxH (default: 256 512 1024 2048 4096 4000x3000)",
    )
    parser.add_argument("--lights", type=int, default=16, help="point lights on the ring (default 16)")
    parser.add_argument(
        "--cameras", nargs="+", choices=("orthographic", "pinhole"), default=["orthographic", "pinhole"]
    )
    parser.add_argument("--solver", help="passed to nplps.reconstruct if it has solver= (auto, direct, multigrid)")
    parser.add_argument("--levels", type=int, help="pyramid levels, passed to nplps.reconstruct if it has levels=")
    parser.add_argument(
        "--option",
        type=parse_option,
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="another keyword of nplps.reconstruct (repeatable), e.g. reflectance=glossy, shadows=true, "
        "interreflections=true, robust=tukey, depth_mode=auto; values are read as JSON where they parse",
    )
    parser.add_argument(
        "--noise", type=float, default=0.0, help="Gaussian image noise, a fraction of the brightest value (default 0)"
    )
    parser.add_argument("--iterations", type=int, default=10, help="maximum iterations (per level) (default 10)")
    parser.add_argument("--tol", type=float, default=1e-6, help="stopping tolerance (default 1e-6, the library's)")
    parser.add_argument(
        "--repeats", type=int, default=1, help="runs per case in its process; medians reported (default 1)"
    )
    parser.add_argument("--threads", type=int, help="solver threads (default: all cores)")
    parser.add_argument(
        "--no-files", action="store_true", help="pass the images as a uint16 array instead of PNG files"
    )
    parser.add_argument(
        "--stack",
        choices=("uint16", "float32"),
        default="uint16",
        help="the stack reconstruct gets: the 16-bit images as they are (uint16, read in place; the "
        "default) or converted to float32 (as before issue 23)",
    )
    parser.add_argument(
        "--no-obj-alone", action="store_true", help="skip the separate write_obj timing (save writes OBJ up to 4 MP)"
    )
    parser.add_argument("--workdir", help="where the cases are written (default: a new temporary directory)")
    parser.add_argument("--keep", action="store_true", help="keep the images and rigs of every case")
    parser.add_argument("--limit", type=float, default=1.5, help="growth per pixel flagged above this (default 1.5)")
    parser.add_argument("--json", help="also write the results to this JSON file")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--make", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        run_child(args.child)
        return
    if args.make:
        run_make(args.make)
        return
    if args.lights < 3 or args.repeats < 1:
        parser.error("--lights must be at least 3 and --repeats at least 1")

    _, unsupported = supported_options({"solver": args.solver, "levels": args.levels, **dict(args.option)})
    if unsupported:
        print(f"note: this nplps.reconstruct has no {', '.join(unsupported)} option; ignored", file=sys.stderr)
    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="nplps-scale-"))
    workdir.mkdir(parents=True, exist_ok=True)
    cases = []
    try:
        for w, h in args.sizes:
            for camera in args.cameras:
                cases.append(run_case(args, workdir, camera, w, h))
    finally:
        if not args.keep and not args.workdir:
            shutil.rmtree(workdir, ignore_errors=True)
    rows = growth(cases)
    settings = f"solver={args.solver or 'default'}, levels={args.levels if args.levels is not None else 'default'}" + (
        f" (unsupported: {', '.join(unsupported)})" if unsupported else ""
    )
    settings += "".join(f", {name}={value}" for name, value in args.option)
    print(
        f"\nnplps {nplps.__version__}, {args.lights} lights, noise {args.noise:g},"
        f" {'arrays' if args.no_files else '16-bit PNG files'}, "
        f"{settings}, iterations {args.iterations}, tol {args.tol:g}, threads {args.threads or 'all'} "
        f"({os.cpu_count()} CPUs); medians of {args.repeats} run(s); seconds\n"
    )
    print(markdown_tables(cases))
    print(
        f"\nPer pixel, relative to the reference size (growth ≤ {args.limit:g} is within the acceptance; ⚠ above, "
        "for sizes of at least 1 MP):\n"
    )
    print(growth_table(rows, args.limit))
    if args.json:
        payload = {
            "nplps": nplps.__version__,
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "args": {k: v for k, v in vars(args).items() if k not in ("child", "make")},
            "unsupported_options": unsupported,
            "cases": cases,
            "growth": rows,
        }
        Path(args.json).write_text(json.dumps(payload, indent=2) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
