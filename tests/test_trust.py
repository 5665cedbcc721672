"""Trust without ground truth: the normal uncertainty and leave-one-light-out maps, the per-light table."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import tifffile

import nplps
from nplps import report


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1.0, 1.0)))


@pytest.mark.parametrize("name", ["sphere", "bumps", "saddle"])
@pytest.mark.parametrize("noise", [0.005, 0.02])
def test_predicted_sigma_matches_the_observed_error(name: str, noise: float) -> None:
    """Gaussian noise over three seeds: RMS observed angular error / RMS predicted sigma in 0.8 .. 1.25."""
    for seed in (0, 1, 2):
        scene = nplps.make_scene(name, n=48, seed=seed, noise=noise)
        r = nplps.reconstruct(scene.images, scene.rig, mask=scene.mask, depth=scene.mean_depth)
        assert r.normal_sigma is not None and r.normal_sigma.dtype == np.float32
        inside = scene.mask & np.isfinite(r.normal_sigma)
        assert inside.sum() == scene.mask.sum()
        assert np.isnan(r.normal_sigma[~scene.mask]).all()
        observed = np.sqrt(np.mean(_angles(r.fit_normals, scene.normals)[inside] ** 2))
        predicted = np.sqrt(np.mean(r.normal_sigma[inside].astype(np.float64) ** 2))
        assert 0.8 < observed / predicted < 1.25, (seed, observed, predicted)
        # The leave-one-out error exceeds the in-sample one: mean |e / (1 - h)| > mean |e| of the
        # Gaussian residual, whose RMS is `residual` (sqrt(2 / pi) = 0.80).
        assert r.held_out_error is not None
        ratio = np.nanmean(r.held_out_error[inside]) / np.sqrt(np.nanmean(r.residual[inside] ** 2))
        assert 0.85 < ratio < 1.3, ratio


@pytest.mark.parametrize(
    "kw", [{"rgb": True}, {"camera": "pinhole"}, {"led": True}, {"camera": "pinhole", "rgb": True, "led": True}]
)
def test_colour_pinhole_and_leds(kw: dict) -> None:
    """Colour (channels' covariances summed), pinhole cameras and LEDs: the same match, three seeds."""
    for seed in (0, 1, 2):
        scene = nplps.make_scene("bumps", n=40, seed=seed, noise=0.01, **kw)
        r = nplps.reconstruct(scene.images, scene.rig, mask=scene.mask, depth=scene.mean_depth)
        assert r.normal_sigma is not None
        inside = scene.mask & np.isfinite(r.normal_sigma)
        observed = np.sqrt(np.mean(_angles(r.fit_normals, scene.normals)[inside] ** 2))
        predicted = np.sqrt(np.mean(r.normal_sigma[inside].astype(np.float64) ** 2))
        assert 0.8 < observed / predicted < 1.25, (seed, observed, predicted)


def test_noise_free_images_give_near_zero_uncertainty() -> None:
    scene = nplps.make_scene("sphere", n=32, seed=0)
    r = nplps.reconstruct(scene.images, scene.rig, mask=scene.mask, depth=scene.mean_depth)
    assert r.normal_sigma is not None
    assert np.nanmax(r.normal_sigma) < 0.05


def test_a_wrong_light_stands_out_in_the_per_light_table() -> None:
    """A light whose rig position is off by 15 % of the distance has the largest held-out residual."""
    scene = nplps.make_scene("bumps", n=48, seed=1, noise=0.002)
    positions = scene.rig.positions.copy()
    positions[4] += [0.15 * scene.mean_depth, 0.0, 0.0]
    rig = scene.rig.with_positions(positions)
    r = nplps.reconstruct(scene.images, rig, mask=scene.mask, depth=scene.mean_depth)
    assert r.light_trust is not None
    held = r.light_trust["held_out"]
    assert int(np.argmax(held)) == 4


def test_saved_maps_summary_and_report(tmp_path: Path) -> None:
    scene = nplps.make_scene("sphere", n=40, seed=0, noise=0.01)
    r = nplps.reconstruct(
        scene.images, scene.rig, mask=scene.mask, depth=scene.mean_depth, refine_lights="intensity", shadows=True
    )
    paths = r.save(tmp_path / "r", report=True)
    sigma = tifffile.imread(paths["normal_sigma"])
    assert sigma.dtype == np.float32
    np.testing.assert_array_equal(sigma, r.normal_sigma)
    np.testing.assert_array_equal(tifffile.imread(paths["held_out_error"]), r.held_out_error)
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    trust = summary["trust"]
    assert trust["pixels"] == int(scene.mask.sum())
    finite = r.normal_sigma[np.isfinite(r.normal_sigma)]
    assert trust["normal_sigma_deg"]["median"] == pytest.approx(float(np.median(finite)))
    assert len(trust["lights"]) == scene.rig.n_lights
    assert all(row["pixels"] > 0 and row["held_out"] > row["residual"] > 0 for row in trust["lights"])
    text = paths["report"].read_text(encoding="utf-8")
    part = re.search(r"<section id='trust'>(.*?)</section>", text, re.S)
    assert part is not None
    body = part.group(1)
    assert body.count("<img") == 2 and "Predicted normal uncertainty" in body
    rows = re.findall(r"<tr><td>(\d+)</td>", body)
    assert rows == [str(i) for i in range(scene.rig.n_lights)]
    assert "±" in body and "cast-shadow share" in body  # the refinement's standard errors, the shadows
    assert "position shift" not in body  # intensities refined, positions not
    # Order: after the held-out section.
    assert text.index("<section id='held-out'>") < text.index("<section id='trust'>")
    # A map removed: the section says so.
    (tmp_path / "r" / "normal_sigma.tiff").unlink()
    assert "normal_sigma.tiff is missing" in report.report_html(tmp_path / "r")
    # A damaged map is refused with the file named.
    tifffile.imwrite(tmp_path / "r" / "held_out_error.tiff", np.zeros((3, 3), np.float32))
    with pytest.raises(nplps.InputError, match=r"held_out_error\.tiff"):
        report.report_html(tmp_path / "r")


def test_the_baseline_has_no_trust_maps(tmp_path: Path) -> None:
    scene = nplps.make_scene("sphere", n=24, seed=0)
    r = nplps.reconstruct_parallel(scene.images, scene.rig, mask=scene.mask, depth=scene.mean_depth)
    assert r.normal_sigma is None and r.summary()["trust"] is None
    text = r.save(tmp_path / "r", report=True)["report"].read_text(encoding="utf-8")
    assert "No uncertainty maps" in text
    assert not (tmp_path / "r" / "normal_sigma.tiff").exists()


def test_robust_fits_count_their_weights() -> None:
    """With Tukey weights, observations the robust fit rejects leave the uncertainty small.

    A tenth of the pixels get a highlight (3 times the value) in one light: the plain fit's
    uncertainty there grows several times, the robust fit's stays at the noise level and matches
    the observed error spread on the other pixels (the plain fit's surface is bent by the spots).
    """
    scene = nplps.make_scene("bumps", n=48, seed=3, noise=0.005)
    images = scene.images.copy()
    rng = np.random.default_rng(3)
    spots = scene.mask & (rng.random(scene.mask.shape) < 0.1)
    images[2][spots] *= 3.0
    sigma = {}
    for robust in (None, "tukey"):
        r = nplps.reconstruct(images, scene.rig, mask=scene.mask, depth=scene.mean_depth, robust=robust)
        assert r.normal_sigma is not None
        sigma[robust] = r.normal_sigma.astype(np.float64)
        if robust is not None:
            clean = scene.mask & ~spots
            observed = np.sqrt(np.mean(_angles(r.fit_normals, scene.normals)[clean] ** 2))
            predicted = np.sqrt(np.mean(sigma[robust][clean] ** 2))
            assert 0.8 < observed / predicted < 1.25, (observed, predicted)
    assert np.median(sigma[None][spots]) > 4 * np.median(sigma["tukey"][spots])
    assert np.median(sigma["tukey"][spots]) < 1.5 * np.median(sigma["tukey"][scene.mask & ~spots])


def test_the_command_line_prints_the_uncertainty(tmp_path: Path, capsys) -> None:
    from nplps import cli

    scene = tmp_path / "scene"
    assert cli.main(["synth", "sphere", "--size", "32", "--noise", "0.01", "--out", str(scene)]) == 0
    args = [str(scene), "--rig", str(scene / "rig.json"), "--mask", str(scene / "mask.png"), "--depth", "200"]
    capsys.readouterr()
    assert cli.main(["reconstruct", *args, "--out", str(tmp_path / "out")]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.strip().startswith("uncertainty"))
    trust = json.loads((tmp_path / "out" / "summary.json").read_text())["trust"]
    assert f"normals {trust['normal_sigma_deg']['median']:.3g}° median" in line


def test_a_damaged_summary_is_refused_or_read_safely(tmp_path: Path) -> None:
    scene = nplps.make_scene("sphere", n=24, seed=0, noise=0.01)
    r = nplps.reconstruct(scene.images, scene.rig, mask=scene.mask, depth=scene.mean_depth, refine_lights="intensity")
    r.save(tmp_path / "r")
    path = tmp_path / "r" / "summary.json"
    good = json.loads(path.read_text())
    for trust in ("x", {"lights": "many"}, {"lights": [{"light": "0"}]}, {"lights": [{"light": 0, "residual": "x"}]}):
        path.write_text(json.dumps({**good, "trust": trust}))
        with pytest.raises(nplps.InputError, match=r"summary\.json.*trust"):
            report.report_html(tmp_path / "r")
    # The refinement's record is read only where it is well formed.
    for refinement in ("x", {"changes": "many"}, {"changes": [{"light": 0, "intensity_factor": "big"}]}):
        path.write_text(json.dumps({**good, "light_refinement": refinement}))
        assert "<section id='trust'>" in report.report_html(tmp_path / "r")
