"""Loaders for photometric-stereo captures in published layouts.

Each loader returns a plain :class:`Capture`: images (file names or a float32 stack), mask,
camera matrix, lights and, when the dataset has them, ground-truth normals, all converted to
the conventions of nplps:

* camera frame (OpenCV): origin at the optical centre, x right (increasing column), y down
  (increasing row), z forward along the optical axis into the scene; millimetres;
* pinhole matrix ``K`` in the 0-based pixel-centre convention: pixel ``(r, c)`` has its centre
  at ``(u, v) = (c, r)``;
* normals face the camera (``n_z < 0``);
* directional lights are unit vectors from the surface towards the light.

Supported layouts:

* :func:`load_near_ps` -- the near-light toolbox of Quéau et al. (``camera.mat`` with ``K``,
  ``light.mat`` with ``S``, ``Dir``, ``Phi``, ``mu``, image files and a mask), with the helpers
  :func:`load_hehe12` and :func:`load_queau_human1` for two published captures;
* :func:`load_diligent` -- DiLiGenT's ``*PNG`` folders (directional lights, ground-truth normals);
* :func:`load_folder` -- a plain folder with ``rig.json`` (nplps's own rig format), images, an
  optional mask and an optional ambient image.

The loaders only convert units and frames; radiometric corrections (ambient subtraction,
vignetting, per-light intensities) are left to the caller, see :mod:`nplps.preprocess`.
``scipy`` is needed for MATLAB files (it is imported on first use).
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Union

import numpy as np

from . import preprocess
from .errors import InputError, RigError

if TYPE_CHECKING:
    from .rig import Rig
from .io import PathLike, read_image, to_float

__all__ = [
    "Capture",
    "IMAGE_EXTENSIONS",
    "find_images",
    "standardize_K",
    "load_matlab_intrinsics",
    "load_near_ps",
    "load_hehe12",
    "load_queau_human1",
    "load_diligent",
    "load_folder",
]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
"""File name extensions (lower case) that the loaders treat as images."""

_AUTO = "auto"
MaskSpec = Union[PathLike, np.ndarray, None]


# --------------------------------------------------------------------------------------------------
# The Capture record
# --------------------------------------------------------------------------------------------------


@dataclass
class Capture:
    """One photometric-stereo capture, in nplps's conventions (see the module docstring).

    Attributes:
        images: the ``k`` images, either as file names (``list[Path]``, read them with
            :meth:`load` or :func:`nplps.io.load_images`) or as a float32 stack
            ``(k, H, W)`` / ``(k, H, W, 3)`` of linear intensities.
        mask: ``(H, W)`` bool, or None (no mask in the dataset).
        K: ``(3, 3)`` float64 pinhole matrix, 0-based pixel centres, or None (unknown).
        distortion: ``(5,)`` OpenCV distortion ``(k1, k2, p1, p2, k3)`` or None (none given).
        positions: ``(k, 3)`` point-light positions in mm (camera frame), or None.
        directions: ``(k, 3)`` unit vectors, or None. For point lights the LED principal axes
            (pointing from the LED towards the scene); for ``directional`` captures the
            directions from the surface towards each light.
        intensities: ``(k,)`` or ``(k, 3)`` (per RGB channel) light intensities, or None. Near
            lights: ``Phi`` of the toolbox model (image units x mm^2); directional lights:
            the relative radiance of each light.
        mu: ``(k,)`` anisotropy exponents of the LED model ``cos(angle to axis)^mu``, or None.
        directional: True for distant (directional) lights, False for point lights.
        normals_gt: ``(H, W, 3)`` ground-truth unit normals (camera frame, ``n_z < 0``; zero
            outside the object), or None.
        ambient: the image with every light off (a file name or an array like one image of
            ``images``), or None.
        name: a short name of the capture.
        notes: free text: provenance, caveats, what the loader did.
        rig_path: the ``rig.json`` of a :func:`load_folder` capture (read it with
            ``nplps.Rig.load``), else None.
        files: the image files the images came from (also when ``images`` is an array).
    """

    images: list[Path] | np.ndarray
    mask: np.ndarray | None = None
    K: np.ndarray | None = None
    distortion: np.ndarray | None = None
    positions: np.ndarray | None = None
    directions: np.ndarray | None = None
    intensities: np.ndarray | None = None
    mu: np.ndarray | None = None
    directional: bool = False
    normals_gt: np.ndarray | None = None
    ambient: Path | np.ndarray | None = None
    name: str = ""
    notes: str = ""
    rig_path: Path | None = None
    files: list[Path] = field(default_factory=list)
    #: Pixel footprint of the orthographic rig used when K is unknown (grows with binning).
    pixel_size: float = 1.0

    @property
    def num_images(self) -> int:
        """The number of images ``k``."""
        return len(self.images)

    @property
    def loaded(self) -> bool:
        """True when ``images`` is an array rather than a list of file names."""
        return isinstance(self.images, np.ndarray)

    def load(self, gray: bool = False) -> Capture:
        """Return a copy whose ``images`` (and ``ambient``) are float32 arrays.

        Files are read with :func:`nplps.io.read_image` (16-bit PNG keeps 16 bits) and scaled to
        ``[0, 1]`` by :func:`nplps.io.to_float`; no other conversion is applied (the files must
        already be linear). ``gray=True`` averages the colour channels, giving ``(k, H, W)``.
        An already loaded capture is returned as a copy (converted to grey if asked).
        """
        images = self.images
        if not isinstance(images, np.ndarray):
            images = _read_stack(images, gray=gray)
        elif gray and images.ndim == 4:
            images = images.mean(axis=3, dtype=np.float64).astype(np.float32)
        ambient = self.ambient
        if ambient is not None and not isinstance(ambient, np.ndarray):
            ambient = _read_float(Path(ambient))
        if ambient is not None and gray and ambient.ndim == 3:
            ambient = ambient.mean(axis=2, dtype=np.float64).astype(np.float32)
        return dataclasses.replace(self, images=images, ambient=ambient)

    def rig(self) -> "Rig":
        """The capture's :class:`~nplps.Rig`: its rig file, or a pinhole camera (orthographic with
        unit pixels when K is unknown) with its point lights (LED model) or directional lights."""
        from .rig import Rig

        if self.rig_path is not None:
            return Rig.load(self.rig_path)
        if self.directional:
            if self.K is None:
                return Rig.orthographic(
                    self.pixel_size, directional_lights=self.directions, directional_intensities=self.intensities
                )
            return Rig.pinhole(self.K, distortion=self.distortion, directional_lights=self.directions,
                               directional_intensities=self.intensities)
        if self.K is None or self.positions is None:
            raise InputError(f"capture {self.name!r} has no camera intrinsics or light positions to build a rig from")
        return Rig.pinhole(self.K, lights=self.positions, distortion=self.distortion, intensities=self.intensities,
                           directions=self.directions, mu=self.mu)

    def select(self, indices: Sequence[int]) -> Capture:
        """Return a copy restricted to the images / lights ``indices`` (0-based, in order)."""
        idx = _check_indices(indices, self.num_images, "select")

        def pick(arr: Any) -> Any:
            return None if arr is None else np.asarray(arr)[idx].copy()

        if isinstance(self.images, np.ndarray):
            images: list[Path] | np.ndarray = self.images[idx].copy()
        else:
            images = [self.images[i] for i in idx]
        files = [self.files[i] for i in idx] if len(self.files) == self.num_images else []
        return dataclasses.replace(
            self,
            images=images,
            positions=pick(self.positions),
            directions=pick(self.directions),
            intensities=pick(self.intensities),
            mu=pick(self.mu),
            files=files,
        )


# --------------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------------


def _natural_key(path: Path) -> list[Any]:
    """Sort key that orders embedded numbers numerically: img2 < img10."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", path.name)]


def find_images(
    folder: PathLike,
    pattern: str = "*",
    exclude: Sequence[str] = ("mask", "ambient"),
) -> list[Path]:
    """Image files of ``folder`` matching the glob ``pattern``, in natural order.

    Files whose extension is not in :data:`IMAGE_EXTENSIONS` (case-insensitive) and files whose
    name contains one of the ``exclude`` words (case-insensitive) are skipped. Natural order
    sorts embedded numbers by value (``img2`` before ``img10``).
    """
    folder = Path(folder)
    words = [w.lower() for w in exclude]
    found = [
        p
        for p in folder.glob(pattern)
        if p.is_file()
        and p.suffix.lower() in IMAGE_EXTENSIONS
        and not any(w in p.name.lower() for w in words)
    ]
    return sorted(found, key=_natural_key)


def _find_one(folder: Path, word: str) -> Path | None:
    """The unique image file of ``folder`` whose name contains ``word``, or None if none."""
    hits = [
        p
        for p in sorted(folder.iterdir())
        if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS and word in p.name.lower()
    ]
    if len(hits) > 1:
        names = ", ".join(p.name for p in hits)
        raise InputError(
            f"several {word} images in '{folder}' ({names}): pass the one to use explicitly"
        )
    return hits[0] if hits else None


def _check_folder(folder: PathLike) -> Path:
    """Return ``folder`` as a Path, or raise InputError if it is not a directory."""
    path = Path(folder)
    if not path.is_dir():
        raise InputError(f"capture folder '{path}' does not exist or is not a directory")
    return path


def _resolve(folder: Path, name: PathLike) -> Path:
    """``name`` relative to ``folder`` unless absolute or already an existing path; must exist."""
    path = Path(name)
    if not path.is_absolute() and not path.is_file():
        path = folder / path
    if not path.is_file():
        raise InputError(f"file '{path}' not found")
    return path


def _image_list(folder: Path, images: Sequence[PathLike] | str | None) -> list[Path]:
    """Resolve the ``images`` argument of the loaders into existing files."""
    if images is None:
        files = find_images(folder)
    elif isinstance(images, str):
        files = find_images(folder, images, exclude=())
    else:
        files = [_resolve(folder, p) for p in images]
    if not files:
        raise InputError(f"no image file found in '{folder}'")
    return files


def _read_float(path: Path) -> np.ndarray:
    """Read one image file as float32 in [0, 1] (integers) or as stored (floats)."""
    return to_float(read_image(path))


def _read_stack(files: Sequence[PathLike], gray: bool) -> np.ndarray:
    """Read image files into a float32 stack ``(k, H, W[, 3])``."""
    arrays = []
    for path in files:
        image = _read_float(Path(path))
        if gray and image.ndim == 3:
            image = image.mean(axis=2, dtype=np.float64).astype(np.float32)
        if arrays and image.shape != arrays[0].shape:
            raise InputError(
                f"image '{path}' has shape {image.shape} but '{files[0]}' has {arrays[0].shape}"
            )
        arrays.append(image)
    return np.stack(arrays)


def _read_mask(path: Path) -> np.ndarray:
    """Read a mask image: channel 0 > 0 (anti-aliased masks count any coverage)."""
    m = read_image(path)
    if m.ndim == 3:
        m = m[..., 0]
    mask = m > 0
    if not mask.any():
        raise InputError(f"mask '{path}' selects no pixel")
    return mask


def _mask_arg(folder: Path, mask: MaskSpec | str) -> np.ndarray | None:
    """Resolve a ``mask`` argument: "auto" (unique file with 'mask' in its name), path, array."""
    if isinstance(mask, str) and mask == _AUTO:
        found = _find_one(folder, "mask")
        return None if found is None else _read_mask(found)
    if mask is None:
        return None
    if isinstance(mask, np.ndarray):
        m = np.asarray(mask)
        m = m[..., 0] if m.ndim == 3 else m
        if m.ndim != 2:
            raise InputError(f"mask: expected shape (H, W), got {np.shape(mask)}")
        return m != 0
    return _read_mask(_resolve(folder, mask))


def _ambient_arg(
    folder: Path, ambient: PathLike | np.ndarray | None | str
) -> Path | np.ndarray | None:
    """Resolve an ``ambient`` argument: "auto" (unique 'ambient' file), path, array or None."""
    if isinstance(ambient, str) and ambient == _AUTO:
        return _find_one(folder, "ambient")
    if ambient is None or isinstance(ambient, np.ndarray):
        return ambient
    return _resolve(folder, ambient)


def _check_indices(indices: Sequence[int], n: int, what: str) -> list[int]:
    """Validate 0-based indices into ``n`` items."""
    out = []
    for i in indices:
        if isinstance(i, (bool, np.bool_)) or int(i) != i:
            raise InputError(f"{what}: indices must be integers, got {i!r}")
        if not 0 <= int(i) < n:
            raise InputError(f"{what}: index {i} out of range 0..{n - 1}")
        out.append(int(i))
    if not out:
        raise InputError(f"{what}: no index given")
    return out


# --------------------------------------------------------------------------------------------------
# MATLAB files
# --------------------------------------------------------------------------------------------------


def _loadmat(path: Path) -> dict[str, Any]:
    """Read a MATLAB (v5/v7) file with scipy, raising RigError with the file name."""
    try:
        import scipy.io  # lazy: scipy is only needed for MATLAB files
    except ImportError as exc:  # pragma: no cover - scipy is installed with the test extras
        raise RigError(f"reading '{path}' needs scipy (pip install scipy)") from exc
    if not path.is_file():
        raise RigError(f"calibration file '{path}' not found")
    try:
        return scipy.io.loadmat(str(path))
    except Exception as exc:  # scipy raises ValueError, TypeError, NotImplementedError (v7.3)...
        raise RigError(f"cannot read MATLAB file '{path}': {exc}") from exc


def _mat_var(data: dict[str, Any], name: str, path: Path) -> np.ndarray:
    """Variable ``name`` of a loaded .mat file as a float64 array."""
    if name not in data:
        found = ", ".join(k for k in data if not k.startswith("__")) or "none"
        raise RigError(f"'{path}' has no variable '{name}' (variables: {found})")
    try:
        arr = np.asarray(data[name], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise RigError(f"'{path}': variable '{name}' is not numeric") from exc
    if not np.all(np.isfinite(arr)):
        raise RigError(f"'{path}': variable '{name}' has non-finite values")
    return arr


def standardize_K(K: np.ndarray, one_based: bool = True) -> np.ndarray:
    """Bring a MATLAB-style camera matrix to the standard 0-based form.

    A valid ``K`` is upper triangular with last row ``[0, 0, 1]``. MATLAB's
    ``cameraParameters.IntrinsicMatrix`` stores the transpose ``[fx 0 0; s fy 0; cx cy 1]``:
    when the last row is not ``[0, 0, 1]`` but the last column is and ``K[2, 0:2]`` is
    nonzero, the matrix is transposed. With ``one_based=True`` (MATLAB pixel coordinates, pixel
    ``(1, 1)`` centred at ``(1, 1)``) the principal point is shifted to the 0-based
    pixel-centre convention: ``cx0 = cx - 1``, ``cy0 = cy - 1``.

    Raises:
        RigError: not a (3, 3) finite matrix of that form, or non-positive focal lengths.
    """
    K = np.array(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise RigError(f"K must be a finite (3, 3) matrix, got {np.shape(K)}")
    last = np.array([0.0, 0.0, 1.0])
    if not np.allclose(K[2], last):
        if np.allclose(K[:, 2], last) and np.any(K[2, :2] != 0):
            K = K.T.copy()
        else:
            raise RigError(
                f"K is not a pinhole matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]]: {K.tolist()}"
            )
    K[2] = last
    if K[1, 0] != 0:
        raise RigError(f"K[1, 0] must be 0, got {K[1, 0]}")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise RigError(f"K has non-positive focal lengths fx={K[0, 0]}, fy={K[1, 1]}")
    if one_based:
        K[0, 2] -= 1.0
        K[1, 2] -= 1.0
    return K


def load_matlab_intrinsics(
    path: PathLike, variable: str = "K", one_based: bool = True
) -> np.ndarray:
    """Read ``K`` from a MATLAB file and return it with :func:`standardize_K` applied.

    E.g. ``camera.mat`` of the near-light toolbox, or ``calib.mat`` of Quéau's robust_ps
    DiLiGenT calibration. Returns a float64 (3, 3) matrix, 0-based pixel centres.
    """
    path = Path(path)
    return standardize_K(_mat_var(_loadmat(path), variable, path), one_based=one_based)


def _per_light(
    arr: np.ndarray, k: int, name: str, path: Path, widths: tuple[int, ...]
) -> np.ndarray:
    """Reshape a light.mat variable to (k, width) (column vectors and scalars broadcast)."""
    a = np.atleast_2d(arr)
    if a.shape[0] != k and a.shape[1] == k and a.shape[0] in widths:
        a = a.T  # stored as a row / transposed
    if a.shape == (1, 1):
        a = np.repeat(a, k, axis=0)
    if a.shape[0] != k or a.shape[1] not in widths:
        raise RigError(
            f"'{path}': {name} has shape {arr.shape}, expected ({k}, "
            + " or ".join(str(w) for w in widths) + ")"
        )
    return a


# --------------------------------------------------------------------------------------------------
# Near-light toolbox layout (Quéau et al.)
# --------------------------------------------------------------------------------------------------


def _srgb_lut(dtype: np.dtype) -> np.ndarray:
    """float32 lookup table of srgb_to_linear for every value of an 8- or 16-bit dtype."""
    top = np.iinfo(dtype).max
    return preprocess.srgb_to_linear(np.arange(top + 1, dtype=np.float64) / top).astype(np.float32)


def _prepare(
    path: Path,
    srgb: bool,
    bin_factor: int,
    grid_shape: tuple[int, int] | None,
    grid_offset: tuple[int, int],
    gray: bool,
) -> np.ndarray:
    """Read one image and bring it onto the calibration grid (see load_near_ps)."""
    raw = read_image(path)
    if srgb and raw.dtype in (np.uint8, np.uint16):
        # A lookup table is exact and much faster than the formula on 18-Mpixel images.
        lut = _srgb_lut(raw.dtype)
        if gray and raw.ndim == 3:
            planes = np.ascontiguousarray(np.moveaxis(raw, -1, 0))
            image = lut[planes[0]]
            for plane in planes[1:]:
                image += lut[plane]
            image *= np.float32(1.0 / len(planes))
        else:
            image = lut[raw]
    elif srgb:
        image = preprocess.srgb_to_linear(to_float(raw))
    else:
        image = to_float(raw)
    if gray and image.ndim == 3:
        image = image.mean(axis=2, dtype=np.float64).astype(np.float32)
    if bin_factor != 1:
        image = preprocess.bin_images(image, bin_factor, stack=False)
    if grid_shape is not None:
        image = preprocess.pad_or_crop(image, grid_shape, stack=False, offset=grid_offset)
    return image.astype(np.float32, copy=False)


def load_near_ps(
    folder: PathLike,
    images: Sequence[PathLike] | str | None = None,
    *,
    lights: Sequence[int] | None = None,
    mask: MaskSpec | str = _AUTO,
    ambient: PathLike | np.ndarray | None | str = _AUTO,
    camera_file: PathLike = "camera.mat",
    light_file: PathLike = "light.mat",
    load: bool = False,
    srgb: bool = False,
    bin_factor: int = 1,
    grid_shape: tuple[int, int] | None = None,
    grid_offset: tuple[int, int] = (0, 0),
    gray: bool = False,
    name: str | None = None,
    notes: str = "",
) -> Capture:
    """Load a capture in the layout of the near-light toolbox of Quéau et al. (``near_ps``).

    Calibration (MATLAB files, read with scipy):

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
    ``gray``, ``bin_factor != 1`` or ``grid_shape`` -- reads them into a float32 stack, each image
    going through: :func:`nplps.io.to_float` (integers scaled to [0, 1]); ``srgb``: sRGB
    decoding (:func:`nplps.preprocess.srgb_to_linear`); ``gray``: channel mean;
    ``bin_factor``: :func:`nplps.preprocess.bin_images`; ``grid_shape`` (with ``grid_offset``):
    :func:`nplps.preprocess.pad_or_crop` (zero fill). These steps describe how the image files
    map onto the pixel grid of ``camera.mat``; ``K`` and the mask are returned unchanged on that
    grid (the mask must have the images' final shape).

    Intensities are ``Phi`` as ``(k,)`` for a k x 1 ``Phi`` and ``(k, 3)`` for k x 3 (averaged
    over R, G, B to ``(k,)`` when ``gray``).

    Raises:
        RigError: missing or malformed calibration files.
        InputError: missing images, image count != light count, shape mismatches.
    """
    folder = _check_folder(folder)
    cam_path = _resolve_calib(folder, camera_file)
    light_path = _resolve_calib(folder, light_file)
    K = load_matlab_intrinsics(cam_path, "K", one_based=True)

    ldata = _loadmat(light_path)
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
    elif gray:
        intensities = intensities.mean(axis=1)

    mask_arr = _mask_arg(folder, mask)
    amb = _ambient_arg(folder, ambient)

    load = load or srgb or gray or bin_factor != 1 or grid_shape is not None
    images_out: list[Path] | np.ndarray = list(files)
    if load:
        bin_factor = int(bin_factor)
        steps = dict(
            srgb=srgb, bin_factor=bin_factor, grid_shape=grid_shape,
            grid_offset=grid_offset, gray=gray,
        )
        stack = [_prepare(p, **steps) for p in files]
        for p, img in zip(files, stack):
            if img.shape != stack[0].shape:
                raise InputError(
                    f"image '{p}' has shape {img.shape} but '{files[0]}' has {stack[0].shape}"
                )
        images_out = np.stack(stack)
        if isinstance(amb, Path):
            amb = _prepare(amb, **steps)
        if mask_arr is not None and mask_arr.shape != images_out.shape[1:3]:
            raise InputError(
                f"the mask has shape {mask_arr.shape} but the images have {images_out.shape[1:3]}"
            )

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
    )


def _resolve_calib(folder: Path, name: PathLike) -> Path:
    """A calibration file relative to ``folder``; RigError if missing."""
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
    """The ``hehe12`` capture of ``marcellliu/near_ps`` (8 LEDs, no ground truth).

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
    gray: bool = True,
    grid_offset: tuple[int, int] = (0, 0),
    lights: Sequence[int] | None = None,
) -> Capture:
    """The ``Human1`` scene of ``yqueau/near_ps`` from its JPEG renders (7 of 8 LEDs).

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

    ``gray=True`` (default) averages R, G, B of the images and of ``Phi``. The calibrated
    ``Phi`` is for the RAW data; the JPEG's tone curve and white balance make the intensities
    only approximately right (a robustness test, not a benchmark).
    """
    folder = _check_folder(folder)
    files = find_images(folder, "photometric_sample_jpg_[0-9]*.png")
    if lights is not None:
        available = dict(zip(_led_rows_from_names(files), files))
        missing = [int(i) for i in lights if int(i) not in available]
        if missing:
            raise InputError(
                f"no image of LED row(s) {missing} in '{folder}' "
                f"(available rows: {sorted(available)})"
            )
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
    common = dict(
        lights=_led_rows_from_names(files),
        ambient="photometric_sample_jpg_ambient.png",
        srgb=True,
        bin_factor=2,
        gray=gray,
        name="queau_human1",
        notes=notes,
    )
    if grid == "raw":
        capture = load_near_ps(
            folder, files, mask=mask, grid_shape=mask.shape, grid_offset=grid_offset, **common
        )
    else:
        if tuple(grid_offset) != (0, 0):
            raise InputError("grid_offset applies to grid='raw' only")
        capture = load_near_ps(folder, files, mask=None, **common)
        capture.mask = preprocess.pad_or_crop(mask, capture.images.shape[1:3])
    return capture


# --------------------------------------------------------------------------------------------------
# DiLiGenT
# --------------------------------------------------------------------------------------------------


def _diligent_folder(folder: Path) -> Path:
    """The folder holding filenames.txt: ``folder`` itself or its unique ``*PNG`` subfolder."""
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


def load_diligent(
    folder: PathLike,
    *,
    load: bool = False,
    gray: bool = False,
    lights: Sequence[int] | None = None,
    normals: bool = True,
    K: np.ndarray | None = None,
) -> Capture:
    """Load one DiLiGenT object (``ballPNG/`` and the like; Shi et al., CVPR 2016).

    ``folder`` is the object folder (holding ``filenames.txt``) or a folder with exactly one
    ``*PNG`` subfolder. Files:

    * ``filenames.txt``: the image names, one per line (16-bit RGB PNG, linear; read by
      :func:`nplps.io.read_image`, which keeps 16 bits, and scaled by 1/65535);
    * ``light_directions.txt``: k x 3 unit vectors from the surface towards each light;
    * ``light_intensities.txt``: k x 3 RGB intensities (divide image i channel c by
      ``intensities[i, c]``, e.g. with :func:`nplps.preprocess.scale_exposure`);
    * ``mask.png`` (channel 0 > 0) and ``Normal_gt.mat`` (variable ``Normal_gt``, H x W x 3).

    DiLiGenT's frame is x right, y up, z towards the viewer; directions and normals are
    converted to the camera frame by negating y and z: ``(x, y, z) -> (x, -y, -z)`` (a rotation
    by 180 degrees about x). Ground-truth normals then have ``n_z <= 0`` (0 on the silhouette)
    and are zero outside the object.

    Args:
        load: return the images as a float32 stack ``(k, H, W, 3)`` (``(k, H, W)`` with
            ``gray``) instead of file names. Reading is slow with pypng (~0.2 s per 612 x 512
            image).
        gray: average the channels of loaded images and of the intensities.
        lights: a subset of the images/lights (0-based indices), e.g. ``range(0, 96, 8)``.
        normals: read ``Normal_gt.mat`` when present (needs scipy).
        K: an optional pinhole matrix (0-based) to attach; DiLiGenT itself gives none
            (an orthographic set-up is assumed). See :func:`load_matlab_intrinsics`.
    """
    root = _diligent_folder(_check_folder(folder))
    names_path = root / "filenames.txt"
    names = [line.strip() for line in names_path.read_text().splitlines() if line.strip()]
    dirs = _loadtxt(root / "light_directions.txt", 3)
    ints = _loadtxt(root / "light_intensities.txt", 3)
    if not (len(names) == dirs.shape[0] == ints.shape[0]):
        raise InputError(
            f"'{root}': {len(names)} file names, {dirs.shape[0]} light directions and "
            f"{ints.shape[0]} light intensities"
        )
    flip = np.array([1.0, -1.0, -1.0])
    dirs = dirs * flip
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    count = len(names)
    rows = list(range(count)) if lights is None else _check_indices(lights, count, "lights")
    files = [_resolve(root, names[i]) for i in rows]
    intensities = ints[rows]
    if gray:
        intensities = intensities.mean(axis=1)

    mask_path = root / "mask.png"
    mask = _read_mask(mask_path) if mask_path.is_file() else None

    normals_gt = None
    gt_path = root / "Normal_gt.mat"
    if normals and gt_path.is_file():
        n = _mat_var(_loadmat(gt_path), "Normal_gt", gt_path)
        if n.ndim != 3 or n.shape[2] != 3:
            raise InputError(f"'{gt_path}': Normal_gt has shape {n.shape}, expected (H, W, 3)")
        normals_gt = n * flip
        normals_gt[normals_gt == 0] = 0.0  # no negative zeros

    images: list[Path] | np.ndarray = list(files)
    if load:
        images = _read_stack(files, gray=gray)
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
            "directions and normals converted to the camera frame (y, z negated). Divide "
            "each image by its RGB light intensity."
        ),
        files=list(files),
    )


# --------------------------------------------------------------------------------------------------
# Plain folder with rig.json
# --------------------------------------------------------------------------------------------------


def load_folder(
    folder: PathLike,
    *,
    rig: PathLike = "rig.json",
    mask: MaskSpec | str = _AUTO,
    ambient: PathLike | np.ndarray | None | str = _AUTO,
    load: bool = False,
    gray: bool = False,
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

    ``load=True`` returns the images (and ambient) as float32 arrays via :meth:`Capture.load`.
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
    return capture.load(gray=gray) if load else capture


# --------------------------------------------------------------------------------------------------
# Pre-processing of a whole capture
# --------------------------------------------------------------------------------------------------


def prepare(
    capture: Capture,
    *,
    bin_factor: int = 1,
    ambient: bool = True,
    vignetting: Literal["cos4"] | np.ndarray | None = "cos4",
    gray: bool = False,
) -> Capture:
    """The usual pre-processing of a near-light capture, as the near_ps authors do it.

    Loads the images if needed, subtracts the ambient image (clipping at 0), divides by the
    vignetting map (``"cos4"`` from K, a flat-field map, or None), and bins by ``bin_factor``
    (images averaged, mask kept where its whole block is, K adjusted: fx' = fx/s,
    cx' = (cx + 1/2)/s - 1/2). Returns a loaded capture on the binned grid; ``capture.rig()``
    then gives the matching rig.
    """
    c = capture.load(gray=gray)
    images = np.asarray(c.images, dtype=np.float32)
    if ambient and c.ambient is not None:
        images = preprocess.subtract_ambient(images, np.asarray(c.ambient, dtype=np.float32))
    if isinstance(vignetting, str):
        if vignetting != "cos4":
            raise InputError(f"vignetting must be 'cos4', a map or None, got {vignetting!r}")
        if c.K is not None:
            images = preprocess.compensate_vignetting(images, preprocess.vignetting_cos4(images.shape[1:3], c.K))
    elif vignetting is not None:
        images = preprocess.compensate_vignetting(images, np.asarray(vignetting))
    K, mask, normals = c.K, c.mask, c.normals_gt
    if bin_factor != 1:
        images = preprocess.bin_images(images, bin_factor)
        K = None if K is None else preprocess.bin_intrinsics(K, bin_factor)
        mask = None if mask is None else preprocess.bin_mask(mask, bin_factor)
        normals = None
    return dataclasses.replace(
        c,
        images=np.ascontiguousarray(images, dtype=np.float32),
        ambient=None,
        K=K,
        mask=mask,
        normals_gt=normals,
        pixel_size=c.pixel_size * bin_factor,
    )
