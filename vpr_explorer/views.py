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

from vpr_explorer.database import DatabaseModel, TraversalDecisions, decide_traversal, fit_database
from vpr_explorer.datasets import Dataset
from vpr_explorer.errors import VPRInputError
from vpr_explorer.evaluation import Evaluation
from vpr_explorer.places import Places, PlaceSpec, make_places
from vpr_explorer.retrieval import QueryDecision, similarity

#: Methods the live pages summarise, in display order (place level; the image-level
#: baseline is left out because it ranks images, not places).
LIVE_METHODS = ("place-baseline", "margin-simple", "margin-weighted", "raw-simple", "raw-weighted", "global-auto")


def default_step(n_frames: int) -> int:
    """The step the app starts with: the paper's 10 on long routes, 5 on short ones."""
    return 10 if n_frames >= 100 else 5


def split_traversals(dataset: Dataset, query: str | int | None = None) -> tuple[tuple[str, ...], str]:
    """Database traversals (every one but the query) and the query traversal (default: the last)."""
    if dataset.n_traversals < 2:
        raise VPRInputError(
            f"{dataset.name!r} has one traversal: the explorer needs a second one to query with; "
            "add a traversal folder or pick another dataset"
        )
    q = dataset.n_traversals - 1 if query is None else dataset.traversal_index(query)
    database = tuple(t for i, t in enumerate(dataset.traversals) if i != q)
    return database, dataset.traversals[q]


@dataclass(frozen=True, eq=False)
class Regrouped:
    """Everything a group/step move changes, for the database/traversal model.

    Attributes:
        places: the places of the new group/step.
        model: database statistics and thresholds (database images only).
        decisions: every query-traversal frame decided under every method.
        database, query: traversal names.
        scored: ``(n_frames,)`` bool, query frames that fall in a place (the others have
            no right answer and are left out of Recall@1).
        recall1: method key -> Recall@1 over the scored query frames.
        rejected: method key -> share of scored query frames rejected.
    """

    places: Places
    model: DatabaseModel
    decisions: TraversalDecisions
    database: tuple[str, ...]
    query: str
    scored: np.ndarray
    recall1: dict[str, float]
    rejected: dict[str, float]

    @property
    def n_scored(self) -> int:
        return int(self.scored.sum())

    def rejected_frames(self, key: str) -> np.ndarray:
        """Query frames (scored or not) that ``key`` rejected."""
        return np.flatnonzero(self.decisions.outcomes[key].answer_place < 0)

    def wrong_frames(self, key: str) -> np.ndarray:
        """Scored query frames that ``key`` did not answer right at rank 1."""
        right = self.decisions.outcomes[key].right
        return np.flatnonzero(self.scored & ~right)


def regroup(
    descriptors: np.ndarray,
    dataset: Dataset,
    spec: PlaceSpec | None,
    query: str | int | None = None,
    *,
    k: float = 0.0,
    user_theta: float | None = None,
) -> Regrouped:
    """Relabel images with ``spec``, refit the database thresholds, decide every query frame.

    This is the whole recomputation a group/step slider move triggers; the descriptors
    ``(n_images, D)`` are only read.
    """
    places = make_places(dataset, spec)
    database, query_name = split_traversals(dataset, query)
    model = fit_database(descriptors, dataset, places, database)
    decisions = decide_traversal(model, descriptors, dataset, places, query_name, k=k, user_theta=user_theta)
    scored = decisions.truth.any(axis=1)
    if not scored.any():
        raise VPRInputError(f"{places.describe()}: no query frame falls in a place; lower step")
    recall1, rejected = {}, {}
    for key, o in decisions.outcomes.items():
        recall1[key] = float((o.rank[scored] == 1).mean())
        rejected[key] = float((~o.accepted[scored]).mean())
    return Regrouped(places, model, decisions, database, query_name, scored, recall1, rejected)


@dataclass(frozen=True, eq=False)
class PlaceDetail:
    """One place's negative mixture, its scores and its thresholds (database model).

    Attributes:
        place: the place id.
        images: ``(n_p,)`` dataset image indices of the place's database images.
        mu, sigma, weight: ``(n_p,)`` the mixture components N(μᵢ, σᵢ²) and weights wᵢ.
        negatives: every negative score s(i, j), i in the place, j a database image of another place.
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
        return float((self.negatives >= theta).mean()) if self.negatives.size else math.nan

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
    own, other = model.images[mine], model.images[~mine]
    mu, sigma, weight = model.stats.components(place)
    negatives = similarity(d[own], d[other]).ravel().astype(np.float64)
    same = similarity(d[own], d[own])
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
    """Place ids to show for a query: the ``n`` best by raw_p, then any right place not among them."""
    order = np.argsort(-decision.raw, kind="stable")
    order = order[np.isfinite(decision.raw[order])]
    top = list(order[:n])
    top += [int(p) for p in decision.true_places if p not in top]
    return np.array(top, dtype=np.int64)


@dataclass(frozen=True, eq=False)
class SimilarityGrid:
    """Query frames × database frames similarity, max-pooled to a displayable size.

    Cell ``(r, c)`` holds the highest s(q, i) over the query frames of row block ``r``
    and the database images (any database traversal) of column block ``c``; the pair
    attaining it is kept so that a click can open exactly that pair.

    Attributes:
        z: ``(R, C)`` similarities (rows: query frames, columns: database frames).
        query_image, db_image: ``(R, C)`` dataset image indices of the pair behind each cell.
        row_frames, col_frames: ``(R,)``, ``(C,)`` first frame of each block.
        block: frames per block along each axis (1 when not pooled).
    """

    z: np.ndarray
    query_image: np.ndarray
    db_image: np.ndarray
    row_frames: np.ndarray
    col_frames: np.ndarray
    block: int


def similarity_grid(
    descriptors: np.ndarray, dataset: Dataset, database: Sequence[str], query: str, *, max_side: int = 200
) -> SimilarityGrid:
    """The query traversal against the database traversals, one cell per frame pair (pooled above ``max_side``)."""
    d = np.asarray(descriptors)
    q = dataset.traversal_index(query)
    db_t = [dataset.traversal_index(t) for t in database]
    n = dataset.n_frames
    qi = np.array([dataset.image_index(q, f) for f in range(n)])
    dbi = np.array([[dataset.image_index(t, f) for f in range(n)] for t in db_t])  # (T, n)
    sims = np.stack([similarity(d[qi], d[row]) for row in dbi])  # (T, n, n)
    best_t = sims.argmax(axis=0)
    frame_max = np.take_along_axis(sims, best_t[None], axis=0)[0]  # (n, n)
    frame_db = dbi[best_t, np.arange(n)[None, :]]  # (n, n) db image of each frame pair
    block = max(1, math.ceil(n / max_side))
    m = math.ceil(n / block) * block
    # Pad to whole blocks with -inf (never the max), then pool each block x block tile.
    padded = np.full((m, m), -np.inf)
    padded[:n, :n] = frame_max
    tiles = padded.reshape(m // block, block, m // block, block).transpose(0, 2, 1, 3).reshape(m // block, m // block, -1)
    arg = tiles.argmax(axis=2)
    z = np.take_along_axis(tiles, arg[..., None], axis=2)[..., 0]
    starts = np.arange(0, m, block)
    rows = starts[:, None] + arg // block
    cols = starts[None, :] + arg % block
    return SimilarityGrid(z, qi[rows], frame_db[rows, cols], starts, starts.copy(), block)


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


def _strict(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {str(k): _strict(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_strict(v) for v in x]
    if isinstance(x, np.generic):
        return _strict(x.item())
    return x


def evaluation_json(ev: Evaluation) -> str:
    """``Evaluation.to_dict()`` as strict JSON: NaN (a rate with nothing to count) becomes ``null``."""
    return json.dumps(_strict(ev.to_dict()), indent=1)
