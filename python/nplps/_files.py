"""Opening the user's files for reading: only regular files are files.

A path can name a device (``/dev/zero`` never ends: a reader that reads its whole input fills the
memory), a FIFO (opening it waits for a writer) or a directory. Every reader of a user's or a
result's file opens it here, and so refuses those at once, from the open file's type, before it
reads a byte. The ground floor of the package's readers: it imports nothing of the package.
"""

from __future__ import annotations

import os
import stat
from typing import Any


class NotRegularFile(Exception):
    """Raised by :func:`open_regular` for a path that is not a regular file.

    ``directory`` tells a directory from a device, FIFO or socket.
    """

    def __init__(self, directory: bool) -> None:
        super().__init__("a directory" if directory else "a device, pipe or socket")
        self.directory = directory


def open_regular(path: str | os.PathLike[str]) -> tuple[Any, int]:
    """Open a regular file (or a link to one) for reading; return the file and its size.

    Opened without blocking (a FIFO would wait for a writer) and checked, on the open file, to
    be a regular file before anything is read (a device such as ``/dev/zero`` never ends).
    Raises :class:`NotRegularFile` for anything else, :class:`OSError` where it cannot be opened.
    """
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise NotRegularFile(stat.S_ISDIR(info.st_mode))
        return os.fdopen(fd, "rb"), info.st_size
    except BaseException:
        os.close(fd)
        raise
