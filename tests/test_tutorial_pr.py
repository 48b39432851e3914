"""VPR_Tutorial precision–recall (``protocols.tutorial_pr``) against a plain loop over thresholds
written from ``createPR``/``recallAt100precision``, hand-computed 2×3 cases, boundaries, bad
input, and GardensPoint night_right (queries) vs day_right (database) with the tutorial's
ground truth."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from vpr_explorer.errors import VPRInputError
from vpr_explorer.protocols.tutorial_pr import Matching, TutorialPR, tutorial_pr

T, F = True, False


# --------------------------------------------------------------------------- the plain-loop reference
# Written from VPR_Tutorial's evaluation/metrics.py, in its orientation: S, GThard, GTsoft are
# (n_database, n_queries), one threshold at a time.


def ref_create_pr(S_in, GThard, GTsoft=None, matching="multi", n_thresh=100):
    GT = GThard.copy()
    S = S_in.copy()
    if GTsoft is not None:
        S[GTsoft & ~GT] = S.min()
    if matching == "single":
        GTP = np.count_nonzero(GT.any(0))
        best = np.argmax(S, axis=0)
        GT = GT[best, np.arange(GT.shape[1])]
        S = np.max(S, axis=0)
    else:
        GTP = np.count_nonzero(GT)
    P, R = [1.0], [0.0]
    for t in np.linspace(S.max(), S.min(), n_thresh):
        B = S >= t
        TP = np.count_nonzero(GT & B)
        FP = np.count_nonzero(~GT & B)
        P.append(TP / (TP + FP))
        R.append(TP / GTP)
    return np.array(P), np.array(R)


def ref_summaries(P, R):
    """``(AUC, R@100P)``: the tutorial's trapezoid over (R, P) and ``R[P == 1].max()``."""
    return float(np.trapezoid(P, R)), float(R[P == 1].max())


def assert_matches_reference(sim, hard, soft, matching, n_thresh=100):
    """Ours on ``(n_queries, n_database)`` against the reference on the transposes."""
    got = tutorial_pr(sim, hard, soft, matching=matching, n_thresholds=n_thresh)
    P, R = ref_create_pr(sim.T, hard.T, None if soft is None else soft.T, matching, n_thresh)
    np.testing.assert_array_equal(got.precision, P)
    np.testing.assert_array_equal(got.recall, R)
    auc, r100 = ref_summaries(P, R)
    assert got.auc == pytest.approx(auc, rel=1e-12, abs=1e-15)
    assert got.recall_at_100_precision == r100
    return got


def random_case(rng, nq, nd, *, quantum=None, dtype=np.float64):
    s = rng.uniform(-1, 1, size=(nq, nd))
    if quantum is not None:
        s = np.round(s / quantum) * quantum  # many exact ties, and scores landing on thresholds
    hard = rng.random((nq, nd)) < 0.15
    hard[0, 0] = True
    soft = hard | (rng.random((nq, nd)) < 0.2)
    return s.astype(dtype), hard, soft


# --------------------------------------------------------------------------- against the reference


@pytest.mark.parametrize("matching", ["single", "multi"])
@pytest.mark.parametrize("with_soft", [False, True])
@pytest.mark.parametrize("seed", range(6))
def test_random_matrices_match_the_loop(seed, with_soft, matching):
    rng = np.random.default_rng(seed)
    nq, nd = rng.integers(3, 40, size=2)
    # quantised scores (exact ties, scores on thresholds) for multi; single rows need a clear top
    quantum = None if matching == "single" else [None, 0.25, 0.01][seed % 3]
    dtype = np.float32 if seed % 2 else np.float64
    s, hard, soft = random_case(rng, nq, nd, quantum=quantum, dtype=dtype)
    if matching == "single":
        # ties within 1e-5 are where the two rules may differ (tested apart): keep every row's top clear
        lowered = s.astype(np.float64)
        if with_soft:
            lowered[soft & ~hard] = lowered.min()
        top2 = np.sort(lowered, axis=1)[:, -2:]
        assert np.all(top2[:, 1] - top2[:, 0] > 1e-5)  # no tie at the top of a row for these seeds
    n_thresh = int(rng.integers(2, 150))
    got = assert_matches_reference(s, hard, soft if with_soft else None, matching, n_thresh)
    assert got.matching == matching and got.soft_ignored is with_soft
    assert got.thresholds.shape == (n_thresh,) and got.precision.shape == (n_thresh + 1,)


def test_quantised_single_rows_without_ties_match_the_loop():
    """Single matching on scores that sit on thresholds, rows kept free of ties at the top."""
    rng = np.random.default_rng(11)
    for _ in range(20):
        s = rng.permutation(np.arange(8 * 12) / 16.0).reshape(8, 12)  # distinct multiples of 1/16
        hard = rng.random(s.shape) < 0.2
        hard[:, 0] |= ~hard.any(axis=1) & (rng.random(8) < 0.5)
        if not hard.any():
            continue
        for n_thresh in (2, 5, 7, 17, 100):
            assert_matches_reference(s, hard, None, "single", n_thresh)


# --------------------------------------------------------------------------- hand-computed 2×3 cases
# S (queries × database), scores on a 1/4 grid so that thresholds are exact:
#     q0: 1.00  0.50  0.00      hard: db0          soft: db0 db1
#     q1: 0.25  0.75  0.50      hard: db2          soft: db1 db2
# soft-only pairs (q0, db1) and (q1, db1) are lowered to min(S) = 0.

S = np.array([[1.0, 0.5, 0.0], [0.25, 0.75, 0.5]])
HARD = np.array([[T, F, F], [F, F, T]])
SOFT = np.array([[T, T, F], [F, T, T]])


def test_hand_multi_without_soft():
    r = tutorial_pr(S, HARD, matching="multi", n_thresholds=5)
    np.testing.assert_array_equal(r.thresholds, [1.0, 0.75, 0.5, 0.25, 0.0])
    # t=1: {1.0✓}; t=.75: +0.75✗; t=.5: +0.5✗ +0.5✓ (scores equal to t are detected);
    # t=.25: +0.25✗; t=0: +0.0✗ — TP/(TP+FP): 1/1, 1/2, 2/4, 2/5, 2/6; recall TP/2
    np.testing.assert_allclose(r.precision, [1, 1, 1 / 2, 2 / 4, 2 / 5, 2 / 6], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(r.recall, [0, 0.5, 0.5, 1, 1, 1])
    assert r.n_positives == 2
    assert r.auc == pytest.approx(0.5 * 1 + 0.5 * 0.5)  # (0→.5)·(1+1)/2 + (.5→1)·(.5+.5)/2
    assert r.recall_at_100_precision == 0.5


def test_hand_multi_with_soft():
    r = tutorial_pr(S, HARD, SOFT, matching="multi", n_thresholds=5)
    np.testing.assert_array_equal(r.thresholds, [1.0, 0.75, 0.5, 0.25, 0.0])
    # lowered: q0 = 1✓ 0 0, q1 = .25 0 .5✓ — t=.5 detects both right ones and nothing else;
    # at t=0 = min(S) every pair is detected, the two lowered soft-only pairs as false positives
    np.testing.assert_allclose(r.precision, [1, 1, 1, 1, 2 / 3, 2 / 6], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(r.recall, [0, 0.5, 0.5, 1, 1, 1])
    assert r.soft_ignored
    assert r.auc == pytest.approx(1.0)
    assert r.recall_at_100_precision == 1.0


def test_hand_single_without_soft():
    r = tutorial_pr(S, HARD, matching="single", n_thresholds=5)
    # best per query: q0 → db0 (1.0, right), q1 → db1 (0.75, wrong); thresholds 1 … 0.75 by 1/16
    np.testing.assert_array_equal(r.thresholds, [1.0, 0.9375, 0.875, 0.8125, 0.75])
    np.testing.assert_array_equal(r.precision, [1, 1, 1, 1, 1, 0.5])
    np.testing.assert_array_equal(r.recall, [0, 0.5, 0.5, 0.5, 0.5, 0.5])
    assert r.n_positives == 2
    assert r.auc == pytest.approx(0.5)
    assert r.recall_at_100_precision == 0.5


def test_hand_single_with_soft():
    r = tutorial_pr(S, HARD, SOFT, matching="single", n_thresholds=5)
    # q1's best (db1, soft-only) is lowered to 0, so its best becomes db2 (0.5, right)
    np.testing.assert_array_equal(r.thresholds, [1.0, 0.875, 0.75, 0.625, 0.5])
    np.testing.assert_array_equal(r.precision, [1, 1, 1, 1, 1, 1])
    np.testing.assert_array_equal(r.recall, [0, 0.5, 0.5, 0.5, 0.5, 1])
    assert r.auc == pytest.approx(1.0)
    assert r.recall_at_100_precision == 1.0


def test_hand_cases_match_the_loop():
    for matching in Matching:
        for soft in (None, SOFT):
            for n in (2, 3, 5, 100):
                assert_matches_reference(S, HARD, soft, matching, n)


def test_single_with_soft_promotes_the_next_best_image():
    """Lowering a soft-only best match does not drop its query: the next best image is the detection."""
    s = np.array([[0.9, 0.8, 0.1], [0.7, 0.2, 0.3]])
    hard = np.array([[F, F, T], [T, F, F]])
    soft = np.array([[T, F, T], [T, F, F]])
    r = tutorial_pr(s, hard, soft, matching="single", n_thresholds=2)
    # q0: db0 lowered to 0.1 → db1 (0.8, wrong) is its detection; q1: db0 (0.7, right)
    np.testing.assert_array_equal(r.thresholds, [0.8, 0.7])
    np.testing.assert_array_equal(r.precision, [1, 0, 0.5])
    np.testing.assert_array_equal(r.recall, [0, 0, 0.5])
    assert r.recall_at_100_precision == 0.0


# --------------------------------------------------------------------------- boundaries


def test_a_score_equal_to_a_threshold_is_detected():
    s = np.array([[0.5, 0.25, 0.0]])
    hard = np.array([[F, T, F]])
    r = tutorial_pr(s, hard, matching="multi", n_thresholds=3)
    np.testing.assert_array_equal(r.thresholds, [0.5, 0.25, 0.0])
    # t = 0.25 detects the right 0.25 (S >= t), with the wrong 0.5
    np.testing.assert_array_equal(r.recall, [0, 0, 1, 1])
    np.testing.assert_array_equal(r.precision, [1, 0, 0.5, 1 / 3])


def test_recall_at_100_precision_needs_precision_exactly_one():
    # 99 right pairs at 1.0 and 2, one of them wrong, at 0.5: the t = 0.5 point has recall 1 and
    # precision 100/101 < 1, so R@100P is the t = 1 point's 99/100, not 1
    s = np.r_[np.ones(99), 0.5, 0.5, 0.0][None, :]
    hard = np.r_[np.ones(100, bool), False, False][None, :]
    r = tutorial_pr(s, hard, matching="multi", n_thresholds=3)
    np.testing.assert_array_equal(r.thresholds, [1.0, 0.5, 0.0])
    np.testing.assert_array_equal(r.precision[:3], [1, 1, 100 / 101])
    np.testing.assert_array_equal(r.recall[:3], [0, 0.99, 1])
    assert r.recall_at_100_precision == 0.99
    # precision exactly 1 at full recall counts
    hard[0, 100] = True
    assert tutorial_pr(s, hard, matching="multi", n_thresholds=3).recall_at_100_precision == 1.0


def test_recall_at_100_precision_is_zero_when_the_first_detection_is_wrong():
    s = np.array([[1.0, 0.0, 0.5]])
    hard = np.array([[F, F, T]])
    r = tutorial_pr(s, hard, matching="multi", n_thresholds=3)
    np.testing.assert_array_equal(r.precision, [1, 0, 0.5, 1 / 3])
    assert r.recall_at_100_precision == 0.0  # only the start point has precision 1
    assert r.recall[-1] == 1.0


def test_single_ties_go_to_the_lowest_index_within_tolerance():
    """np.argmax takes the exact maximum (db1, wrong); the project's rule takes db0 within 1e-5 (right)."""
    s = np.array([[0.5, 0.5 + 5e-6, 0.1], [0.2, 0.9, 0.3]])
    hard = np.array([[T, F, F], [F, T, F]])
    r = tutorial_pr(s, hard, matching="single", n_thresholds=2)
    # the detection's score is the row's top score, as the tutorial's np.max
    np.testing.assert_array_equal(r.thresholds, [0.9, 0.5 + 5e-6])
    np.testing.assert_array_equal(r.precision, [1, 1, 1])
    np.testing.assert_array_equal(r.recall, [0, 0.5, 1])
    P, R = ref_create_pr(s.T, hard.T, None, "single", 2)
    np.testing.assert_array_equal(P, [1, 1, 0.5])  # theirs counts q0's exact maximum, db1, wrong
    # 2e-5 apart is no tie: the exact maximum wins in both
    s[0, 1] = 0.5 + 2e-5
    assert_matches_reference(s, hard, None, "single", 2)


def test_a_query_without_positives_is_a_candidate_in_single_matching():
    s = np.array([[0.9, 0.1], [0.8, 0.2]])
    hard = np.array([[F, F], [T, F]])
    r = tutorial_pr(s, hard, matching="single", n_thresholds=2)
    assert r.n_positives == 1
    np.testing.assert_array_equal(r.precision, [1, 0, 0.5])  # q0's best, 0.9, is wrong
    np.testing.assert_array_equal(r.recall, [0, 0, 1])


def test_a_constant_matrix_has_one_threshold_repeated():
    s = np.full((2, 2), 0.3, dtype=np.float32)
    hard = np.eye(2, dtype=bool)
    r = tutorial_pr(s, hard, matching="multi", n_thresholds=4)
    assert np.all(r.thresholds == np.float64(np.float32(0.3)))
    np.testing.assert_array_equal(r.precision, [1, 0.5, 0.5, 0.5, 0.5])
    np.testing.assert_array_equal(r.recall, [0, 1, 1, 1, 1])


def test_float32_thresholds_are_spaced_in_float32():
    rng = np.random.default_rng(4)
    s, hard, _ = random_case(rng, 20, 30, dtype=np.float32)
    r = tutorial_pr(s, hard, n_thresholds=37)
    np.testing.assert_array_equal(r.thresholds, np.linspace(s.max(), s.min(), 37).astype(np.float64))
    assert np.linspace(s.max(), s.min(), 37).dtype == np.float32


def test_result_is_frozen_and_json_ready():
    r = tutorial_pr(S, HARD, SOFT, matching=Matching.SINGLE, n_thresholds=5)
    assert isinstance(r, TutorialPR) and r.matching is Matching.SINGLE
    with pytest.raises(ValueError):
        r.precision[0] = 0.5
    with pytest.raises(AttributeError):
        r.auc = 0.0
    d = json.loads(json.dumps(r.to_dict(), allow_nan=False))
    assert d["matching"] == "single" and d["soft_ignored"] is True and d["n_positives"] == 2
    assert d["auc"] == r.auc and d["recall_at_100_precision"] == r.recall_at_100_precision
    assert d["precision"] == r.precision.tolist() and len(d["thresholds"]) == 5


def test_to_dict_turns_nan_into_none():
    r = tutorial_pr(S, HARD, n_thresholds=5)
    odd = TutorialPR(precision=np.r_[1.0, np.nan], recall=np.r_[0.0, np.inf], thresholds=np.r_[0.5],
                     matching=Matching.MULTI, soft_ignored=False, n_positives=1, auc=math.nan,
                     recall_at_100_precision=r.recall_at_100_precision)
    d = odd.to_dict()
    assert d["precision"] == [1.0, None] and d["recall"] == [0.0, None] and d["auc"] is None
    json.dumps(d, allow_nan=False)


def test_inputs_are_not_modified():
    s, hard, soft = S.copy(), HARD.copy(), SOFT.copy()
    tutorial_pr(s, hard, soft, matching="single")
    tutorial_pr(s, hard, soft, matching="multi")
    np.testing.assert_array_equal(s, S)
    np.testing.assert_array_equal(hard, HARD)
    np.testing.assert_array_equal(soft, SOFT)


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("kwargs, match", [
    (dict(similarity=S[:, :2]), r"hard: shape \(2, 3\) differs from similarity's \(2, 2\)"),
    (dict(soft=SOFT[:1]), r"soft: shape \(1, 3\)"),
    (dict(similarity=S[0]), r"similarity: must be 2-D"),
    (dict(similarity=np.where(np.eye(2, 3, dtype=bool), np.nan, S)), r"similarity: .*NaN.*query 0, database image 0"),
    (dict(similarity=np.where(np.eye(2, 3, k=1, dtype=bool), np.inf, S)), r"similarity: .*infinite"),
    (dict(similarity=S > 0.5), r"similarity: must hold real numbers"),
    (dict(hard=HARD.astype(int)), r"hard: must be a bool array.*int64.*hard != 0"),
    (dict(soft=SOFT.astype(float)), r"soft: must be a bool array"),
    (dict(hard=np.zeros((2, 3), bool)), r"hard: no query has a positive"),
    (dict(n_thresholds=1), r"n_thresholds=1: must be a whole number, 2 or more"),
    (dict(n_thresholds=2.0), r"n_thresholds=2.0"),
    (dict(n_thresholds=True), r"n_thresholds=True"),
    (dict(matching="best"), r"matching='best': choose single or multi"),
    (dict(similarity=np.zeros((0, 3)), hard=np.zeros((0, 3), bool), soft=None),
     r"similarity: shape \(0, 3\) holds no pair"),
])
def test_bad_input_names_the_parameter(kwargs, match):
    args = dict(similarity=S, hard=HARD, soft=SOFT)
    args.update(kwargs)
    rest = {k: args.pop(k) for k in ("matching", "n_thresholds") if k in args}
    with pytest.raises(VPRInputError, match=match):
        tutorial_pr(args["similarity"], args["hard"], args["soft"], **rest)


# --------------------------------------------------------------------------- real data


def tutorial_ground_truth(n: int) -> tuple[np.ndarray, np.ndarray]:
    """VPR_Tutorial's GardensPoint GThard/GTsoft (database × query): the identity, and it
    convolved with a 17-tall column of ones (``mode='same'``)."""
    from scipy.signal import convolve2d

    gt_hard = np.eye(n).astype(bool)
    gt_soft = convolve2d(gt_hard.astype(int), np.ones((17, 1), int), mode="same").astype(bool)
    return gt_hard, gt_soft


@pytest.mark.realdata
def test_gardens_point_night_against_day_matches_the_loop(gardens_point, gp_pixels):
    from vpr_explorer.data.aligned import database_queries, value_rows
    from vpr_explorer.data.groundtruth import GroundTruth
    from vpr_explorer.method.retrieval import similarity

    v = database_queries(gardens_point, "night_right", database=["day_right"])
    rows = value_rows(v)
    d = gp_pixels if rows is None else gp_pixels[rows]
    sims = similarity(d[v.n_database:], d[:v.n_database])  # float32, as the tutorial's S
    assert sims.shape == (200, 200) and sims.dtype == np.float32

    hard = GroundTruth.from_frames(v.query_frame, v.database_frame, 0).dense()
    soft = GroundTruth.from_frames(v.query_frame, v.database_frame, 8).dense()
    gt_hard, gt_soft = tutorial_ground_truth(200)
    np.testing.assert_array_equal(hard, gt_hard.T)  # same frame
    np.testing.assert_array_equal(soft, gt_soft.T)  # within ±8 frames

    results = {}
    for matching in ("single", "multi"):
        for name, truth in (("no soft", None), ("soft", soft)):
            got = assert_matches_reference(sims, hard, truth, matching)
            results[matching, name] = got
            print(f"\nGardensPoint night_right vs day_right, pixels, {matching}, {name}: "
                  f"AUC {got.auc:.4f}, R@100P {got.recall_at_100_precision:.4f}")
    # multi: the last threshold is min(S), so every pair is detected, the lowered soft-only ones too
    for name in ("no soft", "soft"):
        assert results["multi", name].recall[-1] == 1.0
        assert results["multi", name].precision[-1] == 200 / 200**2
    assert results["multi", "soft"].auc > results["multi", "no soft"].auc
    # single: the last point is Recall@1, the best image of a query right in 6.5% of queries; with
    # soft, a lowered neighbour passes the detection to the next best image (13% right)
    assert results["single", "no soft"].recall[-1] == pytest.approx(13 / 200)
    assert results["single", "soft"].recall[-1] == pytest.approx(26 / 200)
