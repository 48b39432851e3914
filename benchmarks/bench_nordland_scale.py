"""The 50-split paper protocol at Nordland scale, beside one full similarity pass.

    python benchmarks/bench_nordland_scale.py                       # 110,364 × 1,280, 9,197 places
    python benchmarks/bench_nordland_scale.py --places 1000 --runs 5 --check   # small, vs paper_protocol

Generates seeded unit descriptors with place structure (Nordland g3s3's shape: every place
is 3 consecutive frames × 4 traversals; place centres follow the route, so neighbouring
places are correlated; each traversal adds its own appearance shift; frames add noise),
then times

* the floor: one blocked pass computing the similarity of every pair of images once
  (float32 sgemm over the 4,096² blocks I ≤ J, sᵢⱼ = sⱼᵢ; each block reduced to one
  number), and
* ``scale.fast_paper_protocol`` on the same data,

and prints both wall times, their ratio, the CPU seconds of each (this machine may be
shared, so CPU time is the steadier comparison) and the process's peak resident memory.
The floor is timed before and after the protocol and the faster of the two is the one
compared against.

Against the machine's limit: the BLAS kernel in use and numpy's float32 GEMM
rate on the pass's block shape (4,096 × D @ D × 4,096) are measured in the same process
(``gemm_peak``), and each of the two steps prints its achieved rate counting only the flops
it needs, N²·D (half of the 2·N²·D of all ordered pairs: the product is symmetric), as a
share of that peak. Counted for the protocol too: the similarities, nothing else. Its other
work is overhead against that count: the diagonal blocks' second triangle (1/n_blocks more
GEMM flops), the second-moment downdate's products against the query indicators (N²·R
flops dense for the panels' rows, R = splits: 3.9% of N²·D at R = 50, D = 1,280, and about
N²·R/(2m) sparse additions for block J's rows, m images per place), the float64 full-set sums (O(N·D²))
and the per-split steps. Compare kernels with
``env -u OPENBLAS_CORETYPE -u OPENBLAS_L2_SIZE python benchmarks/bench_nordland_scale.py``.
``--device cpu`` (or ``cuda``) runs each panel of the pass, its product and its bookkeeping,
in torch on that device (``scale.device_panel``); the line ``pass:`` says which path ran and
how many panels it computed.
``--phases`` prints the protocol's wall and CPU seconds per step (timers around the step functions
``scale.protocol`` calls; steps that run beside each other overlap, and their CPU seconds are
the whole process's).
``--check`` also runs ``evaluation.paper_protocol`` and asserts identical tables (small N).
``--storage float16`` writes the descriptors as a float16 ``.npy`` and memory-maps it, as
the descriptor cache can.
``--per-split-sample`` also runs the protocol with the automatic θ from a tile sample of each
split's own training images instead of one pooled sample per run
(``training_pair_scores(rows=train, seed=seed + r)``), side by side with the pooled sample
(``thresholds.pooled_pair_sample``), and prints both times and the largest difference of
the automatic θ between the two in units of its spread over the splits.
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import vpr_explorer.protocols.scale.blocked_pass as blocked_pass
import vpr_explorer.protocols.scale.protocol as scale_protocol
from gemm_peak import load_average, measure_peak, share
from vpr_explorer.method.thresholds import auto_global_threshold, training_pair_scores
from vpr_explorer.protocols.options import ProtocolOptions
from vpr_explorer.protocols.scale import fast_paper_protocol
from vpr_explorer.views.report import render

FRAMES, TRAVERSALS = 3, 4


def nordland_like(places: int, dim: int, seed: int, *, chunk: int = 8192) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(places·12, dim)`` float32 unit descriptors, place labels and traversal labels.

    Image (place p, frame f, traversal t) = c_p + 0.25·(frame drift) + 0.5·u_t + 1.0·noise,
    normalised, with c_p an AR(1) walk along the route (ρ = 0.96) and u_t one unit vector per
    traversal. Images are stored traversal-major, as a dataset's folders are.
    """
    rng = np.random.default_rng(seed)
    centres = np.empty((places, dim), dtype=np.float32)
    prev = rng.standard_normal(dim, dtype=np.float32)
    rho = np.float32(0.96)
    for lo in range(0, places, chunk):
        z = rng.standard_normal((min(chunk, places - lo), dim), dtype=np.float32)
        for k in range(len(z)):
            prev = rho * prev + np.sqrt(1 - rho**2) * z[k]
            centres[lo + k] = prev
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    shift = rng.standard_normal((TRAVERSALS, dim), dtype=np.float32)
    shift /= np.linalg.norm(shift, axis=1, keepdims=True)
    n = places * FRAMES * TRAVERSALS
    d = np.empty((n, dim), dtype=np.float32)
    per_trav = places * FRAMES
    frame_place = np.repeat(np.arange(places), FRAMES)
    for t in range(TRAVERSALS):
        for lo in range(0, per_trav, chunk):
            p = frame_place[lo : lo + chunk]
            drift = rng.standard_normal((len(p), dim), dtype=np.float32) / np.sqrt(dim, dtype=np.float32)
            noise = rng.standard_normal((len(p), dim), dtype=np.float32) / np.sqrt(dim, dtype=np.float32)
            x = centres[p] + 0.25 * drift + 0.5 * shift[t] + 1.0 * noise
            d[t * per_trav + lo : t * per_trav + lo + len(p)] = x / np.linalg.norm(x, axis=1, keepdims=True)
    labels = np.tile(frame_place, TRAVERSALS)
    traversal = np.repeat(np.arange(TRAVERSALS), per_trav)
    return d, labels, traversal


def full_similarity_pass(d: np.ndarray, block: int = 4096) -> float:
    """Every pair's similarity once, in float32 blocks I ≤ J (the floor of any exact method); returns a checksum."""
    buf = np.empty((block, block), dtype=np.float32)
    total = 0.0
    for i in range(0, len(d), block):
        xi = np.asarray(d[i : i + block], dtype=np.float32)
        for j in range(i, len(d), block):
            xj = np.asarray(d[j : j + block], dtype=np.float32)
            out = buf[: len(xi), : len(xj)]
            np.matmul(xi, xj.T, out=out)
            total += float(out[0, 0])  # one number per block, so the product is not wasted work
    return total


class PerSplitSample:
    """The automatic θ from a tile sample of each split's own training images (not one pooled sample per run)."""

    def __init__(self, descriptors, trains, *, seed=0):
        self.descriptors, self.trains, self.seed = descriptors, list(trains), seed

    def theta(self, r: int) -> float:
        return auto_global_threshold(training_pair_scores(self.descriptors, rows=self.trains[r], seed=self.seed + r))


#: The protocol's steps (package doc of ``scale``), as ``scale.protocol`` calls them: full-set sums, each split's
#: μ, the automatic θs and their sample, the layout copy, the pass, identical places, per-split thresholds, error
#: scale, scoring, assembly.
PHASES = ("full_set_sums", "split_mu", "automatic_thetas", "pooled_pair_sample", "as_layout32", "blocked_pass",
          "content_classes", "split_thresholds", "error_scale", "uncertainty", "score_splits", "assemble")


def _time_phases() -> dict[str, list]:
    """Wrap the step functions where ``scale.protocol`` reads them with timers; returns name -> [wall s, CPU s of
    the process, calls]."""
    out: dict[str, list] = {}

    def wrap(name):
        fn = getattr(scale_protocol, name)

        def timed_fn(*a, **k):
            w, c = time.perf_counter(), time.process_time()
            try:
                return fn(*a, **k)
            finally:
                acc = out.setdefault(name, [0.0, 0.0, 0])
                acc[0] += time.perf_counter() - w
                acc[1] += time.process_time() - c
                acc[2] += 1
        setattr(scale_protocol, name, timed_fn)

    for name in PHASES:
        wrap(name)
    return out


def counting_panels(device: str | None) -> list[int]:
    """``[panels]``: how many panels the pass's path computes from now on (``DevicePanels.task``
    with a device, ``panel_task`` without), counted by wrapping that function."""
    count = [0]
    if device is None:
        task = blocked_pass.panel_task

        def counted(*a, **k):
            count[0] += 1
            return task(*a, **k)
        blocked_pass.panel_task = counted  # read by blocked_pass
    else:
        cls = blocked_pass.DevicePanels
        method = cls.task

        def counted_method(self, *a, **k):
            count[0] += 1
            return method(self, *a, **k)
        cls.task = counted_method
    return count


def peak_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux


def timed(fn):
    w, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w, time.process_time() - c


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--places", type=int, default=9197, help="places of 12 images (default 9,197: 110,364 images)")
    ap.add_argument("--n", type=int, default=None, help="images instead of places (rounded down to whole places)")
    ap.add_argument("--dim", type=int, default=1280)
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cross-condition", action="store_true")
    ap.add_argument("--storage", choices=["float32", "float16"], default="float32")
    ap.add_argument("--skip-floor", action="store_true", help="do not time the full similarity pass")
    ap.add_argument("--check", action="store_true", help="also run paper_protocol and compare (small N only)")
    ap.add_argument("--device", default=None,
                    help="torch device for the pass's panels, products and bookkeeping (default: numpy on the CPU)")
    ap.add_argument("--profile", action="store_true",
                    help="print the protocol's CPU profile (cProfile on CPU time), the 15 largest by cumulative time")
    ap.add_argument("--phases", action="store_true",
                    help="print the protocol's wall and CPU seconds per step (timers around scale.protocol's steps; "
                         "CPU seconds are the process's: the automatic θs and content classes run beside the "
                         "full-set sums, the per-split steps side by side, so those overlap)")
    ap.add_argument("--per-split-sample", action="store_true",
                    help="also time the protocol with a tile sample per split for the automatic θ "
                         "(instead of one pooled sample per run)")
    args = ap.parse_args()
    places = args.n // (FRAMES * TRAVERSALS) if args.n else args.places

    (d, labels, trav), t_gen, _ = timed(lambda: nordland_like(places, args.dim, args.seed))
    print(f"data: {len(d):,} images × {args.dim} in {places:,} places of {FRAMES * TRAVERSALS} "
          f"({FRAMES} frames × {TRAVERSALS} traversals), seed {args.seed}; generated in {t_gen:.1f} s", flush=True)
    tmp = None
    if args.storage == "float16":
        tmp = tempfile.TemporaryDirectory()
        path = Path(tmp.name) / "descriptors.npy"
        np.save(path, d.astype(np.float16))
        del d
        d = np.load(path, mmap_mode="r")
        print(f"storage: float16, memory-mapped from {path} ({d.nbytes / 2**20:.0f} MiB)", flush=True)

    peak = measure_peak(m=4096, k=args.dim, n=4096)
    print(f"load average {load_average()}")
    for line in peak.lines():
        print(line, flush=True)
    needed = float(len(d)) ** 2 * args.dim  # N²·D: each unordered pair's D multiply-adds, once
    if not args.skip_floor:
        _, w_floor, c_floor = timed(lambda: full_similarity_pass(d))
        print(f"floor  (one blocked pass, each pair once):      {w_floor:8.1f} s wall  {c_floor:8.1f} s CPU   "
              f"peak RSS so far {peak_gib():.2f} GiB", flush=True)

    def bar(done, total, what):
        if done == total or done % max(1, total // 10) == 0:
            print(f"  … {what}", file=sys.stderr, flush=True)

    def protocol():
        options = ProtocolOptions(runs=args.runs, seed=args.seed, cross_condition=args.cross_condition,
                                  device=args.device)
        return fast_paper_protocol(d, labels, trav, places, options, progress=bar,
                                   settings={"data": "nordland-like synthetic"})

    phases = _time_phases() if args.phases else None
    panels = counting_panels(args.device)
    if args.profile:
        import cProfile
        import pstats

        prof = cProfile.Profile(time.process_time)  # CPU time of the whole process, worker threads included
        ev, w_fast, c_fast = timed(lambda: prof.runcall(protocol))
        pstats.Stats(prof).sort_stats("cumulative").print_stats(r"vpr_explorer", 15)
    else:
        ev, w_fast, c_fast = timed(protocol)
    print(f"fast paper protocol ({args.runs} splits):        {w_fast:8.1f} s wall  {c_fast:8.1f} s CPU   "
          f"peak RSS {peak_gib():.2f} GiB", flush=True)
    path = ("numpy on the CPU (panel.panel_task)" if args.device is None
            else f"torch on {args.device} (device_panel.DevicePanels.task)")
    print(f"pass: {path}, {panels[0]:,} panels", flush=True)
    if phases is not None:
        for name, (wall, cpu, calls) in phases.items():
            print(f"  {name:<20} {wall:7.2f} s wall {cpu:7.2f} s CPU  ({calls} calls)")
    if args.per_split_sample:
        autos: dict[str, list[float]] = {"pooled": [], "per split": []}

        def recording(factory, into):  # the sample's θ per split, as the protocol takes them
            def make(*a, **k):
                sample = factory(*a, **k)
                return type("Recorded", (), {"theta": lambda self, r: into.append(sample.theta(r)) or into[-1]})()
            return make

        pooled_sample = scale_protocol.pooled_pair_sample  # read by scale.protocol.automatic_thetas
        try:
            scale_protocol.pooled_pair_sample = recording(pooled_sample, autos["pooled"])
            _, w_pooled, c_pooled = timed(protocol)
            scale_protocol.pooled_pair_sample = recording(PerSplitSample, autos["per split"])
            ev_old, w_old, c_old = timed(protocol)
        finally:
            scale_protocol.pooled_pair_sample = pooled_sample
        new, old = np.array(autos["pooled"]), np.array(autos["per split"])
        print(f"again, side by side: pooled sample {w_pooled:8.1f} s wall {c_pooled:8.1f} s CPU;  per-split samples "
              f"{w_old:8.1f} s wall {c_old:8.1f} s CPU;  per-split / pooled = {w_old / w_pooled:.2f}× wall, "
              f"{c_old / c_pooled:.2f}× CPU", flush=True)
        print(f"automatic θ over the {args.runs} splits: pooled mean {new.mean():.6f} sd {new.std(ddof=1):.2e}; "
              f"per split mean {old.mean():.6f} sd {old.std(ddof=1):.2e}; means differ by "
              f"{(new.mean() - old.mean()) / old.std(ddof=1):+.2f} sd of the per-split θ")
        same = [r.key for r, q in zip(ev.rows, ev_old.rows) if r.key != "global-auto" and all(
            np.array_equal(r.recall[k], q.recall[k]) for k in ev.ks)]
        print(f"rows other than the automatic θ with identical recall: {len(same)} of {len(ev.rows) - 1}")
    if not args.skip_floor:
        # timed again after: on a shared machine the load can change between the two phases
        _, w_again, c_again = timed(lambda: full_similarity_pass(d))
        print(f"floor again, after the protocol:                  {w_again:8.1f} s wall  {c_again:8.1f} s CPU",
              flush=True)
        w_floor, c_floor = min(w_floor, w_again), min(c_floor, c_again)
    peak = peak.best(measure_peak(m=4096, k=args.dim, n=4096))  # again after: on a shared machine the load changes
    print(f"GEMM peak, best of before and after: float32 {peak.float32:.0f} GFLOP/s, "
          f"{peak.float32_cpu:.0f} GFLOP per CPU second")
    if not args.skip_floor:
        print(f"ratio protocol / floor (the faster floor): {w_fast / w_floor:.2f}× wall, {c_fast / c_floor:.2f}× CPU "
              f"(goal ≤ 1.5×, peak < 8 GiB)")
        print(f"floor pass, N²·D flops / time:    {share(needed, w_floor, peak.float32)} (float32 GEMM); "
              f"per CPU second: {share(needed, c_floor, peak.float32_cpu)}")
    print(f"paper protocol, N²·D flops / time: {share(needed, w_fast, peak.float32)} (float32 GEMM; "
          f"{args.runs} splits, goal ≥ 70%); per CPU second: {share(needed, c_fast, peak.float32_cpu)}")
    print()
    print(render(ev))

    if args.check:
        from vpr_explorer.protocols.evaluation import paper_protocol

        ref, w_ref, _ = timed(lambda: paper_protocol(d, labels, trav, places, ProtocolOptions(
            runs=args.runs, seed=args.seed, cross_condition=args.cross_condition)))
        same = ref.same_numbers(ev)
        print(f"\npaper_protocol: {w_ref:.1f} s; identical numbers: {same}")
        if not same:
            sys.exit(1)
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
