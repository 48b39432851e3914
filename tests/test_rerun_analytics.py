"""rerun's usage analytics stay off for the tests (``conftest.rerun_analytics_off``).

rerun 0.41's own command line (``python -m rerun_cli``, the ``rerun`` that opens a ``.rrd``)
prints a first-run notice and writes its analytics config under the user's folders; with
the session's environment it does neither. Each run here gets an empty home, so the user's
own rerun settings play no part.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

#: the variable conftest.rerun_analytics_off sets for the session
RERUN_ANALYTICS_OFF = "CI"
NOTICE = "Welcome to Rerun!"


def rerun_analytics_config(home: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    """``rerun analytics config`` with ``home`` as the user's home, config and data folders."""
    folders = {"HOME": str(home), "XDG_CONFIG_HOME": str(home / "config"), "XDG_DATA_HOME": str(home / "data")}
    home.mkdir()
    return subprocess.run([sys.executable, "-m", "rerun_cli", "analytics", "config"], capture_output=True,
                          text=True, timeout=60, env={**env, **folders})


def files_under(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.is_file()]


def test_rerun_prints_no_notice_and_writes_nothing_in_the_tests(tmp_path):
    assert RERUN_ANALYTICS_OFF in os.environ
    run = rerun_analytics_config(tmp_path / "session", dict(os.environ))
    assert run.returncode == 0, run.stderr
    assert NOTICE not in run.stdout + run.stderr
    assert run.stdout.strip() == "null"  # no analytics config: none is loaded or made
    assert files_under(tmp_path / "session") == []


def test_without_it_rerun_would_print_its_notice(tmp_path):
    """The check above means something: the same command with the variable unset greets a new user."""
    env = {k: v for k, v in os.environ.items() if k != RERUN_ANALYTICS_OFF}
    run = rerun_analytics_config(tmp_path / "user", env)
    assert run.returncode == 0, run.stderr
    assert NOTICE in run.stdout + run.stderr
    assert any(p.name == "analytics.json" for p in files_under(tmp_path / "user"))
