"""The BLAS a benchmark runs on, and its GEMM rate in this process: the yardstick for "% of peak".

    python benchmarks/gemm_peak.py [--m 4096] [--k 1280] [--n 1280]

Benchmarks import it (``from gemm_peak import blas_kernel, measure_peak, share``; scripts in
``benchmarks/`` find it beside them) and print, before their own numbers, which kernel ran
and what numpy's GEMM does on a comparable shape at that moment, then
"achieved X GFLOP/s = Y% of peak" for their own steps.

The kernel is the one OpenBLAS picked for this CPU unless ``OPENBLAS_CORETYPE`` forces one:
``OPENBLAS_CORETYPE=Haswell`` (AVX2) runs a current numpy at about 60% of its SkylakeX
(AVX-512) rate. Compare runs with and without it::

    env -u OPENBLAS_CORETYPE -u OPENBLAS_L2_SIZE python benchmarks/bench_negative_stats.py
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import dataclass

import numpy as np

ENV_VARS = ("OPENBLAS_CORETYPE", "OPENBLAS_L2_SIZE", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")


def blas_kernel() -> str:
    """One line: BLAS library, version, kernel (architecture), threads, and the OpenBLAS variables set."""
    env = ", ".join(f"{k}={os.environ[k]}" for k in ENV_VARS if k in os.environ) or "no OPENBLAS_* variables"
    try:
        from threadpoolctl import threadpool_info
    except ImportError:
        return f"BLAS kernel unknown: threadpoolctl is not installed (pip install threadpoolctl); {env}"
    blas = [i for i in threadpool_info() if i.get("user_api") == "blas"]
    if not blas:
        return f"BLAS kernel unknown: threadpoolctl sees no BLAS loaded by numpy; {env}"
    return "; ".join(
        f"{i.get('internal_api')} {i.get('version')} kernel {i.get('architecture', '?')}, "
        f"{i.get('num_threads')} threads" for i in blas
    ) + f" ({env})"


def gemm_rate(dtype: type = np.float32, m: int = 4096, k: int = 1280, n: int = 1280, repeats: int = 5,
              clock=time.perf_counter) -> float:
    """Best GFLOP/s of numpy's ``(m, k) @ (k, n)`` in ``dtype`` over ``repeats`` runs (2·m·k·n flops each).

    The output buffer is reused, as a tuned step would: a fresh array per product adds page
    faults that are not GEMM time.
    """
    rng = np.random.default_rng(0)
    a = rng.standard_normal((m, k)).astype(dtype)
    b = rng.standard_normal((k, n)).astype(dtype)
    out = np.empty((m, n), dtype=dtype)
    np.matmul(a, b, out=out)  # warm-up: threads started, buffers touched
    best = np.inf
    for _ in range(repeats):
        t0 = clock()
        np.matmul(a, b, out=out)
        best = min(best, clock() - t0)
    return 2 * m * k * n / best / 1e9


@dataclass(frozen=True)
class GemmPeak:
    """GEMM rates measured in this process, with the kernel they ran on."""

    float32: float  # GFLOP/s
    float64: float  # GFLOP/s
    shape: tuple[int, int, int]
    kernel: str
    float32_cpu: float = float("nan")  # GFLOP per CPU second (all BLAS threads): steadier on a shared machine

    def best(self, other: "GemmPeak") -> "GemmPeak":
        """The higher rates of two measurements of the same shape (before and after a step: on a
        shared machine the load changes, and the peak is what the machine can do)."""
        return GemmPeak(max(self.float32, other.float32), max(self.float64, other.float64), self.shape, self.kernel,
                        max(self.float32_cpu, other.float32_cpu))

    def lines(self) -> list[str]:
        m, k, n = self.shape
        return [
            f"BLAS: {self.kernel}",
            f"GEMM peak, ({m}×{k}) @ ({k}×{n}), best of runs: float32 {self.float32:.0f} GFLOP/s, "
            f"float64 {self.float64:.0f} GFLOP/s; float32 per CPU second {self.float32_cpu:.0f} GFLOP",
        ]


def measure_peak(m: int = 4096, k: int = 1280, n: int = 1280, repeats: int = 5) -> GemmPeak:
    """float32 and float64 GEMM rates on ``(m, k) @ (k, n)`` and the kernel, in this process."""
    return GemmPeak(
        float32=gemm_rate(np.float32, m, k, n, repeats),
        float64=gemm_rate(np.float64, m, k, n, repeats),
        shape=(m, k, n),
        kernel=blas_kernel(),
        float32_cpu=gemm_rate(np.float32, m, k, n, repeats, clock=time.process_time),
    )


def decision_flops(n_frames: int, n_database: int, dim: int) -> float:
    """Flops deciding ``n_frames`` query frames against ``n_database`` images needs: their similarities, 2·F·N·D."""
    return 2.0 * n_frames * n_database * dim


def fit_flops(n_database: int, dim: int) -> float:
    """Flops a database fit needs (``numbers.fit_retrieval``, float32 closed form and the automatic θ):
    the symmetric Gram N·D(D+1), the quadratic forms 2·N·D², and 2·D per pair of the automatic
    θ's sample (all pairs, or ``thresholds.tile_groups``' tiles). Per-place terms (O(N·k·D)) are left out."""
    from vpr_explorer.method.thresholds import AUTO_MAX_PAIRS, tile_groups

    n = n_database
    pairs = n * (n - 1) // 2
    if pairs > AUTO_MAX_PAIRS:
        edges, tiles = tile_groups(n, AUTO_MAX_PAIRS)
        sizes = np.diff(edges)
        pairs = sum(int(sizes[a] * sizes[b]) for a, b in tiles)
    return n * dim * (dim + 1) + 2.0 * n * dim * dim + 2.0 * dim * pairs


def torch_gemm_rate(device: str = "cpu", dtype: str = "float32", m: int = 4096, k: int = 1280, n: int = 1280,
                    repeats: int = 5) -> float:
    """Best GFLOP/s of torch's ``(m, k) @ (k, n)`` on ``device`` in ``dtype`` (float32: TF32 off)."""
    import torch

    dev = torch.device(device)
    dt = getattr(torch, dtype)
    saved = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision("highest")
    try:
        a = torch.randn(m, k, device=dev).to(dt)
        b = torch.randn(k, n, device=dev).to(dt)
        out = torch.empty(m, n, device=dev, dtype=dt)
        torch.matmul(a, b, out=out)
        best = float("inf")
        for _ in range(repeats):
            if dev.type == "cuda":
                torch.cuda.synchronize(dev)
            t0 = time.perf_counter()
            torch.matmul(a, b, out=out)
            if dev.type == "cuda":
                torch.cuda.synchronize(dev)
            best = min(best, time.perf_counter() - t0)
    finally:
        torch.set_float32_matmul_precision(saved)
    return 2 * m * k * n / best / 1e9


def torch_flops(fn) -> int:
    """Flops torch counts for ``fn()`` (``torch.utils.flop_counter``: 2 per multiply-add of convolutions
    and matrix products; elementwise work is not counted)."""
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as counter:
        fn()
    return int(counter.get_total_flops())


def share(flops: float, seconds: float, peak_gflops: float) -> str:
    """``"achieved X GFLOP/s = Y% of peak"`` for ``flops`` done in ``seconds``."""
    rate = flops / seconds / 1e9
    return f"achieved {rate:.0f} GFLOP/s = {100 * rate / peak_gflops:.0f}% of peak"


def load_average() -> str:
    """The 1-minute load average (``/proc/loadavg``), to print beside timings on a shared machine."""
    try:
        with open("/proc/loadavg") as f:
            return f.read().split()[0]
    except OSError:
        return "unknown"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--m", type=int, default=4096)
    ap.add_argument("--k", type=int, default=1280)
    ap.add_argument("--n", type=int, default=1280)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    print(f"load average {load_average()}")
    for line in measure_peak(args.m, args.k, args.n, args.repeats).lines():
        print(line)


if __name__ == "__main__":
    main()
