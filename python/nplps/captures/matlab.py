"""MATLAB files: a reader for numeric variables (no scipy) and camera matrices in MATLAB conventions.

Calibration files of the published near-light tools (near_ps ``light.mat`` / ``camera.mat``,
DiLiGenT ``Normal_gt.mat``, Quéau's ``calib.mat``) hold plain numeric matrices in the MAT-file
version 5 format (MATLAB's default from v5 to v7, ``save -v7``). :func:`read_mat` reads those
itself, so reading a real capture needs nothing beyond numpy (issue 22, item 7: every documented
capture command works after ``pip install nplps``). What it reads and what it refuses:

* the 128-byte header (text, version ``0x0100``, byte order ``IM`` little / ``MI`` big endian);
* data elements with an 8-byte tag ``(type, bytes)`` or the 4-byte "small element" tag, padded
  to 8 bytes; ``miCOMPRESSED`` elements (zlib, v7) are inflated;
* ``miMATRIX`` elements of the numeric classes (double, single, int8-64, uint8-64, logical
  through the flags), real or complex, stored column-major with their own (often narrower)
  storage type: returned with the class's dtype and MATLAB's shape (at least 2-D), as
  ``scipy.io.loadmat`` returns them;
* char arrays come back as ``str``; cell arrays, structs, objects, sparse matrices and function
  handles come back as :class:`Unsupported`, which names the class: the loaders report it only
  when they need that variable;
* v7.3 files (HDF5) and v4 files are refused with a :class:`~nplps.errors.RigError` that says
  how to save the file instead (``save(..., '-v7')``).
"""

from __future__ import annotations

import zlib
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import RigError
from ..io import PathLike

# Data types of a data element's tag (MAT-File Format, MathWorks, table 1-1).
_MI_DTYPES = {
    1: "i1",  # miINT8
    2: "u1",  # miUINT8
    3: "i2",  # miINT16
    4: "u2",  # miUINT16
    5: "i4",  # miINT32
    6: "u4",  # miUINT32
    7: "f4",  # miSINGLE
    9: "f8",  # miDOUBLE
    12: "i8",  # miINT64
    13: "u8",  # miUINT64
    16: "u1",  # miUTF8
    17: "u2",  # miUTF16
    18: "u4",  # miUTF32
}
_MI_MATRIX = 14
_MI_COMPRESSED = 15
# Array classes of the array-flags subelement (MAT-File Format, table 1-3): numeric ones and char.
_MX_NUMERIC = {
    6: "f8",  # mxDOUBLE_CLASS
    7: "f4",  # mxSINGLE_CLASS
    8: "i1",
    9: "u1",
    10: "i2",
    11: "u2",
    12: "i4",
    13: "u4",
    14: "i8",
    15: "u8",
}
_MX_CHAR = 4
_MX_NAMES = {1: "cell array", 2: "struct", 3: "object", 5: "sparse matrix", 16: "function handle", 17: "opaque object"}
_FLAG_COMPLEX = 0x0800
_FLAG_LOGICAL = 0x0200


@dataclass(frozen=True)
class Unsupported:
    """A variable of a class :func:`read_mat` does not convert (cell, struct, object, sparse...)."""

    kind: str


class _Bad(Exception):
    """A malformed element (becomes a RigError with the file name)."""


def _elements(buf: bytes, order: str) -> list[tuple[int, bytes]]:
    """Split ``buf`` into ``(type, payload)`` data elements."""
    out = []
    pos = 0
    while pos + 8 <= len(buf):
        first, second = np.frombuffer(buf, dtype=order + "u4", count=2, offset=pos)
        first, second = int(first), int(second)
        if first >> 16:  # small element: bytes in the upper half, data in the tag's second word
            kind, size = first & 0xFFFF, first >> 16
            if size > 4:
                raise _Bad(f"small data element of {size} bytes at byte {pos}")
            out.append((kind, buf[pos + 4 : pos + 4 + size]))
            pos += 8
            continue
        kind, size = first, second
        start = pos + 8
        if start + size > len(buf):
            raise _Bad(f"data element at byte {pos} runs past the end ({size} bytes)")
        out.append((kind, buf[start : start + size]))
        # Elements are padded to 8 bytes; compressed ones are not.
        pos = start + (size if kind == _MI_COMPRESSED else (size + 7) // 8 * 8)
    return out


def _numbers(kind: int, payload: bytes, order: str) -> np.ndarray:
    if kind not in _MI_DTYPES:
        raise _Bad(f"unknown data type {kind}")
    dtype = np.dtype(order + _MI_DTYPES[kind])
    if len(payload) % dtype.itemsize:
        raise _Bad(f"{len(payload)} bytes are not a whole number of {dtype.name}")
    return np.frombuffer(payload, dtype=dtype)


def _matrix(payload: bytes, order: str) -> tuple[str, Any]:
    """Name and value of one miMATRIX element."""
    parts = _elements(payload, order)
    if len(parts) < 3:
        raise _Bad("a matrix element without flags, dimensions and name")
    flags = _numbers(*parts[0], order)
    cls, bits = int(flags[0]) & 0xFF, int(flags[0])
    dims = tuple(int(d) for d in _numbers(*parts[1], order))
    name = bytes(parts[2][1]).decode("ascii", "replace")
    if cls in _MX_NAMES or (cls not in _MX_NUMERIC and cls != _MX_CHAR):
        return name, Unsupported(_MX_NAMES.get(cls, f"class {cls}"))
    if any(d < 0 for d in dims):
        raise _Bad(f"variable '{name}' has negative dimensions {dims}")
    count = int(np.prod(dims))
    if len(parts) < 4:
        raise _Bad(f"variable '{name}' has no data")

    def part(i: int) -> np.ndarray:
        values = _numbers(*parts[i], order)
        if values.size != count:
            raise _Bad(f"variable '{name}' holds {values.size} values for dimensions {dims}")
        return values

    if cls == _MX_CHAR:
        codes = part(3).reshape(dims, order="F")
        rows = ["".join(chr(int(c)) for c in row) for row in codes.reshape(dims[0], -1)]
        return name, rows[0] if len(rows) == 1 else rows
    dtype = np.dtype(_MX_NUMERIC[cls])
    if bits & _FLAG_LOGICAL:
        dtype = np.dtype(bool)
    values = part(3).astype(dtype)
    if bits & _FLAG_COMPLEX:
        if len(parts) < 5:
            raise _Bad(f"complex variable '{name}' has no imaginary part")
        values = values + 1j * part(4).astype(np.float64 if dtype.kind != "f" else dtype)
    return name, values.reshape(dims, order="F")


def read_mat(path: PathLike) -> dict[str, Any]:
    """Read the variables of a MAT-file (version 5 / v7 format) without scipy.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.mat`` file.

    Returns
    -------
    dict
        Variable name to value: numeric arrays (MATLAB's class as dtype, MATLAB's shape, at least
        2-D; logical as bool; complex as complex), char arrays as ``str`` (a list of rows for a
        multi-row array), other classes as :class:`Unsupported`.

    Raises
    ------
    RigError
        Missing file, a v7.3 (HDF5) or v4 file, or a malformed one; the message names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise RigError(f"calibration file '{path}' not found")
    data = path.read_bytes()
    head = data[:128]
    if len(head) < 128 or not head.startswith(b"MATLAB"):
        raise RigError(
            f"'{path}' is not a MAT-file in the version 5 format (no 'MATLAB' header); "
            "save it in MATLAB with save(file, ..., '-v7')"
        )
    if head[126:128] == b"IM":
        order = "<"
    elif head[126:128] == b"MI":
        order = ">"
    else:
        raise RigError(f"'{path}' has no byte-order mark in its MAT-file header")
    version = int(np.frombuffer(head, dtype=order + "u2", count=1, offset=124)[0])
    if version != 0x0100:
        raise RigError(
            f"'{path}' is a MAT-file of version {version:#06x} (v7.3 files are HDF5); "
            "save it in MATLAB with save(file, ..., '-v7')"
        )
    out: dict[str, Any] = {}
    try:
        pending = deque(_elements(data[128:], order))
        while pending:
            kind, payload = pending.popleft()
            if kind == _MI_COMPRESSED:
                try:
                    pending.extendleft(reversed(_elements(zlib.decompress(payload), order)))
                except zlib.error as exc:
                    raise _Bad(f"compressed element: {exc}") from exc
            elif kind == _MI_MATRIX:
                name, value = _matrix(payload, order)
                out[name] = value
    except _Bad as exc:
        raise RigError(f"cannot read MAT-file '{path}': {exc}") from exc
    return out


def _mat_var(data: dict[str, Any], name: str, path: Path) -> np.ndarray:
    """Variable ``name`` of a loaded .mat file as a float64 array."""
    if name not in data:
        found = ", ".join(k for k in data if not k.startswith("__")) or "none"
        raise RigError(f"'{path}' has no variable '{name}' (variables: {found})")
    value = data[name]
    if isinstance(value, Unsupported):
        raise RigError(f"'{path}': variable '{name}' is a MATLAB {value.kind}, not a numeric matrix")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise RigError(f"'{path}': variable '{name}' is not numeric") from exc
    if not np.all(np.isfinite(arr)):
        raise RigError(f"'{path}': variable '{name}' has non-finite values")
    return arr


def standardize_K(K: np.ndarray, one_based: bool = True) -> np.ndarray:
    """Bring a MATLAB-style camera matrix to the standard 0-based form.

    A valid ``K`` is upper triangular with last row ``[0, 0, 1]``. MATLAB's
    ``cameraParameters.IntrinsicMatrix`` stores the transpose ``[fx 0 0; s fy 0; cx cy 1]``:
    when the last row is not ``[0, 0, 1]`` but the last column is and ``K[2, 0:2]`` is
    nonzero, the matrix is transposed. With ``one_based=True`` (MATLAB pixel coordinates, pixel
    ``(1, 1)`` centred at ``(1, 1)``) the principal point is shifted to the 0-based
    pixel-centre convention: ``cx0 = cx - 1``, ``cy0 = cy - 1``.

    Raises
    ------
    RigError
        Not a (3, 3) finite matrix of that form, or non-positive focal lengths.
    """
    K = np.array(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise RigError(f"K must be a finite (3, 3) matrix, got {np.shape(K)}")
    last = np.array([0.0, 0.0, 1.0])
    if not np.allclose(K[2], last):
        if np.allclose(K[:, 2], last) and np.any(K[2, :2] != 0):
            K = K.T.copy()
        else:
            raise RigError(f"K is not a pinhole matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]]: {K.tolist()}")
    K[2] = last
    if K[1, 0] != 0:
        raise RigError(f"K[1, 0] must be 0, got {K[1, 0]}")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise RigError(f"K has non-positive focal lengths fx={K[0, 0]}, fy={K[1, 1]}")
    if one_based:
        K[0, 2] -= 1.0
        K[1, 2] -= 1.0
    return K


def load_matlab_intrinsics(path: PathLike, variable: str = "K", one_based: bool = True) -> np.ndarray:
    """Read ``K`` from a MATLAB file and return it with :func:`standardize_K` applied.

    E.g. ``camera.mat`` of the near-light toolbox, or ``calib.mat`` of Quéau's robust_ps
    DiLiGenT calibration. Returns a float64 (3, 3) matrix, 0-based pixel centres.
    """
    path = Path(path)
    return standardize_K(_mat_var(read_mat(path), variable, path), one_based=one_based)
