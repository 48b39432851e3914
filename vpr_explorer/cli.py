"""Command line: ``vpr-explorer evaluate …`` (and the other sub-commands).

Bad input prints one ``error:`` line naming the file or parameter and exits 2; Ctrl-C
prints one ``error: interrupted`` line and exits 130. Either way the progress bars are
cleared first, so that the line stands on its own.
"""

from __future__ import annotations

import sys

if __name__ == "__main__":
    # ``python -m vpr_explorer.cli`` runs as the console script does: Ctrl-C is handled before the imports below
    from vpr_explorer.entry import main as _entry_main

    sys.exit(_entry_main())

import argparse
import json
from pathlib import Path

from vpr_explorer.errors import VPRInputError
from vpr_explorer.protocols.evaluation import K_GRID, Protocol
from vpr_explorer.pipeline import MAX_RUNS
from vpr_explorer.method.places import PlaceSpec, Reading

INTERRUPTED = "interrupted; run the same command again to resume (descriptors computed so far are cached)"

class _Bars:
    """The progress bars drawn on stderr, so that an ``error:`` line never lands on one's line."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.open: list = []
        self.drawn = False

    def clear(self) -> None:
        """Close the unfinished bars and end their line, so that what follows starts a line of its own."""
        while self.open:
            self.open.pop().close()
        if self.drawn:
            sys.stderr.write("\n")
            sys.stderr.flush()
        self.reset()


_bars = _Bars()


def _bar(desc: str):
    """A ``progress(done, total, *message)`` callback drawing a tqdm bar on stderr; the message goes beside it."""
    from tqdm import tqdm

    state: dict = {}

    def update(done: int, total: int, *message):
        if "bar" not in state:
            _bars.drawn = True  # before the bar exists: Ctrl-C may land while it is being drawn
            state["bar"] = tqdm(total=total, desc=desc, unit="", file=sys.stderr, leave=False, dynamic_ncols=True)
            _bars.open.append(state["bar"])
        bar = state["bar"]
        if message and message[0]:
            bar.set_postfix_str(str(message[0]), refresh=False)
        bar.update(done - bar.n)
        if done >= total and bar in _bars.open:
            bar.close()
            _bars.open.remove(bar)

    return update


def _number(text: str) -> int | float:
    """A group/step value: a whole number of frames, or metres (which may have a fraction)."""
    try:
        return int(text)
    except ValueError:
        pass
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    return int(value) if value.is_integer() and abs(value) < 2**63 else value


def add_dataset_args(p: argparse.ArgumentParser) -> None:
    """Arguments shared by every sub-command that reads a dataset."""
    from vpr_explorer.data.layouts import Layout
    from vpr_explorer.method.places import PlaceGeometry

    p.add_argument("--dataset", required=True,
                   help="dataset folder (or a manifest .csv), or 'demo' for the built-in route")
    p.add_argument("--layout", choices=[x.value for x in Layout], default=Layout.AUTO.value,
                   help="how the dataset is laid out (default: detected): aligned traversal folders, prepared "
                        "Place####_Cond##_G## images, database/ + queries/ with @UTM@ names, VPR-Bench ref/ + query/ "
                        "+ ground_truth_new.npy, traversal folders with positions.csv, or a manifest CSV")
    p.add_argument("--radius", type=float, default=None,
                   help="position-tagged layouts: a database image within this many metres is right (default 25)")
    p.add_argument("--geometry", choices=[g.value for g in PlaceGeometry], default=None,
                   help="database/queries layouts: group/step count database images in order (frames), or metres "
                        "along the route (route) or of a lattice over the plane (lattice); default route or lattice "
                        "where the layout has positions, else frames")
    p.add_argument("--group", type=_number, default=3,
                   help="consecutive frames (or metres, see --geometry) per place (default 3)")
    p.add_argument("--step", type=_number, default=10,
                   help="frames (or metres) from one place to the next (default 10)")
    p.add_argument("--reading", choices=[r.value for r in Reading], default=Reading.STRIDE.value,
                   help="stride: a place starts every STEP frames (authors' code); skip: take GROUP, skip STEP (paper text)")
    p.add_argument("--descriptor", default=None, help="descriptor name (default efficientnet-lite0)")
    p.add_argument("--descriptors", type=Path, default=None, metavar="FILE",
                   help="descriptors computed elsewhere: .npz (names, descriptors), .npy (rows in `vpr-explorer list` "
                        "order, or names in FILE.txt) or an hloc global-feature .h5; named by the file's stem")
    p.add_argument("--names", type=Path, default=None, metavar="FILE",
                   help="with a .npy --descriptors: the file naming its rows (one image path per line)")
    p.add_argument("--cache-dir", type=Path, default=None, help="descriptor cache (default $VPR_EXPLORER_CACHE)")
    p.add_argument("--dtype", choices=["float32", "float16"], default="float32",
                   help="descriptor precision in memory and in the cache: float16 halves the descriptor memory "
                        "and disk, at about 1e-3 relative error in scores (default float32)")


#: evaluate's options that only some protocols read (argparse default None: "not given"),
#: with the protocols that read them and their value when not given.
PROTOCOL_OPTIONS = {
    "runs": ((Protocol.PAPER, Protocol.OPEN_SET), 50),
    "seed": ((Protocol.PAPER, Protocol.OPEN_SET), 0),
    "cross_condition": ((Protocol.PAPER, Protocol.OPEN_SET), False),
    "unknown_share": ((Protocol.OPEN_SET,), 0.3),
    "k": ((Protocol.OPEN_SET,), list(K_GRID)),
    "database": ((Protocol.TRAVERSAL, Protocol.DATABASE), None),
    "queries": ((Protocol.TRAVERSAL, Protocol.DATABASE), None),
}


def _protocol_options(args: argparse.Namespace, options: dict | None = None) -> dict:
    """The options ``args.protocol`` reads, defaults filled in; one it would ignore is refused, named.

    ``options``: option name -> (the protocols that read it, its default); ``PROTOCOL_OPTIONS`` by default.
    """
    protocol = Protocol(args.protocol)
    values = {}
    for name, (protocols, default) in (PROTOCOL_OPTIONS if options is None else options).items():
        value = getattr(args, name)
        if value is not None and protocol not in protocols:
            option = "--" + name.replace("_", "-")
            owners = " and ".join(p.value for p in protocols)
            raise VPRInputError(
                f"{option} applies to the {owners} protocol{'s' if len(protocols) > 1 else ''} only, and this is "
                f"--protocol {protocol.value}: drop {option}, or pick --protocol {protocols[0].value}"
            )
        values[name] = default if value is None else value
    return values


def check_radius_option(args: argparse.Namespace) -> float | None:
    """``--radius`` when given: a positive number of metres (``groundtruth.check_radius``), else ``None``."""
    from vpr_explorer.data.groundtruth import check_radius

    return None if args.radius is None else check_radius(args.radius, "radius")


def check_radius_applies(args: argparse.Namespace, dataset) -> None:
    """Refuse ``--radius`` for a dataset whose ground truth no radius makes (VPR-Bench, a manifest's place ids)."""
    from vpr_explorer.data.layouts import VPR_BENCH_GT, Layout, RetrievalDataset, radius_applies

    if args.radius is None or (isinstance(dataset, RetrievalDataset) and radius_applies(dataset)):
        return
    if not isinstance(dataset, RetrievalDataset):
        where = "the frame index of aligned traversals"
    elif dataset.layout is Layout.VPR_BENCH:
        where = VPR_BENCH_GT
    elif dataset.layout is Layout.MANIFEST:
        where = "its place column (the same place id)"
    else:
        where = dataset.ground_truth.description
    layout = dataset.layout.value if isinstance(dataset, RetrievalDataset) else "traversal folders"
    raise VPRInputError(f"--radius applies to position-tagged layouts; {args.dataset} is {layout}, which takes its "
                        f"ground truth from {where}: drop --radius")


def _benchmark(args: argparse.Namespace):
    """The dataset when ``--dataset``/``--layout`` name a database/queries layout, else ``None``."""
    from vpr_explorer.data.layouts import RETRIEVAL_LAYOUTS, Layout, detect_layout

    check_radius_option(args)
    if args.dataset == "demo":
        layout = Layout(args.layout)
    else:
        path = Path(args.dataset).expanduser()
        layout = detect_layout(path) if args.layout == Layout.AUTO.value and path.exists() else Layout(args.layout)
    if layout not in RETRIEVAL_LAYOUTS:
        for option in ("radius", "geometry"):
            if getattr(args, option) is not None:
                raise VPRInputError(f"--{option} applies to database/queries layouts; {args.dataset} is read as "
                                    f"{'traversal folders' if layout is Layout.AUTO else layout.value}")
        return None
    from vpr_explorer.pipeline import open_dataset

    dataset = open_dataset(args.dataset, layout.value, radius=args.radius, database=getattr(args, "database", None),
                           queries=getattr(args, "queries", None))
    check_radius_applies(args, dataset)
    return dataset


def _places_spec(args: argparse.Namespace, dataset):
    """``(PlaceSpec, MetricPlaceSpec)`` for a database/queries dataset: one of them, from --geometry."""
    from vpr_explorer.method.places import MetricPlaceSpec, PlaceGeometry

    geometry = args.geometry
    if geometry is None:
        geometry = ("frames" if dataset.database_xy is None else "route" if dataset.ordered else "lattice")
    if PlaceGeometry(geometry) is PlaceGeometry.FRAMES:
        return PlaceSpec(args.group, args.step, args.reading), None
    return None, MetricPlaceSpec(args.group, args.step, args.reading, geometry)


def _evaluate_benchmark(args: argparse.Namespace, dataset) -> int:
    from vpr_explorer.pipeline import dataset_descriptors, evaluate_retrieval, imported_descriptors
    from vpr_explorer.views.report import render
    from vpr_explorer.settings import check_cache_root

    protocol = Protocol(args.protocol or Protocol.DATABASE.value)
    if protocol is not Protocol.DATABASE:
        raise VPRInputError(f"--protocol {protocol.value}: {dataset.name} is a {dataset.layout.value} layout, whose "
                            f"queries are given: use --protocol {Protocol.DATABASE.value} (the default for it)")
    args.protocol = protocol.value
    _protocol_options(args)
    if args.tolerance:
        raise VPRInputError("--tolerance counts frames of aligned traversals; a database/queries layout says which "
                            "images are right by its ground truth (position-tagged: --radius)")
    spec, metric = _places_spec(args, dataset)
    descriptor = _descriptor(args)
    source: dict[str, str] = {}  # a descriptor file's path and sha256: never mistaken for an extractor's run
    if args.descriptors is not None:
        imp = imported_descriptors(dataset, args.descriptors, names_file=args.names, dtype=args.dtype)
        desc, descriptor, source = imp.descriptors, imp.name, imp.settings()
        for note in imp.notes:
            print(f"{args.descriptors.name}: {note}")
    else:
        check_cache_root(args.cache_dir)
        desc = dataset_descriptors(dataset, descriptor, cache_root=args.cache_dir, progress=_bar("descriptors"),
                                   dtype=args.dtype)
    ev = evaluate_retrieval(dataset, desc, spec=spec, metric=metric, user_theta=args.theta,
                            settings={"descriptor": descriptor, **source, "dtype": args.dtype},
                            progress=_bar("queries"), pr=args.pr)
    print(dataset.describe())
    for note in dataset.notes:
        print(note)
    print(render(ev))
    _write_json(args, ev)
    return 0


def _descriptor(args: argparse.Namespace) -> str:
    """The extractor's name; refused beside ``--descriptors FILE`` (the file names the descriptor)."""
    if args.descriptors is not None:
        if args.descriptor is not None:
            raise VPRInputError(f"--descriptor {args.descriptor} and --descriptors {args.descriptors}: give one "
                                "(a file of descriptors computed elsewhere, or an extractor to compute them here)")
        return args.descriptors.stem
    if args.names is not None:
        raise VPRInputError("--names goes with a .npy --descriptors FILE")
    return args.descriptor or "efficientnet-lite0"


def _write_json(args: argparse.Namespace, ev) -> None:
    if args.json:
        try:
            args.json.write_text(json.dumps(ev.to_dict(), indent=2, allow_nan=False, default=_json_default))
        except OSError as exc:
            raise VPRInputError(f"--json {args.json}: cannot write ({exc.strerror}); pick a writable path") from exc
        print(f"wrote {args.json}")


def _evaluate(args: argparse.Namespace) -> int:
    from vpr_explorer.pipeline import evaluate_dataset
    from vpr_explorer.views.report import render

    dataset = _benchmark(args)
    if dataset is not None:
        return _evaluate_benchmark(args, dataset)
    if args.protocol is None:
        args.protocol = Protocol.PAPER.value
    elif Protocol(args.protocol) is Protocol.DATABASE:
        raise VPRInputError(f"--protocol {Protocol.DATABASE.value} needs a database/queries layout (database/ + "
                            "queries/, VPR-Bench, traversals with positions.csv, or a manifest); "
                            f"{args.dataset} holds aligned traversals: use paper, traversal or open-set")
    o = _protocol_options(args)
    ev = evaluate_dataset(
        args.dataset, PlaceSpec(args.group, args.step, args.reading), _descriptor(args), args.protocol,
        cache_root=args.cache_dir, extract_progress=_bar("descriptors"), dtype=args.dtype,
        layout=args.layout, descriptors_file=args.descriptors, names_file=args.names,
        runs=o["runs"], seed=o["seed"], cross_condition=o["cross_condition"], unknown_share=o["unknown_share"],
        database=o["database"], queries=o["queries"], tolerance=args.tolerance, user_theta=args.theta,
        k_grid=o["k"], progress=_bar(f"{args.protocol} protocol"), pr=args.pr,
    )
    print(render(ev))
    _write_json(args, ev)
    return 0


def _list(args: argparse.Namespace) -> int:
    """Every image of the dataset in the order descriptors are computed (rows of a ``.npy`` to bring)."""
    from vpr_explorer.pipeline import open_dataset

    from vpr_explorer.descriptors.imported import relative_names

    check_radius_option(args)
    dataset = open_dataset(args.dataset, args.layout, radius=args.radius)
    check_radius_applies(args, dataset)
    for name in relative_names(dataset.image_paths, dataset.root):  # the names a descriptor file matches
        print(name)
    return 0


def _record(args: argparse.Namespace) -> int:
    from vpr_explorer.recording import record_dataset

    from vpr_explorer.data.layouts import Layout

    check_radius_option(args)
    for option in ("radius", "geometry"):
        if getattr(args, option) is not None:
            raise VPRInputError(f"--{option} applies to database/queries layouts; record plays back aligned "
                                "traversal folders, whose frames say which database images are right")
    if args.layout not in (Layout.AUTO.value, Layout.TRAVERSALS.value):
        raise VPRInputError(f"--layout {args.layout}: record plays back aligned traversal folders only; leave "
                            "--layout out (or give traversals)")
    playback = record_dataset(
        args.dataset, PlaceSpec(args.group, args.step, args.reading), _descriptor(args),
        database=args.database, queries=args.queries, out=args.out, k=args.k, tolerance=args.tolerance,
        cache_root=args.cache_dir, extract_progress=_bar("descriptors"), progress=_bar("frames"), dtype=args.dtype,
        descriptors_file=args.descriptors, names_file=args.names,
    )
    print(playback.describe())
    print(f"wrote {playback.rrd}: watch it with `rerun {playback.rrd}` (or `rerun --web-viewer {playback.rrd}`)")
    return 0


def _json_default(o):
    raise TypeError(f"not JSON: {type(o)}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vpr-explorer", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    ev = sub.add_parser("evaluate", help="run a protocol and print the paper's kind of table")
    add_dataset_args(ev)
    ev.add_argument("--protocol", choices=[p.value for p in Protocol], default=None,
                    help=f"default: paper for aligned traversals, {Protocol.DATABASE.value} for a database/queries "
                         "layout")
    ev.add_argument("--runs", type=int, default=None,
                    help=f"paper and open-set protocols: random splits, at most {MAX_RUNS} (default and paper: 50)")
    ev.add_argument("--seed", type=int, default=None, help="paper and open-set protocols: seed of the splits (default 0)")
    ev.add_argument("--cross-condition", action="store_true", default=None,
                    help="paper and open-set protocols: score each query only against database images of other "
                         "traversals")
    ev.add_argument("--unknown-share", type=float, default=None,
                    help="open-set protocol: share of places held out (default 0.3)")
    ev.add_argument("--k", type=float, nargs="+", default=None,
                    help=f"open-set protocol: k values of θ_p + k·s_p (default {' '.join(f'{k:g}' for k in K_GRID)})")
    ev.add_argument("--database", nargs="+", default=None,
                    help="traversal protocol: database traversal(s) (default: a traversal named ref, reference, "
                         "database, db or map, else the first)")
    ev.add_argument("--queries", default=None,
                    help="traversal protocol: query traversal (default: one named query, queries, q or live, "
                         "else the last)")
    ev.add_argument("--tolerance", type=int, default=0,
                    help="frames of slack: a place is right when one of its frames is within this many frames "
                         "of the query's (default 0; the authors count ±2)")
    ev.add_argument("--theta", type=float, default=None, help="also evaluate this global threshold (a finite number)")
    ev.add_argument("--pr", action="store_true",
                    help="also precision–recall per method (AUC, recall at 100%% and 99%% precision, max F1), pooled "
                         "over runs: the global θ swept over the top scores, the per-place methods over θ_p + k·s_p")
    ev.add_argument("--json", type=Path, default=None,
                    help="write the numbers, and every setting that shaped them, to this JSON file")
    ev.set_defaults(func=_evaluate)

    rec = sub.add_parser("record", help="play a query traversal back against a database: write a rerun .rrd")
    add_dataset_args(rec)
    rec.add_argument("--database", nargs="+", required=True, help="database traversal(s), e.g. day_right")
    rec.add_argument("--queries", required=True, help="query traversal, e.g. night_right")
    rec.add_argument("--out", type=Path, required=True, help="the .rrd file to write, e.g. run.rrd")
    rec.add_argument("--k", type=float, default=0.0, help="thresholds θ_p + k·s_p (default 0: the paper's)")
    rec.add_argument("--tolerance", type=int, default=0, help="frames of slack for a right place (default 0)")
    rec.set_defaults(func=_record)

    ls = sub.add_parser("list", help="print the dataset's images in descriptor order (the rows of a .npy to bring)")
    ls.add_argument("--dataset", required=True, help="dataset folder (or a manifest .csv), or 'demo'")
    ls.add_argument("--layout", default="auto", help="as for evaluate (default: detected)")
    ls.add_argument("--radius", type=float, default=None, help=argparse.SUPPRESS)
    ls.set_defaults(func=_list)

    from vpr_explorer import sweep_cli

    sw = sub.add_parser("sweep", help="run a protocol over a grid of group × step (both readings): tables, CSV, JSON",
                        conflict_handler="resolve")  # its --group/--step/--reading take lists
    sweep_cli.add_arguments(sw)
    sw.set_defaults(func=sweep_cli.run)

    from vpr_explorer import extract_cli

    ex = sub.add_parser("extract", help="fill the descriptor cache for a dataset: local threads, or a Ray cluster "
                                        "with --ray ADDRESS|local")
    extract_cli.add_arguments(ex)
    ex.set_defaults(func=extract_cli.run)

    from vpr_explorer.app import launch

    app = sub.add_parser("app", help="open the explorer: Streamlit on the packaged app, from any directory")
    launch.add_arguments(app)
    app.set_defaults(func=launch.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    _bars.reset()
    try:
        args = build_parser().parse_args(argv)  # the parser imports each command's modules: Ctrl-C is handled here too
        return args.func(args)
    except VPRInputError as exc:
        _bars.clear()
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        from vpr_explorer.descriptors import ExtractionInterrupted

        _bars.clear()
        # Ctrl-C during extraction: the finished batches are cached and the exception says how many.
        print(f"error: interrupted; {exc}" if isinstance(exc, ExtractionInterrupted) else f"error: {INTERRUPTED}",
              file=sys.stderr)
        return 130
