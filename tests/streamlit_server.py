"""Start and stop a real ``streamlit run`` server on a free port of 127.0.0.1, for browser tests.

    with streamlit_server("app.py") as url:
        page.goto(url)

The server inherits the environment (so ``VPR_EXPLORER_CACHE`` / ``VPR_EXPLORER_DATA``
set by the test session reach it), listens on 127.0.0.1 only, runs headless with file
watching, usage statistics and the browser launch off, and is ready once
``/_stcore/health`` answers ``ok``. Its output goes to a log file, printed to stderr when
startup fails or the ``with`` block raises (pytest shows it beside the failure).
``serving`` does the same for any command that starts one (``vpr-explorer app``).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STARTUP_TIMEOUT = 60.0


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def healthy(url: str) -> bool:
    """True when the Streamlit server at ``url`` answers its health check."""
    try:
        with urllib.request.urlopen(f"{url}/_stcore/health", timeout=2) as response:
            return response.status == 200 and response.read().strip() == b"ok"
    except (urllib.error.URLError, OSError):
        return False


@contextmanager
def serving(
    cmd: Sequence[str],
    port: int,
    *,
    cwd: str | Path = ROOT,
    env: Mapping[str, str] | None = None,
    timeout: float = STARTUP_TIMEOUT,
) -> Iterator[Callable[[], str]]:
    """Run ``cmd``, a Streamlit server on 127.0.0.1:``port``, until the block ends.

    Yields ``output()``: what the server printed so far (stdout and stderr).

    Args:
        env: extra environment variables for the server (added to ``os.environ``).
        timeout: seconds to wait for ``/_stcore/health``.
    """
    url = f"http://127.0.0.1:{port}"
    log = tempfile.NamedTemporaryFile("w+", prefix="streamlit-", suffix=".log", delete=False)

    def output() -> str:
        log.flush()
        return Path(log.name).read_text()

    proc = subprocess.Popen(list(cmd), cwd=cwd, env={**os.environ, **(env or {})}, stdout=log,
                            stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + timeout
        while not healthy(url):
            if proc.poll() is not None or time.monotonic() > deadline:
                why = f"exited with {proc.returncode}" if proc.poll() is not None else f"not healthy after {timeout:.0f} s"
                raise RuntimeError(f"streamlit server {why} (its log is printed below): {' '.join(cmd)}")
            time.sleep(0.2)
        yield output
    except BaseException:
        # Printed, so that pytest shows the server's side of a failing test.
        print(f"--- streamlit server log ({url}) ---\n{output()[-6000:]}", file=sys.stderr)
        raise
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()
        os.unlink(log.name)


@contextmanager
def streamlit_server(
    script: str | Path = "app.py",
    *,
    cwd: str | Path = ROOT,
    env: Mapping[str, str] | None = None,
    extra_args: tuple[str, ...] = (),
    timeout: float = STARTUP_TIMEOUT,
) -> Iterator[str]:
    """Run ``streamlit run script`` until the block ends; yields its base URL ``http://127.0.0.1:PORT``.

    Args:
        script: the app's entry point, relative to ``cwd``.
        env: extra environment variables for the server (added to ``os.environ``).
        extra_args: more ``streamlit run`` options, e.g. ``("--server.maxUploadSize", "10")``.
        timeout: seconds to wait for ``/_stcore/health``.
    """
    port = free_port()
    cmd = [
        sys.executable, "-m", "streamlit", "run", str(script),
        "--server.headless", "true",
        "--server.address", "127.0.0.1",
        "--server.port", str(port),
        "--server.fileWatcherType", "none",
        "--browser.gatherUsageStats", "false",
        *extra_args,
    ]
    with serving(cmd, port, cwd=cwd, env=env, timeout=timeout):
        yield f"http://127.0.0.1:{port}"
