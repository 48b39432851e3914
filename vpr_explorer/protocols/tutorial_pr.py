"""Precision–recall as VPR_Tutorial counts it (``evaluation/metrics.py``: ``createPR``, ``recallAt100precision``).

The similarity S is ``(n_queries, n_database)``, higher is more similar; ``hard`` and ``soft``
are bool ``(n_queries, n_database)`` positives. VPR_Tutorial's ``S_in``, ``GThard`` and
``GTsoft`` are ``(n_database, n_queries)``: they are these matrices transposed, and their
"per column" is "per row" here.

1. **Soft positives** (``soft`` given): every pair that is a soft positive and not a hard
   one gets the score min(S), the minimum of the whole matrix as given. That is how the
   tutorial "ignores" them, and it is not an exact ignore:

   * with ``matching="multi"`` such a pair is still a candidate, not right: it is a false
     positive at every threshold ≤ min(S), and the last threshold is exactly min(S)
     (below), so the curve's last point counts every pair, those included;
   * with ``matching="single"`` the lowered pair stops being its query's best match, so
     the next best database image is the detection instead (right or wrong): the query is
     not dropped. VPR_Tutorial itself refuses soft positives with ``matching="single"``
     (``ValueError``, "use dilated hard ground truth directly"); here the combination runs
     as the tutorial's code without that check counted it.

2. **Detections.**

   * ``Matching.MULTI``: every pair (q, i) is a candidate with score S[q, i]; it is right
     when ``hard[q, i]``. Positives P = the number of hard pairs.
   * ``Matching.SINGLE``: each query is one candidate, its best database image: the lowest
     index within ``TIE_TOLERANCE`` (1e-5) of the row's top score (``retrieval.top_answer``
     on S as float64); its score is the row's top score, and it is right when that image is
     a hard positive. ``np.argmax`` (the tutorial's) takes the first exact maximum: the two
     differ only where a row's top scores lie within 1e-5 of each other. Positives P = the
     queries with at least one hard positive; a query without one is still a candidate,
     and wrong.

3. **Thresholds**: ``n_thresholds`` (default 100, at least 2) values from the largest
   candidate score to the smallest, ``np.linspace(max, min, n_thresholds)``, so the first
   is the maximum and the last the minimum, exactly. They are spaced in the matrix's own
   dtype (float32 steps for a float32 S), as ``createPR``'s are under NumPy 2, and
   returned as float64. A candidate is detected at threshold t when its score ≥ t (exact;
   a score equal to t is detected).

4. **Counts and rates** at each threshold: TP = right detections, FP = wrong ones,
   precision = TP / (TP + FP), recall = TP / P. The first threshold is the largest score,
   so TP + FP ≥ 1 at every threshold on finite input; where it would be 0, precision is 1
   (nothing accepted: no mistake made). The tutorial divides there (under NumPy 2, 0/0 on
   ``np.int64`` counts, nan with a RuntimeWarning), a case its own thresholds never reach.

5. **Curve**: the point (recall 0, precision 1) first, then one point per threshold:
   ``n_thresholds + 1`` points, ``precision[i + 1]`` and ``recall[i + 1]`` at
   ``thresholds[i]``.

6. **Summaries**: **AUC** = the trapezoid rule over the points in threshold order,
   Σᵢ (Rᵢ − Rᵢ₋₁)(Pᵢ + Pᵢ₋₁)/2 (the tutorial's ``np.trapz(P, R)``, start point included);
   **R@100P** = the largest recall among points whose precision is exactly 1 (FP = 0), the
   start point included, so 0 when the first detection is wrong.

Everything is counted once: the candidate scores and the right ones' are sorted, and each
threshold's detections and TP are what ``np.searchsorted`` finds at or above it in each.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.retrieval import top_answer

#: Thresholds of a curve when none are asked for (the tutorial's ``n_thresh``).
N_THRESHOLDS = 100


class Matching(StrEnum):
    """What counts as a detection."""

    SINGLE = "single"  # the best database image of each query
    MULTI = "multi"  # every query–database pair


@dataclass(frozen=True, eq=False)
class TutorialPR:
    """A VPR_Tutorial precision–recall curve (module doc for every definition).

    Attributes:
        precision: ``(n_thresholds + 1,)``; ``precision[0] = 1`` is the start point.
        recall: ``(n_thresholds + 1,)``; ``recall[0] = 0`` is the start point.
        thresholds: ``(n_thresholds,)`` decreasing, from the largest candidate score to the
            smallest; ``precision[i + 1]`` and ``recall[i + 1]`` are counted at ``thresholds[i]``.
        matching: single-best-match or multi-match.
        soft_ignored: whether soft positives were given (and their pairs lowered to min(S)).
        n_positives: the recall denominator P.
        auc: trapezoid area under precision over recall.
        recall_at_100_precision: the largest recall at precision exactly 1.
    """

    precision: np.ndarray
    recall: np.ndarray
    thresholds: np.ndarray
    matching: Matching
    soft_ignored: bool
    n_positives: int
    auc: float
    recall_at_100_precision: float

    def __post_init__(self) -> None:
        for name in ("precision", "recall", "thresholds"):
            getattr(self, name).setflags(write=False)

    def to_dict(self) -> dict:
        """JSON-ready values; a number that is not finite is ``None``."""
        return {
            "matching": self.matching.value,
            "soft_ignored": self.soft_ignored,
            "n_positives": self.n_positives,
            "auc": _num(self.auc),
            "recall_at_100_precision": _num(self.recall_at_100_precision),
            "thresholds": [_num(x) for x in self.thresholds],
            "precision": [_num(x) for x in self.precision],
            "recall": [_num(x) for x in self.recall],
        }


def tutorial_pr(similarity: np.ndarray, hard: np.ndarray, soft: np.ndarray | None = None, *,
                matching: str = Matching.MULTI, n_thresholds: int = N_THRESHOLDS) -> TutorialPR:
    """VPR_Tutorial's precision–recall curve, AUC and R@100P of ``(n_queries, n_database)`` scores.

    Args:
        similarity: ``(n_queries, n_database)`` finite scores, higher is more similar
            (the transpose of the tutorial's ``S_in``).
        hard: ``(n_queries, n_database)`` bool, the right pairs (``GThard`` transposed).
        soft: ``(n_queries, n_database)`` bool or ``None``; pairs in ``soft`` and not in
            ``hard`` get the score min(S) (``GTsoft`` transposed).
        matching: ``"single"`` or ``"multi"`` (``Matching``).
        n_thresholds: thresholds from the largest candidate score to the smallest, 2 or more.
    """
    s, hard, soft, matching = _check(similarity, hard, soft, matching, n_thresholds)
    lowered = s.astype(np.float64)
    if soft is not None:
        lowered[soft & ~hard] = lowered.min()
    if matching == Matching.SINGLE:
        n_positives = int(np.count_nonzero(hard.any(axis=1)))
        answer = top_answer(lowered)
        scores = lowered.max(axis=1)
        right = hard[np.arange(len(answer)), answer]
    else:
        n_positives = int(np.count_nonzero(hard))
        scores = lowered.ravel()
        right = hard.ravel()

    # the tutorial's np.linspace(S.max(), S.min(), n) on S in its own dtype: the ends are
    # values of that dtype, so casting them back is exact and the steps round as theirs do
    kind = s.dtype.type
    thresholds = np.linspace(kind(scores.max()), kind(scores.min()), n_thresholds).astype(np.float64)

    tp, detected = _counts(scores, right, thresholds)
    precision = np.ones(n_thresholds + 1)
    recall = np.zeros(n_thresholds + 1)
    np.divide(tp, detected, out=precision[1:], where=detected > 0)
    recall[1:] = tp / n_positives
    auc = float(np.sum(np.diff(recall) * (precision[1:] + precision[:-1]) / 2.0))
    perfect = np.r_[True, tp == detected]
    return TutorialPR(
        precision=precision, recall=recall, thresholds=thresholds, matching=matching,
        soft_ignored=soft is not None, n_positives=n_positives, auc=auc,
        recall_at_100_precision=float(recall[perfect].max()),
    )


def _counts(scores: np.ndarray, right: np.ndarray, thresholds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(TP, detections)`` at each threshold, a detection being a score ≥ the threshold."""
    every = np.sort(scores)
    rights = np.sort(scores[right])
    # searchsorted(..., side="left") counts the scores < t; the rest are detected
    detected = every.size - np.searchsorted(every, thresholds, side="left")
    tp = rights.size - np.searchsorted(rights, thresholds, side="left")
    return tp, detected


def _check(similarity, hard, soft, matching, n_thresholds):
    s = np.asarray(similarity)
    if s.ndim != 2:
        raise VPRInputError(f"similarity: must be 2-D (n_queries, n_database); got shape {s.shape}")
    if s.dtype == bool or not (np.issubdtype(s.dtype, np.floating) or np.issubdtype(s.dtype, np.integer)):
        raise VPRInputError(f"similarity: must hold real numbers (float or int); got dtype {s.dtype}")
    if s.size == 0:
        raise VPRInputError(f"similarity: shape {s.shape} holds no pair; give at least one query "
                            f"and one database image")
    bad = ~np.isfinite(s)
    if bad.any():
        q, i = np.argwhere(bad)[0]
        raise VPRInputError(f"similarity: holds {np.count_nonzero(bad)} NaN or infinite score(s), the first at "
                            f"query {q}, database image {i}; thresholds run from the largest score to the "
                            f"smallest, so every score must be finite")
    truths = {"hard": hard} if soft is None else {"hard": hard, "soft": soft}
    for name, value in truths.items():
        value = np.asarray(value)
        if value.shape != s.shape:
            raise VPRInputError(f"{name}: shape {value.shape} differs from similarity's {s.shape}; both are "
                                f"(n_queries, n_database), the transpose of VPR_Tutorial's GThard/GTsoft")
        if value.dtype != bool:
            raise VPRInputError(f"{name}: must be a bool array (True where the database image is a positive of "
                                f"the query); got dtype {value.dtype}: convert it, e.g. `{name} != 0`")
        truths[name] = value
    if not truths["hard"].any():
        raise VPRInputError("hard: no query has a positive, so recall (TP / positives) is undefined; give ground "
                            "truth with at least one True pair")
    if matching not in {m.value for m in Matching}:
        raise VPRInputError(f"matching={matching!r}: choose {' or '.join(m.value for m in Matching)}")
    if isinstance(n_thresholds, bool) or not isinstance(n_thresholds, (int, np.integer)) or n_thresholds < 2:
        raise VPRInputError(f"n_thresholds={n_thresholds!r}: must be a whole number, 2 or more (e.g. 100)")
    return s, truths["hard"], truths.get("soft"), Matching(matching)


def _num(x) -> float | None:
    return float(x) if np.isfinite(x) else None
