"""The numbers behind the app's views of a database/queries dataset, and the map, on small data built here.

Synthetic descriptors (``reference.unit_rows``) on a made-up database/queries dataset with
positions on a line; every figure is checked against a plain loop or the library's own
protocol (``evaluation.retrieval_protocol``, through ``pipeline.evaluate_retrieval``), and
the map's traces by hand.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from reference import loop_rank, unit_rows
from vpr_explorer.views import maps
from vpr_explorer.errors import VPRInputError
from vpr_explorer.data.groundtruth import GroundTruth
from vpr_explorer.data.layouts import Layout, RetrievalDataset
from vpr_explorer.pipeline import evaluate_retrieval
from vpr_explorer.method.places import MetricPlaceSpec, PlaceGeometry, PlaceSpec
from vpr_explorer.method.retrieval import METHODS_BY_KEY
from vpr_explorer.views.numbers import (
    BETWEEN,
    KNOWN,
    UNKNOWN,
    RetrievalPlaces,
    check_geometry,
    database_label,
    default_geometry,
    explain_query,
    find_query,
    find_query_by_name,
    fit_retrieval,
    geometries,
    image_answer,
    overview,
    place_detail,
    place_queries,
    query_label,
    radius_of,
)

N_DB, N_Q, DIM = 60, 30, 16


def dataset(layout=Layout.DATABASE_QUERIES, far=(25, 26, 27, 28, 29)) -> tuple[RetrievalDataset, np.ndarray]:
    """60 database images 10 m apart on a line, 30 queries near every other one; ``far`` queries 5 km off.

    Descriptors: each query is its nearest database image's vector plus noise; a far query
    is a random vector (its place is not in the database: it should be rejected).
    """
    rng = np.random.default_rng(3)
    db_xy = np.column_stack([500_000 + 10.0 * np.arange(N_DB), np.full(N_DB, 6_960_000.0)])
    q_xy = db_xy[::2][:N_Q] + [3.0, 0.0]
    q_xy[list(far), 1] += 5_000.0
    common = unit_rows(rng, 1, DIM)  # what every image shares (as real descriptors do): negatives near 0.6
    db = common + 0.8 * unit_rows(rng, N_DB, DIM)
    q = db[::2][:N_Q] + 0.5 * unit_rows(rng, N_Q, DIM)
    q[list(far)] = unit_rows(rng, len(far), DIM)  # another place: nothing in common with the database
    db /= np.linalg.norm(db, axis=1, keepdims=True)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    root = Path("/data/synthetic")
    ds = RetrievalDataset(
        name="synthetic", root=root, layout=layout,
        database_paths=tuple(root / "database" / f"db{i:03d}.jpg" for i in range(N_DB)),
        query_paths=tuple(root / "queries" / f"q{i:03d}.jpg" for i in range(N_Q)),
        database_xy=db_xy, query_xy=q_xy, ground_truth=GroundTruth.from_positions(q_xy, db_xy, 25.0),
        database_traversal=np.zeros(N_DB, dtype=np.int64), query_traversal=np.ones(N_Q, dtype=np.int64),
        traversals=("day", "night"), ordered=True,
    )
    return ds, np.vstack([db, q]).astype(np.float32)


ROUTE = RetrievalPlaces(PlaceGeometry.ROUTE, metric=MetricPlaceSpec(30.0, 50.0, "stride", "route"))


def test_the_place_level_numbers_are_the_protocols():
    ds, d = dataset()
    f = fit_retrieval(d, ds, ROUTE)
    ov = overview(f, d)
    ev = evaluate_retrieval(ds, d, metric=ROUTE.metric)
    for key in ("place-baseline", "margin-simple", "margin-weighted", "raw-simple", "raw-weighted"):
        assert ov.recall1[key] == pytest.approx(ev.row(key).recall[1][0]), key
    assert ov.n_unknown == 5 == ds.ground_truth.n_unknown
    unknown_rows = {r.key: r.unknown_rejection[0] for r in ev.rows if r.unknown_rejection is not None}
    assert ov.unknown_rejected["margin-weighted"] == pytest.approx(unknown_rows["margin-weighted"])


def test_places_status_and_right_places_by_a_loop():
    ds, d = dataset()
    f = fit_retrieval(d, ds, ROUTE)
    # route, stride 30 m every 50 m: database images at 0, 10, 20 m of every 50 m are in a place
    along = 10.0 * np.arange(N_DB)
    np.testing.assert_array_equal(f.database_place >= 0, (along % 50) < 30)
    assert f.n_places == 12
    for q in range(N_Q):
        pos = ds.ground_truth.positives(q)
        right = sorted({int(f.database_place[i]) for i in pos if f.database_place[i] >= 0})
        np.testing.assert_array_equal(np.flatnonzero(f.right_places([q])[0]), right)
        want = UNKNOWN if not len(pos) else KNOWN if right else BETWEEN
        assert f.query_status(q) == want, q


def test_a_decision_and_the_finder_agree_with_a_loop():
    ds, d = dataset()
    f = fit_retrieval(d, ds, ROUTE)
    rejected = []
    for q in range(N_Q):
        dec = explain_query(f, d, q)
        # raw_p by a loop: the best score of the query against each place's database images
        sims = d[N_DB + q] @ d[:N_DB].T
        for p in range(f.n_places):
            assert dec.raw[p] == pytest.approx(sims[f.database_place == p].max(), abs=1e-6)
        if dec.answer("margin-weighted") < 0:
            rejected.append(q)
    assert rejected, "the synthetic data should have a rejected query"
    found, _ = find_query(f, d, after=0, kind="rejected", method="margin-weighted", first_chunk=4)
    assert found == next(q for q in rejected if q > 0)
    wrong = [q for q in range(N_Q) if (f.query_status(q) == KNOWN and not explain_query(f, d, q).is_right("margin-weighted"))
             or (f.query_status(q) == UNKNOWN and explain_query(f, d, q).answer("margin-weighted") >= 0)]
    found, _ = find_query(f, d, after=N_Q - 1, kind="answered wrong", method="margin-weighted")
    assert found == (wrong[0] if wrong else None)


def test_the_field_image_answer_is_the_top_database_image():
    ds, d = dataset()
    for q in (0, 7, 26):
        a = image_answer(ds, d, q)
        sims = d[N_DB + q] @ d[:N_DB].T
        assert a.image == int(np.argmax(sims)) and a.score == pytest.approx(sims.max())
        assert a.positive == (a.image in ds.ground_truth.positives(q))
        assert a.distance == pytest.approx(np.hypot(*(ds.database_xy[a.image] - ds.query_xy[q])))
        correct = np.zeros(N_DB, dtype=bool)
        correct[ds.ground_truth.positives(q)] = True
        if correct.any():  # the field's R@1 counts the query iff a positive ranks first
            assert (loop_rank(sims[None].astype(np.float64), correct[None])[0] == 1) == a.positive


def test_geometries_offered_and_checked():
    ds, _ = dataset()
    assert geometries(ds) == (PlaceGeometry.FRAMES, PlaceGeometry.ROUTE, PlaceGeometry.LATTICE)
    assert default_geometry(ds) is PlaceGeometry.ROUTE  # one ordered route
    with pytest.raises(VPRInputError, match="geometry='spiral': 'synthetic' offers frames or route or lattice"):
        check_geometry(ds, "spiral")
    frames = RetrievalPlaces(PlaceGeometry.FRAMES, spec=PlaceSpec(3, 10))
    assert fit_retrieval(dataset()[1], ds, frames).n_places == 6
    assert radius_of(ds) == 25.0


def test_names_and_lookups():
    ds, _ = dataset()
    assert query_label(ds, 3) == "q003.jpg" and database_label(ds, 4) == "db004.jpg"
    assert find_query_by_name(ds, "q012.jpg") == 12 == find_query_by_name(ds, "queries/q012.jpg")
    with pytest.raises(VPRInputError, match="no query image of 'synthetic' has that name"):
        find_query_by_name(ds, "nope.jpg")
    tp, _ = dataset(Layout.TRAVERSAL_POSITIONS)
    assert query_label(tp, 3) == "night · frame 3" and database_label(tp, 4) == "day · frame 4"


# --------------------------------------------------------------------------- the map


def test_the_map_by_hand():
    db_xy = np.array([[500_012.0, 6_960_050.0], [500_112.0, 6_960_050.0], [500_212.0, 6_960_050.0]])
    q_xy = np.array([[500_020.0, 6_960_060.0], [500_300.0, 6_960_400.0]])
    fig = maps.layout_map(db_xy, np.array([0, -1, 1]), q_xy, selected=0, radius=25.0, positives=[0],
                          candidates=[1], answer=0)
    traces = {t.meta: t for t in fig.data}
    assert list(traces) == ["database, between places", "database places", "queries", "candidate places", "answer",
                            "positives", "radius", "selected query"]
    # origin: the multiple of 100 m at or below the lowest x and y
    assert fig.layout.xaxis.title.text == "east (m from 500,000)"
    assert fig.layout.yaxis.title.text == "north (m from 6,960,000)"
    np.testing.assert_allclose(traces["database places"].x, [12.0, 212.0])
    assert list(traces["database places"].text) == ["P0", "P1"]
    np.testing.assert_allclose(traces["database, between places"].x, [112.0])
    np.testing.assert_allclose(traces["candidate places"].x, [212.0])
    np.testing.assert_allclose(traces["answer"].x, [12.0])
    ring = traces["radius"]
    np.testing.assert_allclose(np.hypot(np.asarray(ring.x) - 20.0, np.asarray(ring.y) - 60.0), 25.0)
    assert list(traces["queries"].customdata) == [0, 1]
    assert fig.layout.yaxis.scaleanchor == "x"


def test_the_map_draws_big_traces_with_webgl():
    rng = np.random.default_rng(0)
    n = maps.WEBGL_POINTS + 1
    fig = maps.layout_map(rng.uniform(0, 1000, (n, 2)), np.zeros(n, dtype=np.int64), rng.uniform(0, 1000, (10, 2)))
    kinds = {t.meta: t.type for t in fig.data}
    assert kinds["database places"] == "scattergl" and kinds["queries"] == "scatter"


def test_methods_in_the_overview_are_the_pages():
    ds, d = dataset()
    ov = overview(fit_retrieval(d, ds, ROUTE), d)
    assert set(ov.recall1) <= set(METHODS_BY_KEY)


def test_a_places_queries_and_their_raw_p_by_a_loop():
    ds, d = dataset()
    f = fit_retrieval(d, ds, ROUTE)
    for p in range(f.n_places):
        detail = place_detail(f, d, p)
        want = [q for q in range(ds.n_queries) if np.isin(ds.ground_truth.positives(q), detail.images).any()]
        np.testing.assert_array_equal(place_queries(f, p), want)
        np.testing.assert_array_equal(detail.query_images, ds.n_database + np.asarray(want, dtype=np.int64))
        for i, raw in zip(detail.query_images, detail.query_raw):
            assert raw == pytest.approx(max(float(d[i] @ d[j]) for j in detail.images), abs=1e-6)
    far = [p for p in range(f.n_places) if not len(place_queries(f, p))]
    assert far  # the database images the far queries moved away from
    assert np.isnan(place_detail(f, d, far[0]).share_queries_below(0.0))


@pytest.mark.parametrize("query", ["snow", "day"])
def test_a_place_on_aligned_traversals_is_its_frames_in_every_traversal(demo, demo_pixels, query):
    """A place of group/step over frames: its frames in each database traversal, the query traversal's
    frames in it as its queries; scores and thresholds by plain loops over the traversals' rows."""
    from vpr_explorer.data.aligned import database_queries, value_rows
    from vpr_explorer.method.places import frame_places
    from vpr_explorer.method.stats import negative_stats
    from vpr_explorer.method.thresholds import ThresholdMethod, place_thresholds

    spec = PlaceSpec(3, 5)
    value = database_queries(demo, query)
    rows = value_rows(value)
    rows = np.arange(demo.n_images) if rows is None else rows
    f = fit_retrieval(demo_pixels[rows], value, RetrievalPlaces(PlaceGeometry.FRAMES, spec=spec))
    frame_place = frame_places(demo.n_frames, spec)
    database = [t for t in demo.traversals if t != query]
    placed = np.array([demo.image_index(t, fr) for t in database for fr in np.flatnonzero(frame_place >= 0)])
    labels = frame_place[demo.image_frame[placed]]
    stats = negative_stats(demo_pixels[placed], labels, f.n_places)
    theta = {m.value: place_thresholds(stats, m) for m in ThresholdMethod}
    d = np.asarray(demo_pixels, dtype=np.float64)
    for p in range(f.n_places):
        mine = place_detail(f, demo_pixels[rows], p)
        frames = np.flatnonzero(frame_place == p)
        own = np.array([demo.image_index(t, fr) for t in database for fr in frames])
        np.testing.assert_array_equal(rows[mine.images], own)
        queries = [demo.image_index(query, fr) for fr in frames]
        np.testing.assert_array_equal(rows[mine.query_images], queries)  # the query frames in the place
        np.testing.assert_allclose(mine.query_raw, [max(d[q] @ d[i] for i in own) for q in queries], atol=1e-6)
        other = placed[labels != p]
        np.testing.assert_allclose(np.sort(mine.negatives), np.sort([d[i] @ d[j] for i in own for j in other]),
                                   atol=1e-6)
        assert mine.theta == pytest.approx({name: t[p] for name, t in theta.items()}, rel=1e-6)
