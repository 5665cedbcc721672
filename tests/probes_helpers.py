"""Helpers of the area probe modules (``tests/probes_<area>.py``), added to the snippets' namespace.

:func:`helpers` is called by the prelude of ``tests/probes_cases.py`` with its namespace and
returns more names: a saved result folder to damage (:func:`result`), the command line in-process
(:func:`run`), a FIFO with a reader (:func:`fifo`), crafted ``.npy`` headers, and a synchronous
stand-in for ``dask.distributed`` (:func:`fake_dask`) so that ``nplps batch`` runs in the worker
without starting a cluster (the probes are about what nplps does with the results, not Dask).
"""

from __future__ import annotations

import contextlib
import importlib
import io
import json
import os
import shutil
import sys
import threading
import types
from pathlib import Path
from typing import Any


def helpers(ns: dict[str, Any]) -> dict[str, Any]:
    """Return the helpers' names for the prelude namespace ``ns`` (which has ``S``, ``rec``, ``_ctx``)."""
    nplps = ns["nplps"]
    ctx = ns["_ctx"]
    base = Path(ns["SC"]).parent
    cache: dict[str, Path] = {}
    made: dict[str, Any] = {}
    importlib.import_module("nplps.batch")  # nplps.batch in the snippets

    def tmp() -> Path:
        return Path(ctx["tmp"])

    def _reconstruction(kind: str) -> Any:
        if kind not in made:
            S = ns["S"]
            if kind == "plain":
                made[kind] = nplps.reconstruct(S.images, S.rig, mask=S.mask, depth=200.0)
            elif kind == "auto":
                made[kind] = nplps.reconstruct(
                    S.images, S.rig, mask=S.mask, depth="auto", refine_lights="intensity", iterations=5
                )
            elif kind == "pinhole":
                P = ns["PS"]
                made[kind] = nplps.reconstruct(P.images, P.rig, mask=P.mask, depth=200.0)
            else:
                raise ValueError(kind)
        return made[kind]

    def _save(kind: str, where: Path) -> Path:
        r = _reconstruction(kind)
        if kind == "plain":
            r.save(where, report=True, inputs=ns["S"].images)
        elif kind == "auto":
            r.save(where, formats=("stl", "glb", "points", "normals_tiff"))
        else:
            r.save(where)
        return where

    def result(name: str = "r", kind: str = "plain", fresh: bool = False) -> Path:
        """A saved result in the case's directory: "plain" (with report.html and inputs.png),
        "auto" (distance curve, refined rig, every extra format) or "pinhole".

        A copy of one saved once per worker, unless ``fresh``: then saved there (its manifest
        names that folder, as nplps's own; a copy's names the folder it was copied from)."""
        if fresh:
            return _save(kind, tmp() / name)
        if kind not in cache:
            cache[kind] = _save(kind, base / f"result-{kind}")
        return Path(shutil.copytree(cache[kind], tmp() / name, symlinks=True))

    def run(*argv: Any) -> tuple[int, str, str]:
        """``nplps ARGV`` in-process: (exit status, stdout, stderr); exceptions escape."""
        from nplps.cli import main

        out, err = io.StringIO(), io.StringIO()
        cwd = os.getcwd()
        os.chdir(tmp())
        try:
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                try:
                    code = main([str(a) for a in argv])
                except SystemExit as e:
                    code = e.code if isinstance(e.code, int) else 1
        finally:
            os.chdir(cwd)
        return code, out.getvalue(), err.getvalue()

    def files(directory: Any) -> set[str]:
        d = Path(directory)
        return {p.relative_to(d).as_posix() for p in d.rglob("*") if p.is_file() or p.is_symlink()}

    def damaged_line(err: str, *words: str) -> bool:
        """stderr is one line "nplps: error: damaged result file ..." holding every word."""
        lines = err.strip().splitlines()
        assert len(lines) == 1, f"{len(lines)} stderr lines: {lines[:4]}"
        assert lines[0].startswith("nplps: error: damaged result file"), lines[0]
        for w in words:
            assert w in lines[0], f"{w!r} not in {lines[0]!r}"
        return True

    def one_line(err: str, *words: str) -> bool:
        lines = err.strip().splitlines()
        assert len(lines) == 1, f"{len(lines)} stderr lines: {lines[:4]}"
        for w in words:
            assert w.lower() in lines[0].lower(), f"{w!r} not in {lines[0]!r}"
        return True

    def npy_claiming(path: Any, shape: tuple[int, ...], dtype: str = "<f8", data: bytes = b"\0" * 64) -> Path:
        """A .npy file whose header claims ``shape`` of ``dtype``, followed by ``data`` only."""
        p = Path(path)
        p = p if p.is_absolute() else tmp() / p
        header = repr({"descr": dtype, "fortran_order": False, "shape": tuple(shape)}).encode("latin1")
        header += b" " * (63 - (len(header) + 10) % 64) + b"\n"
        p.write_bytes(b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header + data)
        return p

    def edit_json(path: Any, **fields: Any) -> Path:
        p = Path(path)
        doc = json.loads(p.read_text(encoding="utf-8"))
        doc.update(fields)
        p.write_text(json.dumps(doc), encoding="utf-8")
        return p

    def manifest(directory: Any) -> dict[str, Any]:
        return json.loads((Path(directory) / "nplps-manifest.json").read_text(encoding="utf-8"))

    def fifo(name: str) -> tuple[Path, list[bytes]]:
        """A FIFO in the case's directory and a reader thread; what it read lands in the list."""
        p = tmp() / name
        os.mkfifo(p)
        got: list[bytes] = []

        def read() -> None:
            with open(p, "rb") as f:
                got.append(f.read())

        threading.Thread(target=read, daemon=True).start()
        return p, got

    def fifo_done(p: Path, got: list[bytes], timeout: float = 5.0) -> bytes:
        """Wait for the reader of ``fifo`` (unblocking it if nothing was written) and return what it read."""
        import stat
        import time

        end = time.monotonic() + timeout
        while not got and time.monotonic() < end:
            try:  # a writer that opens and closes ends a reader still waiting for one
                fd = os.open(p, os.O_WRONLY | os.O_NONBLOCK)
                os.close(fd)
            except OSError:
                pass
            time.sleep(0.05)
        assert stat.S_ISFIFO(os.lstat(p).st_mode), f"{p.name} is no longer a FIFO"
        return got[0] if got else b""

    def fake_dask() -> None:
        """Install a synchronous stand-in for ``distributed`` (tasks run in this process)."""

        class Future:
            def __init__(self, fn: Any, args: tuple, kwargs: dict) -> None:
                self._value, self._error = None, None
                try:
                    self._value = fn(*args, **kwargs)
                except Exception as e:
                    self._error = e

            def result(self) -> Any:
                if self._error is not None:
                    raise self._error
                return self._value

        class Client:
            def __init__(self, *args: Any, **kwargs: Any) -> None:
                address = args[0] if args else None
                if isinstance(address, str) and "://" not in address:
                    raise ValueError(f"invalid scheduler address {address!r}")

            def __enter__(self) -> Client:
                return self

            def __exit__(self, *exc: Any) -> bool:
                return False

            def submit(self, fn: Any, *args: Any, key: Any = None, pure: Any = None, **kwargs: Any) -> Future:
                return Future(fn, args, kwargs)

            def cancel(self, futures: Any) -> None:
                pass

        class LocalCluster:
            def __init__(self, *args: Any, **kwargs: Any) -> None:
                pass

            def close(self) -> None:
                pass

        m = types.ModuleType("distributed")
        m.Client, m.LocalCluster, m.as_completed = Client, LocalCluster, lambda fs: list(fs)  # type: ignore[attr-defined]
        m.__nplps_fake__ = True  # type: ignore[attr-defined]
        sys.modules["distributed"] = m

    def captures(n: int = 3, root: str = "caps", names: Any = None, scene: Any = None) -> Path:
        """``n`` capture folders (copies of the prelude scene's images and mask) under ``root``."""
        src = Path(ns["SC"] if scene is None else scene)
        r = tmp() / root
        r.mkdir(exist_ok=True)
        for name in names or [f"c{i}" for i in range(n)]:
            d = r / name
            d.mkdir(parents=True)
            for f in src.iterdir():
                if f.suffix == ".png":
                    shutil.copy(f, d / f.name)
        return r

    def batch(pattern: Any, out: Any = "out", **kw: Any) -> list[Any]:
        """``nplps.batch.run`` on the synchronous stand-in, depth 200 and the prelude's rig by default."""
        fake_dask()
        kw.setdefault("depth", 200.0)
        kw.setdefault("report", False)
        rig = kw.pop("rig", ns["S"].rig)
        o = Path(out)
        return nplps.batch.run(str(pattern), rig, o if o.is_absolute() else tmp() / o, **kw)

    return {
        "result": result,
        "run": run,
        "files": files,
        "damaged_line": damaged_line,
        "one_line": one_line,
        "npy_claiming": npy_claiming,
        "edit_json": edit_json,
        "manifest": manifest,
        "fifo": fifo,
        "fifo_done": fifo_done,
        "fake_dask": fake_dask,
        "captures": captures,
        "batch": batch,
        "shutil": shutil,
    }
