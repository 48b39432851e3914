"""θ_p simple / weighted, the family θ_p(k), the automatic global threshold."""

import numpy as np
import pytest
from scipy.stats import norm

from reference import loop_auto_threshold, loop_thresholds, unit_rows
from vpr_explorer.errors import VPRInputError
from vpr_explorer.stats import NegativeStats, mixture_moments, negative_stats
from vpr_explorer.thresholds import (
    AUTO_Z,
    adaptive_k,
    auto_global_threshold,
    mixture_spread,
    place_thresholds,
    threshold_family,
    training_pair_scores,
)


def _stats(mu, sigma, n_neg, labels, n_places):
    a = lambda x, t=float: np.array(x, dtype=t)
    return NegativeStats(a(mu), a(sigma), a(n_neg, np.int64), a(labels, np.int64), n_places)


def test_hand_computed_simple_and_weighted():
    # place 0: μ = 0.2 (σ 0.1), 0.4 (σ 0.2); equal weights
    # simple = 0.3; weighted: τ² = 100, 25 -> (100·0.2 + 25·0.4)/125 = 0.24
    # place 1: a single image: both equal its μ
    st = _stats([0.2, 0.4, 0.5], [0.1, 0.2, 0.3], [1, 1, 2], [0, 0, 1], 3)
    np.testing.assert_allclose(place_thresholds(st, "simple")[:2], [0.3, 0.5])
    np.testing.assert_allclose(place_thresholds(st, "weighted")[:2], [0.24, 0.5])
    assert np.isnan(place_thresholds(st, "simple")[2])  # no training image


def test_weighted_uses_negative_counts_as_weights():
    # w ∝ |S⁻|: 3 and 1 -> (0.75·100·0.2 + 0.25·25·0.4) / (0.75·100 + 0.25·25) = 17.5/81.25
    st = _stats([0.2, 0.4], [0.1, 0.2], [3, 1], [0, 0], 1)
    np.testing.assert_allclose(place_thresholds(st, "weighted"), [17.5 / 81.25])


def test_weighted_is_a_weighted_mean_not_literal_eq4():
    # The literal eq. 4 with wᵢ = 1/n sums to (1/n)·Σ normalised -> half the mean for 2 images.
    st = _stats([0.3, 0.3], [0.1, 0.1], [5, 5], [0, 0], 1)
    assert place_thresholds(st, "weighted")[0] == pytest.approx(0.3)


def test_zero_sigma_dominates_weighted():
    st = _stats([0.2, 0.6], [0.0, 0.1], [2, 2], [0, 0], 1)
    assert place_thresholds(st, "weighted")[0] == pytest.approx(0.2, abs=1e-6)


def test_matches_loop_reference_on_random():
    rng = np.random.default_rng(0)
    d = unit_rows(rng, 200, 16)
    labels = rng.integers(0, 13, 200)
    st = negative_stats(d, labels)
    simple, weighted = loop_thresholds(st.mu, st.sigma, st.n_neg, labels, 13)
    np.testing.assert_allclose(place_thresholds(st, "simple"), simple, atol=1e-12)
    np.testing.assert_allclose(place_thresholds(st, "weighted"), weighted, atol=1e-12)


def test_family_and_spread():
    st = _stats([0.2, 0.4], [0.1, 0.1], [1, 1], [0, 0], 1)
    # mixture of N(0.2, .01) and N(0.4, .01) equally: var = 0.01 + 0.01 = 0.02
    assert mixture_spread(st)[0] == pytest.approx(np.sqrt(0.02))
    theta = place_thresholds(st, "simple")
    np.testing.assert_allclose(threshold_family(theta, mixture_spread(st), 1.5), 0.3 + 1.5 * np.sqrt(0.02))
    np.testing.assert_allclose(threshold_family(theta, mixture_spread(st), 0.0), theta)
    with pytest.raises(VPRInputError, match="k=nan"):
        threshold_family(theta, mixture_spread(st), float("nan"))
    assert mixture_moments(st)[0][0] == pytest.approx(0.3)


def test_adaptive_k_clips():
    k = adaptive_k(np.array([0.9, 0.5, 0.31, np.nan]), np.array([0.3, 0.3, 0.3, 0.3]), np.array([0.1] * 4))
    np.testing.assert_allclose(k, [2.0, 1.0, 1.0, 1.0])
    assert adaptive_k(np.array([0.6]), np.array([0.3]), np.array([0.1]))[0] == pytest.approx(1.5)


def test_auto_threshold_formula_and_reference():
    assert AUTO_Z == pytest.approx(norm.ppf(1 - 1e-6))
    # values 0,1,2,3,4: median 2, MAD 1 -> 2 + 4.753/0.675
    assert auto_global_threshold(np.arange(5.0)) == pytest.approx(2 + AUTO_Z / 0.675)
    rng = np.random.default_rng(1)
    d = unit_rows(rng, 40, 8)
    assert auto_global_threshold(training_pair_scores(d)) == pytest.approx(loop_auto_threshold(d))


def test_pair_sample_when_large():
    rng = np.random.default_rng(2)
    d = unit_rows(rng, 300, 8).astype(np.float32)
    exact = training_pair_scores(d)
    assert exact.size == 300 * 299 // 2
    sample = training_pair_scores(d, max_pairs=20_000, seed=3)
    assert sample.size == 20_000
    assert abs(np.median(sample) - np.median(exact)) < 0.02
    assert not np.isclose(sample, 1.0).any()  # never an image with itself


def test_pair_sample_memory_is_bounded_by_the_block():
    import tracemalloc

    rng = np.random.default_rng(4)
    d = unit_rows(rng, 3000, 512).astype(np.float32)
    whole = training_pair_scores(d, max_pairs=200_000, seed=1, block=200_000, workers=1)
    # Threads score blocks in any order, each pair the same dot product.
    np.testing.assert_array_equal(training_pair_scores(d, max_pairs=200_000, seed=1, block=777, workers=3), whole)
    tracemalloc.start()
    blocked = training_pair_scores(d, max_pairs=200_000, seed=1, block=1_000)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    np.testing.assert_array_equal(blocked, whole)
    # gathering every pair at once would take 2 × 200,000 × 512 × 4 B = 819 MB
    assert peak < 30e6, peak


def test_unknown_method():
    st = _stats([0.2], [0.1], [1], [0], 1)
    with pytest.raises(VPRInputError, match="choose one of simple, weighted"):
        place_thresholds(st, "median")
