"""The rig: camera model and lights, and the JSON rig file.

Rig file (JSON), version 2 (version 1 files, with only light positions, are read too)::

    {
      "version": 2,
      "camera": {"model": "orthographic", "pixel_size": [w, h], "origin": [ox, oy]},
      "lights": [
        {"type": "point", "position": [x, y, z], "intensity": 1.0},
        {"type": "point", "position": [x, y, z], "intensity": [r, g, b],
         "direction": [dx, dy, dz], "mu": 1.0},
        {"type": "directional", "direction": [dx, dy, dz], "intensity": 0.5}
      ]
    }

or, for a pinhole camera, ``"camera": {"model": "pinhole", "K": [[fx, s, cx], [0, fy, cy],
[0, 0, 1]], "distortion": [k1, k2, p1, p2, k3]}`` with K in the 0-based pixel-centre convention
(pixel (r, c) has its centre at (u, v) = (c, r)) and OpenCV's distortion model.

Camera frame as in OpenCV (x right, y down, z forward into the scene), in the user's unit (mm
typical). A point light (LED) at ``position`` emits ``intensity`` (a number, or R, G, B) around
its principal ``direction`` (unit, from the LED towards the scene) with anisotropy ``mu`` (0, the
default, is an isotropic point light):
``I = rho * intensity * ((x - p) . d / |x - p|)^mu * max(0, n . (p - x)) / |p - x|^3``.
A directional light has a unit ``direction`` from the surface towards the light and gives
``I = rho * intensity * max(0, n . direction)``. Readers ignore keys they do not know.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from . import _core
from .errors import RigError

RIG_FILE_VERSION = 2

ArrayLike = Any


@dataclass(frozen=True, eq=False)
class Rig:
    """A calibrated rig: one camera and k lights, in the order of the images.

    ``lights`` holds the (k, 3) positions of point lights; for a directional light (where
    ``directional[i]`` is True) row i is its unit direction towards the light. ``intensities``
    (k, 3) are per-channel intensities (grey images use their mean), ``directions`` (k, 3) the
    LEDs' principal directions and ``mu`` (k,) their anisotropy.
    """

    camera: dict[str, Any]
    lights: np.ndarray = field(repr=False)
    intensities: np.ndarray | None = field(default=None, repr=False)
    directions: np.ndarray | None = field(default=None, repr=False)
    mu: np.ndarray | None = field(default=None, repr=False)
    directional: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        lights = _array(self.lights, "lights", (-1, 3))
        k = lights.shape[0]
        directions_given = self.directions is not None
        set_ = lambda name, value: object.__setattr__(self, name, value)  # noqa: E731
        set_("lights", lights)
        set_("intensities", _intensities(self.intensities, k))
        directions = np.zeros((k, 3)) if self.directions is None else _array(self.directions, "directions", (k, 3))
        norms = np.linalg.norm(directions, axis=1, keepdims=True)
        directions = np.where(norms > 0, directions / np.where(norms > 0, norms, 1.0), [0.0, 0.0, 1.0])
        set_("directions", np.ascontiguousarray(directions))
        set_("mu", np.zeros(k) if self.mu is None else _array(self.mu, "mu", (k,)))
        directional = np.zeros(k, dtype=bool) if self.directional is None else np.asarray(self.directional, dtype=bool)
        if directional.shape != (k,):
            raise RigError(f"directional must have one flag per light ({k}), got shape {directional.shape}")
        set_("directional", directional)
        if not directions_given and np.any(self.mu > 0):  # type: ignore[operator]
            raise RigError("anisotropic LEDs (mu > 0) need their principal directions (directions=...)")
        if np.any(directional):
            unit = np.linalg.norm(lights[directional], axis=1)
            if not np.allclose(unit, 1.0, atol=1e-6):
                raise RigError("directional lights need unit directions (from the surface towards the light)")
        _core.check_rig(self.camera, self._core_lights())

    # -- constructors ---------------------------------------------------------------------------
    @classmethod
    def orthographic(
        cls,
        pixel_size: float | Sequence[float],
        origin: Sequence[float] = (0.0, 0.0),
        lights: ArrayLike = (),
        **light_options: Any,
    ) -> "Rig":
        """The paper's orthographic camera looking along +z.

        Args:
            pixel_size: footprint (w, h) of a pixel on the object, or one number for square pixels.
            origin: scene (x, y) of the top-left corner of pixel (0, 0).
            lights: (k, 3) light positions; lights stand in front of the object (smaller z).
            light_options: ``intensities``, ``directions``, ``mu``, ``directional_lights`` and
                ``directional_intensities`` as in :meth:`pinhole`.
        """
        if np.isscalar(pixel_size):
            pixel_size = (pixel_size, pixel_size)  # type: ignore[assignment]
        w, h = _pair(pixel_size, "pixel_size")
        ox, oy = _pair(origin, "origin")
        camera = {"model": "orthographic", "pixel_size": [w, h], "origin": [ox, oy]}
        return cls._build(camera, lights, **light_options)

    @classmethod
    def pinhole(
        cls,
        K: ArrayLike,
        lights: ArrayLike = (),
        distortion: ArrayLike | None = None,
        intensities: ArrayLike | None = None,
        directions: ArrayLike | None = None,
        mu: ArrayLike | None = None,
        directional_lights: ArrayLike | None = None,
        directional_intensities: ArrayLike | None = None,
    ) -> "Rig":
        """A pinhole camera at the origin.

        Args:
            K: 3 x 3 intrinsics in the 0-based pixel-centre convention (pixel (r, c) has its
                centre at (u, v) = (c, r); MATLAB's 1-based K has cx, cy one larger).
            lights: (k, 3) point-light (LED) positions in the camera frame.
            distortion: OpenCV coefficients (k1, k2[, p1, p2[, k3]]); None for none.
            intensities: per light: a number, or R, G, B (default 1).
            directions: (k, 3) LED principal directions (from the LED towards the scene).
            mu: (k,) LED anisotropy (0 = isotropic, the default).
            directional_lights: (m, 3) unit directions (from the surface towards the light) of
                distant lights, appended after the point lights.
            directional_intensities: their intensities (a number or R, G, B each).
        """
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise RigError(f"K must be a 3 x 3 matrix, got shape {K.shape}")
        camera: dict[str, Any] = {"model": "pinhole", "K": K.tolist()}
        if distortion is not None:
            d = np.asarray(distortion, dtype=np.float64).ravel()
            if d.size > 5:
                raise RigError(f"distortion has {d.size} coefficients; at most 5 (k1, k2, p1, p2, k3)")
            camera["distortion"] = np.pad(d, (0, 5 - d.size)).tolist()
        return cls._build(camera, lights, intensities, directions, mu, directional_lights, directional_intensities)

    @classmethod
    def _build(
        cls,
        camera: dict[str, Any],
        lights: ArrayLike,
        intensities: ArrayLike | None = None,
        directions: ArrayLike | None = None,
        mu: ArrayLike | None = None,
        directional_lights: ArrayLike | None = None,
        directional_intensities: ArrayLike | None = None,
    ) -> "Rig":
        points = _array(lights, "lights", (-1, 3))
        k = points.shape[0]
        far = np.zeros((0, 3)) if directional_lights is None else _array(directional_lights, "directional_lights", (-1, 3))
        m = far.shape[0]
        if m:
            far = far / np.linalg.norm(far, axis=1, keepdims=True)
        pad3 = np.zeros((m, 3))
        dirs = None if directions is None else np.vstack([_array(directions, "directions", (k, 3)), pad3])
        mus = None if mu is None else np.concatenate([_array(mu, "mu", (k,)), np.zeros(m)])
        phi = np.vstack([_intensities(intensities, k), _intensities(directional_intensities, m)])
        return cls(
            camera=camera,
            lights=np.vstack([points, far]),
            intensities=phi,
            directions=dirs,
            mu=mus,
            directional=np.r_[np.zeros(k, dtype=bool), np.ones(m, dtype=bool)],
        )

    # -- properties -----------------------------------------------------------------------------
    @property
    def n_lights(self) -> int:
        """Number of lights k."""
        return int(self.lights.shape[0])

    @property
    def is_pinhole(self) -> bool:
        """Whether the camera is a pinhole camera."""
        return self.camera.get("model") == "pinhole"

    @property
    def K(self) -> np.ndarray | None:
        """The pinhole intrinsics (0-based pixel centres), or None for an orthographic camera."""
        return np.array(self.camera["K"], dtype=np.float64) if self.is_pinhole else None

    def subset(self, indices: Sequence[int]) -> "Rig":
        """The rig with only the lights ``indices`` (in that order; from -k to k - 1 for k lights)."""
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
            raise RigError(f"indices: {int(idx[out][0])} is not a light of the rig (its {k} lights are {-k} .. {k - 1})")
        idx = idx.astype(int)
        return Rig(
            camera=dict(self.camera),
            lights=self.lights[idx],
            intensities=self.intensities[idx],  # type: ignore[index]
            directions=self.directions[idx],  # type: ignore[index]
            mu=self.mu[idx],  # type: ignore[index]
            directional=self.directional[idx],  # type: ignore[index]
        )

    @classmethod
    def _from_core_lights(cls, camera: dict[str, Any], lights: dict[str, Any]) -> "Rig":
        """A rig with ``camera`` and the lights in the compiled core's form."""
        return cls(
            camera=dict(camera),
            lights=np.asarray(lights["vectors"], dtype=np.float64),
            intensities=np.asarray(lights["intensities"], dtype=np.float64),
            directions=np.asarray(lights["axes"], dtype=np.float64),
            mu=np.asarray(lights["mu"], dtype=np.float64),
            directional=np.asarray(lights["directional"], dtype=bool),
        )

    def _core_lights(self) -> dict[str, list[Any]]:
        """The lights in the form the compiled core takes."""
        return {
            "vectors": self.lights.tolist(),
            "directional": self.directional.tolist(),  # type: ignore[union-attr]
            "intensities": self.intensities.tolist(),  # type: ignore[union-attr]
            "axes": self.directions.tolist(),  # type: ignore[union-attr]
            "mu": self.mu.tolist(),  # type: ignore[union-attr]
        }

    # -- files ----------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """The rig as the JSON-ready mapping of the rig file."""
        lights = []
        for i in range(self.n_lights):
            phi = [float(v) for v in self.intensities[i]]  # type: ignore[index]
            intensity: Any = phi[0] if phi[0] == phi[1] == phi[2] else phi
            vector = [float(v) for v in self.lights[i]]
            if self.directional[i]:  # type: ignore[index]
                lights.append({"type": "directional", "direction": vector, "intensity": intensity})
                continue
            light: dict[str, Any] = {"type": "point", "position": vector, "intensity": intensity}
            if self.mu[i] > 0:  # type: ignore[index]
                light["direction"] = [float(v) for v in self.directions[i]]  # type: ignore[index]
                light["mu"] = float(self.mu[i])  # type: ignore[index]
            lights.append(light)
        return {"version": RIG_FILE_VERSION, "camera": dict(self.camera), "lights": lights}

    @classmethod
    def from_dict(cls, data: Any, source: str = "rig") -> "Rig":
        """Reads the mapping of a rig file; raises :class:`RigError` naming what is wrong."""
        if not isinstance(data, dict):
            raise RigError(f"{source}: a rig file holds a JSON object, got {type(data).__name__}")
        missing = [k for k in ("version", "camera", "lights") if k not in data]
        if missing:
            raise RigError(f"{source}: missing key(s) {', '.join(missing)}")
        version = data["version"]
        if not isinstance(version, int) or isinstance(version, bool) or version < 1 or version > RIG_FILE_VERSION:
            raise RigError(f"{source}: unsupported rig file version {version!r} (this nplps reads 1..{RIG_FILE_VERSION})")
        camera = data["camera"]
        if not isinstance(camera, dict) or "model" not in camera:
            raise RigError(f"{source}: 'camera' must be an object with a 'model' key")
        lights = data["lights"]
        if not isinstance(lights, list):
            raise RigError(f"{source}: 'lights' must be a list of objects with a 'position'")
        vectors, phis, axes, mus, flags = [], [], [], [], []
        for i, light in enumerate(lights):
            where = f"{source}: light {i}"
            if not isinstance(light, dict):
                raise RigError(f"{where} must be an object")
            kind = light.get("type", "point")
            if kind not in ("point", "directional"):
                raise RigError(f"{where} has unknown type {kind!r} (point or directional)")
            key = "position" if kind == "point" else "direction"
            vectors.append(_vector(light.get(key), f"{where} {key}"))
            phis.append(_intensities(light.get("intensity", 1.0), 1, where)[0])
            axis = light.get("direction") if kind == "point" else None
            axes.append([0.0, 0.0, 0.0] if axis is None else _vector(axis, f"{where} direction"))
            try:
                mus.append(float(light.get("mu", 0.0)) if kind == "point" else 0.0)
            except (TypeError, ValueError):
                raise RigError(f"{where}: 'mu' must be a number") from None
            if mus[-1] > 0 and axis is None:
                # An LED's falloff about its axis: without the axis its brightness is unknown.
                raise RigError(f"{where}: an anisotropic LED (mu = {mus[-1]:.6g}) needs its principal 'direction'")
            flags.append(kind == "directional")
        if camera["model"] == "orthographic":
            for key in ("pixel_size", "origin"):
                if key not in camera:
                    raise RigError(f"{source}: orthographic camera needs '{key}'")
                _pair(camera[key], f"{source}: camera.{key}")
        elif camera["model"] == "pinhole" and "K" not in camera:
            raise RigError(f"{source}: pinhole camera needs 'K'")
        return cls(
            camera=dict(camera),
            lights=np.array(vectors, dtype=np.float64).reshape(-1, 3),
            intensities=np.array(phis).reshape(-1, 3),
            directions=np.array(axes).reshape(-1, 3),
            mu=np.array(mus),
            directional=np.array(flags, dtype=bool),
        )

    def save(self, path: str | os.PathLike[str]) -> None:
        """Writes the rig file (JSON), under a temporary name renamed when complete."""
        from ._atomic import atomic_write

        with atomic_write(path, "w", encoding="utf-8") as f:
            json.dump(self.to_dict(), f, indent=2)
            f.write("\n")

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> "Rig":
        """Reads a rig file; raises :class:`RigError` when it is missing or malformed."""
        if not isinstance(path, (str, bytes, os.PathLike)):
            raise RigError(f"a rig file is read from a path (str or os.PathLike), got {type(path).__name__}")
        try:
            with open(path, encoding="utf-8") as f:
                data = json.load(f)
        except OSError as e:
            raise RigError(f"cannot read rig file {os.fspath(path)!r}: {e.strerror}") from None
        except json.JSONDecodeError as e:
            raise RigError(f"rig file {os.fspath(path)!r} is not valid JSON: {e}") from None
        except UnicodeDecodeError:
            raise RigError(f"rig file {os.fspath(path)!r} is not a JSON text file") from None
        return cls.from_dict(data, source=os.fspath(path))


def _pair(value: Any, name: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in value)
    except (TypeError, ValueError):
        raise RigError(f"{name} must be two numbers, got {value!r}") from None
    return a, b


def _vector(value: Any, what: str) -> list[float]:
    try:
        v = [float(x) for x in value]
    except (TypeError, ValueError):
        raise RigError(f"{what} must be 3 numbers, got {value!r}") from None
    if len(v) != 3:
        raise RigError(f"{what} must have 3 numbers, got {len(v)}")
    return v


def _array(value: Any, name: str, shape: tuple[int, ...]) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise RigError(f"{name} must be numbers") from None
    if a.size == 0 and shape[0] == -1:
        return np.zeros((0,) + shape[1:])
    expected = tuple(a.shape[0] if s == -1 and a.ndim else s for s in shape)
    if a.shape != expected:
        text = "(" + ", ".join("k" if s == -1 else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        raise RigError(f"{name} must be a {text} array, got shape {a.shape}")
    return np.ascontiguousarray(a)


def _intensities(value: Any, k: int, where: str = "intensities") -> np.ndarray:
    """Per-light RGB intensities (k, 3) from None (ones), a number, (k,) or (k, 3)."""
    if value is None:
        return np.ones((k, 3))
    if isinstance(value, (list, tuple)) and len(value) == k and any(np.ndim(v) == 1 for v in value):
        return np.vstack([_intensities(v, 1, f"{where} (light {i})") for i, v in enumerate(value)])
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise RigError(f"{where}: intensity must be a number or three numbers (R, G, B)") from None
    if a.ndim == 0:
        return np.full((k, 3), float(a))
    if k == 1 and a.shape == (3,):
        return a.reshape(1, 3)
    if a.shape == (k,):
        return np.repeat(a[:, None], 3, axis=1)
    if a.shape == (k, 3):
        return np.ascontiguousarray(a)
    if a.shape == (k, 1):
        return np.repeat(a, 3, axis=1)
    raise RigError(f"{where}: intensities must be a number, (k,) or (k, 3) for {k} lights, got shape {a.shape}")
