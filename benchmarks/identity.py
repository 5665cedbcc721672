"""Bit-identity check of the CLI and the API on the shared captures (issue 10's acceptance).

Runs a fixed set of reconstructions of the three captures in ``../shared/data`` through the
command line and through the Python API, and prints (or writes, with ``--out FILE``) the SHA-256
of every array result: vertex depths, albedo, both kinds of normals, residuals, and the
bytes of every mesh and map file the CLI writes, on the captures and on synthetic scenes
(pinhole and orthographic, LEDs, colour, light refinement, the multigrid solver). Left out, as they
hold timings: ``summary.json`` and the manifest (whose hashes cover the files compared here);
``history.csv`` is compared without its ``elapsed`` column, ``report.html`` with its timings and
dates blanked. Run it on two commits and compare the two JSON files with ``--compare A B``::

    python benchmarks/identity.py --out before.json     # on the old commit
    python benchmarks/identity.py --out after.json      # on the new one
    python benchmarks/identity.py --compare before.json after.json

Written to run unchanged on both sides of the restructuring: every call uses keywords, and
the two normal fields are found by meaning (the per-pixel fits were ``normals`` and became
``fit_normals``; the mesh's were ``mesh_normals`` and became ``normals``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def _digest(array) -> str:
    a = np.ascontiguousarray(np.asarray(array))
    h = hashlib.sha256()
    h.update(str(a.dtype).encode() + str(a.shape).encode())
    h.update(a.tobytes())
    return h.hexdigest()[:16]


def _result_digests(result) -> dict[str, str]:
    if hasattr(result, "fit_normals"):
        fit, mesh = result.fit_normals, result.normals
    else:
        fit, mesh = result.normals, result.mesh_normals
    # The mesh normals inside the mask (outside it, the old mesh_normals kept the normal of every
    # quad whose corners were known; the new normals are NaN there, like the fits).
    masked = np.where(np.asarray(result.mask)[..., None], mesh, np.nan)
    out = {
        "depth": _digest(result.depth),
        "albedo": _digest(result.albedo),
        "fit_normals": _digest(fit),
        "mesh_normals": _digest(mesh),
        "mesh_normals_in_mask": _digest(masked),
    }
    if getattr(result, "residual", None) is not None:
        out["residual"] = _digest(result.residual)
    out["iterations"] = str(len(result.history))
    return out


def _cli(args: list[str]) -> dict[str, str]:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        subprocess.run([sys.executable, "-m", "nplps", "reconstruct", *args, "--out", str(out), "-q"], check=True)
        digests = {}
        for path in sorted(out.rglob("*")):
            if path.is_file() and path.name not in ("summary.json", "nplps-manifest.json"):
                if path.suffix == ".npy":
                    digests[path.name] = _digest(np.load(path))
                elif path.name == "history.csv":
                    rows = [line.split(",") for line in path.read_text().splitlines()]
                    keep = [i for i, name in enumerate(rows[0]) if name != "elapsed"]
                    text = "\n".join(",".join(row[i] for i in keep) for row in rows)
                    digests[path.name] = hashlib.sha256(text.encode()).hexdigest()[:16]
                elif path.name == "report.html":
                    digests[path.name] = hashlib.sha256(_without_timings(path.read_text(), out).encode()).hexdigest()[
                        :16
                    ]
                else:
                    digests[path.name] = hashlib.sha256(path.read_bytes()).hexdigest()[:16]
        return digests


def _without_timings(html: str, out: Path) -> str:
    """Return the report with what changes from run to run blanked: the folder, seconds, dates."""
    html = html.replace(str(out.parent), "TMP")
    html = re.sub(re.escape(tempfile.gettempdir()) + r"/tmp\w+", "TMP", html)
    html = re.sub(r"<h3>Timings \(seconds\)</h3><table>.*?</table>", "TIMINGS", html, flags=re.S)
    html = re.sub(r"\d+(\.\d+)?(e[-+]?\d+)? ?(s|ms)\b", "T", html)
    return re.sub(r"\d{4}-\d{2}-\d{2}[T ]\d{2}:\d{2}(:\d{2}(\.\d+)?)?", "D", html)


def _synthetic(results: dict[str, dict[str, str]]) -> None:
    import nplps

    s = nplps.make_scene("sphere", n=64, camera="pinhole", led=True, noise=0.01, seed=1)
    r = nplps.reconstruct(s.images, s.rig, mask=s.mask, depth=s.mean_depth, refine_lights="position")
    results["api synth sphere pinhole led refine position"] = _result_digests(r)
    s = nplps.make_scene("bumps", n=96, rgb=True, noise=0.005, seed=2)
    r = nplps.reconstruct(s.images, s.rig, mask=s.mask, depth="auto", robust="cauchy")
    results["api synth bumps rgb auto cauchy"] = _result_digests(r)
    s = nplps.make_scene("saddle", n=160, camera="pinhole", seed=3)
    r = nplps.reconstruct(s.images, s.rig, mask=s.mask, depth=s.mean_depth, solver="multigrid", levels=3)
    results["api synth vase multigrid"] = _result_digests(r)
    with tempfile.TemporaryDirectory() as tmp:
        scene = Path(tmp) / "scene"
        subprocess.run(
            [sys.executable, "-m", "nplps", "synth", "sphere", "--out", str(scene)],
            stdout=subprocess.DEVNULL,
            check=True,
        )
        results["cli synth sphere"] = _cli([str(scene), "--rig", str(scene / "rig.json"), "--depth", "auto"])


def run() -> dict[str, dict[str, str]]:
    import nplps
    from nplps import captures

    results: dict[str, dict[str, str]] = {}
    hehe = str(SHARED / "hehe12")
    ball = str(SHARED / "diligent_ball" / "ballPNG")
    results["cli hehe12 bin4"] = _cli(
        ["--capture", "near_ps", hehe, "photometric_sample_raw_000[0-9].png", "--bin", "4", "--depth", "200"]
    )
    results["cli hehe12 bin8 tukey refine"] = _cli(
        [
            "--capture",
            "near_ps",
            hehe,
            "photometric_sample_raw_000[0-9].png",
            "--bin",
            "8",
            "--depth",
            "200",
            "--robust",
            "tukey",
            "--refine-lights",
            "intensity",
        ]
    )
    results["cli diligent ball"] = _cli(["--capture", "diligent", ball, "--depth", "1000", "--iterations", "2"])

    cap = captures.prepare(captures.load_hehe12(hehe), bin_factor=4)
    r = nplps.reconstruct(cap.images, cap.rig(), mask=cap.mask, depth=200.0, iterations=20)
    results["api hehe12 bin4"] = _result_digests(r)
    cap = captures.prepare(captures.load_queau_human1(str(SHARED / "queau_human1")), bin_factor=8)
    r = nplps.reconstruct(cap.images, cap.rig(), mask=cap.mask, depth=700.0, iterations=20)
    results["api queau_human1 bin8"] = _result_digests(r)
    r = nplps.reconstruct(cap.images, cap.rig(), mask=cap.mask, depth="auto", iterations=5)
    results["api queau_human1 bin8 auto"] = _result_digests(r)
    b = captures.load_diligent(ball, load=True)
    r = nplps.reconstruct(b.images, b.rig(), mask=b.mask, depth=1000.0, iterations=1, robust="tukey")
    results["api diligent ball tukey"] = _result_digests(r)
    r = nplps.reconstruct_parallel(b.images, b.rig(), mask=b.mask, depth=1000.0)
    results["api diligent ball parallel"] = _result_digests(r)
    _synthetic(results)
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path)
    parser.add_argument("--compare", nargs=2, type=Path, metavar=("A", "B"))
    args = parser.parse_args()
    if args.compare:
        a, b = (json.loads(p.read_text()) for p in args.compare)
        same = differ = 0
        for case in sorted(set(a) | set(b)):
            for key in sorted(set(a.get(case, {})) | set(b.get(case, {}))):
                x, y = a.get(case, {}).get(key), b.get(case, {}).get(key)
                if x == y:
                    same += 1
                else:
                    differ += 1
                    print(f"DIFFERENT {case}: {key}: {x} vs {y}")
        print(f"{same} identical, {differ} different")
        sys.exit(1 if differ else 0)
    if not SHARED.is_dir():
        sys.exit(f"the shared captures are not at {SHARED}")
    results = run()
    text = json.dumps(results, indent=1, sort_keys=True)
    if args.out:
        args.out.write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
