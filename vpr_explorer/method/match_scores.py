"""Training-free match scores: how sure is a query's top-1 answer (Zaffar et al., CVPR 2024).

Three scores of the image-level top-1 answer, each computed from the query's similarities
to the database alone (no training, no threshold fitted). In every one **smaller means more
confident**: a query is accepted when its score ≤ τ, so a method's precision–recall curve
sweeps τ over the scores (``protocols.precision_recall.pr_curve`` accepts score ≥ θ: give
it ``-score``).

| function          | score (per query)                                          | unit           |
|-------------------|------------------------------------------------------------|----------------|
| ``top1_distance`` | d₁, the descriptor distance of the top-1 database image    | descriptor     |
| ``pa_ratio``      | u = d₁ / d₂, the two nearest database images (PA-ratio)    | none, in [0, 1] |
| ``sue``           | the spatial spread of the top-K database positions (SUE)   | position² (m²) |

**Distances.** For L2-normalised descriptors, ‖q − x‖² = 2 − 2s, so d = √max(0, 2 − 2s)
(``descriptor_distance``); the clamp absorbs float rounding of s just above 1. The nearest
images are those of the largest similarity; distances are computed in float64 from the
similarities as given.

**The top-1 answer** (``MatchScores.top1``) is ``retrieval.top_answer``'s: the lowest-index
database image within ``TIE_TOLERANCE`` (1e-5) of the largest similarity, as the
image-level baseline answers. d₁ is the distance of the largest similarity itself.

**PA-ratio** (Lowe's ratio test on global descriptors): u = d₁/d₂ with d₁ ≤ d₂ the
distances of the two largest similarities s₁ ≥ s₂ (an image that ties with the top-1 counts
as the second). Cases the ratio leaves open:

* **the top two tie** (s₁ − s₂ ≤ ``TIE_TOLERANCE``, which includes d₂ = 0, where
  d₁ = 0 too): u = 1, the most ambiguous value. Two images the retrieval cannot tell apart
  give no evidence for either; 1 is also the limit of d₁/d₂ as d₁ → d₂. The tolerance
  matters only for near-identical images: byte-identical images score 1.0 or 0.99999994
  depending on the BLAS kernel (``retrieval``'s module doc), and near s = 1 the square root
  turns that rounding into d = 0 against d = 3.5e-4, i.e. u = 0 against u = 1. Away from
  s ≈ 1 two similarities within 1e-5 give d₁/d₂ within about 1e-5/(1 − s₂) of 1 anyway.
* **a database of one image** (or one not excluded): d₂ is the distance to the nearest
  *other* image, and with none it is +∞ (the minimum over an empty set), so u = d₁/∞ = 0:
  the ratio test has no competitor that could reject the answer. Its curve is then one
  point (every query scores 0), as it carries no information.

**SUE** (Spatial Uncertainty Estimation; definition read from the authors' public
``sue.py``, MubarizZaffar/SUE): for the K database images of largest similarity, with
descriptor distances dᵢ and positions xᵢ,

    wᵢ = exp(−slope·dᵢ) / Σⱼ exp(−slope·dⱼ)                (a softmax of −slope·d)
    x̄ = Σᵢ wᵢ xᵢ                                            (the weighted mean, not the top-1)
    SUE = ½ Σᵢ wᵢ (c(xᵢ − x̄)² + c(yᵢ − ȳ)²)                (c: clip each axis to ±clip_m)

i.e. the mean of the two axes' weighted variances (the public code computes the x–y
covariance too and does not use it). Defaults are the public code's: K = 10, slope = 350,
clip 500 (metres). Choices made here:

* **distances** are d = √(2 − 2s). The public code takes its retrieval's "L2-distances"
  for STUN descriptors on St Lucia, for which slope 350 was chosen: with other descriptors
  the spread of the top-K distances differs, so the same slope ranges from nearly uniform
  weights to nearly all weight on the top-1 (``slope`` is a parameter; 0 gives uniform).
* **clipping** is symmetric, c(v) = min(clip_m, max(−clip_m, v)), per axis. The public
  code writes ``min(500, v)``, which clips only deviations on the positive side; its comment
  ("everything that is more than 500 meters away contributes equally") is what symmetric
  clipping does. ``clip_m=None`` turns clipping off.
* the softmax is evaluated as exp(−slope·(dᵢ − d₁)) (the same weights: no underflow for
  large slopes), and x̄ as x₁ + Σ wᵢ (xᵢ − x₁) (the same mean: no cancellation for UTM
  coordinates of millions of metres, and exactly 0 spread when every xᵢ is one position).
* **which K**: the K largest similarities, an exact tie at the K-th going to the lowest
  database index (images within float rounding of the K-th may swap between BLAS kernels).
  A database of fewer than K images uses all of them; K = 1 gives 0.

**Excluded images and queries without a candidate.** A similarity of ``-inf`` excludes
its database image (d = +∞: never a nearest image, weight 0 in SUE). A query whose every
image is excluded gets ``top1 = -1`` and score +∞ in every function (never accepted).
Similarities must otherwise be finite cosines: NaN, +∞, or values outside
[−1 − 1e-3, 1 + 1e-3] (not L2-normalised descriptors) raise.

**Memory.** Queries are processed ``block`` rows at a time (default: as many rows as make
about 4M similarities, ``BLOCK_ELEMENTS``), so the temporaries stay bounded whatever the
number of queries; ``sims`` may be a memory map, read a block at a time.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.retrieval import TIE_TOLERANCE, top_answer

#: Similarities per block of queries when ``block`` is not given (≈ 16 MB of float32).
BLOCK_ELEMENTS = 1 << 22

#: How far outside [−1, 1] a similarity may lie (float rounding) before it is refused.
COSINE_SLACK = 1e-3

SUE_K = 10
SUE_SLOPE = 350.0
SUE_CLIP_M = 500.0


@dataclass(frozen=True, eq=False)
class MatchScores:
    """A match score of each query's top-1 answer; smaller is more confident.

    Attributes:
        score: ``(n_queries,)`` float64; ``+inf`` where the query has no candidate.
        top1: ``(n_queries,)`` int64 database index of the top-1 answer, ``-1`` where none.
    """

    score: np.ndarray
    top1: np.ndarray

    def __post_init__(self) -> None:
        self.score.setflags(write=False)
        self.top1.setflags(write=False)


def descriptor_distance(sims: np.ndarray) -> np.ndarray:
    """L2 distance of unit descriptors from their cosine similarity: d = √max(0, 2 − 2s), float64.

    ``-inf`` (an excluded image) gives ``+inf``.
    """
    s = np.asarray(sims, dtype=np.float64)
    return np.sqrt(np.maximum(0.0, 2.0 - 2.0 * s))


def top1_distance(sims: np.ndarray, *, block: int | None = None) -> MatchScores:
    """d₁, the descriptor distance of each query's top-1 database image.

    Args:
        sims: ``(n_queries, n_database)`` cosine similarities of L2-normalised descriptors;
            ``-inf`` excludes an image.
        block: queries per block (default: about ``BLOCK_ELEMENTS`` similarities a block).
    Returns:
        ``MatchScores``: score d₁ = √(2 − 2 s₁) (s₁ the largest similarity), ``+inf`` with
        ``top1 = -1`` where every image is excluded.
    Raises:
        VPRInputError: ``sims`` not a 2-D float array with a database column, NaN, +inf or
            a value outside [−1, 1]; ``block`` not a positive integer.
    """
    sims = _check_sims(sims)
    score, top1 = _outputs(sims.shape[0])
    for rows, b in _blocks(sims, block):
        top1[rows] = top_answer(b)
        score[rows] = descriptor_distance(b.max(axis=1))
    return MatchScores(score, top1)


def pa_ratio(sims: np.ndarray, *, block: int | None = None) -> MatchScores:
    """u = d₁/d₂, the PA-ratio of each query's two nearest database images (accept u ≤ τ).

    Args:
        sims: ``(n_queries, n_database)`` cosine similarities of L2-normalised descriptors;
            ``-inf`` excludes an image.
        block: queries per block (default: about ``BLOCK_ELEMENTS`` similarities a block).
    Returns:
        ``MatchScores``: score u in [0, 1]; 1 where the top two similarities tie (within
        ``TIE_TOLERANCE``, d₂ = 0 included); 0 where there is no second image (a database
        of one, or all others excluded); ``+inf`` with ``top1 = -1`` where every image is
        excluded (module doc).
    Raises:
        VPRInputError: as ``top1_distance``.
    """
    sims = _check_sims(sims)
    score, top1 = _outputs(sims.shape[0])
    n_db = sims.shape[1]
    for rows, b in _blocks(sims, block):
        top1[rows] = top_answer(b)
        if n_db == 1:
            s1, s2 = b[:, 0], np.full(len(b), -np.inf)
        else:
            two = np.partition(b, n_db - 2, axis=1)[:, n_db - 2:]
            s2, s1 = two[:, 0], two[:, 1]
        d1, d2 = descriptor_distance(s1), descriptor_distance(s2)
        with np.errstate(invalid="ignore", divide="ignore"):
            u = d1 / d2  # finite / inf = 0: no second image
            tie = np.asarray(s1, dtype=np.float64) - np.asarray(s2, dtype=np.float64) <= TIE_TOLERANCE
        u[tie & np.isfinite(d1)] = 1.0
        u[~np.isfinite(d1)] = np.inf
        score[rows] = u
    return MatchScores(score, top1)


def sue(sims: np.ndarray, database_xy: np.ndarray, k: int = SUE_K, slope: float = SUE_SLOPE,
        clip_m: float | None = SUE_CLIP_M, *, block: int | None = None) -> MatchScores:
    """SUE, the weighted spatial spread of each query's top-K database positions.

    SUE = ½ Σᵢ wᵢ (c(xᵢ − x̄)² + c(yᵢ − ȳ)²) over the K largest similarities, with
    wᵢ ∝ exp(−slope·dᵢ), x̄ = Σ wᵢ xᵢ and c a clip to ±clip_m per axis (module doc).

    Args:
        sims: ``(n_queries, n_database)`` cosine similarities of L2-normalised descriptors;
            ``-inf`` excludes an image.
        database_xy: ``(n_database, 2)`` finite positions of the database images (metres, for
            ``clip_m`` to mean 500 m).
        k: nearest database images (K ≥ 1; all of them if the database is smaller).
        slope: softmax slope on the descriptor distances (≥ 0, finite; 0: uniform weights).
        clip_m: bound on each axis' deviation from the weighted mean (> 0, finite), or
            ``None`` for no clipping.
        block: queries per block (default: about ``BLOCK_ELEMENTS`` similarities a block).
    Returns:
        ``MatchScores``: score in position units squared (m²), 0 when every one of the K
        images is at one position; ``+inf`` with ``top1 = -1`` where every image is excluded.
    Raises:
        VPRInputError: as ``top1_distance``; ``database_xy`` not ``(n_database, 2)`` finite;
            ``k``, ``slope`` or ``clip_m`` out of range.
    """
    sims = _check_sims(sims)
    n_db = sims.shape[1]
    xy = np.asarray(database_xy)
    if xy.shape != (n_db, 2) or xy.dtype.kind not in "iuf":
        raise VPRInputError(f"database_xy has shape {xy.shape} ({xy.dtype}): give ({n_db}, 2) numeric positions, "
                            "one per database column of sims")
    xy = xy.astype(np.float64)
    if not np.isfinite(xy).all():
        i = int(np.flatnonzero(~np.isfinite(xy).all(axis=1))[0])
        raise VPRInputError(f"database_xy row {i} is {xy[i].tolist()}: give a finite position for every database image")
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise VPRInputError(f"k = {k!r}: give the number of nearest database images as an integer ≥ 1")
    slope = _number(slope, "slope")
    if slope < 0:
        raise VPRInputError(f"slope = {slope}: give a finite slope ≥ 0 (0 weighs the K images equally)")
    if clip_m is not None:
        clip_m = _number(clip_m, "clip_m")
        if clip_m <= 0:
            raise VPRInputError(f"clip_m = {clip_m}: give a bound > 0 in position units, or None for no clipping")
    k = min(int(k), n_db)
    score, top1 = _outputs(sims.shape[0])
    for rows, b in _blocks(sims, block):
        top1[rows] = top_answer(b)
        cols = _top_k(b, k)
        d = descriptor_distance(np.take_along_axis(b, cols, axis=1))
        d1 = d.min(axis=1)
        live = np.isfinite(d1)
        with np.errstate(invalid="ignore"):
            e = np.exp(-slope * (d - d1[:, None]))
        e[~np.isfinite(d)] = 0.0  # excluded images (NaN where slope is 0 or no candidate at all)
        w = e / np.where(live, e.sum(axis=1), 1.0)[:, None]
        ref = xy[cols[np.arange(len(b)), d.argmin(axis=1)]]  # the nearest image's position
        rel = xy[cols] - ref[:, None, :]  # (rows, k, 2)
        dev = rel - np.einsum("rk,rkc->rc", w, rel)[:, None, :]
        if clip_m is not None:
            np.clip(dev, -clip_m, clip_m, out=dev)
        s = 0.5 * np.einsum("rk,rkc->r", w, dev * dev)
        s[~live] = np.inf
        score[rows] = s
    return MatchScores(score, top1)


# --------------------------------------------------------------------------- helpers


def _number(value, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise VPRInputError(f"{name} = {value!r}: give a finite number") from None
    if isinstance(value, bool) or not math.isfinite(v):
        raise VPRInputError(f"{name} = {value!r}: give a finite number")
    return v


def _check_sims(sims) -> np.ndarray:
    a = sims if isinstance(sims, np.ndarray) else np.asarray(sims)
    if a.ndim != 2 or a.dtype.kind != "f" or a.shape[1] == 0:
        raise VPRInputError(f"sims has shape {a.shape} ({a.dtype}): give (n_queries, n_database) float "
                            "similarities with at least one database column")
    return a


def _outputs(n: int) -> tuple[np.ndarray, np.ndarray]:
    return np.empty(n, dtype=np.float64), np.empty(n, dtype=np.int64)


def _blocks(sims: np.ndarray, block: int | None) -> Iterator[tuple[slice, np.ndarray]]:
    """``(rows, sims[rows])`` a block of queries at a time, each block checked for bad values."""
    n_q, n_db = sims.shape
    if block is None:
        block = max(1, BLOCK_ELEMENTS // n_db)
    elif isinstance(block, bool) or not isinstance(block, (int, np.integer)) or block < 1:
        raise VPRInputError(f"block = {block!r}: give the number of queries per block as an integer ≥ 1")
    for start in range(0, n_q, int(block)):
        rows = slice(start, min(n_q, start + int(block)))
        b = np.asarray(sims[rows])
        hi, lo = b.max(), b.min()
        if np.isnan(hi) or np.isnan(lo):
            q = start + int(np.flatnonzero(np.isnan(b).any(axis=1))[0])
            raise VPRInputError(f"sims row {q} holds NaN: give finite similarities (-inf excludes an image)")
        if hi > 1 + COSINE_SLACK or (lo < -1 - COSINE_SLACK
                                     and (lo > -np.inf or ((b < -1 - COSINE_SLACK) & (b > -np.inf)).any())):
            bad = (b > 1 + COSINE_SLACK) | ((b < -1 - COSINE_SLACK) & (b > -np.inf))
            q, i = np.argwhere(bad)[0]
            raise VPRInputError(f"sims[{start + q}, {i}] = {b[q, i]}: similarities must be cosines in [-1, 1] of "
                                "L2-normalised descriptors (normalise them, or use retrieval.similarity)")
        yield rows, b


def _top_k(b: np.ndarray, k: int) -> np.ndarray:
    """``(rows, k)`` columns of the k largest similarities of each row, exact ties to the lowest index."""
    n_db = b.shape[1]
    if k == n_db:
        return np.broadcast_to(np.arange(n_db), b.shape).copy()
    kth = np.partition(b, n_db - k, axis=1)[:, n_db - k][:, None]
    take = b >= kth
    over = np.flatnonzero(take.sum(axis=1) > k)
    if len(over):  # ties at the k-th value: keep the lowest-index ones
        bo, ko = b[over], kth[over]
        room = k - (bo > ko).sum(axis=1)
        eq = bo == ko
        take[over] = (bo > ko) | (eq & (np.cumsum(eq, axis=1, dtype=np.int32) <= room[:, None]))
    return np.nonzero(take)[1].reshape(len(b), k)
