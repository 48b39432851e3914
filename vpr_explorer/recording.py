"""Playback with rerun: the queries of a dataset value decided one by one against its database.

The one module that talks to rerun. Every recording is an explicit
``rerun.RecordingStream`` (never rerun's global one: several browser sessions may record
at once). A dataset value (``layouts.RetrievalDataset``; aligned traversals are one,
``data.aligned.database_queries``, whose query ``q`` is frame ``q`` of the query traversal)
is played back as the sequence of its queries in their order. On one ``query`` timeline
(the query's index) it logs, for each query:

| entity                                   | what                                                        |
|------------------------------------------|-------------------------------------------------------------|
| ``query``                                | the query image (its file's bytes, original size)           |
| ``match/paper``, ``match/baseline``      | the database image behind each method's answer (cleared when rejected) |
| ``decision/paper``, ``decision/baseline``| the answer and whether it was right, as a text log; level INFO right, ERROR wrong accept, WARN wrong reject, DEBUG not scored |
| ``scores/<method>/{raw,theta,margin}``   | raw_p, θ_p and raw_p − θ_p of the method's best place         |
| ``place/{true,paper,baseline}``          | the right place (the best-scoring one) and each answered place |
| ``route/query``, ``route/<method>``      | the query's position and the answered image's position      |

and, static: ``route/path`` and ``route/places`` (the database's route and each place's
centre), ``thresholds/{weighted,simple}`` (θ_p of every place) and ``summary`` (settings
and counts). ``playback_blueprint`` lays them out.

With the acceptance bench (``protocols.acceptance``, run on the same value with the same
places: ``bench_report``), ``log_bench`` adds, on the same ``query`` timeline, for every rule
that ran, under ``bench/<rule key>`` for the closed set and ``bench_open/<rule key>`` for the
natural open set (where it ran):

| entity             | what                                                                         |
|--------------------|------------------------------------------------------------------------------|
| ``.../confidence`` | the rule's confidence (``RuleDecisions.confidence``) where it has a candidate |
| ``.../accepted``   | 1 accepted, 0 rejected, every query                                          |
| ``.../decision``   | the answer (image, file) or rejection and right or wrong, a text log; DEBUG not counted |

and, static, ``bench/summary`` and ``bench_open/summary``: each rule's counts and τ, and each
rule left out with the reason (a rule left out logs nothing else); the natural open set's
says why it did not run where it did not. What is right is the authors' counts
(``acceptance.authors_counts``, ``bench_verdicts``): a genuine query (a right database
image) accepted with a right image; a distractor (none) rejected. The closed set counts
only genuine queries; its distractors are logged as not counted.

What is right (``verdicts``): a query with a right place is right when accepted with it at
rank 1; a query with no positive at all (an unknown place, the open-set case) is right when
rejected, a wrong accept otherwise; a query whose positives all lie outside every place is
not scored (``places.BETWEEN_PLACES_RULE``).

"paper" is the paper's method (margin rule, weighted θ: ``margin-weighted``), "baseline"
the place-level baseline (``place-baseline``). The baseline has no threshold; its θ_p and
margin series show where the paper's weighted θ_p puts the place it picked.

The route: positions in metres where the value has them (for aligned traversals the
positions of their frames), else for aligned traversals frame numbers on a line; a layout
with neither (VPR-Bench) has no route.

Images are read from disk one query at a time and logged as encoded files, so a long
sequence never holds all its images in memory (give the recording a sink first,
``save``/``set_sinks``: one without a sink buffers everything).

Entry points, from the most to the least given: ``log_queries`` (decisions already made,
``decide_every_query``) < ``record_playback`` (a fitted value: decides, writes an ``.rrd``,
optionally served) < ``record_dataset`` (an opened dataset, its descriptors computed or
read: the ``record`` command). ``viewer_servers`` starts rerun's gRPC server and bundled
web viewer once per process.
"""

from __future__ import annotations

import atexit
import shutil
import socket
import tempfile
import threading
import urllib.parse
import uuid
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from vpr_explorer.data.aligned import database_queries, value_rows
from vpr_explorer.data.layouts import RetrievalDataset
from vpr_explorer.data.traversals import Dataset, load_dataset
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.database import Verdict
from vpr_explorer.method.places import (
    BETWEEN_PLACES_RULE,
    MetricPlaceSpec,
    PlaceGeometry,
    PlaceSpec,
    Reading,
    retrieval_places,
)
from vpr_explorer.method.retrieval import METHODS_BY_KEY, Outcome, place_scores, score_queries
from vpr_explorer.protocols import acceptance
from vpr_explorer.protocols.acceptance import RULES, AcceptanceReport, Bench, BenchOptions, RuleDecisions
from vpr_explorer.protocols.options import check_finite, check_whole
from vpr_explorer.settings import check_cache_root
from vpr_explorer.views.numbers import (
    BETWEEN,
    KNOWN,
    SCORE_ELEMS,
    UNKNOWN,
    RetrievalFitted,
    RetrievalPlaces,
    check_geometry,
    fit_retrieval,
    score_rows,
)

APPLICATION_ID = "vpr_explorer"
TIMELINE = "query"
PAPER = "margin-weighted"
BASELINE = "place-baseline"
RECORDED: dict[str, str] = {PAPER: "paper", BASELINE: "baseline"}
"""Method key -> the short name used in entity paths."""

ENCODED_SUFFIXES = frozenset({".jpg", ".jpeg", ".png"})
"""Logged as the file's bytes; other formats are decoded and logged as pixels."""

Progress = Callable[[int, int], None]


LEVELS = {
    Verdict.RIGHT: rr.TextLogLevel.INFO,
    Verdict.WRONG_ACCEPT: rr.TextLogLevel.ERROR,
    Verdict.WRONG_REJECT: rr.TextLogLevel.WARN,
    Verdict.BETWEEN: rr.TextLogLevel.DEBUG,
}

_COLORS = {
    Verdict.RIGHT: (60, 180, 75),
    Verdict.WRONG_ACCEPT: (230, 25, 75),
    Verdict.WRONG_REJECT: (245, 130, 48),
    Verdict.BETWEEN: (150, 150, 150),
}
_SERIES = {"raw": (31, 119, 180), "theta": (214, 39, 40), "margin": (44, 160, 44)}
_SERIES_NAMES = {"raw": "raw_p", "theta": "θ_p (weighted)", "margin": "margin raw_p − θ_p"}
_ROUTE = (120, 120, 120)
_QUERY = (31, 119, 255)
_MARKERS = {"true": "Circle", "paper": "Cross", "baseline": "Diamond"}
_PLACE_COLORS = {"true": (200, 200, 200), "paper": (31, 119, 180), "baseline": (255, 127, 14)}

BENCH_SETS: dict[str, tuple[str, str]] = {"closed": ("bench", "bench, closed set"),
                                          "natural": ("bench_open", "bench, open set")}
"""``AcceptanceReport`` attribute -> the root of its entities and its name in view titles."""
NOT_COUNTED = "not counted"
"""A closed-set query without a right database image: the closed set leaves it out of its counts."""
_BENCH_LEVELS = {**{v.value: level for v, level in LEVELS.items()}, NOT_COUNTED: rr.TextLogLevel.DEBUG}
# matplotlib's tab10, one colour per rule of ``acceptance.RULES``
_RULE_COLORS = ((31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
                (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207))


# --------------------------------------------------------------------------- the decisions


@dataclass(frozen=True, eq=False)
class QueryDecisions:
    """Every query of a dataset value decided against its database under the recorded methods, in query order.

    Attributes:
        fitted: the places and thresholds the queries were decided with.
        status: ``(n_queries,)`` ``numbers.KNOWN`` (a right place), ``BETWEEN`` (positives,
            none in a place: not scored) or ``UNKNOWN`` (no positive at all).
        true_place: ``(n_queries,)`` the right place scoring highest, ``-1`` where there is none.
        true_raw: ``(n_queries,)`` its raw_p (NaN where there is none).
        outcomes: method key -> ``Outcome`` over the queries (``answer_image`` indexes ``fitted.model.images``).
        plotted: method key -> ``(n_queries,)`` the place whose scores are logged: the answer, or
            for a rejected query the one that came closest (highest raw_p − θ_p).
        plotted_raw: method key -> ``(n_queries,)`` raw_p of that place.
        thresholds: the threshold mapping the methods ran with (θ_p + k·s_p).
        k: that k.
    """

    fitted: RetrievalFitted
    status: np.ndarray
    true_place: np.ndarray
    true_raw: np.ndarray
    outcomes: dict[str, Outcome]
    plotted: dict[str, np.ndarray]
    plotted_raw: dict[str, np.ndarray]
    thresholds: dict[str, np.ndarray | float]
    k: float = 0.0

    @property
    def n_queries(self) -> int:
        return len(self.status)

    def theta(self, name: str = "weighted") -> np.ndarray:
        """``(n_places,)`` one threshold of every place (a global one broadcast)."""
        return np.broadcast_to(np.asarray(self.thresholds[name], dtype=np.float64), (self.fitted.n_places,))


def decide_every_query(fitted: RetrievalFitted, descriptors: np.ndarray, *, k: float = 0.0) -> QueryDecisions:
    """Decide every query of ``fitted``'s dataset under the recorded methods (``RECORDED``), in blocks.

    Each block's scores are the query rows against the database images in places
    (``numbers.score_rows``), their place maxima (``retrieval.place_scores``) and the
    methods' outcomes (``retrieval.score_queries``): what ``numbers.explain_query``
    decides one query at a time. Only one block's scores are held at once (``SCORE_ELEMS``).

    Args:
        descriptors: ``(n_images, D)`` of the dataset, database rows first.
        k: thresholds θ_p + k·s_p (0: the paper's).

    Raises:
        VPRInputError: descriptors of another dataset, or a dataset without queries.
    """
    ds, model, n_places = fitted.dataset, fitted.model, fitted.n_places
    if len(descriptors) != ds.n_images:
        raise VPRInputError(f"{len(descriptors)} descriptors for {ds.n_images} images of {ds.name!r}: "
                            "compute them for this dataset")
    if not ds.n_queries:
        raise VPRInputError(f"{ds.name!r} has no query image: there is nothing to play back")
    th = model.thresholds(k)
    methods = tuple(METHODS_BY_KEY[key] for key in RECORDED)
    full = {name: np.broadcast_to(np.asarray(v, dtype=np.float64), (n_places,)) for name, v in th.items()}
    block = max(1, SCORE_ELEMS // max(1, len(model.images)))
    parts: list[tuple] = []
    for lo in range(0, ds.n_queries, block):
        queries = np.arange(lo, min(lo + block, ds.n_queries))
        sims = score_rows(descriptors, ds.n_database + queries, model.images)
        raw, best = place_scores(sims, model.places, n_places)
        truth = fitted.right_places(queries)
        outs = score_queries(sims, model.places, n_places, th, truth, methods, raw_best=(raw, best))
        rows = np.arange(len(queries))
        plotted, plotted_raw = {}, {}
        for m in methods:
            ranking = raw if m.threshold is None else raw - full[m.threshold]
            closest = np.argmax(np.where(np.isfinite(ranking), ranking, -np.inf), axis=1)
            o = outs[m.key]
            plotted[m.key] = np.where(o.accepted, o.answer_place, closest)
            plotted_raw[m.key] = raw[rows, plotted[m.key]]
        known = truth.any(axis=1)
        true = np.argmax(np.where(truth, raw, -np.inf), axis=1)
        status = np.where(known, KNOWN, np.where(ds.ground_truth.counts[queries] == 0, UNKNOWN, BETWEEN))
        parts.append((status, np.where(known, true, -1), np.where(known, raw[rows, true], np.nan), outs, plotted,
                      plotted_raw))

    def joined(i: int, key: str | None = None) -> np.ndarray:
        return np.concatenate([p[i] if key is None else p[i][key] for p in parts])

    outcomes = {m.key: Outcome.joined([p[3][m.key] for p in parts]) for m in methods}
    return QueryDecisions(fitted, joined(0).astype(object), joined(1), joined(2), outcomes,
                          {key: joined(4, key) for key in RECORDED}, {key: joined(5, key) for key in RECORDED},
                          th, float(k))


def verdicts(decisions: QueryDecisions, key: str) -> np.ndarray:
    """``(n_queries,)`` ``Verdict`` values of one method over the queries (module docstring: what is right)."""
    o = decisions.outcomes[key]
    status = decisions.status
    out = np.where(o.right, Verdict.RIGHT.value,
                   np.where(o.accepted, Verdict.WRONG_ACCEPT.value, Verdict.WRONG_REJECT.value))
    out = np.where(status == UNKNOWN, np.where(o.accepted, Verdict.WRONG_ACCEPT.value, Verdict.RIGHT.value), out)
    return np.where(status == BETWEEN, Verdict.BETWEEN.value, out).astype(object)


def verdict_counts(decisions: QueryDecisions, key: str) -> dict[Verdict, int]:
    """How many queries got each verdict under one method."""
    v = verdicts(decisions, key)
    return {verdict: int((v == verdict.value).sum()) for verdict in Verdict}


def describe_queries(decisions: QueryDecisions, key: str) -> list[str]:
    """One method's decision for every query in words, e.g.
    "accepted as place 7 (right): raw 0.812, threshold 0.460, margin +0.352"."""
    o = decisions.outcomes[key]
    method = METHODS_BY_KEY[key]
    theta = None if method.threshold is None else decisions.theta(method.threshold)
    said = verdicts(decisions, key)
    texts = []

    def scores(p: int, raw: float) -> str:
        text = f"raw {raw:.3f}"
        if theta is not None:
            text += f", threshold {theta[p]:.3f}, margin {raw - theta[p]:+.3f}"
        return text

    for i in range(decisions.n_queries):
        answer, p = int(o.answer_place[i]), int(decisions.plotted[key][i])
        body = scores(p, decisions.plotted_raw[key][i])
        if answer >= 0:
            head = f"accepted as place {answer}"
        else:
            head, body = "rejected", f"every place scored below its threshold; the closest, place {p}: {body}"
        verdict, status = Verdict(said[i]), decisions.status[i]
        if verdict is Verdict.BETWEEN:
            texts.append(f"{head} (not scored: the query's right images all lie between places): {body}")
        elif status == UNKNOWN:
            right = "right" if verdict is Verdict.RIGHT else "wrong"
            texts.append(f"{head} ({right}: the query's place is not in the database): {body}")
        elif verdict is Verdict.RIGHT:
            texts.append(f"{head} (right): {body}")
        else:
            true, rank = int(decisions.true_place[i]), o.rank[i]
            at_true = scores(true, decisions.true_raw[i])
            if verdict is Verdict.WRONG_REJECT:
                why = f"the query is place {true} ({at_true})"
            elif not np.isfinite(rank):
                why = f"the true place {true} was dropped ({at_true})"
            elif rank == 1:
                why = f"the true place {true} ties with it at the top, and ties count against the query"
            else:
                why = f"the true place {true} ranked {int(rank)} ({at_true})"
            texts.append(f"{head} (wrong: {why}): {body}")
    return texts


# --------------------------------------------------------------------------- what is logged


@dataclass(frozen=True, eq=False)
class Route:
    """Where a value's images lie, in metres (or frame numbers on a line).

    Attributes:
        path: ``(m, 2)`` the database's route: every frame of aligned traversals, else the
            database images in listed order.
        line: ``path`` is one route in order (drawn as a line), not a set of points.
        database, queries: ``(n, 2)`` each database image's and each query's position.
    """

    path: np.ndarray
    line: bool
    database: np.ndarray
    queries: np.ndarray


def route_of(dataset: RetrievalDataset) -> Route | None:
    """The value's route: its positions, else for aligned traversals ``(frame, 0)``; ``None`` with neither."""
    if dataset.database_frame is not None and dataset.query_frame is not None:
        xy = dataset.frame_xy
        if xy is None:
            f = np.arange(dataset.n_frames, dtype=np.float64)
            xy = np.stack([f, np.zeros_like(f)], axis=1)
        xy = np.asarray(xy, dtype=np.float64)
        return Route(xy, True, xy[dataset.database_frame], xy[dataset.query_frame])
    if dataset.database_xy is not None and dataset.query_xy is not None:
        db = np.asarray(dataset.database_xy, dtype=np.float64)
        return Route(db, bool(dataset.ordered), db, np.asarray(dataset.query_xy, dtype=np.float64))
    return None


#: Longest view title the viewer shows whole in a third of the Playback page's width.
TITLE_CHARS = 40


def playback_blueprint(query: str, database: Sequence[str], *, bench: bool = False) -> rrb.Blueprint:
    """Query and both answers on top, the score series below, route, decisions and thresholds last.

    View titles stay within ``TITLE_CHARS`` so that none is cut in a third of the page;
    colours and units are in each plot's legend instead (the series' names,
    ``_SERIES_NAMES``: rerun's plots have no axis titles) and in the summary. The summary
    shares the widest panel with the decision log, word-wrapped. With ``bench``, the bench's
    summaries, decision logs and series (``log_bench``) join the last panel's tabs.
    """
    legend = rrb.PlotLegend(corner=rrb.Corner2D.LeftTop, visible=True)
    wrap = rrb.archetypes.TextDocumentFormat(word_wrap=True)
    bench_views = [] if not bench else [
        view
        for root, name in BENCH_SETS.values()
        for view in (
            rrb.TextDocumentView(origin=f"{root}/summary", name=f"{name}: summary", format_options=wrap),
            rrb.TextLogView(origin=root, name=f"{name}: decisions"),
            rrb.TimeSeriesView(origin=root, name=f"{name}: confidence, accepted", plot_legend=legend),
        )
    ]
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(
                rrb.Spatial2DView(origin="query", name=_title(f"query ({query})")),
                rrb.Spatial2DView(origin="match/paper", name="paper's answer: margin, weighted θ"),
                rrb.Spatial2DView(origin="match/baseline", name="place-level baseline's answer"),
            ),
            rrb.Horizontal(
                rrb.TimeSeriesView(origin="scores/paper", name="paper: similarity per query",
                                   plot_legend=legend),
                rrb.TimeSeriesView(origin="scores/baseline", name="baseline: similarity per query",
                                   plot_legend=legend),
                rrb.TimeSeriesView(origin="place", name="place: true (grey) and answers", plot_legend=legend),
            ),
            rrb.Horizontal(
                rrb.Spatial2DView(origin="route", name="route: query blue, answers"),
                rrb.Tabs(
                    rrb.TextDocumentView(origin="summary", name="summary", format_options=wrap),
                    rrb.TextLogView(origin="decision", name="decisions"),
                    rrb.BarChartView(origin="thresholds/weighted", name="θ_p weighted (paper) per place"),
                    rrb.BarChartView(origin="thresholds/simple", name="θ_p simple per place"),
                    *bench_views,
                ),
                column_shares=[2, 5],
            ),
            row_shares=[3, 3, 4],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=TIMELINE),
    )


def _title(text: str) -> str:
    """``text`` cut to ``TITLE_CHARS`` with an ellipsis (a traversal name can be long)."""
    return text if len(text) <= TITLE_CHARS else text[:TITLE_CHARS - 1] + "…"


def _image(path: Path) -> rr.AsComponents:
    """The image file as rerun logs it; an unreadable one is an error (rerun would only warn and log nothing)."""
    from PIL import Image, UnidentifiedImageError

    try:
        if path.suffix.lower() in ENCODED_SUFFIXES:
            return rr.EncodedImage(contents=path.read_bytes(), media_type=rr.components.MediaType.guess_from_path(path))
        with Image.open(path) as im:
            return rr.Image(np.asarray(im.convert("RGB")))
    except (OSError, UnidentifiedImageError) as exc:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise VPRInputError(f"{path}: cannot read the image ({why}); restore the file and record again") from exc


def sides(dataset: RetrievalDataset) -> tuple[tuple[str, ...], str]:
    """The database traversals (in order) and the query traversal of a value, by name."""
    order = np.unique(dataset.database_traversal, return_index=True)[1]
    database = tuple(dataset.traversals[int(t)] for t in dataset.database_traversal[np.sort(order)])
    return database, dataset.traversals[int(dataset.query_traversal[0])]


def summary(decisions: QueryDecisions, descriptor: str | None) -> str:
    """The recording's summary (markdown): data, places, thresholds, and each method's counts in one short line."""
    fitted = decisions.fitted
    ds = fitted.dataset
    database, query = sides(ds)
    n_unknown = int((decisions.status == UNKNOWN).sum())
    n_known = int((decisions.status == KNOWN).sum())
    lines = [
        f"# {ds.name}: {query} against {', '.join(database)}",
        "",
        f"- places: {fitted.describe()}",
        f"- right images: {ds.ground_truth.description}",
        f"- descriptor: {descriptor or 'not given'}",
        f"- thresholds: θ_p + k·s_p with k = {decisions.k:g}, from the database images only "
        "(weighted θ uses the normalised weights wᵢτᵢ² / Σⱼ wⱼτⱼ²)",
        f"- {decisions.n_queries} queries in their order on the `{TIMELINE}` timeline: {n_known} with a right "
        f"place, {n_unknown} of an unknown place (no right image: rejecting them is right), "
        f"{decisions.n_queries - n_known - n_unknown} not scored",
        f"- {BETWEEN_PLACES_RULE}",
        "",
        "## Decisions",
        "",
    ]
    # One short line per method, not a wide table: the viewer's text panel would cut its columns.
    for key, short in RECORDED.items():
        c = verdict_counts(decisions, key)
        right_known = int((decisions.outcomes[key].right & (decisions.status == KNOWN)).sum())
        recall = f"{100 * right_known / n_known:.1f} %" if n_known else "— (no query with a right place)"
        lines.append(f"- **{short}** ({METHODS_BY_KEY[key].label}): Recall@1 {recall}; {c[Verdict.RIGHT]} right, "
                     f"{c[Verdict.WRONG_ACCEPT]} wrong accepts, {c[Verdict.WRONG_REJECT]} wrong rejects, "
                     f"{c[Verdict.BETWEEN]} not scored")
    lines += [
        "",
        "## Plots",
        "",
        f"- similarity per query: {', '.join(_SERIES_NAMES.values())} of the method's best place "
        "(the answer, or for a rejected query the closest place), against the query number",
        "- place: the true place id and each answered place id, against the query number",
        "- route: the query's position (blue), each answer's position (green right, red wrong)"
        if route_of(ds) is not None else "- route: none (the layout has neither positions nor frames)",
    ]
    return "\n".join(lines) + "\n"


def log_queries(
    recording: rr.RecordingStream,
    decisions: QueryDecisions,
    *,
    descriptor: str | None = None,
    progress: Progress | None = None,
) -> None:
    """Log decided queries to ``recording`` (entities in the module docstring).

    Static entities and every series go first as columns; then the images, one query at
    a time, read from disk. ``descriptor`` only labels the summary.
    """
    fitted = decisions.fitted
    ds, model = fitted.dataset, fitted.model
    n = decisions.n_queries
    queries = np.arange(n, dtype=np.int64)
    times = [rr.TimeColumn(TIMELINE, sequence=queries)]
    theta = {name: decisions.theta(name) for name in ("weighted", "simple")}

    recording.log("summary", rr.TextDocument(summary(decisions, descriptor), media_type=rr.MediaType.MARKDOWN),
                  static=True)
    for name, values in theta.items():
        recording.log(f"thresholds/{name}", rr.BarChart(np.nan_to_num(values)), static=True)
    route = route_of(ds)
    said = {key: verdicts(decisions, key) for key in RECORDED}
    if route is not None:
        radius = rr.components.Radius.ui_points(1.5)
        recording.log("route/path", rr.LineStrips2D([route.path], colors=[_ROUTE], radii=radius) if route.line
                      else rr.Points2D(route.path, colors=[_ROUTE], radii=radius), static=True)
        # A place's mark sits at the mean position of its database images.
        placed = fitted.database_place >= 0
        counts = np.bincount(fitted.database_place[placed], minlength=fitted.n_places)
        centres = np.stack([np.bincount(fitted.database_place[placed], weights=route.database[placed, axis],
                                        minlength=fitted.n_places) for axis in (0, 1)], axis=1)
        recording.log("route/places", rr.Points2D(
            centres / np.maximum(counts, 1)[:, None], radii=rr.components.Radius.ui_points(3.0), colors=[_ROUTE],
            labels=[f"place {p}: θ {theta['weighted'][p]:.3f}" for p in range(fitted.n_places)],
            show_labels=False,  # shown on hover: drawn, they hide the route
        ), static=True)
        recording.send_columns("route/query", indexes=times, columns=rr.Points2D.columns(
            positions=route.queries, colors=np.tile(_QUERY, (n, 1)),
            radii=np.full(n, rr.components.Radius.ui_points(6.0), dtype=np.float32),
        ))

    known = decisions.true_place >= 0
    recording.log("place/true", rr.SeriesPoints(colors=[_PLACE_COLORS["true"]], markers=[_MARKERS["true"]],
                                                names=["true place"]), static=True)
    recording.send_columns("place/true", indexes=[rr.TimeColumn(TIMELINE, sequence=queries[known])],
                           columns=rr.Scalars.columns(scalars=decisions.true_place[known].astype(np.float64)))
    for key, short in RECORDED.items():
        o = decisions.outcomes[key]
        label = METHODS_BY_KEY[key].label
        raw = decisions.plotted_raw[key]
        series = {"raw": raw, "theta": theta["weighted"][decisions.plotted[key]],
                  "margin": raw - theta["weighted"][decisions.plotted[key]]}
        for name, values in series.items():
            path = f"scores/{short}/{name}"
            recording.log(path, rr.SeriesLines(colors=[_SERIES[name]], names=[_SERIES_NAMES[name]]), static=True)
            recording.send_columns(path, indexes=times, columns=rr.Scalars.columns(scalars=values))
        accepted = o.accepted
        recording.log(f"place/{short}", rr.SeriesPoints(colors=[_PLACE_COLORS[short]], markers=[_MARKERS[short]],
                                                        names=[f"answer ({label})"]), static=True)
        recording.send_columns(f"place/{short}", indexes=[rr.TimeColumn(TIMELINE, sequence=queries[accepted])],
                               columns=rr.Scalars.columns(scalars=o.answer_place[accepted].astype(np.float64)))
        recording.send_columns(f"decision/{short}", indexes=times, columns=rr.TextLog.columns(
            text=[f"query {q} · {label}: {t}" for q, t in zip(queries, describe_queries(decisions, key))],
            level=[LEVELS[Verdict(v)] for v in said[key]],
        ))
        if route is not None:  # one point per accepted query, none for a rejected one (an empty batch clears it)
            answers = model.images[np.maximum(o.answer_image, 0)]
            recording.send_columns(f"route/{short}", indexes=times, columns=rr.Points2D.columns(
                positions=route.database[answers[accepted]],
                colors=np.array([_COLORS[Verdict(v)] for v in said[key][accepted]], dtype=np.uint8).reshape(-1, 3),
                radii=np.full(int(accepted.sum()), rr.components.Radius.ui_points(4.5), dtype=np.float32),
            ).partition(accepted.astype(np.int64)))

    for q in range(n):
        recording.set_time(TIMELINE, sequence=q)
        recording.log("query", _image(ds.query_paths[q]))
        for key, short in RECORDED.items():
            a = int(decisions.outcomes[key].answer_image[q])
            recording.log(f"match/{short}", _image(ds.database_paths[model.images[a]]) if a >= 0
                          else rr.Clear(recursive=False))
        if progress is not None:
            progress(q + 1, n)
    recording.reset_time()


# --------------------------------------------------------------------------- the acceptance bench


def check_bench(dataset: RetrievalDataset) -> None:
    """Refuse, naming the bench, a value the acceptance bench cannot run on (before any descriptor is computed).

    Raises:
        VPRInputError: a value without queries, or more query × database pairs than the bench
            holds (``acceptance.BENCH_PAIRS``: it keeps the whole similarity matrix).
    """
    if not dataset.n_queries:
        raise VPRInputError(f"bench: {dataset.name!r} has no query image, so the acceptance bench has nothing to "
                            "decide; record without the bench")
    pairs = dataset.n_queries * dataset.n_database
    if pairs > acceptance.BENCH_PAIRS:
        raise VPRInputError(f"bench: {dataset.name!r} has {dataset.n_queries:,} queries × {dataset.n_database:,} "
                            f"database images = {pairs:,} pairs, and the acceptance bench holds the whole similarity "
                            f"matrix (at most {acceptance.BENCH_PAIRS:,} pairs): record without the bench, or choose "
                            "fewer queries or a smaller database")


def bench_report(fitted: RetrievalFitted, descriptors: np.ndarray, *, options: BenchOptions | None = None,
                 descriptor: str | None = None) -> AcceptanceReport:
    """The acceptance bench on the value ``fitted`` plays back, with its places (``acceptance.acceptance_report``).

    The per-place rules read ``fitted.database_place`` (the places the recorded methods use),
    unless ``options.places`` asks for discovered places.

    Args:
        descriptors: ``(n_images, D)`` of ``fitted.dataset``, database rows first.
        options: the bench's choices (default ``BenchOptions()``).
        descriptor: its name, for the report's settings.

    Raises:
        VPRInputError: naming the bench: a value it cannot run on (``check_bench``), descriptors
            of another dataset.
    """
    ds = fitted.dataset
    check_bench(ds)
    try:
        return acceptance.acceptance_report(ds, descriptors, labels=fitted.database_place, options=options,
                                            settings={"descriptor": descriptor or "not given",
                                                      "group/step": fitted.places.describe(ds)})
    except VPRInputError as exc:
        raise VPRInputError(f"bench: {exc}") from exc


def check_report(report: AcceptanceReport, dataset: RetrievalDataset) -> None:
    """Refuse a bench report of another value than the one recorded (its queries, database or right images differ).

    Right images are checked through what they decide: the queries with one, and every
    closed-set rule's counts counted again on ``dataset``'s ground truth.

    Raises:
        VPRInputError: naming both values.
    """
    got = (report.settings.get("dataset"), report.settings.get("n_queries"), report.settings.get("n_database"))
    same = got == (dataset.name, dataset.n_queries, dataset.n_database) and np.array_equal(
        report.closed.genuine, dataset.ground_truth.counts > 0)
    if same:
        hard = dataset.ground_truth.dense()
        bench = report.closed
        same = all(acceptance.authors_counts(d.answer, d.accepted, hard, bench.genuine, bench.counted)
                   == bench.counts[key] for key, d in bench.decisions.items())
    if not same:
        raise VPRInputError(f"bench: the report is of {got[0]!r} ({got[1]} queries, {got[2]} database images), the "
                            f"recording of {dataset.name!r} ({dataset.n_queries} queries, {dataset.n_database} "
                            "database images, or other right images): run the bench on the value recorded "
                            "(bench_report)")


def bench_verdicts(bench: Bench, key: str, hard: np.ndarray) -> np.ndarray:
    """``(n_queries,)`` what one rule's decision of each query was, by the authors' counts (module docstring).

    Args:
        bench: the closed set or the natural open set.
        key: a rule that ran (``bench.decisions``).
        hard: ``(n_queries, n_database)`` bool right images of the whole database (the natural
            open set's answers lie in its first part).

    Returns:
        ``Verdict`` values (right, wrong accept, wrong reject) and ``NOT_COUNTED``, as objects.
    """
    d = bench.decisions[key]
    rows = np.arange(len(d.answer))
    hit = d.accepted & hard[rows, np.maximum(d.answer, 0)]
    out = np.where(hit, Verdict.RIGHT.value, np.where(d.accepted, Verdict.WRONG_ACCEPT.value,
                                                      Verdict.WRONG_REJECT.value))
    out = np.where(bench.genuine, out, np.where(d.accepted, Verdict.WRONG_ACCEPT.value, Verdict.RIGHT.value))
    return np.where(bench.counted, out, NOT_COUNTED).astype(object)


def _image_name(dataset: RetrievalDataset, image: int) -> str:
    path = dataset.database_paths[image]
    return f"database image {image}, {path.parent.name}/{path.name}"


def describe_bench(dataset: RetrievalDataset, bench: Bench, key: str, hard: np.ndarray) -> list[str]:
    """One rule's decision of every query in words, e.g.
    "accepted database image 37, day_right/Image037.jpg (right); confidence +0.0521".

    Args:
        hard: ``(n_queries, n_database)`` bool right images of the whole database.
    """
    d = bench.decisions[key]
    said = bench_verdicts(bench, key, hard)
    # the natural open set's database is the first part of the route: its distractors have right images beyond it
    cut = len(bench.places) < dataset.n_database
    missing = (f"no right image in the first {len(bench.places)} database images" if cut
               else "no right image in the database")
    texts = []
    for q in range(len(d.answer)):
        candidate, verdict = int(d.candidate[q]), said[q]
        if d.accepted[q]:
            head = f"accepted {_image_name(dataset, candidate)}"
        elif candidate >= 0:
            head = f"rejected its candidate, {_image_name(dataset, candidate)}"
        else:
            head = "rejected, no candidate"
        if verdict == NOT_COUNTED:
            why = "not counted: the query has no right database image, and the closed set counts only those that do"
        elif not bench.genuine[q]:
            why = f"{'right' if verdict == Verdict.RIGHT.value else 'wrong'}: the query has {missing}"
        elif verdict == Verdict.RIGHT.value:
            why = "right"
        elif verdict == Verdict.WRONG_ACCEPT.value:
            why = "wrong: not a right image of the query"
        else:
            why = "wrong: the query has a right database image"
        conf = f"; confidence {d.confidence[q]:+.4g}" if np.isfinite(d.confidence[q]) else ""
        texts.append(f"{head} ({why}){conf}")
    return texts


def _left_out_reason(report: AcceptanceReport, bench: Bench, key: str) -> str:
    """Why ``key`` did not run: the report's note where it says more than the bench (SUE's positions)."""
    why = bench.left_out[key]
    if why == report.closed.left_out.get(key):
        head = f"{key} left out: "
        why = next((n[len(head):] for n in report.notes if n.startswith(head)), why)
    return why


def bench_summary(report: AcceptanceReport, which: str) -> str:
    """The summary (markdown) of one bench (``BENCH_SETS``): each rule's counts in one line, and each left out."""
    root, name = BENCH_SETS[which]
    bench: Bench | None = getattr(report, which)
    settings = report.settings
    share = settings["reference_share"]
    title = ("closed set: the whole database" if which == "closed"
             else f"natural open set: the first {share:.0%} of the database route")
    lines = [f"# Acceptance bench, {title}", "",
             f"- {settings['dataset']}: {settings['n_queries']:,} queries, {settings['n_database']:,} database "
             f"images; descriptor {settings.get('descriptor', 'not given')}",
             f"- places: {settings['places']} ({settings.get('group/step', 'group/step not given')}), place score "
             f"{settings['place_score']}"]
    if bench is None:
        return "\n".join([*lines, "", f"Not run: {report.natural_note}", ""])
    n_genuine = int((bench.genuine & bench.counted).sum())
    n_distractor = int((~bench.genuine & bench.counted).sum())
    lines += [f"- {n_genuine} genuine queries (a right database image), {n_distractor} distractors (none)"
              + (f", {int((~bench.counted).sum())} not counted (no right database image)"
                 if not bench.counted.all() else ""),
              f"- on the `{TIMELINE}` timeline, per rule: `{root}/<rule>/confidence` (where the rule has a "
              f"candidate), `{root}/<rule>/accepted` (1 accepted, 0 rejected) and `{root}/<rule>/decision`",
              "", "## Rules (the authors' counts, percent)", ""]
    for key, d in bench.decisions.items():
        c = bench.counts[key]
        rejection = "" if c.rejection is None else f", rejection {c.rejection:.1f}"
        tau = f"; τ {d.tau:.4g} ({d.tau_note})" if np.isfinite(d.tau) else ""
        lines.append(f"- **{key}** ({d.rule.label}): F1 {c.f1:.1f}, P {c.precision:.1f}, R {c.recall:.1f}"
                     f"{rejection}; TP {c.tp}, FP {c.fp}, FN {c.fn}, TN {c.tn}{tau}")
    if bench.left_out:
        lines += ["", "## Left out (nothing logged)", ""]
        lines += [f"- **{key}** ({acceptance.RULES_BY_KEY[key].label}): {_left_out_reason(report, bench, key)}"
                  for key in bench.left_out]
    return "\n".join(lines) + "\n"


def bench_lines(report: AcceptanceReport) -> list[str]:
    """The bench in a few lines: each set's rules logged, and those left out with the reason."""
    lines = []
    for which, (root, name) in BENCH_SETS.items():
        bench: Bench | None = getattr(report, which)
        if bench is None:
            lines.append(f"{name}: not run ({report.natural_note})")
            continue
        lines.append(f"{name}: {len(bench.decisions)} rules logged under {root}/ ({', '.join(bench.decisions)})")
        lines += [f"  {key} left out: {_left_out_reason(report, bench, key)}" for key in bench.left_out]
    return lines


def log_bench(recording: rr.RecordingStream, report: AcceptanceReport, dataset: RetrievalDataset) -> None:
    """Log the bench's decisions of ``dataset``'s queries to ``recording`` (entities in the module docstring).

    Raises:
        VPRInputError: a report of another value (``check_report``).
    """
    check_report(report, dataset)
    hard = dataset.ground_truth.dense()
    queries = np.arange(dataset.n_queries, dtype=np.int64)
    times = [rr.TimeColumn(TIMELINE, sequence=queries)]
    colors = {r.key: _RULE_COLORS[i % len(_RULE_COLORS)] for i, r in enumerate(RULES)}
    for which, (root, _) in BENCH_SETS.items():
        recording.log(f"{root}/summary", rr.TextDocument(bench_summary(report, which),
                                                         media_type=rr.MediaType.MARKDOWN), static=True)
        bench: Bench | None = getattr(report, which)
        if bench is None:
            continue
        for key, d in bench.decisions.items():
            _log_rule(recording, f"{root}/{key}", d, colors[key], queries, times,
                      describe_bench(dataset, bench, key, hard), bench_verdicts(bench, key, hard))


def _log_rule(recording: rr.RecordingStream, path: str, d: RuleDecisions, color: tuple[int, int, int],
              queries: np.ndarray, times: list, texts: list[str], said: np.ndarray) -> None:
    key = d.rule.key
    live = np.isfinite(d.confidence)
    recording.log(f"{path}/confidence", rr.SeriesLines(colors=[color], names=[f"{key}: confidence"]), static=True)
    recording.send_columns(f"{path}/confidence", indexes=[rr.TimeColumn(TIMELINE, sequence=queries[live])],
                           columns=rr.Scalars.columns(scalars=np.asarray(d.confidence, dtype=np.float64)[live]))
    recording.log(f"{path}/accepted", rr.SeriesPoints(colors=[color], markers=["Circle"],
                                                      names=[f"{key}: accepted (1) or not (0)"]), static=True)
    recording.send_columns(f"{path}/accepted", indexes=times,
                           columns=rr.Scalars.columns(scalars=np.asarray(d.accepted, dtype=np.float64)))
    recording.send_columns(f"{path}/decision", indexes=times, columns=rr.TextLog.columns(
        text=[f"query {q} · {key}: {t}" for q, t in zip(queries, texts)],
        level=[_BENCH_LEVELS[v] for v in said],
    ))


# --------------------------------------------------------------------------- recording


def new_recording(recording_id: str | None = None) -> rr.RecordingStream:
    """A fresh explicit recording of this application (never rerun's global one), on the query timeline only."""
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id or uuid.uuid4().hex)
    rec.set_log_time_enabled(False)
    return rec


def check_output(path: str | Path) -> Path:
    """``path`` as an ``.rrd`` file that can be written, or a ``VPRInputError`` saying why not."""
    path = Path(path).expanduser()
    if path.suffix.lower() != ".rrd":
        raise VPRInputError(f"{path}: a rerun recording needs the .rrd suffix, e.g. {path.with_suffix('.rrd')}")
    if path.is_dir():
        raise VPRInputError(f"{path}: is a folder; give a file name such as {path / 'run.rrd'}")
    if path.parent.exists() and not path.parent.is_dir():
        raise VPRInputError(f"{path}: {path.parent} is a file, not a folder; pick another path")
    if not path.parent.is_dir():
        raise VPRInputError(f"{path}: the folder {path.parent} does not exist; create it or pick another path")
    existed = path.exists()
    try:
        with path.open("ab"):
            pass
    except OSError as exc:
        raise VPRInputError(f"{path}: cannot write the recording ({exc.strerror}); pick a writable path") from exc
    if not existed:
        path.unlink(missing_ok=True)
    return path


# --------------------------------------------------------------------------- serving


SERVER_MEMORY_LIMIT = "1GiB"
"""What the gRPC server buffers for viewers that connect late; the oldest data goes first."""


@dataclass(frozen=True)
class ViewerServers:
    """The process's rerun gRPC server and bundled web viewer, both reached on 127.0.0.1."""

    grpc_url: str
    web_port: int

    @property
    def viewer_url(self) -> str:
        """The web viewer, connected to the gRPC server."""
        return f"http://127.0.0.1:{self.web_port}/?url={urllib.parse.quote(self.grpc_url, safe='')}"


_lock = threading.Lock()
_servers: ViewerServers | None = None
_server_owner: rr.RecordingStream | None = None
"""The recording that owns the gRPC server: rerun shuts the server down when it goes away."""
_playback_dir: Path | None = None


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def viewer_servers() -> ViewerServers:
    """Start the gRPC server and the bundled web viewer, once per process; later calls reuse them.

    Recordings reach the server through a ``GrpcSink``; the server keeps what it received
    (up to ``SERVER_MEMORY_LIMIT``) for every viewer that connects, so every recording
    made in this process is listed in the viewer, the newest one shown. rerun 0.41 binds
    both servers on all interfaces (it has no host option); the URLs use 127.0.0.1.
    """
    global _servers, _server_owner
    with _lock:
        if _servers is None:
            owner = rr.RecordingStream(APPLICATION_ID, recording_id="playback-server")
            owner.send_recording_name("playback server (holds no data)")
            grpc_url = owner.serve_grpc(grpc_port=_free_port(), server_memory_limit=SERVER_MEMORY_LIMIT)
            web_port = _free_port()
            rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=grpc_url)
            _server_owner = owner
            _servers = ViewerServers(grpc_url=grpc_url, web_port=web_port)
        return _servers


def playback_dir() -> Path:
    """A folder for this process's recordings, removed when the process exits."""
    global _playback_dir
    with _lock:
        if _playback_dir is None:
            _playback_dir = Path(tempfile.mkdtemp(prefix="vpr_explorer_playback_"))
            atexit.register(shutil.rmtree, _playback_dir, True)
        return _playback_dir


# --------------------------------------------------------------------------- end to end


@dataclass(frozen=True, eq=False)
class Playback:
    """A recorded sequence of queries: where its ``.rrd`` is, what was decided and where to watch it.

    Attributes:
        rrd: the recording file.
        recording_id: rerun's recording id (the viewer lists recordings by it).
        dataset: the dataset name.
        database: database traversal names (``("database",)`` for a layout without traversals).
        query: query traversal name.
        decisions: the library's decisions, exactly what was logged.
        viewer_url: the bundled web viewer showing it, when it was served.
        bench: the acceptance bench logged with it (``log_bench``), or ``None``.
    """

    rrd: Path
    recording_id: str
    dataset: str
    database: tuple[str, ...]
    query: str
    decisions: QueryDecisions
    viewer_url: str | None = None
    bench: AcceptanceReport | None = None

    @property
    def n_queries(self) -> int:
        return self.decisions.n_queries

    def counts(self) -> dict[str, dict[Verdict, int]]:
        """Method key -> queries per verdict, for the recorded methods."""
        return {key: verdict_counts(self.decisions, key) for key in RECORDED}

    def describe(self) -> str:
        """One line per recorded method, e.g. "margin, weighted θ: 45 right, 3 wrong accepts, …"."""
        lines = [f"{self.n_queries} queries of {self.query} against {', '.join(self.database)} ({self.dataset})"]
        for key, c in self.counts().items():
            lines.append(
                f"{METHODS_BY_KEY[key].label}: {c[Verdict.RIGHT]} right, {c[Verdict.WRONG_ACCEPT]} wrong accepts, "
                f"{c[Verdict.WRONG_REJECT]} wrong rejects ({c[Verdict.BETWEEN]} queries between places, not scored)"
            )
        if self.bench is not None:
            lines += bench_lines(self.bench)
        return "\n".join(lines)


def check_k(k: float) -> float:
    """``k`` of θ_p + k·s_p as a finite number, or a ``VPRInputError`` naming it."""
    return check_finite("k", k, example="0 for the paper's θ_p, 1 for θ_p + s_p")


def record_playback(
    fitted: RetrievalFitted,
    descriptors: np.ndarray,
    *,
    out: str | Path | None = None,
    serve: bool = False,
    k: float = 0.0,
    descriptor: str | None = None,
    recording_id: str | None = None,
    progress: Progress | None = None,
    bench: AcceptanceReport | None = None,
) -> Playback:
    """Decide every query of a fitted value (``decide_every_query``) and record them, in order, to an ``.rrd``.

    The recording is written beside ``out`` and renamed over it once complete: an interrupted
    or failed run leaves an existing recording as it was (and no partial file).

    Args:
        fitted: the value's places and database thresholds (``numbers.fit_retrieval``).
        descriptors: ``(n_images, D)`` of ``fitted.dataset``, database rows first.
        out: the ``.rrd`` to write; default a new file in ``playback_dir()``.
        serve: also stream it to this process's viewer servers (``viewer_servers``); the
            returned ``Playback.viewer_url`` shows it.
        k: thresholds θ_p + k·s_p (0: the paper's).
        descriptor: its name, for the summary.
        progress: ``progress(done, total)`` after each logged query.
        bench: the acceptance bench of the same value (``bench_report``), logged with the
            queries (``log_bench``); ``None`` records without it.

    Raises:
        VPRInputError: an unwritable ``out``, a non-finite ``k``, descriptors of another dataset, an
            unreadable image, a bench report of another value.
    """
    rid = recording_id or uuid.uuid4().hex
    out = check_output(out if out is not None else playback_dir() / f"{rid}.rrd")
    k = check_k(k)
    if bench is not None:
        check_report(bench, fitted.dataset)
    decisions = decide_every_query(fitted, descriptors, k=k)
    database, query = sides(fitted.dataset)
    servers = viewer_servers() if serve else None
    rec = new_recording(rid)
    partial = out.with_name(f".{out.stem}.{uuid.uuid4().hex[:8]}.partial.rrd")
    sinks: list = [rr.FileSink(partial)]
    if servers is not None:
        sinks.append(rr.GrpcSink(servers.grpc_url))
    try:
        try:
            rec.set_sinks(*sinks)
        except RuntimeError as exc:
            raise VPRInputError(f"{out}: cannot write the recording ({exc}); pick a writable path") from exc
        rec.send_recording_name(f"{fitted.dataset.name}: {query} against {', '.join(database)}")
        rec.send_blueprint(playback_blueprint(query, database, bench=bench is not None))
        try:
            log_queries(rec, decisions, descriptor=descriptor, progress=progress)
            if bench is not None:
                log_bench(rec, bench, fitted.dataset)
        finally:
            # Sends what is buffered and closes the file (writing its footer); the served copy
            # lives on in the gRPC server, which ``_server_owner`` keeps running.
            rec.flush()
            rec.disconnect()
        try:
            partial.replace(out)
        except OSError as exc:
            raise VPRInputError(f"{out}: cannot write the recording ({exc.strerror}); pick a writable path") from exc
    finally:
        partial.unlink(missing_ok=True)
    return Playback(rrd=out, recording_id=rec.get_recording_id(), dataset=fitted.dataset.name, database=database,
                    query=query, decisions=decisions, viewer_url=servers.viewer_url if servers else None,
                    bench=bench)


def load_traversals(source: str | Path, database: Sequence[str] | None = None, queries: str | None = None,
                    layout: str = "auto") -> Dataset:
    """Aligned traversals at ``source`` (or ``"demo"``), with the chosen traversals checked.

    With both ``database`` and ``queries``, a traversal-folder dataset is read with only these
    traversals, so the loader checks that they exist and have equal lengths (frame i must be
    the same spot in each), and the folder's other traversals do not matter.
    """
    from vpr_explorer.pipeline import DEMO, open_dataset

    if database is None or queries is None or str(source) == DEMO:
        dataset = open_dataset(source, layout)
    else:
        if queries in database:
            raise VPRInputError(f"queries={queries!r} is also a database traversal; pick another query traversal")
        try:
            dataset = load_dataset(source, traversals=[*dict.fromkeys(database), queries])
        except VPRInputError as exc:
            raise VPRInputError(f"database={list(database)}, queries={queries!r}: {exc}") from None
    for name in (*(database or ()), *([queries] if queries else [])):
        dataset.traversal_index(name)
    return dataset


def _places(value: RetrievalDataset, group: float, step: float, reading: str, geometry: str | None) -> RetrievalPlaces:
    """The value's places: its own ids, or group/step in the geometry asked (default the value's,
    ``numbers.check_geometry``)."""
    g = check_geometry(value, geometry)
    if g is None:
        return RetrievalPlaces(None)
    if g is PlaceGeometry.FRAMES:
        return RetrievalPlaces(g, spec=PlaceSpec(group, step, reading))
    return RetrievalPlaces(g, metric=MetricPlaceSpec(group, step, reading, g))


def record_dataset(
    dataset: Dataset | RetrievalDataset,
    descriptor: str,
    *,
    query: str | None = None,
    database: Sequence[str] | None = None,
    tolerance: int = 0,
    group: float = 3,
    step: float = 10,
    reading: str = Reading.STRIDE.value,
    geometry: str | None = None,
    out: str | Path | None = None,
    serve: bool = False,
    k: float = 0.0,
    recording_id: str | None = None,
    cache_root: Path | None = None,
    extract_progress: Progress | None = None,
    progress: Progress | None = None,
    dtype: str = "float32",
    descriptors_file: Path | None = None,
    names_file: Path | None = None,
    bench: BenchOptions | None = None,
    descriptor_options: Mapping[str, object] | None = None,
) -> Playback:
    """Everything from an opened dataset (``pipeline.open_dataset``, ``load_traversals``) to a recorded ``.rrd``.

    Aligned traversals become the value ``data.aligned.database_queries(dataset, query,
    database, tolerance)`` (default query: ``Dataset.default_roles``); any other layout is the
    value already. Its places are the layout's own, or group/step in ``geometry`` (frames, or
    metres along the route or over a lattice; default the value's). Options and places are
    checked before any descriptor is computed. ``dtype`` is the descriptors' precision and
    ``descriptor_options`` the extractor's options (``pipeline.dataset_descriptors``). With
    ``descriptors_file``, descriptors computed elsewhere (for the whole dataset) are read from
    it instead. With ``bench`` (its choices), the acceptance bench runs on the same value and
    places (``bench_report``) and is recorded with the queries.

    Raises:
        VPRInputError: naming the option at fault: a non-finite ``k``, a bad tolerance, traversals
            or traversal options for a layout without them, group/step that make no places, a
            value the bench cannot run on (``check_bench``).
    """
    from vpr_explorer.pipeline import dataset_descriptors, imported_descriptors

    k = check_k(k)
    if isinstance(dataset, Dataset):
        check_whole("tolerance", tolerance, low=0, high=dataset.n_frames,
                    why=f" (frames of slack; {dataset.name!r} has {dataset.n_frames:,} frames)")
        if query is None:
            query = dataset.traversals[dataset.default_roles().query]
        value = database_queries(dataset, query, database, tolerance)
    else:
        if query is not None or database is not None or tolerance:
            raise VPRInputError(f"{dataset.name!r} is a {dataset.layout.value} layout: its queries and ground truth "
                                "are set when it is opened; drop the traversals and the tolerance")
        value = dataset
    places = _places(value, group, step, reading, geometry)
    retrieval_places(value, places.spec, places.metric)  # too few places fail before any descriptor is computed
    if bench is not None:
        check_bench(value)
    if descriptors_file is not None:  # the file covers the whole dataset
        whole = load_dataset(dataset.root) if isinstance(dataset, Dataset) else dataset
        imp = imported_descriptors(whole, descriptors_file, names_file=names_file, dtype=dtype)
        descriptors, descriptor = imp.descriptors, imp.name
        if whole.image_paths != dataset.image_paths:  # aligned traversals read with some of their traversals
            row = {p: i for i, p in enumerate(whole.image_paths)}
            descriptors = descriptors[[row[p] for p in dataset.image_paths]]
    else:
        check_cache_root(cache_root)
        descriptors = dataset_descriptors(dataset, descriptor, cache_root=cache_root, progress=extract_progress,
                                          dtype=dtype, options=descriptor_options)
    rows = value_rows(value)
    if rows is not None:
        descriptors = descriptors[rows]
    fitted = fit_retrieval(descriptors, value, places)
    report = None if bench is None else bench_report(fitted, descriptors, options=bench, descriptor=descriptor)
    return record_playback(fitted, descriptors, out=out, serve=serve, k=k, descriptor=descriptor,
                           recording_id=recording_id, progress=progress, bench=report)
