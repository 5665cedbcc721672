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
from .api import _thresholds, reconstruct, reconstruct_parallel
from .errors import InputError
from .io import load_stack
from .reconstruction import Reconstruction
from .rig import Rig
from .types import Images, Mask, Method

__all__ = ["HeldOut", "held_out", "reading"]

# Mean shape errors closer than this ratio count as a tie in :func:`reading`.
_TIE_RATIO = 1.05


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


def reading(near: tuple[float, float], parallel: tuple[float, float]) -> str:
    """Return one sentence that reads a held-out comparison: which model predicts better, and by how much.

    Lower errors are better. The judgement is on the mean shape error (free of each left-out
    light's intensity calibration, which no reconstruction from the other lights can know) when
    the mean relative errors agree with it or are within 5 % of each other; when they clearly
    say the opposite, the sentence says so and names the better model on each. Mean shape
    errors within 5 % of each other are a tie.

    Parameters
    ----------
    near, parallel : (float, float)
        Mean (relative error, shape error) of the near-light method and of the parallel-light
        baseline over the left-out lights (:class:`HeldOut`'s ``relative_error`` and
        ``shape_error``).

    Returns
    -------
    str
        The sentence, e.g. ``"reading: the near-light model (nplps) predicts the held-out images
        better than the parallel-light baseline: mean shape error 0.0102 vs 0.0411 (4.0x lower);
        mean relative error 0.0121 vs 0.0456."`` (the better model's numbers first), or ``"reading:
        mixed: the near-light model (nplps) has the lower mean shape error, 0.0474 vs 0.0584 (1.2x
        lower), but the parallel-light baseline the lower mean relative error, 0.19 vs 0.27 (1.4x
        lower); ..."`` when the two measures disagree.

    Examples
    --------
    >>> from nplps.evaluation import reading
    >>> reading((0.02, 0.01), (0.05, 0.04))[:60]
    'reading: the near-light model (nplps) predicts the held-out '
    """
    (near_rel, near_shape), (par_rel, par_shape) = near, parallel
    if not all(np.isfinite(v) for v in (near_rel, near_shape, par_rel, par_shape)):
        return "reading: no comparison (an error is not a number: no usable pixels in a left-out image)"
    names = ("the near-light model (nplps)", "the parallel-light baseline")
    shape_tie = max(near_shape, par_shape) <= _TIE_RATIO * min(near_shape, par_shape)
    rel_tie = max(near_rel, par_rel) <= _TIE_RATIO * min(near_rel, par_rel)
    if shape_tie:
        if not rel_tie:
            better = names[0] if near_rel < par_rel else names[1]
            low, high = sorted((near_rel, par_rel))
            return (
                "reading: the two models predict the shape of the held-out images about equally well: mean shape "
                f"error {near_shape:.3g} (near) vs {par_shape:.3g} (parallel); {better} has the lower mean relative "
                f"error, {low:.3g} vs {high:.3g}{_lower(high, low)}, which also counts each left-out light's "
                "calibrated intensity."
            )
        return (
            "reading: the two models predict the held-out images about equally well: mean shape error "
            f"{near_shape:.3g} (near) vs {par_shape:.3g} (parallel); "
            f"mean relative error {near_rel:.3g} vs {par_rel:.3g}."
        )
    models = [(names[0], near_rel, near_shape), (names[1], par_rel, par_shape)]
    (better, b_rel, b_shape), (worse, w_rel, w_shape) = sorted(models, key=lambda m: m[2])
    if not rel_tie and b_rel > w_rel:
        # The two measures disagree: say so rather than read only one of them.
        return (
            f"reading: mixed: {better} has the lower mean shape error, {b_shape:.3g} vs {w_shape:.3g}"
            f"{_lower(w_shape, b_shape)}, but {worse} the lower mean relative error, {w_rel:.3g} vs {b_rel:.3g}"
            f"{_lower(b_rel, w_rel)}; the shape error leaves out each left-out light's calibrated intensity, "
            "the relative error counts it."
        )
    return (
        f"reading: {better} predicts the held-out images better than {worse}: mean shape error "
        f"{b_shape:.3g} vs {w_shape:.3g}{_lower(w_shape, b_shape)}; mean relative error {b_rel:.3g} vs {w_rel:.3g}."
    )


def _lower(high: float, low: float) -> str:
    """Return " (4.0x lower)" for the ratio ``high / low`` (nothing if it is not finite)."""
    ratio = high / low if low > 0 else np.inf
    return f" ({ratio:.1f}x lower)" if ratio < 10 else f" ({ratio:.0f}x lower)" if np.isfinite(ratio) else ""
