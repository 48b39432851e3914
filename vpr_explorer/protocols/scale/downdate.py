"""Per split: μ, σ and the thresholds from the downdated full-set sums (package doc, steps 1 and 3).

A split's training image i of place p (queries Q_r, p's held-out image h) has
n⁻ᵢ μᵢ = dᵢ·(T − T_p) − dᵢ·Σ_{q∈Q_r} d_q + dᵢ·d_h (``split_mu``) and
σᵢ² = (aᵢ − V_{i,r})/n⁻ᵢ − (μᵢ − c)² (``downdated_sigma``, V from the pass); the thresholds
follow through the library's own ``NegativeStats`` and ``place_thresholds``
(``split_thresholds``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vpr_explorer.method.stats import NegativeStats, mixture_moments
from vpr_explorer.method.thresholds import ThresholdMethod, adaptive_k
from vpr_explorer.protocols.evaluation import Split
from vpr_explorer.protocols.scale.full_sums import FullSums
from vpr_explorer.protocols.scale.layout import Layout
from vpr_explorer.protocols.scale.twins import Content, thresholds_with_twins, twins


@dataclass(eq=False)
class SplitData:
    """One split's statistics and thresholds; ``uncertainty`` bounds each weighted θ's error.

    Attributes:
        split: the split.
        held: ``(P,)`` held-out slot of every place.
        rows: ``(n_train,)`` layout rows of the training images, in the reference's order.
        stats: their negative statistics.
        v: ``(n_train,)`` the downdate V of each training image.
        twins: ``(P,)`` the first place index with the same training images (``twins.twins``).
        thresholds: θ per method (``(n_places,)`` arrays; ``"auto"`` and ``"user"`` floats).
        spread: ``(n_places,)`` s_p.
        k_adaptive: ``(n_places,)``.
        uncertainty: ``(P,)`` bound on |θ_weighted error|, 0 where exact (package doc, step 6);
            ``None`` until ``near_ties.uncertainty`` sets it.
    """

    split: Split
    held: np.ndarray
    rows: np.ndarray
    stats: NegativeStats
    v: np.ndarray
    twins: np.ndarray
    thresholds: dict[str, np.ndarray | float]
    spread: np.ndarray
    k_adaptive: np.ndarray
    uncertainty: np.ndarray | None = None


def split_mu(r: int, train_rows: np.ndarray, lay: Layout, sums: FullSums,
             held: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """μᵢ and n⁻ᵢ of split r's training rows: n⁻μ = d·(T − T_p) − d·Σ_q d_q + d·d_h (float64).

    Returns:
        ``(mu, n_neg)``, each ``(n_train,)``.
    """
    cr, kr = lay.place_of_row[train_rows], lay.slot_of_row[train_rows]
    n_neg = len(train_rows) - (lay.sizes - 1)[cr]
    sum_neg = sums.dot_other[train_rows] - (sums.dot_queries[train_rows, r] - sums.gram[cr, kr, held[cr]])
    return sum_neg / n_neg, n_neg


def downdated_sigma(sums: FullSums, rows: np.ndarray, v: np.ndarray, mu: np.ndarray, n_neg: np.ndarray) -> np.ndarray:
    """σᵢ of training rows from the downdate: E[(s − c)²] = (aᵢ − Vᵢ)/n⁻ᵢ, σ² = E[(s − c)²] − (μᵢ − c)²."""
    second = (sums.a_centred[rows] - v) / n_neg
    return np.sqrt(np.clip(second - (mu - sums.centre) ** 2, 0.0, None))


def _positive_means(gram: np.ndarray, held: np.ndarray, lay: Layout, n_places: int) -> np.ndarray:
    """``(n_places,)`` Σ_{i≠j∈train_p} dᵢ·dⱼ / (n(n−1)) from the within-place grams ``(P, m, m)``
    (the reference's ``stats.positive_means``, to rounding); NaN for a place of one training image."""
    ar = np.arange(len(lay.places))
    g_hh = gram[ar, held, held]
    pair_sum = gram.sum(axis=(1, 2)) - 2 * gram[ar, held].sum(axis=1) + g_hh
    diag = np.einsum("pkk->p", gram) - g_hh
    n = (lay.sizes - 1).astype(np.float64)
    pos_mean = np.full(n_places, np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        pos_mean[lay.places] = np.where(n > 1, (pair_sum - diag) / (n * (n - 1)), np.nan)
    return pos_mean


def split_thresholds(r: int, sp: Split, lay: Layout, sums: FullSums, v_all: np.ndarray, held: np.ndarray,
                     n_places: int, auto: float, user_theta: float | None, content: Content,
                     mu_n: tuple[np.ndarray, np.ndarray]) -> SplitData:
    """Split r's statistics and thresholds from the downdated moments.

    Args:
        r: the split's index (its column of ``v_all``).
        sp: the split.
        lay, sums: the layout and the full-set sums.
        v_all: ``(n_rows, R)`` V of every row and split (``PassResult.v``).
        held: ``(P,)`` held-out slot of every place.
        n_places: number of place ids.
        auto: the split's automatic global θ; user_theta: the user's, if any.
        content: the slots' content classes (``twins.content_classes``).
        mu_n: ``split_mu`` of its training rows.
    """
    rows = lay.row_of_image[sp.train]
    mu, n_neg = mu_n
    v = v_all[rows, r]
    labels = lay.places[lay.place_of_row[rows]].astype(np.int64)
    stats = NegativeStats(mu=mu, sigma=downdated_sigma(sums, rows, v, mu, n_neg), n_neg=n_neg.astype(np.int64),
                          labels=labels, n_places=n_places)
    first_twin = twins(content, held)
    th: dict[str, np.ndarray | float] = {
        ThresholdMethod.SIMPLE.value: thresholds_with_twins(stats, ThresholdMethod.SIMPLE, lay, first_twin),
        ThresholdMethod.WEIGHTED.value: thresholds_with_twins(stats, ThresholdMethod.WEIGHTED, lay, first_twin),
        "auto": auto,
    }
    if user_theta is not None:
        th["user"] = float(user_theta)
    neg_mean, spread = mixture_moments(stats)
    k_adaptive = adaptive_k(_positive_means(sums.gram, held, lay, n_places), neg_mean, spread)
    return SplitData(sp, held, rows, stats, v, first_twin, th, spread, k_adaptive)
