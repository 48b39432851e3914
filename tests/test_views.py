"""The app's views on big datasets: overviews sample, one-place and one-query views never compute all pairs.

The demo route keeps these fast; the pair budget is lowered so that sampling happens on
60 frames the way it does on 27,591 (``benchmarks/bench_app_scale.py`` runs the real size).
"""

from __future__ import annotations

import numpy as np
import pytest

from vpr_explorer.method import database
from vpr_explorer.views import plots
from vpr_explorer.views import traversal as views
from vpr_explorer.method.database import decide_traversal, explain_query
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import PlaceSpec
from vpr_explorer.views.traversal import FIND_KINDS, find_frame, fit, overview_frames, place_detail, regroup

SPEC = PlaceSpec(3, 5)
BUDGET = 1000  # query x database similarities; the demo's 60 frames x 72 database images are 4,320


@pytest.fixture(scope="module")
def fitted(demo, demo_pixels):
    return fit(demo_pixels, demo, SPEC)


@pytest.fixture(scope="module")
def full(demo, demo_pixels, fitted):
    return decide_traversal(fitted.model, demo_pixels, demo, fitted.places, fitted.query)


@pytest.fixture
def pairs(monkeypatch):
    """Counts the query x database similarities computed (the real function runs)."""
    counter = {"pairs": 0}
    real, real_t = database.similarity, database.similarity_t

    def counting(a, b):
        counter["pairs"] += len(a) * len(b)
        return real(a, b)

    def counting_t(a, b, out=None):  # the fused decisions: database rows × queries, a piece at a time
        counter["pairs"] += len(a) * len(b)
        return real_t(a, b, out=out)

    monkeypatch.setattr(database, "similarity", counting)
    monkeypatch.setattr(database, "similarity_t", counting_t)
    monkeypatch.setattr(views, "similarity", counting)
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


def test_decide_traversal_on_some_frames_equals_those_rows_of_the_whole_traversal(demo, demo_pixels, fitted, full):
    frames = np.array([41, 3, 17, 59, 0])
    some = decide_traversal(fitted.model, demo_pixels, demo, fitted.places, fitted.query, frames=frames)
    np.testing.assert_array_equal(some.query_images, full.query_images[frames])
    np.testing.assert_array_equal(some.truth, full.truth[frames])
    # BLAS sums in another order for another batch shape: equal to float32 rounding.
    np.testing.assert_allclose(some.raw, full.raw[frames], atol=1e-6)
    for key, o in full.outcomes.items():
        for field in ("rank", "answer_place", "answer_image", "n_kept"):
            np.testing.assert_array_equal(getattr(some.outcomes[key], field), getattr(o, field)[frames])
    with pytest.raises(VPRInputError, match="frames"):
        decide_traversal(fitted.model, demo_pixels, demo, fitted.places, fitted.query, frames=np.array([60]))
    with pytest.raises(VPRInputError, match="frames"):
        decide_traversal(fitted.model, demo_pixels, demo, fitted.places, fitted.query, frames=np.array([], int))


def test_a_small_block_gives_the_same_decisions(demo, demo_pixels, fitted, full):
    blocked = decide_traversal(fitted.model, demo_pixels, demo, fitted.places, fitted.query, block=7)
    for key, o in full.outcomes.items():
        np.testing.assert_array_equal(blocked.outcomes[key].rank, o.rank)
    np.testing.assert_allclose(blocked.raw, full.raw, atol=1e-6)


def test_regroup_over_the_budget_decides_a_sample_and_its_numbers_are_those_frames(demo, demo_pixels, full, pairs):
    r = regroup(demo_pixels, demo, SPEC, pair_budget=BUDGET)
    n_db = len(r.model.images)
    assert r.sampled and r.n_frames == 60 and len(r.frames) == BUDGET // n_db
    assert pairs["pairs"] == len(r.frames) * n_db <= BUDGET  # the overview's query x database pairs
    scored = full.truth[r.frames].any(axis=1)
    np.testing.assert_array_equal(r.scored, scored)
    for key, o in full.outcomes.items():
        assert r.recall1[key] == pytest.approx(float((o.rank[r.frames][scored] == 1).mean()))
        assert r.rejected[key] == pytest.approx(float((~o.accepted[r.frames][scored]).mean()))
    rejected = r.rejected_frames("margin-weighted")
    assert set(rejected) <= set(r.frames)
    np.testing.assert_array_equal(rejected, r.frames[full.outcomes["margin-weighted"].answer_place[r.frames] < 0])


def test_regroup_under_the_budget_decides_every_frame(demo, demo_pixels, full):
    r = regroup(demo_pixels, demo, SPEC)
    assert not r.sampled
    np.testing.assert_array_equal(r.frames, np.arange(60))
    np.testing.assert_array_equal(r.decisions.outcomes["raw-weighted"].rank, full.outcomes["raw-weighted"].rank)


def test_one_place_and_one_query_never_compute_the_traversal(demo, demo_pixels, fitted, pairs):
    """The Thresholds and Inspector pages' work: their own rows against the database, nothing more."""
    n_db = len(fitted.model.images)
    d = place_detail(fitted.model, demo_pixels, demo, fitted.places, 4, fitted.query)
    assert pairs["pairs"] == len(d.images) * n_db + len(d.query_images) * len(d.images)
    pairs["pairs"] = 0
    explain_query(fitted.model, demo_pixels, demo, fitted.places, demo.image_index(fitted.query, 31))
    assert pairs["pairs"] == n_db


@pytest.mark.parametrize("kind", FIND_KINDS)
@pytest.mark.parametrize("method", ["margin-weighted", "raw-weighted", "place-baseline"])
def test_find_frame_is_the_next_such_frame_after_the_current_one_wrapping(demo, demo_pixels, fitted, full, kind,
                                                                          method):
    o = full.outcomes[method]
    bad = np.flatnonzero(~o.accepted if kind == "rejected" else (full.truth.any(axis=1) & ~o.right))
    for after in (0, 17, 45, 59):
        found, last = find_frame(fitted, demo_pixels, demo, after=after, kind=kind, method=method)
        if len(bad):
            expected = next((int(f) for f in bad if f > after), int(bad[0]))
            assert (found, last) == (expected, expected)
        else:
            assert (found, last) == (None, after)  # searched every frame


def test_find_frame_stops_at_the_budget_and_pressing_again_searches_on(demo, demo_pixels, fitted, full, pairs):
    o = full.outcomes["place-baseline"]
    bad = np.flatnonzero(full.truth.any(axis=1) & ~o.right)
    assert len(bad) and bad[0] > 5, "the demo should have a first wrong frame beyond frame 5"
    n_db = len(fitted.model.images)
    budget = 3 * n_db  # three frames per press
    after, presses = -1, 0
    while True:
        pairs["pairs"] = 0
        found, last = find_frame(fitted, demo_pixels, demo, after=after % 60, kind="answered wrong",
                                 method="place-baseline", pair_budget=budget, first_chunk=1)
        assert pairs["pairs"] <= budget
        presses += 1
        if found is not None:
            break
        assert last == (after + 3) % 60
        after = last
    assert found == bad[0] and presses == bad[0] // 3 + 1
    with pytest.raises(VPRInputError, match="kind"):
        find_frame(fitted, demo_pixels, demo, after=0, kind="slow", method="place-baseline")


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
