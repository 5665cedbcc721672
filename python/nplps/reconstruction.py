"""The result of a reconstruction, and writing it to files."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from . import _core, export, plots
from ._atomic import write_text
from ._outdir import result_directory
from .rig import Rig


@dataclass
class DistanceEstimate:
    """The working distance estimated from the images (``depth="auto"``)."""

    #: Estimated distance of each region (arithmetic mean depth, or geometric mean depth for a
    #: pinhole camera).
    distance: np.ndarray
    #: Per region, the evaluated (distance, RMS residual) pairs, sorted by distance (N, 2).
    curve: list[np.ndarray]
    #: The (near, far) range searched.
    range: tuple[float, float]

    def save_curve(self, path: str | os.PathLike[str]) -> None:
        """Writes the residual curve(s) as CSV (region, distance, rms_residual)."""
        rows = [f"{r},{d!r},{e!r}" for r, curve in enumerate(self.curve) for d, e in curve]
        write_text(path, "region,distance,rms_residual\n" + "\n".join(rows) + "\n")


class Iteration(NamedTuple):
    """What one local/global iteration did."""

    iteration: int
    #: Largest vertex depth change of the iteration (scene units).
    depth_change: float
    #: RMS image residual over all usable observations (image units).
    rms_residual: float
    #: Seconds since the solver started.
    elapsed: float
    #: Coarse-to-fine pyramid level (0: full resolution; level l has 2**l times fewer pixels
    #: per side).
    level: int = 0
    #: Conjugate-gradient iterations of the global step (0 for the direct solver).
    inner_iterations: int = 0
    #: Largest relative change of a light parameter in the iteration's light step
    #: (``refine_lights``; 0 otherwise): ``|dPhi| / Phi`` or ``|dp| / D``.
    light_change: float = 0.0


@dataclass
class LightRefinement:
    """What the self-calibration of the lights (``refine_lights=``) did.

    The refined rig is the result's :attr:`Reconstruction.rig`; the rig given to
    :func:`nplps.reconstruct` is :attr:`Reconstruction.input_rig`.
    """

    #: "intensity", "position" or "both".
    mode: str
    #: Weight of the prior toward the given positions.
    prior_weight: float
    #: True when refining positions did not lower the photometric residual of a run without
    #: refinement on the first pyramid level: the given lights were kept.
    fell_back: bool
    #: True when the refinement was stopped early because the photometric residual rose (the
    #: joint iteration drifted along weakly determined light parameters): the state of lowest
    #: residual was restored and its lights kept.
    stopped: bool
    #: RMS residual on the first level without / with refinement (NaN when not compared: the
    #: comparison runs only when positions are refined).
    residual_without: float
    residual_with: float
    #: Singular values of the light block of the relative Jacobian after the normals are
    #: eliminated (positions in units of the working distance), largest first. Their spread
    #: tells how well the images determine the lights; integrability adds to it.
    singular_values: np.ndarray | None = None
    #: Per light: standard error of the intensity factor (relative) and of the position
    #: (x, y, z, scene units); NaN where not refined.
    standard_errors: np.ndarray | None = None

    @property
    def condition_number(self) -> float:
        """Ratio of the largest to the smallest singular value (inf if one is 0)."""
        if self.singular_values is None or len(self.singular_values) == 0:
            return float("nan")
        smallest = float(self.singular_values[-1])
        return float(self.singular_values[0]) / smallest if smallest > 0 else float("inf")

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "mode": self.mode,
            "prior_weight": self.prior_weight,
            "fell_back": self.fell_back,
            "stopped": self.stopped,
            "residual_without": _finite_or_none(self.residual_without),
            "residual_with": _finite_or_none(self.residual_with),
            "condition_number": _finite_or_none(self.condition_number),
            "singular_values": None if self.singular_values is None else [float(v) for v in self.singular_values],
            "standard_errors": None
            if self.standard_errors is None
            else [[_finite_or_none(v) for v in row] for row in self.standard_errors],
        }


def _finite_or_none(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def light_changes(before: Rig, after: Rig) -> list[dict[str, Any]]:
    """Per light: the intensity factor (after / before, mean over channels) and the position
    shift (scene units; None for directional lights) from ``before`` to ``after``."""
    rows = []
    for i in range(before.n_lights):
        factor = float(np.mean(after.intensities[i] / before.intensities[i]))
        shift = None
        if not before.directional[i]:
            shift = [float(v) for v in after.positions[i] - before.positions[i]]
        rows.append({"light": i, "intensity_factor": factor, "position_shift": shift})
    return rows


@dataclass
class Reconstruction:
    """A reconstructed surface. Per-pixel arrays are (H, W[, 3]), per-vertex arrays
    (H+1, W+1[, 3]); values outside the mask are NaN (0 for ``lights_used``)."""

    #: Vertex depths z (H+1, W+1).
    depth: np.ndarray
    #: Local-fit unit normals (H, W, 3), facing the camera (n_z < 0).
    normals: np.ndarray
    #: Fitted albedo (H, W), or (H, W, 3) for colour images; NaN where a pixel had fewer than 3
    #: usable lights.
    albedo: np.ndarray
    #: RMS image residual of each pixel's fit (H, W), in image units.
    residual: np.ndarray
    #: Number of usable (lit) lights of each pixel (H, W).
    lights_used: np.ndarray
    #: Region label of each pixel (H, W), -1 outside the mask.
    regions: np.ndarray
    #: Mean vertex depth of each region (the gauge).
    gauge: np.ndarray
    #: One entry per iteration (with ``depth="auto"``: of the final run at the estimate; the
    #: search's evaluations are in ``distance.curve``).
    history: list[Iteration]
    #: Whether the tolerance was reached within the iteration limit (exactly when
    #: :attr:`status` is "converged").
    converged: bool
    #: The mask (H, W) that was reconstructed.
    mask: np.ndarray
    #: The rig the images were taken with.
    rig: Rig
    #: Seconds spent in factorization, local steps, solves and in total.
    timings: dict[str, float] = field(default_factory=dict)
    #: "near" for the near-light method, "parallel" for the conventional baseline.
    method: str = "near"
    #: How the run ended: "converged" (the depth change reached ``tol``), "stalled" (stopped at
    #: the iteration limit, or no progress for 50 iterations), "diverged" (the depth changes
    #: grew) or "degenerate" (more than half of the masked pixels could not be fitted and kept
    #: the starting shape). :attr:`status_reason` says why, with the numbers.
    status: str = "converged"
    #: One sentence explaining :attr:`status`.
    status_reason: str = ""
    #: The distance search, when ``depth="auto"``.
    distance: DistanceEstimate | None = None
    #: The self-calibration of the lights, when ``refine_lights`` was given; :attr:`rig` then
    #: holds the refined lights.
    refinement: LightRefinement | None = None
    #: The rig given to the reconstruction, when the lights were refined (else None: it is
    #: :attr:`rig`).
    input_rig: Rig | None = None

    @classmethod
    def _from_core(cls, out: dict[str, Any], mask: np.ndarray, rig: Rig, method: str) -> "Reconstruction":
        refinement = _refinement(out.get("refinement"))
        input_rig = None
        if refinement is not None:
            input_rig, rig = rig, Rig._from_core_lights(rig.camera, out["lights"], like=rig)
        return cls(
            depth=out["depth"],
            normals=out["normals"],
            albedo=out["albedo"],
            residual=out["residual"],
            lights_used=out["lights_used"],
            regions=out["regions"],
            gauge=out["gauge"],
            history=[Iteration(*h) for h in out["history"]],
            converged=bool(out["converged"]),
            mask=mask,
            rig=rig,
            timings=dict(out["timings"]),
            method=method,
            status=str(out["status"]),
            status_reason=str(out["status_reason"]),
            distance=_distance(out.get("distance_estimate")),
            refinement=refinement,
            input_rig=input_rig,
        )

    def light_changes(self) -> list[dict[str, Any]]:
        """Per light, how the refinement changed it (see :func:`nplps.light_changes`); empty
        without refinement."""
        if self.input_rig is None:
            return []
        return light_changes(self.input_rig, self.rig)

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape (H, W)."""
        return self.mask.shape  # type: ignore[return-value]

    @property
    def vertices(self) -> np.ndarray:
        """3-D vertex positions (H+1, W+1, 3) in the camera frame."""
        return _core.vertices(self.depth, self.rig.camera)

    @property
    def mesh_normals(self) -> np.ndarray:
        """The mesh's own facet normals (H, W, 3): cross product of each quad's diagonals."""
        return _core.mesh_normals(self.depth, self.rig.camera)

    @property
    def unfitted(self) -> int:
        """Number of masked pixels with fewer than 3 usable lights (they kept their shape)."""
        return int(np.count_nonzero(self.mask & (self.lights_used < 3)))

    def predict(self, rig: Rig | None = None, lights: list[int] | None = None) -> np.ndarray:
        """Images (k, H, W[, 3]) predicted from this result under ``rig`` (default: its own),
        for the lights ``lights`` of that rig (default: all).

        Each pixel is shaded with its local-fit normal and albedo at the centre of its quad. A
        parallel-light result predicts with its own model (each point light seen as a direction
        from the surface's centroid). Use it to compare a held-out image with its prediction.
        """
        from .api import _check_rig, _light_indices

        rig = self.rig if rig is None else rig
        _check_rig(rig)
        light_params = rig._core_lights()
        if lights is not None:
            lights = _light_indices(lights, rig.n_lights)
            light_params = {key: [values[i] for i in lights] for key, values in light_params.items()}
        return _core.predict(
            self.depth, self.normals, self.albedo, rig.camera, light_params, self.mask, self.method == "parallel"
        )

    def shaded(self) -> np.ndarray:
        """A grey picture (H, W) of the mesh lit from the camera: ``max(0, -n . v)`` with the mesh
        normal n and the viewing direction v of each pixel; 0 outside the mask."""
        n = self.mesh_normals
        if self.rig.is_pinhole:
            v = self.vertices
            centre = 0.25 * (v[:-1, :-1] + v[:-1, 1:] + v[1:, :-1] + v[1:, 1:])
            view = centre / np.linalg.norm(centre, axis=-1, keepdims=True)
        else:
            view = np.array([0.0, 0.0, 1.0])
        shade = np.clip(-(n * view).sum(axis=-1), 0.0, 1.0)
        return np.where(self.mask & np.isfinite(shade), shade, 0.0)

    def vertex_normals(self) -> np.ndarray:
        """Per-vertex normals (H+1, W+1, 3): the normalized mean of the adjacent pixels' normals."""
        return _normalize(_to_vertices(self.normals))

    def vertex_albedo(self) -> np.ndarray:
        """Per-vertex albedo (H+1, W+1[, 3]): the mean of the adjacent pixels' albedo."""
        if self.albedo.ndim == 3:
            return _to_vertices(self.albedo)
        return _to_vertices(self.albedo[..., None])[..., 0]

    def save_ply(self, path: str | os.PathLike[str], opengl: bool = False) -> None:
        """Binary PLY of the masked facets, with vertex normals and the albedo as vertex colour.

        Triangles are wound counter-clockwise as seen from the camera. ``opengl=True`` writes the
        OpenGL frame (x right, y up, z towards the viewer) instead of the camera's OpenCV frame.
        """
        export.write_ply(path, self.vertices, self.mask, self.vertex_normals(), self.vertex_albedo(), opengl=opengl)

    def save_obj(self, path: str | os.PathLike[str], opengl: bool = False) -> None:
        """Wavefront OBJ of the masked facets (same content and options as :meth:`save_ply`)."""
        export.write_obj(path, self.vertices, self.mask, self.vertex_normals(), self.vertex_albedo(), opengl=opengl)

    def summary(self) -> dict[str, Any]:
        """A JSON-ready summary of the run."""
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
            "light_refinement": None
            if self.refinement is None
            else {**self.refinement.to_dict(), "changes": self.light_changes()},
        }

    def save(
        self, directory: str | os.PathLike[str], stem: str = "mesh", opengl: bool = False, overwrite: bool = False
    ) -> dict[str, Path]:
        """Writes the mesh (PLY and OBJ), the maps and ``summary.json`` into ``directory``.

        Files: ``mesh.ply``, ``mesh.obj``, ``normals.png`` (normal map, see
        :func:`nplps.export.save_normal_map`), ``shaded.png`` (the mesh lit from the camera),
        ``albedo.png`` (16-bit), ``depth.npy`` (float64)
        and ``depth.tiff`` (float32) of the vertex depths, ``normals.npy``, ``residual.npy`` and
        ``summary.json``; with ``depth="auto"`` also ``distance_curve.csv`` and
        ``distance_curve.svg``; with refined lights also ``rig_refined.json`` (the refined rig
        file); and last the manifest ``nplps-manifest.json`` listing the files written.
        Returns the paths written (without the manifest).

        ``directory`` is created if needed. It must be empty unless ``overwrite=True``: then
        files of the same names are replaced and the files of an earlier result that this one
        does not have (listed in its manifest) are removed; other files are kept. Each file is
        written under a temporary name and renamed when complete, so an error never leaves a
        truncated file under its final name.

        Raises:
            OutputExistsError: ``directory`` is not empty and ``overwrite`` is False.
            OSError: a file could not be written (``filename`` names it).
        """
        with result_directory(directory, overwrite) as out:
            names = {
                "ply": f"{stem}.ply",
                "obj": f"{stem}.obj",
                "normal_map": "normals.png",
                "shaded": "shaded.png",
                "albedo": "albedo.png",
                "depth_npy": "depth.npy",
                "depth_tiff": "depth.tiff",
                "normals_npy": "normals.npy",
                "residual_npy": "residual.npy",
            }
            if self.distance is not None:
                names.update(distance_curve="distance_curve.csv", distance_plot="distance_curve.svg")
            if self.refinement is not None:
                names["rig_refined"] = "rig_refined.json"
            names["summary"] = "summary.json"
            paths = {key: out.file(name) for key, name in names.items()}
            # One set of vertex arrays and one mesh for both files.
            export.write_meshes(
                paths["ply"], paths["obj"], self.vertices, self.mask, self.vertex_normals(), self.vertex_albedo(), opengl=opengl
            )
            export.save_normal_map(paths["normal_map"], self.normals, self.mask)
            export.save_grey_png(paths["shaded"], self.shaded())
            summary = self.summary()
            summary["albedo_png_scale"] = export.save_albedo(paths["albedo"], self.albedo)
            export.save_depth_npy(paths["depth_npy"], self.depth)
            export.save_depth_tiff(paths["depth_tiff"], self.depth)
            export.save_npy(paths["normals_npy"], self.normals)
            export.save_npy(paths["residual_npy"], self.residual)
            if self.distance is not None:
                self.distance.save_curve(paths["distance_curve"])
                plots.residual_curve_svg(self.distance.curve, list(self.distance.distance), paths["distance_plot"])
            if self.refinement is not None:
                self.rig.save(paths["rig_refined"])
            write_text(paths["summary"], json.dumps(summary, indent=2) + "\n")
        return paths


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
        range=tuple(d["range"]),  # type: ignore[arg-type]
    )


def _to_vertices(values: np.ndarray) -> np.ndarray:
    """Mean of the finite values of the (up to 4) pixels around each vertex: (H, W, C) -> (H+1, W+1, C)."""
    h, w, c = values.shape
    total = np.zeros((h + 1, w + 1, c))
    count = np.zeros((h + 1, w + 1, 1))
    finite = np.isfinite(values).all(axis=-1, keepdims=True)
    v = np.where(finite, values, 0.0)
    for dr in (0, 1):
        for dc in (0, 1):
            total[dr : dr + h, dc : dc + w] += v
            count[dr : dr + h, dc : dc + w] += finite
    del v
    total /= np.maximum(count, 1)  # in place: no further full-size copies
    total[count[..., 0] == 0] = np.nan
    return total


def _normalize(v: np.ndarray) -> np.ndarray:
    """``v`` (a fresh array, divided in place) scaled to unit length along the last axis."""
    with np.errstate(invalid="ignore", divide="ignore"):
        v /= np.linalg.norm(v, axis=-1, keepdims=True)
    return v
