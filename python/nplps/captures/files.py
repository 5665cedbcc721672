"""File discovery and reading helpers shared by the capture loaders."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import TypeAlias

import numpy as np

from ..errors import InputError
from ..io import PathLike, load_stack, read_image, to_float
from ..pipeline import natural_key, select_color
from ..raw import RAW_SUFFIXES

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", *RAW_SUFFIXES)
"""File name extensions (lower case) that the loaders treat as images (camera RAW: :mod:`nplps.raw`)."""

_AUTO = "auto"
MaskSpec: TypeAlias = PathLike | np.ndarray | None


def find_images(
    folder: PathLike,
    pattern: str = "*",
    exclude: Sequence[str] = ("mask", "ambient"),
) -> list[Path]:
    """Image files of ``folder`` matching the glob ``pattern``, in natural order.

    Files whose extension is not in :data:`IMAGE_EXTENSIONS` (case-insensitive) and files whose
    name contains one of the ``exclude`` words (case-insensitive) are skipped. Natural order
    sorts embedded numbers by value (``img2`` before ``img10``).
    """
    folder = Path(folder)
    words = [w.lower() for w in exclude]
    found = [
        p
        for p in folder.glob(pattern)
        if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS and not any(w in p.name.lower() for w in words)
    ]
    return sorted(found, key=natural_key)


def _find_one(folder: Path, word: str) -> Path | None:
    """Return the unique image file of ``folder`` whose name contains ``word``, or None if none."""
    hits = [
        p
        for p in sorted(folder.iterdir())
        if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS and word in p.name.lower()
    ]
    if len(hits) > 1:
        names = ", ".join(p.name for p in hits)
        raise InputError(f"several {word} images in '{folder}' ({names}): pass the one to use explicitly")
    return hits[0] if hits else None


def _check_folder(folder: PathLike) -> Path:
    """Return ``folder`` as a Path, or raise InputError if it is not a directory."""
    path = Path(folder)
    if not path.is_dir():
        raise InputError(f"capture folder '{path}' does not exist or is not a directory")
    return path


def _resolve(folder: Path, name: PathLike) -> Path:
    """``name`` relative to ``folder`` unless absolute or already an existing path; must exist."""
    path = Path(name)
    if not path.is_absolute() and not path.is_file():
        path = folder / path
    if not path.is_file():
        raise InputError(f"file '{path}' not found")
    return path


def _image_list(folder: Path, images: Sequence[PathLike] | str | None) -> list[Path]:
    """Resolve the ``images`` argument of the loaders into existing files."""
    if images is None:
        files = find_images(folder)
    elif isinstance(images, str):
        files = find_images(folder, images, exclude=())
    else:
        files = [_resolve(folder, p) for p in images]
    if not files:
        raise InputError(f"no image file found in '{folder}'")
    return files


def _read_float(path: Path) -> np.ndarray:
    """Read one image file as float32 in [0, 1] (integers) or as stored (floats)."""
    return to_float(read_image(path))


def _read_stack(files: Sequence[PathLike], color: bool | None) -> tuple[np.ndarray, int | None]:
    """Read image files into a float32 stack ``(k, H, W[, 3])`` and their levels.

    The files are decoded a few at a time (PNG in parallel, :func:`nplps.io.iter_images`) and
    each image is converted into the preallocated stack (:func:`nplps.io.load_stack`);
    ``color=False`` averages the channels of each image as it is read
    (:func:`nplps.pipeline.to_gray`).
    """
    stack, levels = load_stack([os.fspath(f) for f in files], color=color is not False)
    return select_color(stack, color)[0], levels


def _read_mask(path: Path) -> np.ndarray:
    """Read a mask image: channel 0 > 0 (anti-aliased masks count any coverage)."""
    m = read_image(path)
    if m.ndim == 3:
        m = m[..., 0]
    mask = m > 0
    if not mask.any():
        raise InputError(f"mask '{path}' selects no pixel")
    return mask


def _mask_arg(folder: Path, mask: MaskSpec | str) -> np.ndarray | None:
    """Resolve a ``mask`` argument: "auto" (unique file with 'mask' in its name), path, array."""
    if isinstance(mask, str) and mask == _AUTO:
        found = _find_one(folder, "mask")
        return None if found is None else _read_mask(found)
    if mask is None:
        return None
    if isinstance(mask, np.ndarray):
        m = np.asarray(mask)
        m = m[..., 0] if m.ndim == 3 else m
        if m.ndim != 2:
            raise InputError(f"mask: expected shape (H, W), got {np.shape(mask)}")
        return m != 0
    return _read_mask(_resolve(folder, mask))


def _ambient_arg(folder: Path, ambient: PathLike | np.ndarray | str | None) -> Path | np.ndarray | None:
    """Resolve an ``ambient`` argument: "auto" (unique 'ambient' file), path, array or None."""
    if isinstance(ambient, str) and ambient == _AUTO:
        return _find_one(folder, "ambient")
    if ambient is None or isinstance(ambient, np.ndarray):
        return ambient
    return _resolve(folder, ambient)


def _check_indices(indices: Sequence[int], n: int, what: str) -> list[int]:
    """Validate 0-based indices into ``n`` items."""
    out = []
    for i in indices:
        if isinstance(i, (bool, np.bool_)) or int(i) != i:
            raise InputError(f"{what}: indices must be integers, got {i!r}")
        if not 0 <= int(i) < n:
            raise InputError(f"{what}: index {i} out of range 0..{n - 1}")
        out.append(int(i))
    if not out:
        raise InputError(f"{what}: no index given")
    return out
