"""The noise estimate and the default shadow threshold derived from it (issue 20)."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

import nplps
from nplps import _core
from nplps.errors import InputError

SEEDS = range(4)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("name", ["sphere", "bumps", "block", "cube", "saddle"])
@pytest.mark.parametrize("noise", [0.002, 0.005, 0.02])
def test_estimate_within_20_percent(name: str, noise: float, seed: int) -> None:
    camera = "pinhole" if seed % 2 else "orthographic"
    clean = nplps.make_scene(name, n=64, camera=camera, seed=seed, shadows=name == "block")
    scene = nplps.make_scene(name, n=64, camera=camera, seed=seed, noise=noise, shadows=name == "block")
    sigma = nplps.estimate_noise(scene.images, scene.mask)
    assert abs(sigma / (noise * clean.images.max()) - 1) < 0.2


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("name", ["sphere", "bumps", "block", "cube", "saddle"])
def test_noise_free_is_exactly_zero(name: str, seed: int) -> None:
    for camera in ("orthographic", "pinhole"):
        scene = nplps.make_scene(name, n=48, camera=camera, seed=seed, shadows=name == "block")
        assert nplps.estimate_noise(scene.images, scene.mask) == 0.0
        assert nplps.estimate_noise(scene.images) == 0.0


def test_core_matches_python_and_takes_rgb_and_nan() -> None:
    scene = nplps.make_scene("sphere", n=48, noise=0.01, seed=2, rgb=True)
    stack = np.ascontiguousarray(scene.images, dtype=np.float32)
    assert stack.ndim == 4
    sigma = _core.estimate_noise(stack, np.ascontiguousarray(scene.mask))
    assert sigma == nplps.estimate_noise(scene.images, scene.mask)
    holes = stack.copy()
    holes.reshape(-1)[::13] = np.nan
    assert abs(_core.estimate_noise(holes, scene.mask) / sigma - 1) < 0.15


def test_integer_images_are_scaled() -> None:
    scene = nplps.make_scene("sphere", n=64, noise=0.01, seed=3)
    eight = np.round(np.clip(scene.images / scene.images.max(), 0, 1) * 255).astype(np.uint8)
    sigma = nplps.estimate_noise(eight, scene.mask)
    assert abs(sigma / 0.01 - 1) < 0.2


def test_bad_input() -> None:
    with pytest.raises(InputError):
        _core.estimate_noise(np.zeros((2, 8), np.float32))
    with pytest.raises(InputError, match="mask"):
        _core.estimate_noise(np.zeros((2, 8, 8), np.float32), np.ones((4, 4), bool))
    with pytest.raises(InputError):
        nplps.estimate_noise(np.zeros((2, 8, 8), np.float32), np.ones((4, 4), bool))
    assert nplps.estimate_noise(np.zeros((2, 2, 2), np.float32)) == 0.0


def _run(scene: nplps.Scene, **kw: object) -> nplps.Reconstruction:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return nplps.reconstruct(scene.images, scene.rig, depth=scene.mean_depth, mask=scene.mask, progress=False, **kw)


@pytest.mark.parametrize("seed", range(2))
def test_default_dark_is_three_sigma_and_reported(seed: int, tmp_path: object) -> None:
    scene = nplps.make_scene("block", n=48, camera="pinhole", noise=0.005, seed=seed, shadows=True)
    result = _run(scene)
    sigma = nplps.estimate_noise(scene.images, scene.mask)
    assert result.noise == pytest.approx(sigma)
    assert result.dark == pytest.approx(3 * sigma)
    assert result.summary()["dark"] == pytest.approx(3 * sigma)
    assert result.summary()["noise"] == pytest.approx(sigma)
    explicit = _run(scene, dark=0.0)
    assert explicit.dark == 0.0 and explicit.noise is None
    # The cast shadows' noise is left out: the default does better than dark=0.
    m = scene.mask

    def err(r: nplps.Reconstruction) -> float:
        cos = np.clip(np.sum(r.normals[m] * scene.normals[m], axis=-1), -1, 1)
        return float(np.degrees(np.arccos(cos)).mean())

    assert err(result) < err(explicit)
    paths = result.save(tmp_path / "out")  # type: ignore[operator]
    saved = json.loads(paths["summary"].read_text())
    assert saved["dark"] == pytest.approx(3 * sigma)


@pytest.mark.parametrize("name", ["sphere", "block"])
def test_noise_free_results_are_unchanged(name: str) -> None:
    scene = nplps.make_scene(name, n=32, shadows=name == "block")
    default, zero = _run(scene), _run(scene, dark=0.0)
    assert default.dark == 0.0 and default.noise == 0.0
    assert np.array_equal(default.depth, zero.depth, equal_nan=True)
    assert np.array_equal(default.normals, zero.normals, equal_nan=True)


def test_integer_default_is_at_least_one_level() -> None:
    scene = nplps.make_scene("sphere", n=32, seed=1)
    eight = np.round(np.clip(scene.images / scene.images.max(), 0, 1) * 255).astype(np.uint8)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = nplps.reconstruct(eight, scene.rig, depth=scene.mean_depth, mask=scene.mask, progress=False)
    assert result.dark is not None and result.dark >= 1 / 255
    noisy = nplps.make_scene("sphere", n=32, seed=1, noise=0.02)
    eight = np.round(np.clip(noisy.images / noisy.images.max(), 0, 1) * 255).astype(np.uint8)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = nplps.reconstruct(eight, scene.rig, depth=scene.mean_depth, mask=scene.mask, progress=False)
    assert result.noise is not None and result.dark == pytest.approx(max(1 / 255, 3 * result.noise))
    assert result.dark > 1 / 255


def test_parallel_baseline_uses_the_same_default() -> None:
    scene = nplps.make_scene("sphere", n=32, noise=0.01, seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        base = nplps.reconstruct_parallel(scene.images, scene.rig, depth=scene.mean_depth, mask=scene.mask)
    assert base.noise == pytest.approx(nplps.estimate_noise(scene.images, scene.mask))
    assert base.dark == pytest.approx(3 * base.noise)
