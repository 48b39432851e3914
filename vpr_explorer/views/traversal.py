"""The numbers behind each view of the explorer: pure functions over the library's results.

A leaf beside ``plots``: it consumes ``database`` and ``retrieval`` results and never
imports streamlit, so every number an app page shows is testable without a server.

The app's live pages use the **database / traversal model**: the database is every
traversal but one, the query traversal (by default the last, e.g. GardensPoint
``day_left`` + ``day_right`` against ``night_right``); thresholds come from the database
images only. Changing group/step relabels images and refits the closed-form statistics:
descriptors are never recomputed (see ``regroup``).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from vpr_explorer.method.database import (
    PAIRS_PER_BLOCK,
    DatabaseModel,
    TraversalDecisions,
    database_rows,
    decide_traversal,
    fit_database,
)
from vpr_explorer.data.aligned import split_traversals
from vpr_explorer.data.traversals import Dataset
from vpr_explorer.errors import VPRInputError
from vpr_explorer.protocols.evaluation import Evaluation
from vpr_explorer.method.places import Places, PlaceSpec, make_places
from vpr_explorer.views.report import strict
from vpr_explorer.method.retrieval import QueryDecision, similarity

#: Methods the live pages summarise, in display order (place level; the image-level
#: baseline is left out because it ranks images, not places).
LIVE_METHODS = ("place-baseline", "margin-simple", "margin-weighted", "raw-simple", "raw-weighted", "global-auto")


def default_step(n_frames: int) -> int:
    """The step the app starts with: the paper's 10 on long routes, 5 on short ones."""
    return 10 if n_frames >= 100 else 5


#: Query × database similarities an overview computes at most; above it the query frames
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


@dataclass(frozen=True, eq=False)
class Fitted:
    """Places and database thresholds for one group/step and query traversal: no query decided yet.

    What the pages that show one place or one query need; cost O(n_database · D), never
    query × database pairs.
    """

    places: Places
    model: DatabaseModel
    database: tuple[str, ...]
    query: str

    def first_scored_frame(self) -> int:
        """The first query frame that falls in a place."""
        return int(np.flatnonzero(self.places.frame_place >= 0)[0])


def fit(descriptors: np.ndarray, dataset: Dataset, spec: PlaceSpec | None, query: str | int | None = None) -> Fitted:
    """Relabel images with ``spec`` and fit the database thresholds (database: every traversal but ``query``)."""
    places = make_places(dataset, spec)
    database, query_name = split_traversals(dataset, query)
    return Fitted(places, fit_database(descriptors, dataset, places, database), database, query_name)


@dataclass(frozen=True, eq=False)
class Regrouped:
    """Everything a group/step move changes, for the database/traversal model.

    Attributes:
        places: the places of the new group/step.
        model: database statistics and thresholds (database images only).
        decisions: the decided query-traversal frames (``frames``) under every method.
        database, query: traversal names.
        frames: ``(n_decided,)`` ascending query frame numbers decided: every frame, or a
            seeded sample when frames × database images exceed the pair budget.
        n_frames: query frames in the traversal.
        scored: ``(n_decided,)`` bool, decided frames that fall in a place (the others have
            no right answer and are left out of Recall@1).
        recall1: method key -> Recall@1 over the scored decided frames.
        rejected: method key -> share of scored decided frames rejected.
    """

    places: Places
    model: DatabaseModel
    decisions: TraversalDecisions
    database: tuple[str, ...]
    query: str
    frames: np.ndarray
    n_frames: int
    scored: np.ndarray
    recall1: dict[str, float]
    rejected: dict[str, float]

    @property
    def n_scored(self) -> int:
        return int(self.scored.sum())

    @property
    def sampled(self) -> bool:
        """True when only a sample of the query frames was decided."""
        return len(self.frames) < self.n_frames

    def rejected_frames(self, key: str) -> np.ndarray:
        """Decided query frames (scored or not) that ``key`` rejected."""
        return self.frames[self.decisions.outcomes[key].answer_place < 0]

    def wrong_frames(self, key: str) -> np.ndarray:
        """Scored decided query frames that ``key`` did not answer right at rank 1."""
        right = self.decisions.outcomes[key].right
        return self.frames[self.scored & ~right]


def regroup(
    descriptors: np.ndarray,
    dataset: Dataset,
    spec: PlaceSpec | None,
    query: str | int | None = None,
    *,
    k: float = 0.0,
    user_theta: float | None = None,
    pair_budget: int | None = None,
    fitted: Fitted | None = None,
) -> Regrouped:
    """Relabel images with ``spec``, refit the database thresholds, decide the query frames.

    This is the whole recomputation a group/step slider move triggers; the descriptors
    ``(n_images, D)`` are only read. Every query frame is decided while frames × database
    images stay within ``pair_budget``; above it a seeded sample of frames is (``overview_frames``).

    Args:
        pair_budget: default ``PAIR_BUDGET`` (read at call time).
        fitted: ``fit(descriptors, dataset, spec, query)`` when the caller already has it.
    """
    f = fitted if fitted is not None else fit(descriptors, dataset, spec, query)
    budget = PAIR_BUDGET if pair_budget is None else pair_budget
    frames = overview_frames(dataset.n_frames, len(f.model.images), budget)
    decisions = decide_traversal(f.model, descriptors, dataset, f.places, f.query, k=k, user_theta=user_theta,
                                 frames=frames)
    scored = decisions.truth.any(axis=1)
    if not scored.any():
        raise VPRInputError(f"{f.places.describe()}: no query frame falls in a place; lower step")
    recall1, rejected = {}, {}
    for key, o in decisions.outcomes.items():
        recall1[key] = float((o.rank[scored] == 1).mean())
        rejected[key] = float((~o.accepted[scored]).mean())
    return Regrouped(f.places, f.model, decisions, f.database, f.query, frames, dataset.n_frames, scored,
                     recall1, rejected)


#: Kinds of query frames ``find_frame`` looks for.
FIND_KINDS = ("rejected", "answered wrong")


def find_frame(
    fitted: Fitted,
    descriptors: np.ndarray,
    dataset: Dataset,
    *,
    after: int,
    kind: str,
    method: str,
    k: float = 0.0,
    user_theta: float | None = None,
    pair_budget: int | None = None,
    first_chunk: int = 64,
) -> tuple[int | None, int]:
    """The next query frame after ``after`` (wrapping round) that ``method`` rejected or answered wrong.

    Frames are decided in growing chunks from ``after + 1`` on, and the search stops at
    the first match or once ``pair_budget`` query × database similarities are spent, so
    a press of "next" on a 100k-image dataset never decides the whole traversal.

    Returns:
        ``(frame, last)``: the frame found (``None`` if none) and the last frame searched;
        ``last == after`` means every frame was searched.
    """
    if kind not in FIND_KINDS:
        raise VPRInputError(f"kind={kind!r}: choose one of {', '.join(FIND_KINDS)}")
    n = dataset.n_frames
    order = (after + 1 + np.arange(n)) % n  # after+1, ..., n-1, 0, ..., after
    n_db = max(1, len(fitted.model.images))
    limit = max(1, (PAIR_BUDGET if pair_budget is None else pair_budget) // n_db)
    lo, chunk = 0, first_chunk
    while lo < n and lo < limit:
        frames = order[lo:lo + min(chunk, limit - lo)]
        dec = decide_traversal(fitted.model, descriptors, dataset, fitted.places, fitted.query, k=k,
                               user_theta=user_theta, frames=frames)
        o = dec.outcomes[method]
        hit = ~o.accepted if kind == "rejected" else (dec.truth.any(axis=1) & ~o.right)
        if hit.any():
            return int(frames[np.argmax(hit)]), int(frames[np.argmax(hit)])
        lo += len(frames)
        chunk *= 2
    return None, int(order[lo - 1])


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


def place_detail(
    model: DatabaseModel, descriptors: np.ndarray, dataset: Dataset, places: Places, place: int, query: str | int
) -> PlaceDetail:
    """The negative mixture and scores of ``place`` under ``model``."""
    if not 0 <= place < model.n_places:
        raise VPRInputError(f"place {place} is out of range: choose 0..{model.n_places - 1}")
    d = np.asarray(descriptors)
    mine = model.places == place
    own = model.images[mine]
    mu, sigma, weight = model.stats.components(place)
    # One row per image of the place against the whole database (a view, not a copy, when
    # the database is whole traversals): O(n_p · n_database), never all pairs.
    sims = similarity(d[own], database_rows(d, model.images))
    negatives = np.compress(~mine, sims, axis=1).ravel()  # float32, as scored (C order: no copy to flatten)
    same = sims[:, mine]
    positives = same[np.triu_indices(len(own), k=1)].astype(np.float64)
    q = dataset.traversal_index(query)
    query_images = np.array([dataset.image_index(q, f) for f in places.frames_of(place)], dtype=np.int64)
    query_raw = (similarity(d[query_images], d[own]).max(axis=1).astype(np.float64)
                 if len(query_images) and len(own) else np.zeros(0))
    return PlaceDetail(
        place=place, images=own, mu=mu, sigma=sigma, weight=weight, negatives=negatives, positives=positives,
        query_images=query_images, query_raw=query_raw,
        theta={name: float(t[place]) for name, t in model.theta.items()},
        spread=float(model.spread[place]), auto=float(model.auto), k_adaptive=float(model.k_adaptive[place]),
    )


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


@dataclass(frozen=True, eq=False)
class SimilarityGrid:
    """Query frames × database frames similarity, max-pooled to a displayable size.

    Cell ``(r, c)`` holds the highest s(q, i) over the query frames of row block ``r``
    and the database images (any database traversal) of column block ``c``; the pair
    attaining it is kept so that a click can open exactly that pair. When the blocks
    would hold more than the pair budget, each row is one sampled query frame (the
    centre frame of its block) against every database frame: columns stay exact
    maxima, rows are a sample (``sampled``).

    Attributes:
        z: ``(R, C)`` similarities (rows: query frames, columns: database frames).
        query_image, db_image: ``(R, C)`` dataset image indices of the pair behind each cell.
        row_frames, col_frames: ``(R,)``, ``(C,)`` first frame of each block (the sampled
            frame of each row when ``sampled``).
        block: frames per block along each axis (1 when not pooled).
        sampled: rows are single sampled query frames, not block maxima.
    """

    z: np.ndarray
    query_image: np.ndarray
    db_image: np.ndarray
    row_frames: np.ndarray
    col_frames: np.ndarray
    block: int
    sampled: bool = False


def similarity_grid(
    descriptors: np.ndarray,
    dataset: Dataset,
    database: Sequence[str],
    query: str,
    *,
    max_side: int = 200,
    pair_budget: int | None = None,
) -> SimilarityGrid:
    """The query traversal against the database traversals, one cell per frame pair (pooled above ``max_side``).

    Similarities are computed a band of rows at a time (``decide_traversal``'s block
    size), so memory stays at one band whatever the route length.
    """
    d = np.asarray(descriptors)
    q = dataset.traversal_index(query)
    db_t = np.array([dataset.traversal_index(t) for t in database], dtype=np.int64)
    if not len(db_t):
        raise VPRInputError("database: choose at least one database traversal")
    n = dataset.n_frames
    block = max(1, math.ceil(n / max_side))
    n_blocks = math.ceil(n / block)
    m = n_blocks * block
    sampled = n * n * len(db_t) > (PAIR_BUDGET if pair_budget is None else pair_budget)
    if sampled:  # one query frame per row: the centre of each row block
        row_frames = np.minimum(np.arange(n_blocks) * block + block // 2, n - 1)
        row_block = 1
    else:
        row_frames = np.arange(n)
        row_block = block
    rows_needed = n_blocks * row_block
    db_matrix = [d[t * n:(t + 1) * n] for t in db_t]  # each traversal's frames are one run: views
    z = np.empty((n_blocks, n_blocks))
    q_img = np.empty((n_blocks, n_blocks), dtype=np.int64)
    db_img = np.empty((n_blocks, n_blocks), dtype=np.int64)
    band = max(1, PAIRS_PER_BLOCK // (row_block * n * len(db_t)))  # row blocks per band
    for b0 in range(0, n_blocks, band):
        b1 = min(n_blocks, b0 + band)
        rows = np.arange(b0 * row_block, b1 * row_block)  # positions in row_frames (padded past the end)
        frames = row_frames[np.minimum(rows, len(row_frames) - 1)]
        sims = np.stack([similarity(d[q * n + frames], x) for x in db_matrix])  # (T, r, n)
        best_t = sims.argmax(axis=0)
        frame_max = np.take_along_axis(sims, best_t[None], axis=0)[0].astype(np.float64)
        frame_max[rows >= rows_needed if sampled else rows >= n] = -np.inf  # padding rows never win
        # Pad columns to whole blocks with -inf, then pool each row_block x block tile.
        padded = np.full((len(rows), m), -np.inf)
        padded[:, :n] = frame_max
        tiles = (padded.reshape(b1 - b0, row_block, n_blocks, block).transpose(0, 2, 1, 3)
                 .reshape(b1 - b0, n_blocks, row_block * block))
        arg = tiles.argmax(axis=2)
        z[b0:b1] = np.take_along_axis(tiles, arg[..., None], axis=2)[..., 0]
        r_local = (np.arange(b1 - b0)[:, None] * row_block + arg // block)  # row within the band
        cols = np.arange(n_blocks)[None, :] * block + arg % block
        q_img[b0:b1] = q * n + frames[r_local]
        db_img[b0:b1] = db_t[best_t[r_local, np.minimum(cols, n - 1)]] * n + cols
    starts = np.arange(0, m, block)
    return SimilarityGrid(z, q_img, db_img, row_frames if sampled else starts, starts.copy(), block, sampled)


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
