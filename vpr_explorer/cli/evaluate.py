"""``vpr-explorer evaluate``: run a protocol on a dataset and print the paper's kind of table.

Aligned traversal folders run the paper's random-split protocol by default (or traversal,
open-set); a database/queries layout runs the database-queries protocol on its given
queries. ``--json`` writes the numbers and every setting that shaped them (a ``hub:``
descriptor's ``--hub-*`` flags as ``"hub_options"``, right after its name, when given).

A database/queries layout's image-level Recall@K counts the queries that have a positive;
where some have none, one more line gives R@1/5/10 over every query, as
VPR-methods-evaluation counts them (``protocols.evaluation.recall_over_every_query``), and ``--json``
holds them under ``recall_over_every_query`` (for every database/queries evaluation).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from vpr_explorer.cli.common import (
    SPLIT_OPTIONS,
    add_dataset_args,
    add_split_args,
    bar,
    default_note,
    descriptor_name,
    extractor_source,
    hub_options,
    protocol_options,
    retrieval_dataset,
    write_text,
)
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import MetricPlaceSpec, PlaceGeometry, PlaceSpec
from vpr_explorer.protocols.evaluation import Protocol
from vpr_explorer.protocols.options import K_GRID, ProtocolOptions

#: evaluate's options that only some protocols read: ``common.SPLIT_OPTIONS`` and the k grid, the traversals
PROTOCOL_OPTIONS = {
    **SPLIT_OPTIONS,
    "k": ((Protocol.OPEN_SET,), list(K_GRID)),
    "database": ((Protocol.TRAVERSAL, Protocol.DATABASE), None),
    "queries": ((Protocol.TRAVERSAL, Protocol.DATABASE), None),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``evaluate``'s options: the dataset's (``common.add_dataset_args``), the protocol's, the outputs."""
    add_dataset_args(p)
    p.add_argument("--protocol", choices=[x.value for x in Protocol], default=None,
                   help=f"default: paper for aligned traversals, {Protocol.DATABASE.value} for a database/queries "
                        "layout")
    add_split_args(p)
    p.add_argument("--k", type=float, nargs="+", default=None,
                   help="open-set protocol: k values of θ_p + k·s_p" + default_note(PROTOCOL_OPTIONS["k"][1]))
    p.add_argument("--database", nargs="+", default=None,
                   help="traversal protocol: database traversal(s) (default: a traversal named ref, reference, "
                        "database, db or map, else the first)")
    p.add_argument("--queries", default=None,
                   help="traversal protocol: query traversal (default: one named query, queries, q or live, "
                        "else the last)")
    p.add_argument("--tolerance", type=int, default=ProtocolOptions.tolerance,
                   help="frames of slack: a place is right when one of its frames is within this many frames "
                        "of the query's; the authors count ±2")
    p.add_argument("--theta", type=float, default=None, help="also evaluate this global threshold (a finite number)")
    p.add_argument("--pr", action="store_true",
                   help="also precision–recall per method (AUC, recall at 100%% and 99%% precision, max F1), pooled "
                        "over runs: the global θ swept over the top scores, the per-place methods over θ_p + k·s_p")
    p.add_argument("--json", type=Path, default=None,
                   help="write the numbers, and every setting that shaped them, to this JSON file")


def run(args: argparse.Namespace) -> int:
    """Evaluate the dataset ``args`` names; print the table, write ``--json``.

    Returns:
        0 (bad input raises ``VPRInputError``).
    """
    from vpr_explorer.pipeline import evaluate_dataset
    from vpr_explorer.views.report import render

    dataset = retrieval_dataset(args)
    if dataset is not None:
        return _evaluate_retrieval(args, dataset)
    if args.protocol is None:
        args.protocol = Protocol.PAPER.value
    elif Protocol(args.protocol) is Protocol.DATABASE:
        raise VPRInputError(f"--protocol {Protocol.DATABASE.value} needs a database/queries layout (database/ + "
                            "queries/, VPR-Bench, traversals with positions.csv, or a manifest); "
                            f"{args.dataset} holds aligned traversals: use paper, traversal or open-set")
    o = protocol_options(args, PROTOCOL_OPTIONS)
    options = ProtocolOptions(runs=o["runs"], seed=o["seed"], cross_condition=o["cross_condition"],
                              unknown_share=o["unknown_share"], k_grid=o["k"], database=o["database"],
                              queries=o["queries"], tolerance=args.tolerance, user_theta=args.theta, pr=args.pr)
    ev = evaluate_dataset(
        args.dataset, PlaceSpec(args.group, args.step, args.reading), descriptor_name(args), args.protocol, options,
        cache_root=args.cache_dir, extract_progress=bar("descriptors"), progress=bar(f"{args.protocol} protocol"),
        dtype=args.dtype, layout=args.layout, descriptors_file=args.descriptors, names_file=args.names,
        descriptor_options=hub_options(args),
    )
    print(render(ev))
    _write_json(args, ev)
    return 0


def _place_specs(args: argparse.Namespace, dataset) -> tuple[PlaceSpec | None, MetricPlaceSpec | None]:
    """``(PlaceSpec, MetricPlaceSpec)`` for a database/queries dataset: one of them, from ``--geometry``."""
    geometry = args.geometry
    if geometry is None:
        geometry = "frames" if dataset.database_xy is None else "route" if dataset.ordered else "lattice"
    if PlaceGeometry(geometry) is PlaceGeometry.FRAMES:
        return PlaceSpec(args.group, args.step, args.reading), None
    return None, MetricPlaceSpec(args.group, args.step, args.reading, geometry)


def _evaluate_retrieval(args: argparse.Namespace, dataset) -> int:
    """``run`` for a database/queries layout: the database-queries protocol on its given queries."""
    from vpr_explorer.pipeline import dataset_descriptors, evaluate_retrieval, imported_descriptors
    from vpr_explorer.settings import check_cache_root
    from vpr_explorer.protocols.evaluation import recall_over_every_query
    from vpr_explorer.views.report import every_query_line, render

    protocol = Protocol(args.protocol or Protocol.DATABASE.value)
    if protocol is not Protocol.DATABASE:
        raise VPRInputError(f"--protocol {protocol.value}: {dataset.name} is a {dataset.layout.value} layout, whose "
                            f"queries are given: use --protocol {Protocol.DATABASE.value} (the default for it)")
    args.protocol = protocol.value
    protocol_options(args, PROTOCOL_OPTIONS)
    if args.tolerance:
        raise VPRInputError("--tolerance counts frames of aligned traversals; a database/queries layout says which "
                            "images are right by its ground truth (position-tagged: --radius)")
    options = ProtocolOptions(user_theta=args.theta, pr=args.pr)
    spec, metric = _place_specs(args, dataset)
    descriptor = descriptor_name(args)
    source: dict[str, str] = {}  # a file's path and sha256, or the hub flags: runs that differ never look alike
    if args.descriptors is not None:
        imp = imported_descriptors(dataset, args.descriptors, names_file=args.names, dtype=args.dtype)
        desc, descriptor, source = imp.descriptors, imp.name, imp.settings()
        for note in imp.notes:
            print(f"{args.descriptors.name}: {note}")
    else:
        check_cache_root(args.cache_dir)
        desc = dataset_descriptors(dataset, descriptor, cache_root=args.cache_dir, progress=bar("descriptors"),
                                   dtype=args.dtype, options=hub_options(args))
        source = extractor_source(args)
    ev = evaluate_retrieval(dataset, desc, options, spec=spec, metric=metric,
                            settings={"descriptor": descriptor, **source, "dtype": args.dtype}, progress=bar("queries"))
    print(dataset.describe())
    for note in dataset.notes:
        print(note)
    print(render(ev))
    line = every_query_line(ev)
    if line is not None:
        print(line)
    every = recall_over_every_query(ev)
    _write_json(args, ev, {"recall_over_every_query": {str(k): v for k, v in every.items()}})
    return 0


def _write_json(args: argparse.Namespace, ev, extra: dict | None = None) -> None:
    """Write ``ev`` (and ``extra``'s keys beside its own) to ``--json`` when given (strict JSON: no NaN, nothing but
    plain values)."""
    if args.json is not None:
        data = {**ev.to_dict(), **(extra or {})}
        write_text(args.json, json.dumps(data, indent=2, allow_nan=False, default=_not_json), "--json")


def _not_json(o):
    raise TypeError(f"not JSON: {type(o)}")
