"""``vpr-explorer sweep``: one protocol over a grid of group × step, printed as tables, written as CSV/JSON.

    vpr-explorer sweep --dataset GardensPointWalking --descriptor pixels \\
        --groups 1 2 3 --steps 3 5 10 --reading stride skip --protocol paper --runs 10 --csv sweep.csv

The dataset options are ``evaluate``'s (``cli.add_dataset_args``), with ``--groups``,
``--steps`` and ``--reading`` taking several values; the protocol options are
``evaluate``'s too, and ``--k`` is the one k whose unknown-place rejection the open set
reports. The cost (cells, protocol runs, image pairs) is printed before the work starts.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from vpr_explorer.errors import VPRInputError
from vpr_explorer.protocols.evaluation import K_GRID, Protocol
from vpr_explorer.pipeline import MAX_RUNS
from vpr_explorer.method.places import Reading
from vpr_explorer.protocols.sweep import METRIC_LABELS, SWEEP_METHODS, SWEEP_PROTOCOLS, Metric

#: sweep's options that only some protocols read, with those protocols and the value when not given
PROTOCOL_OPTIONS = {
    "runs": ((Protocol.PAPER, Protocol.OPEN_SET), 50),
    "seed": ((Protocol.PAPER, Protocol.OPEN_SET), 0),
    "cross_condition": ((Protocol.PAPER, Protocol.OPEN_SET), False),
    "unknown_share": ((Protocol.OPEN_SET,), 0.3),
    "k": ((Protocol.OPEN_SET,), 0.0),
    "k_grid": ((Protocol.OPEN_SET,), list(K_GRID)),
    "database": ((Protocol.TRAVERSAL,), None),
    "queries": ((Protocol.TRAVERSAL,), None),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``sweep``'s arguments: the dataset's (``cli.add_dataset_args``; group/step/reading take lists), the protocol's.

    ``parser`` must be made with ``conflict_handler="resolve"``: ``--group``, ``--step`` and
    ``--reading`` of ``add_dataset_args`` are replaced by their list-taking forms.
    """
    from vpr_explorer.cli import _number, add_dataset_args

    add_dataset_args(parser)
    # the grid replaces evaluate's single --group/--step/--reading (which stay as aliases): the parser is
    # made with conflict_handler="resolve" (cli.build_parser)
    parser.add_argument("--groups", "--group", dest="groups", type=_number, nargs="+", required=True,
                        metavar="G", help="frames per place, one or more (e.g. 1 2 3 4 5 6)")
    parser.add_argument("--steps", "--step", dest="steps", type=_number, nargs="+", required=True,
                        metavar="S", help="frames from one place to the next (stride) or skipped (skip), one or more")
    parser.add_argument("--reading", "--readings", dest="reading", nargs="+", choices=[r.value for r in Reading],
                        default=[r.value for r in Reading],
                        help="stride (a place starts every STEP frames, authors' code) and/or skip (take GROUP, skip "
                             "STEP, paper text); a grid each (default both)")
    parser.add_argument("--protocol", choices=[p.value for p in SWEEP_PROTOCOLS], default=Protocol.PAPER.value,
                        help="the protocol every cell runs (default paper)")
    parser.add_argument("--method", choices=list(SWEEP_METHODS), default=SWEEP_METHODS[0],
                        help="the thresholded method whose R@1 gain over the place level, unknown-place rejection "
                             f"and AUC the cells report (default {SWEEP_METHODS[0]}, the paper's)")
    parser.add_argument("--runs", type=int, default=None,
                        help=f"paper and open-set protocols: random splits per cell, at most {MAX_RUNS} (default 50)")
    parser.add_argument("--seed", type=int, default=None,
                        help="paper and open-set protocols: seed of the splits (default 0)")
    parser.add_argument("--cross-condition", action="store_true", default=None,
                        help="paper and open-set protocols: score each query only against other traversals")
    parser.add_argument("--unknown-share", type=float, default=None,
                        help="open-set protocol: share of places held out (default 0.3)")
    parser.add_argument("--k", type=float, default=None,
                        help="open-set protocol: the k of θ_p + k·s_p whose unknown-place rejection the cells report "
                             "(default 0, the paper's θ_p; added to --k-grid when missing)")
    parser.add_argument("--k-grid", type=float, nargs="+", default=None,
                        help="open-set protocol: the trade-off's k values (default "
                             f"{' '.join(f'{k:g}' for k in K_GRID)})")
    parser.add_argument("--database", nargs="+", default=None, help="traversal protocol: database traversal(s)")
    parser.add_argument("--queries", default=None, help="traversal protocol: query traversal")
    parser.add_argument("--tolerance", type=int, default=0,
                        help="frames of slack: a place is right when one of its frames is within this many frames of "
                             "the query's (default 0)")
    parser.add_argument("--theta", type=float, default=None, help="also evaluate this global threshold in each cell")
    parser.add_argument("--no-pr", action="store_true",
                        help="skip precision–recall (faster; the AUC column stays empty)")
    parser.add_argument("--metric", nargs="+", choices=[m.value for m in Metric], default=None,
                        help="the grids to print (default all: " +
                             ", ".join(f"{m.value} = {METRIC_LABELS[m]}" for m in Metric).replace("%", "%%") + ")")
    parser.add_argument("--csv", type=Path, default=None, help="write one row per cell, every setting in a column")
    parser.add_argument("--json", type=Path, default=None, help="write the settings and every cell as JSON")


def _write(path: Path | None, text: str, option: str) -> None:
    if path is None:
        return
    try:
        path.write_text(text)
    except OSError as exc:
        raise VPRInputError(f"{option} {path}: cannot write ({exc.strerror}); pick a writable path") from exc
    print(f"wrote {path}")


def run(args: argparse.Namespace) -> int:
    """Run the sweep ``args`` describe; print the cost, the grids and why cells are empty; write CSV/JSON."""
    from vpr_explorer.cli import _bar, _protocol_options, check_radius_option
    from vpr_explorer.data.traversals import Dataset
    from vpr_explorer.pipeline import dataset_descriptors, imported_descriptors, open_dataset
    from vpr_explorer.settings import check_cache_root
    from vpr_explorer.protocols.sweep import SweepSpec, empty_reasons, missing_reasons, sweep, sweep_cost, table

    check_radius_option(args)
    for option in ("radius", "geometry"):
        if getattr(args, option) is not None:
            raise VPRInputError(f"--{option} applies to database/queries layouts; a sweep reads aligned traversal "
                                "folders, whose places group/step make")
    o = _protocol_options(args, PROTOCOL_OPTIONS)
    spec = SweepSpec(groups=args.groups, steps=args.steps, readings=args.reading, protocol=args.protocol,
                     method=args.method, k=o["k"], runs=o["runs"], seed=o["seed"],
                     cross_condition=o["cross_condition"], unknown_share=o["unknown_share"],
                     database=o["database"], queries=o["queries"], tolerance=args.tolerance, user_theta=args.theta,
                     k_grid=o["k_grid"], pr=not args.no_pr)
    if args.descriptors is not None and args.descriptor is not None:
        raise VPRInputError(f"--descriptor {args.descriptor} and --descriptors {args.descriptors}: give one")
    if args.names is not None and args.descriptors is None:
        raise VPRInputError("--names goes with a .npy --descriptors FILE")
    if args.descriptors is None:
        check_cache_root(args.cache_dir)
    dataset = open_dataset(args.dataset, args.layout)
    if not isinstance(dataset, Dataset):
        raise VPRInputError(f"{args.dataset} is a {dataset.layout.value} layout: a sweep reads aligned traversal "
                            "folders (group/step over their frames); evaluate it with `vpr-explorer evaluate`")
    cost = sweep_cost(dataset, spec)  # also refuses a dataset whose file names fix the places, before extraction
    print(f"{dataset.name}: {cost.describe()}")
    source: dict[str, str] = {}
    if args.descriptors is not None:
        imp = imported_descriptors(dataset, args.descriptors, names_file=args.names, dtype=args.dtype)
        desc, descriptor, source = imp.descriptors, imp.name, imp.settings()
    else:
        descriptor = args.descriptor or "efficientnet-lite0"
        desc = dataset_descriptors(dataset, descriptor, cache_root=args.cache_dir, progress=_bar("descriptors"),
                                   dtype=args.dtype)
    result = sweep(dataset, desc, spec, descriptor=descriptor, progress=_bar("sweep cells"),
                   cell_progress=_bar(f"{spec.protocol.value} protocol"), source=source)
    metrics = [Metric(m) for m in (args.metric or [m.value for m in Metric])]
    print(f"{spec.protocol.value} protocol, {descriptor}, method {spec.method}"
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
    for metric in metrics:
        best = result.best(metric)
        if best is not None:
            print(f"best {metric.value}: group {best.group}, step {best.step} ({best.reading.value})")
    _write(args.csv, result.to_csv(), "--csv")
    _write(args.json, result.to_json(), "--json")
    return 0
