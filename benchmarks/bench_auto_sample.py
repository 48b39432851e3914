"""The automatic global θ's sample: dense tiles (one GEMM per tile) against independent pairs (issue 13 §3).

    python benchmarks/bench_auto_sample.py                  # the app's 110k route: 24,831 database images × 2,048
    python benchmarks/bench_auto_sample.py --n 100000 --dim 1280 --seeds 3   # a protocol split at Nordland scale

Above ``thresholds.AUTO_MAX_PAIRS`` (2·10⁶) training pairs, ``training_pair_scores`` samples.
Side by side in one process, on seeded Nordland-like descriptors with place structure
(``bench_nordland_scale.nordland_like``):

1. time of one sample: ``sample="tiles"`` (the default: a seeded permutation cut into groups,
   every pair between neighbouring groups, each tile one float32 GEMM) against
   ``sample="pairs"`` (the former default: 2·10⁶ independent pairs, each a gathered row pair),
   their ratio, and the tiles' GEMM rate as a share of numpy's float32 GEMM peak measured
   in the same run (``gemm_peak``; the step's flops: 2·D per pair);
2. the automatic θ over ``--seeds`` seeds of each sample: mean and standard deviation (its
   sampling error), and the difference of the means in units of its standard error. Pairs
   inside one tile share rows and columns, so they are correlated; the θ must still agree
   with the independent-pairs θ within that error.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench_nordland_scale import FRAMES, TRAVERSALS, nordland_like
from gemm_peak import load_average, measure_peak, share
from vpr_explorer.thresholds import AUTO_MAX_PAIRS, auto_global_threshold, training_pair_scores


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=24_831, help="training images (default 24,831: the app's 110k route)")
    ap.add_argument("--dim", type=int, default=2048)
    ap.add_argument("--seeds", type=int, default=5, help="samples of each kind for the θ spread (default 5)")
    args = ap.parse_args()
    places = -(-args.n // (FRAMES * TRAVERSALS))
    d = nordland_like(places, args.dim, 0)[0][: args.n]
    print(f"data: {len(d):,} × {args.dim} Nordland-like descriptors; {len(d) * (len(d) - 1) // 2:.2e} pairs, "
          f"sample of {AUTO_MAX_PAIRS:.0e}; load average {load_average()}")
    peak = measure_peak(m=4096, k=args.dim, n=256)  # a tall GEMM of the tiles' depth

    theta: dict[str, list[float]] = {"tiles": [], "pairs": []}
    seconds: dict[str, list[float]] = {"tiles": [], "pairs": []}
    sizes = {}
    for seed in range(args.seeds):
        for kind in theta:  # interleaved: both see the same load
            t0 = time.perf_counter()
            scores = training_pair_scores(d, seed=seed, sample=kind)
            seconds[kind].append(time.perf_counter() - t0)
            theta[kind].append(auto_global_threshold(scores))
            sizes[kind] = scores.size
    peak = peak.best(measure_peak(m=4096, k=args.dim, n=256))  # before and after: the load changes
    for line in peak.lines():
        print(line)
    t_tiles, t_pairs = min(seconds["tiles"]), min(seconds["pairs"])
    print(f"one sample, best of {args.seeds}:  tiles {t_tiles:6.2f} s ({sizes['tiles']:,} scores)   "
          f"pairs {t_pairs:6.2f} s ({sizes['pairs']:,} scores)   pairs / tiles = {t_pairs / t_tiles:.1f}×")
    print(f"tiles: {share(2.0 * args.dim * sizes['tiles'], t_tiles, peak.float32)} (float32 GEMM, 2·D flops per score)")
    m = {k: float(np.mean(v)) for k, v in theta.items()}
    s = {k: float(np.std(v, ddof=1)) if len(v) > 1 else float("nan") for k, v in theta.items()}
    for kind in theta:
        print(f"θ_auto, {kind:<5}: mean {m[kind]:.6f}  sd over {args.seeds} seeds {s[kind]:.2e}")
    se = np.sqrt((s["tiles"] ** 2 + s["pairs"] ** 2) / args.seeds)
    print(f"summary: tiles {t_pairs / t_tiles:.1f}× faster than pairs; θ means differ by "
          f"{m['tiles'] - m['pairs']:+.2e} = {abs(m['tiles'] - m['pairs']) / se:.1f} standard errors "
          f"(sd tiles / sd pairs = {s['tiles'] / s['pairs']:.2f})")


if __name__ == "__main__":
    main()
