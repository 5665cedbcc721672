"""Held-out evaluation for captures without ground truth.

Reconstruct with every light but one, predict the left-out image from the result and the rig,
and compare it with the captured image. A model that explains the data better predicts the
left-out images better; this is how near-light and parallel-light results are compared on real
captures.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import numpy as np

from .api import _check_rig, _light_indices, _short, _thresholds, reconstruct, reconstruct_parallel
from .errors import InputError
from .io import load_stack
from .reconstruction import Reconstruction
from .rig import Rig


class HeldOut(NamedTuple):
    """The held-out error of one light."""

    light: int
    #: ``|prediction - image| / |image|`` over the masked pixels where the image is usable and
    #: the prediction finite.
    relative_error: float
    #: The same after scaling the prediction by the least-squares gain ``a`` (reported below):
    #: the error of the shading's shape, free of the left-out light's intensity calibration,
    #: which no reconstruction from the other lights can know.
    shape_error: float
    #: The gain ``a = <prediction, image> / <prediction, prediction>``.
    gain: float
    #: The reconstruction made without this light.
    result: Reconstruction
    #: The predicted image.
    prediction: np.ndarray


def held_out(
    images: Any,
    rig: Rig,
    mask: Any = None,
    depth: Any = None,
    method: str = "near",
    lights: list[int] | None = None,
    dark: float | None = None,
    saturation: float | None = None,
    **options: Any,
) -> list[HeldOut]:
    """Leaves each light in ``lights`` (default: all) out in turn and reports the relative error
    of its predicted image. ``method`` is "near" (nplps) or "parallel" (the baseline); other
    options go to :func:`nplps.reconstruct`. ``depth`` must be a distance or a depth map (estimate
    it first with ``depth="auto"`` on all lights: leaving a light out should not move it).
    """
    if isinstance(depth, str):
        raise InputError("held_out needs a distance or a depth map; estimate it first with reconstruct(depth='auto')")
    if not (isinstance(method, str) and method in ("near", "parallel")):
        raise InputError(f'method must be "near" or "parallel", got {_short(method)}')
    _check_rig(rig)
    if lights is not None:
        lights = _light_indices(lights, rig.n_lights, negative=False)
    stack, levels = load_stack(images, color=options.get("color") is not False)
    if len(stack) != rig.n_lights:
        raise InputError(
            f"{len(stack)} images were given for {rig.n_lights} lights: there must be one image per light, in the rig's order"
        )
    solve: Callable[..., Reconstruction] = reconstruct if method == "near" else reconstruct_parallel
    if method == "parallel":
        options = {k: v for k, v in options.items() if k in ("robust", "color", "threads", "valid")}
    # Thresholds from the source's bit depth, computed once: the stack handed on is float.
    lo, hi = _thresholds(dark, saturation, levels)
    valid = options.pop("valid", None)
    out = []
    for i in range(rig.n_lights) if lights is None else lights:
        keep = [j for j in range(rig.n_lights) if j != i]
        kept_valid = None if valid is None else np.asarray(valid)[keep]
        result = solve(
            stack[keep], rig.subset(keep), mask, depth, dark=lo, saturation=hi, valid=kept_valid, **options
        )
        prediction = result.predict(rig, lights=[i])[0]
        image = stack[i]
        select = (image > lo) & (image < hi) & np.isfinite(prediction)
        if valid is not None:
            select &= np.asarray(valid)[i][..., None] if image.ndim == 3 else np.asarray(valid)[i]
        if image.ndim == 3:
            select = select.all(axis=-1)
        select &= result.mask
        p, q = prediction[select].ravel(), image[select].ravel()
        norm = np.linalg.norm(q)
        gain = float(np.dot(p, q) / np.dot(p, p))
        error = np.linalg.norm(p - q) / norm
        shape_error = np.linalg.norm(gain * p - q) / norm
        out.append(HeldOut(i, float(error), float(shape_error), gain, result, prediction))
    return out
