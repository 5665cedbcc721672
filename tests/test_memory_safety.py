"""Memory exhaustion is a MemoryError, never an abort (issue 18, item 6 / "Why" 8).

Each case runs in a subprocess whose address space is capped (``RLIMIT_AS``) a little above
what it already uses, so that the reconstruction cannot get the memory it needs whatever
``max_memory`` says. On a4ba7e2 these runs aborted ("memory allocation of ... failed", -6).
"""

from __future__ import annotations

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
