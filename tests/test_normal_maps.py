"""Normal maps for other tools (16-bit, explicit convention), EXR outputs, scale bars and units (issue 22, item 5)."""

from __future__ import annotations

import io
import json
import math
import re
import shlex
import sys
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np
import pytest

import nplps
from nplps import cli, export, report, viewer, views
from nplps.errors import InputError
from nplps.export import (
    NORMAL_MAP_FRAMES,
    decode_normal_map,
    normal_map_pixels,
    read_normal_map,
    save_normal_map,
    to_normal_frame,
)

FRAMES = tuple(NORMAL_MAP_FRAMES)


def _random_normals(seed: int, shape: tuple[int, int] = (200, 300)) -> np.ndarray:
    n = np.random.default_rng(seed).normal(size=(*shape, 3))
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    return n


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip((a * b).sum(axis=-1), -1.0, 1.0)))


def _png_bit_depth(path: Path) -> int:
    return path.read_bytes()[24]


@pytest.fixture(scope="module")
def result() -> nplps.Reconstruction:
    scene = nplps.make_scene("sphere", n=32, seed=0)
    return nplps.reconstruct(scene.images, scene.rig, depth=scene.mean_depth, mask=scene.mask)


# --------------------------------------------------------------------------------------------------
# Encoding and decoding
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("frame", "facing", "right", "up"),
    [
        # the normal facing the camera (0, 0, -1), one pointing right (1, 0, 0), one up in the image (0, -1, 0)
        ("opengl", (32768, 32768, 65535), (65535, 32768, 32768), (32768, 65535, 32768)),
        ("directx", (32768, 32768, 65535), (65535, 32768, 32768), (32768, 0, 32768)),
        ("opencv", (32768, 32768, 0), (65535, 32768, 32768), (32768, 0, 32768)),
    ],
)
def test_16_bit_encoding_of_each_convention(tmp_path: Path, frame: str, facing, right, up) -> None:
    normals = np.array([[(0, 0, -1), (1, 0, 0)], [(0, -1, 0), (np.nan, 0, 0)]], dtype=np.float64)
    path = tmp_path / "normals.png"
    save_normal_map(path, normals, frame=frame)

    assert _png_bit_depth(path) == 16
    image = nplps.io.read_image(path)
    assert image.dtype == np.uint16 and image.shape == (2, 2, 3)
    np.testing.assert_array_equal(image[0, 0], facing)
    np.testing.assert_array_equal(image[0, 1], right)
    np.testing.assert_array_equal(image[1, 0], up)
    np.testing.assert_array_equal(image[1, 1], (0, 0, 0))  # no normal: black


def test_8_bit_stays_available_and_is_the_old_encoding(tmp_path: Path) -> None:
    normals = _random_normals(4, (9, 11))
    path = tmp_path / "n8.png"
    save_normal_map(path, normals, bits=8)
    assert _png_bit_depth(path) == 8
    image = nplps.io.read_image(path)
    assert image.dtype == np.uint8
    expected = np.rint((np.clip(normals * (1, -1, -1), -1, 1) + 1) / 2 * 255).astype(np.uint8)
    np.testing.assert_array_equal(image, expected)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_conventions_differ_by_the_signs_of_green_and_blue(seed: int) -> None:
    n = _random_normals(seed)
    gl, dx, cv = (normal_map_pixels(n, frame=f, bits=16).astype(np.int64) for f in FRAMES)
    np.testing.assert_array_equal(gl[..., 0], dx[..., 0])
    np.testing.assert_array_equal(gl[..., 1] + dx[..., 1], 65535)  # green flipped (no exact ties here)
    np.testing.assert_array_equal(gl[..., 2], dx[..., 2])
    np.testing.assert_array_equal(dx[..., 1], cv[..., 1])
    np.testing.assert_array_equal(dx[..., 2] + cv[..., 2], 65535)  # blue flipped


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("frame", FRAMES)
@pytest.mark.parametrize("bits", [8, 16])
def test_read_normal_map_round_trip_within_quantisation(tmp_path: Path, seed: int, frame: str, bits: int) -> None:
    normals = _random_normals(seed)
    mask = np.random.default_rng(seed + 10).random(normals.shape[:2]) < 0.9
    normals[5, 7] = np.nan
    path = tmp_path / "normals.png"
    save_normal_map(path, normals, mask=mask, frame=frame, bits=bits)

    decoded = read_normal_map(path, frame)

    valid = mask & np.isfinite(normals).all(axis=2)
    assert decoded.dtype == np.float64 and decoded.shape == normals.shape
    assert np.isnan(decoded[~valid]).all()
    np.testing.assert_allclose(np.linalg.norm(decoded[valid], axis=1), 1.0, atol=1e-12)
    # Each channel is off by at most half a step (1 / M of the [-1, 1] range): the decoded normal is
    # within asin(sqrt(3) / M) of the one written.
    top = (1 << bits) - 1
    bound = math.degrees(math.asin(math.sqrt(3) / top))
    errors = _angles(decoded[valid], normals[valid])
    assert errors.max() <= bound
    # Decoding in another convention is wrong: it shows (this is why the frame is recorded).
    other = FRAMES[(FRAMES.index(frame) + 1) % 3]
    assert _angles(read_normal_map(path, other)[valid], normals[valid]).mean() > 10.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_quantisation_error_of_8_and_16_bits(seed: int) -> None:
    """The numbers of docs/outputs.md: mean 0.17 / max 0.39 degrees at 8 bits, 0.00066 / 0.0015 at 16."""
    n = _random_normals(seed, (500, 500))
    stats = {}
    for bits in (8, 16):
        errors = _angles(decode_normal_map(normal_map_pixels(n, bits=bits), "opengl"), n)
        stats[bits] = (errors.mean(), errors.max())
    assert 0.16 < stats[8][0] < 0.18 and 0.36 < stats[8][1] < 0.39
    assert 0.00062 < stats[16][0] < 0.00070 and stats[16][1] < 0.0016
    assert stats[8][0] / stats[16][0] > 250  # 257 times finer steps


def test_to_normal_frame_is_its_own_inverse() -> None:
    n = _random_normals(3, (5, 6)).astype(np.float32)
    for frame in FRAMES:
        np.testing.assert_array_equal(to_normal_frame(to_normal_frame(n, frame), frame), n)
    np.testing.assert_array_equal(to_normal_frame(n, "opengl"), n * np.float32([1, -1, -1]))


def test_bad_frame_bits_and_files_are_clear_errors(tmp_path: Path) -> None:
    n = _random_normals(0, (3, 3))
    with pytest.raises(InputError, match="normal_map must be one of opengl, directx, opencv, got 'vulkan'"):
        save_normal_map(tmp_path / "x.png", n, frame="vulkan")
    with pytest.raises(InputError, match="normal_map_bits must be 8 or 16, got 12"):
        save_normal_map(tmp_path / "x.png", n, bits=12)
    grey = tmp_path / "grey.png"
    export.write_png(grey, np.zeros((4, 4), dtype=np.uint16))
    with pytest.raises(InputError, match=r"grey\.png.*\(H, W, 3\) RGB image of 8 or 16 bits"):
        read_normal_map(grey, "opengl")
    assert not (tmp_path / "x.png").exists()


# --------------------------------------------------------------------------------------------------
# Reconstruction.save and summary.json
# --------------------------------------------------------------------------------------------------


def test_save_writes_a_16_bit_opengl_map_by_default_and_records_it(
    result: nplps.Reconstruction, tmp_path: Path
) -> None:
    paths = result.save(tmp_path / "r")
    summary = json.loads(Path(paths["summary"]).read_text())
    assert summary["normal_map"] == {"file": "normals.png", "frame": "opengl", "bits": 16}
    assert summary["units"] is None
    assert _png_bit_depth(Path(paths["normal_map"])) == 16
    decoded = read_normal_map(paths["normal_map"], summary["normal_map"]["frame"])
    valid = result.mask & np.isfinite(result.normals).all(axis=2)
    assert _angles(decoded[valid], result.normals[valid]).max() <= 0.0016
    assert np.isnan(decoded[~result.mask]).all()


@pytest.mark.parametrize(("frame", "bits"), [("directx", 16), ("opencv", 8)])
def test_save_in_another_convention(result: nplps.Reconstruction, tmp_path: Path, frame: str, bits: int) -> None:
    paths = result.save(tmp_path / "r", normal_map=frame, normal_map_bits=bits, units="mm")
    summary = json.loads(Path(paths["summary"]).read_text())
    assert summary["normal_map"] == {"file": "normals.png", "frame": frame, "bits": bits}
    assert summary["units"] == "mm"
    assert _png_bit_depth(Path(paths["normal_map"])) == bits
    decoded = read_normal_map(paths["normal_map"], frame)
    valid = result.mask & np.isfinite(result.normals).all(axis=2)
    bound = math.degrees(math.asin(math.sqrt(3) / ((1 << bits) - 1)))
    assert _angles(decoded[valid], result.normals[valid]).max() <= bound


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"normal_map": "y-up"}, "normal_map must be one of"),
        ({"normal_map_bits": 10}, "normal_map_bits must be 8 or 16"),
        ({"units": ""}, "units must be a non-empty string"),
    ],
)
def test_save_refuses_bad_options_before_writing(
    result: nplps.Reconstruction, tmp_path: Path, options: dict, message: str
) -> None:
    with pytest.raises(InputError, match=message):
        result.save(tmp_path / "r", **options)
    assert not (tmp_path / "r").exists()


def test_summary_check_names_a_bad_normal_map_record(result: nplps.Reconstruction, tmp_path: Path) -> None:
    paths = result.save(tmp_path / "r")
    summary = json.loads(Path(paths["summary"]).read_text())
    summary["normal_map"] = {"frame": "metal", "bits": 16}
    Path(paths["summary"]).write_text(json.dumps(summary))
    with pytest.raises(InputError, match='"normal_map" must be'):
        nplps._results.read_summary(tmp_path / "r")


# --------------------------------------------------------------------------------------------------
# EXR (the optional OpenEXR binding)
# --------------------------------------------------------------------------------------------------


def test_exr_write_and_read_back_exactly(tmp_path: Path) -> None:
    pytest.importorskip("OpenEXR")
    rng = np.random.default_rng(5)
    a = rng.normal(size=(7, 9)).astype(np.float32) * 1e3
    a[2, 3] = np.nan
    b = rng.random((7, 9)).astype(np.float32)
    export.write_exr(tmp_path / "t.exr", {"Z": a, "Y": b}, attributes={"note": "hello"})
    channels, header = export.read_exr(tmp_path / "t.exr")
    assert set(channels) == {"Z", "Y"} and header["note"] == "hello"
    for name, original in (("Z", a), ("Y", b)):
        assert channels[name].dtype == np.float32
        np.testing.assert_array_equal(channels[name], original)  # NaN where NaN


@pytest.mark.parametrize("frame", FRAMES)
def test_save_exr_files(result: nplps.Reconstruction, tmp_path: Path, frame: str) -> None:
    pytest.importorskip("OpenEXR")
    paths = result.save(tmp_path / "r", formats=["exr"], normal_map=frame)
    assert {"depth_exr", "normals_exr", "albedo_exr"} <= set(paths)

    depth, _ = export.read_exr(paths["depth_exr"])
    np.testing.assert_array_equal(depth["Z"], result.depth.astype(np.float32))
    normals, header = export.read_exr(paths["normals_exr"])
    assert header["nplps_normal_frame"] == frame
    stored = np.stack([normals[c] for c in "RGB"], axis=-1)
    np.testing.assert_array_equal(stored, to_normal_frame(result.normals, frame))
    back = to_normal_frame(stored, frame)  # the frame's map is its own inverse
    np.testing.assert_array_equal(back, result.normals.astype(np.float32))
    albedo, _ = export.read_exr(paths["albedo_exr"])
    grey = np.asarray(result.albedo)
    if grey.ndim == 2:
        np.testing.assert_array_equal(albedo["Y"], grey.astype(np.float32))
    else:
        np.testing.assert_array_equal(np.stack([albedo[c] for c in "RGB"], -1), grey.astype(np.float32))

    manifest = json.loads((tmp_path / "r" / "nplps-manifest.json").read_text())
    assert {"depth.exr", "normals.exr", "albedo.exr"} <= set(manifest["files"])


def test_exr_without_openexr_names_the_extra(
    result: nplps.Reconstruction, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "OpenEXR", None)  # import OpenEXR now raises ImportError
    assert not export.exr_available()
    with pytest.raises(InputError, match=re.escape('pip install "nplps[exr]"')):
        result.save(tmp_path / "r", formats=["exr"])
    assert not (tmp_path / "r").exists()  # refused before anything was written
    with pytest.raises(InputError, match=r"t\.exr.*nplps\[exr\]"):
        export.write_exr(tmp_path / "t.exr", {"Z": np.zeros((2, 2), np.float32)})


# --------------------------------------------------------------------------------------------------
# Scale bars and units
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("span", "length"), [(100.0, 20.0), (40.0, 10.0), (7.9, 1.0), (8.0, 2.0), (0.37, 0.05), (2e4, 5e3)]
)
def test_scale_bar_length_is_round(span: float, length: float) -> None:
    assert views.scale_bar_length(span) == pytest.approx(length)
    assert math.isnan(views.scale_bar_length(0.0)) and math.isnan(views.scale_bar_length(float("nan")))


def test_pixel_footprint_of_both_camera_models() -> None:
    depth = np.full((5, 6), np.nan)
    depth[1:4, 1:5] = 200.0
    depth[2, 2] = 300.0
    pinhole = nplps.Rig.pinhole([[500.0, 0, 2.0], [0, 400.0, 2.0], [0, 0, 1]], lights=[[0, 0, 0]])
    mean = float(np.nanmean(depth))
    assert views.pixel_footprint(pinhole, depth) == pytest.approx((mean / 500.0, mean))
    ortho = nplps.Rig.orthographic(pixel_size=(0.25, 0.5), lights=[[0, 0, -100]])
    size, _ = views.pixel_footprint(ortho, depth)
    assert size == pytest.approx(0.25)
    assert views.pixel_footprint(pinhole, np.full((3, 3), np.nan)) is None


def _bars(text: str) -> list[dict[str, str]]:
    return [
        dict(re.findall(r'(data-[a-z]+)="([^"]*)"', m)) for m in re.findall(r'<svg[^>]*class="scalebar"[^>]*>', text)
    ]


def test_report_scale_bars_match_the_pixel_footprint(result: nplps.Reconstruction, tmp_path: Path) -> None:
    out = tmp_path / "r"
    result.save(out, units="mm", report=True)
    text = (out / report.REPORT_NAME).read_text()
    bars = _bars(text)
    assert len(bars) == 3  # normal map, albedo, depth
    # A pixel's width on the surface, from the mesh itself: the spacing of the vertices in x
    # (the scene's camera is orthographic: the same everywhere).
    assert not result.rig.is_pinhole
    footprint = float(np.nanmedian(np.diff(result.vertices[..., 0], axis=1)))
    summary = json.loads((out / "summary.json").read_text())
    box = report._Data(out, summary).box  # the maps are cropped to the mask
    h, w = result.shape if box is None else (box[1] - box[0], box[3] - box[2])
    for bar, width in zip(bars, (w, w, w + 1), strict=True):  # the depth map is the vertex grid
        length = float(bar["data-length"])
        assert bar["data-units"] == "mm"
        mantissa = length / 10 ** math.floor(math.log10(length))
        assert min(abs(mantissa - m) for m in (1, 2, 5)) < 1e-9
        zoom = report._zoom((h, width))
        # the bar is as long on the picture as `length` on the surface at the mean depth
        assert float(bar["data-pixels"]) == pytest.approx(length / footprint * zoom, abs=0.006)  # 2 decimals
        # about a quarter of the picture's width
        assert 0.1 <= length / (width * footprint) <= 0.25 + 1e-9
    depth_section = re.search(r"<section id='depth'>(.*?)</section>", text, re.S).group(1)
    assert "depth z (mm)" in depth_section and "in mm" in depth_section
    maps = re.search(r"<section id='maps'>(.*?)</section>", text, re.S).group(1)
    assert "16-bit, OpenGL convention" in maps


def test_report_without_units_says_rig_units_and_shows_an_8_bit_map_of_an_old_result(
    result: nplps.Reconstruction, tmp_path: Path
) -> None:
    out = tmp_path / "r"
    result.save(out, normal_map_bits=8)
    summary = json.loads((out / "summary.json").read_text())
    del summary["normal_map"], summary["units"]  # as written before these records
    (out / "summary.json").write_text(json.dumps(summary))
    text = report.report_html(out)
    assert {b["data-units"] for b in _bars(text)} == {"rig units"}
    assert "8-bit, OpenGL convention" in text


def test_viewer_takes_units_and_the_normal_convention_from_the_result(
    result: nplps.Reconstruction, tmp_path: Path
) -> None:
    out = tmp_path / "r"
    result.save(out, units="mm", normal_map="directx")
    info = viewer.write_result_viewer(out)
    meta = viewer.read_viewer(info.path)["meta"]
    assert meta["units"] == "mm"
    assert meta["normal_map"] == "directx" and meta["normal_flip"] == [1.0, 1.0, -1.0]
    page = Path(info.path).read_text()
    assert 'id="scale"' in page and "uFlip" in page
    # --units still wins
    assert (
        viewer.read_viewer(viewer.write_result_viewer(out, tmp_path / "v.html", units="cm").path)["meta"]["units"]
        == "cm"
    )


def test_viewer_of_a_folder_without_summary_uses_the_defaults(result: nplps.Reconstruction, tmp_path: Path) -> None:
    out = tmp_path / "r"
    result.save(out, units="mm", normal_map="opencv")
    (out / "summary.json").unlink()
    meta = viewer.read_viewer(viewer.write_result_viewer(out).path)["meta"]
    assert meta["units"] == "rig units" and meta["normal_map"] == "opengl"


def test_viewer_scale_bar_in_headless_chromium(result: nplps.Reconstruction, tmp_path: Path) -> None:
    import shutil
    import subprocess

    browser = next(
        (shutil.which(b) for b in ("chromium", "chromium-browser", "google-chrome") if shutil.which(b)), None
    )
    if browser is None:
        pytest.skip("no Chromium for the headless page")
    out = tmp_path / "r"
    result.save(out, units="mm")
    page = viewer.write_result_viewer(out).path
    positions = viewer.read_viewer(page)["positions"]
    command = [
        browser,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
        "--no-first-run",
        f"--user-data-dir={tmp_path / 'profile'}",
        "--window-size=480,360",
        "--virtual-time-budget=5000",
        "--dump-dom",
        Path(page).resolve().as_uri() + "#zoom=2",
    ]
    dom = subprocess.run(command, capture_output=True, timeout=60, check=False).stdout.decode("utf-8", "replace")
    assert 'data-status="ready"' in dom
    box = re.search(
        r'<div id="scale"[^>]*data-length="([^"]*)" data-pixels="([^"]*)" data-per-pixel="([^"]*)" '
        r'data-view-height="([^"]*)"',
        dom,
    )
    assert box, dom[-2000:]
    length, pixels, per_pixel, height = (float(v) for v in box.groups())
    # length units per CSS pixel at the centre of rotation: the page's camera distance (zoom 2) and
    # its 30° vertical field of view over the canvas's height
    radius = 0.5 * float(np.linalg.norm(positions.max(axis=0) - positions.min(axis=0)))
    distance = radius / math.sin(math.radians(15)) * 1.05 / 2
    assert per_pixel == pytest.approx(2 * distance * math.tan(math.radians(15)) / height, rel=1e-5)
    assert pixels == pytest.approx(length / per_pixel, abs=0.01)
    assert 40 <= pixels <= 100
    assert re.search(r'<span id="scalelabel">[0-9.e+-]+ mm</span>', dom)


# --------------------------------------------------------------------------------------------------
# nplps reconstruct --normal-map / --normal-map-bits / --exr / --units
# --------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def scene_command(tmp_path_factory) -> list[str]:
    out = tmp_path_factory.mktemp("scene") / "sphere"
    buf = io.StringIO()
    with redirect_stdout(buf):
        assert cli.main(["synth", "sphere", "--size", "24", "--seed", "0", "--out", str(out)]) == 0
    line = next(line for line in buf.getvalue().splitlines() if line.strip().startswith("nplps reconstruct"))
    argv = shlex.split(line.strip())[1:]
    del argv[argv.index("--out") : argv.index("--out") + 2]
    return argv


def test_cli_normal_map_exr_and_units(scene_command: list[str], tmp_path: Path, capsys) -> None:
    pytest.importorskip("OpenEXR")
    out = tmp_path / "r"
    argv = [*scene_command, "--normal-map", "directx", "--exr", "--units", "mm", "--no-report", "--out", str(out)]
    assert cli.main(argv) == 0, capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["normal_map"] == {"file": "normals.png", "frame": "directx", "bits": 16}
    assert summary["units"] == "mm"
    assert summary["options"]["normal_map"] == "directx" and summary["options"]["exr"] is True
    assert _png_bit_depth(out / "normals.png") == 16
    _, header = export.read_exr(out / "normals.exr")
    assert header["nplps_normal_frame"] == "directx"
    exr, _ = export.read_exr(out / "depth.exr")
    np.testing.assert_array_equal(exr["Z"], np.load(out / "depth.npy").astype(np.float32))
    decoded = read_normal_map(out / "normals.png", "directx")
    normals = np.load(out / "normals.npy")
    valid = np.isfinite(normals).all(axis=2)
    assert _angles(decoded[valid], normals[valid]).max() <= 0.0016


def test_cli_8_bit_normal_map(scene_command: list[str], tmp_path: Path, capsys) -> None:
    out = tmp_path / "r"
    assert cli.main([*scene_command, "--normal-map-bits", "8", "--no-report", "--out", str(out)]) == 0
    assert _png_bit_depth(out / "normals.png") == 8
    assert json.loads((out / "summary.json").read_text())["normal_map"]["bits"] == 8


def test_cli_exr_without_openexr_fails_before_the_work(
    scene_command: list[str], tmp_path: Path, capsys, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "OpenEXR", None)
    out = tmp_path / "r"
    assert cli.main([*scene_command, "--exr", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert 'pip install "nplps[exr]"' in err
    assert "iterations" not in err  # refused before the reconstruction
    assert not out.exists()


def test_cli_rejects_an_unknown_convention(scene_command: list[str], tmp_path: Path, capsys) -> None:
    assert cli.main([*scene_command, "--normal-map", "vulkan", "--out", str(tmp_path / "r")]) == 2
    assert "invalid choice: 'vulkan'" in capsys.readouterr().err


def test_report_scale_bar_of_a_pinhole_camera(tmp_path: Path) -> None:
    scene = nplps.make_scene("sphere", n=40, seed=0, camera="pinhole")
    result = nplps.reconstruct(scene.images, scene.rig, depth=scene.mean_depth, mask=scene.mask)
    out = tmp_path / "r"
    result.save(out, units="mm", report=True)
    bars = _bars((out / report.REPORT_NAME).read_text())
    assert len(bars) == 3
    footprint, mean = views.pixel_footprint(result.rig, result.depth)
    assert mean == pytest.approx(float(np.nanmean(result.depth)))
    assert footprint == pytest.approx(mean / float(result.rig.K[0, 0]))
    # the mesh agrees: its vertices are about that far apart in x (nearer parts closer, farther wider)
    spacing = float(np.nanmedian(np.diff(result.vertices[..., 0], axis=1)))
    assert footprint == pytest.approx(spacing, rel=0.1)
    summary = json.loads((out / "summary.json").read_text())
    box = report._Data(out, summary).box
    shape = result.shape if box is None else (box[1] - box[0], box[3] - box[2])
    length = float(bars[0]["data-length"])  # under the normal map
    assert float(bars[0]["data-pixels"]) == pytest.approx(length / footprint * report._zoom(shape), abs=0.006)
