# ruff: noqa: E501  (tables of snippets)
"""Probes: memory. ``max_memory`` as a user writes it (strings with units, numbers, nonsense),
and shapes far beyond the machine (broadcast arrays, so that nothing big exists before nplps
allocates): a MemoryError or a MemoryLimitError, never an abort, whatever ``max_memory`` says.
The workers run under a 3 GiB address-space cap.
"""

from __future__ import annotations

from typing import Any

HUGE = "J = np.broadcast_to(np.float32(0.5), (27, 20000, 20000))\n"
HUGE3 = "J = np.broadcast_to(np.float32(0.5), (3, 20000, 20000)); Rg = orth([[30, 0, 50.0], [-15, 26, 50], [-15, -26, 50]])\n"


def add(p: Any) -> None:
    C = "memory/max_memory"
    for tag, value in [
        ("1e30_string", "'1e30'"),
        ("100_GB", "'100 GB'"),
        ("8GB", "'8GB'"),
        ("512MiB", "'512MiB'"),
        ("spaces_case", "'  2 gib '"),
        ("bytes_string", "'4000000000'"),
        ("float", "4e9"),
        ("int", "4 * 2**30"),
        ("numpy_int", "np.int64(2**32)"),
        ("tb", "'1 TB'"),
        ("fraction_gb", "'0.5 GB'"),
    ]:
        p.api(f"max_memory.{tag}", C, f"r = rec(max_memory={value})", p.ok("good(r)"))
    for tag, value in [
        ("zero", "0"),
        ("zero_string", "'0'"),
        ("negative", "-1"),
        ("negative_gb", "'-1 GB'"),
        ("nan", "np.nan"),
        ("nan_string", "'nan GB'"),
        ("unit_only", "'GB'"),
        ("unknown_unit", "'8 XB'"),
        ("double_unit", "'8 GB GB'"),
        ("words", "'lots'"),
        ("empty", "''"),
        ("bool", "True"),
        ("list", "[8]"),
        ("complex", "1j"),
        ("comma", "'8,5 GB'"),
    ]:
        p.api(f"max_memory.{tag}", C, f"rec(max_memory={value})", p.raises("InputError", "max_memory"))
    for tag, value in [("inf_float", "np.inf"), ("inf_string", "'inf'"), ("1e400_gb", "'1e400 GB'")]:
        p.api(f"max_memory.{tag}", C, f"r = rec(max_memory={value})", p.either("good(r)", "InputError", "max_memory"))
    for tag, value in [("1_kB", "'1 kB'"), ("one_byte", "1"), ("1_MiB", "'1 MiB'")]:
        p.api(
            f"max_memory.too_small_{tag}",
            C,
            f"rec(max_memory={value})",
            p.raises("MemoryLimitError", "memory", "max_memory"),
        )
    p.api("max_memory.parallel_too_small", C, "par(max_memory='1 kB')", p.raises("MemoryLimitError", "memory"))
    p.api("max_memory.parallel_words", C, "par(max_memory='lots')", p.raises("InputError", "max_memory"))
    p.api(
        "max_memory.auto_too_small", C, "rec(depth='auto', max_memory='1 kB')", p.raises("MemoryLimitError", "memory")
    )
    p.api(
        "max_memory.error_is_memory_error",
        C,
        "try:\n    rec(max_memory='1 kB')\nexcept MemoryError as e:\n    caught = e",
        p.ok("isinstance(caught, nplps.NplpsError)"),
    )
    # Huge shapes: the limit of the caller does not make nplps abort.
    C = "memory/huge"
    for tag, value in [("default", None), ("1e30", "'1e30'"), ("100_GB", "'100 GB'"), ("1e12_bytes", "1e12")]:
        kw = "" if value is None else f", max_memory={value}"
        p.api(
            f"memory.huge_27_lights_{tag}", C, HUGE + f"rec(images=J, mask=None{kw})", p.mem(), isolate=True, budget=90
        )
        p.api(
            f"memory.huge_3_lights_{tag}",
            C,
            HUGE3 + f"rec(images=J, rig=Rg, mask=None{kw})",
            p.mem(),
            isolate=True,
            budget=90,
        )
    p.api(
        "memory.huge_parallel_1e30",
        C,
        HUGE + "par(images=J, mask=None, max_memory='1e30')",
        p.mem(),
        isolate=True,
        budget=90,
    )
    p.api(
        "memory.huge_auto_1e30",
        C,
        HUGE3 + "rec(images=J, rig=Rg, mask=None, depth='auto', max_memory='1e30')",
        p.mem(),
        isolate=True,
        budget=90,
    )
    p.api(
        "memory.huge_refine_1e30",
        C,
        HUGE3 + "rec(images=J, rig=Rg, mask=None, refine_lights='intensity', max_memory='1e30')",
        p.mem(),
        isolate=True,
        budget=90,
    )
    p.api(
        "memory.huge_mask_one_pixel_1e30",
        C,
        HUGE3
        + "m = np.zeros((20000, 20000), bool); m[5, 5] = True\nr = rec(images=J, rig=Rg, mask=m, max_memory='1e30')",
        p.either("honest(r)", "MemoryError", ""),
        isolate=True,
        budget=90,
    )
    p.api(
        "memory.render_huge_1e30",
        C,
        "nplps.render(np.broadcast_to(200.0, (30001, 30001)), R)",
        p.mem(),
        isolate=True,
        budget=60,
    )
    p.api("memory.scene_huge", C, "nplps.make_scene('bumps', n=40000)", p.mem(), isolate=True, budget=60)
    p.api(
        "memory.still_works_after_memory_error",
        C,
        HUGE3
        + "try:\n    rec(images=J, rig=Rg, mask=None, max_memory='1e30')\nexcept MemoryError:\n    pass\nr = rec()",
        p.ok("good(r)"),
        isolate=True,
        budget=90,
    )
    # The command line.
    C = "memory/cli"
    RC = "reconstruct {SC} --rig {SC}/rig.json --mask {SC}/mask.png --depth 200 -q --out {tmp}/out"
    for tag, value in [("1e30", "1e30"), ("100GB", "'100 GB'"), ("512MiB", "512MiB")]:
        p.cli(f"cli.max_memory_{tag}", C, RC + f" --max-memory {value}", p.exits(0))
    for tag, value in [("words", "lots"), ("zero", "0"), ("negative", "-5"), ("unit_only", "GB"), ("nan", "nan")]:
        p.cli(
            f"cli.max_memory_{tag}",
            C,
            RC + f" --max-memory {value}",
            p.exits(2, ("--max-memory", "max_memory"), check="len(err.strip().splitlines()) == 1"),
        )
    p.cli(
        "cli.max_memory_too_small",
        C,
        RC + " --max-memory 1kB",
        p.exits(
            (1, 2), "memory", check="len(err.strip().splitlines()) <= 2 and not (tmp / 'out' / 'summary.json').exists()"
        ),
    )
