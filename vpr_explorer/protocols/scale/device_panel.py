"""One panel of the pass on a torch device: the GEMM and all its bookkeeping there (package doc, step 2).

``panel.panel_task`` reads a panel's scores slab by slab in a CPU core's cache; on a GPU
that is thousands of small kernel launches per panel. ``DevicePanels.task`` does the same
work on ``ProtocolOptions.device`` in whole-panel tensor operations and returns the same
``panel.PanelResult`` (numpy arrays of the same dtypes, in the same order), which
``blocked_pass`` merges like any other:

* S = X_I X_Jᵀ in float32 (full float32: ``blocked_pass`` holds ``stats.ieee_float32``),
  from the layout rows copied to the device once (``panel.BlockProducts``);
* the squares (S − c)∘(S − c), zeroed on a diagonal panel's same-place pairs;
* V of the panel's rows, (squares) @ M_J: float32 products over ``W_CHUNK`` columns, summed
  in float64, as the numpy panel does; V of the columns, M_Iᵀ @ (squares), dense (on the
  device the flops are cheaper than the numpy panel's sparse indicator), likewise float32
  products over ``W_CHUNK`` panel rows summed in float64. Each float32 sum has at most one
  nonzero term per place among its ``W_CHUNK`` rows or columns, so its rounding is no larger
  than the numpy panel's (whose columns' sums run in float32 over the whole panel); the
  summation order differs, which step 6's measured error scale covers;
* the masks (padding; in cross-condition, the same traversal), b (the best of the own place,
  the own slot left out), the per-(image, place) maxima both ways;
* both sides of the table: the entries at or above the floor (``panel.row_floor``, numpy:
  n numbers), in the order ``panel.table_side`` gives them, with ``table.top2_rows``' t1, a1,
  t2, a2, near (its rules exactly: the first slot reaching a maximum, ties within
  ``table.TIE`` in float32) and the slot scores ``vals``.

A diagonal panel's columns' side waits, as the numpy panel's does, until the floors of the
block's later places are merged. On CUDA each worker thread queues its panels on a stream of
its own, so one thread's transfers do not wait on another's kernels. The streams do not change
the bits: PyTorch gives cuBLAS a workspace per (handle, stream), the condition under which
NVIDIA's cuBLAS documentation promises the same results with streams running side by side
(no ``CUBLAS_WORKSPACE_CONFIG`` needed), and the panels merge in task order, so 1 and 2
threads give the same sums and table bit for bit (``tests/test_scale_device.py`` asks for it
on the device under test).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np

from vpr_explorer.protocols.scale.panel import (
    W_CHUNK,
    Panel,
    PanelResult,
    PanelShape,
    PassState,
    column_floor,
    panel_shape,
    row_floor,
)
from vpr_explorer.protocols.scale.table import TIE


class DevicePanels:
    """The pass's per-panel inputs on ``st.products.device`` (copied once) and the panel task.

    Args:
        st: the pass's state; its ``products`` (a ``BlockProducts`` with a device) hold the
            layout rows there already.
    """

    def __init__(self, st: PassState):
        import torch

        self.torch, self.st = torch, st
        self.device = st.products.device
        self.x = st.products.xt  # (n_rows, D) float32
        self.indicator = torch.from_numpy(st.indicator).to(self.device)  # (n_rows, R) float32 M
        self.pad = torch.from_numpy(st.pad).to(self.device)
        self.traversal = (None if st.row_traversal is None
                          else torch.from_numpy(np.asarray(st.row_traversal, dtype=np.int64)).to(self.device))
        self.centre = torch.tensor(st.centre, dtype=torch.float32, device=self.device)
        self.tie = torch.tensor(np.float32(TIE), device=self.device)  # float32, as numpy's t1 - TIE
        self.local = threading.local()
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)  # the copies above, before other streams read them

    def _stream(self) -> object | None:
        """This thread's CUDA stream (None on other devices)."""
        if self.device.type != "cuda":
            return None
        stream = getattr(self.local, "stream", None)
        if stream is None:
            stream = self.local.stream = self.torch.cuda.Stream(self.device)
        return stream

    def _to(self, a: np.ndarray) -> object:
        return self.torch.from_numpy(np.ascontiguousarray(a)).to(self.device)

    def task(self, p: Panel, wait: Callable[[], object] | None = None) -> PanelResult:
        """``panel.panel_task``'s result for panel ``p``, computed on the device (module doc)."""
        stream = self._stream()
        if stream is None:
            return self._task(p, wait)
        with self.torch.cuda.stream(stream):
            return self._task(p, wait)

    def _task(self, p: Panel, wait: Callable[[], object] | None) -> PanelResult:
        torch, st = self.torch, self.st
        sh = panel_shape(st.lay, p)
        m, n, gp, gj = st.lay.slots, len(sh.rows), sh.gp, sh.gj
        nj = m * gj
        rows_t = self._to(sh.rows)
        cols_t = self._to(sh.cols) if isinstance(sh.cols, np.ndarray) else sh.cols
        s = self.x[rows_t] @ self.x[cols_t].T  # (n, nj) float32; rows slot-major over gp places, cols over gj
        # second moments: squared scores about c, same-place pairs zeroed
        q = (s - self.centre).square_()
        if sh.diagonal:  # row (k, h) against column (k', h), h < gp: the panel's places come first among the columns
            q.view(m, gp, m, gj)[..., :gp].diagonal(0, 1, 3).zero_()
        mi, mj = self.indicator[rows_t], self.indicator[cols_t]
        v_rows = torch.zeros((n, st.runs), dtype=torch.float64, device=self.device)
        for w0 in range(0, nj, W_CHUNK):
            v_rows += (q[:, w0 : w0 + W_CHUNK] @ mj[w0 : w0 + W_CHUNK]).double()
        v_cols = None
        if sh.with_cols:
            v_cols = torch.zeros((st.runs, nj), dtype=torch.float64, device=self.device)
            for w0 in range(0, n, W_CHUNK):
                v_cols += (mi[w0 : w0 + W_CHUNK].T @ q[w0 : w0 + W_CHUNK]).double()
        del q
        # what a query may match: never padding; in cross-condition, not its own traversal
        bad = self.pad[rows_t][:, None] | self.pad[cols_t][None, :]
        if self.traversal is not None:
            bad |= self.traversal[rows_t][:, None] == self.traversal[cols_t][None, :]
        s.masked_fill_(bad, -np.inf)
        del bad
        best = None
        if sh.diagonal:  # b: the own place's slots (column place h of row place h), the own slot left out
            mine = s.view(m, gp, m, gj)[..., :gp].diagonal(0, 1, 3).clone()  # (k, k', h)
            mine.diagonal(0, 0, 1).fill_(-np.inf)
            best = mine.amax(dim=1).reshape(n)
        row_max = s.view(n, m, gj).amax(dim=1)  # (n, gj)
        col_max = s.view(m, gp, nj).amax(dim=0) if sh.with_cols else None  # (gp, nj)
        # the table's side of the rows: their floors, from b on the diagonal
        best_np = None if best is None else best.cpu().numpy()
        if sh.diagonal:
            floor = row_floor(best_np, st.mu_range, st.is_query[sh.rows])
        else:
            floor = st.floor[sh.rows]
        r, c = (row_max >= self._to(floor)[:, None]).nonzero(as_tuple=True)
        side = self._entries(s.view(n, m, gj).permute(0, 2, 1)[r, c], r, c)
        side["own"] = side["place"] == (side["row"] % gp) if sh.diagonal else None
        side["row"] = sh.rows[side["row"]] - sh.row0
        side["place"] = st.lay.block_start[p.bj] + sh.c0 + side["place"]
        sides = [(p.bi, side)]
        cols = sh.cols
        if sh.with_cols:
            sides.append((p.bj, self._column_side(sh, s, col_max, wait)))
            if sh.diagonal:  # those columns' V, too, came with the rows
                after = (np.arange(nj) % gj) >= gp
                v_cols, cols = v_cols[:, self._to(after)], cols[after]
        return PanelResult(p, sh.rows, v_rows.cpu().numpy(), cols, None if v_cols is None else v_cols.cpu().numpy(),
                           best_np, sides)

    def _column_side(self, sh: PanelShape, s: object, col_max: object,
                     wait: Callable[[], object] | None) -> dict[str, np.ndarray]:
        """The table's side of the panel's columns (``panel._column_side``'s, from the device's maxima)."""
        st, m, p = self.st, self.st.lay.slots, sh.panel
        c, r = (col_max >= self._to(column_floor(st, sh, wait))[None, :]).nonzero(as_tuple=True)
        side = self._entries(s.view(m, sh.gp, m * sh.gj).permute(1, 2, 0)[c, r], r, c)
        if sh.diagonal:
            side["row"] = sh.cols[side["row"]] - sh.col0
        side["own"], side["place"] = None, st.lay.block_start[p.bi] + p.g0 + side["place"]
        return side

    def _entries(self, vals: object, r: object, c: object) -> dict[str, np.ndarray]:
        """``table_side``'s dict (local ``row``, ``place``, top-2 and ``vals``) of the ``(n, m)`` slot scores."""
        torch = self.torch
        top = top2_device(vals, self.tie)
        # three transfers, not eight: each one waits for the device
        where = torch.stack([r, c]).cpu().numpy()
        slots = torch.stack([top["a1"], top["a2"], top["near"]]).cpu().numpy()
        scores = torch.cat([top["t1"][:, None], top["t2"][:, None], vals], dim=1).cpu().numpy()
        return {"row": where[0], "place": where[1], "t1": scores[:, 0], "a1": slots[0], "t2": scores[:, 1],
                "a2": slots[1], "near": slots[2], "vals": scores[:, 2:]}


def top2_device(vals: object, tie: object) -> dict[str, object]:
    """``table.top2_rows`` of the ``(n, m)`` float32 tensor ``vals``, on its device.

    The first slot reaching a maximum (as numpy's argmax: ``torch.argmax`` promises the
    first on every device only in recent versions), the best held out for the second and
    both for the third; ``near`` compares in float32 with ``tie`` (float32 ``TIE``).

    Returns:
        ``t1`` and ``t2`` float32, ``a1``, ``a2`` and ``near`` uint8 tensors, each ``(n,)``.
    """
    import torch

    m = vals.shape[1]
    slots = torch.arange(m, device=vals.device)

    def first_max(v: object) -> tuple[object, object]:
        top = v.amax(dim=1)
        return top, torch.where(v == top[:, None], slots, m).amin(dim=1)

    t1, a1 = first_max(vals)
    rest = vals.clone()
    rest.scatter_(1, a1[:, None], -np.inf)
    t2, a2 = first_max(rest)
    rest.scatter_(1, a2[:, None], -np.inf)
    t3 = rest.amax(dim=1)
    near = ((t2 >= t1 - tie) & torch.isfinite(t2)) | ((t3 >= t2 - tie) & torch.isfinite(t3))
    return {"t1": t1, "a1": a1.to(torch.uint8), "t2": t2, "a2": a2.to(torch.uint8), "near": near.to(torch.uint8)}
