"""The glossy model's highlight must be shown where a light falls within its lobe.

With few lights the held-out check (``Reconstruction.lobe_check``, rust/nplps/src/local/check.rs)
cannot judge a lobe whose peak none of the lights samples: the glossy fits then use the lobe's far
tail as a free correction, predict the lights they did not see about as well as the Lambertian
model, and predict a light that falls into the lobe many times too bright. The check therefore also
asks the fits that see the lobe (a light within its half maximum) to confirm the highlight: their
median specular albedo against that of all the fits (``LobeCheck.highlight``).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import nplps
from nplps import captures
from nplps.evaluation import held_out

#: The LED whose mirror direction falls on the synthetic sheet (tilted towards it).
UNLIKE = 0


def sheet(
    seed: int, *, n: int = 48, tilt: float = 18.0, moved: float = 6.0
) -> tuple[np.ndarray, nplps.Rig, np.ndarray]:
    """A matte (Lambertian) sheet 200 mm away under 8 LEDs on a ring in hehe12's arrangement.

    The sheet is tilted by `tilt` degrees towards LED 0, so that LED 0's mirror direction falls on
    it and no other LED's comes within about 7 degrees of its half vectors (a narrow view, 8 n
    pixels focal length). The images are rendered with the LEDs `moved` mm (standard deviation,
    per coordinate, seeded) off the positions of the rig returned: a rig calibrated to a few mm.
    Returns the images, the rig and the mask.
    """
    f = 8.0 * n
    camera = {"model": "pinhole", "K": [[f, 0, n / 2], [0, f, n / 2], [0, 0, 1]]}
    ys, xs = np.mgrid[0 : n + 1, 0 : n + 1].astype(float)
    u, v = (xs - n / 2) / f, (ys - n / 2) / f
    t = np.linspace(0, 2 * np.pi, 8, endpoint=False) + 0.3
    positions = np.stack([85 * np.cos(t), 85 * np.sin(t), np.full(8, 75.0)], 1)
    g = np.tan(np.radians(tilt))
    depth = 200.0 / (1 - g * np.cos(t[UNLIKE]) * u - g * np.sin(t[UNLIKE]) * v)
    rng = np.random.default_rng(seed)
    albedo = 0.5 + 0.1 * rng.random((n, n))
    mask = np.ones((n, n), bool)
    true_rig = nplps.Rig.from_arrays(camera, positions + moved * rng.standard_normal((8, 3)))
    images = nplps.render(depth, true_rig, albedo, mask=mask).astype(np.float32)
    return images, nplps.Rig.from_arrays(camera, positions), mask


def shape_error(result: nplps.Reconstruction, rig: nplps.Rig, images: np.ndarray, light: int) -> float:
    """The held-out shape error of `light` (as ``nplps evaluate``: after the best gain)."""
    p = result.predict(rig, lights=[light])[0]
    q = images[light]
    s = result.mask & np.isfinite(p) & (q > 0)
    p, q = p[s], q[s]
    return float(np.linalg.norm(p @ q / (p @ p) * p - q) / np.linalg.norm(q))


def solve(images: np.ndarray, rig: nplps.Rig, **options: object) -> nplps.Reconstruction:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return nplps.reconstruct(images, rig, **options)


def test_a_light_unlike_the_others_is_predicted_no_worse_than_by_the_lambertian_model() -> None:
    # Measured (8 seeds, LED 0 left out): before the highlight was asked for, seeds 0 and 3 kept
    # the glossy model (roughness 0.031, no fit seeing the lobe) and predicted LED 0 with shape
    # errors 0.12 and 0.67 against 0.0028 and 0.010 Lambertian; the other six dropped it by the
    # held-out error alone. Now every seed falls back to the Lambertian run.
    keep = [k for k in range(8) if k != UNLIKE]
    unconfirmed = 0
    for seed in range(8):
        images, rig, mask = sheet(seed)
        glossy = solve(images[keep], rig.subset(keep), depth=200.0, mask=mask, reflectance="glossy")
        lambertian = solve(images[keep], rig.subset(keep), depth=200.0, mask=mask)
        g, lam = shape_error(glossy, rig, images, UNLIKE), shape_error(lambertian, rig, images, UNLIKE)
        check = glossy.lobe_check
        assert check is not None, seed
        assert g <= 1.05 * lam + 1e-4, (seed, g, lam, check)
        # A lobe the fits do not show is never kept.
        assert glossy.lobe is None or check.highlight_confirmed, (seed, check)
        unconfirmed += not check.highlight_confirmed
        if glossy.lobe is None:
            np.testing.assert_array_equal(glossy.normals, lambertian.normals)
    assert unconfirmed >= 6


@pytest.mark.parametrize("name", ["sphere", "bumps"])
def test_a_glossy_scene_confirms_its_highlight(name: str) -> None:
    # Measured (highlight, the median specular albedo of the fits that see the lobe over all
    # fits'): 0.25-1.8 at roughness 0.3 and 0.15 with 8 and 10 lights, seeds 0 and 2 (noisy).
    for seed, noise in [(0, 0.0), (2, 0.005)]:
        s = nplps.make_scene(name, n=40, camera="pinhole", specular=0.2, roughness=0.15, seed=seed, noise=noise)
        keep = list(range(0, s.rig.n_lights, s.rig.n_lights // 8))[:8]
        result = solve(s.images[keep], s.rig.subset(keep), depth=s.mean_depth, mask=s.mask, reflectance="glossy")
        check = result.lobe_check
        assert check is not None and check.seen > 50 and check.highlight > 0.2, (seed, check)
        assert check.highlight_confirmed and check.glossy_wins and result.lobe is not None
        record = result.summary()["lobe_check"]
        assert record["highlight_confirmed"] is True and record["seen"] == check.seen


@pytest.mark.parametrize("light", [4, 6])
def test_hehe12_without_one_led_falls_back(shared_capture, light: int) -> None:
    # Measured (`nplps evaluate --reflectance glossy`, 7 LEDs each): the runs without LED 4 or 6
    # kept the glossy model (their held-out RMS 0.045 / 0.043 against 0.057 / 0.061 Lambertian)
    # with a lobe of roughness 0.024 that no fit saw (highlight 0 and 0.002), and predicted the
    # LED left out with shape errors 0.81 and 0.098 against 0.022 and 0.034 Lambertian.
    capture = captures.prepare(captures.load_hehe12(shared_capture("hehe12")), bin_factor=4)
    rig = capture.rig()
    options = {"depth": 200.0, "mask": capture.mask, "lights": [light]}
    with pytest.warns(RuntimeWarning, match="do not show the highlight"):
        (glossy,) = held_out(capture.images, rig, reflectance="glossy", **options)
    (lambertian,) = held_out(capture.images, rig, **options)
    check = glossy.result.lobe_check
    assert check is not None and check.glossy < check.lambertian and not check.highlight_confirmed, check
    assert glossy.result.lobe is None
    np.testing.assert_array_equal(glossy.result.normals, lambertian.result.normals)
    assert glossy.shape_error == lambertian.shape_error < 0.04
