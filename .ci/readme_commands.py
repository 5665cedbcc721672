"""Run every ``nplps`` command of the README's shell blocks, in order, with an installed nplps.

Usage: python .ci/readme_commands.py NPLPS_EXECUTABLE [--shared DIR]

Issue 22, item 7: after the README's one install command every command it documents works.
.ci/run installs the wheel it built into a fresh venv (no extras) and runs this script with that
venv's ``nplps``. The commands are read from README.md (continuation lines joined), run in one
temporary folder in the README's order (later commands use earlier results): a ``bash`` block of
the README holds commands that run as written, a ``text`` block templates that need the user's own
files (a RAW shoot, a LUCES copy). Changes made to
run them unattended, each printed:

* ``../shared/data`` is replaced by the real folder of the shared captures (``--shared``); the
  capture commands are skipped when it is absent;
* ``nplps view`` gets ``--no-open`` (no browser here);
* ``nplps batch`` is skipped: it needs the ``batch`` extra and a folder of captures
  (tests/test_batch.py runs it in the test venv).

Exit status 1 when a command fails; its output is printed.
"""

from __future__ import annotations

import argparse
import re
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def commands(readme: Path) -> list[str]:
    """Return the ``nplps`` command lines of the README's bash blocks, continuation lines joined."""
    out = []
    for block in re.findall(r"```(?:bash|sh)\n(.*?)```", readme.read_text(encoding="utf-8"), re.S):
        joined = re.sub(r"\\\n\s*", " ", block)
        for line in joined.splitlines():
            line = line.split(" #")[0].strip()
            if line.startswith("nplps "):
                out.append(line)
    return out


def main() -> int:
    """Run the commands; return the exit status."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("nplps", help="the nplps executable of the venv under test")
    parser.add_argument("--shared", type=Path, default=ROOT.parent / "shared" / "data")
    args = parser.parse_args()
    nplps = str(Path(args.nplps).resolve())  # the commands run in a temporary folder
    found = commands(ROOT / "README.md")
    if len(found) < 10:
        print(f"only {len(found)} nplps commands found in README.md: the extraction is broken", file=sys.stderr)
        return 1
    failed = 0
    with tempfile.TemporaryDirectory(prefix="nplps-readme-") as work:
        for line in found:
            argv = shlex.split(line)[1:]
            note = ""
            if argv[0] == "batch":
                print(
                    f"skip  {line}\n      (needs the batch extra and a folder of captures; tests/test_batch.py runs it)"
                )
                continue
            if "../shared/data" in line:
                if not args.shared.is_dir():
                    print(f"skip  {line}\n      (no shared captures at {args.shared})")
                    continue
                argv = [a.replace("../shared/data", str(args.shared)) for a in argv]
                note = f" [../shared/data -> {args.shared}]"
            if argv[0] == "view" and "--no-open" not in argv:
                argv.append("--no-open")
                note += " [+ --no-open]"
            start = time.perf_counter()
            run = subprocess.run([nplps, *argv], cwd=work, capture_output=True, text=True, stdin=subprocess.DEVNULL)
            took = time.perf_counter() - start
            status = "ok   " if run.returncode == 0 else "FAIL "
            print(f"{status}{line}{note}  ({took:.1f} s)")
            if run.returncode != 0:
                failed += 1
                print(run.stdout[-3000:], run.stderr[-3000:], sep="\n", file=sys.stderr)
    print(f"{len(found)} README commands: {failed} failed")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
