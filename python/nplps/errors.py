"""Exceptions raised by nplps.

Every error that nplps raises on purpose derives from :class:`NplpsError`. Problems with what the
user passed in (images, masks, rig files, depths) are :class:`InputError`, which is also a
``ValueError`` so that generic handlers keep working. The Rust core's typed errors are mapped onto
these classes at the Python boundary (see ``rust/nplps-python``). An output directory that holds
files and may not be overwritten is :class:`OutputExistsError`, also a ``FileExistsError``.
"""

import errno

__all__ = ["InputError", "MemoryLimitError", "NplpsError", "OutputExistsError", "RigError", "SolverError"]


class NplpsError(Exception):
    """Base class of every error nplps raises on purpose."""


class InputError(NplpsError, ValueError):
    """The input (images, mask, depth, options) is invalid; the message names the problem.

    Raised by the core, it also carries what the message is about (None when not known, as for
    the errors raised in Python):

    Attributes
    ----------
    argument : str or None
        The parameter, option or array at fault (``"tol"``, ``"images"``, ``"depth map"``).
    value : object or None
        The value given for it (a parameter out of its range, an option of the wrong kind).
    expected, got : int or None
        The size an array must have and the size it has.
    index : int or None
        Where (row-major) an array's first bad value is.
    path : str or None
        The image file that cannot be read.
    """

    argument: str | None = None
    value: object = None
    expected: int | None = None
    got: int | None = None
    index: int | None = None
    path: str | None = None


class RigError(InputError):
    """The rig (camera or lights) is invalid, or a rig file cannot be read."""


class SolverError(NplpsError, RuntimeError):
    """The solver failed on valid input (for example the sparse factorization)."""


class MemoryLimitError(NplpsError, MemoryError):
    """The computation would need more memory than allowed, so it was refused before starting.

    Raised before any large allocation when the estimated peak memory exceeds ``max_memory``
    (by default 80 % of the memory available to the process: the system's available memory, a
    cgroup limit or an address-space limit, whichever is least). The message gives the estimate
    and the limit. It is also a ``MemoryError``.

    Attributes
    ----------
    what : str or None
        What was being computed.
    needed : int or None
        The estimated (or requested) bytes.
    limit : int or None
        The limit in bytes (None when a large allocation failed without a limit being exceeded).
    explicit : bool or None
        Whether the limit was the ``max_memory`` given (else the default share of the memory).
    """

    what: str | None = None
    needed: int | None = None
    limit: int | None = None
    explicit: bool | None = None


class OutputExistsError(NplpsError, FileExistsError):
    """An output directory is not empty and overwriting was not asked for.

    Overwriting is asked for with ``overwrite=True`` (``--overwrite`` on the command line).

    Parameters
    ----------
    message : str
        The message; it names the directory.
    directory : str
        The directory, also the exception's ``filename``.
    """

    def __init__(self, message: str, directory: str) -> None:
        super().__init__(errno.EEXIST, message, directory)

    def __str__(self) -> str:
        """Return the message alone (without the ``[Errno 17]`` prefix of :class:`OSError`)."""
        return str(self.strerror)
