"""The command line's hard edges: bad numbers, options a protocol would ignore, what the
JSON records, the traversal protocol's direction, error lines beside progress bars, Ctrl-C.

Refusals run ``main`` in this process (they stop before any work); runs, progress bars and
Ctrl-C run ``python -m vpr_explorer.cli`` in a subprocess, as a user would, on the demo
route or small routes written here.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import cli_run
from cli_run import refused, run
from images import write_noisy_route

DEMO = ("--dataset", "demo", "--descriptor", "pixels")
INTERRUPTED = "error: interrupted; run the same command again to resume (descriptors computed so far are cached)"



def assert_one_error_line(r: subprocess.CompletedProcess, *fragments: str) -> str:
    """The one ``error:`` line (a progress bar's lines may stand beside it)."""
    return cli_run.assert_one_error_line(r, *fragments, alone=False)


def write_route(root: Path, names: tuple[str, ...], frames: int = 8, corrupt: str | None = None) -> Path:
    """A small traversal-folder route: one sub-folder of noisy PNG frames per name."""
    return write_noisy_route(root, names, frames, corrupt)


# --------------------------------------------------------------------------- 1. numbers out of range


@pytest.mark.parametrize("args, fragments", [
    (["--seed", "-1"], ["seed=-1", "0 or more"]),
    (["--seed", str(2**63)], [f"seed={2**63}", "9,223,372,036,854,775,807 or less"]),
    (["--group", "99999999999999999999", "--step", "99999999999999999999"],
     ["group=99999999999999999999", "10,000,000"]),
    (["--group", "3", "--step", "99999999999999999999"], ["step=99999999999999999999", "10,000,000"]),
    (["--group", "99999999999999999999", "--reading", "skip"], ["group=99999999999999999999", "10,000,000"]),
    (["--runs", "100000"], ["runs=100000", "1,000 or less", "memory", "the paper uses 50"]),
    (["--theta", "nan"], ["theta=nan", "finite"]),
    (["--theta", "inf"], ["theta=inf", "finite"]),
    (["--tolerance", "-1"], ["tolerance=-1", "0 or more"]),
    (["--protocol", "traversal", "--tolerance", "-3"], ["tolerance=-3", "0 or more"]),
    (["--protocol", "traversal", "--tolerance", "61"], ["tolerance=61", "60 or less", "60 frames"]),
    (["--protocol", "traversal", "--tolerance", "99999999999999999999"], ["tolerance=99999999999999999999",
                                                                          "10,000,000 or less"]),
    (["--protocol", "open-set", "--unknown-share", "nan"], ["unknown_share=nan", "between 0 and 1"]),
    (["--protocol", "open-set", "--unknown-share", "1.5"], ["unknown_share=1.5", "between 0 and 1"]),
    (["--protocol", "open-set", "--k", "0", "inf"], ["k=inf", "finite"]),
])
def test_bad_numbers_are_one_error_line_naming_the_option_and_limit(args, fragments, capsys, tmp_path):
    start = time.perf_counter()
    r = refused(capsys, "evaluate", *DEMO, "--cache-dir", str(tmp_path / "cache"), *args)
    assert_one_error_line(r, *fragments)
    assert r.stdout == ""
    assert not (tmp_path / "cache").exists()  # refused before any descriptor was computed
    assert time.perf_counter() - start < 10


@pytest.mark.parametrize("args, fragments", [
    (["--k", "nan"], ["k=nan", "finite"]),
    (["--tolerance", "-1"], ["tolerance=-1", "0 or more"]),
    (["--group", "99999999999999999999"], ["group=99999999999999999999", "10,000,000"]),
])
def test_record_bad_numbers_are_one_error_line(args, fragments, tmp_path, capsys):
    r = refused(capsys, "record", *DEMO, "--database", "day", "--queries", "night", "--out", str(tmp_path / "x.rrd"),
                *args)
    assert_one_error_line(r, *fragments)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- 4. options a protocol would ignore


@pytest.mark.parametrize("protocol, args, option, owner", [
    ("paper", ["--database", "day"], "--database", "traversal and database-queries protocols"),
    ("paper", ["--queries", "night"], "--queries", "traversal and database-queries protocols"),
    ("open-set", ["--database", "day", "snow"], "--database", "traversal and database-queries protocols"),
    ("open-set", ["--queries", "night"], "--queries", "traversal and database-queries protocols"),
    ("traversal", ["--runs", "3"], "--runs", "paper and open-set protocols"),
    ("traversal", ["--seed", "4"], "--seed", "paper and open-set protocols"),
    ("traversal", ["--cross-condition"], "--cross-condition", "paper and open-set protocols"),
    ("traversal", ["--unknown-share", "0.2"], "--unknown-share", "open-set protocol"),
    ("traversal", ["--k", "1"], "--k", "open-set protocol"),
    ("paper", ["--unknown-share", "0.2"], "--unknown-share", "open-set protocol"),
    ("paper", ["--k", "0", "1"], "--k", "open-set protocol"),
])
def test_an_option_the_protocol_would_ignore_is_refused(protocol, args, option, owner, capsys):
    r = refused(capsys, "evaluate", *DEMO, "--protocol", protocol, *args)
    assert_one_error_line(r, option, owner, f"--protocol {protocol}")


# --------------------------------------------------------------------------- 2. the JSON records every setting


def test_json_records_theta_and_every_option_of_a_paper_run(tmp_path):
    out = tmp_path / "ev.json"
    r = run("evaluate", *DEMO, "--group", "2", "--step", "4", "--runs", "3", "--seed", "7", "--cross-condition",
            "--theta", "0.25", "--json", str(out))
    assert r.returncode == 0, r.stderr
    data = json.loads(out.read_text())
    assert data["protocol"] == "paper"
    s = data["settings"]
    assert s["theta"] == 0.25
    assert {k: s[k] for k in ("descriptor", "dtype", "group", "step", "reading", "runs", "seed", "cross_condition",
                              "tolerance")} == {
        "descriptor": "pixels", "dtype": "float32", "group": 2, "step": 4, "reading": "stride", "runs": 3,
        "seed": 7, "cross_condition": True, "tolerance": 0}
    assert "global-user" in [m["key"] for m in data["methods"]]


def test_json_records_the_open_set_and_traversal_options(tmp_path):
    out = tmp_path / "open.json"
    r = run("evaluate", *DEMO, "--group", "2", "--step", "4", "--reading", "skip", "--protocol", "open-set",
            "--runs", "2", "--unknown-share", "0.4", "--k", "0", "1", "--json", str(out))
    assert r.returncode == 0, r.stderr
    s = json.loads(out.read_text())["settings"]
    assert (s["reading"], s["unknown_share"], s["k_grid"], s["runs"], s["theta"]) == ("skip", 0.4, [0.0, 1.0], 2, None)

    out = tmp_path / "trav.json"
    r = run("evaluate", *DEMO, "--group", "1", "--step", "1", "--protocol", "traversal", "--database", "day",
            "--queries", "snow", "--tolerance", "1", "--theta", "-0.5", "--json", str(out))
    assert r.returncode == 0, r.stderr
    s = json.loads(out.read_text())["settings"]
    assert (s["database"], s["queries"], s["tolerance"], s["theta"], s["group"], s["step"]) == (
        ["day"], "snow", 1, -0.5, 1, 1)


# --------------------------------------------------------------------------- 4. --tolerance works for every protocol


def _recall1(path: Path) -> dict[str, float]:
    return {m["key"]: m["recall"]["1"]["mean"] for m in json.loads(path.read_text())["methods"]}


def test_tolerance_changes_the_paper_protocols_numbers(tmp_path):
    """Contiguous places (group 3, step 3): with ±2 frames of slack a neighbouring place can be right too."""
    r1 = {}
    for tol in (0, 2):
        out = tmp_path / f"tol{tol}.json"
        r = run("evaluate", *DEMO, "--group", "3", "--step", "3", "--runs", "5", "--tolerance", str(tol),
                "--json", str(out))
        assert r.returncode == 0, r.stderr
        assert json.loads(out.read_text())["settings"]["tolerance"] == tol
        r1[tol] = _recall1(out)
    assert all(r1[2][key] >= r1[0][key] for key in r1[0])
    assert any(r1[2][key] > r1[0][key] for key in r1[0])


# --------------------------------------------------------------------------- 6. the traversal protocol's direction


def test_traversal_protocol_recognises_ref_and_query_folders(tmp_path):
    route = write_route(tmp_path / "route", ("query", "ref"))  # folder order alone would make query the database
    r = run("evaluate", "--dataset", str(route), "--descriptor", "pixels", "--group", "1", "--step", "1",
            "--protocol", "traversal", "--cache-dir", str(tmp_path / "cache"))
    assert r.returncode == 0, r.stderr
    assert "database=['ref']" in r.stdout and "queries=query" in r.stdout
    assert "queries query against database ref (default, recognised from the traversal names)" in r.stdout


def test_traversal_protocol_header_counts_the_database_images():
    r = run("evaluate", *DEMO, "--group", "1", "--step", "1", "--protocol", "traversal")
    assert r.returncode == 0, r.stderr
    # the demo's first traversal against its last: 60 places of one database image each, not 3 images
    assert "places=60 places × 1 database images" in r.stdout, r.stdout
    assert "queries snow against database day (default by folder order" in r.stdout


# --------------------------------------------------------------------------- 7. an error beside a progress bar


def test_an_error_during_extraction_is_on_a_line_of_its_own(tmp_path):
    route = write_route(tmp_path / "route", ("a", "b"), corrupt="a/000.png")
    r = run("evaluate", "--dataset", str(route), "--descriptor", "pixels", "--group", "1", "--step", "1",
            "--runs", "1", "--cache-dir", str(tmp_path / "cache"))
    assert "descriptors" in r.stderr  # a bar was drawn before the failure
    assert_one_error_line(r, "000.png")


# --------------------------------------------------------------------------- 9. Ctrl-C


def test_ctrl_c_is_one_line_and_exit_130(tmp_path):
    """SIGINT while descriptors are extracted (an empty cache: efficientnet-lite0 takes seconds on the demo)."""
    # ``python -m vpr_explorer.cli`` with Python's own Ctrl-C handler, whatever SIGINT disposition this
    # process had when it forked (tests/test_cache_interrupt.py's DEFAULT_SIGINT says why)
    cli = ("import runpy, signal; signal.signal(signal.SIGINT, signal.default_int_handler); "
           "runpy.run_module('vpr_explorer.cli', run_name='__main__', alter_sys=True)")
    proc = subprocess.Popen(
        [sys.executable, "-c", cli, "evaluate", "--dataset", "demo", "--descriptor",
         "efficientnet-lite0", "--cache-dir", str(tmp_path / "cache"), "--runs", "1"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=dict(os.environ),
    )
    seen = b""
    while b"descriptors" not in seen:  # the bar is drawn: extraction has started
        chunk = proc.stderr.read1(4096)
        assert chunk, f"exited before extraction: {seen!r}"
        seen += chunk
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    err = (seen + err).decode()
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err
    (line,) = [line for line in err.split("\n") if "error:" in line]
    said = re.fullmatch(r"error: interrupted; (\d+) of 180 descriptors cached; run the same command again to resume",
                        line)
    assert said, line
    from vpr_explorer.descriptors import DescriptorCache

    assert DescriptorCache(tmp_path / "cache").stats()["vectors"] == int(said[1])  # the line tells the truth
    assert out == b""


def test_unusable_cache_fails_before_the_demo_is_drawn(tmp_path, monkeypatch):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("VPR_EXPLORER_CACHE", str(blocker / "cache"))
    r = run("evaluate", *DEMO, "--runs", "1")
    assert_one_error_line(r, "cache folder")
    r = run("record", *DEMO, "--database", "day", "--queries", "night", "--out", str(tmp_path / "x.rrd"))
    assert_one_error_line(r, "cache folder")
    assert not (tmp_path / "x.rrd").exists()
    # a good --cache-dir, but the demo route (drawn under VPR_EXPLORER_CACHE) cannot be written
    r = run("evaluate", *DEMO, "--runs", "1", "--cache-dir", str(tmp_path / "good"))
    assert_one_error_line(r, "cannot write the demo route there")
