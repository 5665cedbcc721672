"""The glossy reflectance model through the solver (``reconstruct(reflectance="glossy")``).

Exact synthetic scenes (``make_scene(..., specular=, roughness=)`` render the solver's own glossy
model) must be recovered, the shared lobe estimated, and the committed Mitsuba renders of
tests/data/pbr (rough plastic: a GGX lobe over a diffuse base that is not Lambertian) must come out
well under the 1.5° of the shiny-objects issue where the Lambertian model is 4-9° off.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import nplps
from pbr_data import angles, load  # tests/pbr_data.py


def solve(
    images: np.ndarray, rig: nplps.Rig, depth: float | str, mask: np.ndarray, **options: object
) -> nplps.Reconstruction:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return nplps.reconstruct(images, rig, depth=depth, mask=mask, **options)


def scene(name: str, seed: int) -> nplps.Scene:
    return nplps.make_scene(name, n=40, camera="pinhole", specular=0.2, roughness=0.3, seed=seed)


@pytest.mark.parametrize("name", ["sphere", "bumps"])
def test_a_given_lobe_recovers_the_glossy_surface(name: str) -> None:
    # Measured at 48 x 48 without noise: sphere 0.007°, bumps 0.10-0.15° (a few pixels with no
    # light near the lobe take a wrong basin), against 3.4° and 4.7-5.8° for the Lambertian model.
    for seed in range(3):
        s = scene(name, seed)
        glossy = solve(s.images, s.rig, s.mean_depth, s.mask, reflectance="glossy", roughness=0.3, eta=1.5)
        lambertian = solve(s.images, s.rig, s.mean_depth, s.mask)
        error = angles(glossy.normals[s.mask], s.normals[s.mask]).mean()
        before = angles(lambertian.normals[s.mask], s.normals[s.mask]).mean()
        assert error < (0.05 if name == "sphere" else 0.25), (seed, error)
        assert error < before / 10, (seed, error, before)
        assert glossy.lobe == nplps.Lobe(0.3, 1.5)
        assert glossy.specular is not None and glossy.specular.shape == s.mask.shape
        # The specular albedo is the render's (0.2 of the albedo) where the fit is good.
        good = s.mask & (angles(glossy.normals, s.normals) < 0.5)
        ratio = glossy.specular[good] / s.albedo[good]
        assert abs(np.median(ratio) - 0.2) < 0.01, np.median(ratio)
        assert lambertian.lobe is None and lambertian.specular is None


def test_the_lobe_is_estimated_from_the_images() -> None:
    # Measured at 48 x 48: roughness 0.291-0.298 for 0.3 (eta is weakly determined: 1.5-2.2 for
    # 1.5), normals 0.04° (sphere) and 0.16-0.20° (bumps).
    for name, seed in [("sphere", 0), ("bumps", 0), ("bumps", 1), ("bumps", 2)]:
        s = scene(name, seed)
        result = solve(s.images, s.rig, s.mean_depth, s.mask, reflectance="glossy")
        assert result.lobe is not None
        assert abs(result.lobe.roughness - 0.3) < 0.015, (name, seed, result.lobe)
        assert 1.0 <= result.lobe.eta <= 3.0
        assert result.lobe.diffuse == "transmitted", (name, seed, result.lobe)
        error = angles(result.normals[s.mask], s.normals[s.mask]).mean()
        assert error < (0.1 if name == "sphere" else 0.3), (name, seed, error)


def test_the_retro_reflective_diffuse_shape_is_chosen_from_the_images() -> None:
    # The bumps rendered with Burley's retro-reflective diffuse term (Mitsuba's principled): the
    # lobe search should choose that shape (the transmitted one above, on every seed) and then
    # recover the surface; the result's prediction uses the shape it chose. Measured at 40 x 40
    # (seeds 0-4): retro on seeds 0, 2, 4 (0.09-0.16 degrees), the transmitted shape near eta 1
    # on seeds 1 and 3 (0.29 and 0.70 degrees); on the 40 x 40 sphere (few grazing pixels, where
    # the shapes differ) the transmitted shape every time (3.0 degrees). A limit of the choice,
    # see docs/method.md; on the 256 x 256 PBR renders it chose the material's own shape on all 16.
    chosen = 0
    for seed in range(5):
        s = scene("bumps", seed)
        images = nplps.render(
            s.depth, s.rig, s.albedo, mask=s.mask, specular=0.2 * s.albedo, roughness=0.3, diffuse="retro"
        )
        result = solve(images, s.rig, s.mean_depth, s.mask, reflectance="glossy")
        assert result.lobe is not None
        if result.lobe.diffuse != "retro":
            continue
        chosen += 1
        assert abs(result.lobe.roughness - 0.3) < 0.015, (seed, result.lobe)
        error = angles(result.normals[s.mask], s.normals[s.mask]).mean()
        assert error < 0.3, (seed, error)
        assert result.summary()["lobe"]["diffuse"] == "retro"
        predicted = result.predict()
        inside = np.broadcast_to(s.mask, predicted.shape)
        assert np.median(np.abs(predicted - images)[inside]) < 1e-3 * images.max()
    assert chosen >= 3, chosen


@pytest.mark.parametrize(
    ("name", "before_at_least"),
    [("sphere-roughplastic-0.3", 4.0), ("bumps-roughplastic-0.1", 8.0), ("shadows-roughplastic-0.3", 6.0)],
)
def test_physically_based_rough_plastic(name: str, before_at_least: float) -> None:
    # Measured (64 x 64, true distance): Lambertian 4.44 / 9.35 / 6.57°, glossy 0.65 / 0.53 / 0.84°
    # (0.59° on the block with shadows=True).
    data, rig = load(name)
    images, mask = data["images"].astype(np.float32), data["mask"]
    lambertian = solve(images, rig, float(data["distance"]), mask)
    glossy = solve(images, rig, float(data["distance"]), mask, reflectance="glossy")
    before = angles(lambertian.normals[mask], data["normals"][mask]).mean()
    after = angles(glossy.normals[mask], data["normals"][mask]).mean()
    assert before > before_at_least
    assert after < 1.0, after
    assert glossy.lobe is not None and 0.05 < glossy.lobe.roughness < 0.5
    assert glossy.matte_lobe is None


@pytest.mark.parametrize("name", ["bumps-roughplastic-0.1", "shadows-roughplastic-0.3"])
def test_the_distance_search_uses_the_glossy_model(name: str) -> None:
    # Measured (64 x 64, one thread): the Lambertian search misses by -9.9 / -9.1 %, the glossy one
    # by +0.14 / -0.11 % (median facet residual; the lobe estimated per candidate in a window that
    # brackets the distance, then the distance searched under each lobe of a grid held in turn,
    # every candidate a run of its own from the starting surface: distance.rs, fresh_stages; until
    # stop 54 an alternation and an index walk from candidate to candidate, -0.67 / -0.82 %).
    # Within 1 %, issue 20's bound. At 256² the 16 glossy renders: README "Shiny objects".
    data, rig = load(name)
    images, mask, distance = data["images"].astype(np.float32), data["mask"], float(data["distance"])
    lambertian = solve(images, rig, "auto", mask, threads=1)
    glossy = solve(images, rig, "auto", mask, reflectance="glossy", threads=1)
    assert lambertian.distance is not None and glossy.distance is not None
    assert abs(lambertian.distance.distance[0] / distance - 1) > 0.05
    found = glossy.distance.distance[0] / distance - 1
    assert abs(found) < 0.01, found
    assert glossy.lobe is not None and glossy.matte_lobe is None
    # The curve holds the wide scan outside the window and the window's candidates, in order.
    curve = np.asarray(glossy.distance.curve[0])
    assert np.all(np.diff(curve[:, 0]) > 0)
    # The window spans about +-14 % around the wide scan's minimum, not the truth: under the rough
    # transmittance the bumps' window ran from -13.0 % to +15.02 % of the true distance.
    near = np.abs(curve[:, 0] / distance - 1) < 0.16
    assert near.sum() >= 7 and (~near).sum() >= 6


def test_the_distance_search_follows_the_index_under_noise() -> None:
    # The 64² rough plastic 0.3 block with 0.1 % Gaussian noise (of the maximum, clipped at 0, as
    # benchmarks/pbr/run.py --noise), three seeds. The index trades against the distance along a
    # valley of the criterion; the search compares the distance's minimum under each index of its
    # grid (distance.rs, fresh_stages; the grid leaves out the index 1, FRESH_ETAS: with it the
    # noise-free block went to -2.65 %, test_the_distance_search_uses_the_glossy_model). Measured
    # (one thread), seeds 0-5: +0.024 / +0.029 / +0.029 / -0.001 / -0.105 / +0.033 %; stop 53's
    # index walk +0.11 / +0.22 / +0.02 / +0.08 / +0.14 / -0.00 %, stop 44's search without it
    # +0.08 / +0.55 / -0.40 / +0.08 / +0.42 / -0.42 %. Each seed within issue 20's 1 %, and their
    # mean within 0.3 % (0.027 %, seeds 0-2).
    data, rig = load("shadows-roughplastic-0.3")
    images, mask, distance = data["images"].astype(np.float32), data["mask"], float(data["distance"])
    errors = []
    for seed in range(3):
        rng = np.random.default_rng(seed)
        noisy = np.clip(images + rng.normal(0.0, 0.001 * float(images.max()), images.shape), 0.0, None)
        glossy = solve(noisy.astype(np.float32), rig, "auto", mask, reflectance="glossy", threads=1)
        assert glossy.distance is not None
        errors.append(glossy.distance.distance[0] / distance - 1)
    assert max(abs(e) for e in errors) < 0.01, errors
    assert np.mean(np.abs(errors)) < 0.003, errors


def test_the_distance_search_finds_a_retro_reflective_surface() -> None:
    # Mitsuba's principled material (roughness 0.5: Burley's retro-reflective diffuse part) on the
    # bumps, 64 x 64. Measured: -0.135 % and 0.106 degrees, the retro shape chosen by the run at
    # the distance found (0.081 degrees at the true distance); stop 44's search, without a stage
    # under the retro shape held, ended on the transmitted shape with index 1.15 at +1.68 % and
    # 1.16 degrees. Both thread counts: the search's result must not depend on the work split.
    data, rig = load("bumps-principled-0.5")
    images, mask, distance = data["images"].astype(np.float32), data["mask"], float(data["distance"])
    for threads in (1, 2):
        glossy = solve(images, rig, "auto", mask, reflectance="glossy", threads=threads)
        assert glossy.distance is not None and glossy.lobe is not None
        found = glossy.distance.distance[0] / distance - 1
        assert abs(found) < 0.01, (threads, found)
        assert glossy.lobe.diffuse == "retro", glossy.lobe
        error = angles(glossy.normals[mask], data["normals"][mask]).mean()
        assert error < 0.3, (threads, error)


@pytest.mark.parametrize("seed", [1, 2, 5, 6])
def test_the_distance_search_does_not_hang_on_the_last_bits(seed: int) -> None:
    # Mitsuba's principled material (roughness 0.3, retro-reflective diffuse part) on the block
    # with cast shadows, 64 x 64, its images jittered by Gaussian noise of 1e-6 of the maximum
    # (below any sensor's quantization). Until stop 54 the search's outcome on this surface hung on
    # the last bits of its fits (docs/shiny.md, stops 52-54: its stages went from candidate to
    # candidate, each from the last one's surface and fits): seeds 0-7 ended at -0.46 / -1.88 /
    # -1.46 / +0.06 / -0.39 / +1.56 / -2.77 / -0.50 % (stop 51), seeds 1, 2 and 6 beyond 1 % still
    # at stop 53. Every candidate is now a run of its own (distance.rs, Fresh): seeds 0-7 at
    # -0.026 / -0.036 / -0.030 / -0.032 / -0.040 / -0.035 / -0.032 / -0.040 % (stop 54), -0.043 /
    # -0.054 / -0.047 / -0.049 / -0.044 / -0.051 / -0.046 / -0.047 % since the candidates start
    # from the lobe run's surface and cast shadows (stop 55). The seeds of the
    # old misses and the old top-of-the-range one (5), each within 0.5 %.
    data, rig = load("shadows-principled-0.3")
    images, mask, distance = data["images"].astype(np.float32), data["mask"], float(data["distance"])
    rng = np.random.default_rng(seed)
    jittered = np.clip(images + rng.normal(0.0, 1e-6 * float(images.max()), images.shape), 0.0, None)
    glossy = solve(jittered.astype(np.float32), rig, "auto", mask, reflectance="glossy", threads=1)
    assert glossy.distance is not None and glossy.lobe is not None
    found = glossy.distance.distance[0] / distance - 1
    assert abs(found) < 0.005, found


def test_the_projected_stop_rule_costs_the_glossy_model_nothing() -> None:
    # The full resolution of a pyramid may stop by the projected rule (two contracting depth
    # changes under one lobe, nothing pending; solver::projected_converged). Measured at 96 x 96,
    # levels=3, seeds 0-2, lobe given and estimated: 4 of 6 runs stopped by it, their normals
    # within 5e-5 degrees of the same run to a tolerance of 1e-9 (which may stop by the rule too,
    # a million times closer; the scale tests' oracle: 0.01).
    projected = 0
    for seed in range(3):
        s = nplps.make_scene("bumps", n=96, camera="pinhole", specular=0.2, roughness=0.3, eta=1.5, seed=seed)
        for lobe in ({"roughness": 0.3, "eta": 1.5}, {}):
            options = {"reflectance": "glossy", "levels": 3, **lobe}
            fast = solve(s.images, s.rig, s.mean_depth, s.mask, **options)
            full = solve(s.images, s.rig, s.mean_depth, s.mask, tol=1e-9, iterations=30, **options)
            assert fast.converged and full.converged
            projected += "projected" in fast.status_reason
            apart = angles(fast.normals[s.mask], full.normals[s.mask]).mean()
            assert apart < 0.01, (seed, lobe, apart)
    assert projected >= 2, projected


def test_noisy_glossy_runs_stop_once_the_residual_settles() -> None:
    # On noisy images the glossy fits end each local step at a slightly different point, so the
    # largest depth change settles far above the depth rule's limit and every level used to run to
    # its last iteration ("stalled"). A level now also stops after a local step whose RMS residual
    # changed by at most solver::GLOSSY_RESIDUAL_FACTOR * tol of it: fewer iterations, the same
    # surface. Measured at 96 x 96, 0.5 % noise, seeds 0-4 (stop 48, with the kept fits): 5
    # iterations (27-30 with tol=0, the rule off), normals 0.008-0.038 degrees from those (10
    # iterations with the rule off were 0.002-0.015 from them), errors against the truth from
    # 2.1e-3 degrees above theirs to 7e-4 below.
    for seed in range(3):
        s = nplps.make_scene("bumps", n=96, camera="pinhole", specular=0.2, noise=0.005, seed=seed)
        fast = solve(s.images, s.rig, s.mean_depth, s.mask, reflectance="glossy")
        full = solve(s.images, s.rig, s.mean_depth, s.mask, reflectance="glossy", tol=0.0, iterations=30)
        assert fast.converged, (seed, fast.status, fast.status_reason)
        assert len(fast.history) < len(full.history), (seed, len(fast.history), len(full.history))
        apart = angles(fast.normals[s.mask], full.normals[s.mask]).mean()
        error = angles(fast.normals[s.mask], s.normals[s.mask]).mean()
        error_full = angles(full.normals[s.mask], s.normals[s.mask]).mean()
        assert apart < 0.05, (seed, apart)
        assert error < error_full + 0.005, (seed, error, error_full)


@pytest.mark.parametrize("name", ["shadows-diffuse", "sphere-diffuse"])
def test_a_matte_object_falls_back_to_the_lambertian_model(name: str) -> None:
    # Measured (64 x 64, true distance): the lobe found is rough (0.85) and on the block it traded
    # with the diffuse part, 1.18° against 0.67° Lambertian, before the fallback; after it both
    # give the Lambertian result (the glossy run's first iterations differ, so not bit for bit).
    data, rig = load(name)
    images, mask = data["images"].astype(np.float32), data["mask"]
    lambertian = solve(images, rig, float(data["distance"]), mask)
    with pytest.warns(RuntimeWarning, match="the images show no highlight"):
        glossy = nplps.reconstruct(images, rig, depth=float(data["distance"]), mask=mask, reflectance="glossy")
    assert glossy.lobe is None and glossy.specular is None
    assert glossy.matte_lobe is not None and glossy.matte_lobe.roughness >= 0.5
    before = angles(lambertian.normals[mask], data["normals"][mask]).mean()
    after = angles(glossy.normals[mask], data["normals"][mask]).mean()
    # With cast shadows (the block) each run marches its mask on its own mesh of iteration 3,
    # and the glossy run's first iterations differ: the two converge to the fixed points of two
    # masks (measured 0.28 vs 0.30 degrees since the rough transmittance, 0.0017 apart before).
    assert abs(after - before) < 0.03, (before, after)
    assert lambertian.matte_lobe is None
    # Without the masks' path the fallback gives the Lambertian result (measured 4e-8 degrees).
    lambertian = solve(images, rig, float(data["distance"]), mask, shadows=False)
    glossy = solve(images, rig, float(data["distance"]), mask, reflectance="glossy", shadows=False)
    assert glossy.lobe is None and glossy.matte_lobe is not None
    assert angles(lambertian.normals[mask], glossy.normals[mask]).mean() < 1e-4
    # A lobe the user gives is kept, however rough.
    given = solve(images, rig, float(data["distance"]), mask, reflectance="glossy", roughness=0.85, eta=1.5)
    assert given.lobe == nplps.Lobe(0.85, 1.5) and given.matte_lobe is None


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"roughness": 0.3, "eta": 1.5}, "roughness and eta are options of reflectance"),
        ({"reflectance": "glossy", "roughness": 0.3}, "both roughness and eta"),
        ({"reflectance": "glossy", "roughness": 0.0, "eta": 1.5}, "roughness"),
        ({"reflectance": "glossy", "roughness": 0.3, "eta": 0.5}, "eta"),
        ({"reflectance": "shiny"}, "reflectance"),
    ],
)
def test_errors_name_the_option(options: dict[str, object], message: str) -> None:
    s = nplps.make_scene("sphere", n=16)
    with pytest.raises(nplps.InputError, match=message):
        nplps.reconstruct(s.images, s.rig, depth=s.mean_depth, **options)  # type: ignore[arg-type]
