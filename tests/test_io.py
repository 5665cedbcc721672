"""Tests of nplps.io: reading images without losing precision, stacks and masks."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np
import png
import pytest
import tifffile
from PIL import Image

from nplps import io
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
