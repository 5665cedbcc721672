"""The values a rig is made of: its lights, its image grid, and the checked reading of rig files.

:class:`PointLight`, :class:`LED`, :class:`DirectionalLight` and :class:`RigGrid` (public as
``nplps.rig.*`` and ``nplps.*``), the checks of the values they are made from, and
:func:`read_small_text` / :func:`read_rig_json`, the bounded readers of rig, lights and camera
files. Below both :mod:`nplps.rig` (the :class:`~nplps.Rig` they make up) and the file formats'
codecs (:mod:`nplps._rig_codecs`), which build lights without knowing the rig. The rig file's
format and rules are in :mod:`nplps.rig`.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from . import _core_types
from ._files import NotRegularFile, open_regular
from .errors import RigError

#: Largest rig file read (bytes).
MAX_RIG_FILE_BYTES = 16 * 2**20


#: Deepest nesting of arrays and objects in a rig file.
MAX_NESTING = 64


ArrayLike = Any


#: Three floats: a position, a unit vector or an intensity per channel (R, G, B).
Vec3 = tuple[float, float, float]


#: The axis the compiled core is given for lights without one (it is unused there).
_NO_AXIS: Vec3 = (0.0, 0.0, 1.0)


_L = TypeVar("_L", "PointLight", "LED", "DirectionalLight")


def _vec3(value: Any, what: str) -> Vec3:
    """Three finite numbers (a list, tuple or 1-D array)."""
    x, y, z = _vector(value, what)
    return (x, y, z)


def _rgb(value: Any, subject: str) -> Vec3:
    """Return an intensity: a positive finite number or three (R, G, B)."""
    x, y, z = _intensity(value, f"{subject} intensity")
    if not (x > 0 and y > 0 and z > 0):
        raise RigError(f"{subject} must have positive intensities, got [{x:.6g}, {y:.6g}, {z:.6g}]")
    return (x, y, z)


def _unit(v: Vec3) -> Vec3:
    """Return ``v`` scaled to unit length; (0, 0, 0) stays zero.

    It is scaled by its largest component first, so that the norm of a huge vector does not
    overflow.
    """
    # The same operations (on a 1 x 3 array) as earlier versions of nplps, for the same bits.
    a = np.array([v], dtype=np.float64)
    a = a / np.maximum(np.abs(a).max(axis=1, keepdims=True), 1e-300)
    n = np.linalg.norm(a, axis=1, keepdims=True)
    if not n[0, 0] > 0:
        return (0.0, 0.0, 0.0)
    x, y, z = (a / n)[0].tolist()
    return (x, y, z)


def _is_unit(v: Vec3) -> bool:
    with np.errstate(over="ignore"):  # a huge vector is no unit vector either
        return bool(abs(float(np.linalg.norm(v)) - 1.0) <= 1e-6)


def _new(cls: type[_L], **values: Any) -> _L:
    """Return an instance of the frozen light type ``cls`` with the (checked) field ``values``."""
    obj = object.__new__(cls)
    for name, value in values.items():
        object.__setattr__(obj, name, value)
    return obj


@dataclass(frozen=True, init=False)
class PointLight:
    """An isotropic point light.

    Parameters
    ----------
    position : sequence of 3 float
        Position ``p`` in the camera frame (lights stand in front of the object: smaller z).
    intensity : float or sequence of 3 float, default 1
        Intensity, one number or R, G, B; stored as three floats.

    Raises
    ------
    RigError
        When a value is not a finite number, or an intensity is not positive.
    """

    #: Position in the camera frame.
    position: Vec3
    #: Intensity per channel (R, G, B).
    intensity: Vec3

    def __init__(self, position: ArrayLike, intensity: float | ArrayLike = 1.0) -> None:
        self._set(type(self).__name__, position, intensity)

    def _set(self, subject: str, position: Any, intensity: Any) -> None:
        object.__setattr__(self, "position", _vec3(position, f"{subject} position"))
        object.__setattr__(self, "intensity", _rgb(intensity, subject))

    @classmethod
    def _checked(cls, subject: str, position: Any, intensity: Any = 1.0) -> PointLight:
        """Return the light, its errors naming ``subject`` (such as ``light 3``)."""
        light = object.__new__(cls)
        light._set(subject, position, intensity)
        return light


@dataclass(frozen=True, init=False)
class LED:
    """A near point light with a principal axis (an anisotropic LED, Quéau et al. 2018).

    Parameters
    ----------
    position : sequence of 3 float
        Position ``p`` in the camera frame.
    intensity : float or sequence of 3 float, default 1
        Intensity, one number or R, G, B; stored as three floats.
    axis : sequence of 3 float
        Principal direction, from the LED towards the scene; scaled to unit length. A zero axis
        is refused when ``mu`` > 0 and stands for +z when ``mu`` = 0 (where it is unused).
    mu : float, default 1
        Anisotropy, >= 0 (0 emits like a :class:`PointLight`).

    Raises
    ------
    RigError
        When a value is not a finite number, an intensity is not positive, ``mu`` is negative, or
        the axis is zero while ``mu`` > 0.
    """

    #: Position in the camera frame.
    position: Vec3
    #: Intensity per channel (R, G, B).
    intensity: Vec3
    #: Unit principal direction, from the LED towards the scene.
    axis: Vec3
    #: Anisotropy (>= 0).
    mu: float

    def __init__(
        self, position: ArrayLike, intensity: float | ArrayLike = 1.0, *, axis: ArrayLike, mu: float = 1.0
    ) -> None:
        self._set(type(self).__name__, position, intensity, axis, mu)

    def _set(self, subject: str, position: Any, intensity: Any, axis: Any, mu: Any) -> None:
        m = _number(mu, f"{subject} mu")
        if m < 0:
            raise RigError(f"{subject} has anisotropy mu = {m:.6g}; it must be >= 0")
        a = _unit(_vec3(axis, f"{subject} axis"))
        if a == (0.0, 0.0, 0.0):
            if m > 0:
                raise RigError(f"{subject}: an anisotropic LED (mu = {m:.6g}) needs a non-zero axis")
            a = _NO_AXIS
        object.__setattr__(self, "position", _vec3(position, f"{subject} position"))
        object.__setattr__(self, "intensity", _rgb(intensity, subject))
        object.__setattr__(self, "axis", a)
        object.__setattr__(self, "mu", m)

    @classmethod
    def _checked(cls, subject: str, position: Any, intensity: Any, axis: Any, mu: Any) -> LED:
        """Return the LED, its errors naming ``subject`` (such as ``light 3``)."""
        light = object.__new__(cls)
        light._set(subject, position, intensity, axis, mu)
        return light


@dataclass(frozen=True, init=False)
class DirectionalLight:
    """A distant light (parallel rays, no falloff).

    Parameters
    ----------
    direction : sequence of 3 float
        Direction from the surface towards the light; scaled to unit length.
    intensity : float or sequence of 3 float, default 1
        Intensity, one number or R, G, B; stored as three floats.

    Raises
    ------
    RigError
        When a value is not a finite number, the direction is zero or an intensity is not
        positive.
    """

    #: Unit direction from the surface towards the light.
    direction: Vec3
    #: Intensity per channel (R, G, B).
    intensity: Vec3

    def __init__(self, direction: ArrayLike, intensity: float | ArrayLike = 1.0) -> None:
        self._set(type(self).__name__, direction, intensity, normalize=True)

    def _set(self, subject: str, direction: Any, intensity: Any, normalize: bool) -> None:
        d = _vec3(direction, f"{subject} direction")
        if normalize:
            d = _unit(d)
        if not _is_unit(d):
            raise RigError(
                f"{subject}: a directional light needs a unit direction (from the surface towards the light), "
                f"got [{', '.join(f'{v:.6g}' for v in d)}]"
            )
        object.__setattr__(self, "direction", d)
        object.__setattr__(self, "intensity", _rgb(intensity, subject))

    @classmethod
    def _checked(cls, subject: str, direction: Any, intensity: Any = 1.0, normalize: bool = True) -> DirectionalLight:
        """Return the light, its errors naming ``subject``.

        ``normalize=False`` checks that the direction is a unit vector (to 1e-6) and keeps it as
        given (rig files, results).
        """
        light = object.__new__(cls)
        light._set(subject, direction, intensity, normalize)
        return light


#: A light of a rig.
Light = PointLight | LED | DirectionalLight


_LIGHT_TYPES = (PointLight, LED, DirectionalLight)


def _kind(light: Light) -> _core_types.LightKind:
    """Return the compiled core's name of the light's type."""
    if isinstance(light, DirectionalLight):
        return "directional"
    return "led" if isinstance(light, LED) else "point"


def _with_position(light: Light, position: Any, subject: str) -> Light:
    if isinstance(light, DirectionalLight):
        raise RigError(f"{subject} is a directional light: it has no position")
    p = _vec3(position, f"{subject} position")
    if isinstance(light, LED):
        return _new(LED, position=p, intensity=light.intensity, axis=light.axis, mu=light.mu)
    return _new(PointLight, position=p, intensity=light.intensity)


def _with_intensity(light: Light, intensity: Any, subject: str) -> Light:
    phi = _rgb(intensity, subject)
    if isinstance(light, LED):
        return _new(LED, position=light.position, intensity=phi, axis=light.axis, mu=light.mu)
    if isinstance(light, PointLight):
        return _new(PointLight, position=light.position, intensity=phi)
    return _new(DirectionalLight, direction=light.direction, intensity=phi)


@dataclass(frozen=True)
class RigGrid:
    """The image grid a rig's camera belongs to.

    Attributes
    ----------
    image_size : (int, int) or None
        Width and height of the images, in pixels (None: not known, only the binning).
    binning : int
        Pixels of the original calibration grid that one pixel averages along each axis (1: the
        original grid; n after :meth:`Rig.binned` ``(n)``).
    """

    image_size: tuple[int, int] | None = None
    binning: int = 1

    def describe(self) -> str:
        """Return "640 x 480 pixels (binned 4 x 4)" and the like."""
        if self.image_size is None:
            size = "images of unknown size"
        else:
            size = f"{self.image_size[0]} x {self.image_size[1]} pixels"
        if self.binning > 1:
            size += f" (binned {self.binning} x {self.binning} from the calibration grid)"
        return size


def read_small_text(path: str | os.PathLike[str], what: str, kind: str = "text file") -> str:
    """Return the UTF-8 text of a file of at most :data:`MAX_RIG_FILE_BYTES` (rig, lights, camera files).

    ``what`` names the file in messages (``"rig file"``, ``".lp file"``) and ``kind`` what it should
    be (``"JSON text file"``). A leading byte-order mark is dropped.

    Raises
    ------
    RigError
        The file cannot be read, is larger than the limit or is not UTF-8.
    """
    name = os.fspath(path)
    try:
        # A device or FIFO is refused before it is read (see _files.open_regular).
        f, _ = open_regular(path)
        with f:
            raw = f.read(MAX_RIG_FILE_BYTES + 1)
    except NotRegularFile as e:
        raise RigError(f"cannot read {what} {name!r}: not a regular file (it is {e})") from None
    except OSError as e:
        raise RigError(f"cannot read {what} {name!r}: {e.strerror}") from None
    if len(raw) > MAX_RIG_FILE_BYTES:
        raise RigError(f"{what} {name!r} is larger than {MAX_RIG_FILE_BYTES // 2**20} MiB: not a {what}")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise RigError(f"{what} {name!r} is not a {kind} (not UTF-8)") from None


def read_rig_json(path: str | os.PathLike[str]) -> Any:
    """Return the JSON value of a rig file, read within the limits of the format.

    Parameters
    ----------
    path : str or os.PathLike
        The file: at most :data:`MAX_RIG_FILE_BYTES` of UTF-8 (a byte order mark is allowed),
        nested at most :data:`MAX_NESTING` levels.

    Returns
    -------
    Any
        The parsed JSON value (not checked as a rig: see :meth:`Rig.from_dict`).

    Raises
    ------
    RigError
        When the file cannot be read or is not such a JSON text.
    """
    name = os.fspath(path)
    text = read_small_text(path, "rig file", "JSON text file")
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
    """Return the deepest nesting of arrays and objects in the JSON text (brackets in strings left out)."""
    if text.count("[") + text.count("{") <= MAX_NESTING:
        return 0
    code = np.frombuffer(_JSON_STRING.sub('""', text).encode("utf-8"), dtype=np.uint8)
    brackets = code[(code == ord("[")) | (code == ord("{")) | (code == ord("]")) | (code == ord("}"))]
    if brackets.size == 0:
        return 0
    steps = np.where((brackets == ord("[")) | (brackets == ord("{")), 1, -1).astype(np.int32)
    return int(np.cumsum(steps).max())


def _describe(value: Any) -> str:
    """Return a short description of a value for messages.

    Never its full repr, which may be huge or nested too deeply to print (the same words as the
    compiled core's).
    """
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


def _number(value: Any, what: str) -> float:
    """Return a finite number: an int or a float (numpy scalars too), not a boolean or a string."""
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


def core_grid(grid: tuple[Any, int] | None) -> RigGrid | None:
    """Return the grid of the compiled core's reading of a rig file (``(size or None, binning)``)."""
    if grid is None:
        return None
    size, binning = grid
    return RigGrid(None if size is None else (size[0], size[1]), binning)


def checked_camera(camera: dict[str, Any]) -> dict[str, Any]:
    """Return a rig file's camera mapping checked by the compiled core, in its canonical form.

    As a :class:`~nplps.Rig` made with it would hold it (with three point lights, which the core
    checks along; a camera error is a :class:`RigError`).
    """
    from . import _core

    points = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    lights: _core_types.LightsDict = {
        "vectors": points,
        "directional": [False] * 3,
        "intensities": [[1.0, 1.0, 1.0]] * 3,
        "axes": [list(_NO_AXIS)] * 3,
        "mu": [0.0] * 3,
        "kind": ["point"] * 3,
    }
    return dict(_core.Rig(dict(camera), lights).camera)


# The public home of the values is nplps.rig (pickles, help() and the documentation name it).
for _public in (PointLight, LED, DirectionalLight, RigGrid):
    _public.__module__ = "nplps.rig"
