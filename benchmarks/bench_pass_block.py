"""Where the blocked pass's time goes: one off-diagonal block pair, against the GEMM peak.

    python benchmarks/bench_pass_block.py [--dim 1280] [--block 4096] [--runs 50] [--threads 2]

For every block pair I < J of the place-major layout (Nordland-like data from
``bench_nordland_scale``, places of 12 images) the pass needs

1. S = X_I X_Jᵀ, the float32 GEMM (the only work the floor pass does);
2. Q = (S − c)², elementwise;
3. the second-moment downdate V += Q M_J and V += Qᵀ M_I, float32 products against the
   (rows × runs) query indicators;
4. the top-2 table for the block's rows and, by symmetry, its columns: each (row, place)'s
   best score over the place's images, and the entries at or above the row's floor.

Timed side by side on the same block pair, in CPU seconds of this process (all threads;
steadier than wall time on a shared machine), best of ``--repeats``:

* **GEMM alone**: step 1 for the whole block, BLAS in its own threads (what the floor does);
* **whole block, step by step** (no panels): the block's GEMM, then each step over the whole
  64 MiB block of scores, steps 1–4 each timed;
* **panels** (``scale.panel.panel_task``, as the pass runs): block I cut into panels of whole
  places (``scale.blocked_pass.PANEL_ROWS`` rows), each one GEMM in one thread and its
  bookkeeping read slab by slab (``scale.panel.SLAB_ROWS`` rows, in cache), ``--threads``
  panels side by side, merged in order.

Each is printed as GFLOP per CPU second for the flops the pair needs (2·rows·cols·D: S once)
and as a share of numpy's float32 GEMM rate on that shape per CPU second, measured in the
same run before and after.
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from bench_nordland_scale import nordland_like
from gemm_peak import blas_kernel, gemm_rate, load_average
from vpr_explorer.method.stats import one_blas_thread
from vpr_explorer.protocols.options import BLOCK_ROWS
from vpr_explorer.protocols.scale import make_layout
from vpr_explorer.protocols.scale.blocked_pass import PANEL_ROWS, panels_of
from vpr_explorer.protocols.scale.layout import as_layout32
from vpr_explorer.protocols.scale.panel import (
    SLAB_ROWS,
    W_CHUNK,
    BlockProducts,
    PassInputs,
    PassState,
    panel_task,
    table_side,
)


def cpu_best(fn, repeats: int) -> float:
    best = np.inf
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return best


def side_whole_block(s3: np.ndarray, floor: np.ndarray, axis: int) -> dict:
    """The top-2 table side as the pass did it on the whole block: maxima, then the entries."""
    return table_side(s3, np.max(s3, axis=axis), floor, axis=axis)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dim", type=int, default=1280)
    ap.add_argument("--block", type=int, default=BLOCK_ROWS, help="rows per block (protocols.options.BLOCK_ROWS)")
    ap.add_argument("--runs", type=int, default=50, help="splits: columns of the query indicators")
    ap.add_argument("--threads", type=int, default=2, help="panels side by side (the pass's threads)")
    ap.add_argument("--panel-rows", type=int, default=PANEL_ROWS, help="rows per panel (scale.blocked_pass.PANEL_ROWS)")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    places = 2 * (args.block // 12)  # two blocks of about --block rows
    d, labels, _ = nordland_like(places, args.dim, 0)
    lay = make_layout(labels, places, args.block)
    x = as_layout32(d, lay)
    ri, rj = lay.rows(0), lay.rows(1)
    ni, nj, m = ri.stop - ri.start, rj.stop - rj.start, lay.slots
    rng = np.random.default_rng(0)
    held = rng.integers(0, m, (args.runs, len(lay.places)))  # one query per place and split
    query_rows = lay.row_of(np.tile(np.arange(len(lay.places)), (args.runs, 1)), held)
    indicator = np.zeros((lay.n_rows, args.runs), dtype=np.float32)
    indicator[query_rows.T, np.arange(args.runs)[None, :]] = 1.0
    mi, mj = indicator[ri], indicator[rj]
    s = np.empty((ni, nj), dtype=np.float32)
    q = np.empty_like(s)
    np.matmul(x[ri], x[rj].T, out=s)
    centre = np.float32(s.mean())
    floor = np.full(lay.n_rows, np.quantile(s[:256], 0.999), dtype=np.float32)  # about one entry per row, as in the pass
    v = np.zeros((lay.n_rows, args.runs))

    def downdate() -> None:
        for c0 in range(0, nj, W_CHUNK):
            v[ri] += q[:, c0 : c0 + W_CHUNK] @ mj[c0 : c0 + W_CHUNK]
        for c0 in range(0, ni, W_CHUNK):
            v[rj] += q[c0 : c0 + W_CHUNK].T @ mi[c0 : c0 + W_CHUNK]

    whole_block = {
        "1. S = X_I X_Jᵀ (GEMM)": lambda: np.matmul(x[ri], x[rj].T, out=s),
        "2. Q = (S − c)²": lambda: np.square(np.subtract(s, centre, out=q), out=q),
        "3. V += Q M_J, Qᵀ M_I": downdate,
        "4. top-2 table, rows": lambda: side_whole_block(s.reshape(ni, m, nj // m), floor[ri], 1),
        "4. top-2 table, columns": lambda: side_whole_block(s.reshape(m, ni // m, nj), floor[rj], 0),
    }
    state = PassState(PassInputs(x, lay, query_rows, None, (0.0, 0.2), centre), BlockProducts(x, None),
                      args.panel_rows)
    state.floor[:] = floor  # as if the diagonal blocks were merged
    tasks = panels_of(lay, 0, 1, args.panel_rows)

    def panels() -> None:
        with ThreadPoolExecutor(args.threads) as pool, one_blas_thread():
            for res in pool.map(lambda t: panel_task(state, t), tasks):
                v[res.rows] += res.v_rows  # the merge, in task order
                v[res.cols] += res.v_cols.T

    def gemm_rate_cpu() -> float:
        return gemm_rate(np.float32, ni, args.dim, nj, args.repeats, clock=time.process_time)

    peak_cpu = gemm_rate_cpu()
    times = {name: cpu_best(fn, args.repeats) for name, fn in whole_block.items()}
    t_panels = cpu_best(panels, args.repeats)
    peak_cpu = max(peak_cpu, gemm_rate_cpu())
    needed = 2.0 * ni * nj * args.dim

    def rate(t: float) -> str:
        return f"{needed / t / 1e9:5.0f} GFLOP per CPU s = {100 * needed / t / 1e9 / peak_cpu:3.0f}% of peak"

    total = sum(times.values())
    gemm = times["1. S = X_I X_Jᵀ (GEMM)"]
    print(f"BLAS: {blas_kernel()}; load average {load_average()}")
    print(f"one block pair {ni:,} × {nj:,} rows, D = {args.dim}, {args.runs} splits; numpy float32 GEMM on that "
          f"shape: {peak_cpu:.0f} GFLOP per CPU second (best of before and after)")
    print(f"GEMM alone (BLAS threads):                 {gemm:7.3f} CPU s  {rate(gemm)}")
    print("whole block, step by step:")
    for name, t in times.items():
        print(f"  {name:<26} {t:7.3f} CPU s  {100 * t / total:5.1f}% of the block")
    print(f"  {'all':<26} {total:7.3f} CPU s  {rate(total)}")
    print(f"panels of {args.panel_rows} rows, slabs of {SLAB_ROWS}, {args.threads} threads: "
          f"{t_panels:7.3f} CPU s  {rate(t_panels)}")
    print(f"summary: panels / whole block = {t_panels / total:.2f}× the CPU seconds; the bookkeeping beside the GEMM "
          f"{total - gemm:.3f} → {t_panels - gemm:.3f} CPU s (against the GEMM alone)")


if __name__ == "__main__":
    main()
