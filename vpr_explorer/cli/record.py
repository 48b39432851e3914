"""``vpr-explorer record``: play a dataset's queries back against its database, into a rerun ``.rrd`` file.

Every layout is one dataset value (``data.aligned.database_queries`` for aligned traversal
folders: the query traversal's frames are the queries, the database traversals' frames the
database). Each query, in order, is matched against the database and logged with its
scores, the place decision and the per-place threshold, on one timeline
(``vpr_explorer.recording``). With ``--bench``, every acceptance rule of the acceptance bench
(``protocols.acceptance``, default choices) runs on the same value and places, and each rule's
confidence, acceptance and decision of every query is logged on the same timeline
(``recording.log_bench``); a rule that cannot run is left out and the recording says why.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from vpr_explorer.cli.common import add_dataset_args, bar, descriptor_name, hub_options
from vpr_explorer.cli.common import retrieval_dataset


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``record``'s options: the dataset's (``common.add_dataset_args``), the traversals, the file to write."""
    add_dataset_args(p)
    p.add_argument("--database", nargs="+", default=None,
                   help="database traversal(s), e.g. day_right (default: every traversal but the query)")
    p.add_argument("--queries", default=None,
                   help="query traversal, e.g. night_right (default: one named query, queries, q or live, else the "
                        "last)")
    p.add_argument("--out", type=Path, required=True, help="the .rrd file to write, e.g. run.rrd")
    p.add_argument("--k", type=float, default=0.0, help="thresholds θ_p + k·s_p; 0 is the paper's")
    p.add_argument("--tolerance", type=int, default=0,
                   help="aligned traversals: frames of slack for a right place")
    p.add_argument("--bench", action="store_true",
                   help="also run the acceptance bench (every acceptance rule, closed set and natural open set) on "
                        "the same queries, database and places, and log each rule's confidence, acceptance and "
                        "decision per query under bench/<rule> and bench_open/<rule>; refused for a value with more "
                        "query × database pairs than the bench holds")


def run(args: argparse.Namespace) -> int:
    """Record the playback ``args`` describe; print what was written and how to watch it.

    The output path, the cache folder and the options are checked before any descriptor is computed.

    Returns:
        0 (bad input raises ``VPRInputError``).
    """
    from vpr_explorer.protocols.acceptance import BenchOptions
    from vpr_explorer.recording import check_output, load_traversals, record_dataset
    from vpr_explorer.settings import check_cache_root

    out = check_output(args.out)
    descriptor = descriptor_name(args)
    if args.descriptors is None:
        check_cache_root(args.cache_dir)  # an unusable cache folder fails before the dataset is read or the demo drawn
    dataset = retrieval_dataset(args)
    aligned = dataset is None
    if aligned:
        dataset = load_traversals(args.dataset, args.database, args.queries, layout=args.layout)
    playback = record_dataset(
        dataset, descriptor, query=args.queries if aligned else None, database=args.database if aligned else None,
        tolerance=args.tolerance, group=args.group, step=args.step, reading=args.reading, geometry=args.geometry,
        out=out, k=args.k, cache_root=args.cache_dir, extract_progress=bar("descriptors"), progress=bar("queries"),
        dtype=args.dtype, descriptors_file=args.descriptors, names_file=args.names,
        bench=BenchOptions() if args.bench else None, descriptor_options=hub_options(args),
    )
    print(playback.describe())
    print(f"wrote {playback.rrd}: watch it with `rerun {playback.rrd}` (or `rerun --web-viewer {playback.rrd}`)")
    return 0
