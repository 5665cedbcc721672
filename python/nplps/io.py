"""Reading input images and masks.

The photometric stereo solver wants linear, single-channel intensities as a float32 stack of shape
``(k, H, W)``. This module reads image files without losing precision and turns whatever the user
passes (paths, arrays, stacks) into that stack, with :class:`~nplps.errors.InputError` messages
that name the offending image.

Precision matters: imageio's default Pillow reader returns 16-bit RGB PNG files as ``uint8``,
silently dropping the low byte. :func:`read_image` therefore reads every 16-bit PNG with pypng and
TIFF files with tifffile (which keeps 16-bit integers and floats); other formats go through
imageio.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Union

import imageio.v3 as iio
import numpy as np
import png
import tifffile

from .errors import InputError

PathLike = Union[str, os.PathLike]
"""A file name: ``str`` or any :class:`os.PathLike`."""

ImageSource = Union[PathLike, np.ndarray]
"""One image: a file name or an array of shape ``(H, W)`` or ``(H, W, 3)``."""

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_BIT_DEPTH_OFFSET = 24
_PNG_COLOUR_TYPE_OFFSET = 25
_PNG_COLOUR_TYPE_PALETTE = 3
_TIFF_SIGNATURES = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
_HEADER_SIZE = 32
_MAX_LISTED = 5


# --------------------------------------------------------------------------------------------------
# Reading one file
# --------------------------------------------------------------------------------------------------


def read_image(path: PathLike) -> np.ndarray:
    """Read an image file and return its pixels in their native dtype.

    The result has shape ``(H, W)`` (grey) or ``(H, W, 3)`` (colour); an alpha channel is
    dropped. The dtype is the file's own (``uint8``, ``uint16``, ``float32``, ...), without any
    scaling.

    * PNG: 16-bit files are read with pypng (imageio would truncate 16-bit RGB to 8 bits), other
      bit depths with imageio. A palette PNG whose used colours are all grey becomes ``(H, W)``.
    * TIFF: read with tifffile, keeping 16-bit integers and floats; planar (channel-first) files
      are returned channel-last.
    * Anything else (JPEG, BMP, ...): imageio.

    Raises:
        InputError: the file is missing or cannot be decoded as a single 2-D image; the message
            names the path and the reason.
    """
    header = _read_header(path)
    try:
        if header.startswith(_PNG_SIGNATURE):
            image = _read_png(path, header)
        elif header.startswith(_TIFF_SIGNATURES):
            image = _read_tiff(path)
        else:
            image = np.asarray(iio.imread(path))
    except InputError:
        raise
    except Exception as exc:  # decoders raise many unrelated types (OSError, ValueError, ...)
        raise InputError(f"cannot read image '{os.fspath(path)}': {exc}") from exc
    return _normalize_channels(image, path)


def _read_header(path: PathLike) -> bytes:
    """Return the first bytes of ``path`` (for format sniffing), or raise InputError."""
    try:
        with open(path, "rb") as file:
            return file.read(_HEADER_SIZE)
    except FileNotFoundError as exc:
        raise InputError(f"cannot read image '{os.fspath(path)}': file not found") from exc
    except OSError as exc:
        raise InputError(f"cannot read image '{os.fspath(path)}': {exc.strerror or exc}") from exc


def _read_png(path: PathLike, header: bytes) -> np.ndarray:
    """Read a PNG file: pypng for 16-bit files, imageio otherwise."""
    if len(header) <= _PNG_COLOUR_TYPE_OFFSET:
        raise InputError(f"cannot read image '{os.fspath(path)}': truncated PNG header")
    if header[_PNG_BIT_DEPTH_OFFSET] == 16:
        return _read_png16(path)
    image = np.asarray(iio.imread(path))
    if image.dtype == np.bool_:  # 1-bit grey PNG: keep the usual 8-bit range
        image = image.astype(np.uint8) * np.uint8(255)
    if header[_PNG_COLOUR_TYPE_OFFSET] == _PNG_COLOUR_TYPE_PALETTE:
        image = _grey_palette_to_grey(_drop_alpha(image))
    return image


def _read_png16(path: PathLike) -> np.ndarray:
    """Read a 16-bit PNG with pypng as ``uint16`` of shape ``(H, W, planes)``."""
    width, height, rows, info = png.Reader(filename=os.fspath(path)).asDirect()
    pixels = np.vstack([np.asarray(row, dtype=np.uint16) for row in rows])
    return pixels.reshape(height, width, info["planes"])


def _grey_palette_to_grey(image: np.ndarray) -> np.ndarray:
    """Reduce an expanded palette image to ``(H, W)`` when all its colours are grey."""
    if image.ndim == 3 and image.shape[2] == 3:
        if np.array_equal(image[..., 0], image[..., 1]) and np.array_equal(
            image[..., 0], image[..., 2]
        ):
            return image[..., 0]
    return image


def _read_tiff(path: PathLike) -> np.ndarray:
    """Read the first series of a TIFF file, channel-last."""
    with tifffile.TiffFile(path) as tif:
        series = tif.series[0]
        image = series.asarray()
        axes = series.axes
    if image.ndim == 3 and axes.startswith("S"):  # planar configuration: channels first
        image = np.moveaxis(image, 0, -1)
    return image


def _drop_alpha(image: np.ndarray) -> np.ndarray:
    """Map ``(H, W, c)`` to ``(H, W)`` (c = 1, 2) or ``(H, W, 3)`` (c = 3, 4); keep others."""
    if image.ndim != 3:
        return image
    channels = image.shape[2]
    if channels in (1, 2):
        return image[..., 0]
    if channels == 4:
        return image[..., :3]
    return image


def _normalize_channels(image: np.ndarray, path: PathLike) -> np.ndarray:
    """Drop alpha and check that the decoded image is ``(H, W)`` or ``(H, W, 3)`` and numeric."""
    image = _drop_alpha(image)
    if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise InputError(
            f"cannot read image '{os.fspath(path)}': expected a single grey or RGB image, "
            f"got an array of shape {image.shape}"
        )
    if not (np.issubdtype(image.dtype, np.integer) or np.issubdtype(image.dtype, np.floating)):
        raise InputError(f"cannot read image '{os.fspath(path)}': unsupported dtype {image.dtype}")
    return image


# --------------------------------------------------------------------------------------------------
# Conversions
# --------------------------------------------------------------------------------------------------


def to_float(img: np.ndarray) -> np.ndarray:
    """Convert pixel values to float32.

    Integer types are scaled to ``[0, 1]`` by the maximum of their dtype (``uint8`` / 255,
    ``uint16`` / 65535, ...); booleans become 0 or 1; floats are returned unchanged (as float32).
    Works on arrays of any shape.

    Raises:
        InputError: the dtype is not numeric (complex, object, strings, ...).
    """
    img = np.asarray(img)
    if img.dtype == np.bool_:
        return img.astype(np.float32)
    if np.issubdtype(img.dtype, np.integer):
        return (img.astype(np.float32) / np.float32(np.iinfo(img.dtype).max)).astype(np.float32)
    if np.issubdtype(img.dtype, np.floating):
        return img.astype(np.float32, copy=False)
    raise InputError(f"unsupported image dtype {img.dtype}: expected integers or floats")


def to_gray(img: np.ndarray) -> np.ndarray:
    """Return a float32 ``(H, W)`` image: the mean of the channels of ``(H, W, 3)`` input.

    ``(H, W)`` input is returned unchanged in value. The input goes through :func:`to_float`
    first, so integer images are scaled to ``[0, 1]``.

    Raises:
        InputError: the shape is neither ``(H, W)`` nor ``(H, W, 3)``.
    """
    img = to_float(img)
    if img.ndim == 2:
        return img
    if img.ndim == 3 and img.shape[2] == 3:
        return img.mean(axis=2, dtype=np.float32)
    raise InputError(f"expected an image of shape (H, W) or (H, W, 3), got shape {img.shape}")


# --------------------------------------------------------------------------------------------------
# Image stacks
# --------------------------------------------------------------------------------------------------


def load_images(images: np.ndarray | Sequence[ImageSource]) -> np.ndarray:
    """Load the input images as a float32 grey stack of shape ``(k, H, W)``.

    Args:
        images: either an array of shape ``(k, H, W)`` or ``(k, H, W, 3)`` of any numeric dtype,
            or a sequence of file names (``str`` / ``os.PathLike``, read with :func:`read_image`)
            and/or arrays of shape ``(H, W)`` or ``(H, W, 3)``.

    Every image goes through :func:`to_float` (integers scaled to ``[0, 1]``) and then
    :func:`to_gray`. Negative values are allowed (the solver warns about them).

    Raises:
        InputError: no image, an image of the wrong number of dimensions, images of different
            sizes, an unreadable file, or NaN / infinite values. The message names the image.
    """
    return load_stack(images, color=False)[0]


def load_stack(images: np.ndarray | Sequence[ImageSource], color: bool = False) -> tuple[np.ndarray, int | None]:
    """Load the input images as float32 ``(k, H, W)``, or ``(k, H, W, 3)`` when ``color`` is set
    and every image is RGB, with integers scaled to ``[0, 1]``.

    Returns the stack and the number of levels of the source (``255`` for 8-bit, ``65535`` for
    16-bit input, the largest of the images' if they differ), or None for floating-point input.
    Raises :class:`InputError` like :func:`load_images`.
    """
    if isinstance(images, np.ndarray):
        if not (images.ndim == 3 or (images.ndim == 4 and images.shape[3] == 3)):
            raise InputError(
                "expected an image stack of shape (k, H, W) or (k, H, W, 3), "
                f"got an array of shape {images.shape}"
            )
        if images.shape[0] == 0:
            raise InputError("no input image: the image stack is empty")
        # One conversion of the whole array (no per-image copies).
        whole = to_float(images)
        if whole.ndim == 4 and not color:
            whole = whole.mean(axis=3, dtype=np.float32)
        stack = np.ascontiguousarray(whole, dtype=np.float32)
        _check_finite(stack, [f"image {i}" for i in range(stack.shape[0])])
        return stack, (int(np.iinfo(images.dtype).max) if np.issubdtype(images.dtype, np.integer) else None)
    else:
        if isinstance(images, (str, os.PathLike)):
            raise InputError(f"expected a sequence of images, got the single path '{os.fspath(images)}'")
        items: list[ImageSource] = list(images)
        if not items:
            raise InputError("no input image: the image list is empty")
        labels = [_label(i, item) for i, item in enumerate(items)]
    raw = [_read_one(item, label) for item, label in zip(items, labels)]
    keep_color = color and all(p.ndim == 3 for p in raw)
    converted = [to_float(p) if keep_color else _gray(p, label) for p, label in zip(raw, labels)]
    _check_same_shape(converted, labels)
    stack = np.ascontiguousarray(np.stack(converted), dtype=np.float32)
    _check_finite(stack, labels)
    levels = [np.iinfo(p.dtype).max for p in raw if np.issubdtype(p.dtype, np.integer)]
    return stack, (max(levels) if levels and len(levels) == len(raw) else None)


def _label(index: int, item: ImageSource) -> str:
    """Name an image in error messages: ``image 3 ('c.png')`` or ``image 3``."""
    if isinstance(item, (str, os.PathLike)):
        return f"image {index} ('{os.fspath(item)}')"
    return f"image {index}"


def _read_one(item: ImageSource, label: str) -> np.ndarray:
    """Read a file or take an array; its shape must be ``(H, W)`` or ``(H, W, 3)``."""
    pixels = read_image(item) if isinstance(item, (str, os.PathLike)) else np.asarray(item)
    if not (pixels.ndim == 2 or (pixels.ndim == 3 and pixels.shape[2] == 3)):
        raise InputError(f"{label}: expected shape (H, W) or (H, W, 3), got {pixels.shape}")
    return pixels


def _gray(pixels: np.ndarray, label: str) -> np.ndarray:
    try:
        return to_gray(pixels)
    except InputError as exc:
        raise InputError(f"{label}: {exc}") from exc


def _check_same_shape(images: list[np.ndarray], labels: list[str]) -> None:
    """Raise InputError naming the first image whose size differs from the first image's."""
    reference = images[0].shape
    for image, label in zip(images[1:], labels[1:]):
        if image.shape != reference:
            raise InputError(
                f"images have different sizes: {label} has shape {image.shape} "
                f"but {labels[0]} has shape {reference}"
            )


def _check_finite(stack: np.ndarray, labels: list[str]) -> None:
    """Raise InputError listing the images that contain NaN or infinite values."""
    bad_counts = np.count_nonzero(~np.isfinite(stack.reshape(stack.shape[0], -1)), axis=1)
    bad = np.flatnonzero(bad_counts)
    if bad.size == 0:
        return
    listed = ", ".join(f"{labels[i]}: {bad_counts[i]}" for i in bad[:_MAX_LISTED])
    more = f" and {bad.size - _MAX_LISTED} more images" if bad.size > _MAX_LISTED else ""
    raise InputError(f"non-finite values (NaN or inf) in the input images: {listed}{more}")


# --------------------------------------------------------------------------------------------------
# Mask
# --------------------------------------------------------------------------------------------------


def load_mask(mask: PathLike | np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
    """Load the pixel mask as a bool array of shape ``shape`` = ``(H, W)``.

    Args:
        mask: ``None`` (every pixel selected); a file name (read with :func:`read_image`, channel
            0 if colour, selected where ``> 0``); or an array of shape ``(H, W)`` or
            ``(H, W, 3)`` (channel 0), selected where nonzero (NaN counts as not selected).
        shape: the image size ``(H, W)``.

    Raises:
        InputError: the mask has the wrong shape, cannot be read, or selects no pixel.
    """
    shape = (int(shape[0]), int(shape[1]))
    if mask is None:
        return np.ones(shape, dtype=bool)
    if isinstance(mask, (str, os.PathLike)):
        selected = _first_channel(read_image(mask), "mask") > 0
        source = f"mask '{os.fspath(mask)}'"
    else:
        selected = _nonzero(_first_channel(np.asarray(mask), "mask"))
        source = "mask"
    if selected.shape != shape:
        raise InputError(
            f"{source} has shape {selected.shape} but the images have shape {shape} (H, W)"
        )
    if not selected.any():
        raise InputError(f"mask is empty: {source} selects no pixel")
    return selected


def _first_channel(array: np.ndarray, name: str) -> np.ndarray:
    """Return ``array`` if 2-D, channel 0 if ``(H, W, c)``; raise InputError otherwise."""
    if array.ndim == 2:
        return array
    if array.ndim == 3:
        return array[..., 0]
    raise InputError(f"{name}: expected shape (H, W) or (H, W, 3), got {array.shape}")


def _nonzero(array: np.ndarray) -> np.ndarray:
    """Boolean ``array != 0``, with NaN mapped to False."""
    if array.dtype == np.bool_:
        return array.copy()
    if np.issubdtype(array.dtype, np.floating):
        return (array != 0) & ~np.isnan(array)
    if np.issubdtype(array.dtype, np.integer):
        return array != 0
    raise InputError(f"mask: unsupported dtype {array.dtype}")
