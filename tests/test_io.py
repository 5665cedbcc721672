"""Tests of nplps.io: reading images without losing precision, stacks and masks."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import png
import pytest
import tifffile
from PIL import Image

from nplps import _core, io
from nplps.errors import InputError


def _write_png16_rgb(path: Path, pixels: np.ndarray) -> None:
    """Write an (H, W, 3) uint16 array as a genuine 16-bit RGB PNG with pypng."""
    height, width, _ = pixels.shape
    png.from_array(pixels.reshape(height, width * 3).tolist(), "RGB;16").save(str(path))


def _rgb16_pixels() -> np.ndarray:
    """16-bit RGB values that use the low byte (257 k + odd) up to 65535."""
    values = (257 * np.arange(12, dtype=np.int64) * 20 + 2 * np.arange(12) + 1).reshape(2, 2, 3)
    values[-1, -1, -1] = 65535
    assert values.max() <= 65535 and np.any(values % 257 != 0)
    return values.astype(np.uint16)


# --------------------------------------------------------------------------------------------------
# read_image
# --------------------------------------------------------------------------------------------------


def test_read_png16_rgb_keeps_all_bits(tmp_path: Path) -> None:
    pixels = _rgb16_pixels()
    path = tmp_path / "rgb16.png"
    _write_png16_rgb(path, pixels)

    image = io.read_image(path)

    assert image.dtype == np.uint16
    assert image.shape == (2, 2, 3)
    np.testing.assert_array_equal(image, pixels)


def test_imageio_default_reader_truncates_png16_rgb(tmp_path: Path) -> None:
    """Documents why read_image bypasses imageio for 16-bit PNG.

    imageio 2.38 + Pillow returns this file as uint8. If a future imageio keeps the 16 bits the
    assertion on imageio is skipped; our reader must be exact either way.
    """
    pixels = _rgb16_pixels()
    path = tmp_path / "rgb16.png"
    _write_png16_rgb(path, pixels)

    by_imageio = np.asarray(iio.imread(path))
    if by_imageio.dtype == np.uint8:  # the known truncation: only 8 of the 16 bits survive
        assert not np.array_equal(by_imageio.astype(np.uint16), pixels)
    np.testing.assert_array_equal(io.read_image(path), pixels)


def test_read_png16_grey(tmp_path: Path) -> None:
    pixels = np.array([[1, 258, 4097], [30001, 65534, 65535]], dtype=np.uint16)
    path = tmp_path / "grey16.png"
    png.from_array(pixels.tolist(), "L;16").save(str(path))

    image = io.read_image(path)

    assert image.dtype == np.uint16
    np.testing.assert_array_equal(image, pixels)


def test_read_png16_rgba_drops_alpha(tmp_path: Path) -> None:
    rgba = np.arange(2 * 3 * 4, dtype=np.uint16).reshape(2, 3, 4) * 1001 + 3
    path = tmp_path / "rgba16.png"
    png.from_array(rgba.reshape(2, 12).tolist(), "RGBA;16").save(str(path))

    image = io.read_image(path)

    np.testing.assert_array_equal(image, rgba[..., :3])


def test_read_png8_rgb_and_to_gray(tmp_path: Path) -> None:
    pixels = np.array([[[0, 30, 60], [255, 255, 255]], [[3, 6, 9], [10, 0, 20]]], dtype=np.uint8)
    path = tmp_path / "rgb8.png"
    iio.imwrite(path, pixels)

    image = io.read_image(path)

    assert image.dtype == np.uint8
    np.testing.assert_array_equal(image, pixels)
    gray = io.to_gray(image)
    assert gray.dtype == np.float32 and gray.shape == (2, 2)
    np.testing.assert_allclose(gray, pixels.mean(axis=2) / 255.0, rtol=1e-6)


def test_read_png8_rgba_drops_alpha(tmp_path: Path) -> None:
    rgba = np.arange(2 * 2 * 4, dtype=np.uint8).reshape(2, 2, 4) * 10
    path = tmp_path / "rgba8.png"
    iio.imwrite(path, rgba)

    np.testing.assert_array_equal(io.read_image(path), rgba[..., :3])


def test_read_grey_palette_png_is_2d(tmp_path: Path) -> None:
    indices = np.array([[0, 1, 2], [3, 2, 1]], dtype=np.uint8)
    levels = [0, 100, 200, 255]
    image = Image.fromarray(indices, mode="P")
    palette = [value for level in levels for value in (level, level, level)]
    image.putpalette(palette)
    path = tmp_path / "palette.png"
    image.save(path)
    assert open(path, "rb").read()[25] == 3  # colour type: palette

    pixels = io.read_image(path)

    assert pixels.shape == (2, 3)
    np.testing.assert_array_equal(pixels, np.array(levels, dtype=np.uint8)[indices])


def test_read_colour_palette_png_is_rgb(tmp_path: Path) -> None:
    indices = np.array([[0, 1], [1, 0]], dtype=np.uint8)
    image = Image.fromarray(indices, mode="P")
    image.putpalette([255, 0, 0, 0, 0, 255])
    path = tmp_path / "palette_rgb.png"
    image.save(path)

    pixels = io.read_image(path)

    assert pixels.shape == (2, 2, 3)
    np.testing.assert_array_equal(pixels[0, 0], [255, 0, 0])
    np.testing.assert_array_equal(pixels[0, 1], [0, 0, 255])


@pytest.mark.parametrize("dtype", [np.float32, np.uint16])
def test_read_tiff_round_trip(tmp_path: Path, dtype: type) -> None:
    rng = np.random.default_rng(0)
    pixels = (rng.random((4, 5)) * 1000).astype(dtype)
    path = tmp_path / "image.tif"
    tifffile.imwrite(path, pixels)

    image = io.read_image(path)

    assert image.dtype == dtype
    np.testing.assert_array_equal(image, pixels)


def test_read_tiff_rgb_planar_is_channel_last(tmp_path: Path) -> None:
    pixels = np.arange(3 * 4 * 5, dtype=np.uint16).reshape(3, 4, 5)
    path = tmp_path / "planar.tif"
    tifffile.imwrite(path, pixels, photometric="rgb", planarconfig="separate")

    image = io.read_image(path)

    np.testing.assert_array_equal(image, np.moveaxis(pixels, 0, -1))


def test_read_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "missing.png"
    with pytest.raises(InputError, match=r"missing\.png.*not found"):
        io.read_image(path)


def test_read_corrupt_file(tmp_path: Path) -> None:
    path = tmp_path / "corrupt.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 10)
    with pytest.raises(InputError, match=r"cannot read image .*corrupt\.png"):
        io.read_image(path)


# --------------------------------------------------------------------------------------------------
# The Rust PNG decoder (nplps._core.read_pngs, used by read_image and load_stack)
# --------------------------------------------------------------------------------------------------


def _write_png(path: Path, rows: np.ndarray, **options: object) -> Path:
    """Write ``rows`` ((H, W * planes) integers) with pypng's Writer and the given options."""
    height, width = rows.shape[0], options.pop("width")
    options.setdefault("greyscale", False)
    with open(path, "wb") as file:
        png.Writer(width, height, **options).write(file, rows.astype(np.int64).tolist())
    return path


def _ramp(shape: tuple[int, ...], top: int) -> np.ndarray:
    """Deterministic values in 0..top that hit both ends."""
    values = (np.arange(int(np.prod(shape))) * 7919) % (top + 1)
    values[0], values[-1] = 0, top
    return values.reshape(shape)


def test_rust_decoder_8bit_grey_and_rgb(tmp_path: Path) -> None:
    grey = _ramp((3, 5), 255).astype(np.uint8)
    rgb = _ramp((3, 5, 3), 255).astype(np.uint8)
    paths = [
        _write_png(tmp_path / "g8.png", grey, width=5, greyscale=True, bitdepth=8),
        _write_png(tmp_path / "rgb8.png", rgb.reshape(3, 15), width=5, greyscale=False, bitdepth=8),
    ]

    out = _core.read_pngs(paths, io.MAX_PIXELS)

    assert [a.dtype for a in out] == [np.uint8, np.uint8]
    np.testing.assert_array_equal(out[0], grey)
    np.testing.assert_array_equal(out[1], rgb)


def test_rust_decoder_16bit_grey_and_rgb_keep_every_bit(tmp_path: Path) -> None:
    grey = _ramp((4, 3), 65535).astype(np.uint16)
    rgb = _ramp((4, 3, 3), 65535).astype(np.uint16)
    assert np.any(grey % 257 != 0) and np.any(rgb % 257 != 0)  # the low byte matters
    paths = [
        _write_png(tmp_path / "g16.png", grey, width=3, greyscale=True, bitdepth=16),
        _write_png(tmp_path / "rgb16.png", rgb.reshape(4, 9), width=3, greyscale=False, bitdepth=16),
    ]

    out = _core.read_pngs(paths, io.MAX_PIXELS)

    assert [a.dtype for a in out] == [np.uint16, np.uint16]
    np.testing.assert_array_equal(out[0], grey)
    np.testing.assert_array_equal(out[1], rgb)


@pytest.mark.parametrize("bitdepth", [8, 16])
def test_rust_decoder_drops_alpha(tmp_path: Path, bitdepth: int) -> None:
    top = 2**bitdepth - 1
    la = _ramp((2, 4, 2), top)
    rgba = _ramp((2, 4, 4), top)
    paths = [
        _write_png(tmp_path / "la.png", la.reshape(2, 8), width=4, greyscale=True, alpha=True, bitdepth=bitdepth),
        _write_png(tmp_path / "rgba.png", rgba.reshape(2, 16), width=4, alpha=True, bitdepth=bitdepth),
    ]

    grey, colour = _core.read_pngs(paths, io.MAX_PIXELS)

    np.testing.assert_array_equal(grey, la[..., 0])
    np.testing.assert_array_equal(colour, rgba[..., :3])


def test_rust_decoder_palettes(tmp_path: Path) -> None:
    """Palette images are expanded; all-grey ones (hehe12's identity ramp) become (H, W); the
    transparency of palette entries (tRNS) is dropped with the alpha channel."""
    indices = np.array([[0, 1, 2, 3], [3, 2, 1, 0]])
    grey_palette = [(0, 0, 0), (90, 90, 90), (180, 180, 180), (255, 255, 255)]
    colour_palette = [(255, 0, 0, 0), (0, 255, 0, 128), (0, 0, 255, 255), (7, 7, 7, 255)]
    paths = [
        _write_png(tmp_path / "grey.png", indices, width=4, palette=grey_palette, bitdepth=2),
        _write_png(tmp_path / "colour.png", indices, width=4, palette=colour_palette, bitdepth=8),
        _write_png(tmp_path / "used_grey.png", np.full((2, 4), 3), width=4, palette=colour_palette, bitdepth=4),
    ]

    grey, colour, used_grey = _core.read_pngs(paths, io.MAX_PIXELS)

    np.testing.assert_array_equal(grey, np.array(grey_palette)[indices, 0])
    assert colour.dtype == np.uint8
    np.testing.assert_array_equal(colour, np.array(colour_palette)[indices, :3])
    # Only grey entries are used: grey, like the imageio-based reader before.
    np.testing.assert_array_equal(used_grey, np.full((2, 4), 7))


@pytest.mark.parametrize("bitdepth", [1, 2, 4])
def test_rust_decoder_low_bit_grey_scaled_like_imageio(tmp_path: Path, bitdepth: int) -> None:
    rows = _ramp((3, 9), 2**bitdepth - 1)
    path = _write_png(tmp_path / "low.png", rows, width=9, greyscale=True, bitdepth=bitdepth)

    (image,) = _core.read_pngs([path], io.MAX_PIXELS)

    assert image.dtype == np.uint8
    np.testing.assert_array_equal(image, rows * (255 // (2**bitdepth - 1)))
    by_imageio = np.asarray(iio.imread(path))
    if by_imageio.dtype == np.bool_:
        by_imageio = by_imageio.astype(np.uint8) * 255
    np.testing.assert_array_equal(image, by_imageio)


@pytest.mark.parametrize("bitdepth", [8, 16])
def test_rust_decoder_interlaced(tmp_path: Path, bitdepth: int) -> None:
    rgb = _ramp((11, 13, 3), 2**bitdepth - 1)
    path = _write_png(tmp_path / "adam7.png", rgb.reshape(11, 39), width=13, bitdepth=bitdepth, interlace=True)

    (image,) = _core.read_pngs([path], io.MAX_PIXELS)

    np.testing.assert_array_equal(image, rgb)


def test_rust_decoder_matches_imageio_on_8bit_variants(tmp_path: Path) -> None:
    """What read_image returned before the Rust decoder (imageio, alpha dropped, grey palette to
    grey) for 8-bit files written by Pillow."""
    rng = np.random.default_rng(3)
    images = {
        "L": rng.integers(0, 256, (6, 7), dtype=np.uint8),
        "LA": rng.integers(0, 256, (6, 7, 2), dtype=np.uint8),
        "RGB": rng.integers(0, 256, (6, 7, 3), dtype=np.uint8),
        "RGBA": rng.integers(0, 256, (6, 7, 4), dtype=np.uint8),
    }
    paths = []
    for mode, pixels in images.items():
        paths.append(tmp_path / f"{mode}.png")
        Image.fromarray(pixels).save(paths[-1])
        assert Image.open(paths[-1]).mode == mode
    decoded = _core.read_pngs(paths, io.MAX_PIXELS)
    for path, image in zip(paths, decoded, strict=True):
        expected = np.asarray(iio.imread(path))
        expected = expected[..., 0] if expected.ndim == 3 and expected.shape[2] == 2 else expected
        expected = expected[..., :3] if expected.ndim == 3 else expected
        np.testing.assert_array_equal(image, expected, err_msg=path.name)


def test_rust_decoder_keeps_the_order_of_many_files(tmp_path: Path) -> None:
    paths = []
    for i in range(23):
        paths.append(tmp_path / f"{i}.png")
        _write_png(paths[-1], np.full((2, 3), 1000 * i), width=3, greyscale=True, bitdepth=16)

    decoded = _core.read_pngs(paths, io.MAX_PIXELS)

    assert [int(image[0, 0]) for image in decoded] == [1000 * i for i in range(23)]


def test_rust_decoder_corrupt_files_raise_input_error_naming_them(tmp_path: Path) -> None:
    good = _write_png(tmp_path / "good.png", np.zeros((2, 2)), width=2, greyscale=True, bitdepth=8)
    garbage = tmp_path / "garbage.png"
    garbage.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 10)
    whole = _write_png(tmp_path / "whole.png", _ramp((64, 64), 65535), width=64, greyscale=True, bitdepth=16)
    truncated = tmp_path / "truncated.png"
    truncated.write_bytes(whole.read_bytes()[:200])

    for bad in (garbage, truncated):
        with pytest.raises(InputError, match=rf"cannot read image '.*{bad.name}'"):
            _core.read_pngs([good, bad, good], io.MAX_PIXELS)
        with pytest.raises(InputError, match=rf"cannot read image '.*{bad.name}'"):
            io.load_stack([good, bad])
    # The first bad file in the order given is the one named.
    with pytest.raises(InputError, match=r"garbage\.png"):
        _core.read_pngs([good, garbage, truncated], io.MAX_PIXELS)
    with pytest.raises(InputError, match=r"nowhere\.png': file not found"):
        _core.read_pngs([good, tmp_path / "nowhere.png"], io.MAX_PIXELS)


def test_pixel_limit_refuses_large_images_before_decoding(tmp_path: Path) -> None:
    path = _write_png(tmp_path / "big.png", np.zeros((20, 30)), width=30, greyscale=True, bitdepth=16)

    assert _core.read_pngs([path], 600)[0].shape == (20, 30)
    with pytest.raises(InputError, match=r"big\.png.*30 x 20 pixels is more than the limit of 599"):
        _core.read_pngs([path], 599)
    with pytest.raises(InputError, match=r"big\.png.*limit of 599"):
        io.read_image(path, max_pixels=599)
    with pytest.raises(InputError, match=r"big\.png.*limit of 100"):
        io.load_stack([path, path], max_pixels=100)
    tif = tmp_path / "big.tif"
    tifffile.imwrite(tif, np.zeros((20, 30, 3), dtype=np.uint16), photometric="rgb")
    assert io.read_image(tif, max_pixels=600).shape == (20, 30, 3)
    with pytest.raises(InputError, match=r"big\.tif.*30 x 20 pixels is more than the limit of 599"):
        io.read_image(tif, max_pixels=599)
    pages = tmp_path / "pages.tif"
    tifffile.imwrite(pages, np.zeros((5, 20, 30), dtype=np.uint8))
    with pytest.raises(InputError, match=r"pages\.tif.*30 x 20 pixels in 5 pages is more than the limit of 1000"):
        io.read_image(pages, max_pixels=1000)
    assert io.MAX_PIXELS == 2**28


def test_pixel_limit_of_the_imageio_formats_counts_every_frame(tmp_path: Path) -> None:
    """JPEG, BMP, GIF, ...: the header's size (every frame of it) is checked before decoding."""
    jpeg = tmp_path / "big.jpg"
    iio.imwrite(jpeg, np.zeros((20, 30, 3), dtype=np.uint8))
    assert io.read_image(jpeg, max_pixels=600).shape == (20, 30, 3)
    with pytest.raises(InputError, match=r"big\.jpg.*30 x 20 pixels is more than the limit of 599"):
        io.read_image(jpeg, max_pixels=599)
    # A GIF's declared shape is (frames, H, W, 3): the old guard took (frames, H) for (H, W).
    gif = tmp_path / "frames.gif"
    iio.imwrite(gif, np.zeros((1, 20, 30, 3), dtype=np.uint8))
    with pytest.raises(InputError, match=r"frames\.gif.*30 x 20 pixels.* is more than the limit of 599"):
        io.read_image(gif, max_pixels=599)


def test_bomb_header_is_refused_without_allocating(tmp_path: Path) -> None:
    """A few hundred bytes that declare a 2^30 x 2^30 image: refused from the header."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", 2**30, 2**30, 16, 2, 0, 0, 0)
    path = tmp_path / "bomb.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\0" * 1000)))

    with pytest.raises(InputError, match=r"bomb\.png.*1073741824 x 1073741824 pixels is more than the limit"):
        io.read_image(path)


def test_load_stack_in_batches_matches_image_by_image(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Files decoded in several parallel batches, mixed with arrays and TIFF files, land in the
    right place of the stack with the values read_image + to_float give."""
    monkeypatch.setattr(io, "_BATCH_BYTES", 1)  # a batch per core's worth of files
    rng = np.random.default_rng(4)
    items: list[object] = []
    for i in range(9):
        rgb = rng.integers(0, 65536, (5, 6, 3), dtype=np.uint16)
        if i == 4:
            items.append(rgb.astype(np.float32) / 65535)
        elif i == 6:
            items.append(tmp_path / f"{i}.tif")
            tifffile.imwrite(items[-1], rgb, photometric="rgb")
        else:
            items.append(_write_png(tmp_path / f"{i}.png", rgb.reshape(5, 18), width=6, bitdepth=16))
    expected = [io.to_float(io.read_image(p) if isinstance(p, Path) else p) for p in items]

    colour, levels = io.load_stack(items, color=True)
    grey, _ = io.load_stack(items, color=False)

    assert levels is None  # one float image
    np.testing.assert_array_equal(colour, np.stack(expected))
    np.testing.assert_array_equal(grey, np.stack([io.to_gray(e) for e in expected]))


def test_load_stack_colour_then_grey_file_gives_grey(tmp_path: Path) -> None:
    rgb = _ramp((3, 4, 3), 255).astype(np.uint8)
    grey = _ramp((3, 4), 65535).astype(np.uint16)
    a = _write_png(tmp_path / "a.png", rgb.reshape(3, 12), width=4, bitdepth=8)
    b = _write_png(tmp_path / "b.png", grey, width=4, greyscale=True, bitdepth=16)

    stack, levels = io.load_stack([a, a, b], color=True)

    assert stack.shape == (3, 3, 4) and levels == 65535
    np.testing.assert_array_equal(stack[0], io.to_gray(rgb))
    np.testing.assert_array_equal(stack[2], io.to_float(grey))


# --------------------------------------------------------------------------------------------------
# to_float / to_gray
# --------------------------------------------------------------------------------------------------


def test_to_float_scales_integers() -> None:
    np.testing.assert_array_equal(io.to_float(np.array([0, 255], dtype=np.uint8)), [0.0, 1.0])
    np.testing.assert_array_equal(io.to_float(np.array([0, 65535], dtype=np.uint16)), [0.0, 1.0])
    assert io.to_float(np.array([257], dtype=np.uint16))[0] == pytest.approx(257 / 65535)
    assert io.to_float(np.zeros(2, dtype=np.uint8)).dtype == np.float32


def test_to_float_keeps_float_values() -> None:
    values = np.array([-0.5, 2.5, 1e6])
    result = io.to_float(values)
    assert result.dtype == np.float32
    np.testing.assert_array_equal(result, values.astype(np.float32))


def test_to_gray_rejects_bad_shape() -> None:
    with pytest.raises(InputError, match=r"\(2, 2, 5\)"):
        io.to_gray(np.zeros((2, 2, 5)))


# --------------------------------------------------------------------------------------------------
# load_images
# --------------------------------------------------------------------------------------------------


def test_load_images_from_uint8_colour_stack() -> None:
    stack = np.full((2, 3, 4, 3), 255, dtype=np.uint8)
    stack[1, ..., 0] = 0

    images = io.load_images(stack)

    assert images.dtype == np.float32 and images.shape == (2, 3, 4)
    np.testing.assert_allclose(images[0], 1.0)
    np.testing.assert_allclose(images[1], 2.0 / 3.0, rtol=1e-6)


def test_load_images_from_float_stack_allows_negative() -> None:
    stack = np.array([[[-0.1, 0.5]], [[0.2, 3.0]]], dtype=np.float64)
    np.testing.assert_allclose(io.load_images(stack), stack.astype(np.float32))


def test_load_images_from_mixed_sequence(tmp_path: Path) -> None:
    grey16 = np.array([[0, 65535], [257, 514]], dtype=np.uint16)
    path = tmp_path / "a.png"
    png.from_array(grey16.tolist(), "L;16").save(str(path))
    rgb = np.zeros((2, 2, 3), dtype=np.float32)
    rgb[..., 1] = 0.3

    images = io.load_images([path, str(path), rgb])

    assert images.shape == (3, 2, 2)
    np.testing.assert_allclose(images[0], grey16 / 65535.0, rtol=1e-6)
    np.testing.assert_array_equal(images[0], images[1])
    np.testing.assert_allclose(images[2], 0.1, rtol=1e-6)


def test_load_images_different_sizes(tmp_path: Path) -> None:
    paths = []
    for name, shape in (("a.png", (3, 4)), ("b.png", (3, 4)), ("c.png", (5, 4))):
        paths.append(tmp_path / name)
        iio.imwrite(paths[-1], np.zeros(shape, dtype=np.uint8))
    with pytest.raises(InputError, match=r"image 2 \('.*c\.png'\) has shape \(5, 4\).*\(3, 4\)"):
        io.load_images(paths)


def test_load_images_nan_counted() -> None:
    stack = np.ones((3, 2, 2), dtype=np.float32)
    stack[1, 0, 0] = np.nan
    stack[1, 1, 1] = np.inf
    with pytest.raises(InputError, match=r"non-finite.*image 1: 2"):
        io.load_images(stack)


def test_load_images_nan_in_file_named(tmp_path: Path) -> None:
    image = np.ones((2, 2), dtype=np.float32)
    image[0, 1] = np.nan
    path = tmp_path / "nan.tif"
    tifffile.imwrite(path, image)
    with pytest.raises(InputError, match=r"image 0 \('.*nan\.tif'\): 1"):
        io.load_images([path])


def test_load_images_empty() -> None:
    with pytest.raises(InputError, match="empty"):
        io.load_images([])
    with pytest.raises(InputError, match="empty"):
        io.load_images(np.zeros((0, 2, 2)))


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # imageio probes its legacy plugins
def test_load_images_unreadable_file(tmp_path: Path) -> None:
    good = tmp_path / "good.png"
    iio.imwrite(good, np.zeros((2, 2), dtype=np.uint8))
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not an image at all")
    with pytest.raises(InputError, match=r"bad\.png"):
        io.load_images([good, bad])
    with pytest.raises(InputError, match=r"nowhere\.png.*not found"):
        io.load_images([good, tmp_path / "nowhere.png"])


def test_load_images_wrong_ndim() -> None:
    with pytest.raises(InputError, match=r"\(k, H, W\).*\(2, 2\)"):
        io.load_images(np.zeros((2, 2)))
    with pytest.raises(InputError, match=r"image 1: expected shape"):
        io.load_images([np.zeros((2, 2)), np.zeros((2, 2, 2, 2))])


def test_load_images_single_path_rejected(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="sequence"):
        io.load_images(str(tmp_path / "a.png"))


# --------------------------------------------------------------------------------------------------
# load_mask
# --------------------------------------------------------------------------------------------------


def test_load_mask_none_is_all_true() -> None:
    mask = io.load_mask(None, (2, 3))
    assert mask.dtype == bool and mask.shape == (2, 3) and mask.all()


def test_load_mask_from_arrays() -> None:
    values = np.array([[0.0, 0.5], [np.nan, -1.0]])
    np.testing.assert_array_equal(io.load_mask(values, (2, 2)), [[False, True], [False, True]])
    colour = np.zeros((2, 2, 3), dtype=np.uint8)
    colour[0, 0, 0] = 255
    colour[1, 1, 1] = 255  # channel 1 is ignored
    np.testing.assert_array_equal(io.load_mask(colour, (2, 2)), [[True, False], [False, False]])


def test_load_mask_from_files(tmp_path: Path) -> None:
    grey = np.array([[0, 255], [1, 0]], dtype=np.uint8)
    path = tmp_path / "mask.png"
    iio.imwrite(path, grey)
    np.testing.assert_array_equal(io.load_mask(path, (2, 2)), grey > 0)

    colour = np.zeros((2, 2, 3), dtype=np.uint8)
    colour[1, 0, 0] = 200
    colour_path = tmp_path / "mask_rgb.png"
    iio.imwrite(colour_path, colour)
    np.testing.assert_array_equal(io.load_mask(str(colour_path), (2, 2)), colour[..., 0] > 0)


def test_load_mask_wrong_shape() -> None:
    with pytest.raises(InputError, match=r"\(2, 3\).*\(3, 2\)"):
        io.load_mask(np.ones((2, 3)), (3, 2))


def test_load_mask_empty(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="mask is empty"):
        io.load_mask(np.zeros((2, 2)), (2, 2))
    path = tmp_path / "black.png"
    iio.imwrite(path, np.zeros((2, 2), dtype=np.uint8))
    with pytest.raises(InputError, match=r"mask is empty.*black\.png"):
        io.load_mask(path, (2, 2))


def test_load_mask_missing_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"nomask\.png"):
        io.load_mask(tmp_path / "nomask.png", (2, 2))


def _raises_within(call: Callable[[], object], seconds: float = 10.0) -> BaseException | None:
    """Run ``call`` in a daemon thread; the exception it raised (None if it returned), or fail
    the test if it is still running after ``seconds`` (a blocked open or an endless read)."""
    import threading

    outcome: list[BaseException | None] = []

    def run() -> None:
        try:
            call()
            outcome.append(None)
        except BaseException as exc:  # handed to the test
            outcome.append(exc)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(seconds)
    assert outcome, f"still running after {seconds} s"
    return outcome[0]


@pytest.mark.skipif(not hasattr(__import__("os"), "mkfifo"), reason="needs FIFOs (POSIX)")
def test_devices_pipes_and_directories_are_refused_before_they_are_read(tmp_path: Path) -> None:
    # /dev/zero never ends (imageio's sniffing read it until the memory ran out), opening a FIFO
    # waits for a writer: both are refused from their file type, at once, naming the path.
    import os

    fifo = tmp_path / "images.png"
    os.mkfifo(fifo)
    for path, kind in [("/dev/zero", "device"), (fifo, "pipe"), (tmp_path, "directory")]:
        if not os.path.exists(path):
            continue
        for call in (partial(io.read_image, path), lambda p=path: list(io.iter_images([p]))):
            exc = _raises_within(call)
            assert isinstance(exc, InputError), exc
            assert str(path) in str(exc) and "not a regular file" in str(exc) and kind in str(exc)


@pytest.mark.skipif(not hasattr(__import__("os"), "mkfifo"), reason="needs FIFOs (POSIX)")
def test_rig_ply_and_raw_readers_refuse_devices_and_pipes(tmp_path: Path) -> None:
    # The other readers of user files: a rig file, a PLY mesh, a camera RAW file. Each is refused
    # from its file type at once (a FIFO would block in open, /dev/zero would be read until a limit).
    import os

    from nplps import export, raw
    from nplps.errors import RigError
    from nplps.rig import read_rig_json

    calls: list[tuple[str, Callable[[str], object], type[Exception]]] = [
        ("rig.json", read_rig_json, RigError),
        ("mesh.ply", export.read_ply, InputError),
    ]
    try:
        import rawpy  # noqa: F401

        calls.append(("image.dng", raw.read_raw, InputError))
    except ImportError:
        pass
    for name, reader, error in calls:
        fifo = tmp_path / name
        os.mkfifo(fifo)
        for path, kind in [("/dev/zero", "device"), (str(fifo), "pipe")]:
            if not os.path.exists(path):
                continue
            exc = _raises_within(partial(reader, path))
            assert isinstance(exc, error), (name, exc)
            assert path in str(exc) and "not a regular file" in str(exc) and kind in str(exc), exc
