"""The rig: camera model and lights, and the JSON rig file.

A :class:`Rig` is one camera (a mapping in the rig file's form) and a tuple of lights, one per
image, each a frozen value of one of three types that mirror the compiled core's ``enum Light``:

* :class:`PointLight` -- an isotropic point light at ``position``:
  ``I = rho * intensity * max(0, n . (p - x)) / |p - x|^3``;
* :class:`LED` -- a point light at ``position`` emitting around its unit ``axis`` (from the LED
  towards the scene) with anisotropy ``mu`` >= 0 (Quéau et al. 2018; ``mu = 0`` emits like a
  point light): ``I = rho * intensity * ((x - p) . axis / |x - p|)^mu * max(0, n . (p - x)) /
  |p - x|^3``;
* :class:`DirectionalLight` -- a distant light along the unit ``direction`` from the surface
  towards the light: ``I = rho * intensity * max(0, n . direction)``.

``intensity`` is per channel (R, G, B; grey images use the mean). Camera frame as in OpenCV (x
right, y down, z forward into the scene), in the user's unit (mm typical).

Rig file (JSON), version 3 (versions 1 and 2 are read too; 1 has only light positions, 2 no
``"grid"``)::

    {
      "version": 3,
      "_comment": "kept when the rig is saved again",
      "camera": {"model": "orthographic", "pixel_size": [w, h], "origin": [ox, oy]},
      "grid": {"image_size": [W, H], "binning": 1},
      "lights": [
        {"type": "point", "position": [x, y, z], "intensity": 1.0},
        {"type": "point", "position": [x, y, z], "intensity": [r, g, b],
         "direction": [dx, dy, dz], "mu": 1.0},
        {"type": "directional", "direction": [dx, dy, dz], "intensity": 0.5}
      ]
    }

The optional ``"grid"`` says which images the camera belongs to (:class:`RigGrid`):
``"image_size"`` their width and height in pixels, ``"binning"`` how many pixels of the original
calibration grid one pixel of them averages along each axis (1: the original; 4 after ``--bin
4``, whose K is the binned one). nplps writes it into every rig it saves with a result, so
that a rig reused on images of another size is refused with both sizes named instead of giving
a silently wrong result (:func:`nplps.pipeline.prepare` checks it). Top-level keys starting with
``_`` (comments) are kept by :meth:`Rig.to_dict` and :meth:`Rig.save`.

In the file an LED is a ``"point"`` light with a ``"direction"``: that key is the LED's
:attr:`LED.axis` (``"mu"`` defaults to 0); a ``"point"`` light without it is a
:class:`PointLight` (it may not have ``"mu"`` > 0). A ``"directional"`` light's ``"direction"``
is :attr:`DirectionalLight.direction`. :meth:`Rig.save` writes an LED's ``"direction"`` and
``"mu"`` and a point light's neither.

The camera is ``"camera": {"model": "pinhole", "K": [[fx, s, cx], [0, fy, cy], [0, 0, 1]],
"distortion": [k1, k2, p1, p2, k3]}`` for a pinhole camera, with K in the 0-based pixel-centre
convention (pixel (r, c) has its centre at (u, v) = (c, r)) and OpenCV's distortion model (also
as OpenCV's 1 x n or n x 1 matrix ``[[k1, k2, p1, p2, k3]]``; 2, 4 or 5 coefficients, missing
ones zero, or 8, 12 or 14 whose rational, thin-prism and tilt terms are zero; 3 are ambiguous
and refused).

Rig files are read strictly, so that a file means one thing (the same to this module and to the
compiled core, which checks the camera mapping with the same rules): every value must have its
type and shape (numbers are JSON numbers, never booleans or strings, and finite), a key that is
not part of the format is an error naming it (a misspelt ``"intensities"`` must not fall back to
the default) except keys starting with ``_``, which are comments and ignored at every level.
Files are at most 16 MiB (:data:`MAX_RIG_FILE_BYTES`), nested at most 64 levels
(:data:`MAX_NESTING`) and hold at most ``_core.MAX_LIGHTS`` (10 000) lights. Every problem is a
:class:`RigError` with a short message.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np

from . import _core, _core_types, _rig_codecs
from ._atomic import write_text
from ._rig_values import (
    _LIGHT_TYPES,
    _NO_AXIS,
    LED,
    MAX_NESTING,
    MAX_RIG_FILE_BYTES,
    ArrayLike,
    DirectionalLight,
    Light,
    PointLight,
    RigGrid,
    Vec3,
    _describe,
    _kind,
    _new,
    _unit,
    _with_intensity,
    _with_position,
    core_grid,
    read_rig_json,
    read_small_text,
)
from .errors import RigError

__all__ = [
    "LED",
    "MAX_LIGHTS",
    "MAX_NESTING",
    "MAX_RIG_FILE_BYTES",
    "RIG_FILE_VERSION",
    "DirectionalLight",
    "Light",
    "PointLight",
    "Rig",
    "RigGrid",
    "read_rig_json",
    "read_small_text",
]

RIG_FILE_VERSION = 3
#: Most lights of a rig.
MAX_LIGHTS: int = _core.MAX_LIGHTS


_NAN3: Vec3 = (math.nan, math.nan, math.nan)


# --------------------------------------------------------------------------------------------------
# Rig
# --------------------------------------------------------------------------------------------------


def _readonly(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


@dataclass(frozen=True, init=False)
class Rig:
    """A calibrated rig: one camera and k lights, in the order of the images.

    Parameters
    ----------
    camera : mapping
        The camera, as the rig file's ``"camera"`` object (checked by the compiled core and kept
        in its canonical form).
    lights : sequence of PointLight, LED and DirectionalLight, or (k, 3) array_like
        The lights. A (k, 3) array of numbers is k isotropic unit :class:`PointLight` at those
        positions (use :meth:`from_arrays` for anything else).

    Raises
    ------
    RigError
        When the camera or a light is invalid, there are fewer than 3 or more than
        :data:`MAX_LIGHTS` lights, or ``lights`` mixes light values and numbers.

    Notes
    -----
    Array views of the lights (read-only, computed once): :attr:`positions`, :attr:`directions`,
    :attr:`axes` and :attr:`intensities` (k, 3), :attr:`mu` and :attr:`directional` (k,). A row
    of a quantity a light does not have is NaN (a directional light's position, a point light's
    direction, the axis of a light that is not an :class:`LED`), so that a direction is never
    used as a position by mistake; :attr:`mu` is 0 for lights that are not LEDs.

    Rigs compare equal when their cameras and lights are equal.
    """

    #: The camera mapping (canonical form).
    camera: dict[str, Any]
    #: The lights, one per image.
    lights: tuple[Light, ...] = field(repr=False)
    #: The image grid the camera belongs to, if known (:class:`RigGrid`; not compared).
    grid: RigGrid | None = field(default=None, repr=False, compare=False)
    #: The rig file's top-level comments (keys starting with ``_``), kept when saved (not compared).
    comments: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)
    if TYPE_CHECKING:
        #: The compiled core's rig (built and validated once; every ``_core`` call takes it); not
        #: a field (it follows from the camera and the lights).
        _native: _core.Rig = field(init=False)

    def __init__(
        self,
        camera: Mapping[str, Any],
        lights: Sequence[Light] | ArrayLike = (),
        *,
        grid: RigGrid | None = None,
        comments: Mapping[str, Any] | None = None,
    ) -> None:
        object.__setattr__(self, "grid", grid)
        object.__setattr__(self, "comments", dict(comments or {}))
        if not isinstance(camera, Mapping):
            raise RigError(f"camera must be a mapping (the rig file's camera object), got {_describe(camera)}")
        values = _lights(lights)
        if len(values) > MAX_LIGHTS:
            raise RigError(f"the rig has {len(values)} lights; at most {MAX_LIGHTS} are supported")
        object.__setattr__(self, "lights", values)
        # The compiled core checks the camera (every key) and the lights, once, and gives the
        # camera's canonical form.
        self._set_native(_core.Rig(dict(camera), self._core_lights()))

    def _set_native(self, native: _core.Rig) -> None:
        object.__setattr__(self, "_native", native)
        object.__setattr__(self, "camera", native.camera)

    def __hash__(self) -> int:
        """Hash the camera mapping and the lights (the array views follow from them)."""
        return hash((json.dumps(self.camera, sort_keys=True), self.lights))

    def __getstate__(self) -> dict[str, Any]:
        """Return the state to pickle: the fields only."""
        # The fields only: the array views are computed again (read-only) after unpickling.
        return {"camera": self.camera, "lights": self.lights, "grid": self.grid, "comments": self.comments}

    def __setstate__(self, state: dict[str, Any]) -> None:
        """Restore a pickled rig (also one pickled before it had a grid)."""
        object.__setattr__(self, "camera", state["camera"])
        object.__setattr__(self, "lights", state["lights"])
        object.__setattr__(self, "grid", state.get("grid"))
        object.__setattr__(self, "comments", state.get("comments", {}))
        self._set_native(_core.Rig(dict(self.camera), self._core_lights()))

    def _like_this(self, camera: Mapping[str, Any], lights: Sequence[Light], grid: RigGrid | None = None) -> Rig:
        """Return a rig with other camera or lights that keeps this one's grid (or ``grid``) and comments."""
        return Rig(camera=camera, lights=lights, grid=grid or self.grid, comments=self.comments)

    def with_grid(self, width: int, height: int) -> Rig:
        """Return the rig with the image size it belongs to recorded (its binning kept).

        Parameters
        ----------
        width, height : int
            The size of its images in pixels.

        Returns
        -------
        Rig
        """
        binning = 1 if self.grid is None else self.grid.binning
        return self._like_this(self.camera, self.lights, RigGrid((int(width), int(height)), binning))

    def check_grid(self, width: int, height: int, what: str = "the images") -> None:
        """Refuse images of another size than the rig's recorded grid (if it has one).

        Raises
        ------
        RigError
            The rig records an image size and ``width`` x ``height`` is another; the message
            names both sizes and, for a rig of binned images, the binning.
        """
        grid = self.grid
        if grid is None or grid.image_size is None or grid.image_size == (int(width), int(height)):
            return
        hint = "use the rig that was calibrated for these images"
        if grid.binning > 1:
            hint = (
                f"its camera is that of images binned {grid.binning} x {grid.binning} (a rig saved with a binned "
                "result): use the original rig file with --bin, or give it images of its size without --bin"
            )
        raise RigError(
            f"the rig belongs to images of {grid.describe()}, but {what} are {int(width)} x {int(height)} pixels: "
            f"{hint}"
        )

    # -- constructors ---------------------------------------------------------------------------
    @classmethod
    def from_arrays(
        cls,
        camera: Mapping[str, Any],
        positions: ArrayLike | None = None,
        *,
        directions: ArrayLike | None = None,
        intensities: ArrayLike | None = None,
        axes: ArrayLike | None = None,
        mu: ArrayLike | None = None,
    ) -> Rig:
        """Build a rig from per-light arrays (the inverse of the array views).

        Parameters
        ----------
        camera : mapping
            The camera, as the rig file's ``"camera"`` object.
        positions : (k, 3) array_like, optional
            Positions of the point lights; NaN rows for directional lights. None: every light is
            directional.
        directions : (k, 3) array_like, optional
            Directions (from the surface towards the light; scaled to unit length) of the
            directional lights; NaN rows for point lights. None: no light is directional.
        intensities : float, (k,), (k, 1) or (k, 3) array_like, optional
            Intensities (or a list of k items, each a number or R, G, B). Default 1.
        axes : (k, 3) array_like, optional
            LED principal directions (from the LED towards the scene; scaled to unit length).
            Rows of lights that are not LEDs are ignored (NaN in :attr:`axes`).
        mu : (k,) array_like, optional
            Anisotropy per light, >= 0, default 0. A point light with ``mu`` > 0 is an
            :class:`LED` (it needs its row of ``axes``); one with ``mu`` = 0 is a
            :class:`PointLight` (its axis, unused, is dropped). 0 (or NaN) for directional lights.

        Returns
        -------
        Rig

        Raises
        ------
        RigError
            When an array has the wrong shape or a non-number, a light has both or neither of a
            position and a direction, an LED has no axis, or a light is invalid.
        """
        return cls._from_arrays(camera, positions, directions, intensities, axes, mu)

    @classmethod
    def _from_arrays(
        cls,
        camera: Mapping[str, Any],
        positions: ArrayLike | None,
        directions: ArrayLike | None = None,
        intensities: ArrayLike | None = None,
        axes: ArrayLike | None = None,
        mu: ArrayLike | None = None,
        positions_name: str = "positions",
    ) -> Rig:
        if positions is not None:
            pos = _array(positions, positions_name, (-1, 3))
            k = pos.shape[0]
            dirs = np.full((k, 3), np.nan) if directions is None else _array(directions, "directions", (k, 3))
        elif directions is not None:
            dirs = _array(directions, "directions", (-1, 3))
            k = dirs.shape[0]
            pos = np.full((k, 3), np.nan)
        else:
            k = 0
            pos = dirs = np.zeros((0, 3))
        if k > MAX_LIGHTS:
            raise RigError(f"the rig has {k} lights; at most {MAX_LIGHTS} are supported")
        phi = _intensities(intensities, k)
        mus = np.zeros(k) if mu is None else _array(mu, "mu", (k,))
        ax = None if axes is None else _array(axes, "axes", (k, 3))
        lights: list[Light] = []
        for i in range(k):
            subject = f"light {i}"
            has_pos, has_dir = not np.isnan(pos[i]).all(), not np.isnan(dirs[i]).all()
            if has_pos and has_dir and directions is not None and positions is not None:
                raise RigError(
                    f"{subject} has both a position and a direction: give NaN in the row of the other "
                    "(positions for point lights, directions for directional lights)"
                )
            if not has_pos and not has_dir and directions is not None and positions is not None:
                raise RigError(f"{subject} has neither a position nor a direction (both rows are NaN)")
            if has_dir or positions is None:
                if mus[i] != 0 and not math.isnan(mus[i]):
                    raise RigError(f"{subject} is directional: it has no anisotropy (mu = {mus[i]:.6g})")
                lights.append(DirectionalLight._checked(subject, dirs[i], phi[i]))
            elif not mus[i] == 0:  # an LED, or an invalid mu (negative or NaN) for LED's checks
                if mus[i] > 0 and (ax is None or np.isnan(ax[i]).all()):
                    raise RigError(f"{subject}: an anisotropic LED (mu = {mus[i]:.6g}) needs its axis (axes=...)")
                axis = _NO_AXIS if ax is None else ax[i]
                lights.append(LED._checked(subject, pos[i], phi[i], axis, mus[i]))
            else:
                lights.append(PointLight._checked(subject, pos[i], phi[i]))
        return cls(camera=camera, lights=tuple(lights))

    @classmethod
    def orthographic(
        cls,
        pixel_size: float | Sequence[float],
        origin: Sequence[float] = (0.0, 0.0),
        lights: Sequence[Light] | ArrayLike = (),
        **arrays: Any,
    ) -> Rig:
        """Return the paper's orthographic camera looking along +z.

        Parameters
        ----------
        pixel_size : float or (w, h)
            Footprint of a pixel on the object, or one number for square pixels.
        origin : (ox, oy), default (0, 0)
            Scene (x, y) of the top-left corner of pixel (0, 0).
        lights : sequence of lights or (k, 3) array_like
            Light values, or the positions of point lights as in :meth:`from_arrays`; lights
            stand in front of the object (smaller z).
        **arrays
            ``directions``, ``intensities``, ``axes``, ``mu`` as in :meth:`from_arrays` (only
            with array ``lights``).

        Returns
        -------
        Rig

        Raises
        ------
        RigError
            When the camera or the lights are invalid (see :meth:`from_arrays`).
        """
        size: Any = pixel_size
        if np.isscalar(size) or (isinstance(size, np.ndarray) and size.ndim == 0):
            size = (size, size)
        # The compiled core checks the values and gives the canonical camera.
        camera = {"model": "orthographic", "pixel_size": size, "origin": origin}
        return cls._build(camera, lights, arrays)

    @classmethod
    def pinhole(
        cls,
        K: ArrayLike,
        lights: Sequence[Light] | ArrayLike = (),
        distortion: ArrayLike | None = None,
        **arrays: Any,
    ) -> Rig:
        """Return a pinhole camera at the origin.

        Parameters
        ----------
        K : (3, 3) array_like
            Intrinsics in the 0-based pixel-centre convention (pixel (r, c) has its centre at
            (u, v) = (c, r); MATLAB's 1-based K has cx, cy one larger).
        lights : sequence of lights or (k, 3) array_like
            Light values, or the positions of point lights (LEDs) in the camera frame as in
            :meth:`from_arrays`.
        distortion : array_like, optional
            OpenCV coefficients (k1, k2[, p1, p2[, k3]]), flat or OpenCV's 1 x n or n x 1
            matrix (8, 12 or 14 when the terms after k3 are zero); None for none.
        **arrays
            ``directions``, ``intensities``, ``axes``, ``mu`` as in :meth:`from_arrays` (only
            with array ``lights``).

        Returns
        -------
        Rig

        Raises
        ------
        RigError
            When the camera or the lights are invalid (see :meth:`from_arrays`).
        """
        # The compiled core checks K and the distortion and gives their canonical form.
        camera: dict[str, Any] = {"model": "pinhole", "K": K}
        if distortion is not None:
            camera["distortion"] = distortion
        return cls._build(camera, lights, arrays)

    @classmethod
    def _build(cls, camera: dict[str, Any], lights: Any, arrays: dict[str, Any]) -> Rig:
        unknown = sorted(set(arrays) - {"directions", "intensities", "axes", "mu"})
        if unknown:
            raise TypeError(
                f"unexpected keyword argument {unknown[0]!r} "
                "(the light arrays are directions, intensities, axes and mu)"
            )
        if _is_light_values(lights):
            given = [name for name, value in arrays.items() if value is not None]
            if given:
                raise RigError(f"{given[0]}= goes with an array of positions, not with light values")
            return cls(camera=camera, lights=lights)
        positions = None if _is_empty(lights) and arrays.get("directions") is not None else lights
        return cls._from_arrays(camera, positions, **arrays, positions_name="lights")

    # -- properties -----------------------------------------------------------------------------
    @property
    def n_lights(self) -> int:
        """Number of lights k."""
        return len(self.lights)

    @property
    def is_pinhole(self) -> bool:
        """Whether the camera is a pinhole camera."""
        return self.camera.get("model") == "pinhole"

    @property
    def K(self) -> np.ndarray | None:
        """The pinhole intrinsics (0-based pixel centres), or None for an orthographic camera."""
        return np.array(self.camera["K"], dtype=np.float64) if self.is_pinhole else None

    @cached_property
    def positions(self) -> np.ndarray:
        """(k, 3) positions of the point lights and LEDs; NaN rows for directional lights."""
        rows = [_NAN3 if isinstance(light, DirectionalLight) else light.position for light in self.lights]
        return _readonly(np.array(rows, dtype=np.float64).reshape(-1, 3))

    @cached_property
    def directions(self) -> np.ndarray:
        """The (k, 3) unit directions (from the surface towards the light) of the directional lights.

        NaN rows for point lights and LEDs.
        """
        rows = [light.direction if isinstance(light, DirectionalLight) else _NAN3 for light in self.lights]
        return _readonly(np.array(rows, dtype=np.float64).reshape(-1, 3))

    @cached_property
    def axes(self) -> np.ndarray:
        """(k, 3) unit principal directions of the LEDs; NaN rows for other lights."""
        rows = [light.axis if isinstance(light, LED) else _NAN3 for light in self.lights]
        return _readonly(np.array(rows, dtype=np.float64).reshape(-1, 3))

    @cached_property
    def intensities(self) -> np.ndarray:
        """(k, 3) intensities per channel (R, G, B)."""
        return _readonly(np.array([light.intensity for light in self.lights], dtype=np.float64).reshape(-1, 3))

    @cached_property
    def mu(self) -> np.ndarray:
        """(k,) anisotropy of the LEDs; 0 for other lights."""
        mus = [light.mu if isinstance(light, LED) else 0.0 for light in self.lights]
        return _readonly(np.array(mus, dtype=np.float64))

    @cached_property
    def directional(self) -> np.ndarray:
        """(k,) whether each light is a :class:`DirectionalLight`."""
        return _readonly(np.array([isinstance(light, DirectionalLight) for light in self.lights], dtype=bool))

    # -- derived rigs ---------------------------------------------------------------------------
    def subset(self, indices: Sequence[int]) -> Rig:
        """Return the rig with only some lights.

        Parameters
        ----------
        indices : sequence of int
            The lights to keep, in that order (from -k to k - 1 for k lights).

        Returns
        -------
        Rig

        Raises
        ------
        RigError
            When an index is not a whole number or not a light of the rig, or fewer than 3
            lights remain.
        """
        try:
            idx = np.asarray(indices)
        except ValueError:  # a ragged nested sequence
            idx = np.asarray(None)
        k = self.n_lights
        if idx.ndim != 1 or not (idx.size == 0 or np.issubdtype(idx.dtype, np.integer)):
            raise RigError(
                f"indices must be a list of whole-number light indices, got a {type(indices).__name__} "
                f"of {idx.dtype}, shape {idx.shape}"
            )
        out = (idx < -k) | (idx >= k)
        if out.any():
            raise RigError(
                f"indices: {int(idx[out][0])} is not a light of the rig (its {k} lights are {-k} .. {k - 1})"
            )
        return self._like_this(self.camera, tuple(self.lights[i] for i in idx.astype(int).tolist()))

    def with_positions(self, positions: ArrayLike) -> Rig:
        """Return the rig with the point lights and LEDs moved.

        Parameters
        ----------
        positions : (k, 3) array_like
            New positions, NaN rows for directional lights (as :attr:`positions`: ``rig.
            with_positions(rig.positions + shift)`` moves the point lights).

        Returns
        -------
        Rig

        Raises
        ------
        RigError
            When the shape is wrong, a directional light's row is not NaN, or a point light's
            row is not finite.
        """
        p = _array(positions, "positions", (self.n_lights, 3))
        lights: list[Light] = []
        for i, light in enumerate(self.lights):
            if isinstance(light, DirectionalLight):
                if not np.isnan(p[i]).all():
                    raise RigError(f"positions: light {i} is a directional light: its row must be NaN")
                lights.append(light)
            else:
                lights.append(_with_position(light, p[i], f"light {i}"))
        return self._like_this(self.camera, tuple(lights))

    def with_intensities(self, intensities: ArrayLike) -> Rig:
        """Return the rig with new intensities.

        Parameters
        ----------
        intensities : float, (k,), (k, 1) or (k, 3) array_like
            The intensities, as in :meth:`from_arrays`.

        Returns
        -------
        Rig

        Raises
        ------
        RigError
            When the shape is wrong or an intensity is not a positive finite number.
        """
        phi = _intensities(intensities, self.n_lights)
        lights = tuple(_with_intensity(light, phi[i], f"light {i}") for i, light in enumerate(self.lights))
        return self._like_this(self.camera, lights)

    def binned(self, n: int) -> Rig:
        """Return the rig of the images binned ``n`` x ``n``.

        Blocks of pixels are averaged; the remainder at the bottom and right is cropped.

        Parameters
        ----------
        n : int
            The binning factor (>= 1).

        Returns
        -------
        Rig
            The same lights; the pinhole K by :func:`nplps.preprocess.bin_intrinsics`, or the
            orthographic pixel size times ``n`` with the origin kept (the top-left corner of
            pixel (0, 0)).

        Raises
        ------
        RigError
            When ``n`` is not a whole number of at least 1.
        """
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise RigError(f"the binning factor must be a whole number of at least 1, got {_describe(n)}")
        from . import preprocess

        camera = dict(self.camera)
        if self.is_pinhole:
            camera["K"] = preprocess.bin_intrinsics(np.array(camera["K"], dtype=np.float64), int(n)).tolist()
        else:
            camera["pixel_size"] = [float(v) * int(n) for v in camera["pixel_size"]]
        n = int(n)
        if n == 1:
            return self
        old = self.grid or RigGrid()
        size = None if old.image_size is None else (old.image_size[0] // n, old.image_size[1] // n)
        return self._like_this(camera, self.lights, RigGrid(size, old.binning * n))

    # -- the compiled core's form ---------------------------------------------------------------
    @classmethod
    def _from_native(
        cls,
        native: _core.Rig,
        like: Rig | None = None,
        grid: RigGrid | None = None,
        comments: Mapping[str, Any] | None = None,
        unit_axes: bool = True,
    ) -> Rig:
        """Return the rig of a compiled core's rig (already validated, each light with its kind).

        ``like``: the rig whose grid and comments it keeps (refined or calibrated lights).
        ``unit_axes``: scale the LED axes to unit length as LED() does (False for the rig file
        reader's rig, which did it with the same operations).
        """
        d = native.lights
        out: list[Light] = []
        for kind, vector, phi, axis, mu in zip(
            d["kind"], d["vectors"], d["intensities"], d["axes"], d["mu"], strict=True
        ):
            v: Vec3 = (vector[0], vector[1], vector[2])
            rgb: Vec3 = (phi[0], phi[1], phi[2])
            if kind == "directional":
                out.append(_new(DirectionalLight, direction=v, intensity=rgb))
            elif kind == "led":
                # Scaled to unit length as LED() does (a unit axis may move by a bit).
                a: Vec3 = (axis[0], axis[1], axis[2])
                out.append(_new(LED, position=v, intensity=rgb, axis=_unit(a) if unit_axes else a, mu=mu))
            else:
                out.append(_new(PointLight, position=v, intensity=rgb))
        rig = object.__new__(cls)
        if like is not None:
            grid, comments = like.grid, like.comments
        object.__setattr__(rig, "grid", grid)
        object.__setattr__(rig, "comments", dict(comments or {}))
        object.__setattr__(rig, "lights", tuple(out))
        if any(isinstance(light, LED) and light.axis != tuple(a) for light, a in zip(out, d["axes"], strict=True)):
            native = _core.Rig(native.camera, rig._core_lights())
        rig._set_native(native)
        return rig

    def _core_lights(self) -> _core_types.LightsDict:
        """Return the lights in the form the compiled core takes.

        Lights that are not LEDs get an axis of (0, 0, 1) and mu = 0.
        """
        vectors, directional, intensities, axes, mus, kinds = [], [], [], [], [], []
        for light in self.lights:
            kinds.append(_kind(light))
            if isinstance(light, DirectionalLight):
                vectors.append(list(light.direction))
            else:
                vectors.append(list(light.position))
            directional.append(isinstance(light, DirectionalLight))
            intensities.append(list(light.intensity))
            axes.append(list(light.axis if isinstance(light, LED) else _NO_AXIS))
            mus.append(light.mu if isinstance(light, LED) else 0.0)
        return {
            "vectors": vectors,
            "directional": directional,
            "intensities": intensities,
            "axes": axes,
            "mu": mus,
            "kind": kinds,
        }

    # -- files ----------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Return the rig as the JSON-ready mapping of the rig file.

        Returns
        -------
        dict
            ``{"version": 3, "_comment": ..., "camera": ..., "grid": ..., "lights": [...]}``: the
            comments and the grid only when the rig has them; an intensity is one number when
            its three channels are equal; an LED's axis is its ``"direction"``.
        """
        lights = []
        for light in self.lights:
            phi = list(light.intensity)
            intensity: Any = phi[0] if phi[0] == phi[1] == phi[2] else phi
            if isinstance(light, DirectionalLight):
                lights.append({"type": "directional", "direction": list(light.direction), "intensity": intensity})
                continue
            entry: dict[str, Any] = {"type": "point", "position": list(light.position), "intensity": intensity}
            if isinstance(light, LED):
                entry["direction"] = list(light.axis)
                entry["mu"] = light.mu
            lights.append(entry)
        data: dict[str, Any] = {"version": RIG_FILE_VERSION, **self.comments, "camera": dict(self.camera)}
        if self.grid is not None:
            grid: dict[str, Any] = {"binning": self.grid.binning}
            if self.grid.image_size is not None:
                grid = {"image_size": list(self.grid.image_size), **grid}
            data["grid"] = grid
        data["lights"] = lights
        return data

    @classmethod
    def from_dict(cls, data: Any, source: str = "rig") -> Rig:
        """Read the mapping of a rig file (see the module documentation for what is checked).

        Parameters
        ----------
        data : mapping
            The rig file's JSON object.
        source : str, default "rig"
            Where it comes from, for messages.

        Returns
        -------
        Rig

        Raises
        ------
        RigError
            Naming what is wrong.
        """
        if not isinstance(data, Mapping):
            raise RigError(f"{source}: a rig file holds a JSON object, got {_describe(data)}")
        try:
            text = json.dumps(data, default=_plain, allow_nan=False)
        except ValueError:
            raise RigError(f"{source}: {_nonfinite(data, '')} must be a finite number") from None
        except RecursionError:
            raise RigError(f"{source}: the rig is nested too deeply (at most {MAX_NESTING} levels)") from None
        except TypeError as e:
            raise RigError(f"{source}: not a rig file's mapping ({e})") from None
        # The compiled core reads it (its rig file reader, the only one) and builds its rig.
        return cls._from_file(_core.parse_rig(text, source))

    @classmethod
    def _from_file(cls, file: tuple[_core.Rig, Any, list[tuple[str, str]]]) -> Rig:
        """Return the rig of the compiled core's reading of a rig file (rig, grid, comments)."""
        native, grid, comments = file
        return cls._from_native(
            native,
            grid=core_grid(grid),
            comments={k: json.loads(v) for k, v in comments},
            unit_axes=False,
        )

    def save(self, path: str | os.PathLike[str], *, fmt: str | None = None, **options: Any) -> None:
        """Write the rig file (JSON), under a temporary name renamed when complete.

        Other formats by extension (``.dome``, ``.lp``, ``.yml``/``.yaml``, a file named
        ``lights.json``) or `fmt`: see :func:`nplps.rig_formats.save`.

        Parameters
        ----------
        path : str or os.PathLike
            The file.
        fmt : str, optional
            One of :data:`nplps.rig_formats.FORMATS`; default: by extension.
        **options
            ``camera_distance``, ``drop_intensities``: see :func:`nplps.rig_formats.save`.

        Raises
        ------
        RigError
            The format cannot represent the rig.
        OSError
            When the file cannot be written.
        """
        if fmt is not None or options or _rig_codecs.output_format(path, None) != "rig":
            _save_rig(self, path, fmt=fmt, **options)
            return
        self._save_json(path)

    def _save_json(self, path: str | os.PathLike[str]) -> None:
        from ._atomic import atomic_write

        with atomic_write(path, "w", encoding="utf-8") as f:
            json.dump(self.to_dict(), f, indent=2)
            f.write("\n")

    @classmethod
    def load(cls, path: str | os.PathLike[str], **options: Any) -> Rig:
        """Read a rig file, or a lights file of another format (by extension or content).

        A ``.dome``, ``.lp`` or AliceVision ``lights.json`` has no camera: give one with
        ``camera=`` (see :func:`nplps.rig_formats.load` for the options).

        Parameters
        ----------
        path : str or os.PathLike
            The file.
        **options
            ``fmt``, ``camera``, ``camera_distance``, ``light_distance``, ``intrinsic``: see
            :func:`nplps.rig_formats.load`.

        Returns
        -------
        Rig

        Raises
        ------
        RigError
            When the file is missing, unreadable or malformed (naming the problem), or a value
            its format lacks is not given.
        """
        if not isinstance(path, (str, bytes, os.PathLike)):
            raise RigError(f"a rig file is read from a path (str or os.PathLike), got {type(path).__name__}")
        name = os.fsdecode(path)
        if options or _rig_codecs.detect_format(name) != "rig":
            return _load_rig(name, **options)
        return cls._from_file(_core.read_rig(name))


# --------------------------------------------------------------------------------------------------
# Other formats (their codecs in _rig_codecs; the public face is nplps.rig_formats)
# --------------------------------------------------------------------------------------------------


def _load_rig(
    path: str | os.PathLike[str],
    *,
    fmt: str | None = None,
    camera: Mapping[str, Any] | str | os.PathLike[str] | None = None,
    camera_distance: float | None = None,
    light_distance: float | None = None,
    intrinsic: str | None = None,
    scale: float | None = None,
) -> Rig:
    """Read a rig file or a lights file of another format: see :func:`nplps.rig_formats.load`."""
    fmt = fmt or _rig_codecs.detect_format(path)
    if fmt not in _rig_codecs.FORMATS:
        raise RigError(f"unknown format {fmt!r}; the formats are {', '.join(_rig_codecs.FORMATS)}")
    name = os.fspath(path)
    if fmt in ("opencv-yaml", "opencv-json", "sfmdata"):
        raise RigError(
            f"{name!r} holds a camera only (no lights): give it as the camera of a lights file "
            "(nplps rig convert LIGHTS OUT --camera CAMERA)"
        )
    if light_distance is not None and camera_distance is None:
        raise RigError("light_distance (--light-distance) needs camera_distance (--camera-distance)")
    if fmt == "rig":
        rig = Rig._from_file(_core.read_rig(name))
        if camera is None:
            return rig
        cam, grid = _rig_codecs.camera_of(camera, intrinsic)
        return Rig(cam, rig.lights, grid=grid or rig.grid, comments=rig.comments)
    if camera is None:
        raise RigError(
            f"{name!r} is a {_rig_codecs.FORMAT_NAMES[fmt]}, which has no camera: give one "
            "(Rig.load(..., camera=...) with "
            "an OpenCV camera YAML/JSON, a rig file or an SfMData), or make a rig file first: "
            f"nplps rig convert {name} rig.json --camera CAMERA"
        )
    cam, grid = _rig_codecs.camera_of(camera, intrinsic)
    if fmt == "dome":
        lights, comments = _rig_codecs.read_dome(name, camera_distance, light_distance, scale)
    elif fmt == "lp":
        lights, comments = _rig_codecs.read_lp(name, camera_distance, light_distance)
    else:
        lights, comments = _rig_codecs.read_alicevision(name)
    return Rig(cam, lights, grid=grid, comments=comments)


def _save_rig(
    rig: Rig,
    path: str | os.PathLike[str],
    *,
    fmt: str | None = None,
    camera_distance: float | None = None,
    drop_intensities: bool = False,
    scale: float | None = None,
) -> str:
    """Write a rig, or the part of it that a format holds: see :func:`nplps.rig_formats.save`."""
    fmt = _rig_codecs.output_format(path, fmt)
    if fmt == "rig":
        rig._save_json(path)
    elif fmt == "dome":
        write_text(path, _rig_codecs.dome_text(rig, camera_distance, scale))
    elif fmt == "lp":
        write_text(path, _rig_codecs.lp_text(rig, drop_intensities))
    elif fmt == "alicevision":
        write_text(path, _rig_codecs.alicevision_text(rig))
    elif fmt in ("opencv-yaml", "opencv-json"):
        _rig_codecs.write_camera(rig.camera, path, grid=rig.grid, fmt=fmt)
    else:
        raise RigError("nplps reads SfMData files (their intrinsics) but does not write them")
    return fmt


def _is_empty(value: Any) -> bool:
    if isinstance(value, np.ndarray):
        return value.size == 0
    return isinstance(value, (list, tuple)) and len(value) == 0


def _is_light_values(value: Any) -> bool:
    """Whether ``value`` is a non-empty sequence of light values."""
    return isinstance(value, (list, tuple)) and len(value) > 0 and any(isinstance(v, _LIGHT_TYPES) for v in value)


def _lights(value: Any) -> tuple[Light, ...]:
    """Return the lights of a rig: a sequence of light values, or a (k, 3) array of point-light positions."""
    if _is_light_values(value):
        for i, light in enumerate(value):
            if not isinstance(light, _LIGHT_TYPES):
                raise RigError(
                    f"lights: light {i} is {_describe(light)}, not a PointLight, LED or DirectionalLight "
                    "(give light values or a (k, 3) array of positions, not both)"
                )
        return tuple(value)
    positions = _array(value, "lights", (-1, 3))
    if positions.shape[0] > MAX_LIGHTS:
        raise RigError(f"the rig has {positions.shape[0]} lights; at most {MAX_LIGHTS} are supported")
    return tuple(PointLight._checked(f"light {i}", p) for i, p in enumerate(positions))


def _plain(value: Any) -> Any:
    """Return a numpy value of a rig mapping as the plain value ``json`` writes."""
    if isinstance(value, (np.ndarray, np.generic)):
        return value.tolist()
    raise TypeError(f"{_describe(value)} is not a JSON value")


def _nonfinite(value: Any, where: str) -> str:
    """Return where in ``value`` (a mapping of a rig file) the first NaN or infinity is."""
    items: Any = ()
    if isinstance(value, Mapping):
        items = ((f"{where}.{k}" if where else str(k), v) for k, v in value.items())
    elif isinstance(value, (list, tuple, np.ndarray)):
        items = ((f"{where}[{i}]", v) for i, v in enumerate(value))
    elif isinstance(value, (float, np.floating)) and not math.isfinite(value):
        return where
    for name, item in items:
        found = _nonfinite(item, name)
        if found:
            return found
    return ""


def _numeric(value: Any, name: str, kinds: str = "iuf") -> np.ndarray:
    """Return ``value`` as an array of numbers of the dtype kinds ``kinds``.

    Strings and objects are refused, and booleans unless asked.
    """
    try:
        a = np.asarray(value)
    except (TypeError, ValueError, OverflowError, RecursionError):
        raise RigError(f"{name} must be an array of numbers, got {_describe(value)}") from None
    if a.size == 0:
        return a.astype(np.float64)
    if a.dtype.kind not in kinds:
        what = {"b": "booleans", "U": "strings", "S": "bytes", "O": "objects", "c": "complex numbers"}
        raise RigError(f"{name} must be numbers, got an array of {what.get(a.dtype.kind, a.dtype.name)}")
    return a


def _array(value: Any, name: str, shape: tuple[int, ...]) -> np.ndarray:
    a = _numeric(value, name).astype(np.float64)
    if a.size == 0 and shape[0] == -1:
        return np.zeros((0, *shape[1:]))
    expected = tuple(a.shape[0] if s == -1 and a.ndim else s for s in shape)
    if a.shape != expected:
        text = "(" + ", ".join("k" if s == -1 else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        raise RigError(f"{name} must be a {text} array, got shape {a.shape}")
    return np.ascontiguousarray(a)  # the compiled core checks that the values are finite


def _intensities(value: Any, k: int, where: str = "intensities") -> np.ndarray:
    """Return per-light RGB intensities (k, 3).

    They are made from None (ones), a number, (k,), (k, 1) or (k, 3), or a list of k items each a
    number or three (R, G, B).
    """
    if value is None:
        return np.ones((k, 3))
    rows_given = isinstance(value, (list, tuple)) and k and len(value) == k
    if rows_given and any(isinstance(v, (list, tuple, np.ndarray)) for v in value):
        rows = []
        for i, v in enumerate(value):
            a = _numeric(v, f"{where} (light {i})").astype(np.float64)
            if a.shape not in ((), (3,)):
                raise RigError(
                    f"{where} (light {i}): intensity must be a number or three numbers (R, G, B), got shape {a.shape}"
                )
            rows.append(np.broadcast_to(a, (3,)))
        out = np.array(rows, dtype=np.float64)
    else:
        a = _numeric(value, where).astype(np.float64)
        if a.ndim == 0:
            out = np.full((k, 3), float(a))
        elif k == 1 and a.shape == (3,):
            out = a.reshape(1, 3)
        elif a.shape == (k,):
            out = np.repeat(a[:, None], 3, axis=1)
        elif a.shape == (k, 3):
            out = a
        elif a.shape == (k, 1):
            out = np.repeat(a, 3, axis=1)
        else:
            raise RigError(f"{where}: intensities must be a number, (k,) or (k, 3) for {k} lights, got shape {a.shape}")
    return np.ascontiguousarray(out)


def _select_core_lights(lights: _core_types.LightsDict, indices: Sequence[int]) -> _core_types.LightsDict:
    """Select lights of the compiled core's light mapping, in the order of ``indices``.

    Parameters
    ----------
    lights : LightsDict
        The core's light mapping (as :meth:`Rig._core_lights` gives it).
    indices : sequence of int
        Light indices, already checked.

    Returns
    -------
    LightsDict
        The same keys, each list holding the chosen lights only.
    """
    return {
        "vectors": [lights["vectors"][i] for i in indices],
        "directional": [lights["directional"][i] for i in indices],
        "intensities": [lights["intensities"][i] for i in indices],
        "axes": [lights["axes"][i] for i in indices],
        "mu": [lights["mu"][i] for i in indices],
    }
