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

**Sweeps** (``--vary PARAM=V1,V2,...``): ``protocols.acceptance_sweep.sweep_bench`` runs the
bench once per value of one parameter: ``ds``, ``patch``, ``fanout``, ``sue_k``,
``reference_share`` (``BenchOptions``' fields) or ``group``, ``step`` (of the group/step
places, in frames, or metres with ``--geometry route|lattice``); the other parameters keep
their options' values, and the varied one's own option is not read. It prints
``acceptance_sweep.render`` (rows = rules, columns = values, cells "closed F1 / open F1 /
rejection") after the bench's table, and ``--json`` holds ``BenchSweep.to_dict()`` under
``"sweep"``. A parameter the dataset value cannot use (every rule that reads it left out, e.g.
``ds`` where the sequence rules are; ``sue_k`` without positions in metres;
``reference_share`` without a natural open set; group/step with discovered places or the
layout's own) is refused by name, with why, before any descriptor is computed.

**VPR_Tutorial's precision–recall** (``--tutorial-pr``): ``protocols.tutorial_pr.tutorial_pr``
on the query × database similarity of the closed set (the queries it counts, the whole
database), matching ``single`` and ``multi``, each on the hard ground truth only and, where the
value has soft positives, with them "ignored" as the tutorial does (their pairs scored min S).
Aligned traversals' soft positives are the database frames within ``--soft-tolerance`` frames
of the query's (default ``SOFT_TOLERANCE`` = 8: VPR_Tutorial's GardensPoint ±8, whose hard
ground truth is the same frame: ``--tolerance 0``); another layout has soft positives where its
ground truth holds them. It prints each curve's AUC and R@100P (``TUTORIAL_ROWS``) and
``--json`` holds the curves under ``"tutorial_pr"``.

Bad input is one ``VPRInputError`` naming the option, raised before any descriptor is
computed where the option alone tells; an option the dataset does not read is refused by
name.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from vpr_explorer.cli.common import (
    add_dataset_args,
    aligned_value,
    bar,
    default_note,
    descriptor_name,
    number,
    retrieval_dataset,
    value_descriptors,
    write_text,
)
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
#: the parameters ``--vary`` takes (``protocols.acceptance_sweep.Parameter``), as whole numbers or not
VARY = {"ds": "whole", "patch": "whole", "fanout": "whole", "sue_k": "whole", "reference_share": "share",
        "group": "place", "step": "place"}
#: aligned traversals: frames of slack of the soft positives of ``--tutorial-pr`` (VPR_Tutorial's GardensPoint ±8)
SOFT_TOLERANCE = 8
#: ``--tutorial-pr``'s curves in print order: (matching, soft positives ignored)
TUTORIAL_ROWS = (("single", False), ("single", True), ("multi", False), ("multi", True))


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
    p.add_argument("--vary", default=None, metavar="PARAM=V1,V2,...",
                   help=f"also run the bench once per value of one parameter ({', '.join(VARY)}) and print the "
                        "table of rules × values (closed F1 / open F1 / rejection); the parameter's own option is "
                        "then not read")
    p.add_argument("--tutorial-pr", action="store_true",
                   help="also print VPR_Tutorial's precision–recall summaries (AUC, R@100P) of the closed set: "
                        "single and multi matching, hard ground truth only and with soft positives ignored")
    p.add_argument("--soft-tolerance", type=int, default=None,
                   help="--tutorial-pr on aligned traversals: a database image within this many frames of the "
                        "query's frame is a soft positive" + default_note(SOFT_TOLERANCE) + ", VPR_Tutorial's "
                        "GardensPoint ±8")
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
    vary = parse_vary(args.vary)
    if args.soft_tolerance is not None and not args.tutorial_pr:
        raise VPRInputError(f"--soft-tolerance {args.soft_tolerance}: it sets the soft positives of --tutorial-pr; "
                            "add --tutorial-pr or drop it")
    descriptor = descriptor_name(args)
    if args.descriptors is None:
        from vpr_explorer.settings import check_cache_root

        check_cache_root(args.cache_dir)  # an unusable cache folder fails before the dataset is read
    value, lines, settings = dataset_value(args, choices)
    labels, spec, metric = None, None, None
    if options.places == "group-step":
        spec, metric = place_specs(args, value)
        labels, n_places = retrieval_places(value, spec, metric)
        how = ("places from the layout" if value.database_place is not None
               else metric.describe() if metric is not None else spec.describe())
        settings["group/step"] = f"{n_places} places ({how})"
    soft_tolerance = tutorial_soft_tolerance(args, value, settings)
    if soft_tolerance is not None:
        settings["soft_tolerance"] = soft_tolerance
    if vary is not None:
        vary = check_vary(args.vary, vary, value, options, labels, spec or metric)
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
    out = report.to_dict()
    if vary is not None:
        from vpr_explorer.protocols.acceptance_sweep import render, sweep_bench

        parameter, values = vary
        sweep = sweep_bench(value, desc, labels=labels, parameter=parameter, values=values, options=options,
                            places=spec or metric, settings=settings, progress=bar(f"{parameter} values"))
        print()
        print(render(sweep))
        out["sweep"] = sweep.to_dict()
    if args.tutorial_pr:
        tutorial = tutorial_curves(value, desc, report.closed.counted, soft_tolerance)
        print()
        for line in tutorial_lines(tutorial):
            print(line)
        out["tutorial_pr"] = tutorial
    if args.json is not None:
        write_text(args.json, json.dumps(out, indent=2, allow_nan=False, default=_not_json), "--json")
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
    if args.database is not None and len(args.database) > 1:
        raise VPRInputError(f"--database {' '.join(args.database)}: give one database traversal; the sequence rules "
                            "read the database as one route in order")
    a = aligned_value(args, choices["tolerance"], first_database_only=True)
    lines = [f"{a.value.name}: queries {a.query} against database {a.database[0]} ({a.how}); right: database "
             f"frames within ±{a.tolerance} frames of the query's"]
    if len(a.defaults) > 1:
        lines.append(f"database: {a.database[0]}, the first of the default database traversals "
                     f"{', '.join(a.defaults)}; the sequence rules read one route: pick another with --database")
    return a.value, lines, {"database": a.database[0], "queries": a.query, "tolerance": a.tolerance}


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


# --------------------------------------------------------------------------- --vary


def parse_vary(text: str | None) -> tuple[str, tuple[int | float, ...]] | None:
    """``--vary PARAM=V1,V2,...`` as ``(parameter, values)`` (``None`` without it); ``sue-k`` is ``sue_k``.

    Raises:
        VPRInputError: not written PARAM=V1,V2,..., a parameter not in ``VARY``, or a value that is
            not a number of the parameter's kind (whole numbers but for ``reference_share``, and
            group/step in metres).
    """
    if text is None:
        return None
    name, sep, rest = text.partition("=")
    name = name.strip().replace("-", "_")
    items = [item.strip() for item in rest.split(",")]
    if not sep or not name or not any(items):
        raise VPRInputError(f"--vary {text}: write PARAM=V1,V2,..., e.g. --vary ds=4,6,10,20")
    if name not in VARY:
        raise VPRInputError(f"--vary {text}: {name!r} is not a parameter the sweep varies; choose from "
                            f"{', '.join(VARY)}")
    values = []
    for item in items:
        try:
            if VARY[name] == "whole":
                values.append(int(item))
            elif VARY[name] == "share":
                values.append(float(item))
            else:
                values.append(number(item))
        except (ValueError, argparse.ArgumentTypeError):
            kind = "a whole number" if VARY[name] == "whole" else "a number"
            raise VPRInputError(f"--vary {text}: {item!r} is not {kind}") from None
    return name, tuple(values)


def check_vary(text: str, vary: tuple[str, tuple], value, options, labels, places):
    """``(parameter, values)`` once the bench on ``value`` is known to read the parameter and take every value.

    Raises:
        VPRInputError: ``--vary`` naming why (``acceptance_sweep.check_parameter``, ``check_values``).
    """
    from vpr_explorer.protocols.acceptance_sweep import check_parameter, check_values

    name, values = vary
    try:
        parameter, _ = check_parameter(value, name, options, labels=labels, places=places)
        return parameter.value, check_values(value, parameter, values, options, places=places)
    except VPRInputError as exc:
        raise VPRInputError(f"--vary {text}: {exc}") from None


# --------------------------------------------------------------------------- --tutorial-pr


def tutorial_soft_tolerance(args: argparse.Namespace, value, settings: dict) -> int | None:
    """``--soft-tolerance`` where ``--tutorial-pr`` reads it (aligned traversals), else ``None``.

    Raises:
        VPRInputError: ``--soft-tolerance`` on a layout without frames, or below ``--tolerance``.
    """
    from vpr_explorer.protocols.options import check_whole

    if not args.tutorial_pr:
        return None
    if value.aligned is None:
        if args.soft_tolerance is not None:
            raise VPRInputError(f"--soft-tolerance counts frames of aligned traversals; {value.name} is a "
                                f"{value.layout.value} layout, whose ground truth says which images are right: drop "
                                "--soft-tolerance")
        return None
    given = args.soft_tolerance is not None
    soft = check_whole("--soft-tolerance", args.soft_tolerance if given else SOFT_TOLERANCE, low=0,
                       high=value.n_frames, why=f" (frames of slack; {value.name!r} has {value.n_frames:,} frames)")
    if soft < settings["tolerance"]:
        shown = f"--soft-tolerance {soft}" + ("" if given else " (the default)")
        raise VPRInputError(f"{shown} is below --tolerance {settings['tolerance']}: soft positives reach at least "
                            f"as far as the hard ones; give --soft-tolerance {settings['tolerance']} or more")
    return soft


def tutorial_curves(value, descriptors, counted, soft_tolerance: int | None) -> dict:
    """VPR_Tutorial's curves of the closed set (module doc), as JSON-ready values.

    Args:
        value: the dataset value of the bench.
        descriptors: ``(n_images, D)`` its descriptors, database rows first.
        counted: ``(n_queries,)`` the queries the closed set counts (``Bench.counted``).
        soft_tolerance: aligned traversals: frames of slack of the soft positives; ``None`` reads the
            ground truth's own soft positives, if it has any.

    Returns:
        ``{"n_queries", "n_database", "hard", "soft", "soft_tolerance", "curves"}``: the ground
        truths' descriptions (``soft`` ``None`` where there is none), the frames of slack of the
        soft positives (``None`` where they are the ground truth's own) and one
        ``TutorialPR.to_dict()`` per row of ``TUTORIAL_ROWS`` that applies, each with its
        ``"ground_truth"``: "hard only" or "soft ignored".
    """
    import numpy as np

    from vpr_explorer.data.groundtruth import GroundTruth
    from vpr_explorer.method.retrieval import similarity
    from vpr_explorer.protocols.tutorial_pr import tutorial_pr

    d = np.asarray(descriptors, dtype=np.float32)  # as acceptance_report reads them
    rows = np.flatnonzero(counted)
    s = similarity(d[value.n_database:], d[:value.n_database])[rows]
    gt = value.ground_truth
    hard = gt.dense(rows)
    soft, soft_text = None, None
    if soft_tolerance is not None:
        soft = GroundTruth.from_frames(value.query_frame, value.database_frame, soft_tolerance).dense(rows)
        soft_text = f"within ±{soft_tolerance} frames"
    elif gt.soft_indptr is not None:
        soft = GroundTruth.from_lists([gt.soft_positives(q) for q in rows], gt.n_database, gt.description).dense()
        soft_text = "the ground truth's soft positives"
    curves = []
    for matching, ignored in TUTORIAL_ROWS:
        if ignored and soft is None:
            continue
        curve = tutorial_pr(s, hard, soft if ignored else None, matching=matching)
        curves.append({"ground_truth": "soft ignored" if ignored else "hard only", **curve.to_dict()})
    return {"n_queries": len(rows), "n_database": value.n_database, "hard": gt.description, "soft": soft_text,
            "soft_tolerance": soft_tolerance, "curves": curves}


def tutorial_lines(tutorial: dict) -> list[str]:
    """``--tutorial-pr``'s lines: what was counted, one row per curve (AUC, R@100P), what each column is."""
    frames = ((" (--tolerance)", " (--soft-tolerance; VPR_Tutorial's GardensPoint: the same frame hard, ±8 soft)")
              if tutorial["soft_tolerance"] is not None else ("", ""))
    lines = [f"VPR_Tutorial's precision–recall (evaluation/metrics.py: createPR, 100 thresholds; "
             f"recallAt100precision) on the closed set: {tutorial['n_queries']:,} queries × "
             f"{tutorial['n_database']:,} database images",
             f"hard ground truth: {tutorial['hard']}{frames[0]}; "
             + (f"soft: {tutorial['soft']}{frames[1]}, each soft pair that is not hard scored min(S), as VPR_Tutorial "
                "ignores them" if tutorial["soft"] else "no soft positives: the curves count hard positives only")]
    head = f"{'matching':<10}{'ground truth':<16}{'AUC':>8}{'R@100P':>9}"
    lines += [head, "-" * len(head)]
    for c in tutorial["curves"]:
        auc = "—" if c["auc"] is None else f"{c['auc']:.3f}"
        r100 = "—" if c["recall_at_100_precision"] is None else f"{c['recall_at_100_precision']:.3f}"
        lines.append(f"{c['matching']:<10}{c['ground_truth']:<16}{auc:>8}{r100:>9}")
    lines.append("AUC: the area under precision over recall (trapezoid rule, from the point recall 0, precision 1); "
                 "R@100P: the largest recall at precision exactly 1; both fractions of 1. single: each query's best "
                 "database image is its one detection (positives: the queries with a hard positive); multi: every "
                 "query–database pair is one (positives: the hard pairs)")
    if tutorial["soft"]:
        lines.append("VPR_Tutorial refuses soft positives with single matching; the single row with soft positives "
                     "ignored counts them as its code would without that check")
    return lines


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
