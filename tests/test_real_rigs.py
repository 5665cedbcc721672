"""Synthetic tests of the real-rig features: pinhole cameras, LED models, colour, directional
lights, robust fitting, prediction and held-out evaluation."""

from __future__ import annotations

import numpy as np
import pytest

import nplps
from nplps.evaluation import held_out

VARIANTS = {
    "pinhole": dict(camera="pinhole"),
    "pinhole-leds": dict(camera="pinhole", led=True),
    "orthographic-leds": dict(led=True),
    "rgb": dict(camera="pinhole", led=True, rgb=True),
    "directional": dict(camera="pinhole", directional=True),
}


@pytest.mark.parametrize("variant", sorted(VARIANTS))
@pytest.mark.parametrize("name", ["saddle", "sphere", "bumps"])
def test_exact_model_is_recovered(variant, name, angular_error):
    s = nplps.make_scene(name, n=48, **VARIANTS[variant])
    r = nplps.reconstruct(s.images, s.rig, mask=s.mask, depth=s.mean_depth, iterations=60, tol=1e-10)
    err = angular_error(r.fit_normals, s.normals, s.mask).mean()  # the mesh's add the twisted quads' discretization
    depth_err = np.nanmax(np.abs(r.depth - s.depth)) / s.size
    print(f"{variant} {name}: {err:.2e} deg, depth {depth_err:.2e} of size, {len(r.history)} iterations")
    assert err < 0.01
    assert depth_err < 1e-3
    if variant == "rgb":
        assert r.albedo.shape == (*s.mask.shape, 3)
        np.testing.assert_allclose(r.albedo[s.mask], s.albedo[s.mask], rtol=5e-3)


def test_pinhole_gauge_is_the_geometric_mean(active_vertices):
    s = nplps.make_scene("bumps", n=40, camera="pinhole", distance=300.0)
    r = nplps.reconstruct(s.images, s.rig, mask=s.mask, depth=s.mean_depth)
    z = r.depth[active_vertices(s.mask)]
    assert np.exp(np.log(z).mean()) == pytest.approx(s.mean_depth, rel=1e-12)
    assert r.gauge[0] == pytest.approx(s.mean_depth, rel=1e-12)
    # Vertices lie on the rays through the pixel corners.
    K = s.rig.K
    v = r.vertices
    u = K[0, 0] * v[..., 0] / v[..., 2] + K[0, 2]
    _rows, cols = np.mgrid[0:41, 0:41]
    np.testing.assert_allclose(u[active_vertices(s.mask)], (cols - 0.5)[active_vertices(s.mask)], atol=1e-9)


def test_distortion_is_undone_along_the_rays():
    K = [[500.0, 0.0, 20.0], [0.0, 500.0, 20.0], [0.0, 0.0, 1.0]]
    lights = [[40.0, 0.0, 0.0], [-30.0, 30.0, 0.0], [0.0, -40.0, 0.0]]
    plain = nplps.Rig.pinhole(K, lights)
    bent = nplps.Rig.pinhole(K, lights, distortion=[-0.3, 0.1])
    depth = np.full((41, 41), 200.0)
    a, b = plain_v, bent_v = [
        nplps.Reconstruction(depth, *(np.zeros(0),) * 6, [], True, np.ones((40, 40), bool), rig).vertices
        for rig in (plain, bent)
    ]
    # Barrel distortion (k1 < 0) bends rays outwards: the undistorted corners lie further out.
    r_plain = np.hypot(a[0, 0, 0], a[0, 0, 1])
    r_bent = np.hypot(b[0, 0, 0], b[0, 0, 1])
    assert r_bent > r_plain
    np.testing.assert_allclose(plain_v[20, 20], bent_v[20, 20], atol=1e-3)


def _corrupt(images, mask, seed, highlight_fraction=0.1):
    """Adds specular highlights to a fraction of the observations and cast shadows (with some
    ambient light left) to others."""
    rng = np.random.default_rng(seed)
    out = images.copy()
    k = images.shape[0]
    select = (rng.random(images.shape) < highlight_fraction) & mask[None]
    out[select] += 0.5 * images.max() * rng.uniform(0.5, 1.0, select.sum())
    # Cast shadows: for each light, a band of pixels darkened to 10 %.
    h, _w = mask.shape
    for i in range(0, k, 3):
        r0 = rng.integers(0, h - h // 4)
        out[i, r0 : r0 + h // 4] *= 0.1
    return out


@pytest.mark.parametrize("robust", ["cauchy", "tukey"])
def test_robust_fit_halves_the_error_under_highlights_and_cast_shadows(robust, angular_error):
    errors = {"plain": [], robust: []}
    for seed, name in enumerate(["sphere", "bumps", "saddle"]):
        s = nplps.make_scene(name, n=40, camera="pinhole", led=True)
        images = _corrupt(s.images, s.mask, seed)
        for key, estimator in (("plain", None), (robust, robust)):
            r = nplps.reconstruct(images, s.rig, mask=s.mask, depth=s.mean_depth, robust=estimator, iterations=20)
            errors[key].append(angular_error(r.normals, s.normals, s.mask).mean())
    plain, fitted = np.mean(errors["plain"]), np.mean(errors[robust])
    print(f"mean error plain {plain:.2f} deg, {robust} {fitted:.2f} deg ({plain / fitted:.1f}x)")
    assert fitted * 2 <= plain


def test_saturated_and_missing_observations_are_left_out(angular_error):
    s = nplps.make_scene("sphere", n=40, camera="pinhole")
    images = s.images.copy()
    top = np.quantile(images[:, s.mask], 0.95)
    clipped = np.minimum(images, top)
    plain = nplps.reconstruct(clipped, s.rig, mask=s.mask, depth=s.mean_depth, saturation=np.inf)
    aware = nplps.reconstruct(clipped, s.rig, mask=s.mask, depth=s.mean_depth, saturation=top * (1 - 1e-6))
    e_plain = angular_error(plain.normals, s.normals, s.mask).mean()
    e_aware = angular_error(aware.normals, s.normals, s.mask).mean()
    assert e_aware < 0.01 < e_plain
    assert (aware.lights_used[s.mask] < s.rig.n_lights).any()
    valid = np.ones(images.shape, bool)
    valid[:5] = False
    r = nplps.reconstruct(images, s.rig, mask=s.mask, depth=s.mean_depth, valid=valid)
    assert r.lights_used[s.mask].max() == s.rig.n_lights - 5
    assert angular_error(r.normals, s.normals, s.mask).mean() < 0.01


def test_integer_images_get_bit_depth_thresholds():
    s = nplps.make_scene("saddle", n=24, camera="pinhole")
    images16 = np.round(s.images / s.images.max() * 65535).astype(np.uint16)
    images16[0, 0, 0] = 65535
    images16[1, 0, 0] = 1
    r = nplps.reconstruct(images16, s.rig, mask=s.mask, depth=s.mean_depth)
    assert r.lights_used[0, 0] == s.rig.n_lights - 2


def test_prediction_reproduces_the_images():
    s = nplps.make_scene("bumps", n=32, camera="pinhole", led=True, rgb=True)
    r = nplps.reconstruct(s.images, s.rig, mask=s.mask, depth=s.mean_depth, iterations=40, tol=1e-10)
    p = r.predict()
    assert p.shape == s.images.shape
    assert np.abs(p - s.images).max() < 1e-3 * s.images.max()
    single = r.predict(lights=[4])
    np.testing.assert_allclose(single[0], p[4])


def test_held_out_prefers_the_near_light_model():
    s = nplps.make_scene("bumps", n=32, camera="pinhole", led=True, noise=0.005)
    near = held_out(s.images, s.rig, mask=s.mask, depth=s.mean_depth, lights=[0, 9, 20])
    parallel = held_out(s.images, s.rig, mask=s.mask, depth=s.mean_depth, method="parallel", lights=[0, 9, 20])
    for a, b in zip(near, parallel, strict=False):
        assert a.light == b.light
        assert a.relative_error < 0.05 < b.relative_error


def test_grey_mode_leaves_out_observations_with_one_saturated_channel():
    s = nplps.make_scene("sphere", n=24, camera="pinhole", rgb=True)
    images = np.round(s.images / s.images.max() * 255).astype(np.uint8)
    images[0, 12, 12, 1] = 255  # only the green channel saturates
    grey = nplps.reconstruct(images, s.rig, mask=s.mask, depth=s.mean_depth, color=False)
    colour = nplps.reconstruct(images, s.rig, mask=s.mask, depth=s.mean_depth)
    assert grey.albedo.ndim == 2 and colour.albedo.ndim == 3
    assert grey.lights_used[12, 12] == colour.lights_used[12, 12] == colour.lights_used[12, 11] - 1
