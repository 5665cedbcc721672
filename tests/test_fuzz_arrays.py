"""Fuzzing of the array inputs of a reconstruction (issue 9).

Hypothesis generates image stacks, masks, depths (scalars and maps), validity masks and options,
mixing sensible values with hostile ones (NaN, infinities, negatives, zeros, huge and tiny values,
wrong shapes and dtypes, complex numbers), and runs ``nplps.reconstruct`` and
``nplps.reconstruct_parallel`` on them. The only outcomes allowed are an nplps exception with a
short message, or a result that does not lie: a status among the four, ``converged`` exactly when
the status says so, and finite depths, unit normals and finite albedo on the fitted pixels of a
converged result.

Each property runs 60 examples by default (CI); ``NPLPS_FUZZ_EXAMPLES=5000`` runs a long session.
"""

from __future__ import annotations

import os
import warnings

import numpy as np
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

import nplps

EXAMPLES = int(os.environ.get("NPLPS_FUZZ_EXAMPLES", "60"))
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
STATUSES = ("converged", "stalled", "diverged", "degenerate")
N = 12
SCENE = nplps.make_scene("bumps", n=N)
K = SCENE.rig.n_lights

#: Values hostile to a solver, mixed into otherwise sensible arrays.
SPECIAL = st.sampled_from([np.nan, np.inf, -np.inf, 0.0, -1.0, 1e30, 1e-30, 5e-324, 1.0, 0.5])


@st.composite
def images(draw: st.DrawFn) -> np.ndarray:
    base = SCENE.images.astype(np.float64) * draw(st.sampled_from([1.0, 1.0, 1.0, 1e-6, 1e6, 0.0, -1.0]))
    if draw(st.booleans()):
        base = base + draw(st.floats(0, 0.2)) * np.random.default_rng(draw(st.integers(0, 99))).standard_normal(
            base.shape
        )
    count = draw(st.sampled_from([0, 0, 0, 1, 3, 40]))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    flat = base.reshape(-1)
    for i in rng.integers(0, flat.size, count):
        flat[i] = draw(SPECIAL)
    dtype = draw(st.sampled_from([np.float32, np.float64, np.uint16, np.uint8]))
    if np.issubdtype(dtype, np.integer):
        top = np.iinfo(dtype).max
        with np.errstate(invalid="ignore"):
            return np.clip(np.nan_to_num(base, nan=0, posinf=1, neginf=0), 0, 1).__mul__(top).astype(dtype)
    with np.errstate(over="ignore"):
        return base.astype(dtype)


@st.composite
def masks(draw: st.DrawFn) -> np.ndarray | None:
    kind = draw(st.sampled_from(["none", "full", "random", "empty", "line", "single"]))
    if kind == "none":
        return None
    m = np.zeros((N, N), bool)
    if kind == "full":
        m[:] = True
    elif kind == "random":
        m = np.random.default_rng(draw(st.integers(0, 999))).random((N, N)) < draw(st.floats(0.05, 0.95))
    elif kind == "line":
        m[N // 2] = True
    elif kind == "single":
        m[draw(st.integers(0, N - 1)), draw(st.integers(0, N - 1))] = True
    return m


@st.composite
def depths(draw: st.DrawFn) -> object:
    kind = draw(st.sampled_from(["true", "true", "scalar", "special", "map", "map", "map_special"]))
    if kind == "true":
        return SCENE.mean_depth
    if kind == "scalar":
        return draw(st.one_of(st.floats(100, 400), st.floats(1e-3, 1e7)))
    if kind == "special":
        return draw(SPECIAL)
    z = np.full((N + 1, N + 1), SCENE.mean_depth) + draw(st.floats(-50, 50)) * np.random.default_rng(
        draw(st.integers(0, 99))
    ).random((N + 1, N + 1))
    if kind == "map_special":
        z.reshape(-1)[draw(st.integers(0, z.size - 1))] = draw(SPECIAL)
    return z


@st.composite
def valids(draw: st.DrawFn) -> np.ndarray | None:
    if draw(st.booleans()):
        return None
    return np.random.default_rng(draw(st.integers(0, 999))).random((K, N, N)) < draw(st.floats(0.0, 1.0))


def _check_outcome(call) -> None:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = call()
    except nplps.NplpsError as e:
        event(f"raised {type(e).__name__}")
        assert len(str(e)) < 1000, f"message of {len(str(e))} characters"
        assert str(e).strip(), "empty message"
        return
    assert r.status in STATUSES
    event(f"status {r.status}")
    assert r.converged == (r.status == "converged")
    if r.converged:
        fitted = r.mask & (r.lights_used >= 3)
        for n in (r.normals[fitted], r.fit_normals[fitted]):
            assert np.isfinite(n).all(), "converged, but normals of fitted pixels are not finite"
            assert np.allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-6)
        assert np.isfinite(r.albedo[fitted]).all(), "converged, but albedo of fitted pixels is not finite"
        used = np.zeros((N + 1, N + 1), bool)
        for dr in (0, 1):
            for dc in (0, 1):
                used[dr : dr + N, dc : dc + N] |= r.mask
        assert np.isfinite(r.depth[used]).all(), "converged, but depths are not finite"


@FUZZ
@given(
    images=images(),
    mask=masks(),
    depth=depths(),
    valid=valids(),
    robust=st.sampled_from([None, "cauchy", "tukey"]),
    iterations=st.integers(1, 30),
    levels=st.sampled_from([None, 1, 2]),
)
def test_reconstruct_never_crashes_or_lies(images, mask, depth, valid, robust, iterations, levels):
    _check_outcome(
        lambda: nplps.reconstruct(
            images, SCENE.rig, mask=mask, depth=depth, valid=valid, robust=robust, iterations=iterations, levels=levels
        )
    )


@FUZZ
@given(images=images(), mask=masks(), depth=depths(), valid=valids())
def test_the_parallel_baseline_never_crashes_or_lies(images, mask, depth, valid):
    _check_outcome(lambda: nplps.reconstruct_parallel(images, SCENE.rig, mask=mask, depth=depth, valid=valid))


@FUZZ
@given(
    shape=st.lists(st.integers(0, 5), min_size=0, max_size=5).map(tuple),
    dtype=st.sampled_from([np.float32, np.float64, np.complex64, np.int8, np.bool_, object, "U3"]),
)
def test_arrays_of_any_shape_and_dtype_are_refused_cleanly(shape, dtype):
    try:
        a = np.zeros(shape, dtype=dtype)
    except (TypeError, ValueError):
        return  # numpy cannot make this array
    for call in (
        lambda: nplps.reconstruct(a, SCENE.rig, depth=200.0),
        lambda: nplps.reconstruct(SCENE.images, SCENE.rig, mask=a, depth=200.0),
        lambda: nplps.reconstruct(SCENE.images, SCENE.rig, depth=a),
    ):
        _check_outcome(call)
