"""The MAT-file reader (``nplps.captures.matlab.read_mat``) against scipy and by hand (issue 22, item 7)."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from nplps.captures.matlab import Unsupported, _mat_var, read_mat
from nplps.errors import RigError

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def _header(order: str, version: int = 0x0100, text: bytes = b"MATLAB 5.0 MAT-file, written by the test") -> bytes:
    mark = b"IM" if order == "<" else b"MI"
    return text.ljust(116, b" ") + b"\0" * 8 + struct.pack(order + "H", version) + mark


def _element(order: str, kind: int, payload: bytes) -> bytes:
    pad = (-len(payload)) % 8
    return struct.pack(order + "II", kind, len(payload)) + payload + b"\0" * pad


def _double_matrix(order: str, name: str, values: np.ndarray) -> bytes:
    """One uncompressed miMATRIX of class double, written with full (not small) tags."""
    flags = _element(order, 6, struct.pack(order + "II", 6, 0))
    dims = _element(order, 5, np.asarray(values.shape, dtype=order + "i4").tobytes())
    label = _element(order, 1, name.encode())
    data = _element(order, 9, np.asarray(values, dtype=order + "f8").tobytes(order="F"))
    return _element(order, 14, flags + dims + label + data)


@pytest.mark.parametrize("order", ["<", ">"])
def test_hand_written_files_of_both_byte_orders(tmp_path: Path, order: str) -> None:
    values = np.arange(24, dtype=np.float64).reshape(2, 3, 4) * 0.5 - 3
    path = tmp_path / "m.mat"
    path.write_bytes(_header(order) + _double_matrix(order, "K", values) + _double_matrix(order, "x", values[:, :, 0]))
    data = read_mat(path)
    assert sorted(data) == ["K", "x"]
    assert data["K"].dtype == np.float64 and np.array_equal(data["K"], values)
    assert np.array_equal(data["x"], values[:, :, 0])


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("compress", [False, True])
def test_equals_scipy_on_files_scipy_writes(tmp_path: Path, seed: int, compress: bool) -> None:
    scipy_io = pytest.importorskip("scipy.io")
    rng = np.random.default_rng(seed)
    shape = tuple(int(s) for s in rng.integers(1, 6, size=int(rng.integers(1, 4))))
    values = {
        "S": rng.normal(size=shape) * 100,
        "single": rng.normal(size=(3, 4)).astype(np.float32),
        "mu": rng.integers(0, 255, size=(8, 1)).astype(np.uint8),
        "i16": rng.integers(-30000, 30000, size=(5, 2)).astype(np.int16),
        "u32": rng.integers(0, 2**32 - 1, size=(2, 2), dtype=np.uint64).astype(np.uint32),
        "i64": np.int64(-(2**40)),
        "flag": rng.integers(0, 2, size=(3,)).astype(bool),
        "empty": np.zeros((0, 3)),
        "z": rng.normal(size=(2, 2)) + 1j * rng.normal(size=(2, 2)),
        "label": "near light",
        "cell": np.array([1, "x"], dtype=object),
        "record": {"a": 1.0},
    }
    path = tmp_path / "v.mat"
    scipy_io.savemat(path, values, do_compression=compress)
    ours = read_mat(path)
    theirs = scipy_io.loadmat(path, mat_dtype=True)
    for name in ("S", "single", "mu", "i16", "u32", "i64", "flag", "empty"):
        assert ours[name].dtype == theirs[name].dtype, name
        assert ours[name].shape == theirs[name].shape, name
        assert np.array_equal(ours[name], theirs[name]), name
    assert np.array_equal(ours["z"], scipy_io.loadmat(path)["z"])
    assert ours["label"] == "near light"
    assert ours["cell"] == Unsupported("cell array") and ours["record"] == Unsupported("struct")
    with pytest.raises(RigError, match="'record' is a MATLAB struct"):
        _mat_var(ours, "record", path)


def test_equals_scipy_on_the_shared_captures() -> None:
    scipy_io = pytest.importorskip("scipy.io")
    files = sorted(SHARED.glob("**/*.mat"))
    if not files:
        pytest.skip("no ../shared/data MAT-files here")
    for path in files:
        ours = read_mat(path)
        theirs = {k: v for k, v in scipy_io.loadmat(path, mat_dtype=True).items() if not k.startswith("__")}
        assert sorted(ours) == sorted(theirs), path
        for name, value in theirs.items():
            assert ours[name].dtype == value.dtype and np.array_equal(ours[name], value), (path, name)


def test_refusals_name_the_file_and_the_way_out(tmp_path: Path) -> None:
    missing = tmp_path / "none.mat"
    with pytest.raises(RigError, match="not found"):
        read_mat(missing)
    v73 = tmp_path / "v73.mat"
    v73.write_bytes(_header("<", version=0x0200, text=b"MATLAB 7.3 MAT-file, HDF5") + b"\0" * 512)
    with pytest.raises(RigError, match=r"v7\.3.*-v7"):
        read_mat(v73)
    v4 = tmp_path / "v4.mat"
    v4.write_bytes(b"\0" * 200)
    with pytest.raises(RigError, match="version 5 format"):
        read_mat(v4)
    cut = tmp_path / "cut.mat"
    cut.write_bytes((_header("<") + _double_matrix("<", "K", np.eye(3)))[:-20])
    with pytest.raises(RigError, match=r"cut\.mat.*runs past the end"):
        read_mat(cut)
    bad_zip = tmp_path / "zip.mat"
    bad_zip.write_bytes(_header("<") + struct.pack("<II", 15, 8) + b"notzlib!")
    with pytest.raises(RigError, match="compressed element"):
        read_mat(bad_zip)
