"""One panel of the pass: a GEMM of whole places against a block, and its bookkeeping (package doc, step 2).

A panel holds every slot of some places of block I, slot-major, so that both sides of the
top-2 table reduce over a place's images inside it: its rows against the columns' places,
and the columns (block J's rows) against its places. Off the diagonal the columns are block
J; on it, the block's places from the panel's first on (slot-major too): the pairs with
earlier places came with those places' panels, by symmetry, so a diagonal block's GEMMs
cover its triangle and the panels on it only. After its GEMM (``PassState.products``) the
panel is read slot by slot, a slab of up to ``SLAB_ROWS`` rows of one slot at a time, which
stays in cache while it gives its squares, both downdate products and both maxima
(``panel_task``). The merge into the pass's sums is ``blocked_pass``'s.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import sparse

from vpr_explorer.protocols.scale.layout import Layout
from vpr_explorer.protocols.scale.table import TIE, round_down32, top2_rows

#: Rows of a panel read at a time after its GEMM (of one slot, so 64 places): 64 × 4,096
#: float32 scores (1 MiB) and their squares stay in a core's cache while they give both
#: downdate products and both maxima.
SLAB_ROWS = 64
#: Rows of M per float32 product of the second-moment downdate's dense side (a panel's own
#: rows; block J's rows take the sparse one, ``PassState.slab_queries``): each float32 sum
#: has one nonzero term per place among them (about 170 for Nordland's places of 12 images);
#: the chunks are summed in float64.
W_CHUNK = 2048


@dataclass(frozen=True, eq=False)
class PassInputs:
    """What the pass reads.

    Attributes:
        x: ``(n_rows, D)`` float32 descriptors in layout order (``layout.as_layout32``).
        lay: the layout.
        query_rows: ``(R, P)`` layout row of each split's query of each place index.
        row_traversal: ``(n_rows,)`` traversal code of each row (cross-condition: a query
            matches other traversals only), or ``None``: every traversal matches.
        mu_range: ``(min μ, max μ)`` over every split's training images: every θ lies within.
        centre: c, the score the squares are taken about (``FullSums.centre``).
    """

    x: np.ndarray
    lay: Layout
    query_rows: np.ndarray
    row_traversal: np.ndarray | None
    mu_range: tuple[float, float]
    centre: float


class BlockProducts:
    """A panel of S = X_I X_Jᵀ by numpy (BLAS), written into a float32 buffer; and, for a pass on a
    torch ``device``, the layout descriptors copied there once (``xt``).

    A pass on a device runs each whole panel there (``device_panel``), reading ``xt``; its float32
    scores may differ from numpy's in the last bits, like another BLAS kernel's: the tie tolerance
    (package doc, step 2) keeps every outcome the same.
    """

    def __init__(self, x: np.ndarray, device: object | None):
        self.x, self.device = x, device
        if device is not None:
            import torch

            self.xt = torch.from_numpy(x).to(self.device)

    def __call__(self, rows: np.ndarray, cols: slice | np.ndarray, out: np.ndarray) -> None:
        np.matmul(self.x[rows], self.x[cols].T, out=out)


class PassState:
    """What every panel reads (products, query indicator, floors) and each worker thread's buffers.

    ``floor`` starts at +∞ and gets a row's floor (``row_floor``) when the row's diagonal
    panel is merged; the panels read it, the merge writes it.
    """

    def __init__(self, inputs: PassInputs, products: BlockProducts, panel_rows: int):
        lay = inputs.lay
        self.lay, self.products = lay, products
        self.runs = inputs.query_rows.shape[0]
        self.indicator = np.zeros((lay.n_rows, self.runs), dtype=np.float32)  # M: row i is a query of split r
        self.indicator[inputs.query_rows.T, np.arange(self.runs)[None, :]] = 1.0
        self.is_query = self.indicator.any(axis=1)
        self.pad = lay.image_of_row < 0
        self.row_traversal = inputs.row_traversal
        self.centre = np.float32(inputs.centre)
        self.mu_range = inputs.mu_range
        self.floor = np.full(lay.n_rows, np.inf, dtype=np.float32)
        widest = lay.slots * int(np.diff(lay.block_start).max())
        self.size = min(max(panel_rows, 1) + lay.slots, widest) * widest  # a panel: at most panel_rows + m rows
        self.slab = SLAB_ROWS * widest
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
        """This thread's float32 buffers: a panel's scores and a slab's squares."""
        buf = getattr(self.local, "buf", None)
        if buf is None:
            buf = self.local.buf = (np.empty(self.size, np.float32), np.empty(self.slab, np.float32))
        return buf


@dataclass(frozen=True)
class Panel:
    """One task of the pass: the places ``g0:g1`` (within block ``bi``) against block ``bj``;
    on the diagonal (``bi == bj``), against the block's places from ``g0`` on."""

    bi: int
    bj: int
    g0: int
    g1: int


@dataclass(eq=False)
class PanelResult:
    """A panel's share of the pass, merged by the main thread in task order (``blocked_pass``).

    Attributes:
        panel: the panel.
        rows: ``(n,)`` layout rows of the panel: slot-major over its places.
        v_rows: ``(n, R)`` float64: the panel rows' share of V.
        cols: layout rows of ``v_cols``: block J's (off the diagonal), or the block's after
            the panel.
        v_cols: ``(R, cols)`` float64: those rows' share of V, transposed; ``None`` when the
            panel has no columns outside its own places.
        best: ``(n,)`` b of the panel rows (diagonal panels), else ``None``.
        sides: ``(table row block, side)`` of each side of the table (``table_side``), with
            layout-block rows, place indices and ``own`` (the entries of the row's own place,
            or ``None``).
    """

    panel: Panel
    rows: np.ndarray
    v_rows: np.ndarray
    cols: slice | np.ndarray
    v_cols: np.ndarray | None
    best: np.ndarray | None
    sides: list


def row_floor(best: np.ndarray, mu_range: tuple[float, float], is_query: np.ndarray) -> np.ndarray:
    """Per row: below it no place reaches a rank or an answer of this query, in any split
    and under any θs in [min μ, max μ] = ``mu_range`` (float32, rounded down).

    With b ≥ max μ ≥ θ_own the own place is kept in every split and a place must reach
    b − (max μ − min μ) − tie; otherwise the answer may be any kept place, and kept means
    raw ≥ θ ≥ min μ. Rows that are never a query get +∞.
    """
    lo, hi = mu_range
    b = best.astype(np.float64)
    with np.errstate(invalid="ignore"):
        f = np.where(b >= hi + 1e-9, b - (hi - lo), np.minimum(b - (hi - lo), lo)) - TIE - 1e-9
    f = np.where(np.isfinite(b), f, -np.inf)
    return np.where(is_query, round_down32(f), np.float32(np.inf))


def table_side(s3: np.ndarray, t1: np.ndarray, floor: np.ndarray, *, axis: int) -> dict[str, np.ndarray]:
    """One side of a panel's top-2 table: the entries whose best score ``t1`` reaches the row's floor.

    Args:
        s3: ``(rows, m, places)`` (axis=1: the panel's rows are the table's rows) or
            ``(m, places, cols)`` (axis=0: its columns are).
        t1: ``s3``'s maximum over ``axis``.
        floor: the floor of each of the table's rows.

    Returns:
        The entries' local ``row`` and ``place``, ``top2_rows``' t1/a1/t2/a2/near and their
        ``(n, m)`` slot scores ``vals``.
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
    return {"row": r, "place": c, **top2_rows(vals), "vals": vals}


@dataclass(frozen=True, eq=False)
class PanelShape:
    """Where a panel's scores sit: its ``rows`` (every slot of its ``gp`` places, slot-major)
    against its ``cols`` (every slot of ``gj`` places from place ``c0`` of block J on)."""

    panel: Panel
    rows: np.ndarray
    cols: slice | np.ndarray
    row0: int  # block I's first layout row
    col0: int  # block J's first layout row
    gp: int
    gj: int
    c0: int

    @property
    def diagonal(self) -> bool:
        return self.panel.bi == self.panel.bj

    @property
    def with_cols(self) -> bool:
        """Whether the panel has a columns' side: places outside its own."""
        return not self.diagonal or self.gj > self.gp

    @property
    def own(self) -> np.ndarray | None:
        """``(gp,)`` each panel place's position among the columns' places (diagonal panels)."""
        return np.arange(self.gp) if self.diagonal else None


def panel_shape(lay: Layout, p: Panel) -> PanelShape:
    m = lay.slots
    ri, rj = lay.rows(p.bi), lay.rows(p.bj)
    gi = (ri.stop - ri.start) // m
    rows = ri.start + (np.arange(m)[:, None] * gi + np.arange(p.g0, p.g1)[None, :]).ravel()
    if p.bi == p.bj:  # the columns' places: the block's from g0 on (the panel's own first)
        gj, c0 = gi - p.g0, p.g0
        cols: slice | np.ndarray = ri.start + (np.arange(m)[:, None] * gi + np.arange(p.g0, gi)[None, :]).ravel()
    else:
        gj, c0, cols = (rj.stop - rj.start) // m, 0, rj
    return PanelShape(p, rows, cols, ri.start, rj.start, p.g1 - p.g0, gj, c0)


def _scores(st: PassState, sh: PanelShape) -> np.ndarray:
    """``(n, m·gj)`` float32 S of the panel's rows against its columns, in this thread's buffer."""
    n, nj = len(sh.rows), st.lay.slots * sh.gj
    s = st.buffers()[0][: n * nj].reshape(n, nj)
    st.products(sh.rows, sh.cols, s)
    return s


@dataclass(eq=False)
class _Reduced:
    """What a panel's slabs add up to (``_reduce``)."""

    v_rows: np.ndarray  # (n, R) float64: V of the panel's rows
    v_cols: np.ndarray | None  # (R, m·gj) float32: V of the columns, transposed (with a columns' side)
    row_max: np.ndarray  # (n, gj) float32: each row's best over each column place's slots
    col_max: np.ndarray | None  # (gp, m·gj) float32: each column's best over each panel place's slots
    best: np.ndarray | None  # (n,) float32: b, the best of the own place's other images (diagonal)


def _reduce(st: PassState, sh: PanelShape, s: np.ndarray) -> _Reduced:
    """Squares, downdate products and maxima of the panel's scores ``s``, slab by slab.

    ``s`` is left masked: −∞ where a pair may not match (padding; in cross-condition, the
    same traversal).
    """
    m, runs = st.lay.slots, st.runs
    n, nj = s.shape
    out = _Reduced(
        v_rows=np.zeros((n, runs)),
        v_cols=np.zeros((runs, nj), dtype=np.float32) if sh.with_cols else None,
        row_max=np.empty((n, sh.gj), dtype=np.float32),
        col_max=np.full((sh.gp, nj), -np.inf, dtype=np.float32) if sh.with_cols else None,
        best=np.empty(n, dtype=np.float32) if sh.diagonal else None,
    )
    own = sh.own
    mj = st.indicator[sh.cols]
    pad_j = st.pad[sh.cols]
    trav_j = st.row_traversal[sh.cols] if st.row_traversal is not None else None
    q_buf = st.buffers()[1]
    for k in range(m):
        for h0 in range(0, sh.gp, SLAB_ROWS):
            h1 = min(h0 + SLAB_ROWS, sh.gp)
            sl, hl, hs = slice(k * sh.gp + h0, k * sh.gp + h1), slice(h0, h1), h1 - h0
            sk = s[sl]
            q = q_buf[: hs * nj].reshape(hs, nj)
            # second moments: squared scores against each split's queries of other places
            np.square(np.subtract(sk, st.centre, out=q), out=q)
            if sh.diagonal:
                q.reshape(hs, m, sh.gj)[np.arange(hs), :, own[hl]] = 0.0
            for w0 in range(0, nj, W_CHUNK):
                out.v_rows[sl] += q[:, w0 : w0 + W_CHUNK] @ mj[w0 : w0 + W_CHUNK]
            if sh.with_cols:  # the slab rows that are queries, as a sparse (R × rows) indicator: few per split
                np.add(out.v_cols, st.slab_queries(int(sh.rows[sl.start]), hs) @ q, out=out.v_cols)
            # what a query may match: never padding; in cross-condition, not its own traversal
            pad_k = st.pad[sh.rows[sl]]
            if pad_k.any():
                sk[pad_k] = -np.inf
            if pad_j.any():
                sk[:, pad_j] = -np.inf
            if trav_j is not None:
                np.putmask(sk, st.row_traversal[sh.rows[sl]][:, None] == trav_j[None, :], -np.inf)
            # the maxima over each place's slots, both ways, and b
            sk3 = sk.reshape(hs, m, sh.gj)
            if sh.diagonal:
                mine = sk3[np.arange(hs), :, own[hl]]
                mine[:, k] = -np.inf
                out.best[sl] = mine.max(axis=1)
            np.max(sk3, axis=1, out=out.row_max[sl])
            if sh.with_cols:
                np.maximum(out.col_max[hl], sk, out=out.col_max[hl])
    return out


def _row_side(st: PassState, sh: PanelShape, s: np.ndarray, red: _Reduced) -> dict[str, np.ndarray]:
    """The table's side of the panel's rows: per row, the columns' places at or above its floor.

    A diagonal panel holds its rows' own place, hence b and their floor (``row_floor``).
    """
    m, n = st.lay.slots, len(sh.rows)
    floor = row_floor(red.best, st.mu_range, st.is_query[sh.rows]) if sh.diagonal else st.floor[sh.rows]
    side = table_side(s.reshape(n, m, sh.gj), red.row_max, floor, axis=1)
    r = side["row"]
    side["own"] = side["place"] == np.tile(sh.own, m)[r] if sh.diagonal else None
    side["row"], side["place"] = sh.rows[r] - sh.row0, st.lay.block_start[sh.panel.bj] + sh.c0 + side["place"]
    return side


def column_floor(st: PassState, sh: PanelShape, wait: Callable[[], object] | None) -> np.ndarray:
    """The floor of each of the panel's columns (a copy); +∞ for the columns of the panel's own places.

    On the diagonal the columns' floors come from their own (diagonal) panels: ``wait()``
    returns once those are merged.
    """
    if sh.diagonal:
        if wait is not None:
            wait()
        floor = st.floor[sh.cols]  # a copy (cols: an index array)
        floor.reshape(st.lay.slots, sh.gj)[:, : sh.gp] = np.inf  # the rows' side has them
        return floor
    return st.floor[sh.cols]


def _column_side(st: PassState, sh: PanelShape, s: np.ndarray, red: _Reduced,
                 wait: Callable[[], object] | None) -> dict[str, np.ndarray]:
    """The table's side of the panel's columns: per column row, the panel's places at or above its floor.

    On the diagonal the columns are the block's places after the panel's, whose floors come
    from their own (diagonal) panels: ``wait()`` returns once those are merged. The columns
    of the panel's own places are its rows' side already.
    """
    m, p = st.lay.slots, sh.panel
    side = table_side(s.reshape(m, sh.gp, m * sh.gj), red.col_max, column_floor(st, sh, wait), axis=0)
    if sh.diagonal:
        side["row"] = sh.cols[side["row"]] - sh.col0
    side["own"], side["place"] = None, st.lay.block_start[p.bi] + p.g0 + side["place"]
    return side


def panel_task(st: PassState, p: Panel, wait: Callable[[], object] | None = None) -> PanelResult:
    """Everything the splits need from one panel of S, in one thread (module doc).

    Args:
        st: the pass's state.
        p: the panel.
        wait: on the diagonal, returns once the panels of the block's later places are
            merged (``blocked_pass`` runs a diagonal block's panels last place first).

    Returns:
        The panel's share of V, b (diagonal panels) and both sides of the table.
    """
    sh = panel_shape(st.lay, p)
    s = _scores(st, sh)
    red = _reduce(st, sh, s)
    sides = [(p.bi, _row_side(st, sh, s, red))]
    v_cols, cols = red.v_cols, sh.cols
    if sh.with_cols:
        sides.append((p.bj, _column_side(st, sh, s, red, wait)))
        if sh.diagonal:  # those columns' V, too, came with the rows
            after = (np.arange(st.lay.slots * sh.gj) % sh.gj) >= sh.gp
            v_cols, cols = v_cols[:, after], cols[after]
    return PanelResult(p, sh.rows, red.v_rows, cols, None if v_cols is None else v_cols.astype(np.float64),
                       red.best, sides)
