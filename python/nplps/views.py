"""Pictures of a result for people: oblique shaded renders of the mesh and colour maps.

Everything here is for display only (the report, :meth:`nplps.Reconstruction._repr_html_`); the
solver's numerics are in the compiled core. It needs numpy only and runs headless.

Oblique renders (:func:`render_mesh`)
-------------------------------------
The mesh is the (H+1, W+1) grid of vertex positions in the camera frame (OpenCV: x right, y
down, z forward), one quad per masked pixel, each split into two triangles. A *view* is an
orthographic camera that orbits the object's centre ``c`` (the median of the vertices):

- ``azimuth`` turns the viewing camera about the vertical (y) axis through ``c``: positive to
  the right (+x) of the real camera, so the object's right side comes into view;
  ``elevation`` lifts it above the object (towards -y, "up" in the image), negative below.
- The view's forward axis is ``f = (-sin a cos e, sin e, cos a cos e)``, its right axis
  ``r = normalize((0, 1, 0) x f)`` and its down axis ``d = f x r``; a point ``p`` lands at
  image column ``(p - c) . r`` and row ``(p - c) . d`` (scaled to fit the picture) with depth
  ``(p - c) . f``. ``azimuth = elevation = 0`` is the real camera's view made orthographic.
- Triangles are rasterized with a z-buffer (per-pixel barycentric tests over each triangle's
  bounding box, the nearest triangle kept per pixel), all in vectorized numpy.
- Shading is Lambertian with a *key light* that moves with the viewer, ``key_light = (a, e)``
  degrees to the left of and above the eye (direction ``l = -cos e cos a f - cos e sin a r -
  sin e d``), a fill light at the eye (direction ``-f``) and an ambient term:
  ``grey = albedo * (ambient + (1 - ambient) (0.7 max(0, n' . l) + 0.3 |n . f|))`` with the
  facet normal ``n`` (cross product of the quad's diagonals) and ``n'`` the same turned towards
  the viewer. The key light makes the relief of surfaces that face the viewer visible (a
  headlight alone shades a flat sheet evenly); ``key_light=None`` is the headlight alone,
  ``grey = albedo * (ambient + (1 - ambient) |n . f|)``. Both sides of the surface are lit, the
  back faces tinted blue so that they can be told apart. The background is white.
- Large meshes are shown decimated: every ``stride``-th vertex row and column is kept, with
  ``stride = ceil(sqrt(masked pixels / max_facets))`` (default ``max_facets`` 250 000, about
  one facet per pixel of a 512 x 512 picture), and a coarse quad is drawn when its four
  corners are on the mesh and at least half of its pixels are masked. A 2-megapixel mesh thus
  renders in about a second.

Colour maps (:func:`colormap`)
------------------------------
A perceptually ordered map from dark violet through blue and green to yellow, interpolated
linearly between seven anchor colours chosen for this package (monotonic lightness), and its
numeric colour bar (:func:`colorbar_ticks`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = [
    "colorbar_ticks",
    "colorize",
    "colormap",
    "downsample",
    "pixel_footprint",
    "render_mesh",
    "scale_bar_length",
    "view_axes",
]

# Anchor colours (sRGB, 0..1) of the sequential map, dark to light; lightness rises steadily.
_ANCHORS = np.array(
    [
        [0.26, 0.02, 0.33],
        [0.28, 0.19, 0.50],
        [0.21, 0.36, 0.55],
        [0.15, 0.50, 0.56],
        [0.16, 0.64, 0.52],
        [0.45, 0.79, 0.35],
        [0.98, 0.91, 0.15],
    ]
)

_BACKGROUND = 255
_BACK_TINT = np.array([0.75, 0.85, 1.0])


def colormap(values: np.ndarray) -> np.ndarray:
    """Map values in [0, 1] to RGB colours of the package's sequential colour map.

    Parameters
    ----------
    values : numpy.ndarray
        Any shape; clipped to [0, 1]. NaN maps to NaN.

    Returns
    -------
    numpy.ndarray
        ``values.shape + (3,)`` floats in [0, 1] (NaN where `values` is NaN).
    """
    v = np.asarray(values, dtype=np.float64)
    t = np.clip(v, 0.0, 1.0) * (len(_ANCHORS) - 1)
    i = np.clip(np.floor(np.nan_to_num(t)), 0, len(_ANCHORS) - 2).astype(np.intp)
    frac = (np.nan_to_num(t) - i)[..., None]
    rgb = _ANCHORS[i] * (1.0 - frac) + _ANCHORS[i + 1] * frac
    rgb[np.isnan(v)] = np.nan
    return rgb


def colorize(
    values: np.ndarray, lo: float, hi: float, *, background: tuple[int, int, int] = (255, 255, 255)
) -> np.ndarray:
    """Colour-map an array between `lo` and `hi` into an 8-bit RGB image.

    Parameters
    ----------
    values : numpy.ndarray
        (H, W) values; NaN is drawn in `background`.
    lo, hi : float
        The values mapped to the two ends of the colour map (clipped beyond).
    background : (int, int, int), default white
        The colour of NaN pixels.

    Returns
    -------
    numpy.ndarray
        (H, W, 3) uint8.
    """
    v = np.asarray(values, dtype=np.float64)
    span = hi - lo if hi > lo else 1.0
    rgb = colormap((v - lo) / span)
    out = np.empty((*v.shape, 3), dtype=np.uint8)
    finite = np.isfinite(v)
    out[...] = np.asarray(background, dtype=np.uint8)
    out[finite] = np.rint(rgb[finite] * 255).astype(np.uint8)
    return out


def colorbar_ticks(lo: float, hi: float, count: int = 5) -> list[float]:
    """Return the tick values of a colour bar from `lo` to `hi`.

    Both ends and the "nice" round numbers (1, 2 or 5 times a power of ten) between them, about
    `count` in all.

    Parameters
    ----------
    lo, hi : float
        The range of the bar.
    count : int, default 5
        About how many ticks.

    Returns
    -------
    list of float
        Increasing; the first is `lo` and the last `hi`.
    """
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo] if math.isfinite(lo) else []
    raw = (hi - lo) / max(count - 1, 1)
    power = 10 ** math.floor(math.log10(raw))
    step = min((m * power for m in (1, 2, 5, 10)), key=lambda s: abs(math.log(s / raw)))
    inner = [round(k * step, 12) for k in range(math.ceil(lo / step), math.floor(hi / step) + 1)]
    gap = 0.4 * step  # leave out round numbers that would crowd the ends' labels
    ticks = [lo] + [t for t in inner if lo + gap < t < hi - gap] + [hi]
    return ticks


#: Values (pixels x channels) of one band of block rows converted to float64 at a time by
#: :func:`downsample` and :func:`_block_mean` (about 32 MB; a band holds at least one row of
#: blocks): the full-size float64 copy and its masks (25 bytes a value, 7.5 GB for a 100 MP
#: normal map) are never made.
BAND_VALUES = 4_000_000


def downsample(image: np.ndarray, max_side: int, *, scale: float | None = None) -> np.ndarray:
    """Shrink an image by an integer factor so that its longer side is at most `max_side`.

    Block means over ``s x s`` pixels (``s = ceil(longer side / max_side)``), ignoring NaN; an
    image already small enough is returned unchanged.

    The blocks are taken a band of block rows at a time (:data:`BAND_VALUES`), each band
    converted to float64 on its own; every block's sum is numpy's sum over the block's axes, as
    for the whole image at once, so the means are the same bits.

    Parameters
    ----------
    image : numpy.ndarray
        (H, W) or (H, W, C), float or integer.
    max_side : int
        The largest side allowed.
    scale : float, optional
        Multiply the values, taken as float64, by this first (``downsample(x, n, scale=c)`` is
        ``downsample(np.asarray(x, dtype=np.float64) * c, n)`` without the full-size product);
        the result is then float64 also when no shrinking is needed.

    Returns
    -------
    numpy.ndarray
        The shrunk image, float64 (or `image` itself).
    """
    h, w = image.shape[:2]
    s = math.ceil(max(h, w) / max_side)
    if s <= 1:
        return image if scale is None else np.asarray(image, dtype=np.float64) * scale
    hh, ww = h // s * s, w // s * s
    channels = math.prod(image.shape[2:])
    out = np.empty((hh // s, ww // s, *image.shape[2:]))
    rows = max(1, BAND_VALUES // max(s * ww * channels, 1))  # block rows a band
    for i in range(0, hh // s, rows):
        j = min(i + rows, hh // s)
        a = np.asarray(image[i * s : j * s, :ww], dtype=np.float64)
        if scale is not None:
            a = a * scale
        out[i:j] = _nan_block_means(a.reshape(j - i, s, ww // s, s, *a.shape[2:]))
    return out


def _nan_block_means(blocks: np.ndarray) -> np.ndarray:
    """Average the finite values of each block of a (rows, s, cols, s[, C]) array.

    NaN where a block has none: the reduction :func:`downsample` and :func:`_block_mean` share.
    """
    finite = np.isfinite(blocks)
    total = np.where(finite, blocks, 0.0).sum(axis=(1, 3))
    count = finite.sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def scale_bar_length(span: float, fraction: float = 0.25) -> float:
    """Return a round length for a scale bar: 1, 2 or 5 times a power of ten, near ``fraction * span``.

    Parameters
    ----------
    span : float
        The width of the picture in length units (positive).
    fraction : float, default 0.25
        The wanted share of the width; the length returned lies between ``fraction / 2.5`` and
        ``fraction * 2`` of `span` (the round number at or below ``fraction * span``).

    Returns
    -------
    float
        The length (NaN when `span` is not a positive finite number).
    """
    target = float(span) * float(fraction)
    if not (math.isfinite(target) and target > 0):
        return float("nan")
    power = 10.0 ** math.floor(math.log10(target))
    for step in (5.0, 2.0, 1.0):
        if step * power <= target * (1 + 1e-9):
            return step * power
    return power  # pragma: no cover - 1 * power <= target always


def pixel_footprint(rig: Any, depth: np.ndarray) -> tuple[float, float] | None:
    """Return a pixel's width on the surface in the rig's length unit, and the depth it holds at.

    A pinhole camera's pixel spans ``z / fx`` at depth ``z``: the mean of the finite values of
    `depth` is used (the object's mean depth; the footprint of nearer and farther parts differs
    by the ratio of their depths). An orthographic camera's pixel spans its ``pixel_size`` (x)
    at every depth.

    Parameters
    ----------
    rig : nplps.Rig
        The result's rig (its camera).
    depth : numpy.ndarray
        The result's depths (the ``(H + 1, W + 1)`` vertex grid; NaN where there is none).

    Returns
    -------
    (float, float) or None
        ``(footprint, mean depth)``, or None when there is no finite positive depth or the camera
        has neither ``K`` nor ``pixel_size``.
    """
    values = np.asarray(depth, dtype=np.float64)
    finite = values[np.isfinite(values)]
    mean = float(finite.mean()) if finite.size else float("nan")
    camera = getattr(rig, "camera", {}) or {}
    if camera.get("model") == "orthographic":
        size = float(camera["pixel_size"][0])
        return (size, mean) if math.isfinite(size) and size > 0 else None
    K = camera.get("K")
    if K is None or not (math.isfinite(mean) and mean > 0):
        return None
    fx = float(K[0][0])
    return (mean / fx, mean) if math.isfinite(fx) and fx > 0 else None


def view_axes(azimuth: float, elevation: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return the (right, down, forward) unit axes of a view, in the camera frame.

    Parameters
    ----------
    azimuth, elevation : float
        Degrees, as in :func:`render_mesh`.

    Returns
    -------
    (numpy.ndarray, numpy.ndarray, numpy.ndarray)
        The right axis r, the down axis d and the forward (viewing) axis f.
    """
    a, e = math.radians(azimuth), math.radians(elevation)
    f = np.array([-math.sin(a) * math.cos(e), math.sin(e), math.cos(a) * math.cos(e)])
    r = np.cross([0.0, 1.0, 0.0], f)
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    return r, d, f


def render_mesh(
    vertices: np.ndarray,
    mask: np.ndarray,
    *,
    azimuth: float = 0.0,
    elevation: float = 0.0,
    size: int = 512,
    albedo: np.ndarray | None = None,
    ambient: float = 0.15,
    key_light: tuple[float, float] | None = (20.0, 25.0),
    max_facets: int = 250_000,
) -> np.ndarray:
    """Render the mesh shaded from a turned viewpoint (see the module notes for the maths).

    Parameters
    ----------
    vertices : numpy.ndarray
        (H+1, W+1, 3) vertex positions in the camera frame (``Reconstruction.vertices``); NaN
        vertices are off the mesh.
    mask : numpy.ndarray
        (H, W) bool: the pixels whose quads make the mesh.
    azimuth : float, default 0
        Degrees the viewer turns about the vertical axis through the object's centre; positive
        to the camera's right.
    elevation : float, default 0
        Degrees the viewer rises above the object (positive: seen from above).
    size : int, default 512
        Width and height of the picture in pixels.
    albedo : numpy.ndarray, optional
        (H, W) or (H, W, 3) albedo to modulate the shading (normalized by its 99th percentile);
        default a uniform grey surface.
    ambient : float, default 0.15
        The share of ambient light.
    key_light : (float, float) or None, default (20, 25)
        Degrees to the left of and above the eye of the key light, which moves with the view;
        None: a headlight only (see the module notes).
    max_facets : int, default 250000
        Meshes with more masked pixels are decimated to about this many facets.

    Returns
    -------
    numpy.ndarray
        (size, size, 3) uint8 RGB picture, white background.

    Raises
    ------
    ValueError
        The shapes do not match.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    mask = np.asarray(mask, dtype=bool)
    h, w = mask.shape
    if vertices.shape != (h + 1, w + 1, 3):
        raise ValueError(f"vertices must have shape {(h + 1, w + 1, 3)} for a {mask.shape} mask, got {vertices.shape}")
    image = np.full((size, size, 3), _BACKGROUND, dtype=np.uint8)
    stride = max(1, math.ceil(math.sqrt(np.count_nonzero(mask) / max(max_facets, 1))))
    v = vertices[::stride, ::stride]
    hh, ww = (v.shape[0] - 1), (v.shape[1] - 1)
    if hh < 1 or ww < 1:
        return image
    cover = _block_mean(mask, stride, hh, ww)  # the mask as 0 / 1, a band at a time
    ok = np.isfinite(v).all(axis=-1)
    quad = (cover >= 0.5) & ok[:-1, :-1] & ok[:-1, 1:] & ok[1:, :-1] & ok[1:, 1:]
    if not quad.any():
        return image
    colour = _albedo_colour(albedo, stride, hh, ww)

    r_ax, d_ax, f_ax = view_axes(azimuth, elevation)
    centre = np.median(v[ok], axis=0)
    rel = v - centre
    px, py, pz = rel @ r_ax, rel @ d_ax, rel @ f_ax
    extent = max(np.ptp(px[ok]), np.ptp(py[ok]), 1e-12)
    scale = 0.9 * (size - 1) / extent
    cx = 0.5 * (px[ok].max() + px[ok].min())
    cy = 0.5 * (py[ok].max() + py[ok].min())
    sx = (px - cx) * scale + 0.5 * (size - 1)
    sy = (py - cy) * scale + 0.5 * (size - 1)

    # Facet normals (diagonals' cross product) and the shading (key, fill and ambient light).
    n = np.cross(v[1:, :-1] - v[:-1, 1:], v[1:, 1:] - v[:-1, :-1])[quad]
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
    facing = n @ f_ax  # < 0: the front side faces the viewer
    if key_light is None:
        light = ambient + (1.0 - ambient) * np.abs(facing)
    else:
        a, e = (math.radians(x) for x in key_light)
        to_key = -math.cos(e) * math.cos(a) * f_ax - math.cos(e) * math.sin(a) * r_ax - math.sin(e) * d_ax
        towards_viewer = np.where((facing > 0)[:, None], -n, n)
        key = np.clip(towards_viewer @ to_key, 0.0, None)
        light = ambient + (1.0 - ambient) * (0.7 * key + 0.3 * np.abs(facing))
    shade = light[:, None] * colour[quad]
    shade = np.where((facing > 0)[:, None], shade * _BACK_TINT, shade)

    rows, cols = np.nonzero(quad)
    corners = [(rows, cols), (rows, cols + 1), (rows + 1, cols + 1), (rows + 1, cols)]
    xs = np.stack([sx[c] for c in corners], axis=1)
    ys = np.stack([sy[c] for c in corners], axis=1)
    zs = np.stack([pz[c] for c in corners], axis=1)
    # Two triangles per quad: (0, 1, 2) and (0, 2, 3).
    tri_x = np.concatenate([xs[:, [0, 1, 2]], xs[:, [0, 2, 3]]])
    tri_y = np.concatenate([ys[:, [0, 1, 2]], ys[:, [0, 2, 3]]])
    tri_z = np.concatenate([zs[:, [0, 1, 2]], zs[:, [0, 2, 3]]])
    tri_shade = np.concatenate([shade, shade])
    zbuf = np.full(size * size, np.inf)
    owner = np.full(size * size, -1, dtype=np.intp)
    _rasterize(tri_x, tri_y, tri_z, size, zbuf, owner)
    hit = owner >= 0
    flat = image.reshape(-1, 3)
    flat[hit] = np.rint(np.clip(tri_shade[owner[hit]], 0.0, 1.0) * 255).astype(np.uint8)
    return image


def _block_mean(values: np.ndarray, s: int, hh: int, ww: int) -> np.ndarray:
    """Mean of each s x s block of an (H, W) array, on the (hh, ww) coarse grid (partial edge blocks kept).

    The values are taken as float64 (a boolean mask as 0 and 1), NaN ignored, a band of block
    rows at a time (:data:`BAND_VALUES`; each band padded with NaN past the array's edges): the
    same bits as padding and reducing the whole array at once, without its full-size float64
    copies.
    """
    h, w = values.shape[:2]
    ch, cw = min(h, hh * s), min(w, ww * s)
    channels = math.prod(values.shape[2:])
    out = np.empty((hh, ww, *values.shape[2:]))
    rows = max(1, BAND_VALUES // max(s * ww * s * channels, 1))  # block rows a band
    for i in range(0, hh, rows):
        j = min(i + rows, hh)
        padded = np.full(((j - i) * s, ww * s, *values.shape[2:]), np.nan)
        r1 = min(j * s, ch)
        if r1 > i * s:
            padded[: r1 - i * s, :cw] = values[i * s : r1, :cw]
        out[i:j] = _nan_block_means(padded.reshape(j - i, s, ww, s, *values.shape[2:]))
    return out


def _albedo_colour(albedo: np.ndarray | None, s: int, hh: int, ww: int) -> np.ndarray:
    """Per coarse facet RGB in [0, 1]: the albedo normalized by its 99th percentile, or 0.85 grey."""
    if albedo is None:
        return np.full((hh, ww, 3), 0.85)
    a = np.asarray(albedo, dtype=np.float64)
    a = a if a.ndim == 3 else a[..., None]
    finite = a[np.isfinite(a)]
    top = float(np.percentile(finite, 99)) if finite.size else 1.0
    coarse = _block_mean(a / (top if top > 0 else 1.0), s, hh, ww)
    coarse = np.clip(np.nan_to_num(coarse, nan=0.85), 0.0, 1.0)
    return np.broadcast_to(coarse, (hh, ww, 3)) if coarse.shape[-1] == 1 else coarse


def _rasterize(
    tx: np.ndarray,
    ty: np.ndarray,
    tz: np.ndarray,
    size: int,
    zbuf: np.ndarray,
    owner: np.ndarray,
    budget: int = 4_000_000,
) -> None:
    """Z-buffer the triangles (pixel centres at integer coordinates), in chunks of candidate pixels.

    Each triangle's bounding box is enumerated; a pixel is inside when its barycentric
    coordinates are all >= 0 (with a small tolerance, so shared edges leave no cracks). The
    nearest triangle per pixel wins: `zbuf` and `owner` (the triangle's index) are updated.
    """
    x0 = np.clip(np.ceil(tx.min(axis=1) - 1e-9), 0, size - 1).astype(np.int64)
    x1 = np.clip(np.floor(tx.max(axis=1) + 1e-9), 0, size - 1).astype(np.int64)
    y0 = np.clip(np.ceil(ty.min(axis=1) - 1e-9), 0, size - 1).astype(np.int64)
    y1 = np.clip(np.floor(ty.max(axis=1) + 1e-9), 0, size - 1).astype(np.int64)
    bw = np.maximum(x1 - x0 + 1, 0)
    bh = np.maximum(y1 - y0 + 1, 0)
    area = (tx[:, 1] - tx[:, 0]) * (ty[:, 2] - ty[:, 0]) - (tx[:, 2] - tx[:, 0]) * (ty[:, 1] - ty[:, 0])
    count = np.where(np.abs(area) > 1e-12, bw * bh, 0)
    ends = np.cumsum(count)
    first = 0
    while first < len(count):
        last = int(np.searchsorted(ends, (ends[first - 1] if first else 0) + budget, side="right"))
        last = max(last, first + 1)
        sel = np.arange(first, last)
        c = count[sel]
        tri = np.repeat(sel, c)
        if tri.size:
            offset = np.arange(tri.size) - np.repeat(np.cumsum(c) - c, c)
            px = x0[tri] + offset % bw[tri]
            py = y0[tri] + offset // bw[tri]
            ax, ay = tx[tri, 0], ty[tri, 0]
            e1x, e1y = tx[tri, 1] - ax, ty[tri, 1] - ay
            e2x, e2y = tx[tri, 2] - ax, ty[tri, 2] - ay
            qx, qy = px - ax, py - ay
            a = area[tri]
            b1 = (qx * e2y - qy * e2x) / a
            b2 = (e1x * qy - e1y * qx) / a
            eps = 1e-6
            inside = (b1 >= -eps) & (b2 >= -eps) & (b1 + b2 <= 1 + eps)
            tri, px, py, b1, b2 = tri[inside], px[inside], py[inside], b1[inside], b2[inside]
            z = tz[tri, 0] * (1 - b1 - b2) + tz[tri, 1] * b1 + tz[tri, 2] * b2
            pix = py * size + px
            order = np.lexsort((z, pix))  # by pixel, then nearest first
            pix, z, tri = pix[order], z[order], tri[order]
            keep = np.ones(pix.size, dtype=bool)
            keep[1:] = pix[1:] != pix[:-1]
            pix, z, tri = pix[keep], z[keep], tri[keep]
            closer = z < zbuf[pix]
            zbuf[pix[closer]] = z[closer]
            owner[pix[closer]] = tri[closer]
        first = last
