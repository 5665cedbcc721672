"""The :class:`Capture` record and :func:`prepare`, the usual pre-processing of a capture."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from .. import preprocess
from ..errors import InputError
from .files import _check_indices, _gray64, _read_float, _read_stack

if TYPE_CHECKING:
    from ..rig import Rig


@dataclass
class Capture:
    """One photometric-stereo capture, in nplps's conventions (see :mod:`nplps.captures`).

    Attributes:
        images: the ``k`` images, either as file names (``list[Path]``, read them with
            :meth:`load` or :func:`nplps.io.load_images`) or as a float32 stack
            ``(k, H, W)`` / ``(k, H, W, 3)`` of linear intensities.
        mask: ``(H, W)`` bool, or None (no mask in the dataset).
        K: ``(3, 3)`` float64 pinhole matrix, 0-based pixel centres, or None (unknown).
        distortion: ``(5,)`` OpenCV distortion ``(k1, k2, p1, p2, k3)`` or None (none given).
        positions: ``(k, 3)`` point-light positions in mm (camera frame), or None.
        directions: ``(k, 3)`` unit vectors, or None. For point lights the LED principal axes
            (pointing from the LED towards the scene); for ``directional`` captures the
            directions from the surface towards each light.
        intensities: ``(k,)`` or ``(k, 3)`` (per RGB channel) light intensities, or None. Near
            lights: ``Phi`` of the toolbox model (image units x mm^2); directional lights:
            the relative radiance of each light.
        mu: ``(k,)`` anisotropy exponents of the LED model ``cos(angle to axis)^mu``, or None.
        directional: True for distant (directional) lights, False for point lights.
        normals_gt: ``(H, W, 3)`` ground-truth unit normals (camera frame, ``n_z < 0``; zero
            outside the object), or None.
        ambient: the image with every light off (a file name or an array like one image of
            ``images``), or None.
        name: a short name of the capture.
        notes: free text: provenance, caveats, what the loader did.
        rig_path: the ``rig.json`` of a :func:`load_folder` capture (read it with
            ``nplps.Rig.load``), else None.
        files: the image files the images came from (also when ``images`` is an array).
    """

    images: list[Path] | np.ndarray
    mask: np.ndarray | None = None
    K: np.ndarray | None = None
    distortion: np.ndarray | None = None
    positions: np.ndarray | None = None
    directions: np.ndarray | None = None
    intensities: np.ndarray | None = None
    mu: np.ndarray | None = None
    directional: bool = False
    normals_gt: np.ndarray | None = None
    ambient: Path | np.ndarray | None = None
    name: str = ""
    notes: str = ""
    rig_path: Path | None = None
    files: list[Path] = field(default_factory=list)
    #: Pixel footprint of the orthographic rig used when K is unknown (grows with binning).
    pixel_size: float = 1.0

    @property
    def num_images(self) -> int:
        """The number of images ``k``."""
        return len(self.images)

    @property
    def loaded(self) -> bool:
        """True when ``images`` is an array rather than a list of file names."""
        return isinstance(self.images, np.ndarray)

    def load(self, gray: bool = False) -> Capture:
        """Return a copy whose ``images`` (and ``ambient``) are float32 arrays.

        Files are read with :func:`nplps.io.read_image` (16-bit PNG keeps 16 bits) and scaled to
        ``[0, 1]`` by :func:`nplps.io.to_float`; no other conversion is applied (the files must
        already be linear). ``gray=True`` averages the colour channels, giving ``(k, H, W)``.
        An already loaded capture is returned as a copy (converted to grey if asked).
        """
        images = self.images
        if not isinstance(images, np.ndarray):
            images = _read_stack(images, gray=gray)
        elif gray and images.ndim == 4:
            # Image by image: the float64 sums never take a whole stack of memory.
            colour = images
            images = np.empty(colour.shape[:3], dtype=np.float32)
            for i, image in enumerate(colour):
                images[i] = _gray64(image)
        ambient = self.ambient
        if ambient is not None and not isinstance(ambient, np.ndarray):
            ambient = _read_float(Path(ambient))
        if ambient is not None and gray and ambient.ndim == 3:
            ambient = _gray64(ambient)
        return dataclasses.replace(self, images=images, ambient=ambient)

    def rig(self) -> "Rig":
        """The capture's :class:`~nplps.Rig`: its rig file, or a pinhole camera (orthographic with
        unit pixels when K is unknown) with its point lights (LED model) or directional lights."""
        from ..rig import Rig

        if self.rig_path is not None:
            return Rig.load(self.rig_path)
        if self.directional:
            if self.K is None:
                return Rig.orthographic(self.pixel_size, directions=self.directions, intensities=self.intensities)
            return Rig.pinhole(self.K, distortion=self.distortion, directions=self.directions,
                               intensities=self.intensities)
        if self.K is None or self.positions is None:
            raise InputError(f"capture {self.name!r} has no camera intrinsics or light positions to build a rig from")
        return Rig.pinhole(self.K, lights=self.positions, distortion=self.distortion, intensities=self.intensities,
                           axes=self.directions, mu=self.mu)

    def select(self, indices: Sequence[int]) -> Capture:
        """Return a copy restricted to the images / lights ``indices`` (0-based, in order)."""
        idx = _check_indices(indices, self.num_images, "select")

        def pick(arr: Any) -> Any:
            return None if arr is None else np.asarray(arr)[idx].copy()

        if isinstance(self.images, np.ndarray):
            images: list[Path] | np.ndarray = self.images[idx].copy()
        else:
            images = [self.images[i] for i in idx]
        files = [self.files[i] for i in idx] if len(self.files) == self.num_images else []
        return dataclasses.replace(
            self,
            images=images,
            positions=pick(self.positions),
            directions=pick(self.directions),
            intensities=pick(self.intensities),
            mu=pick(self.mu),
            files=files,
        )


def prepare(
    capture: Capture,
    *,
    bin_factor: int = 1,
    ambient: bool = True,
    vignetting: Literal["cos4"] | np.ndarray | None = "cos4",
    gray: bool = False,
    overwrite: bool = False,
) -> Capture:
    """The usual pre-processing of a near-light capture, as the near_ps authors do it.

    Loads the images if needed, subtracts the ambient image (clipping at 0), divides by the
    vignetting map (``"cos4"`` from K, a flat-field map, or None), and bins by ``bin_factor``
    (images averaged, mask kept where its whole block is, K adjusted: fx' = fx/s,
    cx' = (cx + 1/2)/s - 1/2). Returns a loaded capture on the binned grid; ``capture.rig()``
    then gives the matching rig.

    Images read from files are corrected in place. A float32 stack in ``capture.images`` is
    copied once by the first correction, unless ``overwrite=True`` hands it over to be
    corrected in place (no copy; the caller's array then holds the corrected values).
    """
    c = capture.load(gray=gray)
    images = np.asarray(c.images, dtype=np.float32)
    # The first step that changes the caller's array makes the one copy (unless overwrite); the
    # others, and every step on images loaded here, work in place.
    given = capture.images
    owned = overwrite or not (isinstance(given, np.ndarray) and np.may_share_memory(images, given))
    if ambient and c.ambient is not None:
        amb = np.asarray(c.ambient, dtype=np.float32)
        images = preprocess.subtract_ambient(images, amb, out=images if owned else None)
        owned = True
    if isinstance(vignetting, str):
        if vignetting != "cos4":
            raise InputError(f"vignetting must be 'cos4', a map or None, got {vignetting!r}")
        if c.K is not None:
            vmap = preprocess.vignetting_cos4(images.shape[1:3], c.K)
            images = preprocess.compensate_vignetting(images, vmap, out=images if owned else None)
            owned = True
    elif vignetting is not None:
        vmap = np.asarray(vignetting)
        images = preprocess.compensate_vignetting(images, vmap, out=images if owned else None)
        owned = True
    K, mask, normals = c.K, c.mask, c.normals_gt
    if bin_factor != 1:
        images = preprocess.bin_images(images, bin_factor)
        K = None if K is None else preprocess.bin_intrinsics(K, bin_factor)
        mask = None if mask is None else preprocess.bin_mask(mask, bin_factor)
        normals = None
    return dataclasses.replace(
        c,
        images=np.ascontiguousarray(images, dtype=np.float32),
        ambient=None,
        K=K,
        mask=mask,
        normals_gt=normals,
        pixel_size=c.pixel_size * bin_factor,
    )
