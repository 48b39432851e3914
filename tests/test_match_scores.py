"""Training-free match scores (``method.match_scores``): L2 top-1 distance, PA-ratio and SUE.

Each function is checked against a plain loop written from the definitions (one query at a
time, Python lists and ``math``; SUE's softmax in the public code's literal form
exp(−slope·d)/Σ, without the shift the library uses), on hand cases, on boundaries (ties
for the top two, exact ties at the K-th, the clip bound, excluded images, one-image
databases), on bad input, and on GardensPoint night_right against day_right (pixels, the
traversal-positions example layout's positions), where PA-ratio's AUC-PR of the top-1
decision must beat random scores.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.match_scores import (
    BLOCK_ELEMENTS,
    MatchScores,
    descriptor_distance,
    pa_ratio,
    sue,
    top1_distance,
)

TOL = 1e-5  # retrieval.TIE_TOLERANCE, written out: the reference does not import the library's rules


# --------------------------------------------------------------------------- plain-loop references


def ref_dist(s: float) -> float:
    return math.inf if s == -math.inf else math.sqrt(max(0.0, 2.0 - 2.0 * s))


def ref_order(row) -> list[int]:
    """Database indices, largest similarity first, exact ties by index; excluded images left out."""
    return sorted((i for i in range(len(row)) if row[i] != -math.inf), key=lambda i: (-float(row[i]), i))


def ref_top1(row) -> int:
    order = ref_order(row)
    if not order:
        return -1
    best = float(row[order[0]])
    return min(i for i in order if float(row[i]) >= best - TOL)


def ref_l2(sims) -> list[tuple[float, int]]:
    out = []
    for row in sims:
        order = ref_order(row)
        out.append((ref_dist(float(row[order[0]])) if order else math.inf, ref_top1(row)))
    return out


def ref_pa(sims) -> list[float]:
    out = []
    for row in sims:
        order = ref_order(row)
        if not order:
            out.append(math.inf)
        elif len(order) == 1:
            out.append(0.0)
        else:
            s1, s2 = float(row[order[0]]), float(row[order[1]])
            out.append(1.0 if s1 - s2 <= TOL else ref_dist(s1) / ref_dist(s2))
    return out


def ref_sue(sims, xy, k=10, slope=350.0, clip_m=500.0) -> list[float]:
    out = []
    for row in sims:
        top = ref_order(row)[:k]
        if not top:
            out.append(math.inf)
            continue
        e = [math.exp(-slope * ref_dist(float(row[i]))) for i in top]
        w = [v / sum(e) for v in e]
        mx = sum(wi * float(xy[i][0]) for wi, i in zip(w, top))
        my = sum(wi * float(xy[i][1]) for wi, i in zip(w, top))

        def c(v):
            return v if clip_m is None else min(clip_m, max(-clip_m, v))

        var_x = sum(wi * c(float(xy[i][0]) - mx) ** 2 for wi, i in zip(w, top))
        var_y = sum(wi * c(float(xy[i][1]) - my) ** 2 for wi, i in zip(w, top))
        out.append((var_x + var_y) / 2)
    return out


def random_sims(rng, n_q, n_db, dim=16, dup=True):
    """Cosines of random unit descriptors; with ``dup``, repeated database rows make exact ties."""
    db = rng.normal(size=(n_db, dim)).astype(np.float32)
    if dup and n_db > 4:
        db[1::4] = db[0::4][: len(db[1::4])]
    q = rng.normal(size=(n_q, dim)).astype(np.float32)
    db /= np.linalg.norm(db, axis=1, keepdims=True)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q @ db.T


# --------------------------------------------------------------------------- hand cases


def test_distance_of_unit_descriptors():
    s = np.array([1.0, 0.5, 0.0, -1.0, 1.0000001, -np.inf])
    np.testing.assert_allclose(descriptor_distance(s), [0.0, 1.0, math.sqrt(2), 2.0, 0.0, np.inf])


def test_two_database_images_at_known_distances():
    sims = np.array([[0.5, 0.875]], dtype=np.float32)  # d = 1 and 0.5, exactly
    l2 = top1_distance(sims)
    assert isinstance(l2, MatchScores)
    assert l2.score.dtype == np.float64 and l2.top1.dtype == np.int64
    assert l2.score.tolist() == [0.5] and l2.top1.tolist() == [1]
    pa = pa_ratio(sims)
    assert pa.score.tolist() == [0.5] and pa.top1.tolist() == [1]  # exactly at τ = 0.5: accepted by u ≤ τ
    # two images, slope 2: w ∝ (e^-1, e^-2) on the top-1 and the other; positions 100 m apart on x
    s = sue(sims, np.array([[100.0, 0.0], [0.0, 0.0]]), slope=2.0)
    w1, w2 = 1 / (1 + math.exp(-1)), math.exp(-1) / (1 + math.exp(-1))
    assert s.score[0] == pytest.approx(1e4 * w1 * w2 / 2, rel=1e-12)
    assert s.top1.tolist() == [1]


def test_top_two_ties_give_ratio_one():
    sims = np.array([
        [0.9, 0.9, 0.1],          # exact tie
        [0.9, 0.9 + 5e-6, 0.1],   # within the tolerance: tie; top-1 the lower index
        [0.9, 0.9 + 4e-5, 0.1],   # beyond: a ratio just under 1
        [1.0, 1.0, 0.3],          # d2 = 0 (and d1 = 0)
        [0.2, 0.7, 0.7],          # tie for the top, not at index 0
    ], dtype=np.float64)
    pa = pa_ratio(sims)
    assert pa.score[[0, 1, 3, 4]].tolist() == [1.0, 1.0, 1.0, 1.0]
    assert 0.999 < pa.score[2] < 1.0
    assert pa.top1.tolist() == [0, 0, 1, 0, 1]
    np.testing.assert_array_equal(pa.score, ref_pa(sims))


def test_one_image_database_and_excluded_images():
    sims = np.array([[0.3], [-np.inf]])
    pa = pa_ratio(sims)
    assert pa.score.tolist() == [0.0, math.inf] and pa.top1.tolist() == [0, -1]
    two = np.array([[0.3, -np.inf], [-np.inf, -np.inf], [-np.inf, 0.5]])
    pa2 = pa_ratio(two)
    assert pa2.score.tolist() == [0.0, math.inf, 0.0] and pa2.top1.tolist() == [0, -1, 1]
    l2 = top1_distance(two)
    assert l2.score[1] == math.inf and l2.score[2] == pytest.approx(1.0)
    xy = np.array([[0.0, 0.0], [300.0, 0.0]])
    for slope in (350.0, 0.0):  # an excluded image weighs nothing, whatever the slope
        s = sue(two, xy, slope=slope)
        assert s.score.tolist() == [0.0, math.inf, 0.0] and s.top1.tolist() == [0, -1, 1]


def test_sue_top_k_at_one_position_is_zero():
    rng = np.random.default_rng(0)
    sims = random_sims(rng, 5, 30, dup=False)
    xy = np.tile([[512_345.678, 6_960_123.4]], (30, 1))  # UTM-sized coordinates, all one spot
    assert sue(sims, xy).score.tolist() == [0.0] * 5
    xy2 = rng.uniform(0, 1000, size=(30, 2))
    assert sue(sims, xy2, k=1).score.tolist() == [0.0] * 5


def test_sue_clips_each_axis_at_the_bound():
    sims = np.array([[0.5, 0.5]])  # equal distances: w = 1/2 each, mean halfway
    at = lambda dx, **kw: sue(sims, np.array([[0.0, 0.0], [dx, 0.0]]), **kw).score[0]  # noqa: E731
    assert at(1000.0) == 125_000.0   # deviations exactly ±500: at the bound, unchanged
    assert at(2000.0) == 125_000.0   # ±1000 clipped to ±500, both signs
    assert at(998.0) == pytest.approx(0.5 * 499.0 ** 2 * 2 / 2)
    assert at(2000.0, clip_m=None) == 500_000.0
    assert at(2000.0, clip_m=100.0) == 5_000.0   # ½ (½·100² + ½·100²)
    # the y axis is clipped on its own
    assert sue(sims, np.array([[0.0, 0.0], [0.0, 4000.0]])).score[0] == 125_000.0


def test_sue_weights_follow_the_slope():
    sims = np.array([[0.875, 0.5, 0.5]])  # d = 0.5, 1, 1
    xy = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 0.0]])
    flat = sue(sims, xy, slope=0.0).score[0]
    assert flat == pytest.approx((1 / 3 * (200 / 3) ** 2 + 2 / 3 * (100 / 3) ** 2) / 2)
    steep = sue(sims, xy, slope=350.0).score[0]
    assert 0.0 < steep < 1e-70  # all weight on the top-1 (e^-175 on the others)
    np.testing.assert_allclose([flat, steep], [ref_sue(sims, xy, slope=0.0)[0], ref_sue(sims, xy)[0]], rtol=1e-9)


def test_sue_exact_ties_at_the_kth_go_to_the_lowest_index():
    sims = np.array([[0.9, 0.5, 0.5, 0.5, 0.1]])
    xy = np.array([[0.0, 0.0], [10.0, 0.0], [50.0, 0.0], [90.0, 0.0], [0.0, 0.0]])
    got = sue(sims, xy, k=2, slope=0.0).score[0]
    assert got == pytest.approx(0.5 * 5.0 ** 2 * 2 / 2)  # images 0 and 1, not 2 or 3
    got3 = sue(sims, xy, k=3, slope=0.0).score[0]
    assert got3 == pytest.approx(ref_sue(sims, xy, k=3, slope=0.0)[0])


def test_no_queries():
    sims = np.zeros((0, 4), dtype=np.float32)
    for r in (top1_distance(sims), pa_ratio(sims), sue(sims, np.zeros((4, 2)))):
        assert r.score.shape == (0,) and r.top1.shape == (0,)


def test_results_are_read_only():
    r = pa_ratio(np.array([[0.1, 0.2]]))
    with pytest.raises(ValueError):
        r.score[0] = 0.0


# --------------------------------------------------------------------------- against the loop


@pytest.mark.parametrize("block", [None, 1, 7, 1000])
def test_vectorised_equals_the_loop_on_random_similarities(block):
    rng = np.random.default_rng(3)
    sims = random_sims(rng, 40, 37)
    sims[5, :] = -np.inf
    sims[6, 3:] = -np.inf  # three candidates: fewer than K
    sims[7] = sims[7, 0]   # every image tied
    xy = rng.uniform(-800, 800, size=(37, 2))
    l2 = top1_distance(sims, block=block)
    ref = ref_l2(sims)
    np.testing.assert_allclose(l2.score, [r[0] for r in ref], rtol=1e-12)
    assert l2.top1.tolist() == [r[1] for r in ref]
    pa = pa_ratio(sims, block=block)
    np.testing.assert_allclose(pa.score, ref_pa(sims), rtol=1e-12)
    assert pa.top1.tolist() == l2.top1.tolist()
    for kw in ({}, {"k": 3, "slope": 20.0}, {"k": 50, "slope": 0.0, "clip_m": None}, {"k": 4, "clip_m": 250.0}):
        s = sue(sims, xy, block=block, **kw)
        np.testing.assert_allclose(s.score, ref_sue(sims, xy, **kw), rtol=1e-9, atol=1e-9)
        assert s.top1.tolist() == l2.top1.tolist()


def test_default_block_splits_large_inputs(monkeypatch):
    import vpr_explorer.method.match_scores as ms

    rng = np.random.default_rng(4)
    sims = random_sims(rng, 23, 11)
    xy = rng.uniform(0, 600, size=(11, 2))
    whole = (top1_distance(sims).score, pa_ratio(sims).score, sue(sims, xy).score)
    monkeypatch.setattr(ms, "BLOCK_ELEMENTS", 30)  # 2 queries a block
    assert ms.BLOCK_ELEMENTS != BLOCK_ELEMENTS
    split = (top1_distance(sims).score, pa_ratio(sims).score, sue(sims, xy).score)
    for a, b in zip(whole, split):
        np.testing.assert_array_equal(a, b)


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("sims, words", [
    (np.zeros(4), "shape"),
    (np.zeros((2, 3, 1)), "shape"),
    (np.zeros((2, 0)), "at least one database column"),
    (np.zeros((2, 3), dtype=np.int64), "float"),
    (np.array([[0.1, np.nan]]), "row 0 holds NaN"),
    (np.array([[0.1, 0.2], [np.inf, 0.1]]), "sims[1, 0]"),
    (np.array([[0.1, 1.5]]), "cosines"),
    (np.array([[-np.inf, -3.0]]), "cosines"),
])
def test_bad_similarities_raise(sims, words):
    for f in (top1_distance, pa_ratio, lambda s: sue(s, np.zeros((s.shape[-1] if s.ndim else 0, 2)))):
        with pytest.raises(VPRInputError, match="sims") as e:
            f(sims)
        assert words in str(e.value)


def test_float_rounding_just_outside_one_is_accepted():
    sims = np.array([[1.0000001, 0.2]], dtype=np.float32)
    assert top1_distance(sims).score.tolist() == [0.0]


@pytest.mark.parametrize("kw, name", [
    ({"k": 0}, "k"), ({"k": 2.5}, "k"), ({"k": True}, "k"),
    ({"slope": -1.0}, "slope"), ({"slope": math.nan}, "slope"), ({"slope": math.inf}, "slope"), ({"slope": "x"}, "slope"),
    ({"clip_m": 0.0}, "clip_m"), ({"clip_m": -5.0}, "clip_m"), ({"clip_m": math.nan}, "clip_m"),
    ({"block": 0}, "block"), ({"block": 1.5}, "block"),
])
def test_bad_sue_parameters_raise(kw, name):
    with pytest.raises(VPRInputError, match=f"^{name} = "):
        sue(np.array([[0.1, 0.2]]), np.zeros((2, 2)), **kw)


@pytest.mark.parametrize("xy", [np.zeros((3, 2)), np.zeros((2, 3)), np.zeros(4), np.array([[0.0, 0.0], [np.nan, 1.0]]),
                                np.array([["a", "b"], ["c", "d"]])])
def test_bad_positions_raise(xy):
    with pytest.raises(VPRInputError, match="database_xy"):
        sue(np.array([[0.1, 0.2]]), xy)


def test_bad_block_raises_for_every_score():
    for f in (top1_distance, pa_ratio):
        with pytest.raises(VPRInputError, match="^block = "):
            f(np.array([[0.1, 0.2]]), block=-1)


# --------------------------------------------------------------------------- real data


@pytest.fixture(scope="module")
def gp_night_vs_day(data_root, tmp_path_factory):
    """GardensPoint night_right queries against day_right: similarities, positions, ground truth."""
    from vpr_explorer.data.example_layouts import write_gardens_point_layouts
    from vpr_explorer.method.retrieval import similarity
    from vpr_explorer.pipeline import dataset_descriptors, open_dataset

    paths = write_gardens_point_layouts(data_root / "GardensPointWalking", tmp_path_factory.mktemp("gp_layouts"))
    v = open_dataset(paths["traversal-positions"], database=["day_right"], queries="night_right")
    assert v.traversals == ("day_right", "night_right") and v.database_xy is not None
    d = dataset_descriptors(v, "pixels")
    return similarity(d[v.n_database:], d[:v.n_database]), v


@pytest.mark.realdata
def test_gardens_point_vectorised_equals_loop(gp_night_vs_day):
    sims, v = gp_night_vs_day
    assert sims.shape == (200, 200)
    l2 = top1_distance(sims, block=64)
    ref = ref_l2(sims)
    np.testing.assert_allclose(l2.score, [r[0] for r in ref], rtol=1e-12)
    assert l2.top1.tolist() == [r[1] for r in ref]
    pa = pa_ratio(sims, block=64)
    np.testing.assert_allclose(pa.score, ref_pa(sims), rtol=1e-12)
    s = sue(sims, v.database_xy, block=64)
    np.testing.assert_allclose(s.score, ref_sue(sims, v.database_xy), rtol=1e-9, atol=1e-6)
    assert (s.score > 0).any() and (s.score <= 500.0 ** 2).all()  # the clip bounds the spread


@pytest.mark.realdata
def test_gardens_point_pa_ratio_beats_random_scores(gp_night_vs_day):
    from vpr_explorer.protocols.precision_recall import pr_curve

    sims, v = gp_night_vs_day
    gt = v.ground_truth
    pa = pa_ratio(sims)
    right = np.array([t in gt.positives(q) for q, t in enumerate(pa.top1)])
    known = gt.known
    aucs = {name: pr_curve(-r.score, right, known).auc
            for name, r in (("L2", top1_distance(sims)), ("PA", pa), ("SUE", sue(sims, v.database_xy)))}
    rng = np.random.default_rng(0)
    random_aucs = [pr_curve(rng.random(len(right)), right, known).auc for _ in range(50)]
    print(f"GardensPoint night_right vs day_right, pixels: R@1 {right.mean():.3f}; AUC-PR of the top-1 decision "
          + ", ".join(f"{k} {a:.3f}" for k, a in aucs.items())
          + f"; random scores {np.mean(random_aucs):.3f} (max of 50: {np.max(random_aucs):.3f})")
    assert 0.0 < aucs["PA"] <= right.mean()  # recall is counted over known queries: at most R@1
    assert aucs["PA"] > max(random_aucs)


@pytest.mark.realdata
def test_nordland_subset_vectorised_equals_loop(data_root):
    """Nordland winter against summer (pixels): 150 queries spread over the route against all 3,576 images.

    Nordland's aligned traversals carry no positions: frames 10 m apart along x stand in for them.
    Its tunnel frames are byte-identical, so exact ties at the top and at the K-th occur.
    """
    from vpr_explorer.data.aligned import database_queries, value_rows
    from vpr_explorer.method.retrieval import similarity
    from vpr_explorer.pipeline import dataset_descriptors, resolve_dataset

    ds = resolve_dataset(data_root / "Nordland_64x32")
    d = dataset_descriptors(ds, "pixels")
    v = database_queries(ds, "winter", database=["summer"])
    rows = value_rows(v)
    dv = d if rows is None else d[rows]
    queries = np.linspace(0, v.n_queries - 1, 150).astype(int)
    sims = similarity(dv[v.n_database:][queries], dv[:v.n_database])
    assert sims.shape == (150, 3576)
    xy = np.c_[np.arange(v.n_database) * 10.0, np.zeros(v.n_database)]
    l2 = top1_distance(sims, block=40)
    ref = ref_l2(sims)
    np.testing.assert_allclose(l2.score, [r[0] for r in ref], rtol=1e-12)
    assert l2.top1.tolist() == [r[1] for r in ref]
    np.testing.assert_allclose(pa_ratio(sims, block=40).score, ref_pa(sims), rtol=1e-12)
    np.testing.assert_allclose(sue(sims, xy, block=40).score, ref_sue(sims, xy), rtol=1e-9, atol=1e-6)
