"""Meshroom integration: a plugin folder and :func:`run`, what its node's ``nplps meshroom`` command does.

The plugin folder (:data:`PLUGIN_PATH`, shipped inside the package) follows Meshroom's plugin
layout: ``meshroom/config.json`` and ``meshroom/nplpsNodes/NplpsPhotometricStereo.py``, a
``desc.CommandLineNode`` that runs ``nplps meshroom``. Add it to ``MESHROOM_PLUGINS_PATH``
(``nplps meshroom --plugin-path`` prints it).

The node follows the contract of Meshroom's photometric-stereo nodes: its input is an SfMData
whose views sharing a poseId are the images of one pose under the different lights; each pose
is reconstructed on its own (:func:`run`) and gets ``<poseId>_normals.png`` (16-bit RGB, OpenGL
or OpenCV frame) and a folder ``<poseId>/`` with the full result of
:meth:`nplps.Reconstruction.save` (mesh.ply, mesh.obj, albedo.png, depth.tiff, depth.npy,
normals.npy, summary.json, ...).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..errors import InputError, RigError

__all__ = ["PLUGIN_PATH", "PoseResult", "normal_png16_pixels", "run", "write_normals_png16"]

#: The plugin folder to add to ``MESHROOM_PLUGINS_PATH``.
PLUGIN_PATH = Path(__file__).resolve().parent

NormalFrame = Literal["opengl", "opencv"]


def normal_png16_pixels(
    normals: np.ndarray, frame: NormalFrame = "opengl", mask: np.ndarray | None = None
) -> np.ndarray:
    """Return the 16-bit RGB pixels of a normal map.

    Each component ``v`` of the normal in the chosen frame (``"opencv"``: nplps's own, x right,
    y down, z into the scene, ``(n_x, n_y, n_z)``; ``"opengl"``: x right, y up, z towards the
    viewer, ``(n_x, -n_y, -n_z)``) is stored as ``round((v + 1) / 2 * 65535)``; decode with
    ``v = 2 * p / 65535 - 1``. Pixels outside ``mask`` or with a NaN normal are ``(0, 0, 0)``.

    Parameters
    ----------
    normals : numpy.ndarray
        ``(H, W, 3)`` unit normals in nplps's (OpenCV) frame.
    frame : {"opengl", "opencv"}, default "opengl"
        The frame of the written normals.
    mask : numpy.ndarray, optional
        ``(H, W)`` bool of the pixels to encode.

    Returns
    -------
    numpy.ndarray
        ``(H, W, 3)`` uint16.
    """
    n = np.asarray(normals, dtype=np.float64)
    if n.ndim != 3 or n.shape[2] != 3:
        raise InputError(f"normals must have shape (H, W, 3), got {n.shape}")
    if frame not in ("opengl", "opencv"):
        raise InputError(f"frame must be 'opengl' or 'opencv', got {frame!r}")
    valid: np.ndarray = np.asarray(np.isfinite(n).all(axis=2))
    if mask is not None:
        valid &= np.asarray(mask, dtype=bool)
    flip = np.array([1.0, -1.0, -1.0]) if frame == "opengl" else np.ones(3)
    v = np.clip(np.where(valid[..., None], n, 0.0) * flip, -1.0, 1.0)
    pixels = np.rint((v + 1.0) / 2.0 * 65535.0).astype(np.uint16)
    pixels[~valid] = 0
    return pixels


def write_normals_png16(
    path: str | os.PathLike[str], normals: np.ndarray, frame: NormalFrame = "opengl", mask: np.ndarray | None = None
) -> None:
    """Write a normal map as a 16-bit RGB PNG, encoded as :func:`normal_png16_pixels`."""
    from ..export import write_png16

    write_png16(path, normal_png16_pixels(normals, frame, mask))


@dataclass(frozen=True)
class PoseResult:
    """What :func:`run` made of one pose: its id, images, normals file, result folder and status."""

    pose_id: str
    images: list[str]
    normals: Path
    folder: Path
    status: str


def _pose_lights(rig: Any, views: Sequence[Any], pose_id: str, lights_name: str) -> Any:
    """Return the rig's lights for the views of one pose (by viewId when the lights file has them)."""
    ids = rig.comments.get("_alicevision_ids")
    if isinstance(ids, list) and ids and all(isinstance(i, list) and i[0] == "viewId" for i in ids):
        index = {str(i[1]): k for k, i in enumerate(ids)}
        missing = [v.view_id for v in views if v.view_id not in index]
        if missing:
            raise RigError(f"{lights_name} has no light for view {missing[0]} of pose {pose_id}")
        return rig.subset([index[v.view_id] for v in views])
    if rig.n_lights != len(views):
        raise RigError(
            f"pose {pose_id} has {len(views)} images but {lights_name} has {rig.n_lights} lights: "
            "the lights must be in the order of the pose's images sorted by path"
        )
    return rig


def run(
    sfmdata: str | os.PathLike[str],
    output: str | os.PathLike[str],
    *,
    lights: str | os.PathLike[str] | None = None,
    depth: float | Literal["auto"] = "auto",
    normal_frame: NormalFrame = "opengl",
    camera_distance: float | None = None,
    light_distance: float | None = None,
    mask_folder: str | os.PathLike[str] | None = None,
    poses: Sequence[str] | None = None,
    overwrite: bool = False,
    **options: Any,
) -> list[PoseResult]:
    """Reconstruct every pose of an SfMData (the views sharing a poseId, one per light).

    Parameters
    ----------
    sfmdata : str or os.PathLike
        The SfMData (JSON) file: views with viewId, poseId, intrinsicId and path, and the pinhole
        intrinsics (the camera of each pose; one intrinsic per pose).
    output : str or os.PathLike
        The output folder (created if needed; other files in it are kept).
    lights : str or os.PathLike, optional
        The lights: AliceVision ``lights.json`` (matched by viewId when it has them, else in the
        order of each pose's images sorted by path), ``.lp``, ``.dome`` or a rig file (its lights
        only). Default: ``lights.json`` beside the SfMData.
    depth : float or "auto", default "auto"
        The working distance (see :func:`nplps.reconstruct`).
    normal_frame : {"opengl", "opencv"}, default "opengl"
        The frame of ``<poseId>_normals.png``.
    camera_distance, light_distance : float, optional
        For a ``.dome``/``.lp`` lights file (see :func:`nplps.rig_formats.load`).
    mask_folder : str or os.PathLike, optional
        A folder with ``<poseId>.png`` masks (a pose without one uses every pixel).
    poses : sequence of str, optional
        The poseIds to reconstruct (default: all).
    overwrite : bool, default False
        Replace the results of an earlier run in ``<poseId>/``.
    **options
        Passed to :func:`nplps.reconstruct` (``iterations``, ``robust``, ...).

    Returns
    -------
    list of PoseResult

    Raises
    ------
    RigError
        The SfMData, its intrinsics or the lights file cannot be used (the message says why).
    """
    from .. import rig_formats
    from ..api import reconstruct
    from ..rig import Rig, RigGrid

    sfm = rig_formats.read_sfmdata(sfmdata)
    groups = sfm.poses()
    if not groups:
        raise RigError(f"SfMData {os.fspath(sfmdata)!r} has no views")
    chosen = list(groups) if poses is None else [str(p) for p in poses]
    unknown = [p for p in chosen if p not in groups]
    if unknown:
        raise RigError(f"SfMData {os.fspath(sfmdata)!r} has no pose {unknown[0]} (poses: {', '.join(groups)})")
    if lights is None or os.fspath(lights) == "":
        lights = os.path.join(os.path.dirname(os.fspath(sfmdata)), "lights.json")
        if not os.path.isfile(lights):
            raise RigError(f"no lights file given and no lights.json beside {os.fspath(sfmdata)!r} (give --lights)")
    lights_name = os.fspath(lights)
    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    results = []
    for pose_id in chosen:
        views = groups[pose_id]
        intrinsic_ids = sorted({v.intrinsic_id for v in views})
        if len(intrinsic_ids) != 1:
            raise RigError(
                f"pose {pose_id}: its views have several intrinsics ({', '.join(intrinsic_ids)}); one camera"
            )
        camera, size = sfm.camera(intrinsic_ids[0])
        light_rig = rig_formats.load(
            lights, camera=camera, camera_distance=camera_distance, light_distance=light_distance
        )
        light_rig = _pose_lights(light_rig, views, pose_id, lights_name)
        rig = Rig(camera, light_rig.lights, grid=RigGrid(size))
        mask = None
        if mask_folder is not None and os.fspath(mask_folder) != "":
            candidate = os.path.join(os.fspath(mask_folder), f"{pose_id}.png")
            mask = candidate if os.path.isfile(candidate) else None
        images = [v.path for v in views]
        result = reconstruct(images, rig, depth=depth, mask=mask, **options)
        folder = out / str(pose_id)
        result.save(folder, overwrite=overwrite, formats=["obj"])  # the node's output names mesh.obj: at any size
        normals = out / f"{pose_id}_normals.png"
        write_normals_png16(normals, result.normals, normal_frame, result.mask)
        results.append(PoseResult(str(pose_id), images, normals, folder, str(result.status)))
    return results
