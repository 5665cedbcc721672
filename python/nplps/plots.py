"""Small dependency-free plots (SVG) of solver diagnostics."""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from ._atomic import write_text

__all__ = ["convergence_svg", "residual_curve_svg"]

_COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b")


def residual_curve_svg(
    curves: Sequence[np.ndarray],
    estimates: Sequence[float],
    path: str | os.PathLike[str] | None = None,
    *,
    width: int = 640,
    height: int = 400,
) -> str:
    """Plot the photometric residual against the working distance as SVG.

    Log-log axes, one line per region, each region's estimate marked by a dashed line.

    Parameters
    ----------
    curves : sequence of numpy.ndarray
        Per region, an (N, 2) array of (distance, residual) (see ``DistanceEstimate.curve``).
    estimates : sequence of float
        The estimated distance of each region.
    path : str or path-like, optional
        The SVG file to write (none by default).
    width, height : int, default 640, 400
        Size of the picture in pixels.

    Returns
    -------
    str
        The SVG document.

    Raises
    ------
    ValueError
        No point is finite and positive.
    """
    pts = np.vstack([c for c in curves if len(c)])
    finite = pts[np.all(np.isfinite(pts), axis=1) & np.all(pts > 0, axis=1)]
    if finite.size == 0:
        raise ValueError("no finite positive point to plot")
    lx, ly = np.log10(finite[:, 0]), np.log10(finite[:, 1])
    x0, x1 = lx.min(), lx.max() + 1e-12
    y0, y1 = ly.min(), ly.max() + 1e-12
    left, right, top, bottom = 70, 20, 30, 50
    sx = lambda v: left + (np.log10(v) - x0) / (x1 - x0) * (width - left - right)  # noqa: E731
    sy = lambda v: height - bottom - (np.log10(v) - y0) / (y1 - y0) * (height - top - bottom)  # noqa: E731
    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
        'font-family="sans-serif" font-size="12">',
        '<rect width="100%" height="100%" fill="white"/>',
        f'<line x1="{left}" y1="{height - bottom}" x2="{width - right}" y2="{height - bottom}" stroke="black"/>',
        f'<line x1="{left}" y1="{top}" x2="{left}" y2="{height - bottom}" stroke="black"/>',
        f'<text x="{(width + left - right) / 2}" y="{height - 12}" text-anchor="middle">working distance (log)</text>',
        f'<text x="16" y="{(height + top - bottom) / 2}" transform="rotate(-90 16 {(height + top - bottom) / 2})" '
        'text-anchor="middle">residual (log)</text>',
        f'<text x="{left}" y="{height - bottom + 16}">{10**x0:.4g}</text>',
        f'<text x="{width - right}" y="{height - bottom + 16}" text-anchor="end">{10**x1:.4g}</text>',
        f'<text x="{left - 4}" y="{height - bottom}" text-anchor="end">{10**y0:.3g}</text>',
        f'<text x="{left - 4}" y="{top + 4}" text-anchor="end">{10**y1:.3g}</text>',
    ]
    for r, (curve, estimate) in enumerate(zip(curves, estimates, strict=False)):
        color = _COLORS[r % len(_COLORS)]
        ok = curve[np.all(np.isfinite(curve), axis=1) & np.all(curve > 0, axis=1)]
        line = " ".join(f"{sx(d):.1f},{sy(e):.1f}" for d, e in ok)
        parts.append(f'<polyline fill="none" stroke="{color}" stroke-width="1.5" points="{line}"/>')
        parts.append(
            f'<line x1="{sx(estimate):.1f}" y1="{top}" x2="{sx(estimate):.1f}" y2="{height - bottom}" '
            f'stroke="{color}" stroke-dasharray="4 3"/>'
        )
        parts.append(
            f'<text x="{sx(estimate) + 4:.1f}" y="{top + 14 + 14 * r}" fill="{color}">region {r}: {estimate:.4g}</text>'
        )
    parts.append("</svg>")
    text = "\n".join(parts) + "\n"
    if path is not None:
        write_text(path, text)
    return text


def convergence_svg(
    depth_changes: Sequence[float],
    levels: Sequence[int] | None = None,
    *,
    width: int = 640,
    height: int = 320,
) -> str:
    """Plot the largest depth change of each iteration on a log scale, as SVG.

    One point per iteration in the order run; with a coarse-to-fine pyramid, each level is a line
    of its own colour, labelled by its level (0 = full resolution).

    Parameters
    ----------
    depth_changes : sequence of float
        The depth change of each iteration (scene units); non-positive or non-finite values are
        left out.
    levels : sequence of int, optional
        The pyramid level of each iteration (default all 0).
    width, height : int, default 640, 320
        Size of the picture in pixels.

    Returns
    -------
    str
        The SVG document.

    Raises
    ------
    ValueError
        No value is finite and positive.
    """
    d = np.asarray(depth_changes, dtype=np.float64)
    lv = np.zeros(len(d), dtype=np.int64) if levels is None else np.asarray(levels, dtype=np.int64)
    good = np.isfinite(d) & (d > 0)
    if not good.any():
        raise ValueError("no finite positive depth change to plot")
    ly = np.log10(d[good])
    y0, y1 = np.floor(ly.min()), np.ceil(ly.max())
    if y1 <= y0:
        y1 = y0 + 1
    left, right, top, bottom = 70, 70, 20, 45
    n = len(d)
    sx = lambda i: left + (i / max(n - 1, 1)) * (width - left - right)  # noqa: E731
    sy = lambda v: height - bottom - (np.log10(v) - y0) / (y1 - y0) * (height - top - bottom)  # noqa: E731
    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
        'font-family="sans-serif" font-size="12">',
        '<rect width="100%" height="100%" fill="white"/>',
    ]
    for e in range(int(y0), int(y1) + 1):  # decade grid lines and labels
        y = sy(10.0**e)
        parts.append(f'<line x1="{left}" y1="{y:.1f}" x2="{width - right}" y2="{y:.1f}" stroke="#ddd"/>')
        parts.append(f'<text x="{left - 4}" y="{y + 4:.1f}" text-anchor="end">1e{e}</text>')
    parts += [
        f'<line x1="{left}" y1="{height - bottom}" x2="{width - right}" y2="{height - bottom}" stroke="black"/>',
        f'<line x1="{left}" y1="{top}" x2="{left}" y2="{height - bottom}" stroke="black"/>',
        f'<text x="{left}" y="{height - bottom + 16}">1</text>',
        f'<text x="{width - right}" y="{height - bottom + 16}" text-anchor="end">{n}</text>',
        f'<text x="{(width + left - right) / 2}" y="{height - 10}" text-anchor="middle">'
        "iteration (in the order run)</text>",
        f'<text x="16" y="{(height + top - bottom) / 2}" transform="rotate(-90 16 {(height + top - bottom) / 2})" '
        'text-anchor="middle">largest depth change (log)</text>',
    ]
    for k, level in enumerate(dict.fromkeys(lv.tolist())):
        color = _COLORS[k % len(_COLORS)]
        idx = [i for i in range(n) if lv[i] == level and good[i]]
        pts = " ".join(f"{sx(i):.1f},{sy(d[i]):.1f}" for i in idx)
        parts.append(f'<polyline fill="none" stroke="{color}" stroke-width="1.5" points="{pts}"/>')
        parts += [f'<circle cx="{sx(i):.1f}" cy="{sy(d[i]):.1f}" r="2.5" fill="{color}"/>' for i in idx]
        if idx:
            parts.append(
                f'<text x="{sx(idx[-1]) + 4:.1f}" y="{sy(d[idx[-1]]) - 4:.1f}" fill="{color}">level {level}</text>'
            )
    parts.append("</svg>")
    return "\n".join(parts) + "\n"
