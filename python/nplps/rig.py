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
(pixel (r, c) has its centre at (u, v) = (c, r)) and OpenCV's distortion model (also as OpenCV's
1 x n or n x 1 matrix ``[[k1, k2, p1, p2, k3]]``; 2, 4 or 5 coefficients, missing ones zero, or
8, 12 or 14 whose rational, thin-prism and tilt terms are zero; 3 are ambiguous and refused).

Camera frame as in OpenCV (x right, y down, z forward into the scene), in the user's unit (mm
typical). A point light (LED) at ``position`` emits ``intensity`` (a number, or R, G, B) around
its principal ``direction`` (unit, from the LED towards the scene) with anisotropy ``mu`` (0, the
default, is an isotropic point light):
``I = rho * intensity * ((x - p) . d / |x - p|)^mu * max(0, n . (p - x)) / |p - x|^3``.
A directional light has a unit ``direction`` from the surface towards the light and gives
``I = rho * intensity * max(0, n . direction)``.

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
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from . import _core, _core_types
from .errors import RigError

RIG_FILE_VERSION = 2
#: Largest rig file read (bytes).
MAX_RIG_FILE_BYTES = 16 * 2**20
#: Deepest nesting of arrays and objects in a rig file.
MAX_NESTING = 64
#: Most lights of a rig.
MAX_LIGHTS: int = _core.MAX_LIGHTS

_TOP_KEYS = ("version", "camera", "lights")
_LIGHT_KEYS = {
    "point": ("type", "position", "intensity", "direction", "mu"),
    "directional": ("type", "direction", "intensity"),
}

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
        if not isinstance(self.camera, Mapping):
            raise RigError(f"camera must be a mapping (the rig file's camera object), got {_describe(self.camera)}")
        set_ = lambda name, value: object.__setattr__(self, name, value)  # noqa: E731
        # The compiled core checks the camera (every key) and gives its canonical form.
        set_("camera", _core.normalize_camera(dict(self.camera)))
        lights = _array(self.lights, "lights", (-1, 3))
        k = lights.shape[0]
        if k > MAX_LIGHTS:
            raise RigError(f"the rig has {k} lights; at most {MAX_LIGHTS} are supported")
        directions_given = self.directions is not None
        set_("lights", lights)
        set_("intensities", _intensities(self.intensities, k))
        set_("mu", np.zeros(k) if self.mu is None else _array(self.mu, "mu", (k,)))
        directions = np.zeros((k, 3)) if self.directions is None else _array(self.directions, "directions", (k, 3))
        if not np.isfinite(directions).all():
            i = int(np.argmax(~np.isfinite(directions).all(axis=1)))
            shown = ", ".join(f"{v:.6g}" for v in directions[i])
            raise RigError(f"light {i} has a non-finite principal direction [{shown}]")
        # Scaled by the largest component first: the norm of a huge vector does not overflow.
        directions = directions / np.maximum(np.abs(directions).max(axis=1, keepdims=True, initial=0.0), 1e-300)
        norms = np.linalg.norm(directions, axis=1, keepdims=True)
        if not directions_given and np.any(self.mu > 0):  # type: ignore[operator]
            raise RigError("anisotropic LEDs (mu > 0) need their principal directions (directions=...)")
        zero = (self.mu > 0) & ~(norms[:, 0] > 0)  # type: ignore[operator]
        if np.any(zero):
            i = int(np.argmax(zero))
            raise RigError(f"light {i}: an anisotropic LED (mu = {self.mu[i]:.6g}) needs a non-zero principal direction")  # type: ignore[index]
        # An isotropic light's axis is unused; a zero one stands for +z.
        directions = np.where(norms > 0, directions / np.where(norms > 0, norms, 1.0), [0.0, 0.0, 1.0])
        set_("directions", np.ascontiguousarray(directions))
        directional = _flags(self.directional, k)
        set_("directional", directional)
        if np.any(directional):
            with np.errstate(over="ignore"):  # a huge vector is no unit vector either
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
        if np.isscalar(pixel_size) or (isinstance(pixel_size, np.ndarray) and pixel_size.ndim == 0):
            pixel_size = (pixel_size, pixel_size)  # type: ignore[assignment]
        # The compiled core checks the values and gives the canonical camera.
        camera = {"model": "orthographic", "pixel_size": pixel_size, "origin": origin}
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
            distortion: OpenCV coefficients (k1, k2[, p1, p2[, k3]]), flat or OpenCV's 1 x n or
                n x 1 matrix (8, 12 or 14 when the terms after k3 are zero); None for none.
            intensities: per light: a number, or R, G, B (default 1).
            directions: (k, 3) LED principal directions (from the LED towards the scene).
            mu: (k,) LED anisotropy (0 = isotropic, the default).
            directional_lights: (m, 3) unit directions (from the surface towards the light) of
                distant lights, appended after the point lights.
            directional_intensities: their intensities (a number or R, G, B each).
        """
        # The compiled core checks K and the distortion and gives their canonical form.
        camera: dict[str, Any] = {"model": "pinhole", "K": K}
        if distortion is not None:
            camera["distortion"] = distortion
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
            far = far / np.abs(far).max(axis=1, keepdims=True)  # no overflow in the norm
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

    def _core_lights(self) -> _core_types.LightsDict:
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
        """Reads the mapping of a rig file; raises :class:`RigError` naming what is wrong (see
        the module documentation for what is checked)."""
        if not isinstance(data, Mapping):
            raise RigError(f"{source}: a rig file holds a JSON object, got {_describe(data)}")
        _check_keys(data, _TOP_KEYS, source, "a rig file has version, camera and lights")
        missing = [k for k in _TOP_KEYS if k not in data]
        if missing:
            raise RigError(f"{source}: missing key(s) {', '.join(missing)}")
        version = data["version"]
        if not isinstance(version, int) or isinstance(version, bool):
            raise RigError(f"{source}: 'version' must be an integer, got {_describe(version)}")
        if version < 1 or version > RIG_FILE_VERSION:
            raise RigError(
                f"{source}: unsupported rig file version {_describe(version)} (this nplps reads 1..{RIG_FILE_VERSION})"
            )
        camera = data["camera"]
        if not isinstance(camera, Mapping) or "model" not in camera:
            raise RigError(f"{source}: 'camera' must be an object with a 'model' key, got {_describe(camera)}")
        lights = data["lights"]
        if not isinstance(lights, (list, tuple)):
            raise RigError(f"{source}: 'lights' must be a list of objects (one per light), got {_describe(lights)}")
        if len(lights) > MAX_LIGHTS:
            raise RigError(f"{source}: the rig has {len(lights)} lights; at most {MAX_LIGHTS} are supported")
        vectors, phis, axes, mus, flags = [], [], [], [], []
        for i, light in enumerate(lights):
            where = f"{source}: light {i}"
            if not isinstance(light, Mapping):
                raise RigError(f"{where} must be an object, got {_describe(light)}")
            kind = light.get("type", "point")
            if not isinstance(kind, str) or kind not in _LIGHT_KEYS:
                raise RigError(f"{where} has unknown type {_describe(kind)} (\"point\" or \"directional\")")
            known = _LIGHT_KEYS[kind]
            _check_keys(light, known, where, f"a {kind} light has {', '.join(known)}")
            key = "position" if kind == "point" else "direction"
            if key not in light:
                raise RigError(f"{where} is missing its '{key}'")
            vectors.append(_vector(light[key], f"{where} {key}"))
            phis.append(_intensity(light.get("intensity", 1.0), f"{where} intensity"))
            axis = light.get("direction") if kind == "point" else None
            axes.append([0.0, 0.0, 0.0] if axis is None else _vector(axis, f"{where} direction"))
            mus.append(_number(light.get("mu", 0.0), f"{where} mu"))
            if mus[-1] > 0 and axis is None:
                # An LED's falloff about its axis: without the axis its brightness is unknown.
                raise RigError(f"{where}: an anisotropic LED (mu = {mus[-1]:.6g}) needs its principal 'direction'")
            flags.append(kind == "directional")
        try:
            return cls(
                camera=dict(camera),
                lights=np.array(vectors, dtype=np.float64).reshape(-1, 3),
                intensities=np.array(phis, dtype=np.float64).reshape(-1, 3),
                directions=np.array(axes, dtype=np.float64).reshape(-1, 3),
                mu=np.array(mus, dtype=np.float64),
                directional=np.array(flags, dtype=bool),
            )
        except RigError as e:
            raise RigError(f"{source}: {e}") from None

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
        return cls.from_dict(read_rig_json(path), source=os.fspath(path))


def read_rig_json(path: str | os.PathLike[str]) -> Any:
    """The JSON value of a rig file, read within the limits of the format (at most
    :data:`MAX_RIG_FILE_BYTES` of UTF-8, nested at most :data:`MAX_NESTING` levels); raises
    :class:`RigError` when the file cannot be read or is not such a JSON text."""
    name = os.fspath(path)
    try:
        with open(path, "rb") as f:
            raw = f.read(MAX_RIG_FILE_BYTES + 1)
    except OSError as e:
        raise RigError(f"cannot read rig file {name!r}: {e.strerror}") from None
    if len(raw) > MAX_RIG_FILE_BYTES:
        raise RigError(f"rig file {name!r} is larger than {MAX_RIG_FILE_BYTES // 2**20} MiB: not a rig file")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise RigError(f"rig file {name!r} is not a JSON text file (not UTF-8)") from None
    depth = _nesting(text)
    if depth > MAX_NESTING:
        raise RigError(f"rig file {name!r} is nested too deeply ({depth} levels; at most {MAX_NESTING})")
    try:
        return json.loads(text)
    except RecursionError:
        raise RigError(f"rig file {name!r} is nested too deeply") from None
    except ValueError as e:  # JSONDecodeError, and integers of more than 4300 digits
        message = str(e)
        message = message if len(message) <= 200 else message[:200] + "..."
        raise RigError(f"rig file {name!r} is not valid JSON: {message}") from None


_JSON_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"', re.S)


def _nesting(text: str) -> int:
    """The deepest nesting of arrays and objects in the JSON text (brackets in strings left out)."""
    if text.count("[") + text.count("{") <= MAX_NESTING:
        return 0
    code = np.frombuffer(_JSON_STRING.sub('""', text).encode("utf-8"), dtype=np.uint8)
    brackets = code[(code == ord("[")) | (code == ord("{")) | (code == ord("]")) | (code == ord("}"))]
    if brackets.size == 0:
        return 0
    steps = np.where((brackets == ord("[")) | (brackets == ord("{")), 1, -1).astype(np.int32)
    return int(np.cumsum(steps).max())


def _describe(value: Any) -> str:
    """A short description of a value for messages: never its full repr, which may be huge or
    nested too deeply to print (the same words as the compiled core's)."""
    if value is None:
        return "null"
    if isinstance(value, (bool, np.bool_)):
        return f"the boolean {str(bool(value)).lower()}"
    if isinstance(value, str):
        return f"the string {json.dumps(value if len(value) <= 40 else value[:37] + '...')}"
    if isinstance(value, (list, tuple)):
        n = len(value)
        return f"a {type(value).__name__} of {n} item{'' if n == 1 else 's'}"
    if isinstance(value, Mapping):
        return "an object (mapping)"
    if isinstance(value, np.ndarray):
        return f"an array of shape {value.shape}"
    if isinstance(value, (int, float, np.integer, np.floating)):
        try:
            return f"{float(value):.6g}"
        except OverflowError:
            return "an integer too large for a floating-point number"
    return f"a value of type {type(value).__name__}"


def _check_keys(mapping: Mapping[Any, Any], known: Sequence[str], where: str, usage: str) -> None:
    """Fails on a key that is not in ``known`` and does not start with '_' (a comment)."""
    for key in mapping:
        if not isinstance(key, str):
            raise RigError(f"{where} has a key that is not a string ({_describe(key)})")
        if not (key.startswith("_") or key in known):
            raise RigError(f"{where} has an unknown key {_describe(key)[11:]} ({usage}; keys starting with '_' are comments)")


def _number(value: Any, what: str) -> float:
    """A finite number: an int or a float (numpy scalars too), not a boolean or a string."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise RigError(f"{what} must be a number, got {_describe(value)}")
    try:
        x = float(value)
    except OverflowError:
        raise RigError(f"{what} is an integer too large for a floating-point number") from None
    if not math.isfinite(x):
        raise RigError(f"{what} must be a finite number, got {x:.6g}")
    return x


def _vector(value: Any, what: str) -> list[float]:
    """Three finite numbers."""
    if isinstance(value, np.ndarray) and value.ndim == 1:
        value = list(value)
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise RigError(f"{what} must be 3 numbers, got {_describe(value)}")
    return [_number(v, f"{what}[{i}]") for i, v in enumerate(value)]


def _intensity(value: Any, what: str) -> list[float]:
    """One light's intensity: a number, or three (R, G, B)."""
    if isinstance(value, (list, tuple, np.ndarray)):
        return _vector(value, what)
    x = _number(value, what)
    return [x, x, x]


def _flags(value: Any, k: int) -> np.ndarray:
    """One boolean per light (None: all False)."""
    if value is None:
        return np.zeros(k, dtype=bool)
    try:
        a = _numeric(value, "directional", kinds="biu")
    except RigError:
        a = None
    if a is None or a.shape != (k,) or (a.dtype.kind != "b" and not np.isin(a, (0, 1)).all()):
        raise RigError(f"directional must have one flag (True or False) per light ({k}), got {_describe(value)}")
    return a.astype(bool)


def _numeric(value: Any, name: str, kinds: str = "iuf") -> np.ndarray:
    """``value`` as an array of numbers of the dtype kinds ``kinds`` (not strings, objects or,
    unless asked, booleans)."""
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
        return np.zeros((0,) + shape[1:])
    expected = tuple(a.shape[0] if s == -1 and a.ndim else s for s in shape)
    if a.shape != expected:
        text = "(" + ", ".join("k" if s == -1 else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        raise RigError(f"{name} must be a {text} array, got shape {a.shape}")
    return np.ascontiguousarray(a)  # the compiled core checks that the values are finite


def _intensities(value: Any, k: int, where: str = "intensities") -> np.ndarray:
    """Per-light RGB intensities (k, 3) from None (ones), a number, (k,), (k, 1) or (k, 3), or a
    list of k items each a number or three (R, G, B)."""
    if value is None:
        return np.ones((k, 3))
    if isinstance(value, (list, tuple)) and k and len(value) == k and any(isinstance(v, (list, tuple, np.ndarray)) for v in value):
        rows = []
        for i, v in enumerate(value):
            a = _numeric(v, f"{where} (light {i})").astype(np.float64)
            if a.shape not in ((), (3,)):
                raise RigError(f"{where} (light {i}): intensity must be a number or three numbers (R, G, B), got shape {a.shape}")
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
