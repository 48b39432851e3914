"""``vpr-explorer sweep``: one protocol over a grid of group × step, printed as tables, written as CSV/JSON.

    vpr-explorer sweep --dataset GardensPointWalking --descriptor pixels \\
        --groups 1 2 3 --steps 3 5 10 --reading stride skip --protocol paper --runs 10 --csv sweep.csv

The dataset options are ``evaluate``'s (``common.add_dataset_args``), with ``--groups``,
``--steps`` and ``--reading`` taking several values; the protocol options are
``evaluate``'s too, and ``--k`` is the one k whose unknown-place rejection the open set
reports. Aligned traversal folders run the paper (default), traversal or open-set protocol
on places of frames; any other layout runs the database-queries protocol, group/step
counting its database images in listed order (``--geometry frames``) or metres along its
route or over a lattice (``--geometry route``/``lattice``, where it has positions). The
cost (cells, protocol runs, image pairs) is printed before the work starts.
"""

from __future__ import annotations

import argparse
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
    number,
    protocol_options,
    retrieval_dataset,
    write_text,
)
from vpr_explorer.method.places import PlaceGeometry, Reading
from vpr_explorer.protocols.evaluation import Protocol
from vpr_explorer.protocols.options import K_GRID
from vpr_explorer.protocols.sweep import (
    METRIC_LABELS,
    SWEEP_METHODS,
    SWEEP_PROTOCOLS,
    Metric,
    SweepResult,
    SweepSpec,
    empty_reasons,
    missing_reasons,
    sweep,
    sweep_cost,
    table,
)

#: sweep's options that only some protocols read: ``common.SPLIT_OPTIONS``, the reported k and its grid,
#: the traversals
PROTOCOL_OPTIONS = {
    **SPLIT_OPTIONS,
    "k": ((Protocol.OPEN_SET,), 0.0),
    "k_grid": ((Protocol.OPEN_SET,), list(K_GRID)),
    "database": ((Protocol.TRAVERSAL, Protocol.DATABASE), None),
    "queries": ((Protocol.TRAVERSAL, Protocol.DATABASE), None),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``sweep``'s options: the dataset's (``common.add_dataset_args``), the grid's, the protocol's, the outputs.

    ``--group``, ``--step`` and ``--reading`` take one value or more here (``--group`` and
    ``--step`` are aliases of ``--groups`` and ``--steps``).
    """
    add_dataset_args(p, places=False)
    p.add_argument("--groups", "--group", dest="groups", type=number, nargs="+", required=True,
                   metavar="G", help="frames (or metres, see --geometry) per place, one or more (e.g. 1 2 3 4 5 6)")
    p.add_argument("--steps", "--step", dest="steps", type=number, nargs="+", required=True,
                   metavar="S", help="frames (or metres) from one place to the next (stride) or skipped (skip), "
                                     "one or more")
    p.add_argument("--reading", "--readings", dest="reading", nargs="+", choices=[r.value for r in Reading],
                   default=[r.value for r in Reading],
                   help="stride (a place starts every STEP frames, authors' code) and/or skip (take GROUP, skip "
                        "STEP, paper text); a grid each")
    p.add_argument("--protocol", choices=[x.value for x in SWEEP_PROTOCOLS], default=None,
                   help=f"the protocol every cell runs (default: paper for aligned traversals, "
                        f"{Protocol.DATABASE.value} for a database/queries layout)")
    p.add_argument("--method", choices=list(SWEEP_METHODS), default=SWEEP_METHODS[0],
                   help="the thresholded method whose R@1 gain over the place level, unknown-place rejection "
                        "and AUC the cells report (default: %(default)s, the paper's)")
    add_split_args(p, "random splits per cell")
    p.add_argument("--k", type=float, default=None,
                   help="open-set protocol: the k of θ_p + k·s_p whose unknown-place rejection the cells report "
                        f"(default: {PROTOCOL_OPTIONS['k'][1]:g}, the paper's θ_p; added to --k-grid when missing)")
    p.add_argument("--k-grid", type=float, nargs="+", default=None,
                   help="open-set protocol: the trade-off's k values" + default_note(PROTOCOL_OPTIONS["k_grid"][1]))
    p.add_argument("--database", nargs="+", default=None,
                   help="traversal protocol: database traversal(s); a layout of traversals with positions: its "
                        "database traversal(s)")
    p.add_argument("--queries", default=None, help="traversal protocol: query traversal; a layout of traversals "
                                                   "with positions: its query traversal")
    p.add_argument("--tolerance", type=int, default=0,
                   help="aligned traversals: frames of slack: a place is right when one of its frames is within this "
                        "many frames of the query's")
    p.add_argument("--theta", type=float, default=None, help="also evaluate this global threshold in each cell")
    p.add_argument("--no-pr", action="store_true",
                   help="skip precision–recall (faster; the AUC column stays empty)")
    p.add_argument("--metric", nargs="+", choices=[m.value for m in Metric], default=None,
                   help="the grids to print, of " +
                        ", ".join(f"{m.value} = {METRIC_LABELS[m]}" for m in Metric).replace("%", "%%") +
                        " (default: all)")
    p.add_argument("--csv", type=Path, default=None, help="write one row per cell, every setting in a column")
    p.add_argument("--json", type=Path, default=None, help="write the settings and every cell as JSON")


def run(args: argparse.Namespace) -> int:
    """Run the sweep ``args`` describe; print the cost, the grids and why cells are empty; write CSV/JSON.

    Returns:
        0 (bad input raises ``VPRInputError``).
    """
    from vpr_explorer import pipeline
    from vpr_explorer.settings import check_cache_root
    from vpr_explorer.views.numbers import check_geometry

    descriptor = descriptor_name(args)
    if args.descriptors is None:
        check_cache_root(args.cache_dir)
    retrieval = retrieval_dataset(args)
    dataset = pipeline.open_dataset(args.dataset, args.layout) if retrieval is None else retrieval
    geometry = PlaceGeometry.FRAMES
    if retrieval is not None:  # none when the layout names its places: sweep_cost says so
        geometry = check_geometry(retrieval, args.geometry) or geometry
    if args.protocol is None:
        args.protocol = (Protocol.PAPER if retrieval is None else Protocol.DATABASE).value
    o = protocol_options(args, PROTOCOL_OPTIONS)
    spec = SweepSpec(groups=args.groups, steps=args.steps, readings=args.reading, protocol=args.protocol,
                     geometry=geometry, method=args.method, k=o["k"], runs=o["runs"], seed=o["seed"],
                     cross_condition=o["cross_condition"], unknown_share=o["unknown_share"],
                     database=o["database"], queries=o["queries"], tolerance=args.tolerance, user_theta=args.theta,
                     k_grid=o["k_grid"], pr=not args.no_pr)
    cost = sweep_cost(dataset, spec)  # refuses data the protocol does not run on, before extraction
    print(f"{dataset.name}: {cost.describe()}")
    hub = extractor_source(args)  # the --hub-* flags given, recorded beside the descriptor's name
    source = hub
    if args.descriptors is not None:
        imp = pipeline.imported_descriptors(dataset, args.descriptors, names_file=args.names, dtype=args.dtype)
        desc, descriptor, source = imp.descriptors, imp.name, imp.settings()
    else:
        desc = pipeline.dataset_descriptors(dataset, descriptor, cache_root=args.cache_dir,
                                            progress=bar("descriptors"), dtype=args.dtype, options=hub_options(args))
    result = sweep(dataset, desc, spec, pipeline, descriptor=descriptor, progress=bar("sweep cells"),
                   cell_progress=bar(f"{spec.protocol.value} protocol"), source=source)
    metrics = [Metric(m) for m in (args.metric or [m.value for m in Metric])]
    _print_result(result, spec, " ".join([descriptor, *hub.values()]), metrics)
    write_text(args.csv, result.to_csv(), "--csv")
    write_text(args.json, result.to_json(), "--json")
    return 0


def _print_result(result: SweepResult, spec: SweepSpec, descriptor: str, metrics: list[Metric]) -> None:
    """The sweep's grids (one per metric and reading), why cells are empty, and the best cell of each metric.

    ``descriptor``: as the header line names it (a ``hub:`` descriptor with its ``--hub-*`` flags).
    """
    print(f"{spec.protocol.value} protocol, {descriptor}, method {spec.method}"
          + (f", group/step in metres ({spec.geometry.value})" if spec.unit == "m" else "")
          + (f", rejection at k = {spec.k:g}" if spec.protocol is Protocol.OPEN_SET else "")
          + f" · {result.seconds:.1f} s")
    for metric in metrics:
        for reading in spec.readings:
            print()
            print(table(result, metric, reading))
    reasons = empty_reasons(result)
    missing = missing_reasons(result)
    if reasons or missing:
        print()
    for line in reasons:
        print(f"empty: {line}")
    for line in missing:
        print(f"missing: {line}")
    shared = [c for c in result.cells if c.same_as is not None]
    if shared:
        print(f"{len(shared)} cell(s) share their places with another reading's cell (skip g/s = stride g/g+s): "
              "evaluated once")
    if spec.protocol in (Protocol.PAPER, Protocol.OPEN_SET):
        print(f"The grids are means over {spec.runs} split(s); each cell's std, 95% interval and the gain's paired "
              "p-value are in the CSV and JSON.")
    for metric in metrics:
        best = result.best(metric)
        if best is not None:
            spread = best.spread(metric)
            print(f"best {metric.value}: group {best.group:g}, step {best.step:g} {spec.unit} ({best.reading.value})"
                  + (f": {spread}" if spread else ""))
