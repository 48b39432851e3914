"""Evaluation protocols: paper (closed set), open set, database/queries.

* **paper**: R seeded random splits; in each, one image per place is the query and the rest
  train; thresholds come from that split's training images only (a query never influences
  its own threshold); Recall@K as mean ± std over splits. ``cross_condition`` scores each
  query only against database images of other traversals, and every method reports the
  share of its accepted top-1 matches that come from the query's own traversal.
* **open set**: as the paper protocol, but a share of places is held out of the database
  entirely; one image of each such place is a query that must be rejected. Reports the
  unknown-place rejection rate beside known-place Recall@1 and the precision of accepted
  matches, over the threshold family θ_p(k) = θ_p + k·s_p and a sweep of global θ.
* **database/queries** (``retrieval_protocol``): a database against queries with the ground
  truth as a relation; thresholds from the database only; one deterministic run. The
  traversal protocol (a database traversal against a query traversal) is this protocol on
  the aligned traversals' value (``data.aligned.database_queries``; ``pipeline.run_protocol``).

Every protocol takes its settings as one ``options.ProtocolOptions``. All functions are
pure: descriptors and labels in, a frozen ``Evaluation`` out. Up to
``shared_scores.SHARED_LIMIT`` images the paper and open-set protocols score every image
pair once (``shared_scores.SharedScores``: the float32 similarity that scores the queries,
the float64 Gram each split's negative statistics come from, pairwise); a caller running
several protocols on the same descriptors (a group/step sweep) passes one as ``shared=``,
and the numbers are the same, bit for bit, as when each run builds its own.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from vpr_explorer.errors import VPRInputError
from vpr_explorer.data.groundtruth import GroundTruth
from vpr_explorer.method.places import right_places
from vpr_explorer.protocols.options import ProtocolOptions
from vpr_explorer.protocols.precision_recall import PRCurve, PRRow, PRSplit, pr_rows
from vpr_explorer.method.retrieval import (
    METHODS_BY_KEY,
    Method,
    Outcome,
    Rule,
    pessimistic_rank,
    place_scores,
    ranking_scores,
    score_queries,
    similarity,
    top_answer,
)
from vpr_explorer.protocols.shared_scores import Negatives, SharedScores, resolve
from vpr_explorer.method.stats import (
    NegativeStats,
    Precision,
    mixture_moments,
    negative_stats,
    positive_means,
    validate_descriptors,
)
from vpr_explorer.method.thresholds import (
    ThresholdMethod,
    adaptive_k,
    auto_global_threshold,
    mixture_spread,
    place_thresholds,
    pooled_pair_sample,
    threshold_family,
    training_pair_scores,
)

#: The database/queries protocol keeps every query's raw_p (float32, exact) for the per-place
#: precision–recall curves up to this many query × place cells (200 MB), and leaves them out above.
PR_RAW_CELLS = 50_000_000
Progress = Callable[[int, int, str], None]


class Protocol(StrEnum):
    PAPER = "paper"
    TRAVERSAL = "traversal"
    OPEN_SET = "open-set"
    DATABASE = "database-queries"


PROTOCOL_LABELS = {
    Protocol.PAPER: "paper: R random splits, one query image per place (closed set)",
    Protocol.TRAVERSAL: "traversal: a database traversal against a query traversal",
    Protocol.OPEN_SET: "open set: a share of places held out; their queries must be rejected",
    Protocol.DATABASE: "database/queries: a benchmark's database against its queries, ground truth as given",
}

Stat = tuple[float, float]  # (mean, sample std with ddof 1) over runs; std NaN for one run


def _mean_std(values: Sequence[float]) -> Stat:
    """Mean and sample std (ddof 1, ``paired.summary``'s convention) of the finite values; one value has no std (NaN)."""
    a = np.asarray(values, dtype=np.float64)
    a = a[np.isfinite(a)]
    if a.size == 0:
        return (float("nan"), float("nan"))
    return (float(a.mean()), float(a.std(ddof=1)) if a.size > 1 else float("nan"))


@dataclass(frozen=True)
class MethodRow:
    """One method's numbers, each ``(mean, std)`` over runs; rates in [0, 1]."""

    key: str
    label: str
    source: str
    recall: dict[int, Stat]
    accepted: Stat
    precision: Stat
    own_traversal: Stat | None = None
    unknown_rejection: Stat | None = None
    #: each rate split by split, in split order ("recall@1" …, "accepted", "precision", and "own_traversal",
    #: "unknown_rejection" where the row has them), NaN where a split leaves it undefined: what
    #: ``paired`` compares split by split
    per_split: dict[str, tuple[float, ...]] = field(default_factory=dict, compare=False, repr=False)


@dataclass(frozen=True)
class TradeoffRow:
    """One point of the open-set trade-off curve.

    ``series`` is ``"θ_p(k) simple"``, ``"θ_p(k) weighted"``, ``"adaptive k weighted"`` …, or
    ``"global θ"``; ``param`` is k or the global θ.
    """

    series: str
    rule: str
    param: float
    known_recall1: Stat
    unknown_rejection: Stat
    precision: Stat
    accepted: Stat
    #: each rate split by split, as ``MethodRow.per_split``
    per_split: dict[str, tuple[float, ...]] = field(default_factory=dict, compare=False, repr=False)


@dataclass(frozen=True)
class Evaluation:
    """The result of one protocol run."""

    protocol: Protocol
    settings: dict
    ks: tuple[int, ...]
    rows: tuple[MethodRow, ...]
    tradeoff: tuple[TradeoffRow, ...] = ()
    notes: tuple[str, ...] = ()
    seconds: float = 0.0
    #: precision–recall per method, pooled over runs (``split_pr``); empty unless asked for (``pr=True``)
    pr: tuple[PRRow, ...] = ()
    #: the curves those rows sit on, by name ("global θ", "θ_p(k) weighted, raw" …)
    pr_curves: dict[str, PRCurve] = field(default_factory=dict, compare=False, repr=False)

    def row(self, key: str) -> MethodRow:
        return next(r for r in self.rows if r.key == key)

    def same_numbers(self, other: Evaluation) -> bool:
        """The same methods with exactly the same Recall@K, accepted, precision and own-traversal share.

        NaN (e.g. the precision of nothing accepted) equals NaN. How the benchmarks check the
        fast paper protocol against ``paper_protocol``.
        """

        def same(a: MethodRow, b: MethodRow) -> bool:
            pairs = [(a.recall[k], b.recall[k]) for k in a.recall]
            pairs += [(a.accepted, b.accepted), (a.precision, b.precision), (a.own_traversal, b.own_traversal)]
            return a.key == b.key and all(
                np.array_equal(np.asarray(x, float), np.asarray(y, float), equal_nan=True) for x, y in pairs
            )

        return len(self.rows) == len(other.rows) and all(same(a, b) for a, b in zip(self.rows, other.rows))

    def to_dict(self) -> dict:
        """JSON-ready numbers (rates in [0, 1]); undefined values (e.g. precision with nothing accepted) are ``None``."""

        def num(x):
            return float(x) if x is not None and np.isfinite(x) else None

        def stat(s):
            return None if s is None else {"mean": num(s[0]), "std": num(s[1])}

        return {
            "protocol": self.protocol.value,
            "settings": self.settings,
            "ks": list(self.ks),
            "seconds": self.seconds,
            "methods": [
                {
                    "key": r.key, "label": r.label, "source": r.source,
                    "recall": {str(k): stat(v) for k, v in r.recall.items()},
                    "accepted": stat(r.accepted), "precision": stat(r.precision),
                    "own_traversal_top1": stat(r.own_traversal), "unknown_rejection": stat(r.unknown_rejection),
                    "per_split": {name: [num(x) for x in values] for name, values in r.per_split.items()},
                }
                for r in self.rows
            ],
            "tradeoff": [
                {"series": t.series, "rule": t.rule, "param": num(t.param),
                 **{f: stat(getattr(t, f)) for f in ("known_recall1", "unknown_rejection", "precision", "accepted")},
                 "per_split": {name: [num(x) for x in values] for name, values in t.per_split.items()}}
                for t in self.tradeoff
            ],
            "notes": list(self.notes),
            **({"pr": [r.to_dict() for r in self.pr],
                "pr_curves": {name: c.to_dict() for name, c in self.pr_curves.items()}} if self.pr else {}),
        }

    @classmethod
    def from_dict(cls, data: Mapping) -> Evaluation:
        """``to_dict`` back: every number as written (``None`` as NaN); the curves where ``data`` holds them.

        Raises:
            VPRInputError: ``data`` is not an evaluation written by ``to_dict`` (naming the first field that is
                missing or of the wrong kind).
        """
        try:
            return _evaluation_from_dict(data)
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise VPRInputError(f"not an evaluation written by vpr-explorer ({type(exc).__name__}: {exc})") from None


def _from_num(x) -> float:
    return math.nan if x is None else float(x)


def _from_stat(s) -> Stat | None:
    return None if s is None else (_from_num(s["mean"]), _from_num(s["std"]))


def _from_splits(d: Mapping) -> dict[str, tuple[float, ...]]:
    return {str(name): tuple(_from_num(x) for x in values) for name, values in d.items()}


def _evaluation_from_dict(data: Mapping) -> Evaluation:
    rows = tuple(
        MethodRow(key=str(m["key"]), label=str(m["label"]), source=str(m["source"]),
                  recall={int(k): _from_stat(v) for k, v in m["recall"].items()},
                  accepted=_from_stat(m["accepted"]), precision=_from_stat(m["precision"]),
                  own_traversal=_from_stat(m.get("own_traversal_top1")),
                  unknown_rejection=_from_stat(m.get("unknown_rejection")),
                  per_split=_from_splits(m.get("per_split", {})))
        for m in data["methods"])
    tradeoff = tuple(
        TradeoffRow(series=str(t["series"]), rule=str(t["rule"]), param=_from_num(t["param"]),
                    **{f: _from_stat(t[f]) for f in ("known_recall1", "unknown_rejection", "precision", "accepted")},
                    per_split=_from_splits(t.get("per_split", {})))
        for t in data.get("tradeoff", ()))
    return Evaluation(
        protocol=Protocol(data["protocol"]), settings=dict(data["settings"]), ks=tuple(int(k) for k in data["ks"]),
        rows=rows, tradeoff=tradeoff, notes=tuple(str(n) for n in data.get("notes", ())),
        seconds=float(data.get("seconds") or 0.0),
        pr=tuple(PRRow.from_dict(r) for r in data.get("pr", ())),
        pr_curves={str(name): PRCurve.from_dict(c) for name, c in (data.get("pr_curves") or {}).items()},
    )


def strict(x):
    """``x`` made strict JSON: NaN and ±inf as ``None``, numpy scalars as Python numbers, keys as strings."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, Mapping):
        return {str(k): strict(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [strict(v) for v in x]
    if hasattr(x, "item") and not isinstance(x, (str, bytes)):  # a numpy scalar
        return strict(x.item())
    return x


# --------------------------------------------------------------------------- split core


@dataclass(frozen=True, eq=False)
class SplitScores:
    """Everything one split produced, for the summaries and the trade-off curve."""

    outcomes: dict[str, Outcome]
    raw: np.ndarray  # (nq, P)
    best: np.ndarray  # (nq, P)
    correct: np.ndarray  # (nq, P)
    known: np.ndarray  # (nq,)
    query_traversal: np.ndarray  # (nq,)
    train_traversal: np.ndarray  # (n_train,)
    thresholds: dict[str, np.ndarray | float]
    spread: np.ndarray  # (P,) s_p
    k_adaptive: np.ndarray  # (P,)
    top: np.ndarray | None = None  # (nq,) top raw score, where raw is not kept (the blocked pass)


def oracle_global_threshold(top_raw: np.ndarray, right_if_accepted: np.ndarray, known: np.ndarray) -> float:
    """The single θ that makes the most queries right, knowing the answers (an oracle).

    A query is right when it is known, accepted and its top place is right, or unknown and
    rejected; it is accepted when its top raw score is >= θ. The smallest best θ is returned.
    """
    order = np.argsort(top_raw, kind="stable")
    v = top_raw[order]
    good_acc = (known & right_if_accepted)[order].astype(np.int64)
    good_rej = (~known)[order].astype(np.int64)
    n = len(v)
    rej_before = np.r_[0, np.cumsum(good_rej)]  # rejected = indices < j
    acc_from = np.r_[np.cumsum(good_acc[::-1])[::-1], 0]  # accepted = indices >= j
    starts = np.r_[np.flatnonzero(np.r_[True, v[1:] != v[:-1]]), n]
    score = rej_before[starts] + acc_from[starts]
    j = starts[int(np.argmax(score))]
    return float(v[j]) if j < n else float(np.nextafter(v[-1], np.inf))


def _thresholds(d_train, lab_train, n_places, *, user_theta, seed, stats: NegativeStats | None = None,
                auto_theta: float | None = None):
    # the protocols are the reference the blocked pass (scale.py) must equal: σ from float64 products,
    # pairwise from the shared Gram (``shared_scores.Negatives``) up to SHARED_LIMIT images, else in closed form;
    # the automatic θ from the run's pooled sample when given (``thresholds.pooled_pair_sample``)
    if stats is None:
        stats = negative_stats(d_train, lab_train, n_places, precision=Precision.FLOAT64)
    if auto_theta is None:
        auto_theta = auto_global_threshold(training_pair_scores(d_train, seed=seed))
    th: dict[str, np.ndarray | float] = {
        ThresholdMethod.SIMPLE.value: place_thresholds(stats, ThresholdMethod.SIMPLE),
        ThresholdMethod.WEIGHTED.value: place_thresholds(stats, ThresholdMethod.WEIGHTED),
        "auto": float(auto_theta),
    }
    if user_theta is not None:
        th["user"] = float(user_theta)
    neg_mean, spread = mixture_moments(stats)
    k_ad = adaptive_k(positive_means(d_train, lab_train, n_places), neg_mean, spread)
    return th, mixture_spread(stats), k_ad


def run_split(
    d_train: np.ndarray,
    lab_train: np.ndarray,
    trav_train: np.ndarray,
    sims: np.ndarray,
    correct: np.ndarray,
    trav_query: np.ndarray,
    n_places: int,
    *,
    cross_condition: bool = False,
    user_theta: float | None = None,
    seed: int = 0,
    stats: NegativeStats | None = None,
    auto_theta: float | None = None,
) -> SplitScores:
    """Thresholds from the training images, then every method on the queries.

    Args:
        d_train: ``(n_train, D)`` training descriptors; lab_train, trav_train their places and traversals.
        sims: ``(n_queries, n_train)`` query-to-training similarities.
        correct: ``(n_queries, n_places)`` bool, each query's right places; a row with none is a
            query of an unknown place.
        trav_query: ``(n_queries,)`` each query's traversal.
        cross_condition: score each query only against training images of other traversals.
        stats: the training images' negative statistics when already known (pairwise from
            ``shared_scores``); default the float64 closed form of ``d_train``.
        auto_theta: the automatic global θ when already known (the pooled protocols':
            ``thresholds.PooledPairSample.theta``); default from ``training_pair_scores(d_train, seed=seed)``.
    """
    th, spread, k_ad = _thresholds(d_train, lab_train, n_places, user_theta=user_theta, seed=seed, stats=stats,
                                   auto_theta=auto_theta)
    sims = np.array(sims, dtype=np.float64)
    if cross_condition:
        sims[trav_query[:, None] == trav_train[None, :]] = -np.inf
    known = correct.any(axis=1)
    raw, best = place_scores(sims, lab_train, n_places)
    outcomes = score_queries(sims, lab_train, n_places, th, correct, raw_best=(raw, best))
    base = outcomes["place-baseline"]
    th["oracle"] = oracle_global_threshold(raw.max(axis=1), base.rank == 1, known)
    outcomes.update(score_queries(sims, lab_train, n_places, th, correct, (METHODS_BY_KEY["global-oracle"],),
                                  raw_best=(raw, best)))
    return SplitScores(outcomes, raw, best, correct, known, trav_query, trav_train, th, spread, k_ad)


def _place_outcome(raw, best, theta, rule: Rule, correct) -> Outcome:
    """A place-level method with an arbitrary θ, from precomputed raw scores."""
    scores = ranking_scores(raw, theta, rule)
    place = top_answer(scores)
    img = np.where(place >= 0, best[np.arange(len(raw)), np.maximum(place, 0)], -1)
    method = Method("custom", "custom", "place", rule, "custom", "")
    return Outcome(method, pessimistic_rank(scores, correct), place, img, np.isfinite(scores).sum(axis=1))


# --------------------------------------------------------------------------- summaries


def split_pr(splits: Sequence[SplitScores]) -> tuple[tuple[PRRow, ...], dict[str, PRCurve]]:
    """Precision–recall rows and curves pooled over the splits (``precision_recall.pr_rows``).

    Pooled, not averaged: one θ (or k) applied to every split, each split with its own
    training thresholds; a mean of per-split R@100P would let every split pick its own θ.
    The per-place family curves need every query's raw_p, which a split of the blocked
    pass (``scale``) does not keep: there only the global and image-level curves come.
    """
    return pr_rows([
        PRSplit(s.outcomes, s.known, s.raw.max(axis=1) if s.raw.size else s.top,
                s.raw if s.raw.size else None, s.correct if s.raw.size else None, s.thresholds, s.spread)
        for s in splits
    ])


def _rates(o: Outcome, known: np.ndarray) -> dict[str, float]:
    acc = o.accepted
    right = o.right & known
    return {
        "known_recall1": float(right[known].mean()) if known.any() else np.nan,
        "unknown_rejection": float((~acc[~known]).mean()) if (~known).any() else np.nan,
        "precision": float(right.sum() / acc.sum()) if acc.any() else np.nan,
        "accepted": float(acc.mean()),
    }


def summarise(splits: list[SplitScores], ks: tuple[int, ...], *, own_traversal: bool) -> tuple[MethodRow, ...]:
    """One ``MethodRow`` per method of the splits: mean and std over the splits of each rate.

    Args:
        splits: the scored splits (every split holds the same methods).
        ks: the K of Recall@K.
        own_traversal: fill ``MethodRow.own_traversal`` (the share of accepted answers from the
            query's own traversal); ``None`` otherwise.
    """
    rows = []
    for key in splits[0].outcomes:
        m = METHODS_BY_KEY[key]
        per = {k: [] for k in ks}
        acc, prec, own, rej = [], [], [], []
        for s in splits:
            o = s.outcomes[key]
            r = _rates(o, s.known)
            for k in ks:
                per[k].append(float((o.rank[s.known] <= k).mean()) if s.known.any() else np.nan)
            acc.append(r["accepted"])
            prec.append(r["precision"])
            rej.append(r["unknown_rejection"])
            ok = o.accepted & (o.answer_image >= 0)
            own.append(float((s.train_traversal[o.answer_image[ok]] == s.query_traversal[ok]).mean()) if ok.any() else np.nan)
        has_unknown = any((~s.known).any() for s in splits)
        rows.append(MethodRow(
            key=key, label=m.label, source=m.source,
            recall={k: _mean_std(v) for k, v in per.items()},
            accepted=_mean_std(acc), precision=_mean_std(prec),
            own_traversal=_mean_std(own) if own_traversal else None,
            unknown_rejection=_mean_std(rej) if has_unknown else None,
            per_split={**{f"recall@{k}": tuple(v) for k, v in per.items()}, "accepted": tuple(acc),
                       "precision": tuple(prec), **({"own_traversal": tuple(own)} if own_traversal else {}),
                       **({"unknown_rejection": tuple(rej)} if has_unknown else {})},
        ))
    return tuple(rows)


def _tradeoff(splits: list[SplitScores], k_grid: Sequence[float]) -> tuple[TradeoffRow, ...]:
    rows: list[TradeoffRow] = []

    def add(series, rule, param, outcomes):
        rates = [_rates(o, s.known) for o, s in zip(outcomes, splits)]
        rows.append(TradeoffRow(
            series=series, rule=rule.value, param=float(param),
            **{name: _mean_std([r[name] for r in rates]) for name in ("known_recall1", "unknown_rejection", "precision", "accepted")},
            per_split={name: tuple(r[name] for r in rates)
                       for name in ("known_recall1", "unknown_rejection", "precision", "accepted")},
        ))

    for base in (ThresholdMethod.SIMPLE, ThresholdMethod.WEIGHTED):
        for rule in (Rule.MARGIN, Rule.RAW):
            for k in k_grid:
                add(f"θ_p(k) {base.value}", rule, k, [
                    _place_outcome(s.raw, s.best, threshold_family(s.thresholds[base.value], s.spread, k), rule, s.correct)
                    for s in splits
                ])
            add(f"adaptive k {base.value}", rule, np.nan, [
                _place_outcome(s.raw, s.best, s.thresholds[base.value] + s.k_adaptive * s.spread, rule, s.correct)
                for s in splits
            ])
    top = np.concatenate([s.raw.max(axis=1) for s in splits])
    grid = np.unique(np.round(np.quantile(top[np.isfinite(top)], np.linspace(0, 1, 21)), 4))
    for theta in grid:
        add("global θ", Rule.RAW, theta, [_place_outcome(s.raw, s.best, theta, Rule.RAW, s.correct) for s in splits])
    for key, series in (("auto", "global θ, automatic"), ("oracle", "global θ, oracle")):
        add(series, Rule.RAW, np.mean([s.thresholds[key] for s in splits]), [
            _place_outcome(s.raw, s.best, s.thresholds[key], Rule.RAW, s.correct) for s in splits
        ])
    return tuple(rows)


# --------------------------------------------------------------------------- protocols


def check_protocol_inputs(descriptors, image_place, image_traversal):
    """The inputs every pooled protocol takes, checked: descriptors and their labels.

    Returns:
        ``(descriptors, image_place, image_traversal)``: the descriptors as
        ``validate_descriptors`` returns them, the labels as ``(n_images,)`` arrays.

    Raises:
        VPRInputError: on bad descriptors, or labels of another length.
    """
    d = validate_descriptors(descriptors)
    image_place = np.asarray(image_place)
    image_traversal = np.asarray(image_traversal)
    if image_place.shape != (len(d),) or image_traversal.shape != (len(d),):
        raise VPRInputError(
            f"descriptors have {len(d)} rows but {image_place.shape} place labels and {image_traversal.shape} traversal labels"
        )
    return d, image_place, image_traversal


def place_members(image_place: np.ndarray, n_places: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Labelled images sorted by place (stable), with each place's start and size.

    Returns:
        ``(order, starts, sizes)``: ``order`` the image indices, place by place; ``starts`` and
        ``sizes`` ``(n_places,)``, each place's first position in ``order`` and its image count.
    """
    labelled = np.flatnonzero(image_place >= 0)
    order = labelled[np.argsort(image_place[labelled], kind="stable")]
    sizes = np.bincount(image_place[labelled], minlength=n_places)
    starts = np.r_[0, np.cumsum(sizes)[:-1]]
    return order, starts, sizes


def _require_two_per_place(sizes: np.ndarray, places: np.ndarray) -> None:
    few = places[sizes[places] < 2]
    if len(few):
        raise VPRInputError(
            f"place(s) {', '.join(map(str, few[:5]))}{' …' if len(few) > 5 else ''} have a single image: the paper "
            "protocol holds one image out as the query and needs another to train; raise group or add traversals"
        )


@dataclass(frozen=True, eq=False)
class Split:
    """One random split: query images (one per place), training images, unknown places."""

    queries: np.ndarray  # (n_queries,) image indices
    train: np.ndarray  # (n_train,) image indices
    unknown: np.ndarray  # (n_places,) bool, places held out of the database


def draw_splits(image_place: np.ndarray, n_places: int, *, runs: int, seed: int,
                unknown_share: float | None = None) -> list[Split]:
    """``runs`` splits seeded with ``seed``: each place gives one random query image; the rest train.

    With ``unknown_share``, that share of places (at least 1, leaving at least 2 known) is
    held out: their query stays, their other images leave the training set. The values are
    ``ProtocolOptions``' (checked there).
    """
    order, starts, sizes = place_members(image_place, n_places)
    places = np.flatnonzero(sizes > 0)
    _require_two_per_place(sizes, places)
    if len(places) < 2:
        raise VPRInputError("the paper protocol needs at least 2 places")
    n_unknown = 0
    if unknown_share is not None:
        if len(places) < 3:
            raise VPRInputError(f"{len(places)} places: the open set needs at least 3 (2 known, 1 unknown)")
        n_unknown = int(np.clip(round(unknown_share * len(places)), 1, len(places) - 2))
    labelled = image_place >= 0
    splits = []
    for ss in np.random.SeedSequence(seed).spawn(runs):
        rng = np.random.default_rng(ss)
        pick = order[starts[places] + (rng.random(len(places)) * sizes[places]).astype(np.int64)]
        unknown = np.zeros(n_places, dtype=bool)
        if n_unknown:
            unknown[rng.choice(places, n_unknown, replace=False)] = True
        train_mask = labelled & ~unknown[np.maximum(image_place, 0)]
        train_mask[pick] = False
        splits.append(Split(queries=pick, train=np.flatnonzero(train_mask), unknown=unknown))
    return splits


def pooled_truth(
    image_place: np.ndarray,
    image_frame: np.ndarray | None,
    frame_place: np.ndarray | None,
    tolerance: int,
    n_places: int,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Which places are right for every image as a query, with a frame tolerance.

    A place is right for a query when it holds a frame within ``tolerance`` frames of the
    query's frame (its own place always is). Returns ``(image, place)`` index pairs of the
    right places other than the image's own, or ``None`` when there are none (tolerance 0,
    or places further apart than the tolerance): then each query's own place is its only
    right place.

    Args:
        image_place: ``(n_images,)`` place of each image, ``-1`` for skipped frames.
        image_frame: ``(n_images,)`` frame index of each image in its traversal.
        frame_place: ``(n_frames,)`` place of each frame index, ``-1`` between places.
        tolerance: frames of slack, as ``ProtocolOptions.tolerance`` checks it.
    """
    if tolerance == 0:
        return None
    if image_frame is None or frame_place is None:
        raise VPRInputError("tolerance needs each image's frame and each frame's place (image_frame, frame_place)")
    labelled = np.flatnonzero(image_place >= 0)
    truth = query_truth(np.asarray(image_frame)[labelled], np.asarray(frame_place), tolerance)
    truth = np.pad(truth, ((0, 0), (0, max(0, n_places - truth.shape[1]))))[:, :n_places]
    truth[np.arange(len(labelled)), image_place[labelled]] = False
    i, p = np.nonzero(truth)
    return (labelled[i], p) if len(i) else None


def check_cross_condition(image_place: np.ndarray, image_traversal: np.ndarray, options: ProtocolOptions) -> None:
    """Refuse ``cross_condition`` on images of one traversal (no query would have anything to match)."""
    if options.cross_condition and len(np.unique(image_traversal[image_place >= 0])) < 2:
        raise VPRInputError("cross_condition needs at least 2 traversals")


def _pooled_splits(d, image_place, image_traversal, n_places, options: ProtocolOptions, *, open_set: bool,
                   progress, extra_truth=None, shared: SharedScores | None = None) -> list[SplitScores]:
    """Every split of the paper / open-set protocol, scored (``run_split``).

    With ``shared`` (``shared_scores.resolve``: up to ``SHARED_LIMIT`` images), the queries'
    scores come from its float32 similarity of all images and each split's negative
    statistics pairwise from its float64 Gram; without, each split scores its queries
    against its training images and fits the statistics in closed form. The automatic θ of
    every split comes from one tile sample of the run (``thresholds.pooled_pair_sample``,
    seeded with ``options.seed``), as ``scale.scale_splits`` takes it.
    """
    check_cross_condition(image_place, image_traversal, options)
    splits = draw_splits(image_place, n_places, runs=options.runs, seed=options.seed,
                         unknown_share=options.unknown_share if open_set else None)
    sample = pooled_pair_sample(d, [sp.train for sp in splits], seed=options.seed)
    full = shared.full() if shared is not None else None
    negatives = Negatives(shared.gram(), np.flatnonzero(image_place >= 0)) if shared is not None else None
    extra = None
    if extra_truth is not None:  # image -> its other right places, as a sparse (image, place) list
        extra = np.zeros((len(d), n_places), dtype=bool) if len(d) * n_places <= 50_000_000 else None
        if extra is None:
            raise VPRInputError(f"tolerance on {len(d):,} images × {n_places:,} places: too large for the "
                                "straightforward protocol; use tolerance 0 or larger step")
        extra[extra_truth] = True
    out = []
    for r, sp in enumerate(splits):
        pick, train = sp.queries, sp.train
        sims = full[np.ix_(pick, train)] if full is not None else similarity(d[pick], d[train])
        correct = np.zeros((len(pick), n_places), dtype=bool)
        known = ~sp.unknown[image_place[pick]]
        correct[np.flatnonzero(known), image_place[pick][known]] = True
        if extra is not None:  # neighbouring places within the frame tolerance, if they are in the database
            correct |= extra[pick] & ~sp.unknown[None, :]
        stats = negatives.stats(train, image_place[train], n_places) if negatives is not None else None
        out.append(run_split(
            d[train], image_place[train], image_traversal[train], sims, correct, image_traversal[pick], n_places,
            cross_condition=options.cross_condition, user_theta=options.user_theta, seed=options.seed + r,
            stats=stats, auto_theta=sample.theta(r),
        ))
        if progress:
            progress(r + 1, options.runs, f"split {r + 1}/{options.runs}")
    return out


def own_traversal_notes(options: ProtocolOptions) -> tuple[str, ...]:
    """The paper protocol's note on what it measures when queries see their own traversal."""
    if options.cross_condition:
        return ()
    return ("queries are matched against all traversals, their own included: see the own-traversal share, and the "
            "cross-condition variant",)


def paper_settings(options: ProtocolOptions, settings: dict | None, queries_per_run: int) -> dict:
    """The paper protocol's ``Evaluation.settings``: the caller's, then the run's own."""
    return {**(settings or {}), "runs": options.runs, "seed": options.seed, "cross_condition": options.cross_condition,
            "tolerance": options.tolerance, "queries_per_run": queries_per_run}


def paper_protocol(
    descriptors: np.ndarray,
    image_place: np.ndarray,
    image_traversal: np.ndarray,
    n_places: int,
    options: ProtocolOptions = ProtocolOptions(),
    *,
    image_frame: np.ndarray | None = None,
    frame_place: np.ndarray | None = None,
    progress: Progress | None = None,
    settings: dict | None = None,
    shared: SharedScores | None = None,
) -> Evaluation:
    """The paper's closed-set protocol over ``options.runs`` seeded splits.

    Reads ``options``' runs, seed, cross_condition, user_theta, ks, tolerance and pr.

    Args:
        descriptors: ``(n_images, D)`` L2-normalised.
        image_place: ``(n_images,)`` place of each image, ``-1`` for skipped frames.
        image_traversal: ``(n_images,)`` traversal of each image.
        image_frame, frame_place: ``(n_images,)`` frame of each image and ``(n_frames,)`` place
            of each frame, which a tolerance above 0 needs (a place holding a frame within
            ``options.tolerance`` frames of the query's frame is right too).
        settings: what the caller records in ``Evaluation.settings`` beside the run's own.
        shared: ``shared_scores.SharedScores`` of these same ``descriptors`` (a sweep shares one
            between its cells); up to ``SHARED_LIMIT`` images one is built when not given, so
            the numbers are the same either way, bit for bit. Not used above the limit.
    """
    t0 = time.perf_counter()
    d, image_place, image_traversal = check_protocol_inputs(descriptors, image_place, image_traversal)
    shared = resolve(shared, descriptors, len(d))
    extra = pooled_truth(image_place, image_frame, frame_place, options.tolerance, n_places)
    splits = _pooled_splits(d, image_place, image_traversal, n_places, options, open_set=False, progress=progress,
                            extra_truth=extra, shared=shared)
    pr_rows_, pr_curves = split_pr(splits) if options.pr else ((), {})
    return Evaluation(
        protocol=Protocol.PAPER, settings=paper_settings(options, settings, len(splits[0].known)),
        ks=options.ks, rows=summarise(splits, options.ks, own_traversal=True), notes=own_traversal_notes(options),
        seconds=time.perf_counter() - t0, pr=pr_rows_, pr_curves=pr_curves,
    )


def open_set_protocol(
    descriptors: np.ndarray,
    image_place: np.ndarray,
    image_traversal: np.ndarray,
    n_places: int,
    options: ProtocolOptions = ProtocolOptions(),
    *,
    image_frame: np.ndarray | None = None,
    frame_place: np.ndarray | None = None,
    progress: Progress | None = None,
    settings: dict | None = None,
    shared: SharedScores | None = None,
) -> Evaluation:
    """Open set: ``options.unknown_share`` of the places are held out of the database in each split.

    Reads what ``paper_protocol`` reads, and unknown_share and k_grid; the other arguments as
    for it: a query of a held-out place with a known place within the tolerance counts as a
    known-place query.
    """
    t0 = time.perf_counter()
    d, image_place, image_traversal = check_protocol_inputs(descriptors, image_place, image_traversal)
    shared = resolve(shared, descriptors, len(d))
    extra = pooled_truth(image_place, image_frame, frame_place, options.tolerance, n_places)
    splits = _pooled_splits(d, image_place, image_traversal, n_places, options, open_set=True, progress=progress,
                            extra_truth=extra, shared=shared)
    n_unknown = int((~splits[0].known).sum())
    pr_rows_, pr_curves = split_pr(splits) if options.pr else ((), {})
    return Evaluation(
        protocol=Protocol.OPEN_SET,
        settings={**(settings or {}), "runs": options.runs, "seed": options.seed,
                  "unknown_share": options.unknown_share, "unknown_places_per_run": n_unknown,
                  "known_places_per_run": int(splits[0].known.sum()), "cross_condition": options.cross_condition,
                  "tolerance": options.tolerance, "k_grid": list(options.k_grid)},
        ks=options.ks, rows=summarise(splits, options.ks, own_traversal=True),
        tradeoff=_tradeoff(splits, options.k_grid),
        notes=("the oracle global θ is chosen knowing which queries are unknown: an upper bound, not a method",),
        seconds=time.perf_counter() - t0, pr=pr_rows_, pr_curves=pr_curves,
    )


def query_truth(query_frames: np.ndarray, frame_place: np.ndarray, tolerance: int) -> np.ndarray:
    """``(n_queries, n_places)`` bool: ``places.right_places``, the one between-place rule (kept under this name)."""
    return right_places(query_frames, frame_place, tolerance)


# --------------------------------------------------------------------------- database and queries with a relation


class RetrievalTally:
    """The database/queries protocol's outcomes, block of queries by block, and the table they make.

    Shared by ``retrieval_protocol`` and ``numbers.evaluate_fitted`` (a memory-mapped
    database): they differ in how a block's scores and its image-level answers are computed,
    not in what is counted.

    Args:
        th: the thresholds (``_thresholds``' dict); the oracle θ is added by ``table``.
        placed, labels: database positions of the images in a place, and their places.
        n_queries, n_database: queries and database images in all; with ``pr``, every query's raw_p is
            kept up to ``PR_RAW_CELLS``.
    """

    def __init__(self, th: dict, n_places: int, placed: np.ndarray, labels: np.ndarray, *, n_queries: int,
                 n_database: int, pr: bool) -> None:
        self.th, self.n_places, self.placed, self.labels, self.pr = th, n_places, placed, labels, pr
        self.place_methods = tuple(m for m in METHODS_BY_KEY.values() if m.level == "place" and m.key != "global-oracle"
                                   and (m.threshold is None or m.threshold in th))
        self.keep_raw = pr and n_queries * n_places <= PR_RAW_CELLS
        self.n_queries, self.n_database = n_queries, n_database
        self.parts: dict[str, list[Outcome]] = {}
        self.tops: list[np.ndarray] = []
        self.bests: list[np.ndarray] = []
        self.base_right: list[np.ndarray] = []
        self.place_known: list[np.ndarray] = []
        self.raws: list[np.ndarray] = []
        self.corrects: list[np.ndarray] = []
        self.image_tops: list[np.ndarray] = []

    def add(self, sims: np.ndarray, correct: np.ndarray, image: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
        """One block of queries: ``sims`` ``(rows, n_database)``, ``correct`` ``(rows, n_places)`` their right
        places, ``image`` their image-level (answer, rank, top score) over every database image."""
        sims_placed = sims[:, self.placed]
        raw, best = place_scores(sims_placed, self.labels, self.n_places)
        out = score_queries(sims_placed, self.labels, self.n_places, self.th, correct, self.place_methods,
                            raw_best=(raw, best))
        for key, o in out.items():  # answers as database positions
            img = np.where(o.answer_image >= 0, self.placed[np.maximum(o.answer_image, 0)], -1)
            self.parts.setdefault(key, []).append(Outcome(o.method, o.rank, o.answer_place, img, o.n_kept))
        answer, rank, top = image
        self.parts.setdefault("image-baseline", []).append(Outcome(
            METHODS_BY_KEY["image-baseline"], rank, answer, answer, np.full(len(sims), self.n_database)))
        self.tops.append(raw.max(axis=1))
        self.bests.append(np.where(correct, raw, -np.inf).max(axis=1))
        if self.pr:
            self.image_tops.append(top)
        if self.keep_raw:  # raw_p is a float32 score: exact in float32
            self.raws.append(raw.astype(np.float32))
            self.corrects.append(correct)
        self.base_right.append(out["place-baseline"].rank == 1)
        self.place_known.append(correct.any(axis=1))

    def evaluation(self, ground_truth: GroundTruth, spread: np.ndarray, k_ad: np.ndarray, ks: tuple[int, ...], *,
                   settings: dict | None, started: float, notes: Sequence[str] = ()) -> Evaluation:
        """The protocol's ``Evaluation`` once every query is added (``started``: its ``time.perf_counter()``;
        ``notes``: the caller's, after the table's own)."""
        rows_, pr_rows_, pr_curves, own, scored = self._table(ground_truth.known, spread, k_ad, ks)
        return Evaluation(
            protocol=Protocol.DATABASE,
            settings={**(settings or {}), "ground_truth": ground_truth.description, "queries": int(self.n_queries),
                      "database_images": int(self.n_database), "database_images_in_places": int(len(self.placed)),
                      "queries_without_positive": int(ground_truth.n_unknown),
                      "queries_between_places": int((~scored).sum())},
            ks=ks, rows=rows_, seconds=time.perf_counter() - started, pr=pr_rows_, pr_curves=pr_curves,
            notes=("image level: a query counts at K when one of its top K database images is a positive; place "
                   "level: when the top K places hold one", *own, *notes),
        )

    def _table(self, known_any: np.ndarray, spread: np.ndarray, k_ad: np.ndarray, ks: tuple[int, ...]):
        """``(rows, pr_rows, pr_curves, notes, scored)`` once every query is added; ``known_any``: each query
        has a positive at all (``GroundTruth.known``); ``scored``: the queries the place level counts."""
        th, n_places = self.th, self.n_places
        outcomes = {key: Outcome.joined(ps) for key, ps in self.parts.items()}
        known = np.concatenate(self.place_known)
        top = np.concatenate(self.tops)
        # place level: queries whose positives all lie outside places are left out (places.BETWEEN_PLACES_RULE);
        # queries with no positive at all stay, as unknown
        scored = known | ~known_any
        th["oracle"] = oracle_global_threshold(top[scored], np.concatenate(self.base_right)[scored], known[scored])
        base = outcomes["place-baseline"]
        # the raw rule with one θ: the right place stays iff its raw ≥ θ, and then so does every place
        # above it, so the rank is the baseline's; the top answer stays iff it is ≥ θ
        acc = top >= th["oracle"]
        outcomes["global-oracle"] = Outcome(METHODS_BY_KEY["global-oracle"],
                                            np.where(np.concatenate(self.bests) >= th["oracle"], base.rank, np.inf),
                                            np.where(acc, base.answer_place, -1), np.where(acc, base.answer_image, -1),
                                            base.n_kept)
        order = ["image-baseline", *[m.key for m in self.place_methods], "global-oracle"]
        outcomes = {k: outcomes[k] for k in order}
        empty = np.empty((0, n_places))

        def summary(outs: dict[str, Outcome], known_rows: np.ndarray) -> tuple[MethodRow, ...]:
            split = SplitScores(outs, empty, empty.astype(np.int64), empty.astype(bool), known_rows,
                                np.zeros(len(known_rows), dtype=np.int64), np.ones(self.n_database, dtype=np.int64),
                                th, spread, k_ad)
            return summarise([split], ks, own_traversal=False)

        place_outs = {k: Outcome(o.method, o.rank[scored], o.answer_place[scored], o.answer_image[scored],
                                 o.n_kept[scored]) for k, o in outcomes.items()}
        rows_ = list(summary(place_outs, known[scored]))
        rows_[0] = summary(outcomes, known_any)[0]  # the image level counts every query
        pr_rows_, pr_curves, notes = (), {}, []
        if self.pr:
            image_rows, image_curves = pr_rows([PRSplit({"image-baseline": outcomes["image-baseline"]}, known_any,
                                                        np.concatenate(self.image_tops))])
            raws = np.concatenate(self.raws)[scored] if self.keep_raw else None
            corrects = np.concatenate(self.corrects)[scored] if self.keep_raw else None
            place_rows, place_curves = pr_rows([PRSplit(
                {k: o for k, o in place_outs.items() if k != "image-baseline"}, known[scored], top[scored],
                raws, corrects, th, spread)])
            pr_rows_, pr_curves = (*image_rows, *place_rows), {**image_curves, **place_curves}
            if not self.keep_raw:
                notes.append(f"precision–recall of the per-place methods left out: {self.n_queries:,} queries × "
                             f"{n_places:,} places exceed {PR_RAW_CELLS:,} raw_p cells")
        return tuple(rows_), pr_rows_, pr_curves, notes, scored


#: the K of VPR-methods-evaluation's recall line (its default ``--recall_values`` begin 1, 5, 10)
EVERY_QUERY_KS = (1, 5, 10)


def recall_over_every_query(ev: Evaluation) -> dict[int, float] | None:
    """The image-level Recall@1/5/10 over every query, as VPR-methods-evaluation counts them.

    VME divides the queries whose top K database images hold a positive by every query
    (``recalls / eval_ds.queries_num``); the image-level row divides them by the queries with
    a positive (a query with none is an unknown place and never a hit). With ``n`` queries of
    which ``u`` have no positive, R_VME@K = hits@K / n, hits@K = R@K · (n − u) (an integer,
    rounded off float error). The two agree when ``u = 0``.

    Returns:
        ``{K: rate in [0, 1]}`` for each K of :data:`EVERY_QUERY_KS` the evaluation counted, or
        ``None`` for a protocol other than database-queries.
    """
    if ev.protocol is not Protocol.DATABASE:
        return None
    n = int(ev.settings["queries"])
    known = n - int(ev.settings["queries_without_positive"])
    image = next(r for r in ev.rows if r.key == "image-baseline")
    out = {}
    for k in EVERY_QUERY_KS:
        if k in image.recall:
            rate = image.recall[k][0]
            hits = round(rate * known) if known and math.isfinite(rate) else 0
            out[k] = hits / n if n else 0.0
    return out


def retrieval_protocol(
    database: np.ndarray,
    queries: np.ndarray,
    database_place: np.ndarray,
    n_places: int,
    ground_truth: GroundTruth,
    options: ProtocolOptions = ProtocolOptions(),
    *,
    settings: dict | None = None,
    progress: Progress | None = None,
    block: int = 2048,
) -> Evaluation:
    """A database against queries with ground truth as a relation (``groundtruth.GroundTruth``).

    Thresholds come from the database images that belong to a place. Recall is counted as
    the field counts it: the image-level baseline ranks every database image (a query
    counts at K when one of its top K is a positive, ties against it), over the queries
    with a positive; the place-level methods rank places, a place being right when it
    holds a positive, over the queries with a positive inside some place. Queries with no
    positive are unknown-place queries: counted apart (their rejection rate), never as
    misses. Reads ``options``' user_theta, ks and pr.

    Args:
        database: ``(n_database, D)``; queries: ``(n_queries, D)``; both L2-normalised.
        database_place: ``(n_database,)`` place of each database image, ``-1`` outside places.
        ground_truth: a ``GroundTruth`` of ``n_queries`` rows over ``n_database`` images.
        options: with ``pr``, the precision–recall rows and curves too; the per-place family
            curves only up to ``PR_RAW_CELLS`` queries × places (they need every query's raw_p).
        settings: what the caller records in ``Evaluation.settings`` beside the run's own.
        block: queries scored at a time (memory: block × n_database float32).
    """
    t0 = time.perf_counter()
    db = validate_descriptors(database)
    q = validate_descriptors(queries)
    database_place = np.asarray(database_place, dtype=np.int64)
    if not isinstance(ground_truth, GroundTruth):
        raise VPRInputError("ground_truth: give a groundtruth.GroundTruth")
    if ground_truth.n_queries != len(q) or ground_truth.n_database != len(db) or database_place.shape != (len(db),):
        raise VPRInputError(
            f"ground truth of {ground_truth.n_queries} × {ground_truth.n_database} for {len(q)} queries and "
            f"{len(db)} database images ({len(database_place)} place labels)"
        )
    if db.shape[1] != q.shape[1]:
        raise VPRInputError(f"database descriptors are {db.shape[1]}-d but query descriptors {q.shape[1]}-d")
    placed = np.flatnonzero(database_place >= 0)
    if len(np.unique(database_place[placed])) < 2:
        raise VPRInputError("the database holds fewer than 2 places: negative statistics need at least 2; "
                            "lower group or step")
    labels = database_place[placed]
    th, spread, k_ad = _thresholds(db[placed], labels, n_places, user_theta=options.user_theta, seed=0)
    tally = RetrievalTally(th, n_places, placed, labels, n_queries=len(q), n_database=len(db), pr=options.pr)
    for lo in range(0, len(q), block):
        rows = np.arange(lo, min(lo + block, len(q)))
        sims = similarity(q[rows], db)
        img_scores = np.asarray(sims, dtype=np.float64)
        # the image level answers with a database image, in a place or not: its "place" here is that image
        tally.add(sims, ground_truth.places(database_place, n_places, rows),
                  (top_answer(img_scores), pessimistic_rank(img_scores, ground_truth.dense(rows)),
                   img_scores.max(axis=1)))
        if progress:
            progress(int(rows[-1]) + 1, len(q), f"queries {int(rows[-1]) + 1}/{len(q)}")
    return tally.evaluation(ground_truth, spread, k_ad, options.ks, settings=settings, started=t0)
