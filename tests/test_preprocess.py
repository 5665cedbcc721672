"""Tests of nplps.preprocess: ambient, exposure, sRGB, vignetting, binning, padding."""

from __future__ import annotations

import numpy as np
import pytest

from nplps import preprocess as pp
from nplps.errors import InputError


def _K(fx: float = 100.0, fy: float = 100.0, cx: float = 10.0, cy: float = 7.0, s: float = 0.0):
    return np.array([[fx, s, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


# --------------------------------------------------------------------------------------------------
# Ambient and exposure
# --------------------------------------------------------------------------------------------------


def test_subtract_ambient_clips_at_zero() -> None:
    images = np.array([[[0.5, 0.1]], [[0.2, 0.3]]], dtype=np.float32)  # (2, 1, 2)
    before = images.copy()
    ambient = np.array([[0.2, 0.2]], dtype=np.float32)
    out = pp.subtract_ambient(images, ambient)
    np.testing.assert_allclose(out, [[[0.3, 0.0]], [[0.0, 0.1]]], atol=1e-7)
    assert out.dtype == np.float32 and out.shape == images.shape
    raw = pp.subtract_ambient(images, ambient, clip=False)
    np.testing.assert_allclose(raw, [[[0.3, -0.1]], [[0.0, 0.1]]], atol=1e-7)
    np.testing.assert_array_equal(images, before)  # input untouched


def test_subtract_ambient_broadcasts_colour_and_scalars() -> None:
    images = np.full((3, 2, 2, 3), 0.5)
    ambient = np.zeros((2, 2, 3))
    ambient[..., 1] = 0.25
    out = pp.subtract_ambient(images, ambient)
    assert out.dtype == np.float64
    np.testing.assert_allclose(out[..., 1], 0.25)
    np.testing.assert_allclose(out[..., 0], 0.5)
    np.testing.assert_allclose(pp.subtract_ambient(images, 0.6), 0.0)


def test_subtract_ambient_scales_integers_and_rejects_bad_shapes() -> None:
    images = np.array([[[255, 100]]], dtype=np.uint8)
    out = pp.subtract_ambient(images, np.array([[51, 200]], dtype=np.uint8))
    np.testing.assert_allclose(out, [[[204 / 255, 0.0]]], rtol=1e-6)
    with pytest.raises(InputError, match="does not broadcast"):
        pp.subtract_ambient(np.zeros((2, 4, 5)), np.zeros((4, 6)))
    with pytest.raises(InputError, match="does not broadcast"):
        pp.subtract_ambient(np.zeros((4, 5)), np.zeros((2, 4, 5)))  # would grow the images


def test_scale_exposure_per_image_and_per_channel() -> None:
    images = np.ones((2, 2, 3), dtype=np.float32)
    out = pp.scale_exposure(images, [2.0, 4.0])
    np.testing.assert_allclose(out[0], 0.5)
    np.testing.assert_allclose(out[1], 0.25)
    assert out.dtype == np.float32
    colour = np.ones((2, 1, 1, 3))
    rgb = pp.scale_exposure(colour, [[1.0, 2.0, 4.0], [0.5, 1.0, 2.0]])
    np.testing.assert_allclose(rgb[:, 0, 0], [[1.0, 0.5, 0.25], [2.0, 1.0, 0.5]])
    with pytest.raises(InputError, match="positive"):
        pp.scale_exposure(images, [1.0, 0.0])
    with pytest.raises(InputError, match="exposures"):
        pp.scale_exposure(images, [1.0, 2.0, 3.0])
    with pytest.raises(InputError, match="exposures"):
        pp.scale_exposure(images, np.ones((2, 3)))  # per-channel needs a colour stack


# --------------------------------------------------------------------------------------------------
# sRGB
# --------------------------------------------------------------------------------------------------


def test_srgb_to_linear_reference_values() -> None:
    x = np.array([0.0, 0.04045, 0.5, 1.0])
    np.testing.assert_allclose(pp.srgb_to_linear(x), [0.0, 0.0031308, 0.21404, 1.0], atol=5e-6)
    assert pp.srgb_to_linear(x).dtype == np.float64
    assert pp.srgb_to_linear(x.astype(np.float32)).dtype == np.float32
    # The two branches meet at the threshold (continuity to ~1e-7).
    eps = 1e-9
    lo, hi = pp.srgb_to_linear(np.array([0.04045 - eps, 0.04045 + eps]))
    assert abs(hi - lo) < 1e-7


def test_srgb_integers_and_round_trip() -> None:
    u8 = np.array([0, 128, 255], dtype=np.uint8)
    np.testing.assert_allclose(pp.srgb_to_linear(u8), [0.0, ((128 / 255 + 0.055) / 1.055) ** 2.4, 1.0], rtol=1e-6)
    x = np.linspace(0.0, 1.0, 1001)
    np.testing.assert_allclose(pp.linear_to_srgb(pp.srgb_to_linear(x)), x, atol=1e-12)
    assert pp.linear_to_srgb(0.21404114048223255) == pytest.approx(0.5, abs=1e-12)


# --------------------------------------------------------------------------------------------------
# Vignetting
# --------------------------------------------------------------------------------------------------


def test_cos4_map_is_one_at_principal_point_and_symmetric() -> None:
    K = _K(fx=90.0, fy=110.0, cx=150.0, cy=20.0)  # f = 100
    vmap = pp.vignetting_cos4((41, 301), K, dtype=np.float64)
    assert vmap.shape == (41, 301)
    assert vmap[20, 150] == 1.0
    assert vmap.max() == 1.0 and vmap.min() > 0
    np.testing.assert_allclose(vmap, vmap[::-1, ::-1], rtol=1e-14)  # point symmetry about (150, 20)
    np.testing.assert_allclose(vmap[:, :150], vmap[:, 151:][:, ::-1], rtol=1e-14)  # mirror in u
    # 100 pixels = f to the right: the ray is at 45 degrees, cos^4 = 1/4.
    assert vmap[20, 250] == pytest.approx(0.25, rel=1e-12)
    # du = 3, dv = 4 -> r^2 = 25
    assert vmap[24, 153] == pytest.approx((100.0 / np.sqrt(25 + 100.0**2)) ** 4, rel=1e-12)
    assert pp.vignetting_cos4((41, 301), K).dtype == np.float32


def test_cos4_map_uses_0_based_pixel_centres() -> None:
    vmap = pp.vignetting_cos4((4, 4), _K(cx=1.5, cy=1.5), dtype=np.float64)
    # The principal point lies between pixels 1 and 2: the four central pixels are equal.
    assert vmap[1, 1] == vmap[1, 2] == vmap[2, 1] == vmap[2, 2]
    np.testing.assert_allclose(vmap, vmap.T)


def test_steps_write_into_out_in_place_with_the_same_values() -> None:
    """out= (the input itself: in place) gives the values of the default path, which are those of
    float64 arithmetic rounded to float32 (now without a float64 copy of the stack)."""
    rng = np.random.default_rng(5)
    stack = rng.random((3, 4, 5), dtype=np.float32)
    ambient = rng.random((4, 5)) * 0.5  # float64
    vmap = rng.uniform(0.3, 1.0, (4, 5)).astype(np.float32)
    cases = [
        (pp.subtract_ambient, ambient, np.maximum(stack - ambient, 0)),
        (pp.scale_exposure, [1.0, 3.0, 7.0], stack / np.array([1.0, 3.0, 7.0])[:, None, None]),
        (pp.compensate_vignetting, vmap, stack / vmap.astype(np.float64)),
    ]
    for step, arg, exact in cases:
        expected = step(stack, arg)
        assert expected.dtype == np.float32
        np.testing.assert_array_equal(expected, exact.astype(np.float32))
        work = stack.copy()
        assert step(work, arg, out=work) is work
        np.testing.assert_array_equal(work, expected)
        with pytest.raises(InputError, match="out"):
            step(stack, arg, out=np.empty(stack.shape))  # float64: not the images' dtype


def test_compensate_vignetting_broadcasts() -> None:
    vmap = np.array([[1.0, 0.5], [0.25, 0.5]])
    stack = np.ones((3, 2, 2), dtype=np.float32)
    out = pp.compensate_vignetting(stack, vmap)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out[2], [[1, 2], [4, 2]])
    colour = np.ones((3, 2, 2, 3))
    np.testing.assert_allclose(pp.compensate_vignetting(colour, vmap)[1, 1, 0], [4, 4, 4])
    cmap = np.ones((2, 2, 3))
    cmap[..., 2] = 0.5
    np.testing.assert_allclose(pp.compensate_vignetting(colour, cmap)[0, 0, 0], [1, 1, 2])
    np.testing.assert_allclose(pp.compensate_vignetting(np.ones((2, 2)), vmap), 1 / vmap)
    with pytest.raises(InputError, match="positive"):
        pp.compensate_vignetting(stack, np.zeros((2, 2)))
    with pytest.raises(InputError, match="does not match"):
        pp.compensate_vignetting(stack, np.ones((3, 2)))


def test_flat_field_map_normalizes_by_max() -> None:
    flat = np.array([[2.0, 4.0], [1.0, 8.0]])
    np.testing.assert_allclose(pp.flat_field_map(flat), flat / 8.0)
    np.testing.assert_allclose(pp.flat_field_map(flat, ambient=1.0), [[1 / 7, 3 / 7], [0, 1]])
    colour = np.stack([flat, 2 * flat, flat + 8], axis=-1)
    fmap = pp.flat_field_map(colour)
    np.testing.assert_allclose(fmap.max(axis=(0, 1)), 1.0)
    np.testing.assert_allclose(fmap[..., 1], flat / 8.0)
    stack = np.stack([flat, 3 * flat])  # (2, 2, 2) grey stack -> averaged
    np.testing.assert_allclose(pp.flat_field_map(stack), flat / 8.0)
    with pytest.raises(InputError, match="maximum"):
        pp.flat_field_map(np.zeros((3, 3)))


# --------------------------------------------------------------------------------------------------
# Binning
# --------------------------------------------------------------------------------------------------


def test_bin_images_known_array_and_remainder() -> None:
    a = np.arange(35, dtype=np.float64).reshape(5, 7)  # a[r, c] = 7 r + c
    b = pp.bin_images(a, 2)
    # Block (i, j) averages rows 2i, 2i+1 and columns 2j, 2j+1: mean = 7 (2i + 0.5) + 2j + 0.5.
    expected = np.array([[7 * (2 * i + 0.5) + 2 * j + 0.5 for j in range(3)] for i in range(2)])
    np.testing.assert_allclose(b, expected)
    assert b.shape == (2, 3)  # last row and column cropped
    np.testing.assert_allclose(b[0, 0], (0 + 1 + 7 + 8) / 4)
    np.testing.assert_allclose(pp.bin_images(a, 3), [[8.0, 11.0]])
    np.testing.assert_array_equal(pp.bin_images(a, 1), a)


def test_bin_images_stacks_and_colour() -> None:
    a = np.arange(24, dtype=np.float32).reshape(4, 6)
    stack = np.stack([a, 10 * a])  # (2, 4, 6)
    b = pp.bin_images(stack, 2)
    assert b.shape == (2, 2, 3) and b.dtype == np.float32
    np.testing.assert_allclose(b[1], 10 * pp.bin_images(a, 2))
    colour = np.stack([a, a + 1, -a], axis=-1)[None].repeat(3, axis=0)  # (3, 4, 6, 3)
    bc = pp.bin_images(colour, 2)
    assert bc.shape == (3, 2, 3, 3)
    np.testing.assert_allclose(bc[2, ..., 0], pp.bin_images(a, 2))
    np.testing.assert_allclose(bc[0, ..., 1], pp.bin_images(a, 2) + 1)
    np.testing.assert_allclose(bc[1, ..., 2], -pp.bin_images(a, 2))
    single = pp.bin_images(colour[0], 2, stack=False)  # one (H, W, 3) image
    np.testing.assert_allclose(single, bc[0])
    u8 = pp.bin_images(np.full((2, 2), 255, dtype=np.uint8), 2)
    assert u8.dtype == np.float32 and u8[0, 0] == 1.0
    with pytest.raises(InputError, match="positive integer"):
        pp.bin_images(a, 0)
    with pytest.raises(InputError, match="positive integer"):
        pp.bin_images(a, 1.5)
    with pytest.raises(InputError, match="smaller than"):
        pp.bin_images(a, 5)


def test_bin_mask_all_and_half() -> None:
    mask = np.array(
        [
            [1, 1, 1, 0, 0, 0, 1],
            [1, 1, 1, 1, 0, 0, 1],
            [0, 0, 0, 0, 0, 0, 1],
        ],
        dtype=np.uint8,
    )
    np.testing.assert_array_equal(pp.bin_mask(mask, 2), [[True, False, False]])
    np.testing.assert_array_equal(pp.bin_mask(mask, 2, rule="half"), [[True, True, False]])
    assert pp.bin_mask(mask, 2).dtype == np.bool_
    with pytest.raises(InputError, match="rule"):
        pp.bin_mask(mask, 2, rule="any")


def test_bin_intrinsics_formulas() -> None:
    K = _K(fx=1000.0, fy=1010.0, cx=319.5, cy=239.5, s=2.0)
    Kb = pp.bin_intrinsics(K, 2)
    np.testing.assert_allclose(Kb, [[500.0, 1.0, 159.5], [0.0, 505.0, 119.5], [0.0, 0.0, 1.0]], rtol=1e-15)
    # Binning by s then by t is binning by s t; factor 1/s undoes factor s.
    twice = pp.bin_intrinsics(pp.bin_intrinsics(K, 2), 3)
    np.testing.assert_allclose(twice, pp.bin_intrinsics(K, 6))
    np.testing.assert_allclose(pp.bin_intrinsics(Kb, 0.5), K, rtol=1e-15)


@pytest.mark.parametrize("factor", [2, 3, 4])
def test_bin_intrinsics_projects_to_binned_pixel_coordinates(factor: int) -> None:
    K = _K(fx=800.0, fy=780.0, cx=301.3, cy=198.7, s=0.0)
    Kb = pp.bin_intrinsics(K, factor)
    rng = np.random.default_rng(3)
    X = np.column_stack([rng.uniform(-50, 50, 20), rng.uniform(-40, 40, 20), rng.uniform(150, 300, 20)])
    uv = (K @ X.T).T
    uv = uv[:, :2] / uv[:, 2:]
    uvb = (Kb @ X.T).T
    uvb = uvb[:, :2] / uvb[:, 2:]
    np.testing.assert_allclose(uvb, (uv + 0.5) / factor - 0.5, rtol=0, atol=1e-9)


def test_bin_intrinsics_matches_binned_image_of_a_spot() -> None:
    # Render a smooth spot centred on the projection of a 3-D point at full resolution, bin the
    # image and compare the centroid of the binned image with the projection through binned K.
    factor = 3
    K = _K(fx=500.0, fy=480.0, cx=64.2, cy=47.9)
    X = np.array([3.0, -2.0, 100.0])
    u, v = (K @ X)[:2] / X[2]
    rows, cols = np.mgrid[0:96, 0:129].astype(np.float64)  # pixel centres (u, v) = (c, r)
    spot = np.exp(-((cols - u) ** 2 + (rows - v) ** 2) / (2 * 6.0**2))
    binned = pp.bin_images(spot, factor)
    rb, cb = np.mgrid[0 : binned.shape[0], 0 : binned.shape[1]]
    cu = (binned * cb).sum() / binned.sum()
    cv = (binned * rb).sum() / binned.sum()
    Kb = pp.bin_intrinsics(K, factor)
    ub, vb = (Kb @ X)[:2] / X[2]
    assert cu == pytest.approx(ub, abs=1e-4) and cv == pytest.approx(vb, abs=1e-4)
    # The naive guesses are off by a third of a binned pixel.
    assert abs(cu - u / factor) > 0.3 and abs(cv - v / factor) > 0.3


# --------------------------------------------------------------------------------------------------
# Padding and cropping
# --------------------------------------------------------------------------------------------------


def test_pad_or_crop_bottom_right() -> None:
    a = np.arange(6, dtype=np.float32).reshape(2, 3)
    padded = pp.pad_or_crop(a, (3, 5))
    np.testing.assert_array_equal(padded, [[0, 1, 2, 0, 0], [3, 4, 5, 0, 0], [0, 0, 0, 0, 0]])
    assert padded.dtype == np.float32
    np.testing.assert_array_equal(pp.pad_or_crop(a, (1, 2)), [[0, 1]])
    np.testing.assert_array_equal(pp.pad_or_crop(a, (3, 2), mode="edge"), [[0, 1], [3, 4], [3, 4]])
    filled = pp.pad_or_crop(a, (2, 4), value=-1)
    np.testing.assert_array_equal(filled, [[0, 1, 2, -1], [3, 4, 5, -1]])
    mask = pp.pad_or_crop(np.ones((2, 2), dtype=bool), (3, 3))
    assert mask.dtype == np.bool_ and mask.sum() == 4


def test_pad_or_crop_stacks_colour_and_offset() -> None:
    stack = np.ones((4, 2, 3, 3))
    assert pp.pad_or_crop(stack, (5, 1)).shape == (4, 5, 1, 3)
    assert pp.pad_or_crop(np.ones((2, 3, 3)), (4, 4)).shape == (2, 4, 4)  # a (k, H, W) stack
    assert pp.pad_or_crop(np.ones((2, 3, 3)), (4, 4), stack=False).shape == (4, 4, 3)
    a = np.arange(6).reshape(2, 3)
    shifted = pp.pad_or_crop(a, (4, 4), offset=(1, 2))
    np.testing.assert_array_equal(shifted[1:3, 2:], [[0, 1], [3, 4]])
    assert shifted.sum() == 0 + 1 + 3 + 4
    np.testing.assert_array_equal(pp.pad_or_crop(a, (2, 2), offset=(-1, -1)), [[4, 5], [0, 0]])
    with pytest.raises(InputError, match="out of"):
        pp.pad_or_crop(a, (2, 2), offset=(5, 0))
