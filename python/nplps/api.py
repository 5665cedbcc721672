"""The Python API: reconstruct, the parallel-light baseline, and rendering."""

from __future__ import annotations

import sys
import warnings
from typing import Any, Callable, Sequence, Union

import numpy as np

from . import _core
from .errors import InputError
from .io import load_images, load_mask
from .reconstruction import Iteration, Reconstruction
from .rig import Rig

Images = Union[np.ndarray, Sequence[Any]]
Depth = Union[float, np.ndarray]
Progress = Union[None, bool, Callable[[Iteration], Any]]


def _prepare(images: Images, rig: Rig, mask: Any, depth: Depth | None) -> tuple[np.ndarray, np.ndarray, float | None, np.ndarray | None]:
    if not isinstance(rig, Rig):
        raise InputError(f"rig must be an nplps.Rig, got {type(rig).__name__}")
    stack = np.ascontiguousarray(load_images(images), dtype=np.float32)
    k, h, w = stack.shape
    if k != rig.n_lights:
        raise InputError(f"{k} images were given for {rig.n_lights} lights: there must be one image per light, in the rig's order")
    mask_arr = np.ascontiguousarray(load_mask(mask, (h, w)))
    if depth is None:
        raise InputError(
            "depth is required: give the working distance (the object's mean depth, in the rig's unit) "
            "or an (H+1, W+1) initial depth map; a wrong distance bends the result"
        )
    if np.isscalar(depth) or np.ndim(depth) == 0:
        d = float(depth)  # type: ignore[arg-type]
        if not np.isfinite(d) or d <= 0:
            raise InputError(f"the working distance must be a positive finite number, got {depth!r}")
        return stack, mask_arr, d, None
    depth_map = np.ascontiguousarray(np.asarray(depth, dtype=np.float64))
    if depth_map.shape != (h + 1, w + 1):
        raise InputError(
            f"the initial depth map has shape {depth_map.shape}; it must have one value per vertex, "
            f"(H+1, W+1) = {(h + 1, w + 1)} for {h} x {w} images"
        )
    return stack, mask_arr, None, depth_map


def _warn_negative(count: int, dark: float) -> None:
    if count:
        treated = "they were treated as unlit" if dark >= 0 else f"those above dark = {dark} were used"
        warnings.warn(
            f"{count} pixel values inside the mask are negative (dark-frame subtraction?); {treated}",
            RuntimeWarning,
            stacklevel=3,
        )


def _progress_callback(progress: Progress, iterations: int) -> Callable[..., None] | None:
    if progress is None or progress is False:
        return None
    if progress is True:

        width = len(str(iterations))

        def report(it: Iteration) -> None:
            print(
                f"iteration {it.iteration:>{width}}/{iterations}: depth change {it.depth_change:.3e}, "
                f"rms residual {it.rms_residual:.3e}, {it.elapsed:.2f} s",
                file=sys.stderr,
                flush=True,
            )

        user: Callable[[Iteration], Any] = report
    elif callable(progress):
        user = progress
    else:
        raise InputError(f"progress must be None, True or a callable, got {progress!r}")

    def call(iteration: int, depth_change: float, rms: float, elapsed: float) -> None:
        user(Iteration(iteration, depth_change, rms, elapsed))

    return call


def reconstruct(
    images: Images,
    rig: Rig,
    mask: Any = None,
    depth: Depth | None = None,
    iterations: int = 10,
    tol: float = 1e-6,
    progress: Progress = None,
    dark: float = 0.0,
    weighting: str = "image",
    threads: int | None = None,
) -> Reconstruction:
    """Reconstructs a surface from k images taken under k near point lights.

    Args:
        images: (k, H, W) or (k, H, W, 3) array, or k image files / arrays (8/16-bit PNG, TIFF,
            ...), one per light in the rig's order. Integer images are scaled to [0, 1]; RGB
            becomes grey (mean of the channels).
        rig: the :class:`~nplps.Rig` (camera and light positions).
        mask: (H, W) boolean array or mask image (non-zero = reconstruct); None: every pixel.
        depth: the working distance (each connected region's mean vertex depth; the surface
            starts as a plane there), or an (H+1, W+1) initial vertex depth map (each region's
            mean depth stays at the map's mean). Required: near-light reconstruction depends on it.
        iterations: maximum number of local/global iterations.
        tol: stop when the largest depth change of an iteration is at most ``tol`` times the
            lateral size of the image footprint.
        progress: None (silent), True (a line per iteration on stderr) or a callable that gets an
            :class:`~nplps.Iteration` after every iteration (raise in it to stop).
        dark: observations at or below this value count as shadowed and are left out of the fits.
        weighting: "image" (least squares in image units, default) or "paper" (the paper's Eq. 6).
        threads: worker threads (None: all cores).

    Returns:
        A :class:`~nplps.Reconstruction`.
    """
    stack, mask_arr, distance, depth_map = _prepare(images, rig, mask, depth)
    if int(iterations) < 1:
        raise InputError(f"iterations must be at least 1, got {iterations}")
    out = _core.reconstruct(
        stack,
        rig.camera,
        rig.lights,
        mask_arr,
        distance,
        depth_map,
        int(iterations),
        float(tol),
        float(dark),
        weighting,
        _threads(threads),
        _progress_callback(progress, int(iterations)),
    )
    _warn_negative(out["negative_observations"], float(dark))
    return Reconstruction._from_core(out, mask_arr, rig, "near")


def reconstruct_parallel(
    images: Images,
    rig: Rig,
    mask: Any = None,
    depth: Depth | None = None,
    dark: float = 0.0,
    threads: int | None = None,
) -> Reconstruction:
    """The conventional baseline: parallel-light photometric stereo, then the same integration.

    Each light becomes one direction, from the centroid of the initial surface (given by
    ``depth`` as in :func:`reconstruct`) to the light, with no falloff. Useful to see what the
    near-light model gains.
    """
    stack, mask_arr, distance, depth_map = _prepare(images, rig, mask, depth)
    out = _core.reconstruct_parallel(stack, rig.camera, rig.lights, mask_arr, distance, depth_map, float(dark), _threads(threads))
    return Reconstruction._from_core(out, mask_arr, rig, "parallel")


def render(depth: np.ndarray, rig: Rig, albedo: float | np.ndarray = 1.0, mask: np.ndarray | None = None) -> np.ndarray:
    """Images (k, H, W) of the surface with vertex depths ``depth`` (H+1, W+1) under ``rig``.

    Each pixel is the quad between its 4 corner vertices, with the quad's mesh normal and its
    centre as the surface point: ``I_k = albedo * max(0, n . (p_k - c)) / |p_k - c|^3``
    (attached shadows clipped at 0). Pixels outside ``mask`` are 0.
    """
    z = np.ascontiguousarray(np.asarray(depth, dtype=np.float64))
    if z.ndim != 2 or min(z.shape) < 2:
        raise InputError(f"depth must be an (H+1, W+1) vertex depth map, got shape {z.shape}")
    shape = (z.shape[0] - 1, z.shape[1] - 1)
    rho = np.ascontiguousarray(np.broadcast_to(np.asarray(albedo, dtype=np.float64), shape))
    m = None if mask is None else np.ascontiguousarray(load_mask(mask, shape))
    return _core.render(z, rig.camera, rig.lights, rho, m)


def _threads(threads: int | None) -> int:
    if threads is None:
        return 0
    if int(threads) < 1:
        raise InputError(f"threads must be at least 1 (or None for all cores), got {threads}")
    return int(threads)
