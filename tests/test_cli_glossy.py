"""The glossy model from the command line: ``--reflectance``, ``--roughness``, ``--eta`` in
``nplps reconstruct`` (and its ``--baseline``), ``nplps batch``, and what the result folder holds."""

from __future__ import annotations

import json

import numpy as np
import pytest

import nplps
from nplps import cli

N = 32
LOBE = ["--reflectance", "glossy", "--roughness", "0.3", "--eta", "1.5"]


@pytest.fixture(scope="module")
def glossy_capture(tmp_path_factory):
    """A glossy sphere (specular albedo 0.2 of the diffuse, roughness 0.3, eta 1.5) on disk."""
    scene = nplps.make_scene("sphere", n=N, seed=1, specular=0.2, roughness=0.3, eta=1.5)
    root = tmp_path_factory.mktemp("glossy")
    scene.save(root / "sphere")
    return scene, root / "sphere"


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))


def _reconstruct(capsys, capture, out, *extra):
    scene, folder = capture
    argv = ["reconstruct", str(folder), "--rig", str(folder / "rig.json"), "--mask", str(folder / "mask.png")]
    argv += ["--depth", repr(scene.mean_depth), "--levels", "1", "-q", "--out", str(out), *extra]
    rc = cli.main(argv)
    captured = capsys.readouterr()
    return rc, captured.out, captured.err


def test_glossy_flags_reach_the_solver_and_the_result_folder(glossy_capture, tmp_path, capsys):
    scene, _ = glossy_capture
    rc, _, stderr = _reconstruct(capsys, glossy_capture, tmp_path / "glossy", *LOBE)
    assert rc == 0, stderr
    out = tmp_path / "glossy"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["reflectance"] == "glossy"
    assert summary["lobe"] == {"roughness": 0.3, "eta": 1.5, "diffuse": "transmitted"}
    assert summary["options"]["solver_options"]["reflectance"] == "glossy"
    assert summary["options"]["roughness"] == 0.3 and summary["options"]["eta"] == 1.5
    specular = np.load(out / "specular.npy")
    assert specular.shape == (N, N)
    m = scene.mask
    # The scene's specular albedo is 0.2 of its diffuse albedo (in the saved images' scale).
    truth = 0.2 * np.load(glossy_capture[1] / "albedo_gt.npy")
    assert np.nanmedian(specular[m] / truth[m]) == pytest.approx(1.0, rel=0.02)
    assert (out / "specular.png").is_file() and summary["specular_png_scale"] > 0
    manifest = json.loads((out / "nplps-manifest.json").read_text())
    assert "specular.npy" in json.dumps(manifest) and "specular.png" in json.dumps(manifest)
    report = (out / "report.html").read_text()
    assert "reflectance" in report and "roughness 0.3" in report and "eta 1.5" in report
    assert "specular albedo" in report and "diffuse albedo" in report
    # The glossy fit is near-exact where the Lambertian one is bent by the highlights.
    rc, _, stderr = _reconstruct(capsys, glossy_capture, tmp_path / "lambertian")
    assert rc == 0, stderr
    glossy_err = _angles(np.load(out / "normals.npy"), scene.normals)[m].mean()
    lambert_err = _angles(np.load(tmp_path / "lambertian" / "normals.npy"), scene.normals)[m].mean()
    assert glossy_err < 0.5 < 2.0 < lambert_err, (glossy_err, lambert_err)


def test_lambertian_results_have_no_specular_files(glossy_capture, tmp_path, capsys):
    rc, _, stderr = _reconstruct(capsys, glossy_capture, tmp_path / "out", "--reflectance", "lambertian")
    assert rc == 0, stderr
    out = tmp_path / "out"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["reflectance"] == "lambertian" and summary["lobe"] is None
    assert "specular_png_scale" not in summary
    assert not list(out.glob("specular*"))
    assert "specular albedo" not in (out / "report.html").read_text()


def test_estimated_lobe_and_the_baseline(glossy_capture, tmp_path, capsys):
    """Without --roughness/--eta the lobe is estimated; --baseline fits the same model."""
    rc, _, stderr = _reconstruct(
        capsys, glossy_capture, tmp_path / "out", "--reflectance", "glossy", "--iterations", "4", "--baseline"
    )
    assert rc == 0, stderr
    near = json.loads((tmp_path / "out" / "summary.json").read_text())
    base = json.loads((tmp_path / "out" / "baseline" / "summary.json").read_text())
    assert near["reflectance"] == base["reflectance"] == "glossy"
    assert 0 < near["lobe"]["roughness"] <= 1 and 1 <= near["lobe"]["eta"] <= 3
    assert (tmp_path / "out" / "baseline" / "specular.npy").is_file()


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--roughness", "0.3"], "add --reflectance glossy"),
        (["--roughness", "0.3", "--eta", "1.5"], "are options of the glossy model"),
        (["--reflectance", "lambertian", "--eta", "1.5"], "is an option of the glossy model"),
        (["--reflectance", "glossy", "--roughness", "0.3"], "--roughness needs --eta too"),
        (["--reflectance", "glossy", "--eta", "1.5"], "--eta needs --roughness too"),
        (["--reflectance", "glossy", "--roughness", "0", "--eta", "1.5"], "--roughness (the GGX alpha) must be"),
        (["--reflectance", "glossy", "--roughness", "0.3", "--eta", "0.9"], "--eta (the relative index"),
        (["--reflectance", "glossy", "--roughness", "nan", "--eta", "1.5"], "--roughness"),
    ],
)
def test_lobe_errors(glossy_capture, tmp_path, capsys, extra, message):
    rc, _, stderr = _reconstruct(capsys, glossy_capture, tmp_path / "out", *extra)
    assert rc == 2
    assert message in stderr
    assert not (tmp_path / "out").exists()  # refused before anything is read or written


def test_bad_reflectance_choice(glossy_capture, tmp_path, capsys):
    rc, _, stderr = _reconstruct(capsys, glossy_capture, tmp_path / "out", "--reflectance", "shiny")
    assert rc == 2 and "invalid choice: 'shiny'" in stderr


def test_help_describes_the_model(capsys):
    for command in ("reconstruct", "batch", "evaluate"):
        assert cli.main([command, "--help"]) == 0
        text = " ".join(capsys.readouterr().out.split())
        assert "--reflectance {lambertian,glossy}" in text, command
        assert "--roughness A" in text and "--eta E" in text
        assert "GGX specular lobe" in text and "shared by the whole object" in text


def test_batch_glossy(glossy_capture, tmp_path, capsys):
    pytest.importorskip("distributed", reason="nplps batch needs dask.distributed (pip install 'nplps[batch]')")
    scene, folder = glossy_capture
    argv = ["batch", str(folder), "--rig", str(folder / "rig.json"), "--depth", repr(scene.mean_depth)]
    argv += ["--levels", "1", "--workers", "1", "--out", str(tmp_path / "out"), *LOBE]
    assert cli.main(argv) == 0, capsys.readouterr().err
    summary = json.loads((tmp_path / "out" / "sphere" / "summary.json").read_text())
    assert summary["lobe"] == {"roughness": 0.3, "eta": 1.5, "diffuse": "transmitted"}
    assert summary["options"]["reflectance"] == "glossy"
    assert (tmp_path / "out" / "sphere" / "specular.png").is_file()
    capsys.readouterr()
    # The lobe's checks come before any capture is read.
    assert cli.main([*argv[:-2], "--out", str(tmp_path / "x")]) == 2
    assert "--roughness needs --eta too" in capsys.readouterr().err and not (tmp_path / "x").exists()
