"""``vpr-explorer bench``: every dataset × descriptor × protocol in one run: one table, CSV, JSON and an HTML report.

    vpr-explorer bench --datasets GardensPointWalking demo --descriptors pixels efficientnet-lite0 \\
        --protocols paper open-set --runs 10 --out bench/

Each cell runs as ``vpr-explorer evaluate --pr`` of the same settings runs it
(``protocols.many``: the numbers are the same), each dataset read once and each dataset ×
descriptor's descriptors extracted (or read from the cache or a file) once for all its
protocols, timed, with its peak memory. ``--out DIR`` receives ``bench.csv`` (the table,
one row per cell × method, every setting in a column), ``bench.json`` (strict JSON: every
setting, each dataset and descriptors step, each cell's numbers with the ``evaluate``
command that gives them alone; a ``hub:`` descriptor's cells and step record its ``--hub-*``
flags as ``"hub_options"``) and ``report.html`` (self-contained: the table and each
dataset's figures, Plotly inlined, nothing loaded from the network); a DIR that holds
anything is refused unless ``--overwrite``.

The options are ``evaluate``'s, with ``--datasets``, ``--descriptors`` and ``--protocols``
taking several values; a protocol option goes to the protocols that read it. A failing
cell (a dataset that cannot be read, an option or protocol that does not apply to it) is
reported in the table with its message and the rest still run.

Exit status: 0 when every cell ran, 1 when any failed, 2 for bad options (one ``error:`` line).
"""

from __future__ import annotations

import argparse
import json
import shlex
from pathlib import Path

from vpr_explorer.cli.common import (
    CACHE_HELP,
    add_hub_args,
    add_split_args,
    bar,
    default_note,
    hub_options,
    number,
    write_text,
)
from vpr_explorer.data.groundtruth import DEFAULT_RADIUS
from vpr_explorer.data.layouts import Layout
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import PlaceGeometry, Reading
from vpr_explorer.method.retrieval import METHODS_BY_KEY
from vpr_explorer.protocols.evaluation import Protocol
from vpr_explorer.protocols.options import K_GRID

#: what ``--out DIR`` receives
OUTPUTS = ("bench.csv", "bench.json", "report.html")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``bench``'s options: the datasets, descriptors, protocols and methods; ``evaluate``'s others; the outputs."""
    p.add_argument("--datasets", nargs="+", required=True, metavar="DATASET",
                   help="dataset folders (or manifest .csv files), or 'demo' for the built-in route")
    p.add_argument("--descriptors", nargs="+", default=None, metavar="NAME",
                   help="extractors, each run on every dataset (e.g. pixels efficientnet-lite0), or "
                        "hub:DIR[:ENTRY] for a model of a local torch.hub repository")
    add_hub_args(p)
    p.add_argument("--descriptors-file", action="append", default=None, metavar="DATASET=FILE",
                   help="descriptors computed elsewhere for one dataset of --datasets (.npz, .npy with rows in "
                        "'vpr-explorer list' order or names in FILE.txt, or an hloc .h5; or a VPR-methods-evaluation "
                        "log folder for a database-queries dataset), named by the file's (folder's) stem; repeat for "
                        "more")
    p.add_argument("--protocols", nargs="+", choices=[x.value for x in Protocol], default=None,
                   help="the protocols every dataset runs (default: each layout's: paper for aligned traversals, "
                        f"{Protocol.DATABASE.value} for a database/queries layout)")
    p.add_argument("--methods", nargs="+", default=None, metavar="KEY",
                   help=f"the methods of the table, by key: {', '.join(METHODS_BY_KEY)} (default: every one a "
                        "cell evaluates; global-user is --theta's)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help=f"folder for {', '.join(OUTPUTS)}; created when missing")
    p.add_argument("--overwrite", action="store_true", help="write into --out even when it holds files")
    p.add_argument("--layout", choices=[x.value for x in Layout], default=Layout.AUTO.value,
                   help="how every dataset is laid out (auto detects each)")
    p.add_argument("--radius", type=float, default=None,
                   help="position-tagged layouts: a database image within this many metres is right"
                        + default_note(DEFAULT_RADIUS))
    p.add_argument("--geometry", choices=[g.value for g in PlaceGeometry], default=None,
                   help="database/queries layouts: group/step count database images in order (frames), or metres "
                        "along the route (route) or of a lattice (lattice); default route or lattice where the "
                        "layout has positions, else frames")
    p.add_argument("--group", type=number, default=3, help="consecutive frames (or metres, see --geometry) per place")
    p.add_argument("--step", type=number, default=10, help="frames (or metres) from one place to the next")
    p.add_argument("--reading", choices=[r.value for r in Reading], default=Reading.STRIDE.value,
                   help="stride: a place starts every STEP frames (authors' code); skip: take GROUP, skip STEP "
                        "(paper text)")
    add_split_args(p)
    p.add_argument("--k-grid", "--k", dest="k_grid", type=float, nargs="+", default=None, metavar="K",
                   help="open-set protocol: k values of θ_p + k·s_p (--k as evaluate names it)"
                        + default_note(list(K_GRID)))
    p.add_argument("--database", nargs="+", default=None,
                   help="traversal protocol: database traversal(s) (default: a traversal named ref, reference, "
                        "database, db or map, else the first); a layout of traversals with positions: its database")
    p.add_argument("--queries", default=None,
                   help="traversal protocol: query traversal (default: one named query, queries, q or live, else "
                        "the last); a layout of traversals with positions: its queries")
    p.add_argument("--tolerance", type=int, default=None,
                   help="aligned traversals: frames of slack: a place is right when one of its frames is within "
                        "this many frames of the query's" + default_note(0))
    p.add_argument("--theta", type=float, default=None, help="also evaluate this global threshold (a finite number)")
    p.add_argument("--cache-dir", type=Path, default=None, help=CACHE_HELP)
    p.add_argument("--dtype", choices=["float32", "float16"], default="float32",
                   help="descriptor precision in memory and in the cache")


def run(args: argparse.Namespace) -> int:
    """Run the bench ``args`` describe; print the table; write ``--out``.

    Returns:
        0 when every cell ran, 1 when any failed (bad options raise ``VPRInputError``: exit 2).
    """
    from vpr_explorer import pipeline
    from vpr_explorer.protocols.many import run_bench
    from vpr_explorer.views.many_report import bench_html

    spec = bench_spec(args)
    out = _check_out(args.out, args.overwrite)
    result = run_bench(spec, pipeline, progress_for=bar)
    commands = [shlex.join(evaluate_argv(args, spec, cell)) for cell in result.cells]
    print(f"{len(result.cells)} cells ({len(result.failed)} failed) · {result.seconds:.1f} s")
    print()
    print(result.table())
    print()
    for d in result.datasets:
        for note in d.notes:
            print(f"{d.name}: {note}")
    data = result.to_dict()
    for cell, command in zip(data["cells"], commands):
        cell["evaluate"] = command
    write_text(out / OUTPUTS[0], result.to_csv(), "--out")
    write_text(out / OUTPUTS[1], json.dumps(data, indent=2, allow_nan=False), "--out")
    write_text(out / OUTPUTS[2], bench_html(result, commands=commands), "--out")
    return 1 if result.failed else 0


def bench_spec(args: argparse.Namespace):
    """The ``protocols.many.BenchSpec`` of the command line (``--descriptors-file DATASET=FILE`` split)."""
    from vpr_explorer.protocols.many import BenchSpec

    files = []
    for item in args.descriptors_file or ():
        owner = max((d for d in args.datasets if item.startswith(d + "=")), key=len, default=None)
        if owner is None:
            raise VPRInputError(f"--descriptors-file {item}: give DATASET=FILE, DATASET one of --datasets "
                                f"({' '.join(args.datasets)})")
        files.append((owner, Path(item[len(owner) + 1:])))
    return BenchSpec(
        datasets=tuple(args.datasets), descriptors=tuple(args.descriptors or ()),
        descriptor_options=tuple(hub_options(args, args.descriptors or []).items()), descriptor_files=tuple(files),
        protocols=None if args.protocols is None else tuple(args.protocols),
        methods=None if args.methods is None else tuple(args.methods), group=args.group, step=args.step,
        reading=args.reading, geometry=args.geometry, layout=args.layout, radius=args.radius, runs=args.runs,
        seed=args.seed, cross_condition=args.cross_condition, unknown_share=args.unknown_share,
        k_grid=None if args.k_grid is None else tuple(args.k_grid), database=None if args.database is None else
        tuple(args.database), queries=args.queries, tolerance=args.tolerance, theta=args.theta, dtype=args.dtype,
        cache_root=args.cache_dir)


def _check_out(out: Path, overwrite: bool) -> Path:
    """``--out``, created; refused when it is a file, or holds anything and ``--overwrite`` is not given."""
    out = out.expanduser()
    if out.exists() and not out.is_dir():
        raise VPRInputError(f"--out {out}: a file, not a folder; name a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise VPRInputError(f"--out {out}: the folder holds files; name an empty or new folder, or add --overwrite")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise VPRInputError(f"--out {out}: cannot create it ({exc.strerror}); pick a writable folder") from exc
    return out


#: evaluate's option of each protocol option the bench routes, by ``BenchSpec`` field
_ROUTED = {"runs": "--runs", "seed": "--seed", "cross_condition": "--cross-condition",
           "unknown_share": "--unknown-share", "k_grid": "--k", "database": "--database", "queries": "--queries"}


def evaluate_argv(args: argparse.Namespace, spec, cell) -> list[str]:
    """The ``vpr-explorer evaluate`` command line that runs ``cell`` alone (the numbers are the same).

    The protocol options go where the cell's protocol reads them (``protocols.many.PROTOCOL_OPTIONS``);
    the dataset options as given.
    """
    from vpr_explorer.descriptors.hub import hub_flags
    from vpr_explorer.protocols.many import PROTOCOL_OPTIONS

    argv = ["vpr-explorer", "evaluate", "--dataset", cell.source]
    file = next((f for d, f in spec.descriptor_files if d == cell.source and f.stem == cell.descriptor), None)
    argv += ["--descriptors", str(file)] if file is not None else ["--descriptor", cell.descriptor]
    argv += hub_flags(spec.extractor_options(cell.descriptor)) if file is None else []
    if cell.protocol is not None:
        argv += ["--protocol", cell.protocol.value]
    if args.layout != Layout.AUTO.value:
        argv += ["--layout", args.layout]
    for name, flag in (("radius", "--radius"), ("geometry", "--geometry"), ("tolerance", "--tolerance"),
                       ("theta", "--theta"), ("cache_dir", "--cache-dir")):
        if getattr(args, name) is not None:
            argv += [flag, str(getattr(args, name))]
    argv += ["--group", str(args.group), "--step", str(args.step), "--reading", args.reading]
    for name, flag in _ROUTED.items():
        value = getattr(spec, name)
        if value is None or cell.protocol not in PROTOCOL_OPTIONS[name][0]:
            continue
        if isinstance(value, bool):
            argv += [flag] if value else []
        else:
            argv += [flag, *map(str, value if isinstance(value, tuple) else (value,))]
    if args.dtype != "float32":
        argv += ["--dtype", args.dtype]
    return [*argv, "--pr"]
