"""Tests of nplps.Rig: construction, the orthographic camera's pixel size, and the rig file."""

from __future__ import annotations

import json

import numpy as np
import pytest

import nplps
from nplps import reference as ref

LIGHTS = [[-30.0, 0.0, 0.0], [30.0, 10.0, 0.0], [0.0, -30.0, -50.0], [5.0, 25.0, -20.0]]


# ------------------------------------------------------------------------------------------------
# construction
# ------------------------------------------------------------------------------------------------
def test_orthographic_scalar_and_pair_pixel_size():
    scalar = nplps.Rig.orthographic(0.5, lights=LIGHTS)
    pair = nplps.Rig.orthographic((0.5, 0.5), lights=LIGHTS)
    assert scalar.camera == pair.camera == {"model": "orthographic", "pixel_size": [0.5, 0.5], "origin": [0.0, 0.0]}
    np.testing.assert_array_equal(scalar.lights, pair.lights)

    rect = nplps.Rig.orthographic((0.5, 0.25), origin=(-8.0, 4.0), lights=LIGHTS)
    assert rect.camera["pixel_size"] == [0.5, 0.25]  # (w, h): x first
    assert rect.camera["origin"] == [-8.0, 4.0]
    assert rect.n_lights == 4
    assert rect.lights.dtype == np.float64 and rect.lights.shape == (4, 3)
    assert rect.lights.flags["C_CONTIGUOUS"]
    # integers and numpy scalars are accepted
    assert nplps.Rig.orthographic(np.float32(2), lights=LIGHTS).camera["pixel_size"] == [2.0, 2.0]
    assert nplps.Rig.orthographic(2, lights=LIGHTS).camera["pixel_size"] == [2.0, 2.0]


def test_rig_is_frozen():
    rig = nplps.Rig.orthographic(1.0, lights=LIGHTS)
    with pytest.raises(AttributeError):
        rig.lights = np.zeros((3, 3))  # type: ignore[misc]


@pytest.mark.parametrize(
    "pixel_size, message",
    [
        ((1.0,), r"pixel_size must be two numbers"),
        ((1.0, 2.0, 3.0), r"pixel_size must be two numbers"),
        (0.0, r"pixel size must be positive and finite"),
        ((0.5, -0.5), r"pixel size must be positive and finite"),
        ((np.inf, 1.0), r"pixel size must be positive and finite"),
    ],
)
def test_orthographic_bad_pixel_size(pixel_size, message):
    with pytest.raises(nplps.RigError, match=message):
        nplps.Rig.orthographic(pixel_size, lights=LIGHTS)


def test_orthographic_non_numeric_scalar_pixel_size():
    with pytest.raises(nplps.RigError, match=r"pixel_size must be"):
        nplps.Rig.orthographic("ab", lights=LIGHTS)


def test_orthographic_bad_origin_and_lights():
    with pytest.raises(nplps.RigError, match=r"origin must be finite"):
        nplps.Rig.orthographic(1.0, origin=(np.nan, 0.0), lights=LIGHTS)
    with pytest.raises(nplps.RigError, match=r"at least 3 lights, the rig has 2"):
        nplps.Rig.orthographic(1.0, lights=LIGHTS[:2])
    with pytest.raises(nplps.RigError, match=r"at least 3 lights, the rig has 0"):
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

    r = nplps.reconstruct(images, rig, None, depth.mean())
    err = angular_error(r.normals, truth).mean()
    assert err < 1e-3
    assert np.abs(r.depth - depth).max() < 1e-4
    np.testing.assert_allclose(r.mesh_normals, ref.mesh_normals(r.depth, pixel_size, origin), rtol=0, atol=1e-12)
    np.testing.assert_allclose(r.vertices[..., 0][0], origin[0] + np.arange(49) * pixel_size[0])
    np.testing.assert_allclose(r.vertices[..., 1][:, 0], origin[1] + np.arange(33) * pixel_size[1])

    swapped = nplps.Rig.orthographic(pixel_size[::-1], origin, lights)
    r = nplps.reconstruct(images, swapped, None, depth.mean())
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
    assert data["version"] == 2
    assert data["camera"] == {"model": "orthographic", "pixel_size": [0.5, 0.25], "origin": [-8.0, 4.125]}
    assert data["lights"] == [{"type": "point", "position": list(p), "intensity": 1.0} for p in rig.lights.tolist()]

    loaded = nplps.Rig.load(path)
    assert loaded.camera == rig.camera
    np.testing.assert_array_equal(loaded.lights, rig.lights)  # exact: JSON floats round-trip
    assert nplps.Rig.load(str(path)).camera == rig.camera
    assert nplps.Rig.from_dict(rig.to_dict()).camera == rig.camera


def test_load_ignores_unknown_keys(tmp_path):
    data = nplps.Rig.orthographic(1.0, lights=LIGHTS).to_dict()
    data["comment"] = "made by hand"
    data["camera"]["serial"] = "A123"
    data["lights"][0]["intensity"] = 0.9
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(data), encoding="utf-8")
    rig = nplps.Rig.load(path)
    np.testing.assert_array_equal(rig.lights, LIGHTS)


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
        ([1, 2, 3], r"rig\.json: a rig file holds a JSON object, got list"),
        (_edit(lambda d: d.pop("lights")), r"rig\.json: missing key\(s\) lights"),
        (_edit(lambda d: (d.pop("version"), d.pop("camera"))), r"missing key\(s\) version, camera"),
        (_edit(lambda d: d.update(version=3)), r"unsupported rig file version 3 \(this nplps reads 1\.\.2\)"),
        (_edit(lambda d: d.update(version=0)), r"unsupported rig file version 0"),
        (_edit(lambda d: d.update(version="1")), r"unsupported rig file version '1'"),
        (_edit(lambda d: d["lights"][1].pop("position")), r"light 1 position must be 3 numbers, got None"),
        (_edit(lambda d: d["lights"][2].update(position=[1, 2])), r"light 2 position must have 3 numbers, got 2"),
        (_edit(lambda d: d["lights"][0].update(position=["a", 0, 0])), r"light 0 position must be 3 numbers"),
        (_edit(lambda d: d.update(lights={"position": [0, 0, 0]})), r"'lights' must be a list"),
        (_edit(lambda d: d.update(lights=d["lights"][:2])), r"at least 3 lights, the rig has 2"),
        (_edit(lambda d: d.update(camera=[])), r"'camera' must be an object with a 'model' key"),
        (_edit(lambda d: d["camera"].pop("pixel_size")), r"orthographic camera needs 'pixel_size'"),
        (_edit(lambda d: d["camera"].update(origin=[0])), r"camera\.origin must be two numbers"),
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
    path.write_text(json.dumps({
        "version": 1,
        "camera": {"model": "orthographic", "pixel_size": [1, 1], "origin": [0, 0]},
        "lights": [{"position": p} for p in LIGHTS],
    }))
    rig = nplps.Rig.load(path)
    np.testing.assert_array_equal(rig.lights, np.array(LIGHTS, dtype=float))
    np.testing.assert_array_equal(rig.intensities, 1.0)
    assert not rig.directional.any() and not rig.mu.any()


def test_pinhole_led_rig_round_trip(tmp_path):
    K = [[800.0, 0.0, 319.5], [0.0, 810.0, 239.5], [0.0, 0.0, 1.0]]
    rig = nplps.Rig.pinhole(
        K,
        lights=[[50.0, 0.0, -10.0], [-40.0, 30.0, -5.0], [0.0, -45.0, -20.0]],
        distortion=[-0.1, 0.01],
        intensities=[1.0, [0.9, 1.0, 1.1], 1.2],
        directions=[[0, 0, 1], [0.1, 0, 1], [0, 0.2, 1]],
        mu=[1.0, 0.0, 2.0],
        directional_lights=[[0.0, 0.0, -2.0]],
        directional_intensities=[0.5],
    )
    assert rig.n_lights == 4 and rig.is_pinhole
    np.testing.assert_allclose(np.linalg.norm(rig.directions, axis=1), 1.0)
    np.testing.assert_array_equal(rig.lights[3], [0.0, 0.0, -1.0])  # normalized
    path = tmp_path / "rig.json"
    rig.save(path)
    data = json.loads(path.read_text())
    assert data["camera"]["model"] == "pinhole" and data["camera"]["distortion"] == [-0.1, 0.01, 0.0, 0.0, 0.0]
    assert [light["type"] for light in data["lights"]] == ["point", "point", "point", "directional"]
    assert "mu" not in data["lights"][1] and data["lights"][2]["mu"] == 2.0
    loaded = nplps.Rig.load(path)
    for name in ("lights", "intensities", "mu", "directional"):
        np.testing.assert_allclose(getattr(loaded, name), getattr(rig, name))
    np.testing.assert_allclose(loaded.directions[[0, 2]], rig.directions[[0, 2]])
    np.testing.assert_allclose(loaded.K, K)


def test_pinhole_and_led_errors():
    good_k = [[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]]
    with pytest.raises(nplps.RigError, match=r"K must be \[\[fx, s, cx\]"):
        nplps.Rig.pinhole([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 1.0, 1.0]], lights=LIGHTS)
    with pytest.raises(nplps.RigError, match=r"K must be a 3 x 3 matrix"):
        nplps.Rig.pinhole(np.eye(2), lights=LIGHTS)
    with pytest.raises(nplps.RigError, match=r"need their principal directions"):
        nplps.Rig.pinhole(good_k, lights=LIGHTS, mu=[1.0] * len(LIGHTS))
    with pytest.raises(nplps.RigError, match=r"anisotropy mu = -1"):
        nplps.Rig.pinhole(good_k, lights=LIGHTS, directions=[[0, 0, 1]] * len(LIGHTS), mu=[-1.0] + [1.0] * (len(LIGHTS) - 1))
    with pytest.raises(nplps.RigError, match=r"positive intensities"):
        nplps.Rig.pinhole(good_k, lights=LIGHTS, intensities=[1.0, 0.0] + [1.0] * (len(LIGHTS) - 2))
    with pytest.raises(nplps.RigError, match=r"intensities must be a number, \(k,\) or \(k, 3\)"):
        nplps.Rig.pinhole(good_k, lights=LIGHTS, intensities=[1.0, 2.0])
