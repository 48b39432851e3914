"""The float64 sums over all labelled images that every split downdates (package doc, step 1).

T = Σⱼ dⱼ, the within-place grams, C = Σⱼ dⱼdⱼᵀ through each row's quadratic form, and each
split's Σ_{q∈Q_r} d_q, once for the run, from the descriptors' own values.

Two ways to the same ``FullSums``: ``full_set_sums`` with numpy float64 BLAS in threads on the
CPU, and, with a torch ``device`` (``ProtocolOptions.device``), ``device_set_sums``: the layout
rows as one float64 tensor there, whole-array float64 products (the full C = XᵀX, not its
triangle; the within-place grams batched; each split's Σ_q d_q through the query indicator),
back to numpy for the last step. Both end in ``_combine`` (c, dᵢ·(T − T_p), aᵢ), so they differ
only by the float64 rounding of sums taken in another order: observed up to 8.4e-15 of a sum's
magnitude (Σ of its terms' absolute values: a within-place gram of Nordland pixels, 2,048
terms; under 1e-15 for the other sums), far below the float32 rounding of V that step 6
covers, so every outcome is the same.
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
#: Rows per float64 product x C on a torch device (``device_set_sums``): 16,384 × 1,280
#: float64 is 160 MiB there, beside the float64 rows themselves (1.1 GiB at Nordland's 110,000).
DEVICE_QUAD_ROWS = 16384


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
                  x32: np.ndarray | None = None, device: object | None = None) -> FullSums:
    """T, T_p, C and the quadratic forms, once (O(N·D²) float64), from the original values.

    Two passes over the layout's row blocks, as pool tasks in ``threads`` threads with BLAS in
    one thread each. The first sums T, C (one syrk per block) and each split's Σ_q d_q into
    float64 lanes (block k on lane k mod ``SUM_LANES``, in order: ``stats.run_in_lanes``) and
    forms the within-place grams; the second gives each row its dot products and quadratic
    form. So the sums are the same numbers for any thread count. With ``device``, they are
    ``device_set_sums``' instead (``threads`` unused).

    Args:
        d: ``(n_images, D)`` descriptors, any float dtype.
        lay: their layout.
        query_rows: ``(R, P)`` layout row of each split's query of each place index.
        threads: threads of the two passes.
        x32: the float32 layout rows (``as_layout32``), read instead of gathering from ``d``
            when ``d`` is float32 or float16.
        device: None (numpy here) or a torch device (``ProtocolOptions.device``).
    """
    if x32 is not None and np.dtype(d.dtype).itemsize > 4:
        x32 = None  # float64 descriptors: the sums take their own values, not float32 roundings
    if device is not None:
        return device_set_sums(d, lay, query_rows, device, x32)
    n_rows, dim = lay.n_rows, d.shape[1]
    m, n_p, runs = lay.slots, len(lay.places), len(query_rows)
    threads = max(1, threads)
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
    return _combine(lay, total, gram, dot_total, dot_place, sq, dot_q)


def device_set_sums(d: np.ndarray, lay: Layout, query_rows: np.ndarray, device: object,
                    x32: np.ndarray | None = None) -> FullSums:
    """``full_set_sums``' ``FullSums`` computed in torch float64 on ``device`` (numpy arrays on the CPU).

    The layout rows go to the device block by block into one ``(n_rows, D)`` float64 tensor
    (from ``x32``, converted there, where given: the same values when ``d`` is float32 or
    float16; gathered from ``d`` in float64 otherwise), then in whole-array operations: T =
    Σ rows, C = XᵀX (the full product), the within-place grams (a batched product per block),
    each split's Σ_q d_q as the ``(R × n_rows)`` query indicator times X, and per row dᵢ·T,
    dᵢ·Σ_q d_q, dᵢᵀCdᵢ (as ((X C)∘X) row sums, ``DEVICE_QUAD_ROWS`` rows at a time) and the
    own place's terms. Products and sums are all float64 (no index_add: on CUDA its atomics
    would make the sums change from run to run). ``_combine`` finishes with numpy.

    Args:
        d: ``(n_images, D)`` descriptors, any float dtype.
        lay: their layout.
        query_rows: ``(R, P)`` layout row of each split's query of each place index.
        device: a torch device (or its name: "cpu", "cuda").
        x32: the float32 layout rows (``as_layout32``); ignored for float64 descriptors, whose
            sums take their own values, not float32 roundings.
    """
    import torch

    dev, f64 = torch.device(device), torch.float64
    n_rows, dim, m, runs = lay.n_rows, d.shape[1], lay.slots, len(query_rows)
    if x32 is not None and np.dtype(d.dtype).itemsize > 4:
        x32 = None
    x = torch.empty((n_rows, dim), dtype=f64, device=dev)
    buffer = None if x32 is not None else np.empty((int(np.diff(lay.block_start).max()) * m, dim))
    grams = []
    for b in range(lay.n_blocks):
        rows = lay.rows(b)
        host = x32[rows] if x32 is not None else _layout_rows64(d, lay, rows, buffer, None)
        xb = x[rows]
        xb.copy_(torch.from_numpy(host))  # synchronous from pageable memory: the buffer is free after
        x3 = xb.view(m, -1, dim).transpose(0, 1)  # (G, m, D): each place's images
        grams.append(x3 @ x3.transpose(1, 2))
    gram = torch.cat(grams)  # (P, m, m)
    total = x.sum(dim=0)
    gram_all = x.T @ x
    indicator = torch.zeros((runs, n_rows), dtype=f64, device=dev)
    indicator[torch.arange(runs, device=dev)[:, None], torch.from_numpy(query_rows).to(dev)] = 1.0
    queries = indicator @ x  # (R, D)
    del indicator
    dot_total = x @ total
    dot_q = x @ queries.T  # (n_rows, R)
    # row (k, g) of a block is gram[g, k]: its own place's scores, zero for padding slots
    own = gram[torch.from_numpy(lay.place_of_row).to(dev), torch.from_numpy(lay.slot_of_row).to(dev)]
    dot_place, own_sq = own.sum(dim=1), own.square().sum(dim=1)
    del own
    quad = torch.cat([(x[lo : lo + DEVICE_QUAD_ROWS] @ gram_all).mul_(x[lo : lo + DEVICE_QUAD_ROWS]).sum(dim=1)
                      for lo in range(0, n_rows, DEVICE_QUAD_ROWS)])
    sq = quad - own_sq  # Σ_{j∉p} s²
    back = [t.cpu().numpy() for t in (total, gram, dot_total, dot_place, sq, dot_q)]
    return _combine(lay, *back)


def _combine(lay: Layout, total: np.ndarray, gram: np.ndarray, dot_total: np.ndarray, dot_place: np.ndarray,
             sq: np.ndarray, dot_q: np.ndarray) -> FullSums:
    """``FullSums`` from the float64 sums: T ``(D,)``, the grams ``(P, m, m)``, per row dᵢ·T,
    dᵢ·T_p and Σ_{j∉p} sᵢⱼ² ``(n_rows,)``, and dᵢ·Σ_q d_q ``(n_rows, R)``: c as a float32 value,
    dᵢ·(T − T_p) and aᵢ = Σ_{j∉p} sᵢⱼ² − 2c·dᵢ·(T − T_p) + c²·n_other (zero on padding rows)."""
    # scores are taken relative to c in the pass: (s − c)² sums carry float32 rounding in
    # proportion to |s − c|, not |s| (descriptors with a shared component score 0.7 everywhere)
    n_lab = int(lay.sizes.sum())
    norms = np.einsum("pkk->", gram)
    centre = float(np.float32((total @ total - norms) / max(n_lab * (n_lab - 1), 1)))
    n_other = n_lab - lay.sizes[lay.place_of_row]
    dot_other = dot_total - dot_place
    a_centred = np.where(lay.image_of_row >= 0, sq - 2 * centre * dot_other + centre**2 * n_other, 0.0)
    return FullSums(dot_other, dot_q, gram, centre, a_centred)
