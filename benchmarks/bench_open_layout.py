"""Opening a 100k-image position-tagged dataset: listing vs ground truth and places, and memory.

Writes ``--n`` image files (hard links to one real PNG, so the folder costs no disk) named
the VPR datasets downloader's way, ``@UTM_east@UTM_north@55@H@…``: a database route of
``0.9·n`` images every 2 m along a random walk and ``0.1·n`` queries near it (a share of them
far away: unknown places). Then, side by side in one run:

* **listing**: ``os.scandir`` of both folders (the least any loader must do);
* **open**: ``pipeline.open_dataset`` (listing, parsing every name, the ground truth within
  25 m as a sparse relation);
* **places**: ``pipeline.retrieval_places`` with group 10 m, step 25 m along the route and
  on a lattice.

It prints each time, the ratio of opening to listing, the ground truth's size in bytes
against the dense ``n_queries × n_database`` bool matrix it avoids, and the peak RSS::

    python benchmarks/bench_open_layout.py --png $VPR_EXPLORER_DATA/Nordland_64x32/summer/images-00010.png
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from vpr_explorer.data.example_layouts import utm_name
from vpr_explorer.pipeline import open_dataset, retrieval_places
from vpr_explorer.method.places import MetricPlaceSpec


def write(root: Path, png: Path, n: int, seed: int = 0) -> None:
    """The dataset under ``root``: hard links to copies of ``png`` (a file takes at most 65,000 links)."""
    rng = np.random.default_rng(seed)
    n_db = int(n * 0.9)
    heading = np.cumsum(rng.normal(0, 0.05, n_db))
    xy = 500_000 + np.cumsum(2.0 * np.c_[np.cos(heading), np.sin(heading)], axis=0) + [0, 6_960_000]
    q_at = rng.integers(0, n_db, n - n_db)
    q_xy = xy[q_at] + rng.normal(0, 5, (n - n_db, 2))
    q_xy[: (n - n_db) // 10] += 10_000  # a tenth of the queries far from the route: unknown places
    k = 0
    for side, pts in (("database", xy), ("queries", q_xy)):
        folder = root / side
        folder.mkdir(parents=True)
        for i, (e, no) in enumerate(pts):
            if k % 50_000 == 0:
                source = root / f"source{k // 50_000}.png"
                shutil.copy(png, source)
            os.link(source, folder / utm_name(e, no, i).replace(".jpg", ".png"))
            k += 1


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--png", type=Path, required=True, help="any real PNG file, hard-linked under every name")
    p.add_argument("--n", type=int, default=100_000)
    args = p.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_layout_"))
    try:
        t = time.perf_counter()
        write(tmp / "ds", args.png, args.n)
        print(f"wrote {args.n:,} names in {time.perf_counter() - t:.1f} s")

        t = time.perf_counter()
        listed = sum(1 for side in ("database", "queries") for _ in os.scandir(tmp / "ds" / side))
        t_list = time.perf_counter() - t

        t = time.perf_counter()
        ds = open_dataset(tmp / "ds")
        t_open = time.perf_counter() - t
        gt = ds.ground_truth

        t = time.perf_counter()
        _, n_route = retrieval_places(ds, metric=MetricPlaceSpec(10, 25, geometry="route"))
        t_route = time.perf_counter() - t
        t = time.perf_counter()
        _, n_lattice = retrieval_places(ds, metric=MetricPlaceSpec(10, 25, geometry="lattice"))
        t_lattice = time.perf_counter() - t

        gt_bytes = gt.indptr.nbytes + gt.indices.nbytes
        dense = ds.n_queries * ds.n_database
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
        print(f"{ds.n_database:,} database + {ds.n_queries:,} query images ({listed:,} listed), "
              f"{int(gt.counts.sum()):,} positive pairs within 25 m, {gt.n_unknown:,} queries with none")
        print(f"listing (os.scandir)        {t_list:8.3f} s")
        print(f"open_dataset (names, GT)    {t_open:8.3f} s   {t_open / t_list:6.1f}x listing")
        print(f"places along the route      {t_route:8.3f} s   ({n_route:,} places)")
        print(f"places on a lattice         {t_lattice:8.3f} s   ({n_lattice:,} places)")
        print(f"ground truth {gt_bytes / 1e6:.2f} MB sparse; a dense bool matrix would be {dense / 1e9:.2f} GB "
              f"({dense / gt_bytes:,.0f}x)")
        print(f"peak RSS {peak:.2f} GiB")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
