"""What is read of a held-out record, and its reading (re-exported by :mod:`nplps.evaluation`).

Below :mod:`nplps.export` and :mod:`nplps.report`, which write and list the records, and
:mod:`nplps.evaluation`, which makes them (:class:`nplps.evaluation.HeldOut`).
"""

from __future__ import annotations

from typing import NamedTuple, Protocol

import numpy as np

__all__ = ["FailedHeldOut", "HeldOutScores", "reading"]

# Mean shape errors closer than this ratio count as a tie in :func:`reading`.
_TIE_RATIO = 1.05


class HeldOutScores(Protocol):
    """What export and the report read of a held-out record (:class:`nplps.evaluation.HeldOut` is one)."""

    @property
    def light(self) -> int: ...
    @property
    def relative_error(self) -> float: ...
    @property
    def shape_error(self) -> float: ...
    @property
    def gain(self) -> float: ...


class FailedHeldOut(NamedTuple):
    """A held-out run that failed (the reconstruction without the light raised `reason`): NaN scores."""

    light: int
    reason: str
    relative_error: float = float("nan")
    shape_error: float = float("nan")
    gain: float = float("nan")


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
