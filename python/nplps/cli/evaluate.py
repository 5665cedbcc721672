"""The ``nplps evaluate`` command: held-out-light errors, printed as a table.

``nplps evaluate``: held-out-light errors of the near-light method and of the parallel-light
baseline, printed as a table.
"""

from __future__ import annotations

import argparse
import os
import time
import warnings
from typing import TYPE_CHECKING, Any

import numpy as np

from .._held_out import FailedHeldOut
from ..errors import InputError, SolverError
from ..progress import Bar, ReconstructionProgress, aborting, format_duration
from .console import PROG, _note, _warnings_to_stderr
from .inputs import INPUT_NOTES, _estimated, add_input_options, build_inputs, near_options
from .parsers import parse_lights

if TYPE_CHECKING:
    from ..evaluation import HeldOut

EVALUATE_DESCRIPTION = f"""\
Check a rig and its reconstruction without ground truth: leave each light out in turn,
reconstruct from the others, predict the left-out image and compare it with the captured one.
Runs the near-light method (nplps) and the parallel-light baseline and prints, per light:
the relative error |prediction - image| / |image| over the masked, usable pixels, and the
shape error (the same after the best gain, free of the light's intensity calibration), plus
the means, and a one-line reading: which model predicts the held-out images better, by how
much, on the mean shape error, or "mixed" when the mean relative errors clearly say the
opposite. Lower is better; a better light model predicts better. RGB images are averaged to
grey.

{INPUT_NOTES}"""

EVALUATE_EPILOG = """\
examples:
  nplps evaluate shots/ --rig rig.json --mask shots/mask.png --depth 250
  nplps evaluate --capture near_ps hehe12/ 'photometric_sample_raw_[0-9]*.png' --depth 200 \\
      --bin 8 --lights 0,3,5
  nplps evaluate --capture queau_human1 queau_human1/ --depth 700 --bin 16 --use-lights 0,1,2,3,5
"""

EVALUATE_COLUMNS = ("light", "near rel. error", "near shape error", "parallel rel. error", "parallel shape error")


def add_evaluate_parser(sub: Any, formatter: Any) -> argparse.ArgumentParser:
    """Add the ``evaluate`` command and its options to the subparsers ``sub``; return its parser."""
    p = sub.add_parser(
        "evaluate",
        help="held-out-light errors of the near-light method and of the parallel-light baseline",
        description=EVALUATE_DESCRIPTION,
        epilog=EVALUATE_EPILOG,
        formatter_class=formatter,
    )
    add_input_options(p, lights_flag="--use-lights")
    p.add_argument("--lights", metavar="I,J,...", help="the lights to leave out, 0-based, e.g. 0,3,5 (default: all)")
    p.add_argument(
        "--out",
        metavar="RESULT_DIR",
        help="also write the table into this result directory (of nplps reconstruct on the same "
        "capture) as held_out.json and re-make its report.html, whose held-out section shows it",
    )
    return p


def cmd_evaluate(args: argparse.Namespace) -> int:
    """Run ``nplps evaluate``; return the exit status."""
    from ..evaluation import held_out

    if args.out is not None and not os.path.isfile(os.path.join(args.out, "summary.json")):
        raise InputError(f"--out '{args.out}' is not a result directory (no summary.json): run nplps reconstruct first")
    inputs = build_inputs(args)
    lights = parse_lights(args.lights, inputs.rig.n_lights)
    if inputs.options["depth"] == "auto":
        from ..api import reconstruct

        display = None if args.quiet else ReconstructionProgress(args.iterations)
        with _warnings_to_stderr():
            with aborting(display):
                estimate = reconstruct(
                    inputs.images,
                    inputs.rig,
                    mask=inputs.mask,
                    valid=inputs.valid,
                    progress=display,
                    **inputs.options,
                    **near_options(args),
                )
            if display is not None:
                display.finish(estimate)
        assert estimate.distance is not None  # depth="auto" always estimates it
        distances = ", ".join(f"{d:.6g}" for d in estimate.distance.distance)
        _note(f"estimated working distance (all lights): {distances}")
        inputs = inputs._replace(options=_estimated(estimate, inputs.options))
    rows = []
    found: dict[str, list[HeldOut | FailedHeldOut]] = {"near": [], "parallel": []}
    failed: list[str] = []
    bar = None if args.quiet else Bar("held-out", total=len(lights))
    with aborting(bar):
        for done, light in enumerate(lights):
            start = time.perf_counter()
            row: list[float] = [light]
            for method in ("near", "parallel"):
                h: HeldOut | FailedHeldOut
                try:
                    with _warnings_to_stderr():
                        (h,) = held_out(
                            inputs.images,
                            inputs.rig,
                            mask=inputs.mask,
                            method=method,
                            lights=[light],
                            valid=inputs.valid,
                            **inputs.options,
                            **near_options(args),
                        )
                except SolverError as e:
                    # One light's run failing does not void the others': its row reads nan.
                    failed.append(f"light {light} left out, {method} model: {e}")
                    h = FailedHeldOut(light, str(e))
                row += [h.relative_error, h.shape_error]
                found[method].append(h)
            rows.append(row)
            if bar is not None:
                left = (len(lights) - done - 1) * bar.elapsed / (done + 1)
                took = format_duration(time.perf_counter() - start)
                bar.update(done + 1, f"light {light} left out in {took}, ~{format_duration(left)} left")
    if bar is not None:
        bar.close(f"{len(lights)} lights left out one at a time in {format_duration(bar.elapsed)}")
    _print_evaluation(rows, inputs.rig.n_lights)
    if failed:
        for line in failed:
            _note(f"{PROG}: warning: the reconstruction failed ({line}); its row reads nan")
        print(f"\n{len(failed)} of {2 * len(lights)} held-out runs failed (see the warnings); the means leave them out")
    if all(isinstance(h, FailedHeldOut) for h in found["near"]):
        _note(f"{PROG}: error: every held-out run of the near-light model failed: nothing to evaluate")
        return 1
    if args.out is not None:
        from ..report import write_held_out

        path = write_held_out(args.out, found["near"], found["parallel"])
        print(f"\nwrote {path} and re-made {os.path.join(args.out, 'report.html')}")
    return 0


def _print_evaluation(rows: list[list[Any]], k: int) -> None:
    from ..evaluation import reading

    print(f"held-out lights: each reconstructed from the other {k - 1} lights and predicted")
    print("relative error = |prediction - image| / |image|; shape error: the same after the best gain\n")
    widths = [5] + [len(c) + 2 for c in EVALUATE_COLUMNS[1:]]
    print("".join(f"{c:>{w}}" for c, w in zip(EVALUATE_COLUMNS, widths, strict=True)))
    for row in rows:
        print(f"{row[0]:>{widths[0]}}" + "".join(f"{v:>{w}.4g}" for v, w in zip(row[1:], widths[1:], strict=True)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a column whose runs all failed: nan
        means = np.nanmean(np.array([r[1:] for r in rows], dtype=float), axis=0)
    print(f"{'mean':>{widths[0]}}" + "".join(f"{v:>{w}.4g}" for v, w in zip(means, widths[1:], strict=True)))
    print("\n" + reading((means[0], means[1]), (means[2], means[3])))
