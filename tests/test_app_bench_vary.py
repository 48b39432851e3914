"""The acceptance bench varied over one parameter on the Evaluation page, under AppTest.

The figure and table functions (``views.bench_plots.sweep_*``) and the values box's parsing
are checked on hand-made cases first. Then on GardensPoint (real pixels, day_left as the
database, day_right as the queries, ±2 frames): varying ds over 4, 6 and then patch over 10,
20 draws, for each metric, one line per rule whose points are ``sweep_bench``'s numbers
(called here on the same value), the rules the parameter does not read faint and dashed;
the table and the CSV hold the same numbers. A value list that does not parse, and one the
library refuses, is an ``st.error`` with the message, never a traceback. On the
database-queries layout (no route in order) ds, patch, fan-out and the reference share are not
offered, the page saying why with ``check_parameter``'s own message, and SUE's K is.
"""

from __future__ import annotations

import io
import math

import numpy as np
import pandas as pd
import pytest
import streamlit as st
from streamlit.testing.v1 import AppTest

from test_app import assert_clean, downloads, figure, navigation_mode, page, trace  # noqa: F401  (fixtures)
from test_app_bench import bench_table, figure_spec, run_bench
from vpr_explorer.app import ENTRY
from vpr_explorer.app.ui.bench import default_values, parse_values, values_text
from vpr_explorer.app.ui.current import effective_spec
from vpr_explorer.app.ui.state import View
from vpr_explorer.data.aligned import database_queries, value_rows
from vpr_explorer.data.example_layouts import write_gardens_point_layouts
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import MetricPlaceSpec, PlaceSpec, retrieval_places
from vpr_explorer.pipeline import open_dataset
from vpr_explorer.protocols.acceptance import RULES_BY_KEY, BenchOptions, Counts
from vpr_explorer.protocols.acceptance_sweep import (
    BenchSweep,
    Parameter,
    SetNumbers,
    SweepPoint,
    check_parameter,
    check_values,
    render,
    sweep_bench,
)
from vpr_explorer.views import bench_plots

TIMEOUT = 240
QUERIES, DATABASE = "day_right", "day_left"


@pytest.fixture(autouse=True)
def fresh_caches():
    st.cache_data.clear()
    st.cache_resource.clear()
    yield


# --------------------------------------------------------------------------- by hand


def _numbers(counts: dict[str, Counts], left_out: dict[str, str] | None = None) -> SetNumbers:
    keys = list(counts)
    return SetNumbers(counts=counts, auc={k: 0.5 for k in keys}, tau={k: math.nan for k in keys},
                      tau_note={k: "oracle: best F1 on these queries" if k == "seqslam" else "" for k in keys},
                      left_out=left_out or {})


def hand_sweep(parameter: Parameter = Parameter.DS) -> BenchSweep:
    """Three values given out of order; seqslam read and left out at the middle one, per-query not read."""
    fixed = Counts(tp=6, fp=2, fn=2, tn=0, n_genuine=8, n_distractor=0)  # F1 75
    by_value = {
        20: Counts(tp=8, fp=0, fn=0, tn=0, n_genuine=8, n_distractor=0),  # F1 100
        4: Counts(tp=4, fp=4, fn=4, tn=0, n_genuine=8, n_distractor=0),  # F1 50
    }
    natural_fixed = Counts(tp=3, fp=1, fn=1, tn=3, n_genuine=4, n_distractor=4)  # F1 75, rejection 75
    points = []
    for v in (20, 10, 4):
        closed = {"per-query": fixed} if v == 10 else {"per-query": fixed, "seqslam": by_value[v]}
        left = {"seqslam": "too long here"} if v == 10 else {}
        natural = None if v == 4 else _numbers({"per-query": natural_fixed})
        points.append(SweepPoint(v, _numbers(closed, left), natural, "no distractor" if natural is None else ""))
    return BenchSweep(parameter, (20, 10, 4), ("seqslam",), tuple(points), {})


def test_sweep_figure_and_table_by_hand():
    sweep = hand_sweep()
    spec = figure_spec(bench_plots.sweep_figure(sweep, "closed"))
    assert [t["meta"] for t in spec["data"]] == ["per-query", "seqslam"]  # RULES order
    seq, pq = trace(spec, "seqslam"), trace(spec, "per-query")
    assert list(seq["x"]) == [4, 10, 20]  # increasing, whatever the order given
    np.testing.assert_array_equal(seq["y"], [50.0, np.nan, 100.0])  # left out at 10: a gap
    np.testing.assert_array_equal(pq["y"], [75.0, 75.0, 75.0])
    assert seq["line"]["dash"] == "solid" and seq["opacity"] == 1.0
    assert pq["line"]["dash"] == "dash" and pq["opacity"] == bench_plots.FAINT
    assert pq["name"] == f"{RULES_BY_KEY['per-query'].label} (does not read ds)"

    spec = figure_spec(bench_plots.sweep_figure(sweep, "rejection"))
    np.testing.assert_array_equal(trace(spec, "per-query")["y"], [np.nan, 75.0, 75.0])  # no natural set at 4
    np.testing.assert_array_equal(trace(spec, "seqslam")["y"], [np.nan] * 3)

    table = bench_plots.sweep_table(sweep, "closed")
    assert [r["key"] for r in table] == ["per-query", "seqslam"]
    assert [r["reads"] for r in table] == [False, True]
    assert [r["rule"] for r in table] == [RULES_BY_KEY["per-query"].label, RULES_BY_KEY["seqslam"].label + " †"]
    assert list(table[1])[3:] == ["ds=20", "ds=10", "ds=4"]  # the order given, as render's columns
    assert table[1]["ds=20"] == 100.0 and math.isnan(table[1]["ds=10"]) and table[1]["ds=4"] == 50.0

    rows = bench_plots.sweep_rows(sweep)
    assert [(r["key"], r["ds"]) for r in rows] == [("per-query", 20), ("per-query", 10), ("per-query", 4),
                                                  ("seqslam", 20), ("seqslam", 10), ("seqslam", 4)]
    assert rows[4]["left out"] == "too long here" and math.isnan(rows[4]["closed F1"])
    assert rows[0]["open F1"] == 75.0 and rows[0]["rejection"] == 75.0 and math.isnan(rows[2]["open F1"])
    assert rows[3]["R"] == 100.0 and rows[5]["P"] == 50.0 and not rows[0]["recomputed"]


def test_reference_share_moves_no_closed_line():
    sweep = hand_sweep(Parameter.REFERENCE_SHARE)
    assert bench_plots.sweep_affected(sweep, "closed") == ()
    assert bench_plots.sweep_affected(sweep, "open") == ("seqslam",)
    dashes = {t["meta"]: t["line"]["dash"] for t in figure_spec(bench_plots.sweep_figure(sweep, "closed"))["data"]}
    assert set(dashes.values()) == {"dash"}


@pytest.mark.parametrize("parameter, text, places, values", [
    (Parameter.DS, "4,6,10,20", None, (4, 6, 10, 20)),
    (Parameter.DS, " 4 , 6 ,", None, (4, 6)),  # spaces and a trailing comma
    (Parameter.PATCH, "10, 20.0", None, (10, 20)),
    (Parameter.REFERENCE_SHARE, "0.5,0.7", None, (0.5, 0.7)),
    (Parameter.GROUP, "1,2", PlaceSpec(2, 10), (1, 2)),
    (Parameter.STEP, "12.5, 25", MetricPlaceSpec(5.0, 25.0), (12.5, 25)),
])
def test_parse_values(parameter, text, places, values):
    got = parse_values(parameter, text, places)
    assert got == values and [type(v) for v in got] == [type(v) for v in values]


@pytest.mark.parametrize("parameter, text, said", [
    (Parameter.DS, "4,x", "'x' is not a whole number"),
    (Parameter.DS, "4,6.5", "'6.5' is not a whole number"),
    (Parameter.REFERENCE_SHARE, "0.5,half", "'half' is not a number"),
    (Parameter.FANOUT, " , ", "none given"),
    (Parameter.GROUP, "nan", "'nan' is not a whole number"),
])
def test_parse_values_refuses_with_the_parameter(parameter, text, said):
    with pytest.raises(VPRInputError, match=str(parameter)) as exc:
        parse_values(parameter, text, PlaceSpec(2, 10))
    assert said in str(exc.value)


def test_default_values():
    assert values_text(default_values(Parameter.DS, None)) == "4, 6, 10, 20"
    assert values_text(default_values(Parameter.PATCH, None)) == "10, 20, 40"
    assert default_values(Parameter.GROUP, PlaceSpec(4, 6)) == (2, 4)  # 8 > step: stride places would overlap
    assert default_values(Parameter.STEP, PlaceSpec(4, 6)) == (6, 12)  # 3 < group
    assert default_values(Parameter.STEP, PlaceSpec(4, 6, "skip")) == (3, 6, 12)
    assert default_values(Parameter.GROUP, MetricPlaceSpec(5.0, 25.0)) == (2.5, 5.0, 10.0)
    assert default_values(Parameter.GROUP, None) == ()  # the layout's own places: group/step are not offered


# --------------------------------------------------------------------------- the app on GardensPoint


def opened(source) -> AppTest:
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT)
    at.query_params.update(source=str(source), descriptor="pixels", query=QUERIES)
    return page(at.run(), "evaluation")


def offered(at: AppTest) -> list[str]:
    """The parameters the picker offers (its labels are "name: description")."""
    return [o.split(":")[0] for o in at.selectbox(key="w_vary_parameter").options]


def vary(at: AppTest, parameter: str, text: str) -> AppTest:
    """Pick the parameter, type the values and press **Vary**."""
    at.selectbox(key="w_vary_parameter").set_value(parameter).run()
    at.text_input(key="w_vary_values").set_value(text)
    return at.button(key="w_vary_run").click().run()


@pytest.fixture(scope="module")
def gp_value(gardens_point, gp_pixels):
    v = database_queries(gardens_point, QUERIES, database=[DATABASE], tolerance=2)
    rows = value_rows(v)
    spec = effective_spec(View(), gardens_point.n_frames, False)
    return v, (gp_pixels if rows is None else gp_pixels[rows]), spec


def direct(gp_value, parameter: str, values) -> BenchSweep:
    v, d, spec = gp_value
    labels = retrieval_places(v, spec)[0]
    return sweep_bench(v, d, labels=labels, parameter=parameter, values=values, options=BenchOptions(), places=spec)


def assert_lines_are_the_sweep(at: AppTest, sweep: BenchSweep, metric: str) -> None:
    spec = figure(at, "bench_sweep")
    keys = bench_plots.sweep_keys(sweep)
    assert [t["meta"] for t in spec["data"]] == keys
    order = np.argsort(sweep.values)
    for key in keys:
        line = trace(spec, key)
        np.testing.assert_array_equal(line["x"], np.asarray(sweep.values)[order])
        want = [bench_plots.sweep_value(sweep.points[i], key, metric) for i in order]
        np.testing.assert_allclose(line["y"], want, rtol=1e-12, equal_nan=True, err_msg=f"{metric} {key}")
        moves = key in sweep.recomputed
        assert line["line"]["dash"] == ("solid" if moves else "dash"), key
        assert line.get("opacity", 1) == (1 if moves else bench_plots.FAINT), key
    table = next(d.value for d in at.dataframe if "reads" in d.value.columns)
    assert table["key"].tolist() == keys and table["reads"].tolist() == [k in sweep.recomputed for k in keys]
    for v, point in zip(sweep.values, sweep.points):
        column = bench_plots.value_label(sweep.parameter, v)
        np.testing.assert_allclose(table[column].to_numpy(dtype=float),
                                   [bench_plots.sweep_value(point, k, metric) for k in keys], rtol=1e-12,
                                   equal_nan=True, err_msg=column)


@pytest.mark.realdata
def test_vary_ds_then_patch_draws_sweep_bench(data_root, gp_value, downloads):
    at = run_bench(opened(data_root / "GardensPointWalking"), w_bench_database=DATABASE)
    assert_clean(at)
    assert len(bench_table(at))
    assert offered(at) == ["ds", "patch", "fanout", "reference_share", "group", "step"]
    assert "- **sue_k**: " in next(m.value for m in at.markdown if m.value.startswith("**Not offered here**"))
    assert not [f for f in at.get("plotly_chart") if f.proto.id.endswith("-bench_sweep")]  # waits for Vary

    for parameter, text, values in (("ds", "4, 6", (4, 6)), ("patch", "10,20", (10, 20))):
        at = vary(at, parameter, text)
        assert_clean(at)
        sweep = direct(gp_value, parameter, values)
        assert sweep.values == values and set(sweep.recomputed) == set(
            {"ds": ("seqslam", "sequence-per-place"), "patch": ("per-query", "per-query-graph")}[parameter])
        for metric in ("closed", "open", "rejection"):
            at.radio(key="w_vary_metric").set_value(metric).run()
            assert_clean(at)
            assert_lines_are_the_sweep(at, sweep, metric)
        csv = pd.read_csv(io.BytesIO(downloads(at.get("download_button")[-1])), keep_default_na=False,
                          na_values=[""])
        want = pd.DataFrame(bench_plots.sweep_rows(sweep))
        assert csv["key"].tolist() == want["key"].tolist() and csv[parameter].tolist() == list(want[parameter])
        for col in ("closed F1", "open F1", "rejection", "AUC-PR"):
            np.testing.assert_allclose(csv[col].to_numpy(dtype=float), want[col].to_numpy(dtype=float),
                                       rtol=1e-12, equal_nan=True, err_msg=col)
        assert any(c.value == render(sweep) for c in at.code)  # the CLI's text table
    # the bench above stays as it was
    assert len(bench_table(at))


@pytest.mark.realdata
def test_a_bad_value_list_is_an_error_not_a_traceback(data_root, gp_value):
    at = run_bench(opened(data_root / "GardensPointWalking"), w_bench_database=DATABASE)
    at = vary(at, "ds", "4,x")
    assert_clean(at, errors=True)
    assert any("ds values '4,x': 'x' is not a whole number" in e.value for e in at.error), [e.value for e in at.error]
    assert not [f for f in at.get("plotly_chart") if f.proto.id.endswith("-bench_sweep")]

    v = gp_value[0]
    with pytest.raises(VPRInputError) as exc:
        check_values(v, Parameter.DS, (4, 5))  # odd: SeqSLAM centres its sequences on the query
    at = vary(at, "ds", "4,5")
    assert_clean(at, errors=True)
    assert [e.value for e in at.error if str(exc.value) in e.value], [e.value for e in at.error]
    assert len(bench_table(at))  # the bench is still shown

    at = vary(at, "ds", "4,6")  # fixed: the sweep runs
    assert_clean(at)
    assert figure(at, "bench_sweep")


@pytest.fixture(scope="module")
def layouts(data_root, tmp_path_factory):
    return write_gardens_point_layouts(data_root / "GardensPointWalking", tmp_path_factory.mktemp("vary_layouts"))


@pytest.mark.realdata
def test_a_layout_that_is_not_a_route_does_not_offer_ds_and_says_why(layouts):
    source = layouts["database-queries"]
    at = opened(source)
    at = run_bench(at)
    assert_clean(at)
    # the per-query rules read runs of the route too: only SUE (positions in metres) and the places remain
    assert offered(at) == ["sue_k", "group", "step"]
    value = open_dataset(source)
    said = next(m.value for m in at.markdown if m.value.startswith("**Not offered here**"))
    for name in ("ds", "patch", "fanout", "reference_share"):
        with pytest.raises(VPRInputError) as exc:
            check_parameter(value, name, BenchOptions(), labels=np.zeros(value.n_database, dtype=int),
                            places=PlaceSpec(1, 1))
        assert f"- **{name}**: {exc.value}" in said, said
    assert "no database route in order" in said

    at = vary(at, "sue_k", "5,20")  # what is offered runs
    assert_clean(at)
    spec = figure(at, "bench_sweep")
    assert {t["meta"] for t in spec["data"] if t["line"]["dash"] == "solid"} == {"sue"}
    assert [r.value for r in at.radio if r.key == "w_vary_metric"][0] == "closed"
    assert at.radio(key="w_vary_metric").options == ["closed-set F1"]  # no natural open set on a set
