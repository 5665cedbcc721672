"""Held-out evaluation for captures without ground truth.

Reconstruct with every light but one, predict the left-out image from the result and the rig,
and compare it with the captured image. A model that explains the data better predicts the
left-out images better; this is how near-light and parallel-light results are compared on real
captures.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

from ._checks import _check_rig, _light_indices, _short
from ._held_out import reading
from .api import _thresholds, reconstruct, reconstruct_parallel
from .errors import InputError
from .io import load_stack
from .reconstruction import Reconstruction
from .rig import Rig
from .types import Images, Mask, Method

__all__ = ["HeldOut", "held_out", "reading"]


class HeldOut(NamedTuple):
    """The held-out error of one light (an entry of :func:`held_out`'s list).

    Attributes
    ----------
    light : int
        Index of the left-out light.
    relative_error : float
        ``|prediction - image| / |image|`` over the masked pixels where the image is usable and
        the prediction finite.
    shape_error : float
        The same after scaling the prediction by the least-squares `gain`: the error of the
        shading's shape, free of the left-out light's intensity calibration, which no
        reconstruction from the other lights can know.
    gain : float
        The gain ``a = <prediction, image> / <prediction, prediction>``.
    result : Reconstruction
        The reconstruction made without this light.
    prediction : numpy.ndarray
        The predicted image.
    """

    light: int
    relative_error: float
    shape_error: float
    gain: float
    result: Reconstruction
    prediction: np.ndarray


def held_out(
    images: Images,
    rig: Rig,
    *,
    depth: float | np.ndarray,
    mask: Mask | None = None,
    method: Method = "near",
    lights: list[int] | None = None,
    dark: float | None = None,
    saturation: float | None = None,
    **options: Any,
) -> list[HeldOut]:
    """Leave each light out in turn and measure how well the rest predict its image.

    Parameters
    ----------
    images : array_like or sequence of str or path-like
        As in :func:`nplps.reconstruct`.
    rig : Rig
        The camera and all the lights.
    depth : float or array_like
        Required, keyword-only: a distance or an (H+1, W+1) depth map, as in
        :func:`nplps.reconstruct`. ``"auto"`` is refused: estimate it first with
        ``reconstruct(..., depth="auto")`` on all lights (leaving a light out should not move it).
    mask : array_like, str or path-like, optional
        As in :func:`nplps.reconstruct`.
    method : {"near", "parallel"}, default "near"
        nplps's near-light method or the parallel-light baseline.
    lights : list of int, optional
        The lights to leave out (indices from 0). Default: all.
    dark, saturation : float, optional
        As in :func:`nplps.reconstruct`, computed once from the images' bit depth; they also
        select the compared pixels of the left-out image.
    **options
        Further keyword arguments of :func:`nplps.reconstruct` (for ``method="parallel"`` only
        ``robust``, ``color``, ``threads`` and ``valid`` are used).

    Returns
    -------
    list of HeldOut
        One entry per left-out light, in the order of `lights`.

    Raises
    ------
    InputError
        An argument is invalid, or ``depth="auto"``.

    Notes
    -----
    The prediction shades each pixel with the left-out reconstruction's fitted normals and
    albedo (:attr:`~nplps.Reconstruction.fit_normals`, see :meth:`~nplps.Reconstruction.predict`):
    the model's own explanation of the images.

    Examples
    --------
    >>> import nplps
    >>> from nplps.evaluation import held_out
    >>> scene = nplps.make_scene("sphere", n=24)
    >>> errors = held_out(scene.images, scene.rig, depth=scene.mean_depth, mask=scene.mask, lights=[0, 1])
    >>> [e.light for e in errors]
    [0, 1]
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
            f"{len(stack)} images were given for {rig.n_lights} lights: "
            "there must be one image per light, in the rig's order"
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
            stack[keep], rig.subset(keep), mask=mask, depth=depth, dark=lo, saturation=hi, valid=kept_valid, **options
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
