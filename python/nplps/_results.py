"""Checked readers of the files of a result directory (``nplps report``, ``nplps view``).

A result directory can be damaged or edited by hand: a file truncated, replaced by another, a
JSON field of the wrong type, a ``.npy`` header that claims a huge shape. Every reader here
checks before it allocates: the file is a regular file of bounded size, a ``.npy`` header's
dtype and shape, and the shape times the item size against the bytes in the file, a PNG's
size (from its header) against the result's before it is decoded, a PLY header's element
counts against the file's size and its face indices against its vertices, the columns of a
CSV file, the types of the JSON fields that are used. Any problem is an :class:`InputError`
whose one-line message names the file and the problem (``nplps`` prints it and exits with
status 2).

The expected shapes come from ``summary.json``'s ``shape`` ``[H, W]``: ``depth.npy`` is the
``(H + 1, W + 1)`` vertex grid, ``residual.npy`` and ``lights_used.npy`` are ``(H, W)``,
``normals.npy`` is ``(H, W, 3)``, and the maps ``mask.png``, ``normals.png`` and ``albedo.png``
are ``W x H`` pictures.
"""

from __future__ import annotations

import json
import math
import os
import struct
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ._files import NotRegularFile, open_regular
from .errors import InputError, RigError

__all__ = [
    "HISTORY_COLUMNS",
    "check_summary",
    "damaged",
    "read_distance_curve",
    "read_held_out",
    "read_history",
    "read_json",
    "read_mesh_ply",
    "read_npy",
    "read_png",
    "read_rig",
    "read_summary",
]

#: Largest JSON file read (summary.json, held_out.json).
MAX_JSON_BYTES = 16 << 20
#: Largest CSV file read (history.csv, distance_curve.csv).
MAX_CSV_BYTES = 64 << 20
#: Deepest nesting of arrays and objects in a JSON file read.
MAX_JSON_NESTING = 64
#: Largest picture without an expected size (inputs.png), in pixels.
MAX_FREE_PIXELS = 1 << 26
#: Largest PLY header, in bytes.
MAX_PLY_HEADER = 1 << 16
#: Deflate expands at most 1032-fold: a PNG whose pixels need more bytes than this many times the
#: file's size (plus a margin) cannot hold them, and is refused before decoding.
_PNG_EXPANSION = 1100

#: The largest depth (or coordinate) a result holds: the mesh files store float32.
MAX_COORDINATE = float(np.finfo(np.float32).max)
#: Most rows read from a CSV file (history.csv, distance_curve.csv).
MAX_CSV_ROWS = 100_000
#: Deepest pyramid level in history.csv.
MAX_LEVEL = 63

#: The first columns of history.csv (more may follow).
HISTORY_COLUMNS = ("level", "iteration", "depth_change", "rms_residual", "elapsed")
_CURVE_COLUMNS = ("region", "distance", "rms_residual")

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}
_PNG_DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}


def damaged(path: str | os.PathLike[str], problem: str) -> InputError:
    """Return the error for a damaged result file: ``damaged result file 'PATH': PROBLEM``."""
    return InputError(f"damaged result file '{os.fspath(path)}': {problem}")


def _read_regular(path: Path, limit: int) -> bytes:
    """Return the bytes of a regular file of at most `limit` bytes (no FIFO or device is opened blocking)."""
    file, size = _open_regular(path)
    with file:
        if size > limit:
            raise damaged(path, f"{size} bytes, more than the {limit >> 20} MiB such a file can have")
        try:
            data = file.read(limit + 1)
        except OSError as e:
            raise InputError(f"cannot read result file '{os.fspath(path)}': {e.strerror or e}") from None
    if len(data) > limit:
        raise damaged(path, f"more than the {limit >> 20} MiB such a file can have")
    return data


def _open_regular(path: Path) -> tuple[Any, int]:
    """:func:`open_regular` for a result file, its failures as :class:`InputError`."""
    try:
        return open_regular(path)
    except NotRegularFile as e:
        kind = "a directory" if e.directory else "not a regular file"
        raise damaged(path, f"{kind}, not a file") from None
    except OSError as e:
        raise InputError(f"cannot read result file '{os.fspath(path)}': {e.strerror or e}") from None


# --------------------------------------------------------------------------------------------------
# JSON
# --------------------------------------------------------------------------------------------------


def read_json(path: str | os.PathLike[str], limit: int = MAX_JSON_BYTES) -> Any:
    """Return the JSON value of a file of at most `limit` bytes, nested at most 64 levels.

    Raises
    ------
    InputError
        The file cannot be read, is too large, not UTF-8 or not JSON (the message names it).
    """
    from ._rig_values import _nesting

    p = Path(path)
    raw = _read_regular(p, limit)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise damaged(p, "not a UTF-8 text file") from None
    depth = _nesting(text)
    if depth > MAX_JSON_NESTING:
        raise damaged(p, f"JSON nested {depth} levels deep (at most {MAX_JSON_NESTING})")
    try:
        return json.loads(text)
    except RecursionError:
        raise damaged(p, "JSON nested too deeply") from None
    except ValueError as e:  # JSONDecodeError, integers of more than 4300 digits
        message = " ".join(str(e).split())
        raise damaged(p, f"not valid JSON ({message[:200]})") from None


def _describe(value: Any) -> str:
    from ._rig_values import _describe as describe

    return describe(value)


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


_SUMMARY_TYPES: dict[str, tuple[str, Any]] = {
    # field: (what it must be, check)
    "method": ("a string", lambda v: isinstance(v, str)),
    "status": ("a string", lambda v: isinstance(v, str)),
    "status_reason": ("a string", lambda v: isinstance(v, str)),
    "converged": ("true or false", lambda v: isinstance(v, bool)),
    "pixels": ("a non-negative integer", lambda v: _is_int(v) and v >= 0),
    "regions": ("a non-negative integer", lambda v: _is_int(v) and v >= 0),
    "iterations": ("a non-negative integer", lambda v: _is_int(v) and v >= 0),
    "unfitted_pixels": ("a non-negative integer", lambda v: _is_int(v) and v >= 0),
    "rms_residual": ("a number or null", lambda v: v is None or _is_number(v)),
    "last_depth_change": ("a number or null", lambda v: v is None or _is_number(v)),
    "timings": (
        "an object of numbers",
        lambda v: isinstance(v, dict) and all(x is None or _is_number(x) for x in v.values()),
    ),
    "estimated_distance": (
        "null or a list of numbers",
        lambda v: v is None or (isinstance(v, list) and all(x is None or _is_number(x) for x in v)),
    ),
    "options": ("null or an object", lambda v: v is None or isinstance(v, dict)),
    "reflectance": ('"lambertian", "glossy" or null', lambda v: v in (None, "lambertian", "glossy")),
    "cast_shadows": (
        "null or an object with a number share and a list of numbers per_light",
        lambda v: (
            v is None
            or (
                isinstance(v, dict)
                and _is_number(v.get("share"))
                and isinstance(v.get("per_light"), list)
                and all(_is_number(x) for x in v["per_light"])
            )
        ),
    ),
    "lobe": (
        "null or an object with numbers roughness and eta",
        lambda v: v is None or (isinstance(v, dict) and all(_is_number(v.get(k)) for k in ("roughness", "eta"))),
    ),
    "specular_png_scale": ("a number or null", lambda v: v is None or _is_number(v)),
    "units": ("a string or null", lambda v: v is None or isinstance(v, str)),
    "normal_map": (
        'null or an object with "frame" opengl, directx or opencv and "bits" 8 or 16',
        lambda v: (
            v is None
            or (
                isinstance(v, dict)
                and v.get("frame") in ("opengl", "directx", "opencv")
                and _is_int(v.get("bits"))
                and v.get("bits") in (8, 16)
            )
        ),
    ),
    "trust": (
        "null or an object with a list of lights (objects of numbers or nulls)",
        lambda v: (
            v is None
            or (
                isinstance(v, dict)
                and isinstance(v.get("lights"), list)
                and all(
                    isinstance(row, dict)
                    and _is_int(row.get("light"))
                    and all(x is None or _is_number(x) for x in row.values())
                    for row in v["lights"]
                )
            )
        ),
    ),
    "distance_check": (
        "null or an object with numbers given, found, ratio and looks_wrong true or false",
        lambda v: (
            v is None
            or (
                isinstance(v, dict)
                and all(_is_number(v.get(k)) for k in ("given", "found", "ratio"))
                and isinstance(v.get("looks_wrong"), bool)
            )
        ),
    ),
}


def check_summary(summary: Any, path: str | os.PathLike[str]) -> dict[str, Any]:
    """Check the value of ``summary.json``: an object, ``shape`` ``[H, W]``, the used fields' types.

    Returns
    -------
    dict
        `summary` itself.

    Raises
    ------
    InputError
        Naming the file and the first field that is wrong.
    """
    if not isinstance(summary, dict):
        raise damaged(path, f"not a JSON object but {_describe(summary)}")
    shape = summary.get("shape")
    if not (isinstance(shape, list) and len(shape) == 2 and all(_is_int(v) and 0 < v < 2**31 for v in shape)):
        what = "missing" if "shape" not in summary else _describe(shape)
        raise damaged(path, f'"shape" must be [H, W], two positive integers, got {what}')
    for key, (what, check) in _SUMMARY_TYPES.items():
        if key in summary and not check(summary[key]):
            raise damaged(path, f'"{key}" must be {what}, got {_describe(summary[key])}')
    return summary


def read_summary(directory: str | os.PathLike[str]) -> dict[str, Any]:
    """Return the checked ``summary.json`` of a result directory (:func:`check_summary`).

    Raises
    ------
    InputError
        There is no ``summary.json`` (not a result directory) or it is damaged.
    """
    root = Path(directory)
    path = root / "summary.json"
    if not root.is_dir():
        raise InputError(f"result directory '{os.fspath(root)}' does not exist or is not a directory")
    if not os.path.lexists(path):  # a broken or looping link is there: read_json names the problem
        raise InputError(f"'{os.fspath(root)}' is not an nplps result directory (it has no summary.json)")
    return check_summary(read_json(path), path)


# --------------------------------------------------------------------------------------------------
# .npy
# --------------------------------------------------------------------------------------------------


def _shape_text(shape: Sequence[int]) -> str:
    return "(" + ", ".join(str(int(s)) for s in shape) + ("," if len(shape) == 1 else "") + ")"


def read_npy(
    path: str | os.PathLike[str],
    *,
    kinds: str,
    shape: tuple[int, ...] | None = None,
    ndim: int | None = None,
    max_abs: float | None = None,
) -> np.ndarray:
    """Read a ``.npy`` file after checking its header against the file and the expected array.

    Parameters
    ----------
    path : str or path-like
        The file.
    kinds : str
        The allowed dtype kinds (``"f"``, ``"iu"``, ...); structured, sub-array and object dtypes
        are refused.
    shape : tuple of int, optional
        The expected shape.
    ndim : int, optional
        The expected number of dimensions (when the shape is not known).
    max_abs : float, optional
        The largest magnitude a value may have (an infinity is beyond it; NaN is left to the caller).

    Returns
    -------
    numpy.ndarray
        The array (C order, the file's dtype).

    Raises
    ------
    InputError
        The header is malformed, the dtype or shape is not the expected one, or the data is
        not as many bytes as the header's shape needs; nothing is allocated for the data before.
    """
    p = Path(path)
    file, size = _open_regular(p)
    with file:
        try:
            version = np.lib.format.read_magic(file)
            if version == (1, 0):
                header = np.lib.format.read_array_header_1_0(file)
            elif version == (2, 0):
                header = np.lib.format.read_array_header_2_0(file)
            else:
                raise ValueError(f"unsupported .npy format version {version[0]}.{version[1]}")
        except OSError as e:
            raise InputError(f"cannot read result file '{os.fspath(p)}': {e.strerror or e}") from None
        except Exception as e:  # numpy's header parser raises ValueError, SyntaxError, TypeError, ...
            message = " ".join(str(e).split())[:200]
            raise damaged(p, f"not a valid .npy file ({message or type(e).__name__})") from None
        found, fortran, dtype = header
        if dtype.hasobject or dtype.fields is not None or dtype.subdtype is not None or dtype.kind not in kinds:
            raise damaged(p, f"holds {dtype} values, expected {_kinds_text(kinds)}")
        if ndim is not None and len(found) != ndim:
            raise damaged(p, f"has {len(found)} dimension(s) {_shape_text(found)}, expected {ndim}")
        if shape is not None and tuple(found) != tuple(shape):
            raise damaged(p, f"has shape {_shape_text(found)}, expected {_shape_text(shape)} for this result")
        count = math.prod(int(s) for s in found)
        needed = count * dtype.itemsize
        offset = file.tell()
        if size - offset != needed:
            raise damaged(
                p,
                f"its header's shape {_shape_text(found)} of {dtype} needs {needed} bytes of data, "
                f"the file holds {max(size - offset, 0)}" + (" (truncated)" if size - offset < needed else ""),
            )
        array = np.empty(count, dtype=dtype)
        try:
            got = file.readinto(array.view(np.uint8).data)
        except OSError as e:
            raise InputError(f"cannot read result file '{os.fspath(p)}': {e.strerror or e}") from None
        if got != needed:
            raise damaged(p, f"truncated while reading ({got} of {needed} bytes)")
    if max_abs is not None and array.size:
        with np.errstate(invalid="ignore"):
            big = np.abs(array[~np.isnan(array)]).max(initial=0)
        if float(big) > max_abs:
            raise damaged(p, f"holds the value {float(big):.4g}, beyond the {max_abs:.4g} such a file can hold")
    if fortran:
        return np.ascontiguousarray(array.reshape(tuple(found)[::-1]).T)
    return array.reshape(tuple(found))


def _kinds_text(kinds: str) -> str:
    names = {"f": "floating-point", "i": "integer", "u": "integer", "b": "boolean"}
    return " or ".join(dict.fromkeys(names.get(k, k) for k in kinds)) + " values"


# --------------------------------------------------------------------------------------------------
# PNG
# --------------------------------------------------------------------------------------------------


def png_header(path: str | os.PathLike[str]) -> tuple[int, int, int, int]:
    """Return a PNG file's (height, width, channels, bit depth) from its header, without decoding.

    Raises
    ------
    InputError
        The file is not a PNG file, its header is malformed, or its pixels cannot fit in it.
    """
    p = Path(path)
    file, size = _open_regular(p)
    with file:
        head = file.read(33)
    if not head.startswith(_PNG_SIGNATURE):
        raise damaged(p, "not a PNG file")
    if len(head) < 33 or head[12:16] != b"IHDR" or struct.unpack(">I", head[8:12])[0] != 13:
        raise damaged(p, "not a valid PNG file (no IHDR header)")
    width, height, depth, colour = struct.unpack(">IIBB", head[16:26])
    if width == 0 or height == 0 or colour not in _PNG_CHANNELS or depth not in _PNG_DEPTHS[colour]:
        raise damaged(p, f"not a valid PNG file (size {width} x {height}, bit depth {depth}, colour type {colour})")
    channels = _PNG_CHANNELS[colour]
    raw = height * (1 + math.ceil(width * channels * depth / 8))
    if raw > _PNG_EXPANSION * size + 65536:
        raise damaged(p, f"a {size}-byte PNG file cannot hold {width} x {height} pixels (truncated or forged)")
    return height, width, channels, depth


def read_png(path: str | os.PathLike[str], *, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read a PNG picture after checking its size (W x H from its header) against `shape` (H, W).

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` or ``(H, W, 3)`` pixels in the file's dtype (:func:`nplps.io.read_image`).

    Raises
    ------
    InputError
        The file is not a PNG picture of that size, or cannot be decoded.
    """
    from .io import read_image

    p = Path(path)
    height, width, _, _ = png_header(p)
    if shape is not None and (height, width) != tuple(shape):
        raise damaged(p, f"a {width} x {height} picture, expected {shape[1]} x {shape[0]} (W x H) for this result")
    if shape is None and height * width > MAX_FREE_PIXELS:
        raise damaged(p, f"a {width} x {height} picture, larger than {MAX_FREE_PIXELS} pixels")
    try:
        pixels = np.asarray(read_image(p, max_pixels=height * width))
    except InputError as e:
        raise damaged(p, " ".join(str(e).split())) from None
    if pixels.shape[:2] != (height, width) or pixels.ndim not in (2, 3):
        raise damaged(p, f"decoded as {pixels.shape}, not as a {width} x {height} picture")
    return pixels


# --------------------------------------------------------------------------------------------------
# CSV
# --------------------------------------------------------------------------------------------------


def _read_table(path: Path, columns: tuple[str, ...], integer: Sequence[int]) -> np.ndarray:
    """Read a CSV table whose header starts with `columns`; every row as many numbers as the header."""
    raw = _read_regular(path, MAX_CSV_BYTES)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise damaged(path, "not a UTF-8 text file") from None
    lines = text.splitlines()
    if not lines:
        raise damaged(path, f"empty (expected the header {','.join(columns)})")
    header = [h.strip() for h in lines[0].split(",")]
    if tuple(header[: len(columns)]) != columns:
        raise damaged(path, f"header {printable_head(lines[0])!r} does not start with the columns {','.join(columns)}")
    width = len(header)
    rows: list[list[float]] = []
    for number, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        fields = line.split(",")
        if len(fields) != width:
            raise damaged(path, f"line {number} has {len(fields)} column(s), the header {width}")
        try:
            values = [float(f) for f in fields]
        except ValueError:
            raise damaged(path, f"line {number} holds a field that is not a number") from None
        for i in integer:
            v = values[i]
            if not (math.isfinite(v) and v == int(v) and 0 <= v < 2**31):
                raise damaged(path, f'line {number}: "{columns[i]}" must be a non-negative integer, got {fields[i]}')
        rows.append(values)
        if len(rows) > MAX_CSV_ROWS:
            raise damaged(path, f"more than {MAX_CSV_ROWS} rows: not a file nplps writes")
    return np.array(rows, dtype=np.float64).reshape(len(rows), width)


def printable_head(text: str, limit: int = 80) -> str:
    """Return the start of a text line for a message (control characters escaped)."""
    from ._text import printable

    return printable(text if len(text) <= limit else text[:limit] + "...")


def read_history(path: str | os.PathLike[str]) -> np.ndarray:
    """Return ``history.csv`` as an (iterations, columns) array; the first five columns are checked.

    The columns start with ``level, iteration, depth_change, rms_residual, elapsed``; level and
    iteration are non-negative integers.
    """
    p = Path(path)
    table = _read_table(p, HISTORY_COLUMNS, integer=(0, 1))
    if len(table) and float(table[:, 0].max()) > MAX_LEVEL:
        raise damaged(p, f'"level" {int(table[:, 0].max())} is deeper than any pyramid ({MAX_LEVEL})')
    return table


def read_distance_curve(path: str | os.PathLike[str]) -> np.ndarray:
    """Return ``distance_curve.csv`` as an (n, 3) array of region, distance, RMS residual."""
    table = _read_table(Path(path), _CURVE_COLUMNS, integer=(0,))
    return table[:, :3]


def read_held_out(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Return the checked ``held_out.json`` (:func:`nplps.report.held_out_record`'s fields).

    ``lights``: integers; ``near``: one row per light of three numbers or nulls; ``parallel``:
    null or the same; ``reading``: a string.
    """
    p = Path(path)
    rec = read_json(p)
    if not isinstance(rec, dict):
        raise damaged(p, f"not a JSON object but {_describe(rec)}")
    lights = rec.get("lights")
    if not isinstance(lights, list) or not all(_is_int(v) for v in lights):
        raise damaged(p, f'"lights" must be a list of integers, got {_describe(lights)}')

    def rows_ok(rows: Any, width: int) -> bool:
        return (
            isinstance(rows, list)
            and len(rows) == len(lights)
            and all(
                isinstance(r, list) and len(r) >= width and all(v is None or _is_number(v) for v in r) for r in rows
            )
        )

    if not rows_ok(rec.get("near"), 3):
        raise damaged(p, f'"near" must be one row [relative error, shape error, gain] per light ({len(lights)})')
    if rec.get("parallel") is not None and not rows_ok(rec["parallel"], 2):
        raise damaged(p, f'"parallel" must be null or one row [relative error, shape error] per light ({len(lights)})')
    if "reading" in rec and not isinstance(rec["reading"], str):
        raise damaged(p, f'"reading" must be a string, got {_describe(rec["reading"])}')
    return rec


# --------------------------------------------------------------------------------------------------
# rig.json
# --------------------------------------------------------------------------------------------------


def read_rig(path: str | os.PathLike[str]) -> Any:
    """Return the :class:`nplps.Rig` of a result's ``rig.json``; a bad file is an InputError naming it."""
    from .rig import Rig

    p = Path(path)
    _open_regular(p)[0].close()  # a regular file (no FIFO is opened by the rig reader)
    try:
        return Rig.load(p)
    except RigError as e:
        message = " ".join(str(e).split())
        raise damaged(p, message) from None


# --------------------------------------------------------------------------------------------------
# PLY
# --------------------------------------------------------------------------------------------------


def read_mesh_ply(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a binary little-endian triangle PLY file, checking its header against its size first.

    The header's element counts times their record sizes must be the bytes after the header;
    faces must be triangles whose indices are vertices of the file.

    Returns
    -------
    dict
        As :func:`nplps.export.read_ply`: ``vertices``, ``normals``, ``colors``, ``faces``,
        ``comments``.

    Raises
    ------
    InputError
        Naming the file and the problem.
    """
    from .export import _PLY_TYPES

    p = Path(path)
    file, size = _open_regular(p)
    with file:
        head = file.read(MAX_PLY_HEADER)
        end = head.find(b"end_header\n")
        if not head.startswith(b"ply\n"):
            raise damaged(p, "not a PLY file (it does not start with 'ply')")
        if end < 0:
            raise damaged(p, f"no 'end_header' line in its first {MAX_PLY_HEADER} bytes")
        try:
            lines = head[:end].decode("ascii").splitlines()
        except UnicodeDecodeError:
            raise damaged(p, "its header is not ASCII text") from None
        if "format binary_little_endian 1.0" not in lines:
            raise damaged(p, "not a binary little-endian PLY file (only 'format binary_little_endian 1.0' is read)")
        comments = [line[len("comment ") :] for line in lines if line.startswith("comment ")]
        elements: list[tuple[str, int, list[tuple[Any, ...]]]] = []
        for number, line in enumerate(lines, start=1):
            words = line.split()
            if words[:1] == ["element"]:
                if len(words) != 3 or not words[2].isdigit():
                    raise damaged(
                        p, f"header line {number}: {printable_head(line)!r}: not 'element NAME COUNT' (a whole number)"
                    )
                elements.append((words[1], int(words[2]), []))
            elif words[:1] == ["property"]:
                if not elements:
                    raise damaged(p, f"header line {number}: a property before any element")
                if len(words) == 5 and words[1] == "list" and words[2] in _PLY_TYPES and words[3] in _PLY_TYPES:
                    if np.dtype(_PLY_TYPES[words[3]]).kind not in "iu":
                        raise damaged(p, f"header line {number}: list items must be integers")
                    fields = [(f"{words[4]}_count", _PLY_TYPES[words[2]]), (words[4], _PLY_TYPES[words[3]], (3,))]
                    elements[-1][2].extend(fields)
                elif len(words) == 3 and words[1] in _PLY_TYPES:
                    elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
                else:
                    raise damaged(p, f"header line {number}: {printable_head(line)!r} is not a supported property")
        names = [name for name, _, _ in elements]
        if names[:1] != ["vertex"] or len(names) != len(set(names)) or not set(names) <= {"vertex", "face"}:
            raise damaged(p, f"expected the elements vertex and face, got {', '.join(names) or 'none'}")
        dtypes = []
        for name, _, fields in elements:
            try:
                dtypes.append(np.dtype(fields))
            except (TypeError, ValueError):
                raise damaged(p, f"the properties of element {name} repeat a name") from None
        offset = end + len(b"end_header\n")
        needed = sum(count * dtype.itemsize for (_, count, _), dtype in zip(elements, dtypes, strict=True))
        if size - offset != needed:
            counts = ", ".join(f"{count} {name}(s)" for name, count, _ in elements)
            held = max(size - offset, 0)
            raise damaged(p, f"its header declares {counts}: {needed} bytes after the header, the file holds {held}")
        file.seek(offset)
        arrays: dict[str, np.ndarray] = {}
        for (name, count, _), dtype in zip(elements, dtypes, strict=True):
            records = np.empty(count, dtype=dtype)
            got = file.readinto(records.view(np.uint8).data)
            if got != count * dtype.itemsize:
                raise damaged(p, "truncated while reading")
            arrays[name] = records
    vertex = arrays["vertex"]
    if not all(n in (vertex.dtype.names or ()) for n in ("x", "y", "z")):
        raise damaged(p, "its vertices have no x, y, z properties")
    n = len(vertex)
    faces = np.zeros((0, 3), dtype=np.int64)
    face = arrays.get("face")
    if face is not None:
        if not {"vertex_indices", "vertex_indices_count"} <= set(face.dtype.names or ()):
            raise damaged(p, "its faces have no vertex_indices list")
        if np.any(face["vertex_indices_count"] != 3):
            raise damaged(p, "only triangle faces are read (a face has another number of vertices)")
        faces = face["vertex_indices"].astype(np.int64)
        if faces.size and (int(faces.min()) < 0 or int(faces.max()) >= n):
            bad = int(faces.max()) if int(faces.max()) >= n else int(faces.min())
            raise damaged(p, f"a face refers to vertex {bad}, the file has {n} vertices")

    def columns(names: tuple[str, ...]) -> np.ndarray | None:
        if not all(c in (vertex.dtype.names or ()) for c in names):
            return None
        return np.stack([vertex[c] for c in names], axis=1)

    return {
        "vertices": columns(("x", "y", "z")),
        "normals": columns(("nx", "ny", "nz")),
        "colors": columns(("red", "green", "blue")),
        "faces": faces,
        "comments": comments,
    }
