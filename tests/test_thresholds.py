"""θ_p simple / weighted, the family θ_p(k), the automatic global threshold."""

import numpy as np
import pytest
from scipy.stats import norm

from reference import loop_auto_threshold, loop_thresholds, unit_rows
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.stats import NegativeStats, mixture_moments, negative_stats
from vpr_explorer.method.thresholds import (
    AUTO_Z,
    adaptive_k,
    auto_global_threshold,
    mixture_spread,
    place_thresholds,
    pooled_pair_sample,
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
    for kind in ("tiles", "pairs"):
        sample = training_pair_scores(d, max_pairs=20_000, seed=3, sample=kind)
        assert sample.size == 20_000 if kind == "pairs" else 17_000 <= sample.size <= 20_000
        assert abs(np.median(sample) - np.median(exact)) < 0.02
        assert not np.isclose(sample, 1.0).any()  # never an image with itself


def test_pair_sample_memory_is_bounded_by_the_block():
    import tracemalloc

    rng = np.random.default_rng(4)
    d = unit_rows(rng, 3000, 512).astype(np.float32)
    kw = {"max_pairs": 200_000, "seed": 1, "sample": "pairs"}
    whole = training_pair_scores(d, block=200_000, workers=1, **kw)
    # Threads score blocks in any order, each pair the same dot product.
    np.testing.assert_array_equal(training_pair_scores(d, block=777, workers=3, **kw), whole)
    tracemalloc.start()
    blocked = training_pair_scores(d, block=1_000, **kw)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    np.testing.assert_array_equal(blocked, whole)
    # gathering every pair at once would take 2 × 200,000 × 512 × 4 B = 819 MB
    assert peak < 30e6, peak


def test_unknown_method():
    st = _stats([0.2], [0.1], [1], [0], 1)
    with pytest.raises(VPRInputError, match="choose one of simple, weighted"):
        place_thresholds(st, "median")


# --------------------------------------------------------------------------- the tile sample


def test_tile_sample_pairs_are_distinct_balanced_and_exact(monkeypatch):
    import vpr_explorer.method.thresholds as thresholds

    rng = np.random.default_rng(5)
    n, dim = 1_000, 24
    d = unit_rows(rng, n, dim).astype(np.float32)
    monkeypatch.setattr(thresholds, "TILE_ROWS", 50)  # several chunks, the wrap tile in its own
    scores = training_pair_scores(d, max_pairs=20_000, seed=7, workers=3)
    # the same pairs, by hand: groups of the seeded permutation, group a against group a + 1
    perm = np.random.default_rng(7).permutation(n)
    edges, tiles = thresholds.tile_groups(n, 20_000)
    assert len(tiles) == len(edges) - 1 == 50
    pairs = np.concatenate([np.stack(np.meshgrid(perm[edges[a]:edges[a + 1]], perm[edges[b]:edges[b + 1]],
                                                 indexing="ij"), -1).reshape(-1, 2) for a, b in tiles])
    assert len(pairs) == len(scores) == 20_000
    assert (pairs[:, 0] != pairs[:, 1]).all()  # never an image with itself
    assert len({(min(i, j), max(i, j)) for i, j in pairs}) == len(pairs)  # each pair once
    assert set(np.bincount(pairs.ravel(), minlength=n)) == {40}  # every image in 2t pairs: balanced
    exact = np.einsum("ij,ij->i", d[pairs[:, 0]].astype(np.float64), d[pairs[:, 1]].astype(np.float64))
    np.testing.assert_allclose(scores, exact, rtol=0, atol=1e-6)
    # rows= reads a larger array in place; workers and BLAS threads change nothing
    big = unit_rows(rng, 3 * n, dim).astype(np.float32)
    at = rng.choice(3 * n, n, replace=False)
    big[at] = d
    np.testing.assert_array_equal(training_pair_scores(big, rows=at, max_pairs=20_000, seed=7, workers=1), scores)
    from threadpoolctl import threadpool_limits

    with threadpool_limits(2):
        np.testing.assert_array_equal(training_pair_scores(d, max_pairs=20_000, seed=7), scores)
    # just above the pair limit: three groups, three tiles
    small = unit_rows(rng, 210, dim).astype(np.float32)
    assert training_pair_scores(small, max_pairs=20_000, seed=1).size == 3 * 70 * 70
    with pytest.raises(VPRInputError, match="sample='grid'"):
        training_pair_scores(d, sample="grid")


def test_tile_sample_above_its_image_limit_reads_a_seeded_subset():
    import vpr_explorer.method.thresholds as thresholds

    # today's largest training sets (the app's 110k route, the protocols) keep their sample
    assert thresholds.AUTO_TILE_IMAGES > 110_364
    rng = np.random.default_rng(6)
    n, m, dim = 1_000, 400, 24
    d = unit_rows(rng, n, dim).astype(np.float32)
    plain = training_pair_scores(d, max_pairs=20_000, seed=7)
    np.testing.assert_array_equal(training_pair_scores(d, max_pairs=20_000, seed=7, images=n), plain)
    scores = training_pair_scores(d, max_pairs=20_000, seed=7, images=m, workers=3)
    # the same pairs, by hand: the first m of the seeded permutation, in groups, group a against a + 1
    sub = np.random.default_rng(7).permutation(n)[:m]
    edges, tiles = thresholds.tile_groups(m, 20_000)
    assert len(tiles) == 8 and set(np.diff(edges)) == {50}  # tiles of 50 × 50 instead of 20 × 20
    pairs = np.concatenate([np.stack(np.meshgrid(sub[edges[a]:edges[a + 1]], sub[edges[b]:edges[b + 1]],
                                                 indexing="ij"), -1).reshape(-1, 2) for a, b in tiles])
    assert len(pairs) == len(scores) == 20_000
    assert (pairs[:, 0] != pairs[:, 1]).all()
    assert len({(min(i, j), max(i, j)) for i, j in pairs}) == len(pairs)
    per_image = np.bincount(pairs.ravel(), minlength=n)
    assert set(per_image[sub]) == {100} and not per_image[np.setdiff1d(np.arange(n), sub)].any()
    exact = np.einsum("ij,ij->i", d[pairs[:, 0]].astype(np.float64), d[pairs[:, 1]].astype(np.float64))
    np.testing.assert_allclose(scores, exact, rtol=0, atol=1e-6)
    big = unit_rows(rng, 3 * n, dim).astype(np.float32)
    at = rng.choice(3 * n, n, replace=False)
    big[at] = d
    np.testing.assert_array_equal(training_pair_scores(big, rows=at, max_pairs=20_000, seed=7, images=m), scores)
    # the independent pairs are never a subset's; a subset too small for max_pairs is refused
    assert training_pair_scores(d, max_pairs=20_000, seed=7, sample="pairs", images=m).size == 20_000
    with pytest.raises(VPRInputError, match="images=150"):
        training_pair_scores(d, max_pairs=20_000, images=150)


def hub_descriptors(n=2_500, dim=32, places=250, seed=0):
    """Place structure plus a per-image shift along one direction: some images score high with
    everything (row effects), the case where pairs sharing a row are most correlated."""
    rng = np.random.default_rng(seed)
    centres = rng.standard_normal((places, dim))
    d = centres[rng.integers(0, places, n)] + rng.standard_normal((n, dim))
    d += 1.5 * rng.standard_normal((n, 1)) / np.sqrt(dim)
    return (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


@pytest.mark.parametrize("images", [None, 1_250], ids=["all images", "subset"])
def test_tile_sample_threshold_agrees_with_independent_pairs_within_sampling_error(images):
    # The tile sample's pairs share rows and columns (correlated); over seeds its θ must
    # centre on the independent-pairs θ, within their sampling error, and spread no wider.
    # A subset of 1,250 of the 2,500 images gives tiles of 16 × 16 at 20,000 pairs, as
    # AUTO_TILE_IMAGES (131,072) gives tiles of 15 × 15 at AUTO_MAX_PAIRS above it.
    d = hub_descriptors()
    full = auto_global_threshold(training_pair_scores(d, max_pairs=10**8))  # all 3.1·10⁶ pairs
    seeds = 40
    kw = {} if images is None else {"images": images}
    theta = {kind: np.array([auto_global_threshold(training_pair_scores(d, max_pairs=20_000, seed=s, sample=kind,
                                                                         **kw))
                             for s in range(seeds)]) for kind in ("tiles", "pairs")}
    sd = {k: v.std(ddof=1) for k, v in theta.items()}
    assert 1e-3 < sd["pairs"] < 0.05  # a real sampling error to compare against
    se = np.sqrt((sd["tiles"] ** 2 + sd["pairs"] ** 2) / seeds)
    assert abs(theta["tiles"].mean() - theta["pairs"].mean()) < 3 * se
    assert sd["tiles"] < 1.5 * sd["pairs"]
    assert np.abs(theta["tiles"] - full).max() < 4 * sd["pairs"]


# --------------------------------------------------------------------------- one sample for all splits


def _kept(sample, r):
    """Which pooled pairs have both images in split r's training set (a plain membership test)."""
    train = sample.trains[r]
    return np.isin(sample.image_a, train) & np.isin(sample.image_b, train)


@pytest.mark.parametrize("unknown_share", [None, 0.3])
def test_pooled_sample_keeps_exactly_each_splits_training_pairs(unknown_share):
    from vpr_explorer.protocols.evaluation import draw_splits

    rng = np.random.default_rng(2)
    n_places, per_place, dim = 200, 6, 24
    labels = np.repeat(np.arange(n_places), per_place)
    labels[::97] = -1  # skipped frames: in no training set, so in no pooled pair
    d = unit_rows(rng, len(labels), dim).astype(np.float32)
    splits = draw_splits(labels, n_places, runs=4, seed=1, unknown_share=unknown_share)
    sample = pooled_pair_sample(d, [sp.train for sp in splits], max_pairs=20_000, seed=5, workers=3)
    pooled = set(zip(sample.image_a.tolist(), sample.image_b.tolist()))
    assert len(pooled) == len(sample.pooled)  # distinct ordered pairs ...
    assert len({(min(i, j), max(i, j)) for i, j in pooled}) == len(pooled)  # ... and distinct unordered
    assert (sample.image_a != sample.image_b).all() and (labels[sample.image_a] >= 0).all()
    union = np.unique(np.concatenate([sp.train for sp in splits]))  # images that train in some split
    counts = np.bincount(np.r_[sample.image_a, sample.image_b], minlength=len(d))
    assert counts[union].max() - counts[union].min() <= 2  # every pooled image in as many pairs (to within 2)
    assert counts.sum() == counts[union].sum()  # and no other image
    exact = np.einsum("ij,ij->i", d[sample.image_a].astype(np.float64), d[sample.image_b].astype(np.float64))
    np.testing.assert_allclose(sample.pooled, exact, rtol=0, atol=1e-6)
    assert (np.diff(sample.pooled) >= 0).all()
    for r, sp in enumerate(splits):
        keep = _kept(sample, r)
        a, b = sample.image_a[keep], sample.image_b[keep]
        train = set(sp.train.tolist())
        want = [(i, j) for i, j in pooled if i in train and j in train]  # the pooled pairs of training images
        assert sorted(zip(a.tolist(), b.tolist())) == sorted(want)
        assert not set(a.tolist()) & set(sp.queries.tolist())  # the queries' rows and columns are dropped
        if unknown_share:
            assert not sp.unknown[labels[np.r_[a, b]]].any()  # so are the held-out places' images
        scores = sample.scores(r)
        assert 0.8 * 20_000 < len(scores) <= 1.05 * 20_000  # about max_pairs for every split
        np.testing.assert_array_equal(scores, sample.pooled[keep])  # those pairs' scores, ascending
        assert sample.theta(r) == auto_global_threshold(scores)  # bit for bit
    # the same sample whatever the threads; a training set of at most max_pairs pairs uses all of them
    again = pooled_pair_sample(d, [sp.train for sp in splits], max_pairs=20_000, seed=5, workers=1)
    np.testing.assert_array_equal(again.pooled, sample.pooled)
    small = pooled_pair_sample(d, [sp.train[:150] for sp in splits], max_pairs=20_000, seed=5)
    assert small.pooled.size == 0
    np.testing.assert_array_equal(small.scores(1), training_pair_scores(d[splits[1].train[:150]]))
    assert small.theta(1) == auto_global_threshold(training_pair_scores(d[splits[1].train[:150]]))


def test_theta_from_sorted_scores_is_np_median_bit_for_bit():
    from vpr_explorer.method.thresholds import _sorted_auto_threshold

    rng = np.random.default_rng(0)
    for t in range(2_000):
        n = int(rng.integers(1, 80))
        if t % 2:  # many ties: a few distinct values
            s = rng.choice(np.round(rng.normal(size=6), 1), n).astype(np.float32)
        else:
            s = rng.normal(0.3, 0.1, n).astype(np.float32)
        s = np.sort(s)
        assert _sorted_auto_threshold(s) == auto_global_threshold(s), (t, s)
    assert _sorted_auto_threshold(np.array([0.5], dtype=np.float32)) == 0.5
    with pytest.raises(VPRInputError, match="at least one training score"):
        _sorted_auto_threshold(np.empty(0, dtype=np.float32))


def test_pooled_threshold_agrees_with_a_per_split_sample_within_sampling_error():
    # One run's splits share one pooled sample; over seeds, a split's θ from it must centre on
    # the θ of its own tile sample (``training_pair_scores`` per split) within their sampling
    # error, spread no wider, and sit near the θ of all its training pairs.
    from vpr_explorer.protocols.evaluation import draw_splits

    d = hub_descriptors(n=2_750)
    labels = np.arange(len(d)) % 250  # 250 places of 11: 2,500 training images, 3.1·10⁶ pairs
    trains = [sp.train for sp in draw_splits(labels, 250, runs=3, seed=0)]
    train = trains[0]  # the pooled tiles cover all 2,750 images; split 0 drops its 250 queries
    full = auto_global_threshold(training_pair_scores(d[train], max_pairs=10**8))
    seeds = 40
    pooled = np.array([pooled_pair_sample(d, trains, max_pairs=20_000, seed=s).theta(0) for s in range(seeds)])
    own = np.array([auto_global_threshold(training_pair_scores(d[train], max_pairs=20_000, seed=s))
                    for s in range(seeds)])
    sd_pooled, sd_own = pooled.std(ddof=1), own.std(ddof=1)
    assert 1e-3 < sd_own < 0.05  # a real sampling error to compare against
    assert abs(pooled.mean() - own.mean()) < 3 * np.sqrt((sd_pooled**2 + sd_own**2) / seeds)
    assert sd_pooled < 1.5 * sd_own
    assert np.abs(pooled - full).max() < 4 * sd_own


@pytest.mark.parametrize("caller_threads", [1, 2])
def test_all_training_pairs_score_the_same_bits_whatever_the_callers_blas_threads(caller_threads):
    # OpenBLAS's Haswell kernel splits the sums of d @ dᵀ between its threads; the fast path
    # scores these pairs in a thread beside another thread's one-thread limiter, the reference
    # in the main thread: both must get the bits of one BLAS thread
    from threadpoolctl import threadpool_limits

    d = unit_rows(np.random.default_rng(3), 780, 260)
    iu = np.triu_indices(len(d), k=1)
    x = d.astype(np.float32)
    with threadpool_limits(1, "blas"):
        one = (x @ x.T)[iu]  # one operand: numpy's symmetric product, as the library's
    with threadpool_limits(caller_threads, "blas"):
        got = training_pair_scores(d)
    assert got.dtype == np.float32 and len(got) == len(iu[0])
    np.testing.assert_array_equal(got, one)
