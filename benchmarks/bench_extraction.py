"""Descriptor extraction throughput: end-to-end pipeline vs the bare forward pass vs the cache.

For each extractor, on the same GardensPoint images and batch size:

* **end-to-end**: ``extract_descriptors`` into a fresh temporary cache (hash, decode,
  resize, forward, normalise, cache write);
* **bare forward**: ``extractor.forward`` alone on batches decoded beforehand (untimed);
  on a GPU this includes the copy of the batch to it and of the descriptors back;
* **cached**: ``extract_descriptors`` again, every image now a cache hit.

The pipeline's goal is end-to-end >= 0.8x bare forward: decoding should hide behind
the model. Against the machine's limit, each torch model's bare forward also
prints its achieved rate, the convolution and matrix flops torch counts for one batch
(``torch.utils.flop_counter``) times the batches over the time, as a share of a GEMM peak
measured in the same process: numpy's float32 GEMM on the CPU (``gemm_peak``, which names
the BLAS kernel), torch's matmul in the run's precision on a GPU. Models whose weights are not installed (AlexNet, CosPlace, EigenPlaces
without a download) run with random weights written to a temporary file: the speed is
the same, the descriptors are meaningless, and the table says so. Run::

    python benchmarks/bench_extraction.py --data /work/shared/datasets --n 192
    python benchmarks/bench_extraction.py --n 600 --device cuda --batch-size 64
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from vpr_explorer import settings
from vpr_explorer.data.traversals import natural_key
from vpr_explorer.descriptors import DescriptorCache, available_extractors, extract_descriptors, get_extractor

DEFAULT_EXTRACTORS = ("pixels", "efficientnet-lite0", "alexnet-conv3")
TORCH_EXTRACTORS = ("efficientnet-lite0", "alexnet-conv3", "cosplace", "eigenplaces")
RANDOM_WEIGHTS_OK = ("alexnet-conv3", "cosplace", "eigenplaces")


def gardens_point_images(data: Path, n: int | None) -> list[Path]:
    """The first ``n`` GardensPoint frames, traversal by traversal."""
    root = data / "GardensPointWalking"
    if not root.is_dir():
        raise SystemExit(f"{root}: not found; pass --data or set {settings.DATA_ENV} to the datasets folder")
    paths = [
        p
        for traversal in ("day_left", "day_right", "night_right")
        for p in sorted((root / traversal).glob("*.jpg"), key=lambda p: natural_key(p.name))
    ]
    return paths[:n] if n else paths


def random_weights(name: str, folder: Path) -> Path:
    """A random-initialised checkpoint in the official format of ``name``'s default model."""
    import torch
    import torchvision

    torch.manual_seed(0)
    path = folder / f"{name}-random.pth"
    if name == "alexnet-conv3":
        torch.save(torchvision.models.alexnet(weights=None).state_dict(), path)
    else:
        from vpr_explorer.descriptors.gem_resnet import GeoLocalizationNet

        torch.save(GeoLocalizationNet("ResNet50", 2048).state_dict(), path)
    return path


def make_extractor(name: str, device: str, precision: str, weights_dir: Path):
    """``(extractor, note)``; the note says when the weights are random."""
    options: dict[str, object] = {}
    if name in TORCH_EXTRACTORS:
        options.update(device=device, precision=precision)
    note = ""
    if name in RANDOM_WEIGHTS_OK and available_extractors()[name] is not None:
        options["weights"] = random_weights(name, weights_dir)
        note = "random weights"
    return get_extractor(name, **options), note


def _sync(extractor) -> None:
    device = getattr(extractor, "device", None)
    if device is not None and device.type == "cuda":
        import torch

        torch.cuda.synchronize(device)


def bench(extractor, paths: list[Path], batch_size: int, workers: int, repeats: int) -> dict[str, float]:
    """Best-of-``repeats`` seconds for decoding (1 thread), bare forward, end-to-end and cached runs.

    The three runs alternate within each repeat, and the fastest of each is kept, so
    that load from other processes on a shared machine hits them alike.
    """
    start = time.perf_counter()
    decoded = [extractor.load(p) for p in paths]
    decode = time.perf_counter() - start
    batches = [np.stack(decoded[i : i + batch_size]) for i in range(0, len(decoded), batch_size)]
    for batch in batches[:2]:
        extractor.forward(batch)  # warm-up: first-call kernel selection is not throughput
    # Warm the pipeline too (thread pool, allocator, cuDNN plans for a last partial batch).
    extract_descriptors(paths[: batch_size + 1], extractor, batch_size=batch_size, workers=workers)
    _sync(extractor)

    best = {"decode": decode, "bare": np.inf, "end_to_end": np.inf, "cached": np.inf}
    for _ in range(repeats):
        start = time.perf_counter()
        for batch in batches:
            extractor.forward(batch)
        _sync(extractor)
        best["bare"] = min(best["bare"], time.perf_counter() - start)

        with tempfile.TemporaryDirectory() as tmp:
            cache = DescriptorCache(Path(tmp))
            start = time.perf_counter()
            fresh = extract_descriptors(paths, extractor, cache=cache, batch_size=batch_size, workers=workers)
            best["end_to_end"] = min(best["end_to_end"], time.perf_counter() - start)
            start = time.perf_counter()
            cached = extract_descriptors(paths, extractor, cache=cache, batch_size=batch_size, workers=workers)
            best["cached"] = min(best["cached"], time.perf_counter() - start)
        if not np.array_equal(fresh, cached):
            raise SystemExit(f"{extractor.name}: the cached descriptors differ from the fresh ones")
    return best


def batch_flops(extractor, paths: list[Path], batch_size: int) -> int:
    """Flops torch counts for one forward pass of a full batch."""
    from gemm_peak import torch_flops

    batch = np.stack([extractor.load(p) for p in paths[:batch_size]])
    return torch_flops(lambda: extractor.forward(batch))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--data", type=Path, default=settings.data_root(), help=f"datasets folder (default ${settings.DATA_ENV})"
    )
    parser.add_argument("--n", type=int, default=None, help="use only the first N images (default: all 600)")
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--workers", type=int, default=None, help="decoding threads (default: one per core, up to 8)")
    parser.add_argument("--repeats", type=int, default=3, help="runs of each measurement; the fastest is reported")
    parser.add_argument("--device", default="auto", help="auto (GPU when there is one), cpu, cuda, cuda:N")
    parser.add_argument("--precision", default="fp32", choices=("fp32", "bf16", "fp16"))
    parser.add_argument(
        "--extractors", nargs="+", default=list(DEFAULT_EXTRACTORS),
        choices=("pixels", *TORCH_EXTRACTORS),
    )
    args = parser.parse_args(argv)
    if args.data is None:
        parser.error(f"give --data or set {settings.DATA_ENV}")

    paths = gardens_point_images(args.data, args.n)
    if args.workers is None:
        from vpr_explorer.settings import default_workers

        args.workers = default_workers()
    import torch  # to report what the forward pass ran on

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from gemm_peak import measure_peak, share, torch_gemm_rate

    cpu_peak = measure_peak()

    print("$ python " + " ".join(shlex.quote(a) for a in [sys.argv[0], *(argv if argv is not None else sys.argv[1:])]))
    gpu = f", GPU {torch.cuda.get_device_name()}" if torch.cuda.is_available() else ", no GPU"
    print(
        f"{len(paths)} GardensPoint images, batch {args.batch_size}, {args.workers} decode threads, "
        f"torch {torch.__version__} with {torch.get_num_threads()} CPU threads{gpu}; "
        f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (other processes skew the timings)"
    )
    for line in cpu_peak.lines():
        print(line)
    gpu_peak: dict[str, float] = {}
    header = (
        f"{'extractor':<20}{'device':>8}{'end-to-end img/s':>18}{'bare fwd img/s':>16}{'ratio':>7}"
        f"{'decode img/s':>14}{'extract s':>11}{'cached s':>10}  note"
    )
    print(header)
    print("-" * len(header))
    with tempfile.TemporaryDirectory() as weights_dir:
        for name in args.extractors:
            extractor, note = make_extractor(name, args.device, args.precision, Path(weights_dir))
            t = bench(extractor, paths, args.batch_size, args.workers, args.repeats)
            n = len(paths)
            device = str(getattr(extractor, "device", "cpu")).replace(":0", "")
            precision = getattr(extractor, "precision", None)
            if precision is not None and precision != "fp32":
                note = ", ".join(filter(None, [note, str(precision)]))
            # pixels' forward is a reshape: the ratio means nothing there
            ratio = f"{t['bare'] / t['end_to_end']:.2f}" if t["bare"] > 0.05 * t["end_to_end"] else "n/a"
            print(
                f"{name:<20}{device:>8}{n / t['end_to_end']:>18.1f}{n / t['bare']:>16.1f}{ratio:>7}"
                f"{n / t['decode']:>14.1f}{t['end_to_end']:>11.3f}{t['cached']:>10.3f}  {note}",
                flush=True,
            )
            flops = batch_flops(extractor, paths, args.batch_size) if name in TORCH_EXTRACTORS else 0
            if flops:
                if device.startswith("cuda"):
                    key = f"{device} {args.precision}"
                    if key not in gpu_peak:
                        gpu_peak[key] = torch_gemm_rate(device, {"fp32": "float32", "bf16": "bfloat16",
                                                                  "fp16": "float16"}[args.precision], 8192, 8192, 8192)
                    peak, what = gpu_peak[key], f"torch {args.precision} matmul peak {gpu_peak[key]:.0f} GFLOP/s"
                else:
                    peak, what = cpu_peak.float32, "numpy float32 GEMM peak"
                per_image = flops / min(args.batch_size, n)
                print(f"{'':<20}forward: {per_image / 1e9:.2f} GFLOP/image, "
                      f"{share(per_image * n, t['bare'], peak)} ({what})", flush=True)
            del extractor
    print(
        "ratio = end-to-end / bare forward throughput (goal >= 0.8); decode = 1 thread, untimed in the others; "
        f"cached s = the same run again, every descriptor read from the cache; load average now {os.getloadavg()[0]:.1f}"
    )


if __name__ == "__main__":
    main()
