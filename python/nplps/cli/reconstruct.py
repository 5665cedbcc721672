"""``nplps reconstruct``: reconstruct from images and a rig, write the results, print a summary."""

from __future__ import annotations

import argparse
import os
import textwrap
import time
from pathlib import Path
from typing import Any, Literal

import numpy as np

from .._text import printable
from ..errors import InputError
from ..progress import Bar, ReconstructionProgress, aborting, format_duration
from .console import _warnings_to_stderr, describe_rig, describe_size
from .inputs import (
    CONVENTIONS,
    INPUT_NOTES,
    _estimated,
    add_input_options,
    build_inputs,
    check_input_args,
    near_options,
)
from .options import OUTPUT, add_options, api_options
from .outputs import add_output_options, output_directory, writing

RECONSTRUCT_DESCRIPTION = f"""\
Reconstruct a surface from k images taken under the k lights of a rig.

Writes into --out: mesh.ply and mesh.obj (the masked surface, vertex normals, albedo as colour;
mesh.obj only up to 4 million masked pixels unless --obj), normals.png (16-bit normal map in
the --normal-map convention), shaded.png (the mesh lit from the upper left), albedo.png
(16-bit), depth.npy / depth.tiff (vertex depths, (H+1, W+1), NaN where no masked pixel),
normals.npy, residual.npy and summary.json (with all the options), and with --refine-lights the
refined rig (rig_refined.json); with --formats also mesh.stl, mesh.glb, points.ply and/or
normals.tiff, with --exr depth.exr, normals.exr and albedo.exr; mask.png, lights_used.npy,
history.csv (convergence), rig.json (the result's rig) and inputs.png (thumbnails of the
images) for the report; report.html, one self-contained page to look at the result (unless
--no-report; `nplps report DIR` re-makes it); last nplps-manifest.json, the list of the files
written. RGB images give an RGB albedo unless --gray.

--out must be a new or empty directory unless --overwrite is given: then files of the same
names are replaced, the files of an earlier nplps result there that this run does not write
(listed in its nplps-manifest.json, e.g. distance_curve.csv or baseline/) are removed, and any
other file is kept. Every file is written under a temporary name and renamed when complete, so
an error or Ctrl-C never leaves a truncated file under its final name.

{INPUT_NOTES}
{textwrap.fill(CONVENTIONS, 95)}
"""

RECONSTRUCT_EPILOG = """\
examples:
  # all images of a folder (sorted by name; files with 'mask' or 'ambient' in the name are skipped):
  nplps reconstruct shots/ --rig rig.json --mask shots/mask.png --depth 250 --out result
  # explicit files, in the rig's light order, initial depth map from a previous run:
  nplps reconstruct a.png b.png c.png d.png --rig rig.json --depth result/depth.npy --out refined
  # compare with conventional (parallel-light) photometric stereo, written to result/baseline:
  nplps reconstruct shots/ --rig rig.json --depth 250 --out result --baseline
  # camera JPEGs from a pinhole rig: decode sRGB, subtract the ambient shot, cos^4, 4 x 4 bins:
  nplps reconstruct shots/ --rig rig.json --depth 200 --srgb --ambient shots/ambient.jpg \\
      --vignetting cos4 --bin 4 --robust tukey --out result
  # a near_ps capture folder (a glob pattern after the folder picks its images if needed):
  nplps reconstruct --capture near_ps hehe12/ 'photometric_sample_raw_[0-9]*.png' \\
      --depth 200 --bin 4 --out hehe12-result
  # LED intensities that disagree with the rig file: refine them (rig_refined.json is written):
  nplps reconstruct --capture near_ps hehe12/ 'photometric_sample_raw_[0-9]*.png' \\
      --depth 200 --bin 4 --refine-lights intensity --out hehe12-refined
  # also a glTF binary (y up, for web viewers), an STL and 32-bit float normals:
  nplps reconstruct shots/ --rig rig.json --depth 250 --formats glb,stl,normals_tiff --opengl --out result
  # a 16-bit normal map for Unreal Engine (DirectX, y down), float EXR maps, a scale in mm:
  nplps reconstruct shots/ --rig rig.json --depth 250 --normal-map directx --exr --units mm --out result
  # the presets of the shared captures (their images, sRGB decoding, light rows and grid):
  nplps reconstruct --capture hehe12 hehe12/ --depth 200 --bin 4 --out hehe12-result
  nplps reconstruct --capture queau_human1 queau_human1/ --depth 700 --bin 8 --out human1-result
  # some lights only: rows of the rig's lights, one per image in the images' order:
  nplps reconstruct a.png b.png c.png d.png --rig rig.json --lights 0,2,4,6 --depth 250 --out result
  # images on a smaller grid than the calibration's: pad them (zeros, bottom/right) to H,W:
  nplps reconstruct shots/ --rig rig.json --grid-shape 1732,2601 --depth 700 --out result
  # a DiLiGenT object, grey:
  nplps reconstruct --capture diligent ballPNG/ --depth 1000 --gray --out ball
"""


def add_reconstruct_parser(sub: Any, formatter: Any) -> argparse.ArgumentParser:
    """Add the ``reconstruct`` command and its options to the subparsers ``sub``; return its parser."""
    p = sub.add_parser(
        "reconstruct",
        help="reconstruct a mesh, normals and albedo from images and a rig file",
        description=RECONSTRUCT_DESCRIPTION,
        epilog=RECONSTRUCT_EPILOG,
        formatter_class=formatter,
    )
    add_input_options(p)
    add_output_options(p)
    add_options(p, OUTPUT)
    p.add_argument(
        "--no-report",
        dest="report",
        action="store_false",
        help="do not write report.html (nplps report DIR makes it later from the files written)",
    )
    p.add_argument(
        "--baseline",
        action="store_true",
        help="also run parallel-light photometric stereo and write it to DIR/baseline",
    )
    return p


def cmd_reconstruct(args: argparse.Namespace) -> int:
    """Run ``nplps reconstruct``; return the exit status."""
    from ..api import reconstruct, reconstruct_parallel
    from ..export import ContactSheet, check_formats

    check_input_args(args)
    args.formats = api_options(args, ("--formats", "--exr", "--obj"))["formats"]  # one list
    check_formats(args.formats)  # the exr format without OpenEXR is refused before the images are read
    if args.units is not None and not args.units.strip():
        raise InputError("--units must not be empty (e.g. --units mm)")
    near = near_options(args)
    out = output_directory(args)  # refuses a non-empty --out before the images are read
    inputs = build_inputs(args)
    out.protect(inputs.sources)  # a result written beside its inputs never removes them
    common = dict(inputs.options, valid=inputs.valid)
    # The images are held by `images` alone, so that they can be freed before the export.
    images: np.ndarray = inputs.images
    rig, mask, steps = inputs.rig, inputs.mask, list(inputs.steps)
    del inputs
    start = time.perf_counter()
    display = None if args.quiet else ReconstructionProgress(args.iterations)
    with _warnings_to_stderr():
        with aborting(display):
            result = reconstruct(images, rig, mask=mask, progress=display, **near, **common)
        if display is not None:
            display.finish(result)
    wall = time.perf_counter() - start
    # inputs.png is made now; without --baseline the images are not needed any more and go
    # before the export, whose peak they would otherwise raise (3.3 GB at 100 MP x 16 lights).
    sheet = ContactSheet.of(images)
    kept: np.ndarray | None = images if args.baseline else None
    del images
    with writing(out):  # one run: the manifest lists the baseline's files too
        recorded = {**_recorded_args(args), "preprocessing": steps, "solver_options": {**near, **common}}
        paths = _save(result, out, args, quiet=args.quiet, report=args.report, inputs=sheet, options=recorded)
        _print_summary("near-light reconstruction (nplps)", result, wall, paths)

        if args.baseline:
            start = time.perf_counter()
            with _warnings_to_stderr():
                # The baseline refines its own intensities under its own model, as the near-light run does.
                refine: Literal["intensity"] | None = (
                    "intensity" if args.refine_lights in ("intensity", "both") else None
                )
                # ... and fits the same reflectance model (its own lobe, unless one is given).
                glossy = {k: near[k] for k in ("reflectance", "roughness", "eta") if near.get(k) is not None}
                assert kept is not None  # the images, kept for the baseline
                base = reconstruct_parallel(
                    kept,
                    rig,
                    mask=mask,
                    refine_lights=refine,
                    **glossy,
                    **_estimated(result, common),
                )
            wall = time.perf_counter() - start
            base_paths = _save(base, out.subdirectory("baseline"), args, quiet=args.quiet)
            print()
            _print_summary("parallel-light baseline", base, wall, base_paths)
    return 0


def _recorded_args(args: argparse.Namespace) -> dict[str, Any]:
    """Return the command's arguments as given (without the parser's internals), for summary.json."""
    return {"command": "reconstruct", **{k: v for k, v in vars(args).items() if k not in ("func",)}}


def _save(result: Any, directory: Any, args: argparse.Namespace, *, quiet: bool, **extra: Any) -> dict[str, Path]:
    """Write a result (``extra``: more keywords of ``save``), with an export line on stderr (a bar on a terminal)."""
    bar = None if quiet else Bar("export")
    if bar is not None:
        bar.update(0, f"writing into {os.fspath(directory)} ...")
    with aborting(bar):
        paths = result.save(
            directory,
            opengl=args.opengl,
            formats=args.formats,
            normal_map=args.normal_map,
            normal_map_bits=args.normal_map_bits,
            units=args.units,
            **extra,
        )
    if bar is not None:
        bar.close(f"{len(paths)} files written in {format_duration(bar.elapsed)}")
    return dict(paths)


def _print_summary(title: str, result: Any, wall: float, paths: dict[str, Path]) -> None:
    s = result.summary()
    print(f"{title}:")
    print(f"  rig             {describe_rig(result.rig)}")
    print(f"  pixels          {s['pixels']} of {describe_size(s['shape'])}")
    print(f"  regions         {s['regions']}")
    if result.distance is not None:
        # The search's own iterations are not the result's: say what each number counts.
        candidates = max((len(curve) for curve in result.distance.curve), default=0)
        print(f"  distance search {candidates} candidate distances evaluated (a few iterations each)")
        print(f"  iterations      {s['iterations']}{_per_level(result)} (the final solve at the estimated distance)")
    elif result.method == "near":  # the baseline does not iterate
        print(f"  iterations      {s['iterations']}{_per_level(result)}")
    print(f"  status          {s['status']}: {s['status_reason']}")
    if s["rms_residual"] is not None:
        print(f"  rms residual    {s['rms_residual']:.3e} (image units, 0..1)")
    trust = s.get("trust") or {}
    if trust.get("normal_sigma_deg"):
        sigma, held = trust["normal_sigma_deg"], trust["held_out_error"]
        print(
            f"  uncertainty     normals {sigma['median']:.3g}° median, {sigma['p90']:.3g}° at the 90th percentile; "
            f"held-out error {held['median']:.3e} median (normal_sigma.tiff, held_out_error.tiff)"
        )
    print(f"  unfitted pixels {s['unfitted_pixels']} (fewer than 3 lit images)")
    lo, hi = s["depth_range"]
    print(f"  depth range     {lo:.6g} .. {hi:.6g}")
    if s.get("estimated_distance"):
        estimates = ", ".join(f"{d:.6g}" for d in s["estimated_distance"])
        print(f"  distance        {estimates} (estimated; residual curve in distance_curve.csv / .svg)")
    check = result.distance_check
    if check is not None:
        verdict = "LOOKS WRONG, try --depth auto" if check.looks_wrong else "agrees"
        print(
            f"  distance check  {verdict}: a {check.side}-pixel level fits {check.found:.4g} "
            f"(given {check.given:.4g}: residual {check.ratio:.3g} times the best)"
        )
    if result.refinement is not None:
        _print_refinement(result)
    print(f"  time            {wall:.2f} s (solver {s['timings'].get('total', float('nan')):.2f} s)")
    files = sorted({str(p.parent) for p in paths.values()})
    # A folder named with escape codes is shown, not obeyed by the terminal.
    print(printable(f"  files written   in {', '.join(files)}: {', '.join(p.name for p in paths.values())}"))


def _per_level(result: Any) -> str:
    """Return ``: 3 at level 1, 2 at full resolution`` for a coarse-to-fine run, else ``""``."""
    levels = sorted({h.level for h in result.history}, reverse=True)
    if len(levels) < 2:
        return ""
    counts = [(level, sum(h.level == level for h in result.history)) for level in levels]
    return ": " + ", ".join(f"{n} at {f'level {level}' if level else 'full resolution'}" for level, n in counts)


def _print_refinement(result: Any) -> None:
    """Print the light refinement's report.

    First what happened, then per light the change and its standard error.
    """
    ref = result.refinement
    state = "refined"
    if ref.fell_back:
        state = (
            f"dropped: it did not lower the residual of a run without it ({ref.residual_with:.3e} vs "
            f"{ref.residual_without:.3e}); the rig's lights were kept"
        )
    elif ref.stopped:
        state = "stopped early (the residual rose); the lights of the lowest residual were kept"
    print(f"  lights          {ref.mode}: {state}")
    if ref.singular_values is not None and len(ref.singular_values):
        print(
            f"                  conditioning {ref.condition_number:.3g} (singular values "
            f"{ref.singular_values[0]:.3g} .. {ref.singular_values[-1]:.3g}, normals eliminated)"
        )
    se = ref.standard_errors
    for row in result.light_changes():
        i = row["light"]
        line = f"    light {i:>2}: intensity x {row['intensity_factor']:.4f}"
        if se is not None and se[i][0] == se[i][0]:
            line += f" (+/- {100 * se[i][0]:.2f} %)"
        if row["position_shift"] is not None and ref.mode in ("position", "both"):
            dx, dy, dz = row["position_shift"]
            line += f", moved ({dx:+.3g}, {dy:+.3g}, {dz:+.3g})"
            if se is not None and se[i][1] == se[i][1]:
                line += f" (+/- {se[i][1]:.2g}, {se[i][2]:.2g}, {se[i][3]:.2g})"
        print(line)
