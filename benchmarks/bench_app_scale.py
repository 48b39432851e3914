"""The app on a 110k-image dataset: every page's run time beside the all-pairs work it avoids.

    python benchmarks/bench_app_scale.py                         # 4 traversals x 27,591 frames = 110,364 images
    python benchmarks/bench_app_scale.py --frames 3000           # a quicker look

Writes a synthetic route of real PNG files (Nordland Mini's shape: 27,591 frames, 4
traversals, 64x32 greyscale; a smooth procedural panorama the camera moves along, each
traversal with its own lighting, noise and jitter) into ``--out`` (kept, so a second run
reuses it), extracts the ``pixels`` descriptors through the real pipeline and cache, then
drives the real app with Streamlit's AppTest (its entry script ``vpr_explorer.app.ENTRY``
and its pages, in process; the data root is ``--out``) and times each page's script run and
the main interactions: the Places page (overview: a sample of query frames decided),
Thresholds (one place), Query inspector (one query, the "next rejected" search), Evaluation
(the similarity matrix from sampled rows; the protocol runs on arrival only under
``numbers.AUTO_RUN_PAIRS`` image pairs, so at full size it waits for Run), a group/step
move.

The pages read the traversals as one dataset value (``data.aligned.database_queries``: the
query traversal's frames against the other three traversals, as the app builds it). Side by
side, in the same run: deciding every query frame against the database
(``views.numbers.decide_queries`` on all 27,591 queries, what a page that ignored the budget
would compute), and the ratio of each page to it.

Against the machine's limit: before the pages, a group/step move at group 4, step 10 (the
Places page's slider move: ``views.numbers.fit_retrieval`` then ``views.numbers.overview``)
is timed outside the app, split into its fit (closed-form statistics, automatic θ, positive
means) and its decisions (the overview's sampled queries), beside its floor: the flops it
needs (``gemm_peak.fit_flops`` + 2·F·N·D) at numpy's float32 GEMM peak measured in the same
run (``gemm_peak``, which names the BLAS kernel), its CPU seconds against the peak per CPU
second (steadier on a shared machine), and the same queries decided again by
``decide_queries`` (scores by place pieces) and by the straightforward path (query ×
database scores, ``retrieval.place_scores``, ``retrieval.score_queries``), alternating, best
of two each, with their decisions compared. ``--move-only`` stops there. AppTest runs the
scripts, not a browser; ``--browser`` then also starts a real ``streamlit run`` server and
walks the same pages in Debian's Chromium (Playwright), timing each from the click to the
last Plotly chart drawn, and saves a screenshot of each page next to the route.
"""

from __future__ import annotations

import argparse
import os
import resource
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.ndimage import gaussian_filter

ROOT = Path(__file__).resolve().parents[1]
TRAVERSALS = ("spring", "summer", "fall", "winter")
WIDTH, HEIGHT, ADVANCE = 64, 32, 6  # image size; pixels the camera moves per frame


def write_route(out: Path, frames: int, seed: int = 0) -> float:
    """Write ``len(TRAVERSALS)`` folders of ``frames`` PNGs (skipped when complete); returns seconds spent."""
    marker = out / f".complete-{frames}-{seed}"
    if marker.exists():
        return 0.0
    start = time.perf_counter()
    rng = np.random.default_rng(seed)
    width = frames * ADVANCE + WIDTH + 4
    # A panorama of blobs at two scales: frames a place apart overlap, distant ones do not.
    pano = gaussian_filter(rng.standard_normal((HEIGHT, width)), (3, 5)) * 3
    pano += gaussian_filter(rng.standard_normal((HEIGHT, width)), (1.5, 2))
    pano = (pano - pano.mean()) / pano.std()
    looks = [(128, 40, 0.15), (140, 45, 0.2), (110, 35, 0.3), (170, 25, 0.35)]  # base, contrast, noise per traversal
    for t, name in enumerate(TRAVERSALS):
        folder = out / name
        folder.mkdir(parents=True, exist_ok=True)
        base, contrast, noise = looks[t]
        for f in range(frames):
            x0 = f * ADVANCE + 2 + int(rng.integers(-2, 3))
            crop = pano[:, x0:x0 + WIDTH] + noise * rng.standard_normal((HEIGHT, WIDTH))
            pixels = np.clip(base + contrast * crop, 0, 255).astype(np.uint8)
            Image.fromarray(pixels, mode="L").save(folder / f"frame_{f:06d}.png", compress_level=1)
    marker.touch()
    return time.perf_counter() - start


def peak_rss_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=27_591, help="frames per traversal (default 27,591)")
    parser.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "vpr_app_scale",
                        help="where the route is written (default: a folder in the temp dir, reused)")
    parser.add_argument("--cache", type=Path, default=None,
                        help="descriptor cache (default: <out>-cache, kept so a second run skips extraction)")
    parser.add_argument("--browser", action="store_true",
                        help="also time the pages in Chromium against a real streamlit server")
    parser.add_argument("--move-only", action="store_true",
                        help="time the group/step move against its floor, then stop (no pages)")
    args = parser.parse_args(argv)
    print("$ python " + " ".join(shlex.quote(a) for a in [sys.argv[0], *(argv if argv is not None else sys.argv[1:])]))
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    route = args.out / f"route{args.frames}"
    written = write_route(route, args.frames)
    os.environ["VPR_EXPLORER_CACHE"] = str(args.cache or Path(f"{args.out}-cache"))
    os.environ["VPR_EXPLORER_DATA_ROOT"] = str(args.out.resolve())  # the app opens only what lies under its data root

    # Imported after the cache is set, as the app would be started with it.
    import streamlit as st
    from streamlit.testing.v1 import AppTest

    from vpr_explorer.app import ENTRY, PAGES
    from vpr_explorer.app.ui.current import effective_places
    from vpr_explorer.app.ui.state import View
    from vpr_explorer.data.aligned import database_queries, value_rows
    from vpr_explorer.pipeline import dataset_descriptors, resolve_dataset
    from vpr_explorer.views.numbers import decide_queries, fit_retrieval

    sys.path.insert(0, str(ROOT / "benchmarks"))
    dataset = resolve_dataset(route)
    print(f"route: {dataset.n_traversals} traversals x {dataset.n_frames:,} frames = {dataset.n_images:,} PNG files"
          + (f", written in {written:.0f} s" if written else " (already written)"))
    start = time.perf_counter()
    descriptors = dataset_descriptors(dataset, "pixels")
    print(f"pixels descriptors {descriptors.shape} through the cache: {time.perf_counter() - start:.1f} s")
    # the value the app's pages read: the default query traversal against every other one
    value = database_queries(dataset, dataset.traversals[dataset.default_roles().query])
    rows = value_rows(value)
    d = descriptors if rows is None else descriptors[rows]
    print(f"value: {value.n_database:,} database images, {value.n_queries:,} queries")

    time_move(d, value)
    if args.move_only:
        return
    # What a page ignoring the budget would compute: every query against the database.
    f = fit_retrieval(d, value, effective_places(View(), value))
    start = time.perf_counter()
    everything = decide_queries(f, d, np.arange(value.n_queries))
    all_pairs = time.perf_counter() - start
    n_pairs = value.n_queries * len(f.model.images)
    print(f"all queries decided (decide_queries, {value.n_queries:,} x {len(f.model.images):,} = "
          f"{n_pairs:.2e} pairs): {all_pairs:.1f} s")
    del everything

    _route_all_pages_through_app()
    st.cache_data.clear()
    st.cache_resource.clear()
    at = AppTest.from_file(str(ENTRY), default_timeout=600)
    at.query_params.update({"source": str(route), "descriptor": "pixels"})
    rows: list[tuple[str, float]] = []

    def timed(label: str, action) -> AppTest:
        start = time.perf_counter()
        result = action()
        seconds = time.perf_counter() - start
        assert not result.exception, [e.value for e in result.exception]
        errors = [e.value for e in result.error]
        assert not errors, errors
        rows.append((label, seconds))
        print(f"  {label:<58} {seconds:7.2f} s   {seconds / all_pairs:6.3f}x", flush=True)
        return result

    def page(name: str):
        return lambda: at.switch_page(str(PAGES / f"{name}.py")).run()

    print(f"  {'page run (AppTest, server side)':<58} {'seconds':>9}   ratio to deciding all queries")
    at = timed("Dataset page, first open (descriptors from the disk cache)", at.run)
    assert not any("data root" in w.value for w in at.warning), [w.value for w in at.warning]
    at = timed("Dataset page, again", at.run)
    at = timed("Places: overview (sampled query frames)", page("places"))
    at = timed("Places: again (cached)", at.run)
    at = timed("Places: group 3 -> 4 (refit + new sample)", lambda: at.slider(key="w_group").set_value(4).run())
    at = timed("Places: back to group 3 (cached)", lambda: at.slider(key="w_group").set_value(3).run())
    at = timed("Thresholds: one place", page("thresholds"))
    places = at.selectbox(key="w_place")
    at = timed("Thresholds: another place", lambda: places.set_value(int(len(places.options) * 0.9)).run())
    at = timed("Inspector: one query", page("inspector"))
    at = timed("Inspector: another frame", lambda: at.slider(key="w_frame").set_value(value.n_queries // 2).run())
    at = timed("Inspector: next rejected (margin, weighted θ)", lambda: at.button(key="w_find_next").click().run())
    at = timed("Evaluation: page (protocol only under AUTO_RUN_PAIRS)", page("evaluation"))
    print(f"peak resident memory of this process: {peak_rss_gib():.2f} GiB")
    slowest = max(rows[2:], key=lambda r: r[1])
    print(f"slowest page run after the first load: {slowest[0]}, {slowest[1]:.2f} s = {slowest[1] / all_pairs:.3f}x "
          "deciding every query")
    if args.browser:
        browser_walk(route, args.out, all_pairs)


def time_move(descriptors, value, group: int = 4, step: int = 10) -> None:
    """One group/step move (``fit_retrieval`` then ``overview``), its fit and decisions, against the GEMM floor;
    then the same queries decided by ``decide_queries`` and by the straightforward path, side by side."""
    from gemm_peak import decision_flops, fit_flops, measure_peak, share

    from vpr_explorer.method.places import PlaceGeometry, PlaceSpec
    from vpr_explorer.views.numbers import RetrievalPlaces, decide_queries, fit_retrieval, overview

    def places(g: int, s: int) -> RetrievalPlaces:
        return RetrievalPlaces(PlaceGeometry.FRAMES, spec=PlaceSpec(g, s))

    dim = descriptors.shape[1]
    overview(fit_retrieval(descriptors, value, places(3, step)), descriptors)  # warm-up: imports, thread pools
    before = measure_peak(m=4096, k=dim, n=2048)
    start, cpu = time.perf_counter(), time.process_time()
    f = fit_retrieval(descriptors, value, places(group, step))
    t_fit = time.perf_counter() - start
    ov = overview(f, descriptors)
    t_move, cpu_move = time.perf_counter() - start, time.process_time() - cpu
    # Side by side, the same queries: the straightforward decisions, then decide_queries again,
    # alternating, best of each (the load on a shared machine changes).
    t_plain, t_pieces, differ = [], [], np.zeros(len(ov.queries), bool)
    for _ in range(2):
        for plain, times in ((True, t_plain), (False, t_pieces)):
            start = time.perf_counter()
            _, again = (decide_straightforward(f, descriptors, ov.queries) if plain
                        else decide_queries(f, descriptors, ov.queries))
            times.append(time.perf_counter() - start)
            differ |= _differences(again, ov.outcomes)
    n_db, n_q = len(f.model.images), len(ov.queries)
    peak = before.best(measure_peak(m=4096, k=dim, n=2048))  # best of before and after: the load changes
    for line in peak.lines():
        print(line)
    flops_fit, flops_dec = fit_flops(n_db, dim), decision_flops(n_q, n_db, dim)
    floor = (flops_fit + flops_dec) / peak.float32 / 1e9
    print(f"group/step move to {group}/{step} (fit_retrieval + overview: {n_db:,} database images x {dim}, {n_q:,} "
          f"of {value.n_queries:,} queries decided): {t_move:.2f} s = fit {t_fit:.2f} s + decisions "
          f"{t_move - t_fit:.2f} s")
    print(f"  fit:       {share(flops_fit, t_fit, peak.float32)}")
    print(f"  decisions: {share(flops_dec, t_move - t_fit, peak.float32)}")
    print(f"  decisions again, best of 2: decide_queries {min(t_pieces):.2f} s, straightforward (score_rows + "
          f"place_scores + score_queries) {min(t_plain):.2f} s = {min(t_plain) / min(t_pieces):.1f}x decide_queries; "
          "ranks, answers, images and kept counts " + ("identical" if not differ.any() else
          f"not identical: {int(differ.sum())} of {len(differ):,} queries differ in a rank, answer, image or kept "
          "count (a kernel that rounds by operand order; the tolerance rule allows it on queries with a score "
          "within 5e-7 of a boundary: tests/test_decide_fused.py)"))
    print(f"  the move in CPU seconds (all threads; steadier on a shared machine): {cpu_move:.2f} CPU s, "
          f"{share(flops_fit + flops_dec, cpu_move, peak.float32_cpu)} per CPU second")
    print(f"summary: move {t_move:.2f} s (goal <= 3 s), floor {floor:.2f} s at the float32 GEMM peak, "
          f"ratio {t_move / floor:.1f}x; {share(flops_fit + flops_dec, t_move, peak.float32)}; "
          f"with the straightforward decisions {t_fit + min(t_plain):.2f} s; load average {os.getloadavg()[0]:.1f}",
          flush=True)


OUTCOME_FIELDS = ("rank", "answer_place", "answer_image", "n_kept")


def decide_straightforward(fitted, descriptors, queries):
    """``decide_queries``' right places and outcomes the straightforward way, in its blocks of queries: the
    query × database scores (``numbers.score_rows``), their place maxima (``retrieval.place_scores``) and every
    method (``retrieval.score_queries``)."""
    from vpr_explorer.method.retrieval import Outcome, place_scores, score_queries
    from vpr_explorer.views.numbers import SCORE_ELEMS, score_rows

    model = fitted.model
    th = model.thresholds()
    truth = fitted.right_places(queries)
    block = max(1, min(2048, SCORE_ELEMS // max(1, len(model.images))))
    parts = []
    for lo in range(0, len(queries), block):
        sims = score_rows(descriptors, fitted.dataset.n_database + queries[lo:lo + block], model.images)
        raw_best = place_scores(sims, model.places, fitted.n_places)
        parts.append(score_queries(sims, model.places, fitted.n_places, th, truth[lo:lo + block], raw_best=raw_best))
    return truth, {key: Outcome(parts[0][key].method, *(np.concatenate([getattr(p[key], f) for p in parts])
                                                         for f in OUTCOME_FIELDS)) for key in parts[0]}


def _differences(a: dict, b: dict) -> np.ndarray:
    """The queries whose rank, answer, image or kept count differ between two outcome mappings, under any method."""
    differ = np.zeros(len(next(iter(a.values())).rank), bool)
    for key in a:
        for f in OUTCOME_FIELDS:
            differ |= getattr(a[key], f) != getattr(b[key], f)
    return differ


CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def browser_walk(route: Path, out: Path, all_pairs: float) -> None:
    """The pages in Chromium against ``streamlit run``: seconds from the click to the last chart drawn."""
    from urllib.parse import quote

    from playwright.sync_api import sync_playwright

    sys.path.insert(0, str(ROOT / "tests"))
    from streamlit_server import streamlit_server

    def settle(page) -> None:
        try:  # the rerun may not have started when the click returns
            page.wait_for_selector('[data-testid="stApp"][data-test-script-state="running"]', timeout=1500)
        except Exception:  # noqa: BLE001  (playwright's TimeoutError: the run was quicker than the poll)
            pass
        page.wait_for_selector('[data-testid="stApp"][data-test-script-state="notRunning"]', timeout=600_000)
        page.wait_for_function(
            """() => Array.from(document.querySelectorAll('[data-testid="stPlotlyChart"]'))
                      .every(c => c.querySelector('.main-svg'))
                  && document.querySelectorAll('[data-testid="stSkeleton"]').length === 0""",
            timeout=120_000,
        )
        if page.locator('[data-testid="stException"]').count():
            raise RuntimeError(page.locator('[data-testid="stException"]').first.inner_text()[:2000])

    print(f"  {'in Chromium (click to last chart drawn)':<58} {'seconds':>9}")
    with streamlit_server("app.py", cwd=ROOT, timeout=120) as url, sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1440, "height": 1000})

        def timed(label: str, action, shot: str | None = None) -> None:
            start = time.perf_counter()
            action()
            settle(page)
            seconds = time.perf_counter() - start
            print(f"  {label:<58} {seconds:7.2f} s   {seconds / all_pairs:6.3f}x", flush=True)
            if shot:
                page.screenshot(path=str(out / f"{shot}.png"), full_page=True)

        def nav(title: str):
            return lambda: page.locator('[data-testid="stSidebarNav"] a', has_text=title).first.click()

        timed("Dataset page, first open (server just started)",
              lambda: page.goto(f"{url}/?source={quote(str(route))}&descriptor=pixels"), "home")
        timed("Places (group/step)", nav("Places (group/step)"), "places")
        timed("Thresholds", nav("Thresholds"), "thresholds")
        timed("Query inspector", nav("Query inspector"), "inspector")
        timed("Evaluation", nav("Evaluation"), "evaluation")
        timed("Places again (cached)", nav("Places (group/step)"))
        browser.close()
    print(f"screenshots: {out}/{{home,places,thresholds,inspector,evaluation}}.png")


def _route_all_pages_through_app() -> None:
    """As tests/test_app.py: leave Streamlit's pages-folder mode, so that every run goes through ``app.py``."""
    from streamlit.runtime.pages_manager import PagesManager

    init = PagesManager.__init__

    def init_after_navigation(self, *a, **kw):
        init(self, *a, **kw)
        PagesManager.uses_pages_directory = False

    PagesManager.__init__ = init_after_navigation


if __name__ == "__main__":
    main()
