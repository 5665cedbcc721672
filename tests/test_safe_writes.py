"""Safe writes (issue 9): files are written under a temporary name and renamed when complete, so a
file size limit, an error or a signal during ``save`` never leaves a truncated file under its
final name; output directories are refused when not empty unless overwriting, and overwriting
removes only the stale files of the earlier nplps result (its ``nplps-manifest.json``)."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import nplps
from nplps import cli, export
from nplps._atomic import TEMPORARY_NAME, atomic_write, is_write_error
from nplps._outdir import MANIFEST, is_complete, load_manifest, read_manifest
from nplps.errors import OutputExistsError

POSIX_ONLY = pytest.mark.skipif(sys.platform == "win32", reason="POSIX resource limits and signals")


@pytest.fixture(scope="module")
def scene() -> nplps.Scene:
    return nplps.make_scene("bumps", n=32)


@pytest.fixture(scope="module")
def result(scene: nplps.Scene) -> nplps.Reconstruction:
    return nplps.reconstruct(scene.images, scene.rig, mask=scene.mask, depth=scene.mean_depth)


@pytest.fixture(scope="module")
def auto_result(scene: nplps.Scene) -> nplps.Reconstruction:
    """A result with a distance search (distance_curve.csv/.svg) and refined lights (rig_refined.json)."""
    return nplps.reconstruct(
        scene.images, scene.rig, mask=scene.mask, depth="auto", refine_lights="intensity", iterations=5
    )


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory: pytest.TempPathFactory, scene: nplps.Scene) -> Path:
    out = tmp_path_factory.mktemp("safe") / "scene"
    scene.save(out)
    return out


def files_under(directory: Path) -> set[str]:
    """Every file below ``directory``, as "/"-separated relative paths."""
    return {p.relative_to(directory).as_posix() for p in directory.rglob("*") if p.is_file()}


def temporaries(directory: Path) -> list[Path]:
    return [p for p in directory.rglob(".*") if TEMPORARY_NAME.match(p.name)]


def reconstruct_argv(scene_dir: Path, out: Path, *extra: object) -> list[str]:
    return [
        "reconstruct", str(scene_dir), "--rig", str(scene_dir / "rig.json"), "--mask", str(scene_dir / "mask.png"),
        "--out", str(out), "-q", *map(str, extra),
    ]  # fmt: skip


def run(capsys: pytest.CaptureFixture[str], argv: list[str]) -> tuple[int, str, str]:
    rc = cli.main(argv)
    captured = capsys.readouterr()
    return rc, captured.out, captured.err


# --------------------------------------------------------------------------------------------------
# (1) A file size limit (RLIMIT_FSIZE) while saving
# --------------------------------------------------------------------------------------------------

# Saves an old result into OLD (and the same again into SAME, to compare with), the new result
# (OpenGL frame: other mesh bytes) into NEW, then sets a file size limit between the sizes of the
# PLY and the OBJ file and saves the new result over OLD: mesh.ply fits, mesh.obj does not.
LIMIT_SCRIPT = textwrap.dedent(
    """
    import json, os, resource, signal, sys
    import nplps
    from nplps import cli

    mode, root = sys.argv[1], sys.argv[2]
    s = nplps.make_scene("bumps", n=32)
    scene = os.path.join(root, "scene")
    s.save(scene)
    r = nplps.reconstruct(s.images, s.rig, mask=s.mask, depth=s.mean_depth)

    def save(out, opengl, overwrite=False):
        if mode == "api":
            r.save(out, opengl=opengl, overwrite=overwrite)
            return 0
        argv = ["reconstruct", scene, "--rig", os.path.join(scene, "rig.json"), "--mask",
                os.path.join(scene, "mask.png"), "--depth", repr(s.mean_depth), "--out", out, "-q"]
        return cli.main(argv + ["--opengl"] * opengl + ["--overwrite"] * overwrite)

    old, same, new = (os.path.join(root, name) for name in ("old", "same", "new"))
    assert save(old, False) == save(same, False) == save(new, True) == 0
    sizes = [os.path.getsize(os.path.join(new, name)) for name in ("mesh.ply", "mesh.obj")]
    assert sizes[0] < sizes[1], sizes
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # write() then fails with EFBIG
    resource.setrlimit(resource.RLIMIT_FSIZE, (sum(sizes) // 2, resource.RLIM_INFINITY))
    try:
        status = save(old, True, overwrite=True)
    except OSError as e:
        print(json.dumps({"errno": e.errno, "filename": e.filename, "message": str(e)}))
        raise SystemExit(0)
    raise SystemExit(status or "saved despite the limit")
    """
)


def _check_old_or_new(root: Path) -> None:
    """Every file in old/ is the complete old version (as in same/) or the complete new one (as
    in new/); nothing else is there, no temporary file either."""
    old, same, new = root / "old", root / "same", root / "new"
    assert files_under(old) == files_under(same), files_under(old) ^ files_under(same)
    assert not temporaries(old)
    replaced = []
    for name in sorted(files_under(old) - {MANIFEST}):
        data, before, after = (_content(d / name) for d in (old, same, new))
        assert data in (before, after), f"{name} is neither old nor new"
        if data != before:
            replaced.append(name)
    assert replaced == ["mesh.ply"]  # written before the limit was hit; mesh.obj kept its old version
    assert read_manifest(old) == read_manifest(same)


def _content(path: Path) -> object:
    """The bytes of a file, without what differs by run.

    That is: summary.json without the timings and the options (they name the output directory),
    history.csv without its elapsed seconds, report.html (it quotes both) as present only.
    """
    if path.name == "summary.json":
        return {k: v for k, v in json.loads(path.read_text()).items() if k not in ("timings", "options")}
    if path.name == "history.csv":
        return [line.split(",")[:4] + line.split(",")[5:] for line in path.read_text().splitlines()]
    if path.name == "report.html":
        return "report"
    return path.read_bytes()


@POSIX_ONLY
def test_file_size_limit_in_save_leaves_no_truncated_file(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-c", LIMIT_SCRIPT, "api", str(tmp_path)], capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr
    error = json.loads(proc.stdout.strip().splitlines()[-1])
    assert error["errno"] == 27  # EFBIG
    assert error["filename"] == str(tmp_path / "old" / "mesh.obj")
    assert "mesh.obj" in error["message"]
    _check_old_or_new(tmp_path)


@POSIX_ONLY
def test_file_size_limit_in_cli_names_the_file(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-c", LIMIT_SCRIPT, "cli", str(tmp_path)], capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 1, proc.stderr
    assert f"nplps: error: cannot write '{tmp_path / 'old' / 'mesh.obj'}': File too large" in proc.stderr
    assert "Traceback" not in proc.stderr
    _check_old_or_new(tmp_path)


# --------------------------------------------------------------------------------------------------
# (2) An exception or a signal while a file is written
# --------------------------------------------------------------------------------------------------


def test_exception_in_a_writer_leaves_no_file(tmp_path: Path, result: nplps.Reconstruction, monkeypatch) -> None:
    def broken(faces: np.ndarray) -> np.ndarray:  # the PLY face records: after header and vertices
        raise KeyboardInterrupt

    monkeypatch.setattr(export, "_ply_face_records", broken)
    with pytest.raises(KeyboardInterrupt):
        result.save(tmp_path / "r")
    assert not (tmp_path / "r" / "mesh.ply").exists()
    assert not temporaries(tmp_path)
    assert files_under(tmp_path / "r") == set()  # mesh.ply is the first file: nothing else either


def test_exception_while_overwriting_keeps_the_old_files(
    tmp_path: Path, result: nplps.Reconstruction, monkeypatch
) -> None:
    out = tmp_path / "r"
    result.save(out)
    before = {name: (out / name).read_bytes() for name in files_under(out)}

    def broken(path: object, array: np.ndarray) -> None:  # normals.npy: after the meshes and images
        raise RuntimeError("writer failed")

    monkeypatch.setattr(export, "save_npy", broken)
    with pytest.raises(RuntimeError, match="writer failed"):
        result.save(out, opengl=True, overwrite=True)
    assert files_under(out) == set(before)
    assert not temporaries(out)
    changed = {name for name in before if (out / name).read_bytes() != before[name]}
    assert changed == {"mesh.ply", "mesh.obj", MANIFEST}  # written (complete) before the failure; the manifest
    assert set(read_manifest(out) or []) == set(before) - {MANIFEST}
    # Two results mixed: the folder says "in progress", never complete.
    manifest = load_manifest(out)
    assert manifest is not None and manifest.state == "in progress" and not is_complete(out)
    assert manifest.files["mesh.ply"] is not None  # finished before the failure: size and hash recorded


def test_atomic_write_keeps_the_old_file_and_umask_permissions(tmp_path: Path) -> None:
    path = tmp_path / "a.txt"
    path.write_text("old")
    with pytest.raises(ValueError):
        with atomic_write(path, "w", encoding="utf-8") as f:
            f.write("new, but not finished")
            raise ValueError
    assert path.read_text() == "old"
    with atomic_write(tmp_path / "b.bin") as f:
        f.write(b"new")
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "b.bin").stat().st_mode & 0o777 == 0o666 & ~umask
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.bin"]


def test_write_error_names_the_final_path(tmp_path: Path) -> None:
    (tmp_path / "depth.npy").mkdir()  # a directory in the way: the rename fails
    with pytest.raises(OSError) as info:
        export.save_depth_npy(tmp_path / "depth.npy", np.zeros((2, 2)))
    assert info.value.filename == str(tmp_path / "depth.npy")
    assert is_write_error(info.value)
    assert list(tmp_path.iterdir()) == [tmp_path / "depth.npy"]


# Runs `nplps reconstruct` with an OBJ writer that writes a little and then waits, so that a
# signal arrives in the middle of mesh.obj.
SIGNAL_SCRIPT = textwrap.dedent(
    """
    import sys, time
    from nplps import cli, export

    def slow(file, jobs):
        file.write(b"v 0 0 0\\n")
        file.flush()
        print("writing", flush=True)
        # A writer that keeps running Python code, as the real one does. Not one long sleep: a
        # signal arriving between the print and the sleep would set Python's flag but run its
        # handler only when the sleep ends (the sleep is not interrupted by a signal that came
        # before it), which made this test hang once in a while under load.
        for _ in range(2400):
            time.sleep(0.05)

    export._write_text = slow
    raise SystemExit(cli.main(sys.argv[1:]))
    """
)


@POSIX_ONLY
@pytest.mark.parametrize("signum, status", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_signal_during_save(tmp_path: Path, scene_dir: Path, scene: nplps.Scene, signum: int, status: int) -> None:
    out = tmp_path / "r"
    argv = reconstruct_argv(scene_dir, out, "--depth", repr(scene.mean_depth))
    proc = subprocess.Popen(
        [sys.executable, "-c", SIGNAL_SCRIPT, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line.strip() == "writing", (line, proc.stderr.read() if proc.stderr else "")
        proc.send_signal(signum)
        try:
            _, stderr = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, stderr = proc.communicate()
            pytest.fail(f"the process did not stop within 60 s of the signal; its stderr:\n{stderr}")
    finally:
        proc.kill()
    assert proc.returncode == status, stderr
    assert "Traceback" not in stderr
    assert files_under(out) == {"mesh.ply", MANIFEST}  # no mesh.obj, no temporary file
    export.read_ply(out / "mesh.ply")  # complete
    manifest = load_manifest(out)  # marked unfinished, listing every file the run announced
    assert manifest is not None and manifest.state == "in progress" and not is_complete(out)
    assert "summary.json" in manifest.files and manifest.files["summary.json"] is None
    record = manifest.files["mesh.ply"]
    assert record is not None and record["size"] == (out / "mesh.ply").stat().st_size
    assert "unfinished" in stderr and "in progress" in stderr


# --------------------------------------------------------------------------------------------------
# (3) Non-empty output directories are refused
# --------------------------------------------------------------------------------------------------


def test_save_refuses_a_non_empty_directory(tmp_path: Path, result: nplps.Reconstruction) -> None:
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(OutputExistsError, match="is not empty; pass overwrite=True") as info:
        result.save(tmp_path)
    assert isinstance(info.value, FileExistsError) and isinstance(info.value, nplps.NplpsError)
    assert nplps.OutputExistsError is OutputExistsError
    assert info.value.filename == str(tmp_path) and str(tmp_path) in str(info.value)
    assert files_under(tmp_path) == {"notes.txt"}
    # An earlier result: the message says so.
    result.save(tmp_path / "r")
    with pytest.raises(OutputExistsError, match="holds an earlier nplps result; pass overwrite=True"):
        result.save(tmp_path / "r")
    # Empty or new directories are fine.
    (tmp_path / "empty").mkdir()
    result.save(tmp_path / "empty")
    result.save(tmp_path / "new" / "deeper")


def test_cli_refuses_a_non_empty_out_before_reading_the_images(
    tmp_path: Path, scene_dir: Path, capsys, monkeypatch
) -> None:
    out = tmp_path / "r"
    out.mkdir()
    (out / "notes.txt").write_text("mine")

    def no_reading(args: object) -> None:
        raise AssertionError("the inputs were read")

    monkeypatch.setattr("nplps.cli.reconstruct.build_inputs", no_reading)
    rc, _stdout, stderr = run(capsys, reconstruct_argv(scene_dir, out, "--depth", "200"))
    assert rc == 2
    assert f"output directory '{out}' is not empty; pass --overwrite" in stderr
    assert files_under(out) == {"notes.txt"}


@pytest.mark.parametrize(
    "command",
    [
        ["synth", "sphere", "--size", "8"],
        ["demo", "--size", "8"],
        ["synth-calibration", "--size", "32", "--lights", "8", "--no-board"],
    ],
)
def test_other_commands_refuse_a_non_empty_out(tmp_path: Path, capsys, command: list[str]) -> None:
    (tmp_path / "notes.txt").write_text("mine")
    rc, _, stderr = run(capsys, [*command, "--out", str(tmp_path)])
    assert rc == 2 and "--overwrite" in stderr and str(tmp_path) in stderr
    assert files_under(tmp_path) == {"notes.txt"}


def test_help_documents_overwrite(capsys) -> None:
    for command in (["reconstruct"], ["synth"], ["demo"], ["synth-calibration"]):
        rc, stdout, _ = run(capsys, [*command, "--help"])
        assert rc == 0 and "--overwrite" in stdout, command
    rc, stdout, _ = run(capsys, ["--help"])
    assert "--overwrite" in stdout and "143" in stdout


# --------------------------------------------------------------------------------------------------
# (4) Overwriting removes the stale files of the earlier result, and only those
# --------------------------------------------------------------------------------------------------


def test_overwrite_removes_stale_files_and_keeps_the_users(
    tmp_path: Path, auto_result: nplps.Reconstruction, result: nplps.Reconstruction
) -> None:
    out = tmp_path / "r"
    auto_result.save(out)
    assert {"distance_curve.csv", "distance_curve.svg", "rig_refined.json"} <= files_under(out)
    (out / "notes.txt").write_text("mine")
    (out / "data").mkdir()
    (out / "data" / "mesh.ply").write_text("the user's, not in the manifest")
    (tmp_path / "outside.txt").write_text("outside")
    # A tampered manifest must not reach outside the directory or into a directory.
    manifest = json.loads((out / MANIFEST).read_text())
    for name in ["../outside.txt", str(tmp_path / "outside.txt"), "data", "notes.txt/.."]:
        manifest["files"][name] = None
    (out / MANIFEST).write_text(json.dumps(manifest))

    paths = result.save(out, overwrite=True)
    written = {p.relative_to(out).as_posix() for p in paths.values()}
    assert files_under(out) == written | {MANIFEST, "notes.txt", "data/mesh.ply"}
    assert not {"distance_curve.csv", "distance_curve.svg", "rig_refined.json"} & files_under(out)
    assert (out / "notes.txt").read_text() == "mine"
    assert (tmp_path / "outside.txt").read_text() == "outside"
    assert read_manifest(out) == sorted(written)


def test_cli_overwrite_removes_an_earlier_baseline_and_distance_curve(
    tmp_path: Path, scene_dir: Path, scene: nplps.Scene, capsys
) -> None:
    out = tmp_path / "r"
    rc, _, stderr = run(capsys, reconstruct_argv(scene_dir, out, "--depth", "auto", "--baseline", "--iterations", "5"))
    assert rc == 0, stderr
    first = files_under(out)
    assert {"distance_curve.csv", "baseline/mesh.ply", "baseline/summary.json"} <= first
    assert set(read_manifest(out) or []) == first - {MANIFEST}
    (out / "notes.txt").write_text("mine")
    (out / "baseline" / "my_notes.txt").write_text("mine too")

    rc, _, stderr = run(capsys, reconstruct_argv(scene_dir, out, "--depth", repr(scene.mean_depth)))
    assert rc == 2 and "holds an earlier nplps result; pass --overwrite" in stderr
    assert files_under(out) == first | {"notes.txt", "baseline/my_notes.txt"}

    rc, _, stderr = run(capsys, reconstruct_argv(scene_dir, out, "--depth", repr(scene.mean_depth), "--overwrite"))
    assert rc == 0, stderr
    now = files_under(out)
    assert "distance_curve.csv" not in now and "distance_curve.svg" not in now
    assert {f for f in now if f.startswith("baseline/")} == {"baseline/my_notes.txt"}
    assert (out / "notes.txt").read_text() == "mine"
    assert set(read_manifest(out) or []) == now - {MANIFEST, "notes.txt", "baseline/my_notes.txt"}

    # Without any user file in baseline/, the emptied folder goes too.
    depth = repr(scene.mean_depth)
    rc, _, _ = run(capsys, reconstruct_argv(scene_dir, out, "--depth", depth, "--baseline", "--overwrite"))
    assert rc == 0
    (out / "baseline" / "my_notes.txt").unlink()
    rc, _, _ = run(capsys, reconstruct_argv(scene_dir, out, "--depth", repr(scene.mean_depth), "--overwrite"))
    assert rc == 0
    assert not (out / "baseline").exists()


def test_scene_overwrite_removes_images_of_an_earlier_scene(tmp_path: Path, scene: nplps.Scene) -> None:
    scene.save(tmp_path)
    (tmp_path / "image_99.png").write_bytes(b"not nplps")  # the user's
    manifest = json.loads((tmp_path / MANIFEST).read_text())
    export.write_png8(tmp_path / "image_27.png", np.zeros((2, 2), np.uint8))  # as if an earlier scene had 28 images
    manifest["files"]["image_27.png"] = None  # finished by no run: removed only as not older than the run
    (tmp_path / MANIFEST).write_text(json.dumps(manifest))
    with pytest.raises(OutputExistsError):
        scene.save(tmp_path)
    scene.save(tmp_path, overwrite=True)
    assert not (tmp_path / "image_27.png").exists()
    assert (tmp_path / "image_99.png").read_bytes() == b"not nplps"


# --------------------------------------------------------------------------------------------------
# (5) The manifest lists exactly the files written
# --------------------------------------------------------------------------------------------------


def test_manifest_lists_exactly_the_files_written(
    tmp_path: Path, auto_result: nplps.Reconstruction, scene: nplps.Scene
) -> None:
    paths = auto_result.save(tmp_path / "r")
    written = {p.relative_to(tmp_path / "r").as_posix() for p in paths.values()}
    assert {"rig_refined.json", "distance_curve.csv", "distance_curve.svg", "summary.json"} <= written
    assert files_under(tmp_path / "r") == written | {MANIFEST}
    manifest = json.loads((tmp_path / "r" / MANIFEST).read_text())
    assert manifest["nplps"] == nplps.__version__ and manifest["state"] == "complete"
    assert manifest["folder"] == os.path.realpath(tmp_path / "r") and list(manifest["files"]) == sorted(written)
    for name, record in manifest["files"].items():
        data = (tmp_path / "r" / name).read_bytes()
        assert record == {"size": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    assert is_complete(tmp_path / "r", verify=True)

    scene_paths = scene.save(tmp_path / "s")
    assert set(read_manifest(tmp_path / "s") or []) == files_under(tmp_path / "s") - {MANIFEST}
    assert {p.name for p in scene_paths.values()} <= files_under(tmp_path / "s")


def test_demo_manifest_covers_its_subfolders(tmp_path: Path, capsys) -> None:
    out = tmp_path / "demo"
    rc, _, stderr = run(capsys, ["demo", "--size", "16", "--out", str(out)])
    assert rc == 0, stderr
    listed = set(read_manifest(out) or [])
    assert listed == files_under(out) - {MANIFEST}
    assert {"scene/rig.json", "near/mesh.ply", "baseline/summary.json"} <= listed
    rc, _, stderr = run(capsys, ["demo", "--size", "16", "--out", str(out), "--overwrite"])
    assert rc == 0, stderr
    assert set(read_manifest(out) or []) == listed
