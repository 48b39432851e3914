"""``scale.fast_paper_protocol`` against ``evaluation.paper_protocol``: the same numbers.

Every comparison is exact (recall, accepted, precision and own-traversal share: mean and
std; per split: ranks, answered places and images, the automatic and oracle θ) except the
per-place thresholds, which agree to float rounding (the fast path downdates float32
scores; see the package doc of ``vpr_explorer.protocols.scale``), and image-level ranks, which the
fast path resolves up to max(ks) (beyond: max(ks) + 1; Recall@K needs no more).
"""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest

import vpr_explorer.protocols.evaluation as evaluation
import vpr_explorer.protocols.scale.blocked_pass as pass_module
import vpr_explorer.protocols.scale.panel as panel
import vpr_explorer.protocols.scale.protocol as protocol
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.thresholds import pooled_pair_sample
from vpr_explorer.protocols.evaluation import draw_splits, paper_protocol
from vpr_explorer.protocols.options import TABLE_MEMORY, ProtocolOptions
from vpr_explorer.protocols.scale import fast_paper_protocol, make_layout, scale_splits
from vpr_explorer.protocols.scale.full_sums import SUM_LANES, full_set_sums
from vpr_explorer.protocols.scale.layout import as_layout32
from vpr_explorer.protocols.scale.panel import PassInputs
from vpr_explorer.protocols.scale.table import Entries
from vpr_explorer.protocols.scale.twins import Content, shared_places, twins

THETA_TOL = 1e-8  # per-place θ: float32 rounding in the downdated σ (typically 1e-11 here)


# --------------------------------------------------------------------------- data


def structured(seed=0, n_places=300, per_place=10, dim=256, noise=1.0, n_trav=2, rho=0.9):
    """Unit descriptors: place centres along a route (neighbours correlated) plus noise, shuffled."""
    rng = np.random.default_rng(seed)
    centres = np.empty((n_places, dim))
    prev = rng.standard_normal(dim)
    for k in range(n_places):
        prev = rho * prev + np.sqrt(1 - rho**2) * rng.standard_normal(dim)
        centres[k] = prev
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    labels = np.repeat(np.arange(n_places), per_place)
    d = centres[labels] + noise * rng.standard_normal((len(labels), dim)) / np.sqrt(dim)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    trav = np.tile(np.arange(per_place) % n_trav, n_places)
    perm = rng.permutation(len(labels))
    return d[perm].astype(np.float32), labels[perm], trav[perm]


def awkward(seed=0, n_places=260, dim=64, noise=1.0):
    """Unequal place sizes (2..15), empty place ids, skipped frames, exact duplicates.

    Duplicates: two images inside a place, one image across two places, a whole place
    copied into the next (identical training sets: the thresholds must tie exactly), and a
    place seen in one traversal only (no cross-condition match for its queries).
    """
    rng = np.random.default_rng(seed)
    sizes = rng.integers(2, 16, n_places)
    sizes[[5, 77]] = 0
    sizes[31] = sizes[30]
    centres = rng.standard_normal((n_places, dim))
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    labels = np.repeat(np.arange(n_places), sizes)
    d = centres[labels] + noise * rng.standard_normal((len(labels), dim)) / np.sqrt(dim)
    trav = rng.integers(0, 3, len(labels))
    inside = np.flatnonzero(labels == 10)
    d[inside[1]] = d[inside[0]]
    d[np.flatnonzero(labels == 21)[0]] = d[np.flatnonzero(labels == 20)[0]]
    d[labels == 31] = d[labels == 30]
    trav[labels == 31] = trav[labels == 30]
    trav[labels == 40] = 1
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    skipped = rng.standard_normal((50, dim))
    skipped /= np.linalg.norm(skipped, axis=1, keepdims=True)
    d = np.r_[d, skipped]
    labels = np.r_[labels, np.full(50, -1)]
    trav = np.r_[trav, rng.integers(0, 3, 50)]
    perm = rng.permutation(len(labels))
    return d[perm].astype(np.float32), labels[perm], trav[perm]


# --------------------------------------------------------------------------- comparisons


def reference_with_splits(monkeypatch, d, labels, trav, n_places, options):
    """``paper_protocol`` and the per-split scores it summarised."""
    captured = {}
    pooled = evaluation._pooled_splits

    def capture(*a, **k):
        captured["splits"] = pooled(*a, **k)
        return captured["splits"]

    monkeypatch.setattr(evaluation, "_pooled_splits", capture)
    ev = paper_protocol(d, labels, trav, n_places, options)
    monkeypatch.setattr(evaluation, "_pooled_splits", pooled)
    return ev, captured["splits"]


def assert_same_evaluation(ref, fast):
    assert [r.key for r in fast.rows] == [r.key for r in ref.rows]
    assert fast.settings == ref.settings and fast.notes == ref.notes and fast.ks == ref.ks
    for a, b in zip(ref.rows, fast.rows):
        for k in ref.ks:
            np.testing.assert_array_equal(b.recall[k], a.recall[k], err_msg=f"{a.key} R@{k}")
        for what in ("accepted", "precision", "own_traversal", "unknown_rejection"):
            x, y = getattr(a, what), getattr(b, what)
            assert (x is None) == (y is None), (a.key, what)
            if x is not None:
                np.testing.assert_array_equal(y, x, err_msg=f"{a.key} {what}")


def assert_same_splits(ref_splits, fast_splits, max_k):
    """Per split: θ to rounding, global θs exactly, every outcome exactly."""
    assert len(ref_splits) == len(fast_splits)
    for r, (a, b) in enumerate(zip(ref_splits, fast_splits)):
        assert list(b.outcomes) == list(a.outcomes)
        for key in ("simple", "weighted"):
            np.testing.assert_allclose(b.thresholds[key], a.thresholds[key], rtol=0, atol=THETA_TOL, equal_nan=True)
        for key in ("auto", "user"):
            assert b.thresholds.get(key) == a.thresholds.get(key), (r, key)
        # the oracle θ is one query's top score: the same query on both paths, its score to float32 rounding
        assert abs(b.thresholds["oracle"] - a.thresholds["oracle"]) <= 1e-6, (r, "oracle")
        for key, oa in a.outcomes.items():
            ob = b.outcomes[key]
            rank_a = oa.rank
            if key == "image-baseline":  # the fast path resolves image-level ranks up to max(ks)
                rank_a = np.where(np.isfinite(rank_a) & (rank_a > max_k), max_k + 1, rank_a)
            np.testing.assert_array_equal(ob.rank, rank_a, err_msg=f"split {r} {key} rank")
            np.testing.assert_array_equal(ob.answer_place, oa.answer_place, err_msg=f"split {r} {key} place")
            np.testing.assert_array_equal(ob.answer_image, oa.answer_image, err_msg=f"split {r} {key} image")
        np.testing.assert_array_equal(b.query_traversal, a.query_traversal)
        np.testing.assert_array_equal(b.train_traversal, a.train_traversal)


def check(monkeypatch, d, labels, trav, n_places, *, fast_kw=None, **kw):
    """``paper_protocol`` against ``fast_paper_protocol`` and ``scale_splits`` with ``ProtocolOptions(**kw)`` (3 runs
    unless said), the fast ones with ``fast_kw``'s pass options too."""
    options = ProtocolOptions(**{"runs": 3, **kw})
    fast_options = dataclasses.replace(options, **(fast_kw or {}))
    ref, ref_splits = reference_with_splits(monkeypatch, d, labels, trav, n_places, options)
    fast = fast_paper_protocol(d, labels, trav, n_places, fast_options)
    assert_same_evaluation(ref, fast)
    splits = draw_splits(labels, n_places, runs=options.runs, seed=options.seed)
    fast_splits = scale_splits(d, labels, trav, n_places, splits, fast_options)
    assert_same_splits(ref_splits, fast_splits, max(options.ks))
    return ref, fast


# --------------------------------------------------------------------------- tests


@pytest.fixture(scope="module")
def data3000():
    return structured()


@pytest.mark.parametrize("fast_kw", [{}, {"block": 640, "table_memory": 0}])
def test_equals_paper_protocol_structured(monkeypatch, data3000, fast_kw):
    # 3,000 × 256 in 300 places of 10: 2,700 training images, so the automatic θ samples
    # about 2M pairs (from the run's pooled tiles); block=640 makes 5 blocks, table_memory=0 spills
    d, labels, trav = data3000
    ref, fast = check(monkeypatch, d, labels, trav, 300, user_theta=0.3, fast_kw=fast_kw)
    r1 = ref.row("place-baseline").recall[1][0]
    assert 0.3 < r1 < 0.99, r1  # neither trivial nor hopeless: ranks and ties get exercised


def test_equals_paper_protocol_cross_condition(monkeypatch, data3000):
    d, labels, trav = data3000
    _, fast = check(monkeypatch, d, labels, trav, 300, cross_condition=True, fast_kw={"block": 1000})
    assert fast.row("place-baseline").own_traversal[0] == 0.0


@pytest.mark.parametrize("cross_condition", [False, True])
def test_equals_paper_protocol_unequal_places_and_ties(monkeypatch, cross_condition):
    d, labels, trav = awkward()
    check(monkeypatch, d, labels, trav, 260, seed=4, cross_condition=cross_condition, user_theta=0.2, ks=(1, 2, 7),
          fast_kw={"block": 500})


def test_equals_paper_protocol_hard_queries(monkeypatch):
    # heavy noise: many wrong places above the own one, image-level records overflow K
    d, labels, trav = awkward(seed=1, noise=4.0)
    check(monkeypatch, d, labels, trav, 260, runs=2, ks=(1, 3), fast_kw={"block": 600})


def test_the_automatic_theta_is_the_runs_pooled_sample(monkeypatch):
    # 2,400 images in 300 places of 8: 2,100 training images (2.2·10⁶ pairs), so sampled: both
    # paths take split r's θ from one tile sample of the run (thresholds.pooled_pair_sample)
    d, labels, trav = structured(seed=5, n_places=300, per_place=8, dim=32)
    _, ref_splits = reference_with_splits(monkeypatch, d, labels, trav, 300, ProtocolOptions(runs=3, seed=2))
    splits = draw_splits(labels, 300, runs=3, seed=2)
    sample = pooled_pair_sample(d, [sp.train for sp in splits], seed=2)
    assert 0 < len(sample.scores(0)) < 2_100 * 2_099 // 2  # a sample, not every pair
    want = [sample.theta(r) for r in range(3)]
    assert [s.thresholds["auto"] for s in ref_splits] == want
    fast = scale_splits(d, labels, trav, 300, splits, ProtocolOptions(seed=2, block=800))
    assert [s.thresholds["auto"] for s in fast] == want
    assert len(set(want)) == 3  # each split's own training pairs: three different θ


def test_equals_paper_protocol_small_exact_pair_branch(monkeypatch):
    # under 2,001 training images the automatic θ uses every pair, as the reference does
    d, labels, trav = structured(seed=3, n_places=90, per_place=8, dim=48)
    check(monkeypatch, d, labels, trav, 90, cross_condition=True, fast_kw={"block": 200})


@pytest.mark.parametrize("dtype", [np.float16, np.float64])
def test_equals_paper_protocol_other_dtypes(monkeypatch, tmp_path, dtype):
    if dtype == np.float16:  # the descriptor cache's half-precision, memory-mapped storage
        d, labels, trav = awkward(seed=2)
        np.save(tmp_path / "d.npy", d.astype(np.float16))
        d = np.load(tmp_path / "d.npy", mmap_mode="r")
        n_places = 260
    else:  # float64: scores from the float32 rounding, statistics from the float64 values
        d, labels, trav = structured(seed=2, n_places=150, per_place=12, dim=64)
        d = d.astype(np.float64) + 1e-6 * np.random.default_rng(0).standard_normal(d.shape)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        n_places = 150
    check(monkeypatch, d, labels, trav, n_places, runs=2, fast_kw={"block": 700})


def test_identical_places_tie_exactly_as_in_the_reference(monkeypatch):
    # place 30: one image six times; place 290 (another block) the same: equal training sets.
    # A shared component makes every score large, so float32 sums round in the last bits.
    d, labels, trav = structured(seed=4, n_places=400, per_place=6, dim=32, noise=2.0)
    d = d + 1.5 * np.ones(32, dtype=np.float32) / np.sqrt(32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[labels == 30] = d[np.flatnonzero(labels == 30)[0]]
    d[labels == 290] = d[labels == 30]
    _, ref_splits = reference_with_splits(monkeypatch, d, labels, trav, 400, ProtocolOptions(runs=3, seed=0))
    splits = draw_splits(labels, 400, runs=3, seed=0)
    fast_splits = scale_splits(d, labels, trav, 400, splits, ProtocolOptions(block=600))
    for a, b in zip(ref_splits, fast_splits):
        for key in ("simple", "weighted"):
            assert a.thresholds[key][30] == a.thresholds[key][290]  # the reference ties them ...
            assert b.thresholds[key][30] == b.thresholds[key][290]  # ... and so must we
    assert_same_splits(ref_splits, fast_splits, 10)  # and with them every margin tie


def test_twins_compare_only_places_that_share_an_image_and_match_all_places():
    # content classes with padding (-1), repeats inside one place (not a twin), places
    # sharing some images but not all, and places whose training sets are equal in some splits
    rng = np.random.default_rng(5)
    n_p, m = 300, 6
    classes = np.arange(n_p * m).reshape(n_p, m)
    classes[rng.random((n_p, m)) < 0.2] = -1  # padding slots
    classes[:, 0] = np.arange(n_p) * m  # every place has an image
    classes[10, 3] = classes[10, 2]  # a repeat within place 10 alone
    classes[200:210] = classes[100]  # ten places of the same images as place 100
    classes[50, :3] = classes[60, :3]  # places 50 and 60 share three images
    classes[71] = classes[70][::-1]  # the same images in another order
    content = Content(classes, shared_places(classes))
    assert list(content.shared) == [50, 60, 70, 71, 100] + list(range(200, 210))
    for _ in range(20):
        held = rng.integers(0, m, n_p)
        k = np.arange(m - 1)[None, :]
        seq = np.where(k < held[:, None], classes[:, :-1], classes[:, 1:])  # every place compared
        _, first, inverse = np.unique(seq, axis=0, return_index=True, return_inverse=True)
        np.testing.assert_array_equal(twins(content, held), first[inverse.ravel()])
    none = Content(classes[:50], shared_places(classes[:50]))
    assert len(none.shared) == 0
    np.testing.assert_array_equal(twins(none, held[:50]), np.arange(50))


def test_near_tie_repair_recomputes_exactly(monkeypatch):
    # with every weighted θ declared unreliable, every query is a near tie: the repair path
    # recomputes its places in float64, which must then agree with the closed form to the
    # last digits, and every outcome with the reference
    def unreliable(sd, lay, kappa):
        return np.full(len(lay.places), np.inf)

    d, labels, trav = awkward(seed=3)
    _, ref_splits = reference_with_splits(monkeypatch, d, labels, trav, 260, ProtocolOptions(runs=2, seed=0))
    monkeypatch.setattr(protocol, "uncertainty", unreliable)  # where scale_splits reads it
    fast = scale_splits(d, labels, trav, 260, draw_splits(labels, 260, runs=2, seed=0),
                        ProtocolOptions(block=600))
    assert_same_splits(ref_splits, fast, 10)
    for a, b in zip(ref_splits, fast):
        np.testing.assert_allclose(b.thresholds["weighted"], a.thresholds["weighted"], rtol=0, atol=1e-14,
                                   equal_nan=True)


def test_the_comparison_can_fail(monkeypatch, data3000):
    # a different seed is a different set of splits: the helpers must see it
    d, labels, trav = data3000
    ref, ref_splits = reference_with_splits(monkeypatch, d, labels, trav, 300, ProtocolOptions(runs=2, seed=0))
    fast = fast_paper_protocol(d, labels, trav, 300, ProtocolOptions(runs=2, seed=1))
    with pytest.raises(AssertionError):
        assert_same_evaluation(ref, fast)
    other = scale_splits(d, labels, trav, 300, draw_splits(labels, 300, runs=2, seed=1),
                         ProtocolOptions(seed=1))
    with pytest.raises(AssertionError):
        assert_same_splits(ref_splits, other, 10)


def test_layout_blocks_whole_places_slot_major():
    labels = np.array([2, 0, 2, 1, -1, 0, 2, 1, 1, 1])
    lay = make_layout(labels, 4, block_rows=8)
    assert list(lay.places) == [0, 1, 2] and lay.slots == 4
    real = lay.image_of_row >= 0
    # every labelled image once; its row holds its place and its rank within the place
    assert sorted(lay.image_of_row[real]) == [0, 1, 2, 3, 5, 6, 7, 8, 9]
    for img in np.flatnonzero(labels >= 0):
        row = lay.row_of_image[img]
        assert lay.places[lay.place_of_row[row]] == labels[img]
        assert lay.slot_of_row[row] == np.sum((labels == labels[img]) & (np.arange(10) < img))
    assert lay.row_of_image[4] == -1
    for b in range(lay.n_blocks):  # inside a block: slot-major, place-minor
        rows = lay.rows(b)
        g = lay.block_start[b + 1] - lay.block_start[b]
        assert list(lay.slot_of_row[rows]) == list(np.repeat(np.arange(4), g))


def test_bad_input_raises_like_the_reference():
    d, labels, trav = structured(seed=5, n_places=20, per_place=4, dim=16)
    with pytest.raises(VPRInputError, match="runs=0"):
        fast_paper_protocol(d, labels, trav, 20, ProtocolOptions(runs=0))
    with pytest.raises(VPRInputError, match="cross_condition needs at least 2 traversals"):
        fast_paper_protocol(d, labels, np.zeros_like(trav), 20, ProtocolOptions(runs=1, cross_condition=True))
    with pytest.raises(VPRInputError, match="have a single image"):
        fast_paper_protocol(d[:20], np.arange(20), trav[:20], 20, ProtocolOptions(runs=1))
    with pytest.raises(VPRInputError, match="block="):
        fast_paper_protocol(d, labels, trav, 20, ProtocolOptions(runs=1, block=0))
    with pytest.raises(VPRInputError, match="threads=0"):
        fast_paper_protocol(d, labels, trav, 20, ProtocolOptions(runs=1, threads=0))
    with pytest.raises(VPRInputError, match="threads=2.5"):
        ProtocolOptions(threads=2.5)
    with pytest.raises(VPRInputError, match="open set"):
        scale_splits(d, labels, trav, 20, draw_splits(labels, 20, runs=1, seed=0, unknown_share=0.3))


# --------------------------------------------------------------------------- real Nordland


@pytest.mark.realdata
def test_nordland_g3s3_pixels_equals_paper_protocol(monkeypatch, data_root):
    from vpr_explorer.data.traversals import load_dataset
    from vpr_explorer.pipeline import dataset_descriptors
    from vpr_explorer.method.places import PlaceSpec, make_places

    dataset = load_dataset(data_root / "Nordland_64x32")
    places = make_places(dataset, PlaceSpec(3, 3))
    desc = dataset_descriptors(dataset, "pixels")
    assert places.n_places == 1192 and desc.shape == (7152, 2048)
    ref, fast = check(monkeypatch, desc, places.image_place, dataset.image_traversal, places.n_places, runs=2)
    # (speed: benchmarks/bench_nordland_real.py; a timing assertion does not belong in a shared-CPU test)


# --------------------------------------------------------------------------- the candidate cutoff


def places_that_matter(raw, b, own, th_s, th_w):
    """``(n_queries, P)`` bool: the places that reach some method's rank or answer (brute force)."""
    matter = raw >= b[:, None]  # place and image baselines, global θs: everything at or above b
    for th in (th_s, th_w):
        m_own = (b - th[own])[:, None]
        kept_own = m_own >= 0
        kept = raw >= th[None, :]
        matter |= kept & ~kept_own  # own place dropped: any kept place may be the answer
        matter |= kept & kept_own & (raw - th[None, :] >= m_own)  # margin rule: ranks and answer
    return matter


def test_candidate_cutoff_holds_for_every_weighted_threshold_within_its_bound():
    # The scoring reads only table entries at or above the cutoff, and the near-tie check only
    # sees those: a place below it must not matter under any weighted θ within the bounds.
    from vpr_explorer.protocols.scale.scoring import candidate_cutoff

    # place 0's margin 0.2995 − 0.10 is just under the own place's 0.5 − 0.30; with θ_0 lower
    # by its bound 1e-3 it ranks above the own place
    th = np.array([0.10, 0.20, 0.30])
    unc = np.full(3, 1e-3)
    b, own = np.array([0.5]), np.array([2])
    assert places_that_matter(np.array([[0.2995, 0.0, 0.5]]), b, own, th, th - unc * [1, 0, 0])[0, 0]
    assert np.float32(0.2995) >= candidate_cutoff(b, own, th, th, unc)[0]

    rng = np.random.default_rng(0)
    n_q, n_p = 400, 30
    th_s = rng.uniform(0.1, 0.3, n_p)
    th_w = th_s + rng.normal(0, 0.02, n_p)
    unc = rng.uniform(0, 0.01, n_p) * (rng.random(n_p) < 0.7)  # 0: an exact place
    own = rng.integers(0, n_p, n_q)
    raw = rng.uniform(0.0, 0.6, (n_q, n_p)).astype(np.float32).astype(np.float64)
    b = raw[np.arange(n_q), own]
    b[:5] = -np.inf  # no image of the own place to match (cross-condition)
    cut = candidate_cutoff(b, own, th_s, th_w, unc)
    assert (raw < cut[:, None]).mean() > 0.2  # the cutoff still leaves places out
    for _ in range(50):  # weighted θs anywhere within their bounds, extremes included
        exact = th_w + unc * rng.choice([-1.0, 1.0, 0.0, -0.5], n_p)
        matter = places_that_matter(raw, b, own, th_s, exact)
        assert not (matter & (raw < cut[:, None])).any()


# --------------------------------------------------------------------------- ties across BLAS kernels

_TABLE_SCRIPT = """
import json, sys
from vpr_explorer.data.traversals import load_dataset
from vpr_explorer.protocols.evaluation import paper_protocol
from vpr_explorer.pipeline import dataset_descriptors
from vpr_explorer.method.places import PlaceSpec, make_places
from vpr_explorer.protocols.options import ProtocolOptions
from vpr_explorer.protocols.scale import fast_paper_protocol

ds = load_dataset(sys.argv[1])
pl = make_places(ds, PlaceSpec(3, 3))
d = dataset_descriptors(ds, "pixels")
args = (d, pl.image_place, ds.image_traversal, pl.n_places)
fast = ProtocolOptions(runs=2, block=int(sys.argv[2]), threads=int(sys.argv[3]))
out = {"fast": fast_paper_protocol(*args, fast).to_dict()["methods"]}
if sys.argv[4] == "ref":
    out["ref"] = paper_protocol(*args, ProtocolOptions(runs=2)).to_dict()["methods"]
print(json.dumps(out))
"""


@pytest.mark.realdata
def test_nordland_tables_do_not_depend_on_blas_kernel_block_size_or_threads(data_root):
    # Nordland's tunnels are runs of byte-identical frames: their scores against one query
    # differ in the last bit between BLAS kernels (Haswell vs Sandybridge vs the CPU's own),
    # block shapes and thread counts. With exact-equality ties the image-level R@5 would move;
    # with the 1e-5 tie tolerance every table must be the same, digit for digit.
    import json
    import os
    import subprocess
    import sys

    from vpr_explorer.data.traversals import load_dataset
    from vpr_explorer.pipeline import dataset_descriptors

    dataset = load_dataset(data_root / "Nordland_64x32")
    dataset_descriptors(dataset, "pixels")  # cached once for the subprocesses (same cache folder)
    configs = [  # (environment, block rows, pass threads, with the reference)
        ({"OPENBLAS_CORETYPE": "Haswell", "OPENBLAS_NUM_THREADS": "1"}, 1024, 1, "ref"),
        ({"OPENBLAS_NUM_THREADS": "2"}, 4096, 2, "ref"),
        ({"OPENBLAS_CORETYPE": "Sandybridge", "OPENBLAS_NUM_THREADS": "2"}, 2500, 2, "fast"),
    ]
    tables = []
    for extra, block, threads, which in configs:
        env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_CORETYPE", "OPENBLAS_L2_SIZE")}
        env.update(extra)
        res = subprocess.run([sys.executable, "-c", _TABLE_SCRIPT, str(data_root / "Nordland_64x32"), str(block),
                              str(threads), which], env=env, capture_output=True, text=True, timeout=600)
        assert res.returncode == 0, res.stderr[-3000:]
        out = json.loads(res.stdout.strip().splitlines()[-1])
        tables += [(f"{extra} {name} block={block} threads={threads}", t) for name, t in out.items()]
    first_name, first = tables[0]
    assert first[0]["key"] == "image-baseline" and 0.2 < first[0]["recall"]["5"]["mean"] < 0.6
    for name, table in tables[1:]:
        assert table == first, f"{name} differs from {first_name}"


def _run_pass(d, lay, query_rows, centre, threads, **kw):
    """``blocked_pass`` of these rows (no cross-condition, records cap 7, μ in [0, 0.2]): its result and entries."""
    entries = Entries(lay, TABLE_MEMORY, None)
    inputs = PassInputs(as_layout32(d, lay), lay, query_rows, None, (0.0, 0.2), centre)
    return pass_module.blocked_pass(inputs, entries, 7, ProtocolOptions(threads=threads), **kw), entries


def _pass_of(d, labels, n_places, splits, threads, block):
    """``blocked_pass`` on these splits: its sums, b, records and table, block by block."""
    lay = make_layout(labels, n_places, block)
    query_rows = np.stack([lay.row_of_image[sp.queries] for sp in splits])
    pas, entries = _run_pass(d, lay, query_rows, full_set_sums(d, lay, query_rows).centre, threads)
    table = [entries.get(b) for b in range(lay.n_blocks)]
    return pas, table


def test_panels_slabs_and_threads_give_the_same_numbers(monkeypatch):
    # the pass cuts each block pair into panels of whole places (one GEMM each), reads them
    # slab by slab, runs panels side by side in threads and merges them in task order: small
    # panels and slabs (several per block pair and per slot) give the reference's outcomes,
    # and the pass's sums, b and table do not depend on the number of threads, bit for bit
    monkeypatch.setattr(pass_module, "PANEL_ROWS", 45)  # read by blocked_pass
    monkeypatch.setattr(panel, "SLAB_ROWS", 2)  # read by PassState and the panels
    d, labels, trav = awkward(seed=2)
    check(monkeypatch, d, labels, trav, 260, seed=1, cross_condition=True, runs=2,
          fast_kw={"block": 500, "threads": 3})
    splits = draw_splits(labels, 260, runs=3, seed=1)
    (p1, t1), *others = (_pass_of(d, labels, 260, splits, threads, 500) for threads in (1, 2, 3))
    assert len(t1) > 1 and len(pass_module.panels_of(make_layout(labels, 260, 500), 0, 1, 45)) > 2
    for p, t in others:  # 1 thread (no pool, BLAS in its own threads), 2 and 3 threads
        np.testing.assert_array_equal(p.v, p1.v)
        np.testing.assert_array_equal(p.best_own, p1.best_own)
        np.testing.assert_array_equal(p.records.n, p1.records.n)
        np.testing.assert_array_equal(np.sort(p.records.place, axis=1), np.sort(p1.records.place, axis=1))
        for a, b in zip(t1, t):
            assert a.keys() == b.keys()
            for k in a:
                np.testing.assert_array_equal(b[k], a[k], err_msg=k)


def test_the_pass_against_straightforward_float64_sums():
    # V (each split's squared scores against its queries of other places) and b (the best
    # score of the image's own place, itself left out) of every labelled row, against plain
    # float64 sums over all pairs: panels of one place and of several, so that diagonal
    # blocks have many panels, each against the block's places from its own on (the rest
    # come by symmetry)
    d, labels, _ = awkward(seed=4)
    splits = draw_splits(labels, 260, runs=3, seed=2)
    lay = make_layout(labels, 260, 400)
    query_rows = np.stack([lay.row_of_image[sp.queries] for sp in splits])
    centre = full_set_sums(d, lay, query_rows).centre
    for panel_rows in (45, 240, pass_module.PANEL_ROWS):
        pas, _ = _run_pass(d, lay, query_rows, centre, 2, panel_rows=panel_rows)
        real = np.flatnonzero(lay.image_of_row >= 0)
        x = d[lay.image_of_row[real]].astype(np.float64)
        place = lay.place_of_row[real]
        s = x @ x.T
        q = (s - centre) ** 2
        q[place[:, None] == place[None, :]] = 0.0
        queries = np.zeros((len(real), len(splits)))
        position = np.full(lay.n_rows, -1)
        position[real] = np.arange(len(real))
        for r in range(len(splits)):
            queries[position[query_rows[r]], r] = 1.0
        v = q @ queries
        np.testing.assert_allclose(pas.v[real], v, rtol=1e-5, atol=1e-7)
        mine = np.where(place[:, None] == place[None, :], s, -np.inf)
        np.fill_diagonal(mine, -np.inf)
        np.testing.assert_allclose(pas.best_own[real], mine.max(axis=1), rtol=0, atol=1e-6)
    short, several = (pass_module.panels_of(lay, 0, 0, rows // pass_module.DIAGONAL_SPLIT) for rows in (45, 240))
    assert len(short) > 10 and len(several) > 3 and min(p.g1 - p.g0 for p in several) > 2


def test_a_failing_panel_on_the_diagonal_ends_the_pass(monkeypatch):
    # diagonal panels wait for the ones merged before them; an error in one must reach the
    # caller, not leave the others waiting (the pool could then never shut down)
    d, labels, _ = awkward(seed=4)
    splits = draw_splits(labels, 260, runs=2, seed=2)
    lay = make_layout(labels, 260, 400)
    query_rows = np.stack([lay.row_of_image[sp.queries] for sp in splits])
    calls, side = [0], panel.table_side

    def failing_side(*a, **k):
        calls[0] += 1
        if calls[0] == 3:
            raise RuntimeError("a panel failed")
        return side(*a, **k)

    monkeypatch.setattr(panel, "table_side", failing_side)  # read by the panels
    outcome = []

    def run():
        try:
            _run_pass(d, lay, query_rows, 0.1, 2, panel_rows=45)
        except RuntimeError as e:
            outcome.append(str(e))

    worker = threading.Thread(target=run, daemon=True)
    worker.start()
    worker.join(120)
    assert not worker.is_alive() and outcome == ["a panel failed"]


def test_full_sums_against_plain_float64_and_any_thread_count():
    # T, T_p, each split's query sums, the within-place grams, c and aᵢ = Σ_{j∉p(i)} (sᵢⱼ − c)²
    # against the formulas computed directly in float64; block sums dealt to lanes in order,
    # so 1, 2 and 3 threads, and the layout copy or a gather from the descriptors, give the
    # same numbers bit for bit (9 blocks: more than the lanes)
    d, labels, _ = awkward(seed=5)
    splits = draw_splits(labels, 260, runs=4, seed=3)
    lay = make_layout(labels, 260, 250)
    assert lay.n_blocks > SUM_LANES
    query_rows = np.stack([lay.row_of_image[sp.queries] for sp in splits])
    first = full_set_sums(d, lay, query_rows, 1)
    for threads, x32 in ((2, None), (3, as_layout32(d, lay)), (1, as_layout32(d, lay))):
        other = full_set_sums(d, lay, query_rows, threads, x32)
        for field in ("dot_other", "dot_queries", "gram", "a_centred"):
            np.testing.assert_array_equal(getattr(other, field), getattr(first, field), err_msg=field)
        assert other.centre == first.centre
    real = np.flatnonzero(lay.image_of_row >= 0)
    x = d[lay.image_of_row[real]].astype(np.float64)
    place = lay.place_of_row[real]
    s = x @ x.T
    same = place[:, None] == place[None, :]
    n = len(real)
    centre = np.float32((s.sum() - np.trace(s)) / (n * (n - 1)))
    assert first.centre == float(centre)
    np.testing.assert_allclose(first.dot_other[real], np.where(same, 0.0, s).sum(axis=1), rtol=1e-12, atol=1e-11)
    for r in range(len(splits)):
        np.testing.assert_allclose(first.dot_queries[real, r], x @ d[splits[r].queries].astype(np.float64).sum(axis=0),
                                   rtol=1e-12, atol=1e-11)
    np.testing.assert_allclose(first.gram[place, lay.slot_of_row[real], lay.slot_of_row[real]], np.diag(s), rtol=1e-12)
    a = np.where(same, 0.0, (s - float(centre)) ** 2).sum(axis=1)
    np.testing.assert_allclose(first.a_centred[real], a, rtol=1e-10)
    assert not first.a_centred[lay.image_of_row < 0].any() and not first.dot_other[lay.image_of_row < 0].any()


def test_torch_device_products_give_the_same_numbers(monkeypatch, device_under_test):
    # the pass on a torch device (its products and bookkeeping as torch operations: CPU tensors
    # here, the GPU under benchmarks/gpu_check.py); last-bit differences from numpy's sgemm
    # never cross the tie tolerance
    d, labels, trav = structured(seed=3, n_places=120, per_place=6, dim=48)
    check(monkeypatch, d, labels, trav, 120, runs=2, fast_kw={"block": 200, "device": device_under_test})
    with pytest.raises(VPRInputError, match="device='tpu'"):
        fast_paper_protocol(d, labels, trav, 120, ProtocolOptions(runs=2, device="tpu"))


def test_progress_counts_every_split_then_the_pass():
    d, labels, trav = structured(seed=6, n_places=40, per_place=4, dim=16)
    calls = []
    fast_paper_protocol(d, labels, trav, 40, ProtocolOptions(runs=7, block=64), progress=lambda *a: calls.append(a))
    totals = {t for _, t, _ in calls}
    assert len(totals) == 1 and calls[-1][0] == calls[-1][1]  # one total, reached at the end
    assert [m for _, _, m in calls[:7]] == [f"split {r}/7: automatic θ" for r in range(1, 8)]
    assert [n for n, _, _ in calls] == sorted(n for n, _, _ in calls)  # never goes backwards
    assert any("similarity block" in m for _, _, m in calls) and any("scoring block" in m for _, _, m in calls)
