"""16-bit stacks read in place (issue 23): ``uint16`` input gives exactly the float32 stack's result.

``nplps.reconstruct`` keeps a ``uint16`` stack (an array, or 16-bit PNG files) as it is and the
local step reads each value as ``float32(v) / 65535``, the value ``nplps.io.load_stack`` puts in
a float32 stack; so every output must be bit for bit the one of that float32 stack with the
16-bit thresholds.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import nplps
from nplps import export
from nplps.io import load_stack

LEVELS = 65535
DARK = 1.0 / LEVELS
SATURATION = 1.0 - 0.5 / LEVELS


@pytest.fixture(scope="module")
def scene() -> nplps.Scene:
    return nplps.make_scene("sphere", n=48)


def _u16(images: np.ndarray, noise: float = 0.0) -> np.ndarray:
    scaled = images / images.max() * LEVELS
    if noise:
        scaled = scaled + np.random.default_rng(1).normal(0.0, noise * LEVELS, scaled.shape)
    return np.rint(np.clip(scaled, 0, LEVELS)).astype(np.uint16)


def _f32(stack: np.ndarray) -> np.ndarray:
    return stack.astype(np.float32) / np.float32(LEVELS)


def _same(a: nplps.Reconstruction, b: nplps.Reconstruction) -> None:
    for name in ("depth", "normals", "albedo", "residual", "lights_used"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.status == b.status
    assert len(a.history) == len(b.history)


def test_load_stack_keeps_uint16_when_asked(tmp_path: Path) -> None:
    stack = _u16(np.random.default_rng(0).random((3, 5, 7)) + 0.1)
    kept, levels = load_stack(stack, uint16=True)
    assert kept.dtype == np.uint16 and levels == LEVELS and np.shares_memory(kept, stack)
    converted, levels = load_stack(stack)
    assert converted.dtype == np.float32 and levels == LEVELS
    np.testing.assert_array_equal(converted, _f32(stack))
    paths = [tmp_path / f"i{i}.png" for i in range(3)]
    for path, image in zip(paths, stack, strict=True):
        export.write_png16(path, image)
    from_files, levels = load_stack(paths, uint16=True)
    assert from_files.dtype == np.uint16 and levels == LEVELS
    np.testing.assert_array_equal(from_files, stack)
    # An 8-bit image among them: the whole stack becomes float32, with the same values as without uint16.
    mixed = [*paths[:2], (stack[2] >> 8).astype(np.uint8)]
    a, levels_a = load_stack(mixed, uint16=True)
    b, levels_b = load_stack(mixed)
    assert a.dtype == np.float32 and levels_a == levels_b
    np.testing.assert_array_equal(a, b)
    # Colour averaged to grey: float32 as before.
    rgb = np.repeat(stack[..., None], 3, axis=3)
    grey, _ = load_stack(rgb, color=False, uint16=True)
    assert grey.dtype == np.float32


@pytest.mark.parametrize("shadows", [True, False])
def test_uint16_reconstructs_like_the_float32_stack(scene: nplps.Scene, shadows: bool) -> None:
    stack = _u16(scene.images, noise=0.002)
    options = dict(depth=scene.mean_depth, mask=scene.mask, shadows=shadows, check_distance=False)
    a = nplps.reconstruct(stack, scene.rig, **options)  # default thresholds and noise estimate: 16-bit
    sigma = nplps._core.estimate_noise(_f32(stack), scene.mask)
    assert nplps._core.estimate_noise(stack, scene.mask) == sigma
    dark = max(DARK, 3.0 * sigma)
    b = nplps.reconstruct(_f32(stack), scene.rig, dark=dark, saturation=SATURATION, **options)
    _same(a, b)


def test_uint16_colour_and_valid_flags(scene: nplps.Scene) -> None:
    grey = _u16(scene.images)
    rgb = np.ascontiguousarray(np.stack([grey, grey // 2, grey // 3], axis=3))
    options = dict(depth=scene.mean_depth, mask=scene.mask, dark=DARK, saturation=SATURATION, check_distance=False)
    _same(
        nplps.reconstruct(rgb, scene.rig, color=True, **options),
        nplps.reconstruct(_f32(rgb), scene.rig, color=True, **options),
    )
    _same(
        nplps.reconstruct(rgb, scene.rig, color=False, **options),
        nplps.reconstruct(_f32(rgb), scene.rig, color=False, **options),
    )
    valid = np.ones(grey.shape, dtype=bool)
    valid[0, ::3] = False
    _same(
        nplps.reconstruct(grey, scene.rig, valid=valid, **options),
        nplps.reconstruct(_f32(grey), scene.rig, valid=valid, **options),
    )
    # The caller's array is never written (valid makes a float32 copy).
    assert grey.dtype == np.uint16 and np.array_equal(grey, _u16(scene.images))


def test_uint16_with_a_pyramid_and_the_direct_solver(scene: nplps.Scene) -> None:
    stack = _u16(scene.images)
    options = dict(depth=scene.mean_depth, mask=scene.mask, dark=DARK, saturation=SATURATION, check_distance=False)
    for extra in ({"levels": 3}, {"solver": "direct"}):
        _same(
            nplps.reconstruct(stack, scene.rig, **options, **extra),
            nplps.reconstruct(_f32(stack), scene.rig, **options, **extra),
        )


def test_the_command_line_pipeline_keeps_16_bit_files(scene: nplps.Scene, tmp_path: Path) -> None:
    """``pipeline.prepare(uint16=True)`` (the CLI's) hands the 16-bit files over as they are, without
    saturation flags, and the result is the float32 stack's with its flags (saturated pixels included)."""
    from nplps import pipeline

    stack = _u16(scene.images * 1.3)  # some values clip at 65535: saturated
    assert (stack == LEVELS).any()
    paths = [tmp_path / f"i{i:02d}.png" for i in range(len(stack))]
    for path, image in zip(paths, stack, strict=True):
        export.write_png16(path, image)
    kept = pipeline.prepare(paths, rig=scene.rig, mask=scene.mask, uint16=True)
    assert kept.images.dtype == np.uint16 and kept.valid is None
    floats = pipeline.prepare(paths, rig=scene.rig, mask=scene.mask)
    assert floats.images.dtype == np.float32 and floats.valid is not None
    assert kept.dark == floats.dark and kept.levels == floats.levels == LEVELS
    options = dict(depth=scene.mean_depth, mask=scene.mask, check_distance=False)
    a = nplps.reconstruct(kept.images, scene.rig, dark=kept.dark, valid=kept.valid, **options)
    b = nplps.reconstruct(floats.images, scene.rig, dark=floats.dark, valid=floats.valid, **options)
    _same(a, b)
    # A correction needs float32: then the stack is float32 as before.
    binned = pipeline.prepare(paths, rig=scene.rig, mask=scene.mask, bin_factor=2, uint16=True)
    assert binned.images.dtype == np.float32
