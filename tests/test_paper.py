"""benchmarks/paper (issue 11, item 8): the paper's figures regenerate in one command.

Runs ``python benchmarks/paper/run.py --quick`` (tiny sizes, one seed: a few seconds) into a
temporary folder, checks that every figure file and paper.html are there, and checks only claims
that hold by a wide margin on noise-free synthetic scenes.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import numpy as np
import pytest

PAPER = Path(__file__).resolve().parents[1] / "benchmarks" / "paper"
PNGS = [
    f"{name}.png" for name in ("fig3_errors", "fig4_normals", "fig4_errors", "fig4_depth", "fig7_depth", "fig7_normals")
]
SVGS = ["fig3_curve.svg", "fig7_profile.svg", "fig8_exact.svg", "fig8_error.svg"]


@pytest.fixture(scope="module")
def quick(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    out = tmp_path_factory.mktemp("paper")
    run = subprocess.run(
        [sys.executable, str(PAPER / "run.py"), "--quick", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 0, run.stderr
    return out, json.loads((out / "results.json").read_text())


def test_every_figure_file_and_the_page_are_written(quick: tuple[Path, dict[str, Any]]) -> None:
    out, results = quick
    for name in PNGS:
        image = iio.imread(out / name)
        assert image.ndim == 3 and image.shape[2] == 3 and image.shape[0] >= 32, name
    for name in SVGS:
        text = (out / name).read_text()
        assert text.startswith("<svg") and "<polyline" in text, name
    page = (out / "paper.html").read_text()
    for title in ("Fig. 3", "Fig. 4", "Fig. 7", "Fig. 8", "Table 1"):
        assert title in page
    assert page.count("data:image/png;base64,") >= 15
    assert 'src="http' not in page and "src='http" not in page  # self-contained
    assert "21.2 s" in page and "131 s" in page  # the paper's Table 1 beside ours
    assert results["quick"] is True and results["seconds"] < 60


def test_quick_numbers_are_sane(quick: tuple[Path, dict[str, Any]]) -> None:
    _, r = quick
    # Fig. 3: the iteration goes from the plane's error (the true slopes) to nearly exact.
    errors = [r["fig3"]["mean_error"][k] for k in sorted(r["fig3"]["mean_error"], key=int)]
    assert errors[0] > 10.0 and errors[-1] < 0.1 and errors[-1] < errors[1] < errors[0]
    # Fig. 4: exact lights, near ~exact, parallel far off; with 5 % light error near stays far better.
    fig4 = r["fig4"]["results"]
    assert fig4["nplps, exact lights"]["normal"]["mean"] < 0.1
    assert fig4["parallel, exact lights"]["normal"]["mean"] > 10.0
    assert fig4["nplps, 5 % light error"]["normal"]["mean"] < 0.5 * fig4["parallel, 5 % light error"]["normal"]["mean"]
    # Fig. 7: every integrator of the parallel normals is far off; the integrator itself is exact.
    fig7 = r["fig7"]["results"]
    near_rms = fig7["nplps"]["depth_rms_pct"]
    for key in ("parallel PS + our global step", "parallel PS + Poisson", "parallel PS + M-estimator"):
        (rms,) = [v["depth_rms_pct"] for k, v in fig7.items() if k.startswith(key)]
        assert rms > 2.0 and rms > 100 * near_rms, key
    assert fig7["check: true normals + Poisson"]["depth_rms_pct"] < 1e-6
    # Fig. 8: parallel gets worse with the ratio, near does not (exact lights), and with 5 %
    # light error near is still better than parallel from ratio 0.4 on.
    ratios = r["fig8"]["ratios"]
    exact, error = r["fig8"]["exact"], r["fig8"]["error"]
    assert np.all(np.diff(exact["parallel"]["mean"]) > 0)
    assert max(exact["near"]["mean"]) < 0.1
    for i, ratio in enumerate(ratios):
        assert exact["near"]["mean"][i] < exact["parallel"]["mean"][i]
        if ratio >= 0.4:
            assert error["near"]["mean"][i] < 0.5 * error["parallel"]["mean"][i]
    # Table 1: a time for every size and run.
    for model in r["table1"]["seconds"].values():
        for by_size in model.values():
            assert len(by_size) == len(r["table1"]["sizes"]) and all(t > 0 for t in by_size.values())


def test_integrators_recover_an_exact_gradient_field() -> None:
    sys.path.insert(0, str(PAPER))
    try:
        from _integrate import gradients, normals_from_depth, poisson, robust
    finally:
        sys.path.remove(str(PAPER))
    y, x = np.mgrid[0:40, 0:56] * 0.5
    z = 0.02 * (x - 12.0) ** 2 - 0.03 * x * y + np.sin(0.3 * y)
    zy, zx = np.gradient(z, 0.5, 0.5)
    n = np.stack([zx, zy, -np.ones_like(z)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    p, q = gradients(n)
    assert np.allclose(p, zx) and np.allclose(q, zy)
    for integrate in (poisson, robust):
        got = integrate(p, q, 0.5, 0.5)
        # Central-difference gradients are not an exact forward-difference field: small residue.
        assert np.sqrt(np.mean((got - (z - z.mean())) ** 2)) < 0.02 * np.ptp(z), integrate.__name__
    flat = normals_from_depth(np.zeros((4, 5)), 1.0, 1.0)
    assert np.allclose(flat, [0.0, 0.0, -1.0])
