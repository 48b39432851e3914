"""GardensPoint Walking written in each of the field's layouts, for worked examples and tests.

``write_gardens_point_layouts(gp, out)`` links the 600 real images (no copies) into:

* ``database-queries/``: ``database/`` = day_right, ``queries/`` = night_right, named
  ``@UTM_east@UTM_north@55@H@…`` with frames 10 m apart on a straight line (so the default
  25 m radius makes frames within ±2 right: the authors' tolerance);
* ``vpr-bench/``: ``ref/`` and ``query/`` (``0.jpg`` …) with ``ground_truth_new.npy`` listing
  the references within ±2 frames of each query;
* ``traversal-positions/``: ``day_right/`` and ``night_right/`` with ``positions.csv`` from the
  dataset's own hand-made route (``gp_pos.csv``, scaled from the unit square to 1 km);
* ``manifest.csv``: day_right as database and night_right as queries, with a ``place`` column
  (group 3, step 10 over the frame index; frames between places have none).

The same data in every layout: where the ground truth is the same (±2 frames), the
place-level numbers equal the traversal protocol's (``tests/test_layouts.py``).
"""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np

from vpr_explorer.errors import VPRInputError

SPACING_M = 10.0
N_FRAMES = 200
DATABASE, QUERIES = "day_right", "night_right"


def _link(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.is_symlink() or dst.exists():
        dst.unlink()
    os.symlink(src.resolve(), dst)


def utm_name(east: float, north: float, index: int) -> str:
    """A VPR-datasets-downloader file name: ``@east@north@zone@letter@lat@lon@pano@…@.jpg``."""
    return f"@{east:.2f}@{north:.2f}@55@H@-27.47@153.02@{index:04d}@@@@@@@@.jpg"


def write_gardens_point_layouts(gp: Path, out: Path) -> dict[str, Path]:
    """Write the four layouts of GardensPoint under ``out``; returns layout name -> path to open."""
    gp = Path(gp).expanduser()
    frames = {t: [gp / t / f"Image{f:03d}.jpg" for f in range(N_FRAMES)] for t in (DATABASE, QUERIES)}
    missing = [p for ps in frames.values() for p in ps if not p.is_file()]
    if missing:
        raise VPRInputError(f"{missing[0]}: not found; give the GardensPointWalking folder")
    out = Path(out).expanduser()
    paths = {}

    dq = out / "database-queries"
    for side, trav in (("database", DATABASE), ("queries", QUERIES)):
        for f, src in enumerate(frames[trav]):
            _link(src, dq / side / utm_name(500_000 + SPACING_M * f, 6_960_000.0, f))
    paths["database-queries"] = dq

    vb = out / "vpr-bench"
    for side, trav in (("ref", DATABASE), ("query", QUERIES)):
        for f, src in enumerate(frames[trav]):
            _link(src, vb / side / f"{f}.jpg")
    gt = np.empty((N_FRAMES, 2), dtype=object)
    for q in range(N_FRAMES):
        gt[q, 0], gt[q, 1] = q, list(range(max(0, q - 2), min(N_FRAMES, q + 3)))
    np.save(vb / "ground_truth_new.npy", gt)
    paths["vpr-bench"] = vb

    tp = out / "traversal-positions"
    with (gp / "gp_pos.csv").open(newline="") as fh:
        unit = np.array([[float(r[0]), float(r[1])] for r in csv.reader(fh) if r and r[0][:1] in "0123456789.-"])
    for trav in (DATABASE, QUERIES):
        for f, src in enumerate(frames[trav]):
            _link(src, tp / trav / src.name)
        np.savetxt(tp / trav / "positions.csv", unit * 1000.0, delimiter=",", header="x,y", comments="", fmt="%.3f")
    paths["traversal-positions"] = tp

    manifest = out / "manifest" / "manifest.csv"
    manifest.parent.mkdir(parents=True, exist_ok=True)
    with manifest.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["path", "role", "place"])
        for role, trav in (("database", DATABASE), ("query", QUERIES)):
            for f, src in enumerate(frames[trav]):
                w.writerow([src.resolve().as_posix(), role, f // 10 if f % 10 < 3 else ""])
    paths["manifest"] = manifest
    return paths


def main(argv: list[str] | None = None) -> int:
    import argparse

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--gardens-point", type=Path, required=True, help="the GardensPointWalking folder")
    p.add_argument("--out", type=Path, required=True, help="where to write the layouts")
    args = p.parse_args(argv)
    for name, path in write_gardens_point_layouts(args.gardens_point, args.out).items():
        print(f"{name}: {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
