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
the same, the descriptors are meaningless, and the table says so.

``--decode device`` times the pipeline with JPEGs decoded and resized on the model's device
(:mod:`vpr_explorer.descriptors.device_decode`), ``both`` the two paths side by side, one
row each, and then, per torch extractor with a recipe, how far the device path is from the
CPU path: the min and mean cosine between their descriptors of every image, the max abs
difference of the decoded pixels (torchvision on the device vs PIL) and of the resized
8-bit levels (the device resize vs PIL's, from the same PIL-decoded pixels) with the share
of values that differ. Extractors without a recipe (``pixels``) run on the CPU path only.
Run::

    python benchmarks/bench_extraction.py --data /work/shared/datasets --n 192
    python benchmarks/bench_extraction.py --n 600 --device cuda --batch-size 64
    python benchmarks/bench_extraction.py --device cuda --decode both --extractors efficientnet-lite0
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


def bench(extractor, paths: list[Path], batch_size: int, workers: int, repeats: int,
          decodes: tuple[str, ...] = ("cpu",)) -> tuple[dict[str, float], dict[str, np.ndarray]]:
    """Best-of-``repeats`` seconds for decoding (1 thread), bare forward, end-to-end and cached runs; and descriptors.

    End-to-end runs once per decode path (``end_to_end:cpu``, ``end_to_end:device``), the
    cached run after the first path's. The runs alternate within each repeat, and the
    fastest of each is kept, so that load from other processes on a shared machine hits
    them alike. The descriptors are each path's last end-to-end result.
    """
    start = time.perf_counter()
    decoded = [extractor.load(p) for p in paths]
    decode = time.perf_counter() - start
    batches = [np.stack(decoded[i : i + batch_size]) for i in range(0, len(decoded), batch_size)]
    for batch in batches[:2]:
        extractor.forward(batch)  # warm-up: first-call kernel selection is not throughput
    # Warm the pipeline too (thread pool, allocator, cuDNN plans for a last partial batch).
    for path in decodes:
        extract_descriptors(paths[: batch_size + 1], extractor, batch_size=batch_size, workers=workers, decode=path)
    _sync(extractor)

    best = {"decode": decode, "bare": np.inf, "cached": np.inf, **{f"end_to_end:{d}": np.inf for d in decodes}}
    results: dict[str, np.ndarray] = {}
    for _ in range(repeats):
        start = time.perf_counter()
        for batch in batches:
            extractor.forward(batch)
        _sync(extractor)
        best["bare"] = min(best["bare"], time.perf_counter() - start)

        for path in decodes:
            with tempfile.TemporaryDirectory() as tmp:
                cache = DescriptorCache(Path(tmp))
                start = time.perf_counter()
                fresh = extract_descriptors(paths, extractor, cache=cache, batch_size=batch_size, workers=workers,
                                            decode=path)
                best[f"end_to_end:{path}"] = min(best[f"end_to_end:{path}"], time.perf_counter() - start)
                results[path] = fresh
                if path != decodes[0]:
                    continue
                start = time.perf_counter()
                cached = extract_descriptors(paths, extractor, cache=cache, batch_size=batch_size, workers=workers,
                                             decode=path)
                best["cached"] = min(best["cached"], time.perf_counter() - start)
            if not np.array_equal(fresh, cached):
                raise SystemExit(f"{extractor.name}: the cached descriptors differ from the fresh ones")
    return best, results


def pixel_differences(extractor, paths: list[Path]) -> dict[str, tuple[int, float]]:
    """``{"decode": (max abs, share differing), "resize": (...)}`` of the device path against PIL's, over the JPEGs.

    decode: torchvision's ``decode_jpeg`` on the extractor's device vs PIL's RGB pixels;
    resize: ``device_decode.resize_levels`` vs PIL's bilinear resize, both from PIL's pixels.
    """
    import torch
    from PIL import Image
    from torchvision.io import ImageReadMode, decode_jpeg

    from vpr_explorer.descriptors.device_decode import device_decodable, resize_levels

    recipe, device = extractor.recipe, extractor.device
    worst = {"decode": 0, "resize": 0}
    differing = {"decode": 0, "resize": 0}
    values = {"decode": 0, "resize": 0}
    for path in paths:
        data = path.read_bytes()
        if not device_decodable(data):
            continue
        with Image.open(path) as image:
            rgb = image.convert("RGB")
        pil = np.asarray(rgb)
        got = decode_jpeg(torch.frombuffer(bytearray(data), dtype=torch.uint8), mode=ImageReadMode.RGB, device=device)
        size = recipe.output_size(rgb.width, rgb.height)
        want = np.asarray(rgb.resize(size, Image.BILINEAR) if size != rgb.size else rgb)
        x = torch.from_numpy(pil.transpose(2, 0, 1).copy())[None].to(device)
        levels = resize_levels(x, recipe)[0]
        for key, a, b in (("decode", pil, got.permute(1, 2, 0).cpu().numpy()),
                          ("resize", want, levels.permute(1, 2, 0).cpu().numpy())):
            diff = np.abs(a.astype(np.int16) - b.astype(np.int16))
            worst[key] = max(worst[key], int(diff.max()))
            differing[key] += int(np.count_nonzero(diff))
            values[key] += diff.size
    return {key: (worst[key], differing[key] / max(values[key], 1)) for key in worst}


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
    parser.add_argument("--decode", default="cpu", choices=("cpu", "device", "both"),
                        help="JPEG decoding of the end-to-end run: PIL in threads (cpu), torchvision on the model's "
                             "device (device), or both, one row each, with the cosine and pixel differences between them")
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
            has_recipe = getattr(extractor, "recipe", None) is not None
            decodes = {"cpu": ("cpu",), "device": ("device",), "both": ("cpu", "device")}[args.decode]
            if not has_recipe:
                decodes = ("cpu",)
                if args.decode != "cpu":
                    note = ", ".join(filter(None, [note, "no device recipe"]))
            t, results = bench(extractor, paths, args.batch_size, args.workers, args.repeats, decodes)
            n = len(paths)
            device = str(getattr(extractor, "device", "cpu")).replace(":0", "")
            precision = getattr(extractor, "precision", None)
            if precision is not None and precision != "fp32":
                note = ", ".join(filter(None, [note, str(precision)]))
            for path in decodes:
                seconds = t[f"end_to_end:{path}"]
                # pixels' forward is a reshape: the ratio means nothing there
                ratio = f"{t['bare'] / seconds:.2f}" if t["bare"] > 0.05 * seconds else "n/a"
                row_note = note if args.decode == "cpu" else ", ".join(filter(None, [f"{path} decode", note]))
                cached = f"{t['cached']:>10.3f}" if path == decodes[0] else f"{'':>10}"
                print(
                    f"{name:<20}{device:>8}{n / seconds:>18.1f}{n / t['bare']:>16.1f}{ratio:>7}"
                    f"{n / t['decode']:>14.1f}{seconds:>11.3f}{cached}  {row_note}",
                    flush=True,
                )
            if len(results) == 2:
                cosines = np.sum(results["cpu"].astype(np.float64) * results["device"], axis=1)
                worst = int(np.argmin(cosines))
                diffs = pixel_differences(extractor, paths)
                print(f"{'':<20}device vs cpu decode: cosine min {cosines.min():.8f} ({paths[worst].name}), "
                      f"mean {cosines.mean():.8f}; pixels max abs diff (share differing): decode "
                      f"{diffs['decode'][0]} ({diffs['decode'][1]:.2%}), resize {diffs['resize'][0]} "
                      f"({diffs['resize'][1]:.2%})", flush=True)
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
