"""Reading input images and masks.

The photometric stereo solver wants linear, single-channel intensities as a float32 stack of shape
``(k, H, W)``. This module reads image files without losing precision and turns whatever the user
passes (paths, arrays, stacks) into that stack, with :class:`~nplps.errors.InputError` messages
that name the offending image.

Precision matters: imageio's default Pillow reader returns 16-bit RGB PNG files as ``uint8``,
silently dropping the low byte. :func:`read_image` therefore decodes every PNG (8 and 16 bits) in
the Rust extension (the ``png`` crate; several files at once in parallel, see
:func:`iter_images`) and TIFF files with tifffile (which keeps 16-bit integers and floats); other
formats go through imageio.

Memory: :func:`load_stack` converts each image straight into one preallocated float32 stack, so
loading k files costs the stack plus a few decoded images, never a float64 copy of the stack.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeAlias

import imageio.v3 as iio
import numpy as np
import tifffile

from . import _core
from ._files import NotRegularFile, open_regular
from .errors import InputError
from .preprocess import to_float
from .preprocess import to_gray as _gray
from .raw import is_raw, read_raw

__all__ = [
    "MAX_PIXELS",
    "iter_images",
    "load_images",
    "load_mask",
    "load_stack",
    "read_image",
    "to_float",
    "to_gray",
]

PathLike: TypeAlias = str | os.PathLike
"""A file name: ``str`` or any :class:`os.PathLike`."""

ImageSource: TypeAlias = PathLike | np.ndarray
"""One image: a file name or an array of shape ``(H, W)`` or ``(H, W, 3)``."""

LoadProgress: TypeAlias = Callable[[int, int, str], Any]
"""``progress(done, total, name)``: called by :func:`load_stack` after each image is loaded."""

MAX_PIXELS = 1 << 28
"""Default limit on the size of one image file, in pixels (H x W): 268 million, e.g.
16384 x 16384 -- far above camera sensors (a 100-Mpixel back has 1e8 pixels). A PNG or TIFF that
declares more is refused with :class:`~nplps.errors.InputError` before any pixel memory is
allocated, so a small crafted file (a "decompression bomb") cannot make the reader allocate
gigabytes. Pass ``max_pixels`` to :func:`read_image` / :func:`load_stack` to change it. Other
formats rely on Pillow's own guard (``PIL.Image.MAX_IMAGE_PIXELS``)."""

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_TIFF_SIGNATURES = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
_HEADER_SIZE = 32
_MAX_LISTED = 5
#: PNG files are decoded in parallel batches that end once they hold this many bytes of pixels
#: and at least one file per core, so that loading a stack holds only a batch of decoded images
#: besides the stack.
_BATCH_BYTES = 128 << 20


# --------------------------------------------------------------------------------------------------
# Reading one file
# --------------------------------------------------------------------------------------------------


def read_image(path: PathLike, max_pixels: int = MAX_PIXELS) -> np.ndarray:
    """Read an image file and return its pixels in their native dtype.

    The result has shape ``(H, W)`` (grey) or ``(H, W, 3)`` (colour); an alpha channel is
    dropped. The dtype is the file's own (``uint8``, ``uint16``, ``float32``, ...), without any
    scaling.

    * PNG (any bit depth and colour type): decoded in the Rust extension, keeping all 16 bits of
      16-bit files (the values as stored: ``sBIT`` is ignored). Grey images below 8 bits are
      scaled to 0..255; a palette PNG becomes RGB, or ``(H, W)`` when all its pixels are grey.
    * TIFF: read with tifffile, keeping 16-bit integers and floats; planar (channel-first) files
      are returned channel-last.
    * Camera RAW (a :class:`~nplps.raw.RawFile`, or a name ending in one of
      :data:`nplps.raw.RAW_SUFFIXES`: ``.dng``, ``.cr2``, ``.nef``, ...): decoded linearly with
      rawpy (:func:`nplps.raw.read_raw`: black level subtracted, white level at 65535, ``uint16``
      RGB), the sensor's size checked first. Needs the ``raw`` extra.
    * Anything else (JPEG, BMP, ...): imageio.

    Parameters
    ----------
    path : PathLike
        The file.
    max_pixels : int, optional
        Refuse a PNG, TIFF or camera RAW file larger than this many pixels (H x W; a RAW
        file's sensor) before decoding it; see :data:`MAX_PIXELS`.

    Raises
    ------
    InputError
        The file is missing, cannot be decoded as a single 2-D image, or is larger
        than ``max_pixels``; the message names the path and the reason.
    """
    header = _read_header(path)
    if is_raw(path):  # before the sniffing: most RAW formats are TIFF files
        return read_raw(path, max_pixels=max_pixels)
    if header.startswith(_PNG_SIGNATURE):
        # Every PNG variant (1 to 16 bits, grey / RGB / palette, alpha, interlaced) goes to the
        # Rust decoder: no fallback reader (PNG files are written by the Rust encoder too).
        return _core.read_pngs([path], int(max_pixels))[0]
    try:
        if header.startswith(_TIFF_SIGNATURES):
            image = _read_tiff(path, max_pixels)
        else:
            # The header first (no decoding): a small file can hold a huge image. imageio reads
            # from files opened here: given a path, it leaves the file open when no plugin can
            # read it (a ResourceWarning), so a bad image file would leak a handle.
            with open(path, "rb") as file:
                shape = iio.improps(file).shape
            _check_pixels(path, shape, max_pixels)
            with open(path, "rb") as file:
                image = np.asarray(iio.imread(file))
    except InputError:
        raise
    except Exception as exc:  # decoders raise many unrelated types (OSError, ValueError, ...)
        reason = str(exc)
        if "Could not find a backend" in reason:  # imageio's words, naming the file object
            reason = "not an image file of a known format (PNG, TIFF, JPEG, BMP, ...)"
        raise InputError(f"cannot read image '{os.fspath(path)}': {reason}") from exc
    return _normalize_channels(image, path)


def iter_images(
    paths: Sequence[PathLike], max_pixels: int = MAX_PIXELS, *, batch_files: int = 0
) -> Iterator[np.ndarray]:
    """Read image files like :func:`read_image`, yielding their pixels in the order of ``paths``.

    PNG files are decoded several at a time, in parallel and without the GIL, in batches of a
    bounded size: iterating (and converting each image before taking the next) keeps only a
    batch of decoded images in memory. ``batch_files`` (if positive) also ends a batch at that
    many files (at least one per core), so that a progress display sees the files arrive.
    Errors are raised like :func:`read_image`'s, when the iteration reaches the batch of the
    offending file.
    """
    batch: list[PathLike] = []
    batch_bytes = 0
    cores = _cores()
    most = max(batch_files, cores) if batch_files > 0 else len(paths) + 1
    for path in paths:
        try:
            header = _read_header(path)
        except InputError:
            yield from _read_pngs(batch, max_pixels)  # report the files before this one first
            raise
        if not header.startswith(_PNG_SIGNATURE):
            yield from _read_pngs(batch, max_pixels)
            batch, batch_bytes = [], 0
            yield read_image(path, max_pixels)
            continue
        batch.append(path)
        batch_bytes += _png_bytes(header)
        if (batch_bytes >= _BATCH_BYTES and len(batch) >= cores) or len(batch) >= most:
            yield from _read_pngs(batch, max_pixels)
            batch, batch_bytes = [], 0
    yield from _read_pngs(batch, max_pixels)


def _read_pngs(paths: list[PathLike], max_pixels: int) -> Iterator[np.ndarray]:
    """Decode PNG files in parallel (Rust) and yield them in order.

    Each is dropped from the batch as it is yielded (so that it is freed once the caller is done
    with it). InputError names the first bad file.
    """
    if not paths:
        return
    decoded = _core.read_pngs(paths, int(max_pixels))
    decoded.reverse()
    while decoded:
        yield decoded.pop()


def _png_bytes(header: bytes) -> int:
    """Return the decoded size in bytes of the PNG whose first bytes are ``header`` (0 if unknown)."""
    if len(header) < 26:
        return 0
    width = int.from_bytes(header[16:20], "big")
    height = int.from_bytes(header[20:24], "big")
    sample_bytes = 2 if header[24] == 16 else 1
    channels = 1 if header[25] in (0, 4) else 3  # grey (+ alpha) or colour / palette
    return width * height * channels * sample_bytes


def _cores() -> int:
    """Return the number of cores this process may use (the size of the decoder's thread pool)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on every platform
        return os.cpu_count() or 1


def _read_header(path: PathLike) -> bytes:
    """Return the first bytes of ``path`` (for format sniffing), or raise InputError.

    Only a regular file (or a link to one) is an image file: a device such as ``/dev/zero``
    never ends (a decoder that reads its whole input would fill the memory) and opening a FIFO
    waits for a writer, so anything else is refused before it is read
    (:func:`nplps._files.open_regular`).
    """
    try:
        file, _ = open_regular(path)
        with file:
            return file.read(_HEADER_SIZE)
    except NotRegularFile as exc:
        raise InputError(f"cannot read image '{os.fspath(path)}': not a regular file (it is {exc})") from None
    except FileNotFoundError as exc:
        raise InputError(f"cannot read image '{os.fspath(path)}': file not found") from exc
    except OSError as exc:
        raise InputError(f"cannot read image '{os.fspath(path)}': {exc.strerror or exc}") from exc


def _check_pixels(path: PathLike, shape: tuple[int, ...], max_pixels: int) -> None:
    """Refuse an image whose header declares more than ``max_pixels`` pixels.

    ``shape`` is the decoder's declared shape: ``(H, W)``, ``(H, W, C)`` or, for files with
    several frames, ``(n, H, W[, C])``; every frame counts (a trailing axis of at most 4 is
    taken as channels).
    """
    dims = tuple(int(n) for n in shape)
    if len(dims) >= 3 and dims[-1] <= 4:
        dims = dims[:-1]
    pixels = int(np.prod(dims, dtype=np.float64)) if len(dims) >= 2 else 0
    if pixels > max_pixels:
        frames = f" in {pixels // max(1, dims[-1] * dims[-2])} frames" if len(dims) > 2 else ""
        raise InputError(
            f"cannot read image '{os.fspath(path)}': {dims[-1]} x {dims[-2]} pixels{frames} is more than "
            f"the limit of {max_pixels} pixels (max_pixels; raise it if the image is genuine)"
        )


def _read_tiff(path: PathLike, max_pixels: int) -> np.ndarray:
    """Read the first series of a TIFF file, channel-last; refuse more than ``max_pixels``."""
    with tifffile.TiffFile(path) as tif:
        series = tif.series[0]
        sizes = dict(zip(series.axes, series.shape, strict=True))
        pixels = int(np.prod([n for axis, n in sizes.items() if axis != "S"], dtype=np.float64))
        if pixels > max_pixels:
            size = f"{sizes['X']} x {sizes['Y']} pixels" if "X" in sizes and "Y" in sizes else f"{pixels} pixels"
            if "X" in sizes and "Y" in sizes and pixels > sizes["X"] * sizes["Y"]:
                size += f" in {pixels // (sizes['X'] * sizes['Y'])} pages"
            raise InputError(
                f"cannot read image '{os.fspath(path)}': {size} is more than the limit "
                f"of {max_pixels} pixels (max_pixels; raise it if the image is genuine)"
            )
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


def _to_float_into(img: np.ndarray, out: np.ndarray) -> None:
    """Write :func:`to_float` of ``img`` into the float32 array ``out`` (same values, no copy)."""
    if img.dtype == np.bool_ or np.issubdtype(img.dtype, np.floating):
        out[...] = img
    elif np.issubdtype(img.dtype, np.integer):
        np.divide(img, np.float32(np.iinfo(img.dtype).max), out=out, dtype=np.float32, casting="unsafe")
    else:
        raise InputError(f"unsupported image dtype {img.dtype}: expected integers or floats")


def _convert_into(img: np.ndarray, out: np.ndarray, gray: bool) -> None:
    """Write :func:`to_gray` (``gray``) or :func:`to_float` of one image into ``out``."""
    if gray and img.ndim == 3:
        out[...] = to_gray(img)
    else:
        _to_float_into(img, out)


def to_gray(img: np.ndarray) -> np.ndarray:
    """Return a float32 ``(H, W)`` image: the mean of the channels of ``(H, W, 3)`` input.

    ``(H, W)`` input is returned unchanged in value. The input goes through :func:`to_float`
    first, so integer images are scaled to ``[0, 1]``. The mean is
    :func:`nplps.pipeline.to_gray`'s (the one grey conversion of nplps).

    Raises
    ------
    InputError
        The shape is neither ``(H, W)`` nor ``(H, W, 3)``.
    """
    img = np.asarray(img)
    if img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3):
        return _gray(img, stack=False)
    raise InputError(f"expected an image of shape (H, W) or (H, W, 3), got shape {img.shape}")


# --------------------------------------------------------------------------------------------------
# Image stacks
# --------------------------------------------------------------------------------------------------


def load_images(images: np.ndarray | Sequence[ImageSource]) -> np.ndarray:
    """Load the input images as a float32 grey stack of shape ``(k, H, W)``.

    Every image goes through :func:`to_float` (integers scaled to ``[0, 1]``) and then
    :func:`to_gray`. Negative values are allowed (the solver warns about them).

    Parameters
    ----------
    images : np.ndarray | Sequence[ImageSource]
        Either an array of shape ``(k, H, W)`` or ``(k, H, W, 3)`` of any numeric dtype,
        or a sequence of file names (``str`` / ``os.PathLike``, read with :func:`read_image`)
        and/or arrays of shape ``(H, W)`` or ``(H, W, 3)``.

    Raises
    ------
    InputError
        No image, an image of the wrong number of dimensions, images of different
        sizes, an unreadable file, or NaN / infinite values. The message names the image.
    """
    return load_stack(images, color=False)[0]


def load_stack(
    images: np.ndarray | Sequence[ImageSource],
    color: bool = False,
    *,
    max_pixels: int = MAX_PIXELS,
    progress: LoadProgress | None = None,
    uint16: bool = False,
) -> tuple[np.ndarray, int | None]:
    """Load the input images as float32 ``(k, H, W)``, or ``(k, H, W, 3)`` in colour.

    Load the input images as float32 ``(k, H, W)``, or ``(k, H, W, 3)`` when ``color`` is set and
    every image is RGB, with integers scaled to ``[0, 1]``.

    Returns the stack and the number of levels of the source (``255`` for 8-bit, ``65535`` for
    16-bit input, the largest of the images' if they differ), or None for floating-point input.
    Files are read with :func:`iter_images` (PNG decoded in parallel) and each image is converted
    straight into the preallocated stack; a float32 ``(k, H, W[, 3])`` array that needs no
    conversion is returned as it is (no copy). ``max_pixels`` limits the size of each file (see
    :data:`MAX_PIXELS`). ``progress(done, total, name)`` is called after each image of a
    sequence is in the stack (``name``: the file's name, or ``image i`` for an array). Raises
    :class:`InputError` like :func:`load_images`.

    With ``uint16``, 16-bit input that needs no grey conversion (every image ``uint16``, and
    grey or kept in colour) is returned as a ``uint16`` stack instead, 2 bytes per value instead
    of 4, with levels 65535: a C-contiguous ``uint16`` array as it is, files decoded straight
    into it. :func:`nplps.reconstruct` reads such a stack in place, each value as
    ``float32(v) / 65535``, the value the float32 stack would hold. Other input is loaded as
    float32 as without it.
    """
    if isinstance(images, np.ndarray):
        if uint16 and images.dtype == np.uint16 and images.ndim in (3, 4) and (color or images.ndim == 3):
            if images.shape[0] == 0 or (images.ndim == 4 and images.shape[3] != 3):
                return _array_stack(images, color)  # the errors of the float path
            return np.ascontiguousarray(images), int(np.iinfo(np.uint16).max)
        return _array_stack(images, color)
    if isinstance(images, (str, os.PathLike)):
        raise InputError(f"expected a sequence of images, got the single path '{os.fspath(images)}'")
    try:
        items: list[ImageSource] = list(images)
    except TypeError:
        raise InputError(
            f"images must be a (k, H, W[, 3]) array or a sequence of image files or arrays, got {type(images).__name__}"
        ) from None
    if not items:
        raise InputError("no input image: the image list is empty")
    labels = [_label(i, item) for i, item in enumerate(items)]
    k = len(items)
    stack: np.ndarray | None = None
    keep_color = color
    levels: list[int | None] = []
    nonfinite = np.zeros(k, dtype=np.int64)
    # With a progress display, batches of about a twentieth of the files (at least 4 per core).
    batch_files = 0 if progress is None else max(4 * _cores(), -(-k // 20))
    for i, pixels in enumerate(_sources(items, max_pixels, batch_files)):
        label = labels[i]
        if not (pixels.ndim == 2 or (pixels.ndim == 3 and pixels.shape[2] == 3)):
            raise InputError(f"{label}: expected shape (H, W) or (H, W, 3), got {pixels.shape}")
        if stack is None:
            keep_color = color and pixels.ndim == 3
            # 16-bit images that need no grey average stay 16-bit while every image is.
            keep_u16 = uint16 and pixels.dtype == np.uint16 and (keep_color or pixels.ndim == 2)
            dtype = np.uint16 if keep_u16 else np.float32
            stack = np.empty((k,) + (pixels.shape if keep_color else pixels.shape[:2]), dtype=dtype)
        elif stack.dtype == np.uint16 and (pixels.dtype != np.uint16 or pixels.ndim != stack.ndim - 1):
            stack = _float_stack(stack, i)
        if stack.dtype != np.uint16 and keep_color and pixels.ndim == 2:
            # Colour is kept only when every image is RGB: the images so far become grey.
            stack = _gray_stack(stack, i)
            keep_color = False
        shape = pixels.shape if keep_color else pixels.shape[:2]
        if shape != stack.shape[1:]:
            raise InputError(
                f"images have different sizes: {label} has shape {shape} but {labels[0]} has shape {stack.shape[1:]}"
            )
        try:
            if stack.dtype == np.uint16:
                stack[i] = pixels
            else:
                _convert_into(pixels, stack[i], gray=not keep_color)
        except InputError as exc:
            raise InputError(f"{label}: {exc}") from exc
        integer = np.issubdtype(pixels.dtype, np.integer)
        levels.append(int(np.iinfo(pixels.dtype).max) if integer else None)
        if not integer and pixels.dtype != np.bool_:
            nonfinite[i] = _count_nonfinite(stack[i])
        if progress is not None:
            item = items[i]
            progress(i + 1, k, os.path.basename(os.fspath(item)) if isinstance(item, (str, os.PathLike)) else label)
    assert stack is not None
    _raise_nonfinite(nonfinite, labels)
    known = [v for v in levels if v is not None]
    return stack, (max(known) if len(known) == k else None)


def _array_stack(images: np.ndarray, color: bool) -> tuple[np.ndarray, int | None]:
    """:func:`load_stack` of one ``(k, H, W[, 3])`` array."""
    if not (images.ndim == 3 or (images.ndim == 4 and images.shape[3] == 3)):
        raise InputError(
            f"expected an image stack of shape (k, H, W) or (k, H, W, 3), got an array of shape {images.shape}"
        )
    k = images.shape[0]
    if k == 0:
        raise InputError("no input image: the image stack is empty")
    if images.ndim == 4 and not color and images.dtype != np.float32:
        # Grey from colour: image by image, so that no float32 colour copy of the stack is made.
        stack = np.empty(images.shape[:3], dtype=np.float32)
        for i in range(k):
            _convert_into(images[i], stack[i], gray=True)
    else:
        # One conversion of the whole array; none at all for a C-contiguous float32 colour stack
        # or grey stack.
        whole = to_float(images)
        if whole.ndim == 4 and not color:
            whole = _gray(whole)
        stack = np.ascontiguousarray(whole, dtype=np.float32)
    labels = [f"image {i}" for i in range(k)]
    if np.issubdtype(images.dtype, np.floating):
        _raise_nonfinite(np.array([_count_nonfinite(image) for image in stack]), labels)
    return stack, (int(np.iinfo(images.dtype).max) if np.issubdtype(images.dtype, np.integer) else None)


def _sources(items: list[ImageSource], max_pixels: int, batch_files: int = 0) -> Iterator[np.ndarray]:
    """Return the pixels of each item in order: arrays as given, runs of files through :func:`iter_images`."""
    run: list[PathLike] = []
    for item in items:
        if isinstance(item, (str, os.PathLike)):
            run.append(item)
            continue
        yield from iter_images(run, max_pixels, batch_files=batch_files)
        run = []
        yield np.asarray(item)
    yield from iter_images(run, max_pixels, batch_files=batch_files)


def _float_stack(stack: np.ndarray, count: int) -> np.ndarray:
    """Return a float32 stack whose first ``count`` images are :func:`to_float` of the ``uint16`` ``stack``'s."""
    out = np.empty(stack.shape, dtype=np.float32)
    for i in range(count):
        _to_float_into(stack[i], out[i])
    return out


def _gray_stack(stack: np.ndarray, count: int) -> np.ndarray:
    """Return a grey ``(k, H, W)`` stack whose first ``count`` images are the channel means of ``stack``'s.

    These are the values :func:`to_gray` gives.
    """
    gray = np.empty(stack.shape[:3], dtype=np.float32)
    for i in range(count):
        gray[i] = to_gray(stack[i])
    return gray


def _label(index: int, item: ImageSource) -> str:
    """Name an image in error messages: ``image 3 ('c.png')`` or ``image 3``."""
    if isinstance(item, (str, os.PathLike)):
        return f"image {index} ('{os.fspath(item)}')"
    return f"image {index}"


def _count_nonfinite(image: np.ndarray) -> int:
    """Return the number of NaN or infinite values of one float image."""
    return int(np.count_nonzero(~np.isfinite(image)))


def _raise_nonfinite(counts: np.ndarray, labels: list[str]) -> None:
    """Raise InputError listing the images with non-finite values (``counts`` per image)."""
    bad = np.flatnonzero(counts)
    if bad.size == 0:
        return
    listed = ", ".join(f"{labels[i]}: {counts[i]}" for i in bad[:_MAX_LISTED])
    more = f" and {bad.size - _MAX_LISTED} more images" if bad.size > _MAX_LISTED else ""
    raise InputError(f"non-finite values (NaN or inf) in the input images: {listed}{more}")


# --------------------------------------------------------------------------------------------------
# Mask
# --------------------------------------------------------------------------------------------------


def load_mask(mask: PathLike | np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
    """Load the pixel mask as a bool array of shape ``shape`` = ``(H, W)``.

    Parameters
    ----------
    mask : PathLike | np.ndarray | None
        ``None`` (every pixel selected); a file name (read with :func:`read_image`, channel
        0 if colour, selected where ``> 0``); or an array of shape ``(H, W)`` or
        ``(H, W, 3)`` (channel 0), selected where nonzero (NaN counts as not selected).
    shape : tuple[int, int]
        The image size ``(H, W)``.

    Raises
    ------
    InputError
        The mask has the wrong shape, cannot be read, or selects no pixel.
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
        raise InputError(f"{source} has shape {selected.shape} but the images have shape {shape} (H, W)")
    if not selected.any():
        raise InputError(f"mask is empty: {source} selects no pixel")
    return selected


def _first_channel(array: np.ndarray, name: str) -> np.ndarray:
    """Return ``array`` if 2-D, channel 0 if ``(H, W, c)``; raise InputError otherwise."""
    if array.ndim == 2:
        return array
    if array.ndim == 3 and array.shape[2] >= 1:
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
