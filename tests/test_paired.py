"""Numbers over splits (``protocols.paired``) and runs compared split by split (``compare.same_splits``,
``difference``, ``method_difference``): plain formulas, scipy, hand cases, real GardensPoint runs, and the
Evaluation page's runs side by side under AppTest.

The references are written here from the definitions: the sample std as √(Σ(xᵢ − x̄)²/(n − 1)) by a loop,
the t statistic and its two-sided p = 2·(1 − F(|t|)) from ``scipy.stats.t``'s distribution function, Welch's
degrees of freedom from the Welch–Satterthwaite formula; then scipy's own tests on the same numbers.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats as sps
from streamlit.testing.v1 import AppTest

from test_app import assert_clean, downloads, fresh_caches, navigation_mode, page  # noqa: F401  (fixtures)
from vpr_explorer.app import ENTRY
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import PlaceSpec, make_places
from vpr_explorer.protocols import compare, paired
from vpr_explorer.protocols.evaluation import Evaluation, MethodRow, Protocol, draw_splits

RNG = np.random.default_rng(7)


# --------------------------------------------------------------------------- plain references


def plain_summary(x: list[float]) -> tuple[float, float, float, float]:
    """mean, sample std (a loop), and the 95% t interval of the mean."""
    n = len(x)
    mean = sum(x) / n
    ss = 0.0
    for v in x:
        ss += (v - mean) ** 2
    sd = math.sqrt(ss / (n - 1))
    half = sps.t.ppf(0.975, n - 1) * sd / math.sqrt(n)
    return mean, sd, mean - half, mean + half


def plain_paired(a: list[float], b: list[float]) -> tuple[float, float, float, float, float]:
    """d̄, s_d, the interval of d̄, and the two-sided p of t = d̄/(s_d/√n) with n − 1 degrees of freedom."""
    d = [x - y for x, y in zip(a, b)]
    mean, sd, low, high = plain_summary(d)
    t = mean / (sd / math.sqrt(len(d)))
    return mean, sd, low, high, 2 * (1 - sps.t.cdf(abs(t), len(d) - 1))


def plain_welch(a: list[float], b: list[float]) -> tuple[float, float, float, float]:
    """x̄_a − x̄_b, Welch–Satterthwaite df, its 95% interval and Welch's two-sided p."""
    ma, sa, _, _ = plain_summary(a)
    mb, sb, _, _ = plain_summary(b)
    va, vb = sa**2 / len(a), sb**2 / len(b)
    se = math.sqrt(va + vb)
    df = (va + vb) ** 2 / (va**2 / (len(a) - 1) + vb**2 / (len(b) - 1))
    diff = ma - mb
    half = sps.t.ppf(0.975, df) * se
    return diff, df, diff - half, diff + half, 2 * (1 - sps.t.cdf(abs(diff / se), df))


# --------------------------------------------------------------------------- against the formulas and scipy


@pytest.mark.parametrize("n", [2, 3, 5, 20, 50])
def test_summary_is_the_sample_std_and_the_t_interval(n):
    x = list(RNG.uniform(0.3, 0.9, n))
    s = paired.summary(x)
    mean, sd, low, high = plain_summary(x)
    assert s.n == n
    assert s.mean == pytest.approx(mean, abs=1e-15) and s.std == pytest.approx(sd, rel=1e-12)
    assert (s.low, s.high) == pytest.approx((low, high), rel=1e-12)
    lo, hi = sps.t.interval(0.95, n - 1, loc=np.mean(x), scale=sps.sem(x))  # scipy on the same numbers
    assert (s.low, s.high) == pytest.approx((lo, hi), rel=1e-12)
    assert s.std == pytest.approx(np.std(x, ddof=1), rel=1e-12)


@pytest.mark.parametrize("n", [2, 4, 10, 50])
def test_paired_difference_interval_and_p_value(n):
    a = RNG.uniform(0.4, 0.9, n)
    b = a - RNG.normal(0.03, 0.05, n)
    d = paired.paired(a, b)
    mean, sd, low, high, p = plain_paired(list(a), list(b))
    assert d.paired and d.n == n and d.df == n - 1
    assert d.mean == pytest.approx(mean, abs=1e-15) and d.std == pytest.approx(sd, rel=1e-12)
    assert (d.low, d.high) == pytest.approx((low, high), rel=1e-12)
    assert d.p == pytest.approx(p, rel=1e-9, abs=1e-15)
    ref = sps.ttest_rel(a, b)
    assert d.p == pytest.approx(ref.pvalue, rel=1e-12)
    ci = ref.confidence_interval(0.95)
    assert (d.low, d.high) == pytest.approx((ci.low, ci.high), rel=1e-12)
    assert d.note == f"paired over {n} splits" and not d.identical


@pytest.mark.parametrize("na, nb", [(2, 2), (3, 7), (20, 5), (50, 50)])
def test_welch_difference_interval_and_p_value(na, nb):
    a, b = RNG.uniform(0.4, 0.9, na), RNG.uniform(0.3, 0.8, nb)
    d = paired.welch(a, b)
    diff, df, low, high, p = plain_welch(list(a), list(b))
    assert not d.paired and d.n == (na, nb)
    assert d.mean == pytest.approx(diff, abs=1e-15) and d.df == pytest.approx(df, rel=1e-12)
    assert (d.low, d.high) == pytest.approx((low, high), rel=1e-12)
    assert d.p == pytest.approx(p, rel=1e-9, abs=1e-15)
    ref = sps.ttest_ind(a, b, equal_var=False)
    assert d.p == pytest.approx(ref.pvalue, rel=1e-12) and d.df == pytest.approx(ref.df, rel=1e-12)
    ci = ref.confidence_interval(0.95)
    assert (d.low, d.high) == pytest.approx((ci.low, ci.high), rel=1e-12)
    assert d.note.startswith("splits differ") and d.tag == "splits differ"


# --------------------------------------------------------------------------- hand cases


def test_two_splits_by_hand():
    # d = (0.25, 0.5): d̄ = 0.375, s_d = √((0.125² + 0.125²)/1) = 0.125·√2, SE = 0.125, t = 3 with 1 df.
    # t with 1 df is Cauchy: F(t) = 1/2 + atan(t)/π, so p = 1 − 2·atan(3)/π; t₀.₉₇₅,₁ = tan(0.475π).
    d = paired.paired([0.5, 0.75], [0.25, 0.25])
    assert d.mean == 0.375 and d.std == pytest.approx(0.125 * math.sqrt(2)) and d.se == pytest.approx(0.125)
    assert d.p == pytest.approx(1 - 2 * math.atan(3) / math.pi, rel=1e-12)
    half = math.tan(0.475 * math.pi) * 0.125
    assert (d.low, d.high) == pytest.approx((0.375 - half, 0.375 + half), rel=1e-12)
    s = paired.summary([0.5, 0.75])  # mean 0.625, std √(2·0.125²) = 0.1768
    assert (s.mean, s.std) == pytest.approx((0.625, 0.125 * math.sqrt(2)))
    assert s.high - s.mean == pytest.approx(math.tan(0.475 * math.pi) * 0.125)
    assert s.text() == "0.625 ± 0.177 [95% -0.963, 2.213]"  # the t interval is not cut to [0, 1]


@pytest.mark.filterwarnings("ignore:Precision loss occurred:RuntimeWarning")  # scipy's own, on the references
def test_every_split_the_same_difference_and_no_difference():
    a, b = np.array([0.7, 0.65, 0.8, 0.35]), np.array([0.6, 0.55, 0.7, 0.25])
    same = paired.paired(a, b)  # 0.1 on every split in exact arithmetic; float rounding leaves 1.1e-16 of spread,
    assert 0 < np.ptp(a - b) < 1e-15  # which scipy divides by (t = 3.6e15): why the tolerance exists
    assert same.mean == pytest.approx(0.1) and same.std == 0.0 and (same.low, same.high) == pytest.approx((0.1, 0.1))
    assert same.p == 0.0 and same.note == "the same difference on all 4 splits" and not same.identical
    assert sps.ttest_rel([1.0, 1.0, 1.0], [0.0, 0.0, 0.0]).pvalue == 0.0  # scipy's answer on exact constants
    none = paired.paired(a, a.copy())
    assert none.identical and none.note == paired.IDENTICAL and none.mean == 0.0 and math.isnan(none.p)
    assert none.text() == "+0.000 [95% +0.000, +0.000] (identical on every split)"
    assert math.isnan(sps.ttest_rel(a, a.copy()).pvalue)  # undefined: 0/0


def test_zero_variance_one_value_and_missing_values():
    flat = paired.summary([0.5, 0.5, 0.5])
    assert flat.std == 0.0 and (flat.low, flat.high) == (0.5, 0.5)
    one = paired.summary([0.4])
    assert one.n == 1 and math.isnan(one.std) and math.isnan(one.low) and one.text() == "0.400 (1 split)"
    assert paired.summary([math.nan, math.nan]) is paired.NO_SUMMARY and paired.NO_SUMMARY.text() == "—"
    # NaN (a split where the rate is undefined) is left out, pair by pair
    d = paired.paired([0.5, math.nan, 0.7, 0.9], [0.4, 0.5, math.nan, 0.7])
    assert d.n == 2 and d.mean == pytest.approx(0.15) and d.p == pytest.approx(sps.ttest_rel([0.5, 0.9],
                                                                                            [0.4, 0.7]).pvalue)
    single = paired.paired([0.5], [0.4])
    assert single.n == 1 and math.isnan(single.p) and "one split" in single.note
    assert math.isnan(paired.paired([math.nan], [0.4]).mean)
    w = paired.welch([0.5], [0.4, 0.6])
    assert w.mean == pytest.approx(0.0) and math.isnan(w.p) and "one split on a side" in w.note
    flat = paired.welch([0.5, 0.5], [0.4, 0.4])
    assert flat.mean == pytest.approx(0.1) and math.isnan(flat.p) and "no spread" in flat.note
    with pytest.raises(VPRInputError, match="not the same splits"):
        paired.paired([0.1, 0.2], [0.1])
    with pytest.raises(VPRInputError, match="1-D"):
        paired.summary([[0.1, 0.2]])


def test_texts():
    d = paired.paired([0.5, 0.75, 0.6], [0.25, 0.25, 0.4])
    assert d.text().endswith("(paired over 3 splits)") and d.text(short=True).endswith("(paired)")
    assert d.text(100, 1).startswith("+31.7 [95% ")
    w = paired.welch([0.5, 0.75, 0.6], [0.25, 0.25, 0.4, 0.3])
    assert "p = " in w.text() and w.text(short=True).endswith("(splits differ)")
    assert paired.single(0.74, "pooled over the splits").text() == "0.740 (pooled over the splits)"


# --------------------------------------------------------------------------- which runs are paired


def _run(run_id: str, **settings) -> compare.RunRecord:
    base = {"dataset": "GardensPointWalking", "descriptor": "pixels", "places": "20 places × 9 images",
            "group": 3, "step": 10, "reading": "stride", "runs": 3, "seed": 0, "cross_condition": False,
            "tolerance": 0}
    values = {"place-baseline": (0.6, 0.7, 0.8), "margin-weighted": (0.65, 0.7, 0.9)}
    rows = [MethodRow(key=k, label=k, source="", recall={1: (float(np.mean(v)), float(np.std(v)))},
                      accepted=(1.0, 0.0), precision=(float(np.mean(v)), 0.0),
                      per_split={"recall@1": v, "accepted": (1.0,) * 3, "precision": v}) for k, v in values.items()]
    protocol = Protocol(settings.pop("protocol", "paper"))
    ev = Evaluation(protocol=protocol, settings={**base, **settings}, ks=(1,), rows=tuple(rows))
    return compare.record(ev, run_id=run_id)


def test_same_seed_runs_and_places_are_paired_else_marked():
    a = _run("run 1")
    for other in (_run("run 2", descriptor="efficientnet-lite0"), _run("run 2", tolerance=2),
                  _run("run 2", cross_condition=True), _run("run 2", theta=0.5)):
        assert compare.same_splits(other, a) == (True, "")  # what the splits do not depend on
        d = compare.difference(other, a, "R@1", "margin-weighted")
        assert d.paired and d.identical
    for changes, why in (({"seed": 1}, "seed 1 vs 0"), ({"runs": 5}, "runs 5 vs 3"),
                         ({"group": 2, "places": "30 places × 6 images"}, "places"),
                         ({"reading": "skip"}, "reading skip vs stride"),
                         ({"dataset": "Nordland"}, "dataset Nordland vs GardensPointWalking"),
                         ({"protocol": "open-set", "unknown_share": 0.3}, "protocol open-set vs paper")):
        other = _run("run 2", **changes)
        same, said = compare.same_splits(other, a)
        assert not same and why in said, (changes, said)
        d = compare.difference(other, a, "R@1", "margin-weighted")
        assert not d.paired and f"splits differ ({said})" in d.note and d.tag == "splits differ"
        assert d.p == pytest.approx(sps.ttest_ind([0.65, 0.7, 0.9], [0.65, 0.7, 0.9], equal_var=False).pvalue)
    open_a = _run("run 3", protocol="open-set", unknown_share=0.3)
    assert not compare.same_splits(_run("run 4", protocol="open-set", unknown_share=0.5), open_a)[0]
    assert compare.same_splits(_run("run 4", protocol="open-set", unknown_share=0.3), open_a)[0]
    # two methods of one run: always paired
    m = compare.method_difference(a, "R@1", "margin-weighted", "place-baseline")
    assert m.paired and m.n == 3 and m.mean == pytest.approx(0.05)
    assert m.p == pytest.approx(sps.ttest_rel([0.65, 0.7, 0.9], [0.6, 0.7, 0.8]).pvalue)
    # a pooled metric, or a row recorded without per-split values: the difference of the numbers, no test
    assert "no per-split values" in compare.difference(
        compare.record(Evaluation(Protocol.PAPER, dict(a.settings), (1,), tuple(
            MethodRow(r.key, r.label, "", r.recall, r.accepted, r.precision) for r in a.evaluation.rows)),
            run_id="run 9"), a, "R@1", "place-baseline").note


# --------------------------------------------------------------------------- real GardensPoint runs


RUNS = 8


@pytest.fixture(scope="module")
def gp_runs(gardens_point, gp_pixels):
    """Paper protocol, group 3 step 10: seed 0, seed 0 with tolerance 1, seed 1, and seed 0 with 5 runs."""
    from vpr_explorer.pipeline import run_protocol

    places = make_places(gardens_point, PlaceSpec(3, 10))
    kept: tuple = ()
    for options in (dict(seed=0), dict(seed=0, tolerance=1), dict(seed=1), dict(seed=0, runs=5)):
        ev = run_protocol(Protocol.PAPER, gardens_point, places, gp_pixels, pr=True, settings={"descriptor": "pixels"},
                          **{"runs": RUNS, **options})
        kept = compare.add_run(kept, compare.record(ev, run_id=compare.next_id(kept, 0)))
    return kept, places


@pytest.mark.realdata
def test_per_split_values_are_what_the_means_summarise(gp_runs):
    runs, _ = gp_runs
    for r in runs:
        for row in r.evaluation.rows:
            assert len(row.per_split["recall@1"]) == r.settings["runs"]
            for metric, name in (("R@1", "recall@1"), ("precision", "precision"), ("R@5", "recall@5")):
                values = np.asarray(row.per_split[name])
                s = r.summary(metric, row.key)
                assert s.mean == r.value(metric, row.key)  # exactly the mean the row reports
                assert s.std == pytest.approx(np.std(values[np.isfinite(values)], ddof=1), abs=1e-15)
            # one convention: the row's own std is the sample std (ddof 1), as the comparison's
            assert row.recall[1][1] == pytest.approx(np.std(row.per_split["recall@1"], ddof=1), abs=1e-15)
            assert row.recall[1][1] == pytest.approx(r.summary("R@1", row.key).std, abs=1e-15)


@pytest.mark.realdata
def test_raw_weighted_against_the_place_level_on_real_splits(gp_runs):
    runs, _ = gp_runs
    run = runs[0]
    # the raw rule ranks places by raw_p, as the place level does: Recall@1 is the same on every split
    d = compare.method_difference(run, "R@1", "raw-weighted", "place-baseline")
    a = run.splits("R@1", "raw-weighted")
    b = run.splits("R@1", "place-baseline")
    assert np.array_equal(a, b) and d.identical and math.isnan(d.p) and d.n == RUNS
    # the margin rule reorders places: a real paired difference, checked against the formula and scipy
    a = run.splits("R@1", "margin-weighted")
    d = compare.method_difference(run, "R@1", "margin-weighted", "place-baseline")
    mean, sd, low, high, p = plain_paired(list(a), list(b))
    assert np.ptp(a - b) > 0
    assert (d.mean, d.std, d.low, d.high) == pytest.approx((mean, sd, low, high), rel=1e-12, abs=1e-15)
    assert d.p == pytest.approx(p, rel=1e-9) and d.p == pytest.approx(sps.ttest_rel(a, b).pvalue, rel=1e-12)
    assert d.mean == pytest.approx(run.value("R@1", "margin-weighted") - run.value("R@1", "place-baseline"))


@pytest.mark.realdata
def test_same_seed_runs_score_the_same_splits_and_are_compared_pair_by_pair(gp_runs, gardens_point):
    runs, places = gp_runs
    base, tolerant, other_seed, fewer = runs
    # the detection is right: the same seed and runs draw the same query images; another seed others
    same = draw_splits(places.image_place, places.n_places, runs=RUNS, seed=0)
    again = draw_splits(places.image_place, places.n_places, runs=RUNS, seed=0)
    other = draw_splits(places.image_place, places.n_places, runs=RUNS, seed=1)
    assert all(np.array_equal(x.queries, y.queries) for x, y in zip(same, again))
    assert not all(np.array_equal(x.queries, y.queries) for x, y in zip(same, other))
    assert compare.same_splits(tolerant, base) == (True, "")
    d = compare.difference(tolerant, base, "R@1", "margin-weighted")
    a, b = tolerant.splits("R@1", "margin-weighted"), base.splits("R@1", "margin-weighted")
    assert d.paired and d.n == RUNS
    if np.ptp(a - b) > 1e-12:
        assert d.p == pytest.approx(sps.ttest_rel(a, b).pvalue, rel=1e-12)
    else:
        assert d.identical or d.p == 0.0
    assert np.all(a >= b)  # a tolerance only adds right places
    for run, why in ((other_seed, "seed 1 vs 0"), (fewer, "runs 5 vs 8")):
        d = compare.difference(run, base, "R@1", "margin-weighted")
        assert not d.paired and why in d.note
        x, y = run.splits("R@1", "margin-weighted"), base.splits("R@1", "margin-weighted")
        assert d.p == pytest.approx(sps.ttest_ind(x, y, equal_var=False).pvalue, rel=1e-12)
    notes = compare.splits_note(runs)
    assert notes[0].endswith("the same splits, paired") and "splits differ (seed 1 vs 0)" in notes[1]
    # pooled numbers: one value each, no test
    auc = compare.difference(tolerant, base, "AUC", "margin-weighted")
    assert math.isnan(auc.p) and "pooled" in auc.note and auc.tag == "pooled, no test"


# --------------------------------------------------------------------------- runs side by side on the page


def _run_form(at: AppTest, **values) -> AppTest:
    for key, value in values.items():
        widget = next(w for kind in ("radio", "slider", "number_input", "checkbox")
                      for w in at.get(kind) if getattr(w, "key", None) == key)
        widget.set_value(value)
    at.button[0].click()
    return at.run()


def _shown(frame):
    """What a styled dataframe shows (its display values), as text."""
    import pyarrow as pa

    return pa.ipc.open_stream(frame.proto.arrow_data.styler.display_values).read_all().to_pandas()


def test_runs_side_by_side_show_intervals_and_paired_differences(downloads):
    at = AppTest.from_file(str(ENTRY), default_timeout=60)
    at = page(at.run(), "evaluation")  # run 1: the paper protocol, its default 20 runs, seed 0
    at = _run_form(at, w_protocol="paper", w_tolerance=1)  # run 2: the same splits
    at = _run_form(at, w_protocol="paper", w_tolerance=0, w_seed=1)  # run 3: other splits
    assert_clean(at)
    kept = at.session_state["eval_kept_runs"]
    assert [r.id for r in kept] == ["run 1", "run 2", "run 3"]
    table = next(d for d in at.dataframe if "key" in d.value.columns and "metric" in d.value.columns)
    numbers, shown = table.value, _shown(table)
    i = int(np.flatnonzero((numbers["key"] == "margin-weighted") & (numbers["metric"] == "R@1"))[0])
    s = kept[0].summary("R@1", "margin-weighted")
    assert numbers[kept[0].name][i] == pytest.approx(s.mean)  # the cell holds the mean, shows its spread
    assert shown[kept[0].name][i] == s.text() and " ± " in s.text() and "[95% " in s.text()
    paired_col = compare.difference_column(kept[1], kept[0])
    welch_col = compare.difference_column(kept[2], kept[0])
    assert shown[paired_col][i] == compare.difference(kept[1], kept[0], "R@1", "margin-weighted").text(short=True)
    assert shown[welch_col][i].endswith("(splits differ)") and "p = " in shown[welch_col][i]
    captions = " ".join(c.value for c in at.caption)
    assert f"{kept[1].name} − {kept[0].name}: the same splits, paired" in captions
    assert f"{kept[2].name} − {kept[0].name}: splits differ (seed 1 vs 0)" in captions
    # the paired difference of two methods, run by run
    diff = next(d for d in at.dataframe if "Δ of" in d.value.columns)
    assert at.selectbox(key="w_paired_a").value == "raw-weighted"
    assert at.selectbox(key="w_paired_b").value == "place-baseline"
    row = int(np.flatnonzero(diff.value["Δ of"] == "R@1")[0])
    want = compare.method_difference(kept[0], "R@1", "raw-weighted", "place-baseline")
    assert _shown(diff)[kept[0].name][row] == want.text(short=True)
    at.selectbox(key="w_paired_a").set_value("margin-weighted").run()
    diff = next(d for d in at.dataframe if "Δ of" in d.value.columns)
    want = compare.method_difference(kept[0], "R@1", "margin-weighted", "place-baseline")
    assert diff.value[kept[0].name][row] == pytest.approx(want.mean)
    assert "paired" in _shown(diff)[kept[0].name][row] or "identical" in _shown(diff)[kept[0].name][row]
    # the CSV: every metric's std, count and interval beside its mean
    button = next(b for b in at.get("download_button") if b.proto.label == "Download runs (CSV)")
    rows = compare.read_runs_csv(downloads(button).decode())
    line = next(r for r in rows if r["run"] == "run 1" and r["method"] == "margin-weighted")
    assert line["R@1 std"] == pytest.approx(s.std) and line["R@1 n"] == s.n
    assert (line["R@1 ci95 low"], line["R@1 ci95 high"]) == pytest.approx((s.low, s.high))
