"""The committed Mitsuba 3 renders of benchmarks/pbr (tests/data/pbr): well-formed, and the control.

The files were written by ``benchmarks/pbr/render.py --size 64 --spp 256 --float16`` (Mitsuba
3.9.1, llvm_ad_rgb, direct light only); Mitsuba is not needed here. The Lambertian control
(``diffuse``) must agree with nplps's own image model and reconstruct at the true distance to
≤ 0.1° on a surface without cast shadows. Glossy assertions are for the reflectance work.

``bowl-diffuse-gi`` and ``sheet-diffuse-gi`` (issue 21) are path traced with global illumination
(``render.py bowl|sheet --size 64 --spp 256 --max-depth 12 --float16``): concave Lambertian
surfaces whose observations hold 10-50 % of indirect light, which nplps's image model does not
have. Only their form and the presence of that light are checked here.
"""

from __future__ import annotations

import importlib.util
import json
import types
import warnings
from pathlib import Path

import numpy as np
import pytest

import nplps
from pbr_data import DATA, angles, load  # tests/pbr_data.py

FILES = {
    "sphere-diffuse": ("sphere", "diffuse"),
    "sphere-roughplastic-0.3": ("sphere", "roughplastic-0.3"),
    "bumps-roughplastic-0.1": ("bumps", "roughplastic-0.1"),
    "shadows-diffuse": ("shadows", "diffuse"),
    "shadows-roughplastic-0.3": ("shadows", "roughplastic-0.3"),
    "bumps-principled-0.5": ("bumps", "principled-0.5"),
    "shadows-principled-0.3": ("shadows", "principled-0.3"),
}

GI_FILES = {"bowl-diffuse-gi": "bowl", "sheet-diffuse-gi": "sheet"}


def reconstruct(images: np.ndarray, rig: nplps.Rig, data: dict[str, np.ndarray], **options: object) -> np.ndarray:
    """Return the per-pixel normal errors (degrees, inside the mask) at the true distance."""
    mask = data["mask"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = nplps.reconstruct(images, rig, depth=float(data["distance"]), mask=mask, **options)
    return angles(result.normals[mask], data["normals"][mask])


def test_total_size_is_small() -> None:
    assert sum(p.stat().st_size for p in DATA.glob("*.npz")) < 3_000_000


@pytest.mark.parametrize("name", sorted(FILES))
def test_files_are_well_formed(name: str) -> None:
    data, rig = load(name)
    shape, material = FILES[name]
    images, mask, depth, normals = data["images"], data["mask"], data["depth"], data["normals"]
    assert str(data["shape"]) == shape and str(data["material"]) == material
    assert images.shape == (16, 64, 64) and len(rig.lights) == 16 and rig.is_pinhole
    assert np.isfinite(images).all() and images.min() >= 0 and images[:, mask].max() > 0.05
    assert (images[:, ~mask] == 0).all()
    assert mask.shape == (64, 64) and mask.dtype == bool and mask.sum() > 1000
    assert depth.shape == (65, 65) and np.isfinite(depth).all() and 150 < depth.min() and depth.max() < 250
    assert normals.shape == (64, 64, 3) and np.isnan(normals[~mask]).all()
    assert np.allclose(np.linalg.norm(normals[mask], axis=-1), 1) and (normals[mask][:, 2] < 0).all()
    # The gauge is nplps's: the geometric mean depth of the vertices the mask uses.
    used = np.zeros((65, 65), dtype=bool)
    for dr in (0, 1):
        for dc in (0, 1):
            used[dr : dr + 64, dc : dc + 64] |= mask
    assert float(data["distance"]) == pytest.approx(np.exp(np.log(depth[used]).mean()), rel=1e-12)
    assert int(data["max_depth"]) == 2 and int(data["spp"]) > 0 and float(data["seconds"]) > 0
    # The share of each pixel in each light's cast shadow: none on the sphere (convex), in 3 % of
    # the observations on "shadows".
    shadow = data["shadow"].astype(np.float32)
    assert shadow.shape == images.shape and shadow.min() >= 0 and shadow.max() <= 1 and (shadow[:, ~mask] == 0).all()
    if shape == "sphere":
        assert (shadow == 0).all()
    if shape == "shadows":
        assert 0.01 < (shadow > 0).mean() < 0.1


def test_true_normals_are_the_mesh_normals() -> None:
    # nplps's own renders of the true surface at the true distance give back the stored normals.
    data, rig = load("sphere-diffuse")
    images = nplps.render(data["depth"], rig, 0.5, mask=data["mask"])
    assert reconstruct(images, rig, data).mean() < 0.01


def test_lambertian_control_matches_nplps_render() -> None:
    # The frame, the principal point and the intensities: Mitsuba's diffuse render equals
    # nplps.render of the true surface with albedo 0.5 (float16 storage: ~3e-4 rounding).
    data, rig = load("sphere-diffuse")
    mask = data["mask"]
    reference = nplps.render(data["depth"], rig, 0.5, mask=mask)
    lit = mask[None] & (reference > 0.05 * reference.max())
    relative = data["images"][lit] / reference[lit] - 1
    assert abs(np.median(relative)) < 2e-4
    assert np.percentile(np.abs(relative), 95) < 3e-3


def test_lambertian_control_sphere() -> None:
    data, rig = load("sphere-diffuse")
    error = reconstruct(data["images"].astype(np.float32), rig, data)
    assert error.mean() < 0.1


def test_lambertian_control_with_cast_shadows() -> None:
    # At 64 x 64 a pixel is 1.6 mm: the pixels a shadow edge crosses are partly lit, which the
    # local image model cannot explain and dark=0 does not drop (measured: 0.67° mean at 64 x 64,
    # 0.20° at 256 x 256). Without the observations in a true cast shadow (the renders' "shadow"
    # array) the control is within 0.1° (measured 0.08°): the renderer agrees with nplps's model
    # everywhere else.
    data, rig = load("shadows-diffuse")
    images = data["images"].astype(np.float32)
    assert reconstruct(images, rig, data).mean() < 1.0
    assert reconstruct(images, rig, data, valid=data["shadow"] == 0).mean() < 0.1


@pytest.mark.parametrize("name", sorted(GI_FILES))
def test_gi_files_are_well_formed(name: str) -> None:
    data, rig = load(name)
    images, mask, depth, normals = data["images"], data["mask"], data["depth"], data["normals"]
    assert str(data["shape"]) == GI_FILES[name] and str(data["material"]) == "diffuse"
    assert int(data["max_depth"]) > 2 and float(data["reflectance"]) == 0.5
    assert images.shape == (16, 64, 64) and len(rig.lights) == 16 and rig.is_pinhole
    assert np.isfinite(images).all() and images.min() >= 0
    assert depth.shape == (65, 65) and np.isfinite(depth).all() and 150 < depth.min() and depth.max() < 250
    assert np.allclose(np.linalg.norm(normals[mask], axis=-1), 1) and (normals[mask][:, 2] < 0).all()
    if name.startswith("bowl"):
        # Only the inside of the bowl exists; the sheet fills the image (and goes on past it).
        assert 1000 < mask.sum() < 2000 and (images[:, ~mask] == 0).all()
    else:
        assert mask.all()
    # Indirect light: brighter than nplps's direct-light image model of the true surface, by 12 %
    # in the median lit observation (measured 12.2 % on the bowl, 12.5 % on the sheet).
    reference = nplps.render(depth, rig, 0.5, mask=mask)
    lit = mask[None] & (reference > 0.05 * reference.max())
    excess = np.median(images[lit].astype(np.float64) / reference[lit] - 1)
    assert 0.08 < excess < 0.2


def _render_module() -> types.ModuleType:
    """Import benchmarks/pbr/render.py (Mitsuba is imported only when rendering)."""

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "pbr" / "render.py"
    spec = importlib.util.spec_from_file_location("pbr_render", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_default_rig_is_the_committed_renders_rig() -> None:
    # `--lights` (issue 20) left the 16-light benchmark rig as it was, bit for bit.
    render = _render_module()
    data, _ = load("sphere-diffuse")
    assert render.make_rig(64).with_grid(64, 64).to_dict() == json.loads(str(data["rig"]))


def test_larger_rigs_add_rings_after_the_16_lights() -> None:
    render = _render_module()
    base = render.make_rig(64)
    for count in (24, 32):
        rig = render.make_rig(64, count)
        assert len(rig.lights) == count
        np.testing.assert_array_equal(rig.positions[:16], base.positions)
        np.testing.assert_array_equal(rig.intensities[:16], base.intensities)
        radii = np.hypot(rig.positions[16:, 0], rig.positions[16:, 1])
        np.testing.assert_allclose(radii, [140.0] * 8 + [60.0] * (count - 24), rtol=1e-12)
    with pytest.raises(SystemExit):
        render.make_rig(64, 20)


def _largest_part_by_search(mask: np.ndarray) -> np.ndarray:
    """The largest 4-connected part by a breadth-first search (the oracle; ties: the part with the
    least first pixel, as the labels' least index)."""
    h, w = mask.shape
    seen = np.zeros_like(mask)
    best: list[tuple[int, int]] = []
    for r0, c0 in np.argwhere(mask):
        start = (int(r0), int(c0))
        if seen[start]:
            continue
        seen[start] = True
        part, queue = [start], [start]
        while queue:
            r, c = queue.pop()
            for rr, cc in ((r - 1, c), (r + 1, c), (r, c - 1), (r, c + 1)):
                if 0 <= rr < h and 0 <= cc < w and mask[rr, cc] and not seen[rr, cc]:
                    seen[rr, cc] = True
                    part.append((rr, cc))
                    queue.append((rr, cc))
        if len(part) > len(best):
            best = part
    out = np.zeros_like(mask)
    for pixel in best:
        out[pixel] = True
    return out


@pytest.mark.parametrize("seed", range(4))
def test_largest_part_is_the_largest_connected_part(seed: int) -> None:
    # render.py's mask clean-up (label propagation with pointer jumping) against a plain search:
    # random masks near the percolation threshold (many parts, long thin ones), a serpentine
    # whose one part is as long as the image's area, and an empty mask.
    render = _render_module()
    rng = np.random.default_rng(seed)
    for shape in [(31, 47), (64, 64), (5, 120)]:
        mask = rng.random(shape) < rng.uniform(0.45, 0.7)
        np.testing.assert_array_equal(render.largest_part(mask), _largest_part_by_search(mask))
    serpentine = np.zeros((41, 41), dtype=bool)
    serpentine[::2] = True
    serpentine[1::4, -1] = True
    serpentine[3::4, 0] = True
    assert render.largest_part(serpentine).sum() == serpentine.sum()
    assert not render.largest_part(np.zeros((4, 6), dtype=bool)).any()
