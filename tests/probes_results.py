# ruff: noqa: E501  (tables of snippets)
"""Probes: ``nplps batch``: capture names that stay inside, globs that end, resume by fingerprint,
the summary escaped for its medium.

The batch runs on a synchronous stand-in for ``dask.distributed`` (``batch()`` / ``fake_dask()``
of the helpers): what is probed is what nplps does with folders, names and results.
"""

from __future__ import annotations

from typing import Any

ITEMS = "[(i.name, i.status) for i in items]"


def add(p: Any) -> None:
    # --- capture names and globs ---------------------------------------------------------------------
    C = "batch/captures"
    for tag, pattern in [
        ("parent", "c / 'c1' / '..'"),
        ("glob_parent", "str(c / 'c*') + '/..'"),
    ]:
        p.api(
            f"batch.name_{tag}",
            C,
            f"c = captures(2)\ntry:\n    batch({pattern}, out=tmp / 'res' / 'out')\n"
            "finally:\n    assert not (tmp / 'res').exists() or files(tmp / 'res') == set(), files(tmp / 'res')",
            p.raises("InputError", "name"),
        )
    for tag, pattern in [("dot", "str(c / 'c1') + '/.'"), ("glob_dot", "str(c / 'c*') + '/.'")]:
        # "c1/." is the folder c1: refused, or its result in out/c1 (never in out itself).
        p.api(
            f"batch.name_{tag}",
            C,
            f"c = captures(2)\ntry:\n    batch({pattern}, out=tmp / 'res' / 'out')\n"
            "finally:\n    assert all(f.startswith(('out/c0/', 'out/c1/', 'out/batch_summary.')) for f in files(tmp / 'res')), files(tmp / 'res')",
            p.either("True", "InputError", "name"),
        )
    p.api("batch.nothing_matches", C, "batch(tmp / 'none*')", p.raises("InputError", "no capture"))
    p.api(
        "batch.only_files_match",
        C,
        "write_text('a.txt', 'x'); batch(tmp / '*.txt')",
        p.raises("InputError", "no capture"),
    )
    p.api(
        "batch.same_name_twice",
        C,
        "captures(1, root='a', names=['x']); captures(1, root='b', names=['x']); batch(str(tmp) + '/*/x')",
        p.raises("InputError", "two captures", "x"),
    )
    p.api(
        "batch.symlink_loops_in_glob",
        C,
        "c = captures(2); os.symlink(tmp, c / 'c0' / 'up'); os.symlink(c, c / 'c1' / 'back')\n"
        "found = nplps.batch.find_captures(str(tmp) + '/**')",
        p.ok("len(found) == len({os.path.realpath(f) for f in found}) and len(found) <= 6"),
        budget=20,
    )
    p.api(
        "batch.self_link_in_glob",
        C,
        "c = captures(1); os.symlink('.', c / 'c0' / 'self')\nfound = nplps.batch.find_captures(str(c) + '/**')",
        p.ok("len(found) == len({os.path.realpath(f) for f in found})"),
        budget=20,
    )
    p.api(
        "batch.out_inside_glob_left_out",
        C,
        "c = captures(2); found = nplps.batch.find_captures(str(c) + '/*', out=c / 'out'); (c / 'out').mkdir()\n"
        "found = nplps.batch.find_captures(str(c) + '/*', out=c / 'out')",
        p.ok("sorted(f.name for f in found) == ['c0', 'c1']"),
    )
    p.api(
        "batch.hidden_dirs_left_out",
        C,
        "c = captures(2); (c / '.git').mkdir(); found = nplps.batch.find_captures(str(c) + '/**')",
        p.ok("not any('.git' in str(f) for f in found)"),
    )
    p.api(
        "batch.natural_order",
        C,
        "c = captures(names=['c10', 'c2', 'c1']); found = nplps.batch.find_captures(str(c / 'c*'))",
        p.ok("[f.name for f in found] == ['c1', 'c2', 'c10']"),
    )
    p.api(
        "batch.link_to_capture_outside",
        C,
        "c = captures(1); o = captures(1, root='other', names=['far']); os.symlink(o / 'far', c / 'far')\n"
        "items = batch(c / '*')",
        p.ok(
            "sorted(" + ITEMS + ") == [('c0', 'ok'), ('far', 'ok')] and (tmp / 'out' / 'far' / 'summary.json').exists()"
        ),
    )
    # --- escaping ---------------------------------------------------------------------------------------
    C = "batch/escaping"
    for tag, name in [
        ("javascript", "javascript:alert(document.domain)"),
        ("data_url", "data:text,hi"),
        ("quote_breakout", '"><img src=x onerror=alert(1)>'),
        ("script_tag", "<script>alert(1)<"),
        ("ampersand", "a&b"),
        ("percent", "100%"),
        ("hash", "#top"),
        ("question", "?x=1"),
    ]:
        p.api(
            f"batch.summary_html_{tag}",
            C,
            f"c = captures(names=[{name!r}]); items = batch(c / '*')\nh = (tmp / 'out' / 'batch_summary.html').read_text()\n"
            'import re; hrefs = re.findall(r\'href="([^"]*)"\', h)',
            p.ok(
                f"items[0].status == 'ok' and hrefs and all(x.startswith('./') for x in hrefs) and {name!r} not in h.replace('&amp;', '&') "
                "or (items[0].status == 'ok' and hrefs and all(x.startswith('./') for x in hrefs) and '<script>' not in h and 'onerror=' not in h.split('<body>')[1].replace('onerror=alert', '', 0) and not re.search(r'<img|<script', h))"
            ),
        )
    for tag, name in [
        ("ansi_red", "\x1b[31mred"),
        ("ansi_clear_screen", "\x1b[2J\x1b[H"),
        ("bell", "ding\x07"),
        ("carriage_return", "ok\rFAKE"),
        ("osc_title", "\x1b]0;owned\x07x"),
    ]:
        p.api(
            f"batch.terminal_{tag}",
            C,
            f"c = captures(names=[{name!r}]); fake_dask()\n"
            "code, out, err = run('batch', str(c / '*'), '--rig', SC / 'rig.json', '--depth', 200, '--out', tmp / 'out', '--no-report')",
            p.ok("code == 0 and '\\x1b' not in out + err and '\\x07' not in out + err and '\\r' not in out + err"),
        )
    p.api(
        "batch.csv_comma_and_newline",
        C,
        "c = captures(names=['a,b', 'x\\ny', 'q\"r']); items = batch(c / '*')\n"
        "import csv; rows = list(csv.DictReader(open(tmp / 'out' / 'batch_summary.csv', newline='')))",
        p.ok("len(rows) == 3 and all(r['status'] == 'ok' for r in rows)"),
    )
    p.api(
        "batch.error_message_escaped",
        C,
        "c = captures(names=['c0', 'bad']); (c / 'bad' / 'image_03.png').write_text('<b>not</b> a png')\n"
        "items = batch(c / '*'); h = (tmp / 'out' / 'batch_summary.html').read_text()",
        p.ok("sorted(" + ITEMS + ") == [('bad', 'failed'), ('c0', 'ok')] and '<b>not</b>' not in h"),
    )
    # --- resume by fingerprint --------------------------------------------------------------------------
    C = "batch/resume"
    FIRST = "c = captures(2); batch(c / 'c*')\n"
    for tag, second, status, word in [
        ("same", "", "skipped", None),
        ("threads_only", "threads=1", "skipped", None),
        ("report_only", "report=True", "skipped", None),
        ("other_depth", "depth=190.0, check_distance=False", "ok", "depth"),
        ("other_robust", "robust='tukey'", "ok", "robust"),
        ("other_bin", "bin_factor=2", "ok", "bin"),
        ("other_iterations", "iterations=3", "ok", "iterations"),
        ("other_tol", "tol=1e-6", "ok", "tol"),
        ("other_rig", "rig=R.with_positions(R.positions + 1.0)", "ok", "rig"),
        ("other_depth_auto", "depth='auto'", "ok", "depth"),
        ("other_dark", "dark=0.01", "ok", "dark"),
        ("other_refine", "refine_lights='intensity'", "ok", "refine"),
        ("other_mask_name", "mask_name=None", "ok", "mask"),
    ]:
        p.api(
            f"batch.resume_{tag}",
            C,
            FIRST + f"items = batch(c / 'c*'{', ' + second if second else ''})",
            p.ok(
                f"all(i.status == {status!r} for i in items)"
                + (f" and all(i.note and {word!r} in i.note for i in items)" if word else "")
            ),
        )
    p.api(
        "batch.resume_image_changed",
        C,
        FIRST + "b = (c / 'c1' / 'image_04.png').read_bytes(); J = iio.imread(c / 'c1' / 'image_04.png')\n"
        "png(c / 'c1' / 'image_04.png', (J // 2).astype(J.dtype)); items = batch(c / 'c*')",
        p.ok("[i.status for i in items] == ['skipped', 'ok'] and 'image' in items[1].note"),
    )
    p.api(
        "batch.resume_mask_changed",
        C,
        FIRST
        + "m = iio.imread(c / 'c0' / 'mask.png'); m[:2] = 0; png(c / 'c0' / 'mask.png', m); items = batch(c / 'c*')",
        p.ok("[i.status for i in items] == ['ok', 'skipped'] and 'mask' in items[0].note"),
    )
    p.api(
        "batch.resume_result_file_deleted",
        C,
        FIRST + "(tmp / 'out' / 'c0' / 'depth.npy').unlink(); items = batch(c / 'c*')",
        p.ok("[i.status for i in items] == ['ok', 'skipped'] and (tmp / 'out' / 'c0' / 'depth.npy').exists()"),
    )
    p.api(
        "batch.resume_result_file_truncated",
        C,
        FIRST + "f = tmp / 'out' / 'c1' / 'mesh.obj'; f.write_bytes(f.read_bytes()[:50]); items = batch(c / 'c*')",
        p.ok("[i.status for i in items] == ['skipped', 'ok']"),
    )
    p.api(
        "batch.resume_killed_first_save",
        C,
        "c = captures(2); from nplps import export\nreal = export.save_npy\n"
        "def killed(*a, **k):\n    raise KeyboardInterrupt\n"
        "export.save_npy = killed\ntry:\n    batch(c / 'c*')\nexcept KeyboardInterrupt:\n    pass\nfinally:\n    export.save_npy = real\n"
        "items = batch(c / 'c*')",
        p.ok(
            "all(i.status == 'ok' for i in items) and all(nplps.batch.is_complete(tmp / 'out' / n) for n in ('c0', 'c1'))"
        ),
    )
    p.api(
        "batch.resume_in_progress_manifest",
        C,
        FIRST
        + "m = manifest(tmp / 'out' / 'c0'); m['state'] = 'in progress'; write_json(tmp / 'out' / 'c0' / 'nplps-manifest.json', m)\n"
        "items = batch(c / 'c*')",
        p.ok("[i.status for i in items] == ['ok', 'skipped'] and items[0].note and 'finish' in items[0].note"),
    )
    p.api(
        "batch.users_file_refused",
        C,
        "c = captures(2); (tmp / 'out' / 'c1').mkdir(parents=True); write_text('out/c1/notes.txt', 'mine')\nitems = batch(c / 'c*')",
        p.ok(
            "[i.status for i in items] == ['ok', 'failed'] and 'overwrite' in items[1].error and (tmp / 'out' / 'c1' / 'notes.txt').read_text() == 'mine' and not (tmp / 'out' / 'c1' / 'summary.json').exists()"
        ),
    )
    p.api(
        "batch.users_file_overwrite_kept",
        C,
        "c = captures(2); (tmp / 'out' / 'c1').mkdir(parents=True); write_text('out/c1/notes.txt', 'mine')\nitems = batch(c / 'c*', overwrite=True)",
        p.ok("all(i.status == 'ok' for i in items) and (tmp / 'out' / 'c1' / 'notes.txt').read_text() == 'mine'"),
    )
    p.api(
        "batch.copied_manifest_deletes_nothing",
        C,
        FIRST + "d = tmp / 'out' / 'c1'; o = result('o', kind='auto', fresh=True)\n"
        "shutil.rmtree(d); d.mkdir(); write_text(d / 'distance_curve.csv', 'mine'); shutil.copy(o / 'nplps-manifest.json', d)\n"
        "items = batch(c / 'c*')",
        p.ok("(tmp / 'out' / 'c1' / 'distance_curve.csv').read_text() == 'mine'"),
    )
    p.api(
        "batch.wrong_image_count",
        C,
        "c = captures(3); (c / 'c1' / 'image_26.png').unlink(); items = batch(c / 'c*')",
        p.ok("[i.status for i in items] == ['ok', 'failed', 'ok'] and '26' in items[1].error"),
    )
    p.api(
        "batch.summary_lists_every_capture",
        C,
        "c = captures(3); (c / 'c1' / 'image_26.png').unlink(); items = batch(c / 'c*'); items = batch(c / 'c*')\n"
        "import csv; rows = list(csv.DictReader(open(tmp / 'out' / 'batch_summary.csv', newline='')))",
        p.ok("[(r['capture'], r['status']) for r in rows] == [('c0', 'skipped'), ('c1', 'failed'), ('c2', 'skipped')]"),
    )
    p.api(
        "batch.skipped_keeps_numbers",
        C,
        FIRST + "items = batch(c / 'c*')",
        p.ok("all(i.status == 'skipped' and i.iterations and i.solver_status == 'converged' for i in items)"),
    )
    p.api(
        "batch.unknown_option", C, "c = captures(1); batch(c / 'c*', frobnicate=1)", p.raises("TypeError", "frobnicate")
    )
    p.api("batch.rig_directory", C, "c = captures(1); batch(c / 'c*', rig=tmp)", p.raises("InputError", "directory"))
    # --- the command line -----------------------------------------------------------------------------
    C = "batch/cli"
    B = "batch {tmp}/caps/c* --rig {SC}/rig.json --depth 200 --out {tmp}/out --no-report"
    cli_setup = "captures(2); fake_dask()"
    p.cli("batch.cli_ok", C, B, p.exits(0, check="(tmp / 'out' / 'batch_summary.csv').exists()"), setup=cli_setup)
    p.cli(
        "batch.cli_rerun_other_options_says_so",
        C,
        B + " --robust tukey",
        p.exits(0, check="'robust' in out + err"),
        setup=cli_setup
        + "; run(*'"
        + B.replace("{tmp}", "TMP").replace("{SC}", "SCD")
        + "'.split())".replace("'.split())", "'.replace('TMP', str(tmp)).replace('SCD', str(SC)).split())"),
    )
    for tag, opt, word in [
        ("scheduler_not_url", "--scheduler 'not a url'", "--scheduler"),
        ("scheduler_empty", "--scheduler ''", "--scheduler"),
        ("workers_zero", "--workers 0", "--workers"),
        ("workers_negative", "--workers -3", "--workers"),
        ("max_memory_bogus", "--max-memory lots", ("--max-memory", "max_memory")),
        ("bin_zero", "--bin 0", "--bin"),
    ]:
        p.cli(
            f"batch.cli_{tag}",
            C,
            B + " " + opt,
            p.exits(2, word, check="len(err.strip().splitlines()) == 1"),
            setup="captures(2)",
            # The real dask.distributed (a subprocess): the address check is nplps's, before any connection.
            **({"proc": True, "budget": 60} if tag.startswith("scheduler") else {}),
        )
    p.cli(
        "batch.cli_no_match",
        C,
        "batch {tmp}/none* --rig {SC}/rig.json --depth 200 --out {tmp}/out",
        p.exits(2, "no capture"),
    )
    p.cli(
        "batch.cli_parent_name",
        C,
        "batch {tmp}/caps/c0/.. --rig {SC}/rig.json --depth 200 --out {tmp}/x/out",
        p.exits(2, "name", check="not (tmp / 'x').exists()"),
        setup="captures(2)",
    )
    p.cli(
        "batch.cli_one_fails_exit_1",
        C,
        B,
        p.exits(1, check="'c1: failed' in out + err and (tmp / 'out' / 'c0' / 'summary.json').exists()"),
        setup=cli_setup + "; (tmp / 'caps' / 'c1' / 'image_03.png').write_bytes(b'x')",
    )
