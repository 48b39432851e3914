"""Retrieval: the image- and place-level baselines and filter-then-rank.

For a query q and place p, raw_p = max over p's database images i of s(q, i).

| method                 | rule                                                          |
|------------------------|---------------------------------------------------------------|
| image-level baseline   | rank database images by s(q, i)                                |
| place-level baseline   | rank places by raw_p                                           |
| margin (paper text)    | m_p = raw_p − θ_p; drop m_p < 0; rank the rest by m_p          |
| raw (authors' code)    | drop raw_p < θ_p; rank the rest by raw_p                       |
| global threshold       | the raw rule with one θ for every place                        |

**Ties** are scores within ``TIE_TOLERANCE`` (1e-5) of each other, and they count against
the query: the rank of the true place is 1 + the number of wrong candidates scoring at
least its score − 1e-5. An answer is the lowest-index candidate within 1e-5 of the top
score, and the image behind raw_p the lowest-index image of the place within 1e-5 of it.
Exact float equality would be a rule about summation order: the same two byte-identical
images (GardensPoint night frames 179 and 183, Nordland's tunnel frames) score 1.0 or
0.99999994 against one query depending on the BLAS kernel, the block shape and the
threads, so every path (a loop, a blocked pass, the app, a recording) agrees only with a
tolerance well above that rounding (~1e-7 for float32 products of unit vectors) and well
below any difference that tells two places apart. Comparisons with a threshold stay exact
(raw_p ≥ θ_p): a score is kept or dropped, never "tied" with a threshold.

A query for which every place is dropped is **rejected**.

Similarity matrices are ``(n_queries, n_database)`` throughout, except the database-major
``(n_database, n_queries)`` ones of ``similarity_t`` and the place layout (``PlaceLayout``),
which the fused decisions of ``views.numbers.decide_queries`` use.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from vpr_explorer.errors import VPRInputError

#: Scores within this of each other tie (module doc): ranks count such ties against the
#: query, and answers go to the lowest index among them.
TIE_TOLERANCE = 1e-5


class Rule(StrEnum):
    """How a threshold filters and ranks places."""

    NONE = "none"
    MARGIN = "margin"
    RAW = "raw"


@dataclass(frozen=True)
class Method:
    """One row of the comparison: a ranking level, a rule and which threshold it uses."""

    key: str
    label: str
    level: str  # "image" or "place"
    rule: Rule
    threshold: str | None  # key into the thresholds mapping
    source: str


METHODS: tuple[Method, ...] = (
    Method("image-baseline", "image-level baseline", "image", Rule.NONE, None, "authors' code 'Baseline'"),
    Method("place-baseline", "place-level baseline", "place", Rule.NONE, None, "no threshold, place level"),
    Method("margin-simple", "margin, simple θ", "place", Rule.MARGIN, "simple", "paper text"),
    Method("margin-weighted", "margin, weighted θ", "place", Rule.MARGIN, "weighted", "paper text"),
    Method("raw-simple", "raw, simple θ", "place", Rule.RAW, "simple", "authors' code"),
    Method("raw-weighted", "raw, weighted θ", "place", Rule.RAW, "weighted", "authors' code"),
    Method("global-auto", "global θ, automatic", "place", Rule.RAW, "auto", "VPR_Tutorial, Beyond ANN"),
    Method("global-oracle", "global θ, oracle", "place", Rule.RAW, "oracle", "best single θ on this data"),
    Method("global-user", "global θ, user value", "place", Rule.RAW, "user", "a value you set"),
)
METHODS_BY_KEY = {m.key: m for m in METHODS}


def methods_for(thresholds: dict[str, object]) -> tuple[Method, ...]:
    """The methods whose threshold is available in ``thresholds``."""
    return tuple(m for m in METHODS if m.threshold is None or m.threshold in thresholds)


def similarity(queries: np.ndarray, database: np.ndarray) -> np.ndarray:
    """``(n_queries, n_database)`` cosine similarity of L2-normalised descriptors."""
    return np.asarray(queries, dtype=np.float32) @ np.asarray(database, dtype=np.float32).T


def similarity_t(database: np.ndarray, queries: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """``similarity(queries, database).T``, computed as ``(n_database, n_queries)`` (into ``out``).

    How each number is rounded is the BLAS kernel's: OpenBLAS's SkylakeX kernel computes each
    as one dot product in the same order whichever operand comes first, so on products of a
    few hundred rows and queries these are ``similarity``'s numbers bit for bit (the 110k-image
    route in ``benchmarks/bench_app_scale.py --move-only`` checks it); its Haswell kernel
    (``OPENBLAS_CORETYPE=Haswell``) rounds by operand order and position, a few ulp (≤ 3e-7
    measured), as tiny products (one query, a few rows) do on any kernel. The tolerance rule
    (module doc) absorbs that: ``tests/test_decide_fused.py`` allows a decision to differ only
    where a score lies within 5e-7 of a boundary.
    """
    return np.matmul(np.asarray(database, dtype=np.float32), np.asarray(queries, dtype=np.float32).T, out=out)


def place_scores(
    sims: np.ndarray, db_places: np.ndarray, n_places: int
) -> tuple[np.ndarray, np.ndarray]:
    """raw_p and the image that attains it, for every query and place.

    Args:
        sims: ``(n_queries, n_database)`` similarities; ``-inf`` marks an excluded image.
        db_places: ``(n_database,)`` place of each database image (``>= 0``).
        n_places: number of place ids.
    Returns:
        raw: ``(n_queries, n_places)`` best score per place, ``-inf`` where a place has no
            (non-excluded) database image.
        best: ``(n_queries, n_places)`` the lowest-index database image of the place scoring
            within ``TIE_TOLERANCE`` of raw, ``-1`` where raw is ``-inf``.
    """
    sims = np.atleast_2d(sims)
    db_places = np.asarray(db_places)
    if sims.shape[1] != len(db_places):
        raise VPRInputError(f"similarity has {sims.shape[1]} database columns but {len(db_places)} place labels")
    nq = sims.shape[0]
    order = np.argsort(db_places, kind="stable")
    sorted_places = db_places[order]
    starts = np.flatnonzero(np.r_[True, sorted_places[1:] != sorted_places[:-1]])
    present = sorted_places[starts]
    sizes = np.diff(np.r_[starts, len(order)])
    cols = sims[:, order]
    seg_max = np.maximum.reduceat(cols, starts, axis=1)
    hit = cols >= np.repeat(seg_max, sizes, axis=1) - TIE_TOLERANCE
    first = np.minimum.reduceat(np.where(hit, order[None, :], len(order)), starts, axis=1)
    raw = np.full((nq, n_places), -np.inf, dtype=np.float64)
    best = np.full((nq, n_places), -1, dtype=np.int64)
    raw[:, present] = seg_max
    best[:, present] = first
    best[~np.isfinite(raw)] = -1
    return raw, best


def place_mean_scores(sims: np.ndarray, db_places: np.ndarray, n_places: int) -> np.ndarray:
    """The mean of each place's similarities, for every query and place (the authors' follow-up's place score).

    Args:
        sims: ``(n_queries, n_database)`` similarities.
        db_places: ``(n_database,)`` place of each database image (``>= 0``).
        n_places: number of place ids.
    Returns:
        ``(n_queries, n_places)`` float64: Σ s(q, i) / n_p over p's images i, summed in database
        order in float64; ``-inf`` where a place has no database image.
    """
    sims = np.atleast_2d(np.asarray(sims, dtype=np.float64))
    db_places = np.asarray(db_places)
    if sims.shape[1] != len(db_places):
        raise VPRInputError(f"similarity has {sims.shape[1]} database columns but {len(db_places)} place labels")
    if len(db_places) and (db_places.min() < 0 or db_places.max() >= n_places):
        raise VPRInputError(f"db_places: give the place (0 to {n_places - 1}) of every database image")
    order = np.argsort(db_places, kind="stable")
    sorted_places = db_places[order]
    out = np.full((sims.shape[0], n_places), -np.inf, dtype=np.float64)
    if not len(order):
        return out
    starts = np.flatnonzero(np.r_[True, sorted_places[1:] != sorted_places[:-1]])
    sizes = np.diff(np.r_[starts, len(order)])
    out[:, sorted_places[starts]] = np.add.reduceat(sims[:, order], starts, axis=1) / sizes
    return out

def ranking_scores(raw: np.ndarray, theta: np.ndarray | float | None, rule: Rule) -> np.ndarray:
    """Scores that rank places under ``rule``; ``-inf`` where a place is dropped.

    ``theta`` broadcasts against ``raw`` (a scalar, ``(n_places,)`` or ``(n_queries, n_places)``);
    a NaN θ (a place without training images) drops the place.
    """
    if rule is Rule.NONE:
        return np.array(raw, dtype=np.float64)
    if theta is None:
        raise VPRInputError(f"the {rule.value} rule needs a threshold")
    theta = np.asarray(theta, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        kept = raw >= theta  # NaN θ or -inf raw compare False
        if rule is Rule.MARGIN:
            return np.where(kept, raw - theta, -np.inf)
    return np.where(kept, raw, -np.inf)


def pessimistic_rank(scores: np.ndarray, correct: np.ndarray) -> np.ndarray:
    """``(n_queries,)`` rank of the best correct candidate, ties counted against the query.

    Args:
        scores: ``(n_queries, n_candidates)``; ``-inf`` marks a dropped candidate.
        correct: ``(n_queries, n_candidates)`` bool, which candidates are right answers.
    Returns:
        1 + the number of wrong candidates scoring at least the best correct one's score
        − ``TIE_TOLERANCE``; ``inf`` where no correct candidate is kept (or the query has none).
    """
    best = np.where(correct, scores, -np.inf).max(axis=1)
    above = ((scores >= best[:, None] - TIE_TOLERANCE) & ~correct).sum(axis=1)
    rank = 1.0 + above
    rank[~np.isfinite(best)] = np.inf
    return rank


def top_answer(scores: np.ndarray) -> np.ndarray:
    """``(n_queries,)`` the lowest index scoring within ``TIE_TOLERANCE`` of the top, ``-1`` if all dropped."""
    top = np.max(scores, axis=1)
    idx = np.argmax(scores >= top[:, None] - TIE_TOLERANCE, axis=1)
    idx[~np.isfinite(top)] = -1
    return idx


@dataclass(frozen=True, eq=False)
class Outcome:
    """What one method did for a batch of queries, each array ``(n_queries,)``.

    Attributes:
        rank: pessimistic rank of the true place (``inf`` if dropped or unknown).
        answer_place: answered place, ``-1`` if rejected.
        answer_image: database image behind the answer (for the own-traversal share), ``-1`` if rejected.
        n_kept: places (images, for the image level) that passed the filter.
    """

    method: Method
    rank: np.ndarray
    answer_place: np.ndarray
    answer_image: np.ndarray
    n_kept: np.ndarray

    @property
    def accepted(self) -> np.ndarray:
        return self.answer_place >= 0

    @property
    def right(self) -> np.ndarray:
        """Accepted with the true place at rank 1 (a tie at the top counts as wrong)."""
        return self.accepted & (self.rank == 1)

    @classmethod
    def joined(cls, blocks: Sequence[Outcome]) -> Outcome:
        """One method's outcomes of consecutive blocks of queries, as one ``Outcome`` (queries in block order).

        Args:
            blocks: outcomes of the same method, at least one.

        Returns:
            The outcome of every query of the blocks.
        """
        return cls(blocks[0].method, *(np.concatenate([getattr(b, f) for b in blocks])
                                       for f in ("rank", "answer_place", "answer_image", "n_kept")))


def score_queries(
    sims: np.ndarray,
    db_places: np.ndarray,
    n_places: int,
    thresholds: dict[str, np.ndarray | float],
    correct: np.ndarray,
    methods: tuple[Method, ...] | None = None,
    raw_best: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict[str, Outcome]:
    """Run every method on a batch of queries.

    Args:
        sims: ``(n_queries, n_database)`` similarities (``-inf`` excludes an image).
        db_places: ``(n_database,)`` place of each database image.
        n_places: number of place ids.
        thresholds: threshold key (``simple``, ``weighted``, ``auto``, ``oracle``, ``user`` …)
            -> θ, a scalar or ``(n_places,)`` or ``(n_queries, n_places)``.
        correct: ``(n_queries, n_places)`` bool, the right places of each query (none for an
            unknown-place query).
        methods: which methods; default every method whose threshold is given.
        raw_best: ``place_scores(sims, db_places, n_places)`` when the caller has it already.
    """
    methods = methods_for(thresholds) if methods is None else methods
    raw, best = place_scores(sims, db_places, n_places) if raw_best is None else raw_best
    out: dict[str, Outcome] = {}
    for m in methods:
        if m.level == "image":
            scores = np.asarray(sims, dtype=np.float64)
            image_correct = correct[:, db_places]
            rank = pessimistic_rank(scores, image_correct)
            img = top_answer(scores)
            place = np.where(img >= 0, db_places[img], -1)
            kept = np.isfinite(scores).sum(axis=1)
            out[m.key] = Outcome(method=m, rank=rank, answer_place=place, answer_image=img, n_kept=kept)
        else:
            out[m.key] = _place_outcome(m, raw, best, thresholds, correct)
    return out


def _place_outcome(
    m: Method, raw: np.ndarray, best: np.ndarray, thresholds: dict[str, np.ndarray | float], correct: np.ndarray
) -> Outcome:
    """One place-level method's ``Outcome`` from raw_p and the image behind it (``score_queries``)."""
    theta = None if m.threshold is None else thresholds[m.threshold]
    scores = ranking_scores(raw, theta, m.rule)
    rank = pessimistic_rank(scores, correct)
    place = top_answer(scores)
    img = np.where(place >= 0, best[np.arange(len(raw)), np.maximum(place, 0)], -1)
    return Outcome(method=m, rank=rank, answer_place=place, answer_image=img, n_kept=np.isfinite(scores).sum(axis=1))


# --------------------------------------------------------------------------- database rows grouped by place


@dataclass(frozen=True, eq=False)
class PlaceLayout:
    """Database images ordered so that a place's images are adjacent rows, places of one size in runs.

    Places are ordered by size, then id; a place's images by database index. A run of ``g``
    places of size ``k`` starting at row ``r`` is then ``scores[r : r + g·k].reshape(g, k, n_queries)``
    for database × query scores in this order, and raw_p is a maximum over its middle axis:
    no column gather and no ``reduceat`` (``layout_place_scores``). The lowest-index image of
    a place is its first row, so "the lowest index within the tolerance" is the first hit.

    Attributes:
        order: ``(n_database,)`` database index of each row.
        places: ``(n_groups,)`` place of each group of rows (the places with database images).
        runs: ``(row, group, n_groups, k)`` for each run of places of size ``k``.
        n_places: number of place ids.
    """

    order: np.ndarray
    places: np.ndarray
    runs: tuple[tuple[int, int, int, int], ...]
    n_places: int

    @classmethod
    def of(cls, db_places: np.ndarray, n_places: int) -> PlaceLayout:
        db_places = np.asarray(db_places)
        if db_places.ndim != 1 or not len(db_places) or db_places.min() < 0 or db_places.max() >= n_places:
            raise VPRInputError(f"db_places: expected database place ids in 0..{n_places - 1}")
        counts = np.bincount(db_places, minlength=n_places)
        order = np.lexsort((np.arange(len(db_places)), db_places, counts[db_places]))
        sorted_places = db_places[order]
        starts = np.flatnonzero(np.r_[True, sorted_places[1:] != sorted_places[:-1]])
        places = sorted_places[starts]
        sizes = counts[places]
        run_starts = np.flatnonzero(np.r_[True, sizes[1:] != sizes[:-1]])
        run_ends = np.r_[run_starts[1:], len(places)]
        runs = tuple((int(starts[a]), int(a), int(b - a), int(sizes[a])) for a, b in zip(run_starts, run_ends))
        return cls(order=order, places=places, runs=runs, n_places=int(n_places))

    def pieces(self, rows: int) -> list[tuple[int, int, int, int]]:
        """The runs cut into pieces of whole places, at most ``rows`` rows each (or one place)."""
        out = []
        for row, group, n, k in self.runs:
            step = max(1, rows // k)
            out += [(row + g * k, group + g, min(step, n - g), k) for g in range(0, n, step)]
        return out


def layout_place_scores(
    scores_t: np.ndarray, layout: PlaceLayout, piece: tuple[int, int, int, int], raw_t: np.ndarray, best_t: np.ndarray
) -> None:
    """raw_p and the image behind it for the places of one piece (``place_scores``, in the layout).

    Args:
        scores_t: ``(n_database, n_queries)`` float32 similarities, rows in ``layout.order``.
        piece: ``(row, group, n_groups, k)`` from ``layout.pieces``.
        raw_t, best_t: ``(n_groups, n_queries)`` outputs: the place maxima (float32, exact), and
            the database index of the first image of the place within ``TIE_TOLERANCE`` of
            them, the tolerance subtracted in the scores' precision as ``place_scores`` does
            (for a NaN maximum, an image of the place).
    """
    row, group, n, k = piece
    x = scores_t[row : row + n * k].reshape(n, k, -1)
    top = x.max(axis=1)
    raw_t[group : group + n] = top
    floor = top - scores_t.dtype.type(TIE_TOLERANCE)  # float32 − 1e-5 rounds as in ``place_scores``
    # the first hit (the maximum itself hits): k − the largest of hit·(k − j) over the place's rows j,
    # a maximum over the middle axis (5× quicker than ``argmax`` over it at 906 queries)
    weight = np.arange(k, 0, -1, dtype=np.uint8 if k < 256 else np.int64)[:, None]
    first = k - np.max((x >= floor[:, None, :]) * weight, axis=1).astype(np.int64)
    # a NaN maximum hits no row (first = k): any row of the place keeps the index in it; such a
    # query's raw_p is NaN, and the caller decides it with ``score_queries``, which defines NaN
    np.minimum(first, k - 1, out=first)
    best_t[group : group + n] = layout.order[row + k * np.arange(n)[:, None] + first]


def score_layout_block(
    scores_t: np.ndarray,
    layout: PlaceLayout,
    raw_t: np.ndarray,
    best_t: np.ndarray,
    thresholds: dict[str, np.ndarray | float],
    correct: np.ndarray,
    db_places: np.ndarray,
    methods: tuple[Method, ...] | None = None,
    max_elems: int = 1 << 22,
    pool: Executor | None = None,
) -> tuple[np.ndarray, np.ndarray, dict[str, Outcome]]:
    """``place_scores`` and ``score_queries`` of a block of queries from scores in the layout.

    Equal to ``score_queries(scores_t[layout.order.argsort()].T, ...)`` in every rank, answer
    and image, for finite scores (the caller checks ``raw_t``): the place-level methods run on
    the same raw_p and images, and the image-level baseline reads only the places that can
    matter. Its rank counts wrong images at or above b − 1e-5 (b the best right image's score),
    which can only lie in wrong places with raw_p ≥ b − 1e-5; its answer is the lowest index
    at or above top − 1e-5, only in places with raw_p ≥ top − 1e-5. Both comparisons are in
    float64, as ``score_queries`` makes them on float64 scores; ``max(raw_p)`` over the right
    places is b exactly (a maximum of the same float32 numbers).

    Args:
        raw_t, best_t: ``(n_groups, n_queries)`` from ``layout_place_scores`` over every piece.
        correct: ``(n_queries, n_places)`` right places.
        db_places: ``(n_database,)`` place of each database image (database order).
        max_elems: scores read back at a time by the image-level baseline.
        pool: runs the methods side by side (each reads only the shared arrays).
    Returns:
        raw ``(n_queries, n_places)`` float64 and best ``(n_queries, n_places)`` int64 as
        ``place_scores`` gives them, and method key -> ``Outcome``.
    """
    nq = scores_t.shape[1]
    n_db = len(layout.order)
    methods = methods_for(thresholds) if methods is None else methods
    raw = np.full((nq, layout.n_places), -np.inf)
    best = np.full((nq, layout.n_places), -1, dtype=np.int64)
    raw[:, layout.places] = raw_t.T
    best[:, layout.places] = best_t.T
    best[~np.isfinite(raw)] = -1

    def outcome(m: Method) -> Outcome:
        if m.level != "image":
            return _place_outcome(m, raw, best, thresholds, correct)
        raw_g = raw[:, layout.places]
        right = correct[:, layout.places]
        b = np.where(right, raw_g, -np.inf).max(axis=1)
        top = raw_g.max(axis=1)
        above = np.zeros(nq, dtype=np.int64)
        img = np.full(nq, n_db, dtype=np.int64)
        with np.errstate(invalid="ignore"):
            wrong_near = (raw_g >= (b - TIE_TOLERANCE)[:, None]) & ~right & np.isfinite(b)[:, None]
            near_top = raw_g >= (top - TIE_TOLERANCE)[:, None]
        for row, group, n, k in layout.runs:
            x = scores_t[row : row + n * k].reshape(n, k, nq)
            step = max(1, max_elems // k)
            q, g = np.nonzero(wrong_near[:, group : group + n])
            for lo in range(0, len(q), step):
                qs, gs = q[lo : lo + step], g[lo : lo + step]
                hits = (x[gs, :, qs] >= (b[qs] - TIE_TOLERANCE)[:, None]).sum(axis=1)
                np.add.at(above, qs, hits)
            q, g = np.nonzero(near_top[:, group : group + n])
            for lo in range(0, len(q), step):
                qs, gs = q[lo : lo + step], g[lo : lo + step]
                index = layout.order[row + k * gs[:, None] + np.arange(k)]
                hit = x[gs, :, qs] >= (top[qs] - TIE_TOLERANCE)[:, None]
                np.minimum.at(img, qs, np.where(hit, index, n_db).min(axis=1))
        rank = 1.0 + above
        rank[~np.isfinite(b)] = np.inf
        img[~np.isfinite(top)] = -1
        place = np.where(img >= 0, db_places[np.maximum(img, 0)], -1)
        return Outcome(method=m, rank=rank, answer_place=place, answer_image=img,
                       n_kept=np.full(nq, n_db, dtype=np.int64))

    outcomes = map(outcome, methods) if pool is None else pool.map(outcome, methods)
    out = {m.key: o for m, o in zip(methods, outcomes)}
    return raw, best, out


def _ordinal(n: float) -> str:
    n = int(n)
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


@dataclass(frozen=True, eq=False)
class QueryDecision:
    """Everything behind one query's answer, under every method.

    Attributes:
        raw: ``(n_places,)`` raw_p.
        best_image: ``(n_places,)`` database image attaining raw_p.
        image_scores: ``(n_database,)`` s(q, i).
        thresholds: threshold key -> ``(n_places,)`` θ (scalars broadcast).
        true_places: the query's right places (empty for an unknown place).
        outcomes: method key -> ``Outcome`` of this single query.
        scores: method key -> ``(n_candidates,)`` ranking score (``-inf`` dropped).
    """

    raw: np.ndarray
    best_image: np.ndarray
    image_scores: np.ndarray
    db_places: np.ndarray
    thresholds: dict[str, np.ndarray]
    true_places: np.ndarray
    outcomes: dict[str, Outcome]
    scores: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n_places(self) -> int:
        return len(self.raw)

    def margin(self, threshold: str) -> np.ndarray:
        """``(n_places,)`` raw_p − θ_p for a threshold key."""
        return self.raw - self.thresholds[threshold]

    def kept(self, key: str) -> np.ndarray:
        """``(n_candidates,)`` which places (images, for the image level) the method kept."""
        return np.isfinite(self.scores[key])

    def place_rank(self, key: str) -> np.ndarray:
        """``(n_places,)`` 1-based rank of every kept place under the method, 0 if dropped."""
        s = self.scores[key]
        order = np.argsort(-s, kind="stable")
        rank = np.zeros(len(s), dtype=np.int64)
        rank[order] = np.arange(1, len(s) + 1)
        rank[~np.isfinite(s)] = 0
        return rank

    def answer(self, key: str) -> int:
        return int(self.outcomes[key].answer_place[0])

    def is_right(self, key: str) -> bool:
        """Right answer: the true place accepted at rank 1, or an unknown-place query rejected."""
        o = self.outcomes[key]
        if len(self.true_places) == 0:
            return not bool(o.accepted[0])
        return bool(o.right[0])

    def describe(self, key: str) -> str:
        """The decision in words, e.g. "rejected: the best place, 7, scored 0.41, below its threshold 0.46"."""
        m = self.outcomes[key].method
        o = self.outcomes[key]
        ans = int(o.answer_place[0])
        known = len(self.true_places) > 0
        true = int(self.true_places[np.argmax(self.raw[self.true_places])]) if known else -1
        theta = self.thresholds.get(m.threshold) if m.threshold else None
        best = int(np.argmax(self.raw))

        def th(p: int) -> str:
            return "" if theta is None else f", threshold {theta[p]:.3f}, margin {self.raw[p] - theta[p]:+.3f}"

        if ans < 0:
            text = (
                f"rejected: the best place, {best}, scored {self.raw[best]:.3f}, below its threshold "
                f"{theta[best]:.3f}; every place scored below its threshold"
            )
            return text + (" (right: the query's place is not in the database)" if not known else
                           f" (wrong: the query is place {true}, raw {self.raw[true]:.3f}{th(true)})")
        level = f"image {int(o.answer_image[0])} → " if m.level == "image" else ""
        head = f"accepted as {level}place {ans}"
        if not known:
            return f"{head} (wrong: the query's place is not in the database): raw {self.raw[ans]:.3f}{th(ans)}"
        if self.is_right(key):
            return f"{head} (right): raw {self.raw[ans]:.3f}{th(ans)}; {int(o.n_kept[0])} kept"
        rank = o.rank[0]
        if not np.isfinite(rank):
            why = (f"the true place {true} scored {self.raw[true]:.3f}, below its threshold {theta[true]:.3f}, "
                   "so it was dropped") if theta is not None else f"the true place {true} has no database image"
        elif rank == 1:
            why = f"the true place {true} ties with it at the top (within 1e-5), and ties count against the query"
        else:
            why = f"the true place {true} ranked {_ordinal(rank)} (raw {self.raw[true]:.3f}{th(true)})"
        return f"{head} (wrong): raw {self.raw[ans]:.3f}{th(ans)}; {why}"


def decide(
    query_sims: np.ndarray,
    db_places: np.ndarray,
    n_places: int,
    thresholds: dict[str, np.ndarray | float],
    true_places: np.ndarray | list[int] = (),
    methods: tuple[Method, ...] | None = None,
) -> QueryDecision:
    """The decision record of one query under every method.

    Args:
        query_sims: ``(n_database,)`` the query's similarity to every database image.
        db_places: ``(n_database,)`` place of each database image.
        thresholds: as for ``score_queries``.
        true_places: the query's right place ids; empty for a query of an unknown place.
    """
    sims = np.asarray(query_sims, dtype=np.float64)[None, :]
    true = np.asarray(true_places, dtype=np.int64).reshape(-1)
    correct = np.zeros((1, n_places), dtype=bool)
    correct[0, true] = True
    methods = methods_for(thresholds) if methods is None else methods
    raw, best = place_scores(sims, db_places, n_places)
    outcomes = score_queries(sims, db_places, n_places, thresholds, correct, methods, (raw, best))
    full = {k: np.broadcast_to(np.asarray(v, dtype=np.float64), (n_places,)) for k, v in thresholds.items()}
    scores = {
        m.key: sims[0] if m.level == "image" else ranking_scores(raw, None if m.threshold is None else full[m.threshold], m.rule)[0]
        for m in methods
    }
    return QueryDecision(
        raw=raw[0], best_image=best[0], image_scores=sims[0], db_places=np.asarray(db_places),
        thresholds=full, true_places=true, outcomes=outcomes, scores=scores,
    )
