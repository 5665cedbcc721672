# ruff: noqa: E501  (tables of snippets)
"""Probes: status that tells the truth, and valid inputs that must be accepted.

* The light refinement never returns the unrefined start as if iterated; a successful
  refinement is not "diverged"; status, ``converged`` and history describe what is returned.
* A run at a given distance far from the data's warns "the working distance looks wrong", and
  the summary says so; at the right distance it does not.
* Options that have no effect say so; valid inputs a new user gives are accepted.
"""

from __future__ import annotations

from typing import Any

MOVED = "rg = R.with_positions(R.positions + np.random.default_rng({seed}).normal(0, 6.0, (27, 3)))\n"


def add(p: Any) -> None:
    C = "honesty/refinement"
    for seed in (1, 2, 3):
        p.api(
            f"status.stiff_prior_not_flat_start_seed{seed}",
            C,
            MOVED.format(seed=seed)
            + "r = rec(rig=rg, depth=S.mean_depth, refine_lights='position', light_prior_weight=1e9)",
            p.ok("honest(r) and (not r.converged or float(np.nanstd(r.depth)) > 1e-3)"),
            budget=30,
        )
    for mode in ("position", "both"):
        p.api(
            f"status.{mode}_refinement_on_true_rig_not_diverged",
            C,
            f"r = rec(depth=S.mean_depth, refine_lights={mode!r})",
            p.ok("honest(r) and r.status != 'diverged' and not warned('moving away')"),
            budget=30,
        )
    p.api(
        "status.refinement_history_matches_iterations",
        C,
        MOVED.format(seed=1) + "r = rec(rig=rg, depth=S.mean_depth, refine_lights='position')",
        p.ok("honest(r) and r.summary()['iterations'] == len(r.history) and r.summary()['status'] == r.status"),
        budget=30,
    )
    p.api(
        "status.intensity_refinement_recovers",
        C,
        "rg = orth(intensities=np.linspace(0.7, 1.3, 27)); r = rec(rig=rg, refine_lights='intensity')",
        p.ok("honest(r) and r.status != 'diverged' and r.refinement is not None"),
        budget=30,
    )
    p.api(
        "status.summary_agrees",
        C,
        "r = rec(refine_lights='intensity'); s = r.summary()",
        p.ok("s['status'] == r.status and s['converged'] == r.converged and s['iterations'] == len(r.history)"),
    )
    p.api(
        "status.one_iteration_not_converged",
        C,
        "r = rec(iterations=1, tol=1e-15, refine_lights='intensity')",
        p.ok("honest(r) and not r.converged"),
    )
    C = "honesty/distance"
    for d in (120.0, 150.0, 260.0, 400.0):
        p.api(
            f"distance.given_{int(d)}_warns",
            C,
            f"r = rec(depth={d})",
            p.either(
                "warned('working distance looks wrong') and r.distance_check is not None and r.distance_check.looks_wrong and r.summary()['distance_check']['looks_wrong']",
                "SolverError",
                ("light", "surface"),
            ),
        )
    for d in (195.0, 200.0, 205.0):
        p.api(
            f"distance.given_{int(d)}_quiet",
            C,
            f"r = rec(depth={d})",
            p.ok("good(r) and not warned('working distance') and not r.distance_check.looks_wrong"),
        )
    p.api(
        "distance.check_off",
        C,
        "r = rec(depth=150.0, check_distance=False)",
        p.ok("not warned('working distance') and r.distance_check is None"),
    )
    p.api(
        "distance.auto_no_check_warning",
        C,
        "r = rec(depth='auto')",
        p.ok("good(r) and not warned('working distance looks wrong')"),
    )
    p.api(
        "distance.pinhole_wrong",
        C,
        "r = nplps.reconstruct(PS.images, PS.rig, mask=PS.mask, depth=140.0)",
        p.either("warned('working distance looks wrong')", "SolverError", "light"),
    )
    p.api("distance.check_distance_string", C, "rec(check_distance='yes')", p.raises("InputError", "check_distance"))
    p.cli(
        "cli.wrong_distance_warns_and_summary",
        C,
        "reconstruct {SC} --rig {SC}/rig.json --mask {SC}/mask.png --depth 150 -q --out {tmp}/out",
        p.exits(
            0, "working distance looks wrong", check="summary(tmp / 'out')['distance_check']['looks_wrong'] is True"
        ),
    )
    p.cli(
        "cli.right_distance_quiet",
        C,
        "reconstruct {SC} --rig {SC}/rig.json --mask {SC}/mask.png --depth 200 -q --out {tmp}/out",
        p.exits(
            0, check="'working distance' not in err and summary(tmp / 'out')['distance_check']['looks_wrong'] is False"
        ),
    )
    C = "honesty/no-effect options"
    RC = "reconstruct {SC} --rig {SC}/rig.json --mask {SC}/mask.png -q --out {tmp}/out"
    for tag, opts, word in [
        ("light_prior_weight_without_refine", "--depth 200 --light-prior-weight 5", "--light-prior-weight"),
        ("depth_range_without_auto", "--depth 200 --depth-range 100,400", "--depth-range"),
        ("prior_weight_without_prior", "--depth 200 --prior-weight 3", "--prior-weight"),
    ]:
        p.cli(
            f"cli.no_effect_{tag}",
            C,
            RC + " " + opts,
            p.exits((0, 2), word, check="code == 2 or 'effect' in err or 'ignored' in err"),
        )
    C = "honesty/valid inputs"
    p.api(
        "valid.predict_two_light_rig",
        C,
        "pr = rec().predict(rig=R.subset([0, 1]))",
        p.ok("pr.shape == (2, 16, 16) and np.isfinite(pr).all()"),
    )
    p.api(
        "valid.predict_one_light_rig",
        C,
        "pr = rec().predict(rig=R.subset([5]))",
        p.ok("pr.shape == (1, 16, 16) and np.isfinite(pr).all()"),
    )
    p.api(
        "valid.predict_other_lights",
        C,
        "pr = rec().predict(rig=R.with_positions(R.positions * 1.1))",
        p.ok("pr.shape == (27, 16, 16) and np.isfinite(pr).all()"),
    )
    p.api(
        "valid.save_into_unicode_folder",
        C,
        "rec().save(tmp / 'Ergebnis ü 結果')",
        p.ok("(tmp / 'Ergebnis ü 結果' / 'summary.json').exists()"),
    )
    p.api("valid.save_pathlike_str", C, "rec().save(str(tmp / 'r'))", p.ok("(tmp / 'r' / 'mesh.ply').exists()"))
    p.api(
        "valid.save_every_format",
        C,
        "rec().save(tmp / 'r', formats=['stl', 'glb', 'points', 'normals_tiff'], report=True)",
        p.ok("{'mesh.stl', 'mesh.glb', 'points.ply', 'normals.tiff', 'report.html'} <= files(tmp / 'r')"),
    )
    p.api(
        "valid.save_formats_tuple_upper",
        C,
        "rec().save(tmp / 'r', formats=('STL',))",
        p.either("(tmp / 'r' / 'mesh.stl').exists()", "InputError", "format"),
    )
    p.api(
        "valid.rig_with_comments",
        C,
        "d = rig_dict(); d['_note'] = 'x'; d['lights'][0]['_id'] = 'L0'; r = rec(rig=Rig.load(write_json('rig.json', d)))",
        p.ok("good(r)"),
    )
    p.api("valid.rig_path_object", C, "R.save(tmp / 'r.json'); rg = Rig.load(Path(tmp / 'r.json'))", p.ok("rg == R"))
    p.cli(
        "cli.paths_with_spaces_and_unicode",
        C,
        "reconstruct '{tmp}/my scene ü' --rig '{tmp}/my scene ü/rig.json' --mask '{tmp}/my scene ü/mask.png' --depth 200 -q --out '{tmp}/résultat 1'",
        p.exits(0, check="(tmp / 'résultat 1' / 'summary.json').exists()"),
        setup="copy_scene('my scene ü')",
    )
    p.cli(
        "cli.report_on_unicode_folder",
        C,
        "report '{tmp}/Ergebnis ü'",
        p.exits(0, check="(tmp / 'Ergebnis ü' / 'report.html').exists()"),
        setup="rec().save(tmp / 'Ergebnis ü')",
    )
    p.cli(
        "cli.view_title_unicode_and_html",
        C,
        "view {tmp}/r --no-open --title '<b>Büste</b> & co'",
        p.exits(0, check="'<b>Büste</b>' not in (tmp / 'r' / 'viewer.html').read_text().split('<script')[0]"),
        setup="rec().save(tmp / 'r')",
    )
    p.cli(
        "cli.report_folder_named_like_html",
        C,
        "report '{tmp}/<img src=x onerror=alert(1)>'",
        p.exits(0, check="'<img src=x' not in (tmp / '<img src=x onerror=alert(1)>' / 'report.html').read_text()"),
        setup="rec().save(tmp / '<img src=x onerror=alert(1)>')",
    )
    p.cli(
        "cli.out_name_with_ansi_printed_escaped",
        C,
        "reconstruct {SC} --rig {SC}/rig.json --depth 200 --out '{tmp}/\x1b[31mred'",
        p.exits(0, check="'\\x1b' not in out + err"),
    )
    p.cli(
        "cli.error_naming_ansi_path_escaped",
        C,
        "reconstruct '{tmp}/\x1b[2Jgone' --rig {SC}/rig.json --depth 200 -q --out {tmp}/out",
        p.exits(2, "gone", check="'\\x1b' not in err"),
    )
    p.cli(
        "cli.synth_then_reconstruct_readme_style",
        C,
        "reconstruct {tmp}/s --rig {tmp}/s/rig.json --mask {tmp}/s/mask.png --depth auto -q --out {tmp}/r",
        p.exits(0, check="summary(tmp / 'r')['status'] == 'converged' and 'working distance' not in err"),
        setup="run('synth', 'sphere', '--size', 16, '--out', tmp / 's')",
    )
