"""The Evaluation page under AppTest: settings in the URL, results that belong to the controls, precision–recall,
runs side by side, and the page's defects a walk-through found, each reproduced.

The demo route with pixel descriptors keeps each test to a few seconds; the automatic-θ
defect needs efficientnet-lite0 on GardensPoint (``realdata``).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import streamlit as st
from streamlit.testing.v1 import AppTest

from test_app import DEMO_SPEC, assert_clean, downloads, figure, navigation_mode, page, trace  # noqa: F401  (fixtures)
from vpr_explorer.protocols import compare
from vpr_explorer.app import ENTRY
from vpr_explorer.protocols.evaluation import Protocol
from vpr_explorer.data.aligned import database_queries, value_rows
from vpr_explorer.pipeline import evaluate_retrieval, run_protocol
from vpr_explorer.method.places import PlaceSpec, make_places


@pytest.fixture(autouse=True)
def fresh_caches():
    st.cache_data.clear()
    st.cache_resource.clear()
    yield


@pytest.fixture
def app() -> AppTest:
    return AppTest.from_file(str(ENTRY), default_timeout=60)


def subheaders(at: AppTest) -> list[str]:
    return [s.value for s in at.subheader]


def frame(at: AppTest, column: str):
    """The one dataframe with a column named ``column`` (dataframes carry no key in the element tree)."""
    found = [d for d in at.dataframe if column in d.value.columns]
    assert len(found) == 1, f"dataframe with {column!r}: {[list(d.value.columns) for d in at.dataframe]}"
    return found[0]


def run_form(at: AppTest, **values) -> AppTest:
    """Set the form's widgets (by key) and press Run."""
    for key, value in values.items():
        widget = next(w for kind in ("radio", "slider", "multiselect", "selectbox", "number_input", "checkbox")
                      for w in at.get(kind) if getattr(w, "key", None) == key)
        widget.set_value(value)
    at.button[0].click()  # the form's submit button
    return at.run()


# --------------------------------------------------------------------------- settings in the URL


def test_run_writes_every_setting_into_the_url(app):
    at = page(app.run(), "evaluation")
    at = run_form(at, w_protocol="traversal", w_database=["day"], w_eval_query="night", w_tolerance=1)
    assert_clean(at)
    params = dict(at.query_params)
    assert params["eval_protocol"] == "traversal" and params["eval_database"] == "day"
    assert params["eval_query"] == "night" and params["eval_tolerance"] == "1"
    assert {"eval_runs", "eval_seed", "eval_cross", "eval_share", "eval_pr", "eval_rule"} <= set(params)


def test_a_link_restores_the_controls_and_the_results(app, demo, demo_pixels):
    app.query_params.update({"eval_protocol": "open-set", "eval_runs": "3", "eval_seed": "7", "eval_cross": "true",
                             "eval_share": "0.4", "eval_tolerance": "1", "eval_rule": "raw"})
    at = page(app.run(), "evaluation")
    assert_clean(at)
    assert at.radio(key="w_protocol").value == "open-set" and at.slider(key="w_runs").value == 3
    assert at.number_input(key="w_seed").value == 7 and at.checkbox(key="w_cross").value is True
    assert at.slider(key="w_share").value == pytest.approx(0.4) and at.number_input(key="w_tolerance").value == 1
    assert at.radio(key="w_rule").value == "raw"
    ev = run_protocol(Protocol.OPEN_SET, demo, make_places(demo, DEMO_SPEC), demo_pixels, runs=3, seed=7,
                      cross_condition=True, unknown_share=0.4, tolerance=1)
    np.testing.assert_allclose(at.dataframe[0].value["R@1"], [100 * r.recall[1][0] for r in ev.rows])
    rows = [t for t in ev.tradeoff if t.series == "θ_p(k) weighted" and t.rule == "raw"]
    np.testing.assert_allclose(trace(figure(at, "tradeoff"), "θ_p(k) weighted")["y"],
                               [t.known_recall1[0] for t in rows])


@pytest.mark.parametrize("param, value, said", [
    ("eval_protocol", "papers", "eval_protocol='papers': choose paper, traversal, open-set; using the default (paper)"),
    ("eval_runs", "500", "eval_runs='500': outside 1 to 50; using the default (20)"),
    ("eval_seed", "x", "eval_seed='x': not a whole number; using the default (0)"),
    ("eval_cross", "maybe", "eval_cross='maybe': choose true or false; using the default (False)"),
    ("eval_share", "0.9", "eval_share='0.9': outside 0.1 to 0.6; using the default (0.3)"),
    ("eval_database", "dusk", "eval_database='dusk': not a traversal of"),
    ("eval_query", "dusk", "eval_query='dusk': not a traversal of"),
    ("eval_tolerance", "-1", "eval_tolerance='-1': outside 0 to 20; using the default (0)"),
])
def test_a_bad_link_value_is_refused_naming_it_and_what_is_used(app, param, value, said):
    app.query_params[param] = value
    at = page(app.run(), "evaluation")
    assert_clean(at)
    assert any(said in w.value for w in at.warning), [w.value for w in at.warning]
    assert at.dataframe  # the page still runs, on the defaults


def test_leaving_and_coming_back_keeps_the_controls_with_their_results(app, demo, demo_pixels):
    """Traversal → Run → Dataset page → Evaluation shows the traversal protocol above its results, not 'paper'."""
    at = page(app.run(), "evaluation")
    at = run_form(at, w_protocol="traversal", w_database=["day"], w_eval_query="night")
    assert subheaders(at)[0].startswith("traversal")
    at = page(at, "home")
    at.radio(key="w_descriptor").set_value("pixels").run()
    at = page(at, "places")
    at = page(at, "evaluation")
    assert_clean(at)
    assert at.radio(key="w_protocol").value == "traversal"
    assert at.multiselect(key="w_database").value == ["day"] and at.selectbox(key="w_eval_query").value == "night"
    assert subheaders(at)[0].startswith("traversal")
    ev = run_protocol(Protocol.TRAVERSAL, demo, make_places(demo, DEMO_SPEC), demo_pixels, database=["day"],
                      queries="night")
    np.testing.assert_allclose(at.dataframe[0].value["R@1"], [100 * r.recall[1][0] for r in ev.rows])


def test_results_follow_a_changed_view_not_the_old_run(app, demo, demo_pixels):
    at = page(app.run(), "evaluation")
    at = run_form(at, w_protocol="traversal", w_database=["day"], w_eval_query="night")
    at = page(at, "places")
    at.slider(key="w_group").set_value(2).run()
    at = page(at, "evaluation")
    assert_clean(at)
    spec = PlaceSpec(2, DEMO_SPEC.step)
    ev = run_protocol(Protocol.TRAVERSAL, demo, make_places(demo, spec), demo_pixels, database=["day"],
                      queries="night")
    np.testing.assert_allclose(at.dataframe[0].value["R@1"], [100 * r.recall[1][0] for r in ev.rows])


@pytest.mark.parametrize("query, database, tolerance", [("snow", None, 0), ("night", ("day",), 1),
                                                      ("day", ("snow", "night"), 2)])
def test_the_database_queries_table_of_aligned_traversals_is_the_traversal_protocol(demo, demo_pixels, query,
                                                                                    database, tolerance):
    """What the page runs for the traversal protocol (``evaluate_retrieval`` on the value, ``cache.queries_evaluation``)
    is ``pipeline.run_protocol("traversal")``: the same rows and the same precision–recall curves."""
    value = database_queries(demo, query, database, tolerance)
    rows = value_rows(value)
    ev = evaluate_retrieval(value, demo_pixels if rows is None else demo_pixels[rows], spec=DEMO_SPEC, pr=True)
    want = run_protocol(Protocol.TRAVERSAL, demo, make_places(demo, DEMO_SPEC), demo_pixels, queries=query,
                        database=database or tuple(t for t in demo.traversals if t != query), tolerance=tolerance,
                        pr=True)
    assert ev.same_numbers(want) and [r.key for r in ev.rows] == [r.key for r in want.rows]
    assert [(r.key, r.auc, r.max_f1) for r in ev.pr] == [(r.key, r.auc, r.max_f1) for r in want.pr]


def test_the_traversal_table_on_the_page_is_the_traversal_protocol(app, demo, demo_pixels, downloads):
    at = page(app.run(), "evaluation")
    at = run_form(at, w_protocol="traversal", w_database=["night", "day"], w_eval_query="snow", w_tolerance=2,
                  w_pr="on")
    assert_clean(at)
    ev = run_protocol(Protocol.TRAVERSAL, demo, make_places(demo, DEMO_SPEC), demo_pixels, database=["night", "day"],
                      queries="snow", tolerance=2, pr=True)
    table = at.dataframe[0].value
    assert list(table["method"]) == [r.label for r in ev.rows]
    for k in ev.ks:
        np.testing.assert_allclose(table[f"R@{k}"], [100 * r.recall[k][0] for r in ev.rows])
    np.testing.assert_allclose(table["accepted"], [100 * r.accepted[0] for r in ev.rows])
    np.testing.assert_allclose(frame(at, "curve").value["AUC"], [r.auc for r in ev.pr])
    assert any("database: night + day (120 images) · queries: snow (60)" in c.value for c in at.caption)
    served = json.loads(downloads(next(b for b in at.get("download_button") if b.proto.label == "Download JSON")))
    assert served["protocol"] == "traversal" and [m["key"] for m in served["methods"]] == [r.key for r in ev.rows]
    kept = at.session_state["eval_kept_runs"][-1].settings
    assert (kept["protocol"], kept["database"], kept["query"]) == ("traversal", "night+day", "snow")


# --------------------------------------------------------------------------- precision–recall


def test_precision_recall_table_and_curves_are_the_library(app, demo, demo_pixels):
    at = page(app.run(), "evaluation")
    assert_clean(at)
    ev = run_protocol(Protocol.PAPER, demo, make_places(demo, DEMO_SPEC), demo_pixels, runs=20, seed=0, pr=True)
    assert "Precision–recall" in subheaders(at)
    table = frame(at, "curve").value
    assert list(table["method"]) == [r.label for r in ev.pr]
    np.testing.assert_allclose(table["AUC"], [r.auc for r in ev.pr])
    np.testing.assert_allclose(table["R@100P"], [100 * r.r_at_100p for r in ev.pr])
    np.testing.assert_allclose(table["R@99P"], [100 * r.r_at_99p for r in ev.pr])
    np.testing.assert_allclose(table["max F1"], [r.max_f1 for r in ev.pr])
    assert list(table["no true match"]) == [r.n_unknown for r in ev.pr]
    spec = figure(at, "pr")
    for name, curve in ev.pr_curves.items():
        line = trace(spec, name)
        np.testing.assert_allclose(line["x"], curve.recall)
        np.testing.assert_allclose(line["y"], curve.precision)
        assert f"{curve.n_unknown:,} of {curve.n_known + curve.n_unknown:,} queries with no true match" in line["name"]
    own = trace(spec, "own margin, weighted θ")
    row = next(r for r in ev.pr if r.key == "margin-weighted")
    assert (own["x"][0], own["y"][0]) == pytest.approx((row.own.recall, row.own.precision))
    caption = " ".join(c.value for c in at.caption)
    for words in ("**true positive**", "**false positive**", "an accepted query of an **unknown place**"):
        assert words in caption


def test_open_set_curves_count_unknown_queries(app, demo, demo_pixels):
    at = page(app.run(), "evaluation")
    at = run_form(at, w_protocol="open-set", w_runs=3)
    assert_clean(at)
    ev = run_protocol(Protocol.OPEN_SET, demo, make_places(demo, DEMO_SPEC), demo_pixels, runs=3, seed=0, pr=True)
    table = frame(at, "curve").value
    assert list(table["no true match"]) == [r.n_unknown for r in ev.pr] and all(r.n_unknown > 0 for r in ev.pr)
    np.testing.assert_allclose(table["AUC"], [r.auc for r in ev.pr])


# --------------------------------------------------------------------------- defects of the page


def test_nan_cells_show_a_dash_not_none(app):
    """A method that accepts nothing has no precision: the cell reads '—' (it read 'None')."""
    at = page(app.run(), "evaluation")
    at = run_form(at, w_protocol="traversal", w_database=["day"], w_eval_query="night")
    table = at.dataframe[0]
    values = table.value
    assert any(math.isnan(p) for p in values["precision"])  # global θ, automatic accepts nothing here
    assert any("global θ, automatic" in w.value and "accepts no query" in w.value or "rejects every query" in w.value
               for w in at.warning)  # and the page says why, beside the table
    assert table.proto.placeholder == "—"  # Streamlit's default placeholder for a missing value is "None"
    config = json.loads(table.proto.columns)
    shown = [c for c in values.columns if c not in ("method", "source") and not config[c].get("hidden")]
    assert shown and all(config[c]["type_config"]["format"] == "%.1f" for c in shown), config
    assert all(config[f"R@{k} ±"].get("hidden") for k in (1, 3, 5, 10))  # one run: no spread to show
    assert any("unknown place" in c.value or "'—': nothing to count" in c.value for c in at.caption)


def test_one_run_protocol_is_not_titled_mean_over_runs(app):
    at = page(app.run(), "evaluation")
    at = run_form(at, w_protocol="traversal", w_database=["day"], w_eval_query="night")
    spec = figure(at, "recall")
    assert spec["layout"]["title"]["text"] == "Recall@K (one run)"
    assert not trace(spec, "R@1")["error_y"]["visible"]
    at = run_form(at, w_protocol="paper", w_runs=3)
    assert figure(at, "recall")["layout"]["title"]["text"] == "Recall@K (mean ± std over 3 runs)"


def test_the_widest_table_keeps_its_last_column_narrow(app):
    at = page(app.run(), "evaluation")
    at = run_form(at, w_protocol="open-set", w_runs=3)
    table = at.dataframe[0]
    assert table.value.columns[-1] == "top-1 from own traversal"
    config = json.loads(table.proto.columns)
    assert config["top-1 from own traversal"]["label"] == "own trav."
    widths = [config[c]["width"] for c in table.value.columns]
    assert sum(widths) <= 960, widths  # the page's main column at 1440 px: 978 (tests/test_browser_evaluation.py)


@pytest.mark.realdata
def test_an_automatic_theta_above_one_says_why_it_rejects_everything(app, data_root, gardens_point, gp_effnet):
    from vpr_explorer.method.auto_theta import auto_parts

    app.query_params.update({"source": str(data_root / "GardensPointWalking"), "descriptor": "efficientnet-lite0",
                             "eval_protocol": "traversal", "eval_database": "day_left", "eval_query": "night_right"})
    at = page(app.run(), "evaluation")
    assert_clean(at)
    rows = at.dataframe[0].value
    auto = rows[rows["method"] == "global θ, automatic"].iloc[0]
    assert auto["R@1"] == 0 and auto["accepted"] == 0
    places = make_places(gardens_point, PlaceSpec(3, 10))
    db = (gardens_point.image_traversal == gardens_point.traversal_index("day_left")) & (places.image_place >= 0)
    parts = auto_parts(gp_effnet[db], seed=0)
    assert parts.theta > 1
    note = next(w.value for w in at.warning if "global θ, automatic" in w.value)
    assert f"= {parts.theta:.3f}" in note and f"MAD {parts.mad:.3f}" in note and "rejects every query" in note


# --------------------------------------------------------------------------- runs side by side


def test_runs_are_kept_compared_renamed_pinned_and_removed(app, demo, demo_pixels):
    at = page(app.run(), "evaluation")  # run 1: the paper protocol, 20 runs
    at = run_form(at, w_protocol="paper", w_runs=3, w_tolerance=1)  # run 2
    assert_clean(at)
    kept = at.session_state["eval_kept_runs"]
    assert [r.id for r in kept] == ["run 1", "run 2"]
    assert kept[1].settings["tolerance"] == 1 and kept[1].settings["runs"] == 3
    runs_table = frame(at, "pinned").value
    assert list(runs_table.columns[3:5]) == ["runs", "tolerance"]  # what differs comes first
    table = frame(at, "metric").value
    diff = f"Δ {kept[1].name} − {kept[0].name}"
    assert diff in table.columns
    r1 = table[(table["key"] == "margin-weighted") & (table["metric"] == "R@1")].iloc[0]
    ev1 = run_protocol(Protocol.PAPER, demo, make_places(demo, DEMO_SPEC), demo_pixels, runs=20, seed=0)
    ev2 = run_protocol(Protocol.PAPER, demo, make_places(demo, DEMO_SPEC), demo_pixels, runs=3, seed=0, tolerance=1)
    a, b = ev1.row("margin-weighted").recall[1][0], ev2.row("margin-weighted").recall[1][0]
    assert (r1[kept[0].name], r1[kept[1].name]) == pytest.approx((a, b)) and r1[diff] == pytest.approx(b - a)
    spec = figure(at, "compare_pr")
    assert {t.get("meta") for t in spec["data"]} >= {"pr run 1", "pr run 2", "own run 1", "own run 2"}
    # the same settings again: no third run
    at = run_form(at, w_runs=3, w_tolerance=1)
    assert len(at.session_state["eval_kept_runs"]) == 2
    # rename, pin, remove
    at.selectbox(key="w_run_pick").set_value("run 1").run()
    at.text_input(key="w_run_name").set_value("twenty runs")
    at = at.button(key="w_run_rename").click().run()
    assert at.session_state["eval_kept_runs"][0].name == "twenty runs"
    assert "twenty runs" in frame(at, "metric").value.columns
    at = at.button(key="w_run_pin").click().run()
    assert at.session_state["eval_kept_runs"][0].pinned
    at.text_input(key="w_run_name").set_value(kept[1].name)  # taken: refused with a message
    at = at.button(key="w_run_rename").click().run()
    assert any("already called" in e.value for e in at.error)
    at.selectbox(key="w_run_pick").set_value("run 2").run()
    at = at.button(key="w_run_remove").click().run()
    assert [r.id for r in at.session_state["eval_kept_runs"]] == ["run 1"]


def test_open_set_runs_overlay_their_tradeoff_and_exports_carry_settings(app, downloads):
    at = page(app.run(), "evaluation")
    at = run_form(at, w_protocol="open-set", w_runs=3)
    at = run_form(at, w_protocol="open-set", w_runs=3, w_cross=True)
    assert_clean(at)
    kept = at.session_state["eval_kept_runs"]
    assert [r.settings["protocol"] for r in kept] == ["paper", "open-set", "open-set"]
    spec = figure(at, "compare_tradeoff")
    for r in kept[1:]:
        line = trace(spec, f"tradeoff {r.id}")
        want = [t for t in r.evaluation.tradeoff if t.series == "θ_p(k) weighted" and t.rule == "margin"]
        np.testing.assert_allclose(line["x"], [t.unknown_rejection[0] for t in want])
    compared = [r for r in kept if r.id in at.multiselect(key="w_compare_runs").value]
    button = next(b for b in at.get("download_button") if b.proto.label == "Download runs (CSV)")
    assert button.proto.file_name if hasattr(button.proto, "file_name") else True
    rows = compare.read_runs_csv(downloads(button).decode())
    assert {r["run"] for r in rows} == {r.id for r in compared}
    assert {r["cross_condition"] for r in rows} == {"True", "False"}
    assert compare.export_stem(compared).count("cross-vs-nocross") + compare.export_stem(compared).count(
        "nocross-vs-cross") == 1
