"""The README's complete example runs as written (issue 11, item 9)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"
MARKER = "A complete example that runs as written"


def _example() -> str:
    text = README.read_text(encoding="utf-8")
    start = text.index(MARKER)
    match = re.search(r"```python\n(.*?)```", text[start:], re.S)
    assert match is not None, "no python block after the README's complete example"
    return match.group(1)


def test_readme_complete_example_runs_as_written(tmp_path: Path) -> None:
    script = tmp_path / "example.py"
    script.write_text(_example(), encoding="utf-8")
    run = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert lines[0].startswith("<Reconstruction 64 x 64 pixels") and "status='converged'" in lines[0]
    found = re.search(r"mean normal error ([0-9.]+) deg", run.stdout)
    assert found is not None, run.stdout
    assert float(found.group(1)) < 1.0
    assert (tmp_path / "result" / "mesh.ply").is_file() and (tmp_path / "scene" / "rig.json").is_file()


def _cli_example() -> list[str]:
    """The command lines of the README's "Use it" block (after ``nplps``)."""
    text = README.read_text(encoding="utf-8")
    start = text.index("## Use it")
    match = re.search(r"```bash\n(.*?)```", text[start:], re.S)
    assert match is not None, "no bash block under 'Use it'"
    lines = [line.split("#")[0].strip() for line in match.group(1).splitlines()]
    return [line for line in lines if line.startswith("nplps ")]


def test_readme_cli_example_reconstructs_at_the_scenes_distance(tmp_path: Path) -> None:
    """The first CLI example gives the scene's own distance: no "looks wrong" warning, converged."""
    import json
    import shlex

    commands = _cli_example()
    assert commands[0].startswith("nplps synth") and commands[1].startswith("nplps reconstruct")
    for command in commands[:2]:
        argv = shlex.split(command)[1:]
        run = subprocess.run(
            [sys.executable, "-m", "nplps", *argv], cwd=tmp_path, capture_output=True, text=True, timeout=600
        )
        assert run.returncode == 0, run.stderr
        assert "looks wrong" not in run.stderr, run.stderr
    summary = json.loads((tmp_path / "result" / "summary.json").read_text(encoding="utf-8"))
    assert summary["status"] == "converged"
    assert summary["distance_check"] is not None and not summary["distance_check"]["looks_wrong"]
    truth = float(
        re.search(
            r"true mean depth ([0-9.]+)",
            subprocess.run(
                [sys.executable, "-m", "nplps", *shlex.split(commands[0])[1:], "--overwrite"],
                cwd=tmp_path,
                capture_output=True,
                text=True,
                timeout=600,
            ).stdout,
        ).group(1)
    )
    given = float(shlex.split(commands[1])[shlex.split(commands[1]).index("--depth") + 1])
    assert abs(given / truth - 1) < 0.01, (given, truth)


def test_ci_runs_every_readme_command_from_the_wheel() -> None:
    """.ci/readme_commands.py (run by .ci/run with the fresh wheel venv) finds every nplps command."""
    import importlib.util

    path = README.parent / ".ci" / "readme_commands.py"
    spec = importlib.util.spec_from_file_location("readme_commands", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    found = module.commands(README)
    text = README.read_text(encoding="utf-8")
    # Every line of a bash block that starts with "nplps " is one command (continuations joined).
    expected = sum(
        1
        for block in re.findall(r"```(?:bash|sh)\n(.*?)```", text, re.S)
        for line in block.splitlines()
        if line.strip().startswith("nplps ")
    )
    assert len(found) == expected >= 10
    assert found[0] == "nplps demo"
    assert not any(c.endswith("\\") for c in found)
    spheres = next(c for c in found if c.startswith("nplps calibrate spheres"))
    assert "--out calib/rig_spheres.json" in spheres  # the continuation line was joined
    assert any("--capture diligent" in c for c in found)
