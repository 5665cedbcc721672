"""``nplps batch``: reconstruct every capture directory a glob matches, with Dask (:mod:`nplps.batch`)."""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any

from .._text import printable
from ..batch import LAYOUTS
from .inputs import _check_numbers, near_options
from .options import OUTPUT, add_options, api_options
from .parsers import parse_depth, parse_exposures

BATCH_DESCRIPTION = """\
Reconstruct many captures with Dask (dask.distributed: pip install "nplps[batch]").

Every directory that CAPTURES_GLOB matches is one capture: its image files, sorted by name (names
containing 'mask' or 'ambient' left out), one per light of --rig, and its mask image if it has
one (a file with 'mask' in its name; see --mask-name). A rig.json inside a capture directory is
that capture's rig: it overrides --rig (which may then be left out when every capture has one);
the summary's rig column says which rig each capture used. With --capture LAYOUT (near_ps,
diligent, luces, hehe12: the layouts of 'nplps reconstruct --capture') each directory is read by
that layout's loader instead (its images, calibration, mask and ambient image; no --rig; cos^4
vignetting by default for near_ps and hehe12, as in 'nplps reconstruct'). Each capture is one task on a local
cluster (--workers processes) or on a running Dask scheduler (--scheduler ADDRESS), and its
result goes to DIR/<capture name>/: the files 'nplps reconstruct' writes with the same options
(--opengl, --formats, --normal-map, --normal-map-bits, --exr, --obj, --units; camera RAW images
decoded as --raw-wb and --raw-half-size say; --exposures auto reads each capture's exposures
from its RAW files' metadata).

Resumable: a capture whose DIR/<name>/ holds a complete result made from the same images, rig
and options (its nplps-manifest.json says so) is skipped; one made with other options (the
output options too) or another rig is redone (the line says which changed), and so is one that
an earlier run did not finish (killed, out of memory). Run the same command again after a failure
or an interruption to do the rest (--overwrite redoes them all). A DIR/<name>/ holding files that
nplps did not write is left alone (that capture fails) unless --overwrite. A failed capture is
reported ('capture NAME: failed: MESSAGE') and the others go on. At the end DIR/batch_summary.csv
and DIR/batch_summary.html list every capture: status (ok, failed, skipped), iterations, the
solver's status, rms residual, seconds, rig, error.

exit status: 0 all captures ok or skipped, 1 some failed, 2 invalid input or usage.
"""

BATCH_EPILOG = """\
examples:
  nplps batch 'captures/*' --rig rig.json --depth 200 --out results
  nplps batch 'shots/object_*' --rig rig.json --depth auto --bin 4 --robust tukey --workers 4 --out results
  nplps batch 'captures/*' --rig rig.json --depth 200 --scheduler tcp://10.0.0.5:8786 --out /shared/results
  nplps batch 'shots/*' --rig rig.json --depth 200 --normal-map directx --exr --units mm --out results
  nplps batch 'dng_shots/*' --rig rig_half.json --depth 200 --raw-half-size --raw-wb camera --out results
  nplps batch 'bracketed/*' --rig rig.json --depth 200 --exposures auto --formats glb,stl --opengl --out results
  nplps batch 'LUCES/data/*' --capture luces --depth 100 --bin 4 --out luces-results
"""

#: The input and solver options of ``nplps batch`` (declared in :data:`nplps.cli.options.OPTIONS`), in its order.
BATCH_OPTIONS = (
    "--dark",
    "--saturation",
    "--robust",
    "--shadows",
    "--interreflections",
    "--reflectance",
    "--roughness",
    "--eta",
    "--gray",
    "--srgb",
    "--vignetting",
    "--flat",
    "--exposures",
    "--refine-lights",
    "--light-prior-weight",
    "--bin",
    "--iterations",
    "--tol",
    "--weighting",
    "--solver",
    "--levels",
    "--threads",
    "--max-memory",
)

#: The camera RAW options of ``nplps batch`` (as ``nplps reconstruct``'s: :data:`nplps.cli.options.GROUPS`).
RAW = ("--raw-wb", "--raw-half-size")

_PREPARE_AND_RUN = (
    "--dark",
    "--saturation",
    "--robust",
    "--threads",
    "--max-memory",
    "--gray",
    "--srgb",
    "--vignetting",
    "--flat",
)


def add_batch_parser(sub: Any, formatter: Any) -> argparse.ArgumentParser:
    """Add the ``batch`` command and its options to the subparsers ``sub``; return its parser."""
    p = sub.add_parser(
        "batch",
        help="reconstruct every capture directory a glob matches, with Dask (resumable)",
        description=BATCH_DESCRIPTION,
        epilog=BATCH_EPILOG,
        formatter_class=formatter,
    )
    p.add_argument("pattern", metavar="CAPTURES_GLOB", help="glob pattern of the capture directories (quote it)")
    p.add_argument(
        "--rig",
        metavar="RIG.json",
        help="rig file of every capture (a capture directory's own rig.json overrides it); not with --capture",
    )
    p.add_argument(
        "--capture",
        choices=LAYOUTS,
        metavar="LAYOUT",
        help=f"read each capture directory in this layout ({', '.join(LAYOUTS)}), as 'nplps reconstruct --capture'",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output directory: DIR/<capture name>/ and the summary")
    add_options(p, ("--depth", "--depth-range"), batch=True)
    p.add_argument(
        "--mask-name",
        default="auto",
        metavar="NAME",
        help="mask file name in each capture (default 'auto': the image file with 'mask' in its name, "
        "if any; 'none': no mask)",
    )
    p.add_argument(
        "--ambient-name",
        metavar="NAME",
        help="ambient image (every light off) in each capture, subtracted "
        "('auto': the file with 'ambient' in its name)",
    )
    p.add_argument(
        "--overwrite", action="store_true", help="reconstruct the captures with a complete result too (replace it)"
    )
    p.add_argument(
        "--no-report",
        dest="report",
        action="store_false",
        help="do not write each capture's report.html (written by default)",
    )

    g = p.add_argument_group("Dask")
    g.add_argument(
        "--scheduler", metavar="ADDRESS", help="address of a running Dask scheduler (default: a local cluster)"
    )
    g.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="worker processes of the local cluster (default: the number of cores, at most the number of captures)",
    )

    g = p.add_argument_group("input and solver (as for 'nplps reconstruct')")
    add_options(g, BATCH_OPTIONS, batch=True)
    add_options(p.add_argument_group("camera RAW files (as for 'nplps reconstruct')"), RAW, batch=True)
    add_options(p.add_argument_group("output of each capture (as for 'nplps reconstruct')"), OUTPUT, batch=True)
    p.set_defaults(depth_prior=None, prior_weight=1.0, quiet=False)
    return p


def cmd_batch(args: argparse.Namespace) -> int:
    """Run ``nplps batch``; return the exit status (1 if a capture failed)."""
    from .. import batch
    from ..errors import InputError
    from ..export import check_formats
    from .inputs import load_rig

    _check_numbers(args)
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers must be at least 1, got {args.workers}")
    if args.scheduler is not None:
        _check_scheduler(args.scheduler)
    if args.flat is not None and not os.path.isfile(args.flat):
        raise InputError(f"--flat '{args.flat}' is not a file")
    if args.capture is not None and (args.rig is not None or args.ambient_name is not None):
        given = "--rig" if args.rig is not None else "--ambient-name"
        raise InputError(f"--capture {args.capture} takes the rig and the ambient image from each folder: not {given}")
    if args.units is not None and not args.units.strip():
        raise InputError("--units must not be empty (e.g. --units mm)")
    output = api_options(args, OUTPUT)
    check_formats(output["formats"])  # --exr without OpenEXR is refused before any capture is read
    rig = None if args.rig is None else load_rig(args.rig)  # before any capture is read
    options = dict(near_options(args), depth=parse_depth(args.depth))
    # The options beside the near-light solver's, by their API keywords (in the order recorded so far).
    options.update(api_options(args, _PREPARE_AND_RUN))
    exposures = args.exposures
    options["exposures"] = None if exposures is None else _exposures(exposures, rig)
    options.update(api_options(args, ("--bin",)))
    # run() leaves out the RAW and output options at their defaults (its fingerprints stay those of
    # the results made before these options existed).
    options.update(api_options(args, RAW), **output)
    keep = ("dark", "saturation", "robust") + (("vignetting",) if args.vignetting is not None else ())
    options = {k: v for k, v in options.items() if v is not None or k in keep}
    mask_name = None if args.mask_name == "none" else args.mask_name
    try:
        items = batch.run(
            args.pattern,
            args.rig,  # checked above; run() reads it again and records its path
            args.out,
            layout=args.capture,
            mask_name=mask_name,
            ambient_name=args.ambient_name,
            scheduler=args.scheduler,
            workers=args.workers,
            overwrite=args.overwrite,
            report=args.report,
            progress=_print_progress,
            **options,
        )
    except ImportError as e:
        raise InputError(str(e)) from None
    counts = {s: sum(i.status == s for i in items) for s in ("ok", "failed", "skipped")}
    print(
        f"{len(items)} captures: {counts['ok']} ok, {counts['failed']} failed, {counts['skipped']} skipped; "
        f"summary in {args.out}/batch_summary.csv and batch_summary.html",
        flush=True,
    )
    return 1 if counts["failed"] else 0


def _exposures(text: str, rig: Any) -> Any:
    """Parse ``--exposures``: one per light of ``rig`` (without one, each capture checks the count).

    ``auto`` stays ``"auto"``: each capture's exposures come from its RAW files' metadata.
    """
    if text.strip().lower() == "auto":
        return "auto"
    return parse_exposures(text, len(text.split(",")) if rig is None else rig.n_lights)


def _check_scheduler(address: str) -> None:
    """Refuse a ``--scheduler`` that is not a Dask address (``tcp://HOST:PORT`` and the like).

    Raises :class:`~nplps.errors.InputError` naming the option, before any capture is read. Without
    Dask installed nothing is checked here (the batch says that Dask is missing).
    """
    from ..errors import InputError

    try:
        from distributed.comm.addressing import parse_address, parse_host_port
    except ImportError:
        return
    example = "a Dask scheduler address such as tcp://10.0.0.5:8786"
    try:
        scheme, location = parse_address(address)
        if scheme == "inproc" and location:
            return  # a scheduler in this process (nplps.cli.main called from Python)
        if scheme not in ("tcp", "tls", "ws", "wss", "ucx"):
            raise ValueError(f"unknown scheme '{scheme}://'")
        host, port = parse_host_port(location)
        if not host or any(c.isspace() for c in host):
            raise ValueError(f"no host name in {address!r}")
        if not 0 < int(port) < 65536:
            raise ValueError(f"port {port} is not 1..65535")
    except (ValueError, TypeError) as e:
        raise InputError(f"--scheduler {printable(repr(address))} is not {example} ({printable(str(e))})") from None


def _print_progress(item: Any, done: int, total: int, failed: int) -> None:
    counts = f"[{done}/{total}, {failed} failed]"
    name = printable(item.name)  # a folder named with escape codes is shown, not obeyed
    if item.status == "failed":
        line = f"capture {name}: failed: {item.error}"
    elif item.status == "skipped":
        line = f"capture {name}: skipped (complete result in {item.out}, made with the same inputs and options)"
    else:
        rms = "" if item.rms_residual is None else f", rms residual {item.rms_residual:.3e}"
        line = f"capture {name}: ok, {item.solver_status}, {item.iterations} iterations{rms}, {item.seconds:.2f} s"
        if item.note:
            line += f" ({item.note})"
    print(printable(f"{counts} {line}"), flush=True)
    for message in item.warnings:
        print(printable(f"capture {name}: warning: {' '.join(message.split())}"), file=sys.stderr, flush=True)
