"""Light calibration: light positions from mirror-sphere highlights, intensities from a flat board.

**Sphere calibration** (:func:`calibrate_spheres`, the paper's section 5). Photograph one or
more shiny spheres of known radius once per light (the k images in the rig's light order),
optionally at two or more *placements* (image sets with the spheres moved). Each sphere is
located in 3-D from its outline (a mask, or detection in the images), the highlight of every
image is found on it (intensity-weighted centroid of the brightest blob, sub-pixel, also when
saturated), and the mirror-reflected viewing ray through the highlight points at the light.
Each light is the least-squares point closest to its rays; rays that agree within
``parallel_tol`` degrees make a distant (directional) light. A light needs rays from two
spheres (in one placement or in several) for a position; one ray gives a direction with a
warning. Spheres of two placements at the same place (a placement given twice) and spheres
under 40 pixels in radius in the images are named in the warnings. The result's
:attr:`SphereCalibration.rig` holds the calibrated lights with unit intensities.

*Orthographic cameras* need the depth of each sphere centre (``center_depth``): for a ball
resting on a board at depth ``z_b`` it is ``z_b - R``, for a hemisphere lying flat on it
``z_b``. *Pinhole cameras* get the depth from the outline: the image of a sphere is the section
of its tangent cone, whose half-angle is ``asin(R / D)``; a given ``center_depth`` overrides it.

**Intensity calibration** (:func:`calibrate_intensities`). Photograph a flat diffuse (white)
board on a known plane ``n . X = d`` (camera frame) once per light. With the light positions
(and LED axes and anisotropy, if known) the image model ``I = rho * Phi_i * max(0, n .
beta_i(X))`` gives each light's intensity by linear least squares. The board's albedo and the
exposure cannot be told apart from the intensities: the result is relative, scaled to a
geometric mean of 1 over all lights (and channels). ``albedo="per_pixel"`` also estimates the
board's albedo per pixel (absorbing texture and vignetting); ``fit_mu`` / ``fit_direction`` fit
the LEDs' anisotropy and axes (principal directions) by Levenberg-Marquardt.

Synthetic calibration scenes (spheres and a board, with the true rig) are in
:mod:`nplps.synth_calibration`, beside :mod:`nplps.synth`.

See ``docs/calibration.md`` for the method and the measured accuracy.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import _core, _core_types, io, pipeline
from ._atomic import atomic_write
from .errors import InputError, RigError
from .rig import DirectionalLight, Light, PointLight, Rig, read_rig_json
from .types import BoardAlbedo, Outline

__all__ = [
    "IntensityCalibration",
    "LightReport",
    "SphereCalibration",
    "SphereReport",
    "calibrate_intensities",
    "calibrate_spheres",
    "compare_lights",
    "light_table",
    "load_camera",
    "reference_summary",
    "save_camera",
]

ImageSet = np.ndarray | Sequence[Any]
"""One placement's images: a (k, H, W[, 3]) array or k image files / arrays."""

# --------------------------------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SphereReport:
    """A located sphere."""

    #: Index over all spheres of all placements.
    index: int
    #: Placement (image set) that shows it.
    placement: int
    #: Centre (x, y, z) in the camera frame.
    center: np.ndarray
    #: Radius (as given).
    radius: float
    #: Image of the centre (u, v), pixels.
    image_center: np.ndarray
    #: Mean image radius, pixels.
    image_radius: float
    #: RMS distance of the outline points from the fitted outline, pixels.
    fit_rms: float
    #: Outline points kept by the robust fit and found.
    outline_points: tuple[int, int]
    #: Orthographic: fitted radius / given radius (1 when the pixel size is right). Pinhole with
    #: a given centre depth: distance from the outline / from the depth. Otherwise 1.
    scale_check: float
    #: How far the joint refinement moved the centre from the outline's (scene units).
    shift: float = 0.0
    #: Precision of the outline's centre assumed by the joint refinement (pixels): 0.01 for a
    #: mask that is the pixel sampling of a circle (fitted by the widest separating circle or
    #: cone), 0.03 for a least-squares outline fit.
    outline_sigma: float = 0.03


@dataclass(frozen=True)
class LightReport:
    """One light's calibration."""

    index: int
    #: "point", "directional" or "missing".
    kind: str
    #: Position (point lights), else None.
    position: np.ndarray | None
    #: Unit direction towards the light (directional lights), else None.
    direction: np.ndarray | None
    #: RMS distance of the rays from the position (NaN unless a point light), scene units.
    rms_miss: float
    #: RMS angle between each ray and the direction to the position (or the mean direction),
    #: degrees.
    rms_angle: float
    #: Largest angle between two rays, degrees.
    spread: float
    #: Number of spheres the light was seen on.
    spheres: int
    #: Why the light is not a located point light, if it is not.
    warning: str | None
    #: Standard error of the position (x, y, z; scene units) that the images' precision gives
    #: (point lights seen on 2 or more spheres, else None): each mirror ray's angle is off by
    #: twice the sphere normal's error, ``2 sqrt(outline_sigma^2 + highlight_sigma^2) / image
    #: radius`` (pixels: the outline's precision and the joint refinement's highlight
    #: precision, 0.03 px without it), and the rays are triangulated with those weights. The
    #: given centre depth, the radius and the camera are taken as exact (docs/calibration.md).
    standard_error: np.ndarray | None = None
    #: A distant light's direction error (degrees; NaN otherwise) from the same ray precisions:
    #: the RMS angle between the found and the true direction (both axes).
    direction_se: float = float("nan")


@dataclass
class SphereCalibration:
    """The result of :func:`calibrate_spheres`."""

    #: The camera mapping of the rig file.
    camera: dict[str, Any]
    spheres: list[SphereReport]
    lights: list[LightReport]
    #: (k, S, 2) sub-pixel highlight (u, v) per light and sphere (NaN where none was taken).
    highlights: np.ndarray = field(repr=False)
    #: (k, S) "ok" or why no highlight was taken.
    status: list[list[str]] = field(repr=False)
    #: (k, S, 3) origins (surface points) and unit directions of the reflected rays (NaN where
    #: none).
    ray_origins: np.ndarray = field(repr=False)
    ray_directions: np.ndarray = field(repr=False)
    #: Notes and warnings (lights seen on fewer than two spheres, a pixel size that does not
    #: match the radius, ignored mask regions, ...).
    warnings: list[str] = field(default_factory=list)
    #: The joint refinement of spheres and lights (None if it did not run): ``iterations``,
    #: ``highlights`` used, ``dropped`` (inconsistent highlights), ``highlight_rms`` before and
    #: after (pixels), ``outline_shift`` (RMS move of the spheres from their outlines' estimates,
    #: pixels), ``highlight_sigma`` (pixels).
    refinement: dict[str, Any] | None = None

    @property
    def rig(self) -> Rig:
        """The calibrated rig.

        Point lights at the positions, directional lights along the directions, all with
        intensity 1. Raises :class:`RigError` when a light was not seen on any sphere.
        """
        missing = [rep.index for rep in self.lights if rep.kind == "missing"]
        if missing:
            raise RigError(
                f"light(s) {', '.join(map(str, missing))} were not seen on any sphere: no rig can be "
                "written (check those images, or the highlight thresholds)"
            )
        # The core's unit directions are kept as they are (not scaled again).
        lights: list[Light] = [
            PointLight._checked(f"light {rep.index}", rep.position)
            if rep.kind == "point"
            else DirectionalLight._checked(f"light {rep.index}", rep.direction, normalize=False)
            for rep in self.lights
        ]
        return Rig(camera=self.camera, lights=lights)

    def rig_or_none(self) -> Rig | None:
        """Return :attr:`rig`, or None when a light was not seen on any sphere."""
        try:
            return self.rig
        except RigError:
            return None

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the calibrated rig file (see :attr:`rig`)."""
        self.rig.save(path)

    def table(self) -> str:
        """Return the per-light report as a text table."""
        return light_table(self.lights)


def light_table(lights: Sequence[LightReport]) -> str:
    """Return a text table of light reports: kind, position or direction, spheres, miss, angle, standard error.

    The ``se`` column is the length of the position's standard error (scene units) for a point
    light, the direction's (degrees) for a distant one.
    """
    lines = [
        f"{'light':>5}  {'kind':<11} {'x / dx':>10} {'y / dy':>10} {'z / dz':>10} {'spheres':>7} "
        f"{'rms miss':>9} {'rms angle':>9} {'spread':>7} {'se':>9}  note"
    ]
    for rep in lights:
        vec = rep.position if rep.kind == "point" else rep.direction
        if vec is None:
            cells = f"{'-':>10} {'-':>10} {'-':>10}"
        elif rep.kind == "point":
            cells = " ".join(f"{v:>10.3f}" for v in vec)
        else:
            cells = " ".join(f"{v:>10.5f}" for v in vec)
        miss = f"{rep.rms_miss:>9.3f}" if np.isfinite(rep.rms_miss) else f"{'-':>9}"
        angle = f"{rep.rms_angle:>8.3f}°" if np.isfinite(rep.rms_angle) else f"{'-':>9}"
        spread = f"{rep.spread:>6.2f}°" if rep.spheres > 1 else f"{'-':>7}"
        note = rep.warning or ""
        se_value = _se_length(rep)
        if not np.isfinite(se_value):
            se = f"{'-':>9}"
        elif rep.kind == "point":
            se = f"{se_value:>9.3f}"
        else:
            se = f"{se_value:>8.3f}°"
        row = f"{rep.index:>5}  {rep.kind:<11} {cells} {rep.spheres:>7} {miss} {angle} {spread} {se}  {note}"
        lines.append(row.rstrip())
    return "\n".join(lines)


def _se_length(rep: LightReport) -> float:
    """Return the length of a light's position standard error, or its direction's (degrees); NaN if none."""
    if rep.kind == "point":
        return float("nan") if rep.standard_error is None else float(np.linalg.norm(rep.standard_error))
    return rep.direction_se


def _ray_standard_errors(
    kind: str, vector: np.ndarray | None, origins: np.ndarray, directions: np.ndarray, angle_sigma: np.ndarray
) -> tuple[np.ndarray | None, float]:
    """Return a light's position standard error (x, y, z) and direction standard error (degrees) from its rays.

    `origins` and `directions` are the light's (S, 3) rays (NaN rows where none), `angle_sigma`
    each ray's angular standard deviation (radians, see :func:`_ray_angle_sigma`). A ray at
    distance L from a point light constrains it across the ray with the standard deviation
    ``angle_sigma * L``; the covariance of the position is the inverse of
    ``sum (I - d d^T) / (angle_sigma L)^2``. A distant light's direction (the rays' mean) is off
    by ``sqrt(2 / sum angle_sigma^-2)`` RMS (two axes). See :attr:`LightReport.standard_error`.
    """
    ok = np.isfinite(origins).all(axis=1) & np.isfinite(directions).all(axis=1) & np.isfinite(angle_sigma)
    o, d, sigma = origins[ok], directions[ok], angle_sigma[ok]
    if vector is None or len(o) < (2 if kind == "point" else 1):
        return None, float("nan")
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    if kind == "point":
        reach = np.linalg.norm(vector[None] - o, axis=1)
        across = np.maximum(sigma * reach, 1e-12)
        projectors = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
        a = np.sum(projectors / across[:, None, None] ** 2, axis=0)
        try:
            cov = np.linalg.inv(a)
        except np.linalg.LinAlgError:
            return None, float("nan")
        return np.sqrt(np.maximum(np.diag(cov), 0.0)), float("nan")
    return None, float(np.degrees(np.sqrt(2.0 / np.sum(sigma**-2.0))))


def _ray_angle_sigma(sphere: SphereReport, highlight_sigma: float) -> float:
    """Return the angular standard deviation (radians) of a mirror ray off `sphere`.

    The sphere's normal at the highlight is off by the error of its centre (the outline's
    precision, :attr:`SphereReport.outline_sigma`) and of the highlight's position
    (`highlight_sigma`), both in pixels, over the sphere's image radius; the mirror ray turns by
    twice that.
    """
    return 2.0 * float(np.hypot(sphere.outline_sigma, highlight_sigma)) / max(sphere.image_radius, 1e-9)


def compare_lights(calibrated: Rig, reference: Rig, distance: float) -> list[dict[str, Any]]:
    """Compare calibrated lights with a reference rig's (e.g. a synthetic scene's ``rig_true.json``).

    Parameters
    ----------
    calibrated, reference : Rig
        Rigs with the same number of lights in the same order.
    distance : float
        The working distance the position errors are given as a percentage of.

    Returns
    -------
    list of dict
        Per light: ``light``, ``kind`` ("point" or "directional", the calibrated light's),
        ``position_error`` (the distance between the positions, scene units; None unless both
        are point lights), ``position_error_percent`` (of `distance`), ``offset`` (calibrated -
        reference, x, y, z), ``direction_error`` (degrees, between the directions of two distant
        lights, else None) and ``intensity_error_percent`` (calibrated / reference - 1, in %,
        after scaling both rigs' intensities to a geometric mean of 1 over the lights and
        channels).

    Raises
    ------
    InputError
        The rigs have different numbers of lights, or `distance` is not positive.
    """
    if calibrated.n_lights != reference.n_lights:
        raise InputError(
            f"the reference rig has {reference.n_lights} lights but the calibration {calibrated.n_lights}: "
            "give the reference of the same lights, in the same order"
        )
    if not (np.isfinite(distance) and distance > 0):
        raise InputError(f"the working distance must be positive, got {distance}")

    def relative(rig: Rig) -> np.ndarray:
        phi = np.asarray(rig.intensities, dtype=np.float64)
        return phi / np.exp(np.mean(np.log(phi)))

    ratio = np.mean(relative(calibrated) / relative(reference), axis=1)
    rows = []
    for i in range(calibrated.n_lights):
        row: dict[str, Any] = {
            "light": i,
            "kind": "directional" if calibrated.directional[i] else "point",
            "position_error": None,
            "position_error_percent": None,
            "offset": None,
            "direction_error": None,
            "intensity_error_percent": float(100 * (ratio[i] - 1)),
        }
        if not calibrated.directional[i] and not reference.directional[i]:
            offset = calibrated.positions[i] - reference.positions[i]
            error = float(np.linalg.norm(offset))
            row.update(
                position_error=error,
                position_error_percent=100 * error / distance,
                offset=[float(v) for v in offset],
            )
        elif calibrated.directional[i] and reference.directional[i]:
            cos = float(np.clip(calibrated.directions[i] @ reference.directions[i], -1.0, 1.0))
            row["direction_error"] = float(np.degrees(np.arccos(cos)))
        rows.append(row)
    return rows


def reference_summary(rows: Sequence[dict[str, Any]]) -> dict[str, float | None]:
    """Return the RMS and largest errors of :func:`compare_lights` rows (None where no light has one)."""

    def stats(key: str) -> tuple[float | None, float | None]:
        values = np.array([r[key] for r in rows if r[key] is not None], dtype=np.float64)
        if not values.size:
            return None, None
        return float(np.sqrt(np.mean(values**2))), float(np.max(np.abs(values)))

    out: dict[str, float | None] = {}
    for key in ("position_error", "position_error_percent", "direction_error", "intensity_error_percent"):
        out[f"{key}_rms"], out[f"{key}_max"] = stats(key)
    return out


@dataclass
class IntensityCalibration:
    """The result of :func:`calibrate_intensities`."""

    #: The input rig with the fitted intensities (and LED axes and mu, if fitted).
    rig: Rig
    #: (k, C) relative intensities (geometric mean 1 over all lights and channels).
    intensities: np.ndarray
    #: (k,) anisotropy mu (as given unless fitted).
    mu: np.ndarray
    #: (k, 3) LED axes (principal directions, as given unless fitted; (0, 0, 1) for lights that
    #: are not LEDs and were not fitted).
    axes: np.ndarray
    #: (k,) RMS residual per light, relative to the light's mean observation.
    rms: np.ndarray
    #: (k,) observations used per light (pixels x channels).
    observations: np.ndarray
    #: The factor removed from the intensities (board albedo times exposure).
    scale: float
    #: Relative board albedo (H, W[, 3]): 1 for a uniform board, the fitted albedo with
    #: ``albedo="per_pixel"``; NaN outside the mask.
    albedo: np.ndarray = field(repr=False)
    iterations: int = 0
    warnings: list[str] = field(default_factory=list)

    @property
    def standard_errors(self) -> np.ndarray:
        """(k,) relative standard error of each light's intensity from its residual: ``rms / sqrt(observations)``.

        The error of a scale fitted to the light's observations alone; it leaves out the fitted
        LED shape (mu, axis) and the error of the light positions, which the intensities
        absorb (docs/calibration.md).
        """
        obs = np.maximum(np.asarray(self.observations, dtype=np.float64), 1.0)
        return np.where(np.asarray(self.observations) > 0, np.asarray(self.rms) / np.sqrt(obs), np.nan)

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the calibrated rig file."""
        self.rig.save(path)

    def table(self) -> str:
        """Return the per-light report as a text table."""
        c = self.intensities.shape[1]
        head = "intensity" if c == 1 else "intensity R, G, B"
        lines = [
            f"{'light':>5}  {'kind':<11} {head:>{10 if c == 1 else 32}} {'mu':>6} {'rms %':>7} {'se %':>7} {'obs':>8}"
        ]
        se = self.standard_errors
        for i in range(self.intensities.shape[0]):
            kind = "directional" if self.rig.directional[i] else "point"
            phi = " ".join(f"{v:>10.5f}" for v in self.intensities[i])
            rms, obs = 100 * self.rms[i], int(self.observations[i])
            lines.append(f"{i:>5}  {kind:<11} {phi} {self.mu[i]:>6.3f} {rms:>7.3f} {100 * se[i]:>7.4f} {obs:>8}")
        return "\n".join(lines)


# --------------------------------------------------------------------------------------------------
# Sphere calibration
# --------------------------------------------------------------------------------------------------


def _camera_of(camera: Rig | Mapping[str, Any]) -> dict[str, Any]:
    if isinstance(camera, Rig):
        return dict(camera.camera)
    if isinstance(camera, Mapping) and "model" in camera:
        # Validate the camera through a rig with three placeholder lights.
        Rig(camera=dict(camera), lights=np.array([[0.0, 0.0, -1.0], [1.0, 0.0, -1.0], [0.0, 1.0, -1.0]]))
        return dict(camera)
    raise RigError("camera must be an nplps.Rig or a camera mapping with a 'model' key (see the rig file)")


def load_camera(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Return the camera mapping of a rig file.

    Its lights, if any, are ignored (a file with ``"lights": []`` describes a camera only). Raises
    :class:`RigError` naming the problem.
    """
    data = read_rig_json(path)  # within the rig file's limits (size, nesting), as Rig.load
    if not isinstance(data, dict) or not isinstance(data.get("camera"), dict):
        raise RigError(f"{os.fspath(path)}: a rig file holds a JSON object with a 'camera' object")
    return _camera_of(data["camera"])


def save_camera(path: str | os.PathLike[str], camera: Rig | Mapping[str, Any]) -> None:
    """Write a rig file with the camera only (``"lights": []``), for :func:`load_camera`."""
    from .rig import RIG_FILE_VERSION

    cam = _camera_of(camera)
    with atomic_write(path, "w", encoding="utf-8") as f:
        json.dump({"version": RIG_FILE_VERSION, "camera": cam, "lights": []}, f, indent=2)
        f.write("\n")


def _placements(images: ImageSet | Sequence[ImageSet]) -> list[ImageSet]:
    """Return the placements: a single (k, H, W[, 3]) array is one placement; otherwise a list."""
    if isinstance(images, np.ndarray):
        if images.ndim in (3, 4):
            return [images]
        raise InputError(f"sphere images must be (k, H, W) or (k, H, W, 3), got shape {images.shape}")
    if isinstance(images, (str, os.PathLike)):
        raise InputError("give a list of placements, each a (k, H, W) array or a list of k image files")
    items = list(images)
    if not items:
        raise InputError("no sphere images (no placement) given")
    return items


def _labels(mask: Any, shape: tuple[int, int], where: str) -> np.ndarray:
    """Read a mask file or array as uint32 labels.

    A binary mask (one non-zero value) becomes 0/1 (each connected component a sphere); integer
    labels are kept.
    """
    if isinstance(mask, (str, os.PathLike)):
        a = io.read_image(mask)
        if a.ndim == 3:
            a = a[..., 0]
    else:
        a = np.asarray(mask)
        if a.ndim == 3:
            a = a[..., 0]
    if a.shape != shape:
        raise InputError(f"{where}: the mask has shape {a.shape} but the images have shape {shape} (H, W)")
    if a.dtype == np.bool_:
        if not a.any():
            raise InputError(f"{where}: the mask is empty (marks no sphere)")
        return np.ascontiguousarray(a, dtype=np.uint32)
    if np.issubdtype(a.dtype, np.floating):
        a = np.nan_to_num(a, nan=0.0)
        if np.any(a < 0):
            raise InputError(f"{where}: mask values must be non-negative")
    values = np.unique(a[a != 0])
    if values.size == 0:
        raise InputError(f"{where}: the mask is empty (marks no sphere)")
    if values.size == 1:
        return np.ascontiguousarray(a != 0, dtype=np.uint32)
    if not np.all(np.equal(np.mod(values, 1), 0)):
        raise InputError(f"{where}: a label mask needs integer labels")
    return np.ascontiguousarray(a, dtype=np.uint32)


def _depths(center_depth: Any, n: int) -> list[list[float]]:
    """Per placement: [] (none), [z] (all its spheres) or [z_0, z_1, ...] (per sphere)."""
    if center_depth is None:
        return [[] for _ in range(n)]
    if np.isscalar(center_depth):
        return [[float(center_depth)] for _ in range(n)]  # type: ignore[arg-type]
    items = list(center_depth)
    if len(items) != n:
        raise InputError(f"center_depth must be one number, or one entry per placement ({n}), got {len(items)} entries")
    out: list[list[float]] = []
    for item in items:
        if item is None:
            out.append([])
        elif np.isscalar(item):
            value: Any = item
            out.append([float(value)])
        else:
            out.append([float(v) for v in item])
    return out


def calibrate_spheres(
    images: ImageSet | Sequence[ImageSet],
    camera: Rig | Mapping[str, Any],
    radius: float,
    *,
    masks: Any = None,
    detect: tuple[float, float] | None = None,
    count: int | None = None,
    center_depth: Any = None,
    outline: Outline = "mask",
    parallel_tol: float = 0.5,
    min_contrast: float = 0.3,
    max_blob_fraction: float = 0.05,
    limb_margin: float = 0.97,
    refine: bool = True,
) -> SphereCalibration:
    """Calibrate the light positions from images of shiny spheres.

    Parameters
    ----------
    images : ImageSet | Sequence[ImageSet]
        A list of placements, each a (k, H, W[, 3]) array or a list of k image files /
        arrays (one per light, in the rig's order; all placements the same k and size). A
        single (k, H, W[, 3]) array is one placement. Integer images are scaled to [0, 1];
        colour becomes grey.
    camera : Rig | Mapping[str, Any]
        An :class:`~nplps.Rig` (its lights are ignored) or the rig file's camera mapping.
    radius : float
        The spheres' radius (scene units; the same for all spheres).
    masks : Any, optional
        Per placement a mask (file or (H, W) array) or None: a binary mask marks each
        sphere as one connected region; an integer label image marks sphere j with label j.
        A single mask (not in a list) serves a single placement.
    detect : tuple[float, float] | None, optional
        (min, max) image radius in pixels: find the spheres in the composite image (each
        pixel's brightest value over the lights) of each
        placement without a mask (they must be brighter than the background).
    count : int | None, optional
        With ``detect``, how many spheres each placement shows (default: all found).
    center_depth : Any, optional
        Depth (z) of the sphere centres: one number for all, or per placement a
        number or a list with one per sphere (in the order of the mask's labels, or of
        detection: by row then column). Required for an orthographic camera; with a pinhole
        camera it overrides the distance from the outline.
    outline : str, optional
        "mask" (the mask's boundary, sub-pixel crack midpoints) or "images" (the
        outline in the composite image, refined from the mask's circle). Detection always uses
        the images.
    parallel_tol : float, optional
        Rays whose RMS angle about their mean direction is at most this many
        degrees make a directional (distant) light.
    min_contrast, max_blob_fraction, limb_margin : float, optional
        Highlight search: the brightest value must exceed the sphere's median by ``min_contrast``
        times itself, the blob above their midpoint may cover at most ``max_blob_fraction`` of the
        sphere, and only the pixels whose ray passes within ``limb_margin`` radii of the centre are
        searched.
    refine : bool, optional
        Refine the sphere centres and the lights jointly (a small bundle adjustment of
        the outlines and the highlights; see ``docs/calibration.md``). A binary mask places
        a sphere's centre only to a few hundredths of a pixel, which turns every ray by about
        0.1 degree; the highlights of all lights pin it much better.

    Returns
    -------
    SphereCalibration
        A :class:`SphereCalibration` with ``.rig``, per-light reports ``.lights`` (position or
        direction, RMS miss distance, spheres seen), ``.spheres``, ``.warnings`` and ``.table()``.

    Raises
    ------
    InputError
        Unreadable or inconsistent images or masks, no sphere found, a bad option.
    RigError
        An invalid camera.
    """
    cam = _camera_of(camera)
    sets = _placements(images)
    n = len(sets)
    stacks = [np.ascontiguousarray(io.load_stack(s, color=False)[0], dtype=np.float32) for s in sets]
    shape = stacks[0].shape
    for i, s in enumerate(stacks):
        if s.shape != shape:
            raise InputError(
                f"placement {i} has {s.shape[0]} images of {s.shape[2]} x {s.shape[1]} pixels but placement 0 "
                f"has {shape[0]} of {shape[2]} x {shape[1]}: every placement needs one image per light, all of one size"
            )
    if masks is None:
        mask_list: list[Any] = [None] * n
    elif isinstance(masks, (str, os.PathLike, np.ndarray)):
        if n != 1:
            raise InputError(f"give one mask per placement ({n}), as a list")
        mask_list = [masks]
    else:
        mask_list = list(masks)
        if len(mask_list) != n:
            raise InputError(f"give one mask (or None) per placement: {n} placements, {len(mask_list)} masks")
    if count is not None and (
        isinstance(count, bool) or not isinstance(count, (int, np.integer)) or not 1 <= int(count) <= 1_000_000
    ):
        raise InputError(f"count must be a whole number of spheres per placement, at least 1, got {count!r}")
    labels: list[np.ndarray | None] = []
    dets: list[tuple[float, float, int | None] | None] = []
    for i, m in enumerate(mask_list):
        if m is not None:
            labels.append(_labels(m, shape[1:], f"placement {i}"))
            dets.append(None)
        elif detect is not None:
            lo, hi = (float(v) for v in detect)
            labels.append(None)
            dets.append((lo, hi, None if count is None else int(count)))
        else:
            raise InputError(f"placement {i} has no mask: give masks=..., or detect=(min, max) image radius in pixels")
    if not (np.isfinite(radius) and radius > 0):
        raise InputError(f"the sphere radius must be positive, got {radius}")
    if cam.get("model") == "orthographic" and center_depth is None:
        raise InputError(
            "an orthographic camera needs the depth of the sphere centres: center_depth=... (command line: "
            "--center-depth); for balls on a board at depth z it is z - radius, for hemispheres lying on it z"
        )
    options: _core_types.SphereOptions = {
        "outline": outline,
        "parallel_tol": float(parallel_tol),
        "min_contrast": float(min_contrast),
        "max_blob_fraction": float(max_blob_fraction),
        "limb_margin": float(limb_margin),
        "refine": bool(refine),
    }
    d = _core.calibrate_spheres(stacks, labels, dets, _depths(center_depth, n), cam, float(radius), options)
    spheres = [
        SphereReport(
            index=j,
            placement=int(s["placement"]),
            center=np.array(s["center"]),
            radius=float(s["radius"]),
            image_center=np.array(s["image_center"]),
            image_radius=float(s["image_radius"]),
            fit_rms=float(s["fit_rms"]),
            outline_points=(int(s["outline_points"][0]), int(s["outline_points"][1])),
            scale_check=float(s["scale_check"]),
            shift=float(s["shift"]),
            outline_sigma=float(s["outline_sigma"]),
        )
        for j, s in enumerate(d["spheres"])
    ]
    lights = []
    obs = d["observations"]
    refinement = d.get("refinement")
    # Highlights without the joint refinement: their sub-pixel centroid taken to 0.03 px.
    highlight_sigma = float(refinement["highlight_sigma"]) if refinement else 0.03
    angle_sigma = np.array([_ray_angle_sigma(sp, highlight_sigma) for sp in spheres])
    for i, rep in enumerate(d["lights"]):
        vec = None if rep["vector"] is None else np.array(rep["vector"])
        se, direction_se = _ray_standard_errors(
            rep["kind"],
            vec,
            np.asarray(obs["origin"][i], dtype=np.float64),
            np.asarray(obs["direction"][i], dtype=np.float64),
            angle_sigma,
        )
        lights.append(
            LightReport(
                index=i,
                kind=rep["kind"],
                position=vec if rep["kind"] == "point" else None,
                direction=vec if rep["kind"] == "directional" else None,
                rms_miss=float(rep["rms_miss"]),
                rms_angle=float(rep["rms_angle"]),
                spread=float(rep["spread"]),
                spheres=int(rep["spheres"]),
                warning=rep["warning"],
                standard_error=se,
                direction_se=direction_se,
            )
        )
    k, ns = obs["peak"].shape
    status = [list(obs["status"][i * ns : (i + 1) * ns]) for i in range(k)]
    notes = [*_same_places(spheres, stacks, float(radius)), *_small_spheres(spheres), *d["warnings"]]
    return SphereCalibration(
        camera=cam,
        spheres=spheres,
        lights=lights,
        highlights=obs["pixel"],
        status=status,
        ray_origins=obs["origin"],
        ray_directions=obs["direction"],
        warnings=notes,
        refinement=dict(d["refinement"]) if "refinement" in d else None,
    )


#: The smallest image radius (pixels) of a sphere that locates the lights well (docs/calibration.md).
MIN_SPHERE_PX = 40.0

# Spheres of two placements whose centres are closer than this many radii stand at the same place.
_SAME_PLACE = 0.05


def _same_places(spheres: Sequence[SphereReport], stacks: Sequence[np.ndarray], radius: float) -> list[str]:
    """Return a warning per pair of placements that put a sphere at the same place.

    Such placements add no second viewpoint: their rays towards a light are parallel, so the lights
    seen only there come out directional (or badly placed). The commonest cause is one placement
    given twice.
    """
    out = []
    placements = sorted({s.placement for s in spheres})
    for a in placements:
        for b in placements:
            if b <= a:
                continue
            pairs = [
                (s.index, t.index, float(np.linalg.norm(s.center - t.center)))
                for s in spheres
                if s.placement == a
                for t in spheres
                if t.placement == b and np.linalg.norm(s.center - t.center) < _SAME_PLACE * radius
            ]
            if not pairs:
                continue
            same = ", ".join(f"sphere {i} and sphere {j} ({gap:.3g} apart)" for i, j, gap in pairs)
            cause = (
                "the images are identical: the same placement given twice?"
                if np.array_equal(stacks[a], stacks[b])
                else "was the sphere moved between them?"
            )
            out.append(
                f"placements {a} and {b} put a sphere at the same place ({same}; {cause}): a sphere seen "
                "twice at one place gives no second viewpoint, so the lights are located as if from one "
                "sphere there (directional or uncertain); move the spheres between placements"
            )
    return out


def _small_spheres(spheres: Sequence[SphereReport]) -> list[str]:
    """Return a warning naming the spheres smaller than :data:`MIN_SPHERE_PX` in the images."""
    # Half a pixel of slack: a ball made 40 px in radius measures 39.99 px.
    small = [s for s in spheres if s.image_radius < MIN_SPHERE_PX - 0.5]
    if not small:
        return []
    names = ", ".join(f"sphere {s.index} (placement {s.placement}) {s.image_radius:.1f} px" for s in small)
    return [
        f"sphere(s) smaller than {MIN_SPHERE_PX:g} pixels in radius in the images: {names}; the light positions "
        f"need at least {MIN_SPHERE_PX:g} px (docs/calibration.md: smaller spheres give errors of several % "
        "and more): use larger spheres or bring the camera closer"
    ]


# --------------------------------------------------------------------------------------------------
# Intensity calibration
# --------------------------------------------------------------------------------------------------


def _plane(plane: Any) -> tuple[list[float], float]:
    """Return (normal, offset) from a depth, a (normal, offset) pair or a mapping."""
    if np.isscalar(plane):
        depth: Any = plane
        z = float(depth)
        if not (np.isfinite(z) and z > 0):
            raise InputError(f"the board depth must be positive, got {depth}")
        return [0.0, 0.0, -1.0], -z
    if isinstance(plane, Mapping):
        plane = (plane.get("normal"), plane.get("offset"))
    try:
        normal, offset = plane
        n = [float(v) for v in normal]
        d = float(offset)
    except (TypeError, ValueError):
        raise InputError(
            "plane must be the board's depth, or (normal, offset) with normal . X = offset in the camera frame"
        ) from None
    if len(n) != 3 or not np.all(np.isfinite(n)) or not np.isfinite(d) or not np.any(n):
        raise InputError(f"plane normal must be 3 finite numbers, not all zero, and the offset finite; got {plane!r}")
    return n, d


def calibrate_intensities(
    images: ImageSet,
    rig: Rig,
    plane: Any,
    *,
    mask: Any = None,
    fit_mu: bool = False,
    fit_direction: bool = False,
    albedo: BoardAlbedo = "uniform",
    color: bool = False,
    dark: float | None = None,
    saturation: float | None = None,
    iterations: int = 100,
) -> IntensityCalibration:
    """Calibrate the light intensities from images of a flat diffuse board.

    Parameters
    ----------
    images : ImageSet
        (k, H, W[, 3]) array or k image files, one per light of ``rig``.
    rig : Rig
        The rig with the light positions (e.g. from :func:`calibrate_spheres`) and, for
        LEDs, their axes and mu if known.
    plane : Any
        The board: its depth z (a plane facing the camera), or ``(normal, offset)`` with
        ``normal . X = offset`` in the camera frame.
    mask : Any, optional
        The board's pixels (file or (H, W) array; None: every pixel).
    fit_mu : bool, optional
        Fit each point light's anisotropy mu (starting from the rig's, or 1).
    fit_direction : bool, optional
        With ``fit_mu``, fit each LED's axis (principal direction) too (starting
        from the rig's, or from the LED towards the board's centre).
    albedo : str, optional
        "uniform" (one albedo for the board) or "per_pixel" (also estimated per pixel:
        absorbs texture and vignetting; needs the lights to differ enough).
    color : bool, optional
        Fit the R, G, B intensities of colour images separately (the board is assumed
        white: its colour is taken as the lights'); default grey.
    dark, saturation : float | None, optional
        Observations at or below ``dark`` or at or above ``saturation`` are
        left out (defaults: one level above black and the top level for integer images).
    iterations : int, optional
        Most alternations (per-pixel albedo) or Levenberg-Marquardt steps.

    Returns
    -------
    IntensityCalibration
        An :class:`IntensityCalibration` with the calibrated ``.rig`` (relative intensities,
        geometric mean 1), per-light ``.intensities``, ``.mu``, ``.axes``, ``.rms``.
    """
    if not isinstance(rig, Rig):
        raise RigError("rig must be an nplps.Rig (the light positions are needed)")
    if albedo not in ("uniform", "per_pixel"):
        raise InputError(f"albedo must be 'uniform' or 'per_pixel', got {albedo!r}")
    if fit_direction and not fit_mu:
        raise InputError("fit_direction needs fit_mu (an isotropic light has no direction)")
    stack, levels = io.load_stack(images, color=color)
    if stack.shape[0] != rig.n_lights:
        raise InputError(f"{stack.shape[0]} board images but the rig has {rig.n_lights} lights: give one per light")
    dark, saturation = pipeline.thresholds(levels, dark=dark, saturation=saturation)
    m = None if mask is None else io.load_mask(mask, stack.shape[1:3])
    normal, offset = _plane(plane)
    options: _core_types.IntensityOptions = {
        "fit_mu": bool(fit_mu),
        "fit_direction": bool(fit_direction),
        "albedo": albedo,
        "dark": float(dark),
        "saturation": float(saturation),
        "iterations": int(iterations),
    }
    d = _core.calibrate_intensities(
        np.ascontiguousarray(stack, dtype=np.float32), m, rig._native, normal, offset, options
    )
    out = Rig._from_native(d["lights"], like=rig)
    return IntensityCalibration(
        rig=out,
        intensities=d["intensity"],
        mu=np.array(d["mu"]),
        axes=np.array(d["axes"]),
        rms=np.array(d["rms"]),
        observations=np.array(d["observations"]),
        scale=float(d["scale"]),
        albedo=d["albedo"],
        iterations=int(d["iterations"]),
        warnings=list(d["warnings"]),
    )
