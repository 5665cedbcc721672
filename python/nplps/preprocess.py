"""Radiometric and geometric preprocessing of photometric-stereo images (pure numpy).

The solver assumes linear intensities that are proportional to the irradiance reaching each
pixel from the LED alone. Real captures need a few corrections first; this module implements
them as small, documented array functions:

* :func:`subtract_ambient` -- remove the light that is there with every LED off;
* :func:`scale_exposure` -- undo per-image exposure times, gains or light intensities;
* :func:`srgb_to_linear` / :func:`linear_to_srgb` -- undo (or apply) the sRGB tone curve of
  JPEG renders;
* :func:`vignetting_cos4`, :func:`flat_field_map`, :func:`compensate_vignetting` -- lens
  vignetting;
* :func:`bin_images`, :func:`bin_mask`, :func:`bin_intrinsics` -- average ``s x s`` pixel blocks
  and the matching pinhole matrix;
* :func:`pad_or_crop` -- bring images onto a grid of another size without moving the origin.

:mod:`nplps.pipeline` decides the order of these steps, their defaults and the memory (the
API, the capture loaders and the command line run them through it).

Notes
-----
.. rubric:: Conventions

* Stacks are ``(k, H, W)`` (grey) or ``(k, H, W, C)`` (colour, normally ``C = 3``); single images
  are ``(H, W)`` or ``(H, W, C)``. Functions that cannot tell a grey stack from a colour image by
  the number of dimensions say how they read a 3-D array.
* Floating-point input keeps its dtype (``float32`` in, ``float32`` out; ``float64`` in,
  ``float64`` out); float32 stacks are never copied to float64 (float64 arithmetic, where a
  step uses it, runs in small buffers or one image at a time). Integer input is first scaled
  to ``[0, 1]`` by :func:`nplps.io.to_float` (``uint8`` / 255, ``uint16`` / 65535), which
  returns ``float32``. ``out=`` lets the stack steps write into an existing array (the input
  itself, to work in place).
* Pixel coordinates are 0-based pixel centres: pixel ``(r, c)`` has its centre at
  ``(u, v) = (c, r)``; the pinhole matrix ``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` maps a
  camera-frame point ``(x, y, z)`` (OpenCV frame: x right, y down, z forward) to
  ``u = (fx x + s y) / z + cx``, ``v = fy y / z + cy``.

Every function raises :class:`~nplps.errors.InputError` on arrays of the wrong shape or with
invalid parameters.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np

from .errors import InputError

__all__ = [
    "bin_images",
    "bin_intrinsics",
    "bin_mask",
    "compensate_vignetting",
    "flat_field_map",
    "linear_to_srgb",
    "pad_or_crop",
    "scale_exposure",
    "srgb_to_linear",
    "subtract_ambient",
    "to_float",
    "to_gray",
    "vignetting_cos4",
]

# IEC 61966-2-1 (sRGB) transfer-function constants.
_SRGB_DECODE_THRESHOLD = 0.04045
_SRGB_ENCODE_THRESHOLD = 0.0031308
_SRGB_LINEAR_SLOPE = 12.92
_SRGB_A = 0.055
_SRGB_GAMMA = 2.4


# --------------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------------


def to_float(img: np.ndarray) -> np.ndarray:
    """Convert pixel values to float32.

    Integer types are scaled to ``[0, 1]`` by the maximum of their dtype (``uint8`` / 255,
    ``uint16`` / 65535, ...); booleans become 0 or 1; floats are returned unchanged (as float32).
    Works on arrays of any shape.

    Raises
    ------
    InputError
        The dtype is not numeric (complex, object, strings, ...).
    """
    img = np.asarray(img)
    if img.dtype == np.bool_:
        return img.astype(np.float32)
    if np.issubdtype(img.dtype, np.integer):
        out = img.astype(np.float32)
        out /= np.float32(np.iinfo(img.dtype).max)  # in place: one float32 copy of the input
        return out
    if np.issubdtype(img.dtype, np.floating):
        return img.astype(np.float32, copy=False)
    raise InputError(f"unsupported image dtype {img.dtype}: expected integers or floats")


def to_gray(images: np.ndarray, *, stack: bool = True) -> np.ndarray:
    """Return the channel mean of colour images, as float32.

    Every grey conversion of nplps goes through here (also as ``nplps.pipeline.to_gray`` and
    behind ``nplps.io.to_gray``), with one arithmetic: the channels are added in float32 in their
    order and the sum is multiplied by ``float32(1 / C)``
    (``(R + G + B) * (1/3)``), in one output array (no float64 and no colour-sized
    temporaries). Integer input is scaled to ``[0, 1]`` first (:func:`to_float`).

    Parameters
    ----------
    images : ndarray
        A stack ``(k, H, W[, C])`` (``stack=True``) or one image ``(H, W[, C])``
        (``stack=False``). Grey input is returned as float32 (no copy if it is float32).
    stack : bool
        How to read a 3-D array: a grey stack ``(k, H, W)`` (True) or a colour image
        ``(H, W, C)`` (False).

    Returns
    -------
    ndarray
        float32, ``(k, H, W)`` or ``(H, W)``.

    Raises
    ------
    InputError
        The array has the wrong number of dimensions or a dtype that is not numeric.
    """
    x = np.asarray(images)
    colour_ndim = 4 if stack else 3
    if x.ndim == colour_ndim - 1:
        return to_float(x)
    if x.ndim != colour_ndim or x.shape[-1] < 1:
        want = "(k, H, W) or (k, H, W, C)" if stack else "(H, W) or (H, W, C)"
        raise InputError(f"expected {want}, got shape {x.shape}")
    if not np.issubdtype(x.dtype, np.floating):
        x = to_float(x)
    channels = x.shape[-1]
    out = np.empty(x.shape[:-1], dtype=np.float32)
    if channels == 1:
        out[...] = x[..., 0]
        return out
    np.add(x[..., 0], x[..., 1], out=out, dtype=np.float32, casting="same_kind")
    for c in range(2, channels):
        np.add(out, x[..., c], out=out, dtype=np.float32, casting="same_kind")
    out *= np.float32(1.0 / channels)
    return out


def _as_float(x: np.ndarray | float, name: str) -> np.ndarray:
    """Return ``x`` as a floating array: floats keep their dtype, integers go through to_float."""
    arr = np.asarray(x)
    if np.issubdtype(arr.dtype, np.floating):
        return arr
    try:
        return to_float(arr)
    except InputError as exc:
        raise InputError(f"{name}: {exc}") from exc


def _output(imgs: np.ndarray, out: np.ndarray | None) -> np.ndarray:
    """Return the array a step writes into: ``out`` (checked; may be ``imgs`` itself) or a new one."""
    if out is None:
        return np.empty(imgs.shape, dtype=imgs.dtype)
    if not isinstance(out, np.ndarray) or out.shape != imgs.shape or out.dtype != imgs.dtype:
        raise InputError(
            f"out: expected an array of shape {imgs.shape} and dtype {imgs.dtype}, got "
            f"{getattr(out, 'shape', None)} {getattr(out, 'dtype', type(out).__name__)}"
        )
    return out


def _spatial_axes(ndim: int, stack: bool, name: str) -> tuple[int, int]:
    """Return the axes (row, column) of an array of ``ndim`` dimensions.

    2-D: ``(H, W)``; 3-D: ``(k, H, W)`` if ``stack`` else ``(H, W, C)``; 4-D: ``(k, H, W, C)``.
    """
    if ndim == 2:
        return 0, 1
    if ndim == 3:
        return (1, 2) if stack else (0, 1)
    if ndim == 4:
        return 1, 2
    raise InputError(f"{name}: expected an image (H, W[, C]) or a stack (k, H, W[, C]), got {ndim} dimensions")


def _check_K(K: np.ndarray) -> np.ndarray:
    """Return ``K`` as a float64 (3, 3) array after basic validity checks."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise InputError(f"K: expected a (3, 3) matrix, got shape {K.shape}")
    if not np.all(np.isfinite(K)):
        raise InputError("K: non-finite entries")
    if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0.0:
        raise InputError(f"K: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(f"K: focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
    return K


# --------------------------------------------------------------------------------------------------
# Ambient light and exposure
# --------------------------------------------------------------------------------------------------


def subtract_ambient(
    images: np.ndarray, ambient: np.ndarray | float, clip: bool = True, *, out: np.ndarray | None = None
) -> np.ndarray:
    """Remove the ambient light: ``J = max(I - A, 0)``.

    With the LEDs off the camera still records ``A`` (room light, dark current, black level).
    Irradiance adds linearly, so the LED-only image is ``I - A``; sensor noise makes it slightly
    negative in dark places, hence the clip at 0 (``clip=True``), which is what the near-light
    toolboxes do. Only meaningful on linear intensities (decode sRGB first).

    Parameters
    ----------
    images : np.ndarray
        A stack ``(k, H, W[, C])`` or a single image ``(H, W[, C])``.
    ambient : np.ndarray | float
        The image with every light off, broadcast against ``images`` with numpy rules:
        ``(H, W[, C])`` for a stack, a per-image stack of the same shape as ``images``, or a
        scalar (black level).
    clip : bool, optional
        Clip the result at 0.
    out : np.ndarray | None, optional
        Optional array for the result, of the shape and floating dtype of ``images``;
        ``images`` itself (when floating) works in place, without a copy.

    Returns
    -------
    np.ndarray
        An array of the shape and floating dtype of ``images`` (``out`` when given).

    Raises
    ------
    InputError
        The shapes do not broadcast to the shape of ``images``, or ``out`` does not
        match.
    """
    imgs = _as_float(images, "images")
    amb = _as_float(ambient, "ambient")
    try:
        shape = np.broadcast_shapes(imgs.shape, amb.shape)
    except ValueError as exc:
        raise InputError(f"ambient of shape {amb.shape} does not broadcast to images of shape {imgs.shape}") from exc
    if shape != imgs.shape:
        raise InputError(f"ambient of shape {amb.shape} does not broadcast to images of shape {imgs.shape}")
    out = _output(imgs, out)
    np.subtract(imgs, amb, out=out)  # a float64 ambient is applied in buffers, not a float64 stack
    if clip:
        np.maximum(out, 0, out=out)
    return out


def scale_exposure(
    images: np.ndarray, exposures: Sequence[float] | np.ndarray, *, out: np.ndarray | None = None
) -> np.ndarray:
    """Divide image ``i`` by ``exposures[i]``: ``J_i = I_i / e_i``.

    Use it to bring images taken with different exposure times, gains or ISO settings, or lit by
    LEDs of different (known) intensities, to a common scale (linear intensities only). DiLiGenT's
    ``light_intensities.txt`` gives one RGB triple per image: pass it as ``(k, 3)`` with a colour
    stack to divide channel by channel.

    Parameters
    ----------
    images : np.ndarray
        A stack ``(k, H, W)`` or ``(k, H, W, C)``.
    exposures : Sequence[float] | np.ndarray
        ``(k,)`` (one factor per image) or ``(k, C)`` (one per image and channel;
        needs a colour stack). Positive and finite.
    out : np.ndarray | None, optional
        Optional array for the result, as in :func:`subtract_ambient`.

    Returns
    -------
    np.ndarray
        An array of the shape and floating dtype of ``images`` (``out`` when given).

    Raises
    ------
    InputError
        Wrong shapes, or a factor that is not positive and finite.
    """
    imgs = _as_float(images, "images")
    if imgs.ndim not in (3, 4):
        raise InputError(f"images: expected a stack (k, H, W[, C]), got shape {imgs.shape}")
    e = np.asarray(exposures, dtype=np.float64)
    k = imgs.shape[0]
    if e.ndim == 1 and e.shape[0] == k:
        factors = e.reshape((k,) + (1,) * (imgs.ndim - 1))
    elif e.ndim == 2 and imgs.ndim == 4 and e.shape == (k, imgs.shape[3]):
        factors = e[:, None, None, :]
    else:
        raise InputError(
            f"exposures: expected shape ({k},) or ({k}, C) for a colour stack, got {e.shape} "
            f"for images of shape {imgs.shape}"
        )
    if not np.all(np.isfinite(e)) or np.any(e <= 0):
        raise InputError("exposures must be positive and finite")
    # Divided in float64 as before, in buffers: no float64 copy of the stack.
    return np.divide(imgs, factors, out=_output(imgs, out))


# --------------------------------------------------------------------------------------------------
# sRGB
# --------------------------------------------------------------------------------------------------


def srgb_to_linear(x: np.ndarray | float) -> np.ndarray:
    """Decode sRGB values to linear light (IEC 61966-2-1).

    For an encoded value ``V`` in ``[0, 1]``::

        L = V / 12.92                         if V <= 0.04045
        L = ((V + 0.055) / 1.055) ** 2.4      otherwise

    e.g. 0 -> 0, 0.04045 -> 0.0031308, 0.5 -> 0.21404, 1 -> 1. Values outside ``[0, 1]`` follow
    the same two formulas (no clipping). Integer input (``uint8`` JPEG renders) is scaled to
    ``[0, 1]`` first. Camera JPEGs are only approximately sRGB (the camera adds its own tone
    curve), so the result is an approximation of the linear sensor signal.

    Returns
    -------
    np.ndarray
        An array of the input's shape; floating input keeps its dtype, integers give float32.
    """
    v = _as_float(x, "srgb_to_linear")
    dtype = v.dtype
    low = v <= _SRGB_DECODE_THRESHOLD
    base = np.where(low, 1.0, (v + _SRGB_A) / (1.0 + _SRGB_A))
    out = np.where(low, v / _SRGB_LINEAR_SLOPE, np.power(base, _SRGB_GAMMA))
    return np.asarray(out, dtype=dtype)


def linear_to_srgb(x: np.ndarray | float) -> np.ndarray:
    """Encode linear values as sRGB (IEC 61966-2-1), the inverse of :func:`srgb_to_linear`.

    For a linear value ``L`` in ``[0, 1]``::

        V = 12.92 L                             if L <= 0.0031308
        V = 1.055 L ** (1 / 2.4) - 0.055        otherwise

    Negative values follow the linear branch; there is no clipping.

    Returns
    -------
    np.ndarray
        An array of the input's shape; floating input keeps its dtype, integers give float32.
    """
    lin = _as_float(x, "linear_to_srgb")
    dtype = lin.dtype
    low = lin <= _SRGB_ENCODE_THRESHOLD
    base = np.where(low, 1.0, lin)
    out = np.where(
        low,
        lin * _SRGB_LINEAR_SLOPE,
        (1.0 + _SRGB_A) * np.power(base, 1.0 / _SRGB_GAMMA) - _SRGB_A,
    )
    return np.asarray(out, dtype=dtype)


# --------------------------------------------------------------------------------------------------
# Vignetting
# --------------------------------------------------------------------------------------------------


def vignetting_cos4(shape: tuple[int, int], K: np.ndarray, dtype: type = np.float32) -> np.ndarray:
    """Return the natural-vignetting ("cos^4 law") map of a pinhole camera.

    The irradiance that a lens delivers to a pixel whose ray makes an angle ``theta`` with the
    optical axis falls off as ``cos(theta)^4``. With ``f = (fx + fy) / 2`` and the pixel-centre
    offsets ``du = u - cx``, ``dv = v - cy`` (``(u, v) = (c, r)``, 0-based)::

        V(r, c) = (f / sqrt(du^2 + dv^2 + f^2)) ** 4 = cos(theta)^4

    which is 1 at the principal point and symmetric about it. Averaging ``fx`` and ``fy`` (and
    ignoring the skew) is the approximation of the near-light toolboxes of Quéau et al.; it is
    exact for square pixels. Divide images by this map (:func:`compensate_vignetting`) to
    compensate. A measured flat field (:func:`flat_field_map`) also captures the lens's optical
    vignetting and is better when available.

    Parameters
    ----------
    shape : tuple[int, int]
        ``(H, W)`` of the images.
    K : np.ndarray
        The (3, 3) pinhole matrix in the 0-based pixel-centre convention.
    dtype : type, optional
        dtype of the result (float32 by default; float64 for full precision).

    Returns
    -------
    np.ndarray
        The map, shape ``(H, W)``, values in ``(0, 1]``.
    """
    if len(shape) != 2 or shape[0] <= 0 or shape[1] <= 0:
        raise InputError(f"shape: expected (H, W) with positive sizes, got {tuple(shape)}")
    K = _check_K(K)
    f = 0.5 * (K[0, 0] + K[1, 1])
    du = np.arange(shape[1], dtype=np.float64) - K[0, 2]
    dv = np.arange(shape[0], dtype=np.float64) - K[1, 2]
    r2 = dv[:, None] ** 2 + du[None, :] ** 2
    cos2 = f * f / (r2 + f * f)
    return (cos2 * cos2).astype(dtype)


def flat_field_map(flat: np.ndarray, ambient: np.ndarray | float | None = None) -> np.ndarray:
    """Normalize a flat-field image into a vignetting map: ``V = F / max(F)``.

    ``flat`` is an image of a uniform, evenly lit target (a white card under diffuse light, or a
    stack of such images, averaged over its first axis if 3-D and not a colour image). When
    ``ambient`` is given it is subtracted first (clipped at 0). A colour flat field
    ``(H, W, C)`` is normalized per channel (``F_c / max(F_c)``), which also corrects the colour
    balance of the lens's fall-off.

    Parameters
    ----------
    flat : np.ndarray
        ``(H, W)``, ``(H, W, C)`` or an ``(n, H, W)`` stack of grey flat fields.
    ambient : np.ndarray | float | None, optional
        Optional dark image or scalar to subtract.

    Returns
    -------
    np.ndarray
        The map in ``(0, 1]`` (float dtype of ``flat``), shape ``(H, W)`` or ``(H, W, C)``.

    Raises
    ------
    InputError
        Wrong shape, non-finite values, or a non-positive maximum.
    """
    f = _as_float(flat, "flat")
    if ambient is not None:
        f = subtract_ambient(f, ambient, clip=True)
    if f.ndim == 3 and f.shape[2] not in (3, 4):
        f = f.mean(axis=0, dtype=np.float64).astype(f.dtype)
    if f.ndim not in (2, 3):
        raise InputError(f"flat: expected (H, W) or (H, W, C), got shape {f.shape}")
    if not np.all(np.isfinite(f)):
        raise InputError("flat: non-finite values")
    peak = f.max(axis=(0, 1), keepdims=True)
    if np.any(peak <= 0):
        raise InputError("flat: the maximum is not positive")
    return (f / peak).astype(f.dtype, copy=False)


def compensate_vignetting(images: np.ndarray, vignetting: np.ndarray, *, out: np.ndarray | None = None) -> np.ndarray:
    """Divide by a vignetting map: ``J = I / V``.

    The map's ``(H, W)`` is matched against the trailing axes of ``images``: an ``(H, W)`` map
    divides ``(k, H, W)`` and ``(H, W)`` directly, and ``(k, H, W, C)`` and ``(H, W, 3)``
    channel by channel.

    Parameters
    ----------
    images : np.ndarray
        A stack ``(k, H, W[, C])`` or a single image ``(H, W[, C])``.
    vignetting : np.ndarray
        ``(H, W)`` (a :func:`vignetting_cos4` map or a grey flat field) or
        ``(H, W, C)`` (a colour flat field from :func:`flat_field_map`, for colour images).
        Strictly positive.
    out : np.ndarray | None, optional
        Optional array for the result, as in :func:`subtract_ambient`.

    Returns
    -------
    np.ndarray
        An array of the shape and floating dtype of ``images`` (``out`` when given).

    Raises
    ------
    InputError
        The map's size does not match the images, or it has values <= 0 / non-finite.
    """
    imgs = _as_float(images, "images")
    vmap = np.asarray(vignetting, dtype=np.float64)
    if vmap.ndim == 2:
        if imgs.ndim >= 2 and imgs.shape[-2:] == vmap.shape:
            div = vmap
        elif imgs.shape[-3:-1] == vmap.shape and (imgs.ndim == 4 or (imgs.ndim == 3 and imgs.shape[-1] == 3)):
            div = vmap[..., None]
        else:
            raise InputError(f"vignetting map of shape {vmap.shape} does not match images of shape {imgs.shape}")
    elif vmap.ndim == 3 and imgs.ndim >= 3 and imgs.shape[-3:] == vmap.shape:
        div = vmap
    else:
        raise InputError(f"vignetting map of shape {vmap.shape} does not match images of shape {imgs.shape}")
    if not np.all(np.isfinite(vmap)) or np.any(vmap <= 0):
        raise InputError("vignetting map must be positive and finite everywhere")
    # The division runs in float64 (the map is float64) in buffers: no float64 copy of the stack.
    return np.divide(imgs, div, out=_output(imgs, out))


# --------------------------------------------------------------------------------------------------
# Binning
# --------------------------------------------------------------------------------------------------


def _check_factor(factor: int) -> int:
    """Return ``factor`` as a positive int, or raise InputError."""
    if isinstance(factor, (bool, np.bool_)) or int(factor) != factor or int(factor) < 1:
        raise InputError(f"binning factor must be a positive integer, got {factor!r}")
    return int(factor)


def _block_view(x: np.ndarray, factor: int, axes: tuple[int, int], name: str) -> np.ndarray:
    """Crop ``x`` to multiples of ``factor`` along ``axes`` and split each into (n, factor)."""
    ra, ca = axes
    h, w = x.shape[ra], x.shape[ca]
    hb, wb = h // factor, w // factor
    if hb == 0 or wb == 0:
        raise InputError(f"{name}: {w} x {h} pixels is smaller than one {factor} x {factor} block")
    index = [slice(None)] * x.ndim
    index[ra] = slice(0, hb * factor)
    index[ca] = slice(0, wb * factor)
    cropped = x[tuple(index)]
    new_shape = (*cropped.shape[:ra], hb, factor, *cropped.shape[ra + 1 : ca], wb, factor, *cropped.shape[ca + 1 :])
    return cropped.reshape(new_shape)


def bin_images(images: np.ndarray, factor: int, stack: bool = True) -> np.ndarray:
    """Average non-overlapping ``factor x factor`` pixel blocks.

    Binned pixel ``(i, j)`` is the mean of the original pixels ``(factor i + a, factor j + b)``,
    ``0 <= a, b < factor``::

        J[i, j] = (1 / s^2) sum_{a, b < s} I[s i + a, s j + b]      (s = factor)

    The last ``H mod s`` rows and ``W mod s`` columns are dropped (cropping at the bottom/right
    keeps the top-left origin, so :func:`bin_intrinsics` applies unchanged). Averaging is linear,
    so bin linear intensities (decode sRGB first); it divides the noise standard deviation by
    ``s`` and the data by ``s^2``. The sums are accumulated in float64.

    Parameters
    ----------
    images : np.ndarray
        ``(H, W)``, ``(k, H, W)``, ``(k, H, W, C)``; a 3-D array is a grey stack
        ``(k, H, W)`` unless ``stack=False``, which reads it as one colour image
        ``(H, W, C)``.
    factor : int
        The block size ``s >= 1`` (1 returns a copy).
    stack : bool, optional
        How to read a 3-D array (see above).

    Returns
    -------
    np.ndarray
        The binned array, shape with ``H // s`` and ``W // s``; floating dtype of the input.
    """
    s = _check_factor(factor)
    x = _as_float(images, "images")
    ra, ca = _spatial_axes(x.ndim, stack, "images")
    blocks = _block_view(x, s, (ra, ca), "images")
    # After splitting, the block axes sit at ra + 1 and ca + 2.
    if ra == 0:
        return blocks.mean(axis=(ra + 1, ca + 2), dtype=np.float64).astype(x.dtype)
    # A stack: one image at a time, so that the float64 sums take one binned image of memory.
    shape = list(x.shape)
    shape[ra] //= s
    shape[ca] //= s
    out = np.empty(shape, dtype=x.dtype)
    for i in range(out.shape[0]):
        out[i] = blocks[i].mean(axis=(ra, ca + 1), dtype=np.float64)
    return out


def bin_mask(mask: np.ndarray, factor: int, rule: Literal["all", "half"] = "all") -> np.ndarray:
    """Bin a 2-D pixel mask into ``factor x factor`` blocks.

    With ``rule="all"`` (the default) a binned pixel is selected only if **every** pixel of its
    block is: the binned image then only averages selected pixels, so no background or occluding
    edge leaks into a binned pixel. ``rule="half"`` selects it when at least half of its block
    is (``count >= s^2 / 2``), which keeps the silhouette's area better. The remainder rows and
    columns are cropped as in :func:`bin_images`.

    Parameters
    ----------
    mask : np.ndarray
        ``(H, W)`` array; nonzero (and not NaN) means selected.
    factor : int
        Block size ``s >= 1``.
    rule : Literal[all, half], optional
        ``"all"`` or ``"half"``.

    Returns
    -------
    np.ndarray
        Bool array of shape ``(H // s, W // s)``.
    """
    s = _check_factor(factor)
    m = np.asarray(mask)
    if m.ndim != 2:
        raise InputError(f"mask: expected shape (H, W), got {m.shape}")
    if np.issubdtype(m.dtype, np.floating):
        m = (m != 0) & ~np.isnan(m)
    else:
        m = m != 0
    counts = _block_view(m.astype(np.int64), s, (0, 1), "mask").sum(axis=(1, 3))
    if rule == "all":
        return counts == s * s
    if rule == "half":
        return 2 * counts >= s * s
    raise InputError(f"bin_mask: rule must be 'all' or 'half', got {rule!r}")


def bin_intrinsics(K: np.ndarray, factor: float) -> np.ndarray:
    """Return the pinhole matrix of images binned by ``factor`` (see :func:`bin_images`).

    Binned pixel ``j`` averages the original pixels ``s j .. s j + s - 1``, whose centres have the
    mean coordinate ``s j + (s - 1) / 2``. An original coordinate ``u`` therefore becomes
    ``u' = (u + 1/2) / s - 1/2`` (exact for the 0-based pixel-centre convention), and since
    ``u = (fx x + skew y) / z + cx``::

        fx' = fx / s      skew' = skew / s      cx' = (cx + 1/2) / s - 1/2
        fy' = fy / s                            cy' = (cy + 1/2) / s - 1/2

    Cropping the remainder at the bottom/right does not change K. ``factor`` may be any positive
    number: ``1 / s`` gives the matrix of an image upsampled ``s`` times (e.g. from a 2 x 2-binned
    RAW grid back to a full-size JPEG render).

    Parameters
    ----------
    K : np.ndarray
        (3, 3) pinhole matrix, 0-based pixel-centre convention.
    factor : float
        The binning factor ``s > 0``.

    Returns
    -------
    np.ndarray
        The new (3, 3) float64 matrix.
    """
    K = _check_K(K)
    s = float(factor)
    if not np.isfinite(s) or s <= 0:
        raise InputError(f"binning factor must be positive, got {factor!r}")
    out = K.copy()
    out[0, 0] = K[0, 0] / s
    out[0, 1] = K[0, 1] / s
    out[1, 1] = K[1, 1] / s
    out[0, 2] = (K[0, 2] + 0.5) / s - 0.5
    out[1, 2] = (K[1, 2] + 0.5) / s - 0.5
    return out


# --------------------------------------------------------------------------------------------------
# Padding and cropping
# --------------------------------------------------------------------------------------------------


def pad_or_crop(
    image: np.ndarray,
    shape: tuple[int, int],
    mode: Literal["constant", "edge"] = "constant",
    value: float = 0.0,
    stack: bool = True,
    offset: tuple[int, int] = (0, 0),
) -> np.ndarray:
    """Bring an image or stack to ``shape = (H', W')`` by padding or cropping.

    With the default ``offset=(0, 0)`` everything happens at the bottom/right: rows
    ``H' <= r < H`` and columns ``W' <= c < W`` are dropped, missing rows/columns are added after
    the last ones. Pixel ``(r, c)`` keeps its coordinates, so a pinhole matrix K that describes
    the input grid also describes the output grid.

    ``offset = (top, left)`` places input pixel ``(r, c)`` at output pixel ``(r + top, c + left)``
    instead (negative values crop at the top/left). Use it to register images onto a calibration
    grid whose origin is elsewhere; K of the *output* grid is then the calibration's K.

    Added pixels are filled with ``value`` (``mode="constant"``) or with copies of the nearest
    edge row/column (``mode="edge"``). Any dtype (bool masks included) is kept.

    Parameters
    ----------
    image : np.ndarray
        ``(H, W)``, ``(k, H, W)``, ``(k, H, W, C)``; a 3-D array is ``(k, H, W)`` unless
        ``stack=False`` (then ``(H, W, C)``).
    shape : tuple[int, int]
        Target ``(H', W')``.
    mode : Literal[constant, edge], optional
        ``"constant"`` or ``"edge"``.
    value : float, optional
        Fill value of ``mode="constant"``.
    stack : bool, optional
        How to read a 3-D array.
    offset : tuple[int, int], optional
        ``(top, left)`` shift of the content, in pixels.

    Returns
    -------
    np.ndarray
        The array with its spatial size replaced by ``shape``.
    """
    x = np.asarray(image)
    if len(shape) != 2 or int(shape[0]) <= 0 or int(shape[1]) <= 0:
        raise InputError(f"shape: expected (H, W) with positive sizes, got {tuple(shape)}")
    if mode not in ("constant", "edge"):
        raise InputError(f"pad_or_crop: mode must be 'constant' or 'edge', got {mode!r}")
    if len(offset) != 2 or any(int(o) != o for o in offset):
        raise InputError(f"offset: expected two integers (top, left), got {offset!r}")
    ra, ca = _spatial_axes(x.ndim, stack, "image")
    target = (int(shape[0]), int(shape[1]))
    index = [slice(None)] * x.ndim
    pad = [(0, 0)] * x.ndim
    for axis, size, shift in ((ra, target[0], int(offset[0])), (ca, target[1], int(offset[1]))):
        # Output position p holds input position p - shift, for 0 <= p < size.
        start = max(0, -shift)  # first input index kept
        stop = min(x.shape[axis], size - shift)  # one past the last input index kept
        if stop <= start:
            raise InputError(f"pad_or_crop: offset {tuple(offset)} moves the image entirely out of {target}")
        index[axis] = slice(start, stop)
        before = max(0, shift)
        pad[axis] = (before, size - before - (stop - start))
    x = x[tuple(index)]
    if all(p == (0, 0) for p in pad):
        return x.copy()
    if mode == "edge":
        return np.pad(x, pad, mode="edge")
    return np.pad(x, pad, mode="constant", constant_values=np.asarray(value).astype(x.dtype))
