"""Real captures made by other people (../shared/data, see its README): DiLiGenT's ball with
ground-truth normals, and two near-LED captures judged by held-out prediction.

The tests skip when the data folder is absent; the data are never copied into the repository.
Pictures of the results (normal map, shaded mesh) go to ``$NPLPS_PICTURES`` when it is set, else
to the test's temporary folder.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

import nplps
from nplps import captures
from nplps.evaluation import held_out


def _pictures(tmp_path: Path, name: str) -> Path:
    root = os.environ.get("NPLPS_PICTURES")
    return (Path(root) if root else tmp_path) / name


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))


def test_diligent_ball_beats_least_squares(tmp_path, shared_capture):
    ball = captures.load_diligent(shared_capture("diligent_ball"), load=True)
    mask, truth = ball.mask, ball.normals_gt
    # Plain least squares from the same 16-bit data: intensities divided out, channels averaged,
    # every light, no thresholds.
    grey = (ball.images / ball.intensities[:, None, None, :]).mean(axis=-1)
    g = np.linalg.lstsq(ball.directions, grey[:, mask], rcond=None)[0].T
    ls = _angles(g / np.linalg.norm(g, axis=1, keepdims=True), truth[mask]).mean()

    rig = ball.rig()
    result = nplps.reconstruct(ball.images, rig, mask=mask, depth=1000.0, iterations=1, robust="tukey")
    ours = _angles(result.normals[mask], truth[mask]).mean()
    plain = nplps.reconstruct(ball.images, rig, mask=mask, depth=1000.0, iterations=1)
    ours_plain = _angles(plain.normals[mask], truth[mask]).mean()
    print(f"ball: least squares {ls:.2f} deg, nplps {ours_plain:.2f} deg, nplps robust {ours:.2f} deg")
    assert 4.0 < ls < 4.6  # the README's 4.3 deg for a 16-bit grey read
    assert ours < ls and ours_plain < ls
    result.save(_pictures(tmp_path, "diligent_ball"), overwrite=True)


def test_diligent_ball_glossy_continuation(shared_capture):
    """The glossy model with its lobe estimated (sharp: roughness about 0.03): the fits in the
    ball's centre, where the highlights of most of the 96 lights fall, start by continuation from
    a rough lobe (issue 20). Before, they ended 7-10 degrees off there (mean 2.82 degrees). With
    96 lights the index is chosen by the held-out score (the residual is flat in it and chose 1:
    2.27 degrees)."""
    ball = captures.load_diligent(shared_capture("diligent_ball"), load=True)
    mask, truth = ball.mask, ball.normals_gt
    result = nplps.reconstruct(ball.images, ball.rig(), mask=mask, depth=1000.0, reflectance="glossy")
    error = _angles(result.normals[mask], truth[mask])
    centre = -truth[mask][:, 2] > 0.95
    print(f"ball glossy: {error.mean():.3f} deg, centre {error[centre].mean():.2f} deg, {result.lobe}")
    assert result.lobe is not None and result.lobe.roughness < 0.1
    assert result.lobe.eta > 1.1  # the residual's choice was 1
    assert error.mean() < 1.8  # 1.53 when written (2.27 with the index chosen by the residual)
    assert error[centre].mean() < 4.0  # 9.5 before the continuation


def _near_led_case(capture: captures.Capture, distance: float, tmp_path: Path, name: str) -> dict[str, list]:
    rig = capture.rig()
    scores = {}
    for method in ("near", "parallel"):
        scores[method] = held_out(capture.images, rig, mask=capture.mask, depth=distance, method=method, iterations=20)
    print(f"{name} held-out error per left-out light (relative / gain-free shape):")
    for a, b in zip(scores["near"], scores["parallel"], strict=True):
        print(
            f"  light {a.light}: near {a.relative_error:.3f} / {a.shape_error:.3f}, "
            f"parallel {b.relative_error:.3f} / {b.shape_error:.3f}"
        )
    result = nplps.reconstruct(capture.images, rig, mask=capture.mask, depth=distance, iterations=20)
    print(f"  photometric residual (rms, all lights): {result.history[-1].rms_residual:.4g}")
    result.save(_pictures(tmp_path, name), overwrite=True)
    return {m: [(h.relative_error, h.shape_error) for h in s] for m, s in scores.items()}


def test_hehe12_near_light_predicts_held_out_images_better(tmp_path, shared_capture):
    capture = captures.prepare(captures.load_hehe12(shared_capture("hehe12")), bin_factor=4)
    scores = _near_led_case(capture, 200.0, tmp_path, "hehe12")
    near, parallel = np.mean(scores["near"], axis=0), np.mean(scores["parallel"], axis=0)
    print(f"hehe12 mean: near {near}, parallel {parallel}")
    # The shape of the predicted shading (free of the left-out LED's intensity calibration).
    assert near[1] < parallel[1]


def test_queau_human1_near_light_predicts_held_out_images_better(tmp_path, shared_capture):
    capture = captures.prepare(captures.load_queau_human1(shared_capture("queau_human1")), bin_factor=8)
    scores = _near_led_case(capture, 700.0, tmp_path, "queau_human1")
    near, parallel = np.mean(scores["near"], axis=0), np.mean(scores["parallel"], axis=0)
    print(f"queau_human1 mean: near {near}, parallel {parallel}")
    assert near[0] < parallel[0] and near[1] < parallel[1]
