"""Every page under Streamlit's AppTest: main interactions, figure numbers against the library, bad input.

Figures are read from the element tree (the Plotly JSON spec Streamlit sends to the
browser) and compared with the library's own values. The demo route with pixel
descriptors keeps most tests to a second or two; ``realdata`` tests use GardensPoint.
"""

from __future__ import annotations

import base64
import csv
import io
import json
from pathlib import Path

import numpy as np
import pytest
import streamlit as st
from PIL import Image
from streamlit.testing.v1 import AppTest

from images import write_noisy_route
from vpr_explorer.app import ENTRY, PAGES as PAGE_FILES
from vpr_explorer.protocols.evaluation import PROTOCOL_LABELS, Protocol
from vpr_explorer.pipeline import evaluate_retrieval, run_protocol
from vpr_explorer.method.places import PlaceSpec, make_places
from vpr_explorer.views.report import method_csv
from vpr_explorer.data.aligned import database_queries, value_rows
from vpr_explorer.method.places import PlaceGeometry
from vpr_explorer.views.numbers import RetrievalPlaces, fit_retrieval, overview, place_detail
from vpr_explorer.views.numbers import database_label, describe_answer, find_query, image_answer
from vpr_explorer.views.numbers import explain_query
from vpr_explorer.views.numbers import top_candidates

ROOT = Path(__file__).resolve().parents[1]

TIMEOUT = 60
PAGES = ("places", "thresholds", "inspector", "evaluation")


# --------------------------------------------------------------------------- helpers


@pytest.fixture(autouse=True)
def fresh_caches():
    """Each test starts with empty Streamlit caches (the on-disk descriptor cache is kept)."""
    st.cache_data.clear()
    st.cache_resource.clear()
    yield


@pytest.fixture(autouse=True)
def navigation_mode(monkeypatch):
    """Route every run through the entry script's ``st.navigation``, as a running server does.

    With a ``pages/`` folder beside the entry script, Streamlit starts in its older multipage
    mode (pages found in the folder, each run on its own) and leaves it for good at the
    first ``st.navigation`` call. AppTest resets that flag before every run, so without
    this each page would run without the entry script (and ``routing`` would send it back).
    """
    from streamlit.runtime.pages_manager import PagesManager

    init = PagesManager.__init__

    def init_after_navigation(self, *args, **kwargs):
        init(self, *args, **kwargs)
        PagesManager.uses_pages_directory = False

    monkeypatch.setattr(PagesManager, "__init__", init_after_navigation)


@pytest.fixture
def downloads(monkeypatch):
    """``downloads(button) -> bytes``: what a download button serves.

    AppTest stores the files in an in-memory media storage made for each run and dropped
    after it; this keeps the latest one so that a button's URL can be read back.
    """
    from streamlit.testing.v1 import app_test

    stores = []

    class Kept(app_test.MemoryMediaFileStorage):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            stores.append(self)

    monkeypatch.setattr(app_test, "MemoryMediaFileStorage", Kept)

    def served(button) -> bytes:
        assert button.proto.url, f"{button.proto.label!r} serves no file (a deferred download?)"
        return stores[-1].get_file(button.proto.url.rsplit("/", 1)[-1]).content

    return served


@pytest.fixture
def app() -> AppTest:
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT)  # the packaged app, as `vpr-explorer app` runs it
    return at


def page(at: AppTest, name: str) -> AppTest:
    return at.switch_page(str(PAGE_FILES / f"{name}.py")).run()  # the packaged page, whichever entry script runs


def assert_clean(at: AppTest, *, errors: bool = False) -> None:
    """No exception box; and no st.error unless ``errors``."""
    assert not at.exception, [e.value for e in at.exception]
    if not errors:
        assert not at.error, [e.value for e in at.error]


def decode(value):
    """Plotly's JSON typed arrays (``{"dtype", "bdata", "shape"}``) back to numpy; lists as arrays."""
    if isinstance(value, dict) and "bdata" in value:
        array = np.frombuffer(base64.b64decode(value["bdata"]), dtype=np.dtype(value["dtype"]))
        if "shape" in value:
            array = array.reshape([int(s) for s in str(value["shape"]).split(",")])
        return array
    return np.asarray(value) if isinstance(value, list) else value


def figure(at: AppTest, key: str) -> dict:
    """The Plotly spec of the chart with widget/element key ``key``."""
    charts = [c for c in at.get("plotly_chart") if c.proto.id.endswith(f"-{key}")]
    assert len(charts) == 1, f"chart {key!r}: found {[c.proto.id for c in at.get('plotly_chart')]}"
    return json.loads(charts[0].proto.spec)


def trace(spec: dict, meta: str) -> dict:
    found = [t for t in spec["data"] if t.get("meta") == meta]
    assert len(found) == 1, f"{meta!r} in {[t.get('meta') for t in spec['data']]}"
    return {k: decode(v) for k, v in found[0].items()}


def metric(at: AppTest, label: str) -> str:
    return next(m.value for m in at.metric if m.label == label)


DEMO_SPEC = PlaceSpec(3, 5)  # the app's default on a 60-frame route


# --------------------------------------------------------------------------- landing and every page


def test_fresh_user_lands_on_the_demo_route(app):
    at = app.run()
    assert_clean(at)
    assert at.selectbox(key="w_source").value == "demo"
    assert at.radio(key="w_descriptor").value == "pixels"
    assert any("descriptors ready: 180 × 2048" in s.value for s in at.success)
    assert len(at.image) == 3 * 8  # a strip of 8 thumbnails per traversal
    assert at.query_params == {}  # the default view needs no parameters


@pytest.mark.parametrize("name", PAGES)
def test_every_page_runs_on_the_demo(app, name):
    at = page(app.run(), name)
    assert_clean(at)
    assert at.get("plotly_chart"), f"{name} shows no figure"
    assert at.title[0].value


def test_every_page_again_after_visiting_all(app):
    at = app.run()
    for name in (*PAGES, "home", *reversed(PAGES)):
        page(at, name)
        assert_clean(at)


def test_a_broken_models_settings_file_is_an_error_not_a_crash(app, tmp_path, monkeypatch):
    bad = tmp_path / "models.toml"
    bad.write_text("[models.mine\nfile = ")  # not TOML
    monkeypatch.setenv("VPR_EXPLORER_MODELS", str(bad))
    at = app.run()
    assert_clean(at, errors=True)
    assert any("models.toml" in e.value for e in at.error)
    assert at.radio(key="w_descriptor").value == "pixels"  # the built-ins still work


@pytest.mark.parametrize("layout", ["demo", pytest.param("database-queries", marks=pytest.mark.realdata)])
def test_playback_page_records_every_query_as_the_library_decides(app, layout, request, tmp_path):
    """The demo route (aligned traversals: snow's frames against day and night) and GardensPoint as a
    database/queries layout: the page's counts are the inspector's decisions of every query."""
    from collections import Counter

    from vpr_explorer.method.database import Verdict
    from vpr_explorer.method.retrieval import METHODS_BY_KEY
    from vpr_explorer.pipeline import dataset_descriptors, open_dataset, resolve_dataset
    from vpr_explorer.views.numbers import BETWEEN, UNKNOWN

    if layout == "demo":
        dataset = resolve_dataset("demo")
        value = database_queries(dataset, "snow")
        d, rows = dataset_descriptors(dataset, "pixels"), value_rows(value)
        d = d if rows is None else d[rows]
    else:
        from vpr_explorer.data.example_layouts import write_gardens_point_layouts

        path = write_gardens_point_layouts(request.getfixturevalue("data_root") / "GardensPointWalking",
                                           tmp_path)[layout]
        app.query_params.update(source=str(path), descriptor="pixels")
        value = open_dataset(path)
        d = dataset_descriptors(value, "pixels")
    at = page(app.run(), "playback")
    assert_clean(at)
    assert at.title[0].value == "Playback"
    at.button[0].click().run()
    assert_clean(at)
    assert at.get("component_instance"), "no viewer embedded after recording"  # app/ui/rerun_viewer.py
    assert at.get("download_button"), "no .rrd download offered"
    playback = at.session_state["playback"]
    assert playback.n_queries == value.n_queries
    fitted = fit_retrieval(d, value, playback.decisions.fitted.places)
    counts = {key: Counter() for key in ("margin-weighted", "place-baseline")}
    for q in range(value.n_queries):
        dec, status = explain_query(fitted, d, q), fitted.query_status(q)
        for key, c in counts.items():
            o = dec.outcomes[key]
            c[Verdict.BETWEEN if status == BETWEEN else
              (Verdict.WRONG_ACCEPT if o.accepted[0] else Verdict.RIGHT) if status == UNKNOWN else
              Verdict.RIGHT if o.right[0] else Verdict.WRONG_ACCEPT if o.accepted[0] else Verdict.WRONG_REJECT] += 1
    table = next(m.value for m in at.markdown if m.value.startswith("| method |"))
    for key, c in counts.items():
        assert (f"| {METHODS_BY_KEY[key].label} | {c[Verdict.RIGHT]} | {c[Verdict.WRONG_ACCEPT]} | "
                f"{c[Verdict.WRONG_REJECT]} | {c[Verdict.BETWEEN]} |") in table
    at.number_input(key="w_playback_frame").set_value(17).run()
    opened = at.button(key="w_playback_inspect")
    assert "17 in the Query inspector" in opened.label
    opened.click().run()
    assert at.title[0].value == "Query inspector" and at.session_state["view"].frame == 17


# --------------------------------------------------------------------------- places


def fitted_value(dataset, descriptors, spec: PlaceSpec, query: str | None = None):
    """Aligned traversals as the app reads them (``aligned.database_queries``, descriptors in the value's order),
    fitted with group/step ``spec`` in frames: ``(fitted, descriptors)``."""
    value = database_queries(dataset, query)
    rows = value_rows(value)
    d = descriptors if rows is None else descriptors[rows]
    return fit_retrieval(d, value, RetrievalPlaces(PlaceGeometry.FRAMES, spec=spec)), d


def test_places_live_numbers_are_the_library_overview(app, demo, demo_pixels):
    at = page(app.run(), "places")
    f, d = fitted_value(demo, demo_pixels, DEMO_SPEC)
    ov = overview(f, d)
    assert metric(at, "places") == str(f.n_places) == "12"
    assert metric(at, "database images per place") == "6"  # 3 frames × the 2 database traversals
    assert metric(at, "place-level R@1") == f"{ov.recall1['place-baseline']:.0%}"
    assert metric(at, "margin, weighted θ R@1") == f"{ov.recall1['margin-weighted']:.0%}"
    assert metric(at, "raw, weighted θ R@1") == f"{ov.recall1['raw-weighted']:.0%}"
    assert "unknown rejected" not in [m.label for m in at.metric]  # every query has a right database image
    hist = figure(at, "theta_hist")
    np.testing.assert_allclose(trace(hist, "θ_p weighted")["x"], f.model.theta["weighted"])
    assert trace(hist, "global θ, automatic")["x"][0] == pytest.approx(f.model.auto)
    bars = trace(figure(at, "recall_live"), "recall1")
    np.testing.assert_allclose(bars["y"], [ov.recall1[k] for k in bars["customdata"]])
    stride = figure(at, "route_stride")
    np.testing.assert_array_equal(trace(stride, "places snow")["x"],
                                  np.flatnonzero(f.database_place[:demo.n_frames] >= 0))
    spec = figure(at, "layout_map")  # the demo has positions: the database frames by place, the query frames
    assert list(trace(spec, "database places")["text"]) == [f"P{p}" for p in f.database_place[f.database_place >= 0]]
    assert len(trace(spec, "queries")["x"]) == demo.n_frames


def test_places_query_traversal_changes_the_numbers(app, demo, demo_pixels):
    at = page(app.run(), "places")
    at.selectbox(key="w_query").set_value("day").run()  # database: night + snow
    assert_clean(at)
    assert at.query_params["query"] == "day"
    f, d = fitted_value(demo, demo_pixels, DEMO_SPEC, "day")
    ov = overview(f, d)
    snow, snow_d = fitted_value(demo, demo_pixels, DEMO_SPEC)
    assert f.model.theta["weighted"] != pytest.approx(snow.model.theta["weighted"])
    assert ov.recall1 != overview(snow, snow_d).recall1
    assert metric(at, "place-level R@1") == f"{ov.recall1['place-baseline']:.0%}"
    assert metric(at, "margin, weighted θ R@1") == f"{ov.recall1['margin-weighted']:.0%}"
    np.testing.assert_allclose(trace(figure(at, "theta_hist"), "θ_p weighted")["x"], f.model.theta["weighted"])
    bars = trace(figure(at, "recall_live"), "recall1")
    np.testing.assert_allclose(bars["y"], [ov.recall1[k] for k in bars["customdata"]])


def test_places_slider_moves_recompute_and_go_into_the_url(app, demo, demo_pixels):
    at = page(app.run(), "places")
    at.slider(key="w_group").set_value(2).run()
    at.slider(key="w_step").set_value(4).run()
    assert_clean(at)
    f, _ = fitted_value(demo, demo_pixels, PlaceSpec(2, 4))
    assert metric(at, "places") == str(f.n_places) == "15"
    assert metric(at, "database images per place") == "4"
    np.testing.assert_allclose(trace(figure(at, "theta_hist"), "θ_p simple")["x"], f.model.theta["simple"])
    assert at.query_params["group"] == "2" and at.query_params["step"] == "4"
    at.radio(key="w_reading").set_value("skip").run()
    assert_clean(at)
    skip = make_places(demo, PlaceSpec(2, 4, "skip"))
    assert metric(at, "places") == str(skip.n_places)
    assert at.query_params["reading"] == "skip"


def test_slider_moves_never_re_extract(app, monkeypatch):
    """Descriptors are per image: a group/step move relabels images and refits the statistics only."""
    from vpr_explorer.app.ui import cache

    calls = []
    extract = cache.dataset_descriptors
    monkeypatch.setattr(cache, "dataset_descriptors", lambda *a, **k: calls.append(a) or extract(*a, **k))
    at = page(app.run(), "places")
    assert len(calls) == 1
    for group, step in ((2, 4), (4, 6), (1, 1), (3, 5)):
        at.slider(key="w_group").set_value(group).run()
        at.slider(key="w_step").set_value(step).run()
        assert_clean(at)
    page(at, "thresholds")
    page(at, "inspector")
    assert len(calls) == 1


def test_places_too_few_places_shows_an_error_and_keeps_the_last_good_value(app):
    at = page(app.run(), "places")
    at.slider(key="w_step").set_value(59).run()  # group 3, step 59 on 60 frames: one place
    assert_clean(at, errors=True)
    assert any("at least 2 places" in e.value and "lower group or step" in e.value for e in at.error)
    assert at.slider(key="w_step").value == 5 and metric(at, "places") == "12"
    at.slider(key="w_step").set_value(10).run()  # still usable
    assert_clean(at)
    assert metric(at, "places") == "6"


def test_places_stride_overlap_is_refused_with_the_fix(app):
    at = page(app.run(), "places")
    at.slider(key="w_group").set_value(8).run()  # step 5 < group 8 in the stride reading
    assert_clean(at, errors=True)
    assert any("places would overlap" in e.value for e in at.error)
    assert at.slider(key="w_group").value == 3


# --------------------------------------------------------------------------- thresholds


def test_thresholds_figure_lines_are_the_computed_thresholds(app, demo, demo_pixels):
    at = page(app.run(), "thresholds")
    f, d = fitted_value(demo, demo_pixels, DEMO_SPEC)
    p = at.selectbox(key="w_place").value
    spec = figure(at, "mixture")
    assert trace(spec, "θ_p weighted")["x"][0] == pytest.approx(f.model.theta["weighted"][p])
    assert trace(spec, "θ_p simple")["x"][0] == pytest.approx(f.model.theta["simple"][p])
    assert trace(spec, "global θ, automatic")["x"][0] == pytest.approx(f.model.auto)
    detail = place_detail(f, d, p)
    mix = trace(spec, "mixture")
    from vpr_explorer.method.stats import mixture_pdf

    np.testing.assert_allclose(mix["y"], mixture_pdf(mix["x"], detail.mu, detail.sigma, detail.weight))
    raw = trace(spec, "query_raw")  # the place's query frames (snow) and their raw_p
    np.testing.assert_array_equal(raw["customdata"], detail.query_images)
    np.testing.assert_allclose(raw["x"], detail.query_raw)
    first = 5 * p  # place p of group 3, step 5 holds frames 5p .. 5p + 2
    np.testing.assert_array_equal(detail.query_images - f.dataset.n_database, first + np.arange(3))
    overview = trace(figure(at, "overview"), "theta")
    np.testing.assert_allclose(overview["y"], np.sort(f.model.theta["weighted"]))
    assert any("normalised" in i.value for i in at.info)
    captions = [img.caption for element in at.image for img in element.proto.imgs]
    assert captions[:3] == [f"day · frame {first + i} (database)" for i in range(3)]
    assert captions[-3:] == [f"snow · frame {first + i} (query, raw_p {r:.3f})" for i, r in
                             enumerate(detail.query_raw)]
    dropped = detail.share_queries_below(detail.theta["weighted"])
    assert metric(at, "own queries dropped at θ_p(k=0)") == f"{dropped:.0%}"


def test_thresholds_place_k_and_user_theta_move_the_lines(app, demo, demo_pixels):
    at = page(app.run(), "thresholds")
    at.selectbox(key="w_place").set_value(7).run()
    at.slider(key="w_k").set_value(1.5).run()
    at.checkbox(key="w_user_on").check().run()
    at.number_input(key="w_user_theta").set_value(0.42).run()
    assert_clean(at)
    f, _ = fitted_value(demo, demo_pixels, DEMO_SPEC)
    spec = figure(at, "mixture")
    assert spec["layout"]["title"]["text"].startswith("P7: ")
    assert trace(spec, "θ_p(k)")["x"][0] == pytest.approx(f.model.thresholds(1.5)["weighted"][7])
    assert trace(spec, "global θ, user value")["x"][0] == pytest.approx(0.42)
    assert at.query_params["place"] == "7" and at.query_params["k"] == "1.5"
    at.radio(key="w_method").set_value("simple").run()
    assert trace(figure(at, "mixture"), "θ_p(k)")["x"][0] == pytest.approx(f.model.thresholds(1.5)["simple"][7])


# --------------------------------------------------------------------------- query inspector


def test_inspector_bars_are_raw_p_with_thresholds_and_the_answer_in_words(app, demo, demo_pixels):
    at = page(app.run(), "inspector")
    at.slider(key="w_frame").set_value(31).run()
    assert_clean(at)
    f, d = fitted_value(demo, demo_pixels, DEMO_SPEC)
    dec = explain_query(f, d, 31)  # query 31 of the value: snow frame 31
    cands = top_candidates(dec, 8)
    for key, threshold in (("place-baseline", None), ("margin-weighted", "weighted"), ("raw-simple", "simple"),
                           ("global-auto", "auto")):
        spec = figure(at, f"bars_{key}")
        bars = trace(spec, "raw_p")
        np.testing.assert_array_equal(bars["customdata"], cands)
        np.testing.assert_allclose(bars["y"], dec.raw[cands])
        if threshold:
            np.testing.assert_allclose(trace(spec, "theta")["y"], dec.thresholds[threshold][cands])
        assert describe_answer(f, dec, key, 31) == dec.describe(key)  # a query with a right place
        assert any(c.value == dec.describe(key) for c in at.caption), key
    assert at.query_params["frame"] == "31"
    text = " ".join(md.value for md in at.markdown)
    assert "**Right place(s):** P6" in text  # place 6 of group 3, step 5 holds frames 30-32
    answer = image_answer(f.dataset, d, 31)
    assert f"its most similar database image is {database_label(f.dataset, answer.image)}" in text


def test_inspector_jumps_to_a_rejected_query(app, demo, demo_pixels):
    at = page(app.run(), "inspector")
    at.selectbox(key="w_find_method").set_value("global-auto").run()
    at.button(key="w_find_next").click().run()
    assert_clean(at)
    frame = at.slider(key="w_frame").value
    f, d = fitted_value(demo, demo_pixels, DEMO_SPEC)
    found, _ = find_query(f, d, after=0, kind="rejected", method="global-auto")
    assert frame == found == at.number_input(key="w_frame_number").value
    dec = explain_query(f, d, frame)
    assert dec.answer("global-auto") == -1
    said = describe_answer(f, dec, "global-auto", frame)
    assert said.startswith("rejected") and any(c.value == said for c in at.caption)


def test_inspector_jump_with_none_found_says_so(app):
    at = page(app.run(), "inspector")
    at.selectbox(key="w_find_method").set_value("place-baseline").run()  # never rejects
    frame = at.slider(key="w_frame").value
    at.button(key="w_find_next").click().run()
    assert_clean(at)
    assert at.slider(key="w_frame").value == frame
    assert any("no query was rejected" in i.value for i in at.info)


def test_inspector_opens_a_pair_picked_in_the_similarity_matrix(app, demo):
    """What a heatmap click does (see ``pages/evaluation.py``'s callback): the pair opens in the inspector."""
    value = database_queries(demo)  # database: day then night; queries: snow
    night = value.database_traversal == demo.traversal_index("night")
    db = int(np.flatnonzero(night & (value.database_frame == 13))[0])
    at = app.run()
    at.session_state["picked_pair"] = (12, db)
    at.session_state["view"] = at.session_state["view"].__class__(frame=12)
    page(at, "inspector")
    assert_clean(at)
    assert at.slider(key="w_frame").value == 12
    assert any("Opened from the similarity matrix" in c.value and "night · frame 13" in c.value for c in at.caption)


def test_inspector_query_traversal_and_file_name_pick_the_query(app, demo, demo_pixels):
    at = page(app.run(), "inspector")
    at.selectbox(key="w_query").set_value("night").run()  # database: day + snow
    at.text_input(key="w_query_name").input(demo.paths[demo.traversal_index("night")][17].name).run()
    assert_clean(at)
    assert at.query_params["query"] == "night" and at.slider(key="w_frame").value == 17
    f, d = fitted_value(demo, demo_pixels, DEMO_SPEC, "night")
    dec = explain_query(f, d, 17)
    np.testing.assert_allclose(trace(figure(at, "bars_margin-weighted"), "raw_p")["y"], dec.raw[top_candidates(dec, 8)])
    assert any(c.value == describe_answer(f, dec, "raw-weighted", 17) for c in at.caption)


# --------------------------------------------------------------------------- evaluation


def test_evaluation_paper_protocol_table_equals_the_library(app, demo, demo_pixels, downloads):
    at = page(app.run(), "evaluation")
    assert_clean(at)
    ev = run_protocol(Protocol.PAPER, demo, make_places(demo, DEMO_SPEC), demo_pixels, runs=20, seed=0)
    table = at.dataframe[0].value
    np.testing.assert_allclose(table["R@1"], [100 * r.recall[1][0] for r in ev.rows])
    np.testing.assert_allclose(table["R@5 ±"], [100 * r.recall[5][1] for r in ev.rows])
    spec = figure(at, "recall")
    np.testing.assert_allclose(trace(spec, "R@1")["y"], [r.recall[1][0] for r in ev.rows])
    np.testing.assert_allclose(trace(spec, "R@3")["error_y"]["array"], [r.recall[3][1] for r in ev.rows])
    assert "top-1 from own traversal" in table.columns
    # The CSV the button serves: the fixed columns, one row per method in the table's order, the table's numbers.
    button = next(b for b in at.get("download_button") if b.proto.label == "Download CSV")
    served = downloads(button).decode()
    assert served == method_csv(ev)
    rows = list(csv.DictReader(io.StringIO(served)))
    assert list(rows[0]) == ["protocol", "method", "label", "R@1 mean", "R@1 std", "R@3 mean", "R@3 std", "R@5 mean",
                             "R@5 std", "R@10 mean", "R@10 std", "accepted", "precision", "unknown_rejection",
                             "own_traversal_top1"]
    assert [r["method"] for r in rows] == [r.key for r in ev.rows] and len(rows) == 8
    assert [r["label"] for r in rows] == list(table["method"]) and {r["protocol"] for r in rows} == {"paper"}
    for column, shown in [("R@1 mean", "R@1"), ("R@5 std", "R@5 ±"), ("R@10 mean", "R@10"), ("accepted", "accepted"),
                          ("precision", "precision"), ("own_traversal_top1", "top-1 from own traversal")]:
        np.testing.assert_allclose([100 * float(r[column]) for r in rows], table[shown], err_msg=column)
    assert all(r["unknown_rejection"] == "" for r in rows)  # a closed-set protocol has no unknown places


def test_evaluation_open_set_and_traversal_protocols(app, demo, demo_pixels):
    at = page(app.run(), "evaluation")
    at.radio(key="w_protocol").set_value("open-set")
    at.slider(key="w_runs").set_value(3)
    at.button[0].click()  # the form's submit button
    at = at.run()
    assert_clean(at)
    ev = run_protocol(Protocol.OPEN_SET, demo, make_places(demo, DEMO_SPEC), demo_pixels, runs=3, seed=0,
                      unknown_share=0.3)
    spec = figure(at, "tradeoff")
    rows = [t for t in ev.tradeoff if t.series == "θ_p(k) weighted" and t.rule == "margin"]
    np.testing.assert_allclose(trace(spec, "θ_p(k) weighted")["y"], [t.known_recall1[0] for t in rows])
    k0 = next(t for t in rows if t.param == 0)
    assert trace(spec, "k0 θ_p(k) weighted")["x"][0] == pytest.approx(k0.unknown_rejection[0])
    assert "unknown rejected" in at.dataframe[0].value.columns
    at.radio(key="w_protocol").set_value("traversal")
    at.multiselect(key="w_database").set_value(["day"])
    at.selectbox(key="w_eval_query").set_value("night")
    at.number_input(key="w_tolerance").set_value(1)
    at.button[0].click()
    at = at.run()
    assert_clean(at)
    ev = evaluated_value(demo, demo_pixels, DEMO_SPEC, "night", ["day"], 1)  # the database/queries protocol
    table = at.dataframe[0].value
    assert list(table["method"]) == [r.label for r in ev.rows]
    for k in ev.ks:
        np.testing.assert_allclose(table[f"R@{k}"], [100 * r.recall[k][0] for r in ev.rows])
    np.testing.assert_allclose(table["precision"], [100 * r.precision[0] for r in ev.rows])
    caption = " ".join(c.value for c in at.caption)
    assert "database: day (60 images) · queries: night (60)" in caption
    assert "ground truth: within ±1 frames" in caption
    assert at.subheader[0].value.startswith("traversal: a database traversal against a query traversal")


def evaluated_value(dataset, descriptors, spec, query=None, database=None, tolerance=0, **options):
    """The database/queries protocol on aligned traversals' value (``aligned.database_queries``), as the
    Evaluation page's traversal protocol runs it."""
    value = database_queries(dataset, query, database, tolerance)
    rows = value_rows(value)
    return evaluate_retrieval(value, descriptors if rows is None else descriptors[rows], spec=spec, **options)


def test_evaluation_bad_protocol_setting_shows_an_error(app):
    at = page(app.run(), "evaluation")
    at.radio(key="w_protocol").set_value("traversal")
    at.multiselect(key="w_database").set_value(["day", "snow"])
    at.selectbox(key="w_eval_query").set_value("snow")  # query traversal also in the database
    at.button[0].click()
    at = at.run()
    assert_clean(at, errors=True)
    assert any("traversal 'snow' is both the query and in the database" in e.value for e in at.error)
    assert at.get("plotly_chart")  # the similarity matrix below still shows


def test_evaluation_similarity_matrix_is_the_library_grid(app, demo, demo_pixels):
    from vpr_explorer.views.numbers import similarity_grid

    at = page(app.run(), "evaluation")
    value = database_queries(demo)
    assert value_rows(value) is None  # snow, the last traversal, queries: the traversals' own order
    d = demo_pixels
    grid = similarity_grid(value, d)  # 60 snow queries × 120 database images (day, then night)
    assert grid.z.shape == (60, 120) and not grid.sampled
    np.testing.assert_allclose(grid.z, d[120:] @ d[:120].T, rtol=1e-5)
    spec = figure(at, "simgrid")
    np.testing.assert_allclose(trace(spec, "similarity")["z"], grid.z, rtol=1e-6)
    pairs = trace(spec, "cells")["customdata"]
    np.testing.assert_array_equal(pairs[:, 0], grid.query_image.ravel())
    np.testing.assert_array_equal(pairs[:, 1], grid.db_image.ravel())
    assert "60 queries (snow) × 120 database images" in spec["layout"]["title"]["text"]


# --------------------------------------------------------------------------- big datasets
#
# The budgets that make a 110k-image dataset interactive (benchmarks/bench_app_scale.py)
# lowered so that the demo's 60 frames cross them.


def test_places_over_the_pair_budget_decides_a_sample_and_says_so(app, demo, demo_pixels, monkeypatch):
    from vpr_explorer.views import numbers as views

    monkeypatch.setattr(views, "PAIR_BUDGET", 1000)
    at = page(app.run(), "places")
    assert_clean(at)
    ov = overview(*fitted_value(demo, demo_pixels, DEMO_SPEC), pair_budget=1000)
    assert ov.sampled
    assert any(f"seeded random sample of **{len(ov.queries)} of the 60 queries**" in c.value for c in at.caption)
    assert metric(at, "place-level R@1") == f"{ov.recall1['place-baseline']:.0%}"
    bars = trace(figure(at, "recall_live"), "recall1")
    np.testing.assert_allclose(bars["y"], [ov.recall1[k] for k in bars["customdata"]])


def test_inspector_search_over_the_budget_moves_on_and_says_to_press_again(app, monkeypatch):
    from vpr_explorer.views import numbers as views

    at = page(app.run(), "inspector")
    at.selectbox(key="w_find_method").set_value("place-baseline").run()  # never rejects: searches everything
    frame = at.slider(key="w_frame").value
    n_db = 12 * 3 * 2  # 12 places x 3 frames x 2 database traversals
    monkeypatch.setattr(views, "PAIR_BUDGET", 5 * n_db)  # five queries per press
    at.button(key="w_find_next").click().run()
    assert_clean(at)
    assert at.slider(key="w_frame").value == frame + 5
    assert any("press next again to search on" in i.value for i in at.info)


def test_evaluation_over_the_auto_run_size_waits_for_run(app, demo, demo_pixels, monkeypatch):
    from vpr_explorer.views import numbers as views

    monkeypatch.setattr(views, "AUTO_RUN_PAIRS", 100)
    monkeypatch.setattr(views, "PAIR_BUDGET", 1000)
    at = page(app.run(), "evaluation")
    assert_clean(at)
    assert any("does not start by itself" in i.value for i in at.info)
    assert not at.dataframe  # nothing ran
    assert any("each row is one query (the centre of its block" in c.value for c in at.caption)
    value = database_queries(demo)
    grid = views.similarity_grid(value, demo_pixels)  # snow queries: the traversals' own order
    assert grid.sampled and grid.z.shape[0] * value.n_database <= 1000
    np.testing.assert_allclose(trace(figure(at, "simgrid"), "similarity")["z"], grid.z, rtol=1e-6)
    at.slider(key="w_runs").set_value(2)
    at.button[0].click()  # the form's submit button
    at = at.run()
    assert_clean(at)
    ev = run_protocol(Protocol.PAPER, demo, make_places(demo, DEMO_SPEC), demo_pixels, runs=2, seed=0)
    np.testing.assert_allclose(at.dataframe[0].value["R@1"], [100 * r.recall[1][0] for r in ev.rows])


# --------------------------------------------------------------------------- URL


def test_a_shared_url_reopens_the_view(app):
    app.query_params.update({"group": "2", "step": "4", "place": "3", "k": "0.5"})
    at = page(app.run(), "thresholds")
    assert_clean(at)
    assert at.selectbox(key="w_place").value == 3
    assert at.slider(key="w_k").value == 0.5
    page(at, "places")
    assert metric(at, "places") == "15"


def test_a_bad_url_parameter_is_ignored_with_a_warning(app):
    app.query_params.update({"group": "three", "k": "nan"})
    at = app.run()
    assert_clean(at)
    assert any("group='three'" in w.value for w in at.warning)


@pytest.mark.parametrize("params, said", [
    ({"group": "0"}, ["group='0'", "1 or more", "using the default (3)"]),
    ({"group": "99999999999999999999"}, ["group='99999999999999999999'", "10,000,000", "using the default (3)"]),
    ({"step": "1"}, ["step='1'", "step=1 < group=3", "using the dataset's default step"]),
    ({"reading": "diagonal"}, ["reading='diagonal'", "using the stride reading"]),
    ({"k": "10"}, ["k='10'", "outside -1 to 3", "using k = 0"]),
    ({"theta": "5"}, ["theta='5'", "outside -1 to 1", "no global θ of your own"]),
    ({"place": "-2"}, ["place='-2'", "0 or more", "the default place"]),
])
def test_a_bad_url_value_is_named_with_what_is_used_instead(app, params, said):
    app.query_params.update(params)
    at = app.run()
    assert_clean(at)
    warning = next((w.value for w in at.warning if "Ignored in the link" in w.value), "")
    assert all(fragment in warning for fragment in said), (warning, said)
    for name in ("places", "thresholds"):  # and every page then runs on what was used instead
        page(at, name)
        assert_clean(at)
    assert metric(at, "negative scores ≥ θ_p weighted")
    assert at.slider(key="w_k").value == 0.0


def test_a_url_query_traversal_the_dataset_lacks_is_replaced_with_a_warning(app):
    app.query_params.update({"query": "dusk"})
    at = app.run()
    assert_clean(at)
    assert any("query='dusk'" in w.value and "using 'snow' instead" in w.value and "**Places** page" in w.value
               for w in at.warning), [w.value for w in at.warning]
    assert "query" not in at.query_params
    at = page(at, "places")
    assert_clean(at)
    assert at.selectbox(key="w_query").value == "snow"


@pytest.mark.parametrize("name, param, value, said", [
    ("thresholds", "place", "999", "place=999 is not a place here (12 places, P0 to P11)"),
    ("inspector", "frame", "999", "frame=999 is not a query of 'demo' (0 to 59)"),
])
def test_a_url_place_or_frame_out_of_range_says_what_is_shown_instead(app, name, param, value, said):
    app.query_params.update({param: value})
    at = page(app.run(), name)
    assert_clean(at)
    assert any(said in w.value and "instead" in w.value for w in at.warning), [w.value for w in at.warning]
    assert param not in at.query_params


@pytest.mark.parametrize("name", ["thresholds", "inspector", "evaluation"])
def test_a_group_step_error_names_the_places_page(app, name):
    app.query_params.update({"group": "40", "step": "40"})  # one place on the demo's 60 frames
    at = page(app.run(), name)
    assert_clean(at, errors=True)
    (error,) = [e.value for e in at.error]
    assert "at least 2 places" in error and "**Places** page" in error and "Dataset" not in error


def test_on_the_places_page_a_group_step_error_points_at_its_own_sliders(app):
    app.query_params.update({"group": "40", "step": "40"})
    at = page(app.run(), "places")
    assert_clean(at, errors=True)
    (error,) = [e.value for e in at.error]
    assert "at least 2 places" in error and "Change group or step above." in error
    at.slider(key="w_group").set_value(3).run()
    at.slider(key="w_step").set_value(5).run()
    assert_clean(at)
    assert metric(at, "places") == "12"


# --------------------------------------------------------------------------- bad input


def choose_folder(at: AppTest, path: Path | str) -> AppTest:
    at.selectbox(key="w_source").set_value("__folder__").run()
    at.text_input(key="w_folder").input(str(path)).run()
    return at


def test_a_folder_that_does_not_exist_shows_an_error_and_keeps_the_demo(app, tmp_path):
    at = choose_folder(app.run(), tmp_path / "nope")
    assert_clean(at, errors=True)
    assert any("does not exist" in e.value for e in at.error)
    assert at.session_state["view"].source == "demo"
    page(at, "places")  # still usable
    assert_clean(at)


def test_a_folder_without_images_shows_an_error(app, tmp_path):
    (tmp_path / "day").mkdir()
    (tmp_path / "day" / "notes.txt").write_text("no images here")
    at = choose_folder(app.run(), tmp_path)
    assert_clean(at, errors=True)
    assert any("no traversal found" in e.value for e in at.error)
    assert at.session_state["view"].source == "demo"


def make_route(root: Path, frames: int = 12, corrupt: str | None = None, names: tuple[str, ...] = ("a", "b")) -> Path:
    return write_noisy_route(root, names, frames, corrupt)


def test_a_corrupt_image_shows_an_error_naming_it_and_the_app_recovers(app, tmp_path):
    route = make_route(tmp_path / "route", corrupt="b/005.png")
    at = choose_folder(app.run(), route)
    assert_clean(at, errors=True)
    assert at.session_state["view"].source == str(route)  # the folder opens; its image fails at extraction
    assert any("005.png" in e.value and "cannot read the image" in e.value for e in at.error)
    for name in PAGES:
        page(at, name)
        assert_clean(at, errors=True)
        assert any("005.png" in e.value for e in at.error), name
    page(at, "home")
    fixed = np.random.default_rng(5).integers(0, 255, size=(24, 32, 3), dtype=np.uint8)
    Image.fromarray(fixed).save(route / "b" / "005.png")  # the user replaces the broken file
    at.run()
    assert_clean(at)
    assert any("descriptors ready: 24 × 2048" in s.value for s in at.success)
    at.selectbox(key="w_source").set_value("demo").run()
    assert_clean(at)
    page(at, "places")
    assert_clean(at)
    assert metric(at, "places") == "12"


def test_a_small_typed_folder_works_end_to_end(app, tmp_path):
    route = make_route(tmp_path / "route")
    at = choose_folder(app.run(), route)
    assert_clean(at)
    assert at.query_params["source"] == str(route)
    at = page(at, "places")
    at.slider(key="w_step").set_value(3).run()  # 12 frames, group 3, step 3: 4 places
    assert_clean(at)
    assert metric(at, "places") == "4"
    for name in ("thresholds", "inspector", "evaluation"):
        page(at, name)
        assert_clean(at)


def test_an_unavailable_descriptor_is_listed_with_its_reason_and_refused(app, monkeypatch):
    from vpr_explorer.descriptors import registry

    entry = registry.ExtractorEntry(registry._pixels, lambda: "its weights are not on this machine")
    monkeypatch.setitem(registry._REGISTRY, "needs-weights", entry)
    at = app.run()
    radio = at.radio(key="w_descriptor")
    assert "needs-weights" in radio.options
    assert any("its weights are not on this machine" in c for c in radio.proto.captions)
    radio.set_value("needs-weights").run()
    assert_clean(at, errors=True)
    assert any("unavailable here" in e.value for e in at.error)
    assert at.session_state["view"].descriptor == "pixels"


# --------------------------------------------------------------------------- real data


@pytest.mark.realdata
def test_gardens_point_pages_show_the_library_numbers(app, data_root, gardens_point, gp_pixels, monkeypatch):
    gp = str(data_root / "GardensPointWalking")
    monkeypatch.setenv("VPR_EXPLORER_DATA_ROOT", str(data_root))  # its folders are listed on the Dataset page
    at = app.run()
    assert "GardensPointWalking  (under the data root)" in at.selectbox(key="w_source").options
    at.selectbox(key="w_source").set_value(gp).run()
    assert_clean(at)
    assert at.session_state["view"].source == gp
    page(at, "places")
    assert_clean(at)
    f, d = fitted_value(gardens_point, gp_pixels, PlaceSpec(3, 10))
    ov = overview(f, d)
    assert metric(at, "places") == "20" and metric(at, "database images per place") == "6"
    assert metric(at, "place-level R@1") == f"{ov.recall1['place-baseline']:.0%}"
    assert metric(at, "margin, weighted θ R@1") == f"{ov.recall1['margin-weighted']:.0%}"
    np.testing.assert_allclose(trace(figure(at, "theta_hist"), "θ_p weighted")["x"], f.model.theta["weighted"])
    at.selectbox(key="w_query").set_value("day_right").run()  # database: day_left + night_right
    assert_clean(at)
    f2, d2 = fitted_value(gardens_point, gp_pixels, PlaceSpec(3, 10), "day_right")
    assert metric(at, "place-level R@1") == f"{overview(f2, d2).recall1['place-baseline']:.0%}"
    at.selectbox(key="w_query").set_value("night_right").run()
    page(at, "thresholds")
    assert_clean(at)
    p = at.selectbox(key="w_place").value
    assert trace(figure(at, "mixture"), "θ_p weighted")["x"][0] == pytest.approx(f.model.theta["weighted"][p])
    detail = place_detail(f, d, p)
    assert metric(at, "negative scores ≥ θ_p weighted") == \
        f"{detail.share_negatives_above(detail.theta['weighted']):.0%}"
    dropped = detail.share_queries_below(detail.theta["weighted"])
    assert metric(at, "own queries dropped at θ_p(k=0)") == f"{dropped:.0%}"
    page(at, "inspector")
    at.slider(key="w_frame").set_value(101).run()
    assert_clean(at)
    dec = explain_query(f, d, 101)  # query 101: night_right frame 101
    np.testing.assert_allclose(trace(figure(at, "bars_margin-weighted"), "raw_p")["y"],
                               dec.raw[top_candidates(dec, 8)])
    assert any(c.value == describe_answer(f, dec, "margin-weighted", 101) for c in at.caption)
    page(at, "evaluation")
    assert_clean(at)
    offered = [PROTOCOL_LABELS[Protocol(p)] for p in ("paper", "traversal", "open-set")]
    assert at.radio(key="w_protocol").options == offered
    ev = run_protocol(Protocol.PAPER, gardens_point, make_places(gardens_point, PlaceSpec(3, 10)), gp_pixels, runs=20,
                      seed=0)
    np.testing.assert_allclose(at.dataframe[0].value["R@1"], [100 * r.recall[1][0] for r in ev.rows])
    at.radio(key="w_protocol").set_value("traversal")
    at.button(key="w_run").click().run()
    assert_clean(at)
    ev = evaluated_value(gardens_point, gp_pixels, PlaceSpec(3, 10))  # day_left + day_right against night_right
    np.testing.assert_allclose(at.dataframe[0].value["R@1"], [100 * r.recall[1][0] for r in ev.rows])


def test_query_and_ref_folders_query_with_query(app, tmp_path):
    """Folder order would make ``query/`` the database; the names say otherwise."""
    route = make_route(tmp_path / "route", frames=18, names=("query", "ref"))
    at = choose_folder(app.run(), route)
    at = page(at, "places")
    assert_clean(at)
    assert at.selectbox(key="w_query").value == "query"
    at = page(at, "evaluation")
    at.radio(key="w_protocol").set_value("traversal")
    at.button[0].click()
    at = at.run()
    assert_clean(at)
    caption = next(c.value for c in at.caption if c.value.startswith("database:"))
    assert "database: ref (18 images) · queries: query (18)" in caption
    assert "12 of 18 database images in 4 places" in caption  # group 3, step 5 of the 18 frames, ref's images only
