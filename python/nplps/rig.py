"""The rig: camera model and light positions, and the JSON rig file.

Rig file (JSON), version 1::

    {
      "version": 1,
      "camera": {"model": "orthographic", "pixel_size": [w, h], "origin": [ox, oy]},
      "lights": [{"position": [x, y, z]}, ...]
    }

Camera frame as in OpenCV (x right, y down, z forward into the scene). ``pixel_size`` is the
footprint (w, h) of one pixel on the object and ``origin`` the scene (x, y) of the top-left
corner of pixel (0, 0), in the same unit as the light positions (mm typical). Later versions add
keys to ``camera`` and to each light; readers ignore keys they do not know.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from . import _core
from .errors import RigError

RIG_FILE_VERSION = 1


@dataclass(frozen=True)
class Rig:
    """A calibrated rig: one camera and k point lights (positions in the camera frame)."""

    camera: dict[str, Any]
    lights: np.ndarray = field(repr=False)

    def __post_init__(self) -> None:
        lights = np.ascontiguousarray(np.asarray(self.lights, dtype=np.float64))
        if lights.ndim != 2 or lights.shape[1] != 3:
            raise RigError(f"lights must be a (k, 3) array of positions, got shape {lights.shape}")
        object.__setattr__(self, "lights", lights)
        _core.check_rig(self.camera, lights)

    @classmethod
    def orthographic(
        cls,
        pixel_size: float | Sequence[float],
        origin: Sequence[float] = (0.0, 0.0),
        lights: Sequence[Sequence[float]] | np.ndarray = (),
    ) -> "Rig":
        """The paper's orthographic camera looking along +z.

        Args:
            pixel_size: footprint (w, h) of a pixel on the object, or one number for square pixels.
            origin: scene (x, y) of the top-left corner of pixel (0, 0).
            lights: (k, 3) light positions; lights stand in front of the object (smaller z).
        """
        if np.isscalar(pixel_size):
            pixel_size = (pixel_size, pixel_size)  # type: ignore[assignment]
        w, h = _pair(pixel_size, "pixel_size")
        ox, oy = _pair(origin, "origin")
        camera = {"model": "orthographic", "pixel_size": [w, h], "origin": [ox, oy]}
        return cls(camera=camera, lights=np.asarray(lights, dtype=np.float64).reshape(-1, 3))

    @property
    def n_lights(self) -> int:
        """Number of lights k."""
        return int(self.lights.shape[0])

    def to_dict(self) -> dict[str, Any]:
        """The rig as the JSON-ready mapping of the rig file."""
        return {
            "version": RIG_FILE_VERSION,
            "camera": dict(self.camera),
            "lights": [{"position": [float(v) for v in p]} for p in self.lights],
        }

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
        positions = []
        for i, light in enumerate(lights):
            try:
                position = [float(v) for v in light["position"]]
            except (TypeError, KeyError, ValueError) as e:
                raise RigError(f"{source}: light {i} needs a 'position' of 3 numbers ({e})") from None
            if len(position) != 3:
                raise RigError(f"{source}: light {i} position must have 3 numbers, got {len(position)}")
            positions.append(position)
        if camera["model"] == "orthographic":
            for key in ("pixel_size", "origin"):
                if key not in camera:
                    raise RigError(f"{source}: orthographic camera needs '{key}'")
                _pair(camera[key], f"{source}: camera.{key}")
        return cls(camera=dict(camera), lights=np.array(positions, dtype=np.float64).reshape(-1, 3))

    def save(self, path: str | os.PathLike[str]) -> None:
        """Writes the rig file (JSON)."""
        with open(path, "w", encoding="utf-8") as f:
            json.dump(self.to_dict(), f, indent=2)
            f.write("\n")

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> "Rig":
        """Reads a rig file; raises :class:`RigError` when it is missing or malformed."""
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
