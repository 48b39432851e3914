"""Why the automatic global θ is what it is, and when it cannot accept anything.

The automatic global θ (``thresholds.auto_global_threshold``) is

    θ = median(S) + Φ⁻¹(1 − 10⁻⁶)·MAD(S)/0.675

over the training similarity scores S. With descriptors whose similarities spread widely
(efficientnet-lite0 on GardensPoint: median 0.45, MAD 0.08), θ lands above 1, the largest
cosine similarity of two L2-normalised descriptors: the method then rejects every query,
and a table showing its 0% recall must say so. ``auto_parts`` gives the pieces, and
``rejects_all_note`` the sentence the app shows beside the method.

The paper and open-set protocols fit θ in every run on that run's training images, from one
pooled sample (``thresholds.pooled_pair_sample``); ``runs_auto_parts`` gives the θ they report
(the mean of the runs' θ, as the trade-off's and the precision–recall's automatic point) with
the mean median and MAD it equals: θ is linear in them, so mean θ = mean median +
Φ⁻¹(1 − 10⁻⁶)·mean MAD/0.675.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vpr_explorer.method.thresholds import (
    AUTO_Z,
    MAD_PER_SIGMA,
    auto_global_threshold,
    pooled_pair_sample,
    training_pair_scores,
)

#: The largest similarity two L2-normalised descriptors can have (cosine).
MAX_SIMILARITY = 1.0


@dataclass(frozen=True)
class AutoParts:
    """The automatic θ and what it came from: median and MAD of the training scores."""

    theta: float
    median: float
    mad: float
    n_scores: int

    @property
    def rejects_everything(self) -> bool:
        """True when θ exceeds the largest possible similarity: no query can reach it."""
        return self.theta > MAX_SIMILARITY


def auto_parts(descriptors: np.ndarray, *, seed: int = 0, rows: np.ndarray | None = None) -> AutoParts:
    """The automatic θ of these training descriptors ``(n, D)`` with its median and MAD (the same scores as the
    protocols: ``training_pair_scores(descriptors, seed=seed, rows=rows)``; ``rows``: the training rows of a larger
    array, read without gathering them)."""
    s = np.asarray(training_pair_scores(descriptors, seed=seed, rows=rows), dtype=np.float64).ravel()
    med = float(np.median(s))
    mad = float(np.median(np.abs(s - med)))
    return AutoParts(auto_global_threshold(s), med, mad, int(s.size))


def runs_auto_parts(descriptors: np.ndarray, trains, *, seed: int = 0) -> AutoParts:
    """The automatic θ of a protocol run's splits as the protocols take it, and what it came from (module docstring).

    Args:
        descriptors: ``(n_images, D)``, the protocol's.
        trains: per run, the indices of its training images (``evaluation.draw_splits``' ``train``).
        seed: the protocol's seed (``pooled_pair_sample``'s).

    Returns:
        θ: the mean of the runs' θ (``PooledPairSample.theta``); median, MAD: their means over the
        runs; n_scores: the runs' training similarities, on average.
    """
    sample = pooled_pair_sample(descriptors, trains, seed=seed)
    thetas, medians, mads, counts = [], [], [], []
    for r in range(len(sample.trains)):
        s = np.asarray(sample.scores(r), dtype=np.float64)
        med = float(np.median(s))
        thetas.append(sample.theta(r))
        medians.append(med)
        mads.append(float(np.median(np.abs(s - med))))
        counts.append(s.size)
    return AutoParts(float(np.mean(thetas)), float(np.mean(medians)), float(np.mean(mads)), round(np.mean(counts)))


def rejects_all_note(parts: AutoParts, *, over: str = "the training images") -> str | None:
    """The sentence shown beside the automatic θ when it rejects everything; ``None`` when it does not."""
    if not parts.rejects_everything:
        return None
    return (f"**global θ, automatic = {parts.theta:.3f}**, from {over}: median {parts.median:.3f} + "
            f"{AUTO_Z:.2f} × MAD {parts.mad:.3f} / {MAD_PER_SIGMA:g} over {parts.n_scores:,} training similarities. That is "
            f"above {MAX_SIMILARITY:g}, the largest similarity two descriptors can have, so it **rejects every "
            "query**: its 0% recall and empty precision come from the threshold, not from the places. "
            "These descriptors' similarities spread too widely for the rule; set a global θ of your own on the "
            "**Query inspector** page to compare a global threshold.")
