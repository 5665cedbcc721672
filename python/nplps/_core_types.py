"""The typed boundary of the compiled core ``nplps._core``.

The TypedDicts of its option, rig and result mappings (pydantic-core's way: typed dicts,
checked against the compiled module by ``python -m mypy.stubtest nplps._core``, whose stub
``_core.pyi`` uses them).

The core reads every options mapping strictly: a key that is not declared in its TypedDict is an
``InputError`` naming it and the valid keys; a missing key (or None) takes the core's default.
Keys that a result holds only sometimes are in a ``total=False`` subclass (``refinement``,
``distance_estimate``, ``conditioning``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, Literal, TypedDict

import numpy as np
import numpy.typing as npt

from .types import BoardAlbedo, Outline, RefineLights, Reflectance, Robust, Solver, Status, Weighting

if TYPE_CHECKING:
    from ._core import IterationStats, Rig

F64 = npt.NDArray[np.float64]


# -- the rig --------------------------------------------------------------------------------------


class OrthographicCameraDict(TypedDict):
    """An orthographic camera: pixel footprint (w, h) and the (x, y) of pixel (0, 0)'s corner."""

    model: Literal["orthographic"]
    pixel_size: list[float]
    origin: list[float]


class _PinholeCameraBase(TypedDict):
    model: Literal["pinhole"]
    K: list[list[float]]


class PinholeCameraDict(_PinholeCameraBase, total=False):
    """A pinhole camera: 3 x 3 intrinsics (0-based pixel centres) and OpenCV's distortion.

    The distortion is (k1, k2, p1, p2, k3): the canonical form has all 5; input may omit it, or
    give 2, 4, 5, 8, 12 or 14 coefficients.
    """

    distortion: list[float] | list[list[float]] | None


#: The camera in its canonical form (what ``normalize_camera`` returns).
CameraDict = OrthographicCameraDict | PinholeCameraDict

#: A camera mapping as the core reads it: a :data:`CameraDict`, possibly with ``_`` comment keys
#: and numpy arrays for the lists (which a TypedDict cannot express), checked strictly at runtime.
Camera = Mapping[str, Any]


#: The type of a light (an LED with mu = 0 is still an LED).
LightKind = Literal["point", "led", "directional"]


class _LightsBase(TypedDict):
    vectors: list[list[float]]
    directional: list[bool]
    intensities: list[list[float]]
    axes: list[list[float]]
    mu: list[float]


class LightsDict(_LightsBase, total=False):
    """Per-light lists, one item per light.

    ``vectors`` (positions of point lights, unit directions towards directional lights),
    ``directional`` flags, ``intensities`` (R, G, B), ``axes`` (LED principal directions),
    ``mu`` (LED anisotropy) and ``kind`` (each light's type; read from the lights when missing:
    an LED when mu > 0). ``_core.Rig.lights`` always has ``kind``.
    """

    kind: list[LightKind]


#: A rig file read by the core (``read_rig``, ``parse_rig``): the rig, the grid (None or
#: (image_size or None, binning)) and the top-level comments as (key, JSON text of the value), in
#: the order of the file.
RigFile = tuple["Rig", tuple[tuple[int, int] | None, int] | None, list[tuple[str, str]]]


# -- options --------------------------------------------------------------------------------------


class SolverOptions(TypedDict, total=False):
    """Options of ``reconstruct_parallel`` (and the solver options of ``reconstruct``)."""

    iterations: int | None
    tol: float | None
    dark: float | None
    saturation: float | None
    weighting: Weighting | None
    robust: Robust | Literal["none"] | None
    reflectance: Reflectance | None
    roughness: float | None
    eta: float | None
    shadows: Literal["auto", "on", "off"] | None
    interreflections: bool | None
    threads: int | None
    solver: Solver | None
    levels: int | None
    refine_lights: RefineLights | Literal["none"] | None
    light_prior_weight: float | None
    max_memory: float | None


class ReconstructOptions(SolverOptions, total=False):
    """Options of ``reconstruct``.

    The solver's, the distance search (``auto``, ``depth_range``, ``depth_guess``) and the depth
    prior ((H+1, W+1) ``prior`` with ``prior_weight``).
    """

    auto: bool | None
    check_distance: bool | None
    depth_range: tuple[float, float] | None
    depth_guess: float | None
    prior: F64 | None
    prior_weight: float | None


class SceneOptions(TypedDict, total=False):
    """Variations of a synthetic scene (all false by default)."""

    pinhole: bool
    led: bool
    rgb: bool
    directional: bool


class SphereOptions(TypedDict, total=False):
    """Options of ``calibrate_spheres``."""

    outline: Outline | None
    parallel_tol: float | None
    min_contrast: float | None
    max_blob_fraction: float | None
    limb_margin: float | None
    min_component: int | None
    refine: bool | None


class IntensityOptions(TypedDict, total=False):
    """Options of ``calibrate_intensities``."""

    fit_mu: bool | None
    fit_direction: bool | None
    albedo: BoardAlbedo | None
    dark: float | None
    saturation: float | None
    iterations: int | None


class SphereRenderOptions(TypedDict, total=False):
    """Material of ``synth_spheres`` and its rays per pixel and side (``supersample``)."""

    diffuse: float | None
    specular: float | None
    exponent: float | None
    background: float | None
    supersample: int | None


# -- results --------------------------------------------------------------------------------------


class TimingsDict(TypedDict):
    """Seconds spent in each part of a reconstruction."""

    factorization: float
    local: float
    solve: float
    pyramid: float
    lights: float
    shadows: float
    indirect: float
    total: float


class ConditioningDict(TypedDict):
    """How well the images determine the refined lights."""

    singular_values: list[float]
    standard_errors: list[list[float]]
    rms_residual: float
    distance: float


class _RefinementBase(TypedDict):
    mode: str
    prior_weight: float
    fell_back: bool
    stopped: bool
    residual_without: float
    residual_with: float


class RefinementDict(_RefinementBase, total=False):
    """The light refinement's report (``conditioning`` when it could be computed)."""

    conditioning: ConditioningDict


class DistanceEstimateDict(TypedDict):
    """The estimated working distance of each region and the residual curves."""

    distance: list[float]
    curve: list[list[tuple[float, float]]]
    range: tuple[float, float]


class _ReconstructionBase(TypedDict):
    depth: F64
    normals: F64
    albedo: F64
    residual: F64
    lights_used: npt.NDArray[np.uint32]
    regions: npt.NDArray[np.int32]
    gauge: F64
    history: list[IterationStats]
    converged: bool
    status: Status
    status_reason: str
    negative_observations: int
    timings: TimingsDict
    #: The rig with the final (refined) lights, of the input's kinds.
    lights: Rig


class DistanceCheckDict(TypedDict):
    """A given distance checked by a coarse search (``check_distance``)."""

    given: float
    found: float
    residual_given: float
    residual_found: float
    side: int
    looks_wrong: bool


class LobeCheckDict(TypedDict):
    """The held-out comparison of the glossy and Lambertian models (``reflectance="glossy"``)."""

    glossy: float
    lambertian: float
    observations: int
    seen: int
    highlight: float
    highlight_confirmed: bool


class ReconstructionDict(_ReconstructionBase, total=False):
    """A reconstruction as the core returns it.

    (H+1, W+1) depth, (H, W, 3) normals (the local fits), (H, W[, 3]) albedo, (H, W) residual,
    lights used and regions, the per-region gauge, the history and the status; ``refinement``
    when the lights were refined, ``distance_estimate`` with ``auto``, ``lobe`` and
    ``specular`` with the glossy model.
    """

    refinement: RefinementDict
    distance_estimate: DistanceEstimateDict
    distance_check: DistanceCheckDict
    #: The glossy model's shared lobe (roughness, eta) and the (H, W) specular albedo.
    lobe: tuple[float, float]
    #: The shape of the lobe's diffuse part: "transmitted" or "retro".
    lobe_diffuse: str
    specular: F64
    #: With the glossy model: the estimated lobe that was too rough to be a highlight (the
    #: result is then the Lambertian model's).
    matte_lobe: tuple[float, float]
    #: With the glossy model and the lobe estimated: the held-out RMS prediction errors of the
    #: glossy and the Lambertian model (the Lambertian one was used where it is not larger).
    lobe_check: LobeCheckDict
    #: With ``shadows``: the final level's cast shadows, bit-packed (H, W, ceil(k / 64)) words
    #: (bit k % 64 of word k // 64 is light k).
    shadow_bits: npt.NDArray[np.uint64]
    #: Near-light runs: the (H, W) float32 normal uncertainty (degrees) and leave-one-light-out
    #: error (image units), and per-light residuals (see :class:`LightTrustDict`).
    normal_sigma: npt.NDArray[np.float32]
    held_out_error: npt.NDArray[np.float32]
    light_trust: LightTrustDict


class LightTrustDict(TypedDict):
    """Per light (arrays of k): RMS residual, RMS leave-one-out residual, mean observation, facets."""

    residual: F64
    held_out: F64
    mean_intensity: F64
    facets: F64


class SceneDict(TypedDict):
    """A synthetic scene with ground truth."""

    depth: F64
    mask: npt.NDArray[np.bool_]
    albedo: F64
    rig: Rig
    size: float


class SphereDict(TypedDict):
    """A sphere located by ``calibrate_spheres``."""

    placement: int
    center: list[float]
    radius: float
    image_center: list[float]
    image_radius: float
    fit_rms: float
    outline_points: list[int]
    scale_check: float
    shift: float
    outline_sigma: float


class LightEstimateDict(TypedDict):
    """A light located by ``calibrate_spheres``."""

    kind: Literal["point", "directional", "missing"]
    vector: list[float] | None
    rms_miss: float
    rms_angle: float
    spread: float
    spheres: int
    warning: str | None


class ObservationsDict(TypedDict):
    """Per light and sphere, (k, S[, 2 | 3]) arrays of the highlights and their rays."""

    pixel: F64
    peak: F64
    area: npt.NDArray[np.uint64]
    saturated: npt.NDArray[np.uint64]
    correction: F64
    origin: F64
    direction: F64
    status: list[str]


class SphereRefinementDict(TypedDict):
    """The joint refinement of spheres and lights."""

    iterations: int
    highlights: int
    dropped: int
    highlight_rms: list[float]
    outline_shift: float
    highlight_sigma: float


class _SphereCalibrationBase(TypedDict):
    spheres: list[SphereDict]
    lights: list[LightEstimateDict]
    observations: ObservationsDict
    warnings: list[str]


class SphereCalibrationDict(_SphereCalibrationBase, total=False):
    """The result of ``calibrate_spheres`` (``refinement`` when the joint refinement ran)."""

    refinement: SphereRefinementDict


class IntensityCalibrationDict(TypedDict):
    """The result of ``calibrate_intensities``."""

    #: The rig with the calibrated lights (a point light given mu > 0 is an LED).
    lights: Rig
    intensity: F64
    mu: list[float]
    axes: list[list[float]]
    rms: list[float]
    observations: list[int]
    scale: float
    albedo: F64
    iterations: int
    warnings: list[str]


class SphereImagesDict(TypedDict):
    """Rendered sphere radiance (k, H, W) and the (H, W) labels of the spheres."""

    images: F64
    labels: npt.NDArray[np.uint32]


#: The progress callback: gets the :class:`nplps._core.IterationStats` of each iteration (its
#: ``search`` is set during the distance search only); its return value is ignored.
ProgressCallback = Callable[["IterationStats"], Any]
