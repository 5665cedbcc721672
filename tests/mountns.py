"""Run test code in a private mount namespace, with small tmpfs file systems and device nodes.

Tests that need a full disk (a tmpfs of a few MB) or a device file (a character device made with
``mknod`` on that tmpfs, never the real ``/dev``) run their code here: a child process in a new
mount namespace (``unshare --mount --propagation private``), so nothing it mounts is seen outside
it and everything it mounts is gone when it ends. It needs root and ``unshare``; :func:`reason`
says why it cannot run (a test then skips).
"""

from __future__ import annotations

import functools
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Mapping


@functools.cache
def reason() -> str | None:
    """Why private mount namespaces cannot be used here (None if they can)."""
    if sys.platform != "linux":
        return "private mount namespaces are Linux only"
    if os.geteuid() != 0:
        return "mounting a tmpfs needs root"
    if shutil.which("unshare") is None or shutil.which("mount") is None:
        return "unshare or mount is not installed"
    with tempfile.TemporaryDirectory() as d:
        probe = f"mount -t tmpfs -o size=1m tmpfs {shlex.quote(d)} && mknod {shlex.quote(d)}/null c 1 3"
        try:
            done = subprocess.run(
                ["unshare", "--mount", "--propagation", "private", "sh", "-c", probe],
                capture_output=True,
                timeout=30,
            )
        except (OSError, subprocess.TimeoutExpired) as e:
            return f"unshare failed: {e}"
        if done.returncode != 0:
            return f"no private mount namespace with a tmpfs here: {done.stderr.decode(errors='replace').strip()}"
    return None


def run(
    argv: list[str],
    *,
    tmpfs: Mapping[str, int] | None = None,
    devices: Mapping[str, tuple[int, int]] | None = None,
    timeout: float = 300.0,
    cwd: str | None = None,
    env: Mapping[str, str] | None = None,
) -> subprocess.CompletedProcess[str]:
    """Run ``argv`` in a private mount namespace.

    Parameters
    ----------
    argv : list of str
        The command (e.g. ``[sys.executable, "-c", CODE]``).
    tmpfs : mapping of str to int, optional
        Existing directories to mount a tmpfs on, with its size in bytes (a "disk" that fills up).
    devices : mapping of str to (int, int), optional
        Character devices to create (``mknod PATH c MAJOR MINOR``), on one of the tmpfs mounts:
        ``{"/x/t/null": (1, 3)}`` makes a null device.

    Returns
    -------
    subprocess.CompletedProcess
        Its exit status and output (text).
    """
    steps = [f"mount -t tmpfs -o size={int(size)} tmpfs {shlex.quote(d)}" for d, size in (tmpfs or {}).items()]
    steps += [f"mknod {shlex.quote(p)} c {int(a)} {int(b)}" for p, (a, b) in (devices or {}).items()]
    steps.append("exec " + shlex.join(argv))
    return subprocess.run(
        ["unshare", "--mount", "--propagation", "private", "sh", "-c", " && ".join(steps)],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=cwd,
        env=None if env is None else dict(env),
        stdin=subprocess.DEVNULL,
    )
