"""Cast shadows predicted from the current mesh inside the solver (``reconstruct(shadows=...)``).

The committed 64 x 64 Mitsuba render of a block on a plane (tests/data/pbr, direct light only)
casts shadows over 2.2 % of its observations. Without the march (``shadows=False``) the shadow
edges' partly lit pixels bend the normals (0.67° mean); with it (True, and the default "auto",
whose probe finds the block's shadows) the observations the mesh hides are left out.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

import nplps
from pbr_data import angles, load  # tests/pbr_data.py


def run(images: np.ndarray, rig: nplps.Rig, data: dict[str, np.ndarray], **options: object) -> nplps.Reconstruction:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return nplps.reconstruct(images, rig, depth=float(data["distance"]), mask=data["mask"], **options)


def error(result: nplps.Reconstruction, data: dict[str, np.ndarray]) -> float:
    m = data["mask"]
    return float(angles(result.normals[m], data["normals"][m]).mean())


@pytest.mark.parametrize("noise", [0.0, 0.005])
def test_shadows_from_the_mesh_lower_the_error(noise: float) -> None:
    # Measured: 0.67° -> 0.28° noise-free, 0.66-0.68° -> 0.40-0.41° with 0.5 % noise (4 seeds).
    data, rig = load("shadows-diffuse")
    clean = data["images"].astype(np.float32)
    truth = nplps.cast_shadows(data["depth"], rig, mask=data["mask"])
    for seed in range(3 if noise else 1):
        rng = np.random.default_rng(seed)
        images = np.clip(clean + rng.normal(0.0, noise * clean.max(), clean.shape), 0.0, None).astype(np.float32)
        plain = run(images, rig, data, shadows=False)
        shadowed = run(images, rig, data, shadows=True)
        default = run(images, rig, data)
        assert plain.shadows is None and plain.shadow_bits is None
        assert np.array_equal(default.normals, shadowed.normals, equal_nan=True)
        assert error(shadowed, data) < 0.5
        assert error(shadowed, data) < error(plain, data) - 0.2
        # The masks the fits used are those of the true surface but for a few edge pixels.
        found = shadowed.shadows
        assert found is not None and found.shape == truth.shape and found.dtype == bool
        assert np.mean(found != truth) < 0.005
        assert found.sum() > 0.9 * truth.sum()
        assert shadowed.timings["shadows"] > 0.0


def test_shadow_bits_unpack_past_64_lights() -> None:
    # 70 lights: two words a pixel. The unpacked masks agree with nplps.cast_shadows of the result's
    # own surface where the mesh is converged (the final masks come from an iteration before the
    # last: a few pixels may differ).
    scene = nplps.make_scene("block", n=48, camera="pinhole", shadows=True)
    rng = np.random.default_rng(3)
    angle = rng.uniform(0.0, 2.0 * np.pi, 70)
    radius = rng.uniform(20.0, 90.0, 70)
    positions = np.stack([radius * np.cos(angle), radius * np.sin(angle), rng.uniform(-20.0, 20.0, 70)], axis=1)
    rig = nplps.Rig.pinhole(scene.rig.to_dict()["camera"]["K"], positions)
    images = nplps.render(scene.depth, rig, mask=scene.mask, shadows=True).astype(np.float32)
    truth = nplps.cast_shadows(scene.depth, rig, mask=scene.mask)
    assert truth[64:].any(), "the test needs shadows of lights past the first word"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = nplps.reconstruct(images, rig, depth=scene.mean_depth, mask=scene.mask, shadows=True)
    assert result.shadow_bits is not None and result.shadow_bits.shape == (48, 48, 2)
    found = result.shadows
    assert found is not None and found.shape == (70, 48, 48)
    assert np.mean(found != truth) < 0.01
    assert np.mean(found[64:] != truth[64:]) < 0.01 and found[64:].any()


def test_shadows_must_be_a_flag_or_auto() -> None:
    scene = nplps.make_scene("sphere", n=16)
    for wrong in ("yes", "on", 1):
        with pytest.raises(nplps.InputError, match='shadows must be "auto", True or False'):
            nplps.reconstruct(scene.images, scene.rig, depth=scene.mean_depth, shadows=wrong)  # type: ignore[arg-type]


@pytest.mark.parametrize("name", ["sphere", "bumps"])
def test_automatic_shadows_change_nothing_on_objects_without_cast_shadows(name: str) -> None:
    # The default probes a lattice of pixels; on a surface that hides no light from itself the
    # result is that of shadows=False, bit for bit (256 x 256: two pyramid levels, probes on both).
    scene = nplps.make_scene(name, n=256, camera="pinhole", noise=0.005, seed=1)
    kw = {"depth": scene.mean_depth, "mask": scene.mask, "progress": False}
    off = nplps.reconstruct(scene.images, scene.rig, shadows=False, **kw)
    auto = nplps.reconstruct(scene.images, scene.rig, **kw)
    assert auto.shadows is None
    assert auto.timings["shadows"] > 0.0 and off.timings["shadows"] == 0.0
    for a, b in ((auto.normals, off.normals), (auto.depth, off.depth), (auto.albedo, off.albedo)):
        assert np.array_equal(a, b, equal_nan=True)


def test_the_command_line_flag_and_the_result_folder(tmp_path, capsys) -> None:
    from nplps import cli

    scene = nplps.make_scene("block", n=32, camera="pinhole", shadows=True)
    scene.save(tmp_path / "block")
    folder = tmp_path / "block"
    argv = ["reconstruct", str(folder), "--rig", str(folder / "rig.json"), "--mask", str(folder / "mask.png")]
    argv += ["--depth", repr(scene.mean_depth), "-q", "--shadows", "--out", str(tmp_path / "out")]
    assert cli.main(argv) == 0, capsys.readouterr().err
    out = tmp_path / "out"
    summary = json.loads((out / "summary.json").read_text())
    cast = summary["cast_shadows"]
    truth = nplps.cast_shadows(scene.depth, scene.rig, mask=scene.mask)
    assert cast["share"] == pytest.approx(truth[:, scene.mask].mean(), rel=0.3)
    assert len(cast["per_light"]) == scene.rig.n_lights
    assert summary["options"]["shadows"] == "on" and summary["options"]["solver_options"]["shadows"] is True
    bits = np.load(out / "shadows.npy")
    assert bits.shape == (32, 32, 1) and bits.dtype == np.uint64
    assert (out / "shadows.png").is_file()
    assert "cast shadows predicted from the mesh" in (out / "report.html").read_text()
    # Without the flag ("auto"): this small block hides 0.27 % of the observations, below the
    # 0.5 % from which the default uses masks, so no shadow files and null in the summary, as
    # with --shadows off.
    assert cast["share"] < 0.005
    default = [a for a in argv if a != "--shadows"]
    off = [*default[:-2], "--shadows", "off", "--out", str(tmp_path / "plain")]
    default[-1] = str(tmp_path / "default")
    for args, name in ((default, "default"), (off, "plain")):
        assert cli.main(args) == 0
        assert json.loads((tmp_path / name / "summary.json").read_text())["cast_shadows"] is None
        assert not (tmp_path / name / "shadows.npy").exists()
