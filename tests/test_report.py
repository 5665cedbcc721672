"""The report (nplps.report), the oblique renders and colour maps (nplps.views), ``nplps report``."""

from __future__ import annotations

import dataclasses
import json
import re
import time
from pathlib import Path

import numpy as np
import pytest

import nplps
from nplps import cli, report, views
from nplps.evaluation import held_out, reading

SECTIONS = (
    "inputs",
    "maps",
    "residual",
    "unfitted",
    "depth",
    "renders",
    "convergence",
    "distance",
    "held-out",
    "trust",
    "options",
)


@pytest.fixture(scope="module")
def scene() -> nplps.synth.Scene:
    return nplps.make_scene("sphere", n=40, seed=0)


@pytest.fixture(scope="module")
def result(scene: nplps.synth.Scene) -> nplps.Reconstruction:
    return nplps.reconstruct(scene.images, scene.rig, depth="auto", mask=scene.mask)


def _check_self_contained(text: str) -> None:
    assert not re.search(r"""(src|href)\s*=\s*["']?\s*(https?:)?//""", text, re.I)
    assert "<script" not in text.lower()
    sources = re.findall(r"<img[^>]*\ssrc=\"([^\"]*)\"", text)
    assert sources and all(s.startswith("data:image/png;base64,") for s in sources)
    assert len(sources) == len(re.findall(r"<img\b", text))


def _section(text: str, anchor: str) -> str:
    match = re.search(rf"<section id='{anchor}'>(.*?)</section>", text, re.S)
    assert match, anchor
    return match.group(1)


def test_save_writes_a_self_contained_report_with_every_section(
    scene: nplps.synth.Scene, result: nplps.Reconstruction, tmp_path: Path
) -> None:
    paths = result.save(tmp_path / "r", report=True, inputs=scene.images, options={"depth": "auto", "n": 40})
    text = paths["report"].read_text(encoding="utf-8")
    _check_self_contained(text)
    for anchor in SECTIONS:
        _section(text, anchor)
    order = [text.index(f"<section id='{a}'>") for a in SECTIONS]
    assert order == sorted(order)
    header = text[: text.index("<section")]
    assert "40 x 40 pixels (W x H)" in header and "converged" in header
    assert f"<td>{scene.rig.n_lights}</td>" in header
    assert "input images" in _section(text, "inputs")  # the thumbnails, not the "none" line
    assert 'class="none"' not in _section(text, "distance")  # the depth was searched
    assert "<svg" in _section(text, "convergence") and "<svg" in _section(text, "distance")
    assert _section(text, "renders").count("<img") == 3
    assert "&quot;auto&quot;" in _section(text, "options")  # the options recorded
    manifest = json.loads((tmp_path / "r" / "nplps-manifest.json").read_text())["files"]
    assert {"report.html", "inputs.png", "history.csv", "rig.json", "mask.png", "lights_used.npy"} <= set(manifest)
    history = np.loadtxt(tmp_path / "r" / "history.csv", delimiter=",", skiprows=1, ndmin=2)
    np.testing.assert_allclose(history[:, 2], [h.depth_change for h in result.history])


def test_sections_without_data_say_so(scene: nplps.synth.Scene, tmp_path: Path) -> None:
    r = nplps.reconstruct(scene.images, scene.rig, depth=scene.mean_depth, mask=scene.mask)
    text = r.save(tmp_path / "r", report=True)["report"].read_text(encoding="utf-8")
    assert "No input thumbnails" in _section(text, "inputs")
    assert "given, not searched" in _section(text, "distance")
    assert "No held-out evaluation" in _section(text, "held-out")
    assert "options were not recorded" in _section(text, "options")
    assert "None: every one of the" in _section(text, "unfitted")
    # Files of the report removed: their sections say so instead of disappearing.
    for name in ("rig.json", "history.csv", "residual.npy", "lights_used.npy"):
        (tmp_path / "r" / name).unlink()
    text = report.report_html(tmp_path / "r")
    assert "rig.json missing" in _section(text, "renders")
    assert "history.csv is missing" in _section(text, "convergence")
    assert "residual.npy is missing" in _section(text, "residual")
    assert "lights_used.npy is missing" in _section(text, "unfitted")


def test_unfitted_pixels_are_shown(scene: nplps.synth.Scene, tmp_path: Path) -> None:
    valid = np.ones(scene.images.shape, dtype=bool)
    valid[3:, 10:14, 10:14] = False  # 16 masked pixels keep only 3 of their lights... fewer: 3 left
    valid[2:, 10:12, 10:12] = False  # 4 pixels with 2 lights
    r = nplps.reconstruct(scene.images, scene.rig, depth=scene.mean_depth, mask=scene.mask, valid=valid)
    assert r.unfitted > 0
    text = r.save(tmp_path / "r", report=True)["report"].read_text(encoding="utf-8")
    assert f"{r.unfitted} of {int(scene.mask.sum())} masked pixels" in _section(text, "unfitted")


def test_held_out_table_and_reading(scene: nplps.synth.Scene, result: nplps.Reconstruction, tmp_path: Path) -> None:
    small = nplps.make_scene("sphere", n=20, seed=0)
    kw = dict(depth=small.mean_depth, mask=small.mask, lights=[0, 5])
    near = held_out(small.images, small.rig, **kw)
    parallel = held_out(small.images, small.rig, method="parallel", **kw)
    text = result.save(tmp_path / "r", report=True, held_out=(near, parallel))["report"].read_text(encoding="utf-8")
    part = _section(text, "held-out")
    assert "reading: " in part and "<td>5</td>" in part
    record = json.loads((tmp_path / "r" / "held_out.json").read_text())
    assert record["lights"] == [0, 5] and len(record["parallel"]) == 2


def test_colour_bars_match_the_data(result: nplps.Reconstruction, tmp_path: Path) -> None:
    text = result.save(tmp_path / "r", report=True)["report"].read_text(encoding="utf-8")
    depth = _section(text, "depth")
    lo, hi = float(np.nanmin(result.depth)), float(np.nanmax(result.depth))
    (bar,) = re.findall(r'data-min="([^"]+)" data-max="([^"]+)"', depth)
    assert float(bar[0]) == pytest.approx(lo) and float(bar[1]) == pytest.approx(hi)
    ticks = [float(t) for t in re.findall(r'class="tick"[^>]*>([^<]+)<', depth)]
    assert ticks[0] == pytest.approx(lo, rel=1e-3) and ticks[-1] == pytest.approx(hi, rel=1e-3)
    assert ticks == sorted(ticks) and len(ticks) >= 3
    residual = _section(text, "residual")
    (bar,) = re.findall(r'data-min="([^"]+)" data-max="([^"]+)"', residual)
    finite = result.residual[result.mask]
    assert float(bar[0]) == 0.0 and float(bar[1]) == pytest.approx(np.percentile(finite, 99.5), rel=1e-6)


def test_colorbar_ticks_and_colormap() -> None:
    assert views.colorbar_ticks(0.0, 1.0) == [0.0, 0.2, 0.4, 0.6, 0.8, 1.0]
    ticks = views.colorbar_ticks(170.01, 191.44)
    assert ticks[0] == 170.01 and ticks[-1] == 191.44 and 180.0 in ticks
    rgb = views.colormap(np.linspace(0, 1, 50))
    lightness = rgb @ np.array([0.2126, 0.7152, 0.0722])
    assert np.all(np.diff(lightness) > 0)  # perceptually ordered: lightness rises
    assert np.isnan(views.colormap(np.array([np.nan]))).all()


def test_cli_reconstruct_writes_the_report_and_nplps_report_remakes_it(tmp_path: Path, capsys) -> None:
    scene = tmp_path / "scene"
    assert cli.main(["synth", "bumps", "--size", "32", "--seed", "1", "--out", str(scene)]) == 0
    common = [str(scene), "--rig", str(scene / "rig.json"), "--mask", str(scene / "mask.png"), "--quiet"]
    assert cli.main(["reconstruct", *common, "--depth", "auto", "--out", str(tmp_path / "out")]) == 0
    page = tmp_path / "out" / "report.html"
    text = page.read_text(encoding="utf-8")
    _check_self_contained(text)
    for anchor in SECTIONS:
        _section(text, anchor)
    assert "input images" in _section(text, "inputs")
    options = json.loads((tmp_path / "out" / "summary.json").read_text())["options"]
    assert options["depth"] == "auto" and options["solver_options"]["iterations"] == 10

    page.unlink()
    capsys.readouterr()
    assert cli.main(["report", str(tmp_path / "out")]) == 0
    assert "report.html" in capsys.readouterr().out
    assert page.read_text(encoding="utf-8").count("<section") == len(SECTIONS)

    assert cli.main(["reconstruct", *common, "--depth", "200", "--no-report", "--out", str(tmp_path / "plain")]) == 0
    assert not (tmp_path / "plain" / "report.html").exists()
    assert cli.main(["report", str(tmp_path / "plain")]) == 0
    manifest = json.loads((tmp_path / "plain" / "nplps-manifest.json").read_text())["files"]
    assert "report.html" in manifest

    assert cli.main(["report", str(scene)]) == 2  # not a result directory
    assert "not an nplps result directory" in capsys.readouterr().err


def _silhouette(image: np.ndarray) -> np.ndarray:
    return (image != 255).any(axis=-1)


def test_sphere_seen_from_the_side(result: nplps.Reconstruction) -> None:
    front = views.render_mesh(result.vertices, result.mask, size=200)
    side = views.render_mesh(result.vertices, result.mask, azimuth=35, size=200)
    inside = _silhouette(side)
    rows, cols = np.nonzero(inside)
    box = (np.ptp(rows) + 1) * (np.ptp(cols) + 1)
    assert 0.7 < inside.sum() / box < 0.85  # filled, roughly elliptic (pi/4 of its box)
    grey = side[..., 0][inside].astype(float)
    assert grey.std() > 10  # shaded, not a flat silhouette
    assert np.abs(front.astype(float) - side.astype(float)).mean() > 5  # not the camera's view
    # Seen from the right the left limb turns away: darker on the left than on the right.
    mid = side[rows.min() + (np.ptp(rows) // 2)]
    lit = np.nonzero(_silhouette(mid[None])[0])[0]
    assert mid[lit[:5], 0].mean() < mid[lit[-5:], 0].mean()


def test_tilted_plane_brightens_towards_its_normal() -> None:
    h = w = 30
    rows, cols = np.mgrid[0 : h + 1, 0 : w + 1].astype(float)
    x, y = cols - w / 2, rows - h / 2
    z = 100 + 0.5 * x  # recedes to the right: its normal points to +x (and to the camera)
    vertices = np.stack([x, y, z], axis=-1)
    mask = np.ones((h, w), dtype=bool)
    grey = {az: views.render_mesh(vertices, mask, azimuth=az, size=120) for az in (-35, 0, 35)}
    level = {az: float(img[_silhouette(img)][:, 0].mean()) for az, img in grey.items()}
    assert level[35] > level[0] > level[-35]
    # and its projected width grows as the view turns towards the normal
    widths = {az: int(_silhouette(img).any(axis=0).sum()) for az, img in grey.items()}
    assert widths[35] >= widths[-35]


def test_key_light_shows_the_relief_of_a_sheet_facing_the_viewer() -> None:
    # A gently curved sheet facing the viewer: a headlight shades it almost evenly, the key light
    # (above left of the eye) brightens the part that faces up and left.
    h = w = 40
    rows, cols = np.mgrid[0 : h + 1, 0 : w + 1].astype(float)
    x, y = cols - w / 2, rows - h / 2
    vertices = np.stack([x, y, 100 + 0.01 * (x**2 + y**2)], axis=-1)  # a dome: nearest at the centre
    mask = np.ones((h, w), dtype=bool)
    keyed = views.render_mesh(vertices, mask, size=160)[..., 0].astype(float)
    head = views.render_mesh(vertices, mask, size=160, key_light=None)[..., 0].astype(float)
    inside = keyed < 255
    q = 160 // 4
    # The dome's upper left faces up and left, towards the key light; its lower right away.
    assert keyed[q, q] - keyed[3 * q, 3 * q] > 25
    assert abs(head[3 * q, 3 * q] - head[q, q]) < 3  # the headlight: symmetric
    assert keyed[inside].std() > 2 * head[head < 255].std()


def test_large_mesh_renders_in_seconds() -> None:
    h, w = 1000, 1200  # 1.2 megapixels
    rows, cols = np.mgrid[0 : h + 1, 0 : w + 1].astype(float)
    z = 500 + 40 * np.exp(-((cols - w / 2) ** 2 + (rows - h / 2) ** 2) / (2 * 300.0**2))
    vertices = np.stack([cols * 0.1, rows * 0.1, z], axis=-1)
    start = time.perf_counter()
    image = views.render_mesh(vertices, np.ones((h, w), dtype=bool), azimuth=30, elevation=10, size=400)
    assert time.perf_counter() - start < 10
    inside = _silhouette(image)
    assert inside.mean() > 0.3
    # no cracks: every row of the silhouette is one run of pixels
    for row in inside[60:340:20]:
        idx = np.nonzero(row)[0]
        assert idx.size and idx[-1] - idx[0] + 1 == idx.size


def test_repr_html_is_compact(result: nplps.Reconstruction) -> None:
    n = 512
    rng = np.random.default_rng(0)
    big = dataclasses.replace(
        result,
        depth=200 + rng.normal(0, 0.5, (n + 1, n + 1)),
        fit_normals=np.zeros((n, n, 3)),
        albedo=rng.uniform(0, 1, (n, n)),
        residual=np.zeros((n, n)),
        lights_used=np.full((n, n), 27),
        regions=np.zeros((n, n), dtype=int),
        mask=np.ones((n, n), dtype=bool),
    )
    text = big._repr_html_()
    assert len(text) < 200_000
    assert "512 x 512" in text and text.count("<img") == 2
    assert "\n" not in repr(big)


# --------------------------------------------------------------------------------------------------
# the reading of a held-out comparison
# --------------------------------------------------------------------------------------------------


def test_reading_names_the_better_model_and_by_how_much():
    text = reading((0.02, 0.01), (0.05, 0.04))
    assert "\n" not in text
    assert text.startswith("reading: the near-light model (nplps) predicts the held-out images better")
    assert "mean shape error 0.01 vs 0.04 (4.0x lower)" in text and "mean relative error 0.02 vs 0.05" in text
    text = reading((0.05, 0.06), (0.05, 0.03))
    assert text.startswith("reading: the parallel-light baseline predicts") and "(2.0x lower)" in text
    assert "(25x lower)" in reading((0.1, 0.002), (0.1, 0.05))
    assert "about equally well" in reading((0.05, 0.0410), (0.05, 0.0400))
    assert "no comparison" in reading((float("nan"), 0.01), (0.05, 0.04))


def test_a_contact_sheet_made_beforehand_writes_the_same_inputs_png(
    scene: nplps.synth.Scene, result: nplps.Reconstruction, tmp_path: Path
) -> None:
    # The command line makes the sheet, then frees the images before saving (issue 23).
    sheet = nplps.export.ContactSheet.of(scene.images)
    assert sheet.pixels.dtype == np.uint8 and sheet.pixels.ndim == 3 and sheet.pixels.shape[2] == 3
    direct = result.save(tmp_path / "a", inputs=scene.images)["inputs"].read_bytes()
    made = result.save(tmp_path / "b", inputs=sheet)["inputs"].read_bytes()
    assert made == direct
    # Without inputs there is no inputs.png.
    assert "inputs" not in result.save(tmp_path / "c")
