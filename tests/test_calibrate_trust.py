"""Calibration you can check: per-light standard errors and the comparison with a reference rig (``--reference``)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import nplps
from nplps import calibrate as cal
from nplps import synth_calibration as scenes
from nplps.cli import main


@pytest.mark.parametrize("camera", ["orthographic", "pinhole"])
def test_standard_errors_match_the_errors_over_seeds(camera: str) -> None:
    """Position errors over their standard errors have an RMS near 1 per axis; distant lights' angles too."""
    z, angles = [], []
    for seed in range(3):
        scene = scenes.make_sphere_scene(camera, lights=27, directional=True, spheres=2, seed=seed)
        depth = scene.center_depths if not scene.rig.is_pinhole else None
        result = cal.calibrate_spheres(scene.images, scene.rig, scene.radius, masks=scene.labels, center_depth=depth)
        truth = scene.rig
        for light in result.lights:
            i = light.index
            if light.kind == "point" and not truth.directional[i]:
                assert light.standard_error is not None and (light.standard_error > 0).all()
                z.append((light.position - truth.positions[i]) / light.standard_error)
            elif light.kind == "directional" and truth.directional[i]:
                assert light.standard_error is None and light.direction_se > 0
                cos = np.clip(light.direction @ truth.directions[i], -1.0, 1.0)
                angles.append(np.degrees(np.arccos(cos)) / light.direction_se)
    rms = np.sqrt(np.mean(np.asarray(z) ** 2, axis=0))
    assert ((rms > 0.6) & (rms < 1.4)).all(), rms
    assert 0.6 < np.sqrt(np.mean(np.square(angles))) < 1.4


def test_compare_lights_exact_values() -> None:
    camera = {"model": "orthographic", "pixel_size": [1.0, 1.0], "origin": [0.0, 0.0]}
    positions = np.array([[0.0, 20.0, 0.0], [50.0, 0.0, 10.0], [np.nan] * 3])
    directions = np.array([[np.nan] * 3, [np.nan] * 3, [0.0, 0.0, -1.0]])
    reference = nplps.Rig.from_arrays(camera, positions, directions=directions, intensities=[1.0, 2.0, 4.0])
    moved = positions.copy()
    moved[1] += [3.0, 4.0, 0.0]
    tilt = np.radians(2.0)
    turned = directions.copy()
    turned[2] = [np.sin(tilt), 0.0, -np.cos(tilt)]
    calibrated = nplps.Rig.from_arrays(camera, moved, directions=turned, intensities=[1.0, 2.0, 4.4])
    rows = cal.compare_lights(calibrated, reference, 200.0)
    assert rows[0]["position_error"] == 0.0 and rows[1]["position_error"] == pytest.approx(5.0)
    assert rows[1]["position_error_percent"] == pytest.approx(2.5) and rows[1]["offset"] == pytest.approx([3, 4, 0])
    assert rows[2]["kind"] == "directional" and rows[2]["direction_error"] == pytest.approx(2.0)
    # Intensities compared after scaling both to a geometric mean of 1: light 2 is 10 % brighter
    # relative to the others.
    factor = 1.1 ** (-1 / 3)
    expected = [100 * (factor - 1), 100 * (factor - 1), 100 * (1.1 * factor - 1)]
    assert [r["intensity_error_percent"] for r in rows] == pytest.approx(expected)
    summary = cal.reference_summary(rows)
    assert summary["position_error_max"] == pytest.approx(5.0)
    assert summary["position_error_rms"] == pytest.approx(np.sqrt(25 / 2))
    assert summary["direction_error_max"] == pytest.approx(2.0)
    with pytest.raises(nplps.InputError, match="2 lights but the calibration 3"):
        cal.compare_lights(calibrated, reference.subset([0, 1]), 200.0)


def test_command_line_reference_and_reports(tmp_path, capsys) -> None:
    out = tmp_path / "calib"
    assert main(["synth-calibration", "--out", str(out), "--lights", "8"]) == 0
    scene = json.loads((out / "scene.json").read_text())
    depths = [str(d[0]) for d in scene["center_depths"]]
    capsys.readouterr()
    spheres = [
        "calibrate",
        "spheres",
        str(out / "placement_0"),
        str(out / "placement_1"),
        "--camera",
        str(out / "camera.json"),
        "--radius",
        "20",
        "--center-depth",
        depths[0],
        "--center-depth",
        depths[1],
        "--out",
        str(out / "rig_spheres.json"),
        "--report",
        str(out / "spheres.json"),
        "--reference",
        str(out / "rig_true.json"),
        "--working-distance",
        "200",
        "-q",
    ]
    assert main(spheres) == 0
    printed = capsys.readouterr().out
    assert "against the reference" in printed and "D = 200, given" in printed and "% of D" in printed
    report = json.loads((out / "spheres.json").read_text())
    assert all(len(light["standard_error"]) == 3 for light in report["lights"])
    truth = nplps.Rig.load(out / "rig_true.json")
    found = nplps.Rig.load(out / "rig_spheres.json")
    errors = np.linalg.norm(found.positions - truth.positions, axis=1)
    ref = report["reference"]
    assert ref["distance"] == 200.0
    assert [r["position_error"] for r in ref["lights"]] == pytest.approx(errors)
    assert ref["summary"]["position_error_percent_rms"] == pytest.approx(100 * np.sqrt(np.mean(errors**2)) / 200)
    assert f"{ref['summary']['position_error_percent_rms']:.3f} % of D" in printed
    intensity = [
        "calibrate",
        "intensity",
        str(out / "board"),
        "--rig",
        str(out / "rig_spheres.json"),
        "--plane-depth",
        str(scene["board_depth"]),
        "--out",
        str(out / "rig.json"),
        "--report",
        str(out / "intensity.json"),
        "--reference",
        str(out / "rig_true.json"),
        "-q",
    ]
    assert main(intensity) == 0
    printed = capsys.readouterr().out
    assert "se %" in printed and "intensities RMS" in printed
    record = json.loads((out / "intensity.json").read_text())
    assert len(record["lights"]) == 8
    assert all(0 < light["standard_error"] < light["rms"] for light in record["lights"])
    assert record["reference"]["summary"]["intensity_error_percent_max"] < 5.0
    # A reference with other lights is refused before the work.
    truth.subset([0, 1, 2]).save(tmp_path / "three.json")
    bad = [*intensity[:-3], "--reference", str(tmp_path / "three.json"), "--overwrite", "-q"]
    assert main(bad) == 2
    assert "has 3 lights but --rig 8" in capsys.readouterr().err
