"""Processes that never abort or hang (issue 9): fork safety, huge iteration limits, strict rig
files. Each case runs where a failure cannot take the test session down with it (a forked or
spawned child with a time limit)."""

from __future__ import annotations

import multiprocessing
import os
import sys
import time

import numpy as np
import pytest

import nplps
from nplps import RigError


def _small_run(_: int = 0) -> float:
    scene = nplps.make_scene("sphere", n=24, seed=0)
    result = nplps.reconstruct(scene.images, scene.rig, scene.mask, scene.mean_depth, iterations=5)
    return float(np.nanmean(result.depth))


@pytest.mark.skipif(not hasattr(os, "fork"), reason="os.fork is POSIX only")
def test_forked_child_does_not_hang():
    _small_run()  # the parent has used nplps (and rayon's global pool) before the fork
    pid = os.fork()
    if pid == 0:  # child
        try:
            ok = np.isfinite(_small_run())
            os._exit(0 if ok else 1)
        except BaseException:
            os._exit(2)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0
            return
        time.sleep(0.05)
    os.kill(pid, 9)
    os.waitpid(pid, 0)
    pytest.fail("nplps hung in a forked child")


@pytest.mark.parametrize("method", [m for m in ("fork", "spawn", "forkserver") if m in multiprocessing.get_all_start_methods()])
def test_multiprocessing_pool(method):
    _small_run()
    context = multiprocessing.get_context(method)
    with context.Pool(2) as pool:
        values = pool.map_async(_small_run, range(4)).get(timeout=180)
    assert np.allclose(values, values[0]) and np.isfinite(values[0])


@pytest.mark.parametrize("iterations", [10**9, sys.maxsize])
def test_huge_iteration_limits_do_not_abort(iterations):
    """The history grows as iterations run: no allocation for the limit up front."""
    scene = nplps.make_scene("sphere", n=24, seed=0)
    result = nplps.reconstruct(scene.images, scene.rig, scene.mask, scene.mean_depth, iterations=iterations, tol=1e-3)
    assert result.converged and len(result.history) < 100


def test_led_without_direction_in_a_rig_file_is_an_error(tmp_path):
    data = {
        "version": 2,
        "camera": {"model": "orthographic", "pixel_size": [1, 1], "origin": [0, 0]},
        "lights": [{"type": "point", "position": [i, 0, 0], "mu": 1.0} for i in range(3)],
    }
    with pytest.raises(RigError, match="needs its principal 'direction'"):
        nplps.Rig.from_dict(data)


def _sphere():
    return nplps.make_scene("sphere", n=32, seed=0)


@pytest.mark.parametrize(
    "lights",
    [
        [[0, 0, 50.0], [0, 0, 80], [0, 0, 110]],  # collinear with the object
        [[10, 0, 50.0], [10, 0, 50], [10, 0, 50]],  # coincident
    ],
)
def test_degenerate_light_geometry_is_a_rig_error(lights):
    scene = _sphere()
    rig = nplps.Rig(camera=scene.rig.camera, lights=np.array(lights))
    with pytest.raises(RigError, match="cannot determine the normals"):
        nplps.reconstruct(scene.images[:3], rig, scene.mask, 200.0)


def test_very_distant_lights_are_a_rig_error_for_both_methods():
    scene = _sphere()
    far = scene.rig.lights.copy()
    far[:, 2] = -1e6
    rig = nplps.Rig(camera=scene.rig.camera, lights=far)
    with pytest.raises(RigError, match="cannot determine the normals"):
        nplps.reconstruct(scene.images, rig, scene.mask, 200.0)
    with pytest.raises(RigError, match="cannot determine the normals"):
        nplps.reconstruct_parallel(scene.images, rig, scene.mask, 200.0)


@pytest.mark.parametrize(
    "case",
    ["zeros", "negative", "dark above every value", "valid all False"],
)
def test_nothing_fittable_is_an_input_error(case):
    scene = _sphere()
    images, kwargs = scene.images, {}
    if case == "zeros":
        images = np.zeros_like(images)
    elif case == "negative":
        images = -np.ones_like(images)
    elif case == "dark above every value":
        kwargs = dict(dark=10.0, saturation=20.0)
    else:
        kwargs = dict(valid=np.zeros(images.shape, dtype=bool))
    with pytest.raises(nplps.InputError, match="no masked pixel has 3 or more usable observations"):
        nplps.reconstruct(images, scene.rig, scene.mask, 200.0, **kwargs)
    with pytest.raises(nplps.InputError, match="no masked pixel"):
        nplps.reconstruct_parallel(images, scene.rig, scene.mask, 200.0, **kwargs)


def test_mostly_unfitted_result_warns():
    scene = _sphere()
    images = scene.images.copy()
    images[3:] = 0.0  # only 3 lights light anything: fitted, but
    images[:, :20] = 0.0  # most rows see nothing
    with pytest.warns(RuntimeWarning, match="had fewer than 3 usable observations"):
        nplps.reconstruct(images, scene.rig, scene.mask, 200.0)


@pytest.mark.parametrize(
    "kwargs, fragment",
    [
        (dict(iterations="ten"), "iterations"),
        (dict(iterations=1.5), "iterations"),
        (dict(iterations=True), "iterations"),
        (dict(tol="x"), "tol"),
        (dict(depth=200 + 1j), "depth"),
        (dict(depth=np.full((17, 17), 200 + 1j)), "real numbers"),
        (dict(depth="auto", depth_range="100,400"), "depth_range"),
        (dict(depth="auto", depth_range=(float("nan"), 400)), "depth_range"),
        (dict(depth="auto", depth_range=(400, 100)), "near < far"),
        (dict(depth="auto", depth_guess="x"), "depth_guess"),
        (dict(prior_weight="a"), "prior_weight"),
    ],
)
def test_bad_arguments_are_input_errors(kwargs, fragment):
    scene = nplps.make_scene("sphere", n=16, seed=0)
    kwargs = {"depth": 200.0, **kwargs}
    with pytest.raises(nplps.InputError, match=fragment):
        nplps.reconstruct(scene.images, scene.rig, scene.mask, **kwargs)


def test_bad_images_scene_size_and_prediction_index_are_input_errors():
    scene = nplps.make_scene("sphere", n=16, seed=0)
    with pytest.raises(nplps.InputError, match="images must be"):
        nplps.reconstruct(12, scene.rig, scene.mask, 200.0)
    with pytest.raises(nplps.InputError, match="at least 2"):
        nplps.make_scene("sphere", n=-4)
    result = nplps.reconstruct(scene.images, scene.rig, scene.mask, 200.0)
    with pytest.raises(nplps.InputError, match="indices of the rig's 27 lights"):
        result.predict(lights=[99])


@pytest.mark.parametrize("extension", [".jpg", ".bmp", ".png", ".tiff"])
def test_pixel_limit_applies_to_every_image_format(tmp_path, extension):
    """A decompression bomb is refused from the header, whatever the format."""
    import imageio.v3 as iio

    from nplps import io

    path = tmp_path / f"image{extension}"
    iio.imwrite(path, np.zeros((40, 30), dtype=np.uint8))
    with pytest.raises(nplps.InputError, match="pixels is more than the limit of 1000 pixels"):
        io.read_image(path, max_pixels=1000)
    assert io.read_image(path, max_pixels=1200).shape == (40, 30)
