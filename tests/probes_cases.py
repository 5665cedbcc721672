"""Bad-input probes of issue 9 ("never abort, never hang, never lie"): the cases, and the worker
that runs them.

Each case is a small Python snippet (``api``) or a command line with the files it needs
(``cli``), plus what a demanding user expects of it:

* ``ok(check)``: a result, and an honest one: ``check`` (a Python expression over the snippet's
  variables, e.g. ``good(r)``) holds;
* ``raises(cls, *fragments)``: an exception of class ``cls`` (an nplps class unless the case is
  about the user's own exception) whose message contains every fragment (a fragment may be a
  tuple of alternatives; case-insensitive, and "_" matches a space), normally the name of the
  offending argument;
* ``either(check, cls, *fragments)``: one of the two (for inputs where both answers are fine);
* ``mem(*fragments)``: ``MemoryError``, or an nplps exception mentioning memory (or a fragment);
* ``exits(codes, *fragments, check=...)``: a command line's exit status is in ``codes``, its
  stderr holds every fragment and never a Python traceback.

The expectations are what the user should get, not what the code does today. The runner lives
in ``tests/test_probes.py``; ``python tests/probes_cases.py --worker RESULTS ID...`` runs cases
in one interpreter and appends a JSON line per case (a ``start`` line before it, an ``end`` line
after it) to RESULTS, so that the runner can pin a crash or a hang on its case.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shlex
import sys
import time
from typing import Any

# --------------------------------------------------------------------------------------------------
# Case definitions
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Case:
    id: str
    category: str
    #: "api" (a Python snippet) or "cli" (a command line).
    kind: str
    #: api: the snippet; cli: setup code run before the command.
    code: str
    expect: dict
    #: cli: the command line after ``nplps`` ({tmp}, {SC}, {PSC} are replaced by paths).
    argv: str = ""
    #: Seconds before the case counts as hung.
    budget: float = 10.0
    #: Run in a process of its own (cases that allocate a lot or that may abort).
    isolate: bool = False
    #: cli: run ``python -m nplps`` in a subprocess instead of calling ``nplps.cli.main``.
    proc: bool = False


def ok(check: str | None = None) -> dict:
    return {"kind": "ok", "check": check}


def raises(cls: str, *fragments: Any) -> dict:
    return {"kind": "raises", "cls": cls, "fragments": [list(f) if isinstance(f, tuple) else [f] for f in fragments]}


def either(check: str | None, cls: str, *fragments: Any) -> dict:
    return {"kind": "either", "check": check, **{k: v for k, v in raises(cls, *fragments).items() if k != "kind"}}


def mem(*fragments: str) -> dict:
    return {"kind": "mem", "fragments": [["memory", *fragments]]}


def exits(codes: int | tuple[int, ...], *fragments: Any, check: str | None = None) -> dict:
    codes = (codes,) if isinstance(codes, int) else tuple(codes)
    return {
        "kind": "exit",
        "codes": list(codes),
        "fragments": [list(f) if isinstance(f, tuple) else [f] for f in fragments],
        "check": check,
    }


def describe(expect: dict) -> str:
    """The expectation in a few words (for the table and the failure messages)."""

    def frags(fs: list[list[str]]) -> str:
        return " & ".join("/".join(repr(a) for a in f) for f in fs)

    kind = expect["kind"]
    if kind == "ok":
        return "ok" + (f": {expect['check']}" if expect["check"] else "")
    if kind == "raises":
        return f"{expect['cls']}" + (f" ∋ {frags(expect['fragments'])}" if expect["fragments"] else "")
    if kind == "either":
        ok_part = "ok" + (f": {expect['check']}" if expect["check"] else "")
        return f"{ok_part} | {expect['cls']}" + (f" ∋ {frags(expect['fragments'])}" if expect["fragments"] else "")
    if kind == "mem":
        return f"MemoryError | NplpsError ∋ {frags(expect['fragments'])}"
    if kind == "exit":
        codes = "/".join(str(c) for c in expect["codes"])
        text = f"exit {codes}" + (f", stderr ∋ {frags(expect['fragments'])}" if expect["fragments"] else "")
        text += ", no traceback"
        return text + (f"; {expect['check']}" if expect["check"] else "")
    return kind


CASES: list[Case] = []


def api(id: str, category: str, code: str, expect: dict, **kw: Any) -> None:
    CASES.append(Case(id, category, "api", code, expect, **kw))


def cli(id: str, category: str, argv: str, expect: dict, setup: str = "", **kw: Any) -> None:
    CASES.append(Case(id, category, "cli", setup, expect, argv=argv, **kw))


STATUSES = ("converged", "stalled", "diverged", "degenerate")

# --- reconstruct: images ---------------------------------------------------------------------------
C = "reconstruct/images"
api("images.ndim2", C, "rec(images=I[0])", raises("InputError", "image"))
api("images.ndim5", C, "rec(images=I[..., None, None])", raises("InputError", "image"))
api("images.fewer_than_lights", C, "rec(images=I[:5])", raises("InputError", "image", "27"))
api("images.more_than_lights", C, "rec(images=np.concatenate([I, I[:1]]))", raises("InputError", "image", "27"))
api("images.empty_stack", C, "rec(images=I[:0])", raises("InputError", "image"))
api("images.empty_list", C, "rec(images=[])", raises("InputError", "image"))
api("images.zero_height", C, "rec(images=np.zeros((27, 0, 16)), mask=None)", raises("InputError", "image"))
api("images.one_pixel", C, "r = rec(images=I[:, :1, :1], mask=None)", either("honest(r)", "InputError", "image"))
api("images.nan", C, "J = I.copy(); J[3, 5, 5] = np.nan; rec(images=J)", raises("InputError", "image 3"))
api("images.inf", C, "J = I.copy(); J[3, 5, 5] = np.inf; rec(images=J)", raises("InputError", "image 3"))
api("images.neg_inf", C, "J = I.copy(); J[4, 0, 0] = -np.inf; rec(images=J)", raises("InputError", "image 4"))
api("images.all_nan", C, "rec(images=np.full(I.shape, np.nan))", raises("InputError", "image"))
api(
    "images.some_negative",
    C,
    "J = I.copy(); J[0, :4] = -0.1; r = rec(images=J)",
    ok("honest(r) and r.converged and warned('negative')"),
)
api("images.all_negative", C, "rec(images=-np.ones_like(I))", raises("InputError", "observations"))
api("images.all_zero", C, "rec(images=np.zeros_like(I))", raises("InputError", "observations"))
api(
    "images.constant",
    C,
    "r = rec(images=np.full_like(I, 0.5))",
    ok("honest(r) and r.history[-1].rms_residual > 1e-2"),
)
api("images.complex", C, "rec(images=I.astype(complex))", raises("InputError", "image", "complex"))
api("images.object_dtype", C, "rec(images=I.astype(object))", raises("InputError", "image"))
api("images.strings", C, "rec(images=np.full(I.shape, 'a'))", raises("InputError", "image"))
api("images.bool", C, "r = rec(images=I > np.median(I))", either("honest(r)", "InputError", "image"))
api("images.scaled_1e30", C, "r = rec(images=I * 1e30)", ok("good(r)"))
api("images.scaled_1e-30", C, "r = rec(images=I * 1e-30)", ok("good(r)"))
api("images.beyond_float32", C, "r = rec(images=I * 1e40)", either("good(r)", "InputError", "image"))
api("images.list_of_arrays", C, "r = rec(images=list(I))", ok("good(r)"))
api("images.nested_lists", C, "r = rec(images=I.tolist())", ok("good(r)"))
api("images.generator", C, "r = rec(images=(x for x in I))", ok("good(r)"))
api("images.list_wrong_size", C, "rec(images=list(I[:-1]) + [np.zeros((8, 8))])", raises("InputError", "image 26"))
api("images.list_with_none", C, "rec(images=list(I[:-1]) + [None])", raises("InputError", "image 26"))
api("images.single_path", C, "rec(images='photo.png')", raises("InputError", "photo.png"))
api("images.int", C, "rec(images=12)", raises("InputError", "images"))
api("images.none", C, "rec(images=None)", raises("InputError", "images"))
api("images.dict", C, "rec(images={'a': I[0]})", raises("InputError", "image"))
api(
    "images.rgb",
    C,
    "r = rec(images=np.repeat(I[..., None], 3, axis=-1))",
    ok("good(r) and r.albedo.shape == (16, 16, 3)"),
)
api(
    "images.rgba_array",
    C,
    "r = rec(images=np.repeat(I[..., None], 4, axis=-1))",
    either("good(r)", "InputError", "image"),
)
api("images.one_channel_axis", C, "r = rec(images=I[..., None])", either("good(r)", "InputError", "image"))
api("images.color_true_on_grey", C, "rec(color=True)", raises("InputError", "color"))
api(
    "images.color_string",
    C,
    "rec(images=np.repeat(I[..., None], 3, axis=-1), color='no')",
    raises("InputError", "color"),
)
api("images.uint8", C, "r = rec(images=np.round(I / I.max() * 255).astype(np.uint8))", ok("honest(r) and r.converged"))
api("images.uint16", C, "r = rec(images=np.round(I / I.max() * 65535).astype(np.uint16))", ok("good(r)"))
api("images.int64", C, "r = rec(images=np.round(I / I.max() * 65535).astype(np.int64))", ok("good(r)"))
api("images.float16", C, "r = rec(images=I.astype(np.float16))", ok("good(r, tol=2.0)"))
api("images.fortran_order", C, "r = rec(images=np.asfortranarray(I))", ok("good(r)"))
api("images.strided_view", C, "r = rec(images=np.repeat(I, 2, axis=2)[:, :, ::2])", ok("good(r)"))
api(
    "images.readonly",
    C,
    "J = I.astype(np.float32); J.setflags(write=False); r = rec(images=J)",
    ok("good(r)"),
)
api(
    "images.caller_array_untouched",
    C,
    "J = I.astype(np.float32); J[0, 0, 0] = 0.0; K0 = J.copy()\n"
    "v = np.ones(J.shape, bool); v[1, 2, 2] = False\n"
    "r = rec(images=J, valid=v)",
    ok("good(r) and np.array_equal(J, K0)"),
)

# --- reconstruct: mask -----------------------------------------------------------------------------
C = "reconstruct/mask"
api("mask.wrong_shape", C, "rec(mask=np.ones((8, 8), bool))", raises("InputError", "mask"))
api("mask.one_column_more", C, "rec(mask=np.ones((16, 17), bool))", raises("InputError", "mask"))
api("mask.all_false", C, "rec(mask=np.zeros((16, 16), bool))", raises("InputError", "mask"))
api("mask.all_nan", C, "rec(mask=np.full((16, 16), np.nan))", raises("InputError", "mask"))
api("mask.strings", C, "rec(mask=np.full((16, 16), 'x'))", raises("InputError", "mask"))
api("mask.object", C, "rec(mask=np.ones((16, 16), object))", raises("InputError", "mask"))
api("mask.complex", C, "rec(mask=np.ones((16, 16), complex))", raises("InputError", "mask"))
api("mask.ndim1", C, "rec(mask=np.ones(256, bool))", raises("InputError", "mask"))
api("mask.ndim4", C, "rec(mask=np.ones((16, 16, 3, 1), bool))", raises("InputError", "mask"))
api("mask.scalar", C, "rec(mask=True)", raises("InputError", "mask"))
api("mask.rgb", C, "r = rec(mask=np.repeat(M[..., None], 3, axis=-1))", ok("good(r)"))
api("mask.list", C, "r = rec(mask=M.tolist())", ok("good(r)"))
api("mask.uint8_255", C, "r = rec(mask=M.astype(np.uint8) * 255)", ok("good(r)"))
api("mask.missing_file", C, "rec(mask=str(tmp / 'nothere.png'))", raises("InputError", ("mask", "nothere.png")))
api("mask.text_file", C, "p = write_text('m.png', 'hello'); rec(mask=str(p))", raises("InputError", ("mask", "m.png")))
api(
    "mask.file_wrong_size",
    C,
    "p = png('m.png', np.full((8, 8), 255, np.uint8)); rec(mask=str(p))",
    raises("InputError", "mask"),
)
api(
    "mask.file_black",
    C,
    "p = png('m.png', np.zeros((16, 16), np.uint8)); rec(mask=str(p))",
    raises("InputError", "mask"),
)
api("mask.single_pixel", C, "m = np.zeros((16, 16), bool); m[8, 8] = True; r = rec(mask=m)", ok("honest(r)"))
api("mask.checkerboard", C, "m = (np.indices((16, 16)).sum(0) % 2).astype(bool); r = rec(mask=m)", ok("honest(r)"))
api("mask.one_row", C, "m = np.zeros((16, 16), bool); m[8] = True; r = rec(mask=m)", ok("honest(r)"))

# --- reconstruct: depth ----------------------------------------------------------------------------
C = "reconstruct/depth"
for name, value in [("nan", "np.nan"), ("inf", "np.inf"), ("negative", "-200.0"), ("zero", "0.0"), ("none", "None")]:
    api(f"depth.{name}", C, f"rec(depth={value})", raises("InputError", "depth"))
api(
    "depth.1e300",
    C,
    "r = rec(depth=1e300)",
    either("r.status in ('degenerate', 'diverged')", "InputError", "depth"),
)
api("depth.1e-300_lights_behind", C, "rec(depth=1e-300)", raises("InputError", ("depth", "light")))
api("depth.between_lights", C, "rec(depth=20.0)", raises("InputError", ("depth", "light")))
api("depth.complex", C, "rec(depth=200 + 1j)", raises("InputError", "depth"))
api("depth.string_number", C, "rec(depth='200')", raises("InputError", "depth"))
api("depth.AUTO_uppercase", C, "rec(depth='AUTO')", raises("InputError", "depth"))
api("depth.bool", C, "rec(depth=True)", raises("InputError", "depth"))
api("depth.list_one", C, "rec(depth=[200.0])", raises("InputError", "depth"))
api("depth.np_float32", C, "r = rec(depth=np.float32(200))", ok("good(r)"))
api("depth.0d_array", C, "r = rec(depth=np.array(200.0))", ok("good(r)"))
api("depth.decimal", C, "import decimal; r = rec(depth=decimal.Decimal(200))", ok("good(r)"))
api("depth.map_wrong_shape", C, "rec(depth=np.full((16, 16), 200.0))", raises("InputError", "depth"))
api("depth.map_3d", C, "rec(depth=np.full((17, 17, 1), 200.0))", raises("InputError", "depth"))
api("depth.map_nan_inside_mask", C, "z = S.depth.copy(); z[8, 8] = np.nan; rec(depth=z)", raises("InputError", "depth"))
api(
    "depth.map_nan_outside_mask",
    C,
    "m = M.copy(); m[:4] = False; z = S.depth.copy(); z[:3] = np.nan; r = rec(mask=m, depth=z)",
    ok("honest(r) and r.converged"),
)
api("depth.map_all_inf", C, "rec(depth=np.full((17, 17), np.inf))", raises("InputError", "depth"))
api("depth.map_negative", C, "rec(depth=-S.depth)", raises("InputError", ("depth", "light")))
api("depth.map_object", C, "rec(depth=np.full((17, 17), 200.0, dtype=object))", raises("InputError", "depth"))
api("depth.map_strings", C, "rec(depth=np.full((17, 17), 'a'))", raises("InputError", "depth"))
api("depth.map_int", C, "r = rec(depth=np.full((17, 17), 200))", ok("good(r)"))
api("depth.map_lists", C, "r = rec(depth=np.full((17, 17), 200.0).tolist())", ok("good(r)"))
api(
    "depth.map_outlier",
    C,
    "z = S.depth.copy(); z[8, 8] = 1e300; r = rec(depth=z)",
    either("honest(r)", "InputError", "depth"),
)

# --- reconstruct: depth="auto" ---------------------------------------------------------------------
C = "reconstruct/auto"
api("auto.basic", C, "r = rec(depth='auto')", ok("good(r) and r.distance is not None"))
for name, value in [
    ("zero", "(0, 400)"),
    ("negative", "(-1, 400)"),
    ("reversed", "(400, 100)"),
    ("equal", "(100, 100)"),
    ("nan", "(np.nan, 400)"),
    ("inf", "(100, np.inf)"),
    ("string", "'100,400'"),
    ("triple", "(100, 200, 300)"),
    ("scalar", "300"),
    ("none_inside", "(100, None)"),
]:
    api(f"auto.range_{name}", C, f"rec(depth='auto', depth_range={value})", raises("InputError", "depth_range"))
api(
    "auto.range_excludes_truth",
    C,
    "r = rec(depth='auto', depth_range=(1000, 2000))",
    either("warned('range')", "InputError", "depth_range"),
)
api(
    "auto.range_behind_lights",
    C,
    "rec(depth='auto', depth_range=(1, 10))",
    raises("InputError", ("depth_range", "light")),
)
for name, value in [("negative", "-5"), ("zero", "0"), ("nan", "np.nan"), ("inf", "np.inf"), ("string", "'x'")]:
    api(f"auto.guess_{name}", C, f"rec(depth='auto', depth_guess={value})", raises("InputError", "depth_guess"))
api("auto.pinhole", C, "r = nplps.reconstruct(PS.images, PS.rig, mask=PS.mask, depth='auto')", ok("good(r, PS)"))
api("auto.guess_ok", C, "r = rec(depth='auto', depth_guess=200.0)", ok("good(r)"))
api(
    "auto.directional_only",
    C,
    "Rd = orth(directional=[[0.3, 0, -1], [0, 0.3, -1], [-0.3, 0, -1], [0, -0.3, -1], [0.2, 0.2, -1]])\n"
    "rec(images=render_for(Rd), rig=Rd, depth='auto')",
    raises("InputError", ("depth", "auto")),
)
api(
    "auto.three_lights",
    C,
    "rec(images=I[[0, 9, 18]], rig=R.subset([0, 9, 18]), depth='auto')",
    raises("InputError", ("depth", "auto")),
)
api("auto.parallel", C, "par(depth='auto')", raises("InputError", ("depth", "auto")))

# --- reconstruct: solver options -------------------------------------------------------------------
C = "reconstruct/iterations"
for name, value in [
    ("zero", "0"),
    ("negative", "-1"),
    ("string", "'ten'"),
    ("fraction", "2.5"),
    ("bool", "True"),
    ("none", "None"),
    ("inf", "np.inf"),
    ("numeric_string", "'10'"),
    ("huge_negative", "-10**30"),
]:
    api(f"iterations.{name}", C, f"rec(iterations={value})", raises("InputError", "iterations"))
api("iterations.1e9", C, "r = rec(iterations=10**9, tol=1e-3)", ok("good(r)"))
api("iterations.maxsize", C, "r = rec(iterations=sys.maxsize, tol=1e-3)", ok("good(r)"))
api("iterations.2pow64", C, "r = rec(iterations=2**64, tol=1e-3)", either("good(r)", "InputError", "iterations"))
api("iterations.integral_float", C, "r = rec(iterations=10.0)", ok("good(r)"))
api("iterations.numpy_int", C, "r = rec(iterations=np.int64(10))", ok("good(r)"))
api("iterations.one", C, "r = rec(iterations=1, tol=1e-12)", ok("honest(r) and not r.converged"))
api("iterations.1e9_tol0_no_hang", C, "r = rec(iterations=10**9, tol=0)", ok("honest(r)"), budget=20)

C = "reconstruct/tol"
for name, value in [("negative", "-1.0"), ("nan", "np.nan"), ("string", "'x'"), ("complex", "1j"), ("none", "None")]:
    api(f"tol.{name}", C, f"rec(tol={value})", raises("InputError", "tol"))
api("tol.inf", C, "r = rec(tol=np.inf)", either("honest(r)", "InputError", "tol"))
api("tol.zero", C, "r = rec(tol=0.0, iterations=20)", ok("honest(r)"))

C = "reconstruct/prior"
for name, value in [("negative", "-1.0"), ("nan", "np.nan"), ("inf", "np.inf"), ("string", "'a'")]:
    api(
        f"prior.weight_{name}",
        C,
        f"rec(depth_prior=S.depth, prior_weight={value})",
        raises("InputError", "prior_weight"),
    )
api(
    "prior.weight_zero",
    C,
    "r = rec(depth_prior=S.depth, prior_weight=0.0)",
    either("good(r)", "InputError", "prior_weight"),
)
api("prior.exact", C, "r = rec(depth_prior=S.depth)", ok("good(r)"))
api(
    "prior.all_nan", C, "r = rec(depth_prior=np.full((17, 17), np.nan))", either("good(r)", "InputError", "depth_prior")
)
api("prior.wrong_shape", C, "rec(depth_prior=np.ones((16, 16)))", raises("InputError", "depth_prior"))
api("prior.string", C, "rec(depth_prior='x')", raises("InputError", "depth_prior"))
api(
    "prior.inf",
    C,
    "z = S.depth.copy(); z[3, 3] = np.inf; r = rec(depth_prior=z)",
    either("good(r)", "InputError", "depth_prior"),
)
api("prior.complex", C, "rec(depth_prior=S.depth + 1j)", raises("InputError", "depth_prior"))
api(
    "prior.negative_pinhole",
    C,
    "nplps.reconstruct(PS.images, PS.rig, mask=PS.mask, depth=200.0, depth_prior=-PS.depth)",
    raises("InputError", "depth_prior"),
)

C = "reconstruct/thresholds"
for name, value in [("nan", "np.nan"), ("string", "'x'"), ("neg_inf", "-np.inf"), ("inf", "np.inf"), ("complex", "1j")]:
    api(f"dark.{name}", C, f"rec(dark={value})", raises("InputError", "dark"))
api("dark.above_everything", C, "rec(dark=10.0)", raises("InputError", "dark"))
api("dark.negative", C, "r = rec(dark=-0.1)", ok("honest(r)"))
for name, value in [("zero", "0.0"), ("nan", "np.nan"), ("negative", "-1.0"), ("string", "'x'")]:
    api(f"saturation.{name}", C, f"rec(saturation={value})", raises("InputError", "saturation"))
api("saturation.below_everything", C, "rec(saturation=1e-9)", raises("InputError", "saturation"))
api("saturation.below_dark", C, "rec(dark=0.5, saturation=0.2)", raises("InputError", ("saturation", "dark")))

C = "reconstruct/options"
api("weighting.bogus", C, "rec(weighting='bogus')", raises("InputError", "weighting"))
api("weighting.none", C, "r = rec(weighting=None)", either("good(r)", "InputError", "weighting"))
api("weighting.paper", C, "r = rec(weighting='paper')", ok("honest(r) and r.converged"))
api("robust.huber", C, "rec(robust='huber')", raises("InputError", "robust"))
api("robust.true", C, "rec(robust=True)", raises("InputError", "robust"))
api("robust.empty", C, "rec(robust='')", raises("InputError", "robust"))
api("robust.cauchy", C, "r = rec(robust='cauchy')", ok("good(r)"))
api("robust.tukey", C, "r = rec(robust='tukey')", ok("good(r)"))
api("solver.bogus", C, "rec(solver='qr')", raises("InputError", "solver"))
api("solver.none", C, "rec(solver=None)", raises("InputError", "solver"))
api("solver.direct", C, "r = rec(solver='direct')", ok("good(r)"))
api("solver.multigrid", C, "r = rec(solver='multigrid')", ok("good(r)"))
for name, value in [("zero", "0"), ("negative", "-1"), ("string", "'2'"), ("bool", "True")]:
    api(f"levels.{name}", C, f"rec(levels={value})", raises("InputError", "levels"))
api("levels.two", C, "r = rec(levels=2)", ok("good(r)"))
api("levels.integral_float", C, "r = rec(levels=2.0)", either("good(r)", "InputError", "levels"))
api("levels.hundred", C, "r = rec(levels=100)", either("good(r)", "InputError", "levels"))
api("levels.1e30", C, "r = rec(levels=10**30)", either("good(r)", "InputError", "levels"))
api("unknown_keyword", C, "rec(iteration=5)", raises("TypeError", "iteration"))
api("rig.none", C, "rec(rig=None)", raises("InputError", "rig"))
api("rig.dict", C, "rec(rig=R.to_dict())", raises("InputError", "rig"))
api("rig.path", C, "rec(rig=str(SC / 'rig.json'))", raises("InputError", "rig"))

C = "reconstruct/threads"
for name, value in [("zero", "0"), ("negative", "-1"), ("string", "'x'"), ("fraction", "2.5")]:
    api(f"threads.{name}", C, f"rec(threads={value})", raises("InputError", "threads"))
api("threads.one", C, "r = rec(threads=1)", ok("good(r)"))
api("threads.bool", C, "r = rec(threads=True)", either("good(r)", "InputError", "threads"))
api("threads.million", C, "r = rec(threads=10**6)", either("good(r)", "InputError", "threads"), isolate=True)
api("threads.2pow64", C, "r = rec(threads=2**64)", either("good(r)", "InputError", "threads"))
api(
    "threads.concurrent_calls",
    C,
    "import threading\nout = [None] * 4\n"
    "def run(i):\n    out[i] = rec().depth\n"
    "ts = [threading.Thread(target=run, args=(i,)) for i in range(4)]\n"
    "[t.start() for t in ts]; [t.join(15) for t in ts]\nr = rec()",
    ok("all(o is not None and np.array_equal(o, r.depth, equal_nan=True) for o in out)"),
)

C = "reconstruct/progress"
api("progress.string", C, "rec(progress='yes')", raises("InputError", "progress"))
api("progress.int", C, "rec(progress=1)", raises("InputError", "progress"))
api("progress.true", C, "r = rec(progress=True)", ok("good(r)"))
api("progress.callable", C, "its = []; r = rec(progress=its.append)", ok("good(r) and len(its) == len(r.history)"))
api("progress.raises", C, "rec(progress=lambda it: 1 / 0)", raises("ZeroDivisionError"))
api(
    "progress.keyboard_interrupt",
    C,
    "def stop(it):\n    raise KeyboardInterrupt\nrec(progress=stop)",
    raises("KeyboardInterrupt"),
)
api("progress.wrong_signature", C, "rec(progress=lambda: None)", raises("TypeError|InputError"))
api(
    "progress.reentrant",
    C,
    "inner = []; r = rec(progress=lambda it: inner.append(rec(iterations=2)))",
    ok("good(r) and len(inner) == len(r.history)"),
)

C = "reconstruct/valid"
api("valid.wrong_shape", C, "rec(valid=np.ones((27, 8, 8), bool))", raises("InputError", "valid"))
api("valid.per_pixel_only", C, "rec(valid=np.ones((16, 16), bool))", raises("InputError", "valid"))
api("valid.all_false", C, "rec(valid=np.zeros(I.shape, bool))", raises("InputError", ("valid", "observations")))
api("valid.string", C, "rec(valid='x')", raises("InputError", "valid"))
api("valid.lists", C, "r = rec(valid=np.ones(I.shape, bool).tolist())", ok("good(r)"))

C = "reconstruct/refine_lights"
for name, value in [("bogus", "'bogus'"), ("uppercase", "'INTENSITY'"), ("true", "True"), ("int", "1")]:
    api(f"refine.{name}", C, f"rec(refine_lights={value})", raises("InputError", "refine_lights"))
api("refine.intensity", C, "r = rec(refine_lights='intensity')", ok("good(r)"))
api("refine.position", C, "r = rec(refine_lights='position')", ok("honest(r)"))
api("refine.both", C, "r = rec(refine_lights='both')", ok("honest(r)"))
api("refine.false", C, "r = rec(refine_lights=False)", ok("good(r)"))
for name, value in [("negative", "-1.0"), ("nan", "np.nan"), ("inf", "np.inf"), ("string", "'x'"), ("complex", "1j")]:
    api(
        f"refine.prior_weight_{name}",
        C,
        f"rec(refine_lights='position', light_prior_weight={value})",
        raises("InputError", "light_prior_weight"),
    )
api(
    "refine.prior_weight_zero",
    C,
    "r = rec(refine_lights='position', light_prior_weight=0.0)",
    either("honest(r)", "InputError", "light_prior_weight"),
)

# --- reconstruct_parallel --------------------------------------------------------------------------
C = "reconstruct_parallel"
api("parallel.basic", C, "r = par()", ok("honest(r) and r.method == 'parallel'"))
api("parallel.fewer_images", C, "par(images=I[:5])", raises("InputError", "image"))
api("parallel.depth_nan", C, "par(depth=np.nan)", raises("InputError", "depth"))
api("parallel.depth_none", C, "par(depth=None)", raises("InputError", "depth"))
api("parallel.robust_bogus", C, "par(robust='huber')", raises("InputError", "robust"))
api("parallel.dark_string", C, "par(dark='x')", raises("InputError", "dark"))
api("parallel.saturation_zero", C, "par(saturation=0.0)", raises("InputError", "saturation"))
api("parallel.threads_zero", C, "par(threads=0)", raises("InputError", "threads"))
api("parallel.valid_shape", C, "par(valid=np.ones((27, 8, 8), bool))", raises("InputError", "valid"))
api("parallel.all_zero", C, "par(images=np.zeros_like(I))", raises("InputError", "observations"))
api(
    "parallel.collinear_lights",
    C,
    "Rc = orth([[0, 0, 50.0], [0, 0, 80], [0, 0, 110]]); par(images=I[:3], rig=Rc)",
    raises("RigError", "normals"),
)
api("parallel.refine_position", C, "par(refine_lights='position')", raises("InputError", "refine"))
api("parallel.refine_bogus", C, "par(refine_lights='bogus')", raises("InputError", "refine_lights"))
api("parallel.iterations_keyword", C, "par(iterations=5)", raises("TypeError", "iterations"))

# --- make_scene ------------------------------------------------------------------------------------
C = "make_scene"
for name, value in [
    ("negative", "-4"),
    ("zero", "0"),
    ("one", "1"),
    ("float", "16.0"),
    ("string", "'16'"),
    ("none", "None"),
]:
    api(f"scene.n_{name}", C, f"nplps.make_scene('bumps', n={value})", raises("InputError", "image size"))
api(
    "scene.n_two",
    C,
    "s = nplps.make_scene('bumps', n=2)",
    ok("s.images.shape == (27, 2, 2) and np.isfinite(s.images).all()"),
)
api("scene.n_1e6", C, "nplps.make_scene('bumps', n=10**6)", mem("image size"), isolate=True, budget=30)
api("scene.n_20000", C, "nplps.make_scene('bumps', n=20000)", mem("image size"), isolate=True, budget=30)
api("scene.n_2pow40", C, "nplps.make_scene('bumps', n=2**40)", mem("image size"), isolate=True, budget=30)
api("scene.name_bogus", C, "nplps.make_scene('bogus', n=16)", raises("InputError", "bogus"))
api("scene.name_none", C, "nplps.make_scene(None, n=16)", raises("InputError", ("name", "scene")))
for name, value in [("zero", "0"), ("negative", "-1"), ("nan", "np.nan"), ("string", "'x'")]:
    api(f"scene.size_{name}", C, f"nplps.make_scene('bumps', n=16, size={value})", raises("InputError", "size"))
for name, value in [("zero", "0"), ("negative", "-200"), ("nan", "np.nan")]:
    api(
        f"scene.distance_{name}",
        C,
        f"nplps.make_scene('bumps', n=16, distance={value})",
        raises("InputError", "distance"),
    )
for name, value in [("negative", "-1"), ("nan", "np.nan"), ("string", "'x'"), ("inf", "np.inf")]:
    api(f"scene.noise_{name}", C, f"nplps.make_scene('bumps', n=16, noise={value})", raises("InputError", "noise"))
api(
    "scene.led_rgb_reconstruct",
    C,
    "s = nplps.make_scene('bumps', n=16, led=True, rgb=True); "
    "r = nplps.reconstruct(s.images, s.rig, mask=s.mask, depth=200.0)",
    ok("good(r, s) and r.albedo.shape == (16, 16, 3)"),
)
api(
    "scene.directional_reconstruct",
    C,
    "s = nplps.make_scene('bumps', n=16, directional=True); "
    "r = nplps.reconstruct(s.images, s.rig, mask=s.mask, depth=200.0)",
    ok("good(r, s)"),
)
api("scene.camera_bogus", C, "nplps.make_scene('bumps', n=16, camera='fisheye')", raises("InputError", "camera"))
api("scene.seed_string", C, "nplps.make_scene('bumps', n=16, seed='x')", raises("InputError", "seed"))
api(
    "scene.seed_negative",
    C,
    "s = nplps.make_scene('bumps', n=16, seed=-1)",
    either("np.isfinite(s.images).all()", "InputError", "seed"),
)

# --- render / predict / held_out -------------------------------------------------------------------
C = "render"
api("render.depth_1d", C, "nplps.render(np.ones(17), R)", raises("InputError", "depth"))
api("render.depth_one_row", C, "nplps.render(np.ones((1, 5)), R)", raises("InputError", "depth"))
api("render.depth_complex", C, "nplps.render(S.depth + 1j, R)", raises("InputError", "depth"))
api("render.depth_string", C, "nplps.render('x', R)", raises("InputError", "depth"))
api("render.depth_none", C, "nplps.render(None, R)", raises("InputError", "depth"))
api(
    "render.depth_nan_inside",
    C,
    "z = S.depth.copy(); z[8, 8] = np.nan; out = nplps.render(z, R)",
    either("np.isnan(out[:, 7, 7]).all()", "InputError", "depth"),
)
api(
    "render.depth_nan_outside_mask",
    C,
    "m = M.copy(); m[:4] = False; z = S.depth.copy(); z[0] = np.nan; out = nplps.render(z, R, 1.0, mask=m)",
    ok("np.isfinite(out).all() and (out[:, :4] == 0).all()"),
)
api("render.albedo_wrong_shape", C, "nplps.render(S.depth, R, np.ones((5, 5)))", raises("InputError", "albedo"))
api("render.albedo_string", C, "nplps.render(S.depth, R, 'x')", raises("InputError", "albedo"))
api("render.rig_string", C, "nplps.render(S.depth, 'x')", raises("InputError", "rig"))
api(
    "render.mask_wrong_shape",
    C,
    "nplps.render(S.depth, R, 1.0, mask=np.ones((8, 8), bool))",
    raises("InputError", "mask"),
)
api(
    "render.huge_depth",
    C,
    "nplps.render(np.broadcast_to(200.0, (20001, 20001)), R)",
    mem("depth"),
    isolate=True,
    budget=30,
)

C = "predict"
for name, value in [
    ("out_of_range", "[99]"),
    ("below_range", "[-28]"),
    ("float", "[1.0]"),
    ("string", "'0'"),
    ("int", "5"),
]:
    api(f"predict.lights_{name}", C, f"rec().predict(lights={value})", raises("InputError", "lights"))
api("predict.lights_empty", C, "p = rec().predict(lights=[])", either("p.shape[0] == 0", "InputError", "lights"))
api(
    "predict.lights_array",
    C,
    "p = rec().predict(lights=np.array([0, 1]))",
    ok("p.shape == (2, 16, 16) and np.isfinite(p).all()"),
)
api("predict.all", C, "p = rec().predict()", ok("p.shape == (27, 16, 16) and np.abs(p - I).max() < 0.05 * I.max()"))
api("predict.rig_string", C, "rec().predict(rig='x')", raises("InputError", "rig"))
api(
    "predict.parallel_result", C, "p = par().predict(lights=[0])", ok("p.shape == (1, 16, 16) and np.isfinite(p).all()")
)

C = "evaluate (held_out)"
api(
    "held_out.fewer_images",
    C,
    "nplps.evaluation.held_out(I[:5], R, mask=M, depth=200.0, lights=[0])",
    raises("InputError", "image"),
)
api(
    "held_out.light_out_of_range",
    C,
    "nplps.evaluation.held_out(I, R, mask=M, depth=200.0, lights=[99])",
    raises("InputError", "lights"),
)
api(
    "held_out.method_bogus",
    C,
    "nplps.evaluation.held_out(I, R, mask=M, depth=200.0, method='bogus', lights=[0])",
    raises("InputError", "method"),
)
api(
    "held_out.auto",
    C,
    "nplps.evaluation.held_out(I, R, mask=M, depth='auto', lights=[0])",
    raises("InputError", "depth"),
)
api(
    "held_out.basic",
    C,
    "h = nplps.evaluation.held_out(I, R, mask=M, depth=200.0, lights=[0])",
    ok("len(h) == 1 and 0 <= h[0].relative_error < 0.05"),
)
api(
    "held_out.black_image",
    C,
    "J = I.copy(); J[0] = 0; h = nplps.evaluation.held_out(J, R, mask=M, depth=200.0, lights=[0])",
    either("not np.isfinite(h[0].relative_error)", "InputError", ("image 0", "light 0")),
)

# --- Rig constructors ------------------------------------------------------------------------------
C = "Rig constructors"
for name, value in [
    ("zero", "0"),
    ("negative", "-1.0"),
    ("nan", "np.nan"),
    ("inf", "np.inf"),
    ("string", "'x'"),
    ("triple", "(1, 2, 3)"),
]:
    api(f"rig.pixel_size_{name}", C, f"Rig.orthographic({value}, lights=L)", raises("RigError", "pixel_size"))
api("rig.origin_nan", C, "Rig.orthographic(6.25, origin=(np.nan, 0), lights=L)", raises("RigError", "origin"))
api("rig.origin_string", C, "Rig.orthographic(6.25, origin='ab', lights=L)", raises("RigError", "origin"))
api(
    "rig.lights_nan",
    C,
    "L2 = L.copy(); L2[3, 0] = np.nan; Rig.orthographic(6.25, lights=L2)",
    raises("RigError", "light"),
)
api(
    "rig.lights_inf",
    C,
    "L2 = L.copy(); L2[3, 2] = -np.inf; Rig.orthographic(6.25, lights=L2)",
    raises("RigError", "light"),
)
api("rig.lights_shape", C, "Rig.orthographic(6.25, lights=np.ones((5, 2)))", raises("RigError", "lights"))
api("rig.lights_string", C, "Rig.orthographic(6.25, lights='abc')", raises("RigError", "lights"))
api("rig.no_lights", C, "rg = Rig.orthographic(6.25, lights=[])", either("rg.n_lights == 0", "RigError", "lights"))
api(
    "rig.two_lights",
    C,
    "rec(images=I[[0, 9]], rig=R.subset([0, 9]))",
    raises("InputError", ("light", "normals")),
)
api(
    "rig.coincident_lights",
    C,
    "Rc = orth([[10, 0, 50.0]] * 3); rec(images=I[:3], rig=Rc)",
    raises("RigError", "normals"),
)
api(
    "rig.collinear_lights",
    C,
    "Rc = orth([[0, 0, 50.0], [0, 0, 80], [0, 0, 110]]); rec(images=I[:3], rig=Rc)",
    raises("RigError", "normals"),
)
api(
    "rig.lights_behind_surface",
    C,
    "L2 = L.copy(); L2[:, 2] = 300.0; rec(rig=orth(L2))",
    raises("InputError", ("behind", "light")),
)
api(
    "rig.lights_in_surface_plane",
    C,
    "L2 = L.copy(); L2[:, 2] = 200.0; rec(rig=orth(L2))",
    raises("InputError", ("behind", "light")),
)
api(
    "rig.one_light_behind",
    C,
    "L2 = L.copy(); L2[5, 2] = 300.0; rec(rig=orth(L2))",
    raises("InputError", "light 5"),
)
for name, value in [
    ("zero", "0.0"),
    ("negative", "-1.0"),
    ("nan", "np.nan"),
    ("wrong_shape", "np.ones(5)"),
    ("string", "'x'"),
]:
    api(f"rig.intensities_{name}", C, f"orth(intensities={value})", raises("RigError", "intensit"))
for name, value in [("negative", "-np.ones(27)"), ("nan", "np.full(27, np.nan)")]:
    api(f"rig.mu_{name}", C, f"orth(mu={value}, axes=np.tile([0, 0, 1.0], (27, 1)))", raises("RigError", "mu"))
api("rig.mu_without_directions", C, "orth(mu=np.ones(27))", raises("RigError", "axis"))
api("rig.led_zero_direction", C, "orth(mu=np.ones(27), axes=np.zeros((27, 3)))", raises("RigError", "axis"))
api(
    "rig.led_nan_direction",
    C,
    "orth(mu=np.ones(27), axes=np.full((27, 3), np.nan))",
    raises("RigError", "axis"),
)
api("rig.directional_zero", C, "orth(directional=[[0, 0, 0.0]])", raises("RigError", "direction"))
api("rig.directional_nan", C, "orth(directional=[[np.nan, 0, -1.0]])", raises("RigError", "direction"))
api(
    "rig.directional_flags_shape",
    C,
    "Rig.from_arrays(R.camera, L, directions=[[0, 0, -1.0]])",
    raises("RigError", "directions"),
)
api("rig.subset_out_of_range", C, "R.subset([99])", raises("InputError", ("indices", "99")))
C = "Rig constructors/pinhole"
api("rig.K_shape", C, "Rig.pinhole(np.eye(2), lights=L)", raises("RigError", "K"))
api("rig.K_zero_focal", C, "K = np.array(KP); K[0, 0] = 0; Rig.pinhole(K, lights=L)", raises("RigError", "K"))
api("rig.K_negative_focal", C, "K = np.array(KP); K[1, 1] = -32; Rig.pinhole(K, lights=L)", raises("RigError", "K"))
api("rig.K_nan", C, "K = np.array(KP); K[0, 2] = np.nan; Rig.pinhole(K, lights=L)", raises("RigError", "K"))
api("rig.K_zeros", C, "Rig.pinhole(np.zeros((3, 3)), lights=L)", raises("RigError", "K"))
api("rig.K_last_row", C, "K = np.array(KP); K[2] = [1, 1, 1]; Rig.pinhole(K, lights=L)", raises("RigError", "K"))
api("rig.K_string", C, "Rig.pinhole('K', lights=L)", raises("RigError", "K"))
api("rig.K_none", C, "Rig.pinhole(None, lights=L)", raises("RigError", "K"))
api("rig.distortion_six", C, "Rig.pinhole(KP, lights=L, distortion=[0] * 6)", raises("RigError", "distortion"))
api("rig.distortion_nan", C, "Rig.pinhole(KP, lights=L, distortion=[np.nan, 0])", raises("RigError", "distortion"))
api("rig.distortion_string", C, "Rig.pinhole(KP, lights=L, distortion='abc')", raises("RigError", "distortion"))
api(
    "rig.distortion_nested",
    C,
    "rg = Rig.pinhole(KP, lights=L, distortion=[[0.01, 0, 0, 0, 0]])",
    ok("rg.camera['distortion'] == [0.01, 0, 0, 0, 0]"),
)
api(
    "rig.distortion_two",
    C,
    "rg = Rig.pinhole(KP, lights=L, distortion=[0.01, 0.0])",
    ok("len(rg.camera['distortion']) == 5"),
)
api("rig.camera_empty", C, "Rig(camera={}, lights=L)", raises("RigError", "model"))
api("rig.camera_fisheye", C, "Rig(camera={'model': 'fisheye'}, lights=L)", raises("RigError", ("fisheye", "model")))
api("rig.camera_string", C, "Rig(camera='orthographic', lights=L)", raises("RigError", "camera"))

# --- rig files ---------------------------------------------------------------------------------------
C = "rig files"
api("rigfile.missing", C, "Rig.load(tmp / 'norig.json')", raises("RigError", "norig.json"))
api("rigfile.directory", C, "Rig.load(tmp)", raises("RigError", "rig"))
api("rigfile.empty", C, "Rig.load(write_text('rig.json', ''))", raises("RigError", "rig.json"))
api("rigfile.invalid_json", C, "Rig.load(write_text('rig.json', '{'))", raises("RigError", "rig.json"))
api("rigfile.binary", C, "Rig.load(write_bytes('rig.json', bytes(range(256))))", raises("RigError", "rig.json"))
api("rigfile.top_level_list", C, "Rig.load(write_json('rig.json', [1, 2]))", raises("RigError", "rig.json"))
api("rigfile.null", C, "Rig.load(write_json('rig.json', None))", raises("RigError", "rig.json"))
api(
    "rigfile.deep_nesting_10000",
    C,
    "Rig.load(write_text('rig.json', '[' * 10000 + ']' * 10000))",
    raises("RigError", "rig.json"),
)
api(
    "rigfile.deep_nesting_in_camera",
    C,
    "d = rig_dict(); t = json.dumps(d).replace('\"pixel_size\": [', '\"pixel_size\": ' + '[' * 20000 + '[', 1)\n"
    "t = t.replace(']', ']' * 20001, 1)\nRig.load(write_text('rig.json', t))",
    raises("RigError", "rig.json"),
)
api(
    "rigfile.deep_nesting_1e6",
    C,
    "Rig.load(write_text('rig.json', '{\"a\": ' * 10**6 + '1' + '}' * 10**6))",
    raises("RigError", "rig.json"),
    isolate=True,
    budget=30,
)
api(
    "rigfile.huge_garbage",
    C,
    "Rig.load(write_text('rig.json', ' ' * (64 << 20) + '{'))",
    raises("RigError", "rig.json"),
    isolate=True,
    budget=30,
)
api(
    "rigfile.200k_lights",
    C,
    "d = rig_dict(); d['lights'] = d['lights'] * (200000 // 27 + 1); rg = Rig.load(write_json('rig.json', d))",
    either("rg.n_lights > 200000", "RigError", "rig.json"),
    isolate=True,
    budget=60,
)
for key in ("version", "camera", "lights"):
    api(
        f"rigfile.missing_{key}",
        C,
        f"d = rig_dict(); del d['{key}']; Rig.load(write_json('rig.json', d))",
        raises("RigError", key),
    )
for name, value in [("string", "'2'"), ("four", "4"), ("zero", "0"), ("bool", "True")]:
    api(
        f"rigfile.version_{name}",
        C,
        f"d = rig_dict(); d['version'] = {value}; Rig.load(write_json('rig.json', d))",
        raises("RigError", "version"),
    )
api(
    "rigfile.version_float",
    C,
    "d = rig_dict(); d['version'] = 2.0; rg = Rig.load(write_json('rig.json', d))",
    either("rg.n_lights == 27", "RigError", "version"),
)
api("rigfile.v1", C, "rg = Rig.load(write_json('rig.json', rig_v1()))", ok("rg.n_lights == 27"))
api(
    "rigfile.round_trip_led",
    C,
    "s = nplps.make_scene('bumps', n=8, led=True); s.rig.save(tmp / 'r.json'); rg = Rig.load(tmp / 'r.json')",
    ok("np.allclose(rg.mu, s.rig.mu) and np.allclose(rg.positions, s.rig.positions)"),
)
api(
    "rigfile.utf8_bom",
    C,
    "rg = Rig.load(write_bytes('rig.json', b'\\xef\\xbb\\xbf' + json.dumps(rig_dict()).encode()))",
    either("rg.n_lights == 27", "RigError", "rig.json"),
)
api(
    "rigfile.model_unknown",
    C,
    "d = rig_dict(); d['camera']['model'] = 'fisheye'; Rig.load(write_json('rig.json', d))",
    raises("RigError", ("fisheye", "model")),
)
api(
    "rigfile.model_missing",
    C,
    "d = rig_dict(); del d['camera']['model']; Rig.load(write_json('rig.json', d))",
    raises("RigError", "model"),
)
api(
    "rigfile.camera_list",
    C,
    "d = rig_dict(); d['camera'] = [1, 2]; Rig.load(write_json('rig.json', d))",
    raises("RigError", "camera"),
)
for name, value in [
    ("missing", None),
    ("string", "'abc'"),
    ("one", "[1]"),
    ("zero", "[0, 0]"),
    ("negative", "[-1, -1]"),
    ("nan", "[np.nan, np.nan]"),
]:
    code = "d = rig_dict(); " + (
        "del d['camera']['pixel_size']" if value is None else f"d['camera']['pixel_size'] = {value}"
    )
    api(
        f"rigfile.pixel_size_{name}",
        C,
        code + "; Rig.load(write_json('rig.json', d))",
        raises("RigError", "pixel_size"),
    )
api(
    "rigfile.origin_missing",
    C,
    "d = rig_dict(); del d['camera']['origin']; Rig.load(write_json('rig.json', d))",
    raises("RigError", "origin"),
)
api(
    "rigfile.origin_strings",
    C,
    "d = rig_dict(); d['camera']['origin'] = ['a', 'b']; Rig.load(write_json('rig.json', d))",
    raises("RigError", "origin"),
)
for name, value in [
    ("missing", None),
    ("2x2", "[[1, 0], [0, 1]]"),
    ("strings", "[['a'] * 3] * 3"),
    ("null", "None"),
    ("zeros", "[[0] * 3] * 3"),
    ("negative_focal", "[[-32, 0, 7.5], [0, 32, 7.5], [0, 0, 1]]"),
]:
    code = "d = rig_dict(PS); " + ("del d['camera']['K']" if value is None else f"d['camera']['K'] = {value}")
    api(f"rigfile.K_{name}", C, code + "; Rig.load(write_json('rig.json', d))", raises("RigError", "K"))
api(
    "rigfile.distortion_nested_accepted",
    C,
    "d = rig_dict(PS); d['camera']['distortion'] = [[0, 0, 0, 0, 0]]; rg = Rig.load(write_json('rig.json', d))\n"
    "r = nplps.reconstruct(PS.images, rg, mask=PS.mask, depth=200.0)",
    ok("good(r, PS)"),
)
api(
    "rigfile.distortion_four",
    C,
    "d = rig_dict(PS); d['camera']['distortion'] = [0, 0, 0, 0]; rg = Rig.load(write_json('rig.json', d))\n"
    "r = nplps.reconstruct(PS.images, rg, mask=PS.mask, depth=200.0)",
    ok("good(r, PS)"),
)
for name, value in [
    ("six", "[0] * 6"),
    ("string", "'abc'"),
    ("nan", "[np.nan, 0, 0, 0, 0]"),
    ("object", "{'k1': 0}"),
    ("nested_six", "[[0] * 6]"),
]:
    api(
        f"rigfile.distortion_{name}",
        C,
        f"d = rig_dict(PS); d['camera']['distortion'] = {value}; Rig.load(write_json('rig.json', d))",
        raises("RigError", "distortion"),
    )
api(
    "rigfile.lights_dict",
    C,
    "d = rig_dict(); d['lights'] = {'a': 1}; Rig.load(write_json('rig.json', d))",
    raises("RigError", "lights"),
)
api(
    "rigfile.lights_empty",
    C,
    "d = rig_dict(); d['lights'] = []; rg = Rig.load(write_json('rig.json', d))",
    either("rg.n_lights == 0", "RigError", "lights"),
)
api(
    "rigfile.light_number",
    C,
    "d = rig_dict(); d['lights'][2] = 5; Rig.load(write_json('rig.json', d))",
    raises("RigError", "light 2"),
)
for name, value in [
    ("missing", None),
    ("two", "[1, 2]"),
    ("strings", "['a', 'b', 'c']"),
    ("nan", "[np.nan, 0, 0]"),
    ("inf", "[1e400, 0, 0]"),
    ("huge_int", "[10**400, 0, 0]"),
]:
    code = "d = rig_dict(); " + (
        "del d['lights'][3]['position']" if value is None else f"d['lights'][3]['position'] = {value}"
    )
    api(f"rigfile.position_{name}", C, code + "; Rig.load(write_json('rig.json', d))", raises("RigError", "position"))
api(
    "rigfile.light_type_spot",
    C,
    "d = rig_dict(); d['lights'][0]['type'] = 'spot'; Rig.load(write_json('rig.json', d))",
    raises("RigError", "spot"),
)
api(
    "rigfile.led_without_direction",
    C,
    "d = rig_dict(); d['lights'][0]['mu'] = 1.0; Rig.load(write_json('rig.json', d))",
    raises("RigError", "direction"),
)
for name, value in [("string", "'x'"), ("negative", "-1.0"), ("nan", "np.nan")]:
    api(
        f"rigfile.mu_{name}",
        C,
        f"d = rig_dict(); d['lights'][0].update(mu={value}, direction=[0, 0, 1]); Rig.load(write_json('rig.json', d))",
        raises("RigError", "mu"),
    )
for name, value in [
    ("negative", "-1.0"),
    ("zero", "0.0"),
    ("string", "'bright'"),
    ("pair", "[1, 2]"),
    ("nan", "np.nan"),
]:
    api(
        f"rigfile.intensity_{name}",
        C,
        f"d = rig_dict(); d['lights'][1]['intensity'] = {value}; Rig.load(write_json('rig.json', d))",
        raises("RigError", "intensit"),
    )
api(
    "rigfile.directional_zero",
    C,
    "d = rig_dict(); d['lights'][4] = {'type': 'directional', 'direction': [0, 0, 0]}; "
    "Rig.load(write_json('rig.json', d))",
    raises("RigError", "direction"),
)
api(
    "rigfile.directional_not_unit",
    C,
    "d = rig_dict(); d['lights'][4] = {'type': 'directional', 'direction': [0, 0, -2]}; "
    "rg = Rig.load(write_json('rig.json', d))",
    either("np.allclose(np.linalg.norm(rg.directions[4]), 1)", "RigError", "direction"),
)
api("rigfile.from_dict_none", C, "Rig.from_dict(None)", raises("RigError", "rig"))
api("rigfile.load_none", C, "Rig.load(None)", raises("RigError", "rig"))

# --- image files -------------------------------------------------------------------------------------
C = "image files"
FILES = "P = imgs(); P[5] = str(BAD); rec(images=P)"
api("files.zero_byte_png", C, "BAD = write_bytes('bad.png', b'')\n" + FILES, raises("InputError", "bad.png"))
api(
    "files.truncated_header",
    C,
    "BAD = write_bytes('bad.png', Path(imgs()[5]).read_bytes()[:60])\n" + FILES,
    raises("InputError", "bad.png"),
)
api(
    "files.truncated_data",
    C,
    "b = Path(imgs()[5]).read_bytes(); BAD = write_bytes('bad.png', b[: len(b) // 2])\n" + FILES,
    raises("InputError", "bad.png"),
)
api(
    "files.missing_iend",
    C,
    "BAD = write_bytes('bad.png', Path(imgs()[5]).read_bytes()[:-12])\nP = imgs(); P[5] = str(BAD); r = rec(images=P)",
    either(
        "good(r) and np.array_equal(nplps.io.read_image(BAD), nplps.io.read_image(imgs()[5]))", "InputError", "bad.png"
    ),
)
api(
    "files.corrupt_crc",
    C,
    "b = bytearray(Path(imgs()[5]).read_bytes()); b[60] ^= 0xFF; BAD = write_bytes('bad.png', bytes(b))\n" + FILES,
    raises("InputError", "bad.png"),
)
api("files.text_as_png", C, "BAD = write_text('bad.png', 'not an image')\n" + FILES, raises("InputError", "bad.png"))
api("files.png_width_zero", C, "BAD = png_header_only('bad.png', 0, 16)\n" + FILES, raises("InputError", "bad.png"))
api(
    "files.png_bomb_30000",
    C,
    "BAD = png_header_only('bomb.png', 30000, 30000)\nP = imgs(); P[0] = str(BAD); rec(images=P)",
    raises("InputError", "bomb.png", "pixels"),
    budget=10,
)
api(
    "files.png_bomb_under_limit",
    C,
    "BAD = png_header_only('bomb.png', 16000, 16000)\nP = imgs(); P[0] = str(BAD); rec(images=P)",
    raises("InputError", "bomb.png"),
    isolate=True,
    budget=20,
)
api(
    "files.tiff_bomb",
    C,
    "BAD = tiff_header_only('bomb.tiff', 30000, 30000)\nP = imgs(); P[0] = str(BAD); rec(images=P)",
    raises("InputError", "bomb.tiff", "pixels"),
    budget=10,
)
api(
    "files.bmp_bomb",
    C,
    "BAD = bmp_header_only('bomb.bmp', 30000, 30000)\nP = imgs(); P[0] = str(BAD); rec(images=P)",
    raises("InputError", "bomb.bmp", "pixels"),
    budget=10,
)
api(
    "files.jpeg_bomb",
    C,
    "BAD = jpeg_header_only('bomb.jpg', 30000, 30000)\nP = imgs(); P[0] = str(BAD); rec(images=P)",
    raises("InputError", "bomb.jpg", "pixels"),
    budget=10,
)
api(
    "files.mismatched_size",
    C,
    "BAD = png('bad.png', np.zeros((8, 8), np.uint16))\n" + FILES,
    raises("InputError", "bad.png"),
)
api(
    "files.rgb_among_grey",
    C,
    "a = nplps.io.read_image(imgs()[5]); BAD = png('bad.png', np.stack([a] * 3, -1))\n"
    "P = imgs(); P[5] = str(BAD); r = rec(images=P)",
    ok("good(r)"),
)
api(
    "files.tiff_nan",
    C,
    "a = np.ones((16, 16), np.float32); a[2, 2] = np.nan; BAD = tiff('bad.tiff', a)\n" + FILES,
    raises("InputError", "bad.tiff"),
)
api(
    "files.tiff_complex",
    C,
    "BAD = tiff('bad.tiff', np.ones((16, 16), np.complex64))\n" + FILES,
    raises("InputError", "bad.tiff"),
)
api(
    "files.tiff_multipage",
    C,
    "BAD = tiff('bad.tiff', np.ones((5, 16, 16), np.uint16))\n" + FILES,
    raises("InputError", "bad.tiff"),
)
api("files.directory_named_png", C, "BAD = tmp / 'bad.png'; BAD.mkdir()\n" + FILES, raises("InputError", "bad.png"))
api("files.symlink_loop", C, "BAD = tmp / 'loop.png'; os.symlink(BAD, BAD)\n" + FILES, raises("InputError", "loop.png"))
api("files.missing", C, "BAD = tmp / 'gone.png'\n" + FILES, raises("InputError", "gone.png"))
api("files.dev_zero", C, "BAD = '/dev/zero'\n" + FILES, raises("InputError", "/dev/zero"), isolate=True, budget=20)
api(
    "files.read_image_dev_zero",
    C,
    "nplps.io.read_image('/dev/zero')",
    raises("InputError", "/dev/zero"),
    isolate=True,
    budget=20,
)
api(
    "files.png16_grey_alpha",
    C,
    "a = nplps.io.read_image(imgs()[5]); BAD = png('bad.png', np.stack([a, np.full_like(a, 65535)], -1))\n"
    "P = imgs(); P[5] = str(BAD); r = rec(images=P)",
    ok("good(r)"),
)

# --- degenerate data -----------------------------------------------------------------------------------
C = "degenerate data"
api(
    "degenerate.saturated_uint16",
    C,
    "rec(images=np.full(I.shape, 65535, np.uint16))",
    raises("InputError", ("saturat", "observations")),
)
api(
    "degenerate.very_distant_lights",
    C,
    "L2 = L.copy(); L2[:, 2] = -1e6; rec(rig=orth(L2))",
    raises("RigError", "normals"),
)
api(
    "degenerate.very_distant_lights_parallel",
    C,
    "L2 = L.copy(); L2[:, 2] = -1e6; par(rig=orth(L2))",
    raises("RigError", "normals"),
)
api(
    "degenerate.reversed_light_order",
    C,
    "r = rec(images=I[::-1])",
    ok("honest(r) and r.history[-1].rms_residual > 10 * rec().history[-1].rms_residual"),
)

# --- result status (fix in progress) -----------------------------------------------------------------
C = "result status"
api("status.converged", C, "r = rec()", ok("r.status == 'converged'"))
api(
    "status.iteration_limit",
    C,
    "r = rec(iterations=1, tol=1e-12)",
    ok("not r.converged and r.status in STATUSES and r.status != 'converged'"),
)
api("status.in_summary", C, "r = rec()", ok("r.summary().get('status') == r.status"))

# --- memory ----------------------------------------------------------------------------------------------
C = "memory"
BIG = "J = np.full((3, 12000, 12000), 0.5, np.float32); Rg = orth([[30, 0, 50.0], [-15, 26, 50], [-15, -26, 50]])\n"
api("memory.reconstruct_large", C, BIG + "rec(images=J, rig=Rg, mask=None)", mem(), isolate=True, budget=90)
api(
    "memory.reconstruct_large_auto",
    C,
    BIG + "rec(images=J, rig=Rg, mask=None, depth='auto')",
    mem(),
    isolate=True,
    budget=90,
)
api("memory.parallel_large", C, BIG + "par(images=J, rig=Rg, mask=None)", mem(), isolate=True, budget=90)

# --- command line --------------------------------------------------------------------------------------------
RC = "reconstruct {SC} --rig {SC}/rig.json --mask {SC}/mask.png --out {tmp}/out -q"
COPY = "d = copy_scene('s')\n"
RD = "reconstruct {tmp}/s --rig {tmp}/s/rig.json --mask {tmp}/s/mask.png --out {tmp}/out -q --depth 200"

C = "cli/usage"
cli(
    "cli.ok",
    C,
    RC + " --depth 200",
    exits(0, check="(tmp / 'out' / 'depth.npy').exists() and summary(tmp / 'out')['converged']"),
)
cli(
    "cli.ok_subprocess",
    C,
    RC + " --depth 200",
    exits(0, check="(tmp / 'out' / 'mesh.ply').exists()"),
    proc=True,
    budget=30,
)
cli("cli.no_arguments", C, "", exits(2), proc=True, budget=30)
cli("cli.version", C, "--version", exits(0), proc=True, budget=30)
cli("cli.help", C, "reconstruct --help", exits(0))
cli("cli.unknown_command", C, "frobnicate", exits(2, "frobnicate"), proc=True, budget=30)
cli("cli.unknown_option", C, RC + " --depth 200 --frobnicate", exits(2, "--frobnicate"))
cli("cli.missing_depth", C, RC, exits(2, "--depth"))
cli("cli.missing_out", C, "reconstruct {SC} --rig {SC}/rig.json --depth 200", exits(2, "--out"))
cli("cli.missing_rig", C, "reconstruct {SC} --depth 200 --out {tmp}/out", exits(2, "--rig"))
cli("cli.no_images", C, "reconstruct --rig {SC}/rig.json --depth 200 --out {tmp}/out", exits(2, ("IMAGES", "no input")))
cli(
    "cli.status_in_summary", C, RC + " --depth 200", exits(0, check="summary(tmp / 'out').get('status') == 'converged'")
)

C = "cli/depth"
for name, value in [("string", "abc"), ("negative", "-5"), ("zero", "0"), ("nan", "nan"), ("inf", "inf")]:
    cli(f"cli.depth_{name}", C, RC + f" --depth {value}", exits(2, "--depth"))
cli("cli.depth_1e300", C, RC + " --depth 1e300", exits(2, "depth"))
cli("cli.depth_auto", C, RC + " --depth auto", exits(0, check="summary(tmp / 'out')['estimated_distance'] is not None"))
for name, value in [
    ("reversed", "400,100"),
    ("string", "abc"),
    ("triple", "1,2,3"),
    ("zero", "0,400"),
    ("nan", "nan,400"),
]:
    cli(
        f"cli.depth_range_{name}",
        C,
        RC + f" --depth auto --depth-range {value}",
        exits(2, ("--depth-range", "depth_range")),
    )
cli("cli.depth_range_excludes_truth", C, RC + " --depth auto --depth-range 1000,2000", exits((0, 2), "range"))
NPY = "reconstruct {SC} --rig {SC}/rig.json --mask {SC}/mask.png --out {tmp}/out -q --depth {tmp}/d.npy"
cli("cli.depth_npy_ok", C, NPY, exits(0), setup="np.save(tmp / 'd.npy', np.full((17, 17), 200.0))")
cli(
    "cli.depth_npy_complex",
    C,
    NPY,
    exits(2, ("--depth", "d.npy")),
    setup="np.save(tmp / 'd.npy', np.full((17, 17), 200.0 + 1j))",
)
cli(
    "cli.depth_npy_pickled",
    C,
    NPY,
    exits(2, ("--depth", "d.npy")),
    setup="np.save(tmp / 'd.npy', np.array([{'a': 1}], dtype=object), allow_pickle=True)",
)
cli("cli.depth_npy_empty_file", C, NPY, exits(2, ("--depth", "d.npy")), setup="write_bytes('d.npy', b'')")
cli(
    "cli.depth_npy_truncated",
    C,
    NPY,
    exits(2, ("--depth", "d.npy")),
    setup="np.save(tmp / 'd.npy', np.full((17, 17), 200.0)); write_bytes('d.npy', (tmp / 'd.npy').read_bytes()[:200])",
)
cli("cli.depth_npy_text", C, NPY, exits(2, ("--depth", "d.npy")), setup="write_text('d.npy', 'hello')")
cli("cli.depth_npy_wrong_shape", C, NPY, exits(2, "depth"), setup="np.save(tmp / 'd.npy', np.full((16, 16), 200.0))")
cli(
    "cli.depth_npy_structured",
    C,
    NPY,
    exits(2, ("--depth", "d.npy")),
    setup="np.save(tmp / 'd.npy', np.zeros((17, 17), dtype=[('a', 'f8')]))",
)
cli(
    "cli.depth_npy_nan_inside",
    C,
    NPY,
    exits(2, "depth"),
    setup="z = np.full((17, 17), 200.0); z[8, 8] = np.nan; np.save(tmp / 'd.npy', z)",
)
cli(
    "cli.depth_prior_complex",
    C,
    RC + " --depth 200 --depth-prior {tmp}/p.npy",
    exits(2, ("prior", "p.npy")),
    setup="np.save(tmp / 'p.npy', np.full((17, 17), 200.0 + 1j))",
)
cli(
    "cli.prior_weight_negative",
    C,
    RC + " --depth 200 --depth-prior {tmp}/p.npy --prior-weight -1",
    exits(2, "prior"),
    setup="np.save(tmp / 'p.npy', np.full((17, 17), 200.0))",
)

C = "cli/options"
for name, value in [("zero", "0"), ("negative", "-1"), ("string", "ten")]:
    cli(f"cli.iterations_{name}", C, RC + f" --depth 200 --iterations {value}", exits(2, "--iterations"))
cli("cli.iterations_1e9", C, RC + " --depth 200 --iterations 1000000000", exits(0))
cli(
    "cli.iterations_beyond_int64",
    C,
    RC + " --depth 200 --iterations 99999999999999999999999",
    exits((0, 2), check="code == 0 or 'iterations' in err"),
)
for name, value in [("negative", "-1"), ("nan", "nan")]:
    cli(f"cli.tol_{name}", C, RC + f" --depth 200 --tol {value}", exits(2, "--tol"))
cli("cli.threads_zero", C, RC + " --depth 200 --threads 0", exits(2, "--threads"))
cli(
    "cli.threads_100000",
    C,
    RC + " --depth 200 --threads 100000",
    exits((0, 2), check="code == 0 or 'threads' in err"),
    isolate=True,
)
cli("cli.bin_zero", C, RC + " --depth 200 --bin 0", exits(2, "--bin"))
cli("cli.bin_larger_than_image", C, RC + " --depth 200 --bin 1000", exits(2, "--bin"))
cli("cli.bin_not_dividing", C, RC + " --depth 200 --bin 3", exits((0, 2), check="code == 0 or '--bin' in err"))
cli("cli.dark_nan", C, RC + " --depth 200 --dark nan", exits(2, "--dark"))
cli("cli.dark_string", C, RC + " --depth 200 --dark abc", exits(2, "--dark"))
cli("cli.dark_above_everything", C, RC + " --depth 200 --dark 10", exits(2, "dark"))
cli("cli.saturation_zero", C, RC + " --depth 200 --saturation 0", exits(2, "--saturation"))
cli("cli.levels_zero", C, RC + " --depth 200 --levels 0", exits(2, "--levels"))
cli("cli.solver_bogus", C, RC + " --depth 200 --solver qr", exits(2, "--solver"))
cli("cli.robust_bogus", C, RC + " --depth 200 --robust huber", exits(2, "--robust"))
cli("cli.refine_bogus", C, RC + " --depth 200 --refine-lights bogus", exits(2, "--refine-lights"))
cli(
    "cli.light_prior_weight_negative",
    C,
    RC + " --depth 200 --refine-lights position --light-prior-weight -1",
    exits(2, "prior"),
)
cli(
    "cli.light_prior_weight_nan",
    C,
    RC + " --depth 200 --refine-lights position --light-prior-weight nan",
    exits(2, "prior"),
)
cli("cli.exposures_count", C, RC + " --depth 200 --exposures 1,2", exits(2, "--exposures"))
cli("cli.exposures_zero", C, RC + " --depth 200 --exposures " + ",".join(["0"] * 27), exits(2, "--exposures"))
cli("cli.exposures_string", C, RC + " --depth 200 --exposures abc", exits(2, "--exposures"))
cli("cli.ambient_missing", C, RC + " --depth 200 --ambient {tmp}/amb.png", exits(2, "--ambient"))
cli(
    "cli.ambient_wrong_size",
    C,
    RC + " --depth 200 --ambient {tmp}/amb.png",
    exits(2, ("ambient", "amb.png")),
    setup="png('amb.png', np.zeros((8, 8), np.uint16))",
)
cli(
    "cli.flat_zeros",
    C,
    RC + " --depth 200 --flat {tmp}/flat.png",
    exits(2, ("flat", "flat.png")),
    setup="png('flat.png', np.zeros((16, 16), np.uint16))",
)
cli("cli.vignetting_orthographic", C, RC + " --depth 200 --vignetting cos4", exits(2, "vignetting"))
cli("cli.gray_on_grey", C, RC + " --depth 200 --gray", exits(0))

C = "cli/files"
cli(
    "cli.folder_missing",
    C,
    "reconstruct {tmp}/nope --rig {SC}/rig.json --depth 200 --out {tmp}/out -q",
    exits(2, "nope"),
)
cli(
    "cli.folder_empty",
    C,
    "reconstruct {tmp}/empty --rig {SC}/rig.json --depth 200 --out {tmp}/out -q",
    exits(2, "empty"),
    setup="(tmp / 'empty').mkdir()",
)
cli("cli.folder_one_image_short", C, RD, exits(2, ("26", "rig.json")), setup=COPY + "(d / 'image_26.png').unlink()")
cli(
    "cli.file_list_one_missing",
    C,
    "reconstruct {SC}/image_00.png {SC}/image_01.png {tmp}/missing.png --rig {SC}/rig.json --depth 200 "
    "--out {tmp}/out -q",
    exits(2, "missing.png"),
)
cli(
    "cli.folder_and_files",
    C,
    "reconstruct {SC} {SC}/image_00.png --rig {SC}/rig.json --depth 200 --out {tmp}/out -q",
    exits(2, "director"),
)
cli("cli.zero_byte_png", C, RD, exits(2, "image_05.png"), setup=COPY + "(d / 'image_05.png').write_bytes(b'')")
cli(
    "cli.truncated_png",
    C,
    RD,
    exits(2, "image_05.png"),
    setup=COPY + "p = d / 'image_05.png'; p.write_bytes(p.read_bytes()[:100])",
)
cli("cli.text_as_png", C, RD, exits(2, "image_05.png"), setup=COPY + "(d / 'image_05.png').write_text('hello')")
cli(
    "cli.png_bomb",
    C,
    RD,
    exits(2, "image_05.png"),
    setup=COPY + "png_header_only(d / 'image_05.png', 30000, 30000)",
    budget=10,
)
cli(
    "cli.mismatched_sizes",
    C,
    RD,
    exits(2, "image_05.png"),
    setup=COPY + "png(d / 'image_05.png', np.zeros((8, 8), np.uint16))",
)
cli(
    "cli.rig_missing",
    C,
    "reconstruct {SC} --rig {tmp}/norig.json --depth 200 --out {tmp}/out -q",
    exits(2, "norig.json"),
)
cli("cli.rig_directory", C, "reconstruct {SC} --rig {tmp} --depth 200 --out {tmp}/out -q", exits(2, "rig"))
cli(
    "cli.rig_invalid_json",
    C,
    "reconstruct {SC} --rig {tmp}/bad.json --depth 200 --out {tmp}/out -q",
    exits(2, "bad.json"),
    setup="write_text('bad.json', '{\"version\": 2,')",
)
cli(
    "cli.rig_deep_nesting",
    C,
    "reconstruct {SC} --rig {tmp}/deep.json --depth 200 --out {tmp}/out -q",
    exits(2, "deep.json"),
    setup="write_text('deep.json', '[' * 10000 + ']' * 10000)",
)
cli(
    "cli.rig_led_without_direction",
    C,
    "reconstruct {SC} --rig {tmp}/led.json --depth 200 --out {tmp}/out -q",
    exits(2, "direction"),
    setup="d = rig_dict(); d['lights'][0]['mu'] = 1.0; write_json('led.json', d)",
)
cli(
    "cli.rig_five_lights",
    C,
    "reconstruct {SC} --rig {tmp}/five.json --depth 200 --out {tmp}/out -q",
    exits(2, ("five.json", "27")),
    setup="d = rig_dict(); d['lights'] = d['lights'][:5]; write_json('five.json', d)",
)
cli(
    "cli.rig_nested_distortion_accepted",
    C,
    "reconstruct {PSC} --rig {tmp}/rig.json --mask {PSC}/mask.png --depth 200 --out {tmp}/out -q",
    exits(0),
    setup="d = rig_dict(PS); d['camera']['distortion'] = [[0, 0, 0, 0, 0]]; write_json('rig.json', d)",
)
cli(
    "cli.mask_missing",
    C,
    RC.replace("{SC}/mask.png", "{tmp}/nomask.png") + " --depth 200",
    exits(2, ("--mask", "nomask.png")),
)
cli(
    "cli.mask_wrong_size",
    C,
    RC.replace("{SC}/mask.png", "{tmp}/m.png") + " --depth 200",
    exits(2, "mask"),
    setup="png('m.png', np.full((8, 8), 255, np.uint8))",
)
cli(
    "cli.mask_black",
    C,
    RC.replace("{SC}/mask.png", "{tmp}/m.png") + " --depth 200",
    exits(2, "mask"),
    setup="png('m.png', np.zeros((16, 16), np.uint8))",
)
cli(
    "cli.mask_text",
    C,
    RC.replace("{SC}/mask.png", "{tmp}/m.png") + " --depth 200",
    exits(2, "m.png"),
    setup="write_text('m.png', 'hello')",
)
cli(
    "cli.capture_missing_folder",
    C,
    "reconstruct --capture near_ps {tmp}/nope --depth 200 --out {tmp}/out -q",
    exits(2, "nope"),
)
cli(
    "cli.capture_diligent_empty",
    C,
    "reconstruct --capture diligent {tmp}/obj --depth 200 --out {tmp}/out -q",
    exits(2, "obj"),
    setup="(tmp / 'obj').mkdir()",
)
cli(
    "cli.capture_with_rig",
    C,
    "reconstruct --capture near_ps {SC} --rig {SC}/rig.json --depth 200 --out {tmp}/out -q",
    exits(2, "--rig"),
)
cli("cli.capture_bogus", C, "reconstruct --capture bogus {SC} --depth 200 --out {tmp}/out -q", exits(2, "--capture"))

C = "cli/output"
cli(
    "cli.out_is_file",
    C,
    RC.replace("{tmp}/out", "{tmp}/outfile") + " --depth 200",
    exits((1, 2), "outfile"),
    setup="write_text('outfile', 'x')",
)
cli(
    "cli.out_unwritable",
    C,
    RC.replace("{tmp}/out", "/proc/nplps-probe/out") + " --depth 200",
    exits((1, 2), "/proc/nplps-probe"),
)
cli(
    "cli.out_nonempty_refused",
    C,
    RC + " --depth 200",
    exits((1, 2), ("--overwrite", "not empty"), check="sorted(os.listdir(tmp / 'out')) == ['precious.txt']"),
    setup="(tmp / 'out').mkdir(); write_text('out/precious.txt', 'keep')",
)
cli(
    "cli.out_nonempty_untouched",
    C,
    RC + " --depth 200",
    exits(
        (1, 2),
        check="sorted(os.listdir(tmp / 'out')) == ['mesh.ply'] and (tmp / 'out' / 'mesh.ply').read_text() == 'keep'",
    ),
    setup="(tmp / 'out').mkdir(); write_text('out/mesh.ply', 'keep')",
)
cli(
    "cli.out_nonempty_overwrite",
    C,
    RC + " --depth 200 --overwrite",
    exits(0, check="(tmp / 'out' / 'depth.npy').exists()"),
    setup="(tmp / 'out').mkdir(); write_text('out/precious.txt', 'keep')",
)
cli("cli.out_empty_dir_ok", C, RC + " --depth 200", exits(0), setup="(tmp / 'out').mkdir()")

C = "cli/evaluate"
EV = "evaluate {SC} --rig {SC}/rig.json --mask {SC}/mask.png -q --depth 200"
cli("cli.evaluate_ok", C, EV + " --lights 0", exits(0, check="'mean' in out"))
cli(
    "cli.evaluate_auto",
    C,
    "evaluate {SC} --rig {SC}/rig.json --mask {SC}/mask.png -q --depth auto --lights 0",
    exits(0),
)
cli("cli.evaluate_light_99", C, EV + " --lights 99", exits(2, "--lights"))
cli("cli.evaluate_lights_string", C, EV + " --lights abc", exits(2, "--lights"))
cli("cli.evaluate_lights_empty", C, EV + " --lights=", exits(2, "--lights"))
cli(
    "cli.evaluate_rig_five_lights",
    C,
    "evaluate {SC} --rig {tmp}/five.json -q --depth 200 --lights 0",
    exits(2, ("five.json", "27")),
    setup="d = rig_dict(); d['lights'] = d['lights'][:5]; write_json('five.json', d)",
)
cli(
    "cli.evaluate_rig_deep",
    C,
    "evaluate {SC} --rig {tmp}/deep.json -q --depth 200",
    exits(2, "deep.json"),
    setup="write_text('deep.json', '[' * 10000 + ']' * 10000)",
)

C = "cli/synth, demo, calibrate"
cli("cli.synth_ok", C, "synth bumps --size 8 --out {tmp}/sc", exits(0, check="(tmp / 'sc' / 'rig.json').exists()"))
cli("cli.synth_size_zero", C, "synth bumps --size 0 --out {tmp}/sc", exits(2, "size"))
cli("cli.synth_size_one", C, "synth bumps --size 1 --out {tmp}/sc", exits(2, "size"))
cli(
    "cli.synth_size_1e6",
    C,
    "synth bumps --size 1000000 --out {tmp}/sc",
    exits((1, 2), ("size", "memory")),
    isolate=True,
    budget=30,
)
cli("cli.synth_noise_negative", C, "synth bumps --size 8 --noise -1 --out {tmp}/sc", exits(2, "noise"))
cli("cli.synth_noise_nan", C, "synth bumps --size 8 --noise nan --out {tmp}/sc", exits(2, "noise"))
cli("cli.synth_distance_zero", C, "synth bumps --size 8 --distance 0 --out {tmp}/sc", exits(2, "distance"))
cli("cli.synth_object_size_negative", C, "synth bumps --size 8 --object-size -1 --out {tmp}/sc", exits(2, "size"))
cli(
    "cli.synth_out_is_file",
    C,
    "synth bumps --size 8 --out {tmp}/synthfile",
    exits((1, 2), "synthfile"),
    setup="write_text('synthfile', 'x')",
)
cli("cli.synth_bogus_scene", C, "synth bogus --out {tmp}/sc", exits(2, "bogus"))
cli("cli.demo_size_zero", C, "demo --size 0 --out {tmp}/demo", exits(2, "size"))
cli("cli.calibrate_nothing", C, "calibrate", exits(2))
cli(
    "cli.calibrate_spheres_missing",
    C,
    "calibrate spheres {tmp}/nope --camera {SC}/rig.json --radius 20 --out {tmp}/r.json -q",
    exits(2, "nope"),
)
cli(
    "cli.calibrate_spheres_radius",
    C,
    "calibrate spheres {SC} --camera {SC}/rig.json --radius -1 --out {tmp}/r.json -q",
    exits(2, "--radius"),
)
cli(
    "cli.calibrate_spheres_camera_deep",
    C,
    "calibrate spheres {SC} --camera {tmp}/deep.json --radius 20 --out {tmp}/r.json -q",
    exits(2, "deep.json"),
    setup="write_text('deep.json', '[' * 10000 + ']' * 10000)",
)
cli(
    "cli.calibrate_intensity_no_rig",
    C,
    "calibrate intensity {SC} --plane-depth 200 --out {tmp}/r.json -q",
    exits(2, "--rig"),
)
cli(
    "cli.calibrate_intensity_plane_depth",
    C,
    "calibrate intensity {SC} --rig {SC}/rig.json --plane-depth -5 --out {tmp}/r.json -q",
    exits(2, "depth"),
)
cli(
    "cli.calibrate_intensity_plane_zero",
    C,
    "calibrate intensity {SC} --rig {SC}/rig.json --plane 0 0 0 5 --out {tmp}/r.json -q",
    exits(2, "plane"),
)
cli("cli.synth_calibration_size", C, "synth-calibration --size 8 --out {tmp}/c", exits(2, "--size"))

del C, name, value, code, key

# More cases, one module per area (``tests/probes_<area>.py``): each defines ``add(p)``, which
# registers its cases with ``p.api`` / ``p.cli`` (``p`` is this module, also when it runs as the
# worker's ``__main__``).
AREAS = ("results", "writes", "readers", "core", "rigs", "honesty")


def _add_areas() -> None:
    import importlib

    here = os.path.dirname(os.path.abspath(__file__))
    if here not in sys.path:
        sys.path.insert(0, here)
    this = sys.modules[__name__]
    for area in AREAS:
        try:
            module = importlib.import_module(f"probes_{area}")
        except ModuleNotFoundError as e:
            if e.name != f"probes_{area}":
                raise
            continue
        module.add(this)


_add_areas()


# --------------------------------------------------------------------------------------------------
# Worker
# --------------------------------------------------------------------------------------------------

BY_ID = {c.id: c for c in CASES}


def _prelude(base: os.PathLike[str]) -> dict[str, Any]:
    """The namespace the snippets run in: numpy, nplps, a small scene and helpers."""
    import copy
    import math
    import struct
    import warnings
    import zlib
    from pathlib import Path

    import imageio.v3 as iio
    import numpy as np
    import tifffile

    import nplps
    from nplps import InputError, NplpsError, Rig, RigError, SolverError

    base = Path(base)
    S = nplps.make_scene("bumps", n=16, seed=0)
    PS = nplps.make_scene("bumps", n=16, seed=0, camera="pinhole")
    SC, PSC = base / "scene", base / "pinhole-scene"
    S.save(SC)
    PS.save(PSC)
    for a in (S.depth, S.mask, S.albedo, S.images, PS.depth, PS.mask, PS.albedo, PS.images):
        a.setflags(write=False)
    ns: dict[str, Any] = {}
    #: What the helpers need of the case running: its directory and the warnings it raised.
    ctx: dict[str, Any] = {"tmp": base, "W": []}
    missing = object()

    def rec(images=missing, rig=missing, mask=missing, depth=missing, **kw):
        return nplps.reconstruct(
            S.images if images is missing else images,
            S.rig if rig is missing else rig,
            mask=S.mask if mask is missing else mask,
            depth=200.0 if depth is missing else depth,
            **kw,
        )

    def par(images=missing, rig=missing, mask=missing, depth=missing, **kw):
        return nplps.reconstruct_parallel(
            S.images if images is missing else images,
            S.rig if rig is missing else rig,
            mask=S.mask if mask is missing else mask,
            depth=200.0 if depth is missing else depth,
            **kw,
        )

    def used(mask):
        h, w = mask.shape
        u = np.zeros((h + 1, w + 1), dtype=bool)
        for dr in (0, 1):
            for dc in (0, 1):
                u[dr : dr + h, dc : dc + w] |= mask
        return u

    def honest(r):
        """A result that does not lie: converged is a bool (and agrees with status, if there is
        one); a converged result has finite depths, unit normals and finite albedo where fitted."""
        assert isinstance(r.converged, bool), f"converged is {r.converged!r}"
        status = getattr(r, "status", None)
        if status is not None:
            assert status in STATUSES, f"unknown status {status!r}"
            assert (status == "converged") == r.converged, f"status {status!r} but converged={r.converged}"
        if r.converged:
            u = used(r.mask)
            bad = int(np.count_nonzero(~np.isfinite(r.depth[u])))
            assert bad == 0, f"converged, but {bad} depths of masked vertices are not finite"
            fitted = r.mask & (r.lights_used >= 3)
            for n in (r.normals[fitted], r.fit_normals[fitted]):
                assert np.isfinite(n).all(), "converged, but normals of fitted pixels are not finite"
                assert np.allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-6), "normals are not unit vectors"
            assert np.isfinite(r.albedo[fitted]).all(), "converged, but albedo of fitted pixels is not finite"
        return True

    def good(r, scene=S, tol=1.0):
        """honest, converged and right: RMS depth error (after the mean offset) below tol (1 % of
        the object size)."""
        honest(r)
        assert r.converged, f"not converged after {len(r.history)} iterations"
        u = used(r.mask) & used(scene.mask)
        e = r.depth[u] - scene.depth[u]
        rms = float(np.sqrt(np.mean((e - e.mean()) ** 2)))
        assert rms < tol, f"RMS depth error {rms:.3g} (tolerance {tol})"
        return True

    def warned(fragment):
        return any(fragment.lower() in w.lower() for w in ctx["W"])

    def rig_dict(scene=S):
        return copy.deepcopy(scene.rig.to_dict())

    def rig_v1():
        return {
            "version": 1,
            "camera": dict(S.rig.camera),
            "lights": [{"position": [float(v) for v in p]} for p in S.rig.positions],
        }

    def path(name):
        p = Path(name)
        return p if p.is_absolute() else ctx["tmp"] / p

    def write_text(name, text):
        p = path(name)
        p.write_text(text, encoding="utf-8")
        return p

    def write_bytes(name, data):
        p = path(name)
        p.write_bytes(data)
        return p

    def write_json(name, data):
        return write_text(name, json.dumps(data))

    def png(name, array):
        p = path(name)
        a = np.asarray(array)
        if a.dtype == np.uint16:
            import png as pypng

            channels = 1 if a.ndim == 2 else a.shape[2]
            writer = pypng.Writer(
                a.shape[1], a.shape[0], greyscale=channels in (1, 2), alpha=channels in (2, 4), bitdepth=16
            )
            with open(p, "wb") as f:
                writer.write(f, a.reshape(a.shape[0], -1).tolist())
        else:
            iio.imwrite(p, a, extension=".png")
        return p

    def tiff(name, array):
        p = path(name)
        tifffile.imwrite(p, array)
        return p

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    def png_header_only(name, width, height, bit_depth=16):
        """A PNG whose header claims width x height grey pixels, with a few bytes of data."""
        ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, 0, 0, 0, 0)
        data = (
            b"\x89PNG\r\n\x1a\n"
            + chunk(b"IHDR", ihdr)
            + chunk(b"IDAT", zlib.compress(b"\0" * 4096))
            + chunk(b"IEND", b"")
        )
        return write_bytes(name, data)

    def tiff_header_only(name, width, height):
        """A little-endian TIFF whose one strip claims width x height 8-bit pixels."""
        entries = [
            (256, 4, width),
            (257, 4, height),
            (258, 3, 8),
            (259, 3, 1),
            (262, 3, 1),
            (273, 4, 0),
            (277, 3, 1),
            (278, 4, height),
            (279, 4, width * height),
        ]
        offset = 8 + 2 + 12 * len(entries) + 4
        ifd = struct.pack("<H", len(entries))
        for tag, kind, value in entries:
            value = offset if tag == 273 else value
            ifd += struct.pack("<HHI", tag, kind, 1) + (
                struct.pack("<HH", value, 0) if kind == 3 else struct.pack("<I", value)
            )
        return write_bytes(name, b"II*\x00" + struct.pack("<I", 8) + ifd + struct.pack("<I", 0) + b"\0" * 64)

    def bmp_header_only(name, width, height):
        header = b"BM" + struct.pack("<IHHI", 54 + 64, 0, 0, 54)
        header += struct.pack("<IiiHHIIiiII", 40, width, height, 1, 24, 0, 0, 2835, 2835, 0, 0)
        return write_bytes(name, header + b"\0" * 64)

    def jpeg_header_only(name, width, height):
        p = path(name)
        iio.imwrite(p, np.zeros((16, 16), np.uint8), extension=".jpg")
        b = bytearray(p.read_bytes())
        i = b.index(b"\xff\xc0")
        b[i + 5 : i + 9] = struct.pack(">HH", height, width)
        p.write_bytes(bytes(b))
        return p

    def imgs(scene_dir=SC):
        return [str(scene_dir / f"image_{i:02d}.png") for i in range(27)]

    def copy_scene(name, scene_dir=SC):
        import shutil

        return Path(shutil.copytree(scene_dir, path(name)))

    def orth(lights=None, directional=None, **kw):
        lights = S.rig.positions if lights is None else lights
        if directional is not None:
            lights, kw["directions"] = (), directional
        cam = S.rig.camera
        return Rig.orthographic(cam["pixel_size"][0], origin=cam["origin"], lights=lights, **kw)

    def render_for(rig):
        return nplps.render(S.depth, rig, S.albedo, mask=S.mask)

    def summary(directory):
        return json.loads((Path(directory) / "summary.json").read_text())

    ns.update(
        np=np,
        nplps=nplps,
        Rig=Rig,
        InputError=InputError,
        RigError=RigError,
        SolverError=SolverError,
        NplpsError=NplpsError,
        json=json,
        os=os,
        sys=sys,
        math=math,
        Path=Path,
        warnings=warnings,
        iio=iio,
        S=S,
        PS=PS,
        I=S.images,
        R=S.rig,
        M=S.mask,
        L=np.array(S.rig.positions),
        KP=PS.rig.K.tolist(),
        SC=SC,
        PSC=PSC,
        STATUSES=STATUSES,
        rec=rec,
        par=par,
        honest=honest,
        good=good,
        warned=warned,
        rig_dict=rig_dict,
        rig_v1=rig_v1,
        write_text=write_text,
        write_bytes=write_bytes,
        write_json=write_json,
        png=png,
        tiff=tiff,
        png_header_only=png_header_only,
        tiff_header_only=tiff_header_only,
        bmp_header_only=bmp_header_only,
        jpeg_header_only=jpeg_header_only,
        imgs=imgs,
        copy_scene=copy_scene,
        orth=orth,
        render_for=render_for,
        summary=summary,
        _ctx=ctx,
    )
    # The area modules' helpers (a saved result to damage, the command line in-process, ...).
    import probes_helpers

    ns.update(probes_helpers.helpers(ns))
    return ns


def _exception_class(name: str) -> type:
    import builtins

    import nplps

    cls = getattr(nplps, name, None) or getattr(builtins, name, None)
    if not (isinstance(cls, type) and issubclass(cls, BaseException)):
        raise ValueError(f"unknown exception class {name!r}")
    return cls


def _matches(text: str, fragments: list[list[str]]) -> list[str]:
    """The fragments (alternatives joined by '/') that ``text`` lacks: case-insensitive, and an
    underscore matches a space (the message "the prior weight ..." names ``prior_weight``)."""

    def norm(t: str) -> str:
        return t.lower().replace("_", " ")

    low = norm(text)
    return ["/".join(alts) for alts in fragments if not any(norm(a) in low for a in alts)]


def _short(text: str, n: int = 400) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= n else text[: n - 3] + "..."


def _check(expr: str | None, ns: dict[str, Any]) -> str | None:
    """None when ``expr`` holds, else why not."""
    if not expr:
        return None
    try:
        value = eval(expr, ns)
    except AssertionError as e:
        return f"check failed: {e}"
    except BaseException as e:
        return f"check raised {type(e).__name__}: {_short(e, 300)}"
    return None if value else f"check is false: {expr}"


def _judge_api(case: Case, ns: dict[str, Any], error: BaseException | None) -> tuple[bool, str]:
    import nplps

    e = case.expect
    kind = e["kind"]
    if error is None:
        happened = "returned"
        if kind in ("ok", "either"):
            why = _check(e.get("check"), ns)
            return (why is None, happened + ("" if why is None else f"; {why}"))
        return False, happened + " (no exception)" + (f"; warnings: {_short(ns['_W'], 200)}" if ns.get("_W") else "")
    happened = f"{type(error).__module__}.{type(error).__qualname__}: {_short(error)}".replace("builtins.", "")
    if kind == "ok":
        return False, happened
    if kind == "mem":
        if isinstance(error, MemoryError):
            return True, happened
        if isinstance(error, nplps.NplpsError) and not _matches(str(error), e["fragments"]):
            return True, happened
        return False, happened
    classes = tuple(_exception_class(n) for n in e["cls"].split("|"))
    if not isinstance(error, classes):
        return False, happened
    lacking = _matches(str(error), e["fragments"])
    if lacking:
        return False, happened + f"  [message lacks {', '.join(map(repr, lacking))}]"
    return True, happened


def _run_api(case: Case, ns: dict[str, Any]) -> tuple[bool, str]:
    import warnings

    error = None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            exec(compile(case.code, f"<probe {case.id}>", "exec"), ns)
        except BaseException as exc:
            error = exc
    ns["_W"] = ns["_ctx"]["W"] = [str(w.message) for w in caught]
    return _judge_api(case, ns, error)


def _run_cli(case: Case, ns: dict[str, Any]) -> tuple[bool, str]:
    import contextlib
    import io
    import subprocess
    import warnings

    if case.code:
        exec(compile(case.code, f"<setup {case.id}>", "exec"), ns)
    argv = shlex.split(case.argv.format(tmp=ns["tmp"], SC=ns["SC"], PSC=ns["PSC"]))
    uncaught = None
    if case.proc:
        p = subprocess.run(
            [sys.executable, "-m", "nplps", *argv], capture_output=True, text=True, timeout=case.budget, cwd=ns["tmp"]
        )
        code, out, err = p.returncode, p.stdout, p.stderr
    else:
        from nplps.cli import main

        out_io, err_io = io.StringIO(), io.StringIO()
        cwd = os.getcwd()
        os.chdir(ns["tmp"])
        try:
            # The interpreter's default warning filters, as for the console script.
            with warnings.catch_warnings(), contextlib.redirect_stdout(out_io), contextlib.redirect_stderr(err_io):
                try:
                    code = main(argv)
                except SystemExit as exc:  # what the console script would do
                    code = exc.code if isinstance(exc.code, int) else 1
                except BaseException as exc:
                    uncaught, code = exc, 1
        finally:
            os.chdir(cwd)
        out, err = out_io.getvalue(), err_io.getvalue()
    ns.update(code=code, out=out, err=err)
    e = case.expect
    tail = _short(err[-600:], 300) if err.strip() else "(empty stderr)"
    if uncaught is not None:
        return False, f"uncaught {type(uncaught).__name__} escaped main() (a traceback): {_short(uncaught, 300)}"
    happened = f"exit {code}; stderr: {tail}"
    if "Traceback (most recent call last)" in err:
        return False, "traceback in stderr; " + happened
    if code not in e["codes"]:
        return False, happened
    lacking = _matches(err, e["fragments"])
    if lacking:
        return False, happened + f"  [stderr lacks {', '.join(map(repr, lacking))}]"
    why = _check(e.get("check"), ns)
    return (why is None, happened + ("" if why is None else f"; {why}"))


def worker(results_path: str, ids: list[str]) -> None:
    """Runs the cases ``ids`` in this interpreter; appends start/end JSON lines to results_path."""
    import faulthandler
    import shutil
    import tempfile
    from pathlib import Path

    faulthandler.enable()
    base = Path(tempfile.mkdtemp(prefix="nplps-probes-"))
    results = open(results_path, "a", encoding="utf-8", buffering=1)
    try:
        base_ns = _prelude(base / "shared")
        for n, case_id in enumerate(ids):
            case = BY_ID[case_id]
            results.write(json.dumps({"id": case_id, "event": "start"}) + "\n")
            results.flush()
            tmp = base / f"case{n}"
            tmp.mkdir()
            ns = dict(base_ns, tmp=tmp)
            ns["_ctx"].update(tmp=tmp, W=[])
            start = time.perf_counter()
            try:
                passed, happened = (_run_api if case.kind == "api" else _run_cli)(case, ns)
            except BaseException as exc:
                passed, happened = False, f"probe setup failed: {type(exc).__name__}: {_short(exc)}"
            seconds = time.perf_counter() - start
            results.write(
                json.dumps({"id": case_id, "event": "end", "passed": passed, "happened": happened, "seconds": seconds})
                + "\n"
            )
            results.flush()
            shutil.rmtree(tmp, ignore_errors=True)
            del ns
    finally:
        results.close()
        shutil.rmtree(base, ignore_errors=True)


if __name__ == "__main__":
    if len(sys.argv) >= 3 and sys.argv[1] == "--worker":
        worker(sys.argv[2], sys.argv[3:])
    else:
        print(f"{len(CASES)} cases; run them with: python tests/test_probes.py --table", file=sys.stderr)
