"""Safe writes: every file nplps writes is written under a temporary name and renamed into place.

Each file is written under a temporary name in its own directory and renamed into place
(:func:`os.replace`) only once it is complete.

So an error while writing (a full disk, a file size limit, Ctrl-C) never leaves a truncated file
under the final name: the final name holds either the complete new file or whatever was there
before. On an exception the temporary file is removed; if the process is killed outright
(SIGKILL, or a signal that is not handled) a hidden ``.NAME.nplps-XXXXXXXX[.ext]`` file may stay
behind, never the final name.

Only regular files are replaced. An existing target that is a character device or a FIFO
(``/dev/null``, ``/dev/stdout``, a named pipe), or a symbolic link to one, is written directly,
in place: renaming over it would turn the device into a regular file. Any other kind of target
(a block device, a socket, a symbolic link to a regular file or a directory) is refused with
"cannot write X: not a regular file": nplps does not replace links or write through them.

An :class:`OSError` raised while writing is re-raised with the final path as its ``filename``
(the temporary name means nothing to the user) and marked as a write error (see
:func:`is_write_error`), so that messages can say "cannot write PATH: REASON".
"""

from __future__ import annotations

import errno
import os
import re
import secrets
import shutil
import stat
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from typing import IO, Any, Union

PathLike = Union[str, "os.PathLike[str]"]

#: Names of the temporary files: ``.NAME.nplps-XXXXXXXX`` plus NAME's extension (so that writers
#: that pick the format from the extension see the right one).
TEMPORARY_NAME = re.compile(r"^\..+\.nplps-[0-9a-f]{8}(\.[^.]*)?$")

_WRITE_ERROR = "_nplps_write_error"
_MAX_NAME = 200  # of the part of the final name that is repeated in the temporary name


@contextmanager
def atomic_path(path: PathLike) -> Iterator[str]:
    """Yield a new, empty temporary file name next to ``path`` with the same extension.

    It is for writers that take a file name (``imageio``, ``tifffile``). When the block ends without
    an exception the file is renamed to ``path``; otherwise it is removed.

    Raises
    ------
    OSError
        Creating, writing or renaming failed; ``filename`` is ``path``.
    """
    final = os.fspath(path)
    try:
        direct = _writes_in_place(final)
    except OSError as e:
        raise write_error(e, final) from e
    if direct:
        # A pipe or a device takes the bytes in order, and writers seek (numpy's tofile, tifffile):
        # the file is made as a regular temporary file and copied to the target when complete.
        fd, staging = tempfile.mkstemp(prefix=".nplps-", suffix=os.path.splitext(final)[1])
        os.close(fd)
        try:
            yield staging
            with open(staging, "rb") as source, open(final, "wb") as target:
                shutil.copyfileobj(source, target, 1 << 20)
        except OSError as e:
            raise write_error(e, final) from e
        finally:
            _remove(staging)
        return
    directory, name = os.path.split(os.path.abspath(final))
    suffix = os.path.splitext(name)[1]
    temporary = None
    try:
        temporary = _create(directory, name, suffix)
        yield temporary
        os.replace(temporary, final)
        temporary = None
    except OSError as e:
        raise write_error(e, final) from e
    finally:
        if temporary is not None:
            _remove(temporary)


@contextmanager
def atomic_write(
    path: PathLike, mode: str = "wb", encoding: str | None = None, newline: str | None = None
) -> Iterator[IO[Any]]:
    """Open ``path`` for writing under a temporary name, renamed into place when the block ends.

    Like ``open(path, mode)`` for writing (``"w"`` or ``"wb"``), but the file is written under a
    temporary name and renamed to ``path`` when the block ends without an exception; on an exception
    it is removed and ``path`` is left as it was.

    Raises
    ------
    OSError
        Opening, writing or renaming failed; ``filename`` is ``path``.
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write writes new files (mode 'w' or 'wb'), got mode {mode!r}")
    with atomic_path(path) as temporary:
        with open(temporary, mode, encoding=encoding, newline=newline) as file:
            yield file


def write_text(path: PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` with :func:`atomic_write`."""
    with atomic_write(path, "w", encoding="utf-8") as file:
        file.write(text)


def write_error(error: OSError, path: PathLike) -> OSError:
    """``error`` as an OSError of the same kind (errno) naming ``path``, marked as a write error."""
    if is_write_error(error):
        return error
    if error.errno is not None:
        # OSError(errno, ...) makes the errno's subclass (PermissionError, ...).
        new = OSError(error.errno, error.strerror or str(error), os.fspath(path))
    else:
        new = OSError(f"{error}: {os.fspath(path)!r}")
        new.filename = os.fspath(path)
    setattr(new, _WRITE_ERROR, True)
    return new


def is_write_error(error: BaseException) -> bool:
    """Tell whether ``error`` comes from :func:`atomic_write` / :func:`atomic_path` or :func:`write_error`.

    If so, its ``filename`` is the file that could not be written.
    """
    return bool(getattr(error, _WRITE_ERROR, False))


def _writes_in_place(path: str) -> bool:
    """Whether ``path`` is to be written in place (a character device or FIFO, or a link to one).

    Raises
    ------
    OSError
        ``path`` exists and is neither a regular file nor such a target (see the module docstring).
    """
    try:
        info = os.lstat(path)
    except FileNotFoundError:
        return False
    if stat.S_ISREG(info.st_mode):
        return False
    target = info
    if stat.S_ISLNK(info.st_mode):
        try:
            target = os.stat(path)
        except OSError:
            target = info  # a dangling link
    if stat.S_ISCHR(target.st_mode) or stat.S_ISFIFO(target.st_mode):
        return True
    kind = (
        "a symbolic link"
        if stat.S_ISLNK(info.st_mode)
        else "a directory"
        if stat.S_ISDIR(info.st_mode)
        else "a block device"
        if stat.S_ISBLK(info.st_mode)
        else "a socket"
        if stat.S_ISSOCK(info.st_mode)
        else "a special file"
    )
    raise OSError(
        errno.EEXIST,
        f"not a regular file (it is {kind}; nplps replaces only regular files and writes devices and pipes in place)",
        path,
    )


def _create(directory: str, name: str, suffix: str) -> str:
    """Create a new empty temporary file in ``directory``; return its name."""
    stem = name[:_MAX_NAME]
    for _ in range(100):
        temporary = os.path.join(directory, f".{stem}.nplps-{secrets.token_hex(4)}{suffix}")
        try:
            # 0o666 and the umask: the permissions open() would give the file.
            fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
        except FileExistsError:
            continue
        os.close(fd)
        return temporary
    raise FileExistsError(f"no free temporary name for {name!r} in {directory!r}")


def _remove(path: str) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass
