"""The explorer on a synthetic 1,000,000-image position-tagged database.

Writes (once, into ``--out``) a route of ``--database`` images one metre apart and
``--queries`` queries (``vpr_explorer.data.example_million``: a manifest ``path,role,x,y``,
symbolic links to one small PNG as the images, and the descriptors as a float16 ``.npy``
in the manifest's order). The descriptors come as a float16 descriptor file, not through
the cache: the cache is keyed by each image's content, and a million distinct images would
be gigabytes written only to be hashed; the file is the other way a big database arrives
(descriptors computed on a GPU machine), and both end in the same float16 memory map
(``tests/test_million.py`` checks the cache's dataset view against the file's).

Then, in one process, each step of the explorer on it, timed against **one blocked pass
over the same query × database scores** measured in the same run (every query against every
database image, the database read once from the memory map, a float32 GEMM per block, the
row maxima kept: the least any evaluation of all queries must do), with the peak resident
memory after it (``ru_maxrss``; the memory map's pages count in it while resident):

* first load: the manifest (a million lines, each image checked, the 25 m ground truth) and
  the descriptor file (hashed for its key, every row checked), mapped, not read into memory;
* a group/step change in metres (the fit: closed-form statistics over the images in places,
  a block at a time, and the automatic θ's tile sample), the move back (kept fits: free),
  the Places page's sampled overview; each fit with its GEMM floor (2·N·D² flops, the Gram
  and the quadratic forms, at the floor pass's rate), and at the end whether any refit can
  be under 3 s on this machine (at D = 2,048 and 500,000 images in places it cannot);
* one place (its images against the database: the Thresholds page), one query, the next
  rejected query (the Query inspector);
* the evaluation of every query with the database/queries protocol;
* ``--faiss``: the image-level top-10 of every query by ``faiss.IndexFlatIP`` against the
  same blocked numpy pass (numbers side by side, results compared);
* ``--app``: the app's pages on the same files under AppTest, in process.

``--device cuda`` runs the fits' two N·D² products on the GPU (``fit_retrieval(device=…)``, what
the app does under ``VPR_EXPLORER_DEVICE``); the floor pass stays numpy's.

``python benchmarks/bench_million.py --dim 512 --skip-eval`` takes about 1.5 minutes on 2 cores (the
Haswell kernel) once its files are written (1 GB under ``--out``, written once, about a minute and
a quarter); the protocol over every query and ``--app`` add about 2 and 3 minutes (5 minutes in
all with both). ``--dim 2048``: 4 GB of files, about 4× each pass.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
PAGE_GOAL_S = 3.0
MEMORY_GOAL_GIB = 8.0


def peak_rss_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def blocked_pass(descriptors: np.ndarray, n_database: int, n_queries: int, rows: int = 8_192,
                 top_k: int = 0) -> tuple[np.ndarray, np.ndarray | None, float]:
    """Every query against every database image: the database a block of ``rows`` at a time (float16 -> float32
    once), one GEMM per block; the row maxima (and with ``top_k`` the top-k ids). Returns them and the seconds."""
    start = time.perf_counter()
    q = np.asarray(descriptors[n_database:n_database + n_queries], dtype=np.float32)
    best = np.full(n_queries, -np.inf, dtype=np.float32)
    top_s = np.full((n_queries, top_k), -np.inf, dtype=np.float32) if top_k else None
    top_i = np.full((n_queries, top_k), -1, dtype=np.int64) if top_k else None
    buf = np.empty((rows, descriptors.shape[1]), dtype=np.float32)
    for lo in range(0, n_database, rows):
        x = buf[: min(rows, n_database - lo)]
        np.copyto(x, descriptors[lo:lo + len(x)], casting="same_kind")
        s = q @ x.T
        np.maximum(best, s.max(axis=1), out=best)
        if top_k:
            part = np.argpartition(-s, top_k - 1, axis=1)[:, :top_k]
            cand_s = np.concatenate([top_s, np.take_along_axis(s, part, axis=1)], axis=1)
            cand_i = np.concatenate([top_i, part + lo], axis=1)
            keep = np.argsort(-cand_s, axis=1, kind="stable")[:, :top_k]
            top_s = np.take_along_axis(cand_s, keep, axis=1)
            top_i = np.take_along_axis(cand_i, keep, axis=1)
    return best, (top_s, top_i) if top_k else None, time.perf_counter() - start


def faiss_search(descriptors: np.ndarray, n_database: int, n_queries: int, k: int, rows: int = 8_192):
    """``faiss.IndexFlatIP`` over the database (added a float32 block at a time), searched by every query."""
    import faiss

    start = time.perf_counter()
    index = faiss.IndexFlatIP(descriptors.shape[1])
    for lo in range(0, n_database, rows):
        index.add(np.asarray(descriptors[lo:min(lo + rows, n_database)], dtype=np.float32))
    built = time.perf_counter() - start
    q = np.asarray(descriptors[n_database:n_database + n_queries], dtype=np.float32)
    scores, ids = index.search(q, k)
    return scores, ids, built, time.perf_counter() - start


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(os.environ.get("TMPDIR", "/tmp")) / "vpr_million",
                        help="folder for the database's files (kept for the next run; delete it when done)")
    parser.add_argument("--database", type=int, default=1_000_000)
    parser.add_argument("--queries", type=int, default=10_000)
    parser.add_argument("--dim", type=int, default=512, help="descriptor length (512 or 2048)")
    parser.add_argument("--group", type=float, default=25.0, help="metres per place")
    parser.add_argument("--step", type=float, default=100.0, help="metres between places")
    parser.add_argument("--step2", type=float, default=50.0, help="the step moved to")
    parser.add_argument("--faiss", action="store_true", help="compare faiss.IndexFlatIP (pip install faiss-cpu)")
    parser.add_argument("--app", action="store_true", help="time the app's pages under AppTest")
    parser.add_argument("--skip-eval", action="store_true", help="leave out the protocol over every query")
    parser.add_argument("--device", default=None,
                        help="torch device for the fits' products (cpu, cuda; default numpy, as VPR_EXPLORER_DEVICE)")
    args = parser.parse_args(argv)

    from gemm_peak import blas_kernel, load_average

    from vpr_explorer.views import numbers as rv
    from vpr_explorer.data.example_million import write_route_database
    from vpr_explorer.pipeline import evaluate_retrieval, imported_descriptors, open_dataset
    from vpr_explorer.method.places import MetricPlaceSpec, PlaceGeometry
    from vpr_explorer.method.stats import prepare_float16_reads

    folder = args.out / f"db{args.database}_q{args.queries}_d{args.dim}"
    manifest, npy = folder / "manifest.csv", folder / "descriptors.npy"
    if not (manifest.is_file() and npy.is_file()):
        start = time.perf_counter()
        write_route_database(folder, n_database=args.database, n_queries=args.queries, dim=args.dim)
        print(f"wrote {folder}: manifest, {args.database + args.queries:,} image links, float16 descriptors "
              f"({npy.stat().st_size / 2**30:.2f} GiB) in {time.perf_counter() - start:.0f} s")
    print(f"{args.database:,} database + {args.queries:,} query images, D = {args.dim}, float16 descriptor file "
          f"{npy.stat().st_size / 2**30:.2f} GiB; load average {load_average()}; BLAS: {blas_kernel()}; "
          f"fits' products: {'numpy' if args.device is None else 'torch on ' + args.device}")
    rows: list[tuple[str, float, float]] = []

    def report(label: str, seconds: float, floor: float | None, note: str = "") -> None:
        rss = peak_rss_gib()
        rows.append((label, seconds, rss))
        ratio = f"{seconds / floor:8.3f}x" if floor else " " * 9
        print(f"  {label:<52} {seconds:8.2f} s {ratio}   peak RSS {rss:5.2f} GiB  {note}", flush=True)

    # first load: what the Dataset page does
    start = time.perf_counter()
    dataset = open_dataset(manifest)
    opened = time.perf_counter() - start
    imp = imported_descriptors(dataset, npy, mmap=True)  # the app maps it by itself from 1 GiB (mmap='auto')
    prepare_float16_reads()  # as the app does when it loads a float16 map: torch's cast imported meanwhile
    load = time.perf_counter() - start
    d = imp.descriptors
    assert isinstance(d, np.memmap) and d.dtype == np.float16, (type(d), d.dtype)
    print(f"{dataset.describe()}")

    print(f"first load (manifest + descriptor file, mapped): {load:.2f} s (manifest {opened:.1f} s, descriptor file "
          f"{load - opened:.1f} s); peak RSS {peak_rss_gib():.2f} GiB")
    # the floor, side by side: one blocked pass over every query x database score
    _, _, floor = blocked_pass(d, dataset.n_database, dataset.n_queries)
    per_query = floor / dataset.n_queries
    print(f"floor: one blocked pass over {dataset.n_queries:,} x {dataset.n_database:,} scores: {floor:.2f} s "
          f"({2 * dataset.n_queries * dataset.n_database * args.dim / floor / 1e9:.0f} GFLOP/s), "
          f"{per_query * 1000:.1f} ms a query (one row of scores); peak RSS {peak_rss_gib():.2f} GiB")
    print(f"  {'step':<52} {'time':>10} {'/ floor':>9}   memory")
    report("first load (manifest + descriptor file, mapped)", load, floor)

    rate = 2 * dataset.n_queries * dataset.n_database * args.dim / floor  # the floor's GEMM rate, flop/s

    def fit_floor(n_images: int) -> str:
        """The least a fit can take here: its Gram and quadratic forms, 2·N·D² flops at the floor's GEMM rate."""
        return f"GEMM floor {2 * n_images * args.dim ** 2 / rate:.2f} s"

    places_a = rv.RetrievalPlaces(PlaceGeometry.ROUTE, metric=MetricPlaceSpec(args.group, args.step))
    places_b = rv.RetrievalPlaces(PlaceGeometry.ROUTE, metric=MetricPlaceSpec(args.group, args.step2))
    start = time.perf_counter()
    fa = rv.fit_retrieval(d, dataset, places_a, device=args.device)
    report(f"fit {args.group:g} m / {args.step:g} m ({len(fa.model.images):,} images in places)",
           time.perf_counter() - start, floor, f"{fa.n_places:,} places; {fit_floor(len(fa.model.images))}")
    start = time.perf_counter()
    fb = rv.fit_retrieval(d, dataset, places_b, device=args.device)
    report(f"group/step change to {args.group:g} m / {args.step2:g} m ({len(fb.model.images):,} images)",
           time.perf_counter() - start, floor, f"{fb.n_places:,} places; {fit_floor(len(fb.model.images))}")
    change_floor = 2 * len(fb.model.images) * args.dim ** 2 / rate
    start = time.perf_counter()
    rv.fit_retrieval(d, dataset, places_a, device=args.device)
    report("back to the first group/step (kept fit)", time.perf_counter() - start, floor)
    start = time.perf_counter()
    ov = rv.overview(fa, d)
    report(f"Places overview ({len(ov.queries):,} sampled queries decided)", time.perf_counter() - start, floor)
    place = int(np.median(fa.model.places))
    start = time.perf_counter()
    detail = rv.place_detail(fa, d, place)
    report(f"one place ({len(detail.images)} images x {len(fa.model.images):,})", time.perf_counter() - start,
           floor, f"{per_query * len(detail.images) * len(fa.model.images) / dataset.n_database:.2f} s of floor rows")
    q = int(np.flatnonzero(dataset.ground_truth.counts > 0)[0])
    start = time.perf_counter()
    rv.explain_query(fa, d, q)
    rv.image_answer(dataset, d, q)
    report("one query (its places, and its top image over all)", time.perf_counter() - start, floor,
           f"{2 * per_query:.2f} s of floor rows")
    start = time.perf_counter()
    found, last = rv.find_query(fa, d, after=q, kind="rejected", method="global-auto")
    report(f"next rejected query (automatic global θ): {found}", time.perf_counter() - start, floor,
           f"{(last - q) % dataset.n_queries} queries searched")
    if not args.skip_eval:
        start = time.perf_counter()
        ev = evaluate_retrieval(dataset, d, metric=places_a.metric)
        report(f"evaluation of {dataset.n_queries:,} queries (database/queries protocol)",
               time.perf_counter() - start, floor)
        for r in ev.rows:
            print(f"      {r.label:<22} R@1 {100 * r.recall[1][0]:5.1f}  accepted {100 * r.accepted[0]:5.1f}")

    if args.faiss:
        k = 10
        _, (np_s, np_i), numpy_s = blocked_pass(d, dataset.n_database, dataset.n_queries, top_k=k)
        try:
            f_s, f_i, built, faiss_s = faiss_search(d, dataset.n_database, dataset.n_queries, k)
        except ImportError:
            print("faiss: not installed (pip install faiss-cpu)")
        else:
            from vpr_explorer.method.retrieval import TIE_TOLERANCE

            same_top = np.mean(np.abs(f_s[:, 0] - np_s[:, 0]) <= TIE_TOLERANCE)
            print(f"top-{k} of every query: numpy blocked pass {numpy_s:.2f} s, faiss.IndexFlatIP {faiss_s:.2f} s "
                  f"(of which building the float32 index {built:.2f} s, "
                  f"{d.shape[1] * dataset.n_database * 4 / 2**30:.2f} GiB in memory); faiss / numpy = {faiss_s / numpy_s:.2f}x; top-1 score equal within "
                  f"TIE_TOLERANCE for {100 * same_top:.2f}% of queries, max |Δ| over the top {k} "
                  f"{np.abs(f_s - np_s).max():.1e}; peak RSS {peak_rss_gib():.2f} GiB")

    if args.app:
        app_pages(manifest, npy, dataset, args, floor, report)

    worst = max((s for label, s, _ in rows if not label.startswith("first load") and not label.startswith("evaluation")
                 and not label.startswith("app: Dataset") and not label.startswith("app: Evaluation")), default=0.0)
    print(f"summary: peak RSS {peak_rss_gib():.2f} GiB (goal < {MEMORY_GOAL_GIB:g}); slowest page step "
          f"{worst:.2f} s (goal < {PAGE_GOAL_S:g} s except the first load and the protocol over every query)")
    print(f"a group/step change refits: its Gram and quadratic forms are at least 2·N·D² = "
          f"{2 * len(fb.model.images) * args.dim ** 2 / 1e9:,.0f} GFLOP at {len(fb.model.images):,} images in places, "
          f"{change_floor:.2f} s at this run's GEMM rate ({rate / 1e9:.0f} GFLOP/s): "
          + (f"no refit can take under {PAGE_GOAL_S:g} s here" if change_floor >= PAGE_GOAL_S else
             f"{change_floor / PAGE_GOAL_S:.0%} of the {PAGE_GOAL_S:g} s goal"))


def app_pages(manifest: Path, npy: Path, dataset, args, floor: float, report) -> None:
    """The app's pages on the same files, under AppTest (in process, server side)."""
    import streamlit as st
    from streamlit.testing.v1 import AppTest

    from vpr_explorer.app import DATA_ROOT_ENV, ENTRY, PAGES
    from vpr_explorer.descriptors.store import MMAP_ENV

    os.environ[MMAP_ENV] = "0"  # the same memory-mapped path at any size (by itself the app maps from 1 GiB)
    os.environ[DATA_ROOT_ENV] = str(manifest.parent.resolve())  # the app opens only what lies under its data root
    st.cache_data.clear()
    st.cache_resource.clear()
    at = AppTest.from_file(str(ENTRY), default_timeout=1800)
    at.query_params.update(source=str(manifest), descriptors=str(npy), geometry="route",
                           group_m=str(args.group), step_m=str(args.step))

    def timed(label: str, action) -> AppTest:
        start = time.perf_counter()
        result = action()
        seconds = time.perf_counter() - start
        assert not result.exception, [e.value for e in result.exception]
        errors = [e.value for e in result.error]
        assert not errors, errors
        report(f"app: {label}", seconds, floor)
        return result

    at = timed("Dataset page, first open", at.run)
    assert not any("data root" in w.value for w in at.warning), [w.value for w in at.warning]
    at = timed("Dataset page, again", at.run)

    def page(name: str):
        return lambda: at.switch_page(str(PAGES / f"{name}.py")).run()

    at = timed("Places (fit, sampled overview, map)", page("places"))
    at = timed("Thresholds: one place", page("thresholds"))
    at = timed("Thresholds: another place", lambda: at.selectbox(key="w_place").set_value(7).run())
    at = timed("Places: again (kept fit)", page("places"))
    at = timed(f"Places: step {args.step:g} -> {args.step2:g} m",
               lambda: at.number_input(key="w_step_m").set_value(args.step2).run())
    at = timed(f"Places: back to {args.step:g} m (kept)",
               lambda: at.number_input(key="w_step_m").set_value(args.step).run())
    at = timed("Inspector: one query", page("inspector"))
    at = timed("Inspector: another query", lambda: at.number_input(key="w_frame_number").set_value(
        dataset.n_queries // 2).run())
    at = timed("Inspector: next rejected", lambda: at.button(key="w_find_next").click().run())  # the paper's method
    at = timed("Evaluation: page (Run above the pair budget)", page("evaluation"))
    if not args.skip_eval:
        at = timed(f"Evaluation: Run ({dataset.n_queries:,} queries)", lambda: at.button(key="w_run").click().run())


if __name__ == "__main__":
    main()
