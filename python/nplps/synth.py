"""Synthetic scenes with ground truth (rendered by the same image model as the solver).

Scenes are built by the Rust core (``saddle``, ``sphere``, ``cube``, ``bumps``, ``block``): an object of
lateral size ``size`` at working distance ``distance`` under an orthographic camera, lit by 27
point lights in three layers 1.5, 2.25 and 3 object sizes in front of it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import _core, export
from ._checks import _finite_number, _flag, _positive, _short, _whole
from ._outdir import result_directory
from .api import _lobe, render
from .errors import InputError
from .rig import Rig
from .types import Camera, SceneName

__all__ = ["SCENES", "Scene", "make_scene"]

#: The scenes :func:`make_scene` builds.
SCENES: tuple[SceneName, ...] = ("saddle", "sphere", "cube", "bumps", "block")


@dataclass
class Scene:
    """A synthetic scene with ground truth, as :func:`make_scene` returns it.

    Attributes
    ----------
    name : str
        The scene's name (one of :data:`SCENES`, or the caller's).
    depth : numpy.ndarray
        True vertex depths (H+1, W+1).
    mask : numpy.ndarray
        Mask (H, W).
    albedo : numpy.ndarray
        True albedo (H, W), or (H, W, 3) for a colour scene.
    rig : Rig
        The camera and the lights the images were rendered with.
    size : float
        Lateral object size (scene units).
    images : numpy.ndarray
        Images (k, H, W[, 3]) rendered by the model (with noise if requested).
    """

    name: str
    depth: np.ndarray
    mask: np.ndarray
    albedo: np.ndarray
    rig: Rig
    size: float
    images: np.ndarray = field(repr=False)

    @property
    def normals(self) -> np.ndarray:
        """True normals (H, W, 3): the facet normals of the true mesh, NaN outside the mask.

        These are the normals the images were rendered with.
        """
        n = _core.mesh_normals(self.depth, self.rig.camera)
        n[~self.mask] = np.nan
        return n

    @property
    def mean_depth(self) -> float:
        """The true gauge: the mean true depth of the vertices the mask uses.

        Arithmetic for an orthographic camera, geometric for a pinhole camera.
        """
        h, w = self.mask.shape
        used = np.zeros((h + 1, w + 1), dtype=bool)
        for dr in (0, 1):
            for dc in (0, 1):
                used[dr : dr + h, dc : dc + w] |= self.mask
        z = self.depth[used]
        return float(np.exp(np.log(z).mean())) if self.rig.is_pinhole else float(z.mean())

    def save(self, directory: str | os.PathLike[str], *, overwrite: bool = False) -> dict[str, Path]:
        """Write the scene as files that ``nplps reconstruct`` reads.

        Writes ``image_XX.png`` (16-bit), ``rig.json``, ``mask.png`` and ground truth
        (``depth_gt.npy``, ``normals_gt.npy``, ``albedo_gt.npy``), and the manifest
        ``nplps-manifest.json``. Images are scaled so that their maximum is 65535; the scale is
        absorbed by the albedo.

        Parameters
        ----------
        directory : str or path-like
            Created if needed; it must be empty unless `overwrite` is True.
        overwrite : bool, default False
            Replace the files of an earlier scene there (as for
            :meth:`nplps.Reconstruction.save`; an earlier scene's images are removed).

        Returns
        -------
        dict of str to pathlib.Path
            The paths written (images, rig, mask, depth_gt), by kind.

        Raises
        ------
        OutputExistsError
            `directory` is not empty and `overwrite` is False.
        """
        with result_directory(directory, overwrite) as out:
            scale = 65535.0 / max(float(self.images.max()), 1e-300)
            paths: dict[str, Path] = {}
            for i, image in enumerate(self.images):
                p = paths[f"image_{i:02d}"] = out.file(f"image_{i:02d}.png")
                export.write_png16(p, np.clip(np.rint(image * scale), 0, 65535).astype(np.uint16))
            paths.update(rig=out.file("rig.json"), mask=out.file("mask.png"), depth_gt=out.file("depth_gt.npy"))
            self.rig.with_grid(self.images.shape[2], self.images.shape[1]).save(paths["rig"])
            export.write_png8(paths["mask"], (self.mask * 255).astype(np.uint8))
            export.save_depth_npy(paths["depth_gt"], self.depth)
            export.save_npy(out.file("normals_gt.npy"), self.normals)
            export.save_npy(out.file("albedo_gt.npy"), self.albedo * scale / 65535.0)
        return paths


def make_scene(
    name: SceneName,
    *,
    n: int = 128,
    size: float = 100.0,
    distance: float = 200.0,
    seed: int = 0,
    noise: float = 0.0,
    camera: Camera = "orthographic",
    led: bool = False,
    rgb: bool = False,
    directional: bool = False,
    specular: float = 0.0,
    roughness: float = 0.3,
    eta: float = 1.5,
    shadows: bool = False,
) -> Scene:
    """Build and render a synthetic scene with ground truth.

    Parameters
    ----------
    name : {"saddle", "sphere", "cube", "bumps", "block"}
        ``"saddle"``, ``"sphere"`` (a sphere cap in a disc mask), ``"cube"`` (two faces of a
        turned cube, the sharp edge on a pixel line), ``"bumps"`` (random smooth bumps) or
        ``"block"`` (a square block, 0.4 `size` wide and 0.2 `size` tall with one-pixel walls,
        on a plane: the one scene whose lights cast shadows, see `shadows`).
    n : int, default 128
        Image size, n x n pixels.
    size : float, default 100.0
        Lateral object size.
    distance : float, default 200.0
        Working distance (same unit as `size`).
    seed : int, default 0
        Seed of the random bumps and of the noise (a whole number from 0 to 2**64 - 1).
    noise : float, default 0.0
        Standard deviation of Gaussian image noise as a fraction of the maximum intensity, finite
        and >= 0 (images are clipped at 0 afterwards).
    camera : {"orthographic", "pinhole"}, default "orthographic"
        A pinhole camera sits at the origin, its view spanning the object at the working
        distance.
    led : bool, default False
        Anisotropic LEDs aimed at the object (mu 0.5 to 2) with unequal RGB intensities.
    rgb : bool, default False
        Colour albedo and (k, H, W, 3) images.
    directional : bool, default False
        Every third light is a distant (directional) light.
    specular : float, default 0.0
        The specular albedo as a fraction of the diffuse albedo (of its grey mean, per pixel),
        finite and >= 0. 0 renders the Lambertian model; above 0 the glossy model of
        :func:`nplps.render` with `roughness` and `eta`.
    roughness : float, default 0.3
        The GGX roughness of the specular lobe, in (0, 1] (used when `specular` > 0).
    eta : float, default 1.5
        The relative index of refraction, >= 1 (used when `specular` > 0).
    shadows : bool, default False
        Render cast shadows (0 where the surface hides a light; see :func:`nplps.cast_shadows`).

    Returns
    -------
    Scene
        The true surface, mask, albedo, rig and the rendered images.

    Raises
    ------
    InputError
        An argument is invalid.
    MemoryLimitError
        The scene would not fit in memory.

    Notes
    -----
    Scenes are built by the Rust core: an object of lateral size `size` at working distance
    `distance`, lit by 27 point lights in three layers 1.5, 2.25 and 3 object sizes in front of
    it.

    Examples
    --------
    >>> import nplps
    >>> scene = nplps.make_scene("bumps", n=32, noise=0.01, seed=1)
    >>> scene.images.shape, scene.depth.shape
    ((27, 32, 32), (33, 33))
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
    specular = _finite_number(specular, "specular (a fraction of the albedo)")
    roughness, eta = _lobe(roughness, eta)
    shadows = _flag(shadows, "shadows")
    d = _core.synth_scene(
        name,
        int(n),
        size,
        distance,
        seed,
        pinhole=camera == "pinhole",
        led=led,
        rgb=rgb,
        directional=directional,
    )
    rig = Rig._from_native(d["rig"])
    albedo = d["albedo"]
    rho_s = specular * (albedo.mean(axis=2) if albedo.ndim == 3 else albedo) if specular > 0 else None
    images = render(
        d["depth"], rig, albedo, mask=d["mask"], specular=rho_s, roughness=roughness, eta=eta, shadows=shadows
    )
    if noise > 0:
        rng = np.random.default_rng(seed)
        images = np.clip(images + rng.normal(0.0, noise * images.max(), images.shape), 0.0, None)
    return Scene(name, d["depth"], d["mask"], d["albedo"], rig, float(d["size"]), images)
