"""Type stubs of the compiled core ``nplps._core`` (Rust, pyo3).

Use the wrappers in :mod:`nplps` rather than these functions directly: they validate and
convert the input.

The boundary passes plain dicts, typed here as TypedDicts and checked against the compiled module
by ``python -m mypy.stubtest nplps._core`` (pydantic-core's way). The core reads every options
mapping strictly: a key that is not declared in its TypedDict is an ``InputError`` naming it and
the valid keys; a missing key (or None) takes the core's default. The TypedDicts exist for type
checkers only: import them under ``typing.TYPE_CHECKING``.

A rig crosses as a :class:`Rig`, built and validated once (``nplps.Rig`` holds it) and passed by
reference to every function that takes a rig; refined and calibrated lights come back as one,
each light of its kind. ``camera`` (of ``Rig``, ``predict``, ``mesh_normals``, ``vertices``,
``calibrate_spheres``) is the rig file's camera mapping (see :class:`CameraDict`; read strictly:
unknown keys are a ``RigError``, keys starting with ``_`` are comments, values may be lists,
tuples or numpy arrays); ``lights`` a mapping of per-light lists (:class:`LightsDict`, built by
``Rig._core_lights``). The progress callback gets the :class:`IterationStats` of each
iteration, whose ``search`` (:class:`SearchProgress`) is None except for the iterations of the
distance search; a result's ``history`` holds the same records. Core errors carry their fields as
attributes (``MemoryLimitError.needed`` / ``.limit``, ``InputError.argument`` / ``.value``, ...).
"""

import os
from collections.abc import Sequence
from typing import Any, final

import numpy as np
import numpy.typing as npt
from typing_extensions import Unpack

from nplps._core_types import (
    F64,
    Camera,
    CameraDict,
    IntensityCalibrationDict,
    IntensityOptions,
    LightsDict,
    ProgressCallback,
    ReconstructionDict,
    ReconstructOptions,
    RigFile,
    SceneDict,
    SceneOptions,
    SolverOptions,
    SphereCalibrationDict,
    SphereImagesDict,
    SphereOptions,
    SphereRenderOptions,
)

__all__ = [
    "MAX_LIGHTS",
    "MULTIGRID_MAX_ITERATIONS",
    "IterationStats",
    "Rig",
    "SearchProgress",
    "__version__",
    "calibrate_intensities",
    "calibrate_spheres",
    "cast_shadows",
    "check_rig",
    "estimate_noise",
    "grey_pixels",
    "mesh_arrays",
    "mesh_normals",
    "normal_map_pixels",
    "normalize_camera",
    "parse_rig",
    "predict",
    "read_pngs",
    "read_rig",
    "reconstruct",
    "reconstruct_parallel",
    "render",
    "synth_board",
    "synth_scene",
    "synth_spheres",
    "trust_figures",
    "vertex_means",
    "vertices",
    "write_ply",
    "write_pngs",
]

__version__: str
#: Most conjugate-gradient iterations of one multigrid global step.
MULTIGRID_MAX_ITERATIONS: int
#: Most lights a rig may have.
MAX_LIGHTS: int

# -- records --------------------------------------------------------------------------------------

@final
class SearchProgress:
    """Where the distance search is, with each of its iterations.

    The candidate (1-based) of how many, its distance and its residual (NaN until its last
    iteration), the best distance so far and its residual (NaN before the first).
    """

    @property
    def candidate(self) -> int: ...
    @property
    def candidates(self) -> int: ...
    @property
    def distance(self) -> float: ...
    @property
    def residual(self) -> float: ...
    @property
    def best_distance(self) -> float: ...
    @property
    def best_residual(self) -> float: ...

@final
class IterationStats:
    """What one local/global iteration did (read by name into :class:`nplps.Iteration`)."""

    @property
    def iteration(self) -> int: ...
    @property
    def depth_change(self) -> float: ...
    @property
    def rms_residual(self) -> float: ...
    @property
    def elapsed(self) -> float: ...
    @property
    def level(self) -> int: ...
    @property
    def inner_iterations(self) -> int: ...
    @property
    def light_change(self) -> float: ...
    @property
    def search(self) -> SearchProgress | None: ...

# -- the rig --------------------------------------------------------------------------------------

@final
class Rig:
    """A rig validated once by the core: camera and lights, each light with its kind."""

    def __new__(cls, camera: Camera, lights: LightsDict) -> Rig: ...
    @property
    def camera(self) -> CameraDict: ...
    @property
    def lights(self) -> LightsDict:
        """The lights mapping, with ``kind``."""
    @property
    def n_lights(self) -> int: ...
    def subset(self, indices: Sequence[int]) -> Rig: ...
    def __reduce__(self) -> tuple[type[Rig], tuple[CameraDict, LightsDict]]: ...

def read_rig(path: str | os.PathLike[str]) -> RigFile:
    """Read a rig file (the core's reader); RigError names the file and the key."""

def parse_rig(text: str, source: str) -> RigFile:
    """Read the JSON text of a rig file; ``source`` names it in the messages."""

# -- functions ------------------------------------------------------------------------------------

def reconstruct(
    images: npt.NDArray[np.float32] | npt.NDArray[np.uint16],
    rig: Rig,
    mask: npt.NDArray[np.bool_] | None,
    depth: float | F64,
    options: ReconstructOptions,
    progress: ProgressCallback | None,
) -> ReconstructionDict:
    """Near-light reconstruction; ``depth`` is the working distance or an (H+1, W+1) map."""

def reconstruct_parallel(
    images: npt.NDArray[np.float32] | npt.NDArray[np.uint16],
    rig: Rig,
    mask: npt.NDArray[np.bool_] | None,
    distance: float | None,
    depth_map: F64 | None,
    options: SolverOptions,
) -> ReconstructionDict:
    """Parallel-light baseline; exactly one of ``distance`` and ``depth_map``."""

def render(
    depth: F64,
    rig: Rig,
    albedo: F64,
    mask: npt.NDArray[np.bool_] | None = None,
    *,
    specular: float | F64 | None = None,
    roughness: float = 0.3,
    eta: float = 1.5,
    shadows: bool = False,
    diffuse: str = "transmitted",
) -> F64: ...
def cast_shadows(
    depth: F64,
    rig: Rig,
    mask: npt.NDArray[np.bool_] | None = None,
    *,
    max_steps: int | None = None,
) -> npt.NDArray[np.bool_]: ...
def estimate_noise(
    images: npt.NDArray[np.float32] | npt.NDArray[np.uint16], mask: npt.NDArray[np.bool_] | None = None
) -> float: ...
def predict(
    depth: F64,
    normals: F64,
    albedo: F64,
    camera: Camera,
    lights: LightsDict,
    mask: npt.NDArray[np.bool_] | None,
    parallel: bool,
    specular: F64 | None = None,
    lobe: tuple[float, float] | None = None,
    diffuse: str = "transmitted",
) -> F64: ...
def mesh_normals(depth: F64, camera: Camera, mask: npt.NDArray[np.bool_] | None = None) -> F64: ...
def grey_pixels(image: F64) -> npt.NDArray[np.uint8]: ...
def normal_map_pixels(
    normals: F64, mask: npt.NDArray[np.bool_] | None, flip: tuple[float, float, float], bits: int
) -> npt.NDArray[Any]: ...
def trust_figures(
    mask: npt.NDArray[np.bool_], sigma: npt.NDArray[Any], held: npt.NDArray[Any]
) -> tuple[int, float, float, float, float, float, float]: ...
def vertices(depth: F64, camera: Camera) -> F64: ...
def vertex_means(values: F64, normalize: bool) -> F64: ...
def mesh_arrays(
    vertices: F64, mask: npt.NDArray[np.bool_], normals: F64 | None, opengl: bool
) -> tuple[
    npt.NDArray[np.int64], npt.NDArray[np.float32], npt.NDArray[np.float32] | None, npt.NDArray[np.int32], int
]: ...
def write_ply(
    path: str | os.PathLike[str],
    vertices: F64,
    mask: npt.NDArray[np.bool_],
    normals: F64 | None,
    albedo: F64 | None,
    per_pixel: bool,
    opengl: bool,
    scale: float | None = None,
    camera: Camera | None = None,
) -> tuple[int, int, int, int]: ...
def check_rig(camera: Camera, lights: LightsDict) -> None: ...
def normalize_camera(camera: Camera) -> CameraDict: ...
def synth_scene(
    name: str, n: int, size: float, distance: float, seed: int, **options: Unpack[SceneOptions]
) -> SceneDict: ...
def read_pngs(
    paths: Sequence[str | os.PathLike[str]], max_pixels: int
) -> list[npt.NDArray[np.uint8] | npt.NDArray[np.uint16]]:
    """Decode PNG files in parallel (GIL released).

    Returns uint8 / uint16 arrays (H, W) or (H, W, 3) as stored (alpha dropped, palettes
    expanded, grey palettes to grey, 1/2/4-bit grey to 0..255). InputError names the first
    missing or broken file, or one above max_pixels pixels.
    """

def write_pngs(
    jobs: Sequence[tuple[str | os.PathLike[str], npt.NDArray[np.uint8] | npt.NDArray[np.uint16]]],
    compression: str,
    filter: str,
) -> None:
    """Write (H, W) / (H, W, 3) uint8 / uint16 arrays as PNG files in parallel (GIL released).

    compression: "none", "fast", "balanced" or "high"; filter: "adaptive", "none", "sub", "up"
    or "paeth". OSError (with filename) for the first file that cannot be written; InputError
    for an array that is not a C-contiguous 8- or 16-bit image (before anything is written).
    """

# -- light calibration (nplps.calibrate) ----------------------------------------------------------
def calibrate_spheres(
    images: Sequence[npt.NDArray[np.float32]],
    labels: Sequence[npt.NDArray[np.uint32] | None],
    detect: Sequence[tuple[float, float, int | None] | None],
    center_depth: Sequence[Sequence[float]],
    camera: Camera,
    radius: float,
    options: SphereOptions,
) -> SphereCalibrationDict:
    """Calibrate the lights from images of shiny spheres.

    Per placement: (k, H, W) images and a (H, W) label image or a detection (min radius, max
    radius, count) in pixels, and centre depths ([], [z] or one per sphere).
    """

def calibrate_intensities(
    images: npt.NDArray[np.float32],
    mask: npt.NDArray[np.bool_] | None,
    rig: Rig,
    normal: Sequence[float],
    offset: float,
    options: IntensityOptions,
) -> IntensityCalibrationDict:
    """Intensity calibration from (k, H, W[, 3]) images of the board ``normal . X = offset``."""

def synth_spheres(
    rig: Rig,
    shape: tuple[int, int],
    centers: Sequence[Sequence[float]],
    radius: float,
    board: tuple[Sequence[float], float] | None,
    options: SphereRenderOptions,
) -> SphereImagesDict:
    """Render (k, H, W) float64 radiance of shiny spheres and their (H, W) uint32 labels."""

def synth_board(
    rig: Rig,
    normal: Sequence[float],
    offset: float,
    albedo: F64,
) -> F64:
    """Render (k, H, W[, 3]) images of a flat board with albedo (H, W[, 3]) by the image model."""
