"""LUCES object folders (Mecca, Logothetis, Budvytis, Cipolla: near-field LEDs, ground-truth normals and depth).

LUCES ("a dataset for near-fieLd point light soUrCe photomEtric Stereo", 14 objects, 52 LEDs,
introduced with Logothetis et al., "A CNN based approach for the point-light photometric stereo
problem", arXiv 2210.04655) stores one folder per object. The layout read here, and where each fact
comes from, is in ``docs/luces.md``; in short:

* ``led_params.txt``: line 1 a header; line 2 ``N_img nrows ncols f x0 y0 mean_distance``; then one
  line per LED: position (3, mm), principal direction (3), ``Phi`` (3 RGB values, or 1), ``mu``
  and an optional trailing 0;
* ``01.png`` .. ``52.png``: 16-bit RGB images, image ``i`` lit by LED line ``i``;
* ``mask.png`` (channel 0 > 0), ``normals.png`` (16-bit RGB, ``n = 2 v / 65535 - 1``, x right, y up,
  z towards the camera) and ``zgt.npz`` (array ``zgt``: depth in mm).

No copy of LUCES was at hand when this loader was written: it is tested on synthetic captures
written in this layout (``tests/test_luces.py``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..errors import InputError, RigError
from ..io import PathLike, read_image
from .capture import Capture
from .files import _check_folder, _check_indices, _read_mask, _read_stack

__all__ = [
    "LED_PARAMS",
    "N_OBJECTS",
    "PUBLISHED",
    "LedParams",
    "LucesCapture",
    "decode_normals",
    "find_luces_objects",
    "load_luces",
    "read_led_params",
]

#: The calibration file of a LUCES object folder.
LED_PARAMS = "led_params.txt"

#: The number of objects in LUCES (arXiv 2210.04655, abstract), over which the published averages are taken.
N_OBJECTS = 14

#: Published mean angular errors on LUCES (degrees, mean over the 14 objects), by method. Per-object
#: numbers could not be sourced for this module (the papers' tables were not readable here), so only
#: the averages are kept; ``nplps benchmark luces`` prints them under the table.
PUBLISHED: dict[str, float] = {
    # Lichy, Sengupta, Jacobs, "Fast light-weight near-field photometric stereo", CVPR 2022 (abstract:
    # "11.3 vs. 13.3 degrees mean angular error", the latter the iterative optimization of Logothetis et al.).
    "FastNFPS (Lichy et al. 2022)": 11.3,
    "Logothetis et al. (as quoted by FastNFPS)": 13.3,
    # As quoted in nplps issue 22 (not checked against the paper here).
    "LINO-UniPS": 9.4,
}


@dataclass
class LucesCapture(Capture):
    """A :class:`Capture` with LUCES's extra ground truth.

    Attributes
    ----------
    depth_gt : np.ndarray | None
        ``(H, W)`` ground-truth depth z in mm (camera frame), NaN where unknown, or None.
    mean_distance : float | None
        The object's mean distance from the camera in mm (``led_params.txt``), a starting depth.
    """

    depth_gt: np.ndarray | None = None
    mean_distance: float | None = None


def _numbers(line: str) -> list[float] | None:
    """Return the numbers of a whitespace-separated line, or None when a token is not a number."""
    try:
        return [float(t) for t in line.split()]
    except ValueError:
        return None


class LedParams(NamedTuple):
    """The contents of a LUCES ``led_params.txt`` (see :func:`read_led_params`)."""

    n_images: int
    rows: int
    cols: int
    f: float
    x0: float
    y0: float
    mean_distance: float
    positions: np.ndarray
    directions: np.ndarray
    phi: np.ndarray
    mu: np.ndarray


def read_led_params(path: PathLike) -> LedParams:
    """Read a LUCES ``led_params.txt``.

    Returns the image line (``n_images``, ``rows``, ``cols``, ``f``, ``x0``, ``y0``,
    ``mean_distance``) and the per-LED arrays ``positions`` (k, 3), ``directions`` (k, 3, unit),
    ``phi`` (k, 3) and ``mu`` (k,), as written (no frame change: LUCES's frame is already x right,
    y down, z forward).

    Raises
    ------
    RigError
        The file is missing or does not have the layout above (naming the line).
    """
    path = Path(path)
    if not path.is_file():
        raise RigError(f"LUCES calibration '{path}' not found (each object folder holds {LED_PARAMS})")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (UnicodeDecodeError, OSError) as exc:
        raise RigError(f"cannot read '{path}': {exc}") from None
    # (line number, text) of the non-blank lines. Line 1 is a text header; tolerate its absence
    # (the first all-numeric line is the image line).
    lines = [(i, ln) for i, ln in enumerate(text.splitlines(), 1) if ln.strip()]
    if lines and _numbers(lines[0][1]) is None:
        lines = lines[1:]
    if len(lines) < 2:
        raise RigError(f"'{path}': expected a header, an image line and one line per LED, got {len(lines)} lines")
    number, line = lines[0]
    head = _numbers(line)
    if head is None or len(head) != 7:
        raise RigError(
            f"'{path}' line {number}: expected 7 numbers 'N_img nrows ncols f x0 y0 mean_distance', "
            f"got {line.strip()!r}"
        )
    count, rows, cols, f, x0, y0, mean_distance = head
    leds = []
    for number, line in lines[1:]:
        values = _numbers(line)
        if values is None or len(values) not in (8, 9, 10, 11):
            raise RigError(
                f"'{path}' line {number}: expected 'x y z dx dy dz Phi_r Phi_g Phi_b mu [0]' "
                f"(or one Phi), got {line.strip()!r}"
            )
        if len(values) in (8, 9):  # one Phi value, mu, [0]
            phi = [values[6]] * 3
            mu = values[7]
        else:
            phi = values[6:9]
            mu = values[9]
        leds.append(values[0:6] + phi + [mu])
    table = np.array(leds, dtype=np.float64)
    if int(count) != count or int(count) != len(leds):
        raise RigError(f"'{path}': the image line says {count:g} images but {len(leds)} LED lines follow")
    if not np.all(np.isfinite(table)) or not np.isfinite(head).all():
        raise RigError(f"'{path}': the values must be finite numbers")
    norms = np.linalg.norm(table[:, 3:6], axis=1)
    if np.any(norms < 1e-9):
        bad = int(np.argmin(norms)) + 1
        raise RigError(f"'{path}': LED {bad} has a zero direction")
    if f <= 0 or mean_distance <= 0 or rows < 1 or cols < 1:
        raise RigError(f"'{path}': f, mean_distance, nrows and ncols must be positive, got {head}")
    return LedParams(
        len(leds),
        int(rows),
        int(cols),
        f,
        x0,
        y0,
        mean_distance,
        table[:, 0:3],
        table[:, 3:6] / norms[:, None],
        table[:, 6:9],
        table[:, 9],
    )


def decode_normals(pixels: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Decode a LUCES ``normals.png`` into unit normals in nplps's camera frame.

    The file's channels R, G, B hold ``(n + 1) / 2`` scaled to the integer range, in a frame with
    x right, y up, z towards the camera; the camera frame's normal is ``(x, -y, -z)`` (n_z < 0).
    Pixels outside ``mask`` and pixels whose decoded length is not near 1 (LUCES writes the
    background as white, length sqrt(3)) are 0.
    """
    v = np.asarray(pixels)
    if v.ndim != 3 or v.shape[2] < 3:
        raise InputError(f"normals: expected an RGB image, got shape {v.shape}")
    top = float(np.iinfo(v.dtype).max) if np.issubdtype(v.dtype, np.integer) else 1.0
    n = 2.0 * v[..., :3].astype(np.float64) / top - 1.0
    n *= np.array([1.0, -1.0, -1.0])
    length = np.linalg.norm(n, axis=2)
    ok = np.abs(length - 1.0) < 0.1
    if mask is not None:
        ok &= mask
    out = np.zeros_like(n)
    out[ok] = n[ok] / length[ok, None]
    return out


def _read_depth(path: Path, key: str) -> np.ndarray:
    """Read the ground-truth depth of ``zgt.npz`` (array ``key``); 0 and non-finite values become NaN."""
    try:
        with np.load(path, allow_pickle=False) as data:
            if key not in data.files:
                raise InputError(f"'{path}' has no array {key!r} (it has {', '.join(data.files) or 'none'})")
            z = np.asarray(data[key], dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read '{path}': {exc}") from None
    if z.ndim != 2:
        raise InputError(f"'{path}': {key} has shape {z.shape}, expected (H, W)")
    z = z.copy()
    z[~np.isfinite(z) | (z <= 0)] = np.nan
    return z


def is_luces_object(folder: PathLike) -> bool:
    """Tell whether ``folder`` is a LUCES object folder (it holds ``led_params.txt``)."""
    return (Path(folder) / LED_PARAMS).is_file()


def find_luces_objects(folder: PathLike, objects: Sequence[str] | None = None) -> list[Path]:
    """Return the LUCES object folders under ``folder``: itself if it is one, else its subfolders that are.

    ``objects`` keeps only these names (case-insensitive); a name with no folder is an error.
    """
    from ..pipeline import natural_key

    root = _check_folder(folder)
    found = (
        [root]
        if is_luces_object(root)
        else sorted((p for p in root.iterdir() if p.is_dir() and is_luces_object(p)), key=lambda p: natural_key(p.name))
    )
    if not found:
        raise InputError(f"no LUCES object folder (one holding {LED_PARAMS}) in '{root}'")
    if objects is not None:
        by_name = {p.name.lower(): p for p in found}
        missing = [o for o in objects if o.lower() not in by_name]
        if missing:
            raise InputError(
                f"no LUCES object {', '.join(missing)} in '{root}' (found: {', '.join(p.name for p in found)})"
            )
        found = [by_name[o.lower()] for o in objects]
    return found


def load_luces(
    folder: PathLike,
    *,
    load: bool = False,
    color: bool | None = None,
    lights: Sequence[int] | None = None,
    normals: bool = True,
    depth: bool = True,
    one_based: bool = False,
    image_digits: int = 2,
) -> LucesCapture:
    """Load one LUCES object folder (``led_params.txt``, ``01.png`` ..., ``mask.png``, ground truth).

    Parameters
    ----------
    folder : PathLike
        The object folder (holding ``led_params.txt``).
    load : bool, optional
        Return the images as a float32 stack ``(k, H, W, 3)`` (16 bits kept, scaled by 1/65535)
        instead of file names.
    color : bool | None, optional
        None (keep RGB), True (require RGB) or False (average the channels of loaded images and
        of ``Phi``).
    lights : Sequence[int] | None, optional
        A subset of the LEDs (0-based rows of ``led_params.txt``; image ``i + 1``).
    normals : bool, optional
        Read ``normals.png`` into ``normals_gt`` when present.
    depth : bool, optional
        Read ``zgt.npz`` (array ``zgt``, mm) into ``depth_gt`` when present.
    one_based : bool, optional
        Read ``x0 y0`` as 1-based pixel coordinates (MATLAB's). LUCES does not say; the default
        (False) takes them as 0-based pixel centres (OpenCV's, which the dataset's Python code
        uses), see ``docs/luces.md``.
    image_digits : int, optional
        The width of the image numbers (``01.png``: 2).

    Returns
    -------
    LucesCapture
        Point lights (LED model ``Phi (cos)^mu / r^2``) with RGB intensities ``Phi``, pinhole
        ``K = [[f, 0, x0], [0, f, y0], [0, 0, 1]]``, the mask, ``normals_gt`` (camera frame,
        ``n_z < 0``, zero outside the object), ``depth_gt`` (mm, NaN outside) and
        ``mean_distance``.

    Raises
    ------
    RigError
        ``led_params.txt`` is missing or malformed.
    InputError
        An image is missing, or the files disagree on the image size.
    """
    root = _check_folder(folder)
    p = read_led_params(root / LED_PARAMS)
    count = p.n_images
    rows = list(range(count)) if lights is None else _check_indices(lights, count, "lights")
    files = [root / f"{i + 1:0{image_digits}d}.png" for i in rows]
    missing = [f.name for f in files if not f.is_file()]
    if missing:
        raise InputError(f"LUCES object '{root}': image(s) {', '.join(missing[:5])} not found")
    shift = 1.0 if one_based else 0.0
    K = np.array([[p.f, 0.0, p.x0 - shift], [0.0, p.f, p.y0 - shift], [0.0, 0.0, 1.0]])
    stated = (p.rows, p.cols)

    mask_path = root / "mask.png"
    mask = _read_mask(mask_path) if mask_path.is_file() else None
    normals_gt = None
    if normals and (root / "normals.png").is_file():
        normals_gt = decode_normals(read_image(root / "normals.png"), mask)
    depth_gt = _read_depth(root / "zgt.npz", "zgt") if depth and (root / "zgt.npz").is_file() else None

    phi = p.phi[rows]
    if color is False:
        phi = phi.mean(axis=1)
    images: list[Path] | np.ndarray = list(files)
    levels = None
    if load:
        images, levels = _read_stack(files, color)
    shapes = {"mask.png": mask, "normals.png": normals_gt, "zgt.npz": depth_gt}
    if isinstance(images, np.ndarray):
        shapes["the images"] = images[0]
    for name, arr in shapes.items():
        if arr is not None and arr.shape[:2] != stated and arr.shape[:2] != stated[::-1]:
            raise InputError(
                f"LUCES object '{root}': {name} is {arr.shape[1]} x {arr.shape[0]} pixels but {LED_PARAMS} "
                f"says nrows {stated[0]}, ncols {stated[1]}"
            )
    grids = {name: arr.shape[:2] for name, arr in shapes.items() if arr is not None}
    if len(set(grids.values())) > 1:
        raise InputError(f"LUCES object '{root}': the files disagree on the image size: {grids}")
    return LucesCapture(
        images=images,
        mask=mask,
        K=K,
        positions=p.positions[rows].copy(),
        directions=p.directions[rows].copy(),
        intensities=np.ascontiguousarray(phi),
        mu=p.mu[rows].copy(),
        directional=False,
        normals_gt=normals_gt,
        name=root.name,
        notes=(
            "LUCES (Mecca et al.): 52 LEDs, 16-bit linear RGB, positions in mm in the camera frame "
            "(x right, y down, z forward); ground-truth normals decoded from normals.png (y, z negated); "
            "depth from zgt.npz (mm). The RGB Phi are in the rig: do not divide the images by them."
        ),
        files=list(files),
        levels=levels,
        depth_gt=depth_gt,
        mean_distance=p.mean_distance,
    )
