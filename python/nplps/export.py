"""Writing reconstruction results: meshes (PLY, OBJ, STL, GLB), point clouds, normal, albedo and depth maps.

Meshes are built from the vertex grid of the reconstruction: vertex ``(r, c)`` of the
``(H + 1, W + 1)`` grid is the top-left corner of pixel ``(r, c)``, and every masked pixel is the
quad facet with corners ``00 = (r, c)``, ``01 = (r, c + 1)``, ``10 = (r + 1, c)`` and
``11 = (r + 1, c + 1)``. Each facet is written as the two triangles ``(00, 10, 11)`` and
``(00, 11, 01)``: counter-clockwise as seen from the camera, so their right-hand normals point at
the camera (``n_z < 0`` in the OpenCV frame: x right, y down, z forward).

Everything is vectorized with numpy (no Python loop per vertex or face), so meshes with millions
of vertices are written quickly; the OBJ text is formatted by numpy too (see "Text formatting"),
giving the same characters as Python's ``%`` operator.

Every file is written under a temporary name in its directory and renamed into place when
complete (see :mod:`nplps._atomic`): an error while writing never leaves a truncated file under
the final name, and the OSError names the final path.
"""

from __future__ import annotations

import json
import os
import threading
import warnings
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from contextlib import ExitStack
from dataclasses import dataclass, field
from functools import partial
from typing import IO, TYPE_CHECKING, Any, TypeAlias

import numpy as np
import tifffile

from . import _core, plots, views
from ._atomic import atomic_path, atomic_write, write_error, write_text
from ._files import NotRegularFile, open_regular
from ._held_out import HeldOutScores, reading
from ._outdir import jsonable
from .errors import InputError

if TYPE_CHECKING:
    from pathlib import Path

    from ._outdir import ResultDirectory
    from ._records import Result

__all__ = [
    "EXR_EXTRA",
    "EXR_FILES",
    "EXTRA_FORMATS",
    "FORMATS",
    "NORMAL_MAP_FRAMES",
    "OBJ_MAX_FACETS",
    "ContactSheet",
    "OutputFormat",
    "check_formats",
    "check_normal_map",
    "decode_normal_map",
    "exr_available",
    "formats_help",
    "normal_map_pixels",
    "obj_skipped_note",
    "read_exr",
    "read_normal_map",
    "read_ply",
    "save_albedo",
    "save_albedo_exr",
    "save_depth_exr",
    "save_depth_npy",
    "save_depth_tiff",
    "save_grey_png",
    "save_normal_map",
    "save_normals_exr",
    "save_normals_tiff",
    "save_npy",
    "to_normal_frame",
    "write_exr",
    "write_glb",
    "write_meshes",
    "write_obj",
    "write_ply",
    "write_png",
    "write_png8",
    "write_png16",
    "write_pngs",
    "write_point_cloud",
    "write_result",
    "write_stl",
]

PathLike: TypeAlias = str | os.PathLike
"""A file name: ``str`` or any :class:`os.PathLike`."""

_OPENGL_FLIP = np.array([1.0, -1.0, -1.0], dtype=np.float32)
_COLOR_PERCENTILE = 99.0
_ALBEDO_PERCENTILE = 99.9
_OBJ_CHUNK_ROWS = 1 << 14
_GATHER_CHUNK = 1 << 20

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2",
    "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
    "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
}  # fmt: skip


# --------------------------------------------------------------------------------------------------
# Mesh construction (shared by the mesh and point formats)
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Mesh:
    """A triangle mesh ready to be written.

    Attributes
    ----------
    points : numpy.ndarray
        ``(n, 3)`` float32 vertex positions, in the output frame.
    normals : numpy.ndarray or None
        ``(n, 3)`` float32 vertex normals in the output frame.
    colors : numpy.ndarray or None
        ``(n, 3)`` uint8 grey vertex colours.
    faces : numpy.ndarray
        ``(m, 3)`` int32 vertex indices (0-based).
    frame : {"opencv", "opengl"}
        The output frame.
    overflow : numpy.ndarray
        Indices of the `points` beyond the float32 range (infinite there), in increasing order.
    overflow_points : numpy.ndarray
        ``(len(overflow), 3)`` float64 positions of those points (in the output frame), for the
        text formats (OBJ); the binary float32 formats refuse them (:func:`_require_float32`).
    """

    points: np.ndarray
    normals: np.ndarray | None
    colors: np.ndarray | None
    faces: np.ndarray
    frame: str
    overflow: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    overflow_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


def _build_mesh(
    vertices: np.ndarray,
    mask: np.ndarray,
    normals: np.ndarray | None,
    albedo: np.ndarray | None,
    opengl: bool,
) -> _Mesh:
    """Validate the grids and build the mesh of the masked, finite facets.

    The facets, the vertices they use, their float32 positions and normals and the triangles
    come from the Rust extension in one pass (``nplps._core.mesh_arrays``, the GIL released).
    """
    vertices, mask, normals, albedo = _check_mesh_inputs(vertices, mask, normals, albedo)
    used, points, mesh_normals, faces, skipped = _core.mesh_arrays(
        np.ascontiguousarray(vertices, dtype=np.float64),
        np.ascontiguousarray(mask),
        None if normals is None else np.ascontiguousarray(normals, dtype=np.float64),
        opengl,
    )
    _check_facets(skipped, len(faces))
    flip = _OPENGL_FLIP if opengl else None
    # The vertices used are finite: an infinite float32 point overflowed.
    overflow = np.flatnonzero(~_all_finite(points))
    wide = vertices.reshape(-1, 3)[used[overflow]].astype(np.float64)
    return _Mesh(
        points=points,
        normals=mesh_normals,
        colors=None if albedo is None else _grey_colors(albedo.reshape(-1, *albedo.shape[2:])[used]),
        faces=faces,
        frame="opengl" if opengl else "opencv",
        overflow=overflow,
        overflow_points=wide if flip is None else wide * flip.astype(np.float64),
    )


def _check_facets(skipped: int, triangles: int) -> None:
    """Warn about the masked facets left out for a non-finite corner; raise InputError if none is left."""
    if skipped:
        warnings.warn(
            f"skipped {skipped} masked facet(s) with a non-finite corner (NaN or inf)",
            RuntimeWarning,
            stacklevel=4,
        )
    if not triangles:
        raise InputError("no facet to write: the mask is empty or every masked facet has NaN")


def _all_finite(values: np.ndarray) -> np.ndarray:
    """Return whether every value along the last axis is finite (``np.isfinite(values).all(axis=-1)``, faster).

    numpy's reduction over a short last axis is several times slower than combining its columns.
    """
    finite = np.isfinite(values)
    out = finite[..., 0].copy()
    for i in range(1, values.shape[-1]):
        out &= finite[..., i]
    return out


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


def _used_vertices(facets: np.ndarray) -> np.ndarray:
    """Boolean ``(H + 1, W + 1)`` grid of the vertices that are a corner of a facet."""
    used = np.zeros((facets.shape[0] + 1, facets.shape[1] + 1), dtype=bool)
    used[:-1, :-1] |= facets
    used[:-1, 1:] |= facets
    used[1:, :-1] |= facets
    used[1:, 1:] |= facets
    return used


def _quantize(values: np.ndarray, percentile: float, max_value: int, dtype: type) -> tuple[np.ndarray, float]:
    """Scale ``values`` so their ``percentile`` maps to ``max_value``; clip, round, NaN -> 0.

    Returns the integer array and the scale factor (pixel = value * scale). Without finite
    positive values the scale is 1.
    """
    values = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(values)
    reference = float(np.percentile(values[finite], percentile)) if finite.any() else 0.0
    scale = max_value / reference if reference > 0 else 1.0
    scaled = np.multiply(values, scale)  # one temporary, then in place
    np.clip(scaled, 0, max_value, out=scaled)
    np.rint(scaled, out=scaled)
    scaled[~finite] = 0.0  # NaN and inf (inf * scale would clip to max_value)
    return scaled.astype(dtype), scale


def _grey_colors(albedo: np.ndarray) -> np.ndarray:
    """Return ``(n, 3)`` uint8 colours from the albedo.

    The albedo (grey ``(n,)`` or RGB ``(n, 3)``) scaled by its 99th percentile (over all channels)
    to 0..255.
    """
    colors, _ = _quantize(albedo, _COLOR_PERCENTILE, 255, np.uint8)
    return colors if colors.ndim == 2 else np.repeat(colors[:, None], 3, axis=1)


# --------------------------------------------------------------------------------------------------
# PLY
# --------------------------------------------------------------------------------------------------


def write_ply(
    path: PathLike,
    vertices: np.ndarray,
    mask: np.ndarray,
    *,
    normals: np.ndarray | None = None,
    albedo: np.ndarray | None = None,
    opengl: bool = False,
) -> None:
    """Write the masked part of a vertex grid as a binary little-endian PLY triangle mesh.

    Parameters
    ----------
    path : str or path-like
        Output file.
    vertices : numpy.ndarray
        ``(H + 1, W + 1, 3)`` vertex positions (OpenCV camera frame).
    mask : numpy.ndarray
        ``(H, W)`` bool; every selected pixel becomes two triangles ``(00, 10, 11)`` and
        ``(00, 11, 01)`` (facing the camera, see the module docstring).
    normals : numpy.ndarray, optional
        ``(H + 1, W + 1, 3)`` per-vertex normals, written as ``nx, ny, nz``.
    albedo : numpy.ndarray, optional
        ``(H + 1, W + 1)`` per-vertex albedo, written as grey ``red, green, blue`` uchar colours
        scaled so that the 99th percentile of the written finite values is 255 (clipped;
        NaN -> 0).
    opengl : bool, default False
        Write in the OpenGL frame (y up, z backwards): positions ``(x, -y, -z)`` and normals
        ``(nx, -ny, -nz)``. This is a rotation, so faces keep facing the viewer.

    Raises
    ------
    InputError
        The shapes do not match, there is no facet to write, or a vertex position is beyond the
        float32 range that PLY stores.

    Warns
    -----
    RuntimeWarning
        Masked facets with a non-finite corner position (or normal) were skipped.

    Notes
    -----
    Only the vertices used by the written facets are stored (row-major order). The header has the
    comments ``nplps`` and ``frame opencv`` / ``frame opengl``.
    """
    _stream_ply(path, vertices, mask, normals, albedo, opengl)


def _stream_ply(
    path: PathLike,
    vertices: np.ndarray,
    mask: np.ndarray,
    normals: np.ndarray | None,
    albedo: np.ndarray | None,
    opengl: bool,
    *,
    per_pixel: bool = False,
    camera: Mapping[str, Any] | None = None,
) -> None:
    """Write :func:`write_ply`'s file without whole-mesh arrays (``nplps._core.write_ply``, the GIL released).

    The Rust extension counts and numbers the used vertices (4 bytes per vertex) and computes the
    colours' scale, then writes the vertex and face records in blocks of rows: the same bytes as
    :func:`_write_ply_mesh` of :func:`_build_mesh`'s mesh. With ``per_pixel``, ``normals``
    (``(H, W, 3)``) and ``albedo`` (``(H, W)`` or ``(H, W, 3)``) are per-pixel maps whose vertex
    means (``Reconstruction.vertex_normals``, ``vertex_albedo``) are computed as the records are
    written, with no per-vertex grid. With ``camera`` (per-pixel maps only), ``vertices`` is the
    ``(H + 1, W + 1)`` vertex depth map and the positions (``_core.vertices(depth, camera)``)
    are made vertex by vertex too.
    """
    vertices = np.asarray(vertices)
    if per_pixel:
        if camera is None:
            vertices, mask, _, _ = _check_mesh_inputs(vertices, mask, None, None)
        mask = np.asarray(mask, dtype=bool)
        pixels = (vertices.shape[0] - 1, vertices.shape[1] - 1)
        _require_shape("mask", mask, pixels)
        if normals is not None:
            _require_shape("normals", np.asarray(normals), (*pixels, 3))
        if albedo is not None and np.ndim(albedo) == 3:
            _require_shape("albedo", np.asarray(albedo), (*pixels, 3))
        elif albedo is not None:
            _require_shape("albedo", np.asarray(albedo), pixels)
    else:
        vertices, mask, normals, albedo = _check_mesh_inputs(vertices, mask, normals, albedo)
    normals = None if normals is None else np.ascontiguousarray(normals, dtype=np.float64)
    grey = None
    if albedo is not None:
        albedo = np.asarray(albedo)
        grey = np.ascontiguousarray(albedo if albedo.ndim == 3 else albedo[..., None], dtype=np.float64)
    with atomic_path(path) as temporary:
        _, facets, skipped, overflow = _core.write_ply(
            temporary,
            np.ascontiguousarray(vertices, dtype=np.float64),
            np.ascontiguousarray(mask),
            normals,
            grey,
            per_pixel,
            opengl,
            camera=None if camera is None else dict(camera),
        )
        _check_facets(skipped, 2 * facets)
        if overflow:
            raise _float32_error("PLY", path, overflow)


def write_meshes(
    ply_path: PathLike | None,
    obj_path: PathLike | None,
    vertices: np.ndarray,
    mask: np.ndarray,
    *,
    normals: np.ndarray | None = None,
    albedo: np.ndarray | None = None,
    opengl: bool = False,
    stl_path: PathLike | None = None,
    glb_path: PathLike | None = None,
    points_path: PathLike | None = None,
) -> None:
    """Write the same mesh as PLY and OBJ (and STL, GLB, a point cloud), building it once.

    Parameters
    ----------
    ply_path, obj_path : str or path-like or None
        The files to write (None: not that one).
    vertices, mask, normals, albedo, opengl
        As in :func:`write_ply`.
    stl_path, glb_path, points_path : str or path-like, optional
        Also write the mesh as binary STL (:func:`write_stl`), glTF binary (:func:`write_glb`)
        or its vertices as a PLY point cloud (:func:`write_point_cloud`).

    See Also
    --------
    write_ply, write_obj, write_stl, write_glb, write_point_cloud
    """
    extra = {"stl": stl_path, "glb": glb_path, "points": points_path}
    _write_meshes(ply_path, obj_path, vertices, mask, normals, albedo, opengl, extra)


def _write_meshes(
    ply_path: PathLike | None,
    obj_path: PathLike | None,
    vertices: np.ndarray,
    mask: np.ndarray,
    normals: np.ndarray | None,
    albedo: np.ndarray | None,
    opengl: bool,
    extra: Mapping[str, PathLike | None],
) -> None:
    """:func:`write_meshes` with the extra mesh formats by their :data:`FORMATS` name."""
    if ply_path is not None and obj_path is None and not any(extra.values()):
        _stream_ply(ply_path, vertices, mask, normals, albedo, opengl)  # no mesh arrays
        return
    mesh = _build_mesh(vertices, mask, normals, albedo, opengl)
    targets = [(f, extra.get(f.name)) for f in FORMATS.values() if f.mesh is not None]
    float32 = [("PLY", ply_path)] + [(f.mesh, target) for f, target in targets]
    for fmt, target in float32:  # before any file is written
        if fmt is not None and target is not None:
            _require_float32(mesh, fmt, target)
    if ply_path is not None:
        _write_ply_mesh(ply_path, mesh)
    if obj_path is not None:
        _write_obj_mesh(obj_path, mesh)
    for f, target in targets:
        if target is not None:
            f.write(target, mesh)


#: Rows (vertices or faces) per block of the binary PLY writer.
_PLY_BLOCK = 1 << 18


def _write_ply_mesh(path: PathLike, mesh: _Mesh) -> None:
    _require_float32(mesh, "PLY", path)
    with atomic_write(path) as file:
        file.write(_ply_header(mesh).encode("ascii"))
        _write_ply_vertices(file, mesh)
        for start in range(0, len(mesh.faces), _PLY_BLOCK):
            file.write(_ply_face_records(mesh.faces[start : start + _PLY_BLOCK]).view(np.uint8).data)


def _write_ply_vertices(file: IO[bytes], mesh: _Mesh) -> None:
    """Write the vertex element of ``mesh`` in blocks of :data:`_PLY_BLOCK` records (no whole-file buffer)."""
    for start in range(0, len(mesh.points), _PLY_BLOCK):
        block = slice(start, start + _PLY_BLOCK)
        part = _Mesh(
            points=mesh.points[block],
            normals=None if mesh.normals is None else mesh.normals[block],
            colors=None if mesh.colors is None else mesh.colors[block],
            faces=mesh.faces[:0],
            frame=mesh.frame,
        )
        file.write(_ply_vertex_records(part).view(np.uint8).data)  # no copy of the records


def _ply_header(mesh: _Mesh, *, faces: bool = True) -> str:
    """Return the ASCII header of the PLY file for ``mesh`` (without the face element: a point cloud)."""
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
    if faces:
        lines += [f"element face {len(mesh.faces)}", "property list uchar int vertex_indices"]
    return "\n".join([*lines, "end_header"]) + "\n"


def _ply_vertex_records(mesh: _Mesh) -> np.ndarray:
    """Return the vertex element of ``mesh`` as one packed structured array."""
    groups = [(("x", "y", "z"), "<f4", mesh.points)]
    if mesh.normals is not None:
        groups.append((("nx", "ny", "nz"), "<f4", mesh.normals))
    if mesh.colors is not None:
        groups.append((("red", "green", "blue"), "u1", mesh.colors))
    dtype = np.dtype([(name, kind) for names, kind, _ in groups for name in names])
    records = np.empty(len(mesh.points), dtype=dtype)
    raw = records.view(np.uint8).reshape(len(records), dtype.itemsize)
    offset = 0
    for _, kind, values in groups:  # one (n, 3) block per group, copied as fixed-size items
        block = np.ascontiguousarray(values, dtype=kind)
        width = block.itemsize * 3
        raw[:, offset : offset + width].view(f"V{width}")[...] = block.view(f"V{width}")
        offset += width
    return records


def _ply_face_records(faces: np.ndarray) -> np.ndarray:
    """Return the face element: ``uchar 3`` followed by three ``int`` indices per face."""
    records = np.empty(len(faces), dtype=[("count", "u1"), ("vertex_indices", "<i4", (3,))])
    records["count"] = 3
    records["vertex_indices"] = faces
    return records


def read_ply(path: PathLike) -> dict[str, np.ndarray | list[str] | None]:
    """Read a binary little-endian triangle PLY file such as those :func:`write_ply` writes.

    Parameters
    ----------
    path : str or path-like
        The PLY file.

    Returns
    -------
    dict
        ``vertices`` (``(n, 3)`` float), ``normals`` (``(n, 3)`` float or None), ``colors``
        (``(n, 3)`` uint8 or None), ``faces`` (``(m, 3)`` int64, 0-based) and ``comments`` (the
        header comment lines, without ``comment``).

    Raises
    ------
    InputError
        The file cannot be read or is not a binary little-endian triangle PLY file.
    """
    try:
        # A device or FIFO is refused before it is read (see _files.open_regular).
        file, _ = open_regular(path)
        with file:
            data = file.read()
    except NotRegularFile as exc:
        raise InputError(f"cannot read PLY file '{os.fspath(path)}': not a regular file (it is {exc})") from None
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
    """Return the elements declared by the header: name, count and record dtype.

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
            elements[-1][2].extend([(f"{name}_count", _PLY_TYPES[count_type]), (name, _PLY_TYPES[item_type], (3,))])
        elif words[:1] == ["property"]:
            elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
    return [(name, count, np.dtype(fields)) for name, count, fields in elements]


def _ply_result(arrays: dict[str, np.ndarray], comments: list[str]) -> dict[str, np.ndarray | list[str] | None]:
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
    *,
    normals: np.ndarray | None = None,
    albedo: np.ndarray | None = None,
    opengl: bool = False,
) -> None:
    """Write the masked part of a vertex grid as a Wavefront OBJ triangle mesh.

    Parameters
    ----------
    path, vertices, mask, normals, albedo, opengl
        As in :func:`write_ply` (same mesh and frames).

    Raises
    ------
    InputError
        The shapes do not match, or there is no facet to write.

    Notes
    -----
    Vertices are written as ``v x y z`` or, with `albedo`, ``v x y z r g b`` (grey colours as
    floats in 0..1, the PLY colours divided by 255); normals as ``vn nx ny nz``; faces with
    1-based indices as ``f a//a b//b c//c`` (with normals) or ``f a b c``. The file starts with
    the comments ``# nplps`` and ``# frame opencv`` / ``# frame opengl``. Positions are written
    at float32 precision, as in the other formats; a position beyond the float32 range (which
    PLY, STL and GLB refuse) is written exactly, from its float64 value.
    """
    _write_obj_mesh(path, _build_mesh(vertices, mask, normals, albedo, opengl))


def _write_obj_mesh(path: PathLike, mesh: _Mesh) -> None:
    with atomic_write(path) as file:
        file.write(f"# nplps\n# frame {mesh.frame}\n".encode("ascii"))
        _write_text(file, _obj_chunks(mesh))


def _obj_chunks(mesh: _Mesh) -> Iterator[Callable[[], bytes]]:
    """Return the OBJ body of ``mesh`` as jobs that each format a chunk of lines, in file order.

    The lines are those of the %-formats ``"v %.9g %.9g %.9g[ %.6g %.6g %.6g]"`` (points;
    colours / 255; a point beyond the float32 range as the shortest exact text of its float64
    position), ``"vn %.7g %.7g %.7g"`` and ``"f %d//%d %d//%d %d//%d"`` or ``"f %d %d %d"``
    (1-based indices).
    """
    points, normals, colors, faces = mesh.points, mesh.normals, mesh.colors, mesh.faces
    for start in range(0, len(points), _OBJ_CHUNK_ROWS):
        chunk = slice(start, start + _OBJ_CHUNK_ROWS)
        job = partial(_vertex_lines, points[chunk], None if colors is None else colors[chunk])
        lo, hi = np.searchsorted(mesh.overflow, [start, start + _OBJ_CHUNK_ROWS])
        if hi > lo:  # positions beyond float32: written in full (float64) precision
            job = partial(_widen, job, mesh.overflow[lo:hi] - start, mesh.overflow_points[lo:hi])
        yield job
    if normals is not None:
        for start in range(0, len(normals), _OBJ_CHUNK_ROWS):
            yield partial(_normal_lines, normals[start : start + _OBJ_CHUNK_ROWS])
    for start in range(0, len(faces), _OBJ_CHUNK_ROWS):
        yield partial(_face_lines, faces[start : start + _OBJ_CHUNK_ROWS], normals is not None)


def _vertex_lines(points: np.ndarray, colors: np.ndarray | None) -> bytes:
    fields: list[Any] = [_format_float32(points[:, i], 9) for i in range(3)]
    if colors is not None:
        fields += [np.take(_COLOR_TEXT, colors[:, i], axis=0) for i in range(3)]
    return _lines([b"v ", *_join(b" ", fields), b"\n"])


def _widen(job: Callable[[], bytes], rows: np.ndarray, points: np.ndarray) -> bytes:
    """Return the vertex lines of ``job`` with the positions of lines ``rows`` as ``points`` (float64, exact)."""
    lines = job().split(b"\n")
    for row, point in zip(rows.tolist(), points, strict=True):
        words = lines[row].split(b" ")
        words[1:4] = [repr(float(v)).encode("ascii") for v in point]
        lines[row] = b" ".join(words)
    return b"\n".join(lines)


def _normal_lines(normals: np.ndarray) -> bytes:
    return _lines([b"vn ", *_join(b" ", [_format_float32(normals[:, i], 7) for i in range(3)]), b"\n"])


def _face_lines(faces: np.ndarray, with_normals: bool) -> bytes:
    corners, blanks = zip(*(_format_int(faces[:, i] + 1) for i in range(3)), strict=True)
    fields: list[Any] = [[c, b"//", c] for c in corners] if with_normals else list(corners)
    return _lines([b"f ", *_join(b" ", fields), b"\n"], compact=any(blanks))


def _join(separator: bytes, fields: list) -> list:
    """``fields`` with ``separator`` between them."""
    out: list = []
    for i, item in enumerate(fields):
        out += [separator, item] if i else [item]
    return out


def _write_text(file: IO[bytes], jobs: Iterator[Callable[[], bytes]]) -> None:
    """Run the formatting ``jobs`` on a few threads and write their results in order.

    Numpy releases the GIL; a bounded number of chunks is in flight.
    """
    workers = max(1, min(4, os.cpu_count() or 1))
    if workers == 1:
        for job in jobs:
            file.write(job())
        return
    with ThreadPoolExecutor(workers) as pool:
        pending: list = []
        for job in jobs:
            pending.append(pool.submit(job))
            if len(pending) > 2 * workers:
                file.write(pending.pop(0).result())
        for future in pending:
            file.write(future.result())


# --------------------------------------------------------------------------------------------------
# STL, glTF binary (GLB) and point clouds
# --------------------------------------------------------------------------------------------------

_STL_RECORD = np.dtype([("normal", "<f4", (3,)), ("corners", "<f4", (3, 3)), ("attribute", "<u2")])
_GLB_MAGIC, _GLB_VERSION = 0x46546C67, 2  # b"glTF"
_GLB_JSON, _GLB_BIN = 0x4E4F534A, 0x004E4942  # b"JSON", b"BIN\0"
_GL_FLOAT, _GL_UNSIGNED_BYTE, _GL_UNSIGNED_INT = 5126, 5121, 5125
_GL_ARRAY_BUFFER, _GL_ELEMENT_ARRAY_BUFFER, _GL_TRIANGLES = 34962, 34963, 4


def write_stl(path: PathLike, vertices: np.ndarray, mask: np.ndarray, *, opengl: bool = False) -> None:
    """Write the masked part of a vertex grid as a binary STL triangle mesh.

    Parameters
    ----------
    path : str or path-like
        Output file.
    vertices, mask, opengl
        As in :func:`write_ply`: the same triangles, two per masked facet, in the same order.

    Raises
    ------
    InputError
        The shapes do not match, or there is no facet to write.

    Notes
    -----
    Binary STL: an 80-byte header (``nplps binary STL, frame opencv`` / ``opengl``, padded with
    spaces), the triangle count (uint32) and 50 bytes per triangle: the unit facet normal (the
    right-hand normal of the corners, so facing the camera), the three corners (float32) and a
    zero attribute word. STL has no vertex normals or colours. The triangles are converted and
    written in chunks.
    """
    _write_stl_mesh(path, _build_mesh(vertices, mask, None, None, opengl))


def write_glb(
    path: PathLike,
    vertices: np.ndarray,
    mask: np.ndarray,
    *,
    normals: np.ndarray | None = None,
    albedo: np.ndarray | None = None,
    opengl: bool = False,
) -> None:
    """Write the masked part of a vertex grid as a glTF 2.0 binary file (GLB).

    Parameters
    ----------
    path : str or path-like
        Output file.
    vertices, mask, normals, albedo, opengl
        As in :func:`write_ply` (same vertices, triangles and frames). glTF viewers expect y up:
        use ``opengl=True`` for them.

    Raises
    ------
    InputError
        The shapes do not match, or there is no facet to write.

    Notes
    -----
    One buffer, one mesh with one triangle primitive, one node and one scene. Attributes:
    ``POSITION`` (float32 VEC3, with ``min`` / ``max``), ``NORMAL`` (float32 VEC3, the vertex
    normals) and ``COLOR_0`` (normalized unsigned byte VEC4: the grey colours of the PLY file and
    alpha 255); indices are uint32. The JSON chunk is padded with spaces and the BIN chunk with
    zeros to 4 bytes; every accessor starts on a 4-byte boundary. ``asset.extras.frame`` names the
    frame.
    """
    _write_glb_mesh(path, _build_mesh(vertices, mask, normals, albedo, opengl))


def write_point_cloud(
    path: PathLike,
    vertices: np.ndarray,
    mask: np.ndarray,
    *,
    normals: np.ndarray | None = None,
    albedo: np.ndarray | None = None,
    opengl: bool = False,
) -> None:
    """Write the vertices of the masked mesh as a binary PLY point cloud (no faces).

    Parameters
    ----------
    path : str or path-like
        Output file.
    vertices, mask, normals, albedo, opengl
        As in :func:`write_ply`: the same vertex element (positions, normals, grey colours, in the
        same order), without the face element.

    Raises
    ------
    InputError
        The shapes do not match, there is no facet to write, or a vertex position is beyond the
        float32 range that PLY stores.
    """
    _write_points_mesh(path, _build_mesh(vertices, mask, normals, albedo, opengl))


def save_normals_tiff(path: PathLike, normals: np.ndarray) -> None:
    """Save per-pixel normals as a 32-bit float RGB TIFF (values as is, NaN kept).

    Parameters
    ----------
    path : str or path-like
        Output file (written as TIFF whatever its extension).
    normals : numpy.ndarray
        ``(H, W, 3)`` normals, stored as ``(H, W, 3)`` float32 in the frame given (the OpenCV frame
        for :attr:`nplps.Reconstruction.normals`; unlike the PNG normal map, no flip).

    Raises
    ------
    InputError
        `normals` has the wrong shape.
    """
    normals = np.asarray(normals, dtype=np.float32)
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise InputError(f"normals must have shape (H, W, 3), got {normals.shape}")
    with atomic_path(path) as temporary:
        tifffile.imwrite(temporary, normals, photometric="rgb")


def _require_float32(mesh: _Mesh, fmt: str, path: PathLike) -> None:
    """Refuse a mesh whose positions do not fit float32 (they became infinite): PLY, STL and GLB store float32.

    OBJ (text) writes those positions in full (double) precision instead.
    """
    if len(mesh.overflow):
        raise _float32_error(fmt, path, len(mesh.overflow))


def _float32_error(fmt: str, path: PathLike, count: int) -> InputError:
    """Return the error of :func:`_require_float32` for ``count`` positions beyond the float32 range."""
    return InputError(
        f"cannot write {fmt} file '{os.fspath(path)}': {count} vertex position(s) "
        f"beyond the float32 range (|value| > {float(np.finfo(np.float32).max):.4g}) that {fmt} stores"
    )


def _write_stl_mesh(path: PathLike, mesh: _Mesh) -> None:
    _require_float32(mesh, "STL", path)
    header = f"nplps binary STL, frame {mesh.frame}".encode("ascii").ljust(80, b" ")
    with atomic_write(path) as file:
        file.write(header)
        file.write(np.uint32(len(mesh.faces)).astype("<u4").tobytes())
        for start in range(0, len(mesh.faces), _GATHER_CHUNK):
            faces = mesh.faces[start : start + _GATHER_CHUNK]
            records = np.zeros(len(faces), dtype=_STL_RECORD)
            corners = mesh.points[faces]  # (m, 3, 3) float32
            records["corners"] = corners
            a, b, c = (corners[:, i].astype(np.float64) for i in range(3))
            records["normal"] = _normalize_rows(np.cross(b - a, c - a))
            file.write(records.view(np.uint8).data)


def _normalize_rows(v: np.ndarray) -> np.ndarray:
    """Rows of ``v`` scaled to unit length (zero rows stay zero)."""
    length = np.linalg.norm(v, axis=1, keepdims=True)
    return v / np.where(length > 0, length, 1.0)


def _glb_json(mesh: _Mesh) -> tuple[bytes, list[tuple[np.ndarray | None, int]]]:
    """Return the padded JSON chunk data of ``mesh``'s GLB and the BIN chunk's parts.

    The parts are (array or None, byte length): None stands for the colours, converted to RGBA
    while writing.
    """
    n, m = len(mesh.points), len(mesh.faces)
    parts: list[tuple[np.ndarray | None, int]] = []
    views: list[dict[str, Any]] = []
    accessors: list[dict[str, Any]] = []
    attributes: dict[str, int] = {}

    def add(array: np.ndarray | None, length: int, target: int, accessor: dict[str, Any]) -> int:
        offset = sum(size for _, size in parts)
        parts.append((array, length))
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": length, "target": target})
        accessors.append({"bufferView": len(views) - 1, "byteOffset": 0, **accessor})
        return len(accessors) - 1

    low = [float(v) for v in mesh.points.min(axis=0)]
    high = [float(v) for v in mesh.points.max(axis=0)]
    vec3 = {"componentType": _GL_FLOAT, "count": n, "type": "VEC3"}
    attributes["POSITION"] = add(mesh.points, 12 * n, _GL_ARRAY_BUFFER, {**vec3, "min": low, "max": high})
    if mesh.normals is not None:
        attributes["NORMAL"] = add(mesh.normals, 12 * n, _GL_ARRAY_BUFFER, vec3)
    if mesh.colors is not None:
        color = {"componentType": _GL_UNSIGNED_BYTE, "normalized": True, "count": n, "type": "VEC4"}
        attributes["COLOR_0"] = add(None, 4 * n, _GL_ARRAY_BUFFER, color)
    scalar = {"componentType": _GL_UNSIGNED_INT, "count": 3 * m, "type": "SCALAR"}
    indices = add(mesh.faces, 12 * m, _GL_ELEMENT_ARRAY_BUFFER, scalar)
    document = {
        "asset": {"version": "2.0", "generator": "nplps", "extras": {"frame": mesh.frame}},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "nplps"}],
        "meshes": [{"primitives": [{"attributes": attributes, "indices": indices, "mode": _GL_TRIANGLES}]}],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": sum(size for _, size in parts)}],
    }
    text = json.dumps(document, separators=(",", ":")).encode("utf-8")
    return text + b" " * (-len(text) % 4), parts


def _write_glb_mesh(path: PathLike, mesh: _Mesh) -> None:
    _require_float32(mesh, "GLB", path)
    json_chunk, parts = _glb_json(mesh)
    binary = sum(size for _, size in parts)  # every part is a multiple of 4 bytes
    total = 12 + 8 + len(json_chunk) + 8 + binary
    with atomic_write(path) as file:
        file.write(np.array([_GLB_MAGIC, _GLB_VERSION, total], dtype="<u4").tobytes())
        file.write(np.array([len(json_chunk), _GLB_JSON], dtype="<u4").tobytes())
        file.write(json_chunk)
        file.write(np.array([binary, _GLB_BIN], dtype="<u4").tobytes())
        for array, _ in parts:
            if array is None:  # the grey colours as RGBA, in chunks
                assert mesh.colors is not None
                for start in range(0, len(mesh.colors), _GATHER_CHUNK):
                    rgb = mesh.colors[start : start + _GATHER_CHUNK]
                    rgba = np.full((len(rgb), 4), 255, dtype=np.uint8)
                    rgba[:, :3] = rgb
                    file.write(rgba.data)
            else:
                # Float32 as is; the int32 indices (all >= 0) have the bytes of uint32: no copy.
                dtype = "<i4" if array.dtype.kind in "iu" else "<f4"
                file.write(np.ascontiguousarray(array, dtype=dtype).view(np.uint8).data)


def _write_points_mesh(path: PathLike, mesh: _Mesh) -> None:
    _require_float32(mesh, "PLY", path)
    with atomic_write(path) as file:
        file.write(_ply_header(mesh, faces=False).encode("ascii"))
        _write_ply_vertices(file, mesh)


@dataclass(frozen=True)
class OutputFormat:
    """An optional output format of ``Reconstruction.save`` and ``--formats`` (an entry of :data:`FORMATS`).

    Attributes
    ----------
    name : str
        The format's name in ``formats=`` and ``--formats``.
    file : str
        The file written in the result directory (``{stem}`` is the mesh's stem).
    help : str
        What the file holds, for ``--formats``'s help text.
    write : callable
        ``write(path, data)``: the writer; `data` is the mesh built once for all mesh formats
        (`mesh` set) or the result's :attr:`~nplps.Reconstruction.normals` (`mesh` None).
    mesh : str or None
        The name of a mesh format in the message that refuses positions beyond float32 (None:
        not written from the mesh).
    """

    name: str
    file: str
    help: str
    write: Callable[[PathLike, Any], None]
    mesh: str | None = None


def _three_files(path: PathLike, data: Any) -> None:  # pragma: no cover - never called
    raise AssertionError("the exr format's files are written by write_result")


#: The optional output formats by name (one declaration each: file, writer and help).
FORMATS: dict[str, OutputFormat] = {
    f.name: f
    for f in (
        OutputFormat("stl", "{stem}.stl", "", _write_stl_mesh, mesh="STL"),
        OutputFormat(
            "glb", "{stem}.glb", "glTF 2.0 binary; use --opengl for y-up viewers", _write_glb_mesh, mesh="GLB"
        ),
        OutputFormat("points", "points.ply", "a point cloud with normals and colours", _write_points_mesh, mesh="PLY"),
        OutputFormat("normals_tiff", "normals.tiff", "32-bit float normals", save_normals_tiff),
        OutputFormat(
            "obj",
            "{stem}.obj",
            "Wavefront OBJ text; written anyway up to 4 million facets (OBJ_MAX_FACETS)",
            _write_obj_mesh,
            mesh="OBJ",
        ),
        # Three files (EXR_FILES), written by write_result itself: not through `write`.
        OutputFormat(
            "exr",
            "depth.exr, normals.exr, albedo.exr",
            "32-bit float; normals in the --normal-map frame; needs OpenEXR: pip install nplps[exr]",
            _three_files,
        ),
    )
}

#: ``Reconstruction.save`` writes ``mesh.obj`` by default only for results of at most this many
#: facets (masked pixels): 4 million, a 4 MP result, whose OBJ file is about 0.8 GB of text (a
#: 12 MP result's is 2.4 GB and takes longer to write than everything else together). Larger
#: results get it when asked for: ``formats=["obj"]``, ``nplps reconstruct --formats obj`` or
#: ``--obj``; ``summary.json``'s ``"skipped"`` says when it was left out and how to get it.
OBJ_MAX_FACETS = 4_000_000


def obj_skipped_note(facets: int) -> str:
    """Return the note of ``summary.json``'s ``"skipped"`` for an OBJ file left out (:data:`OBJ_MAX_FACETS`)."""
    return (
        f"not written by default: {facets} facets is more than {OBJ_MAX_FACETS} (OBJ_MAX_FACETS); "
        'ask for it with formats=["obj"] or nplps reconstruct --obj (the same mesh is in the PLY file)'
    )


#: The files of the ``"exr"`` format by kind (:meth:`nplps.Reconstruction.save`'s paths).
EXR_FILES = {"depth_exr": "depth.exr", "normals_exr": "normals.exr", "albedo_exr": "albedo.exr"}

#: The optional output formats of :meth:`nplps.Reconstruction.save` (``formats=``) and
#: ``nplps reconstruct --formats``: file name (``{stem}`` is the mesh's stem) by format
#: (made from :data:`FORMATS`; for ``"exr"`` its three names, comma-separated: :data:`EXR_FILES`).
EXTRA_FORMATS: dict[str, str] = {name: f.file for name, f in FORMATS.items()}


def formats_help() -> str:
    """Return ``--formats``'s list of the formats: ``stl (mesh.stl), glb (mesh.glb, ...), ...``."""
    return ", ".join(
        f"{f.name} ({f.file.format(stem='mesh')}{', ' + f.help if f.help else ''})" for f in FORMATS.values()
    )


def check_formats(formats: Iterable[str]) -> list[str]:
    """Return the extra formats of :meth:`nplps.Reconstruction.save`, checked, without repeats."""
    if isinstance(formats, str):
        formats = [formats]
    chosen = list(dict.fromkeys(formats))
    unknown = [f for f in chosen if f not in FORMATS]
    if unknown:
        known = ", ".join(FORMATS)
        raise InputError(f"formats: unknown format(s) {', '.join(map(repr, unknown))}; choose from {known}")
    if "exr" in chosen and not exr_available():
        raise InputError(f"the exr format needs the OpenEXR Python binding 3.3 or later: {EXR_EXTRA}")
    return chosen


# --------------------------------------------------------------------------------------------------
# Text formatting
# --------------------------------------------------------------------------------------------------
#
# An OBJ file of a 12-megapixel result holds about 250 million numbers, which Python's % operator
# formats one by one in half a minute. The functions below produce the same characters as
# "%.<P>g" (for float32 values) and "%d" (for non-negative integers) with numpy, a column of
# characters at a time: each number becomes a row of bytes in which unused positions hold the
# byte 0; a chunk of lines is laid out as a table of such rows and literal separators, and the
# 0 bytes are dropped. Values the vectorized path does not cover (NaN, inf, magnitudes of 10^P
# and above or below about 10^(P - 18)) are formatted by Python.

_BLANK, _ZERO, _POINT, _MINUS, _PLUS, _E = 0, ord("0"), ord("."), ord("-"), ord("+"), ord("e")
_POW10 = 10.0 ** np.arange(13)  # exact in float64, and 5^12 < 2^29
_POW5 = np.array([5**k for k in range(18)], dtype=np.uint64)  # 2^24 * 5^17 < 2^64


def _digit_tables() -> dict[str, np.ndarray]:
    """Return four-digit groups 0000..9999 as one uint32 (4 ASCII bytes) each.

    ``full`` is zero-padded, ``lead`` with its leading zeros blank (0 is all blank), ``last`` like
    ``lead`` but 0 is "0".
    """
    n = np.arange(10000)
    powers = 10 ** np.arange(3, -1, -1)
    digits = (n[:, None] // powers % 10 + _ZERO).astype(np.uint8)
    lead = np.where(n[:, None] < powers, np.uint8(_BLANK), digits)
    last = lead.copy()
    last[0, 3] = _ZERO
    return {
        name: np.ascontiguousarray(table).view(np.uint32).ravel()
        for name, table in (("full", digits), ("lead", lead), ("last", last))
    }


_DIGITS = _digit_tables()


def _color_text() -> np.ndarray:
    """``"%.6g" % (c / 255)`` for the 256 colour levels, as rows of bytes (0-padded)."""
    texts = [("%.6g" % (c / 255.0)).encode("ascii") for c in range(256)]
    table = np.zeros((256, max(map(len, texts))), dtype=np.uint8)
    for c, text in enumerate(texts):
        table[c, : len(text)] = np.frombuffer(text, dtype=np.uint8)
    return table


_COLOR_TEXT = _color_text()


def _lines(fields: Sequence[bytes | np.ndarray | list[np.ndarray]], compact: bool = True) -> bytes:
    """Return the text of lines made of ``fields``.

    Fields are literal bytes (the same on every line), arrays of characters, ``(n,)`` or
    ``(n, width)`` uint8 with 0 for nothing, or lists of such arrays. ``compact=False`` says that
    there is no 0 byte to drop.
    """
    pieces = [p for f in fields for p in (f if isinstance(f, list) else [f])]
    n = next(len(p) for p in pieces if isinstance(p, np.ndarray))
    widths = [len(p) if isinstance(p, bytes) else (p.shape[1] if p.ndim == 2 else 1) for p in pieces]
    table = np.empty((n, sum(widths)), dtype=np.uint8)
    column = 0
    for piece, width in zip(pieces, widths, strict=True):
        if isinstance(piece, bytes):  # byte by byte: faster than a broadcast row
            for k, byte in enumerate(piece):
                table[:, column + k] = byte
        elif piece.ndim == 1:
            table[:, column] = piece
        else:  # one fixed-size item per row: faster than a 2-D copy of short rows
            table[:, column : column + width].view(f"V{width}")[...] = piece.view(f"V{width}")
        column += width
    flat = table.ravel()
    return flat[flat != _BLANK].tobytes() if compact else flat.tobytes()


def _format_int(values: np.ndarray) -> tuple[np.ndarray, bool]:
    """Return ``"%d"`` of non-negative integers below 2^32, as ``(n, width)`` characters.

    Also return whether there are 0 bytes among them (not when all values have as many digits).
    """
    v = np.asarray(values).ravel()
    top, bottom = (int(v.max()), int(v.min())) if v.size else (0, 0)
    if bottom < 0 or top >= 2**32:
        raise ValueError("_format_int formats integers in [0, 2^32)")
    v = v.astype(np.uint32)
    groups = 1 if top < 10**4 else 2 if top < 10**8 else 3
    out = np.empty((len(v), groups), dtype=np.uint32)
    rest = v
    for g in range(groups - 1, -1, -1):  # least significant group first
        higher = rest // np.uint32(10000)
        group = rest - higher * np.uint32(10000)  # (faster than %)
        unpadded = np.take(_DIGITS["last"] if g == groups - 1 else _DIGITS["lead"], group)
        if g:  # zero-padded where a higher group follows (uint32 arithmetic wraps: no np.where)
            unpadded += (higher > 0) * (np.take(_DIGITS["full"], group) - unpadded)
        out[:, g] = unpadded
        rest = higher
    text = out.view(np.uint8).reshape(len(v), 4 * groups)
    digits = len(str(top))
    if len(str(bottom)) == digits:
        return text[:, 4 * groups - digits :], False
    return text, True


def _format_float32(values: np.ndarray, precision: int) -> list[np.ndarray]:
    """Return ``"%.<precision>g"`` (precision 1 to 9) of float32 values.

    The result is a list of ``(n,)`` columns of characters.
    """
    with np.errstate(all="ignore"):
        return _float_columns(np.ascontiguousarray(values, dtype=np.float32).ravel(), int(precision))


def _float_columns(v: np.ndarray, p: int) -> list[np.ndarray]:
    n = len(v)
    bits = v.view(np.uint32)
    negative = bits >= np.uint32(1 << 31)
    magnitude = bits & np.uint32(0x7FFFFFFF)
    zero = magnitude == 0
    special = magnitude >= np.uint32(0x7F800000)  # inf, NaN
    plain = zero | special
    a = np.abs(v).astype(np.float64)
    # The decimal exponent x and the p significant digits d (an integer), rounded half to even.
    x = np.floor(np.log10(a)).astype(np.int64) * ~plain  # 0 for 0, inf, NaN
    low, high = np.uint64(10 ** (p - 1)), np.uint64(10**p)
    d, ok = _significand(a, bits, x, p)
    ok &= ~plain
    below = ok & (d < low)
    above = ok & (d > high)
    todo = np.flatnonzero(below | above)
    for _ in range(2):  # log10 can be one off next to powers of ten
        if todo.size == 0:
            break
        x[todo] += above[todo].astype(np.int64) - below[todo].astype(np.int64)
        d[todo], ok[todo] = _significand(a[todo], bits[todo], x[todo], p)
        below[todo] = ok[todo] & (d[todo] < low)
        above[todo] = ok[todo] & (d[todo] > high)
        todo = todo[below[todo] | above[todo]]
    carry = np.flatnonzero(d == high)  # rounded up to 10^p: one more digit before the point
    d[carry] = low
    x[carry] += 1
    fallback = special | ~(zero | (ok & (d >= low) & (d < high)))
    any_fallback = bool(fallback.any())
    if any_fallback:
        d[fallback] = 0
    # The digits as one row of characters per digit.
    full = _DIGITS["full"]
    d32 = d.astype(np.uint32)  # < 10^9
    high4 = d32 // np.uint32(10**4)
    top = high4 // np.uint32(10**4)
    groups = np.empty((3, n), dtype=np.uint32)
    np.take(full, top, out=groups[0])
    np.take(full, high4 - top * np.uint32(10**4), out=groups[1])
    np.take(full, d32 - high4 * np.uint32(10**4), out=groups[2])
    digits = np.ascontiguousarray(groups.view(np.uint8).reshape(3, n, 4).transpose(0, 2, 1).reshape(12, n)[12 - p :])
    # %g: fixed notation for -4 <= x < p, else d.ddde+xx; trailing zeros (and point) dropped.
    # (Characters are made by multiplying flags: much faster than np.where with scalars.)
    fixed = (x >= -4) & (x < p)
    small = fixed & (x < 0)  # 0.000ddd
    scientific = ~fixed & ~fallback
    before = (np.maximum(x + 1, 0) * fixed + ~fixed).astype(np.int8)  # digits before the point
    first, last = int(before.min()), int(before.max())
    columns: list[np.ndarray] = []
    if any_fallback or negative.any():
        columns.append(_char(negative, _MINUS))
    if any_fallback or small.any():
        columns += [_char(small, _ZERO), _char(small, _POINT)]
        columns += [_char(small & (x <= -k), _ZERO) for k in (2, 3, 4)]
    # Right to left: a trailing zero after the point is dropped; the point after digit j is
    # written if a digit after it is.
    trailing = np.ones(n, dtype=bool)
    backwards: list[np.ndarray] = []
    for j in range(p - 1, -1, -1):
        if j < p - 1 and (any_fallback or first <= j + 1 <= last):
            backwards.append(_char((before == j + 1) & ~trailing, _POINT))
        digit = digits[j]
        trailing &= digit == _ZERO
        drop = trailing & (before <= j) if last > j else trailing
        backwards.append(digit * (~drop).view(np.uint8))
    columns += backwards[::-1]
    if any_fallback or scientific.any():
        e = np.abs(x)
        sign = np.where(x < 0, np.uint8(_MINUS), np.uint8(_PLUS))
        columns.append(_char(scientific, _E))
        columns.append(sign * scientific.view(np.uint8))
        columns.append((_ZERO + e // 100 % 10).astype(np.uint8) * (scientific & (e >= 100)).view(np.uint8))
        columns.append((_ZERO + e // 10 % 10).astype(np.uint8) * scientific.view(np.uint8))
        columns.append((_ZERO + e % 10).astype(np.uint8) * scientific.view(np.uint8))
    for i in np.flatnonzero(fallback):  # at least 2 p + 10 columns here
        text = ("%.*g" % (p, float(v[i]))).encode("ascii")  # noqa: UP031 (the % operator's characters)
        for k, column in enumerate(columns):
            column[i] = text[k] if k < len(text) else _BLANK
    return columns


def _char(flags: np.ndarray, char: int) -> np.ndarray:
    """``char`` where ``flags`` (bool) is set, else 0."""
    return flags.view(np.uint8) * np.uint8(char)


def _significand(a: np.ndarray, bits: np.ndarray, x: np.ndarray, p: int) -> tuple[np.ndarray, np.ndarray]:
    """Return ``round(a * 10^(p - 1 - x))``, ties to even, and where it was computed.

    ``a`` are positive float32 values (given as float64 and as their bits); 10^(p - 1 - x) is from 1
    to 5^17 2^17.
    """
    q = p - 1 - x
    # a has 24 significant bits and 10^q = 5^q 2^q with 5^q < 2^29: the product is exact.
    d = np.rint(a * np.take(_POW10, q, mode="clip")).astype(np.uint64)
    ok = (q >= 0) & (q < len(_POW10))
    slow = np.flatnonzero(~ok)
    if slow.size:
        d[slow], ok[slow] = _significand_exact(bits[slow], q[slow])
    return d, ok


def _significand_exact(bits: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return ``round(m 2^e 10^q)``, ties to even, in integers, and where it was computed.

    Here float32 ``bits`` = m 2^e and 0 <= q <= 17.
    """
    biased = ((bits >> np.uint32(23)) & np.uint32(0xFF)).astype(np.int64)
    fraction = (bits & np.uint32(0x7FFFFF)).astype(np.uint64)
    m = np.where(biased > 0, fraction | np.uint64(1 << 23), fraction)
    e = np.where(biased > 0, biased - 150, -149)
    qc = np.clip(q, 0, len(_POW5) - 1)
    n = m * _POW5[qc]
    t = e + qc  # the result is n 2^t
    ok = (q >= 0) & (q < len(_POW5)) & (t <= 30) & (t > -64)
    one = np.uint64(1)
    s = np.clip(-t, 1, 63).astype(np.uint64)
    down = np.right_shift(n, s)
    rest = n & (np.left_shift(one, s) - one)
    half = np.left_shift(one, s - one)
    up = (rest > half) | ((rest == half) & ((down & one) == one))
    return np.where(t >= 0, np.left_shift(n, np.clip(t, 0, 30).astype(np.uint64)), down + up), ok


# --------------------------------------------------------------------------------------------------
# Images
# --------------------------------------------------------------------------------------------------


#: The encodings of a normal map (:func:`save_normal_map`, ``--normal-map``), by name: the sign
#: each camera-frame (OpenCV: x right, y down, z forward) component is multiplied by before
#: encoding. ``"opengl"``: x right, y up, z towards the viewer (the "OpenGL" / "Y+" maps of
#: Blender and Unity); ``"directx"``: x right, y down, z towards the viewer (the "DirectX" / "Y-"
#: maps of Unreal Engine); ``"opencv"``: the camera frame as is (z forward, so a normal facing the
#: camera has ``n_z < 0`` and a blue value below one half). See docs/outputs.md.
NORMAL_MAP_FRAMES: dict[str, tuple[float, float, float]] = {
    "opengl": (1.0, -1.0, -1.0),
    "directx": (1.0, 1.0, -1.0),
    "opencv": (1.0, 1.0, 1.0),
}

#: The default encoding of ``normals.png``: the OpenGL convention, 16 bits per channel.
DEFAULT_NORMAL_MAP = "opengl"
DEFAULT_NORMAL_MAP_BITS = 16


def check_normal_map(frame: str, bits: int = DEFAULT_NORMAL_MAP_BITS) -> tuple[str, int]:
    """Return a normal map's ``(frame, bits)`` checked: a name of :data:`NORMAL_MAP_FRAMES` and 8 or 16.

    Raises
    ------
    InputError
        Naming the value and the choices.
    """
    if not isinstance(frame, str) or frame not in NORMAL_MAP_FRAMES:
        raise InputError(f"normal_map must be one of {', '.join(NORMAL_MAP_FRAMES)}, got {frame!r}")
    if isinstance(bits, bool) or bits not in (8, 16):
        raise InputError(f"normal_map_bits must be 8 or 16, got {bits!r}")
    return frame, int(bits)


def to_normal_frame(normals: np.ndarray, frame: str) -> np.ndarray:
    """Return camera-frame (OpenCV) normals expressed in a normal-map frame (float32, NaN kept).

    Parameters
    ----------
    normals : numpy.ndarray
        ``(..., 3)`` normals in the camera frame (x right, y down, z forward).
    frame : {"opengl", "directx", "opencv"}
        The frame (:data:`NORMAL_MAP_FRAMES`). The map is its own inverse: applying it to
        normals in `frame` gives camera-frame normals back.

    Returns
    -------
    numpy.ndarray
        float32, same shape.
    """
    check_normal_map(frame)
    return np.asarray(normals, dtype=np.float32) * np.array(NORMAL_MAP_FRAMES[frame], dtype=np.float32)


def save_normal_map(
    path: PathLike,
    normals: np.ndarray,
    *,
    mask: np.ndarray | None = None,
    frame: str = DEFAULT_NORMAL_MAP,
    bits: int = DEFAULT_NORMAL_MAP_BITS,
) -> None:
    """Save per-pixel normals as an RGB PNG normal map (16 bits per channel by default).

    Encoding: the camera-frame (OpenCV) normal ``(n_x, n_y, n_z)`` is first expressed in the
    chosen `frame` (:data:`NORMAL_MAP_FRAMES`; ``"opengl"``: ``(n_x, -n_y, -n_z)``); each
    component ``v`` (clipped to [-1, 1]) is stored as ``round((v + 1) / 2 * M)`` in R, G, B, with
    ``M = 65535`` (16 bits) or ``255`` (8 bits). In the OpenGL frame a normal facing the camera,
    ``(0, 0, -1)``, is thus ``(32768, 32768, 65535)`` (8 bits: ``(128, 128, 255)``, the familiar
    light-blue look) and ``(1, 0, 0)`` is ``(65535, 32768, 32768)``. Pixels with a NaN normal or
    outside ``mask`` are ``(0, 0, 0)`` (no unit normal encodes to that). :func:`read_normal_map`
    decodes the file.

    Quantisation moves a decoded normal by at most ``asin(sqrt(3) / M)``: 0.0015 degrees at 16
    bits, 0.39 degrees at 8 bits (means over random normals 0.00066 and 0.17 degrees; see
    docs/outputs.md).

    Parameters
    ----------
    path : str or path-like
        Output file (written as PNG whatever its extension).
    normals : numpy.ndarray
        ``(H, W, 3)`` unit normals, OpenCV frame.
    mask : numpy.ndarray, optional
        ``(H, W)`` bool of the pixels to encode.
    frame : {"opengl", "directx", "opencv"}, default "opengl"
        The normal-map convention.
    bits : {16, 8}, default 16
        Bits per channel.

    Raises
    ------
    InputError
        The shapes are wrong, or `frame` or `bits` is not one of the choices.
    """
    write_png(path, normal_map_pixels(normals, mask=mask, frame=frame, bits=bits))


def normal_map_pixels(
    normals: np.ndarray, *, mask: np.ndarray | None = None, frame: str = DEFAULT_NORMAL_MAP, bits: int = 8
) -> np.ndarray:
    """Return the RGB pixels of the normal map of :func:`save_normal_map` (same encoding).

    Parameters
    ----------
    normals : numpy.ndarray
        ``(H, W, 3)`` unit normals, OpenCV frame.
    mask : numpy.ndarray, optional
        ``(H, W)`` bool of the pixels to encode; the others, and NaN normals, are black.
    frame : {"opengl", "directx", "opencv"}, default "opengl"
        The normal-map convention (:data:`NORMAL_MAP_FRAMES`).
    bits : {8, 16}, default 8
        Bits per channel (8 here, for pictures; :func:`save_normal_map` writes 16 by default).

    Returns
    -------
    numpy.ndarray
        ``(H, W, 3)`` uint8 (8 bits) or uint16 (16 bits).

    Raises
    ------
    InputError
        The shapes are wrong, or `frame` or `bits` is not one of the choices.
    """
    frame, bits = check_normal_map(frame, bits)
    normals = np.asarray(normals)
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise InputError(f"normals must have shape (H, W, 3), got {normals.shape}")
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        _require_shape("mask", mask, normals.shape[:2])
    # One parallel pass of the Rust extension: per pixel, round(((clip(n f, -1, 1) + 1) / 2) top)
    # with numpy's float64 arithmetic and rounding (np.rint), black where masked out or not finite.
    return _core.normal_map_pixels(
        np.ascontiguousarray(normals, dtype=np.float64),
        None if mask is None else np.ascontiguousarray(mask),
        NORMAL_MAP_FRAMES[frame],
        bits,
    )


def decode_normal_map(pixels: np.ndarray, frame: str) -> np.ndarray:
    """Decode the pixels of a normal map into camera-frame unit normals (the inverse of :func:`normal_map_pixels`).

    Parameters
    ----------
    pixels : numpy.ndarray
        ``(H, W, 3)`` uint8 (8 bits) or uint16 (16 bits).
    frame : {"opengl", "directx", "opencv"}
        The convention the map was written in.

    Returns
    -------
    numpy.ndarray
        ``(H, W, 3)`` float64 unit normals in the camera frame (OpenCV: x right, y down, z
        forward); NaN where the pixel is ``(0, 0, 0)`` (no normal).

    Raises
    ------
    InputError
        The pixels are not an RGB image of 8 or 16 bits, or `frame` is unknown.
    """
    check_normal_map(frame)
    pixels = np.asarray(pixels)
    if pixels.ndim != 3 or pixels.shape[2] != 3 or pixels.dtype not in (np.uint8, np.uint16):
        raise InputError(
            f"a normal map must be an (H, W, 3) RGB image of 8 or 16 bits, got shape {pixels.shape} of {pixels.dtype}"
        )
    top = 255.0 if pixels.dtype == np.uint8 else 65535.0
    n = pixels.astype(np.float64) * (2.0 / top) - 1.0
    n *= np.array(NORMAL_MAP_FRAMES[frame])
    with np.errstate(invalid="ignore", divide="ignore"):
        n /= np.linalg.norm(n, axis=2, keepdims=True)
    n[~pixels.any(axis=2)] = np.nan
    return n


def read_normal_map(path: PathLike, frame: str) -> np.ndarray:
    """Read a normal map (:func:`save_normal_map`, ``normals.png``) back into camera-frame normals.

    An 8- or 16-bit RGB PNG (read keeping all 16 bits, :func:`nplps.io.read_image`); the frame is
    not in the file: it is ``summary.json``'s ``"normal_map"`` ``"frame"`` for a result directory.

    Parameters
    ----------
    path : str or path-like
        The PNG file.
    frame : {"opengl", "directx", "opencv"}
        The convention the map was written in (:data:`NORMAL_MAP_FRAMES`).

    Returns
    -------
    numpy.ndarray
        ``(H, W, 3)`` float64 unit normals in the camera frame (OpenCV), NaN where the pixel is
        black (no normal). Within quantisation of the normals written: at most 0.0015 degrees
        apart at 16 bits, 0.39 degrees at 8 bits.

    Raises
    ------
    InputError
        The file cannot be read or is not an RGB image of 8 or 16 bits, or `frame` is unknown.
    """
    from .io import read_image

    check_normal_map(frame)
    pixels = np.asarray(read_image(path))
    try:
        return decode_normal_map(pixels, frame)
    except InputError as e:
        raise InputError(f"'{os.fspath(path)}': {e}") from None


def save_albedo(path: PathLike, albedo: np.ndarray) -> float:
    """Save a per-pixel albedo map as a 16-bit grey PNG and return the scale factor.

    The pixel value is ``round(clip(albedo * scale, 0, 65535))`` where ``scale`` maps the 99.9th
    percentile of the finite albedo values to 65535 (``scale = 1`` if there is no positive finite
    value); NaN is written as 0. Divide the pixel values by the returned ``scale`` to recover the
    albedo.

    Parameters
    ----------
    path : str or path-like
        Output file (written as PNG whatever its extension).
    albedo : numpy.ndarray
        ``(H, W)`` grey or ``(H, W, 3)`` RGB albedo (16-bit RGB PNG, one scale for all channels).

    Returns
    -------
    float
        The scale: divide the pixel values by it to recover the albedo.

    Raises
    ------
    InputError
        `albedo` has the wrong shape.
    """
    albedo = np.asarray(albedo)
    if not (albedo.ndim == 2 or (albedo.ndim == 3 and albedo.shape[2] == 3)):
        raise InputError(f"albedo must have shape (H, W) or (H, W, 3), got {albedo.shape}")
    pixels, scale = _albedo_pixels(albedo)
    write_png16(path, pixels)
    return scale


def _albedo_pixels(albedo: np.ndarray) -> tuple[np.ndarray, float]:
    """Return the uint16 pixels of :func:`save_albedo` and their scale."""
    return _quantize(np.asarray(albedo), _ALBEDO_PERCENTILE, 65535, np.uint16)


def save_grey_png(path: PathLike, image: np.ndarray) -> None:
    """Write an (H, W) image with values in [0, 1] as an 8-bit grey PNG (NaN -> 0)."""
    write_png8(path, _grey_pixels(image))


def _grey_pixels(image: np.ndarray) -> np.ndarray:
    """Return the uint8 pixels of :func:`save_grey_png`: ``round(clip(image, 0, 1) * 255)``, NaN -> 0."""
    # One parallel pass of the Rust extension (no float64 copy; numpy's clip, product and rint).
    image = np.ascontiguousarray(image, dtype=np.float64)
    return _core.grey_pixels(image.reshape(1, -1)).reshape(image.shape)


#: How the PNG files are compressed (:func:`write_pngs`): fdeflate's fast DEFLATE, made for PNG
#: rows. On the 12 MP benchmark's 16-bit normal map: 0.25 s and 28 MB, against 5.1 s and 12 MB
#: at zlib's default level ("balanced") and 2.9 s and 62 MB with pypng before (docs/outputs.md).
PNG_COMPRESSION = "fast"
#: The PNG row filter (:func:`write_pngs`): per row, the one whose output is smallest.
PNG_FILTER = "adaptive"


def write_pngs(images: Sequence[tuple[PathLike, np.ndarray]]) -> None:
    """Write several integer images as PNG files, encoded in parallel by the Rust extension.

    Each image is grey ``(H, W)`` or RGB ``(H, W, 3)``, written with 8 bits per sample for uint8
    and 16 bits (big-endian, as PNG stores them) for any other integer type (converted to
    uint16), as a non-interlaced PNG that any reader reads (compression :data:`PNG_COMPRESSION`,
    filter :data:`PNG_FILTER`). The files are encoded on the extension's threads with the GIL
    released, each under a temporary name renamed into place when all are complete
    (:mod:`nplps._atomic`). The file is PNG whatever the extension of its path.

    Raises
    ------
    InputError
        An array is not an ``(H, W)`` or ``(H, W, 3)`` image with at least one pixel.
    OSError
        A file could not be written (``filename`` is its path).
    """
    _write_pngs(images)


def _write_pngs(images: Sequence[tuple[PathLike, np.ndarray]], before_rename: Callable[[], None] | None = None) -> None:
    """:func:`write_pngs`, with ``before_rename()`` run (it may raise) once encoded, before the renames."""
    arrays = []
    for path, pixels in images:
        pixels = np.asarray(pixels)
        dtype = np.uint8 if pixels.dtype == np.uint8 else np.uint16
        if not (pixels.ndim == 2 or (pixels.ndim == 3 and pixels.shape[2] == 3)) or pixels.size == 0:
            raise InputError(f"cannot write image {os.fspath(path)!r}: shape {pixels.shape} is not (H, W) or (H, W, 3)")
        arrays.append((path, np.ascontiguousarray(pixels, dtype=dtype)))
    with ExitStack() as stack:
        jobs = [(stack.enter_context(atomic_path(path)), pixels) for path, pixels in arrays]
        try:
            _core.write_pngs(jobs, PNG_COMPRESSION, PNG_FILTER)
        except OSError as e:  # named by its temporary file: name the final one
            finals = {temporary: path for (temporary, _), (path, _) in zip(jobs, arrays, strict=True)}
            final = finals.get(e.filename, arrays[0][0])
            raise write_error(_os_error(e, final), final) from None
        if before_rename is not None:
            before_rename()


def _os_error(error: OSError, path: PathLike) -> OSError:
    """Return an OSError of the extension's writers naming ``path``, in the system's words for its errno."""
    reason = os.strerror(error.errno) if error.errno else (error.strerror or str(error))
    return OSError(error.errno, reason, os.fspath(path))


def write_png(path: PathLike, pixels: np.ndarray) -> None:
    """Write an integer image as a PNG: 8-bit for uint8, else 16-bit (:func:`write_pngs`).

    Grey ``(H, W)`` or RGB ``(H, W, 3)``.
    """
    write_pngs([(path, pixels)])


def write_png8(path: PathLike, pixels: np.ndarray) -> None:
    """Write a uint8 ``(H, W)`` grey or ``(H, W, 3)`` RGB image as an 8-bit PNG (:func:`write_pngs`).

    The file is PNG whatever the extension of `path`.
    """
    write_pngs([(path, np.asarray(pixels, dtype=np.uint8))])


def write_png16(path: PathLike, pixels: np.ndarray) -> None:
    """Write a uint16 ``(H, W)`` grey or ``(H, W, 3)`` RGB image as a 16-bit PNG (:func:`write_pngs`)."""
    write_pngs([(path, np.asarray(pixels, dtype=np.uint16))])


def save_depth_npy(path: PathLike, depth: np.ndarray) -> None:
    """Save a depth map as float64 ``.npy`` (values as is, NaN kept) exactly at ``path``."""
    save_npy(path, _depth_array(depth, np.float64))


def save_npy(path: PathLike, array: np.ndarray) -> None:
    """Save an array as ``.npy`` exactly at `path` (no ``.npy`` appended)."""
    with atomic_write(path) as file:
        np.save(file, np.asarray(array))


def save_depth_tiff(path: PathLike, depth: np.ndarray) -> None:
    """Save a depth map as a float32 TIFF (NaN kept)."""
    depth = _depth_array(depth, np.float32)
    with atomic_path(path) as temporary:
        tifffile.imwrite(temporary, depth)


#: The optional dependency of the EXR files, as the message that asks for it names it.
EXR_EXTRA = 'pip install "nplps[exr]" (or "OpenEXR>=3.3")'


def exr_available() -> bool:
    """Tell whether EXR files can be written: the OpenEXR Python binding (3.3 or later) is installed."""
    try:
        import OpenEXR
    except ImportError:
        return False
    return hasattr(OpenEXR, "File")


def _openexr(path: PathLike | None = None) -> Any:
    """Import the OpenEXR binding, or raise InputError naming the extra that installs it."""
    try:
        import OpenEXR
    except ImportError:
        OpenEXR = None
    if OpenEXR is None or not hasattr(OpenEXR, "File"):  # OpenEXR.File arrived in 3.3
        what = f"'{os.fspath(path)}'" if path is not None else "EXR files"
        raise InputError(f"writing or reading {what} needs the OpenEXR Python binding 3.3 or later: {EXR_EXTRA}")
    return OpenEXR


def write_exr(
    path: PathLike, channels: Mapping[str, np.ndarray], *, attributes: Mapping[str, str] | None = None
) -> None:
    """Write float32 channels as a single-part scan-line EXR file (ZIP compression, lossless).

    Needs the optional OpenEXR binding (``pip install "nplps[exr]"``).

    Parameters
    ----------
    path : str or path-like
        Output file (written under a temporary name, renamed when complete).
    channels : mapping of str to numpy.ndarray
        Channel name (``"R"``, ``"G"``, ``"B"``, ``"Y"``, ``"Z"``, ...) to an ``(H, W)`` array, all
        the same shape; stored as 32-bit float (NaN kept).
    attributes : mapping of str to str, optional
        Extra string attributes of the header (e.g. ``{"nplps_normal_frame": "opengl"}``).

    Raises
    ------
    InputError
        OpenEXR is not installed (the message names the extra), or the shapes differ.
    """
    exr = _openexr(path)
    arrays = {name: np.ascontiguousarray(a, dtype=np.float32) for name, a in channels.items()}
    shapes = {a.shape for a in arrays.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise InputError(f"EXR channels must be (H, W) arrays of one shape, got {sorted(shapes)}")
    header: dict[str, Any] = {"compression": exr.ZIP_COMPRESSION, "type": exr.scanlineimage}
    header.update({str(k): str(v) for k, v in (attributes or {}).items()})
    with atomic_path(path) as temporary, exr.File(header, arrays) as file:
        file.write(temporary)


def read_exr(path: PathLike) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read an EXR file's channels (each its own ``(H, W)`` array) and header.

    Needs the optional OpenEXR binding (``pip install "nplps[exr]"``).

    Returns
    -------
    channels : dict of str to numpy.ndarray
        By channel name, in the file's pixel type (float32 for the files nplps writes).
    header : dict
        The header's attributes (``nplps_normal_frame`` for ``normals.exr``).

    Raises
    ------
    InputError
        OpenEXR is not installed, or the file cannot be read as EXR.
    """
    exr = _openexr(path)
    if not os.path.isfile(path):
        raise InputError(f"EXR file '{os.fspath(path)}' does not exist or is not a file")
    try:
        with exr.File(os.fspath(path), separate_channels=True) as file:
            channels = {name: np.array(c.pixels) for name, c in file.channels().items()}
            header = dict(file.header())
    except Exception as e:  # the binding raises RuntimeError and others for a file it cannot read
        raise InputError(f"cannot read '{os.fspath(path)}' as an EXR file: {e}") from None
    return channels, header


def save_depth_exr(path: PathLike, depth: np.ndarray) -> None:
    """Save a depth map as a one-channel (``"Z"``) float32 EXR file (NaN kept), as :func:`save_depth_tiff`."""
    write_exr(path, {"Z": _depth_array(depth, np.float32)})


def save_normals_exr(path: PathLike, normals: np.ndarray, *, frame: str = DEFAULT_NORMAL_MAP) -> None:
    """Save per-pixel normals as a float32 RGB EXR file in a normal-map frame (NaN kept).

    ``R, G, B`` hold the normal's ``x, y, z`` in `frame` (:func:`to_normal_frame`; not encoded
    as ``(n + 1) / 2``); the frame is also the header's ``nplps_normal_frame`` attribute.

    Raises
    ------
    InputError
        `normals` has the wrong shape, `frame` is unknown, or OpenEXR is missing.
    """
    n = to_normal_frame(normals, frame)
    if n.ndim != 3 or n.shape[2] != 3:
        raise InputError(f"normals must have shape (H, W, 3), got {n.shape}")
    write_exr(path, {"R": n[..., 0], "G": n[..., 1], "B": n[..., 2]}, attributes={"nplps_normal_frame": frame})


def save_albedo_exr(path: PathLike, albedo: np.ndarray) -> None:
    """Save an albedo map as float32 EXR, unscaled (NaN kept): ``"Y"`` for grey, ``R, G, B`` for colour.

    Raises
    ------
    InputError
        `albedo` has the wrong shape, or OpenEXR is missing.
    """
    a = np.asarray(albedo, dtype=np.float32)
    if a.ndim == 2:
        write_exr(path, {"Y": a})
    elif a.ndim == 3 and a.shape[2] == 3:
        write_exr(path, {"R": a[..., 0], "G": a[..., 1], "B": a[..., 2]})
    else:
        raise InputError(f"albedo must have shape (H, W) or (H, W, 3), got {a.shape}")


def save_map_tiff(path: PathLike, values: np.ndarray) -> None:
    """Save a per-pixel (H, W) map as a float32 TIFF (NaN kept), e.g. ``normal_sigma.tiff``."""
    values = np.asarray(values, dtype=np.float32)
    if values.ndim != 2:
        raise InputError(f"a map must be a 2-D array, got shape {values.shape}")
    with atomic_path(path) as temporary:
        tifffile.imwrite(temporary, values)


def _depth_array(depth: np.ndarray, dtype: type) -> np.ndarray:
    """Convert ``depth`` to a 2-D array of ``dtype``; raise InputError otherwise."""
    depth = np.asarray(depth, dtype=dtype)
    if depth.ndim != 2:
        raise InputError(f"depth must be a 2-D array, got shape {depth.shape}")
    return depth


# --------------------------------------------------------------------------------------------------
# The result directory (Reconstruction.save) and the small files it writes for the report
# --------------------------------------------------------------------------------------------------


_HISTORY_HEADER = "level,iteration,depth_change,rms_residual,elapsed,inner_iterations,light_change"


def history_csv(history: Sequence[Any]) -> str:
    """Return the convergence history as CSV text (``history.csv``).

    Parameters
    ----------
    history : sequence of Iteration
        ``Reconstruction.history``.

    Returns
    -------
    str
        A header ``level,iteration,depth_change,rms_residual,elapsed,inner_iterations,light_change``
        and one row per iteration in the order run, plain numbers (``numpy.loadtxt(path,
        delimiter=",", skiprows=1, ndmin=2)`` reads it).
    """
    rows = [
        f"{h.level},{h.iteration},{float(h.depth_change)!r},{float(h.rms_residual)!r},{float(h.elapsed)!r},"
        f"{h.inner_iterations},{float(h.light_change)!r}"
        for h in history
    ]
    return _HISTORY_HEADER + "\n" + "".join(r + "\n" for r in rows)


def contact_sheet(images: np.ndarray, *, max_side: int | None = None, columns: int | None = None) -> np.ndarray:
    """Return a contact sheet of an image stack: small copies in a grid, row by row in light order.

    Each image is shrunk by block means; all share one brightness scale (the 99.5th percentile
    of the stack maps to white) and a display gamma of 1/2.2, so their relative brightness shows.

    Parameters
    ----------
    images : numpy.ndarray
        (k, H, W) or (k, H, W, 3) images.
    max_side : int, optional
        Longest side of each copy (default 128 for up to 16 images, else 72).
    columns : int, optional
        Copies per row (default about the square root of k, at most 12).

    Returns
    -------
    numpy.ndarray
        (rows, cols, 3) uint8 RGB, 2-pixel white gaps.

    Raises
    ------
    InputError
        `images` is not a stack of images.
    """
    stack = np.asarray(images)
    if stack.ndim not in (3, 4) or (stack.ndim == 4 and stack.shape[3] != 3) or len(stack) == 0:
        raise InputError(f"images must be a (k, H, W) or (k, H, W, 3) stack, got shape {stack.shape}")
    k = len(stack)
    side = max_side or (128 if k <= 16 else 72)
    # Images whose values float32 holds exactly (integers of up to 16 bits, float32) are shrunk as
    # they are, a band at a time, without a full-size float32 copy each: the same values.
    exact = stack.dtype == np.float32 or (stack.dtype.kind in "biu" and stack.dtype.itemsize <= 2)
    small = [views.downsample(im if exact else np.asarray(im, dtype=np.float32), side) for im in stack]
    sample = np.concatenate([np.asarray(s, dtype=np.float64).ravel()[::7] for s in small])
    finite = sample[np.isfinite(sample)]
    top = float(np.percentile(finite, 99.5)) if finite.size else 1.0
    top = top if top > 0 else 1.0
    cols = columns or min(12, int(np.ceil(np.sqrt(k))))
    rows = int(np.ceil(k / cols))
    th, tw = small[0].shape[:2]
    gap = 2
    sheet = np.full((rows * (th + gap) - gap, cols * (tw + gap) - gap, 3), 255, dtype=np.uint8)
    for i, s in enumerate(small):
        v = np.clip(np.nan_to_num(np.asarray(s, dtype=np.float64) / top), 0.0, 1.0) ** (1 / 2.2)
        rgb = np.rint(v * 255).astype(np.uint8)
        rgb = rgb if rgb.ndim == 3 else np.repeat(rgb[..., None], 3, axis=2)
        r, c = divmod(i, cols)
        sheet[r * (th + gap) : r * (th + gap) + th, c * (tw + gap) : c * (tw + gap) + tw] = rgb
    return sheet


@dataclass(frozen=True)
class ContactSheet:
    """A contact sheet of a result's images (:func:`contact_sheet`), made before the images are freed.

    ``Reconstruction.save(inputs=ContactSheet.of(images))`` writes ``inputs.png`` as
    ``inputs=images`` does, without holding the images through the save: a caller can let them
    go first (``nplps reconstruct`` does; the stack is the largest input of the export, 3.3 GB
    at 100 MP x 16 lights in 16 bits).
    """

    #: (rows, cols, 3) uint8 RGB.
    pixels: np.ndarray

    @classmethod
    def of(cls, images: np.ndarray) -> ContactSheet:
        """Return the contact sheet of a (k, H, W) or (k, H, W, 3) image stack."""
        return cls(contact_sheet(images))


def held_out_record(near: Sequence[HeldOutScores], parallel: Sequence[HeldOutScores] | None = None) -> dict[str, Any]:
    """Return the held-out evaluation as the JSON-ready dict of ``held_out.json``.

    Parameters
    ----------
    near : sequence of HeldOut
        :func:`nplps.evaluation.held_out` of the near-light method.
    parallel : sequence of HeldOut, optional
        The same lights left out with ``method="parallel"``, for the comparison.

    Returns
    -------
    dict
        ``{"lights": [...], "near": [[relative_error, shape_error, gain], ...], "parallel": [...]
        or None, "reading": str}``; the reading is :func:`nplps.evaluation.reading` of the means.
    """

    def rows(items: Sequence[HeldOutScores]) -> list[list[float | None]]:
        return [[_num(h.relative_error), _num(h.shape_error), _num(h.gain)] for h in items]

    if parallel is not None:
        means = [
            tuple(_finite_mean([getattr(h, a) for h in m]) for a in ("relative_error", "shape_error"))
            for m in (near, parallel)
        ]
        text = reading(means[0], means[1])  # type: ignore[arg-type]
    else:
        text = "reading: no parallel-light baseline was evaluated, so there is nothing to compare with."
    return {
        "lights": [int(h.light) for h in near],
        "near": rows(near),
        "parallel": None if parallel is None else rows(parallel),
        "reading": text,
    }


def _num(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def _finite_mean(values: Sequence[float]) -> float:
    """Return the mean of the finite values (a failed held-out run's NaN left out); NaN when there are none."""
    finite = [float(v) for v in values if np.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


def write_result(
    result: Result,
    out: ResultDirectory,
    *,
    stem: str,
    opengl: bool,
    formats: Sequence[str],
    inputs: np.ndarray | ContactSheet | None,
    options: dict[str, Any] | None,
    held_out: tuple[Sequence[HeldOutScores], Sequence[HeldOutScores] | None] | None,
    normal_map: str = DEFAULT_NORMAL_MAP,
    normal_map_bits: int = DEFAULT_NORMAL_MAP_BITS,
    units: str | None = None,
) -> dict[str, Path]:
    """Write a result's files into a result directory (the body of :meth:`nplps.Reconstruction.save`).

    `formats` are checked names (:func:`check_formats`), `stem` a checked file name; the other
    arguments are :meth:`~nplps.Reconstruction.save`'s. Returns the paths written by kind; the
    report (written from these files) is the caller's.
    """
    facets = int(np.count_nonzero(result.mask))
    names = {"ply": f"{stem}.ply"}
    if "obj" in formats or facets <= OBJ_MAX_FACETS:
        names["obj"] = f"{stem}.obj"
    names.update(
        {
            "normal_map": "normals.png",
            "shaded": "shaded.png",
            "albedo": "albedo.png",
            "depth_npy": "depth.npy",
            "depth_tiff": "depth.tiff",
            "normals_npy": "normals.npy",
            "residual_npy": "residual.npy",
        }
    )
    names.update({name: FORMATS[name].file.format(stem=stem) for name in formats if name not in ("exr", "obj")})
    if "exr" in formats:
        names.update(EXR_FILES)
    if result.specular is not None:  # the glossy model's specular albedo (none for Lambertian results)
        names.update(specular_npy="specular.npy", specular="specular.png")
    if result.shadow_bits is not None:  # shadows=True: the cast shadows the fits left out
        names.update(shadows_npy="shadows.npy", shadows="shadows.png")
    if result.normal_sigma is not None and result.held_out_error is not None:  # near-light runs: the trust maps
        names.update(normal_sigma="normal_sigma.tiff", held_out_error="held_out_error.tiff")
    if result.distance is not None:
        names.update(distance_curve="distance_curve.csv", distance_plot="distance_curve.svg")
    if result.refinement is not None:
        names["rig_refined"] = "rig_refined.json"
    names.update(mask="mask.png", lights_used="lights_used.npy", history="history.csv", rig="rig.json")
    if inputs is not None:
        names["inputs"] = "inputs.png"
    if held_out is not None:
        names["held_out"] = "held_out.json"
    names["summary"] = "summary.json"
    paths = {key: out.file(name) for key, name in names.items()}
    summary = result.summary()
    if "obj" not in paths:
        summary["skipped"] = {f"{stem}.obj": obj_skipped_note(facets)}
    _ = result.normals  # computed (and cached) once, before two threads read it
    # The PNG images are made and encoded on a thread of their own (the encoder runs in parallel
    # with the GIL released) while the meshes and the other files are written; they are renamed
    # into place only after the meshes, so a mesh that fails leaves no other new file.
    meshes_written = threading.Event()
    state = {"meshes": False}

    def after_meshes(wait: bool = True) -> None:  # raises _Abandoned once the meshes failed
        if wait:
            meshes_written.wait()
        if meshes_written.is_set() and not state["meshes"]:
            raise _Abandoned

    with ThreadPoolExecutor(1) as pool:
        encoded = pool.submit(_write_result_pngs, result, paths, normal_map, normal_map_bits, inputs, after_meshes)
        try:
            # One set of vertex arrays and one mesh for both files and the extra mesh formats.
            mesh_formats = {name: paths[name] for name in formats if FORMATS[name].mesh is not None and name != "obj"}
            if "obj" in paths or mesh_formats:
                _write_meshes(
                    paths["ply"],
                    paths.get("obj"),
                    result.vertices,
                    result.mask,
                    result.vertex_normals(),
                    result.vertex_albedo(),
                    opengl,
                    mesh_formats,
                )
            else:  # streamed: vertex normals and colours made as the records are written
                _stream_ply(
                    paths["ply"],
                    result.depth,
                    result.mask,
                    result.normals,
                    result.albedo,
                    opengl,
                    per_pixel=True,
                    camera=result.rig.camera,
                )
            state["meshes"] = True
            meshes_written.set()
            # The manifest's hashes are computed on a thread of their own as the files are done.
            out.finished(p for k, p in paths.items() if k in ("ply", "obj") or k in mesh_formats)
            # Each file's hash starts as soon as it is written (the hashing thread keeps up with
            # the writes instead of taking them all after the last one).
            _write_other_files(result, paths, formats, normal_map, lambda key: out.finished([paths[key]]))
        finally:
            meshes_written.set()
            wait([encoded])  # never leave with a file still being written
        summary.update(encoded.result())
        out.finished(p for k, p in paths.items() if k not in ("held_out", "summary"))  # the files written by now
    # How normals.png (and normals.exr) is encoded: read_normal_map(path, frame) decodes it.
    summary["normal_map"] = {"file": names["normal_map"], "frame": normal_map, "bits": normal_map_bits}
    summary["units"] = units
    if held_out is not None:
        record = held_out_record(held_out[0], held_out[1])
        write_text(paths["held_out"], json.dumps(record, indent=2) + "\n")
    if options is not None:
        summary["options"] = jsonable(options)
    write_text(paths["summary"], json.dumps(summary, indent=2) + "\n")
    return paths


def _write_other_files(
    result: Result,
    paths: dict[str, Path],
    formats: Sequence[str],
    normal_map: str,
    written: Callable[[str], None] = lambda key: None,
) -> None:
    """Write the result's files other than the meshes, the PNG images and the summary (:func:`write_result`).

    ``written(key)`` is called after each large file (by its key in `paths`) is in place.
    """
    for name in formats:
        if FORMATS[name].mesh is None and name != "exr":
            FORMATS[name].write(paths[name], result.normals)
    if "exr" in formats:
        save_depth_exr(paths["depth_exr"], result.depth)
        save_normals_exr(paths["normals_exr"], result.normals, frame=normal_map)
        save_albedo_exr(paths["albedo_exr"], result.albedo)
    save_depth_npy(paths["depth_npy"], result.depth)
    written("depth_npy")
    save_depth_tiff(paths["depth_tiff"], result.depth)
    written("depth_tiff")
    save_npy(paths["normals_npy"], result.normals)
    written("normals_npy")
    save_npy(paths["residual_npy"], result.residual)
    written("residual_npy")
    if result.specular is not None:
        save_npy(paths["specular_npy"], np.asarray(result.specular, dtype=np.float64))
        written("specular_npy")
    if result.shadow_bits is not None:
        save_npy(paths["shadows_npy"], np.asarray(result.shadow_bits, dtype=np.uint64))
        written("shadows_npy")
    if result.normal_sigma is not None and result.held_out_error is not None:
        save_map_tiff(paths["normal_sigma"], result.normal_sigma)
        written("normal_sigma")
        save_map_tiff(paths["held_out_error"], result.held_out_error)
        written("held_out_error")
    if result.distance is not None:
        result.distance.save_curve(paths["distance_curve"])
        plots.residual_curve_svg(result.distance.curve, list(result.distance.distance), paths["distance_plot"])
    if result.refinement is not None:
        result.rig.with_grid(result.shape[1], result.shape[0]).save(paths["rig_refined"])
    # Clipped straight into the uint16 array (the same values as clipping, then converting): one
    # 2-byte copy instead of an 8-byte temporary and then the 2-byte copy.
    used = np.asarray(result.lights_used)
    save_npy(paths["lights_used"], np.minimum(used, 65535, out=np.empty(used.shape, np.uint16), casting="unsafe"))
    written("lights_used")
    write_text(paths["history"], history_csv(result.history))
    # The rig records the image size it belongs to (and its binning): reused on images of
    # another size it is refused with both sizes named (see nplps.rig.RigGrid).
    result.rig.with_grid(result.shape[1], result.shape[0]).save(paths["rig"])


class _Abandoned(Exception):
    """The PNG files of a result are not renamed into place: writing the meshes failed."""


def _write_result_pngs(
    result: Result,
    paths: dict[str, Path],
    normal_map: str,
    normal_map_bits: int,
    inputs: np.ndarray | ContactSheet | None,
    after_meshes: Callable[..., None],
) -> dict[str, float]:
    """Make and write a result's PNG images (:func:`write_result`); return the summary's PNG scales.

    ``after_meshes()`` waits for the meshes and raises if they failed; ``after_meshes(False)``
    only raises if they already failed (checked before the encoding: no work for nothing).
    """
    scales = {}
    normals = normal_map_pixels(result.normals, mask=result.mask, frame=normal_map, bits=normal_map_bits)
    pngs = [(paths["normal_map"], normals), (paths["shaded"], _grey_pixels(result.shaded()))]
    albedo_pixels, scales["albedo_png_scale"] = _albedo_pixels(result.albedo)
    pngs.append((paths["albedo"], albedo_pixels))
    if result.specular is not None:
        specular_pixels, scales["specular_png_scale"] = _albedo_pixels(result.specular)
        pngs.append((paths["specular"], specular_pixels))
    if result.shadow_bits is not None:
        shadowed = result.shadows
        assert shadowed is not None
        pngs.append((paths["shadows"], _grey_pixels(np.where(result.mask, shadowed.mean(axis=0), 0.0))))
    # _grey_pixels of the mask as 0.0 and 1.0, without the float64 copy: 255 inside, 0 outside.
    pngs.append((paths["mask"], np.where(result.mask, np.uint8(255), np.uint8(0))))
    if inputs is not None:
        sheet = inputs.pixels if isinstance(inputs, ContactSheet) else contact_sheet(inputs)
        pngs.append((paths["inputs"], np.asarray(sheet, dtype=np.uint8)))
    after_meshes(False)
    _write_pngs(pngs, after_meshes)
    return scales
