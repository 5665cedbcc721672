"""The near-light toolbox layout of Quéau et al. (``near_ps``) and two published captures in it."""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import numpy as np

from .. import pipeline, preprocess
from ..errors import InputError, RigError
from ..io import LoadProgress, PathLike, read_image, to_float
from .capture import Capture
from .files import (
    _AUTO,
    MaskSpec,
    _ambient_arg,
    _check_folder,
    _check_indices,
    _image_list,
    _mask_arg,
    _read_mask,
    _resolve,
    find_images,
)
from .matlab import _mat_var, load_matlab_intrinsics, read_mat


def _per_light(arr: np.ndarray, k: int, name: str, path: Path, widths: tuple[int, ...]) -> np.ndarray:
    """Reshape a light.mat variable to (k, width) (column vectors and scalars broadcast)."""
    a = np.atleast_2d(arr)
    if a.shape[0] != k and a.shape[1] == k and a.shape[0] in widths:
        a = a.T  # stored as a row / transposed
    if a.shape == (1, 1):
        a = np.repeat(a, k, axis=0)
    if a.shape[0] != k or a.shape[1] not in widths:
        raise RigError(
            f"'{path}': {name} has shape {arr.shape}, expected ({k}, " + " or ".join(str(w) for w in widths) + ")"
        )
    return a


def _prepare(
    path: Path,
    srgb: bool,
    bin_factor: int,
    grid_shape: tuple[int, int] | None,
    grid_offset: tuple[int, int],
    color: bool | None,
) -> tuple[np.ndarray, int | None]:
    """Read one image and bring it onto the calibration grid (see load_near_ps).

    Also return the top integer value of the file (None for floats).
    """
    raw = read_image(path)
    levels = int(np.iinfo(raw.dtype).max) if np.issubdtype(raw.dtype, np.integer) else None
    # sRGB of 8/16-bit files by an exact lookup table (fast on 18-Mpixel images), then grey.
    image = pipeline.decode_srgb(raw) if srgb else to_float(raw)
    if color is False and image.ndim == 3:
        image = pipeline.to_gray(image, stack=False)
    if bin_factor != 1:
        image = preprocess.bin_images(image, bin_factor, stack=False)
    if grid_shape is not None:
        image = preprocess.pad_or_crop(image, grid_shape, stack=False, offset=grid_offset)
    return image.astype(np.float32, copy=False), levels


def load_near_ps(
    folder: PathLike,
    images: Sequence[PathLike] | str | None = None,
    *,
    lights: Sequence[int] | None = None,
    mask: MaskSpec | str = _AUTO,
    ambient: PathLike | np.ndarray | str | None = _AUTO,
    camera_file: PathLike = "camera.mat",
    light_file: PathLike = "light.mat",
    load: bool = False,
    srgb: bool = False,
    bin_factor: int = 1,
    grid_shape: tuple[int, int] | None = None,
    grid_offset: tuple[int, int] = (0, 0),
    color: bool | None = None,
    name: str | None = None,
    notes: str = "",
    progress: LoadProgress | None = None,
) -> Capture:
    """Load a capture in the layout of the near-light toolbox of Quéau et al. (``near_ps``).

    Calibration (MATLAB files, read by :func:`nplps.captures.matlab.read_mat`):

    * ``camera.mat``: ``K``, 1-based MATLAB pixel coordinates, possibly stored transposed;
      converted with :func:`standardize_K` (``cx0 = K[0, 2] - 1``, ``cy0 = K[1, 2] - 1``).
      No distortion (``distortion`` stays None).
    * ``light.mat``: ``S`` (k x 3 LED positions, mm), ``Dir`` (k x 3 principal directions from
      the LED towards the scene; renormalized), ``Phi`` (k x 3 RGB or k x 1 intensities) and
      ``mu`` (k x 1 anisotropy). The toolbox's frame is already nplps's camera frame (x right,
      y down, z forward; LEDs in front of the camera have z > 0). The LED model is
      ``s_i(X) = Phi_i ((X - S_i).Dir_i / |X - S_i|)^mu_i (S_i - X) / |S_i - X|^3``.

    Images:

    * ``images``: None (every image file of the folder whose name contains neither "mask" nor
      "ambient", natural order), a glob pattern (``"photometric_sample_raw_*.png"``) or a list of
      file names (relative to ``folder`` or absolute). Their number must equal the number of
      selected lights.
    * ``lights``: the rows of ``S``/``Dir``/``Phi``/``mu`` that the images correspond to, in
      image order (0-based); None = all rows.
    * ``mask``: ``"auto"`` (the unique image file with "mask" in its name, if any), a file
      name, an array or None. Files are read as channel 0 > 0.
    * ``ambient``: ``"auto"`` (the unique file with "ambient" in its name, if any), a file name,
      an array or None. Processed like the images when they are loaded.

    By default the images are returned as file names. ``load=True`` -- implied by ``srgb``,
    ``color=False``, ``bin_factor != 1`` or ``grid_shape`` -- reads them into a float32 stack,
    each image going through: :func:`nplps.io.to_float` (integers scaled to [0, 1]); ``srgb``:
    sRGB decoding (:func:`nplps.pipeline.decode_srgb`); ``color=False``: channel mean
    (:func:`nplps.pipeline.to_gray`);
    ``bin_factor``: :func:`nplps.preprocess.bin_images`; ``grid_shape`` (with ``grid_offset``):
    :func:`nplps.preprocess.pad_or_crop` (zero fill). These steps describe how the image files
    map onto the pixel grid of ``camera.mat``; ``K`` and the mask are returned unchanged on that
    grid (the mask must have the images' final shape). The capture's ``preprocessed`` lists
    ``srgb`` / ``bin`` / ``pad`` when they ran, and ``levels`` is the files' top integer value
    while the values are as read.

    Intensities are ``Phi`` as ``(k,)`` for a k x 1 ``Phi`` and ``(k, 3)`` for k x 3 (averaged
    over R, G, B to ``(k,)`` with ``color=False``).

    ``progress``: ``progress(done, total, name)`` after each image is read, when they are loaded
    (:data:`nplps.io.LoadProgress`).

    Raises
    ------
    RigError
        Missing or malformed calibration files.
    InputError
        Missing images, image count != light count, shape mismatches.
    """
    folder = _check_folder(folder)
    cam_path = _resolve_calib(folder, camera_file)
    light_path = _resolve_calib(folder, light_file)
    K = load_matlab_intrinsics(cam_path, "K", one_based=True)

    ldata = read_mat(light_path)
    S = _mat_var(ldata, "S", light_path)
    if S.ndim == 2 and S.shape[1] == 3:
        n = S.shape[0]
    elif S.ndim == 2 and S.shape[0] == 3:
        n = S.shape[1]  # stored transposed (3 x k)
    else:
        raise RigError(f"'{light_path}': S has shape {S.shape}, expected (k, 3)")
    S = _per_light(S, n, "S", light_path, (3,))
    Dir = _per_light(_mat_var(ldata, "Dir", light_path), n, "Dir", light_path, (3,))
    Phi = _per_light(_mat_var(ldata, "Phi", light_path), n, "Phi", light_path, (1, 3))
    if "mu" in ldata:
        mu = _per_light(_mat_var(ldata, "mu", light_path), n, "mu", light_path, (1,))[:, 0]
    else:
        mu = np.ones(n)
    norms = np.linalg.norm(Dir, axis=1)
    if np.any(norms < 1e-9):
        raise RigError(f"'{light_path}': Dir has a zero row")
    Dir = Dir / norms[:, None]

    rows = list(range(n)) if lights is None else _check_indices(lights, n, "lights")
    files = _image_list(folder, images)
    if len(files) != len(rows):
        listed = ", ".join(p.name for p in files[:12]) + (" ..." if len(files) > 12 else "")
        raise InputError(
            f"{len(files)} image files ({listed}) but {len(rows)} lights selected from "
            f"'{light_path.name}' ({n} rows): pass images= and lights= explicitly"
        )

    intensities = Phi[rows]
    if intensities.shape[1] == 1:
        intensities = intensities[:, 0]
    elif color is False:
        intensities = intensities.mean(axis=1)

    mask_arr = _mask_arg(folder, mask)
    amb = _ambient_arg(folder, ambient)

    load = load or srgb or color is False or bin_factor != 1 or grid_shape is not None
    images_out: list[Path] | np.ndarray = list(files)
    levels: int | None = None
    done: tuple[str, ...] = ()
    if load:
        bin_factor = int(bin_factor)
        read = []
        for i, p in enumerate(files):
            read.append(_prepare(p, srgb, bin_factor, grid_shape, grid_offset, color))
            if progress is not None:
                progress(i + 1, len(files), Path(p).name)
        stack = [image for image, _ in read]
        for p, img in zip(files, stack, strict=True):
            if img.shape != stack[0].shape:
                raise InputError(f"image '{p}' has shape {img.shape} but '{files[0]}' has {stack[0].shape}")
        images_out = np.stack(stack)
        if color is True and images_out.ndim != 4:
            raise InputError("color=True needs RGB images")
        done = tuple(
            step for step, ran in (("srgb", srgb), ("bin", bin_factor != 1), ("pad", grid_shape is not None)) if ran
        )
        file_levels = [v for _, v in read]
        if not done and None not in file_levels:
            levels = max(v for v in file_levels if v is not None)
        if isinstance(amb, Path):
            amb = _prepare(amb, srgb, bin_factor, grid_shape, grid_offset, color)[0]
        if mask_arr is not None and mask_arr.shape != images_out.shape[1:3]:
            raise InputError(f"the mask has shape {mask_arr.shape} but the images have {images_out.shape[1:3]}")

    return Capture(
        images=images_out,
        mask=mask_arr,
        K=K,
        positions=S[rows].copy(),
        directions=Dir[rows].copy(),
        intensities=np.ascontiguousarray(intensities),
        mu=mu[rows].copy(),
        directional=False,
        ambient=amb,
        name=name if name is not None else folder.name,
        notes=notes,
        files=list(files),
        levels=levels,
        preprocessed=done,
    )


def _resolve_calib(folder: Path, name: PathLike) -> Path:
    """Return a calibration file relative to ``folder``; RigError if missing."""
    path = Path(name)
    if not path.is_absolute():
        path = folder / path
    if not path.is_file():
        raise RigError(f"calibration file '{path}' not found")
    return path


def _led_rows_from_names(files: Sequence[Path]) -> list[int]:
    """LED rows (0-based) from the last number in each file name (``..._0006.png`` -> 5)."""
    rows = []
    for p in files:
        numbers = re.findall(r"\d+", p.stem)
        if not numbers:
            raise InputError(f"cannot tell the LED of '{p.name}': no number in its name")
        rows.append(int(numbers[-1]) - 1)
    return rows


def load_hehe12(folder: PathLike, *, load: bool = False) -> Capture:
    """Load the ``hehe12`` capture of ``marcellliu/near_ps`` (8 LEDs, no ground truth).

    Images ``photometric_sample_raw_0001..0008.png`` (1920 x 1200, 8-bit grey, linear, dim),
    ambient ``photometric_sample_raw_ambient.png``, mask ``photometric_sample_mask_raw.png``
    (channel 0 > 0). ``camera.mat`` stores K transposed (handled by :func:`standardize_K`).
    ``photometric_sample_all.png`` (a composite) is not an input image.
    The LED of each image is read from the number in its name (``_0003`` -> row 2).
    """
    folder = _check_folder(folder)
    files = find_images(folder, "photometric_sample_raw_[0-9]*.png")
    return load_near_ps(
        folder,
        files,
        lights=_led_rows_from_names(files),
        mask="photometric_sample_mask_raw.png",
        ambient="photometric_sample_raw_ambient.png",
        load=load,
        name="hehe12",
        notes=(
            "near_ps toolbox capture (marcellliu/near_ps, Example_Img/hehe12): 8-bit grey, "
            "treat as linear; LEDs ~90 mm off-axis, ~75 mm in front of the lens (z > 0); "
            "object ~200 mm away. Preprocess: subtract the ambient image (clip at 0), divide "
            "by the cos^4 vignetting map."
        ),
    )


def load_queau_human1(
    folder: PathLike,
    *,
    grid: Literal["raw", "jpeg"] = "raw",
    grid_offset: tuple[int, int] = (0, 0),
    lights: Sequence[int] | None = None,
    color: bool | None = False,
    progress: LoadProgress | None = None,
) -> Capture:
    """Load the ``Human1`` scene of ``yqueau/near_ps`` from its JPEG renders (7 of 8 LEDs).

    Only ``photometric_sample_jpg_000{1,2,3,4,6,7,8}.png`` exist (5184 x 3456 8-bit sRGB, LED 5
    missing); the LED of each file is read from its number, so rows 0, 1, 2, 3, 5, 6, 7 of the
    calibration are used. The images are decoded from sRGB to linear (exactly, by a lookup
    table) and averaged in 2 x 2 blocks (2592 x 1728), which puts them on the half-resolution
    RAW grid of ``camera.mat`` and of the mask (2601 x 1732). Then:

    * ``grid="raw"`` (default): the images (and the ambient image) are padded with zeros by 4
      rows at the bottom and 9 columns at the right to the RAW grid, 1732 x 2601; K and the
      mask are used as they are.
    * ``grid="jpeg"``: the images stay 1728 x 2592 and the mask is cropped at the
      bottom/right to that size (it selects nothing in the cropped band); K is unchanged since
      the origin does not move.

    Either way pixel ``(r, c)`` of the binned JPEG is taken as RAW pixel ``(r, c)``
    (``grid_offset = (top, left)`` shifts the JPEG content on the RAW grid instead, if a better
    registration is known). The correspondence is approximate (a few pixels): the JPEG is the
    camera's crop of the sensor area, and its exact placement on the RAW grid is not recorded.

    ``lights``: load only these LED rows (0-based calibration rows, e.g. ``[0, 5]``); None =
    all seven available. Loading all seven takes a few seconds (18-Mpixel PNG decoding).

    ``color=False`` (default) averages R, G, B of the images and of ``Phi``; ``color=None``
    keeps them. The
    calibrated ``Phi`` is for the RAW data; the JPEG's tone curve and white balance make the intensities
    only approximately right (a robustness test, not a benchmark).

    ``progress``: ``progress(done, total, name)`` after each image is read.
    """
    folder = _check_folder(folder)
    files = find_images(folder, "photometric_sample_jpg_[0-9]*.png")
    if lights is not None:
        available = dict(zip(_led_rows_from_names(files), files, strict=True))
        missing = [int(i) for i in lights if int(i) not in available]
        if missing:
            raise InputError(f"no image of LED row(s) {missing} in '{folder}' (available rows: {sorted(available)})")
        files = [available[int(i)] for i in lights]
    mask_path = _resolve(folder, "photometric_sample_mask_raw.png")
    mask = _read_mask(mask_path)
    if grid not in ("raw", "jpeg"):
        raise InputError(f"grid must be 'raw' or 'jpeg', got {grid!r}")
    notes = (
        "yqueau/near_ps Datasets/Human1 from the camera's 8-bit sRGB JPEG renders (the RAW "
        "images the calibration is for are not available). Decoded to linear, 2x2-binned onto "
        f"the RAW grid ({grid} grid). LEDs 350-520 mm in front of the camera (z > 0), object "
        "~700 mm away. Preprocess: subtract the ambient image (clip at 0), divide by the "
        "cos^4 vignetting map."
    )
    if grid == "jpeg" and tuple(grid_offset) != (0, 0):
        raise InputError("grid_offset applies to grid='raw' only")
    raw = grid == "raw"
    capture = load_near_ps(
        folder,
        files,
        lights=_led_rows_from_names(files),
        mask=mask if raw else None,
        ambient="photometric_sample_jpg_ambient.png",
        srgb=True,
        bin_factor=2,
        grid_shape=mask.shape if raw else None,
        grid_offset=grid_offset if raw else (0, 0),
        color=color,
        name="queau_human1",
        notes=notes,
        progress=progress,
    )
    if not raw:
        assert isinstance(capture.images, np.ndarray)  # srgb loads them
        capture.mask = preprocess.pad_or_crop(mask, capture.images.shape[1:3])
    return capture
