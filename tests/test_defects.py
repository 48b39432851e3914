"""The walk-through's defects (issue 12 §4) in the library and the figures, each pinned on real data.

- the inspector's candidates always carry every method's answer and the right place(s)
  (Nordland 64x32, winter frame 0: the margin rule answers a place far down the raw_p order);
- one between-place rule (``places.right_places``): the inspector, the Places overview, the
  traversal protocol and a recording agree frame by frame on GardensPoint, with and
  without a tolerance;
- figures that misled: bars cut off above zero, a legend swatch unlike its bars, threshold
  lines drawn on one another, the modebar over a subplot title, an unreadable 358-bar
  overview, a colour bar titled "s";
- labels: images named by traversal and frame, never by database position; missing values
  as "—", never "nan" or "None"; help that defines what a control or number is;
- playback: view titles that fit, named series and a visible legend, a summary without a
  wide table, and a frame that opens in the inspector.

Expectations come from the library's decisions and the dataset directly.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
import streamlit as st
from streamlit.testing.v1 import AppTest

from vpr_explorer.views import plots
from vpr_explorer.app import ENTRY, PAGES as PAGE_FILES
from vpr_explorer.method.database import (
    Verdict,
    between_note,
    decide_traversal,
    describe_query,
    explain_query,
    query_verdict,
)
from vpr_explorer.protocols.options import ProtocolOptions
from vpr_explorer.pipeline import dataset_descriptors, run_protocol
from vpr_explorer.method.places import BETWEEN_PLACES_RULE, PlaceSpec, between_places, right_places
from vpr_explorer.recording import TITLE_CHARS, _summary, frame_verdicts, playback_blueprint
from vpr_explorer.views.traversal import LIVE_METHODS, fit, place_detail, regroup, similarity_grid, top_candidates

GP_SPEC = PlaceSpec(3, 10)  # the app's default on GardensPoint (and Nordland): frame 85 lies between places
DEMO_SPEC = PlaceSpec(3, 5)


@pytest.fixture(scope="module")
def nordland(data_root):
    from vpr_explorer.data.traversals import load_dataset

    ds = load_dataset(data_root / "Nordland_64x32")
    return ds, dataset_descriptors(ds, "pixels")


@pytest.fixture(scope="module")
def gp_fit(gardens_point, gp_pixels):
    return fit(gp_pixels, gardens_point, GP_SPEC)  # database day_left + day_right, queries night_right


def shown_answers(decision) -> set[int]:
    return {decision.answer(k) for k in decision.outcomes if decision.answer(k) >= 0}


# --------------------------------------------------------------------------- 1. the answer is always shown


def test_nordland_winter_frame_0_candidates_carry_the_margin_answer(nordland):
    ds, d = nordland
    f = fit(d, ds, GP_SPEC, "winter")
    dec = explain_query(f.model, d, ds, f.places, ds.image_index("winter", 0), user_theta=0.9)
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
def test_every_gardens_point_query_shows_every_answer_and_right_place(gardens_point, gp_pixels, gp_fit, k):
    ds, f = gardens_point, gp_fit
    for frame in range(ds.n_frames):
        dec = explain_query(f.model, gp_pixels, ds, f.places, ds.image_index(f.query, frame), k=k, tolerance=2)
        cands = set(top_candidates(dec, 3).tolist())
        assert shown_answers(dec) | set(dec.true_places.tolist()) <= cands, frame


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
    ds, f = gardens_point, gp_fit
    assert f.places.frame_place[85] == -1
    dec = explain_query(f.model, gp_pixels, ds, f.places, ds.image_index(f.query, 85))
    for key in dec.outcomes:  # the inspector: neither right nor wrong, and said so
        assert query_verdict(dec, key) is Verdict.BETWEEN
        text = describe_query(dec, key, f.model, ds)
        assert "not scored" in text and "(wrong" not in text and "(right" not in text, text
    assert "not scored" in between_note(85) and "reject it" not in between_note(85)
    r = regroup(gp_pixels, ds, GP_SPEC)  # Places page
    assert not r.scored[list(r.frames).index(85)]
    rec = decide_traversal(f.model, gp_pixels, ds, f.places, f.query)  # playback
    assert {frame_verdicts(rec, k)[85] for k in ("margin-weighted", "place-baseline")} == {Verdict.BETWEEN.value}
    # ... and within a tolerance it belongs to its nearest place, on every page alike
    dec2 = explain_query(f.model, gp_pixels, ds, f.places, ds.image_index(f.query, 88), tolerance=2)
    assert dec2.true_places.tolist() == [9] and query_verdict(dec2, "place-baseline") is not Verdict.BETWEEN


@pytest.mark.parametrize("tolerance", [0, 3])
def test_every_page_scores_the_same_frames_the_same_way(gardens_point, gp_pixels, gp_fit, tolerance):
    ds, f = gardens_point, gp_fit
    q = ds.traversal_index(f.query)
    expected = between_places(right_places(np.arange(ds.n_frames), f.places.frame_place, tolerance))
    assert 0 < expected.sum() < ds.n_frames
    rec = decide_traversal(f.model, gp_pixels, ds, f.places, f.query, tolerance=tolerance)
    ev = run_protocol("traversal", ds, f.places, gp_pixels,
                      ProtocolOptions(database=f.database, queries=f.query, tolerance=tolerance))
    assert ev.settings["queries_between_places"] == int(expected.sum())
    assert ev.settings["queries_scored"] == int((~expected).sum())
    for key in ("margin-weighted", "place-baseline"):
        recorded = frame_verdicts(rec, key)
        assert [v == Verdict.BETWEEN.value for v in recorded] == expected.tolist()
        inspected = [query_verdict(explain_query(f.model, gp_pixels, ds, f.places, ds.image_index(q, fr),
                                                 tolerance=tolerance), key).value for fr in range(ds.n_frames)]
        assert inspected == list(recorded)
        # the protocol's Recall@1 counts exactly the frames the recording and the inspector call right
        row = next(r for r in ev.rows if r.key == key)
        assert row.recall[1][0] == pytest.approx(np.mean([v == Verdict.RIGHT.value for v, b in
                                                          zip(recorded, expected) if not b]))
    if tolerance == 0:
        assert np.array_equal(~regroup(gp_pixels, ds, GP_SPEC).scored, expected)


def test_the_rule_is_stated_once_in_the_readme():
    from pathlib import Path

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    assert readme.count("**Frames between places:**") == 1 and "`places.right_places`" in readme
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


def test_no_bar_is_cut_off_above_zero(demo, demo_pixels, gp_fit, gardens_point, gp_pixels):
    f = gp_fit
    dec = explain_query(f.model, gp_pixels, gardens_point, f.places, gardens_point.image_index(f.query, 31))
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
    r = regroup(demo_pixels, demo, DEMO_SPEC)
    assert not truncated_bars(plots.recall_bars(r.recall1, rejected=r.rejected))


def test_legend_swatches_are_the_colour_of_their_bars(demo, demo_pixels):
    r = regroup(demo_pixels, demo, DEMO_SPEC)
    fig = plots.recall_bars({k: r.recall1[k] for k in LIVE_METHODS}, rejected={k: r.rejected[k] for k in LIVE_METHODS})
    for t in fig.data:
        assert isinstance(t.marker.color, str), f"{t.name}: one colour per bar, the legend shows only the first"
    fig = plots.route_figure(r.places.frame_place, demo.traversals, demo.positions)
    for t in fig.data:
        if t.showlegend is not False and t.mode == "markers":
            assert isinstance(t.marker.color, str), f"{t.name}: its swatch would show only one of its colours"


def test_coincident_thresholds_are_told_apart(gp_fit, gardens_point, gp_pixels):
    f = gp_fit
    d = place_detail(f.model, gp_pixels, gardens_point, f.places, 4, f.query)
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


def test_the_modebar_leaves_the_route_map_title_alone(gardens_point, gp_fit):
    fig = plots.route_figure(gp_fit.places.frame_place, [gp_fit.query], gardens_point.positions)
    assert "route map" in [a.text for a in fig.layout.annotations]
    assert fig.layout.modebar.orientation == "v" and fig.layout.margin.r >= 40


def test_the_nordland_overview_is_readable(nordland):
    ds, d = nordland
    f = fit(d, ds, GP_SPEC, "winter")
    assert f.model.n_places == 358
    fig = plots.places_overview(f.model.theta["weighted"], f.model.positive_mean, f.model.negative_mean, selected=7)
    assert fig.layout.xaxis.type != "category"  # 358 labels cannot be read: ranks, the place in the hover
    theta = next(t for t in fig.data if t.meta == "theta")
    assert theta.type == "scatter" and max(theta.marker.size) <= 10 and len(theta.x) == 358
    assert [t.meta for t in fig.data if t.type == "bar"] == ["pick"]
    assert "358 places" in fig.layout.title.text
    assert all(h.startswith(f"place {p}:") for p, h in zip(theta.customdata, theta.text))


def test_the_similarity_colour_bar_is_named(demo, demo_pixels):
    grid = similarity_grid(demo_pixels, demo, ("day", "night"), "snow", max_side=30)
    title = plots.similarity_heatmap(grid, query="snow", database=("day", "night")).data[0].colorbar.title.text
    assert "similarity" in title and title != "s"


# --------------------------------------------------------------------------- 4. labels


def test_decisions_name_images_by_traversal_and_frame(gardens_point, gp_pixels, gp_fit):
    ds, f = gardens_point, gp_fit
    named = 0
    for frame in (0, 31, 81, 85, 120):
        dec = explain_query(f.model, gp_pixels, ds, f.places, ds.image_index(f.query, frame))
        text = describe_query(dec, "image-baseline", f.model, ds)
        img = int(f.model.images[dec.outcomes["image-baseline"].answer_image[0]])
        want = f"{ds.traversals[ds.image_traversal[img]]} · frame {ds.image_frame[img]} → place "
        assert want in text and not re.search(r"image \d+", text), text
        named += 1
    assert named == 5


def test_missing_values_read_as_a_dash(gp_fit, gardens_point, gp_pixels):
    f = gp_fit
    dec = explain_query(f.model, gp_pixels, gardens_point, f.places, gardens_point.image_index(f.query, 31),
                        user_theta=float("nan"))
    fig = plots.candidate_bars(dec, "global-user", top_candidates(dec))
    labels = list(next(t for t in fig.data if t.meta == "raw_p").text)
    assert labels and set(labels) == {"—"}
    pos = np.array(f.model.positive_mean, dtype=float)
    pos[2] = np.nan  # a place with one database image has no same-place pair
    fig = plots.places_overview(f.model.theta["weighted"], pos, f.model.negative_mean)
    hovers = " ".join(next(t for t in fig.data if t.meta == "theta").text)
    assert "μ⁺ —" in hovers and "nan" not in hovers and "None" not in hovers


# --------------------------------------------------------------------------- 5. playback


def test_playback_views_fit_and_plots_name_their_series(demo, demo_pixels):
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
    from vpr_explorer.method.database import fit_database
    from vpr_explorer.method.places import make_places

    places = make_places(demo, DEMO_SPEC)
    model = fit_database(demo_pixels, demo, places, ["day", "night"])
    dec = decide_traversal(model, demo_pixels, demo, places, "snow")
    summary = _summary(demo, places, model, dec, "snow", "pixels", 0.0)
    assert not any(line.startswith("|") for line in summary.splitlines())  # no wide table to cut
    assert "TextDocumentFormat" in str(views["summary"].properties)  # word-wrapped: nothing cut at the edge
    assert "raw_p" in summary and BETWEEN_PLACES_RULE in summary


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


def test_playback_help_and_a_frame_opens_in_the_inspector(app):
    at = page(app.run(), "playback")
    assert not at.exception
    assert sentence(at.multiselect[0].help) and sentence(at.slider(key="w_playback_k").help)
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
