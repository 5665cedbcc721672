"""Rig interchange formats: .dome, .lp, AliceVision lights.json and SfMData, OpenCV cameras."""

from __future__ import annotations

import json

import numpy as np
import pytest

import nplps
from nplps import rig_formats
from nplps.cli import main
from nplps.errors import RigError
from nplps.rig import LED, DirectionalLight, PointLight, Rig

K = [[812.5, 0.0, 319.5], [0.0, 815.25, 241.0], [0.0, 0.0, 1.0]]
DIST = [0.101, -0.02, 0.0015, -0.0007, 0.003]


def _directions(rng: np.random.Generator, k: int = 12) -> np.ndarray:
    d = rng.normal(size=(k, 3))
    d[:, 2] = -np.abs(d[:, 2]) - 0.5  # towards the camera
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _point_rig(seed: int) -> Rig:
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(15, 3)) * rng.uniform(1, 300)
    p[:, 2] = rng.uniform(-50, 150, 15)
    return Rig.pinhole(K, p, distortion=DIST, intensities=rng.uniform(0.1, 5.0, (15, 3))).with_grid(640, 480)


def _directional_rig(seed: int, intensities: bool = True) -> Rig:
    rng = np.random.default_rng(seed)
    d = _directions(rng)
    phi = rng.uniform(0.1, 5.0, (12, 3)) if intensities else None
    return Rig.pinhole(K, [], directions=d, intensities=phi).with_grid(640, 480)


def _exact(a: Rig, b: Rig) -> None:
    assert a == b
    for la, lb in zip(a.lights, b.lights, strict=True):
        assert type(la) is type(lb)
        assert la == lb  # every float bit for bit (tuples compare with ==; -0.0 == 0.0)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_dome_point_lights_round_trip_exact(tmp_path, seed):
    rig = _point_rig(seed)
    distance = float(np.random.default_rng(seed).uniform(100, 1000))
    rig.save(tmp_path / "r.dome", camera_distance=distance)
    back = Rig.load(tmp_path / "r.dome", camera=rig.camera, camera_distance=distance)
    _exact(back, rig)
    # and the file read back writes the same file
    back.save(tmp_path / "again.dome")  # the distance is kept in the "_dome" comment
    assert (tmp_path / "again.dome").read_text() == (tmp_path / "r.dome").read_text()
    data = json.loads((tmp_path / "r.dome").read_text())
    assert data["lightConfiguration"] == "lights3d"
    # the dome's frame: y up, z up from the object plane at the camera distance
    p = rig.lights[0].position
    q = data["positions3d"][0]
    assert (q["x"], q["y"]) == (p[0], -p[1] + 0.0)
    assert q["z"] == pytest.approx(distance - p[2], abs=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_dome_unit_scale_round_trip_exact(tmp_path, seed):
    """A rig in cm written to a .dome in mm (scale 0.1: cm per mm) and read back."""
    rig = _point_rig(seed)
    rig.save(tmp_path / "mm.dome", camera_distance=61.5, scale=0.1)
    data = json.loads((tmp_path / "mm.dome").read_text())
    p, q = rig.lights[2].position, data["positions3d"][2]
    assert (q["x"], q["y"], q["z"]) == pytest.approx((p[0] * 10, -p[1] * 10, (61.5 - p[2]) * 10), rel=1e-12)
    _exact(Rig.load(tmp_path / "mm.dome", camera=rig.camera, camera_distance=61.5, scale=0.1), rig)


@pytest.mark.parametrize("seed", [0, 5])
def test_dome_directional_round_trip_exact(tmp_path, seed):
    rig = _directional_rig(seed)
    rig.save(tmp_path / "d.dome")
    back = Rig.load(tmp_path / "d.dome", camera=rig.camera)
    _exact(back, rig)
    data = json.loads((tmp_path / "d.dome").read_text())
    d = rig.lights[3].direction
    assert [data["directions"][3][c] for c in "xyz"] == [d[0], -d[1] + 0.0, -d[2] + 0.0]
    # ledAdjust multiplies pixel values: the reciprocal of the intensity
    assert data["ledAdjust"][3]["g"] == pytest.approx(1 / rig.lights[3].intensity[1], rel=1e-15)


def test_dome_file_round_trip_exact(tmp_path):
    """A RelightLab-style .dome (float32 values as Qt writes them) reads and writes back the same values."""
    text = {
        "label": "ring",
        "notes": "",
        "imageWidth": 0,
        "domeDiameter": 800,
        "verticalOffset": 0,
        "lightConfiguration": "spherical",
        "directions": [],
        "positionsSphere": [
            {"x": 123.45600128173828, "y": -54.29999923706055, "z": 380.1000061035156},
            {"x": -200.0, "y": 17.25, "z": 310.5},
            {"x": 5.5, "y": 250.75, "z": 299.9999694824219},
        ],
        "ledAdjust": [{"r": 1, "g": 0.9, "b": 1.1}, {"r": 1, "g": 1, "b": 1}, {"r": 0.8, "g": 0.8, "b": 0.8}],
    }
    (tmp_path / "in.dome").write_text(json.dumps(text))
    rig = Rig.load(tmp_path / "in.dome", camera={"model": "pinhole", "K": K}, camera_distance=650.0)
    assert rig.lights[0].position == (123.45600128173828, 54.29999923706055, 650.0 - 380.1000061035156)
    assert rig.lights[0].intensity[1] == 1 / 0.9
    rig.save(tmp_path / "out.json")
    again = Rig.load(tmp_path / "out.json")
    again.save(tmp_path / "out.dome")
    out = json.loads((tmp_path / "out.dome").read_text())
    for a, b in zip(out["positions3d"], text["positionsSphere"], strict=True):
        assert (a["x"], a["y"], a["z"]) == (b["x"], b["y"], b["z"])
    for a, b in zip(out["ledAdjust"], text["ledAdjust"], strict=True):
        assert (a["r"], a["g"], a["b"]) == (b["r"], b["g"], b["b"])
    assert out["domeDiameter"] == 800


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_lp_round_trip_exact(tmp_path, seed):
    rig = _directional_rig(seed, intensities=False)
    rig.save(tmp_path / "l.lp")
    lines = (tmp_path / "l.lp").read_text().splitlines()
    assert lines[0] == "12" and len(lines) == 13
    back = Rig.load(tmp_path / "l.lp", camera=rig.camera)
    _exact(back, rig)
    back.save(tmp_path / "again.lp")
    assert (tmp_path / "again.lp").read_text() == (tmp_path / "l.lp").read_text()


def test_lp_file_keeps_names_and_values(tmp_path):
    text = "3\nIMG_0001.JPG 0.5 0.5 0.7071067811865476\nIMG_0002.JPG -0.6 0 0.8\nIMG_0003.JPG 0 -0.28 0.96\n"
    (tmp_path / "a.lp").write_text(text)
    rig = Rig.load(tmp_path / "a.lp", camera={"model": "pinhole", "K": K})
    assert isinstance(rig.lights[1], DirectionalLight)
    assert rig.lights[1].direction == (-0.6, 0.0, -0.8)  # y and z flipped: y down, z into the scene
    rig.save(tmp_path / "r.json")
    Rig.load(tmp_path / "r.json").save(tmp_path / "b.lp")
    out = [line.split() for line in (tmp_path / "b.lp").read_text().splitlines()[1:]]
    for a, b in zip(out, [line.split() for line in text.splitlines()[1:]], strict=True):
        assert a[0] == b[0] and [float(v) for v in a[1:]] == [float(v) for v in b[1:]]


@pytest.mark.parametrize("seed", [0, 3])
def test_alicevision_round_trip_exact(tmp_path, seed):
    rig = _directional_rig(seed)
    rig.save(tmp_path / "lights.json")
    data = json.loads((tmp_path / "lights.json").read_text())
    assert data["lights"][0]["type"] == "directional" and data["lights"][0]["lightId"] == 0
    assert data["lights"][2]["direction"] == list(rig.lights[2].direction)  # OpenCV frame as is
    back = Rig.load(tmp_path / "lights.json", camera=rig.camera)
    _exact(back, rig)


def test_alicevision_strings_and_view_ids(tmp_path):
    """boost's JSON writer quotes every number; viewIds are kept."""
    lights = [
        {"viewId": "1001", "type": "directional", "direction": ["0.1", "-0.2", "-0.97467943448089633"],
         "intensity": ["1", "0.5", "2"]},
        {"viewId": "1002", "type": "directional", "direction": ["0.6", "0", "-0.8"], "intensity": ["1", "1", "1"]},
        {"viewId": "1003", "type": "directional", "direction": ["0", "0.6", "-0.8"], "intensity": ["1", "1", "1"]},
    ]  # fmt: skip
    (tmp_path / "lights.json").write_text(json.dumps({"lights": lights}))
    rig = Rig.load(tmp_path / "lights.json", camera={"model": "pinhole", "K": K})
    assert rig.lights[0].direction == (0.1, -0.2, -0.97467943448089633)
    assert rig.lights[0].intensity == (1.0, 0.5, 2.0)
    rig.save(tmp_path / "lights2.json", fmt="alicevision")
    out = json.loads((tmp_path / "lights2.json").read_text())
    assert [e["viewId"] for e in out["lights"]] == [1001, 1002, 1003]
    bad = {"lights": [{"lightId": 0, "type": "SH", "direction": [0] * 9, "intensity": [1, 1, 1]}]}
    (tmp_path / "sh.json").write_text(json.dumps(bad))
    with pytest.raises(RigError, match="directional lights only"):
        Rig.load(tmp_path / "sh.json", camera={"model": "pinhole", "K": K})


@pytest.mark.parametrize("suffix", [".yml", ".yaml", ".json"])
def test_opencv_camera_round_trip_exact(tmp_path, suffix):
    rig = _point_rig(0)
    fmt = "opencv-json" if suffix == ".json" else None
    rig.save(tmp_path / f"camera{suffix}", fmt=fmt)
    camera, grid = rig_formats.read_camera(tmp_path / f"camera{suffix}")
    assert camera == rig.camera and grid is not None and grid.image_size == (640, 480)
    # the camera and a lights file make the rig again
    rig_dir = _directional_rig(1)
    rig_dir.save(tmp_path / "d.dome")
    assert Rig.load(tmp_path / "d.dome", camera=tmp_path / f"camera{suffix}") == Rig(rig.camera, rig_dir.lights)


def test_opencv_yaml_as_opencv_writes_it(tmp_path):
    text = """%YAML:1.0
---
calibration_time: "Fri Dec  4 10:00:00 2026"
image_width: 1280
image_height: 960
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 1.1089762345678901e+03, 0., 6.3951234567890123e+02, 0.,
       1.1101234567890123e+03, 4.7925e+02, 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 5
   cols: 1
   dt: d
   data: [ -1.2e-01, 8.5e-02, 1.0e-04, -2.0e-04, 0. ]
avg_reprojection_error: 2.1e-01
"""
    (tmp_path / "cam.yml").write_text(text)
    camera, grid = rig_formats.read_camera(tmp_path / "cam.yml")
    assert camera["K"][0] == [1.1089762345678901e03, 0.0, 6.3951234567890123e02]
    assert camera["K"][1][2] == 479.25
    assert camera["distortion"] == [-0.12, 0.085, 1e-4, -2e-4, 0.0]
    assert grid.image_size == (1280, 960)
    # as some tools write it: the matrix's keys not indented, a flow list on one line
    flat = (
        "%YAML:1.0\ncamera_matrix: !!opencv-matrix\nrows: 3\ncols: 3\ndt: d\n"
        "data: [ 500., 0., 320., 0., 500., 240., 0., 0., 1. ]\n"
    )
    (tmp_path / "flat.yml").write_text(flat)
    assert rig_formats.read_camera(tmp_path / "flat.yml")[0]["K"][1] == [0.0, 500.0, 240.0]


def test_refusals(tmp_path):
    point = _point_rig(0)
    with pytest.raises(RigError, match="directions only"):
        point.save(tmp_path / "x.lp")
    with pytest.raises(RigError, match="directional lights only"):
        point.save(tmp_path / "lights.json")
    with pytest.raises(RigError, match="camera's distance"):
        point.save(tmp_path / "x.dome")
    led = Rig.pinhole(K, [LED((0, 0, 0), axis=(0, 0, 1), mu=1.0), PointLight((1, 0, 0)), PointLight((0, 1, 0))])
    with pytest.raises(RigError, match="LED"):
        led.save(tmp_path / "x.dome", camera_distance=100.0)
    with pytest.raises(RigError, match="intensities"):
        _directional_rig(0).save(tmp_path / "x.lp")
    _directional_rig(0).save(tmp_path / "x.lp", drop_intensities=True)
    ortho = nplps.make_scene("sphere", n=8).rig
    with pytest.raises(RigError, match="pinhole"):
        ortho.save(tmp_path / "c.yml")
    with pytest.raises(RigError, match="no camera"):
        Rig.load(tmp_path / "x.lp")
    with pytest.raises(RigError, match="camera only"):
        point.save(tmp_path / "c.yml")
        Rig.load(tmp_path / "c.yml")
    point.save(tmp_path / "p.dome", camera_distance=300.0)
    with pytest.raises(RigError, match="camera_distance"):
        Rig.load(tmp_path / "p.dome", camera=point.camera)
    (tmp_path / "bad.lp").write_text("4\na 0 0 1\nb 0 1 0\n")
    with pytest.raises(RigError, match="announces 4 lights"):
        Rig.load(tmp_path / "bad.lp", camera=point.camera)


def test_lp_as_point_lights(tmp_path):
    """Directions placed at a distance R from the dome origin, the origin D in front of the camera."""
    rig = _directional_rig(2, intensities=False)
    rig.save(tmp_path / "l.lp")
    near = Rig.load(tmp_path / "l.lp", camera=rig.camera, camera_distance=500.0, light_distance=300.0)
    expected = np.array([0.0, 0.0, 500.0]) + 300.0 * np.array([d.direction for d in rig.lights])
    np.testing.assert_allclose(near.positions, expected, rtol=0, atol=1e-9)


def _sfmdata(tmp_path, version=("1", "2", "12"), **intrinsic) -> str:
    item = {
        "intrinsicId": "42",
        "width": "640",
        "height": "480",
        "sensorWidth": "6.4",
        "type": "pinhole",
        "focalLength": "8.125",
        "pixelRatio": "1",
        "principalPoint": ["-0.5", "1.0"],
        "distortionType": "radialk3",
        "distortionParams": ["0.1", "-0.01", "0.001"],
    }
    item.update(intrinsic)
    views = [{"viewId": str(i), "poseId": "7", "intrinsicId": "42", "path": f"img_{i}.png"} for i in range(3)]
    path = tmp_path / "cameras.sfm"
    path.write_text(json.dumps({"version": list(version), "views": views, "intrinsics": [item]}))
    return str(path)


def test_sfmdata_intrinsics(tmp_path):
    camera, grid = rig_formats.read_camera(_sfmdata(tmp_path))
    assert camera["K"] == [[812.5, 0.0, 319.5], [0.0, 812.5, 241.0], [0.0, 0.0, 1.0]]
    assert camera["distortion"] == [0.1, -0.01, 0.0, 0.0, 0.001]
    assert grid.image_size == (640, 480)
    # pixelRatio since 1.2.5 is fy / fx, before it was fx / fy
    assert rig_formats.read_camera(_sfmdata(tmp_path, pixelRatio="2"))[0]["K"][1][1] == 1625.0
    old = _sfmdata(tmp_path, version=("1", "2", "4"), pixelRatio="2")
    assert rig_formats.read_camera(old)[0]["K"][1][1] == 406.25
    # before 1.2.1 the principal point was absolute
    older = _sfmdata(tmp_path, version=("1", "2", "0"), pxFocalLength=["800", "801"], principalPoint=["320", "240"])
    assert rig_formats.read_camera(older)[0]["K"] == [[800.0, 0.0, 320.0], [0.0, 801.0, 240.0], [0.0, 0.0, 1.0]]
    fisheye = _sfmdata(tmp_path, type="equidistant_r3")
    with pytest.raises(RigError, match="pinhole intrinsics only"):
        rig_formats.read_camera(fisheye)
    sfm = rig_formats.read_sfmdata(_sfmdata(tmp_path))
    assert list(sfm.poses()) == ["7"] and len(sfm.poses()["7"]) == 3
    # several intrinsics: choose one
    data = json.loads(open(_sfmdata(tmp_path)).read())
    data["intrinsics"].append(dict(data["intrinsics"][0], intrinsicId="43", focalLength="4.0"))
    (tmp_path / "two.sfm").write_text(json.dumps(data))
    with pytest.raises(RigError, match="choose one"):
        rig_formats.read_camera(tmp_path / "two.sfm")
    assert rig_formats.read_camera(tmp_path / "two.sfm", intrinsic="43")[0]["K"][0][0] == 400.0
    # an SfMData alone is a camera, not a rig
    with pytest.raises(RigError, match="camera only"):
        Rig.load(tmp_path / "two.sfm")


def test_rig_file_text_round_trip(tmp_path):
    """rig.json -> .dome -> rig.json gives the same file (no -0.0 from the flipped axes)."""
    scene_rig = nplps.make_scene("sphere", n=8, camera="pinhole").rig.with_grid(8, 8)
    scene_rig.save(tmp_path / "rig.json")
    assert (
        main(["rig", "convert", str(tmp_path / "rig.json"), str(tmp_path / "d.dome"), "--camera-distance", "200"]) == 0
    )
    code = main(["rig", "convert", str(tmp_path / "d.dome"), str(tmp_path / "back.json"), "--camera",
                 str(tmp_path / "rig.json"), "--camera-distance", "200"])  # fmt: skip
    assert code == 0
    back = json.loads((tmp_path / "back.json").read_text())
    assert back["lights"] == json.loads((tmp_path / "rig.json").read_text())["lights"]
    assert json.dumps(back["lights"]) == json.dumps(json.loads((tmp_path / "rig.json").read_text())["lights"])


def test_cli_convert(tmp_path, capsys):
    rig = _point_rig(4)
    rig.save(tmp_path / "rig.json")
    assert main(["rig", "convert", str(tmp_path / "rig.json"), str(tmp_path / "cam.yml")]) == 0
    assert (
        main(["rig", "convert", str(tmp_path / "rig.json"), str(tmp_path / "d.dome"), "--camera-distance", "420"]) == 0
    )
    out = tmp_path / "back.json"
    code = main(
        ["rig", "convert", str(tmp_path / "d.dome"), str(out), "--camera", str(tmp_path / "cam.yml"),
         "--camera-distance", "420"]
    )  # fmt: skip
    assert code == 0
    assert Rig.load(out) == rig
    assert "wrote" in capsys.readouterr().out
    assert main(["rig", "convert", str(tmp_path / "rig.json"), str(tmp_path / "x.lp")]) == 2
    assert "directions only" in capsys.readouterr().err
