"""Synthetic calibration scenes, beside :mod:`nplps.synth`'s reconstruction scenes.

:func:`make_sphere_scene` renders shiny spheres (Lambertian plus a Phong lobe, highlights
saturating, 8-bit, noise) on a dark board and :func:`make_board_scene` a flat board, for the
same rigs as :func:`nplps.make_scene` (:func:`standard_rig`), with the true rig for comparison;
:func:`nplps.calibrate.calibrate_spheres` and :func:`nplps.calibrate.calibrate_intensities`
calibrate from them (``nplps synth-calibration`` writes them as files).
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from . import _core, _core_types, export
from ._atomic import write_text
from ._outdir import result_directory
from .calibrate import _plane, save_camera
from .errors import InputError
from .rig import Rig

__all__ = [
    "LIGHTS_8",
    "BoardScene",
    "SphereScene",
    "default_placements",
    "make_board_scene",
    "make_sphere_scene",
    "standard_rig",
]

#: The 8 of the 27 standard lights used by ``lights=8`` (spread over the three layers; with
#: ``directional=True`` lights 2, 14 and 23 are directional).
LIGHTS_8 = (0, 2, 4, 7, 12, 14, 19, 23)


@dataclass
class SphereScene:
    """A synthetic sphere-calibration scene."""

    #: Per placement, the (k, H, W) images (uint8 for 8 bits, uint16 above, float64 for 0).
    images: list[np.ndarray] = field(repr=False)
    #: Per placement, (H, W) uint32 labels (0 background, j + 1 for the placement's sphere j):
    #: the pixels whose centre sees a sphere.
    labels: list[np.ndarray] = field(repr=False)
    #: Per placement, (S, 3) true sphere centres.
    centers: list[np.ndarray]
    radius: float
    #: The true rig (camera and lights, as :func:`nplps.make_scene` builds them).
    rig: Rig
    #: Indices of the lights into the 27 standard lights.
    light_indices: list[int]
    #: Depth of the board the spheres rest on.
    board_depth: float
    #: Working distance of :func:`nplps.make_scene` (object size ``size``).
    distance: float
    size: float

    @property
    def masks(self) -> list[np.ndarray]:
        """Per placement, the (H, W) boolean mask of the spheres."""
        return [lab > 0 for lab in self.labels]

    @property
    def center_depths(self) -> list[list[float]]:
        """Per placement, the true depth of each sphere centre."""
        return [[float(c[2]) for c in cs] for cs in self.centers]

    def save(self, directory: str | os.PathLike[str], overwrite: bool = False) -> dict[str, Path]:
        """Write the images, masks, camera, true rig and scene description into ``directory``.

        Write ``placement_<i>/image_XX.png`` and ``placement_<i>/mask.png`` per placement,
        ``camera.json`` (the camera, no lights), ``rig_true.json`` and ``scene.json`` (radius,
        centre depths, board depth), and the manifest ``nplps-manifest.json``. ``directory`` must be
        empty unless ``overwrite=True`` (see :meth:`nplps.Reconstruction.save`).
        """
        meta = {
            "radius": self.radius,
            "center_depths": self.center_depths,
            "centers": [c.tolist() for c in self.centers],
            "board_depth": self.board_depth,
            "light_indices": self.light_indices,
            "distance": self.distance,
            "size": self.size,
        }
        with result_directory(directory, overwrite) as out:
            paths: dict[str, Path] = {}
            for p, (stack, lab) in enumerate(zip(self.images, self.labels, strict=True)):
                for i, image in enumerate(stack):
                    export.write_png(out.file(f"placement_{p}/image_{i:02d}.png"), image)
                export.write_png8(out.file(f"placement_{p}/mask.png"), ((lab > 0) * 255).astype(np.uint8))
                paths[f"placement_{p}"] = out.path / f"placement_{p}"
            paths.update(
                camera=out.file("camera.json"), rig_true=out.file("rig_true.json"), scene=out.file("scene.json")
            )
            save_camera(paths["camera"], self.rig)
            self.rig.save(paths["rig_true"])
            write_text(paths["scene"], json.dumps(meta, indent=2) + "\n")
        return paths


@dataclass
class BoardScene:
    """A synthetic board for intensity calibration."""

    #: (k, H, W) images.
    images: np.ndarray = field(repr=False)
    #: The board plane (normal, offset), ``normal . X = offset``.
    plane: tuple[list[float], float]
    #: The true rig.
    rig: Rig
    #: (H, W) board albedo.
    albedo: np.ndarray = field(repr=False)

    def save(self, directory: str | os.PathLike[str], overwrite: bool = False) -> dict[str, Path]:
        """Write ``image_XX.png`` and ``board.json`` (the plane) into ``directory``, and the manifest.

        The manifest is ``nplps-manifest.json``. ``directory`` must be empty unless
        ``overwrite=True`` (see :meth:`nplps.Reconstruction.save`).
        """
        with result_directory(directory, overwrite) as out:
            for i, image in enumerate(self.images):
                export.write_png(out.file(f"image_{i:02d}.png"), image)
            normal, offset = self.plane
            plane = out.file("board.json")
            write_text(plane, json.dumps({"normal": normal, "offset": offset}) + "\n")
        return {"board": out.path, "plane": plane}


def _light_indices(lights: int | Sequence[int]) -> list[int]:
    if isinstance(lights, (int, np.integer)):
        if int(lights) == 27:
            return list(range(27))
        if int(lights) == 8:
            return list(LIGHTS_8)
        raise InputError(f"lights must be 8, 27 or a list of indices into the 27 standard lights, got {lights}")
    idx = [int(i) for i in lights]
    if not idx or any(i < 0 or i >= 27 for i in idx) or len(set(idx)) != len(idx):
        raise InputError("light indices must be distinct numbers 0..26")
    return idx


def standard_rig(
    camera: str = "orthographic",
    n: int = 200,
    size: float = 100.0,
    distance: float = 200.0,
    lights: int | Sequence[int] = 27,
    directional: bool = False,
    led: bool = False,
) -> Rig:
    """Return the rig of :func:`nplps.make_scene`, restricted to ``lights``.

    The rig has ``n`` x ``n`` pixels, object ``size`` at ``distance``; ``lights`` is 8, 27 or
    indices into the 27 standard lights.
    """
    if camera not in ("orthographic", "pinhole"):
        raise InputError(f"camera must be 'orthographic' or 'pinhole', got {camera!r}")
    d = _core.synth_scene("saddle", 2, float(size), float(distance), 0, pinhole=False, led=led, directional=directional)
    # The camera must match an n x n image: rebuild it as make_scene does for n pixels.
    if camera == "pinhole":
        f = n * distance / size
        c = (n - 1) / 2.0
        K = [[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]]
        cam: dict[str, Any] = {"model": "pinhole", "K": K, "distortion": [0.0] * 5}
    else:
        cam = {"model": "orthographic", "pixel_size": [size / n, size / n], "origin": [-size / 2, -size / 2]}
    idx = _light_indices(lights)
    return Rig(cam, Rig._from_native(d["rig"].subset(idx)).lights)


def default_placements(
    camera: str, radius: float, board_depth: float, spheres: int = 1, seed: int | None = None
) -> list[np.ndarray]:
    """Return two placements for the standard 100-wide view at depth 200 (scaled with the board depth).

    One sphere each (upper left, then lower right), or two spheres each (one diagonal, then the
    other) with ``spheres=2``. With a ``seed`` every centre moves by up to 1 (scene unit, about 2
    pixels) in x and y, so that the digitisation of the spheres' outlines differs from seed to seed
    as it does from photograph to photograph.
    """
    z = board_depth - radius
    s = board_depth / 200.0
    # Keep the spheres inside the view: a pinhole camera sees less at the spheres' depth.
    if camera == "pinhole":
        p1, p2 = (-18.37 * s, -15.21 * s), (17.73 * s, 14.63 * s)
        q1, q2 = (-17.91 * s, 14.87 * s), (18.19 * s, -15.43 * s)
    else:
        p1, p2 = (-22.37 * s, -17.83 * s), (21.61 * s, 18.29 * s)
        q1, q2 = (-21.93 * s, 18.11 * s), (22.17 * s, -17.57 * s)
    if spheres == 1:
        out = [np.array([[*p1, z]]), np.array([[*p2, z]])]
    elif spheres == 2:
        out = [np.array([[*p1, z], [*p2, z]]), np.array([[*q1, z], [*q2, z]])]
    else:
        raise InputError("spheres must be 1 or 2 per placement for the default placements")
    if seed is not None:
        rng = np.random.default_rng([int(seed), 7919])
        for c in out:
            c[:, :2] += rng.uniform(-1.0, 1.0, (c.shape[0], 2)) * s
    return out


def _quantize(
    radiance: list[np.ndarray], scale: float, noise: float, bits: int, rng: np.random.Generator
) -> list[np.ndarray]:
    out = []
    for r in radiance:
        x = r * scale
        if noise > 0:
            x = x + rng.normal(0.0, noise, x.shape)
        x = np.clip(x, 0.0, 1.0)
        if bits == 0:
            out.append(x)
            continue
        top = (1 << bits) - 1
        dtype = np.uint8 if bits <= 8 else np.uint16
        out.append(np.rint(x * top).astype(dtype))
    return out


def make_sphere_scene(
    camera: str = "orthographic",
    n: int = 200,
    lights: int | Sequence[int] = 27,
    *,
    directional: bool = False,
    led: bool = False,
    radius: float = 20.0,
    placements: Sequence[Any] | None = None,
    spheres: int = 1,
    noise: float = 0.01,
    seed: int = 0,
    bits: int = 8,
    supersample: int = 4,
    size: float = 100.0,
    distance: float = 200.0,
    highlight_px: float = 1.5,
    specular: float = 20.0,
    exposure: float = 0.5,
    background: float = 0.05,
) -> SphereScene:
    """Render a synthetic sphere-calibration scene for the rig of :func:`nplps.make_scene`.

    Shiny spheres (Lambertian albedo 1 plus a Phong lobe of strength ``specular``) rest on a dark
    board (albedo ``background``) at the working distance; every placement is rendered under
    every light with ``supersample``² rays per pixel. The exposure maps the 99.5th percentile of
    the sphere pixels (the diffuse part) to ``exposure``, so the highlights saturate; Gaussian
    noise of ``noise`` times the full scale is added and the images are quantised to ``bits``
    (0: float images in [0, 1]).

    Parameters
    ----------
    camera : str, optional
        "orthographic" or "pinhole" (as in :func:`nplps.make_scene`).
    n : int, optional
        Image size n x n.
    lights : int | Sequence[int], optional
        27 (the standard lights), 8 (:data:`LIGHTS_8`) or indices into the 27.
    directional : bool, optional
        Every third standard light is a distant light (as in make_scene).
    led : bool, optional
        Anisotropic LEDs with unequal intensities (as in make_scene).
    radius : float, optional
        Sphere radius (scene units); the image radius is about ``radius * n / size``
        pixels (orthographic), a little more for the pinhole camera.
    placements : Sequence[Any] | None, optional
        Per placement an (S, 3) array of sphere centres; default
        :func:`default_placements` (two placements of ``spheres`` spheres, moved by up to 1
        in x and y with the seed).
    highlight_px : float, optional
        Standard deviation of the highlight lobe in pixels (sets the Phong
        exponent from the sphere's image radius).
    """
    if not (np.isfinite(noise) and noise >= 0):
        raise InputError(f"noise must be >= 0 (a fraction of the full scale), got {noise}")
    if not (0 <= bits <= 16):
        raise InputError(f"bits must be 0 (float) or 1..16, got {bits}")
    rig = standard_rig(camera, n, size, distance, lights, directional, led)
    idx = _light_indices(lights)
    board = distance
    centers = (
        default_placements(camera, radius, board, spheres, seed)
        if placements is None
        else [np.asarray(c, dtype=float).reshape(-1, 3) for c in placements]
    )
    r_px = radius * n / size
    if camera == "pinhole":
        r_px *= distance / float(np.mean([c[:, 2].mean() for c in centers]))
    exponent = (r_px / (2.0 * highlight_px)) ** 2
    options: _core_types.SphereRenderOptions = {
        "diffuse": 1.0,
        "specular": float(specular),
        "exponent": float(exponent),
        "background": float(background),
        "supersample": int(supersample),
    }
    radiance, labels = [], []
    for c in centers:
        d = _core.synth_spheres(
            rig._native,
            (n, n),
            c.tolist(),
            float(radius),
            ([0.0, 0.0, -1.0], -board),
            options,
        )
        radiance.append(d["images"])
        labels.append(d["labels"])
    inside = np.concatenate([r[:, lab > 0].ravel() for r, lab in zip(radiance, labels, strict=True)])
    if inside.size == 0:
        raise InputError("no sphere is visible in the images: check the placements and the radius")
    scale = exposure / float(np.quantile(inside, 0.97))
    rng = np.random.default_rng(seed)
    images = _quantize(radiance, scale, float(noise), int(bits), rng)
    return SphereScene(images, labels, centers, float(radius), rig, idx, float(board), float(distance), float(size))


def make_board_scene(
    rig: Rig,
    n: int = 200,
    plane: Any = None,
    *,
    albedo: float | np.ndarray = 0.8,
    noise: float = 0.01,
    seed: int = 0,
    bits: int = 8,
    exposure: float = 0.9,
    distance: float = 200.0,
) -> BoardScene:
    """Render k images (one per light of ``rig``) of a flat Lambertian board for intensity calibration.

    The board is the plane ``plane`` (default: facing the camera at ``distance``), albedo a number
    or (n, n) array, the brightest value mapped to ``exposure`` of the full scale, Gaussian noise of
    ``noise`` times the full scale, quantised to ``bits`` (0: float).
    """
    if not (np.isfinite(noise) and noise >= 0):
        raise InputError(f"noise must be >= 0 (a fraction of the full scale), got {noise}")
    normal, offset = _plane(distance if plane is None else plane)
    a = np.broadcast_to(np.asarray(albedo, dtype=np.float64), (n, n)).copy()
    radiance = _core.synth_board(rig._native, normal, offset, a)
    scale = exposure / float(radiance.max())
    rng = np.random.default_rng(seed)
    images = _quantize([radiance], scale, float(noise), int(bits), rng)[0]
    return BoardScene(images, (normal, offset), rig, a)
