"""Each weighted θ's error bound, and its exact float64 recomputation (package doc, step 6).

The downdated σ carries the float32 rounding of the pass's scores in V. ``error_scale``
measures it on a seeded sample of exactly recomputed images, ``uncertainty`` turns it into
a bound per weighted θ, and ``make_exact`` recomputes the places of a doubtful comparison in
float64 (``scoring`` finds them).
"""

from __future__ import annotations

import numpy as np

from vpr_explorer.method.stats import SIGMA_FLOOR, NegativeStats
from vpr_explorer.method.thresholds import ThresholdMethod
from vpr_explorer.protocols.evaluation import Split
from vpr_explorer.protocols.scale.downdate import SplitData, downdated_sigma
from vpr_explorer.protocols.scale.full_sums import FullSums
from vpr_explorer.protocols.scale.layout import Layout
from vpr_explorer.protocols.scale.twins import thresholds_with_twins

#: The per-place error bound of the weighted θ is this many times the largest error seen
#: in a sample of exactly recomputed images (errors are sums of many roundings: their
#: extremes over a whole run exceed a sample's by a small factor, not by 20).
SAFETY = 20.0
#: Training images recomputed exactly to measure that error (spread over up to 8 splits).
SAMPLE = 256


def exact_v(d: np.ndarray, lay: Layout, sums: FullSums, split: Split, rows: np.ndarray) -> np.ndarray:
    """V of training rows in float64 from the original descriptors: Σ_{q∈Q_r, other place} (dᵢ·d_q − c)²."""
    q = np.asarray(d[split.queries], dtype=np.float64)  # ordered by place index
    out = np.empty(len(rows))
    step = 512
    for lo in range(0, len(rows), step):
        rr = rows[lo : lo + step]
        s = np.asarray(d[lay.image_of_row[rr]], dtype=np.float64) @ q.T - sums.centre
        s[np.arange(len(rr)), lay.place_of_row[rr]] = 0.0  # the own place's query is no negative
        out[lo : lo + step] = np.einsum("ij,ij->i", s, s)
    return out


def error_scale(d: np.ndarray, lay: Layout, sums: FullSums, data: list[SplitData], seed: int) -> float:
    """κ: the largest |V − V_exact| / √V_exact over a seeded sample of training images."""
    rng = np.random.default_rng(seed)
    picks = rng.choice(len(data), size=min(len(data), 8), replace=False)
    kappa = 0.0
    for r in picks:
        sd = data[r]
        idx = rng.choice(len(sd.rows), size=min(len(sd.rows), SAMPLE // len(picks)), replace=False)
        exact = exact_v(d, lay, sums, sd.split, sd.rows[idx])
        kappa = max(kappa, float(np.max(np.abs(sd.v[idx] - exact) / np.sqrt(np.maximum(exact, 1e-300)))))
    return kappa


def uncertainty(sd: SplitData, lay: Layout, kappa: float) -> np.ndarray:
    """``(P,)`` error bound of each weighted θ, from the V error scale κ.

    θ = Σᵢ wᵢμᵢ/Σw with wᵢ ∝ 1/σᵢ², so |δθ| ≤ Σᵢ (wᵢ/Σw)·|μᵢ − θ|·|δσᵢ²|/σᵢ², and
    |δσᵢ²| = |δVᵢ|/n⁻ᵢ ≤ safety·κ·√Vᵢ/n⁻ᵢ.
    """
    st = sd.stats
    theta = sd.thresholds["weighted"]
    var = np.maximum(st.sigma, SIGMA_FLOOR) ** 2
    w = st.weights / var
    wsum = np.bincount(st.labels, weights=w, minlength=st.n_places)
    rel = SAFETY * kappa * np.sqrt(np.maximum(sd.v, 0.0)) / st.n_neg / var
    with np.errstate(invalid="ignore", divide="ignore"):
        bound = np.bincount(st.labels, weights=w * np.abs(st.mu - theta[st.labels]) * rel, minlength=st.n_places) / wsum
    return np.nan_to_num(bound[lay.places], nan=0.0) * 2 + 1e-15  # ×2: second-order terms


def make_exact(sd: SplitData, places: np.ndarray, d: np.ndarray, lay: Layout, sums: FullSums) -> bool:
    """Recompute σ (hence the weighted θ) of these places' training images in float64.

    Twins go together (a twin's θ is its first twin's). ``sd``'s ``v``, ``stats``,
    ``thresholds`` and ``uncertainty`` are replaced by new values (0: exact).

    Returns:
        Whether any place was not exact yet.
    """
    places = np.setdiff1d(places, np.flatnonzero(sd.uncertainty == 0))
    if len(places) == 0:
        return False
    group = np.flatnonzero(np.isin(sd.twins, sd.twins[places]))
    sel = np.flatnonzero(np.isin(lay.place_of_row[sd.rows], group))
    rows, st = sd.rows[sel], sd.stats
    sd.v = sd.v.copy()
    sd.v[sel] = exact_v(d, lay, sums, sd.split, rows)
    sigma = st.sigma.copy()
    sigma[sel] = downdated_sigma(sums, rows, sd.v[sel], st.mu[sel], st.n_neg[sel])
    sd.stats = NegativeStats(mu=st.mu, sigma=sigma, n_neg=st.n_neg, labels=st.labels, n_places=st.n_places)
    weighted = thresholds_with_twins(sd.stats, ThresholdMethod.WEIGHTED, lay, sd.twins)
    sd.thresholds = {**sd.thresholds, ThresholdMethod.WEIGHTED.value: weighted}
    sd.uncertainty = sd.uncertainty.copy()
    sd.uncertainty[group] = 0.0
    return True
