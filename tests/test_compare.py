"""Runs side by side (``compare``): hand-built runs, their table, differences, exports and round trips."""

from __future__ import annotations

import csv
import io
import json
import math
import re

import numpy as np
import pytest

from vpr_explorer.protocols import compare
from vpr_explorer.views import compare_plots
from vpr_explorer.errors import VPRInputError
from vpr_explorer.protocols.evaluation import Evaluation, MethodRow, Protocol, TradeoffRow
from vpr_explorer.protocols.precision_recall import PRPoint, PRRow, curve_from_counts


def _row(key: str, label: str, r1: float, precision: float, rejection: float | None = None) -> MethodRow:
    return MethodRow(key=key, label=label, source="", recall={1: (r1, 0.01), 5: (min(1.0, r1 + 0.1), 0.0)},
                     accepted=(0.9, 0.0), precision=(precision, 0.0),
                     unknown_rejection=None if rejection is None else (rejection, 0.0))


def _pr(key: str, label: str, auc: float, r100: float, f1: float) -> PRRow:
    return PRRow(key=key, label=label, curve="global θ", param="θ", auc=auc, r_at_100p=r100, r_at_99p=r100,
                 max_f1=f1, max_f1_at=0.5, own=PRPoint(0.5, 6, 8, 10, 0), n_known=10, n_unknown=0)


def _evaluation(protocol: Protocol, settings: dict, rows, pr=(), curves=None, tradeoff=()) -> Evaluation:
    return Evaluation(protocol=protocol, settings=settings, ks=(1, 5), rows=tuple(rows), pr=tuple(pr),
                      pr_curves=curves or {}, tradeoff=tuple(tradeoff))


SETTINGS = {"dataset": "GardensPointWalking", "descriptor": "pixels", "places": "20 places × 9 images", "group": 3,
            "step": 10, "reading": "stride", "theta": None, "tolerance": 0, "runs": 20, "seed": 0,
            "cross_condition": False, "queries_per_run": 20}


@pytest.fixture
def runs():
    """Two paper runs (pixels, efficientnet-lite0) by hand; the second lacks precision–recall for the oracle."""
    curve = curve_from_counts("θ", [np.inf, 0.9, 0.5, 0.1], [0, 2, 6, 7], [0, 2, 8, 10], 10, 0)
    a = _evaluation(Protocol.PAPER, SETTINGS,
                    [_row("place-baseline", "place-level baseline", 0.60, 0.60),
                     _row("margin-weighted", "margin, weighted θ", 0.55, 0.80)],
                    [_pr("place-baseline", "place-level baseline", 0.50, 0.20, 0.60)], {"global θ": curve})
    b = _evaluation(Protocol.PAPER, {**SETTINGS, "descriptor": "efficientnet-lite0", "tolerance": 2},
                    [_row("place-baseline", "place-level baseline", 0.85, 0.85),
                     _row("margin-weighted", "margin, weighted θ", 0.80, 0.95),
                     _row("global-oracle", "global θ, oracle", 0.70, 0.99)],
                    [_pr("place-baseline", "place-level baseline", 0.75, 0.40, 0.80)], {"global θ": curve})
    kept: tuple = ()
    for ev in (a, b):
        kept = compare.add_run(kept, compare.record(ev, run_id=compare.next_id(kept, 0)))
    return kept


def test_records_hold_every_setting_flat_and_name_themselves(runs):
    a, b = runs
    assert (a.id, b.id) == ("run 1", "run 2")
    assert a.name == "run 1: paper · pixels" and b.name == "run 2: paper · efficientnet-lite0"
    assert a.settings["protocol"] == "paper" and a.settings["group"] == 3 and "theta" not in a.settings  # None left out
    ev = _evaluation(Protocol.TRAVERSAL, {"database": ["day_left", "night_right"], "queries": "day_right"}, [])
    assert compare.run_settings(ev)["database"] == "day_left+night_right"


def test_metric_table_columns_values_and_differences(runs):
    a, b = runs
    rows = compare.metric_table(runs, ["R@1", "precision", "AUC", "R@100P"])
    assert [(r["key"], r["metric"]) for r in rows][:4] == [("place-baseline", m) for m in
                                                          ("R@1", "precision", "AUC", "R@100P")]
    diff = f"Δ {b.name} − {a.name}"
    assert list(rows[0]) == ["method", "key", "metric", a.name, b.name, diff]
    by = {(r["key"], r["metric"]): r for r in rows}
    r1 = by[("place-baseline", "R@1")]
    assert (r1[a.name], r1[b.name]) == (0.60, 0.85) and r1[diff] == pytest.approx(0.25)  # hand-computed
    assert by[("place-baseline", "AUC")][diff] == pytest.approx(0.25)
    assert by[("margin-weighted", "precision")][diff] == pytest.approx(0.15)
    # a method only the second run has: NaN for the first and for the difference, never 0
    oracle = by[("global-oracle", "R@1")]
    assert math.isnan(oracle[a.name]) and oracle[b.name] == 0.70 and math.isnan(oracle[diff])
    # a metric without precision–recall rows for that method: NaN in both
    assert math.isnan(by[("margin-weighted", "AUC")][a.name])


def test_the_reference_run_can_be_any_run(runs):
    a, b = runs
    rows = compare.metric_table(runs, ["R@1"], methods=["place-baseline"], reference=b.id)
    assert list(rows[0]) == ["method", "key", "metric", a.name, b.name, f"Δ {a.name} − {b.name}"]
    assert rows[0][f"Δ {a.name} − {b.name}"] == pytest.approx(-0.25)
    with pytest.raises(VPRInputError, match="no run 'run 9'"):
        compare.metric_table(runs, ["R@1"], reference="run 9")
    with pytest.raises(VPRInputError, match="metric"):
        compare.metric_table(runs, ["R@2000"])


def test_the_list_pins_renames_removes_and_keeps_no_duplicates(runs):
    a, b = runs
    again = compare.add_run(runs, compare.record(a.evaluation, run_id="run 3"))
    assert again == runs  # the same settings: the same run, not a second copy
    renamed = compare.rename(runs, a.id, "pixels")
    assert renamed[0].name == "pixels" and renamed[1] is b
    with pytest.raises(VPRInputError, match="already called"):
        compare.rename(renamed, b.id, "pixels")
    with pytest.raises(VPRInputError, match="cannot be empty"):
        compare.rename(runs, a.id, "  ")
    pinned = compare.pin(runs, a.id)
    assert pinned[0].pinned and not pinned[1].pinned
    assert compare.remove(runs, a.id) == (b,)
    # beyond max_runs unpinned runs the oldest unpinned one goes; a pinned one stays
    kept = compare.pin(runs, a.id)
    for i in range(3, 6):
        ev = _evaluation(Protocol.PAPER, {**SETTINGS, "seed": i}, a.evaluation.rows)
        kept = compare.add_run(kept, compare.record(ev, run_id=compare.next_id(kept, i - 1)), max_runs=2)
    assert [r.id for r in kept] == ["run 1", "run 4", "run 5"]
    assert compare.next_id(kept, 9) == "run 10"


def test_settings_rows_put_what_differs_first(runs):
    rows = compare.settings_rows(runs)
    assert list(rows[0])[:5] == ["run", "name", "pinned", "descriptor", "tolerance"]
    assert compare.differing_settings(runs) == ["descriptor", "tolerance"]
    assert rows[1]["descriptor"] == "efficientnet-lite0" and rows[0]["tolerance"] == 0


def test_export_file_name_carries_the_settings(runs):
    stem = compare.export_stem(runs)
    assert stem == ("vpr_runs_GardensPointWalking_pixels-vs-efficientnet-lite0_paper_g3_s10_"
                    "stride_r20_seed0_nocross_tol0-vs-tol2")
    assert re.fullmatch(r"[A-Za-z0-9._+-]+", stem)


def test_runs_csv_carries_every_setting_and_round_trips(runs):
    text = compare.runs_csv(runs)
    header = next(csv.reader(io.StringIO(text)))
    assert header[:3] == ["run", "name", "pinned"]
    assert set(compare.setting_names(runs)) <= set(header)
    back = compare.read_runs_csv(text)
    assert len(back) == 5  # 2 methods + 3 methods
    for r in runs:
        for row in r.evaluation.rows:
            line = next(x for x in back if x["run"] == r.id and x["method"] == row.key)
            assert line["name"] == r.name and line["descriptor"] == r.settings["descriptor"]
            assert line["tolerance"] == str(r.settings["tolerance"]) and line["protocol"] == "paper"
            for m in compare.METRICS:
                want = r.value(m, row.key)
                assert (math.isnan(line[m]) and math.isnan(want)) or line[m] == want, (r.id, row.key, m)


def test_runs_json_is_strict_and_round_trips(runs):
    a, b = runs
    text = compare.runs_json(runs, ["R@1", "AUC"], reference=b.id)
    data = compare.read_runs_json(text)
    json.loads(text, parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))
    assert [r["settings"] for r in data["runs"]] == [dict(a.settings), dict(b.settings)]
    assert data["differing_settings"] == ["descriptor", "tolerance"]
    assert data["comparison"]["reference"] == b.id
    table = compare.metric_table(runs, ["R@1", "AUC"], reference=b.id)
    for want, got in zip(table, data["comparison"]["rows"]):
        assert {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in want.items()} == got
    ev = data["runs"][1]["evaluation"]
    assert ev["methods"][0]["recall"]["1"]["mean"] == 0.85 and ev["pr"][0]["auc"] == 0.75
    with pytest.raises(VPRInputError, match="not a runs export"):
        compare.read_runs_json('{"rows": []}')


def test_overlaid_curves_are_each_runs_curves(runs):
    a, b = runs
    fig = compare_plots.pr_overlay(runs, "place-baseline")
    curve = a.evaluation.pr_curves["global θ"]
    line = next(t for t in fig.data if t.meta == f"pr {a.id}")
    np.testing.assert_allclose(line.x, curve.recall)
    np.testing.assert_allclose(line.y, curve.precision)
    own = next(t for t in fig.data if t.meta == f"own {b.id}")
    assert (own.x[0], own.y[0]) == (0.6, 0.75)
    fig = compare_plots.pr_overlay(runs, "margin-weighted")  # no PR rows for it: both runs named as missing
    assert not fig.data and a.name in fig.layout.annotations[0].text
    t = [TradeoffRow("θ_p(k) weighted", "margin", k, (r, 0.0), (j, 0.0), (0.9, 0.0), (0.5, 0.0))
         for k, r, j in ((0.0, 0.8, 0.3), (1.0, 0.6, 0.7))]
    open_set = compare.record(_evaluation(Protocol.OPEN_SET, SETTINGS, a.evaluation.rows, tradeoff=t), run_id="run 3")
    fig = compare_plots.tradeoff_overlay((*runs, open_set))
    line = next(x for x in fig.data if x.meta == "tradeoff run 3")
    assert list(line.x) == [0.3, 0.7] and list(line.y) == [0.8, 0.6]
    assert next(x for x in fig.data if x.meta == "k0 run 3").x[0] == 0.3
    assert "not an open-set run" in fig.layout.annotations[0].text





# --------------------------------------------------------------------------- over splits


def _split_row(key: str, r1: tuple[float, ...], precision: tuple[float, ...]) -> MethodRow:
    return MethodRow(key=key, label=key, source="", recall={1: (float(np.mean(r1)), float(np.std(r1)))},
                     accepted=(1.0, 0.0), precision=(float(np.nanmean(precision)), 0.0),
                     per_split={"recall@1": r1, "accepted": (1.0,) * len(r1), "precision": precision})


@pytest.fixture
def split_runs():
    """Two paper runs of the same splits (tolerance 0 and 1) and one of another seed, with per-split values."""
    pr = [_pr("place-baseline", "place-level baseline", 0.5, 0.2, 0.6)]
    made = []
    for settings, shift in (({}, 0.0), ({"tolerance": 1}, 0.05), ({"seed": 1}, 0.02)):
        r1 = tuple(x + shift for x in (0.6, 0.7, 0.8, 0.55))
        made.append(_evaluation(Protocol.PAPER, {**SETTINGS, "runs": 4, **settings},
                                [_split_row("place-baseline", r1, (r1[0], math.nan, *r1[2:]))], pr))
    kept: tuple = ()
    for ev in made:
        kept = compare.add_run(kept, compare.record(ev, run_id=compare.next_id(kept, 0)))
    return kept


def test_metric_stats_hold_summaries_and_paired_or_welch_differences(split_runs):
    a, b, c = split_runs
    rows = compare.metric_stats(split_runs, ["R@1", "precision", "AUC"])
    table = compare.metric_table(split_runs, ["R@1", "precision", "AUC"])
    assert [list(r) for r in rows] == [list(r) for r in table]  # the same cells
    r1 = rows[0]
    s = r1[a.name]
    assert s.n == 4 and s.mean == pytest.approx(np.mean([0.6, 0.7, 0.8, 0.55]))
    assert s.std == pytest.approx(np.std([0.6, 0.7, 0.8, 0.55], ddof=1))
    same = r1[compare.difference_column(b, a)]
    assert same.paired and same.mean == pytest.approx(0.05) and same.p == 0.0  # +0.05 on every split
    other = r1[compare.difference_column(c, a)]
    assert not other.paired and "seed 1 vs 0" in other.note
    assert other.mean == pytest.approx(0.02) and other.mean == pytest.approx(table[0][compare.difference_column(c, a)])
    prec = rows[1][a.name]
    assert prec.n == 3  # the split with no precision (nothing accepted) is left out
    auc = rows[2]
    assert auc[a.name].n == 1 and auc[a.name].note == compare.POOLED and math.isnan(auc[a.name].std)
    assert "pooled" in auc[compare.difference_column(b, a)].note
    assert compare.splits_note(split_runs) == [f"{b.name} − {a.name}: the same splits, paired",
                                               f"{c.name} − {a.name}: splits differ (seed 1 vs 0): Welch's t-test, "
                                               "unpaired"]
    # a hand-built run without per-split values says so, never an interval it cannot have
    assert "no per-split values" in compare.record(_evaluation(Protocol.PAPER, SETTINGS, [
        _row("place-baseline", "place-level baseline", 0.6, 0.6)]), run_id="x").summary("R@1", "place-baseline").note


def test_runs_csv_and_json_carry_std_and_interval(split_runs):
    a = split_runs[0]
    text = compare.runs_csv(split_runs, ["R@1", "precision", "AUC"])
    header = next(csv.reader(io.StringIO(text)))
    assert header[-15:] == [c for m in ("R@1", "precision", "AUC") for c in (m, *(f"{m} {x}" for x in
                                                                                  compare.STAT_COLUMNS))]
    line = next(r for r in compare.read_runs_csv(text) if r["run"] == a.id)
    s = a.summary("R@1", "place-baseline")
    assert (line["R@1"], line["R@1 std"], line["R@1 n"], line["R@1 ci95 low"], line["R@1 ci95 high"]) == \
        pytest.approx((s.mean, s.std, 4, s.low, s.high))
    assert line["AUC"] == 0.5 and line["AUC n"] == 1 and math.isnan(line["AUC std"])
    data = compare.read_runs_json(compare.runs_json(split_runs, ["R@1"]))
    stat = data["comparison"]["statistics"][0]
    assert stat[a.name]["std"] == pytest.approx(s.std) and stat[a.name]["ci95_low"] == pytest.approx(s.low)
    diff = stat[compare.difference_column(split_runs[1], a)]
    assert diff["paired"] is True and diff["mean"] == pytest.approx(0.05)
    assert data["per_split"][0]["methods"]["place-baseline"]["precision"][1] is None  # NaN in strict JSON
    assert data["comparison"]["splits"][1].startswith(f"{split_runs[2].name} − {a.name}: splits differ")
