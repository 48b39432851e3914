"""Negative statistics: closed form (O(N·D²)) against the pairwise computation (O(N²·D)), side by side.

    python benchmarks/bench_negative_stats.py [--n 20000] [--dim 1280] [--places 2000]

Both run in this process on the same seeded unit descriptors with place structure; the
pairwise side is the reference computation done in row blocks (never holding N×N).
Prints both times, their ratio, and the largest difference of μ and σ.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from vpr_explorer.stats import negative_stats


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


def structured_descriptors(n: int, dim: int, places: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    labels = np.sort(rng.integers(0, places, n))
    centres = rng.normal(size=(places, dim)).astype(np.float32)
    d = centres[labels] + 0.8 * rng.normal(size=(n, dim)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d, labels


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20_000)
    ap.add_argument("--dim", type=int, default=1280)
    ap.add_argument("--places", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    d, labels = structured_descriptors(args.n, args.dim, args.places, args.seed)
    print(f"N = {args.n} descriptors × D = {args.dim}, {args.places} places (seed {args.seed})")

    t0 = time.perf_counter()
    st = negative_stats(d, labels)
    t_closed = time.perf_counter() - t0
    t0 = time.perf_counter()
    mu, sigma = pairwise(d, labels)
    t_pair = time.perf_counter() - t0

    print(f"{'closed form':>12}: {t_closed:8.2f} s")
    print(f"{'pairwise':>12}: {t_pair:8.2f} s")
    print(f"{'ratio':>12}: pairwise / closed form = {t_pair / t_closed:.1f}×")
    print(f"max |Δμ| = {np.abs(st.mu - mu).max():.2e}   max |Δσ| = {np.abs(st.sigma - sigma).max():.2e}")


if __name__ == "__main__":
    main()
