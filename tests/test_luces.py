"""LUCES loader and ``nplps benchmark luces`` on synthetic captures written in LUCES's layout.

No copy of LUCES is used: :func:`write_luces_object` renders a scene with 52 LEDs (``nplps.render``)
and writes it as LUCES stores an object (see docs/luces.md): ``led_params.txt``, ``01.png`` ..
``52.png`` (16-bit RGB), ``mask.png``, ``normals.png`` (16-bit RGB, x right, y up, z towards the
camera, ``v = (n + 1) / 2 * 65535``, white background) and ``zgt.npz`` (``zgt``, mm). The writer
encodes the ground truth from the documented convention on its own (not with the loader's
decoder), so a frame or sign error on either side shows as a large error.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

import nplps
from nplps import export
from nplps.captures import load_luces
from nplps.captures.luces import decode_normals, find_luces_objects, read_led_params
from nplps.cli import main
from nplps.errors import InputError, RigError

K_LEDS = 52


def _leds(distance: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """52 LEDs on a 7 x 8 grid (corners left out) in the plane z = 10 mm, aimed at the object."""
    xs, ys = np.meshgrid(np.linspace(-90, 90, 8), np.linspace(-75, 75, 7))
    keep = np.ones(xs.shape, dtype=bool)
    keep[[0, 0, -1, -1], [0, -1, 0, -1]] = False
    positions = np.stack([xs[keep], ys[keep], np.full(K_LEDS, 10.0)], axis=1)
    target = np.array([0.0, 0.0, distance]) + rng.normal(0, 5.0, (K_LEDS, 3))
    axes = target - positions
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    mu = rng.uniform(0.0, 1.5, K_LEDS)
    phi = rng.uniform(0.8, 1.2, (K_LEDS, 3))
    return positions, axes, mu, phi


def write_luces_object(
    folder: Path,
    *,
    seed: int = 0,
    n: int = 64,
    scene: str = "bumps",
    flip_normal_y: bool = False,
    phi_columns: int = 3,
    noise: float = 0.0,
) -> dict:
    """Write a synthetic object in LUCES's layout; return its truth (normals, depth, K, rig)."""
    rng = np.random.default_rng(seed)
    base = nplps.make_scene(scene, n=n, camera="pinhole", rgb=True, seed=seed)
    distance = base.mean_depth
    positions, axes, mu, phi = _leds(distance, rng)
    if phi_columns == 1:
        phi = np.repeat(phi[:, :1], 3, axis=1)
    K = np.asarray(base.rig.K, dtype=float)
    rig = nplps.Rig.pinhole(K, lights=positions, axes=axes, mu=mu, intensities=phi)
    images = nplps.render(base.depth, rig, base.albedo, mask=base.mask)
    if noise > 0:  # Gaussian noise, a fraction of the brightest value
        images = np.clip(images + rng.normal(0.0, noise * images.max(), images.shape), 0.0, None)
    scale = 60000.0 / images.max()
    folder.mkdir(parents=True)
    for i, image in enumerate(images):
        export.write_png16(folder / f"{i + 1:02d}.png", np.rint(image * scale).astype(np.uint16))
    export.write_png8(folder / "mask.png", base.mask.astype(np.uint8) * 255)
    # Ground truth as LUCES stores it: normals in x right, y up, z towards the camera.
    truth = base.normals
    stored = truth * np.array([1.0, -1.0, -1.0])
    if flip_normal_y:
        stored[..., 1] *= -1  # a writer with the wrong frame
    pixels = np.rint((stored + 1.0) / 2.0 * 65535.0)
    pixels[~base.mask] = 65535  # LUCES's white background
    export.write_png16(folder / "normals.png", np.clip(pixels, 0, 65535).astype(np.uint16))
    v = base.depth
    z = 0.25 * (v[:-1, :-1] + v[:-1, 1:] + v[1:, :-1] + v[1:, 1:])
    np.savez(folder / "zgt.npz", zgt=np.where(base.mask, z, 0.0), zgt_int=np.zeros_like(z))
    lines = ["N_img nrows ncols f x0 y0 mean_distance sfull:[Lpos Ldir Phi mu 0]"]
    lines.append(f"{K_LEDS} {n} {n} {K[0, 0]:.6f} {K[0, 2]:.6f} {K[1, 2]:.6f} {distance:.4f}")
    for i in range(K_LEDS):
        values = [*positions[i], *axes[i], *(phi[i] if phi_columns == 3 else phi[i, :1]), mu[i], 0.0]
        lines.append(" ".join(f"{x:.6f}" for x in values))
    (folder / "led_params.txt").write_text("\n".join(lines) + "\n")
    return {"normals": truth, "depth": z, "mask": base.mask, "K": K, "rig": rig, "phi": phi, "distance": distance}


def test_led_params_and_ground_truth_round_trip(tmp_path: Path) -> None:
    truth = write_luces_object(tmp_path / "Bumps", seed=3)
    p = read_led_params(tmp_path / "Bumps" / "led_params.txt")
    assert p.n_images == K_LEDS and (p.rows, p.cols) == (64, 64)
    np.testing.assert_allclose(p.positions, truth["rig"].positions, atol=1e-6)
    np.testing.assert_allclose(p.directions, truth["rig"].axes, atol=1e-5)
    np.testing.assert_allclose(p.mu, truth["rig"].mu, atol=1e-6)

    cap = load_luces(tmp_path / "Bumps", load=True)
    assert cap.images.shape == (K_LEDS, 64, 64, 3)
    assert cap.levels == 65535
    np.testing.assert_allclose(cap.K, truth["K"], atol=1e-6)
    np.testing.assert_allclose(cap.intensities, truth["phi"], atol=1e-6)
    np.testing.assert_array_equal(cap.mask, truth["mask"])
    m = truth["mask"]
    # 16-bit quantization: the decoded normals are within 1e-4 of the true ones, facing the camera.
    assert np.max(np.abs(cap.normals_gt[m] - truth["normals"][m])) < 1e-4
    assert np.all(cap.normals_gt[m][:, 2] < 0)
    assert np.all(cap.normals_gt[~m] == 0)
    np.testing.assert_allclose(cap.depth_gt[m], truth["depth"][m], rtol=1e-12)
    assert np.all(np.isnan(cap.depth_gt[~m]))
    assert cap.mean_distance == pytest.approx(truth["distance"], abs=1e-4)
    rig = cap.rig()
    np.testing.assert_allclose(rig.positions, truth["rig"].positions, atol=1e-6)


def test_subset_grey_and_one_phi(tmp_path: Path) -> None:
    write_luces_object(tmp_path / "A", seed=1, n=32, phi_columns=1)
    cap = load_luces(tmp_path / "A", lights=[0, 5, 51], color=False, load=True)
    assert cap.images.shape == (3, 32, 32)
    assert cap.intensities.shape == (3,)
    assert [f.name for f in cap.files] == ["01.png", "06.png", "52.png"]
    one = load_luces(tmp_path / "A", one_based=True)
    np.testing.assert_allclose(one.K[:2, 2], cap.K[:2, 2] - 1.0)


def test_decode_normals_frame() -> None:
    # x right, y up, z towards the camera in the file -> (x, -y, -z) in the camera frame.
    a = round((1 + 0.5**0.5) / 2 * 65535)  # (1/sqrt(2) + 1) / 2 in 16 bits
    pixels = np.array([[[a, 32768, a], [32768, 65535, 32768], [65535, 65535, 65535]]], dtype=np.uint16)
    n = decode_normals(pixels)
    np.testing.assert_allclose(n[0, 0], [0.5**0.5, 0, -(0.5**0.5)], atol=1e-4)
    np.testing.assert_allclose(n[0, 1], [0, -1, 0], atol=1e-4)
    np.testing.assert_array_equal(n[0, 2], [0, 0, 0])  # white background


def test_malformed_files_are_named(tmp_path: Path) -> None:
    write_luces_object(tmp_path / "A", n=16)
    params = tmp_path / "A" / "led_params.txt"
    text = params.read_text().splitlines()
    params.write_text("\n".join(text[:-1]) + "\n")
    with pytest.raises(RigError, match="52 images but 51 LED lines"):
        load_luces(tmp_path / "A")
    params.write_text("\n".join([*text[:5], "1 2 3", *text[6:]]) + "\n")
    with pytest.raises(RigError, match="line 6:"):
        load_luces(tmp_path / "A")
    params.write_text("\n".join(text) + "\n")
    (tmp_path / "A" / "07.png").unlink()
    with pytest.raises(InputError, match=r"07\.png"):
        load_luces(tmp_path / "A")
    with pytest.raises(InputError, match="no LUCES object"):
        find_luces_objects(tmp_path / "A", ["Nope"])


def _benchmark(tmp_path: Path, data: Path, *extra: str, capsys: pytest.CaptureFixture[str]) -> tuple[int, dict, str]:
    out = tmp_path / "bench"
    status = main(["benchmark", "luces", str(data), "--out", str(out), "-q", *extra])
    printed = capsys.readouterr().out
    record = json.loads((out / "luces_benchmark.json").read_text())
    return status, record, printed


def _table(printed: str) -> dict[str, list[str]]:
    """The table's rows by object name (the lines before the published numbers)."""
    lines = printed.split("\n\n")[0].splitlines()
    assert lines[0].split()[:2] == ["object", "pixels"]
    return {line.split()[0]: line.split()[1:] for line in lines[1:]}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_benchmark_prints_small_errors_on_a_synthetic_capture(
    tmp_path: Path, seed: int, capsys: pytest.CaptureFixture[str]
) -> None:
    data = tmp_path / "data"
    write_luces_object(data / "Bumps", seed=seed)
    write_luces_object(data / "Sphere", seed=seed, scene="sphere")
    status, record, printed = _benchmark(tmp_path, data, capsys=capsys)
    assert status == 0
    table = _table(printed)
    assert set(table) == {"Bumps", "Sphere", "mean"}
    for name in ("Bumps", "Sphere"):
        mean_deg, median_deg, rms_mm, abs_mm = (float(x) for x in table[name][1:5])
        assert mean_deg < 0.2 and median_deg <= mean_deg + 1e-9
        assert rms_mm < 0.05 and abs_mm <= rms_mm + 1e-9
    row = {r["object"]: r for r in record["objects"]}
    assert row["Bumps"]["mean_deg"] == pytest.approx(float(table["Bumps"][1]), abs=1e-3)
    assert "FastNFPS" in printed and "11.3" in printed and "9.4" in printed
    rows = list(csv.DictReader((tmp_path / "bench" / "luces_benchmark.csv").open()))
    assert [r["object"] for r in rows] == ["Bumps", "Sphere", "mean"]


def test_benchmark_catches_a_wrong_ground_truth_frame(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_luces_object(tmp_path / "data" / "Bumps", seed=0, flip_normal_y=True)
    status, _, printed = _benchmark(tmp_path, tmp_path / "data", capsys=capsys)
    assert status == 0
    assert float(_table(printed)["Bumps"][1]) > 5.0


def test_benchmark_binning_and_objects(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = tmp_path / "data"
    write_luces_object(data / "Bumps", seed=4, n=96)
    write_luces_object(data / "Other", seed=5, n=32)
    status, record, printed = _benchmark(tmp_path, data, "--bin", "2", "--objects", "bumps", capsys=capsys)
    assert status == 0
    table = _table(printed)
    assert set(table) == {"Bumps", "mean"}
    assert float(table["Bumps"][1]) < 2.0
    assert record["bin"] == 2 and "compare with care" in printed


def test_capture_luces_on_the_command_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    truth = write_luces_object(tmp_path / "Bumps", seed=6, n=48)
    out = tmp_path / "rec"
    status = main(["reconstruct", "--capture", "luces", str(tmp_path / "Bumps"), "--depth", "200", "--out", str(out)])
    assert status == 0
    assert "mean distance" in capsys.readouterr().err
    normals = np.load(out / "normals.npy")
    m = truth["mask"]
    dot = np.clip(np.sum(normals[m] * truth["normals"][m], axis=-1), -1, 1)
    assert np.degrees(np.arccos(dot)).mean() < 0.2
    summary = json.loads((out / "summary.json").read_text())
    assert "vignetting" not in json.dumps(summary.get("preprocessing", ""))


def test_image_size_is_checked_against_led_params(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_luces_object(tmp_path / "A", n=16)
    params = tmp_path / "A" / "led_params.txt"
    lines = params.read_text().splitlines()
    head = lines[1].split()
    params.write_text("\n".join([lines[0], " ".join([head[0], "16", "20", *head[3:]]), *lines[2:]]) + "\n")
    with pytest.raises(InputError, match="says nrows 16, ncols 20"):
        load_luces(tmp_path / "A")
    assert main(["benchmark", "luces", str(tmp_path), "--objects", "B", "--out", str(tmp_path / "o")]) == 2
    assert "no LUCES object B" in capsys.readouterr().err
    # A broken object folder fails alone: its row reads nan, the others run, exit status 1.
    write_luces_object(tmp_path / "B", n=16, seed=2)
    assert main(["benchmark", "luces", str(tmp_path), "--out", str(tmp_path / "o"), "-q"]) == 1
    printed = capsys.readouterr()
    table = _table(printed.out)
    assert table["A"][1] == "nan" and float(table["B"][1]) < 1.0  # 16 x 16 bumps: coarse
    assert "object A: " in printed.err and "nrows 16, ncols 20" in printed.err


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_benchmark_with_image_noise(tmp_path: Path, seed: int, capsys: pytest.CaptureFixture[str]) -> None:
    # 0.5 % Gaussian noise (measured: about 0.1 degrees and 0.004 mm at 96 x 96 over seeds 0-2).
    write_luces_object(tmp_path / "data" / "Bumps", seed=seed, noise=0.005)
    status, record, _ = _benchmark(tmp_path, tmp_path / "data", capsys=capsys)
    assert status == 0
    (row,) = record["objects"]
    assert 0.01 < row["mean_deg"] < 0.4 and row["depth_rms_mm"] < 0.05
