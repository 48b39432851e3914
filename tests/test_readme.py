"""The README's commands are the ones CI runs."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _bash_blocks(text: str) -> list[str]:
    return [b.strip() for b in re.findall(r"```bash\n(.*?)```", text, flags=re.S)]


def test_ci_runs_the_readmes_test_command_verbatim():
    readme = (ROOT / "README.md").read_text()
    two = readme[readme.index("## Two commands"):readme.index("## What it computes")]
    app, tests = _bash_blocks(two)[:2]
    assert app.endswith("streamlit run app.py") and "python -m pip install" in app
    assert tests.endswith("python -m pytest") and "python -m pip install" in tests  # one pip spelling
    ci = (ROOT / ".ci" / "run").read_text()
    assert f"({tests}) 2>&1" in ci
