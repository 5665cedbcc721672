"""DiLiGenT's ``*PNG`` object folders (directional lights, ground-truth normals)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .. import preprocess
from ..errors import InputError
from ..io import PathLike
from .capture import Capture
from .files import _check_folder, _check_indices, _read_mask, _read_stack, _resolve
from .matlab import _mat_var, read_mat


def _diligent_folder(folder: Path) -> Path:
    """Return the folder holding filenames.txt: ``folder`` itself or its unique ``*PNG`` subfolder."""
    if (folder / "filenames.txt").is_file():
        return folder
    subs = [p for p in sorted(folder.glob("*PNG")) if (p / "filenames.txt").is_file()]
    if len(subs) == 1:
        return subs[0]
    if not subs:
        raise InputError(f"'{folder}' is not a DiLiGenT object folder (no filenames.txt)")
    names = ", ".join(p.name for p in subs)
    raise InputError(f"'{folder}' holds several DiLiGenT objects ({names}): pick one")


def _loadtxt(path: Path, columns: int) -> np.ndarray:
    """Read a whitespace-separated numeric table with ``columns`` columns."""
    if not path.is_file():
        raise InputError(f"DiLiGenT file '{path}' not found")
    try:
        arr = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise InputError(f"cannot read '{path}': {exc}") from exc
    if arr.shape[1] != columns or not np.all(np.isfinite(arr)):
        raise InputError(f"'{path}': expected {columns} finite numbers per line, got {arr.shape}")
    return arr


def _read_names(path: Path) -> str:
    """Return the text of ``filenames.txt``: UTF-8 (a byte-order mark is allowed; ASCII is UTF-8).

    Raises :class:`InputError` naming the file when it is not UTF-8 text (the image names could only
    be guessed, and a wrong guess would name other files).
    """
    data = path.read_bytes()
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(
            f"'{path}' is not UTF-8 text (byte 0x{data[exc.start]:02x} at offset {exc.start}): "
            "save the list of image names as UTF-8"
        ) from None
    if "\0" in text:
        raise InputError(f"'{path}' is not a text file (it holds NUL bytes): it should list the image names")
    return text


def load_diligent(
    folder: PathLike,
    *,
    load: bool = False,
    color: bool | None = None,
    lights: Sequence[int] | None = None,
    normals: bool = True,
    K: np.ndarray | None = None,
) -> Capture:
    """Load one DiLiGenT object (``ballPNG/`` and the like; Shi et al., CVPR 2016).

    ``folder`` is the object folder (holding ``filenames.txt``) or a folder with exactly one
    ``*PNG`` subfolder. Files:

    * ``filenames.txt``: the image names, one per line, UTF-8 text (16-bit RGB PNG, linear; read by
      :func:`nplps.io.read_image`, which keeps 16 bits, and scaled by 1/65535);
    * ``light_directions.txt``: k x 3 unit vectors from the surface towards each light;
    * ``light_intensities.txt``: k x 3 RGB intensities, returned as ``intensities``; the rig of
      :meth:`Capture.rig` includes them, so the images are passed as loaded, not divided by them
      (see :mod:`nplps.captures`);
    * ``mask.png`` (channel 0 > 0) and ``Normal_gt.mat`` (variable ``Normal_gt``, H x W x 3).

    DiLiGenT's frame is x right, y up, z towards the viewer; directions and normals are
    converted to the camera frame by negating y and z: ``(x, y, z) -> (x, -y, -z)`` (a rotation
    by 180 degrees about x). Ground-truth normals then have ``n_z <= 0`` (0 on the silhouette)
    and are zero outside the object.

    Parameters
    ----------
    load : bool, optional
        Return the images as a float32 stack ``(k, H, W, 3)`` (``(k, H, W)`` with
        ``color=False``) instead of file names (16-bit PNG decoded in Rust, in parallel:
        about 0.5 s for the 96 images of ballPNG).
    color : bool | None, optional
        None (keep RGB), True (require RGB) or False: average the channels of loaded
        images (:func:`nplps.pipeline.to_gray`) and of the intensities.
    lights : Sequence[int] | None, optional
        A subset of the images/lights (0-based indices), e.g. ``range(0, 96, 8)``.
    normals : bool, optional
        Read ``Normal_gt.mat`` when present.
    K : np.ndarray | None, optional
        An optional pinhole matrix (0-based) to attach; DiLiGenT itself gives none
        (an orthographic set-up is assumed). See :func:`load_matlab_intrinsics`.
    """
    root = _diligent_folder(_check_folder(folder))
    names_path = root / "filenames.txt"
    names = [line.strip() for line in _read_names(names_path).splitlines() if line.strip()]
    dirs = _loadtxt(root / "light_directions.txt", 3)
    ints = _loadtxt(root / "light_intensities.txt", 3)
    if not (len(names) == dirs.shape[0] == ints.shape[0]):
        raise InputError(
            f"'{root}': {len(names)} file names, {dirs.shape[0]} light directions and {ints.shape[0]} light intensities"
        )
    flip = np.array([1.0, -1.0, -1.0])
    dirs = dirs * flip
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    count = len(names)
    rows = list(range(count)) if lights is None else _check_indices(lights, count, "lights")
    files = [_resolve(root, names[i]) for i in rows]
    intensities = ints[rows]
    if color is False:
        intensities = intensities.mean(axis=1)

    mask_path = root / "mask.png"
    mask = _read_mask(mask_path) if mask_path.is_file() else None

    normals_gt = None
    gt_path = root / "Normal_gt.mat"
    if normals and gt_path.is_file():
        n = _mat_var(read_mat(gt_path), "Normal_gt", gt_path)
        if n.ndim != 3 or n.shape[2] != 3:
            raise InputError(f"'{gt_path}': Normal_gt has shape {n.shape}, expected (H, W, 3)")
        normals_gt = n * flip
        normals_gt[normals_gt == 0] = 0.0  # no negative zeros

    images: list[Path] | np.ndarray = list(files)
    levels = None
    if load:
        images, levels = _read_stack(files, color)
        if mask is not None and mask.shape != images.shape[1:3]:
            raise InputError(f"mask.png has shape {mask.shape} but the images {images.shape[1:3]}")

    return Capture(
        images=images,
        mask=mask,
        K=None if K is None else preprocess._check_K(K),
        intensities=intensities,
        directions=dirs[rows],
        directional=True,
        normals_gt=normals_gt,
        name=root.name[:-3] if root.name.endswith("PNG") else root.name,
        notes=(
            "DiLiGenT (Shi et al., CVPR 2016): directional lights, 16-bit linear RGB; "
            "directions and normals converted to the camera frame (y, z negated). The RGB light "
            "intensities are in the rig (Capture.rig()): do not divide the images by them."
        ),
        files=list(files),
        levels=levels,
    )
