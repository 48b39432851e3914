"""Evaluation page: the paper, traversal and open-set protocols; Recall@K, precision–recall, the trade-off,
runs side by side, the similarity matrix.

Every setting of the page lives in the URL beside the view (``eval_protocol``, ``eval_runs``,
``eval_seed``, ``eval_cross``, ``eval_share``, ``eval_database``, ``eval_query``,
``eval_tolerance``, ``eval_pr``, ``eval_rule``): a link reopens the same settings, and a
bad value is refused with a warning naming it and what is used instead. The settings the
form shows are the ones the results were computed with: the form is drawn from the
committed settings on every run (they are committed only by **Run**), and the results are
looked up from them, so leaving the page and coming back can never show one protocol's
controls above another's results. The page draws its controls first and computes after,
with a progress bar.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import pandas as pd  # before plotly: plotly.py#2433
import streamlit as st

from vpr_explorer.views import plots
from vpr_explorer.method.auto_theta import auto_parts, rejects_all_note
from vpr_explorer.errors import VPRInputError
from vpr_explorer.protocols.evaluation import PROTOCOL_LABELS, Protocol
from vpr_explorer.method.places import make_places
from vpr_explorer.views.report import method_csv
from vpr_explorer.views.traversal import AUTO_RUN_PAIRS, evaluation_json, evaluation_rows, protocol_pairs

from vpr_explorer.app.ui import cache, runs as runs_ui, state
from vpr_explorer.app.ui.current import current
from vpr_explorer.app.ui.feedback import PLACES_HINT, show_error, stop_on_input_error
from vpr_explorer.app.ui.routing import ensure_routed, page_file

ensure_routed(__file__)

INSPECTOR = page_file("inspector")

#: Precision–recall of the per-place methods scores every query against every place at each
#: of ~200 k: on by default up to this many query × place cells (GardensPoint: 8·10³; the
#: Nordland traversal protocol, 1.3·10⁶, waits for a tick and Run).
PR_AUTO_CELLS = 1_000_000
RUNS_RANGE = (1, 50)
SEED_RANGE = (0, 10_000)
SHARE_RANGE = (0.1, 0.6)
TOLERANCE_RANGE = (0, 20)
PROTOCOLS = (Protocol.PAPER.value, Protocol.TRAVERSAL.value, Protocol.OPEN_SET.value)

if st.session_state.pop("goto_inspector", False):
    st.switch_page(INSPECTOR)

st.title("Evaluation")
with stop_on_input_error():
    cur = current()
    if cur.retrieval is not None:  # a database/queries layout: its own protocol (ui.retrieval_eval)
        from vpr_explorer.app.ui import retrieval_eval
        retrieval_eval.render(cur)
        st.stop()
ds = cur.data.dataset
v = state.view()


# --------------------------------------------------------------------------- settings (URL ⇄ form)


@dataclass(frozen=True)
class EvalSettings:
    """Every setting of the page; ``database``/``query`` ``None``: the Places page's traversals."""

    protocol: str = Protocol.PAPER.value
    runs: int = 20
    seed: int = 0
    cross: bool = False
    share: float = 0.3
    database: tuple[str, ...] | None = None
    query: str | None = None
    tolerance: int = 0
    pr: str = "auto"  # "auto": on when cheap (PR_AUTO_CELLS); "on"; "off"
    rule: str = "margin"


_PARAMS = {"protocol": "eval_protocol", "runs": "eval_runs", "seed": "eval_seed", "cross": "eval_cross",
           "share": "eval_share", "database": "eval_database", "query": "eval_query", "tolerance": "eval_tolerance",
           "pr": "eval_pr", "rule": "eval_rule"}
_DEFAULT = EvalSettings()


def _whole(text: str, low: int, high: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise ValueError("not a whole number") from None
    if not low <= value <= high:
        raise ValueError(f"outside {low} to {high}")
    return value


def _parse(field: str, text: str) -> object:
    """One ``eval_*`` value of a link; ``ValueError`` saying why it cannot be used."""
    if field == "protocol":
        if text not in PROTOCOLS:
            raise ValueError(f"choose {', '.join(PROTOCOLS)}")
        return text
    if field == "runs":
        return _whole(text, *RUNS_RANGE)
    if field == "seed":
        return _whole(text, *SEED_RANGE)
    if field == "tolerance":
        return _whole(text, *TOLERANCE_RANGE)
    if field == "cross":
        if text.lower() not in ("true", "false", "1", "0"):
            raise ValueError("choose true or false")
        return text.lower() in ("true", "1")
    if field == "share":
        try:
            value = float(text)
        except ValueError:
            raise ValueError("not a number") from None
        if not (math.isfinite(value) and SHARE_RANGE[0] <= value <= SHARE_RANGE[1]):
            raise ValueError(f"outside {SHARE_RANGE[0]:g} to {SHARE_RANGE[1]:g}")
        return round(value, 2)
    if field == "database":
        names = tuple(t for t in text.split("+") if t)
        missing = [t for t in names if t not in ds.traversals]
        if not names or missing:
            raise ValueError(f"{'no traversal named' if not names else 'not a traversal of ' + ds.name}: "
                             f"{', '.join(missing) or text!r}; choose among {', '.join(ds.traversals)} joined by +")
        return names
    if field == "query":
        if text not in ds.traversals:
            raise ValueError(f"not a traversal of {ds.name}; choose one of {', '.join(ds.traversals)}")
        return text
    if field == "pr":
        if text not in ("auto", "on", "off"):
            raise ValueError("choose on, off or auto")
        return text
    if field == "rule":
        if text not in ("margin", "raw"):
            raise ValueError("choose margin or raw")
        return text
    raise ValueError("unknown setting")


def _instead(field: str) -> str:
    if field == "database":
        return f"the Places page's database traversals ({' + '.join(cur.database)})"
    if field == "query":
        return f"the Places page's query traversal ({cur.query})"
    value = getattr(_DEFAULT, field)
    return f"the default ({'on when cheap' if field == 'pr' else value})"


def settings_from_params(params: dict[str, str]) -> tuple[EvalSettings, list[str]]:
    """Settings from a link's ``eval_*`` parameters, and a warning for each one refused."""
    values, refused = {}, []
    for field, name in _PARAMS.items():
        if name in params:
            try:
                values[field] = _parse(field, params[name])
            except ValueError as exc:
                refused.append(f"{name}={params[name]!r}: {exc}; using {_instead(field)}")
    return EvalSettings(**values), refused


def _valid_here(s: EvalSettings) -> tuple[EvalSettings, list[str]]:
    """Settings whose traversals this dataset has (another dataset may have been opened since)."""
    notes = []
    if s.database is not None and any(t not in ds.traversals for t in s.database):
        notes.append(f"database traversals {' + '.join(s.database)} are not all in {ds.name}; "
                     f"using {_instead('database')}")
        s = replace(s, database=None)
    if s.query is not None and s.query not in ds.traversals:
        notes.append(f"query traversal {s.query!r} is not in {ds.name}; using {_instead('query')}")
        s = replace(s, query=None)
    return s, notes


def committed() -> EvalSettings:
    """The page's settings: from the link on a session's first run, then what **Run** committed."""
    if "eval_settings" not in st.session_state:
        s, refused = settings_from_params(state.page_params())
        st.session_state["eval_settings"] = s
        if refused:
            st.session_state["eval_refused"] = refused
    s, notes = _valid_here(st.session_state["eval_settings"])
    st.session_state["eval_settings"] = s
    st.session_state.setdefault("eval_refused", [])
    st.session_state["eval_refused"] = [*st.session_state["eval_refused"], *notes]
    return s


def to_url(s: EvalSettings) -> None:
    """Every setting into the address bar (``state.sync_url`` writes it)."""
    state.set_page_params(**{name: _text(getattr(s, field)) for field, name in _PARAMS.items()})


def _text(value: object) -> str | None:
    if value is None:
        return None
    if isinstance(value, tuple):
        return "+".join(value)
    if isinstance(value, bool):
        return str(value).lower()
    return str(value)


def _commit() -> None:
    """The form's **Run**: its widgets become the committed settings (and the URL)."""
    ss = st.session_state
    database = tuple(ss["w_database"])
    s = EvalSettings(protocol=ss["w_protocol"], runs=int(ss["w_runs"]), seed=int(ss["w_seed"]),
                     cross=bool(ss["w_cross"]), share=round(float(ss["w_share"]), 2),
                     database=None if database == tuple(cur.database) else database,
                     query=None if ss["w_eval_query"] == cur.query else ss["w_eval_query"],
                     tolerance=int(ss["w_tolerance"]), pr=ss["w_pr"], rule=ss["eval_settings"].rule)
    ss["eval_settings"] = s
    ss["eval_submitted"] = True
    to_url(s)


def _commit_rule() -> None:
    s = replace(st.session_state["eval_settings"], rule=st.session_state["w_rule"])
    st.session_state["eval_settings"] = s
    to_url(s)


settings = committed()
to_url(settings)
for message in st.session_state.pop("eval_refused", []):
    st.warning(message, icon=":material/link_off:")
submitted = st.session_state.pop("eval_submitted", False)
database = settings.database or tuple(cur.database)
query = settings.query or cur.query

# The widgets show the committed settings, every run (a widget's own state is dropped while
# another page is shown, and a form's unsent edits are not settings).
for key, value in (("w_protocol", settings.protocol), ("w_runs", settings.runs), ("w_seed", settings.seed),
                   ("w_cross", settings.cross), ("w_share", settings.share), ("w_database", list(database)),
                   ("w_eval_query", query), ("w_tolerance", settings.tolerance), ("w_pr", settings.pr),
                   ("w_rule", settings.rule)):
    st.session_state[key] = value

with st.form("protocol_form"):
    st.radio("Protocol", PROTOCOLS, format_func=lambda p: PROTOCOL_LABELS[Protocol(p)], key="w_protocol")
    c = st.columns(4)
    c[0].slider("runs (paper: 50)", *RUNS_RANGE, key="w_runs",
                help="How many seeded random splits the paper and open-set protocols average over (mean ± std).")
    c[1].number_input("seed", *SEED_RANGE, key="w_seed",
                      help="Seeds the random splits: the same seed draws the same query images.")
    c[2].checkbox("cross-condition", key="w_cross",
                  help="Score each query only against database images of other traversals, so that a query "
                       "cannot be matched by its own traversal's neighbouring frames.")
    c[3].slider("unknown share (open set)", *SHARE_RANGE, step=0.05, key="w_share",
                help="The share of places held out of the database in each open-set split: their queries must "
                     "be rejected.")
    c = st.columns(4)
    c[0].multiselect("database traversals (traversal protocol)", list(ds.traversals), key="w_database")
    c[1].selectbox("query traversal (traversal protocol)", list(ds.traversals), key="w_eval_query")
    c[2].number_input("tolerance ± frames", *TOLERANCE_RANGE, key="w_tolerance",
                      help="A place holding a frame within this many frames of the query's is right too "
                           "(the authors count ±2); 0: only the query's own place.")
    c[3].selectbox("precision–recall", ["auto", "on", "off"], key="w_pr",
                   format_func={"auto": "on when quick", "on": "on", "off": "off"}.get,
                   help="PR curves, AUC, R@100P, R@99P and max F1. The per-place curves score every query "
                        "against every place at ~200 values of k: 'on when quick' leaves them off on large datasets.")
    st.form_submit_button("Run", type="primary", on_click=_commit)

with stop_on_input_error(hint=PLACES_HINT):
    places = make_places(ds, cur.spec)
protocol = settings.protocol
runs = 1 if protocol == Protocol.TRAVERSAL else settings.runs
cells = (ds.n_frames * places.n_places if protocol == Protocol.TRAVERSAL else runs * places.n_places ** 2)
with_pr = settings.pr == "on" or (settings.pr == "auto" and cells <= PR_AUTO_CELLS)
options = {"user_theta": v.theta, "tolerance": settings.tolerance, "pr": with_pr}
if protocol == Protocol.TRAVERSAL:
    options.update(database=list(database), queries=query)
else:
    options.update(runs=settings.runs, seed=settings.seed, cross_condition=settings.cross)
    if protocol == Protocol.OPEN_SET:
        options["unknown_share"] = settings.share
cost = protocol_pairs(protocol, places, ds, runs=settings.runs, database=database, unknown_share=settings.share)

results_box = st.container()  # filled last: the controls and the page show before anything is computed
runs_box = st.container()
st.subheader("Similarity matrix: click a cell to open that query in the inspector")
grid_box = st.container()


# --------------------------------------------------------------------------- results


PR_CAPTION = (
    "**How the curves count** (the field's single-best-match rule, VPR_Tutorial's `createPR`): the threshold sweeps "
    "(one global θ over the top scores; for the per-place methods the family θ_p(k) = θ_p + k·s_p over k) and each "
    "query's top-1 answer is accepted or rejected. An accepted query whose top-1 is right is a **true positive**; "
    "an accepted wrong top-1 is a **false positive**; an accepted query of an **unknown place** (no true match in "
    "the database) is a **false positive** too. Recall = TP / queries with a true match; precision = TP / "
    "accepted (1 when nothing is accepted). AUC: trapezoids over recall; R@100P / R@99P: the largest recall at "
    "precision 100% / ≥ 99%; max F1: the best 2PR/(P+R). Circles: each method at its own θ (k = 0 for θ_p). "
    "Runs are pooled (one θ or k for every run, each run with its own training thresholds)."
)


#: What a cell with nothing to count shows (Streamlit's default is "None").
MISSING = "—"


def _column_config(table: pd.DataFrame, one_run: bool) -> dict:
    """Narrow numeric columns with short headers (the definition in each one's help), so the widest table (open
    set) fits a laptop's page without hiding its last column; no ± columns for a one-run protocol."""
    helps = {"accepted": "share of queries given an answer (not rejected), %",
             "precision": "share of accepted top-1 answers that are right, %",
             "unknown rejected": "share of unknown-place queries rejected, %",
             "top-1 from own traversal": "share of accepted top-1 answers from the query's own traversal, %"}
    config: dict = {"method": st.column_config.TextColumn("method", width=170),
                    "source": st.column_config.TextColumn("source", width=100, help="where the method comes from")}
    short = {"unknown rejected": "unknown rej.", "top-1 from own traversal": "own trav."}
    for col in table.columns:
        if col in config:
            continue
        if col.endswith(" ±"):
            k = col[:-2]
            config[col] = None if one_run else st.column_config.NumberColumn(
                "±", width=44, format="%.1f", help=f"{k}: standard deviation over the runs, points")
        elif col.startswith("R@"):
            config[col] = st.column_config.NumberColumn(col, width=52, format="%.1f",
                                                        help=f"Recall@{col[2:]}, %: a query is right when a right "
                                                             f"place is among its first {col[2:]} answers")
        else:
            config[col] = st.column_config.NumberColumn(short.get(col, col), width=84 if col == "unknown rejected"
                                                        else 64, format="%.1f", help=helps.get(col, col))
    return config


def show_auto_note(ev) -> None:
    """Say why the automatic global θ accepts nothing, beside the table that shows its 0% recall."""
    auto = next((r for r in ev.rows if r.key == "global-auto"), None)
    if auto is None or auto.accepted[0] > 0:
        return
    if ev.protocol is Protocol.TRAVERSAL:
        db = [ds.traversal_index(t) for t in database]
        rows = [i for i in range(ds.n_images) if ds.image_traversal[i] in db and places.image_place[i] >= 0]
        over, seed = f"the database images ({' + '.join(database)})", 0
    else:
        rows = [i for i in range(ds.n_images) if places.image_place[i] >= 0]
        over, seed = "all place images (each run's training images: all but its queries)", settings.seed
    parts = auto_parts(cur.data.descriptors[rows], seed=seed)
    note = rejects_all_note(parts, over=over)
    if note is None:  # θ ≤ 1 but above every query's top score
        note = (f"**global θ, automatic = {parts.theta:.3f}** (median {parts.median:.3f}, MAD {parts.mad:.3f} of "
                f"the training similarities) is above every query's top score here, so it accepts no query.")
    st.warning(note, icon=":material/block:")


def show_pr(ev) -> None:
    st.subheader("Precision–recall")
    if not with_pr:
        st.caption(f"Off: {cells:,} query × place cells per sweep point make the per-place curves slow here. Choose "
                   "**precision–recall: on** above and press **Run** (or `vpr-explorer evaluate --pr`).")
        return
    st.caption(PR_CAPTION)
    rows = []
    for r in ev.pr:
        rows.append({"method": r.label, "curve": r.curve, "AUC": r.auc, "R@100P": 100 * r.r_at_100p,
                     "R@99P": 100 * r.r_at_99p, "max F1": r.max_f1, "at θ or k": r.max_f1_at,
                     "own P": 100 * r.own.precision if r.own.accepted else math.nan,
                     "own R": 100 * r.own.recall, "with a true match": r.n_known, "no true match": r.n_unknown})
    if not rows:
        st.caption("No curve: " + " ".join(n for n in ev.notes if "precision" in n))
        return
    table = pd.DataFrame(rows)
    fmt = {"AUC": "{:.3f}", "max F1": "{:.3f}", "at θ or k": "{:+.3f}", "R@100P": "{:.1f}", "R@99P": "{:.1f}",
           "own P": "{:.1f}", "own R": "{:.1f}", "with a true match": "{:,}", "no true match": "{:,}"}
    st.dataframe(table.style.format(fmt, na_rep=MISSING), hide_index=True, key="pr_table", placeholder=MISSING,
                 column_config={
        "R@100P": st.column_config.NumberColumn("R@100P", help="recall at 100% precision, %"),
        "R@99P": st.column_config.NumberColumn("R@99P", help="recall at precision ≥ 99%, %"),
        "own P": st.column_config.NumberColumn("own P", help="precision at the method's own θ, %"),
        "own R": st.column_config.NumberColumn("own R", help="recall at the method's own θ, %"),
        "no true match": st.column_config.NumberColumn("no true match", help="queries of an unknown place, "
                                                       "summed over runs: each accepted one is a false positive"),
    })
    st.plotly_chart(plots.evaluation_pr_figure(ev), key="pr", width="stretch")
    left_out = [n for n in ev.notes if "precision–recall" in n and "left out" in n]
    for n in left_out:
        st.caption(f"note: {n}")


def show_results(ev) -> None:
    st.subheader(f"{PROTOCOL_LABELS[ev.protocol]}")
    shown = {k: val for k, val in ev.settings.items() if k not in ("k_grid", "group", "step", "reading") and val is not None}
    st.caption(", ".join(f"{k}: {val}" for k, val in shown.items()) + f" · {ev.seconds:.1f} s")
    for note in ev.notes:
        st.caption(f"note: {note}")
    st.caption("The image-level baseline ranks images (the authors' 'Baseline'); the place-level baseline ranks places "
               "with no threshold. The gap between them is the change of level, not the threshold. "
               "'—': nothing to count (e.g. the precision of a method that accepted no query).")
    table = pd.DataFrame(evaluation_rows(ev))
    one_run = not (isinstance(ev.settings.get("runs"), int) and ev.settings["runs"] > 1)
    st.dataframe(table, hide_index=True, key="results", width="stretch", placeholder=MISSING,
                 column_config=_column_config(table, one_run))
    show_auto_note(ev)
    st.plotly_chart(plots.recall_figure(ev), key="recall", width="stretch")
    d1, d2 = st.columns(2)
    stem = runs_ui.file_stem(ev)
    d1.download_button("Download CSV", method_csv(ev), file_name=f"{stem}.csv", mime="text/csv", key="w_csv")
    d2.download_button("Download JSON", evaluation_json(ev), file_name=f"{stem}.json", mime="application/json", key="w_json")

    if ev.protocol is Protocol.OPEN_SET:
        st.radio("filter rule of the θ_p(k) curves", ["margin", "raw"], horizontal=True, key="w_rule",
                 on_change=_commit_rule)
        st.plotly_chart(plots.tradeoff_figure(ev, settings.rule), key="tradeoff", width="stretch")
        st.caption("k = 0 (circled) is the paper: it sits near zero rejection, because θ_p lies in the centre of the "
                   "negative scores. Raising k trades known-place recall for rejection of unknown places; the grey "
                   "line is one global θ for every place, the stars its automatic and oracle values.")
    else:
        st.caption("Run the open-set protocol to see the trade-off between rejecting unknown places and Recall@1.")
    show_pr(ev)


with results_box:
    failed = False
    try:
        ev = cache.evaluation(cur.data, cur.spec, protocol, peek=True, **options)
        if ev is None and (submitted or (cost <= AUTO_RUN_PAIRS and (not with_pr or cells <= PR_AUTO_CELLS))):
            ev = cache.evaluation(cur.data, cur.spec, protocol, **options)
    except VPRInputError as exc:  # the rest of the page (the kept runs, the matrix) stays usable
        show_error(exc, hint=getattr(exc, "hint", None)
                   or "Change the protocol settings above, or group/step on the **Places** page.")
        ev, failed = None, True
    if failed:
        pass
    elif ev is None:
        why = (f"the {PROTOCOL_LABELS[Protocol(protocol)]} scores about {cost:.1e} image pairs" if cost > AUTO_RUN_PAIRS
               else f"precision–recall scores {cells:.1e} query × place cells at each of ~200 k")
        st.info(f"{ds.n_images:,} images: {why} (a minute or more on a laptop), so it does not start by itself. "
                "Choose the settings and press **Run**; a progress bar shows how far it is, and the result stays in "
                "memory for this dataset.", icon=":material/timer:")
    else:
        show_results(ev)
        runs_ui.keep(ev, extra={"precision_recall": "on" if with_pr else "off"}, pressed=submitted)

with runs_box:
    runs_ui.render()


# --------------------------------------------------------------------------- similarity matrix


def open_pair() -> None:
    points = st.session_state["simgrid"].selection.points
    pair = plots.selected_pair(points[0]) if points else None
    if pair is None:
        return
    q_image, db_image = pair
    st.session_state["picked_pair"] = (q_image, db_image)
    state.update(query=ds.traversals[ds.image_traversal[q_image]], frame=int(ds.image_frame[q_image]))
    st.session_state["goto_inspector"] = True


with grid_box:
    with stop_on_input_error(hint="Pick the query traversal on the **Places** page."):
        grid = cache.grid(cur.data, cur.database, cur.query)
    if grid.sampled:
        st.caption(f"{ds.n_frames:,} frames: each row is one query frame (the centre of its block of {grid.block}) "
                   "against every database frame, each column the best of its block; computing every block's rows "
                   f"too would take {ds.n_frames:,}² × {len(cur.database)} similarities.")
    picked = st.session_state.get("picked_pair")
    marked = (int(ds.image_frame[picked[0]]), int(ds.image_frame[picked[1]])) if picked else None
    st.plotly_chart(plots.similarity_heatmap(grid, query=cur.query, database=cur.database, marked=marked),
                    key="simgrid", on_select=open_pair, selection_mode="points", width="stretch")
