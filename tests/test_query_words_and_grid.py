"""``numbers.describe_answer`` and ``numbers.similarity_grid`` against plain references.

The demo route as the app reads it (``aligned.database_queries``: snow queries against the
day and night database) with group 3, step 5 (frames 3 and 4 of every 5 lie between
places), and the same value with a ground truth that leaves some queries with no right
image (unknown places).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vpr_explorer.data.aligned import database_queries, value_rows
from vpr_explorer.data.groundtruth import GroundTruth
from vpr_explorer.method.places import PlaceGeometry, PlaceSpec
from vpr_explorer.views import numbers as views
from vpr_explorer.views.numbers import (
    BETWEEN,
    KNOWN,
    UNKNOWN,
    RetrievalPlaces,
    database_label,
    describe_answer,
    explain_query,
    fit_retrieval,
    similarity_grid,
)
from vpr_explorer.views.numbers import LIVE_METHODS

PLACES = RetrievalPlaces(PlaceGeometry.FRAMES, spec=PlaceSpec(3, 5))


@pytest.fixture(scope="module")
def value(demo, demo_pixels):
    v = database_queries(demo)
    assert value_rows(v) is None  # snow, the last traversal, queries: the traversals' own order
    return v, np.asarray(demo_pixels)


# --------------------------------------------------------------------------- the answer in words


def test_a_query_with_a_right_place_reads_as_the_decision_with_images_named(value):
    v, d = value
    f = fit_retrieval(d, v, PLACES)
    assert f.query_status(31) == KNOWN
    dec = explain_query(f, d, 31)
    for key in LIVE_METHODS:
        assert describe_answer(f, dec, key, 31) == dec.describe(key)
    img = int(dec.outcomes["image-baseline"].answer_image[0])
    said = describe_answer(f, dec, "image-baseline", 31)
    assert f"accepted as {database_label(v, int(f.model.images[img]))} → place" in said
    assert "accepted as image" not in said


def test_a_query_between_places_is_not_scored_whatever_the_answer(value):
    v, d = value
    f = fit_retrieval(d, v, PLACES)
    assert f.query_status(3) == BETWEEN  # frame 3: places hold frames 0-2, 5-7, …
    dec = explain_query(f, d, 3, user_theta=1.5)  # a global θ above every score: rejected under it
    for key in ("place-baseline", "margin-weighted", "global-user"):
        said = describe_answer(f, dec, key, 3)
        assert "(not scored: its right database images lie between places)" in said
        assert "not in the database" not in said and "right:" not in said and "wrong" not in said
    assert describe_answer(f, dec, "global-user", 3).startswith("rejected (not scored")
    assert describe_answer(f, dec, "place-baseline", 3).startswith(f"accepted as place {dec.answer('place-baseline')}")


def test_an_unknown_place_query_is_right_when_rejected_and_a_false_positive_when_accepted(value):
    v, d = value
    lists = [v.ground_truth.positives(q) if q < 40 else [] for q in range(v.n_queries)]  # 40-59: no right image
    unknown = dataclasses.replace(v, ground_truth=GroundTruth.from_lists(lists, v.n_database, "frames 0-39 only"))
    f = fit_retrieval(d, unknown, PLACES)
    assert f.query_status(45) == UNKNOWN
    dec = explain_query(f, d, 45, user_theta=1.5)
    assert describe_answer(f, dec, "place-baseline", 45).startswith(
        f"accepted as place {dec.answer('place-baseline')} (wrong: an unknown-place query accepted: a false positive)")
    rejected = describe_answer(f, dec, "global-user", 45)
    assert rejected.startswith("rejected (right: an unknown-place query rejected): every place scored below")
    closest = int(np.argmax(dec.raw - dec.thresholds["user"]))
    assert f"the closest, place {closest}: raw {dec.raw[closest]:.3f}" in rejected


# --------------------------------------------------------------------------- the similarity matrix


def reference(grid, scores: np.ndarray) -> None:
    """Each cell is its block's maximum of ``scores`` (queries × database), and the pair behind it attains it."""
    n_q, n_db = scores.shape
    for r, first in enumerate(grid.row_frames):
        rows = [first] if grid.sampled else range(first, min(first + grid.row_block, n_q))
        for c, col in enumerate(grid.col_frames):
            block = scores[np.ix_(list(rows), list(range(col, min(col + grid.block, n_db))))]
            assert grid.z[r, c] == pytest.approx(block.max(), abs=1e-6)
            q, i = grid.query_image[r, c], grid.db_image[r, c]
            assert q in rows and col <= i < col + grid.block
            assert scores[q, i] == pytest.approx(grid.z[r, c], abs=1e-6)


@pytest.mark.parametrize("max_side, budget, shape, sampled", [
    (200, None, (60, 120), False),  # one cell a pair
    (25, None, (20, 24), False),  # 3 queries × 5 database images a cell
    (7, None, (7, 7), False),  # a last block that is not full
    (25, 1000, (8, 24), True),  # over the budget: one query per row, at most 1,000 similarities
    (200, 100, (1, 120), True),  # a budget below one row: one row
])
def test_the_grid_pools_block_maxima_and_keeps_their_pair(value, monkeypatch, max_side, budget, shape, sampled):
    v, d = value
    monkeypatch.setattr(views, "SCORE_ELEMS", 700)  # several bands of queries
    grid = similarity_grid(v, d, max_side=max_side, pair_budget=budget)
    assert grid.z.shape == shape and grid.sampled is sampled
    if sampled:
        assert len(grid.row_frames) * v.n_database <= max(budget, v.n_database)
        np.testing.assert_array_equal(grid.row_frames, np.minimum(np.arange(shape[0]) * grid.row_block
                                                                  + grid.row_block // 2, v.n_queries - 1))
    reference(grid, d[v.n_database:] @ d[:v.n_database].T)


def test_the_grid_of_float16_descriptors_reads_them_a_block_at_a_time(value):
    v, d = value
    half = d.astype(np.float16)
    grid = similarity_grid(v, half, max_side=25)
    exact = half[v.n_database:].astype(np.float32) @ half[:v.n_database].astype(np.float32).T
    reference(grid, exact)
