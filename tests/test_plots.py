"""Figures draw the library's numbers: each figure's data is checked against the value it stands for.

Mirrors ``vpr_explorer/views/plots.py`` and ``vpr_explorer/views/numbers.py``. Most tests use the
built-in demo route as its dataset value (``data.aligned.database_queries``: database day +
night, queries the snow frames) with pixel descriptors (seconds); the ``realdata`` ones use
GardensPoint through ``VPR_EXPLORER_DATA``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from vpr_explorer.data.aligned import database_queries, split_traversals, value_rows
from vpr_explorer.method.places import PlaceGeometry, PlaceSpec, frame_places, make_places
from vpr_explorer.method.retrieval import similarity
from vpr_explorer.method.stats import mixture_pdf, negative_stats
from vpr_explorer.method.thresholds import ThresholdMethod, place_thresholds
from vpr_explorer.pipeline import run_protocol
from vpr_explorer.protocols.evaluation import Protocol
from vpr_explorer.views import plots
from vpr_explorer.views.numbers import (
    LIVE_METHODS,
    RetrievalPlaces,
    explain_query,
    fit_retrieval,
    overview,
    place_detail,
    similarity_grid,
    top_candidates,
)

SPEC = PlaceSpec(3, 5)
PLACES = RetrievalPlaces(PlaceGeometry.FRAMES, spec=SPEC)


@pytest.fixture(scope="module")
def value(demo):
    return database_queries(demo)  # the descriptors' own order: database rows 0-119, query q at row 120 + q


@pytest.fixture(scope="module")
def fitted(value, demo_pixels):
    return fit_retrieval(demo_pixels, value, PLACES)


@pytest.fixture(scope="module")
def ov(fitted, demo_pixels):
    return overview(fitted, demo_pixels)


def by_meta(fig, meta):
    """The one trace whose ``meta`` is ``meta``."""
    found = [t for t in fig.data if t.meta == meta]
    assert len(found) == 1, f"{len(found)} traces with meta {meta!r}: {[t.meta for t in fig.data]}"
    return found[0]


def vline_x(fig, name):
    trace = by_meta(fig, name)
    assert trace.x[0] == trace.x[1]
    return trace.x[0]


# --------------------------------------------------------------------------- views (the numbers)


def test_split_is_every_other_traversal_against_the_last(demo):
    assert split_traversals(demo) == (("day", "night"), "snow")
    assert split_traversals(demo, "day") == (("night", "snow"), "day")


def test_overview_recall_equals_the_traversal_protocol(demo, demo_pixels, ov):
    """The live page's Recall@1 is the library's traversal protocol on the same split."""
    ev = run_protocol(Protocol.TRAVERSAL, demo, make_places(demo, SPEC), demo_pixels,
                      database=["day", "night"], queries="snow")
    for key in LIVE_METHODS:
        assert ov.recall1[key] == pytest.approx(ev.row(key).recall[1][0]), key
    assert ov.n_scored == ev.settings["queries_scored"]


def test_thresholds_come_from_the_database_only(demo, demo_pixels, value, fitted):
    model = fitted.model
    assert set(value.database_traversal[model.images]) == {0, 1} and model.images.max() < value.n_database
    # the closed form on the database images in places, and nothing else, gives the fitted θ_p
    stats = negative_stats(demo_pixels[model.images], model.places, fitted.n_places)
    for method in ThresholdMethod:
        np.testing.assert_allclose(model.theta[method.value], place_thresholds(stats, method), rtol=1e-6)
    # other query descriptors leave every threshold as it was
    other = demo_pixels.copy()
    other[value.n_database:] = demo_pixels[::-1][:value.n_queries]
    refit = fit_retrieval(other, value, PLACES).model
    for name, theta in model.theta.items():
        np.testing.assert_array_equal(refit.theta[name], theta)


@pytest.mark.parametrize("n", [1, 1000, 3 * (1 << 10) + 17])
def test_density_histogram_in_parts_is_one_numpy_histogram(monkeypatch, n):
    # parts of 1,024 values counted side by side: numpy's density histogram of the float64 copy, bit for bit
    monkeypatch.setattr(plots, "HISTOGRAM_PART", 1 << 10)
    x = (np.random.default_rng(n).standard_normal(n) * 0.1 + 0.3).astype(np.float32)
    lo, hi = float(x.min()), float(x.max()) + 0.01
    density, edges = plots.density_histogram(x, 60, lo, hi)
    want, want_edges = np.histogram(x.astype(np.float64), bins=60, range=(lo, hi), density=True)
    np.testing.assert_array_equal(density, want)
    np.testing.assert_array_equal(edges, want_edges)
    assert edges.dtype == np.float64


def test_place_detail_scores_equal_a_pairwise_reference(demo, demo_pixels, value, fitted):
    p = 4
    d = place_detail(fitted, demo_pixels, p)
    model = fitted.model
    own = model.images[model.places == p]
    other = model.images[model.places != p]
    sims = np.asarray(demo_pixels, dtype=np.float64) @ np.asarray(demo_pixels, dtype=np.float64).T
    np.testing.assert_allclose(np.sort(d.negatives), np.sort(sims[np.ix_(own, other)].ravel()), atol=1e-5)
    pos = [sims[i, j] for a, i in enumerate(own) for j in own[a + 1:]]
    np.testing.assert_allclose(np.sort(d.positives), np.sort(pos), atol=1e-5)
    # μᵢ of each component is the mean of that image's negative scores (the closed form equals the pairs).
    np.testing.assert_allclose(d.mu, sims[np.ix_(own, other)].mean(axis=1), atol=1e-5)
    frames = np.flatnonzero(frame_places(demo.n_frames, SPEC) == p)  # the snow frames of place p
    query = [demo.image_index("snow", f) for f in frames]  # = n_database + query q: the value's own rows
    np.testing.assert_array_equal(d.query_images, query)
    np.testing.assert_allclose(d.query_raw, sims[np.ix_(query, own)].max(axis=1), atol=1e-5)
    assert d.theta["weighted"] == pytest.approx(model.theta["weighted"][p])
    assert d.theta_k(1.5) == pytest.approx(model.thresholds(1.5)["weighted"][p])
    assert d.share_negatives_above(-2.0) == 1.0 and d.share_negatives_above(2.0) == 0.0
    # the scores are kept as float32 (as scored); a θ between two float32 values is compared in float64
    top = float(d.negatives.max())
    assert d.negatives.dtype == np.float32
    assert d.share_negatives_above(top) == pytest.approx(np.mean(d.negatives == d.negatives.max()))
    assert d.share_negatives_above(top + 1e-9) == 0.0  # rounded to float32, top + 1e-9 would be top


def test_top_candidates_keeps_the_right_place(demo_pixels, fitted):
    dec = explain_query(fitted, demo_pixels, 16)
    cands = top_candidates(dec, 3)
    np.testing.assert_array_equal(cands[:3], np.argsort(-dec.raw, kind="stable")[:3])
    assert set(dec.true_places) <= set(cands)


def _pair_reference(d, value, queries):
    """Plain loops: s(query q, database image i) of the value's rows, in float64."""
    out = np.full((len(queries), value.n_database), -np.inf)
    for a, q in enumerate(queries):
        for i in range(value.n_database):
            out[a, i] = float(d[value.n_database + q] @ d[i])
    return out


def _pooled(z, rows, cols):
    """Maxima of ``z`` over blocks of ``rows`` × ``cols``, the last ones padded with -inf."""
    r, c = -(-z.shape[0] // rows), -(-z.shape[1] // cols)
    padded = np.full((r * rows, c * cols), -np.inf)
    padded[:z.shape[0], :z.shape[1]] = z
    return padded.reshape(r, rows, c, cols).max(axis=(1, 3))


def assert_cells_hold_their_pair(grid, d, value):
    """The pair behind every cell scores exactly the cell's value, and is a query x database image pair."""
    s = np.einsum("ijk,ijk->ij", d[value.n_database + grid.query_image], d[grid.db_image])
    np.testing.assert_allclose(s, grid.z, atol=1e-5)
    assert 0 <= grid.query_image.min() and grid.query_image.max() < value.n_queries
    assert 0 <= grid.db_image.min() and grid.db_image.max() < value.n_database


def test_similarity_grid_pools_block_maxima_and_keeps_their_pair(demo_pixels, value):
    full = similarity_grid(value, demo_pixels)
    assert full.block == full.row_block == 1 and full.z.shape == (60, 120) and not full.sampled
    d = np.asarray(demo_pixels, dtype=np.float64)
    reference = _pair_reference(d, value, range(60))
    np.testing.assert_allclose(full.z, reference, atol=1e-5)
    pooled = similarity_grid(value, demo_pixels, max_side=25)  # 60 queries in blocks of 3, 120 images in 5
    assert (pooled.row_block, pooled.block) == (3, 5) and pooled.z.shape == (20, 24)
    np.testing.assert_array_equal(pooled.z, _pooled(full.z, 3, 5))
    np.testing.assert_array_equal(pooled.row_frames, np.arange(20) * 3)
    np.testing.assert_array_equal(pooled.col_frames, np.arange(24) * 5)
    for grid in (full, pooled):
        assert_cells_hold_their_pair(grid, np.asarray(demo_pixels), value)
    # the database holds both database traversals: each column block one traversal's frames
    assert set(value.database_traversal[pooled.db_image.ravel()]) == {0, 1}


def test_similarity_grid_over_the_pair_budget_samples_rows_and_keeps_exact_column_maxima(demo_pixels, value):
    """Above the budget each row is one query (its block's centre) against every database image."""
    grid = similarity_grid(value, demo_pixels, max_side=25, pair_budget=1000)
    # 1,000 // 120 = 8 rows of one query each: 960 similarities, within the budget
    assert grid.sampled and grid.row_block == 8 and grid.block == 5 and grid.z.shape == (8, 24)
    # each row block's centre; the last block (56-59) is short: its last query
    np.testing.assert_array_equal(grid.row_frames, [4, 12, 20, 28, 36, 44, 52, 59])
    np.testing.assert_array_equal(grid.query_image, np.repeat(grid.row_frames[:, None], 24, 1))
    reference = _pair_reference(np.asarray(demo_pixels, dtype=np.float64), value, grid.row_frames)
    np.testing.assert_allclose(grid.z, _pooled(reference, 1, 5), atol=1e-5)
    assert_cells_hold_their_pair(grid, np.asarray(demo_pixels), value)


def test_similarity_grid_handles_a_last_block_that_is_not_full(demo, demo_pixels):
    one = database_queries(demo, "snow", ["day"])  # 60 database images: the snow rows move up
    rows = value_rows(one)
    d = demo_pixels[rows]
    grid = similarity_grid(one, d, max_side=7)  # 60 queries and 60 images in blocks of 9: 6 + 6 left
    assert grid.block == grid.row_block == 9 and grid.z.shape == (7, 7)
    reference = _pair_reference(np.asarray(d, dtype=np.float64), one, range(60))
    np.testing.assert_allclose(grid.z, _pooled(reference, 9, 9), atol=1e-5)
    assert_cells_hold_their_pair(grid, d, one)
    np.testing.assert_allclose(reference, np.asarray(demo_pixels[120:], np.float64) @
                               np.asarray(demo_pixels[:60], np.float64).T, atol=1e-12)  # snow × day


# --------------------------------------------------------------------------- figures


def test_route_figure_marks_place_and_skipped_frames(demo, value, fitted):
    fp = frame_places(demo.n_frames, SPEC)  # what the Places page draws
    np.testing.assert_array_equal(fitted.database_place, fp[value.database_frame])  # the fit's places
    fig = plots.route_figure(fp, demo.traversals, demo.positions)
    for t in demo.traversals:
        places = by_meta(fig, f"places {t}")
        np.testing.assert_array_equal(places.x, np.flatnonzero(fp >= 0))
        np.testing.assert_array_equal(places.customdata, fp[fp >= 0])
        np.testing.assert_array_equal(by_meta(fig, f"skipped {t}").x, np.flatnonzero(fp < 0))
    np.testing.assert_allclose(by_meta(fig, "map places").x, demo.positions[fp >= 0, 0])
    assert all(t.meta != "route" for t in plots.route_figure(fp, demo.traversals).data)


def test_theta_histogram_holds_every_theta_and_the_global_line(fitted):
    model = fitted.model
    fig = plots.theta_histogram(model.theta, model.auto, user_theta=0.3)
    for name in ("simple", "weighted"):
        np.testing.assert_allclose(by_meta(fig, f"θ_p {name}").x, model.theta[name])
    assert vline_x(fig, "global θ, automatic") == pytest.approx(model.auto)
    assert vline_x(fig, "global θ, user value") == pytest.approx(0.3)


def test_recall_bars_heights_are_the_recalls(ov):
    recall = {k: ov.recall1[k] for k in LIVE_METHODS}
    fig = plots.recall_bars(recall, rejected={k: ov.rejected[k] for k in LIVE_METHODS})
    np.testing.assert_allclose(by_meta(fig, "recall1").y, list(recall.values()))
    assert list(by_meta(fig, "recall1").customdata) == list(LIVE_METHODS)
    np.testing.assert_allclose(by_meta(fig, "rejected").y, [ov.rejected[k] for k in LIVE_METHODS])


def test_places_overview_sorted_by_theta_with_place_ids(fitted):
    model = fitted.model
    fig = plots.places_overview(model.theta["weighted"], model.positive_mean, model.negative_mean, selected=2)
    bars = by_meta(fig, "theta")
    order = np.argsort(model.theta["weighted"], kind="stable")
    np.testing.assert_array_equal(bars.customdata, order)
    np.testing.assert_allclose(bars.y, model.theta["weighted"][order])
    assert np.all(np.diff(bars.y) >= 0)
    np.testing.assert_allclose(by_meta(fig, "positive_mean").y, model.positive_mean[order])
    assert bars.marker.color[list(order).index(2)] == plots.POSITIVE


def test_mixture_figure_curves_and_lines_are_the_library_values(demo_pixels, fitted):
    p = 6
    d = place_detail(fitted, demo_pixels, p)
    fig = plots.mixture_figure(d, k=1.0, method="simple", user_theta=0.45)
    mixture = by_meta(fig, "mixture")
    x = np.asarray(mixture.x)
    np.testing.assert_allclose(mixture.y, mixture_pdf(x, d.mu, d.sigma, d.weight))
    components = [by_meta(fig, f"component {i}") for i in range(len(d.mu))]
    for i, c in enumerate(components):
        np.testing.assert_allclose(c.y, d.weight[i] * np.exp(-0.5 * ((x - d.mu[i]) / d.sigma[i]) ** 2)
                                   / (d.sigma[i] * np.sqrt(2 * np.pi)))
    np.testing.assert_allclose(np.sum([c.y for c in components], axis=0), mixture.y)
    model = fitted.model
    assert vline_x(fig, "θ_p simple") == pytest.approx(model.theta["simple"][p])
    assert vline_x(fig, "θ_p weighted") == pytest.approx(model.theta["weighted"][p])
    assert vline_x(fig, "θ_p(k)") == pytest.approx(model.thresholds(1.0)["simple"][p])
    assert vline_x(fig, "global θ, automatic") == pytest.approx(model.auto)
    assert vline_x(fig, "global θ, user value") == pytest.approx(0.45)
    # The negative scores are binned on the server (10⁶ of them at 100k images): the bars
    # are numpy's density histogram of every negative score, and integrate to 1.
    bars = by_meta(fig, "negatives")
    density, edges = np.histogram(d.negatives.astype(np.float64), bins=plots.NEGATIVE_BINS, density=True)
    np.testing.assert_array_equal(bars.y, density)  # float32 scores binned on float64 edges
    np.testing.assert_allclose(bars.x, (edges[:-1] + edges[1:]) / 2)
    assert np.sum(np.asarray(bars.y) * np.asarray(bars.width)) == pytest.approx(1.0)
    np.testing.assert_allclose(by_meta(fig, "positives").x, d.positives)
    np.testing.assert_allclose(by_meta(fig, "query_raw").x, d.query_raw)


@pytest.mark.parametrize("key", LIVE_METHODS)
def test_candidate_bars_are_raw_p_with_theta_and_kept_colours(demo_pixels, fitted, key):
    dec = explain_query(fitted, demo_pixels, 31, k=0.5)
    cands = top_candidates(dec, 6)
    fig = plots.candidate_bars(dec, key, cands)
    bars = by_meta(fig, "raw_p")
    np.testing.assert_allclose(bars.y, dec.raw[cands])
    np.testing.assert_array_equal(bars.customdata, cands)
    kept = dec.kept(key)[cands]
    assert list(bars.marker.color) == [plots.KEPT if k else plots.DROPPED for k in kept]
    outlined = [c for c, colour in zip(cands, bars.marker.line.color) if colour == "#000"]
    assert outlined == ([dec.answer(key)] if dec.answer(key) in cands else [])
    threshold = {"place-baseline": None, "global-auto": "auto"}.get(key, key.split("-")[1])
    if threshold is None:
        assert all(t.meta != "theta" for t in fig.data)
    else:
        np.testing.assert_allclose(by_meta(fig, "theta").y, dec.thresholds[threshold][cands])
        np.testing.assert_array_equal(np.asarray(by_meta(fig, "theta").y) <= bars.y, kept)


@pytest.fixture(scope="module")
def open_set(demo, demo_pixels):
    return run_protocol(Protocol.OPEN_SET, demo, make_places(demo, SPEC), demo_pixels, runs=4, seed=1)


def test_evaluation_rows_and_strict_json(open_set):
    import json

    from vpr_explorer.views.numbers import evaluation_json, evaluation_rows

    rows = evaluation_rows(open_set)
    assert [r["method"] for r in rows] == [r.label for r in open_set.rows]
    for row, r in zip(rows, open_set.rows):
        assert row["R@1"] == pytest.approx(100 * r.recall[1][0])
        assert row["R@10 ±"] == pytest.approx(100 * r.recall[10][1])
        assert row["unknown rejected"] == pytest.approx(100 * r.unknown_rejection[0])
    text = evaluation_json(open_set)
    data = json.loads(text, parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))
    assert data["protocol"] == "open-set" and len(data["tradeoff"]) == len(open_set.tradeoff)
    methods = {m["key"]: m for m in data["methods"]}
    assert list(methods) == [r.key for r in open_set.rows]
    for r in open_set.rows:  # every number is the library's
        m = methods[r.key]
        assert (m["recall"]["1"]["mean"], m["recall"]["10"]["std"]) == (r.recall[1][0], r.recall[10][1])
        assert [m[name]["mean"] for name in ("accepted", "precision", "unknown_rejection", "own_traversal_top1")] \
            == [r.accepted[0], r.precision[0], r.unknown_rejection[0], r.own_traversal[0]]
    # The automatic θ accepts 1 query in 12 (0.0833; none at all in some splits), and each of those is right:
    # precision 1 in every split that accepts, and those without accepted queries are left out, not NaN.
    auto = methods["global-auto"]
    assert auto["accepted"]["mean"] == pytest.approx(1 / 12) and auto["accepted"]["std"] > 0
    assert auto["precision"] == {"mean": 1.0, "std": 0.0}
    # A θ of the sweep above every query's best score accepts none in any split: its precision is
    # undefined in the library (NaN) and null in the strict JSON.
    none_accepted = [t for t in open_set.tradeoff if t.accepted[0] == 0]
    assert none_accepted and all(math.isnan(t.precision[0]) for t in none_accepted)
    for t, j in zip(open_set.tradeoff, data["tradeoff"]):
        assert j["precision"] == ({"mean": None, "std": None} if t.accepted[0] == 0 else
                                  {"mean": t.precision[0], "std": t.precision[1]})


def test_recall_figure_bars_and_error_bars_are_the_rows(open_set):
    fig = plots.recall_figure(open_set)
    for k in open_set.ks:
        trace = by_meta(fig, f"R@{k}")
        np.testing.assert_allclose(trace.y, [r.recall[k][0] for r in open_set.rows])
        np.testing.assert_allclose(trace.error_y.array, [r.recall[k][1] for r in open_set.rows])
        assert list(trace.customdata) == [r.key for r in open_set.rows]


@pytest.mark.parametrize("rule", ["margin", "raw"])
def test_tradeoff_figure_points_are_the_tradeoff_rows(open_set, rule):
    fig = plots.tradeoff_figure(open_set, rule)
    for series in ("θ_p(k) simple", "θ_p(k) weighted"):
        rows = [t for t in open_set.tradeoff if t.series == series and t.rule == rule]
        curve = by_meta(fig, series)
        np.testing.assert_allclose(curve.x, [t.unknown_rejection[0] for t in rows])
        np.testing.assert_allclose(curve.y, [t.known_recall1[0] for t in rows])
        np.testing.assert_allclose(curve.customdata, [t.param for t in rows])
        paper = next(t for t in rows if t.param == 0.0)
        k0 = by_meta(fig, f"k0 {series}")
        assert (k0.x[0], k0.y[0]) == pytest.approx((paper.unknown_rejection[0], paper.known_recall1[0]))
    auto = next(t for t in open_set.tradeoff if t.series == "global θ, automatic")
    marker = by_meta(fig, "global θ, automatic")
    assert (marker.x[0], marker.y[0]) == pytest.approx((auto.unknown_rejection[0], auto.known_recall1[0]))
    sweep = [t for t in open_set.tradeoff if t.series == "global θ"]
    np.testing.assert_allclose(by_meta(fig, "global θ").customdata, [t.param for t in sweep])


def test_similarity_heatmap_cells_carry_their_pair(demo_pixels, value):
    grid = similarity_grid(value, demo_pixels, max_side=30)
    fig = plots.similarity_heatmap(grid, query="snow", database=("day", "night"), marked=(4, 7))
    np.testing.assert_allclose(by_meta(fig, "similarity").z, grid.z)
    cells = by_meta(fig, "cells")
    assert len(cells.x) == grid.z.size
    pairs = np.asarray(cells.customdata)
    np.testing.assert_array_equal(pairs[:, 0], grid.query_image.ravel())
    np.testing.assert_array_equal(pairs[:, 1], grid.db_image.ravel())
    # A cell's marker sits at its row/column block's first query and database image, so a click
    # opens the pair drawn there.
    np.testing.assert_array_equal(cells.y, np.repeat(grid.row_frames, len(grid.col_frames)))
    np.testing.assert_array_equal(cells.x, np.tile(grid.col_frames, len(grid.row_frames)))
    assert (by_meta(fig, "marked").x[0], by_meta(fig, "marked").y[0]) == (7, 4)


def test_selected_pair_reads_both_forms_of_a_clicked_point():
    assert plots.selected_pair({"customdata": [132, 30]}) == (132, 30)
    assert plots.selected_pair({"customdata": {"1": 30, "0": 132}}) == (132, 30)  # typed-array form
    assert plots.selected_pair({"x": 3}) is None
    assert plots.selected_pair({"customdata": 7}) is None


def test_plots_module_never_imports_streamlit():
    import ast
    from pathlib import Path

    for module in ("plots.py", "numbers.py"):
        tree = ast.parse((Path(plots.__file__).parent / module).read_text())
        names = {a.name for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom)) for a in n.names}
        names |= {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
        assert not any(str(x).startswith("streamlit") for x in names), module


# --------------------------------------------------------------------------- real data


@pytest.mark.realdata
def test_gardens_point_theta_line_is_the_computed_theta(gardens_point, gp_pixels):
    """GardensPoint, paper places (group 3, step 10): 20 places; the drawn θ_p is the fitted one."""
    assert split_traversals(gardens_point) == (("day_left", "day_right"), "night_right")
    value = database_queries(gardens_point)
    assert value_rows(value) is None  # the descriptors' own order
    f = fit_retrieval(gp_pixels, value, RetrievalPlaces(PlaceGeometry.FRAMES, spec=PlaceSpec(3, 10)))
    assert f.n_places == 20
    for p in (0, 7, 19):
        d = place_detail(f, gp_pixels, p)
        fig = plots.mixture_figure(d, k=0.5)
        assert vline_x(fig, "θ_p weighted") == pytest.approx(f.model.theta["weighted"][p])
        assert vline_x(fig, "θ_p(k)") == pytest.approx(f.model.thresholds(0.5)["weighted"][p])
        assert len(d.images) == 6 and len(d.query_images) == 3
    sims = similarity(gp_pixels[d.query_images], gp_pixels[d.images])
    np.testing.assert_allclose(d.query_raw, sims.max(axis=1), atol=1e-6)
