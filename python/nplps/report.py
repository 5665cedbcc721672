"""The report of a result: one self-contained ``report.html`` to look at and share.

:func:`write_report` makes it from the files of a result directory (what
:meth:`nplps.Reconstruction.save` and ``nplps reconstruct`` write), so that ``nplps report DIR``
re-makes it at any time. Every picture is embedded as a ``data:`` URI or inline SVG: the file
needs no network, no script and no other file. Its sections, in order:

1. a header: the capture (the images or ``--capture`` folder, when the options were recorded),
   the directory, the size "W x H", the number of lights, status, iterations and solver time;
2. the inputs (a contact sheet, ``inputs.png``, written when the images were given to ``save``);
3. the mask, the normal map (as written: its convention and bit depth from ``summary.json``'s
   ``"normal_map"``), the albedo (and, under the glossy model, the specular albedo; the header
   then names the model and its lobe);
4. the residual map (RMS image residual per pixel) and the depth map, colour-mapped, each with
   a numeric colour bar; the unfitted pixels (masked pixels with fewer than 3 lit images, which
   kept their starting shape). The normal, albedo and depth maps have a scale bar: a round
   length in ``summary.json``'s ``"units"`` ("rig units" without) at the object's mean depth
   (:func:`nplps.views.pixel_footprint`);
5. three oblique shaded renders of the mesh (:func:`nplps.views.render_mesh`): turned 35
   degrees to the left and to the right about the vertical axis through the object's centre,
   and seen from 35 degrees above;
6. the convergence history (the largest depth change of each iteration, log scale), the
   distance curve (``depth="auto"``) and the held-out table with its reading (when
   ``held_out.json`` exists), the normal-uncertainty and leave-one-light-out maps with the
   per-light table (``normal_sigma.tiff``, ``held_out_error.tiff``, ``trust`` in
   ``summary.json``; docs/trust.md);
7. the timings, all the options used (when recorded) and the rest of ``summary.json``.

A section without data says so in one line.

Files the report reads (all written by ``save``): ``summary.json`` (required), ``depth.npy``,
``normals.png``, ``albedo.png``, ``residual.npy``, ``mask.png``, ``lights_used.npy``,
``history.csv``, ``rig.json``; and, when present, ``inputs.png``, ``distance_curve.csv``,
``held_out.json`` (:func:`held_out_record`) and, for the glossy model, ``specular.png``.
"""

from __future__ import annotations

import base64
import html
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import tifffile

from . import _core, _results, export, plots, views
from ._atomic import write_text
from ._outdir import add_to_manifest
from .errors import InputError
from .export import contact_sheet, held_out_record, history_csv

if TYPE_CHECKING:
    from ._held_out import HeldOutScores
    from ._records import Result

__all__ = [
    "REPORT_NAME",
    "compact_html",
    "contact_sheet",
    "held_out_record",
    "history_csv",
    "png_data_uri",
    "report_html",
    "write_held_out",
    "write_report",
]

#: The report's file name in a result directory.
REPORT_NAME = "report.html"

#: Longest side of the maps embedded in the report (pixels); larger maps are shrunk.
MAP_SIDE = 640

#: Width and height of each oblique render (pixels).
RENDER_SIZE = 420

#: The oblique views: (title, azimuth, elevation) in degrees (see :func:`nplps.views.render_mesh`).
VIEWS = (
    ("turned 35° to the left", -35.0, 0.0),
    ("turned 35° to the right", 35.0, 0.0),
    ("seen from 35° above", 0.0, 35.0),
)

#: The .npy files the report reads: allowed dtype kinds and the shape after (H, W) (the vertex
#: grid (H + 1, W + 1) for depth.npy).
_NPY_FILES: dict[str, tuple[str, tuple[int, ...]]] = {
    "depth.npy": ("f", ()),
    "residual.npy": ("f", ()),
    "normals.npy": ("f", (3,)),
    "lights_used.npy": ("iu", ()),
}

_STYLE = """
body{font-family:sans-serif;margin:1.5em;color:#222;max-width:1400px}
h1{font-size:1.4em}h2{font-size:1.15em;border-bottom:1px solid #ccc;margin-top:1.6em}
table{border-collapse:collapse}td,th{padding:2px 10px;text-align:left;vertical-align:top;border-bottom:1px solid #eee}
figure{display:inline-table;margin:0 1em 1em 0;vertical-align:top}
figcaption{display:table-caption;caption-side:bottom;font-size:.9em;color:#555}
img{image-rendering:pixelated;max-width:100%;border:1px solid #ccc}.none{color:#777;font-style:italic}
code{font-size:.9em;word-break:break-all}
"""


# --------------------------------------------------------------------------------------------------
# Pictures
# --------------------------------------------------------------------------------------------------


def png_data_uri(pixels: np.ndarray) -> str:
    """Return an image as a ``data:image/png;base64,...`` URI.

    Parameters
    ----------
    pixels : numpy.ndarray
        (H, W) or (H, W, 3) uint8.

    Returns
    -------
    str
        The URI, for an ``<img src=...>``.
    """
    import imageio.v3 as iio

    data = iio.imwrite("<bytes>", np.ascontiguousarray(pixels, dtype=np.uint8), extension=".png")
    return "data:image/png;base64," + base64.b64encode(data).decode("ascii")


def _grey_rgb(values: np.ndarray) -> np.ndarray:
    """Scale values by their 99.5th percentile into 8-bit (NaN black), as the exported maps are scaled."""
    return export._quantize(values, 99.5, 255, np.uint8)[0]


#: Small maps are shown enlarged by a whole factor (pixelated) until their longer side reaches this.
MIN_SIDE = 320


def _zoom(shape: tuple[int, ...], min_side: int = MIN_SIDE) -> int:
    """Return the whole factor by which a picture of `shape` is shown (1 for large ones)."""
    return max(1, min_side // max(shape[0], shape[1], 1))


def _img(pixels: np.ndarray, alt: str, zoom: bool = True) -> str:
    f = _zoom(pixels.shape) if zoom else 1
    size = f' width="{pixels.shape[1] * f}" height="{pixels.shape[0] * f}"'
    return f'<img src="{png_data_uri(pixels)}" alt="{html.escape(alt)}"{size}>'


def _figure(pixels: np.ndarray, caption: str, zoom: bool = True, scale: str = "") -> str:
    return f"<figure>{_img(pixels, caption, zoom)}{scale}<figcaption>{html.escape(caption)}</figcaption></figure>"


def _scale_bar(d: _Data, shape: tuple[int, ...], shown: tuple[int, ...]) -> str:
    """Return a scale bar (inline SVG) for a map of `shape` pixels (cropped, full size) shown as `shown`.

    Its length is a round number of the rig's unit (:func:`nplps.views.scale_bar_length`, about a
    quarter of the map's width) at the object's mean depth (:func:`nplps.views.pixel_footprint`);
    ``data-length``, ``data-units`` and ``data-pixels`` (its length in picture pixels) say what it
    shows. "" when the footprint is unknown (no rig.json or depth.npy).
    """
    footprint = d.footprint
    if footprint is None or not shape[1] or not shown[1]:
        return ""
    size, mean = footprint
    zoom = _zoom(shown)
    per_pixel = size * shape[1] / shown[1] / zoom  # length units per picture pixel
    length = views.scale_bar_length(shown[1] * zoom * per_pixel)
    if not np.isfinite(length):
        return ""
    bar = length / per_pixel
    label = f"{length:g} {d.units}"
    title = f"{label} at the mean depth {_fmt(mean)} {d.units} (a pixel spans {_fmt(size)} {d.units} there)"
    return (
        f'<svg xmlns="http://www.w3.org/2000/svg" class="scalebar" style="display:block" '
        f'width="{bar + 12 + 7 * len(label):.0f}" '
        f'height="20" data-length="{length!r}" data-units="{html.escape(d.units)}" data-pixels="{bar:.2f}" '
        f'font-family="sans-serif" font-size="11"><title>{html.escape(title)}</title>'
        f'<rect x="0" y="6" width="{bar:.2f}" height="5" fill="black"/>'
        f'<text x="{bar + 6:.2f}" y="14">{html.escape(label)}</text></svg>'
    )


def _colorbar_svg(lo: float, hi: float, label: str, *, height: int = 300) -> str:
    """Return a vertical colour bar with its numbers as inline SVG (``data-min``, ``data-max``: the range)."""
    ticks = views.colorbar_ticks(lo, hi)
    stops = "".join(
        f'<stop offset="{t:.3f}" stop-color="rgb({r},{g},{b})"/>'
        for t, (r, g, b) in zip(
            np.linspace(0, 1, 17), np.rint(views.colormap(np.linspace(1, 0, 17)) * 255).astype(int), strict=True
        )
    )
    top, bar_h, x = 24, height - 32, 8
    gid = "cb-" + "".join(c if c.isalnum() else "-" for c in label)  # one bar per label in a report
    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" class="colorbar" width="150" height="{height}" '
        f'data-min="{lo!r}" data-max="{hi!r}" font-family="sans-serif" font-size="11">',
        f'<defs><linearGradient id="{gid}" x1="0" y1="0" x2="0" y2="1">{stops}</linearGradient></defs>',
        f'<rect x="{x}" y="{top}" width="18" height="{bar_h}" fill="url(#{gid})" stroke="black"/>',
    ]
    span = hi - lo if hi > lo else 1.0
    for t in ticks:
        y = top + (1 - (t - lo) / span) * bar_h
        parts.append(f'<line x1="{x + 18}" y1="{y:.1f}" x2="{x + 23}" y2="{y:.1f}" stroke="black"/>')
        parts.append(f'<text class="tick" x="{x + 26}" y="{y + 4:.1f}">{_fmt(t)}</text>')
    parts.append(f'<text x="{x}" y="12">{html.escape(label)}</text></svg>')
    return "".join(parts)


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{float(v):.4g}"


def _none(text: str) -> str:
    return f'<p class="none">{html.escape(text)}</p>'


# --------------------------------------------------------------------------------------------------
# The report
# --------------------------------------------------------------------------------------------------


def write_report(directory: str | os.PathLike[str], *, path: str | os.PathLike[str] | None = None) -> Path:
    """Make ``report.html`` from the files of a result directory.

    Parameters
    ----------
    directory : str or path-like
        A result directory written by :meth:`nplps.Reconstruction.save` or ``nplps reconstruct``.
    path : str or path-like, optional
        Where to write the report (default ``directory/report.html``; then the directory's
        manifest lists it).

    Returns
    -------
    pathlib.Path
        The report's path.

    Raises
    ------
    InputError
        `directory` holds no ``summary.json`` (it is not a result directory).
    OSError
        The report could not be written.

    Examples
    --------
    >>> import nplps, tempfile
    >>> scene = nplps.make_scene("sphere", n=24)
    >>> result = nplps.reconstruct(scene.images, scene.rig, depth=scene.mean_depth, mask=scene.mask)
    >>> out = tempfile.mkdtemp()
    >>> _ = result.save(out, overwrite=True)
    >>> write_report(out).name
    'report.html'
    """
    root = Path(directory)
    target = root / REPORT_NAME if path is None else Path(path)
    write_text(target, report_html(root))
    if path is None:
        add_to_manifest(root, REPORT_NAME)
    return target


def write_held_out(
    directory: str | os.PathLike[str], near: Sequence[HeldOutScores], parallel: Sequence[HeldOutScores] | None = None
) -> Path:
    """Add a held-out evaluation to a result directory and re-make its report.

    Writes ``held_out.json`` (:func:`held_out_record`), lists it in the directory's manifest and
    re-makes ``report.html`` (:func:`write_report`), whose held-out section then shows the table
    and its reading. ``nplps evaluate --out DIR`` calls it.

    Parameters
    ----------
    directory : str or path-like
        A result directory written by :meth:`nplps.Reconstruction.save` or ``nplps reconstruct``.
    near : sequence of HeldOut
        :func:`nplps.evaluation.held_out` of the near-light method.
    parallel : sequence of HeldOut, optional
        The same lights left out with ``method="parallel"``.

    Returns
    -------
    pathlib.Path
        The path of ``held_out.json``.

    Raises
    ------
    InputError
        `directory` holds no ``summary.json`` (it is not a result directory).
    """
    root = Path(directory)
    if not (root / "summary.json").is_file():
        raise InputError(f"'{root}' is not a result directory (it has no summary.json): run nplps reconstruct first")
    target = root / "held_out.json"
    write_text(target, json.dumps(held_out_record(near, parallel), indent=2) + "\n")
    add_to_manifest(root, target.name)
    write_report(root)
    return target


def report_html(directory: str | os.PathLike[str]) -> str:
    """Return the report of a result directory as HTML text (see the module notes).

    Parameters
    ----------
    directory : str or path-like
        The result directory.

    Returns
    -------
    str
        A self-contained HTML document.

    Raises
    ------
    InputError
        `directory` holds no readable ``summary.json``.
    """
    root = Path(directory)
    d = _Data(root, _results.read_summary(root))
    sections = [
        _section_header(d),
        _section_inputs(d),
        _section_maps(d),
        _section_residual(d),
        _section_unfitted(d),
        _section_depth(d),
        _section_renders(d),
        _section_convergence(d),
        _section_distance(d),
        _section_held_out(d),
        _section_trust(d),
        _section_options(d),
    ]
    title = html.escape(f"nplps report: {d.name}")
    return (
        f"<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'><title>{title}</title>"
        f"<style>{_STYLE}</style></head><body>\n" + "\n".join(sections) + "\n</body></html>\n"
    )


class _Data:
    """The files of a result directory, read on first use (None when missing or unreadable)."""

    def __init__(self, root: Path, summary: dict[str, Any]) -> None:
        self.root = root
        self.summary = summary
        self.options: dict[str, Any] = summary.get("options") or {}
        self.shape: tuple[int, int] = (int(summary["shape"][0]), int(summary["shape"][1]))
        self.name = root.resolve().name or os.fspath(root)
        self._cache: dict[str, Any] = {}

    def _load(self, name: str) -> Any:
        """Return the checked contents of a file of the directory, or None when it is missing.

        A file that is there but damaged (wrong type, shape or size, truncated) raises
        :class:`InputError` naming it (:mod:`nplps._results`).
        """
        if name in self._cache:
            return self._cache[name]
        p = self.root / name
        value: Any = None
        if os.path.lexists(p):
            h, w = self.shape
            if name in _NPY_FILES:
                kinds, extra = _NPY_FILES[name]
                grid = (h + 1, w + 1) if name == "depth.npy" else (h, w)
                limit = _results.MAX_COORDINATE if name == "depth.npy" else None
                value = _results.read_npy(p, kinds=kinds, shape=grid + extra, max_abs=limit)
            elif name == "inputs.png":
                value = _results.read_png(p)
            elif name.endswith(".png"):
                value = _results.read_png(p, shape=(h, w))
            elif name == "history.csv":
                value = _results.read_history(p)
            elif name == "distance_curve.csv":
                value = _results.read_distance_curve(p)
            elif name == "held_out.json":
                value = _results.read_held_out(p)
            else:  # pragma: no cover - every file the report reads is listed above
                raise ValueError(f"no reader for {name}")
        self._cache[name] = value
        return value

    @property
    def mask(self) -> np.ndarray | None:
        m = self._load("mask.png")
        if m is not None:
            return np.asarray(m).reshape((*m.shape[:2], -1))[..., 0] > 0
        n = self._load("normals.npy")
        return None if n is None else np.isfinite(n).all(axis=-1)

    @property
    def box(self) -> tuple[int, int, int, int] | None:
        """Return the mask's bounding box with a margin (r0, r1, c0, c1), or None for the whole image."""
        if "box" not in self._cache:
            mask, box = self.mask, None
            if mask is not None and mask.any():
                rows, cols = np.nonzero(mask.any(axis=1))[0], np.nonzero(mask.any(axis=0))[0]
                h, w = mask.shape
                m = max(2, int(0.04 * max(rows[-1] - rows[0], cols[-1] - cols[0])))
                box = (max(rows[0] - m, 0), min(rows[-1] + 1 + m, h), max(cols[0] - m, 0), min(cols[-1] + 1 + m, w))
                if box == (0, h, 0, w):
                    box = None
            self._cache["box"] = box
        return self._cache["box"]

    def cropped(self, image: np.ndarray, vertex: bool = False) -> np.ndarray:
        """Return a per-pixel (or, with `vertex`, per-vertex) map cut to :attr:`box`."""
        if self.box is None:
            return image
        r0, r1, c0, c1 = self.box
        e = 1 if vertex else 0
        return image[r0 : r1 + e, c0 : c1 + e]

    @property
    def crop_note(self) -> str:
        """Return the caption's note on the crop ("" when not cropped)."""
        if self.box is None:
            return ""
        r0, r1, c0, c1 = self.box
        return f"; cropped to the mask: rows {r0}..{r1 - 1}, columns {c0}..{c1 - 1}"

    @property
    def units(self) -> str:
        """The rig's length unit (``summary.json``'s ``"units"``), or "rig units"."""
        units = self.summary.get("units")
        return units if isinstance(units, str) and units.strip() else "rig units"

    @property
    def footprint(self) -> tuple[float, float] | None:
        """A pixel's width on the surface at the mean depth, and that depth (None if unknown)."""
        if "footprint" not in self._cache:
            depth, rig = self._load("depth.npy"), self.rig
            self._cache["footprint"] = None if depth is None or rig is None else views.pixel_footprint(rig, depth)
        return self._cache["footprint"]

    @property
    def rig(self) -> Any:
        if "rig" not in self._cache:
            path = self.root / "rig.json"
            self._cache["rig"] = _results.read_rig(path) if os.path.lexists(path) else None
        return self._cache["rig"]


def _section(title: str, body: str, anchor: str) -> str:
    return f"<section id='{anchor}'><h2>{html.escape(title)}</h2>\n{body}\n</section>"


def _table(rows: Sequence[tuple[str, str]]) -> str:
    cells = "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>" for k, v in rows)
    return f"<table>{cells}</table>"


def _section_header(d: _Data) -> str:
    s = d.summary
    h, w = s.get("shape", [0, 0])
    o = d.options
    capture = o.get("capture") or o.get("images") or "not recorded (options were not given to save)"
    if isinstance(capture, list):
        capture = " ".join(str(c) for c in capture[:3]) + (f" ... ({len(capture)} items)" if len(capture) > 3 else "")
    rig = d.rig
    lights = str(rig.n_lights) if rig is not None else "unknown (no rig.json)"
    total = (s.get("timings") or {}).get("total")
    rows = [
        ("capture", str(capture)),
        ("result directory", os.fspath(d.root.resolve())),
        ("size", f"{w} x {h} pixels (W x H), {s.get('pixels', '?')} in the mask, {s.get('regions', '?')} region(s)"),
        ("lights", lights),
        ("method", str(s.get("method"))),
        ("status", f"{s.get('status')} (converged: {s.get('converged')}): {s.get('status_reason', '')}"),
        ("iterations", str(s.get("iterations"))),
        ("solver time", "unknown" if total is None else f"{total:.3f} s"),
    ]
    steps = _preprocessing(o)
    if steps is not None:
        rows.insert(1, ("pre-processing", "; ".join(steps) if steps else "none"))
    if s.get("reflectance") is not None:
        rows.append(("reflectance", _reflectance_text(s)))
    if s.get("estimated_distance"):
        rows.append(("estimated distance", ", ".join(_fmt(v) for v in s["estimated_distance"])))
    check = s.get("distance_check")
    if check:
        rows.append(("distance check", _distance_check_text(check)))
    return f"<header><h1>nplps report: {html.escape(d.name)}</h1>{_table(rows)}</header>"


def _reflectance_text(summary: dict[str, Any]) -> str:
    """Return the reflectance model of ``summary.json`` and its lobe in one line."""
    lobe = summary.get("lobe")
    if summary.get("reflectance") != "glossy" or not lobe:
        return "lambertian"
    if lobe.get("diffuse") == "retro":
        return (
            f"glossy (retro-reflective diffuse + GGX specular lobe): lobe roughness "
            f"{_fmt(lobe['roughness'])}, eta {_fmt(lobe['eta'])}"
        )
    return (
        f"glossy (diffuse with Fresnel transmittance + GGX specular lobe): lobe roughness "
        f"{_fmt(lobe['roughness'])}, eta {_fmt(lobe['eta'])}"
    )


def _distance_check_text(check: dict[str, Any]) -> str:
    """Return the distance check of ``summary.json`` in one line."""
    verdict = "LOOKS WRONG, try depth='auto'" if check["looks_wrong"] else "agrees with the images"
    return (
        f"{verdict}: a coarse level fits {_fmt(check['found'])} (given {_fmt(check['given'])}; "
        f"residual there {_fmt(check['ratio'])} times the best)"
    )


def _section_inputs(d: _Data) -> str:
    sheet = d._load("inputs.png")
    if sheet is None:
        body = _none("No input thumbnails: the images were not given to save() (inputs.png is missing).")
    else:
        body = _img(np.clip(sheet, 0, 255).astype(np.uint8), "input images", zoom=False) + (
            "<p>The input images after pre-processing, in light order (row by row), one brightness scale.</p>"
        )
    return _section("Inputs", body, "inputs")


def _section_maps(d: _Data) -> str:
    figures = []
    mask = d.mask
    if mask is not None:
        small = views.downsample(mask.astype(np.uint8) * 255, MAP_SIDE // 2).astype(np.uint8)
        figures.append(_figure(small, "mask (the whole image)"))
    else:
        figures.append(_none("Mask: not available (mask.png is missing)."))
    normals = d._load("normals.png")
    if normals is not None:
        # As written: 16-bit files (and 8-bit ones of results before the "normal_map" record) shown in 8 bits.
        record = d.summary.get("normal_map") or {"frame": "opengl", "bits": 8}
        top = 65535.0 if np.asarray(normals).dtype == np.uint16 else 255.0
        cropped = d.cropped(normals)
        small = views.downsample(cropped, MAP_SIDE, scale=255.0 / top)  # float64 values x 255 / top
        caption = (
            f"normal map as written in normals.png ({record['bits']}-bit, {_FRAMES.get(record['frame'], '?')})"
            f"{d.crop_note}"
        )
        pixels = np.rint(np.clip(np.nan_to_num(small), 0, 255)).astype(np.uint8)
        figures.append(_figure(pixels, caption, scale=_scale_bar(d, cropped.shape, pixels.shape)))
    else:
        figures.append(_none("Normal map: not available (normals.png is missing)."))
    glossy = d.summary.get("reflectance") == "glossy"
    albedo = d._load("albedo.png")
    name = "diffuse albedo" if glossy else "albedo"
    if albedo is not None:
        cropped = d.cropped(albedo)
        small = views.downsample(cropped, MAP_SIDE, scale=1.0)  # as float64, a band at a time
        scale = _scale_bar(d, cropped.shape, small.shape)
        figures.append(_figure(_grey_rgb(small), f"{name} (scaled to its 99.5th percentile){d.crop_note}", scale=scale))
    else:
        figures.append(_none("Albedo: not available (albedo.png is missing)."))
    cast = d.summary.get("cast_shadows")
    if isinstance(cast, dict):
        shadows = d._load("shadows.png")
        if shadows is not None:
            small = views.downsample(d.cropped(shadows), MAP_SIDE, scale=1.0)
            caption = (
                f"cast shadows predicted from the mesh: the share of the lights each pixel is hidden from "
                f"(black none, white all; {100 * float(cast.get('share', 0.0)):.1f} % of the observations "
                f"left out){d.crop_note}"
            )
            figures.append(_figure(np.rint(np.clip(np.nan_to_num(small), 0, 255)).astype(np.uint8), caption))
    if not glossy:
        return _section("Mask, normal map, albedo", "".join(figures), "maps")
    specular = d._load("specular.png")
    if specular is not None:
        small = views.downsample(d.cropped(specular), MAP_SIDE, scale=1.0)
        caption = f"specular albedo (scaled to its 99.5th percentile; the values are in specular.npy){d.crop_note}"
        figures.append(_figure(_grey_rgb(small), caption))
    else:
        figures.append(_none("Specular albedo: not available (specular.png is missing)."))
    return _section("Mask, normal map, albedo, specular albedo", "".join(figures), "maps")


def _mapped(values: np.ndarray, lo: float, hi: float, caption: str, label: str, d: _Data | None = None) -> str:
    """Return a colour-mapped map with its colour bar, and with `d` a scale bar (:func:`_scale_bar`)."""
    small = views.downsample(values, MAP_SIDE)
    shown = small.shape[0] * _zoom(small.shape)
    scale = "" if d is None else _scale_bar(d, values.shape, small.shape)
    return (
        f"<figure><div style='display:flex;align-items:flex-start'>{_img(views.colorize(small, lo, hi), caption)}"
        f"{_colorbar_svg(lo, hi, label, height=max(shown, 200))}</div>{scale}"
        f"<figcaption>{html.escape(caption)}</figcaption></figure>"
    )


#: How each normal-map convention is described in the report.
_FRAMES = {
    "opengl": "OpenGL convention: x right, y up, z towards the viewer; facing the camera = light blue",
    "directx": "DirectX convention: x right, y down, z towards the viewer",
    "opencv": "OpenCV camera frame: x right, y down, z forward",
}


def _section_residual(d: _Data) -> str:
    res = d._load("residual.npy")
    if res is None:
        return _section("Residual", _none("Residual map: not available (residual.npy is missing)."), "residual")
    res = np.asarray(res, dtype=np.float64)
    mask = d.mask
    if mask is not None and mask.shape == res.shape:
        res = np.where(mask, res, np.nan)
    finite = res[np.isfinite(res)]
    if finite.size == 0:
        return _section("Residual", _none("Residual map: no finite residual in the mask."), "residual")
    hi = float(np.percentile(finite, 99.5))
    hi = hi if hi > 0 else float(finite.max()) or 1.0
    caption = (
        f"RMS image residual of each pixel's fit (image units, 0..1); colour scale 0 .. {_fmt(hi)} "
        f"(the 99.5th percentile; largest {_fmt(float(finite.max()))}, median {_fmt(float(np.median(finite)))})"
    )
    caption += d.crop_note
    return _section("Residual", _mapped(d.cropped(res), 0.0, hi, caption, "residual"), "residual")


def _section_unfitted(d: _Data) -> str:
    used, mask = d._load("lights_used.npy"), d.mask
    if used is None or mask is None:
        return _section(
            "Unfitted pixels", _none("Unfitted pixels: not available (lights_used.npy is missing)."), "unfitted"
        )
    unfitted = mask & (np.asarray(used) < 3)
    count = int(unfitted.sum())
    if count == 0:
        body = _none(f"None: every one of the {int(mask.sum())} masked pixels had at least 3 lit images.")
    else:
        rgb = np.zeros((*mask.shape, 3), dtype=np.uint8)
        rgb[mask] = 200
        rgb[unfitted] = (220, 30, 30)
        body = _figure(
            views.downsample(d.cropped(rgb), MAP_SIDE).astype(np.uint8),
            f"{count} of {int(mask.sum())} masked pixels ({100 * count / max(int(mask.sum()), 1):.2f} %) had fewer "
            f"than 3 lit images and kept their starting shape (red; grey: fitted){d.crop_note}",
        )
    return _section("Unfitted pixels", body, "unfitted")


def _section_depth(d: _Data) -> str:
    depth = d._load("depth.npy")
    if depth is None:
        return _section("Depth", _none("Depth map: not available (depth.npy is missing)."), "depth")
    depth = np.asarray(depth, dtype=np.float64)
    finite = depth[np.isfinite(depth)]
    if finite.size == 0:
        return _section("Depth", _none("Depth map: no finite depth."), "depth")
    lo, hi = float(finite.min()), float(finite.max())
    unit = d.units
    caption = f"vertex depth z (distance along the optical axis, in {unit}): {_fmt(lo)} .. {_fmt(hi)} {unit}"
    caption += d.crop_note
    body = _mapped(d.cropped(depth, vertex=True), lo, hi, caption, f"depth z ({unit})", d)
    return _section("Depth", body, "depth")


def _section_renders(d: _Data) -> str:
    depth, rig, mask = d._load("depth.npy"), d.rig, d.mask
    if depth is None or rig is None or mask is None:
        missing = ", ".join(n for n, v in (("depth.npy", depth), ("rig.json", rig), ("mask.png", mask)) if v is None)
        return _section("Oblique views of the mesh", _none(f"No renders: {missing} missing."), "renders")
    vertices = _core.vertices(np.asarray(depth, dtype=np.float64), rig.camera)
    figures = [
        _figure(
            views.render_mesh(vertices, mask, azimuth=az, elevation=el, size=RENDER_SIZE),
            f"{title} (azimuth {az:+.0f}°, elevation {el:+.0f}°)",
            zoom=False,
        )
        for title, az, el in VIEWS
    ]
    note = (
        "<p>The mesh seen from beside the camera (orthographic views about the object's centre, "
        "grey surface lit from above left of the viewer; back faces tinted blue).</p>"
    )
    return _section("Oblique views of the mesh", note + "".join(figures), "renders")


def _section_convergence(d: _Data) -> str:
    hist = d._load("history.csv")
    if hist is None or len(hist) == 0:
        return _section(
            "Convergence", _none("No convergence history (history.csv is missing or empty)."), "convergence"
        )
    try:
        svg = plots.convergence_svg(hist[:, 2], hist[:, 0].astype(int))
    except ValueError:
        svg = _none("No positive depth change to plot.")
    last = hist[-1]
    text = (
        f"<p>{len(hist)} iterations; last: depth change {_fmt(last[2])}, RMS residual {_fmt(last[3])} "
        f"(image units), {_fmt(last[4])} s. {html.escape(str(d.summary.get('status_reason', '')))}</p>"
    )
    return _section("Convergence", svg + text, "convergence")


def _section_distance(d: _Data) -> str:
    curve = d._load("distance_curve.csv")
    if curve is None:
        return _section(
            "Working distance",
            _none("The working distance was given, not searched (no distance_curve.csv)."),
            "distance",
        )
    regions = sorted({int(r) for r in curve[:, 0]})
    curves = [curve[curve[:, 0] == r][:, 1:] for r in regions]
    recorded = d.summary.get("estimated_distance") or []
    # One estimate per region of the curve (the region's number indexes the recorded list).
    estimates = [
        float(recorded[r]) if r < len(recorded) and recorded[r] is not None and recorded[r] > 0 else np.nan
        for r in regions
    ]
    try:
        svg = plots.residual_curve_svg(curves, estimates)
    except ValueError:
        svg = _none("No finite point on the distance curve.")
    text = (
        "<p>RMS photometric residual against the working distance; estimate(s): "
        + ", ".join(_fmt(e) for e in estimates)
        + ".</p>"
    )
    return _section("Working distance", svg + text, "distance")


def _section_held_out(d: _Data) -> str:
    rec = d._load("held_out.json")
    if not isinstance(rec, dict) or "near" not in rec:
        return _section(
            "Held-out lights",
            _none(
                "No held-out evaluation (held_out.json is missing; "
                "run nplps evaluate ... --out RESULT_DIR, or save(held_out=...))."
            ),
            "held-out",
        )
    par = rec.get("parallel")
    head = "<tr><th>light</th><th>near: relative error</th><th>near: shape error</th><th>gain</th>"
    head += "<th>parallel: relative error</th><th>parallel: shape error</th></tr>" if par else "</tr>"
    rows = []
    for i, light in enumerate(rec.get("lights", [])):
        cells = [str(light)] + [_cell(v) for v in rec["near"][i]]
        if par:
            cells += [_cell(v) for v in par[i][:2]]
        rows.append("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in cells) + "</tr>")
    body = f"<table>{head}{''.join(rows)}</table><p><b>{html.escape(str(rec.get('reading', '')))}</b></p>"
    return _section("Held-out lights", body, "held-out")


def _trust_map(d: _Data, name: str) -> np.ndarray | None:
    """Return a float32 (H, W) trust map of the directory (``normal_sigma.tiff``...), or None when missing."""
    key = f"trust:{name}"
    if key not in d._cache:
        p = d.root / name
        value = None
        if os.path.lexists(p):
            try:
                _results._open_regular(p)[0].close()
                value = np.asarray(tifffile.imread(p))
            except (OSError, ValueError) as e:
                raise _results.damaged(p, f"not a readable TIFF ({e})") from None
            if value.shape != d.shape or value.dtype.kind != "f":
                raise _results.damaged(
                    p, f"expected a float ({d.shape[0]}, {d.shape[1]}) map, got {value.dtype} {value.shape}"
                )
            mask = d.mask
            value = value.astype(np.float64)
            if mask is not None and mask.shape == value.shape:
                value = np.where(mask, value, np.nan)
        d._cache[key] = value
    return d._cache[key]


def _trust_figure(d: _Data, name: str, text: str, label: str) -> str:
    values = _trust_map(d, name)
    if values is None:
        return _none(f"{text}: not available ({name} is missing).")
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return _none(f"{text}: no finite value in the mask.")
    hi = float(np.percentile(finite, 99))
    hi = hi if hi > 0 else float(finite.max()) or 1.0
    caption = (
        f"{text}; colour scale 0 .. {_fmt(hi)} (the 99th percentile; median {_fmt(float(np.median(finite)))}, "
        f"90th percentile {_fmt(float(np.percentile(finite, 90)))})" + d.crop_note
    )
    return _mapped(d.cropped(values), 0.0, hi, caption, label)


def _section_trust(d: _Data) -> str:
    """Return the uncertainty and leave-one-light-out maps and the per-light table (``summary["trust"]``)."""
    trust = d.summary.get("trust")
    if not isinstance(trust, dict):
        return _section(
            "Uncertainty and held-out error",
            _none("No uncertainty maps (a parallel-light baseline, or a result saved before they existed)."),
            "trust",
        )
    figures = _trust_figure(
        d,
        "normal_sigma.tiff",
        "Predicted normal uncertainty (degrees): the RMS angle between each pixel's fitted normal and the "
        "true one that the image noise alone gives, from the covariance of its Lambertian fit (4 or more lights)",
        "normal σ (°)",
    ) + _trust_figure(
        d,
        "held_out_error.tiff",
        "Leave-one-light-out error (image units): the mean over each pixel's lights of |I_k − the prediction "
        "of I_k by a fit without light k|",
        "held-out error",
    )
    note = (
        "<p>Both maps come from each pixel's linear Lambertian fit at the final surface (under the glossy "
        "model too). The uncertainty counts the image noise and what the model does not explain (the "
        "residual) but not an error of the rig (lights, distance): those bend normals alike without "
        "raising the residual. A held-out error well above the residual means the pixel's fit leans on "
        "single lights.</p>"
    )
    return _section("Uncertainty and held-out error", figures + note + _light_table(d, trust), "trust")


def _light_table(d: _Data, trust: dict[str, Any]) -> str:
    """Per light: residual, held-out residual, mean observation, pixels, intensity, refinement ± SE, shadow share."""
    lights = trust.get("lights") or []
    if not lights:
        return ""
    rig = d.rig
    # light_refinement is not checked field by field (_results): take only well-formed parts.
    refinement = d.summary.get("light_refinement")
    refinement = refinement if isinstance(refinement, dict) else {}
    listed = refinement.get("changes")
    changes = {c.get("light"): c for c in listed if isinstance(c, dict)} if isinstance(listed, list) else {}
    errors = refinement.get("standard_errors")
    errors = errors if isinstance(errors, list) else []
    shadows = (d.summary.get("cast_shadows") or {}).get("per_light") or []
    head = ["light", "RMS residual", "held-out RMS residual", "mean image value", "pixels", "intensity"]
    positions = refinement.get("mode") in ("position", "both")
    if changes:
        head += ["refined intensity factor ± SE"] + (["position shift ± SE"] if positions else [])
    if shadows:
        head += ["cast-shadow share"]
    rows = []
    for row in lights:
        i = int(row["light"])
        cells = [str(i), *(_number_cell(row.get(k)) for k in ("residual", "held_out", "mean_intensity"))]
        cells.append(str(row.get("pixels", "")))
        intensity = "n/a"
        if rig is not None and i < rig.n_lights:
            intensity = _fmt(float(np.mean(rig.intensities[i])))
        cells.append(intensity)
        if changes:
            c = changes.get(i, {})
            se = errors[i] if i < len(errors) and isinstance(errors[i], list) and len(errors[i]) == 4 else [None] * 4
            cells.append(f"{_number_cell(c.get('intensity_factor'))} ± {_number_cell(se[0])}")
            shift = c.get("position_shift")
            if not positions:
                pass
            elif isinstance(shift, list) and len(shift) == 3:
                cells.append(
                    ", ".join(f"{_number_cell(v)} ± {_number_cell(e)}" for v, e in zip(shift, se[1:4], strict=True))
                )
            else:
                cells.append("n/a")
        if shadows:
            cells.append(f"{100 * float(shadows[i]):.1f} %" if i < len(shadows) else "n/a")
        rows.append("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in cells) + "</tr>")
    header = "<tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>"
    caption = (
        "<p>Per light, over the pixels whose fit used it: residuals in image units (held-out: predicted by "
        "the pixel's fit without that light), the rig's intensity"
        + (" (the refined rig's; the refinement's change and standard error beside it)" if changes else "")
        + (", and the share of masked pixels in its cast shadow" if shadows else "")
        + ". A light whose held-out residual stands out from the others is the first to check.</p>"
    )
    return f"<h3>Per light</h3>{caption}<table>{header}{''.join(rows)}</table>"


def _number_cell(v: Any) -> str:
    """Return a number's cell, "n/a" for None or anything that is not a number."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return "n/a"
    return _fmt(float(v))


def _cell(v: Any) -> str:
    return "n/a" if v is None else _fmt(float(v))


#: The options whose effect :func:`_preprocessing`'s steps describe (recorded as typed).
_PREPROCESSING_FLAGS = ("srgb", "ambient", "exposures", "vignetting", "flat", "bin", "preprocessing")


def _preprocessing(options: dict[str, Any]) -> list[str] | None:
    """Return the pre-processing steps a result records (``options.preprocessing``), or None.

    None when they were not recorded (older results, the Python API without them) or are not a
    list (a hand-edited summary.json): then the options are shown as recorded.
    """
    steps = options.get("preprocessing")
    if not isinstance(steps, list):
        return None
    return [str(step) for step in steps]


def _section_options(d: _Data) -> str:
    s = d.summary
    timings = s.get("timings") or {}
    parts = ["<h3>Timings (seconds)</h3>"]
    parts.append(_table([(str(k), _fmt(v)) for k, v in timings.items()]) if timings else _none("No timings."))
    parts.append("<h3>Options</h3>")
    if d.options:
        options = d.options
        steps = _preprocessing(options)
        if steps is not None:
            # The steps applied say what was done; the flags as typed (srgb false, ambient null for
            # a capture preset that decoded sRGB and subtracted its ambient image) would mislead.
            options = {k: v for k, v in options.items() if k not in _PREPROCESSING_FLAGS}
            parts.append(
                "<p>Pre-processing applied: "
                + html.escape("; ".join(steps) if steps else "none")
                + " (the pre-processing flags as typed are left out of the table).</p>"
            )
        parts.append(_table([(k, json.dumps(v)) for k, v in options.items()]))
    else:
        parts.append(_none("The options were not recorded (saved from the Python API without options=)."))
    parts.append("<h3>summary.json</h3>")
    rest = [(k, json.dumps(v)) for k, v in s.items() if k not in ("timings", "options", "trust")]  # trust: its section
    parts.append(_table(rest))
    return _section("Timings and options", "".join(parts), "options")


# --------------------------------------------------------------------------------------------------
# Jupyter
# --------------------------------------------------------------------------------------------------


def compact_html(result: Result, *, side: int = 160) -> str:
    """Return the compact HTML of a result for Jupyter: small normal map and albedo, key numbers.

    Parameters
    ----------
    result : Result
        The result.
    side : int, default 160
        Longest side of the two pictures (pixels).

    Returns
    -------
    str
        An HTML fragment (a few tens of kilobytes).
    """
    facts = result._facts()
    rows = [
        ("Size (W x H)", facts["size"]),
        ("Method", facts["method"]),
        ("Status", facts["status"] + (f": {result.status_reason}" if result.status_reason else "")),
        ("Iterations", facts["iterations"]),
        ("Depth range", facts["depth"]),
        ("Mask", facts["mask"]),
        ("Unfitted", f"{result.unfitted} pixels"),
    ]
    if result.history:
        rows.append(("RMS residual", _fmt(result.history[-1].rms_residual)))
    if "total" in result.timings:
        rows.append(("Solver time", f"{result.timings['total']:.3f} s"))
    if result.distance is not None:
        rows.append(("Estimated distance", ", ".join(f"{v:.6g}" for v in result.distance.distance)))
    if result.distance_check is not None:
        rows.append(("Distance check", _distance_check_text(result.distance_check.to_dict())))
    left = "style='text-align:left'"
    cells = "".join(f"<tr><th {left}>{html.escape(k)}</th><td {left}>{html.escape(v)}</td></tr>" for k, v in rows)
    normals = export.normal_map_pixels(views.downsample(result.normals, side))
    albedo = _grey_rgb(views.downsample(np.asarray(result.albedo, dtype=np.float64), side))
    pics = "".join(
        f"<figure style='display:inline-block;margin:0 8px 0 0'>{_img(p, c)}<figcaption>{c}</figcaption></figure>"
        for p, c in ((normals, "normals"), (albedo, "albedo"))
    )
    return f"<div><table><caption {left}>nplps Reconstruction</caption>{cells}</table>{pics}</div>"
