"""Tests of nplps.captures: near_ps (.mat), DiLiGenT and plain-folder loaders.

Synthetic datasets are written to ``tmp_path``. The real captures under ``../shared/data``
(relative to the project root) are read in place, never copied; their tests skip when the
folder is absent.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import textwrap
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import png
import pytest

scipy_io = pytest.importorskip("scipy.io")

from nplps import captures as cap  # noqa: E402
from nplps import preprocess as pp  # noqa: E402
from nplps.errors import InputError, RigError  # noqa: E402


def _write_png16_rgb(path: Path, pixels: np.ndarray) -> None:
    h, w, _ = pixels.shape
    png.from_array(pixels.reshape(h, w * 3).tolist(), "RGB;16").save(str(path))


# --------------------------------------------------------------------------------------------------
# K conventions
# --------------------------------------------------------------------------------------------------


def test_standardize_K_one_based_and_transposed() -> None:
    K1 = np.array([[1000.0, 0.0, 321.0], [0.0, 1010.0, 241.0], [0.0, 0.0, 1.0]])
    K0 = cap.standardize_K(K1)
    np.testing.assert_allclose(K0, [[1000, 0, 320], [0, 1010, 240], [0, 0, 1]])
    np.testing.assert_allclose(cap.standardize_K(K1.T), K0)  # MATLAB IntrinsicMatrix form
    np.testing.assert_allclose(cap.standardize_K(K1, one_based=False), K1)
    skewed = K1.copy()
    skewed[0, 1] = 3.0
    np.testing.assert_allclose(cap.standardize_K(skewed.T)[0, 1], 3.0)
    with pytest.raises(RigError, match="pinhole"):
        cap.standardize_K(np.eye(3) + 1)
    with pytest.raises(RigError, match="focal"):
        cap.standardize_K(np.diag([-1.0, 1.0, 1.0]))
    with pytest.raises(RigError):
        cap.standardize_K(np.eye(2))


# --------------------------------------------------------------------------------------------------
# Synthetic near_ps folder
# --------------------------------------------------------------------------------------------------


def _near_ps_folder(folder: Path, k: int = 4, transposed: bool = True, phi_cols: int = 1, shape=(6, 8)) -> dict:
    folder.mkdir(exist_ok=True)
    K1 = np.array([[500.0, 0.0, 4.5], [0.0, 505.0, 3.5], [0.0, 0.0, 1.0]])  # 1-based
    scipy_io.savemat(folder / "camera.mat", {"K": K1.T if transposed else K1})
    rng = np.random.default_rng(0)
    S = np.column_stack([rng.uniform(-90, 90, k), rng.uniform(-90, 90, k), np.full(k, 75.0)])
    Dir = -S + np.array([0.0, 0.0, 200.0])
    Dir = 2.0 * Dir / np.linalg.norm(Dir, axis=1, keepdims=True)  # not unit on purpose
    Phi = rng.uniform(1e6, 4e6, (k, phi_cols))
    mu = np.ones((k, 1), dtype=np.uint8)
    scipy_io.savemat(folder / "light.mat", {"S": S, "Dir": Dir, "Phi": Phi, "mu": mu})
    h, w = shape
    for i in range(k):
        iio.imwrite(folder / f"img_{i + 1}.png", np.full((h, w), 10 * (i + 1), dtype=np.uint8))
    iio.imwrite(folder / "img_ambient.png", np.full((h, w), 3, dtype=np.uint8))
    mask = np.zeros((h, w, 3), dtype=np.uint8)
    mask[1:4, 2:6, 0] = 255
    iio.imwrite(folder / "img_mask.png", mask)
    return {"K1": K1, "S": S, "Dir": Dir, "Phi": Phi}


def test_near_ps_transposed_K_and_lights(tmp_path: Path) -> None:
    truth = _near_ps_folder(tmp_path / "c", k=4, transposed=True)
    c = cap.load_near_ps(tmp_path / "c")
    np.testing.assert_allclose(c.K, [[500, 0, 3.5], [0, 505, 2.5], [0, 0, 1]])
    np.testing.assert_allclose(c.positions, truth["S"])
    np.testing.assert_allclose(c.directions, truth["Dir"] / 2.0)
    np.testing.assert_allclose(np.linalg.norm(c.directions, axis=1), 1.0)
    assert c.intensities.shape == (4,)
    np.testing.assert_allclose(c.intensities, truth["Phi"][:, 0])
    np.testing.assert_array_equal(c.mu, 1.0)
    assert c.mu.dtype == np.float64 and not c.directional
    assert [p.name for p in c.images] == ["img_1.png", "img_2.png", "img_3.png", "img_4.png"]
    assert c.ambient == tmp_path / "c" / "img_ambient.png"
    assert c.mask.shape == (6, 8) and c.mask.sum() == 12 and c.mask[1:4, 2:6].all()
    assert c.distortion is None and c.normals_gt is None and c.name == "c"


def test_near_ps_standard_K_light_selection_and_load(tmp_path: Path) -> None:
    truth = _near_ps_folder(tmp_path / "c", k=5, transposed=False, phi_cols=3)
    with pytest.raises(InputError, match=r"5 image files .* but 3 lights"):
        cap.load_near_ps(tmp_path / "c", lights=[0, 2, 4])
    files = ["img_1.png", "img_4.png", "img_5.png"]
    c = cap.load_near_ps(tmp_path / "c", files, lights=[0, 3, 4], load=True)
    np.testing.assert_allclose(c.K[:2, 2], [3.5, 2.5])
    np.testing.assert_allclose(c.positions, truth["S"][[0, 3, 4]])
    assert c.intensities.shape == (3, 3)
    np.testing.assert_allclose(c.intensities, truth["Phi"][[0, 3, 4]])
    assert c.images.dtype == np.float32 and c.images.shape == (3, 6, 8)
    np.testing.assert_allclose(c.images[:, 0, 0], np.array([10, 40, 50]) / 255, rtol=1e-6)
    np.testing.assert_allclose(c.ambient, 3 / 255, rtol=1e-6)
    gray = cap.load_near_ps(tmp_path / "c", files, lights=[0, 3, 4], color=False)
    np.testing.assert_allclose(gray.intensities, truth["Phi"][[0, 3, 4]].mean(axis=1))
    with pytest.raises(InputError, match="out of range"):
        cap.load_near_ps(tmp_path / "c", files, lights=[0, 3, 5])


def test_near_ps_glob_natural_order_and_errors(tmp_path: Path) -> None:
    _near_ps_folder(tmp_path / "c", k=12, shape=(2, 2))
    c = cap.load_near_ps(tmp_path / "c", "img_[0-9]*.png", mask=None, ambient=None)
    assert [p.name for p in c.images][:3] == ["img_1.png", "img_2.png", "img_3.png"]
    assert c.images[-1].name == "img_12.png" and c.mask is None and c.ambient is None
    with pytest.raises(RigError, match="not found"):
        cap.load_near_ps(tmp_path / "c", camera_file="missing.mat")
    scipy_io.savemat(tmp_path / "c" / "bad.mat", {"S": np.zeros((12, 3))})
    with pytest.raises(RigError, match="no variable 'Dir'"):
        cap.load_near_ps(tmp_path / "c", light_file="bad.mat")
    with pytest.raises(InputError, match="does not exist"):
        cap.load_near_ps(tmp_path / "nowhere")


def test_near_ps_srgb_binning_and_grid(tmp_path: Path) -> None:
    # A JPEG-like 8-bit sRGB RGB render at twice the calibration resolution, 2 rows and 3
    # columns short of the calibration grid after 2 x 2 binning.
    folder = tmp_path / "c"
    _near_ps_folder(folder, k=2, shape=(6, 8))  # the calibration grid: 6 x 8 (mask)
    rng = np.random.default_rng(1)
    renders = rng.integers(0, 256, (2, 8, 10, 3), dtype=np.uint8)
    names = []
    for i, r in enumerate(renders):
        names.append(f"jpg_{i + 1}.png")
        iio.imwrite(folder / names[-1], r)
    c = cap.load_near_ps(folder, names, srgb=True, bin_factor=2, grid_shape=(6, 8), color=False, ambient=None)
    assert c.images.shape == (2, 6, 8) and c.images.dtype == np.float32
    lin = pp.srgb_to_linear(renders.astype(np.float64) / 255).mean(axis=3)
    expected = pp.pad_or_crop(pp.bin_images(lin, 2), (6, 8))
    np.testing.assert_allclose(c.images, expected, rtol=1e-5, atol=1e-7)
    assert np.all(c.images[:, 4:] == 0) and np.all(c.images[:, :, 5:] == 0)
    seen: list[tuple[int, int, str]] = []
    colour = cap.load_near_ps(
        folder, names, srgb=True, bin_factor=2, grid_shape=(6, 8), progress=lambda *a: seen.append(a)
    )
    assert seen == [(1, 2, "jpg_1.png"), (2, 2, "jpg_2.png")]  # load progress, once per image
    assert colour.images.shape == (2, 6, 8, 3)
    np.testing.assert_allclose(colour.images.mean(axis=3), c.images, rtol=1e-5, atol=1e-7)
    with pytest.raises(InputError, match="mask has shape"):
        cap.load_near_ps(folder, names, srgb=True, bin_factor=2)  # 4 x 5 images, 6 x 8 mask


# --------------------------------------------------------------------------------------------------
# Synthetic DiLiGenT folder
# --------------------------------------------------------------------------------------------------


def _diligent_folder(root: Path, k: int = 3, h: int = 5, w: int = 6) -> dict:
    obj = root / "toyPNG"
    obj.mkdir(parents=True)
    rng = np.random.default_rng(2)
    images = rng.integers(0, 65536, (k, h, w, 3), dtype=np.uint16)
    names = [f"{i + 1:03d}.png" for i in range(k)]
    for name, img in zip(names, images, strict=True):
        _write_png16_rgb(obj / name, img)
    (obj / "filenames.txt").write_text("\n".join(names) + "\n")
    dirs = rng.normal(size=(k, 3))
    dirs[:, 2] = np.abs(dirs[:, 2]) + 1  # towards the viewer: z > 0 in DiLiGenT's frame
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    np.savetxt(obj / "light_directions.txt", dirs, fmt="%.6f")
    ints = rng.uniform(0.5, 2.5, (k, 3))
    np.savetxt(obj / "light_intensities.txt", ints, fmt="%.4f")
    mask = np.zeros((h, w), dtype=np.uint8)
    mask[1:4, 1:5] = 255
    iio.imwrite(obj / "mask.png", np.stack([mask] * 3, axis=-1))
    normals = np.zeros((h, w, 3))
    normals[mask > 0] = [0.6, 0.0, 0.8]  # DiLiGenT frame: facing the viewer (z > 0)
    normals[2, 2] = [0.0, 0.6, 0.8]  # pointing up
    scipy_io.savemat(obj / "Normal_gt.mat", {"Normal_gt": normals})
    return {"obj": obj, "images": images, "dirs": dirs, "ints": ints, "normals": normals}


def test_diligent_frame_conversion(tmp_path: Path) -> None:
    t = _diligent_folder(tmp_path)
    for folder in (t["obj"], tmp_path):  # the object folder or its parent
        c = cap.load_diligent(folder)
        assert c.directional and c.name == "toy" and c.K is None and c.positions is None
        assert [p.name for p in c.images] == ["001.png", "002.png", "003.png"]
        np.testing.assert_allclose(c.directions, t["dirs"] * [1, -1, -1], atol=1e-6)
        assert np.all(c.directions[:, 2] < 0)  # lights on the camera side
        np.testing.assert_allclose(c.intensities, t["ints"], atol=1e-4)
        np.testing.assert_allclose(c.normals_gt, t["normals"] * [1, -1, -1])
        assert np.all(c.normals_gt[c.mask][:, 2] < 0)
        np.testing.assert_allclose(c.normals_gt[2, 2], [0.0, -0.6, -0.8])  # up = -y
        assert not np.signbit(c.normals_gt[~c.mask]).any()  # zeros, not -0.0
        assert c.mask.sum() == 12


def test_diligent_load_keeps_16_bits_and_selects(tmp_path: Path) -> None:
    t = _diligent_folder(tmp_path)
    c = cap.load_diligent(tmp_path, load=True, lights=[2, 0])
    assert c.images.shape == (2, 5, 6, 3) and c.images.dtype == np.float32
    np.testing.assert_allclose(c.images, t["images"][[2, 0]] / 65535.0, rtol=1e-6)
    np.testing.assert_allclose(c.directions, t["dirs"][[2, 0]] * [1, -1, -1], atol=1e-6)
    g = cap.load_diligent(tmp_path, load=True, color=False, lights=[1], normals=False)
    assert g.images.shape == (1, 5, 6) and g.intensities.shape == (1,)
    assert g.normals_gt is None
    np.testing.assert_allclose(g.images[0], t["images"][1].mean(axis=2) / 65535.0, rtol=1e-5)
    K = np.array([[3772.0, 0, 304.875], [0, 3759.0, 254.875], [0, 0, 1]])
    np.testing.assert_array_equal(cap.load_diligent(tmp_path, K=K).K, K)


def test_diligent_inconsistent_files(tmp_path: Path) -> None:
    t = _diligent_folder(tmp_path)
    (t["obj"] / "filenames.txt").write_text("001.png\n002.png\n")
    with pytest.raises(InputError, match="2 file names, 3 light directions"):
        cap.load_diligent(t["obj"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="not a DiLiGenT"):
        cap.load_diligent(tmp_path / "empty")


# --------------------------------------------------------------------------------------------------
# Plain folder and the Capture record
# --------------------------------------------------------------------------------------------------


def test_load_folder(tmp_path: Path) -> None:
    (tmp_path / "rig.json").write_text(json.dumps({"note": "not parsed by the loader"}))
    for name, value in [("img10.png", 10), ("img2.png", 2), ("img1.png", 1)]:
        iio.imwrite(tmp_path / name, np.full((3, 4), value, dtype=np.uint8))
    iio.imwrite(tmp_path / "ambient.png", np.full((3, 4), 1, dtype=np.uint8))
    mask = np.zeros((3, 4), dtype=np.uint8)
    mask[1, 1:3] = 255
    iio.imwrite(tmp_path / "mask.png", mask)
    (tmp_path / "notes.txt").write_text("ignored")
    c = cap.load_folder(tmp_path)
    assert c.rig_path == tmp_path / "rig.json"
    assert [p.name for p in c.images] == ["img1.png", "img2.png", "img10.png"]
    assert c.ambient == tmp_path / "ambient.png" and c.mask.sum() == 2
    assert c.K is None and c.positions is None
    loaded = cap.load_folder(tmp_path, load=True)
    np.testing.assert_allclose(loaded.images[:, 0, 0], np.array([1, 2, 10]) / 255, rtol=1e-6)
    np.testing.assert_allclose(loaded.ambient, 1 / 255, rtol=1e-6)
    (tmp_path / "rig.json").unlink()
    with pytest.raises(RigError, match="rig file"):
        cap.load_folder(tmp_path)


def test_capture_select_and_load(tmp_path: Path) -> None:
    _near_ps_folder(tmp_path / "c", k=4)
    c = cap.load_near_ps(tmp_path / "c")
    sub = c.select([3, 1])
    assert [p.name for p in sub.images] == ["img_4.png", "img_2.png"]
    np.testing.assert_allclose(sub.positions, c.positions[[3, 1]])
    np.testing.assert_allclose(sub.intensities, c.intensities[[3, 1]])
    loaded = sub.load()
    assert loaded.loaded and not sub.loaded
    np.testing.assert_allclose(loaded.images[:, 0, 0], np.array([40, 20]) / 255, rtol=1e-6)
    assert loaded.select([1]).images.shape == (1, 6, 8)
    with pytest.raises(InputError, match="out of range"):
        c.select([4])


def test_prepare_copies_a_given_stack_once_unless_overwrite(tmp_path: Path) -> None:
    _near_ps_folder(tmp_path / "c", k=4)
    c = cap.load_near_ps(tmp_path / "c")
    from_files = cap.prepare(c)  # loaded here: corrected in place
    stack = c.load().images
    given = stack.copy()

    copied = cap.prepare(dataclasses.replace(c, images=given))
    np.testing.assert_array_equal(given, stack)  # the caller's array is left alone
    np.testing.assert_array_equal(copied.images, from_files.images)

    overwritten = cap.prepare(dataclasses.replace(c, images=given), overwrite=True)
    assert np.shares_memory(overwritten.images, given)
    np.testing.assert_array_equal(given, from_files.images)


# --------------------------------------------------------------------------------------------------
# Real captures (../shared/data)
# --------------------------------------------------------------------------------------------------


def test_real_hehe12(shared_capture) -> None:
    folder = shared_capture("hehe12")
    start = time.perf_counter()
    c = cap.load_hehe12(folder, load=True)
    elapsed = time.perf_counter() - start
    assert c.images.shape == (8, 1200, 1920) and c.images.dtype == np.float32
    assert [p.name for p in c.files] == [f"photometric_sample_raw_000{i}.png" for i in range(1, 9)]
    # Dim 8-bit images: maxima 51..137 of 255.
    assert 0.15 < c.images.max() < 0.6 and c.images.min() == 0.0
    assert c.ambient.shape == (1200, 1920) and c.ambient.max() <= 3 / 255 + 1e-7
    # camera.mat stores K transposed; 1-based -> 0-based.
    np.testing.assert_allclose(c.K[2], [0, 0, 1])
    assert c.K[0, 0] == pytest.approx(3043.08, abs=0.01)
    assert c.K[1, 1] == pytest.approx(3026.46, abs=0.01)
    assert c.K[0, 2] == pytest.approx(969.607, abs=1e-3)
    assert c.K[1, 2] == pytest.approx(761.657, abs=1e-3)
    assert 0 < c.K[0, 2] < 1919 and 0 < c.K[1, 2] < 1199
    # LEDs ~90 mm off-axis, ~75 mm in front of the lens: z > 0 in the camera frame.
    assert c.positions.shape == (8, 3)
    off_axis = np.hypot(c.positions[:, 0], c.positions[:, 1])
    assert np.all((80 < off_axis) & (off_axis < 110))
    assert np.all((70 < c.positions[:, 2]) & (c.positions[:, 2] < 80))
    # The LEDs aim inwards and forwards.
    assert np.all(c.directions[:, 2] > 0)
    assert np.all(np.sum(c.directions[:, :2] * c.positions[:, :2], axis=1) < 0)
    assert c.intensities.shape == (8,) and np.all(c.intensities > 1e6)
    np.testing.assert_array_equal(c.mu, 1.0)
    assert c.mask.shape == (1200, 1920) and 3e5 < c.mask.sum() < 4e5
    # Frame check: LEDs below the axis (y > 0) light the lower half of the object more.
    lit = pp.subtract_ambient(c.images, c.ambient)
    rows = np.nonzero(c.mask)[0]
    lower = rows > np.median(rows)
    contrast = np.array([im[c.mask][lower].mean() - im[c.mask][~lower].mean() for im in lit])
    assert np.corrcoef(c.positions[:, 1], contrast)[0, 1] > 0.8
    assert elapsed < 10


def test_real_queau_human1(shared_capture) -> None:
    folder = shared_capture("queau_human1")
    start = time.perf_counter()
    c = cap.load_queau_human1(folder)
    elapsed = time.perf_counter() - start
    assert c.num_images == 7 and c.images.shape == (7, 1732, 2601)
    numbers = [p.name[-8:-4] for p in c.files]
    assert numbers == ["0001", "0002", "0003", "0004", "0006", "0007", "0008"]
    # Rows 0, 1, 2, 3, 5, 6, 7 of the calibration (LED 5 = row 4 missing).
    S = scipy_io.loadmat(folder / "light.mat")["S"]
    np.testing.assert_allclose(c.positions, S[[0, 1, 2, 3, 5, 6, 7]])
    assert np.all((340 < c.positions[:, 2]) & (c.positions[:, 2] < 530))
    assert c.intensities.shape == (7,)  # Phi averaged over R, G, B
    assert c.K[0, 0] == pytest.approx(4092.66, abs=0.01)
    np.testing.assert_allclose(c.K[:2, 2], [1243.1218, 902.5837], atol=1e-4)
    assert c.mask.shape == (1732, 2601) and c.mask.sum() > 1e5
    # Padding: the last 4 rows and 9 columns are empty; the rest is linear light in [0, 1].
    assert np.all(c.images[:, 1728:] == 0) and np.all(c.images[:, :, 2592:] == 0)
    assert 0.05 < c.images.max() <= 1.0
    assert c.ambient.shape == (1732, 2601) and c.ambient.max() < 0.01
    # Frame check: LEDs on the right (x > 0) light the right half of the face more.
    cols = np.nonzero(c.mask)[1]
    right = cols > np.median(cols)
    contrast = np.array([im[c.mask][right].mean() - im[c.mask][~right].mean() for im in c.images])
    side = np.abs(c.positions[:, 0]) > 100  # LED 4 (row 3) is almost on the axis
    assert side.sum() == 6
    assert np.all(np.sign(contrast[side]) == np.sign(c.positions[side, 0]))
    assert elapsed < 60


def test_real_queau_human1_jpeg_grid_subset(shared_capture) -> None:
    folder = shared_capture("queau_human1")
    c = cap.load_queau_human1(folder, grid="jpeg", lights=[5], color=None)
    assert c.images.shape == (1, 1728, 2592, 3) and c.mask.shape == (1728, 2592)
    assert c.intensities.shape == (1, 3)
    with pytest.raises(InputError, match="LED row"):
        cap.load_queau_human1(folder, lights=[4])


def test_real_diligent_ball(shared_capture) -> None:
    folder = shared_capture("diligent_ball")
    c = cap.load_diligent(folder)
    assert c.num_images == 96 and c.directional and c.name == "ball"
    assert np.all(c.directions[:, 2] < 0)
    np.testing.assert_allclose(np.linalg.norm(c.directions, axis=1), 1.0, atol=1e-12)
    assert c.intensities.shape == (96, 3)
    assert c.mask.shape == (512, 612) and c.mask.sum() == 15791
    n = c.normals_gt[c.mask]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
    assert np.all(n[:, 2] <= 0) and np.mean(n[:, 2] < 0) > 0.99  # n_z = 0 on the silhouette
    # The top of the ball faces up: -y in the camera frame.
    rows, cols = np.nonzero(c.mask)
    top = (rows.min() + 2, (cols.min() + cols.max()) // 2)
    assert c.normals_gt[top][1] < -0.9
    # 16-bit images, a subset of 8 (pypng reads ~0.2 s per image; all 96 take ~18 s).
    sub = cap.load_diligent(folder, load=True, lights=range(0, 96, 12))
    assert sub.images.shape == (8, 512, 612, 3) and sub.images.dtype == np.float32
    assert len(np.unique(sub.images[0, ..., 0])) > 1000  # more than 8 bits
    # Lambertian consistency of images, lights and normals in the converted frame: the
    # intensity-corrected grey image follows max(0, n . l) (specular top 3% excluded), with
    # the same albedo for every light. With y left unflipped some correlations turn negative.
    scaled = pp.scale_exposure(sub.images, sub.intensities).mean(axis=3)
    shading = np.clip(np.einsum("hwc,kc->khw", sub.normals_gt, sub.directions), 0, None)
    inner = c.mask & (c.normals_gt[..., 2] < -0.3)
    albedos = []
    for img, sh in zip(scaled, shading, strict=True):
        a, b = img[inner], sh[inner]
        keep = a < np.percentile(a, 97)
        assert np.corrcoef(a[keep], b[keep])[0, 1] > 0.99
        albedos.append(np.median(a[b > 0.2] / b[b > 0.2]))
    assert np.std(albedos) < 0.03 * np.mean(albedos)
    K = cap.load_matlab_intrinsics(folder / "thirdparty_queau_robust_ps" / "calib.mat")
    np.testing.assert_allclose(K[:2, 2], [304.875, 254.875])


# --------------------------------------------------------------------------------------------------
# the documented use of a capture (intensities in the rig, images not divided)
# --------------------------------------------------------------------------------------------------


def _docstring_example() -> str:
    """The code of the Examples section of ``nplps.captures``' module docstring."""
    doc = inspect.getdoc(cap) or ""
    after = doc.split("Examples\n--------\n", 1)[1]
    block = after.split("::\n", 1)[1]
    lines = []
    for line in block.splitlines():
        if line and not line.startswith("    "):
            break
        lines.append(line)
    return textwrap.dedent("\n".join(lines)).strip()


def test_capture_docs_do_not_divide_by_the_intensities():
    code = _docstring_example()
    assert "ball.rig()" in code and "intensities" not in code
    # The README's captures section shows the same code.
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    section = readme.split("## Real captures", 1)[1].split("\n## ", 1)[0]
    assert textwrap.indent(code, "  ") in section
    diligent_doc = inspect.getdoc(cap.load_diligent) or ""
    assert "divide image" not in diligent_doc.lower()


def test_documented_capture_example_on_the_ball(shared_capture, monkeypatch, angular_error):
    folder = shared_capture("diligent_ball")
    monkeypatch.chdir(folder.parent)
    namespace: dict[str, object] = {}
    exec(_docstring_example(), namespace)  # the documented example, exactly as written
    ball, result = namespace["ball"], namespace["result"]
    error = angular_error(result.normals, ball.normals_gt, ball.mask).mean()
    print(f"documented example on DiLiGenT's ball: mean normal error {error:.2f} deg")
    assert 3.5 < error < 4.6  # about 4.1 deg; dividing the images by the intensities too gave 16
