"""Precision–recall curves: a hand-counted case, sklearn as the independent reference, the
per-place family against a loop re-running ``score_queries`` at every k."""

import math

import numpy as np
import pytest
from sklearn.metrics import auc, precision_recall_curve

from reference import unit_rows
from vpr_explorer.errors import VPRInputError
from vpr_explorer.protocols.evaluation import draw_splits, run_split
from vpr_explorer.protocols.options import ProtocolOptions
from vpr_explorer.protocols.precision_recall import (
    GLOBAL_CURVE,
    IMAGE_CURVE,
    PRSplit,
    curve_from_counts,
    family_counts,
    family_curve_name,
    family_grid,
    family_pr,
    family_range,
    operating_point,
    pool_points,
    pooled_family_pr,
    pr_curve,
    pr_rows,
)
from vpr_explorer.method.retrieval import TIE_TOLERANCE, Method, Rule, score_queries, similarity
from vpr_explorer.method.thresholds import threshold_family

# Six queries; C and D tie at 0.7 (accepted together).
#      A     B     C     D     E     F
SCORE = np.array([0.9, 0.8, 0.7, 0.7, 0.5, 0.3])
RIGHT = np.array([True, False, True, False, True, False])
KNOWN = np.array([True, True, True, False, True, False])  # D, F: places not in the database


def test_hand_counted_curve():
    c = pr_curve(SCORE, RIGHT, KNOWN)
    # n_known = 4 (A B C E), n_unknown = 2 (D F)
    # θ      accepted        TP  FP   precision  recall
    # +inf   —                0   0   1 (conv.)  0
    # 0.9    A                1   0   1          1/4
    # 0.8    A B              1   1   1/2        1/4    B: known, wrong top-1: FP (and a miss)
    # 0.7    A B C D          2   2   1/2        2/4    D: unknown, accepted: FP
    # 0.5    A B C D E        3   2   3/5        3/4
    # 0.3    all six          3   3   1/2        3/4    F: unknown, accepted: FP
    assert (c.n_known, c.n_unknown, c.param) == (4, 2, "θ")
    np.testing.assert_array_equal(c.threshold, [np.inf, 0.9, 0.8, 0.7, 0.5, 0.3])
    np.testing.assert_array_equal(c.accepted, [0, 1, 2, 4, 5, 6])
    np.testing.assert_array_equal(c.tp, [0, 1, 1, 2, 3, 3])
    np.testing.assert_allclose(c.precision, [1, 1, 1 / 2, 1 / 2, 3 / 5, 1 / 2])
    np.testing.assert_allclose(c.recall, [0, 1 / 4, 1 / 4, 2 / 4, 3 / 4, 3 / 4])
    # AUC, trapezoids over recall: 1/4·(1+1)/2 + 0 + 1/4·(1/2+1/2)/2 + 1/4·(1/2+3/5)/2 + 0
    #                            = 0.25 + 0.125 + 0.1375 = 0.5125
    assert c.auc == pytest.approx(0.5125, abs=1e-15)
    assert c.r_at_100p == 0.25 and c.r_at_99p == 0.25
    # F1 = 2·TP / (accepted + n_known): 0, 2/5, 2/6, 4/8, 6/9, 6/10 → max 2/3 at θ = 0.5
    assert c.max_f1 == pytest.approx(2 / 3) and c.max_f1_threshold == 0.5
    p = c.point(0.75)  # accepts score ≥ 0.75: A, B
    assert (p.accepted, p.tp, p.precision, p.recall) == (2, 1, 0.5, 0.25)
    assert c.point(1.0).accepted == 0 and c.point(-5.0).accepted == 6


def test_recall_at_99_precision_is_counted_in_integers():
    # 150 right, then 1 wrong, then 50 right, all known: at 201 accepted precision is 200/201 ≥ 0.99
    right = np.r_[np.ones(150, bool), False, np.ones(50, bool)]
    c = pr_curve(np.linspace(1, 0, len(right)), right, np.ones(len(right), bool))
    assert c.r_at_100p == pytest.approx(150 / 201)
    assert c.r_at_99p == pytest.approx(200 / 201)


def _sklearn_check(score, right, known):
    """Points, precision, recall and AUC against sklearn (``y_true = right``)."""
    c = pr_curve(score, right, known)
    sk_p, sk_r, sk_t = precision_recall_curve(right.astype(int), score)
    # sklearn: thresholds increasing, the start point (P 1, R 0) last; ours: decreasing, first
    np.testing.assert_array_equal(c.threshold[1:], sk_t[::-1])
    np.testing.assert_allclose(c.precision, sk_p[::-1], rtol=0, atol=1e-15)
    # sklearn's recall is over the right queries, ours over the known ones
    scale = right.sum() / known.sum()
    np.testing.assert_allclose(c.recall, sk_r[::-1] * scale, rtol=1e-14, atol=0)
    assert c.auc == pytest.approx(auc(sk_r, sk_p) * scale, rel=1e-12)
    return c


@pytest.mark.parametrize("seed", range(5))
def test_equals_sklearn_with_every_query_known(seed):
    rng = np.random.default_rng(seed)
    n = 300
    score = np.round(rng.random(n), 2)  # two decimals: many ties in score
    right = rng.random(n) < 0.3 + 0.6 * score  # higher scores are right more often
    _sklearn_check(score, right, np.ones(n, bool))


def test_unknown_queries_accepted_are_false_positives():
    rng = np.random.default_rng(7)
    n = 200
    score = rng.random(n)
    known = rng.random(n) < 0.7
    right = known & (rng.random(n) < 0.3 + 0.6 * score)
    c = _sklearn_check(score, right, known)
    # Where the definitions part: sklearn with y_true = right counts recall over the right
    # queries only (it has no notion of "known but answered wrong"), so its last recall is 1;
    # here it is the share of known queries answered right, Recall@1 over known queries.
    assert c.recall[-1] == pytest.approx(right.sum() / known.sum()) and c.recall[-1] < 1
    # An unknown query is never in recall's denominator but always a false positive when
    # accepted: it moves precision only. sklearn with y_true = known (a tempting mistake)
    # would count an accepted known query with a wrong top-1 as a true positive:
    hand = pr_curve(SCORE, RIGHT, KNOWN)
    sk_p, _, sk_t = precision_recall_curve(KNOWN.astype(int), SCORE)
    assert sk_p[list(sk_t).index(0.8)] == 1.0 and hand.point(0.8).precision == 0.5
    # and adding an accepted unknown query changes precision and nothing else
    more = pr_curve(np.r_[SCORE, 0.95], np.r_[RIGHT, False], np.r_[KNOWN, False])
    assert (more.n_known, more.n_unknown) == (4, 3)
    assert more.point(0.9).precision == 0.5 and more.point(0.9).recall == 0.25


def test_ties_in_score_are_accepted_together_whatever_the_order():
    rng = np.random.default_rng(3)
    score = np.repeat([0.9, 0.7, 0.4], 4)
    right = rng.random(12) < 0.5
    known = right | (rng.random(12) < 0.5)
    c = pr_curve(score, right, known)
    np.testing.assert_array_equal(c.threshold, [np.inf, 0.9, 0.7, 0.4])  # one point per distinct score
    for _ in range(5):
        perm = rng.permutation(12)
        d = pr_curve(score[perm], right[perm], known[perm])
        for f in ("threshold", "tp", "accepted"):
            np.testing.assert_array_equal(getattr(d, f), getattr(c, f))
        assert (d.auc, d.max_f1, d.max_f1_threshold) == (c.auc, c.max_f1, c.max_f1_threshold)
    # a threshold comparison is exact: scores within TIE_TOLERANCE are still two thresholds
    near = pr_curve(np.array([0.7, 0.7 - TIE_TOLERANCE / 2]), np.array([False, True]), np.array([True, True]))
    np.testing.assert_array_equal(near.accepted, [0, 1, 2])
    assert near.r_at_100p == 0.0  # the first accepted answer is wrong


def test_max_f1_ties_go_to_the_highest_threshold():
    # F1 = 2·TP/(accepted + 2): θ 0.9 → 2/3, 0.8 → 1/2, 0.7 → 2/5, 0.6 → 4/6 = 2/3: the highest θ wins
    flags = np.array([True, False, False, True])  # right = known: B and C are unknown places
    c = pr_curve(np.array([0.9, 0.8, 0.7, 0.6]), flags, flags)
    assert c.max_f1 == pytest.approx(2 / 3) and c.max_f1_threshold == 0.9


def test_never_accepted_queries_and_no_known_query():
    c = pr_curve(np.array([0.8, -np.inf]), np.array([True, False]), np.array([True, True]))
    np.testing.assert_array_equal(c.threshold, [np.inf, 0.8])  # -inf is never a threshold
    assert c.recall[-1] == 0.5  # the never-accepted known query is a miss
    none = pr_curve(np.array([0.5, 0.4]), np.array([False, False]), np.array([False, False]))
    assert math.isnan(none.auc) and math.isnan(none.r_at_100p) and none.precision[-1] == 0.0
    empty = pr_curve(np.array([]), np.array([], bool), np.array([], bool))
    assert len(empty.threshold) == 1 and math.isnan(empty.max_f1)


def test_bad_input_is_named():
    with pytest.raises(VPRInputError, match="right but not known"):
        pr_curve(SCORE, RIGHT | ~KNOWN, KNOWN)
    with pytest.raises(VPRInputError, match="NaN"):
        pr_curve(np.r_[SCORE[:-1], np.nan], RIGHT, KNOWN)
    with pytest.raises(VPRInputError, match="flags"):
        pr_curve(SCORE[:-1], RIGHT, KNOWN)
    with pytest.raises(VPRInputError, match="bool"):
        pr_curve(SCORE, RIGHT.astype(int), KNOWN)
    with pytest.raises(VPRInputError, match="accept nothing"):
        curve_from_counts("θ", [1.0], [1], [1], 1, 0)
    with pytest.raises(VPRInputError, match="not a point"):
        family_pr(np.zeros((1, 2)), 0.0, 1.0, np.array([[True, False]]), Rule.RAW, ks=[0.0]).point(0.5)
    with pytest.raises(VPRInputError, match="margin or raw"):
        family_counts(np.zeros((1, 2)), 0.0, 1.0, np.array([[True, False]]), Rule.NONE, [0.0])


def test_operating_point_and_pooling():
    accepted = np.array([True, True, False, True])
    right = np.array([True, False, False, False])
    known = np.array([True, True, True, False])
    p = operating_point(accepted, right, known, 0.0)
    assert (p.tp, p.accepted, p.n_known, p.n_unknown, p.precision, p.recall) == (1, 3, 3, 1, 1 / 3, 1 / 3)
    assert operating_point(np.zeros(4, bool), np.zeros(4, bool), known).precision == 1.0  # the convention
    q = pool_points([p, p])
    assert (q.tp, q.accepted, q.n_known, q.precision) == (2, 6, 6, 1 / 3)
    with pytest.raises(VPRInputError, match="right but not accepted"):
        operating_point(~accepted, right, known)


# --------------------------------------------------------------------------- the per-place family


def _open_set_split(seed=0, n_places=10, per_place=5, dim=24, noise=1.1):
    """One open-set split of a synthetic route: 3 places held out, their queries unknown."""
    rng = np.random.default_rng(seed)
    centres = unit_rows(rng, n_places, dim)
    labels = np.repeat(np.arange(n_places), per_place)
    d = centres[labels] + noise * rng.normal(size=(len(labels), dim)) / np.sqrt(dim)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    trav = np.tile(np.arange(per_place) % 3, n_places)
    sp = draw_splits(labels, n_places, runs=1, seed=seed, unknown_share=0.3)[0]
    q, tr = sp.queries, sp.train
    correct = np.zeros((len(q), n_places), bool)
    known = ~sp.unknown[labels[q]]
    correct[np.flatnonzero(known), labels[q][known]] = True
    sims = similarity(d[q], d[tr])
    split = run_split(d[tr], labels[tr], trav[tr], sims, correct, trav[q], n_places, user_theta=0.2, seed=seed)
    return split, sims, labels[tr], n_places


def _brute_force_family(sims, db_places, n_places, theta, spread, correct, rule, ks):
    """At every k, ``score_queries`` from the similarities with θ_p(k), counted by hand."""
    method = Method("k", "θ_p(k)", "place", rule, "k", "test")
    tp, acc = [], []
    for k in ks:
        o = score_queries(sims, db_places, n_places, {"k": threshold_family(theta, spread, k)}, correct,
                          (method,))["k"]
        tp.append(int(o.right.sum()))
        acc.append(int(o.accepted.sum()))
    return np.array(tp), np.array(acc)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("rule", [Rule.MARGIN, Rule.RAW])
@pytest.mark.parametrize("base", ["simple", "weighted"])
def test_family_equals_score_queries_at_every_k(seed, rule, base):
    split, sims, db_places, n_places = _open_set_split(seed)
    theta = split.thresholds[base]
    curve = family_pr(split.raw, theta, split.spread, split.correct, rule, n=60)
    ks = curve.threshold[1:]
    tp, acc = _brute_force_family(sims, db_places, n_places, theta, split.spread, split.correct, rule, ks)
    np.testing.assert_array_equal(curve.tp[1:], tp)
    np.testing.assert_array_equal(curve.accepted[1:], acc)
    assert curve.n_known == int(split.known.sum()) and curve.n_unknown == int((~split.known).sum()) > 0
    # the grid runs from nothing accepted to every query accepted, through k = 0 ...
    assert curve.accepted[1] == 0 and curve.accepted[-1] == len(split.known) and 0.0 in ks
    # ... where the method's own outcome sits
    own = split.outcomes[f"{rule.value}-{base}"]
    point = curve.point(0.0)
    assert (point.tp, point.accepted) == (int(own.right.sum()), int(own.accepted.sum()))


def test_family_range_is_where_acceptance_changes():
    # one query, two places: κ = (0.8 − 0.5)/0.1 = 3 and (0.6 − 0.5)/0.05 = 2
    raw = np.array([[0.8, 0.6], [0.55, 0.4]])  # second query: κ = 0.5 and −2
    lo, hi = family_range(raw, np.array([0.5, 0.5]), np.array([0.1, 0.05]))
    assert (lo, hi) == pytest.approx((0.5, 3.0))
    ks = family_grid(lo, hi, 11)
    # 11 values over [0.5, 3] padded by 1% of the range each side, then k = 0 (the method's own θ_p)
    assert len(ks) == 12 and ks[0] == pytest.approx(3.025) and ks[-2] == pytest.approx(0.475) and ks[-1] == 0.0
    assert np.all(np.diff(ks) < 0)
    # a place whose s_p is 0 does not move with k, and a NaN θ_p drops the place
    assert family_range(raw, np.array([0.5, np.nan]), np.array([0.0, 0.1])) == (0.0, 0.0)


def test_raw_rule_family_recall_can_rise_with_k():
    # one known query: place 1 (wrong) has the higher raw but the higher threshold.
    # k small: both kept, the wrong one answers; k between κ_1 = 1 and κ_0 = 2: only the right one.
    raw = np.array([[0.7, 0.8]])
    correct = np.array([[True, False]])
    tp, acc = family_counts(raw, np.array([0.5, 0.7]), np.array([0.1, 0.1]), correct, Rule.RAW, [2.5, 1.5, 0.5])
    assert tp.tolist() == [0, 1, 0] and acc.tolist() == [0, 1, 1]
    c = family_pr(raw, np.array([0.5, 0.7]), np.array([0.1, 0.1]), correct, Rule.RAW, ks=[2.5, 1.5, 0.5])
    # along the curve as drawn: recall 0 → 0 → 1 → 0 with precision 1, 1, 1, 0: ∫P dR = 1 − 1/2
    assert c.auc == pytest.approx(0.5) and c.r_at_100p == 1.0


def test_pooled_family_sums_the_runs():
    a, *_ = _open_set_split(0)
    b, *_ = _open_set_split(1)
    ks = np.linspace(3, -1, 17)
    parts = [(s.raw, s.thresholds["weighted"], s.spread, s.correct) for s in (a, b)]
    pooled = pooled_family_pr(parts, Rule.MARGIN, ks)
    one = [family_counts(*p, Rule.MARGIN, ks) for p in parts]
    np.testing.assert_array_equal(pooled.tp[1:], one[0][0] + one[1][0])
    np.testing.assert_array_equal(pooled.accepted[1:], one[0][1] + one[1][1])
    assert pooled.n_known == int(a.known.sum() + b.known.sum())


def test_pr_rows_pool_runs_and_place_each_method_on_its_curve():
    splits = [_open_set_split(s)[0] for s in range(3)]
    pr = [PRSplit(s.outcomes, s.known, s.raw.max(axis=1), s.raw, s.correct, s.thresholds, s.spread) for s in splits]
    rows, curves = pr_rows(pr, n=40)
    by_key = {r.key: r for r in rows}
    assert set(curves) == {IMAGE_CURVE, GLOBAL_CURVE, *(family_curve_name(b, r) for b in ("simple", "weighted")
                                                      for r in ("margin", "raw"))}
    glob = curves[GLOBAL_CURVE]
    concat = pr_curve(np.concatenate([s.raw.max(axis=1) for s in splits]),
                      np.concatenate([s.outcomes["place-baseline"].right for s in splits]),
                      np.concatenate([s.known for s in splits]))
    np.testing.assert_array_equal(glob.tp, concat.tp)
    assert by_key["global-user"].auc == glob.auc and by_key["global-user"].n_unknown == 9
    # one θ in every run: the user θ's own point is the pooled curve's point at θ
    user = by_key["global-user"].own
    assert (user.tp, user.accepted) == (glob.point(0.2).tp, glob.point(0.2).accepted)
    # the baselines accept everything: the curve's last point
    base = by_key["place-baseline"].own
    assert (base.tp, base.accepted) == (glob.tp[-1], glob.accepted[-1]) and base.threshold == -math.inf
    # the per-place methods sit on their family's k = 0
    for key in ("margin-simple", "margin-weighted", "raw-simple", "raw-weighted"):
        r = by_key[key]
        p = curves[r.curve].point(0.0)
        assert (r.own.tp, r.own.accepted, r.own.threshold, r.param) == (p.tp, p.accepted, 0.0, "k")
    # JSON-ready
    d = by_key["margin-weighted"].to_dict()
    assert d["own"]["threshold"] == 0.0 and d["n_unknown"] == 9
    cd = curves[GLOBAL_CURVE].to_dict(max_points=5)
    assert cd["threshold"][0] is None and len(cd["recall"]) <= 6


def test_pr_rows_without_raw_leave_the_family_out():
    s = _open_set_split(0)[0]
    rows, curves = pr_rows([PRSplit(s.outcomes, s.known, s.raw.max(axis=1))])
    assert set(curves) == {IMAGE_CURVE, GLOBAL_CURVE}
    assert {r.key for r in rows} == {"image-baseline", "place-baseline", "global-auto", "global-oracle", "global-user"}


def test_float32_raw_counts_as_float64():
    # raw_p is the max of float32 scores: the database/queries protocol keeps it in float32
    s, *_ = _open_set_split(2)
    raw32 = s.raw.astype(np.float32)
    assert np.array_equal(raw32.astype(np.float64), s.raw)
    ks = np.linspace(3, -1, 21)
    for rule in (Rule.MARGIN, Rule.RAW):
        a = family_counts(s.raw, s.thresholds["weighted"], s.spread, s.correct, rule, ks)
        b = family_counts(raw32, s.thresholds["weighted"], s.spread, s.correct, rule, ks)
        np.testing.assert_array_equal(a, b)


# --------------------------------------------------------------------------- the counts against the previous loop


def _family_counts_by_methods(raw, theta, spread, correct, rule, ks):
    """The counts as ``family_counts`` computed them before (issue 12 §2): ``retrieval``'s own
    ``ranking_scores``, ``top_answer`` and ``pessimistic_rank`` at every k, on the whole matrix."""
    from vpr_explorer.method.retrieval import pessimistic_rank, ranking_scores, top_answer

    r = np.asarray(raw, dtype=np.float64)
    tp, acc = [], []
    for k in ks:
        scores = ranking_scores(r, theta + k * spread, Rule(rule))
        accepted = top_answer(scores) >= 0
        acc.append(int(accepted.sum()))
        tp.append(int((accepted & (pessimistic_rank(scores, correct) == 1)).sum()))
    return np.array(tp), np.array(acc)


def _awkward_family(seed):
    """Raw scores on a grid of 1/64 (exact), θ_p and s_p in 1/64 and 1/16: θ_p + k·s_p hits raw_p
    exactly at grid k; places 1e-5 apart (the tie tolerance) and 1e-5 ± 1 ulp; NaN θ, s = 0,
    -inf raw (a place with no image to match), queries with two right places, unknown queries."""
    rng = np.random.default_rng(seed)
    nq, n_p = 300, 40
    raw = rng.integers(16, 60, (nq, n_p)) / 64
    raw[:, 5] = raw[:, 4] - TIE_TOLERANCE
    raw[:, 6] = np.nextafter(raw[:, 4] - TIE_TOLERANCE, 0.0)
    raw[:, 7] = np.nextafter(raw[:, 4] - TIE_TOLERANCE, 1.0)
    raw[rng.random((nq, n_p)) < 0.05] = -np.inf
    theta = rng.integers(30, 50, n_p) / 64
    spread = rng.integers(1, 4, n_p) / 16
    theta[[8, 9]], spread[[8, 9]] = [50 / 64, 70 / 64], 0.0  # do not move with k: kept by raw ≥ 50/64, never
    theta[3] = np.nan
    spread[3] = np.nan
    correct = np.zeros((nq, n_p), bool)
    truth = rng.integers(0, n_p, nq)
    correct[np.arange(nq), truth] = True
    twice = rng.random(nq) < 0.2
    correct[np.flatnonzero(twice), (truth[twice] + 1) % n_p] = True
    correct[rng.random(nq) < 0.2] = False  # unknown queries
    correct[:40, 4] = True  # right place 4, with wrong places 5-7 at the tolerance's edge
    correct[:40, 5:8] = False
    return raw, theta, spread, correct


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("rule", [Rule.MARGIN, Rule.RAW])
@pytest.mark.parametrize("mode", ["default", "dense", "kept pairs", "blocks"])
def test_family_counts_equal_the_previous_loop(monkeypatch, seed, rule, mode):
    # default: a dense pass at the low k where many places are kept, the kept pairs above; "dense":
    # dense passes at every k; "kept pairs": the kept pairs at every k; "blocks": blocks of 25
    # queries, each with more kept pairs than _BLOCK_CELLS = 1000, so dense passes throughout
    import vpr_explorer.protocols.precision_recall as precision_recall

    calls = []
    dense_counts = precision_recall._dense_counts
    monkeypatch.setattr(precision_recall, "_dense_counts", lambda r, c, th, rule: calls.append(len(th)) or
                        dense_counts(r, c, th, rule))
    share = {"default": precision_recall._DENSE_KEPT, "dense": -1.0, "kept pairs": 1.0, "blocks": 1.0}[mode]
    monkeypatch.setattr(precision_recall, "_DENSE_KEPT", share)
    if mode == "blocks":
        monkeypatch.setattr(precision_recall, "_BLOCK_CELLS", 1000)
    raw, theta, spread, correct = _awkward_family(seed)
    ks = np.r_[np.arange(-4, 4.01, 0.25), family_grid(*family_range(raw, theta, spread), 50)]
    tp, acc = family_counts(raw, theta, spread, correct, rule, ks)
    ref_tp, ref_acc = _family_counts_by_methods(raw, theta, spread, correct, rule, ks)
    np.testing.assert_array_equal(tp, ref_tp)
    np.testing.assert_array_equal(acc, ref_acc)
    assert len(set(zip(tp.tolist(), acc.tolist()))) > 10  # the counts move along the grid
    expect = {"default": lambda: len(calls) == 1 and 0 < calls[0] < len(ks), "dense": lambda: calls == [len(ks)],
              "kept pairs": lambda: calls == [], "blocks": lambda: calls == [len(ks)] * 12}
    assert expect[mode](), calls


@pytest.mark.realdata
def test_family_counts_equal_the_previous_loop_on_gardens_point(monkeypatch, gardens_point, gp_pixels):
    # real raw_p, θ_p and s_p: an open-set run with a frame tolerance of 1 (two right places)
    import vpr_explorer.protocols.evaluation as evaluation
    from vpr_explorer.method.places import PlaceSpec, make_places

    captured = []
    pooled = evaluation._pooled_splits
    monkeypatch.setattr(evaluation, "_pooled_splits", lambda *a, **k: captured.extend(pooled(*a, **k)) or captured)
    places = make_places(gardens_point, PlaceSpec(2, 2))  # adjacent places: a frame's neighbour is right too
    evaluation.open_set_protocol(gp_pixels, places.image_place, gardens_point.image_traversal, places.n_places,
                                 ProtocolOptions(runs=2, tolerance=1), image_frame=gardens_point.image_frame,
                                 frame_place=places.frame_place)
    assert any(s.correct.sum(axis=1).max() > 1 for s in captured)
    for s in captured:
        for base in ("simple", "weighted"):
            ks = family_grid(*family_range(s.raw, s.thresholds[base], s.spread), 80)
            for rule in (Rule.MARGIN, Rule.RAW):
                got = family_counts(s.raw, s.thresholds[base], s.spread, s.correct, rule, ks)
                want = _family_counts_by_methods(s.raw, s.thresholds[base], s.spread, s.correct, rule, ks)
                np.testing.assert_array_equal(got, want)
