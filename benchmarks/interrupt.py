"""How fast Ctrl-C stops a reconstruction (issue 9: "Ctrl-C within 0.5 s anywhere").

Usage::

    python benchmarks/interrupt.py [--sizes 1024 2048] [--delays 0.05 0.3 0.7 1.2 2.0]
                                   [--cases multigrid direct tukey refine]

For every size and case, a child process loads a synthetic scene (bumps, 27 lights, float32
stack written once to a temporary folder), prints "ready" and starts a reconstruction with
``iterations=1000, tol=0``; the parent sends SIGINT after each delay (so the signal lands in
different stages: input checks, pyramid, set-up, local steps, conjugate gradients, final fit)
and measures the time until the child has caught ``KeyboardInterrupt`` (the child reports the
moment on the same monotonic clock). It prints the latencies, their median and maximum.
"""

from __future__ import annotations

import argparse
import signal
import statistics
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

CASES = {
    "multigrid": "",
    "direct": ', solver="direct"',
    "tukey": ', robust="tukey"',
    "refine": ', refine_lights="intensity"',
}


def child_script(folder: Path, options: str) -> str:
    return textwrap.dedent(
        f"""
        import sys, time, numpy as np, nplps
        images = np.load({str(folder / "images.npy")!r})
        mask = np.load({str(folder / "mask.npy")!r})
        rig = nplps.Rig.load({str(folder / "rig.json")!r})
        depth = float(open({str(folder / "depth.txt")!r}).read())
        print("ready", flush=True)
        try:
            nplps.reconstruct(images, rig, mask=mask, depth=depth, iterations=1000, tol=0.0{options})
        except KeyboardInterrupt:
            print("interrupted", time.monotonic(), flush=True)
            sys.exit(3)
        print("finished", flush=True)
        """
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1024, 2048])
    parser.add_argument("--delays", type=float, nargs="+", default=[0.05, 0.3, 0.7, 1.2, 2.0])
    parser.add_argument("--cases", nargs="+", choices=sorted(CASES), default=["multigrid", "direct", "tukey", "refine"])
    args = parser.parse_args()
    import numpy as np

    import nplps

    print("| size | case | latencies (s) | median | max |")
    print("|---|---|---|---|---|")
    for n in args.sizes:
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp)
            scene = nplps.make_scene("bumps", n=n)
            np.save(folder / "images.npy", scene.images.astype(np.float32))
            np.save(folder / "mask.npy", scene.mask)
            scene.rig.save(folder / "rig.json")
            (folder / "depth.txt").write_text(repr(scene.mean_depth))
            del scene
            for case in args.cases:
                if case == "direct" and n > 1024:
                    continue  # the direct factor at 2048^2 takes minutes and gigabytes
                latencies = []
                for delay in args.delays:
                    proc = subprocess.Popen(
                        [sys.executable, "-c", child_script(folder, CASES[case])], stdout=subprocess.PIPE, text=True
                    )
                    assert proc.stdout is not None
                    assert proc.stdout.readline().strip() == "ready"
                    time.sleep(delay)
                    sent = time.monotonic()
                    proc.send_signal(signal.SIGINT)
                    out = proc.stdout.read()
                    proc.wait()
                    if proc.returncode != 3:
                        print(
                            f"  {n} {case} delay {delay}: exit {proc.returncode}, {out.strip()[:60]!r}", file=sys.stderr
                        )
                        continue
                    latencies.append(float(out.split()[1]) - sent)
                text = ", ".join(f"{x:.3f}" for x in latencies)
                print(
                    f"| {n}² | {case} | {text} | {statistics.median(latencies):.3f} | {max(latencies):.3f} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
