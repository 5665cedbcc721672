"""Synthetic scenes with ground truth (rendered by the same image model as the solver).

Scenes are built by the Rust core (``saddle``, ``sphere``, ``cube``, ``bumps``): an object of
lateral size ``size`` at working distance ``distance`` under an orthographic camera, lit by 27
point lights in three layers 1.5, 2.25 and 3 object sizes in front of it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import _core, export
from ._outdir import result_directory
from .api import _finite_number, _positive, _short, _whole, render
from .errors import InputError
from .rig import Rig

SCENES = ("saddle", "sphere", "cube", "bumps")


@dataclass
class Scene:
    """A synthetic scene: true surface, mask, albedo, rig and rendered images."""

    name: str
    #: True vertex depths (H+1, W+1).
    depth: np.ndarray
    #: Mask (H, W).
    mask: np.ndarray
    #: True albedo (H, W).
    albedo: np.ndarray
    rig: Rig
    #: Lateral object size (scene units).
    size: float
    #: Images (k, H, W) rendered by the model (with noise if requested).
    images: np.ndarray = field(repr=False)

    @property
    def normals(self) -> np.ndarray:
        """True mesh normals (H, W, 3), NaN outside the mask."""
        n = _core.mesh_normals(self.depth, self.rig.camera)
        n[~self.mask] = np.nan
        return n

    @property
    def mean_depth(self) -> float:
        """Mean true depth of the vertices the mask uses: arithmetic (orthographic camera) or
        geometric (pinhole camera) — the true gauge."""
        h, w = self.mask.shape
        used = np.zeros((h + 1, w + 1), dtype=bool)
        for dr in (0, 1):
            for dc in (0, 1):
                used[dr : dr + h, dc : dc + w] |= self.mask
        z = self.depth[used]
        return float(np.exp(np.log(z).mean())) if self.rig.is_pinhole else float(z.mean())

    def save(self, directory: str | os.PathLike[str], overwrite: bool = False) -> dict[str, Path]:
        """Writes ``image_XX.png`` (16-bit), ``rig.json``, ``mask.png`` and ground truth
        (``depth_gt.npy``, ``normals_gt.npy``, ``albedo_gt.npy``) into ``directory``, and the
        manifest ``nplps-manifest.json``.

        Images are scaled so that their maximum is 65535; the scale is absorbed by the albedo.
        ``directory`` must be empty unless ``overwrite=True``, as for
        :meth:`nplps.Reconstruction.save` (an earlier scene's images are then removed).
        """
        with result_directory(directory, overwrite) as out:
            scale = 65535.0 / max(float(self.images.max()), 1e-300)
            paths: dict[str, Path] = {}
            for i, image in enumerate(self.images):
                p = paths[f"image_{i:02d}"] = out.file(f"image_{i:02d}.png")
                export.write_png16(p, np.clip(np.rint(image * scale), 0, 65535).astype(np.uint16))
            paths.update(rig=out.file("rig.json"), mask=out.file("mask.png"), depth_gt=out.file("depth_gt.npy"))
            self.rig.save(paths["rig"])
            export.write_png8(paths["mask"], (self.mask * 255).astype(np.uint8))
            export.save_depth_npy(paths["depth_gt"], self.depth)
            export.save_npy(out.file("normals_gt.npy"), self.normals)
            export.save_npy(out.file("albedo_gt.npy"), self.albedo * scale / 65535.0)
        return paths


def make_scene(
    name: str,
    n: int = 128,
    size: float = 100.0,
    distance: float = 200.0,
    seed: int = 0,
    noise: float = 0.0,
    camera: str = "orthographic",
    led: bool = False,
    rgb: bool = False,
    directional: bool = False,
) -> Scene:
    """Builds and renders a synthetic scene.

    Args:
        name: one of ``saddle``, ``sphere`` (a sphere cap in a disc mask), ``cube`` (two faces
            of a turned cube, the sharp edge on a pixel line) or ``bumps`` (random smooth bumps).
        n: image size n x n pixels.
        size: lateral object size; distance: working distance (same unit).
        seed: seed of the random bumps and of the noise (a whole number from 0 to 2**64 - 1).
        noise: standard deviation of Gaussian image noise as a fraction of the maximum intensity,
            finite and >= 0 (images are clipped at 0 afterwards).
        camera: "orthographic" or "pinhole" (a camera at the origin whose view spans the object
            at the working distance).
        led: anisotropic LEDs aimed at the object (mu 0.5 to 2) with unequal RGB intensities.
        rgb: colour albedo and (k, H, W, 3) images.
        directional: every third light is a distant (directional) light.
    """
    if not (isinstance(name, str) and name in SCENES):
        raise InputError(f"name must be one of the scenes {', '.join(SCENES)}, got {_short(name)}")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 2:
        raise InputError(f"n (the image size in pixels) must be a whole number of at least 2, got {_short(n)}")
    if not (isinstance(camera, str) and camera in ("orthographic", "pinhole")):
        raise InputError(f"camera must be 'orthographic' or 'pinhole', got {_short(camera)}")
    size = _positive(size, "size")
    distance = _positive(distance, "distance")
    noise = _finite_number(noise, "noise (a fraction of the maximum intensity)")
    seed = _whole(seed, "seed", 0)
    if seed >= 2**64:
        raise InputError(f"seed must be less than 2**64, got {_short(seed)}")
    d = _core.synth_scene(
        name, int(n), size, distance, seed,
        pinhole=camera == "pinhole", led=led, rgb=rgb, directional=directional,
    )
    lights = d["lights"]
    rig = Rig(
        camera=dict(d["camera"]),
        lights=np.array(lights["vectors"]),
        intensities=np.array(lights["intensities"]),
        directions=np.array(lights["axes"]),
        mu=np.array(lights["mu"]),
        directional=np.array(lights["directional"]),
    )
    images = render(d["depth"], rig, d["albedo"], d["mask"])
    if noise > 0:
        rng = np.random.default_rng(seed)
        images = np.clip(images + rng.normal(0.0, noise * images.max(), images.shape), 0.0, None)
    return Scene(name, d["depth"], d["mask"], d["albedo"], rig, float(d["size"]), images)
