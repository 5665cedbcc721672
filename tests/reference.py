"""Independent pure-numpy/scipy implementation of the nplps iteration: the tests' oracle.

It lives with the tests, not in the shipped package: it is an oracle, not an API. Tests import it
as ``import reference`` (pytest puts ``tests/`` on ``sys.path``); ``benchmarks/bench.py`` adds
``tests/`` to ``sys.path`` itself.

This module repeats, step for step, the iteration specified in ``docs/method.md`` (near-light
photometric stereo by mesh deformation, Xie, Dai & Wang, CVPR 2015) without using the compiled
Rust core. It serves two purposes:

* **validation**: the Rust core implements the same specification, and the two must agree to
  floating-point round-off;
* **benchmark baseline**: it is a fair, vectorized numpy/scipy implementation (batched local step
  over all facets, sparse normal matrix assembled and factored once with SuperLU, one back
  substitution per iteration). It is nevertheless much slower than the Rust core.

scipy is imported lazily inside the functions that need it, so ``import reference`` works
without scipy; :func:`mesh_normals` and :func:`render` need numpy only.

Conventions (see ``docs/method.md``): images are ``(k, H, W)``, lights ``(k, 3)`` positions in the
camera frame (x right, y down, z forward), depth maps ``(H+1, W+1)`` at the vertices, vertex
``(r, c)`` at ``x = ox + c*w``, ``y = oy + r*h``; ``pixel_size = (w, h)``, ``origin = (ox, oy)``.
"""

from __future__ import annotations

import time
from numbers import Integral, Real

import numpy as np

try:  # the package's error classes, so that the tests can expect the same exceptions
    from nplps.errors import InputError, SolverError
except ImportError:  # without nplps (it needs its compiled core)
    InputError = ValueError  # type: ignore[assignment,misc]
    SolverError = RuntimeError  # type: ignore[assignment,misc]

__all__ = ["NZ_MIN", "mesh_normals", "reconstruct", "reconstruct_parallel", "render"]

#: Facet normals are limited to ``n_z <= -NZ_MIN`` when turned into target corner depths.
NZ_MIN = 0.01

# Facets per chunk in the local step: (k, _CHUNK) float64 work arrays stay cache-sized.
_CHUNK = 2048


# --------------------------------------------------------------------------------------------
# input checking
# --------------------------------------------------------------------------------------------
def _pair(value, name, positive):
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be a number or a pair of numbers") from exc
    if arr.ndim == 0:
        arr = np.array([arr, arr], dtype=np.float64)
    if arr.shape != (2,):
        raise InputError(f"{name} must be a pair (got shape {arr.shape})")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name} must be finite")
    if positive and not np.all(arr > 0):
        raise InputError(f"{name} must be positive")
    return float(arr[0]), float(arr[1])


def _lights(lights, k=None):
    lights = np.asarray(lights, dtype=np.float64)
    if lights.ndim != 2 or lights.shape[1] != 3:
        raise InputError(f"lights must have shape (k, 3) (got {lights.shape})")
    if k is not None and lights.shape[0] != k:
        raise InputError(f"{lights.shape[0]} lights for {k} images")
    if not np.all(np.isfinite(lights)):
        raise InputError("light positions must be finite")
    return lights


def _mask(mask, H, W):
    if mask is None:
        return np.ones((H, W), dtype=bool)
    mask = np.asarray(mask)
    if mask.shape != (H, W):
        raise InputError(f"mask must have shape {(H, W)} (got {mask.shape})")
    return mask.astype(bool, copy=False)


def _images(images):
    images = np.asarray(images, dtype=np.float64)
    if images.ndim != 3:
        raise InputError(f"images must have shape (k, H, W) (got {images.shape})")
    k, H, W = images.shape
    if k < 3:
        raise InputError(f"at least 3 images are needed (got {k})")
    if H < 1 or W < 1:
        raise InputError("images are empty")
    return images


# --------------------------------------------------------------------------------------------
# geometry
# --------------------------------------------------------------------------------------------
def _grid_xy(H, W, pixel_size, origin):
    """x of the vertex columns (W+1,) and y of the vertex rows (H+1,)."""
    w, h = pixel_size
    ox, oy = origin
    return ox + np.arange(W + 1) * w, oy + np.arange(H + 1) * h


def _cross_normals(x00, x01, x10, x11, y00, y01, y10, y11, z00, z01, z10, z11):
    """normalize((v10 - v01) x (v11 - v00)), component arrays in, (..., 3) out."""
    ax, ay, az = x10 - x01, y10 - y01, z10 - z01
    bx, by, bz = x11 - x00, y11 - y00, z11 - z00
    nx = ay * bz - az * by
    ny = az * bx - ax * bz
    nz = ax * by - ay * bx
    norm = np.sqrt(nx * nx + ny * ny + nz * nz)
    return np.stack([nx / norm, ny / norm, nz / norm], axis=-1)


def mesh_normals(depth, pixel_size, origin):
    """Facet normals of the depth mesh, ``normalize((v10 - v01) x (v11 - v00))``.

    ``depth`` is the ``(H+1, W+1)`` vertex depth map; returns ``(H, W, 3)``. A visible facet has
    ``n_z < 0`` (facing the camera). NaN depths give NaN normals.
    """
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2 or depth.shape[0] < 2 or depth.shape[1] < 2:
        raise InputError(f"depth must be an (H+1, W+1) map (got shape {depth.shape})")
    pixel_size = _pair(pixel_size, "pixel_size", True)
    origin = _pair(origin, "origin", False)
    H, W = depth.shape[0] - 1, depth.shape[1] - 1
    xs, ys = _grid_xy(H, W, pixel_size, origin)
    X = np.broadcast_to(xs[None, :], depth.shape)
    Y = np.broadcast_to(ys[:, None], depth.shape)
    c = (slice(None, -1), slice(None, -1))
    c01 = (slice(None, -1), slice(1, None))
    c10 = (slice(1, None), slice(None, -1))
    c11 = (slice(1, None), slice(1, None))
    return _cross_normals(
        X[c], X[c01], X[c10], X[c11], Y[c], Y[c01], Y[c10], Y[c11], depth[c], depth[c01], depth[c10], depth[c11]
    )


def render(depth, lights, pixel_size, origin, albedo=1.0, mask=None):
    """Render the depth mesh with the image model of ``docs/method.md``.

    ``I_k = rho * max(0, n . (p_k - c)) / |p_k - c|^3`` at each facet centre ``c`` (mean of its 4
    corners) with the mesh facet normal ``n``. ``albedo`` is a scalar or an ``(H, W)`` map.
    Returns ``(k, H, W)`` float64, 0 outside ``mask``.
    """
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2 or depth.shape[0] < 2 or depth.shape[1] < 2:
        raise InputError(f"depth must be an (H+1, W+1) map (got shape {depth.shape})")
    H, W = depth.shape[0] - 1, depth.shape[1] - 1
    lights = _lights(lights)
    pixel_size = _pair(pixel_size, "pixel_size", True)
    origin = _pair(origin, "origin", False)
    mask = _mask(mask, H, W)
    rho = np.broadcast_to(np.asarray(albedo, dtype=np.float64), (H, W))
    n = mesh_normals(depth, pixel_size, origin)
    xs, ys = _grid_xy(H, W, pixel_size, origin)
    cx = ((xs[:-1] + xs[1:] + xs[:-1] + xs[1:]) * 0.25)[None, :]
    cy = ((ys[:-1] + ys[:-1] + ys[1:] + ys[1:]) * 0.25)[:, None]
    cz = (depth[:-1, :-1] + depth[:-1, 1:] + depth[1:, :-1] + depth[1:, 1:]) * 0.25
    out = np.zeros((lights.shape[0], H, W))
    with np.errstate(invalid="ignore"):
        for i, p in enumerate(lights):
            ax, ay, az = p[0] - cx, p[1] - cy, p[2] - cz
            r2 = ax * ax + ay * ay + az * az
            r3 = r2 * np.sqrt(r2)
            dot = n[..., 0] * ax + n[..., 1] * ay + n[..., 2] * az
            out[i] = np.where(mask, rho * np.maximum(dot, 0.0) / r3, 0.0)
    return out


# --------------------------------------------------------------------------------------------
# problem set-up: facets, active vertices, regions, normal matrix
# --------------------------------------------------------------------------------------------
class _Problem:
    """Everything that depends only on the mask and the grid."""

    def __init__(self, mask, pixel_size, origin):
        from scipy import ndimage

        H, W = mask.shape
        self.H, self.W = H, W
        self.w, self.h = pixel_size
        fr, fc = np.nonzero(mask)  # row-major facet order
        if fr.size == 0:
            raise InputError("the mask is empty")
        self.fr, self.fc = fr, fc
        self.F = fr.size
        active = np.zeros((H + 1, W + 1), dtype=bool)
        active[:-1, :-1] |= mask
        active[:-1, 1:] |= mask
        active[1:, :-1] |= mask
        active[1:, 1:] |= mask
        self.active = active
        self.n = int(active.sum())
        vid = np.full((H + 1, W + 1), -1, dtype=np.int64)
        vid[active] = np.arange(self.n)  # compact index keeps row-major order
        # corners in the fixed order 00, 01, 10, 11
        self.cid = np.stack([vid[fr, fc], vid[fr, fc + 1], vid[fr + 1, fc], vid[fr + 1, fc + 1]], axis=1)
        # vertex coordinates (compact) and facet centres (x, y fixed)
        xs, ys = _grid_xy(H, W, pixel_size, origin)
        vr, vc = np.nonzero(active)
        self.vx, self.vy = xs[vc], ys[vr]
        cx = self.vx[self.cid]
        cy = self.vy[self.cid]
        self.cx = (cx[:, 0] + cx[:, 1] + cx[:, 2] + cx[:, 3]) * 0.25
        self.cy = (cy[:, 0] + cy[:, 1] + cy[:, 2] + cy[:, 3]) * 0.25
        self.dx = np.array([-0.5 * self.w, 0.5 * self.w, -0.5 * self.w, 0.5 * self.w])
        self.dy = np.array([-0.5 * self.h, -0.5 * self.h, 0.5 * self.h, 0.5 * self.h])

        # regions: 8-connected components, numbered by their first pixel in row-major order
        lab, nlab = ndimage.label(mask, structure=np.ones((3, 3), dtype=bool))
        flab = lab[fr, fc]
        _, first = np.unique(flab, return_index=True)  # first facet of labels 1..nlab
        order = np.argsort(first, kind="stable")
        relabel = np.empty(nlab + 1, dtype=np.int64)
        relabel[0] = -1
        relabel[1 + order] = np.arange(nlab)
        self.R = nlab
        self.freg = relabel[flab]
        self.regions = relabel[lab]
        vreg = np.empty(self.n, dtype=np.int64)
        for j in range(4):
            vreg[self.cid[:, j]] = self.freg
        self.vreg = vreg
        self.vcount = np.bincount(vreg, minlength=self.R).astype(np.float64)
        # lowest-index active vertex of a region = corner 00 of its first pixel (row-major)
        self.pin = self.cid[np.sort(first), 0]
        self.lu = None

    # ---- global step -----------------------------------------------------------------------
    def factor(self):
        """Assemble A = sum_f S_f^T N S_f + pins, factor it once (SuperLU, symmetric mode)."""
        from scipy import sparse
        from scipy.sparse import linalg as spla

        Nmat = np.eye(4) - 0.25
        rows = np.repeat(self.cid, 4, axis=1).ravel()
        cols = np.tile(self.cid, (1, 4)).ravel()
        vals = np.tile(Nmat.ravel(), self.F)
        rows = np.concatenate([rows, self.pin])
        cols = np.concatenate([cols, self.pin])
        vals = np.concatenate([vals, np.ones(self.R)])
        A = sparse.coo_matrix((vals, (rows, cols)), shape=(self.n, self.n)).tocsc()
        A.sum_duplicates()
        self.A = A
        try:
            # A is symmetric positive definite: symmetric ordering, no pivoting
            self.lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        except RuntimeError as exc:  # pragma: no cover - A is SPD by construction
            raise SolverError(f"sparse factorization failed: {exc}") from exc

    def gauge(self, z, g):
        """Shift each region so that the mean of its active vertex depths equals g[region]."""
        mean = np.bincount(self.vreg, weights=z, minlength=self.R) / self.vcount
        return z + (g - mean)[self.vreg]

    def global_step(self, t, z, g):
        b = np.bincount(self.cid.ravel(), weights=t.ravel(), minlength=self.n)
        b[self.pin] += z[self.pin]
        return self.gauge(self.lu.solve(b), g)

    def mesh_normals(self, z, idx):
        c = self.cid[idx]
        return _cross_normals(
            *(self.vx[c[:, j]] for j in range(4)),
            *(self.vy[c[:, j]] for j in range(4)),
            *(z[c[:, j]] for j in range(4)),
        )


def _chol3_solve(T00, T01, T02, T11, T12, T22, s0, s1, s2):
    """Batched Cholesky solve of symmetric 3x3 systems; ok = factorization succeeded."""
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = T00 > 0
        l00 = np.sqrt(T00)
        l10 = T01 / l00
        l20 = T02 / l00
        d1 = T11 - l10 * l10
        ok &= d1 > 0
        l11 = np.sqrt(d1)
        l21 = (T12 - l20 * l10) / l11
        d2 = T22 - l20 * l20 - l21 * l21
        ok &= d2 > 0
        l22 = np.sqrt(d2)
        y0 = s0 / l00
        y1 = (s1 - l10 * y0) / l11
        y2 = (s2 - l20 * y0 - l21 * y1) / l22
        g2 = y2 / l22
        g1 = (y1 - l21 * g2) / l11
        g0 = (y0 - l10 * g1 - l20 * g2) / l00
    return g0, g1, g2, ok


class _Local:
    """The per-facet local step (vectorized over facets, in chunks)."""

    def __init__(self, prob, images, lights, dark, weighting, parallel_dirs=None):
        self.prob = prob
        k = images.shape[0]
        flat = prob.fr * prob.W + prob.fc
        self.I = np.take(images.reshape(k, -1), flat, axis=1)  # (k, F)
        with np.errstate(invalid="ignore"):
            self.usable = self.I > dark  # NaN -> unusable
        self.Iu = self.I.copy()
        np.copyto(self.Iu, 0.0, where=~self.usable)
        self.Uf = self.usable.astype(np.float64)
        # chunks where every observation is usable skip the weighting by Uf
        self.chunk = _CHUNK
        self.all_usable = [bool(self.usable[:, lo : lo + self.chunk].all()) for lo in range(0, prob.F, self.chunk)]
        self.nuse = self.usable.sum(axis=0)
        self.lights = lights
        self.weighting = weighting
        self.parallel_dirs = parallel_dirs  # (k, 3) unit directions for the parallel baseline

    def run(self, z, want_targets=True):
        """Local step on vertex depths z (compact). Returns a dict of per-facet arrays."""
        prob = self.prob
        F = prob.F
        cid = prob.cid
        zc = z[cid]
        cz = (zc[:, 0] + zc[:, 1] + zc[:, 2] + zc[:, 3]) * 0.25
        g = np.empty((F, 3))
        ok = np.empty(F, dtype=bool)
        ssq = np.empty(F)
        P = self.lights
        px, py, pz = P[:, 0:1], P[:, 1:2], P[:, 2:3]
        chunk = self.chunk
        for lo in range(0, F, chunk):
            hi = min(lo + chunk, F)
            Iu = self.Iu[:, lo:hi]  # 0 where unusable
            Uf = None if self.all_usable[lo // chunk] else self.Uf[:, lo:hi]
            if self.parallel_dirs is None:
                ax = px - prob.cx[lo:hi]
                ay = py - prob.cy[lo:hi]
                az = pz - cz[lo:hi]
                r2 = ax * ax
                r2 += ay * ay
                r2 += az * az
                r3 = np.sqrt(r2)
                r3 *= r2  # |a|^3
                bx, by, bz = ax / r3, ay / r3, az / r3
                if self.weighting == "image":  # T = sum b b^T, s = sum I b
                    vx, vy, vz, Iw = bx, by, bz, Iu
                else:  # paper, Eq. 6: T = sum a a^T, s = sum |a|^3 I a
                    vx, vy, vz, Iw = ax, ay, az, Iu * r3
            else:
                D = self.parallel_dirs
                shape = Iu.shape
                bx = np.broadcast_to(D[:, 0:1], shape)
                by = np.broadcast_to(D[:, 1:2], shape)
                bz = np.broadcast_to(D[:, 2:3], shape)
                vx, vy, vz, Iw = bx, by, bz, Iu
            if Uf is None:
                ux, uy, uz = vx, vy, vz
            else:
                ux, uy, uz = vx * Uf, vy * Uf, vz * Uf
            T00 = np.einsum("kf,kf->f", ux, vx)
            T01 = np.einsum("kf,kf->f", ux, vy)
            T02 = np.einsum("kf,kf->f", ux, vz)
            T11 = np.einsum("kf,kf->f", uy, vy)
            T12 = np.einsum("kf,kf->f", uy, vz)
            T22 = np.einsum("kf,kf->f", uz, vz)
            s0 = np.einsum("kf,kf->f", vx, Iw)
            s1 = np.einsum("kf,kf->f", vy, Iw)
            s2 = np.einsum("kf,kf->f", vz, Iw)
            g0, g1, g2, okc = _chol3_solve(T00, T01, T02, T11, T12, T22, s0, s1, s2)
            g[lo:hi, 0], g[lo:hi, 1], g[lo:hi, 2] = g0, g1, g2
            ok[lo:hi] = okc
            # residual in image units, whatever the weighting: e_k = b_k . g - I_k (usable k)
            with np.errstate(invalid="ignore", over="ignore"):
                e = bx * g0
                e += by * g1
                e += bz * g2
                e -= Iu
                if Uf is not None:
                    e *= Uf
                ssq[lo:hi] = np.einsum("kf,kf->f", e, e)
        with np.errstate(invalid="ignore", over="ignore"):
            rho = np.sqrt(g[:, 0] ** 2 + g[:, 1] ** 2 + g[:, 2] ** 2)
            valid = ok & (self.nuse >= 3) & np.isfinite(rho) & (rho > 0) & np.all(np.isfinite(g), axis=1)
            n = g / rho[:, None]
        nvalid = self.nuse[valid].sum()
        rms = float(np.sqrt(ssq[valid].sum() / nvalid)) if nvalid > 0 else float("nan")
        out = {"valid": valid, "g": g, "rho": rho, "n": n, "ssq": ssq, "rms": rms}
        if want_targets:
            t = np.empty((F, 4))
            nv = n[valid]
            nzc = np.minimum(nv[:, 2], -NZ_MIN)
            t[valid] = -(nv[:, 0:1] * prob.dx + nv[:, 1:2] * prob.dy) / nzc[:, None]
            inv = ~valid
            zi = zc[inv]
            t[inv] = zi - ((zi[:, 0] + zi[:, 1] + zi[:, 2] + zi[:, 3]) * 0.25)[:, None]
            out["t"] = t
        return out


# --------------------------------------------------------------------------------------------
# drivers
# --------------------------------------------------------------------------------------------
def _setup(images, lights, pixel_size, origin, mask, depth):
    images = _images(images)
    k, H, W = images.shape
    lights = _lights(lights, k)
    pixel_size = _pair(pixel_size, "pixel_size", True)
    origin = _pair(origin, "origin", False)
    mask = _mask(mask, H, W)
    prob = _Problem(mask, pixel_size, origin)
    if depth is None:
        raise InputError("depth is required: a working distance or an (H+1, W+1) depth map")
    if isinstance(depth, Real) or np.ndim(depth) == 0:
        d = float(depth)
        if not np.isfinite(d):
            raise InputError("depth must be finite")
        z0 = np.full(prob.n, d)
        g = np.full(prob.R, d)
    else:
        dmap = np.asarray(depth, dtype=np.float64)
        if dmap.shape != (H + 1, W + 1):
            raise InputError(f"depth map must have shape {(H + 1, W + 1)} (got {dmap.shape})")
        z0 = dmap[prob.active]
        if not np.all(np.isfinite(z0)):
            raise InputError("depth map must be finite at the active vertices")
        g = np.bincount(prob.vreg, weights=z0, minlength=prob.R) / prob.vcount
    z0 = prob.gauge(z0, g)
    return images, lights, pixel_size, origin, mask, prob, z0, g


def _outputs(prob, loc, res, z, g, history, timings):
    H, W = prob.H, prob.W
    fr, fc = prob.fr, prob.fc
    valid = res["valid"]
    depth = np.full((H + 1, W + 1), np.nan)
    depth[prob.active] = z
    normals = np.full((H, W, 3), np.nan)
    n = res["n"].copy()
    inv = ~valid
    if inv.any():
        n[inv] = prob.mesh_normals(z, np.nonzero(inv)[0])
    normals[fr, fc] = n
    albedo = np.full((H, W), np.nan)
    albedo[fr, fc] = np.where(valid, res["rho"], np.nan)
    residual = np.full((H, W), np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        residual[fr, fc] = np.where(valid, np.sqrt(res["ssq"] / loc.nuse), np.nan)
    lights_used = np.zeros((H, W), dtype=np.int64)
    lights_used[fr, fc] = loc.nuse
    return {
        "depth": depth,
        "normals": normals,
        "albedo": albedo,
        "residual": residual,
        "lights_used": lights_used,
        "history": history,
        "gauge": np.asarray(g, dtype=np.float64).copy(),
        "regions": prob.regions.copy(),
        "timings": timings,
    }


def reconstruct(
    images, lights, pixel_size, origin, mask=None, depth=None, iterations=10, tol=1e-6, dark=0.0, weighting="image"
):
    """Near-light photometric stereo by mesh deformation (pure numpy/scipy reference).

    Parameters
    ----------
    images : (k, H, W) array
        Linear radiance images, one per light.
    lights : (k, 3) array
        Light positions in the camera frame (x right, y down, z forward).
    pixel_size : (w, h)
        Lateral size of a pixel (same unit as the lights and depths).
    origin : (ox, oy)
        Lateral position of the top-left corner of pixel (0, 0).
    mask : (H, W) bool array, optional
        Facets (pixels) to reconstruct; default all.
    depth : float or (H+1, W+1) array
        Working distance (initial plane and gauge of every region) or an initial vertex depth
        map (its per-region mean is the gauge). Required.
    iterations : int
        Maximum number of local/global iterations.
    tol : float
        Stop when ``max |z_new - z| <= tol * max(W*w, H*h)``.
    dark : float
        Observations ``I_k <= dark`` (and NaN) are not used.
    weighting : {"image", "paper"}
        Least squares in image units (default) or the paper's Eq. 6.

    Returns
    -------
    dict with ``depth`` (H+1, W+1), ``normals`` (H, W, 3), ``albedo`` (H, W), ``residual``
    (H, W), ``lights_used`` (H, W) int, ``history`` list of ``(dz, rms)`` per iteration,
    ``gauge`` (regions,), ``regions`` (H, W) int (-1 outside the mask), and ``timings`` (seconds
    spent in set-up, factorization, local steps and global solves). NaN outside the mask and at
    inactive vertices.
    """
    t_start = time.perf_counter()
    if weighting not in ("image", "paper"):
        raise InputError(f"weighting must be 'image' or 'paper' (got {weighting!r})")
    if not isinstance(iterations, Integral) or iterations < 0:
        raise InputError(f"iterations must be a non-negative integer (got {iterations!r})")
    tol = float(tol)
    if not (np.isfinite(tol) and tol >= 0):
        raise InputError(f"tol must be finite and >= 0 (got {tol})")
    dark = float(dark)
    if not np.isfinite(dark):
        raise InputError("dark must be finite")
    images, lights, pixel_size, origin, mask, prob, z, g = _setup(images, lights, pixel_size, origin, mask, depth)
    loc = _Local(prob, images, lights, dark, weighting)
    timings = {"setup": 0.0, "factor": 0.0, "local": 0.0, "solve": 0.0}
    t0 = time.perf_counter()
    timings["setup"] = t0 - t_start
    prob.factor()
    timings["factor"] = time.perf_counter() - t0
    L = max(prob.W * pixel_size[0], prob.H * pixel_size[1])
    history = []
    for _ in range(int(iterations)):
        t0 = time.perf_counter()
        res = loc.run(z)
        t1 = time.perf_counter()
        z_new = prob.global_step(res["t"], z, g)
        t2 = time.perf_counter()
        timings["local"] += t1 - t0
        timings["solve"] += t2 - t1
        dz = float(np.max(np.abs(z_new - z)))
        z = z_new
        history.append((dz, res["rms"]))
        if dz <= tol * L:
            break
    t0 = time.perf_counter()
    res = loc.run(z, want_targets=False)
    timings["local"] += time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_start
    return _outputs(prob, loc, res, z, g, history, timings)


def reconstruct_parallel(images, lights, pixel_size, origin, mask=None, depth=None, dark=0.0):
    """Conventional (parallel-light) photometric stereo baseline, integrated by one global step.

    One direction per light, ``l_k = (p_k - x0) / |p_k - x0|`` with ``x0`` the centroid of the
    initial surface's active vertices; no falloff. Per facet ``g = argmin sum_k (l_k . g - I_k)^2``
    over usable lights; the normals are integrated by one global step with the same matrix, pins
    and gauge as :func:`reconstruct`. Same arguments (``depth`` is required) and same outputs;
    ``history`` holds the one step; ``residual`` is in the parallel model's units.
    """
    t_start = time.perf_counter()
    dark = float(dark)
    if not np.isfinite(dark):
        raise InputError("dark must be finite")
    images, lights, pixel_size, origin, mask, prob, z, g = _setup(images, lights, pixel_size, origin, mask, depth)
    x0 = np.array([prob.vx.mean(), prob.vy.mean(), z.mean()])
    d = lights - x0
    dirs = d / np.sqrt((d * d).sum(axis=1))[:, None]
    loc = _Local(prob, images, lights, dark, "image", parallel_dirs=dirs)
    timings = {"setup": 0.0, "factor": 0.0, "local": 0.0, "solve": 0.0}
    t0 = time.perf_counter()
    timings["setup"] = t0 - t_start
    prob.factor()
    t1 = time.perf_counter()
    timings["factor"] = t1 - t0
    res = loc.run(z)
    t2 = time.perf_counter()
    z_new = prob.global_step(res["t"], z, g)
    t3 = time.perf_counter()
    timings["local"] = t2 - t1
    timings["solve"] = t3 - t2
    history = [(float(np.max(np.abs(z_new - z))), res["rms"])]
    timings["total"] = time.perf_counter() - t_start
    return _outputs(prob, loc, res, z_new, g, history, timings)
