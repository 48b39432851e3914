"""``shared_scores``: split statistics pairwise from a shared float64 Gram, and the protocols on it.

The pairwise statistics are checked against the loop reference (``reference.pairwise_negative_stats``)
and the float64 closed form (``stats.negative_stats(..., precision="float64")``), on a hand-computed
case and on structured and awkward descriptors (unequal places, skipped frames, duplicates, a
whole place copied); identical places must tie exactly. A protocol given shared scores equals
one that builds its own, bit for bit; above ``SHARED_LIMIT`` the closed form gives the same
outcomes.
"""

from __future__ import annotations

import numpy as np
import pytest
from reference import pairwise_negative_stats
from test_scale import awkward, structured

import vpr_explorer.protocols.shared_scores as shared_scores
from vpr_explorer.errors import VPRInputError
from vpr_explorer.protocols.evaluation import draw_splits, open_set_protocol, paper_protocol
from vpr_explorer.protocols.options import ProtocolOptions
from vpr_explorer.protocols.shared_scores import Negatives, SharedScores, resolve
from vpr_explorer.method.stats import negative_stats
from vpr_explorer.method.thresholds import place_thresholds

TOL = 1e-12  # |Δμ|, |Δσ| against both references (measured: 1e-16 to 7e-15)


def _everything(ev) -> dict:
    return {k: v for k, v in ev.to_dict().items() if k != "seconds"}


def _pairwise(d, labels, train, n_places, members=None):
    sh = SharedScores(d)
    members = np.flatnonzero(labels >= 0) if members is None else members
    return Negatives(sh.gram(), members).stats(train, labels[train], n_places)


def test_hand_computed_case():
    # 2-d unit vectors at angles: place 0 = {0°, 90°}, place 1 = {180°}, place 2 = {45°}
    ang = np.deg2rad([0.0, 90.0, 180.0, 45.0])
    d = np.c_[np.cos(ang), np.sin(ang)]
    labels = np.array([0, 0, 1, 2])
    st = _pairwise(d, labels, np.arange(4), 3)
    h = np.sqrt(0.5)
    # image 0: negatives −1 (180°), h (45°); image 1: 0, h; image 2: −1, 0, −h; image 3: h, h, −h
    expect = [[-1, h], [0, h], [-1, 0, -h], [h, h, -h]]
    np.testing.assert_allclose(st.mu, [np.mean(e) for e in expect], rtol=0, atol=1e-15)
    np.testing.assert_allclose(st.sigma, [np.std(e) for e in expect], rtol=0, atol=1e-15)
    assert st.n_neg.tolist() == [2, 2, 3, 3] and st.labels.tolist() == [0, 0, 1, 2]
    # a split without image 1 (a query): image 0 keeps −1 and h, image 2 loses 0
    st = _pairwise(d, labels, np.array([0, 2, 3]), 3)
    np.testing.assert_allclose(st.mu, [np.mean([-1, h]), np.mean([-1, -h]), np.mean([h, -h])], atol=1e-15)
    np.testing.assert_allclose(st.sigma, [np.std([-1, h]), np.std([-1, -h]), np.std([h, -h])], atol=1e-15)


@pytest.mark.parametrize("data, n_places, unknown_share", [
    ("structured", 120, None), ("structured", 120, 0.3), ("awkward", 260, None), ("awkward", 260, 0.25),
])
def test_split_statistics_equal_the_references(data, n_places, unknown_share):
    d, labels, _ = structured(seed=1, n_places=120, per_place=8, dim=64) if data == "structured" else awkward()
    sh = SharedScores(d)
    neg = Negatives(sh.gram(), np.flatnonzero(labels >= 0))
    for sp in draw_splits(labels, n_places, runs=2, seed=5, unknown_share=unknown_share):
        tr = sp.train
        st = neg.stats(tr, labels[tr], n_places)
        closed = negative_stats(d[tr], labels[tr], n_places, precision="float64")
        mu, sigma = pairwise_negative_stats(d[tr], labels[tr])
        np.testing.assert_array_equal(st.n_neg, closed.n_neg)
        for ref_mu, ref_sigma in ((mu, sigma), (closed.mu, closed.sigma)):
            np.testing.assert_allclose(st.mu, ref_mu, rtol=0, atol=TOL)
            np.testing.assert_allclose(st.sigma, ref_sigma, rtol=0, atol=TOL)


def test_shared_component_keeps_sigma_precise():
    # scores all near 0.95 with σ ≈ 0.02: sums about each row's centre do not cancel (the
    # closed form's E[s²] − μ² is ~2e-14 off here, the pairwise sums ~1e-17)
    d, labels, _ = structured(seed=2, n_places=60, per_place=6, dim=32, noise=0.3)
    d = d + 4.0 * np.ones(32, dtype=np.float32) / np.sqrt(32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    st = _pairwise(d, labels, np.arange(len(d)), 60)
    mu, sigma = pairwise_negative_stats(d, labels)
    assert 0.9 < mu.mean() < 0.99 and sigma.mean() < 0.03
    np.testing.assert_allclose(st.sigma, sigma, rtol=0, atol=1e-15)


def test_identical_places_and_duplicates_tie_exactly():
    # place 30: one image six times, place 290 the same, far apart in the matrix (a GEMM's rounding
    # can depend on a row's position: the Gram's rows are the distinct descriptors)
    d, labels, _ = structured(seed=4, n_places=400, per_place=6, dim=32, noise=2.0)
    d = d + 1.5 * np.ones(32, dtype=np.float32) / np.sqrt(32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[labels == 30] = d[np.flatnonzero(labels == 30)[0]]
    d[labels == 290] = d[labels == 30]
    g = SharedScores(d).gram()
    assert len(g.values) == len(d) - 11 and len(set(g.row[labels == 30]) | set(g.row[labels == 290])) == 1
    neg = Negatives(g, np.arange(len(d)))
    for sp in draw_splits(labels, 400, runs=3, seed=0):
        st = neg.stats(sp.train, labels[sp.train], 400)
        for method in ("simple", "weighted"):
            theta = place_thresholds(st, method)
            assert theta[30] == theta[290]
    # awkward: place 31 is place 30 copied, its images at other indices in another order: each
    # copy's μ, σ equal its original's bit for bit (θ_p then sums them in image order)
    d, labels, _ = awkward()
    members = np.flatnonzero(labels >= 0)
    st = _pairwise(d, labels, members, 260)
    g = SharedScores(d).gram()
    a, b = members[labels[members] == 30], members[labels[members] == 31]
    a, b = a[np.argsort(g.row[a])], b[np.argsort(g.row[b])]
    assert np.array_equal(g.row[a], g.row[b])
    at = np.searchsorted(members, [a, b])
    assert np.array_equal(st.mu[at[0]], st.mu[at[1]]) and np.array_equal(st.sigma[at[0]], st.sigma[at[1]])


def test_protocols_with_and_without_shared_scores_agree_bit_for_bit():
    d, labels, trav = awkward(seed=2)
    sh = SharedScores(d)
    options = ProtocolOptions(runs=3, seed=1, pr=True, k_grid=(0.0, 1.0))
    a = paper_protocol(d, labels, trav, 260, options, shared=sh)
    assert _everything(a) == _everything(paper_protocol(d, labels, trav, 260, options))
    a = open_set_protocol(d, labels, trav, 260, options, shared=sh)
    assert _everything(a) == _everything(open_set_protocol(d, labels, trav, 260, options))
    assert sh.gram() is sh.gram()  # one Gram of every image, shared by every run on them


def test_protocol_numbers_match_the_closed_form_above_the_limit(monkeypatch):
    # past SHARED_LIMIT the closed form: θ to float64 rounding, every outcome the same
    d, labels, trav = structured(seed=3, n_places=90, per_place=8, dim=48)
    options = ProtocolOptions(runs=3, user_theta=0.3)
    pairwise = paper_protocol(d, labels, trav, 90, options)
    monkeypatch.setattr(shared_scores, "SHARED_LIMIT", 100)
    assert resolve(None, d, len(d)) is None
    closed = paper_protocol(d, labels, trav, 90, options)
    assert pairwise.same_numbers(closed)


def test_wrong_descriptors_are_refused():
    d, labels, trav = structured(seed=5, n_places=20, per_place=4, dim=16)
    sh = SharedScores(d)
    other = d.copy()
    with pytest.raises(VPRInputError, match="shared scores were built from other descriptors"):
        paper_protocol(other, labels, trav, 20, ProtocolOptions(runs=1), shared=sh)
    with pytest.raises(VPRInputError, match="expected a SharedScores"):
        paper_protocol(d, labels, trav, 20, ProtocolOptions(runs=1), shared=d)
    assert resolve(sh, np.asarray(d), len(d)) is sh  # a view of the same memory is the same descriptors
    assert resolve(None, d, len(d)) is not sh  # none given: a new one
    with pytest.raises(VPRInputError, match="not among this run's members"):
        Negatives(sh.gram(), np.arange(10)).stats(np.arange(12), labels[:12], 20)
