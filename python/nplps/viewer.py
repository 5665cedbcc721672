"""A 3-D viewer of a reconstructed mesh: one self-contained, offline HTML page.

:func:`write_viewer` writes a page that shows a vertex-grid mesh (the (H+1, W+1, 3) vertices and
the (H, W) mask of a result) with its own small WebGL code: no library, no network access, the
mesh embedded in the page as base64 little-endian arrays (float32 positions and normals, uint8
colours, uint32 triangle indices). The page can be opened from disk in any browser with WebGL
and sent around as one file.

The page: a canvas filling the window; drag to rotate about the object, wheel or pinch to zoom,
right-drag or shift-drag to pan, alt-drag or the two sliders to move the light (it moves with
the eye: by default 20 degrees left of and 25 degrees above the viewing direction, plus a weak
light from the eye), albedo / shaded / normals colouring (keys 1, 2, 3; normals in the colours of
``normals.png``: its convention, ``summary.json``'s ``"normal_map"``, as 8-bit), reset (key R), a
one-line help, the size and extent of the mesh, and a scale bar: a round length (1, 2 or 5 times
a power of ten of the rig's unit, "rig units" unless known; 40 to 100 screen pixels) as long on
the screen as that length at the centre of rotation (the object's centre until panned),
recomputed as the view zooms. The object is shown upright as the camera saw it: the camera
frame (x right, y down, z forward) is drawn with y up on the screen, and azimuth = elevation =
0 is the camera's own viewpoint. The initial view is oblique (azimuth 35, elevation 25
degrees); a URL hash sets another one, e.g.
``viewer.html#azimuth=-40&elevation=10&zoom=1.5&mode=normals&light_azimuth=30&light_elevation=20``
(``ui=0`` hides the panel and the help line, for pictures). The page sets the ``data-status`` attribute of its
``<html>`` element to ``"ready"`` after the first frame and to ``"error: ..."`` on an error
(which it also shows), so that a headless browser can tell (``--dump-dom``).

Large meshes are decimated on a regular grid: every ``stride``-th vertex row and column (and the
last ones), the smallest stride that leaves at most `max_triangles` triangles; the page says so.
A coarse facet is kept where at least half of the pixels it covers are in the mask. The vertex
normals of a decimated mesh are computed by the page from the triangles it draws.

:func:`write_result_viewer` writes the page of a result directory (what ``nplps reconstruct``
and :meth:`nplps.Reconstruction.save` write: ``mesh.ply`` and ``depth.npy`` are read);
``nplps view RESULT_DIR`` calls it. :meth:`nplps.Reconstruction.save_viewer` writes the page of
a result in memory. :func:`read_viewer` decodes the mesh of a page back into arrays.
"""

from __future__ import annotations

import base64
import html
import json
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from . import _results, export
from ._atomic import write_text
from ._outdir import add_to_manifest
from .errors import InputError

__all__ = [
    "DEFAULT_MAX_TRIANGLES",
    "VIEWER_FILE",
    "ViewerInfo",
    "read_viewer",
    "write_result_viewer",
    "write_viewer",
]

DEFAULT_MAX_TRIANGLES = 2_000_000
"""The default largest number of triangles a page holds (about 50 MB of HTML)."""

VIEWER_FILE = "viewer.html"
"""The file name :func:`write_result_viewer` writes into a result directory by default."""

_DATA_ID = "nplps-mesh"
_DATA_RE = re.compile(r'<script id="nplps-mesh" type="application/json">(.*?)</script>', re.S)
_OPENGL_FLIP = np.array([1.0, -1.0, -1.0], dtype=np.float32)


@dataclass(frozen=True)
class ViewerInfo:
    """What :func:`write_viewer` wrote.

    Attributes
    ----------
    path : pathlib.Path
        The page.
    triangles : int
        Triangles in the page.
    full_triangles : int
        Triangles of the mesh before decimation.
    stride : int
        The decimation stride (1: not decimated).
    size_bytes : int
        Size of the page in bytes.
    """

    path: Path
    triangles: int
    full_triangles: int
    stride: int
    size_bytes: int


def write_viewer(
    path: str | os.PathLike[str],
    vertices: np.ndarray,
    mask: np.ndarray,
    *,
    normals: np.ndarray | None = None,
    albedo: np.ndarray | None = None,
    title: str = "nplps mesh",
    units: str | None = None,
    max_triangles: int = DEFAULT_MAX_TRIANGLES,
    normal_map: str = "opengl",
) -> ViewerInfo:
    """Write a self-contained HTML page that shows a vertex-grid mesh in 3-D (WebGL, offline).

    Parameters
    ----------
    path : str or path-like
        The page to write (replaced if it exists; written under a temporary name first).
    vertices : numpy.ndarray
        ``(H + 1, W + 1, 3)`` vertex positions in the camera frame (x right, y down, z forward),
        NaN where there is no vertex.
    mask : numpy.ndarray
        ``(H, W)`` facets to show (non-zero); facets with a non-finite corner are left out.
    normals : numpy.ndarray, optional
        ``(H + 1, W + 1, 3)`` vertex normals (camera frame); used when the mesh is not
        decimated. Without them, or when decimated, the page computes vertex normals from its
        triangles.
    albedo : numpy.ndarray, optional
        ``(H + 1, W + 1)`` grey or ``(H + 1, W + 1, 3)`` RGB vertex albedo, shown as colour
        (scaled by its 99th percentile). Without it the albedo colouring is grey.
    title : str, default "nplps mesh"
        The page's title, shown in its corner.
    units : str, optional
        The length unit shown with the extent and the scale bar (e.g. ``"mm"``). Default: "rig units".
    max_triangles : int, default 2_000_000
        At most this many triangles are written: a larger mesh is decimated on a regular grid
        stride (see the module notes), and the page says so.
    normal_map : {"opengl", "directx", "opencv"}, default "opengl"
        The convention of the normals colouring (:data:`nplps.export.NORMAL_MAP_FRAMES`).

    Returns
    -------
    ViewerInfo
        The path, the triangle counts and the stride.

    Raises
    ------
    InputError
        A shape does not match, `max_triangles` is below 2, `normal_map` is unknown, or no
        facet is left.
    OSError
        The page could not be written (``filename`` names it).

    Examples
    --------
    ::

        info = nplps.viewer.write_viewer("view.html", result.vertices, result.mask)
        print(info.path, info.triangles)
    """
    if isinstance(max_triangles, bool) or not isinstance(max_triangles, (int, np.integer)) or max_triangles < 2:
        raise InputError(f"max_triangles must be an integer of at least 2, got {max_triangles!r}")
    export.check_normal_map(normal_map)
    vertices = np.asarray(vertices)
    mask = np.asarray(mask, dtype=bool)
    if vertices.ndim != 3 or vertices.shape[2] != 3:
        raise InputError(f"vertices must have shape (H + 1, W + 1, 3), got {vertices.shape}")
    if mask.shape != (vertices.shape[0] - 1, vertices.shape[1] - 1):
        raise InputError(f"mask has shape {mask.shape}, expected {(vertices.shape[0] - 1, vertices.shape[1] - 1)}")
    finite = np.isfinite(vertices).all(axis=2)
    facets = mask & finite[:-1, :-1] & finite[:-1, 1:] & finite[1:, :-1] & finite[1:, 1:]
    full = 2 * int(np.count_nonzero(facets))
    if full == 0:
        raise InputError("no facet to show: the mask is empty or every masked facet has a non-finite corner")
    stride, rows, cols, coarse = _decimation(facets, finite, int(max_triangles))
    if stride > 1:
        grid = np.ix_(rows, cols)
        vertices = vertices[grid]
        albedo = None if albedo is None else np.asarray(albedo)[grid]
        normals = None
    mesh = export._build_mesh(vertices, coarse, normals, albedo, opengl=False)
    h, w = mask.shape
    meta: dict[str, Any] = {
        "title": str(title),
        "units": units or "rig units",
        "size": f"{w} x {h} pixels",
        "triangles": len(mesh.faces),
        "full_triangles": full,
        "stride": stride,
        "normal_map": normal_map,
        "normal_flip": list(export.NORMAL_MAP_FRAMES[normal_map]),
    }
    text = _page(meta, mesh.points, mesh.faces, mesh.normals, mesh.colors)
    write_text(path, text)
    return ViewerInfo(Path(path), len(mesh.faces), full, stride, len(text.encode("utf-8")))


def _decimation(
    facets: np.ndarray, finite: np.ndarray, max_triangles: int
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """Choose the smallest grid stride that leaves at most `max_triangles` triangles.

    Returns the stride, the kept vertex rows and columns (every stride-th and the last), and the
    coarse facet mask: at least half of the covered pixels are facets, and the four corners are
    finite.
    """
    h, w = facets.shape
    stride = 1
    full = 2 * int(np.count_nonzero(facets))
    if full > max_triangles:
        stride = max(2, math.ceil(math.sqrt(full / max_triangles)))
    while True:
        rows = _kept(h, stride)
        cols = _kept(w, stride)
        if stride == 1:
            coarse = facets
        else:
            counts = np.add.reduceat(np.add.reduceat(facets.astype(np.int64), rows[:-1], axis=0), cols[:-1], axis=1)
            area = np.diff(rows)[:, None] * np.diff(cols)[None, :]
            ok = finite[np.ix_(rows, cols)]
            coarse = (2 * counts >= area) & ok[:-1, :-1] & ok[:-1, 1:] & ok[1:, :-1] & ok[1:, 1:]
        triangles = 2 * int(np.count_nonzero(coarse))
        if triangles <= max_triangles and triangles > 0:
            return stride, rows, cols, coarse
        if triangles == 0 or stride >= max(h, w):
            raise InputError(f"no facet left after decimating to at most {max_triangles} triangles")
        stride += 1


def _kept(n: int, stride: int) -> np.ndarray:
    """Vertex indices 0, stride, 2 stride, ... and the last one, n."""
    kept = np.arange(0, n + 1, stride)
    return kept if kept[-1] == n else np.append(kept, n)


def write_result_viewer(
    directory: str | os.PathLike[str],
    out: str | os.PathLike[str] | None = None,
    *,
    title: str | None = None,
    units: str | None = None,
    max_triangles: int = DEFAULT_MAX_TRIANGLES,
) -> ViewerInfo:
    """Write the viewer page of a result directory (``nplps view``).

    Reads ``mesh.ply`` (positions, vertex normals and albedo colours; either frame) and
    ``depth.npy`` (which places the PLY's vertices on the vertex grid) of a directory written by
    :meth:`nplps.Reconstruction.save` or ``nplps reconstruct``.

    Parameters
    ----------
    directory : str or path-like
        The result directory.
    out : str or path-like, optional
        The page to write. Default: ``viewer.html`` in `directory`.
    title : str, optional
        The page's title. Default: the directory's name.
    units : str, optional
        The length unit shown with the extent and the scale bar. Default: ``summary.json``'s
        ``"units"`` (``--units`` of ``nplps reconstruct``), else "rig units".
    max_triangles : int, default 2_000_000
        Decimate larger meshes (see :func:`write_viewer`).

    Returns
    -------
    ViewerInfo
        As :func:`write_viewer`.

    Raises
    ------
    InputError
        `directory` is missing or not a complete result directory, or its ``mesh.ply`` and
        ``depth.npy`` do not belong together.
    OSError
        The page could not be written.
    """
    vertices, mask, normals, albedo = _read_result(Path(directory))
    # summary.json names the unit and the normal map's convention; a folder without one gets the defaults.
    has_summary = os.path.lexists(Path(directory) / "summary.json")
    summary = _results.read_summary(directory) if has_summary else {}
    if units is None and isinstance(summary.get("units"), str) and summary["units"].strip():
        units = summary["units"]
    frame = (summary.get("normal_map") or {}).get("frame", "opengl")
    target = Path(directory) / VIEWER_FILE if out is None else Path(out)
    name = title if title is not None else Path(os.path.abspath(directory)).name
    info = write_viewer(
        target,
        vertices,
        mask,
        normals=normals,
        albedo=albedo,
        title=name,
        units=units,
        max_triangles=max_triangles,
        normal_map=frame,
    )
    if out is None:
        add_to_manifest(directory, VIEWER_FILE)
    return info


def _read_result(directory: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Return the vertex grid, mask, vertex normals and vertex albedo of a result directory."""
    if not directory.is_dir():
        raise InputError(f"result directory '{directory}' does not exist or is not a directory")
    # Missing: not there at all (a FIFO, a directory or a broken link there is named by its reader).
    missing = [name for name in ("mesh.ply", "depth.npy") if not os.path.lexists(directory / name)]
    if missing:
        raise InputError(
            f"'{directory}' is not a complete nplps result directory: {' and '.join(missing)} missing "
            "(write one with 'nplps reconstruct ... --out DIR')"
        )
    ply = _results.read_mesh_ply(directory / "mesh.ply")
    depth = _results.read_npy(directory / "depth.npy", kinds="f", ndim=2, max_abs=_results.MAX_COORDINATE)
    raw = np.asarray(ply["vertices"], dtype=np.float64)
    if not (np.isfinite(raw).all() and float(np.abs(raw).max(initial=0.0)) <= float(np.finfo(np.float32).max)):
        raise InputError(f"'{directory / 'mesh.ply'}' has a vertex that is not a finite float32 position")
    points = raw.astype(np.float32)
    faces = np.asarray(ply["faces"])
    opengl = "frame opengl" in (ply["comments"] or [])
    flip = _OPENGL_FLIP if opengl else np.ones(3, dtype=np.float32)
    if depth.ndim != 2 or depth.shape[0] < 2 or depth.shape[1] < 2:
        raise InputError(f"'{directory / 'depth.npy'}' is not an (H + 1, W + 1) vertex depth map")
    used = np.flatnonzero(np.isfinite(depth))
    mismatch = f"'{directory}': mesh.ply and depth.npy do not belong to the same result"
    if len(used) != len(points) or len(faces) % 2:
        raise InputError(f"{mismatch} ({len(points)} mesh vertices, {len(used)} finite depths)")
    points = points * flip
    if len(points):
        finite_depth = depth.ravel()[used].astype(np.float64)
        scale = max(float(np.max(np.abs(finite_depth))), 1e-30)
        if float(np.max(np.abs(points[:, 2] - finite_depth))) > 1e-4 * scale:
            raise InputError(f"{mismatch} (the vertex depths differ)")
    h1, w1 = depth.shape
    # The nplps PLY has two triangles (00, 10, 11), (00, 11, 01) per masked facet.
    f00 = used[faces[0::2, 0]]
    if not (
        np.array_equal(used[faces[0::2, 1]], f00 + w1)
        and np.array_equal(used[faces[0::2, 2]], f00 + w1 + 1)
        and bool(np.all(f00 % w1 < w1 - 1))
    ):
        raise InputError(f"'{directory / 'mesh.ply'}' is not a vertex-grid mesh written by nplps")
    mask = np.zeros((h1 - 1, w1 - 1), dtype=bool)
    mask[f00 // w1, f00 % w1] = True
    vertices = _scatter(points, used, (h1, w1, 3))
    normals = None if ply["normals"] is None else _scatter(np.asarray(ply["normals"]) * flip, used, (h1, w1, 3))
    colors = ply["colors"]
    albedo = None if colors is None else _scatter(np.asarray(colors, dtype=np.float32) / 255.0, used, (h1, w1, 3))
    return vertices, mask, normals, albedo


def _scatter(values: np.ndarray, used: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """Return an NaN grid of `shape` with `values` at the flat vertex indices `used`."""
    grid = np.full(shape, np.nan, dtype=np.float32)
    grid.reshape(-1, shape[2])[used] = values
    return grid


def read_viewer(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Decode the mesh embedded in a page written by :func:`write_viewer`.

    Parameters
    ----------
    path : str or path-like
        The page.

    Returns
    -------
    dict
        ``positions`` ((n, 3) float32, camera frame), ``faces`` ((m, 3) uint32), ``normals``
        ((n, 3) float32 or None), ``colors`` ((n, 3) uint8 or None) and ``meta`` (title, units,
        size, triangles, full_triangles, stride).

    Raises
    ------
    InputError
        The file is not such a page.
    """
    text = Path(path).read_text(encoding="utf-8")
    found = _DATA_RE.search(text)
    if found is None:
        raise InputError(f"'{os.fspath(path)}' is not an nplps viewer page")
    data = json.loads(found.group(1))

    def decode(key: str, dtype: str, width: int) -> np.ndarray | None:
        raw = data.get(key)
        if raw is None:
            return None
        return np.frombuffer(base64.b64decode(raw), dtype=dtype).reshape(-1, width)

    return {
        "positions": decode("positions", "<f4", 3),
        "faces": decode("indices", "<u4", 3),
        "normals": decode("normals", "<f4", 3),
        "colors": decode("colors", "u1", 3),
        "meta": data["meta"],
    }


def _b64(array: np.ndarray | None, dtype: str) -> str | None:
    if array is None:
        return None
    return base64.b64encode(np.ascontiguousarray(array, dtype=dtype).tobytes()).decode("ascii")


def _page(
    meta: dict[str, Any], points: np.ndarray, faces: np.ndarray, normals: np.ndarray | None, colors: np.ndarray | None
) -> str:
    """Return the HTML of the page."""
    data = {
        "meta": meta,
        "positions": _b64(points, "<f4"),
        "indices": _b64(faces, "<u4"),
        "normals": _b64(normals, "<f4"),
        "colors": _b64(colors, "u1"),
    }
    # No tag inside the script (json.dumps writes every other character outside ASCII escaped).
    blob = json.dumps(data, separators=(",", ":")).replace("<", "\\u003c")
    parts = {
        "TITLE": _escape(meta["title"]),
        "SCRIPT": _SCRIPT,
        "DATA": f'<script id="{_DATA_ID}" type="application/json">{blob}</script>',
    }
    # One pass over the template: a title holding "@SCRIPT@" or "@DATA@" stays text.
    return _PLACEHOLDER.sub(lambda m: parts[m.group(1)], _HTML)


_PLACEHOLDER = re.compile(r"@(TITLE|SCRIPT|DATA)@")


def _escape(text: str) -> str:
    """Escape text for HTML content and attribute values (&, <, >, both quotes)."""
    return html.escape(text, quote=True)


_HTML = """<!DOCTYPE html>
<html lang="en" data-status="loading">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>@TITLE@</title>
<style>
html, body { margin: 0; height: 100%; overflow: hidden; background: #20242a; font: 13px sans-serif; color: #e8e8e8; }
canvas { position: fixed; left: 0; top: 0; width: 100%; height: 100%; touch-action: none; display: block; }
#panel { position: fixed; left: 8px; top: 8px; background: rgba(20, 22, 26, 0.75); padding: 6px 9px;
  border-radius: 4px; max-width: 30em; line-height: 1.5; }
#panel b { font-size: 14px; }
#panel label { margin-right: 0.6em; white-space: nowrap; }
#panel input[type=range] { width: 7em; vertical-align: middle; }
#help { position: fixed; left: 8px; bottom: 6px; background: rgba(20, 22, 26, 0.75); padding: 3px 8px;
  border-radius: 4px; }
#scale { position: fixed; right: 10px; bottom: 52px; background: rgba(20, 22, 26, 0.75); padding: 3px 8px;
  border-radius: 4px; text-align: center; }
#scalebar { height: 5px; background: #e8e8e8; margin: 2px auto 3px; }
#error { display: none; position: fixed; left: 10%; top: 40%; width: 80%; background: #7a1f1f; color: #fff;
  padding: 12px; border-radius: 4px; font-size: 15px; }
</style>
</head>
<body>
<canvas id="view"></canvas>
<div id="panel">
<b>@TITLE@</b><br>
<span id="info"></span><br>
<span id="note"></span>
<div>
<label><input type="radio" name="mode" value="albedo" checked> albedo</label>
<label><input type="radio" name="mode" value="shaded"> shaded</label>
<label><input type="radio" name="mode" value="normals"> normals</label>
<button id="reset" type="button">reset view</button>
</div>
<div>light <label>azimuth <input id="laz" type="range" min="-89" max="89" value="0"></label>
<label>elevation <input id="lel" type="range" min="-89" max="89" value="0"></label></div>
</div>
<div id="help">drag: rotate &middot; wheel/pinch: zoom &middot; right- or shift-drag: pan &middot;
alt-drag or sliders: light &middot; 1 2 3: albedo/shaded/normals &middot; R: reset</div>
<div id="scale"><div id="scalebar"></div><span id="scalelabel"></span></div>
<div id="error"></div>
@DATA@
<script>
@SCRIPT@
</script>
</body>
</html>
"""

_SCRIPT = r"""(function () {
"use strict";
var errorBox = document.getElementById("error");
function fail(message) {
  document.documentElement.setAttribute("data-status", "error: " + message);
  document.title = "viewer error";
  errorBox.textContent = "Viewer error: " + message;
  errorBox.style.display = "block";
}
window.addEventListener("error", function (e) { fail(e.message || String(e)); });

function decode(text, Type) {
  if (text === null) return null;
  var bin = atob(text), n = bin.length, bytes = new Uint8Array(n);
  for (var i = 0; i < n; i++) bytes[i] = bin.charCodeAt(i);
  return new Type(bytes.buffer);  // little-endian, as every WebGL platform
}

function main() {
  var data = JSON.parse(document.getElementById("nplps-mesh").textContent);
  var meta = data.meta;
  var pos = decode(data.positions, Float32Array), idx = decode(data.indices, Uint32Array);
  var nrm = decode(data.normals, Float32Array), col = decode(data.colors, Uint8Array);
  var nv = pos.length / 3;
  if (!nrm) nrm = vertexNormals(pos, idx);
  // The object's box, in the camera frame.
  var lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
  for (var i = 0; i < nv; i++) for (var k = 0; k < 3; k++) {
    var v = pos[3 * i + k]; if (v < lo[k]) lo[k] = v; if (v > hi[k]) hi[k] = v;
  }
  var centre = [0, 1, 2].map(function (k) { return 0.5 * (lo[k] + hi[k]); });
  var radius = 0.5 * Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) || 1;
  var ext = [0, 1, 2].map(function (k) { return fmt(hi[k] - lo[k]); });
  document.getElementById("info").textContent = meta.size + ", " + meta.triangles.toLocaleString("en") +
    " triangles; extent " + ext.join(" x ") + " " + meta.units + " (x, y, z)";
  document.getElementById("note").textContent = meta.stride > 1 ?
    "decimated on a regular grid of stride " + meta.stride + " (" + meta.full_triangles.toLocaleString("en") +
    " triangles at full resolution)" : "full resolution";

  var canvas = document.getElementById("view");
  var gl = canvas.getContext("webgl", { antialias: true, preserveDrawingBuffer: true });
  if (!gl) throw new Error("this browser has no WebGL");
  if (!gl.getExtension("OES_element_index_uint")) {
    throw new Error("WebGL lacks 32-bit indices (OES_element_index_uint)");
  }
  var prog = program(gl, VERTEX, FRAGMENT);
  function buffer(array, target) {
    var b = gl.createBuffer(); gl.bindBuffer(target, b); gl.bufferData(target, array, gl.STATIC_DRAW); return b;
  }
  var bPos = buffer(pos, gl.ARRAY_BUFFER), bNrm = buffer(nrm, gl.ARRAY_BUFFER);
  var bCol = col ? buffer(col, gl.ARRAY_BUFFER) : null;
  var bIdx = buffer(idx, gl.ELEMENT_ARRAY_BUFFER);
  var loc = {};
  ["aPos", "aNrm", "aCol"].forEach(function (n) { loc[n] = gl.getAttribLocation(prog, n); });
  ["uModel", "uView", "uProj", "uNormal", "uLight", "uMode", "uFlip"].forEach(function (n) {
    loc[n] = gl.getUniformLocation(prog, n);
  });

  // Model: centre the object and turn the camera frame (y down, z forward) into GL's (y up, z to the eye).
  var model = [1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0, -centre[0], centre[1], centre[2], 1];
  var FOV = 30 * Math.PI / 180;
  var view0 = { azimuth: 35, elevation: 25, zoom: 1, mode: "albedo", light_azimuth: -20, light_elevation: 25,
    ui: 1 };
  var state = {};
  var target = [0, 0, 0];
  function fromHash() {
    var s = Object.assign({}, view0);
    location.hash.replace(/^#/, "").split("&").forEach(function (kv) {
      var p = kv.split("="); if (p.length !== 2 || !(p[0] in view0)) return;
      var value = decodeURIComponent(p[1]);
      s[p[0]] = p[0] === "mode" ? value : (isFinite(parseFloat(value)) ? parseFloat(value) : s[p[0]]);
    });
    if (["albedo", "shaded", "normals"].indexOf(s.mode) < 0) s.mode = "albedo";
    return s;
  }
  function reset() {
    state = fromHash(); target = [0, 0, 0];
    state.distance = radius / Math.sin(FOV / 2) * 1.05 / Math.max(state.zoom, 1e-6);
    ["panel", "help", "scale"].forEach(function (id) {
      document.getElementById(id).style.display = state.ui ? "" : "none";
    });
    syncControls(); draw();
  }
  function syncControls() {
    document.querySelectorAll("input[name=mode]").forEach(function (r) { r.checked = r.value === state.mode; });
    document.getElementById("laz").value = state.light_azimuth;
    document.getElementById("lel").value = state.light_elevation;
  }

  function draw() {
    var dpr = window.devicePixelRatio || 1;
    var w = Math.max(1, Math.round(canvas.clientWidth * dpr)), h = Math.max(1, Math.round(canvas.clientHeight * dpr));
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
    gl.viewport(0, 0, w, h);
    gl.clearColor(0.125, 0.14, 0.165, 1); gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.DEPTH_TEST);
    var el = clamp(state.elevation, -89.9, 89.9) * Math.PI / 180, az = state.azimuth * Math.PI / 180;
    var d = state.distance;
    var eye = [target[0] + d * Math.sin(az) * Math.cos(el), target[1] + d * Math.sin(el),
      target[2] + d * Math.cos(az) * Math.cos(el)];
    var view = lookAt(eye, target, [0, 1, 0]);
    var near = Math.max(d - 2 * radius, d * 1e-3), far = d + 2 * radius;
    var proj = perspective(FOV, w / h, near, far);
    var nm = mul(view, model);
    var normal = [nm[0], nm[1], nm[2], nm[4], nm[5], nm[6], nm[8], nm[9], nm[10]];
    var laz = state.light_azimuth * Math.PI / 180, lel = state.light_elevation * Math.PI / 180;
    gl.useProgram(prog);
    gl.uniformMatrix4fv(loc.uModel, false, model);
    gl.uniformMatrix4fv(loc.uView, false, view);
    gl.uniformMatrix4fv(loc.uProj, false, proj);
    gl.uniformMatrix3fv(loc.uNormal, false, normal);
    gl.uniform3f(loc.uLight, Math.sin(laz) * Math.cos(lel), Math.sin(lel), Math.cos(laz) * Math.cos(lel));
    gl.uniform1i(loc.uMode, ["albedo", "shaded", "normals"].indexOf(state.mode));
    var flip = meta.normal_flip || [1, -1, -1];
    gl.uniform3f(loc.uFlip, flip[0], flip[1], flip[2]);
    attribute(bPos, loc.aPos, gl.FLOAT, false);
    attribute(bNrm, loc.aNrm, gl.FLOAT, false);
    if (bCol) attribute(bCol, loc.aCol, gl.UNSIGNED_BYTE, true);
    else { gl.disableVertexAttribArray(loc.aCol); gl.vertexAttrib3f(loc.aCol, 0.8, 0.8, 0.8); }
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, bIdx);
    gl.drawElements(gl.TRIANGLES, idx.length, gl.UNSIGNED_INT, 0);
    scaleBar(2 * d * Math.tan(FOV / 2) / Math.max(canvas.clientHeight, 1));
  }
  // The scale bar: a round length near 100 screen pixels at the centre of rotation (perspective:
  // nearer parts look larger). perPixel: length units per CSS pixel at the target's distance.
  function scaleBar(perPixel) {
    var target = 100 * perPixel, p = Math.pow(10, Math.floor(Math.log10(target)));
    var length = target >= 5 * p ? 5 * p : target >= 2 * p ? 2 * p : p;
    var px = length / perPixel, box = document.getElementById("scale");
    document.getElementById("scalebar").style.width = px.toFixed(1) + "px";
    document.getElementById("scalelabel").textContent = +length.toPrecision(3) + " " + meta.units;
    box.title = "at the centre of rotation (nearer parts look larger)";
    box.setAttribute("data-length", String(length));
    box.setAttribute("data-pixels", px.toFixed(2));
    box.setAttribute("data-per-pixel", String(perPixel));
    box.setAttribute("data-view-height", String(canvas.clientHeight));
  }
  function attribute(b, l, type, normalized) {
    if (l < 0) return;
    gl.bindBuffer(gl.ARRAY_BUFFER, b);
    gl.enableVertexAttribArray(l);
    gl.vertexAttribPointer(l, 3, type, normalized, 0, 0);
  }
  var pending = false;
  function redraw() {
    if (!pending) { pending = true; requestAnimationFrame(function () { pending = false; draw(); }); }
  }

  // Mouse, touch and pen.
  var pointers = {}, mode = null, pinch = 0;
  function count() { return Object.keys(pointers).length; }
  canvas.addEventListener("contextmenu", function (e) { e.preventDefault(); });
  canvas.addEventListener("pointerdown", function (e) {
    try { canvas.setPointerCapture(e.pointerId); } catch (err) { /* not an active pointer */ }
    pointers[e.pointerId] = [e.clientX, e.clientY];
    mode = e.button === 2 || e.shiftKey ? "pan" : e.altKey ? "light" : "rotate";
    pinch = 0;
  });
  function release(e) { delete pointers[e.pointerId]; pinch = 0; }
  canvas.addEventListener("pointerup", release);
  canvas.addEventListener("pointercancel", release);
  canvas.addEventListener("pointermove", function (e) {
    var p = pointers[e.pointerId]; if (!p) return;
    var dx = e.clientX - p[0], dy = e.clientY - p[1];
    pointers[e.pointerId] = [e.clientX, e.clientY];
    if (count() >= 2) {  // pinch: zoom by the change of the distance between two fingers
      var ids = Object.keys(pointers), a = pointers[ids[0]], b = pointers[ids[1]];
      var gap = Math.hypot(a[0] - b[0], a[1] - b[1]);
      if (pinch > 0 && gap > 0) state.distance *= pinch / gap;
      pinch = gap;
    } else if (mode === "pan") {
      pan(dx, dy);
    } else if (mode === "light") {
      state.light_azimuth = clamp(state.light_azimuth + 0.4 * dx, -89, 89);
      state.light_elevation = clamp(state.light_elevation - 0.4 * dy, -89, 89);
      syncControls();
    } else {
      state.azimuth -= 0.4 * dx;
      state.elevation = clamp(state.elevation + 0.4 * dy, -89.9, 89.9);
    }
    redraw();
  });
  function pan(dx, dy) {
    var el = state.elevation * Math.PI / 180, az = state.azimuth * Math.PI / 180;
    var right = [Math.cos(az), 0, -Math.sin(az)];
    var up = [-Math.sin(el) * Math.sin(az), Math.cos(el), -Math.sin(el) * Math.cos(az)];
    var s = 2 * state.distance * Math.tan(FOV / 2) / Math.max(canvas.clientHeight, 1);
    for (var k = 0; k < 3; k++) target[k] += s * (-dx * right[k] + dy * up[k]);
  }
  canvas.addEventListener("wheel", function (e) {
    e.preventDefault();
    state.distance *= Math.exp(clamp(e.deltaY, -200, 200) * 0.0015);
    redraw();
  }, { passive: false });
  document.querySelectorAll("input[name=mode]").forEach(function (r) {
    r.addEventListener("change", function () { state.mode = r.value; redraw(); });
  });
  document.getElementById("laz").addEventListener("input", function (e) {
    state.light_azimuth = +e.target.value; redraw();
  });
  document.getElementById("lel").addEventListener("input", function (e) {
    state.light_elevation = +e.target.value; redraw();
  });
  document.getElementById("reset").addEventListener("click", reset);
  window.addEventListener("keydown", function (e) {
    if (e.key === "r" || e.key === "R") reset();
    else if (e.key === "1" || e.key === "2" || e.key === "3") {
      state.mode = ["albedo", "shaded", "normals"][+e.key - 1]; syncControls(); redraw();
    }
  });
  window.addEventListener("resize", redraw);
  window.addEventListener("hashchange", reset);
  reset();
  var glError = gl.getError();
  if (glError !== gl.NO_ERROR) throw new Error("WebGL error " + glError);
  document.documentElement.setAttribute("data-status", "ready");
}

function vertexNormals(pos, idx) {  // area-weighted sums of the triangles' normals
  var n = new Float32Array(pos.length);
  for (var t = 0; t < idx.length; t += 3) {
    var a = 3 * idx[t], b = 3 * idx[t + 1], c = 3 * idx[t + 2];
    var ux = pos[b] - pos[a], uy = pos[b + 1] - pos[a + 1], uz = pos[b + 2] - pos[a + 2];
    var vx = pos[c] - pos[a], vy = pos[c + 1] - pos[a + 1], vz = pos[c + 2] - pos[a + 2];
    var x = uy * vz - uz * vy, y = uz * vx - ux * vz, z = ux * vy - uy * vx;
    n[a] += x; n[a + 1] += y; n[a + 2] += z;
    n[b] += x; n[b + 1] += y; n[b + 2] += z;
    n[c] += x; n[c + 1] += y; n[c + 2] += z;
  }
  for (var i = 0; i < n.length; i += 3) {  // facing the camera (n_z < 0), as nplps's normals
    var l = Math.hypot(n[i], n[i + 1], n[i + 2]) || 1;
    if (n[i + 2] > 0) l = -l;
    n[i] /= l; n[i + 1] /= l; n[i + 2] /= l;
  }
  return n;
}

function fmt(x) { return x >= 100 ? x.toFixed(0) : x >= 1 ? x.toPrecision(3) : x.toPrecision(2); }
function clamp(x, a, b) { return Math.min(b, Math.max(a, x)); }
function perspective(fov, aspect, near, far) {
  var f = 1 / Math.tan(fov / 2), r = 1 / (near - far);
  return [f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) * r, -1, 0, 0, 2 * far * near * r, 0];
}
function lookAt(eye, at, up) {
  var z = norm([eye[0] - at[0], eye[1] - at[1], eye[2] - at[2]]), x = norm(cross(up, z)), y = cross(z, x);
  return [x[0], y[0], z[0], 0, x[1], y[1], z[1], 0, x[2], y[2], z[2], 0,
    -dot(x, eye), -dot(y, eye), -dot(z, eye), 1];
}
function mul(a, b) {  // column-major 4 x 4: a * b
  var m = new Array(16);
  for (var c = 0; c < 4; c++) for (var r = 0; r < 4; r++) {
    m[4 * c + r] = a[r] * b[4 * c] + a[4 + r] * b[4 * c + 1] + a[8 + r] * b[4 * c + 2] + a[12 + r] * b[4 * c + 3];
  }
  return m;
}
function cross(a, b) { return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]; }
function dot(a, b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
function norm(a) { var l = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / l, a[1] / l, a[2] / l]; }
function program(gl, vs, fs) {
  function shader(type, source) {
    var s = gl.createShader(type); gl.shaderSource(s, source); gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error("shader: " + gl.getShaderInfoLog(s));
    return s;
  }
  var p = gl.createProgram();
  gl.attachShader(p, shader(gl.VERTEX_SHADER, vs)); gl.attachShader(p, shader(gl.FRAGMENT_SHADER, fs));
  gl.linkProgram(p);
  if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error("program: " + gl.getProgramInfoLog(p));
  return p;
}

var VERTEX = [
  "attribute vec3 aPos; attribute vec3 aNrm; attribute vec3 aCol;",
  "uniform mat4 uModel, uView, uProj; uniform mat3 uNormal;",
  "varying vec3 vEye; varying vec3 vN; varying vec3 vCam; varying vec3 vCol;",
  "void main() {",
  "  vec4 e = uView * (uModel * vec4(aPos, 1.0));",
  "  vEye = e.xyz; vN = uNormal * aNrm; vCam = aNrm; vCol = aCol;",
  "  gl_Position = uProj * e;",
  "}"].join("\n");
var FRAGMENT = [
  "precision highp float;",
  "varying vec3 vEye; varying vec3 vN; varying vec3 vCam; varying vec3 vCol;",
  "uniform vec3 uLight; uniform int uMode; uniform vec3 uFlip;",
  "void main() {",
  "  if (uMode == 2) {  // the normal map's colours: the normal in its frame (uFlip) as (v + 1) / 2",
  "    vec3 c = normalize(vCam) * uFlip; gl_FragColor = vec4(0.5 * c + 0.5, 1.0); return;",
  "  }",
  "  vec3 n = normalize(vN); float back = 1.0;",
  "  if (dot(n, vEye) > 0.0) { n = -n; back = 0.6; }  // seen from behind: light the other side, darker",
  "  float key = max(dot(n, normalize(uLight)), 0.0), fill = max(dot(n, normalize(-vEye)), 0.0);",
  "  float shade = 0.08 + 0.64 * key + 0.28 * fill;  // the movable light and a weak headlight",
  "  vec3 base = uMode == 0 ? vCol : vec3(0.82);",
  "  gl_FragColor = vec4(base * shade * back, 1.0);",
  "}"].join("\n");

try { main(); } catch (e) { fail(e && e.message ? e.message : String(e)); }
})();
"""
