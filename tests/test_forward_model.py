"""Tests of the forward model: the glossy lobe and cast shadows of nplps.render, nplps.cast_shadows.

Scenes come from :func:`nplps.make_scene` (object size 100 at working distance 200, 27 near point
lights), 32 x 32 pixels.
"""

from __future__ import annotations

import numpy as np
import pytest

import nplps

N = 32


@pytest.fixture(scope="module")
def bumps() -> nplps.Scene:
    return nplps.make_scene("bumps", n=N, rgb=True)


@pytest.fixture(scope="module")
def block() -> nplps.Scene:
    return nplps.make_scene("block", n=N)


@pytest.mark.parametrize("camera", ["orthographic", "pinhole"])
def test_glossy_at_eta_one_without_specular_is_lambertian(camera: str) -> None:
    scene = nplps.make_scene("bumps", n=N, camera=camera, rgb=True)  # type: ignore[arg-type]
    lambert = nplps.render(scene.depth, scene.rig, scene.albedo, mask=scene.mask)
    np.testing.assert_array_equal(lambert, scene.images)
    glossy = nplps.render(scene.depth, scene.rig, scene.albedo, mask=scene.mask, specular=0.0, eta=1.0)
    np.testing.assert_allclose(glossy, lambert, rtol=0, atol=1e-12 * lambert.max())
    # The default index 1.5 dims the diffuse term (Fresnel transmittance) at grazing angles only.
    dimmed = nplps.render(scene.depth, scene.rig, scene.albedo, mask=scene.mask, specular=0.0)
    assert (dimmed <= lambert * (1 + 1e-12)).all() and dimmed.max() > 0.9 * lambert.max()


def test_specular_raises_the_images_only_near_the_mirror_direction(bumps: nplps.Scene) -> None:
    kw = {"mask": bumps.mask, "roughness": 0.1, "eta": 1.5}
    matte = nplps.render(bumps.depth, bumps.rig, bumps.albedo, specular=0.0, **kw)
    rho_s = 0.5 * bumps.albedo.mean(axis=2)
    shiny = nplps.render(bumps.depth, bumps.rig, bumps.albedo, specular=rho_s, **kw)
    assert (shiny >= matte).all()
    # The angle between each facet's normal and the half vector of its light and the camera.
    normals = bumps.normals
    centres = nplps._core.vertices(bumps.depth, bumps.rig.camera)
    centres = 0.25 * (centres[:-1, :-1] + centres[1:, :-1] + centres[:-1, 1:] + centres[1:, 1:])
    positions = np.array([light.position for light in bumps.rig.lights])  # type: ignore[union-attr]
    to_light = positions[:, None, None, :] - centres[None]
    to_light /= np.linalg.norm(to_light, axis=-1, keepdims=True)
    half = to_light + np.array([0.0, 0.0, -1.0])
    half /= np.linalg.norm(half, axis=-1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip((half * normals[None]).sum(-1), -1, 1)))
    gain = (shiny - matte).mean(axis=3) / matte.mean(axis=3).max()
    inside = np.broadcast_to(bumps.mask, angle.shape)
    near, far = inside & (angle < 3), inside & (angle > 25)
    assert near.any() and far.any()
    # Measured: the gain is 0.35 to 2.8 of the brightest matte value within 3 degrees of the
    # mirror direction, at most 0.012 beyond 25 degrees.
    assert gain[near].min() > 20 * gain[far].max()
    assert gain[far].max() < 2e-2


def test_shadows_zero_exactly_the_cast_shadows(block: nplps.Scene) -> None:
    shadowed = nplps.cast_shadows(block.depth, block.rig, block.mask)
    assert shadowed.shape == block.images.shape and shadowed.dtype == bool
    assert 0.005 < shadowed.mean() < 0.2
    plain = nplps.render(block.depth, block.rig, block.albedo, mask=block.mask)
    np.testing.assert_array_equal(plain, block.images)
    with_shadows = nplps.render(block.depth, block.rig, block.albedo, mask=block.mask, shadows=True)
    np.testing.assert_array_equal(with_shadows, np.where(shadowed, 0.0, plain))
    scene = nplps.make_scene("block", n=N, shadows=True)
    np.testing.assert_array_equal(scene.images, with_shadows)
    # The other scenes cast no shadows at the default rig.
    for name in ("saddle", "sphere", "cube", "bumps"):
        s = nplps.make_scene(name, n=N)  # type: ignore[arg-type]
        assert not nplps.cast_shadows(s.depth, s.rig, s.mask).any(), name


def test_make_scene_specular(block: nplps.Scene) -> None:
    shiny = nplps.make_scene("block", n=N, specular=0.5, roughness=0.2)
    assert (shiny.images >= block.images * (1 - 1e-12)).all() or shiny.images.max() > block.images.max()
    assert shiny.images.max() > block.images.max()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"specular": -1.0}, "specular"),
        ({"specular": np.ones((3, 3))}, "specular must be a number or a map"),
        ({"specular": "shiny"}, "specular"),
        ({"specular": 0.5, "roughness": 0.0}, "roughness"),
        ({"specular": 0.5, "roughness": 2.0}, "roughness"),
        ({"specular": 0.5, "eta": 0.5}, "eta"),
        ({"specular": 0.5, "eta": float("nan")}, "eta"),
        ({"shadows": "yes"}, "shadows"),
    ],
)
def test_argument_errors(block: nplps.Scene, kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(nplps.InputError, match=message):
        nplps.render(block.depth, block.rig, block.albedo, **kwargs)  # type: ignore[arg-type]


def test_cast_shadows_and_make_scene_argument_errors(block: nplps.Scene) -> None:
    with pytest.raises(nplps.InputError, match="depth"):
        nplps.cast_shadows(block.depth[0], block.rig)
    with pytest.raises(nplps.InputError):
        nplps.cast_shadows(block.depth, block.rig, np.ones((3, 3), bool))
    with pytest.raises(nplps.InputError, match="specular"):
        nplps.make_scene("block", n=N, specular=-0.5)
    with pytest.raises(nplps.InputError, match="roughness"):
        nplps.make_scene("block", n=N, roughness=0.0)
    with pytest.raises(nplps.InputError, match="shadows"):
        nplps.make_scene("block", n=N, shadows=1)  # type: ignore[arg-type]
    # The core refuses a bad lobe too, with the same kind of error.
    with pytest.raises(nplps.InputError, match="roughness"):
        nplps._core.render(block.depth, block.rig._native, block.albedo, specular=1.0, roughness=-1.0)
    with pytest.raises(nplps.InputError, match="specular"):
        nplps._core.render(block.depth, block.rig._native, block.albedo, specular=np.ones((2, 2)))
