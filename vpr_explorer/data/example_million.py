"""A synthetic position-tagged database of any size, for the million-image benchmark and tests.

Written as a user would hand one over (docs/performance.md, the million-image database): a manifest
``manifest.csv`` (``path,role,x,y``: database images along a route, then queries), the
image files it names, and a float16 descriptor ``.npy`` in the manifest's order (what
``vpr-explorer list`` prints), so that the app and ``pipeline.imported_descriptors`` open it
through the memory-mapped path (``descriptors.store``).

The images are symbolic links to one small real PNG (a million distinct files would be
gigabytes of nothing; every link is a file the manifest loader checks and the app can show).
Database image i lies ``spacing`` metres along a straight route; its descriptor is a point on
a smooth random curve of the position (anchors every ``ANCHOR_M`` metres, interpolated)
plus noise, L2-normalised, so nearby images score high and places separate. Queries are
taken at random positions along the route (0.5 m across it) with stronger noise; a share
``unknown`` lies 1 km off the route: no database image within the radius (the open set).

``python -m vpr_explorer.data.example_million --out DIR --database 1000000 --queries 10000 --dim 512``
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
from PIL import Image

ANCHOR_M = 40.0
"""Metres between the random anchors the descriptor curve interpolates."""
PER_FOLDER = 10_000
ROWS = 32_768


def _curve(positions: np.ndarray, anchors: np.ndarray, noise: float, rng: np.random.Generator) -> np.ndarray:
    """Unit float32 rows: the anchors interpolated at ``positions`` (metres) plus Gaussian noise."""
    t = positions / ANCHOR_M
    k = np.clip(np.floor(t).astype(np.int64), 0, len(anchors) - 2)
    f = (t - k).astype(np.float32)[:, None]
    x = (1 - f) * anchors[k] + f * anchors[k + 1]
    x += noise * rng.standard_normal(x.shape, dtype=np.float32)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return x


def write_route_database(out: Path, *, n_database: int, n_queries: int, dim: int, spacing: float = 1.0,
                         unknown: float = 0.1, seed: int = 0, links: bool = True,
                         name: str = "descriptors") -> tuple[Path, Path]:
    """Write the manifest, the images (links) and the float16 descriptors ``<name>.npy``; return both paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    length = n_database * spacing
    anchors = rng.standard_normal((int(length / ANCHOR_M) + 2, dim), dtype=np.float32)
    db_x = np.arange(n_database) * spacing
    q_x = rng.uniform(0, length, n_queries)
    q_y = rng.normal(0, 0.5, n_queries)
    off = rng.random(n_queries) < unknown
    q_y[off] += 1000.0
    png = out / "image.png"
    if not png.exists():
        Image.fromarray((rng.random((32, 64, 3)) * 255).astype(np.uint8)).save(png)

    def rel(role: str, i: int) -> str:
        return f"{role}/{i // PER_FOLDER:04d}/{i:07d}.png"

    if links:
        for role, n in (("database", n_database), ("queries", n_queries)):
            for i in range(n):
                path = out / rel(role, i)
                if i % PER_FOLDER == 0:
                    path.parent.mkdir(parents=True, exist_ok=True)
                if not os.path.lexists(path):
                    os.symlink(png, path)
    manifest = out / "manifest.csv"
    with open(manifest, "w") as fh:
        fh.write("path,role,x,y\n")
        fh.writelines(f"{rel('database', i)},database,{db_x[i]:.2f},0\n" for i in range(n_database))
        fh.writelines(f"{rel('queries', i)},query,{q_x[i]:.2f},{q_y[i]:.2f}\n" for i in range(n_queries))
    npy = out / f"{name}.npy"
    tmp = npy.with_name(f".{npy.name}.tmp")
    rows = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.float16, shape=(n_database + n_queries, dim))
    for lo in range(0, n_database, ROWS):
        hi = min(lo + ROWS, n_database)
        rows[lo:hi] = _curve(db_x[lo:hi], anchors, 0.35, rng)
    rows[n_database:] = _curve(q_x, anchors, 0.6, rng)
    rows.flush()
    del rows
    os.replace(tmp, npy)
    return manifest, npy


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--database", type=int, default=1_000_000)
    parser.add_argument("--queries", type=int, default=10_000)
    parser.add_argument("--dim", type=int, default=512)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    manifest, npy = write_route_database(args.out, n_database=args.database, n_queries=args.queries, dim=args.dim,
                                         seed=args.seed)
    print(manifest, npy)


if __name__ == "__main__":
    main()
