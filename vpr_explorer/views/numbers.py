"""The numbers behind every view of the explorer: pure functions over one dataset value.

Every dataset reaches the views as a database/queries dataset (``layouts.RetrievalDataset``;
aligned traversals through ``data.aligned``): database images and query images with the
ground truth as a relation (``groundtruth.GroundTruth``). Places cover database images
only, made by one of (``RetrievalPlaces``):

* the layout's own place ids (prepared places' file names, a manifest's ``place`` column);
* ``frames``: group/step counting frames along the route (aligned traversals) or database
  images in listed order (``places.PlaceSpec``);
* ``route`` / ``lattice``: group/step in metres along the route, or cells of a square
  lattice over the plane (``places.MetricPlaceSpec``), where the dataset has positions.

Thresholds come from the database images that fall in a place (as in
``evaluation.retrieval_protocol``); a query's right places are those holding one of its
positives. A query with no positive at all is an *unknown-place* query (the open-set case:
the right answer is to reject it); one whose positives all lie between places has no
right place either, and is left out of Recall@1. Changing group/step relabels database
images and refits the closed-form statistics: descriptors are never recomputed.

Pure functions over arrays; never imports streamlit, so every number a page shows is
testable without a server.
"""

from __future__ import annotations

import functools
import json
import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path

import numpy as np

from vpr_explorer.method.database import DatabaseModel, database_rows
from vpr_explorer.errors import VPRInputError
from vpr_explorer.protocols.evaluation import Evaluation, RetrievalTally, strict
from vpr_explorer.protocols.options import KS
from vpr_explorer.data.layouts import Layout, RetrievalDataset
from vpr_explorer.method.places import GEOMETRY_LABELS, MetricPlaceSpec, PlaceGeometry, PlaceSpec, retrieval_places
from vpr_explorer.method.retrieval import (
    METHODS_BY_KEY,
    TIE_TOLERANCE,
    Outcome,
    PlaceLayout,
    QueryDecision,
    decide,
    layout_place_scores,
    place_scores,
    score_layout_block,
    score_queries,
    similarity,
    similarity_t,
)
from vpr_explorer.method.stats import RowsOf, mixture_moments, one_blas_thread, stats_rows
from vpr_explorer.method.thresholds import (
    ThresholdMethod,
    auto_global_threshold,
    place_thresholds,
    training_pair_scores,
)
from vpr_explorer.settings import default_workers

#: Methods the live pages summarise, in display order (place level; the image-level
#: baseline is left out because it ranks images, not places).
LIVE_METHODS = ("place-baseline", "margin-simple", "margin-weighted", "raw-simple", "raw-weighted", "global-auto")


def default_step(n_frames: int) -> int:
    """The step the app starts with: the paper's 10 on long routes, 5 on short ones."""
    return 10 if n_frames >= 100 else 5



#: Query × database similarities an overview computes at most; above it the queries
#: it decides are a seeded random sample (the pages say so). 3·10⁷ keeps GardensPoint
#: (8·10⁴) and Nordland 64x32 (1.3·10⁷) exact, and 110k images at a few hundred sampled
#: query frames (``benchmarks/bench_app_scale.py`` times a slider move there).
PAIR_BUDGET = 30_000_000
OVERVIEW_SEED = 0


def overview_frames(n_frames: int, n_database: int, budget: int = PAIR_BUDGET) -> np.ndarray:
    """Query frames an overview decides: all of them, or a seeded sample with frames × database ≤ ``budget``.

    A random sample rather than every s-th frame: a stride can beat with group/step and
    land every sampled frame between places (or on the same offset inside each place).
    """
    if n_frames * max(1, n_database) <= budget:
        return np.arange(n_frames)
    size = max(1, min(n_frames, budget // max(1, n_database)))
    return np.sort(np.random.default_rng(OVERVIEW_SEED).choice(n_frames, size=size, replace=False))



class FindKind(StrEnum):
    """Which queries ``find_query`` looks for, by one method's answer (``method.database.Verdict``'s terms).

    Every kind counts only scored queries: those with a right place (a positive in a place) and
    unknown-place queries (no positive at all). A query whose positives all lie between places
    has no right answer and is never found (``places.BETWEEN_PLACES_RULE``).

    * ``rejected``: rejected, whatever the query (a wrong reject, or an unknown-place query rightly rejected);
    * ``wrongly rejected``: a query with a right place, rejected (``Verdict.WRONG_REJECT``);
    * ``wrong answer``: a query with a right place, accepted without that place at rank 1 (a tie at the top
      counts as wrong, as ``Outcome.right`` says);
    * ``accepted unknown``: an unknown-place query accepted (a false positive);
    * ``answered wrong``: any of the three wrong ones (``Verdict.WRONG_REJECT`` or ``Verdict.WRONG_ACCEPT``);
    * ``right``: a right place answered at rank 1, or an unknown-place query rejected (``Verdict.RIGHT``).
    """

    REJECTED = "rejected"
    WRONGLY_REJECTED = "wrongly rejected"
    WRONG_ANSWER = "wrong answer"
    ACCEPTED_UNKNOWN = "accepted unknown"
    ANSWERED_WRONG = "answered wrong"
    RIGHT = "right"


#: Kinds of queries ``find_query`` looks for (``FindKind``'s values, in display order).
FIND_KINDS = tuple(k.value for k in FindKind)


class Direction(StrEnum):
    """Which way ``find_query`` walks from the current query: to higher indices or lower ones, wrapping round."""

    NEXT = "next"
    PREVIOUS = "previous"


#: Each ``FindKind`` as a test of a block of queries: ``(known, unknown, accepted, right) -> found``, all ``(n,)``
#: bools (``known``: the query has a right place; ``right``: ``Outcome.right``).
_FINDS = {
    FindKind.REJECTED: lambda known, unknown, accepted, right: (known | unknown) & ~accepted,
    FindKind.WRONGLY_REJECTED: lambda known, unknown, accepted, right: known & ~accepted,
    FindKind.WRONG_ANSWER: lambda known, unknown, accepted, right: known & accepted & ~right,
    FindKind.ACCEPTED_UNKNOWN: lambda known, unknown, accepted, right: unknown & accepted,
    FindKind.ANSWERED_WRONG: lambda known, unknown, accepted, right: (known & ~right) | (unknown & accepted),
    FindKind.RIGHT: lambda known, unknown, accepted, right: (known & right) | (unknown & ~accepted),
}

#: Group and step in metres the app starts with: a place about as long as the field's 25 m
#: radius, one every 100 m (GardensPoint at 10 m a frame: the paper's group 3, step 10).
DEFAULT_GROUP_M = 25.0
DEFAULT_STEP_M = 100.0

#: What a query's ground truth makes of it (``query_status``).
KNOWN, BETWEEN, UNKNOWN = "known", "between places", "unknown place"

#: float32 scores one block of queries may hold (``decide_queries``): 2²⁵, 128 MB, so that
#: at a million database images a block is 32 queries, not 2,048 (8 GB).
SCORE_ELEMS = 1 << 25
#: float32 scores the database/queries protocol's block may hold (``evaluate_fitted``): 2²⁸,
#: 1 GB; the database is read (and converted from float16) once per block, so bigger
#: blocks convert it fewer times; the per-query work then goes ``EVAL_ROWS`` rows at a time.
EVAL_SCORE_ELEMS = 1 << 28
EVAL_ROWS = 32
#: float32 entries of a memory-mapped block converted at a time (``score_rows``): 2²⁰, 4 MB,
#: 2,048 rows at D = 512. Small enough that the allocator reuses one block's memory for the
#: next (a block above glibc's largest reuse threshold is a fresh mapping, paid in page
#: faults each time) and that the converted rows are still in cache when a narrow product
#: (one query, one place's images, the overview's sample) reads them
#: (``benchmarks/bench_million.py`` times narrow and wide products).
SCORE_BLOCK_ELEMS = 1 << 20
#: threads converting and scoring blocks side by side (BLAS in one thread each)
SCORE_THREADS = default_workers(4)


# --------------------------------------------------------------------------- scores over a large database


def dense(descriptors: np.ndarray) -> bool:
    """Whether ``descriptors`` is an in-memory float32 matrix (scored in one product), not a memmap or float16."""
    return (isinstance(descriptors, np.ndarray) and not isinstance(descriptors, np.memmap)
            and descriptors.dtype == np.float32)


def _block_rows(dim: int) -> int:
    return max(1, SCORE_BLOCK_ELEMS // max(1, dim))


def _in_blocks(n: int, dim: int, work, pieces: list[tuple[int, int]] | None = None) -> None:
    """``work(lo, hi)`` over ``pieces`` (default: blocks of ``SCORE_BLOCK_ELEMS`` entries covering
    ``range(n)``), ``SCORE_THREADS`` at a time with BLAS in one thread each: every piece writes
    its own rows or columns, and a GEMM's entry is one dot product whatever thread computes it."""
    if pieces is None:
        step = _block_rows(dim)
        pieces = [(lo, min(lo + step, n)) for lo in range(0, n, step)]
    if SCORE_THREADS <= 1 or len(pieces) <= 1:
        for lo, hi in pieces:
            work(lo, hi)
        return
    with one_blas_thread(), ThreadPoolExecutor(SCORE_THREADS, thread_name_prefix="vpr-score") as pool:
        list(pool.map(lambda p: work(*p), pieces))


def score_rows(descriptors: np.ndarray, images: np.ndarray, rows: np.ndarray | int) -> np.ndarray:
    """``(len(images), n_rows)`` float32 similarities of images ``images`` against the rows ``rows``.

    Args:
        descriptors: ``(n_images, D)`` unit rows: float32 in memory (one product, as
            ``retrieval.similarity``), or a float16/memory-mapped matrix, read
            ``SCORE_BLOCK_ELEMS`` entries at a time (``SCORE_THREADS`` blocks side by side),
            each block converted to float32, scored and dropped (never a float32 copy of the database).
        rows: indices of the rows to score against, or ``n`` for the first ``n`` rows (the database).
    """
    d = descriptors
    q = np.asarray(d[np.asarray(images, dtype=np.int64)], dtype=np.float32)
    if dense(d):
        return similarity(q, d[:rows] if isinstance(rows, (int, np.integer)) else database_rows(d, rows))
    view = RowsOf(d, None if isinstance(rows, (int, np.integer)) and rows == len(d) else
                  np.arange(int(rows)) if isinstance(rows, (int, np.integer)) else rows)
    out = np.empty((len(q), len(view)), dtype=np.float32)

    def work(lo: int, hi: int) -> None:
        np.matmul(q, np.asarray(view[lo:hi], dtype=np.float32).T, out=out[:, lo:hi])  # float16 to float32: exact

    _in_blocks(len(view), d.shape[1], work)
    return out


def score_rows_t(descriptors: np.ndarray, rows: np.ndarray, queries: np.ndarray,
                 pieces: list[tuple[int, int]] | None = None, then=None) -> np.ndarray:
    """``(len(rows), len(queries))`` float32 similarities, database rows ``rows`` × query images ``queries``
    (``retrieval.similarity_t``: the same numbers as ``score_rows``' GEMMs), a piece of rows at a time.

    ``then(lo, hi, out)`` runs on each piece right after its scores, while they are in cache
    (``decide_queries``: the piece's place maxima).
    """
    d = descriptors
    q = np.asarray(d[np.asarray(queries, dtype=np.int64)], dtype=np.float32)
    view = RowsOf(d, rows)
    out = np.empty((len(view), len(q)), dtype=np.float32)
    pieces = pieces if pieces is not None else [
        (lo, min(lo + _block_rows(d.shape[1]), len(view))) for lo in range(0, len(view), _block_rows(d.shape[1]))]

    def work(lo: int, hi: int) -> None:
        similarity_t(view[lo:hi], q, out=out[lo:hi])
        if then is not None:
            then(lo, hi, out)

    _in_blocks(len(view), d.shape[1], work, pieces)
    return out


# --------------------------------------------------------------------------- places


@dataclass(frozen=True)
class RetrievalPlaces:
    """How a dataset value's database images become places.

    Attributes:
        geometry: ``None`` for the layout's own place ids, else frames / route / lattice.
        spec: group/step in frames (``frames``: frames along the route of aligned traversals,
            database images in listed order otherwise), else ``None``.
        metric: group/step in metres (``route``, ``lattice``), else ``None``.
    """

    geometry: PlaceGeometry | None
    spec: PlaceSpec | None = None
    metric: MetricPlaceSpec | None = None

    def describe(self, dataset: RetrievalDataset | None = None) -> str:
        """E.g. "group 3, step 10 (stride reading) over frames along the route".

        Args:
            dataset: the value the places are made on: says what group/step count (frames along
                the route of aligned traversals, database images in listed order otherwise).

        Returns:
            One phrase for captions and notes.
        """
        if self.geometry is None:
            return "places given by the layout"
        if self.metric is not None:
            return self.metric.describe()
        if dataset is not None and dataset.database_frame is not None:
            return f"{self.spec.describe()} over frames along the route"
        return f"{self.spec.describe()} over database images in listed order"


def geometries(dataset: RetrievalDataset) -> tuple[PlaceGeometry, ...]:
    """The place geometries a dataset offers: none when its layout fixes the places; metres only with positions."""
    if dataset.database_place is not None:
        return ()
    if dataset.database_xy is None:
        return (PlaceGeometry.FRAMES,)
    return (PlaceGeometry.FRAMES, PlaceGeometry.ROUTE, PlaceGeometry.LATTICE)


def default_geometry(dataset: RetrievalDataset) -> PlaceGeometry | None:
    """Frames for aligned traversals; metres where there are positions (along the route when the database is one
    route in order, else a lattice), else frames; ``None`` when the layout fixes the places (the command line's
    default too)."""
    offered = geometries(dataset)
    if not offered:
        return None
    if PlaceGeometry.ROUTE not in offered or dataset.database_frame is not None:
        return PlaceGeometry.FRAMES
    return PlaceGeometry.ROUTE if dataset.ordered else PlaceGeometry.LATTICE


def check_geometry(dataset: RetrievalDataset, geometry: str | None) -> PlaceGeometry | None:
    """``geometry`` (or the default) as one the dataset offers; ``VPRInputError`` naming it otherwise."""
    if geometry is None:
        return default_geometry(dataset)
    offered = geometries(dataset)
    try:
        g = PlaceGeometry(geometry)
    except ValueError:
        g = None
    if g not in offered:
        if not offered:
            raise VPRInputError(f"geometry={geometry!r}: {dataset.name!r} names its places in its "
                                f"{dataset.layout.value}; group/step do not apply")
        raise VPRInputError(f"geometry={geometry!r}: {dataset.name!r} offers {' or '.join(offered)}"
                            + ("" if dataset.database_xy is not None else " (its layout has no positions)"))
    return g


def geometry_label(geometry: PlaceGeometry) -> str:
    return GEOMETRY_LABELS[geometry]


# --------------------------------------------------------------------------- one place, one query


@dataclass(frozen=True, eq=False)
class PlaceDetail:
    """One place's negative mixture, its scores and its thresholds (database model).

    Attributes:
        place: the place id.
        images: ``(n_p,)`` dataset image indices of the place's database images.
        mu, sigma, weight: ``(n_p,)`` the mixture components N(μᵢ, σᵢ²) and weights wᵢ.
        negatives: every negative score s(i, j), i in the place, j a database image of another place
            (float32, as scored: a place of a million-image database has 10⁷ of them).
        positives: same-place scores s(i, j), i < j both database images of the place.
        query_images: dataset image indices of the query traversal's frames of this place.
        query_raw: ``(len(query_images),)`` raw_p of those query frames: what decides them.
        theta: ``{"simple", "weighted"}`` the paper's θ_p (k = 0).
        spread: s_p, the mixture's standard deviation.
        auto: the automatic global threshold.
        k_adaptive: this place's k = clip((μ⁺ − μ⁻)/(2σ⁻), 1, 2).
    """

    place: int
    images: np.ndarray
    mu: np.ndarray
    sigma: np.ndarray
    weight: np.ndarray
    negatives: np.ndarray
    positives: np.ndarray
    query_images: np.ndarray
    query_raw: np.ndarray
    theta: dict[str, float]
    spread: float
    auto: float
    k_adaptive: float

    def theta_k(self, k: float, method: str = "weighted") -> float:
        """θ_p(k) = θ_p + k·s_p."""
        return self.theta[method] + k * self.spread

    def share_negatives_above(self, theta: float) -> float:
        """Share of negative scores at or above ``theta`` (other places this θ would keep)."""
        # compared in float64 (a Python float against float32 scores would be rounded to float32)
        return float((self.negatives >= np.float64(theta)).mean()) if self.negatives.size else math.nan

    def share_positives_below(self, theta: float) -> float:
        """Share of same-place database scores below ``theta``."""
        return float((self.positives < theta).mean()) if self.positives.size else math.nan

    def share_queries_below(self, theta: float) -> float:
        """Share of the place's own query frames whose raw_p is below ``theta`` (they would be dropped)."""
        return float((self.query_raw < theta).mean()) if self.query_raw.size else math.nan


def top_candidates(decision: QueryDecision, n: int = 8) -> np.ndarray:
    """Place ids to show for a query: the ``n`` best by raw_p, every method's answer and every right place.

    An answer or a right place outside the ``n`` best by raw_p (the margin rule can answer
    a place far down the raw_p order) joins them, so the bars always carry each method's
    answer and the right place(s); all are shown in descending raw_p (ties by place id).
    """
    raw = np.asarray(decision.raw, dtype=np.float64)
    order = np.argsort(-raw, kind="stable")
    order = order[np.isfinite(raw[order])]
    shown = set(int(p) for p in order[:n])
    shown |= {int(o.answer_place[0]) for o in decision.outcomes.values() if o.answer_place[0] >= 0}
    shown |= {int(p) for p in decision.true_places}
    return np.array(sorted(shown, key=lambda p: (-raw[p] if np.isfinite(raw[p]) else np.inf, p)), dtype=np.int64)


def true_place_rank(decision: QueryDecision) -> tuple[int, int] | None:
    """The query's best right place (the right place of highest raw_p) and its rank by raw_p, 1 for the best place.

    Ranked as ``top_candidates`` orders places: descending raw_p, ties by place id.
    ``None`` for a query with no right place (unknown place, or between places).
    """
    if not len(decision.true_places):
        return None
    raw = np.asarray(decision.raw, dtype=np.float64)
    true = np.asarray(decision.true_places, dtype=np.int64)
    place = int(true[np.argmax(raw[true])])  # the first of equal bests: the lowest id, as ranked below
    ahead = (raw > raw[place]) | ((raw == raw[place]) & (np.arange(len(raw)) < place))
    return place, 1 + int(ahead.sum())


# --------------------------------------------------------------------------- the fitted database


@dataclass(frozen=True, eq=False)
class RetrievalFitted:
    """Places of the database images and the thresholds fitted on them: no query decided yet.

    Attributes:
        dataset: the dataset.
        places: how the places were made.
        database_place: ``(n_database,)`` place of each database image, ``-1`` outside every place.
        n_places: number of places.
        model: thresholds fitted on the database images in places; ``model.images`` are their
            indices into the dataset's images (database images come first, so also database positions).
    """

    dataset: RetrievalDataset
    places: RetrievalPlaces
    database_place: np.ndarray
    n_places: int
    model: DatabaseModel

    def __post_init__(self) -> None:
        self.database_place.setflags(write=False)

    def describe(self) -> str:
        per = np.bincount(self.model.places, minlength=self.n_places)
        counts = f"{per.min()}" if per.min() == per.max() else f"{per.min()}-{per.max()}"
        skipped = self.dataset.n_database - len(self.model.images)
        return (f"{self.n_places} places × {counts} database images ({self.places.describe(self.dataset)}); "
                f"{skipped} of {self.dataset.n_database} database images between places")

    def right_places(self, queries: np.ndarray) -> np.ndarray:
        """``(len(queries), n_places)`` bool: places holding a positive of each query."""
        return self.dataset.ground_truth.places(self.database_place, self.n_places, np.asarray(queries, dtype=np.int64))

    @functools.cached_property
    def layout(self) -> tuple[PlaceLayout, np.ndarray]:
        """The database images in places grouped by place (``retrieval.PlaceLayout``), and their rows in the
        descriptors in that order (``decide_queries``)."""
        layout = PlaceLayout.of(self.model.places, self.n_places)
        rows = self.model.images[layout.order]
        rows.setflags(write=False)
        return layout, rows

    @functools.cached_property
    def between(self) -> np.ndarray:
        """``(n_queries,)`` bool: the query has positives and none lies in a place (``BETWEEN``: not scored).

        Read from the ground truth's positives (a running count of those in a place), never a
        queries × places matrix.
        """
        gt = self.dataset.ground_truth
        in_place = np.concatenate([[0], np.cumsum(self.database_place[gt.indices] >= 0)])
        out = (gt.counts > 0) & (in_place[gt.indptr[1:]] == in_place[gt.indptr[:-1]])
        out.setflags(write=False)
        return out

    def query_status(self, query: int) -> str:
        """``KNOWN`` (a right place), ``BETWEEN`` (positives, none in a place) or ``UNKNOWN`` (no positive)."""
        if self.dataset.ground_truth.counts[query] == 0:
            return UNKNOWN
        return KNOWN if self.right_places([query]).any() else BETWEEN


#: fits of memory-mapped databases kept per (dataset, descriptors, places): moving back to a
#: group/step fitted before is free (the app keeps its own cache too; the protocol reuses these)
FIT_MEMO = 8
_FITS: dict[tuple, tuple] = {}


def fit_retrieval(descriptors: np.ndarray, dataset: RetrievalDataset, places: RetrievalPlaces, *,
                  device: str | None = None) -> RetrievalFitted:
    """Label the database images with ``places`` and fit the thresholds on those in a place.

    Args:
        descriptors: ``(n_images, D)`` L2-normalised, database rows first (``dataset.image_paths``' order),
            in memory or memory-mapped (float16 or float32; read a block at a time, never copied whole).
            The fits of a memory-mapped (read-only) matrix are kept, the last ``FIT_MEMO``.
        device: ``None`` (numpy) or a torch device for the statistics' two N·D² products
            (``stats.stats_rows``); the app passes ``stats.fit_device()``.
    """
    if dense(descriptors):
        return _fit(descriptors, dataset, places, device)
    key = (id(dataset), id(descriptors), places, device)
    hit = _FITS.pop(key, None)
    if hit is None:
        hit = (dataset, descriptors, _fit(descriptors, dataset, places, device))  # holding both keeps their ids unique
    _FITS[key] = hit
    while len(_FITS) > FIT_MEMO:
        _FITS.pop(next(iter(_FITS)))
    return hit[2]


def _fit(descriptors: np.ndarray, dataset: RetrievalDataset, places: RetrievalPlaces,
         device: str | None = None) -> RetrievalFitted:
    if len(descriptors) != dataset.n_images:
        raise VPRInputError(f"{len(descriptors)} descriptors for {dataset.n_images} images of {dataset.name!r}: "
                            "recompute them")
    place, n_places = retrieval_places(dataset, places.spec, places.metric)
    images = np.flatnonzero(place >= 0)
    labels = place[images]
    # the rows in places, read a block at a time (a memory-mapped float16 database is never
    # gathered nor converted whole); the same sums as on descriptors[images]
    stats, positive_mean = stats_rows(descriptors, images, labels, n_places, device=device)
    neg_mean, spread = mixture_moments(stats)
    model = DatabaseModel(
        images=images, places=labels, traversals=tuple(int(t) for t in np.unique(dataset.database_traversal)),
        n_places=n_places, stats=stats, theta={m.value: place_thresholds(stats, m) for m in ThresholdMethod},
        spread=spread, negative_mean=neg_mean, positive_mean=positive_mean,
        auto=auto_global_threshold(training_pair_scores(descriptors, rows=images)),
    )
    return RetrievalFitted(dataset, places, np.asarray(place, dtype=np.int64), n_places, model)


def _check_query(fitted: RetrievalFitted, query: int) -> int:
    n = fitted.dataset.n_queries
    if isinstance(query, bool) or not isinstance(query, (int, np.integer)) or not 0 <= query < n:
        raise VPRInputError(f"query {query!r}: choose a query image from 0 to {n - 1}")
    return int(query)


def explain_query(fitted: RetrievalFitted, descriptors: np.ndarray, query: int, *, k: float = 0.0,
                  user_theta: float | None = None) -> QueryDecision:
    """The decision record of query image ``query`` (0-based among the queries) under every method.

    The right places are those holding a positive of the query; none for an unknown-place
    query or one whose positives lie between places (rejecting it is then right).
    """
    q = _check_query(fitted, query)
    sims = score_rows(descriptors, [fitted.dataset.n_database + q], fitted.model.images)[0]
    truth = fitted.right_places([q])[0]
    return decide(sims, fitted.model.places, fitted.n_places, fitted.model.thresholds(k, user_theta),
                  np.flatnonzero(truth))


def place_queries(fitted: RetrievalFitted, place: int) -> np.ndarray:
    """``(m,)`` ascending query indices whose right places include ``place`` (a positive of theirs lies in it).

    For aligned traversals (ground truth: the same frame) these are the query traversal's
    frames in the place. Read from the ground truth's positives, never a queries × places matrix.
    """
    gt = fitted.dataset.ground_truth
    hits = np.flatnonzero(fitted.database_place[gt.indices] == place)
    return np.unique(np.searchsorted(gt.indptr, hits, side="right") - 1).astype(np.int64)


def place_detail(fitted: RetrievalFitted, descriptors: np.ndarray, place: int) -> PlaceDetail:
    """One place's negative mixture, its scores and thresholds (``PlaceDetail``, for ``plots.mixture_figure``).

    Scores only the place's own rows: its database images against every database image in a
    place (n_p × n_placed, a block of the database at a time on a memory map), never all
    pairs; and the queries whose right places include it (``place_queries``) against its
    database images.

    Returns:
        The detail; its ``images`` and ``query_images`` are indices into the dataset's images
        (database images first, so ``images`` are database positions and ``query_images``
        are ``n_database`` + the query indices), ``query_raw`` each of those queries' raw_p
        (its best score against the place's database images).

    Raises:
        VPRInputError: ``place`` is not one of the places.
    """
    model = fitted.model
    if isinstance(place, bool) or not isinstance(place, (int, np.integer)) or not 0 <= place < fitted.n_places:
        raise VPRInputError(f"place {place!r}: choose a place from 0 to {fitted.n_places - 1}")
    mine = model.places == place
    own = model.images[mine]
    mu, sigma, weight = model.stats.components(int(place))
    sims = score_rows(descriptors, own, model.images) if len(own) else np.zeros((0, len(model.images)), np.float32)
    same = sims[:, mine]
    queries = fitted.dataset.n_database + place_queries(fitted, int(place))
    query_raw = (score_rows(descriptors, queries, own).max(axis=1).astype(np.float64) if len(queries)
                 else np.zeros(0))
    return PlaceDetail(
        place=int(place), images=own, mu=mu, sigma=sigma, weight=weight,
        negatives=np.compress(~mine, sims, axis=1).ravel(),  # float32 (C order: flattened without a copy)
        positives=same[np.triu_indices(len(own), k=1)].astype(np.float64),
        query_images=queries, query_raw=query_raw,
        theta={name: float(t[place]) for name, t in model.theta.items()},
        spread=float(model.spread[place]), auto=float(model.auto), k_adaptive=float(model.k_adaptive[place]),
    )


@dataclass(frozen=True)
class ImageAnswer:
    """The field's image-level answer of one query: its most similar database image (every one, in a place or not).

    Attributes:
        image: database position of the top image.
        score: its similarity.
        positive: whether it is a positive of the query (the field's R@1 counts the query).
        distance: metres from the query to it, where the layout has positions.
    """

    image: int
    score: float
    positive: bool
    distance: float | None


def image_answer(dataset: RetrievalDataset, descriptors: np.ndarray, query: int) -> ImageAnswer:
    """The top database image of ``query`` over every database image (the field's image-level retrieval)."""
    sims = score_rows(descriptors, [dataset.n_database + query], dataset.n_database)[0]
    top = int(np.argmax(sims))
    distance = (float(np.linalg.norm(dataset.database_xy[top] - dataset.query_xy[query]))
                if dataset.database_xy is not None and dataset.query_xy is not None else None)
    return ImageAnswer(top, float(sims[top]), bool(np.isin(top, dataset.ground_truth.positives(query))), distance)


# --------------------------------------------------------------------------- many queries


def decide_queries(fitted: RetrievalFitted, descriptors: np.ndarray, queries: np.ndarray, *, k: float = 0.0,
                   user_theta: float | None = None, block: int = 2048) -> tuple[np.ndarray, dict[str, Outcome]]:
    """Right places ``(n, n_places)`` and every method's ``Outcome`` for query images ``queries`` (blocks of rows).

    A block holds at most ``SCORE_ELEMS`` scores (fewer queries than ``block`` on a big
    database). The scores are database × queries with the database images in places grouped
    by place (``retrieval.PlaceLayout``): each
    piece of places is read (a block of the memory map, converted), scored and its place
    maxima taken while in cache, and the image-level baseline reads back only the places
    that can matter (``retrieval.score_layout_block``): the same ranks, answers and images as
    ``score_queries`` on the query × database scores (``tests/test_million.py``), without
    the column gather, the float64 copy and the dense image-level mask of every block. A
    block with a non-finite score takes ``score_queries``, which defines what that means.
    """
    queries = np.asarray(queries, dtype=np.int64)
    if not len(queries):
        raise VPRInputError("queries: no query image to decide; choose at least one")
    n = fitted.dataset.n_queries
    outside = queries[(queries < 0) | (queries >= n)]
    if len(outside):
        raise VPRInputError(f"query {int(outside[0])}: not a query of {fitted.dataset.name!r}; choose queries from 0 "
                            f"to {n - 1}")
    model = fitted.model
    images = model.images
    block = max(1, min(block, SCORE_ELEMS // max(1, len(images))))
    th = fitted.model.thresholds(k, user_theta)
    truth = fitted.right_places(queries)
    layout, db_rows = fitted.layout
    pieces = layout.pieces(_block_rows(descriptors.shape[1]))
    groups = {p[0]: p for p in pieces}
    parts = []
    for lo in range(0, len(queries), block):
        rows = fitted.dataset.n_database + queries[lo:lo + block]
        raw_t = np.empty((len(layout.places), len(rows)), dtype=np.float32)
        best_t = np.empty((len(layout.places), len(rows)), dtype=np.int64)

        def maxima(r0: int, r1: int, scores_t: np.ndarray) -> None:
            layout_place_scores(scores_t, layout, groups[r0], raw_t, best_t)

        scores_t = score_rows_t(descriptors, db_rows, rows, [(p[0], p[0] + p[2] * p[3]) for p in pieces], maxima)
        if np.isfinite(raw_t).all():
            parts.append(score_layout_block(scores_t, layout, raw_t, best_t, th, truth[lo:lo + block], model.places)[2])
        else:
            sims = score_rows(descriptors, rows, images)
            raw, best = place_scores(sims, model.places, fitted.n_places)
            parts.append(score_queries(sims, model.places, fitted.n_places, th, truth[lo:lo + block],
                                       raw_best=(raw, best)))
        del scores_t
    outcomes = {key: Outcome.joined([p[key] for p in parts]) for key in parts[0]}
    return truth, outcomes


def image_level(sims: np.ndarray, gt, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The field's image level of some queries: ``retrieval.top_answer`` and ``retrieval.pessimistic_rank`` of
    their float64 scores against ``gt.dense(rows)``, and each top score, without either dense copy.

    ``sims`` stays float32: comparing it with a float64 bound casts each score to float64 on the
    way (exactly), so every comparison is the float64 one; the positives are read from the
    sparse ground truth, and a rank is 1 + the scores at least the best positive's − tolerance,
    less the positives among them. ``tests/test_million.py`` checks it against the two functions.
    """
    top = sims.max(axis=1).astype(np.float64)
    answer = np.argmax(sims >= (top - TIE_TOLERANCE)[:, None], axis=1)
    answer[~np.isfinite(top)] = -1
    _, r, j = gt._pairs(rows)
    pos = sims[r, j].astype(np.float64)
    best = np.full(len(rows), -np.inf)
    np.maximum.at(best, r, pos)
    bound = best - TIE_TOLERANCE
    count = (sims >= bound[:, None]).sum(axis=1)
    count -= np.bincount(r, weights=pos >= bound[r], minlength=len(rows)).astype(np.int64)
    rank = 1.0 + count
    rank[~np.isfinite(best)] = np.inf
    return answer, rank, top


def evaluate_fitted(fitted: RetrievalFitted, descriptors: np.ndarray, *, user_theta: float | None = None,
                    settings: dict | None = None, progress=None, pr: bool = False,
                    score_elems: int = EVAL_SCORE_ELEMS) -> Evaluation:
    """The database/queries protocol (``evaluation.retrieval_protocol``'s table) with the fit's thresholds.

    What ``pipeline.evaluate_retrieval`` runs on a memory-mapped (or float16) database: the
    thresholds are ``fitted``'s (float32 closed-form products, as the app fits, within
    ``stats.sigma_sq_error_bound`` of the protocol's float64 ones, so a group/step already
    fitted is not fitted again), and the queries are scored in blocks of at most
    ``score_elems`` float32 scores, the database read once per block a ``SCORE_BLOCK_ELEMS`` slice
    at a time (``score_rows``); every per-query step after the scores is
    ``retrieval_protocol``'s, on ``EVAL_ROWS`` queries at a time. ``tests/test_million.py``
    checks the table equals ``retrieval_protocol``'s on the same data.
    """
    t0 = time.perf_counter()
    ds = fitted.dataset
    gt = ds.ground_truth
    n_db, n_q, n_places = ds.n_database, ds.n_queries, fitted.n_places
    model = fitted.model
    placed, labels = model.images, model.places
    database_place = fitted.database_place
    th: dict = {ThresholdMethod.SIMPLE.value: model.theta[ThresholdMethod.SIMPLE.value],
                ThresholdMethod.WEIGHTED.value: model.theta[ThresholdMethod.WEIGHTED.value], "auto": model.auto}
    if user_theta is not None:
        th["user"] = float(user_theta)
    tally = RetrievalTally(th, n_places, placed, labels, n_queries=n_q, n_database=n_db, pr=pr)
    block = max(EVAL_ROWS, score_elems // max(1, n_db))
    for b0 in range(0, n_q, block):
        sims_block = score_rows(descriptors, n_db + np.arange(b0, min(b0 + block, n_q)), n_db)
        for lo in range(b0, min(b0 + block, n_q), EVAL_ROWS):
            rows = np.arange(lo, min(lo + EVAL_ROWS, b0 + len(sims_block), n_q))
            sims = sims_block[rows - b0]
            tally.add(sims, gt.places(database_place, n_places, rows), image_level(sims, gt, rows))
        del sims_block
        if progress:
            done = min(b0 + block, n_q)
            progress(done, n_q, f"queries {done}/{n_q}")
    return tally.evaluation(gt, model.spread, model.k_adaptive, KS, settings=settings, started=t0, notes=(
        "thresholds from the explorer's fit of these places (float32 closed-form products; the command line's "
        "protocol uses float64 ones, within the bound of stats.sigma_sq_error_bound); descriptors read as "
        f"{np.dtype(descriptors.dtype).name} a block at a time",))


@dataclass(frozen=True, eq=False)
class RetrievalOverview:
    """The query images decided for one set of places: what a group/step move changes.

    Attributes:
        queries: ``(n,)`` ascending query indices decided: all, or a seeded sample when queries ×
            database images exceed the pair budget (``overview_frames``).
        n_queries: query images in the dataset.
        scored: ``(n,)`` the query has a right place (Recall@1 counts it).
        unknown: ``(n,)`` the query has no positive at all (an unknown-place query).
        outcomes: method key -> ``Outcome`` over ``queries``.
        recall1: method key -> Recall@1 over the scored queries.
        rejected: method key -> share of the scored queries rejected.
        unknown_rejected: method key -> share of the unknown-place queries rejected (NaN without any).
    """

    queries: np.ndarray
    n_queries: int
    scored: np.ndarray
    unknown: np.ndarray
    outcomes: dict[str, Outcome]
    recall1: dict[str, float]
    rejected: dict[str, float]
    unknown_rejected: dict[str, float]

    @property
    def sampled(self) -> bool:
        return len(self.queries) < self.n_queries

    @property
    def n_scored(self) -> int:
        return int(self.scored.sum())

    @property
    def n_unknown(self) -> int:
        return int(self.unknown.sum())


def overview(fitted: RetrievalFitted, descriptors: np.ndarray, *, k: float = 0.0, user_theta: float | None = None,
             pair_budget: int | None = None) -> RetrievalOverview:
    """Decide the query images (a seeded sample above ``pair_budget`` similarities) and summarise every method."""
    n_q = fitted.dataset.n_queries
    queries = overview_frames(n_q, len(fitted.model.images), PAIR_BUDGET if pair_budget is None else pair_budget)
    truth, outcomes = decide_queries(fitted, descriptors, queries, k=k, user_theta=user_theta)
    scored = truth.any(axis=1)
    unknown = fitted.dataset.ground_truth.counts[queries] == 0
    recall1, rejected, unknown_rejected = {}, {}, {}
    for key, o in outcomes.items():
        recall1[key] = float((o.rank[scored] == 1).mean()) if scored.any() else float("nan")
        rejected[key] = float((~o.accepted[scored]).mean()) if scored.any() else float("nan")
        unknown_rejected[key] = float((~o.accepted[unknown]).mean()) if unknown.any() else float("nan")
    if not scored.any():
        raise VPRInputError(f"{fitted.describe()}: no query has a positive inside a place; lower step or raise group")
    return RetrievalOverview(queries, n_q, scored, unknown, outcomes, recall1, rejected, unknown_rejected)


def search_order(n: int, after: int, direction: str = Direction.NEXT) -> np.ndarray:
    """``(n,)`` the queries in the order ``find_query`` looks at them: from the one beside ``after`` round to ``after``.

    ``next``: after + 1, after + 2, …, n − 1, 0, …, after; ``previous``: after − 1, …, 0, n − 1, …, after.
    """
    step = -1 if _check_direction(direction) is Direction.PREVIOUS else 1
    return (after + step * (1 + np.arange(n))) % n


def _check_direction(direction: str) -> Direction:
    if direction not in {d.value for d in Direction}:
        raise VPRInputError(f"direction={direction!r}: choose {' or '.join(d.value for d in Direction)}")
    return Direction(direction)


def find_query(fitted: RetrievalFitted, descriptors: np.ndarray, *, after: int, kind: str, method: str,
               direction: str = Direction.NEXT, k: float = 0.0, user_theta: float | None = None,
               pair_budget: int | None = None, first_chunk: int = 64) -> tuple[int | None, int]:
    """The first query of kind ``kind`` (``FindKind``) under ``method``, walking from ``after`` in ``direction``.

    The walk is ``search_order``: every query but ``after`` first, wrapping round at the end
    (``walked`` says whether it did), ``after`` itself last. Queries whose positives all lie
    between places are never found, whatever the kind. Queries are decided in growing chunks
    along the walk and the search stops at ``pair_budget`` similarities (default
    ``PAIR_BUDGET``); on a memory-mapped database the first chunk is a whole block of
    ``decide_queries`` (each chunk reads the database once, whatever its size).

    Returns:
        ``(query, last)``: the query found (``None`` if none) and the last query searched
        (the query found; ``after`` when every query was searched; else where the budget ran out).

    Raises:
        VPRInputError: an unknown kind or direction, or ``after`` not a query.
    """
    if kind not in FIND_KINDS:
        raise VPRInputError(f"kind={kind!r}: choose one of {', '.join(FIND_KINDS)}")
    order = search_order(fitted.dataset.n_queries, _check_query(fitted, after), _check_direction(direction))
    n = len(order)
    limit = max(1, (PAIR_BUDGET if pair_budget is None else pair_budget) // max(1, len(fitted.model.images)))
    unknown_all = fitted.dataset.ground_truth.counts == 0
    found_in = _FINDS[FindKind(kind)]
    lo, chunk = 0, first_chunk
    if not dense(descriptors):  # a pass over a memory map costs the same for 64 queries as for a block of them
        chunk = max(first_chunk, min(limit, SCORE_ELEMS // max(1, len(fitted.model.images))))
    while lo < n and lo < limit:
        queries = order[lo:lo + min(chunk, limit - lo)]
        truth, outcomes = decide_queries(fitted, descriptors, queries, k=k, user_theta=user_theta)
        o = outcomes[method]
        hit = found_in(truth.any(axis=1), unknown_all[queries], o.accepted, o.right)
        if hit.any():
            found = int(queries[np.argmax(hit)])
            return found, found
        lo += len(queries)
        chunk *= 2
    return None, int(order[lo - 1])


def walked(fitted: RetrievalFitted, after: int, last: int, direction: str = Direction.NEXT) -> tuple[bool, int]:
    """What ``find_query``'s walk from ``after`` to ``last`` (as it returned it) went past.

    Returns:
        ``(wrapped, skipped)``: whether it went round the end (past query n − 1 to 0 walking
        next, past 0 to n − 1 walking previous; a walk over every query did), and how many
        queries between places it passed over, ``last`` included (``RetrievalFitted.between``).
    """
    n = fitted.dataset.n_queries
    after, last = _check_query(fitted, after), _check_query(fitted, last)
    forward = _check_direction(direction) is Direction.NEXT
    steps = ((last - after) if forward else (after - last)) % n or n  # queries walked, ``last`` the final one
    wrapped = last <= after if forward else last >= after
    return wrapped, int(fitted.between[search_order(n, after, direction)[:steps]].sum())


# --------------------------------------------------------------------------- names


def query_label(dataset: RetrievalDataset, query: int) -> str:
    """How a page names query image ``query``: ``"<traversal> · frame N"`` for traversal folders, else its file name."""
    if dataset.query_frame is not None:
        return f"{dataset.traversals[int(dataset.query_traversal[query])]} · frame {int(dataset.query_frame[query])}"
    if dataset.layout is Layout.TRAVERSAL_POSITIONS:
        return f"{dataset.traversals[int(dataset.query_traversal[query])]} · frame {query}"
    return Path(dataset.query_paths[query]).name


def database_label(dataset: RetrievalDataset, image: int) -> str:
    """How a page names database image ``image`` (database position): as ``query_label`` does."""
    if dataset.database_frame is not None:
        t = int(dataset.database_traversal[image])
        return f"{dataset.traversals[t]} · frame {int(dataset.database_frame[image])}"
    if dataset.layout is Layout.TRAVERSAL_POSITIONS:
        t = int(dataset.database_traversal[image])
        first = int(np.argmax(dataset.database_traversal == t))
        return f"{dataset.traversals[t]} · frame {image - first}"
    return Path(dataset.database_paths[image]).name


#: The longest word a thumbnail's caption shows whole (a longer one is cut off under the picture).
THUMBNAIL_CHARS = 24


def thumbnail_label(dataset: RetrievalDataset, image: int, *, query: bool = False) -> str:
    """How a thumbnail's caption names an image: ``query_label`` / ``database_label`` when every word of it fits
    under the picture (``THUMBNAIL_CHARS``), else ``"query N"`` / ``"database image N"`` (the indices the map,
    the finder and the tables use); a long ``@UTM@`` file name is never shown cut off."""
    label = query_label(dataset, image) if query else database_label(dataset, image)
    if max(map(len, label.split()), default=0) <= THUMBNAIL_CHARS:
        return label
    return f"query {image}" if query else f"database image {image}"


def find_query_by_name(dataset: RetrievalDataset, text: str) -> int:
    """The query whose file name (or path below the dataset folder, or label) is ``text``; ``VPRInputError`` if none."""
    text = text.strip().replace("\\", "/")
    if not text:
        raise VPRInputError("query file name: type a query image's file name")
    for q, p in enumerate(dataset.query_paths):
        path = Path(p)
        names = {path.name, query_label(dataset, q)}
        try:
            names.add(path.relative_to(dataset.root).as_posix())
        except ValueError:
            pass
        if text in names:
            return q
    raise VPRInputError(f"query file name {text!r}: no query image of {dataset.name!r} has that name; "
                        f"e.g. {Path(dataset.query_paths[0]).name!r}")


def radius_of(dataset: RetrievalDataset) -> float | None:
    """The positive radius in metres of a position-tagged dataset (from its ground truth), else ``None``."""
    desc = dataset.ground_truth.description
    if desc.startswith("within ") and desc.endswith(" m"):
        return float(desc[len("within "):-len(" m")])
    return None


# --------------------------------------------------------------------------- a query's answers in words


#: Why a query with no right place is judged as it is (``describe_answer``): (accepted, rejected).
_NO_RIGHT_PLACE = {
    BETWEEN: ("not scored: its right database images lie between places",) * 2,
    UNKNOWN: ("wrong: an unknown-place query accepted: a false positive", "right: an unknown-place query rejected"),
}


def describe_answer(fitted: RetrievalFitted, decision: QueryDecision, key: str, query: int) -> str:
    """Method ``key``'s answer for query ``query`` in the pages' words, whatever the layout.

    A query with a right place reads as ``decision.describe(key)``; a query with none as what
    its ground truth makes of it (``query_status``): between places it is not scored,
    of an unknown place rejecting it is right and accepting it a false positive. An
    image-level answer names its database image (``database_label``: "day · frame 81" or
    a file name), never its position among the images in places.

    Args:
        decision: ``explain_query(fitted, descriptors, query, ...)``.
    """
    m = METHODS_BY_KEY[key]
    o = decision.outcomes[key]
    ans, img = int(o.answer_place[0]), int(o.answer_image[0])
    named = (f"{database_label(fitted.dataset, int(fitted.model.images[img]))} → "
             if m.level == "image" and img >= 0 else "")
    status = fitted.query_status(query)
    if status == KNOWN:
        text = decision.describe(key)
        return text.replace(f"accepted as image {img} → ", f"accepted as {named}", 1) if named else text
    theta = decision.thresholds.get(m.threshold) if m.threshold else None

    def scores(p: int) -> str:
        if theta is None:
            return f"raw {decision.raw[p]:.3f}"
        return f"raw {decision.raw[p]:.3f}, threshold {theta[p]:.3f}, margin {decision.raw[p] - theta[p]:+.3f}"

    accepted, rejected = _NO_RIGHT_PLACE[status]
    if ans >= 0:
        return f"accepted as {named}place {ans} ({accepted}): {scores(ans)}"
    ranking = decision.raw if theta is None else decision.raw - theta
    closest = int(np.argmax(np.where(np.isfinite(ranking), ranking, -np.inf)))
    return (f"rejected ({rejected}): every place scored below its threshold; the closest, place {closest}: "
            f"{scores(closest)}")


# --------------------------------------------------------------------------- the similarity matrix


@dataclass(frozen=True, eq=False)
class SimilarityGrid:
    """Queries × database images similarity, max-pooled to a displayable size (``plots.similarity_heatmap``).

    Cell ``(r, c)`` holds the highest s(q, i) over the queries of row block ``r`` and the
    database images of column block ``c``, and the pair attaining it, so that a click opens
    exactly that pair. Above the pair budget each row is one sampled query (the centre of
    its block) against every database image: columns stay exact maxima, rows are a sample.

    Attributes:
        z: ``(R, C)`` similarities (rows: queries, columns: database images).
        query_image, db_image: ``(R, C)`` query index and database index of the pair behind each cell.
        row_frames: ``(R,)`` first query of each row block (the sampled query when ``sampled``);
            for aligned traversals query q is frame q of the query traversal.
        col_frames: ``(C,)`` first database image of each column block (database order).
        block: database images per column block.
        row_block: queries per row block.
        sampled: rows are single sampled queries, not block maxima.
        n_queries, n_database: the value's queries and database images the grid covers.
    """

    z: np.ndarray
    query_image: np.ndarray
    db_image: np.ndarray
    row_frames: np.ndarray
    col_frames: np.ndarray
    block: int
    row_block: int
    sampled: bool
    n_queries: int
    n_database: int


def similarity_grid(dataset: RetrievalDataset, descriptors: np.ndarray, *, max_side: int = 200,
                    pair_budget: int | None = None) -> SimilarityGrid:
    """The queries against the database images, at most ``max_side`` blocks a side.

    Every query is scored while queries × database images stay within ``pair_budget``
    (default ``PAIR_BUDGET``, read at call time); above it, one query per row block, with
    at most ``pair_budget`` similarities in all. Scores come a band of queries at a time
    (``score_rows``: at most ``SCORE_ELEMS`` of them; a memory-mapped database is read a
    block at a time), each band pooled before the next.

    Args:
        descriptors: ``(n_images, D)`` unit rows, database rows first.
    """
    n_q, n_db = dataset.n_queries, dataset.n_database
    budget = PAIR_BUDGET if pair_budget is None else pair_budget
    block = math.ceil(n_db / max_side)
    n_cols = math.ceil(n_db / block)
    n_rows = min(n_q, max_side)
    sampled = n_q * n_db > budget
    if sampled:
        n_rows = max(1, min(n_rows, budget // n_db))
    row_block = math.ceil(n_q / n_rows)
    n_rows = math.ceil(n_q / row_block)
    if sampled:  # one query per row: the centre of each row block
        queries = row_frames = np.minimum(np.arange(n_rows) * row_block + row_block // 2, n_q - 1)
        step = 1
    else:
        queries, step = np.arange(n_q), row_block
        row_frames = np.arange(n_rows) * row_block
    z = np.empty((n_rows, n_cols))
    q_img = np.empty((n_rows, n_cols), dtype=np.int64)
    db_img = np.empty((n_rows, n_cols), dtype=np.int64)
    band = max(step, SCORE_ELEMS // max(1, n_db) // step * step)  # queries per band: whole row blocks
    for lo in range(0, len(queries), band):
        qs = queries[lo:lo + band]
        rows = math.ceil(len(qs) / step)
        # padding rows and columns at -inf never win a tile (each tile holds a real score)
        padded = np.full((rows * step, n_cols * block), -np.inf, dtype=np.float32)
        padded[:len(qs), :n_db] = score_rows(descriptors, n_db + qs, n_db)
        tiles = padded.reshape(rows, step, n_cols, block).transpose(0, 2, 1, 3).reshape(rows, n_cols, step * block)
        arg = tiles.argmax(axis=2)
        r0 = lo // step
        z[r0:r0 + rows] = np.take_along_axis(tiles, arg[..., None], axis=2)[..., 0]
        q_img[r0:r0 + rows] = qs[np.arange(rows)[:, None] * step + arg // block]
        db_img[r0:r0 + rows] = np.arange(n_cols)[None, :] * block + arg % block
    return SimilarityGrid(z, q_img, db_img, row_frames, np.arange(n_cols) * block, block, row_block, sampled, n_q, n_db)


# --------------------------------------------------------------------------- protocol tables


#: The Evaluation page runs its default protocol on arrival only below this many image
#: pairs (GardensPoint: 3.6·10⁵, Nordland 64x32 g3s3: 5·10⁷); above, it waits for "Run".
AUTO_RUN_PAIRS = 100_000_000


def evaluation_rows(ev: Evaluation) -> list[dict[str, object]]:
    """One row per method: Recall@K mean and std, accepted, precision and the protocol's extra columns, in %."""
    rows = []
    for r in ev.rows:
        row: dict[str, object] = {"method": r.label, "source": r.source}
        for k in ev.ks:
            row[f"R@{k}"] = 100 * r.recall[k][0]
            row[f"R@{k} ±"] = 100 * r.recall[k][1]
        row["accepted"] = 100 * r.accepted[0]
        row["precision"] = 100 * r.precision[0]
        if r.unknown_rejection is not None:
            row["unknown rejected"] = 100 * r.unknown_rejection[0]
        if r.own_traversal is not None:
            row["top-1 from own traversal"] = 100 * r.own_traversal[0]
        rows.append(row)
    return rows


def evaluation_json(ev: Evaluation) -> str:
    """``Evaluation.to_dict()`` as strict JSON: NaN (a rate with nothing to count) becomes ``null``."""
    return json.dumps(strict(ev.to_dict()), indent=1)
