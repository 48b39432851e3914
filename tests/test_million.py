"""A million-image database on one machine: float16 memory maps, chunked fits, the app on them.

Everything here runs the same code path as the 1,000,000-image benchmark
(``benchmarks/bench_million.py``), on databases small enough for a test: descriptors as a
float16 memory map (from a descriptor file, or the cache's dataset view), never converted
whole; fits and decisions a block of rows at a time.
"""

from __future__ import annotations

import hashlib
import os
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest
from streamlit.testing.v1 import AppTest

# the autouse fixtures of test_app (fresh caches, navigation mode) apply here too
from test_app import assert_clean, fresh_caches, metric, navigation_mode, page  # noqa: F401
from vpr_explorer.views import numbers as rv
from vpr_explorer.app import ENTRY
from vpr_explorer.descriptors import DescriptorCache, DescriptorCacheWarning
from vpr_explorer.descriptors import cache as cache_module
from vpr_explorer.descriptors.store import MMAP_ENV
from vpr_explorer.errors import VPRInputError
from vpr_explorer.protocols.evaluation import retrieval_protocol
from vpr_explorer.data.example_million import write_route_database
from vpr_explorer.data.groundtruth import GroundTruth
from vpr_explorer.data.layouts import Layout, RetrievalDataset
from vpr_explorer.pipeline import dataset_descriptors, evaluate_retrieval, imported_descriptors, open_dataset, \
    resolve_dataset, retrieval_places
from vpr_explorer.method.places import MetricPlaceSpec, PlaceGeometry
from vpr_explorer.method import stats as stats_module
from vpr_explorer.method.retrieval import pessimistic_rank, place_scores, score_queries, similarity, top_answer
from vpr_explorer.method.stats import negative_stats, negative_stats_rows, positive_means, stats_rows, validate_descriptors, \
    validate_rows, RowsOf
from vpr_explorer.views.numbers import evaluation_rows

ROUTE = rv.RetrievalPlaces(PlaceGeometry.ROUTE, metric=MetricPlaceSpec(25.0, 100.0))


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """8,000 database images one metre apart and 400 queries, D = 48: the manifest, links and a float16 .npy."""
    folder = tmp_path_factory.mktemp("small_db")
    manifest, npy = write_route_database(folder, n_database=8_000, n_queries=400, dim=48, seed=1)
    ds = open_dataset(manifest)
    mm = imported_descriptors(ds, npy, mmap=True).descriptors
    return ds, npy, mm


def test_a_float16_file_is_mapped_as_stored_not_copied(small):
    ds, npy, mm = small
    assert isinstance(mm, np.memmap) and mm.dtype == np.float16 and Path(mm.filename) == npy.resolve()
    assert not mm.flags.writeable
    # "auto" maps from MMAP_MIN_BYTES: this file is far smaller, so it is read into memory
    small_read = imported_descriptors(ds, npy).descriptors
    assert not isinstance(small_read, np.memmap) and small_read.dtype == np.float32
    assert validate_descriptors(mm) is mm  # checked chunk-wise, returned as is


def test_the_memmap_path_equals_the_dense_float32_path(small):
    ds, _, mm = small
    dense = np.asarray(mm, dtype=np.float32)  # the same values, in memory
    a, b = rv.fit_retrieval(dense, ds, ROUTE), rv.fit_retrieval(mm, ds, ROUTE)
    # the rows of places read a block at a time, each float16 block converted to float32 (exactly), give
    # the closed form of the gathered float32 rows bit for bit: same blocks, same products, same order
    for key in a.model.theta:
        np.testing.assert_array_equal(b.model.theta[key], a.model.theta[key])
    np.testing.assert_array_equal(b.model.spread, a.model.spread)
    np.testing.assert_array_equal(b.model.positive_mean, a.model.positive_mean)
    assert b.model.auto == a.model.auto  # the tile sample scores the same float32 values
    same = negative_stats(dense[a.model.images], a.model.places, a.n_places)
    np.testing.assert_array_equal(negative_stats_rows(dense, a.model.images, a.model.places, a.n_places).sigma,
                                  same.sigma)  # bit-identical to the gathered rows' closed form
    queries = np.arange(ds.n_queries)
    truth_a, out_a = rv.decide_queries(a, dense, queries)
    truth_b, out_b = rv.decide_queries(b, mm, queries)
    np.testing.assert_array_equal(truth_a, truth_b)
    for key, o in out_a.items():
        for field in ("rank", "answer_place", "answer_image", "n_kept"):
            np.testing.assert_array_equal(getattr(out_b[key], field), getattr(o, field), err_msg=f"{key} {field}")
    for q in (0, 17, ds.n_queries - 1):
        assert rv.image_answer(ds, mm, q) == rv.image_answer(ds, dense, q)
        da, db = rv.explain_query(a, dense, q), rv.explain_query(b, mm, q)
        np.testing.assert_array_equal(da.raw, db.raw)
    pa, pb = rv.place_detail(a, dense, 5), rv.place_detail(b, mm, 5)
    np.testing.assert_array_equal(pa.negatives, pb.negatives)


def _float16_rows(n: int, dim: int, seed: int = 0) -> np.ndarray:
    """Unit rows stored as float16 (what a descriptor file holds), route-like: neighbours alike."""
    rng = np.random.default_rng(seed)
    x = np.cumsum(rng.standard_normal((n, dim), dtype=np.float32), axis=0) * 0.05 + rng.standard_normal(dim)
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float16)


@pytest.mark.parametrize("block, threads", [(4096, None), (1000, 2), (4096, 1)])
def test_one_reading_for_the_fit_gives_the_closed_form_bit_for_bit_and_the_positive_means(block, threads):
    # 13,522 rows in places, with gaps between runs (a last block of 1,234; chunks of the positive
    # means straddling blocks of 1,000), places of 20 images (the last of 2); the closed form with
    # the same threads (one thread leaves BLAS its own, whose Haswell kernel splits some sums)
    d16 = _float16_rows(20_000, 40)
    rows = np.flatnonzero(np.arange(20_000) % 37 < 25)[:13_522]
    labels = np.arange(len(rows)) // 20
    n_places = int(labels.max()) + 1
    gathered = d16[rows].astype(np.float32)
    want = negative_stats(gathered, labels, n_places, block=block, threads=threads)
    got, pm = stats_rows(d16, rows, labels, n_places, block=block, threads=threads)
    np.testing.assert_array_equal(got.mu, want.mu)
    np.testing.assert_array_equal(got.sigma, want.sigma)
    np.testing.assert_array_equal(got.n_neg, want.n_neg)
    # the positive means from the place terms' same-place scores: positive_means summed otherwise
    np.testing.assert_allclose(pm, positive_means(gathered, labels, n_places, threads=1), rtol=0, atol=1e-13)
    np.testing.assert_array_equal(negative_stats_rows(d16, rows, labels, n_places, block=block, threads=threads).sigma,
                                  want.sigma)


def test_float16_blocks_convert_to_the_same_float32_numbers():
    # torch's cast (as_float32, every read of a float16 map) is numpy's, bit for bit: every float16
    # (subnormals, signed zeros, inf) but NaNs, which stay NaN (the hardware cast sets a signalling
    # NaN's quiet bit; the checks refuse NaN rows either way); read-only (a map's rows) and strided
    # blocks too, without a warning
    bits = np.arange(2**16, dtype=np.uint16).view(np.float16).reshape(256, 256)
    bits.flags.writeable = False
    for block in (bits, bits[::3, 1::2], bits[:0]):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            got = stats_module.as_float32(block)
        want = block.astype(np.float32)
        assert got.dtype == np.float32 and got.shape == want.shape
        nan = np.isnan(want)
        np.testing.assert_array_equal(np.isnan(got), nan)
        np.testing.assert_array_equal(got[~nan].view(np.uint32), want[~nan].view(np.uint32))
    d32 = np.ones((3, 2), dtype=np.float32)
    assert stats_module.as_float32(d32) is d32  # float32 as is


def test_a_fit_read_out_of_order_falls_back_to_its_own_passes(monkeypatch):
    # a stray read before the Gram's (as a changed closed form might make) breaks the one-reading
    # order: the checks and the positive means then run on their own, and the numbers are the same
    d16 = _float16_rows(9_000, 24, seed=1)
    rows = np.arange(0, 9_000, 2)
    labels = np.arange(len(rows)) // 15
    closed_form = stats_module._closed_form_float32

    def stray_first(d, *args):
        d[0:10]
        return closed_form(d, *args)

    monkeypatch.setattr(stats_module, "_closed_form_float32", stray_first)
    got, pm = stats_rows(d16, rows, labels, threads=2)
    gathered = d16[rows].astype(np.float32)
    np.testing.assert_array_equal(got.sigma, negative_stats(gathered, labels).sigma)
    np.testing.assert_allclose(pm, positive_means(gathered, labels, int(labels.max()) + 1), rtol=0, atol=1e-13)


def test_a_bad_row_stops_the_one_reading_fit_with_the_checks_message():
    d16 = _float16_rows(12_000, 16, seed=2)
    d16[5_000] = np.nan
    d16[9_001] = 0
    rows = np.arange(12_000)
    labels = np.arange(12_000) // 10
    with pytest.raises(VPRInputError, match=r"rows 5000 contain NaN or inf.*\(counting from row 0\)"):
        validate_rows(RowsOf(d16, rows), "training descriptors")  # the checks alone, in blocks of CHECK_ELEMS
    with pytest.raises(VPRInputError) as fitted:  # on the Gram's blocks: row 4,096 + 904, before any product
        stats_rows(d16, rows, labels)
    assert "rows 904 contain NaN or inf" in str(fitted.value) and "(counting from row 4,096)" in str(fitted.value)
    d16[5_000] = d16[4_999]
    with pytest.raises(VPRInputError, match=r"rows 713 are all zero.*\(counting from row 8,288\)"):
        stats_rows(d16, rows, labels, block=4144)


def test_decisions_by_place_pieces_equal_the_straightforward_scoring(small):
    # decide_queries scores database x queries a piece of places at a time (retrieval.PlaceLayout); the
    # straightforward path (query x database scores, place_scores, score_queries) defines the answers
    ds, _, mm = small
    dense = np.asarray(mm, dtype=np.float32)
    for places in (ROUTE, rv.RetrievalPlaces(PlaceGeometry.LATTICE, metric=MetricPlaceSpec(30.0, 30.0))):
        f = rv.fit_retrieval(mm, ds, places)
        queries = np.arange(0, ds.n_queries, 3)
        th = f.model.thresholds(0.5, 0.7)
        sims = similarity(dense[ds.n_database + queries], dense[f.model.images])
        want = score_queries(sims, f.model.places, f.n_places, th, f.right_places(queries),
                             raw_best=place_scores(sims, f.model.places, f.n_places))
        for d, block in ((mm, 2048), (dense, 2048), (mm, 7)):
            _, got = rv.decide_queries(f, d, queries, k=0.5, user_theta=0.7, block=block)
            assert got.keys() == want.keys()
            for key, o in want.items():
                for field in ("rank", "answer_place", "answer_image", "n_kept"):
                    np.testing.assert_array_equal(getattr(got[key], field), getattr(o, field), err_msg=f"{key} {field}")


def test_the_protocol_on_a_memmap_gives_the_protocols_table(small):
    ds, _, mm = small
    dense = np.asarray(mm, dtype=np.float32)
    place, n_places = retrieval_places(ds, None, ROUTE.metric)
    want = retrieval_protocol(dense[:ds.n_database], dense[ds.n_database:], place, n_places, ds.ground_truth)
    got = evaluate_retrieval(ds, mm, metric=ROUTE.metric)  # blocks of the memmap, the fit's float32 thresholds
    assert [r.key for r in got.rows] == [r.key for r in want.rows]
    for g, w in zip(got.rows, want.rows):
        np.testing.assert_equal((g.recall, g.accepted, g.unknown_rejection),  # a one-run std is NaN on both sides
                                (w.recall, w.accepted, w.unknown_rejection), err_msg=g.key)
    # small query blocks (a million-image database's) give the same table
    tiny = rv.evaluate_fitted(rv.fit_retrieval(mm, ds, ROUTE), mm, score_elems=ds.n_database * 40)
    np.testing.assert_equal([r.recall for r in tiny.rows], [r.recall for r in got.rows])
    assert any("float16 a block at a time" in n for n in got.notes)


def test_the_image_level_without_dense_copies_is_the_reference(small):
    ds, _, mm = small
    rows = np.arange(ds.n_queries)
    sims = rv.score_rows(mm, ds.n_database + rows, ds.n_database)
    sims[5, :40] = sims[5].max()  # ties at the top: the lowest index within the tolerance answers
    pos = ds.ground_truth.positives(7)
    sims[7, pos[0] + 1] = sims[7, pos].max() + 0.5e-5  # a wrong image within the tolerance of the best positive
    answer, rank, top = rv.image_level(sims, ds.ground_truth, rows)
    wide = sims.astype(np.float64)
    np.testing.assert_array_equal(answer, top_answer(wide))
    np.testing.assert_array_equal(rank, pessimistic_rank(wide, ds.ground_truth.dense(rows)))
    np.testing.assert_array_equal(top, wide.max(axis=1))
    assert answer[5] == 0 and np.isinf(rank[ds.ground_truth.counts == 0]).all()


def test_float16_rows_with_nan_or_zero_are_named(small, tmp_path):
    ds, npy, mm = small
    rows = np.array(mm)
    rows[3] = np.nan
    rows[ds.n_database + 2] = 0
    bad = tmp_path / "bad.npy"
    np.save(bad, rows)
    with pytest.raises(VPRInputError) as exc:
        imported_descriptors(ds, bad, mmap=True)
    text = str(exc.value)
    assert "1 are NaN or infinite (database/0000/0000003.png)" in text
    assert "1 are all zero (queries/0000/0000002.png)" in text and str(bad) in text
    mapped = np.load(bad, mmap_mode="r")
    with pytest.raises(VPRInputError, match="rows 3 contain NaN"):
        validate_descriptors(mapped)


def test_a_fit_on_a_memmap_holds_memory_in_proportion_to_a_block(tmp_path):
    n, dim = 200_000, 512
    rng = np.random.default_rng(0)
    path = tmp_path / "d.npy"
    out = np.lib.format.open_memmap(path, mode="w+", dtype=np.float16, shape=(n + 10, dim))
    for lo in range(0, n + 10, 50_000):
        x = rng.standard_normal((min(50_000, n + 10 - lo), dim), dtype=np.float32)
        out[lo:lo + len(x)] = x / np.linalg.norm(x, axis=1, keepdims=True)
    out.flush()
    del out
    mm = np.load(path, mmap_mode="r")
    xy = np.c_[np.arange(n, dtype=np.float64), np.zeros(n)]
    qxy = np.c_[np.linspace(0, n, 10), np.zeros(10)]
    ds = RetrievalDataset(name="synthetic", root=tmp_path, layout=Layout.MANIFEST,
                          database_paths=tuple(Path(f"d{i}.png") for i in range(n)),
                          query_paths=tuple(Path(f"q{i}.png") for i in range(10)), database_xy=xy, query_xy=qxy,
                          ground_truth=GroundTruth.from_positions(qxy, xy, 25.0),
                          database_traversal=np.zeros(n, dtype=np.int64), query_traversal=np.ones(10, dtype=np.int64),
                          traversals=("database", "queries"), ordered=True)
    places = rv.RetrievalPlaces(PlaceGeometry.ROUTE, metric=MetricPlaceSpec(50.0, 50.0))  # every image in a place
    tracemalloc.start()
    try:
        fitted = rv.fit_retrieval(mm, ds, places)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(fitted.model.images) == n
    float32_copy = n * dim * 4  # 410 MB: what converting the database whole would take
    # the fit's own per-image arrays (places, μ, σ, counts, labels, terms, the tile sample; about 340 bytes
    # an image measured, whatever D), then a few blocks of rows, the D × D Gram matrices and the place sums
    per_image = 48 * 8 * n
    blocks = 8 * 4096 * dim * 4 + 4 * dim * dim * 8 + 8 * (n // 50) * dim
    assert peak < per_image + blocks < float32_copy / 2, (peak, per_image + blocks, float32_copy)


# --------------------------------------------------------------------------- the cache's dataset view


def _hashes(n: int, seed: int = 0) -> list[str]:
    return [hashlib.sha256(f"{seed}-{i}".encode()).hexdigest() for i in range(n)]


@pytest.fixture
def scattered(tmp_path):
    """A float32 cache holding 600 vectors over three shards, and the dataset's order (shuffled)."""
    cache = DescriptorCache(tmp_path / "cache")
    rng = np.random.default_rng(0)
    hashes = _hashes(600)
    vectors = rng.standard_normal((600, 64)).astype(np.float32)
    vectors /= np.linalg.norm(vectors, axis=1, keepdims=True)
    for part in np.array_split(rng.permutation(600), 3):
        cache.store("key", [hashes[i] for i in part], vectors[part])
    order = rng.permutation(600)
    return cache, [hashes[i] for i in order], vectors[order]


def test_the_dataset_view_is_compacted_once_in_dataset_order(scattered):
    cache, hashes, vectors = scattered
    view = cache.dataset_view("key", hashes)
    assert isinstance(view, np.memmap) and view.dtype == np.float16
    np.testing.assert_array_equal(view, vectors.astype(np.float16))
    files = sorted(p.name for p in (cache.folder / "key" / "views").iterdir())
    assert len(files) == 2 and files[0].endswith(".json") and files[1].endswith(".npy")  # no temporary left
    stamp = (cache.folder / "key" / "views" / files[1]).stat().st_mtime_ns
    again = cache.dataset_view("key", hashes)  # opened, not written again
    assert (cache.folder / "key" / "views" / files[1]).stat().st_mtime_ns == stamp
    np.testing.assert_array_equal(again, view)
    assert cache.dataset_view("key", hashes + _hashes(1, seed=9)) is None  # one image not cached: no view
    assert len(list((cache.folder / "key" / "views").iterdir())) == 2
    cache.clear("key")
    assert not (cache.folder / "key").exists()


@pytest.mark.parametrize("damage", ["byte", "truncate", "byte-full"])
def test_a_damaged_view_is_refused_and_written_again(scattered, damage):
    cache, hashes, vectors = scattered
    cache.dataset_view("key", hashes)
    npy = next((cache.folder / "key" / "views").glob("*.npy"))
    st = npy.stat()
    with open(npy, "r+b") as fh:
        if damage == "truncate":
            fh.truncate(st.st_size - 128)
        else:
            fh.seek(st.st_size // 2)
            byte = fh.read(1)
            fh.seek(st.st_size // 2)
            fh.write(bytes([byte[0] ^ 0x40]))
    if damage != "truncate":
        os.utime(npy, ns=(st.st_atime_ns, st.st_mtime_ns))  # silent damage: same size and mtime
    with pytest.warns(DescriptorCacheWarning, match="damaged dataset view"):
        view = cache.dataset_view("key", hashes, verify="full" if damage == "byte-full" else "spots")
    np.testing.assert_array_equal(view, vectors.astype(np.float16))  # written again from the shards


def test_a_compaction_that_dies_leaves_nothing_visible(scattered, monkeypatch):
    cache, hashes, vectors = scattered

    def dies(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(cache_module.os, "replace", dies)
    with pytest.raises(VPRInputError, match="cannot write a dataset view"):
        cache.dataset_view("key", hashes)
    monkeypatch.undo()
    assert not list((cache.folder / "key" / "views").iterdir())  # its temporary removed, no manifest
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_array_equal(cache.dataset_view("key", hashes), vectors.astype(np.float16))


@pytest.mark.realdata
def test_cached_descriptors_of_real_images_come_back_as_the_float16_view(data_root, tmp_path):
    ds = resolve_dataset(data_root / "GardensPointWalking")
    dense = dataset_descriptors(ds, "pixels", cache_root=tmp_path)
    view = dataset_descriptors(ds, "pixels", cache_root=tmp_path, mmap=True)
    assert isinstance(view, np.memmap) and view.shape == dense.shape
    np.testing.assert_array_equal(view, dense.astype(np.float16))
    fresh = tmp_path / "fresh"  # nothing cached yet: extracted into the cache first, then compacted
    np.testing.assert_array_equal(dataset_descriptors(ds, "pixels", cache_root=fresh, mmap=True), view)


# --------------------------------------------------------------------------- the app on a memory-mapped database


def test_the_app_walks_a_memory_mapped_database(tmp_path, monkeypatch):
    monkeypatch.setenv(MMAP_ENV, "0")  # the path a 1 GiB file takes, at a test's size
    manifest, npy = write_route_database(tmp_path, n_database=50_000, n_queries=500, dim=64, seed=2)
    ds = open_dataset(manifest)
    mm = imported_descriptors(ds, npy).descriptors
    assert isinstance(mm, np.memmap)
    at = AppTest.from_file(str(ENTRY), default_timeout=120)
    at.query_params.update(source=str(manifest), descriptors=str(npy), geometry="route", group_m="25.0",
                           step_m="100.0")
    at.run()
    assert_clean(at)
    assert any("memory-mapped as stored (float16" in c.value for c in at.caption), [c.value for c in at.caption]

    at = page(at, "places")
    assert_clean(at)
    f = rv.fit_retrieval(mm, ds, ROUTE)
    assert metric(at, "places") == f"{f.n_places}" == "500"
    assert any("the 20,000 nearest the selected query" in c.value for c in at.caption)
    at = page(at, "thresholds")
    at.selectbox(key="w_place").set_value(7).run()
    assert_clean(at)
    detail = rv.place_detail(f, mm, 7)
    n_db, n_q = len(detail.images), len(detail.query_images)
    assert any(f"**P7**: {n_db:,} database image{'s' * (n_db != 1)} and {n_q:,} quer{'ies' if n_q != 1 else 'y'}"
               in m.value
               for m in at.markdown)
    above = detail.share_negatives_above(detail.theta["weighted"])
    assert metric(at, "negative scores ≥ θ_p weighted") == f"{above:.0%}"
    at = page(at, "places")
    at.number_input(key="w_step_m").set_value(50.0).run()
    assert_clean(at)
    assert metric(at, "places") == "1000"

    at = page(at, "inspector")
    assert_clean(at)
    at.selectbox(key="w_find_method").set_value("global-auto").run()
    at.button(key="w_find_next").click().run()
    assert_clean(at)
    f50 = rv.fit_retrieval(mm, ds, rv.RetrievalPlaces(PlaceGeometry.ROUTE, metric=MetricPlaceSpec(25.0, 50.0)))
    found, _ = rv.find_query(f50, mm, after=0, kind="rejected", method="global-auto")
    assert at.number_input(key="w_frame_number").value == found

    at = page(at, "evaluation")  # 500 × 50,000 pairs: it runs by itself (a million-image one waits for Run)
    assert_clean(at)
    ev = evaluate_retrieval(ds, mm, metric=MetricPlaceSpec(25.0, 50.0))
    table = at.dataframe[0].value
    assert table["method"].tolist() == [r["method"] for r in evaluation_rows(ev)]
    assert table["R@1"].tolist() == pytest.approx([r["R@1"] for r in evaluation_rows(ev)])
