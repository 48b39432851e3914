"""A database with its per-place thresholds, and what a method's answer for one query was.

``DatabaseModel``: the database images in places with their negative statistics and
thresholds (``views.numbers.fit_retrieval`` fits one on a dataset value); ``Verdict``:
what one method's answer to one query was, as the recorder and the Playback page count it.
Pure values over arrays.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from vpr_explorer.method.stats import NegativeStats
from vpr_explorer.method.thresholds import adaptive_k


@dataclass(frozen=True, eq=False)
class DatabaseModel:
    """Database images with their places, negative statistics and thresholds.

    Attributes:
        images: ``(n_db,)`` image indices (into the dataset) of the database.
        places: ``(n_db,)`` place of each database image.
        traversals: database traversal indices.
        stats: negative statistics of the database images.
        theta: ``{"simple": (P,), "weighted": (P,)}`` the paper's θ_p (k = 0).
        spread: ``(P,)`` s_p, standard deviation of each place's mixture.
        negative_mean: ``(P,)`` mean of each place's mixture.
        positive_mean: ``(P,)`` mean same-place score (NaN for a single-image place).
        auto: the automatic global threshold.
    """

    images: np.ndarray
    places: np.ndarray
    traversals: tuple[int, ...]
    n_places: int
    stats: NegativeStats
    theta: dict[str, np.ndarray]
    spread: np.ndarray
    negative_mean: np.ndarray
    positive_mean: np.ndarray
    auto: float

    def thresholds(self, k: float = 0.0, user_theta: float | None = None) -> dict[str, np.ndarray | float]:
        """Threshold mapping for ``retrieval``: θ_p(k) = θ_p + k·s_p, the automatic and user global θ."""
        th: dict[str, np.ndarray | float] = {name: t + k * self.spread for name, t in self.theta.items()}
        th["auto"] = self.auto
        if user_theta is not None:
            th["user"] = float(user_theta)
        return th

    @property
    def k_adaptive(self) -> np.ndarray:
        """Per-place k = clip((μ⁺ − μ⁻)/(2σ⁻), 1, 2)."""
        return adaptive_k(self.positive_mean, self.negative_mean, self.spread)


def database_rows(descriptors: np.ndarray, images: np.ndarray) -> np.ndarray:
    """``descriptors[images]``, as a view (no copy) when ``images`` is one ascending run.

    The database images of a dataset value come first and, group/step aside, in one run, so
    at 100k images this saves copying most of the descriptors on every query.
    """
    d = np.asarray(descriptors)
    images = np.asarray(images)
    if images.size and images[-1] - images[0] + 1 == images.size and np.all(np.diff(images) == 1):
        return d[images[0]:images[-1] + 1]
    return d[images]


class Verdict(StrEnum):
    """What one method's answer for one query was (``BETWEEN``: its right database images all lie between places; ``places.BETWEEN_PLACES_RULE``)."""

    RIGHT = "right"
    WRONG_ACCEPT = "wrong accept"
    WRONG_REJECT = "wrong reject"
    BETWEEN = "between places"
