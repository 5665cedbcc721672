"""Rig interchange: RelightLab ``.dome`` and ``.lp``, AliceVision ``lights.json`` and SfMData, OpenCV cameras.

Each format holds only part of a rig; :func:`load` combines a lights file with a camera and
:func:`save` writes the part a format can hold, refusing (:class:`~nplps.RigError`) what it cannot
represent instead of dropping it silently. The conventions of each format, with their sources,
are in ``docs/formats.md``; in short (nplps: OpenCV camera frame, x right, y down, z forward):

* ``.dome`` (RelightLab, JSON): x right, y towards the top of the image, z up towards the
  camera, origin on the object plane at the image centre; lights as ``"directions"`` (unit, from
  the object to the light), ``"positionsSphere"`` or ``"positions3d"`` (mm) chosen by
  ``"lightConfiguration"``; ``"ledAdjust"`` (r, g, b) multiplies the pixel values, so the
  intensity is its reciprocal. Positions need the camera's distance to the object plane
  (``camera_distance``): ``p_camera = (x, -y, D - z)``.
* ``.lp`` (RTI light positions): a count line, then ``file x y z`` per image, unit directions
  in the frame of the ``.dome``; ``d_camera = (x, -y, -z)``.
* AliceVision ``lights.json``: ``{"lights": [{"lightId" | "viewId": id, "type": "directional",
  "direction": [x, y, z], "intensity": [r, g, b]}]}`` in the OpenCV camera frame (numbers may be
  JSON strings, as boost's writer makes them).
* AliceVision SfMData (``.sfm``/``.json``): views (viewId, poseId, intrinsicId, path) and pinhole
  intrinsics (focal length in mm with the sensor width, or in pixels in old files; principal
  point as an offset from the image centre since file version 1.2.1).
* OpenCV FileStorage camera (``.yml``/``.yaml`` or ``.json``): ``camera_matrix`` (3 x 3),
  ``distortion_coefficients`` and optionally ``image_width``/``image_height``.

Round trips are exact: a rig written to a format and read back is equal to the rig (the values
that go through an offset or a reciprocal are written as the shortest decimal that reads back to
the same double), and a file written by nplps reads back to the same values.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

from ._rig_codecs import FORMATS, SfmData, SfmView, detect_format, read_camera, read_sfmdata, write_camera
from .rig import Rig, _load_rig, _save_rig

__all__ = [
    "FORMATS",
    "SfmData",
    "SfmView",
    "detect_format",
    "load",
    "read_camera",
    "read_sfmdata",
    "save",
    "write_camera",
]


def load(
    path: str | os.PathLike[str],
    *,
    fmt: str | None = None,
    camera: Mapping[str, Any] | str | os.PathLike[str] | None = None,
    camera_distance: float | None = None,
    light_distance: float | None = None,
    intrinsic: str | None = None,
    scale: float | None = None,
) -> Rig:
    """Read a rig from a rig file or a lights file of another format.

    Parameters
    ----------
    path : str or os.PathLike
        A rig file (JSON), a RelightLab ``.dome`` or ``.lp`` or an AliceVision ``lights.json``.
    fmt : str, optional
        The format (:data:`FORMATS`); default: :func:`detect_format`.
    camera : mapping, str or os.PathLike, optional
        The camera, for formats without one: a rig file's ``"camera"`` mapping or a file that
        :func:`read_camera` reads (OpenCV YAML/JSON, a rig file, an SfMData). Given with a rig
        file, it replaces the rig's camera.
    camera_distance : float, optional
        Distance from the camera centre to the ``.dome`` frame's origin (on the object plane,
        along the optical axis): needed for the positions of a ``.dome`` and for
        `light_distance`.
    light_distance : float, optional
        Read the unit directions of a ``.lp`` or directional ``.dome`` as point lights at this
        distance from the ``.dome`` frame's origin (needs `camera_distance`).
    intrinsic : str, optional
        With an SfMData `camera`: the intrinsicId to use when it has several.
    scale : float, optional
        Rig units per unit of the ``.dome``'s positions (default 1: the rig has the ``.dome``'s
        unit, mm for current RelightLab files; 0.1 gives cm). `camera_distance` and
        `light_distance` are in rig units.

    Returns
    -------
    Rig

    Raises
    ------
    RigError
        The file cannot be read or is malformed, a camera or a distance it needs is missing, or
        `fmt` does not read rigs (OpenCV files and SfMData hold a camera only).
    """
    return _load_rig(
        path,
        fmt=fmt,
        camera=camera,
        camera_distance=camera_distance,
        light_distance=light_distance,
        intrinsic=intrinsic,
        scale=scale,
    )


def save(
    rig: Rig,
    path: str | os.PathLike[str],
    *,
    fmt: str | None = None,
    camera_distance: float | None = None,
    drop_intensities: bool = False,
    scale: float | None = None,
) -> str:
    """Write a rig, or the part of it that a format holds.

    Parameters
    ----------
    rig : Rig
        The rig.
    path : str or os.PathLike
        The file; written under a temporary name renamed when complete.
    fmt : str, optional
        The format (:data:`FORMATS` but ``"sfmdata"``). Default: by extension (``.dome``,
        ``.lp``, ``.yml``/``.yaml``; a file named ``lights.json`` is AliceVision's, any other a
        rig file).
    camera_distance : float, optional
        For a ``.dome`` of point lights: distance from the camera centre to the ``.dome``
        frame's origin (default: the one the rig was read with, kept in its ``"_dome"`` comment).
    drop_intensities : bool, default False
        Write a ``.lp`` even though the rig's intensities are not all 1 (a ``.lp`` has none).
    scale : float, optional
        For a ``.dome``: rig units per unit of the file's positions (default: the one the rig was
        read with, else 1).

    Returns
    -------
    str
        The format written.

    Raises
    ------
    RigError
        The format cannot represent the rig (the message says what and what to use instead).
    OSError
        The file cannot be written.
    """
    return _save_rig(
        rig, path, fmt=fmt, camera_distance=camera_distance, drop_intensities=drop_intensities, scale=scale
    )
