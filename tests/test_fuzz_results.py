"""Fuzzing of ``nplps report`` and ``nplps view`` over damaged result folders (issue 18).

A small real result (a 12 x 12 sphere, ``depth="auto"``, with the input thumbnails, the options
and a held-out table) is damaged at random by hypothesis: files truncated at random offsets,
random bytes written or appended, files deleted, swapped or copied over each other, fields of
``summary.json`` and ``held_out.json`` given values of other types, ``.npy`` headers rewritten
(other shapes, huge ones, other dtypes, Fortran order), PLY header lines edited (counts such as
1e30, other property types, lines left out) and face indices changed, CSV columns dropped or
fields made text, PNG maps replaced by pictures of another size or their IHDR sizes changed.
Then both commands run in-process (``nplps.cli.main``) and must:

- return 0, or 1 / 2 with exactly one line on stderr, ``nplps: error: ...``, naming a file of the
  folder (or the folder); no exception escapes ``main`` and nothing on stderr is a traceback or
  a numpy warning;
- allocate nothing huge: each run is under an address-space limit (``RLIMIT_AS``) of the
  process's current size plus 2 GiB, so a ``.npy`` header claiming 100000 x 100000 floats would
  be a ``MemoryError`` here, and the peak resident size must not grow by more than 1 GiB;
- finish within 30 seconds.

An undamaged copy must give status 0 (so the test can tell a working reader from one that refuses
everything).

CI runs ``NPLPS_FUZZ_EXAMPLES`` examples (default 100); ``NPLPS_FUZZ_SECONDS=600`` runs batches of
examples for ten minutes and prints the count.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import struct
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import nplps
from nplps.cli import main

resource = pytest.importorskip("resource")

EXAMPLES = int(os.environ.get("NPLPS_FUZZ_EXAMPLES", "100"))
SECONDS = float(os.environ.get("NPLPS_FUZZ_SECONDS", "0"))
TIME_LIMIT = 30.0
EXTRA_ADDRESS_SPACE = 2 << 30
RSS_GROWTH = 1 << 30

#: The files report and view read (the others are left alone more often).
READ = [
    "summary.json",
    "depth.npy",
    "normals.npy",
    "residual.npy",
    "lights_used.npy",
    "mask.png",
    "normals.png",
    "albedo.png",
    "inputs.png",
    "history.csv",
    "distance_curve.csv",
    "held_out.json",
    "rig.json",
    "mesh.ply",
]
NPY = [n for n in READ if n.endswith(".npy")]
PNG = [n for n in READ if n.endswith(".png")]
CSV = ["history.csv", "distance_curve.csv"]
DESCRS = ["<f8", "<f4", ">f8", "<f2", "<u2", "<i8", "|u1", "|b1", "<c16", "<U4", "|V8", "O", "<M8[s]"]

COUNTS: dict[str, int] = {"examples": 0, "refused": 0, "accepted": 0}
FINDINGS: list[str] = []


# --------------------------------------------------------------------------------------------------
# The undamaged result
# --------------------------------------------------------------------------------------------------

_BASE: dict[str, Path] = {}


def _base() -> Path:
    if "dir" not in _BASE:
        scene = nplps.make_scene("sphere", n=12, seed=0)
        result = nplps.reconstruct(scene.images, scene.rig, depth="auto", mask=scene.mask)
        root = Path(tempfile.mkdtemp(prefix="nplps-fuzz-base-"))
        result.save(root, overwrite=True, inputs=scene.images, options={"capture": "sphere", "depth": "auto"})
        held = {
            "lights": [0, 5],
            "near": [[0.01, 0.02, 1.0], [0.03, None, 0.9]],
            "parallel": [[0.05, 0.06], [0.07, 0.08]],
            "reading": "near-light is better",
        }
        (root / "held_out.json").write_text(json.dumps(held))
        _BASE["dir"] = root
    return _BASE["dir"]


# --------------------------------------------------------------------------------------------------
# Damage
# --------------------------------------------------------------------------------------------------

json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**70), 2**70)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=12),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=10,
)
sizes = st.one_of(st.integers(0, 40), st.integers(0, 2**40), st.sampled_from([1, 12, 13, 100000, 10**30]))


def _files(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir())


def _pick(data: st.DataObject, d: Path, names: list[str] | None = None) -> Path | None:
    present = [n for n in (names or READ) if (d / n).is_file()]
    if not present:
        return None
    return d / data.draw(st.sampled_from(present))


def damage_truncate(data: st.DataObject, d: Path) -> str:
    p = _pick(data, d)
    if p is None:
        return "nothing to truncate"
    size = p.stat().st_size
    cut = data.draw(st.integers(0, max(size - 1, 0)))
    os.truncate(p, cut)
    return f"truncate {p.name} to {cut}"


def damage_bytes(data: st.DataObject, d: Path) -> str:
    p = _pick(data, d)
    if p is None:
        return "nothing to overwrite"
    raw = bytearray(p.read_bytes())
    at = data.draw(st.integers(0, max(len(raw) - 1, 0)))
    new = data.draw(st.binary(min_size=1, max_size=16))
    raw[at : at + len(new)] = new
    p.write_bytes(bytes(raw))
    return f"bytes {new!r} at {at} of {p.name}"


def damage_append(data: st.DataObject, d: Path) -> str:
    p = _pick(data, d)
    if p is None:
        return "nothing to append to"
    with open(p, "ab") as f:
        f.write(data.draw(st.binary(min_size=1, max_size=64)))
    return f"append to {p.name}"


def damage_replace(data: st.DataObject, d: Path) -> str:
    p = _pick(data, d)
    if p is None:
        return "nothing to replace"
    p.write_bytes(data.draw(st.binary(max_size=200)))
    return f"random contents in {p.name}"


def damage_delete(data: st.DataObject, d: Path) -> str:
    p = _pick(data, d)
    if p is None:
        return "nothing to delete"
    p.unlink()
    kind = data.draw(st.sampled_from(["delete", "delete", "directory", "fifo", "device link", "dangling link"]))
    if kind == "directory":
        p.mkdir()
    elif kind == "fifo":  # a reader that opens it blocking would hang (the time limit catches it)
        os.mkfifo(p)
    elif kind == "device link":
        p.symlink_to("/dev/zero")
    elif kind == "dangling link":
        p.symlink_to(d / "no such file")
    return f"{p.name}: {kind}"


def damage_swap(data: st.DataObject, d: Path) -> str:
    a, b = _pick(data, d), _pick(data, d)
    if a is None or b is None or a == b:
        return "nothing to swap"
    if data.draw(st.booleans()):
        shutil.copyfile(a, b)
        return f"copy {a.name} over {b.name}"
    ra, rb = a.read_bytes(), b.read_bytes()
    a.write_bytes(rb)
    b.write_bytes(ra)
    return f"swap {a.name} and {b.name}"


def damage_summary(data: st.DataObject, d: Path) -> str:
    name = data.draw(st.sampled_from(["summary.json", "summary.json", "held_out.json"]))
    p = d / name
    if not p.is_file():
        return f"no {name}"
    try:
        doc = json.loads(p.read_text())
    except ValueError:
        return f"{name} unreadable already"
    if not isinstance(doc, dict) or data.draw(st.integers(0, 9)) == 0:
        doc = data.draw(json_values)
        what = "whole document"
    else:
        keys = [*sorted(doc), "shape", "timings", "options", "estimated_distance", "lights", "near", "parallel"]
        key = data.draw(st.sampled_from(keys))
        special = {
            "shape": st.sampled_from([[12, 12], [13, 13], [12], [0, 12], [2**40, 2], [10**5, 10**5], [12.0, 12], "12"]),
            "estimated_distance": st.sampled_from([[], [None], ["a"], [-1.0], [1e308, 2.0], [180.0, 190.0, 200.0]]),
        }
        value = data.draw(special.get(key, json_values) | json_values)
        if data.draw(st.booleans()) and isinstance(doc.get(key), dict) and doc[key]:
            inner = data.draw(st.sampled_from(sorted(doc[key])))
            doc[key][inner] = value
            what = f"{key}.{inner}"
        elif data.draw(st.integers(0, 5)) == 0:
            doc.pop(key, None)
            what = f"drop {key}"
        else:
            doc[key] = value
            what = key
    p.write_text(json.dumps(doc))
    return f"{name}: {what}"


def damage_npy_header(data: st.DataObject, d: Path) -> str:
    p = _pick(data, d, NPY)
    if p is None:
        return "no .npy"
    raw = p.read_bytes()
    try:
        with open(p, "rb") as f:
            version = np.lib.format.read_magic(f)
            read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, fortran, dtype = read(f)
            body = raw[f.tell() :]
    except Exception:
        return f"{p.name} header unreadable already"
    new_shape = data.draw(
        st.one_of(
            st.just(tuple(shape)),
            st.just(tuple(shape)[::-1]),
            st.lists(sizes, max_size=4).map(tuple),
            st.sampled_from([(100000, 100000), (13, 13), (12, 12, 3), (12, 12), (0,), ()]),
        )
    )
    descr = data.draw(st.sampled_from([dtype.str, *DESCRS]))
    header: dict[str, Any] = {
        "descr": descr,
        "fortran_order": data.draw(st.booleans()) if data.draw(st.integers(0, 3)) == 0 else fortran,
        "shape": new_shape,
    }
    out = io.BytesIO()
    try:
        if data.draw(st.booleans()):
            np.lib.format.write_array_header_1_0(out, header)
        else:
            np.lib.format.write_array_header_2_0(out, header)
    except Exception:
        return "header not writable"
    body = body if data.draw(st.integers(0, 3)) else b""
    p.write_bytes(out.getvalue() + body)
    return f"{p.name}: header {header}, {len(body)} data bytes"


def damage_ply(data: st.DataObject, d: Path) -> str:
    p = d / "mesh.ply"
    if not p.is_file():
        return "no mesh.ply"
    raw = p.read_bytes()
    end = raw.find(b"end_header\n")
    if end < 0:
        return "mesh.ply header gone already"
    lines = raw[:end].decode("latin-1").split("\n")
    body = raw[end + len(b"end_header\n") :]
    choice = data.draw(st.integers(0, 4))
    if choice == 0:  # element counts
        index = [i for i, line in enumerate(lines) if line.startswith("element ")]
        if not index:
            return "no element line"
        i = data.draw(st.sampled_from(index))
        count = data.draw(st.one_of(sizes.map(str), st.sampled_from(["1e30", "-1", "abc", "", "193 2", "0x10", "+5"])))
        words = lines[i].split(" ")
        lines[i] = " ".join([*words[:2], count])
        what = lines[i]
    elif choice == 1:  # property types
        index = [i for i, line in enumerate(lines) if line.startswith("property ")]
        i = data.draw(st.sampled_from(index))
        kind = data.draw(st.sampled_from(["float", "double", "uchar", "int", "short", "list uchar int", "bogus"]))
        lines[i] = f"property {kind} {lines[i].split()[-1]}"
        what = lines[i]
    elif choice == 2:  # a header line left out or doubled
        i = data.draw(st.integers(0, len(lines) - 1))
        what = f"line {lines[i]!r} " + ("doubled" if data.draw(st.booleans()) else "dropped")
        lines[i : i + 1] = [lines[i], lines[i]] if what.endswith("doubled") else []
    elif choice == 3:  # a face index
        faces = [line for line in lines if line.startswith("element face ")]
        if not faces or len(body) < 13:
            return "no faces"
        words = faces[0].split()
        if len(words) != 3 or not words[2].isdigit():
            return "face count damaged already"  # an earlier step of this example edited it
        n_faces = int(words[2])
        face = data.draw(st.integers(0, max(n_faces - 1, 0)))
        corner = data.draw(st.integers(0, 2))
        at = len(body) - 13 * (n_faces - face) + 1 + 4 * corner
        value = data.draw(st.integers(-(2**31), 2**31 - 1) | st.integers(-2, 400))
        body = body[:at] + struct.pack("<i", value) + body[at + 4 :]
        what = f"face {face} corner {corner} = {value}"
    else:  # a vertex coordinate
        if len(body) < 4:
            return "no vertices"
        at = data.draw(st.integers(0, 20)) * 4
        value = data.draw(st.sampled_from([np.nan, np.inf, -np.inf, 3.4e38, 0.0, 1e30]))
        body = body[:at] + struct.pack("<f", value) + body[at + 4 :]
        what = f"float {value} at {at}"
    p.write_bytes(("\n".join(lines) + "\n").encode("latin-1") + b"end_header\n" + body)
    return f"mesh.ply: {what}"


def damage_csv(data: st.DataObject, d: Path) -> str:
    p = _pick(data, d, CSV)
    if p is None:
        return "no csv"
    rows = [line.split(",") for line in p.read_text(errors="replace").splitlines()]
    if not rows:
        return "empty csv"
    choice = data.draw(st.integers(0, 3))
    if choice == 0:
        col = data.draw(st.integers(0, 6))
        rows = [r[:col] + r[col + 1 :] for r in rows]
        what = f"drop column {col}"
    elif choice == 1:
        r = data.draw(st.integers(0, len(rows) - 1))
        c = data.draw(st.integers(0, max(len(rows[r]) - 1, 0)))
        value = data.draw(st.sampled_from(["x", "", "nan", "inf", "-1", "1e308", "1e400", "2.5", "99999999999"]))
        rows[r][c : c + 1] = [value]
        what = f"row {r} column {c} = {value!r}"
    elif choice == 2:
        rows.append(data.draw(st.lists(st.sampled_from(["0", "1", "x", "1.5"]), max_size=9)))
        what = "odd row"
    else:
        rows = rows[:1] + rows[1:] * data.draw(st.integers(0, 3))
        what = "rows repeated"
    p.write_text("\n".join(",".join(r) for r in rows) + "\n")
    return f"{p.name}: {what}"


def damage_png(data: st.DataObject, d: Path) -> str:
    p = _pick(data, d, PNG)
    if p is None:
        return "no png"
    if data.draw(st.booleans()):
        h, w = data.draw(st.integers(1, 30)), data.draw(st.integers(1, 30))
        channels = data.draw(st.sampled_from([1, 3]))
        dtype = data.draw(st.sampled_from([np.uint8, np.uint16]))
        pixels = np.full((h, w) if channels == 1 else (h, w, channels), 200, dtype=dtype)
        nplps.export.write_png(p, pixels)
        return f"{p.name}: a {w} x {h} x {channels} {np.dtype(dtype)} picture"
    raw = bytearray(p.read_bytes())
    if len(raw) < 24:
        return "png too short"
    field = data.draw(st.sampled_from([16, 20]))
    value = data.draw(st.integers(0, 2**32 - 1) | st.integers(0, 40))
    raw[field : field + 4] = struct.pack(">I", value)
    p.write_bytes(bytes(raw))
    return f"{p.name}: IHDR {'width' if field == 16 else 'height'} = {value}"


DAMAGES = [
    damage_truncate,
    damage_bytes,
    damage_append,
    damage_replace,
    damage_delete,
    damage_swap,
    damage_summary,
    damage_summary,
    damage_npy_header,
    damage_npy_header,
    damage_ply,
    damage_ply,
    damage_csv,
    damage_png,
]


# --------------------------------------------------------------------------------------------------
# Running the commands
# --------------------------------------------------------------------------------------------------


def _address_space() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")


@contextlib.contextmanager
def memory_guard():
    """Limit the address space to the current size plus 2 GiB while the block runs (Linux)."""
    if not sys.platform.startswith("linux"):
        yield
        return
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    limit = _address_space() + EXTRA_ADDRESS_SPACE
    if hard != resource.RLIM_INFINITY:
        limit = min(limit, hard)
    if soft != resource.RLIM_INFINITY:
        limit = min(limit, soft)
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


def run(argv: list[str]) -> tuple[int, str, str, float]:
    """Run ``nplps ARGV`` in-process; return status, stdout, stderr and seconds."""
    out, err = io.StringIO(), io.StringIO()
    start = time.perf_counter()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    with memory_guard(), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main(argv)
    grown = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 - rss
    assert grown < RSS_GROWTH, f"nplps {argv[0]}: peak resident size grew by {grown / 2**20:.0f} MiB"
    return status, out.getvalue(), err.getvalue(), time.perf_counter() - start


def check(argv: list[str], d: Path, damage: list[str]) -> int:
    status, _, err, seconds = run(argv)
    where = f"nplps {' '.join(argv[:1])} after {damage}"
    assert seconds < TIME_LIMIT, f"{where}: took {seconds:.1f} s"
    assert "Traceback" not in err, f"{where}: traceback on stderr:\n{err}"
    assert "encountered in" not in err, f"{where}: a numpy warning:\n{err}"
    lines = [line for line in err.splitlines() if not line.startswith("nplps: warning: ")]
    assert status in (0, 1, 2), f"{where}: exit status {status}\n{err}"
    if status == 0:
        assert lines == [], f"{where}: status 0 with stderr:\n{err}"
    else:
        assert len(lines) == 1 and lines[0].startswith("nplps: error: "), f"{where}: not one error line:\n{err}"
        assert os.fspath(d) in lines[0] or any(n in lines[0] for n in READ), f"{where}: names no file: {lines[0]}"
    return status


def one_example(data: st.DataObject) -> None:
    d = Path(tempfile.mkdtemp(prefix="nplps-fuzz-"))
    try:
        shutil.copytree(_base(), d, dirs_exist_ok=True)
        steps = data.draw(st.integers(0, 3))
        damage = [data.draw(st.sampled_from(DAMAGES))(data, d) for _ in range(steps)]
        statuses = [check(["report", os.fspath(d)], d, damage), check(["view", os.fspath(d), "--no-open"], d, damage)]
        if not damage:
            assert statuses == [0, 0], "the undamaged result must give status 0"
        COUNTS["examples"] += 1
        COUNTS["refused" if any(statuses) else "accepted"] += 1
    finally:
        shutil.rmtree(d, ignore_errors=True)


def _settings(examples: int) -> settings:
    return settings(
        max_examples=examples,
        deadline=None,
        database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
    )


def test_undamaged_result_reports_and_views(tmp_path: Path) -> None:
    shutil.copytree(_base(), tmp_path / "r")
    assert check(["report", os.fspath(tmp_path / "r")], tmp_path / "r", []) == 0
    assert check(["view", os.fspath(tmp_path / "r"), "--no-open"], tmp_path / "r", []) == 0


def test_fuzz_damaged_results() -> None:
    """Random damage to a result folder: report and view fail cleanly in one line, or succeed."""
    _base()
    batch = given(st.data())(_settings(EXAMPLES if not SECONDS else 200)(one_example))
    end = time.monotonic() + SECONDS
    batch()
    while time.monotonic() < end:
        batch()
    if SECONDS:
        print(f"\nfuzzed {COUNTS['examples']} damaged result folders in {SECONDS:.0f} s: {COUNTS}")
