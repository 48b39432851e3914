"""The graph sequence matcher: an explicit graph with Bellman–Ford, hand cases, boundaries, real data."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.graph_matcher import FANOUT, GraphMatch, full_pipeline, sequence_match
from vpr_explorer.method.query_threshold import QueryThresholdSpec, query_thresholds
from vpr_explorer.method.retrieval import TIE_TOLERANCE, similarity

# ---------------------------------------------------------------------------------------------
# The reference: the graph of ovysotska/image_sequence_matcher as a dict of out-edges, and a
# textbook Bellman–Ford (relax every edge until nothing changes; strict improvement, so the
# first edge relaxed wins an exact tie).


def ref_graph(cost: np.ndarray, fanout: int) -> dict:
    """Node -> [(head, weight)]: source, (query, image) nodes, target; an edge carries its head's cost."""
    nq, nd = cost.shape
    graph: dict = {"source": [((0, j), float(cost[0, j])) for j in range(nd)]}
    for q in range(nq - 1):
        for j in range(nd):
            graph[(q, j)] = [((q + 1, k), float(cost[q + 1, k]))
                             for k in range(max(0, j - fanout), min(nd, j + fanout))]
    for j in range(nd):
        graph[(nq - 1, j)] = [("target", 0.0)]
    graph["target"] = []
    return graph


def ref_bellman_ford(graph: dict, source="source") -> tuple[dict, dict]:
    dist = {v: math.inf for v in graph}
    parent: dict = {v: None for v in graph}
    dist[source] = 0.0
    for _ in range(len(graph) - 1):
        changed = False
        for u, edges in graph.items():
            if dist[u] == math.inf:
                continue
            for v, w in edges:
                if dist[u] + w < dist[v]:
                    dist[v] = dist[u] + w
                    parent[v] = u
                    changed = True
        if not changed:
            break
    return dist, parent


def ref_match(sim: np.ndarray, nmc: float, fanout: int) -> tuple[list[int], list[int], list[float], float]:
    """(matched, path, node_cost, path_cost): a node on the path is matched when its cost < nmc."""
    cost = 1.0 - np.asarray(sim, dtype=np.float64)
    dist, parent = ref_bellman_ford(ref_graph(cost, fanout))
    nodes = []
    v = parent["target"]
    while v != "source":
        nodes.append(v)
        v = parent[v]
    nodes.reverse()
    assert [q for q, _ in nodes] == list(range(cost.shape[0]))
    path = [j for _, j in nodes]
    node_cost = [float(cost[q, j]) for q, j in nodes]
    matched = [j if c < nmc else -1 for j, c in zip(path, node_cost)]
    return matched, path, node_cost, dist["target"]


def assert_same(fast: GraphMatch, sim: np.ndarray, nmc: float, fanout: int) -> None:
    matched, path, node_cost, path_cost = ref_match(sim, nmc, fanout)
    np.testing.assert_array_equal(fast.path, path)
    np.testing.assert_array_equal(fast.matched, matched)
    np.testing.assert_array_equal(fast.node_cost, node_cost)
    # the same additions in the same order: the same number
    assert fast.path_cost == path_cost


def diagonal(nq: int, nd: int, columns, high: float = 0.9, low: float = 0.1) -> np.ndarray:
    s = np.full((nq, nd), low)
    s[np.arange(nq), columns] = high
    return s


# ---------------------------------------------------------------------------------------------
# Against the reference


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("shape", [(1, 1), (1, 6), (6, 1), (7, 9), (12, 5), (15, 15)])
@pytest.mark.parametrize("fanout", [1, 2, 3, 5, 40])
def test_random_matrices_match_bellman_ford(seed, shape, fanout):
    rng = np.random.default_rng(seed)
    s = rng.uniform(-1, 1, shape)
    nmc = float(rng.uniform(0.2, 1.8))
    assert_same(sequence_match(s, non_matching_cost=nmc, fanout=fanout), s, nmc, fanout)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("fanout", [1, 2, 3])
def test_coarse_values_full_of_exact_ties_match_bellman_ford(seed, fanout):
    # quarters add exactly: every tie is exact, and the reference's first relaxation is the lowest column
    rng = np.random.default_rng(100 + seed)
    s = rng.integers(0, 4, (10, 8)) / 4
    assert_same(sequence_match(s, non_matching_cost=0.5, fanout=fanout), s, 0.5, fanout)


def test_float32_and_integer_matrices():
    rng = np.random.default_rng(7)
    s32 = rng.uniform(0, 1, (9, 11)).astype(np.float32)
    assert_same(sequence_match(s32, non_matching_cost=0.6, fanout=3), s32, 0.6, 3)
    s_int = rng.integers(-1, 2, (6, 7))
    assert_same(sequence_match(s_int, non_matching_cost=0.5, fanout=2), s_int, 0.5, 2)


def test_a_fanout_beyond_the_database_reaches_every_image():
    rng = np.random.default_rng(3)
    s = rng.uniform(0, 1, (8, 6))
    wide = sequence_match(s, non_matching_cost=0.5, fanout=6)
    wider = sequence_match(s, non_matching_cost=0.5, fanout=1000)
    np.testing.assert_array_equal(wide.path, wider.path)
    assert wide.path_cost == wider.path_cost
    # every image reachable: the path is each row's best image
    np.testing.assert_array_equal(wider.path, s.argmax(axis=1))
    assert_same(wider, s, 0.5, 1000)


def test_the_non_matching_cost_labels_the_path_but_never_moves_it():
    rng = np.random.default_rng(11)
    s = rng.uniform(0, 1, (20, 20))
    results = [sequence_match(s, non_matching_cost=c, fanout=3) for c in (-1.0, 0.3, 0.6, 2.0)]
    for r in results[1:]:
        np.testing.assert_array_equal(r.path, results[0].path)
        assert r.path_cost == results[0].path_cost
    assert (results[0].matched == -1).all()
    np.testing.assert_array_equal(results[-1].matched, results[-1].path)


# ---------------------------------------------------------------------------------------------
# Hand-computed cases


def test_a_clear_diagonal_is_matched_exactly():
    columns = np.arange(8) + 2
    r = sequence_match(diagonal(8, 14, columns), non_matching_cost=0.5, fanout=5)
    np.testing.assert_array_equal(r.matched, columns)
    np.testing.assert_array_equal(r.path, columns)
    np.testing.assert_allclose(r.node_cost, 0.1)
    assert r.path_cost == pytest.approx(0.8, abs=1e-12)
    assert not r.hidden.any()


def test_rows_below_the_non_matching_similarity_go_through_hidden_nodes():
    nmc = 0.5
    s = diagonal(12, 20, np.arange(12) + 3)
    s[4:7] = 0.3  # similarity below 1 − nmc = 0.5 everywhere: cost 0.7 ≥ nmc
    r = sequence_match(s, non_matching_cost=nmc, fanout=5)
    np.testing.assert_array_equal(r.matched[4:7], -1)
    np.testing.assert_array_equal(r.hidden, np.isin(np.arange(12), [4, 5, 6]))
    keep = np.r_[0:4, 7:12]
    np.testing.assert_array_equal(r.matched[keep], keep + 3)
    # a hidden node's own cost counts in full
    np.testing.assert_allclose(r.node_cost[4:7], 0.7)
    assert r.path_cost == pytest.approx(9 * 0.1 + 3 * 0.7, abs=1e-12)
    # the hidden stretch continues through the fan-out: every step within −F … F − 1
    assert np.all(np.diff(r.path) >= -5) and np.all(np.diff(r.path) <= 4)
    assert_same(r, s, nmc, 5)


@pytest.mark.parametrize("fanout", [1, 3, 5])
def test_fanout_bounds_back_f_forward_f_minus_one(fanout):
    def jump(step: int) -> np.ndarray:
        columns = np.r_[np.full(5, 10), np.full(5, 10 + step)]
        return diagonal(10, 25, columns, high=1.0, low=0.0), columns

    for step, taken in ((-fanout, True), (-fanout - 1, False), (fanout - 1, True), (fanout, False)):
        s, columns = jump(step)
        r = sequence_match(s, non_matching_cost=0.5, fanout=fanout)
        assert np.all(np.diff(r.path) >= -fanout) and np.all(np.diff(r.path) <= fanout - 1)
        assert np.array_equal(r.path, columns) is taken, (step, r.path)
        assert_same(r, s, 0.5, fanout)


def test_exact_ties_take_the_lowest_image():
    # one query, two equal best images
    r = sequence_match(np.array([[0.2, 0.7, 0.7, 0.1]]), non_matching_cost=0.5)
    assert r.path.tolist() == [1] and r.matched.tolist() == [1]
    # two parallel diagonals, equally good: the lower one, all along
    s = np.zeros((6, 20))
    s[np.arange(6), np.arange(6) + 2] = 0.8
    s[np.arange(6), np.arange(6) + 12] = 0.8
    np.testing.assert_array_equal(sequence_match(s, non_matching_cost=0.5).path, np.arange(6) + 2)


def test_ties_within_the_tolerance():
    s = np.zeros((6, 20))
    s[np.arange(6), np.arange(6) + 2] = 0.8
    s[np.arange(6), np.arange(6) + 12] = 0.8
    below = TIE_TOLERANCE / 10
    s2 = s.copy()
    s2[5, 17] += below  # the higher path ends better by less than the tolerance: still the lower
    r = sequence_match(s2, non_matching_cost=0.5)
    np.testing.assert_array_equal(r.path, np.arange(6) + 2)
    s3 = s.copy()
    s3[5, 17] += 10 * TIE_TOLERANCE  # by more: the higher path
    np.testing.assert_array_equal(sequence_match(s3, non_matching_cost=0.5).path, np.arange(6) + 12)


def test_a_node_with_two_parents_within_the_tolerance_takes_the_lower():
    # two branches (images 3, 4 and 7, 8) merge at image 6 of query 2, reachable from 4 (+2) and 8 (−2)
    s = np.zeros((4, 12))
    s[[0, 1, 0, 1, 2, 3], [3, 4, 7, 8, 6, 7]] = 0.8
    assert sequence_match(s, non_matching_cost=0.5).path.tolist() == [3, 4, 6, 7]
    s[1, 8] += TIE_TOLERANCE / 10
    r = sequence_match(s, non_matching_cost=0.5)
    assert r.path.tolist() == [3, 4, 6, 7]
    assert r.path_cost == pytest.approx(4 * 0.2, abs=1e-12)
    s[1, 8] += TIE_TOLERANCE
    assert sequence_match(s, non_matching_cost=0.5).path.tolist() == [7, 8, 6, 7]


def test_a_cost_exactly_at_the_non_matching_cost_is_hidden():
    # 1 − 0.75 = 0.25 exactly: hidden (matched only when the cost is below C_nm)
    s = diagonal(3, 6, [1, 2, 3], high=0.75, low=0.0)
    r = sequence_match(s, non_matching_cost=0.25)
    assert r.matched.tolist() == [-1, -1, -1] and r.path.tolist() == [1, 2, 3]
    s[1, 2] = np.nextafter(0.75, 1.0)
    assert sequence_match(s, non_matching_cost=0.25).matched.tolist() == [-1, 2, -1]


def test_a_path_may_start_and_end_anywhere():
    s = np.zeros((4, 10))
    s[np.arange(4), [7, 8, 9, 9]] = 1.0
    r = sequence_match(s, non_matching_cost=0.5)
    assert r.path.tolist() == [7, 8, 9, 9]
    assert r.path_cost == 0.0


def test_result_fields_and_readonly():
    r = sequence_match(diagonal(5, 7, np.arange(5)), non_matching_cost=0.5)
    assert r.matched.dtype == np.int64 and r.path.dtype == np.int64 and r.node_cost.dtype == np.float64
    assert r.matched.shape == r.path.shape == r.node_cost.shape == (5,)
    assert isinstance(r.path_cost, float) and r.non_matching_cost == 0.5
    for a in (r.matched, r.path, r.node_cost):
        with pytest.raises(ValueError):
            a[0] = 0
    assert r.path_cost == pytest.approx(r.node_cost.sum(), abs=1e-12)
    assert FANOUT == 5


# ---------------------------------------------------------------------------------------------
# The full pipeline


def _sequence(nq: int = 80, nd: int = 100, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    s = rng.normal(0.3, 0.05, (nq, nd))
    q = np.arange(nq)
    s[q, q + 10] += 0.4
    s[30:40] = rng.normal(0.3, 0.05, (10, nd))  # a stretch with no match
    return s


def test_full_pipeline_non_matching_cost_is_one_minus_the_median_threshold():
    s = _sequence()
    match, nmc = full_pipeline(s)
    assert nmc == 1.0 - float(np.median(query_thresholds(s).threshold))
    assert match.non_matching_cost == nmc
    direct = sequence_match(s, non_matching_cost=nmc, fanout=FANOUT)
    np.testing.assert_array_equal(match.matched, direct.matched)
    assert_same(match, s, nmc, FANOUT)
    # the match stretch is found, the stretch with no match is mostly hidden
    q = np.r_[0:30, 40:80]
    assert (match.matched[q] == q + 10).mean() > 0.9
    assert match.hidden[30:40].mean() > 0.5


def test_full_pipeline_passes_its_settings_on():
    s = _sequence(seed=1)
    spec = QueryThresholdSpec(patch=10)
    match, nmc = full_pipeline(s, fanout=3, spec=spec)
    assert nmc == 1.0 - float(np.median(query_thresholds(s, spec).threshold))
    assert_same(match, s, nmc, 3)


# ---------------------------------------------------------------------------------------------
# Bad input


@pytest.mark.parametrize("bad", [np.zeros(5), np.zeros((2, 2, 2)), np.zeros((0, 4)), np.zeros((3, 0)),
                                 np.array([[0.1, np.nan]]), np.array([[np.inf, 0.1]]), [["a", "b"]],
                                 np.array([[1 + 1j]])])
def test_bad_matrices_are_refused(bad):
    with pytest.raises(VPRInputError, match="similarity"):
        sequence_match(bad, non_matching_cost=0.5)
    with pytest.raises(VPRInputError, match="similarity"):
        full_pipeline(bad)


@pytest.mark.parametrize("fanout", [0, -1, 2.5, True, "5", None])
def test_bad_fanout_is_named(fanout):
    with pytest.raises(VPRInputError, match="fanout"):
        sequence_match(np.zeros((3, 3)), non_matching_cost=0.5, fanout=fanout)
    with pytest.raises(VPRInputError, match="fanout"):
        full_pipeline(np.array([[np.nan]]), fanout=fanout)  # checked before the thresholds


@pytest.mark.parametrize("cost", [float("nan"), float("inf"), -float("inf"), "a", None, True])
def test_bad_non_matching_cost_is_named(cost):
    with pytest.raises(VPRInputError, match="non_matching_cost"):
        sequence_match(np.zeros((3, 3)), non_matching_cost=cost)


# ---------------------------------------------------------------------------------------------
# Real data


def _sims(dataset, descriptors, query: str, database: str) -> np.ndarray:
    from vpr_explorer.data.aligned import database_queries, value_rows
    from vpr_explorer.method.sequences import check_sequence

    v = database_queries(dataset, query, database=[database])
    check_sequence(v)
    rows = value_rows(v)
    d = descriptors if rows is None else descriptors[rows]
    nd = len(v.database_frame)
    return similarity(d[nd:], d[:nd])


@pytest.mark.realdata
def test_gardens_point_day_against_night_matches_bellman_ford(gardens_point, gp_pixels):
    s = _sims(gardens_point, gp_pixels, "day_right", "night_right")
    assert s.shape == (200, 200)
    match, nmc = full_pipeline(s)
    assert_same(match, s, nmc, FANOUT)
    n = len(s)
    frames = np.arange(n)
    path_right = np.abs(match.path - frames) <= 2
    top1_right = np.abs(s.argmax(axis=1) - frames) <= 2
    m = ~match.hidden
    print(f"\nGardensPoint day_right -> night_right, pixels, C_nm {nmc:.4f}: {m.sum()} of {n} matched; "
          f"within 2 frames: path {path_right.mean():.3f} vs single-image top-1 {top1_right.mean():.3f}; "
          f"matched and right {(path_right & m).sum()} (precision {path_right[m].mean():.3f})")
    assert path_right.mean() > top1_right.mean()


@pytest.mark.realdata
def test_nordland_slice_matches_bellman_ford(data_root):
    from vpr_explorer.pipeline import dataset_descriptors, resolve_dataset

    ds = resolve_dataset(data_root / "Nordland_64x32")
    # frames 1000–1199 of both seasons: the train runs (its first frames hold a long stop, where
    # neither the path nor the top-1 image finds the frame)
    cut = slice(1000, 1200)
    s = np.ascontiguousarray(_sims(ds, dataset_descriptors(ds, "pixels"), "winter", "summer")[cut, cut])
    match, nmc = full_pipeline(s)
    assert_same(match, s, nmc, FANOUT)
    frames = np.arange(len(s))
    path_right = np.abs(match.path - frames) <= 2
    top1_right = np.abs(s.argmax(axis=1) - frames) <= 2
    m = ~match.hidden
    print(f"\nNordland winter -> summer, frames 1000–1199, pixels, C_nm {nmc:.4f}: {m.sum()} of {len(s)} matched; "
          f"within 2 frames: path {path_right.mean():.3f} vs single-image top-1 {top1_right.mean():.3f}; "
          f"matched and right {(path_right & m).sum()}")
    assert path_right.mean() > top1_right.mean() + 0.2
