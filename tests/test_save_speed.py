"""The save path's shortcuts give numpy's own figures bit for bit (issue 23, stop 44)."""

import numpy as np
import pytest

from nplps import _core


def _samples(rng: np.random.Generator, n: int, kind: int, dtype: type) -> np.ndarray:
    if kind == 0:
        return (rng.random(n) * rng.uniform(0.1, 100.0)).astype(dtype)
    if kind == 1:  # many ties: the ranks land inside runs of equal values
        return (rng.integers(0, 5, n) * 0.3).astype(dtype)
    return (rng.standard_exponential(n) ** 3).astype(dtype)  # heavy tail, as the held-out errors


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_trust_figures_are_numpys_bit_for_bit(seed: int, dtype: type) -> None:
    # The Rust figures (radix selection, pairwise sums) against numpy's median, percentile and
    # mean of the float64 values, over sizes around numpy's pairwise block (128) and its halving.
    rng = np.random.default_rng(seed)
    sizes = [*range(1, 140), 255, 256, 257, 1000, 4097, 65_537, int(rng.integers(100_000, 300_000))]
    for n in sizes:
        for kind in range(3):
            sigma = _samples(rng, n, kind, dtype)[None, :]
            held = _samples(rng, n, (kind + 1) % 3, dtype)[None, :]
            s, h = sigma.astype(np.float64), held.astype(np.float64)
            expected = (
                n,
                float(np.median(s)),
                float(np.percentile(s, 90)),
                float(np.sqrt(np.mean(s**2))),
                float(np.mean(h)),
                float(np.median(h)),
                float(np.percentile(h, 90)),
            )
            got = _core.trust_figures(np.ones((1, n), bool), sigma, held)
            assert got == expected, (n, kind, got, expected)


def _old_trust_figures(sigma_map: np.ndarray, held_map: np.ndarray, mask: np.ndarray) -> dict:
    """summary.json's trust figures as main computed them (float64 copies, numpy's median/percentile)."""
    inside = mask & np.isfinite(sigma_map) & np.isfinite(held_map)
    sigma = sigma_map[inside].astype(np.float64)
    held = held_map[inside].astype(np.float64)
    return {
        "pixels": int(sigma.size),
        "normal_sigma_deg": {
            "median": float(np.median(sigma)),
            "p90": float(np.percentile(sigma, 90)),
            "rms": float(np.sqrt(np.mean(sigma**2))),
        },
        "held_out_error": {
            "mean": float(np.mean(held)),
            "median": float(np.median(held)),
            "p90": float(np.percentile(held, 90)),
        },
    }


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("dtypes", [(np.float32, np.float32), (np.float64, np.float64), (np.float32, np.float64)])
def test_trust_summary_is_mains_bit_for_bit(seed: int, dtypes: tuple[type, type]) -> None:
    from types import SimpleNamespace

    from nplps.reconstruction import Reconstruction

    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(50, 700)), int(rng.integers(50, 700))
    sigma = (rng.standard_exponential((h, w)) * rng.uniform(0.01, 5)).astype(dtypes[0])
    held = (rng.standard_exponential((h, w)) ** 2 * 1e-3).astype(dtypes[1])
    sigma[rng.random((h, w)) < 0.05] = np.nan  # left out, as the maps' unknown pixels
    held[rng.random((h, w)) < 0.05] = np.inf
    mask = rng.random((h, w)) < 0.8
    fake = SimpleNamespace(normal_sigma=sigma, held_out_error=held, mask=mask, light_trust=None)
    got = Reconstruction._trust_summary(fake)  # type: ignore[arg-type]
    assert got is not None
    assert got.pop("lights") == []
    assert got == _old_trust_figures(sigma, held, mask)
    fake.mask = np.zeros_like(mask)
    assert Reconstruction._trust_summary(fake) == {  # type: ignore[arg-type]
        "pixels": 0,
        "normal_sigma_deg": None,
        "held_out_error": None,
        "lights": [],
    }


@pytest.mark.parametrize("camera", ["orthographic", "pinhole"])
def test_masked_mesh_normals_are_mains_bit_for_bit(camera: str) -> None:
    # The mask given to the Rust function against main's way: the normals of the whole depth map,
    # then NaN written outside the mask (the Rust unit test compares the banded normals with the
    # quads of the whole vertex grid, main's algorithm, bit for bit).
    import nplps

    scene = nplps.make_scene("sphere", n=37, camera=camera)  # type: ignore[arg-type]
    rng = np.random.default_rng(3)
    depth = scene.depth + rng.normal(0, 0.01, scene.depth.shape)
    depth[rng.random(depth.shape) < 0.03] = np.nan
    mask = rng.random((depth.shape[0] - 1, depth.shape[1] - 1)) < 0.7
    expected = _core.mesh_normals(depth, scene.rig.camera)
    expected[~mask] = np.nan
    got = _core.mesh_normals(depth, scene.rig.camera, mask)
    assert np.array_equal(got.view(np.uint64), expected.view(np.uint64))


def _old_shaded(result, light) -> np.ndarray:  # type: ignore[no-untyped-def]
    """``Reconstruction.shaded`` as main computed it: the (H, W, 3) product summed over its last axis."""
    n = result.normals
    if isinstance(light, str) and not result.rig.is_pinhole:
        to_light = np.array([0.0, 0.0, -1.0])
    elif isinstance(light, str):
        v = result.vertices
        centre = 0.25 * (v[:-1, :-1] + v[:-1, 1:] + v[1:, :-1] + v[1:, 1:])
        to_light = -centre / np.linalg.norm(centre, axis=-1, keepdims=True)
    else:
        d = np.asarray(light, dtype=np.float64)
        to_light = d / np.linalg.norm(d)
    shade = np.clip((n * to_light).sum(axis=-1), 0.0, 1.0)
    return np.where(result.mask & np.isfinite(shade), shade, 0.0)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("camera", ["orthographic", "pinhole"])
def test_shaded_is_the_summed_product_bit_for_bit(seed: int, camera: str) -> None:
    import nplps
    from nplps.reconstruction import SHADED_LIGHT

    scene = nplps.make_scene("sphere", n=24, camera=camera)  # type: ignore[arg-type]
    result = nplps.reconstruct(scene.images, scene.rig, depth=scene.mean_depth, mask=scene.mask, iterations=2)
    assert result.rig.is_pinhole == (camera == "pinhole")  # "camera": per-pixel directions or one
    rng = np.random.default_rng(seed)
    # Random normals of every sign and scale, with NaN, infinities, zeros and negative zeros.
    n = rng.standard_normal(result.normals.shape) * rng.choice([1e-3, 1.0, 1e3], result.normals.shape)
    special = rng.random(n.shape)
    n[special < 0.02] = np.nan
    n[(special >= 0.02) & (special < 0.03)] = np.inf
    n[(special >= 0.03) & (special < 0.05)] = 0.0
    n[(special >= 0.05) & (special < 0.07)] = -0.0
    result.__dict__["normals"] = n  # the cached property's value
    lights = [SHADED_LIGHT, "camera", tuple(rng.standard_normal(3))]
    for light in lights:
        got = result.shaded(None if light is SHADED_LIGHT else light)
        expected = _old_shaded(result, light)
        assert got.dtype == expected.dtype and got.shape == expected.shape
        assert np.array_equal(got.view(np.uint64), expected.view(np.uint64)), light


def _old_grey_pixels(image: np.ndarray) -> np.ndarray:
    """``export._grey_pixels`` as main computed it (numpy, float64 copy)."""
    image = np.array(image, dtype=np.float64)
    np.nan_to_num(image, copy=False, nan=0.0)
    np.clip(image, 0.0, 1.0, out=image)
    image *= 255
    np.rint(image, out=image)
    return image.astype(np.uint8)


def _old_normal_map_pixels(normals: np.ndarray, mask: np.ndarray | None, frame: str, bits: int) -> np.ndarray:
    """``export.normal_map_pixels`` as main computed it (numpy, whole image at once)."""
    from nplps.export import NORMAL_MAP_FRAMES

    top = (1 << bits) - 1
    flip = np.array(NORMAL_MAP_FRAMES[frame])
    n = np.asarray(normals, dtype=np.float64)
    valid = np.isfinite(n).all(axis=-1)
    if mask is not None:
        valid &= mask
    flipped = np.clip(np.where(valid[..., None], n, 0.0) * flip, -1.0, 1.0)
    encoded = np.rint((flipped + 1.0) / 2.0 * top).astype(np.uint8 if bits == 8 else np.uint16)
    encoded[~valid] = 0
    return encoded


def _special(rng: np.random.Generator, shape: tuple[int, ...], scale: float) -> np.ndarray:
    """Random values of both signs around [-scale, scale] with NaN, infinities, zeros, exact halves."""
    v = rng.uniform(-scale, scale, shape)
    u = rng.random(shape)
    v[u < 0.02] = np.nan
    v[(u >= 0.02) & (u < 0.03)] = np.inf
    v[(u >= 0.03) & (u < 0.04)] = -np.inf
    v[(u >= 0.04) & (u < 0.05)] = -0.0
    halves = (u >= 0.05) & (u < 0.1)  # k / 510: x 255 lands on halves (rounding to even)
    v[halves] = rng.integers(0, 511, int(halves.sum())) / 510.0
    return v


@pytest.mark.parametrize("seed", range(4))
def test_png_pixels_are_mains_bit_for_bit(seed: int) -> None:
    from nplps.export import NORMAL_MAP_FRAMES, _grey_pixels, normal_map_pixels

    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(1, 300)), int(rng.integers(1, 300))
    image = _special(rng, (h, w), 1.5)
    assert np.array_equal(_grey_pixels(image), _old_grey_pixels(image))
    normals = rng.standard_normal((h, w, 3))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    normals[rng.random((h, w)) < 0.2] *= 1.5  # beyond [-1, 1]: clipped
    normals[rng.random((h, w, 3)) < 0.03] = np.nan
    mask = rng.random((h, w)) < 0.8
    for frame in NORMAL_MAP_FRAMES:
        for bits in (8, 16):
            for m in (mask, None):
                got = normal_map_pixels(normals, mask=m, frame=frame, bits=bits)
                expected = _old_normal_map_pixels(normals, m, frame, bits)
                assert got.dtype == expected.dtype and np.array_equal(got, expected), (frame, bits)
    # float32 normals are widened as before
    n32 = normals.astype(np.float32)
    assert np.array_equal(normal_map_pixels(n32, mask=mask, bits=16), _old_normal_map_pixels(n32, mask, "opengl", 16))
