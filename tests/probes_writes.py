# ruff: noqa: E501  (tables of snippets)
"""Probes: writing files safely: special targets, paths that stay inside, the result lifecycle.

* A target that is a FIFO (or a link to one) is written in place and stays a FIFO; a link to a
  user's file, a dangling link, a directory or a socket is refused with "not a regular file" (or
  names the path), and what it points to is untouched.
* ``stem=`` is a name, not a path; stale-file removal never leaves the folder, never follows a
  link, never removes a file nplps did not write there.
* A result folder has a lifecycle: "in progress" before the first file, "complete" after the
  last; an interrupted or failed save is never reported complete.

Only FIFOs, sockets and links under the case's directory are used (never the real /dev).
"""

from __future__ import annotations

from typing import Any

# Writers: (id, setup, call with {t} the target, the bytes a complete file starts with).
WRITERS = [
    ("save_ply", "r = rec()", "r.save_ply({t})", b"ply"),
    ("save_ply_opengl", "r = rec()", "r.save_ply({t}, opengl=True)", b"ply"),
    ("save_obj", "r = rec()", "r.save_obj({t})", b""),
    ("save_stl", "r = rec()", "r.save_stl({t})", b""),
    ("save_glb", "r = rec()", "r.save_glb({t})", b"glTF"),
    ("save_points", "r = rec()", "r.save_points({t})", b"ply"),
    ("save_normals_tiff", "r = rec()", "r.save_normals_tiff({t})", b""),
    ("save_viewer", "r = rec()", "r.save_viewer({t})", b"<"),
    ("rig_save", "", "R.save({t})", b"{"),
    ("save_depth_npy", "r = rec()", "nplps.export.save_depth_npy({t}, r.depth)", b"\x93NUMPY"),
    ("write_png8", "", "nplps.export.write_png8({t}, np.zeros((4, 4), np.uint8))", b"\x89PNG"),
    ("write_report", "d = result()", "nplps.report.write_report(d, path={t})", b"<"),
]


def add(p: Any) -> None:
    # --- special targets, every writer ---------------------------------------------------------------
    C = "writes/special targets"
    for name, setup, call, magic in WRITERS:
        pre = (setup + "\n") if setup else ""
        p.api(
            f"writes.{name}.fifo",
            C,
            pre + "t, got = fifo('target')\n" + call.format(t="t") + "\ndata = fifo_done(t, got)",
            p.ok(f"len(data) > 0 and data.startswith({magic!r})"),
        )
        p.api(
            f"writes.{name}.link_to_fifo",
            C,
            pre
            + "f, got = fifo('pipe'); t = tmp / 'target'; os.symlink(f, t)\n"
            + call.format(t="t")
            + "\ndata = fifo_done(f, got)",
            p.ok(f"t.is_symlink() and len(data) > 0 and data.startswith({magic!r})"),
        )
        p.api(
            f"writes.{name}.link_to_users_file",
            C,
            pre + "u = write_text('users.txt', 'mine'); t = tmp / 'target'; os.symlink(u, t)\n"
            "try:\n    " + call.format(t="t") + "\n"
            "finally:\n    assert u.read_text() == 'mine' and t.is_symlink(), 'the link or its file changed'",
            p.raises("OSError", "not a regular file"),
        )
        p.api(
            f"writes.{name}.dangling_link",
            C,
            pre + "u = tmp / 'nowhere' / 'x'; t = tmp / 'target'; os.symlink(u, t)\n"
            "try:\n    " + call.format(t="t") + "\n"
            "finally:\n    assert t.is_symlink() and not u.exists(), 'the link changed or was followed'",
            p.raises("OSError", "not a regular file"),
        )
        p.api(
            f"writes.{name}.directory",
            C,
            pre + "t = tmp / 'target'; t.mkdir(); write_text('target/keep.txt', 'mine')\n"
            "try:\n    " + call.format(t="t") + "\n"
            "finally:\n    assert (t / 'keep.txt').read_text() == 'mine'",
            p.raises("OSError", "target"),
        )
        p.api(
            f"writes.{name}.socket",
            C,
            pre + "import socket; s = socket.socket(socket.AF_UNIX); t = tmp / 'target'; s.bind(str(t))\n"
            "try:\n    " + call.format(t="t") + "\n"
            "finally:\n    import stat; assert stat.S_ISSOCK(os.lstat(t).st_mode); s.close()",
            p.raises("OSError", "not a regular file"),
        )
        p.api(
            f"writes.{name}.regular_replaced",
            C,
            pre + "t = write_text('target', 'old'); os.chmod(t, 0o640)\n" + call.format(t="t"),
            p.ok(f"t.read_bytes().startswith({magic!r}) and t.read_bytes() != b'old' and not t.is_symlink()"),
        )

    # --- special targets on the command line ----------------------------------------------------------
    C = "writes/cli targets"
    for command, magic in (("report", "<"), ("view", "<")):
        extra = " --no-open" if command == "view" else ""
        p.cli(
            f"writes.cli_{command}_out_fifo",
            C,
            f"{command} {{tmp}}/r --out {{tmp}}/pipe.html{extra}",
            p.exits(0, check=f"fifo_done(tmp / 'pipe.html', got).startswith({magic.encode()!r})"),
            setup="d = result(); _, got = fifo('pipe.html')",
        )
        p.cli(
            f"writes.cli_{command}_out_link_to_users_file",
            C,
            f"{command} {{tmp}}/r --out {{tmp}}/link.html{extra}",
            p.exits(1, "link.html", "not a regular file", check="(tmp / 'mine.html').read_text() == 'mine'"),
            setup="d = result(); write_text('mine.html', 'mine'); os.symlink(tmp / 'mine.html', tmp / 'link.html')",
        )
        p.cli(
            f"writes.cli_{command}_out_directory",
            C,
            f"{command} {{tmp}}/r --out {{tmp}}/adir{extra}",
            p.exits((1, 2), "adir", check="os.listdir(tmp / 'adir') == ['k.txt']"),
            setup="d = result(); (tmp / 'adir').mkdir(); write_text('adir/k.txt', 'k')",
        )
        p.cli(
            f"writes.cli_{command}_out_missing_parent",
            C,
            f"{command} {{tmp}}/r --out {{tmp}}/no/such/dir/page.html{extra}",
            p.exits((0, 1, 2), check="code == 0 and (tmp / 'no/such/dir/page.html').exists() or 'no/such' in err"),
            setup="d = result()",
        )
        p.cli(
            f"writes.cli_{command}_out_dash_is_stdout",
            C,
            f"{command} {{tmp}}/r --out -{extra}",
            p.exits(
                (0, 2),
                check="not (tmp / '-').exists() and (code == 2 and '-' in err or out.lstrip().startswith('<'))",
            ),
            setup="d = result()",
        )
    p.cli(
        "writes.cli_reconstruct_out_fifo",
        C,
        "reconstruct {SC} --rig {SC}/rig.json --depth 200 -q --out {tmp}/pipe",
        p.exits((1, 2), "pipe", check="__import__('stat').S_ISFIFO(os.lstat(tmp / 'pipe').st_mode)"),
        setup="os.mkfifo(tmp / 'pipe')",
    )
    p.cli(
        "writes.cli_synth_out_fifo",
        C,
        "synth bumps --size 8 --out {tmp}/pipe",
        p.exits((1, 2), "pipe", check="__import__('stat').S_ISFIFO(os.lstat(tmp / 'pipe').st_mode)"),
        setup="os.mkfifo(tmp / 'pipe')",
    )
    p.cli(
        "writes.cli_reconstruct_out_link_to_dir",
        C,
        "reconstruct {SC} --rig {SC}/rig.json --depth 200 -q --out {tmp}/link",
        p.exits(0, check="(tmp / 'real' / 'summary.json').exists() and (tmp / 'link').is_symlink()"),
        setup="(tmp / 'real').mkdir(); os.symlink(tmp / 'real', tmp / 'link')",
    )
    p.cli(
        "writes.cli_reconstruct_mesh_ply_link_out",
        C,
        "reconstruct {SC} --rig {SC}/rig.json --depth 200 -q --out {tmp}/r --overwrite",
        p.exits((0, 1, 2), check="(tmp / 'outside.ply').read_text() == 'mine'"),
        setup="d = result(fresh=True); (d / 'mesh.ply').unlink(); write_text('outside.ply', 'mine'); "
        "os.symlink(tmp / 'outside.ply', d / 'mesh.ply')",
    )
    p.cli(
        "writes.cli_view_title_template_markers",
        C,
        "view {tmp}/r --no-open --title @SCRIPT@@DATA@ --out {tmp}/v.html",
        p.exits(
            0,
            check="(tmp / 'v.html').read_text().count('@SCRIPT@@DATA@') >= 1 and "
            "(tmp / 'v.html').stat().st_size < 3 * (tmp / 'r' / 'viewer.html').stat().st_size + 10**6",
        ),
        setup="d = result(); run('view', d, '--no-open')",
    )

    # --- paths stay inside --------------------------------------------------------------------------
    C = "writes/inside"
    for tag, stem in [
        ("parent", "'../x'"),
        ("deep_parent", "'a/../../x'"),
        ("slash", "'a/b'"),
        ("backslash", "'a\\\\b'"),
        ("absolute", "str(tmp / 'abs')"),
        ("empty", "''"),
        ("dot", "'.'"),
        ("dotdot", "'..'"),
        ("nul", "'x\\0y'"),
        ("none", "None"),
        ("int", "3"),
        ("path_object", "Path('sub') / 'x'"),
    ]:
        p.api(
            f"writes.stem_{tag}",
            C,
            f"r = rec()\ntry:\n    r.save(tmp / 'out', stem={stem})\n"
            "finally:\n    assert sorted(os.listdir(tmp)) in (['out'], []) and not (tmp / 'out').exists() "
            "or files(tmp / 'out') == set(), files(tmp)",
            p.raises("InputError", "stem"),
        )
    for tag, stem in [("unicode", "'größe'"), ("spaces", "'my mesh'"), ("dots", "'v1.2'"), ("dash", "'-mesh'")]:
        p.api(
            f"writes.stem_{tag}_accepted",
            C,
            f"r = rec(); paths = r.save(tmp / 'out', stem={stem})",
            p.ok(f"(tmp / 'out' / ({stem} + '.ply')).exists() and (tmp / 'out' / ({stem} + '.obj')).exists()"),
        )
    for tag, name in [
        ("parent", "'../outside.txt'"),
        ("absolute", "str(tmp / 'outside.txt')"),
        ("sub_parent", "'sub/../../outside.txt'"),
        ("directory", "'data'"),
        ("dot_dot_in_file", "'notes.txt/..'"),
        ("self", "'.'"),
        ("empty", "''"),
        ("link_out", "'link.txt'"),
    ]:
        p.api(
            f"writes.manifest_names_{tag}",
            C,
            "r = rec(); d = tmp / 'r'; r.save(d); write_text('outside.txt', 'outside'); (d / 'data').mkdir()\n"
            "write_text('r/data/keep.txt', 'k'); write_text('r/notes.txt', 'n'); os.symlink(tmp / 'outside.txt', d / 'link.txt')\n"
            f"m = manifest(d); m['files'][{name}] = None; write_json(d / 'nplps-manifest.json', m)\n"
            "try:\n    r.save(d, overwrite=True)\nexcept Exception:\n    pass\n",
            p.ok(
                "(tmp / 'outside.txt').read_text() == 'outside' and (tmp / 'r' / 'data' / 'keep.txt').exists() "
                "and (tmp / 'r' / 'notes.txt').exists() and (tmp / 'r' / 'link.txt').is_symlink()"
            ),
        )
    p.cli(
        "writes.baseline_link_elsewhere",
        C,
        "reconstruct {SC} --rig {SC}/rig.json --depth 200 -q --baseline --overwrite --out {tmp}/out",
        p.exits((0, 1, 2), check="files(tmp / 'elsewhere') == {'mine.txt'}"),
        setup="run('reconstruct', SC, '--rig', SC / 'rig.json', '--depth', 200, '-q', '--out', tmp / 'out')\n"
        "(tmp / 'elsewhere').mkdir(); write_text('elsewhere/mine.txt', 'mine')\n"
        "os.symlink(tmp / 'elsewhere', tmp / 'out' / 'baseline')",
    )
    p.cli(
        "writes.baseline_link_elsewhere_new_files",
        C,
        "reconstruct {SC} --rig {SC}/rig.json --depth 200 -q --baseline --overwrite --out {tmp}/out",
        p.exits((0, 1, 2), check="files(tmp / 'elsewhere') == set()"),
        setup="run('reconstruct', SC, '--rig', SC / 'rig.json', '--depth', 200, '-q', '--out', tmp / 'out')\n"
        "(tmp / 'elsewhere').mkdir(); os.symlink(tmp / 'elsewhere', tmp / 'out' / 'baseline')",
    )
    p.cli(
        "writes.out_is_input_scene",
        C,
        "reconstruct {tmp}/s --rig {tmp}/s/rig.json --mask {tmp}/s/mask.png --depth 200 -q --out {tmp}/s --overwrite",
        p.exits(
            (0, 2),
            check="all((tmp / 's' / f'image_{i:02d}.png').read_bytes() == (SC / f'image_{i:02d}.png').read_bytes() "
            "for i in range(27)) and (tmp / 's' / 'depth_gt.npy').exists()",
        ),
        setup="copy_scene('s')",
    )
    p.cli(
        "writes.out_inside_input_scene",
        C,
        "reconstruct {tmp}/s --rig {tmp}/s/rig.json --mask {tmp}/s/mask.png --depth 200 -q --out {tmp}/s/result",
        p.exits(
            0,
            check="(tmp / 's' / 'result' / 'summary.json').exists() and len(list((tmp / 's').glob('image_*.png'))) == 27",
        ),
        setup="copy_scene('s')",
    )
    p.api(
        "writes.subfolder_link_out_on_overwrite",
        C,
        "r = rec(); d = tmp / 'r'; r.save(d); (tmp / 'else').mkdir(); write_text('else/summary.json', 'mine')\n"
        "os.symlink(tmp / 'else', d / 'baseline')\nr.save(d, overwrite=True)",
        p.ok("(tmp / 'else' / 'summary.json').read_text() == 'mine'"),
    )

    # --- lifecycle ---------------------------------------------------------------------------------
    C = "writes/lifecycle"
    IC = "from nplps._outdir import is_complete, unfinished, load_manifest\n"
    base = "r = rec(); d = tmp / 'r'; r.save(d)\n"
    for tag, edit, complete in [
        ("fresh", "", True),
        ("file_deleted", "(d / 'depth.npy').unlink()", False),
        ("summary_deleted", "(d / 'summary.json').unlink()", False),
        ("file_truncated", "b = (d / 'mesh.obj').read_bytes(); (d / 'mesh.obj').write_bytes(b[:100])", False),
        ("file_grown", "(d / 'history.csv').write_text((d / 'history.csv').read_text() + '1,2\\n')", False),
        ("file_replaced_by_dir", "(d / 'normals.npy').unlink(); (d / 'normals.npy').mkdir()", False),
        (
            "file_replaced_by_link",
            "(d / 'mesh.ply').rename(tmp / 'm.ply'); os.symlink(tmp / 'm.ply', d / 'mesh.ply')",
            False,
        ),
        ("manifest_deleted", "(d / 'nplps-manifest.json').unlink()", False),
        ("manifest_garbage", "write_text(d / 'nplps-manifest.json', '{{{')", False),
        ("manifest_list", "write_json(d / 'nplps-manifest.json', [1, 2])", False),
        ("manifest_empty", "write_text(d / 'nplps-manifest.json', '')", False),
        (
            "manifest_in_progress",
            "m = manifest(d); m['state'] = 'in progress'; write_json(d / 'nplps-manifest.json', m)",
            False,
        ),
        (
            "manifest_state_bogus",
            "m = manifest(d); m['state'] = 'done!'; write_json(d / 'nplps-manifest.json', m)",
            False,
        ),
        (
            "manifest_files_string",
            "m = manifest(d); m['files'] = 'all'; write_json(d / 'nplps-manifest.json', m)",
            False,
        ),
        (
            "manifest_no_summary",
            "m = manifest(d); del m['files']['summary.json']; write_json(d / 'nplps-manifest.json', m)",
            False,
        ),
        (
            "manifest_size_lie",
            "m = manifest(d); m['files']['depth.npy']['size'] += 1; write_json(d / 'nplps-manifest.json', m)",
            False,
        ),
        (
            "manifest_other_folder",
            "m = manifest(d); m['folder'] = str(tmp / 'elsewhere'); write_json(d / 'nplps-manifest.json', m)",
            False,
        ),
        ("manifest_is_dir", "(d / 'nplps-manifest.json').unlink(); (d / 'nplps-manifest.json').mkdir()", False),
        ("manifest_fifo", "(d / 'nplps-manifest.json').unlink(); os.mkfifo(d / 'nplps-manifest.json')", False),
        (
            "manifest_link_loop",
            "(d / 'nplps-manifest.json').unlink(); os.symlink(d / 'nplps-manifest.json', d / 'nplps-manifest.json')",
            False,
        ),
        ("manifest_huge", "write_text(d / 'nplps-manifest.json', ' ' * (60 << 20) + '{}')", False),
        ("manifest_deep", "write_text(d / 'nplps-manifest.json', '[' * 100000 + ']' * 100000)", False),
        (
            "manifest_copied_from_other",
            "r.save(tmp / 'o'); shutil.copy(tmp / 'o' / 'nplps-manifest.json', d / 'nplps-manifest.json')",
            False,
        ),
        ("user_file_added", "write_text(d / 'notes.txt', 'mine')", True),
    ]:
        want = "True" if complete else "False"
        p.api(
            f"lifecycle.is_complete_{tag}",
            C,
            IC + base + (edit + "\n" if edit else "") + "a = is_complete(d); b = nplps.batch.is_complete(d)",
            p.ok(f"a is {want} and b is {want}"),
        )
    p.api(
        "lifecycle.is_complete_missing_folder",
        C,
        IC + "a = is_complete(tmp / 'nope'); b = nplps.batch.is_complete(tmp / 'nope')",
        p.ok("a is False and b is False"),
    )
    p.api(
        "lifecycle.is_complete_a_file",
        C,
        IC + "f = write_text('f', 'x'); a = is_complete(f); b = nplps.batch.is_complete(f)",
        p.ok("a is False and b is False"),
    )
    p.api(
        "lifecycle.is_complete_verify_hash",
        C,
        IC
        + base
        + "b = bytearray((d / 'depth.npy').read_bytes()); b[-1] ^= 1; (d / 'depth.npy').write_bytes(bytes(b))\n"
        "a = is_complete(d, verify=True)",
        p.ok("a is False"),
    )
    # An interruption or a failure while saving: never complete, marked unfinished.
    for tag, writer, exc in [
        ("ctrl_c_npy", "save_npy", "KeyboardInterrupt"),
        ("ctrl_c_depth", "save_depth_npy", "KeyboardInterrupt"),
        ("ctrl_c_png", "_write_pngs", "KeyboardInterrupt"),  # the PNG files, encoded together
        ("disk_full_npy", "save_npy", "OSError(28, 'No space left on device')"),
        ("disk_full_depth", "save_depth_npy", "OSError(28, 'No space left on device')"),
        ("error_png", "_write_pngs", "RuntimeError('writer failed')"),
    ]:
        setup = (
            IC + "from nplps import export\nr = rec(); d = tmp / 'r'\n"
            f"real = export.{writer}\n"
            f"def broken(*a, **k):\n    raise {exc}\n"
            f"export.{writer} = broken\n"
            "try:\n    r.save(d)\nexcept BaseException as e:\n    caught = e\nelse:\n    caught = None\n"
            f"finally:\n    export.{writer} = real\n"
        )
        p.api(
            f"lifecycle.new_folder_{tag}",
            C,
            setup,
            p.ok(
                "caught is not None and not is_complete(d) and unfinished(d) and "
                "not (d / 'summary.json').exists() and not any(f.startswith('.') for f in os.listdir(d))"
            ),
        )
        p.api(
            f"lifecycle.overwrite_{tag}",
            C,
            IC
            + "rec(images=I[:, ::2, ::2], rig=R.binned(2), mask=M[::2, ::2]).save(tmp / 'r')\n"
            + setup.replace("r.save(d)", "r.save(d, overwrite=True)"),
            p.ok(
                "caught is not None and not is_complete(d) and unfinished(d) and "
                "load_manifest(d).state == 'in progress' and not nplps.batch.is_complete(d)"
            ),
        )
    CLI_INT = (
        "from nplps import export\nreal = export.save_npy\n"
        "def broken(*a, **k):\n    raise KeyboardInterrupt\n"
        "export.save_npy = broken\n"
        "try:\n    code0, _, err0 = run('reconstruct', SC, '--rig', SC / 'rig.json', '--depth', 200, '-q', '--out', tmp / 'r')\n"
        "finally:\n    export.save_npy = real\n"
    )
    p.api(
        "lifecycle.cli_ctrl_c_says_unfinished",
        C,
        CLI_INT,
        p.ok("code0 == 130 and 'unfinished' in err0 and 'Traceback' not in err0"),
    )
    p.api(
        "lifecycle.cli_rerun_after_ctrl_c",
        C,
        CLI_INT
        + "code1, _, err1 = run('reconstruct', SC, '--rig', SC / 'rig.json', '--depth', 200, '-q', '--out', tmp / 'r')",
        p.ok("code1 == 0 or (code1 == 2 and 'overwrite' in err1)"),
    )
    p.api(
        "lifecycle.cli_overwrite_after_ctrl_c",
        C,
        IC
        + CLI_INT
        + "code1, _, err1 = run('reconstruct', SC, '--rig', SC / 'rig.json', '--depth', 200, '-q', '--out', tmp / 'r', '--overwrite')",
        p.ok("code1 == 0 and is_complete(tmp / 'r')"),
    )
    p.api(
        "lifecycle.cli_disk_full_exit_1",
        C,
        "from nplps import export\nreal = export.save_depth_npy\n"
        "def full(path, *a, **k):\n    raise OSError(28, 'No space left on device', str(path))\n"
        "export.save_depth_npy = full\n"
        "try:\n    code0, _, err0 = run('reconstruct', SC, '--rig', SC / 'rig.json', '--depth', 200, '-q', '--out', tmp / 'r')\n"
        "finally:\n    export.save_depth_npy = real\n",
        p.ok("code0 == 1 and 'depth.npy' in err0 and 'Traceback' not in err0 and len(err0.strip().splitlines()) <= 3"),
    )
    # Overwrite removes only the earlier result's stale files, never the user's.
    p.api(
        "lifecycle.overwrite_removes_stale",
        C,
        "d = result('r', kind='auto', fresh=True); rec().save(d, overwrite=True)",
        p.ok("not (tmp / 'r' / 'distance_curve.csv').exists() and not (tmp / 'r' / 'rig_refined.json').exists()"),
    )
    p.api(
        "lifecycle.overwrite_keeps_edited_stale",
        C,
        "d = result('r', kind='auto', fresh=True); write_text(d / 'distance_curve.csv', 'my edit')\nrec().save(d, overwrite=True)",
        p.ok("(tmp / 'r' / 'distance_curve.csv').read_text() == 'my edit'"),
    )
    p.api(
        "lifecycle.overwrite_keeps_users_files",
        C,
        "d = result(fresh=True); write_text(d / 'notes.txt', 'n'); (d / 'sub').mkdir(); write_text(d / 'sub' / 'mesh.ply', 'x')\n"
        "rec().save(d, overwrite=True)",
        p.ok("(tmp / 'r' / 'notes.txt').read_text() == 'n' and (tmp / 'r' / 'sub' / 'mesh.ply').read_text() == 'x'"),
    )
    p.api(
        "lifecycle.copied_manifest_deletes_nothing",
        C,
        "o = result('o', kind='auto', fresh=True); d = tmp / 'mine'; d.mkdir(); write_text('mine/distance_curve.csv', 'mine')\n"
        "write_text('mine/rig_refined.json', 'mine'); shutil.copy(o / 'nplps-manifest.json', d)\n"
        "rec().save(d, overwrite=True)",
        p.ok(
            "(tmp / 'mine' / 'distance_curve.csv').read_text() == 'mine' and (tmp / 'mine' / 'rig_refined.json').read_text() == 'mine'"
        ),
    )
    p.api(
        "lifecycle.copied_manifest_without_overwrite",
        C,
        "o = result('o', fresh=True); d = tmp / 'mine'; d.mkdir(); write_text('mine/depth.npy', 'mine')\n"
        "shutil.copy(o / 'nplps-manifest.json', d)\n"
        "try:\n    rec().save(d)\nfinally:\n    assert (d / 'depth.npy').read_text() == 'mine'",
        p.raises("OutputExistsError", "overwrite"),
    )
    p.api(
        "lifecycle.earlier_result_refused",
        C,
        "d = result(fresh=True); before = (d / 'depth.npy').read_bytes()\n"
        "try:\n    rec(depth=190.0, check_distance=False).save(d)\nfinally:\n    assert (d / 'depth.npy').read_bytes() == before",
        p.raises("OutputExistsError", "earlier nplps result", "overwrite"),
    )
    p.api(
        "lifecycle.scene_overwrite_keeps_users",
        C,
        "s = nplps.make_scene('bumps', n=8); s.save(tmp / 's'); write_text('s/notes.txt', 'n'); s.save(tmp / 's', overwrite=True)",
        p.ok("(tmp / 's' / 'notes.txt').read_text() == 'n' and len(list((tmp / 's').glob('image_*.png'))) == 27"),
    )
    p.api(
        "lifecycle.scene_fewer_images_removes_stale",
        C,
        "import dataclasses\ns = nplps.make_scene('bumps', n=8); s.save(tmp / 's')\n"
        "s3 = dataclasses.replace(s, images=s.images[:20], rig=s.rig.subset(range(20)))\n"
        "s3.save(tmp / 's', overwrite=True)",
        p.ok("len(list((tmp / 's').glob('image_*.png'))) == 20"),
    )
    p.api(
        "lifecycle.save_no_temporaries_left",
        C,
        "r = rec(); r.save(tmp / 'r', formats=('stl', 'glb', 'points', 'normals_tiff'), report=True)",
        p.ok("not [f for f in files(tmp / 'r') if '.nplps-' in f]"),
    )
    p.api(
        "lifecycle.manifest_lists_every_file",
        C,
        "r = rec(); r.save(tmp / 'r', formats=('stl', 'glb', 'points', 'normals_tiff'), report=True)",
        p.ok("set(manifest(tmp / 'r')['files']) == files(tmp / 'r') - {'nplps-manifest.json'}"),
    )
    p.api(
        "lifecycle.manifest_sizes_match",
        C,
        "r = rec(); r.save(tmp / 'r')",
        p.ok("all(v['size'] == (tmp / 'r' / k).stat().st_size for k, v in manifest(tmp / 'r')['files'].items())"),
    )
    p.api(
        "lifecycle.view_adds_to_manifest",
        C,
        "from nplps._outdir import is_complete\nd = result(fresh=True); code, _, _ = run('view', d, '--no-open')",
        p.ok("code == 0 and 'viewer.html' in manifest(d)['files'] and is_complete(d)"),
    )
    p.api(
        "lifecycle.report_keeps_complete",
        C,
        "from nplps._outdir import is_complete\nd = result(fresh=True); code, _, _ = run('report', d)",
        p.ok("code == 0 and is_complete(d)"),
    )
