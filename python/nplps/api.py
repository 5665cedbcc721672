"""The Python API: :func:`reconstruct`, the parallel-light baseline :func:`reconstruct_parallel`, and :func:`render`.

The images and the rig are positional; every option is keyword-only, and ``depth`` (the working
distance, an initial depth map or ``"auto"``) is required. String options are typed with the
:data:`~typing.Literal` aliases of :mod:`nplps.types`.
"""

from __future__ import annotations

import math
import sys
import warnings
from collections.abc import Callable, Sequence
from typing import Any, Literal

import numpy as np

from . import _core, _core_types, pipeline
from ._checks import (
    MAX_THREADS,
    _check_rig,
    _depth_range,
    _finite_number,
    _flag,
    _levels,
    _memory_limit,
    _positive,
    _real,
    _real_array,
    _refine_choice,
    _shadows,
    _short,
    _solver_choice,
    _threads,
    _whole,
)
from .errors import InputError
from .io import load_mask, load_stack
from .progress import CTRL_C_HINT, PipelineProgress, ReconstructionProgress, aborting
from .reconstruction import Iteration, Reconstruction
from .rig import Rig
from .types import Depth, Images, Mask, Progress, RefineLights, Reflectance, Robust, Solver, Weighting, _iteration

__all__ = [
    "MAX_DEPTH_RATIO",
    "MAX_THREADS",
    "cast_shadows",
    "estimate_noise",
    "reconstruct",
    "reconstruct_parallel",
    "render",
]


#: A depth (the working distance, or a value of an initial depth map or a depth prior at a vertex
#: the mask uses) may be at most this many times the rig's size (:func:`_rig_size`: the farthest
#: point light, or for an orthographic camera image corner, from the origin). Farther, the lights
#: seen from the object differ in direction by less than a microradian, so the near-light model
#: has nothing to work with, and float64 depths keep fewer than 10 significant digits of the
#: object's relief: such a depth is a mistake (a wrong unit, a corrupt map), not a scene.
MAX_DEPTH_RATIO = 1e6


def _prepare(
    images: Images,
    rig: Rig,
    mask: Mask | None,
    depth: Depth | None,
    color: bool | None = None,
    loading: PipelineProgress | None = None,
    uint16: bool = False,
) -> tuple[np.ndarray, np.ndarray, float | None, np.ndarray | None, int | None]:
    _check_rig(rig)
    if not (color is None or isinstance(color, (bool, np.bool_))):
        raise InputError(f"color must be None, True or False, got {_short(color)}")
    if loading is None:
        stack, levels = load_stack(images, color=True, uint16=uint16)
    else:
        with aborting(loading):
            stack, levels = load_stack(
                images, color=True, progress=lambda i, k, name: loading("load", i, k, name), uint16=uint16
            )
        loading.finish()
    if color and stack.ndim != 4:
        raise InputError("color=True needs RGB images (k, H, W, 3)")
    k, h, w = stack.shape[:3]
    if k != rig.n_lights:
        raise InputError(
            f"{k} images were given for {rig.n_lights} lights: there must be one image per light, in the rig's order"
        )
    rig.check_grid(w, h)  # a rig that records its images' size refuses images of another size
    mask_arr = np.ascontiguousarray(load_mask(mask, (h, w)))
    if depth is None:
        raise InputError(
            "depth is required: give the working distance (the object's mean depth, in the rig's unit), "
            "an (H+1, W+1) initial depth map, or 'auto' to estimate it; a wrong distance bends the result"
        )
    if isinstance(depth, str):
        if depth != "auto":
            raise InputError(f"depth must be a number, a depth map or 'auto', got {_short(depth)}")
        return stack, mask_arr, _auto_start(rig), None, levels
    try:
        scalar = np.ndim(depth) == 0
    except ValueError:  # a ragged nested sequence: _real_array says what is wrong
        scalar = False
    if scalar:
        d = _positive(depth, "depth (the working distance)")
        _check_depth_values(np.array([d]), None, rig, (h, w), "depth (the working distance)")
        return stack, mask_arr, d, None, levels
    depth_map = _real_array(depth, "depth (the initial depth map)")
    if depth_map.shape != (h + 1, w + 1):
        raise InputError(
            f"the initial depth map has shape {depth_map.shape}; it must have one value per vertex, "
            f"(H+1, W+1) = {(h + 1, w + 1)} for images of {w} x {h} pixels"
        )
    _check_depth_values(depth_map, mask_arr, rig, (h, w), "depth (the initial depth map)")
    return stack, mask_arr, None, depth_map, levels


def _used_vertices(mask: np.ndarray) -> np.ndarray:
    """(H+1, W+1) booleans: the vertices of the pixels in ``mask`` (H, W)."""
    h, w = mask.shape
    used = np.zeros((h + 1, w + 1), dtype=bool)
    for dr in (0, 1):
        for dc in (0, 1):
            used[dr : dr + h, dc : dc + w] |= mask
    return used


def _rig_size(rig: Rig, shape: tuple[int, int]) -> float:
    """Return the rig's size for :data:`MAX_DEPTH_RATIO`.

    It is the largest distance from the origin (the camera centre) of a point light or, for an
    orthographic camera, of a corner of the image footprint of ``shape`` (H, W) pixels; 0 when there
    is neither (a pinhole camera with only directional lights: then no depth is too far).
    """
    sizes = [0.0]
    points = rig.positions[~rig.directional]
    if len(points):
        sizes.append(float(np.linalg.norm(points, axis=1).max()))
    if not rig.is_pinhole:
        (px, py), (ox, oy) = rig.camera["pixel_size"], rig.camera["origin"]
        h, w = shape
        sizes += [math.hypot(ox + a * w * px, oy + b * h * py) for a in (0, 1) for b in (0, 1)]
    size = max(sizes)
    return size if np.isfinite(size) else 0.0


def _check_depth_values(
    values: np.ndarray, mask: np.ndarray | None, rig: Rig, shape: tuple[int, int], name: str
) -> None:
    """Fail when a finite value of ``values`` is too far from the rig.

    Only the values at the vertices ``mask`` uses count, if given; too far is farther than
    :data:`MAX_DEPTH_RATIO` times the rig's size (see there).
    """
    size = _rig_size(rig, shape)
    if size <= 0:
        return
    limit = MAX_DEPTH_RATIO * size
    z = values if mask is None else np.where(_used_vertices(mask), values, np.nan)
    with np.errstate(invalid="ignore"):
        far = np.isfinite(z) & (np.abs(z) > limit)
    if far.any():
        i = np.unravel_index(int(np.argmax(far)), z.shape)
        where = f" at vertex (row {i[0]}, column {i[1]})" if z.ndim == 2 else ""
        raise InputError(
            f"{name} is {z[i]:.6g}{where}, more than {MAX_DEPTH_RATIO:.0e} times the rig's size "
            f"({size:.6g}, the farthest light or image corner from the camera): at such a distance the "
            "lights act as parallel lights and the relief is lost to rounding; check the value and its unit "
            "(the rig's)"
        )


def _auto_start(rig: Rig) -> float:
    """Return a starting plane for the distance search, well beyond the point lights.

    The search sets the gauge itself.
    """
    points = rig.positions[~rig.directional]
    if len(points) == 0:
        return 1.0
    spread = float(np.ptp(points, axis=0).max()) or 1.0
    return float(points[:, 2].max()) + 10.0 * spread


def _thresholds(dark: float | None, saturation: float | None, levels: int | None) -> tuple[float, float]:
    """Return the shadow and saturation thresholds.

    By default one level above black and the top level for integer images (values are scaled to
    [0, 1]), 0 and none for floating-point images.
    """
    dark, saturation = pipeline.thresholds(levels, dark=dark, saturation=saturation)
    return _real(dark, "dark"), _real(saturation, "saturation")


def _noise_dark(dark: float | None, default: float, stack: np.ndarray, mask: np.ndarray) -> tuple[float, float | None]:
    """Return the shadow threshold and the noise estimate it came from.

    A given ``dark`` is kept (no estimate, None). Else the larger of ``default`` (one level above
    black for integer images, else 0) and 3 sigma of :func:`estimate_noise` on ``stack`` (the
    images as they are fitted) inside ``mask``.
    """
    if dark is not None:
        return default, None
    sigma = float(_core.estimate_noise(stack, mask))
    return max(default, 3.0 * sigma), sigma


def _channels(stack: np.ndarray, color: bool | None, saturation: float) -> tuple[np.ndarray, Any]:
    """Average RGB to grey when ``color`` is False.

    Observations with a saturated channel are returned as missing (the grey average would hide
    them).
    """
    if stack.ndim == 4 and color is False:
        stack = _float32(stack)
    return pipeline.select_color(stack, color, saturation)


def _float32(stack: np.ndarray) -> np.ndarray:
    """Return a ``uint16`` stack as float32 on ``[0, 1]``, others as they are.

    The values are those :func:`nplps.io.load_stack` gives.
    """
    if stack.dtype != np.uint16:
        return stack
    out = np.empty(stack.shape, dtype=np.float32)
    for i in range(stack.shape[0]):  # image by image: no temporary of the whole stack
        np.divide(stack[i], np.float32(65535), out=out[i], dtype=np.float32, casting="unsafe")
    return out


def _owned(stack: np.ndarray, images: Images) -> bool:
    """Return True when ``stack`` was made here, not the caller's array itself.

    Made here means from files, a list, a conversion or the grey average; then it may be modified in
    place.
    """
    return not (isinstance(images, np.ndarray) and np.may_share_memory(stack, images))


def _apply_valid(stack: np.ndarray, valid: Any, missing: np.ndarray | None = None, owned: bool = False) -> np.ndarray:
    """Mark the observations where ``valid`` is False, or ``missing`` is True, as missing (NaN).

    This is done in ``stack`` itself when it is ``owned`` (see :func:`_owned`), in a copy otherwise.
    """
    if valid is None and missing is None:
        return stack
    v = np.ones(stack.shape[:3], dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    if v.shape != stack.shape[:3]:
        raise InputError(f"valid must have one flag per observation, shape {stack.shape[:3]}, got {v.shape}")
    if missing is not None:
        v = v & ~missing
    if stack.dtype == np.uint16:  # NaN marks a missing observation: float32 (a new array)
        stack, owned = _float32(stack), True
    out = stack if owned else stack.copy()
    out[~v] = np.nan
    return out


def _warn_negative(count: int, dark: float) -> None:
    if count:
        treated = "they were treated as unlit" if dark >= 0 else f"those above dark = {dark} were used"
        warnings.warn(
            f"{count} pixel values inside the mask are negative (dark-frame subtraction?); {treated}",
            RuntimeWarning,
            stacklevel=3,
        )


def _warn_slow_multigrid(history: Sequence[Iteration]) -> None:
    """Warn when the multigrid solver stopped at its iteration limit in some global step.

    The mask's thin structures defeat its coarsening; that step's depths are inexact.
    """
    limit = _core.MULTIGRID_MAX_ITERATIONS
    stuck = sum(1 for h in history if h.inner_iterations >= limit)
    if stuck:
        warnings.warn(
            f"the multigrid solver reached its limit of {limit} conjugate-gradient iterations in {stuck} "
            "global step(s), so those steps are inexact; masks made of thin one-pixel strips converge slowly: "
            'try solver="direct" (exact; its memory grows faster than the pixels)',
            RuntimeWarning,
            stacklevel=3,
        )


def _warn_status(result: Reconstruction) -> None:
    """Warn when the result is not to be trusted.

    That is status "degenerate" (more than half of the masked pixels had fewer than 3 usable
    observations and kept the starting shape, which says nothing about the object) or "diverged"
    (the depth changes grew). The core decides the status (see ``Reconstruction.status``).
    """
    if result.status == "degenerate":
        total = int(result.mask.sum())
        warnings.warn(
            f"{result.unfitted} of {total} masked pixels ({100 * result.unfitted / total:.0f} %) had fewer "
            "than 3 usable observations and kept the starting shape; check dark, saturation, valid and the mask",
            RuntimeWarning,
            stacklevel=3,
        )
    elif result.status == "diverged":
        warnings.warn(f"the reconstruction diverged: {result.status_reason}", RuntimeWarning, stacklevel=3)
    check = result.lobe_check
    if result.matte_lobe is not None and check is not None and not check.glossy_wins:
        reasons = []
        if check.glossy >= check.lambertian:
            reasons.append(
                f"the glossy model predicted held-out lights worse than the Lambertian one (RMS {check.glossy:.4g} "
                f"vs {check.lambertian:.4g}: too few lights for its unknowns, or no surface highlight)"
            )
        if not check.highlight_confirmed:
            where = (
                f"the {check.seen} fits with a light within it found {check.highlight:.2g} times the others' "
                "specular albedo"
                if check.seen
                else "no fit had a light within it"
            )
            reasons.append(
                f"the images do not show the highlight of the lobe they fit best (roughness "
                f"{result.matte_lobe.roughness:.3g}; {where}): its specular albedos were fitted to the lobe's far "
                "tail and would mispredict a light that falls into it"
            )
        warnings.warn(
            f"reflectance='glossy': {'; and '.join(reasons)}; so the Lambertian model was used; give roughness= "
            "and eta= to force the glossy model",
            RuntimeWarning,
            stacklevel=3,
        )
    elif result.matte_lobe is not None:
        warnings.warn(
            f"reflectance='glossy': the images show no highlight (the lobe they fit best has roughness "
            f"{result.matte_lobe.roughness:.2f}, as broad as the diffuse part), so the Lambertian model "
            "was used; give roughness= and eta= to force the glossy model",
            RuntimeWarning,
            stacklevel=3,
        )


#: With ``interreflections=True``, a median albedo outside this range is not a reflectance.
ALBEDO_RANGE = (0.01, 1.0)


def _warn_albedo_scale(result: Reconstruction) -> None:
    """Warn when the albedo is no reflectance, so that the modelled indirect light is off.

    The indirect light is gathered from the observed images: it has the right strength relative to
    the rig's light only when the fitted albedo is the surface's reflectance, i.e. the rig's
    intensities are calibrated in those units (docs/method.md). An albedo far outside (0, 1] says
    they are not (queau_human1: about 2e-5, where the option mostly changes which observations
    count as lit).
    """
    albedo = np.asarray(result.albedo)[result.mask]
    albedo = albedo[np.isfinite(albedo)]
    if albedo.size == 0:
        return
    median = float(np.median(albedo))
    low, high = ALBEDO_RANGE
    if not low <= median <= high:
        warnings.warn(
            f"interreflections=True: the median albedo is {median:.3g}, not a reflectance in ({low}, {high}]: the "
            "rig's intensities are not in the units the indirect light assumes (it has its true strength only "
            "when the albedo is the reflectance); calibrate the intensities against a reference of known "
            "reflectance, or leave the option off",
            RuntimeWarning,
            stacklevel=3,
        )


_hinted = False


def _hint_once() -> None:
    """Print the Ctrl-C hint on stderr, the first time a call shows progress."""
    global _hinted
    if not _hinted:
        _hinted = True
        print(f"({CTRL_C_HINT})", file=sys.stderr, flush=True)


def _progress_callback(
    progress: Progress, iterations: int
) -> tuple[_core_types.ProgressCallback | None, ReconstructionProgress | None]:
    """Return the core's progress callback for `progress`, and the display of ``progress=True``.

    ``True`` shows bars on stderr (:class:`nplps.progress.ReconstructionProgress`, with the
    Ctrl-C hint once per process); a callable gets an :class:`Iteration` per iteration, with the
    distance search's candidate fields set during the search.
    """
    display: ReconstructionProgress | None = None
    if progress is None or progress is False:
        return None, None
    if progress is True:
        display = ReconstructionProgress(iterations)
        user: Callable[[Iteration], Any] = display
    elif callable(progress):
        user = progress
    else:
        raise InputError(f"progress must be None, True or a callable, got {progress!r}")

    def call(stats: _core.IterationStats) -> None:
        user(_iteration(stats))

    return call, display


def reconstruct(
    images: Images,
    rig: Rig,
    *,
    depth: Depth,
    mask: Mask | None = None,
    iterations: int = 10,
    tol: float = 1e-6,
    progress: Progress = None,
    dark: float | None = None,
    saturation: float | None = None,
    weighting: Weighting = "image",
    robust: Robust | None = None,
    reflectance: Reflectance = "lambertian",
    roughness: float | None = None,
    eta: float | None = None,
    shadows: bool | Literal["auto"] = "auto",
    interreflections: bool = False,
    color: bool | None = None,
    valid: Any = None,
    threads: int | None = None,
    depth_range: tuple[float, float] | None = None,
    depth_guess: float | None = None,
    depth_prior: np.ndarray | None = None,
    prior_weight: float = 1.0,
    solver: Solver = "auto",
    levels: int | None = None,
    refine_lights: RefineLights | None = None,
    light_prior_weight: float | None = None,
    max_memory: float | str | None = None,
    check_distance: bool = True,
) -> Reconstruction:
    """Reconstruct a surface from k images taken under k near lights.

    Alternates the paper's local step (each pixel's normal and albedo fitted under the near-light
    model at the current surface) and global step (one depth map fitted to all the facet planes)
    until the depths converge; see docs/method.md.

    Parameters
    ----------
    images : array_like or sequence of str or path-like
        A (k, H, W) or (k, H, W, 3) array, or k image files or arrays (8/16-bit PNG, TIFF, JPEG,
        ...), one per light in the rig's order. Integer images are scaled to [0, 1]; RGB images
        give an RGB albedo (see `color`).
    rig : Rig
        The camera and the lights (:class:`~nplps.Rig`).
    depth : float, array_like or "auto"
        Required, keyword-only: near-light reconstruction depends on it (10 % off costs about 4
        degrees of normal error). The working distance, an (H+1, W+1) initial vertex depth map,
        or ``"auto"``. It sets each connected region's gauge: the arithmetic mean vertex depth
        (orthographic camera) or the geometric mean vertex depth (pinhole camera); the surface
        starts there. ``"auto"`` estimates each region's gauge by minimizing the photometric
        residual (see ``result.distance``), searching `depth_range`, or ``depth_guess / 2`` to
        ``depth_guess * 2``, or a range derived from the lights. A distance, or a map value at a
        vertex the mask uses, more than :data:`MAX_DEPTH_RATIO` (a million) times the rig's size
        is refused.
    mask : array_like, str or path-like, optional
        (H, W) boolean array or mask image (non-zero = reconstruct). Default: every pixel.
    iterations : int, default 10
        Most local/global iterations (per pyramid level).
    tol : float, default 1e-6
        Stop when the largest depth change of an iteration is at most `tol` times the lateral
        size of the image footprint.
    progress : None, bool or callable, optional
        None or False (silent); True: progress bars on stderr (:mod:`nplps.progress`: image
        files read, the distance search's candidates with the best so far and the time left,
        the iterations with their depth change; one line redrawn in place on a terminal, a few
        plain lines otherwise); or a callable that gets an :class:`~nplps.Iteration` after every
        iteration, also those of the distance search (``it.candidate > 0``; raise in it to stop).
    dark : float, optional
        Observations at or below it count as shadowed and are left out of the fits. Default: three
        times the noise that :func:`estimate_noise` measures in the images inside the mask (0 for
        noise-free images), and at least one level above black for integer images. The value used
        is ``result.dark`` (and ``"dark"`` in ``summary.json``), the estimate ``result.noise``.
    saturation : float, optional
        Observations at or above it count as saturated and are left out. Default: the top level
        for integer images, none for floating-point images.
    weighting : {"image", "paper"}, default "image"
        Least squares in image units, or the paper's Eq. 6.
    robust : {None, "cauchy", "tukey"}, optional
        Iteratively reweighted fits that resist highlights and cast shadows. Default: plain
        least squares.
    reflectance : {"lambertian", "glossy"}, default "lambertian"
        The image model of each pixel's fit. "glossy": a diffuse part with Fresnel transmittance
        plus a GGX specular lobe (Smith masking, Fresnel shape), fitted per pixel from the
        Lambertian fit by damped Gauss-Newton; the lobe's `roughness` and `eta` are shared by the
        whole object (see docs/method.md). The result then has ``lobe`` and ``specular`` (the
        specular albedo); `albedo` is the diffuse albedo. For shiny objects: plastics, glazes,
        coated or polished parts.
    roughness, eta : float, optional
        With ``reflectance="glossy"``: the lobe's GGX roughness (0 < roughness <= 1) and relative
        index of refraction (1 to 3), both or neither. Default: estimated from the images.
    shadows : bool or "auto", default "auto"
        Predict cast shadows from the current mesh: at the first, third and eighth iteration of
        each pyramid level every pixel's path to every light is marched over the mesh's depth
        map, and the observations the surface itself hides are left out of the fits (as below
        `dark`). For objects that shadow themselves: steps, pockets, deep relief. With True it
        costs one to three marches a level (measured 0.3-0.7 s at 256 x 256 x 16 lights, 12-20 s
        at 1 MP on a 2-core machine). With "auto" (the default) a level without masks first
        marches from a lattice of about 1024 pixels (1/900 of a march at 1 MP) and marches
        every pixel only when 0.5 % or more of the lattice's observations are hidden; masks
        below that share are not used. Objects that do not shadow themselves then get the
        result of False, bit for bit, at the cost of the probes. False never marches. The masks
        of the final level, when used, are ``result.shadows``.
    interreflections : bool, default False
        Model the light that the surface sends to itself (concave objects: bowls, grooves,
        folds). Once a level of 128-256 pixels a side (or a smaller image) converges, the
        indirect irradiance of every pixel under every light is gathered from the observed
        images over the current mesh (on a grid of 32 x 32 to 64 x 64 cells), added to the
        fits' light vectors, and the iteration runs again, up to 4 rounds; the finer levels
        iterate with that field (2-7x the time of a default run). Only for captures with real
        interreflections (direct-only renders get worse). With ``refine_lights`` the light
        step adds the same indirect light to its rows (Lambertian model only; the intensities'
        common factor stays the rig's). With ``reflectance="glossy"`` the modelled diffuse part
        of the images emits (the observations less the fitted specular part) and the glossy
        fits see the observations less the indirect light they receive as a Lambertian surface
        (its glossy reflection is ignored), the rounds at full resolution. See the README
        ("Concave objects") for its cost and limits.
    color : bool, optional
        None: RGB images give an RGB albedo; True: require RGB images; False: average them to
        grey (an observation with a saturated channel is left out).
    valid : array_like of bool, optional
        (k, H, W) flags; False marks an observation to leave out.
    threads : int, optional
        Worker threads, at most :data:`MAX_THREADS` (1024). Default: all cores.
    depth_range : (float, float), optional
        (near, far) range that ``depth="auto"`` searches.
    depth_guess : float, optional
        ``depth="auto"`` searches ``depth_guess / 2`` to ``depth_guess * 2``.
    depth_prior : array_like, optional
        An (H+1, W+1) prior depth map (NaN where unknown), e.g. from a coarse scan, fused in the
        global step with `prior_weight` relative to the facet terms (on depth, or on log-depth
        for a pinhole camera). `depth` keeps its meaning (start and gauge).
    prior_weight : float, default 1.0
        Weight of `depth_prior`.
    solver : {"auto", "direct", "multigrid"}, default "auto"
        How the global step's linear system is solved: "direct" (sparse Cholesky, exact; its
        memory grows faster than the pixels), "multigrid" (conjugate gradients with a multigrid
        preconditioner: linear time and memory) or "auto" (direct up to 40 000 mesh vertices,
        about 200 x 200 pixels, multigrid above).
    levels : int, optional
        Coarse-to-fine pyramid levels. The images are halved (2 x 2 averages, the camera adjusted
        exactly) ``levels - 1`` times; the coarsest level converges from the starting plane and
        each finer level starts from the level below. Default: halve while the longer side stays
        at least 128 pixels; 1: full resolution only. With ``depth="auto"`` the distance search
        runs on the coarsest level.
    refine_lights : {None, "intensity", "position", "both"}, optional
        Self-calibration of the lights from the images. None: the rig is trusted; "intensity": a
        factor per light (their geometric mean stays the rig's); "position": each point light's
        position, held toward the rig's by `light_prior_weight`; "both". Each iteration takes one
        damped Gauss-Newton step on the lights with the normals eliminated per pixel. When
        positions are refined the first level also runs without refinement, and the refinement
        is dropped (``refinement.fell_back``) unless it lowers the photometric residual. With
        ``depth="auto"`` the distance search refines intensities only.
    light_prior_weight : float, optional
        Weight ``w`` of the prior ``w/2 sum |p - p0|^2 / D^2`` (D: the working distance) against
        the squared residual in units of the noise variance: a Gaussian prior of standard
        deviation ``D / sqrt(w)`` on each coordinate of a light. Default 1000 (about 3 % of D);
        smaller trusts the images more.
    max_memory : float or str, optional
        Memory limit in bytes (a number, or a string such as ``"8 GB"`` or ``"512MiB"``;
        ``float("inf")``: no limit). Default: 80 % of the memory available to the process (the
        least of the system's available memory, a cgroup limit and an address-space limit).
    check_distance : bool, default True
        With a given `depth`, compare it afterwards with the distance a quick search on a coarse
        level (at most 32 pixels a side) prefers (``result.distance_check``), and warn "the
        working distance looks wrong" when the images fit another distance clearly better. It
        needs at least 4 lights, one of them a point light; its cost does not grow with the
        image size.

    Returns
    -------
    Reconstruction
        Vertex depths, normals (the mesh's; the local fits are ``fit_normals``), albedo,
        residuals, how the run ended (``status``) and, with ``depth="auto"`` or
        `refine_lights`, the distance estimate and the refined rig.

    Raises
    ------
    TypeError
        `depth` is missing, or an argument after `rig` is passed by position.
    InputError
        An argument is invalid (the message names it); also a ``ValueError``.
    RigError
        The lights cannot determine a normal anywhere (collinear, coincident or very distant).
    MemoryLimitError
        The estimated peak memory is above `max_memory` (checked before any large allocation).
    SolverError
        The surface reached a light, or the solver failed on valid input.

    Warns
    -----
    RuntimeWarning
        The run diverged or is degenerate (more than half of the masked pixels could not be
        fitted), pixel values inside the mask are negative, the multigrid solver stopped at
        its iteration limit, or the working distance looks wrong (see `check_distance`).

    See Also
    --------
    reconstruct_parallel : the conventional parallel-light baseline.
    nplps.evaluation.held_out : check a result without ground truth.

    Notes
    -----
    Pixels with fewer than 3 usable observations keep their shape; they are counted in
    ``result.unfitted``. ``result.status`` is "converged", "stalled", "diverged" or
    "degenerate", with the numbers in ``result.status_reason``. Ctrl-C stops a run within a
    fraction of a second (``KeyboardInterrupt``, no partial result).

    Examples
    --------
    >>> import nplps
    >>> scene = nplps.make_scene("sphere", n=32)
    >>> result = nplps.reconstruct(scene.images, scene.rig, depth=scene.mean_depth, mask=scene.mask)
    >>> result.status
    'converged'
    >>> result.normals.shape, result.depth.shape
    ((32, 32, 3), (33, 33))
    """
    pyramid_levels = _levels(levels)
    refine_mode = _refine_choice(refine_lights)
    if progress is True:
        _hint_once()
    loading = PipelineProgress() if progress is True and not isinstance(images, np.ndarray) else None
    stack, mask_arr, distance, depth_map, bit_levels = _prepare(images, rig, mask, depth, color, loading, uint16=True)
    dark_, saturation_ = _thresholds(dark, saturation, bit_levels)
    stack, missing = _channels(stack, color, saturation_)
    fitted = _apply_valid(stack, valid, missing, _owned(stack, images))
    dark_, noise = _noise_dark(dark, dark_, fitted, mask_arr)
    iterations = _whole(iterations, "iterations", 1)
    tol = _real(tol, "tol")
    options: _core_types.ReconstructOptions = {
        "iterations": iterations,
        "tol": tol,
        "dark": dark_,
        "saturation": saturation_,
        "weighting": weighting,
        "robust": "none" if robust is None else robust,
        "reflectance": reflectance,
        "roughness": None if roughness is None else _finite_number(roughness, "roughness"),
        "eta": None if eta is None else _finite_number(eta, "eta"),
        "shadows": _shadows(shadows),
        "interreflections": _flag(interreflections, "interreflections"),
        "threads": _threads(threads),
        "auto": isinstance(depth, str),
        "check_distance": _flag(check_distance, "check_distance"),
        "depth_range": _depth_range(depth_range),
        "depth_guess": None if depth_guess is None else _positive(depth_guess, "depth_guess"),
        "prior_weight": _real(prior_weight, "prior_weight"),
        "solver": _solver_choice(solver),
        "levels": pyramid_levels,
        "refine_lights": refine_mode,
        "max_memory": _memory_limit(max_memory),
    }
    if light_prior_weight is not None:
        options["light_prior_weight"] = _finite_number(light_prior_weight, "light_prior_weight")
    prior = None
    if depth_prior is not None:
        prior = _real_array(depth_prior, "depth_prior")
        if prior.shape != (mask_arr.shape[0] + 1, mask_arr.shape[1] + 1):
            raise InputError(
                f"depth_prior must be an (H+1, W+1) = {(mask_arr.shape[0] + 1, mask_arr.shape[1] + 1)} map, "
                f"got {prior.shape}"
            )
        _check_depth_values(prior, mask_arr, rig, mask_arr.shape, "depth_prior")
    if prior is not None:
        options["prior"] = prior
    depth_arg = distance if depth_map is None else depth_map
    assert depth_arg is not None  # _prepare gives exactly one of them
    callback, display = _progress_callback(progress, int(iterations))
    with aborting(display):
        out = _core.reconstruct(
            fitted,
            rig._native,
            mask_arr,
            depth_arg,
            options,
            callback,
        )
    result = Reconstruction._from_core(out, mask_arr, rig, "near", dark=dark_, noise=noise)
    if display is not None:
        display.finish(result)
    _warn_negative(out["negative_observations"], dark_)
    _warn_slow_multigrid(result.history)
    _warn_status(result)
    if interreflections:
        _warn_albedo_scale(result)
    if result.distance_check is not None and result.distance_check.looks_wrong:
        warnings.warn(result.distance_check.message, RuntimeWarning, stacklevel=2)
    return result


def reconstruct_parallel(
    images: Images,
    rig: Rig,
    *,
    depth: float | np.ndarray,
    mask: Mask | None = None,
    dark: float | None = None,
    saturation: float | None = None,
    robust: Robust | None = None,
    reflectance: Reflectance = "lambertian",
    roughness: float | None = None,
    eta: float | None = None,
    color: bool | None = None,
    valid: Any = None,
    threads: int | None = None,
    refine_lights: RefineLights | None = None,
    max_memory: float | str | None = None,
) -> Reconstruction:
    """Reconstruct with the conventional baseline: parallel-light photometric stereo, then the same integration.

    Each point light becomes one direction, from the centroid of the initial surface (given by
    `depth` as in :func:`reconstruct`) to the light, with no falloff; directional lights keep
    theirs. Useful to see what the near-light model gains.

    Parameters
    ----------
    images : array_like or sequence of str or path-like
        As in :func:`reconstruct`.
    rig : Rig
        The camera and the lights.
    depth : float or array_like
        Required, keyword-only: the working distance or an (H+1, W+1) initial depth map, as in
        :func:`reconstruct`. ``"auto"`` is not supported (the parallel-light model cannot tell the
        distance): pass the distance that ``reconstruct(..., depth="auto")`` found
        (``result.distance``) or its depth map.
    mask, dark, saturation, robust, color, valid, threads, max_memory
        As in :func:`reconstruct`.
    reflectance : {"lambertian", "glossy"}, default "lambertian"
        As in :func:`reconstruct`: "glossy" fits the diffuse + GGX model with each light's one
        direction and the view vector at the initial surface; a lobe not given (`roughness`,
        `eta`) is estimated once, on the initial surface with the rig's intensities. The result
        then has ``lobe`` and ``specular``.
    roughness, eta : float, optional
        With ``reflectance="glossy"``: the lobe, both or neither, as in :func:`reconstruct`.
    refine_lights : {None, "intensity"}, optional
        "intensity" refines the intensities under this model (to convergence: the model does not
        depend on the depths); the result's ``rig`` then carries them.

    Returns
    -------
    Reconstruction
        With ``method == "parallel"``.

    Raises
    ------
    TypeError
        `depth` is missing, or an argument after `rig` is passed by position.
    InputError
        An argument is invalid, ``depth="auto"``, or `refine_lights` is "position" or "both".
    RigError, MemoryLimitError, SolverError
        As in :func:`reconstruct`.

    See Also
    --------
    reconstruct : the near-light method.

    Examples
    --------
    >>> import nplps
    >>> scene = nplps.make_scene("sphere", n=32)
    >>> base = nplps.reconstruct_parallel(scene.images, scene.rig, depth=scene.mean_depth, mask=scene.mask)
    >>> base.method
    'parallel'
    """
    if isinstance(depth, str) and depth == "auto":
        raise InputError(
            'depth="auto" is not supported by the parallel-light baseline (it cannot tell the distance): '
            'pass the distance found by reconstruct(..., depth="auto") (result.distance) or its depth map'
        )
    refine_mode = _refine_choice(refine_lights)
    if refine_mode not in ("none", "intensity"):
        raise InputError(
            'the parallel-light baseline can refine only "intensity" (it has no light positions), '
            f"got {refine_lights!r}"
        )
    stack, mask_arr, distance, depth_map, levels = _prepare(images, rig, mask, depth, color)
    dark_, saturation_ = _thresholds(dark, saturation, levels)
    stack, missing = _channels(stack, color, saturation_)
    fitted = _apply_valid(stack, valid, missing, _owned(stack, images))
    dark_, noise = _noise_dark(dark, dark_, fitted, mask_arr)
    options: _core_types.SolverOptions = {
        "dark": dark_,
        "saturation": saturation_,
        "robust": "none" if robust is None else robust,
        "reflectance": reflectance,
        "roughness": None if roughness is None else _finite_number(roughness, "roughness"),
        "eta": None if eta is None else _finite_number(eta, "eta"),
        "threads": _threads(threads),
        "refine_lights": refine_mode,
        "max_memory": _memory_limit(max_memory),
    }
    out = _core.reconstruct_parallel(fitted, rig._native, mask_arr, distance, depth_map, options)
    return Reconstruction._from_core(out, mask_arr, rig, "parallel", dark=dark_, noise=noise)


def _vertex_depths(depth: Any) -> np.ndarray:
    """``depth`` as a contiguous (H+1, W+1) float64 vertex depth map, or InputError."""
    z = _real_array(depth, "depth")
    if z.ndim != 2 or min(z.shape) < 2:
        raise InputError(f"depth must be an (H+1, W+1) vertex depth map, got shape {z.shape}")
    return z


def _specular_map(specular: Any, shape: tuple[int, int]) -> float | np.ndarray:
    """``specular`` as a number or an (H, W) float64 map, finite and >= 0, or InputError."""
    if np.ndim(specular) == 0:
        return _finite_number(specular, "specular (the specular albedo)")
    s = _real_array(specular, "specular")
    if s.shape != shape:
        raise InputError(f"specular must be a number or a map of the image's shape {shape}, got shape {s.shape}")
    if not (np.isfinite(s).all() and (s >= 0).all()):
        raise InputError("specular (the specular albedo) must be finite and >= 0 everywhere")
    return s


def _lobe(roughness: Any, eta: Any) -> tuple[float, float]:
    """Check the glossy lobe's ``(roughness, eta)``: ``0 < roughness <= 1``, finite ``eta >= 1``."""
    alpha = _real(roughness, "roughness")
    if not (0 < alpha <= 1):
        raise InputError(f"roughness (the GGX alpha) must be in (0, 1], got {alpha:.6g}")
    index = _real(eta, "eta")
    if not (math.isfinite(index) and index >= 1):
        raise InputError(f"eta (the relative index of refraction) must be a finite number >= 1, got {index:.6g}")
    return alpha, index


def render(
    depth: np.ndarray,
    rig: Rig,
    albedo: float | np.ndarray = 1.0,
    *,
    mask: Mask | None = None,
    specular: float | np.ndarray | None = None,
    roughness: float = 0.3,
    eta: float = 1.5,
    shadows: bool = False,
    diffuse: str = "transmitted",
) -> np.ndarray:
    """Render the images of a surface under a rig by the solver's image model.

    Each pixel is the quad between its 4 corner vertices, with the quad's mesh normal ``n`` and
    its centre ``c`` as the surface point: ``I = albedo * intensity * max(0, n . beta(c))`` with
    the light's ``beta`` (point light: ``(p - c) / |p - c|^3`` times the LED factor; directional:
    its direction); attached shadows are clipped at 0.

    With `specular`, the glossy model (``nplps::reflectance``) instead:
    ``I = intensity * a * (albedo * D(n) + specular * S(n))`` with ``a = |beta(c)|``, the light
    direction ``l = beta(c) / a`` and the view direction ``v`` from ``c`` to the camera:
    ``D(n) = (n.l) T(n.l) T(n.v) / T(1)^2`` is the diffuse term with the Fresnel transmittance
    ``T`` of index `eta`, ``S(n)`` the GGX specular lobe of roughness `roughness` with Smith
    masking and the Fresnel shape. ``eta=1`` with ``specular=0`` is the Lambertian image (to
    rounding). With ``diffuse="retro"`` the diffuse term is Burley's (Disney's principled)
    instead: ``D(n) = (n.l) (1 + k F5(n.l)) (1 + k F5(n.v))``, ``F5(c) = (1 - c)^5``,
    ``k = 2 sqrt(roughness) (l.h)^2 - 1/2`` (``h`` the half vector). Facets turned away from the
    camera are 0 in this model.

    Parameters
    ----------
    depth : array_like
        (H+1, W+1) vertex depths.
    rig : Rig
        The camera and the lights.
    albedo : float or array_like, default 1.0
        A number, R, G, B, an (H, W) map or an (H, W, 3) map.
    mask : array_like, str or path-like, optional
        (H, W) pixels to render (non-zero) or a mask image. Default: every pixel.
    specular : float or array_like, optional
        The specular albedo (grey: the same in every channel), a number or an (H, W) map, finite
        and >= 0, in the units of `albedo`. Default None: the Lambertian model (and `roughness`,
        `eta` unused).
    roughness : float, default 0.3
        The GGX roughness ``alpha`` of the specular lobe, in (0, 1] (about 0.05 polished, 0.3
        satin, 0.6 rough).
    eta : float, default 1.5
        The relative index of refraction of the surface layer, >= 1 (1.5 for most plastics).
    shadows : bool, default False
        Cast shadows: an observation whose path to the light passes behind the surface (see
        :func:`cast_shadows`) is 0.
    diffuse : {"transmitted", "retro"}, default "transmitted"
        The shape of the glossy model's diffuse term (see above and :class:`Lobe`).

    Returns
    -------
    numpy.ndarray
        (k, H, W) images, or (k, H, W, 3) for an RGB albedo. Pixels outside `mask` are 0; pixels
        inside with a non-finite corner depth (NaN: unknown) are NaN in every image, so an
        unknown surface does not pass for a shadow.

    Raises
    ------
    InputError
        `depth`, `albedo` or `specular` has the wrong shape or type, `roughness` or `eta` is
        out of range, or `shadows` is not a bool.
    MemoryLimitError
        The images would not fit in memory.

    Examples
    --------
    >>> import numpy as np, nplps
    >>> scene = nplps.make_scene("sphere", n=16)
    >>> images = nplps.render(scene.depth, scene.rig, scene.albedo, mask=scene.mask)
    >>> images.shape == scene.images.shape
    True
    """
    _check_rig(rig)
    z = _vertex_depths(depth)
    shape = (z.shape[0] - 1, z.shape[1] - 1)
    alpha, index = _lobe(roughness, eta)
    cast = _flag(shadows, "shadows")
    rho_s = None if specular is None else _specular_map(specular, shape)
    a = _real_array(albedo, "albedo")
    target = (*shape, 3) if a.ndim == 3 or (a.ndim == 1 and a.shape == (3,)) else shape
    try:
        rho = np.ascontiguousarray(np.broadcast_to(a, target))
    except ValueError:
        raise InputError(
            f"albedo must be a number, R, G, B, or a map of the image's shape {shape} (or {(*shape, 3)}), "
            f"got shape {a.shape}"
        ) from None
    m = None if mask is None else np.ascontiguousarray(load_mask(mask, shape))
    return _core.render(
        z, rig._native, rho, m, specular=rho_s, roughness=alpha, eta=index, shadows=cast, diffuse=diffuse
    )


def estimate_noise(images: Images, mask: Mask | None = None) -> float:
    """Estimate the standard deviation of the image noise.

    Each image (and colour channel) is filtered with the 3 x 3 kernel ``[1, -2, 1]`` (x)
    ``[1, -2, 1]`` / 6, which passes white noise with its variance and removes smooth shading up
    to its third-order terms. The lower quartile of the absolute residuals (divided by 0.3186,
    so that edges and highlights in up to 3 of 4 windows do not count) over the windows inside
    `mask` whose 9 values are positive (images clipped at black have no Gaussian noise in their
    shadows) gives a first estimate; it is then measured again on the darkest quarter of
    the windows whose mean is at least 4 times that estimate, where it matters for the shadow
    threshold. The cost is linear in the pixels (at most 1 Mi windows, evenly strided, are
    measured). See ``rust/nplps/src/noise.rs`` for the details.

    Parameters
    ----------
    images : array_like or sequence of str or path-like
        (k, H, W) or (k, H, W, 3) images, or k image files. Integer images are scaled to [0, 1]
        first. NaN values (missing observations) are left out.
    mask : array_like, str or path-like, optional
        (H, W) pixels to measure (non-zero) or a mask image. Default: every pixel.

    Returns
    -------
    float
        The noise's standard deviation on the scale of the (loaded) images. Exactly 0 for
        noise-free images: estimates below 1e-4 of the largest value in the mask, and images
        without a 3 x 3 window of positive values in the mask.

    Raises
    ------
    InputError
        `images` or `mask` cannot be read, or their shapes do not match.

    See Also
    --------
    reconstruct : its default ``dark`` threshold is 3 times this estimate.

    Examples
    --------
    >>> import nplps
    >>> scene = nplps.make_scene("sphere", n=64, noise=0.01, seed=1)
    >>> sigma = nplps.estimate_noise(scene.images, scene.mask)
    >>> bool(abs(sigma / (0.01 * scene.images.max()) - 1) < 0.2)
    True
    >>> nplps.estimate_noise(nplps.make_scene("sphere", n=64).images)
    0.0
    """
    stack, _ = load_stack(images, color=True)
    m = None if mask is None else np.ascontiguousarray(load_mask(mask, stack.shape[1:3]))
    return float(_core.estimate_noise(np.ascontiguousarray(stack, dtype=np.float32), m))


def cast_shadows(depth: np.ndarray, rig: Rig, mask: Mask | None = None) -> np.ndarray:
    """Which pixels the surface itself hides from which light (cast shadows).

    For each pixel's facet (the quad between its 4 corner vertices, centre ``c``) and each light,
    the segment from ``c`` towards the light (a point light's position, or along a directional
    light's direction) is marched through the image half a pixel at a time; the facet is in a
    cast shadow when the segment passes behind the surface, that is when the depth of the
    surface there (bilinear in the vertex depths) is smaller than the segment's by more than a
    small tolerance. The march stops when the segment leaves the image or `mask`, or comes
    nearer to the camera than the nearest vertex. Facets turned away from a light (attached
    shadows, already dark) are not marked. The cost is at most ``k H W`` times twice the image
    diagonal in samples (usually far less: segments from flat regions are cut at once).

    Parameters
    ----------
    depth : array_like
        (H+1, W+1) vertex depths (NaN: unknown; the march stops there).
    rig : Rig
        The camera and the lights.
    mask : array_like, str or path-like, optional
        (H, W) pixels of the surface (non-zero) or a mask image. Default: every pixel.

    Returns
    -------
    numpy.ndarray
        (k, H, W) bool: True where the pixel is in a cast shadow of the light. False outside
        `mask` and at pixels with a non-finite corner.

    Raises
    ------
    InputError
        `depth` or `mask` has the wrong shape or type.
    RigError
        The camera has no ray at a vertex.
    MemoryLimitError
        The vertices or the mask would not fit in memory.

    Examples
    --------
    >>> import nplps
    >>> scene = nplps.make_scene("block", n=32)
    >>> shadowed = nplps.cast_shadows(scene.depth, scene.rig, scene.mask)
    >>> shadowed.shape, bool(shadowed.any())
    ((27, 32, 32), True)
    """
    _check_rig(rig)
    z = _vertex_depths(depth)
    shape = (z.shape[0] - 1, z.shape[1] - 1)
    m = None if mask is None else np.ascontiguousarray(load_mask(mask, shape))
    return _core.cast_shadows(z, rig._native, m)
