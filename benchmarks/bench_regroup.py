"""A group/step slider move on GardensPoint: the recomputation it triggers beside the extraction it avoids.

Descriptors belong to images, so moving the Places page's group or step slider only
relabels images and refits the closed-form negative statistics. This times exactly what
the app runs on such a move, ``views.regroup`` (places, database thresholds from
day_left + day_right, every night_right frame decided under every method), for a few
group/step settings, one run each and not served from any cache; and, once, the
descriptor extraction a naive app would redo on every move (a fresh temporary cache,
so every image is decoded and run through the model).

Against the machine's limit (issue 13): each move's achieved rate, counting only the flops
it needs (the database fit, ``gemm_peak.fit_flops``, and the decided frames' similarities,
2·F·N·D), as a share of numpy's float32 GEMM rate measured in the same run on the
database's shape (``gemm_peak``, which names the BLAS kernel). Run::

    python benchmarks/bench_regroup.py --data /work/shared/datasets
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
from vpr_explorer.data.traversals import load_dataset
from vpr_explorer.pipeline import dataset_descriptors
from vpr_explorer.method.places import PlaceSpec
from vpr_explorer.views.traversal import regroup

MOVES = ((3, 10), (4, 10), (4, 8), (2, 5), (5, 20), (3, 3))


def move_flops(r, dim: int) -> float:
    """Flops a move needs: the database fit and the decided frames' similarities."""
    return fit_flops(len(r.model.images), dim) + decision_flops(len(r.frames), len(r.model.images), dim)


def time_regroup(descriptors: np.ndarray, dataset, spec: PlaceSpec) -> tuple[float, str, float]:
    """Seconds of one ``regroup`` (what a slider move recomputes), what it produced, and its flops."""
    start = time.perf_counter()
    r = regroup(descriptors, dataset, spec)
    seconds = time.perf_counter() - start
    return seconds, f"{r.places.n_places} places, place-level R@1 {r.recall1['place-baseline']:.0%}", \
        move_flops(r, descriptors.shape[1])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=settings.data_root(),
                        help=f"datasets folder (default ${settings.DATA_ENV})")
    parser.add_argument("--descriptor", default="efficientnet-lite0", help="descriptor (default efficientnet-lite0)")
    args = parser.parse_args(argv)
    if args.data is None:
        parser.error(f"give --data or set {settings.DATA_ENV}")
    dataset = load_dataset(args.data / "GardensPointWalking")
    print("$ python " + " ".join(shlex.quote(a) for a in [sys.argv[0], *(argv if argv is not None else sys.argv[1:])]))

    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        descriptors = dataset_descriptors(dataset, args.descriptor, cache_root=Path(tmp))
        extraction = time.perf_counter() - start
        start = time.perf_counter()
        dataset_descriptors(dataset, args.descriptor, cache_root=Path(tmp))
        cached = time.perf_counter() - start
    print(f"GardensPoint: {dataset.n_images} images, {args.descriptor} descriptors {descriptors.shape}; "
          f"database {' + '.join(dataset.traversals[:-1])}, queries {dataset.traversals[-1]}")
    print(f"extraction (fresh cache, the work a move would redo without per-image descriptors): {extraction:.2f} s")
    print(f"reading them back from the on-disk cache: {cached:.2f} s")
    warm = regroup(descriptors, dataset, PlaceSpec(3, 10))  # warm-up: first-call imports and allocations are not a move
    peak = measure_peak(m=4096, k=descriptors.shape[1], n=max(256, min(len(warm.model.images), 4096)))
    for line in peak.lines():
        print(line)
    header = (f"{'group/step':<12}{'recompute ms':>14}{'extraction s':>14}{'extraction / recompute':>24}"
              f"{'% of peak':>11}  result")
    print(header)
    print("-" * len(header))
    for group, step in MOVES:
        seconds, what, flops = time_regroup(descriptors, dataset, PlaceSpec(group, step))
        print(f"{f'{group}/{step}':<12}{1000 * seconds:>14.1f}{extraction:>14.2f}{extraction / seconds:>23.0f}x"
              f"{100 * flops / seconds / 1e9 / peak.float32:>10.1f}%  {what}", flush=True)
    print("% of peak: the flops a move needs (database fit, 2·F·N·D for the decided frames) over its time, "
          "against the float32 GEMM peak above; moves this small are bookkeeping, not GEMM")


if __name__ == "__main__":
    main()
