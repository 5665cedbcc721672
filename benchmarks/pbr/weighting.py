"""Highlight-aware weighting against Tukey and the glossy model, per pixel at the true points (issue 20 item 2).

    python benchmarks/pbr/weighting.py /work/pbr-data/256/*.npz
    python benchmarks/pbr/weighting.py /work/pbr-data/256/bumps-*.npz --noise 0.005 --seed 1
    python benchmarks/pbr/weighting.py FILES --full --json out.json    # also nplps's full solver
    python benchmarks/pbr/weighting.py out.json more.json              # the tables of weighting.md

What it measures: each pixel's normal fitted from its 16 observations alone, with the light
vectors taken from the TRUE 3-D point of the pixel (the centre of its facet, the mean of its four
true vertices), so that only the local image model differs between the methods (no global step,
no depth error). Point lights as nplps's ``PointLight``: ``beta_k = Phi_k (p_k - x) / |p_k - x|^3``;
the view vector is ``v = -x / |x|``. Per scene the mean and median angle (degrees) between each
fitted normal and the true facet normal over the mask:

- ``a``  Lambertian least squares over the usable observations (``I > dark``).
- ``b``  Tukey IRLS as nplps's ``robust="tukey"`` (``rust/nplps/src/local/mod.rs``): residual
  ``|rho n . r_k - I_k|``, scale ``1.4826 * median`` (the upper median of the usable ones,
  floored at ``1e-9 * max I``), biweight ``(1 - (e / 4.685 sigma)^2)^2``, 8 rounds, a pixel stops
  where fewer than 3 weights stay positive.
- ``c``  highlight-aware IRLS, started from ``b``: each round the share of the glossy model's
  specular term in each observation at the current normal,
  ``share_k = r S_k(n) / (D_k(n) + r S_k(n))`` (``D``, ``S`` of ``nplps::reflectance``: Fresnel
  transmitted diffuse, GGX lobe with Smith G1 and the Fresnel shape; checked against
  ``nplps.render(specular=...)`` to 1e-13), weights the Lambertian least squares, 8 rounds.
  Weights: ``soft`` ``w = (1 - share)^2``, ``cut.1`` ``w = [share < 0.1]`` (0.3 was tried: between
  the two), ``x tukey`` times the Tukey weight of the current fit; ``+F`` also divides each
  observation by the diffuse model's Fresnel factor ``T(n.l) T(n.v) / T(1)^2`` at the current
  normal (the glossy model's diffuse part, linearised). The lobe (alpha, eta) and the ratio
  ``r = rho_s / rho_d``:

  * ``est`` lobe found from the images: on a grid (alpha, then eta, then alpha) the one that
    minimises the summed residual of the per-pixel least-squares ``(rho_d, rho_s >= 0)`` fits at
    the Tukey normals (4096 pixels); ``r`` global: the median over the pixels of those fits'
    ``rho_s / rho_d``. Needs nothing from the user.
  * ``nom`` the lobe of the material's name (roughplastic-A: alpha A; principled-R: alpha R^2 as
    Mitsuba's principled BSDF; diffuse: alpha 0.3, a user's guess), eta 1.5; ``r`` global. The
    lobe is the truth for roughplastic (an upper bound on a user-given lobe), close for
    principled (not the same BSDF).
  * ``pix`` nominal lobe, ``r`` per pixel (its ``(rho_d, rho_s)`` refitted at each round's normal).
  * ``nplps`` (with ``--full``) the lobe nplps's glossy full solve estimated, ``r`` global: what
    the solver would have at hand.
  * ``orc`` nominal lobe, ``r`` from the fits at the TRUE normals; ``orc-n`` also the shares
    computed at the TRUE normals (one round): upper bounds of the weighting, not methods.

- ``d``  the glossy model itself fitted per pixel (model (1) of the issue): Levenberg-Marquardt on
  ``(rho_d n, rho_s)`` (numerical Jacobian, 30 steps), started from ``b``, under the estimated
  (``d est``), nplps's (``d nplps``) or the nominal (``d nom``) lobe -- nplps's
  ``reflectance="glossy"`` local fit, at the true points.

With ``--full`` also nplps's full solver at the true distance (``reconstruct(depth=distance)``:
default, ``robust="tukey"``, ``reflectance="glossy"``, each with the same ``dark``; mesh
normals, not at the true points) and the lobe nplps estimated.

``--noise S`` adds Gaussian noise of S times the image maximum (clipped at 0, as run.py),
``--seed`` its seed; ``dark`` is then 3 noise sigmas, else ``1e-6 * max`` (drops the exact zeros
of shadows). The seconds per method are numpy wall time of the vectorised fit over all pixels
divided by the pixels (microseconds a pixel): indicative of relative cost only.
"""

from __future__ import annotations

import argparse
import json
import os
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

import nplps

ETA = 1.5
IRLS_ROUNDS = 8
ALPHA_GRID = (0.04, 0.06, 0.09, 0.13, 0.19, 0.28, 0.4, 0.6, 0.85)
ETA_GRID = (1.0, 1.15, 1.3, 1.45, 1.6, 1.8, 2.1)


def angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles in degrees between vectors (..., 3)."""
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))


@dataclass
class Scene:
    """One render's pixels at their true points."""

    name: str
    material: str
    data: dict[str, Any]
    values: np.ndarray  # (P, K) observations
    usable: np.ndarray  # (P, K) I > dark
    normals: np.ndarray  # (P, 3) true facet normals
    light: np.ndarray  # (P, K, 3) unit directions to the lights
    scale: np.ndarray  # (P, K) Phi_k / |p_k - x|^2
    view: np.ndarray  # (P, 3)
    dark: float


def nominal_alpha(material: str) -> float:
    """GGX alpha of a material name (roughplastic: alpha; principled: roughness^2; diffuse: 0.3)."""
    kind, _, value = material.partition("-")
    if kind == "roughplastic":
        return float(value)
    if kind == "principled":
        return float(value) ** 2
    return 0.3


def load(path: str, noise: float, seed: int) -> Scene:
    """Read a render and put its pixels at their true facet centres."""
    with np.load(path) as f:
        data = dict(f)
    rig = json.loads(str(data["rig"]))
    K = np.asarray(rig["camera"]["K"], dtype=np.float64)
    mask = data["mask"].astype(bool)
    h, w = mask.shape
    rows, cols = np.mgrid[0 : h + 1, 0 : w + 1].astype(np.float64)
    z = data["depth"].astype(np.float64)
    verts = np.stack([(cols - 0.5 - K[0, 2]) / K[0, 0] * z, (rows - 0.5 - K[1, 2]) / K[1, 1] * z, z], -1)
    centre = 0.25 * (verts[:-1, :-1] + verts[:-1, 1:] + verts[1:, :-1] + verts[1:, 1:])
    x = centre[mask]
    images = data["images"].astype(np.float64)
    peak = float(images.max())
    dark = 1e-6 * peak
    if noise > 0:
        sigma = noise * peak
        rng = np.random.default_rng(seed)
        images = np.clip(images + rng.normal(0.0, sigma, images.shape), 0.0, None)
        dark = 3 * sigma
    values = images[:, mask].T
    pos = np.array([light["position"] for light in rig["lights"]], dtype=np.float64)
    phi = np.array([np.mean(light["intensity"]) for light in rig["lights"]], dtype=np.float64)
    d = pos[None] - x[:, None]
    dist = np.linalg.norm(d, axis=-1)
    view = -x / np.linalg.norm(x, axis=-1, keepdims=True)
    normals = data["normals"][mask].astype(np.float64)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    normals *= np.sign((normals * view).sum(-1))[:, None]
    name = os.path.basename(path).removesuffix(".npz").removesuffix("-256")
    return Scene(
        name=name,
        material=str(data["material"]),
        data=data,
        values=values,
        usable=values > dark,
        normals=normals,
        light=d / dist[..., None],
        scale=phi / dist**2,
        view=view,
        dark=dark,
    )


# --------------------------------------------------------------------------------------------------
# The glossy model (numpy copy of nplps::reflectance)
# --------------------------------------------------------------------------------------------------


def fresnel(c: np.ndarray, eta: float) -> np.ndarray:
    """Unpolarised Fresnel reflectance of a dielectric of index eta at incidence cosine c."""
    t = np.sqrt(np.clip(1.0 - (1.0 - c * c) / eta**2, 0.0, None))
    rs = (c - eta * t) / (c + eta * t)
    rp = (eta * c - t) / (eta * c + t)
    return 0.5 * (rs * rs + rp * rp)


class Lobe:
    """D and S of nplps's glossy model for one scene's observations under a lobe (alpha, eta)."""

    def __init__(self, scene: Scene, alpha: float, eta: float = ETA) -> None:
        self.alpha, self.eta = alpha, eta
        self.a2 = alpha * alpha
        half = scene.light + scene.view[:, None]
        self.half = half / np.linalg.norm(half, axis=-1, keepdims=True)
        f1 = ((eta - 1) / (eta + 1)) ** 2
        if f1 > 1e-12:
            self.fshape = fresnel((scene.view[:, None] * self.half).sum(-1), eta) / f1
        else:
            self.fshape = np.ones(self.half.shape[:2])
        self.t1 = 1.0 - f1
        self.scene = scene

    def smith(self, c: np.ndarray) -> np.ndarray:
        return 2 * c / (c + np.sqrt(self.a2 + (1 - self.a2) * c * c))

    def shade(self, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """D (P, K) and S (P, K) at the unit normals n (P, 3); 0 where n.l <= 0 or n.v <= 0."""
        s = self.scene
        cl = np.einsum("pkj,pj->pk", s.light, n)
        cv = (n * s.view).sum(-1)[:, None]
        ch = np.einsum("pkj,pj->pk", self.half, n)
        lit = (cl > 0) & (cv > 0)
        cl_, cv_ = np.where(lit, cl, 1.0), np.where(cv > 0, cv, 1.0)
        tl = (1 - fresnel(cl_, self.eta)) / self.t1
        tv = (1 - fresnel(cv_, self.eta)) / self.t1
        diffuse = np.where(lit, cl_ * tl * tv, 0.0)
        ggx = self.a2 / (np.pi * (ch * ch * (self.a2 - 1) + 1) ** 2)
        spec = self.fshape * ggx * self.smith(cl_) * self.smith(cv_) / (4 * cv_)
        return diffuse, np.where(lit & (ch > 0), spec, 0.0)


# --------------------------------------------------------------------------------------------------
# Fits
# --------------------------------------------------------------------------------------------------


def weighted_lambert(scene: Scene, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel the weighted least-squares g = rho n; returns g (P, 3) and whether it is valid."""
    r = scene.scale[..., None] * scene.light
    t = np.einsum("pk,pki,pkj->pij", w, r, r)
    s = np.einsum("pk,pki,pk->pi", w, r, scene.values)
    diag = t[:, 0, 0] * t[:, 1, 1] * t[:, 2, 2]
    ok = ((w > 0).sum(1) >= 3) & (diag > 0)
    ok &= np.linalg.det(np.where(ok[:, None, None], t, np.eye(3))) > 1e-12 * np.where(ok, diag, 1.0)
    t = np.where(ok[:, None, None], t, np.eye(3))
    g = np.linalg.solve(t, s[..., None])[..., 0]
    ok &= np.linalg.norm(g, axis=-1) > 0
    return g, ok


def unit(g: np.ndarray) -> np.ndarray:
    return g / np.linalg.norm(g, axis=-1, keepdims=True)


def lambert(scene: Scene) -> np.ndarray:
    """(a): Lambertian least squares over the usable observations."""
    g, ok = weighted_lambert(scene, scene.usable.astype(np.float64))
    g[~ok] = scene.normals[~ok] * np.nan
    return g


def upper_median(e: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """Per row the element at index count // 2 of the sorted usable values (nplps's median)."""
    srt = np.sort(np.where(usable, e, np.inf), axis=1)
    idx = np.minimum(usable.sum(1) // 2, e.shape[1] - 1)
    return srt[np.arange(len(e)), idx]


def tukey(scene: Scene, g: np.ndarray) -> np.ndarray:
    """(b): Tukey IRLS from the fit g, as nplps's robust="tukey"."""
    g = g.copy()
    active = np.isfinite(g).all(1)
    for _ in range(IRLS_ROUNDS):
        w = tukey_weights(scene, g)
        active &= (w > 0).sum(1) >= 3
        g2, ok = weighted_lambert(scene, w)
        upd = active & ok
        g[upd] = g2[upd]
        active &= ok
    return g


def ratio_fit(scene: Scene, lobe: Lobe, n: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """Per pixel the least-squares (rho_d, rho_s >= 0) at the normal n; returns rho_d, rho_s, sse."""
    d, s = lobe.shade(n)
    u = scene.usable.astype(np.float64) if w is None else w
    a, b, y = scene.scale * d, scene.scale * s, scene.values
    aa, ab, bb = (u * a * a).sum(1), (u * a * b).sum(1), (u * b * b).sum(1)
    ay, by = (u * a * y).sum(1), (u * b * y).sum(1)
    det = aa * bb - ab * ab
    with np.errstate(divide="ignore", invalid="ignore"):
        rd = (bb * ay - ab * by) / det
        rs = (aa * by - ab * ay) / det
        neg = ~(rs >= 0) | ~np.isfinite(rd)
        rd = np.where(neg, ay / aa, rd)
        rs = np.where(neg, 0.0, rs)
    sse = (u * (y - rd[:, None] * a - rs[:, None] * b) ** 2).sum(1)
    return rd, rs, sse


def global_ratio(scene: Scene, lobe: Lobe, n: np.ndarray) -> float:
    """The median over the pixels of rho_s / rho_d at the normals n."""
    rd, rs, _ = ratio_fit(scene, lobe, n)
    r = rs / rd
    r = r[np.isfinite(r) & (rd > 0)]
    return float(np.median(r)) if r.size else 0.0


def estimate_lobe(scene: Scene, n: np.ndarray, sample: int = 4096) -> tuple[float, float]:
    """The lobe (alpha, eta) on ALPHA_GRID x ETA_GRID with the least summed residual of the
    per-pixel (rho_d, rho_s) fits at the normals n (a subsample): alpha at eta 1.5, then eta,
    then alpha again (nplps's coordinate search, without its refits of the normals)."""
    rng = np.random.default_rng(0)
    ok = np.flatnonzero(np.isfinite(n).all(1))
    pick = rng.choice(ok, size=min(sample, ok.size), replace=False)
    sub = subset(scene, pick)

    def cost(alpha: float, eta: float) -> float:
        return float(ratio_fit(sub, Lobe(sub, alpha, eta), n[pick])[2].sum())

    alpha = min(ALPHA_GRID, key=lambda a: cost(a, ETA))
    eta = min(ETA_GRID, key=lambda e: cost(alpha, e))
    alpha = min(ALPHA_GRID, key=lambda a: cost(a, eta))
    return float(alpha), float(eta)


def subset(scene: Scene, pick: np.ndarray) -> Scene:
    return Scene(
        name=scene.name,
        material=scene.material,
        data=scene.data,
        values=scene.values[pick],
        usable=scene.usable[pick],
        normals=scene.normals[pick],
        light=scene.light[pick],
        scale=scene.scale[pick],
        view=scene.view[pick],
        dark=scene.dark,
    )


def soft(share: np.ndarray) -> np.ndarray:
    """w = (1 - share)^2."""
    return (1 - share) ** 2


def cut(tau: float) -> Callable[[np.ndarray], np.ndarray]:
    """w = [share < tau]."""
    return lambda share: (share < tau).astype(np.float64)


WEIGHTS = {"soft": soft, "cut.3": cut(0.3), "cut.1": cut(0.1)}


def tukey_weights(scene: Scene, g: np.ndarray) -> np.ndarray:
    """nplps's Tukey weights of the fit g (0 for unusable observations)."""
    r = scene.scale[..., None] * scene.light
    peak = np.where(scene.usable, scene.values, 0).max(1)
    e = np.abs(np.einsum("pkj,pj->pk", r, np.nan_to_num(g)) - scene.values)
    sigma = np.maximum(1.4826 * upper_median(e, scene.usable), 1e-9 * peak)
    x = e / (4.685 * sigma[:, None])
    return np.where(scene.usable & (x < 1), (1 - x * x) ** 2, 0.0)


def highlight(
    scene: Scene,
    g: np.ndarray,
    lobe: Lobe,
    ratio: float | None,
    weight: Callable[[np.ndarray], np.ndarray],
    times_tukey: bool = False,
    fresnel_diffuse: bool = False,
    at: np.ndarray | None = None,
) -> np.ndarray:
    """(c): IRLS whose weights are the predicted specular shares at the current normal.

    ``ratio`` None: r per pixel, refitted at each round's normal. ``times_tukey``: the weights
    times the Tukey weights of the current fit. ``fresnel_diffuse``: each observation divided by
    the diffuse model's Fresnel factor ``T(n.l) T(n.v) / T(1)^2`` at the current normal before
    the Lambertian fit (the diffuse part of the glossy model, linearised). ``at``: the weights
    from these normals (the true ones: an oracle), one round.
    """
    g = g.copy()
    active = np.isfinite(g).all(1)
    values = scene.values
    for _ in range(1 if at is not None else IRLS_ROUNDS):
        n = at if at is not None else unit(np.where(active[:, None], g, scene.normals))
        d, s = lobe.shade(n)
        if ratio is None:
            rd, rs, _ = ratio_fit(scene, lobe, n)
            r: Any = np.where(rd > 0, rs / np.where(rd > 0, rd, 1.0), 0.0)[:, None]
        else:
            r = ratio
        total = d + r * s
        share = np.where(total > 0, r * s / np.where(total > 0, total, 1.0), 0.0)
        w = np.where(scene.usable, weight(share), 0.0)
        if times_tukey:
            scene.values = values
            w = w * tukey_weights(scene, g)
        if fresnel_diffuse:
            cl = np.einsum("pkj,pj->pk", scene.light, n)
            factor = np.where((d > 0) & (cl > 0), d / np.where(cl > 0, cl, 1.0), 1.0)
            scene.values = values / factor
        g2, ok = weighted_lambert(scene, w)
        scene.values = values
        upd = active & ok
        g[upd] = g2[upd]
        active &= ok
    return g


class Shading(Protocol):
    """A per-pixel reflectance model: the diffuse and specular factors of each observation for normals n."""

    def shade(self, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


def lm_fit(scene: Scene, g: np.ndarray, model: Shading, steps: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on (b = rho_d n, rho_s) per pixel from the fit g (rho_s 0) under `model`.

    Returns the unknowns (pixels x 4: b, rho_s) and each pixel's squared residual.
    """
    u = scene.usable.astype(np.float64)
    bad = ~np.isfinite(g).all(1)
    theta = np.concatenate([np.where(bad[:, None], scene.normals * 0.1, g), np.zeros((len(g), 1))], 1)

    def residual(th: np.ndarray) -> np.ndarray:
        rho = np.linalg.norm(th[:, :3], axis=-1)
        d, s = model.shade(th[:, :3] / rho[:, None])
        return u * (scene.values - scene.scale * (rho[:, None] * d + th[:, 3:4] * s))

    res = residual(theta)
    sse = (res**2).sum(1)
    lam = np.full(len(g), 1e-3)
    for _ in range(steps):
        jac = np.empty((*res.shape, 4))
        for j in range(4):
            h = 1e-6 * np.maximum(np.abs(theta[:, j]), 1e-3 * np.linalg.norm(theta[:, :3], axis=-1))
            th = theta.copy()
            th[:, j] += h
            jac[..., j] = (residual(th) - res) / h[:, None]
        jtj = np.einsum("pki,pkj->pij", jac, jac)
        jtr = np.einsum("pki,pk->pi", jac, res)
        a = jtj + lam[:, None, None] * (np.eye(4) * np.diagonal(jtj, axis1=1, axis2=2)[:, None] + 1e-12 * np.eye(4))
        step = -np.linalg.solve(a, jtr[..., None])[..., 0]
        new = theta + step
        new[:, 3] = np.maximum(new[:, 3], 0.0)
        res2 = residual(new)
        sse2 = (res2**2).sum(1)
        better = np.isfinite(sse2) & (sse2 < sse)
        theta[better], res[better], sse[better] = new[better], res2[better], sse2[better]
        lam = np.where(better, lam * 0.3, lam * 10)
    return theta, sse


def glossy(scene: Scene, g: np.ndarray, lobe: Lobe, steps: int = 30) -> np.ndarray:
    """(d): Levenberg-Marquardt on (b = rho_d n, rho_s) per pixel from the fit g (rho_s 0)."""
    return lm_fit(scene, g, lobe, steps)[0][:, :3]


# --------------------------------------------------------------------------------------------------
# The comparison
# --------------------------------------------------------------------------------------------------


def full_solver(scene: Scene) -> dict[str, Any]:
    """nplps's full solver at the true distance: default, tukey, glossy (mesh normals)."""
    data = scene.data
    rig = nplps.Rig.from_dict(json.loads(str(data["rig"])))
    mask = data["mask"].astype(bool)
    images = np.zeros_like(data["images"], dtype=np.float32)
    images[:, mask] = scene.values.T
    out: dict[str, Any] = {}
    runs: list[tuple[str, dict[str, Any]]] = [
        ("default", {}),
        ("tukey", {"robust": "tukey"}),
        ("glossy", {"reflectance": "glossy"}),
    ]
    for label, opts in runs:
        start = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = nplps.reconstruct(images, rig, depth=float(data["distance"]), mask=mask, dark=scene.dark, **opts)
        err = angles(result.normals[mask], data["normals"][mask])
        out[label] = {
            "mean": float(np.nanmean(err)),
            "median": float(np.nanmedian(err)),
            "seconds": time.perf_counter() - start,
        }
        if result.lobe is not None:
            out["lobe"] = float(result.lobe.roughness)
            out["lobe_eta"] = float(result.lobe.eta)
    return out


def run(path: str, args: argparse.Namespace) -> dict[str, Any]:
    """All the fits of one scene; returns the errors and timings."""
    scene = load(path, args.noise, args.seed)
    pixels = len(scene.values)
    row: dict[str, Any] = {"scene": scene.name, "material": scene.material, "pixels": pixels}
    errors: dict[str, tuple[float, float]] = {}
    micro: dict[str, float] = {}

    def record(label: str, g: np.ndarray, seconds: float) -> None:
        err = angles(unit(g), scene.normals)
        err = np.where(np.isfinite(err), err, 90.0)  # a failed fit counts as 90 degrees
        errors[label] = (float(err.mean()), float(np.median(err)))
        micro[label] = 1e6 * seconds / pixels

    def timed(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> tuple[Any, float]:
        start = time.perf_counter()
        out = fn(*args, **kwargs)
        return out, time.perf_counter() - start

    ga, ta = timed(lambert, scene)
    record("a", ga, ta)
    gb, tb = timed(tukey, scene, ga)
    record("b", gb, tb + ta)
    nb = unit(np.where(np.isfinite(gb).all(1)[:, None], gb, scene.normals))

    alpha_nom = nominal_alpha(scene.material)
    lobe_est, t_est = timed(estimate_lobe, scene, nb)
    row.update(alpha_nominal=alpha_nom, lobe_estimated=lobe_est, lobe_seconds=t_est)
    lobes = {"nom": Lobe(scene, alpha_nom), "est": Lobe(scene, *lobe_est)}
    ratios = {
        "nom": global_ratio(scene, lobes["nom"], nb),
        "est": global_ratio(scene, lobes["est"], nb),
        "orc": global_ratio(scene, lobes["nom"], scene.normals),
    }
    full = full_solver(scene) if args.full else None
    if full is not None and "lobe" in full:
        lobes["nplps"] = Lobe(scene, full["lobe"], full["lobe_eta"])
        ratios["nplps"] = global_ratio(scene, lobes["nplps"], nb)
    row["ratios"] = ratios
    base = ta + tb
    runs: list[tuple[str, str, float | None, str, dict[str, Any]]] = [
        ("c est soft", "est", ratios["est"], "soft", {}),
        ("c est cut.1", "est", ratios["est"], "cut.1", {}),
        ("c est soft x tukey", "est", ratios["est"], "soft", {"times_tukey": True}),
        ("c nom cut.1", "nom", ratios["nom"], "cut.1", {}),
        ("c nom cut.1 +F", "nom", ratios["nom"], "cut.1", {"fresnel_diffuse": True}),
        ("c pix cut.1", "nom", None, "cut.1", {}),
        ("c orc cut.1", "nom", ratios["orc"], "cut.1", {}),
        ("c orc-n cut.1", "nom", ratios["orc"], "cut.1", {"at": scene.normals}),
    ]
    if "nplps" in lobes:
        for label, extra in (
            ("c nplps cut.1", {}),
            ("c nplps cut.1 x tukey", {"times_tukey": True}),
            ("c nplps cut.1 x tukey +F", {"times_tukey": True, "fresnel_diffuse": True}),
        ):
            runs.append((label, "nplps", ratios["nplps"], "cut.1", extra))
    for label, lobe_name, ratio, wname, extra in runs:
        g, t = timed(highlight, scene, gb, lobes[lobe_name], ratio, WEIGHTS[wname], **extra)
        record(label, g, t + base)
    if not args.no_glossy:
        for variant in [v for v in ("est", "nplps", "nom") if v in lobes]:
            g, t = timed(glossy, scene, gb, lobes[variant])
            record(f"d {variant}", g, t + base)
    row["errors"] = errors
    row["us_per_pixel"] = micro
    if full is not None:
        row["full"] = full
    return row


MAIN = [
    "a",
    "b",
    "c est soft",
    "c est cut.1",
    "c est soft x tukey",
    "c nplps cut.1",
    "c nplps cut.1 x tukey",
    "c nplps cut.1 x tukey +F",
    "c nom cut.1",
    "c nom cut.1 +F",
    "c pix cut.1",
    "c orc cut.1",
    "c orc-n cut.1",
    "d est",
    "d nplps",
    "d nom",
]


KEY = ["a", "b", "c est soft x tukey", "c nplps cut.1 x tukey", "c nplps cut.1 x tukey +F", "c orc-n cut.1", "d nplps"]


def summarise(paths: list[str]) -> None:
    """Print the markdown tables of weighting.md from saved --json files."""
    runs = []
    for path in paths:
        with open(path) as f:
            runs.append(json.load(f))
    clean = [row for run in runs if run["noise"] == 0 for row in run["rows"]]
    noisy = [(run["seed"], row) for run in runs if run["noise"] > 0 for row in run["rows"]]
    order = {shape: i for i, shape in enumerate(("sphere", "bumps", "torus", "shadows"))}
    clean.sort(key=lambda r: (order.get(r["scene"].split("-")[0], 9), r["scene"]))
    if clean:
        print("### Noise-free, mean (median) degrees\n")
        head = [*KEY, "full tukey", "full glossy"]
        print("| scene | " + " | ".join(head) + " | nplps lobe |")
        print("|" + "---|" * (len(head) + 2))
        for row in clean:
            e, f = row["errors"], row.get("full", {})
            cells = [f"{e[m][0]:.2f} ({e[m][1]:.2f})" if m in e else "" for m in KEY]
            cells += [f"{f[m]['mean']:.2f} ({f[m]['median']:.2f})" if m in f else "" for m in ("tukey", "glossy")]
            lobe = f"{f['lobe']:.2f}, {f['lobe_eta']:.2f}" if "lobe" in f else ""
            print(f"| {row['scene']} | " + " | ".join(cells) + f" | {lobe} |")
        labels = [m for m in MAIN if any(m in row["errors"] for row in clean)]
        print("\n### Noise-free, every variant, mean degrees\n")
        print("| scene | " + " | ".join(labels) + " | full default | lobe est |")
        print("|" + "---|" * (len(labels) + 3))
        for row in clean:
            e, f = row["errors"], row.get("full", {})
            cells = [f"{e[m][0]:.2f}" if m in e else "" for m in labels]
            default = f"{f['default']['mean']:.2f}" if "default" in f else ""
            alpha, eta = row["lobe_estimated"]
            print(f"| {row['scene']} | " + " | ".join(cells) + f" | {default} | {alpha:.2g}, {eta:.2g} |")
    if noisy:
        seeds = sorted({seed for seed, _ in noisy})
        print(f"\n### Noise {runs[-1]['noise']}, seeds {seeds}: mean degrees, average over the seeds [min, max]\n")
        head = [*KEY, "full tukey", "full glossy"]
        print("| scene | " + " | ".join(head) + " | ranking per seed |")
        print("|" + "---|" * (len(head) + 2))
        for scene in sorted({row["scene"] for _, row in noisy}):
            rows = [(seed, row) for seed, row in noisy if row["scene"] == scene]
            cells = []
            for m in head:
                if m.startswith("full "):
                    values = [row["full"][m[5:]]["mean"] for _, row in rows if "full" in row]
                else:
                    values = [row["errors"][m][0] for _, row in rows if m in row["errors"]]
                cells.append(f"{np.mean(values):.2f} [{min(values):.2f}, {max(values):.2f}]" if values else "")
            rank = []
            for _, row in sorted(rows, key=lambda sr: sr[0]):
                ranked = sorted(("a", "b", "c nplps cut.1 x tukey", "d nplps"), key=lambda m: row["errors"][m][0])
                rank.append(" < ".join(m.split(" ")[0] for m in ranked))
            print(f"| {scene} | " + " | ".join(cells) + " | " + "; ".join(rank) + " |")
    allrows = clean + [row for _, row in noisy]
    print("\n### Cost: microseconds a pixel (numpy, cumulative), median over the runs\n")
    labels = [m for m in MAIN if any(m in row["us_per_pixel"] for row in allrows)]
    print("| " + " | ".join(labels) + " |")
    print("|" + "---|" * len(labels))
    print(
        "| "
        + " | ".join(
            f"{np.median([r['us_per_pixel'][m] for r in allrows if m in r['us_per_pixel']]):.0f}" for m in labels
        )
        + " |"
    )
    full = [row["full"] for row in allrows if "full" in row]
    if full:
        print(
            "\nnplps full solver, median seconds: "
            + ", ".join(f"{m} {np.median([f[m]['seconds'] for f in full]):.2f}" for m in ("default", "tukey", "glossy"))
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("files", nargs="+")
    parser.add_argument("--noise", type=float, default=0.0, help="Gaussian noise, a fraction of the maximum")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--full", action="store_true", help="also nplps's full solver (and its lobe)")
    parser.add_argument("--no-glossy", action="store_true", help="skip the per-pixel glossy fits (d)")
    parser.add_argument("--json", help="write the numbers to this file")
    args = parser.parse_args()
    if all(path.endswith(".json") for path in args.files):
        summarise(args.files)
        return
    print(f"noise {args.noise}, seed {args.seed}: mean (median) normal error, degrees, at the true points\n")
    rows = []
    header = None
    for path in args.files:
        row = run(path, args)
        rows.append(row)
        labels = [m for m in MAIN if m in row["errors"]]
        if header is None:
            full = " | full default | full tukey | full glossy (lobe) |" if args.full else " |"
            header = "| scene | alpha nom / est, eta | " + " | ".join(labels) + full
            print(header)
            print("|" + "---|" * (header.count("|") - 1))
        cells = [f"{row['errors'][m][0]:.2f} ({row['errors'][m][1]:.2f})" for m in labels]
        alpha, eta = row["lobe_estimated"]
        line = f"| {row['scene']} | {row['alpha_nominal']:.2g} / {alpha:.2g}, {eta:.2g} | " + " | ".join(cells) + " |"
        if args.full:
            f = row["full"]
            lobe = f"{f.get('lobe', float('nan')):.2f}, {f.get('lobe_eta', float('nan')):.2f}"
            line += f" {f['default']['mean']:.2f} | {f['tukey']['mean']:.2f} | {f['glossy']['mean']:.2f} ({lobe}) |"
        print(line, flush=True)
    print("\nmicroseconds a pixel (numpy, cumulative: c and d include a and b):")
    for row in rows:
        print(row["scene"], {k: round(v, 1) for k, v in row["us_per_pixel"].items()})
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"noise": args.noise, "seed": args.seed, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
