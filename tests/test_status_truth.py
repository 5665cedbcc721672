"""Status that tells the truth (issue 18, item 8): what a refinement returns is what its status says."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import nplps


def _perturbed(seed: int, sd: float = 6.0) -> tuple[nplps.Scene, nplps.Rig]:
    s = nplps.make_scene("bumps", n=48, seed=seed)
    rig = s.rig.with_positions(s.rig.positions + np.random.default_rng(seed + 10).normal(0, sd, (27, 3)))
    return s, rig


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_stiff_prior_does_not_return_the_flat_start(seed: int) -> None:
    s, rig = _perturbed(seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = nplps.reconstruct(
            s.images, rig, depth=s.mean_depth, mask=s.mask, refine_lights="position", light_prior_weight=1e9
        )
    # The start is a plane (depth std ~1e-14); the surface has bumps of several mm.
    assert np.nanstd(r.depth) > 0.3 * np.nanstd(s.depth)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_successful_position_refinement_is_not_diverged(seed: int) -> None:
    s, rig = _perturbed(seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plain = nplps.reconstruct(s.images, rig, depth=s.mean_depth, mask=s.mask)
        refined = nplps.reconstruct(s.images, rig, depth=s.mean_depth, mask=s.mask, refine_lights="position")

    def error(r: nplps.Reconstruction) -> float:
        return float(np.sqrt(np.nanmean((r.depth - s.depth) ** 2)))

    assert refined.refinement is not None and not refined.refinement.fell_back
    assert error(refined) < 0.5 * error(plain)  # the refinement helped a lot
    assert refined.status != "diverged", refined.summary()["status_reason"]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_fallen_back_refinement_is_assessed_on_the_run_it_returns(seed: int) -> None:
    """With exact lights the refinement cannot lower the residual and falls back: the plain run is
    returned, so the status must quote the plain run's iterations and depth change, not the
    discarded refined run's."""
    import re

    s = nplps.make_scene("bumps", n=32, seed=seed)
    r = nplps.reconstruct(s.images, s.rig, depth=s.mean_depth, mask=s.mask, refine_lights="position", levels=1)
    assert r.refinement is not None and r.refinement.fell_back
    # Both runs are in the history (each from iteration 1); the plain one comes first.
    starts = [i for i, h in enumerate(r.history) if h.iteration == 1]
    assert len(starts) == 2
    plain = r.history[: starts[1]]
    assert r.status == "converged"
    found = re.search(r"iteration (\d+) \(([-0-9.e+]+)\)", r.status_reason)
    assert found is not None, r.status_reason
    assert int(found.group(1)) == len(plain)
    assert float(found.group(2)) == pytest.approx(plain[-1].depth_change, rel=1e-5)
