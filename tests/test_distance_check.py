"""The check of a given working distance: a run at a distance the images contradict says so.

Before, a run at a distance 11 % off (the README's first example) reported "converged" at 6° of
normal error without a word. Rates over many scenes and seeds are in
``benchmarks/distance_check.py``; these tests hold the behaviour over a few seeds.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

import nplps


def _run(scene: nplps.Scene, factor: float, **kw: object) -> tuple[nplps.Reconstruction, list[str]]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = nplps.reconstruct(scene.images, scene.rig, depth=scene.mean_depth * factor, mask=scene.mask, **kw)
    return r, [str(w.message) for w in caught]


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("name", ["sphere", "bumps"])
def test_the_true_distance_does_not_warn(name: str, seed: int) -> None:
    s = nplps.make_scene(name, n=64, seed=seed, noise=0.01)
    r, messages = _run(s, 1.0)
    assert not any("looks wrong" in m for m in messages), messages
    c = r.distance_check
    assert c is not None and not c.looks_wrong
    assert c.given == pytest.approx(s.mean_depth, rel=1e-9)
    # The coarse level finds about the true distance.
    assert abs(c.found / s.mean_depth - 1) < 0.03, c


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("factor", [0.75, 1.25])
def test_a_distance_far_off_warns_and_names_the_better_one(factor: float, seed: int) -> None:
    s = nplps.make_scene("bumps", n=64, seed=seed, noise=0.01)
    r, messages = _run(s, factor)
    wrong = [m for m in messages if "the working distance looks wrong" in m]
    assert len(wrong) == 1, messages
    assert "try --depth auto" in wrong[0]
    c = r.distance_check
    assert c is not None and c.looks_wrong and c.ratio > 1.5
    assert abs(c.found / s.mean_depth - 1) < 0.05, c
    assert f"{c.found:.4g}" in wrong[0] and f"{c.given:.4g}" in wrong[0]


def test_the_readme_case_warns_at_200_for_a_scene_at_179_7() -> None:
    s = nplps.make_scene("sphere", n=128)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = nplps.reconstruct(s.images, s.rig, depth=200.0, mask=s.mask)
    assert r.status == "converged"  # the status alone says nothing about the distance
    assert any("looks wrong" in str(w.message) for w in caught)
    assert r.distance_check is not None and abs(r.distance_check.found - s.mean_depth) < 0.02 * s.mean_depth


def test_the_check_can_be_switched_off() -> None:
    s = nplps.make_scene("bumps", n=32, seed=0)
    r, messages = _run(s, 1.3, check_distance=False)
    assert r.distance_check is None
    assert not any("looks wrong" in m for m in messages)
    with pytest.raises(nplps.InputError, match="check_distance"):
        nplps.reconstruct(s.images, s.rig, depth=s.mean_depth, mask=s.mask, check_distance="yes")  # type: ignore[arg-type]


def test_no_check_where_the_rig_cannot_reveal_the_distance() -> None:
    s = nplps.make_scene("bumps", n=32, seed=0)
    three = [2, 5, 8]
    r = nplps.reconstruct(s.images[three], s.rig.subset(three), depth=s.mean_depth, mask=s.mask)
    assert r.distance_check is None
    d = nplps.make_scene("bumps", n=32, seed=0, directional=True)
    keep = [int(i) for i in np.flatnonzero(d.rig.directional)]
    assert len(keep) >= 4
    r = nplps.reconstruct(d.images[keep], d.rig.subset(keep), depth=d.mean_depth, mask=d.mask)
    assert r.distance_check is None


def test_no_check_with_depth_auto() -> None:
    s = nplps.make_scene("bumps", n=32, seed=0)
    r = nplps.reconstruct(s.images, s.rig, depth="auto", mask=s.mask)
    assert r.distance_check is None and r.distance is not None


def test_summary_json_holds_the_check(tmp_path: Path) -> None:
    s = nplps.make_scene("bumps", n=48, seed=1, noise=0.01)
    r, _ = _run(s, 1.3)
    r.save(tmp_path / "out")
    summary = json.loads((tmp_path / "out" / "summary.json").read_text(encoding="utf-8"))
    check = summary["distance_check"]
    assert check["looks_wrong"] is True and check["given"] == pytest.approx(s.mean_depth * 1.3)
    assert np.isfinite(check["ratio"]) and check["ratio"] > 1.5


def test_the_cli_warns_and_prints_the_check(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from nplps.cli import main

    s = nplps.make_scene("bumps", n=48, seed=2, noise=0.01)
    s.save(tmp_path / "scene")
    code = main(
        [
            "reconstruct",
            str(tmp_path / "scene"),
            "--rig",
            str(tmp_path / "scene" / "rig.json"),
            "--mask",
            str(tmp_path / "scene" / "mask.png"),
            "--depth",
            f"{s.mean_depth * 0.75:.6g}",
            "--out",
            str(tmp_path / "out"),
        ]
    )
    assert code == 0
    out, err = capsys.readouterr()
    assert "the working distance looks wrong" in err and "try --depth auto" in err
    assert "distance check  LOOKS WRONG" in out


@pytest.mark.parametrize("given, wrong", [(200.0, False), (160.0, True), (250.0, True)])
def test_a_real_capture_warns_20_percent_off_and_not_at_its_distance(
    shared_capture: object, given: float, wrong: bool
) -> None:
    """hehe12 (documented 200 mm): its residual is mostly model error, the ratio at 20-25 % off
    is only about 1.05, yet the coarse level finds 199-200 from either side."""
    from nplps import captures

    cap = captures.prepare(captures.load_hehe12(shared_capture("hehe12")), bin_factor=4)  # type: ignore[operator]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = nplps.reconstruct(cap.images, cap.rig(), depth=given, mask=cap.mask)
    c = r.distance_check
    assert c is not None and c.looks_wrong is wrong, c
    assert abs(c.found / 200.0 - 1) < 0.03, c


def test_the_report_shows_the_check(tmp_path: Path) -> None:
    from nplps.cli import main

    s = nplps.make_scene("bumps", n=48, seed=1, noise=0.01)
    r, _ = _run(s, 1.3)
    r.save(tmp_path / "out", report=True)
    html = (tmp_path / "out" / "report.html").read_text(encoding="utf-8")
    assert "distance check" in html.lower() and "LOOKS WRONG" in html
    # Re-made from the files alone.
    assert main(["report", str(tmp_path / "out"), "--out", str(tmp_path / "again.html")]) == 0
    again = (tmp_path / "again.html").read_text(encoding="utf-8")
    assert "distance check" in again and "LOOKS WRONG" in again


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_glossy_check_judges_as_the_lambertian_one(seed: int) -> None:
    # The check under the glossy model (3 iterations a candidate, stop 46): at the distance no
    # warning and about the true distance found; 25 % off a warning that names it. Glossy
    # bumps rendered by the glossy model itself, lobe estimated.
    s = nplps.make_scene("bumps", n=64, seed=seed, noise=0.005, camera="pinhole", specular=0.2, roughness=0.3)
    for factor in (0.75, 1.0, 1.25):
        r, messages = _run(s, factor, reflectance="glossy")
        c = r.distance_check
        assert r.lobe is not None and c is not None
        assert c.looks_wrong == (factor != 1.0), (factor, c)
        assert any("looks wrong" in m for m in messages) == (factor != 1.0), messages
        assert abs(c.found / s.mean_depth - 1) < 0.03, (factor, c)
        assert c.ratio > 3 if factor != 1.0 else c.ratio == 1.0, (factor, c)
