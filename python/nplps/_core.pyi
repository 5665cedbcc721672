"""Type stubs of the compiled core ``nplps._core`` (Rust, pyo3). Use the wrappers in
:mod:`nplps` rather than these functions directly: they validate and convert the input.

``camera`` is the rig file's camera mapping; ``lights`` a mapping of per-light lists
(``vectors``, ``directional``, ``intensities``, ``axes``, ``mu``: see ``Rig._core_lights``);
``options`` a mapping with the keyword options of :func:`nplps.reconstruct` (``iterations``,
``tol``, ``dark``, ``saturation``, ``weighting``, ``robust``, ``threads``, ``solver``, ``levels``,
``refine_lights`` ("none", "intensity", "position", "both"), ``light_prior_weight``, and for the
distance search and the prior ``auto``, ``depth_range``, ``depth_guess``, ``prior_weight``). The
progress callback gets (iteration, depth change, rms residual, elapsed seconds, pyramid level,
conjugate-gradient iterations, light change). The result holds ``lights`` (the final lights, as a
lights mapping) and, when refining, ``refinement``."""

import os
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import numpy.typing as npt

__version__: str
#: Most conjugate-gradient iterations of one multigrid global step.
MULTIGRID_MAX_ITERATIONS: int
#: Most lights a rig may have.
MAX_LIGHTS: int

Camera = Mapping[str, Any]
Lights = Mapping[str, list[Any]]
ProgressCallback = Callable[[int, float, float, float, int, int, float], Any]

def reconstruct(
    images: npt.NDArray[np.float32],
    camera: Camera,
    lights: Lights,
    mask: npt.NDArray[np.bool_] | None,
    distance: float | None,
    depth_map: npt.NDArray[np.float64] | None,
    options: Mapping[str, Any],
    progress: ProgressCallback | None,
    prior: npt.NDArray[np.float64] | None = None,
) -> dict[str, Any]: ...
def reconstruct_parallel(
    images: npt.NDArray[np.float32],
    camera: Camera,
    lights: Lights,
    mask: npt.NDArray[np.bool_] | None,
    distance: float | None,
    depth_map: npt.NDArray[np.float64] | None,
    options: Mapping[str, Any],
) -> dict[str, Any]: ...
def render(
    depth: npt.NDArray[np.float64],
    camera: Camera,
    lights: Lights,
    albedo: npt.NDArray[np.float64],
    mask: npt.NDArray[np.bool_] | None = None,
) -> npt.NDArray[np.float64]: ...
def predict(
    depth: npt.NDArray[np.float64],
    normals: npt.NDArray[np.float64],
    albedo: npt.NDArray[np.float64],
    camera: Camera,
    lights: Lights,
    mask: npt.NDArray[np.bool_] | None,
    parallel: bool,
) -> npt.NDArray[np.float64]: ...
def mesh_normals(depth: npt.NDArray[np.float64], camera: Camera) -> npt.NDArray[np.float64]: ...
def vertices(depth: npt.NDArray[np.float64], camera: Camera) -> npt.NDArray[np.float64]: ...
def check_rig(camera: Camera, lights: Lights) -> None: ...
def normalize_camera(camera: Camera) -> dict[str, Any]: ...
def synth_scene(
    name: str,
    n: int,
    size: float,
    distance: float,
    seed: int,
    pinhole: bool = False,
    led: bool = False,
    rgb: bool = False,
    directional: bool = False,
) -> dict[str, Any]: ...
def read_pngs(
    paths: Sequence[str | os.PathLike[str]], max_pixels: int
) -> list[npt.NDArray[np.uint8] | npt.NDArray[np.uint16]]:
    """Decode PNG files in parallel (GIL released): uint8 / uint16 arrays (H, W) or (H, W, 3) as
    stored (alpha dropped, palettes expanded, grey palettes to grey, 1/2/4-bit grey to 0..255).
    InputError names the first missing or broken file, or one above max_pixels pixels."""

# -- light calibration (nplps.calibrate) ----------------------------------------------------------
def calibrate_spheres(
    images: Sequence[npt.NDArray[np.float32]],
    labels: Sequence[npt.NDArray[np.uint32] | None],
    detect: Sequence[tuple[float, float, int | None] | None],
    center_depth: Sequence[Sequence[float]],
    camera: Camera,
    radius: float,
    options: Mapping[str, Any],
) -> dict[str, Any]:
    """Sphere calibration: per placement (k, H, W) images and a (H, W) label image or a detection
    (min radius, max radius, count) in pixels, and centre depths ([], [z] or one per sphere).
    ``options``: ``outline`` ("mask" / "images"), ``parallel_tol`` (degrees), ``min_contrast``,
    ``max_blob_fraction``, ``limb_margin``, ``min_component``, ``refine``. Returns ``spheres``,
    ``lights`` (kind, vector, rms_miss, rms_angle, spread, spheres, warning), ``observations``
    ((k, S[, 2 | 3]) arrays: pixel, peak, area, saturated, correction, origin, direction; status),
    ``warnings`` and ``refinement``."""

def calibrate_intensities(
    images: npt.NDArray[np.float32],
    mask: npt.NDArray[np.bool_] | None,
    camera: Camera,
    lights: Lights,
    normal: Sequence[float],
    offset: float,
    options: Mapping[str, Any],
) -> dict[str, Any]:
    """Intensity calibration from (k, H, W[, 3]) images of the board ``normal . X = offset``.
    ``options``: ``fit_mu``, ``fit_direction``, ``albedo`` ("uniform" / "per_pixel"), ``dark``,
    ``saturation``, ``iterations``. Returns ``lights`` (the lights mapping), ``intensity``
    (k, C), ``mu``, ``axes``, ``rms``, ``observations``, ``scale``, ``albedo``, ``iterations``,
    ``warnings``."""

def synth_spheres(
    camera: Camera,
    lights: Lights,
    height: int,
    width: int,
    centers: Sequence[Sequence[float]],
    radius: float,
    board: tuple[Sequence[float], float] | None,
    material: Mapping[str, float],
    supersample: int,
) -> dict[str, Any]:
    """Renders (k, H, W) float64 radiance of shiny spheres (``material``: ``diffuse``,
    ``specular``, ``exponent``, ``background``) and their (H, W) uint32 labels."""

def synth_board(
    camera: Camera,
    lights: Lights,
    normal: Sequence[float],
    offset: float,
    albedo: npt.NDArray[np.float64],
) -> npt.NDArray[np.float64]:
    """Renders (k, H, W[, 3]) images of a flat board with albedo (H, W[, 3]) by the image model."""
