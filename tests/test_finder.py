"""The Query inspector's finder and best candidates: ``numbers.find_query`` against a plain loop, and the page.

The reference decides every query one at a time (``explain_query``, the single-query path, not
the blocks ``find_query`` decides) and sorts it into the finder's kinds from their definitions:
a query whose right images all lie between places belongs to none; one with a right place is
rejected (wrongly), answered right, or answered with a wrong place; an unknown-place query is
rejected (right) or accepted (wrong). The expected find is then the first query of the kind on
a walk from the current query, one step at a time, round the end. Real GardensPoint (pixels,
night_right queries against day_right, group 3 step 10: 140 of the 200 queries lie between
places) and an open-set cut of it (day_right's first 140 frames: queries 140-199 have no
right image) cover every kind; the page is driven under AppTest on the demo route and GardensPoint.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest
from streamlit.testing.v1 import AppTest

from test_app import DEMO_SPEC, app, assert_clean, fitted_value, fresh_caches, navigation_mode, page  # noqa: F401
from vpr_explorer.app import ENTRY
from vpr_explorer.app.ui.candidates import BEST_IMAGES, ordinal
from vpr_explorer.data.aligned import database_queries, value_rows
from vpr_explorer.data.groundtruth import GroundTruth
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import PlaceGeometry, PlaceSpec
from vpr_explorer.views.numbers import (
    FIND_KINDS,
    RetrievalPlaces,
    database_label,
    explain_query,
    find_query,
    fit_retrieval,
    search_order,
    top_candidates,
    true_place_rank,
    walked,
)

GP_SPEC = PlaceSpec(3, 10)
OPEN_FRAMES = 140
"""The open-set cut keeps day_right's first 140 frames: queries 140-199 have no right image."""


# --------------------------------------------------------------------------- the reference


def loop_kinds(f, d, method: str, k: float = 0.0, user_theta: float | None = None) -> dict[str, list[int]]:
    """Every query's decision, one at a time, sorted into the finder's kinds from their definitions."""
    kinds: dict[str, list[int]] = {kind: [] for kind in FIND_KINDS}
    for q in range(f.dataset.n_queries):
        positives = f.dataset.ground_truth.positives(q)
        true = {int(f.database_place[i]) for i in positives if f.database_place[i] >= 0}
        if len(positives) and not true:
            continue  # between places: no right answer, never found
        dec = explain_query(f, d, q, k=k, user_theta=user_theta)
        answer = dec.answer(method)
        if not len(positives):  # an unknown place: rejecting it is right
            said = ["rejected", "right"] if answer < 0 else ["accepted unknown", "answered wrong"]
        elif answer < 0:
            said = ["rejected", "wrongly rejected", "answered wrong"]
        elif dec.is_right(method):
            assert answer in true
            said = ["right"]
        else:
            said = ["wrong answer", "answered wrong"]
        for kind in said:
            kinds[kind].append(q)
    return kinds


def first_on_walk(hits: list[int], after: int, n: int, direction: str) -> int | None:
    """The first of ``hits`` walking from ``after`` one query at a time (``after`` itself last), round the end."""
    step = 1 if direction == "next" else -1
    q = after
    for _ in range(n):
        q = (q + step) % n
        if q in hits:
            return q
    return None


def afters(hits: list[int], n: int) -> list[int]:
    """Queries to search from: both ends, a run of between-place frames (80-92), and either side of every hit's ends."""
    picked = {0, 1, 82, 83, 87, 89, 90, n - 1}
    for h in (hits[:1] + hits[-1:]):
        picked |= {h, (h - 1) % n, (h + 1) % n}
    return sorted(picked)


# --------------------------------------------------------------------------- GardensPoint values


@pytest.fixture(scope="module")
def closed(gardens_point, gp_pixels):
    """night_right queries against day_right, group 3 step 10: ``(fitted, descriptors)``."""
    value = database_queries(gardens_point, "night_right", database=["day_right"])
    rows = value_rows(value)
    d = gp_pixels if rows is None else gp_pixels[rows]
    return fit_retrieval(d, value, RetrievalPlaces(PlaceGeometry.FRAMES, spec=GP_SPEC)), d


@pytest.fixture(scope="module")
def open_set(closed):
    """The same with day_right cut after its first 140 frames: queries 140-199 are of unknown places."""
    f, d = closed
    value = f.dataset
    keep = value.database_frame < OPEN_FRAMES
    cut = dataclasses.replace(
        value, database_paths=tuple(p for p, kept in zip(value.database_paths, keep) if kept),
        database_xy=None if value.database_xy is None else value.database_xy[keep],
        ground_truth=GroundTruth.from_frames(value.query_frame, value.database_frame[keep]),
        database_traversal=value.database_traversal[keep], database_frame=value.database_frame[keep],
        n_frames=OPEN_FRAMES, frame_xy=None if value.frame_xy is None else value.frame_xy[:OPEN_FRAMES], aligned=None)
    dc = np.vstack([d[:value.n_database][keep], d[value.n_database:]])
    return fit_retrieval(dc, cut, RetrievalPlaces(PlaceGeometry.FRAMES, spec=GP_SPEC)), dc


#: (value, method, k): together they leave no kind without queries and none without an empty case.
#: ("answered wrong" has queries in every case: pixels at night never get every query right.)
CASES = [("closed", "margin-weighted", 0.0), ("closed", "margin-weighted", 2.0), ("closed", "global-auto", 0.0),
         ("closed", "place-baseline", 0.0), ("open", "margin-weighted", 0.0), ("open", "raw-weighted", 2.0),
         ("open", "global-auto", 0.0)]


@pytest.fixture(scope="module")
def reference(closed, open_set):
    values = {"closed": closed, "open": open_set}

    @functools.cache
    def kinds(which: str, method: str, k: float) -> dict[str, list[int]]:
        return loop_kinds(*values[which], method, k)

    return values, kinds


def test_the_cases_cover_every_kind_found_and_not_found(reference):
    values, kinds = reference
    for kind in FIND_KINDS:
        sizes = [len(kinds(*case)[kind]) for case in CASES]
        assert max(sizes) > 0 and (min(sizes) == 0 or kind == "answered wrong"), (kind, sizes)
    # the open set's unknown-place queries: accepted at k = 0, rejected (rightly) by the automatic θ
    assert set(kinds("open", "margin-weighted", 0.0)["accepted unknown"]) == set(range(OPEN_FRAMES, 200))
    assert set(range(OPEN_FRAMES, 200)) <= set(kinds("open", "global-auto", 0.0)["right"])


@pytest.mark.parametrize("direction", ["next", "previous"])
@pytest.mark.parametrize("kind", FIND_KINDS)
@pytest.mark.parametrize("case", CASES, ids=["-".join(map(str, c)) for c in CASES])
def test_find_query_is_the_first_such_query_on_the_walk(reference, case, kind, direction):
    values, kinds = reference
    which, method, k = case
    f, d = values[which]
    n = f.dataset.n_queries
    hits = kinds(which, method, k)[kind]
    for after in afters(hits, n):
        found, last = find_query(f, d, after=after, kind=kind, method=method, k=k, direction=direction)
        expected = first_on_walk(hits, after, n, direction)
        assert (found, last) == ((expected, expected) if expected is not None else (None, after)), after
        if found is not None:
            assert not f.between[found]
            assert walked(f, after, found, direction) == walk_past(f, after, found, direction)


def walk_past(f, after: int, last: int, direction: str) -> tuple[bool, int]:
    """One step at a time from ``after`` to ``last`` (a whole round when they are equal): whether a step went
    round the end (n − 1 to 0, or 0 to n − 1), and the queries passed that lie between places, ``last`` included."""
    n, step = f.dataset.n_queries, 1 if direction == "next" else -1
    q, wrapped, between = after, False, 0
    while True:
        nxt = (q + step) % n
        wrapped |= nxt < q if step == 1 else nxt > q
        q = nxt
        between += f.query_status(q) == "between places"
        if q == last:
            return wrapped, between


def test_between_place_frames_are_never_found_and_the_old_walk_is_gone(closed):
    """Global-auto rejects every query: "rejected" walks 80, 81, 82, then 90 (83-89 lie between places)."""
    f, d = closed
    assert np.array_equal(np.flatnonzero(f.between), [q for q in range(200) if q % 10 >= 3])  # group 3 of every 10
    assert [f.query_status(q) for q in (82, 83, 89, 90)] == ["known", "between places", "between places", "known"]
    walk, q = [], 79
    for _ in range(4):
        q, _ = find_query(f, d, after=q, kind="rejected", method="global-auto")
        walk.append(q)
    assert walk == [80, 81, 82, 90]
    assert walked(f, 82, 90, "next") == (False, 7)
    q, _ = find_query(f, d, after=90, kind="rejected", method="global-auto", direction="previous")
    assert q == 82 and walked(f, 90, 82, "previous") == (False, 7)
    for kind in FIND_KINDS:
        for method in ("global-auto", "margin-weighted"):
            for after in (83, 85, 199):
                found, _ = find_query(f, d, after=after, kind=kind, method=method, k=2.0)
                assert found is None or not f.between[found]


def test_wrap_round_at_either_end(closed):
    f, d = closed
    # "rejected" under global-auto: every query with a right place, 0-2, 10-12, …, 190-192
    assert find_query(f, d, after=192, kind="rejected", method="global-auto") == (0, 0)
    assert walked(f, 192, 0, "next") == (True, 7)  # 193-199 between places
    assert find_query(f, d, after=0, kind="rejected", method="global-auto", direction="previous") == (192, 192)
    assert walked(f, 0, 192, "previous") == (True, 7)
    assert find_query(f, d, after=199, kind="rejected", method="global-auto") == (0, 0)
    assert walked(f, 199, 0, "next") == (True, 0)
    # none at all: every query searched, the current one last; the walk went round and skipped every between frame
    assert find_query(f, d, after=57, kind="wrongly rejected", method="margin-weighted") == (None, 57)
    assert walked(f, 57, 57, "previous") == (True, 140)


def test_the_only_query_of_its_kind_is_found_from_itself(closed):
    f, d = closed
    kinds = loop_kinds(f, d, "margin-weighted", 1.0)
    assert len(kinds["wrongly rejected"]) == 1, kinds["wrongly rejected"]
    q = kinds["wrongly rejected"][0]
    for direction in ("next", "previous"):
        assert find_query(f, d, after=q, kind="wrongly rejected", method="margin-weighted", k=1.0,
                          direction=direction) == (q, q)
        assert walked(f, q, q, direction)[0]


@pytest.mark.parametrize("direction", ["next", "previous"])
def test_a_search_over_the_budget_stops_and_the_next_press_searches_on(closed, direction):
    f, d = closed
    n_db = len(f.model.images)
    hits = loop_kinds(f, d, "margin-weighted", 2.0)["wrongly rejected"]
    after, presses, searched = 100, 0, 0
    while True:
        found, last = find_query(f, d, after=after, kind="wrongly rejected", method="margin-weighted", k=2.0,
                                 direction=direction, pair_budget=7 * n_db, first_chunk=2)
        presses += 1
        if found is not None:
            break
        assert last == search_order(200, after, direction)[6]  # 7 queries a press
        searched += 7
        after = last
    assert found == first_on_walk(hits, 100, 200, direction)
    assert presses == searched // 7 + 1


def test_search_order_and_bad_input():
    assert search_order(5, 3, "next").tolist() == [4, 0, 1, 2, 3]
    assert search_order(5, 1, "previous").tolist() == [0, 4, 3, 2, 1]
    with pytest.raises(VPRInputError, match="direction='back'"):
        search_order(5, 1, "back")


def test_bad_kind_direction_or_query_is_named(closed):
    f, d = closed
    with pytest.raises(VPRInputError, match="kind='slow'"):
        find_query(f, d, after=0, kind="slow", method="place-baseline")
    with pytest.raises(VPRInputError, match="direction='up'"):
        find_query(f, d, after=0, kind="right", method="place-baseline", direction="up")
    with pytest.raises(VPRInputError, match="query 200"):
        find_query(f, d, after=200, kind="right", method="place-baseline")
    with pytest.raises(VPRInputError, match="query -1"):
        walked(f, 0, -1, "next")


# --------------------------------------------------------------------------- the true place's rank


def test_true_place_rank_is_its_place_in_the_raw_order(closed):
    f, d = closed
    ranks = []
    for q in range(200):
        dec = explain_query(f, d, q)
        got = true_place_rank(dec)
        if not len(dec.true_places):
            assert got is None and f.between[q]
            continue
        true = max(dec.true_places, key=lambda p: (dec.raw[p], -p))
        order = sorted(range(f.n_places), key=lambda p: (-dec.raw[p], p))
        assert got == (true, order.index(true) + 1)
        assert true in top_candidates(dec, 8)  # the charts carry it too
        ranks.append(got[1])
    assert max(ranks) > BEST_IMAGES and min(ranks) == 1  # GardensPoint by pixels at night: often far down


def test_ordinals():
    words = {1: "1st", 2: "2nd", 3: "3rd", 4: "4th", 11: "11th", 12: "12th", 13: "13th", 18: "18th", 21: "21st",
             22: "22nd", 23: "23rd", 101: "101st", 111: "111th", 112: "112th"}
    assert {n: ordinal(n) for n in words} == words


# --------------------------------------------------------------------------- the page (AppTest)


def info(at) -> str:
    return " | ".join(i.value for i in at.info)


def finder(at, kind: str, method: str):
    at.selectbox(key="w_find_kind").set_value(kind).run()
    at.selectbox(key="w_find_method").set_value(method).run()
    return at


def press(at, direction: str):
    at.button(key="w_find_next" if direction == "next" else "w_find_previous").click().run()
    assert_clean(at)
    return at.slider(key="w_frame").value


def test_previous_and_next_walk_the_library_s_finds_on_the_demo(app, demo, demo_pixels):
    f, d = fitted_value(demo, demo_pixels, DEMO_SPEC)
    hits = loop_kinds(f, d, "global-auto")["rejected"]
    assert 3 not in hits and 4 not in hits and f.between[3] and f.between[4]  # global-auto rejects them too
    at = finder(page(app.run(), "inspector"), "rejected", "global-auto")
    assert_clean(at)
    assert any("skips the 24 of 60 whose right database images all lie between places" in c.value for c in at.caption)
    frame = at.slider(key="w_frame").value
    assert frame == 0
    visited, notes = [], []
    for direction in ("next", "next", "next", "previous", "next", "next"):
        before, frame = frame, press(at, direction)
        assert frame == first_on_walk(hits, before, 60, direction) == at.number_input(key="w_frame_number").value
        assert not f.between[frame]
        _, skipped = walk_past(f, before, frame, direction)
        said = info(at)
        assert said.startswith(f"query {frame}: the {direction} query rejected under global θ, automatic"), said
        assert said.endswith(f" ({skipped} queries between places skipped on the way)" if skipped else "automatic")
        visited.append(frame)
        notes.append(skipped)
    assert visited == [1, 2, 5, 2, 5, 7] and notes == [0, 0, 2, 2, 2, 0]  # 3 and 4 lie between places


def test_the_walk_wraps_round_and_says_so(app, demo, demo_pixels):
    f, d = fitted_value(demo, demo_pixels, DEMO_SPEC)
    hits = loop_kinds(f, d, "global-auto")["rejected"]
    at = finder(page(app.run(), "inspector"), "rejected", "global-auto")
    at.slider(key="w_frame").set_value(hits[-1]).run()
    assert press(at, "next") == hits[0]
    assert f"no later one after query {hits[-1]}: wrapped round to the start, query {hits[0]} is the first" in info(at)
    assert press(at, "previous") == hits[-1]
    assert f"no earlier one before query {hits[0]}: wrapped round to the end, query {hits[-1]} is the last" in info(at)
    assert at.query_params["inspector_method"] == "global-auto" and "inspector_find" not in at.query_params


def test_kind_and_method_are_kept_in_the_url_and_a_link_restores_them(app, demo, demo_pixels):
    at = finder(page(app.run(), "inspector"), "wrong answer", "raw-weighted")
    assert at.query_params["inspector_find"] == "wrong answer"
    assert at.query_params["inspector_method"] == "raw-weighted"
    frame = press(at, "next")
    f, d = fitted_value(demo, demo_pixels, DEMO_SPEC)
    assert frame == find_query(f, d, after=0, kind="wrong answer", method="raw-weighted")[0] == 12
    page(at, "places")
    at = page(at, "inspector")  # another page and back: kept
    assert at.selectbox(key="w_find_kind").value == "wrong answer"
    shared = dict(at.query_params)

    fresh = AppTest.from_file(str(ENTRY), default_timeout=60)
    fresh.query_params.update(shared)
    fresh = page(fresh.run(), "inspector")
    assert_clean(fresh)
    assert fresh.selectbox(key="w_find_kind").value == "wrong answer"
    assert fresh.selectbox(key="w_find_method").value == "raw-weighted"
    assert fresh.slider(key="w_frame").value == 12
    fresh.selectbox(key="w_find_kind").set_value("rejected").run()  # the default: left out of the link
    assert "inspector_find" not in fresh.query_params


def test_a_refused_link_setting_is_said_and_the_default_used(app):
    app.query_params.update(inspector_find="sideways", inspector_method="global-user")
    at = page(app.run(), "inspector")
    assert_clean(at)
    warned = " ".join(w.value for w in at.warning)
    assert "inspector_find='sideways': choose one of rejected, wrongly rejected" in warned
    assert "inspector_method='global-user': your own global θ is off" in warned
    assert at.selectbox(key="w_find_kind").value == "rejected"
    assert at.selectbox(key="w_find_method").value == "margin-weighted"
    assert "inspector_find" not in at.query_params and "inspector_method" not in at.query_params
    at.run()
    assert not at.warning


def test_none_found_says_so_with_the_between_places_skipped(app):
    at = finder(page(app.run(), "inspector"), "accepted unknown", "margin-weighted")
    frame = at.slider(key="w_frame").value
    assert press(at, "previous") == frame
    assert ("no query was accepted though of an unknown place under margin, weighted θ (24 queries between places "
            "skipped on the way)") in info(at)


# --------------------------------------------------------------------------- best candidates (AppTest, GardensPoint)


def tiles(at) -> list[str]:
    return [c for element in at.image for c in element.captions if "raw_p" in c]


def test_the_true_place_is_among_the_best_candidates_at_its_rank(app, data_root, gardens_point, gp_pixels):
    f, d = fitted_value(gardens_point, gp_pixels, GP_SPEC)  # the app's value: night_right against day_left + day_right
    ranked = {q: true_place_rank(explain_query(f, d, q)) for q in range(0, 200, 10)}
    far = next(q for q, r in ranked.items() if r[1] > BEST_IMAGES)
    near = next(q for q, r in ranked.items() if r[1] <= BEST_IMAGES)
    app.query_params.update(source=str(data_root / "GardensPointWalking"), descriptor="pixels", frame=str(far))
    at = page(app.run(), "inspector")
    assert_clean(at)
    dec = explain_query(f, d, far)
    place, rank = ranked[far]
    label = database_label(f.dataset, int(f.model.images[dec.best_image[place]]))[:40]
    shown = tiles(at)
    assert len(shown) == BEST_IMAGES + 1
    assert shown[-1] == f"P{place}, {label}: raw_p {dec.raw[place]:.3f} (true place, ranked {ordinal(rank)})"
    assert [c.split(",")[0] for c in shown[:-1]] == [f"P{p}" for p in top_candidates(dec, 8)[:BEST_IMAGES]]
    assert any(f"it ranks {ordinal(rank)} of {f.n_places}" in c.value for c in at.caption)

    at.slider(key="w_frame").set_value(near).run()
    assert_clean(at)
    shown = tiles(at)
    assert len(shown) == BEST_IMAGES and sum(c.endswith("(right place)") for c in shown) == 1
    at.slider(key="w_frame").set_value(near + 5).run()  # between places: no true place to add
    assert len(tiles(at)) == BEST_IMAGES and not any("true place" in c for c in tiles(at))
