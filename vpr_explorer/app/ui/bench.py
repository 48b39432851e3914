"""The acceptance bench on the Evaluation page, and discovered places on the Places page.

**The bench** (``protocols.acceptance`` through ``cache.bench``): a form whose **Run the
bench** button commits its settings, like the page's protocol form: the widgets are drawn
from the committed settings on every run and the results are looked up from them, so the
controls above a table are always the ones it was computed with. Nothing is computed before
the button is pressed (Nordland: about 12 s); afterwards the result is cached and shown
again while the dataset value, its places and the settings stay the same. Settings:

* the database traversal (aligned traversals only; one, so that the sequence rules see one
  route; default the first traversal that is not the query) and the tolerance of the
  ground truth in frames (default 2, the authors' ±2);
* the per-place rules' places: group/step from the sidebar (``PlaceSource.GROUP_STEP``,
  the default) or discovered online (``PlaceSource.DISCOVERED``, refused with the reason
  where the database is not one route in order); their score, best (default) or mean;
* the natural open set's reference share F, in percent (default 70);
* the per-query threshold's patch p, the graph matcher's fan-out and SeqSLAM's ds
  (defaults ``PATCH``, ``FANOUT``, ``DS``).

Shown: the authors' table (``bench_plots.bench_rows``), the rules left out with their
reasons, the bench varied over one parameter (below), every rule's precision–recall curve
with its own decisions marked (closed set, or the natural open set by a toggle), and
VPR_Tutorial's single- and multi-match curves on the same value (``protocols.tutorial_pr``;
soft positives ignored in the multi-match curve where the ground truth has them; the single
curve counts hard positives only, as VPR_Tutorial refuses soft positives with single
matching).

**Vary one parameter** (``protocols.acceptance_sweep.sweep_bench``, the app's counterpart of
``vpr-explorer acceptance --vary``), under the table: the bench once per value of one
parameter, the others at the committed settings. The picker offers only the parameters the
value's bench reads (``offered_parameters``: ``check_parameter``, whose refusals are listed
with why, e.g. ds where the queries are not one route in order); the values box starts from
``DEFAULT_VALUES`` (group/step: around the sidebar's, ``default_values``), comma-separated,
whole numbers but for ``reference_share`` (a fraction, as the CLI takes it) and metres.
Nothing runs before **Vary** is pressed (Nordland's 3,576 frames: 4–8 s a value, under a
spinner); the sweep is cached (``bench_sweep``: keyed like ``cache.bench``, with the
parameter and its values) and shown while the bench's value, places and settings stay those
it was pressed with. Shown: for one metric (closed-set F1, natural open-set F1 or rejection,
a radio) one line per rule across the values, the rules the parameter does not affect faint
and dashed (``bench_plots.sweep_figure``); the same numbers as a table, the rules left out at
some value, a CSV of every number (``bench_plots.sweep_rows``) and the CLI's text table. A
value list that does not parse, or one the library refuses, is an ``st.error`` with the
library's message, never a traceback.

**Discovered places** (``method.place_discovery.discover``, the authors' defaults): on the
database images of one route in order. For aligned traversals, one database traversal
(a selectbox where there are several; default the first); for another layout, its database
when it is one route in order, and otherwise the reason.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, replace

import numpy as np
import pandas as pd  # before plotly: plotly.py#2433
import streamlit as st

from vpr_explorer.data.layouts import RetrievalDataset
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.graph_matcher import FANOUT
from vpr_explorer.method.place_discovery import ALPHA, HYSTERESIS, MIN_SIZE, Discovery, discover
from vpr_explorer.method.places import MetricPlaceSpec, PlaceSpec, Reading, retrieval_places
from vpr_explorer.method.query_threshold import PATCH
from vpr_explorer.method.retrieval import similarity
from vpr_explorer.method.sequences import DS
from vpr_explorer.protocols.acceptance import (
    REFERENCE_SHARE,
    RULES,
    RULES_BY_KEY,
    AcceptanceReport,
    BenchOptions,
    PlaceScore,
    PlaceSource,
)
from vpr_explorer.protocols.acceptance_sweep import (
    DESCRIPTIONS,
    BenchSweep,
    Parameter,
    check_parameter,
    render,
    sweep_bench,
)
from vpr_explorer.protocols.tutorial_pr import Matching, TutorialPR, tutorial_pr
from vpr_explorer.views import bench_plots
from vpr_explorer.views.numbers import RetrievalPlaces

from vpr_explorer.app.ui import cache
from vpr_explorer.app.ui.current import Current
from vpr_explorer.app.ui.feedback import show_error

TOLERANCE_RANGE = (0, 20)
SHARE_RANGE = (5, 95)
PATCH_RANGE = (2, 500)
FANOUT_RANGE = (1, 50)
DS_RANGE = (2, 200)
#: Discovery is a Python loop over the stream (Nordland's 3,576 frames: 0.05 s); past this many
#: database images the Places page does not run it by itself.
DISCOVERY_FRAMES = 100_000
PLACE_LABELS = {PlaceSource.GROUP_STEP.value: "group/step from the sidebar",
                PlaceSource.DISCOVERED.value: "discovered online"}
SCORE_LABELS = {PlaceScore.BEST.value: "best similarity (paper)", PlaceScore.MEAN.value: "mean similarity"}
BENCH_CAPTION = (
    "The authors' counts (NickTrinh/VPR_Tutorial `final_all_datasets.py`): over genuine queries (a right database "
    "image) and distractors (none), TP = accepted with a right image, FP = accepted with a wrong one or an accepted "
    "distractor, FN = a rejected genuine query, TN = a rejected distractor; F1 from P = TP/(TP+FP) and "
    "R = TP/(TP+FN), in percent. R@K: genuine queries accepted with a right image among the first K. **Closed set**: "
    "the whole database, genuine queries only. **Natural open set**: the database cut to its first F of the route; "
    "queries whose right images all lie beyond the cut are distractors, and **rejection** is the share of them "
    "rejected. AUC-PR: the closed set's curve. † τ at the best F1 on these very queries (oracle): a bound on what "
    "the rule can do, not a rule you could run."
)
#: the values box's first values per parameter (group/step: ``default_values``, around the sidebar's)
DEFAULT_VALUES: dict[Parameter, tuple[int | float, ...]] = {
    Parameter.DS: (4, 6, 10, 20), Parameter.PATCH: (10, 20, 40), Parameter.FANOUT: (1, 3, 5, 10),
    Parameter.SUE_K: (5, 10, 20), Parameter.REFERENCE_SHARE: (0.5, 0.6, 0.7, 0.8)}
#: the parameters whose values are whole numbers (reference_share is a fraction; group/step follow the places)
WHOLE = (Parameter.DS, Parameter.PATCH, Parameter.FANOUT, Parameter.SUE_K)


@dataclass(frozen=True)
class BenchSettings:
    """The bench's committed settings; ``database`` ``None``: the first traversal that is not the query."""

    database: str | None = None
    tolerance: int = 2
    places: str = PlaceSource.GROUP_STEP.value
    place_score: str = PlaceScore.BEST.value
    share: int = round(100 * REFERENCE_SHARE)
    patch: int = PATCH
    fanout: int = FANOUT
    ds: int = DS


_WIDGETS = {"database": "w_bench_database", "tolerance": "w_bench_tolerance", "places": "w_bench_places",
            "place_score": "w_bench_place_score", "share": "w_bench_share", "patch": "w_bench_patch",
            "fanout": "w_bench_fanout", "ds": "w_bench_ds"}


def route_problem(ds: RetrievalDataset) -> str | None:
    """Why the value's database is not one route in order (what discovery and the natural open set read), or ``None``."""
    traversals = np.unique(ds.database_traversal) if ds.database_traversal is not None else ()
    if not ds.ordered:
        return (f"the database of {ds.name!r} ({ds.layout.value} layout) is not one route in order: its images are "
                "a set, with no order along a route")
    if len(traversals) > 1:
        return f"the database of {ds.name!r} holds {len(traversals)} traversals, not one route"
    if ds.database_frame is not None and np.any(np.diff(ds.database_frame) <= 0):
        return f"the database of {ds.name!r} is not in frame order"
    return None


def database_choices(cur: Current) -> tuple[str, ...]:
    """The traversals the bench may take as its database: every traversal but the query (aligned traversals)."""
    if cur.aligned is None:
        return ()
    return tuple(t for t in cur.aligned.traversals if t != cur.query)


def bench_value(cur: Current, s: BenchSettings) -> cache.Loaded:
    """The dataset value the bench runs on: one database traversal against the query traversal (aligned
    traversals, ``s.tolerance`` frames either side right), or the layout's own value."""
    if cur.aligned is None:
        return cur.data
    choices = database_choices(cur)
    database = s.database if s.database in choices else choices[0]
    return cache.value(cur.source, cur.query, database=(database,), tolerance=s.tolerance)


def bench_options(s: BenchSettings, value: RetrievalDataset) -> BenchOptions:
    """The library's options of the settings; discovered places are refused where the database is not a route.

    Raises:
        VPRInputError: naming the setting and what to choose instead.
    """
    if s.places == PlaceSource.DISCOVERED:
        why = route_problem(value)
        if why is not None:
            raise VPRInputError(f"places=discovered: discovery cuts the database into places in route order, and "
                                f"{why}; choose group/step places")
    return BenchOptions(places=s.places, place_score=s.place_score, reference_share=s.share / 100,
                        patch=int(s.patch), fanout=int(s.fanout), ds=int(s.ds))


def _committed(cur: Current) -> BenchSettings:
    s = st.session_state.get("bench_settings", BenchSettings())
    if s.database is not None and s.database not in database_choices(cur):
        s = replace(s, database=None)  # another dataset, or that traversal became the query
    st.session_state["bench_settings"] = s
    return s


def _commit(cur: Current) -> None:
    """The form's **Run the bench**: its widgets become the committed settings, and a run is asked for."""
    ss = st.session_state
    choices = database_choices(cur)
    values = {field: ss[key] for field, key in _WIDGETS.items() if key in ss}
    if len(choices) < 2 or values.get("database") == choices[0]:
        values["database"] = None  # the default: the first traversal that is not the query
    if not choices:
        values.pop("tolerance", None)  # the layout fixes its ground truth
    s = replace(ss.get("bench_settings", BenchSettings()), **values)
    ss["bench_settings"] = s
    ss["bench_asked"] = True


def _identity(value: cache.Loaded, cur: Current, s: BenchSettings) -> tuple:
    """What a shown bench depends on: the value (its key holds database, query and tolerance), places, settings."""
    return value.key, cache.places_key(cur.places), s


def controls(cur: Current, s: BenchSettings) -> None:
    """The bench's form, drawn from the committed settings ``s``."""
    choices = database_choices(cur)
    drawn = [f for f in _WIDGETS if f not in ("database", "tolerance")]
    if choices:
        drawn.append("tolerance")
    if len(choices) > 1:
        drawn.append("database")
    # the widgets show the committed settings, every run (a form's unsent edits are not settings)
    shown = {**asdict(s), "database": s.database or (choices[0] if choices else None)}
    for field in drawn:
        st.session_state[_WIDGETS[field]] = shown[field]
    with st.form("bench_form"):
        c = st.columns(4)
        if len(choices) > 1:
            c[0].selectbox("database traversal", list(choices), key=_WIDGETS["database"],
                           help=f"One traversal, so that the sequence rules see one route; the queries are "
                                f"{cur.query} (the Places page's query traversal).")
        elif choices:
            c[0].markdown(f"database traversal: **{choices[0]}**  \nqueries: **{cur.query}**")
        if choices:
            c[1].number_input("tolerance ± frames", *TOLERANCE_RANGE, key=_WIDGETS["tolerance"],
                              help="A database image within this many frames of the query's is right (the authors "
                                   "count ±2).")
        c[2].radio("places (per-place rules)", list(PLACE_LABELS), format_func=PLACE_LABELS.get,
                   key=_WIDGETS["places"], help=f"Group/step: {cur.places.describe(cur.dataset)}. Discovered: cut "
                                                "online from the database stream (the authors' follow-up).")
        c[3].radio("place score", list(SCORE_LABELS), format_func=SCORE_LABELS.get, key=_WIDGETS["place_score"],
                   help="A place's score for a query: the best of its images' similarities (the paper) or their "
                        "mean (the authors' follow-up).")
        c = st.columns(4)
        c[0].slider("open set: reference share F", *SHARE_RANGE, step=5, format="%d%%",
                    key=_WIDGETS["share"], help="The database is cut to its first F of the route; queries whose "
                                                "right images lie beyond it are distractors.")
        c[1].number_input("patch p (per-query threshold)", *PATCH_RANGE, key=_WIDGETS["patch"],
                          help="Vysotska et al.'s per-query threshold: the patch of ranked similarities it reads.")
        c[2].number_input("fan-out (graph matcher)", *FANOUT_RANGE, key=_WIDGETS["fanout"],
                          help="Successors of each node in the graph matcher of the per-query full pipeline.")
        c[3].number_input("sequence length ds (SeqSLAM)", *DS_RANGE, key=_WIDGETS["ds"],
                          help="SeqSLAM's sequence length, also of the per-place rule on sequence scores.")
        st.form_submit_button("Run the bench", type="primary", key="w_bench_run", on_click=_commit, args=(cur,))


def section(cur: Current) -> None:
    """The Evaluation page's acceptance bench: the form, and the results of the committed settings once run."""
    s = _committed(cur)
    asked = st.session_state.pop("bench_asked", False)
    value, error = None, None
    try:
        value = bench_value(cur, s)
    except VPRInputError as exc:
        error = exc
    identity = None if value is None else _identity(value, cur, s)
    ran = identity is not None and st.session_state.get("bench_ran") == identity
    with st.expander("Acceptance bench: every acceptance rule on the same queries", expanded=ran or asked):
        st.caption("The acceptance rules of the paper, its follow-up and the field (per-place θ, per-query "
                   "threshold, graph matcher, SeqSLAM, top-1 distance, PA-ratio, SUE) on one similarity matrix, "
                   "decision by decision. Computed when you press **Run the bench** (Nordland: about 12 s).")
        controls(cur, s)
        if value is None:
            show_error(error, hint="Change the bench's database traversal or tolerance above.")
            return
        if not (ran or asked):
            return
        try:
            options = bench_options(s, value.dataset)
            report = cache.bench(value, cur.places, options)
        except VPRInputError as exc:
            st.session_state.pop("bench_ran", None)
            show_error(exc, hint=getattr(exc, "hint", None)
                       or "Change the bench's settings above, or group/step on the **Places** page.")
            return
        st.session_state["bench_ran"] = identity
        results(report, value)
        vary_section(cur, value, options, identity)
        curves(report, value)


def _column_config(share: int) -> dict:
    """Narrow columns with short headers (the definition in each one's help), so the table fits the page."""
    number = {"closed F1": (64, "F1 on the closed set (the whole database, genuine queries only), %"),
              "R@1": (52, "Recall@1 with rejection on the closed set, %"),
              "R@5": (52, "Recall@5 with rejection on the closed set, %"),
              "open F1": (96, f"F1 on the natural open set (the first {share}% of the database route), %"),
              "rejection": (72, f"distractors rejected on the natural open set (first {share}% of the route), %")}
    config: dict = {col: st.column_config.NumberColumn(f"open F1 ({share}%)" if col == "open F1" else col,
                                                       width=width, format="%.1f", help=help_)
                    for col, (width, help_) in number.items()}
    config.update({
        "key": None,  # the rule's name in JSON and the CLI: in the data, not shown
        "rule": st.column_config.TextColumn("rule", width=190, help="† τ at the best F1 on these queries (oracle)"),
        "source": st.column_config.TextColumn("source", width=140, help="where the rule comes from"),
        "AUC-PR": st.column_config.NumberColumn("AUC-PR", width=64, format="%.3f",
                                                help="area under the closed set's precision–recall curve"),
        "τ": st.column_config.NumberColumn("τ", width=56, format="%.4g",
                                           help="the τ a rule with a free τ ran at (none: the rule's own thresholds)"),
        "τ from": st.column_config.TextColumn("τ from", width=150, help="where τ came from"),
    })
    return config


def results(report: AcceptanceReport, value: cache.Loaded) -> None:
    """The table and the rules left out of one report."""
    ds = value.dataset
    share = round(100 * report.settings["reference_share"])
    places = PLACE_LABELS[report.settings["places"]]
    if report.settings["places"] == PlaceSource.GROUP_STEP:
        places += f" ({report.settings.get('group/step', '')})"
    sides = "" if ds.aligned is None else (f" ({ds.traversals[int(ds.query_traversal[0])]} against "
                                           f"{' + '.join(ds.traversals[int(t)] for t in pd.unique(ds.database_traversal))})")
    st.markdown(f"**{ds.name}**: {ds.n_queries:,} queries × {ds.n_database:,} database images{sides} · ground "
                f"truth: {ds.ground_truth.description} · places: {places}, {report.closed.n_places:,} of them · "
                f"place score: {report.settings['place_score']} · descriptor: {report.settings.get('descriptor')}")
    st.dataframe(pd.DataFrame(bench_plots.bench_rows(report)), hide_index=True, width="stretch",
                 column_config=_column_config(share), key="bench_table", placeholder="—")
    st.caption(BENCH_CAPTION)
    if report.natural is not None:
        n = report.natural
        st.caption(f"Natural open set: the first {share}% of the database route; {int((n.genuine & n.counted).sum()):,} "
                   f"genuine queries, {int((~n.genuine & n.counted).sum()):,} distractors.")
    else:
        st.caption(f"Natural open set not run: {report.natural_note}")
    left = bench_plots.left_out_rows(report)
    if left:
        st.markdown("**Rules left out**\n\n" + "\n".join(f"- **{r['rule']}** ({r['where']}): {r['reason']}"
                                                          for r in left))
    said = tuple(f"{key}: τ = " for key in report.closed.decisions)  # τ is in the table already
    for note in report.notes:
        if " left out: " not in note and not note.startswith(said):
            st.caption(f"note: {note}")
    st.download_button("Download the bench (JSON)", json.dumps(report.to_dict(), indent=1, allow_nan=False),
                       file_name=f"acceptance-{ds.name}.json", mime="application/json", key="w_bench_json")


def curves(report: AcceptanceReport, value: cache.Loaded) -> None:
    """Every rule's precision–recall figure of one report, and VPR_Tutorial's on the same value."""
    share = round(100 * report.settings["reference_share"])
    sets = ["closed"] + (["natural"] if report.natural is not None else [])
    if st.session_state.get("w_bench_set") not in sets:
        st.session_state["w_bench_set"] = "closed"
    which = st.radio("precision–recall of", sets, horizontal=True, key="w_bench_set",
                     format_func=lambda k: bench_plots.SETS[k] + (f" (first {share}% of the route)"
                                                                  if k == "natural" else ""))
    bench = report.natural if which == "natural" else report.closed
    title = (f"Every rule's precision–recall, natural open set (first {share}% of the route)" if which == "natural"
             else "Every rule's precision–recall, closed set")
    st.plotly_chart(bench_plots.bench_pr_figure(bench, title=title), key="bench_pr", width="stretch")
    st.caption("Circles: each rule's own decisions (for a rule with a free τ, at the τ of the table). Each curve "
               "sweeps the rule's own free parameter (θ, k, c or τ). The per-place rules' curves count a right "
               "place, their circles a right image, so a circle may sit off its curve.")
    try:
        curves = tutorial_curves(value)
    except VPRInputError as exc:
        show_error(exc)
        return
    soft = curves["multi"].soft_ignored
    st.plotly_chart(bench_plots.tutorial_pr_figure(curves, title="VPR_Tutorial's precision–recall (createPR)"),
                    key="bench_tutorial_pr", width="stretch")
    st.caption("VPR_Tutorial's own counting (`evaluation/metrics.py`), on every query and the whole database: "
               "**single-best-match** takes each query's best database image as its one detection; **multi-match** "
               "counts every query–database pair. "
               + ("The ground truth has soft positives: the multi-match curve ignores them as the tutorial does "
                  "(their scores lowered to min S); the single curve counts hard positives only, as VPR_Tutorial "
                  "refuses soft positives with single matching." if soft else
                  "This ground truth has no soft positives: both curves count hard positives only."))


# --------------------------------------------------------------------------- vary one parameter


def place_spec(places: RetrievalPlaces) -> PlaceSpec | MetricPlaceSpec | None:
    """The group/step spec whose group or step a sweep varies: metres where the places are, else frames (``None``
    for the layout's own places)."""
    return places.metric if places.metric is not None else places.spec


def bench_labels(ds: RetrievalDataset, places: RetrievalPlaces) -> np.ndarray:
    """``(n_database,)`` place of each database image, as ``cache.bench`` gives the bench: the layout's own ids
    where it has them, else group/step (``-1`` between places).

    Raises:
        VPRInputError: group/step that make no places (``retrieval_places``).
    """
    if ds.database_place is not None:
        return ds.database_place
    return retrieval_places(ds, places.spec, places.metric)[0]


def offered_parameters(ds: RetrievalDataset, options: BenchOptions, labels: np.ndarray | None,
                       places: PlaceSpec | MetricPlaceSpec | None) -> tuple[list[Parameter], dict[Parameter, str]]:
    """The parameters the bench on ``ds`` reads (``Parameter`` order), and each other one with why not
    (``acceptance_sweep.check_parameter``'s refusal)."""
    offered, refused = [], {}
    for p in Parameter:
        try:
            check_parameter(ds, p.value, options, labels=labels, places=places)
        except VPRInputError as exc:
            refused[p] = str(exc)
        else:
            offered.append(p)
    return offered, refused


def _spread(centre: int | float, whole: bool) -> list[int | float]:
    """Half, the value itself and double (half at least 1 frame for whole numbers)."""
    half = max(1, int(centre) // 2) if whole else centre / 2
    return sorted({half, centre, 2 * centre})


def default_values(parameter: Parameter, places: PlaceSpec | MetricPlaceSpec | None) -> tuple[int | float, ...]:
    """The values box's first values: ``DEFAULT_VALUES``; group/step: half, the sidebar's value and double, kept
    where the stride reading's places would not overlap (group ≤ step)."""
    if parameter not in (Parameter.GROUP, Parameter.STEP):
        return DEFAULT_VALUES[parameter]
    if places is None:
        return ()
    whole = isinstance(places, PlaceSpec)
    stride = places.reading is Reading.STRIDE
    if parameter is Parameter.GROUP:
        return tuple(v for v in _spread(places.group, whole) if not stride or v <= places.step)
    return tuple(v for v in _spread(places.step, whole) if not stride or v >= places.group)


def values_text(values: tuple[int | float, ...]) -> str:
    """Values as the box shows them, e.g. ``"4, 6, 10, 20"``."""
    return ", ".join(f"{v:g}" for v in values)


def parse_values(parameter: Parameter, text: str, places: PlaceSpec | MetricPlaceSpec | None = None,
                 ) -> tuple[int | float, ...]:
    """The values box as numbers: whole numbers for ``WHOLE`` and group/step in frames, a fraction for
    ``reference_share``, metres (a whole number where it is one) for group/step of ``MetricPlaceSpec``.
    Empty items (``"4,,6"``, a trailing comma) are skipped; the library checks the values themselves.

    Raises:
        VPRInputError: no value, or an item that is not a number of the parameter's kind.
    """
    example = values_text(default_values(parameter, places)) or "1, 2"
    items = [item.strip() for item in str(text).split(",") if item.strip()]
    if not items:
        raise VPRInputError(f"{parameter} values: none given; write them comma-separated, e.g. {example}")
    whole = parameter in WHOLE or (parameter in (Parameter.GROUP, Parameter.STEP)
                                   and not isinstance(places, MetricPlaceSpec))
    out: list[int | float] = []
    for item in items:
        try:
            number = float(item)
        except ValueError:
            number = math.nan
        if whole and not (math.isfinite(number) and number.is_integer()):
            raise VPRInputError(f"{parameter} values {text!r}: {item!r} is not a whole number; write whole numbers "
                                f"comma-separated, e.g. {example}")
        if not math.isfinite(number):
            raise VPRInputError(f"{parameter} values {text!r}: {item!r} is not a number; write numbers "
                                f"comma-separated, e.g. {example}")
        metres_whole = isinstance(places, MetricPlaceSpec) and number.is_integer()
        out.append(int(number) if whole or metres_whole else number)
    return tuple(out)


# the rules that read the parameter once per value, the others once (Nordland: 14 s for ds=4,6,10,20)
@st.cache_resource(show_spinner=False, max_entries=8)
def _sweep(key: str, places: tuple, options: tuple, parameter: str, values: tuple, _data: cache.Loaded,
           _places: RetrievalPlaces, _options: BenchOptions) -> BenchSweep:
    ds = _data.dataset
    return sweep_bench(ds, _data.descriptors, labels=bench_labels(ds, _places), parameter=parameter, values=values,
                       options=_options, places=place_spec(_places),
                       settings={"descriptor": _data.descriptor, "group/step": _places.describe(ds)})


def bench_sweep(value: cache.Loaded, places: RetrievalPlaces, options: BenchOptions, parameter: Parameter | str,
                values: tuple[int | float, ...]) -> BenchSweep:
    """The bench of ``cache.bench(value, places, options)`` at each value of one parameter (cached).

    Raises:
        VPRInputError: as ``acceptance_sweep.sweep_bench`` (a parameter the bench does not read, a value
            it refuses).
    """
    p = Parameter(parameter)
    with st.spinner(f"Varying {p} over {len(values)} value{'s' * (len(values) != 1)}: the rules that read it run "
                    "once per value (Nordland: 4–8 s a value)…"):
        return _sweep(value.key, cache.places_key(places), cache.options_key(options), p.value, tuple(values), value,
                      places, options)


def _new_parameter(places: PlaceSpec | MetricPlaceSpec | None) -> None:
    """Another parameter picked: the values box starts again from its defaults."""
    p = Parameter(st.session_state["w_vary_parameter"])
    st.session_state["w_vary_values"] = values_text(default_values(p, places))


def _commit_vary(identity: tuple) -> None:
    """**Vary**: the picked parameter and the box's text are run on the bench shown (``identity``)."""
    ss = st.session_state
    ss["vary_settings"] = (identity, ss["w_vary_parameter"], ss["w_vary_values"])


def vary_section(cur: Current, value: cache.Loaded, options: BenchOptions, identity: tuple) -> None:
    """The bench varied over one parameter: picker, values, **Vary**, then the figure, the table and the CSV."""
    st.markdown("**Vary one parameter**")
    st.caption("The bench once per value of one parameter, every other setting as above (`vpr-explorer acceptance "
               "--vary`): the rules that read it run again at each value, the others once. Computed when you press "
               "**Vary** (Nordland: 4–8 s a value).")
    ds = value.dataset
    spec = place_spec(cur.places)
    try:
        labels = bench_labels(ds, cur.places)
    except VPRInputError:  # the bench above ran on these places; without them its per-place rules are left out
        labels = None
    offered, refused = offered_parameters(ds, options, labels, spec)
    if refused:
        st.markdown("**Not offered here**\n\n" + "\n".join(f"- **{p}**: {why}" for p, why in refused.items()))
    if not offered:
        st.info("The bench on this value reads none of the parameters a sweep varies.", icon=":material/info:")
        return
    ss = st.session_state
    names = [p.value for p in offered]
    if ss.get("w_vary_parameter") not in names:
        ss["w_vary_parameter"] = names[0]
        ss["w_vary_values"] = values_text(default_values(offered[0], spec))
    elif "w_vary_values" not in ss:
        ss["w_vary_values"] = values_text(default_values(Parameter(ss["w_vary_parameter"]), spec))
    c = st.columns([2, 3, 1], vertical_alignment="bottom")
    c[0].selectbox("parameter", names, key="w_vary_parameter", on_change=_new_parameter, args=(spec,),
                   format_func=lambda name: f"{name}: {DESCRIPTIONS[Parameter(name)]}",
                   help="Only the parameters the bench on this value reads; the others are listed above with why.")
    c[1].text_input("values (comma-separated)", key="w_vary_values",
                    help="Whole numbers; reference_share as a fraction of the route (0.5, 0.7); group and step in "
                         "the places' unit (frames, or metres). Each value is checked as the bench checks it.")
    c[2].button("Vary", key="w_vary_run", on_click=_commit_vary, args=(identity,), width="stretch")

    committed = ss.get("vary_settings")
    if committed is None or committed[0] != identity:
        return
    _, name, text = committed
    try:
        parameter = Parameter(name)
        sweep = bench_sweep(value, cur.places, options, parameter, parse_values(parameter, text, spec))
    except VPRInputError as exc:
        show_error(exc, hint="Change the values or the parameter and press **Vary** again.")
        return
    sweep_results(sweep, value)


def _sweep_column_config(sweep: BenchSweep, metric: str) -> dict:
    what = bench_plots.SWEEP_METRICS[metric]
    p = sweep.parameter
    config: dict = {
        "key": None,
        "rule": st.column_config.TextColumn("rule", width=190, help="† τ at the best F1 on these queries (oracle), "
                                                                  "at each value"),
        "reads": st.column_config.CheckboxColumn(f"reads {p}", width=80,
                                                 help=f"the rule's {what} moves with {p} (run again at each value)"),
    }
    for v in sweep.values:
        label = bench_plots.value_label(p, v)
        config[label] = st.column_config.NumberColumn(label, width=72, format="%.1f", help=f"{what} at {label}, %")
    return config


def _left_out_lines(sweep: BenchSweep) -> list[str]:
    """A rule run again at each value and left out at every one, once; one left out at some values, per value
    (closed set). The rules run once are the bench's own: its list above says why they are left out."""
    out = []
    for r in RULES:
        if r.key not in sweep.recomputed:
            continue
        whys = [pt.closed.left_out.get(r.key, "") for pt in sweep.points]
        if all(whys) and len(set(whys)) == 1:
            out.append(f"- **{r.label}**: {whys[0]}")
        else:
            out += [f"- **{r.label}** at {bench_plots.value_label(sweep.parameter, v)}: {why}"
                    for v, why in zip(sweep.values, whys) if why]
    return out


def sweep_results(sweep: BenchSweep, value: cache.Loaded) -> None:
    """One metric of a sweep as a figure and a table (a radio picks it), the rules left out, the CSV, the text."""
    ss = st.session_state
    p = sweep.parameter
    ds = value.dataset
    metrics = ["closed"] + (["open", "rejection"] if any(pt.natural is not None for pt in sweep.points) else [])
    if ss.get("w_vary_metric") not in metrics:
        ss["w_vary_metric"] = "closed"
    metric = st.radio("metric", metrics, format_func=bench_plots.SWEEP_METRICS.get, horizontal=True,
                      key="w_vary_metric")
    what = bench_plots.SWEEP_METRICS[metric]
    fig = bench_plots.sweep_figure(sweep, metric, title=f"{ds.name}: {what} of every rule as {p} varies")
    st.plotly_chart(fig, key="bench_sweep", width="stretch")
    if metric == "closed" and p is Parameter.REFERENCE_SHARE:
        st.caption("reference_share cuts the natural open set only: no rule's closed-set F1 moves with it, so every "
                   "line is faint here; pick the open-set F1 or rejection.")
    else:
        readers = ", ".join(RULES_BY_KEY[k].label for k in sweep.recomputed)
        st.caption(f"Solid: the rules that read {p} ({DESCRIPTIONS[p]}), run again at each value: {readers}. Faint "
                   f"and dashed: the rules that do not read it, run once; their numbers stand the same at every "
                   "value. A gap: the rule did not run at that value (see below).")
    st.dataframe(pd.DataFrame(bench_plots.sweep_table(sweep, metric)), hide_index=True, width="stretch",
                 column_config=_sweep_column_config(sweep, metric), key="bench_sweep_table", placeholder="—")
    left = _left_out_lines(sweep)
    if left:
        st.markdown("**Left out in the sweep**\n\n" + "\n".join(left))
    notes = list(dict.fromkeys(pt.natural_note for pt in sweep.points if pt.natural is None and pt.natural_note))
    if notes:
        st.caption("Natural open set not run: " + "; ".join(notes))
    csv = pd.DataFrame(bench_plots.sweep_rows(sweep)).to_csv(index=False)
    st.download_button("Download the sweep (CSV)", csv, file_name=f"acceptance-{ds.name}-{p}.csv", mime="text/csv",
                       key="w_vary_csv")
    with st.expander("The sweep as `vpr-explorer acceptance --vary` prints it"):
        st.code(render(sweep), language=None)


def soft_matrix(ds: RetrievalDataset) -> np.ndarray | None:
    """``(n_queries, n_database)`` bool soft positives, or ``None`` where the ground truth has none."""
    gt = ds.ground_truth
    if gt.soft_indptr is None:
        return None
    out = np.zeros((gt.n_queries, gt.n_database), dtype=bool)
    out[np.repeat(np.arange(gt.n_queries), np.diff(gt.soft_indptr)), gt.soft_indices] = True
    return out


# the whole similarity matrix (up to the bench's BENCH_PAIRS): once per value, not on every rerun
@st.cache_resource(show_spinner="Counting VPR_Tutorial's precision–recall…", max_entries=4)
def _tutorial(key: str, _data: cache.Loaded) -> dict[str, TutorialPR]:
    ds, d = _data.dataset, _data.descriptors
    s = similarity(d[ds.n_database:], d[:ds.n_database])
    hard = ds.ground_truth.dense()
    return {"single": tutorial_pr(s, hard, matching=Matching.SINGLE),
            "multi": tutorial_pr(s, hard, soft_matrix(ds), matching=Matching.MULTI)}


def tutorial_curves(value: cache.Loaded) -> dict[str, TutorialPR]:
    """VPR_Tutorial's single- and multi-match curves of a value (module doc)."""
    return _tutorial(value.key, value)


# --------------------------------------------------------------------------- discovered places (Places page)


@st.cache_resource(show_spinner="Discovering places along the route…", max_entries=8)
def _discovery(key: str, _descriptors: np.ndarray) -> Discovery:
    return discover(_descriptors)


def discovery_value(cur: Current) -> tuple[cache.Loaded | None, str]:
    """The value whose database discovery reads (one route in order), or ``None`` and why not."""
    choices = cur.database
    if cur.aligned is not None and len(choices) > 1:
        traversal = st.selectbox("traversal the places are discovered on", list(choices), key="w_discovery_traversal",
                                 help="Discovery reads one route in order; group/step places are the same frames in "
                                      "every traversal.")
        return cache.value(cur.source, cur.query, database=(traversal,)), ""
    why = route_problem(cur.dataset)
    return (cur.data, "") if why is None else (None, why)


def _sizes(place: np.ndarray, n: int) -> str:
    sizes = np.bincount(place[place >= 0], minlength=n)
    if not len(sizes):
        return "no place"
    spread = f"{sizes.min()}" if sizes.min() == sizes.max() else f"{sizes.min()}–{sizes.max()} (median {np.median(sizes):g})"
    return f"{n} places of {spread} images"


def discovery_section(cur: Current) -> None:
    """Discovered places beside group/step along the route, the online score against θ, counts and sizes."""
    st.subheader("Discovered places beside group/step")
    st.caption(f"Places cut online from the database stream in route order (the authors' follow-up; α = {ALPHA:g}, "
               f"m = {MIN_SIZE}, h = {HYSTERESIS}): a frame stays in the current place while its mean similarity to "
               "the place is above θ = μ⁻ + n·σ⁻; h frames in a row at or below θ open a new place. The acceptance "
               "bench on the **Evaluation** page can use them instead of group/step.")
    value, why = discovery_value(cur)
    if value is None:
        st.info(f"No discovered places here: {why}. Discovery reads the database as one route in order: open aligned "
                "traversals, a traversal-positions layout with one database traversal, or VPR-Bench.",
                icon=":material/info:")
        return
    ds = value.dataset
    if ds.n_database > DISCOVERY_FRAMES:
        st.info(f"{ds.n_database:,} database images: discovery runs one frame at a time, so the Places page does not "
                f"run it past {DISCOVERY_FRAMES:,}.", icon=":material/timer:")
        return
    try:
        found = _discovery(value.key, value.descriptors[:ds.n_database])
    except VPRInputError as exc:
        show_error(exc)
        return
    try:
        labels, n_group = retrieval_places(ds, cur.places.spec, cur.places.metric)
        group = f"{_sizes(labels, n_group)}, {int((labels < 0).sum()):,} of {ds.n_database:,} images in no place"
    except VPRInputError as exc:  # the page's own error says where to fix it: a caption here, not a second error
        labels, group = np.full(ds.n_database, -1), f"no places ({exc})"
    db = " + ".join(ds.traversals[int(t)] for t in pd.unique(ds.database_traversal))
    fig = bench_plots.discovery_figure(labels, found, title=f"{db}: {ds.n_database:,} database images in route order")
    st.plotly_chart(fig, key="discovery", width="stretch")
    trailing = int((found.place < 0).sum())
    online = (f"bootstrap on frames 0–{found.online_from - 1}, online from frame {found.online_from}"
              if found.online_from < ds.n_database else "the whole route in the bootstrap (no online phase)")
    st.caption(f"**group/step** ({cur.places.describe(ds)}): {group} · **discovered**: "
               f"{_sizes(found.place, found.n_places)}, {trailing} trailing image{'s' * (trailing != 1)} still "
               f"pending at the end (in no place); {online}. Black ticks: where a place starts.")
