"""Output directories of results (``Reconstruction.save``, ``Scene.save``, ``nplps reconstruct --out`` ...).

nplps writes a result only into a new or empty directory, unless told to overwrite
(``overwrite=True``, ``--overwrite``). Then it writes its files (replacing files of the same
names) and removes the files that an earlier nplps run wrote there and this run did not (a
``distance_curve.csv`` of an earlier ``--depth auto`` run, an earlier ``baseline/``); it never
removes any other file.

What a run wrote is recorded in the directory's manifest, ``nplps-manifest.json``, written last::

    {"nplps": "0.1.0", "files": ["albedo.png", "baseline/albedo.png", ..., "summary.json"]}

``files`` lists, sorted, the relative ("/"-separated) paths of every file the run wrote into the
directory and its subdirectories, without the manifest itself. A run that fails part-way leaves
the manifest listing the files of the earlier run and those it wrote, so that the next
overwriting run can still clean up.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from types import TracebackType

from ._atomic import TEMPORARY_NAME, PathLike, write_error, write_text
from .errors import OutputExistsError

#: The manifest's file name.
MANIFEST = "nplps-manifest.json"


@dataclass
class _Run:
    root: Path
    #: Files of the earlier run (from its manifest) when overwriting.
    previous: list[str]
    written: list[str] = field(default_factory=list)
    closed: bool = False


class ResultDirectory(os.PathLike):
    """A directory that one run writes its result files into.

    Creating it checks the directory (see the module docstring) and raises
    :class:`~nplps.errors.OutputExistsError` if it holds files and ``overwrite`` is False;
    ``option`` is how the message tells the user to overwrite. Files are registered with
    :meth:`file`; :meth:`close` (or the end of a ``with`` block) removes the earlier run's stale
    files and writes the manifest. A :meth:`subdirectory` shares the run of its parent.
    """

    def __init__(self, path: PathLike, overwrite: bool = False, option: str = "overwrite=True") -> None:
        root = Path(path)
        self._run = _Run(root, _check(root, overwrite, option))
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

        The file is recorded as written; its parent directories are created.
        """
        relative = self._prefix + name
        path = self._run.root / relative
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise write_error(e, path.parent) from e
        if relative not in self._run.written:
            self._run.written.append(relative)
        return path

    def subdirectory(self, name: str) -> ResultDirectory:
        """Return the subdirectory ``name``, written as part of this directory's run."""
        view = object.__new__(ResultDirectory)
        view._run = self._run
        view._prefix = f"{self._prefix}{name.strip('/')}/"
        return view

    @property
    def written(self) -> list[str]:
        """The files written so far, relative to the top directory, in order."""
        return list(self._run.written)

    def close(self, complete: bool = True) -> None:
        """End the run (a subdirectory's close does nothing).

        When ``complete``, it removes the earlier run's files that this run did not write and writes
        the manifest of this run's files; otherwise (the run failed) writes a manifest of the
        earlier run's files and the files of this run that exist, so that nothing nplps wrote is
        forgotten. Nothing is done if nothing was written.
        """
        run = self._run
        if self._prefix or run.closed:
            return
        run.closed = True
        if not run.written:
            return
        if not complete:
            # (Files are recorded before they are written: list those that exist.)
            files = set(run.previous) | {f for f in run.written if os.path.lexists(run.root / f)}
            if files != set(run.previous):  # else the earlier manifest (if any) is right
                try:
                    _write_manifest(run.root, sorted(files))
                except OSError:
                    pass  # the run's own error is the one to report
            return
        written = set(run.written)
        _remove_stale(run.root, [f for f in run.previous if f not in written])
        _remove_temporaries(run.root, run.written)
        _write_manifest(run.root, sorted(written))

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


def read_manifest(directory: PathLike) -> list[str] | None:
    """Return the files listed by the manifest in ``directory``, or None if there is no readable manifest.

    Only safe relative paths inside ``directory`` are listed.
    """
    try:
        data = json.loads((Path(directory) / MANIFEST).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    files = data.get("files") if isinstance(data, dict) else None
    if not isinstance(files, list):
        return None
    return [f for f in files if isinstance(f, str) and _is_relative(f)]


def add_to_manifest(directory: PathLike, name: str) -> None:
    """List ``name`` (a file just written into the result directory) in its manifest, if it has one.

    For files added to a finished result later (``report.html``, ``held_out.json``,
    ``viewer.html``), so that a later run with overwrite removes them with the rest.
    """
    root = Path(directory)
    files = read_manifest(root)
    if files is not None and name not in files:
        _write_manifest(root, sorted([*files, name]))


def _check(root: Path, overwrite: bool, option: str) -> list[str]:
    """Refuse a non-empty ``root`` unless ``overwrite``; return the files of its manifest."""
    try:
        with os.scandir(root) as entries:
            empty = next(entries, None) is None
    except FileNotFoundError:
        return []
    except OSError as e:  # not a directory, no permission
        raise write_error(e, root) from e
    if empty:
        return []
    previous = read_manifest(root)
    if overwrite:
        return previous or []
    if previous is not None:
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
        and not path.is_absolute()
        and not any(part in ("", ".", "..") for part in name.split("/"))
        and name != MANIFEST
    )


def _inside(root: Path, path: Path) -> bool:
    """Whether ``path``'s directory really is ``root`` or below it (no symbolic link out)."""
    top = os.path.realpath(root)
    parent = os.path.realpath(path.parent)
    return parent == top or parent.startswith(top + os.sep)


def _remove_stale(root: Path, stale: list[str]) -> None:
    """Remove the files ``stale`` (relative to ``root``) and the directories they leave empty."""
    parents: set[Path] = set()
    for name in stale:
        path = root / name
        if not _inside(root, path) or (path.is_dir() and not path.is_symlink()):
            continue
        try:
            path.unlink()
        except FileNotFoundError:
            pass
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


def _write_manifest(root: Path, files: list[str]) -> None:
    from ._core import __version__

    write_text(root / MANIFEST, json.dumps({"nplps": __version__, "files": files}, indent=2) + "\n")
