"""The diffuse shape of the glossy model per pixel at the true points (issue 20, principled 0.5).

    python benchmarks/pbr/diffuse_shape.py /work/pbr-data/256/*-256.npz
    python benchmarks/pbr/diffuse_shape.py FILES --grid        # also the lobe-grid residuals

Each pixel's normal fitted from its observations alone at its TRUE 3-D point (as
``weighting.py``: only the local image model differs), from its Tukey fit, by Levenberg-Marquardt
on ``(rho_d n, rho_s)`` (30 steps), with the GGX lobe of nplps's glossy model and one of these
diffuse shapes ``D(n)`` (all ``n.l`` at normal incidence):

- ``lambert``  ``D = n.l``;
- ``rough``    ``D = n.l T(n.l) T(n.v) / T(1)^2``, ``T`` the rough interface's transmittance of
  the lobe (nplps today; Mitsuba's ``roughplastic``);
- ``disney``   ``D = n.l (1 + k F(n.l)) (1 + k F(n.v))``, ``F(c) = (1 - c)^5``,
  ``k = 2 R (h.l)^2 - 0.5``, ``R = sqrt(alpha)`` (Burley's diffuse with retro-reflection, as
  Mitsuba's ``principled`` evaluates it; its GGX alpha is ``R^2``).

Per scene and shape: the mean normal error (degrees) and the summed squared residual relative
to the smallest of the shapes, at the nominal lobe (roughplastic-A: alpha A; principled-R:
alpha R^2; eta 1.5). With ``--grid`` also, per shape, the lobe on the search's grids
(alpha x eta for ``rough``, alpha for the others) with the least summed residual of the fits
on a subsample, and the mean error there.
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from weighting import (
    ALPHA_GRID,
    ETA_GRID,
    Scene,
    angles,
    fresnel,
    lambert,
    lm_fit,
    load,
    nominal_alpha,
    subset,
    tukey,
    unit,
)

SHAPES = ("lambert", "rough", "disney")


def rough_table(alpha: float, eta: float, steps: int = 256, nodes: int = 24) -> np.ndarray:
    """nplps's rough transmittance T(mu) / T(1) at mu = i / steps (numpy copy of the integral)."""
    x, w = np.polynomial.legendre.leggauss(nodes)
    u, wu = 0.5 * (1 - x), 0.5 * w
    u1, u2 = np.meshgrid(u, u, indexing="ij")
    ww = np.outer(wu, wu).ravel()
    r_cos, r_sin = (np.sqrt(u1) * np.cos(2 * np.pi * u2)).ravel(), (np.sqrt(u1) * np.sin(2 * np.pi * u2)).ravel()
    a2 = alpha * alpha
    out = []
    for i in range(steps + 1):
        mu = max(i / steps, 1e-6)
        sin = np.sqrt(max(0.0, 1 - mu * mu))
        vh = np.array([alpha * sin, 0.0, mu])
        vh /= np.linalg.norm(vh)
        if vh[0] > 0:
            t1, t2 = np.array([0.0, 1, 0]), np.array([-vh[2], 0, vh[0]])
        else:
            t1, t2 = np.array([1.0, 0, 0]), np.array([0.0, 1, 0])
        s = 0.5 * (1 + vh[2])
        p1, p2 = r_cos, (1 - s) * np.sqrt(1 - r_cos**2) + s * r_sin
        p3 = np.sqrt(np.clip(1 - p1**2 - p2**2, 0, None))
        nh = p1[:, None] * t1 + p2[:, None] * t2 + p3[:, None] * vh
        m = np.stack([alpha * nh[:, 0], alpha * nh[:, 1], np.maximum(nh[:, 2], 1e-9)], -1)
        m /= np.linalg.norm(m, axis=-1, keepdims=True)
        wv = np.array([sin, 0.0, mu])
        c = m @ wv
        ok = c > 0
        cc = np.clip(c, 1e-12, 1)
        f = fresnel(cc, eta)
        ct = np.sqrt(np.clip(1 - (1 - cc * cc) / eta**2, 0, None))
        tz = -wv[2] / eta + (cc / eta - ct) * m[:, 2]
        ok &= tz < 0
        cz = -tz
        g1 = 2 * cz / (cz + np.sqrt(a2 + (1 - a2) * cz * cz))
        out.append(float((ww * np.where(ok, (1 - f) * g1, 0.0)).sum()))
    t = np.array(out)
    return t / t[-1]


class Model:
    """D and S of a diffuse shape with nplps's GGX lobe for one scene's observations."""

    def __init__(self, scene: Scene, shape: str, alpha: float, eta: float = 1.5, retro: float | None = None) -> None:
        self.shape, self.alpha, self.eta = shape, alpha, eta
        self.a2 = alpha * alpha
        half = scene.light + scene.view[:, None]
        self.half = half / np.linalg.norm(half, axis=-1, keepdims=True)
        f1 = ((eta - 1) / (eta + 1)) ** 2
        self.fshape = fresnel((scene.view[:, None] * self.half).sum(-1), eta) / f1 if f1 > 1e-12 else 1.0
        self.table = rough_table(alpha, eta) if shape == "rough" and eta != 1.0 else None
        r = np.sqrt(alpha) if retro is None else retro
        cd = (scene.light * self.half).sum(-1)
        self.k = 2 * r * cd * cd - 0.5
        self.scene = scene

    def smith(self, c: np.ndarray) -> np.ndarray:
        return 2 * c / (c + np.sqrt(self.a2 + (1 - self.a2) * c * c))

    def transmittance(self, c: np.ndarray) -> np.ndarray:
        if self.table is None:
            return np.ones_like(c)
        return np.interp(c, np.linspace(0, 1, len(self.table)), self.table)

    def shade(self, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = self.scene
        cl = np.einsum("pkj,pj->pk", s.light, n)
        cv = (n * s.view).sum(-1)[:, None]
        ch = np.einsum("pkj,pj->pk", self.half, n)
        lit = (cl > 0) & (cv > 0)
        cl_, cv_ = np.where(lit, cl, 1.0), np.where(cv > 0, cv, 1.0)
        if self.shape == "rough":
            d = cl_ * self.transmittance(cl_) * self.transmittance(cv_)
        elif self.shape == "disney":
            fl, fv = (1 - np.clip(cl_, 0, 1)) ** 5, (1 - np.clip(cv_, 0, 1)) ** 5
            d = cl_ * (1 + self.k * fl) * (1 + self.k * fv)
        else:
            d = cl_
        ggx = self.a2 / (np.pi * (ch * ch * (self.a2 - 1) + 1) ** 2)
        spec = self.fshape * ggx * self.smith(cl_) * self.smith(cv_) / (4 * cv_)
        return np.where(lit, d, 0.0), np.where(lit & (ch > 0), spec, 0.0)


def fit(scene: Scene, g: np.ndarray, model: Model, steps: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """LM on (rho_d n, rho_s) from g (rho_s 0): the normals and each pixel's squared residual."""
    theta, sse = lm_fit(scene, g, model, steps)
    return unit(theta[:, :3]), sse


def error(scene: Scene, n: np.ndarray) -> float:
    e = angles(n, scene.normals)
    return float(np.where(np.isfinite(e), e, 90.0).mean())


def run(path: str, args: argparse.Namespace) -> dict[str, Any]:
    scene = load(path, 0.0, 0)
    gb = tukey(scene, lambert(scene))
    alpha = nominal_alpha(scene.material)
    row: dict[str, Any] = {"scene": scene.name, "alpha": alpha}
    sses = {}
    for shape in SHAPES:
        n, sse = fit(scene, gb, Model(scene, shape, alpha))
        row[shape] = error(scene, n)
        sses[shape] = float(sse.sum())
    least = min(sses.values())
    row["sse"] = {k: v / least for k, v in sses.items()}
    if args.grid:
        rng = np.random.default_rng(0)
        ok = np.flatnonzero(np.isfinite(gb).all(1))
        pick = rng.choice(ok, size=min(args.sample, ok.size), replace=False)
        sub = subset(scene, pick)
        g = gb[pick]
        best: dict[str, Any] = {}
        for shape in SHAPES:
            etas = ETA_GRID if shape == "rough" else (1.5,)
            costs = {}
            for a in ALPHA_GRID:
                for e in etas:
                    n, sse = fit(sub, g, Model(sub, shape, a, e), steps=15)
                    costs[(a, e)] = (float(sse.sum()), error(sub, n))
            key = min(costs, key=lambda k: costs[k][0])
            best[shape] = (key, costs[key])
        least = min(v[1][0] for v in best.values())
        row["grid"] = {k: (v[0], v[1][0] / least, v[1][1]) for k, v in best.items()}
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("files", nargs="+")
    p.add_argument("--grid", action="store_true", help="also the least-residual lobe per shape")
    p.add_argument("--sample", type=int, default=2048)
    args = p.parse_args()
    print(
        "| scene | alpha | "
        + " | ".join(f"{s} °" for s in SHAPES)
        + " | "
        + " | ".join(f"{s} sse" for s in SHAPES)
        + " |"
    )
    for path in args.files:
        r = run(path, args)
        line = f"| {r['scene']} | {r['alpha']:.3g} | " + " | ".join(f"{r[s]:.3f}" for s in SHAPES)
        line += " | " + " | ".join(f"{r['sse'][s]:.3f}" for s in SHAPES) + " |"
        if "grid" in r:
            line += " grid: " + "; ".join(
                f"{s} a{k[0]:.2f} e{k[1]:.2f} sse {rel:.3f} {err:.3f}°" for s, (k, rel, err) in r["grid"].items()
            )
        print(line, flush=True)


if __name__ == "__main__":
    main()
