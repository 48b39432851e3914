"""Retrieval methods on hand-computed cases: margin vs raw ranking, rejection, ties."""

import numpy as np
import pytest

from reference import loop_rank
from vpr_explorer.method.retrieval import (
    TIE_TOLERANCE,
    Rule,
    decide,
    pessimistic_rank,
    place_scores,
    ranking_scores,
    score_queries,
    top_answer,
)

# One query, three places of two database images each.
DB_PLACES = np.array([0, 0, 1, 1, 2, 2])
SIMS = np.array([0.20, 0.30, 0.50, 0.40, 0.45, 0.10])
THETA = {"simple": np.array([0.10, 0.60, 0.40]), "weighted": np.array([0.25, 0.45, 0.50]), "auto": 0.48}


def test_place_scores_max_and_argmax():
    raw, best = place_scores(SIMS[None], DB_PLACES, 4)
    np.testing.assert_allclose(raw[0, :3], [0.30, 0.50, 0.45])
    assert raw[0, 3] == -np.inf and best[0, 3] == -1  # place 3 has no database image
    assert best[0, :3].tolist() == [1, 2, 4]


def test_place_scores_with_excluded_images_and_unsorted_labels():
    sims = np.array([[0.9, -np.inf, 0.1, -np.inf], [0.2, 0.3, -np.inf, -np.inf]])
    raw, best = place_scores(sims, np.array([1, 0, 1, 0]), 2)
    np.testing.assert_allclose(raw, [[-np.inf, 0.9], [0.3, 0.2]])
    assert best.tolist() == [[-1, 0], [1, 0]]


def test_margin_and_raw_rank_differently():
    raw = np.array([[0.30, 0.50, 0.45]])
    # simple θ: place 1 dropped (0.50 < 0.60); margins 0.20 (p0), 0.05 (p2)
    margin = ranking_scores(raw, THETA["simple"], Rule.MARGIN)
    np.testing.assert_allclose(margin, [[0.20, -np.inf, 0.05]])
    assert top_answer(margin).tolist() == [0]
    rawrule = ranking_scores(raw, THETA["simple"], Rule.RAW)
    np.testing.assert_allclose(rawrule, [[0.30, -np.inf, 0.45]])
    assert top_answer(rawrule).tolist() == [2]


def test_margin_zero_is_kept_and_nan_theta_drops():
    raw = np.array([[0.4, 0.4]])
    assert np.isfinite(ranking_scores(raw, np.array([0.4, np.nan]), Rule.MARGIN)).tolist() == [[True, False]]


def test_rejection_when_every_place_is_below():
    raw = np.array([[0.30, 0.50, 0.45]])
    s = ranking_scores(raw, 0.6, Rule.RAW)
    assert top_answer(s).tolist() == [-1]
    assert pessimistic_rank(s, np.array([[False, True, False]])).tolist() == [np.inf]


def test_ties_count_against_the_query():
    scores = np.array([[0.5, 0.5, 0.1], [0.5, 0.5, 0.1], [0.7, 0.5, 0.5]])
    correct = np.array([[True, False, False], [False, True, False], [False, False, True]])
    assert pessimistic_rank(scores, correct).tolist() == [2, 2, 3]
    assert top_answer(scores).tolist() == [0, 0, 0]


def test_scores_within_the_tolerance_tie_whatever_their_last_bits():
    # byte-identical images score 1.0, 0.99999994 or 0.99999988 against one query depending
    # on the BLAS kernel and block shape (float32 spacing below 1 is 6e-8): all ties
    one = np.float32(1.0)
    below = [float(np.nextafter(one, 0, dtype=np.float32)), float(np.nextafter(np.nextafter(one, 0), 0))]
    for right, wrong in ((1.0, below[0]), (below[1], 1.0), (below[0], below[1])):
        scores = np.array([[right, wrong, 0.5]])
        correct = np.array([[True, False, False]])
        assert pessimistic_rank(scores, correct).tolist() == [2]  # the wrong twin counts against
        assert top_answer(scores).tolist() == [0]  # the lowest index among the tied
        assert top_answer(scores[:, ::-1]).tolist() == [1]
    # the tolerance and no more: 2e-5 apart is no tie
    assert pessimistic_rank(np.array([[0.8, 0.8 - 2e-5]]), np.array([[True, False]])).tolist() == [1]
    assert pessimistic_rank(np.array([[0.8, 0.8 - 0.5e-5]]), np.array([[True, False]])).tolist() == [2]
    assert TIE_TOLERANCE == 1e-5


def test_image_behind_raw_is_the_lowest_index_within_the_tolerance():
    sims = np.array([[0.3, 0.9 - 4e-6, 0.9, 0.9 - 3e-5]])
    raw, best = place_scores(sims, np.array([0, 0, 0, 0]), 1)
    assert raw[0, 0] == 0.9 and best[0, 0] == 1


def test_ranks_and_answers_do_not_move_with_last_bit_noise():
    # what a different summation order does to float32 scores: ±2 ulp, everywhere
    rng = np.random.default_rng(1)
    base = np.round(rng.uniform(0.2, 1.0, size=(300, 40)), 3).astype(np.float32)  # many exact ties
    correct = rng.random(base.shape) < 0.1
    ulp = np.spacing(base)
    noisy = base + ulp * rng.integers(-2, 3, base.shape).astype(np.float32)
    for a, b in ((base, noisy), (noisy, base + ulp)):
        np.testing.assert_array_equal(pessimistic_rank(a.astype(float), correct), pessimistic_rank(b.astype(float), correct))
        np.testing.assert_array_equal(top_answer(a.astype(float)), top_answer(b.astype(float)))
    # exact equality would not survive it: that is the point of the tolerance
    exact_base = ((base[:, :, None] >= base[:, None, :]).sum(axis=2))
    exact_noisy = ((noisy[:, :, None] >= noisy[:, None, :]).sum(axis=2))
    assert (exact_base != exact_noisy).any()


def test_rank_matches_sorting_reference():
    rng = np.random.default_rng(0)
    scores = np.round(rng.normal(size=(200, 15)), 1)  # rounding makes ties frequent
    scores[rng.random(scores.shape) < 0.2] = -np.inf
    correct = rng.random(scores.shape) < 0.15
    np.testing.assert_array_equal(pessimistic_rank(scores, correct), loop_rank(scores, correct))


def test_score_queries_every_method():
    correct = np.array([[False, False, True]])
    out = score_queries(SIMS[None], DB_PLACES, 3, THETA, correct)
    got = {k: (o.answer_place[0], o.rank[0]) for k, o in out.items()}
    assert got == {
        "image-baseline": (1, 2), "place-baseline": (1, 2),
        "margin-simple": (0, 2), "margin-weighted": (0, np.inf),
        "raw-simple": (2, 1), "raw-weighted": (1, np.inf),
        "global-auto": (1, np.inf),
    }
    assert out["raw-simple"].right.tolist() == [True]
    assert out["image-baseline"].answer_image.tolist() == [2]


def test_decision_record_explains_rejection():
    d = decide(SIMS, DB_PLACES, 3, {"weighted": np.array([0.55, 0.60, 0.50])}, true_places=[2])
    assert d.answer("raw-weighted") == -1
    assert d.describe("raw-weighted").startswith(
        "rejected: the best place, 1, scored 0.500, below its threshold 0.600; every place scored below its threshold"
    )
    assert "the query is place 2" in d.describe("raw-weighted")
    assert d.kept("margin-weighted").tolist() == [False, False, False]
    np.testing.assert_allclose(d.margin("weighted"), [-0.25, -0.10, -0.05])
    assert not d.is_right("margin-weighted")


def test_decision_record_unknown_place_rejected_is_right():
    d = decide(SIMS, DB_PLACES, 3, {"auto": 0.9}, true_places=[])
    assert d.is_right("global-auto") and not d.is_right("place-baseline")
    assert "not in the database" in d.describe("global-auto")


def test_decision_record_ranks_and_wording():
    d = decide(SIMS, DB_PLACES, 3, THETA, true_places=[2])
    assert d.place_rank("margin-simple").tolist() == [1, 0, 2]
    assert d.place_rank("place-baseline").tolist() == [3, 1, 2]
    assert d.describe("raw-simple") == (
        "accepted as place 2 (right): raw 0.450, threshold 0.400, margin +0.050; 2 kept"
    )
    assert "the true place 2 ranked 2nd" in d.describe("margin-simple")
    assert "below its threshold 0.500, so it was dropped" in d.describe("margin-weighted")
    assert d.describe("image-baseline").startswith("accepted as image 2 → place 1 (wrong)")


def test_similarity_orientation():
    """Row i is query i against every database image, column j database image j: ``(n_queries, n_database)``."""
    from vpr_explorer.errors import VPRInputError
    from vpr_explorer.method.retrieval import similarity

    q = np.array([[1.0, 0.0, 0.0], [0.0, 0.6, 0.8]])  # 2 queries
    db = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.6, 0.8, 0.0]])  # 4 database images
    by_hand = np.array([
        [0.0, 1.0, 0.0, 0.6],  # query 0 = e0: the database images' first components
        [0.6, 0.0, 0.8, 0.48],  # query 1: 0.6·1, 0, 0.8·1, 0.6·0.8
    ])
    s = similarity(q, db)
    assert s.shape == (2, 4) and s.dtype == np.float32
    np.testing.assert_allclose(s, by_hand, atol=1e-7)
    loops = [[sum(q[i, d] * db[j, d] for d in range(3)) for j in range(4)] for i in range(2)]
    np.testing.assert_allclose(s, loops, atol=1e-7)
    assert np.argmax(s[0]) == 1 and np.argmax(s[1]) == 2  # each query's nearest database image
    with pytest.raises(VPRInputError, match="database columns"):
        place_scores(np.zeros((1, 3)), np.array([0, 1]), 2)
