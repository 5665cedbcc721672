"""Surface-from-gradient baselines for the paper's Fig. 7 (comparison only, not package code).

The paper (Sec. 5, Fig. 7) integrates the normal field of parallel-light photometric stereo with
DGP [20], Poisson [21], an M-estimator [22] and a regularization [23] to show that the shape
error comes from the parallel-light assumption, not from the integrator. Two of them are written
here in numpy, on the pixel-centre grid of an orthographic camera (spacing ``w`` along x =
columns, ``h`` along y = rows):

- :func:`poisson`: least squares on the forward differences, ``min sum (z[i,j+1] - z[i,j] -
  gx)^2 + (z[i+1,j] - z[i,j] - gy)^2`` with ``gx``, ``gy`` the gradients averaged onto the edges.
  Its normal equations are the Neumann Laplacian, diagonalized by the DCT-II; the DCT is done with
  numpy's FFT on the even (mirrored) extension.
- :func:`robust`: the same functional under an M-estimator (Cauchy weights ``1 / (1 + (r/s)^2)``
  with ``s`` 1.4826 times the median absolute residual), by iteratively reweighted least squares;
  each weighted system is solved by conjugate gradients preconditioned with the Poisson solve.

The integrated depth is defined up to a constant; callers align it (mean of the true depth).
"""

from __future__ import annotations

import numpy as np

__all__ = ["gradients", "normals_from_depth", "poisson", "robust"]


def gradients(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depth gradients (dz/dx, dz/dy) of an (H, W, 3) normal field (OpenCV frame, n_z < 0).

    A surface z(x, y) has the normal (z_x, z_y, -1) / |.|, so z_x = -n_x / n_z. Normals too close
    to grazing (|n_z| < 0.05) or not finite give a zero gradient.
    """
    nz = normals[..., 2]
    ok = np.isfinite(normals).all(-1) & (np.abs(nz) >= 0.05)
    safe = np.where(ok, nz, -1.0)
    p = np.where(ok, -normals[..., 0] / safe, 0.0)
    q = np.where(ok, -normals[..., 1] / safe, 0.0)
    return p, q


def normals_from_depth(z: np.ndarray, w: float, h: float) -> np.ndarray:
    """Unit normals (H, W, 3) of a depth map on the pixel-centre grid, by central differences."""
    zy, zx = np.gradient(z, h, w)
    n = np.stack([zx, zy, -np.ones_like(z)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _edges(p: np.ndarray, q: np.ndarray, w: float, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Depth differences the gradients ask for along the x edges (H, W-1) and y edges (H-1, W)."""
    return 0.5 * (p[:, 1:] + p[:, :-1]) * w, 0.5 * (q[1:, :] + q[:-1, :]) * h


def _adjoint(ex: np.ndarray, ey: np.ndarray) -> np.ndarray:
    """A^T e for the forward-difference operator A (edges x nodes)."""
    out = np.zeros((ey.shape[0] + 1, ex.shape[1] + 1))
    out[:, :-1] -= ex
    out[:, 1:] += ex
    out[:-1, :] -= ey
    out[1:, :] += ey
    return out


def _apply(z: np.ndarray, wx: np.ndarray, wy: np.ndarray) -> np.ndarray:
    """A^T W A z: the weighted Neumann Laplacian."""
    return _adjoint(wx * (z[:, 1:] - z[:, :-1]), wy * (z[1:, :] - z[:-1, :]))


def _solve_laplacian(rhs: np.ndarray) -> np.ndarray:
    """Solve A^T A z = rhs (Neumann Laplacian) by the DCT-II, zero-mean solution."""
    hh, ww = rhs.shape
    ext = np.concatenate([rhs, rhs[::-1]], axis=0)
    ext = np.concatenate([ext, ext[:, ::-1]], axis=1)
    ly = 2.0 - 2.0 * np.cos(np.pi * np.arange(2 * hh) / hh)
    lx = 2.0 - 2.0 * np.cos(np.pi * np.arange(2 * ww) / ww)
    denom = ly[:, None] + lx[None, :]
    denom[0, 0] = 1.0
    spec = np.fft.fft2(ext) / denom
    spec[0, 0] = 0.0
    z: np.ndarray = np.real(np.fft.ifft2(spec))[:hh, :ww]
    return z - z.mean()


def poisson(p: np.ndarray, q: np.ndarray, w: float, h: float) -> np.ndarray:
    """Least-squares (Poisson) integration of the gradient field (p, q); zero-mean depth (H, W)."""
    ex, ey = _edges(p, q, w, h)
    return _solve_laplacian(_adjoint(ex, ey))


def _pcg(rhs: np.ndarray, wx: np.ndarray, wy: np.ndarray, z0: np.ndarray, iters: int = 300) -> np.ndarray:
    """Conjugate gradients on A^T W A z = rhs, preconditioned by the unweighted Poisson solve."""
    z = z0.copy()
    r = rhs - _apply(z, wx, wy)
    r -= r.mean()
    s = _solve_laplacian(r)
    d = s.copy()
    rs = float((r * s).sum())
    norm0 = float(np.sqrt((rhs * rhs).sum())) + 1e-300
    for _ in range(iters):
        if np.sqrt((r * r).sum()) < 1e-10 * norm0:
            break
        ad = _apply(d, wx, wy)
        alpha = rs / float((d * ad).sum())
        z += alpha * d
        r -= alpha * ad
        s = _solve_laplacian(r)
        rs_new = float((r * s).sum())
        d = s + (rs_new / rs) * d
        rs = rs_new
    return z - z.mean()


def robust(p: np.ndarray, q: np.ndarray, w: float, h: float, *, rounds: int = 10) -> np.ndarray:
    """M-estimator (Cauchy) integration of (p, q) by IRLS, from the Poisson solution; zero-mean depth."""
    ex, ey = _edges(p, q, w, h)
    z = _solve_laplacian(_adjoint(ex, ey))
    for _ in range(rounds):
        rx = (z[:, 1:] - z[:, :-1]) - ex
        ry = (z[1:, :] - z[:-1, :]) - ey
        scale = 1.4826 * float(np.median(np.abs(np.concatenate([rx.ravel(), ry.ravel()]))))
        scale = max(scale, 1e-6 * max(w, h))
        wx = 1.0 / (1.0 + (rx / scale) ** 2)
        wy = 1.0 / (1.0 + (ry / scale) ** 2)
        z = _pcg(_adjoint(wx * ex, wy * ey), wx, wy, z)
    return z
