"""The acceptance bench swept over one parameter (``protocols.acceptance_sweep``).

Every value's numbers are those of ``acceptance_report`` run with that option, whole (every
rule), on GardensPoint pixels (day_left database, day_right queries, ±2 frames): the sweep
reruns only the rules that read the parameter, and these tests hold it to the full bench.
Refusals are checked against the messages of what refuses the value (``BenchOptions``,
``PlaceSpec``) and the reasons the bench gives for leaving rules out.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from vpr_explorer.data.aligned import database_queries, value_rows
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import PlaceSpec, retrieval_places
from vpr_explorer.protocols.acceptance import RULES, BenchOptions, Counts, acceptance_report
from vpr_explorer.protocols.acceptance_sweep import (
    MAX_VALUES,
    READERS,
    Parameter,
    SetNumbers,
    SweepPoint,
    cell,
    render,
    sweep_bench,
)

SPEC = PlaceSpec(3, 10)


@pytest.fixture(scope="module")
def gp(gardens_point, gp_pixels):
    """GardensPoint: day_left database, day_right queries, ±2 frames; pixels in the value's order; group 3, step 10."""
    value = database_queries(gardens_point, "day_right", database=["day_left"], tolerance=2)
    rows = value_rows(value)
    d = np.asarray(gp_pixels if rows is None else gp_pixels[rows], dtype=np.float32)
    labels, _ = retrieval_places(value, SPEC)
    return value, d, labels


def same(a: float, b: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or a == b


def assert_set_is_bench(numbers: SetNumbers, bench) -> None:
    """Every rule's counts, AUC-PR, τ and left-out reason are the bench's."""
    assert list(numbers.counts) == [r.key for r in RULES if r.key in bench.decisions]  # in RULES order
    assert numbers.counts == bench.counts
    for key, d in bench.decisions.items():
        assert same(numbers.auc[key], d.curve.auc), key
        assert same(numbers.tau[key], d.tau) and numbers.tau_note[key] == d.tau_note, key
    assert numbers.left_out == bench.left_out


def assert_point_is_report(point: SweepPoint, report) -> None:
    assert_set_is_bench(point.closed, report.closed)
    assert (point.natural is None) == (report.natural is None)
    if report.natural is not None:
        assert_set_is_bench(point.natural, report.natural)
    assert point.natural_note == report.natural_note


@pytest.mark.parametrize("parameter, values", [
    ("ds", [4, 6, 20]),
    ("patch", [10, 40]),
    ("fanout", [1, 3]),
    ("reference_share", [0.5, 0.9]),
])
def test_each_value_is_the_whole_bench_with_that_option(gp, parameter, values):
    value, d, labels = gp
    sweep = sweep_bench(value, d, labels=labels, parameter=parameter, values=values)
    assert sweep.values == tuple(values) and sweep.parameter is Parameter(parameter)
    assert sweep.recomputed == READERS[Parameter(parameter)]
    assert sweep.settings[parameter] == values
    for v, point in zip(values, sweep.points):
        assert point.value == v
        assert_point_is_report(point, acceptance_report(value, d, labels=labels,
                                                        options=BenchOptions(**{parameter: v})))


def test_an_odd_ds_is_refused_by_name(gp):
    value, d, labels = gp
    with pytest.raises(VPRInputError, match="ds=5: .*even"):
        sweep_bench(value, d, labels=labels, parameter="ds", values=[5, 6])


@pytest.mark.parametrize("parameter, values", [("group", [1, 5]), ("step", [10, 25])])
def test_group_and_step_relabel_the_places(gp, parameter, values):
    value, d, labels = gp
    sweep = sweep_bench(value, d, labels=labels, parameter=parameter, values=values, places=SPEC)
    assert sweep.recomputed == ("per-place", "per-place-k", "sequence-per-place")
    for v, point in zip(values, sweep.points):
        spec = PlaceSpec(v, SPEC.step) if parameter == "group" else PlaceSpec(SPEC.group, v)
        at, _ = retrieval_places(value, spec)
        assert_point_is_report(point, acceptance_report(value, d, labels=at, options=BenchOptions()))


def test_sue_k_with_positions_in_metres(gp):
    value, d, labels = gp
    xy = np.asarray(value.database_xy) * 500.0  # gp_pos.csv is the unit square: make it 500 m across
    sweep = sweep_bench(value, d, labels=labels, parameter="sue_k", values=[1, 5], database_xy=xy,
                        options=BenchOptions(rules=("baseline", "sue")))
    assert sweep.recomputed == ("sue",)
    for v, point in zip((1, 5), sweep.points):
        report = acceptance_report(value, d, labels=labels, database_xy=xy,
                                   options=BenchOptions(rules=("baseline", "sue"), sue_k=v))
        assert_point_is_report(point, report)
    assert sweep.points[0].closed.counts["sue"] != sweep.points[1].closed.counts["sue"]


def test_given_rules_and_taus_stand_in_every_column(gp):
    value, d, labels = gp
    options = BenchOptions(rules=("baseline", "seqslam", "per-query-graph"), taus={"seqslam": 0.99})
    sweep = sweep_bench(value, d, labels=labels, parameter="ds", values=[4, 8], options=options)
    assert sweep.recomputed == ("seqslam",)
    for v, point in zip((4, 8), sweep.points):
        report = acceptance_report(value, d, labels=labels, options=BenchOptions(
            rules=options.rules, taus=options.taus, ds=v))
        assert_point_is_report(point, report)
        assert point.closed.tau["seqslam"] == 0.99 and point.closed.tau_note["seqslam"] == "given"


def test_values_run_once_each_with_progress(gp):
    value, d, labels = gp
    seen = []
    sweep = sweep_bench(value, d, labels=labels, parameter="fanout", values=[3, 3, np.int64(2)],
                        options=BenchOptions(rules=("per-query-graph",)), progress=lambda *a: seen.append(a))
    assert sweep.values == (3, 2) and all(type(v) is int for v in sweep.values)
    assert seen == [(1, 2), (2, 2)]
    assert sweep_bench(value, d, labels=labels, parameter="fanout", values=np.array([2]),
                       options=BenchOptions(rules=("per-query-graph",))).values == (2,)


# --------------------------------------------------------------------------- refusals


def bench_message(**option) -> str:
    with pytest.raises(VPRInputError) as exc:
        BenchOptions(**option)
    return str(exc.value)


@pytest.mark.parametrize("parameter, values, option", [
    ("ds", [4, 1], {"ds": 1}),
    ("patch", [10, 1], {"patch": 1}),
    ("fanout", [0], {"fanout": 0}),
    ("reference_share", [0.5, 1.0], {"reference_share": 1.0}),
    ("ds", [4.5], {"ds": 4.5}),
])
def test_values_the_bench_refuses_are_refused_with_its_message(gp, parameter, values, option):
    value, d, labels = gp
    with pytest.raises(VPRInputError) as exc:
        sweep_bench(value, d, labels=labels, parameter=parameter, values=values)
    assert str(exc.value) == bench_message(**option)


def test_group_step_values_are_refused_with_placespecs_message(gp):
    value, d, labels = gp
    with pytest.raises(VPRInputError) as exc:
        sweep_bench(value, d, labels=labels, parameter="group", values=[3, 12], places=SPEC)
    with pytest.raises(VPRInputError) as want:
        PlaceSpec(12, 10)
    assert str(exc.value) == str(want.value)
    with pytest.raises(VPRInputError, match=r"step=300: .*1 place"):
        sweep_bench(value, d, labels=labels, parameter="step", values=[300], places=SPEC)


@pytest.mark.parametrize("kwargs, fragments", [
    ({"parameter": "nope", "values": [1]}, ("parameter='nope'", "ds, patch, fanout, sue_k, reference_share, group, "
                                                                "step")),
    ({"parameter": "places", "values": ["discovered"]}, ("parameter='places'",)),
    ({"parameter": "ds", "values": []}, ("ds: give at least one value",)),
    ({"parameter": "ds", "values": 4}, ("ds: give at least one value",)),
    ({"parameter": "ds", "values": list(range(2, 2 * MAX_VALUES + 4, 2))}, (f"give at most {MAX_VALUES}",)),
    ({"parameter": "reference_share", "values": [0.004]}, ("reference_share=0.004 keeps 0 of 200",)),
    ({"parameter": "sue_k", "values": [3]}, ("sue_k", "read by sue only", "not metres")),
    ({"parameter": "ds", "values": [4], "options": BenchOptions(rules=("baseline",))},
     ("ds", "rules=['baseline'] leaves them out")),
    ({"parameter": "fanout", "values": [3], "options": BenchOptions(rules=("per-query", "seqslam"))},
     ("fanout", "per-query-graph only",)),
    ({"parameter": "group", "values": [3]}, ("group: give the group/step spec",)),
    ({"parameter": "step", "values": [10], "places": SPEC, "options": BenchOptions(places="discovered")},
     ("step spaces the group/step places", "places='discovered'")),
])
def test_parameters_the_bench_does_not_read_are_refused_by_name(gp, kwargs, fragments):
    value, d, labels = gp
    with pytest.raises(VPRInputError) as exc:
        sweep_bench(value, d, labels=labels, **kwargs)
    for fragment in fragments:
        assert fragment in str(exc.value)


def test_sequence_parameters_are_refused_where_the_sequence_rules_are_left_out(gardens_point, gp_pixels):
    # two database traversals: not one route, so no sequence rule and no natural open set
    value = database_queries(gardens_point, "night_right", database=["day_left", "day_right"], tolerance=2)
    rows = value_rows(value)
    d = gp_pixels if rows is None else gp_pixels[rows]
    labels, _ = retrieval_places(value, SPEC)
    for parameter in ("ds", "patch", "fanout"):
        with pytest.raises(VPRInputError) as exc:
            sweep_bench(value, d, labels=labels, parameter=parameter, values=[4])
        assert str(exc.value).startswith(f"{parameter} (") and "no database route in order" in str(exc.value)
    with pytest.raises(VPRInputError, match="reference_share cuts the natural open set.*not one route in order"):
        sweep_bench(value, d, labels=labels, parameter="reference_share", values=[0.5])
    # the per-place rules still read group/step there
    sweep = sweep_bench(value, d, labels=labels, parameter="group", values=[2], places=SPEC,
                        options=BenchOptions(rules=("per-place", "sequence-per-place")))
    assert "per-place" in sweep.points[0].closed.counts and "sequence-per-place" in sweep.points[0].closed.left_out
    assert sweep.points[0].natural is None and "not one route in order" in sweep.points[0].natural_note


# --------------------------------------------------------------------------- the table and JSON


def test_a_cell_by_hand():
    # P = 3/4, R = 3/4: F1 75; the natural open set: 2 of 4 distractors rejected
    closed = Counts(tp=3, fp=1, fn=1, tn=0, n_genuine=5, n_distractor=0)
    natural = Counts(tp=1, fp=3, fn=1, tn=2, n_genuine=3, n_distractor=4)  # P 25, R 50: F1 100/3
    nan = float("nan")
    point = SweepPoint(4, SetNumbers({"baseline": closed}, {"baseline": nan}, {"baseline": nan}, {"baseline": ""}, {}),
                       None, "not run")
    assert cell(point, "baseline") == "75.0 / — / —"
    point = SweepPoint(4, point.closed, SetNumbers({"baseline": natural}, {"baseline": 0.5}, {"baseline": nan},
                                                   {"baseline": ""}, {}), "")
    assert cell(point, "baseline") == "75.0 / 33.3 / 50.0"
    assert cell(point, "seqslam") == "— / — / —"


def test_render_and_strict_json(gp):
    value, d, labels = gp
    sweep = sweep_bench(value, d, labels=labels, parameter="patch", values=[10, 40], settings={"descriptor": "pixels"})
    text = render(sweep)
    assert "patch varied" in text and "patch=10" in text and "patch=40" in text
    for key in ("per-query", "per-query-graph", "baseline"):
        label = next(r.label for r in RULES if r.key == key)
        line = next(line for line in text.splitlines() if line[2:].startswith(label + " "))
        assert line.startswith("* " if key in sweep.recomputed else "  ")
        for point in sweep.points:
            c, o = point.closed.counts[key], point.natural.counts[key]
            assert f"{c.f1:.1f} / {o.f1:.1f} / {o.rejection:.1f}" in line
    assert "sue left out: " in text

    def refuse(constant):
        raise ValueError(constant)

    data = json.loads(json.dumps(sweep.to_dict(), allow_nan=False), parse_constant=refuse)
    assert data["parameter"] == "patch" and data["values"] == [10, 40]
    assert data["settings"]["descriptor"] == "pixels" and data["settings"]["patch"] == [10, 40]
    for point, got in zip(sweep.points, data["points"]):
        for key, counts in point.closed.counts.items():
            row = got["closed_set"]["rules"][key]
            assert row["F1"] == counts.f1 and row["TP"] == counts.tp
            auc = point.closed.auc[key]
            assert row["auc"] == (auc if np.isfinite(auc) else None)
        assert got["natural_open_set"]["rules"]["baseline"]["rejection"] == point.natural.counts["baseline"].rejection
        assert got["closed_set"]["left_out"] == point.closed.left_out
