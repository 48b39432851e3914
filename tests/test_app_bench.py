"""The acceptance bench on the Evaluation page and discovered places on the Places page, under AppTest.

On GardensPoint (real data, pixel descriptors): the bench waits for its button; once pressed,
its table has a row for every rule that ran, with the library's numbers
(``protocols.acceptance.acceptance_report`` on the same value, computed here), the rules left
out with their reasons, and a precision–recall figure whose curves and points are the
report's; the reference share F changes the natural open set's numbers and nothing of the
closed set; a layout that is not one route (database-queries) says why the sequence rules and
the natural open set do not run; discovered places on such a layout are refused with
``st.error``, never a traceback. The Places page draws the discovered places beside
group/step (``place_discovery.discover`` on the same database). The figure functions
(``views.bench_plots``) are checked on hand-made cases first.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import streamlit as st
from streamlit.testing.v1 import AppTest

from test_app import assert_clean, figure, navigation_mode, page, trace  # noqa: F401  (fixtures)
from vpr_explorer.app import ENTRY
from vpr_explorer.app.ui.bench import soft_matrix
from vpr_explorer.app.ui.current import effective_spec
from vpr_explorer.app.ui.state import View
from vpr_explorer.data.aligned import database_queries, value_rows
from vpr_explorer.data.example_layouts import write_gardens_point_layouts
from vpr_explorer.data.groundtruth import GroundTruth
from vpr_explorer.method.place_discovery import discover
from vpr_explorer.method.places import retrieval_places
from vpr_explorer.method.retrieval import similarity
from vpr_explorer.protocols.acceptance import RULES, BenchOptions, Counts, acceptance_report
from vpr_explorer.protocols.tutorial_pr import tutorial_pr
from vpr_explorer.views import bench_plots

TIMEOUT = 180
SEQUENCE_RULES = [r.key for r in RULES if r.needs == "sequence"]


@pytest.fixture(autouse=True)
def fresh_caches():
    st.cache_data.clear()
    st.cache_resource.clear()
    yield


# --------------------------------------------------------------------------- the figures, by hand


@pytest.mark.parametrize("place, starts", [
    ([-1, 0, 0, 1, 1, -1, 2, 2, -1], [1, 3, 6]),
    ([0, 0, 0], [0]),
    ([3, 3, -1, 3], [0, 3]),  # the same id after a gap starts again
    ([-1, -1], []),
    ([0, 1, 2], [0, 1, 2]),
])
def test_place_starts_by_hand(place, starts):
    assert bench_plots.place_starts(np.array(place)).tolist() == starts


def test_operating_point_by_hand():
    bench = SimpleNamespace(counts={
        "some": Counts(tp=3, fp=1, fn=4, tn=2, n_genuine=8, n_distractor=3),
        "none": Counts(tp=0, fp=0, fn=5, tn=3, n_genuine=5, n_distractor=3),
        "no genuine": Counts(tp=0, fp=2, fn=0, tn=1, n_genuine=0, n_distractor=3),
    })
    # recall over every genuine query (3 of 8, the curve's), precision TP/(TP+FP)
    assert bench_plots.operating_point(bench, "some") == (3 / 8, 3 / 4)
    assert bench_plots.operating_point(bench, "none") == (0.0, 1.0)  # nothing accepted: precision 1, as the curves
    r, p = bench_plots.operating_point(bench, "no genuine")
    assert math.isnan(r) and p == 0.0


def test_soft_matrix_and_tutorial_labels():
    gt = GroundTruth.from_lists([[0], [], [2]], 4, "by hand", soft=[[0, 1], [3], [1, 2]])
    ds = SimpleNamespace(ground_truth=gt)
    np.testing.assert_array_equal(soft_matrix(ds), [[1, 1, 0, 0], [0, 0, 0, 1], [0, 1, 1, 0]])
    assert soft_matrix(SimpleNamespace(ground_truth=GroundTruth.from_lists([[0]], 2, "hard"))) is None
    s = np.array([[0.9, 0.8, 0.1, 0.0], [0.5, 0.4, 0.3, 0.2], [0.1, 0.7, 0.6, 0.0]])
    hard = np.zeros((3, 4), dtype=bool)
    hard[0, 0] = hard[2, 2] = True
    curves = {"single": tutorial_pr(s, hard, matching="single"),
              "multi": tutorial_pr(s, hard, soft_matrix(ds), matching="multi")}
    spec = figure_spec(bench_plots.tutorial_pr_figure(curves))
    assert trace(spec, "single")["name"].startswith("single-best-match, hard ground truth only: AUC")
    assert trace(spec, "multi")["name"].startswith("multi-match, soft positives ignored: AUC")
    for key, curve in curves.items():
        np.testing.assert_array_equal(trace(spec, key)["y"], curve.precision)
        np.testing.assert_array_equal(trace(spec, key)["x"], curve.recall)


def test_discovery_figure_draws_the_library_arrays():
    rng = np.random.default_rng(3)
    centres = rng.normal(size=(4, 16))
    x = np.repeat(centres, 6, axis=0) + 0.05 * rng.normal(size=(24, 16))
    found = discover(x / np.linalg.norm(x, axis=1, keepdims=True))
    group = np.where(np.arange(24) % 6 < 3, np.arange(24) // 6, -1)  # group 3, step 6
    spec = figure_spec(bench_plots.discovery_figure(group, found))
    for band, place in (("group/step", group), ("discovered", found.place)):
        inside = trace(spec, f"places {band}")
        np.testing.assert_array_equal(inside["x"], np.flatnonzero(place >= 0))
        np.testing.assert_array_equal(inside["customdata"], place[place >= 0])
        np.testing.assert_array_equal(trace(spec, f"outside {band}")["x"], np.flatnonzero(place < 0))
        np.testing.assert_array_equal(trace(spec, f"starts {band}")["x"], bench_plots.place_starts(place) - 0.5)
    np.testing.assert_array_equal(trace(spec, "score")["y"], found.score)
    np.testing.assert_array_equal(trace(spec, "θ")["y"], found.theta)
    with np.errstate(invalid="ignore"):
        np.testing.assert_array_equal(trace(spec, "below θ")["x"], np.flatnonzero(found.score <= found.theta))


def figure_spec(fig) -> dict:
    """A figure as the element tree holds it (``plotly.io.to_json``: typed arrays)."""
    import json

    import plotly.io as pio

    return json.loads(pio.to_json(fig))


# --------------------------------------------------------------------------- the app on GardensPoint

@pytest.fixture(scope="module")
def layouts(data_root, tmp_path_factory):
    return write_gardens_point_layouts(data_root / "GardensPointWalking", tmp_path_factory.mktemp("bench_layouts"))


def opened(source, name: str = "evaluation") -> AppTest:
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT)
    at.query_params.update(source=str(source), descriptor="pixels")
    return page(at.run(), name)


def run_bench(at: AppTest, **values) -> AppTest:
    """Set the bench form's widgets (by key) and press **Run the bench**."""
    for key, value in values.items():
        widget = next(w for kind in ("radio", "slider", "selectbox", "number_input")
                      for w in at.get(kind) if getattr(w, "key", None) == key)
        widget.set_value(value)
    return at.button(key="w_bench_run").click().run()


def bench_table(at: AppTest):
    found = [d.value for d in at.dataframe if "closed F1" in d.value.columns]
    assert len(found) == 1, [list(d.value.columns) for d in at.dataframe]
    return found[0]


def left_out_text(at: AppTest) -> str:
    found = [m.value for m in at.markdown if m.value.startswith("**Rules left out**")]
    return found[0] if found else ""


def app_value(gp, pixels, *, database: str | None = None, tolerance: int = 2):
    """The value the app's bench runs on: ``database`` (default the first traversal that is not the query) against
    the query traversal."""
    query = gp.traversals[gp.default_roles().query]
    database = database or next(t for t in gp.traversals if t != query)
    v = database_queries(gp, query, database=[database], tolerance=tolerance)
    rows = value_rows(v)
    return v, (pixels if rows is None else pixels[rows])


def expected(gp, pixels, *, database: str | None = None, tolerance: int = 2, **options):
    v, d = app_value(gp, pixels, database=database, tolerance=tolerance)
    labels = retrieval_places(v, effective_spec(View(), gp.n_frames, False))[0]
    return acceptance_report(v, d, labels=labels, options=BenchOptions(**options)), v, d


def assert_table_is_the_report(table, report) -> None:
    rows = bench_plots.bench_rows(report)
    assert table["key"].tolist() == [r["key"] for r in rows]
    for col in ("closed F1", "R@1", "R@5", "open F1", "rejection", "AUC-PR", "τ"):
        np.testing.assert_allclose(table[col].to_numpy(dtype=float), [r[col] for r in rows], rtol=1e-12,
                                   equal_nan=True, err_msg=col)
    assert table["τ from"].tolist() == [r["τ from"] for r in rows]


@pytest.mark.realdata
def test_the_bench_waits_for_its_button(data_root):
    at = opened(data_root / "GardensPointWalking")
    assert_clean(at)
    assert at.button(key="w_bench_run")
    assert not [d for d in at.dataframe if "closed F1" in d.value.columns]
    assert at.number_input(key="w_bench_tolerance").value == 2 and at.slider(key="w_bench_share").value == 70


@pytest.mark.realdata
def test_the_bench_shows_every_rule_its_left_out_notes_and_curves(data_root, gardens_point, gp_pixels):
    at = run_bench(opened(data_root / "GardensPointWalking"))
    assert_clean(at)
    report, v, d = expected(gardens_point, gp_pixels)
    table = bench_table(at)
    ran = [r.key for r in RULES if r.key in report.closed.decisions]
    assert table["key"].tolist() == ran and len(ran) + len(report.closed.left_out) == len(RULES)
    assert set(SEQUENCE_RULES) <= set(ran)  # one database traversal: one route, the sequence rules run
    assert_table_is_the_report(table, report)
    said = left_out_text(at)
    for row in bench_plots.left_out_rows(report):
        assert f"**{row['rule']}** ({row['where']}): {row['reason']}" in said
    # the closed set's curves and each rule's own point
    spec = figure(at, "bench_pr")
    for key in ran:
        curve = report.closed.decisions[key].curve
        np.testing.assert_allclose(trace(spec, key)["y"], curve.precision)
        np.testing.assert_allclose(trace(spec, key)["x"], curve.recall)
        point = trace(spec, f"own {key}")
        assert (point["x"][0], point["y"][0]) == pytest.approx(bench_plots.operating_point(report.closed, key))
    # VPR_Tutorial's curves on the same value: no soft positives in this ground truth
    tut = figure(at, "bench_tutorial_pr")
    s = similarity(d[v.n_database:], d[:v.n_database])
    for matching in ("single", "multi"):
        np.testing.assert_allclose(trace(tut, matching)["y"],
                                   tutorial_pr(s, v.ground_truth.dense(), matching=matching).precision)
    assert any("no soft positives" in c.value for c in at.caption)

    # the toggle draws the natural open set's curves
    at.radio(key="w_bench_set").set_value("natural").run()
    assert_clean(at)
    spec = figure(at, "bench_pr")
    assert "natural open set" in spec["layout"]["title"]["text"]
    for key, dec in report.natural.decisions.items():
        np.testing.assert_allclose(trace(spec, key)["y"], dec.curve.precision)


@pytest.mark.realdata
def test_the_reference_share_changes_the_open_set_numbers(data_root, gardens_point, gp_pixels):
    at = run_bench(opened(data_root / "GardensPointWalking"))
    before = bench_table(at)
    at = run_bench(at, w_bench_share=50)
    assert_clean(at)
    after = bench_table(at)
    report, _, _ = expected(gardens_point, gp_pixels, reference_share=0.5)
    assert_table_is_the_report(after, report)
    assert not np.allclose(before["open F1"], after["open F1"], equal_nan=True)
    for col in ("closed F1", "R@1", "R@5", "AUC-PR"):  # the closed set does not move
        np.testing.assert_array_equal(before[col], after[col])
    assert at.slider(key="w_bench_share").value == 50  # the form shows what the table was computed with
    assert any("the first 50% of the database route" in c.value for c in at.caption)


@pytest.mark.realdata
def test_every_control_reaches_the_bench(data_root, gardens_point, gp_pixels):
    """Database traversal, tolerance, discovered places, mean place score, patch, fan-out and ds, all at once."""
    at = run_bench(opened(data_root / "GardensPointWalking"), w_bench_database="day_right", w_bench_tolerance=1,
                   w_bench_places="discovered", w_bench_place_score="mean", w_bench_patch=10, w_bench_fanout=3,
                   w_bench_ds=6)
    assert_clean(at)
    report, v, _ = expected(gardens_point, gp_pixels, database="day_right", tolerance=1, places="discovered",
                            place_score="mean", patch=10, fanout=3, ds=6)
    assert_table_is_the_report(bench_table(at), report)
    assert at.selectbox(key="w_bench_database").value == "day_right" and at.number_input(key="w_bench_ds").value == 6
    said = " ".join(m.value for m in at.markdown)
    assert f"{v.n_queries:,} queries × {v.n_database:,} database images (night_right against day_right)" in said
    assert "ground truth: within ±1 frames" in said and "places: discovered online" in said


@pytest.mark.realdata
def test_a_layout_that_is_not_a_route_says_why(layouts):
    at = run_bench(opened(layouts["database-queries"]))
    assert_clean(at)
    assert not [w for w in at.number_input if w.key == "w_bench_tolerance"]  # the layout fixes its ground truth
    table = bench_table(at)
    assert not set(SEQUENCE_RULES) & set(table["key"])
    said = left_out_text(at)
    for key in SEQUENCE_RULES:
        label = next(r.label for r in RULES if r.key == key)
        assert f"**{label}** (both sets): " in said and "has no database route in order" in said, said
    assert any(c.value.startswith("Natural open set not run:") and "not one route in order" in c.value
               for c in at.caption)
    assert table["open F1"].isna().all()


@pytest.mark.realdata
def test_discovered_places_on_a_set_is_an_error_not_a_traceback(layouts):
    at = run_bench(opened(layouts["database-queries"]), w_bench_places="discovered")
    assert_clean(at, errors=True)
    assert any("places=discovered" in e.value and "not one route in order" in e.value for e in at.error), \
        [e.value for e in at.error]
    assert not [d for d in at.dataframe if "closed F1" in d.value.columns]
    at = run_bench(at, w_bench_places="group-step")  # fixed: the bench runs again
    assert_clean(at)
    assert len(bench_table(at))


@pytest.mark.realdata
def test_discovered_places_on_the_places_page(data_root, gardens_point, gp_pixels, layouts):
    at = opened(data_root / "GardensPointWalking", "places")
    assert_clean(at)
    query = gardens_point.traversals[gardens_point.default_roles().query]
    first = next(t for t in gardens_point.traversals if t != query)
    assert at.selectbox(key="w_discovery_traversal").value == first
    v = database_queries(gardens_point, query, database=[first])
    d = gp_pixels[value_rows(v)][:v.n_database]
    found = discover(d)
    spec = figure(at, "discovery")
    np.testing.assert_array_equal(trace(spec, "places discovered")["customdata"], found.place[found.place >= 0])
    np.testing.assert_allclose(trace(spec, "score")["y"], found.score)
    group = retrieval_places(v, effective_spec(View(), gardens_point.n_frames, False))[0]
    np.testing.assert_array_equal(trace(spec, "starts group/step")["x"], bench_plots.place_starts(group) - 0.5)
    said = " ".join(c.value for c in at.caption)
    assert f"**discovered**: {found.n_places} places of {found.sizes.min()}–{found.sizes.max()}" in said

    at = opened(layouts["database-queries"], "places")
    assert_clean(at)
    assert any("No discovered places here" in i.value and "not one route in order" in i.value for i in at.info)
