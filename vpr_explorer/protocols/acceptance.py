"""The acceptance bench: every acceptance rule on the same queries, decision by decision.

One similarity matrix S ``(n_queries, n_database)``, the database descriptors and places,
and the hard ground truth (which database images are right for each query) give, for each
rule of ``RULES``, one ``RuleDecisions``: per query the answer it would give (a database
image), whether it accepts it, a confidence that orders its acceptances, and the rank of the
first right candidate. On those, ``Bench`` counts

* **the authors' counts** (NickTrinh/VPR_Tutorial ``experiments/final_all_datasets.py``):
  over *genuine* queries (at least one right database image) and *distractors* (none),
  TP = a genuine query accepted with a right image, FP = a genuine query accepted with a
  wrong one or an accepted distractor, FN = a rejected genuine query, TN = a rejected
  distractor; P = TP/(TP+FP), R = TP/(TP+FN), F1 = 2PR/(P+R), rejection = TN/distractors.
  Their recall leaves a genuine query accepted with a wrong image out of its denominator
  (it is an FP, not an FN); ``protocols.precision_recall`` counts it as a miss
  (R = TP/genuine). Both are reported, named;
* **Recall@K with rejection**: the share of genuine queries the rule accepts with a right
  candidate among its first K (ties within ``TIE_TOLERANCE`` count against the query);
* **the precision–recall curve** over the rule's own free parameter (``BenchRule.sweep``).

Rules (``RULES``; what each reads, and what its curve sweeps):

| key | rule | accepts when | curve sweeps |
|---|---|---|---|
| ``baseline`` | image-level top-1 | always | the top-1 similarity (a global θ) |
| ``per-place`` | the paper's θ_p (weighted), raw rule | some place scores ≥ its θ_p | k of θ_p + k·s_p |
| ``per-place-k`` | θ_k = μ⁻ + k·σ⁻, k = clip(sep/2, 1, 2) | some place scores ≥ θ_k | k' of θ_k + k'·s_p |
| ``per-query`` | Vysotska's per-query threshold | s₁ ≥ θ_q | c of θ_q + c |
| ``per-query-graph`` | θ_q and the graph matcher | the path takes a matching node | the matched similarity |
| ``seqslam`` | SeqSLAM (OpenSeqSLAM) | ratio ≤ τ | τ |
| ``sequence-per-place`` | θ_p on sequence place scores | some place ≥ θ_p | k of θ_p + k·s_p |
| ``top1-distance`` | L2 distance of the top-1 | d₁ ≤ τ | τ |
| ``pa-ratio`` | d₁/d₂ | u ≤ τ | τ |
| ``sue`` | SUE over the top-K positions | SUE ≤ τ | τ |

**A rule with a free τ** (SeqSLAM, top-1 distance, PA-ratio, SUE) has no threshold of its
own: the bench runs it at the τ that gives the highest authors' F1 on these very queries,
and says so (``tau_note``, "oracle"): a bound on what the rule can do, not a rule you could
run. Give ``BenchOptions.taus`` to fix τ instead.

**Places.** ``per-place`` and ``per-place-k`` read the database's places: group/step (the
caller's labels) or discovered online (``method.place_discovery``); a place's score for a
query is the best of its similarities (``PlaceScore.BEST``, the paper) or their mean
(``PlaceScore.MEAN``, the authors' follow-up); the answer is the place's best image.
Thresholds come from the database images in places only.

**Sequences.** ``per-query``, ``per-query-graph``, ``seqslam`` and ``sequence-per-place``
read the order of the queries and of the database; where either is not one route in
order they are left out, with the reason (``Bench.left_out``). ``sue`` needs database
positions in metres and is left out without them.

**The natural open set** (``natural_open_set``): the database cut to its first F of the
route (F = ``reference_share``, 70% by default, the first ⌊F·n⌋ database images); a query
whose own image (the same frame, for aligned traversals; a right image otherwise) is in the
kept part is genuine, any other a distractor, as the authors decide it: a query just past
the cut is a distractor even where a right image within the tolerance is kept. Places, thresholds
and every rule are computed again on the cut database. The closed set keeps the whole
database and counts only genuine queries (a query without a right image is left out, as
the authors do).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from vpr_explorer.data.groundtruth import GroundTruth
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.graph_matcher import FANOUT, sequence_match
from vpr_explorer.method.match_scores import SUE_K, pa_ratio, sue, top1_distance
from vpr_explorer.method.place_discovery import discovered_places
from vpr_explorer.method.query_threshold import PATCH, QueryThresholdSpec, query_thresholds
from vpr_explorer.method.retrieval import (
    Rule,
    pessimistic_rank,
    place_mean_scores,
    place_scores,
    ranking_scores,
    top_answer,
)
from vpr_explorer.method.sequences import DS, seqslam, sequence_fault, sequence_place_scores
from vpr_explorer.method.stats import mixture_moments, stats_rows
from vpr_explorer.method.thresholds import adaptive_k, place_thresholds
from vpr_explorer.protocols.options import KS, check_finite
from vpr_explorer.protocols.precision_recall import PRCurve, family_pr, pr_curve

#: Share of the route the natural open set keeps as the database (the authors' 70%).
REFERENCE_SHARE = 0.7
#: Most query × database pairs the bench scores: it holds the whole similarity matrix (float32).
BENCH_PAIRS = 60_000_000
#: Positions spanning at most this many metres are not metres (e.g. a route drawn in the unit square).
MIN_SPAN_M = 1.0


class PlaceScore(StrEnum):
    """A place's score for a query: the best of its similarities (paper) or their mean (authors' follow-up)."""

    BEST = "best"
    MEAN = "mean"


class PlaceSource(StrEnum):
    """Where the per-place rules' places come from."""

    GROUP_STEP = "group-step"
    DISCOVERED = "discovered"


@dataclass(frozen=True)
class BenchRule:
    """One acceptance rule of the bench.

    Attributes:
        key: its name in tables, JSON and the CLI.
        label: the name shown to people.
        source: where the rule comes from.
        needs: ``"sequence"`` (queries and database each one route in order), ``"positions"``
            (database positions in metres) or ``None``.
        sweep: what its precision–recall curve sweeps.
        free: the rule has a free τ (no threshold of its own; module doc).
    """

    key: str
    label: str
    source: str
    needs: str | None
    sweep: str
    free: bool = False


RULES: tuple[BenchRule, ...] = (
    BenchRule("baseline", "image-level top-1, no threshold", "every VPR pipeline", None, "global θ on the top-1 similarity"),
    BenchRule("per-place", "per-place θ_p (paper, weighted)", "Trinh & Lyons", None, "k of θ_p + k·s_p"),
    BenchRule("per-place-k", "per-place θ_k, adaptive k", "the authors' follow-up", None, "k' of θ_k + k'·s_p"),
    BenchRule("per-query", "per-query threshold", "Vysotska et al., ICRA 2025", "sequence", "c of θ_q + c"),
    BenchRule("per-query-graph", "per-query threshold + graph matcher", "Vysotska et al., full pipeline",
              "sequence", "the matched similarity"),
    BenchRule("seqslam", "SeqSLAM, uniqueness ratio", "OpenSeqSLAM", "sequence", "τ of ratio ≤ τ", free=True),
    BenchRule("sequence-per-place", "per-place θ_p on sequence scores", "θ_p on SeqSLAM-aggregated scores",
              "sequence", "k of θ_p + k·s_p"),
    BenchRule("top1-distance", "top-1 distance", "Zaffar et al., CVPR 2024", None, "τ of d₁ ≤ τ", free=True),
    BenchRule("pa-ratio", "PA-ratio d₁/d₂", "Zaffar et al., CVPR 2024", None, "τ of u ≤ τ", free=True),
    BenchRule("sue", "SUE", "Zaffar et al., CVPR 2024", "positions", "τ of SUE ≤ τ", free=True),
)
RULES_BY_KEY = {r.key: r for r in RULES}


@dataclass(frozen=True)
class BenchOptions:
    """The bench's choices (module doc); every one validates itself.

    Attributes:
        rules: which rules (keys of ``RULES``), default all that apply.
        places: group/step labels given by the caller, or discovered online.
        place_score: best or mean similarity of a place's images.
        reference_share: F of the natural open set.
        patch: p of the per-query threshold.
        fanout: the graph matcher's fan-out.
        ds: SeqSLAM's sequence length (and the sequence place scores').
        sue_k: K of SUE, the nearest database images whose positions it spreads.
        taus: rule key -> a fixed τ for a rule with a free τ (otherwise the oracle τ).
        ks: Recall@K's K values.
    """

    rules: tuple[str, ...] | None = None
    places: str = PlaceSource.GROUP_STEP
    place_score: str = PlaceScore.BEST
    reference_share: float = REFERENCE_SHARE
    patch: int = PATCH
    fanout: int = FANOUT
    ds: int = DS
    sue_k: int = SUE_K
    taus: Mapping[str, float] = field(default_factory=dict)
    ks: tuple[int, ...] = KS

    def __post_init__(self) -> None:
        if self.rules is not None:
            unknown = [r for r in self.rules if r not in RULES_BY_KEY]
            if unknown or not self.rules:
                raise VPRInputError(f"rules={list(self.rules)!r}: choose from {', '.join(RULES_BY_KEY)}")
        for name, enum in (("places", PlaceSource), ("place_score", PlaceScore)):
            value = getattr(self, name)
            if value not in {e.value for e in enum}:
                raise VPRInputError(f"{name}={value!r}: choose {' or '.join(e.value for e in enum)}")
            object.__setattr__(self, name, enum(value))
        check_finite("reference_share", self.reference_share, low=0.0, high=1.0)
        if not 0 < self.reference_share < 1:
            raise VPRInputError(f"reference_share={self.reference_share!r}: a share of the route strictly between "
                                "0 and 1 (the authors use 0.7)")
        for name, low in (("fanout", 1), ("patch", 2), ("ds", 2), ("sue_k", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
                raise VPRInputError(f"{name}={value!r}: a whole number, {low} or more")
        if self.ds % 2:
            raise VPRInputError(f"ds={self.ds}: SeqSLAM's sequences are centred on the query, so ds is even "
                                "(OpenSeqSLAM: 10)")
        for key, tau in self.taus.items():
            rule = RULES_BY_KEY.get(key)
            if rule is None or not rule.free:
                free = ", ".join(r.key for r in RULES if r.free)
                raise VPRInputError(f"τ given for {key!r}: only rules with a free τ take one ({free})")
            check_finite(f"τ of {key}", tau)
        if isinstance(self.ks, (int, np.integer)) or not self.ks or any(
                isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1 for k in self.ks):
            raise VPRInputError(f"ks={self.ks!r}: give whole numbers, 1 or more")


@dataclass(frozen=True)
class Counts:
    """The authors' counts of one rule (module doc); P, R, F1 and rejection in percent.

    ``recall_all`` is TP over every genuine query (``protocols.precision_recall``'s recall).
    ``rejection`` is ``None`` without distractors.
    """

    tp: int
    fp: int
    fn: int
    tn: int
    n_genuine: int
    n_distractor: int

    @property
    def precision(self) -> float:
        return 100.0 * self.tp / max(self.tp + self.fp, 1)

    @property
    def recall(self) -> float:
        return 100.0 * self.tp / max(self.tp + self.fn, 1)

    @property
    def recall_all(self) -> float:
        return 100.0 * self.tp / max(self.n_genuine, 1)

    @property
    def f1(self) -> float:
        p, r = self.precision, self.recall
        return 2 * p * r / max(p + r, 1e-8)

    @property
    def rejection(self) -> float | None:
        return 100.0 * self.tn / self.n_distractor if self.n_distractor else None

    def to_dict(self) -> dict:
        return {"P": self.precision, "R": self.recall, "F1": self.f1, "R_all": self.recall_all,
                "rejection": self.rejection, "TP": self.tp, "FP": self.fp, "FN": self.fn, "TN": self.tn,
                "n_genuine": self.n_genuine, "n_distractor": self.n_distractor}


def authors_counts(answer: np.ndarray, accepted: np.ndarray, hard: np.ndarray, genuine: np.ndarray,
                   counted: np.ndarray | None = None) -> Counts:
    """The authors' TP/FP/FN/TN of answers (module doc).

    Args:
        answer: ``(n_queries,)`` database image answered (any value where not accepted).
        accepted: ``(n_queries,)`` bool.
        hard: ``(n_queries, n_database)`` bool, the right images.
        genuine: ``(n_queries,)`` bool, the query has a right image; the others are distractors.
        counted: ``(n_queries,)`` bool, the queries counted (default all); the closed set leaves
            the distractors out.
    """
    answer, accepted, genuine = np.asarray(answer), np.asarray(accepted, dtype=bool), np.asarray(genuine, dtype=bool)
    counted = np.ones(len(answer), dtype=bool) if counted is None else np.asarray(counted, dtype=bool)
    rows = np.arange(len(answer))
    hit = accepted & np.asarray(hard)[rows, np.clip(answer, 0, None)]
    g, d = counted & genuine, counted & ~genuine
    tp = int((g & hit).sum())
    return Counts(tp=tp, fp=int((g & accepted & ~hit).sum() + (d & accepted).sum()), fn=int((g & ~accepted).sum()),
                  tn=int((d & ~accepted).sum()), n_genuine=int(g.sum()), n_distractor=int(d.sum()))


@dataclass(frozen=True, eq=False)
class RuleDecisions:
    """What one rule did for every query, each array ``(n_queries,)``.

    Attributes:
        rule: the rule.
        answer: database image answered, ``-1`` where rejected.
        candidate: the answer it weighed before accepting or rejecting, ``-1`` where it has none
            (e.g. SeqSLAM's ds/2 queries at either end).
        accepted: it accepts ``candidate``.
        rank: rank of the first right candidate among those it keeps (pessimistic; ``inf`` where
            none is kept); place-level for the per-place rules.
        confidence: what orders its acceptances (larger = more confident; ``-inf`` where it has
            no candidate); for a rule with a free τ, it accepts when confidence ≥ −τ.
        tau: the τ it ran at (NaN for a rule with thresholds of its own).
        tau_note: where τ came from ("oracle": best F1 on these queries; "given").
        detail: what explains each decision (the rule's own numbers, e.g. ``threshold``, ``ratio``).
        curve: its precision–recall curve (``sweep`` of its rule).
        result: the rule's own result, for figures that explain a decision: ``QueryThresholds``
            (per-query), ``(GraphMatch, QueryThresholds)`` (per-query-graph), ``SeqSLAMResult``,
            ``MatchScores`` (top-1 distance, PA-ratio, SUE); ``None`` for the others.
    """

    rule: BenchRule
    answer: np.ndarray
    candidate: np.ndarray
    accepted: np.ndarray
    rank: np.ndarray
    confidence: np.ndarray
    tau: float
    tau_note: str
    detail: dict[str, np.ndarray]
    curve: PRCurve
    result: object = None

    def recall_at(self, k: int, genuine: np.ndarray) -> float:
        """Recall@K with rejection over the genuine queries, in percent."""
        genuine = np.asarray(genuine, dtype=bool)
        hit = self.accepted & (self.rank <= k) & genuine
        return 100.0 * hit.sum() / max(int(genuine.sum()), 1)


@dataclass(frozen=True, eq=False)
class Bench:
    """Every rule's decisions on one set of queries and one database, and their counts.

    Attributes:
        decisions: rule key -> ``RuleDecisions``, in ``RULES`` order.
        counts: rule key -> the authors' ``Counts``.
        recall: rule key -> {K: Recall@K with rejection, percent}.
        left_out: rule key -> why it did not run.
        genuine: ``(n_queries,)`` queries with a right image.
        counted: ``(n_queries,)`` queries the counts cover.
        n_places: places of the per-place rules (0 when none ran).
        places: ``(n_database,)`` place of each database image (−1 between places).
    """

    decisions: dict[str, RuleDecisions]
    counts: dict[str, Counts]
    recall: dict[str, dict[int, float]]
    left_out: dict[str, str]
    genuine: np.ndarray
    counted: np.ndarray
    n_places: int
    places: np.ndarray

    def to_dict(self) -> dict:
        rules = {}
        for key, d in self.decisions.items():
            rules[key] = {"label": d.rule.label, "source": d.rule.source, **self.counts[key].to_dict(),
                          "recall_at": {str(k): v for k, v in self.recall[key].items()},
                          "tau": None if not np.isfinite(d.tau) else float(d.tau), "tau_note": d.tau_note,
                          "curve": {"sweeps": d.rule.sweep, "auc": _num(d.curve.auc),
                                    "max_f1": _num(d.curve.max_f1)}}
        return {"rules": rules, "left_out": dict(self.left_out), "n_places": self.n_places,
                "n_genuine": int((self.genuine & self.counted).sum()),
                "n_distractor": int((~self.genuine & self.counted).sum())}


def _num(x) -> float | None:
    return float(x) if x is not None and np.isfinite(x) else None


# --------------------------------------------------------------------------- the rules


def _curve(confidence: np.ndarray, right: np.ndarray, counted: np.ndarray, genuine: np.ndarray) -> PRCurve:
    """The precision–recall curve of accepting a query's candidate when its confidence clears a threshold.

    Only counted queries take part; a distractor's acceptance is always wrong (its candidate may
    still be a right image within the tolerance: the authors count it a distractor).
    """
    return pr_curve(np.where(counted, confidence, -np.inf), right & counted & genuine, genuine & counted)


def _oracle_tau(confidence: np.ndarray, candidate_right: np.ndarray, genuine: np.ndarray,
                counted: np.ndarray) -> float:
    """The −confidence threshold with the highest authors' F1 (the highest confidence cut on ties of F1)."""
    live = counted & np.isfinite(confidence)
    c = confidence[live]
    order = np.argsort(-c, kind="stable")
    v = c[order]
    if not len(v):
        return float("nan")
    ends = np.flatnonzero(np.r_[v[1:] != v[:-1], True])
    g = genuine[live][order]
    tp = np.cumsum(g & candidate_right[live][order])[ends]
    acc = np.cumsum(np.ones(len(v), dtype=np.int64))[ends]
    acc_genuine = np.cumsum(g)[ends]
    fp = acc - tp
    fn = int((counted & genuine).sum()) - acc_genuine
    p = tp / np.maximum(tp + fp, 1)
    r = tp / np.maximum(tp + fn, 1)
    f1 = 2 * p * r / np.maximum(p + r, 1e-12)
    return float(-v[ends][int(np.argmax(f1))])


def _gated(rule: BenchRule, candidate: np.ndarray, confidence: np.ndarray, rank: np.ndarray, hard: np.ndarray,
           genuine: np.ndarray, counted: np.ndarray, taus: Mapping[str, float],
           detail: dict[str, np.ndarray], result: object = None) -> RuleDecisions:
    """A rule that weighs one candidate per query and accepts it when confidence ≥ −τ."""
    rows = np.arange(len(candidate))
    right = (candidate >= 0) & hard[rows, np.maximum(candidate, 0)]
    if rule.key in taus:
        tau, note = float(taus[rule.key]), "given"
    else:
        tau, note = _oracle_tau(confidence, right, genuine, counted), "oracle: best F1 on these queries"
    with np.errstate(invalid="ignore"):
        accepted = (candidate >= 0) & (confidence >= -tau)
    curve = _curve(confidence, right, counted, genuine)
    return RuleDecisions(rule, np.where(accepted, candidate, -1), candidate, accepted, rank, confidence, tau, note,
                         detail, curve, result)


def _own(rule: BenchRule, candidate: np.ndarray, accepted: np.ndarray, rank: np.ndarray, confidence: np.ndarray,
         curve: PRCurve, detail: dict[str, np.ndarray], result: object = None) -> RuleDecisions:
    accepted = accepted & (candidate >= 0)
    return RuleDecisions(rule, np.where(accepted, candidate, -1), candidate, accepted, rank, confidence,
                         float("nan"), "its own thresholds", detail, curve, result)


@dataclass(frozen=True, eq=False)
class _Fit:
    """Per-place thresholds of the database images in places."""

    labels: np.ndarray  # (n_database,) place or −1
    n_places: int
    theta: np.ndarray  # paper's weighted θ_p
    theta_k: np.ndarray  # μ⁻ + k σ⁻, adaptive k
    spread: np.ndarray
    k: np.ndarray


def _fit(database: np.ndarray, labels: np.ndarray, n_places: int) -> _Fit:
    rows = np.flatnonzero(labels >= 0)
    stats, positive_mean = stats_rows(database, rows, labels[rows], n_places)
    neg_mean, spread = mixture_moments(stats)
    k = adaptive_k(positive_mean, neg_mean, spread)
    return _Fit(labels, n_places, place_thresholds(stats, "weighted"), neg_mean + k * spread, spread, k)


def _place_rule(rule: BenchRule, raw: np.ndarray, best: np.ndarray, theta: np.ndarray, spread: np.ndarray,
                correct: np.ndarray, counted: np.ndarray, genuine: np.ndarray) -> RuleDecisions:
    scores = ranking_scores(raw, theta, Rule.RAW)
    top = top_answer(scores)
    rows = np.arange(len(raw))
    candidate_place = top_answer(raw)
    accepted = top >= 0
    place = np.where(accepted, top, candidate_place)
    candidate = np.where(place >= 0, best[rows, np.maximum(place, 0)], -1)
    rank = pessimistic_rank(scores, correct)
    with np.errstate(invalid="ignore"):
        margin = np.where(np.isfinite(raw), raw - theta, -np.inf).max(axis=1)
    # a distractor has no right place, whatever images near it the tolerance would allow
    curve = family_pr(raw[counted], theta, spread, correct[counted] & genuine[counted, None], Rule.RAW)
    return _own(rule, candidate, accepted, rank, margin, curve,
                {"place": place, "raw": np.where(place >= 0, raw[rows, np.maximum(place, 0)], np.nan),
                 "theta": np.where(place >= 0, theta[np.maximum(place, 0)], np.nan)})


def run_bench(similarity: np.ndarray, database: np.ndarray, hard: np.ndarray, *, labels: np.ndarray | None,
              sequence: str | None, database_xy: np.ndarray | None = None,
              options: BenchOptions | None = None, counted: np.ndarray | None = None,
              genuine: np.ndarray | None = None) -> Bench:
    """Every rule of ``options.rules`` on one similarity matrix (module doc).

    Args:
        similarity: ``(n_queries, n_database)`` cosine similarities of unit descriptors.
        database: ``(n_database, D)`` the database descriptors (places and thresholds).
        hard: ``(n_queries, n_database)`` bool right images.
        labels: ``(n_database,)`` group/step place of each database image (``-1`` between
            places); ignored with discovered places; ``None`` leaves the per-place rules out.
        sequence: ``None`` when queries and database are each one route in order, else why not
            (the sequence rules are then left out with it).
        database_xy: ``(n_database, 2)`` positions in metres for SUE, or ``None``.
        options: the choices (default ``BenchOptions()``).
        counted: ``(n_queries,)`` the queries the counts cover (default all).
        genuine: ``(n_queries,)`` the queries that have a right answer (default: a right image in ``hard``).
    """
    options = BenchOptions() if options is None else options
    s = np.asarray(similarity, dtype=np.float32)
    hard = np.asarray(hard, dtype=bool)
    if s.ndim != 2 or hard.shape != s.shape:
        raise VPRInputError(f"similarity {s.shape} and ground truth {hard.shape}: give one (n_queries, n_database) "
                            "matrix of each")
    if not np.isfinite(s).all():
        raise VPRInputError("similarity holds NaN or infinite values: recompute it from finite descriptors")
    nq, nd = s.shape
    genuine = hard.any(axis=1) if genuine is None else np.asarray(genuine, dtype=bool)
    counted = np.ones(nq, dtype=bool) if counted is None else np.asarray(counted, dtype=bool)
    wanted = [r for r in RULES if options.rules is None or r.key in options.rules]
    left_out: dict[str, str] = {}
    rows = np.arange(nq)
    ranks: dict[str, np.ndarray] = {}

    def image_rank() -> np.ndarray:
        """The image ranking's pessimistic rank, computed once, for the rules that read it."""
        if "image" not in ranks:
            ranks["image"] = pessimistic_rank(s.astype(np.float64), hard)
        return ranks["image"]

    out: dict[str, RuleDecisions] = {}

    fit = None
    needs_places = {"per-place", "per-place-k", "sequence-per-place"}
    if any(r.key in needs_places for r in wanted):
        if options.places is PlaceSource.DISCOVERED:
            found, n_places = discovered_places(database)
            fit = _fit(database, found, n_places)
        elif labels is None:
            for r in wanted:
                if r.key in needs_places:
                    left_out[r.key] = "no places: give group/step labels or discovered places"
        else:
            lab = np.asarray(labels, dtype=np.int64)
            present = np.unique(lab[lab >= 0])
            remap = np.full(int(lab.max()) + 1 if lab.max() >= 0 else 1, -1, dtype=np.int64)
            remap[present] = np.arange(len(present))
            lab = np.where(lab >= 0, remap[np.maximum(lab, 0)], -1)
            if len(present) < 2:
                for r in wanted:
                    if r.key in needs_places:
                        left_out[r.key] = f"{len(present)} place in the database: per-place thresholds need 2 or more"
            else:
                fit = _fit(database, lab, len(present))

    top_sim = s.max(axis=1).astype(np.float64)
    top = top_answer(s)
    qt = None
    for rule in wanted:
        if rule.key in left_out:
            continue
        if rule.needs == "sequence" and sequence is not None:
            left_out[rule.key] = sequence
            continue
        if rule.needs == "positions" and database_xy is None:
            left_out[rule.key] = "the database has no positions in metres"
            continue
        key = rule.key
        if key == "baseline":
            out[key] = _own(rule, top, np.ones(nq, dtype=bool), image_rank(), top_sim,
                            _curve(top_sim, hard[rows, top], counted, genuine), {"score": top_sim})
        elif key in ("per-place", "per-place-k"):
            in_place = np.flatnonzero(fit.labels >= 0)
            lab = fit.labels[in_place]
            if options.place_score is PlaceScore.MEAN:
                raw = place_mean_scores(s[:, in_place], lab, fit.n_places)
                _, best = place_scores(s[:, in_place], lab, fit.n_places)
            else:
                raw, best = place_scores(s[:, in_place], lab, fit.n_places)
            best = np.where(best >= 0, in_place[np.maximum(best, 0)], -1)
            correct = _correct_places(hard, fit.labels, fit.n_places)
            theta = fit.theta if key == "per-place" else fit.theta_k
            out[key] = _place_rule(rule, raw, best, theta, fit.spread, correct, counted, genuine)
        elif key == "sequence-per-place":
            # images between places get a spare id, whose column is dropped after the place maxima
            try:
                raw, best = sequence_place_scores(s, _spare(fit), fit.n_places + 1, ds=options.ds)
            except VPRInputError as exc:
                left_out[key] = str(exc)
                continue
            raw, best = raw[:, :fit.n_places], best[:, :fit.n_places]
            correct = _correct_places(hard, fit.labels, fit.n_places)
            out[key] = _place_rule(rule, raw, best, fit.theta, fit.spread, correct, counted, genuine)
        elif key == "per-query":
            qt = qt if qt is not None else query_thresholds(s, QueryThresholdSpec(patch=options.patch))
            kept = s >= qt.threshold[:, None]
            rank = pessimistic_rank(np.where(kept, s, -np.inf).astype(np.float64), hard)
            out[key] = _own(rule, qt.best_match, qt.accepted, rank, qt.top_score - qt.threshold,
                            _curve(qt.top_score - qt.threshold, hard[rows, qt.best_match], counted, genuine),
                            {"threshold": qt.threshold, "score": qt.top_score, "bimodal": qt.bimodal}, qt)
        elif key == "per-query-graph":
            # the full pipeline (``graph_matcher.full_pipeline``) on the per-query thresholds computed once
            qt = qt if qt is not None else query_thresholds(s, QueryThresholdSpec(patch=options.patch))
            graph_qt = qt
            cost = 1.0 - float(np.median(qt.threshold))
            match = sequence_match(s, non_matching_cost=cost, fanout=options.fanout)
            m = match.matched
            acc = m >= 0
            conf = np.where(acc, s[rows, np.maximum(m, 0)], -np.inf).astype(np.float64)
            right = acc & hard[rows, np.maximum(m, 0)]
            rank = np.where(right, 1.0, np.inf)
            out[key] = _own(rule, m, acc, rank, conf,
                            _curve(conf, right, counted, genuine),
                            {"node_cost": match.node_cost, "non_matching_cost": np.full(nq, cost)}, (match, graph_qt))
        elif key == "seqslam":
            try:
                res = seqslam(s, kind="similarity", ds=options.ds)
            except VPRInputError as exc:
                left_out[key] = str(exc)
                continue
            conf = np.where(res.matched, -res.ratio, -np.inf)
            rank = pessimistic_rank(np.where(np.isfinite(res.scores), -res.scores, -np.inf), hard)
            out[key] = _gated(rule, res.match, conf, rank, hard, genuine, counted, options.taus,
                              {"ratio": res.ratio, "velocity": res.velocity}, res)
        elif key in ("top1-distance", "pa-ratio", "sue"):
            ms = {"top1-distance": lambda: top1_distance(s), "pa-ratio": lambda: pa_ratio(s),
                  "sue": lambda: sue(s, database_xy, k=options.sue_k)}[key]()
            conf = np.where(np.isfinite(ms.score), -ms.score, -np.inf)
            out[key] = _gated(rule, ms.top1, conf, image_rank(), hard, genuine, counted, options.taus,
                              {"score": ms.score}, ms)
    counts = {k: authors_counts(d.answer, d.accepted, hard, genuine, counted) for k, d in out.items()}
    recall = {k: {kk: d.recall_at(kk, genuine & counted) for kk in options.ks} for k, d in out.items()}
    return Bench(decisions=out, counts=counts, recall=recall, left_out=left_out, genuine=genuine, counted=counted,
                 n_places=0 if fit is None else fit.n_places,
                 places=np.full(nd, -1, dtype=np.int64) if fit is None else fit.labels)


def _spare(fit: _Fit) -> np.ndarray:
    """Labels with a spare id for images between places (their column is dropped afterwards)."""
    return np.where(fit.labels >= 0, fit.labels, fit.n_places)


def _correct_places(hard: np.ndarray, labels: np.ndarray, n_places: int) -> np.ndarray:
    """``(n_queries, n_places)`` the places holding a right image of each query."""
    q, j = np.nonzero(hard)
    p = labels[j]
    out = np.zeros((hard.shape[0], n_places), dtype=bool)
    out[q[p >= 0], p[p >= 0]] = True
    return out


def natural_open_set(similarity: np.ndarray, database: np.ndarray, hard: np.ndarray, *, labels: np.ndarray | None,
                     sequence: str | None, ordered: bool, database_xy: np.ndarray | None = None,
                     options: BenchOptions | None = None, exact: np.ndarray | None = None) -> Bench:
    """The bench on the database cut to its first F of the route (module doc).

    Args:
        ordered: the database is one route in order; the cut means nothing otherwise and is refused.
        exact: ``(n_queries, n_database)`` the query's own images (the same frame, no tolerance): a
            query is genuine when one of them is kept, as the authors decide it (default ``hard``).
        the rest: as for ``run_bench``, on the whole database (the cut is made here).
    """
    options = BenchOptions() if options is None else options
    if not ordered:
        raise VPRInputError("the natural open set cuts the database at a share of its route, and this database is "
                            "not one route in order: use the open-set protocol (places held out) instead")
    nd = np.asarray(similarity).shape[1]
    cut = int(nd * options.reference_share)
    if cut < 2 or cut >= nd:
        raise VPRInputError(f"reference_share={options.reference_share:g} keeps {cut} of {nd} database images: keep "
                            "at least 2 and leave at least 1 out")
    lab = None if labels is None else np.asarray(labels)[:cut]
    xy = None if database_xy is None else np.asarray(database_xy)[:cut]
    own = np.asarray(hard if exact is None else exact, dtype=bool)[:, :cut]
    return run_bench(np.asarray(similarity)[:, :cut], np.asarray(database)[:cut], np.asarray(hard)[:, :cut],
                     labels=lab, sequence=sequence, database_xy=xy, options=options, genuine=own.any(axis=1))


def closed_set(similarity: np.ndarray, database: np.ndarray, hard: np.ndarray, *, labels: np.ndarray | None,
               sequence: str | None, database_xy: np.ndarray | None = None,
               options: BenchOptions | None = None, exact: np.ndarray | None = None) -> Bench:
    """The bench on the whole database, counting only the queries with a right image (module doc).

    ``exact`` as for ``natural_open_set``: the genuine queries are those with an own image.
    """
    genuine = np.asarray(hard if exact is None else exact, dtype=bool).any(axis=1)
    return run_bench(similarity, database, hard, labels=labels, sequence=sequence, database_xy=database_xy,
                     options=options, counted=genuine, genuine=genuine)



# --------------------------------------------------------------------------- a dataset value


@dataclass(frozen=True, eq=False)
class AcceptanceReport:
    """The bench on a dataset value: the closed set and the natural open set, with what shaped them.

    Attributes:
        closed: every rule on the whole database (genuine queries only).
        natural: every rule on the database cut to ``options.reference_share`` of its route;
            ``None`` where the database is not one route (``natural_note`` says why).
        settings: dataset, descriptor, places and every option, for tables and JSON.
        notes: what the bench decided (rules left out, positions, places).
    """

    closed: Bench
    natural: Bench | None
    natural_note: str
    settings: dict
    notes: tuple[str, ...]

    def to_dict(self) -> dict:
        return {"settings": self.settings, "notes": list(self.notes), "closed_set": self.closed.to_dict(),
                "natural_open_set": None if self.natural is None else self.natural.to_dict(),
                "natural_open_set_note": self.natural_note}


def sequence_reason(dataset) -> str | None:
    """``None`` when the value's queries and database are each one route in order, else why not.

    The per-query threshold, the graph matcher, SeqSLAM and the sequence place scores read
    runs of consecutive images on both sides: ``sequences.sequence_fault`` says why not.
    """
    return sequence_fault(dataset, "the sequence rules (per-query threshold, graph matcher, SeqSLAM, sequence "
                                   "place scores)")


def metres_positions(dataset) -> tuple[np.ndarray | None, str]:
    """The database positions SUE reads, or ``None`` and why not.

    Positions are read as metres; a dataset whose positions span at most ``MIN_SPAN_M``
    (e.g. GardensPoint's ``gp_pos.csv``, a route drawn in the unit square) is taken not to
    hold metres, and SUE is left out rather than run on a scale its constants do not fit.
    """
    xy = dataset.database_xy
    if xy is None:
        return None, "the database has no positions"
    xy = np.asarray(xy, dtype=np.float64)
    span = float(np.max(xy.max(axis=0) - xy.min(axis=0))) if len(xy) else 0.0
    if span <= MIN_SPAN_M:
        return None, (f"the database positions span {span:.3g} (at most {MIN_SPAN_M:g} m): they are not metres, "
                      "and SUE's constants are in metres")
    return xy, ""


def acceptance_report(dataset, descriptors: np.ndarray, *, labels: np.ndarray | None,
                      options: BenchOptions | None = None, settings: dict | None = None,
                      database_xy: np.ndarray | None = None) -> AcceptanceReport:
    """The closed set and the natural open set of every rule on a dataset value (module doc).

    Args:
        dataset: a ``data.layouts.RetrievalDataset`` (its ground truth's hard positives are the right images).
        descriptors: ``(n_images, D)`` unit descriptors in the value's order (database rows first).
        labels: ``(n_database,)`` group/step place of each database image (``-1`` between places).
        options: the bench's choices.
        settings: what else shaped the numbers (descriptor, places), copied into the report.
        database_xy: database positions in metres for SUE; default ``metres_positions(dataset)``
            (SUE is left out, with the reason, without them).
    """
    from vpr_explorer.method.retrieval import similarity as similarity_of

    options = BenchOptions() if options is None else options
    d = np.asarray(descriptors, dtype=np.float32)
    if len(d) != dataset.n_images:
        raise VPRInputError(f"{len(d)} descriptors for {dataset.n_images} images of {dataset.name!r}: recompute them")
    if options.places is PlaceSource.DISCOVERED and not dataset.ordered:
        raise VPRInputError(f"places=discovered: {dataset.name!r} has no database route in order, and places are "
                            "discovered along one; use group/step places")
    pairs = dataset.n_queries * dataset.n_database
    if pairs > BENCH_PAIRS:
        raise VPRInputError(f"{dataset.n_queries:,} queries × {dataset.n_database:,} database images = {pairs:,} pairs: "
                            f"the acceptance bench holds the whole similarity matrix and takes at most "
                            f"{BENCH_PAIRS:,}; choose fewer queries or a smaller database")
    db, queries = d[:dataset.n_database], d[dataset.n_database:]
    s = similarity_of(queries, db)
    hard = dataset.ground_truth.dense()
    exact = None
    if dataset.query_frame is not None and dataset.database_frame is not None:
        exact = GroundTruth.from_frames(dataset.query_frame, dataset.database_frame, 0).dense()
    sequence = sequence_reason(dataset)
    xy_note = ""
    if database_xy is None:
        database_xy, xy_note = metres_positions(dataset)
    closed = closed_set(s, db, hard, labels=labels, sequence=sequence, database_xy=database_xy, options=options,
                        exact=exact)
    natural, note = None, ""
    try:
        natural = natural_open_set(s, db, hard, labels=labels, sequence=sequence, ordered=dataset.ordered,
                                   database_xy=database_xy, options=options, exact=exact)
    except VPRInputError as exc:
        note = str(exc)
    for bench in (closed, natural):
        if bench is not None and xy_note and "sue" in bench.left_out:
            bench.left_out["sue"] = xy_note
    notes = [f"{key} left out: {why}" for key, why in closed.left_out.items()]
    notes += [f"{r.key}: τ = {closed.decisions[r.key].tau:.4g} ({closed.decisions[r.key].tau_note})"
              for r in RULES if r.key in closed.decisions and r.free]
    all_settings = {"dataset": dataset.name, "n_queries": dataset.n_queries, "n_database": dataset.n_database,
                    "places": str(options.places), "place_score": str(options.place_score),
                    "reference_share": options.reference_share, "patch": options.patch, "fanout": options.fanout,
                    "ds": options.ds, "sue_k": options.sue_k, **(settings or {})}
    return AcceptanceReport(closed, natural, note, all_settings, tuple(notes))


def render_report(report: AcceptanceReport) -> str:
    """The report as the authors' table shape: rules × (closed-set F1, open-set F1, rejection), then details."""
    lines = [f"{report.settings['dataset']}: {report.settings['n_queries']:,} queries, "
             f"{report.settings['n_database']:,} database images"]
    share = report.settings["reference_share"]
    head = f"{'rule':<40}{'closed F1':>10}{'R@1':>8}{f'open F1 ({share:.0%})':>16}{'rejection':>11}{'AUC-PR':>8}"
    lines += [head, "-" * len(head)]
    for rule in RULES:
        c = report.closed.decisions.get(rule.key)
        if c is None:
            continue
        cc = report.closed.counts[rule.key]
        r1 = report.closed.recall[rule.key].get(1, float("nan"))
        o = None if report.natural is None else report.natural.counts.get(rule.key)
        open_f1 = "—" if o is None else f"{o.f1:.1f}"
        rej = "—" if o is None or o.rejection is None else f"{o.rejection:.1f}"
        auc = "—" if not np.isfinite(c.curve.auc) else f"{c.curve.auc:.3f}"
        label = rule.label + (" †" if c.tau_note.startswith("oracle") else "")
        lines.append(f"{label:<40}{cc.f1:>10.1f}{r1:>8.1f}{open_f1:>16}{rej:>11}{auc:>8}")
    lines += ["", "F1 and rejection in percent, the authors' counts (P = TP/(TP+FP), R = TP/(TP+FN)); R@1: Recall@1 "
                  "with rejection over the genuine queries (the right place for the per-place rules); "
                  "† τ at the best F1 on these queries (oracle)"]
    if report.natural is not None:
        n = report.natural
        lines.append(f"natural open set: the first {share:.0%} of the database route; "
                     f"{int(n.genuine.sum()):,} genuine queries, {int((~n.genuine).sum()):,} distractors")
    elif report.natural_note:
        lines.append(f"natural open set not run: {report.natural_note}")
    lines += list(report.notes)
    return "\n".join(lines)
