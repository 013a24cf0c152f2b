"""The README's set-up commands and CI stay in step."""
from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _readme_commands() -> list[str]:
    text = (REPO / "README.md").read_text()
    blocks = re.findall(r"```bash\n(.*?)```", text, flags=re.S)
    return [line.strip() for line in blocks[0].splitlines() if line.strip() and not line.startswith("#")]


def test_readme_starts_with_the_two_fresh_machine_commands():
    cmds = _readme_commands()
    assert len(cmds) == 2
    assert cmds[0].startswith("python3 -m venv .venv") and cmds[0].endswith("monostixels demo")
    assert "pip install torch==2.13.0" in cmds[0] and "pip install torch==2.13.0" in cmds[1]
    assert cmds[1].endswith("python -m pytest -q")


def test_ci_runs_the_readme_test_command():
    ci = (REPO / ".ci" / "run").read_text()
    want = _readme_commands()[1].replace("pip install ", "pip install -q ")
    assert want in ci
