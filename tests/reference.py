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


def loop_rank(scores, correct, tie=1e-5):
    """Pessimistic rank: wrong candidates within ``tie`` of the best correct score or above count against the query."""
    out = []
    for s, c in zip(scores, correct):
        kept_correct = [v for v, ok in zip(s, c) if ok and v > -np.inf]
        if not kept_correct:
            out.append(np.inf)
            continue
        best = max(kept_correct)
        out.append(1 + sum(1 for v, ok in zip(s, c) if not ok and v >= best - tie))
    return np.array(out, dtype=float)


def unit_rows(rng, n, dim):
    x = rng.normal(size=(n, dim))
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def _lowest_within(values, tie):
    """Index of the lowest position whose value is within ``tie`` of the finite maximum, or -1."""
    finite = [v for v in values if v > -np.inf]
    if not finite:
        return -1
    top = max(finite)
    return next(i for i, v in enumerate(values) if v > -np.inf and v >= top - tie)


def loop_mixture_spread(mu, sigma, n_neg, labels, n_places):
    """s_p: the standard deviation of Σ wᵢ N(μᵢ, σᵢ²), wᵢ = n⁻ᵢ / Σ n⁻ⱼ, by looping."""
    out = np.full(n_places, np.nan)
    for p in range(n_places):
        idx = [i for i in range(len(labels)) if labels[i] == p]
        if idx:
            w = [n_neg[i] / sum(n_neg[j] for j in idx) for i in idx]
            mean = sum(wi * mu[i] for wi, i in zip(w, idx))
            out[p] = np.sqrt(max(sum(wi * (sigma[i] ** 2 + mu[i] ** 2) for wi, i in zip(w, idx)) - mean**2, 0.0))
    return out


def loop_protocol(d, labels, trav, n_places, splits, *, cross_condition=False, ks=(1, 3, 5, 10), ks_family=(),
                  tie=1e-5):
    """Every method of the paper / open-set protocols by plain loops over the given splits.

    Returns ``{method: {"recall": {k: (mean, std)}, "accepted", "precision", "own", "rejection"}}``
    with (mean, std) over splits (NaN-free values only), for the baselines, margin/raw ×
    simple/weighted and, for each k in ``ks_family``, ``("family", base, rule, k)``.
    """
    d = np.asarray(d, dtype=np.float64)
    per = {}

    def add(key, split_values):
        per.setdefault(key, []).append(split_values)

    for sp in splits:
        tr, q = list(sp.train), list(sp.queries)
        mu, sigma = pairwise_negative_stats(d[tr], labels[tr])
        n_neg = np.array([np.sum(labels[tr] != labels[i]) for i in tr])
        simple, weighted = loop_thresholds(mu, sigma, n_neg, labels[tr], n_places)
        spread = loop_mixture_spread(mu, sigma, n_neg, labels[tr], n_places)
        thetas = {"simple": simple, "weighted": weighted}
        methods = [("image-baseline", None, None), ("place-baseline", "none", None)]
        methods += [(f"{rule}-{base}", rule, thetas[base]) for rule in ("margin", "raw") for base in ("simple", "weighted")]
        methods += [(("family", base, rule, k), rule, thetas[base] + k * spread)
                    for base in ("simple", "weighted") for rule in ("margin", "raw") for k in ks_family]
        for key, rule, theta in methods:
            rows = []
            for qi in q:
                known = not sp.unknown[labels[qi]]
                usable = [j for j in tr if not (cross_condition and trav[j] == trav[qi])]
                s = {j: float(d[qi] @ d[j]) for j in usable}
                if rule is None:  # image level: candidates are the training images, in training order
                    cand = [s.get(j, -np.inf) for j in tr]
                    correct = [known and labels[j] == labels[qi] for j in tr]
                    ans = _lowest_within(cand, tie)
                    img = tr[ans] if ans >= 0 else -1
                else:
                    raw, best_img = [], []
                    for p in range(n_places):
                        members = [j for j in tr if labels[j] == p and j in s]
                        scores = [s[j] for j in members]
                        r = max(scores) if scores else -np.inf
                        raw.append(r)
                        best_img.append(members[_lowest_within(scores, tie)] if scores else -1)
                    cand = []
                    for p in range(n_places):
                        if rule == "none":
                            cand.append(raw[p])
                        elif raw[p] > -np.inf and not np.isnan(theta[p]) and raw[p] >= theta[p]:
                            cand.append(raw[p] - theta[p] if rule == "margin" else raw[p])
                        else:
                            cand.append(-np.inf)
                    correct = [known and p == labels[qi] for p in range(n_places)]
                    ans = _lowest_within(cand, tie)
                    img = best_img[ans] if ans >= 0 else -1
                rank = loop_rank(np.array([cand]), np.array([correct]), tie)[0]
                accepted = ans >= 0
                rows.append((known, rank, accepted, accepted and rank == 1, img, trav[qi]))
            known = np.array([r[0] for r in rows])
            rank = np.array([r[1] for r in rows])
            acc = np.array([r[2] for r in rows])
            right = np.array([r[3] for r in rows]) & known
            own = [trav[r[4]] == r[5] for r in rows if r[2] and r[4] >= 0]
            add(key, {
                "recall": {k: np.mean(rank[known] <= k) if known.any() else np.nan for k in ks},
                "accepted": acc.mean(),
                "precision": right.sum() / acc.sum() if acc.any() else np.nan,
                "own": np.mean(own) if own else np.nan,
                "rejection": np.mean(~acc[~known]) if (~known).any() else np.nan,
            })

    def stat(values):  # the sample std (ddof 1) over the splits; one split has none
        a = np.array([v for v in values if not np.isnan(v)])
        if not a.size:
            return (np.nan, np.nan)
        return (a.mean(), a.std(ddof=1) if a.size > 1 else np.nan)

    return {
        key: {
            "recall": {k: stat([r["recall"][k] for r in rs]) for k in ks},
            **{f: stat([r[f] for r in rs]) for f in ("accepted", "precision", "own", "rejection")},
        }
        for key, rs in per.items()
    }


def synthetic_places(seed=0, n_places=12, per_place=6, dim=32, noise=0.9, n_trav=3):
    """Unit descriptors: one random centre per place plus noise; traversal = image index within the place mod n_trav."""
    rng = np.random.default_rng(seed)
    centres = unit_rows(rng, n_places, dim)
    labels = np.repeat(np.arange(n_places), per_place)
    d = centres[labels] + noise * rng.normal(size=(len(labels), dim)) / np.sqrt(dim)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    trav = np.tile(np.arange(per_place) % n_trav, n_places)
    return d, labels, trav
