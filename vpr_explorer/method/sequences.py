"""SeqSLAM as OpenSeqSLAM computes it: contrast-enhanced differences, straight trajectories, a uniqueness ratio.

Source: Milford & Wyeth, "SeqSLAM" (ICRA 2012), as implemented by OpenSeqSLAM (N. Sünderhauf,
2013, MATLAB: ``defaultParameters.m``, ``doContrastEnhancement.m``, ``doFindMatches.m``).
OpenSeqSLAM's difference matrix is database × queries; here every matrix is
``(n_queries, n_database)``, both axes in route order, and the steps read:

1. **Difference.** ``kind="difference"``: the matrix as given (OpenSeqSLAM: the mean absolute
   difference of patch-normalised 64×32 images). ``kind="similarity"``: D = 1 − S. Step 2 is
   unchanged by any map D ↦ aD + b with a > 0, so 1 − S, 2 − 2S or −S give the same result.
2. **Local contrast enhancement** along the *database* axis, for each query separately
   (OpenSeqSLAM normalises row i of its database × queries matrix by the mean and std of rows
   i − R/2 … i + R/2, column by column): with R = ``contrast_window`` (10),
   E[q, j] = (D[q, j] − mean W) / std W, W = D[q, max(0, j − R/2) … min(n_db − 1, j + R/2)],
   i.e. R + 1 = 11 database images inside the route and 6 at either end; std is the sample
   std (MATLAB's ``std``, N − 1). Where std W ≤ 1e-9·(1 + |mean W|) (a window of equal
   differences, to rounding), E = 0 (OpenSeqSLAM would divide by zero). Then E ← E − min(E)
   over the whole matrix (OpenSeqSLAM: "let the minimum distance be 0").
3. **Trajectories.** A trajectory spans ds + 1 query frames q − ds/2 … q + ds/2, centred on
   the query (OpenSeqSLAM's ``n_start : n_start + ds``: with ds = 10 that is 11 frames, five
   of them after the query, so a match waits for ds/2 frames to come); at query offset
   k = 0 … ds it visits database image s + ⌊k·v⌋, s its start and v a velocity in
   ``velocities`` (0.8, 0.9, 1.0, 1.1, 1.2: OpenSeqSLAM's whole-image moves
   ``vmin·ds : vmax·ds``; its ``vskip`` is unused). ⌊k·v⌋ is taken with a 1e-9 guard, so that
   a product like 0.3·3 = 0.8999… floors to the 1 it means. A trajectory that runs past the
   last database image costs ∞ (OpenSeqSLAM's added row of ``inf``).
4. **Scores.** OpenSeqSLAM reports start s as database image s + ds/2, whatever the velocity,
   so the score of database image j for query q is the trajectory starting ds/2 images before
   it: S[q, j] = min over v of Σ_k E[q − ds/2 + k, j − ds/2 + ⌊k·v⌋] (it passes through j at
   the query itself only for v = 1). **Lower is better.** Images j < ds/2 have no trajectory
   (S = ∞). The best image is the lowest index within ``TIE_TOLERANCE`` (1e-5) of the minimum
   (OpenSeqSLAM: MATLAB's ``min``, the first exact minimum; the tolerance is this package's
   rule for every answer, ``method.retrieval``); the best velocity is the first in
   ``velocities`` attaining the image's minimum exactly.
5. **Uniqueness ratio.** ratio = S[q, j*] / min{S[q, j] : |j − j*| > W/2}, W =
   ``ratio_window`` (10): the best score over the best outside the W + 1 images around it
   (OpenSeqSLAM's ``Rwindow``). It lies in [0, 1] (0 with no second best, which the sizes
   below rule out); **lower is more distinctive**, and a match
   is accepted when ratio ≤ threshold (OpenSeqSLAM's demo drops ``score > thresh``: a ratio
   exactly at the threshold is kept; threshold 1 keeps every match). A second best of 0 (then
   the best is 0 too) gives ratio 1.
6. **Queries at either end.** Like OpenSeqSLAM (``N = ds/2 + 1 … end − ds/2``), the first
   ds/2 and the last ds/2 queries have no centred trajectory and are not matched: ``match``
   −1, ``score``, ``ratio`` and ``velocity`` NaN, never accepted; their rows of ``scores``
   are ∞.

Sizes and parameters must make sense: ``ds``, ``contrast_window``, ``ratio_window`` even and
≥ 2 (OpenSeqSLAM rounds an odd ds up and fails on an odd window; here both are refused);
velocities finite and ≥ 0.5 (a slower trajectory could be reported at an image past the
database's end); at least ds + 1 queries; at least ⌊ds·min v⌋ + ratio_window + 2 database
images, so that every matched query has a finite second best.

**Sequence scores for per-place thresholds** (``sequence_similarity``,
``sequence_place_scores``): for each query and database image j, the trajectory of step 4
that attains S[q, j] (chosen on the enhanced differences), and the *mean raw similarity*
along it, (1/(ds + 1)) Σ_k sim[q − ds/2 + k, j − ds/2 + ⌊k·v*⌋]: a cosine similarity on
the scale of single-image scores, so the paper's per-place θ_p apply to it unchanged. Per
place, the best over the place's images (the paper's raw_p, ``retrieval.place_scores``).
−∞ where image j has no trajectory and for every image of an unmatched query.

**Order matters**: ``check_sequence`` refuses a dataset value whose database is not one route
in order (``ordered`` false: database-queries, manifest, several database traversals) or whose
queries are not one traversal in frame order. The sequence functions take matrices and cannot
check; callers run ``check_sequence`` on the value first.

**Cost.** Everything is shifted adds over blocks of query rows that stay in the CPU cache
(no loop over queries; the blocks of trajectory sums run on ``settings.default_workers()``
threads, each writing its own rows), in float64: the enhancement is 2(R + 1) of them (two passes, so that
a flat window's std is 0 to rounding), the trajectories ds + 1 per velocity less the prefixes
velocities share (32 for OpenSeqSLAM's five instead of 55), each sum added in k order, so
that a plain loop over queries, starts and velocities gets the same numbers bit for bit.
``benchmarks/bench_acceptance.py`` times it beside the similarity matrix.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from vpr_explorer.data.layouts import RetrievalDataset
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.retrieval import TIE_TOLERANCE, place_scores
from vpr_explorer.settings import default_workers

#: OpenSeqSLAM's defaults (``defaultParameters.m``).
CONTRAST_WINDOW = 10
DS = 10
VELOCITIES = (0.8, 0.9, 1.0, 1.1, 1.2)
RATIO_WINDOW = 10
#: ⌊k·v⌋ is taken as ⌊k·v + FLOOR_GUARD⌋ (module doc, step 3).
FLOOR_GUARD = 1e-9
#: A window whose std is at most this × (1 + |mean|) is flat: its entries get E = 0 (module doc, step 2).
FLAT_STD = 1e-9
#: Bytes of one block of rows the shifted adds work on (kept within a CPU's L2 cache).
_BLOCK_BYTES = 1 << 20


class MatrixKind(StrEnum):
    """What a matrix given to SeqSLAM holds: lower is better, or higher is better."""

    DIFFERENCE = "difference"
    SIMILARITY = "similarity"


@dataclass(frozen=True, eq=False)
class SeqSLAMResult:
    """SeqSLAM's answer for every query, each array ``(n_queries,)`` unless said.

    Attributes:
        match: best database image, ``-1`` for a query at either end (unmatched).
        score: its sequence score S[q, match] (lower is better), NaN if unmatched.
        ratio: the uniqueness ratio (module doc, step 5), NaN if unmatched.
        velocity: the velocity of the best trajectory, NaN if unmatched.
        scores: ``(n_queries, n_database)`` sequence scores S, ``inf`` where no trajectory.
    """

    match: np.ndarray
    score: np.ndarray
    ratio: np.ndarray
    velocity: np.ndarray
    scores: np.ndarray

    def __post_init__(self) -> None:
        for a in (self.match, self.score, self.ratio, self.velocity, self.scores):
            a.setflags(write=False)

    @property
    def matched(self) -> np.ndarray:
        """``(n_queries,)`` bool: the query has a centred trajectory (not one of the ds/2 at either end)."""
        return self.match >= 0

    def accepted(self, threshold: float) -> np.ndarray:
        """``(n_queries,)`` bool: matched and ratio ≤ ``threshold`` (a ratio exactly at it is accepted).

        Raises:
            VPRInputError: ``threshold`` is not a finite number.
        """
        t = _finite_number(threshold, "threshold")
        with np.errstate(invalid="ignore"):
            return self.ratio <= t  # NaN (unmatched) compares False


# --------------------------------------------------------------------------- checks


def _finite_number(value: object, name: str) -> float:
    try:
        x = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise VPRInputError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(x):
        raise VPRInputError(f"{name} must be finite, got {value!r}")
    return x


def _even_window(value: object, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 2 or value % 2:
        raise VPRInputError(f"{name} must be an even whole number ≥ 2 (OpenSeqSLAM: 10), got {value!r}")
    return int(value)


def _velocities(velocities: Sequence[float]) -> np.ndarray:
    try:
        v = np.asarray(velocities, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise VPRInputError(f"velocities must be numbers, got {velocities!r}") from None
    if v.size == 0 or not np.all(np.isfinite(v)) or np.any(v < 0.5):
        raise VPRInputError(
            "velocities must be finite numbers ≥ 0.5, at least one (OpenSeqSLAM: 0.8 to 1.2 in steps of 0.1), "
            f"got {velocities!r}"
        )
    return v


def _matrix(matrix: object, name: str) -> np.ndarray:
    """The matrix as a float array (float32 stays float32: blocks are widened to float64 one at a time)."""
    try:
        m = np.asarray(matrix)
        if m.dtype.kind != "f":
            m = m.astype(np.float64)
    except (TypeError, ValueError):
        raise VPRInputError(f"{name} must be a numeric (n_queries, n_database) matrix") from None
    if m.ndim != 2:
        raise VPRInputError(f"{name} must be 2-D (n_queries, n_database), got shape {m.shape}")
    if not np.isfinite(m).all():
        raise VPRInputError(
            f"{name} holds NaN or infinite values: SeqSLAM needs every pair's score; fill or drop them first"
        )
    return m


def _kind(kind: MatrixKind | str) -> MatrixKind:
    try:
        return MatrixKind(kind)
    except ValueError:
        raise VPRInputError(f"kind must be one of {', '.join(m.value for m in MatrixKind)}, got {kind!r}") from None


def trajectory_offsets(ds: int = DS, velocities: Sequence[float] = VELOCITIES) -> np.ndarray:
    """``(n_velocities, ds + 1)`` database offsets ⌊k·v⌋ of each trajectory from its start (module doc, step 3).

    Raises:
        VPRInputError: ``ds`` odd or < 2, a velocity below 0.5 or not finite.
    """
    ds = _even_window(ds, "ds")
    v = _velocities(velocities)
    return np.floor(np.arange(ds + 1)[None, :] * v[:, None] + FLOOR_GUARD).astype(np.int64)


def _check_sizes(n_queries: int, n_database: int, ds: int, offsets: np.ndarray, ratio_window: int) -> None:
    if n_queries < ds + 1:
        raise VPRInputError(f"SeqSLAM needs at least ds + 1 = {ds + 1} queries in sequence, got {n_queries}: lower ds")
    need = int(offsets[:, -1].min()) + ratio_window + 2
    if n_database < need:
        raise VPRInputError(
            f"SeqSLAM needs at least {need} database images (the slowest trajectory's length + ratio_window + 2) "
            f"to find a second best outside the window, got {n_database}: lower ds or ratio_window"
        )


def check_sequence(dataset: RetrievalDataset) -> None:
    """Refuse a dataset value whose order along the route means nothing to a sequence method.

    Args:
        dataset: the dataset value the similarity matrix comes from.

    Raises:
        VPRInputError: naming the dataset, when its database is not one route in order
            (``ordered`` false: a database-queries or manifest layout, several database
            traversals), or its queries are not one traversal in frame order.
    """
    name = f"{dataset.name!r} ({dataset.layout.value})"
    if not dataset.ordered:
        raise VPRInputError(
            f"dataset {name} is not one ordered route: SeqSLAM matches runs of consecutive images and needs the "
            "database as one traversal in route order; use aligned traversals with one database traversal, "
            "a traversal-positions layout with one, or VPR-Bench, or a single-image method"
        )
    for side, traversal, frame in (("database", dataset.database_traversal, dataset.database_frame),
                                   ("queries", dataset.query_traversal, dataset.query_frame)):
        if len(np.unique(traversal)) > 1:
            raise VPRInputError(
                f"the {side} of dataset {name} come from {len(np.unique(traversal))} traversals: SeqSLAM needs "
                f"one traversal in order on each side; choose one {'database' if side == 'database' else 'query'} "
                "traversal"
            )
        if frame is not None and np.any(np.diff(frame) <= 0):
            raise VPRInputError(
                f"the {side} of dataset {name} are not in frame order: SeqSLAM needs each side in route order"
            )


# --------------------------------------------------------------------------- steps


def _rows_per_block(width: int, halo: int) -> int:
    return max(1, _BLOCK_BYTES // (8 * width) - halo)


def _enhance(m: np.ndarray, kind: MatrixKind, r: int) -> tuple[np.ndarray, float]:
    """E before the shift (module doc, step 2) and its minimum, from a validated matrix.

    Two passes over each window, as shifted adds (a sum of squares from running sums would
    lose √eps of the std to cancellation, and with it the flat windows).
    """
    nq, nd = m.shape
    if nd < 2:
        raise VPRInputError(f"contrast enhancement needs at least 2 database images, got {nd}")
    h = r // 2
    j = np.arange(nd)
    lo, hi = np.maximum(0, j - h), np.minimum(nd - 1, j + h)
    count = (hi - lo + 1).astype(np.float64)
    edges = np.flatnonzero(count < r + 1)  # windows cut by an end of the route
    out = np.empty((nq, nd), dtype=np.float64)
    rows = _rows_per_block(4 * (nd + r), 0)
    starts = range(0, nq, rows)
    windows = (lo, hi, count, edges)
    with ThreadPoolExecutor(max_workers=max(1, min(default_workers(), len(starts)))) as pool:
        list(pool.map(lambda r0: _enhance_block(m[r0:r0 + rows], kind, r, windows, out[r0:r0 + rows]), starts))
    return out, float(out.min())


def _enhance_block(block: np.ndarray, kind: MatrixKind, r: int, windows: tuple, out: np.ndarray) -> None:
    """``_enhance`` of a block of query rows, written into ``out`` (that block's rows of the result)."""
    lo, hi, count, edges = windows
    b, nd = block.shape
    h = r // 2
    padded = np.zeros((b, nd + r), dtype=np.float64)
    d = padded[:, h:h + nd]
    d[...] = block
    if kind is MatrixKind.SIMILARITY:
        np.subtract(1.0, d, out=d)
    total = padded[:, 0:nd].copy()  # zeros beyond either end add nothing
    for o in range(1, r + 1):
        total += padded[:, o:o + nd]
    mean = np.divide(total, count, out=total)
    squares = np.zeros((b, nd), dtype=np.float64)
    dev = np.empty((b, nd), dtype=np.float64)
    for o in range(r + 1):
        np.subtract(padded[:, o:o + nd], mean, out=dev)
        np.multiply(dev, dev, out=dev)
        squares += dev
    for c in edges:  # the zeros beyond the end are not in the window: recount those columns
        w = d[:, lo[c]:hi[c] + 1] - mean[:, c:c + 1]
        squares[:, c] = np.einsum("ij,ij->i", w, w)
    std = np.sqrt(np.divide(squares, count - 1.0, out=squares), out=squares)
    e = np.subtract(d, mean, out=dev)
    flat = std <= FLAT_STD * (1.0 + np.abs(mean))
    np.divide(e, std, out=e, where=~flat)
    e[flat] = 0.0
    out[...] = e


def contrast_enhance(difference: np.ndarray, contrast_window: int = CONTRAST_WINDOW) -> np.ndarray:
    """OpenSeqSLAM's local contrast enhancement, minimum shifted to 0 (module doc, step 2).

    Args:
        difference: ``(n_queries, n_database)`` differences (lower is better), database in route order.
        contrast_window: R; each entry is normalised over the database images j − R/2 … j + R/2.

    Returns:
        ``(n_queries, n_database)`` float64 E ≥ 0, with min(E) = 0.

    Raises:
        VPRInputError: ``contrast_window`` odd or < 2, a matrix that is not 2-D or not finite,
            fewer than 2 database images.
    """
    r = _even_window(contrast_window, "contrast_window")
    e, low = _enhance(_matrix(difference, "the difference matrix"), MatrixKind.DIFFERENCE, r)
    e -= low
    return e


def _path_sums(e: np.ndarray, b: int, nd: int, ds: int, offsets: np.ndarray) -> list[np.ndarray]:
    """Σ_k e[c + k, s + off[k]] for every trajectory, ``(b, nd)`` each, added in k order.

    Trajectories sharing their first offsets share those partial sums (0.8 and 0.9 share
    six, 1.0 and 1.1 ten): 32 shifted adds for OpenSeqSLAM's five velocities instead of 55.
    """
    out: list[np.ndarray | None] = [None] * len(offsets)
    # (partial sum, next k, velocities sharing it); the sum may be handed on without a copy
    stack = [(e[0:b, 0:nd].copy(), 1, list(range(len(offsets))))]
    while stack:
        acc, k, group = stack.pop()
        while k <= ds and len({int(offsets[i, k]) for i in group}) == 1:
            o = int(offsets[group[0], k])
            acc += e[k:k + b, o:o + nd]
            k += 1
        if k > ds:
            for i in group:
                out[i] = acc if i == group[0] else acc.copy()
            continue
        branches: dict[int, list[int]] = {}
        for i in group:
            branches.setdefault(int(offsets[i, k]), []).append(i)
        for n, sub in enumerate(branches.values()):
            stack.append((acc if n == 0 else acc.copy(), k, sub))
    return out  # type: ignore[return-value]


def _trajectories(enhanced: np.ndarray, low: float, ds: int, offsets: np.ndarray,
                  values: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Sequence scores S of E = ``enhanced`` − ``low``, the best velocity's index, and ``values`` summed
    along that trajectory (step 4).

    Returns ``(scores, velocity_index, value_sums)``, each ``(n_queries, n_database)``: ``inf``,
    ``-1`` and NaN where image j has no trajectory or the query is unmatched.
    """
    nq, nd = enhanced.shape
    pad = int(offsets.max()) + 1
    scores = np.full((nq, nd), np.inf, dtype=np.float64)
    best_v = np.full((nq, nd), -1, dtype=np.int8 if len(offsets) < 128 else np.int64)
    sums = None if values is None else np.full((nq, nd), np.nan, dtype=np.float64)
    n_centres = nq - ds
    rows = _rows_per_block((nd + pad) * (1 if values is None else 2), ds)
    out = (scores, best_v, sums)
    starts = range(0, n_centres, rows)
    # blocks of centres write disjoint rows; numpy's adds and comparisons release the GIL
    with ThreadPoolExecutor(max_workers=max(1, min(default_workers(), len(starts)))) as pool:
        list(pool.map(lambda c0: _trajectory_block(enhanced, low, values, ds, offsets, c0, min(n_centres, c0 + rows),
                                                   out), starts))
    return scores, best_v, sums


def _trajectory_block(enhanced: np.ndarray, low: float, values: np.ndarray | None, ds: int, offsets: np.ndarray,
                      c0: int, c1: int, out: tuple[np.ndarray, np.ndarray, np.ndarray | None]) -> None:
    """``_trajectories`` for the centre queries ``c0 + ds/2 … c1 − 1 + ds/2``, written into ``out``'s rows of them."""
    scores, best_v, sums = out
    nd = enhanced.shape[1]
    h = ds // 2
    width = nd + int(offsets.max()) + 1
    b = c1 - c0
    e = np.full((b + ds, width), np.inf, dtype=np.float64)
    # the trajectory of centre c + h runs over rows c … c + ds
    np.subtract(enhanced[c0:c1 + ds], low, out=e[:, :nd])
    acc = _path_sums(e, b, nd, ds, offsets)
    acc_x = None
    if values is not None:
        x = np.zeros((b + ds, width), dtype=np.float64)
        x[:, :nd] = values[c0:c1 + ds]
        acc_x = _path_sums(x, b, nd, ds, offsets)
    best, vel = acc[0], np.zeros((b, nd), dtype=best_v.dtype)
    best_x = acc_x[0] if acc_x is not None else None
    for i in range(1, len(offsets)):
        better = acc[i] < best
        np.copyto(best, acc[i], where=better)
        np.copyto(vel, i, where=better)
        if acc_x is not None:
            np.copyto(best_x, acc_x[i], where=better)
    # start s is reported as image s + ds/2; starts past n_db - ds/2 run out (velocities ≥ 0.5)
    scores[c0 + h:c1 + h, h:] = best[:, :nd - h]
    best_v[c0 + h:c1 + h, h:] = np.where(np.isfinite(best[:, :nd - h]), vel[:, :nd - h], -1)
    if sums is not None:
        sums[c0 + h:c1 + h, h:] = np.where(np.isfinite(best[:, :nd - h]), best_x[:, :nd - h], np.nan)


def _sequence_inputs(matrix, what: str, contrast_window: int, ds: int, velocities) -> tuple[np.ndarray, int, np.ndarray]:
    """The checked matrix, contrast window and trajectory offsets of ``sequence_scores`` and ``sequence_similarity``."""
    offsets = trajectory_offsets(ds, velocities)
    r = _even_window(contrast_window, "contrast_window")
    m = _matrix(matrix, what)
    if m.shape[0] < ds + 1:
        raise VPRInputError(f"SeqSLAM needs at least ds + 1 = {ds + 1} queries in sequence, got {m.shape[0]}: lower ds")
    return m, r, offsets


def sequence_scores(difference: np.ndarray, *, contrast_window: int = CONTRAST_WINDOW, ds: int = DS,
                    velocities: Sequence[float] = VELOCITIES) -> tuple[np.ndarray, np.ndarray]:
    """SeqSLAM's sequence score of every (query, database image) pair (module doc, steps 2–4).

    Args:
        difference: ``(n_queries, n_database)`` differences, both axes in route order.
        contrast_window: R of the contrast enhancement.
        ds: the trajectory spans ds + 1 query frames centred on the query.
        velocities: database images per query frame of the straight trajectories.

    Returns:
        scores: ``(n_queries, n_database)`` S (lower is better), ``inf`` where image j has no
            trajectory (j < ds/2, or every trajectory runs past the database) and on the rows of
            the ds/2 queries at either end.
        velocity: ``(n_queries, n_database)`` index into ``velocities`` of the trajectory
            attaining S, ``-1`` where S is ``inf``.

    Raises:
        VPRInputError: a bad parameter or matrix (see ``seqslam``).
    """
    d, r, offsets = _sequence_inputs(difference, "the difference matrix", contrast_window, ds, velocities)
    scores, vel, _ = _trajectories(*_enhance(d, MatrixKind.DIFFERENCE, r), ds, offsets)
    return scores, vel


def uniqueness(scores: np.ndarray, ratio_window: int = RATIO_WINDOW) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The best image, its score and the uniqueness ratio of every query (module doc, step 5).

    Args:
        scores: ``(n_queries, n_database)`` sequence scores, lower is better, ``inf`` where none.
        ratio_window: W; the second best is the best score farther than W/2 images from the best.

    Returns:
        match: ``(n_queries,)`` lowest index within ``TIE_TOLERANCE`` of the row's minimum,
            ``-1`` where the row is all ``inf``.
        score: ``(n_queries,)`` the row's minimum, NaN where none.
        ratio: ``(n_queries,)`` best / second best (1 where the second best is 0; 0 where there
            is none), NaN where no match.

    Raises:
        VPRInputError: ``ratio_window`` odd or < 2, ``scores`` not 2-D or holding NaN.
    """
    w = _even_window(ratio_window, "ratio_window")
    s = np.asarray(scores, dtype=np.float64)
    if s.ndim != 2:
        raise VPRInputError(f"scores must be 2-D (n_queries, n_database), got shape {s.shape}")
    if np.isnan(s).any():
        raise VPRInputError("scores hold NaN: mark a pair without a trajectory with inf")
    nq, nd = s.shape
    if nd == 0:
        return np.full(nq, -1, dtype=np.int64), np.full(nq, np.nan), np.full(nq, np.nan)
    best = s.min(axis=1)
    has = np.isfinite(best)
    match = np.argmax(s <= best[:, None] + TIE_TOLERANCE, axis=1)
    rest = s.copy()
    rows = np.arange(nq)
    for o in range(-(w // 2), w // 2 + 1):
        j = match + o
        inside = (j >= 0) & (j < nd)
        rest[rows[inside], j[inside]] = np.inf
    second = rest.min(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(second == 0.0, 1.0, best / second)
    match = np.where(has, match, -1).astype(np.int64)
    return match, np.where(has, best, np.nan), np.where(has, ratio, np.nan)


def seqslam(matrix: np.ndarray, *, kind: MatrixKind | str = MatrixKind.DIFFERENCE,
            contrast_window: int = CONTRAST_WINDOW, ds: int = DS, velocities: Sequence[float] = VELOCITIES,
            ratio_window: int = RATIO_WINDOW) -> SeqSLAMResult:
    """SeqSLAM's best database image and uniqueness ratio for every query (the module doc's steps 1–6).

    Args:
        matrix: ``(n_queries, n_database)`` differences or similarities, both axes in route order
            (run ``check_sequence`` on the dataset value first).
        kind: ``"difference"`` (lower is better) or ``"similarity"`` (D = 1 − S).
        contrast_window: R of the contrast enhancement (OpenSeqSLAM: 10).
        ds: the trajectory spans ds + 1 query frames centred on the query (OpenSeqSLAM: 10).
        velocities: database images per query frame (OpenSeqSLAM: 0.8 to 1.2 in steps of 0.1).
        ratio_window: W of the uniqueness ratio (OpenSeqSLAM: 10).

    Returns:
        The matches, their scores, ratios and velocities, and the whole score matrix.

    Raises:
        VPRInputError: an unknown ``kind``; ``ds``, ``contrast_window`` or ``ratio_window`` odd or
            < 2; a velocity below 0.5 or not finite; a matrix that is not 2-D or holds NaN/inf;
            fewer than ds + 1 queries or too few database images (module doc).
    """
    offsets = trajectory_offsets(ds, velocities)
    r = _even_window(contrast_window, "contrast_window")
    _even_window(ratio_window, "ratio_window")
    k = _kind(kind)
    d = _matrix(matrix, f"the {k.value} matrix")
    _check_sizes(d.shape[0], d.shape[1], ds, offsets, ratio_window)
    scores, vel, _ = _trajectories(*_enhance(d, k, r), ds, offsets)
    match, score, ratio = uniqueness(scores, ratio_window)
    v = np.asarray(velocities, dtype=np.float64).reshape(-1)
    rows = np.arange(len(match))
    velocity = np.where(match >= 0, v[vel[rows, np.maximum(match, 0)]], np.nan)
    return SeqSLAMResult(match=match, score=score, ratio=ratio, velocity=velocity, scores=scores)


def sequence_similarity(similarity: np.ndarray, *, contrast_window: int = CONTRAST_WINDOW, ds: int = DS,
                        velocities: Sequence[float] = VELOCITIES) -> np.ndarray:
    """Mean similarity along each (query, database image) pair's best SeqSLAM trajectory.

    The trajectory is the one attaining S[q, j] on the contrast-enhanced differences D = 1 − S
    (module doc, steps 2–4); the value is the mean of the raw similarities along it, on the
    scale of single-image similarities.

    Args:
        similarity: ``(n_queries, n_database)`` similarities, both axes in route order.
        contrast_window, ds, velocities: as for ``seqslam``.

    Returns:
        ``(n_queries, n_database)`` float64, ``-inf`` where image j has no trajectory and on
        the rows of the ds/2 queries at either end.

    Raises:
        VPRInputError: a bad parameter or matrix (see ``seqslam``).
    """
    s, r, offsets = _sequence_inputs(similarity, "the similarity matrix", contrast_window, ds, velocities)
    _, _, sums = _trajectories(*_enhance(s, MatrixKind.SIMILARITY, r), ds, offsets, values=s)
    out = sums / (ds + 1)
    out[np.isnan(out)] = -np.inf
    return out


def sequence_place_scores(similarity: np.ndarray, db_places: np.ndarray, n_places: int, *,
                          contrast_window: int = CONTRAST_WINDOW, ds: int = DS,
                          velocities: Sequence[float] = VELOCITIES) -> tuple[np.ndarray, np.ndarray]:
    """Sequence-aggregated raw_p: per place, the best ``sequence_similarity`` of its images.

    Per-place thresholds θ_p apply to it as to single-image raw_p (``retrieval.ranking_scores``).

    Args:
        similarity: ``(n_queries, n_database)`` similarities, both axes in route order.
        db_places: ``(n_database,)`` place of each database image (``>= 0``).
        n_places: number of place ids.
        contrast_window, ds, velocities: as for ``seqslam``.

    Returns:
        raw: ``(n_queries, n_places)``, ``-inf`` where a place has no image with a trajectory
            (every place of the ds/2 queries at either end).
        best: ``(n_queries, n_places)`` the image behind raw (``retrieval.place_scores``), ``-1``
            where raw is ``-inf``.

    Raises:
        VPRInputError: a bad parameter or matrix; labels that do not match the database columns.
    """
    labels = np.asarray(db_places)
    if labels.ndim != 1 or (len(labels) and (labels.min() < 0 or labels.max() >= n_places)):
        raise VPRInputError(f"db_places: give the place (0 to {n_places - 1}) of every database image; an image "
                            "between places has none: leave its column out of the similarity matrix")
    seq = sequence_similarity(similarity, contrast_window=contrast_window, ds=ds, velocities=velocities)
    return place_scores(seq, labels, n_places)
