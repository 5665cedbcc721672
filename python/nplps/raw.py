"""Camera RAW input (CR2, CR3, NEF, ARW, DNG, ...) through rawpy (LibRaw), decoded linearly.

Photometric stereo needs intensities proportional to the light that reached each pixel. A camera's
JPEG is tone-mapped; its RAW file holds the sensor's counts. :func:`read_raw` decodes a RAW file
with LibRaw so that the values stay linear in those counts:

* the black level is subtracted and the white level maps to the top of the output
  (``(raw - black) / (white - black)``), with nothing else: no gamma curve (``gamma=(1, 1)``), no
  automatic brightening (``no_auto_bright``), no adjustment of the white level to the brightest
  pixel found (``adjust_maximum_thr=0``) and no colour matrix (the camera's own colour space,
  ``ColorSpace.raw``);
* white balance: ``"none"`` (every channel multiplied by 1: the sensor's response) or
  ``"camera"`` (the as-shot multipliers stored by the camera; the smallest is 1, and values
  pushed beyond the white level clip there and read as saturated);
* demosaiced at full size (LibRaw's AHD interpolation), or ``half_size``: each 2 x 2 cell of the
  colour filter array becomes one pixel (red and blue as recorded, green the mean of the two
  greens, rounded down): no interpolation, so the values stay exactly linear. The half-size
  image is the sensor's grid binned 2 x 2: its rig is :meth:`nplps.rig.Rig.binned` ``(2)`` of the
  sensor's rig;
* the image is kept as the sensor records it: the file's orientation (rotation) is not applied;
* the size is checked against ``max_pixels`` from the file's header, before anything is decoded.

The result is ``uint16`` RGB ``(H, W, 3)`` (white level = 65535); ``output="float"`` gives the
same values as float32 on ``[0, 1]``. Loaded by :func:`nplps.io.load_stack` it counts as a 16-bit
image (levels 65535); the command line passes the sensor's levels instead (:func:`sensor_levels`,
``white - black``), so that its default thresholds are one sensor level: shadows at or below one
level above black, saturation at the white level.

Exposure metadata (:func:`read_exposure`, :func:`exposures_from_metadata`, the command line's
``--exposures auto``): LibRaw gives the shutter time and, for most formats, the ISO
(``raw.other``). Where it gives no ISO (a DNG whose ISO tag is in its first directory rather than
its EXIF directory, as DNG writers such as pidng do), the TIFF tags ExposureTime (33434) and
ISOSpeedRatings / PhotographicSensitivity (34855) are read with tifffile (TIFF-based RAW formats
only: DNG, CR2, NEF, ARW, PEF, SRW, ...).

rawpy is an optional dependency: ``pip install 'nplps[raw]'``.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from typing import Any, Literal, NamedTuple, TypeAlias

import numpy as np
import tifffile

from ._files import NotRegularFile, open_regular
from .errors import InputError

__all__ = [
    "RAW_SUFFIXES",
    "Exposure",
    "RawFile",
    "RawOptions",
    "exposures_from_metadata",
    "is_raw",
    "read_exposure",
    "read_raw",
    "sensor_levels",
]

PathLike: TypeAlias = str | os.PathLike

#: The file name endings read as camera RAW files (case-insensitive).
RAW_SUFFIXES = (".dng", ".cr2", ".cr3", ".crw", ".nef", ".nrw", ".arw", ".orf", ".rw2", ".raf", ".pef", ".srw", ".raw")

WhiteBalance: TypeAlias = Literal["none", "camera"]

#: Default limit on the sensor's pixels (as :data:`nplps.io.MAX_PIXELS`; repeated to keep this
#: module free of a circular import).
_MAX_PIXELS = 1 << 28

_INSTALL = "rawpy is not installed: install the 'raw' extra (pip install 'nplps[raw]') or rawpy itself"


@dataclasses.dataclass(frozen=True)
class RawOptions:
    """How :func:`read_raw` decodes a RAW file.

    Attributes
    ----------
    white_balance : {"none", "camera"}
        ``"none"``: every channel multiplied by 1 (the sensor's response); ``"camera"``: the
        as-shot multipliers the camera stored.
    half_size : bool
        Each 2 x 2 cell of the colour filter array becomes one pixel (no interpolation); else
        full-size demosaicing (AHD).
    output : {"uint16", "float"}
        ``uint16`` (the white level at 65535) or float32 on ``[0, 1]``.
    """

    white_balance: WhiteBalance = "none"
    half_size: bool = False
    output: Literal["uint16", "float"] = "uint16"

    def __post_init__(self) -> None:
        """Check the values."""
        if self.white_balance not in ("none", "camera"):
            raise InputError(f"RAW white balance must be 'none' or 'camera', got {self.white_balance!r}")
        if self.output not in ("uint16", "float"):
            raise InputError(f"RAW output must be 'uint16' or 'float', got {self.output!r}")
        if not isinstance(self.half_size, (bool, np.bool_)):
            raise InputError(f"RAW half_size must be True or False, got {self.half_size!r}")


class RawFile(os.PathLike):
    """A RAW file's path together with the :class:`RawOptions` to decode it with.

    It is a path (``os.fspath`` gives the file's name), so it goes wherever an image file may
    (:func:`nplps.io.load_stack`, :func:`nplps.pipeline.prepare`, the ``images`` of
    :func:`nplps.reconstruct`), and :func:`nplps.io.read_image` decodes it with its options. A
    plain path ending in one of :data:`RAW_SUFFIXES` is decoded with the default options.

    Parameters
    ----------
    path : PathLike
        The file.
    options : RawOptions, optional
        Default: ``RawOptions()``.
    """

    __slots__ = ("options", "path")

    def __init__(self, path: PathLike, options: RawOptions | None = None) -> None:
        self.path = os.fspath(path)
        self.options = RawOptions() if options is None else options

    def __fspath__(self) -> str:
        """Return the file's name."""
        return self.path

    def __repr__(self) -> str:
        """Show the path and the options."""
        return f"RawFile({self.path!r}, {self.options!r})"


class Exposure(NamedTuple):
    """A RAW file's exposure metadata (None where the file does not say)."""

    #: Shutter time in seconds.
    shutter: float | None
    #: ISO speed (gain).
    iso: float | None


def is_raw(path: Any) -> bool:
    """Return whether ``path`` is a :class:`RawFile` or a path ending in one of :data:`RAW_SUFFIXES`."""
    if isinstance(path, RawFile):
        return True
    if isinstance(path, (str, os.PathLike)):
        return os.fspath(path).lower().endswith(RAW_SUFFIXES)
    return False


def _rawpy(path: PathLike) -> Any:
    try:
        import rawpy
    except ImportError as exc:
        raise InputError(f"cannot read camera RAW file '{os.fspath(path)}': {_INSTALL}") from exc
    return rawpy


def _open(path: PathLike) -> Any:
    """Open a RAW file with rawpy (header only, nothing decoded); InputError naming the file."""
    rawpy = _rawpy(path)
    name = os.fspath(path)
    if not os.path.exists(name):
        raise InputError(f"cannot read image '{name}': file not found")
    try:
        # LibRaw is given the name; a device or FIFO is refused before it reads (or waits on) it.
        open_regular(name)[0].close()
    except NotRegularFile as exc:
        raise InputError(f"cannot read camera RAW file '{name}': not a regular file (it is {exc})") from None
    except OSError:
        pass  # LibRaw reports it below, in its words
    try:
        return rawpy.imread(name)
    except Exception as exc:  # LibRawFileUnsupportedError, LibRawIOError, OSError, ...
        raise InputError(f"cannot read camera RAW file '{name}': {_reason(exc)}") from exc


def _reason(exc: Exception) -> str:
    """Return LibRaw's message (rawpy passes it as bytes) as text."""
    arg = exc.args[0] if exc.args else exc
    text = arg.decode(errors="replace") if isinstance(arg, bytes) else str(arg)
    return f"{text} (LibRaw {type(exc).__name__})" if text else type(exc).__name__


def read_raw(
    path: PathLike, options: RawOptions | None = None, *, max_pixels: int = _MAX_PIXELS, **kwargs: Any
) -> np.ndarray:
    """Decode a camera RAW file linearly (see the module's notes).

    Parameters
    ----------
    path : PathLike
        The RAW file (a :class:`RawFile` brings its own options).
    options : RawOptions, optional
        How to decode; default: the :class:`RawFile`'s options, else ``RawOptions()``.
    max_pixels : int, optional
        Refuse a file whose sensor has more pixels than this, before decoding it.
    **kwargs
        Fields of :class:`RawOptions` (``white_balance``, ``half_size``, ``output``) that replace
        those of ``options``.

    Returns
    -------
    np.ndarray
        ``(H, W, 3)`` (``(H / 2, W / 2, 3)`` with ``half_size``), ``uint16`` with the white level
        at 65535, or float32 on ``[0, 1]``.

    Raises
    ------
    InputError
        rawpy is not installed, the file is missing, LibRaw cannot read it, it is larger than
        ``max_pixels`` or it is not a 3-colour sensor.
    """
    if options is None:
        options = path.options if isinstance(path, RawFile) else RawOptions()
    if kwargs:
        options = dataclasses.replace(options, **kwargs)
    name = os.fspath(path)
    rawpy = _rawpy(path)
    with _open(path) as raw:
        sizes = raw.sizes
        pixels = int(sizes.raw_height) * int(sizes.raw_width)
        if pixels > max_pixels:
            raise InputError(
                f"cannot read image '{name}': {sizes.raw_width} x {sizes.raw_height} sensor pixels is more than "
                f"the limit of {max_pixels} pixels (max_pixels; raise it if the image is genuine)"
            )
        try:
            image = raw.postprocess(
                gamma=(1, 1),
                no_auto_bright=True,
                adjust_maximum_thr=0.0,
                output_bps=16,
                output_color=rawpy.ColorSpace.raw,
                user_flip=0,
                half_size=bool(options.half_size),
                use_camera_wb=options.white_balance == "camera",
                user_wb=None if options.white_balance == "camera" else [1.0, 1.0, 1.0, 1.0],
                highlight_mode=rawpy.HighlightMode.Clip,
            )
        except Exception as exc:
            raise InputError(f"cannot decode camera RAW file '{name}': {_reason(exc)}") from exc
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise InputError(f"cannot read camera RAW file '{name}': decoded to shape {image.shape}, expected (H, W, 3)")
    if options.output == "float":
        return np.divide(image, np.float32(65535), dtype=np.float32)
    return image.astype(np.uint16, copy=False)


def sensor_levels(path: PathLike) -> int | None:
    """Return the sensor's levels between black and white (``white - black``), from the file's header.

    The decoded values are ``(raw - black) x 65535 / (white - black)``: one sensor level is
    ``1 / sensor_levels`` of the full scale. None when the file gives no usable levels (white at or
    below black). The black level is the smallest of the channels'.

    Raises
    ------
    InputError
        rawpy is not installed, the file is missing or LibRaw cannot read it.
    """
    with _open(path) as raw:
        black = min(int(b) for b in raw.black_level_per_channel)
        white = int(raw.white_level)
    return white - black if white > black else None


def stack_levels(paths: Sequence[Any]) -> int | None:
    """Return the levels of a stack of camera RAW images: the largest ``white - black`` of their sensors.

    Decoded RAW images are 16-bit, but their levels are the sensor's: the default thresholds
    (shadows one level above black, saturation at the top level, :func:`nplps.pipeline.thresholds`)
    are then one sensor level. None unless every path is a RAW file (:func:`is_raw`) giving its
    levels (:func:`sensor_levels`). ``nplps reconstruct`` and ``nplps batch`` both use it.
    """
    if not paths or not all(is_raw(p) for p in paths):
        return None
    levels = [sensor_levels(p) for p in paths]
    return None if any(n is None for n in levels) else max(n for n in levels if n is not None)


def read_exposure(path: PathLike) -> Exposure:
    """Return a RAW file's shutter time (seconds) and ISO, None where the file does not give them.

    LibRaw's values first; where it has none (it reads ISO from the EXIF directory only), the TIFF
    tags ExposureTime (33434) and ISOSpeedRatings / PhotographicSensitivity (34855) of a
    TIFF-based RAW file (DNG, CR2, NEF, ...), in its first directory or its EXIF directory.

    Raises
    ------
    InputError
        rawpy is not installed, the file is missing or LibRaw cannot read it.
    """
    with _open(path) as raw:
        other = raw.other
        shutter = float(other.shutter_speed) if other.shutter_speed and other.shutter_speed > 0 else None
        iso = float(other.iso_speed) if other.iso_speed and other.iso_speed > 0 else None
    if shutter is None or iso is None:
        tagged = _tiff_exposure(path)
        shutter = tagged.shutter if shutter is None else shutter
        iso = tagged.iso if iso is None else iso
    return Exposure(shutter, iso)


#: The TIFF tags of the exposure: code, and the names tifffile gives them in an EXIF directory.
_EXPOSURE_TAGS = ((33434, ("ExposureTime",)), (34855, ("ISOSpeedRatings", "PhotographicSensitivity")))


def _tiff_exposure(path: PathLike) -> Exposure:
    """Return ExposureTime and ISO from the TIFF tags of ``path`` (None each when absent or not TIFF).

    The first directory's tags first, then its EXIF directory's.
    """
    found: dict[int, Any] = {}
    try:
        with tifffile.TiffFile(os.fspath(path)) as tif:
            tags = tif.pages[0].tags
            exif = tags.get(34665)  # the EXIF directory, read by tifffile into a dict by tag name
            exif_values = exif.value if exif is not None and isinstance(exif.value, dict) else {}
            for code, names in _EXPOSURE_TAGS:
                tag = tags.get(code)
                if tag is not None:
                    found[code] = tag.value
                    continue
                found[code] = next((exif_values[name] for name in names if name in exif_values), None)
    except Exception:  # not a TIFF-based RAW format, or damaged tags: no metadata from here
        return Exposure(None, None)
    return Exposure(_number(found.get(33434)), _number(found.get(34855)))


def _number(value: Any) -> float | None:
    """Return a positive number from a TIFF tag's value (a rational pair, a sequence or a scalar), or None."""
    if value is None:
        return None
    try:
        if isinstance(value, (tuple, list)) and len(value) == 2 and all(isinstance(v, int) for v in value):
            number = value[0] / value[1] if value[1] else 0.0
        elif isinstance(value, (tuple, list, np.ndarray)):
            number = float(np.asarray(value, dtype=np.float64).ravel()[0])
        else:
            number = float(value)
    except (TypeError, ValueError, IndexError, ZeroDivisionError):
        return None
    return number if np.isfinite(number) and number > 0 else None


def exposures_from_metadata(paths: Sequence[PathLike]) -> np.ndarray:
    """Return each image's exposure relative to the first's, from the RAW files' metadata.

    The exposure of an image is its shutter time times its ISO (the sensor's gain is proportional
    to ISO); when no file gives an ISO, the shutter time alone. The first image's is 1, so that
    dividing by them (``exposures=``) keeps the first image's values.

    Raises
    ------
    InputError
        A file is not a RAW file, has no shutter time, or only some files give an ISO; the message
        names the file and suggests giving the exposures by hand.
    """
    fix = "give the exposures by hand (--exposures E1,E2,..., exposures=[...])"
    names = [os.fspath(p) for p in paths]
    if not names:
        raise InputError("exposures from metadata: no image")
    for name in names:
        if not is_raw(name):
            raise InputError(
                f"exposures from metadata: '{name}' is not a camera RAW file ({', '.join(RAW_SUFFIXES)}): "
                f"the exposure is read from RAW files only; {fix}"
            )
    found = [read_exposure(p) for p in paths]
    for name, exposure in zip(names, found, strict=True):
        if exposure.shutter is None:
            raise InputError(f"exposures from metadata: '{name}' gives no shutter time; {fix}")
    with_iso = [e.iso is not None for e in found]
    if any(with_iso) and not all(with_iso):
        missing = names[with_iso.index(False)]
        raise InputError(f"exposures from metadata: '{missing}' gives no ISO but other images do; {fix}")
    values = np.array([(e.shutter or 0.0) * (e.iso or 1.0) for e in found], dtype=np.float64)
    return values / values[0]
