"""Type aliases of the public API: the string options and the argument kinds.

Use them to annotate code that calls nplps::

    from nplps.types import Robust

    def run(images, rig, robust: Robust | None = "tukey"):
        return nplps.reconstruct(images, rig, depth="auto", robust=robust)

Each string option is a :data:`typing.Literal`, so a type checker catches a misspelt value; at run
time a wrong value is an :class:`nplps.InputError` (a ``ValueError``) that names the argument.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from typing import Any, Literal, NamedTuple, TypeAlias

import numpy as np

__all__ = [
    "BoardAlbedo",
    "Camera",
    "Depth",
    "Images",
    "Mask",
    "Method",
    "Outline",
    "Progress",
    "RefineLights",
    "Reflectance",
    "Robust",
    "SceneName",
    "Solver",
    "Status",
    "Weighting",
]

#: Least squares of the local step: ``"image"`` (in image units) or ``"paper"`` (the paper's Eq. 6).
Weighting: TypeAlias = Literal["image", "paper"]
#: Robust reweighting of each pixel's fit (``None``: plain least squares).
Robust: TypeAlias = Literal["cauchy", "tukey"]
#: The reflectance model of each pixel's fit: ``"lambertian"`` (the method's) or ``"glossy"``
#: (diffuse with Fresnel transmittance plus a GGX specular lobe; see docs/method.md).
Reflectance: TypeAlias = Literal["lambertian", "glossy"]
#: How the global step's linear system is solved.
Solver: TypeAlias = Literal["auto", "direct", "multigrid"]
#: Which light parameters ``refine_lights`` refines (``None``: none).
RefineLights: TypeAlias = Literal["intensity", "position", "both"]
#: The reconstruction method: ``"near"`` (nplps) or ``"parallel"`` (the conventional baseline).
Method: TypeAlias = Literal["near", "parallel"]
#: How a reconstruction ended (:attr:`nplps.Reconstruction.status`).
Status: TypeAlias = Literal["converged", "stalled", "diverged", "degenerate"]
#: Camera model of a synthetic scene (:func:`nplps.make_scene`).
Camera: TypeAlias = Literal["orthographic", "pinhole"]
#: The synthetic scenes (:func:`nplps.make_scene`).
SceneName: TypeAlias = Literal["saddle", "sphere", "cube", "bumps", "block"]
#: Where sphere calibration takes each sphere's outline (:func:`nplps.calibrate_spheres`).
Outline: TypeAlias = Literal["mask", "images"]
#: The board's albedo in intensity calibration (:func:`nplps.calibrate_intensities`).
BoardAlbedo: TypeAlias = Literal["uniform", "per_pixel"]

#: Images: a (k, H, W) or (k, H, W, 3) array, or k image files or arrays.
Images: TypeAlias = np.ndarray | Sequence[str | os.PathLike[str] | np.ndarray]
#: A mask: an (H, W) array (non-zero = reconstruct) or a mask image file.
Mask: TypeAlias = np.ndarray | str | os.PathLike[str]
#: The working distance (a number), an (H+1, W+1) initial depth map, or ``"auto"``.
Depth: TypeAlias = float | np.ndarray | Literal["auto"]
#: ``None`` or ``False`` (silent), ``True`` (a line per iteration on stderr) or a callable that
#: gets an :class:`nplps.Iteration` after every iteration.
Progress: TypeAlias = bool | Callable[["Iteration"], Any] | None


class Iteration(NamedTuple):
    """What one local/global iteration did (``result.history``, the ``progress`` callback).

    Attributes
    ----------
    iteration : int
        The iteration's number (from 1, per pyramid level).
    depth_change : float
        Largest vertex depth change of the iteration (scene units).
    rms_residual : float
        RMS image residual over all usable observations (image units).
    elapsed : float
        Seconds since the solver started.
    level : int
        Coarse-to-fine pyramid level (0: full resolution; level l has 2**l times fewer pixels per
        side).
    inner_iterations : int
        Conjugate-gradient iterations of the global step (0 for the direct solver).
    light_change : float
        Largest relative change of a light parameter in the iteration's light step
        (``refine_lights``; 0 otherwise): ``|dPhi| / Phi`` or ``|dp| / D``.
    candidate : int
        0 for the reconstruction's own iterations (the ones in ``result.history``); with
        ``depth="auto"``, the 1-based number of the candidate distance this iteration of the
        distance search evaluates (these iterations reach only the ``progress`` callback).
    candidates : int
        How many candidates the distance search evaluates (0 outside it).
    distance : float
        The candidate's distance (the rig's unit; the mean over regions), NaN outside the search.
    candidate_residual : float
        The candidate's RMS photometric residual, on its last iteration only (NaN otherwise).
    best_distance, best_residual : float
        The evaluated candidate of lowest residual so far and its residual (NaN before the first).
    """

    iteration: int
    depth_change: float
    rms_residual: float
    elapsed: float
    level: int = 0
    inner_iterations: int = 0
    light_change: float = 0.0
    candidate: int = 0
    candidates: int = 0
    distance: float = math.nan
    candidate_residual: float = math.nan
    best_distance: float = math.nan
    best_residual: float = math.nan


def _iteration(stats: Any) -> Iteration:
    """Return the :class:`Iteration` of the core's ``IterationStats`` record, read by its names."""
    plain = {
        "iteration": stats.iteration,
        "depth_change": stats.depth_change,
        "rms_residual": stats.rms_residual,
        "elapsed": stats.elapsed,
        "level": stats.level,
        "inner_iterations": stats.inner_iterations,
        "light_change": stats.light_change,
    }
    search = stats.search
    if search is None:
        return Iteration(**plain)
    return Iteration(
        **plain,
        candidate=search.candidate,
        candidates=search.candidates,
        distance=search.distance,
        candidate_residual=search.residual,
        best_distance=search.best_distance,
        best_residual=search.best_residual,
    )


# The public home of Iteration (``nplps.Iteration``): its repr and pickles are as before the move.
Iteration.__module__ = "nplps.reconstruction"
