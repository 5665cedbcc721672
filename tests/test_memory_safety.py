"""Memory exhaustion is a MemoryError, never an abort (issue 18, item 6 / "Why" 8).

Each case runs in a subprocess whose address space is capped (``RLIMIT_AS``) a little above
what it already uses, so that the reconstruction cannot get the memory it needs whatever
``max_memory`` says. On a4ba7e2 these runs aborted ("memory allocation of ... failed", -6).
"""

from __future__ import annotations

import pathlib
import subprocess
import sys
import textwrap

import pytest

resource = pytest.importorskip("resource")

SCRIPT = textwrap.dedent(
    """
    import resource, sys
    import numpy as np
    import nplps
    n, extra, limit = int(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
    s = nplps.make_scene("bumps", n=n, seed=0)
    images = np.asarray(s.images, dtype=np.float32)
    with open("/proc/self/status") as f:
        vm = next(int(l.split()[1]) * 1024 for l in f if l.startswith("VmSize"))
    cap = vm + int(extra * 2**30)
    resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    try:
        nplps.reconstruct(images, s.rig, depth=s.mean_depth, mask=s.mask, max_memory=limit)
    except MemoryError as e:
        print("MemoryError:", type(e).__name__, e)
        sys.exit(3)
    print("finished")
    """
)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="needs /proc and RLIMIT_AS")
@pytest.mark.parametrize(
    ("n", "extra", "limit"),
    [(1000, 0.05, "1e30"), (1000, 0.15, "100 GB"), (1400, 0.2, "1e30"), (1400, 0.3, "100 GB")],
)
def test_exhaustion_under_an_address_space_cap_is_a_memory_error(n: int, extra: float, limit: str) -> None:
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(n), str(extra), limit],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode not in (-6, 134), proc.stderr[-2000:]
    assert proc.returncode == 3, (proc.returncode, proc.stdout, proc.stderr[-2000:])
    assert "MemoryLimitError" in proc.stdout
    assert "out of memory" in proc.stdout and "smaller images" in proc.stdout


# --- the command line -------------------------------------------------------------------------
#
# ``nplps reconstruct`` runs in a subprocess whose address space is capped at exec time
# (``preexec_fn``) at the interpreter's own size with nplps imported plus ``extra`` GiB. Measured
# on a4ba7e2 with this 1000 x 1000, 27-light scene: +0.1 GiB aborted while decoding the PNG files
# ("memory allocation of 2000000 bytes failed", exit -6), +0.45 and +0.5 GiB aborted in the
# reconstruction (27000000 and 516128 bytes); +0.03 GiB now fails cleanly in the PNG decoder and
# +0.45 to +0.75 GiB in the core's memory probe. Since issue 23 items 1/4 (leaner multigrid, its
# buffers and the solver's allocated zeroed) the run fits in +0.6 GiB. Since items 1/2 (computed
# facet corners and vertex positions, buffers given back between the steps) the reconstruction
# fits in +0.5 GiB and the caps of +0.5 and +0.55 stop the export instead (a one-line refusal
# of its own memory check): the largest caps are +0.4 and +0.45, refused in the core's probe.
# Since issue 23's leaner iterations (targets given back in the global step, chunked statistics,
# no stored starting depths) the reconstruction fits in +0.45 GiB too and the export refuses
# there: the largest caps are +0.35 and +0.4.

CLI_SIZE = 1000
CLI_DEPTH = "198.22"
BASE_VM = (
    "import numpy, nplps, nplps.cli, imageio.v3, PIL.Image\n"
    "print(next(int(l.split()[1]) * 1024 for l in open('/proc/self/status') if l.startswith('VmSize')))"
)
linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="needs /proc and RLIMIT_AS")


@pytest.fixture(scope="module")
def cli_scene(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, int]:
    """Return a synthetic 1000 x 1000, 27-light scene folder and the interpreter's base VmSize."""
    folder = tmp_path_factory.mktemp("cli_memory") / "scene"
    subprocess.run(
        [sys.executable, "-m", "nplps", "synth", "bumps", "--size", str(CLI_SIZE), "--out", str(folder)],
        check=True,
        capture_output=True,
        timeout=600,
    )
    base = subprocess.run([sys.executable, "-c", BASE_VM], check=True, capture_output=True, text=True)
    return str(folder), int(base.stdout.split()[-1])


def _reconstruct_capped(scene: str, base: int, extra: float, out: str) -> subprocess.CompletedProcess[str]:
    cap = base + int(extra * 2**30)

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))

    argv = [sys.executable, "-m", "nplps", "reconstruct", scene, "--rig", f"{scene}/rig.json"]
    argv += ["--mask", f"{scene}/mask.png", "--depth", CLI_DEPTH, "--max-memory", "1e30"]
    argv += ["--out", out, "-q"]
    return subprocess.run(argv, capture_output=True, text=True, preexec_fn=limit, timeout=600)


@linux_only
@pytest.mark.parametrize("extra", [0.03, 0.1, 0.2, 0.35, 0.4])
def test_cli_never_aborts_under_an_address_space_cap(
    cli_scene: tuple[str, int], extra: float, tmp_path: pathlib.Path
) -> None:
    scene, base = cli_scene
    proc = _reconstruct_capped(scene, base, extra, str(tmp_path / "out"))
    assert proc.returncode not in (-6, 134), proc.stderr[-2000:]
    assert proc.returncode != 0, "the cap is meant to be too small for the reconstruction"
    # numpy's MemoryError (reading or preparing the images) is one line too, never a traceback.
    assert "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert "out of memory" in proc.stderr.lower(), proc.stderr[-2000:]


@linux_only
@pytest.mark.parametrize("extra", [0.03, 0.35, 0.4])
def test_cli_exhaustion_in_the_core_is_a_one_line_memory_error(
    cli_scene: tuple[str, int], extra: float, tmp_path: pathlib.Path
) -> None:
    scene, base = cli_scene
    proc = _reconstruct_capped(scene, base, extra, str(tmp_path / "out"))
    assert proc.returncode not in (-6, 134), proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    assert len(lines) == 1 and lines[0].startswith("nplps: error: "), proc.stderr[-2000:]
    assert "out of memory" in lines[0] and "smaller images" in lines[0], lines[0]
