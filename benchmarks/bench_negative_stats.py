"""Negative statistics: the closed form in float32 and float64 side by side, and against pairwise.

    python benchmarks/bench_negative_stats.py [--n 100000] [--dim 1280] [--places 12500]
        [--pair-n 20000] [--pair-places 2000] [--shared 0.0] [--repeats 3] [--device cuda]

1. The closed form (O(N·D²)) at N = 100,000, D = 1,280, 12,500 places, with float32
   products (the default) and in float64 (in blocks of 8,192 rows): times, ratio, max |Δμ|
   and |Δσ| between them, the flops the step needs and those it does, and the share of this
   process's float32 GEMM peak (``gemm_peak``).
2. The closed form against the pairwise computation (O(N²·D)) at N = 20,000, 2,000 places:
   the pairwise side is the reference done in row blocks (never holding N×N).

All runs share one process and seeded unit descriptors with place structure; ``--shared S``
adds a component shared by all images, so that every score sits near S (σ ≪ μ, the case
where E[s²] − μ² cancels). Timings are the best of ``--repeats`` runs; the 1-minute load
average is printed beside them (the machine may be shared). The BLAS kernel is printed
first: run with and without ``OPENBLAS_CORETYPE`` / ``OPENBLAS_L2_SIZE`` to compare.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from gemm_peak import load_average, measure_peak, share
from vpr_explorer.method.stats import BLOCK, negative_stats

FLOAT64_BLOCK = 8192  # rows per block of the float64 closed form


def pairwise(d: np.ndarray, labels: np.ndarray, block: int = 2048) -> tuple[np.ndarray, np.ndarray]:
    """μᵢ, σᵢ from explicit similarity rows, in float64 sums over float32 products."""
    n = len(d)
    mu, sigma = np.empty(n), np.empty(n)
    for lo in range(0, n, block):
        s = (d[lo:lo + block] @ d.T).astype(np.float64)
        neg = labels[lo:lo + block, None] != labels[None, :]
        cnt = neg.sum(axis=1)
        m = np.where(neg, s, 0).sum(axis=1) / cnt
        mu[lo:lo + block] = m
        sigma[lo:lo + block] = np.sqrt((np.where(neg, (s - m[:, None]) ** 2, 0)).sum(axis=1) / cnt)
    return mu, sigma


def structured_descriptors(
    n: int, dim: int, places: int, seed: int, shared: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """``(n, dim)`` float32 unit rows (place centre + noise) and sorted place labels.

    ``shared`` > 0 mixes in one unit vector u shared by all: rows √shared·u + √(1−shared)·r,
    r ⟂ u, so every score is near ``shared``.
    """
    rng = np.random.default_rng(seed)
    labels = np.sort(rng.integers(0, places, n))
    centres = rng.normal(size=(places, dim)).astype(np.float32)
    d = centres[labels] + 0.8 * rng.normal(size=(n, dim)).astype(np.float32)
    if shared > 0:
        u = rng.normal(size=dim).astype(np.float32)
        u /= np.linalg.norm(u)
        d -= np.outer(d @ u, u)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        d = np.float32(np.sqrt(1 - shared)) * d + np.float32(np.sqrt(shared)) * u
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d, labels


def step_flops(n: int, dim: int, labels: np.ndarray) -> dict[str, float]:
    """Flops (a multiply-add is 2) of the closed form: what it needs, and what each precision does.

    needed: Gram with symmetry N·D(D+1); quadratic forms dᵢᵀCdᵢ 2·N·D² (the GEMM X·C and the
    row sums; the plain formulation); per place, float64: the k × (k+2) scores of each of
    its k images against the place, T and m, 2·Σ_p k_p(k_p + 2)·D; centring and T 2·N·D.
    float32 does: syrk N·D(D+1); quadratic forms through the block triangular W,
    2·N·Σ_J b_J·end_J ≈ (1 + 1/8)·N·D² (``stats._quadratic_forms``); the same per-place terms.
    """
    k = np.bincount(labels)
    k = k[k > 0].astype(float)
    places = 2 * float((k * (k + 2)).sum()) * dim
    gram = float(n) * dim * (dim + 1)
    from vpr_explorer.method.stats import _TRI_BLOCKS

    edges = np.linspace(0, dim, min(_TRI_BLOCKS, dim) + 1).round().astype(int)
    tri = 2.0 * n * sum(float(hi - lo) * hi for lo, hi in zip(edges[:-1], edges[1:])) + 2.0 * n * dim
    return {
        "gram": gram,
        "quad": 2.0 * n * dim * dim + 2.0 * n * dim,
        "places": places + 2.0 * n * dim,
        "float32 gemm": gram + tri,
        "float32 all": gram + tri + places + 2.0 * n * dim,
    }


def best_time(fn, repeats: int) -> tuple[float, object]:
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def side_by_side(args: argparse.Namespace, peak32: float) -> None:
    d, labels = structured_descriptors(args.n, args.dim, args.places, args.seed, args.shared)
    print(f"\n1. closed form, float32 products against float64: N = {args.n:,} × D = {args.dim:,}, "
          f"{args.places:,} places (seed {args.seed}, shared component {args.shared})")
    print(f"   load average before: {load_average()}")
    t32, st32 = best_time(lambda: negative_stats(d, labels, precision="float32"), args.repeats)
    print(f"   float32 products: {t32:6.2f} s   (block {BLOCK}, load {load_average()})")
    t64, st64 = best_time(lambda: negative_stats(d, labels, precision="float64", block=FLOAT64_BLOCK), args.repeats)
    print(f"   float64         : {t64:6.2f} s   (block {FLOAT64_BLOCK}, load {load_average()})")
    print(f"   ratio           : float64 / float32 = {t64 / t32:.2f}×")
    print(f"   max |Δμ| = {np.abs(st32.mu - st64.mu).max():.2e}   max |Δσ| = {np.abs(st32.sigma - st64.sigma).max():.2e}"
          f"   (μ {st64.mu.min():.3f}..{st64.mu.max():.3f}, σ {st64.sigma.min():.4f}..{st64.sigma.max():.4f})")
    f = step_flops(args.n, args.dim, labels)
    needed = f["gram"] + f["quad"] + f["places"]
    print(f"   flops the step needs: Gram (symmetric) {f['gram']:.3g} + quadratic forms (X·C) {f['quad']:.3g} + "
          f"per-place float64 {f['places']:.3g} = {needed:.3g}")
    print(f"   flops float32 does  : syrk {f['gram']:.3g} + quadratic forms (triangular W) "
          f"{f['float32 gemm'] - f['gram']:.3g} + per-place float64 {f['places']:.3g} = {f['float32 all']:.3g}")
    print(f"   float32, the step's flops / time: {share(needed, t32, peak32)} (float32 GEMM; effective, "
          f"W does fewer)")
    print(f"   float32, flops done / time      : {share(f['float32 all'], t32, peak32)} (float32 GEMM)")
    if args.device:
        tdev, stdev = best_time(lambda: negative_stats(d, labels, device=args.device), args.repeats)
        print(f"   torch on {args.device:<8}: {tdev:6.2f} s   float32 / torch = {t32 / tdev:.2f}×   "
              f"max |Δμ| = {np.abs(stdev.mu - st64.mu).max():.2e}   max |Δσ| = {np.abs(stdev.sigma - st64.sigma).max():.2e}"
              f" (against float64)")
        print(f"   torch, the step's flops / time  : {share(needed, tdev, peak32)} (numpy float32 GEMM on the CPU)")


def against_pairwise(args: argparse.Namespace) -> None:
    d, labels = structured_descriptors(args.pair_n, args.dim, args.pair_places, args.seed, args.shared)
    print(f"\n2. closed form against pairwise: N = {args.pair_n:,} × D = {args.dim:,}, {args.pair_places:,} places")
    t32, st32 = best_time(lambda: negative_stats(d, labels), args.repeats)
    t64, st64 = best_time(lambda: negative_stats(d, labels, precision="float64", block=FLOAT64_BLOCK), args.repeats)
    t0 = time.perf_counter()
    mu, sigma = pairwise(d, labels)
    t_pair = time.perf_counter() - t0
    print(f"   {'closed, float32':>16}: {t32:8.2f} s   (load {load_average()})")
    print(f"   {'closed, float64':>16}: {t64:8.2f} s")
    print(f"   {'pairwise':>16}: {t_pair:8.2f} s")
    print(f"   {'ratio':>16}: pairwise / closed float32 = {t_pair / t32:.1f}×, / closed float64 = {t_pair / t64:.1f}×")
    for name, st in (("float32", st32), ("float64", st64)):
        print(f"   {name} vs pairwise: max |Δμ| = {np.abs(st.mu - mu).max():.2e}   "
              f"max |Δσ| = {np.abs(st.sigma - sigma).max():.2e}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--dim", type=int, default=1280)
    ap.add_argument("--places", type=int, default=12_500)
    ap.add_argument("--pair-n", type=int, default=20_000, help="0 skips the pairwise comparison")
    ap.add_argument("--pair-places", type=int, default=2000)
    ap.add_argument("--shared", type=float, default=0.0, help="shared component: scores near this value")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default=None, help="also the torch path on this device (cpu, cuda)")
    args = ap.parse_args()
    print(f"load average {load_average()}")
    peak = measure_peak(BLOCK, args.dim, args.dim)
    for line in peak.lines():
        print(line)
    side_by_side(args, peak.float32)
    if args.pair_n:
        against_pairwise(args)


if __name__ == "__main__":
    main()
