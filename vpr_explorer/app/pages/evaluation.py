"""Evaluation page: the protocols that apply to the dataset value; Recall@K, precision–recall, the trade-off,
runs side by side, the acceptance bench, the similarity matrix.

The database/queries protocol (``pipeline.evaluate_retrieval`` on the value) runs on every
layout; on aligned traversals it is the traversal protocol: database traversals against a
query traversal, right database images within a tolerance of the query's frame. Aligned
traversals with places made of frames also offer the paper's random splits and the open
set (``pipeline.run_protocol`` on the traversals). A protocol that does not apply is
refused by name, with what is shown instead.

Every setting of the page lives in the URL beside the view (``eval_protocol``, ``eval_runs``,
``eval_seed``, ``eval_cross``, ``eval_share``, ``eval_database``, ``eval_query``,
``eval_tolerance``, ``eval_pr``, ``eval_rule``): a link reopens the same settings, and a
bad value is refused with a warning naming it and what is used instead. The settings the
form shows are the ones the results were computed with: the form is drawn from the
committed settings on every run (they are committed only by **Run**), and the results are
looked up from them, so leaving the page and coming back can never show one protocol's
controls above another's results. The page draws its controls first and computes after,
with a progress bar.

The failure table (``ui.failure_table``) lists every query a chosen method got wrong on the
database/queries protocol's value (the traversals chosen above on aligned traversals), with
the query, the method's answer and the true match as pictures; a selected row opens its query
in the Query inspector.

The automatic global θ is one number wherever the page shows it: the database/queries
protocol's fit of the value, or for the paper and open-set protocols the mean of their runs' θ
(``auto_theta.runs_auto_parts``: the trade-off's and the precision–recall's automatic point),
always to three decimals. The precision–recall table tells the method's own threshold ("own
at") from the point of its curve where F1 is largest ("max F1 at").

The acceptance bench (``ui.bench``: every acceptance rule on one similarity matrix, the
authors' table and precision–recall) has its own form, in its own expander, and runs only
when its button is pressed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import pandas as pd  # before plotly: plotly.py#2433
import streamlit as st

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.auto_theta import auto_parts, rejects_all_note, runs_auto_parts
from vpr_explorer.method.places import make_places, retrieval_places
from vpr_explorer.protocols.cost import protocol_pairs
from vpr_explorer.protocols.evaluation import PROTOCOL_LABELS, Protocol, draw_splits
from vpr_explorer.protocols.options import SEED, UNKNOWN_SHARE
from vpr_explorer.views import plots
from vpr_explorer.views.report import at_text, method_csv
from vpr_explorer.views.numbers import AUTO_RUN_PAIRS, evaluation_json, evaluation_rows

from vpr_explorer.app.ui import bench as bench_ui, cache, failure_table, runs as runs_ui, state
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
#: Settings of the aligned traversals' protocols only: another layout fixes its database, queries and ground truth.
ALIGNED_ONLY = ("runs", "seed", "cross", "share", "database", "query", "tolerance", "rule")

if st.session_state.pop("goto_inspector", False):
    st.switch_page(INSPECTOR)

st.title("Evaluation")
with stop_on_input_error():
    cur = current()
ds, aligned = cur.dataset, cur.aligned
v = state.view()
#: The database/queries protocol's name here: on aligned traversals it is the traversal protocol.
VALUE_PROTOCOL = (Protocol.TRAVERSAL if aligned is not None else Protocol.DATABASE).value


def refusal(protocol: str) -> str | None:
    """Why ``protocol`` does not apply to this dataset and its places; ``None`` when it does."""
    if protocol in (Protocol.TRAVERSAL, Protocol.DATABASE):
        return None
    what = "the random split" if protocol == Protocol.PAPER else "the held-out places"
    if aligned is None:
        return f"{what} needs aligned traversals ({ds.name!r} is read in the {ds.layout.value} layout)"
    if cur.places.metric is not None:
        return f"{what} needs places made of frames (these are in metres: choose frames on the **Places** page)"
    return None


PROTOCOLS = tuple(p for p in (Protocol.PAPER.value, VALUE_PROTOCOL, Protocol.OPEN_SET.value) if refusal(p) is None)


# --------------------------------------------------------------------------- settings (URL ⇄ form)


@dataclass(frozen=True)
class EvalSettings:
    """Every setting of the page; ``database``/``query`` ``None``: the Places page's traversals."""

    protocol: str = PROTOCOLS[0]
    runs: int = 20  # the page's own default: 20 seeded splits answer in seconds on GardensPoint
    seed: int = SEED
    cross: bool = False
    share: float = UNKNOWN_SHARE
    database: tuple[str, ...] | None = None
    query: str | None = None
    tolerance: int = 0
    pr: str = "auto"  # "auto": on when cheap (PR_AUTO_CELLS); "on"; "off"
    rule: str = "margin"


_PARAMS = {"protocol": "eval_protocol", "runs": "eval_runs", "seed": "eval_seed", "cross": "eval_cross",
           "share": "eval_share", "database": "eval_database", "query": "eval_query", "tolerance": "eval_tolerance",
           "pr": "eval_pr", "rule": "eval_rule"}
_DEFAULT = EvalSettings()
TRAVERSALS = aligned.traversals if aligned is not None else ()


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
        if text in (Protocol.TRAVERSAL, Protocol.DATABASE):  # one protocol, named for the layout
            return VALUE_PROTOCOL
        if text not in PROTOCOLS:
            raise ValueError(refusal(text) if text in {p.value for p in Protocol} else f"choose {', '.join(PROTOCOLS)}")
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
        missing = [t for t in names if t not in TRAVERSALS]
        if not names or missing:
            raise ValueError(f"{'no traversal named' if not names else 'not a traversal of ' + ds.name}: "
                             f"{', '.join(missing) or text!r}; choose among {', '.join(TRAVERSALS)} joined by +")
        return names
    if field == "query":
        if text not in TRAVERSALS:
            raise ValueError(f"not a traversal of {ds.name}; choose one of {', '.join(TRAVERSALS)}")
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
        if name not in params:
            continue
        if aligned is None and field in ALIGNED_ONLY:
            refused.append(f"{name}={params[name]!r}: applies to aligned traversals ({ds.name!r} is read in the "
                           f"{ds.layout.value} layout, which fixes its database, queries and ground truth); ignored")
            continue
        try:
            values[field] = _parse(field, params[name])
        except ValueError as exc:
            refused.append(f"{name}={params[name]!r}: {exc}; using {_instead(field)}")
    return replace(_DEFAULT, **values), refused


def _valid_here(s: EvalSettings) -> tuple[EvalSettings, list[str]]:
    """Settings that apply to this dataset (another dataset may have been opened since)."""
    notes = []
    if s.protocol in (Protocol.TRAVERSAL, Protocol.DATABASE):
        s = replace(s, protocol=VALUE_PROTOCOL)
    elif s.protocol not in PROTOCOLS:
        notes.append(f"eval_protocol={s.protocol!r}: {refusal(s.protocol)}; using {_instead('protocol')}")
        s = replace(s, protocol=_DEFAULT.protocol)
    if s.database is not None and any(t not in TRAVERSALS for t in s.database):
        if aligned is not None:
            notes.append(f"database traversals {' + '.join(s.database)} are not all in {ds.name}; "
                         f"using {_instead('database')}")
        s = replace(s, database=None)
    if s.query is not None and s.query not in TRAVERSALS:
        if aligned is not None:
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
    """The settings that apply here into the address bar (``state.sync_url`` writes it)."""
    state.set_page_params(**{name: None if aligned is None and field in ALIGNED_ONLY else _text(getattr(s, field))
                             for field, name in _PARAMS.items()})


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
    s = ss["eval_settings"]
    database = tuple(ss.get("w_database", cur.database))
    query = ss.get("w_eval_query", cur.query)
    s = replace(s, protocol=ss["w_protocol"], runs=int(ss.get("w_runs", s.runs)), seed=int(ss.get("w_seed", s.seed)),
                cross=bool(ss.get("w_cross", s.cross)), share=round(float(ss.get("w_share", s.share)), 2),
                database=None if database == tuple(cur.database) else database,
                query=None if query == cur.query else query,
                tolerance=int(ss.get("w_tolerance", s.tolerance)), pr=ss["w_pr"])
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
    pr_box = st
    if aligned is not None:
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
        c[0].multiselect("database traversals (traversal protocol)", list(TRAVERSALS), key="w_database")
        c[1].selectbox("query traversal (traversal protocol)", list(TRAVERSALS), key="w_eval_query")
        c[2].number_input("tolerance ± frames", *TOLERANCE_RANGE, key="w_tolerance",
                          help="A database image within this many frames of the query's is right too (the authors "
                               "count ±2); 0: only the query's own frame.")
        pr_box = c[3]
    pr_box.selectbox("precision–recall", ["auto", "on", "off"], key="w_pr",
                     format_func={"auto": "on when quick", "on": "on", "off": "off"}.get,
                     help="PR curves, AUC, R@100P, R@99P and max F1. The per-place curves score every query "
                          "against every place at ~200 values of k: 'on when quick' leaves them off on large "
                          "datasets.")
    st.form_submit_button("Run", type="primary", on_click=_commit, key="w_run")

protocol = settings.protocol
with stop_on_input_error(hint=PLACES_HINT):
    if protocol == VALUE_PROTOCOL:
        places = None
        cells = ds.n_queries * retrieval_places(ds, cur.places.spec, cur.places.metric)[1]
    else:
        places = make_places(aligned, cur.spec)
        cells = settings.runs * places.n_places ** 2
with_pr = settings.pr == "on" or (settings.pr == "auto" and cells <= PR_AUTO_CELLS)


def value_to_run() -> cache.Loaded:
    """The dataset value the database/queries protocol runs on: the chosen traversals on aligned ones."""
    if aligned is None:
        return cur.data
    default = tuple(t for t in TRAVERSALS if t != query)
    return cache.value(cur.source, query, database=None if database == default else database,
                       tolerance=settings.tolerance)


results_box = st.container()  # filled last: the controls and the page show before anything is computed
failures_box = st.container()
runs_box = st.container()
bench_box = st.container()
st.subheader("Similarity matrix: click a cell to open that pair in the inspector")
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


def theta_text(theta: float) -> str:
    """A threshold as every part of the page writes it (the note, the tables, the legends): three decimals."""
    return f"{theta:.3f}"


# sampling up to 2·10⁶ training pairs: once per descriptors, places and seed, not on every rerun
@st.cache_data(show_spinner=False, max_entries=8)
def _auto_parts(key: str, places: tuple, seed: int, _descriptors: np.ndarray, _rows: np.ndarray):
    return auto_parts(_descriptors, seed=seed, rows=_rows)


@st.cache_data(show_spinner=False, max_entries=8)
def _runs_auto_parts(key: str, places: tuple, runs: int, seed: int, share: float | None, _descriptors: np.ndarray,
                     _image_place: np.ndarray, n_places: int):
    splits = draw_splits(_image_place, n_places, runs=runs, seed=seed, unknown_share=share)
    return runs_auto_parts(_descriptors, [sp.train for sp in splits], seed=seed)


def auto_theta_parts(ev, data: cache.Loaded | None):
    """The automatic global θ the run ``ev`` used, and its median and MAD (``auto_theta.AutoParts``), and over what.

    ``data``: the value the database/queries protocol ran on (its fit's θ); ``None`` for the paper
    and open-set protocols (the mean of the runs' θ, ``auto_theta.runs_auto_parts``).
    """
    if data is not None:
        place, _ = retrieval_places(data.dataset, cur.places.spec, cur.places.metric)
        parts = _auto_parts(data.key, cache.places_key(cur.places), 0, data.descriptors, np.flatnonzero(place >= 0))
        return parts, f"the database images in places ({' + '.join(sides(data)[0])})"
    runs, seed = int(ev.settings.get("runs", settings.runs)), int(ev.settings.get("seed", settings.seed))
    share = float(ev.settings.get("unknown_share", settings.share)) if ev.protocol is Protocol.OPEN_SET else None
    parts = _runs_auto_parts(cur.source.key, cache.places_key(cur.places), runs, seed, share, cur.source.descriptors,
                             places.image_place, places.n_places)
    held = ", less the held-out places' images" if share is not None else ""
    return parts, (f"each of the {runs} runs' training images (all place images but the run's queries{held}), "
                   f"the mean of the runs' θ")


def show_auto_note(ev, data: cache.Loaded | None) -> None:
    """Say why the automatic global θ accepts nothing, beside the table that shows its 0% recall.

    ``data``: the value the database/queries protocol ran on (``None`` for the paper and open-set protocols).
    """
    auto = next((r for r in ev.rows if r.key == "global-auto"), None)
    if auto is None or auto.accepted[0] > 0:
        return
    parts, over = auto_theta_parts(ev, data)
    note = rejects_all_note(parts, over=over)
    if note is None:  # θ ≤ 1 but above every query's top score
        note = (f"**global θ, automatic = {theta_text(parts.theta)}** (median {parts.median:.3f}, MAD "
                f"{parts.mad:.3f} of the training similarities) is above every query's top score here, so it "
                "accepts no query.")
    st.warning(note, icon=":material/block:")


def sides(data: cache.Loaded) -> tuple[list[str], str]:
    """The database traversals (in order) and the query traversal of a dataset value, by name."""
    d = data.dataset
    return [d.traversals[int(t)] for t in pd.unique(d.database_traversal)], d.traversals[int(d.query_traversal[0])]


def value_caption(ev, data: cache.Loaded) -> str:
    """What the database/queries protocol ran on and counted apart."""
    s = ev.settings
    db, q = sides(data)
    return (f"database: {' + '.join(db)} ({s['database_images']:,} images) · queries: {q} ({s['queries']:,}) · "
            f"ground truth: {s['ground_truth']} · **{s['queries_without_positive']:,} with no right database "
            f"image** (unknown places: counted apart, as their rejection rate) · {s['queries_between_places']:,} "
            f"whose right images all lie between places (left out of the place-level rows) · "
            f"{s['database_images_in_places']:,} of {s['database_images']:,} database images in {s['places']} · "
            f"descriptor: {s.get('descriptor')} · {ev.seconds:.1f} s")


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
                     "R@99P": 100 * r.r_at_99p, "max F1": r.max_f1, "max F1 at": at_text(r.max_f1_at, r.param),
                     "own at": at_text(r.own.threshold, r.param),
                     "own P": 100 * r.own.precision if r.own.accepted else math.nan,
                     "own R": 100 * r.own.recall, "with a true match": r.n_known, "no true match": r.n_unknown})
    if not rows:
        st.caption("No curve: " + " ".join(n for n in ev.notes if "precision" in n))
        return
    table = pd.DataFrame(rows)
    fmt = {"AUC": "{:.3f}", "max F1": "{:.3f}", "R@100P": "{:.1f}", "R@99P": "{:.1f}",
           "own P": "{:.1f}", "own R": "{:.1f}", "with a true match": "{:,}", "no true match": "{:,}"}
    st.dataframe(table.style.format(fmt, na_rep=MISSING), hide_index=True, key="pr_table", placeholder=MISSING,
                 column_config={
        "R@100P": st.column_config.NumberColumn("R@100P", help="recall at 100% precision, %"),
        "R@99P": st.column_config.NumberColumn("R@99P", help="recall at precision ≥ 99%, %"),
        "max F1 at": st.column_config.TextColumn(
            "max F1 at", help="Where on its curve the method's best F1 lies: the global θ (θ=…) on the global-θ and "
                              "image-level curves, the k of θ_p(k) = θ_p + k·s_p (k=…) on the per-place curves. A "
                              "point of the sweep, not the method's own threshold (that is 'own at')."),
        "own at": st.column_config.TextColumn(
            "own at", help="The method's own threshold, where 'own P' and 'own R' are counted: its global θ (the "
                           "automatic θ of several runs: the mean of theirs), k=+0.00 for the per-place θ_p, "
                           "'none' for a method that accepts every query."),
        "own P": st.column_config.NumberColumn("own P", help="precision at the method's own θ, %; '—': it accepts "
                                                             "no query, so there is no precision"),
        "own R": st.column_config.NumberColumn("own R", help="recall at the method's own θ, %"),
        "no true match": st.column_config.NumberColumn("no true match", help="queries of an unknown place, "
                                                       "summed over runs: each accepted one is a false positive"),
    })
    st.plotly_chart(plots.evaluation_pr_figure(ev), key="pr", width="stretch")
    left_out = [n for n in ev.notes if "precision–recall" in n and "left out" in n]
    for n in left_out:
        st.caption(f"note: {n}")


def show_results(ev, data: cache.Loaded | None) -> None:
    """The table, Recall@K, downloads, the open set's trade-off and precision–recall of one run."""
    st.subheader(PROTOCOL_LABELS[ev.protocol])
    if data is not None:
        st.caption(value_caption(ev, data))
        st.caption("The database/queries protocol: thresholds from the database images in places, every query "
                   "decided once; the image-level baseline ranks every database image (the field's Recall@K).")
    else:
        shown = {k: val for k, val in ev.settings.items()
                 if k not in ("k_grid", "group", "step", "reading") and val is not None}
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
    show_auto_note(ev, data)
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
    elif aligned is not None:
        st.caption("Run the open-set protocol to see the trade-off between rejecting unknown places and Recall@1.")
    show_pr(ev)


def run() -> tuple[object, cache.Loaded | None, int]:
    """The committed protocol's run (``None`` when it waits for **Run**), the value it ran on, and its cost."""
    options = {"user_theta": v.theta, "pr": with_pr}
    if protocol == VALUE_PROTOCOL:
        data = value_to_run()
        cost = data.dataset.n_queries * data.dataset.n_database
        ready = cache.queries_evaluated(data, cur.places, **options)
        start = ready or submitted or (cost <= AUTO_RUN_PAIRS and (not with_pr or cells <= PR_AUTO_CELLS))
        if not start:
            return None, data, cost
        ev = cache.queries_evaluation(data, cur.places, **options)
        # named for the layout, as pipeline.run_protocol names the traversal protocol it runs on the value
        return replace(ev, protocol=Protocol(VALUE_PROTOCOL)), data, cost
    options.update(tolerance=settings.tolerance, runs=settings.runs, seed=settings.seed,
                   cross_condition=settings.cross)
    if protocol == Protocol.OPEN_SET:
        options["unknown_share"] = settings.share
    cost = protocol_pairs(protocol, places, aligned, runs=settings.runs, unknown_share=settings.share)
    ev = cache.evaluation(cur.source, cur.spec, protocol, peek=True, **options)
    if ev is None and (submitted or (cost <= AUTO_RUN_PAIRS and (not with_pr or cells <= PR_AUTO_CELLS))):
        ev = cache.evaluation(cur.source, cur.spec, protocol, **options)
    return ev, None, cost


with results_box:
    try:
        ev, data, cost = run()
    except VPRInputError as exc:  # the rest of the page (the kept runs, the matrix) stays usable
        show_error(exc, hint=getattr(exc, "hint", None)
                   or "Change the protocol settings above, or group/step on the **Places** page.")
    else:
        if ev is None:
            why = (f"the {PROTOCOL_LABELS[Protocol(protocol)]} scores about {cost:.1e} image pairs"
                   if cost > AUTO_RUN_PAIRS else f"precision–recall scores {cells:.1e} query × place cells at each "
                                                 "of ~200 k")
            st.info(f"{ds.n_images:,} images: {why} (a minute or more on a laptop), so it does not start by itself. "
                    "Choose the settings and press **Run**; a progress bar shows how far it is, and the result stays "
                    "in memory for this dataset.", icon=":material/timer:")
        else:
            show_results(ev, data)
            extra = {"precision_recall": "on" if with_pr else "off"}
            if data is not None:
                extra.update(zip(("database", "query"), sides(data)))
            runs_ui.keep(ev, extra=extra, pressed=submitted)

# --------------------------------------------------------------------------- failures


def _goto_inspector() -> None:
    """A failure table's row was opened: the next run goes to the inspector (the top of the page)."""
    st.session_state["goto_inspector"] = True


def failures_caption(data: cache.Loaded) -> str:
    """What the failure table decides, and where the inspector's value differs from it."""
    d = data.dataset
    db, q = sides(data)
    text = (f"Each query of the database/queries value decided once, as the "
            f"{PROTOCOL_LABELS[Protocol(VALUE_PROTOCOL)].split(':')[0]} protocol decides it: queries {q} "
            f"({d.n_queries:,}) against {' + '.join(db)} ({d.n_database:,} images), thresholds fitted on its "
            "database images in places.")
    if protocol != VALUE_PROTOCOL:
        text += (f" (The {PROTOCOL_LABELS[Protocol(protocol)].split(':')[0]} protocol above draws its queries at "
                 "random in every run, so its failures are not one per query.)")
    others = [t for t in TRAVERSALS if t != q]
    if aligned is not None and (db != others or settings.tolerance):
        text += (f" The Query inspector decides a query against every other traversal ({' + '.join(others)}), its "
                 "own frame alone right: its answer there can differ from this table's.")
    return text


with failures_box:
    st.subheader("Failures: every query a method got wrong")
    try:
        failed_on = value_to_run()
    except VPRInputError as exc:
        show_error(exc, hint="Change the traversals or the tolerance above.")
    else:
        st.caption(failures_caption(failed_on))
        pairs = failed_on.dataset.n_queries * failed_on.dataset.n_database
        started = st.session_state.get("eval_failures_started") == failed_on.key
        if pairs > AUTO_RUN_PAIRS and not started:
            st.info(f"Deciding every query scores {pairs:.1e} image pairs, so the failure table does not start by "
                    "itself.", icon=":material/timer:")
            if st.button("Find the failures", key="w_failures_start"):
                st.session_state["eval_failures_started"] = failed_on.key
                st.rerun()
        else:
            failure_table.show(failed_on, cur.places, key="eval_failures", user_theta=v.theta,
                               query_traversal=sides(failed_on)[1] if aligned is not None else None,
                               navigate=_goto_inspector)

with runs_box:
    runs_ui.render()


# --------------------------------------------------------------------------- similarity matrix


def open_pair() -> None:
    """A clicked cell: its query and database image open in the inspector."""
    points = st.session_state["simgrid"].selection.points
    pair = plots.selected_pair(points[0]) if points else None
    if pair is None:
        return
    st.session_state["picked_pair"] = pair
    state.update(frame=pair[0])
    st.session_state["goto_inspector"] = True


with grid_box:
    grid = cache.similarity_grid(cur.data)
    n_q, n_db = ds.n_queries, ds.n_database
    if grid.sampled:
        st.caption(f"{n_q:,} queries × {n_db:,} database images: each row is one query (the centre of its block of "
                   f"{grid.row_block}) against every database image, each column the best of its block of "
                   f"{grid.block}; computing every query's row would take {n_q * n_db:.1e} similarities.")
    picked = st.session_state.get("picked_pair")
    marked = picked if picked and picked[0] < n_q and picked[1] < n_db else None
    fig = plots.similarity_heatmap(grid, query=cur.query, database=cur.database, marked=marked)
    st.plotly_chart(fig, key="simgrid", on_select=open_pair, selection_mode="points", width="stretch")


# --------------------------------------------------------------------------- acceptance bench (on demand)


with bench_box:
    bench_ui.section(cur)
