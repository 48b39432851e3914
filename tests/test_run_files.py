"""Runs read back from files (``compare.read_run_file``): an evaluation's JSON round trip, a runs export and a real
``vpr-explorer bench`` result opened in the Evaluation page's runs side by side, and the links that reopen them.

The bench runs once for the module on the demo route (pixels, the paper protocol with 3 splits and the traversal
protocol); the app tests open its ``bench.json`` under AppTest.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from streamlit.testing.v1 import AppTest

from test_app import app, assert_clean, fresh_caches, navigation_mode, page  # noqa: F401  (fixtures)
from vpr_explorer import pipeline
from vpr_explorer.app import DATA_ROOT_ENV, ENTRY
from vpr_explorer.cli import main
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import PlaceSpec, make_places
from vpr_explorer.protocols import compare
from vpr_explorer.protocols.evaluation import Evaluation


def same(a, b) -> bool:
    """Equal numbers, NaN equal to NaN, in nested dicts and lists."""
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return isinstance(b, (list, tuple)) and len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b


def paper_run(demo, demo_pixels, **options) -> Evaluation:
    """The paper protocol on the demo route, 3 splits."""
    places = make_places(demo, PlaceSpec(3, 10))
    return pipeline.run_protocol("paper", demo, places, demo_pixels, runs=3, seed=0,
                                 settings={"dataset": "demo", "descriptor": "pixels"}, **options)


@pytest.fixture(scope="module")
def demo_run(demo, demo_pixels):
    """precision–recall on: per-split values, PR rows and curves."""
    return paper_run(demo, demo_pixels, pr=True)


def test_an_evaluation_comes_back_from_its_json(demo_run):
    ev = demo_run
    back = Evaluation.from_dict(json.loads(json.dumps(ev.to_dict())))
    assert back.same_numbers(ev)
    assert back.protocol is ev.protocol and back.ks == ev.ks and back.settings == ev.settings
    for a, b in zip(ev.rows, back.rows):
        assert a.per_split.keys() == b.per_split.keys() and a.per_split
        for name in a.per_split:
            np.testing.assert_array_equal(a.per_split[name], b.per_split[name])  # NaN where a split has none
        assert same(a.unknown_rejection, b.unknown_rejection)
    assert [p.to_dict() for p in back.pr] == [p.to_dict() for p in ev.pr]
    assert back.pr_curves.keys() == ev.pr_curves.keys()
    for name, curve in back.pr_curves.items():
        assert curve.threshold[0] == np.inf  # the start point, None in JSON
        assert curve.to_dict() == ev.pr_curves[name].to_dict()  # the written points, counts and summaries
        assert curve.auc == pytest.approx(ev.pr_curves[name].auc, abs=0)


def test_a_bad_evaluation_is_named():
    with pytest.raises(VPRInputError, match="not an evaluation written by vpr-explorer"):
        Evaluation.from_dict({"protocol": "paper"})


def test_a_runs_export_reads_back_with_its_numbers(demo_run, demo, demo_pixels, tmp_path):
    other = paper_run(demo, demo_pixels, tolerance=1)
    runs, _ = compare.add_runs((), [compare.record(demo_run, run_id=""), compare.record(other, run_id="")], 0)
    path = tmp_path / "runs.json"
    path.write_text(compare.runs_json(runs))
    found, notes = compare.read_run_file(path)
    assert notes == [] and [r.name for r in found] == [r.name for r in runs]
    back, issued = compare.add_runs((), found, 0)
    assert [r.id for r in back] == ["run 1", "run 2"] and issued == 2
    metrics = ["R@1", "precision", "AUC"]
    assert same(compare.metric_table(back, metrics), compare.metric_table(runs, metrics))
    # the two runs share their splits: read back, their difference is paired, split by split, as it is in memory
    d0, d1 = (compare.difference(r[1], r[0], "R@1", "margin-weighted") for r in (runs, back))
    assert d1.paired and same(d1.to_dict(), d0.to_dict())
    again, _ = compare.add_runs(back, found, issued)
    assert len(again) == 2  # the same settings are not kept twice


@pytest.fixture(scope="module")
def bench_json(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench") / "out"
    missing = out.parent / "no-such-dataset"
    code = main(["bench", "--datasets", "demo", str(missing), "--descriptors", "pixels", "--protocols", "paper",
                 "traversal", "--runs", "3", "--out", str(out)])
    assert code == 1  # the missing dataset's cells failed
    return out / "bench.json"


def test_a_bench_result_is_one_run_per_cell(bench_json):
    data = json.loads(bench_json.read_text())
    found, notes = compare.read_run_file(bench_json)
    ran = [c for c in data["cells"] if c["evaluation"] is not None]
    assert len(found) == len(ran) == 2 and len(notes) == len(data["cells"]) - len(ran) >= 1
    assert all("failed in the bench" in n and "no-such-dataset" in n for n in notes)
    for run, cell in zip(found, ran):
        assert run.name == f"{cell['dataset']} · {cell['descriptor']} · {cell['protocol']}"
        assert run.settings["descriptor"] == "pixels" and run.settings["protocol"] == cell["protocol"]
        by_key = {m["key"]: m for m in cell["evaluation"]["methods"]}
        for key, m in by_key.items():
            assert run.value("R@1", key) == pytest.approx(m["recall"]["1"]["mean"], abs=0)
    paper = next(r for r in found if r.settings["protocol"] == "paper")
    diff = compare.method_difference(paper, "R@1", "margin-weighted", "place-baseline")
    assert diff.n == 3  # per-split values came with the file: a paired difference over the 3 splits


@pytest.mark.parametrize("content, fragment", [
    ("not json", "not JSON"),
    ('{"something": 1}', "neither a runs export"),
    ('{"runs": [{"name": "a"}]}', "lacks 'settings'"),
    ('{"runs": [{"name": "a", "settings": {}, "evaluation": {"protocol": "nope"}}]}',
     "not an evaluation written by vpr-explorer"),
])
def test_a_file_that_is_not_runs_is_named(tmp_path, content, fragment):
    path = tmp_path / "runs.json"
    path.write_text(content)
    with pytest.raises(VPRInputError, match=fragment) as info:
        compare.read_run_file(path)
    assert str(path) in str(info.value)


def test_a_file_too_large_or_missing_is_refused(tmp_path, monkeypatch):
    with pytest.raises(VPRInputError, match="cannot be read"):
        compare.read_run_file(tmp_path / "absent.json")
    path = tmp_path / "big.json"
    path.write_text('{"runs": []}' + " " * 100)
    monkeypatch.setattr(compare, "MAX_RUN_FILE_BYTES", 64)
    with pytest.raises(VPRInputError, match="more than a runs file holds"):
        compare.read_run_file(path)


# --------------------------------------------------------------------------- the app




def runs_table(at: AppTest):
    return next(d for d in at.dataframe if "name" in d.value.columns and "pinned" in d.value.columns).value


def test_the_app_opens_a_bench_result_and_its_link_reopens_it(app, bench_json):
    at = page(app.run(), "evaluation")
    at.text_input(key="w_runs_file").set_value(str(bench_json)).run()
    assert_clean(at)
    names = list(runs_table(at)["name"])
    assert "demo · pixels · paper" in names and "demo · pixels · traversal" in names
    assert any("2 runs read from" in c.value for c in at.caption)
    assert any("failed in the bench" in c.value for c in at.caption)
    params = dict(at.query_params)
    assert params["eval_runs_file"] == str(bench_json.resolve())
    file_ids = [i for i in at.multiselect(key="w_compare_runs").options]
    at.multiselect(key="w_compare_metrics").set_value(["R@1", "precision"]).run()
    picked = [o for o in at.multiselect(key="w_compare_runs").value]
    link = dict(at.query_params)
    assert link["eval_compare_metrics"] == "R@1,precision" and link["eval_compare"]
    assert file_ids and picked

    fresh = AppTest.from_file(str(ENTRY), default_timeout=60)
    fresh.query_params.update({k: v for k, v in link.items() if k.startswith("eval_compare")
                               or k == "eval_runs_file"})
    fresh = page(fresh.run(), "evaluation")
    assert_clean(fresh)
    assert {"demo · pixels · paper", "demo · pixels · traversal"} <= set(runs_table(fresh)["name"])
    assert fresh.multiselect(key="w_compare_metrics").value == ["R@1", "precision"]
    from_file = [i for i in link["eval_compare"].split(",") if i in ("run 1", "run 2")]
    assert from_file and set(from_file) <= set(fresh.multiselect(key="w_compare_runs").value)


def test_a_link_to_runs_of_another_session_says_so(app):
    app.query_params.update({"eval_compare": "run 7"})
    at = page(app.run(), "evaluation")
    assert any("run 7 is not among this session's runs" in w.value for w in at.warning)


def test_a_runs_file_outside_the_data_root_or_not_runs_is_an_error(app, bench_json, tmp_path, monkeypatch):
    monkeypatch.setenv(DATA_ROOT_ENV, str(tmp_path))
    at = page(app.run(), "evaluation")
    at.text_input(key="w_runs_file").set_value(str(bench_json)).run()  # a real bench, elsewhere
    assert any("not under the app's data root" in e.value for e in at.error)
    assert not any(f"read from {bench_json.resolve()}" in c.value for c in at.caption)  # nothing of it was read
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    at.text_input(key="w_runs_file").set_value(str(bad)).run()
    assert any("neither a runs export" in e.value for e in at.error)
    assert not at.exception and "eval_runs_file" not in dict(at.query_params)
