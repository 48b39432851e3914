"""Ctrl-C while ``vpr-explorer`` is still starting: one ``error:`` line and exit 130, never a traceback.

Real processes and real signals: the installed console script (and ``python -m
vpr_explorer.cli``, which runs the same way) is started on the demo route and sent SIGINT
while it imports numpy and scipy, watched through ``/proc/PID/maps``; the console script
also at fixed instants after it was started.

What no code of the package can reach is Python's own start-up before the console script
calls ``main()``: a SIGINT that lands before the interpreter has installed its handler ends
the process by the signal, silently (the shell reports 130); one that lands while Python
initialises (its streams, ``site``) or while the script imports ``vpr_explorer.cli`` ends
in Python's traceback. The fixed instants accept exactly those outcomes there (:func:`before_main`) and
nothing else after; that stretch ends about 20-40 ms after the start on this project's machine
(an editable install's ``.pth`` imports pathlib in ``site``; without bytecode caches the
script compiles ``vpr_explorer.cli`` too).
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = Path(sys.executable).parent / "vpr-explorer"
#: how the command is started: the console script, and ``python -m`` from this checkout
LAUNCHERS = {"console-script": [str(SCRIPT)], "python-m": [sys.executable, "-m", "vpr_explorer.cli"]}
STARTING = "error: interrupted while starting; nothing was done"
#: shared objects mapped while ``vpr_explorer.cli`` imports, in the order they load: numpy's core
#: (numpy's import is half done), scipy's first, scipy.stats' own (near the end)
MARKERS = {
    "numpy": re.compile(r"/numpy/_?core/_multiarray_umath"),
    "scipy": re.compile(r"/scipy/"),
    "scipy.stats": re.compile(r"/scipy/stats/_stats\."),
}
#: when a SIGINT is sent, in ms after the process was started (``Popen`` returns once exec has run)
INSTANTS_MS = (0, 20, 50, 100, 200, 400, 1000)

pytestmark = pytest.mark.skipif(not Path("/proc/self/maps").is_file(), reason="reads /proc/PID/maps (Linux)")


def default_sigint() -> None:
    """In the child before exec: SIGINT's default action, so that Python installs its own handler.

    Python installs its handler only over the default; an ignored SIGINT, which exec keeps,
    would leave the child deaf to the test's signal (tests/test_cache_interrupt.py says when
    a test process has one).
    """
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def start(launcher: str, tmp_path: Path) -> subprocess.Popen:
    """``vpr-explorer evaluate --dataset demo`` with a cache of its own, from this checkout's root."""
    command = [*LAUNCHERS[launcher], "evaluate", "--dataset", "demo", "--cache-dir", str(tmp_path / "cache")]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                            preexec_fn=default_sigint)


def mapped(pid: int, marker: re.Pattern) -> bool:
    try:
        return marker.search(Path(f"/proc/{pid}/maps").read_text()) is not None
    except (FileNotFoundError, ProcessLookupError):  # it has exited
        return False


def before_main(proc: subprocess.Popen, err: str) -> bool:
    """Whether the signal ended the process before the console script called ``main()``, as Python does.

    Before the interpreter has installed its handler, the signal's default action ends it
    silently; inside the rest of its initialisation (its standard streams, the ``site``
    import), "Fatal Python error: init_…" and a traceback; inside the generated script's own imports
    (``from vpr_explorer.cli import main`` and the packages it imports), a traceback whose outermost
    frame is one of those lines. Once the script has called ``main()`` none of these may happen.
    """
    if proc.returncode == -signal.SIGINT and err == "":
        return True
    if err.startswith("Fatal Python error: init_"):  # init_sys_streams, init_import_site: Python's initialisation
        return True
    outermost = re.search(r'Traceback \(most recent call last\):\n  File "([^"]+)", line \d+, in <module>\n(.*)', err)
    if outermost is None or outermost[1] != str(SCRIPT) or "main()" in outermost[2]:
        return False
    return all(map(before_main_imports, re.findall(r'^  File "([^"]+)", line \d+, in ', err, re.MULTILINE)))


def before_main_imports(file: str) -> bool:
    """Whether a traceback's frame is in what the script imports before ``main()``: the package's
    ``__init__`` and ``errors``, ``cli/__init__``, the standard library, an editable install's finder."""
    path = Path(file)
    if file.startswith("<frozen ") or path == SCRIPT:
        return True
    if path.parent.name == "vpr_explorer":
        return path.name in ("__init__.py", "errors.py")
    if path.parent.name == "cli" and path.parent.parent.name == "vpr_explorer":
        return path.name == "__init__.py"
    return "site-packages" not in path.parts or path.name.startswith("__editable__")


def assert_one_error_line(proc: subprocess.Popen, err: str) -> list[str]:
    assert proc.returncode == 130, err[-3000:]
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err[-3000:]
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines and lines[-1].startswith("error: interrupted"), err[-3000:]
    return lines


@pytest.mark.parametrize("launcher", list(LAUNCHERS))
@pytest.mark.parametrize("marker", list(MARKERS))
def test_ctrl_c_while_the_modules_load_is_one_line(launcher, marker, tmp_path):
    proc = start(launcher, tmp_path)
    deadline = time.monotonic() + 60
    while not mapped(proc.pid, MARKERS[marker]):
        assert proc.poll() is None, f"exited before {marker} was loaded: {proc.communicate()}"
        assert time.monotonic() < deadline, f"{marker} never loaded"
        time.sleep(0.001)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    lines = assert_one_error_line(proc, err)
    assert lines == [STARTING]  # the modules were still loading: nothing ran, nothing else printed
    assert out == ""


def test_ctrl_c_at_each_instant_of_the_start(tmp_path):
    """The console script (``python -m`` has one more stretch of Python's own: runpy finding and reading the module)."""
    ours = []
    for ms in INSTANTS_MS:
        started = time.monotonic()
        proc = start("console-script", tmp_path)
        time.sleep(max(0.0, started + ms / 1000 - time.monotonic()))
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
        if before_main(proc, err):
            continue
        assert_one_error_line(proc, err)
        ours.append(ms)
    assert ours and ours[-1] == INSTANTS_MS[-1], ours  # the later instants reach the command's own handling


def test_an_ignored_sigint_stays_ignored_while_starting(tmp_path):
    """Started with SIGINT ignored (``nohup``, a background job of a script): the command runs on to its end."""
    proc = subprocess.Popen([str(SCRIPT), "list", "--dataset", "demo"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=ROOT, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    deadline = time.monotonic() + 60
    while not mapped(proc.pid, MARKERS["numpy"]) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.001)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err[-3000:]
    assert "error:" not in err
    assert "day/frame_000.png" in out
