"""Playback cost: logging a query traversal to rerun beside the decisions themselves, and its memory.

Each dataset is the value of two aligned traversals (``data.aligned.database_queries``),
fitted with ``views.numbers.fit_retrieval`` (places over frames); its queries are decided
by ``recording.decide_every_query`` and logged by ``recording.log_queries``.

* **GardensPoint**: night_right against day_right, all 200 query frames with their images
  at original size (960×540 JPEG): the time of ``decide_every_query`` (the decisions)
  beside the time of ``log_queries`` (writing them, and 600 images, to an ``.rrd``).
* **Nordland_64x32**: winter against summer, 3,576 query frames. Images are read from
  disk one query at a time; the resident memory added while logging is sampled and
  printed beside the bytes of all images logged. As a control, the same logging into an
  in-memory sink (which keeps everything) shows what holding every image costs.

Against the machine's limit: the decisions' achieved rate, counting only the
similarities they need (2·F·N·D flops for F query frames against N database images), as a
share of numpy's float32 GEMM rate on a comparable shape measured in the same run
(``gemm_peak``, which names the BLAS kernel). Run::

    python benchmarks/bench_recording.py --data /work/shared/datasets
"""

from __future__ import annotations

import argparse
import tempfile
import threading
import time
import tracemalloc
from pathlib import Path

import numpy as np

from gemm_peak import decision_flops, measure_peak, share
from vpr_explorer import settings
from vpr_explorer.data.aligned import database_queries, value_rows
from vpr_explorer.data.traversals import load_dataset
from vpr_explorer.method.places import PlaceGeometry, PlaceSpec
from vpr_explorer.pipeline import dataset_descriptors
from vpr_explorer.recording import RECORDED, decide_every_query, log_queries, new_recording
from vpr_explorer.views.numbers import RetrievalPlaces, fit_retrieval

MB = 1024 * 1024


def rss() -> int:
    """Resident set size of this process now, in bytes (Linux)."""
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * 4096


class FrameLoopMemory:
    """Memory added while ``log_queries`` streams the images, query by query.

    Use as its ``progress`` callback: at the first query it notes the resident set size and
    resets tracemalloc's peak; a thread samples the resident size every 5 ms until ``stop``.
    Everything logged before the query loop (the series, as columns) is excluded.
    """

    def __init__(self) -> None:
        self.start = self.peak = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()

    def _sample(self) -> None:
        while not self._stop.wait(0.005):
            if self.start:
                self.peak = max(self.peak, rss())

    def __call__(self, done: int, total: int) -> None:
        if done == 1:
            if tracemalloc.is_tracing():
                tracemalloc.reset_peak()
            self.start = self.peak = rss()

    def stop(self) -> tuple[int, int]:
        """(resident growth, Python heap peak) in bytes over the query loop."""
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, rss())
        heap = tracemalloc.get_traced_memory()[1] if tracemalloc.is_tracing() else 0
        return self.peak - self.start, heap


def setup(root: Path, descriptor: str, spec: PlaceSpec, database: str, query: str):
    """The value of traversals ``query`` against ``database``, its descriptors in its order, and its fit."""
    dataset = load_dataset(root, [database, query])
    desc = dataset_descriptors(dataset, descriptor)
    value = database_queries(dataset, query, [database])
    rows = value_rows(value)
    d = desc if rows is None else desc[rows]
    return d, fit_retrieval(d, value, RetrievalPlaces(PlaceGeometry.FRAMES, spec=spec))


def timed(fn, repeat: int) -> tuple[float, object]:
    """Best of ``repeat`` wall-clock seconds, and the last result."""
    best, out = float("inf"), None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def logged_image_bytes(decisions) -> tuple[int, int]:
    """(files, bytes) of the images one recording logs: each query and each method's answer image."""
    value, model = decisions.fitted.dataset, decisions.fitted.model
    files = [Path(p) for p in value.query_paths]
    for key in RECORDED:
        a = decisions.outcomes[key].answer_image
        files += [Path(value.database_paths[model.images[i]]) for i in a[a >= 0]]
    return len(files), sum(p.stat().st_size for p in files)


def record_to_file(path: Path, decisions, progress=None) -> None:
    rec = new_recording()
    rec.save(path)
    log_queries(rec, decisions, progress=progress)
    rec.flush()
    rec.disconnect()


def bench_gardens_point(data: Path, descriptor: str, repeat: int) -> None:
    desc, fitted = setup(data / "GardensPointWalking", descriptor, PlaceSpec(3, 10), "day_right", "night_right")
    t_decide, decisions = timed(lambda: decide_every_query(fitted, desc), repeat)
    n_files, n_bytes = logged_image_bytes(decisions)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "gp.rrd"
        t_log, _ = timed(lambda: record_to_file(out, decisions), repeat)
        size = out.stat().st_size
    n = decisions.n_queries
    print(f"GardensPoint: night_right against day_right, {descriptor}, {fitted.describe()}, {n} query frames")
    print(f"  decisions (decide_every_query)   {t_decide * 1e3:8.1f} ms")
    print(f"  recording (log_queries → .rrd)   {t_log * 1e3:8.1f} ms   {t_log / n * 1e3:.2f} ms/query; "
          f"{n_files} images at original size ({n_bytes / MB:.1f} MB of JPEG), .rrd {size / MB:.1f} MB")
    print(f"  recording / decisions            {t_log / t_decide:8.1f} x   (best of {repeat})")
    print_share(t_decide, n, len(fitted.model.images), desc.shape[1])


def print_share(seconds: float, n_frames: int, n_database: int, dim: int) -> None:
    """The decisions' rate, by the similarities they need, against the float32 GEMM peak now."""
    peak = measure_peak(m=4096, k=dim, n=min(max(n_database, 256), 4096))
    print(f"  decisions, 2·F·N·D flops / time  {share(decision_flops(n_frames, n_database, dim), seconds, peak.float32)} "
          f"(float32 GEMM {peak.float32:.0f} GFLOP/s on ({peak.shape[0]}×{dim}) @ ({dim}×{peak.shape[2]}))")


def bench_nordland(data: Path, descriptor: str, spec: PlaceSpec) -> None:
    desc, fitted = setup(data / "Nordland_64x32", descriptor, spec, "summer", "winter")
    t = time.perf_counter()
    decisions = decide_every_query(fitted, desc)
    t_decide = time.perf_counter() - t
    n_files, n_bytes = logged_image_bytes(decisions)
    n = decisions.n_queries
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "nordland.rrd"
        tracemalloc.start()
        watch = FrameLoopMemory()
        t = time.perf_counter()
        record_to_file(out, decisions, progress=watch)
        t_log = time.perf_counter() - t
        file_growth, heap_peak = watch.stop()
        tracemalloc.stop()
        size = out.stat().st_size
    watch = FrameLoopMemory()
    rec = new_recording()
    held = rec.memory_recording()
    log_queries(rec, decisions, progress=watch)
    rec.flush()
    memory_growth, _ = watch.stop()
    memory_size = len(held.drain_as_bytes())
    del held, rec
    print(f"Nordland_64x32: winter against summer, {descriptor}, {fitted.describe()}, {n} query frames")
    print(f"  decisions (decide_every_query)   {t_decide * 1e3:8.1f} ms")
    print_share(t_decide, n, len(fitted.model.images), desc.shape[1])
    print(f"  recording (log_queries → .rrd)   {t_log * 1e3:8.1f} ms   {t_log / n * 1e3:.2f} ms/query; "
          f".rrd {size / MB:.1f} MB")
    print(f"  images logged                    {n_files} files, {n_bytes / MB:.1f} MB on disk")
    print(f"  while streaming the images       Python heap peak {heap_peak / MB:.2f} MB (tracemalloc), "
          f"resident +{file_growth / MB:.1f} MB (file sink)")
    print(f"  control: in-memory sink          resident +{memory_growth / MB:.1f} MB, holding "
          f"{memory_size / MB:.1f} MB of recording at the end")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=settings.data_root(),
                        help=f"datasets folder (default ${settings.DATA_ENV})")
    parser.add_argument("--descriptor", default="pixels", help="descriptor name (default pixels)")
    parser.add_argument("--repeat", type=int, default=3, help="GardensPoint: best of this many runs")
    parser.add_argument("--skip-nordland", action="store_true")
    # Group 2, step 4: the figures the documentation quotes. Above 2,000 database images the automatic
    # θ scores a tile sample (``thresholds.training_pair_scores``), which reads each image about once.
    parser.add_argument("--nordland-group", type=int, default=2)
    parser.add_argument("--nordland-step", type=int, default=4)
    args = parser.parse_args(argv)
    if args.data is None:
        parser.error(f"give --data or set {settings.DATA_ENV}")
    np.set_printoptions(precision=3)
    from gemm_peak import blas_kernel

    print(f"BLAS: {blas_kernel()}")
    bench_gardens_point(args.data, args.descriptor, args.repeat)
    if not args.skip_nordland:
        bench_nordland(args.data, args.descriptor, PlaceSpec(args.nordland_group, args.nordland_step))


if __name__ == "__main__":
    main()
