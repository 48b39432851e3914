"""Defects found walking through the explorer, in the library and the figures, each pinned on real data.

- the inspector's candidates always carry every method's answer and the right place(s)
  (Nordland 64x32, winter frame 0: the margin rule answers a place far down the raw_p order);
- one between-place rule (``places.right_places``): the inspector, the Places overview, the
  traversal protocol and a recording agree query by query on GardensPoint, with and
  without a tolerance;
- figures that misled: bars cut off above zero, a legend swatch unlike its bars, threshold
  lines drawn on one another, the modebar over a subplot title, an unreadable 358-bar
  overview, a colour bar titled "s";
- labels: images named by traversal and frame, never by database position; missing values
  as "—", never "nan" or "None"; help that defines what a control or number is;
- playback: view titles that fit, named series and a visible legend, a summary without a
  wide table, and a query that opens in the inspector.

Aligned traversals are read as their dataset value (``data.aligned.database_queries``: query
``q`` is frame ``q`` of the query traversal). Expectations come from the library's decisions
and the dataset directly.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
import streamlit as st
from streamlit.testing.v1 import AppTest

from vpr_explorer.app import ENTRY, PAGES as PAGE_FILES
from vpr_explorer.data.aligned import database_queries
from vpr_explorer.method.database import Verdict
from vpr_explorer.method.places import (
    BETWEEN_PLACES_RULE,
    PlaceGeometry,
    PlaceSpec,
    between_places,
    frame_places,
    make_places,
    right_places,
)
from vpr_explorer.pipeline import dataset_descriptors, run_protocol
from vpr_explorer.protocols.options import ProtocolOptions
from vpr_explorer.recording import RECORDED, TITLE_CHARS, decide_every_query, playback_blueprint, summary, verdicts
from vpr_explorer.views import plots
from vpr_explorer.views.numbers import (
    BETWEEN,
    KNOWN,
    LIVE_METHODS,
    RetrievalPlaces,
    describe_answer,
    explain_query,
    fit_retrieval,
    overview,
    place_detail,
    similarity_grid,
    top_candidates,
)

GP_SPEC = PlaceSpec(3, 10)  # the app's default on GardensPoint (and Nordland): frame 85 lies between places
DEMO_SPEC = PlaceSpec(3, 5)


def frames_fit(dataset, descriptors, spec: PlaceSpec, tolerance: int = 0):
    """The value of ``dataset`` (database every traversal but the last, queries the last) fitted with group/step
    ``spec``; the descriptors are in the value's order (the last traversal is the query)."""
    value = database_queries(dataset, tolerance=tolerance)
    return fit_retrieval(descriptors, value, RetrievalPlaces(PlaceGeometry.FRAMES, spec=spec))


@pytest.fixture(scope="module")
def nordland(data_root):
    from vpr_explorer.data.traversals import load_dataset

    ds = load_dataset(data_root / "Nordland_64x32")  # summer, winter: winter is the query
    return ds, dataset_descriptors(ds, "pixels")


@pytest.fixture(scope="module")
def gp_fit(gardens_point, gp_pixels):
    return frames_fit(gardens_point, gp_pixels, GP_SPEC)  # database day_left + day_right, queries night_right


@pytest.fixture(scope="module")
def demo_fit(demo, demo_pixels):
    return frames_fit(demo, demo_pixels, DEMO_SPEC)  # database day + night, queries snow


def shown_answers(decision) -> set[int]:
    return {decision.answer(k) for k in decision.outcomes if decision.answer(k) >= 0}


# --------------------------------------------------------------------------- 1. the answer is always shown


def test_nordland_winter_frame_0_candidates_carry_the_margin_answer(nordland):
    ds, d = nordland
    f = frames_fit(ds, d, GP_SPEC)
    assert f.dataset.traversals[f.dataset.query_traversal[0]] == "winter"
    dec = explain_query(f, d, 0, user_theta=0.9)
    top8 = np.argsort(-dec.raw, kind="stable")[:8]
    margin = dec.answer("margin-weighted")
    assert margin not in top8  # the case the walk-through found: the answer is far down the raw_p order
    cands = top_candidates(dec, 8)
    assert shown_answers(dec) | set(dec.true_places.tolist()) <= set(cands.tolist())
    assert set(top8.tolist()) <= set(cands.tolist())
    assert len(set(cands.tolist())) == len(cands)
    assert np.all(np.diff(dec.raw[cands]) <= 0)  # still read as a ranking by raw_p
    for key in LIVE_METHODS:  # the figure outlines exactly one point, the answer
        points = next(t for t in plots.candidate_bars(dec, key, cands).data if t.meta == "raw_p")
        outlined = [int(p) for p, c in zip(points.customdata, points.marker.line.color) if c == "#000"]
        assert outlined == ([dec.answer(key)] if dec.answer(key) >= 0 else [])


@pytest.mark.parametrize("k", [0.0, 1.5])
def test_every_gardens_point_query_shows_every_answer_and_right_place(gardens_point, gp_pixels, k):
    f = frames_fit(gardens_point, gp_pixels, GP_SPEC, tolerance=2)
    for query in range(f.dataset.n_queries):
        dec = explain_query(f, gp_pixels, query, k=k)
        cands = set(top_candidates(dec, 3).tolist())
        assert shown_answers(dec) | set(dec.true_places.tolist()) <= cands, query


# --------------------------------------------------------------------------- 2. one between-place rule


def test_right_places_hand_case():
    frame_place = np.array([0, 0, -1, -1, -1, 1, 1, -1])  # place 0: frames 0-1, place 1: frames 5-6
    frames = np.arange(8)
    t0 = right_places(frames, frame_place, 0)
    assert between_places(t0).tolist() == [False, False, True, True, True, False, False, True]
    t1 = right_places(frames, frame_place, 1)  # within 1 frame of a place's frame: it belongs to it
    assert [np.flatnonzero(r).tolist() for r in t1] == [[0], [0], [0], [], [1], [1], [1], [1]]
    assert between_places(t1).tolist() == [False, False, False, True, False, False, False, False]
    t2 = right_places(frames, frame_place, 2)
    assert t2[3].tolist() == [True, True] and not between_places(t2).any()


def test_frame_85_is_not_scored_on_any_page(gardens_point, gp_pixels, gp_fit):
    f = gp_fit
    assert (f.database_place[f.dataset.database_frame == 85] == -1).all()
    dec = explain_query(f, gp_pixels, 85)
    assert f.query_status(85) == BETWEEN and len(dec.true_places) == 0  # the inspector: unmarked
    for key in dec.outcomes:  # ... neither right nor wrong, and said so; not an unknown place either
        text = describe_answer(f, dec, key, 85)
        assert "not scored" in text and "(wrong" not in text and "(right" not in text, text
        assert "unknown-place" not in text, text
    ov = overview(f, gp_pixels)  # Places page
    assert not ov.sampled and not ov.scored[85]
    rec = decide_every_query(f, gp_pixels)  # playback
    assert {verdicts(rec, k)[85] for k in RECORDED} == {Verdict.BETWEEN.value}
    # ... and within a tolerance it belongs to its nearest place, on every page alike
    f2 = frames_fit(gardens_point, gp_pixels, GP_SPEC, tolerance=2)
    dec2 = explain_query(f2, gp_pixels, 88)
    assert dec2.true_places.tolist() == [9] and f2.query_status(88) == KNOWN
    assert verdicts(decide_every_query(f2, gp_pixels), "place-baseline")[88] != Verdict.BETWEEN.value


def inspector_verdict(fitted, descriptors, query: int, key: str) -> str:
    """What the Query inspector marks a query under one method: not scored between places, else right or wrong."""
    if fitted.query_status(query) == BETWEEN:
        return Verdict.BETWEEN.value
    return Verdict.RIGHT.value if explain_query(fitted, descriptors, query).is_right(key) else "wrong"


@pytest.mark.parametrize("tolerance", [0, 3])
def test_every_page_scores_the_same_frames_the_same_way(gardens_point, gp_pixels, tolerance):
    ds = gardens_point
    f = frames_fit(ds, gp_pixels, GP_SPEC, tolerance=tolerance)
    expected = between_places(right_places(np.arange(ds.n_frames), frame_places(ds.n_frames, GP_SPEC), tolerance))
    assert 0 < expected.sum() < ds.n_frames
    rec = decide_every_query(f, gp_pixels)
    ev = run_protocol("traversal", ds, make_places(ds, GP_SPEC), gp_pixels,
                      ProtocolOptions(database=("day_left", "day_right"), queries="night_right", tolerance=tolerance))
    assert ev.settings["queries_between_places"] == int(expected.sum())
    assert ev.settings["queries_scored"] == int((~expected).sum())
    for key in RECORDED:
        recorded = verdicts(rec, key)
        assert [v == Verdict.BETWEEN.value for v in recorded] == expected.tolist()
        inspected = [inspector_verdict(f, gp_pixels, q, key) for q in range(ds.n_frames)]
        assert inspected == [v if v in (Verdict.BETWEEN.value, Verdict.RIGHT.value) else "wrong" for v in recorded]
        # the protocol's Recall@1 counts exactly the frames the recording and the inspector call right
        row = next(r for r in ev.rows if r.key == key)
        assert row.recall[1][0] == pytest.approx(np.mean([v == Verdict.RIGHT.value for v, b in
                                                          zip(recorded, expected) if not b]))
    if tolerance == 0:
        assert np.array_equal(~overview(f, gp_pixels).scored, expected)


def test_the_rule_is_stated_once_in_the_method_page():
    from pathlib import Path

    method = (Path(__file__).resolve().parents[1] / "docs" / "method.md").read_text()
    assert method.count("**Frames between places.**") == 1 and "`places.right_places`" in method
    assert "left out of scoring" in BETWEEN_PLACES_RULE


# --------------------------------------------------------------------------- 3. charts that mislead


def truncated_bars(fig) -> list[str]:
    """Visible bar traces drawn on a value axis that does not start at (or below) zero."""
    bad = []
    for t in fig.data:
        if t.type != "bar" or t.base is not None:
            continue
        rng = fig.layout.yaxis.range
        if rng is not None and rng[0] > 0:
            bad.append(str(t.meta))
    return bad


def test_no_bar_is_cut_off_above_zero(demo_pixels, demo_fit, gp_fit, gp_pixels):
    f = gp_fit
    dec = explain_query(f, gp_pixels, 31)
    cands = top_candidates(dec)
    for key in LIVE_METHODS:
        fig = plots.candidate_bars(dec, key, cands)
        assert not truncated_bars(fig) and next(t for t in fig.data if t.meta == "raw_p").type == "scatter"
    fig = plots.places_overview(f.model.theta["weighted"], f.model.positive_mean, f.model.negative_mean, selected=3)
    assert not truncated_bars(fig)
    assert next(t for t in fig.data if t.meta == "theta").type == "scatter"
    pick = next(t for t in fig.data if t.meta == "pick")  # click targets: see-through but the selected place
    tints = dict(zip(pick.customdata, pick.marker.color))
    assert tints.pop(3) != "rgba(0,0,0,0)" and set(tints.values()) == {"rgba(0,0,0,0)"}
    ov = overview(demo_fit, demo_pixels)
    assert not truncated_bars(plots.recall_bars(ov.recall1, rejected=ov.rejected))


def test_legend_swatches_are_the_colour_of_their_bars(demo, demo_pixels, demo_fit):
    ov = overview(demo_fit, demo_pixels)
    fig = plots.recall_bars({k: ov.recall1[k] for k in LIVE_METHODS}, rejected={k: ov.rejected[k] for k in LIVE_METHODS})
    for t in fig.data:
        assert isinstance(t.marker.color, str), f"{t.name}: one colour per bar, the legend shows only the first"
    fig = plots.route_figure(frame_places(demo.n_frames, DEMO_SPEC), demo.traversals, demo.positions)
    for t in fig.data:
        if t.showlegend is not False and t.mode == "markers":
            assert isinstance(t.marker.color, str), f"{t.name}: its swatch would show only one of its colours"


def test_coincident_thresholds_are_told_apart(gp_fit, gp_pixels):
    d = place_detail(gp_fit, gp_pixels, 4)
    fig = plots.mixture_figure(d, k=0.0, method="weighted", user_theta=round(d.theta["simple"], 9))
    k_line = next(t for t in fig.data if t.meta == "θ_p(k)")
    assert "= θ_p weighted" in k_line.name  # θ_p(k=0) is θ_p weighted: drawn on it, and named so
    user = next(t for t in fig.data if t.meta == "global θ, user value")
    assert "= θ_p simple" in user.name
    notes = [a.text for a in fig.layout.annotations]
    assert any("θ_p weighted" in n and "θ_p(k)" in n for n in notes), notes
    fig = plots.mixture_figure(d, k=1.0, method="weighted")  # apart: no note
    assert not any("θ_p(k)" in a.text for a in fig.layout.annotations)
    # closer than a pixel (not equal) is said too: ≈
    fig = plots.mixture_figure(d, k=0.0, method="weighted", user_theta=d.theta["weighted"] + 1e-3)
    assert "≈ θ_p weighted" in next(t for t in fig.data if t.meta == "global θ, user value").name


def test_the_modebar_leaves_the_route_map_title_alone(gardens_point):
    fig = plots.route_figure(frame_places(gardens_point.n_frames, GP_SPEC), ["night_right"], gardens_point.positions)
    assert "route map" in [a.text for a in fig.layout.annotations]
    assert fig.layout.modebar.orientation == "v" and fig.layout.margin.r >= 40


def test_the_nordland_overview_is_readable(nordland):
    ds, d = nordland
    f = frames_fit(ds, d, GP_SPEC)
    assert f.n_places == 358
    fig = plots.places_overview(f.model.theta["weighted"], f.model.positive_mean, f.model.negative_mean, selected=7)
    assert fig.layout.xaxis.type != "category"  # 358 labels cannot be read: ranks, the place in the hover
    theta = next(t for t in fig.data if t.meta == "theta")
    assert theta.type == "scatter" and max(theta.marker.size) <= 10 and len(theta.x) == 358
    assert [t.meta for t in fig.data if t.type == "bar"] == ["pick"]
    assert "358 places" in fig.layout.title.text
    assert all(h.startswith(f"P{p}:") for p, h in zip(theta.customdata, theta.text))


def test_the_similarity_colour_bar_is_named(demo_fit, demo_pixels):
    grid = similarity_grid(demo_fit.dataset, demo_pixels, max_side=30)
    title = plots.similarity_heatmap(grid, query="snow", database=("day", "night")).data[0].colorbar.title.text
    assert "similarity" in title and title != "s"


# --------------------------------------------------------------------------- 4. labels


def test_decisions_name_images_by_traversal_and_frame(gp_pixels, gp_fit):
    f = gp_fit
    ds = f.dataset
    named = 0
    for query in (0, 31, 81, 85, 120):
        dec = explain_query(f, gp_pixels, query)
        text = describe_answer(f, dec, "image-baseline", query)
        img = int(f.model.images[dec.outcomes["image-baseline"].answer_image[0]])  # a database position
        want = f"{ds.traversals[ds.database_traversal[img]]} · frame {ds.database_frame[img]} → place "
        assert want in text and not re.search(r"image \d+", text), text
        named += 1
    assert named == 5


def test_missing_values_read_as_a_dash(gp_fit, gp_pixels):
    f = gp_fit
    dec = explain_query(f, gp_pixels, 31, user_theta=float("nan"))
    fig = plots.candidate_bars(dec, "global-user", top_candidates(dec))
    labels = list(next(t for t in fig.data if t.meta == "raw_p").text)
    assert labels and set(labels) == {"—"}
    pos = np.array(f.model.positive_mean, dtype=float)
    pos[2] = np.nan  # a place with one database image has no same-place pair
    fig = plots.places_overview(f.model.theta["weighted"], pos, f.model.negative_mean)
    hovers = " ".join(next(t for t in fig.data if t.meta == "theta").text)
    assert "μ⁺ —" in hovers and "nan" not in hovers and "None" not in hovers


# --------------------------------------------------------------------------- 5. playback


def test_playback_views_fit_and_plots_name_their_series(demo_pixels, demo_fit):
    bp = playback_blueprint("a-rather-long-query-traversal-name-from-a-user", ["day", "night"])
    names, legends, views = [], [], {}

    def walk(node):
        if not hasattr(node, "origin"):  # a container
            for c in node.contents:
                walk(c)
            return
        names.append(str(node.name))
        views[str(node.name)] = node
        if node.class_identifier == "TimeSeries":
            legends.append(node.properties["PlotLegend"])

    walk(bp.root_container)
    assert len(names) == 11 and all(len(n) <= TITLE_CHARS for n in names), names
    assert len(legends) == 3 and all(leg.visible.as_arrow_array().to_pylist() == [True] for leg in legends)
    text = summary(decide_every_query(demo_fit, demo_pixels), "pixels")
    assert not any(line.startswith("|") for line in text.splitlines())  # no wide table to cut
    assert "TextDocumentFormat" in str(views["summary"].properties)  # word-wrapped: nothing cut at the edge
    assert "raw_p" in text and BETWEEN_PLACES_RULE in text


# --------------------------------------------------------------------------- help and the playback link (AppTest)


@pytest.fixture
def app(monkeypatch):
    from streamlit.runtime.pages_manager import PagesManager

    init = PagesManager.__init__

    def init_after_navigation(self, *args, **kwargs):  # as tests/test_app.py: route through st.navigation
        init(self, *args, **kwargs)
        PagesManager.uses_pages_directory = False

    monkeypatch.setattr(PagesManager, "__init__", init_after_navigation)
    st.cache_data.clear()
    st.cache_resource.clear()
    return AppTest.from_file(str(ENTRY), default_timeout=60)


def page(at: AppTest, name: str) -> AppTest:
    return at.switch_page(str(PAGE_FILES / f"{name}.py")).run()


def sentence(text: str | None) -> bool:
    """A help text that defines something: at least one full sentence of some length."""
    return bool(text) and len(text) >= 80 and text.rstrip().endswith((".", ")"))


def test_thresholds_help_defines_each_number(app):
    at = page(app.run(), "thresholds")
    assert not at.exception
    assert len(at.metric) == 4 and all(sentence(m.help) for m in at.metric), [m.help for m in at.metric]
    assert sentence(at.selectbox(key="w_place").help) and sentence(at.radio(key="w_method").help)
    assert "nan" not in " ".join(m.value for m in at.metric)


def test_playback_help_and_a_query_opens_in_the_inspector(app):
    at = page(app.run(), "playback")
    assert not at.exception
    assert sentence(at.slider(key="w_playback_k").help)
    assert sentence(at.button[0].help)
    at.button[0].click().run()
    assert not at.exception
    at.number_input(key="w_playback_frame").set_value(17).run()
    open_ = next(b for b in at.button if b.key == "w_playback_inspect")
    assert "17" in open_.label
    open_.click().run()
    assert not at.exception
    assert at.title[0].value == "Query inspector"
    assert at.session_state["view"].frame == 17
    assert at.session_state["view"].query == at.session_state["playback"].query == "snow"
    assert at.slider(key="w_frame").value == 17
