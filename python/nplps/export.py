"""Writing reconstruction results: meshes (PLY, OBJ), normal maps, albedo and depth images.

Meshes are built from the vertex grid of the reconstruction: vertex ``(r, c)`` of the
``(H + 1, W + 1)`` grid is the top-left corner of pixel ``(r, c)``, and every masked pixel is the
quad facet with corners ``00 = (r, c)``, ``01 = (r, c + 1)``, ``10 = (r + 1, c)`` and
``11 = (r + 1, c + 1)``. Each facet is written as the two triangles ``(00, 10, 11)`` and
``(00, 11, 01)``: counter-clockwise as seen from the camera, so their right-hand normals point at
the camera (``n_z < 0`` in the OpenCV frame: x right, y down, z forward).

Everything is vectorized with numpy (no Python loop per vertex or face), so meshes with millions
of vertices are written quickly.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from typing import IO, Union

import imageio.v3 as iio
import numpy as np
import tifffile

from .errors import InputError

PathLike = Union[str, os.PathLike]
"""A file name: ``str`` or any :class:`os.PathLike`."""

_OPENGL_FLIP = np.array([1.0, -1.0, -1.0], dtype=np.float32)
_COLOR_PERCENTILE = 99.0
_ALBEDO_PERCENTILE = 99.9
_OBJ_CHUNK_ROWS = 65536

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2",
    "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
    "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
}  # fmt: skip


# --------------------------------------------------------------------------------------------------
# Mesh construction (shared by PLY and OBJ)
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Mesh:
    """A triangle mesh ready to be written.

    Attributes:
        points: ``(n, 3)`` float32 vertex positions, in the output frame.
        normals: ``(n, 3)`` float32 vertex normals in the output frame, or None.
        colors: ``(n, 3)`` uint8 grey vertex colours, or None.
        faces: ``(m, 3)`` int32 vertex indices (0-based).
        frame: ``"opencv"`` or ``"opengl"``.
    """

    points: np.ndarray
    normals: np.ndarray | None
    colors: np.ndarray | None
    faces: np.ndarray
    frame: str


def _build_mesh(
    vertices: np.ndarray,
    mask: np.ndarray,
    normals: np.ndarray | None,
    albedo: np.ndarray | None,
    opengl: bool,
) -> _Mesh:
    """Validate the grids and build the mesh of the masked, finite facets."""
    vertices, mask, normals, albedo = _check_mesh_inputs(vertices, mask, normals, albedo)
    facets = _valid_facets(vertices, mask, normals)
    used = _used_vertices(facets)
    index = np.full(used.shape, -1, dtype=np.int64)
    index[used] = np.arange(np.count_nonzero(used))
    flip = _OPENGL_FLIP if opengl else np.ones(3, dtype=np.float32)
    return _Mesh(
        points=vertices[used].astype(np.float32) * flip,
        normals=None if normals is None else normals[used].astype(np.float32) * flip,
        colors=None if albedo is None else _grey_colors(albedo[used]),
        faces=_triangles(index, facets),
        frame="opengl" if opengl else "opencv",
    )


def _check_mesh_inputs(
    vertices: np.ndarray,
    mask: np.ndarray,
    normals: np.ndarray | None,
    albedo: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Convert to arrays and check the shapes against the vertex grid ``(H + 1, W + 1, 3)``."""
    vertices = np.asarray(vertices)
    mask = np.asarray(mask, dtype=bool)
    if vertices.ndim != 3 or vertices.shape[2] != 3:
        raise InputError(f"vertices must have shape (H + 1, W + 1, 3), got {vertices.shape}")
    grid = vertices.shape[:2]
    _require_shape("mask", mask, (grid[0] - 1, grid[1] - 1))
    if normals is not None:
        normals = np.asarray(normals)
        _require_shape("normals", normals, vertices.shape)
    if albedo is not None:
        albedo = np.asarray(albedo)
        _require_shape("albedo", albedo, grid + albedo.shape[2:] if albedo.ndim == 3 else grid)
        if albedo.ndim == 3 and albedo.shape[2] != 3:
            raise InputError(f"albedo has shape {albedo.shape}, expected (H + 1, W + 1) or (H + 1, W + 1, 3)")
    return vertices, mask, normals, albedo


def _require_shape(name: str, array: np.ndarray, shape: tuple[int, ...]) -> None:
    """Raise InputError if ``array.shape != shape``."""
    if array.shape != tuple(shape):
        raise InputError(f"{name} has shape {array.shape}, expected {tuple(shape)}")


def _valid_facets(
    vertices: np.ndarray, mask: np.ndarray, normals: np.ndarray | None
) -> np.ndarray:
    """Masked facets whose four corners have finite positions (and normals); warn about others."""
    finite = np.isfinite(vertices).all(axis=2)
    if normals is not None:
        finite &= np.isfinite(normals).all(axis=2)
    corners_finite = finite[:-1, :-1] & finite[:-1, 1:] & finite[1:, :-1] & finite[1:, 1:]
    facets = mask & corners_finite
    skipped = np.count_nonzero(mask) - np.count_nonzero(facets)
    if skipped:
        warnings.warn(
            f"skipped {skipped} masked facet(s) with a non-finite corner (NaN or inf)",
            RuntimeWarning,
            stacklevel=4,
        )
    if not facets.any():
        raise InputError("no facet to write: the mask is empty or every masked facet has NaN")
    return facets


def _used_vertices(facets: np.ndarray) -> np.ndarray:
    """Boolean ``(H + 1, W + 1)`` grid of the vertices that are a corner of a facet."""
    used = np.zeros((facets.shape[0] + 1, facets.shape[1] + 1), dtype=bool)
    used[:-1, :-1] |= facets
    used[:-1, 1:] |= facets
    used[1:, :-1] |= facets
    used[1:, 1:] |= facets
    return used


def _triangles(index: np.ndarray, facets: np.ndarray) -> np.ndarray:
    """Two triangles ``(00, 10, 11)``, ``(00, 11, 01)`` per facet, in row-major facet order."""
    rows, cols = np.nonzero(facets)
    i00 = index[rows, cols]
    i01 = index[rows, cols + 1]
    i10 = index[rows + 1, cols]
    i11 = index[rows + 1, cols + 1]
    pairs = np.stack([np.stack([i00, i10, i11], axis=1), np.stack([i00, i11, i01], axis=1)], axis=1)
    return pairs.reshape(-1, 3).astype(np.int32)


def _quantize(
    values: np.ndarray, percentile: float, max_value: int, dtype: type
) -> tuple[np.ndarray, float]:
    """Scale ``values`` so their ``percentile`` maps to ``max_value``; clip, round, NaN -> 0.

    Returns the integer array and the scale factor (pixel = value * scale). Without finite
    positive values the scale is 1.
    """
    values = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(values)
    reference = float(np.percentile(values[finite], percentile)) if finite.any() else 0.0
    scale = max_value / reference if reference > 0 else 1.0
    scaled = np.where(finite, values * scale, 0.0)
    return np.rint(np.clip(scaled, 0, max_value)).astype(dtype), scale


def _grey_colors(albedo: np.ndarray) -> np.ndarray:
    """``(n, 3)`` uint8 colours: albedo (grey ``(n,)`` or RGB ``(n, 3)``) scaled by its 99th
    percentile (over all channels) to 0..255."""
    colors, _ = _quantize(albedo, _COLOR_PERCENTILE, 255, np.uint8)
    return colors if colors.ndim == 2 else np.repeat(colors[:, None], 3, axis=1)


# --------------------------------------------------------------------------------------------------
# PLY
# --------------------------------------------------------------------------------------------------


def write_ply(
    path: PathLike,
    vertices: np.ndarray,
    mask: np.ndarray,
    normals: np.ndarray | None = None,
    albedo: np.ndarray | None = None,
    opengl: bool = False,
) -> None:
    """Write the masked part of a vertex grid as a binary little-endian PLY triangle mesh.

    Args:
        path: output file.
        vertices: ``(H + 1, W + 1, 3)`` vertex positions (OpenCV camera frame).
        mask: ``(H, W)`` bool; every selected pixel becomes two triangles
            ``(00, 10, 11)`` and ``(00, 11, 01)`` (facing the camera, see the module docstring).
        normals: optional ``(H + 1, W + 1, 3)`` per-vertex normals, written as ``nx, ny, nz``.
        albedo: optional ``(H + 1, W + 1)`` per-vertex albedo, written as grey ``red, green,
            blue`` uchar colours scaled so that the 99th percentile of the written finite values
            is 255 (clipped; NaN -> 0).
        opengl: write in the OpenGL frame (y up, z backwards): positions ``(x, -y, -z)`` and
            normals ``(nx, -ny, -nz)``. This is a rotation, so faces keep facing the viewer.

    Only the vertices used by the written facets are stored (row-major order). Masked facets with
    a non-finite corner position (or normal) are skipped with one RuntimeWarning. The header has
    the comments ``nplps`` and ``frame opencv`` / ``frame opengl``.

    Raises:
        InputError: the shapes do not match, or there is no facet to write.
    """
    mesh = _build_mesh(vertices, mask, normals, albedo, opengl)
    with open(path, "wb") as file:
        file.write(_ply_header(mesh).encode("ascii"))
        file.write(_ply_vertex_records(mesh).tobytes())
        file.write(_ply_face_records(mesh.faces).tobytes())


def _ply_header(mesh: _Mesh) -> str:
    """The ASCII header of the PLY file for ``mesh``."""
    lines = [
        "ply",
        "format binary_little_endian 1.0",
        "comment nplps",
        f"comment frame {mesh.frame}",
        f"element vertex {len(mesh.points)}",
        *(f"property float {name}" for name in ("x", "y", "z")),
    ]
    if mesh.normals is not None:
        lines += [f"property float {name}" for name in ("nx", "ny", "nz")]
    if mesh.colors is not None:
        lines += [f"property uchar {name}" for name in ("red", "green", "blue")]
    lines += [f"element face {len(mesh.faces)}", "property list uchar int vertex_indices"]
    return "\n".join(lines + ["end_header"]) + "\n"


def _ply_vertex_records(mesh: _Mesh) -> np.ndarray:
    """The vertex element of ``mesh`` as one packed structured array."""
    groups = [(("x", "y", "z"), "<f4", mesh.points)]
    if mesh.normals is not None:
        groups.append((("nx", "ny", "nz"), "<f4", mesh.normals))
    if mesh.colors is not None:
        groups.append((("red", "green", "blue"), "u1", mesh.colors))
    dtype = np.dtype([(name, kind) for names, kind, _ in groups for name in names])
    records = np.empty(len(mesh.points), dtype=dtype)
    for names, _, values in groups:
        for column, name in enumerate(names):
            records[name] = values[:, column]
    return records


def _ply_face_records(faces: np.ndarray) -> np.ndarray:
    """The face element: ``uchar 3`` followed by three ``int`` indices per face."""
    records = np.empty(len(faces), dtype=[("count", "u1"), ("vertex_indices", "<i4", (3,))])
    records["count"] = 3
    records["vertex_indices"] = faces
    return records


def read_ply(path: PathLike) -> dict[str, np.ndarray | list[str] | None]:
    """Read a binary little-endian triangle PLY file such as those :func:`write_ply` writes.

    Returns a dict with ``vertices`` (``(n, 3)`` float), ``normals`` (``(n, 3)`` float or None),
    ``colors`` (``(n, 3)`` uint8 or None), ``faces`` (``(m, 3)`` int64, 0-based) and
    ``comments`` (the header comment lines, without ``comment``).

    Raises:
        InputError: the file cannot be read or is not a binary little-endian triangle PLY file.
    """
    try:
        with open(path, "rb") as file:
            data = file.read()
    except OSError as exc:
        raise InputError(f"cannot read PLY file '{os.fspath(path)}': {exc}") from exc
    try:
        return _parse_ply(data)
    except (ValueError, IndexError, KeyError) as exc:
        raise InputError(f"cannot read PLY file '{os.fspath(path)}': {exc}") from exc


def _parse_ply(data: bytes) -> dict[str, np.ndarray | list[str] | None]:
    """Parse the bytes of a binary PLY file (see :func:`read_ply`)."""
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise ValueError("not a PLY file (missing 'ply' or 'end_header')")
    lines = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise ValueError("only 'format binary_little_endian 1.0' is supported")
    comments = [line[len("comment ") :] for line in lines if line.startswith("comment ")]
    offset = end + len(b"end_header\n")
    arrays: dict[str, np.ndarray] = {}
    for name, count, dtype in _ply_elements(lines):
        arrays[name] = np.frombuffer(data, dtype=dtype, count=count, offset=offset)
        offset += count * dtype.itemsize
    return _ply_result(arrays, comments)


def _ply_elements(lines: list[str]) -> list[tuple[str, int, np.dtype]]:
    """The elements declared by the header: name, count and record dtype.

    Scalar properties map to fields; a list property is supported only for triangles (three
    items per record), as field ``<name>_count`` plus a 3-vector field ``<name>``.
    """
    elements: list[tuple[str, int, list[tuple]]] = []
    for line in lines:
        words = line.split()
        if words[:1] == ["element"]:
            elements.append((words[1], int(words[2]), []))
        elif words[:1] == ["property"] and words[1] == "list":
            count_type, item_type, name = words[2:5]
            elements[-1][2].extend(
                [(f"{name}_count", _PLY_TYPES[count_type]), (name, _PLY_TYPES[item_type], (3,))]
            )
        elif words[:1] == ["property"]:
            elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
    return [(name, count, np.dtype(fields)) for name, count, fields in elements]


def _ply_result(
    arrays: dict[str, np.ndarray], comments: list[str]
) -> dict[str, np.ndarray | list[str] | None]:
    """Assemble the :func:`read_ply` result from the decoded elements."""
    vertex = arrays["vertex"]
    face = arrays.get("face")
    faces = np.zeros((0, 3), dtype=np.int64)
    if face is not None:
        if np.any(face["vertex_indices_count"] != 3):
            raise ValueError("only triangle faces are supported")
        faces = face["vertex_indices"].astype(np.int64)
    return {
        "vertices": _columns(vertex, ("x", "y", "z")),
        "normals": _columns(vertex, ("nx", "ny", "nz")),
        "colors": _columns(vertex, ("red", "green", "blue")),
        "faces": faces,
        "comments": comments,
    }


def _columns(records: np.ndarray, names: tuple[str, ...]) -> np.ndarray | None:
    """Stack the named fields of ``records`` as columns, or None if a field is missing."""
    if not all(name in (records.dtype.names or ()) for name in names):
        return None
    return np.stack([records[name] for name in names], axis=1)


# --------------------------------------------------------------------------------------------------
# OBJ
# --------------------------------------------------------------------------------------------------


def write_obj(
    path: PathLike,
    vertices: np.ndarray,
    mask: np.ndarray,
    normals: np.ndarray | None = None,
    albedo: np.ndarray | None = None,
    opengl: bool = False,
) -> None:
    """Write the masked part of a vertex grid as a Wavefront OBJ triangle mesh.

    Same arguments, mesh and frames as :func:`write_ply`. Vertices are written as
    ``v x y z`` or, with ``albedo``, ``v x y z r g b`` (grey colours as floats in 0..1, the
    PLY colours divided by 255); normals as ``vn nx ny nz``; faces with 1-based indices as
    ``f a//a b//b c//c`` (with normals) or ``f a b c``. The file starts with the comments
    ``# nplps`` and ``# frame opencv`` / ``# frame opengl``.

    Raises:
        InputError: the shapes do not match, or there is no facet to write.
    """
    mesh = _build_mesh(vertices, mask, normals, albedo, opengl)
    with open(path, "w", encoding="ascii", newline="\n") as file:
        file.write(f"# nplps\n# frame {mesh.frame}\n")
        if mesh.colors is None:
            _write_rows(file, "v %.9g %.9g %.9g\n", mesh.points)
        else:
            colors = mesh.colors.astype(np.float64) / 255.0
            _write_rows(file, "v %.9g %.9g %.9g %.6g %.6g %.6g\n", np.hstack([mesh.points, colors]))
        if mesh.normals is not None:
            _write_rows(file, "vn %.7g %.7g %.7g\n", mesh.normals)
            _write_rows(file, "f %d//%d %d//%d %d//%d\n", np.repeat(mesh.faces + 1, 2, axis=1))
        else:
            _write_rows(file, "f %d %d %d\n", mesh.faces + 1)


def _write_rows(file: IO[str], line_format: str, rows: np.ndarray) -> None:
    """Write ``rows`` with one %-format per row, formatting a whole chunk of rows at once."""
    for start in range(0, len(rows), _OBJ_CHUNK_ROWS):
        chunk = rows[start : start + _OBJ_CHUNK_ROWS]
        file.write((line_format * len(chunk)) % tuple(chunk.ravel().tolist()))


# --------------------------------------------------------------------------------------------------
# Images
# --------------------------------------------------------------------------------------------------


def save_normal_map(path: PathLike, normals: np.ndarray, mask: np.ndarray | None = None) -> None:
    """Save per-pixel normals as an 8-bit RGB PNG normal map.

    Encoding: the OpenCV-frame normal ``(n_x, n_y, n_z)`` is first expressed in the usual
    normal-map frame (x right, y up, z towards the viewer) as ``(n_x, -n_y, -n_z)``; each
    component ``v`` (clipped to [-1, 1]) is stored as ``round((v + 1) / 2 * 255)`` in R, G, B.
    A normal facing the camera, ``(0, 0, -1)``, is thus ``(128, 128, 255)`` (the familiar
    light-blue look) and ``(1, 0, 0)`` is ``(255, 128, 128)``. Pixels with a NaN normal or
    outside ``mask`` are ``(0, 0, 0)``.

    Args:
        path: output file (written as PNG whatever its extension).
        normals: ``(H, W, 3)`` unit normals, OpenCV frame.
        mask: optional ``(H, W)`` bool of the pixels to encode.
    """
    normals = np.asarray(normals, dtype=np.float64)
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise InputError(f"normals must have shape (H, W, 3), got {normals.shape}")
    valid = np.isfinite(normals).all(axis=2)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        _require_shape("mask", mask, normals.shape[:2])
        valid &= mask
    flipped = np.clip(np.where(valid[..., None], normals, 0.0) * _OPENGL_FLIP, -1.0, 1.0)
    encoded = np.rint((flipped + 1.0) / 2.0 * 255.0).astype(np.uint8)
    encoded[~valid] = 0
    iio.imwrite(path, encoded, extension=".png")


def save_albedo(path: PathLike, albedo: np.ndarray) -> float:
    """Save a per-pixel albedo map as a 16-bit grey PNG and return the scale factor.

    The pixel value is ``round(clip(albedo * scale, 0, 65535))`` where ``scale`` maps the 99.9th
    percentile of the finite albedo values to 65535 (``scale = 1`` if there is no positive finite
    value); NaN is written as 0. Divide the pixel values by the returned ``scale`` to recover the
    albedo.

    Args:
        path: output file (written as PNG whatever its extension).
        albedo: ``(H, W)`` grey or ``(H, W, 3)`` RGB albedo (16-bit RGB PNG, one scale for all
            channels).
    """
    albedo = np.asarray(albedo)
    if not (albedo.ndim == 2 or (albedo.ndim == 3 and albedo.shape[2] == 3)):
        raise InputError(f"albedo must have shape (H, W) or (H, W, 3), got {albedo.shape}")
    pixels, scale = _quantize(albedo, _ALBEDO_PERCENTILE, 65535, np.uint16)
    write_png16(path, pixels)
    return scale


def save_grey_png(path: PathLike, image: np.ndarray) -> None:
    """Writes an (H, W) image with values in [0, 1] as an 8-bit grey PNG (NaN -> 0)."""
    image = np.nan_to_num(np.asarray(image, dtype=np.float64), nan=0.0)
    iio.imwrite(path, np.rint(np.clip(image, 0.0, 1.0) * 255).astype(np.uint8), extension=".png")


def write_png16(path: PathLike, pixels: np.ndarray) -> None:
    """Writes a uint16 ``(H, W)`` grey or ``(H, W, 3)`` RGB image as a 16-bit PNG (with pypng:
    Pillow cannot write 16-bit RGB)."""
    import png

    pixels = np.asarray(pixels, dtype=np.uint16)
    h, w = pixels.shape[:2]
    grey = pixels.ndim == 2
    with open(path, "wb") as file:
        png.Writer(w, h, greyscale=grey, bitdepth=16).write(file, pixels.reshape(h, -1).tolist())


def save_depth_npy(path: PathLike, depth: np.ndarray) -> None:
    """Save a depth map as float64 ``.npy`` (values as is, NaN kept) exactly at ``path``."""
    depth = _depth_array(depth, np.float64)
    with open(path, "wb") as file:
        np.save(file, depth)


def save_depth_tiff(path: PathLike, depth: np.ndarray) -> None:
    """Save a depth map as a float32 TIFF (NaN kept)."""
    tifffile.imwrite(path, _depth_array(depth, np.float32))


def _depth_array(depth: np.ndarray, dtype: type) -> np.ndarray:
    """Convert ``depth`` to a 2-D array of ``dtype``; raise InputError otherwise."""
    depth = np.asarray(depth, dtype=dtype)
    if depth.ndim != 2:
        raise InputError(f"depth must be a 2-D array, got shape {depth.shape}")
    return depth
