"""The failure table (``views.failures``' table, ``ui.failure_table``) and the Evaluation page's θ display, under
AppTest and against the library.

GardensPoint Walking, pixel descriptors, night_right queries against the day_right database,
group 3 step 10 (``tests/test_failures.py``'s value): the page's rows are
``views.failures.find_failures``' classification, which is the plain loop over
``explain_query`` written from the definition (``test_failures.reference_kinds``); the kind
filter and the sorts are checked against sorting the library's rows by hand, the CSV by
reading it back, and selecting a row must open that query in the Query inspector with the
finder on its kind and method. The θ defects need efficientnet-lite0 (its automatic θ lies
above 1 on GardensPoint): one θ on the whole page to three decimals, "accepts no query" the
same in the legend and the tables, and one sentence saying why θ above 1 accepts nothing.

AppTest has no row-selection call for a read-only dataframe: ``select_row`` sends the
selection the browser would send (the table's widget state, Streamlit's selection JSON)
with the page's other widget states, through AppTest's runner (``tests/test_browser_failure_table.py``
clicks the row in Chromium).
"""

from __future__ import annotations

import csv
import io
import json
import math
import re

import numpy as np
import pytest
import streamlit as st
from streamlit.proto.WidgetStates_pb2 import WidgetState
from streamlit.testing.v1 import AppTest

from test_app import assert_clean, downloads, figure, navigation_mode, page, trace  # noqa: F401  (fixtures)
from test_failures import fitted_gp, reference_kinds
from vpr_explorer.app import ENTRY
from vpr_explorer.app.ui import failure_table as ft
from vpr_explorer.data.aligned import database_queries, value_rows
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.auto_theta import runs_auto_parts
from vpr_explorer.method.places import PlaceGeometry, PlaceSpec, make_places
from vpr_explorer.protocols.evaluation import draw_splits
from vpr_explorer.views import failures as vf
from vpr_explorer.views.numbers import FindKind, RetrievalPlaces, explain_query, fit_retrieval

GP_SPEC = PlaceSpec(3, 10)  # the app's default on GardensPoint's 200 frames


@pytest.fixture(autouse=True)
def fresh_caches():
    st.cache_data.clear()
    st.cache_resource.clear()
    yield


@pytest.fixture(scope="module")
def gp0(gardens_point):
    """night_right against day_right, the same frame right: the page's value with eval_database=day_right."""
    return fitted_gp(gardens_point, 0)


@pytest.fixture
def app() -> AppTest:
    return AppTest.from_file(str(ENTRY), default_timeout=180)


def gp_link(app: AppTest, data_root, descriptor: str = "pixels", **params: str) -> AppTest:
    app.query_params.update({"source": str(data_root / "GardensPointWalking"), "descriptor": descriptor,
                             "eval_protocol": "traversal", "eval_database": "day_right",
                             "eval_query": "night_right", **params})
    return page(app.run(), "evaluation")


def table(at: AppTest, prefix: str = "eval_failures"):
    found = [d for d in at.dataframe if d.key and d.key.startswith(f"{prefix}_table_")]
    assert len(found) == 1, [d.key for d in at.dataframe]
    return found[0]


def widget(at: AppTest, key: str):
    return next(w for kind in ("selectbox", "multiselect", "toggle") for w in at.get(kind)
                if getattr(w, "key", None) == key)


def select_row(at: AppTest, frame, row: int) -> AppTest:
    """What the browser sends when a row's box is ticked: the table's selection, with every other widget's state."""
    states = at._tree.get_widget_states()
    kept = [w for w in states.widgets if w.id != frame.proto.id]
    del states.widgets[:]
    states.widgets.extend(kept)
    states.widgets.append(WidgetState(
        id=frame.proto.id, string_value=json.dumps({"selection": {"rows": [row], "columns": [], "cells": []}})))
    return at._run(states)


def library_rows(fitted, desc, key: str, **kwargs) -> list[dict]:
    return vf.table_rows(fitted, vf.find_failures(fitted, desc, key, top=1, queries=vf.failure_queries(fitted),
                                                  **kwargs))


# --------------------------------------------------------------------------- the library's table


def test_explained_queries_are_explain_query_bit_for_bit(gp0):
    fitted, desc = gp0
    for q, d in vf.explained_queries(fitted, desc, np.arange(fitted.dataset.n_queries)):
        e = explain_query(fitted, desc, q)
        assert np.array_equal(d.raw, e.raw) and np.array_equal(d.image_scores, e.image_scores)
        assert np.array_equal(d.true_places, e.true_places)
        for key, o in e.outcomes.items():
            mine = d.outcomes[key]
            assert all(np.array_equal(getattr(o, f), getattr(mine, f))
                       for f in ("rank", "answer_place", "answer_image", "n_kept")), (q, key)


@pytest.mark.parametrize("key", ["margin-weighted", "raw-weighted", "place-baseline", "image-baseline", "global-auto"])
def test_table_rows_are_the_plain_loop(gp0, key):
    fitted, desc = gp0
    want = reference_kinds(fitted, desc, key)
    rows = library_rows(fitted, desc, key)
    assert [(r["query"], r["kind"]) for r in rows] == sorted(want.items())
    for r in rows:
        d = explain_query(fitted, desc, r["query"])
        o = d.outcomes[key]
        assert r["reason"] == vf.describe_answer(fitted, d, key, r["query"])
        if math.isnan(r["θ"]):
            assert key in ("place-baseline", "image-baseline") and math.isnan(r["margin"])
        else:
            assert r["margin"] == pytest.approx(r["score"] - r["θ"], abs=1e-12)
        if o.answer_place[0] >= 0:
            assert r["answer"] == f"place {o.answer_place[0]}"
        else:
            assert r["answer"].startswith("rejected, closest place ")
        true = d.true_places[np.argmax(d.raw[d.true_places])]
        assert r["true place"] == true and r["true rank"] == o.rank[0]


def test_a_sampled_table_counts_the_sample(gp0):
    """Above the pair budget the table decides ``overview_frames``' sample: its rows are the plain loop's on it."""
    fitted, desc = gp0
    budget = 60 * len(fitted.model.images)  # 60 of the 200 queries
    sample = vf.failure_queries(fitted, budget)
    assert len(sample) == 60 and np.all(np.diff(sample) > 0)
    result = vf.find_failures(fitted, desc, "raw-weighted", top=1, queries=sample)
    assert result.sampled and result.decided.tolist() == sample.tolist()
    want = {q: kind for q, kind in reference_kinds(fitted, desc, "raw-weighted").items() if q in set(sample.tolist())}
    assert [(f.query, f.kind.value) for f in result.failures] == sorted(want.items())
    assert "a seeded sample of the 200" in vf.summary_lines(result)[0]
    assert not vf.find_failures(fitted, desc, "raw-weighted", limit=0).sampled


def test_sort_rows_hand_cases():
    rows = [{"query": q, "margin": m, "score": s} for q, m, s in
            [(4, 0.2, 0.5), (1, math.nan, 0.9), (2, -0.1, 0.5), (3, 0.2, 0.1), (0, math.nan, 0.3)]]
    order = lambda rs: [r["query"] for r in rs]  # noqa: E731
    assert order(vf.sort_rows(rows, "margin")) == [2, 3, 4, 0, 1]  # ties by query, empty margins last
    assert order(vf.sort_rows(rows, "margin", descending=True)) == [3, 4, 2, 0, 1]
    assert order(vf.sort_rows(rows, "score")) == [3, 0, 2, 4, 1]
    assert order(vf.sort_rows(rows, "score", descending=True)) == [1, 2, 4, 0, 3]
    assert order(vf.sort_rows(rows, "query", descending=True)) == [4, 3, 2, 1, 0]
    with pytest.raises(VPRInputError, match="sort by 'kind'"):
        vf.sort_rows(rows, "kind")


def test_table_csv_reads_back(gp0):
    fitted, desc = gp0
    rows = library_rows(fitted, desc, "margin-weighted")
    back = list(csv.DictReader(io.StringIO(vf.table_csv(rows))))
    assert tuple(back[0]) == vf.TABLE_COLUMNS and len(back) == len(rows)
    for r, b in zip(rows, back):
        assert int(b["query"]) == r["query"] and b["kind"] == r["kind"] and b["reason"] == r["reason"]
        assert float(b["score"]) == pytest.approx(r["score"], abs=5e-5)
        assert float(b["θ"]) == pytest.approx(r["θ"], abs=5e-5) and b["margin"][0] in "+-"
        assert b["true rank"] == vf.rank_text(r["true rank"])


def test_accepts_nothing_is_said_for_a_theta_above_one(gp0):
    fitted, desc = gp0
    said = vf.accepts_nothing(fitted, "global-user", user_theta=1.25)
    assert said == ("global θ, user value of this database = 1.250 is above 1, the largest similarity two descriptors "
                    "can have, so it accepts no query: every query with a right place is a wrong reject here, "
                    "whatever its scores.")
    result = vf.find_failures(fitted, desc, "global-user", user_theta=1.25, top=1)
    assert {f.kind for f in result.failures} == {vf.FailureKind.WRONG_REJECT}
    assert len(result.failures) == result.n_known
    assert vf.accepts_nothing(fitted, "global-user", user_theta=0.5) is None
    assert vf.accepts_nothing(fitted, "place-baseline") is None
    k = float(np.max((1.01 - fitted.model.theta["weighted"]) / fitted.model.spread))  # every θ_p(k) above 1
    assert "every place's θ of margin, weighted θ" in vf.accepts_nothing(fitted, "margin-weighted", k=k)
    assert vf.accepts_nothing(fitted, "margin-weighted") is None


def test_runs_auto_parts_is_the_protocol_s_theta(gardens_point, gp_pixels):
    """The open set's automatic θ (the trade-off's star) is the mean of the runs' θ, and its median and MAD make it."""
    from vpr_explorer.method.thresholds import AUTO_Z, MAD_PER_SIGMA
    from vpr_explorer.pipeline import run_protocol
    from vpr_explorer.protocols.evaluation import Protocol

    places = make_places(gardens_point, GP_SPEC)
    ev = run_protocol(Protocol.OPEN_SET, gardens_point, places, gp_pixels, runs=3, seed=4, unknown_share=0.3)
    star = next(t for t in ev.tradeoff if t.series == "global θ, automatic")
    splits = draw_splits(places.image_place, places.n_places, runs=3, seed=4, unknown_share=0.3)
    parts = runs_auto_parts(gp_pixels, [sp.train for sp in splits], seed=4)
    assert parts.theta == star.param
    assert parts.theta == pytest.approx(parts.median + AUTO_Z * parts.mad / MAD_PER_SIGMA, abs=1e-12)


# --------------------------------------------------------------------------- the Evaluation page


@pytest.mark.realdata
def test_the_page_s_rows_are_the_library_s(app, data_root, gp0):
    fitted, desc = gp0
    at = gp_link(app, data_root)
    assert_clean(at)
    shown = table(at).value
    want = reference_kinds(fitted, desc, "margin-weighted")
    assert list(zip(shown["query"], shown["kind"])) == sorted(want.items())
    rows = library_rows(fitted, desc, "margin-weighted")
    assert list(shown["reason"]) == [r["reason"] for r in rows]
    np.testing.assert_allclose(shown["margin"], [r["margin"] for r in rows])
    np.testing.assert_allclose(shown["θ"], [r["θ"] for r in rows])
    assert set(shown["method"]) == {"margin, weighted θ"}
    for column in ft.PICTURES:
        assert all(str(u).startswith("data:image/jpeg;base64,") for u in shown[column]), column
    caption = " ".join(c.value for c in at.caption)
    assert "queries night_right (200) against day_right (200 images)" in caption
    assert f"{len(want)} rows. Select a row" in caption and "sample" not in caption
    # another method: its own failures
    widget(at, "eval_failures_method").set_value("raw-weighted").run()
    assert list(zip(table(at).value["query"], table(at).value["kind"])) == sorted(
        reference_kinds(fitted, desc, "raw-weighted").items())


@pytest.mark.realdata
def test_above_the_pair_budget_the_page_says_it_is_a_sample(app, data_root, gp0, monkeypatch):
    from vpr_explorer.views import numbers

    fitted, desc = gp0
    monkeypatch.setattr(numbers, "PAIR_BUDGET", 50 * len(fitted.model.images))  # 50 of the 200 queries
    sample = set(numbers.overview_frames(200, len(fitted.model.images), numbers.PAIR_BUDGET).tolist())
    at = gp_link(app, data_root)
    assert_clean(at)
    shown = table(at).value
    want = {q: kind for q, kind in reference_kinds(fitted, desc, "margin-weighted").items() if q in sample}
    assert list(zip(shown["query"], shown["kind"])) == sorted(want.items())
    caption = " ".join(c.value for c in at.caption)
    assert "A sample: the 50 queries the page decides, seeded, of the 200" in caption
    assert "of the 50 queries decided (a seeded sample of the 200)" in caption


@pytest.mark.realdata
def test_filters_sort_and_csv(app, data_root, gp0, downloads):
    fitted, desc = gp0
    at = gp_link(app, data_root, theta="0.15")  # your own global θ: wrong answers and wrong rejects
    widget(at, "eval_failures_method").set_value("global-user").run()
    rows = library_rows(fitted, desc, "global-user", user_theta=0.15)
    kinds = {r["kind"] for r in rows}
    assert kinds == {"wrong-answer", "wrong-reject"} and {r["θ"] for r in rows} == {0.15}
    widget(at, "eval_failures_kinds").set_value(["wrong-reject"]).run()
    shown = table(at).value
    assert set(shown["kind"]) == {"wrong-reject"}
    assert list(shown["query"]) == [r["query"] for r in rows if r["kind"] == "wrong-reject"]
    assert all(a.startswith("rejected, closest place") for a in shown["answer"])
    widget(at, "eval_failures_kinds").set_value(list(vf.FailureKind)).run()
    widget(at, "eval_failures_sort").set_value("margin").run()
    widget(at, "eval_failures_descending").set_value(True).run()
    want = vf.sort_rows(rows, "margin", descending=True)
    shown = table(at).value
    assert list(shown["query"]) == [r["query"] for r in want]
    assert all(np.diff(shown["margin"]) <= 0)
    served = downloads(next(b for b in at.get("download_button") if b.proto.label == "Download failures (CSV)"))
    assert served.decode() == vf.table_csv(want)
    back = list(csv.DictReader(io.StringIO(served.decode())))
    assert [int(r["query"]) for r in back] == [r["query"] for r in want] and "query picture" not in back[0]
    widget(at, "eval_failures_sort").set_value("score").run()
    widget(at, "eval_failures_descending").set_value(False).run()
    assert list(table(at).value["query"]) == [r["query"] for r in vf.sort_rows(rows, "score")]
    assert all(np.diff(table(at).value["score"]) >= 0)


@pytest.mark.realdata
def test_selecting_a_row_opens_its_query_in_the_inspector(app, data_root, gp0):
    fitted, desc = gp0
    at = gp_link(app, data_root, theta="0.15")
    widget(at, "eval_failures_method").set_value("global-user").run()
    widget(at, "eval_failures_kinds").set_value(["wrong-reject"]).run()
    shown = table(at).value
    assert list(shown["query"]) == sorted(q for q, kind in reference_kinds(fitted, desc, "global-user",
                                                                          user_theta=0.15).items()
                                          if kind == "wrong-reject")
    row = 2
    q = int(shown["query"][row])
    at = select_row(at, table(at), row)
    assert_clean(at)
    assert at.title[0].value == "Query inspector"
    params = dict(at.query_params)
    assert params["frame"] == str(q) and params["query"] == "night_right"
    assert params["inspector_find"] == FindKind.WRONGLY_REJECTED.value and params["inspector_method"] == "global-user"
    assert at.selectbox(key="w_find_kind").value == FindKind.WRONGLY_REJECTED.value
    assert at.selectbox(key="w_find_method").value == "global-user"
    assert at.number_input(key="w_frame_number").value == q


@pytest.mark.realdata
def test_the_inspector_s_failures_section(app, data_root, gardens_point, gp_pixels):
    """The inspector's value (night_right against every other traversal), its k: the same rows; a row opens here."""
    app.query_params.update({"source": str(data_root / "GardensPointWalking"), "descriptor": "pixels", "k": "0.5"})
    at = page(app.run(), "inspector")
    assert not [d for d in at.dataframe if d.key and d.key.startswith("inspector_failures_table_")]  # closed: nothing
    at.session_state[ft.OPEN] = True
    at = at.run()
    assert_clean(at)
    value = database_queries(gardens_point, "night_right")
    rows = value_rows(value)
    desc = gp_pixels if rows is None else gp_pixels[rows]
    fitted = fit_retrieval(desc, value, RetrievalPlaces(PlaceGeometry.FRAMES, GP_SPEC))
    want = reference_kinds_k(fitted, desc, "margin-weighted", 0.5)
    shown = table(at, "inspector_failures").value
    assert list(zip(shown["query"], shown["kind"])) == sorted(want.items())
    q = int(shown["query"][1])
    at = select_row(at, table(at, "inspector_failures"), 1)
    assert_clean(at)
    assert at.title[0].value == "Query inspector" and at.number_input(key="w_frame_number").value == q


def reference_kinds_k(fitted, desc, key: str, k: float) -> dict[int, str]:
    """``test_failures.reference_kinds`` at θ_p(k)."""
    out = {}
    for q in range(fitted.dataset.n_queries):
        d = explain_query(fitted, desc, q, k=k)
        o = d.outcomes[key]
        accepted, known = o.answer_place[0] >= 0, len(d.true_places) > 0
        if known and not accepted:
            out[q] = "wrong-reject"
        elif known and o.rank[0] != 1:
            out[q] = "wrong-answer"
        elif not len(fitted.dataset.ground_truth.positives(q)) and accepted:
            out[q] = "accepted-unknown"
    return out


# --------------------------------------------------------------------------- one θ on the page


def thetas_said(text: str) -> set[str]:
    """Every automatic θ a text gives: "automatic = 1.032", "automatic (θ=1.032", "θ=1.032" …"""
    return set(re.findall(r"automatic[^0-9]{0,40}?(\d\.\d{3})", text))


@pytest.mark.realdata
def test_one_automatic_theta_on_the_open_set_page(app, data_root, gp_effnet):
    at = gp_link(app, data_root, "efficientnet-lite0", eval_protocol="open-set", eval_runs="3")
    assert_clean(at)
    note = next(w.value for w in at.warning if "global θ, automatic" in w.value)
    star = next(t["name"] for t in figure(at, "tradeoff")["data"] if t.get("meta") == "global θ, automatic")
    pr = next(d for d in at.dataframe if "own at" in d.value.columns).value
    own = pr[pr["method"] == "global θ, automatic"].iloc[0]["own at"]
    said = thetas_said(note) | thetas_said(star) | {own.removeprefix("θ=")}
    assert len(said) == 1, (note, star, own)
    theta = float(said.pop())
    assert theta > 1 and "the mean over 3 runs" in star and "accepts no query" in star and "rejects every query" in note
    assert "each of the 3 runs' training images" in note


@pytest.mark.realdata
def test_accepts_nothing_is_the_same_everywhere_and_says_why(app, data_root, gp_effnet):
    """efficientnet-lite0, night_right against day_left: the automatic θ (above 1) accepts no query."""
    at = gp_link(app, data_root, "efficientnet-lite0", eval_database="day_left")
    assert_clean(at)
    results = at.dataframe[0].value
    auto = results[results["method"] == "global θ, automatic"].iloc[0]
    assert auto["accepted"] == 0 and math.isnan(auto["precision"])  # shown '—'
    pr = next(d for d in at.dataframe if "own at" in d.value.columns).value
    own = pr[pr["method"] == "global θ, automatic"].iloc[0]
    assert math.isnan(own["own P"])
    legend = trace(figure(at, "pr"), "own global θ, automatic")["name"]
    assert legend == "global θ, automatic: accepts no query (P —, R 0%)"
    assert all("accepts no query" not in trace(figure(at, "pr"), f"own {m}")["name"]
               for m in pr["method"] if m != "global θ, automatic")
    note = next(w.value for w in at.warning if "global θ, automatic" in w.value)
    # the failure table under the automatic θ: every query with a right place rejected, and one sentence why
    widget(at, "eval_failures_method").set_value("global-auto").run()
    shown = table(at).value
    assert set(shown["kind"]) == {"wrong-reject"} and len(shown) == 60
    why = next(c.value for c in at.caption if "is above 1" in c.value)
    assert why.count(". ") == 0 and why.endswith("whatever its scores.")
    values = {f"{t:.3f}" for t in shown["θ"]}
    said = thetas_said(note) | {own["own at"].removeprefix("θ=")} | values | set(re.findall(r"= (\d\.\d{3})", why))
    assert len(said) == 1 and float(said.pop()) > 1, (note, own["own at"], values, why)
