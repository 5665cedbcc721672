"""The display shrinks a band of block rows at a time: the same bits as the whole-array code.

``views.downsample`` and ``views._block_mean`` (the report's maps, the contact sheet, the oblique
renders' mask cover) used to convert the whole image to float64 and reduce it at once (25 bytes
a value of temporaries: 7.5 GB for a 100 MP normal map). They now take bands of block rows
(``views.BAND_VALUES``); these tests hold them to the old code, kept here, bit for bit, with the
band size made small so that many bands and the ragged last one are exercised.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from nplps import export, views


def old_downsample(image: np.ndarray, max_side: int) -> np.ndarray:
    """``views.downsample`` before the bands (the whole image at once)."""
    h, w = image.shape[:2]
    s = math.ceil(max(h, w) / max_side)
    if s <= 1:
        return image
    hh, ww = h // s * s, w // s * s
    a = np.asarray(image[:hh, :ww], dtype=np.float64)
    blocks = a.reshape(hh // s, s, ww // s, s, *a.shape[2:])
    finite = np.isfinite(blocks)
    total = np.where(finite, blocks, 0.0).sum(axis=(1, 3))
    count = finite.sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def old_block_mean(values: np.ndarray, s: int, hh: int, ww: int) -> np.ndarray:
    """``views._block_mean`` before the bands (the whole array padded at once)."""
    h, w = values.shape[:2]
    padded = np.full((hh * s, ww * s, *values.shape[2:]), np.nan)
    ch, cw = min(h, hh * s), min(w, ww * s)
    padded[:ch, :cw] = values[:ch, :cw]
    blocks = padded.reshape(hh, s, ww, s, *values.shape[2:])
    finite = np.isfinite(blocks)
    total = np.where(finite, blocks, 0.0).sum(axis=(1, 3))
    count = finite.sum(axis=(1, 3))
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def old_contact_sheet_small(stack: np.ndarray, side: int) -> list[np.ndarray]:
    """The contact sheet's shrunk copies before: each image made float32 first."""
    return [old_downsample(np.asarray(im, dtype=np.float32), side) for im in stack]


def random_image(rng: np.random.Generator, trial: int) -> np.ndarray:
    h, w = (int(v) for v in rng.integers(1, 400, 2))
    channels = [(), (3,), (1,), (4,)][trial % 4]
    kind = trial % 5
    if kind == 0:
        return rng.integers(0, 65536, (h, w, *channels)).astype(np.uint16)
    if kind == 1:
        return rng.integers(0, 256, (h, w, *channels)).astype(np.uint8)
    x = rng.standard_normal((h, w, *channels)) * 10.0 ** rng.uniform(-6, 6)
    if kind == 2:
        x[rng.random(x.shape) < 0.2] = np.nan
        x[rng.random(x.shape) < 0.01] = np.inf
    if kind == 3:
        x = x.astype(np.float32)
    return x


@pytest.mark.parametrize("band", [1, 7, 1000, views.BAND_VALUES])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_downsample_in_bands_is_the_whole_arrays_bit_for_bit(monkeypatch, band, seed):
    monkeypatch.setattr(views, "BAND_VALUES", band)
    rng = np.random.default_rng(seed)
    for trial in range(60):
        x = random_image(rng, trial)
        side = int(rng.integers(1, 150))
        new, old = views.downsample(x, side), old_downsample(x, side)
        assert new.dtype == old.dtype and new.shape == old.shape
        assert np.array_equal(new, old, equal_nan=True), (x.shape, x.dtype, side)
        if new is not x:  # shrunk: the bits, NaN and -0 included
            assert np.array_equal(new.view(np.uint64), old.view(np.uint64))
        c = float(rng.uniform(0.1, 300.0))
        scaled, reference = (
            views.downsample(x, side, scale=c),
            old_downsample(np.asarray(x, dtype=np.float64) * c, side),
        )
        assert scaled.dtype == np.float64 and scaled.shape == reference.shape
        assert np.array_equal(scaled.view(np.uint64), np.asarray(reference, dtype=np.float64).view(np.uint64))


def test_a_band_is_a_multiple_of_whole_blocks_and_the_last_is_ragged(monkeypatch):
    # 10 block rows of 3 x 3 pixels; bands of 4 block rows: 4 + 4 + 2.
    monkeypatch.setattr(views, "BAND_VALUES", 4 * 3 * 30)
    x = np.arange(31 * 30, dtype=np.float64).reshape(31, 30)
    out = views.downsample(x, 11)  # s = ceil(31 / 11) = 3
    assert out.shape == (10, 10)
    assert out[0, 0] == x[:3, :3].mean() and out[9, 9] == x[27:30, 27:30].mean()


@pytest.mark.parametrize("band", [1, 50, views.BAND_VALUES])
@pytest.mark.parametrize("seed", [0, 1])
def test_block_mean_in_bands_is_the_whole_arrays_bit_for_bit(monkeypatch, band, seed):
    monkeypatch.setattr(views, "BAND_VALUES", band)
    rng = np.random.default_rng(seed)
    for trial in range(60):
        h, w = (int(v) for v in rng.integers(2, 300, 2))
        s = int(rng.integers(1, 12))
        hh = max(1, math.ceil((h + 1) / s) - int(rng.integers(0, 2)))  # as render_mesh: past the edge or short of it
        ww = max(1, math.ceil((w + 1) / s) - int(rng.integers(0, 2)))
        if trial % 3 == 0:
            values = rng.random((h, w)) < 0.6  # the mask, as render_mesh passes it
            reference = old_block_mean(values.astype(np.float64), s, hh, ww)
        else:
            values = rng.standard_normal((h, w, *[(), (3,)][trial % 2])) * 10.0 ** rng.uniform(-4, 4)
            values[rng.random(values.shape) < 0.1] = np.nan
            reference = old_block_mean(values, s, hh, ww)
        new = views._block_mean(values, s, hh, ww)
        assert new.shape == reference.shape
        assert np.array_equal(new.view(np.uint64), reference.view(np.uint64)), (h, w, s, hh, ww)


@pytest.mark.parametrize("dtype", [np.uint16, np.uint8, np.int16, np.bool_, np.float32, np.float64])
def test_contact_sheet_is_the_same_without_the_float32_copies(monkeypatch, dtype):
    monkeypatch.setattr(views, "BAND_VALUES", 5000)
    rng = np.random.default_rng(3)
    for shape in [(5, 300, 451), (3, 90, 60), (16, 257, 129), (4, 100, 140, 3)]:
        if dtype == np.bool_:
            stack = rng.random(shape) < 0.5
        elif np.issubdtype(dtype, np.integer):
            info = np.iinfo(dtype)
            stack = rng.integers(info.min, int(info.max) + 1, shape).astype(dtype)
        else:
            stack = (rng.random(shape) * 3.0).astype(dtype)
            stack[rng.random(shape) < 0.05] = np.nan
        side = 128 if shape[0] <= 16 else 72
        new = [views.downsample(s, side) for s in _contact_inputs(stack)]
        old = old_contact_sheet_small(stack, side)
        for a, b in zip(new, old, strict=True):
            assert np.array_equal(np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64), equal_nan=True)
        # ... and so the sheet itself: the old sheet from the old copies.
        sheet = export.contact_sheet(stack)
        with monkeypatch.context() as m:
            m.setattr(views, "downsample", lambda im, n: old_downsample(np.asarray(im, dtype=np.float32), n))
            assert np.array_equal(sheet, export.contact_sheet(stack))


def _contact_inputs(stack: np.ndarray) -> list[np.ndarray]:
    """What ``contact_sheet`` now hands ``downsample``: the images as they are when float32 holds them."""
    exact = stack.dtype == np.float32 or (stack.dtype.kind in "biu" and stack.dtype.itemsize <= 2)
    return [im if exact else np.asarray(im, dtype=np.float32) for im in stack]


def test_render_mesh_is_the_same_with_the_banded_cover(monkeypatch):
    import nplps

    scene = nplps.make_scene("bumps", n=96)
    result = nplps.reconstruct(scene.images, scene.rig, mask=scene.mask, depth=scene.mean_depth)
    vertices = result.vertices
    monkeypatch.setattr(views, "BAND_VALUES", 300)
    for max_facets in (400, 2000, 250_000):
        new = views.render_mesh(vertices, result.mask, azimuth=30, elevation=20, size=96, max_facets=max_facets)
        with monkeypatch.context() as m:
            m.setattr(views, "_block_mean", old_block_mean)
            old = views.render_mesh(vertices, result.mask, azimuth=30, elevation=20, size=96, max_facets=max_facets)
        assert np.array_equal(new, old)
