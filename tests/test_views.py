"""The app's views on big datasets: overviews sample, one-place and one-query views never compute all pairs.

The demo route as its dataset value (``data.aligned.database_queries``: database day + night,
queries the snow frames) keeps these fast; the pair budget is lowered so that sampling happens
on 60 queries the way it does on 27,591 (``benchmarks/bench_app_scale.py`` runs the real size).
"""

from __future__ import annotations

import numpy as np
import pytest

from vpr_explorer.data.aligned import database_queries
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import PlaceGeometry, PlaceSpec
from vpr_explorer.views import numbers as views
from vpr_explorer.views import plots
from vpr_explorer.views.numbers import (
    FIND_KINDS,
    RetrievalPlaces,
    decide_queries,
    explain_query,
    find_query,
    fit_retrieval,
    overview,
    overview_frames,
    place_detail,
)

SPEC = PlaceSpec(3, 5)
PLACES = RetrievalPlaces(PlaceGeometry.FRAMES, spec=SPEC)
BUDGET = 1000  # query x database similarities; the demo's 60 queries x 72 database images in places are 4,320


@pytest.fixture(scope="module")
def value(demo):
    return database_queries(demo)  # query q is snow frame q; the descriptors' own order (no row moves)


@pytest.fixture(scope="module")
def fitted(value, demo_pixels):
    return fit_retrieval(demo_pixels, value, PLACES)


@pytest.fixture(scope="module")
def full(value, demo_pixels, fitted):
    """``(truth, outcomes)`` of every query."""
    return decide_queries(fitted, demo_pixels, np.arange(value.n_queries))


@pytest.fixture
def pairs(monkeypatch):
    """Counts the query x database similarities computed (the real functions run)."""
    counter = {"pairs": 0}
    real, real_t = views.similarity, views.similarity_t

    def counting(a, b):
        counter["pairs"] += len(a) * len(b)
        return real(a, b)

    def counting_t(a, b, out=None):  # the decisions: database rows × queries, a piece at a time
        counter["pairs"] += len(a) * len(b)
        return real_t(a, b, out=out)

    monkeypatch.setattr(views, "similarity", counting)
    monkeypatch.setattr(views, "similarity_t", counting_t)
    return counter


def test_overview_frames_are_all_under_the_budget_and_a_fixed_sample_above():
    np.testing.assert_array_equal(overview_frames(60, 72, 60 * 72), np.arange(60))
    sample = overview_frames(27_591, 82_773, 30_000_000)
    assert len(sample) == 30_000_000 // 82_773 == 362
    assert np.all(np.diff(sample) > 0) and sample[0] >= 0 and sample[-1] < 27_591
    np.testing.assert_array_equal(sample, overview_frames(27_591, 82_773, 30_000_000))  # seeded
    # A random sample does not beat with the place layout: a stride of 10 with step 10 would
    # land on one offset inside every place.
    assert len(np.unique(sample % 10)) == 10


def assert_rows(outcomes, full_outcomes, rows):
    for key, o in full_outcomes.items():
        for field in ("rank", "answer_place", "answer_image", "n_kept"):
            np.testing.assert_array_equal(getattr(outcomes[key], field), getattr(o, field)[rows],
                                          err_msg=f"{key} {field}")


def test_deciding_some_queries_equals_those_rows_of_every_query(demo_pixels, fitted, full):
    queries = np.array([41, 3, 17, 59, 0])
    truth, outcomes = decide_queries(fitted, demo_pixels, queries)
    np.testing.assert_array_equal(truth, full[0][queries])
    assert_rows(outcomes, full[1], queries)


@pytest.mark.parametrize("queries", [np.array([60]), np.array([-1]), np.array([], dtype=np.int64)])
def test_deciding_a_query_that_is_not_one_is_refused_naming_it(demo_pixels, fitted, queries):
    with pytest.raises(VPRInputError, match="quer"):
        decide_queries(fitted, demo_pixels, queries)


def test_a_small_block_gives_the_same_decisions(demo_pixels, fitted, full):
    truth, blocked = decide_queries(fitted, demo_pixels, np.arange(60), block=7)
    np.testing.assert_array_equal(truth, full[0])
    assert_rows(blocked, full[1], np.arange(60))


def test_overview_over_the_budget_decides_a_sample_and_its_numbers_are_those_queries(demo_pixels, fitted, full,
                                                                                      pairs):
    truth, outcomes = full
    ov = overview(fitted, demo_pixels, pair_budget=BUDGET)
    n_db = len(fitted.model.images)
    assert ov.sampled and ov.n_queries == 60 and len(ov.queries) == BUDGET // n_db
    assert pairs["pairs"] == len(ov.queries) * n_db <= BUDGET  # the overview's query x database pairs
    scored = truth[ov.queries].any(axis=1)
    np.testing.assert_array_equal(ov.scored, scored)
    for key, o in outcomes.items():
        assert ov.recall1[key] == pytest.approx(float((o.rank[ov.queries][scored] == 1).mean()))
        assert ov.rejected[key] == pytest.approx(float((~o.accepted[ov.queries][scored]).mean()))
    assert_rows(ov.outcomes, outcomes, ov.queries)


def test_overview_under_the_budget_decides_every_query(demo_pixels, fitted, full):
    ov = overview(fitted, demo_pixels)
    assert not ov.sampled
    np.testing.assert_array_equal(ov.queries, np.arange(60))
    np.testing.assert_array_equal(ov.outcomes["raw-weighted"].rank, full[1]["raw-weighted"].rank)


def test_one_place_and_one_query_never_compute_every_query(demo_pixels, fitted, pairs):
    """The Thresholds and Inspector pages' work: their own rows against the database, nothing more."""
    n_db = len(fitted.model.images)
    d = place_detail(fitted, demo_pixels, 4)
    assert pairs["pairs"] == len(d.images) * n_db + len(d.query_images) * len(d.images)
    pairs["pairs"] = 0
    explain_query(fitted, demo_pixels, 31)
    assert pairs["pairs"] == n_db


# the two kinds whose test is one line here; tests/test_finder.py checks every kind against a plain loop
@pytest.mark.parametrize("kind", ["rejected", "answered wrong"])
@pytest.mark.parametrize("method", ["margin-weighted", "raw-weighted", "place-baseline"])
def test_find_query_is_the_next_such_query_after_the_current_one_wrapping(demo_pixels, fitted, full, kind, method):
    truth, outcomes = full
    o = outcomes[method]
    bad = np.flatnonzero(~o.accepted if kind == "rejected" else (truth.any(axis=1) & ~o.right))
    for after in (0, 17, 45, 59):
        found, last = find_query(fitted, demo_pixels, after=after, kind=kind, method=method)
        if len(bad):
            expected = next((int(f) for f in bad if f > after), int(bad[0]))
            assert (found, last) == (expected, expected)
        else:
            assert (found, last) == (None, after)  # searched every query


def test_find_query_stops_at_the_budget_and_pressing_again_searches_on(demo_pixels, fitted, full, pairs):
    truth, outcomes = full
    o = outcomes["place-baseline"]
    bad = np.flatnonzero(truth.any(axis=1) & ~o.right)
    assert len(bad) and bad[0] > 5, "the demo should have a first wrong query beyond query 5"
    n_db = len(fitted.model.images)
    budget = 3 * n_db  # three queries per press
    after, presses = -1, 0
    while True:
        pairs["pairs"] = 0
        found, last = find_query(fitted, demo_pixels, after=after % 60, kind="answered wrong",
                                 method="place-baseline", pair_budget=budget, first_chunk=1)
        assert pairs["pairs"] <= budget
        presses += 1
        if found is not None:
            break
        assert last == (after + 3) % 60
        after = last
    assert found == bad[0] and presses == bad[0] // 3 + 1
    with pytest.raises(VPRInputError, match="kind"):
        find_query(fitted, demo_pixels, after=0, kind="slow", method="place-baseline")


def test_route_figure_of_a_long_route_shows_its_start_and_says_so():
    frame_place = np.repeat(np.arange(1000), 3)[:2500]
    positions = np.stack([np.linspace(0, 1, 2500), np.zeros(2500)], axis=1)
    fig = plots.route_figure(frame_place, ["a", "b"], positions, max_frames=600)
    strip = next(t for t in fig.data if t.meta == "places a")
    assert len(strip.x) == 600 and max(strip.x) == 599
    assert "frames 0–599 of 2,500 shown" in fig.layout.title.text
    on_map = next(t for t in fig.data if t.meta == "map places")
    assert len(on_map.x) <= 600
    np.testing.assert_array_equal(np.asarray(on_map.customdata)[:, 1], frame_place[np.asarray(on_map.customdata)[:, 0]])


def test_protocol_pairs_is_each_protocols_scored_pairs(demo):
    from vpr_explorer.method.places import make_places
    from vpr_explorer.protocols.cost import protocol_pairs

    places = make_places(demo, SPEC)  # 12 places x 9 images
    n = 12 * 9
    assert protocol_pairs("paper", places, demo) == n * n
    assert protocol_pairs("traversal", places, demo) == 60 * 2 * 60  # every frame against two traversals
    assert protocol_pairs("traversal", places, demo, database=["day"]) == 60 * 60
    # open set: per split, one query per place against the known places' images, one held out of each
    known = 12 - round(0.3 * 12)  # 8
    assert protocol_pairs("open-set", places, demo, runs=5) == 5 * 12 * (known * 9 - known)
