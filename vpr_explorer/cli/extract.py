"""``vpr-explorer extract``: fill the descriptor cache for a dataset, with local threads or on Ray.

Without ``--ray`` the local extractor runs (:func:`~vpr_explorer.descriptors.extract_descriptors`:
decoding threads beside the model); with ``--ray ADDRESS|local`` the job runs on a Ray
cluster (:mod:`vpr_explorer.descriptors.distributed`, which imports ray only when a job
starts). Either way the vectors land in the same content-keyed cache, so whichever runs
next (the other kind, ``evaluate``, the app) finds them there. The last line gives
images/s and how many were already cached.

``--descriptor hub:DIR[:ENTRY]`` runs a torch.hub repository's model
(:mod:`vpr_explorer.descriptors.hub`), with ``--hub-arg key=value`` (repeatable),
``--hub-size W H`` or ``--hub-short-side N``, and ``--hub-normalisation``; these are refused
with any other descriptor.

``--decode device`` decodes and resizes JPEGs on the model's device
(:mod:`vpr_explorer.descriptors.device_decode`); ``auto`` (the default) does so when a torch
model runs on a GPU. Local extraction only: Ray actors decode with ``auto``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from vpr_explorer.cli.common import CACHE_HELP, DEFAULT_DESCRIPTOR, add_hub_args, default_note, hub_options
from vpr_explorer.data.layouts import Layout
from vpr_explorer.errors import VPRInputError


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``extract``'s options: the dataset, the extractor, where it runs."""
    from vpr_explorer.descriptors.distributed import LOCAL, SHARD_IMAGES

    p.add_argument("--dataset", required=True, help="dataset folder (or a manifest .csv), or 'demo'")
    p.add_argument("--layout", choices=[x.value for x in Layout], default=Layout.AUTO.value,
                   help="how the dataset is laid out, as for evaluate; auto detects it")
    p.add_argument("--descriptor", default=DEFAULT_DESCRIPTOR,
                   help="descriptor name, or hub:DIR[:ENTRY] for a model of a local torch.hub repository")
    add_hub_args(p)
    p.add_argument("--cache-dir", type=Path, default=None, help=CACHE_HELP)
    p.add_argument("--dtype", choices=["float32", "float16"], default="float32",
                   help="storage dtype of the cached vectors; float16 halves the disk")
    p.add_argument("--precision", choices=["fp32", "bf16", "fp16"], default=None,
                   help="arithmetic of a torch model's forward pass (default: fp32; bf16/fp16 have cache keys of "
                        "their own; fp16 needs a GPU)")
    p.add_argument("--decode", choices=["auto", "cpu", "device"], default=None,
                   help="where JPEGs are decoded and resized: cpu (PIL in the decoding threads), device (torchvision "
                        "on the model's device, nvJPEG on a GPU; other formats stay on the CPU; same descriptors "
                        "within float rounding, same cache), auto: device when a torch model runs on a GPU, else "
                        "cpu; local extraction only" + default_note("auto"))
    p.add_argument("--batch-size", type=int, default=32, help="images per forward pass")
    p.add_argument("--ray", default=None, metavar="ADDRESS|local",
                   help=f"run on Ray: '{LOCAL}' starts an instance on this machine, HOST:PORT joins a cluster "
                        "('ray start --head' prints it), 'auto' the cluster this machine joined; needs "
                        "pip install \".[ray]\"")
    p.add_argument("--shard-images", type=int, default=None,
                   help="with --ray: images an actor forwards per call and writes as one cache shard; a killed job "
                        "loses at most one call per actor" + default_note(SHARD_IMAGES))
    p.add_argument("--actors", type=int, default=None,
                   help="with --ray: model actors (default: one per GPU, each with num_gpus=1; else one per node)")


def run(args: argparse.Namespace) -> int:
    """Extract into the cache; print images/s and how many were cached already.

    Returns:
        0 (bad input raises ``VPRInputError``).
    """
    from vpr_explorer.pipeline import open_dataset
    from vpr_explorer.settings import check_cache_root

    if args.batch_size < 1:
        raise VPRInputError(f"--batch-size {args.batch_size}: must be 1 or more")
    if args.ray is None and (args.actors is not None or args.shard_images is not None):
        raise VPRInputError("--actors and --shard-images apply with --ray only: add --ray local (or an address)")
    if args.ray is not None and args.decode is not None:
        raise VPRInputError("--decode applies to local extraction only (Ray actors decode with auto): drop it or --ray")
    check_cache_root(args.cache_dir)
    dataset = open_dataset(args.dataset, args.layout)
    paths = list(dataset.image_paths)
    options = {} if args.precision is None else {"precision": args.precision}
    options.update(hub_options(args))
    line = _local(args, paths, options) if args.ray is None else _on_ray(args, paths, options)
    print(line, flush=True)
    return 0


class _Bar:
    """A progress bar of images on stderr that remembers how many were done at its first call (the cached ones).

    :meth:`close` ends its line before any error line.
    """

    def __init__(self, desc: str) -> None:
        self.desc = desc
        self.bar = None
        self.first: int | None = None

    def __call__(self, done: int, total: int) -> None:
        if self.first is None:
            self.first = done
        if self.bar is None:
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc=self.desc, unit="img", file=sys.stderr, leave=False, dynamic_ncols=True)
        self.bar.update(done - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _local(args: argparse.Namespace, paths: list[Path], options: dict) -> str:
    """Extract with this machine's threads; the line to print."""
    from vpr_explorer.descriptors import DescriptorCache, extract_descriptors, get_extractor

    cache = DescriptorCache(args.cache_dir, dtype=args.dtype)
    extractor = get_extractor(args.descriptor, **options)
    progress = _Bar(f"{args.descriptor} (local)")
    start = time.perf_counter()
    try:
        extract_descriptors(paths, extractor, cache=cache, batch_size=args.batch_size, progress=progress,
                            dtype=args.dtype, decode=args.decode or "auto")
    finally:
        progress.close()
    seconds = time.perf_counter() - start
    cached = progress.first or 0
    rate = (len(paths) - cached) / seconds if seconds > 0 else 0.0
    return (f"{len(paths)} images: {cached} already cached, {len(paths) - cached} computed locally in "
            f"{seconds:.1f} s, {rate:.1f} images/s")


def _on_ray(args: argparse.Namespace, paths: list[Path], options: dict) -> str:
    """Extract on the Ray cluster ``--ray`` names; the line to print."""
    from vpr_explorer.descriptors.distributed import extract_on_ray

    progress = _Bar(f"{args.descriptor} (Ray)")
    try:
        job = extract_on_ray(paths, args.descriptor, options=options, cache_root=args.cache_dir, dtype=args.dtype,
                             address=args.ray, batch_size=args.batch_size, actors=args.actors, progress=progress,
                             **({} if args.shard_images is None else {"shard_images": args.shard_images}))
    finally:
        progress.close()
    return job.describe()
