"""``vpr-explorer extract --ray HOST:PORT`` where no Ray head answers: one line naming what did, within 15 s.

Real servers on 127.0.0.1 (threads of the test, random ports) and the real command in a
subprocess: Python's ``http.server``, a server that accepts and says nothing, one that
closes at once, one that answers like Redis (``-ERR``), and one that answers as an HTTP/2
server (a SETTINGS frame) and then says nothing, so that the probe lets it through and
ray.init's bounded join has to end it. A Ray head's GCS answers the probe as the last one
does; tests/test_ray.py joins a real one.
"""

from __future__ import annotations

import functools
import http.server
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from images import write_random_png

from vpr_explorer.descriptors import distributed

ROOT = Path(__file__).resolve().parents[1]
WITHIN_S = 15.0  # what a user waits at most, from the command's start to its error line
#: an HTTP/2 server's first frame: SETTINGS (type 4) with no settings, on stream 0
SETTINGS = bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """Two traversal folders of two tiny PNGs each."""
    root = tmp_path_factory.mktemp("tiny")
    for t, traversal in enumerate(("day", "night")):
        (root / traversal).mkdir()
        for f in range(2):
            write_random_png(root / traversal / f"{f:03d}.png", seed=10 * t + f, size=(16, 12))
    return root


@contextmanager
def tcp_server(answer: Callable[[socket.socket], None]) -> Iterator[str]:
    """``127.0.0.1:PORT`` of a server that runs ``answer`` on each connection it accepts."""
    listener = socket.create_server(("127.0.0.1", 0))
    held: list[socket.socket] = []

    def serve() -> None:
        while True:
            try:
                conn, _ = listener.accept()
            except OSError:  # the listener was closed
                return
            held.append(conn)
            threading.Thread(target=answer, args=(conn,), daemon=True).start()

    threading.Thread(target=serve, daemon=True).start()
    try:
        yield f"127.0.0.1:{listener.getsockname()[1]}"
    finally:
        listener.close()
        for conn in held:
            conn.close()


def say_nothing(conn: socket.socket) -> None:
    try:
        while conn.recv(4096):
            pass
    except OSError:
        pass


def close_at_once(conn: socket.socket) -> None:
    conn.close()


def like_redis(conn: socket.socket) -> None:
    try:
        conn.recv(4096)
        conn.sendall(b"-ERR unknown command 'PRI', with args beginning with: \r\n")
        say_nothing(conn)
    except OSError:
        pass


def like_http2(conn: socket.socket) -> None:
    try:
        conn.sendall(SETTINGS)
        say_nothing(conn)
    except OSError:
        pass


@contextmanager
def http_server(folder: Path) -> Iterator[str]:
    """``127.0.0.1:PORT`` of Python's ``http.server`` serving ``folder``."""

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(folder)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield f"127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()


def extract(dataset: Path, cache: Path, address: str) -> list[str]:
    return [sys.executable, "-m", "vpr_explorer.cli", "extract", "--dataset", str(dataset), "--descriptor", "pixels",
            "--cache-dir", str(cache), "--ray", address]


def run_extract(dataset: Path, tmp_path: Path, address: str) -> tuple[subprocess.CompletedProcess, float]:
    """The command's result and how long it took (killed, and the test failed, after 60 s)."""
    start = time.monotonic()
    out = subprocess.run(extract(dataset, tmp_path / "cache", address), capture_output=True, text=True, cwd=ROOT,
                         timeout=60)
    return out, time.monotonic() - start


def the_error_line(out: subprocess.CompletedProcess) -> str:
    """The one line on stderr, an ``error:`` line, of a command that exited 2."""
    assert out.returncode == 2, out.stderr[-3000:]
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), out.stderr[-3000:]
    assert out.stdout == ""
    return lines[0]


# ------------------------------------------------------------------ the probe names what answered


def test_an_http_server_is_named_with_its_status_line_and_server(dataset, tmp_path):
    with http_server(tmp_path) as address:
        out, seconds = run_extract(dataset, tmp_path, address)
    line = the_error_line(out)
    assert line.startswith(f"error: --ray {address}: not a Ray cluster: an HTTP server answered there "
                           f"(HTTP/1.0 200 OK, Server: SimpleHTTP/"), line
    assert "ray start --head" in line
    assert seconds < WITHIN_S


@pytest.mark.parametrize("answer, said", [
    (say_nothing, "it accepted the connection but said nothing within 3 s"),  # distributed.PROBE_TIMEOUT_S
    (close_at_once, "it accepted the connection and closed it without a word"),
    (like_redis, "it answered b\"-ERR unknown command 'PRI'"),
], ids=["silent", "closes", "redis"])
def test_a_server_that_is_no_ray_head_is_one_line_naming_what_it_did(dataset, tmp_path, answer, said):
    with tcp_server(answer) as address:
        out, seconds = run_extract(dataset, tmp_path, address)
    line = the_error_line(out)
    assert line.startswith(f"error: --ray {address}: not a Ray cluster: {said}"), line
    assert seconds < WITHIN_S


def test_an_http2_answer_passes_the_probe(monkeypatch):
    with tcp_server(like_http2) as address:
        start = time.monotonic()
        distributed._check_reachable(address)  # no error: a Ray head's GCS answers so
        assert time.monotonic() - start < 1.0
    # with RAY_USE_TLS the plain preface is not sent: a TLS head would not answer it
    monkeypatch.setenv("RAY_USE_TLS", "1")
    with tcp_server(say_nothing) as address:
        start = time.monotonic()
        distributed._check_reachable(address)
        assert time.monotonic() - start < 1.0


# ------------------------------------------------------------------ past the probe: ray.init, bounded


def test_an_http2_server_that_never_takes_the_join_ends_within_the_bound(dataset, tmp_path):
    pytest.importorskip("ray")
    with tcp_server(like_http2) as address:
        out, seconds = run_extract(dataset, tmp_path, address)
    assert out.returncode == 2, out.stderr[-3000:]
    assert "Traceback" not in out.stderr
    # Ray logs its own tries on stderr meanwhile, from C++ too; the command's error is one line among them
    (line,) = [line for line in out.stderr.splitlines() if line.startswith("error:")]
    assert line.startswith(f"error: --ray {address}: no Ray cluster joined within 10 s: "  # JOIN_TIMEOUT_S
                           "it answers as an HTTP/2 server"), line
    # the join's bound, plus Python's and Ray's imports (about 2 s here, more on a busy machine)
    assert 10 <= seconds < WITHIN_S + 5


def test_ctrl_c_while_ray_tries_to_join_ends_at_once(dataset, tmp_path):
    pytest.importorskip("ray")
    with tcp_server(like_http2) as address:
        proc = subprocess.Popen(extract(dataset, tmp_path / "cache", address), stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, cwd=ROOT,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        seen = b""
        while b"Connecting to existing Ray cluster" not in seen:  # Ray's first line: ray.init has begun
            chunk = proc.stderr.read1(4096)
            assert chunk, f"exited before joining: {seen!r}"
            seen += chunk
        time.sleep(1.0)  # well inside its tries
        proc.send_signal(signal.SIGINT)
        sent = time.monotonic()
        _, err = proc.communicate(timeout=60)
        waited = time.monotonic() - sent
    err = (seen + err).decode()
    assert proc.returncode == 130, err[-3000:]
    assert "Traceback" not in err
    assert [line for line in err.splitlines() if line.startswith("error:")] == [
        "error: interrupted; run the same command again to resume (descriptors computed so far are cached)"]
    assert waited < 3.0
