"""The glossy model in the parallel-light baseline and in the light refinement (issue 20).

Statistical claims over several seeds; the measurements behind the thresholds are in the
module documentation of ``rust/nplps/src/refine.rs``.
"""

from __future__ import annotations

import numpy as np
import pytest

import nplps
from nplps import InputError, Rig
from nplps.rig import DirectionalLight

SEEDS = range(3)
GLOSSY = dict(specular=0.2, roughness=0.3, eta=1.5)
LOBE = dict(reflectance="glossy", roughness=0.3, eta=1.5)


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))


def _relative(phi: np.ndarray) -> np.ndarray:
    return phi / np.exp(np.mean(np.log(phi)))


def _directional(seed: int, n: int = 40) -> tuple[nplps.Scene, Rig, np.ndarray]:
    """Bumps lit by 27 directional lights (the directions of the scene's point lights from its
    centre), glossy: the parallel-light model is exact."""
    scene = nplps.make_scene("bumps", n=n, seed=seed)
    directions = scene.rig.positions - np.array([0.0, 0.0, scene.mean_depth])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    rig = Rig(scene.rig.camera, [DirectionalLight(d) for d in directions])
    images = nplps.render(scene.depth, rig, scene.albedo, mask=scene.mask, specular=0.2 * scene.albedo, roughness=0.3)
    return scene, rig, images


def test_parallel_baseline_fits_the_glossy_model():
    for seed in SEEDS:
        scene, rig, images = _directional(seed)
        m = scene.mask
        kw = dict(depth=scene.mean_depth, mask=m)
        lambertian = nplps.reconstruct_parallel(images, rig, **kw)
        assert lambertian.lobe is None and lambertian.specular is None
        given = nplps.reconstruct_parallel(images, rig, **kw, **LOBE)
        estimated = nplps.reconstruct_parallel(images, rig, **kw, reflectance="glossy")
        err = {
            name: _angles(r.fit_normals, scene.normals)[m].mean()
            for name, r in (("lambertian", lambertian), ("given", given), ("estimated", estimated))
        }
        # Measured: 5.3-6.1 degrees Lambertian, 0.000 with the lobe given (the baseline's glossy
        # fits continue for 4 warm passes: 0.12 after its one local step alone), 0.05-0.15 estimated.
        assert err["lambertian"] > 4.0 and err["given"] < 0.01 and err["estimated"] < 0.2, (seed, err)
        assert given.lobe == nplps.Lobe(0.3, 1.5)
        np.testing.assert_allclose(given.specular[m], 0.2 * scene.albedo[m], rtol=1e-4)  # float32 images
        assert estimated.lobe.roughness == pytest.approx(0.3, rel=0.05)
        # eta is weakly determined (docs/method.md): the anchored lobe search of the faster glossy
        # step lands at 2.1 (the grid's top) here, the earlier one at 1.37-1.44; the normals
        # above hold either way.
        assert 1.0 <= estimated.lobe.eta <= 3.0
        assert estimated.summary()["reflectance"] == "glossy" and estimated.method == "parallel"


def test_parallel_baseline_refines_intensities_with_the_lambertian_light_step():
    """The baseline's intensity refinement stays the Lambertian light step under the glossy model
    (baseline.rs says why): intensities 30 % off come back within about 1 % RMS, and the glossy
    fit with them is far better than the Lambertian one."""
    for seed in SEEDS:
        scene, rig, images = _directional(seed)
        factors = 1.0 + 0.3 * np.sin(np.arange(rig.n_lights) * 2.1 + seed)
        bad = rig.with_intensities(rig.intensities * factors[:, None])
        kw = dict(depth=scene.mean_depth, mask=scene.mask, refine_lights="intensity")
        glossy = nplps.reconstruct_parallel(images, bad, **kw, **LOBE)
        lambertian = nplps.reconstruct_parallel(images, bad, **kw)
        phi = _relative(glossy.rig.intensities[:, 0]) / _relative(rig.intensities[:, 0])
        assert np.sqrt(np.mean((phi - 1) ** 2)) < 0.015, (seed, phi)
        np.testing.assert_allclose(glossy.rig.intensities, lambertian.rig.intensities)
        err = [_angles(r.fit_normals, scene.normals)[scene.mask].mean() for r in (glossy, lambertian)]
        assert err[0] < 0.5 * err[1], (seed, err)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(roughness=0.3, eta=1.5), 'options of reflectance="glossy"'),
        (dict(reflectance="glossy", roughness=0.3), "give both roughness and eta"),
        (dict(reflectance="glossy", eta=1.5), "give both roughness and eta"),
        (dict(reflectance="glossy", roughness=1.5, eta=1.5), "roughness must be a number in (0, 1]"),
        (dict(reflectance="shiny"), 'reflectance must be "lambertian" or "glossy"'),
    ],
)
def test_parallel_baseline_lobe_errors(kwargs, message):
    scene = nplps.make_scene("sphere", n=16)
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)").replace("]", r"\]")):
        nplps.reconstruct_parallel(scene.images, scene.rig, depth=scene.mean_depth, mask=scene.mask, **kwargs)


def test_refined_intensities_are_not_bent_by_highlights():
    """The light step predicts the specular part from the mesh and the lobe (refine.rs): on
    glossy scenes the refined intensities come back within 0.05 % RMS (the Lambertian light step:
    0.15-0.26 %), and the normals as with the true rig."""
    for seed in SEEDS:
        scene = nplps.make_scene("bumps", n=48, seed=seed, **GLOSSY)
        rng = np.random.default_rng(100 + seed)
        bad = scene.rig.with_intensities(scene.rig.intensities * rng.uniform(0.65, 1.35, (scene.rig.n_lights, 1)))
        kw = dict(depth=scene.mean_depth, mask=scene.mask, iterations=50, tol=1e-7, check_distance=False, **LOBE)
        refined = nplps.reconstruct(scene.images, bad, refine_lights="intensity", **kw)
        phi = _relative(refined.rig.intensities[:, 0]) / _relative(scene.rig.intensities[:, 0])
        rms = np.sqrt(np.mean((phi - 1) ** 2))
        assert rms < 5e-4, (seed, rms)
        err = _angles(refined.normals, scene.normals)[scene.mask].mean()
        assert err < 0.3, (seed, err)
