"""The input pipeline: from image files or arrays and options to the core's input.

This module is the one place that turns what a user has (image files, arrays, an ambient image,
a flat field, a binning factor, a colour choice) into what the solver takes (a float32 image
stack, a mask, per-observation flags, a rig on the same pixel grid and the thresholds). The
Python API (:mod:`nplps.api`), the capture loaders (:mod:`nplps.captures`) and the command line
(:mod:`nplps.cli`) all call it, so an option means the same thing everywhere. The arithmetic of
each correction lives in :mod:`nplps.preprocess`; this module decides the order, the defaults
and the memory.

Notes
-----
.. rubric:: Order of the steps (:func:`prepare`) and why

1. **Load** (:func:`load_images`): every image goes straight into one preallocated float32
   stack ``(k, H, W[, 3])``, integers scaled to ``[0, 1]`` by their dtype's top value; the
   number of ``levels`` of integer sources is kept (255, 65535), None for floating-point ones.
2. **Saturation** (:func:`saturated`): on the raw values, before anything changes them. Any
   channel at or above the threshold (default: the top level, ``1 - 0.5 / levels``) marks the
   observation: averaging channels would hide a clipped one, and the corrections below move
   the levels.
3. **sRGB decoding** (:func:`decode_srgb`): the tone curve is not linear, so it is undone
   before anything averages or subtracts values (channel mean, ambient, binning).
4. **Grey** (:func:`to_gray`, ``color=False``): the channel mean, as soon as the values are
   linear, so that the remaining steps work on a third of the data.
5. **Ambient** subtraction (clipped at 0), 6. **exposures** (divide image ``i`` by ``e_i``),
   7. **vignetting** (a cos^4 map from K, or a flat field): linear intensities of one light
   only, in the order of the physics (the ambient light is not scaled by the exposure of the
   LED images; the lens darkens both alike).
8. **Binning** (:func:`bin_inputs`): last, because averaging is linear only on corrected
   values (the clip at 0 and the sRGB curve are not), and the maps above are at full
   resolution. Images are averaged over ``n x n`` blocks; mask and flags are kept where the
   whole block is; the rig's camera (K or the pixel size) and a vertex depth map follow.
9. **Thresholds** (:func:`thresholds`): the shadow threshold ``dark`` defaults to one level
   above black (``1 / levels``) only when no step 3, 5-8 ran: those subtractions, divisions and
   averages move the levels, and then the default is 0. The grey average does not count (its
   values stay on the levels' scale).

.. rubric:: Memory

Images are converted to float32 once, when they are read (float32 arrays are taken as they
are, without a copy). No step makes a float64 copy of a stack: float64 arithmetic, where a step
uses it (vignetting maps, binning sums), runs in numpy's buffers or one image at a time. With
``overwrite=True`` (and always for images read from files) the steps work in place; otherwise
the first step that changes the caller's array makes the one copy.

.. rubric:: The dark rule for API users

:func:`nplps.captures.prepare` runs this pipeline and records what ran: its
:class:`~nplps.captures.Capture` carries ``levels``, ``preprocessed`` (the steps) and ``valid``
(the saturation flags), and ``capture.dark`` / ``capture.options()`` give the default the
command line uses, to pass on: ``nplps.reconstruct(cap.images, cap.rig(), depth=...,
**cap.options())``. :func:`nplps.reconstruct` itself, given a float32 array, cannot know where
its values came from and keeps its defaults (0 and no saturation for floating-point images).

.. rubric:: Grey or colour

One keyword names the choice everywhere in the Python API: ``color`` -- None (keep what the
images are: RGB images give an RGB albedo), True (require RGB) or False (average to grey). The
command line's ``--gray`` is ``color=False``.
"""

from __future__ import annotations

import dataclasses
import os
import re
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Literal, TypeAlias

import numpy as np

from . import preprocess
from .errors import InputError
from .io import ImageSource, LoadProgress, PathLike, load_mask, load_stack, read_image, to_float
from .preprocess import to_gray

if TYPE_CHECKING:
    from .rig import Rig

__all__ = [
    "STEPS",
    "Binned",
    "Prepared",
    "StageProgress",
    "bin_depth",
    "bin_inputs",
    "correct",
    "decode_srgb",
    "load_images",
    "natural_key",
    "prepare",
    "saturated",
    "select_color",
    "thresholds",
    "to_gray",
]

#: The names of the pre-processing steps, in the order they run (as listed in ``steps``).
STEPS = ("srgb", "ambient", "exposures", "flat", "vignetting", "bin")

Images: TypeAlias = np.ndarray | Sequence[ImageSource]
SideImage: TypeAlias = PathLike | np.ndarray
#: ``progress(stage, done, total, name)`` of :func:`prepare`: ``("load", i, k, file name)`` after
#: each image is loaded, ``("preprocess", i, 0, step)`` before each step of :data:`STEPS` runs
#: (``i`` counts the steps; their number is not known ahead). :class:`nplps.progress.PipelineProgress`
#: shows them.
StageProgress: TypeAlias = Callable[[str, int, int, str], Any]


# --------------------------------------------------------------------------------------------------
# Thresholds and saturation
# --------------------------------------------------------------------------------------------------


def thresholds(
    levels: int | None, *, dark: float | None = None, saturation: float | None = None, preprocessed: bool = False
) -> tuple[float, float]:
    """Return the shadow and saturation thresholds, on the ``[0, 1]`` scale of the loaded images.

    Parameters
    ----------
    levels : int or None
        The top integer value of the source images (255 for 8-bit, 65535 for 16-bit), or None
        for floating-point images.
    dark : float, optional
        Values at or below it are shadows. Default: one level above black (``1 / levels``) for
        integer images whose values no pre-processing step changed, else 0.
    saturation : float, optional
        Values at or above it are saturated. Default: the top level (``1 - 0.5 / levels``,
        half a level below 1) for integer images, none (``inf``) for floating-point images.
    preprocessed : bool
        True when a pre-processing step (sRGB, ambient, exposures, vignetting, binning) has
        changed the values, which moves the levels: the default ``dark`` is then 0.

    Returns
    -------
    dark, saturation : float
        The thresholds; given values are returned unchanged.
    """
    if dark is None:
        dark = 1.0 / levels if levels and not preprocessed else 0.0
    if saturation is None:
        saturation = 1.0 - 0.5 / levels if levels else float("inf")
    return dark, saturation


def saturated(images: np.ndarray, saturation: float) -> np.ndarray | None:
    """Return the observations with a value at or above ``saturation`` in any channel.

    Parameters
    ----------
    images : ndarray
        A stack ``(k, H, W)`` or ``(k, H, W, C)``, on the scale of ``saturation``.
    saturation : float
        The threshold; ``inf`` (or NaN) flags nothing.

    Returns
    -------
    ndarray of bool or None
        ``(k, H, W)``, True where saturated; None when nothing is.
    """
    if not np.isfinite(saturation):
        return None
    bad = np.asarray(images >= saturation)
    if bad.ndim == 4:
        bad = np.asarray(bad.any(axis=3))
    return bad if bad.any() else None


# --------------------------------------------------------------------------------------------------
# Grey and colour, sRGB
# --------------------------------------------------------------------------------------------------


def select_color(
    stack: np.ndarray, color: bool | None, saturation: float = float("inf")
) -> tuple[np.ndarray, np.ndarray | None]:
    """Apply the colour choice to a loaded stack.

    Parameters
    ----------
    stack : ndarray
        float32 ``(k, H, W)`` or ``(k, H, W, 3)``.
    color : bool or None
        None: keep the stack as it is; True: require RGB; False: average RGB to grey
        (:func:`to_gray`).
    saturation : float
        With ``color=False``, the observations with a channel at or above it are returned as
        saturated (the grey average would hide them).

    Returns
    -------
    stack : ndarray
        The stack, grey when ``color`` is False.
    saturated : ndarray of bool or None
        ``(k, H, W)`` flags of the averaged observations (see :func:`saturated`), or None.

    Raises
    ------
    InputError
        ``color`` is not None, True or False, or True with grey images.
    """
    if not (color is None or isinstance(color, (bool, np.bool_))):
        raise InputError(f"color must be None, True or False, got {color!r}")
    if color and stack.ndim != 4:
        raise InputError("color=True needs RGB images (k, H, W, 3)")
    if stack.ndim != 4 or color is not False:
        return stack, None
    return to_gray(stack), saturated(stack, saturation)


def decode_srgb(images: np.ndarray, *, out: np.ndarray | None = None) -> np.ndarray:
    """Undo the sRGB tone curve (:func:`nplps.preprocess.srgb_to_linear`), image by image.

    ``uint8`` and ``uint16`` input is decoded exactly by a float32 lookup table of every level
    (fast on large camera images); floating-point input by the formula in float32, one image
    at a time (no stack-sized temporaries).

    Parameters
    ----------
    images : ndarray
        A stack ``(k, H, W[, C])`` of floats (float64 is converted to float32 first), or
        integer images of any shape.
    out : ndarray, optional
        float32, where to write the result for floating-point input (``images`` itself works
        in place).

    Returns
    -------
    ndarray
        float32.
    """
    x = np.asarray(images)
    if x.dtype in (np.uint8, np.uint16):
        return _srgb_lut(x.dtype)[x]
    x = to_float(x)  # float32: other integers scaled, float64 converted once
    if out is None:
        out = np.empty(x.shape, dtype=x.dtype)
    if x.ndim < 3:
        out[...] = preprocess.srgb_to_linear(x)
        return out
    for i in range(x.shape[0]):
        out[i] = preprocess.srgb_to_linear(x[i])
    return out


def _srgb_lut(dtype: np.dtype) -> np.ndarray:
    """float32 lookup table of srgb_to_linear for every value of an 8- or 16-bit dtype."""
    top = int(np.iinfo(dtype).max)
    return preprocess.srgb_to_linear(np.arange(top + 1, dtype=np.float64) / top).astype(np.float32)


# --------------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------------


def load_images(
    images: Images, *, max_pixels: int | None = None, progress: LoadProgress | None = None, uint16: bool = False
) -> tuple[np.ndarray, int | None]:
    """Load images as one float32 stack, colour kept (:func:`nplps.io.load_stack`).

    Parameters
    ----------
    images : ndarray or sequence
        A ``(k, H, W[, 3])`` array, or image files and/or ``(H, W[, 3])`` arrays.
    max_pixels : int, optional
        Limit on the size of one file (default :data:`nplps.io.MAX_PIXELS`).
    progress : callable, optional
        ``progress(done, total, name)`` after each image of a sequence is loaded (``name``: the
        file's name).
    uint16 : bool
        Keep 16-bit images as a ``uint16`` stack (see :func:`nplps.io.load_stack`).

    Returns
    -------
    stack : ndarray
        float32 ``(k, H, W)`` or ``(k, H, W, 3)`` (colour only when every image is RGB);
        a float32 array is returned as it is, without a copy; ``uint16`` with `uint16` and
        16-bit images.
    levels : int or None
        The top integer value of the sources, None for floating-point ones.

    Raises
    ------
    InputError
        As :func:`nplps.io.load_stack`.
    """
    if max_pixels is None:
        return load_stack(images, color=True, progress=progress, uint16=uint16)
    return load_stack(images, color=True, max_pixels=max_pixels, progress=progress, uint16=uint16)


def _side_image(source: SideImage, images: np.ndarray, srgb: bool, name: str) -> np.ndarray:
    """Return an ambient or flat-field image on the ``[0, 1]`` scale.

    It is sRGB-decoded with ``srgb``, grey for a grey stack; its size checked against the stack's.
    """
    if isinstance(source, (str, os.PathLike)):
        label = f"{name} '{os.fspath(source)}'"
        image = to_float(read_image(source))
    else:
        label = name
        image = to_float(np.asarray(source))
    if srgb:
        image = decode_srgb(image[None])[0]
    if image.ndim not in (2, 3):
        raise InputError(f"{label}: expected an image (H, W) or (H, W, 3), got shape {image.shape}")
    if image.shape[:2] != images.shape[1:3]:
        raise InputError(
            f"{label} is {image.shape[1]} x {image.shape[0]} pixels but the images are "
            f"{images.shape[2]} x {images.shape[1]}"
        )
    return to_gray(image, stack=False) if images.ndim == 3 else image


# --------------------------------------------------------------------------------------------------
# Corrections
# --------------------------------------------------------------------------------------------------


def correct(
    images: np.ndarray,
    *,
    srgb: bool = False,
    color: bool | None = None,
    ambient: SideImage | None = None,
    exposures: Sequence[float] | np.ndarray | None = None,
    vignetting: Literal["cos4"] | np.ndarray | None = None,
    flat: SideImage | None = None,
    K: np.ndarray | None = None,
    overwrite: bool = False,
    progress: Callable[[str], Any] | None = None,
) -> tuple[np.ndarray, list[str]]:
    """Apply the radiometric corrections, in this order: sRGB, grey, ambient, exposures, vignetting.

    Parameters
    ----------
    images : ndarray
        float32 stack ``(k, H, W)`` or ``(k, H, W, 3)``.
    srgb : bool
        Decode the sRGB tone curve (also of the ambient and flat-field images).
    color : bool or None
        The colour choice (:func:`select_color`), applied once the values are linear.
    ambient : path or ndarray, optional
        The image with every light off, subtracted with a clip at 0 (grey for grey images; a
        grey one applies to every channel of colour images).
    exposures : sequence of float, optional
        ``(k,)`` or ``(k, C)`` factors: image ``i`` is divided by ``exposures[i]``.
    vignetting : "cos4" or ndarray, optional
        Divide by the cos^4 map of the pinhole matrix ``K``, or by this map.
    flat : path or ndarray, optional
        A flat-field image: divide by it, normalized to maximum 1 (not with ``vignetting``).
    K : ndarray, optional
        The (3, 3) pinhole matrix for ``vignetting="cos4"``.
    overwrite : bool
        The caller hands ``images`` over: the steps work in it. Otherwise the first step copies.
    progress : callable, optional
        Called with each step's name (from :data:`STEPS`) before the step runs.

    Returns
    -------
    images : ndarray
        The corrected float32 stack (``images`` itself if nothing ran or ``overwrite``).
    steps : list of str
        The steps that ran, from :data:`STEPS`.

    Raises
    ------
    InputError
        A side image of the wrong size, bad exposures or map, ``vignetting="cos4"`` without
        ``K``, or both ``vignetting`` and ``flat``.
    """
    if flat is not None and vignetting is not None:
        raise InputError("vignetting and flat: give one of them (a flat field is a measured vignetting map)")
    owned = overwrite
    steps: list[str] = []

    def starting(step: str) -> None:
        if progress is not None:
            progress(step)

    if srgb:
        starting("srgb")
        images = decode_srgb(images, out=images if owned else None)
        owned = True
        steps.append("srgb")
    gray = select_color(images, color)[0]
    owned = owned or gray is not images
    images = gray
    if ambient is not None:
        starting("ambient")
        amb = _side_image(ambient, images, srgb, "ambient")
        amb = amb[..., None] if images.ndim > amb.ndim + 1 else amb
        images = preprocess.subtract_ambient(images, amb, out=images if owned else None)
        owned = True
        steps.append("ambient")
    if exposures is not None:
        starting("exposures")
        images = preprocess.scale_exposure(images, exposures, out=images if owned else None)
        owned = True
        steps.append("exposures")
    vmap = None
    if flat is not None:
        starting("flat")
        vmap = preprocess.flat_field_map(_side_image(flat, images, srgb, "flat"))
        steps.append("flat")
    elif isinstance(vignetting, str):
        if vignetting != "cos4":
            raise InputError(f"vignetting must be 'cos4', a map or None, got {vignetting!r}")
        if K is None:
            raise InputError(
                "vignetting 'cos4' needs a pinhole camera (K), but the camera is orthographic: "
                "use a flat field or no vignetting correction"
            )
        starting("vignetting")
        vmap = preprocess.vignetting_cos4(images.shape[1:3], K)
        steps.append("vignetting")
    elif vignetting is not None:
        starting("vignetting")
        vmap = np.asarray(vignetting)
        steps.append("vignetting")
    if vmap is not None:
        images = preprocess.compensate_vignetting(images, vmap, out=images if owned else None)
    return images, steps


# --------------------------------------------------------------------------------------------------
# Binning
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Binned:
    """What :func:`bin_inputs` returns: everything on the binned grid (None where not given).

    Attributes
    ----------
    images : ndarray
        float32 ``(k, H, W)`` or ``(k, H, W, 3)``.
    mask : ndarray or None
        ``(H, W)`` bool, or None (every pixel).
    valid : ndarray or None
        ``(k, H, W)`` bool, False where an observation is left out; None if none is.
    rig : Rig or None
        The rig on the images' grid.
    K : ndarray or None
        The pinhole matrix on the images' grid.
    depth : ndarray or None
        The vertex depth map on the images' grid.
    """

    images: np.ndarray
    mask: np.ndarray | None
    valid: np.ndarray | None
    rig: Any
    K: np.ndarray | None
    depth: np.ndarray | None


def bin_inputs(
    images: np.ndarray,
    factor: int,
    *,
    mask: np.ndarray | None = None,
    valid: np.ndarray | None = None,
    rig: Rig | None = None,
    K: np.ndarray | None = None,
    depth: np.ndarray | None = None,
) -> Binned:
    """Bin images and everything on their pixel grid by ``factor``.

    Images are averaged over ``factor x factor`` blocks (:func:`nplps.preprocess.bin_images`;
    the last ``H mod n`` rows and ``W mod n`` columns are dropped); the mask and the ``valid``
    flags are kept where the whole block is (:func:`nplps.preprocess.bin_mask`); the rig's
    camera follows (K by :func:`nplps.preprocess.bin_intrinsics`, or the orthographic pixel
    size times ``n`` with the origin kept); a vertex depth map keeps every ``n``-th vertex
    (:func:`bin_depth`).

    Parameters
    ----------
    images : ndarray
        float32 ``(k, H, W[, 3])``.
    factor : int
        The block size ``n >= 1`` (1 returns everything unchanged).
    mask : ndarray, optional
        ``(H, W)`` bool.
    valid : ndarray, optional
        ``(k, H, W)`` bool, False where an observation is left out.
    rig : Rig, optional
        The rig of the images.
    K : ndarray, optional
        A (3, 3) pinhole matrix of the images (without a rig).
    depth : ndarray, optional
        An ``(H + 1, W + 1)`` vertex depth map.

    Returns
    -------
    Binned
        The binned values, None where not given.

    Raises
    ------
    InputError
        ``factor`` is not a positive integer, the images are smaller than one block, or no
        block lies wholly inside the mask.
    """
    n = preprocess._check_factor(factor)
    if n == 1:
        return Binned(images, mask, valid, rig, K, depth)
    h, w = images.shape[1:3]
    if n > min(h, w):
        raise InputError(f"bin_factor {n}: the images ({w} x {h} pixels) are smaller than one {n} x {n} block")
    images = preprocess.bin_images(images, n)
    if mask is not None:
        mask = preprocess.bin_mask(mask, n)
        if not mask.any():
            raise InputError(f"bin_factor {n}: no {n} x {n} block lies wholly inside the mask")
    if valid is not None:
        valid = np.stack([preprocess.bin_mask(v, n) for v in valid])
    return Binned(
        images,
        mask,
        valid,
        None if rig is None else rig.binned(n),
        None if K is None else preprocess.bin_intrinsics(K, n),
        None if depth is None else bin_depth(depth, n),
    )


def bin_depth(depth: np.ndarray, factor: int) -> np.ndarray:
    """Return the vertex depth map of images binned by ``factor``: every ``factor``-th vertex.

    The corners of binned pixel ``(i, j)`` are the original vertices ``(n i, n j)`` to
    ``(n i + n, n j + n)``, so binned vertex ``(i, j)`` is original vertex ``(n i, n j)``
    (exact for both cameras: :func:`nplps.preprocess.bin_intrinsics` and the orthographic pixel
    size keep the corners in place).

    Parameters
    ----------
    depth : ndarray
        ``(H + 1, W + 1)`` vertex depths.
    factor : int
        The block size ``n >= 1``.

    Returns
    -------
    ndarray
        ``(H // n + 1, W // n + 1)``, a copy.

    Raises
    ------
    InputError
        ``depth`` is not a 2-D map of at least 2 x 2 vertices, or ``factor`` is not valid.
    """
    n = preprocess._check_factor(factor)
    z = np.asarray(depth)
    if z.ndim != 2 or min(z.shape) < 2:
        raise InputError(f"depth: expected an (H+1, W+1) vertex depth map, got shape {z.shape}")
    h, w = z.shape[0] - 1, z.shape[1] - 1
    return z[: (h // n) * n + 1 : n, : (w // n) * n + 1 : n].copy()


# --------------------------------------------------------------------------------------------------
# The whole pipeline
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Prepared(Binned):
    """What :func:`prepare` returns.

    The core's input, the fields of :class:`Binned` (``images`` C-contiguous float32; ``valid``
    False where an observation was saturated or flagged) and the attributes below.

    Attributes
    ----------
    levels : int or None
        The top integer value of the source images, None for floating-point ones.
    steps : tuple of str
        The pre-processing steps that changed the values (:data:`STEPS`), including those a
        loader ran before (``preprocessed``).
    dark : float
        The shadow threshold: the one given, or the default of :func:`thresholds`.
    """

    levels: int | None = None
    steps: tuple[str, ...] = ()
    dark: float = 0.0


def prepare(
    images: Images,
    *,
    rig: Rig | None = None,
    K: np.ndarray | None = None,
    mask: PathLike | np.ndarray | None = None,
    depth: np.ndarray | None = None,
    color: bool | None = None,
    levels: int | None = None,
    preprocessed: Sequence[str] = (),
    valid: np.ndarray | None = None,
    dark: float | None = None,
    saturation: float | None = None,
    srgb: bool = False,
    ambient: SideImage | None = None,
    exposures: Sequence[float] | np.ndarray | None = None,
    vignetting: Literal["cos4"] | np.ndarray | None = None,
    flat: SideImage | None = None,
    bin_factor: int = 1,
    overwrite: bool = False,
    progress: StageProgress | None = None,
    uint16: bool = False,
) -> Prepared:
    """Turn images and options into the core's input, in the order of the module's docstring.

    Parameters
    ----------
    images : ndarray or sequence
        Image files and/or arrays, or a ``(k, H, W[, 3])`` stack (see :func:`load_images`).
    rig : Rig, optional
        The rig of the images; returned binned with the images.
    K : ndarray, optional
        The pinhole matrix for cos^4 vignetting; default: the rig's.
    mask : path or ndarray, optional
        The pixel mask (non-zero = reconstruct); None keeps None (every pixel).
    depth : ndarray, optional
        An ``(H + 1, W + 1)`` vertex depth map, binned with the images.
    color : bool or None
        None: keep colour; True: require RGB; False: average to grey (see :func:`select_color`).
    levels : int, optional
        The top integer value of the source of a loaded float stack (a capture's ``levels``);
        default: what loading finds.
    preprocessed : sequence of str
        Steps already applied to ``images`` (by a loader): the values are not raw, so no
        default saturation flags, and the default ``dark`` is 0.
    valid : ndarray, optional
        ``(k, H, W)`` bool flags given with the images (False: leave the observation out),
        combined with the saturation flags and binned with the images.
    dark, saturation : float, optional
        Thresholds; defaults from :func:`thresholds`. Saturation is judged on the raw values
        (any channel) and returned in the ``valid`` flags.
    srgb, ambient, exposures, vignetting, flat :
        The corrections of :func:`correct`.
    bin_factor : int
        Average ``n x n`` blocks (:func:`bin_inputs`).
    overwrite : bool
        A float32 stack in ``images`` is handed over and corrected in place (no copy).
    progress : callable, optional
        ``progress(stage, done, total, name)``, see :data:`StageProgress`.
    uint16 : bool
        Keep 16-bit images as they are (a ``uint16`` stack, 2 bytes per value instead of 4, that
        :func:`nplps.reconstruct` reads in place) when nothing changes their values: no
        correction, no binning, no grey average, no `valid`, `levels` and `saturation` the
        defaults. Then no saturation flags are made: the core leaves out the same values, those
        at or above the default threshold of 16-bit images.

    Returns
    -------
    Prepared
        The float32 (or, see `uint16`, ``uint16``) stack, mask, flags, rig, K, depth, levels,
        steps and ``dark``.

    Raises
    ------
    InputError
        Unreadable or inconsistent images, a mask or side image of the wrong size, invalid
        options, or a binning that leaves nothing.
    """
    loaded = None if progress is None else (lambda i, k, name: progress("load", i, k, name))
    as_is = not (srgb or preprocessed or bin_factor != 1 or color is False)
    as_is = as_is and all(v is None for v in (valid, saturation, ambient, exposures, vignetting, flat))
    as_is = as_is and levels in (None, 65535)
    stack, found = load_images(images, progress=loaded, uint16=uint16 and as_is)
    levels = found if levels is None else levels
    counted: list[str] = []

    def starting(step: str) -> None:
        if progress is not None:
            counted.append(step)
            progress("preprocess", len(counted), 0, step)

    owned = overwrite or not (isinstance(images, np.ndarray) and np.may_share_memory(stack, images))
    shape = stack.shape[1:3]
    mask_arr = None if mask is None else load_mask(mask, shape)
    raw = not preprocessed
    _, threshold = thresholds(levels if raw else None, saturation=saturation)
    # Saturation is judged on the raw values, before the corrections overwrite them; a uint16
    # stack (no correction) is judged by the core, with the same threshold.
    bad = None if stack.dtype == np.uint16 else saturated(stack, threshold)
    flags = _valid_flags(valid, bad, stack.shape[:3])
    if K is None and rig is not None:
        K = rig.K
    stack, steps = correct(
        stack,
        srgb=srgb,
        color=color,
        ambient=ambient,
        exposures=exposures,
        vignetting=vignetting,
        flat=flat,
        K=K,
        overwrite=owned,
        progress=starting,
    )
    if rig is not None:
        # A rig saved with a result knows its images' size: images of another size (say the
        # original images with a rig whose K is already binned) are refused with both sizes.
        rig.check_grid(stack.shape[2], stack.shape[1])
    if bin_factor != 1:
        starting("bin")
    binned = bin_inputs(stack, bin_factor, mask=mask_arr, valid=flags, rig=rig, K=K, depth=depth)
    if binned.images is not stack:
        steps.append("bin")
    done = tuple(preprocessed) + tuple(steps)
    dark_, _ = thresholds(levels, dark=dark, preprocessed=bool(done))
    return Prepared(
        images=np.ascontiguousarray(binned.images, dtype=np.uint16 if binned.images.dtype == np.uint16 else np.float32),
        mask=binned.mask,
        valid=binned.valid,
        rig=binned.rig,
        K=binned.K,
        depth=binned.depth,
        levels=levels,
        steps=done,
        dark=dark_,
    )


def _valid_flags(valid: np.ndarray | None, bad: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray | None:
    """Given flags and-ed with not-saturated, or None when neither leaves anything out."""
    if valid is not None:
        v = np.asarray(valid, dtype=bool)
        if v.shape != shape:
            raise InputError(f"valid must have one flag per observation, shape {shape}, got {v.shape}")
        return v if bad is None else v & ~bad
    return None if bad is None else ~bad


# --------------------------------------------------------------------------------------------------
# File order
# --------------------------------------------------------------------------------------------------


def natural_key(name: PathLike) -> tuple[Any, ...]:
    """Sort key of a file name in natural order: numbers compare by value (``img2 < img10``).

    Only the last path component counts. Text compares case-insensitively; numbers come
    before text at the same place; names that still tie (``img02`` / ``img2``, ``A`` / ``a``)
    are ordered by their exact text, so the order never depends on the directory listing.

    Parameters
    ----------
    name : str or path
        A file name or path.

    Returns
    -------
    tuple
        The key for :func:`sorted`.
    """
    text = os.path.basename(os.fspath(name))
    parts = tuple(
        (0, int(part), part) if part.isdigit() else (1, 0, part.lower()) for part in re.split(r"(\d+)", text) if part
    )
    return (parts, text)
