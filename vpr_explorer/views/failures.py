"""One method's failing queries: which failed, how and why, and a picture of each.

**Which queries fail.** Method ``key`` (one of ``method.retrieval.METHODS``) fails a query
in one of three ways, by what the query's ground truth makes of it
(``numbers.RetrievalFitted.query_status``) and by its ``Outcome``:

| kind | the query | the method |
|---|---|---|
| ``wrong-answer`` | has a right place (a positive in a place) | accepted it without that place at rank 1 (a tie at the top counts as wrong, as ``Outcome.right`` says) |
| ``wrong-reject`` | has a right place | rejected it: every place below its threshold |
| ``accepted-unknown`` | has no positive at all (an unknown-place query) | accepted it: a false positive |

These are ``numbers.FindKind``'s wrong answer, wrongly rejected and accepted unknown. A query
whose positives all lie between places has no right answer and is not scored (Recall@1 leaves
it out), so it never fails; neither does an unknown-place query rejected.

Every query's kind comes from ``numbers.decide_queries`` (the queries in blocks, the
protocol's pass); each failure kept is then explained by ``numbers.explain_query`` (one
query against the database), which gives the reason sentence (``numbers.describe_answer``:
``QueryDecision.describe`` for a query with a right place) and the candidates drawn. The two
passes round float32 products differently (``retrieval.similarity_t``); where a score lies
within that rounding of a boundary they may disagree, and the explained record decides
(its kind is the row's, and a query it finds right is left out with a note), so that a
row's kind and reason never contradict each other.

**The picture** (``draw_failure``), after VPR-methods-evaluation's prediction grids
(``visualizations.py``, ``--save_only_wrong_preds``): one row of tiles under a title line
(the kind, the query and the reason sentence, wrapped to ``TITLE_LINES`` lines), each
picture fitted inside ``TILE_W`` × ``TILE_H`` on white, a ``BORDER``-pixel frame around it
and ``CAPTION_LINES`` lines of caption under it:

1. the query (a grey frame);
2. the top ``top`` candidates (default 5) in the method's ranking: the candidates it kept,
   its answer first and the rest by its ranking score (raw_p for the raw rule and the
   place-level baseline, raw_p − θ_p for the margin rule, s(q, i) for the image-level
   baseline), then, where fewer were kept, the places it dropped by the same score before
   the filter (a rejected query's closest places). A place-level candidate is drawn as the
   place's best image (the one behind raw_p). Green frame: the candidate's place is one of
   the query's right places; red: it is not. Captioned with its rank (or "dropped"), place,
   database index and label, score, and θ and margin for a method with a threshold;
3. the true match: the query's best right database image (the image behind raw_p of its
   right place of highest raw_p; for the image-level baseline that is its best right
   image), always drawn, with the method's rank of the true place (``Outcome.rank``, ties
   counted against the query; "dropped" where the filter dropped it). An unknown-place
   query has none: a grey tile says so.

A PNG is ``grid_size(n_tiles)`` pixels; tile ``i``'s frame is ``tile_box(i)``.

**Which queries are decided.** Every query of the dataset value (``find_failures``'s
default), or the ones a caller gives (``queries``): the app's pages decide
``failure_queries``, every query up to ``numbers.PAIR_BUDGET`` query × database
similarities and above it the overview's seeded sample (``numbers.overview_frames``), so
that the failure table scores no more pairs than the page's overview; ``Failures.sampled``
says when it is a sample. Each failing query is then explained on its own
(``explained_queries``: ``numbers.explain_query``'s record, bit for bit, with the database
images in places gathered once).

**The table** (``failure_rows``, ``index_html``): one row per failure kept, ``COLUMNS``:
query index and label, kind, answer (``place P``, or ``rejected``), the answer's image, the
true place, its image and rank, the score and margin of the method's top candidate (its
answer; for a rejected query the place it came closest to accepting), the reason sentence
and the PNG's file name. ``index_html`` is one self-contained page (inline style and
script, thumbnails as data URIs, links to the PNGs beside it): the settings and counts on
top, the table below, sorted by clicking a header.

**The app's failure table** (``table_rows``, ``sort_rows``, ``table_csv``): one row per
failure, ``TABLE_COLUMNS``: the query (index and file), the kind, the method's label, its
answer (``place P``; ``rejected, closest place P`` for a rejected query, P the place it came
closest to accepting), the answer's database image (that closest place's best image when
rejected), the true place, its best image and its rank, and the top candidate's score
(raw_p; s(q, i) for the image-level baseline), θ (its place's θ_p(k), or the global θ; empty
for a method without threshold) and margin = score − θ, and the reason sentence.
``sort_rows`` orders them by ``SORT_KEYS``: the query, the margin or the score, an empty
margin last either way and ties by query. ``table_csv`` writes the same columns, the
numbers as ``failure_rows`` writes them. ``accepts_nothing`` is the sentence for a method
whose every θ lies above 1, the largest similarity: it accepts no query.

Pure: reads image files to draw them, writes nothing.
"""

from __future__ import annotations

import base64
import csv
import functools
import html
import io
import math
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont, ImageOps

from vpr_explorer.descriptors.base import open_image
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.auto_theta import MAX_SIMILARITY
from vpr_explorer.method.database import database_rows
from vpr_explorer.method.retrieval import METHODS_BY_KEY, QueryDecision, Rule, decide, similarity
from vpr_explorer.method.stats import one_blas_thread
from vpr_explorer.views import numbers
from vpr_explorer.views.numbers import (
    BETWEEN,
    KNOWN,
    UNKNOWN,
    RetrievalFitted,
    database_label,
    decide_queries,
    dense,
    describe_answer,
    explain_query,
    overview_frames,
    query_label,
)


class FailureKind(StrEnum):
    """How a method failed a query (module docstring)."""

    WRONG_ANSWER = "wrong-answer"
    WRONG_REJECT = "wrong-reject"
    ACCEPTED_UNKNOWN = "accepted-unknown"


#: Each kind in words, for titles and summaries.
KIND_WORDS = {
    FailureKind.WRONG_ANSWER: "wrong answer: a query with a right place, answered without it at rank 1",
    FailureKind.WRONG_REJECT: "wrong reject: a query with a right place, rejected",
    FailureKind.ACCEPTED_UNKNOWN: "accepted unknown: a query of no database place, accepted",
}

#: Picture geometry in pixels: a picture's box, its frame, the space between tiles and around them.
TILE_W, TILE_H = 288, 216
BORDER = 6
GAP = 12
MARGIN = 12
#: Text: font size, line height, lines of the title and of each caption.
FONT_SIZE = 13
LINE_H = 17
TITLE_LINES = 3
CAPTION_LINES = 3
#: Frame colours: a right candidate, a wrong one, the query and a missing true match.
GREEN = (0, 160, 0)
RED = (215, 25, 25)
GREY = (140, 140, 140)
WHITE = (255, 255, 255)
TEXT = (20, 20, 20)
#: Width of the thumbnails ``index_html`` shows.
THUMB_W = 360

#: The table's columns (``failure_rows``), as the CSV's header writes them.
COLUMNS = ("query", "query image", "kind", "answer", "answer image", "true place", "true image", "true rank",
           "score", "margin", "reason", "png")
#: The columns ``index_html`` sorts as numbers.
NUMERIC = ("query", "true place", "true rank", "score", "margin")


# --------------------------------------------------------------------------- which queries fail


def failure_kinds(known: np.ndarray, unknown: np.ndarray, accepted: np.ndarray, right: np.ndarray) -> np.ndarray:
    """``(n,)`` each query's ``FailureKind`` value, ``""`` where the method did not fail it.

    Args:
        known: ``(n,)`` bool, the query has a right place.
        unknown: ``(n,)`` bool, the query has no positive at all.
        accepted, right: ``(n,)`` bool, ``Outcome.accepted`` and ``Outcome.right``.
    """
    known, unknown = np.asarray(known, dtype=bool), np.asarray(unknown, dtype=bool)
    accepted, right = np.asarray(accepted, dtype=bool), np.asarray(right, dtype=bool)
    out = np.full(len(known), "", dtype=object)
    out[known & accepted & ~right] = FailureKind.WRONG_ANSWER.value
    out[known & ~accepted] = FailureKind.WRONG_REJECT.value
    out[unknown & accepted] = FailureKind.ACCEPTED_UNKNOWN.value
    return out


def decision_kind(decision: QueryDecision, key: str, status: str) -> FailureKind | None:
    """The kind of failure of one explained query (``None``: not a failure).

    Args:
        decision: ``numbers.explain_query``'s record.
        status: ``RetrievalFitted.query_status`` of the query.
    """
    o = decision.outcomes[key]
    kind = failure_kinds([status == KNOWN], [status == UNKNOWN], o.accepted, o.right)[0]
    return FailureKind(kind) if kind else None


def check_method(fitted: RetrievalFitted, key: str, user_theta: float | None) -> None:
    """Refuse a method that is not one of ``METHODS`` or whose threshold the fit does not give.

    Raises:
        VPRInputError: an unknown key, ``global-oracle`` (its θ is fitted on the queries'
            own answers), ``global-user`` without ``user_theta``.
    """
    if key not in METHODS_BY_KEY:
        raise VPRInputError(f"method={key!r}: choose one of {', '.join(METHODS_BY_KEY)}")
    m = METHODS_BY_KEY[key]
    if m.threshold is not None and m.threshold not in fitted.model.thresholds(0.0, user_theta):
        need = "a user θ" if m.threshold == "user" else f"the {m.threshold} θ, which the database fit does not give"
        raise VPRInputError(f"method={key!r} needs {need}: pick another method")


# --------------------------------------------------------------------------- one failure


@dataclass(frozen=True)
class Tile:
    """One picture of a failure's row and its caption.

    Attributes:
        path: the image file; ``None`` for the true match of an unknown-place query (a grey tile).
        right: its place is one of the query's right places (green), or not (red); ``None``
            for the query and a missing true match (grey).
        caption: the lines under the picture.
    """

    path: Path | None
    right: bool | None
    caption: tuple[str, ...]

    @property
    def colour(self) -> tuple[int, int, int]:
        return GREY if self.right is None else GREEN if self.right else RED


@dataclass(frozen=True)
class Failure:
    """One failing query under one method, explained.

    Attributes:
        query: the query's index (0-based among the queries).
        label: the query's name (``numbers.query_label``).
        kind: how the method failed it.
        reason: the method's decision in words (``numbers.describe_answer``).
        answer_place, answer_image: the answered place and database image (a database
            position); ``-1`` when rejected.
        top_place, top_image: the method's top candidate (its answer; for a rejected query
            the place it came closest to accepting) and its database image.
        score: the top candidate's raw_p (s(q, i) for the image-level baseline).
        margin: its raw_p − θ_p, NaN for a method without threshold.
        true_place, true_image: the query's best right place and its best image; ``-1`` without one.
        true_rank: the method's rank of the true place (``Outcome.rank``: ``inf`` where dropped); NaN without one.
        true_score: raw_p of the true place; NaN without one.
        tiles: the query, the top candidates, the true match (module docstring).
        theta: the top candidate's θ (its place's θ_p(k), or the global θ), NaN for a method without threshold:
            ``margin`` is ``score − theta``.
    """

    query: int
    label: str
    kind: FailureKind
    reason: str
    answer_place: int
    answer_image: int
    top_place: int
    top_image: int
    score: float
    margin: float
    true_place: int
    true_image: int
    true_rank: float
    true_score: float
    tiles: tuple[Tile, ...]
    theta: float = math.nan

    @property
    def title(self) -> str:
        """The picture's title line: kind, query and reason."""
        return f"{self.kind.value} · query {self.query} ({self.label}): {self.reason}"


def ranked_candidates(decision: QueryDecision, key: str, top: int) -> list[tuple[int, int | None]]:
    """The ``top`` candidates a failure's picture shows: ``(candidate, rank)``, rank ``None`` for a dropped one.

    A candidate is a place id (an index among the images in places for the image-level
    baseline). The kept ones come first, the answer at rank 1 and the rest by the method's
    ranking score, ties by index; then the dropped ones by the same score before the
    filter (raw_p, or raw_p − θ_p for the margin rule), ties by index.
    """
    m = METHODS_BY_KEY[key]
    scores = np.asarray(decision.scores[key], dtype=np.float64)
    if m.level == "image":
        answer, before = int(decision.outcomes[key].answer_image[0]), decision.image_scores
    else:
        answer, before = decision.answer(key), np.asarray(decision.raw, dtype=np.float64)
        if m.rule is Rule.MARGIN:
            before = decision.margin(m.threshold)
    kept = np.flatnonzero(np.isfinite(scores))
    kept = kept[np.lexsort((kept, -scores[kept]))]
    if answer >= 0:
        kept = np.r_[answer, kept[kept != answer]]
    out: list[tuple[int, int | None]] = [(int(c), r + 1) for r, c in enumerate(kept[:top])]
    if len(out) < top:
        with np.errstate(invalid="ignore"):
            dropped = np.flatnonzero(~np.isfinite(scores) & np.isfinite(before))
        dropped = dropped[np.lexsort((dropped, -before[dropped]))]
        out += [(int(c), None) for c in dropped[:top - len(out)]]
    return out


def _scores_text(raw: float, theta: float | None, level: str) -> str:
    head = f"{'s' if level == 'image' else 'raw'} {raw:.3f}"
    return head if theta is None else f"{head} · θ {theta:.3f} · margin {raw - theta:+.3f}"


def explain_failure(fitted: RetrievalFitted, decision: QueryDecision, key: str, query: int, kind: FailureKind,
                    top: int = 5) -> Failure:
    """The ``Failure`` of query ``query`` from its explained record (``numbers.explain_query``).

    Args:
        kind: how the method failed it (``decision_kind``).
        top: candidates drawn (module docstring).
    """
    ds, images = fitted.dataset, fitted.model.images
    m = METHODS_BY_KEY[key]
    o = decision.outcomes[key]
    theta = decision.thresholds[m.threshold] if m.threshold is not None else None
    place_of = decision.db_places
    raw = np.asarray(decision.raw, dtype=np.float64)
    true_set = set(int(p) for p in decision.true_places)

    def candidate(c: int) -> tuple[int, int, float, float | None]:
        """(place, database image, score, θ) of a candidate."""
        if m.level == "image":
            p = int(place_of[c])
            return p, int(images[c]), float(decision.image_scores[c]), None
        return c, int(images[decision.best_image[c]]), float(raw[c]), None if theta is None else float(theta[c])

    label = query_label(ds, query)
    tiles = [Tile(Path(ds.query_paths[query]), None, (f"query {query}", label, KIND_WORDS[kind].split(":")[0]))]
    ranked = ranked_candidates(decision, key, top)
    for c, rank in ranked:
        p, img, s, th = candidate(c)
        head = f"#{rank}" if rank is not None else "dropped"
        if rank == 1 and o.accepted[0]:
            head += " answer"
        tiles.append(Tile(Path(ds.database_paths[img]), p in true_set,
                          (f"{head} · place {p} · db {img}", database_label(ds, img), _scores_text(s, th, m.level))))
    if true_set:
        true = np.asarray(decision.true_places, dtype=np.int64)
        tp = int(true[np.argmax(raw[true])])
        t_img = int(images[decision.best_image[tp]])
        t_rank = float(o.rank[0])
        t_th = None if theta is None else float(theta[tp])
        ranked_as = f"rank {int(t_rank)}" if math.isfinite(t_rank) else "dropped"
        tiles.append(Tile(Path(ds.database_paths[t_img]), True,
                          (f"true match · {ranked_as} · place {tp} · db {t_img}", database_label(ds, t_img),
                           _scores_text(float(raw[tp]), t_th, m.level))))
        t_score = float(raw[tp])
    else:
        tp, t_img, t_rank, t_score = -1, -1, math.nan, math.nan
        tiles.append(Tile(None, None, ("no true match", "no database image is right", "for this query")))
    if ranked:
        top_place, top_image, score, th = candidate(ranked[0][0])
    else:
        top_place, top_image, score, th = -1, -1, math.nan, None
    answer = int(o.answer_place[0])
    return Failure(
        query=int(query), label=label, kind=kind, reason=describe_answer(fitted, decision, key, int(query)),
        answer_place=answer, answer_image=int(images[o.answer_image[0]]) if answer >= 0 else -1,
        top_place=top_place, top_image=top_image, score=score, margin=math.nan if th is None else score - th,
        true_place=tp, true_image=t_img, true_rank=t_rank, true_score=t_score, tiles=tuple(tiles),
        theta=math.nan if th is None else th,
    )


# --------------------------------------------------------------------------- every failure of a method


@dataclass(frozen=True, eq=False)
class Failures:
    """A method's failing queries over a dataset value: all counted, the first ``limit`` explained.

    Attributes:
        key: the method.
        kinds: the kinds asked for.
        counts: every kind -> its failing queries among those decided (whatever was asked for).
        failing: ``(n,)`` ascending query indices of the kinds asked for.
        failures: the first ``limit`` of them explained (``Failure``), in query order.
        left_out: failing queries of the kinds asked for beyond ``limit``.
        n_queries: query images of the dataset.
        n_known, n_unknown, n_between: queries decided with a right place, with no positive, with
            positives only between places (not scored).
        notes: what else the reader should know (a query the two passes disagree on).
        decided: ``(m,)`` ascending query indices decided: every query, or the caller's (``queries``).
    """

    key: str
    kinds: tuple[FailureKind, ...]
    counts: dict[FailureKind, int]
    failing: np.ndarray
    failures: tuple[Failure, ...]
    left_out: int
    n_queries: int
    n_known: int
    n_unknown: int
    n_between: int
    notes: tuple[str, ...]
    decided: np.ndarray

    def __post_init__(self) -> None:
        self.failing.setflags(write=False)
        self.decided.setflags(write=False)

    @property
    def sampled(self) -> bool:
        """Fewer queries decided than the dataset holds (``failure_queries``' sample)."""
        return len(self.decided) < self.n_queries


def failure_queries(fitted: RetrievalFitted, pair_budget: int | None = None) -> np.ndarray:
    """``(m,)`` the queries the app's failure table decides: those of ``numbers.overview`` (every query up to
    ``pair_budget`` query × database-image-in-a-place similarities, default ``numbers.PAIR_BUDGET`` read at call
    time, above it its seeded sample)."""
    budget = numbers.PAIR_BUDGET if pair_budget is None else pair_budget
    return overview_frames(fitted.dataset.n_queries, len(fitted.model.images), budget)


def explained_queries(fitted: RetrievalFitted, descriptors: np.ndarray, queries: np.ndarray, *, k: float = 0.0,
                      user_theta: float | None = None):
    """Yield ``(query, record)`` for each of ``queries``: ``numbers.explain_query``'s record, bit for bit.

    On in-memory float32 descriptors the database images in places are gathered once and each
    query scored against them by the same ``1 × D`` product as ``explain_query``'s, BLAS in one
    thread (a product that small waits on its threads more than it computes: 0.1 ms against
    several on a loaded machine; each score is one dot product whatever the thread count,
    ``stats.one_blas_thread``); on a memory map or float16 each query is ``explain_query``
    itself (it reads the database a block at a time).
    """
    queries = np.asarray(queries, dtype=np.int64)
    if not dense(descriptors):
        for q in queries:
            yield int(q), explain_query(fitted, descriptors, int(q), k=k, user_theta=user_theta)
        return
    model = fitted.model
    n_db = fitted.dataset.n_database
    database = database_rows(descriptors, model.images)
    thresholds = model.thresholds(k, user_theta)
    truth = fitted.right_places(queries)
    with one_blas_thread():
        for q, right in zip(queries, truth):
            sims = similarity(descriptors[np.asarray([n_db + q])], database)[0]
            yield int(q), decide(sims, model.places, fitted.n_places, thresholds, np.flatnonzero(right))


def find_failures(fitted: RetrievalFitted, descriptors: np.ndarray, key: str, *,
                  kinds: tuple[FailureKind | str, ...] | None = None, top: int = 5, limit: int | None = None,
                  user_theta: float | None = None, k: float = 0.0, queries: np.ndarray | None = None,
                  progress=None) -> Failures:
    """Every query method ``key`` fails, and the first ``limit`` of them explained (module docstring).

    Args:
        fitted: the places and thresholds (``numbers.fit_retrieval``).
        descriptors: ``(n_images, D)`` unit rows, database rows first.
        key: the method (``retrieval.METHODS_BY_KEY``).
        kinds: the kinds to keep (default: every ``FailureKind``).
        top: candidates drawn per failure, at least 1.
        limit: failures explained at most (default: all), in query order.
        user_theta: the global θ of ``global-user``.
        k: the per-place family's θ_p(k) = θ_p + k·s_p (0: the paper's θ_p).
        queries: the query indices to decide (default: every query; ``failure_queries``: the app's).
        progress: ``progress(done, total)`` while failures are explained.

    Raises:
        VPRInputError: an unknown method or one whose threshold is missing, an unknown kind,
            ``top`` < 1, ``limit`` < 0, no query or one outside the dataset.
    """
    check_method(fitted, key, user_theta)
    try:
        wanted = tuple(FailureKind) if kinds is None else tuple(dict.fromkeys(FailureKind(x) for x in kinds))
    except ValueError:
        raise VPRInputError(f"kinds={kinds!r}: choose from {', '.join(x.value for x in FailureKind)}") from None
    if isinstance(top, bool) or not isinstance(top, (int, np.integer)) or top < 1:
        raise VPRInputError(f"top={top!r}: draw at least 1 candidate")
    if limit is not None and (isinstance(limit, bool) or not isinstance(limit, (int, np.integer)) or limit < 0):
        raise VPRInputError(f"limit={limit!r}: give a whole number of failures, 0 or more")
    ds = fitted.dataset
    decided = np.arange(ds.n_queries) if queries is None else np.unique(np.asarray(queries, dtype=np.int64))
    truth, outcomes = decide_queries(fitted, descriptors, decided, k=k, user_theta=user_theta)
    known = truth.any(axis=1)
    unknown = ds.ground_truth.counts[decided] == 0
    o = outcomes[key]
    kind = failure_kinds(known, unknown, o.accepted, o.right)
    counts = {f: int((kind == f.value).sum()) for f in FailureKind}
    failing = decided[np.isin(kind, [f.value for f in wanted])]
    kind_of = dict(zip(decided.tolist(), kind.tolist()))
    chosen = failing if limit is None else failing[:limit]
    failures, notes = [], []
    for i, (q, decision) in enumerate(explained_queries(fitted, descriptors, chosen, k=k, user_theta=user_theta)):
        again = decision_kind(decision, key, fitted.query_status(q))
        if again is None or again not in wanted:
            notes.append(f"query {q}: {kind_of[q]} in the blocked pass, "
                         f"{again.value if again else 'right'} explained alone (a score within float32 rounding "
                         "of a boundary): left out")
        else:
            failures.append(explain_failure(fitted, decision, key, q, again, top))
        if progress is not None:
            progress(i + 1, len(chosen))
    return Failures(
        key=key, kinds=wanted, counts=counts, failing=failing, failures=tuple(failures),
        left_out=len(failing) - len(chosen), n_queries=ds.n_queries, n_known=int(known.sum()),
        n_unknown=int(unknown.sum()), n_between=int((~known & ~unknown).sum()), notes=tuple(notes), decided=decided,
    )


def summary_lines(result: Failures) -> list[str]:
    """The counts in words: failures of each kind against the queries that can fail that way."""
    c = result.counts
    m = METHODS_BY_KEY[result.key]
    n = len(result.decided)
    of = (f"{result.n_queries} queries" if not result.sampled else
          f"the {n:,} queries decided (a seeded sample of the {result.n_queries:,})")
    lines = [
        f"{m.key} ({m.label}): {c[FailureKind.WRONG_ANSWER]} wrong answers and {c[FailureKind.WRONG_REJECT]} wrong "
        f"rejects of {result.n_known} queries with a right place; {c[FailureKind.ACCEPTED_UNKNOWN]} accepted of "
        f"{result.n_unknown} unknown-place queries; {result.n_between} of {of} not scored "
        f"({BETWEEN}: {'their' if result.n_between != 1 else 'its'} right images all lie between places)",
    ]
    shown = len(result.failures)
    asked = ", ".join(k.value for k in result.kinds)
    lines.append(f"drawn: {shown} of {len(result.failing)} failures ({asked})"
                 + (f"; {result.left_out} left out by the limit" if result.left_out else ""))
    return lines + list(result.notes)


def accepts_nothing(fitted: RetrievalFitted, key: str, *, k: float = 0.0, user_theta: float | None = None) -> str | None:
    """The sentence for method ``key`` when every θ it has lies above 1 (it accepts no query); ``None`` otherwise.

    1 is the largest cosine similarity two unit descriptors can have (``auto_theta.MAX_SIMILARITY``).
    """
    m = METHODS_BY_KEY[key]
    if m.threshold is None:
        return None
    theta = np.asarray(fitted.model.thresholds(k, user_theta)[m.threshold], dtype=np.float64)
    if not theta.size or theta.min() <= MAX_SIMILARITY:
        return None
    what = (f"{m.label} of this database = {float(theta.min()):.3f}" if theta.ndim == 0 else
            f"every place's θ of {m.label} on this database (the lowest {float(theta.min()):.3f})")
    return (f"{what} is above {MAX_SIMILARITY:g}, the largest similarity two descriptors can have, so it accepts no "
            "query: every query with a right place is a wrong reject here, whatever its scores.")


# --------------------------------------------------------------------------- the app's table


#: The app's failure table's columns (``table_rows``), as its CSV writes them.
TABLE_COLUMNS = ("query", "query image", "kind", "method", "answer", "answer image", "true place", "true image",
                 "true rank", "score", "θ", "margin", "reason")
#: What ``sort_rows`` orders by.
SORT_KEYS = ("query", "margin", "score")


def answer_text(failure: Failure) -> str:
    """The method's answer in the table: ``place P``, or ``rejected, closest place P``."""
    if failure.answer_place >= 0:
        return f"place {failure.answer_place}"
    return "rejected" + (f", closest place {failure.top_place}" if failure.top_place >= 0 else "")


def table_rows(fitted: RetrievalFitted, result: Failures) -> list[dict[str, object]]:
    """One row of ``TABLE_COLUMNS`` per explained failure, in query order (module docstring).

    Numbers stay numbers (NaN where empty; ``true place`` −1 and ``true rank`` NaN without a
    true match, ``inf`` where the method dropped it); ``answer image`` is the database image
    behind the answer, or behind the closest place of a rejected query.
    """
    ds = fitted.dataset
    label = METHODS_BY_KEY[result.key].label
    rows = []
    for f in result.failures:
        shown = f.answer_image if f.answer_image >= 0 else f.top_image
        rows.append({
            "query": f.query, "query image": f.label, "kind": f.kind.value, "method": label,
            "answer": answer_text(f), "answer image": database_label(ds, shown) if shown >= 0 else "",
            "true place": f.true_place, "true image": database_label(ds, f.true_image) if f.true_image >= 0 else "",
            "true rank": f.true_rank, "score": f.score, "θ": f.theta, "margin": f.margin, "reason": f.reason,
        })
    return rows


def row_pictures(fitted: RetrievalFitted, failure: Failure) -> tuple[Path, Path | None, Path | None]:
    """The image files of a row: the query, the answer (the closest place's best image when rejected; ``None``
    when there is no candidate) and the true match (``None`` for an unknown-place query)."""
    ds = fitted.dataset
    shown = failure.answer_image if failure.answer_image >= 0 else failure.top_image
    return (Path(ds.query_paths[failure.query]), Path(ds.database_paths[shown]) if shown >= 0 else None,
            Path(ds.database_paths[failure.true_image]) if failure.true_image >= 0 else None)


def sort_rows(rows: list[dict[str, object]], by: str = "query", *, descending: bool = False) -> list[dict[str, object]]:
    """``rows`` ordered by ``by`` (``SORT_KEYS``); an empty (NaN) value last either way, ties by query.

    Raises:
        VPRInputError: ``by`` is not one of ``SORT_KEYS``.
    """
    if by not in SORT_KEYS:
        raise VPRInputError(f"sort by {by!r}: choose one of {', '.join(SORT_KEYS)}")
    sign = -1.0 if descending else 1.0

    def order(row: dict[str, object]) -> tuple[bool, float, int]:
        value = float(row[by])
        return math.isnan(value), 0.0 if math.isnan(value) else sign * value, int(row["query"])

    return sorted(rows, key=order)


def rank_text(rank: float) -> str:
    """A true place's rank in words: the number, ``dropped`` (below the method's threshold), empty without one."""
    rank = float(rank)
    return "" if math.isnan(rank) else "dropped" if math.isinf(rank) else str(int(rank))


def _cell(column: str, value: object) -> str:
    """A ``table_rows`` value as the CSV writes it (``failure_rows``' number formats)."""
    if column == "true rank":
        return rank_text(value)
    if column in ("score", "θ", "margin"):
        x = float(value)
        if math.isnan(x):
            return ""
        return f"{x:+.4f}" if column == "margin" else f"{x:.4f}"
    if column == "true place":
        return "" if int(value) < 0 else str(int(value))
    return str(value)


def table_csv(rows: list[dict[str, object]]) -> str:
    """``rows`` (``table_rows``, in the order given) as CSV, ``TABLE_COLUMNS`` for header."""
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(TABLE_COLUMNS)
    for row in rows:
        writer.writerow([_cell(c, row[c]) for c in TABLE_COLUMNS])
    return buffer.getvalue()


# --------------------------------------------------------------------------- the picture


def grid_size(n_tiles: int) -> tuple[int, int]:
    """``(width, height)`` in pixels of a picture of ``n_tiles`` tiles."""
    width = 2 * MARGIN + n_tiles * (TILE_W + 2 * BORDER) + (n_tiles - 1) * GAP
    return width, _title_height() + TILE_H + 2 * BORDER + 4 + CAPTION_LINES * LINE_H + MARGIN


def tile_box(i: int) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)``: the frame of tile ``i`` (0: the query), its outer edge, ``x1``/``y1`` exclusive.

    The frame is ``BORDER`` pixels wide inside this box; the picture lies within it.
    """
    x0 = MARGIN + i * (TILE_W + 2 * BORDER + GAP)
    y0 = _title_height()
    return x0, y0, x0 + TILE_W + 2 * BORDER, y0 + TILE_H + 2 * BORDER


def _title_height() -> int:
    return MARGIN + TITLE_LINES * LINE_H + MARGIN // 2


@functools.cache
def _font() -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    """DejaVu Sans where the system has it (it has θ and →), else PIL's own font."""
    try:
        return ImageFont.truetype("DejaVuSans.ttf", FONT_SIZE)
    except OSError:
        pass
    try:
        return ImageFont.load_default(size=FONT_SIZE)
    except TypeError:  # Pillow before 10.1: the bitmap font, one size
        return ImageFont.load_default()


def _fit_line(draw: ImageDraw.ImageDraw, text: str, width: int) -> str:
    """``text`` cut with an ellipsis to ``width`` pixels."""
    font = _font()
    if draw.textlength(text, font=font) <= width:
        return text
    lo, hi = 0, len(text)
    while lo < hi:  # the longest prefix that fits with the ellipsis
        mid = (lo + hi + 1) // 2
        if draw.textlength(text[:mid] + "…", font=font) <= width:
            lo = mid
        else:
            hi = mid - 1
    return text[:lo] + "…"


def wrap(draw: ImageDraw.ImageDraw, text: str, width: int, lines: int) -> list[str]:
    """``text`` wrapped at spaces to ``width`` pixels, at most ``lines`` lines (the last cut with an ellipsis)."""
    font = _font()
    out: list[str] = []
    words = text.split(" ")
    line = ""
    for i, word in enumerate(words):
        trial = word if not line else f"{line} {word}"
        if draw.textlength(trial, font=font) <= width or not line:
            line = trial
            continue
        out.append(line)
        line = word
        if len(out) == lines - 1:
            line = " ".join(words[i:])
            break
    out.append(line)
    return [_fit_line(draw, t, width) for t in out[:lines]]


def _picture(path: Path | None) -> Image.Image | None:
    """The image at ``path`` scaled to fit ``TILE_W`` × ``TILE_H`` (up or down, its aspect kept); ``None`` for none."""
    if path is None:
        return None
    return ImageOps.contain(open_image(path, "RGB", display_size=(TILE_W, TILE_H)), (TILE_W, TILE_H),
                            Image.Resampling.LANCZOS)


def draw_failure(failure: Failure) -> Image.Image:
    """The failure's picture (module docstring): an RGB image of ``grid_size(len(failure.tiles))`` pixels.

    Raises:
        VPRInputError: an image file cannot be read (``descriptors.base.open_image`` names it).
    """
    n = len(failure.tiles)
    canvas = Image.new("RGB", grid_size(n), WHITE)
    draw = ImageDraw.Draw(canvas)
    font = _font()
    width = canvas.width - 2 * MARGIN
    for j, line in enumerate(wrap(draw, failure.title, width, TITLE_LINES)):
        draw.text((MARGIN, MARGIN + j * LINE_H), line, fill=TEXT, font=font)
    for i, tile in enumerate(failure.tiles):
        x0, y0, x1, y1 = tile_box(i)
        picture = _picture(tile.path)
        if picture is None:
            draw.rectangle((x0 + BORDER, y0 + BORDER, x1 - BORDER - 1, y1 - BORDER - 1), fill=(235, 235, 235))
        else:
            canvas.paste(picture, (x0 + BORDER + (TILE_W - picture.width) // 2,
                                   y0 + BORDER + (TILE_H - picture.height) // 2))
        draw.rectangle((x0, y0, x1 - 1, y1 - 1), outline=tile.colour, width=BORDER)
        for j, line in enumerate(tile.caption[:CAPTION_LINES]):
            draw.text((x0, y1 + 4 + j * LINE_H), _fit_line(draw, line, x1 - x0), fill=TEXT, font=font)
    return canvas


def thumbnail_uri(picture: Image.Image, width: int = THUMB_W) -> str:
    """A ``data:image/jpeg;base64,…`` URI of ``picture`` scaled to ``width`` pixels wide (for ``index_html``)."""
    scale = width / picture.width
    small = picture.resize((width, max(1, round(picture.height * scale))), Image.Resampling.LANCZOS,
                           reducing_gap=2.0)  # a box reduction first, then Lanczos: 5x quicker, the same to the eye
    buffer = io.BytesIO()
    small.save(buffer, format="JPEG", quality=85)
    return "data:image/jpeg;base64," + base64.b64encode(buffer.getvalue()).decode("ascii")


# --------------------------------------------------------------------------- the table


def failure_rows(fitted: RetrievalFitted, failures: tuple[Failure, ...] | list[Failure],
                 pngs: dict[int, str] | None = None) -> list[dict[str, str]]:
    """One row of ``COLUMNS`` per failure, every value a string (as the CSV holds it).

    Args:
        pngs: query -> its PNG's file name (an empty cell where missing).
    """
    ds = fitted.dataset
    rows = []
    for f in failures:
        rows.append({
            "query": str(f.query),
            "query image": f.label,
            "kind": f.kind.value,
            "answer": f"place {f.answer_place}" if f.answer_place >= 0 else "rejected",
            "answer image": database_label(ds, f.answer_image) if f.answer_image >= 0 else "",
            "true place": str(f.true_place) if f.true_place >= 0 else "",
            "true image": database_label(ds, f.true_image) if f.true_image >= 0 else "",
            "true rank": ("" if math.isnan(f.true_rank) else "dropped" if math.isinf(f.true_rank)
                          else str(int(f.true_rank))),
            "score": "" if math.isnan(f.score) else f"{f.score:.4f}",
            "margin": "" if math.isnan(f.margin) else f"{f.margin:+.4f}",
            "reason": f.reason,
            "png": (pngs or {}).get(f.query, ""),
        })
    return rows


_STYLE = """
body { font-family: sans-serif; margin: 1.5em; color: #222; }
table { border-collapse: collapse; font-size: 13px; }
th, td { border: 1px solid #ccc; padding: 4px 6px; vertical-align: top; text-align: left; }
th { background: #eee; cursor: pointer; user-select: none; position: sticky; top: 0; }
th.asc::after { content: " ▲"; } th.desc::after { content: " ▼"; }
td.reason { max-width: 34em; }
dl.settings { display: grid; grid-template-columns: max-content auto; gap: 2px 1em; }
dl.settings dt { font-weight: bold; } dl.settings dd { margin: 0; }
.wrong-answer { color: #b00; } .wrong-reject { color: #a60; } .accepted-unknown { color: #707; }
"""

# Sorts the table by the clicked header: numbers by data-v (a blank cell after every number), else text.
_SCRIPT = """
document.querySelectorAll("table.failures th").forEach((th, col) => th.addEventListener("click", () => {
  const body = th.closest("table").tBodies[0];
  const up = !th.classList.contains("asc");
  th.parentNode.querySelectorAll("th").forEach(h => h.classList.remove("asc", "desc"));
  th.classList.add(up ? "asc" : "desc");
  const value = row => { const c = row.cells[col]; return c.dataset.v !== undefined ? c.dataset.v : c.textContent; };
  const rows = Array.from(body.rows).sort((a, b) => {
    const x = value(a), y = value(b), nx = parseFloat(x), ny = parseFloat(y);
    let c;
    if (th.dataset.numeric) c = (isNaN(nx) ? Infinity : nx) - (isNaN(ny) ? Infinity : ny) || 0;
    else c = x.localeCompare(y, undefined, {numeric: true});
    return up ? c : -c;
  });
  rows.forEach(r => body.appendChild(r));
}));
"""


def _sort_value(column: str, text: str) -> str | None:
    """``data-v`` of a numeric cell: the number (a dropped rank is ``Infinity``), blank for an empty cell."""
    if column not in NUMERIC:
        return None
    if text == "dropped":
        return "Infinity"
    return text.replace("place ", "")


def index_html(rows: list[dict[str, str]], settings: dict[str, str], summary: list[str],
               thumbnails: dict[str, str] | None = None) -> str:
    """The failures as one self-contained HTML page (module docstring).

    Args:
        rows: ``failure_rows``.
        settings: name -> value shown on top (dataset, descriptor, method, places, tolerance …).
        summary: lines shown under the settings (``summary_lines``).
        thumbnails: PNG file name -> ``thumbnail_uri`` of its picture (a plain link where missing).
    """
    e = html.escape
    thumbnails = thumbnails or {}
    numeric = ' data-numeric="1"'
    head = "".join(f"<th{numeric if c in NUMERIC else ''}>{e(c)}</th>" for c in COLUMNS)
    body = []
    for row in rows:
        cells = []
        for c in COLUMNS:
            text = row[c]
            if c == "png":
                if text:
                    thumb = thumbnails.get(text)
                    inner = (f'<img src="{thumb}" width="{THUMB_W}" alt="{e(text)}"><br>' if thumb else "") + e(text)
                    cells.append(f'<td><a href="{e(text)}">{inner}</a></td>')
                else:
                    cells.append("<td></td>")
                continue
            v = _sort_value(c, text)
            attr = "" if v is None else f' data-v="{e(v)}"'
            cls = f' class="{e(text)}"' if c == "kind" else ' class="reason"' if c == "reason" else ""
            cells.append(f"<td{attr}{cls}>{e(text)}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    items = "".join(f"<dt>{e(k)}</dt><dd>{e(str(v))}</dd>" for k, v in settings.items())
    notes = "".join(f"<p>{e(line)}</p>" for line in summary)
    title = f"failures: {settings.get('method', '')} on {settings.get('dataset', '')}"
    return (
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
        f"<title>{e(title)}</title><style>{_STYLE}</style></head>\n<body>\n"
        f"<h1>{e(title)}</h1>\n<dl class=\"settings\">{items}</dl>\n{notes}\n"
        f"<p>{len(rows)} rows; click a header to sort by it.</p>\n"
        f"<table class=\"failures\"><thead><tr>{head}</tr></thead>\n<tbody>\n" + "\n".join(body)
        + f"\n</tbody></table>\n<script>{_SCRIPT}</script>\n</body></html>\n"
    )
