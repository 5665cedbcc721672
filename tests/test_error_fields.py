"""The core's errors reach Python with their fields as attributes, set from real failing calls."""

import pickle

import pytest

import nplps
from nplps import _core
from nplps.errors import InputError, MemoryLimitError


@pytest.fixture(scope="module")
def scene() -> nplps.synth.Scene:
    return nplps.make_scene("sphere", n=16)


def test_memory_limit_error_carries_needed_and_limit(scene: nplps.synth.Scene) -> None:
    with pytest.raises(MemoryLimitError) as info:
        nplps.reconstruct(scene.images, scene.rig, depth=scene.mean_depth, mask=scene.mask, max_memory=1000)
    e = info.value
    assert e.limit == 1000
    assert isinstance(e.needed, int) and e.needed > 1000
    assert e.explicit is True
    assert e.what is not None and e.what.startswith("reconstructing 16 x 16 pixels")
    assert "above the limit of 1.00 kB (the max_memory given)" in str(e)


def test_out_of_range_option_carries_argument_and_value(scene: nplps.synth.Scene) -> None:
    with pytest.raises(InputError, match=r"^tol must be >= 0, got -1$") as info:
        nplps.reconstruct(scene.images, scene.rig, depth=scene.mean_depth, mask=scene.mask, tol=-1.0)
    assert info.value.argument == "tol"
    assert info.value.value == -1.0


def test_bad_choice_carries_argument_and_value(scene: nplps.synth.Scene) -> None:
    with pytest.raises(InputError, match=r'^robust must be None, "cauchy" or "tukey", got "huber"$') as info:
        nplps.reconstruct(scene.images, scene.rig, depth=scene.mean_depth, mask=scene.mask, robust="huber")  # type: ignore[arg-type]
    assert (info.value.argument, info.value.value) == ("robust", "huber")


def test_unknown_core_option_names_it() -> None:
    with pytest.raises(
        InputError, match=r'^unknown option "tolerance"; the options are directional, led, pinhole, rgb$'
    ) as info:
        _core.synth_scene("sphere", 8, 1.0, 10.0, 0, tolerance=1)  # type: ignore[call-arg]
    assert info.value.argument == "tolerance"
    assert info.value.value is None


def test_python_raised_errors_have_none_fields() -> None:
    e = InputError("a message")
    assert (e.argument, e.value, e.expected, e.got, e.index, e.path) == (None,) * 6
    m = MemoryLimitError("too big")
    assert (m.what, m.needed, m.limit, m.explicit) == (None,) * 4


def test_fields_survive_pickling(scene: nplps.synth.Scene) -> None:
    with pytest.raises(InputError) as info:
        nplps.reconstruct(scene.images, scene.rig, depth=scene.mean_depth, mask=scene.mask, tol=-1.0)
    again = pickle.loads(pickle.dumps(info.value))
    assert (again.argument, again.value, str(again)) == ("tol", -1.0, "tol must be >= 0, got -1")


def test_progress_and_history_are_named_records(scene: nplps.synth.Scene) -> None:
    seen: list[nplps.Iteration] = []
    result = nplps.reconstruct(scene.images, scene.rig, depth=scene.mean_depth, mask=scene.mask, progress=seen.append)
    assert seen and all(isinstance(it, nplps.Iteration) for it in seen)
    assert [it.iteration for it in seen][: len(result.history)] == [h.iteration for h in result.history]
    assert all(isinstance(h, nplps.Iteration) and h.candidate == 0 for h in result.history)
