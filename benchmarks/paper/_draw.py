"""Pictures for benchmarks/paper: colour-mapped PNGs (numpy + imageio) and inline SVG plots."""

from __future__ import annotations

import base64
import html
import io
from collections.abc import Sequence
from pathlib import Path

import imageio.v3 as iio
import numpy as np

__all__ = ["colorbar_svg", "colorize", "curves_svg", "data_uri", "png_bytes", "row", "shaded"]

# Anchors of the error colour map (blue -> cyan -> green -> yellow -> red), as the paper's error
# maps read from the text (blue small, red large); our own choice of anchors.
_ANCHORS = np.array(
    [
        [0.00, 0.05, 0.10, 0.55],
        [0.20, 0.10, 0.45, 0.95],
        [0.40, 0.10, 0.85, 0.85],
        [0.60, 0.45, 0.90, 0.25],
        [0.80, 1.00, 0.80, 0.10],
        [1.00, 0.80, 0.05, 0.05],
    ]
)
_COLORS = {"near": "#d62728", "parallel": "#1f77b4", "poisson": "#2ca02c", "robust": "#9467bd", "dgp": "#1f77b4"}


def colorize(values: np.ndarray, vmax: float, *, vmin: float = 0.0) -> np.ndarray:
    """Map an (H, W) array to RGB uint8 with the error colour map; NaN is light grey."""
    t = np.clip((np.nan_to_num(values, nan=vmin) - vmin) / max(vmax - vmin, 1e-300), 0.0, 1.0)
    rgb = np.stack([np.interp(t, _ANCHORS[:, 0], _ANCHORS[:, c]) for c in (1, 2, 3)], axis=-1)
    rgb[~np.isfinite(values)] = 0.85
    return np.asarray(np.round(rgb * 255), dtype=np.uint8)


def shaded(normals: np.ndarray) -> np.ndarray:
    """Normal map as RGB uint8, (n_x, -n_y, -n_z) -> (v + 1) / 2 as the package's normals.png."""
    v = np.nan_to_num(normals * np.array([1.0, -1.0, -1.0]), nan=0.0)
    return np.asarray(np.round((v + 1.0) * 127.5), dtype=np.uint8)


def row(images: Sequence[np.ndarray], *, gap: int = 4, scale: int = 1) -> np.ndarray:
    """Place RGB uint8 images side by side on white, each enlarged ``scale`` times (nearest)."""
    big = [np.repeat(np.repeat(im, scale, axis=0), scale, axis=1) for im in images]
    height = max(im.shape[0] for im in big)
    width = sum(im.shape[1] for im in big) + gap * (len(big) - 1)
    out = np.full((height, width, 3), 255, dtype=np.uint8)
    x = 0
    for im in big:
        out[: im.shape[0], x : x + im.shape[1]] = im
        x += im.shape[1] + gap
    return out


def png_bytes(image: np.ndarray) -> bytes:
    """Encode an RGB uint8 image as PNG."""
    buf = io.BytesIO()
    iio.imwrite(buf, image, extension=".png")
    return buf.getvalue()


def data_uri(path: Path) -> str:
    """A data: URI of a PNG file (to embed it in the HTML page)."""
    return "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode("ascii")


def colorbar_svg(vmax: float, label: str, *, width: int = 420, ticks: int = 5) -> str:
    """A horizontal colour bar from 0 to ``vmax`` as inline SVG."""
    stops = "".join(
        f'<stop offset="{a[0]:.2f}" stop-color="rgb({int(a[1] * 255)},{int(a[2] * 255)},{int(a[3] * 255)})"/>'
        for a in _ANCHORS
    )
    x0, x1 = 10, width - 10
    parts = [
        f'<div><svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="54" '
        'font-family="sans-serif" font-size="11">',
        f'<defs><linearGradient id="cb{int(vmax * 1000)}">{stops}</linearGradient></defs>',
        f'<rect x="{x0}" y="4" width="{x1 - x0}" height="14" fill="url(#cb{int(vmax * 1000)})" stroke="black"/>',
    ]
    for i in range(ticks + 1):
        x = x0 + (x1 - x0) * i / ticks
        parts.append(f'<line x1="{x:.1f}" y1="18" x2="{x:.1f}" y2="22" stroke="black"/>')
        parts.append(f'<text x="{x:.1f}" y="33" text-anchor="middle">{vmax * i / ticks:.3g}</text>')
    parts.append(f'<text x="{width / 2}" y="48" text-anchor="middle">{html.escape(label)}</text></svg></div>')
    return "".join(parts)


def curves_svg(
    series: Sequence[tuple[str, str, np.ndarray, np.ndarray, np.ndarray | None]],
    *,
    xlabel: str,
    ylabel: str,
    title: str = "",
    width: int = 460,
    height: int = 320,
    ymax: float | None = None,
    logy: bool = False,
) -> str:
    """A line plot (linear x, linear or log y) as inline SVG.

    ``series``: (label, colour key or #rgb, x, y, spread or None); the spread is drawn as error bars
    (y - spread .. y + spread). With ``logy``, values are floored at 1e-6 of the largest.
    """
    if logy:
        top = max(float(np.nanmax(s[3])) for s in series)
        floor = 1e-6 * top
        series = [(a, b, x, np.log10(np.maximum(y, floor)), None) for a, b, x, y, _ in series]
    xs = np.concatenate([s[2] for s in series])
    tops = [s[3] + (s[4] if s[4] is not None else 0.0) for s in series]
    x0, x1 = 0.0, float(xs.max()) * 1.05
    y0 = float(np.floor(min(float(np.nanmin(s[3])) for s in series))) if logy else 0.0
    y1 = ymax if ymax is not None else float(np.nanmax(np.concatenate(tops))) * 1.1 + 1e-9
    if logy:
        y1 = float(np.ceil(y1 / 1.1))
    left, right, top, bottom = 56, 14, 26 if title else 12, 44
    sx = lambda v: left + (v - x0) / (x1 - x0) * (width - left - right)  # noqa: E731
    sy = lambda v: height - bottom - (min(v, y1) - y0) / (y1 - y0) * (height - top - bottom)  # noqa: E731
    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" font-family="sans-serif" '
        'font-size="11">',
        '<rect width="100%" height="100%" fill="white"/>',
    ]
    if title:
        parts.append(f'<text x="{width / 2}" y="16" text-anchor="middle" font-size="13">{html.escape(title)}</text>')
    yticks = np.arange(np.floor(y0), np.ceil(y1) + 0.5) if logy else y0 + (y1 - y0) * np.arange(6) / 5
    if logy and len(yticks) > 8:
        yticks = yticks[:: int(np.ceil(len(yticks) / 8))]
    for yv in yticks:
        parts.append(
            f'<line x1="{left}" y1="{sy(yv):.1f}" x2="{width - right}" y2="{sy(yv):.1f}" stroke="#ddd"/>'
            f'<text x="{left - 4}" y="{sy(yv) + 4:.1f}" text-anchor="end">{10**yv if logy else yv:.3g}</text>'
        )
    xticks = np.unique(np.round(xs, 6))
    if len(xticks) > 12 or np.min(np.diff(xticks), initial=x1) / (x1 - x0) * (width - left - right) < 28:
        step = 10 ** np.floor(np.log10(x1 / 5))
        step *= 2 if x1 / step > 10 else 1
        xticks = np.arange(0.0, x1, step)
    for xv in xticks:
        parts.append(f'<text x="{sx(xv):.1f}" y="{height - bottom + 14}" text-anchor="middle">{xv:.3g}</text>')
    parts += [
        f'<line x1="{left}" y1="{height - bottom}" x2="{width - right}" y2="{height - bottom}" stroke="black"/>',
        f'<line x1="{left}" y1="{top}" x2="{left}" y2="{height - bottom}" stroke="black"/>',
        f'<text x="{(width + left - right) / 2}" y="{height - 8}" text-anchor="middle">{html.escape(xlabel)}</text>',
        f'<text x="14" y="{(height + top - bottom) / 2}" transform="rotate(-90 14 {(height + top - bottom) / 2})" '
        f'text-anchor="middle">{html.escape(ylabel)}</text>',
    ]
    for k, (label, color, x, y, spread) in enumerate(series):
        c = _COLORS.get(color, color)
        pts = " ".join(f"{sx(a):.1f},{sy(b):.1f}" for a, b in zip(x, y, strict=True) if np.isfinite(b))
        parts.append(f'<polyline fill="none" stroke="{c}" stroke-width="1.8" points="{pts}"/>')
        dash = ' stroke-dasharray="5 4"' if color == "#000000" else ""
        if dash:
            parts[-1] = parts[-1].replace("/>", f"{dash}/>")
        for i, (a, b) in enumerate(zip(x, y, strict=True)):
            if len(x) <= 30:
                parts.append(f'<circle cx="{sx(a):.1f}" cy="{sy(b):.1f}" r="2.6" fill="{c}"/>')
            if spread is not None and spread[i] > 0:
                parts.append(
                    f'<line x1="{sx(a):.1f}" y1="{sy(b - spread[i]):.1f}" x2="{sx(a):.1f}" '
                    f'y2="{sy(b + spread[i]):.1f}" stroke="{c}"/>'
                )
        parts.append(
            f'<line x1="{left + 10}" y1="{top + 10 + 15 * k}" x2="{left + 30}" y2="{top + 10 + 15 * k}" '
            f'stroke="{c}" stroke-width="2"{dash}/>'
            f'<text x="{left + 34}" y="{top + 14 + 15 * k}">{html.escape(label)}</text>'
        )
    parts.append("</svg>")
    return "".join(parts)
