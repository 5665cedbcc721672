"""Ctrl-C stops a long reconstruction between iterations (the core checks for signals)."""

import signal
import subprocess
import sys
import textwrap

import pytest

SCRIPT = textwrap.dedent(
    """
    import sys, time
    import nplps
    s = nplps.make_scene("bumps", n=128)
    def progress(it):
        # A line per iteration, slowed down so that the run outlasts the signal (without the
        # pause it could stop on its own, "stalled", before the signal arrives).
        print("iteration", it.iteration, file=sys.stderr, flush=True)
        time.sleep(0.05)
    try:
        nplps.reconstruct(s.images, s.rig, mask=s.mask, depth=s.mean_depth,
                          iterations=1_000_000, tol=0.0, progress=progress)
    except KeyboardInterrupt:
        print("interrupted", flush=True)
        raise SystemExit(3)
    print("finished", flush=True)
    """
)


@pytest.mark.skipif(sys.platform == "win32", reason="SIGINT delivery differs on Windows")
def test_sigint_interrupts_a_running_reconstruction():
    proc = subprocess.Popen([sys.executable, "-c", SCRIPT], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        # Wait until the solver is iterating (a progress line on stderr), then press Ctrl-C.
        line = proc.stderr.readline()
        assert line.startswith("iteration"), line
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 3
    assert "interrupted" in out
