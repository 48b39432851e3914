"""Per-place thresholds θ_p from negative statistics, the threshold family, global thresholds.

* simple:   θ_p = (1/n_p) Σᵢ μᵢ
* weighted: θ_p = Σᵢ (wᵢτᵢ² / Σⱼ wⱼτⱼ²) μᵢ with τ = 1/σ (paper eq. 4, weights normalised
  as the authors' code does; read literally, eq. 4 with wᵢ = 1/n is not a weighted mean)
* family:   θ_p(k) = θ_p + k·s_p, s_p the standard deviation of the mixture M(p); k = 0 is
  the paper
* automatic global (VPR_Tutorial, after Schubert et al. "Beyond ANN"):
  θ = median(S) + Φ⁻¹(1 − 10⁻⁶)·MAD(S)/0.675 over the training similarity matrix
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from enum import StrEnum

import numpy as np
from scipy.stats import norm

from vpr_explorer.errors import VPRInputError
from vpr_explorer.stats import SIGMA_FLOOR, NegativeStats, mixture_moments

#: Φ⁻¹(1 − 10⁻⁶) ≈ 4.753, the automatic threshold's multiple of the robust spread.
AUTO_Z = float(norm.ppf(1 - 1e-6))
#: Pairs used for the automatic global threshold when the training set has more.
AUTO_MAX_PAIRS = 2_000_000
# Sampled pairs scored per task, and threads (110k-image app benchmark, 24,831 x 2048
# database: 13.5 s in one thread with 65,536-pair blocks, 7.8 s with two).
PAIR_BLOCK = 4096
PAIR_WORKERS = min(4, os.cpu_count() or 1)


class ThresholdMethod(StrEnum):
    """How μᵢ of a place's images combine into θ_p."""

    SIMPLE = "simple"
    WEIGHTED = "weighted"


THRESHOLD_LABELS = {
    ThresholdMethod.SIMPLE: "simple: mean of the place's μᵢ",
    ThresholdMethod.WEIGHTED: "weighted (eq. 4, normalised): Σ wᵢτᵢ²μᵢ / Σ wⱼτⱼ², τ = 1/σ",
}


def _simple(stats: NegativeStats) -> np.ndarray:
    return np.bincount(stats.labels, weights=stats.mu, minlength=stats.n_places) / stats.counts


def _weighted(stats: NegativeStats) -> np.ndarray:
    tau2 = 1.0 / np.maximum(stats.sigma, SIGMA_FLOOR) ** 2
    v = stats.weights * tau2
    return np.bincount(stats.labels, weights=v * stats.mu, minlength=stats.n_places) / np.bincount(
        stats.labels, weights=v, minlength=stats.n_places
    )


_THRESHOLDS = {ThresholdMethod.SIMPLE: _simple, ThresholdMethod.WEIGHTED: _weighted}


def place_thresholds(stats: NegativeStats, method: ThresholdMethod | str = ThresholdMethod.WEIGHTED) -> np.ndarray:
    """``(n_places,)`` θ_p; NaN for places without training images."""
    try:
        fn = _THRESHOLDS[ThresholdMethod(method)]
    except ValueError:
        raise VPRInputError(
            f"threshold method {method!r}: choose one of {', '.join(m.value for m in ThresholdMethod)}"
        ) from None
    with np.errstate(invalid="ignore", divide="ignore"):
        theta = fn(stats)
    theta[stats.counts == 0] = np.nan
    return theta


def threshold_family(theta: np.ndarray, spread: np.ndarray, k: float) -> np.ndarray:
    """θ_p(k) = θ_p + k·s_p, each ``(n_places,)``."""
    if not np.isfinite(k):
        raise VPRInputError(f"k={k!r}: must be a finite number of mixture standard deviations")
    return theta + k * spread


def mixture_spread(stats: NegativeStats) -> np.ndarray:
    """``(n_places,)`` s_p, the standard deviation of each place's negative mixture M(p)."""
    return mixture_moments(stats)[1]


def adaptive_k(positive_mean: np.ndarray, negative_mean: np.ndarray, negative_std: np.ndarray) -> np.ndarray:
    """Per-place k = clip((μ⁺ − μ⁻) / (2σ⁻), 1, 2), from the authors' later work.

    μ⁺ is the mean same-place score, μ⁻ and σ⁻ the mixture's mean and standard deviation.
    A place without a same-place pair (μ⁺ NaN) gets k = 1.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        k = (positive_mean - negative_mean) / (2 * np.maximum(negative_std, SIGMA_FLOOR))
    return np.clip(np.nan_to_num(k, nan=1.0), 1.0, 2.0)


def training_pair_scores(
    descriptors: np.ndarray, *, max_pairs: int = AUTO_MAX_PAIRS, seed: int = 0, block: int = PAIR_BLOCK,
    workers: int = PAIR_WORKERS,
) -> np.ndarray:
    """Similarities of distinct training pairs i < j: all of them, or a seeded sample of ``max_pairs``.

    Sampled pairs are scored ``block`` at a time by ``workers`` threads (gathering the
    rows is memory-bound and numpy releases the GIL for it), so memory stays at
    ``2·workers·block·D`` floats whatever ``max_pairs`` is. Each pair's score is the same
    float32 dot product whatever the block size or thread count.
    """
    d = np.asarray(descriptors, dtype=np.float32)
    n = len(d)
    total = n * (n - 1) // 2
    if total == 0:
        raise VPRInputError("the automatic global threshold needs at least 2 training images")
    if total <= max_pairs:
        iu = np.triu_indices(n, k=1)
        return (d @ d.T)[iu]
    rng = np.random.default_rng(seed)
    i = rng.integers(0, n, size=max_pairs)
    j = rng.integers(0, n - 1, size=max_pairs)
    j = j + (j >= i)  # uniform over j != i
    out = np.empty(max_pairs, dtype=np.float32)

    def score(lo: int) -> None:
        hi = lo + block
        out[lo:hi] = np.einsum("ij,ij->i", d[i[lo:hi]], d[j[lo:hi]])

    with ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="vpr-pairs") as pool:
        list(pool.map(score, range(0, max_pairs, block)))
    return out


def auto_global_threshold(scores: np.ndarray) -> float:
    """θ = median(S) + Φ⁻¹(1 − 10⁻⁶)·MAD(S)/0.675 over flat training similarity scores ``S``."""
    s = np.asarray(scores, dtype=np.float64).ravel()
    if s.size == 0:
        raise VPRInputError("the automatic global threshold needs at least one training score")
    med = np.median(s)
    mad = np.median(np.abs(s - med))
    return float(med + AUTO_Z * mad / 0.675)
