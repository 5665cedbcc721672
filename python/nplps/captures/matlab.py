"""MATLAB files: reading variables (scipy) and camera matrices in MATLAB conventions."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..errors import RigError
from ..io import PathLike


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

    Raises
    ------
    RigError
        Not a (3, 3) finite matrix of that form, or non-positive focal lengths.
    """
    K = np.array(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise RigError(f"K must be a finite (3, 3) matrix, got {np.shape(K)}")
    last = np.array([0.0, 0.0, 1.0])
    if not np.allclose(K[2], last):
        if np.allclose(K[:, 2], last) and np.any(K[2, :2] != 0):
            K = K.T.copy()
        else:
            raise RigError(f"K is not a pinhole matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]]: {K.tolist()}")
    K[2] = last
    if K[1, 0] != 0:
        raise RigError(f"K[1, 0] must be 0, got {K[1, 0]}")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise RigError(f"K has non-positive focal lengths fx={K[0, 0]}, fy={K[1, 1]}")
    if one_based:
        K[0, 2] -= 1.0
        K[1, 2] -= 1.0
    return K


def load_matlab_intrinsics(path: PathLike, variable: str = "K", one_based: bool = True) -> np.ndarray:
    """Read ``K`` from a MATLAB file and return it with :func:`standardize_K` applied.

    E.g. ``camera.mat`` of the near-light toolbox, or ``calib.mat`` of Quéau's robust_ps
    DiLiGenT calibration. Returns a float64 (3, 3) matrix, 0-based pixel centres.
    """
    path = Path(path)
    return standardize_K(_mat_var(_loadmat(path), variable, path), one_based=one_based)
