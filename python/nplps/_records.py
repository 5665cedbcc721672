"""The small records of a result, and what the writers of a result read of it.

The distance estimate and check, the light refinement report, and :class:`Result`: what export,
the report, the viewer and the held-out records read of a reconstruction.

They sit below :mod:`nplps.reconstruction` so that the modules which write a result do not import
the module that defines :class:`~nplps.Reconstruction` (which delegates its files to them).
Their public home is :mod:`nplps.reconstruction` (repr, pickles).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from ._atomic import write_text

if TYPE_CHECKING:
    from .rig import Rig
    from .types import Iteration, Method, RefineLights, Status

__all__ = ["DistanceCheck", "DistanceEstimate", "LightRefinement", "Lobe", "LobeCheck", "Result"]


@dataclass(frozen=True)
class Lobe:
    """The specular lobe of the glossy model, shared by the whole object (``reflectance="glossy"``).

    Attributes
    ----------
    roughness : float
        GGX roughness alpha (about 0.05 polished, 0.3 satin, 0.6 rough).
    eta : float
        Relative index of refraction of the surface layer: it sets the Fresnel shape of the lobe
        and, with the ``"transmitted"`` diffuse part, how it falls off at grazing angles (1:
        Lambertian diffuse).
    diffuse : str
        The shape of the diffuse part: ``"transmitted"`` through the rough interface of the lobe
        (rough plastic), or ``"retro"``: Burley's (Disney's principled) diffuse with
        retro-reflection, brighter towards grazing angles the rougher the lobe (see
        docs/method.md).
    """

    roughness: float
    eta: float
    diffuse: str = "transmitted"


@dataclass(frozen=True)
class LobeCheck:
    """Which reflectance model predicts unseen lights better (``reflectance="glossy"``, lobe estimated).

    The lights are split into up to 8 folds; each facet of a subsample (at most 1024) is fitted
    without one fold's lights, by the Lambertian model and by the glossy model under the lobe
    found, and predicts that fold's images. The solver keeps the glossy model only where it
    predicts them better and where the fits that see the lobe (one of their lights within its
    half maximum) confirm its highlight (see docs/method.md, "Which model: held-out prediction").

    Attributes
    ----------
    glossy, lambertian : float
        RMS prediction errors of the held-out observations (image units).
    observations : int
        How many observations (lights x channels of the subsample's facets) were predicted.
    seen : int
        How many of the glossy fits (facets x folds) see the lobe: one of the lights they were
        fitted with lies within its half maximum.
    highlight : float
        The median specular albedo of those fits over that of all the glossy fits (0 when none
        sees the lobe): about 1 on a glossy surface, near 0 where the images show no highlight
        where the lobe puts one.
    highlight_confirmed : bool
        Whether `highlight` reached the solver's threshold (0.01); below it the specular
        albedos were fitted to the lobe's far tail, and the glossy model is dropped.
    """

    glossy: float
    lambertian: float
    observations: int
    seen: int = 0
    highlight: float = 1.0
    highlight_confirmed: bool = True

    @property
    def glossy_wins(self) -> bool:
        """Whether the glossy model predicted the held-out images better and showed its highlight (then kept)."""
        return self.highlight_confirmed and self.glossy < self.lambertian

    def to_dict(self) -> dict[str, float | int | bool]:
        """Return the comparison as a JSON-ready dict."""
        return {
            "glossy": self.glossy,
            "lambertian": self.lambertian,
            "observations": self.observations,
            "seen": self.seen,
            "highlight": self.highlight,
            "highlight_confirmed": self.highlight_confirmed,
            "glossy_wins": self.glossy_wins,
        }


@dataclass
class DistanceEstimate:
    """The working distance estimated from the images (``depth="auto"``).

    Attributes
    ----------
    distance : numpy.ndarray
        Estimated distance of each region (arithmetic mean vertex depth, or geometric mean vertex
        depth for a pinhole camera).
    curve : list of numpy.ndarray
        Per region, the evaluated (distance, residual) pairs, sorted by distance, (N, 2): the RMS
        image residual, or with ``reflectance="glossy"`` the median of the pixels' RMS residuals
        (the search's criterion; see docs/method.md). The CSV column keeps the name
        ``rms_residual``.
    range : (float, float)
        The (near, far) range searched.
    """

    distance: np.ndarray
    curve: list[np.ndarray]
    range: tuple[float, float]

    def save_curve(self, path: str | os.PathLike[str]) -> None:
        """Write the residual curve(s) as CSV.

        Parameters
        ----------
        path : str or path-like
            The file to write: a header ``region,distance,rms_residual`` and one row per
            evaluated distance, plain numbers at full precision (``numpy.loadtxt(path,
            delimiter=",", skiprows=1)`` reads it).
        """
        rows = [f"{r},{float(d)!r},{float(e)!r}" for r, curve in enumerate(self.curve) for d, e in curve]
        write_text(path, "region,distance,rms_residual\n" + "\n".join(rows) + "\n")


@dataclass(frozen=True)
class DistanceCheck:
    """A given working distance checked against the images (``reconstruct(check_distance=True)``).

    After a run at a given distance, a quick distance search on a coarse level (longer side at
    most 64 pixels) finds the distance the images fit best there; both distances are evaluated
    the same way on that level.

    Attributes
    ----------
    given : float
        The given distance (mean over regions of the gauge, as a depth).
    found : float
        The distance the coarse search found.
    residual_given, residual_found : float
        The search's criterion (see :attr:`DistanceEstimate.curve`) on the coarse level at the
        given and at the found distance.
    side : int
        The coarse level's longer side in pixels.
    looks_wrong : bool
        The images fit the found distance better: the residual at the given distance is more
        than 1.02 times the best one and the distances differ by more than 10 % (thresholds measured by
        ``benchmarks/distance_check.py``). ``reconstruct`` then warns "the working distance looks
        wrong".
    """

    given: float
    found: float
    residual_given: float
    residual_found: float
    side: int
    looks_wrong: bool

    @property
    def ratio(self) -> float:
        """``residual_given / residual_found``."""
        return self.residual_given / self.residual_found if self.residual_found > 0 else math.inf

    @property
    def message(self) -> str:
        """One sentence with the numbers (the warning's text when `looks_wrong`)."""
        if self.looks_wrong:
            return (
                f"the working distance looks wrong: the images fit {self.found:.4g} better than the given "
                f"{self.given:.4g} (residual {self.ratio:.3g} times higher at the given distance on a "
                f"{self.side}-pixel level); try --depth auto (depth='auto')"
            )
        return (
            f"the working distance agrees with the images: a {self.side}-pixel level fits {self.found:.4g}, "
            f"the residual at the given {self.given:.4g} is {self.ratio:.3g} times the best"
        )

    def to_dict(self) -> dict[str, Any]:
        """Return the check as a JSON-ready dict (``summary.json``'s ``distance_check``)."""
        return {
            "given": self.given,
            "found": self.found,
            "residual_given": self.residual_given,
            "residual_found": self.residual_found,
            "ratio": self.ratio,
            "side": self.side,
            "looks_wrong": self.looks_wrong,
        }


@dataclass
class LightRefinement:
    """What the self-calibration of the lights (``refine_lights=``) did.

    The refined rig is the result's :attr:`Reconstruction.rig`; the rig given to
    :func:`nplps.reconstruct` is :attr:`Reconstruction.input_rig`.

    Attributes
    ----------
    mode : {"intensity", "position", "both"}
        What was refined.
    prior_weight : float
        Weight of the prior toward the given positions.
    fell_back : bool
        True when refining positions did not lower the photometric residual of a run without
        refinement on the first pyramid level: the given lights were kept.
    stopped : bool
        True when the refinement was stopped early because the photometric residual rose (the
        joint iteration drifted along weakly determined light parameters): the state of lowest
        residual was restored and its lights kept.
    residual_without, residual_with : float
        RMS residual on the first level without / with refinement (NaN when not compared: the
        comparison runs only when positions are refined).
    singular_values : numpy.ndarray or None
        Singular values of the light block of the relative Jacobian after the normals are
        eliminated (positions in units of the working distance), largest first. Their spread
        tells how well the images determine the lights; integrability adds to it.
    standard_errors : numpy.ndarray or None
        Per light (k, 4): standard error of the intensity factor (relative) and of the position
        (x, y, z, scene units); NaN where not refined.
    """

    mode: RefineLights
    prior_weight: float
    fell_back: bool
    stopped: bool
    residual_without: float
    residual_with: float
    singular_values: np.ndarray | None = None
    standard_errors: np.ndarray | None = None

    @property
    def condition_number(self) -> float:
        """Ratio of the largest to the smallest singular value (inf if one is 0, NaN if none)."""
        if self.singular_values is None or len(self.singular_values) == 0:
            return float("nan")
        smallest = float(self.singular_values[-1])
        return float(self.singular_values[0]) / smallest if smallest > 0 else float("inf")

    def to_dict(self) -> dict[str, Any]:
        """Return the refinement as a JSON-ready dict (non-finite numbers as None).

        Returns
        -------
        dict
            The attributes, and ``condition_number``.
        """
        return {
            "mode": self.mode,
            "prior_weight": self.prior_weight,
            "fell_back": self.fell_back,
            "stopped": self.stopped,
            "residual_without": _finite_or_none(self.residual_without),
            "residual_with": _finite_or_none(self.residual_with),
            "condition_number": _finite_or_none(self.condition_number),
            "singular_values": None if self.singular_values is None else [float(v) for v in self.singular_values],
            "standard_errors": None
            if self.standard_errors is None
            else [[_finite_or_none(v) for v in row] for row in self.standard_errors],
        }


def _finite_or_none(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


for _record in (DistanceEstimate, DistanceCheck, LightRefinement):
    _record.__module__ = "nplps.reconstruction"


class Result(Protocol):
    """What the writers of a result read of it: :class:`nplps.Reconstruction` is one.

    Export (``Reconstruction.save``), the report, the viewer and the held-out records take a
    `Result`, so that they need not import the class that calls them.
    """

    depth: np.ndarray
    fit_normals: np.ndarray
    albedo: np.ndarray
    residual: np.ndarray
    lights_used: np.ndarray
    mask: np.ndarray
    rig: Rig
    converged: bool
    status: Status
    method: Method
    history: list[Iteration]
    timings: dict[str, float]
    status_reason: str
    distance: DistanceEstimate | None
    refinement: LightRefinement | None
    distance_check: DistanceCheck | None
    lobe: Lobe | None
    specular: np.ndarray | None
    shadow_bits: np.ndarray | None
    normal_sigma: np.ndarray | None
    held_out_error: np.ndarray | None

    @property
    def shape(self) -> tuple[int, int]: ...
    @property
    def shadows(self) -> np.ndarray | None: ...
    @property
    def vertices(self) -> np.ndarray: ...
    @property
    def normals(self) -> np.ndarray: ...
    @property
    def unfitted(self) -> int: ...
    def vertex_normals(self) -> np.ndarray: ...
    def vertex_albedo(self) -> np.ndarray: ...
    def predict(self, rig: Rig | None = None, *, lights: list[int] | None = None) -> np.ndarray: ...
    def shaded(self, light: Any = None) -> np.ndarray: ...
    def summary(self) -> dict[str, Any]: ...
    def _facts(self) -> dict[str, str]: ...
