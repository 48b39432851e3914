"""The prepared device check: the GPU tests and the GPU benchmarks in one run, each figure beside its floor.

    bash benchmarks/gpu_check.sh                    # on the device machine: carried wheels, then this
    python benchmarks/gpu_check.py --device cpu --quick --logs /tmp/gpu_check   # the same steps, small, here

Steps, in order, under one time budget (``--budget`` seconds, default 330): a step that its
estimate says cannot finish in what is left is skipped, and the summary says so.

1. **machine**: the GPU (name, memory, driver, multiprocessors), CPU cores, the BLAS kernel;
   the device's measured peaks in this process: torch matmul of 8,192³ in fp32 (TF32 off)
   and bf16, a device-to-device copy's bandwidth; numpy's float32 GEMM on every core.
2. **tests**: the device tests (``DEVICE_TESTS``) with ``VPR_EXPLORER_TEST_DEVICE`` set to
   the device, in a pytest of their own (``pytest.log``).
3. **decode**: GardensPoint's JPEGs decoded by ``torchvision.io.decode_jpeg`` on the device
   (nvJPEG on a GPU): batches of 64, and all of them as one batch, decode alone and decode +
   resize to 224 × 224.
4. **extraction**: EfficientNet-Lite0 (the packaged weights) and CosPlace ResNet-50 (random
   weights of the real shapes: the speed is the same, the descriptors are meaningless), fp32
   and bf16, through ``bench_extraction.bench``: end-to-end into a fresh cache with JPEGs
   decoded on the CPU and on the device, beside the bare forward pass on batches decoded
   beforehand (the goal: end-to-end ≥ 0.8 × bare); the forward's flops as a share of the
   matmul peak; the least cosine between the two decodes' descriptors (the tests require >
   0.9999); once, the device decoder's and resize's pixels against PIL's
   (``bench_extraction.pixel_differences``).
5. **statistics**: the closed form (``negative_stats``) at 100,000 × 1,280, 12,500 places,
   on the device beside numpy on every core, and the largest |Δμ|, |Δσ| between them.
6. **protocol**: the 50-split paper protocol (``fast_paper_protocol``) at 110,364 × 1,280
   (Nordland g3s3's shape, ``bench_nordland_scale.nordland_like``) with the device, beside
   the numpy floor pass on every core (each pair's similarity once) and the device's floor
   (the same N²·D products as torch matmuls there); identical numbers to the numpy pass's
   (``Evaluation.same_numbers``) at 1,000 places, and at full size when time is left; the
   wall time of each of its steps (``bench_nordland_scale.PHASES``).
7. **million**: ``bench_million.py --skip-eval --device`` (1,000,000 database images, D = 512):
   the group/step change's refit with its products on the device (what the app does under
   ``VPR_EXPLORER_DEVICE``), beside its GEMM floor, when time is left.

Writes into ``--logs``: ``summary.md`` (the table, the machine; rewritten after each step),
``check.log`` (all that is printed) and ``pytest.log``, ``million.log`` (their subprocesses'
output, stopped at the budget's end): four files, within what the device tool brings back.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

#: The tests run on the device (``VPR_EXPLORER_TEST_DEVICE`` names it): files, or tests within one.
DEVICE_TESTS = (
    "tests/test_device_decode.py",
    "tests/test_scale_device.py",
    "tests/test_scale_full_sums_device.py",
    "tests/test_stats.py::test_torch_device_within_the_same_bound",
    "tests/test_stats.py::test_cuda_device_runs_or_says_why",
    "tests/test_stats.py::test_a_database_fit_on_a_device_reads_the_rows_in_places_within_the_bound",
    "tests/test_scale.py::test_torch_device_products_give_the_same_numbers",
)
PRECISIONS = ("fp32", "bf16")
EXTRACTION_GOAL = 0.8
PROTOCOL_GOAL_S = 2.0
REFIT_GOAL_S = 0.5


@dataclass
class Sizes:
    """How big each step is: the device run's, or ``--quick``'s for a check on the CPU."""

    images: int | None = None  # GardensPoint images (None: all 600)
    batch: int = 64
    repeats: int = 3
    stats_n: int = 100_000
    stats_places: int = 12_500
    places: int = 9_197
    check_places: int = 1_000
    runs: int = 50
    dim: int = 1_280
    peak_side: int = 8_192
    extractors: tuple[str, ...] = ("efficientnet-lite0", "cosplace")
    million: bool = True

    @classmethod
    def quick(cls) -> "Sizes":
        return cls(images=16, batch=8, repeats=1, stats_n=4_000, stats_places=500, places=150, check_places=60,
                   runs=3, dim=64, peak_side=512, extractors=("efficientnet-lite0",), million=False)


@dataclass
class Summary:
    """The rows of ``summary.md``: figure, measured, floor, ratio, goal, note."""

    rows: list[tuple[str, ...]] = field(default_factory=list)
    machine: list[str] = field(default_factory=list)

    def add(self, figure: str, measured: str, floor: str = "", ratio: str = "", goal: str = "", note: str = "") -> None:
        self.rows.append((figure, measured, floor, ratio, goal, note))
        print(f"  -> {figure}: {measured}" + (f" | floor {floor}" if floor else "") + (f" | {ratio}" if ratio else "")
              + (f" | goal {goal}" if goal else "") + (f" | {note}" if note else ""), flush=True)

    def markdown(self) -> str:
        head = ["# Device check", "", *[f"- {line}" for line in self.machine], "",
                "| figure | measured | floor | ratio | goal | note |", "|---|---|---|---|---|---|"]
        return "\n".join(head + ["| " + " | ".join(r) + " |" for r in self.rows]) + "\n"


class Budget:
    """Seconds left of the run; a step runs only when its estimate fits."""

    def __init__(self, seconds: float):
        self.end = time.monotonic() + seconds

    def left(self) -> float:
        return self.end - time.monotonic()

    def allows(self, name: str, estimate: float, summary: Summary) -> bool:
        if self.left() >= estimate:
            return True
        summary.add(name, "skipped", note=f"needs about {estimate:.0f} s, {max(self.left(), 0):.0f} s left")
        return False


class Tee(io.TextIOBase):
    """Writes to the terminal and to ``check.log``."""

    def __init__(self, *streams):
        self.streams = streams

    def write(self, text: str) -> int:
        for s in self.streams:
            s.write(text)
        return len(text)

    def flush(self) -> None:
        for s in self.streams:
            s.flush()


def sync(device) -> None:
    import torch

    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def best_of(fn: Callable[[], object], repeats: int, device) -> tuple[float, object]:
    """Fastest wall seconds of ``repeats`` calls (the device synchronised around each) and the last result."""
    best, out = np.inf, None
    for _ in range(repeats):
        sync(device)
        t0 = time.perf_counter()
        out = fn()
        sync(device)
        best = min(best, time.perf_counter() - t0)
    return best, out


# ------------------------------------------------------------------ steps


def machine(device, sizes: Sizes, summary: Summary) -> dict[str, float]:
    """The machine's lines and the measured peaks: GFLOP/s for fp32 / bf16 matmul, GB/s for a copy, numpy's GFLOP/s."""
    import torch

    from gemm_peak import blas_kernel, measure_peak, torch_gemm_rate

    dev = torch.device(device)
    lines = [f"python {platform.python_version()}, torch {torch.__version__}, numpy {np.__version__}, "
             f"{os.cpu_count()} CPU cores, BLAS {blas_kernel()}"]
    if dev.type == "cuda":
        props = torch.cuda.get_device_properties(dev)
        lines.append(f"GPU {props.name}, {props.total_memory / 2**30:.1f} GiB, {props.multi_processor_count} "
                     f"multiprocessors, CUDA {torch.version.cuda}")
        with contextlib.suppress(OSError, subprocess.SubprocessError):
            smi = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version,clocks.max.sm,memory.total",
                                  "--format=csv,noheader"], capture_output=True, text=True, timeout=20)
            lines.append(f"nvidia-smi: {smi.stdout.strip()}")
    else:
        lines.append(f"no GPU: the device steps ran on torch's {dev.type} tensors (a check of the script, not figures)")
    side = sizes.peak_side
    peaks = {
        "fp32": torch_gemm_rate(str(dev), "float32", side, side, side, repeats=5),
        "bf16": torch_gemm_rate(str(dev), "bfloat16", side, side, side, repeats=5),
    }
    n = side * side * 8  # float32 elements: 256 MiB at 8,192
    a = torch.empty(n, dtype=torch.float32, device=dev)
    b = torch.empty_like(a)
    seconds, _ = best_of(lambda: b.copy_(a), 5, dev)
    peaks["copy"] = 2 * a.numel() * 4 / seconds / 1e9  # bytes read and written
    peaks["numpy"] = measure_peak(m=4096, k=sizes.dim, n=4096).float32
    a = b = None  # the device's memory back
    lines.append(f"measured peaks on {dev}: matmul {side}³ fp32 (TF32 off) {peaks['fp32']:,.0f} GFLOP/s, bf16 "
                 f"{peaks['bf16']:,.0f} GFLOP/s; copy {peaks['copy']:,.0f} GB/s (read + written); numpy float32 "
                 f"GEMM (4,096 × {sizes.dim} @ {sizes.dim} × 4,096) on the CPU {peaks['numpy']:,.0f} GFLOP/s")
    summary.machine.extend(lines)
    for line in lines:
        print(line, flush=True)
    return peaks


def within(cmd: list[str], seconds: float, log: Path, **kw) -> subprocess.CompletedProcess:
    """``cmd``'s run, stopped after ``seconds``; its command line and output written to ``log`` either way."""
    try:
        done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=max(seconds, 1), **kw)
    except subprocess.TimeoutExpired as exc:
        out = (exc.stdout or b"").decode(errors="replace") if isinstance(exc.stdout, bytes) else exc.stdout or ""
        err = (exc.stderr or b"").decode(errors="replace") if isinstance(exc.stderr, bytes) else exc.stderr or ""
        done = subprocess.CompletedProcess(cmd, -1, out, err + f"\nstopped after {seconds:.0f} s: the budget's end\n")
    log.write_text("$ " + " ".join(cmd) + "\n" + done.stdout + done.stderr)
    return done


def tests(device, logs: Path, summary: Summary, seconds: float) -> None:
    """The device tests in a pytest of their own; its output in ``pytest.log``."""
    env = {**os.environ, "VPR_EXPLORER_TEST_DEVICE": str(device)}
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *DEVICE_TESTS]
    t0 = time.perf_counter()
    done = within(cmd, seconds, logs / "pytest.log", env=env)
    last = (done.stdout.strip().splitlines() or ["no output"])[-1]
    summary.add("device tests", last, note=f"exit {done.returncode}, {time.perf_counter() - t0:.0f} s; pytest.log")


def gardens_point(data: Path, n: int | None) -> list[Path]:
    from bench_extraction import gardens_point_images

    return gardens_point_images(data, n)


def decode(device, paths: list[Path], sizes: Sizes, summary: Summary) -> None:
    """JPEG decode (and resize to 224²) on the device, in batches of ``sizes.batch`` and as one batch."""
    import torch
    import torch.nn.functional as F
    from torchvision.io import ImageReadMode, decode_jpeg

    datas = [torch.frombuffer(bytearray(p.read_bytes()), dtype=torch.uint8) for p in paths]

    def run(batch: int, resize: bool) -> None:
        for lo in range(0, len(datas), batch):
            images = decode_jpeg(datas[lo : lo + batch], mode=ImageReadMode.RGB, device=device)
            if resize:
                x = torch.stack(images).float()
                F.interpolate(x, size=(224, 224), mode="bilinear", antialias=True, align_corners=False)

    for batch in (sizes.batch, len(datas)):
        for resize in (False, True):
            run(batch, resize)  # warm-up: the decoder's buffers, the kernels
            seconds, _ = best_of(lambda: run(batch, resize), sizes.repeats, device)
            what = "decode + resize to 224²" if resize else "decode"
            summary.add(f"JPEG {what} on {device}, batches of {batch}", f"{len(datas) / seconds:,.0f} img/s",
                        note=f"{len(datas)} GardensPoint JPEGs, bytes read beforehand")


def extraction(device, paths: list[Path], sizes: Sizes, peaks: dict[str, float], summary: Summary) -> None:
    """``bench_extraction.bench`` per model and precision: end-to-end with CPU and device decoding beside the
    bare forward pass; the device decoder's pixels against PIL's (``bench_extraction.pixel_differences``)."""
    from bench_extraction import batch_flops, bench, make_extractor, pixel_differences

    from vpr_explorer.settings import default_workers

    workers, n = default_workers(), len(paths)
    with tempfile.TemporaryDirectory() as weights:
        for name in sizes.extractors:
            for precision in PRECISIONS:
                extractor, note = make_extractor(name, str(device), precision, Path(weights))
                label = f"{name} {precision}"
                if name == sizes.extractors[0] and precision == PRECISIONS[0]:
                    for key, (worst, share) in pixel_differences(extractor, paths).items():
                        summary.add(f"{'JPEG decode' if key == 'decode' else 'resize'} on {device} against PIL's",
                                    f"largest difference {worst} levels", note=f"{100 * share:.2f}% of values differ")
                best, out = bench(extractor, paths, sizes.batch, workers, sizes.repeats, decodes=("cpu", "device"))
                flops = batch_flops(extractor, paths, sizes.batch) / min(sizes.batch, n) * n
                peak = peaks["fp32" if precision == "fp32" else "bf16"]
                summary.add(f"{label}: bare forward", f"{n / best['bare']:,.0f} img/s",
                            note=f"{flops / best['bare'] / 1e9:,.0f} GFLOP/s = "
                                 f"{100 * flops / best['bare'] / 1e9 / peak:.0f}% of the {precision} matmul peak"
                                 + (f"; {note}" if note else ""))
                for how in ("cpu", "device"):
                    seconds = best[f"end_to_end:{how}"]
                    summary.add(f"{label}: end-to-end, JPEGs decoded on the {'CPU' if how == 'cpu' else 'device'}",
                                f"{n / seconds:,.0f} img/s", f"{n / best['bare']:,.0f} img/s (bare)",
                                f"{best['bare'] / seconds:.2f}", f"≥ {EXTRACTION_GOAL}",
                                f"{workers} reading threads, batch {sizes.batch}, into a fresh cache")
                cosine = np.einsum("ij,ij->i", out["cpu"].astype(np.float64), out["device"].astype(np.float64))
                summary.add(f"{label}: cosine, device vs CPU decode", f"least {cosine.min():.6f}",
                            note=f"median {np.median(cosine):.7f}; the tests require > 0.9999")
                extractor = None  # the model's memory back


def statistics(device, sizes: Sizes, summary: Summary) -> None:
    """The closed form on the device beside numpy on every core."""
    from bench_negative_stats import structured_descriptors

    from vpr_explorer.method.stats import negative_stats

    d, labels = structured_descriptors(sizes.stats_n, sizes.dim, sizes.stats_places, 0)
    negative_stats(d[:1000], labels[:1000] % 10, device=device)  # warm-up: the device's context, cuBLAS
    t_np, ref = best_of(lambda: negative_stats(d, labels), sizes.repeats, "cpu")
    t_dev, got = best_of(lambda: negative_stats(d, labels, device=device), sizes.repeats, device)
    summary.add(f"closed-form statistics {sizes.stats_n:,} × {sizes.dim:,}, {sizes.stats_places:,} places",
                f"{t_dev:.2f} s on {device}", f"{t_np:.2f} s numpy, {os.cpu_count()} cores", f"numpy / device {t_np / t_dev:.1f}",
                note=f"largest Δμ {np.abs(got.mu - ref.mu).max():.1e}, Δσ {np.abs(got.sigma - ref.sigma).max():.1e}")


def protocol(device, sizes: Sizes, peaks: dict[str, float], budget: Budget, summary: Summary) -> None:
    """The 50-split paper protocol with the device, beside both floors; identical numbers to the numpy pass's."""
    import torch

    from bench_nordland_scale import full_similarity_pass, nordland_like

    from vpr_explorer.protocols.options import ProtocolOptions
    from vpr_explorer.protocols.scale import fast_paper_protocol

    def run(places: int, dev, d, labels, trav):
        return fast_paper_protocol(d, labels, trav, places, ProtocolOptions(runs=sizes.runs, device=dev))

    small = nordland_like(sizes.check_places, sizes.dim, 1)
    on_device = run(sizes.check_places, device, *small)
    same = on_device.same_numbers(run(sizes.check_places, None, *small))
    summary.add(f"paper protocol {len(small[0]):,} × {sizes.dim}, {sizes.runs} splits: device vs numpy pass",
                "identical numbers" if same else "NUMBERS DIFFER", goal="identical")

    d, labels, trav = nordland_like(sizes.places, sizes.dim, 0)
    n = len(d)
    flops = float(n) ** 2 * sizes.dim  # each unordered pair once
    t_floor, _ = best_of(lambda: full_similarity_pass(d), 1, "cpu")
    xt = torch.from_numpy(d).to(device)

    def device_floor():
        block, total = 8192, 0.0
        for i in range(0, n, block):
            for j in range(i, n, block):
                total += float((xt[i : i + block] @ xt[j : j + block].T)[0, 0])
        return total

    from vpr_explorer.method.stats import ieee_float32

    with ieee_float32():
        device_floor()
        t_dev_floor, _ = best_of(device_floor, sizes.repeats, device)
    xt = None
    run(sizes.places, device, d, labels, trav)  # warm-up: the device's buffers
    from bench_nordland_scale import _time_phases

    phases = _time_phases()  # the protocol's steps timed from here on (wall s, CPU s, calls)
    t_protocol, ev = best_of(lambda: run(sizes.places, device, d, labels, trav), 1, device)
    steps = ", ".join(f"{name} {wall:.2f}" for name, (wall, _, _) in sorted(phases.items(), key=lambda kv: -kv[1][0]))
    summary.add("paper protocol: its steps, wall s (steps beside each other overlap)", steps)
    summary.add(f"paper protocol {n:,} × {sizes.dim:,}, {sizes.runs} splits, on {device}", f"{t_protocol:.2f} s",
                f"{t_floor:.2f} s numpy floor pass ({os.cpu_count()} cores)", f"{t_protocol / t_floor:.2f}× the floor",
                f"≤ {PROTOCOL_GOAL_S:g} s",
                f"device floor (the N²·D products, fp32) {t_dev_floor:.2f} s = {flops / t_dev_floor / 1e9:,.0f} GFLOP/s, "
                f"{100 * flops / t_dev_floor / 1e9 / peaks['fp32']:.0f}% of its fp32 peak")
    if budget.allows("paper protocol at full size: device vs numpy pass", 6 * t_floor, summary):
        same = ev.same_numbers(run(sizes.places, None, d, labels, trav))
        summary.add(f"paper protocol {n:,} × {sizes.dim:,}: device vs numpy pass",
                    "identical numbers" if same else "NUMBERS DIFFER", goal="identical")


def million(device, logs: Path, summary: Summary, seconds: float) -> None:
    """``bench_million.py --skip-eval --device``: the refit after a group/step change at a million images."""
    cmd = [sys.executable, str(ROOT / "benchmarks" / "bench_million.py"), "--skip-eval", "--device", str(device),
           "--out", str(Path(tempfile.gettempdir()) / "vpr_million")]
    done = within(cmd, seconds, logs / "million.log")
    change = refit_time(done.stdout)
    summary.add(f"group/step change at 1,000,000 images, the fit's products on {device}",
                f"{change[1]} s" if change else f"exit {done.returncode}: see million.log",
                goal=f"≤ {REFIT_GOAL_S:g} s", note=f"to {change[0]}; million.log" if change else "million.log")


def refit_time(report: str) -> tuple[str, str] | None:
    """``(what it moved to, seconds)`` of the group/step change in ``bench_million.py``'s report, or None."""
    for line in report.splitlines():
        found = re.search(r"group/step change to (.*?\)) +([\d.]+) s", line)
        if found:
            return found[1], found[2]
    return None


# ------------------------------------------------------------------ main


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda", help="torch device of the device steps (default cuda)")
    parser.add_argument("--logs", type=Path, default=Path(os.environ.get("OUT", tempfile.gettempdir())) / "gpu_check",
                        help="folder for summary.md and the logs (default $OUT/gpu_check)")
    parser.add_argument("--data", type=Path, default=None, help="datasets folder (default $VPR_EXPLORER_DATA)")
    parser.add_argument("--budget", type=float, default=330.0, help="seconds for every step together")
    parser.add_argument("--quick", action="store_true", help="small sizes: a check of the script itself, on any device")
    parser.add_argument("--skip", nargs="*", default=[],
                        choices=("tests", "decode", "extraction", "statistics", "protocol", "million"))
    args = parser.parse_args(argv)

    import torch

    from vpr_explorer import settings

    if torch.device(args.device).type == "cuda" and not torch.cuda.is_available():
        parser.error(f"--device {args.device}: torch sees no CUDA GPU here; give --device cpu to check the script")
    data = args.data or settings.data_root()
    if data is None:
        parser.error(f"give --data or set {settings.DATA_ENV}")
    sizes = Sizes.quick() if args.quick else Sizes()
    args.logs.mkdir(parents=True, exist_ok=True)
    budget, summary = Budget(args.budget), Summary()
    device = torch.device(args.device)
    with open(args.logs / "check.log", "w") as log, contextlib.redirect_stdout(Tee(sys.stdout, log)):
        print("$ python benchmarks/gpu_check.py " + " ".join(argv if argv is not None else sys.argv[1:]), flush=True)
        peaks = machine(device, sizes, summary)
        paths = gardens_point(Path(data), sizes.images)
        # estimates on an H100 from the steps' sizes; ``--quick`` runs are seconds each
        steps: list[tuple[str, float, Callable[[], None]]] = [
            ("tests", 90, lambda: tests(device, args.logs, summary, budget.left() - 5)),
            ("decode", 15, lambda: decode(device, paths, sizes, summary)),
            ("extraction", 80, lambda: extraction(device, paths, sizes, peaks, summary)),
            ("statistics", 20, lambda: statistics(device, sizes, summary)),
            ("protocol", 60, lambda: protocol(device, sizes, peaks, budget, summary)),
        ]
        if sizes.million:
            steps.append(("million", 120, lambda: million(device, args.logs, summary, budget.left() - 5)))
        for name, estimate, step in steps:
            if name in args.skip or not budget.allows(name, 0 if args.quick else estimate, summary):
                continue
            print(f"\n== {name} ({budget.left():.0f} s left)", flush=True)
            t0 = time.perf_counter()
            try:
                step()
            except Exception as exc:  # one failed step is reported; the others still run
                summary.add(name, f"FAILED: {type(exc).__name__}: {str(exc)[:300]}")
            print(f"   {name}: {time.perf_counter() - t0:.1f} s", flush=True)
            (args.logs / "summary.md").write_text(summary.markdown())  # after each step: a run cut short keeps it
        (args.logs / "summary.md").write_text(summary.markdown())
        print("\n" + summary.markdown(), flush=True)
    failed = any(r[1].startswith(("FAILED", "NUMBERS DIFFER")) for r in summary.rows)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
