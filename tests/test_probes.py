"""The bad-input probe suite of issue 9: never abort, never hang, never lie.

Every case of ``tests/probes_cases.py`` (API snippets, command lines, crafted files) runs in a
worker subprocess under an address-space cap (``RLIMIT_AS``, 3 GiB) and a per-case time budget.
Cases run in batches, one interpreter per batch, and cases that allocate a lot or may abort run
alone. The worker logs a line before and after each case, so that a crash (a signal, an abort,
an exit) or a hang (the case's budget exceeded: the worker is killed) is pinned on its case; the
batch then goes on in a new worker with the cases left. A crash inside a batch is re-run alone to
tell whether it reproduces by itself.

Each case is one test (``test_probe[<case id>]``); a failure says what was expected and what
happened. ``python tests/test_probes.py --table`` runs them all and prints the markdown table
(``--failures`` only the failing cases, ``-k TEXT`` only cases whose id contains TEXT,
``--jobs N`` parallel workers).
"""

from __future__ import annotations

import concurrent.futures
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

import probes_cases  # noqa: E402
from probes_cases import CASES, Case, describe  # noqa: E402

#: Address-space cap of the workers.
ADDRESS_SPACE = 3 << 30
#: Cases per worker process.
BATCH = 50
#: Seconds a worker may take to start (imports, the small scenes) before it counts as hung.
STARTUP = 60.0
#: Attempts to start a worker that dies before its first case (nplps being rebuilt), and the
#: pause between them.
START_ATTEMPTS = 3
START_PAUSE = 20.0


@dataclass
class Outcome:
    id: str
    passed: bool
    happened: str
    seconds: float = 0.0


def _limit() -> None:
    """In the worker, before exec: the address-space cap, no core files."""
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE, ADDRESS_SPACE))
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))


def _signal_name(code: int) -> str:
    try:
        return signal.Signals(-code).name
    except ValueError:
        return f"signal {-code}"


MARKERS = ("memory allocation of", "panicked at", "Fatal Python error", "Segmentation fault", "Killed", "MemoryError")


def _tail(path: Path, n: int = 600) -> str:
    """What the worker printed when it died: the abort/panic lines and the innermost Python frame
    (faulthandler's dump), else its last lines."""
    try:
        text = path.read_text(errors="replace")
    except OSError:
        return ""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    key = [line for line in lines if any(m in line for m in MARKERS)][:3]
    for i, line in enumerate(lines):
        if "most recent call first" in line and i + 1 < len(lines):
            key.append("innermost: " + lines[i + 1])
            break
    return (" | ".join(key) if key else " | ".join(lines[-8:]))[-n:]


def _run_worker(ids: list[str], workdir: Path) -> tuple[dict[str, Outcome], str | None, str]:
    """Runs ``ids`` in one worker. Returns the finished outcomes, the case that crashed or hung
    (None if the worker ended normally), and a description of the crash or hang."""
    results = workdir / f"results-{os.getpid()}-{time.monotonic_ns()}.jsonl"
    log = results.with_suffix(".log")
    results.touch()
    env = dict(os.environ, PYTHONFAULTHANDLER="1", PYTHONDONTWRITEBYTECODE="1")
    with open(log, "wb") as log_file:
        proc = subprocess.Popen(
            [sys.executable, str(HERE / "probes_cases.py"), "--worker", str(results), *ids],
            stdin=subprocess.DEVNULL,
            stdout=log_file,
            stderr=subprocess.STDOUT,
            preexec_fn=_limit,
            start_new_session=True,
            env=env,
            cwd=str(workdir),
        )
        done: dict[str, Outcome] = {}
        current: str | None = None
        since = time.monotonic()
        budget = STARTUP
        offset = 0
        culprit, what = None, ""
        while True:
            with open(results, encoding="utf-8") as f:
                f.seek(offset)
                chunk = f.read()
            complete = chunk[: chunk.rfind("\n") + 1]
            offset += len(complete.encode("utf-8"))
            for line in complete.splitlines():
                rec = json.loads(line)
                if rec["event"] == "start":
                    current, since = rec["id"], time.monotonic()
                    budget = probes_cases.BY_ID[current].budget
                else:
                    done[rec["id"]] = Outcome(rec["id"], rec["passed"], rec["happened"], rec["seconds"])
                    current, since, budget = None, time.monotonic(), STARTUP
            code = proc.poll()
            if code is not None:
                if len(done) == len(ids):
                    break
                culprit = current
                how = f"killed by {_signal_name(code)}" if code < 0 else f"exited with status {code}"
                what = f"CRASH: the process {how}; output: {_tail(log) or '(none)'}"
                break
            if time.monotonic() - since > budget:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
                culprit = current
                what = f"HANG: still running after {budget:.0f} s (killed); output: {_tail(log) or '(none)'}"
                break
            time.sleep(0.02)
    for p in (results, log):
        p.unlink(missing_ok=True)
    if culprit is None and len(done) < len(ids):
        # Died outside a case: at start-up (e.g. nplps being rebuilt) or between two cases.
        culprit = next(i for i in ids if i not in done)
        what = ("worker failed before its first case: " if not done else "worker failed between cases: ") + what
    return done, culprit, what


def _run_batch(ids: list[str], workdir: Path) -> dict[str, Outcome]:
    """Runs ``ids`` in workers until each has an outcome; pins crashes and hangs on their case."""
    outcomes: dict[str, Outcome] = {}
    left = list(ids)
    failed_starts = 0
    while left:
        done, culprit, what = _run_worker(left, workdir)
        outcomes.update(done)
        if culprit is None:
            break
        if what.startswith("worker failed before its first case"):
            failed_starts += 1
            if failed_starts < START_ATTEMPTS:
                time.sleep(START_PAUSE)  # nplps may be being rebuilt: try again
                continue
            for i in left:
                outcomes[i] = Outcome(i, False, f"not run: {what}")
            break
        if len(left) > 1 and what.startswith("CRASH"):
            again, again_culprit, _ = _run_worker([culprit], workdir)
            if again_culprit == culprit:
                what += " (reproduced alone)"
            elif culprit in again:
                what += f" (did NOT reproduce alone, where it gave: {again[culprit].happened})"
        outcomes[culprit] = Outcome(culprit, False, what)
        left = [i for i in left if i not in outcomes]
    return outcomes


def run_cases(cases: list[Case], jobs: int | None = None) -> dict[str, Outcome]:
    """Runs the cases (batched, isolated ones alone) in ``jobs`` parallel workers."""
    jobs = jobs or max(1, min(4, os.cpu_count() or 1))
    # The longest first (big allocations, then the batches), so that the workers finish together.
    isolated = sorted(([c] for c in cases if c.isolate), key=lambda b: -b[0].budget)
    batched = [c for c in cases if not c.isolate]
    chunks = [batched[i : i + BATCH] for i in range(0, len(batched), BATCH)]
    ordered = [b for b in isolated if b[0].budget >= 60] + chunks + [b for b in isolated if b[0].budget < 60]
    batches = [[c.id for c in b] for b in ordered]
    outcomes: dict[str, Outcome] = {}
    with tempfile.TemporaryDirectory(prefix="nplps-probe-runner-") as workdir:
        with concurrent.futures.ThreadPoolExecutor(jobs) as pool:
            for result in pool.map(lambda b: _run_batch(b, Path(workdir)), batches):
                outcomes.update(result)
    return outcomes


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def table(cases: list[Case], outcomes: dict[str, Outcome], failures_only: bool = False) -> str:
    rows = ["| # | case | category | expected | outcome | result |", "|---|---|---|---|---|---|"]
    for n, c in enumerate(cases, 1):
        o = outcomes[c.id]
        if failures_only and o.passed:
            continue
        rows.append(
            f"| {n} | `{c.id}` | {c.category} | {_cell(describe(c.expect))} | {_cell(o.happened)} | "
            f"{'pass' if o.passed else '**FAIL**'} |"
        )
    return "\n".join(rows)


# --------------------------------------------------------------------------------------------------
# pytest
# --------------------------------------------------------------------------------------------------

try:
    import pytest
except ImportError:  # the --table entry point does not need pytest
    pytest = None

if pytest is not None:

    @pytest.fixture(scope="session")
    def probe_outcomes(request):
        """Runs the probes that this session selected, all at once (batched, in parallel)."""
        selected = set()
        for item in request.session.items:
            callspec = getattr(item, "callspec", None)
            if getattr(item, "originalname", None) == "test_probe" and callspec is not None:
                selected.add(callspec.params["case_id"])
        return run_cases([c for c in CASES if c.id in selected])

    @pytest.mark.parametrize("case_id", [c.id for c in CASES])
    def test_probe(case_id, probe_outcomes):
        case = probes_cases.BY_ID[case_id]
        outcome = probe_outcomes[case_id]
        if not outcome.passed:
            pytest.fail(
                f"probe {case_id} [{case.category}]\n"
                f"  input:    {case.argv if case.kind == 'cli' else case.code}\n"
                f"  expected: {describe(case.expect)}\n"
                f"  happened: {outcome.happened}",
                pytrace=False,
            )

    def test_probe_suite_covers_the_issue():
        """At least 150 cases, unique ids, across the API, the command line and files."""
        assert len(CASES) >= 150
        assert len({c.id for c in CASES}) == len(CASES)
        kinds = {c.kind for c in CASES}
        assert kinds == {"api", "cli"}
        assert any(c.id.startswith("files.") for c in CASES) and any(c.id.startswith("rigfile.") for c in CASES)


def main(argv: list[str]) -> int:
    import argparse

    p = argparse.ArgumentParser(description="Run the bad-input probes and print the table.")
    p.add_argument("--table", action="store_true", help="print the markdown table of every case")
    p.add_argument("--failures", action="store_true", help="print only the failing cases")
    p.add_argument("-k", default=None, help="only the cases whose id contains this text")
    p.add_argument("--jobs", type=int, default=None)
    args = p.parse_args(argv)
    cases = [c for c in CASES if args.k is None or args.k in c.id]
    start = time.perf_counter()
    outcomes = run_cases(cases, args.jobs)
    wall = time.perf_counter() - start
    failed = [c for c in cases if not outcomes[c.id].passed]
    if args.table or args.failures:
        print(table(cases, outcomes, failures_only=args.failures and not args.table))
        print()
    crashes = sum(outcomes[c.id].happened.startswith("CRASH") for c in failed)
    hangs = sum(outcomes[c.id].happened.startswith("HANG") for c in failed)
    print(
        f"{len(cases)} cases: {len(cases) - len(failed)} pass, {len(failed)} fail "
        f"({crashes} crashes, {hangs} hangs) in {wall:.1f} s"
    )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
