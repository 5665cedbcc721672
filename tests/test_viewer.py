"""The 3-D viewer page (nplps.viewer, ``nplps view``): self-contained, the same mesh, rendered headless."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

import nplps
from nplps import viewer
from nplps.cli import main
from nplps.export import read_ply

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


@pytest.fixture(scope="module")
def result_dir(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, nplps.Reconstruction]:
    scene = nplps.make_scene("bumps", n=40, size=100.0, distance=200.0, seed=0)
    result = nplps.reconstruct(scene.images, scene.rig, mask=scene.mask, depth=200.0)
    out = tmp_path_factory.mktemp("viewer") / "result"
    result.save(out)
    return out, result


@pytest.fixture(scope="module")
def page(result_dir: tuple[Path, nplps.Reconstruction], tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("page") / "viewer.html"
    viewer.write_result_viewer(result_dir[0], out, title="bumps <test>")
    return out


def test_page_is_self_contained(page: Path) -> None:
    text = page.read_text(encoding="utf-8")
    assert not re.search(r"https?://", text)
    assert not re.search(r"<(script|img|link|iframe)[^>]*\s(src|href)=", text, re.I)
    assert "<title>bumps &lt;test&gt;</title>" in text and "<test>" not in text


def test_page_holds_the_mesh_of_the_result(result_dir: tuple[Path, nplps.Reconstruction], page: Path) -> None:
    ply = read_ply(result_dir[0] / "mesh.ply")
    decoded = viewer.read_viewer(page)
    np.testing.assert_array_equal(decoded["positions"], ply["vertices"])
    np.testing.assert_array_equal(decoded["faces"], ply["faces"])
    np.testing.assert_array_equal(decoded["normals"], ply["normals"])
    assert np.abs(decoded["colors"].astype(int) - ply["colors"].astype(int)).max() <= 1
    meta = decoded["meta"]
    assert meta["stride"] == 1 and meta["triangles"] == meta["full_triangles"] == len(ply["faces"])
    assert meta["size"] == "40 x 40 pixels" and meta["units"] == "rig units"


def test_opengl_frame_results_give_the_same_page(
    result_dir: tuple[Path, nplps.Reconstruction], page: Path, tmp_path: Path
) -> None:
    result_dir[1].save(tmp_path / "gl", opengl=True)
    info = viewer.write_result_viewer(tmp_path / "gl")
    assert info.path == tmp_path / "gl" / viewer.VIEWER_FILE
    ours, theirs = viewer.read_viewer(info.path), viewer.read_viewer(page)
    for key in ("positions", "faces", "normals"):
        np.testing.assert_array_equal(ours[key], theirs[key])
    assert ours["meta"]["title"] == "gl"


def test_save_viewer_matches_the_result(result_dir: tuple[Path, nplps.Reconstruction], tmp_path: Path) -> None:
    result = result_dir[1]
    path = result.save_viewer(tmp_path / "v.html", title="api", units="mm")
    decoded = viewer.read_viewer(path)
    ply = read_ply(result_dir[0] / "mesh.ply")
    np.testing.assert_array_equal(decoded["positions"], ply["vertices"])
    np.testing.assert_array_equal(decoded["faces"], ply["faces"])
    assert decoded["meta"]["units"] == "mm" and decoded["meta"]["title"] == "api"


def test_large_meshes_are_decimated_on_a_grid(result_dir: tuple[Path, nplps.Reconstruction], tmp_path: Path) -> None:
    result = result_dir[1]
    info = viewer.write_viewer(tmp_path / "v.html", result.vertices, result.mask, max_triangles=500)
    decoded = viewer.read_viewer(info.path)
    assert info.stride > 1 and 0 < info.triangles <= 500 < info.full_triangles
    assert decoded["meta"]["stride"] == info.stride and len(decoded["faces"]) == info.triangles
    assert decoded["normals"] is None  # computed by the page from the coarse triangles
    # The kept vertices are vertices of the full grid, every stride-th row and column.
    full = result.vertices.reshape(-1, 3).astype(np.float32)
    on_grid = (decoded["positions"][:, None, :] == full[None, :, :]).all(axis=2).any(axis=1)
    assert on_grid.all()
    with pytest.raises(nplps.InputError, match="max_triangles"):
        viewer.write_viewer(tmp_path / "w.html", result.vertices, result.mask, max_triangles=1)


def test_missing_or_mismatched_result_is_a_clear_error(
    result_dir: tuple[Path, nplps.Reconstruction], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(nplps.InputError, match="does not exist"):
        viewer.write_result_viewer(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(nplps.InputError, match=r"not a complete nplps result directory: mesh\.ply and depth\.npy"):
        viewer.write_result_viewer(tmp_path / "empty")
    other = tmp_path / "other"
    shutil.copytree(result_dir[0], other)
    depth = np.load(other / "depth.npy")
    depth[0, :] = 123.0
    np.save(other / "depth.npy", depth)
    with pytest.raises(nplps.InputError, match="do not belong to the same result"):
        viewer.write_result_viewer(other)
    assert main(["view", str(tmp_path / "empty"), "--no-open"]) == 2
    assert "not a complete nplps result directory" in capsys.readouterr().err


def test_cli_writes_the_page_and_opens_it_only_with_a_display(
    result_dir: tuple[Path, nplps.Reconstruction],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    opened: list[str] = []
    monkeypatch.setattr("webbrowser.open", lambda url: opened.append(url) or True)
    out = tmp_path / "page.html"
    assert main(["view", str(result_dir[0]), "--out", str(out), "--no-open", "--max-triangles", "1000"]) == 0
    text = capsys.readouterr().out
    assert out.is_file() and not opened
    assert f"viewer written: {out}" in text and "decimated on a grid of stride" in text
    assert out.resolve().as_uri() in text
    monkeypatch.setenv("CI", "true")
    assert main(["view", str(result_dir[0]), "--out", str(out)]) == 0
    assert not opened and "open it in a web browser" in capsys.readouterr().out
    monkeypatch.setenv("CI", "false")
    monkeypatch.setenv("DISPLAY", ":0")
    assert main(["view", str(result_dir[0]), "--out", str(out)]) == 0
    assert opened == [out.resolve().as_uri()]
    assert "open it in a web browser" not in capsys.readouterr().out
    assert main(["view", str(result_dir[0]), "--max-triangles", "1", "--no-open"]) == 2


def test_the_page_in_the_result_directory_is_in_its_manifest(
    result_dir: tuple[Path, nplps.Reconstruction], tmp_path: Path
) -> None:
    directory = tmp_path / "result"
    result_dir[1].save(directory)
    assert main(["view", str(directory), "--no-open"]) == 0
    manifest = json.loads((directory / "nplps-manifest.json").read_text())["files"]
    assert "viewer.html" in manifest
    result_dir[1].save(directory, overwrite=True)  # a new result removes the old page
    assert not (directory / "viewer.html").exists()


# --------------------------------------------------------------------------------------------------
# Headless rendering
# --------------------------------------------------------------------------------------------------


def _browser() -> str:
    for name in BROWSERS:
        found = shutil.which(name)
        if found:
            return found
    pytest.skip("no Chromium for the headless render (apt-get install chromium)")


def _chromium(browser: str, profile: Path, url: str, *args: str) -> subprocess.CompletedProcess[bytes]:
    command = [
        browser,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
        "--no-first-run",
        f"--user-data-dir={profile}",
        "--window-size=480,360",
        "--virtual-time-budget=5000",
        *args,
        url,
    ]
    return subprocess.run(command, capture_output=True, timeout=60, check=False)


def _status(browser: str, profile: Path, url: str) -> str:
    dom = _chromium(browser, profile, url, "--dump-dom").stdout.decode("utf-8", "replace")
    found = re.search(r'<html[^>]* data-status="([^"]*)"', dom)
    assert found, dom[:500]
    return found.group(1)


def _screenshot(browser: str, profile: Path, url: str, png: Path) -> np.ndarray:
    done = _chromium(browser, profile, url, f"--screenshot={png}")
    assert png.is_file(), done.stderr.decode("utf-8", "replace")[-2000:]
    return nplps.io.read_image(png)[..., :3] / 255.0


def test_headless_chromium_renders_the_mesh(page: Path, tmp_path: Path) -> None:
    browser = _browser()
    profile = tmp_path / "profile"
    url = page.resolve().as_uri()
    assert _status(browser, profile, url) == "ready"
    background = np.array([0.125, 0.14, 0.165])
    views = []
    for name, view in (("a", "azimuth=35&elevation=25"), ("b", "azimuth=-50&elevation=-10&mode=shaded")):
        image = _screenshot(browser, profile, f"{url}#{view}&ui=0", tmp_path / f"{name}.png")
        assert image.shape[:2] == (360, 480)
        foreground = np.abs(image - background).max(axis=2) > 0.04
        assert 0.05 < foreground.mean() < 0.9, foreground.mean()
        grey = image.mean(axis=2)[foreground]
        assert grey.std() > 0.03 and grey.max() - grey.min() > 0.2  # shaded, not a flat silhouette
        views.append(image)
    assert np.abs(views[0] - views[1]).mean() > 0.02  # the two views differ


INTERACTION = """<script>
(function () {
  var c = document.getElementById("view");
  function ev(type, x, y, extra) {
    var init = { clientX: x, clientY: y, pointerId: 7, button: 0, bubbles: true };
    c.dispatchEvent(new PointerEvent(type, Object.assign(init, extra || {})));
  }
  ev("pointerdown", 200, 200); ev("pointermove", 260, 230); ev("pointerup", 260, 230);  // rotate
  ev("pointerdown", 200, 200, { shiftKey: true }); ev("pointermove", 215, 190); ev("pointerup", 215, 190);  // pan
  ev("pointerdown", 200, 200, { altKey: true }); ev("pointermove", 150, 150); ev("pointerup", 150, 150);  // light
  c.dispatchEvent(new WheelEvent("wheel", { deltaY: -120, bubbles: true, cancelable: true }));  // zoom
  window.dispatchEvent(new KeyboardEvent("keydown", { key: "3" }));  // normals
  if (location.hash.indexOf("reset") >= 0) window.dispatchEvent(new KeyboardEvent("keydown", { key: "r" }));
})();
</script>
</body>"""


def test_headless_chromium_mouse_keys_and_reset(page: Path, tmp_path: Path) -> None:
    browser = _browser()
    profile = tmp_path / "profile"
    interactive = tmp_path / "interactive.html"
    interactive.write_text(page.read_text(encoding="utf-8").replace("</body>", INTERACTION), encoding="utf-8")
    url = interactive.resolve().as_uri()
    assert _status(browser, profile, url) == "ready"  # no error in the handlers
    before = _screenshot(browser, profile, page.resolve().as_uri() + "#ui=0", tmp_path / "before.png")
    moved = _screenshot(browser, profile, url + "#ui=0", tmp_path / "moved.png")
    reset = _screenshot(browser, profile, url + "#ui=0&reset", tmp_path / "reset.png")
    assert np.abs(moved - before).mean() > 0.02
    assert np.abs(reset - before).max() < 0.02


def test_headless_chromium_page_reports_errors(page: Path, tmp_path: Path) -> None:
    browser = _browser()
    broken = tmp_path / "broken.html"
    text = page.read_text(encoding="utf-8")
    broken.write_text(re.sub(r'"indices":"[^"]*"', '"indices":"!!"', text), encoding="utf-8")
    status = _status(browser, tmp_path / "profile", broken.resolve().as_uri())
    assert status.startswith("error: "), status


def test_can_open_browser(monkeypatch: pytest.MonkeyPatch) -> None:
    from nplps.cli.view import can_open_browser

    monkeypatch.setenv("CI", "true")
    assert not can_open_browser()
    monkeypatch.delenv("CI")
    if os.sys.platform.startswith("linux"):
        monkeypatch.delenv("DISPLAY", raising=False)
        monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
        assert not can_open_browser()
        monkeypatch.setenv("WAYLAND_DISPLAY", "wayland-0")
        assert can_open_browser()
