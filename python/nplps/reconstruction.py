"""The result of a reconstruction (:class:`Reconstruction`), its parts, and writing it to files.

A result carries two normals per pixel. :attr:`Reconstruction.normals` are the mesh's own facet
normals (the cross product of each quad's diagonals): the surface that was reconstructed, and
the normals the normal map, ``normals.npy``, the PLY/OBJ vertex normals and the shaded picture
use. :attr:`Reconstruction.fit_normals` are the local step's per-pixel fits, which the model
fitted jointly with the albedo: :meth:`Reconstruction.predict` (and so held-out evaluation)
shades with them. On noisy images the mesh normals are the more accurate (docs/method.md).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from . import _core, export
from . import report as report_module
from ._checks import _check_rig, _light_indices
from ._outdir import result_directory
from ._records import DistanceCheck, DistanceEstimate, LightRefinement, Lobe, LobeCheck
from .errors import InputError
from .rig import Rig, _select_core_lights
from .types import Iteration, _iteration

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

    from ._held_out import HeldOutScores
    from .types import Method, Status

__all__ = [
    "SHADED_LIGHT",
    "DistanceCheck",
    "DistanceEstimate",
    "Iteration",
    "LightRefinement",
    "Lobe",
    "LobeCheck",
    "Reconstruction",
    "light_changes",
]

#: The default light of :meth:`Reconstruction.shaded` (and ``shaded.png``): the direction towards it
#: in the camera frame, from the upper left and in front (negative x: left, negative y: up,
#: negative z: towards the camera),
#: 50 degrees off the viewing axis.
SHADED_LIGHT: tuple[float, float, float] = (-0.5417, -0.5417, -0.6428)


def light_changes(before: Rig, after: Rig) -> list[dict[str, Any]]:
    """How each light changed from one rig to another (e.g. by ``refine_lights``).

    Parameters
    ----------
    before, after : Rig
        Rigs with the same lights in the same order.

    Returns
    -------
    list of dict
        Per light: ``light`` (its index), ``intensity_factor`` (after / before, mean over
        channels) and ``position_shift`` (x, y, z in scene units; None for a directional light).
    """
    rows = []
    for i in range(before.n_lights):
        factor = float(np.mean(after.intensities[i] / before.intensities[i]))
        shift = None
        if not before.directional[i]:
            shift = [float(v) for v in after.positions[i] - before.positions[i]]
        rows.append({"light": i, "intensity_factor": factor, "position_shift": shift})
    return rows


@dataclass(repr=False)
class Reconstruction:
    """A reconstructed surface, as :func:`nplps.reconstruct` returns it.

    Per-pixel arrays are (H, W[, 3]), per-vertex arrays (H+1, W+1[, 3]); values outside the mask
    are NaN (0 for `lights_used`).

    Attributes
    ----------
    depth : numpy.ndarray
        Vertex depths z (H+1, W+1).
    fit_normals : numpy.ndarray
        The local step's per-pixel unit normals (H, W, 3), fitted jointly with the albedo to each
        pixel's observations at the final surface; facing the camera (n_z < 0). Pixels with
        fewer than 3 usable lights hold the mesh normal. :meth:`predict` shades with these.
    albedo : numpy.ndarray
        Fitted albedo (H, W), or (H, W, 3) for colour images; NaN where a pixel had fewer than 3
        usable lights.
    residual : numpy.ndarray
        RMS image residual of each pixel's fit (H, W), in image units.
    lights_used : numpy.ndarray
        Number of usable (lit) lights of each pixel (H, W).
    regions : numpy.ndarray
        Region label of each pixel (H, W), -1 outside the mask.
    gauge : numpy.ndarray
        Mean vertex depth of each region (the gauge).
    history : list of Iteration
        One entry per iteration (with ``depth="auto"``: of the final run at the estimate; the
        search's evaluations are in ``distance.curve``).
    converged : bool
        Whether the tolerance was reached within the iteration limit (exactly when `status` is
        "converged").
    mask : numpy.ndarray
        The mask (H, W) that was reconstructed.
    rig : Rig
        The rig of the result: the given one, or the refined one with ``refine_lights``.
    timings : dict of str to float
        Seconds spent in factorization, local steps, solves and in total.
    method : {"near", "parallel"}
        "near" for the near-light method, "parallel" for the conventional baseline.
    status : {"converged", "stalled", "diverged", "degenerate"}
        How the run ended: the depth change reached ``tol``; stopped at the iteration limit or
        without progress for 50 iterations; the depth changes grew; or more than half of the
        masked pixels could not be fitted and kept the starting shape.
    status_reason : str
        One sentence explaining `status`, with the numbers.
    distance : DistanceEstimate or None
        The distance search, when ``depth="auto"``.
    distance_check : DistanceCheck or None
        With a given distance (``check_distance=True``, the default): how it compares with the
        distance a quick coarse search prefers; None when the rig cannot reveal the distance.
    refinement : LightRefinement or None
        The self-calibration of the lights, when ``refine_lights`` was given; `rig` then holds
        the refined lights.
    input_rig : Rig or None
        The rig given to the reconstruction when the lights were refined (else None: it is
        `rig`).
    lobe : Lobe or None
        With ``reflectance="glossy"``: the specular lobe (given, or estimated from the images).
        `albedo` is then the diffuse albedo.
    matte_lobe : Lobe or None
        With ``reflectance="glossy"`` and the lobe estimated: the lobe found when it was too
        rough to be a highlight (roughness 0.5 or more): the images
        show none, so the solver went on with the Lambertian model and `lobe` is None (a
        warning says so), or when the glossy model predicted held-out lights worse than the
        Lambertian one (see `lobe_check`). None otherwise.
    lobe_check : LobeCheck or None
        With ``reflectance="glossy"`` and the lobe estimated: the held-out prediction errors of
        the glossy and the Lambertian model; the glossy model is kept only where it predicts
        better. None otherwise.
    specular : numpy.ndarray or None
        With ``reflectance="glossy"``: the specular albedo of each pixel (H, W).
    shadow_bits : numpy.ndarray or None
        With ``shadows=True``: the cast shadows the last local steps used, bit-packed (H, W,
        ceil(k / 64)) uint64 (bit ``k % 64`` of word ``k // 64`` is light k); :attr:`shadows`
        unpacks them.
    dark : float or None
        The shadow threshold the fits used (observations at or below it were left out): the
        given ``dark``, or by default 3 times `noise` (at least one level above black for integer
        images). None for a result read back without it.
    noise : float or None
        The image noise (standard deviation, on the scale of the loaded images) that
        :func:`nplps.estimate_noise` measured for the default `dark`; None when ``dark`` was given.
    normal_sigma : numpy.ndarray or None
        Near-light runs: the predicted uncertainty of each pixel's fitted normal (H, W) float32,
        degrees: ``sqrt(trace Cov(n))``, the RMS angle between the fitted and the true normal that
        the image noise alone gives, from the covariance ``s^2 (S^T W S)^-1`` of the pixel's
        linear Lambertian fit at the final surface (``s^2`` its residual variance) projected on
        the tangent plane (docs/trust.md). NaN outside the mask and where fewer than 4 lights
        were usable. Under the glossy model it is the Lambertian fit's. None for the baseline.
    held_out_error : numpy.ndarray or None
        Near-light runs: each pixel's leave-one-light-out re-rendering error (H, W) float32,
        image units: the mean over its usable lights of ``|I_k - prediction of I_k by a fit
        without light k|`` (the linear Lambertian fit's ``e_k / (1 - h_kk)``). NaN as
        `normal_sigma`.
    light_trust : dict of str to numpy.ndarray or None
        Near-light runs, per light (arrays of k): ``residual`` (RMS residual of its observations,
        image units), ``held_out`` (RMS leave-one-out residual), ``mean_intensity`` (mean usable
        observation) and ``facets`` (pixels that used it), from the same fits.

    Notes
    -----
    :attr:`normals` (the mesh's facet normals) and :attr:`fit_normals` (the per-pixel fits) are
    both estimates of the surface normal. ``benchmarks/normals.py`` measured the mesh normals at
    0.55 times the fits' error on noisy synthetic scenes (all 54 case groups) and 0.05 to 0.22
    degrees behind them on DiLiGenT's ball (docs/method.md), so they are the default: the normal
    map, ``normals.npy``, the PLY/OBJ vertex normals and the shaded picture use them.
    """

    depth: np.ndarray
    fit_normals: np.ndarray
    albedo: np.ndarray
    residual: np.ndarray
    lights_used: np.ndarray
    regions: np.ndarray
    gauge: np.ndarray
    history: list[Iteration]
    converged: bool
    mask: np.ndarray
    rig: Rig
    timings: dict[str, float] = field(default_factory=dict)
    method: Method = "near"
    status: Status = "converged"
    status_reason: str = ""
    distance: DistanceEstimate | None = None
    refinement: LightRefinement | None = None
    input_rig: Rig | None = None
    distance_check: DistanceCheck | None = None
    lobe: Lobe | None = None
    matte_lobe: Lobe | None = None
    lobe_check: LobeCheck | None = None
    specular: np.ndarray | None = None
    shadow_bits: np.ndarray | None = None
    dark: float | None = None
    noise: float | None = None
    normal_sigma: np.ndarray | None = None
    held_out_error: np.ndarray | None = None
    light_trust: dict[str, np.ndarray] | None = None

    @classmethod
    def _from_core(
        cls,
        out: Mapping[str, Any],
        mask: np.ndarray,
        rig: Rig,
        method: Method,
        *,
        dark: float | None = None,
        noise: float | None = None,
    ) -> Reconstruction:
        refinement = _refinement(out.get("refinement"))
        input_rig = None
        if refinement is not None:
            input_rig, rig = rig, Rig._from_native(out["lights"], like=rig)
        return cls(
            depth=out["depth"],
            fit_normals=out["normals"],
            albedo=out["albedo"],
            residual=out["residual"],
            lights_used=out["lights_used"],
            regions=out["regions"],
            gauge=out["gauge"],
            history=[_iteration(h) for h in out["history"]],
            converged=bool(out["converged"]),
            mask=mask,
            rig=rig,
            timings=dict(out["timings"]),
            method=method,
            status=out["status"],
            status_reason=str(out["status_reason"]),
            distance=_distance(out.get("distance_estimate")),
            refinement=refinement,
            input_rig=input_rig,
            distance_check=_distance_check(out.get("distance_check")),
            lobe=None if "lobe" not in out else _lobe(out["lobe"], out.get("lobe_diffuse", "transmitted")),
            matte_lobe=None if "matte_lobe" not in out else _lobe(out["matte_lobe"], "transmitted"),
            lobe_check=None if "lobe_check" not in out else _lobe_check(out["lobe_check"]),
            specular=out.get("specular"),
            shadow_bits=out.get("shadow_bits"),
            dark=dark,
            noise=noise,
            normal_sigma=out.get("normal_sigma"),
            held_out_error=out.get("held_out_error"),
            light_trust=None if "light_trust" not in out else {k: np.asarray(v) for k, v in out["light_trust"].items()},
        )

    def light_changes(self) -> list[dict[str, Any]]:
        """How the refinement changed each light (see :func:`nplps.light_changes`).

        Returns
        -------
        list of dict
            One entry per light; empty without refinement.
        """
        if self.input_rig is None:
            return []
        return light_changes(self.input_rig, self.rig)

    def _trust_summary(self) -> dict[str, Any] | None:
        """Return the trust figures of ``summary.json`` (None without them: the parallel baseline)."""
        if self.normal_sigma is None or self.held_out_error is None:
            return None
        lights = []
        if self.light_trust is not None:
            t = self.light_trust
            for i in range(len(t["residual"])):
                lights.append(
                    {
                        "light": i,
                        "residual": _finite(t["residual"][i]),
                        "held_out": _finite(t["held_out"][i]),
                        "mean_intensity": _finite(t["mean_intensity"][i]),
                        "pixels": int(t["facets"][i]),
                    }
                )
        # One Rust function (``nplps._core.trust_figures``): the order statistics selected by
        # radix passes over the maps and numpy's pairwise sums for the means, with no masked copy
        # and no float64 widening of the maps; the same numbers as numpy's ``median``,
        # ``percentile(.., 90)`` and ``mean`` of the float64 values inside (tests/test_save_speed.py).
        sigma, held = np.asarray(self.normal_sigma), np.asarray(self.held_out_error)
        if not (sigma.dtype == held.dtype == np.float32):
            sigma, held = sigma.astype(np.float64), held.astype(np.float64)  # exact for float32
        pixels, sigma_median, sigma_p90, sigma_rms, held_mean, held_median, held_p90 = _core.trust_figures(
            np.ascontiguousarray(self.mask, dtype=bool), np.ascontiguousarray(sigma), np.ascontiguousarray(held)
        )
        if not pixels:
            return {"pixels": 0, "normal_sigma_deg": None, "held_out_error": None, "lights": lights}
        return {
            "pixels": pixels,
            "normal_sigma_deg": {"median": sigma_median, "p90": sigma_p90, "rms": sigma_rms},
            "held_out_error": {"mean": held_mean, "median": held_median, "p90": held_p90},
            "lights": lights,
        }

    def _shadow_summary(self) -> dict[str, Any] | None:
        """With ``shadows=True``: the share of the masked observations in a cast shadow, overall and per light."""
        shadows = self.shadows
        if shadows is None:
            return None
        inside = shadows[:, self.mask]
        per_light = inside.mean(axis=1) if inside.size else np.zeros(len(shadows))
        return {"share": float(inside.mean()) if inside.size else 0.0, "per_light": [float(v) for v in per_light]}

    @property
    def shadows(self) -> np.ndarray | None:
        """The cast shadows (k, H, W) bool the fits left out (``shadows=True``; else None).

        True where the final mesh (as the last local steps saw it) hides the pixel from the light;
        unpacked from :attr:`shadow_bits` on each access (k bytes a pixel).
        """
        if self.shadow_bits is None:
            return None
        k = self.rig.n_lights
        bits = np.ascontiguousarray(self.shadow_bits, dtype="<u8")
        flat = np.unpackbits(bits.view(np.uint8), axis=-1, bitorder="little")[..., :k]
        return np.moveaxis(flat.astype(bool), -1, 0)

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape (H, W)."""
        return self.mask.shape

    def _facts(self) -> dict[str, str]:
        """Return the facts of :meth:`__repr__` and :meth:`_repr_html_`, as text, by label."""
        h, w = self.shape
        finite = self.depth[np.isfinite(self.depth)]
        depth = f"{finite.min():.6g} .. {finite.max():.6g}" if finite.size else "none"
        return {
            "size": f"{w} x {h} pixels",
            "method": self.method,
            "status": self.status,
            "iterations": str(len(self.history)),
            "depth": depth,
            "mask": f"{int(np.count_nonzero(self.mask))} pixels",
        }

    def __repr__(self) -> str:
        """Return one line: size (W x H), method, status, iterations, depth range and mask pixels."""
        f = self._facts()
        return (
            f"<Reconstruction {f['size']}, method={f['method']!r}, status={f['status']!r}, "
            f"iterations={f['iterations']}, depth {f['depth']}, mask {f['mask']}>"
        )

    def _repr_html_(self) -> str:
        """Return a compact HTML view for Jupyter: the key numbers, a small normal map and albedo."""
        return report_module.compact_html(self)

    @property
    def vertices(self) -> np.ndarray:
        """3-D vertex positions (H+1, W+1, 3) in the camera frame."""
        return _core.vertices(self.depth, self.rig.camera)

    @cached_property
    def normals(self) -> np.ndarray:
        """The mesh's facet normals (H, W, 3): the default normals of a result.

        The normalized cross product of each pixel quad's diagonals, ``(v10 - v01) x (v11 -
        v00)``, facing the camera (n_z < 0); NaN outside the mask. Computed from `depth` on first
        use and kept. The normal map, ``normals.npy`` and the mesh files' vertex normals use
        them; the per-pixel fits of the local step are :attr:`fit_normals`.
        """
        # NaN outside the mask written by the Rust function itself, band by band of rows from the
        # depths (no whole vertex grid): the same bits as the quads of :attr:`vertices`.
        return _core.mesh_normals(self.depth, self.rig.camera, np.ascontiguousarray(self.mask, dtype=bool))

    @property
    def unfitted(self) -> int:
        """Number of masked pixels with fewer than 3 usable lights (they kept their shape)."""
        return int(np.count_nonzero(self.mask & (self.lights_used < 3)))

    def predict(self, rig: Rig | None = None, *, lights: list[int] | None = None) -> np.ndarray:
        """Return the images predicted from this result by the image model.

        Each pixel is shaded with its fitted normal (:attr:`fit_normals`) and albedo at the
        centre of its quad (under the glossy model with its specular albedo and the lobe too):
        the model's own explanation of the images, which the normals and the
        albedo were fitted for jointly. A parallel-light result predicts with its own model (each
        point light seen as a direction from the surface's centroid).

        Parameters
        ----------
        rig : Rig, optional
            The rig to predict under. Default: the result's own.
        lights : list of int, optional
            Indices of the lights of `rig` to predict (negative from the end). Default: all.

        Returns
        -------
        numpy.ndarray
            (k, H, W) or (k, H, W, 3) images, NaN outside the mask.

        Raises
        ------
        InputError
            `rig` is not a :class:`~nplps.Rig`, or `lights` holds an invalid index.

        Examples
        --------
        Compare a held-out image with its prediction (see :func:`nplps.evaluation.held_out`)::

            predicted = result.predict(full_rig, lights=[i])[0]
        """
        rig = self.rig if rig is None else rig
        _check_rig(rig)
        light_params = rig._core_lights()
        if lights is not None:
            light_params = _select_core_lights(light_params, _light_indices(lights, rig.n_lights))
        glossy = self.lobe is not None and self.specular is not None
        return _core.predict(
            self.depth,
            self.fit_normals,
            self.albedo,
            rig.camera,
            light_params,
            self.mask,
            self.method == "parallel",
            specular=np.nan_to_num(np.asarray(self.specular, dtype=np.float64), nan=0.0) if glossy else None,
            lobe=(self.lobe.roughness, self.lobe.eta) if glossy and self.lobe is not None else None,
            diffuse=self.lobe.diffuse if glossy and self.lobe is not None else "transmitted",
        )

    def shaded(self, light: ArrayLike | Literal["camera"] | None = None) -> np.ndarray:
        """Return a grey picture of the mesh (the mesh normals) under one distant light.

        Parameters
        ----------
        light : (3,) array_like, "camera" or None, optional
            The direction towards the light in the camera frame (x right, y down, z forward),
            normalized here. Default (None): :data:`SHADED_LIGHT`, from the upper left and in
            front, about 50 degrees off the viewing axis, so that relief shows as shading (a
            surface facing the camera is mid-grey, not a white silhouette). ``"camera"``: a
            light at the camera, along each pixel's viewing ray.

        Returns
        -------
        numpy.ndarray
            (H, W) values ``max(0, n . l)`` with the mesh normal n (:attr:`normals`) and the
            light direction l (``-v`` for the viewing direction v of each pixel with
            ``"camera"``); 0 outside the mask.
        """
        n = self.normals
        if isinstance(light, str):
            if light != "camera":
                raise InputError(f'light must be a direction (3 numbers), "camera" or None, got {light!r}')
            if self.rig.is_pinhole:
                v = self.vertices
                centre = 0.25 * (v[:-1, :-1] + v[:-1, 1:] + v[1:, :-1] + v[1:, 1:])
                to_light = -centre / np.linalg.norm(centre, axis=-1, keepdims=True)
            else:
                to_light = np.array([0.0, 0.0, -1.0])
        else:
            d = np.asarray(SHADED_LIGHT if light is None else light, dtype=np.float64)
            if d.shape != (3,) or not np.all(np.isfinite(d)) or not np.linalg.norm(d) > 0:
                raise InputError(f"light must be a non-zero direction of 3 finite numbers, got {light!r}")
            to_light = d / np.linalg.norm(d)
        # n . l as ((n_x l_x + n_y l_y) + n_z l_z) + 0, the bits of ``(n * l).sum(axis=-1)`` (whose
        # sum starts from +0, so that a sum of negative zeros is +0; adding +0 last changes nothing
        # else), with (H, W) temporaries instead of an (H, W, 3) product: at 12 MP a third of the
        # memory traffic (tests/test_save_speed.py checks the bits).
        shade = n[..., 0] * to_light[..., 0]
        shade += n[..., 1] * to_light[..., 1]
        shade += n[..., 2] * to_light[..., 2]
        shade += 0.0
        np.clip(shade, 0.0, 1.0, out=shade)
        return np.where(self.mask & np.isfinite(shade), shade, 0.0)

    def vertex_normals(self) -> np.ndarray:
        """Per-vertex normals: the normalized mean of the adjacent masked pixels' :attr:`normals`.

        Returns
        -------
        numpy.ndarray
            (H+1, W+1, 3); NaN at vertices of no masked pixel.
        """
        return _to_vertices(self.normals, normalize=True)

    def vertex_albedo(self) -> np.ndarray:
        """Per-vertex albedo: the mean of the adjacent pixels' albedo.

        Returns
        -------
        numpy.ndarray
            (H+1, W+1) or (H+1, W+1, 3).
        """
        if self.albedo.ndim == 3:
            return _to_vertices(self.albedo)
        return _to_vertices(self.albedo[..., None])[..., 0]

    def save_ply(self, path: str | os.PathLike[str], *, opengl: bool = False) -> None:
        """Write the masked facets as a binary PLY mesh.

        With the vertex normals (:meth:`vertex_normals`) and the albedo as grey vertex colour;
        triangles wound counter-clockwise as seen from the camera.

        Parameters
        ----------
        path : str or path-like
            The file to write.
        opengl : bool, default False
            Write the OpenGL frame (x right, y up, z towards the viewer) instead of the camera's
            OpenCV frame.
        """
        # Streamed: the vertex normals and colours are made from the per-pixel maps as it is written.
        export._stream_ply(
            path, self.depth, self.mask, self.normals, self.albedo, opengl, per_pixel=True, camera=self.rig.camera
        )

    def save_obj(self, path: str | os.PathLike[str], *, opengl: bool = False) -> None:
        """Write the masked facets as a Wavefront OBJ mesh (same content and options as :meth:`save_ply`).

        Parameters
        ----------
        path : str or path-like
            The file to write.
        opengl : bool, default False
            Write the OpenGL frame instead of the camera's OpenCV frame.
        """
        export.write_obj(
            path, self.vertices, self.mask, normals=self.vertex_normals(), albedo=self.vertex_albedo(), opengl=opengl
        )

    def save_stl(self, path: str | os.PathLike[str], *, opengl: bool = False) -> None:
        """Write the masked facets as a binary STL mesh (the triangles of :meth:`save_ply`).

        Parameters
        ----------
        path : str or path-like
            The file to write.
        opengl : bool, default False
            Write the OpenGL frame instead of the camera's OpenCV frame.

        See Also
        --------
        nplps.export.write_stl
        """
        export.write_stl(path, self.vertices, self.mask, opengl=opengl)

    def save_glb(self, path: str | os.PathLike[str], *, opengl: bool = False) -> None:
        """Write the masked facets as a glTF 2.0 binary file (content and options as :meth:`save_ply`).

        Parameters
        ----------
        path : str or path-like
            The file to write.
        opengl : bool, default False
            Write the OpenGL frame instead of the camera's OpenCV frame (glTF viewers expect y
            up: use True for them).

        See Also
        --------
        nplps.export.write_glb
        """
        export.write_glb(
            path, self.vertices, self.mask, normals=self.vertex_normals(), albedo=self.vertex_albedo(), opengl=opengl
        )

    def save_points(self, path: str | os.PathLike[str], *, opengl: bool = False) -> None:
        """Write the mesh's vertices as a PLY point cloud with normals and colours (no faces).

        Parameters
        ----------
        path : str or path-like
            The file to write.
        opengl : bool, default False
            Write the OpenGL frame instead of the camera's OpenCV frame.

        See Also
        --------
        nplps.export.write_point_cloud
        """
        export.write_point_cloud(
            path, self.vertices, self.mask, normals=self.vertex_normals(), albedo=self.vertex_albedo(), opengl=opengl
        )

    def save_normals_tiff(self, path: str | os.PathLike[str]) -> None:
        """Write :attr:`normals` as an (H, W, 3) 32-bit float TIFF (OpenCV frame, NaN outside the mask).

        Parameters
        ----------
        path : str or path-like
            The file to write.
        """
        export.save_normals_tiff(path, self.normals)

    def save_viewer(
        self,
        path: str | os.PathLike[str],
        *,
        title: str = "nplps mesh",
        units: str | None = None,
        max_triangles: int | None = None,
    ) -> Path:
        """Write a self-contained 3-D viewer page of the mesh (offline WebGL, see :mod:`nplps.viewer`).

        Parameters
        ----------
        path : str or path-like
            The HTML page to write (replaced if it exists).
        title : str, default "nplps mesh"
            The page's title.
        units : str, optional
            The length unit shown with the extent and the scale bar (default "rig units").
        max_triangles : int, optional
            Decimate larger meshes on a regular grid (default
            :data:`nplps.viewer.DEFAULT_MAX_TRIANGLES`).

        Returns
        -------
        pathlib.Path
            The page: open it in a browser, or in Jupyter show it with
            ``IPython.display.IFrame(str(path), width=800, height=500)``.
        """
        from . import viewer

        info = viewer.write_viewer(
            path,
            self.vertices,
            self.mask,
            normals=self.vertex_normals(),
            albedo=self.vertex_albedo(),
            title=title,
            units=units,
            max_triangles=viewer.DEFAULT_MAX_TRIANGLES if max_triangles is None else max_triangles,
        )
        return info.path

    def summary(self) -> dict[str, Any]:
        """Return a JSON-ready summary of the run (what ``summary.json`` holds, without the albedo scale).

        Returns
        -------
        dict
            Method, shape, pixels, regions and gauge, iterations, status, last depth change and
            residual, unfitted pixels, depth range, timings, estimated distance, light
            refinement, the shadow threshold used (``dark``), the noise estimate (``noise``), the
            reflectance model (``reflectance``: "lambertian" or "glossy") and the glossy model's
            lobe (``lobe``: ``{"roughness": ..., "eta": ...}``, None under the Lambertian model) and
            ``trust`` (near-light runs: ``normal_sigma_deg`` and ``held_out_error`` with their
            median, 90th percentile and RMS or mean over the fitted pixels, and ``lights``, one
            row per light of :attr:`light_trust`; None for the baseline).
        """
        last = self.history[-1] if self.history else None
        return {
            "method": self.method,
            "shape": list(self.shape),
            "pixels": int(self.mask.sum()),
            "regions": len(self.gauge),
            "gauge": [float(g) for g in self.gauge],
            "iterations": len(self.history),
            "converged": self.converged,
            "status": self.status,
            "status_reason": self.status_reason,
            "last_depth_change": None if last is None else last.depth_change,
            "rms_residual": None if last is None else last.rms_residual,
            "unfitted_pixels": self.unfitted,
            "depth_range": [float(np.nanmin(self.depth)), float(np.nanmax(self.depth))],
            "timings": self.timings,
            "estimated_distance": None if self.distance is None else [float(d) for d in self.distance.distance],
            "distance_check": None if self.distance_check is None else self.distance_check.to_dict(),
            "light_refinement": None
            if self.refinement is None
            else {**self.refinement.to_dict(), "changes": self.light_changes()},
            "dark": None if self.dark is None else float(self.dark),
            "noise": None if self.noise is None else float(self.noise),
            "cast_shadows": self._shadow_summary(),
            "trust": self._trust_summary(),
            "reflectance": "lambertian" if self.lobe is None else "glossy",
            "lobe": None
            if self.lobe is None
            else {"roughness": self.lobe.roughness, "eta": self.lobe.eta, "diffuse": self.lobe.diffuse},
            "lobe_check": None if self.lobe_check is None else self.lobe_check.to_dict(),
        }

    def save(
        self,
        directory: str | os.PathLike[str],
        *,
        stem: str = "mesh",
        opengl: bool = False,
        overwrite: bool = False,
        formats: Iterable[str] = (),
        report: bool = False,
        inputs: np.ndarray | export.ContactSheet | None = None,
        options: dict[str, Any] | None = None,
        held_out: tuple[Sequence[HeldOutScores], Sequence[HeldOutScores] | None] | None = None,
        normal_map: str = "opengl",
        normal_map_bits: int = 16,
        units: str | None = None,
    ) -> dict[str, Path]:
        """Write the mesh (PLY and OBJ), the maps and ``summary.json`` into a directory.

        Files: ``mesh.ply`` and ``mesh.obj`` (vertex normals from :attr:`normals`; ``mesh.obj``
        only for results of at most :data:`nplps.export.OBJ_MAX_FACETS` (4 million) masked
        pixels unless `formats` has ``"obj"``: a 12 MP result's OBJ file is 2.4 GB of text;
        when it is left out ``summary.json``'s ``"skipped"`` says so and how to get it),
        ``normals.png`` (the normal map of :attr:`normals` in the `normal_map` convention, 16 bits
        per channel by default, see :func:`nplps.export.save_normal_map`; its frame and bits are
        ``summary.json``'s ``"normal_map"``, and :func:`nplps.export.read_normal_map` decodes it),
        ``shaded.png`` (the mesh lit from the upper left, :meth:`shaded`),
        ``albedo.png`` (16-bit), ``depth.npy`` (float64) and ``depth.tiff`` (float32) of the
        vertex depths, ``normals.npy`` (:attr:`normals`), ``residual.npy`` and ``summary.json``;
        under the glossy model also ``specular.npy`` (:attr:`specular`, float64, NaN where
        unfitted) and ``specular.png`` (16-bit, scaled as ``albedo.png``; the scale is
        ``specular_png_scale`` in ``summary.json``);
        with ``depth="auto"`` also ``distance_curve.csv`` and ``distance_curve.svg``; with
        refined lights also ``rig_refined.json`` (the refined rig file); and last the manifest
        ``nplps-manifest.json`` listing the files written. Near-light results also write
        ``normal_sigma.tiff`` and ``held_out_error.tiff`` (float32 maps of :attr:`normal_sigma`
        and :attr:`held_out_error`; docs/trust.md).

        What the report (:mod:`nplps.report`) needs is always written, so that ``nplps report
        DIR`` can make it later: ``mask.png`` (8-bit, 255 in the mask), ``lights_used.npy`` (the
        lit images of each pixel, uint16), ``history.csv`` (the convergence history,
        :func:`nplps.report.history_csv`) and ``rig.json`` (the result's rig: the refined one
        with ``refine_lights``). With `report`, also ``report.html``; with `inputs`,
        ``inputs.png`` (a contact sheet of the images, :func:`nplps.report.contact_sheet`); with
        `held_out`, ``held_out.json`` (:func:`nplps.report.held_out_record`).

        `formats` adds files in other formats (none by default): ``"obj"`` (``mesh.obj`` at any
        size, :meth:`save_obj`), ``"stl"`` (``mesh.stl``, binary
        STL, :meth:`save_stl`), ``"glb"`` (``mesh.glb``, glTF 2.0 binary with vertex normals and
        colours, :meth:`save_glb`), ``"points"`` (``points.ply``, the mesh's vertices as a point
        cloud with normals and colours, :meth:`save_points`), ``"normals_tiff"``
        (``normals.tiff``, :attr:`normals` as 32-bit float, :meth:`save_normals_tiff`) and
        ``"exr"`` (``depth.exr``, ``normals.exr`` in the `normal_map` frame and ``albedo.exr``,
        32-bit float; needs the optional OpenEXR binding, ``pip install "nplps[exr]"``).

        Parameters
        ----------
        directory : str or path-like
            Created if needed. It must be empty unless `overwrite` is True.
        stem : str, default "mesh"
            File name (without extension) of the PLY and OBJ files.
        opengl : bool, default False
            Write the meshes in the OpenGL frame (see :meth:`save_ply`).
        overwrite : bool, default False
            Replace files of the same names, and remove the files of an earlier result that
            this one does not have (listed in its manifest); other files are kept.
        formats : iterable of str, default ()
            Extra formats to write, any of ``"obj"``, ``"stl"``, ``"glb"``, ``"points"``,
            ``"normals_tiff"`` and ``"exr"`` (:data:`nplps.export.FORMATS`); `opengl` applies to
            the mesh and point formats.
        report : bool, default False
            Also write ``report.html``, the self-contained report of the result
            (:func:`nplps.report.write_report`).
        inputs : numpy.ndarray, optional
            The (k, H, W[, 3]) images the result was made from; a contact sheet of them
            (``inputs.png``) is written for the report. Or that contact sheet itself, made
            beforehand by :func:`nplps.export.contact_sheet` (an (h, w, 3) ``uint8`` array wrapped
            in :class:`nplps.export.ContactSheet`), so that the images can be freed before saving
            (the command line does this: at 100 MP the 16-bit stack is 3.3 GB).
        options : dict, optional
            The options of the run (JSON-ready values; arrays are recorded by their shape),
            stored in ``summary.json`` under ``"options"`` and listed by the report.
        held_out : (list of HeldOut, list of HeldOut or None), optional
            A held-out evaluation (:func:`nplps.evaluation.held_out`) of the near-light method
            and optionally of the parallel baseline, written as ``held_out.json``.
        normal_map : {"opengl", "directx", "opencv"}, default "opengl"
            The convention of ``normals.png`` and ``normals.exr``
            (:data:`nplps.export.NORMAL_MAP_FRAMES`): ``"opengl"`` x right, y up, z towards the
            viewer (Blender, Unity); ``"directx"`` y down (Unreal Engine); ``"opencv"`` the camera
            frame as is (z forward).
        normal_map_bits : {16, 8}, default 16
            Bits per channel of ``normals.png``.
        units : str, optional
            The length unit of the rig (e.g. ``"mm"``), recorded in ``summary.json`` as
            ``"units"`` and shown by the report and the viewer (default: "rig units").

        Returns
        -------
        dict of str to pathlib.Path
            The paths written (without the manifest), by kind (``"ply"``, ``"normal_map"``, ...,
            and each extra format by its name).

        Raises
        ------
        InputError
            `formats` holds an unknown name (checked before anything is written),
            `normal_map` or `normal_map_bits` is not one of the choices, `units` is not a
            string, or `formats` holds ``"exr"`` and OpenEXR is not installed.
        OutputExistsError
            `directory` is not empty and `overwrite` is False.
        OSError
            A file could not be written (``filename`` names it).

        Notes
        -----
        Each file is written under a temporary name and renamed when complete, so an error never
        leaves a truncated file under its final name. The PNG images are encoded in parallel
        (the Rust encoder, fast DEFLATE: :func:`nplps.export.write_pngs`) while the meshes and
        arrays are written, and renamed into place after the meshes. ``mesh.ply`` alone (no OBJ,
        STL, GLB or point cloud) is streamed by the Rust extension in blocks of rows: the vertex
        normals and colours are made vertex by vertex from the per-pixel maps as the records are
        written, with no whole position, normal or face array (5 bytes per vertex); with other
        mesh formats the mesh arrays are built once (in Rust) for all of them. The manifest's
        SHA-256 of the large files are computed on a background thread while the later files are
        written.
        """
        extra = export.check_formats(formats)
        export.check_normal_map(normal_map, normal_map_bits)
        if units is not None and (not isinstance(units, str) or not units.strip()):
            raise InputError(f"units must be a non-empty string such as 'mm', got {units!r}")
        if not isinstance(stem, str) or not stem or stem in (".", "..") or any(c in stem for c in "/\\\0"):
            raise InputError(f"stem must be a file name without a directory (it names mesh files), got {stem!r}")
        with result_directory(directory, overwrite) as out:
            paths = export.write_result(
                self,
                out,
                stem=stem,
                opengl=opengl,
                formats=extra,
                inputs=inputs,
                options=options,
                held_out=held_out,
                normal_map=normal_map,
                normal_map_bits=normal_map_bits,
                units=units,
            )
            if report:
                paths["report"] = out.file(report_module.REPORT_NAME)
                report_module.write_report(out.path, path=paths["report"])
        return paths


def _finite(v: Any) -> float | None:
    v = float(v)
    return v if np.isfinite(v) else None


def _refinement(d: dict[str, Any] | None) -> LightRefinement | None:
    if d is None:
        return None
    c = d.get("conditioning")
    return LightRefinement(
        mode=d["mode"],
        prior_weight=float(d["prior_weight"]),
        fell_back=bool(d["fell_back"]),
        stopped=bool(d["stopped"]),
        residual_without=float(d["residual_without"]),
        residual_with=float(d["residual_with"]),
        singular_values=None if c is None else np.asarray(c["singular_values"], dtype=np.float64),
        standard_errors=None if c is None else np.asarray(c["standard_errors"], dtype=np.float64).reshape(-1, 4),
    )


def _distance(d: dict[str, Any] | None) -> DistanceEstimate | None:
    if d is None:
        return None
    return DistanceEstimate(
        distance=np.asarray(d["distance"]),
        curve=[np.asarray(c, dtype=np.float64).reshape(-1, 2) for c in d["curve"]],
        range=tuple(d["range"]),
    )


def _lobe(pair: tuple[float, float], diffuse: str) -> Lobe:
    """Return the glossy model's lobe ``(roughness, eta)`` of the core's result with its diffuse shape."""
    return Lobe(float(pair[0]), float(pair[1]), str(diffuse))


def _lobe_check(d: Mapping[str, Any]) -> LobeCheck:
    """Return the core's held-out comparison of the glossy and Lambertian models."""
    return LobeCheck(
        float(d["glossy"]),
        float(d["lambertian"]),
        int(d["observations"]),
        int(d["seen"]),
        float(d["highlight"]),
        bool(d["highlight_confirmed"]),
    )


def _distance_check(d: dict[str, Any] | None) -> DistanceCheck | None:
    if d is None:
        return None
    return DistanceCheck(
        given=float(d["given"]),
        found=float(d["found"]),
        residual_given=float(d["residual_given"]),
        residual_found=float(d["residual_found"]),
        side=int(d["side"]),
        looks_wrong=bool(d["looks_wrong"]),
    )


def _to_vertices(values: np.ndarray, normalize: bool = False) -> np.ndarray:
    """Mean of the finite values of the (up to 4) pixels around each vertex: (H, W, C) -> (H+1, W+1, C).

    Computed by the Rust extension (``nplps._core.vertex_means``, the GIL released): each vertex
    sums its pixels in the order top-left pixel (r, c), (r, c - 1), (r - 1, c), (r - 1, c - 1)
    (a pixel counts when all its C values are finite) and divides by their number; NaN without
    one. With ``normalize``, each mean is then scaled to unit length (``sqrt((x² + y²) + z²)``).
    """
    return _core.vertex_means(np.ascontiguousarray(values, dtype=np.float64), normalize)
