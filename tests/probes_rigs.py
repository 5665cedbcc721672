# ruff: noqa: E501  (tables of snippets)
"""Probes: rigs know their grid. A rig file records the image size it belongs to and the binning
applied; images of another size are refused with a message naming both sizes (or adapted
exactly), a binned result's rig says so, and comments survive a save.
"""

from __future__ import annotations

from typing import Any

GRID = "d = rig_dict(); d['grid'] = {grid}; rg = Rig.load(write_json('rig.json', d))\n"


def add(p: Any) -> None:
    C = "rigs/grid file"
    for tag, grid in [
        ("not_object", "[16, 16]"),
        ("string", "'16x16'"),
        ("size_string", "{'image_size': 'big', 'binning': 1}"),
        ("size_one", "{'image_size': [16], 'binning': 1}"),
        ("size_three", "{'image_size': [16, 16, 3], 'binning': 1}"),
        ("size_zero", "{'image_size': [0, 16], 'binning': 1}"),
        ("size_negative", "{'image_size': [16, -16], 'binning': 1}"),
        ("size_float", "{'image_size': [16.5, 16], 'binning': 1}"),
        ("size_bool", "{'image_size': [True, 16], 'binning': 1}"),
        ("size_huge", "{'image_size': [2**40, 16], 'binning': 1}"),
        ("binning_zero", "{'image_size': [16, 16], 'binning': 0}"),
        ("binning_negative", "{'image_size': [16, 16], 'binning': -2}"),
        ("binning_string", "{'image_size': [16, 16], 'binning': '2'}"),
        ("binning_float", "{'image_size': [16, 16], 'binning': 2.5}"),
        ("binning_null", "{'image_size': [16, 16], 'binning': None}"),
        ("unknown_key", "{'image_size': [16, 16], 'binning': 1, 'dpi': 300}"),
    ]:
        p.api(f"rig.grid_{tag}", C, GRID.format(grid=grid), p.raises("RigError", "grid"))
    for tag, grid in [
        ("matching", "{'image_size': [16, 16], 'binning': 1}"),
        ("binning_only", "{'binning': 1}"),
        ("empty", "{}"),
        ("comment_key", "{'image_size': [16, 16], 'binning': 1, '_note': 'from the lab'}"),
        ("integral_float_binning", "{'image_size': [16, 16], 'binning': 1.0}"),
    ]:
        p.api(
            f"rig.grid_{tag}_accepted",
            C,
            GRID.format(grid=grid) + "r = rec(rig=rg)",
            p.either("good(r)", "RigError", "grid") if "float" in tag else p.ok("good(r)"),
        )
    p.api(
        "rig.grid_missing_accepted",
        C,
        "d = rig_dict(); d.pop('grid', None); rg = Rig.load(write_json('rig.json', d)); r = rec(rig=rg)",
        p.ok("good(r)"),
    )
    C = "rigs/grid mismatch"
    for tag, size in [
        ("larger", "(32, 32)"),
        ("smaller", "(8, 8)"),
        ("transposed", "(16, 32)"),
        ("one_pixel_off", "(17, 16)"),
    ]:
        p.api(
            f"rig.grid_mismatch_{tag}",
            C,
            f"rec(rig=R.with_grid(*{size}))",
            p.raises("RigError", f"{eval(size)[0]} x {eval(size)[1]}", "16 x 16"),
        )
    p.api(
        "rig.grid_mismatch_parallel",
        C,
        "par(rig=R.with_grid(32, 32))",
        p.raises("RigError", "32 x 32", "16 x 16"),
    )
    p.api(
        "rig.grid_mismatch_binned_says_binned",
        C,
        "rec(rig=R.binned(4).with_grid(4, 4))",
        p.raises("RigError", "4 x 4", "16 x 16", "binned"),
    )
    p.api(
        "rig.grid_binned_on_binned_images",
        C,
        "r = rec(images=I[:, ::2, ::2] * 0 + I.reshape(27, 8, 2, 8, 2).mean((2, 4)), rig=R.binned(2).with_grid(8, 8), mask=M[::2, ::2])",
        p.ok("honest(r) and r.converged"),
    )
    p.api("rig.binned_records_binning", C, "g = R.binned(4).grid", p.ok("g is not None and g.binning == 4"))
    p.api("rig.binned_twice", C, "g = R.binned(2).binned(2).grid", p.ok("g is not None and g.binning == 4"))
    p.api("rig.binned_zero", C, "R.binned(0)", p.raises("InputError|RigError", ("bin", "factor")))
    p.api("rig.binned_negative", C, "R.binned(-2)", p.raises("InputError|RigError", ("bin", "factor")))
    p.api("rig.binned_string", C, "R.binned('2')", p.raises("InputError|RigError|TypeError", ("bin", "factor", "int")))
    p.api(
        "rig.grid_round_trip",
        C,
        "R.with_grid(16, 16).save(tmp / 'g.json'); rg = Rig.load(tmp / 'g.json')",
        p.ok("rg.grid is not None and rg.grid.image_size == (16, 16) and rg.grid.binning == 1"),
    )
    p.api(
        "rig.grid_binned_round_trip",
        C,
        "R.binned(2).with_grid(8, 8).save(tmp / 'g.json'); rg = Rig.load(tmp / 'g.json')",
        p.ok("rg.grid.image_size == (8, 8) and rg.grid.binning == 2"),
    )
    p.api(
        "rig.comments_kept_on_save",
        C,
        "d = rig_dict(); d['_comment'] = 'calibrated 2024-05-01'; Rig.load(write_json('rig.json', d)).save(tmp / 'out.json')\n"
        "saved = json.loads((tmp / 'out.json').read_text())",
        p.ok("saved.get('_comment') == 'calibrated 2024-05-01'"),
    )
    p.api(
        "rig.comments_kept_through_result",
        C,
        "d = rig_dict(); d['_comment'] = 'lab rig'; rg = Rig.load(write_json('rig.json', d)); rec(rig=rg).save(tmp / 'r')\n"
        "saved = json.loads((tmp / 'r' / 'rig.json').read_text())",
        p.ok("saved.get('_comment') == 'lab rig'"),
    )
    p.api(
        "rig.unknown_top_level_key",
        C,
        "d = rig_dict(); d['lightz'] = []; Rig.load(write_json('rig.json', d))",
        p.raises("RigError", "lightz"),
    )
    # The command line: a binned result's rig reused.
    C = "rigs/cli"
    RC = "reconstruct {SC} --rig {rig} --mask {SC}/mask.png --depth 200 -q --out {tmp}/out2"
    BIN = "run('reconstruct', SC, '--rig', SC / 'rig.json', '--mask', SC / 'mask.png', '--depth', 200, '-q', '--bin', 2, '--out', tmp / 'b')"
    p.cli(
        "cli.binned_result_rig_records_binning",
        C,
        "reconstruct {SC} --rig {SC}/rig.json --mask {SC}/mask.png --depth 200 -q --bin 2 --out {tmp}/b",
        p.exits(
            0, check="json.loads((tmp / 'b' / 'rig.json').read_text())['grid'] == {'image_size': [8, 8], 'binning': 2}"
        ),
    )
    p.cli(
        "cli.binned_result_rig_with_bin_again",
        C,
        RC.replace("{rig}", "{tmp}/b/rig.json") + " --bin 2",
        p.exits(2, "8 x 8", "binned", check="len(err.strip().splitlines()) == 1"),
        setup=BIN,
    )
    p.cli(
        "cli.binned_result_rig_without_bin",
        C,
        RC.replace("{rig}", "{tmp}/b/rig.json"),
        p.exits(2, "8 x 8", "16 x 16", check="len(err.strip().splitlines()) == 1"),
        setup=BIN,
    )
    p.cli(
        "cli.binned_result_rig_on_binned_images",
        C,
        "reconstruct {tmp}/small --rig {tmp}/b/rig.json --depth 200 -q --out {tmp}/out2",
        p.exits(0),
        setup=BIN + "\n(tmp / 'small').mkdir()\n"
        "for i in range(27):\n    png(tmp / 'small' / f'image_{i:02d}.png', np.round(I[i].reshape(8, 2, 8, 2).mean((1, 3)) / I.max() * 65535).astype(np.uint16))",
    )
    p.cli(
        "cli.rig_grid_other_size",
        C,
        RC.replace("{rig}", "{tmp}/g.json"),
        p.exits(2, "32 x 32", "16 x 16", check="len(err.strip().splitlines()) == 1"),
        setup="d = rig_dict(); d['grid'] = {'image_size': [32, 32], 'binning': 1}; write_json('g.json', d)",
    )
    p.cli(
        "cli.grid_shape_pads_to_rig_no_mask",
        C,
        "reconstruct {SC} --rig {tmp}/g.json --depth 200 -q --out {tmp}/out2 --grid-shape 20,20",
        p.exits(0, check="json.loads((tmp / 'out2' / 'rig.json').read_text())['grid']['image_size'] == [20, 20]"),
        setup="d = rig_dict(); d['grid'] = {'image_size': [20, 20], 'binning': 1}; write_json('g.json', d)",
    )
    p.cli(
        "cli.grid_shape_mask_of_the_old_size",
        C,
        RC.replace("{rig}", "{tmp}/g.json") + " --grid-shape 20,20",
        p.exits(2, "mask", "(16, 16)", "(20, 20)", check="len(err.strip().splitlines()) == 1"),
        setup="d = rig_dict(); d['grid'] = {'image_size': [20, 20], 'binning': 1}; write_json('g.json', d)",
    )
    p.cli(
        "cli.grid_shape_pads_to_rig",
        C,
        RC.replace("{rig}", "{tmp}/g.json").replace("{SC}/mask.png", "{tmp}/m20.png") + " --grid-shape 20,20",
        p.exits(0, check="json.loads((tmp / 'out2' / 'rig.json').read_text())['grid']['image_size'] == [20, 20]"),
        setup="d = rig_dict(); d['grid'] = {'image_size': [20, 20], 'binning': 1}; write_json('g.json', d)\n"
        "m = np.zeros((20, 20), np.uint8); m[:16, :16] = M * 255; png('m20.png', m)",
    )
    p.cli(
        "cli.evaluate_rig_grid_other_size",
        C,
        "evaluate {SC} --rig {tmp}/g.json --mask {SC}/mask.png --depth 200 -q --lights 0",
        p.exits(2, "32 x 32", "16 x 16"),
        setup="d = rig_dict(); d['grid'] = {'image_size': [32, 32], 'binning': 1}; write_json('g.json', d)",
    )
