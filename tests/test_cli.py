"""The command line, run as a user would: the installed ``vpr-explorer`` script in a subprocess."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest


def run(*args, env=None):
    return subprocess.run(
        [sys.executable, "-m", "vpr_explorer.cli", *args], capture_output=True, text=True, timeout=600,
        env={**os.environ, **(env or {})},
    )


def test_evaluate_demo_paper_protocol_json(tmp_path):
    out = tmp_path / "ev.json"
    r = run("evaluate", "--dataset", "demo", "--descriptor", "pixels", "--group", "2", "--step", "4",
            "--runs", "5", "--json", str(out))
    assert r.returncode == 0, r.stderr
    for label in ("image-level baseline", "place-level baseline", "margin, simple θ", "margin, weighted θ",
                  "raw, simple θ", "raw, weighted θ", "global θ, automatic", "global θ, oracle"):
        assert label in r.stdout
    data = json.loads(out.read_text())
    assert data["protocol"] == "paper" and data["settings"]["runs"] == 5
    keys = [m["key"] for m in data["methods"]]
    assert keys[:2] == ["image-baseline", "place-baseline"]
    r1 = {m["key"]: m["recall"]["1"]["mean"] for m in data["methods"]}
    assert all(0 <= v <= 1 for v in r1.values())
    # the printed table carries the JSON's numbers (percent, one decimal)
    line = next(l for l in r.stdout.splitlines() if l.startswith("place-level baseline"))
    assert f"{100 * r1['place-baseline']:.1f}" in line


def test_evaluate_open_set_prints_tradeoff():
    r = run("evaluate", "--dataset", "demo", "--descriptor", "pixels", "--group", "2", "--step", "4",
            "--runs", "3", "--protocol", "open-set", "--k", "0", "1", "2")
    assert r.returncode == 0, r.stderr
    assert "unknown rejected" in r.stdout
    assert "θ_p(k) weighted (margin)" in r.stdout and "global θ (raw)" in r.stdout


def test_evaluate_traversal_protocol():
    r = run("evaluate", "--dataset", "demo", "--descriptor", "pixels", "--group", "1", "--step", "1",
            "--protocol", "traversal", "--database", "day", "--queries", "night", "--tolerance", "1")
    assert r.returncode == 0, r.stderr
    assert "database=['day']" in r.stdout and "queries=night" in r.stdout


@pytest.mark.parametrize("args, fragment", [
    (["--dataset", "/nonexistent/route"], "the dataset folder does not exist"),
    (["--dataset", "demo", "--group", "3", "--step", "2"], "step=2 < group=3"),
    (["--dataset", "demo", "--group", "40", "--step", "40"], "at least 2 places"),
    (["--dataset", "demo", "--descriptor", "sift"], "sift"),
    (["--dataset", "demo", "--protocol", "traversal", "--queries", "dusk"], "traversal 'dusk' is not in dataset"),
    (["--dataset", "demo", "--runs", "0"], "runs=0"),
])
def test_bad_input_is_one_clear_line(args, fragment):
    r = run("evaluate", "--descriptor", "pixels", *args)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("error: ") and fragment in last


def test_unwritable_json_path(tmp_path):
    r = run("evaluate", "--dataset", "demo", "--descriptor", "pixels", "--group", "2", "--step", "4", "--runs", "1",
            "--json", str(tmp_path / "missing" / "x.json"))
    assert r.returncode == 2 and "--json" in r.stderr and "cannot write" in r.stderr


def test_evaluate_float16_descriptors(tmp_path):
    # Its own cache folder: float16 shards in the session cache would serve other tests' float32 runs.
    common = ("evaluate", "--dataset", "demo", "--descriptor", "pixels", "--group", "2", "--step", "4", "--runs", "3")
    half = run(*common, "--dtype", "float16", "--cache-dir", str(tmp_path / "c16"), "--json", str(tmp_path / "16.json"))
    assert half.returncode == 0, half.stderr
    for label in ("image-level baseline", "place-level baseline", "margin, weighted θ", "global θ, oracle"):
        assert label in half.stdout
    shards = list((tmp_path / "c16").rglob("*.npy"))
    assert shards and all(np.load(p).dtype == np.float16 for p in shards)
    single = run(*common, "--cache-dir", str(tmp_path / "c32"), "--json", str(tmp_path / "32.json"))
    assert single.returncode == 0, single.stderr
    r1 = [{m["key"]: m["recall"]["1"]["mean"] for m in json.loads((tmp_path / f"{bits}.json").read_text())["methods"]}
          for bits in (16, 32)]
    assert r1[0].keys() == r1[1].keys()
    for key in r1[1]:  # ~1e-3 relative error in the scores moves a recall by a few ties at most
        assert abs(r1[0][key] - r1[1][key]) <= 0.02, key


def test_record_float16_descriptors(tmp_path):
    out = tmp_path / "run.rrd"
    r = run("record", "--dataset", "demo", "--database", "day", "--queries", "night", "--descriptor", "pixels",
            "--group", "2", "--step", "4", "--dtype", "float16", "--cache-dir", str(tmp_path / "c16"),
            "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert f"wrote {out}" in r.stdout and out.stat().st_size > 0
    shards = list((tmp_path / "c16").rglob("*.npy"))
    assert shards and all(np.load(p).dtype == np.float16 for p in shards)


@pytest.mark.parametrize("command", ["evaluate", "record"])
def test_bad_dtype_is_refused_by_argparse(command, tmp_path):
    r = run(command, "--dataset", "demo", "--dtype", "float64", "--database", "day", "--queries", "night",
            "--out", str(tmp_path / "x.rrd"))
    assert r.returncode == 2
    assert "argument --dtype: invalid choice: 'float64'" in r.stderr and "float16" in r.stderr
    assert r.stdout == "" and not (tmp_path / "x.rrd").exists()


def test_dtype_help_names_the_tradeoff():
    r = run("evaluate", "--help")
    assert r.returncode == 0
    text = " ".join(r.stdout.split())
    assert "--dtype {float32,float16}" in text
    assert "float16 halves the descriptor memory and disk, at about 1e-3 relative error in scores" in text
