"""The typed boundary of the compiled core (nplps._core): its option mappings are read strictly
(an unknown key is an InputError naming it and the valid keys, never a silent default), and its
result mappings hold the keys their TypedDicts (nplps._core_types) declare."""

from __future__ import annotations

import numpy as np
import pytest

import nplps
from nplps import _core, _core_types
from nplps.errors import InputError


def _keys(td: type) -> frozenset[str]:
    return td.__required_keys__ | td.__optional_keys__


@pytest.fixture(scope="module")
def scene() -> nplps.synth.Scene:
    return nplps.make_scene("sphere", n=12)


def _call(scene: nplps.synth.Scene, options: dict[str, object]) -> dict[str, object]:
    images = np.ascontiguousarray(scene.images, dtype=np.float32)
    return dict(
        _core.reconstruct(
            images,
            scene.rig._native,
            scene.mask,
            200.0,
            options,
            None,  # type: ignore[arg-type]
        )
    )


def test_unknown_option_keys_are_refused(scene: nplps.synth.Scene) -> None:
    with pytest.raises(InputError, match=r'unknown option "prior_weigth"; the options are .*prior_weight'):
        _call(scene, {"prior_weigth": 2.0})
    with pytest.raises(InputError, match=r'unknown option "levels"'):
        _core.synth_scene("sphere", 4, 100.0, 200.0, 0, levels=2)  # type: ignore[call-arg]
    images = np.zeros((3, 8, 8), dtype=np.float32)
    with pytest.raises(InputError, match=r'unknown option "fit_axis"; the options are albedo, dark, fit_direction'):
        _core.calibrate_intensities(
            images,
            None,
            _core.Rig(
                {"model": "orthographic", "pixel_size": [1, 1], "origin": [0, 0]},
                {
                    "vectors": [[0, 0, -10]] * 3,
                    "directional": [False] * 3,
                    "intensities": [[1, 1, 1]] * 3,
                    "axes": [[0, 0, 1]] * 3,
                    "mu": [0.0] * 3,
                },
            ),
            [0.0, 0.0, -1.0],
            -100.0,
            {"fit_axis": True},  # type: ignore[typeddict-unknown-key]
        )


def test_every_declared_option_is_accepted(scene: nplps.synth.Scene) -> None:
    # Each key of ReconstructOptions, set to None, takes the core's default.
    keys = _keys(_core_types.ReconstructOptions)
    out = _call(scene, dict.fromkeys(keys))
    assert out["status"] in ("converged", "stalled")


def test_results_hold_their_declared_keys(scene: nplps.synth.Scene) -> None:
    out = _call(scene, {"iterations": 3})
    declared = _core_types.ReconstructionDict.__required_keys__
    assert declared <= out.keys() <= _keys(_core_types.ReconstructionDict)
    assert set(out["timings"]) == _keys(_core_types.TimingsDict)  # type: ignore[call-overload]
    refined = out["lights"]
    assert isinstance(refined, _core.Rig)
    assert set(refined.lights) == _keys(_core_types.LightsDict)
    s = _core.synth_scene("sphere", 4, 100.0, 200.0, 0, pinhole=True)
    assert set(s) == _keys(_core_types.SceneDict)
    assert set(s["rig"].camera) == {"model", "K", "distortion"}
