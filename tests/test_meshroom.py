"""The Meshroom node description and the ``nplps meshroom`` command, without Meshroom installed."""

from __future__ import annotations

import contextlib
import importlib.util
import json
import shlex
import sys
import types

import numpy as np
import png
import pytest

import nplps
from nplps.cli import build_parser, main
from nplps.errors import RigError
from nplps.meshroom import PLUGIN_PATH, normal_png16_pixels

NODE_FILE = PLUGIN_PATH / "meshroom" / "nplpsNodes" / "NplpsPhotometricStereo.py"


class _Attribute:
    def __init__(self, **kwargs):
        self.__dict__.update(kwargs)


class _CommandLineNode:
    pass


@pytest.fixture
def node(monkeypatch):
    """Import the node file with a stub ``meshroom.core.desc`` (the names Meshroom plugins use)."""
    desc = types.ModuleType("meshroom.core.desc")
    for name in ("File", "StringParam", "FloatParam", "ChoiceParam", "BoolParam", "IntParam"):
        setattr(desc, name, type(name, (_Attribute,), {}))
    desc.CommandLineNode = _CommandLineNode
    core = types.ModuleType("meshroom.core")
    core.desc = desc
    meshroom = types.ModuleType("meshroom")
    meshroom.core = core
    monkeypatch.setitem(sys.modules, "meshroom", meshroom)
    monkeypatch.setitem(sys.modules, "meshroom.core", core)
    monkeypatch.setitem(sys.modules, "meshroom.core.desc", desc)
    spec = importlib.util.spec_from_file_location("nplps_meshroom_node", NODE_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.NplpsPhotometricStereo


def test_plugin_layout():
    assert (PLUGIN_PATH / "meshroom" / "nplpsNodes" / "__init__.py").is_file()
    config = json.loads((PLUGIN_PATH / "meshroom" / "config.json").read_text())
    assert config["name"] == "nplps"


def test_node_description(node):
    assert issubclass(node, _CommandLineNode)
    inputs = {a.name: a for a in node.inputs}
    assert set(inputs) == {"inputPath", "lights", "maskFolder", "depth", "cameraDistance", "normalFrame"}
    assert type(inputs["inputPath"]).__name__ == "File"
    assert inputs["normalFrame"].values == ["opengl", "opencv"]
    outputs = {a.name: a for a in node.outputs}
    assert outputs["output"].value == "{nodeCacheFolder}"
    assert outputs["normals"].value == "{nodeCacheFolder}/<POSE_ID>_normals.png"
    assert node.commandLine.startswith("nplps meshroom ")
    # every {nameValue} of the command is an attribute, and the command parses as nplps's
    names = set(inputs) | set(outputs)
    placeholders = {p[: -len("Value")] for p in __import__("re").findall(r"\{(\w+)\}", node.commandLine)}
    assert placeholders <= names
    values = {f"{a.name}Value": a.value for a in node.inputs}
    values.update(inputValue="", outputValue="/cache/node", inputPathValue="/data/sfm.sfm")
    command = node.commandLine.format(**{k: shlex.quote(str(v)) for k, v in values.items()})
    args = build_parser().parse_args(shlex.split(command)[1:])
    assert args.command == "meshroom" and args.sfmdata == "/data/sfm.sfm" and args.output == "/cache/node"
    assert args.normal_frame == "opengl" and args.depth == "auto" and args.lights == ""


def test_plugin_path_command(capsys):
    assert main(["meshroom", "--plugin-path"]) == 0
    assert capsys.readouterr().out.strip() == str(PLUGIN_PATH)


def test_png16_encoding():
    n = np.array([[[0.0, 0.0, -1.0], [0.6, -0.8, 0.0]]])
    gl = normal_png16_pixels(n, "opengl")
    cv = normal_png16_pixels(n, "opencv")
    assert gl[0, 0].tolist() == [32768, 32768, 65535]  # facing the viewer: +z in OpenGL
    assert cv[0, 0].tolist() == [32768, 32768, 0]
    assert gl[0, 1].tolist() == [52428, 58982, 32768]


def _read_png16(path) -> np.ndarray:
    w, h, rows, info = png.Reader(filename=str(path)).read()
    assert info["bitdepth"] == 16 and info["planes"] == 3
    return np.array([np.asarray(r, dtype=np.uint16) for r in rows]).reshape(h, w, 3)


def _write_sfmdata(tmp_path, scenes):
    """Two poses, 27 views each; the pinhole camera as AliceVision writes it (mm focal, centre offset)."""
    views, k = [], None
    for pose, scene in enumerate(scenes):
        folder = tmp_path / f"pose{pose}"
        scene.save(folder)
        for i in range(scene.images.shape[0]):
            views.append(
                {"viewId": str(1000 * (pose + 1) + i), "poseId": str(77 + pose), "intrinsicId": "5",
                 "path": f"pose{pose}/image_{i:02d}.png"}
            )  # fmt: skip
        k = scene.rig.K
    n = scenes[0].images.shape[1]
    intrinsic = {
        "intrinsicId": "5",
        "width": str(n),
        "height": str(n),
        "sensorWidth": str(n),  # focalLength (mm) = fx (px) * sensorWidth / width
        "sensorHeight": str(n),
        "type": "pinhole",
        "focalLength": repr(float(k[0, 0])),
        "pixelRatio": "1",
        "principalPoint": [repr(float(k[0, 2]) - n / 2), repr(float(k[1, 2]) - n / 2)],
        "distortionType": "none",
        "distortionParams": "",
    }
    path = tmp_path / "cameras.sfm"
    path.write_text(json.dumps({"version": ["1", "2", "12"], "views": views, "intrinsics": [intrinsic]}))
    scenes[0].rig.save(tmp_path / "lights_rig.json")
    return path


@pytest.mark.parametrize("seed", [1, 2])
def test_meshroom_command_on_synthetic_sfmdata(tmp_path, seed):
    scenes = [
        nplps.make_scene("sphere", n=32, camera="pinhole", seed=seed),
        nplps.make_scene("bumps", n=32, camera="pinhole", seed=seed),
    ]
    sfm = _write_sfmdata(tmp_path, scenes)
    (tmp_path / "masks").mkdir()
    nplps.export.write_png8(tmp_path / "masks" / "77.png", scenes[0].mask.astype(np.uint8) * 255)
    out = tmp_path / "out"
    lights = str(tmp_path / "lights_rig.json")
    command = ["meshroom", str(sfm), "--output", str(out), "--lights", lights, "--depth", "200"]
    assert main([*command, "--mask-folder", str(tmp_path / "masks")]) == 0
    for pose, scene, masked, limit in zip(("77", "78"), scenes, (True, False), (6.0, 1.0), strict=True):
        assert (out / pose / "mesh.obj").is_file() and (out / pose / "mesh.ply").is_file()
        assert (out / pose / "albedo.png").is_file() and (out / pose / "depth.tiff").is_file()
        raw = _read_png16(out / f"{pose}_normals.png")
        gl = raw.astype(np.float64) / 65535 * 2 - 1
        n = gl * np.array([1.0, -1.0, -1.0])  # OpenGL -> nplps's OpenCV frame
        # the same normals as the Python API gives on the pose's image files and the scene's rig
        files = sorted((tmp_path / f"pose{int(pose) - 77}").glob("image_*.png"))
        with pytest.warns(RuntimeWarning) if masked else contextlib.nullcontext():  # the distance check's note
            api = nplps.reconstruct(files, scene.rig, depth=200.0, mask=scene.mask if masked else None)
        written = raw.sum(axis=2) > 0
        assert np.array_equal(written, api.mask & np.isfinite(api.normals).all(axis=2))
        np.testing.assert_allclose(n[written], api.normals[written], rtol=0, atol=1.0 / 65535 + 1e-12)
        # and near the ground truth (the sphere's cap at 32 x 32 pixels is the method's hard case)
        inside = scene.mask & written
        cos = np.sum(n[inside] * scene.normals[inside], axis=1) / np.linalg.norm(n[inside], axis=1)
        error = np.degrees(np.arccos(np.clip(cos, -1, 1)))
        assert np.median(error) < limit, (pose, np.median(error))
    # the OpenCV frame: the same normals with y and z flipped
    out_cv = tmp_path / "out_cv"
    assert main(["meshroom", str(sfm), "--output", str(out_cv), "--lights", lights, "--depth", "200",
                 "--normal-frame", "opencv", "--poses", "78"]) == 0  # fmt: skip
    assert not (out_cv / "77_normals.png").exists()
    cv = _read_png16(out_cv / "78_normals.png").astype(np.int64)
    gl16 = _read_png16(out / "78_normals.png").astype(np.int64)
    inside = scenes[1].mask & (gl16.sum(axis=2) > 0)
    np.testing.assert_array_less(np.abs(cv[inside][:, 0] - gl16[inside][:, 0]), 2)
    np.testing.assert_array_less(np.abs(cv[inside][:, 1:] - (65535 - gl16[inside][:, 1:])), 2)


def test_meshroom_lights_by_view_id(tmp_path):
    """An AliceVision lights.json keyed by viewId (directional lights) picks each pose's lights."""
    scene = nplps.make_scene("sphere", n=24, camera="pinhole", directional=True)
    sfm = _write_sfmdata(tmp_path, [scene])
    entries = []
    for i in reversed(range(scene.rig.n_lights)):  # another order than the views
        entries.append({"viewId": str(1000 + i), "type": "directional", "direction": [0.0, 0.0, -1.0],
                        "intensity": [1.0, 1.0, 1.0]})  # fmt: skip
    (tmp_path / "lights.json").write_text(json.dumps({"lights": entries}))
    from nplps import rig_formats
    from nplps.meshroom import _pose_lights

    data = rig_formats.read_sfmdata(sfm)
    rig = rig_formats.load(tmp_path / "lights.json", camera=scene.rig.camera)
    picked = _pose_lights(rig, data.poses()["77"], "77", "lights.json")
    assert picked.n_lights == scene.images.shape[0]
    del entries[3]
    (tmp_path / "lights.json").write_text(json.dumps({"lights": entries}))
    rig = rig_formats.load(tmp_path / "lights.json", camera=scene.rig.camera)
    with pytest.raises(RigError, match="no light for view"):
        _pose_lights(rig, data.poses()["77"], "77", "lights.json")
    # without --lights, lights.json beside the SfMData is used
    assert main(["meshroom", str(sfm), "--output", str(tmp_path / "o")]) == 2


def test_meshroom_with_dome_lights_gives_the_same_normals(tmp_path):
    """The lights as a .dome (positions on the object plane's frame) give the rig file's result bit for bit."""
    scene = nplps.make_scene("bumps", n=24, camera="pinhole", seed=4)
    sfm = _write_sfmdata(tmp_path, [scene])
    assert main(["rig", "convert", str(tmp_path / "lights_rig.json"), str(tmp_path / "l.dome"),
                 "--camera-distance", "180"]) == 0  # fmt: skip
    base = ["meshroom", str(sfm), "--depth", "200"]
    assert main([*base, "--output", str(tmp_path / "a"), "--lights", str(tmp_path / "lights_rig.json")]) == 0
    dome = ["--lights", str(tmp_path / "l.dome"), "--camera-distance", "180"]
    assert main([*base, "--output", str(tmp_path / "b"), *dome]) == 0
    a = _read_png16(tmp_path / "a" / "77_normals.png")
    b = _read_png16(tmp_path / "b" / "77_normals.png")
    assert np.array_equal(a, b)
    # without the distance the .dome's positions cannot be placed
    assert main([*base, "--output", str(tmp_path / "c"), "--lights", str(tmp_path / "l.dome")]) == 2
