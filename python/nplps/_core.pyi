"""Type stubs of the compiled core ``nplps._core`` (Rust, pyo3). Use the wrappers in
:mod:`nplps` rather than these functions directly: they validate and convert the input."""

from typing import Any, Callable, Mapping

import numpy as np
import numpy.typing as npt

__version__: str

Camera = Mapping[str, Any]
ProgressCallback = Callable[[int, float, float, float], Any]

def reconstruct(
    images: npt.NDArray[np.float32],
    camera: Camera,
    lights: npt.NDArray[np.float64],
    mask: npt.NDArray[np.bool_] | None,
    distance: float | None,
    depth_map: npt.NDArray[np.float64] | None,
    iterations: int,
    tol: float,
    dark: float,
    weighting_name: str,
    threads: int,
    progress: ProgressCallback | None,
) -> dict[str, Any]: ...
def reconstruct_parallel(
    images: npt.NDArray[np.float32],
    camera: Camera,
    lights: npt.NDArray[np.float64],
    mask: npt.NDArray[np.bool_] | None,
    distance: float | None,
    depth_map: npt.NDArray[np.float64] | None,
    dark: float,
    threads: int,
) -> dict[str, Any]: ...
def render(
    depth: npt.NDArray[np.float64],
    camera: Camera,
    lights: npt.NDArray[np.float64],
    albedo: npt.NDArray[np.float64],
    mask: npt.NDArray[np.bool_] | None = None,
) -> npt.NDArray[np.float64]: ...
def mesh_normals(depth: npt.NDArray[np.float64], camera: Camera) -> npt.NDArray[np.float64]: ...
def vertices(depth: npt.NDArray[np.float64], camera: Camera) -> npt.NDArray[np.float64]: ...
def check_rig(camera: Camera, lights: npt.NDArray[np.float64]) -> None: ...
def synth_scene(name: str, n: int, size: float, distance: float, seed: int) -> dict[str, Any]: ...
