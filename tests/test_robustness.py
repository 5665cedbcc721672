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
    result = nplps.reconstruct(scene.images, scene.rig, mask=scene.mask, depth=scene.mean_depth, iterations=5)
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


@pytest.mark.parametrize(
    "method", [m for m in ("fork", "spawn", "forkserver") if m in multiprocessing.get_all_start_methods()]
)
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
    result = nplps.reconstruct(
        scene.images, scene.rig, mask=scene.mask, depth=scene.mean_depth, iterations=iterations, tol=1e-3
    )
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
        nplps.reconstruct(scene.images[:3], rig, mask=scene.mask, depth=200.0)


def test_very_distant_lights_are_a_rig_error_for_both_methods():
    scene = _sphere()
    far = scene.rig.positions.copy()
    far[:, 2] = -1e6
    rig = nplps.Rig(camera=scene.rig.camera, lights=far)
    with pytest.raises(RigError, match="cannot determine the normals"):
        nplps.reconstruct(scene.images, rig, mask=scene.mask, depth=200.0)
    with pytest.raises(RigError, match="cannot determine the normals"):
        nplps.reconstruct_parallel(scene.images, rig, mask=scene.mask, depth=200.0)


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
        nplps.reconstruct(images, scene.rig, mask=scene.mask, depth=200.0, **kwargs)
    with pytest.raises(nplps.InputError, match="no masked pixel"):
        nplps.reconstruct_parallel(images, scene.rig, mask=scene.mask, depth=200.0, **kwargs)


def test_mostly_unfitted_result_warns():
    scene = _sphere()
    images = scene.images.copy()
    images[3:] = 0.0  # only 3 lights light anything: fitted, but
    images[:, :20] = 0.0  # most rows see nothing
    with pytest.warns(RuntimeWarning, match="had fewer than 3 usable observations"):
        nplps.reconstruct(images, scene.rig, mask=scene.mask, depth=200.0)


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
        nplps.reconstruct(scene.images, scene.rig, mask=scene.mask, **kwargs)


def test_bad_images_scene_size_and_prediction_index_are_input_errors():
    scene = nplps.make_scene("sphere", n=16, seed=0)
    with pytest.raises(nplps.InputError, match="images must be"):
        nplps.reconstruct(12, scene.rig, mask=scene.mask, depth=200.0)
    with pytest.raises(nplps.InputError, match="at least 2"):
        nplps.make_scene("sphere", n=-4)
    result = nplps.reconstruct(scene.images, scene.rig, mask=scene.mask, depth=200.0)
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


# --------------------------------------------------------------------------------------------------
# Bad arguments of the Python API and the command line name the argument (probe suite, issue 9)
# --------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sphere16():
    return nplps.make_scene("sphere", n=16, seed=0)


def _short_message(error: BaseException) -> str:
    """The message, checked to hold no number of more than 12 digits in a row."""
    import re

    message = str(error)
    assert not re.search(r"\d{13}", message), message
    return message


@pytest.mark.parametrize(
    "kwargs, fragment",
    [
        ({"dark": "x"}, "dark must be a real number"),
        ({"dark": 1j}, "dark must be a real number"),
        ({"saturation": "x"}, "saturation must be a real number"),
        ({"threads": "x"}, "threads must be a whole number"),
        ({"threads": 2.5}, "threads must be a whole number"),
        ({"threads": 10**6}, "threads must be at most 1024"),
        ({"threads": 2**64}, "threads must be at most 1024"),
        ({"depth_prior": "x"}, "depth_prior must be an array of real numbers"),
        ({"depth_prior": np.full((17, 17), 200.0 + 1j)}, "depth_prior must be an array of real numbers.*complex"),
        ({"color": "no"}, "color must be None, True or False"),
        ({"depth": np.nan}, r"depth \(the working distance\) must be a positive finite number, got nan"),
        ({"depth": np.inf}, r"depth \(the working distance\) must be a positive finite number, got inf"),
        ({"depth": 0.0}, r"depth \(the working distance\) must be a positive finite number, got 0"),
        ({"depth": 1e300}, r"depth \(the working distance\) is 1e\+300, more than 1e\+06 times the rig's size"),
    ],
)
def test_bad_options_name_the_argument(sphere16, kwargs, fragment):
    s = sphere16
    start = time.monotonic()
    with pytest.raises(nplps.InputError, match=fragment) as info:
        nplps.reconstruct(s.images, s.rig, mask=s.mask, **{"depth": 200.0, **kwargs})
    _short_message(info.value)
    assert time.monotonic() - start < 5  # threads=10**6 fails before starting any thread
    if "depth_prior" not in kwargs:
        with pytest.raises(nplps.InputError, match=fragment):
            nplps.reconstruct_parallel(s.images, s.rig, mask=s.mask, **{"depth": 200.0, **kwargs})


def test_threads_bound_is_documented():
    assert nplps.api.MAX_THREADS == 1024
    assert "MAX_THREADS" in nplps.reconstruct.__doc__


def test_absurd_depth_map_values_name_the_depth(sphere16):
    s = sphere16
    z = s.depth.copy()
    z[8, 8] = 1e300
    with pytest.raises(
        nplps.InputError, match=r"depth \(the initial depth map\) is 1e\+300 at vertex \(row 8, column 8\)"
    ):
        nplps.reconstruct(s.images, s.rig, mask=s.mask, depth=z)
    # the same value at a vertex no masked pixel uses is ignored, like a NaN there
    mask = s.mask.copy()
    mask[:4] = False
    z = s.depth.copy()
    z[0, 0] = 1e300
    assert (
        mask[:4].sum() == 0
        and nplps.reconstruct(s.images, s.rig, mask=mask, depth=z, iterations=2).depth.shape == z.shape
    )
    with pytest.raises(nplps.InputError, match=r"depth_prior is 1e\+300"):
        prior = s.depth.copy()
        prior[8, 8] = 1e300
        nplps.reconstruct(s.images, s.rig, mask=s.mask, depth=200.0, depth_prior=prior)
    # a plausible far distance still reaches the solver (which blames the lights' geometry)
    with pytest.raises(nplps.RigError, match="lights cannot determine the normals"):
        nplps.reconstruct(s.images, s.rig, mask=s.mask, depth=1e7)


def test_parallel_baseline_refuses_auto_depth(sphere16):
    s = sphere16
    with pytest.raises(nplps.InputError, match='depth="auto" is not supported by the parallel-light baseline'):
        nplps.reconstruct_parallel(s.images, s.rig, mask=s.mask, depth="auto")


@pytest.mark.parametrize(
    "kwargs, fragment",
    [
        ({"name": None}, "name must be one of the scenes"),
        ({"size": "x"}, "size must be a real number"),
        ({"distance": "x"}, "distance must be a real number"),
        ({"noise": "x"}, "noise .* must be a real number"),
        ({"noise": np.inf}, "noise .* must be a finite number >= 0, got inf"),
        ({"seed": "x"}, "seed must be a whole number"),
        ({"seed": -1}, "seed must be at least 0"),
        ({"seed": 2**64}, r"seed must be less than 2\*\*64"),
    ],
)
def test_make_scene_bad_arguments(kwargs, fragment):
    kwargs = {"name": "bumps", "n": 16, **kwargs}
    with pytest.raises(nplps.InputError, match=fragment) as info:
        nplps.make_scene(**kwargs)
    _short_message(info.value)


def test_render_bad_arguments_and_unknown_depths(sphere16):
    s = sphere16
    for depth in ("x", s.depth + 1j, None):
        with pytest.raises(nplps.InputError, match="depth must be an array of real numbers"):
            nplps.render(depth, s.rig)
    with pytest.raises(nplps.InputError, match=r"albedo must be .* got shape \(5, 5\)"):
        nplps.render(s.depth, s.rig, np.ones((5, 5)))
    with pytest.raises(nplps.InputError, match="albedo must be an array of real numbers"):
        nplps.render(s.depth, s.rig, "x")
    with pytest.raises(nplps.InputError, match=r"rig must be an nplps\.Rig, got str"):
        nplps.render(s.depth, "x")
    # A NaN vertex: its four pixels are unknown (NaN), not shadowed (0); outside the mask, 0.
    z = s.depth.copy()
    z[8, 8] = np.nan
    out = nplps.render(z, s.rig)
    assert np.isnan(out[:, 7:9, 7:9]).all()
    assert np.isfinite(out).sum() == out.size - 4 * len(out)
    mask = np.ones((16, 16), dtype=bool)
    mask[7, 7] = False
    out = nplps.render(z, s.rig, 1.0, mask=mask)
    assert (out[:, 7, 7] == 0).all() and np.isnan(out[:, 8, 8]).all()


def test_predict_and_held_out_bad_arguments(sphere16):
    s = sphere16
    result = nplps.reconstruct(s.images, s.rig, mask=s.mask, depth=200.0, iterations=2)
    with pytest.raises(nplps.InputError, match="lights must be a list of light indices, got 5"):
        result.predict(lights=5)
    with pytest.raises(nplps.InputError, match=r"got 1 \(float\)"):
        result.predict(lights=[1.0])
    with pytest.raises(nplps.InputError, match=r"rig must be an nplps\.Rig, got str"):
        result.predict(rig="x")
    from nplps.evaluation import held_out

    start = time.monotonic()
    with pytest.raises(nplps.InputError, match="5 images were given for 27 lights"):
        held_out(s.images[:5], s.rig, mask=s.mask, depth=200.0, lights=[0])
    with pytest.raises(nplps.InputError, match='method must be "near" or "parallel", got \'bogus\''):
        held_out(s.images, s.rig, mask=s.mask, depth=200.0, method="bogus", lights=[0])
    with pytest.raises(
        nplps.InputError, match=r"lights must be whole-number indices of the rig's 27 lights \(0 .. 26\), got 99"
    ):
        held_out(s.images, s.rig, mask=s.mask, depth=200.0, lights=[99])
    assert time.monotonic() - start < 5  # refused before any reconstruction


def test_rig_subset_and_load_bad_arguments(sphere16):
    rig = sphere16.rig
    with pytest.raises(
        nplps.InputError, match=r"indices: 99 is not a light of the rig \(its 27 lights are -27 .. 26\)"
    ):
        rig.subset([99])
    with pytest.raises(nplps.InputError, match="indices must be a list of whole-number light indices"):
        rig.subset([1.5])
    assert rig.subset([0, 1, -1]).lights == (rig.lights[0], rig.lights[1], rig.lights[26])
    with pytest.raises(RigError, match="rig file is read from a path"):
        nplps.Rig.load(None)


def test_cli_depth_files_and_threads(tmp_path, capsys, sphere16):
    from nplps import cli
    from nplps.cli.parsers import parse_depth

    empty = tmp_path / "empty.npy"
    empty.write_bytes(b"")
    with pytest.raises(nplps.InputError, match=r"--depth: cannot read '.*empty\.npy'"):
        parse_depth(str(empty))
    complex_map = tmp_path / "c.npy"
    np.save(complex_map, np.full((17, 17), 200.0 + 1j))
    with pytest.raises(nplps.InputError, match=r"--depth: '.*c\.npy' holds a complex128 array"):
        parse_depth(str(complex_map))
    with pytest.raises(nplps.InputError, match=r"--depth-prior: '.*c\.npy' holds a complex128 array"):
        parse_depth(str(complex_map), "--depth-prior")

    folder = tmp_path / "scene"
    sphere16.save(folder)
    common = ["reconstruct", str(folder), "--rig", str(folder / "rig.json"), "--mask", str(folder / "mask.png"), "-q"]
    start = time.monotonic()
    rc = cli.main([*common, "--out", str(tmp_path / "a"), "--depth", "200", "--threads", "100000"])
    assert rc == 2 and "--threads must be from 1 to 1024, got 100000" in capsys.readouterr().err
    assert time.monotonic() - start < 10
    rc = cli.main([*common, "--out", str(tmp_path / "b"), "--depth", "1e300"])
    err = capsys.readouterr().err
    assert rc == 2 and "depth (the working distance) is 1e+300" in err and "Traceback" not in err


def test_cli_calibrate_spheres_bad_placement_and_camera(tmp_path, capsys, sphere16):
    from nplps import cli
    from nplps.calibrate import load_camera

    deep = tmp_path / "deep.json"
    deep.write_text("[" * 10000 + "]" * 10000)
    with pytest.raises(RigError, match=r"deep\.json' is nested too deeply"):
        load_camera(deep)
    sphere16.rig.save(tmp_path / "rig.json")
    rc = cli.main(
        [
            "calibrate",
            "spheres",
            str(tmp_path / "nope"),
            "--camera",
            str(tmp_path / "rig.json"),
            "--radius",
            "20",
            "--out",
            str(tmp_path / "r.json"),
            "-q",
        ]
    )
    err = capsys.readouterr().err
    assert rc == 2 and "placement '" in err and "nope' not found" in err


def test_unreadable_image_file_leaves_no_open_handle(tmp_path):
    import gc
    import warnings

    from nplps import io

    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"hello, not an image")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ResourceWarning)
        with pytest.raises(nplps.InputError, match=r"bad\.jpg': not an image file of a known format"):
            io.read_image(bad)
        gc.collect()
    assert not [w for w in caught if issubclass(w.category, ResourceWarning)]
