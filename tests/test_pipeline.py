"""Tests of nplps.pipeline: each step, their order, the dark rule for API users, float32 memory."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

import nplps
from nplps import captures, io, pipeline
from nplps import preprocess as pp
from nplps.cli import build_parser
from nplps.cli.inputs import build_inputs
from nplps.errors import InputError

K = np.array([[200.0, 0.0, 15.5], [0.0, 210.0, 11.5], [0.0, 0.0, 1.0]])


def _stack(k: int = 4, h: int = 24, w: int = 32, colour: bool = False, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    shape = (k, h, w, 3) if colour else (k, h, w)
    return (0.1 + 0.6 * rng.random(shape)).astype(np.float32)


# --------------------------------------------------------------------------------------------------
# Thresholds and saturation
# --------------------------------------------------------------------------------------------------


def test_thresholds_defaults_follow_levels_and_preprocessing() -> None:
    assert pipeline.thresholds(255) == (1 / 255, 1 - 0.5 / 255)
    assert pipeline.thresholds(65535, preprocessed=True) == (0.0, 1 - 0.5 / 65535)
    assert pipeline.thresholds(None) == (0.0, float("inf"))
    assert pipeline.thresholds(255, dark=0.2, saturation=0.9, preprocessed=True) == (0.2, 0.9)


def test_saturated_flags_any_channel_and_none_when_clean() -> None:
    images = np.zeros((2, 3, 4, 3), dtype=np.float32)
    images[1, 2, 3, 1] = 1.0
    flags = pipeline.saturated(images, 0.99)
    assert flags is not None and flags.shape == (2, 3, 4) and flags.sum() == 1 and flags[1, 2, 3]
    assert pipeline.saturated(images, 1.5) is None
    assert pipeline.saturated(images, float("inf")) is None


# --------------------------------------------------------------------------------------------------
# Grey and colour
# --------------------------------------------------------------------------------------------------


def test_to_gray_is_one_float32_arithmetic_everywhere(tmp_path: Path) -> None:
    colour = _stack(colour=True)
    expected = (colour[..., 0] + colour[..., 1] + colour[..., 2]) * np.float32(1 / 3)
    gray = pipeline.to_gray(colour)
    assert gray.dtype == np.float32
    np.testing.assert_array_equal(gray, expected)
    np.testing.assert_array_equal(pipeline.to_gray(colour[0], stack=False), expected[0])
    # every grey conversion of the package gives the same bits
    np.testing.assert_array_equal(io.to_gray(colour[0]), expected[0])
    np.testing.assert_array_equal(io.load_stack(colour, color=False)[0], expected)
    np.testing.assert_array_equal(io.load_stack(list(colour.astype(np.float64)), color=False)[0], expected)
    np.testing.assert_array_equal(pipeline.select_color(colour, False)[0], expected)
    c = captures.Capture(images=colour.copy())
    np.testing.assert_array_equal(c.load(color=False).images, expected)
    np.testing.assert_array_equal(pipeline.prepare(colour, color=False).images, expected)
    # grey input passes through without a copy
    assert pipeline.to_gray(expected) is expected
    # integers are scaled first
    np.testing.assert_allclose(pipeline.to_gray(np.full((1, 2, 2, 3), 255, np.uint8)), 1.0)
    with pytest.raises(InputError):
        pipeline.to_gray(np.zeros((2, 2)))


def test_select_color_choices() -> None:
    colour = _stack(colour=True)
    colour[0, 0, 0, 2] = 1.0
    kept, flags = pipeline.select_color(colour, None, 0.99)
    assert kept is colour and flags is None
    gray, flags = pipeline.select_color(colour, False, 0.99)
    assert gray.shape == colour.shape[:3] and flags is not None and flags[0, 0, 0] and flags.sum() == 1
    with pytest.raises(InputError, match="RGB"):
        pipeline.select_color(_stack(), True)
    with pytest.raises(InputError, match="color"):
        pipeline.select_color(colour, "grey")  # type: ignore[arg-type]


def test_decode_srgb_lut_and_formula() -> None:
    raw = np.arange(256, dtype=np.uint8).reshape(16, 16)
    exact = pp.srgb_to_linear(np.arange(256, dtype=np.float64) / 255).astype(np.float32)
    np.testing.assert_array_equal(pipeline.decode_srgb(raw), exact.reshape(16, 16))
    stack = _stack()
    np.testing.assert_array_equal(pipeline.decode_srgb(stack), pp.srgb_to_linear(stack))  # image by image
    out = stack.copy()
    assert pipeline.decode_srgb(out, out=out) is out
    assert pipeline.decode_srgb(stack.astype(np.float64)).dtype == np.float32


# --------------------------------------------------------------------------------------------------
# Corrections and their order
# --------------------------------------------------------------------------------------------------


def test_correct_runs_the_steps_in_order() -> None:
    images = _stack()
    ambient = np.full(images.shape[1:], 0.05, dtype=np.float32)
    exposures = np.array([1.0, 2.0, 0.5, 4.0])
    expected = pp.srgb_to_linear(images)
    expected = pp.subtract_ambient(expected, pp.srgb_to_linear(ambient))
    expected = pp.scale_exposure(expected, exposures)
    expected = pp.compensate_vignetting(expected, pp.vignetting_cos4(images.shape[1:], K))
    given = images.copy()
    out, steps = pipeline.correct(given, srgb=True, ambient=ambient, exposures=exposures, vignetting="cos4", K=K)
    assert steps == ["srgb", "ambient", "exposures", "vignetting"]
    np.testing.assert_array_equal(out, expected)
    np.testing.assert_array_equal(given, images)  # not overwritten without overwrite=True
    out2, _ = pipeline.correct(
        given, srgb=True, ambient=ambient, exposures=exposures, vignetting="cos4", K=K, overwrite=True
    )
    assert out2 is given
    np.testing.assert_array_equal(out2, expected)


def test_correct_side_images_follow_the_stack() -> None:
    colour = _stack(colour=True)
    grey_ambient = np.full(colour.shape[1:3], 0.05, dtype=np.float32)
    out, _ = pipeline.correct(colour, ambient=grey_ambient)  # a grey ambient applies to every channel
    np.testing.assert_array_equal(out, np.maximum(colour - 0.05 * np.ones(3, np.float32), 0))
    colour_ambient = np.full(colour.shape[1:], 0.05, dtype=np.float32)
    grey = pipeline.to_gray(colour)
    out, _ = pipeline.correct(grey, ambient=colour_ambient)  # a colour ambient becomes grey
    np.testing.assert_array_equal(out, pp.subtract_ambient(grey, pipeline.to_gray(colour_ambient[None])[0]))
    flat = np.linspace(0.5, 1.0, grey[0].size, dtype=np.float32).reshape(grey.shape[1:])
    out, steps = pipeline.correct(grey, flat=flat)
    assert steps == ["flat"]
    np.testing.assert_array_equal(out, pp.compensate_vignetting(grey, pp.flat_field_map(flat)))
    with pytest.raises(InputError, match="pixels but the images"):
        pipeline.correct(grey, ambient=np.zeros((3, 3)))
    with pytest.raises(InputError, match="pinhole"):
        pipeline.correct(grey, vignetting="cos4")
    with pytest.raises(InputError, match="one of them"):
        pipeline.correct(grey, vignetting="cos4", flat=flat, K=K)


def test_srgb_is_decoded_before_grey() -> None:
    """sRGB is not linear: the channel mean of the decoded values, not the decoded mean."""
    colour = _stack(colour=True)
    out = pipeline.prepare(colour, color=False, srgb=True).images
    np.testing.assert_array_equal(out, pipeline.to_gray(pp.srgb_to_linear(colour)))
    assert not np.array_equal(out, pp.srgb_to_linear(pipeline.to_gray(colour)))


# --------------------------------------------------------------------------------------------------
# Binning
# --------------------------------------------------------------------------------------------------


def test_bin_inputs_bins_everything_on_the_grid() -> None:
    images = _stack(h=25, w=33)
    mask = np.ones((25, 33), dtype=bool)
    mask[0, 0] = False
    valid = np.ones(images.shape, dtype=bool)
    valid[1, 5, 5] = False
    depth = np.arange(26 * 34, dtype=np.float64).reshape(26, 34)
    rig = nplps.Rig.pinhole(K, lights=[[10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [-10.0, 0.0, 0.0], [0.0, -10.0, 0.0]])
    b = pipeline.bin_inputs(images, 2, mask=mask, valid=valid, rig=rig, K=K, depth=depth)
    np.testing.assert_array_equal(b.images, pp.bin_images(images, 2))
    assert b.mask is not None and b.mask.shape == (12, 16) and not b.mask[0, 0] and b.mask[0, 1]
    assert b.valid is not None and not b.valid[1, 2, 2] and b.valid.sum() == b.valid.size - 1
    np.testing.assert_array_equal(b.K, pp.bin_intrinsics(K, 2))
    np.testing.assert_array_equal(b.rig.K, pp.bin_intrinsics(K, 2))
    assert b.depth is not None and b.depth.shape == (13, 17)
    np.testing.assert_array_equal(b.depth, depth[:25:2, :33:2])
    ortho = nplps.Rig.orthographic((0.5, 0.25), origin=(-1.0, -2.0), lights=rig.lights)
    binned = pipeline.bin_inputs(images, 3, rig=ortho).rig
    assert binned.camera["pixel_size"] == [1.5, 0.75] and list(binned.camera["origin"]) == [-1.0, -2.0]
    assert pipeline.bin_inputs(images, 1).images is images
    with pytest.raises(InputError, match="smaller than one"):
        pipeline.bin_inputs(images, 40)
    with pytest.raises(InputError, match="wholly inside the mask"):
        pipeline.bin_inputs(images, 2, mask=np.eye(25, 33, dtype=bool))


def test_bin_depth_keeps_the_block_corners() -> None:
    depth = np.add.outer(np.arange(7.0), 10 * np.arange(9.0))  # 6 x 8 pixels
    binned = pipeline.bin_depth(depth, 3)
    np.testing.assert_array_equal(binned, depth[::3, ::3][:3, :3])
    with pytest.raises(InputError):
        pipeline.bin_depth(np.zeros(4), 2)


# --------------------------------------------------------------------------------------------------
# The whole pipeline
# --------------------------------------------------------------------------------------------------


def test_prepare_judges_saturation_on_raw_values_and_sets_dark() -> None:
    raw = np.full((3, 6, 8), 100, dtype=np.uint8)
    raw[2, 1, 1] = 255
    plain = pipeline.prepare(raw)
    assert plain.levels == 255 and plain.steps == () and plain.dark == 1 / 255
    assert plain.valid is not None and not plain.valid[2, 1, 1] and plain.valid.sum() == plain.valid.size - 1
    # the ambient moves the value below the top level, but the raw value was saturated
    done = pipeline.prepare(raw, ambient=np.full((6, 8), 50, dtype=np.uint8))
    assert done.steps == ("ambient",) and done.dark == 0.0
    assert done.valid is not None and not done.valid[2, 1, 1]
    # grey alone keeps the default; given thresholds win; already pre-processed values: no flags
    colour = np.repeat(raw[..., None], 3, axis=3)
    assert pipeline.prepare(colour, color=False).dark == 1 / 255
    assert pipeline.prepare(raw, dark=0.3, bin_factor=2).dark == 0.3
    later = pipeline.prepare(io.to_float(raw), levels=255, preprocessed=("bin",))
    assert later.valid is None and later.dark == 0.0 and later.steps == ("bin",)


def test_prepare_outputs_are_float32_and_no_step_upcasts_the_stack() -> None:
    k, h, w = 32, 96, 128
    images = _stack(k, h, w)
    options = dict(
        K=K,
        srgb=True,
        ambient=np.full((h, w), 0.01, np.float32),
        exposures=np.linspace(1.0, 2.0, k),
        vignetting="cos4",
        bin_factor=2,
    )
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        out = pipeline.prepare(images, overwrite=True, **options)  # type: ignore[arg-type]
        in_place = tracemalloc.get_traced_memory()[1] - base
        base = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        copied = pipeline.prepare(images.copy(), **options)  # type: ignore[arg-type]
        one_copy = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert out.images.dtype == np.float32 and out.images.flags.c_contiguous
    assert copied.images.dtype == np.float32
    assert out.steps == ("srgb", "ambient", "exposures", "vignetting", "bin")
    # a float64 copy of the stack would be 2x its size; in place the steps need less than half
    # of it (the binned stack is a quarter), with a copy one float32 copy more
    assert in_place < 0.5 * images.nbytes, in_place / images.nbytes
    assert one_copy < 1.5 * images.nbytes + images.nbytes, one_copy / images.nbytes


def test_prepare_accepts_every_dtype_and_returns_float32(tmp_path: Path) -> None:
    for dtype in (np.uint8, np.uint16, np.float64, np.float32):
        raw = (np.ones((3, 4, 5)) * (7 if np.issubdtype(dtype, np.integer) else 0.25)).astype(dtype)
        assert pipeline.prepare(raw, bin_factor=2).images.dtype == np.float32
    files = []
    for i in range(3):
        files.append(tmp_path / f"im{i}.png")
        iio.imwrite(files[-1], np.full((4, 5, 3), 40 * i, dtype=np.uint8))
    out = pipeline.prepare(files, color=False)
    assert out.images.dtype == np.float32 and out.images.shape == (3, 4, 5) and out.levels == 255


# --------------------------------------------------------------------------------------------------
# The API, the captures and the command line share it
# --------------------------------------------------------------------------------------------------


def _files_and_rig(folder: Path) -> tuple[list[Path], Path]:
    folder.mkdir()
    rng = np.random.default_rng(3)
    files = []
    for i in range(4):
        files.append(folder / f"led{i + 1}.png")
        image = (40 + 150 * rng.random((16, 20))).astype(np.uint8)
        image[2, 3] = 255
        iio.imwrite(files[-1], image)
    rig = nplps.Rig.orthographic(0.5, lights=[[30.0, 0, 0], [0, 30.0, 0], [-30.0, 0, 0], [0, -30.0, 0]])
    rig.save(folder / "rig.json")
    return files, folder / "rig.json"


@pytest.mark.parametrize("bin_factor", [1, 2])
def test_cli_and_captures_prepare_give_the_same_input(tmp_path: Path, bin_factor: int) -> None:
    files, rig_path = _files_and_rig(tmp_path / "shots")
    args = build_parser().parse_args(
        [
            "reconstruct",
            *map(str, files),
            "--rig",
            str(rig_path),
            "--depth",
            "100",
            "--bin",
            str(bin_factor),
            "-q",
            "--out",
            str(tmp_path / "r"),
        ]
    )
    cli = build_inputs(args)
    capture = captures.Capture(images=list(files), files=list(files), rig_path=rig_path)
    prepared = captures.prepare(capture, bin_factor=bin_factor, ambient=False, vignetting=None)
    np.testing.assert_array_equal(prepared.images, cli.images)
    np.testing.assert_array_equal(prepared.valid, cli.valid)
    # the dark rule: the CLI's default, now also the capture's
    assert prepared.dark == cli.options["dark"] == (1 / 255 if bin_factor == 1 else 0.0)
    assert prepared.preprocessed == (() if bin_factor == 1 else ("bin",))
    options = prepared.options()
    assert options["dark"] == prepared.dark and options["valid"] is prepared.valid
    assert prepared.rig().camera == cli.rig.camera  # the rig file's camera, binned alike


def test_dark_rule_for_api_users(tmp_path: Path) -> None:
    files, rig_path = _files_and_rig(tmp_path / "shots")
    capture = captures.Capture(images=list(files), files=list(files), rig_path=rig_path)
    loaded = capture.load()
    assert loaded.levels == 255 and loaded.preprocessed == () and loaded.dark == 1 / 255
    done = captures.prepare(capture, bin_factor=2)
    assert done.preprocessed == ("bin",) and done.dark == 0.0 and done.levels == 255
    assert done.valid is not None and done.valid.shape == done.images.shape  # grey: (k, H, W)
    # a second prepare keeps the flags and counts the earlier steps
    again = captures.prepare(done, ambient=False, vignetting=None)
    assert again.preprocessed == ("bin",) and again.dark == 0.0
    np.testing.assert_array_equal(again.valid, done.valid)
    rig = done.rig()
    result = nplps.reconstruct(done.images, rig, depth=100.0, iterations=1, **done.options())
    assert result.depth.shape == (9, 11)


def test_natural_key_orders_numbers_by_value_and_breaks_ties() -> None:
    names = ["img10.png", "IMG2.png", "img2.png", "img02.png", "img1.png", "a.png", "1.png", "img.png"]
    ordered = sorted(names, key=pipeline.natural_key)
    # as before: the extension is text too, so "img.png" sorts after "img1.png" ("img" < "img.png")
    assert ordered == ["1.png", "a.png", "img1.png", "img02.png", "IMG2.png", "img2.png", "img10.png", "img.png"]
    assert sorted(reversed(names), key=pipeline.natural_key) == ordered  # no dependence on the input order
    assert pipeline.natural_key("dir9/img2.png") == pipeline.natural_key(Path("other/img2.png"))


def test_cli_and_captures_sort_files_alike(tmp_path: Path) -> None:
    from nplps.cli.imagefiles import resolve_images

    names = ["img10.png", "img2.png", "img1.png", "img02.png"]
    for n in names:
        iio.imwrite(tmp_path / n, np.zeros((2, 2), np.uint8))
    cli = [Path(p).name for p in resolve_images([str(tmp_path)], quiet=True)]
    loaders = [p.name for p in captures.find_images(tmp_path)]
    assert cli == loaders == ["img1.png", "img02.png", "img2.png", "img10.png"]
