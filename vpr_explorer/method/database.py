"""A database with its per-place thresholds, and the decisions for queries against it.

What the app's inspector and the rerun recorder share: choose database traversals, fit
the negative statistics and thresholds on their images only, then decide any query frame
(of another traversal) under every method. Pure functions over arrays.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from vpr_explorer.data.traversals import Dataset
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import Places, right_places
from vpr_explorer.method.retrieval import (
    METHODS_BY_KEY,
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
from vpr_explorer.method.stats import NegativeStats, mixture_moments, negative_stats, one_blas_thread, positive_means
from vpr_explorer.method.thresholds import (
    ThresholdMethod,
    adaptive_k,
    auto_global_threshold,
    place_thresholds,
    training_pair_scores,
)
from vpr_explorer.settings import default_workers


#: Query × database similarities held at once by ``decide_traversal`` (64 MB of float32).
PAIRS_PER_BLOCK = 1 << 24
#: Query frames from which ``decide_traversal`` takes the fused path by default: the path first
#: groups the database rows by place (one copy of the database), a cost that only many query
#: frames repay (``benchmarks/bench_app_scale.py --move-only`` times both paths).
FUSED_MIN_FRAMES = 64
#: Database × query similarities the fused path holds at once (128 MB of float32, in the
#: database's place order: no float64 copy): the app's 906 sampled frames against 33,108
#: database images are one block, so each database row is read once.
FUSED_PAIRS_PER_BLOCK = 1 << 25


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


def fit_database(
    descriptors: np.ndarray, dataset: Dataset, places: Places, traversals: Sequence[str | int]
) -> DatabaseModel:
    """Fit thresholds on the images of ``traversals`` that belong to a place."""
    trav = tuple(dataset.traversal_index(t) for t in traversals)
    if not trav:
        raise VPRInputError("database: choose at least one database traversal")
    images = np.flatnonzero(np.isin(dataset.image_traversal, trav) & (places.image_place >= 0))
    labels = places.image_place[images]
    d = database_rows(descriptors, images)
    stats = negative_stats(d, labels, places.n_places)
    neg_mean, spread = mixture_moments(stats)
    return DatabaseModel(
        images=images, places=labels, traversals=trav, n_places=places.n_places, stats=stats,
        theta={m.value: place_thresholds(stats, m) for m in ThresholdMethod},
        spread=spread, negative_mean=neg_mean, positive_mean=positive_means(d, labels, places.n_places),
        auto=auto_global_threshold(training_pair_scores(d)),
    )


def database_rows(descriptors: np.ndarray, images: np.ndarray) -> np.ndarray:
    """``descriptors[images]``, as a view (no copy) when ``images`` is one ascending run.

    The database of the traversal model is usually whole traversals stored one after the
    other, so at 100k images this saves copying most of the descriptors on every query.
    """
    d = np.asarray(descriptors)
    images = np.asarray(images)
    if images.size and images[-1] - images[0] + 1 == images.size and np.all(np.diff(images) == 1):
        return d[images[0]:images[-1] + 1]
    return d[images]


def query_places(dataset: Dataset, places: Places, query_images: np.ndarray, tolerance: int = 0) -> np.ndarray:
    """``(n_queries, n_places)`` bool: the right places of each query image (``places.right_places``)."""
    return right_places(dataset.image_frame[np.asarray(query_images)], places.frame_place, tolerance)


class Verdict(StrEnum):
    """What one method's answer for one query frame was (``places.BETWEEN_PLACES_RULE`` for ``BETWEEN``)."""

    RIGHT = "right"
    WRONG_ACCEPT = "wrong accept"
    WRONG_REJECT = "wrong reject"
    BETWEEN = "between places"


def query_verdict(decision: QueryDecision, key: str) -> Verdict:
    """The verdict on one query frame of the traversal model under method ``key``.

    A frame with no right place lies between places (every place of the traversal model
    is in the database, so it is never an unknown place): it is not scored, whatever the
    method answered, exactly as the traversal protocol, the Places page and a recording
    leave it out.
    """
    if not len(decision.true_places):  # an all-False row of ``places.right_places``
        return Verdict.BETWEEN
    o = decision.outcomes[key]
    if o.right[0]:
        return Verdict.RIGHT
    return Verdict.WRONG_ACCEPT if o.accepted[0] else Verdict.WRONG_REJECT


def image_name(dataset: Dataset, image: int) -> str:
    """A dataset image as the pages name it: "<traversal> · frame N"."""
    return f"{dataset.traversals[dataset.image_traversal[image]]} · frame {dataset.image_frame[image]}"


def describe_query(decision: QueryDecision, key: str, model: DatabaseModel, dataset: Dataset) -> str:
    """``decision.describe(key)`` for the traversal model, in the pages' words.

    The image-level answer is named by traversal and frame ("accepted as day_right ·
    frame 81 → place 8"), never by its position in the database; a frame between places
    is said to be not scored instead of judged as an unknown place.
    """
    m = METHODS_BY_KEY[key]
    o = decision.outcomes[key]
    ans, img = int(o.answer_place[0]), int(o.answer_image[0])
    named = f"{image_name(dataset, int(model.images[img]))} → " if m.level == "image" and img >= 0 else ""
    if query_verdict(decision, key) is not Verdict.BETWEEN:
        text = decision.describe(key)
        return text.replace(f"accepted as image {img} → ", f"accepted as {named}", 1) if named else text
    theta = decision.thresholds.get(m.threshold) if m.threshold else None

    def scores(p: int) -> str:
        if theta is None:
            return f"raw {decision.raw[p]:.3f}"
        return f"raw {decision.raw[p]:.3f}, threshold {theta[p]:.3f}, margin {decision.raw[p] - theta[p]:+.3f}"

    why = "not scored: the query frame lies between places, so no answer is right or wrong"
    if ans >= 0:
        return f"accepted as {named}place {ans} ({why}): {scores(ans)}"
    ranking = decision.raw if theta is None else decision.raw - theta
    closest = int(np.argmax(np.where(np.isfinite(ranking), ranking, -np.inf)))
    return f"rejected ({why}): every place scored below its threshold; the closest, place {closest}: {scores(closest)}"


def between_note(frame: int, tolerance: int = 0) -> str:
    """What the inspector says of a query frame between places (``places.BETWEEN_PLACES_RULE``)."""
    where = (f"no place holds a frame within {tolerance} frame{'s' if tolerance != 1 else ''} of it" if tolerance
             else "group/step put it in no place")
    return (f"**Frame {frame} lies between places** ({where}): it has no right answer, so, as on every page, "
            "protocol and recording, it is **not scored**; each method's answer is shown unmarked.")


def explain_query(
    model: DatabaseModel,
    descriptors: np.ndarray,
    dataset: Dataset,
    places: Places,
    query_image: int,
    *,
    k: float = 0.0,
    user_theta: float | None = None,
    tolerance: int = 0,
) -> QueryDecision:
    """The decision record of one query image against the database, under every method."""
    if dataset.image_traversal[query_image] in model.traversals:
        raise VPRInputError(
            f"query traversal {dataset.traversals[dataset.image_traversal[query_image]]!r} is in the database; "
            "pick a query from another traversal or change the database"
        )
    sims = similarity(np.asarray(descriptors)[[query_image]], database_rows(descriptors, model.images))[0]
    truth = query_places(dataset, places, np.array([query_image]), tolerance)[0]
    return decide(sims, model.places, model.n_places, model.thresholds(k, user_theta), np.flatnonzero(truth))


@dataclass(frozen=True, eq=False)
class TraversalDecisions:
    """Every frame of a query traversal decided against a database.

    Attributes:
        query_images: ``(n_frames,)`` image index of each query frame.
        truth: ``(n_frames, n_places)`` right places of each frame (none between places).
        raw: ``(n_frames, n_places)`` float32 raw_p (a maximum of float32 similarities: exact).
        best: ``(n_frames, n_places)`` int32 database image (index into ``model.images``)
            attaining raw_p. Both halve the memory of float64/int64: a whole Nordland Mini
            traversal (27,591 frames × 9,197 places) holds 2 GB instead of 4.
        outcomes: method key -> ``Outcome`` over the frames.
        thresholds: the threshold mapping used.
    """

    query_images: np.ndarray
    truth: np.ndarray
    raw: np.ndarray
    best: np.ndarray
    outcomes: dict[str, Outcome]
    thresholds: dict[str, np.ndarray | float]


def decide_traversal(
    model: DatabaseModel,
    descriptors: np.ndarray,
    dataset: Dataset,
    places: Places,
    query_traversal: str | int,
    *,
    k: float = 0.0,
    user_theta: float | None = None,
    tolerance: int = 0,
    frames: np.ndarray | None = None,
    block: int = 4096,
    threads: int | None = None,
    fused: bool | None = None,
) -> TraversalDecisions:
    """Decide every frame of ``query_traversal`` (or only ``frames``); similarities computed in blocks of frames.

    Args:
        frames: query frame numbers to decide, in the order wanted (default: all, in order).
            Deciding a sample is how an overview of a 100k-image dataset stays interactive
            (``traversal.regroup``): the cost is ``len(frames) × n_database`` similarities.
        block: query frames per block (at most ``PAIRS_PER_BLOCK`` similarities held at once,
            ``FUSED_PAIRS_PER_BLOCK`` on the fused path).
        threads: threads sharing a block's products and place maxima (default: CPU count, at
            most 8); the results do not depend on it.
        fused: ``True``: the database rows grouped by place (``retrieval.PlaceLayout``), and each
            block's similarities computed a piece of places at a time with their maxima while the
            piece is in cache (``_decide_block``); blocks of up to ``FUSED_PAIRS_PER_BLOCK``
            similarities, so that the app's sample is one block whose pieces gather their own rows
            (with several blocks the grouped rows are copied once per call). ``False``: the
            straightforward path (``retrieval.place_scores`` and ``score_queries`` on each
            block), which the fused path equals in every rank, answer and image
            (``tests/test_decide_fused.py``). ``None`` (default): fused from ``FUSED_MIN_FRAMES``
            query frames on, below which the copy costs more than it saves.
    """
    q = dataset.traversal_index(query_traversal)
    if q in model.traversals:
        raise VPRInputError(f"queries={dataset.traversals[q]!r} is also a database traversal; pick another")
    if frames is None:
        qi = np.flatnonzero(dataset.image_traversal == q)
    else:
        frames = np.asarray(frames, dtype=np.int64)
        if frames.ndim != 1 or (frames.size and (frames.min() < 0 or frames.max() >= dataset.n_frames)):
            raise VPRInputError(f"frames: must be frame numbers in 0..{dataset.n_frames - 1}")
        qi = q * dataset.n_frames + frames  # image order: traversal by traversal (Dataset.image_index)
    if not len(qi):
        raise VPRInputError("frames: no query frame to decide; choose at least one")
    truth = query_places(dataset, places, qi, tolerance)
    th = model.thresholds(k, user_theta)
    d = np.asarray(descriptors)
    parts_raw, parts_best, parts_out = [], [], []
    if fused or (fused is None and len(qi) >= FUSED_MIN_FRAMES):
        block = max(1, min(block, FUSED_PAIRS_PER_BLOCK // max(1, len(model.images))))
        layout = PlaceLayout.of(model.places, model.n_places)
        threads = default_workers() if threads is None else max(1, int(threads))
        rows = model.images[layout.order]  # database rows grouped by place
        with one_blas_thread(), ThreadPoolExecutor(threads, thread_name_prefix="vpr-decide") as pool:
            # several blocks read every row several times: copy them grouped once; one block reads
            # each piece's rows once, so the pieces gather their own (no copy of the database)
            db = _gather_rows(d, rows, pool) if len(qi) > block else None
            for lo in range(0, len(qi), block):
                raw, best, out = _decide_block(model, d, db, rows, layout, qi[lo:lo + block], th, truth[lo:lo + block],
                                               pool)
                parts_raw.append(raw.astype(np.float32))
                parts_best.append(best.astype(np.int32))
                parts_out.append(out)
    else:
        block = max(1, min(block, PAIRS_PER_BLOCK // max(1, len(model.images))))
        db = database_rows(d, model.images)
        for lo in range(0, len(qi), block):
            sims = similarity(d[qi[lo:lo + block]], db)
            raw, best = place_scores(sims, model.places, model.n_places)
            parts_raw.append(raw.astype(np.float32))
            parts_best.append(best.astype(np.int32))
            parts_out.append(score_queries(sims, model.places, model.n_places, th, truth[lo:lo + block],
                                           raw_best=(raw, best)))
    outcomes = {
        key: Outcome(
            method=parts_out[0][key].method,
            **{f: np.concatenate([getattr(p[key], f) for p in parts_out]) for f in ("rank", "answer_place", "answer_image", "n_kept")},
        )
        for key in parts_out[0]
    }
    return TraversalDecisions(qi, truth, np.concatenate(parts_raw), np.concatenate(parts_best), outcomes, th)


def _gather_rows(d: np.ndarray, rows: np.ndarray, pool: ThreadPoolExecutor, part: int = 4096) -> np.ndarray:
    """float32 ``d[rows]``, gathered by the pool's threads ``part`` rows at a time."""
    out = np.empty((len(rows), d.shape[1]), dtype=np.float32)

    def gather(lo: int) -> None:
        np.copyto(out[lo : lo + part], d[rows[lo : lo + part]], casting="same_kind")

    list(pool.map(gather, range(0, len(rows), part)))
    return out


#: Database rows per piece of ``_decide_block`` (whole places): a piece's similarities with a
#: block's queries (1,024 × 906 float32 for the app's sample at 110k images, 3.7 MB) are still
#: in the core's cache when their maxima are taken.
PIECE_ROWS = 1024


def _decide_block(
    model: DatabaseModel,
    d: np.ndarray,
    db: np.ndarray | None,
    rows: np.ndarray,
    layout: PlaceLayout,
    qi: np.ndarray,
    th: dict[str, np.ndarray | float],
    truth: np.ndarray,
    pool: ThreadPoolExecutor,
) -> tuple[np.ndarray, np.ndarray, dict[str, Outcome]]:
    """One block of query images: raw_p, the image behind it and every method's ``Outcome``.

    The pool's threads each take pieces of whole places: one float32 GEMM of the piece's
    database rows (a slice of ``db``, the rows grouped by place, or, when ``db`` is None,
    gathered by the piece itself from ``d`` at ``rows``: the same contiguous float32 rows)
    against the block's queries (each similarity ``similarity``'s float32 number, bit for bit on
    OpenBLAS's SkylakeX kernel, within a few ulp where the kernel rounds by shape: see
    ``retrieval.similarity_t``), then the piece's place maxima. The
    image-level baseline reads back only the places within the tolerance of its thresholds
    (``retrieval.score_layout_block``). A block with a non-finite similarity (a NaN or inf
    in a descriptor) takes the straightforward path, which defines what that means.
    """
    queries = np.asarray(d[qi], dtype=np.float32)
    scores_t = np.empty((len(rows), len(qi)), dtype=np.float32)
    raw_t = np.empty((len(layout.places), len(qi)), dtype=np.float32)
    best_t = np.empty((len(layout.places), len(qi)), dtype=np.int64)

    def piece(p: tuple[int, int, int, int]) -> None:
        at = slice(p[0], p[0] + p[2] * p[3])
        x = db[at] if db is not None else np.asarray(d[rows[at]], dtype=np.float32)  # the same rows either way
        similarity_t(x, queries, out=scores_t[at])
        layout_place_scores(scores_t, layout, p, raw_t, best_t)

    list(pool.map(piece, layout.pieces(PIECE_ROWS)))
    if not np.isfinite(raw_t).all():
        sims = similarity(queries, database_rows(d, model.images))
        raw, best = place_scores(sims, model.places, model.n_places)
        return raw, best, score_queries(sims, model.places, model.n_places, th, truth, raw_best=(raw, best))
    return score_layout_block(scores_t, layout, raw_t, best_t, th, truth, model.places, pool=pool)
