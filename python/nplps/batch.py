"""Reconstruct many captures at once with Dask (``nplps batch``).

Every directory that a glob pattern matches is one capture: its image files (sorted by name,
as ``nplps reconstruct DIR`` reads a directory; names with ``mask`` or ``ambient`` left out)
and, if present, its mask image. The captures share one rig, except that a ``rig.json`` inside a
capture directory is that capture's rig (it overrides the shared one; each item records the rig
it used). With ``layout`` (``"near_ps"``, ``"diligent"``, ``"luces"``, ``"hehe12"``: the layouts of
``nplps reconstruct --capture``) each directory is read by that layout's loader of
:mod:`nplps.captures` instead: its images, calibration (the rig), mask and ambient image. Each
capture is one Dask task
(:mod:`dask.distributed`, an optional dependency: ``pip install "nplps[batch]"``) that runs
:func:`nplps.pipeline.prepare`, :func:`nplps.reconstruct` and
:meth:`nplps.Reconstruction.save` into ``OUT/<capture name>/``.

- Resumable, by fingerprint: a capture whose result directory holds a complete result (see
  :func:`is_complete`) made from the same images, rig and options is skipped; one made from
  other images, another rig or other options is redone (the item's ``note`` names what
  changed). A result that an earlier run did not finish (killed, out of memory, a dead worker:
  its manifest still says "in progress" and the folder holds only nplps's files) is redone. A
  result directory holding other files is left alone (the capture fails) unless ``overwrite``.
- A capture that fails is reported and the others go on.
- ``OUT/batch_summary.csv`` and ``OUT/batch_summary.html`` list every capture (written
  atomically, at the end of the run).
"""

from __future__ import annotations

import csv
import dataclasses
import glob
import html
import inspect
import io
import json
import os
import time
import urllib.parse
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal

from ._atomic import PathLike, write_text
from ._outdir import ResultDirectory, damaged, file_identity, fingerprint, jsonable, load_manifest, unfinished
from ._outdir import is_complete as _is_complete
from ._text import printable
from .captures.files import _find_one, find_images
from .errors import InputError, NplpsError
from .rig import Rig

__all__ = ["SUMMARY_COLUMNS", "BatchItem", "find_captures", "is_complete", "run", "write_summary"]

#: Columns of ``batch_summary.csv``.
SUMMARY_COLUMNS = ("capture", "status", "iterations", "solver_status", "rms_residual", "seconds", "rig", "error")

#: The capture layouts that :func:`run` reads with ``layout=`` (those of ``nplps reconstruct --capture``
#: that hold one capture per directory; ``queau_human1``, one published capture, is not among them).
LAYOUTS = ("near_ps", "diligent", "luces", "hehe12")

#: A capture directory's own rig file, which overrides the batch's rig for that capture.
RIG_FILE = "rig.json"

#: Keyword options that go to :func:`nplps.pipeline.prepare` (the others go to :func:`nplps.reconstruct`,
#: except those of :data:`RAW_OPTIONS` and :data:`SAVE_OPTIONS`).
PREPARE_OPTIONS = ("color", "saturation", "srgb", "exposures", "vignetting", "flat", "bin_factor")

#: Keyword options of the camera RAW decoding (:class:`nplps.raw.RawOptions`), with their defaults: as
#: ``nplps reconstruct --raw-wb / --raw-half-size``, for the RAW files of a capture (its images, its
#: ambient image and the flat field); they change nothing in a capture without RAW files.
RAW_OPTIONS: dict[str, Any] = {"white_balance": "none", "half_size": False}

#: Keyword options of :meth:`nplps.Reconstruction.save` (what each result directory holds), with their
#: defaults: as ``nplps reconstruct --opengl / --formats (--exr, --obj) / --normal-map /
#: --normal-map-bits / --units``.
SAVE_OPTIONS: dict[str, Any] = {
    "formats": [],
    "normal_map": "opengl",
    "units": None,
    "opengl": False,
    "normal_map_bits": 16,
}

BatchStatus = Literal["ok", "failed", "skipped"]


@dataclasses.dataclass
class BatchItem:
    """The outcome of one capture of a batch.

    Attributes
    ----------
    name : str
        The capture's name (its directory's name); its result is in ``out``.
    folder : str
        The capture directory.
    out : str
        The result directory, ``OUT/<name>``.
    status : {"ok", "failed", "skipped"}
        ``"skipped"``: a complete result was already there.
    iterations : int or None
        Iterations of the solver (None if failed).
    solver_status : str or None
        How the reconstruction ended (``"converged"``, ``"stalled"``, ...; None if failed).
    rms_residual : float or None
        RMS residual of the last iteration (image units).
    seconds : float or None
        Wall time of the task (None when skipped or when the task never ran).
    error : str or None
        The error message of a failed capture.
    warnings : list of str
        Warnings the reconstruction gave (e.g. a diverged run).
    note : str or None
        Why an existing result was redone (other options, an unfinished earlier run).
    rig : str or None
        The rig the capture was reconstructed with: its own ``rig.json``, the batch's rig file
        (or ``"given"`` for a :class:`~nplps.Rig` object) or its layout's calibration files.
    """

    name: str
    folder: str
    out: str
    status: BatchStatus = "ok"
    iterations: int | None = None
    solver_status: str | None = None
    rms_residual: float | None = None
    seconds: float | None = None
    error: str | None = None
    warnings: list[str] = dataclasses.field(default_factory=list)
    note: str | None = None
    rig: str | None = None

    def row(self) -> dict[str, str]:
        """Return the item as a row of ``batch_summary.csv`` (text; ``nan`` for missing numbers)."""
        return {
            "capture": _field(self.name),
            "status": self.status,
            "iterations": "nan" if self.iterations is None else str(self.iterations),
            "solver_status": _field(self.solver_status or ""),
            "rms_residual": "nan" if self.rms_residual is None else f"{self.rms_residual:.6e}",
            "seconds": "nan" if self.seconds is None else f"{self.seconds:.3f}",
            "rig": _field(self.rig or ""),
            "error": _field(self.error or ""),
        }


#: ``progress(item, done, total, failed)``, called in the calling process as each capture finishes.
ProgressCallback = Callable[[BatchItem, int, int, int], None]


def find_captures(pattern: str, out: PathLike | None = None) -> list[Path]:
    """Return the capture directories that the glob ``pattern`` matches, sorted by name.

    Parameters
    ----------
    pattern : str
        A glob pattern (``**`` allowed) of directories; files it matches are ignored.
    out : path-like, optional
        The batch's output directory: it and the directories inside it are left out.

    Returns
    -------
    list of pathlib.Path
        The directories, in natural order of their names.

    Raises
    ------
    InputError
        Nothing matches, or two captures have the same name (their results would collide).
    """
    from .pipeline import natural_key

    top = None if out is None else os.path.realpath(out)
    found = []
    for match in _glob_directories(os.path.expanduser(pattern)):
        real = os.path.realpath(match)
        if top is not None and (real == top or real.startswith(top + os.sep)):
            continue
        name = Path(match).name
        if name in ("", ".", "..") or os.sep in name or (os.altsep and os.altsep in name):
            raise InputError(
                f"capture directory {match!r} has no name of its own ({name!r}): its result would land outside "
                "the output directory; write the pattern without '.' or '..' parts"
            )
        found.append(Path(match))
    if not found:
        raise InputError(f"no capture directory matches {printable(pattern)!r}")
    found.sort(key=lambda p: (natural_key(p.name), str(p)))
    names: dict[str, Path] = {}
    for path in found:
        if path.name in names:
            raise InputError(
                f"two captures are named '{path.name}' ('{names[path.name]}' and '{path}'): "
                "their results would go to the same directory"
            )
        names[path.name] = path
    return found


def _glob_directories(pattern: str) -> list[str]:
    """Return the directories that the glob ``pattern`` matches, each real directory once.

    As :func:`glob.glob` with ``recursive=True`` (``**`` matches any number of directories, hidden
    ones left out), but a ``**`` walk follows each real directory once: symbolic links back to an
    ancestor (loops) do not make it run for ever.
    """
    parts = pattern.split(os.sep)
    if "**" not in parts:
        return [m for m in glob.glob(pattern) if os.path.isdir(m)]
    i = parts.index("**")
    head = os.sep.join(parts[:i]) or ("" if not pattern.startswith(os.sep) else os.sep)
    rest = os.sep.join(parts[i + 1 :])
    bases = [head] if not glob.has_magic(head) else [m for m in glob.glob(head) if os.path.isdir(m)]
    seen: set[str] = set()
    found: list[str] = []
    for base in bases or ([head] if head == "" else []):
        start = base or os.curdir
        if not os.path.isdir(start):
            continue
        for top, dirs, _ in os.walk(start, followlinks=True):
            real = os.path.realpath(top)
            if real in seen:
                dirs[:] = []
                continue
            seen.add(real)
            dirs[:] = sorted(d for d in dirs if not d.startswith("."))
            shown = top if base else os.path.relpath(top)
            if not rest:
                found.append(shown)
            else:
                found.extend(_glob_directories(os.path.join(glob.escape(shown), rest)))
    unique: dict[str, str] = {}
    for match in found:
        unique.setdefault(os.path.realpath(match), match)
    return list(unique.values())


def is_complete(directory: PathLike) -> bool:
    """Tell whether ``directory`` holds a complete nplps result.

    Its manifest (``nplps-manifest.json``) is nplps's own for this directory, says the result is
    complete (it was completed last, after every file), lists ``summary.json``, and every file
    it lists is present with its recorded size.

    Parameters
    ----------
    directory : path-like
        A result directory.

    Returns
    -------
    bool
        True if the result is complete.
    """
    return _is_complete(directory)


def _resume(item: BatchItem, fp: str, inputs: dict[str, Any]) -> tuple[bool, bool]:
    """Decide a capture of a rerun: ``(skip, replace)``; sets ``item.note`` when a result is redone."""
    if _is_complete(item.out):
        manifest = load_manifest(item.out)
        if manifest is not None and manifest.fingerprint == fp:
            return True, False
        earlier = (manifest.inputs if manifest is not None else None) or {}
        changed = sorted(k for k in set(earlier) | set(inputs) if earlier.get(k) != inputs.get(k))
        item.note = "redone: the earlier result was made from other " + (
            ", ".join(changed) if changed else "inputs or options"
        )
        return False, True
    if unfinished(item.out):
        item.note = "redone: an earlier run did not finish it"
        return False, True
    if damaged(item.out):
        item.note = "redone: the earlier result there lost or changed a file (missing or of another size)"
        return False, True
    return False, False


@dataclasses.dataclass
class _Plan:
    """What one capture is read from: image files, rig (and where it came from), mask, ambient image."""

    files: list[Path]
    rig: Rig
    rig_source: str
    mask: Path | Any | None
    ambient: Path | Any | None
    vignetting: str | None = None  # the layout's default correction, used unless the options say


def _plan_capture(
    folder: Path,
    rig: Rig | None,
    rig_source: str,
    layout: str | None,
    mask_name: str | None,
    ambient_name: str | None,
) -> _Plan:
    """Find a capture's inputs (reading only calibration files and, for a layout, the mask).

    Without a layout: the image files of ``folder``, its own ``rig.json`` if it has one (else the
    batch's ``rig``) and the mask and ambient image by ``mask_name`` / ``ambient_name``. With a
    layout: that layout's loader gives the image files, rig, mask and ambient image; a
    ``mask_name`` other than ``"auto"`` replaces the loader's mask.
    """
    if layout is None:
        own = folder / RIG_FILE
        if own.is_file():
            rig, rig_source = Rig.load(own), os.fspath(own)
        if rig is None:
            raise InputError(f"no rig: '{folder}' has no {RIG_FILE} and the batch has no rig (--rig)")
        files = find_images(folder)
        return _Plan(
            files, rig, rig_source, _side_file(folder, mask_name, "mask"), _side_file(folder, ambient_name, "ambient")
        )
    capture = _layout_capture(layout, folder)
    mask = capture.mask if mask_name == "auto" else _side_file(folder, mask_name, "mask")
    vignetting = "cos4" if capture.K is not None and layout in ("near_ps", "hehe12") else None
    source = f"{layout} calibration in '{folder}'"
    return _Plan(list(capture.files), capture.rig(), source, mask, capture.ambient, vignetting)


def _layout_capture(layout: str, folder: Path) -> Any:
    """Read a capture directory with the loader of ``layout`` (file names only, no images)."""
    from . import captures

    if layout == "near_ps":
        return captures.load_near_ps(folder)
    if layout == "diligent":
        return captures.load_diligent(folder, normals=False)
    if layout == "luces":
        return captures.load_luces(folder, normals=False, depth=False)
    if layout == "hehe12":
        return captures.load_hehe12(folder)
    raise InputError(f"unknown capture layout {layout!r}: one of {', '.join(LAYOUTS)}")


def _capture_inputs(plan: _Plan, depth: Any, layout: str | None, options: dict[str, Any]) -> dict[str, Any]:
    """Return what a capture's result is made from (for its fingerprint): image files, rig, depth and options.

    The options are those of :func:`run` without their defaults where :func:`_without_defaults`
    left them out (the output and RAW options: results made before they existed keep their
    fingerprint). A capture holding camera RAW files records the RAW options always (with their
    defaults), one without them never.
    """
    try:
        images = [file_identity(f) for f in plan.files]
    except OSError:
        images = []
    side: dict[str, Any] = {}
    for word, value in (("mask", plan.mask), ("ambient", plan.ambient)):
        if isinstance(value, Path):
            try:
                side[word] = file_identity(value)
            except OSError:
                side[word] = None
        else:
            side[word] = None if value is None else fingerprint({word: value})
    ignored = ("threads", "report", *RAW_OPTIONS)  # how fast, not what; the RAW options: below
    raw = _has_raw(plan, options)  # the RAW options do nothing without RAW files: no redo for them
    layout_part = {} if layout is None else {"layout": layout}
    return {
        "images": images,
        "mask": side["mask"],
        "ambient": side["ambient"],
        "rig": fingerprint(plan.rig.to_dict()),
        **layout_part,
        "depth": fingerprint({"depth": depth}) if hasattr(depth, "shape") else jsonable(depth),
        **{f"option {k}": jsonable(v) for k, v in sorted(options.items()) if k not in ignored},
        **({f"option {k}": jsonable(options.get(k, v)) for k, v in RAW_OPTIONS.items()} if raw else {}),
    }


def _has_raw(plan: _Plan, options: dict[str, Any]) -> bool:
    """Tell whether a capture reads a camera RAW file: an image, its ambient image or the flat field."""
    from .raw import is_raw

    return any(is_raw(f) for f in [*plan.files, plan.ambient, options.get("flat")] if isinstance(f, (str, Path)))


def _without_defaults(options: dict[str, Any]) -> dict[str, Any]:
    """Return ``options`` checked, without the RAW and output options that are at their defaults.

    ``formats`` becomes a list without repeats (:func:`nplps.export.check_formats`: ``"exr"`` without
    OpenEXR is refused here, before any capture runs); ``normal_map`` and the RAW options are
    checked as :meth:`~nplps.Reconstruction.save` and :class:`~nplps.raw.RawOptions` check them.
    """
    from .export import check_formats, check_normal_map
    from .raw import RawOptions

    options = dict(options)
    if "formats" in options:
        options["formats"] = check_formats(options["formats"] or ())
    if "normal_map" in options or "normal_map_bits" in options:
        check_normal_map(options.get("normal_map", "opengl"), options.get("normal_map_bits", 16))
    if "opengl" in options and not isinstance(options["opengl"], bool):
        raise InputError(f"opengl must be True or False, got {options['opengl']!r}")
    if "units" in options and options["units"] is not None and not str(options["units"]).strip():
        raise InputError("units must not be empty (e.g. units='mm')")
    raw = {k: options[k] for k in RAW_OPTIONS if k in options}
    if raw:
        RawOptions(**raw)
    defaults = {**RAW_OPTIONS, **SAVE_OPTIONS}
    return {k: v for k, v in options.items() if k not in defaults or v != defaults[k]}


def run(
    pattern: str,
    rig: Rig | PathLike | None,
    out: PathLike,
    *,
    depth: Any,
    layout: str | None = None,
    mask_name: str | None = "auto",
    ambient_name: str | None = None,
    scheduler: str | None = None,
    workers: int | None = None,
    overwrite: bool = False,
    report: bool = True,
    progress: ProgressCallback | None = None,
    summary: bool = True,
    **options: Any,
) -> list[BatchItem]:
    """Reconstruct every capture directory that ``pattern`` matches, one Dask task each.

    Parameters
    ----------
    pattern : str
        Glob pattern of the capture directories (see :func:`find_captures`). A capture's images
        are its image files in natural order (names containing ``mask`` or ``ambient`` left
        out), one per light of ``rig``.
    rig : Rig, path-like or None
        The rig of every capture, or its rig file. A capture directory holding a ``rig.json`` is
        reconstructed with that rig instead; None: every capture must have one (or use
        ``layout``). Each item's ``rig`` says which rig its capture used.
    out : path-like
        Output directory: each capture's result goes to ``out/<capture name>/`` (through
        :meth:`~nplps.Reconstruction.save`), and the summary to ``out/batch_summary.csv`` and
        ``out/batch_summary.html``.
    depth : float, ndarray or "auto"
        As for :func:`nplps.reconstruct` (the same for every capture).
    layout : str, optional
        Read each capture directory with the loader of this layout (one of :data:`LAYOUTS`, as
        ``nplps reconstruct --capture``): its images, rig, mask and ambient image come from the
        layout's files (``rig`` must then be None). ``near_ps`` and ``hehe12`` captures get the
        cos^4 vignetting correction unless ``vignetting`` (or ``flat``) is given, as on the
        command line.
    mask_name : str or None, default "auto"
        ``"auto"``: the capture's image file with ``mask`` in its name, if there is one (no mask
        otherwise); a file name: that file in each capture directory (a capture without it
        fails); None: no mask.
    ambient_name : str or None, default None
        As ``mask_name`` for an ambient image (every light off) subtracted from the images.
    scheduler : str, optional
        Address of a running Dask scheduler (``"tcp://host:8786"``); default: a
        :class:`~distributed.LocalCluster` of `workers` processes, one thread each, started
        and closed by this call. Its workers need nplps installed.
    workers : int, optional
        Worker processes of the local cluster (default: the number of cores, at most the
        number of captures to run). Unless ``threads`` is given, each reconstruction then
        uses ``cores // workers`` threads.
    overwrite : bool, default False
        Reconstruct the captures with a complete result too (replacing it) instead of skipping
        them; also write into result directories that hold files nplps did not write.
    report : bool, default True
        Write each capture's ``report.html`` (:mod:`nplps.report`) with its input thumbnails and
        the options used.
    progress : callable, optional
        ``progress(item, done, total, failed)``, called as each capture finishes (skipped ones
        first).
    summary : bool, default True
        Write ``batch_summary.csv`` and ``batch_summary.html``.
    **options
        Options of :func:`nplps.pipeline.prepare` (``color``, ``saturation``, ``srgb``,
        ``exposures``, ``vignetting``, ``flat``, ``bin_factor``), of
        :func:`nplps.reconstruct` (``iterations``, ``tol``, ``robust``, ``dark``, ``threads``,
        ``solver``, ``levels``, ...), of the camera RAW decoding (:data:`RAW_OPTIONS`:
        ``white_balance``, ``half_size``, as :class:`nplps.raw.RawOptions`; for the captures'
        RAW files, whose default thresholds are then one sensor level, as in ``nplps
        reconstruct``) and of :meth:`nplps.Reconstruction.save` (:data:`SAVE_OPTIONS`:
        ``formats``, ``normal_map``, ``units``, ``opengl``, ``normal_map_bits``).
        ``exposures="auto"`` reads each capture's exposures from its camera RAW files' metadata
        (shutter time x ISO relative to its first image, :func:`nplps.raw.exposures_from_metadata`;
        a capture without RAW files fails). All of them are part of each capture's
        fingerprint: a result made with other ones (the output options too) is redone, not
        skipped; options at their defaults are the same as options left out.

    Returns
    -------
    list of BatchItem
        One per capture, in the order of :func:`find_captures`.

    Raises
    ------
    ImportError
        dask.distributed is not installed.
    InputError
        No capture matches, or two have the same name.
    RigError
        The rig file cannot be read.
    TypeError
        An unknown option.

    Notes
    -----
    A failing capture (unreadable image, wrong number of images, solver error, ...) gives an
    item with status ``"failed"`` and its message; the others go on. A worker that dies is
    retried by Dask, then the capture fails.

    Examples
    --------
    >>> items = nplps.batch.run("captures/*", "rig.json", "results", depth=200.0, workers=4)  # doctest: +SKIP
    >>> [item.status for item in items]  # doctest: +SKIP
    ['ok', 'ok', 'failed', ...]
    """
    from .api import reconstruct

    known = set(inspect.signature(reconstruct).parameters) - {"images", "rig", "mask", "depth", "progress", "valid"}
    unknown = sorted(set(options) - known - set(PREPARE_OPTIONS) - set(RAW_OPTIONS) - set(SAVE_OPTIONS))
    if unknown:
        raise TypeError(f"run() got unknown option(s): {', '.join(unknown)}")
    options = _without_defaults(options)
    exposures = options.get("exposures")
    if isinstance(exposures, str):
        if exposures.strip().lower() != "auto":
            raise InputError(f"exposures must be numbers, one per light, or 'auto', got {exposures!r}")
        options["exposures"] = "auto"
    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError as e:
        raise ImportError(
            'nplps batch needs dask.distributed: pip install "nplps[batch]" (or "dask[distributed]")'
        ) from e

    if layout is not None and layout not in LAYOUTS:
        raise InputError(f"unknown capture layout {layout!r}: one of {', '.join(LAYOUTS)}")
    if layout is not None and rig is not None:
        raise InputError(f"a {layout} capture takes its rig from its calibration files: give no rig with a layout")
    rig_source = "given"
    if rig is not None and not isinstance(rig, Rig):
        if os.path.isdir(rig):
            raise InputError(f"rig file '{os.fspath(rig)}' is a directory")
        rig_source = os.fspath(rig)
        rig = Rig.load(rig)
    out = Path(out)
    folders = find_captures(pattern, out)
    if rig is None and layout is None:
        bare = [f.name for f in folders if not (f / RIG_FILE).is_file()]
        if bare:
            listed = ", ".join(bare[:5]) + (", ..." if len(bare) > 5 else "")
            raise InputError(
                f"no rig for {len(bare)} capture(s) ({listed}): give a rig file (--rig) or put a {RIG_FILE} "
                "in each capture directory"
            )
    if layout is not None and not any(k in options for k in ("vignetting", "flat")):
        options = dict(options, vignetting="layout")  # the layout's default, per capture (see _process)
    items: list[BatchItem] = []
    todo: list[BatchItem] = []
    plans: dict[str, tuple[bool, str, dict[str, Any]]] = {}
    sources: dict[str, _Plan] = {}
    unreadable: list[BatchItem] = []
    for folder in folders:
        item = BatchItem(folder.name, os.fspath(folder), os.fspath(out / folder.name))
        items.append(item)
        try:
            plan = _plan_capture(folder, rig, rig_source, layout, mask_name, ambient_name)
        except (NplpsError, OSError) as e:  # this capture's calibration or side files: it fails, the others go on
            item.status, item.error = "failed", _message(e)
            unreadable.append(item)
            continue
        item.rig = plan.rig_source
        sources[item.name] = plan
        inputs = _capture_inputs(plan, depth, layout, options)
        fp = fingerprint(inputs)
        skip, replace = (False, True) if overwrite else _resume(item, fp, inputs)
        if skip:
            _fill_skipped(item)
        else:
            plans[item.name] = (replace, fp, inputs)
            todo.append(item)
    total, done, failed = len(items), 0, 0
    for item in items:
        if item.status in ("skipped", "failed"):
            done += 1
            failed += item.status == "failed"
            if progress is not None:
                progress(item, done, total, failed)

    if todo:
        out.mkdir(parents=True, exist_ok=True)
        prepare_options = {k: v for k, v in options.items() if k in PREPARE_OPTIONS}
        raw_options = {k: v for k, v in options.items() if k in RAW_OPTIONS}
        save_options = {k: v for k, v in options.items() if k in SAVE_OPTIONS}
        others = (*PREPARE_OPTIONS, *RAW_OPTIONS, *SAVE_OPTIONS)
        solve_options = {k: v for k, v in options.items() if k not in others}
        cluster = None
        if scheduler is None:
            cores = os.cpu_count() or 1
            n = max(1, min(workers or cores, len(todo)))
            solve_options.setdefault("threads", max(1, cores // n))
            cluster = LocalCluster(
                n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=40
            )
        try:
            with Client(cluster if cluster is not None else scheduler) as client:
                futures = {
                    client.submit(
                        _process,
                        _absolute(item) if scheduler is not None else item,
                        _absolute_plan(sources[item.name]) if scheduler is not None else sources[item.name],
                        depth,
                        prepare_options,
                        solve_options,
                        plans[item.name],
                        report,
                        save_options,
                        raw_options,
                        key=f"nplps-batch-{item.name}-{os.urandom(4).hex()}",
                        pure=False,
                    ): item
                    for item in todo
                }
                by_name = {item.name: i for i, item in enumerate(items)}
                finished: set[str] = set()
                try:
                    for future in as_completed(futures):
                        item = futures[future]
                        try:
                            result = future.result()
                        except Exception as e:  # the task raised outside _process's handler: a dead worker
                            result = dataclasses.replace(item, status="failed", error=_message(e))
                        result = dataclasses.replace(result, folder=item.folder, out=item.out)
                        items[by_name[item.name]] = result
                        finished.add(item.name)
                        done += 1
                        failed += result.status == "failed"
                        if progress is not None:
                            progress(result, done, total, failed)
                except BaseException:  # Ctrl-C, SIGTERM: the summary says which captures did not finish
                    client.cancel(list(futures))
                    for item in todo:
                        if item.name not in finished:
                            item.status, item.error = "failed", "interrupted"
                    if summary:
                        write_summary(items, out)
                    raise
        finally:
            if cluster is not None:
                cluster.close()
    if summary:
        write_summary(items, out)
    return items


def write_summary(items: Sequence[BatchItem], out: PathLike) -> tuple[Path, Path]:
    """Write ``batch_summary.csv`` and ``batch_summary.html`` into ``out``, each atomically.

    The CSV has the header :data:`SUMMARY_COLUMNS` and one row per item; no field holds a comma
    or a quote (they are replaced), and missing numbers are ``nan``, so both :mod:`csv` and
    ``numpy.loadtxt(path, delimiter=",", skiprows=1, dtype=str)`` read it.

    Parameters
    ----------
    items : sequence of BatchItem
        The captures.
    out : path-like
        The directory (created if needed).

    Returns
    -------
    tuple of pathlib.Path
        The CSV and the HTML file.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=SUMMARY_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for item in items:
        writer.writerow(item.row())
    csv_path, html_path = out / "batch_summary.csv", out / "batch_summary.html"
    write_text(csv_path, text.getvalue())
    write_text(html_path, _html(items))
    return csv_path, html_path


def _process(
    item: BatchItem,
    source: _Plan,
    depth: Any,
    prepare_options: dict[str, Any],
    solve_options: dict[str, Any],
    plan: tuple[bool, str, dict[str, Any]],
    report: bool = True,
    save_options: dict[str, Any] | None = None,
    raw_options: dict[str, Any] | None = None,
) -> BatchItem:
    """Reconstruct one capture and save it (the Dask task); errors become a failed item.

    ``plan`` is ``(replace, fingerprint, inputs)``: whether the result directory may hold files
    (an earlier result of nplps's that :func:`_resume` chose to redo, or ``overwrite``), and what
    the result is made from, recorded in its manifest. ``save_options`` go to
    :meth:`~nplps.Reconstruction.save` (:data:`SAVE_OPTIONS`); ``raw_options`` decode the camera
    RAW files (:data:`RAW_OPTIONS`), whose levels are then the sensor's, as in ``nplps reconstruct``.
    """
    from . import pipeline
    from .api import reconstruct
    from .export import ContactSheet
    from .raw import RawOptions, is_raw, stack_levels

    save_options = save_options or {}
    decoding = RawOptions(**(raw_options or {}))

    start = time.perf_counter()
    caught: list[str] = []
    replace, fp, inputs = plan
    try:
        # Checked before the work: a directory holding other files only with overwrite.
        target = ResultDirectory(
            item.out, overwrite=replace, option="overwrite (--overwrite)", fingerprint=fp, inputs=inputs
        )
        folder = Path(item.folder)
        files, rig = source.files, source.rig
        if not files:
            raise InputError(f"no image files in '{folder}'")
        if len(files) != rig.n_lights:
            raise InputError(
                f"{len(files)} images in '{folder}' but its rig ({source.rig_source}) has {rig.n_lights} lights: "
                "there must be exactly one image per light"
            )
        if prepare_options.get("vignetting") == "layout":
            prepare_options = dict(prepare_options, vignetting=source.vignetting)
        if isinstance(prepare_options.get("exposures"), str):  # "auto": this capture's RAW metadata
            from .raw import exposures_from_metadata

            prepare_options = dict(prepare_options, exposures=exposures_from_metadata(files))
        images = [_raw_file(os.fspath(f), decoding) for f in files]
        if prepare_options.get("flat") is not None:
            prepare_options = dict(prepare_options, flat=_raw_file(prepare_options["flat"], decoding))
        prepared = pipeline.prepare(
            images,
            rig=rig,
            mask=source.mask,
            ambient=_raw_file(source.ambient, decoding),
            dark=solve_options.get("dark"),
            levels=stack_levels(images),  # the sensor's levels of RAW images, as in nplps reconstruct
            overwrite=True,
            **prepare_options,
        )
        options = dict(solve_options, dark=prepared.dark)
        with warnings.catch_warnings(record=True) as records:
            warnings.simplefilter("always")
            result = reconstruct(
                prepared.images, prepared.rig, depth=depth, mask=prepared.mask, valid=prepared.valid, **options
            )
        caught = [str(w.message) for w in records]
        # inputs.png is made now and the images go before the save, whose peak they would raise
        # (as in nplps reconstruct).
        sheet = ContactSheet.of(prepared.images)
        del prepared
        with target:
            recorded = {"capture": os.fspath(folder), "rig": source.rig_source, "depth": depth}
            recorded.update(mask=_described(source.mask), ambient=_described(source.ambient))
            recorded.update(prepare_options, **options)
            if any(is_raw(f) for f in images):  # how they were decoded (the defaults too)
                recorded.update(white_balance=decoding.white_balance, half_size=decoding.half_size)
            recorded.update({k: v for k, v in save_options.items() if k in ("formats", "opengl")})
            if prepare_options.get("exposures") is not None:  # one per light: kept whole, not as a shape
                recorded["exposures"] = [float(e) for e in prepare_options["exposures"]]
            result.save(target, report=report, inputs=sheet, options=recorded, **save_options)
        s = result.summary()
    except Exception as e:
        return dataclasses.replace(
            item, status="failed", error=_message(e), seconds=time.perf_counter() - start, warnings=caught
        )
    return dataclasses.replace(
        item,
        status="ok",
        iterations=s["iterations"],
        solver_status=s["status"],
        rms_residual=s["rms_residual"],
        seconds=time.perf_counter() - start,
        warnings=caught,
    )


def _raw_file(path: Any, options: Any) -> Any:
    """Return ``path`` as a :class:`nplps.raw.RawFile` decoded with ``options`` if it is a RAW file, else as it is."""
    from .raw import RawFile, is_raw

    if isinstance(path, (str, os.PathLike)) and not isinstance(path, RawFile) and is_raw(path):
        return RawFile(path, options)
    return path


def _absolute(item: BatchItem) -> BatchItem:
    """Return ``item`` with absolute paths, for workers that may run elsewhere (a shared file system)."""
    return dataclasses.replace(item, folder=os.path.abspath(item.folder), out=os.path.abspath(item.out))


def _described(side: Any) -> Any:
    """Return a mask or ambient image as a result records it: its file, None, or (from a loader) its shape."""
    if side is None or isinstance(side, Path):
        return None if side is None else os.fspath(side)
    return f"array of shape {tuple(side.shape)} (from the capture's loader)"


def _absolute_plan(plan: _Plan) -> _Plan:
    """Return ``plan`` with absolute file paths (see :func:`_absolute`)."""

    def absolute(value: Any) -> Any:
        return value.absolute() if isinstance(value, Path) else value

    return dataclasses.replace(
        plan, files=[f.absolute() for f in plan.files], mask=absolute(plan.mask), ambient=absolute(plan.ambient)
    )


def _side_file(folder: Path, name: str | None, word: str) -> Path | None:
    """Return the capture's mask or ambient image: ``"auto"`` finds it by ``word``, a name must exist."""
    if name is None:
        return None
    if name == "auto":
        return _find_one(folder, word)
    path = folder / name
    if not path.is_file():
        raise InputError(f"{word} file '{path}' not found")
    return path


def _fill_skipped(item: BatchItem) -> None:
    """Mark ``item`` skipped and take iterations, status and residual from its ``summary.json``."""
    item.status = "skipped"
    try:
        s = json.loads((Path(item.out) / "summary.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return
    if isinstance(s, dict):
        item.iterations = s.get("iterations") if isinstance(s.get("iterations"), int) else None
        item.solver_status = s.get("status") if isinstance(s.get("status"), str) else None
        rms = s.get("rms_residual")
        item.rms_residual = float(rms) if isinstance(rms, (int, float)) else None


def _message(e: BaseException) -> str:
    """One line for an exception: its message (with the type unless it is nplps's own or a ValueError)."""
    text = " ".join(str(e).split())
    if isinstance(e, OSError) and e.filename is not None and os.fspath(e.filename) not in text:
        text = f"'{os.fspath(e.filename)}': {e.strerror or text}"
    if isinstance(e, (NplpsError, ValueError)) and text:
        return text
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def _field(text: str) -> str:
    """``text`` on one line without commas or double quotes (a CSV field that needs no quoting)."""
    return " ".join(text.split()).replace(",", ";").replace('"', "'")


_COLOURS = {"ok": "#e6f4ea", "failed": "#fce8e6", "skipped": "#eef1f5"}


def _html(items: Sequence[BatchItem]) -> str:
    """Return the summary as one self-contained HTML page."""
    counts = {s: sum(i.status == s for i in items) for s in ("ok", "failed", "skipped")}
    head = "".join(f"<th>{html.escape(c)}</th>" for c in SUMMARY_COLUMNS)
    rows = []
    for item in items:
        row = item.row()
        row["error"] = html.escape(" ".join((item.error or "").split()))
        cells = []
        for column in SUMMARY_COLUMNS:
            value = row[column] if column == "error" else html.escape(row[column])
            if column == "capture" and item.status != "failed":
                # The capture's report when it has one (a result made with report=False has not).
                has_report = (Path(item.out) / "report.html").is_file()
                # Relative ("./") and percent-encoded: a capture named "javascript:..." is a path, not a URL scheme.
                link = "./" + urllib.parse.quote(item.name) + ("/report.html" if has_report else "/")
                value = f'<a href="{html.escape(link)}">{value}</a>'
            cells.append(f"<td>{'' if value == 'nan' else value}</td>")
        rows.append(f'<tr style="background:{_COLOURS[item.status]}">{"".join(cells)}</tr>')
    title = f"nplps batch: {len(items)} captures"
    summary = ", ".join(f"{n} {s}" for s, n in counts.items())
    return (
        "<!DOCTYPE html>\n<html><head><meta charset='utf-8'>"
        f"<title>{html.escape(title)}</title><style>"
        "body{font-family:sans-serif;margin:2em}table{border-collapse:collapse}"
        "td,th{border:1px solid #ccc;padding:4px 8px;text-align:left}"
        "</style></head><body>"
        f"<h1>{html.escape(title)}</h1><p>{html.escape(summary)}</p>"
        f"<table><thead><tr>{head}</tr></thead><tbody>\n" + "\n".join(rows) + "\n</tbody></table></body></html>\n"
    )
