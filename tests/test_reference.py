"""Tests of the pure numpy/scipy reference implementation (``tests/reference.py``).

Synthetic scenes are built here with numpy (object size S = 100, mean depth about 200, 27 near
point lights in three layers), rendered with ``reference.render`` and reconstructed from a plane
at the true mean vertex depth. Noise-free data: the method must recover the mesh to high accuracy.
"""

import numpy as np
import pytest

import reference as ref  # tests/reference.py: pytest puts tests/ on sys.path

pytest.importorskip("scipy")

S = 100.0
Z0 = 200.0


# ---------------------------------------------------------------------------------------------
# scene helpers
# ---------------------------------------------------------------------------------------------
def lights27():
    """27 lights: 3 layers at z = 200 - (150, 225, 300), 9 lights on a circle each."""
    out = []
    for j, (dz, rad) in enumerate([(150.0, 0.3 * S), (225.0, 0.4 * S), (300.0, 0.5 * S)]):
        for i in range(9):
            a = 2 * np.pi * i / 9 + 0.35 * j + 0.1
            out.append([rad * np.cos(a), rad * np.sin(a), Z0 - dz])
    return np.array(out)


def grid(n):
    w = S / n
    o = -S / 2
    xs = o + np.arange(n + 1) * w
    X, Y = np.meshgrid(xs, xs)  # vertex coordinates, (n+1, n+1)
    xc = o + (np.arange(n) + 0.5) * w
    XC, YC = np.meshgrid(xc, xc)  # pixel centres, (n, n)
    return X, Y, XC, YC, (w, w), (o, o)


def albedo(n):
    _, _, XC, YC, _, _ = grid(n)
    pattern = 0.5 + 0.5 * np.sin(2 * np.pi * 1.3 * XC / S) * np.cos(2 * np.pi * 0.9 * YC / S + 0.4)
    return Z0**2 * (0.6 + 0.4 * pattern)


def active_vertices(mask):
    H, W = mask.shape
    act = np.zeros((H + 1, W + 1), dtype=bool)
    act[:-1, :-1] |= mask
    act[:-1, 1:] |= mask
    act[1:, :-1] |= mask
    act[1:, 1:] |= mask
    return act


def saddle(n):
    X, Y, _, _, ps, o = grid(n)
    return Z0 + 0.5 * (X**2 - Y**2) / S, np.ones((n, n), dtype=bool), ps, o


def sphere_cap(n):
    X, Y, XC, YC, ps, o = grid(n)
    R = 0.6 * S
    with np.errstate(invalid="ignore"):  # grid corners beyond the sphere: NaN, never used
        z = -np.sqrt(R**2 - X**2 - Y**2)  # the front of the sphere faces the camera
    mask = XC**2 + YC**2 <= (0.45 * S) ** 2
    act = active_vertices(mask)
    z = z - z[act].mean() + Z0
    return z, mask, ps, o


def cube_edge(n):
    """Two planes meeting at a crease on the vertex column x = 0 (n even), edge towards camera."""
    assert n % 2 == 0
    X, Y, _, _, ps, o = grid(n)
    return Z0 + 20.0 - 0.8 * np.abs(X) + 0.2 * Y, np.ones((n, n), dtype=bool), ps, o


SCENES = {"saddle": (saddle, 48), "sphere_cap": (sphere_cap, 64), "cube_edge": (cube_edge, 56)}


def angle_deg(a, b):
    """Angle between unit vectors along the last axis (stable near 0)."""
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    return np.degrees(np.arctan2(cross, np.sum(a * b, axis=-1)))


def make(scene):
    fn, n = SCENES[scene]
    z, mask, ps, o = fn(n)
    L = lights27()
    images = ref.render(z, L, ps, o, albedo(n), mask)
    return z, mask, ps, o, L, images


def errors(res, z, mask, ps, o):
    act = active_vertices(mask)
    ang = angle_deg(res["normals"], ref.mesh_normals(z, ps, o))[mask]
    dz = np.abs(res["depth"] - z)[act]
    return ang.mean(), dz.max()


# ---------------------------------------------------------------------------------------------
# geometry and rendering
# ---------------------------------------------------------------------------------------------
def test_mesh_normals_of_a_plane():
    n = 6
    X, Y, _, _, ps, o = grid(n)
    px, py = 0.3, -0.7
    z = 150.0 + px * X + py * Y
    nrm = ref.mesh_normals(z, ps, o)
    want = np.array([px, py, -1.0]) / np.sqrt(px**2 + py**2 + 1)
    assert nrm.shape == (n, n, 3)
    np.testing.assert_allclose(nrm, np.broadcast_to(want, nrm.shape), atol=1e-14)


def test_render_matches_the_image_model_and_clips():
    n = 8
    z, mask, ps, o = saddle(n)
    mask = mask.copy()
    mask[0, :3] = False
    L = np.array([[0.0, 0.0, 50.0], [10.0, 5.0, 20.0], [-400.0, 0.0, 230.0]])  # last one grazes
    rho = albedo(n)
    img = ref.render(z, L, ps, o, rho, mask)
    assert img.shape == (3, n, n) and img.dtype == np.float64
    assert np.all(img[:, ~mask] == 0.0)
    assert np.all(img >= 0.0)
    # one facet by hand
    r, c = 3, 5
    w, h = ps
    corners = np.array(
        [[o[0] + cc * w, o[1] + rr * h, z[rr, cc]] for rr, cc in [(r, c), (r, c + 1), (r + 1, c), (r + 1, c + 1)]]
    )
    nrm = np.cross(corners[2] - corners[1], corners[3] - corners[0])
    nrm /= np.linalg.norm(nrm)
    cen = corners.mean(axis=0)
    for i in range(3):
        a = L[i] - cen
        want = rho[r, c] * max(0.0, nrm @ a) / np.linalg.norm(a) ** 3
        assert img[i, r, c] == pytest.approx(want, rel=1e-13, abs=1e-300)
    assert np.any(img[2][mask] == 0.0)  # the grazing light leaves some facets unlit


# ---------------------------------------------------------------------------------------------
# reconstruction accuracy from a plane at the true mean depth
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("scene", sorted(SCENES))
def test_reconstruct_recovers_the_scene(scene):
    z, mask, ps, o, L, images = make(scene)
    act = active_vertices(mask)
    z_mean = z[act].mean()
    res = ref.reconstruct(images, L, ps, o, mask, depth=z_mean, iterations=50, tol=1e-10)
    ang, dz = errors(res, z, mask, ps, o)
    assert ang < 0.01, ang
    assert dz < 1e-3 * S, dz
    # outputs: shapes, NaN outside, gauge, albedo, lights used
    H, W = mask.shape
    assert res["depth"].shape == (H + 1, W + 1)
    assert res["normals"].shape == (H, W, 3)
    assert np.all(np.isnan(res["depth"][~act])) and np.all(np.isfinite(res["depth"][act]))
    assert np.all(np.isnan(res["normals"][~mask])) and np.all(np.isnan(res["albedo"][~mask]))
    assert np.all(res["lights_used"][~mask] == 0)
    assert res["lights_used"].dtype.kind == "i"
    assert np.all(res["lights_used"][mask] >= 3)
    assert res["depth"][act].mean() == pytest.approx(z_mean, abs=1e-9)
    np.testing.assert_array_equal(res["gauge"], [z_mean])
    np.testing.assert_array_equal(res["regions"], np.where(mask, 0, -1))
    np.testing.assert_allclose(res["albedo"][mask], albedo(H)[mask], rtol=1e-3)
    assert np.nanmax(res["residual"]) < 1e-5 * np.max(images)
    # converged: the stopping rule ended the loop before the iteration limit
    dzs = [d for d, _ in res["history"]]
    assert len(dzs) < 50
    assert dzs[-1] <= 1e-10 * S
    assert all(np.isfinite(rms) for _, rms in res["history"])


@pytest.mark.parametrize("scene", sorted(SCENES))
def test_paper_weighting_converges(scene):
    z, mask, ps, o, L, images = make(scene)
    z_mean = z[active_vertices(mask)].mean()
    res = ref.reconstruct(images, L, ps, o, mask, depth=z_mean, iterations=50, tol=1e-10, weighting="paper")
    ang, dz = errors(res, z, mask, ps, o)
    assert ang < 0.01, ang
    assert dz < 1e-3 * S, dz
    assert res["history"][-1][0] <= 1e-10 * S


def test_few_iterations_from_a_plane():
    """The default budget (10 iterations, tol 1e-6) is ample for these scenes."""
    z, mask, ps, o, L, images = make("cube_edge")
    z_mean = z[active_vertices(mask)].mean()
    res = ref.reconstruct(images, L, ps, o, mask, depth=z_mean)
    ang, dz = errors(res, z, mask, ps, o)
    assert ang < 1e-3 and dz < 1e-4 * S
    dzs = [d for d, _ in res["history"]]
    assert dzs == sorted(dzs, reverse=True)  # monotone decrease of the update
    res3 = ref.reconstruct(images, L, ps, o, mask, depth=z_mean, iterations=3)
    ang3, dz3 = errors(res3, z, mask, ps, o)
    assert len(res3["history"]) == 3
    assert ang3 < 0.01 and dz3 < 1e-3 * S


def test_two_islands_with_their_own_gauge():
    n = 56
    X, Y, XC, YC, ps, o = grid(n)
    # left island a saddle near 190, right island a tilted plane near 225
    z = np.where(X < 0, Z0 - 10 + 0.5 * (X**2 - Y**2) / S, Z0 + 25 + 0.3 * X - 0.2 * Y)
    mask = ((XC + 0.25 * S) ** 2 + YC**2 <= (0.2 * S) ** 2) | (
        (np.abs(XC - 0.27 * S) <= 0.2 * S) & (np.abs(YC - 0.05 * S) <= 0.3 * S)
    )
    act = active_vertices(mask)
    assert not np.any(act & (np.abs(X) < 1e-9))  # the step lies in the gap
    L = lights27()
    images = ref.render(z, L, ps, o, albedo(n), mask)
    left = act & (X < 0)
    right = act & (X > 0)
    init = np.full_like(z, Z0)
    init[left] = z[left].mean()
    init[right] = z[right].mean()
    res = ref.reconstruct(images, L, ps, o, mask, depth=init, iterations=50, tol=1e-10)
    ang, dz = errors(res, z, mask, ps, o)
    assert ang < 0.05, ang
    assert dz < 1e-3 * S, dz
    # regions numbered by their first pixel in row-major order
    first = np.argmax(mask.ravel())
    first_region_left = XC.ravel()[first] < 0
    want = [z[left].mean(), z[right].mean()]
    if not first_region_left:
        want = want[::-1]
    np.testing.assert_allclose(res["gauge"], want, rtol=1e-13)
    assert set(np.unique(res["regions"])) == {-1, 0, 1}
    assert res["regions"].ravel()[first] == 0
    np.testing.assert_array_equal(res["regions"] >= 0, mask)
    for label, sel in enumerate([left, right] if first_region_left else [right, left]):
        assert res["depth"][sel].mean() == pytest.approx(res["gauge"][label], abs=1e-9)
    # one scalar depth for both islands: the gauge is 200 for both, so the islands sit at the
    # wrong distances and, with near lights, their shapes come out wrong too
    res1 = ref.reconstruct(images, L, ps, o, mask, depth=Z0, iterations=50, tol=1e-10)
    np.testing.assert_array_equal(res1["gauge"], [Z0, Z0])
    for label in range(2):
        sel = active_vertices(res1["regions"] == label)
        assert res1["depth"][sel].mean() == pytest.approx(Z0, abs=1e-9)
    ang1, _ = errors(res1, z, mask, ps, o)
    assert ang1 > 10 * ang, (ang1, ang)


def test_facets_with_fewer_than_three_lights():
    z, mask, ps, o, L, images = make("saddle")
    n = mask.shape[0]
    images = images.copy()
    dark = np.zeros((n, n), dtype=bool)
    dark[20:24, 30:34] = True
    dark[5, 7] = True
    images[2:, dark] = 0.0  # only lights 0 and 1 remain
    z_mean = z.mean()
    res = ref.reconstruct(images, L, ps, o, depth=z_mean, iterations=50, tol=1e-10)
    assert np.all(np.isfinite(res["depth"]))
    assert np.all(np.isfinite(res["normals"]))
    assert np.all(res["lights_used"][dark] == 2)
    assert np.all(res["lights_used"][~dark] == 27)
    assert np.all(np.isnan(res["albedo"][dark])) and np.all(np.isnan(res["residual"][dark]))
    assert np.all(np.isfinite(res["albedo"][~dark]))
    # invalid facets report the mesh normal of the result
    np.testing.assert_allclose(res["normals"][dark], ref.mesh_normals(res["depth"], ps, o)[dark], atol=1e-15)
    # the lit facets are still reconstructed well
    ang = angle_deg(res["normals"], ref.mesh_normals(z, ps, o))
    assert ang[~dark].mean() < 0.01, ang[~dark].mean()
    assert np.abs(res["depth"] - z).max() < 1e-3 * S


def test_dark_threshold_and_nan_observations_are_skipped():
    z, mask, ps, o, L, images = make("saddle")
    images = images.copy()
    images[4, 10, 10] = np.nan
    images[7, 11, 12] = -1.0
    images[9, 12, 12] = 1e-30
    res = ref.reconstruct(images, L, ps, o, depth=z.mean(), iterations=50, tol=1e-10, dark=1e-20)
    assert res["lights_used"][10, 10] == 26
    assert res["lights_used"][11, 12] == 26
    assert res["lights_used"][12, 12] == 26
    ang, dz = errors(res, z, mask, ps, o)
    assert ang < 0.01 and dz < 1e-3 * S


def test_parallel_baseline_is_worse():
    z, mask, ps, o, L, images = make("sphere_cap")
    z_mean = z[active_vertices(mask)].mean()
    npl = ref.reconstruct(images, L, ps, o, mask, depth=z_mean, iterations=50, tol=1e-10)
    par = ref.reconstruct_parallel(images, L, ps, o, mask, depth=z_mean)
    ang_npl, dz_npl = errors(npl, z, mask, ps, o)
    ang_par, dz_par = errors(par, z, mask, ps, o)
    assert ang_par > 1.0 and ang_par > 100 * ang_npl, (ang_par, ang_npl)
    assert dz_par > 0.01 * S and dz_par > 10 * dz_npl, (dz_par, dz_npl)
    assert len(par["history"]) == 1
    assert par["depth"][active_vertices(mask)].mean() == pytest.approx(z_mean, abs=1e-9)
    assert np.all(np.isnan(par["normals"][~mask]))


def test_zero_iterations_reports_the_initial_plane():
    _, _, ps, o, L, images = make("saddle")
    res = ref.reconstruct(images, L, ps, o, depth=200.0, iterations=0)
    assert res["history"] == []
    assert np.all(res["depth"] == 200.0)


def test_input_errors():
    _, mask, ps, o, L, images = make("saddle")
    with pytest.raises(ValueError):
        ref.reconstruct(images, L, ps, o)  # depth is required
    with pytest.raises(ValueError):
        ref.reconstruct(images, L[:-1], ps, o, depth=200.0)
    with pytest.raises(ValueError):
        ref.reconstruct(images, L, ps, o, depth=np.zeros((3, 3)))
    with pytest.raises(ValueError):
        ref.reconstruct(images, L, ps, o, depth=200.0, weighting="other")
    with pytest.raises(ValueError):
        ref.reconstruct(images, L, ps, o, mask=np.zeros(mask.shape, bool), depth=200.0)
    with pytest.raises(ValueError):
        ref.reconstruct(images, L, (0.0, 1.0), o, depth=200.0)
