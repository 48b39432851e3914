"""The float64 sums over all labelled images that every split downdates (package doc, step 1).

T = Σⱼ dⱼ, the within-place grams, C = Σⱼ dⱼdⱼᵀ through each row's quadratic form, and each
split's Σ_{q∈Q_r} d_q, once for the run, from the descriptors' own values.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from vpr_explorer.method.stats import one_blas_thread, run_in_lanes, triangular_blocks, triangular_quadratic_forms
from vpr_explorer.protocols.scale.layout import Layout

#: Float64 sums of the first pass that row blocks are dealt to in turn (``full_set_sums``).
SUM_LANES = 4
#: Rows per float64 product of the quadratic forms (their products stay in cache).
QUAD_ROWS = 1024


@dataclass(frozen=True, eq=False)
class FullSums:
    """Float64 sums over all labelled images, per layout row (zero on padding rows).

    Attributes:
        dot_other: ``(n_rows,)`` dᵢ·(T − T_p(i)) = Σ_{j∉p(i)} dᵢ·dⱼ.
        dot_queries: ``(n_rows, R)`` dᵢ·Σ_{q∈Q_r} d_q.
        gram: ``(P, m, m)`` within-place dᵢ·dⱼ (zero for padding slots).
        centre: c, the mean score over all pairs of distinct labelled images, a float32 value.
        a_centred: ``(n_rows,)`` aᵢ = Σ_{j∉p(i)} (dᵢ·dⱼ − c)².
    """

    dot_other: np.ndarray
    dot_queries: np.ndarray
    gram: np.ndarray
    centre: float
    a_centred: np.ndarray


def _layout_rows64(d: np.ndarray, lay: Layout, rows: slice, out: np.ndarray, x32: np.ndarray | None) -> np.ndarray:
    """``(len(rows), D)`` float64 descriptors of these layout rows in ``out``'s memory, zero rows
    for padding: converted from ``x32`` (``as_layout32``, the same values when ``d`` holds
    float32 or float16) where given, gathered from ``d`` otherwise."""
    x = out[: rows.stop - rows.start]
    if x32 is not None:
        np.copyto(x, x32[rows])
        return x
    img = lay.image_of_row[rows]
    np.copyto(x, d[np.maximum(img, 0)])
    x[img < 0] = 0.0
    return x


def full_set_sums(d: np.ndarray, lay: Layout, query_rows: np.ndarray, threads: int = 1,
                  x32: np.ndarray | None = None) -> FullSums:
    """T, T_p, C and the quadratic forms, once (O(N·D²) float64), from the original values.

    Two passes over the layout's row blocks, as pool tasks in ``threads`` threads with BLAS in
    one thread each. The first sums T, C (one syrk per block) and each split's Σ_q d_q into
    float64 lanes (block k on lane k mod ``SUM_LANES``, in order: ``stats.run_in_lanes``) and
    forms the within-place grams; the second gives each row its dot products and quadratic
    form. So the sums are the same numbers for any thread count.

    Args:
        d: ``(n_images, D)`` descriptors, any float dtype.
        lay: their layout.
        query_rows: ``(R, P)`` layout row of each split's query of each place index.
        threads: threads of the two passes.
        x32: the float32 layout rows (``as_layout32``), read instead of gathering from ``d``
            when ``d`` is float32 or float16.
    """
    n_rows, dim = lay.n_rows, d.shape[1]
    m, n_p, runs = lay.slots, len(lay.places), len(query_rows)
    threads = max(1, threads)
    if x32 is not None and np.dtype(d.dtype).itemsize > 4:
        x32 = None  # float64 descriptors: the sums take their own values, not float32 roundings
    widest = int(np.diff(lay.block_start).max()) * m
    buffers = threading.local()  # each thread's float64 rows and products, reused across its blocks

    def rows64(b: int) -> np.ndarray:
        if not hasattr(buffers, "x"):
            buffers.x, buffers.y = np.empty((widest, dim)), np.empty((min(QUAD_ROWS, widest), dim))
            buffers.g = np.empty((dim, dim))
        return _layout_rows64(d, lay, lay.rows(b), buffers.x, x32)

    lanes = [(np.zeros(dim), np.zeros((dim, dim)), np.zeros((runs, dim)))
             for _ in range(min(SUM_LANES, lay.n_blocks))]
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
    with ThreadPoolExecutor(threads) as pool, one_blas_thread():
        run_in_lanes(pool, range(lay.n_blocks), len(lanes), first, in_flight=threads)
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
            quad = np.concatenate([triangular_quadratic_forms(x[lo : lo + QUAD_ROWS], cols, w, buffers.y)
                                   for lo in range(0, len(x), QUAD_ROWS)])
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
    return FullSums(dot_other, dot_q, gram, centre, a_centred)
