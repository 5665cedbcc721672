"""Small dependency-free plots (SVG) of solver diagnostics."""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from ._atomic import write_text

__all__ = ["residual_curve_svg"]

_COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b")


def residual_curve_svg(
    curves: Sequence[np.ndarray],
    estimates: Sequence[float],
    path: str | os.PathLike[str],
    *,
    width: int = 640,
    height: int = 400,
) -> None:
    """Plot the photometric residual against the working distance as an SVG file.

    Log-log axes, one line per region, each region's estimate marked by a dashed line.

    Parameters
    ----------
    curves : sequence of numpy.ndarray
        Per region, an (N, 2) array of (distance, RMS residual).
    estimates : sequence of float
        The estimated distance of each region.
    path : str or path-like
        The SVG file to write.
    width, height : int, default 640, 400
        Size of the picture in pixels.

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
        'text-anchor="middle">RMS residual (log)</text>',
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
    write_text(path, "\n".join(parts) + "\n")
