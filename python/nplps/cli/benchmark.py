"""``nplps benchmark luces DIR``: reconstruct every LUCES object and compare with its ground truth."""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import os
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from .._atomic import write_text
from ..errors import InputError, NplpsError
from .console import _note, _warnings_to_stderr, describe_size

BENCHMARK_DESCRIPTION = """\
Reconstruct every object of a benchmark dataset with ground truth and print, per object, the
angular error of the normals (mean, median, degrees) and the depth error (RMS and mean absolute,
mm) against the ground truth, the time, and the published numbers beside.

Dataset: luces -- LUCES (Mecca et al.; 14 objects, 52 LEDs): DIR is the dataset's data folder
(one folder per object, each with led_params.txt, 01.png .. 52.png, mask.png, normals.png and
zgt.npz) or one object folder; see docs/luces.md for the layout and its sources. Each object is
reconstructed from its calibration (point lights with RGB Phi and mu, pinhole K from f, x0, y0)
starting from a plane at its mean_distance. Published per-object numbers could not be sourced;
only published averages are printed, under the table.

The errors are measured over the pixels of the (binned) mask where the ground truth is known.
The table is also written as luces_benchmark.json and luces_benchmark.csv in --out.

exit status: 0 every object ran, 1 some object could not be read or reconstructed (its row reads
nan, the message is on stderr), 2 invalid input.
"""

BENCHMARK_EPILOG = """\
examples:
  nplps benchmark luces LUCES/data --bin 4
  nplps benchmark luces LUCES/data --objects Ball,Bell --bin 4 --out bench
"""

#: Columns of the table and of luces_benchmark.csv.
BENCHMARK_COLUMNS = (
    "object",
    "pixels",
    "mean_deg",
    "median_deg",
    "depth_rms_mm",
    "depth_mean_abs_mm",
    "seconds",
    "published_mean_deg",
)

_HEADINGS = ("object", "pixels", "mean [deg]", "median [deg]", "depth RMS [mm]", "depth |err| [mm]", "time [s]")


def add_benchmark_parser(sub: Any, formatter: Any) -> argparse.ArgumentParser:
    """Add the ``benchmark`` command and its options to the subparsers ``sub``; return its parser."""
    p = sub.add_parser(
        "benchmark",
        help="reconstruct a dataset with ground truth (LUCES) and print the errors beside published numbers",
        description=BENCHMARK_DESCRIPTION,
        epilog=BENCHMARK_EPILOG,
        formatter_class=formatter,
    )
    p.add_argument("dataset", choices=("luces",), help="the dataset's layout")
    p.add_argument("folder", metavar="DIR", help="the dataset folder (its object folders) or one object folder")
    p.add_argument("--objects", metavar="A,B,...", help="only these objects (folder names, comma-separated)")
    p.add_argument("--bin", type=int, default=1, metavar="N", help="average N x N pixel blocks first (default 1)")
    p.add_argument("--gray", action="store_true", help="average R, G, B (and Phi) to grey before reconstructing")
    p.add_argument(
        "--vignetting",
        choices=("none", "cos4"),
        default="none",
        help="divide the images by the cos^4 vignetting map of K (default none: LUCES's own code does not)",
    )
    p.add_argument(
        "--one-based",
        action="store_true",
        help="read x0, y0 of led_params.txt as 1-based (MATLAB) pixel coordinates (default: 0-based)",
    )
    p.add_argument("--iterations", type=int, default=10, metavar="N", help="solver iterations (default 10)")
    p.add_argument("--threads", type=int, metavar="N", help="threads of the solver (default: all cores)")
    p.add_argument("--out", default=".", metavar="DIR", help="where to write luces_benchmark.json/.csv (default .)")
    p.add_argument("-q", "--quiet", action="store_true", help="print only the table")
    return p


def _bin_ground_truth(
    normals: np.ndarray | None, depth: np.ndarray | None, factor: int
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Bin ground-truth normals (block mean, renormalized) and depth (block mean) like the images.

    A binned pixel is known only when every pixel of its block is (the remainder rows and columns
    are cropped, as :func:`nplps.preprocess.bin_images` does).
    """
    if factor == 1:
        return normals, depth

    def blocks(a: np.ndarray) -> np.ndarray:
        h, w = a.shape[0] // factor, a.shape[1] // factor
        a = a[: h * factor, : w * factor]
        return a.reshape(h, factor, w, factor, *a.shape[2:])

    n_out = None
    if normals is not None:
        b = blocks(normals)
        known = np.all(np.linalg.norm(b, axis=-1) > 0, axis=(1, 3))
        mean = b.mean(axis=(1, 3))
        length = np.linalg.norm(mean, axis=-1)
        n_out = np.zeros_like(mean)
        known &= length > 0
        n_out[known] = mean[known] / length[known, None]
    d_out = None
    if depth is not None:
        d_out = blocks(depth).mean(axis=(1, 3))  # NaN when any pixel of the block is unknown
    return n_out, d_out


def pixel_depth(vertex_depth: np.ndarray) -> np.ndarray:
    """Depth at the pixel centres: the mean of each pixel's four vertex depths (H+1, W+1) -> (H, W)."""
    v = np.asarray(vertex_depth, dtype=np.float64)
    return 0.25 * (v[:-1, :-1] + v[:-1, 1:] + v[1:, :-1] + v[1:, 1:])


def object_errors(
    normals: np.ndarray, depth: np.ndarray, normals_gt: np.ndarray | None, depth_gt: np.ndarray | None, mask: np.ndarray
) -> dict[str, float]:
    """Angular errors (degrees) and depth errors (mm) of one reconstruction against its ground truth.

    ``normals`` (H, W, 3) and ``depth`` (H, W, at the pixel centres) are the reconstruction's;
    the errors are taken over ``mask`` where the ground truth is known and the reconstruction
    finite.
    """
    out = {"pixels": 0.0, "mean_deg": math.nan, "median_deg": math.nan}
    out.update(depth_rms_mm=math.nan, depth_mean_abs_mm=math.nan)
    if normals_gt is not None:
        use = mask & (np.linalg.norm(normals_gt, axis=-1) > 0) & np.all(np.isfinite(normals), axis=-1)
        dot = np.sum(normals[use] * normals_gt[use], axis=-1)
        err = np.degrees(np.arccos(np.clip(dot, -1.0, 1.0)))
        out["pixels"] = float(use.sum())
        if err.size:
            out["mean_deg"], out["median_deg"] = float(err.mean()), float(np.median(err))
    if depth_gt is not None:
        use = mask & np.isfinite(depth_gt) & np.isfinite(depth)
        diff = depth[use] - depth_gt[use]
        if diff.size:
            out["depth_rms_mm"] = float(np.sqrt(np.mean(diff**2)))
            out["depth_mean_abs_mm"] = float(np.mean(np.abs(diff)))
        if normals_gt is None:
            out["pixels"] = float(use.sum())
    return out


def run_luces_object(folder: Path, args: argparse.Namespace) -> dict[str, Any]:
    """Load, prepare, reconstruct and score one LUCES object; return its row."""
    from ..api import reconstruct
    from ..captures import load_luces, prepare

    # The images are read by prepare, which corrects and bins them in place: one full-size stack at
    # most (52 RGB float32 images of 2048 x 1536 would take 2 GB).
    capture = load_luces(folder, color=False if args.gray else None, one_based=args.one_based)
    normals_gt, depth_gt = capture.normals_gt, capture.depth_gt
    prepared = prepare(
        capture,
        bin_factor=args.bin,
        ambient=False,
        vignetting="cos4" if args.vignetting == "cos4" else None,
        color=False if args.gray else None,
    )
    normals_gt, depth_gt = _bin_ground_truth(normals_gt, depth_gt, args.bin)
    assert isinstance(prepared.images, np.ndarray)
    mask = prepared.mask if prepared.mask is not None else np.ones(prepared.images.shape[1:3], dtype=bool)
    if not args.quiet:
        _note(f"{folder.name}: {prepared.num_images} images, {describe_size(prepared.images.shape[1:3])}")
    start = time.perf_counter()
    with _warnings_to_stderr():
        result = reconstruct(
            prepared.images,
            prepared.rig(),
            depth=capture.mean_distance if capture.mean_distance is not None else "auto",
            iterations=args.iterations,
            threads=args.threads,
            **prepared.options(),
        )
    seconds = time.perf_counter() - start
    row: dict[str, Any] = {"object": folder.name}
    row.update(object_errors(result.normals, pixel_depth(result.depth), normals_gt, depth_gt, mask))
    row["seconds"] = seconds
    return row


def cmd_benchmark(args: argparse.Namespace) -> int:
    """Run ``nplps benchmark``; return the exit status (1 when an object failed)."""
    from ..captures.luces import N_OBJECTS, PUBLISHED, find_luces_objects

    if args.bin < 1:
        raise InputError(f"--bin must be at least 1, got {args.bin}")
    if args.iterations < 1:
        raise InputError(f"--iterations must be at least 1, got {args.iterations}")
    names = None if args.objects is None else [o.strip() for o in args.objects.split(",") if o.strip()]
    folders = find_luces_objects(args.folder, names)
    rows: list[dict[str, Any]] = []
    failed = []
    for folder in folders:
        try:
            row = run_luces_object(folder, args)
        except NplpsError as e:  # an unreadable folder or a failed run: its row reads nan, the others go on
            failed.append(f"{folder.name}: {e}")
            row = {"object": folder.name, "pixels": 0.0, "seconds": math.nan}
            row.update(mean_deg=math.nan, median_deg=math.nan, depth_rms_mm=math.nan, depth_mean_abs_mm=math.nan)
        row["published_mean_deg"] = None  # no per-object number could be sourced (see captures/luces.py)
        rows.append(row)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all rows nan
        means = {k: float(np.nanmean([r[k] for r in rows])) for k in BENCHMARK_COLUMNS[2:7]}
    _print_table(rows, means)
    print(f"\npublished mean angular error over the {N_OBJECTS} LUCES objects (per-object numbers not included):")
    for method, value in PUBLISHED.items():
        print(f"  {method}: {value:.1f} deg")
    if len(folders) != N_OBJECTS:
        print(f"(these averages are over all {N_OBJECTS} objects; this run has {len(folders)}: compare with care)")
    for line in failed:
        _note(f"nplps: warning: object {line}; its row reads nan")
    record = {
        "dataset": "luces",
        "folder": os.fspath(args.folder),
        "bin": args.bin,
        "gray": args.gray,
        "vignetting": args.vignetting,
        "one_based": args.one_based,
        "iterations": args.iterations,
        "objects": [{k: _num(v) for k, v in r.items()} for r in rows],
        "mean": {k: _num(v) for k, v in means.items()},
        "published_mean_deg": PUBLISHED,
        "notes": f"published per-object numbers not sourced; averages are over the {N_OBJECTS} LUCES objects",
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "luces_benchmark.json", json.dumps(record, indent=2) + "\n")
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=BENCHMARK_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: _cell(r.get(k)) for k in BENCHMARK_COLUMNS})
    writer.writerow({"object": "mean", **{k: _cell(v) for k, v in means.items()}, "published_mean_deg": ""})
    write_text(out / "luces_benchmark.csv", text.getvalue())
    if not args.quiet:
        _note(f"wrote {out / 'luces_benchmark.json'} and {out / 'luces_benchmark.csv'}")
    return 1 if failed else 0


def _num(v: Any) -> Any:
    """JSON value: NaN as null."""
    return None if isinstance(v, float) and not math.isfinite(v) else v


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return "nan" if not math.isfinite(v) else f"{v:.6g}"
    return str(v)


def _print_table(rows: list[dict[str, Any]], means: dict[str, float]) -> None:
    width = max([len("object")] + [len(r["object"]) for r in rows]) + 2
    widths = [width] + [len(h) + 2 for h in _HEADINGS[1:]]
    print(f"{_HEADINGS[0]:<{width}}" + "".join(f"{h:>{w}}" for h, w in zip(_HEADINGS[1:], widths[1:], strict=True)))
    keys = BENCHMARK_COLUMNS[1:7]
    for r in rows:
        cells = [f"{int(r['pixels']):>{widths[1]}}"]
        cells += [f"{r[k]:>{w}.3f}" for k, w in zip(keys[1:], widths[2:], strict=True)]
        print(f"{r['object']:<{width}}" + "".join(cells))
    cells = [f"{'':>{widths[1]}}"] + [f"{means[k]:>{w}.3f}" for k, w in zip(keys[1:], widths[2:], strict=True)]
    print(f"{'mean':<{width}}" + "".join(cells))
