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

**Cost.** Everything is shifted adds over blocks of query rows that stay in the CPU's cache (no
loop over queries): both steps run their blocks on ``settings.default_workers()`` threads, each
writing its own rows and keeping its buffers from block to block. All in float64, each sum
added in the order of the definition, so that a plain loop over queries, starts and velocities
gets the same numbers bit for bit: the enhancement is 2(R + 1) shifted passes (two passes over
each window, so that a flat window's std is 0 to rounding; running sums would round
differently); the trajectories are ds + 1 adds per velocity less the prefixes velocities share
(32 for OpenSeqSLAM's five instead of 55), each trajectory folded into S as soon as it is summed
(no matrix per velocity). Choices are made without branches — ``np.minimum`` for S, a select on
the bits for ``sequence_similarity``'s values — since a masked copy on a mask as mixed as "this
velocity is better" costs about fifteen adds. ``seqslam`` finds each query's best and second best in
the same blocks and sums each velocity's trajectory again at the match alone for its velocity.
On Nordland 64×32, winter queries against summer (3,576 × 3,576, pixels, D = 2048), on 2 cores,
``seqslam`` takes 0.2 s: 0.9× the similarity matrix it reads (``retrieval.similarity``, a
float32 GEMM of 0.22 s on OpenBLAS's Haswell kernel, which ``OPENBLAS_CORETYPE=Haswell``
chooses) and 1.8–2.1× it on the SkylakeX kernel OpenBLAS picks by itself (0.11 s);
``sequence_similarity`` 0.29 s (1.4× and 2.7×; the benchmark's "sequence place scores" add
``retrieval.place_scores`` to it). Measured by
``python benchmarks/bench_acceptance.py --data /work/shared/datasets --only nordland``, once as
is and once under ``env -u OPENBLAS_CORETYPE``.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from vpr_explorer.data.layouts import RetrievalDataset
from vpr_explorer.errors import VPRInputError, finite_number
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
#: Bytes of one array of a block of query rows (the enhancement's padded differences, the trajectories' costs
#: with their ds-row halo): near a CPU's L2 cache, yet big enough that a numpy call holds the GIL for a small
#: part of its time (on Nordland, two threads on blocks a quarter this size ran 1.3× one thread, not 1.75×).
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
        t = finite_number(threshold, "threshold")
        with np.errstate(invalid="ignore"):
            return self.ratio <= t  # NaN (unmatched) compares False


# --------------------------------------------------------------------------- checks


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


def sequence_fault(dataset: RetrievalDataset, reader: str = "SeqSLAM") -> str | None:
    """``None`` when ``dataset``'s database and queries are each one traversal in route order, else why not.

    Args:
        dataset: the dataset value the similarity matrix comes from.
        reader: what reads the sequences, as the reason names it (``"SeqSLAM"``, or the acceptance bench's
            sequence rules).

    The database is not one route in order when ``ordered`` is false (a database-queries or
    manifest layout, several database traversals); either side fails when it comes from several
    traversals or is not in frame order.
    """
    name = f"{dataset.name!r} ({dataset.layout.value})"
    if not dataset.ordered:
        return (f"dataset {name} is not one ordered route and has no database route in order, and {reader} reads "
                "runs of consecutive images along one: use aligned traversals with one database traversal, a "
                "traversal-positions layout with one, or VPR-Bench, or a single-image method")
    for side, traversal, frame in (("database", dataset.database_traversal, dataset.database_frame),
                                   ("queries", dataset.query_traversal, dataset.query_frame)):
        n = len(np.unique(traversal))
        if n > 1:
            return (f"the {side} of dataset {name} come from {n} traversals, and {reader} reads one traversal in "
                    f"order on each side: choose one {'database' if side == 'database' else 'query'} traversal")
        if frame is not None and np.any(np.diff(frame) <= 0):
            return f"the {side} of dataset {name} are not in frame order, and {reader} reads each side in route order"
    return None


def check_sequence(dataset: RetrievalDataset) -> None:
    """Refuse a dataset value whose order along the route means nothing to a sequence method.

    Raises:
        VPRInputError: ``sequence_fault``'s reason, naming the dataset.
    """
    fault = sequence_fault(dataset)
    if fault is not None:
        raise VPRInputError(fault)


# --------------------------------------------------------------------------- steps


def _rows_per_block(width: int, halo: int) -> int:
    return max(1, _BLOCK_BYTES // (8 * width) - halo)


def _each_block(starts: range, work: Callable[[int, dict], None]) -> None:
    """``work(start, scratch)`` for every start, on ``settings.default_workers()`` threads.

    Blocks are handed out in order to whichever thread is free; ``scratch`` is the thread's
    own dict of buffers, kept from one block to the next (a block never has more rows than the
    first, so buffers sized on a thread's first block fit every later one).
    """
    n = max(1, min(default_workers(), len(starts)))
    todo = iter(starts)
    lock = threading.Lock()

    def worker() -> None:
        scratch: dict = {}
        while True:
            with lock:
                start = next(todo, None)
            if start is None:
                return
            work(start, scratch)

    if n == 1:
        worker()
        return
    with ThreadPoolExecutor(max_workers=n) as pool:
        for future in [pool.submit(worker) for _ in range(n)]:
            future.result()


def _buffer(scratch: dict, name: str, shape: tuple[int, int], dtype: type = np.float64,
            fill: float | None = None) -> np.ndarray:
    """The ``shape`` corner of the thread's buffer ``name``, made (and filled) on first use."""
    buf = scratch.get(name)
    if buf is None:
        buf = scratch[name] = np.empty(shape, dtype) if fill is None else np.full(shape, fill, dtype)
    return buf[:shape[0], :shape[1]]


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
    windows = (lo, hi, count, count - 1.0, edges)
    out = np.empty((nq, nd), dtype=np.float64)
    rows = _rows_per_block(nd + r, 0)
    lows: list[float] = []
    _each_block(range(0, nq, rows), lambda r0, scratch: lows.append(
        _enhance_block(m[r0:r0 + rows], kind, r, windows, out[r0:r0 + rows], scratch)))
    return out, float(np.min(lows))  # NaN if any block's is, as the whole matrix's minimum


def _enhance_block(block: np.ndarray, kind: MatrixKind, r: int, windows: tuple, out: np.ndarray,
                   scratch: dict) -> float:
    """``_enhance`` of a block of query rows, written into ``out`` (that block's rows of the result); its minimum."""
    lo, hi, count, count_less_one, edges = windows
    b, nd = block.shape
    h = r // 2
    padded = _buffer(scratch, "padded", (b, nd + r), fill=0.0)  # zeros beyond either end add nothing
    mean, squares, dev, centred = (_buffer(scratch, name, (b, nd)) for name in ("mean", "squares", "dev", "centred"))
    d = padded[:, h:h + nd]
    if kind is MatrixKind.SIMILARITY:
        np.subtract(1.0, block, out=d, dtype=np.float64)  # widened first, then 1 − S in float64
    else:
        d[...] = block
    np.add(padded[:, 0:nd], padded[:, 1:1 + nd], out=mean)
    for o in range(2, r + 1):
        mean += padded[:, o:o + nd]
    np.divide(mean, count, out=mean)
    # squares of the deviations, added in window order from the first (0 + x is x)
    np.subtract(padded[:, 0:nd], mean, out=dev)
    np.multiply(dev, dev, out=squares)
    for o in range(1, r + 1):
        if o == h:  # the centre's deviation is E's numerator: kept
            np.subtract(d, mean, out=centred)
            np.multiply(centred, centred, out=dev)
        else:
            np.subtract(padded[:, o:o + nd], mean, out=dev)
            np.multiply(dev, dev, out=dev)
        squares += dev
    for c in edges:  # the zeros beyond the end are not in the window: recount those columns
        w = d[:, lo[c]:hi[c] + 1] - mean[:, c:c + 1]
        squares[:, c] = np.einsum("ij,ij->i", w, w)
    std = np.sqrt(np.divide(squares, count_less_one, out=squares), out=squares)
    # a flat window has std ≤ FLAT_STD·(1 + |mean|) ≤ FLAT_STD·(1 + max |mean|): test each entry unless
    # the block's smallest std is above that (a NaN from overflowing values takes the test too)
    bound = FLAT_STD * (1.0 + max(abs(float(mean.max())), abs(float(mean.min()))))
    if not float(std.min()) > bound:
        flat = std <= FLAT_STD * (1.0 + np.abs(mean))
        std[flat] = 1.0
        np.divide(centred, std, out=out)
        out[flat] = 0.0
    else:
        np.divide(centred, std, out=out)
    return float(out.min())


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


def _walk_paths(sources: tuple[np.ndarray, ...], b: int, ns: int, ds: int, offsets: np.ndarray,
                take: Callable[[], tuple[np.ndarray, ...]],
                leaf: Callable[[int, tuple[np.ndarray, ...]], None]) -> None:
    """Σ_k src[k + c, s + off[i, k]] for every source, centre row c < ``b`` and start s < ``ns``, added in k order.

    Calls ``leaf(i, sums)`` once per distinct trajectory, ``i`` the first velocity with those
    offsets and ``sums`` one ``(b, ns)`` array per source, handed over to ``leaf``. Trajectories
    sharing their first offsets share those partial sums (0.8 and 0.9 share six, 1.0 and 1.1
    ten): 32 shifted adds for OpenSeqSLAM's five velocities instead of 55. Where the
    trajectories part, each branch but the last adds into a fresh array from ``take``, the last
    into its parent's; branches go in order of their first velocity, so OpenSeqSLAM's five reach
    ``leaf`` in list order.
    """
    moves = offsets.tolist()

    def shifted(k: int, o: int) -> tuple[np.ndarray, ...]:
        return tuple(src[k:k + b, o:o + ns] for src in sources)

    def walk(acc: tuple[np.ndarray, ...], owned: bool, k: int, group: list[int]) -> None:
        while k <= ds:
            branches: dict[int, list[int]] = {}
            for i in group:
                branches.setdefault(moves[i][k], []).append(i)
            parts = list(branches.items())
            for n, (o, sub) in enumerate(parts):
                last = n == len(parts) - 1
                child = acc if last and owned else take()
                for c, a, s in zip(child, acc, shifted(k, o)):
                    np.add(a, s, out=c, dtype=np.float64)  # float32 values are widened, then added
                if not last:
                    walk(child, True, k + 1, sub)
            acc, owned, k, group = child, True, k + 1, parts[-1][1]
        leaf(group[0], acc)

    walk(shifted(0, 0), False, 1, list(range(len(offsets))))


@dataclass(frozen=True, eq=False)
class _Trajectories:
    """What ``_trajectories`` was asked for, ``(n_queries, n_database)`` unless said; ``None`` if not asked."""

    scores: np.ndarray | None      # S, inf where no trajectory
    velocity: np.ndarray | None    # index of the first velocity attaining S, -1 where S is inf
    mean: np.ndarray | None        # mean of the values along that trajectory, -inf where S is inf
    match: np.ndarray | None       # (n_queries,) ``uniqueness`` of S's rows
    score: np.ndarray | None
    ratio: np.ndarray | None


def _trajectories(enhanced: np.ndarray, low: float, ds: int, offsets: np.ndarray, *, scores: bool = True,
                  velocity: bool = False, values: np.ndarray | None = None,
                  ratio_window: int | None = None) -> _Trajectories:
    """Sequence scores S of E = ``enhanced`` − ``low`` (step 4), and what else is asked for, block by block.

    ``velocity``: the index of the first velocity attaining S; ``values``: their mean along that
    trajectory; ``ratio_window``: ``uniqueness`` of S's rows (needs ``scores``). Blocks of centre
    queries run on threads, each writing its own rows.
    """
    nq, nd = enhanced.shape
    h = ds // 2
    n_centres = nq - ds
    rows = _rows_per_block(nd + int(offsets.max()) + 1, ds)
    index = np.int8 if len(offsets) < 128 else np.int64
    out = {
        "scores": np.empty((nq, nd)) if scores else None,
        "velocity": np.empty((nq, nd), dtype=index) if velocity else None,
        "mean": np.empty((nq, nd)) if values is not None else None,
    }
    for name, a in out.items():
        if a is not None:  # the queries at either end
            a[:h] = a[nq - h:] = _BLANK[name]
    unique = None
    if ratio_window is not None:
        unique = (np.full(nq, -1, dtype=np.int64), np.full(nq, np.nan), np.full(nq, np.nan))
    order: list[int] = []
    _walk_paths((), 0, 0, ds, offsets, tuple, lambda i, _: order.append(i))
    # with the trajectories in list order, the first velocity attaining S is the last one strictly
    # below all before it; in any other order the index decides ties, and is kept
    track = index if velocity or (values is not None and order != sorted(order)) else None
    _each_block(range(0, n_centres, rows), lambda c0, scratch: _trajectory_block(
        enhanced, low, values, ds, offsets, c0, min(n_centres, c0 + rows), out, unique, ratio_window, track,
        scratch))
    return _Trajectories(out["scores"], out["velocity"], out["mean"], *(unique or (None, None, None)))


#: What ``_trajectories`` writes where image j has no trajectory.
_BLANK = {"scores": np.inf, "velocity": -1, "mean": -np.inf}


def _trajectory_block(enhanced: np.ndarray, low: float, values: np.ndarray | None, ds: int, offsets: np.ndarray,
                      c0: int, c1: int, out: dict, unique: tuple | None, ratio_window: int | None,
                      track: type | None, scratch: dict) -> None:
    """``_trajectories`` for the centre queries ``c0 + ds/2 … c1 − 1 + ds/2``, into ``out``'s rows of them."""
    nd = enhanced.shape[1]
    h = ds // 2
    b = c1 - c0
    ns = nd - h  # start s is reported as image s + ds/2; starts past n_db - ds/2 run out (velocities ≥ 0.5)
    rows = slice(c0 + h, c1 + h)
    for name, a in out.items():
        if a is not None:  # images j < ds/2 have no trajectory
            a[rows, :h] = _BLANK[name]
    if ns > 0:
        # the trajectory of centre c + h runs over rows c … c + ds; past the database it costs ∞
        width = nd + int(offsets.max()) + 1
        e = _buffer(scratch, "e", (b + ds, width), fill=np.inf)
        np.subtract(enhanced[c0:c1 + ds], low, out=e[:, :nd])
        sources = (e,)
        if values is not None:
            x = _buffer(scratch, "x", (b + ds, width), values.dtype, fill=0)
            x[:, :nd] = values[c0:c1 + ds]
            sources = (e, x)
        _fold_block(sources, b, ns, ds, offsets, track, scratch,
                    {name: None if a is None else a[rows, h:h + ns] for name, a in out.items()})
    if unique is not None:
        match, score, ratio = unique
        match[rows], score[rows], ratio[rows] = _best_and_ratio(out["scores"][rows], ratio_window)


def _fold_block(sources: tuple[np.ndarray, ...], b: int, ns: int, ds: int, offsets: np.ndarray,
                track: type | None, scratch: dict, out: dict) -> None:
    """Every trajectory's sums of one block, folded into S (the minimum over velocities) as each is done.

    ``out`` holds the block's ``(b, ns)`` windows of the outputs. The values' sums (``sources[1]``)
    follow the first velocity attaining S: a trajectory replaces the best so far where its S is
    lower, or, with ``track`` (the velocity index's dtype), equal and from an earlier velocity.
    """
    shape = (b, ns)
    pool: list[tuple[np.ndarray, ...]] = scratch.setdefault("pool", [])

    def take() -> tuple[np.ndarray, ...]:
        bases = pool.pop() if pool else tuple(np.empty(shape) for _ in sources)
        return tuple(a[:b, :ns] for a in bases)

    def give(acc: tuple[np.ndarray, ...]) -> None:
        pool.append(tuple(a.base for a in acc))

    vel = None if track is None else _buffer(scratch, "vel", shape, track)
    state: dict = {}

    def leaf(i: int, acc: tuple[np.ndarray, ...]) -> None:
        if "best" not in state:
            state["best"], state["last"] = acc, i
            if vel is not None:
                vel[...] = i
            return
        best = state["best"]
        if vel is not None or len(acc) > 1:
            better = np.less(acc[0], best[0], out=_buffer(scratch, "better", shape, bool))
            if vel is not None:
                if i < state["last"]:  # a later velocity is in: an exact tie goes to the earlier
                    tie = np.equal(acc[0], best[0], out=_buffer(scratch, "tie", shape, bool))
                    tie &= np.greater(vel, i, out=_buffer(scratch, "later", shape, bool))
                    better |= tie
                state["last"] = max(state["last"], i)
                step = np.subtract(vel, i, out=_buffer(scratch, "step", shape, track))
                step *= better
                np.subtract(vel, step, out=vel)  # i where better
            # best ← acc where better, on the bits (exact, without branches): the values' sums, and S
            # itself where a tie may go to the trajectory folded later
            mask = np.negative(better, out=_buffer(scratch, "mask", shape, np.int64), dtype=np.int64)
            diff = _buffer(scratch, "diff", shape, np.int64)
            for n in range(0 if vel is not None else 1, len(acc)):
                kept, new = best[n].view(np.int64), acc[n].view(np.int64)
                np.bitwise_xor(kept, new, out=diff)
                diff &= mask
                kept ^= diff
        if vel is None:  # on a tie np.minimum returns its second argument: the earlier trajectory's bits
            np.minimum(acc[0], best[0], out=best[0])
        give(acc)

    _walk_paths(sources, b, ns, ds, offsets, take, leaf)
    best = state["best"]
    if out["scores"] is not None:
        out["scores"][...] = best[0]
    if out["velocity"] is not None or out["mean"] is not None:
        none = np.isfinite(best[0], out=_buffer(scratch, "better", shape, bool))
        np.logical_not(none, out=none)
        if out["velocity"] is not None:
            out["velocity"][...] = vel
            np.copyto(out["velocity"], -1, where=none)
        if out["mean"] is not None:
            np.divide(best[1], ds + 1, out=out["mean"])
            np.copyto(out["mean"], -np.inf, where=none)
    give(best)


def _best_and_ratio(s: np.ndarray, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``uniqueness`` of the rows of ``s``, which it marks and restores (the window's entries are set to ∞ for
    the second best and put back)."""
    nq, nd = s.shape
    best = s.min(axis=1)
    has = np.isfinite(best)
    match = np.argmax(s <= best[:, None] + TIE_TOLERANCE, axis=1)
    rows = np.arange(nq)[:, None]
    # the window's columns, clipped to the matrix: a clipped column repeats one inside the window
    cols = np.clip(match[:, None] + np.arange(-(w // 2), w // 2 + 1), 0, nd - 1)
    kept = s[rows, cols]
    s[rows, cols] = np.inf
    second = s.min(axis=1)
    s[rows, cols] = kept
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(second == 0.0, 1.0, best / second)
    match = np.where(has, match, -1).astype(np.int64)
    return match, np.where(has, best, np.nan), np.where(has, ratio, np.nan)


def _velocity_at(enhanced: np.ndarray, low: float, ds: int, offsets: np.ndarray, match: np.ndarray,
                 score: np.ndarray) -> np.ndarray:
    """Index of the first velocity whose trajectory to ``match`` sums to ``score`` (-1 where unmatched).

    Each trajectory is summed again at the match alone, with the additions of ``_walk_paths`` in
    the same order, so it equals the S it attains bit for bit.
    """
    nq, nd = enhanced.shape
    h = ds // 2
    first = np.full(nq, -1, dtype=np.int64)
    q = np.flatnonzero(match >= 0)
    rows = q[:, None] - h + np.arange(ds + 1)[None, :]
    for i in range(len(offsets)):
        cols = (match[q] - h)[:, None] + offsets[i][None, :]
        inside = (cols < nd).all(axis=1)
        terms = enhanced[rows, np.minimum(cols, nd - 1)] - low
        total = terms[:, 0].copy()
        for k in range(1, ds + 1):
            total += terms[:, k]
        total[~inside] = np.inf
        hit = (total == score[q]) & (first[q] < 0)
        first[q[hit]] = i
    return first


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
    t = _trajectories(*_enhance(d, MatrixKind.DIFFERENCE, r), ds, offsets, velocity=True)
    return t.scores, t.velocity


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
    return _best_and_ratio(s.copy(), w)


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
    enhanced, low = _enhance(d, k, r)
    t = _trajectories(enhanced, low, ds, offsets, ratio_window=ratio_window)
    vel = _velocity_at(enhanced, low, ds, offsets, t.match, t.score)
    v = np.asarray(velocities, dtype=np.float64).reshape(-1)
    velocity = np.where(t.match >= 0, v[np.maximum(vel, 0)], np.nan)
    return SeqSLAMResult(match=t.match, score=t.score, ratio=t.ratio, velocity=velocity, scores=t.scores)


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
    return _trajectories(*_enhance(s, MatrixKind.SIMILARITY, r), ds, offsets, scores=False, values=s).mean


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
