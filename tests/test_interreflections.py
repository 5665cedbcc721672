"""Interreflections (issue 21): ``interreflections=True`` on the committed 64² GI renders, its refusals, the CLI flag.

The renders (tests/data/pbr, see tests/test_pbr_renders.py) are path traced with global
illumination; at the true distance the default solver absorbs their indirect light. Measured on
this build (mean normal error, albedo error in the median): the bowl 2.23° / +9.9 % without the
option, 0.37° / +0.2 % with it; the corrugated sheet 7.58° / +1.8 % without, 1.66° / +0.6 % with
(2.63° before the mesh was continued past the image border: the sheet goes on past the image,
and that surface lights it and shadows it). Under the glossy model (lobe given, index 1) the bowl
comes out at 0.340° / +0.01 % with the option.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

import nplps
from pbr_data import angles, load  # tests/pbr_data.py


def run(name: str, **options: object) -> tuple[float, float, nplps.Reconstruction]:
    """Return the mean normal error (degrees), the median albedo error (relative) and the result."""
    data, rig = load(name)
    mask = data["mask"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = nplps.reconstruct(
            data["images"].astype(np.float32), rig, depth=float(data["distance"]), mask=mask, threads=1, **options
        )
    error = float(angles(result.normals[mask], data["normals"][mask]).mean())
    albedo = float(np.median(result.albedo[mask] / float(data["reflectance"]) - 1))
    return error, albedo, result


def test_the_gi_bowl_is_recovered() -> None:
    off, off_albedo, plain = run("bowl-diffuse-gi")
    on, on_albedo, result = run("bowl-diffuse-gi", interreflections=True)
    assert off > 2.0 and off_albedo > 0.08  # measured 2.23°, +9.9 %
    assert on < 0.5 and abs(on_albedo) < 0.01  # measured 0.37°, +0.2 %
    assert plain.timings["indirect"] == 0 and result.timings["indirect"] > 0
    assert len(result.history) > len(plain.history)


def test_the_gi_sheet_improves() -> None:
    off, _, _ = run("sheet-diffuse-gi")
    on, on_albedo, _ = run("sheet-diffuse-gi", interreflections=True)
    assert off > 7.0  # measured 7.58°
    assert on < 2.0 and abs(on_albedo) < 0.02  # measured 1.66°, +0.6 % (2.63° without the margin)


def test_the_option_is_a_flag_and_refuses_what_it_does_not_support() -> None:
    scene = nplps.make_scene("sphere", n=16)
    args = (scene.images, scene.rig)
    with pytest.raises(nplps.InputError, match="interreflections"):
        nplps.reconstruct(*args, depth=scene.mean_depth, interreflections="yes")  # type: ignore[arg-type]
    with pytest.raises(nplps.InputError, match="refine_lights"):
        nplps.reconstruct(
            *args, depth=scene.mean_depth, interreflections=True, refine_lights="intensity", reflectance="glossy"
        )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_intensity_refinement_with_interreflections(seed: int) -> None:
    """Intensities off by up to 20 % (their geometric mean kept) on the GI bowl: with the option the
    light step sees the indirect light and recovers them; without it the indirect light bends them."""
    data, rig = load("bowl-diffuse-gi")
    factors = np.random.default_rng(seed).uniform(0.8, 1.2, rig.n_lights)
    factors /= np.exp(np.log(factors).mean())
    bad = rig.with_intensities(rig.intensities * factors[:, None])

    def refined(interreflections: bool) -> tuple[float, float]:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = nplps.reconstruct(
                data["images"].astype(np.float32),
                bad,
                depth=float(data["distance"]),
                mask=data["mask"],
                threads=1,
                refine_lights="intensity",
                interreflections=interreflections,
            )
        mask = data["mask"]
        error = float(angles(result.normals[mask], data["normals"][mask]).mean())
        found = result.rig.intensities[:, 0] / rig.intensities[:, 0]
        return error, float(np.abs(found / np.exp(np.log(found).mean()) - 1).mean())

    on, on_light = refined(True)
    off, off_light = refined(False)
    # Measured (seeds 0-3): with the option 0.373°, intensities off by 0.062 % on average (the true
    # rig with the option: 0.370°); without it 2.214°, 0.20 %.
    assert on < 0.45 and on_light < 0.001
    assert off > 2.0 and off_light > 2 * on_light


def test_glossy_interreflections_recover_the_gi_bowl() -> None:
    """Under the glossy model (lobe given) the rounds model the indirect light as the Lambertian ones do.

    The committed GI bowl is matte (Lambertian: the lobe's index 1, whose diffuse term is
    Lambert's; under eta 1.5 its glossy fits are 4.36° off without the option, 2.56° with it, a
    wrong diffuse shape): its glossy fits keep a small specular albedo, the modelled diffuse part
    emits and the fits see the observations less the light they receive. Measured 0.340°, +0.01 %
    (the Lambertian model's rounds: 0.370°, +0.2 %).
    """
    lobe = {"reflectance": "glossy", "roughness": 0.3, "eta": 1.0}
    off, off_albedo, plain = run("bowl-diffuse-gi", **lobe)
    on, on_albedo, result = run("bowl-diffuse-gi", interreflections=True, **lobe)
    assert off > 2.0 and off_albedo > 0.08, (off, off_albedo)
    assert on < 0.5 and abs(on_albedo) < 0.01, (on, on_albedo)
    assert plain.timings["indirect"] == 0 and result.timings["indirect"] > 0
    assert result.lobe is not None and len(result.history) > len(plain.history)


def test_the_command_line_flag(tmp_path, capsys) -> None:
    from nplps import cli

    scene = nplps.make_scene("sphere", n=32, camera="pinhole")
    folder = tmp_path / "sphere"
    scene.save(folder)
    argv = ["reconstruct", str(folder), "--rig", str(folder / "rig.json"), "--mask", str(folder / "mask.png")]
    argv += ["--depth", repr(scene.mean_depth), "-q", "--threads", "1"]
    assert cli.main([*argv, "--interreflections", "--out", str(tmp_path / "on")]) == 0, capsys.readouterr().err
    assert cli.main([*argv, "--out", str(tmp_path / "off")]) == 0, capsys.readouterr().err
    on = json.loads((tmp_path / "on" / "summary.json").read_text())
    off = json.loads((tmp_path / "off" / "summary.json").read_text())
    assert on["options"]["interreflections"] is True and on["options"]["solver_options"]["interreflections"] is True
    assert off["options"]["interreflections"] is False
    assert on["timings"]["indirect"] > 0 and off["timings"]["indirect"] == 0


def test_an_albedo_that_is_no_reflectance_is_warned() -> None:
    # make_scene's rig has unit intensities at millimetre distances: its albedo is about 3e4, so
    # the indirect light gathered from the images is out of scale with the direct light. Scaled so
    # that the albedo is 0.5 (a reflectance), the warning goes.
    scene = nplps.make_scene("sphere", n=24, camera="pinhole", seed=0)
    scale = float(np.median(scene.albedo[scene.mask])) / 0.5
    calibrated = nplps.Rig.from_dict(
        {
            **scene.rig.to_dict(),
            "lights": [{**light, "intensity": light["intensity"] * scale} for light in scene.rig.to_dict()["lights"]],
        }
    )
    options = {"depth": scene.mean_depth, "mask": scene.mask, "interreflections": True}
    with pytest.warns(RuntimeWarning, match="median albedo is .* not a reflectance"):
        nplps.reconstruct(scene.images, scene.rig, **options)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        result = nplps.reconstruct(scene.images, calibrated, **options)
    assert abs(float(np.median(result.albedo[scene.mask])) - 0.5) < 0.01
