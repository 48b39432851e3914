"""The command line as the tests run it: in a subprocess, or ``main`` in this process, and its one error line."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from vpr_explorer.cli import main


def run(*args: str, cwd: Path | None = None, timeout: float = 600) -> subprocess.CompletedProcess:
    """``python -m vpr_explorer.cli ARGS`` in a subprocess, with this process's environment."""
    return subprocess.run([sys.executable, "-m", "vpr_explorer.cli", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=cwd, env=dict(os.environ))


def refused(capsys, *args: str) -> subprocess.CompletedProcess:
    """``main(args)`` in this process, as a finished process (return code, stdout, stderr)."""
    code = main(list(args))
    out, err = capsys.readouterr()
    return subprocess.CompletedProcess(args, code, out, err)


def assert_one_error_line(r: subprocess.CompletedProcess, *fragments: str, alone: bool = True) -> str:
    """Exit 2, no traceback, and one ``error:`` line holding every fragment; returns that line.

    ``alone``: stderr holds nothing else (no other non-blank line); without it, other lines
    (a progress bar's) may stand beside the one ``error:`` line.
    """
    assert r.returncode == 2, (r.returncode, r.stdout[-300:], r.stderr[-1000:])
    assert "Traceback" not in r.stderr, r.stderr[-2000:]
    lines = [line for line in r.stderr.split("\n") if line.strip() and (alone or "error:" in line)]
    assert len(lines) == 1 and lines[0].startswith("error: "), repr(r.stderr[-500:])
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    return lines[0]
