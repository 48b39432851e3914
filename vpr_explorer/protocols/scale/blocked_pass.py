"""The pass: every panel of every block pair I ≤ J, in threads, merged in task order (package doc, step 2).

Each block pair is cut into panels of whole places of block I (``panel.panel_task``: the
GEMM of the panel's rows and its bookkeeping, slab by slab in cache, in one thread).
``threads`` threads run panels side by side, BLAS in one thread each, and the main thread
merges their results in task order, so the sums and the table do not depend on the number
of threads. Diagonal blocks come first: they hold each image's own place, hence b and the
row's floor, which the off-diagonal blocks need. A diagonal block's panels run last place
first, and each waits, before the side of its columns (the block's later places), until the
panel before it is merged: the floors of those columns are then known.

BLAS runs in one thread whatever ``threads`` is: OpenBLAS's Haswell sgemm splits the sum of
a (64 × 2,048) @ (2,048 × 50) product (the downdate's shape) between its threads, which
would make V depend on their number.

With ``ProtocolOptions.device`` a panel is ``device_panel.DevicePanels.task`` instead: its
GEMM, squares, downdate products, masks, maxima, b and the selection of its table entries run
on the torch device in whole-panel operations (what costs there is kernel launches, not cache
misses), and only the floors (n numbers a panel) and the merge stay on the CPU. Panels there
are ``DEVICE_PANEL_ROWS`` rows (a whole default block), at most ``DEVICE_THREADS`` of them in
flight side by side, merged in task order as on the CPU; matmuls run in full float32
(``stats.ieee_float32``, no TF32) throughout the pass.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from vpr_explorer.method.stats import ieee_float32, one_blas_thread
from vpr_explorer.protocols.options import ProtocolOptions
from vpr_explorer.protocols.scale.device_panel import DevicePanels
from vpr_explorer.protocols.scale.layout import Layout
from vpr_explorer.protocols.scale.panel import (
    BlockProducts,
    Panel,
    PanelResult,
    PassInputs,
    PassState,
    panel_task,
    row_floor,
)
from vpr_explorer.protocols.scale.table import TIE, Entries, NearSlots, Records

#: Rows per panel of the pass (whole places): one panel of a block pair, 1,536 × 4,096
#: float32 scores (24 MiB), is one GEMM in one thread and its bookkeeping.
PANEL_ROWS = 1536
#: Panels on a diagonal block are this many times shorter: each computes the block's places
#: from its own on (``panel.panel_task``), so 8 panels of a 4,096-row block compute 9/16 of
#: it (3 would compute 2/3; the triangle alone is 1/2).
DIAGONAL_SPLIT = 3
#: Rows per panel on a torch device: a block of up to 8,192 rows is one panel (the default
#: 4,096-row block: 64 MiB of float32 scores there, as much for their squares); fewer, larger
#: panels mean fewer kernel launches.
DEVICE_PANEL_ROWS = 8192
#: Panels in flight on a device at once: one computes while another's results come back and
#: the next is queued (each holds its scores there).
DEVICE_THREADS = 2


@dataclass(frozen=True, eq=False)
class PassResult:
    """What the pass leaves besides the top-2 table (which it files in ``Entries``).

    Attributes:
        v: ``(n_rows, R)`` Σ_{q∈Q_r, other place} (s_iq − c)².
        best_own: ``(n_rows,)`` b: the best score in the own place, the image itself left out.
        records: the image-level records (``Records``).
        near: the slot scores of the near-tie entries (``NearSlots``).
    """

    v: np.ndarray
    best_own: np.ndarray
    records: Records
    near: NearSlots


def panels_of(lay: Layout, bi: int, bj: int, panel_rows: int) -> list[Panel]:
    """Block ``bi``'s places cut into panels of about ``panel_rows`` rows (all slots of each place)."""
    gi = int(lay.block_start[bi + 1] - lay.block_start[bi])
    parts = max(1, -(-gi * lay.slots // panel_rows))
    edges = np.linspace(0, gi, parts + 1).astype(int)
    return [Panel(bi, bj, int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


@dataclass(frozen=True, eq=False)
class _Plan:
    """The pass's panels in task order, and what the diagonal ones wait for."""

    diagonal: list[Panel]  # every diagonal block's panels, each block's last place first
    off_diagonal: list[Panel]  # then those of the pairs I < J
    per_pair: dict[tuple[int, int], int]  # panels of each block pair
    before: dict[Panel, Panel]  # a diagonal panel -> the panel merged before it
    merged: dict[Panel, threading.Event]  # diagonal panels: set once merged

    def wait_for(self, p: Panel) -> Callable[[], object] | None:
        """What ``p`` waits on before its columns' side: the merge of the panel before it."""
        before = self.before.get(p)
        return None if before is None else self.merged[before].wait

    def mark_merged(self, p: Panel) -> None:
        event = self.merged.get(p)
        if event is not None:
            event.set()

    def release(self) -> None:
        """Let every waiting panel go (the pass failed), so that the pool can shut down."""
        for event in self.merged.values():
            event.set()


def _plan(lay: Layout, panel_rows: int) -> _Plan:
    diagonal: list[Panel] = []
    per_pair: dict[tuple[int, int], int] = {}
    before: dict[Panel, Panel] = {}
    for b in range(lay.n_blocks):  # shorter panels (more of the triangle left out), last place first
        ps = panels_of(lay, b, b, max(1, panel_rows // DIAGONAL_SPLIT))[::-1]
        before.update(zip(ps[1:], ps))
        per_pair[(b, b)] = len(ps)
        diagonal += ps
    off_diagonal: list[Panel] = []
    for bi in range(lay.n_blocks):
        for bj in range(bi + 1, lay.n_blocks):
            ps = panels_of(lay, bi, bj, panel_rows)
            per_pair[(bi, bj)] = len(ps)
            off_diagonal += ps
    return _Plan(diagonal, off_diagonal, per_pair, before, {p: threading.Event() for p in diagonal})


class _Merge:
    """The pass's sums, b, floors and table, merged panel by panel in task order (main thread).

    ``progress(pairs done, message)`` after each block pair's last panel.
    """

    def __init__(self, st: PassState, entries: Entries, cap: int, plan: _Plan,
                 progress: Callable[[int, str], None] | None):
        lay = st.lay
        self.st, self.entries, self.plan, self.progress = st, entries, plan, progress
        self.v = np.zeros((lay.n_rows, st.runs))
        self.best_own = np.full(lay.n_rows, -np.inf, dtype=np.float32)
        self.records = Records(lay.n_rows, lay.slots, cap)
        self.near = NearSlots(len(lay.places))
        self.left = dict(plan.per_pair)  # block pair -> panels not merged yet
        self.pairs_done = 0

    def __call__(self, res: PanelResult) -> None:
        st = self.st
        self.v[res.rows] += res.v_rows
        if res.v_cols is not None:
            self.v[res.cols] += res.v_cols.T
        if res.best is not None:
            self.best_own[res.rows] = res.best
            st.floor[res.rows] = row_floor(res.best, st.mu_range, st.is_query[res.rows])
        for row_block, side in res.sides:
            self._file(side, row_block)
        self.plan.mark_merged(res.panel)
        self._count(res.panel)

    def _file(self, side: dict, row_block: int) -> None:
        """File one side's entries; record the wrong places whose second best already ties b.

        The side's ``row`` is local to ``row_block``, its ``place`` a place index; ``own`` (on
        a diagonal panel) marks the entries of the row's own place.
        """
        row0 = self.st.lay.rows(row_block).start
        r = side["row"]
        self.entries.put(row_block, side)
        b = self.best_own[row0 + r]
        tied = b.astype(np.float64) - TIE
        sel = (side["t2"] >= tied) & np.isfinite(b)
        if side["own"] is not None:
            sel &= ~side["own"]
        if sel.any():
            self.records.add(row0 + r[sel], side["place"][sel], side["vals"][sel] >= tied[sel][:, None])
        amb = side["near"].astype(bool)
        if amb.any():
            self.near.add(row0 + r[amb], side["place"][amb], side["vals"][amb])

    def _count(self, p: Panel) -> None:
        pair = (p.bi, p.bj)
        self.left[pair] -= 1
        if self.left[pair] == 0:
            self.pairs_done += 1
            if self.progress:
                self.progress(self.pairs_done, f"similarity block {self.pairs_done}/{len(self.left)}")

    def result(self) -> PassResult:
        return PassResult(self.v, self.best_own, self.records, self.near)


def _run(panels: list[Panel], task: Callable[[Panel], PanelResult], merge: _Merge,
         pool: ThreadPoolExecutor | None, ahead: int) -> None:
    """``merge(task(p))`` for every panel in order: in this thread without a pool, else as pool
    tasks, up to ``ahead`` of them in flight beyond the merge."""
    if pool is None:
        for p in panels:
            merge(task(p))
        return
    window: deque = deque()
    for p in panels:
        window.append(pool.submit(task, p))
        if len(window) > ahead:
            merge(window.popleft().result())
    while window:
        merge(window.popleft().result())


def blocked_pass(inputs: PassInputs, entries: Entries, cap: int, options: ProtocolOptions, *,
                 progress: Callable[[int, str], None] | None = None, panel_rows: int | None = None) -> PassResult:
    """Everything the splits need from the similarities, in one pass over block pairs I ≤ J (module doc).

    Args:
        inputs: what the pass reads: the float32 layout rows, the queries, the floors' μ range.
        entries: where the top-2 table's entries are filed.
        cap: image-level records kept per row (max(ks): more put the rank beyond every K).
        options: ``threads`` (panels side by side) and ``device`` (a torch device: each panel's
            product and bookkeeping run there, ``device_panel``, in at most ``DEVICE_THREADS``
            threads; None: numpy on the CPU, ``panel.panel_task``).
        progress: ``progress(pairs done, message)`` after each block pair.
        panel_rows: rows per panel (default ``PANEL_ROWS``, ``DEVICE_PANEL_ROWS`` on a device).

    Returns:
        V, b, the image-level records and the near-tie slot scores.
    """
    device = options.device
    if panel_rows is None:
        panel_rows = PANEL_ROWS if device is None else DEVICE_PANEL_ROWS
    st = PassState(inputs, BlockProducts(inputs.x, device), panel_rows)
    plan = _plan(inputs.lay, panel_rows)
    merge = _Merge(st, entries, cap, plan, progress)
    if device is not None:
        on_device = DevicePanels(st)
        with ieee_float32():  # process-wide: set once here, not by each worker thread
            _run_all(plan, lambda p: on_device.task(p, plan.wait_for(p)), merge, min(options.threads, DEVICE_THREADS))
        return merge.result()

    def task(p: Panel) -> PanelResult:
        return panel_task(st, p, plan.wait_for(p))

    _run_all(plan, task, merge, options.threads)
    return merge.result()


def _run_all(plan: _Plan, task: Callable[[Panel], PanelResult], merge: _Merge, threads: int) -> None:
    """The diagonal panels, then the others, each merged in task order, in ``threads`` threads."""
    if threads == 1:  # BLAS in one thread here too: a multithreaded sgemm may split the sums
        with one_blas_thread():
            _run(plan.diagonal, task, merge, None, 0)
            _run(plan.off_diagonal, task, merge, None, 0)
        return
    ahead = 2 * threads
    with ThreadPoolExecutor(threads) as pool, one_blas_thread():
        try:
            _run(plan.diagonal, task, merge, pool, ahead)  # b and the floors, which every other panel reads
        except BaseException:
            plan.release()
            raise
        _run(plan.off_diagonal, task, merge, pool, ahead)
