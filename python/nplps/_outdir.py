"""Output directories of results (``Reconstruction.save``, ``Scene.save``, ``nplps reconstruct --out`` ...).

nplps writes a result only into a new or empty directory, unless told to overwrite
(``overwrite=True``, ``--overwrite``). Then it writes its files (replacing files of the same
names) and removes the files that an earlier nplps run wrote there and this run did not (a
``distance_curve.csv`` of an earlier ``--depth auto`` run, an earlier ``baseline/``); it never
removes any other file.

The lifecycle of a result directory
-----------------------------------
The directory's manifest, ``nplps-manifest.json``, says what state it is in::

    {"nplps": "0.1.0", "manifest": 2, "state": "complete", "folder": "/abs/real/path",
     "started": 1764745200.5, "fingerprint": "3f2a...", "inputs": {...},
     "files": {"albedo.png": {"size": 81234, "sha256": "9c1e..."}, ..., "summary.json": {...}}}

1. Before the first file of a run is written (and so, when overwriting, before anything of the
   earlier result is touched) the manifest is written with ``"state": "in progress"``. It lists
   every file the run has announced so far (without size and hash: ``null``) and the files of the
   earlier result it may still remove, and it is rewritten as each new file is announced. So a
   run killed at any moment (SIGKILL, the OOM killer, a dead Dask worker, a full disk) leaves a
   folder marked unfinished whose manifest names every file nplps may have written.
2. The files are written, each under a temporary name renamed into place (:mod:`nplps._atomic`).
3. When the run ends without an error, the earlier result's stale files are removed, the
   temporaries of interrupted runs are removed, and the manifest is completed, last, with each
   file's size and SHA-256 and ``"state": "complete"`` (the hashes of files the run marked
   finished, :meth:`ResultDirectory.finished`, were computed meanwhile on a background thread
   and are kept only if the file is still the one hashed). A run that fails or is interrupted
   (Ctrl-C) leaves ``"state": "in progress"`` with the size and hash of each file it finished.

:func:`load_manifest` reads a manifest; :func:`is_complete` verifies one (complete, every file
present with its recorded size). A manifest is *trusted* to say which files are nplps's only if
it names this very folder (``folder``, its real path): a manifest copied in from elsewhere is
not. A file listed by a trusted manifest is removed as stale only if it still is the file nplps
wrote: its size and hash match, or (for a file an interrupted run did not finish) it is not
older than the run. Files the run reads as its inputs are never removed (``keep``).

``fingerprint`` identifies what the result was made from (inputs and options, see
:func:`fingerprint`), so that ``nplps batch`` can tell a finished result made with other options
from one it can skip; ``inputs`` holds the options themselves, to name the ones that changed.

Every file is written inside the directory: names are plain relative paths (no ``..``, no
absolute paths) and no directory on the way may be a symbolic link out of it.
"""

from __future__ import annotations

import errno
import hashlib
import json
import math
import os
import stat
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from types import TracebackType
from typing import Any

import numpy as np

from ._atomic import TEMPORARY_NAME, PathLike, write_error, write_text
from .errors import InputError, OutputExistsError

#: The manifest's file name.
MANIFEST = "nplps-manifest.json"
#: The manifest's format (1: a bare list of files, before the lifecycle).
FORMAT = 2
#: A manifest larger than this is not nplps's (one lists a few dozen files).
MAX_MANIFEST_BYTES = 16 << 20
IN_PROGRESS = "in progress"
COMPLETE = "complete"

#: A file's record in a manifest: ``{"size": bytes, "sha256": hex}``, or None when not finished.
FileRecord = dict[str, Any] | None

_CHUNK = 1 << 22


@dataclass(frozen=True)
class Manifest:
    """A result directory's manifest, as read by :func:`load_manifest`.

    Attributes
    ----------
    state : str
        ``"complete"`` or ``"in progress"`` (``"unknown"`` for a manifest of format 1).
    files : dict of str to dict or None
        The files, by relative "/"-separated path: ``{"size", "sha256"}`` or None (not finished).
    folder : str or None
        The real path of the directory the manifest was written for.
    started : float or None
        When the run began (Unix time).
    fingerprint : str or None
        The fingerprint of the run's inputs and options (:func:`fingerprint`).
    inputs : dict or None
        What the fingerprint was computed from.
    """

    state: str
    files: dict[str, FileRecord]
    folder: str | None = None
    started: float | None = None
    fingerprint: str | None = None
    inputs: dict[str, Any] | None = None

    def trusted(self, directory: PathLike) -> bool:
        """Whether the manifest was written by nplps for ``directory`` itself (not copied in)."""
        return self.folder is not None and self.folder == os.path.realpath(directory)


@dataclass
class _Run:
    root: Path
    #: The earlier manifest, if trusted (its files may be replaced or removed).
    previous: Manifest | None
    fingerprint: str | None
    inputs: dict[str, Any] | None
    keep: set[str]
    started: float = field(default_factory=time.time)
    written: list[str] = field(default_factory=list)
    closed: bool = False
    #: Hashes started as soon as files were finished (:meth:`ResultDirectory.finished`), by name:
    #: the file's identity when it was hashed and its record.
    early: dict[str, Future[tuple[tuple[int, int, int], FileRecord]]] = field(default_factory=dict)
    hasher: ThreadPoolExecutor | None = None


class ResultDirectory(os.PathLike):
    """A directory that one run writes its result files into.

    Creating it checks the directory (see the module docstring) and raises
    :class:`~nplps.errors.OutputExistsError` if it holds files and ``overwrite`` is False;
    ``option`` is how the message tells the user to overwrite. Files are registered with
    :meth:`file` (the first one marks the directory "in progress"); :meth:`close` (or the end of
    a ``with`` block) removes the earlier run's stale files and completes the manifest. A
    :meth:`subdirectory` shares the run of its parent.

    Parameters
    ----------
    path : path-like
        The directory (created with the first file).
    overwrite : bool
        Write into a directory that holds files.
    option : str
        How error messages name the overwrite option.
    fingerprint : str, optional
        :func:`fingerprint` of the run's inputs and options, recorded in the manifest.
    inputs : dict, optional
        What the fingerprint was computed from (JSON-ready), recorded in the manifest.
    keep : iterable of path-like
        Files this run reads (its input images, rig, mask ...): never removed, even when an
        earlier result's manifest lists them.
    """

    def __init__(
        self,
        path: PathLike,
        overwrite: bool = False,
        option: str = "overwrite=True",
        *,
        fingerprint: str | None = None,
        inputs: dict[str, Any] | None = None,
        keep: Iterable[PathLike] = (),
    ) -> None:
        root = Path(path)
        previous = _check(root, overwrite, option)
        kept = {os.path.realpath(p) for p in keep}
        self._run = _Run(root, previous, fingerprint, inputs, kept)
        self._prefix = ""

    @property
    def path(self) -> Path:
        """The directory."""
        return self._run.root / self._prefix if self._prefix else self._run.root

    def __fspath__(self) -> str:
        return os.fspath(self.path)

    def __repr__(self) -> str:
        return f"ResultDirectory({os.fspath(self.path)!r})"

    def file(self, name: str) -> Path:
        """Return the path of the file ``name`` (relative, "/"-separated) in this directory.

        The file is recorded as written (the manifest, "in progress", lists it before it is
        written); its parent directories are created.

        Raises
        ------
        InputError
            ``name`` is not a plain relative path (absolute, with ``..``, empty parts).
        OSError
            A directory on the way cannot be made or is a symbolic link out of the directory.
        """
        relative = self._prefix + name
        if not _is_relative(relative):
            raise InputError(f"cannot write {relative!r} into a result directory: it must be a plain file name")
        run = self._run
        path = run.root / relative
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise write_error(e, path.parent) from e
        if not _inside(run.root, path):
            raise write_error(
                OSError(errno.ELOOP, f"a directory on the way is a symbolic link out of {os.fspath(run.root)!r}"), path
            )
        if relative not in run.written:
            run.written.append(relative)
            self._mark_in_progress()
        return path

    def finished(self, paths: Iterable[PathLike]) -> None:
        """Start hashing ``paths`` (files of this run, complete and renamed into place) on a background thread.

        The manifest's hashes are then computed while the run writes its other files instead of
        after the last one. :meth:`close` uses such a hash only if the file is still the one that
        was hashed (same inode, size and modification time); otherwise it hashes the file again.
        """
        run = self._run
        for path in paths:
            name = Path(path).resolve().relative_to(run.root.resolve()).as_posix()
            if name not in run.written or name in run.early:
                continue
            if run.hasher is None:
                run.hasher = ThreadPoolExecutor(1, thread_name_prefix="nplps-hash")
            run.early[name] = run.hasher.submit(_identified_record, run.root / name)

    def protect(self, paths: Iterable[PathLike]) -> None:
        """Never remove ``paths`` (files this run reads), even if an earlier result's manifest lists them."""
        self._run.keep.update(os.path.realpath(p) for p in paths)

    def subdirectory(self, name: str) -> ResultDirectory:
        """Return the subdirectory ``name``, written as part of this directory's run."""
        if not _is_relative(name.strip("/")):
            raise InputError(f"cannot write the subdirectory {name!r}: it must be a plain name")
        view = object.__new__(ResultDirectory)
        view._run = self._run
        view._prefix = f"{self._prefix}{name.strip('/')}/"
        return view

    @property
    def written(self) -> list[str]:
        """The files written so far, relative to the top directory, in order."""
        return list(self._run.written)

    def _mark_in_progress(self, records: dict[str, FileRecord] | None = None) -> None:
        """Write the manifest "in progress": the earlier files still in place and this run's."""
        run = self._run
        files: dict[str, FileRecord] = {}
        if run.previous is not None:
            files.update(run.previous.files)
        for name in run.written:
            files[name] = (records or {}).get(name)
        _write_manifest(run.root, IN_PROGRESS, files, run.started, run.fingerprint, run.inputs)

    def close(self, complete: bool = True) -> None:
        """End the run (a subdirectory's close does nothing).

        When ``complete``, it removes the earlier run's files that this run did not write and writes
        the complete manifest of this run's files (sizes and hashes); otherwise (the run failed)
        the manifest stays "in progress", with the sizes and hashes of the files that exist, so that
        nothing nplps wrote is forgotten. Nothing is done if nothing was written.
        """
        run = self._run
        if self._prefix or run.closed:
            return
        run.closed = True
        early = self._early_records()
        if not run.written:
            return
        if not complete:
            try:
                records = {name: _record(run.root / name) for name in run.written}
                if run.previous is None and not any(os.path.lexists(run.root / n) for n in run.written):
                    # Nothing of the run's is there and there was no earlier result: no trace either.
                    (run.root / MANIFEST).unlink(missing_ok=True)
                    _remove_stale(run.root, {}, None, set(), [n for n in run.written if "/" in n])
                    return
                self._mark_in_progress({k: v for k, v in records.items() if v is not None})
            except (OSError, KeyboardInterrupt):
                pass  # the run's own error is the one to report; the manifest already says "in progress"
            return
        written = set(run.written)
        if run.previous is not None:
            stale = {k: v for k, v in run.previous.files.items() if k not in written}
            _remove_stale(run.root, stale, run.previous.started, run.keep)
        _remove_temporaries(run.root, run.written)
        records = {}
        names = sorted(written)
        # The files not hashed yet (or changed since) are hashed now on a few threads (hashlib
        # releases the GIL): a 12 MP result is over a gigabyte.
        late = [name for name in names if not _same_file(run.root / name, early.get(name))]
        with ThreadPoolExecutor(max(1, min(4, os.cpu_count() or 1))) as pool:
            found = dict(zip(late, pool.map(_record, [run.root / name for name in late]), strict=True))
        for name in names:
            record = found[name] if name in found else early[name][1]
            if record is None:
                raise write_error(FileNotFoundError(2, "a file of the result vanished"), run.root / name)
            records[name] = record
        _write_manifest(run.root, COMPLETE, records, run.started, run.fingerprint, run.inputs)

    def _early_records(self) -> dict[str, tuple[tuple[int, int, int], FileRecord]]:
        """Wait for the hashes :meth:`finished` started; return those that succeeded, by name."""
        run = self._run
        if run.hasher is None:
            return {}
        run.hasher.shutdown(wait=True)
        run.hasher = None
        done = {}
        for name, future in run.early.items():
            try:
                done[name] = future.result()
            except OSError:
                pass  # hashed again (or reported) by close
        run.early.clear()
        return done

    def __enter__(self) -> ResultDirectory:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, traceback: TracebackType | None
    ) -> None:
        self.close(complete=kind is None)


@contextmanager
def result_directory(directory: PathLike, overwrite: bool = False) -> Iterator[ResultDirectory]:
    """Return a :class:`ResultDirectory` for a ``save`` method.

    It is ``directory`` itself if it is one (the caller's run, which the caller closes), else a new
    one, closed at the end of the block.
    """
    if isinstance(directory, ResultDirectory):
        yield directory
        return
    with ResultDirectory(directory, overwrite) as out:
        yield out


def fingerprint(parts: dict[str, Any]) -> str:
    """Return the SHA-256 (hex) of ``parts`` as canonical JSON: what a result was made from.

    Arrays count by their shape, type and bytes; paths by their text; other objects by ``repr``.
    """
    text = json.dumps(jsonable(parts, _array_digest), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _array_digest(value: np.ndarray) -> dict[str, Any]:
    data = np.ascontiguousarray(value)
    return {"array": list(data.shape), "dtype": str(data.dtype), "sha256": hashlib.sha256(data.data).hexdigest()}


def _array_shape(value: np.ndarray) -> Any:
    return value.tolist() if value.size <= 16 else f"array of shape {value.shape}"


def jsonable(value: Any, array: Callable[[np.ndarray], Any] = _array_shape) -> Any:
    """Return ``value`` as JSON-ready data: paths as text, non-finite floats as text, numbers as numbers.

    Arrays become ``array(a)`` (by default: up to 16 values as a list, else ``"array of shape
    (...)"``); objects of other types their ``repr``.
    """
    if isinstance(value, dict):
        return {str(k): jsonable(v, array) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v, array) for v in value]
    if isinstance(value, np.ndarray):
        out = array(value)
        return jsonable(out, array) if isinstance(out, list) else out
    if isinstance(value, np.generic):
        return jsonable(value.item(), array)
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return repr(value)


def file_identity(path: PathLike) -> list[Any]:
    """Return ``[name, size, mtime_ns]`` of an input file, for :func:`fingerprint` (cheap: no reading)."""
    info = os.stat(path)
    return [os.path.basename(os.fspath(path)), info.st_size, info.st_mtime_ns]


def load_manifest(directory: PathLike) -> Manifest | None:
    """Return the manifest in ``directory``, or None if there is none or it cannot be read.

    Only safe relative paths inside ``directory`` are kept. A manifest of format 1 (a list of
    files) has state ``"unknown"`` and is never trusted.
    """
    path = Path(directory) / MANIFEST
    try:
        # Only a regular file (a FIFO would block, a device never end) of a sane size.
        info = os.lstat(path)
        if not stat.S_ISREG(info.st_mode) or info.st_size > MAX_MANIFEST_BYTES:
            return None
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        return None
    if not isinstance(data, dict):
        return None
    files = data.get("files")
    if isinstance(files, list):  # format 1
        return Manifest("unknown", {f: None for f in files if isinstance(f, str) and _is_relative(f)})
    if not isinstance(files, dict):
        return None
    records: dict[str, FileRecord] = {}
    for name, record in files.items():
        if not (isinstance(name, str) and _is_relative(name)):
            continue
        ok = (
            isinstance(record, dict)
            and isinstance(record.get("size"), int)
            and not isinstance(record.get("size"), bool)
            and isinstance(record.get("sha256"), str)
        )
        records[name] = {"size": record["size"], "sha256": record["sha256"]} if ok else None
    state = data.get("state")
    folder, started = data.get("folder"), data.get("started")
    fp, inputs = data.get("fingerprint"), data.get("inputs")
    return Manifest(
        state if state in (IN_PROGRESS, COMPLETE) else "unknown",
        records,
        folder if isinstance(folder, str) else None,
        float(started) if isinstance(started, (int, float)) and not isinstance(started, bool) else None,
        fp if isinstance(fp, str) else None,
        inputs if isinstance(inputs, dict) else None,
    )


def read_manifest(directory: PathLike) -> list[str] | None:
    """Return the files listed by the manifest in ``directory`` (sorted), or None if there is no readable manifest."""
    manifest = load_manifest(directory)
    return None if manifest is None else sorted(manifest.files)


def is_complete(directory: PathLike, verify: bool = False) -> bool:
    """Tell whether ``directory`` holds a complete nplps result.

    Its manifest is nplps's own for this directory, says "complete", lists ``summary.json``, and
    every file it lists is a regular file of the recorded size (with ``verify``, also of the
    recorded SHA-256, which reads every file).
    """
    manifest = load_manifest(directory)
    if manifest is None or manifest.state != COMPLETE or not manifest.trusted(directory):
        return False
    if "summary.json" not in manifest.files:
        return False
    for name, record in manifest.files.items():
        path = Path(directory) / name
        if record is None or not _inside(Path(directory), path):
            return False
        try:
            info = os.lstat(path)
        except OSError:
            return False
        if not stat.S_ISREG(info.st_mode) or info.st_size != record["size"]:
            return False
        if verify and _sha256(path) != record["sha256"]:
            return False
    return True


def unfinished(directory: PathLike) -> bool:
    """Tell whether ``directory`` is an unfinished nplps result that a resume may redo.

    Its manifest is nplps's own for this directory and says "in progress", and every entry of
    the directory is a file it lists, a directory holding only such files, or a temporary file
    of an interrupted write.
    """
    manifest = load_manifest(directory)
    if manifest is None or manifest.state != IN_PROGRESS or not manifest.trusted(directory):
        return False
    return _only_listed(Path(directory), manifest)


def damaged(directory: PathLike) -> bool:
    """Tell whether ``directory`` is a finished nplps result that lost or changed a file since.

    Its manifest is nplps's own for this directory and says "complete", but a file it lists is
    missing or not of the recorded size (:func:`is_complete` is False), and the directory holds
    nothing else (as for :func:`unfinished`): a resume may redo it.
    """
    manifest = load_manifest(directory)
    if manifest is None or manifest.state != COMPLETE or not manifest.trusted(directory):
        return False
    return not is_complete(directory) and _only_listed(Path(directory), manifest)


def _only_listed(root: Path, manifest: Manifest) -> bool:
    """Tell whether every entry below ``root`` is a file ``manifest`` lists (or a temporary file)."""
    listed = set(manifest.files) | {MANIFEST}
    for top, dirs, names in os.walk(root):
        for name in names:
            relative = Path(top, name).relative_to(root).as_posix()
            if relative not in listed and not TEMPORARY_NAME.match(name):
                return False
        for d in dirs:
            if os.path.islink(os.path.join(top, d)):
                return False
    return True


def add_to_manifest(directory: PathLike, name: str) -> None:
    """Record ``name`` (a file just written into a finished result directory) in its manifest.

    For files added to a finished result later (``report.html``, ``held_out.json``,
    ``viewer.html``), so that a later run with overwrite removes them with the rest. A complete
    manifest gets the file's size and hash; an untrusted or missing manifest is left alone.
    """
    root = Path(directory)
    manifest = load_manifest(root)
    if manifest is None or not manifest.trusted(root) or not _is_relative(name):
        return
    files = dict(manifest.files)
    files[name] = _record(root / name) if manifest.state == COMPLETE else files.get(name)
    if manifest.state == COMPLETE and files[name] is None:
        return
    _write_manifest(
        root,
        manifest.state,
        files,
        manifest.started or time.time(),
        manifest.fingerprint,
        manifest.inputs,
    )


def _check(root: Path, overwrite: bool, option: str) -> Manifest | None:
    """Refuse a non-empty ``root`` unless ``overwrite``; return its manifest if trusted."""
    try:
        with os.scandir(root) as entries:
            empty = next(entries, None) is None
    except FileNotFoundError:
        return None
    except OSError as e:  # not a directory, no permission
        raise write_error(e, root) from e
    if empty:
        return None
    manifest = load_manifest(root)
    trusted = manifest is not None and manifest.trusted(root)
    if overwrite:
        return manifest if trusted else None
    if trusted:
        message = (
            f"output directory {os.fspath(root)!r} holds an earlier nplps result; pass {option} to replace it "
            "(files nplps did not write there are kept)"
        )
    else:
        message = (
            f"output directory {os.fspath(root)!r} is not empty; pass {option} to write into it anyway "
            "(files of the same names are replaced, other files are kept)"
        )
    raise OutputExistsError(message, os.fspath(root))


def _is_relative(name: str) -> bool:
    """Whether ``name`` is a plain relative path ("a/b.png") that stays inside its directory."""
    path = PurePosixPath(name)
    return (
        bool(name)
        and "\\" not in name
        and "\0" not in name
        and not path.is_absolute()
        and not any(part in ("", ".", "..") for part in name.split("/"))
        and name != MANIFEST
    )


def _inside(root: Path, path: Path) -> bool:
    """Whether ``path``'s directory really is ``root`` or below it (no symbolic link out)."""
    top = os.path.realpath(root)
    parent = os.path.realpath(path.parent)
    return parent == top or parent.startswith(top.rstrip(os.sep) + os.sep)


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def _identity(info: os.stat_result) -> tuple[int, int, int]:
    return (info.st_ino, info.st_size, info.st_mtime_ns)


def _identified_record(path: Path) -> tuple[tuple[int, int, int], FileRecord]:
    """Return the identity (inode, size, modification time) of ``path`` before hashing it, and its record."""
    return _identity(os.lstat(path)), _record(path)


def _same_file(path: Path, early: tuple[tuple[int, int, int], FileRecord] | None) -> bool:
    """Whether an early hash ``early`` of ``path`` is still valid (the file was not replaced or changed since)."""
    if early is None or early[1] is None:
        return False
    try:
        info = os.lstat(path)
    except OSError:
        return False
    return stat.S_ISREG(info.st_mode) and _identity(info) == early[0] and info.st_size == early[1]["size"]


def _record(path: Path) -> FileRecord:
    """Return the size and SHA-256 of the regular file ``path``, or None if it is not one."""
    try:
        info = os.lstat(path)
    except OSError:
        return None
    if not stat.S_ISREG(info.st_mode):
        return None
    return {"size": info.st_size, "sha256": _sha256(path)}


def _ours(path: Path, record: FileRecord, started: float | None) -> bool:
    """Whether ``path`` still is the file nplps wrote (see the module docstring)."""
    try:
        info = os.lstat(path)
    except OSError:
        return False
    if not stat.S_ISREG(info.st_mode):
        return False
    if record is not None:
        return info.st_size == record["size"] and _sha256(path) == record["sha256"]
    return started is not None and info.st_mtime >= started - 2.0


def _remove_stale(
    root: Path, stale: dict[str, FileRecord], started: float | None, keep: set[str], emptied: Iterable[str] = ()
) -> None:
    """Remove the files ``stale`` (relative to ``root``) still nplps's and the directories they leave empty.

    The parent directories of ``emptied`` (relative paths) are removed too if empty.
    """
    parents: set[Path] = {p for name in emptied for p in Path(name).parents if p != Path(".")}
    for name, record in stale.items():
        path = root / name
        if not _inside(root, path) or os.path.realpath(path) in keep or not _ours(path, record, started):
            continue
        try:
            path.unlink()
        except FileNotFoundError:
            pass
        except OSError:
            continue
        parents.update(p for p in path.relative_to(root).parents if p != Path("."))
    for parent in sorted(parents, key=lambda p: len(p.parts), reverse=True):
        try:
            (root / parent).rmdir()  # only if empty
        except OSError:
            pass


def _remove_temporaries(root: Path, written: list[str]) -> None:
    """Remove temporary files that an interrupted nplps run left in the directories written."""
    for directory in {(root / name).parent for name in written}:
        try:
            with os.scandir(directory) as entries:
                leftovers = [
                    e.path for e in entries if TEMPORARY_NAME.match(e.name) and e.is_file(follow_symlinks=False)
                ]
        except OSError:
            continue
        for path in leftovers:
            try:
                os.unlink(path)
            except OSError:
                pass


def _write_manifest(
    root: Path,
    state: str,
    files: dict[str, FileRecord],
    started: float,
    fp: str | None,
    inputs: dict[str, Any] | None,
) -> None:
    from ._core import __version__

    data = {
        "nplps": __version__,
        "manifest": FORMAT,
        "state": state,
        "folder": os.path.realpath(root),
        "started": started,
        "fingerprint": fp,
        "inputs": inputs,
        "files": dict(sorted(files.items())),
    }
    write_text(root / MANIFEST, json.dumps(data, indent=2) + "\n")
