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
