"""Fuzzing of the rig file reader and of the compiled core's rig parser (issue 9).

Hypothesis generates rig mappings and JSON texts, valid ones and corrupted ones (wrong types,
NaN and infinities, huge numbers, bools and strings where numbers belong, missing, extra and
misspelt keys, nested lists, deep nesting, truncated text), and feeds them to ``Rig.from_dict``,
``Rig.load``, the core's camera parser and a small reconstruction. The only outcomes allowed are
success or :class:`nplps.RigError` / :class:`nplps.InputError` (a reconstruction may also end in
:class:`nplps.SolverError`), with a short message; and whatever is accepted means the same to
Python and to the core.

Each property runs 200 examples by default (CI); ``NPLPS_FUZZ_EXAMPLES=20000`` runs a long
fuzzing session.
"""

from __future__ import annotations

import json
import math
import os
import re
from typing import Any

import numpy as np
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

import nplps
from nplps import _core

EXAMPLES = int(os.environ.get("NPLPS_FUZZ_EXAMPLES", "200"))
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
)
ALLOWED = (nplps.RigError, nplps.InputError)
DEPTH = np.full((3, 4), 150.0)  # a 2 x 3 image's vertex depths


# ------------------------------------------------------------------------------------------------
# strategies
# ------------------------------------------------------------------------------------------------
def _floats(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.floats(lo, hi, allow_nan=False, allow_infinity=False)


#: Values that do not belong where a number, a list or an object is expected.
JUNK = st.one_of(
    st.sampled_from(
        [math.nan, math.inf, -math.inf, 1e308, -1e308, 5e-324, 0.0, -0.0, 10**400, -(10**30), True, False, None]
    ),
    st.floats(),
    st.integers(),
    st.text(max_size=8),
    st.lists(st.floats(-10, 10), max_size=6),
    st.lists(st.lists(st.integers(-3, 3), max_size=3), max_size=3),
    st.dictionaries(st.text(max_size=4), st.integers(), max_size=2),
)


def _nested(value: Any, depth: int) -> Any:
    for _ in range(depth):
        value = [value]
    return value


def _distortion(valid: bool = True) -> st.SearchStrategy[Any]:
    """OpenCV distortion coefficients, flat or as a 1 x n or n x 1 matrix: 0, 1, 2, 4 or 5 of
    them (or 8, 12, 14 with zeros after k3); any number up to 14 unless ``valid``."""
    sizes = st.sampled_from([0, 1, 2, 4, 5]) if valid else st.integers(0, 15)
    coefficients = sizes.flatmap(lambda n: st.lists(_floats(-0.3, 0.3), min_size=n, max_size=n))
    return st.one_of(
        coefficients,
        coefficients.map(lambda c: [c]),  # OpenCV's 1 x n
        coefficients.map(lambda c: [[v] for v in c]),  # OpenCV's n x 1
        st.tuples(st.sampled_from([8, 12, 14]), st.lists(_floats(-0.1, 0.1), min_size=5, max_size=5)).map(
            lambda t: t[1] + [0.0] * (t[0] - 5)
        ),
        st.none(),
    )


def _camera(valid: bool = True) -> st.SearchStrategy[dict[str, Any]]:
    orthographic = st.fixed_dictionaries(
        {
            "model": st.just("orthographic"),
            "pixel_size": st.lists(_floats(0.01, 5.0), min_size=2, max_size=2),
            "origin": st.lists(_floats(-100, 100), min_size=2, max_size=2),
        }
    )
    pinhole = st.builds(
        lambda f, c, s: {"model": "pinhole", "K": [[f[0], s, c[0]], [0.0, f[1], c[1]], [0.0, 0.0, 1.0]]},
        st.lists(_floats(50, 3000), min_size=2, max_size=2),
        st.lists(_floats(-5, 5), min_size=2, max_size=2),
        st.sampled_from([0.0, 0.0, 0.5]),
    )
    with_distortion = st.tuples(pinhole, _distortion(valid)).map(lambda t: {**t[0], "distortion": t[1]})
    return st.one_of(orthographic, pinhole, with_distortion)


def _light() -> st.SearchStrategy[dict[str, Any]]:
    intensity = st.one_of(_floats(0.1, 5), st.lists(_floats(0.1, 5), min_size=3, max_size=3))
    position = st.tuples(_floats(-60, 60), _floats(-60, 60), _floats(-80, 0)).map(list)
    point = st.fixed_dictionaries(
        {"type": st.just("point"), "position": position},
        optional={"intensity": intensity},
    )
    led = st.fixed_dictionaries(
        {
            "type": st.just("point"),
            "position": position,
            "intensity": intensity,
            "direction": st.tuples(_floats(-0.3, 0.3), _floats(-0.3, 0.3), _floats(0.5, 1)).map(list),
            "mu": _floats(0.0, 3.0),
        }
    )
    directional = st.tuples(_floats(-0.5, 0.5), _floats(-0.5, 0.5), intensity).map(
        lambda t: {
            "type": "directional",
            "direction": (np.array([t[0], t[1], -1.0]) / np.linalg.norm([t[0], t[1], -1.0])).tolist(),
            "intensity": t[2],
        }
    )
    untyped = position.map(lambda p: {"position": p})  # version 1 style
    return st.one_of(point, led, directional, untyped)


def _rig_dict() -> st.SearchStrategy[dict[str, Any]]:
    return st.fixed_dictionaries(
        {"version": st.sampled_from([1, 2]), "camera": _camera(), "lights": st.lists(_light(), min_size=3, max_size=8)}
    )


def _paths(value: Any, path: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every path (keys and indices) into a JSON value."""
    out = [path]
    if isinstance(value, dict):
        for k, v in value.items():
            out += _paths(v, (*path, k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            out += _paths(v, (*path, i))
    return out


def _get(value: Any, path: tuple[Any, ...]) -> Any:
    for p in path:
        value = value[p]
    return value


@st.composite
def corrupted(draw: st.DrawFn) -> Any:
    """A rig mapping with a few mutations: a value replaced by junk, nested, wrapped or deeply
    nested; a key removed, added (known, misspelt, comment) or given a non-string name."""
    data = draw(_rig_dict())
    for _ in range(draw(st.integers(1, 3))):
        paths = _paths(data)
        path = draw(st.sampled_from(paths))
        kind = draw(st.sampled_from(["junk", "wrap", "deep", "delete", "add", "unwrap"]))
        if not path:
            if kind in ("junk", "wrap", "deep"):
                data = draw(JUNK) if kind == "junk" else _nested(data, 1 if kind == "wrap" else 200)
            continue
        parent, key = _get(data, path[:-1]), path[-1]
        if kind == "junk":
            parent[key] = draw(JUNK)
        elif kind == "wrap":
            parent[key] = [parent[key]]
        elif kind == "deep":
            parent[key] = _nested(parent[key], draw(st.sampled_from([2, 50, 300])))
        elif kind == "unwrap" and isinstance(parent[key], list) and parent[key]:
            parent[key] = parent[key][0]
        elif kind == "delete":
            del parent[key]
        elif kind == "add" and isinstance(parent, dict):
            name = draw(
                st.sampled_from(
                    ["intensities", "distorsion", "_comment", "mu", "direction", "position", "K", "type", "serial"]
                )
            )
            parent[name] = draw(st.one_of(JUNK, st.just([0.0, 0.0, 1.0])))
    return data


# ------------------------------------------------------------------------------------------------
# checks
# ------------------------------------------------------------------------------------------------
def _short(e: Exception) -> None:
    """Messages are short and print no number with hundreds of digits (quoted strings from the
    file, cut at 40 characters, aside)."""
    text = str(e)
    assert len(text) < 1500, text[:300]
    assert not re.search(r"\d{25}", re.sub(r'"[^"]*"', "", text)), text[:300]


def _vertices(camera: Any) -> np.ndarray | str:
    """The core's vertices of DEPTH under ``camera``, or the message of its RigError (a camera
    whose distortion cannot be undone at some pixel corner has no vertex there)."""
    try:
        return _core.vertices(DEPTH, camera)
    except nplps.RigError as e:
        _short(e)
        return str(e)


def _same_vertices(a: Any, b: Any) -> None:
    va, vb = _vertices(a), _vertices(b)
    assert type(va) is type(vb), (va, vb)
    if isinstance(va, str):
        assert va == vb
    else:
        np.testing.assert_array_equal(va, vb)


def _read(data: Any) -> nplps.Rig | None:
    """Rig.from_dict: a rig, or None after a RigError."""
    try:
        rig = nplps.Rig.from_dict(data)
    except ALLOWED as e:
        assert isinstance(e, nplps.RigError), repr(e)
        _short(e)
        event("rig refused")
        return None
    event("rig accepted")
    return rig


def _check_accepted(rig: nplps.Rig, data: Any) -> None:
    """An accepted rig is sane, means the same to the core, and round-trips through its file."""
    k = rig.n_lights
    # Rigs hold 1 to MAX_LIGHTS lights (rendering takes any number); reconstruct asks for 3.
    assert 1 <= k <= nplps.rig.MAX_LIGHTS
    assert np.isfinite(_vectors(rig)).all()
    for name in ("intensities", "mu"):
        assert np.isfinite(getattr(rig, name)).all(), name
    led = np.array([isinstance(light, nplps.LED) for light in rig.lights], dtype=bool)
    assert np.isfinite(rig.axes[led]).all() and np.isnan(rig.axes[~led]).all()
    assert (rig.intensities > 0).all() and (rig.mu >= 0).all()
    # The core reads the file's camera mapping as Python did.
    assert _core.normalize_camera(data["camera"]) == rig.camera
    _same_vertices(data["camera"], rig.camera)
    again = nplps.Rig.from_dict(json.loads(json.dumps(rig.to_dict())))
    assert again.camera == rig.camera
    assert [type(light) for light in again.lights] == [type(light) for light in rig.lights]
    for name in ("positions", "directions", "intensities", "mu", "directional"):
        np.testing.assert_array_equal(getattr(again, name), getattr(rig, name))


def _vectors(rig: nplps.Rig) -> np.ndarray:
    """Each light's position, or direction for a directional light."""
    return np.where(rig.directional[:, None], rig.directions, rig.positions)


# ------------------------------------------------------------------------------------------------
# properties
# ------------------------------------------------------------------------------------------------
@FUZZ
@given(_rig_dict())
def test_valid_rig_files_are_read(data):
    rig = nplps.Rig.from_dict(data)
    _check_accepted(rig, data)


@FUZZ
@given(corrupted())
def test_corrupted_rig_mappings_are_rig_errors(data):
    rig = _read(data)
    if rig is not None:
        _check_accepted(rig, data)


@FUZZ
@given(st.one_of(_camera(valid=False), corrupted().map(lambda d: d.get("camera") if isinstance(d, dict) else d)))
def test_python_and_the_core_agree_on_the_camera(camera):
    """The file reader (with good lights) and the core's parser given the raw camera mapping
    accept the same cameras and place the same vertices."""
    lights = [{"position": [-30.0, 0.0, -10.0]}, {"position": [30.0, 10.0, -10.0]}, {"position": [0.0, -30.0, -20.0]}]
    rig = _read({"version": 2, "camera": camera, "lights": lights})
    try:
        core = _core.normalize_camera(camera)
    except ALLOWED as e:
        _short(e)
        core = None
    except TypeError:
        # The core's functions take a dict: the file reader refuses anything else too.
        assert not isinstance(camera, dict)
        core = None
    assert (rig is None) == (core is None), (camera, rig)
    if rig is not None:
        assert core == rig.camera
        _same_vertices(camera, rig.camera)


def _mutate_text(text: str, data: st.DataObject) -> str:
    kind = data.draw(st.sampled_from(["truncate", "insert", "delete", "nest", "replace", "bom", "none"]))
    if kind == "none" or not text:
        return text
    i = data.draw(st.integers(0, len(text) - 1))
    if kind == "truncate":
        return text[:i]
    if kind == "insert":
        return (
            text[:i]
            + data.draw(
                st.sampled_from(
                    ["[", "]", "{", "}", ",", '"', "NaN", "Infinity", "-", "1e999", "9" * 5000, "\\", "\x00"]
                )
            )
            + text[i:]
        )
    if kind == "delete":
        return text[:i] + text[i + 1 :]
    if kind == "nest":
        n = data.draw(st.sampled_from([10, 65, 1000, 100000]))
        return "[" * n + text + "]" * n
    if kind == "bom":
        return "\ufeff" + text
    return re.sub(
        r"-?\d+\.\d+",
        lambda m: data.draw(st.sampled_from(["NaN", "-Infinity", "1e400", "true", '"1"', "null", "[]"])),
        text,
        count=1,
    )


@FUZZ
@given(st.one_of(_rig_dict(), corrupted()), st.data())
def test_rig_files_load_or_fail_with_a_rig_error(tmp_path_factory, data, draws):
    try:
        text = json.dumps(data)
    except (ValueError, RecursionError):  # unserialisable (e.g. a deep nesting of junk)
        return
    text = _mutate_text(text, draws)
    path = tmp_path_factory.mktemp("fuzz") / "rig.json"
    path.write_bytes(text.encode("utf-8", "surrogatepass"))
    try:
        rig = nplps.Rig.load(path)
    except ALLOWED as e:
        assert isinstance(e, nplps.RigError), repr(e)
        _short(e)
        event("file refused")
        return
    event("file read")
    assert np.isfinite(_vectors(rig)).all()


@FUZZ
@given(st.one_of(_rig_dict(), corrupted()), st.integers(0, 2**32 - 1))
def test_a_small_reconstruction_fails_only_with_typed_errors(data, seed):
    """A rig that was read runs a 4 x 4 reconstruction, or fails with a typed error."""
    rig = _read(data)
    if rig is None:
        return
    rng = np.random.default_rng(seed)
    images = rng.uniform(0.1, 1.0, (rig.n_lights, 4, 4)).astype(np.float32)
    try:
        r = nplps.reconstruct(images, rig, mask=None, depth=120.0, iterations=2)
    except (nplps.RigError, nplps.InputError, nplps.SolverError) as e:
        _short(e)
        event(f"reconstruction: {type(e).__name__}")
        return
    event("reconstruction: done")
    assert np.isfinite(r.depth).all() and np.isfinite(r.normals).all()


@FUZZ
@given(
    st.one_of(
        st.lists(st.lists(st.one_of(_floats(-50, 50), JUNK), min_size=0, max_size=4), min_size=0, max_size=6),
        JUNK,
    ),
    st.one_of(st.none(), JUNK, st.lists(st.one_of(_floats(0, 3), JUNK), max_size=6)),
    st.one_of(st.none(), JUNK, st.lists(st.one_of(_floats(0.1, 3), JUNK), max_size=6)),
)
def test_rig_constructors_fail_only_with_rig_errors(lights, mu, intensities):
    """The Python constructors (arrays rather than a file) refuse what they cannot use."""
    for build in (
        lambda: nplps.Rig.orthographic(
            1.0, lights=lights, mu=mu, intensities=intensities, axes=None if mu is None else lights
        ),
        lambda: nplps.Rig.from_arrays({"model": "orthographic", "pixel_size": [1, 1], "origin": [0, 0]}, lights, mu=mu),
        lambda: nplps.Rig({"model": "orthographic", "pixel_size": [1, 1], "origin": [0, 0]}, lights),
        lambda: nplps.Rig.from_arrays(
            {"model": "orthographic", "pixel_size": [1, 1], "origin": [0, 0]}, directions=lights
        ),
        lambda: nplps.Rig.pinhole([[500, 0, 2], [0, 500, 2], [0, 0, 1]], lights=lights, distortion=intensities),
    ):
        try:
            rig = build()
        except ALLOWED as e:
            _short(e)
            continue
        assert np.isfinite(_vectors(rig)).all() and rig.n_lights >= 1
