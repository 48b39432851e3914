"""Precision–recall: how the field judges a threshold (VPR_Tutorial ``evaluation/metrics.py``).

Every query has one top-1 answer. A threshold accepts or rejects it, and over a sweep of
the threshold (single-best-match VPR, as ``createPR(..., matching='single')`` counts):

* accepted and right → a true positive (TP); accepted and wrong → a false positive (FP).
  A query of a place that is not in the database (**unknown**) has no right answer, so
  accepting it is always a false positive;
* recall = TP / n_known, n_known the queries with a right answer in the database: a known
  query that is rejected, or accepted with a wrong top-1, is a miss (a wrong accepted
  top-1 is a miss *and* a false positive);
* precision = TP / (TP + FP), and **1 when nothing is accepted**: the convention of
  VPR_Tutorial's ``createPR`` (``P = [1]``, ``R = [0]``) and of sklearn's
  ``precision_recall_curve``. Every curve starts at that point, recall 0 and precision 1.

Summaries of a curve, over its points (the start point included):

* **AUC**: the trapezoid rule over recall, ∫ P dR = Σᵢ (Rᵢ − Rᵢ₋₁)(Pᵢ + Pᵢ₋₁)/2, the
  points taken in threshold order. It is VPR_Tutorial's ``np.trapz(P, R)`` over exact
  points instead of 100 evenly spaced thresholds, and sklearn's ``auc(recall, precision)``
  over ``precision_recall_curve`` once recall is counted over known queries (see below).
  Not average precision: AP's step rule and this trapezoid differ where precision moves.
* **R@100P** (``recallAt100precision``): the largest recall among points of precision
  exactly 1 (TP = accepted); **R@99P**: precision ≥ 0.99, tested in integers
  (100·TP ≥ 99·accepted). Both are 0 when the first answer accepted is wrong.
* **max F1**: the largest 2PR/(P + R) = 2·TP/(accepted + n_known) (0 at recall 0), with
  the threshold that reaches it: the highest one, where several do.

How this differs from sklearn's ``precision_recall_curve(right, score)``: sklearn counts
recall over the *right* queries (TP + FN = queries whose top-1 is right), so its curve
reaches recall 1; here a known query whose top-1 is wrong is a miss too, so recall ends
at the method's Recall@1 over known queries. The points and precision are the same; recall
(and the AUC) is sklearn's times n_right / n_known.

Two kinds of sweep:

* **one global θ** (``pr_curve``): a query is accepted when its score ≥ θ. With the raw
  rule and one θ the answer never changes with θ (the top place stays while anything
  does), so a query is a (score, right, known) triple: score = its top raw score (the
  top image score at the image level), right = the baseline's rank 1.
* **the per-place family** θ_p(k) = θ_p + k·s_p (``family_pr``): the answer changes with
  k (the raw rule promotes the next place when a wrong top one is dropped; the margin
  rule re-ranks places by raw_p − θ_p(k)), so each point of a k grid is counted exactly
  with ``retrieval``'s own rules (``ranking_scores``, ``top_answer``,
  ``pessimistic_rank``: ties within ``TIE_TOLERANCE`` count against the query).

**Ties in the score.** A threshold comparison is exact (score ≥ θ, as ``retrieval``
compares with a threshold), so queries of equal score are accepted together: the curve
has one point per distinct score, whatever the order of the queries (sklearn does the
same). Scores that differ by less than ``TIE_TOLERANCE`` are distinct thresholds.

**Pooling runs.** Counts add: a curve over several splits sums TP and accepted at each
common threshold (θ, or k), each split scored with its own training thresholds; see
``pool_points``, ``pooled_family_pr`` and ``pr_rows``.

Every array is ``(n_queries,)``, or ``(n_queries, n_places)`` where places are named.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.retrieval import (
    METHODS_BY_KEY,
    TIE_TOLERANCE,
    Outcome,
    Rule,
)

#: Points of a per-place family curve (k values) when no grid is given.
FAMILY_POINTS = 200
#: Share of the k range added at each end of the default grid, so that the ends are
#: "nothing accepted" and "every acceptable query accepted" despite the rounding of
#: θ_p + k·s_p at the extreme k.
_GRID_PAD = 0.01
#: Query rows scored at a time by ``family_counts`` (times n_places: the float64 matrix held).
_BLOCK_CELLS = 1 << 22
#: ``family_counts`` scores a k in one dense pass when more than this share of the query × place
#: pairs are kept there, and only the kept pairs below it (a dense pass costs ~1/25 of scoring
#: every pair one by one).
_DENSE_KEPT = 0.04


# --------------------------------------------------------------------------- values


@dataclass(frozen=True)
class PRPoint:
    """One operating point: how many queries a threshold accepted and how many of those are right.

    ``threshold`` is θ, k (per-place family), ``-inf`` for a method that accepts every
    query, or NaN where the point pools runs of different θ.
    """

    threshold: float
    tp: int
    accepted: int
    n_known: int
    n_unknown: int

    @property
    def precision(self) -> float:
        """TP / accepted; 1 when nothing is accepted (the module's convention)."""
        return self.tp / self.accepted if self.accepted else 1.0

    @property
    def recall(self) -> float:
        """TP / n_known; NaN when no query is known."""
        return self.tp / self.n_known if self.n_known else math.nan

    @property
    def f1(self) -> float:
        return 2 * self.tp / (self.accepted + self.n_known) if self.accepted + self.n_known else math.nan

    def to_dict(self) -> dict:
        return {"threshold": _num(self.threshold), "precision": _num(self.precision), "recall": _num(self.recall),
                "tp": self.tp, "accepted": self.accepted, "n_known": self.n_known, "n_unknown": self.n_unknown}

    @classmethod
    def from_dict(cls, d: Mapping) -> PRPoint:
        """``to_dict`` back (a ``None`` threshold, written for ±inf or NaN, as NaN)."""
        return cls(_from_num(d["threshold"]), int(d["tp"]), int(d["accepted"]), int(d["n_known"]),
                   int(d["n_unknown"]))


@dataclass(frozen=True, eq=False)
class PRCurve:
    """A precision–recall curve: counts at every threshold of a sweep, nothing accepted first.

    Attributes:
        param: what ``threshold`` holds: ``"θ"`` (a score: accept score ≥ θ) or ``"k"``
            (the per-place family θ_p + k·s_p).
        threshold: ``(n_points,)`` decreasing; ``threshold[0] = +inf`` is the start point
            (nothing accepted, precision 1 by convention).
        tp: ``(n_points,)`` accepted queries whose top-1 is right.
        accepted: ``(n_points,)`` accepted queries (FP = accepted − tp).
        n_known: queries with a right answer in the database (recall's denominator).
        n_unknown: queries without one: their every acceptance is a false positive.
        auc, r_at_100p, r_at_99p, max_f1, max_f1_threshold: the summaries of the module
            doc (NaN when no query is known).
    """

    param: str
    threshold: np.ndarray
    tp: np.ndarray
    accepted: np.ndarray
    n_known: int
    n_unknown: int
    auc: float
    r_at_100p: float
    r_at_99p: float
    max_f1: float
    max_f1_threshold: float

    @property
    def precision(self) -> np.ndarray:
        """``(n_points,)`` TP / accepted, 1 where nothing is accepted."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.accepted > 0, self.tp / np.maximum(self.accepted, 1), 1.0)

    @property
    def recall(self) -> np.ndarray:
        """``(n_points,)`` TP / n_known (NaN when no query is known)."""
        return self.tp / self.n_known if self.n_known else np.full(len(self.tp), np.nan)

    @property
    def f1(self) -> np.ndarray:
        """``(n_points,)`` 2·TP / (accepted + n_known)."""
        den = self.accepted + self.n_known
        return np.where(den > 0, 2 * self.tp / np.maximum(den, 1), np.nan)

    def point(self, threshold: float) -> PRPoint:
        """The point of one threshold: for θ, the queries with score ≥ θ; for k, a k of the grid."""
        t = float(threshold)
        if math.isnan(t):
            raise VPRInputError("threshold is NaN: give a number (θ, or a k of the grid)")
        if self.param == "θ":
            i = int(np.flatnonzero(self.threshold >= t)[-1])  # the start point's +inf always qualifies
        else:
            hit = np.flatnonzero(self.threshold == t)
            if not len(hit):
                raise VPRInputError(f"k={t!r} is not a point of this curve's grid; pass it in ks")
            i = int(hit[0])
        return PRPoint(t, int(self.tp[i]), int(self.accepted[i]), self.n_known, self.n_unknown)

    def to_dict(self, max_points: int = 201) -> dict:
        """JSON-ready points (at most ``max_points``, always keeping the start, the end and max F1) and summaries."""
        idx = _thin(len(self.tp), max_points, keep=[int(np.nanargmax(self.f1))] if self.n_known else [])
        return {
            "param": self.param, "n_known": self.n_known, "n_unknown": self.n_unknown,
            "auc": _num(self.auc), "r_at_100p": _num(self.r_at_100p), "r_at_99p": _num(self.r_at_99p),
            "max_f1": _num(self.max_f1), "max_f1_threshold": _num(self.max_f1_threshold),
            "threshold": [_num(x) for x in self.threshold[idx]],
            "precision": [_num(x) for x in self.precision[idx]],
            "recall": [_num(x) for x in self.recall[idx]],
            "tp": [int(x) for x in self.tp[idx]], "accepted": [int(x) for x in self.accepted[idx]],
        }

    @classmethod
    def from_dict(cls, d: Mapping) -> PRCurve:
        """``to_dict`` back: its points (every point, or the thinned ones it kept) and its summaries as written.

        The start point's threshold (``None`` in JSON) is +inf again; another ``None`` threshold is NaN.
        """
        threshold = np.array([_from_num(x) for x in d["threshold"]], dtype=np.float64)
        if len(threshold) and np.isnan(threshold[0]):
            threshold[0] = np.inf
        return cls(str(d["param"]), threshold, np.asarray(d["tp"], dtype=np.int64),
                   np.asarray(d["accepted"], dtype=np.int64), int(d["n_known"]), int(d["n_unknown"]),
                   *(_from_num(d[k]) for k in ("auc", "r_at_100p", "r_at_99p", "max_f1", "max_f1_threshold")))


def _num(x) -> float | None:
    return float(x) if x is not None and np.isfinite(x) else None


def _from_num(x) -> float:
    return math.nan if x is None else float(x)


def _thin(n: int, max_points: int, keep: Sequence[int] = ()) -> np.ndarray:
    if n <= max_points:
        return np.arange(n)
    return np.unique(np.r_[np.round(np.linspace(0, n - 1, max(2, max_points - len(keep)))).astype(np.int64),
                           np.asarray(keep, dtype=np.int64)])


def curve_from_counts(param: str, threshold, tp, accepted, n_known: int, n_unknown: int) -> PRCurve:
    """A ``PRCurve`` from counts at thresholds in decreasing order, the start point first.

    Args:
        threshold: ``(n_points,)`` decreasing; the first point must accept nothing.
        tp, accepted: ``(n_points,)`` counts at each threshold.
    """
    threshold = np.array(threshold, dtype=np.float64)
    tp = np.array(tp, dtype=np.int64)
    accepted = np.array(accepted, dtype=np.int64)
    if not (threshold.shape == tp.shape == accepted.shape) or threshold.ndim != 1 or len(threshold) == 0:
        raise VPRInputError(f"threshold {threshold.shape}, tp {tp.shape}, accepted {accepted.shape}: give three "
                            "equal-length 1-d arrays")
    if accepted[0] != 0:
        raise VPRInputError("the first point of a curve must accept nothing (precision 1, recall 0)")
    n_known, n_unknown = int(n_known), int(n_unknown)
    if (tp > accepted).any() or (tp > n_known).any() or (accepted > n_known + n_unknown).any():
        raise VPRInputError("counts out of range: need tp ≤ accepted ≤ n_known + n_unknown and tp ≤ n_known")
    if not n_known:
        nan = math.nan
        summary = (nan, nan, nan, nan, nan)
    else:
        precision = np.where(accepted > 0, tp / np.maximum(accepted, 1), 1.0)
        recall = tp / n_known
        auc = float(np.sum(np.diff(recall) * (precision[1:] + precision[:-1]) / 2))
        r100 = float(recall[tp == accepted].max())
        r99 = float(recall[100 * tp >= 99 * accepted].max())
        f1 = 2 * tp / (accepted + n_known)
        best = int(np.argmax(f1))  # the first maximum: the highest threshold reaching it
        summary = (auc, r100, r99, float(f1[best]), float(threshold[best]))
    for a in (threshold, tp, accepted):
        a.setflags(write=False)
    return PRCurve(param, threshold, tp, accepted, n_known, n_unknown, *summary)


# --------------------------------------------------------------------------- one global threshold


def _check_queries(right, known, n: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    right = np.asarray(right)
    known = np.asarray(known)
    if right.dtype != bool or known.dtype != bool or right.ndim != 1 or right.shape != known.shape:
        raise VPRInputError(f"right {right.shape} {right.dtype} and known {known.shape} {known.dtype}: give two "
                            "bool arrays of one entry per query")
    if n is not None and len(right) != n:
        raise VPRInputError(f"{n} scores but {len(right)} right/known flags: give one per query")
    if (right & ~known).any():
        i = int(np.flatnonzero(right & ~known)[0])
        raise VPRInputError(f"query {i} is right but not known: a query without a right answer in the database "
                            "cannot be answered right")
    return right, known


def pr_curve(score, right, known) -> PRCurve:
    """The precision–recall curve of one global threshold swept over every distinct score.

    Args:
        score: ``(n_queries,)`` the value the threshold is compared with (accept score ≥ θ):
            the top raw score for a global θ. ``-inf``: never accepted (e.g. no database image).
        right: ``(n_queries,)`` bool, the query's top-1 is right (the place baseline's
            rank 1, ties against the query): what an accepted query counts as.
        known: ``(n_queries,)`` bool, the query has a right answer in the database.
    Returns:
        a ``PRCurve`` with ``param="θ"``: one point per distinct finite score (accepting
        every query scoring at least it), after the start point ``θ = +inf``.
    """
    score = np.asarray(score, dtype=np.float64)
    if score.ndim != 1:
        raise VPRInputError(f"score has shape {score.shape}: give one score per query")
    right, known = _check_queries(right, known, len(score))
    if np.isnan(score).any() or (score == np.inf).any():
        raise VPRInputError("score holds NaN or +inf: give a finite score per query (-inf for never accepted)")
    live = score > -np.inf
    order = np.argsort(-score[live], kind="stable")
    v = score[live][order]
    ends = np.flatnonzero(np.r_[v[1:] != v[:-1], True]) if len(v) else np.empty(0, dtype=np.int64)
    tp = np.cumsum(right[live][order])[ends] if len(v) else np.empty(0, dtype=np.int64)
    return curve_from_counts("θ", np.r_[np.inf, v[ends]], np.r_[0, tp], np.r_[0, ends + 1],
                             int(known.sum()), int((~known).sum()))


def operating_point(accepted, right, known, threshold: float = math.nan) -> PRPoint:
    """Precision and recall of a method at its own threshold.

    Args:
        accepted, right: ``(n_queries,)`` bool, an ``Outcome``'s ``accepted`` and ``right``.
        known: ``(n_queries,)`` bool, the query has a right answer in the database.
        threshold: recorded with the point (θ, k = 0, or ``-inf`` for no threshold).
    """
    accepted = np.asarray(accepted)
    right, known = _check_queries(right, known)
    if accepted.shape != right.shape or accepted.dtype != bool:
        raise VPRInputError(f"accepted {accepted.shape} {accepted.dtype}: give a bool array of one entry per query")
    if (right & ~accepted).any():
        raise VPRInputError("a query is right but not accepted: right means accepted with a right top-1")
    return PRPoint(float(threshold), int(right.sum()), int(accepted.sum()), int(known.sum()), int((~known).sum()))


def pool_points(points: Sequence[PRPoint], threshold: float | None = None) -> PRPoint:
    """The operating point of several runs: their counts summed (threshold: given, or the mean)."""
    if not points:
        raise VPRInputError("pool_points: give at least one point")
    t = float(np.mean([p.threshold for p in points])) if threshold is None else float(threshold)
    return PRPoint(t, *(sum(getattr(p, f) for p in points) for f in ("tp", "accepted", "n_known", "n_unknown")))


# --------------------------------------------------------------------------- the per-place family


def _check_family(raw, theta, spread, correct, rule) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, Rule]:
    raw = np.asarray(raw)  # float32 raw_p (max of float32 scores) is exact: widened a block at a time
    correct = np.asarray(correct)
    if raw.ndim != 2 or raw.dtype.kind != "f" or correct.shape != raw.shape or correct.dtype != bool:
        raise VPRInputError(f"raw {raw.shape} {raw.dtype} and correct {correct.shape} {correct.dtype}: give "
                            "(n_queries, n_places) float scores and a bool array of the same shape")
    n_places = raw.shape[1]
    try:
        theta = np.broadcast_to(np.asarray(theta, dtype=np.float64), (n_places,))
        spread = np.broadcast_to(np.asarray(spread, dtype=np.float64), (n_places,))
    except ValueError:
        raise VPRInputError(f"theta and spread must be (n_places,) = ({n_places},) or scalars") from None
    if (spread < 0).any():
        raise VPRInputError("spread s_p < 0: give mixture standard deviations (thresholds.mixture_spread)")
    try:
        rule = Rule(rule)
    except ValueError:
        raise VPRInputError(f"rule {rule!r}: choose margin or raw") from None
    if rule is Rule.NONE:
        raise VPRInputError("rule none has no threshold to sweep: choose margin or raw")
    return raw, theta, spread, correct, rule


def family_range(raw, theta, spread) -> tuple[float, float]:
    """The k range over which acceptance changes: ``(min, max)`` over queries of κ_q.

    κ_q = max_p (raw_p − θ_p)/s_p over places with s_p > 0 is the largest k at which the
    query is still accepted (θ_p(k) ≤ raw_p for some p): above max κ_q nothing is
    accepted, below min κ_q every query that can be is. Places with s_p = 0 do not move
    with k and are left out. ``(0.0, 0.0)`` when no query has a finite κ_q.
    """
    raw = np.asarray(raw)
    theta = np.broadcast_to(np.asarray(theta, dtype=np.float64), raw.shape[1:])
    spread = np.broadcast_to(np.asarray(spread, dtype=np.float64), raw.shape[1:])
    moving = np.flatnonzero((spread > 0) & np.isfinite(theta))
    if not len(moving) or raw.shape[0] == 0:
        return (0.0, 0.0)
    rows = max(1, _BLOCK_CELLS // len(moving))
    with np.errstate(invalid="ignore"):
        kappa = np.concatenate([((raw[lo:lo + rows][:, moving] - theta[moving]) / spread[moving]).max(axis=1)
                                for lo in range(0, raw.shape[0], rows)])
    kappa = kappa[np.isfinite(kappa)]
    return (float(kappa.min()), float(kappa.max())) if kappa.size else (0.0, 0.0)


def family_grid(lo: float, hi: float, n: int = FAMILY_POINTS) -> np.ndarray:
    """``(≤ n + 1,)`` k values, decreasing: ``n`` evenly over [lo, hi] padded 1% each side, and k = 0."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 2:
        raise VPRInputError(f"n={n!r}: a family curve needs at least 2 values of k")
    if not (np.isfinite(lo) and np.isfinite(hi)) or lo > hi:
        raise VPRInputError(f"k range ({lo}, {hi}): give finite lo ≤ hi")
    pad = _GRID_PAD * (hi - lo) if hi > lo else 0.5
    return np.unique(np.r_[np.linspace(lo - pad, hi + pad, n), 0.0])[::-1]


def _check_ks(ks) -> np.ndarray:
    ks = np.asarray(ks, dtype=np.float64).reshape(-1)
    if not ks.size or not np.isfinite(ks).all():
        raise VPRInputError(f"ks={ks.tolist()}: give finite values of k")
    return np.unique(ks)[::-1]


def family_counts(raw, theta, spread, correct, rule: Rule | str, ks) -> tuple[np.ndarray, np.ndarray]:
    """``(tp, accepted)``, each ``(len(ks),)``: the counts at each k under θ_p(k) = θ_p + k·s_p.

    At each k this is ``retrieval.score_queries`` for one place-level method with the
    thresholds θ_p + k·s_p (``thresholds.threshold_family``): places below θ_p(k) dropped,
    the rest ranked by ``rule``; a query is accepted when a place is kept and right when
    its best right place is at pessimistic rank 1 (a wrong place within ``TIE_TOLERANCE``
    of it makes it wrong).

    Args:
        raw: ``(n_queries, n_places)`` raw_p (``retrieval.place_scores``).
        theta, spread: ``(n_places,)`` θ_p and s_p.
        correct: ``(n_queries, n_places)`` bool, each query's right places (none: unknown).
        rule: margin or raw.
        ks: the k values, in the order the counts come back.
    """
    raw, theta, spread, correct, rule = _check_family(raw, theta, spread, correct, rule)
    ks = np.asarray(ks, dtype=np.float64).reshape(-1)
    if not np.isfinite(ks).all():
        raise VPRInputError(f"ks={ks.tolist()}: give finite values of k")
    order = np.argsort(ks, kind="stable")
    # θ_p(k) for every k, ascending: thresholds.threshold_family's θ + k·s, the same products and sums;
    # a NaN θ_p(k) keeps no place (as raw ≥ NaN is false), and neither does +inf
    th = theta[None, :] + ks[order][:, None] * spread[None, :]
    th[np.isnan(th)] = np.inf
    tp = np.zeros(len(ks), dtype=np.int64)
    acc = np.zeros(len(ks), dtype=np.int64)
    rows = max(1, _BLOCK_CELLS // max(1, raw.shape[1]))
    for lo in range(0, raw.shape[0], rows):
        r, c = raw[lo:lo + rows].astype(np.float64), correct[lo:lo + rows]
        t, a = _block_counts(r, c, th, rule)
        tp[order] += t
        acc[order] += a
    return tp, acc


def _block_counts(r, c, th, rule: Rule) -> tuple[np.ndarray, np.ndarray]:
    """``family_counts`` of one block of queries at every k (ascending).

    Args:
        r: ``(n, P)`` float64 raw_p; c: ``(n, P)`` their right places.
        th: ``(K, P)`` θ_p(k), rows in ascending k (so each column is non-decreasing: s_p ≥ 0
            and rounding is monotone).

    The comparisons of ``ranking_scores``, ``top_answer`` and ``pessimistic_rank`` at each
    k, without forming the K × n × P scores: a query is accepted when some place is kept
    (raw_p ≥ θ_p(k)), and right when its best kept right place scores b and no wrong kept
    place scores ≥ b − ``TIE_TOLERANCE`` (any(xᵢ ≥ y) ⟺ max xᵢ ≥ y, the same float
    comparison). As θ_p(k) grows with k, place p is kept for the first m_qp values of k
    exactly, m_qp = #{k : θ_p(k) ≤ raw_qp} (a binary search of the same floats). At the low
    k where more than ``_DENSE_KEPT`` of the pairs are kept, each k gets a dense pass
    (``_dense_counts``, the same comparisons); above, only the kept (k, query, place)
    triples are scored (about 1% of K·n·P on Nordland in all), unless more than
    ``_BLOCK_CELLS`` of them are left (then dense passes throughout).
    """
    n, n_places = r.shape
    n_k = len(th)
    th_t, r_t = np.ascontiguousarray(th.T), np.ascontiguousarray(r.T)
    kept = np.empty((n_places, n), dtype=np.int64)  # m_qp, place-major
    for p in range(n_places):
        kept[p] = np.searchsorted(th_t[p], r_t[p], side="right")
    # pairs kept at the i-th k: those with m_qp > i
    at_k = np.cumsum(np.bincount(kept.ravel(), minlength=n_k + 1)[::-1])[::-1][1:]
    dense = int((at_k > _DENSE_KEPT * n * n_places).sum())  # the first k's (at_k does not grow with k)
    if np.clip(kept - dense, 0, None).sum() > _BLOCK_CELLS:
        dense = n_k
    tp = np.zeros(n_k, dtype=np.int64)
    if dense:
        tp[:dense] = _dense_counts(r, c, th[:dense], rule)[0]
    # accepted at the i-th k: some place kept there, i.e. i < max_p m_qp
    most = np.bincount(kept.max(axis=0), minlength=n_k + 1)
    acc = np.cumsum(most[::-1])[::-1][1:]
    if dense == n_k:
        return tp, acc
    p, q = np.nonzero(kept > dense)
    m = kept[p, q] - dense
    k_of = dense + np.arange(m.sum()) - np.repeat(np.cumsum(m) - m, m)  # each pair at k = dense … m_qp − 1
    q, p = np.repeat(q, m), np.repeat(p, m)
    raw_qp = r[q, p]
    score = raw_qp - th[k_of, p] if rule is Rule.MARGIN else raw_qp
    right = c[q, p]
    cell = k_of * n + q  # (k, query) flat
    best = np.full(n_k * n, -np.inf)
    np.maximum.at(best, cell[right], score[right])
    top_wrong = np.full(n_k * n, -np.inf)
    np.maximum.at(top_wrong, cell[~right], score[~right])
    best, top_wrong = best.reshape(n_k, n)[dense:], top_wrong.reshape(n_k, n)[dense:]
    tp[dense:] = (np.isfinite(best) & ~(top_wrong >= best - TIE_TOLERANCE)).sum(axis=1)
    return tp, acc


def _dense_counts(r, c, th, rule: Rule) -> tuple[np.ndarray, np.ndarray]:
    """``_block_counts`` one k at a time on the whole block: two or three passes over it per k.

    The right places (one, or a few with a frame tolerance) are scored apart; the wrong ones
    give one maximum per query.
    """
    wrong = np.where(c, -np.inf, r)
    qi, pi = np.nonzero(c)  # row-major: each query's right places together
    has = np.flatnonzero(np.r_[True, qi[1:] != qi[:-1]]) if len(qi) else np.empty(0, dtype=np.int64)
    rq = r[qi, pi]
    buf = np.empty_like(r) if rule is Rule.MARGIN else None
    best = np.full(len(r), -np.inf)
    tp = np.zeros(len(th), dtype=np.int64)
    acc = np.zeros(len(th), dtype=np.int64)
    for i, t in enumerate(th):
        if rule is Rule.MARGIN:
            np.subtract(wrong, t, out=buf)  # ≥ 0 exactly where raw ≥ θ (the sign of a float difference is exact)
            top_wrong = buf.max(axis=1)
            top_wrong[top_wrong < 0] = -np.inf  # no wrong place kept
            right = np.where(rq >= t[pi], rq - t[pi], -np.inf)
        else:
            top_wrong = np.where(wrong >= t, wrong, -np.inf).max(axis=1)
            right = np.where(rq >= t[pi], rq, -np.inf)
        best.fill(-np.inf)
        if len(qi):
            best[qi[has]] = np.maximum.reduceat(right, has)
        found = np.isfinite(best)
        acc[i] = int((found | np.isfinite(top_wrong)).sum())
        tp[i] = int((found & ~(top_wrong >= best - TIE_TOLERANCE)).sum())
    return tp, acc


def family_pr(raw, theta, spread, correct, rule: Rule | str, ks=None, *, n: int = FAMILY_POINTS) -> PRCurve:
    """The precision–recall curve of a per-place method over its family θ_p(k) = θ_p + k·s_p.

    Args:
        raw, theta, spread, correct, rule: as for ``family_counts``.
        ks: the k values; default ``family_grid`` of ``n`` values over ``family_range``,
            with k = 0 (the method's own θ_p: ``curve.point(0.0)``).
    Returns:
        a ``PRCurve`` with ``param="k"``: the start point (k = +inf, nothing accepted by
        convention), then k decreasing. Recall need not grow as k falls (with the raw
        rule a lower k can keep a wrong place above the right one); the AUC is then the
        trapezoid along the curve as drawn, a backward step subtracting its area.
    """
    return pooled_family_pr([(raw, theta, spread, correct)], rule, ks, n=n)


def pooled_family_pr(parts: Sequence[tuple], rule: Rule | str, ks=None, *, n: int = FAMILY_POINTS) -> PRCurve:
    """One family curve over several runs: ``(raw, theta, spread, correct)`` each, counts summed at each k.

    Each run keeps its own θ_p and s_p (from its own training images); k is the common
    parameter. The default grid spans the union of the runs' ``family_range``.
    """
    if not parts:
        raise VPRInputError("pooled_family_pr: give at least one run")
    if ks is None:
        ranges = [family_range(raw, theta, spread) for raw, theta, spread, _ in parts]
        ks = family_grid(min(r[0] for r in ranges), max(r[1] for r in ranges), n)
    ks = _check_ks(ks)
    tp = np.zeros(len(ks), dtype=np.int64)
    acc = np.zeros(len(ks), dtype=np.int64)
    n_known = n_unknown = 0
    for raw, theta, spread, correct in parts:
        t, a = family_counts(raw, theta, spread, correct, rule, ks)
        tp += t
        acc += a
        known = np.asarray(correct).any(axis=1)
        n_known += int(known.sum())
        n_unknown += int((~known).sum())
    return curve_from_counts("k", np.r_[np.inf, ks], np.r_[0, tp], np.r_[0, acc], n_known, n_unknown)


# --------------------------------------------------------------------------- per method, over runs


@dataclass(frozen=True, eq=False)
class PRSplit:
    """What one run gives the precision–recall rows.

    Attributes:
        outcomes: method key -> ``Outcome`` (``retrieval.score_queries``).
        known: ``(n_queries,)`` bool, the query has a right answer in the database.
        top: ``(n_queries,)`` each query's top raw score (the global θ's score; also the top
            image score when every database image is in a place).
        raw, correct: ``(n_queries, n_places)`` raw_p and right places, for the per-place
            family curves; ``None`` leaves those curves out.
        thresholds: threshold key -> θ (as ``score_queries`` takes them).
        spread: ``(n_places,)`` s_p; ``None`` leaves the family curves out.

    Where the image level scores other queries than the place level (a database/queries
    benchmark), give the image-level baseline a ``PRSplit`` of its own (``top`` = the top
    image score) and merge the rows.
    """

    outcomes: Mapping[str, Outcome]
    known: np.ndarray
    top: np.ndarray
    raw: np.ndarray | None = None
    correct: np.ndarray | None = None
    thresholds: Mapping[str, object] | None = None
    spread: np.ndarray | None = None


@dataclass(frozen=True)
class PRRow:
    """One method's precision–recall numbers, pooled over runs (rates in [0, 1]).

    ``curve`` names the sweep the method sits on (``"global θ"``, ``"θ_p(k) weighted, raw"``
    …), ``param`` its parameter (θ or k); ``max_f1_at`` is the θ or k of max F1; ``own`` the
    method's own operating point (its runs' counts summed, at their own thresholds).
    """

    key: str
    label: str
    curve: str
    param: str
    auc: float
    r_at_100p: float
    r_at_99p: float
    max_f1: float
    max_f1_at: float
    own: PRPoint
    n_known: int
    n_unknown: int

    def to_dict(self) -> dict:
        return {"key": self.key, "label": self.label, "curve": self.curve, "param": self.param,
                "auc": _num(self.auc), "r_at_100p": _num(self.r_at_100p), "r_at_99p": _num(self.r_at_99p),
                "max_f1": _num(self.max_f1), "max_f1_at": _num(self.max_f1_at), "own": self.own.to_dict(),
                "n_known": self.n_known, "n_unknown": self.n_unknown}

    @classmethod
    def from_dict(cls, d: Mapping) -> PRRow:
        """``to_dict`` back (``None`` as NaN)."""
        return cls(str(d["key"]), str(d["label"]), str(d["curve"]), str(d["param"]),
                   *(_from_num(d[k]) for k in ("auc", "r_at_100p", "r_at_99p", "max_f1", "max_f1_at")),
                   PRPoint.from_dict(d["own"]), int(d["n_known"]), int(d["n_unknown"]))


IMAGE_CURVE = "image-level top score"
GLOBAL_CURVE = "global θ"


def family_curve_name(threshold: str, rule: Rule | str) -> str:
    """``"θ_p(k) weighted, raw"`` …: the curve of a per-place method."""
    return f"θ_p(k) {threshold}, {Rule(rule).value}"


def _curve_of(key: str) -> str:
    m = METHODS_BY_KEY[key]
    if m.level == "image":
        return IMAGE_CURVE
    if m.rule is Rule.NONE or not isinstance(m.threshold, str) or m.threshold not in ("simple", "weighted"):
        return GLOBAL_CURVE
    return family_curve_name(m.threshold, m.rule)


def pr_rows(splits: Sequence[PRSplit], *, n: int = FAMILY_POINTS) -> tuple[tuple[PRRow, ...], dict[str, PRCurve]]:
    """Every method's PR row, and the curves they sit on, pooled over runs.

    Curves:

    * ``"image-level top score"`` (image-level baseline): score = top image score, right =
      the image baseline's rank 1 (VPR_Tutorial's single-best-match curve);
    * ``"global θ"`` (place-level baseline and the global θ methods): score = top raw
      score, right = the place baseline's rank 1;
    * ``"θ_p(k) <simple|weighted>, <margin|raw>"`` (the per-place methods): ``pooled_family_pr``
      over a grid of ``n`` k values with k = 0, when every split has ``raw``, ``correct``
      and ``spread``; otherwise their rows are left out.

    Runs are pooled, not averaged: each run's queries are scored with that run's own
    thresholds, and one threshold value (θ, or k) is applied to every run at once. The
    mean of per-run R@100P or max F1 would pick a different θ in every run, an oracle per
    split; the pooled curve is what one setting of the method does.

    A method's own point sums its runs' counts at their own θ: on the pooled curve for the
    baselines, the user θ and the per-place methods (k = 0 is on the grid); for the
    automatic and oracle θ, which differ between runs, it can sit beside the curve
    (its ``threshold`` is their mean).
    """
    if not splits:
        raise VPRInputError("pr_rows: give at least one run")
    keys = list(splits[0].outcomes)
    curves: dict[str, PRCurve] = {}

    known = np.concatenate([s.known for s in splits])
    for key, name in (("image-baseline", IMAGE_CURVE), ("place-baseline", GLOBAL_CURVE)):
        if key in keys:  # the answer does not move with a global θ: one (score, right) per query
            curves[name] = pr_curve(np.concatenate([s.top for s in splits]),
                                    np.concatenate([s.outcomes[key].right & s.known for s in splits]), known)
    has_raw = all(s.raw is not None and s.raw.size and s.correct is not None and s.spread is not None
                  and s.thresholds is not None for s in splits)
    rows = []
    for key in keys:
        m = METHODS_BY_KEY[key]
        name = _curve_of(key)
        if name not in curves:
            if not name.startswith("θ_p(k)") or not has_raw:
                continue
            curves[name] = pooled_family_pr(
                [(s.raw, s.thresholds[m.threshold], s.spread, s.correct) for s in splits], m.rule, n=n)
        c = curves[name]
        points = []
        for s in splits:
            o = s.outcomes[key]
            if name.startswith("θ_p(k)"):
                t = 0.0
            elif m.threshold is None:
                t = -math.inf
            else:
                t = float(s.thresholds[m.threshold]) if s.thresholds is not None else math.nan
            points.append(operating_point(o.accepted, o.right & s.known, s.known, t))
        rows.append(PRRow(key=key, label=m.label, curve=name, param=c.param, auc=c.auc, r_at_100p=c.r_at_100p,
                          r_at_99p=c.r_at_99p, max_f1=c.max_f1, max_f1_at=c.max_f1_threshold,
                          own=pool_points(points), n_known=c.n_known, n_unknown=c.n_unknown))
    return tuple(rows), curves
