"""Memory and time of reading cached descriptors as float32 or float16 (the ``--dtype`` option).

    python benchmarks/bench_float16_memory.py                  # 110,000 × 1,280, 3 repeats
    python benchmarks/bench_float16_memory.py --n 20000 --repeats 1

Builds a descriptor cache of N seeded unit vectors (1,280-d: EfficientNet-Lite0's), stored
with ``DescriptorCache.store`` under made-up sha256 hashes (sha256 of ``str(i)``) in shards
of ``extract.SHARD_SIZE``, once with float32 storage and once with float16, in a temporary
folder deleted at the end. Then, each in a fresh subprocess so that its peak resident
memory is its own, it reads all N vectors back the way ``extract_descriptors`` does on a
warm run (``DescriptorCache.lookup``, then ``renormalise_in_place`` for a float32 result):

* storage float32, dtype float32 (the default),
* storage float16, dtype float32 (float16 on disk only, float32 in memory),
* storage float16, dtype float16 (``--dtype float16``).

Prints per configuration the median wall time of the lookup (and of the renormalisation),
the result's size, and the child's peak RSS (``VmHWM``) minus its RSS after the imports
and the hash list (``VmRSS``), over ``--repeats`` runs (interleaved, so a drifting machine
load hits every configuration alike); then the float16/float32 ratio of that increase,
and the load average before and after (the machine may be shared).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CACHE_KEY = "bench-1"
CONFIGS = (("float32", "float32"), ("float16", "float32"), ("float16", "float16"))  # (storage, dtype)


def fake_hashes(n: int) -> list[str]:
    """Valid sha256 hex digests standing for ``n`` images."""
    return [hashlib.sha256(str(i).encode()).hexdigest() for i in range(n)]


def _status_kib(field: str) -> int:
    """A ``/proc/self/status`` memory field (``VmRSS``, ``VmHWM``) in KiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"/proc/self/status has no {field} (Linux only)")


def child(root: Path, storage: str, dtype: str, n: int, dim: int) -> None:
    """Read all ``n`` vectors of the ``storage`` cache as ``dtype``; print one JSON line."""
    import numpy as np

    from vpr_explorer.descriptors import DescriptorCache
    from vpr_explorer.descriptors.extract import renormalise_in_place

    hashes = fake_hashes(n)
    cache = DescriptorCache(root / storage, dtype=storage)
    rss_before = _status_kib("VmRSS")
    start = time.perf_counter()
    index, vectors = cache.lookup(CACHE_KEY, hashes, dim, dtype=dtype)
    lookup_s = time.perf_counter() - start
    start = time.perf_counter()
    if dtype == "float32":  # what extract_descriptors does to float32 hits
        renormalise_in_place(vectors)
    renormalise_s = time.perf_counter() - start
    if len(index) != n or vectors.dtype != np.dtype(dtype) or vectors.shape != (n, dim):
        raise SystemExit(f"lookup returned {len(index)} hits, {vectors.dtype} {vectors.shape}")
    print(json.dumps({
        "lookup_s": lookup_s, "renormalise_s": renormalise_s, "result_mb": vectors.nbytes / 1e6,
        "rss_before_mb": rss_before * 1024 / 1e6, "peak_mb": _status_kib("VmHWM") * 1024 / 1e6,
    }))


def build(root: Path, n: int, dim: int) -> None:
    """The float32 and float16 caches of the same ``n`` seeded unit vectors, a shard at a time."""
    import numpy as np

    from vpr_explorer.descriptors import DescriptorCache
    from vpr_explorer.descriptors.extract import SHARD_SIZE

    caches = [DescriptorCache(root / storage, dtype=storage) for storage in ("float32", "float16")]
    hashes = fake_hashes(n)
    rng = np.random.default_rng(0)
    for lo in range(0, n, SHARD_SIZE):
        rows = rng.standard_normal((min(SHARD_SIZE, n - lo), dim), dtype=np.float32)
        rows /= np.linalg.norm(rows, axis=1, keepdims=True)
        for cache in caches:
            cache.store(CACHE_KEY, hashes[lo : lo + SHARD_SIZE], rows)


def disk_mb(folder: Path) -> float:
    return sum(p.stat().st_size for p in folder.rglob("*.npy")) / 1e6


def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=110_000, help="cached vectors (default 110,000)")
    parser.add_argument("--dim", type=int, default=1280, help="descriptor length (default 1,280)")
    parser.add_argument("--repeats", type=int, default=3, help="runs of each configuration (default 3)")
    parser.add_argument("--child", nargs=2, metavar=("ROOT", "STORAGE:DTYPE"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.n < 1 or args.dim < 1 or args.repeats < 1:
        parser.error("--n, --dim and --repeats must be 1 or more")
    if args.child:
        storage, dtype = args.child[1].split(":")
        child(Path(args.child[0]), storage, dtype, args.n, args.dim)
        return 0

    from vpr_explorer.descriptors.extract import SHARD_SIZE

    print(f"cache lookup of {args.n:,} x {args.dim:,} vectors in shards of {SHARD_SIZE:,}, "
          f"{args.repeats} run(s) of each configuration, each in a fresh process")
    print(f"load average before: {load()} ({os.cpu_count()} cores)")
    root = Path(tempfile.mkdtemp(prefix="vpr-bench-f16-"))
    try:
        start = time.perf_counter()
        build(root, args.n, args.dim)
        print(f"built the caches in {time.perf_counter() - start:.1f} s: "
              f"float32 shards {disk_mb(root / 'float32'):.1f} MB, float16 shards {disk_mb(root / 'float16'):.1f} MB on disk")
        runs: dict[tuple[str, str], list[dict]] = {c: [] for c in CONFIGS}
        for _ in range(args.repeats):
            for storage, dtype in CONFIGS:
                done = subprocess.run(
                    [sys.executable, __file__, "--n", str(args.n), "--dim", str(args.dim),
                     "--child", str(root), f"{storage}:{dtype}"],
                    capture_output=True, text=True, check=False,
                )
                if done.returncode != 0:
                    print(done.stdout, done.stderr, file=sys.stderr)
                    return 1
                runs[(storage, dtype)].append(json.loads(done.stdout.strip().splitlines()[-1]))
    finally:
        shutil.rmtree(root, ignore_errors=True)

    print()
    print(f"{'storage':<8} {'dtype':<8} {'result MB':>9} {'lookup s':>9} {'renorm s':>9} "
          f"{'RSS before MB':>13} {'peak RSS MB':>11} {'increase MB':>11}")
    increase = {}
    for (storage, dtype), rs in runs.items():
        med = {k: statistics.median(r[k] for r in rs) for k in rs[0]}
        increase[(storage, dtype)] = statistics.median(r["peak_mb"] - r["rss_before_mb"] for r in rs)
        print(f"{storage:<8} {dtype:<8} {med['result_mb']:9.1f} {med['lookup_s']:9.3f} {med['renormalise_s']:9.3f} "
              f"{med['rss_before_mb']:13.1f} {med['peak_mb']:11.1f} {increase[(storage, dtype)]:11.1f}")
    print("(medians over the runs; increase = peak RSS minus the RSS after imports and the hash list)")
    ratio = increase[("float16", "float16")] / increase[("float32", "float32")]
    lookups = {c: statistics.median(r["lookup_s"] + r["renormalise_s"] for r in rs) for c, rs in runs.items()}
    print(f"peak RSS increase, float16/float32 (storage and dtype alike): {ratio:.3f}")
    print(f"lookup (+ renormalisation) time, float16/float32: "
          f"{lookups[('float16', 'float16')] / lookups[('float32', 'float32')]:.3f}")
    print(f"load average after: {load()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
