"""Extraction on Ray against the local extractor, on the same images, in one run.

For each descriptor: the local threaded extractor (``extract_descriptors``) and a Ray job
(``extract_on_ray``) on one local Ray instance of this machine, each into a cold cache of
its own, in alternating order over ``--repeats`` rounds. Prints images/s of both, the
overhead ratio (Ray over local; the goal is >= 0.8 on 2 CPUs), the start-up cost of a
Ray job (a job of one image: scheduling, starting Ray Data and the actor, loading the
model), the ratio net of that cost (what a job of many thousand images
approaches), and the largest difference between the two runs' vectors.

    python benchmarks/bench_ray.py --data $VPR_EXPLORER_DATA --n 600
    python benchmarks/bench_ray.py --data $VPR_EXPLORER_DATA --dataset nordland --n 3000

``--dataset`` picks the images: GardensPoint Walking (600 JPEGs of 960x540 and 640x360)
or Nordland 64x32 (7,152 small PNGs; a larger job, over which a job's fixed start-up
spreads thinner); ``--n`` takes the first N of them. ``--timeline`` runs one more Ray job
per descriptor and reads its phases from Ray's timeline (``ray.timeline()``): when the model
actor's first call began, how long its start-up took (the model included), and its rate
inside its calls, against the local extractor's.

With ``--gpu-rate`` it also projects the time for 1.6 million images (MSLS) at that
per-GPU rate in images/s, for a given number of GPUs.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from vpr_explorer.data.traversals import load_dataset
from vpr_explorer.descriptors import DescriptorCache, extract_descriptors, get_extractor
from vpr_explorer.descriptors.distributed import SHARD_IMAGES, connect, disconnect, extract_on_ray

MSLS_IMAGES = 1_600_000
DATASETS = {"gardens": ("GardensPointWalking", "GardensPoint"), "nordland": ("Nordland_64x32", "Nordland 64x32")}


def run_local(paths, name, batch_size):
    extractor = get_extractor(name)  # the process's shared model: built once, before timing
    with tempfile.TemporaryDirectory() as root:
        start = time.perf_counter()
        out = extract_descriptors(paths, extractor, cache=DescriptorCache(Path(root)), batch_size=batch_size)
        seconds = time.perf_counter() - start
    return seconds, np.array(out)


def run_ray(paths, name, batch_size, shard_images):
    with tempfile.TemporaryDirectory() as root:
        job = extract_on_ray(paths, name, cache_root=Path(root), batch_size=batch_size, shard_images=shard_images)
        # read back through the local extractor: every image must be cached
        hits = []
        out = extract_descriptors(paths, get_extractor(name), cache=DescriptorCache(Path(root)),
                                  batch_size=batch_size, progress=lambda d, t: hits.append(d))
    assert hits[0] == len(paths), f"only {hits[0]} of {len(paths)} cached after the Ray job"
    return job.seconds, np.array(out), job


def ray_phases(paths, name, batch_size, shard_images):
    """One more Ray job, read from Ray's timeline: ``(job s, first actor call s, actor start-up s, actor busy s)``.

    The model actor is the pool's ``__init__`` that took longest (Ray Data starts small
    actors of its own); its calls are Ray Data's ``submit`` tasks. ``None`` when this
    Ray names them otherwise.
    """
    import ray

    t0 = time.time()
    seconds = run_ray(paths, name, batch_size, shard_images)[0]
    events = [e for e in ray.timeline() if e.get("ph") == "X" and e["ts"] / 1e6 >= t0]
    inits = [e for e in events if e["name"] == "__init__"]
    calls = [e for e in events if e["name"] == "submit"]
    if not inits or not calls:
        return None
    first = min(e["ts"] for e in calls) / 1e6 - t0
    return seconds, first, max(e["dur"] for e in inits) / 1e6, sum(e["dur"] for e in calls) / 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=os.environ.get("VPR_EXPLORER_DATA"))
    parser.add_argument("--dataset", choices=list(DATASETS), default="gardens",
                        help="GardensPoint Walking (600 images) or Nordland 64x32 (7,152)")
    parser.add_argument("--n", type=int, default=400, help="the first N images of the dataset")
    parser.add_argument("--descriptors", nargs="+", default=["pixels", "efficientnet-lite0"])
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--shard-images", type=int, default=SHARD_IMAGES,
                        help=f"images per actor call and cache shard (default {SHARD_IMAGES}, as the command's)")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--timeline", action="store_true",
                        help="then one more Ray job per descriptor, its phases read from Ray's timeline")
    parser.add_argument("--gpu-rate", type=float, default=None, help="measured images/s of one GPU actor")
    parser.add_argument("--gpus", type=int, default=8, help="GPUs for the projection")
    args = parser.parse_args()
    if args.data is None:
        parser.error("give --data or set VPR_EXPLORER_DATA")
    folder, label = DATASETS[args.dataset]
    paths = list(load_dataset(args.data / folder).image_paths)[: args.n]
    cores = len(os.sched_getaffinity(0))
    import ray
    import torch

    # Ray runs its workers at niceness 15, so any other busy process starves them; the local
    # extractor runs at 0. Same priority for both, so that the ratio compares the engines.
    os.environ.setdefault("RAY_worker_niceness", "0")
    start = time.perf_counter()
    connect("local", num_cpus=cores)
    started = time.perf_counter() - start
    print(f"{len(paths)} {label} images, batch {args.batch_size}, shard {args.shard_images}, "
          f"Ray {ray.__version__} local instance on {cores} CPUs (started in {started:.1f} s, not timed), "
          f"torch {torch.__version__}, Ray workers at niceness {os.environ['RAY_worker_niceness']}, "
          f"load average {os.getloadavg()[0]:.1f} on {cores} cores")
    print(f"{'extractor':20s} {'local img/s':>11s} {'Ray img/s':>10s} {'ratio':>6s} {'Ray start s':>11s} "
          f"{'Ray net img/s':>13s} {'net ratio':>9s} {'max |Δ|':>9s}")
    try:
        for name in args.descriptors:
            local, on_ray, fixed, delta = [], [], [], 0.0
            # Untimed: the model's first passes, and the instance's start-up tail (its workers
            # start and import in the background for seconds after ray.init, which slowed a
            # first local run to a third of its rate).
            run_local(paths[: 2 * args.batch_size], name, args.batch_size)
            run_ray(paths[:1], name, args.batch_size, args.shard_images)
            for r in range(args.repeats):
                order = ("local", "ray", "start") if r % 2 == 0 else ("start", "ray", "local")
                for kind in order:
                    if kind == "local":
                        seconds, out_local = run_local(paths, name, args.batch_size)
                        local.append(seconds)
                    elif kind == "ray":
                        seconds, out_ray, job = run_ray(paths, name, args.batch_size, args.shard_images)
                        on_ray.append(seconds)
                    else:
                        # a job of one image: connecting, starting the actors and loading the model
                        fixed.append(run_ray(paths[:1], name, args.batch_size, args.shard_images)[0])
                delta = max(delta, float(np.abs(out_local - out_ray).max()))
            n = len(paths)
            lo, ra, st = n / statistics.median(local), n / statistics.median(on_ray), statistics.median(fixed)
            net = n / max(statistics.median(on_ray) - st, 1e-9)
            print(f"{name:20s} {lo:11.1f} {ra:10.1f} {ra / lo:6.2f} {st:11.1f} {net:13.1f} {net / lo:9.2f} "
                  f"{delta:9.1e}")
            if args.timeline:
                phases = ray_phases(paths, name, args.batch_size, args.shard_images)
                if phases is None:
                    print(f"  {name}: no model actor in Ray's timeline")
                else:
                    seconds, first, init, busy = phases
                    print(f"  {name} timeline: a job of {seconds:.1f} s; the model actor's first call at {first:.1f} s "
                          f"(its start, model included, {init:.1f} s), then {n / busy:.1f} images/s in its calls "
                          f"({busy:.1f} s; local {lo:.1f} images/s)")
    finally:
        disconnect()
    print(f"load average {os.getloadavg()[0]:.1f} at the end")
    print(f"(medians of {args.repeats} rounds after an untimed one of each, local and Ray alternating; "
          f"each run into a cold cache; "
          f"{job.actors} model actor(s) of {job.cpus:g} CPUs, decoding beside the model)")
    if args.gpu_rate:
        hours = MSLS_IMAGES / (args.gpu_rate * args.gpus) / 3600
        print(f"projection: {MSLS_IMAGES:,} images at {args.gpu_rate:.0f} images/s per GPU on {args.gpus} GPUs: "
              f"{hours:.1f} h")


if __name__ == "__main__":
    main()
