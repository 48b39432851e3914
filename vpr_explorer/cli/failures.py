"""``vpr-explorer failures``: a picture of every query one method fails, an index page and a CSV.

For method ``--method`` (one of ``method.retrieval.METHODS``; default ``raw-weighted``, the
authors' code) on one dataset value, ``views.failures`` finds the failing queries
(``wrong-answer``, ``wrong-reject``, ``accepted-unknown``: its module doc defines them, and the
picture) from ``views.numbers.fit_retrieval`` and ``decide_queries``, explains each with
``explain_query``, and this command writes into ``--out DIR``:

* one PNG per failure, ``<query>-<kind>.png`` (the query index zero-padded): the query, the
  top ``--top`` candidates (default 5) in the method's ranking framed green (right place) or
  red, and the true match with its rank; the kind and the reason sentence on top;
* ``failures.csv``: one row per PNG, the columns of ``views.failures.COLUMNS``;
* ``index.html``: the same rows with a thumbnail and a link to each PNG, the settings on
  top, sorted by clicking a header; one file, no external assets.

``--kind`` keeps some kinds (default ``all``); ``--limit`` (default 200) draws at most that
many, the first in query order, and says how many it left out. ``--out`` must be a new or
empty folder unless ``--overwrite``, which replaces files of the same names and keeps
every other file.

The dataset value, as ``evaluate`` reads the dataset options (``common.add_dataset_args``):

* **aligned traversal folders** (and prepared places): the query traversal ``--queries``
  against the database traversal(s) ``--database`` (default: the traversal protocol's,
  ``pipeline.default_traversals``), a database image right within ``--tolerance`` frames
  of the query's frame (default 0: the same frame, as ``evaluate``'s traversal protocol);
  places are group/step over frames (``--group``, ``--step``, ``--reading``);
* **database/queries layouts**: the layout's queries, database and ground truth
  (``--tolerance`` is refused; ``--radius`` sets a position-tagged one), places from the
  layout, or group/step in frames or metres (``--geometry``, default as ``evaluate``).

Bad input is one ``VPRInputError`` naming the option, raised before any descriptor is
computed where the option alone tells.
"""

from __future__ import annotations

import argparse
import csv
import io
from pathlib import Path

from vpr_explorer.cli.common import (
    add_dataset_args,
    aligned_value,
    bar,
    default_note,
    descriptor_name,
    retrieval_dataset,
    value_descriptors,
)
from vpr_explorer.errors import VPRInputError

# views.failures is imported where the command runs (numpy, PIL and the views): the parser builds every
# command's options each time any command starts. Its kinds are restated here for the choices.

#: the kinds of failure (``views.failures.FailureKind``' values) and ``all``
KINDS = ("wrong-answer", "wrong-reject", "accepted-unknown")
ALL = "all"
#: defaults of --method, --top, --limit and --tolerance
METHOD, TOP, LIMIT, TOLERANCE = "raw-weighted", 5, 200, 0
#: methods the command offers: every ``retrieval.METHODS`` key but ``global-oracle``, whose θ is fitted on the
#: queries' own answers (``global-user`` takes ``--theta``)
METHOD_KEYS = ("image-baseline", "place-baseline", "margin-simple", "margin-weighted", "raw-simple", "raw-weighted",
               "global-auto", "global-user")
#: the files written beside the PNGs
CSV_NAME, INDEX_NAME = "failures.csv", "index.html"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``failures``' options: the dataset's (``common.add_dataset_args``), the traversals, the method, the output."""
    add_dataset_args(p)
    p.add_argument("--database", nargs="+", default=None, metavar="TRAVERSAL",
                   help="traversal folders: the database traversal(s) (default: a traversal named ref, reference, "
                        "database, db or map, else the first)")
    p.add_argument("--queries", default=None, metavar="TRAVERSAL",
                   help="traversal folders: the query traversal (default: one named query, queries, q or live, "
                        "else the last)")
    p.add_argument("--tolerance", type=int, default=None,
                   help="aligned traversals: a database image within this many frames of the query's frame is right"
                        + default_note(TOLERANCE))
    p.add_argument("--method", default=METHOD, metavar="KEY",
                   help=f"the method whose failures are drawn: {', '.join(METHOD_KEYS)}")
    p.add_argument("--theta", type=float, default=None,
                   help="--method global-user: the global threshold (a finite number)")
    p.add_argument("--kind", nargs="+", choices=(*KINDS, ALL), default=[ALL], metavar="KIND",
                   help="the failures drawn, one or more of: wrong-answer (a query with a right place answered "
                        "without it at rank 1), wrong-reject (one rejected), accepted-unknown (a query of no database "
                        "place accepted), all")
    p.add_argument("--top", type=int, default=TOP, help="candidates drawn per failure, in the method's ranking")
    p.add_argument("--limit", type=int, default=LIMIT,
                   help="PNGs written at most: the first failures in query order (the rest are counted)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="folder for the PNGs, failures.csv and index.html: new or empty (see --overwrite)")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a non-empty --out folder: files of the same names are replaced, others kept")


def run(args: argparse.Namespace) -> int:
    """Draw the failures of ``--method`` on the dataset ``args`` names; write the PNGs, the CSV and the index.

    Returns:
        0 (bad input raises ``VPRInputError``).
    """
    from vpr_explorer.method.retrieval import METHODS_BY_KEY
    from vpr_explorer.views import failures as vf
    from vpr_explorer.views.numbers import RetrievalPlaces, fit_retrieval

    check_options(args)
    check_out(args.out, args.overwrite)
    descriptor = descriptor_name(args)
    if args.descriptors is None:
        from vpr_explorer.settings import check_cache_root

        check_cache_root(args.cache_dir)  # an unusable cache folder fails before the dataset is read
    value, lines, settings = dataset_value(args)
    geometry, spec, metric = places_of(args, value)
    desc, descriptor, source, notes = value_descriptors(args, value, descriptor)
    fitted = fit_retrieval(desc, value, RetrievalPlaces(geometry, spec, metric))
    kinds = None if ALL in args.kind else tuple(args.kind)
    result = vf.find_failures(fitted, desc, args.method, kinds=kinds, top=args.top, limit=args.limit,
                              user_theta=args.theta, progress=bar("failures explained"))
    settings = {"dataset": f"{value.name} ({value.root})", **settings, "descriptor": descriptor, **source,
                "method": f"{args.method} ({METHODS_BY_KEY[args.method].label})",
                **({"theta": f"{args.theta:g}"} if args.theta is not None else {}),
                "places": fitted.describe(), "kinds": ", ".join(k.value for k in result.kinds), "top": str(args.top),
                "limit": str(args.limit)}
    summary = vf.summary_lines(result)
    written = write_outputs(args.out, fitted, result, settings, summary)
    for line in (*lines, *notes, f"places: {fitted.describe()}", *summary):
        print(line)
    print(f"wrote {written} PNG{'s' if written != 1 else ''}, {CSV_NAME} and {INDEX_NAME} to {args.out}")
    return 0


# --------------------------------------------------------------------------- the options


def check_options(args: argparse.Namespace) -> None:
    """Refuse ``--method``, ``--theta``, ``--top`` and ``--limit`` values by their option, before any work.

    Raises:
        VPRInputError: an unknown method, ``global-user`` without ``--theta`` (or ``--theta``
            with another method, or not finite), ``--top`` < 1, ``--limit`` < 0.
    """
    import math

    if args.method not in METHOD_KEYS:
        why = (": its θ is fitted on the queries' own answers; draw global-user with --theta instead"
               if args.method == "global-oracle" else "")
        raise VPRInputError(f"--method {args.method}: not offered{why}; choose one of {', '.join(METHOD_KEYS)}")
    if args.method == "global-user":
        if args.theta is None:
            raise VPRInputError("--method global-user needs --theta, the global threshold (e.g. --theta 0.5)")
        if not math.isfinite(args.theta):
            raise VPRInputError(f"--theta {args.theta}: give a finite number (e.g. --theta 0.5)")
    elif args.theta is not None:
        raise VPRInputError(f"--theta applies to --method global-user only, and this is --method {args.method}: "
                            "drop --theta, or pick --method global-user")
    if args.top < 1:
        raise VPRInputError(f"--top {args.top}: draw at least 1 candidate per failure")
    if args.limit < 0:
        raise VPRInputError(f"--limit {args.limit}: give 0 or more PNGs (0 writes the index and the CSV only)")


def check_out(out: Path, overwrite: bool) -> None:
    """Refuse an ``--out`` that is a file, or a non-empty folder without ``--overwrite``.

    Raises:
        VPRInputError: naming ``--out`` and what to do.
    """
    try:
        if not out.exists():
            return
        if not out.is_dir():
            raise VPRInputError(f"--out {out}: a file, not a folder; give a new or empty folder")
        if not overwrite and any(out.iterdir()):
            raise VPRInputError(f"--out {out}: the folder is not empty; give a new or empty folder, or add "
                                "--overwrite (files of the same names are replaced, other files are kept)")
    except OSError as exc:
        raise VPRInputError(f"--out {out}: cannot read the folder ({exc.strerror}); pick another") from exc


# --------------------------------------------------------------------------- the dataset value


def dataset_value(args: argparse.Namespace):
    """The dataset value ``args`` names, the lines that say how it was chosen, and its settings.

    Returns:
        ``(value, lines, settings)``: a ``data.layouts.RetrievalDataset``, the lines to print,
        and the traversals and ground truth for the index's settings.

    Raises:
        VPRInputError: ``--tolerance``, ``--database`` or ``--queries`` on a layout that does
            not read them, or what opening the dataset raises.
    """
    dataset = retrieval_dataset(args)
    if dataset is not None:
        return _layout_value(args, dataset)
    a = aligned_value(args, TOLERANCE if args.tolerance is None else args.tolerance)
    right = f"database frames within ±{a.tolerance} frames of the query's" if a.tolerance else "the same frame"
    lines = [f"{a.value.name}: queries {a.query} against database {', '.join(a.database)} ({a.how}); right: {right}"]
    settings = {"queries": a.query, "database": ", ".join(a.database),
                "tolerance": f"±{a.tolerance} frames" if a.tolerance else "0 frames (the same frame)"}
    return a.value, lines, settings


def _layout_value(args: argparse.Namespace, dataset):
    """``dataset_value`` for a database/queries layout: its own queries and ground truth."""
    from vpr_explorer.data.layouts import Layout

    layout = dataset.layout.value
    if args.tolerance is not None:
        raise VPRInputError(f"--tolerance counts frames of aligned traversals; {dataset.name} is a {layout} layout, "
                            f"whose ground truth says which images are right ({dataset.ground_truth.description}): "
                            "drop --tolerance (position-tagged layouts: --radius)")
    if dataset.layout is not Layout.TRAVERSAL_POSITIONS:
        for option in ("database", "queries"):
            if getattr(args, option) is not None:
                raise VPRInputError(f"--{option} picks traversal folders; {dataset.name} is a {layout} layout, whose "
                                    f"queries and database are given: drop --{option}")
    settings = {"layout": layout, "tolerance": f"right: {dataset.ground_truth.description}"}
    if dataset.layout is Layout.TRAVERSAL_POSITIONS:
        settings["database"] = ", ".join(dataset.traversals[t]
                                         for t in dict.fromkeys(dataset.database_traversal.tolist()))
        settings["queries"] = dataset.traversals[int(dataset.query_traversal[0])]
    return dataset, [dataset.describe(), *dataset.notes], settings


def places_of(args: argparse.Namespace, value):
    """``(geometry, PlaceSpec, MetricPlaceSpec)`` of the places: the layout's own (all ``None``), else group/step.

    The geometry is ``--geometry``, default frames for aligned traversals and where there are
    no positions, else route along an ordered database and lattice over an unordered one
    (``views.numbers.default_geometry``, as ``evaluate`` reads it).

    Raises:
        VPRInputError: ``--geometry`` the dataset does not offer.
    """
    from vpr_explorer.method.places import MetricPlaceSpec, PlaceGeometry, PlaceSpec
    from vpr_explorer.views.numbers import check_geometry

    try:
        geometry = check_geometry(value, args.geometry)
    except VPRInputError as exc:
        raise VPRInputError(f"--{exc}") from None
    if geometry is None:
        return None, None, None
    if geometry is PlaceGeometry.FRAMES:
        return geometry, PlaceSpec(args.group, args.step, args.reading), None
    return geometry, None, MetricPlaceSpec(args.group, args.step, args.reading, geometry.value)


# --------------------------------------------------------------------------- the files


def png_name(query: int, kind: str, n_queries: int) -> str:
    """``<query>-<kind>.png``, the query index zero-padded to the widest index's digits."""
    return f"{query:0{len(str(max(0, n_queries - 1)))}d}-{kind}.png"


def write_outputs(out: Path, fitted, result, settings: dict[str, str], summary: list[str]) -> int:
    """Write every failure's PNG, ``failures.csv`` and ``index.html`` into ``out`` (made where missing).

    Returns:
        The PNGs written.

    Raises:
        VPRInputError: a file cannot be written (naming ``--out``), an image cannot be read.
    """
    from vpr_explorer.views import failures as vf

    try:
        out.mkdir(parents=True, exist_ok=True)
        pngs, thumbnails = {}, {}
        progress = bar("pictures")
        for i, failure in enumerate(result.failures):
            name = png_name(failure.query, failure.kind.value, result.n_queries)
            picture = vf.draw_failure(failure)
            picture.save(out / name, format="PNG", compress_level=3)  # half of level 6's time, 3% larger
            pngs[failure.query], thumbnails[name] = name, vf.thumbnail_uri(picture)
            progress(i + 1, len(result.failures))
        rows = vf.failure_rows(fitted, result.failures, pngs)
        text = io.StringIO()
        writer = csv.DictWriter(text, fieldnames=vf.COLUMNS, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        (out / CSV_NAME).write_text(text.getvalue(), encoding="utf-8")
        (out / INDEX_NAME).write_text(vf.index_html(rows, settings, summary, thumbnails), encoding="utf-8")
    except OSError as exc:
        raise VPRInputError(f"--out {out}: cannot write ({exc.strerror or exc}); pick a writable folder") from exc
    return len(pngs)
