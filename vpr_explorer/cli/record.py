"""``vpr-explorer record``: play a query traversal back against a database, into a rerun ``.rrd`` file.

Each query frame is matched against the database traversal(s) and logged with its scores,
the place decision and the per-place threshold, on one timeline (``vpr_explorer.recording``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from vpr_explorer.cli.common import (
    add_dataset_args,
    bar,
    check_radius_option,
    descriptor_name,
    refuse_retrieval_options,
)
from vpr_explorer.data.layouts import Layout
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import PlaceSpec


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``record``'s options: the dataset's (``common.add_dataset_args``), the traversals, the file to write."""
    add_dataset_args(p)
    p.add_argument("--database", nargs="+", required=True, help="database traversal(s), e.g. day_right")
    p.add_argument("--queries", required=True, help="query traversal, e.g. night_right")
    p.add_argument("--out", type=Path, required=True, help="the .rrd file to write, e.g. run.rrd")
    p.add_argument("--k", type=float, default=0.0, help="thresholds θ_p + k·s_p; 0 is the paper's")
    p.add_argument("--tolerance", type=int, default=0, help="frames of slack for a right place")


def run(args: argparse.Namespace) -> int:
    """Record the playback ``args`` describe; print what was written and how to watch it.

    Returns:
        0 (bad input raises ``VPRInputError``).
    """
    from vpr_explorer.recording import record_dataset

    check_radius_option(args)
    refuse_retrieval_options(args, "record plays back aligned traversal folders, whose frames say which database "
                                   "images are right")
    if args.layout not in (Layout.AUTO.value, Layout.TRAVERSALS.value):
        raise VPRInputError(f"--layout {args.layout}: record plays back aligned traversal folders only; leave "
                            "--layout out (or give traversals)")
    playback = record_dataset(
        args.dataset, PlaceSpec(args.group, args.step, args.reading), descriptor_name(args),
        database=args.database, queries=args.queries, out=args.out, k=args.k, tolerance=args.tolerance,
        cache_root=args.cache_dir, extract_progress=bar("descriptors"), progress=bar("frames"), dtype=args.dtype,
        descriptors_file=args.descriptors, names_file=args.names,
    )
    print(playback.describe())
    print(f"wrote {playback.rrd}: watch it with `rerun {playback.rrd}` (or `rerun --web-viewer {playback.rrd}`)")
    return 0
