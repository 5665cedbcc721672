"""Result folders with a lifecycle (issue 18): nothing lost, nothing outside, nothing silent.

Each test is a finding of the issue, reproduced as it was found; every one of them failed on the
code before the lifecycle (a4ba7e2).
"""

from __future__ import annotations

import json
import os
import signal
import stat
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import numpy as np
import pytest

import mountns
import nplps
from nplps import batch, cli, export
from nplps._atomic import write_text
from nplps._outdir import MANIFEST, ResultDirectory, is_complete, load_manifest, unfinished
from nplps.errors import InputError, OutputExistsError

POSIX_ONLY = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals, FIFOs and links")


@pytest.fixture(scope="module")
def scene() -> nplps.Scene:
    return nplps.make_scene("bumps", n=24)


@pytest.fixture(scope="module")
def result(scene: nplps.Scene) -> nplps.Reconstruction:
    return nplps.reconstruct(scene.images, scene.rig, mask=scene.mask, depth=scene.mean_depth)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory: pytest.TempPathFactory, scene: nplps.Scene) -> Path:
    out = tmp_path_factory.mktemp("life") / "scene"
    scene.save(out)
    return out


def files_under(directory: Path) -> set[str]:
    return {p.relative_to(directory).as_posix() for p in directory.rglob("*") if p.is_file()}


def reconstruct_argv(scene_dir: Path, out: Path, *extra: object) -> list[str]:
    return [
        "reconstruct", str(scene_dir), "--rig", str(scene_dir / "rig.json"), "--mask", str(scene_dir / "mask.png"),
        "--out", str(out), "-q", *map(str, extra),
    ]  # fmt: skip


# --------------------------------------------------------------------------------------------------
# 1. An interrupted overwrite is never reported complete
# --------------------------------------------------------------------------------------------------


def test_failed_overwrite_is_marked_in_progress_not_complete(
    tmp_path: Path, scene: nplps.Scene, result: nplps.Reconstruction, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "r"
    small = nplps.reconstruct(scene.images[:, ::2, ::2], scene.rig.binned(2), depth=scene.mean_depth)
    small.save(out)
    assert is_complete(out) and batch.is_complete(out)

    def full_disk(*args: object, **kwargs: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(export, "save_depth_npy", full_disk)
    with pytest.raises(OSError, match="No space"):
        result.save(out, overwrite=True)
    # The folder holds the new meshes beside the old depth.npy: not complete, and batch redoes it.
    assert not is_complete(out) and not batch.is_complete(out)
    manifest = load_manifest(out)
    assert manifest is not None and manifest.state == "in progress"
    assert unfinished(out)


KILL_SCRIPT = textwrap.dedent(
    """
    import os, sys
    from nplps import cli, export

    real = export.save_depth_npy

    def killed(*args, **kwargs):
        os.kill(os.getpid(), int(os.environ["NPLPS_TEST_SIGNAL"]))

    export.save_depth_npy = killed
    raise SystemExit(cli.main(sys.argv[1:]))
    """
)


@POSIX_ONLY
@pytest.mark.parametrize("signum", [signal.SIGKILL, signal.SIGTERM, signal.SIGINT])
def test_signal_during_overwrite_leaves_no_complete_mix(
    tmp_path: Path, scene_dir: Path, scene: nplps.Scene, signum: int
) -> None:
    out = tmp_path / "r"
    depth = repr(scene.mean_depth)
    assert cli.main(reconstruct_argv(scene_dir, out, "--depth", depth, "--bin", "2")) == 0
    assert is_complete(out)
    env = dict(os.environ, NPLPS_TEST_SIGNAL=str(int(signum)))
    done = subprocess.run(
        [sys.executable, "-c", KILL_SCRIPT, *reconstruct_argv(scene_dir, out, "--depth", depth, "--overwrite")],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert done.returncode != 0 and "Traceback" not in done.stderr
    assert not is_complete(out) and unfinished(out)
    if signum != signal.SIGKILL:  # a handled signal: the command says what the folder holds
        assert "unfinished" in done.stderr and "in progress" in done.stderr


def test_interrupt_into_a_new_folder_says_unfinished(
    tmp_path: Path, scene_dir: Path, scene: nplps.Scene, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    out = tmp_path / "new"

    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(export, "save_npy", interrupted)
    assert cli.main(reconstruct_argv(scene_dir, out, "--depth", repr(scene.mean_depth))) == 130
    err = capsys.readouterr().err
    assert "unfinished" in err and not is_complete(out) and unfinished(out)
    assert "summary.json" not in files_under(out)


@pytest.mark.skipif(mountns.reason() is not None, reason=str(mountns.reason()))
def test_full_disk_during_overwrite_on_a_tmpfs(tmp_path: Path) -> None:
    disk = tmp_path / "disk"
    disk.mkdir()
    code = textwrap.dedent(
        f"""
        import nplps, sys
        from nplps import batch
        s = nplps.make_scene("bumps", n=128, seed=0)
        small = nplps.reconstruct(s.images[:, ::8, ::8], s.rig.binned(8), depth=s.mean_depth)
        small.save({str(disk / "out")!r})
        assert batch.is_complete({str(disk / "out")!r})
        big = nplps.reconstruct(s.images, s.rig, depth=s.mean_depth)
        try:
            big.save({str(disk / "out")!r}, overwrite=True)
        except OSError as e:
            print("full:", e.errno)
        print("complete:", batch.is_complete({str(disk / "out")!r}))
        """
    )
    done = mountns.run([sys.executable, "-c", code], tmpfs={str(disk): 3_000_000})
    assert done.returncode == 0, done.stderr
    assert "full: 28" in done.stdout and "complete: False" in done.stdout


# --------------------------------------------------------------------------------------------------
# 2. Only regular files are replaced
# --------------------------------------------------------------------------------------------------


@POSIX_ONLY
def test_a_fifo_target_is_written_in_place(tmp_path: Path, result: nplps.Reconstruction) -> None:
    fifo = tmp_path / "pipe.ply"
    os.mkfifo(fifo)
    received: list[bytes] = []
    reader = threading.Thread(target=lambda: received.append(fifo.read_bytes()))
    reader.start()
    result.save_ply(fifo)
    reader.join(timeout=60)
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)  # still the pipe
    assert received and received[0].startswith(b"ply\n")


@POSIX_ONLY
def test_a_symbolic_link_target_is_refused(tmp_path: Path, result: nplps.Reconstruction) -> None:
    target = tmp_path / "elsewhere.ply"
    target.write_text("the user's")
    link = tmp_path / "link.ply"
    link.symlink_to(target)
    with pytest.raises(OSError, match="not a regular file"):
        result.save_ply(link)
    assert link.is_symlink() and target.read_text() == "the user's"


@pytest.mark.skipif(mountns.reason() is not None, reason=str(mountns.reason()))
def test_a_null_device_stays_a_device(tmp_path: Path, scene_dir: Path) -> None:
    dev = tmp_path / "dev"
    dev.mkdir()
    code = textwrap.dedent(
        f"""
        import os, stat, nplps
        s = nplps.make_scene("sphere", n=16)
        r = nplps.reconstruct(s.images, s.rig, depth=s.mean_depth, mask=s.mask)
        r.save_ply({str(dev / "null")!r})
        nplps.export.save_normal_map({str(dev / "null")!r}, r.normals)
        print("char device:", stat.S_ISCHR(os.lstat({str(dev / "null")!r}).st_mode))
        """
    )
    done = mountns.run([sys.executable, "-c", code], tmpfs={str(dev): 1_000_000}, devices={str(dev / "null"): (1, 3)})
    assert done.returncode == 0, done.stderr
    assert "char device: True" in done.stdout


# --------------------------------------------------------------------------------------------------
# 3./4. Batch resume: unfinished results redone, finished ones by fingerprint
# --------------------------------------------------------------------------------------------------


def _item(out: Path) -> batch.BatchItem:
    return batch.BatchItem(out.name, "folder", os.fspath(out))


def test_resume_redoes_a_result_killed_in_its_first_save(tmp_path: Path) -> None:
    out = tmp_path / "c1"
    run = ResultDirectory(out)
    write_text(run.file("mesh.ply"), "ply\n")
    run.file("summary.json")  # announced, never written: the process died here (no close)
    assert not is_complete(out) and unfinished(out)
    assert batch._resume(_item(out), "fp", {}) == (False, True)
    # A user's file beside it: not nplps's folder any more, left alone.
    (out / "notes.txt").write_text("mine")
    assert not unfinished(out)
    assert batch._resume(_item(out), "fp", {}) == (False, False)


def test_resume_by_fingerprint(tmp_path: Path) -> None:
    out = tmp_path / "c1"
    inputs = {"option bin_factor": 1, "option robust": None}
    with ResultDirectory(out, fingerprint="a", inputs=inputs) as run:
        write_text(run.file("summary.json"), "{}")
    assert batch._resume(_item(out), "a", inputs) == (True, False)
    item = _item(out)
    assert batch._resume(item, "b", {"option bin_factor": 2, "option robust": "tukey"}) == (False, True)
    assert item.note is not None and "bin_factor" in item.note and "robust" in item.note


def test_a_copied_in_manifest_deletes_nothing(tmp_path: Path, result: nplps.Reconstruction) -> None:
    first = tmp_path / "first"
    result.save(first)
    user = tmp_path / "user"
    user.mkdir()
    (user / "distance_curve.csv").write_text("the user's own file")
    (user / MANIFEST).write_text((first / MANIFEST).read_text())
    manifest = json.loads((user / MANIFEST).read_text())
    manifest["files"]["distance_curve.csv"] = None
    (user / MANIFEST).write_text(json.dumps(manifest))
    assert not unfinished(user) and not is_complete(user)
    with pytest.raises(OutputExistsError, match="is not empty"):
        result.save(user)  # a copied-in manifest does not make it "an earlier nplps result"
    result.save(user, overwrite=True)
    assert (user / "distance_curve.csv").read_text() == "the user's own file"


def test_a_changed_file_listed_by_the_manifest_is_kept(tmp_path: Path, result: nplps.Reconstruction) -> None:
    out = tmp_path / "r"
    paths = result.save(out, formats=["stl"])
    paths["stl"].write_text("edited by the user after the run")
    result.save(out, overwrite=True)  # mesh.stl is stale, but no longer the file nplps wrote
    assert paths["stl"].read_text() == "edited by the user after the run"


def test_reconstructing_into_the_scene_folder_keeps_its_inputs(
    tmp_path: Path, scene: nplps.Scene, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "s"
    scene.save(folder)
    images = sorted(p.name for p in folder.glob("image_*.png"))
    assert images
    argv = reconstruct_argv(folder, folder, "--depth", repr(scene.mean_depth), "--overwrite")
    assert cli.main(argv) == 0, capsys.readouterr().err
    assert sorted(p.name for p in folder.glob("image_*.png")) == images
    assert (folder / "mask.png").is_file() and is_complete(folder)


# --------------------------------------------------------------------------------------------------
# 5./6./7. Paths stay inside; names escaped; no glob hang
# --------------------------------------------------------------------------------------------------


def test_a_capture_named_dotdot_is_refused(tmp_path: Path) -> None:
    (tmp_path / "caps" / "c1").mkdir(parents=True)
    with pytest.raises(InputError, match="no name of its own"):
        batch.find_captures(str(tmp_path / "caps" / "c1" / ".."), tmp_path / "out")


def test_stem_is_a_name_not_a_path(tmp_path: Path, result: nplps.Reconstruction) -> None:
    for stem in ("../x", "a/b", "..", ""):
        with pytest.raises(InputError, match="stem"):
            result.save(tmp_path / "r", stem=stem)
    assert not (tmp_path / "x.ply").exists() and not (tmp_path / "r").exists()


@POSIX_ONLY
def test_a_baseline_link_out_of_the_folder_is_not_written_through(
    tmp_path: Path, scene_dir: Path, scene: nplps.Scene, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    depth = repr(scene.mean_depth)
    assert cli.main(reconstruct_argv(scene_dir, out, "--depth", depth, "--baseline")) == 0
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    import shutil

    shutil.rmtree(out / "baseline")
    (out / "baseline").symlink_to(elsewhere)
    capsys.readouterr()
    assert cli.main(reconstruct_argv(scene_dir, out, "--depth", depth, "--baseline", "--overwrite")) == 1
    assert "symbolic link out of" in capsys.readouterr().err
    assert list(elsewhere.iterdir()) == []


def test_batch_summary_links_are_relative_and_encoded(tmp_path: Path) -> None:
    name = "javascript:alert(document.domain)"
    item = batch.BatchItem(name, "f", os.fspath(tmp_path / name), status="ok")
    _, page = batch.write_summary([item], tmp_path)
    text = page.read_text()
    assert 'href="./javascript%3Aalert%28document.domain%29/"' in text
    assert 'href="javascript:' not in text


def test_capture_names_are_escaped_on_the_terminal(capsys: pytest.CaptureFixture[str]) -> None:
    from nplps.cli.batch import _print_progress

    item = batch.BatchItem("c\x1b[2J\x1b]0;owned\x07", "f", "o", status="failed", error="bad \x1b[31m")
    _print_progress(item, 1, 1, 1)
    out = capsys.readouterr().out
    assert "\x1b" not in out and "\x07" not in out and "\\x1b[2J" in out


@POSIX_ONLY
def test_glob_with_symlink_loops_terminates(tmp_path: Path) -> None:
    root = tmp_path / "d"
    (root / "a" / "b").mkdir(parents=True)
    (root / "a" / "b" / "up").symlink_to(root)
    (root / "a" / "up2").symlink_to(root)
    code = "import sys; from nplps import batch; print(sorted(p.name for p in batch.find_captures(sys.argv[1])))"
    # (In a child process with a time limit: the walk used to run for minutes.)
    done = subprocess.run([sys.executable, "-c", code, str(root / "**")], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "['a', 'b', 'd']"


def test_glob_matches_as_before(tmp_path: Path) -> None:
    for name in ("x/c1", "x/c2", "x/deep/c3", "x/.hidden/c4"):
        (tmp_path / name).mkdir(parents=True)
    (tmp_path / "x" / "c5.png").write_bytes(b"")
    names = {p.name for p in batch.find_captures(str(tmp_path / "x" / "**" / "c*"))}
    assert names == {"c1", "c2", "c3"}
    assert {p.name for p in batch.find_captures(str(tmp_path / "x" / "c*"))} == {"c1", "c2"}


# --------------------------------------------------------------------------------------------------
# 10. Options that do nothing are named
# --------------------------------------------------------------------------------------------------


def test_options_without_effect_warn(
    tmp_path: Path, scene_dir: Path, scene: nplps.Scene, capsys: pytest.CaptureFixture[str]
) -> None:
    depth = repr(scene.mean_depth)
    argv = reconstruct_argv(scene_dir, tmp_path / "a", "--depth", depth, "--light-prior-weight", "5")
    assert cli.main(argv) == 0
    assert "--light-prior-weight has no effect without --refine-lights" in capsys.readouterr().err
    argv = reconstruct_argv(scene_dir, tmp_path / "b", "--depth", depth, "--depth-range", "150,250")
    assert cli.main(argv) == 0
    assert "--depth-range has no effect without --depth auto" in capsys.readouterr().err


def test_preprocessing_steps_are_recorded(tmp_path: Path, scene_dir: Path, scene: nplps.Scene) -> None:
    out = tmp_path / "r"
    assert cli.main(reconstruct_argv(scene_dir, out, "--depth", repr(scene.mean_depth), "--bin", "2")) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert any("binned 2 x 2" in step for step in summary["options"]["preprocessing"])


def test_manifest_hash_matches_every_file(tmp_path: Path, result: nplps.Reconstruction) -> None:
    out = tmp_path / "r"
    result.save(out, report=True)
    assert is_complete(out, verify=True)
    data = bytearray((out / "depth.npy").read_bytes())
    data[-1] ^= 0xFF  # same size, other content
    (out / "depth.npy").write_bytes(bytes(data))
    assert is_complete(out) and not is_complete(out, verify=True)
    np.testing.assert_equal(np.load(out / "normals.npy"), result.normals)


# --------------------------------------------------------------------------------------------------
# 9. Rigs know their grid; comments are kept
# --------------------------------------------------------------------------------------------------


def test_a_binned_results_rig_is_refused_on_the_original_images(
    tmp_path: Path, scene_dir: Path, scene: nplps.Scene, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "r"
    depth = repr(scene.mean_depth)
    assert cli.main(reconstruct_argv(scene_dir, out, "--depth", depth, "--bin", "4")) == 0
    saved = nplps.Rig.load(out / "rig.json")
    assert saved.grid == nplps.RigGrid((6, 6), 4)
    assert json.loads((out / "rig.json").read_text())["grid"] == {"image_size": [6, 6], "binning": 4}
    capsys.readouterr()
    argv = reconstruct_argv(scene_dir, tmp_path / "again", "--depth", depth, "--bin", "4")
    argv[argv.index("--rig") + 1] = str(out / "rig.json")
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "6 x 6 pixels (binned 4 x 4" in err and "24 x 24 pixels" in err
    # On images of its own size it works.
    small = nplps.pipeline.prepare(scene.images[:, :24:4, :24:4].copy(), rig=saved)
    assert small.images.shape[1:3] == (6, 6)


def test_rig_comments_and_grid_survive_save_and_derivation(tmp_path: Path, scene: nplps.Scene) -> None:
    data = scene.rig.to_dict()
    data["_comment"] = "LED dome 2, calibrated 2026-11-30"
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(data))
    rig = nplps.Rig.load(path).with_grid(24, 24)
    for derived in (rig.subset([0, 1, 2, 3]), rig.with_intensities(2.0), rig.with_positions(rig.positions)):
        assert derived.comments == {"_comment": "LED dome 2, calibrated 2026-11-30"}
        assert derived.grid == nplps.RigGrid((24, 24), 1)
    assert rig.binned(2).grid == nplps.RigGrid((12, 12), 2)
    rig.binned(3).save(tmp_path / "b.json")
    again = json.loads((tmp_path / "b.json").read_text())
    assert again["_comment"] == "LED dome 2, calibrated 2026-11-30" and again["grid"]["binning"] == 3
    import pickle

    assert pickle.loads(pickle.dumps(rig)).grid == rig.grid


def test_early_hashes_are_used_only_for_the_file_they_hashed(tmp_path: Path) -> None:
    """Files hashed as soon as they were finished (ResultDirectory.finished) and rewritten after get their new hash."""
    import hashlib

    out = tmp_path / "run"
    with ResultDirectory(out) as run:
        kept, rewritten, late = run.file("kept.bin"), run.file("rewritten.bin"), run.file("late.bin")
        write_text(kept, "kept")
        write_text(rewritten, "first")
        run.finished([kept, rewritten, late])  # late.bin does not exist yet: hashed at the end
        write_text(rewritten, "second, longer")
        write_text(late, "late")
    files = load_manifest(out).files  # type: ignore[union-attr]
    for name, text in (("kept.bin", "kept"), ("rewritten.bin", "second, longer"), ("late.bin", "late")):
        assert files[name] == {"size": len(text), "sha256": hashlib.sha256(text.encode()).hexdigest()}


def test_save_manifest_hashes_match_the_files(result: nplps.Reconstruction, tmp_path: Path) -> None:
    result.save(tmp_path / "out")
    assert is_complete(tmp_path / "out", verify=True)
