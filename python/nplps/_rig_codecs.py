"""The codecs of the rig interchange formats (see :mod:`nplps.rig_formats`, their public face).

Readers return lights (:class:`~nplps.PointLight`, :class:`~nplps.LED`,
:class:`~nplps.DirectionalLight`), camera mappings and :class:`~nplps.RigGrid` values; writers read
a rig's lights, camera, grid and comments (:class:`RigParts`). Neither knows the
:class:`~nplps.Rig` class: :mod:`nplps.rig` (``Rig.load`` / ``Rig.save``) combines them into rigs,
above this module, and :mod:`nplps.rig_formats` offers both. The formats' conventions are in the
documentation of :mod:`nplps.rig_formats` and in ``docs/formats.md``.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from decimal import Decimal, localcontext
from fractions import Fraction
from typing import Any, Protocol

from ._atomic import write_text
from ._rig_values import (
    LED,
    DirectionalLight,
    Light,
    PointLight,
    RigGrid,
    checked_camera,
    core_grid,
    read_rig_json,
    read_small_text,
)
from .errors import RigError

#: The formats, by name: what :func:`load` reads and :func:`save` writes.
FORMATS = ("rig", "dome", "lp", "alicevision", "sfmdata", "opencv-yaml", "opencv-json")

_EXTENSIONS = {".dome": "dome", ".lp": "lp", ".yml": "opencv-yaml", ".yaml": "opencv-yaml", ".sfm": "sfmdata"}
_UNIT_TOLERANCE = 1e-6


class RigParts(Protocol):
    """What the writers read of a rig (a :class:`nplps.Rig`)."""

    @property
    def camera(self) -> dict[str, Any]: ...
    @property
    def lights(self) -> tuple[Light, ...]: ...
    @property
    def grid(self) -> RigGrid | None: ...
    @property
    def comments(self) -> dict[str, Any]: ...
    @property
    def n_lights(self) -> int: ...


# --------------------------------------------------------------------------------------------------
# Numbers
# --------------------------------------------------------------------------------------------------


class _Raw(str):
    """A number already written as JSON/YAML text (kept as is by :func:`_dump_json`)."""


def _fraction(value: Any, what: str) -> Fraction:
    """Return a finite number of a file (a number, a Decimal or a numeric string) exactly."""
    if isinstance(value, bool) or value is None:
        raise RigError(f"{what} must be a number, got {json.dumps(value)}")
    try:
        if isinstance(value, str):
            value = Decimal(value.strip())
        if isinstance(value, Decimal) and not value.is_finite():
            raise ValueError
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError
        return Fraction(value)
    except (ValueError, TypeError, ArithmeticError):
        shown = value if isinstance(value, str) and len(value) <= 40 else type(value).__name__
        raise RigError(f"{what} must be a finite number, got {shown!r}") from None


def _number(value: Any, what: str) -> float:
    """Return a number of a file as the nearest double."""
    return float(_fraction(value, what))


def _shortest(target: float, ideal: Fraction, back: Callable[[Fraction], float]) -> _Raw:
    """Return the shortest decimal ``s`` near ``ideal`` with ``back(s) == target``.

    Used where the file holds a value that nplps maps to its own by an offset or a reciprocal:
    the decimal written then reads back to exactly ``target``.
    """
    sign = "-" if ideal < 0 else ""
    magnitude = abs(ideal)
    for digits in range(1, 60):
        if magnitude == 0:
            text = "0"
        else:
            with localcontext() as ctx:
                ctx.prec = digits
                text = format(Decimal(magnitude.numerator) / Decimal(magnitude.denominator), "g")
        candidate = sign + text if text != "0" else "0"
        if back(Fraction(Decimal(candidate))) == target:
            return _Raw(candidate)
    raise RigError(f"cannot write {target!r} exactly")  # pragma: no cover - 59 digits always suffice


def _text(x: float) -> _Raw:
    """Return the shortest text of a double that reads back to it (0.0 for -0.0)."""
    return _Raw(repr(float(x) + 0.0))


def _dump_json(value: Any, indent: int = 0) -> str:
    """Write JSON with :class:`_Raw` numbers as given and floats as their shortest text."""
    pad, inner = " " * indent, " " * (indent + 4)
    if isinstance(value, _Raw):
        return str(value)
    if isinstance(value, Mapping):
        if not value:
            return "{}"
        items = [f"{inner}{json.dumps(str(k))}: {_dump_json(v, indent + 4)}" for k, v in value.items()]
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(value, (list, tuple)):
        if not value:
            return "[]"
        if all(isinstance(v, (int, float, _Raw)) and not isinstance(v, bool) for v in value):
            return "[" + ", ".join(_dump_json(v) for v in value) + "]"
        return "[\n" + ",\n".join(inner + _dump_json(v, indent + 4) for v in value) + "\n" + pad + "]"
    if isinstance(value, float):
        return repr(value)
    return json.dumps(value)


def _is_unit(v: Sequence[float]) -> bool:
    return abs(math.sqrt(sum(x * x for x in v)) - 1.0) <= _UNIT_TOLERANCE


def _directional(subject: str, d: Sequence[float], intensity: Any = 1.0) -> DirectionalLight:
    """Return a directional light; a direction within 1e-6 of unit length is kept bit for bit."""
    return DirectionalLight._checked(subject, list(d), intensity, normalize=not _is_unit(d))


# --------------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------------


def _read_json(path: str | os.PathLike[str], what: str, exact: bool = False) -> Any:
    text = read_small_text(path, what)
    try:
        if exact:
            return json.loads(text, parse_float=Decimal, parse_int=Decimal)
        return json.loads(text)
    except (ValueError, RecursionError) as e:
        raise RigError(f"{what} {os.fspath(path)!r} is not valid JSON: {str(e)[:200]}") from None


def detect_format(path: str | os.PathLike[str]) -> str:
    """Return the format of a rig, lights or camera file (one of :data:`FORMATS`).

    By extension (``.dome``, ``.lp``, ``.yml``/``.yaml``, ``.sfm``); a ``.json`` file by its
    keys: ``"camera_matrix"`` (OpenCV), ``"views"`` and ``"intrinsics"`` (SfMData), ``"lights"``
    whose entries have a ``"lightId"`` or ``"viewId"`` and no ``"camera"`` or ``"version"``
    (AliceVision; without ids, say ``fmt="alicevision"``), anything else a rig file.

    Parameters
    ----------
    path : str or os.PathLike
        The file.

    Returns
    -------
    str
    """
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext in _EXTENSIONS:
        return _EXTENSIONS[ext]
    if ext != ".json":
        return "rig"
    try:
        data = read_rig_json(path)
    except RigError:
        return "rig"  # the rig file reader says what is wrong
    if not isinstance(data, dict):
        return "rig"
    if "camera_matrix" in data:
        return "opencv-json"
    if "views" in data and "intrinsics" in data:
        return "sfmdata"
    lights = data.get("lights")
    if "camera" not in data and "version" not in data and isinstance(lights, list):
        if any(isinstance(e, dict) and ("lightId" in e or "viewId" in e) for e in lights):
            return "alicevision"
    return "rig"


def output_format(path: str | os.PathLike[str], fmt: str | None) -> str:
    if fmt is not None:
        if fmt not in FORMATS:
            raise RigError(f"unknown format {fmt!r}; the formats are {', '.join(FORMATS)}")
        return fmt
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext in _EXTENSIONS:
        return _EXTENSIONS[ext]
    if ext == ".json" and os.path.basename(os.fspath(path)).lower() == "lights.json":
        return "alicevision"
    return "rig"


# --------------------------------------------------------------------------------------------------
# Loading and saving rigs
# --------------------------------------------------------------------------------------------------


FORMAT_NAMES = {
    "dome": "RelightLab .dome",
    "lp": ".lp light file",
    "alicevision": "AliceVision lights.json",
    "rig": "rig file",
}


def _kinds(rig: RigParts) -> tuple[bool, bool, int | None]:
    """Return (all directional, all point lights (not LEDs), index of the first LED or None)."""
    directional = all(isinstance(light, DirectionalLight) for light in rig.lights)
    point = all(type(light) is PointLight for light in rig.lights)
    led = next((i for i, light in enumerate(rig.lights) if isinstance(light, LED)), None)
    return directional, point, led


def _comment(rig: RigParts, key: str) -> Any:
    value = rig.comments.get(key)
    return value if isinstance(value, dict) else {}


# --------------------------------------------------------------------------------------------------
# RelightLab .dome
# --------------------------------------------------------------------------------------------------

_DOME_CONFIGS = ("directional", "spherical", "lights3d")
_DOME_META = ("label", "notes", "imageWidth", "domeDiameter", "verticalOffset")


def _xyz(item: Any, what: str) -> tuple[Fraction, Fraction, Fraction]:
    if not isinstance(item, dict) or not all(k in item for k in "xyz"):
        raise RigError(f"{what} must be an object with x, y and z")
    return _fraction(item["x"], f"{what}.x"), _fraction(item["y"], f"{what}.y"), _fraction(item["z"], f"{what}.z")


def _positive(value: float | None, what: str) -> Fraction:
    if value is None or isinstance(value, bool) or not math.isfinite(float(value)) or float(value) <= 0:
        raise RigError(f"{what} must be a positive number, got {value!r}")
    return Fraction(float(value))


def read_dome(
    name: str, camera_distance: float | None, light_distance: float | None, scale: float | None = None
) -> tuple[list[Any], dict]:
    data = _read_json(name, "dome file", exact=True)
    if not isinstance(data, dict):
        raise RigError(f"dome file {name!r} must hold a JSON object")
    config = str(data.get("lightConfiguration", "directional"))
    if config not in _DOME_CONFIGS:
        raise RigError(f"dome file {name!r}: lightConfiguration {config!r} is not one of {', '.join(_DOME_CONFIGS)}")
    key = {"directional": "directions", "spherical": "positionsSphere", "lights3d": "positions3d"}[config]
    items = data.get(key)
    if not isinstance(items, list) or not items:
        raise RigError(f"dome file {name!r}: lightConfiguration is {config!r} but {key!r} is missing or empty")
    adjust = data.get("ledAdjust") or []
    if adjust and (not isinstance(adjust, list) or len(adjust) != len(items)):
        raise RigError(f"dome file {name!r}: ledAdjust must have one entry per light ({len(items)})")
    intensities: list[Any] = []
    for i, a in enumerate(adjust):
        if not isinstance(a, dict) or not all(c in a for c in "rgb"):
            raise RigError(f"dome file {name!r}: ledAdjust[{i}] must be an object with r, g and b")
        rgb = [_fraction(a[c], f"ledAdjust[{i}].{c}") for c in "rgb"]
        if not all(v > 0 for v in rgb):
            raise RigError(f"dome file {name!r}: ledAdjust[{i}] must be positive")
        intensities.append([float(1 / v) for v in rgb])
    if not intensities:
        intensities = [1.0] * len(items)
    lights: list[Any] = []
    meta: dict[str, Any] = {"lightConfiguration": config}
    for k in _DOME_META:
        if k in data:
            v = data[k]
            meta[k] = float(v) if isinstance(v, Decimal) else v
    if config == "directional" and light_distance is None:
        for i, item in enumerate(items):
            x, y, z = _xyz(item, f"{key}[{i}]")
            lights.append(_directional(f"light {i}", [float(x), -float(y) + 0.0, -float(z) + 0.0], intensities[i]))
        return lights, {"_dome": meta}
    if camera_distance is None:
        raise RigError(
            f"dome file {name!r} holds light positions in the dome's frame (origin on the object plane, z up): "
            "give the camera's distance to that plane (camera_distance, --camera-distance) to place them"
        )
    dist = _positive(camera_distance, "camera_distance")
    unit = Fraction(1) if scale is None else _positive(scale, "scale")
    meta["camera_distance"] = float(dist)
    if unit != 1:
        meta["scale"] = float(unit)
    for i, item in enumerate(items):
        x, y, z = _xyz(item, f"{key}[{i}]")
        if config == "directional":  # unit directions placed at light_distance (rig units)
            assert light_distance is not None
            r = _positive(light_distance, "light_distance")
            n = math.sqrt(float(x * x + y * y + z * z))
            x, y, z = Fraction(float(x) / n) * r, Fraction(float(y) / n) * r, Fraction(float(z) / n) * r
        else:  # positions in the .dome's unit (exact rational products, rounded once)
            x, y, z = x * unit, y * unit, z * unit
        lights.append(PointLight._checked(f"light {i}", [float(x), -float(y) + 0.0, float(dist - z)], intensities[i]))
    return lights, {"_dome": meta}


def dome_text(rig: RigParts, camera_distance: float | None, scale: float | None = None) -> str:
    directional, point, led = _kinds(rig)
    if led is not None:
        raise RigError(
            f"light {led} is an LED (axis and anisotropy): a .dome cannot hold them; write a rig file (.json)"
        )
    if not (directional or point):
        raise RigError("the rig mixes point and directional lights: a .dome holds one kind; write a rig file (.json)")
    meta = _comment(rig, "_dome")
    dome: dict[str, Any] = {
        "label": str(meta.get("label", "nplps")),
        "notes": str(meta.get("notes", "")),
        "imageWidth": float(meta.get("imageWidth", 0.0)),
        "domeDiameter": float(meta.get("domeDiameter", 0.0)),
        "verticalOffset": float(meta.get("verticalOffset", 0.0)),
    }
    adjust = [
        {c: _shortest(v, 1 / Fraction(v), lambda s: float(1 / s)) for c, v in zip("rgb", light.intensity, strict=True)}
        for light in rig.lights
    ]
    if directional:
        dirs = [light.direction for light in rig.lights if isinstance(light, DirectionalLight)]
        dome["lightConfiguration"] = "directional"
        dome["directions"] = [{"x": _text(d[0]), "y": _text(-d[1]), "z": _text(-d[2])} for d in dirs]
        dome["ledAdjust"] = adjust
        return _dump_json(dome) + "\n"
    if camera_distance is None:
        camera_distance = meta.get("camera_distance")
    if camera_distance is None:
        raise RigError(
            "a .dome holds positions on the object plane's frame: give the camera's distance to that plane "
            "(camera_distance, --camera-distance)"
        )
    dist = _positive(camera_distance, "camera_distance")
    if scale is None:
        scale = meta.get("scale")
    unit = Fraction(1) if scale is None else _positive(scale, "scale")
    positions, directions = [], []
    for light in rig.lights:
        assert isinstance(light, PointLight)
        px, py, pz = light.position
        # The decimal whose reading (times the unit, from the plane) gives back the rig's double.
        z = _shortest(pz, (dist - Fraction(pz)) / unit, lambda s: float(dist - s * unit))
        if unit == 1:
            x, y = _text(px), _text(-py)
        else:
            x = _shortest(px, Fraction(px) / unit, lambda s: float(s * unit))
            y = _shortest(-py + 0.0, Fraction(-py) / unit, lambda s: -float(-s * unit) + 0.0)
        positions.append({"x": x, "y": y, "z": z})
        v = (px, -py, float(dist - Fraction(pz)))
        n = math.sqrt(sum(c * c for c in v)) or 1.0
        directions.append({"x": _text(v[0] / n), "y": _text(v[1] / n), "z": _text(v[2] / n)})
    dome["lightConfiguration"] = "lights3d"
    dome["directions"] = directions
    dome["positions3d"] = positions
    dome["ledAdjust"] = adjust
    return _dump_json(dome) + "\n"


# --------------------------------------------------------------------------------------------------
# .lp
# --------------------------------------------------------------------------------------------------


def read_lp(name: str, camera_distance: float | None, light_distance: float | None) -> tuple[list[Any], dict]:
    lines = [line for line in read_small_text(name, ".lp file").splitlines() if line.strip()]
    if not lines:
        raise RigError(f".lp file {name!r} is empty")
    try:
        count = int(lines[0].split()[0])
    except (ValueError, IndexError):
        raise RigError(
            f".lp file {name!r}: the first line must be the number of lights, got {lines[0][:40]!r}"
        ) from None
    if count < 1 or len(lines) - 1 != count:
        raise RigError(f".lp file {name!r} announces {count} lights but has {len(lines) - 1} light lines")
    files, dirs = [], []
    for i, line in enumerate(lines[1:]):
        tokens = line.split()
        if len(tokens) < 4:
            raise RigError(f".lp file {name!r}, line {i + 2}: expected 'file x y z', got {line[:60]!r}")
        files.append(" ".join(tokens[:-3]))
        x, y, z = (_number(t, f".lp file {name!r}, line {i + 2}") for t in tokens[-3:])
        if math.sqrt(x * x + y * y + z * z) < 1e-4:
            raise RigError(f".lp file {name!r}, line {i + 2}: the direction is zero")
        dirs.append((x, y, z))
    comments: dict[str, Any] = {"_lp_files": files}
    if light_distance is None:
        return [_directional(f"light {i}", [x, -y + 0.0, -z + 0.0]) for i, (x, y, z) in enumerate(dirs)], comments
    dist = _positive(camera_distance, "camera_distance")
    r = _positive(light_distance, "light_distance")
    lights = []
    for i, (x, y, z) in enumerate(dirs):
        n = math.sqrt(x * x + y * y + z * z)
        px, py, pz = (float(Fraction(c / n) * r) for c in (x, y, z))
        lights.append(PointLight._checked(f"light {i}", [px, -py + 0.0, float(dist - Fraction(pz))]))
    return lights, comments


def lp_text(rig: RigParts, drop_intensities: bool) -> str:
    directional, _, _ = _kinds(rig)
    if not directional:
        first = next(i for i, light in enumerate(rig.lights) if not isinstance(light, DirectionalLight))
        raise RigError(
            f"a .lp holds light directions only, and light {first} is a point light: write a .dome (with the "
            "camera distance) or a rig file (.json)"
        )
    if not drop_intensities and any(light.intensity != (1.0, 1.0, 1.0) for light in rig.lights):
        raise RigError(
            "a .lp holds no intensities and this rig's are not all 1: write a .dome or lights.json, or drop them "
            "(drop_intensities=True, --drop-intensities)"
        )
    files = rig.comments.get("_lp_files")
    if not (isinstance(files, list) and len(files) == rig.n_lights and all(isinstance(f, str) for f in files)):
        files = [f"image_{i:03d}" for i in range(rig.n_lights)]
    lines = [str(rig.n_lights)]
    for f, light in zip(files, rig.lights, strict=True):
        assert isinstance(light, DirectionalLight)
        x, y, z = light.direction
        lines.append(f"{f} {_text(x)} {_text(-y)} {_text(-z)}")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------------
# AliceVision lights.json
# --------------------------------------------------------------------------------------------------


def read_alicevision(name: str) -> tuple[list[Any], dict]:
    data = _read_json(name, "lights file", exact=True)
    items = data.get("lights") if isinstance(data, dict) else None
    if not isinstance(items, list) or not items:
        raise RigError(f'lights file {name!r} must be an object with a non-empty list "lights"')
    lights, ids = [], []
    for i, item in enumerate(items):
        what = f"lights file {name!r}, light {i}"
        if not isinstance(item, dict):
            raise RigError(f"{what} must be an object")
        kind = str(item.get("type", "directional"))
        if kind != "directional":
            raise RigError(f"{what} is of type {kind!r}: nplps reads directional lights only")
        d = item.get("direction")
        if not isinstance(d, list) or len(d) != 3:
            raise RigError(f'{what}: "direction" must be 3 numbers')
        phi = item.get("intensity", [1, 1, 1])
        phi = phi if isinstance(phi, list) else [phi] * 3
        if len(phi) != 3:
            raise RigError(f'{what}: "intensity" must be one number or 3 (R, G, B)')
        vec = [_number(v, f"{what} direction") for v in d]
        lights.append(_directional(f"light {i}", vec, [_number(v, f"{what} intensity") for v in phi]))
        key = "viewId" if "viewId" in item else "lightId" if "lightId" in item else None
        ids.append(None if key is None else [key, str(item[key])])
    comments = {"_alicevision_ids": ids} if any(ids) else {}
    return lights, comments


def alicevision_text(rig: RigParts) -> str:
    directional, _, _ = _kinds(rig)
    if not directional:
        first = next(i for i, light in enumerate(rig.lights) if not isinstance(light, DirectionalLight))
        raise RigError(
            f"AliceVision's lights.json holds directional lights only, and light {first} is a point light: "
            "write a rig file (.json) or a .dome"
        )
    ids = rig.comments.get("_alicevision_ids")
    if not (isinstance(ids, list) and len(ids) == rig.n_lights):
        ids = [None] * rig.n_lights
    entries = []
    for i, (light, key) in enumerate(zip(rig.lights, ids, strict=True)):
        assert isinstance(light, DirectionalLight)
        entry: dict[str, Any] = {}
        if isinstance(key, list) and len(key) == 2:
            entry[str(key[0])] = _Raw(str(int(key[1]))) if str(key[1]).isdigit() else str(key[1])
        else:
            entry["lightId"] = i
        entry["type"] = "directional"
        entry["direction"] = [_text(v) for v in light.direction]
        entry["intensity"] = [_text(v) for v in light.intensity]
        entries.append(entry)
    return _dump_json({"lights": entries}) + "\n"


# --------------------------------------------------------------------------------------------------
# Cameras: OpenCV FileStorage (YAML and JSON), rig files, SfMData
# --------------------------------------------------------------------------------------------------


def camera_of(camera: Any, intrinsic: str | None) -> tuple[dict[str, Any], RigGrid | None]:
    if isinstance(camera, Mapping):
        return dict(camera), None
    if isinstance(camera, (str, os.PathLike)):
        return read_camera(camera, intrinsic=intrinsic)
    raise RigError(f"camera must be a mapping or a camera file, got {type(camera).__name__}")


def read_camera(
    path: str | os.PathLike[str], *, fmt: str | None = None, intrinsic: str | None = None
) -> tuple[dict[str, Any], RigGrid | None]:
    """Read a camera: OpenCV FileStorage YAML or JSON, a rig file's camera, or an SfMData's intrinsics.

    Parameters
    ----------
    path : str or os.PathLike
        The file.
    fmt : str, optional
        ``"opencv-yaml"``, ``"opencv-json"``, ``"rig"`` or ``"sfmdata"``; default:
        :func:`detect_format`.
    intrinsic : str, optional
        The intrinsicId of an SfMData with several.

    Returns
    -------
    camera : dict
        The rig file's camera mapping (pinhole, K in the 0-based pixel-centre convention,
        OpenCV distortion).
    grid : RigGrid or None
        The image size, when the file gives it.

    Raises
    ------
    RigError
        The file cannot be read, is not a camera, or has a camera nplps cannot represent.
    """
    fmt = fmt or detect_format(path)
    name = os.fspath(path)
    if fmt == "opencv-yaml":
        return _opencv_camera(_parse_opencv_yaml(read_small_text(name, "camera file"), name), name)
    if fmt == "opencv-json":
        data = _read_json(name, "camera file")
        if not isinstance(data, dict):
            raise RigError(f"camera file {name!r} must hold a JSON object")
        return _opencv_camera(data, name)
    if fmt == "sfmdata":
        sfm = read_sfmdata(name)
        ids = sorted(set(sfm.intrinsics) | set(sfm.unusable))
        if intrinsic is None:
            if len(ids) != 1:
                raise RigError(
                    f"SfMData {name!r} has {len(ids)} intrinsics ({', '.join(ids)}): choose one (--intrinsic)"
                )
            intrinsic = ids[0]
        cam, size = sfm.camera(intrinsic)
        return cam, RigGrid(size)
    if fmt == "rig":
        from . import _core

        native, grid, _ = _core.read_rig(name)
        return dict(native.camera), core_grid(grid)
    raise RigError(f"{name!r} ({fmt}) is not a camera file")


def _matrix(node: Any, what: str) -> list[list[float]]:
    """Return an OpenCV matrix node ``{rows, cols, dt, data}`` as a list of rows."""
    if not isinstance(node, Mapping):
        raise RigError(f"{what} must be an OpenCV matrix (rows, cols, dt, data)")
    try:
        rows, cols = int(node["rows"]), int(node["cols"])
        data = node["data"]
    except (KeyError, TypeError, ValueError):
        raise RigError(f"{what} must be an OpenCV matrix with rows, cols and data") from None
    if not isinstance(data, list) or len(data) != rows * cols:
        raise RigError(f"{what}: data must hold rows x cols = {rows * cols} numbers")
    values = [_number(v, what) for v in data]
    return [values[r * cols : (r + 1) * cols] for r in range(rows)]


def _opencv_camera(data: Mapping[str, Any], name: str) -> tuple[dict[str, Any], RigGrid | None]:
    if "camera_matrix" not in data:
        raise RigError(f"camera file {name!r} has no camera_matrix")
    K = _matrix(data["camera_matrix"], f"{name!r}: camera_matrix")
    camera: dict[str, Any] = {"model": "pinhole", "K": K}
    if "distortion_coefficients" in data:
        rows = _matrix(data["distortion_coefficients"], f"{name!r}: distortion_coefficients")
        camera["distortion"] = [v for row in rows for v in row]
    grid = None
    if "image_width" in data and "image_height" in data:
        w, h = _number(data["image_width"], "image_width"), _number(data["image_height"], "image_height")
        if w != int(w) or h != int(h) or w < 1 or h < 1:
            raise RigError(f"camera file {name!r}: image_width and image_height must be whole numbers")
        grid = RigGrid((int(w), int(h)))
    try:
        camera = checked_camera(camera)
    except RigError as e:
        raise RigError(f"camera file {name!r}: {e}") from None
    return camera, grid


_YAML_KEY = re.compile(r"^([A-Za-z_][\w-]*)\s*:\s*(.*)$")


def _parse_opencv_yaml(text: str, name: str) -> dict[str, Any]:
    """Parse the subset of YAML that OpenCV's FileStorage writes for a camera.

    Top-level ``key: scalar`` lines and ``key: !!opencv-matrix`` blocks of ``rows``, ``cols``,
    ``dt`` and ``data: [ ... ]`` (indented or not; the list may span lines); ``#`` comments.
    """
    lines = [line.split("#", 1)[0].rstrip() for line in text.splitlines()]
    if not lines or not lines[0].startswith("%YAML"):
        raise RigError(f"camera file {name!r} is not OpenCV YAML (it must start with %YAML:1.0)")
    out: dict[str, Any] = {}
    i = 1
    while i < len(lines):
        line = lines[i]
        i += 1
        if not line.strip() or line.strip() == "---":
            continue
        if line[0].isspace():
            raise RigError(f"camera file {name!r}, line {i}: unexpected indented line {line.strip()[:40]!r}")
        m = _YAML_KEY.match(line)
        if not m:
            raise RigError(f"camera file {name!r}, line {i}: expected 'key: value', got {line[:40]!r}")
        key, rest = m.group(1), m.group(2).strip()
        if rest.startswith("!!opencv-matrix"):
            # The matrix's lines (indented as OpenCV writes them, or not): up to the end of its data list.
            block = [rest[len("!!opencv-matrix") :].strip()]
            while i < len(lines) and not re.search(r"data\s*:\s*\[[^\]]*\]", " ".join(block), re.S):
                block.append(lines[i].strip())
                i += 1
            out[key] = _yaml_matrix(" ".join(block), name, key)
        else:
            out[key] = rest.strip("\"'")
    return out


def _yaml_matrix(block: str, name: str, key: str) -> dict[str, Any]:
    m = re.search(r"data\s*:\s*\[(.*?)\]", block, re.S)
    node: dict[str, Any] = {}
    for field_name in ("rows", "cols", "dt"):
        f = re.search(rf"\b{field_name}\s*:\s*([^\s,]+)", block)
        if f:
            node[field_name] = f.group(1)
    if m is None or "rows" not in node or "cols" not in node:
        raise RigError(f"camera file {name!r}: {key} must have rows, cols and data: [ ... ]")
    node["data"] = [t for t in re.split(r"[\s,]+", m.group(1)) if t]
    return node


def write_camera(
    camera: Mapping[str, Any],
    path: str | os.PathLike[str],
    *,
    grid: RigGrid | None = None,
    fmt: str | None = None,
) -> None:
    """Write a pinhole camera as an OpenCV FileStorage file (YAML, or its JSON form).

    Parameters
    ----------
    camera : mapping
        A rig's camera (pinhole).
    path : str or os.PathLike
        The file (``.yml``/``.yaml``: YAML, else JSON unless `fmt` says).
    grid : RigGrid, optional
        Writes ``image_width`` and ``image_height`` when it has the image size.
    fmt : {"opencv-yaml", "opencv-json"}, optional
        Default: by extension.

    Raises
    ------
    RigError
        The camera is not a pinhole camera (OpenCV's model).
    """
    if camera.get("model") != "pinhole":
        raise RigError(
            f"an OpenCV camera file holds a pinhole camera; this camera is {camera.get('model')!r}: write a rig file"
        )
    fmt = fmt or output_format(path, None)
    K = [float(v) for row in camera["K"] for v in row]
    dist = [float(v) for v in camera.get("distortion", [0.0] * 5)]
    size = grid.image_size if grid is not None else None
    if fmt == "opencv-json":
        data: dict[str, Any] = {}
        if size is not None:
            data["image_width"], data["image_height"] = size
        for key, values, rows in (("camera_matrix", K, 3), ("distortion_coefficients", dist, 1)):
            data[key] = {
                "type_id": "opencv-matrix",
                "rows": rows,
                "cols": len(values) // rows,
                "dt": "d",
                "data": [_text(v) for v in values],
            }
        write_text(path, _dump_json(data) + "\n")
        return
    lines = ["%YAML:1.0", "---"]
    if size is not None:
        lines += [f"image_width: {size[0]}", f"image_height: {size[1]}"]
    for key, values, rows in (("camera_matrix", K, 3), ("distortion_coefficients", dist, 1)):
        lines += [
            f"{key}: !!opencv-matrix",
            f"   rows: {rows}",
            f"   cols: {len(values) // rows}",
            "   dt: d",
            f"   data: [ {', '.join(_text(v) for v in values)} ]",
        ]
    write_text(path, "\n".join(lines) + "\n")


@dataclass(frozen=True)
class SfmView:
    """One view of an SfMData: an image, its pose (poseId) and its camera (intrinsicId)."""

    view_id: str
    pose_id: str
    intrinsic_id: str
    path: str


@dataclass(frozen=True)
class SfmData:
    """The views and pinhole intrinsics of an AliceVision SfMData file.

    Attributes
    ----------
    views : list of SfmView
        In the file's order.
    intrinsics : dict
        intrinsicId -> (camera mapping, (width, height)).
    version : tuple of int
        The file version.
    unusable : dict
        intrinsicId -> why nplps cannot use it (not a pinhole camera, another distortion).
    """

    views: list[SfmView]
    intrinsics: dict[str, tuple[dict[str, Any], tuple[int, int]]] = field(default_factory=dict)
    version: tuple[int, int, int] = (1, 2, 12)
    unusable: dict[str, str] = field(default_factory=dict)

    def camera(self, intrinsic_id: str) -> tuple[dict[str, Any], tuple[int, int]]:
        """Return the camera mapping and image size of an intrinsic, or refuse it with the reason."""
        if intrinsic_id in self.unusable:
            raise RigError(self.unusable[intrinsic_id])
        if intrinsic_id not in self.intrinsics:
            raise RigError(f"the SfMData has no intrinsic {intrinsic_id!r}")
        return self.intrinsics[intrinsic_id]

    def poses(self) -> dict[str, list[SfmView]]:
        """Return the views grouped by poseId, each group sorted by image path."""
        groups: dict[str, list[SfmView]] = {}
        for view in self.views:
            groups.setdefault(view.pose_id, []).append(view)
        return {pose: sorted(views, key=lambda v: v.path) for pose, views in groups.items()}


def read_sfmdata(path: str | os.PathLike[str]) -> SfmData:
    """Read the views and the pinhole intrinsics of an AliceVision SfMData (JSON) file.

    Focal lengths in mm are converted with the sensor width as AliceVision does
    (``fx = focalLength / sensorWidth * width``; ``fy`` from ``pixelRatio``), older files'
    ``pxFocalLength`` are read as pixels; the principal point is an offset from the image centre
    (``cx = width / 2 + offset``; absolute before file version 1.2.1). Distortion ``radialk1``
    and ``radialk3`` become OpenCV coefficients; intrinsics of other models are refused when
    used (they are in :attr:`SfmData.unusable` with the reason).

    Parameters
    ----------
    path : str or os.PathLike
        The ``.sfm`` or ``.json`` file.

    Returns
    -------
    SfmData

    Raises
    ------
    RigError
        The file cannot be read or is malformed.
    """
    name = os.fspath(path)
    data = _read_json(name, "SfMData")
    if not isinstance(data, dict) or not isinstance(data.get("views"), list):
        raise RigError(f'SfMData {name!r} must be a JSON object with a list "views"')
    try:
        version = tuple(int(str(v)) for v in data.get("version", [1, 2, 12]))
    except ValueError:
        raise RigError(f"SfMData {name!r}: version must be three whole numbers") from None
    version3 = (*version, 0, 0, 0)[:3]
    views = []
    base = os.path.dirname(name)
    for i, v in enumerate(data["views"]):
        if not isinstance(v, dict) or not all(k in v for k in ("viewId", "poseId", "intrinsicId", "path")):
            raise RigError(f"SfMData {name!r}: view {i} must have viewId, poseId, intrinsicId and path")
        p = str(v["path"])
        views.append(SfmView(str(v["viewId"]), str(v["poseId"]), str(v["intrinsicId"]), os.path.join(base, p)))
    intrinsics, unusable = {}, {}
    for i, item in enumerate(data.get("intrinsics") or []):
        if not isinstance(item, dict) or "intrinsicId" not in item:
            raise RigError(f"SfMData {name!r}: intrinsic {i} must be an object with an intrinsicId")
        key = str(item["intrinsicId"])
        try:
            intrinsics[key] = _sfm_intrinsic(item, version3, f"SfMData {name!r}, intrinsic {key}")
        except RigError as e:
            unusable[key] = str(e)
    return SfmData(views, intrinsics, (version3[0], version3[1], version3[2]), unusable)


def _sfm_intrinsic(item: dict[str, Any], version: tuple[int, ...], what: str) -> tuple[dict[str, Any], tuple[int, int]]:
    kind = str(item.get("type", "pinhole"))
    if kind not in ("pinhole", "radial1", "radial3"):
        raise RigError(f"{what} is a {kind!r} camera: nplps reads pinhole intrinsics only")
    w, h = _number(item.get("width"), f"{what} width"), _number(item.get("height"), f"{what} height")
    if w != int(w) or h != int(h) or w < 1 or h < 1:
        raise RigError(f"{what}: width and height must be whole numbers")
    pp = item.get("principalPoint", [0, 0])
    if not isinstance(pp, list) or len(pp) != 2:
        raise RigError(f"{what}: principalPoint must be 2 numbers")
    ppx, ppy = _number(pp[0], f"{what} principalPoint"), _number(pp[1], f"{what} principalPoint")
    if version < (1, 2, 1):
        ppx -= w / 2.0
        ppy -= h / 2.0
    if version < (1, 2, 0):
        fx = fy = _number(item.get("pxFocalLength"), f"{what} pxFocalLength")
    elif version < (1, 2, 2):
        f = item.get("pxFocalLength")
        if not isinstance(f, list) or len(f) != 2:
            raise RigError(f"{what}: pxFocalLength must be 2 numbers")
        fx, fy = _number(f[0], f"{what} pxFocalLength"), _number(f[1], f"{what} pxFocalLength")
    else:
        fmm = _number(item.get("focalLength", 1.0), f"{what} focalLength")
        sensor = _number(item.get("sensorWidth", 36.0), f"{what} sensorWidth")
        ratio = _number(item.get("pixelRatio", 1.0), f"{what} pixelRatio")
        if sensor <= 0 or ratio <= 0:
            raise RigError(f"{what}: sensorWidth and pixelRatio must be positive")
        fx = (fmm / sensor) * w
        # Before file version 1.2.5 "pixelRatio" held fx / fy; since, the pixel aspect ratio fy / fx.
        fy = fx / ratio if version < (1, 2, 5) else fx / (1.0 / ratio)
    if not (fx > 0 and fy > 0):
        raise RigError(f"{what}: the focal length must be positive (the intrinsic is not calibrated)")
    dist_type = str(item.get("distortionType", {"radial1": "radialk1", "radial3": "radialk3"}.get(kind, "none")))
    params = item.get("distortionParams") or []
    if not isinstance(params, list):
        params = []
    k = [_number(v, f"{what} distortionParams") for v in params]
    if dist_type in ("none", ""):
        distortion = [0.0] * 5
    elif dist_type == "radialk1" and len(k) == 1:
        distortion = [k[0], 0.0, 0.0, 0.0, 0.0]
    elif dist_type == "radialk3" and len(k) == 3:
        distortion = [k[0], k[1], 0.0, 0.0, k[2]]
    else:
        raise RigError(
            f"{what} has distortion {dist_type!r} with {len(k)} parameters: nplps reads none, radialk1 and radialk3"
        )
    K = [[fx, 0.0, w / 2.0 + ppx], [0.0, fy, h / 2.0 + ppy], [0.0, 0.0, 1.0]]
    camera = {"model": "pinhole", "K": K, "distortion": distortion}
    return camera, (int(w), int(h))
