"""The :class:`Capture` record and :func:`prepare`, the usual pre-processing of a capture."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from .. import pipeline
from ..errors import InputError
from .files import _check_indices, _read_float, _read_stack

if TYPE_CHECKING:
    from ..rig import Rig


@dataclass
class Capture:
    """One photometric-stereo capture, in nplps's conventions (see :mod:`nplps.captures`).

    Attributes
    ----------
    images : list[Path] | np.ndarray
        The ``k`` images, either as file names (``list[Path]``, read them with
        :meth:`load` or :func:`nplps.io.load_images`) or as a float32 stack
        ``(k, H, W)`` / ``(k, H, W, 3)`` of linear intensities.
    mask : np.ndarray | None
        ``(H, W)`` bool, or None (no mask in the dataset).
    K : np.ndarray | None
        ``(3, 3)`` float64 pinhole matrix, 0-based pixel centres, or None (unknown).
    distortion : np.ndarray | None
        ``(5,)`` OpenCV distortion ``(k1, k2, p1, p2, k3)`` or None (none given).
    positions : np.ndarray | None
        ``(k, 3)`` point-light positions in mm (camera frame), or None.
    directions : np.ndarray | None
        ``(k, 3)`` unit vectors, or None. For point lights the LED principal axes
        (pointing from the LED towards the scene); for ``directional`` captures the
        directions from the surface towards each light.
    intensities : np.ndarray | None
        ``(k,)`` or ``(k, 3)`` (per RGB channel) light intensities, or None. Near
        lights: ``Phi`` of the toolbox model (image units x mm^2); directional lights:
        the relative radiance of each light.
    mu : np.ndarray | None
        ``(k,)`` anisotropy exponents of the LED model ``cos(angle to axis)^mu``, or None.
    directional : bool
        True for distant (directional) lights, False for point lights.
    normals_gt : np.ndarray | None
        ``(H, W, 3)`` ground-truth unit normals (camera frame, ``n_z < 0``; zero
        outside the object), or None.
    ambient : Path | np.ndarray | None
        The image with every light off (a file name or an array like one image of
        ``images``), or None.
    name : str
        A short name of the capture.
    notes : str
        Free text: provenance, caveats, what the loader did.
    rig_path : Path | None
        The ``rig.json`` of a :func:`load_folder` capture (read it with
        ``nplps.Rig.load``), else None.
    files : list[Path]
        The image files the images came from (also when ``images`` is an array).
    pixel_size : float
        The pixel footprint of the orthographic rig used when K is unknown (grows
        with binning).
    bin_factor : int
        The binning :func:`prepare` applied since the files, for the grid of the rig
        file (``rig_path``).
    levels : int | None
        The top integer value of the image files (255, 65535) while ``images`` holds
        their values as read (scaled to ``[0, 1]``), else None (floating-point files, or
        values a step has changed before :func:`prepare` saw them).
    preprocessed : tuple[str, ...]
        The pre-processing steps that changed the values of ``images``, in order
        (names of :data:`nplps.pipeline.STEPS`, and ``"pad"``): set by the loaders'
        ``srgb`` / ``bin_factor`` / ``grid_shape`` and by :func:`prepare`.
    valid : np.ndarray | None
        ``(k, H, W)`` bool, False where an observation was saturated in the files (judged
        by :func:`prepare` on the values as read), or None.
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
    pixel_size: float = 1.0
    bin_factor: int = 1
    levels: int | None = None
    preprocessed: tuple[str, ...] = ()
    valid: np.ndarray | None = None

    @property
    def num_images(self) -> int:
        """The number of images ``k``."""
        return len(self.images)

    @property
    def loaded(self) -> bool:
        """True when ``images`` is an array rather than a list of file names."""
        return isinstance(self.images, np.ndarray)

    @property
    def dark(self) -> float:
        """The default shadow threshold of this capture's images, as the command line sets it.

        One level above black (``1 / levels``) while the values are as read from integer files, 0
        once a pre-processing step has changed them (see :func:`nplps.pipeline.thresholds`).
        """
        return pipeline.thresholds(self.levels, preprocessed=bool(self.preprocessed))[0]

    def options(self) -> dict[str, Any]:
        """Return keyword arguments for :func:`nplps.reconstruct` and :func:`nplps.reconstruct_parallel`.

        They carry what the capture knows about its images: ``mask``, ``dark`` (:attr:`dark`) and
        ``valid`` (the saturation flags). Use as
        ``nplps.reconstruct(cap.images, cap.rig(), depth=..., **cap.options())``.
        """
        return {"mask": self.mask, "dark": self.dark, "valid": self.valid}

    def load(self, *, color: bool | None = None) -> Capture:
        """Return a copy whose ``images`` (and ``ambient``) are float32 arrays.

        Files are read with :func:`nplps.io.load_stack` (16-bit PNG keeps 16 bits; integers
        scaled to ``[0, 1]``, ``levels`` recorded); no other conversion is applied (the files
        must already be linear). ``color=False`` averages the colour channels
        (:func:`nplps.pipeline.to_gray`), giving ``(k, H, W)``; ``color=True`` requires RGB;
        None keeps what the files are. An already loaded capture is returned as a copy
        (converted to grey if asked).
        """
        images = self.images
        levels = self.levels
        if not isinstance(images, np.ndarray):
            images, levels = _read_stack(images, color)
        else:
            images = pipeline.select_color(images, color)[0]
        ambient = self.ambient
        if ambient is not None and not isinstance(ambient, np.ndarray):
            ambient = _read_float(Path(ambient))
        if ambient is not None and color is False and ambient.ndim == 3:
            ambient = pipeline.to_gray(ambient, stack=False)
        return dataclasses.replace(self, images=images, ambient=ambient, levels=levels)

    def rig(self) -> Rig:
        """Return the capture's :class:`~nplps.Rig`.

        That is its rig file, or a pinhole camera (orthographic with unit pixels when K is unknown)
        with its point lights (LED model) or directional lights.
        """
        from ..rig import Rig

        if self.rig_path is not None:
            rig = Rig.load(self.rig_path)
            return rig if self.bin_factor == 1 else rig.binned(self.bin_factor)
        if self.directional:
            if self.K is None:
                return Rig.orthographic(self.pixel_size, directions=self.directions, intensities=self.intensities)
            return Rig.pinhole(
                self.K, distortion=self.distortion, directions=self.directions, intensities=self.intensities
            )
        if self.K is None or self.positions is None:
            raise InputError(f"capture {self.name!r} has no camera intrinsics or light positions to build a rig from")
        return Rig.pinhole(
            self.K,
            lights=self.positions,
            distortion=self.distortion,
            intensities=self.intensities,
            axes=self.directions,
            mu=self.mu,
        )

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
            valid=pick(self.valid),
            files=files,
        )


def prepare(
    capture: Capture,
    *,
    bin_factor: int = 1,
    ambient: bool = True,
    vignetting: Literal["cos4"] | np.ndarray | None = "cos4",
    color: bool | None = None,
    saturation: float | None = None,
    overwrite: bool = False,
) -> Capture:
    """Apply the usual pre-processing of a near-light capture, as the near_ps authors do it.

    Runs :func:`nplps.pipeline.prepare` (the command line's pipeline): loads the images if
    needed, judges saturation on the values as read (``saturation``, default the top level of
    integer files; any channel) into ``valid``, averages to grey with ``color=False``, subtracts
    the ambient image (clipping at 0), divides by the vignetting map (``"cos4"`` from K when K is
    known, a flat-field map, or None), and bins by ``bin_factor`` (images averaged, mask and
    ``valid`` kept where the whole block is, K adjusted: fx' = fx/s, cx' = (cx + 1/2)/s - 1/2).
    Returns a loaded capture on the binned grid whose ``preprocessed`` lists the steps that
    ran; ``capture.rig()`` gives the matching rig and ``capture.options()`` the ``mask``,
    ``dark`` (0 after any step, as on the command line) and ``valid`` to pass to
    :func:`nplps.reconstruct`.

    Images read from files are corrected in place. A float32 stack in ``capture.images`` is
    copied once by the first correction, unless ``overwrite=True`` hands it over to be
    corrected in place (no copy; the caller's array then holds the corrected values).
    """
    c = capture.load()
    given = capture.images
    # Images read here (not the caller's array) are corrected in place.
    owned = overwrite or not (isinstance(given, np.ndarray) and np.may_share_memory(c.images, given))
    if isinstance(vignetting, str) and vignetting == "cos4" and c.K is None:
        vignetting = None  # no K, no cos^4 map
    out = pipeline.prepare(
        np.asarray(c.images, dtype=np.float32),
        K=c.K,
        mask=c.mask,
        color=color,
        levels=c.levels,
        preprocessed=c.preprocessed,
        valid=c.valid,
        saturation=saturation,
        ambient=c.ambient if ambient else None,
        vignetting=vignetting,
        bin_factor=bin_factor,
        overwrite=owned,
    )
    return dataclasses.replace(
        c,
        images=out.images,
        ambient=None,
        K=out.K,
        mask=out.mask,
        normals_gt=None if bin_factor != 1 else c.normals_gt,
        pixel_size=c.pixel_size * bin_factor,
        bin_factor=c.bin_factor * bin_factor,
        preprocessed=out.steps,
        valid=out.valid,
    )
