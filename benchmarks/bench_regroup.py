"""A group/step slider move on GardensPoint: the recomputation it triggers beside the extraction it avoids.

Descriptors belong to images, so moving the Places page's group or step slider only
relabels images and refits the closed-form negative statistics. This times exactly what
the app runs on such a move, on the dataset value of the aligned traversals
(``data.aligned.database_queries``: database day_left + day_right, queries night_right):
``views.numbers.fit_retrieval`` (places over frames, database thresholds) and
``views.numbers.overview`` (every query decided under every method), for a few group/step
settings, one run each and not served from any cache; and, once, the descriptor extraction
a naive app would redo on every move (a fresh temporary cache, so every image is decoded
and run through the model).

Against the machine's limit: each move's achieved rate, counting only the flops it needs
(the database fit, ``gemm_peak.fit_flops``, and the decided queries' similarities,
2·F·N·D), as a share of numpy's float32 GEMM rate measured in the same run on the
database's shape (``gemm_peak``, which names the BLAS kernel). Run::

    python benchmarks/bench_regroup.py --data /work/shared/datasets [--descriptor pixels]
"""

from __future__ import annotations

import argparse
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from gemm_peak import decision_flops, fit_flops, measure_peak
from vpr_explorer import settings
from vpr_explorer.data.aligned import database_queries, value_rows
from vpr_explorer.data.traversals import load_dataset
from vpr_explorer.method.places import PlaceGeometry, PlaceSpec
from vpr_explorer.pipeline import dataset_descriptors
from vpr_explorer.views.numbers import RetrievalPlaces, fit_retrieval, overview

MOVES = ((3, 10), (4, 10), (4, 8), (2, 5), (5, 20), (3, 3))


def move(descriptors: np.ndarray, value, spec: PlaceSpec):
    """One slider move: the fit of ``spec``'s places and the overview of the queries."""
    fitted = fit_retrieval(descriptors, value, RetrievalPlaces(PlaceGeometry.FRAMES, spec=spec))
    return fitted, overview(fitted, descriptors)


def time_move(descriptors: np.ndarray, value, spec: PlaceSpec) -> tuple[float, str, float]:
    """Seconds of one move, what it produced, and the flops it needs (the fit and the decided queries' scores)."""
    start = time.perf_counter()
    fitted, ov = move(descriptors, value, spec)
    seconds = time.perf_counter() - start
    n_db, dim = len(fitted.model.images), descriptors.shape[1]
    flops = fit_flops(n_db, dim) + decision_flops(len(ov.queries), n_db, dim)
    return seconds, f"{fitted.n_places} places, place-level R@1 {ov.recall1['place-baseline']:.0%}", flops


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=settings.data_root(),
                        help=f"datasets folder (default ${settings.DATA_ENV})")
    parser.add_argument("--descriptor", default="efficientnet-lite0", help="descriptor (default efficientnet-lite0)")
    args = parser.parse_args(argv)
    if args.data is None:
        parser.error(f"give --data or set {settings.DATA_ENV}")
    dataset = load_dataset(args.data / "GardensPointWalking")
    value = database_queries(dataset)
    print("$ python " + " ".join(shlex.quote(a) for a in [sys.argv[0], *(argv if argv is not None else sys.argv[1:])]))

    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        descriptors = dataset_descriptors(dataset, args.descriptor, cache_root=Path(tmp))
        extraction = time.perf_counter() - start
        start = time.perf_counter()
        dataset_descriptors(dataset, args.descriptor, cache_root=Path(tmp))
        cached = time.perf_counter() - start
    rows = value_rows(value)
    d = descriptors if rows is None else descriptors[rows]
    print(f"GardensPoint: {dataset.n_images} images, {args.descriptor} descriptors {descriptors.shape}; "
          f"database {' + '.join(dataset.traversals[:-1])} ({value.n_database} images), "
          f"queries {dataset.traversals[-1]} ({value.n_queries})")
    print(f"extraction (fresh cache, the work a move would redo without per-image descriptors): {extraction:.2f} s")
    print(f"reading them back from the on-disk cache: {cached:.2f} s")
    warm, _ = move(d, value, PlaceSpec(3, 10))  # warm-up: first-call imports and allocations are not a move
    peak = measure_peak(m=4096, k=d.shape[1], n=max(256, min(len(warm.model.images), 4096)))
    for line in peak.lines():
        print(line)
    header = (f"{'group/step':<12}{'recompute ms':>14}{'extraction s':>14}{'extraction / recompute':>24}"
              f"{'% of peak':>11}  result")
    print(header)
    print("-" * len(header))
    for group, step in MOVES:
        seconds, what, flops = time_move(d, value, PlaceSpec(group, step))
        print(f"{f'{group}/{step}':<12}{1000 * seconds:>14.1f}{extraction:>14.2f}{extraction / seconds:>23.0f}x"
              f"{100 * flops / seconds / 1e9 / peak.float32:>10.1f}%  {what}", flush=True)
    print("% of peak: the flops a move needs (database fit, 2·F·N·D for the decided queries) over its time, "
          "against the float32 GEMM peak above; moves this small are bookkeeping, not GEMM")


if __name__ == "__main__":
    main()
