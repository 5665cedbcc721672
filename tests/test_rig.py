"""Tests of nplps.Rig: construction, the orthographic camera's pixel size, and the rig file."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

import nplps
import reference as ref  # tests/reference.py, the numpy oracle

LIGHTS = [[-30.0, 0.0, 0.0], [30.0, 10.0, 0.0], [0.0, -30.0, -50.0], [5.0, 25.0, -20.0]]


# ------------------------------------------------------------------------------------------------
# construction
# ------------------------------------------------------------------------------------------------
def test_orthographic_scalar_and_pair_pixel_size():
    scalar = nplps.Rig.orthographic(0.5, lights=LIGHTS)
    pair = nplps.Rig.orthographic((0.5, 0.5), lights=LIGHTS)
    assert scalar.camera == pair.camera == {"model": "orthographic", "pixel_size": [0.5, 0.5], "origin": [0.0, 0.0]}
    assert scalar.lights == pair.lights

    rect = nplps.Rig.orthographic((0.5, 0.25), origin=(-8.0, 4.0), lights=LIGHTS)
    assert rect.camera["pixel_size"] == [0.5, 0.25]  # (w, h): x first
    assert rect.camera["origin"] == [-8.0, 4.0]
    assert rect.n_lights == 4
    assert rect.positions.dtype == np.float64 and rect.positions.shape == (4, 3)
    assert rect.positions.flags["C_CONTIGUOUS"]
    assert all(isinstance(light, nplps.PointLight) for light in rect.lights)
    # integers and numpy scalars are accepted
    assert nplps.Rig.orthographic(np.float32(2), lights=LIGHTS).camera["pixel_size"] == [2.0, 2.0]
    assert nplps.Rig.orthographic(2, lights=LIGHTS).camera["pixel_size"] == [2.0, 2.0]


def test_rig_is_frozen():
    rig = nplps.Rig.orthographic(1.0, lights=LIGHTS)
    with pytest.raises(AttributeError):
        rig.lights = ()  # type: ignore[misc]
    with pytest.raises(AttributeError):
        rig.lights[0].position = (0.0, 0.0, 0.0)  # type: ignore[misc]
    with pytest.raises(ValueError, match="read-only"):
        rig.positions[0, 0] = 1.0


@pytest.mark.parametrize(
    "pixel_size, message",
    [
        ((1.0,), r"camera\.pixel_size must be 2 numbers, got a tuple of 1 item"),
        ((1.0, 2.0, 3.0), r"camera\.pixel_size must be 2 numbers, got a tuple of 3 items"),
        (0.0, r"pixel size must be positive and finite, got \[0, 0\]"),
        ((0.5, -0.5), r"pixel size must be positive and finite"),
        ((np.inf, 1.0), r"camera\.pixel_size\[0\] must be a finite number, got inf"),
        ((True, 1.0), r"camera\.pixel_size\[0\] must be a number, got the boolean true"),
    ],
)
def test_orthographic_bad_pixel_size(pixel_size, message):
    with pytest.raises(nplps.RigError, match=message):
        nplps.Rig.orthographic(pixel_size, lights=LIGHTS)


def test_orthographic_non_numeric_scalar_pixel_size():
    with pytest.raises(nplps.RigError, match=r"pixel_size\[0\] must be a number, got the string \"ab\""):
        nplps.Rig.orthographic("ab", lights=LIGHTS)


def test_orthographic_bad_origin_and_lights():
    with pytest.raises(nplps.RigError, match=r"camera\.origin\[0\] must be a finite number, got NaN"):
        nplps.Rig.orthographic(1.0, origin=(np.nan, 0.0), lights=LIGHTS)
    # Fewer than 3 lights make a rig (prediction, rendering and calibration take them); only
    # reconstruction needs 3 (test_api.test_bad_rig). No light at all is no rig.
    assert nplps.Rig.orthographic(1.0, lights=LIGHTS[:2]).n_lights == 2
    with pytest.raises(nplps.RigError, match=r"a rig needs at least one light, it has 0 lights"):
        nplps.Rig.orthographic(1.0)
    with pytest.raises(nplps.RigError, match=r"unknown camera model \"fisheye\""):
        nplps.Rig(camera={"model": "fisheye", "pixel_size": [1, 1], "origin": [0, 0]}, lights=LIGHTS)
    with pytest.raises(nplps.RigError, match=r"camera is missing the key \"K\""):
        nplps.Rig(camera={"model": "pinhole"}, lights=LIGHTS)
    with pytest.raises(nplps.RigError, match=r"camera is missing the key \"origin\""):
        nplps.Rig(camera={"model": "orthographic", "pixel_size": [1, 1]}, lights=LIGHTS)


def _anisotropic_case():
    """A 32 x 48 image with pixels 2.0 wide and 1.5 high, of a surface with planar quads."""
    h_px, w_px, w, h = 32, 48, 2.0, 1.5
    origin = (-48.0, -24.0)
    xs = origin[0] + np.arange(w_px + 1) * w
    ys = origin[1] + np.arange(h_px + 1) * h
    x, y = np.meshgrid(xs, ys)
    depth = 200.0 + 0.004 * x**2 - 0.006 * y**2 + 0.05 * x - 0.08 * y
    lights = nplps.make_scene("saddle", n=8).rig.lights
    return depth, (w, h), origin, lights


def test_pair_pixel_size_is_width_then_height(angular_error):
    """Non-square pixels and a non-square image. Measured: 2.5e-6 deg with (w, h) = (2, 1.5);
    13.8 deg with the pair swapped, 7.5 deg with square pixels."""
    depth, pixel_size, origin, lights = _anisotropic_case()
    rig = nplps.Rig.orthographic(pixel_size, origin, lights)
    images = nplps.render(depth, rig, 4e4)
    assert images.shape == (27, 32, 48)
    truth = ref.mesh_normals(depth, pixel_size, origin)

    r = nplps.reconstruct(images, rig, mask=None, depth=depth.mean())
    err = angular_error(r.normals, truth).mean()
    assert err < 1e-3
    assert np.abs(r.depth - depth).max() < 1e-4
    np.testing.assert_allclose(r.normals, ref.mesh_normals(r.depth, pixel_size, origin), rtol=0, atol=1e-12)
    np.testing.assert_allclose(r.vertices[..., 0][0], origin[0] + np.arange(49) * pixel_size[0])
    np.testing.assert_allclose(r.vertices[..., 1][:, 0], origin[1] + np.arange(33) * pixel_size[1])

    swapped = nplps.Rig.orthographic(pixel_size[::-1], origin, lights)
    r = nplps.reconstruct(images, swapped, mask=None, depth=depth.mean())
    assert angular_error(r.normals, truth).mean() > 5.0


# ------------------------------------------------------------------------------------------------
# rig file
# ------------------------------------------------------------------------------------------------
def test_save_load_round_trip(tmp_path):
    rig = nplps.Rig.orthographic((0.5, 0.25), origin=(-8.0, 4.125), lights=np.array(LIGHTS) + 1e-9)
    path = tmp_path / "rig.json"
    rig.save(path)
    data = json.loads(path.read_text(encoding="utf-8"))
    assert set(data) == {"version", "camera", "lights"}
    assert list(data) == ["version", "camera", "lights"]
    assert data["version"] == 3
    assert data["camera"] == {"model": "orthographic", "pixel_size": [0.5, 0.25], "origin": [-8.0, 4.125]}
    assert data["lights"] == [{"type": "point", "position": list(p), "intensity": 1.0} for p in rig.positions.tolist()]

    loaded = nplps.Rig.load(path)
    assert loaded.camera == rig.camera
    np.testing.assert_array_equal(loaded.positions, rig.positions)  # exact: JSON floats round-trip
    assert loaded == rig
    assert nplps.Rig.load(str(path)).camera == rig.camera
    assert nplps.Rig.from_dict(rig.to_dict()).camera == rig.camera


def test_load_ignores_comment_keys(tmp_path):
    data = nplps.Rig.orthographic(1.0, lights=LIGHTS).to_dict()
    data["_comment"] = "made by hand"
    data["camera"]["_serial"] = "A123"
    data["lights"][0]["intensity"] = 0.9
    data["lights"][1]["_note"] = {"anything": [[[1]]], "goes": None}
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(data), encoding="utf-8")
    rig = nplps.Rig.load(path)
    np.testing.assert_array_equal(rig.positions, LIGHTS)
    assert rig.camera == {"model": "orthographic", "pixel_size": [1.0, 1.0], "origin": [0.0, 0.0]}


@pytest.mark.parametrize(
    "edit, message",
    [
        (
            lambda d: d.update(comment="x"),
            r"rig\.json has an unknown key \"comment\" \(a rig file has version, camera, lights and optionally grid"
            r"; keys starting with '_' are comments\)",
        ),
        (
            lambda d: d["camera"].update(serial="A123"),
            r"camera has an unknown key \"serial\" \(an orthographic camera has model, pixel_size and origin",
        ),
        (lambda d: d["camera"].update(K=[[1, 0, 0], [0, 1, 0], [0, 0, 1]]), r"camera has an unknown key \"K\""),
        (
            lambda d: d["lights"][0].update(intensities=[1, 2, 3]),
            r"light 0 has an unknown key \"intensities\" \(a point light has type, position, intensity, direction, mu",
        ),
        (
            lambda d: d["lights"][1].update(type="directional", direction=[0, 0, -1], position=[0, 0, 0]),
            r"light 1 has an unknown key \"position\" \(a directional light has",
        ),
        (
            lambda d: d["lights"].__setitem__(1, {"type": "directional", "direction": [0, 0, -1], "mu": 1.0}),
            r"light 1 has an unknown key \"mu\"",
        ),
    ],
)
def test_unknown_keys_are_errors(tmp_path, edit, message):
    """A misspelt or misplaced key must not silently fall back to a default."""
    data = nplps.Rig.orthographic(1.0, lights=LIGHTS).to_dict()
    edit(data)
    with pytest.raises(nplps.RigError, match=message):
        nplps.Rig.load(_write(tmp_path, data))


def _write(tmp_path, data):
    path = tmp_path / "rig.json"
    path.write_text(data if isinstance(data, str) else json.dumps(data), encoding="utf-8")
    return path


def _good():
    return nplps.Rig.orthographic(1.0, lights=LIGHTS).to_dict()


def _edit(fn):
    data = _good()
    fn(data)
    return data


@pytest.mark.parametrize(
    "content, message",
    [
        ("{not json", r"rig file '.*rig\.json' is not valid JSON"),
        ("", r"is not valid JSON"),
        ([1, 2, 3], r"rig\.json: a rig file holds a JSON object, got a list of 3 items"),
        (_edit(lambda d: d.pop("lights")), r"rig\.json: missing key\(s\) lights"),
        (_edit(lambda d: (d.pop("version"), d.pop("camera"))), r"missing key\(s\) version, camera"),
        (_edit(lambda d: d.update(version=4)), r"unsupported rig file version 4 \(this nplps reads 1\.\.3\)"),
        (_edit(lambda d: d.update(version=0)), r"unsupported rig file version 0"),
        (_edit(lambda d: d.update(version="1")), r"'version' must be an integer, got the string \"1\""),
        (_edit(lambda d: d.update(version=2.0)), r"'version' must be an integer, got 2"),
        (_edit(lambda d: d.update(version=True)), r"'version' must be an integer, got the boolean true"),
        (_edit(lambda d: d["lights"][1].pop("position")), r"light 1 is missing its 'position'"),
        (
            _edit(lambda d: d["lights"][2].update(position=[1, 2])),
            r"light 2 position must be 3 numbers, got a list of 2 items",
        ),
        (
            _edit(lambda d: d["lights"][0].update(position=["a", 0, 0])),
            r"light 0 position\[0\] must be a number, got the string \"a\"",
        ),
        (
            _edit(lambda d: d["lights"][0].update(position=[[1], 0, 0])),
            r"light 0 position\[0\] must be a number, got a list of 1 item",
        ),
        (
            _edit(lambda d: d["lights"][0].update(position=[True, 0, 0])),
            r"light 0 position\[0\] must be a number, got the boolean true",
        ),
        (
            _edit(lambda d: d["lights"][0].update(position=[10**400, 0, 0])),
            r"light 0 position\[0\] is an integer too large",
        ),
        (
            _edit(lambda d: d["lights"][0].update(intensity="1")),
            r"light 0 intensity must be a number, got the string \"1\"",
        ),
        (
            _edit(lambda d: d["lights"][0].update(intensity=[1, 2])),
            r"light 0 intensity must be 3 numbers, got a list of 2 items",
        ),
        (
            _edit(lambda d: d["lights"][0].update(intensity=[[1, 2, 3]])),
            r"light 0 intensity must be 3 numbers, got a list of 1 item",
        ),
        (
            _edit(lambda d: d["lights"][0].update(intensity=0)),
            r"light 0 must have positive intensities, got \[0, 0, 0\]",
        ),
        (_edit(lambda d: d["lights"][0].update(mu="2")), r"light 0 mu must be a number, got the string \"2\""),
        (
            _edit(lambda d: d["lights"][0].update(type=1)),
            r"light 0 has unknown type 1 \(\"point\" or \"directional\"\)",
        ),
        (_edit(lambda d: d["lights"].__setitem__(0, [0, 0, 0])), r"light 0 must be an object, got a list of 3 items"),
        (_edit(lambda d: d.update(lights={"position": [0, 0, 0]})), r"'lights' must be a list"),
        (_edit(lambda d: d.update(lights=[])), r"a rig needs at least one light, it has 0 lights"),
        (_edit(lambda d: d.update(camera=[])), r"'camera' must be an object with a 'model' key"),
        (_edit(lambda d: d["camera"].pop("pixel_size")), r"rig\.json: camera is missing the key \"pixel_size\""),
        (
            _edit(lambda d: d["camera"].update(origin=[0])),
            r"rig\.json: camera\.origin must be 2 numbers, got a list of 1 item",
        ),
        (
            _edit(lambda d: d["camera"].update(origin={"x": 0, "y": 0})),
            r"camera\.origin must be 2 numbers, got an object",
        ),
        (
            _edit(lambda d: d["camera"].update(model=["orthographic"])),
            r"camera\.model must be a string, got a list of 1 item",
        ),
        (_edit(lambda d: d["camera"].update(pixel_size=[0, 1])), r"pixel size must be positive"),
        (_edit(lambda d: d["camera"].update(model="fisheye")), r"unknown camera model \"fisheye\""),
    ],
)
def test_load_errors(tmp_path, content, message):
    path = _write(tmp_path, content)
    with pytest.raises(nplps.RigError, match=message) as info:
        nplps.Rig.load(path)
    assert isinstance(info.value, nplps.InputError)


def test_load_missing_file(tmp_path):
    missing = tmp_path / "nowhere" / "rig.json"
    with pytest.raises(nplps.RigError, match=r"cannot read rig file '.*nowhere.*rig\.json': No such file"):
        nplps.Rig.load(missing)
    with pytest.raises(nplps.RigError, match=r"cannot read rig file"):
        nplps.Rig.load(tmp_path)  # a directory


def test_version_1_files_are_read(tmp_path):
    path = tmp_path / "rig.json"
    path.write_text(
        json.dumps(
            {
                "version": 1,
                "camera": {"model": "orthographic", "pixel_size": [1, 1], "origin": [0, 0]},
                "lights": [{"position": p} for p in LIGHTS],
            }
        )
    )
    rig = nplps.Rig.load(path)
    np.testing.assert_array_equal(rig.positions, np.array(LIGHTS, dtype=float))
    np.testing.assert_array_equal(rig.intensities, 1.0)
    assert not rig.directional.any() and not rig.mu.any()


def test_pinhole_led_rig_round_trip(tmp_path):
    K = [[800.0, 0.0, 319.5], [0.0, 810.0, 239.5], [0.0, 0.0, 1.0]]
    nan = [np.nan] * 3
    rig = nplps.Rig.pinhole(
        K,
        lights=[[50.0, 0.0, -10.0], [-40.0, 30.0, -5.0], [0.0, -45.0, -20.0], nan],
        distortion=[-0.1, 0.01],
        directions=[nan, nan, nan, [0.0, 0.0, -2.0]],
        intensities=[1.0, [0.9, 1.0, 1.1], 1.2, 0.5],
        axes=[[0, 0, 1], [0.1, 0, 1], [0, 0.2, 1], nan],
        mu=[1.0, 0.0, 2.0, 0.0],
    )
    assert rig.n_lights == 4 and rig.is_pinhole
    assert [type(light).__name__ for light in rig.lights] == ["LED", "PointLight", "LED", "DirectionalLight"]
    np.testing.assert_allclose(np.linalg.norm(rig.axes[[0, 2]], axis=1), 1.0)
    assert np.isnan(rig.axes[[1, 3]]).all()  # a point light (mu = 0: its axis is dropped) and a directional light
    np.testing.assert_array_equal(rig.directions[3], [0.0, 0.0, -1.0])  # normalized
    assert np.isnan(rig.positions[3]).all() and np.isnan(rig.directions[:3]).all()
    path = tmp_path / "rig.json"
    rig.save(path)
    data = json.loads(path.read_text())
    assert data["camera"]["model"] == "pinhole" and data["camera"]["distortion"] == [-0.1, 0.01, 0.0, 0.0, 0.0]
    assert [light["type"] for light in data["lights"]] == ["point", "point", "point", "directional"]
    assert "mu" not in data["lights"][1] and data["lights"][2]["mu"] == 2.0
    assert data["lights"][2]["direction"] == list(rig.lights[2].axis)  # the file's "direction" is the LED axis
    loaded = nplps.Rig.load(path)
    for name in ("positions", "directions", "axes", "intensities", "mu", "directional"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(rig, name))
    assert loaded == rig
    np.testing.assert_allclose(loaded.K, K)


def test_pinhole_and_led_errors():
    good_k = [[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]]
    with pytest.raises(nplps.RigError, match=r"K must be \[\[fx, s, cx\]"):
        nplps.Rig.pinhole([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 1.0, 1.0]], lights=LIGHTS)
    with pytest.raises(nplps.RigError, match=r"K must be a 3 x 3 matrix"):
        nplps.Rig.pinhole(np.eye(2), lights=LIGHTS)
    with pytest.raises(nplps.RigError, match=r"light 0: an anisotropic LED \(mu = 1\) needs its axis \(axes=\.\.\.\)"):
        nplps.Rig.pinhole(good_k, lights=LIGHTS, mu=[1.0] * len(LIGHTS))
    with pytest.raises(nplps.RigError, match=r"light 0 has anisotropy mu = -1; it must be >= 0"):
        nplps.Rig.pinhole(good_k, lights=LIGHTS, axes=[[0, 0, 1]] * len(LIGHTS), mu=[-1.0] + [1.0] * (len(LIGHTS) - 1))
    with pytest.raises(nplps.RigError, match=r"light 1 must have positive intensities"):
        nplps.Rig.pinhole(good_k, lights=LIGHTS, intensities=[1.0, 0.0] + [1.0] * (len(LIGHTS) - 2))
    with pytest.raises(nplps.RigError, match=r"intensities must be a number, \(k,\) or \(k, 3\)"):
        nplps.Rig.pinhole(good_k, lights=LIGHTS, intensities=[1.0, 2.0])


# ------------------------------------------------------------------------------------------------
# strict rig files (issue 9): every key checked, one meaning for Python and the core
# ------------------------------------------------------------------------------------------------
K_TEST = [[500.0, 0.0, 2.0], [0.0, 500.0, 2.0], [0.0, 0.0, 1.0]]
D5 = [-0.2, 0.05, 0.001, -0.002, 0.01]


def _pinhole_file(distortion):
    data = nplps.Rig.pinhole(K_TEST, lights=LIGHTS).to_dict()
    data["camera"]["distortion"] = distortion
    return data


@pytest.mark.parametrize(
    "form",
    [
        D5,
        [D5],  # OpenCV's 1 x 5 (numpy's dist.tolist())
        [[v] for v in D5],  # OpenCV's 5 x 1
        np.array([D5]),
        tuple(D5),
        [*D5, 0.0, 0.0, 0.0],  # OpenCV's rational model with k4 = k5 = k6 = 0
        [D5 + [0.0] * 9],  # 1 x 14, the extra terms zero
    ],
    ids=["flat", "1x5", "5x1", "array", "tuple", "8", "1x14"],
)
def test_opencv_distortion_forms_mean_the_same_to_python_and_the_core(tmp_path, form):
    depth = np.full((4, 5), 150.0)
    flat = {"model": "pinhole", "K": K_TEST, "distortion": D5}
    expected = nplps._core.vertices(depth, flat)
    camera = {"model": "pinhole", "K": K_TEST, "distortion": form}
    # The core reads the nested forms itself (it used to drop them silently) ...
    np.testing.assert_array_equal(nplps._core.vertices(depth, camera), expected)
    assert nplps._core.normalize_camera(camera) == flat
    # ... and the file reader and the constructors give the same canonical camera.
    assert nplps.Rig.pinhole(K_TEST, lights=LIGHTS, distortion=form).camera == flat
    if not isinstance(form, np.ndarray):
        rig = nplps.Rig.load(_write(tmp_path, _pinhole_file(form)))
        assert rig.camera == flat
        np.testing.assert_array_equal(nplps._core.vertices(depth, rig.camera), expected)


@pytest.mark.parametrize(
    "distortion, message",
    [
        ([0.1, 0.0, 0.0], r"camera\.distortion has 3 coefficients, which is ambiguous"),
        ([0.0] * 6, r"camera\.distortion has 6 coefficients; OpenCV's models have 4, 5, 8, 12 or 14"),
        ([*D5, 0.1, 0.0, 0.0], r"camera\.distortion has 8 coefficients and k4 = 0\.1 is not zero"),
        ([[0.0] * 14 + [1.0]], r"camera\.distortion has 15 items; at most 14"),
        (
            [[0.1, 0.0], [0.0, 0.0]],
            r"camera\.distortion must be a list of numbers or OpenCV's 1 x n or n x 1 matrix, got a 2 x 2 matrix",
        ),
        ([[[0.1]]], r"camera\.distortion\[0\] must be a number, got a list of 1 item"),
        ("abc", r"camera\.distortion must be a list, got the string \"abc\""),
        ({"k1": 0.1}, r"camera\.distortion must be a list, got an object"),
        (0.1, r"camera\.distortion must be a list, got 0\.1"),
        ([0.1, True], r"camera\.distortion\[1\] must be a number, got the boolean true"),
        ([0.1, "0"], r"camera\.distortion\[1\] must be a number, got the string \"0\""),
        ([float("nan"), 0.0], r"camera\.distortion\[0\] must be a finite number, got NaN"),
        ([0.1, float("inf")], r"camera\.distortion\[1\] must be a finite number, got inf"),
        ([10**400, 0.0], r"camera\.distortion\[0\] is an integer too large for a floating-point number"),
    ],
)
def test_malformed_distortion_is_a_rig_error_naming_it(tmp_path, distortion, message):
    with pytest.raises(nplps.RigError, match=message):
        nplps._core.vertices(np.full((3, 3), 100.0), {"model": "pinhole", "K": K_TEST, "distortion": distortion})
    with pytest.raises(nplps.RigError, match=message):
        nplps.Rig.load(_write(tmp_path, _pinhole_file(distortion)))
    with pytest.raises(nplps.RigError, match=message):
        nplps.Rig.pinhole(K_TEST, lights=LIGHTS, distortion=distortion)


def test_distortion_that_cannot_be_undone_is_a_rig_error():
    """Far from the centre a strong barrel distortion maps no ray: refused, not a made-up ray."""
    camera = {"model": "pinhole", "K": [[10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [0.0, 0.0, 1.0]], "distortion": [-0.2, 0.0]}
    assert np.isfinite(nplps._core.vertices(np.full((5, 5), 100.0), camera)).all()
    with pytest.raises(
        nplps.RigError, match=r"no ray at pixel corner \(row \d+, column \d+\): its distortion cannot be undone"
    ):
        nplps._core.vertices(np.full((12, 12), 100.0), camera)
    # Vertices of unknown depth (outside a reconstruction's mask) need no ray.
    depth = np.full((12, 12), np.nan)
    depth[:5, :5] = 100.0
    v = nplps._core.vertices(depth, camera)
    assert np.isfinite(v[:5, :5]).all() and np.isnan(v[6:, 6:]).all()


@pytest.mark.parametrize("nesting", [100, 100_000])
def test_deeply_nested_rig_files_are_rig_errors(tmp_path, nesting):
    path = tmp_path / "rig.json"
    path.write_text("[" * nesting + "]" * nesting, encoding="utf-8")
    with pytest.raises(
        nplps.RigError, match=rf"rig file '.*rig\.json' is nested too deeply \({nesting} levels; at most 64\)"
    ):
        nplps.Rig.load(path)
    # Nested inside a comment of a good file: still too deep; at 60 levels it is read.
    data = _good()
    data["_note"] = _deep = []
    for _ in range(nesting - 2):
        _deep.append([])
        _deep = _deep[0]
    if nesting < 900:
        with pytest.raises(nplps.RigError, match=r"nested too deeply"):
            nplps.Rig.load(_write(tmp_path, data))
    data["_note"] = json.loads("[" * 60 + "]" * 60)
    assert nplps.Rig.load(_write(tmp_path, data)).n_lights == 4


def test_brackets_in_strings_do_not_count_as_nesting(tmp_path):
    data = _good()
    data["_note"] = "[" * 1000 + "{" * 1000
    assert nplps.Rig.load(_write(tmp_path, data)).n_lights == 4


def test_oversized_and_odd_json_files_are_rig_errors(tmp_path):
    path = tmp_path / "rig.json"
    path.write_bytes(b" " * (16 * 2**20) + b"{}")
    with pytest.raises(nplps.RigError, match=r"is larger than 16 MiB"):
        nplps.Rig.load(path)
    path.write_text('{"version": ' + "9" * 5000 + ', "camera": {"model": "pinhole"}, "lights": []}', encoding="utf-8")
    with pytest.raises(nplps.RigError, match=r"'version' must be an integer, got an integer too large for a floating"):
        nplps.Rig.load(path)
    path.write_bytes(b"\xff\xfe{}")
    with pytest.raises(nplps.RigError, match=r"is not a JSON text file \(not UTF-8\)"):
        nplps.Rig.load(path)
    # A UTF-8 byte order mark (Windows editors) is fine.
    path.write_bytes(b"\xef\xbb\xbf" + json.dumps(_good()).encode())
    assert nplps.Rig.load(path).n_lights == 4


@pytest.mark.parametrize(
    "edit, message",
    [
        (
            lambda d: d["lights"][0].update(position=[float("nan"), 0, 0]),
            r"light 0 position\[0\] must be a finite number, got NaN",
        ),
        (
            lambda d: d["lights"][1].update(intensity=float("inf")),
            r"light 1 intensity must be a finite number, got inf",
        ),
        (
            lambda d: d["lights"][2].update(intensity=[1, float("-inf"), 1]),
            r"light 2 intensity\[1\] must be a finite number, got -inf",
        ),
        (
            lambda d: d["lights"][0].update(mu=float("nan"), direction=[0, 0, 1]),
            r"light 0 mu must be a finite number, got NaN",
        ),
        (
            lambda d: d["lights"][0].update(mu=1, direction=[0, float("nan"), 1]),
            r"light 0 direction\[1\] must be a finite number",
        ),
        (
            lambda d: d["camera"].update(pixel_size=[1, float("nan")]),
            r"camera\.pixel_size\[1\] must be a finite number, got NaN",
        ),
        (
            lambda d: d["camera"].update(origin=[float("inf"), 0]),
            r"camera\.origin\[0\] must be a finite number, got inf",
        ),
        (
            lambda d: d["lights"][0].update(position=[1e13, 0, 0]),
            r"light 0's position has the value 1\.00000e13, beyond 1\.00000e12 in magnitude",
        ),
        (
            lambda d: d["camera"].update(pixel_size=[1e-300, 1]),
            r"pixel size must be at least 1\.00000e-12, got \[1\.00000e-300, 1\]",
        ),
    ],
)
def test_non_finite_and_absurd_values_are_rig_errors(tmp_path, edit, message):
    data = _good()
    edit(data)
    with pytest.raises(nplps.RigError, match=message) as info:
        nplps.Rig.load(_write(tmp_path, data))
    assert len(str(info.value)) < 300


def test_non_finite_pinhole_values_are_rig_errors(tmp_path):
    data = _pinhole_file(D5)
    data["camera"]["K"][0][2] = float("nan")
    with pytest.raises(nplps.RigError, match=r"camera\.K\[0\]\[2\] must be a finite number, got NaN"):
        nplps.Rig.load(_write(tmp_path, data))
    data["camera"]["K"] = [[500, 0, 2], [0, 500, 2]]
    with pytest.raises(nplps.RigError, match=r"camera\.K must be a 3 x 3 matrix, got a list of 2 items"):
        nplps.Rig.load(_write(tmp_path, data))


def test_too_many_lights_are_a_rig_error(tmp_path):
    data = _good()
    data["lights"] = [{"position": [float(i % 100), float(i // 100), -10.0]} for i in range(nplps.rig.MAX_LIGHTS + 1)]
    with pytest.raises(nplps.RigError, match=r"the rig has 10001 lights; at most 10000 are supported"):
        nplps.Rig.load(_write(tmp_path, data))


def test_anisotropic_led_needs_a_nonzero_finite_axis():
    """A zero axis used to become +z silently."""
    with pytest.raises(nplps.RigError, match=r"light 1: an anisotropic LED \(mu = 2\) needs a non-zero axis"):
        nplps.Rig.orthographic(1.0, lights=LIGHTS, axes=[[0, 0, 1], [0, 0, 0], [0, 0, 1], [0, 0, 1]], mu=[1, 2, 1, 1])
    with pytest.raises(nplps.RigError, match=r"light 0 axis\[1\] must be a finite number, got inf"):
        nplps.Rig.orthographic(1.0, lights=LIGHTS, axes=[[0, np.inf, 1]] + [[0, 0, 1]] * 3, mu=[1] * 4)
    with pytest.raises(nplps.RigError, match=r"light 0: an anisotropic LED \(mu = 1\) needs its axis"):
        nplps.Rig.orthographic(1.0, lights=LIGHTS, axes=[[np.nan] * 3] + [[0, 0, 1]] * 3, mu=[1] * 4)
    # An isotropic light's axis is unused: it is a PointLight, whatever its axis.
    rig = nplps.Rig.orthographic(1.0, lights=LIGHTS, axes=[[0, 0, 0]] * 4, mu=[0] * 4)
    assert all(type(light) is nplps.PointLight for light in rig.lights)
    assert np.isnan(rig.axes).all()
    # An LED of mu = 0 built by hand keeps its axis; a zero one stands for +z.
    assert nplps.LED((0, 0, 0), axis=(0, 0, 0), mu=0).axis == (0.0, 0.0, 1.0)
    with pytest.raises(nplps.RigError, match=r"LED: an anisotropic LED \(mu = 1\) needs a non-zero axis"):
        nplps.LED((0, 0, 0), axis=(0, 0, 0))


def test_non_mapping_camera_and_bool_arrays_are_rig_errors():
    with pytest.raises(
        nplps.RigError, match=r"camera must be a mapping \(the rig file's camera object\), got a list of 2 items"
    ):
        nplps.Rig(camera=["orthographic", 1.0], lights=LIGHTS)
    with pytest.raises(nplps.RigError, match=r"lights must be numbers, got an array of booleans"):
        nplps.Rig.orthographic(1.0, lights=np.ones((4, 3), dtype=bool))
    with pytest.raises(nplps.RigError, match=r"lights must be numbers, got an array of strings"):
        nplps.Rig.orthographic(1.0, lights=[["1", "2", "3"]] * 4)
    with pytest.raises(nplps.RigError, match=r"mu must be numbers, got an array of strings"):
        nplps.Rig.orthographic(1.0, lights=LIGHTS, mu=["yes"] * 4)


def test_the_core_refuses_malformed_light_mappings():
    """The core's lights mapping (built by Rig) is checked as strictly as the camera."""
    rig = nplps.Rig.orthographic(1.0, lights=LIGHTS)
    lights = rig._core_lights()
    for key, value, message in [
        ("mu", [0, 0, "1", 0], r"lights\.mu\[2\] must be a number, got the string \"1\""),
        ("directional", [0, 0, 0, 0], r"lights\.directional\[0\] must be a boolean, got 0"),
        ("vectors", [[0, 0, 0]] * 3 + [[0, 0]], r"lights\.vectors\[3\] must be 3 numbers, got a list of 2 items"),
        ("intensities", [[1, 1, True]] * 4, r"lights\.intensities\[0\]\[2\] must be a number, got the boolean true"),
        ("extra", [], r"lights has an unknown key \"extra\""),
    ]:
        with pytest.raises(nplps.RigError, match=message):
            nplps._core.check_rig(rig.camera, {**lights, key: value})


def test_the_readme_rig_file_examples_are_read():
    import pathlib
    import re

    readme = (pathlib.Path(__file__).parent.parent / "README.md").read_text(encoding="utf-8")
    blocks = re.findall(r"```json\n(.*?)```", readme, re.S)
    assert len(blocks) >= 2
    for block in blocks:
        assert nplps.Rig.from_dict(json.loads(block), source="README").n_lights >= 3


# ------------------------------------------------------------------------------------------------
# typed lights (issue 10): PointLight, LED, DirectionalLight; Rig.lights a tuple of them
# ------------------------------------------------------------------------------------------------
ORTHO = {"model": "orthographic", "pixel_size": [1.0, 1.0], "origin": [0.0, 0.0]}
NAN3 = [np.nan] * 3


def _mixed_rig():
    return nplps.Rig(
        ORTHO,
        [
            nplps.PointLight((-30.0, 0.0, 0.0)),
            nplps.LED([30.0, 10.0, 0.0], [0.9, 1.0, 1.1], axis=(0.0, 0.0, 2.0), mu=1.5),
            nplps.DirectionalLight(np.array([0.0, 0.0, -3.0]), intensity=0.5),
            nplps.PointLight((5.0, 25.0, -20.0), 2),
        ],
    )


def test_light_values_are_typed_frozen_and_normalized():
    p = nplps.PointLight([1, 2, 3])
    assert p.position == (1.0, 2.0, 3.0) and p.intensity == (1.0, 1.0, 1.0)
    assert all(type(v) is float for v in p.position + p.intensity)
    assert nplps.PointLight((1, 2, 3), np.float32(0.5)).intensity == (0.5, 0.5, 0.5)
    assert nplps.PointLight((1, 2, 3), (0.5, 1, 2)).intensity == (0.5, 1.0, 2.0)
    led = nplps.LED((0, 0, -10), axis=(0, 3, 4), mu=2)
    assert led.axis == (0.0, 0.6, 0.8) and led.mu == 2.0 and led.intensity == (1.0, 1.0, 1.0)
    assert nplps.LED((0, 0, 0), axis=(1e300, 0, 1e300)).axis == pytest.approx((2**-0.5, 0.0, 2**-0.5))
    d = nplps.DirectionalLight((0, 0, -2))
    assert d.direction == (0.0, 0.0, -1.0)
    with pytest.raises(AttributeError):
        p.position = (0.0, 0.0, 0.0)  # type: ignore[misc]
    # Values: equal when their fields are, hashable.
    assert nplps.PointLight((1, 2, 3)) == p and hash(nplps.PointLight((1, 2, 3))) == hash(p)
    assert nplps.PointLight((1, 2, 3)) != nplps.LED((1, 2, 3), axis=(0, 0, 1), mu=0)
    assert repr(d) == "DirectionalLight(direction=(0.0, 0.0, -1.0), intensity=(1.0, 1.0, 1.0))"


@pytest.mark.parametrize(
    "build, message",
    [
        (lambda: nplps.PointLight((0, 0)), r"PointLight position must be 3 numbers, got a tuple of 2 items"),
        (lambda: nplps.PointLight((0, np.nan, 0)), r"PointLight position\[1\] must be a finite number, got nan"),
        (lambda: nplps.PointLight((0, "1", 0)), r"PointLight position\[1\] must be a number, got the string \"1\""),
        (lambda: nplps.PointLight((0, 0, 0), 0.0), r"PointLight must have positive intensities, got \[0, 0, 0\]"),
        (lambda: nplps.PointLight((0, 0, 0), (1, -1, 1)), r"PointLight must have positive intensities"),
        (
            lambda: nplps.PointLight((0, 0, 0), (1, 1)),
            r"PointLight intensity must be 3 numbers, got a tuple of 2 items",
        ),
        (lambda: nplps.PointLight((0, 0, 0), np.inf), r"PointLight intensity must be a finite number, got inf"),
        (lambda: nplps.PointLight((0, 0, 0), True), r"PointLight intensity must be a number, got the boolean true"),
        (lambda: nplps.LED((0, 0, 0), axis=(0, 0, 1), mu=-1), r"LED has anisotropy mu = -1; it must be >= 0"),
        (lambda: nplps.LED((0, 0, 0), axis=(0, 0, 1), mu=np.nan), r"LED mu must be a finite number, got nan"),
        (
            lambda: nplps.LED((0, 0, 0), axis=(0, 0, 0), mu=1),
            r"LED: an anisotropic LED \(mu = 1\) needs a non-zero axis",
        ),
        (lambda: nplps.LED((0, 0, 0), axis=(0, np.inf, 0)), r"LED axis\[1\] must be a finite number, got inf"),
        (lambda: nplps.DirectionalLight((0, 0, 0)), r"DirectionalLight: a directional light needs a unit direction"),
        (lambda: nplps.DirectionalLight((0, 0, -1), -1), r"DirectionalLight must have positive intensities"),
    ],
)
def test_light_values_are_validated_on_construction(build, message):
    with pytest.raises(nplps.RigError, match=message):
        build()


def test_rig_holds_light_values_and_array_views():
    rig = _mixed_rig()
    assert isinstance(rig.lights, tuple) and rig.n_lights == 4
    assert [type(light) for light in rig.lights] == [
        nplps.PointLight,
        nplps.LED,
        nplps.DirectionalLight,
        nplps.PointLight,
    ]
    np.testing.assert_array_equal(rig.positions, [[-30, 0, 0], [30, 10, 0], NAN3, [5, 25, -20]])
    np.testing.assert_array_equal(rig.directions, [NAN3, NAN3, [0, 0, -1], NAN3])
    np.testing.assert_array_equal(rig.axes, [NAN3, [0, 0, 1], NAN3, NAN3])
    np.testing.assert_array_equal(rig.intensities, [[1, 1, 1], [0.9, 1, 1.1], [0.5] * 3, [2] * 3])
    np.testing.assert_array_equal(rig.mu, [0, 1.5, 0, 0])
    np.testing.assert_array_equal(rig.directional, [False, False, True, False])
    for name, shape, dtype in [
        ("positions", (4, 3), np.float64),
        ("directions", (4, 3), np.float64),
        ("axes", (4, 3), np.float64),
        ("intensities", (4, 3), np.float64),
        ("mu", (4,), np.float64),
        ("directional", (4,), np.bool_),
    ]:
        view = getattr(rig, name)
        assert view.shape == shape and view.dtype == dtype and not view.flags.writeable, name
        assert getattr(rig, name) is view  # computed once
    # The compiled core's form is the one the bindings take (an unused axis is +z).
    assert rig._core_lights() == {
        "vectors": [[-30.0, 0.0, 0.0], [30.0, 10.0, 0.0], [0.0, 0.0, -1.0], [5.0, 25.0, -20.0]],
        "directional": [False, False, True, False],
        "intensities": [[1.0] * 3, [0.9, 1.0, 1.1], [0.5] * 3, [2.0] * 3],
        "axes": [[0.0, 0.0, 1.0]] * 4,
        "mu": [0.0, 1.5, 0.0, 0.0],
        "kind": ["point", "led", "directional", "point"],
    }


def test_rig_equality_hash_subset_and_replace():
    rig = _mixed_rig()
    assert rig == _mixed_rig() and hash(rig) == hash(_mixed_rig())
    assert rig != rig.subset([0, 1, 3, 2]) and rig.subset([0, 1, 2, 3]) == rig
    sub = rig.subset([3, 2, 1])
    assert sub.lights == (rig.lights[3], rig.lights[2], rig.lights[1]) and sub.camera == rig.camera
    moved = dataclasses.replace(rig, camera={**ORTHO, "pixel_size": [2.0, 2.0]})
    assert moved.lights == rig.lights and moved.camera["pixel_size"] == [2.0, 2.0]
    assert dataclasses.replace(rig, lights=rig.lights[:2]).n_lights == 2
    with pytest.raises(nplps.RigError, match="at least one light"):
        dataclasses.replace(rig, lights=())


def test_rig_refuses_mixed_or_foreign_lights():
    with pytest.raises(
        nplps.RigError, match=r"lights: light 1 is a list of 3 items, not a PointLight, LED or DirectionalLight"
    ):
        nplps.Rig(ORTHO, [nplps.PointLight((0, 0, 0)), [1.0, 0.0, 0.0], nplps.PointLight((0, 1, 0))])
    with pytest.raises(nplps.RigError, match=r"intensities= goes with an array of positions, not with light values"):
        nplps.Rig.orthographic(1.0, lights=list(_mixed_rig().lights), intensities=2.0)
    with pytest.raises(TypeError, match=r"unexpected keyword argument 'directional_lights'"):
        nplps.Rig.orthographic(1.0, lights=LIGHTS, directional_lights=[[0, 0, -1]])
    with pytest.raises(TypeError):
        nplps.Rig(ORTHO, LIGHTS, directional=[False] * 4)  # type: ignore[call-arg]


def test_from_arrays_is_the_inverse_of_the_views():
    rig = _mixed_rig()
    views = dict(directions=rig.directions, intensities=rig.intensities, axes=rig.axes, mu=rig.mu)
    assert nplps.Rig.from_arrays(rig.camera, rig.positions, **views) == rig
    # Only point lights, or only directional lights.
    points = nplps.Rig.from_arrays(ORTHO, LIGHTS, intensities=[1, 2, 3, 4])
    assert all(type(light) is nplps.PointLight for light in points.lights)
    np.testing.assert_array_equal(points.intensities[:, 1], [1, 2, 3, 4])
    far = nplps.Rig.from_arrays(ORTHO, directions=[[0, 0, -1], [0.3, 0, -1], [0, 0.3, -1]])
    assert far.directional.all() and np.isnan(far.positions).all()
    np.testing.assert_allclose(np.linalg.norm(far.directions, axis=1), 1.0)
    # An LED is a point light with mu > 0; mu = 0 is a PointLight whatever its axis.
    leds = nplps.Rig.from_arrays(ORTHO, LIGHTS, axes=[[0, 0, 1]] * 4, mu=[1, 0, 2, 0])
    assert [type(light).__name__ for light in leds.lights] == ["LED", "PointLight", "LED", "PointLight"]
    # Orthographic and pinhole take the same arrays.
    assert nplps.Rig.orthographic(1.0, lights=LIGHTS, axes=[[0, 0, 1]] * 4, mu=[1, 0, 2, 0]) == leds


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(positions=LIGHTS, directions=[[0, 0, -1]] * 4), r"light 0 has both a position and a direction: give NaN"),
        (dict(positions=[NAN3] * 4, directions=[NAN3] * 4), r"light 0 has neither a position nor a direction"),
        (
            dict(positions=[NAN3, *LIGHTS[1:]], directions=[[0, 0, -1]] + [NAN3] * 3, mu=[1, 0, 0, 0]),
            r"light 0 is directional: it has no anisotropy \(mu = 1\)",
        ),
        (
            dict(positions=LIGHTS, directions=[[0, 0, -1]] * 3),
            r"directions must be a \(4, 3\) array, got shape \(3, 3\)",
        ),
        (
            dict(positions=LIGHTS, mu=[1, 0, 0, 0]),
            r"light 0: an anisotropic LED \(mu = 1\) needs its axis \(axes=\.\.\.\)",
        ),
        (dict(positions=LIGHTS, axes=[[0, 0, 1]] * 4, mu=[0, 0, 0]), r"mu must be a \(4,\) array, got shape \(3,\)"),
        (dict(positions=np.zeros((4, 2))), r"positions must be a \(k, 3\) array, got shape \(4, 2\)"),
        (dict(positions=LIGHTS, intensities=[1, 1]), r"intensities must be a number, \(k,\) or \(k, 3\)"),
        (dict(directions=[[0, 0, 0]] * 3), r"light 0: a directional light needs a unit direction"),
        (dict(), r"a rig needs at least one light, it has 0 lights"),
    ],
)
def test_from_arrays_errors(kwargs, message):
    with pytest.raises(nplps.RigError, match=message):
        nplps.Rig.from_arrays(ORTHO, **kwargs)


def test_with_positions_and_intensities():
    rig = _mixed_rig()
    moved = rig.with_positions(rig.positions + 1.0)  # NaN rows stay NaN
    np.testing.assert_array_equal(moved.positions, rig.positions + 1.0)
    assert moved.lights[2] is rig.lights[2]
    assert moved.lights[1].axis == rig.lights[1].axis and moved.lights[1].mu == 1.5
    with pytest.raises(nplps.RigError, match=r"positions: light 2 is a directional light: its row must be NaN"):
        rig.with_positions(np.zeros((4, 3)))
    with pytest.raises(nplps.RigError, match=r"light 0 position\[0\] must be a finite number"):
        rig.with_positions([NAN3] * 4)
    brighter = rig.with_intensities(rig.intensities * 2)
    np.testing.assert_array_equal(brighter.intensities, rig.intensities * 2)
    np.testing.assert_array_equal(brighter.positions, rig.positions)
    assert rig.with_intensities(3.0).intensities.min() == 3.0
    with pytest.raises(nplps.RigError, match=r"light 1 must have positive intensities"):
        rig.with_intensities([1, 0, 1, 1])


def test_rig_file_round_trip_of_typed_lights(tmp_path):
    rig = nplps.Rig(
        ORTHO,
        [*_mixed_rig().lights, nplps.LED((1, 2, -3), axis=(0, 0.6, 0.8), mu=0.0)],
    )
    path = tmp_path / "rig.json"
    rig.save(path)
    data = json.loads(path.read_text())
    assert data["lights"][1] == {
        "type": "point",
        "position": [30.0, 10.0, 0.0],
        "intensity": [0.9, 1.0, 1.1],
        "direction": [0.0, 0.0, 1.0],
        "mu": 1.5,
    }
    assert data["lights"][2] == {"type": "directional", "direction": [0.0, 0.0, -1.0], "intensity": 0.5}
    assert data["lights"][4]["direction"] == list(rig.lights[4].axis) and data["lights"][4]["mu"] == 0.0
    loaded = nplps.Rig.load(path)
    assert loaded.lights[:4] == rig.lights[:4]
    assert type(loaded.lights[4]) is nplps.LED  # a "direction" makes an LED, also with mu = 0
    # An LED's axis is scaled to unit length when read (as it always was), which may change
    # its last bit: (0, 0.6, 0.8) became (0, 0.5999999999999999, 0.8) when built, and that
    # reads back as (0, 0.6, 0.8000000000000002).
    assert loaded.lights[4].axis == pytest.approx(rig.lights[4].axis, abs=1e-15)
    # A rig read and written again gives the same bytes when its axes are fixed points.
    first, again = tmp_path / "first.json", tmp_path / "again.json"
    _mixed_rig().save(first)
    nplps.Rig.load(first).save(again)
    assert again.read_bytes() == first.read_bytes()
    # A point light with "mu": 0 and no "direction" is a PointLight.
    data["lights"][0]["mu"] = 0
    assert type(nplps.Rig.from_dict(data).lights[0]) is nplps.PointLight
    data["lights"][0]["mu"] = 1
    with pytest.raises(nplps.RigError, match=r"light 0: an anisotropic LED \(mu = 1\) needs its principal 'direction'"):
        nplps.Rig.from_dict(data)


def test_directional_directions_in_files_must_be_unit_and_are_kept():
    data = _mixed_rig().to_dict()
    data["lights"][2]["direction"] = [0.0, 0.6, -0.8000001]  # within 1e-6 of unit: kept as written
    assert nplps.Rig.from_dict(data).lights[2].direction == (0.0, 0.6, -0.8000001)
    data["lights"][2]["direction"] = [0.0, 0.0, -2.0]
    with pytest.raises(nplps.RigError, match=r"rig: light 2: a directional light needs a unit direction"):
        nplps.Rig.from_dict(data)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_binned(n):
    ortho = nplps.Rig.orthographic((0.5, 0.25), origin=(-8.0, 4.0), lights=LIGHTS)
    b = ortho.binned(n)
    assert b.camera == {"model": "orthographic", "pixel_size": [0.5 * n, 0.25 * n], "origin": [-8.0, 4.0]}
    assert b.lights == ortho.lights
    K = [[800.0, 0.5, 319.5], [0.0, 810.0, 239.5], [0.0, 0.0, 1.0]]
    pin = nplps.Rig.pinhole(K, lights=_mixed_rig().lights, distortion=[-0.1, 0.01])
    b = pin.binned(n)
    np.testing.assert_array_equal(b.K, nplps.preprocess.bin_intrinsics(np.array(K), n))
    assert b.camera["distortion"] == pin.camera["distortion"] and b.lights == pin.lights


def test_binned_vertices_cover_the_same_footprint():
    """Binned vertex (r, c) is original vertex (n r, n c) for the orthographic camera."""
    rig = nplps.Rig.orthographic((0.5, 0.25), origin=(-8.0, 4.0), lights=LIGHTS)
    v = nplps._core.vertices(np.full((13, 13), 100.0), rig.camera)
    vb = nplps._core.vertices(np.full((5, 5), 100.0), rig.binned(3).camera)
    np.testing.assert_allclose(vb, v[::3, ::3][:5, :5])


@pytest.mark.parametrize("n", [0, -2, 1.5, True, "2", None])
def test_binned_refuses_bad_factors(n):
    with pytest.raises(nplps.RigError, match="binning factor must be a whole number of at least 1"):
        nplps.Rig.orthographic(1.0, lights=LIGHTS).binned(n)


def test_lights_of_a_scene_are_typed():
    scene = nplps.make_scene("saddle", n=8, camera="pinhole", led=True, directional=True)
    kinds = {type(light) for light in scene.rig.lights}
    assert kinds == {nplps.LED, nplps.DirectionalLight}
    assert (scene.rig.mu[~scene.rig.directional] > 0).all()


def test_rig_pickles_without_its_views():
    import pickle

    rig = _mixed_rig()
    assert not rig.positions.flags.writeable
    again = pickle.loads(pickle.dumps(rig))
    assert again == rig and "positions" not in again.__dict__
    assert not again.positions.flags.writeable
