"""``vpr-explorer acceptance``: every acceptance rule on one dataset's queries, the authors' table.

Runs ``protocols.acceptance.acceptance_report`` (its module doc defines the rules, the
counts, the closed set and the natural open set) on one dataset value and prints
``render_report``; ``--json FILE`` writes ``AcceptanceReport.to_dict()`` as strict JSON
(no NaN), with every setting that shaped the numbers.

The dataset value:

* **aligned traversal folders** (and prepared places): one query traversal against **one**
  database traversal (``data.aligned.database_queries``), since the sequence rules read one
  route in order. ``--queries`` and ``--database`` pick them; by default they are what the
  traversal protocol of ``evaluate`` picks (``pipeline.default_traversals``: names, else the
  last traversal against the first), keeping only the first database traversal where that
  default names several (the output says so). A database image is right for a query within
  ``--tolerance`` frames of its frame (default ``TOLERANCE`` = 2: the authors' ±2).
* **database/queries layouts**: the layout's own queries, database and ground truth
  (``--tolerance`` is refused: ``--radius`` makes position-tagged ground truth); a
  traversal-positions layout whose default database is several traversals keeps the first,
  as above. Where the database or the queries are not one route in order (database/ +
  queries/, a manifest), the bench leaves the sequence rules and the natural open set out
  and says why.

Places of the per-place rules: group/step (``--group``, ``--step``, ``--reading``; in
metres with ``--geometry route|lattice`` on a layout with positions, as ``evaluate`` reads
them) or discovered online (``--places discovered``); a place scores its best similarity
(``--place-score best``, the paper) or the mean (``mean``).

The bench's own choices (``protocols.acceptance.BenchOptions``, defaults there):
``--reference-share`` (0.7), ``--rules``, ``--tau RULE=VALUE`` (a fixed τ for a rule with a
free τ instead of the oracle τ), ``--patch`` (20), ``--fanout`` (5), ``--ds`` (10).
``--authors`` is the authors' follow-up (``AUTHORS``): discovered places, mean place score,
±2 frames, fan-out 5; an option given beside it that says otherwise is refused.

Bad input is one ``VPRInputError`` naming the option, raised before any descriptor is
computed where the option alone tells; an option the dataset does not read is refused by
name.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from vpr_explorer.cli.common import add_dataset_args, bar, default_note, descriptor_name, retrieval_dataset, write_text
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import MetricPlaceSpec, PlaceGeometry, PlaceSpec

# protocols.acceptance is imported where the command runs: it imports scipy.stats (about half a second), and the
# parser builds every command's options each time any command starts. Its defaults and choices are restated here for
# the help (tests/test_cli_acceptance.py checks they are the bench's).

#: frames of slack of aligned traversals' ground truth by default: the authors' ±2
TOLERANCE = 2
#: ``protocols.acceptance.BenchOptions``' defaults of the options below
BENCH_DEFAULTS = {"places": "group-step", "place_score": "best", "reference_share": 0.7, "patch": 20, "fanout": 5,
                  "ds": 10}
#: ``PlaceSource`` and ``PlaceScore`` values
PLACES, PLACE_SCORES = ("group-step", "discovered"), ("best", "mean")
#: the rules with a free τ (``BenchRule.free``)
FREE_RULES = ("seqslam", "top1-distance", "pa-ratio", "sue")
#: what ``--authors`` sets: option -> value (the authors' follow-up)
AUTHORS = {"places": "discovered", "place_score": "mean", "tolerance": TOLERANCE, "fanout": 5}
#: the options ``--authors`` sets, with their value when neither it nor they are given
CHOICES = {"places": BENCH_DEFAULTS["places"], "place_score": BENCH_DEFAULTS["place_score"], "tolerance": TOLERANCE,
           "fanout": BENCH_DEFAULTS["fanout"]}
#: ``BenchOptions`` field -> its option
BENCH_FLAGS = {"rules": "--rules", "places": "--places", "place_score": "--place-score",
               "reference_share": "--reference-share", "patch": "--patch", "fanout": "--fanout", "ds": "--ds"}


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``acceptance``'s options: the dataset's (``common.add_dataset_args``), the traversals, the bench's, --json."""
    add_dataset_args(p)
    p.add_argument("--database", nargs="+", default=None, metavar="TRAVERSAL",
                   help="traversal folders: the one database traversal (the sequence rules read one route); "
                        "default: the traversal protocol's (a traversal named ref, reference, database, db or map, "
                        "else the first), the first of them where it names several")
    p.add_argument("--queries", default=None, metavar="TRAVERSAL",
                   help="traversal folders: the query traversal (default: one named query, queries, q or live, "
                        "else the last)")
    p.add_argument("--tolerance", type=int, default=None,
                   help="aligned traversals: a database image within this many frames of the query's frame is right"
                        + default_note(TOLERANCE) + ", the authors' ±2")
    p.add_argument("--places", choices=PLACES, default=None,
                   help="the per-place rules' places: group/step (--group, --step), or discovered online from the "
                        "database" + default_note(CHOICES["places"]))
    p.add_argument("--place-score", choices=PLACE_SCORES, default=None,
                   help="a place's score for a query: its best similarity (paper) or the mean (authors' follow-up)"
                        + default_note(CHOICES["place_score"]))
    p.add_argument("--reference-share", type=float, default=BENCH_DEFAULTS["reference_share"],
                   help="natural open set: the share of the database route kept as its database, as the authors")
    p.add_argument("--rules", nargs="+", default=None, metavar="RULE",
                   help="run only these rules, by key: baseline, per-place, per-query, seqslam, … (an unknown key "
                        "lists them all; default: every one that applies)")
    p.add_argument("--tau", action="append", default=None, metavar="RULE=VALUE",
                   help=f"a fixed τ for a rule with a free τ ({', '.join(FREE_RULES)}), instead of the oracle τ "
                        "(best F1 on these queries); repeat for several rules")
    p.add_argument("--patch", type=int, default=BENCH_DEFAULTS["patch"], help="per-query threshold: patch size p")
    p.add_argument("--fanout", type=int, default=None,
                   help="graph matcher: from one query to the next the path moves at most this many database "
                        "images back (one fewer forward)" + default_note(CHOICES["fanout"]))
    p.add_argument("--ds", type=int, default=BENCH_DEFAULTS["ds"], help="SeqSLAM: sequence length in queries")
    p.add_argument("--authors", action="store_true",
                   help="the authors' follow-up choices: --places discovered --place-score mean --tolerance 2 "
                        "--fanout 5")
    p.add_argument("--json", type=Path, default=None,
                   help="write the numbers, and every setting that shaped them, to this JSON file")


def run(args: argparse.Namespace) -> int:
    """Run the bench on the dataset ``args`` names; print the table, write ``--json``.

    Returns:
        0 (bad input raises ``VPRInputError``).
    """
    from vpr_explorer.method.places import retrieval_places
    from vpr_explorer.protocols.acceptance import acceptance_report, render_report

    choices = authors_choices(args)
    options = bench_options(args, choices)
    descriptor = descriptor_name(args)
    if args.descriptors is None:
        from vpr_explorer.settings import check_cache_root

        check_cache_root(args.cache_dir)  # an unusable cache folder fails before the dataset is read
    value, lines, settings = dataset_value(args, choices)
    labels = None
    if options.places == "group-step":
        spec, metric = place_specs(args, value)
        labels, n_places = retrieval_places(value, spec, metric)
        how = ("places from the layout" if value.database_place is not None
               else metric.describe() if metric is not None else spec.describe())
        settings["group/step"] = f"{n_places} places ({how})"
    desc, descriptor, source, notes = value_descriptors(args, value, descriptor)
    settings = {"descriptor": descriptor, **source, "dtype": args.dtype, **settings, "authors": args.authors}
    if options.rules is not None:
        settings["rules"] = list(options.rules)
    if options.taus:
        settings["taus"] = dict(options.taus)  # render_report marks the other free rules' τ as the oracle's
    report = acceptance_report(value, desc, labels=labels, options=options, settings=settings)
    for line in (*lines, *notes, *places_lines(options, settings), *authors_lines(args, value)):
        print(line)
    print(render_report(report))
    if args.json is not None:
        write_text(args.json, json.dumps(report.to_dict(), indent=2, allow_nan=False, default=_not_json), "--json")
    return 0


# --------------------------------------------------------------------------- the options


def authors_choices(args: argparse.Namespace) -> dict:
    """The values of the options ``--authors`` sets: given, else the authors' (with ``--authors``), else the defaults.

    Raises:
        VPRInputError: ``--authors`` beside one of those options given another value.
    """
    out = {}
    for name, default in CHOICES.items():
        given = getattr(args, name)
        if args.authors and given is not None and given != AUTHORS[name]:
            option = "--" + name.replace("_", "-")
            raise VPRInputError(f"--authors sets {option} {AUTHORS[name]}, and {option} {given} was given: drop one "
                                "of them")
        out[name] = given if given is not None else AUTHORS[name] if args.authors else default
    return out


def parse_taus(items: list[str] | None, rules: tuple[str, ...] | None) -> dict[str, float]:
    """``--tau RULE=VALUE`` items as rule key -> τ.

    Args:
        items: the ``--tau`` values as given (None: none).
        rules: the ``--rules`` asked for (None: all).

    Raises:
        VPRInputError: an item not written RULE=VALUE, a rule that is not one with a free τ or not
            among ``--rules``, a value that is not a finite number, a rule given twice.
    """
    from vpr_explorer.protocols.acceptance import RULES_BY_KEY

    taus: dict[str, float] = {}
    for item in items or ():
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise VPRInputError(f"--tau {item}: write RULE=VALUE, e.g. --tau seqslam=0.9")
        if key not in RULES_BY_KEY:
            raise VPRInputError(f"--tau {item}: {key!r} is not a rule; rules with a free τ: {', '.join(FREE_RULES)}")
        if not RULES_BY_KEY[key].free:
            raise VPRInputError(f"--tau {item}: {key} has thresholds of its own and takes no τ; only the rules with a "
                                f"free τ do: {', '.join(FREE_RULES)}")
        if rules is not None and key not in rules:
            raise VPRInputError(f"--tau {item}: {key} is not among --rules {' '.join(rules)}: add it or drop the τ")
        if key in taus:
            raise VPRInputError(f"--tau {key} given twice: give one τ per rule")
        try:
            tau = float(text)
        except ValueError:
            tau = math.nan
        if not math.isfinite(tau):
            raise VPRInputError(f"--tau {item}: τ must be a finite number, e.g. --tau {key}=0.9")
        taus[key] = tau
    return taus


def bench_options(args: argparse.Namespace, choices: dict):
    """The ``protocols.acceptance.BenchOptions`` the command line gives, each value refused by its option.

    Args:
        args: the parsed command line.
        choices: the values of the options ``--authors`` sets (:func:`authors_choices`).

    Raises:
        VPRInputError: naming the option (``--rules``, ``--tau``, ``--reference-share``, ``--patch``,
            ``--fanout``, ``--ds``) and what it takes.
    """
    from vpr_explorer.protocols.acceptance import RULES_BY_KEY, BenchOptions

    rules = None
    if args.rules is not None:
        unknown = [r for r in args.rules if r not in RULES_BY_KEY]
        if unknown:
            raise VPRInputError(f"--rules {' '.join(unknown)}: not a rule; choose from {', '.join(RULES_BY_KEY)}")
        rules = tuple(dict.fromkeys(args.rules))
    fields = {"rules": rules, "places": choices["places"], "place_score": choices["place_score"],
              "reference_share": args.reference_share, "patch": args.patch, "fanout": choices["fanout"],
              "ds": args.ds}
    for name, value in fields.items():
        try:
            BenchOptions(**{name: value})
        except VPRInputError as exc:
            text = str(exc)
            why = text.partition(": ")[2] if text.startswith(f"{name}=") else text
            raise VPRInputError(f"{BENCH_FLAGS[name]} {value}: {why}") from None
    return BenchOptions(**fields, taus=parse_taus(args.tau, rules))


# --------------------------------------------------------------------------- the dataset value


def dataset_value(args: argparse.Namespace, choices: dict):
    """The dataset value ``args`` names, the lines that say how it was chosen, and its settings.

    Returns:
        ``(value, lines, settings)``: a ``data.layouts.RetrievalDataset``, the lines to print
        before the table, and the traversals and tolerance for the report's settings.

    Raises:
        VPRInputError: several ``--database`` traversals for aligned traversals, ``--tolerance``
            or the traversal options on a layout that does not read them, or what opening the
            dataset raises.
    """
    dataset = retrieval_dataset(args)
    if dataset is not None:
        return _layout_value(args, dataset)
    from vpr_explorer.data.aligned import database_queries
    from vpr_explorer.pipeline import default_traversals, open_dataset, traversal_direction
    from vpr_explorer.protocols.options import check_whole

    if args.database is not None and len(args.database) > 1:
        raise VPRInputError(f"--database {' '.join(args.database)}: give one database traversal; the sequence rules "
                            "read the database as one route in order")
    aligned = open_dataset(args.dataset, args.layout)
    tolerance = check_whole("--tolerance", choices["tolerance"], low=0, high=aligned.n_frames,
                            why=f" (frames of slack; {aligned.name!r} has {aligned.n_frames:,} frames)")
    db, q = default_traversals(aligned, args.database, args.queries)
    names = [aligned.traversals[t] for t in db]
    how = "as given" if args.database or args.queries else traversal_direction(aligned, db, q)
    lines = [f"{aligned.name}: queries {aligned.traversals[q]} against database {names[0]} ({how}); right: database "
             f"frames within ±{tolerance} frames of the query's"]
    if len(db) > 1:
        lines.append(f"database: {names[0]}, the first of the default database traversals {', '.join(names)}; the "
                     "sequence rules read one route: pick another with --database")
    value = database_queries(aligned, q, database=db[:1], tolerance=tolerance)
    return value, lines, {"database": names[0], "queries": aligned.traversals[q], "tolerance": tolerance}


def _layout_value(args: argparse.Namespace, dataset):
    """``dataset_value`` for a database/queries layout: its own queries and ground truth."""
    from vpr_explorer.data.layouts import Layout
    from vpr_explorer.pipeline import open_dataset

    layout = dataset.layout.value
    if args.tolerance is not None:
        raise VPRInputError(f"--tolerance counts frames of aligned traversals; {dataset.name} is a {layout} layout, "
                            f"whose ground truth says which images are right ({dataset.ground_truth.description}): "
                            "drop --tolerance (position-tagged layouts: --radius)")
    lines, notes = [], dataset.notes  # the loader's notes name the traversals it picked by default
    if dataset.layout is Layout.TRAVERSAL_POSITIONS:
        if args.database is not None and len(args.database) > 1:
            raise VPRInputError(f"--database {' '.join(args.database)}: give one database traversal; the sequence "
                                "rules read the database as one route in order")
        if args.database is None and not dataset.ordered:
            names = [dataset.traversals[t] for t in dict.fromkeys(dataset.database_traversal.tolist())]
            query = dataset.traversals[int(dataset.query_traversal[0])]
            lines.append(f"database: {names[0]}, the first of the default database traversals {', '.join(names)}; "
                         "the sequence rules read one route: pick another with --database")
            dataset = open_dataset(args.dataset, layout, radius=args.radius, database=[names[0]], queries=query)
    else:
        for option in ("database", "queries"):
            if getattr(args, option) is not None:
                raise VPRInputError(f"--{option} picks traversal folders; {dataset.name} is a {layout} layout, whose "
                                    f"queries and database are given: drop --{option}")
    lines = [dataset.describe(), *notes, *lines]
    settings = {"layout": layout}
    if dataset.layout is Layout.TRAVERSAL_POSITIONS:
        settings["database"] = [dataset.traversals[t] for t in dict.fromkeys(dataset.database_traversal.tolist())]
        settings["queries"] = dataset.traversals[int(dataset.query_traversal[0])]
    return dataset, lines, settings


def place_specs(args: argparse.Namespace, value) -> tuple[PlaceSpec | None, MetricPlaceSpec | None]:
    """``(PlaceSpec, MetricPlaceSpec)`` of ``--group``/``--step``/``--reading``: one of them, by ``--geometry``.

    The geometry defaults to frames without database positions, else route along an ordered
    database and lattice over an unordered one (as ``evaluate`` reads it); aligned traversals
    count frames.
    """
    geometry = args.geometry
    if geometry is None:
        geometry = ("frames" if value.database_xy is None or value.aligned is not None
                    else "route" if value.ordered else "lattice")
    if PlaceGeometry(geometry) is PlaceGeometry.FRAMES:
        return PlaceSpec(args.group, args.step, args.reading), None
    return None, MetricPlaceSpec(args.group, args.step, args.reading, geometry)


def value_descriptors(args: argparse.Namespace, value, descriptor: str):
    """The value's descriptors (database rows first): extracted through the cache, or read from ``--descriptors``.

    Returns:
        ``(descriptors, name, source, notes)``: the ``(n_images, D)`` matrix, the descriptor's
        name, the file's path and sha256 (empty for an extractor) and what reading the file noted.
    """
    from vpr_explorer.data.aligned import value_rows
    from vpr_explorer.pipeline import dataset_descriptors, imported_descriptors

    if args.descriptors is None:
        desc = dataset_descriptors(value, descriptor, cache_root=args.cache_dir, progress=bar("descriptors"),
                                   dtype=args.dtype)
        return desc, descriptor, {}, ()
    # a file lists the dataset's images ('vpr-explorer list'): aligned traversals' rows move to the value's order
    owner = value if value.aligned is None else value.aligned
    imp = imported_descriptors(owner, args.descriptors, names_file=args.names, dtype=args.dtype)
    rows = value_rows(value) if value.aligned is not None else None
    desc = imp.descriptors if rows is None else imp.descriptors[rows]
    return desc, imp.name, imp.settings(), tuple(f"{args.descriptors.name}: {note}" for note in imp.notes)


# --------------------------------------------------------------------------- what is printed


def places_lines(options, settings: dict) -> list[str]:
    """One line naming the per-place rules' places and place score."""
    where = ("discovered online from the database" if options.places == "discovered"
             else settings.get("group/step", "group/step"))
    return [f"places: {where}; place score: {options.place_score.value} similarity of a place's images"]


def authors_lines(args: argparse.Namespace, value) -> list[str]:
    """The line saying what ``--authors`` set (none without it)."""
    if not args.authors:
        return []
    if value.aligned is not None:
        return ["--authors: the authors' follow-up choices: discovered places, mean place score, ±2 frames, "
                "fan-out 5"]
    return ["--authors: the authors' follow-up choices: discovered places, mean place score, fan-out 5 (their ±2 "
            f"frames: {value.name} has its own ground truth)"]


def _not_json(o):
    raise TypeError(f"not JSON: {type(o)}")
