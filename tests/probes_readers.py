"""Probes: ``nplps report`` / ``nplps view`` on damaged, hand-edited or foreign result folders.

A demanding user gets, for a damaged file, exit status 2 and one stderr line ``nplps: error:
damaged result file 'PATH': PROBLEM`` (never a traceback, never an allocation of what a header
claims); for a folder that is fine (other valid encodings of the same data, optional files
missing), a page.
"""

from __future__ import annotations

from typing import Any

R = "d = result()\n"
RA = "d = result(kind='auto')\n"


def add(p: Any) -> None:
    R = "d = result()\n"

    def damaged(id: str, category: str, setup: str, file: Any, commands: tuple[str, ...] = ("report",)) -> None:
        for command in commands:
            argv = f"{command} {{tmp}}/r" + (" --no-open" if command == "view" else "")
            check = "damaged_line(err)" if isinstance(file, tuple) else f"damaged_line(err, {file!r})"
            p.cli(f"{command}.{id}", category, argv, p.exits(2, "damaged result file", file, check=check), setup=setup)

    def unreadable(id: str, category: str, setup: str, file: str, commands: tuple[str, ...] = ("report",)) -> None:
        """A file that cannot be read at all (a link loop): one line naming it, exit 2."""
        for command in commands:
            argv = f"{command} {{tmp}}/r" + (" --no-open" if command == "view" else "")
            p.cli(
                f"{command}.{id}",
                category,
                argv,
                p.exits(2, ("damaged result file", "cannot read result file"), file, check=f"one_line(err, {file!r})"),
                setup=setup,
            )

    def fine(id: str, category: str, setup: str, commands: tuple[str, ...] = ("report",), check: str = "") -> None:
        for command in commands:
            argv = f"{command} {{tmp}}/r" + (" --no-open" if command == "view" else "")
            out = "report.html" if command == "report" else "viewer.html"
            p.cli(
                f"{command}.{id}",
                category,
                argv,
                p.exits(0, check=f"(tmp / 'r' / {out!r}).stat().st_size > 1000" + (f" and {check}" if check else "")),
                setup=setup,
            )

    def either(id: str, category: str, setup: str, file: str, commands: tuple[str, ...] = ("report",)) -> None:
        """A hand edit that may be read as it is or refused: never a traceback, one line if refused."""
        for command in commands:
            argv = f"{command} {{tmp}}/r" + (" --no-open" if command == "view" else "")
            p.cli(
                f"{command}.{id}",
                category,
                argv,
                p.exits((0, 2), check=f"code == 0 or damaged_line(err, {file!r})"),
                setup=setup,
            )

    BOTH = ("report", "view")
    damaged_only = damaged

    def damaged_or_either(
        id: str, category: str, setup: str, file: str, commands: tuple[str, ...] = ("report",)
    ) -> None:
        either(id, category, setup, file, commands)

    # --- summary.json: not an object, not JSON ------------------------------------------------------
    C = "readers/summary.json"
    for name, value in [("list", "[1, 2]"), ("string", "'text'"), ("number", "3"), ("null", "None"), ("true", "True")]:
        damaged(f"summary_{name}", C, R + f"write_json(d / 'summary.json', {value})", "summary.json")
    damaged("summary_empty", C, R + "write_text(d / 'summary.json', '')", "summary.json")
    damaged(
        "summary_truncated",
        C,
        R + "t = (d / 'summary.json').read_text(); write_text(d / 'summary.json', t[: len(t) // 2])",
        "summary.json",
    )
    damaged("summary_binary", C, R + "write_bytes(d / 'summary.json', bytes(range(256)))", "summary.json")
    damaged(
        "summary_deep_nesting", C, R + "write_text(d / 'summary.json', '[' * 100000 + ']' * 100000)", "summary.json"
    )
    damaged(
        "summary_huge_whitespace",
        C,
        R + "write_text(d / 'summary.json', ' ' * (80 << 20) + '{}')",
        "summary.json",
    )
    damaged(
        "summary_is_directory", C, R + "(d / 'summary.json').unlink(); (d / 'summary.json').mkdir()", "summary.json"
    )
    unreadable(
        "summary_symlink_loop",
        C,
        R + "(d / 'summary.json').unlink(); os.symlink(d / 'summary.json', d / 'summary.json')",
        "summary.json",
    )
    damaged("summary_fifo", C, R + "(d / 'summary.json').unlink(); os.mkfifo(d / 'summary.json')", "summary.json")
    either(
        "summary_utf8_bom",
        C,
        R + "write_bytes(d / 'summary.json', b'\\xef\\xbb\\xbf' + (d / 'summary.json').read_bytes())",
        "summary.json",
    )
    damaged(
        "summary_utf16",
        C,
        R + "write_bytes(d / 'summary.json', (d / 'summary.json').read_text().encode('utf-16'))",
        "summary.json",
    )
    damaged(
        "summary_latin1_garbage",
        C,
        R + "write_bytes(d / 'summary.json', b'{\"method\": \"\\xff\\xfe\"}')",
        "summary.json",
    )
    p.cli(
        "report.summary_missing",
        C,
        "report {tmp}/r",
        p.exits(2, "summary.json", check="one_line(err, 'not an nplps result')"),
        setup=R + "(d / 'summary.json').unlink()",
    )
    # --- summary.json: fields of the wrong type -------------------------------------------------------
    C = "readers/summary fields"
    for name, value in [
        ("text", "'16x16'"),
        ("one", "[16]"),
        ("three", "[16, 16, 3]"),
        ("zero", "[0, 16]"),
        ("negative", "[-1, 16]"),
        ("floats", "[16.0, 16.0]"),
        ("bools", "[True, True]"),
        ("huge", "[2**40, 16]"),
        ("null", "None"),
        ("strings", "['16', '16']"),
    ]:
        damaged(f"summary_shape_{name}", C, R + f"edit_json(d / 'summary.json', shape={value})", "summary.json")
    damaged(
        "summary_shape_missing",
        C,
        R + "s = summary(d); del s['shape']; write_json(d / 'summary.json', s)",
        "summary.json",
    )
    for field, value in [
        ("method", "3"),
        ("status", "5"),
        ("status_reason", "[]"),
        ("converged", "'yes'"),
        ("converged", "1"),
        ("pixels", "-1"),
        ("pixels", "1.5"),
        ("regions", "'2'"),
        ("iterations", "-3"),
        ("iterations", "'10'"),
        ("iterations", "True"),
        ("unfitted_pixels", "[]"),
        ("rms_residual", "'small'"),
        ("rms_residual", "[1]"),
        ("last_depth_change", "{}"),
        ("timings", "'fast'"),
        ("timings", "{'total': '1 s'}"),
        ("timings", "[1, 2]"),
        ("estimated_distance", "['far']"),
        ("estimated_distance", "{'a': 1}"),
        ("options", "[1]"),
        ("options", "'x'"),
    ]:
        tag = "".join(ch if ch.isalnum() else "_" for ch in value).strip("_") or "empty"
        damaged(f"summary_{field}_{tag}", C, R + f"edit_json(d / 'summary.json', {field}={value})", "summary.json")
    for field, value in [
        ("distance_check", "[1, 2]"),
        ("distance_check", "'wrong'"),
        ("light_refinement", "'x'"),
        ("light_refinement", "{'changes': 'many'}"),
        ("depth_range", "'abc'"),
        ("depth_range", "[None, 'x']"),
        ("albedo_png_scale", "'x'"),
        ("gauge", "{'x': [1]}"),
        ("status", "'exploded'"),
        ("method", "'magic'"),
    ]:
        tag = "".join(ch if ch.isalnum() else "_" for ch in value).strip("_") or "empty"
        either(f"summary_{field}_{tag}", C, R + f"edit_json(d / 'summary.json', {field}={value})", "summary.json")
    fine("summary_extra_fields", C, R + "edit_json(d / 'summary.json', my_notes='mine', n=[1, 2])")
    fine("summary_rms_nan", C, R + "edit_json(d / 'summary.json', rms_residual=float('nan'))")
    fine("summary_rms_null", C, R + "edit_json(d / 'summary.json', rms_residual=None, last_depth_change=None)")
    fine("summary_minimal_fields", C, R + "s = summary(d); write_json(d / 'summary.json', {'shape': s['shape']})")
    damaged(
        "summary_shape_other_result",
        C,
        R + "edit_json(d / 'summary.json', shape=[32, 32])",
        ("npy", "png"),
    )

    # --- depth.npy --------------------------------------------------------------------------------------
    C = "readers/depth.npy"
    DN = "(d / 'depth.npy')"
    damaged(
        "depth_truncated",
        C,
        R + f"b = {DN}.read_bytes(); write_bytes({DN}, b[: len(b) // 2])",
        "depth.npy",
        BOTH,
    )
    damaged("depth_empty", C, R + f"write_bytes({DN}, b'')", "depth.npy", BOTH)
    damaged("depth_text", C, R + f"write_text({DN}, 'hello')", "depth.npy", BOTH)
    damaged("depth_header_only", C, R + f"write_bytes({DN}, {DN}.read_bytes()[:128])", "depth.npy", BOTH)
    damaged("depth_claims_100000_squared", C, R + f"npy_claiming({DN}, (100000, 100000))", "depth.npy", BOTH)
    damaged("depth_claims_2pow40", C, R + f"npy_claiming({DN}, (2**40, 2))", "depth.npy", BOTH)
    damaged("depth_claims_negative", C, R + f"npy_claiming({DN}, (-17, 17))", "depth.npy", BOTH)
    damaged("depth_claims_17x17_short", C, R + f"npy_claiming({DN}, (17, 17))", "depth.npy", BOTH)
    damaged(
        "depth_pickled_object",
        C,
        R + f"np.save({DN}, np.array([{{'a': 1}}], dtype=object), allow_pickle=True)",
        "depth.npy",
        BOTH,
    )
    damaged("depth_complex", C, R + f"np.save({DN}, np.load({DN}) + 1j)", "depth.npy", BOTH)
    damaged("depth_strings", C, R + f"np.save({DN}, np.full((17, 17), 'a'))", "depth.npy", BOTH)
    damaged("depth_structured", C, R + f"np.save({DN}, np.zeros((17, 17), dtype=[('a', 'f8')]))", "depth.npy", BOTH)
    damaged("depth_1d", C, R + f"np.save({DN}, np.load({DN}).ravel())", "depth.npy", BOTH)
    damaged("depth_3d", C, R + f"np.save({DN}, np.load({DN})[..., None])", "depth.npy", BOTH)
    damaged("depth_scalar", C, R + f"np.save({DN}, np.float64(200))", "depth.npy", BOTH)
    damaged("depth_value_1e300", C, R + f"z = np.load({DN}); z[8, 8] = 1e300; np.save({DN}, z)", "depth.npy", BOTH)
    damaged("depth_value_inf", C, R + f"z = np.load({DN}); z[8, 8] = np.inf; np.save({DN}, z)", "depth.npy", BOTH)
    damaged("depth_is_directory", C, R + f"{DN}.unlink(); {DN}.mkdir()", "depth.npy", BOTH)
    damaged("depth_fifo", C, R + f"{DN}.unlink(); os.mkfifo({DN})", "depth.npy", BOTH)
    unreadable("depth_symlink_loop", C, R + f"{DN}.unlink(); os.symlink({DN}, {DN})", "depth.npy", BOTH)
    damaged("depth_wrong_size", C, R + f"np.save({DN}, np.full((16, 16), 200.0))", "depth.npy", ("report",))
    p.cli(
        "view.depth_wrong_size",
        C,
        "view {tmp}/r --no-open",
        p.exits(2, "depth.npy", check="one_line(err, 'depth.npy')"),
        setup=R + f"np.save({DN}, np.full((16, 16), 200.0))",
    )
    p.cli(
        "view.depth_of_another_result",
        C,
        "view {tmp}/r --no-open",
        p.exits(2, ("same result", "differ", "depth.npy"), check="one_line(err)"),
        setup=R + f"np.save({DN}, np.load({DN}) + 50.0)",
    )
    p.cli(
        "view.depth_missing",
        C,
        "view {tmp}/r --no-open",
        p.exits(2, "depth.npy", check="one_line(err, 'missing')"),
        setup=R + f"{DN}.unlink()",
    )
    fine("depth_float32", C, R + f"np.save({DN}, np.load({DN}).astype(np.float32))", BOTH)
    fine("depth_big_endian", C, R + f"np.save({DN}, np.load({DN}).astype('>f8'))", BOTH)
    fine("depth_fortran_order", C, R + f"np.save({DN}, np.asfortranarray(np.load({DN})))", BOTH)
    fine(
        "depth_npy_version_2",
        C,
        R + f"z = np.load({DN})\nwith open({DN}, 'wb') as f:\n    np.lib.format.write_array(f, z, version=(2, 0))",
        BOTH,
    )
    fine("depth_missing_report", C, R + f"{DN}.unlink()")

    # --- the other maps ---------------------------------------------------------------------------------
    C = "readers/maps"
    # normals.npy is read when mask.png is missing (the mask then comes from the finite normals).
    for f, shape in [("normals.npy", "(16, 16, 3)"), ("residual.npy", "(16, 16)"), ("lights_used.npy", "(16, 16)")]:
        FN = f"(d / {f!r})"
        stem = f.split(".")[0]
        R = "d = result()\n" + ("(d / 'mask.png').unlink()\n" if f == "normals.npy" else "")
        damaged(f"{stem}_truncated", C, R + f"b = {FN}.read_bytes(); write_bytes({FN}, b[: len(b) // 2])", f)
        damaged(f"{stem}_text", C, R + f"write_text({FN}, 'x')", f)
        damaged(f"{stem}_claims_huge", C, R + f"npy_claiming({FN}, (100000, 100000) + {shape}[2:])", f)
        damaged(f"{stem}_wrong_shape", C, R + f"np.save({FN}, np.zeros((8, 8) + {shape}[2:]))", f)
        damaged(f"{stem}_complex", C, R + f"np.save({FN}, np.load({FN}) + 1j)", f)
        damaged(f"{stem}_pickled", C, R + f"np.save({FN}, np.array([None], dtype=object), allow_pickle=True)", f)
        fine(f"{stem}_missing", C, R + f"{FN}.unlink()")
    damaged(
        "normals_two_components",
        C,
        R + "(d / 'mask.png').unlink(); np.save(d / 'normals.npy', np.zeros((16, 16, 2)))",
        "normals.npy",
    )
    fine(
        "normals_nan_outside",
        C,
        R
        + "(d / 'mask.png').unlink(); n = np.load(d / 'normals.npy'); n[0, 0] = np.nan; np.save(d / 'normals.npy', n)",
    )
    R = "d = result()\n"
    damaged("residual_inf_claim", C, R + "npy_claiming(d / 'residual.npy', (16, 16), '<f8', b'')", "residual.npy")
    for f in ("mask.png", "albedo.png", "normals.png", "shaded.png", "inputs.png"):
        FN = f"(d / {f!r})"
        stem = f.split(".")[0]
        # shaded.png is not read by the report (it renders the mesh itself): read or ignored, never a traceback.
        damaged = damaged_or_either if f == "shaded.png" else damaged_only
        damaged(f"{stem}_png_text", C, R + f"write_text({FN}, 'not a png')", f)
        damaged(f"{stem}_png_truncated", C, R + f"b = {FN}.read_bytes(); write_bytes({FN}, b[: len(b) // 2])", f)
        damaged(f"{stem}_png_bomb", C, R + f"png_header_only({FN}, 60000, 60000)", f)
        if f != "inputs.png":
            damaged(f"{stem}_png_wrong_size", C, R + f"png({FN}, np.zeros((8, 8), np.uint8))", f)
        fine(f"{stem}_png_missing", C, R + f"{FN}.unlink()")
    damaged = damaged_only
    fine("mask_png_rgb", C, R + "m = iio.imread(d / 'mask.png'); png(d / 'mask.png', np.stack([m] * 3, -1))")
    fine("mask_png_16bit", C, R + "m = iio.imread(d / 'mask.png'); png(d / 'mask.png', m.astype(np.uint16) * 257)")

    # --- history.csv, distance_curve.csv, held_out.json, rig.json ------------------------------------------
    C = "readers/tables"
    H = "(d / 'history.csv')"
    damaged("history_two_columns", C, R + f"write_text({H}, 'iteration,rms\\n1,0.1\\n')", "history.csv")
    damaged("history_text", C, R + f"write_text({H}, 'hello world')", "history.csv")
    damaged("history_binary", C, R + f"write_bytes({H}, bytes(range(256)) * 4)", "history.csv")
    damaged(
        "history_non_numeric",
        C,
        R + f"t = {H}.read_text().splitlines(); t[1] = ','.join(['x'] * len(t[1].split(','))); "
        f"write_text({H}, '\\n'.join(t))",
        "history.csv",
    )
    damaged(
        "history_ragged_row",
        C,
        R + f"t = {H}.read_text().splitlines(); t[1] = t[1] + ',7,8'; write_text({H}, '\\n'.join(t))",
        "history.csv",
    )
    damaged(
        "history_huge_line",
        C,
        R + f"write_text({H}, {H}.read_text().splitlines()[0] + '\\n' + '1' * (30 << 20))",
        "history.csv",
    )
    either("history_header_only", C, R + f"write_text({H}, {H}.read_text().splitlines()[0] + '\\n')", "history.csv")
    either("history_empty", C, R + f"write_text({H}, '')", "history.csv")
    fine("history_missing", C, R + f"{H}.unlink()")
    fine("history_crlf", C, R + f"write_bytes({H}, {H}.read_bytes().replace(b'\\n', b'\\r\\n'))")
    DC = "(d / 'distance_curve.csv')"
    damaged("distance_curve_text", C, RA + f"write_text({DC}, 'nonsense')", "distance_curve.csv")
    damaged("distance_curve_one_column", C, RA + f"write_text({DC}, 'distance\\n100\\n200\\n')", "distance_curve.csv")
    damaged("distance_curve_binary", C, RA + f"write_bytes({DC}, bytes(range(256)))", "distance_curve.csv")
    fine("auto_result", C, RA)
    fine("distance_curve_missing", C, RA + f"{DC}.unlink()")
    HO = "(d / 'held_out.json')"
    damaged("held_out_list", C, R + f"write_json({HO}, [1, 2, 3])", "held_out.json")
    damaged("held_out_text", C, R + f"write_text({HO}, 'nope')", "held_out.json")
    damaged("held_out_fields", C, R + f"write_json({HO}, {{'near': 'x', 'parallel': 5}})", "held_out.json")
    damaged("held_out_deep", C, R + f"write_text({HO}, '[' * 50000 + ']' * 50000)", "held_out.json")
    RJ = "(d / 'rig.json')"
    damaged("rig_invalid_json", C, R + f"write_text({RJ}, '{{')", "rig.json")
    damaged("rig_not_object", C, R + f"write_json({RJ}, [1])", "rig.json")
    damaged("rig_deep_nesting", C, R + f"write_text({RJ}, '[' * 100000 + ']' * 100000)", "rig.json")
    damaged(
        "rig_bad_light",
        C,
        R + f"r = json.loads({RJ}.read_text()); r['lights'][0]['position'] = 'x'; write_json({RJ}, r)",
        "rig.json",
    )
    fine("rig_missing", C, R + f"{RJ}.unlink()")
    fine("pinhole_result", C, "d = result(kind='pinhole')\n", BOTH)
    fine("own_result", C, R, BOTH)
    fine("report_html_garbage", C, R + "write_text(d / 'report.html', '<script>')")

    # --- mesh.ply ------------------------------------------------------------------------------------------
    C = "readers/mesh.ply"
    PL = "(d / 'mesh.ply')"

    def recount(element: str, count: str) -> str:
        """Setup code: mesh.ply's header claims ``count`` elements ``element`` (the data unchanged)."""
        edited = f"re.sub(r'element {element} \\d+', 'element {element} {count}', head)"
        return f"import re; write_bytes({PL}, {edited}.encode() + b[i:])"

    HEAD = f"b = {PL}.read_bytes(); i = b.index(b'end_header\\n') + 11; head = b[:i].decode()\n"
    damaged(
        "ply_claims_1e30_vertices",
        C,
        R + HEAD + recount("vertex", "1000000000000000000000000000000"),
        "mesh.ply",
        ("view",),
    )
    damaged(
        "ply_claims_2pow40_faces",
        C,
        R + HEAD + recount("face", "1099511627776"),
        "mesh.ply",
        ("view",),
    )
    damaged(
        "ply_negative_count",
        C,
        R + HEAD + recount("vertex", "-5"),
        "mesh.ply",
        ("view",),
    )
    damaged(
        "ply_face_index_past_vertices",
        C,
        R + "import re\n" + HEAD + "n = int(re.search(r'element vertex (\\d+)', head).group(1))\n"
        "body = bytearray(b[i:]); body[-12:-8] = (n + 5).to_bytes(4, 'little'); "
        f"write_bytes({PL}, b[:i] + bytes(body))",
        "mesh.ply",
        ("view",),
    )
    damaged(
        "ply_truncated",
        C,
        R + f"b = {PL}.read_bytes(); write_bytes({PL}, b[: len(b) // 2])",
        "mesh.ply",
        ("view",),
    )
    damaged("ply_header_only", C, R + HEAD + f"write_bytes({PL}, b[:i])", "mesh.ply", ("view",))
    damaged(
        "ply_no_end_header",
        C,
        R + f"write_text({PL}, 'ply\\nformat binary_little_endian 1.0\\n')",
        "mesh.ply",
        ("view",),
    )
    damaged("ply_text", C, R + f"write_text({PL}, 'not a mesh')", "mesh.ply", ("view",))
    damaged("ply_empty", C, R + f"write_bytes({PL}, b'')", "mesh.ply", ("view",))
    damaged("ply_huge_header", C, R + f"write_text({PL}, 'ply\\n' + 'comment x\\n' * 3000000)", "mesh.ply", ("view",))
    damaged(
        "ply_unknown_property_type",
        C,
        R + HEAD + f"write_bytes({PL}, head.replace('property float x', 'property quux x', 1).encode() + b[i:])",
        "mesh.ply",
        ("view",),
    )
    damaged(
        "ply_big_endian_claim",
        C,
        R + HEAD + f"write_bytes({PL}, head.replace('binary_little_endian', 'binary_big_endian').encode() + b[i:])",
        "mesh.ply",
        ("view",),
    )
    damaged("ply_fifo", C, R + f"{PL}.unlink(); os.mkfifo({PL})", "mesh.ply", ("view",))
    p.cli(
        "view.ply_of_another_result",
        C,
        "view {tmp}/r --no-open",
        p.exits(2, ("same result", "mesh.ply"), check="one_line(err)"),
        setup=R + "s = nplps.make_scene('sphere', n=12); nplps.reconstruct(s.images, s.rig, mask=s.mask, "
        "depth=s.mean_depth).save_ply(d / 'mesh.ply')",
    )
    p.cli(
        "view.ply_vertex_nan",
        C,
        "view {tmp}/r --no-open",
        p.exits(2, "mesh.ply", check="one_line(err, 'mesh.ply')"),
        setup=R
        + HEAD
        + f"body = bytearray(b[i:]); body[0:4] = bytes.fromhex('0000c07f'); write_bytes({PL}, b[:i] + bytes(body))",
    )
    p.cli(
        "view.ply_missing",
        C,
        "view {tmp}/r --no-open",
        p.exits(2, "mesh.ply", check="one_line(err, 'missing')"),
        setup=R + f"{PL}.unlink()",
    )
    fine("ply_opengl_frame", C, "s = S; r0 = rec(); r0.save(tmp / 'r', opengl=True)\n", ("view",))
    fine("ply_missing_report", C, R + f"{PL}.unlink()")

    # --- not result folders ---------------------------------------------------------------------------------
    C = "readers/not a result"
    for command in ("report", "view"):
        extra = " --no-open" if command == "view" else ""
        p.cli(f"{command}.missing_dir", C, f"{command} {{tmp}}/nope{extra}", p.exits(2, "nope", check="one_line(err)"))
        p.cli(
            f"{command}.a_file",
            C,
            f"{command} {{tmp}}/f.txt{extra}",
            p.exits(2, "f.txt", check="one_line(err)"),
            setup="write_text('f.txt', 'x')",
        )
        p.cli(
            f"{command}.empty_dir",
            C,
            f"{command} {{tmp}}/e{extra}",
            p.exits(2, "e", check="one_line(err)"),
            setup="(tmp / 'e').mkdir()",
        )
        p.cli(
            f"{command}.scene_folder",
            C,
            f"{command} {{SC}}{extra}",
            p.exits(2, "scene", check="one_line(err)"),
        )
