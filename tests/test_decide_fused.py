"""The decisions by place pieces (``views.numbers.decide_queries``) equal the straightforward path exactly.

``decide_queries`` groups the database images in places by place (``retrieval.PlaceLayout``),
computes each block's similarities a piece of places at a time with their maxima
(``layout_place_scores``) and reads back only the places that can change the image-level
baseline (``score_layout_block``). Every rank, answer and image must equal those of
``place_scores`` + ``score_queries`` on the same float32 similarities: checked on real
GardensPoint and Nordland (whose tunnels are runs of byte-identical frames, so exact and
near ties are real), and on adversarial score matrices, across block sizes, piece sizes and
thread counts. (``tests/test_million.py`` checks the same on a float16 memory map.)

Why decisions are equal, not merely close: every comparison is made in the precision of the
straightforward path (a place's tie floor raw − 1e-5 in float32, the image-level rank and
answer floors in float64), so equal similarities give equal decisions; the adversarial
tests below feed both paths the very same float32 matrix and compare every decision exactly.

End to end, the two paths compute the similarities as different GEMMs (``similarity_t``:
database rows first, in pieces), and a GEMM's rounding is the BLAS kernel's own: on
OpenBLAS's SkylakeX kernel each similarity is the same float32 number whichever operand
comes first and however rows are cut (bit for bit), while its Haswell kernel (which
``OPENBLAS_CORETYPE=Haswell`` selects) rounds by operand order and position, a few ulp
(~1e-7). The tolerance rule covers that: ranks, answers and images are equal unless a
score lies within ``EPS`` of a decision boundary, another score ± 1e-5 or a threshold
(``retrieval`` module doc). The end-to-end tests compare every decision exactly, except on
such borderline queries (``borderline``), which must be rare.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from vpr_explorer.data.aligned import database_queries, value_rows
from vpr_explorer.method.places import PlaceGeometry, PlaceSpec
from vpr_explorer.method.retrieval import (
    TIE_TOLERANCE,
    Outcome,
    PlaceLayout,
    layout_place_scores,
    place_scores,
    score_layout_block,
    score_queries,
    similarity,
    similarity_t,
)
from vpr_explorer.views import numbers as views
from vpr_explorer.views.numbers import RetrievalFitted, RetrievalPlaces, decide_queries, fit_retrieval

FIELDS = ("rank", "answer_place", "answer_image", "n_kept")
#: Two GEMMs of the same unit descriptors differ by a few float32 ulp on any BLAS kernel
#: (at most 2.7e-7 on the Haswell kernel here); a score within this of a boundary may go
#: either way.
EPS = 5e-7


@dataclass(frozen=True, eq=False)
class Straightforward:
    """The straightforward path's decisions of some queries: query × database scores, their place
    maxima (``place_scores``) and every method's outcome (``score_queries``)."""

    sims: np.ndarray
    raw: np.ndarray
    truth: np.ndarray
    thresholds: dict
    db_places: np.ndarray
    outcomes: dict[str, Outcome]


def straightforward(fitted: RetrievalFitted, descriptors: np.ndarray, queries: np.ndarray, *, k: float = 0.0,
                    user_theta: float | None = None) -> Straightforward:
    model = fitted.model
    q = np.asarray(descriptors[fitted.dataset.n_database + queries], dtype=np.float32)
    sims = similarity(q, np.asarray(descriptors[model.images], dtype=np.float32))
    raw, best = place_scores(sims, model.places, fitted.n_places)
    th = model.thresholds(k, user_theta)
    truth = fitted.right_places(queries)
    outcomes = score_queries(sims, model.places, fitted.n_places, th, truth, raw_best=(raw, best))
    return Straightforward(sims, raw, truth, th, model.places, outcomes)


def borderline(ref: Straightforward) -> np.ndarray:
    """``(n_queries,)`` the queries whose decisions may go either way (``retrieval`` module doc).

    A query with a score within ``EPS`` of a decision boundary: an image at its best right
    score or its top score − 1e-5 (ranks, the image-level answer), a place at the top
    raw_p − 1e-5 (the answer) or at a threshold (kept or not), or, among the places that can
    be its answer, a place with an image scoring its raw_p − 1e-5 (which of its images is
    "best" may go either way). Scores from ``similarity``, the straightforward path's own.
    """
    sims, places = ref.sims.astype(np.float64), ref.db_places
    raw = ref.raw.astype(np.float64)
    with np.errstate(invalid="ignore"):
        def at(values, edge):
            return np.abs(values - (edge - TIE_TOLERANCE)) <= EPS

        cell_hit = at(sims, raw[:, places])
        cells = np.zeros(raw.shape, dtype=bool)
        for p in np.unique(places):
            cells[:, p] = cell_hit[:, places == p].any(axis=1)
        right = np.where(ref.truth, raw, -np.inf).max(axis=1, keepdims=True)
        top = raw.max(axis=1, keepdims=True)
        queries = at(sims, right).any(axis=1) | at(sims, sims.max(axis=1, keepdims=True)).any(axis=1)
        queries |= at(raw, top).any(axis=1)
        queries |= (cells & (raw >= top - TIE_TOLERANCE - EPS)).any(axis=1)
        for th in ref.thresholds.values():
            queries |= (np.abs(raw - np.asarray(th, dtype=np.float64)) <= EPS).any(axis=1)
    return queries


def assert_same_decisions(got: dict[str, Outcome], ref: Straightforward):
    """Equal ranks, answers and images but on the queries ``borderline`` marks, which must be rare
    (at most 2%; Nordland's tunnels, runs of near-identical frames, have 1.5% of their frames there)."""
    near = borderline(ref)
    assert near.mean() <= 0.02, f"{near.sum()} borderline queries"
    assert got.keys() == ref.outcomes.keys()
    keep = ~near
    for key, o in ref.outcomes.items():
        for f in FIELDS:
            x, y = getattr(got[key], f), getattr(o, f)
            np.testing.assert_array_equal(x[keep], y[keep], err_msg=f"{key}.{f}")
            assert x.dtype == y.dtype, (key, f)


def assert_same_outcomes(a, b):
    assert a.keys() == b.keys()
    for key in a:
        for f in FIELDS:
            np.testing.assert_array_equal(getattr(a[key], f), getattr(b[key], f), err_msg=f"{key}.{f}")


def layout_decisions(sims, db_places, n_places, th, correct, piece_rows):
    """The place-piece path's retrieval steps on a given ``(n_queries, n_database)`` float32 matrix."""
    layout = PlaceLayout.of(db_places, n_places)
    scores_t = np.ascontiguousarray(sims.T[layout.order])
    raw_t = np.empty((len(layout.places), sims.shape[0]), dtype=sims.dtype)
    best_t = np.empty(raw_t.shape, dtype=np.int64)
    for piece in layout.pieces(piece_rows):
        layout_place_scores(scores_t, layout, piece, raw_t, best_t)
    return score_layout_block(scores_t, layout, raw_t, best_t, th, correct, db_places)


def test_similarity_t_is_similarity_within_a_few_ulp(gp_pixels):
    # bit for bit on OpenBLAS's SkylakeX kernel, a few ulp on its Haswell kernel (module doc)
    rng = np.random.default_rng(0)
    q, db = gp_pixels[rng.choice(600, 37, replace=False)], gp_pixels[rng.permutation(600)[:411]]
    reference = similarity(q, db)
    exact = q.astype(np.float64) @ db.T.astype(np.float64)
    bound = 4 * np.finfo(np.float32).eps  # unit rows: |s| ≤ 1, a dot product of depth 2,048 in float32
    np.testing.assert_allclose(similarity_t(db, q), reference.T, rtol=0, atol=EPS)
    np.testing.assert_allclose(similarity_t(db, q), exact.T, rtol=0, atol=bound)
    out = np.empty((100, 37), dtype=np.float32)
    similarity_t(db[200:300], q, out=out)  # a piece: rows cut differently
    np.testing.assert_allclose(out, reference[:, 200:300].T, rtol=0, atol=EPS)


def test_layout_groups_each_place_in_index_order_and_runs_by_size():
    places = np.array([4, 1, 1, 0, 4, 4, 2, 0, 1, 4, 6])
    layout = PlaceLayout.of(places, 7)
    np.testing.assert_array_equal(layout.places, [2, 6, 0, 1, 4])  # sizes 1, 1, 2, 3, 4
    assert layout.runs == ((0, 0, 2, 1), (2, 2, 1, 2), (4, 3, 1, 3), (7, 4, 1, 4))
    np.testing.assert_array_equal(layout.order, [6, 10, 3, 7, 1, 2, 8, 0, 4, 5, 9])
    assert layout.pieces(2) == [(0, 0, 2, 1), (2, 2, 1, 2), (4, 3, 1, 3), (7, 4, 1, 4)]
    assert layout.pieces(1) == [(0, 0, 1, 1), (1, 1, 1, 1), (2, 2, 1, 2), (4, 3, 1, 3), (7, 4, 1, 4)]
    assert sum(n * k for _, _, n, k in layout.pieces(3)) == len(places)


def adversarial(seed):
    """Scores with exact ties, ties within 1e-5, near misses just beyond it, duplicates, places
    of many sizes, queries with no right place and right places without database images."""
    rng = np.random.default_rng(seed)
    n_places = 40
    sizes = rng.integers(0, 7, n_places)
    db_places = rng.permutation(np.repeat(np.arange(n_places), sizes))
    nq, n = 120, len(db_places)
    levels = np.float32([0.9, 0.9 - 4e-6, 0.9 - 1e-5, 0.9 - 1.1e-5, 0.9 - 2e-5, 0.8, 0.5])
    sims = levels[rng.integers(0, len(levels), (nq, n))]
    sims += np.spacing(sims) * rng.integers(-2, 3, sims.shape).astype(np.float32)  # last-bit noise
    spread = rng.random(sims.shape) < 0.3
    sims[spread] = rng.uniform(0.1, 1.0, int(spread.sum()))
    sims[:5] = sims[5]  # identical rows
    sims[:, :3] = sims[:, [3]]  # identical database images
    correct = rng.random((nq, n_places)) < 0.08
    correct[10:14] = False  # between places
    th = {
        "simple": rng.uniform(0.5, 0.95, n_places),
        "weighted": np.where(rng.random(n_places) < 0.1, np.nan, rng.uniform(0.5, 0.95, n_places)),
        "auto": float(levels[2]),  # a threshold equal to a score: kept (raw >= θ)
        "user": 0.85,
    }
    return sims.astype(np.float32), db_places, n_places, th, correct


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("piece_rows", [1, 5, 4096])
def test_layout_scores_equal_place_scores_and_score_queries_on_ties(seed, piece_rows):
    sims, db_places, n_places, th, correct = adversarial(seed)
    raw, best = place_scores(sims, db_places, n_places)
    expected = score_queries(sims, db_places, n_places, th, correct, raw_best=(raw, best))
    raw2, best2, got = layout_decisions(sims, db_places, n_places, th, correct, piece_rows)
    np.testing.assert_array_equal(raw2, raw)
    np.testing.assert_array_equal(best2, best)
    assert_same_outcomes(got, expected)
    # the ties are there: some image-level ranks > 1 come from scores within 1e-5, and
    # some places' best image is not their argmax
    assert (expected["image-baseline"].rank > 1).any() and np.isinf(expected["image-baseline"].rank).any()
    argmax = np.full_like(best, -1)
    order = np.argsort(db_places, kind="stable")
    for p in np.unique(db_places):
        cols = order[db_places[order] == p]
        argmax[:, p] = cols[np.argmax(sims[:, cols], axis=1)]
    assert ((best != argmax) & (best >= 0)).any()


def test_layout_scores_with_a_small_chunk_of_candidates():
    sims, db_places, n_places, th, correct = adversarial(0)
    layout = PlaceLayout.of(db_places, n_places)
    scores_t = np.ascontiguousarray(sims.T[layout.order])
    raw_t = np.empty((len(layout.places), sims.shape[0]), dtype=np.float32)
    best_t = np.empty(raw_t.shape, dtype=np.int64)
    for piece in layout.pieces(7):
        layout_place_scores(scores_t, layout, piece, raw_t, best_t)
    expected = score_queries(sims, db_places, n_places, th, correct)
    _, _, got = score_layout_block(scores_t, layout, raw_t, best_t, th, correct, db_places, max_elems=3)
    assert_same_outcomes(got, expected)


@pytest.fixture(scope="module")
def gp_fit(gardens_point, gp_pixels):
    """GardensPoint's value: database day_left + day_right, queries night_right (the descriptors' own order)."""
    value = database_queries(gardens_point, "night_right")
    assert value_rows(value) is None
    return fit_retrieval(gp_pixels, value, RetrievalPlaces(PlaceGeometry.FRAMES, spec=PlaceSpec(3, 5)))


def pieces_of(monkeypatch, rows: int, dim: int) -> None:
    """``decide_queries`` cuts the places into pieces of at most ``rows`` database rows."""
    monkeypatch.setattr(views, "SCORE_BLOCK_ELEMS", rows * dim)


@pytest.mark.parametrize("block, threads, piece_rows", [(4096, None, 2048), (7, 2, 4), (64, 1, 64), (200, 3, 1)])
def test_gardens_point_by_pieces_equals_straightforward(monkeypatch, gp_pixels, gp_fit, block, threads, piece_rows):
    queries = np.arange(gp_fit.dataset.n_queries)
    ref = straightforward(gp_fit, gp_pixels, queries, k=1.0, user_theta=0.6)
    pieces_of(monkeypatch, piece_rows, gp_pixels.shape[1])
    if threads is not None:
        monkeypatch.setattr(views, "SCORE_THREADS", threads)
    _, got = decide_queries(gp_fit, gp_pixels, queries, k=1.0, user_theta=0.6, block=block)
    assert_same_decisions(got, ref)


def test_a_nan_query_takes_the_straightforward_path(gardens_point, gp_pixels, gp_fit):
    d = gp_pixels.copy()
    d[gardens_point.image_index("night_right", 7)] = np.nan  # query 7 (the value's rows are the traversals')
    queries = np.arange(1, 200, 3)  # 1, 4, 7, ...: query 7 in the first block of 10
    ref = straightforward(gp_fit, d, queries)
    assert not np.isfinite(ref.raw[queries == 7]).any()
    truth, got = decide_queries(gp_fit, d, queries, block=10)
    np.testing.assert_array_equal(truth, ref.truth)
    assert_same_decisions(got, ref)


def test_nordland_tunnels_by_pieces_equal_straightforward(data_root):
    # Nordland's tunnels are runs of byte-identical frames: ties at 1.0 and within 1e-5
    from vpr_explorer.data.traversals import load_dataset
    from vpr_explorer.pipeline import dataset_descriptors

    dataset = load_dataset(data_root / "Nordland_64x32")
    value = database_queries(dataset, "winter", ["summer"])
    rows = value_rows(value)
    d = dataset_descriptors(dataset, "pixels")
    d = d if rows is None else d[rows]
    fitted = fit_retrieval(d, value, RetrievalPlaces(PlaceGeometry.FRAMES, spec=PlaceSpec(3, 3)))
    queries = np.arange(0, value.n_queries, 2)
    ref = straightforward(fitted, d, queries)
    _, got = decide_queries(fitted, d, queries, block=512)
    assert_same_decisions(got, ref)
    image = ref.outcomes["image-baseline"]
    assert (np.isfinite(image.rank) & (image.rank > 1)).any()


def test_first_image_within_the_tolerance_in_places_of_more_than_255_images():
    # ``layout_place_scores`` finds a place's first image within 1e-5 of its maximum as a maximum
    # of hit·(k − j) over its rows j: uint8 weights up to 255 images, wider above
    rng = np.random.default_rng(5)
    sizes = np.array([300, 256, 255, 3, 1])
    db_places = rng.permutation(np.repeat(np.arange(len(sizes)), sizes))
    sims = rng.uniform(0.1, 0.85, (9, len(db_places))).astype(np.float32)
    for p in range(len(sizes)):  # the maximum last in each place, an image within 1e-5 of it just before
        cols = np.flatnonzero(db_places == p)
        sims[:, cols[-1]] = 0.9
        sims[:, cols[max(0, len(cols) - 2)]] = np.float32(0.9) - np.float32(4e-6)
    correct = np.zeros((9, len(sizes)), dtype=bool)
    correct[:, 0] = True
    th = {"simple": np.full(len(sizes), 0.5), "weighted": np.full(len(sizes), 0.95), "auto": 0.7}
    raw, best = place_scores(sims, db_places, len(sizes))
    expected = score_queries(sims, db_places, len(sizes), th, correct, raw_best=(raw, best))
    for piece_rows in (1, 256, 4096):
        raw2, best2, got = layout_decisions(sims, db_places, len(sizes), th, correct, piece_rows)
        np.testing.assert_array_equal(raw2, raw)
        np.testing.assert_array_equal(best2, best)
        assert_same_outcomes(got, expected)
    big = np.flatnonzero(db_places == 0)
    np.testing.assert_array_equal(best[:, 0], big[-2])  # the image within 1e-5 before the maximum


def test_decide_queries_leaves_blas_threads_as_found(monkeypatch, gp_pixels, gp_fit):
    # the pieces run side by side with BLAS held at one thread (``stats.one_blas_thread``),
    # whether the queries make several blocks or one
    from threadpoolctl import threadpool_info

    def blas_threads():
        return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]

    monkeypatch.setattr(views, "SCORE_THREADS", 3)
    pieces_of(monkeypatch, 64, gp_pixels.shape[1])  # several pieces: they run in the threads
    before = blas_threads()
    for block in (4096, 50):
        decide_queries(gp_fit, gp_pixels, np.arange(gp_fit.dataset.n_queries), block=block)
        assert blas_threads() == before
