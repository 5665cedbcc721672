"""A plain capture folder with ``rig.json`` (nplps's own rig format)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import RigError
from ..io import PathLike
from .capture import Capture
from .files import _AUTO, MaskSpec, _ambient_arg, _check_folder, _image_list, _mask_arg


def load_folder(
    folder: PathLike,
    *,
    rig: PathLike = "rig.json",
    mask: MaskSpec | str = _AUTO,
    ambient: PathLike | np.ndarray | str | None = _AUTO,
    load: bool = False,
    color: bool | None = None,
) -> Capture:
    """Load a plain capture folder: ``rig.json``, images, optional mask and ambient image.

    * ``rig_path``: ``folder / rig`` (must exist); the lights and camera are **not** parsed
      here -- read them with ``nplps.Rig.load(capture.rig_path)``, so K, positions etc. stay None.
    * images: every image file (:data:`IMAGE_EXTENSIONS`) whose name contains neither "mask"
      nor "ambient", in natural order (``img2`` before ``img10``); their order must match the
      order of the lights in the rig.
    * mask: ``"auto"`` = ``mask.png`` if present, else the unique image file with "mask" in its
      name, else None; or a file name / array / None.
    * ambient: ``"auto"`` = the unique image file with "ambient" in its name, or None.

    ``load=True`` returns the images (and ambient) as float32 arrays via :meth:`Capture.load`
    (``color=False``: averaged to grey).
    """
    folder = _check_folder(folder)
    rig_path = Path(rig) if Path(rig).is_absolute() else folder / rig
    if not rig_path.is_file():
        raise RigError(f"rig file '{rig_path}' not found")
    if isinstance(mask, str) and mask == _AUTO and (folder / "mask.png").is_file():
        mask = "mask.png"
    files = _image_list(folder, None)
    capture = Capture(
        images=list(files),
        mask=_mask_arg(folder, mask),
        ambient=_ambient_arg(folder, ambient),
        name=folder.name,
        rig_path=rig_path,
        files=list(files),
    )
    return capture.load(color=color) if load else capture
