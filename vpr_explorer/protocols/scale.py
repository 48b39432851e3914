"""The paper protocol at Nordland scale: one blocked pass over all image pairs (issue 6).

``fast_paper_protocol`` returns the numbers of ``evaluation.paper_protocol`` — same seeded
splits, the same float32 similarities, the same thresholds (to float rounding), ranks, tie
rules and answers — without an N×N matrix and without a pass per split. At Nordland g3s3's
110,000 images the straightforward protocol does, per split, an N×D² gram and a 9,197 × N
similarity; this module does one pass over the image pairs for all splits.

Algorithm
---------
A split holds exactly one image of every place out (the query) and trains on the rest.
``scale_splits`` runs the steps below as 1 (full-set sums; 4, the automatic θ, beside them
in a second thread), 2, 1 and 3 (per split), 6 (error bounds), then 5 and 6 together; the
functions doing each step are named at its end.

1. **Negative statistics by downdating** (DESIGN.md §2). From the full-set sums T = Σⱼ dⱼ,
   T_p, C = Σⱼ dⱼdⱼᵀ and aᵢ = Σ_{j∉p(i)} (dᵢ·dⱼ − c)² (from dᵢᵀCdᵢ, float64, once; c is the
   mean score, a float32 value), a training image i of place p in split r (queries Q_r,
   p's held-out image h) has

       n⁻ᵢ μᵢ             = dᵢ·(T − T_p) − dᵢ·Σ_{q∈Q_r} d_q + dᵢ·d_h
       n⁻ᵢ E[(s − c)²]ᵢ   = aᵢ − V_{i,r},    V_{i,r} = Σ_{q∈Q_r, p(q)≠p} (dᵢ·d_q − c)²
       σᵢ²                = E[(s − c)²]ᵢ − (μᵢ − c)²

   so no split forms a D×D gram: dᵢ·Σ_q d_q for all splits is one (N×D)·(D×R) product,
   dᵢᵀCdᵢ is dᵢᵀWdᵢ with W block upper triangular (``stats.triangular_blocks``: float64
   GEMMs, (1 + 1/8)·N·D² flops instead of 2·N·D²), and V comes out of the pass (2). μ,
   hence the simple θ, is exact to float64 rounding; σ carries the float32 rounding of the
   scores in V (taken about c, so descriptors whose scores all sit near 0.8 lose no more
   than centred ones), which moves a weighted θ_p by ~1e-11 (synthetic) to ~2e-9 (Nordland
   pixels). Step 6 keeps that from changing any
   outcome. Places whose training images are byte-identical get one θ, as in the
   reference (same inputs, same operations: their margins tie exactly).
   ``_full_sums``, ``_split_mu``, ``_sigma``; twins: ``_content_classes``, ``_twins``.
2. **One blocked pass** over the block pairs I ≤ J of a place-major layout (``Layout``).
   S = X_I X_Jᵀ in float32. Its scores may differ from the reference's in the last bits
   (the BLAS kernel, block shape and threads change the summation order): every tie and
   answer is therefore decided with ``retrieval.TIE_TOLERANCE``, which such differences
   never cross, so the outcomes are the reference's. Each block pair is cut into panels of
   whole places of block I (``PANEL_ROWS`` rows, every slot of each place; on a diagonal
   block, panels ``_DIAGONAL_SPLIT`` times shorter, each against the block's places from its
   own on, so that the block's GEMMs cover little more than its triangle): a panel is one
   GEMM in one thread, read after it slab by slab (``_SLAB_ROWS`` rows of one slot, which
   stay in cache) for everything below; panels run side by side in ``threads`` threads
   (BLAS in one thread each) and are merged in task order, so the sums and the table are
   the same for any number of threads. Each panel gives, for its rows and, by symmetry,
   block J's rows:

   * V (above): ((S − c)∘(S − c)) @ M, same-place pairs zeroed, with M the (N × R) query
     indicator: for the panel's rows, float32 products over chunks of ``_W_CHUNK`` columns
     (one nonzero term per place in the chunk); for block J's, each slab row that is a
     query of split r added to split r's float32 sum (a sparse (R × rows) indicator, about
     R/m rows per split: 1/m of the dense product's flops, ``_PassState.slab_queries``),
     one term per place of the panel; both summed in float64 across panels;
   * the **top-2 table**: per (image, place) the best and second-best score and the slots
     reaching them. In split r, raw_p of a query is p's best score unless p's held-out
     image is that best, then the second (on a tie the second equals the best). A query is
     held out of its own place, so its best correct score b_q is split-independent. Where
     two of a place's images score within the tie tolerance (t2 ≥ t1 − tol or
     t3 ≥ t2 − tol: near-duplicate images, rare), the entry keeps all its slot scores
     (``_NearSlots``), from which raw_p and its image (the lowest slot within the
     tolerance) follow exactly in every split;
   * for the image-level baseline, the places where two or more images reach b_q, with
     the slots that do (at most max(ks) per image: more, and the rank is beyond every K).

   The table is kept only where it can matter: for images that are a query in some split,
   and above the row's floor. Every exact θ_p is a convex combination of its place's μᵢ,
   so all lie in [min μ, max μ] (known before the pass), and no place below
   b − (max μ − min μ) (or min μ when the own place can be dropped, −∞ when b is) reaches
   any rank or answer. Entries are (row, place, t1, a1, t2, a2), 18 bytes each, in RAM up
   to ``table_memory`` bytes, then in a temporary file.
   ``_blocked_pass``, ``_panel_task``, ``_floor``, ``_Entries``, ``_Records``.
3. **Per split thresholds** from the downdated moments through the library's own
   ``NegativeStats`` and ``place_thresholds``. ``_split_thresholds``.
4. **The automatic global θ** is the reference's own: one tile sample for the whole run
   (``thresholds.pooled_pair_sample``: ~2.4·10⁶ scores in dense tiles over every image in a
   place, drawn once), of which each split keeps the pairs of its training images and reads
   median and MAD off the sorted scores (~0.02 s per split at 110k × 1,280, where a tile
   sample per split took ~0.4 CPU s); the reference protocol makes the same calls, so the
   θ are equal bit for bit. ``scale_splits``.
5. **Per split scoring**, one row block of queries at a time, reads each query's table
   entries at or above its cutoff — the lowest score that can still reach a rank or an
   answer under any method of the split, with every weighted θ anywhere within its error
   bound (6) — and runs every method on those candidates only (the cutoff is a bound, not
   a heuristic). The global θs follow from b, the top raw score and the place baseline.
   ``_score_block`` (``_candidates``, ``_candidate_cutoff``, ``_score_place_level``,
   ``_score_image_level``), ``_assemble``.
6. **Near ties.** Each weighted θ_p gets an error bound: first order in the σ errors,
   scaled by the largest error of V seen when a seeded sample of images is recomputed
   exactly, times ``_SAFETY`` (observed errors stay under 3% of the bound), doubled for
   the second-order terms. Where a comparison that a change within those bounds could
   overturn decides a query's outcome (a keep test, a margin against the own place's or
   the top answer's), the places involved get σ, hence θ, recomputed in float64 —
   exactly the closed form — and that row block of that split is scored again, until no
   such comparison is left. ``_error_scale``, ``_uncertainty``, ``_near_tie_places``,
   ``_make_exact``, ``_score_splits``.

Ranks, ties and answers follow ``retrieval``: scores within ``TIE_TOLERANCE`` tie, ties
count against the query, answers are the lowest index within the tolerance of the best
(place id; image index within a place; image index across places at the image level),
cross-condition queries see other traversals only.
Image-level ranks beyond max(ks) are reported as max(ks) + 1 (Recall@K never needs more).
"""

from __future__ import annotations

import dataclasses
import os
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy import sparse

from vpr_explorer.errors import VPRInputError
from vpr_explorer.protocols.evaluation import (
    KS,
    Evaluation,
    Progress,
    Protocol,
    Split,
    SplitScores,
    _check_common,
    _members,
    _summarise,
    draw_splits,
    oracle_global_threshold,
    paper_protocol,
    pooled_truth,
    split_pr,
)
from vpr_explorer.method.retrieval import METHODS_BY_KEY, TIE_TOLERANCE, Outcome
from vpr_explorer.protocols.shared_scores import SharedScores
from vpr_explorer.method.stats import (
    SIGMA_FLOOR,
    NegativeStats,
    mixture_moments,
    one_blas_thread,
    run_in_lanes,
    triangular_blocks,
    triangular_quadratic_forms,
)
from vpr_explorer.method.thresholds import (
    ThresholdMethod,
    adaptive_k,
    place_thresholds,
    pooled_pair_sample,
)

#: Default rows per block of the pass: a 4,096 × 4,096 float32 block is 64 MiB.
BLOCK_ROWS = 4096
#: Rows per panel of the pass (whole places): one panel of a block pair, 1,536 × 4,096
#: float32 scores (24 MiB), is one GEMM in one thread (at about the rate of the whole block's
#: GEMM in two; 768 rows lose 4%, 192 rows 15%) and its bookkeeping.
PANEL_ROWS = 1536
#: Rows of a panel read at a time after its GEMM (of one slot, so 64 places): 64 × 4,096
#: float32 scores (1 MiB) and their squares stay in a core's cache while they give both
#: downdate products and both maxima.
_SLAB_ROWS = 64
#: Panels on a diagonal block are this many times shorter: each computes the block's places
#: from its own on (``_panel_task``), so 8 panels of a 4,096-row block compute 9/16 of it
#: (3 would compute 2/3; the triangle alone is 1/2).
_DIAGONAL_SPLIT = 3
#: ``pr=True`` hands runs × places² up to this to ``paper_protocol`` (the per-place PR curves
#: score every query against every place at each of ~200 k: about 60 s at this size).
PR_FAMILY_CELLS = 10_000_000
#: Bytes of top-2 table entries kept in RAM; beyond, entries go to a temporary file.
TABLE_MEMORY = 2 * 1024**3
#: Rows of M per float32 product of the second-moment downdate's dense side (a panel's own
#: rows; block J's rows take the sparse one, ``_PassState.slab_queries``): each float32 sum
#: has one nonzero term per place among them (about 170 for Nordland's places of 12 images);
#: the chunks are summed in float64.
_W_CHUNK = 2048
#: Descriptor rows read (and converted) at a time outside the pass.
_CHUNK = 8192
#: Float64 sums of the full-set sums' first pass that row blocks are dealt to in turn (``_full_sums``).
_SUM_LANES = 4
#: Rows per float64 product of the full-set sums' quadratic forms (their products stay in cache).
_QUAD_ROWS = 1024
#: One top-2 table entry: layout row, place index, best score and its slot, second best and its slot.
_ENTRY = (("row", np.int32), ("place", np.int32), ("t1", np.float32), ("a1", np.uint8), ("t2", np.float32),
          ("a2", np.uint8), ("near", np.uint8))
#: Ties (``retrieval.TIE_TOLERANCE``): scores within it of each other tie.
_TIE = TIE_TOLERANCE
#: Most rows a block may have: flat indices into a block's scores are int32 (46,000² < 2³¹).
_MAX_BLOCK_ROWS = 46_000


# --------------------------------------------------------------------------- layout


@dataclass(frozen=True, eq=False)
class Layout:
    """Labelled images reordered place by place, each place padded to ``slots`` rows, in blocks.

    Inside a block of G places rows run slot-major: row = first_row + slot·G + (place − first),
    so a block's similarity viewed as ``(rows, slots, G)`` or ``(slots, G, cols)`` reduces over
    a place's images along a middle axis. Padding rows are zero descriptors, masked to −inf.

    Attributes:
        places: ``(P,)`` place ids that have images, ascending; "place index" c means places[c].
        slots: the largest place size m; slot k of a place is its k-th image by index.
        block_start: ``(n_blocks + 1,)`` first place index of each block.
        image_of_row: ``(n_rows,)`` image of each layout row, ``-1`` for padding.
        row_of_image: ``(n_images,)`` layout row of each image, ``-1`` for unlabelled frames.
        sizes: ``(P,)`` images per place.
        place_of_row, slot_of_row: ``(n_rows,)`` place index and slot of every row.
    """

    places: np.ndarray
    slots: int
    block_start: np.ndarray
    image_of_row: np.ndarray
    row_of_image: np.ndarray
    sizes: np.ndarray
    place_of_row: np.ndarray
    slot_of_row: np.ndarray

    @property
    def n_blocks(self) -> int:
        return len(self.block_start) - 1

    @property
    def n_rows(self) -> int:
        return len(self.image_of_row)

    @property
    def full_rows(self) -> int:
        """Rows of every block but the last (which may be shorter)."""
        return self.slots * int(self.block_start[1] - self.block_start[0])

    def rows(self, b: int) -> slice:
        """The layout rows of block b."""
        return slice(int(self.block_start[b]) * self.slots, int(self.block_start[b + 1]) * self.slots)

    def place_range(self, b: int) -> slice:
        """The place indices of block b."""
        return slice(int(self.block_start[b]), int(self.block_start[b + 1]))

    def row_of(self, c: np.ndarray, slot: np.ndarray) -> np.ndarray:
        """Layout row of (place index, slot)."""
        return _row_of(self.block_start, self.slots, c, slot)


def _row_of(block_start: np.ndarray, slots: int, c: np.ndarray, slot: np.ndarray) -> np.ndarray:
    blk = np.searchsorted(block_start, c, side="right") - 1
    first = block_start[blk]
    return first * slots + slot * (block_start[blk + 1] - first) + (c - first)


def make_layout(image_place: np.ndarray, n_places: int, block_rows: int = BLOCK_ROWS) -> Layout:
    """The place-major, slot-padded, blocked layout of the labelled images.

    Blocks hold whole places and about ``block_rows`` rows; all but the last hold the same
    number of places (so a row's block is row // full_rows).
    """
    if isinstance(block_rows, bool) or not isinstance(block_rows, (int, np.integer)) or not 1 <= block_rows <= 40_000:
        raise VPRInputError(f"block={block_rows!r}: rows per block must be a whole number from 1 to 40,000 (e.g. 4096)")
    order, starts, sizes = _members(image_place, n_places)
    places = np.flatnonzero(sizes > 0)
    psize = sizes[places]
    m = int(psize.max())
    n_p = len(places)
    wanted = max(1, -(-n_p * m // int(block_rows)))  # blocks of about block_rows rows
    per_block = -(-n_p // wanted)  # places per block; the last block may hold fewer
    block_start = np.r_[np.arange(0, n_p, per_block), n_p].astype(np.int64)
    n_blocks = len(block_start) - 1
    if m * per_block > _MAX_BLOCK_ROWS:
        raise VPRInputError(f"places of {m} images: a block would exceed {_MAX_BLOCK_ROWS:,} rows; lower block=")
    place_idx = np.repeat(np.arange(n_p), psize)
    slot = np.arange(len(order)) - np.repeat(starts[places], psize)
    rows = _row_of(block_start, m, place_idx, slot)
    image_of_row = np.full(n_p * m, -1, dtype=np.int64)
    image_of_row[rows] = order
    row_of_image = np.full(len(image_place), -1, dtype=np.int64)
    row_of_image[order] = rows
    width = np.diff(block_start)
    place_of_row = np.concatenate([np.tile(np.arange(block_start[b], block_start[b + 1]), m) for b in range(n_blocks)])
    slot_of_row = np.concatenate([np.repeat(np.arange(m), width[b]) for b in range(n_blocks)])
    return Layout(places, m, block_start, image_of_row, row_of_image, psize, place_of_row, slot_of_row)


# --------------------------------------------------------------------------- top-2 entries


def _top2_rows(vals: np.ndarray) -> dict[str, np.ndarray]:
    """Best and second-best of each row of ``vals`` ``(n, m)``, the first slots reaching them,
    and whether two slots could tie.

    a1 is the first slot of the best value; with the best twice, t2 = t1 and a2 is the next
    such slot (argmax returns the first maximum). ``near`` marks rows where the best or, with
    the best held out, the second has another slot within the tie tolerance (t2 ≥ t1 − tie
    or t3 ≥ t2 − tie): only there can the image behind raw_p (the lowest slot within the
    tolerance) differ from a1/a2, and those rows keep all their slot scores (``_NearSlots``).
    """
    at = np.arange(len(vals))
    a1 = np.argmax(vals, axis=1)
    rest = vals.copy()
    rest[at, a1] = -np.inf
    a2 = np.argmax(rest, axis=1)
    t1, t2 = vals[at, a1], rest[at, a2]
    rest[at, a2] = -np.inf
    t3 = rest.max(axis=1)
    with np.errstate(invalid="ignore"):
        near = ((t2 >= t1 - _TIE) & np.isfinite(t2)) | ((t3 >= t2 - _TIE) & np.isfinite(t3))
    return {"t1": t1, "a1": a1.astype(np.uint8), "t2": t2, "a2": a2.astype(np.uint8), "near": near.astype(np.uint8)}


class _NearSlots:
    """Every slot score of the table entries marked ``near`` (rare: near-duplicate images).

    Keyed by (layout row, place index); ``lookup`` returns the ``(n, m)`` scores of the
    given keys, all of which must have been added.
    """

    def __init__(self, n_places: int):
        self.n_places = n_places
        self.keys: list[np.ndarray] = []
        self.vals: list[np.ndarray] = []
        self._sorted: tuple[np.ndarray, np.ndarray] | None = None

    def add(self, rows: np.ndarray, places: np.ndarray, vals: np.ndarray) -> None:
        if len(rows):
            self.keys.append(rows.astype(np.int64) * self.n_places + places)
            self.vals.append(np.array(vals, dtype=np.float32))
            self._sorted = None

    def lookup(self, rows: np.ndarray, places: np.ndarray) -> np.ndarray:
        if self._sorted is None:
            keys = np.concatenate(self.keys) if self.keys else np.empty(0, np.int64)
            vals = np.concatenate(self.vals) if self.vals else np.empty((0, 0), np.float32)
            order = np.argsort(keys, kind="stable")
            self._sorted = (keys[order], vals[order])
        keys, vals = self._sorted
        want = rows.astype(np.int64) * self.n_places + places
        pos = np.minimum(np.searchsorted(keys, want), max(len(keys) - 1, 0))
        if len(want) and (len(keys) == 0 or not np.array_equal(keys[pos], want)):
            raise RuntimeError("internal error: a near-tie entry without its slot scores")  # pragma: no cover
        return vals[pos]


class _Entries:
    """Top-2 table entries (row, place, t1, a1, t2, a2), filed by the block of their row.

    In RAM up to ``limit`` bytes, then appended to a temporary file that is deleted on
    ``close`` (or by the OS if the process dies). ``get`` returns a row block's entries
    sorted by (row, place) with a CSR row pointer.
    """

    def __init__(self, lay: Layout, limit: int, spill_dir: str | os.PathLike | None):
        self.lay, self.limit, self.spill_dir = lay, limit, spill_dir
        self.in_ram = 0
        self.file = None
        self.offset = 0
        self.chunks: dict[int, list] = {}

    def put(self, row_block: int, parts: dict[str, np.ndarray]) -> None:
        n = len(parts["row"])
        if n == 0:
            return
        arrays = {k: np.ascontiguousarray(parts[k], dtype=t) for k, t in _ENTRY}
        size = sum(a.nbytes for a in arrays.values())
        if self.in_ram + size <= self.limit:
            self.in_ram += size
            self.chunks.setdefault(row_block, []).append(arrays)
            return
        if self.file is None:
            self.file = tempfile.TemporaryFile(prefix="vpr_top2_", dir=self.spill_dir)
        self.file.seek(self.offset)
        for k, _ in _ENTRY:
            self.file.write(arrays[k].tobytes())
        self.chunks.setdefault(row_block, []).append((self.offset, n))
        self.offset += size

    def get(self, row_block: int) -> dict[str, np.ndarray]:
        parts = []
        for chunk in self.chunks.get(row_block, []):
            if isinstance(chunk, dict):
                parts.append(chunk)
                continue
            offset, n = chunk
            self.file.seek(offset)
            parts.append({k: np.fromfile(self.file, dtype=t, count=n) for k, t in _ENTRY})
        out = {k: np.concatenate([p[k] for p in parts]) if parts else np.empty(0, t) for k, t in _ENTRY}
        order = np.lexsort((out["place"], out["row"]))
        out = {k: v[order] for k, v in out.items()}
        rows = self.lay.rows(row_block)
        out["ptr"] = np.r_[0, np.cumsum(np.bincount(out["row"], minlength=rows.stop - rows.start))]
        return out

    def close(self) -> None:
        if self.file is not None:
            self.file.close()


class _Records:
    """Per layout row, up to ``cap`` (place, slots ≥ b) records for the image-level count.

    A record is kept where two or more images of a wrong place reach the row's own best
    score b; the packed slot mask says which. Such a place adds at least one wrong image
    above b in any split, so ``cap`` records already put the rank beyond ``cap``: ``n``
    counts every such place of a row, kept or not.
    """

    def __init__(self, n_rows: int, slots: int, cap: int):
        self.cap = cap
        self.n = np.zeros(n_rows, dtype=np.int64)
        self.place = np.full((n_rows, cap), -1, dtype=np.int64)
        self.bits = np.zeros((n_rows, cap, (slots + 7) // 8), dtype=np.uint8)

    def add(self, rows: np.ndarray, places: np.ndarray, ge: np.ndarray) -> None:
        """``rows``, ``places`` ``(n,)``; ``ge`` ``(n, slots)`` bool, which slots reach b."""
        if len(rows) == 0:
            return
        order = np.argsort(rows, kind="stable")
        rows, places, ge = rows[order], places[order], ge[order]
        first = np.r_[True, rows[1:] != rows[:-1]]
        run_start = np.maximum.accumulate(np.where(first, np.arange(len(rows)), 0))
        pos = self.n[rows] + (np.arange(len(rows)) - run_start)
        keep = pos < self.cap
        self.place[rows[keep], pos[keep]] = places[keep]
        self.bits[rows[keep], pos[keep]] = np.packbits(ge[keep], axis=1, bitorder="little")
        np.add.at(self.n, rows, 1)


# --------------------------------------------------------------------------- exact full-set sums


@dataclass(frozen=True, eq=False)
class _FullSums:
    """Float64 sums over all labelled images, per layout row (zero on padding rows)."""

    dot_other: np.ndarray  # (n_rows,) dᵢ·(T − T_p(i)): Σ_{j∉p(i)} dᵢ·dⱼ
    dot_queries: np.ndarray  # (n_rows, R) dᵢ·Σ_{q∈Q_r} d_q
    gram: np.ndarray  # (P, m, m) within-place dᵢ·dⱼ (zero for padding slots)
    centre: float  # c: the mean score over all pairs of distinct labelled images, a float32 value
    a_centred: np.ndarray  # (n_rows,) aᵢ = Σ_{j∉p(i)} (dᵢ·dⱼ − c)²


def _layout_rows64(d: np.ndarray, lay: Layout, rows: slice, out: np.ndarray, x32: np.ndarray | None) -> np.ndarray:
    """``(len(rows), D)`` float64 descriptors of these layout rows in ``out``'s memory, zero rows
    for padding: converted from ``x32`` (``_as_layout32``, the same values when ``d`` holds
    float32 or float16) where given, gathered from ``d`` otherwise."""
    x = out[: rows.stop - rows.start]
    if x32 is not None:
        np.copyto(x, x32[rows])
        return x
    img = lay.image_of_row[rows]
    np.copyto(x, d[np.maximum(img, 0)])
    x[img < 0] = 0.0
    return x


def _full_sums(d: np.ndarray, lay: Layout, query_rows: np.ndarray, threads: int = 1,
               x32: np.ndarray | None = None) -> _FullSums:
    """T, T_p, C and the quadratic forms, once (O(N·D²) float64), from the original values (step 1).

    Two passes over the layout's row blocks, as pool tasks in ``threads`` threads with BLAS in
    one thread each. The first sums T, C (one syrk per block) and each split's Σ_q d_q into
    float64 lanes (block k on lane k mod ``_SUM_LANES``, in order: ``stats.run_in_lanes``) and
    forms the within-place grams; the second gives each row its dot products and quadratic
    form. So the sums are the same numbers for any thread count. ``x32``: the float32 layout
    rows (``_as_layout32``), read instead of gathering from ``d`` when ``d`` is float32 or float16.
    """
    n_rows, dim = lay.n_rows, d.shape[1]
    m, n_p, runs = lay.slots, len(lay.places), len(query_rows)
    if x32 is not None and np.dtype(d.dtype).itemsize > 4:
        x32 = None  # float64 descriptors: the sums take their own values, not float32 roundings
    widest = int(np.diff(lay.block_start).max()) * m
    buffers = threading.local()  # each thread's float64 rows and products, reused across its blocks

    def rows64(b: int) -> np.ndarray:
        if not hasattr(buffers, "x"):
            buffers.x, buffers.y = np.empty((widest, dim)), np.empty((min(_QUAD_ROWS, widest), dim))
            buffers.g = np.empty((dim, dim))
        return _layout_rows64(d, lay, lay.rows(b), buffers.x, x32)

    lanes = [(np.zeros(dim), np.zeros((dim, dim)), np.zeros((runs, dim)))
             for _ in range(min(_SUM_LANES, lay.n_blocks))]
    gram = np.zeros((n_p, m, m))

    def first(lane: int, b: int) -> None:
        rows, x = lay.rows(b), rows64(b)
        total, gram_all, queries = lanes[lane]
        total += x.sum(axis=0)
        gram_all += np.matmul(x.T, x, out=buffers.g)  # numpy hands Xᵀ X to syrk
        x3 = x.reshape(m, -1, dim).transpose(1, 0, 2)  # (G, m, D): each place's images
        gram[lay.place_range(b)] = x3 @ x3.transpose(0, 2, 1)
        # the block's queries of every split at once: its (rows × R) query indicator, transposed, times x
        r_of, local = np.nonzero((query_rows >= rows.start) & (query_rows < rows.stop))
        indicator = np.zeros((runs, rows.stop - rows.start))
        indicator[r_of, query_rows[r_of, local] - rows.start] = 1.0
        queries += indicator @ x

    dot_total, dot_place, sq = np.zeros(n_rows), np.zeros(n_rows), np.zeros(n_rows)
    dot_q = np.zeros((n_rows, runs))
    with ThreadPoolExecutor(max(1, threads)) as pool, one_blas_thread():
        run_in_lanes(pool, range(lay.n_blocks), len(lanes), first)
        total, gram_all, queries = lanes[0]
        for lane in lanes[1:]:  # in lane order
            for acc, part in zip(lanes[0], lane):
                acc += part
        cols, w = triangular_blocks(gram_all, np.float64)

        def second(b: int) -> None:
            rows, x = lay.rows(b), rows64(b)
            gb = gram[lay.place_range(b)]  # (G, m, m); row (k, g) of the block is gb[g, k]
            dot_total[rows] = x @ total
            dot_q[rows] = x @ queries.T
            dot_place[rows] = gb.sum(axis=2).T.reshape(-1)
            # float64 products: each xᵢᵀWxᵢ is off by at most γ_D·|xᵢ|ᵀ|W||xᵢ| ≤ 2γ_D·N for unit
            # rows, about 3·10⁻¹³·N at D = 1,280: far below the float32 rounding of V (step 6)
            quad = np.concatenate([triangular_quadratic_forms(x[lo : lo + _QUAD_ROWS], cols, w, buffers.y)
                                   for lo in range(0, len(x), _QUAD_ROWS)])
            sq[rows] = quad - (gb**2).sum(axis=2).T.reshape(-1)  # Σ_{j∉p} s²

        list(pool.map(second, range(lay.n_blocks)))
    # scores are taken relative to c in the pass: (s − c)² sums carry float32 rounding in
    # proportion to |s − c|, not |s| (descriptors with a shared component score 0.7 everywhere)
    n_lab = int(lay.sizes.sum())
    norms = np.einsum("pkk->", gram)
    centre = float(np.float32((total @ total - norms) / max(n_lab * (n_lab - 1), 1)))
    n_other = n_lab - lay.sizes[lay.place_of_row]
    dot_other = dot_total - dot_place
    a_centred = np.where(lay.image_of_row >= 0, sq - 2 * centre * dot_other + centre**2 * n_other, 0.0)
    return _FullSums(dot_other, dot_q, gram, centre, a_centred)


# --------------------------------------------------------------------------- the pass


@dataclass(frozen=True, eq=False)
class _PassResult:
    """What the pass leaves besides the top-2 table (which it files in ``_Entries``)."""

    v: np.ndarray  # (n_rows, R) Σ_{q∈Q_r, other place} (s_iq − c)²
    best_own: np.ndarray  # (n_rows,) b: best score in the own place, the image itself left out
    records: _Records
    near: _NearSlots


def _as_layout32(d: np.ndarray, lay: Layout, threads: int = 1) -> np.ndarray:
    """``(n_rows, D)`` float32 descriptors in layout order, zero rows for padding.

    Gathered ``_CHUNK`` rows at a time by ``threads`` threads (numpy's gather and conversion
    release the GIL; each chunk writes its own rows, so the result does not depend on them).
    """
    x = np.empty((lay.n_rows, d.shape[1]), dtype=np.float32)
    img = lay.image_of_row

    def chunk(lo: int) -> None:
        part = img[lo : lo + _CHUNK]
        x[lo : lo + len(part)] = d[np.maximum(part, 0)]
        x[lo + np.flatnonzero(part < 0)] = 0.0  # padding

    if threads > 1:
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(chunk, range(0, lay.n_rows, _CHUNK)))
    else:
        for lo in range(0, lay.n_rows, _CHUNK):
            chunk(lo)
    return x


def _round_down32(x: np.ndarray) -> np.ndarray:
    """The largest float32 values ≤ x (the scores are float32: compared with them, nothing is lost)."""
    x32 = x.astype(np.float32)
    return np.where(x32.astype(np.float64) > x, np.nextafter(x32, np.float32(-np.inf)), x32)


def _floor(best: np.ndarray, mu_range: tuple[float, float], is_query: np.ndarray) -> np.ndarray:
    """Per row: below it no place reaches a rank or an answer of this query, in any split
    and under any θs in [min μ, max μ] = ``mu_range`` (float32, rounded down).

    With b ≥ max μ ≥ θ_own the own place is kept in every split and a place must reach
    b − (max μ − min μ) − tie; otherwise the answer may be any kept place, and kept means
    raw ≥ θ ≥ min μ. Rows that are never a query get +∞.
    """
    lo, hi = mu_range
    b = best.astype(np.float64)
    with np.errstate(invalid="ignore"):
        f = np.where(b >= hi + 1e-9, b - (hi - lo), np.minimum(b - (hi - lo), lo)) - _TIE - 1e-9
    f = np.where(np.isfinite(b), f, -np.inf)
    return np.where(is_query, _round_down32(f), np.float32(np.inf))


def _side(s3: np.ndarray, t1: np.ndarray, floor: np.ndarray, *, axis: int) -> dict[str, np.ndarray]:
    """One side of a panel's top-2 table: the entries whose best score ``t1`` reaches the row's floor.

    ``s3`` is ``(rows, m, places)`` (axis=1: the panel's rows are the table's rows) or
    ``(m, places, cols)`` (axis=0: its columns are); ``t1`` its maximum over that axis.
    Returns the entries' local row and place, t1/a1/t2/a2 and their ``(n, m)`` slot scores.
    """
    # the few rows (columns) with any entry first: the full comparison then runs on those only
    if axis == 1:
        hit = np.flatnonzero(t1.max(axis=1) >= floor)
        r, c = np.nonzero(t1[hit] >= floor[hit, None])
        r = hit[r]
        vals = s3[r, :, c]
    else:
        hit = np.flatnonzero(t1.max(axis=0) >= floor)
        c, r = np.nonzero(t1[:, hit] >= floor[None, hit])
        r = hit[r]
        vals = s3[:, c, r].T
    return {"row": r, "place": c, **_top2_rows(vals), "vals": vals}


class _BlockProducts:
    """A panel of S = X_I X_Jᵀ, written into a float32 buffer: numpy (BLAS), or torch on ``device``.

    With a device the layout descriptors are copied there once (CPU tensors share numpy's
    memory) and each panel's product comes back to the CPU buffer. Its float32 scores may
    differ from numpy's in the last bits, like another BLAS kernel's: the tie tolerance
    (module doc, step 2) keeps every outcome the same.
    """

    def __init__(self, x: np.ndarray, device: object | None):
        self.x, self.device = x, device
        if device is not None:
            import torch

            from vpr_explorer.method.stats import torch_device

            self.device = torch_device(device)
            self.xt = torch.from_numpy(x).to(self.device)

    def __call__(self, rows: np.ndarray, cols: slice | np.ndarray, out: np.ndarray) -> None:
        if self.device is None:
            np.matmul(self.x[rows], self.x[cols].T, out=out)
            return
        import torch

        from vpr_explorer.method.stats import ieee_float32

        idx = torch.from_numpy(rows).to(self.device)
        cdx = cols if isinstance(cols, slice) else torch.from_numpy(cols).to(self.device)
        with ieee_float32():
            if self.device.type == "cpu":
                torch.matmul(self.xt[idx], self.xt[cdx].T, out=torch.from_numpy(out))
            else:
                torch.from_numpy(out).copy_(self.xt[idx] @ self.xt[cdx].T)


@dataclass(frozen=True)
class _Panel:
    """One task of the pass: the places ``g0:g1`` (within block ``bi``) against block ``bj``;
    on the diagonal (``bi == bj``), against the block's places from ``g0`` on."""

    bi: int
    bj: int
    g0: int
    g1: int


@dataclass(eq=False)
class _PanelResult:
    """A panel's share of the pass, merged by the main thread in task order (``_blocked_pass``)."""

    panel: _Panel
    rows: np.ndarray  # (n,) layout rows of the panel: slot-major over its places
    v_rows: np.ndarray  # (n, R) float64: the panel rows' share of V
    cols: slice | np.ndarray  # layout rows of ``v_cols``: block J's (off the diagonal), or the block's after the panel
    v_cols: np.ndarray | None  # (R, cols) float64: those rows' share of V, transposed
    best: np.ndarray | None  # (n,) b of the panel rows (diagonal panels)
    sides: list  # (table row block, side dict with layout rows/places, own place per entry or None)


class _PassState:
    """What the panels read (descriptors, indicator, floors) and each worker thread's buffers."""

    def __init__(self, lay: Layout, products: _BlockProducts, indicator: np.ndarray, pad: np.ndarray,
                 row_traversal: np.ndarray | None, centre: np.float32, floor: np.ndarray, panel_rows: int):
        self.lay, self.products, self.indicator, self.pad = lay, products, indicator, pad
        self.row_traversal, self.centre, self.floor = row_traversal, centre, floor
        widest = lay.slots * int(np.diff(lay.block_start).max())
        self.size = min(max(panel_rows, 1) + lay.slots, widest) * widest  # a panel: at most panel_rows + m rows
        self.slab = _SLAB_ROWS * widest
        self.local = threading.local()
        self.sparse_queries: dict[tuple[int, int], sparse.csr_array] = {}

    def slab_queries(self, row0: int, n: int) -> sparse.csr_array:
        """``(R, n)`` float32 CSR: the indicator of layout rows ``row0 … row0 + n − 1``, transposed.

        A slab's rows are a query in about R/m splits each, so ``slab_queries(…) @ q`` adds
        each such row of q once (a twelfth of the flops of the dense product at m = 12). Kept
        per slab: block I's panels are the same for every block J.
        """
        key = (row0, n)
        found = self.sparse_queries.get(key)
        if found is None:  # threads may build the same one: equal values, either is kept
            found = self.sparse_queries[key] = sparse.csr_array(self.indicator[row0 : row0 + n].T)
        return found

    def buffers(self) -> tuple[np.ndarray, np.ndarray]:
        buf = getattr(self.local, "buf", None)
        if buf is None:
            buf = self.local.buf = (np.empty(self.size, np.float32), np.empty(self.slab, np.float32))
        return buf


def _panel_task(st: _PassState, p: _Panel, mu_range: tuple[float, float], is_query: np.ndarray,
                wait: Callable[[], object] | None = None) -> _PanelResult:
    """Everything the splits need from one panel of S, in one thread (step 2).

    The panel holds every slot of the places ``g0:g1`` of block I, slot-major, so that both
    sides of the top-2 table reduce over a place's images inside it: its rows against the
    columns' places, and block J's rows (the columns) against its places. Off the diagonal
    the columns are block J; on it, the block's places from ``g0`` on (slot-major too): the
    pairs with earlier places came with those places' panels, by symmetry, so a diagonal
    block's GEMMs cover its triangle and the panels on it (the panel's own places with each
    other) only. After its GEMM the panel is read slot by slot, a slab of up to
    ``_SLAB_ROWS`` rows of one slot (1 MiB at 4,096 columns) at a time, which stays in cache
    while it gives its squares, both downdate products and both maxima.

    On the diagonal the columns' side is of places after the panel, whose floors come from
    their own (diagonal) panels: ``wait()`` returns once those are merged (``_blocked_pass``
    runs a diagonal block's panels last place first).
    """
    lay, m = st.lay, st.lay.slots
    ri, rj = lay.rows(p.bi), lay.rows(p.bj)
    gi = (ri.stop - ri.start) // m
    gp = p.g1 - p.g0
    rows = ri.start + (np.arange(m)[:, None] * gi + np.arange(p.g0, p.g1)[None, :]).ravel()
    diagonal = p.bi == p.bj
    if diagonal:  # the columns' places: the block's from g0 on (the panel's own first)
        gj, c0 = gi - p.g0, p.g0
        cols: slice | np.ndarray = ri.start + (np.arange(m)[:, None] * gi + np.arange(p.g0, gi)[None, :]).ravel()
    else:
        gj, c0, cols = (rj.stop - rj.start) // m, 0, rj
    n, nj, runs = len(rows), m * gj, st.indicator.shape[1]
    s_buf, q_buf = st.buffers()
    s = s_buf[: n * nj].reshape(n, nj)
    st.products(rows, cols, s)
    own = np.arange(gp) if diagonal else None  # the slab rows' place among the columns' places
    with_cols = not diagonal or gj > gp  # a columns' side: places outside the panel
    mj = st.indicator[cols]
    pad_j = st.pad[cols]
    trav_j = st.row_traversal[cols] if st.row_traversal is not None else None
    v_rows = np.zeros((n, runs))
    v_cols = np.zeros((runs, nj), dtype=np.float32) if with_cols else None  # transposed: rows of the slab's q added
    row_max = np.empty((n, gj), dtype=np.float32)
    col_max = np.full((gp, nj), -np.inf, dtype=np.float32) if with_cols else None
    best = np.empty(n, dtype=np.float32) if diagonal else None
    for k, h0 in ((k, h0) for k in range(m) for h0 in range(0, gp, _SLAB_ROWS)):
        h1 = min(h0 + _SLAB_ROWS, gp)
        sl, hl, hs = slice(k * gp + h0, k * gp + h1), slice(h0, h1), h1 - h0
        sk = s[sl]
        q = q_buf[: hs * nj].reshape(hs, nj)
        # second moments: squared scores against each split's queries of other places
        np.square(np.subtract(sk, st.centre, out=q), out=q)
        if diagonal:
            q.reshape(hs, m, gj)[np.arange(hs), :, own[hl]] = 0.0
        for w0 in range(0, nj, _W_CHUNK):
            v_rows[sl] += q[:, w0 : w0 + _W_CHUNK] @ mj[w0 : w0 + _W_CHUNK]
        if with_cols:  # the slab rows that are queries, as a sparse (R × rows) indicator: few of them per split
            np.add(v_cols, st.slab_queries(int(rows[sl.start]), hs) @ q, out=v_cols)
        # what a query may match: never padding; in cross-condition, not its own traversal
        pad_k = st.pad[rows[sl]]
        if pad_k.any():
            sk[pad_k] = -np.inf
        if pad_j.any():
            sk[:, pad_j] = -np.inf
        if trav_j is not None:
            np.putmask(sk, st.row_traversal[rows[sl]][:, None] == trav_j[None, :], -np.inf)
        sk3 = sk.reshape(hs, m, gj)
        if diagonal:  # b: the best of the own place's other images
            mine = sk3[np.arange(hs), :, own[hl]]
            mine[:, k] = -np.inf
            best[sl] = mine.max(axis=1)
        np.max(sk3, axis=1, out=row_max[sl])
        if with_cols:
            np.maximum(col_max[hl], sk, out=col_max[hl])
    floor = _floor(best, mu_range, is_query[rows]) if diagonal else st.floor[rows]
    side = _side(s.reshape(n, m, gj), row_max, floor, axis=1)
    r = side["row"]
    side["own"] = side["place"] == np.tile(own, m)[r] if diagonal else None
    side["row"], side["place"] = rows[r] - ri.start, lay.block_start[p.bj] + c0 + side["place"]
    sides = [(p.bi, side)]
    if with_cols:
        if diagonal:  # the columns of the panel's own places are its rows' side already
            if wait is not None:
                wait()
            col_floor = st.floor[cols]  # a copy (cols: an index array)
            col_floor.reshape(m, gj)[:, :gp] = np.inf
        else:
            col_floor = st.floor[cols]
        side = _side(s.reshape(m, gp, nj), col_max, col_floor, axis=0)
        if diagonal:
            side["row"] = cols[side["row"]] - rj.start
        side["own"], side["place"] = None, lay.block_start[p.bi] + p.g0 + side["place"]
        sides.append((p.bj, side))
        if diagonal:  # those columns' V, too, came with the rows
            after = (np.arange(nj) % gj) >= gp
            v_cols, cols = v_cols[:, after], cols[after]
    return _PanelResult(p, rows, v_rows, cols, None if v_cols is None else v_cols.astype(np.float64), best, sides)


def _panels(lay: Layout, bi: int, bj: int, panel_rows: int) -> list[_Panel]:
    """Block I's places cut into panels of about ``panel_rows`` rows (all slots of each place)."""
    gi = int(lay.block_start[bi + 1] - lay.block_start[bi])
    parts = max(1, -(-gi * lay.slots // panel_rows))
    edges = np.linspace(0, gi, parts + 1).astype(int)
    return [_Panel(bi, bj, int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def _blocked_pass(
    x: np.ndarray,
    lay: Layout,
    query_rows: np.ndarray,
    row_traversal: np.ndarray | None,
    entries: _Entries,
    cap: int,
    mu_range: tuple[float, float],
    centre: float,
    threads: int,
    progress: Callable[[int, str], None] | None,
    device: object | None = None,
    panel_rows: int | None = None,
) -> _PassResult:
    """Everything the splits need from the similarities, in one pass over block pairs I ≤ J (step 2).

    Each block pair is cut into panels of whole places of block I (``_panel_task``: the GEMM
    of the panel's rows and its bookkeeping, slab by slab in cache, in one thread);
    ``threads`` threads run panels side by side, BLAS in one thread each, and the main thread
    merges their results in task order, so the sums and the table do not depend on the number
    of threads. Diagonal blocks come first: they hold each image's own place, hence b and
    the row's floor, which the off-diagonal blocks need. A diagonal block's panels run last
    place first, and each waits, before the side of its columns (the block's later places),
    until the panel before it is merged: the floors of those columns are then known. BLAS
    runs in one thread whatever ``threads`` is: OpenBLAS's Haswell sgemm splits the sum of
    a (64 × 2,048) @ (2,048 × 50) product (the downdate's shape) between its threads, which
    would make V depend on their number. ``progress(pairs done, message)``
    after each pair. ``device``: a torch device for the panel products (``_BlockProducts``);
    the bookkeeping stays in numpy on the CPU.
    """
    n_rows, m, nb = lay.n_rows, lay.slots, lay.n_blocks
    panel_rows = PANEL_ROWS if panel_rows is None else panel_rows
    runs = query_rows.shape[0]
    indicator = np.zeros((n_rows, runs), dtype=np.float32)  # M: row i is a query of split r
    indicator[query_rows.T, np.arange(runs)[None, :]] = 1.0
    is_query = indicator.any(axis=1)
    v = np.zeros((n_rows, runs))
    best_own = np.full(n_rows, -np.inf, dtype=np.float32)
    floor = np.full(n_rows, np.inf, dtype=np.float32)
    records = _Records(n_rows, m, cap)
    near = _NearSlots(len(lay.places))
    st = _PassState(lay, _BlockProducts(x, device), indicator, lay.image_of_row < 0, row_traversal,
                    np.float32(centre), floor, panel_rows)
    pairs = [(i, i) for i in range(nb)] + [(i, j) for i in range(nb) for j in range(i + 1, nb)]
    left = {}  # block pair -> panels not merged yet
    done = [0]

    def merge(res: _PanelResult) -> None:
        p = res.panel
        v[res.rows] += res.v_rows
        if res.v_cols is not None:
            v[res.cols] += res.v_cols.T
        if res.best is not None:
            best_own[res.rows] = res.best
            floor[res.rows] = _floor(res.best, mu_range, is_query[res.rows])
        for row_block, side in res.sides:
            _store_side(entries, records, near, side, row_block, lay.rows(row_block).start, best_own)
        if p in merged:
            merged[p].set()
        left[(p.bi, p.bj)] -= 1
        if left[(p.bi, p.bj)] == 0:
            done[0] += 1
            if progress:
                progress(done[0], f"similarity block {done[0]}/{len(pairs)}")

    def run(phase: list[tuple[int, int]], pool: ThreadPoolExecutor | None) -> None:
        tasks = []
        for bi, bj in phase:
            if bi == bj:  # shorter panels (more of the triangle left out), last place first (``_panel_task``)
                ps = _panels(lay, bi, bj, max(1, panel_rows // _DIAGONAL_SPLIT))[::-1]
                merged.update((t, threading.Event()) for t in ps)
                waits.update((t, merged[before].wait) for before, t in zip(ps, ps[1:]))
            else:
                ps = _panels(lay, bi, bj, panel_rows)
            left[(bi, bj)] = len(ps)
            tasks += ps
        if pool is None:
            for t in tasks:
                merge(_panel_task(st, t, mu_range, is_query, waits.get(t)))
            return
        window: deque = deque()
        for t in tasks:  # a few tasks in flight ahead of the merge, merged in order
            window.append(pool.submit(_panel_task, st, t, mu_range, is_query, waits.get(t)))
            if len(window) > 2 * threads:
                merge(window.popleft().result())
        while window:
            merge(window.popleft().result())

    merged: dict[_Panel, threading.Event] = {}  # diagonal panels: set once merged
    waits: dict[_Panel, Callable[[], object]] = {}  # diagonal panels: the wait for the panel merged before
    if threads > 1:
        with ThreadPoolExecutor(threads) as pool, one_blas_thread():
            try:
                run(pairs[:nb], pool)  # the diagonal: b and the floors, which every other panel reads
            except BaseException:  # let waiting panels end, so that the pool can shut down
                for event in merged.values():
                    event.set()
                raise
            run(pairs[nb:], pool)
    else:  # BLAS in one thread here too: a multithreaded sgemm may split the sums (below)
        with one_blas_thread():
            run(pairs[:nb], None)
            run(pairs[nb:], None)
    return _PassResult(v, best_own, records, near)


def _store_side(entries: _Entries, records: _Records, near: _NearSlots, side: dict, row_block: int, row0: int,
                best: np.ndarray) -> None:
    """File one side's entries; record the wrong places whose second best already ties b.

    The side's ``row`` is local to ``row_block`` (which starts at layout row ``row0``), its
    ``place`` a place index; ``best`` is b of every layout row; ``own`` (on a diagonal
    panel) marks the entries of the row's own place.
    """
    r = side["row"]
    entries.put(row_block, side)
    b = best[row0 + r]
    tied = b.astype(np.float64) - _TIE
    sel = (side["t2"] >= tied) & np.isfinite(b)
    if side["own"] is not None:
        sel &= ~side["own"]
    if sel.any():
        records.add(row0 + r[sel], side["place"][sel], side["vals"][sel] >= tied[sel][:, None])
    amb = side["near"].astype(bool)
    if amb.any():
        near.add(row0 + r[amb], side["place"][amb], side["vals"][amb])


# --------------------------------------------------------------------------- per split


@dataclass(eq=False)
class _SplitData:
    """One split's statistics and thresholds; ``uncertainty`` bounds each weighted θ's error."""

    split: Split
    held: np.ndarray  # (P,) held-out slot of every place
    rows: np.ndarray  # (n_train,) layout rows of the training images, in the reference's order
    stats: NegativeStats
    v: np.ndarray  # (n_train,) the downdate V of each training image
    twins: np.ndarray  # (P,) the first place index with the same training images (``_twins``)
    thresholds: dict[str, np.ndarray | float]
    spread: np.ndarray  # (n_places,) s_p
    k_adaptive: np.ndarray  # (n_places,)
    uncertainty: np.ndarray | None = None  # (P,) bound on |θ_weighted error|; 0 where exact (step 6)


def _split_mu(r: int, train_rows: np.ndarray, lay: Layout, sums: _FullSums, held: np.ndarray):
    """μᵢ and n⁻ᵢ of split r's training rows: n⁻μ = d·(T − T_p) − d·Σ_q d_q + d·d_h (float64)."""
    cr, kr = lay.place_of_row[train_rows], lay.slot_of_row[train_rows]
    n_neg = len(train_rows) - (lay.sizes - 1)[cr]
    sum_neg = sums.dot_other[train_rows] - (sums.dot_queries[train_rows, r] - sums.gram[cr, kr, held[cr]])
    return sum_neg / n_neg, n_neg


@dataclass(frozen=True, eq=False)
class _Content:
    """The slots' content classes, and the places that can have a twin."""

    classes: np.ndarray  # (P, m) a class per slot: equal for byte-identical descriptors, -1 for padding
    shared: np.ndarray  # place indices, ascending, with a slot whose class another place has too


def _shared_places(classes: np.ndarray) -> np.ndarray:
    """Place indices with a slot whose content class appears in another place as well.

    Only they can have a twin: any other place trains, in every split, on an image that no
    other place holds.
    """
    n_p = classes.shape[0]
    place, _ = np.nonzero(classes >= 0)
    pairs = np.unique(classes[classes >= 0] * n_p + place)  # distinct (class, place), class-major
    cls = pairs // n_p
    in_many = np.bincount(cls)[cls] > 1
    return np.unique(pairs[in_many] % n_p)


def _content_classes(d: np.ndarray, lay: Layout) -> _Content:
    """A class per slot (``(P, m)``: equal for byte-identical descriptors, ``-1`` for padding),
    and the places that share a class with another place (``_shared_places``)."""
    real = np.flatnonzero(lay.image_of_row >= 0)
    img = lay.image_of_row[real]
    w = np.random.default_rng(0).standard_normal(d.shape[1])
    key = np.empty(len(real))
    for lo in range(0, len(real), _CHUNK):
        key[lo : lo + _CHUNK] = np.einsum("ij,j->i", np.asarray(d[img[lo : lo + _CHUNK]], dtype=np.float64), w)
    order = np.argsort(key, kind="stable")
    new = np.r_[True, key[order][1:] != key[order][:-1]]
    run = np.cumsum(new) - 1
    # equal keys: confirm byte equality with the run's first row
    first = order[np.flatnonzero(new)][run]
    clash = np.zeros(len(order), dtype=bool)
    shared = np.flatnonzero(np.bincount(run)[run] > 1)  # a key of one image needs no check
    for lo in range(0, len(shared), _CHUNK):
        at = shared[lo : lo + _CHUNK]
        a = np.ascontiguousarray(d[img[order[at]]])
        b = np.ascontiguousarray(d[img[first[at]]])
        clash[at] = np.any(a.view(np.uint8) != b.view(np.uint8), axis=1)
    sorted_cls = run.copy()
    fresh = int(run.max()) + 1
    for k in np.unique(run[clash]):  # a key shared by different descriptors (vanishingly rare)
        members = np.flatnonzero(run == k)
        rows = np.ascontiguousarray(d[img[order[members]]])
        _, sub = np.unique(rows.view(np.uint8).reshape(len(rows), -1), axis=0, return_inverse=True)
        sorted_cls[members] = fresh + sub.ravel()
        fresh += int(sub.max()) + 1
    cls = np.empty(len(real), dtype=np.int64)
    cls[order] = sorted_cls
    content = np.full((len(lay.places), lay.slots), -1, dtype=np.int64)
    content[lay.place_of_row[real], lay.slot_of_row[real]] = cls
    return _Content(content, _shared_places(content))


def _twins(content: _Content, held: np.ndarray) -> np.ndarray:
    """``(P,)`` for each place, the first place whose training images are the same, in order.

    Only the places that share a content class with another place are compared (the others
    are their own first); none at all on routes without repeated frames.

    Args:
        content: the slots' content classes (``_content_classes``).
        held: ``(P,)`` held-out slot of each place in this split.
    """
    twins = np.arange(len(held))
    shared = content.shared
    if len(shared) > 1:
        classes = content.classes[shared]
        k = np.arange(classes.shape[1] - 1)[None, :]
        seq = np.where(k < held[shared, None], classes[:, :-1], classes[:, 1:])  # the training slots, in order
        _, first, inverse = np.unique(seq, axis=0, return_index=True, return_inverse=True)
        twins[shared] = shared[first[inverse.ravel()]]
    return twins


def _sigma(sums: _FullSums, rows: np.ndarray, v: np.ndarray, mu: np.ndarray, n_neg: np.ndarray) -> np.ndarray:
    """σᵢ of training rows from the downdate: E[(s − c)²] = (aᵢ − Vᵢ)/n⁻ᵢ, σ² = E[(s − c)²] − (μᵢ − c)²."""
    second = (sums.a_centred[rows] - v) / n_neg
    return np.sqrt(np.clip(second - (mu - sums.centre) ** 2, 0.0, None))


def _place_thresholds(stats: NegativeStats, method: ThresholdMethod, lay: Layout, twins: np.ndarray) -> np.ndarray:
    """``place_thresholds``, with places whose training images are identical given one θ.

    The straightforward computation gives such places the very same θ (same inputs, same
    operations), so their margins tie exactly and the tie goes to the lower place id; the
    float32 rounding in the downdated σ would break that tie.
    """
    theta = place_thresholds(stats, method)
    theta[lay.places] = theta[lay.places[twins]]
    return theta


def _split_thresholds(r: int, sp: Split, lay: Layout, sums: _FullSums, pas: _PassResult, held: np.ndarray,
                      n_places: int, auto: float, user_theta: float | None, content: _Content,
                      mu_n: tuple[np.ndarray, np.ndarray]) -> _SplitData:
    """Split r's statistics and thresholds from the downdated moments (module doc, steps 1 and 3);
    ``mu_n``: ``_split_mu`` of its training rows."""
    rows = lay.row_of_image[sp.train]
    mu, n_neg = mu_n
    v = pas.v[rows, r]
    labels = lay.places[lay.place_of_row[rows]].astype(np.int64)
    stats = NegativeStats(mu=mu, sigma=_sigma(sums, rows, v, mu, n_neg), n_neg=n_neg.astype(np.int64),
                          labels=labels, n_places=n_places)
    twins = _twins(content, held)
    th: dict[str, np.ndarray | float] = {
        ThresholdMethod.SIMPLE.value: _place_thresholds(stats, ThresholdMethod.SIMPLE, lay, twins),
        ThresholdMethod.WEIGHTED.value: _place_thresholds(stats, ThresholdMethod.WEIGHTED, lay, twins),
        "auto": auto,
    }
    if user_theta is not None:
        th["user"] = float(user_theta)
    # for k_adaptive, the positive means Σ_{i≠j∈train_p} dᵢ·dⱼ / (n(n−1)) from the within-place
    # grams (the reference's stats.positive_means, to rounding)
    gram, ar = sums.gram, np.arange(len(lay.places))
    g_hh = gram[ar, held, held]
    pair_sum = gram.sum(axis=(1, 2)) - 2 * gram[ar, held].sum(axis=1) + g_hh
    diag = np.einsum("pkk->p", gram) - g_hh
    n = (lay.sizes - 1).astype(np.float64)
    pos_mean = np.full(n_places, np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        pos_mean[lay.places] = np.where(n > 1, (pair_sum - diag) / (n * (n - 1)), np.nan)
    neg_mean, spread = mixture_moments(stats)
    return _SplitData(sp, held, rows, stats, v, twins, th, spread, adaptive_k(pos_mean, neg_mean, spread))


# --------------------------------------------------------------------------- near ties


#: The per-place error bound of the weighted θ is this many times the largest error seen
#: in a sample of exactly recomputed images (errors are sums of many roundings: their
#: extremes over a whole run exceed a sample's by a small factor, not by 20).
_SAFETY = 20.0
#: Training images recomputed exactly to measure that error (spread over up to 8 splits).
_SAMPLE = 256


def _exact_v(d: np.ndarray, lay: Layout, sums: _FullSums, split: Split, rows: np.ndarray) -> np.ndarray:
    """V of training rows in float64 from the original descriptors: Σ_{q∈Q_r, other place} (dᵢ·d_q − c)²."""
    q = np.asarray(d[split.queries], dtype=np.float64)  # ordered by place index
    out = np.empty(len(rows))
    step = 512
    for lo in range(0, len(rows), step):
        rr = rows[lo : lo + step]
        s = np.asarray(d[lay.image_of_row[rr]], dtype=np.float64) @ q.T - sums.centre
        s[np.arange(len(rr)), lay.place_of_row[rr]] = 0.0  # the own place's query is no negative
        out[lo : lo + step] = np.einsum("ij,ij->i", s, s)
    return out


def _error_scale(d: np.ndarray, lay: Layout, sums: _FullSums, data: list[_SplitData], seed: int) -> float:
    """κ: the largest |V − V_exact| / √V_exact over a seeded sample of training images."""
    rng = np.random.default_rng(seed)
    picks = rng.choice(len(data), size=min(len(data), 8), replace=False)
    kappa = 0.0
    for r in picks:
        sd = data[r]
        idx = rng.choice(len(sd.rows), size=min(len(sd.rows), _SAMPLE // len(picks)), replace=False)
        exact = _exact_v(d, lay, sums, sd.split, sd.rows[idx])
        kappa = max(kappa, float(np.max(np.abs(sd.v[idx] - exact) / np.sqrt(np.maximum(exact, 1e-300)))))
    return kappa


def _uncertainty(sd: _SplitData, lay: Layout, kappa: float) -> np.ndarray:
    """``(P,)`` error bound of each weighted θ (step 6), from the V error scale κ.

    θ = Σᵢ wᵢμᵢ/Σw with wᵢ ∝ 1/σᵢ², so |δθ| ≤ Σᵢ (wᵢ/Σw)·|μᵢ − θ|·|δσᵢ²|/σᵢ², and
    |δσᵢ²| = |δVᵢ|/n⁻ᵢ ≤ safety·κ·√Vᵢ/n⁻ᵢ.
    """
    st = sd.stats
    theta = sd.thresholds["weighted"]
    var = np.maximum(st.sigma, SIGMA_FLOOR) ** 2
    w = st.weights / var
    wsum = np.bincount(st.labels, weights=w, minlength=st.n_places)
    rel = _SAFETY * kappa * np.sqrt(np.maximum(sd.v, 0.0)) / st.n_neg / var
    with np.errstate(invalid="ignore", divide="ignore"):
        bound = np.bincount(st.labels, weights=w * np.abs(st.mu - theta[st.labels]) * rel, minlength=st.n_places) / wsum
    return np.nan_to_num(bound[lay.places], nan=0.0) * 2 + 1e-15  # ×2: second-order terms


def _make_exact(sd: _SplitData, places: np.ndarray, d: np.ndarray, lay: Layout, sums: _FullSums) -> bool:
    """Recompute σ (hence the weighted θ) of these places' training images in float64.

    Twins go together (a twin's θ is its first twin's). Returns whether any place was not
    exact yet.
    """
    places = np.setdiff1d(places, np.flatnonzero(sd.uncertainty == 0))
    if len(places) == 0:
        return False
    group = np.flatnonzero(np.isin(sd.twins, sd.twins[places]))
    sel = np.flatnonzero(np.isin(lay.place_of_row[sd.rows], group))
    rows, st = sd.rows[sel], sd.stats
    sd.v = sd.v.copy()
    sd.v[sel] = _exact_v(d, lay, sums, sd.split, rows)
    sigma = st.sigma.copy()
    sigma[sel] = _sigma(sums, rows, sd.v[sel], st.mu[sel], st.n_neg[sel])
    sd.stats = NegativeStats(mu=st.mu, sigma=sigma, n_neg=st.n_neg, labels=st.labels, n_places=st.n_places)
    sd.thresholds = {**sd.thresholds,
                     ThresholdMethod.WEIGHTED.value: _place_thresholds(sd.stats, ThresholdMethod.WEIGHTED, lay, sd.twins)}
    sd.uncertainty = sd.uncertainty.copy()
    sd.uncertainty[group] = 0.0
    return True


def _first_argmax(score: np.ndarray, seg: np.ndarray, seg_of: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per segment: the largest score and the first element within the tie tolerance of it
    (−1 where all are −inf)."""
    top = np.maximum.reduceat(score, seg)
    idx = np.where(score >= top[seg_of] - _TIE, np.arange(len(score)), len(score))
    first = np.minimum.reduceat(idx, seg)
    first[~np.isfinite(top)] = -1
    return top, first


def _candidate_cutoff(b: np.ndarray, own: np.ndarray, th_s: np.ndarray, th_w: np.ndarray,
                      unc_w: np.ndarray) -> np.ndarray:
    """Per query, the lowest raw score that can reach any method's rank or answer (step 5).

    Args:
        b: ``(n,)`` each query's best correct score (``-inf``: none); own: its place index.
        th_s, th_w: ``(P,)`` simple and weighted θ per place index; unc_w: the weighted θ's
            error bounds (step 6).
    Returns:
        ``(n,)`` float32, rounded down. Places at or above b − tie count for the baselines and
        the global θs. Under a per-place θ, with the own place kept (b ≥ θ_own) a place counts
        if its margin ties or beats the own one, raw ≥ θ_p + (b − θ_own) − tie; with it
        dropped, any kept place may be the answer, raw ≥ θ_p. Both are at least
        min θ + max(b − θ_own, 0) − tie. The
        weighted θs enter at their bounds' lowest θ_p and highest θ_own, so that a place
        below the cutoff matters under no θ within the bounds, and the near-tie check sees
        every place that might.
    """
    cut = b
    for low, high in ((th_s, th_s), (th_w - unc_w, th_w + unc_w)):
        cut = np.minimum(cut, float(np.min(low)) + np.maximum(b - high[own], 0.0))
    return _round_down32(cut - _TIE - 1e-12)


#: The methods scored per block, in the reference's order (the global θs follow in ``_assemble``).
_ORDER = ("image-baseline", "place-baseline", "margin-simple", "margin-weighted", "raw-simple", "raw-weighted")


@dataclass(frozen=True, eq=False)
class _Candidates:
    """One split's queries of a row block and their candidate places, query by query (step 5).

    Per query ``(G,)``: ``own`` its place index (= its position among the split's queries),
    ``row`` its layout row, ``b`` its best correct score (``-inf``: none).
    Per candidate ``(n,)``, grouped by query and in place order within one (``start``: each
    query's first): ``query`` (position in the block), ``place`` (place index), ``t1``/``t2``
    the place's best and second-best score over all its images, ``held`` its held-out slot,
    ``hit`` whether its best image is the held-out one, ``raw`` raw_p in this split (``t2`` on
    a hit, else ``t1``) and ``image`` the lowest-index training image within the tie tolerance
    of it. ``near`` indexes the candidates whose place has images within the tolerance of
    each other, ``slots`` their ``(len(near), m)`` slot scores (held-out and padding ``-inf``)
    and ``near_images`` the training image of each of those slots.
    """

    own: np.ndarray
    row: np.ndarray
    b: np.ndarray
    query: np.ndarray
    start: np.ndarray
    place: np.ndarray
    t1: np.ndarray
    t2: np.ndarray
    held: np.ndarray
    hit: np.ndarray
    raw: np.ndarray
    image: np.ndarray
    near: np.ndarray
    slots: np.ndarray
    near_images: np.ndarray

    @property
    def is_own(self) -> np.ndarray:
        return self.place == self.own[self.query]


def _candidates(ent: dict[str, np.ndarray], blk: int, sd: _SplitData, lay: Layout, pas: _PassResult,
                th_s: np.ndarray, th_w: np.ndarray) -> _Candidates:
    """The table entries of the block's queries at or above their cutoffs, with raw_p of the split."""
    own = np.arange(lay.block_start[blk], lay.block_start[blk + 1])  # the block's places = its queries
    qrow = lay.row_of(own, sd.held[own])
    b = pas.best_own[qrow].astype(np.float64)
    cut32 = _candidate_cutoff(b, own, th_s, th_w, sd.uncertainty)
    local = qrow - lay.rows(blk).start
    start, count = ent["ptr"][local], ent["ptr"][local + 1] - ent["ptr"][local]
    qi = np.repeat(np.arange(len(own)), count)
    idx = np.arange(len(qi)) - np.repeat(np.cumsum(count) - count, count) + np.repeat(start, count)
    keep = ent["t1"][idx] >= cut32[qi]
    idx, qi = idx[keep], qi[keep]
    seg = np.flatnonzero(np.r_[True, qi[1:] != qi[:-1]])
    if len(seg) != len(own):  # pragma: no cover - the own place is always an entry above the cutoff
        raise RuntimeError("internal error: a query without its own place among the candidates")
    pc, t1, t2 = ent["place"][idx].astype(np.int64), ent["t1"][idx], ent["t2"][idx]
    a1, a2 = ent["a1"][idx], ent["a2"][idx]
    held = sd.held[pc]
    hit = a1 == held  # the best image of that place is the one held out: its second counts
    raw = np.where(hit, t2, t1).astype(np.float64)
    slot = np.where(hit, a2, a1).astype(np.int64)
    near = np.flatnonzero(ent["near"][idx])
    slots = np.empty((0, lay.slots), dtype=np.float32)
    near_images = np.empty((0, lay.slots), dtype=np.int64)
    if len(near):  # several images of the place within the tolerance: raw_p and its image from every slot
        slots = pas.near.lookup(qrow[qi[near]], pc[near]).copy()
        slots[np.arange(len(near)), held[near]] = -np.inf
        top = slots.max(axis=1)
        raw[near] = top
        slot[near] = np.argmax(slots >= top[:, None].astype(np.float64) - _TIE, axis=1)
        m = lay.slots
        near_images = lay.image_of_row[lay.row_of(np.repeat(pc[near], m), np.tile(np.arange(m), len(near)))]
        near_images = near_images.reshape(len(near), m)
    image = lay.image_of_row[lay.row_of(pc, slot)]
    return _Candidates(own, qrow, b, qi, seg, pc, t1, t2, held, hit, raw, image, near, slots, near_images)


def _score_place_level(c: _Candidates, th_s: np.ndarray, th_w: np.ndarray, places: np.ndarray,
                       out: dict[str, dict[str, np.ndarray]]) -> np.ndarray:
    """The place-level methods of ``_ORDER`` into ``out``; returns each query's top raw score."""
    qi, seg, pc, raw, own = c.query, c.start, c.place, c.raw, c.own
    is_own, bq = c.is_own, c.b[qi]

    def put(key, rank, first):
        o = out[key]
        o["rank"][own] = rank
        o["place"][own] = np.where(first >= 0, places[pc[np.maximum(first, 0)]], -1)
        o["image"][own] = np.where(first >= 0, c.image[np.maximum(first, 0)], -1)

    tied = bq - _TIE
    rank_base = np.where(np.isfinite(c.b), 1.0 + np.add.reduceat((raw >= tied) & ~is_own, seg), np.inf)
    top, first = _first_argmax(raw, seg, qi)
    put("place-baseline", rank_base, first)
    for name, th in (("simple", th_s), ("weighted", th_w)):
        thc = th[pc]
        kept = raw >= thc
        kept_own = c.b >= th[own]
        score = np.where(kept, raw, -np.inf)
        _, f = _first_argmax(score, seg, qi)
        put(f"raw-{name}", np.where(kept_own, 1.0 + np.add.reduceat((score >= tied) & ~is_own, seg), np.inf), f)
        margin = np.where(kept, raw - thc, -np.inf)
        _, f = _first_argmax(margin, seg, qi)
        m_own = (c.b - th[own])[qi]
        put(f"margin-{name}",
            np.where(kept_own, 1.0 + np.add.reduceat((margin >= m_own - _TIE) & ~is_own, seg), np.inf), f)
    return top


def _near_tie_places(c: _Candidates, th_w: np.ndarray, uncertainty: np.ndarray) -> np.ndarray:
    """Places whose weighted θ must be exact before these outcomes can be trusted (step 6).

    A comparison is doubtful when the θs' error bounds could overturn it: a candidate's keep
    test, its margin against the own place's less the tie tolerance (the rank), or against
    the top margin less the tolerance (the answer, the lowest place within it); and the own
    place's keep test. Every place of a doubtful comparison is returned.
    """
    qi, seg, pc, own = c.query, c.start, c.place, c.own
    unc = uncertainty[pc]
    u_own = uncertainty[own]
    m_all = c.raw - th_w[pc]
    m_own = (c.b - th_w[own])[qi]
    kept_m = np.where(c.raw >= th_w[pc], m_all, -np.inf)
    top_w, f_w = _first_argmax(kept_m, seg, qi)
    idx = np.where(kept_m == top_w[qi], np.arange(len(pc)), len(pc))  # the place reaching the top itself
    p_top = np.minimum.reduceat(idx, seg)
    p_top[~np.isfinite(top_w)] = -1
    u_top = np.where(p_top >= 0, unc[np.maximum(p_top, 0)], 0.0)[qi]
    with np.errstate(invalid="ignore"):  # −inf − −inf: NaN, never near
        near = (np.abs(m_all) <= unc) & (unc > 0)  # kept or not
        near |= (np.abs(m_all - (m_own - _TIE)) <= unc + u_own[qi]) & (unc + u_own[qi] > 0) & ~c.is_own
        near |= ((np.abs(m_all - (top_w[qi] - _TIE)) <= unc + u_top) & (unc + u_top > 0)
                 & (np.arange(len(pc)) != p_top[qi]) & np.isfinite(top_w[qi]))
        flagged = (np.add.reduceat(near, seg) > 0) | ((np.abs(c.b - th_w[own]) <= u_own) & (u_own > 0))
    if not flagged.any():
        return np.empty(0, np.int64)
    top_place = np.where(f_w >= 0, pc[np.maximum(f_w, 0)], own)
    peak_place = np.where(p_top >= 0, pc[np.maximum(p_top, 0)], own)
    return np.unique(np.concatenate([pc[near & flagged[qi]], own[flagged], top_place[flagged], peak_place[flagged]]))


def _score_image_level(c: _Candidates, top: np.ndarray, records: _Records, slots: int,
                       out: dict[str, dict[str, np.ndarray]]) -> None:
    """The image-level baseline into ``out`` (its answered place is filled in by ``_assemble``).

    The top image is the lowest-index training image within the tie tolerance of the top
    score; the rank counts the wrong training images within it of b or above, resolved up to
    ``records.cap``.
    """
    qi, seg, pc = c.query, c.start, c.place
    bq, finite = c.b[qi] - _TIE, np.isfinite(c.b)
    cap = records.cap
    floor_top = top[qi] - _TIE
    tied = (c.raw >= floor_top) & np.isfinite(top[qi])
    image = c.image.copy()  # outside the near-duplicate places only raw_p's image can reach the top
    if len(c.near):
        ok = c.slots >= floor_top[c.near][:, None]
        slot = np.argmax(ok, axis=1)
        image[c.near] = np.where(ok.any(axis=1), c.near_images[np.arange(len(c.near)), slot], c.image[c.near])
    img_top = np.minimum.reduceat(np.where(tied, image, np.iinfo(np.int64).max), seg)
    img_top[~np.isfinite(top)] = -1
    above = (c.t1 >= bq) & ~c.is_own & finite[qi]
    contrib = np.where(above & (c.t2 < bq), (~c.hit).astype(np.int64), 0)  # one image reaches b: unless held out
    multi = np.flatnonzero(above & (c.t2 >= bq))
    beyond = np.zeros(len(c.own), dtype=bool)
    if len(multi):  # two or more images reach b: count them from the records
        mrow = c.row[qi[multi]]
        over = records.n[mrow] >= cap
        match = records.place[mrow] == pc[multi][:, None]
        found = match.any(axis=1)
        bits = records.bits[mrow, np.argmax(match, axis=1)]
        ge = np.unpackbits(bits, axis=1, bitorder="little")[:, :slots].astype(bool)
        contrib[multi] = np.where(found, ge.sum(axis=1) - ge[np.arange(len(multi)), c.held[multi]], 1)
        beyond[qi[multi][over]] = True
        if not (found | over).all():  # pragma: no cover
            raise RuntimeError("internal error: a multi-image record is missing")
    resolved = np.minimum(1.0 + np.add.reduceat(contrib, seg), cap + 1)
    out["image-baseline"]["rank"][c.own] = np.where(finite, np.where(beyond, cap + 1, resolved), np.inf)
    out["image-baseline"]["image"][c.own] = img_top


def _score_block(ent: dict[str, np.ndarray], blk: int, sd: _SplitData, lay: Layout, pas: _PassResult,
                 out: dict[str, dict[str, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Every method of ``_ORDER`` for the split's queries of one row block (module doc, step 5).

    ``out[key]`` holds ``rank``, ``place`` and ``image`` arrays over the split's queries (in
    place-index order); the block's part is written. Returns the queries' top raw score and
    the places whose weighted θ must be made exact before the outcomes can be trusted.
    """
    th_s = np.asarray(sd.thresholds["simple"], dtype=np.float64)[lay.places]
    th_w = np.asarray(sd.thresholds["weighted"], dtype=np.float64)[lay.places]
    c = _candidates(ent, blk, sd, lay, pas, th_s, th_w)
    top = _score_place_level(c, th_s, th_w, lay.places, out)
    _score_image_level(c, top, pas.records, lay.slots, out)
    return top, _near_tie_places(c, th_w, sd.uncertainty)


def _score_splits(entries: _Entries, data: list[_SplitData], lay: Layout, pas: _PassResult, d: np.ndarray,
                  sums: _FullSums, progress: Callable[[int, str], None] | None, done_before: int,
                  ) -> tuple[list[dict[str, dict[str, np.ndarray]]], list[np.ndarray]]:
    """Steps 5 and 6: every split scored block by block, near ties made exact and scored again.

    Where a block's outcomes of a split hang on a near tie, the places involved get their
    float64 θ and that block of that split is scored again, until no near tie is left.
    Returns per split the ``out`` of ``_score_block`` over all its queries and their top raw
    scores.
    """
    n_p = len(lay.places)
    outs = [{k: {"rank": np.empty(n_p), "place": np.empty(n_p, np.int64), "image": np.empty(n_p, np.int64)}
             for k in _ORDER} for _ in data]
    tops = [np.empty(n_p) for _ in data]
    todo = {blk: list(range(len(data))) for blk in range(lay.n_blocks)}  # row block -> splits to score
    first_round = True
    while todo:
        fixes: dict[int, dict[int, np.ndarray]] = {}  # split -> row block -> places to make exact
        for blk in sorted(todo):
            ent = entries.get(blk)
            for r in todo[blk]:
                tops[r][lay.place_range(blk)], fix = _score_block(ent, blk, data[r], lay, pas, outs[r])
                if len(fix):
                    fixes.setdefault(r, {})[blk] = fix
            if progress and first_round:
                progress(done_before + blk + 1, f"scoring block {blk + 1}/{lay.n_blocks}")
        first_round = False
        todo = {}
        for r, by_block in sorted(fixes.items()):
            if not _make_exact(data[r], np.unique(np.concatenate(list(by_block.values()))), d, lay, sums):
                # pragma: no cover - every doubtful comparison involves a place not yet exact
                raise RuntimeError("internal error: near ties did not resolve")
            for blk in by_block:
                todo.setdefault(blk, []).append(r)
    return outs, tops


def _assemble(sd: _SplitData, out: dict[str, dict[str, np.ndarray]], top: np.ndarray, b: np.ndarray,
              image_place: np.ndarray, image_traversal: np.ndarray, n_places: int) -> SplitScores:
    """The split's ``SplitScores`` as the reference has them, answers as positions in the training set.

    ``top`` and ``b`` are each query's top raw score and best correct score; the global θs
    follow from them and the place baseline.
    """
    sp = sd.split
    n_q = len(sp.queries)
    known = np.ones(n_q, dtype=bool)

    def outcome(key: str, rank, place, image) -> Outcome:
        pos = np.where(image >= 0, np.searchsorted(sp.train, np.maximum(image, 0)), -1)
        return Outcome(METHODS_BY_KEY[key], rank, place, pos, np.full(n_q, -1))

    img = out["image-baseline"]
    img["place"] = np.where(img["image"] >= 0, image_place[np.maximum(img["image"], 0)], -1)
    outcomes = {k: outcome(k, out[k]["rank"], out[k]["place"], out[k]["image"]) for k in _ORDER}
    base = out["place-baseline"]
    th = dict(sd.thresholds)

    def global_outcome(key: str, theta: float) -> Outcome:
        # the raw rule with one θ: the own place stays iff b ≥ θ, and then so does every
        # place above it, so the rank is the baseline's; the top answer stays iff it is ≥ θ
        rank = np.where(b >= theta, base["rank"], np.inf)
        acc = top >= theta
        return outcome(key, rank, np.where(acc, base["place"], -1), np.where(acc, base["image"], -1))

    outcomes["global-auto"] = global_outcome("global-auto", th["auto"])
    if "user" in th:
        outcomes["global-user"] = global_outcome("global-user", th["user"])
    th["oracle"] = oracle_global_threshold(top, outcomes["place-baseline"].rank == 1, known)
    outcomes["global-oracle"] = global_outcome("global-oracle", th["oracle"])
    empty = np.empty((0, n_places))
    return SplitScores(
        outcomes=outcomes, raw=empty, best=empty.astype(np.int64), correct=empty.astype(bool), known=known,
        query_traversal=image_traversal[sp.queries], train_traversal=image_traversal[sp.train],
        thresholds=th, spread=sd.spread, k_adaptive=sd.k_adaptive, top=top,
    )


# --------------------------------------------------------------------------- public


def _cpus() -> int:
    """CPUs this process may run on (its affinity, where the OS tells it)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - macOS, Windows
        return os.cpu_count() or 1


def scale_splits(
    descriptors: np.ndarray,
    image_place: np.ndarray,
    image_traversal: np.ndarray,
    n_places: int,
    splits: list[Split],
    *,
    cross_condition: bool = False,
    user_theta: float | None = None,
    seed: int = 0,
    max_k: int = max(KS),
    block: int = BLOCK_ROWS,
    table_memory: int = TABLE_MEMORY,
    spill_dir: str | os.PathLike | None = None,
    threads: int | None = None,
    progress: Progress | None = None,
    device: object | None = None,
) -> list[SplitScores]:
    """The paper protocol's splits scored through one blocked pass (see the module doc).

    Args:
        descriptors: ``(n_images, D)`` L2-normalised, any float dtype; read in row chunks,
            so a float16 memory-mapped array works and is never copied whole.
        image_place, image_traversal: ``(n_images,)`` labels (place ``-1``: a skipped frame).
        splits: from ``evaluation.draw_splits`` without unknown places.
        seed: the protocol's seed (the automatic threshold's pooled sample is drawn with it).
        max_k: image-level ranks beyond it are reported as ``max_k + 1``.
        block, table_memory, spill_dir, threads, device: see ``fast_paper_protocol``.
        progress: ``progress(done, total, message)`` over the splits (their automatic θ), the
            pass's block pairs, then the scoring's row blocks.
    Returns:
        One ``SplitScores`` per split, with the reference's outcomes and thresholds. Its
        per-query matrices ``raw``/``best``/``correct`` are empty ``(0, n_places)`` (they
        are what this path avoids holding) and every ``Outcome.n_kept`` is ``-1``.
    """
    d = descriptors
    image_place, image_traversal = np.asarray(image_place), np.asarray(image_traversal)
    threads = min(_cpus(), 32) if threads is None else max(1, int(threads))
    if any(sp.unknown.any() for sp in splits):
        raise VPRInputError("scale_splits: splits with unknown places (the open set) are not supported; "
                            "use evaluation.open_set_protocol")
    if device is not None:  # a bad device fails before any work
        from vpr_explorer.method.stats import torch_device

        device = torch_device(device)
    lay = make_layout(image_place, n_places, block)
    query_rows = np.stack([lay.row_of_image[sp.queries] for sp in splits])  # (R, P): queries by place index
    held = lay.slot_of_row[query_rows]
    runs = len(splits)
    n_pairs = lay.n_blocks * (lay.n_blocks + 1) // 2
    steps = runs + n_pairs + lay.n_blocks  # per split (automatic θ), per block pair, per row block
    report = (lambda done, what: progress(done, steps, what)) if progress else None
    with ThreadPoolExecutor(1) as aside:
        # in a thread beside the full-set sums (which leave a core idle now and then: their
        # lanes wait in turn), with more than one thread: the automatic θ (step 4, the
        # reference's own pooled sample, drawn once for the run) and the twins' content
        # classes, which need neither the sums nor the pass
        later = aside.submit if threads > 1 else _now
        autos, content = later(_automatic_thetas, d, splits, seed), later(_content_classes, d, lay)
        x = _as_layout32(d, lay, threads)  # the pass's float32 rows, which the full-set sums read too
        sums = _full_sums(d, lay, query_rows, threads, x)
        # every θ_p is a convex combination of its place's μᵢ: all lie in [min μ, max μ] (the pass's floor)
        mus = [_split_mu(r, lay.row_of_image[sp.train], lay, sums, held[r]) for r, sp in enumerate(splits)]
        mu_lo = min(float(mu.min()) for mu, _ in mus)
        mu_hi = max(float(mu.max()) for mu, _ in mus)
        autos, content = autos.result(), content.result()
    if report:
        for r in range(runs):
            report(r + 1, f"split {r + 1}/{runs}: automatic θ")
    row_traversal = None
    if cross_condition:
        _, codes = np.unique(image_traversal, return_inverse=True)
        row_traversal = np.full(lay.n_rows, -1, dtype=np.int64)
        real = lay.image_of_row >= 0
        row_traversal[real] = codes.ravel()[lay.image_of_row[real]]
    pass_report = (lambda done, what: report(runs + done, what)) if report else None
    entries = _Entries(lay, table_memory, spill_dir)
    try:
        pas = _blocked_pass(x, lay, query_rows, row_traversal, entries, max_k, (mu_lo, mu_hi), sums.centre,
                            threads, pass_report, device)
        del x
        with ThreadPoolExecutor(threads) as pool:  # splits side by side: each writes only its own results
            data = list(pool.map(lambda r: _split_thresholds(r, splits[r], lay, sums, pas, held[r], n_places,
                                                             autos[r], user_theta, content, mus[r]), range(runs)))
            kappa = _error_scale(d, lay, sums, data, seed)
            for sd in data:
                sd.uncertainty = _uncertainty(sd, lay, kappa)
            outs, tops = _score_splits(entries, data, lay, pas, d, sums, report, runs + n_pairs)
            return list(pool.map(lambda r: _assemble(data[r], outs[r], tops[r],
                                                     pas.best_own[query_rows[r]].astype(np.float64), image_place,
                                                     image_traversal, n_places), range(runs)))
    finally:
        entries.close()


def _now(fn: Callable, *args) -> Future:
    """``fn(*args)`` run now, in a finished future (``executor.submit``'s stand-in)."""
    future: Future = Future()
    future.set_result(fn(*args))
    return future


def _automatic_thetas(d: np.ndarray, splits: list[Split], seed: int) -> list[float]:
    """Each split's automatic global θ from one pooled tile sample for the run (module doc, step 4)."""
    sample = pooled_pair_sample(d, [sp.train for sp in splits], seed=seed)
    return [sample.theta(r) for r in range(len(splits))]


def fast_paper_protocol(
    descriptors: np.ndarray,
    image_place: np.ndarray,
    image_traversal: np.ndarray,
    n_places: int,
    *,
    runs: int = 50,
    seed: int = 0,
    cross_condition: bool = False,
    user_theta: float | None = None,
    ks: tuple[int, ...] = KS,
    progress: Progress | None = None,
    settings: dict | None = None,
    block: int = BLOCK_ROWS,
    table_memory: int = TABLE_MEMORY,
    spill_dir: str | os.PathLike | None = None,
    threads: int | None = None,
    tolerance: int = 0,
    image_frame: np.ndarray | None = None,
    frame_place: np.ndarray | None = None,
    pr: bool = False,
    device: object | None = None,
    shared: SharedScores | None = None,
) -> Evaluation:
    """``evaluation.paper_protocol`` through one blocked pass: the same ``Evaluation``.

    Same arguments and meaning as ``paper_protocol`` (``runs`` seeded splits, one query image
    per place, thresholds from each split's training images, ``cross_condition``,
    ``user_theta``, ``ks``), plus:

    Args:
        block: rows per block of the pass; its buffers take about 4·block·(``PANEL_ROWS`` + 76)
            bytes per thread (25 MiB at 4,096).
        table_memory: bytes of top-2 table entries kept in RAM before spilling to a file.
        spill_dir: folder for that temporary file (default: the system's temporary folder).
        threads: panels of the pass run side by side, each GEMM in one BLAS thread (default: the
            CPUs this process may use, at most 32); the numbers do not depend on it.
        tolerance, image_frame, frame_place: as for ``paper_protocol``. When the tolerance
            makes a neighbouring place right for some query (places closer than the
            tolerance), this path, built on one right place per query, hands the run to
            ``paper_protocol`` and says so in the notes.
        pr: also the precision–recall rows and curves. The per-place family curves need every
            query's raw_p, which the pass does not keep: up to ``PR_FAMILY_CELLS`` runs × places²
            the run goes to ``paper_protocol`` (the same numbers), above it they are left out.
        device: ``None`` (numpy) or a torch device ("cpu", "cuda") for the pass's block
            products; the same numbers (the tie tolerance absorbs last-bit differences).
        shared: ``shared_scores.SharedScores`` of ``descriptors``, for a run handed to
            ``paper_protocol`` (a sweep builds one for all its cells); the pass does not need it.
    """
    t0 = time.perf_counter()
    d, image_place, image_traversal, ks = _check_common(descriptors, image_place, image_traversal, runs, ks)
    if cross_condition and len(np.unique(image_traversal[image_place >= 0])) < 2:
        raise VPRInputError("cross_condition needs at least 2 traversals")
    straight = None
    if pooled_truth(image_place, image_frame, frame_place, tolerance, n_places) is not None:
        straight = (f"a frame tolerance of {tolerance} makes neighbouring places right: scored by the straightforward "
                    "protocol (one right place per query is what the blocked pass assumes)")
    elif pr and runs * n_places**2 <= PR_FAMILY_CELLS:
        straight = ("precision–recall of the per-place methods needs every query's raw_p: scored by the "
                    "straightforward protocol (the same numbers)")
    if straight is not None:
        ev = paper_protocol(d, image_place, image_traversal, n_places, runs=runs, seed=seed,
                            cross_condition=cross_condition, user_theta=user_theta, ks=ks, progress=progress,
                            settings=settings, tolerance=tolerance, image_frame=image_frame, frame_place=frame_place,
                            pr=pr, shared=shared)
        return dataclasses.replace(ev, notes=(*ev.notes, straight), seconds=time.perf_counter() - t0)
    splits = draw_splits(image_place, n_places, runs=runs, seed=seed)
    scored = scale_splits(
        d, image_place, image_traversal, n_places, splits, cross_condition=cross_condition, user_theta=user_theta,
        seed=seed, max_k=max(ks), block=block, table_memory=table_memory, spill_dir=spill_dir, threads=threads,
        progress=progress, device=device,
    )
    notes = []
    if not cross_condition:
        notes.append("queries are matched against all traversals, their own included: see the own-traversal "
                     "share, and the cross-condition variant")
    pr_rows, pr_curves = split_pr(scored) if pr else ((), {})
    if pr:
        notes.append(f"precision–recall of the per-place methods left out: {runs} runs × {n_places:,}² places "
                     f"exceed {PR_FAMILY_CELLS:,} cells (the blocked pass keeps no raw_p)")
    return Evaluation(
        protocol=Protocol.PAPER,
        settings={**(settings or {}), "runs": runs, "seed": seed, "cross_condition": cross_condition,
                  "tolerance": int(tolerance), "queries_per_run": len(scored[0].known)},
        ks=ks, rows=_summarise(scored, ks, own_traversal=True), notes=tuple(notes),
        seconds=time.perf_counter() - t0, pr=pr_rows, pr_curves=pr_curves,
    )
