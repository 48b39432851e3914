"""Where the blocked pass's time goes: one off-diagonal block pair, step by step, against the GEMM peak (issue 13 §4).

    python benchmarks/bench_pass_block.py [--dim 1280] [--block 4096] [--runs 50]

``scale._blocked_pass`` does, for every block pair I < J of the place-major layout (Nordland-like
data from ``bench_nordland_scale``, places of 12 images):

1. S = X_I X_Jᵀ, the float32 GEMM (the only work the floor pass does);
2. Q = (S − c)², elementwise;
3. the second-moment downdate V += Q M_J and V += Qᵀ M_I, float32 GEMMs against the
   (rows × runs) query indicators in chunks of 2,048 rows (``_W_CHUNK``);
4. the top-2 table for the block's rows and, by symmetry, its columns (``_table_side``).

Each step is timed alone on the same block (best of ``--repeats``, CPU seconds of this
process: steadier than wall time on a shared machine), and printed with its share of the
block's time; the GEMM's rate is given as a share of numpy's float32 GEMM rate on the same
shape, measured in the same run, per CPU second. The pass's share of the peak, for its
necessary flops, is at most the GEMM's share times the GEMM's part of the block's time.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench_nordland_scale import nordland_like
from gemm_peak import blas_kernel, gemm_rate, load_average
from vpr_explorer.scale import _W_CHUNK, _as_layout32, _table_side, make_layout


def cpu_best(fn, repeats: int) -> float:
    best = np.inf
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dim", type=int, default=1280)
    ap.add_argument("--block", type=int, default=4096, help="rows per block (scale.BLOCK_ROWS)")
    ap.add_argument("--runs", type=int, default=50, help="splits: columns of the query indicators")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    places = 2 * (args.block // 12)  # two blocks of about --block rows
    d, labels, _ = nordland_like(places, args.dim, 0)
    lay = make_layout(labels, places, args.block)
    x = _as_layout32(d, lay)
    ri, rj = lay.rows(0), lay.rows(1)
    ni, nj, m = ri.stop - ri.start, rj.stop - rj.start, lay.slots
    s = np.empty((ni, nj), dtype=np.float32)
    q = np.empty_like(s)
    rng = np.random.default_rng(0)
    mi = (rng.random((ni, args.runs)) < 1 / m).astype(np.float32)  # one query per place and split
    mj = (rng.random((nj, args.runs)) < 1 / m).astype(np.float32)
    v = np.zeros((ni + nj, args.runs))
    np.matmul(x[ri], x[rj].T, out=s)
    centre = np.float32(s.mean())
    floor_i = np.full(ni, np.quantile(s[:256], 0.999), dtype=np.float32)  # about one entry per row, as in the pass
    floor_j = np.full(nj, floor_i[0], dtype=np.float32)

    def downdate() -> None:
        for c0 in range(0, nj, _W_CHUNK):
            v[:ni] += q[:, c0 : c0 + _W_CHUNK] @ mj[c0 : c0 + _W_CHUNK]
        for c0 in range(0, ni, _W_CHUNK):
            v[ni:] += q[c0 : c0 + _W_CHUNK].T @ mi[c0 : c0 + _W_CHUNK]

    steps = {
        "1. S = X_I X_Jᵀ (GEMM)": lambda: np.matmul(x[ri], x[rj].T, out=s),
        "2. Q = (S − c)²": lambda: np.square(np.subtract(s, centre, out=q), out=q),
        "3. V += Q M_J, Qᵀ M_I": downdate,
        "4. top-2 table, rows": lambda: _table_side(None, s.reshape(ni, m, nj // m), floor_i, axis=1, parts=1),
        "4. top-2 table, columns": lambda: _table_side(None, s.reshape(m, ni // m, nj), floor_j, axis=0, parts=1),
    }
    peak_cpu = gemm_rate(np.float32, ni, args.dim, nj, args.repeats, clock=time.process_time)
    times = {name: cpu_best(fn, args.repeats) for name, fn in steps.items()}
    peak_cpu = max(peak_cpu, gemm_rate(np.float32, ni, args.dim, nj, args.repeats, clock=time.process_time))
    total = sum(times.values())
    print(f"BLAS: {blas_kernel()}; load average {load_average()}")
    print(f"one block pair {ni:,} × {nj:,} rows, D = {args.dim}, {args.runs} splits; numpy float32 GEMM on that "
          f"shape: {peak_cpu:.0f} GFLOP per CPU second (best of before and after)")
    for name, t in times.items():
        print(f"  {name:<26} {t:7.3f} CPU s  {100 * t / total:5.1f}% of the block")
    gemm = times["1. S = X_I X_Jᵀ (GEMM)"]
    needed = 2.0 * ni * nj * args.dim
    print(f"summary: the GEMM is {100 * gemm / total:.0f}% of the block's CPU time and runs at "
          f"{100 * needed / gemm / 1e9 / peak_cpu:.0f}% of peak; the block at "
          f"{100 * needed / total / 1e9 / peak_cpu:.0f}% of peak for its necessary flops (2·rows·cols·D)")


if __name__ == "__main__":
    main()
