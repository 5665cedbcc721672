"""Pre-processing of the loaded images for the command line: saturation flags, grey, sRGB, ambient,
exposures, vignetting / flat field, and binning of images, mask and rig."""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

from ..errors import InputError
from .parsers import parse_exposures


def saturation_valid(raw: np.ndarray, levels: int | None, saturation: float | None) -> np.ndarray | None:
    """(k, H, W) flags, False where a raw value (any channel) is at or above the saturation level
    (--saturation, or the top level of integer images); None when nothing is saturated."""
    if saturation is None:
        if levels is None:
            return None
        saturation = 1.0 - 0.5 / levels
    bad = raw >= saturation
    if bad.ndim == 4:
        bad = bad.any(axis=3)
    return ~bad if bad.any() else None


def _to_gray(images: np.ndarray) -> np.ndarray:
    return images.mean(axis=3, dtype=np.float32) if images.ndim == 4 else images


def preprocess_images(
    images: np.ndarray, args: argparse.Namespace, K: np.ndarray | None, in_place: bool = False
) -> tuple[np.ndarray, list[str]]:
    """--srgb, --ambient, --exposures, --vignetting / --flat, in this order; returns the images
    and the list of the steps done. ``in_place``: the caller hands ``images`` over, and the
    steps overwrite it instead of copying it (the first step copies otherwise)."""
    from .. import preprocess

    steps = []
    if args.srgb:
        images = preprocess.srgb_to_linear(images)
        in_place = True
        steps.append("sRGB decoded")
    if args.ambient:
        ambient = _side_image(args.ambient, "--ambient", images, args.srgb)
        ambient = ambient[..., None] if images.ndim > ambient.ndim + 1 else ambient
        images = preprocess.subtract_ambient(images, ambient, out=images if in_place else None)
        in_place = True
        steps.append(f"ambient '{args.ambient}' subtracted")
    if args.exposures:
        exposures = parse_exposures(args.exposures, images.shape[0])
        images = preprocess.scale_exposure(images, exposures, out=images if in_place else None)
        in_place = True
        steps.append("divided by the exposures")
    vmap, vstep = vignetting_map(args, K, images, default="none")
    if vmap is not None:
        images = preprocess.compensate_vignetting(images, vmap, out=images if in_place else None)
        steps.append(vstep)
    return images, steps


def vignetting_map(
    args: argparse.Namespace, K: np.ndarray | None, images: np.ndarray, default: str
) -> tuple[np.ndarray | None, str]:
    """The map to divide by (--flat, or cos^4 from K), or None; and what it is."""
    from .. import preprocess

    if args.flat:
        flat = preprocess.flat_field_map(_side_image(args.flat, "--flat", images, args.srgb))
        return flat, f"divided by the flat field '{args.flat}'"
    if (args.vignetting or default) != "cos4":
        return None, ""
    if K is None:
        raise InputError(
            "--vignetting cos4 needs a pinhole camera (K), but the rig's camera is orthographic: "
            "use --flat FILE or --vignetting none"
        )
    return preprocess.vignetting_cos4(images.shape[1:3], K), "divided by the cos^4 vignetting map"


def _side_image(path: str, option: str, images: np.ndarray, srgb: bool) -> np.ndarray:
    """An --ambient or --flat image on the 0..1 scale (sRGB decoded with --srgb), grey for grey images."""
    from .. import preprocess
    from ..io import read_image, to_float

    image = to_float(read_image(path))
    if srgb:
        image = preprocess.srgb_to_linear(image)
    if image.shape[:2] != images.shape[1:3]:
        raise InputError(
            f"{option} '{path}' is {image.shape[1]} x {image.shape[0]} pixels but the images are "
            f"{images.shape[2]} x {images.shape[1]}"
        )
    return _to_gray(image[None])[0] if images.ndim == 3 else image


def bin_inputs(
    images: np.ndarray, rig: Any, mask: np.ndarray | None, valid: np.ndarray | None, n: int
) -> tuple[np.ndarray, Any, np.ndarray | None, np.ndarray | None]:
    """--bin N: images averaged over N x N blocks; mask and valid flags kept where the whole block
    is; the rig's K (pinhole) or pixel size (orthographic) adjusted."""
    from .. import preprocess

    h, w = images.shape[1:3]
    if n > min(h, w):
        raise InputError(f"--bin {n}: the images ({w} x {h} pixels) are smaller than one {n} x {n} block")
    images = preprocess.bin_images(images, n)
    mask = None if mask is None else preprocess.bin_mask(mask, n)
    if mask is not None and not mask.any():
        raise InputError(f"--bin {n}: no {n} x {n} block lies wholly inside the mask")
    valid = None if valid is None else np.stack([preprocess.bin_mask(v, n) for v in valid])
    return images, bin_rig(rig, n), mask, valid


def bin_rig(rig: Any, n: int) -> Any:
    """The rig of images binned by n: K by :func:`nplps.preprocess.bin_intrinsics` (pinhole), or
    the pixel size times n with the origin kept at the top-left corner (orthographic)."""
    return rig.binned(n)
