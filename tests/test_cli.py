"""The command line: run as a user would (``python -m vpr_explorer.cli`` in a subprocess), and each option's
effect through ``main`` in this process."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from vpr_explorer.cli import main


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


# --------------------------------------------------------------------------- each option changes what it should
# These run ``main`` in this process (the demo route, a second or less each), reading the
# numbers back from ``--json`` and the printed table.

DEMO = ("--dataset", "demo", "--descriptor", "pixels")


def evaluate(tmp_path, capsys, *args: str) -> tuple[str, dict]:
    """``vpr-explorer evaluate`` on the demo route: (stdout, the --json file's content)."""
    out = tmp_path / f"ev{len(list(tmp_path.glob('ev*.json')))}.json"
    code = main(["evaluate", *DEMO, *args, "--json", str(out)])
    stdout = capsys.readouterr().out
    assert code == 0, stdout
    return stdout, json.loads(out.read_text())


def numbers(data: dict) -> dict:
    """Every method's numbers (Recall@K, accepted, precision, shares), by method key."""
    return {m["key"]: {k: v for k, v in m.items() if k not in ("key", "label", "source")} for m in data["methods"]}


def test_reading_skip_makes_fewer_places_and_other_numbers(tmp_path, capsys):
    # 60 frames, group 2, step 4: a place every 4 frames (stride, 15 places) or every 2 + 4 (skip, 10)
    stride_out, stride = evaluate(tmp_path, capsys, "--group", "2", "--step", "4", "--runs", "5")
    skip_out, skip = evaluate(tmp_path, capsys, "--group", "2", "--step", "4", "--runs", "5", "--reading", "skip")
    assert stride["settings"]["reading"] == "stride" and skip["settings"]["reading"] == "skip"
    assert stride["settings"]["places"].startswith("15 places × 6 images")
    assert skip["settings"]["places"].startswith("10 places × 6 images")
    assert "places=10 places × 6 images (group 2, step 4 (skip reading))" in skip_out.splitlines()[0]
    assert (stride["settings"]["queries_per_run"], skip["settings"]["queries_per_run"]) == (15, 10)
    assert numbers(stride) != numbers(skip)


def test_seed_draws_other_splits_and_the_same_seed_the_same_numbers(tmp_path, capsys):
    common = ("--group", "2", "--step", "4", "--runs", "5")
    out0, zero = evaluate(tmp_path, capsys, *common, "--seed", "0")
    again_out, again = evaluate(tmp_path, capsys, *common)  # 0 is the default
    _, one = evaluate(tmp_path, capsys, *common, "--seed", "1")
    assert (zero["settings"]["seed"], again["settings"]["seed"], one["settings"]["seed"]) == (0, 0, 1)
    assert numbers(zero) == numbers(again)
    assert out0.split("\n(")[0] == again_out.split("\n(")[0]  # the same table, timing aside
    assert numbers(one) != numbers(zero)
    r1 = {seed: {k: v["recall"]["1"]["mean"] for k, v in numbers(d).items()} for seed, d in ((0, zero), (1, one))}
    assert r1[0] != r1[1]


def test_cross_condition_leaves_no_top_1_match_in_the_own_traversal(tmp_path, capsys):
    common = ("--group", "2", "--step", "4", "--runs", "5")
    _, pooled = evaluate(tmp_path, capsys, *common)
    out, cross = evaluate(tmp_path, capsys, *common, "--cross-condition")
    assert cross["settings"]["cross_condition"] is True and pooled["settings"]["cross_condition"] is False
    own = {m["key"]: m["own_traversal_top1"]["mean"] for m in cross["methods"]}
    accepted = {m["key"]: m["accepted"]["mean"] for m in cross["methods"]}
    # None only where a method accepted no query in any split (no top-1 match to count)
    assert all(own[k] == 0.0 if accepted[k] > 0 else own[k] is None for k in own), own
    assert own["place-baseline"] == 0.0 and own["margin-weighted"] == 0.0
    assert {m["key"]: m["own_traversal_top1"]["mean"] for m in pooled["methods"]}["place-baseline"] > 0.2
    assert numbers(cross)["place-baseline"]["recall"] != numbers(pooled)["place-baseline"]["recall"]
    row = next(line for line in out.splitlines() if line.startswith("place-level baseline"))
    assert row.endswith("  0.0")


def test_unknown_share_holds_out_that_share_of_places(tmp_path, capsys):
    common = ("--group", "2", "--step", "4", "--runs", "4", "--protocol", "open-set", "--k", "0", "1")
    _, default = evaluate(tmp_path, capsys, *common)
    out, half = evaluate(tmp_path, capsys, *common, "--unknown-share", "0.5")
    # 15 places: round(0.3 * 15) = round(4.5) = 4 (to even), round(0.5 * 15) = round(7.5) = 8
    assert default["settings"]["unknown_share"] == 0.3 and half["settings"]["unknown_share"] == 0.5
    assert (default["settings"]["unknown_places_per_run"], default["settings"]["known_places_per_run"]) == (4, 11)
    assert (half["settings"]["unknown_places_per_run"], half["settings"]["known_places_per_run"]) == (8, 7)
    assert "unknown_places_per_run=8, known_places_per_run=7" in out.splitlines()[0]
    assert numbers(default) != numbers(half)


def test_theta_adds_the_user_row_and_a_higher_theta_accepts_fewer(tmp_path, capsys):
    common = ("--group", "2", "--step", "4", "--runs", "5")
    plain_out, plain = evaluate(tmp_path, capsys, *common)
    low_out, low = evaluate(tmp_path, capsys, *common, "--theta", "0.4")
    _, high = evaluate(tmp_path, capsys, *common, "--theta", "0.6")
    assert "global-user" not in numbers(plain) and "global θ, user value" not in plain_out
    assert "global θ, user value" in low_out
    assert (plain["settings"]["theta"], low["settings"]["theta"], high["settings"]["theta"]) == (None, 0.4, 0.6)
    accepted = [numbers(d)["global-user"]["accepted"]["mean"] for d in (low, high)]
    assert 0 < accepted[1] < accepted[0]
    # the other rows do not depend on --theta
    assert {k: v for k, v in numbers(low).items() if k != "global-user"} == numbers(plain)


def record(tmp_path, capsys, name: str, *args: str):
    """``vpr-explorer record`` night against day on the demo route, contiguous places; the .rrd read back."""
    from test_recording import read_rrd

    out = tmp_path / f"{name}.rrd"
    code = main(["record", *DEMO, "--database", "day", "--queries", "night", "--group", "2", "--step", "2",
                 "--out", str(out), *args])
    assert code == 0, capsys.readouterr().err
    capsys.readouterr()
    temporal, static = read_rrd(out)
    thresholds = np.asarray(static["/thresholds/weighted"]["BarChart:values"][0]["buffer"])
    levels = {f: row["TextLog:level"][0] for f, row in temporal["/decision/paper"].items()}
    return thresholds, levels, temporal, static


@pytest.fixture(scope="module")
def demo_day_model():
    """The demo route, its places (group 2, step 2) and the database model ``record`` fits: night against day."""
    from vpr_explorer.data.aligned import database_queries, value_rows
    from vpr_explorer.method.places import PlaceGeometry, PlaceSpec, make_places
    from vpr_explorer.pipeline import dataset_descriptors, resolve_dataset
    from vpr_explorer.views.numbers import RetrievalPlaces, fit_retrieval

    dataset = resolve_dataset("demo")
    spec = PlaceSpec(2, 2)
    value = database_queries(dataset, "night", ["day"])
    rows = value_rows(value)
    d = dataset_descriptors(dataset, "pixels")
    fitted = fit_retrieval(d if rows is None else d[rows], value, RetrievalPlaces(PlaceGeometry.FRAMES, spec=spec))
    return dataset, make_places(dataset, spec), fitted.model


def test_record_k_raises_the_logged_thresholds_and_changes_decisions(tmp_path, capsys, demo_day_model):
    _, _, model = demo_day_model
    theta0, levels0, _, static0 = record(tmp_path, capsys, "k0", "--k", "0")
    theta2, levels2, _, static2 = record(tmp_path, capsys, "k2", "--k", "2")
    np.testing.assert_allclose(theta0, model.theta["weighted"], rtol=1e-6)
    np.testing.assert_allclose(theta2, model.theta["weighted"] + 2 * model.spread, rtol=1e-6)
    assert np.all(theta2 > theta0)
    assert "k = 2" in static2["/summary"]["TextDocument:text"][0] and "k = 0" in static0["/summary"]["TextDocument:text"][0]
    # raised thresholds reject: right answers and wrong accepts become wrong rejects, never the other way
    changed = {f for f in levels0 if levels0[f] != levels2[f]}
    assert changed and all(levels2[f] == "WARN" for f in changed)
    assert "WARN" not in levels0.values()


def test_record_tolerance_counts_a_neighbouring_place_as_right(tmp_path, capsys, demo_day_model):
    dataset, places, _ = demo_day_model
    _, strict, temporal, _ = record(tmp_path, capsys, "t0")
    _, loose, _, _ = record(tmp_path, capsys, "t2", "--tolerance", "2")
    changed = sorted(f for f in strict if strict[f] != loose[f])
    assert changed, "--tolerance 2 changed no verdict"
    for f in changed:
        # a wrong accept made right: the answered place holds a frame within 2 frames of the query's
        assert (strict[f], loose[f]) == ("ERROR", "INFO")
        answered = int(temporal["/place/paper"][f]["Scalars:scalars"][0])
        frames = np.flatnonzero(places.frame_place == answered)
        assert answered != places.frame_place[f] and np.abs(frames - f).min() <= 2
    assert all(loose[f] == strict[f] for f in strict if f not in changed)
