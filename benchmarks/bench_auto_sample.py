"""The automatic global θ's sample: dense tiles (one GEMM per tile) against independent pairs.

    python benchmarks/bench_auto_sample.py                  # the app's 110k route: 24,831 database images × 2,048
    python benchmarks/bench_auto_sample.py --n 100000 --dim 1280 --seeds 3   # a protocol split at Nordland scale
    python benchmarks/bench_auto_sample.py --n 110364 --dim 1280 --seeds 20 --pooled 50   # one sample per run
    python benchmarks/bench_auto_sample.py --n 500000 --dim 512 --mmap --seeds 20   # a million-image step change

Above ``thresholds.AUTO_MAX_PAIRS`` (2·10⁶) training pairs, ``training_pair_scores`` samples.
Side by side in one process, on seeded Nordland-like descriptors with place structure
(``bench_nordland_scale.nordland_like``):

1. time of one sample: ``sample="tiles"`` (the default: a seeded permutation cut into groups,
   every pair between neighbouring groups, each tile one float32 GEMM) against
   ``sample="pairs"`` (2·10⁶ independent pairs, each a gathered row pair),
   their ratio, and the tiles' GEMM rate as a share of numpy's float32 GEMM peak measured
   in the same run (``gemm_peak``; the step's flops: 2·D per pair);
2. the automatic θ over ``--seeds`` seeds of each sample: mean and standard deviation (its
   sampling error), and the difference of the means in units of its standard error. Pairs
   inside one tile share rows and columns, so they are correlated; the θ must still agree
   with the independent-pairs θ within that error.

Above ``thresholds.AUTO_TILE_IMAGES`` (131,072) training images the tiles are drawn over a
seeded subset of that many images: the run then also times and compares the tiles
over all ``--n`` images (``images=n``). ``--mmap`` reads the descriptors from a float16
memory map (a temporary file), as the app reads a million-image database, instead of memory.

``--pooled RUNS`` instead compares two ways of taking each split's θ in a protocol,
on the ``--n`` images as places of 12 and ``RUNS`` seeded splits (one query per place):
a tile sample of each split's own training images (``training_pair_scores(rows=train)``)
against one tile sample per run over all images, of which each split keeps its
training pairs (``thresholds.pooled_pair_sample``). It prints the time of all the
splits' θ each way (best of ``--seeds``), and split 0's θ over ``--seeds`` seeds of each:
mean, standard deviation, and the difference of the means in standard errors.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from bench_nordland_scale import FRAMES, TRAVERSALS, nordland_like
from gemm_peak import load_average, measure_peak, share
from vpr_explorer.protocols.evaluation import draw_splits
from vpr_explorer.method.thresholds import (
    AUTO_MAX_PAIRS,
    AUTO_TILE_IMAGES,
    auto_global_threshold,
    pooled_pair_sample,
    training_pair_scores,
)


def pooled_against_per_split(d: np.ndarray, labels: np.ndarray, runs: int, seeds: int) -> None:
    """Each split's automatic θ from its own tile sample, and from the run's pooled one: time and θ."""
    trains = [sp.train for sp in draw_splits(labels, int(labels.max()) + 1, runs=runs, seed=0)]
    print(f"{runs} splits of {len(trains[0]):,} training images each; {len(d):,} images in the pooled tiles")
    peak = measure_peak(m=4096, k=d.shape[1], n=256)
    theta: dict[str, list[float]] = {"per split": [], "pooled": []}
    seconds: dict[str, list[float]] = {"per split": [], "pooled": []}
    size = 0
    for seed in range(seeds):  # interleaved: both see the same load
        t0 = time.perf_counter()
        per = [auto_global_threshold(training_pair_scores(d, rows=t, seed=seed + r)) for r, t in enumerate(trains)]
        seconds["per split"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        sample = pooled_pair_sample(d, trains, seed=seed)
        pooled = [sample.theta(r) for r in range(runs)]
        seconds["pooled"].append(time.perf_counter() - t0)
        theta["per split"].append(per[0])
        theta["pooled"].append(pooled[0])
        size = sample.pooled.size
    peak = peak.best(measure_peak(m=4096, k=d.shape[1], n=256))
    for line in peak.lines():
        print(line)
    t_old, t_new = min(seconds["per split"]), min(seconds["pooled"])
    print(f"all {runs} splits' θ, best of {seeds}:  per split {t_old:6.2f} s   pooled {t_new:6.2f} s "
          f"({size:,} pooled scores, {len(sample.scores(0)):,} kept by split 0)   per split / pooled = "
          f"{t_old / t_new:.1f}×")
    m = {k: float(np.mean(v)) for k, v in theta.items()}
    s = {k: float(np.std(v, ddof=1)) if len(v) > 1 else float("nan") for k, v in theta.items()}
    for kind in theta:
        print(f"split 0's θ_auto, {kind:<9}: mean {m[kind]:.6f}  sd over {seeds} seeds {s[kind]:.2e}")
    se = np.sqrt((s["pooled"] ** 2 + s["per split"] ** 2) / seeds)
    print(f"summary: pooled {t_old / t_new:.1f}× faster than per split; θ means differ by "
          f"{m['pooled'] - m['per split']:+.2e} = {abs(m['pooled'] - m['per split']) / se:.1f} standard errors "
          f"(sd pooled / sd per split = {s['pooled'] / s['per split']:.2f})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=24_831, help="training images (default 24,831: the app's 110k route)")
    ap.add_argument("--dim", type=int, default=2048)
    ap.add_argument("--seeds", type=int, default=5, help="samples of each kind for the θ spread (default 5)")
    ap.add_argument("--pooled", type=int, default=0, metavar="RUNS",
                    help="compare per-split tile samples with one pooled sample over RUNS splits instead")
    ap.add_argument("--mmap", action="store_true", help="read the descriptors from a float16 memory map")
    args = ap.parse_args()
    places = -(-args.n // (FRAMES * TRAVERSALS))
    if args.pooled:
        places = args.n // (FRAMES * TRAVERSALS)
        d, labels, _ = nordland_like(places, args.dim, 0)
        print(f"data: {len(d):,} × {args.dim} Nordland-like descriptors in {places:,} places of "
              f"{FRAMES * TRAVERSALS}; load average {load_average()}")
        pooled_against_per_split(d, labels, args.pooled, args.seeds)
        return
    d = nordland_like(places, args.dim, 0)[0][: args.n]
    with tempfile.TemporaryDirectory() as folder:
        if args.mmap:
            np.save(Path(folder) / "d.npy", d.astype(np.float16))
            d = np.load(Path(folder) / "d.npy", mmap_mode="r")
        tiles_against_pairs(d, args)


def tiles_against_pairs(d: np.ndarray, args: argparse.Namespace) -> None:
    """One sample of each kind, its time and the θ over ``args.seeds`` seeds."""
    n = len(d)
    print(f"data: {n:,} × {args.dim} Nordland-like descriptors{' (float16 memory map)' if args.mmap else ''}; "
          f"{n * (n - 1) // 2:.2e} pairs, sample of {AUTO_MAX_PAIRS:.0e}; load average {load_average()}")
    peak = measure_peak(m=4096, k=args.dim, n=256)  # a tall GEMM of the tiles' depth

    kinds = {"tiles": {"sample": "tiles"}, "pairs": {"sample": "pairs"}}
    if n > AUTO_TILE_IMAGES:  # the default tiles are a subset's: the tiles over every image too
        kinds["all-image tiles"] = {"sample": "tiles", "images": n}
        print(f"tiles over a seeded subset of {AUTO_TILE_IMAGES:,} of the {n:,} images (AUTO_TILE_IMAGES); "
              f"all-image tiles: over all {n:,}")
    theta: dict[str, list[float]] = {k: [] for k in kinds}
    seconds: dict[str, list[float]] = {k: [] for k in kinds}
    cpu: dict[str, list[float]] = {k: [] for k in kinds}
    sizes = {}
    for seed in range(args.seeds):
        for kind, kw in kinds.items():  # interleaved: all see the same load
            t0, c0 = time.perf_counter(), time.process_time()
            scores = training_pair_scores(d, seed=seed, **kw)
            seconds[kind].append(time.perf_counter() - t0)
            cpu[kind].append(time.process_time() - c0)
            theta[kind].append(auto_global_threshold(scores))
            sizes[kind] = scores.size
    peak = peak.best(measure_peak(m=4096, k=args.dim, n=256))  # before and after: the load changes
    for line in peak.lines():
        print(line)
    t_tiles, t_pairs = min(seconds["tiles"]), min(seconds["pairs"])
    print(f"one sample, best of {args.seeds}:  tiles {t_tiles:6.2f} s ({sizes['tiles']:,} scores)   "
          f"pairs {t_pairs:6.2f} s ({sizes['pairs']:,} scores)   pairs / tiles = {t_pairs / t_tiles:.1f}×")
    for kind in kinds:
        print(f"  {kind:<15}: best {min(seconds[kind]):6.2f} s wall, {min(cpu[kind]):6.2f} s CPU")
    print(f"tiles: {share(2.0 * args.dim * sizes['tiles'], t_tiles, peak.float32)} (float32 GEMM, 2·D flops per score)")
    m = {k: float(np.mean(v)) for k, v in theta.items()}
    s = {k: float(np.std(v, ddof=1)) if len(v) > 1 else float("nan") for k, v in theta.items()}
    for kind in theta:
        print(f"θ_auto, {kind:<15}: mean {m[kind]:.6f}  sd over {args.seeds} seeds {s[kind]:.2e}")
    for kind in [k for k in kinds if k != "pairs"]:
        se = np.sqrt((s[kind] ** 2 + s["pairs"] ** 2) / args.seeds)
        print(f"summary: {kind} {t_pairs / min(seconds[kind]):.1f}× faster than pairs; θ means differ by "
              f"{m[kind] - m['pairs']:+.2e} = {abs(m[kind] - m['pairs']) / se:.1f} standard errors "
              f"(sd {kind} / sd pairs = {s[kind] / s['pairs']:.2f})")
    if "all-image tiles" in kinds:
        print(f"summary: subset tiles / all-image tiles, CPU: {min(cpu['tiles']):.2f} s / "
              f"{min(cpu['all-image tiles']):.2f} s = {min(cpu['tiles']) / min(cpu['all-image tiles']):.2f}")


if __name__ == "__main__":
    main()
