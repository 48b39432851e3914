"""Plain, obviously-correct reference implementations the fast code must equal.

Loops and full matrices on purpose: nothing here is clever.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import norm


def pairwise_negative_stats(d, labels):
    """μᵢ, σᵢ (population) of each image's scores against images of other places, from the full matrix."""
    s = np.asarray(d, dtype=np.float64) @ np.asarray(d, dtype=np.float64).T
    mu, sigma = [], []
    for i in range(len(d)):
        neg = s[i, labels != labels[i]]
        mu.append(neg.mean())
        sigma.append(neg.std())
    return np.array(mu), np.array(sigma)


def loop_thresholds(mu, sigma, n_neg, labels, n_places):
    """θ simple and weighted (normalised eq. 4) by looping over places."""
    simple, weighted = np.full(n_places, np.nan), np.full(n_places, np.nan)
    for p in range(n_places):
        idx = [i for i in range(len(labels)) if labels[i] == p]
        if not idx:
            continue
        simple[p] = sum(mu[i] for i in idx) / len(idx)
        w = [n_neg[i] / sum(n_neg[j] for j in idx) for i in idx]
        t2 = [1 / sigma[i] ** 2 for i in idx]
        weighted[p] = sum(wi * ti * mu[i] for wi, ti, i in zip(w, t2, idx)) / sum(wi * ti for wi, ti in zip(w, t2))
    return simple, weighted


def loop_auto_threshold(d):
    s = np.asarray(d, dtype=np.float64) @ np.asarray(d, dtype=np.float64).T
    vals = [s[i, j] for i in range(len(d)) for j in range(i + 1, len(d))]
    med = np.median(vals)
    mad = np.median([abs(v - med) for v in vals])
    return med + norm.ppf(1 - 1e-6) * mad / 0.675


def loop_rank(scores, correct):
    """Pessimistic rank by sorting: ties with wrong candidates count against the query."""
    out = []
    for s, c in zip(scores, correct):
        kept_correct = [v for v, ok in zip(s, c) if ok and v > -np.inf]
        if not kept_correct:
            out.append(np.inf)
            continue
        best = max(kept_correct)
        out.append(1 + sum(1 for v, ok in zip(s, c) if not ok and v >= best))
    return np.array(out, dtype=float)


def unit_rows(rng, n, dim):
    x = rng.normal(size=(n, dim))
    return x / np.linalg.norm(x, axis=1, keepdims=True)
