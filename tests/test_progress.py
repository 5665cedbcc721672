"""Progress that tells the truth (issue 11, item 6): one display per stage, bounded output.

The distance search names its candidates and the best so far, the final solve is told apart from
the search's iterations, a terminal gets lines redrawn in place, a pipe a few plain lines.
"""

from __future__ import annotations

import io
import math
import re

import numpy as np
import pytest

import nplps
from nplps import cli, pipeline
from nplps.progress import CTRL_C_HINT, Bar, PipelineProgress, ReconstructionProgress, aborting, format_duration


class FakeTerminal(io.StringIO):
    """A text stream that says it is a terminal."""

    def isatty(self) -> bool:
        return True


class FakeClock:
    """A clock that advances by ``step`` seconds at every reading."""

    def __init__(self, step: float) -> None:
        self.now, self.step = 0.0, step

    def __call__(self) -> float:
        self.now += self.step
        return self.now


@pytest.fixture(scope="module")
def auto_scene(tmp_path_factory):
    """A small scene saved as files, and the result of ``depth="auto"`` on it with every report."""
    scene = nplps.make_scene("sphere", n=32, seed=0)
    folder = tmp_path_factory.mktemp("progress") / "scene"
    scene.save(folder)
    seen: list[nplps.Iteration] = []
    result = nplps.reconstruct(scene.images, scene.rig, mask=scene.mask, depth="auto", progress=seen.append)
    return scene, folder, seen, result


def test_the_callable_gets_the_search_candidates_then_the_final_solve(auto_scene):
    _, _, seen, result = auto_scene
    search = [it for it in seen if it.candidate > 0]
    solve = [it for it in seen if it.candidate == 0]
    assert search and solve
    # The search comes first; the final solve's iterations are exactly the result's history.
    assert seen.index(solve[0]) == len(search)
    assert [tuple(it[:7]) for it in solve] == [tuple(h[:7]) for h in result.history]
    assert all(math.isnan(it.distance) for it in solve)
    # Candidates are numbered 1..n; a plan is announced (it grows when the search needs more, and the
    # search may end sooner) and every candidate's last iteration carries its residual.
    n = search[-1].candidate
    assert [it.candidate for it in search] == sorted(it.candidate for it in search)
    assert {it.candidate for it in search} == set(range(1, n + 1))
    assert all(it.candidates >= it.candidate for it in search)
    assert [it.candidates for it in search] == sorted(it.candidates for it in search)
    last = {it.candidate: it for it in search}
    assert all(math.isfinite(it.candidate_residual) for it in last.values())
    assert sum(math.isfinite(it.candidate_residual) for it in search) == n
    # The curve of the estimate holds the same candidates, and the best one is the lowest residual.
    curve = result.distance.curve[0]
    assert len(curve) == n
    assert sorted(it.distance for it in last.values()) == pytest.approx([d for d, _ in curve])
    best = min(last.values(), key=lambda it: it.candidate_residual)
    assert last[n].best_distance == pytest.approx(best.distance)
    assert last[n].best_residual == pytest.approx(best.candidate_residual)
    assert result.distance.distance[0] == pytest.approx(best.distance, rel=0.01)


def test_cli_depth_auto_prints_a_few_lines_naming_the_candidates_and_the_best(auto_scene, tmp_path, capsys):
    _, folder, _, _ = auto_scene
    argv = [folder, "--rig", folder / "rig.json", "--mask", folder / "mask.png", "--depth", "auto"]
    rc = cli.main(["reconstruct", *map(str, argv), "--out", str(tmp_path / "out")])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    lines = captured.err.splitlines()
    assert len(lines) < 40, captured.err  # was ~142 "iteration k/10" lines
    assert lines.count(f"({CTRL_C_HINT})") == 1
    assert lines.index(f"({CTRL_C_HINT})") < min(i for i, line in enumerate(lines) if line.startswith("load"))
    # Each stage ends with one summary line.
    assert re.search(r"^load: 27 images read in ", captured.err, re.M)
    summary = re.search(r"^distance search: (\d+) candidates, best ([\d.]+) \(residual ", captured.err, re.M)
    assert summary, captured.err
    assert re.search(r"^iterations: \d+ iterations?, last depth change .*, converged, ", captured.err, re.M)
    assert re.search(r"^export: \d+ files written in ", captured.err, re.M)
    # Lines in between name the candidate distance, its residual and the best so far.
    assert re.search(
        r"^distance search: \d+/\d+ ~\S+ s left, best [\d.]+, candidate [\d.]+: residual \S+$", captured.err, re.M
    )
    assert "iteration 1/10" not in captured.err
    # The summary says what each number counts.
    assert f"distance search {summary.group(1)} candidate distances evaluated" in captured.out
    assert re.search(r"iterations +\d+ \(the final solve at the estimated distance\)", captured.out)


def test_progress_true_draws_bars_in_place_on_a_terminal(monkeypatch):
    scene = nplps.make_scene("sphere", n=24, seed=1)
    term = FakeTerminal()
    monkeypatch.setattr("sys.stderr", term)
    nplps.reconstruct(scene.images, scene.rig, mask=scene.mask, depth="auto", progress=True)
    text = term.getvalue()
    assert "\r" in text
    # Every stage's line is redrawn in place and ends with its summary: a few newlines only.
    finished = [line.rsplit("\r", 1)[-1].rstrip() for line in text.split("\n") if line]
    assert len(finished) <= 4, finished
    assert any(line.startswith("distance search: ") and "candidates, best" in line for line in finished)
    assert any(line.startswith("iterations: ") and "converged" in line for line in finished)
    # The bar itself is drawn while the search runs.
    assert re.search(r"\rdistance search \[[#.]{10}\] \d+/\d+ .*candidate [\d.]+: ", text)


def test_a_plain_stream_gets_a_bounded_number_of_lines():
    out = io.StringIO()
    bar = Bar("stage", total=1000, stream=out, clock=FakeClock(0.5))
    for i in range(1, 1001):
        bar.update(i, f"item {i}")
    bar.close("1000 items")
    lines = out.getvalue().splitlines()
    # 4 milestones (20 % .. 80 %) and at most one line per 10 s of the fake 500 s, then the summary.
    assert 5 <= len(lines) <= 4 + 50 + 1
    assert lines[-1] == "stage: 1000 items"
    fast = io.StringIO()
    bar = Bar("stage", total=1000, stream=fast, clock=FakeClock(1e-4))
    for i in range(1, 1001):
        bar.update(i)
    bar.close("done")
    assert fast.getvalue().splitlines() == [f"stage: {n}/1000" for n in (200, 400, 600, 800)] + ["stage: done"]


def test_a_terminal_bar_is_rate_limited_and_cleared():
    term = FakeTerminal()
    bar = Bar("load", total=100, stream=term, clock=FakeClock(0.01))
    for i in range(1, 101):
        bar.update(i, "a-long-file-name.png" if i < 50 else "b.png")
    bar.close("100 images read")
    text = term.getvalue()
    assert text.count("\r") <= 100 // 10 + 2  # at most 10 redraws a second
    assert text.endswith("\n") and text.count("\n") == 1
    *_, before, final = text.split("\r")
    assert final.startswith("load: 100 images read")
    assert len(final.rstrip("\n")) >= len(before)  # the longer bar line is blanked out


def test_pipeline_reports_each_image_and_each_step(tmp_path):
    scene = nplps.make_scene("bumps", n=16, seed=2)
    scene.save(tmp_path / "s")
    files = sorted((tmp_path / "s").glob("image_*.png"))
    events: list[tuple[str, int, int, str]] = []
    prepared = pipeline.prepare(
        files, rig=scene.rig, ambient=np.zeros((16, 16)), bin_factor=2, progress=lambda *e: events.append(e)
    )
    loads = [e for e in events if e[0] == "load"]
    assert [e[1] for e in loads] == list(range(1, len(files) + 1))
    assert {e[2] for e in loads} == {len(files)}
    assert [e[3] for e in loads] == [f.name for f in files]
    steps = [e[3] for e in events if e[0] == "preprocess"]
    assert steps == ["ambient", "bin"] == list(prepared.steps)
    out = io.StringIO()
    display = PipelineProgress(stream=out)
    pipeline.prepare(files, rig=scene.rig, bin_factor=2, progress=display)
    display.finish()
    lines = out.getvalue().splitlines()
    assert lines[-2].startswith(f"load: {len(files)} images read in ")
    assert lines[-1].startswith("preprocess: bin in ")


def test_reconstruction_progress_summaries_without_a_search():
    out = io.StringIO()
    display = ReconstructionProgress(10, stream=out)
    for i in range(1, 4):
        display(nplps.Iteration(i, 10.0**-i, 0.1, 0.1 * i))
    display.finish()
    assert out.getvalue().splitlines()[-1].startswith("iterations: 3 iterations, last depth change 1.00e-03, ")
    assert display.search_summary() == ""


def test_format_duration():
    assert format_duration(0.123) == "0.12 s"
    assert format_duration(42.4) == "42 s"
    assert format_duration(185) == "3 min 5 s"
    assert format_duration(3720) == "1 h 2 min"
    assert format_duration(float("nan")) == "?"


def test_the_core_gives_sizes_width_first():
    """The Rust messages print sizes "W x H" like Python's (issue 11): a 24-row, 16-column stack."""
    scene = nplps.make_scene("bumps", n=16, seed=3)
    images = np.concatenate([scene.images, scene.images[:, :8]], axis=1)  # (k, 24, 16)
    with pytest.raises(nplps.MemoryLimitError, match=r"reconstructing 16 x 24 pixels"):
        nplps.reconstruct(images, scene.rig, depth=scene.mean_depth, max_memory="1 kB")
    from nplps import _core

    with pytest.raises(nplps.InputError, match=r"the mask is 15 x 24 pixels but the images are 16 x 24"):
        _core.calibrate_intensities(
            np.ascontiguousarray(images, dtype=np.float32),
            np.ones((24, 15), dtype=bool),
            scene.rig._native,
            [0.0, 0.0, -1.0],
            scene.mean_depth,
            {},
        )


def test_aborting_ends_the_open_line_and_reraises():
    stream = FakeTerminal()
    bar = Bar("load", total=4, stream=stream, clock=FakeClock(1.0))
    bar.update(1, "a.png")
    with pytest.raises(KeyboardInterrupt), aborting(bar):
        raise KeyboardInterrupt
    assert bar.closed and stream.getvalue().endswith("\n")  # the error message starts on its own line
    with aborting(None):  # nothing shown: nothing to end
        pass
    ok = Bar("export", stream=FakeTerminal())
    with aborting(ok):
        ok.update(0, "writing")
    assert not ok.closed  # no error: the caller closes it with its summary
