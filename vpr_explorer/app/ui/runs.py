"""Runs side by side on the Evaluation page: every run kept while the app is open, pinned, renamed, compared.

The list lives in ``st.session_state`` (one browser session's runs; a reload starts a new
list) as ``compare.RunRecord`` s. Runs from a file join it: a runs export (**Download runs
(JSON)**) or a ``vpr-explorer bench`` folder's ``bench.json``, under the app's data root
(``compare.read_run_file``). The link keeps the file (``eval_runs_file``) and the comparison's
choices (``eval_compare``, ``eval_compare_ref``, ``eval_compare_metrics``,
``eval_compare_methods``): a session opened from it reads the file again and compares the
same runs. Runs computed in a session are not in its link (their results are not in a URL);
a link naming one says so. everything numeric is ``vpr_explorer.protocols.compare``
(means, mean ± std and 95% intervals over splits, paired or Welch differences:
``protocols.paired``) and ``compare_plots``: this module only draws widgets around them.
A table's cells hold the numbers (means, differences of means) and show their text
(``"0.755 ± 0.104 [95% 0.681, 0.829]"``) through the table's formatting.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pandas as pd  # before plotly: plotly.py#2433
import streamlit as st

from vpr_explorer.app.ui import state
from vpr_explorer.protocols import compare
from vpr_explorer.protocols import paired
from vpr_explorer.views import compare_plots
from vpr_explorer.errors import VPRInputError
from vpr_explorer.protocols.evaluation import Evaluation
from vpr_explorer.method.retrieval import METHODS_BY_KEY

_KEY = "eval_kept_runs"
_ISSUED = "eval_runs_issued"
_DISMISSED = "eval_runs_removed"


def kept() -> tuple[compare.RunRecord, ...]:
    """The session's runs, oldest first."""
    return st.session_state.get(_KEY, ())


def keep(ev: Evaluation, extra: Mapping[str, object] | None = None, *, pressed: bool = False) -> None:
    """Add a run shown on the page to the list, once per set of settings.

    A run the user removed is not added back while its results stay on the page; pressing
    **Run** for it again (``pressed``) does.
    """
    runs = kept()
    settings = compare.run_settings(ev, extra)
    key = compare.settings_key(settings)
    dismissed = st.session_state.setdefault(_DISMISSED, set())
    if pressed:
        dismissed.discard(key)
    if key in dismissed or compare.find_run(runs, settings) is not None:
        return
    issued = st.session_state.get(_ISSUED, 0)
    new = compare.record(ev, run_id=compare.next_id(runs, issued), extra=extra)
    st.session_state[_KEY] = compare.add_run(runs, new)
    st.session_state[_ISSUED] = int(new.id.split()[-1])
    if "w_compare_runs" in st.session_state:  # a new run joins the comparison
        st.session_state["w_compare_runs"] = [*st.session_state["w_compare_runs"], new.id]


def file_stem(ev: Evaluation) -> str:
    """A download's file name for one run: every setting in it."""
    return compare.export_stem([compare.record(ev, run_id="run")], prefix="vpr_eval")


def _act(action: str) -> None:
    """A button of the run manager: rename, pin/unpin or remove the picked run."""
    ss = st.session_state
    run_id = ss.get("w_run_pick")
    try:
        if action == "rename":
            ss[_KEY] = compare.rename(kept(), run_id, ss.get("w_run_name", ""))
        elif action == "pin":
            run = next(r for r in kept() if r.id == run_id)
            ss[_KEY] = compare.pin(kept(), run_id, not run.pinned)
        elif action == "remove":
            run = next(r for r in kept() if r.id == run_id)
            ss[_KEY] = compare.remove(kept(), run_id)
            ss.setdefault(_DISMISSED, set()).add(compare.settings_key(run.settings))
            ss.pop("w_run_pick", None)
    except (VPRInputError, StopIteration) as exc:
        ss["runs_rejected"] = str(exc) or f"no run {run_id!r}"
    ss.pop("w_run_name_for", None)  # the name field shows the run's (new) name again


#: The runs file in the link (the page's own parameter).
FILE_PARAM = "eval_runs_file"
#: The comparison's widgets and their parameters in the link (values joined by ``,``).
SELECTION_PARAMS = {"w_compare_runs": "eval_compare", "w_compare_ref": "eval_compare_ref",
                    "w_compare_metrics": "eval_compare_metrics", "w_compare_methods": "eval_compare_methods"}
_FROM_URL = "eval_compare_from_url"  # the link's choices are applied once per session
_FILE_READ = "eval_runs_file_read"  # the file the session has read (a link reads its file once)
_SEP = ","


def open_file(text: str) -> bool:
    """Read a runs file typed or linked (under the data root) into the session's runs; keep it in the link.

    A refusal (outside the data root, unreadable, not a runs file) is kept for ``render`` to show.
    """
    from vpr_explorer.app import OutsideDataRoot, under_data_root

    ss = st.session_state
    try:
        path = under_data_root(text.strip(), what="runs file")
        found, notes = compare.read_run_file(path)
    except (OutsideDataRoot, VPRInputError) as exc:
        ss["runs_rejected"] = str(exc)
        return False
    ss[_KEY], ss[_ISSUED] = compare.add_runs(kept(), found, ss.get(_ISSUED, 0))
    ss[_FILE_READ] = str(path)
    ss["runs_file_notes"] = [f"{len(found)} run{'s' * (len(found) != 1)} read from {path}", *notes]
    state.set_page_params(**{FILE_PARAM: str(path)})
    return True


def _open_typed() -> None:
    text = st.session_state.get("w_runs_file", "").strip()
    if text:
        open_file(text)


def _from_link() -> None:
    """On a session's first look: read the link's runs file, then its comparison choices (seeded once)."""
    ss = st.session_state
    params = state.page_params()
    linked = params.get(FILE_PARAM)
    if linked and _FILE_READ not in ss:
        ss[_FILE_READ] = linked
        if not open_file(linked):
            state.set_page_params(**{FILE_PARAM: None})
    if _FROM_URL in ss:
        return
    ss[_FROM_URL] = True
    ids = {r.id for r in kept()}
    for widget, param in SELECTION_PARAMS.items():
        if param not in params:
            continue
        values = [v for v in params[param].split(_SEP) if v]
        if widget in ("w_compare_runs", "w_compare_ref"):
            unknown = [v for v in values if v not in ids]
            if unknown:
                ss.setdefault("runs_link_notes", []).append(
                    f"{param}={params[param]!r}: {', '.join(unknown)} {'is' if len(unknown) == 1 else 'are'} not "
                    "among this session's runs. Runs computed in a session are not in its link: download them "
                    "(JSON), put the file under the data root and open it below; its link then reopens them.")
            values = [v for v in values if v in ids]
        ss[widget] = values[0] if widget == "w_compare_ref" and values else values
        if widget == "w_compare_ref" and not values:
            ss.pop(widget, None)


def _to_link() -> None:
    """The comparison's choices into the link (``state.sync_url`` writes it)."""
    ss = st.session_state
    state.set_page_params(**{param: (_SEP.join(ss[w]) if isinstance(ss[w], list) else ss[w]) if ss.get(w) else None
                             for w, param in SELECTION_PARAMS.items()})


#: What a cell with nothing to count shows (Streamlit's default is "None").
MISSING = "—"


def _table(rows: list[dict], texts: list[dict]):
    """``rows`` (numbers) as a table whose cells show ``texts`` (same rows, same keys; text where given)."""
    df = pd.DataFrame(rows)
    styler = df.style.format(na_rep=MISSING)
    for i, shown in enumerate(texts):
        for column, text in shown.items():
            styler = styler.format(lambda _, t=text: t, subset=pd.IndexSlice[[i], [column]])
    return styler


def _text(value: paired.Summary | paired.Difference) -> str:
    if isinstance(value, paired.Difference):
        return value.text(short=True)
    if value.note == compare.POOLED and np.isfinite(value.mean):  # the caption says what pooled means
        return f"{value.mean:.3f} (pooled)"
    return value.text()


def _texts(row: dict) -> dict[str, str]:
    """The text of each ``Summary`` / ``Difference`` of a ``compare.metric_stats`` row."""
    return {k: _text(v) for k, v in row.items() if isinstance(v, (paired.Summary, paired.Difference))}


#: A run's column: wide enough for "0.755 ± 0.104 [95% 0.681, 0.829]"; a difference's for its interval and p.
RUN_WIDTH, DIFF_WIDTH = 250, 380


def _method_difference(compared: list[compare.RunRecord], metrics: list[str], methods: list[str]) -> None:
    """Two methods of each run compared split by split: one paired difference row per metric."""
    if len(methods) < 2:
        return
    ss = st.session_state
    first = next((m for m in ("raw-weighted", "margin-weighted") if m in methods), methods[0])
    second = next((m for m in ("place-baseline", *methods) if m in methods and m != first))
    if ss.get("w_paired_a") not in methods:
        ss["w_paired_a"] = first
    if ss.get("w_paired_b") not in methods:
        ss["w_paired_b"] = second
    c = st.columns(2)
    label = lambda k: METHODS_BY_KEY[k].label  # noqa: E731
    a = c[0].selectbox("paired difference of", methods, format_func=label, key="w_paired_a")
    b = c[1].selectbox("minus", methods, format_func=label, key="w_paired_b")
    if a == b:
        st.caption("Choose two different methods to compare them split by split.")
        return
    # one row per metric; the first column is "Δ of" (the Evaluation page's tests find the comparison table by
    # its "metric" column)
    found = [{"Δ of": row.pop("metric"), **row} for row in compare.method_differences(compared, metrics, a, b)]
    rows = [{k: v.mean if isinstance(v, paired.Difference) else v for k, v in row.items()} for row in found]
    wide = {r.name: st.column_config.NumberColumn(r.name, width=DIFF_WIDTH, help=r.name) for r in compared}
    st.dataframe(_table(rows, [_texts(row) for row in found]), hide_index=True, key="paired_table",
                 width="stretch", placeholder=MISSING,
                 column_config={"difference": None,  # the same in every row: the selectboxes and caption say it
                                "Δ of": st.column_config.TextColumn("Δ of", width=80), **wide})
    st.caption(f"{label(a)} − {label(b)} in each run, split by split (the same splits): the mean of the per-split "
               "differences [95% Student-t interval] and the paired t-test's p. 'identical on every split': every "
               "split gave both the same number, so there is nothing to test.")


def render() -> None:
    """The section: the kept runs with their settings, a manager, a comparison table, overlaid curves, exports."""
    st.subheader("Runs side by side")
    _from_link()
    c = st.columns([5, 1], vertical_alignment="bottom")
    c[0].text_input("Open runs from a file", key="w_runs_file", on_change=_open_typed,
                    placeholder="runs.json or a bench folder's bench.json, under the data root",
                    help="A runs export (Download runs (JSON) below) or the bench.json that vpr-explorer bench "
                         "writes: its runs join this list, and the link keeps the file.")
    c[1].button("Open", key="w_runs_file_open", on_click=_open_typed)
    message = st.session_state.pop("runs_rejected", None)
    if message:
        st.error(message, icon=":material/error:")
    for note in st.session_state.pop("runs_file_notes", []):
        st.caption(note)
    for note in st.session_state.pop("runs_link_notes", []):
        st.warning(note, icon=":material/link_off:")
    runs = kept()
    if not runs:
        st.caption("Every run shown above is kept here while the app is open, to compare descriptors, readings, "
                   "cross-condition on/off or tolerance on the same data.")
        return
    st.caption(f"Every run made while the app is open or read from a file, settings and results ({len(runs)} kept; "
               f"the oldest unpinned ones go beyond {compare.MAX_RUNS}, pinned ones stay). The settings that differ "
               "come first.")
    rows = [{k: x if k == "pinned" else (None if x is None else str(x)) for k, x in row.items()}
            for row in compare.settings_rows(runs)]  # as given: 20 stays "20" beside a run without runs
    st.dataframe(pd.DataFrame(rows), hide_index=True, key="runs_table", width="stretch", placeholder=MISSING,
                 column_config={"name": st.column_config.TextColumn("name", width="large")})

    ids = [r.id for r in runs]
    names = {r.id: r.name for r in runs}
    if st.session_state.get("w_run_pick") not in ids:
        st.session_state["w_run_pick"] = ids[-1]
    c = st.columns([2, 3, 1, 1, 1], vertical_alignment="bottom")
    pick = c[0].selectbox("run", ids, format_func=lambda i: names[i], key="w_run_pick")
    if st.session_state.get("w_run_name_for") != pick:
        st.session_state["w_run_name"] = names[pick]
        st.session_state["w_run_name_for"] = pick
    c[1].text_input("name", key="w_run_name", help="A name for the run (unique): the comparison's column header.")
    c[2].button("Rename", key="w_run_rename", on_click=_act, args=("rename",))
    pinned = next(r.pinned for r in runs if r.id == pick)
    c[3].button("Unpin" if pinned else "Pin", key="w_run_pin", on_click=_act, args=("pin",),
                help="A pinned run stays however many runs follow.")
    c[4].button("Remove", key="w_run_remove", on_click=_act, args=("remove",))

    # Widgets keep their state by key while their options change: kept to the runs that exist.
    ss = st.session_state
    ss["w_compare_runs"] = [i for i in ss.get("w_compare_runs", ids[-4:]) if i in ids]
    c = st.columns(2)
    chosen = c[0].multiselect("compare runs", ids, format_func=lambda i: names[i], key="w_compare_runs")
    compared = [r for r in runs if r.id in chosen]
    if not compared:
        _to_link()
        st.caption("Choose runs to compare.")
        return
    if ss.get("w_compare_ref") not in chosen:
        ss["w_compare_ref"] = compared[0].id
    ref = c[1].selectbox("reference run (the differences are run − reference)", [r.id for r in compared],
                         format_func=lambda i: names[i], key="w_compare_ref")
    c = st.columns(2)
    ss["w_compare_metrics"] = [m for m in ss.get("w_compare_metrics", compare.DEFAULT_METRICS) if m in compare.METRICS]
    metrics = c[0].multiselect("metrics", list(compare.METRICS), key="w_compare_metrics",
                               help="; ".join(f"{m}: {d}" for m, (d, _) in compare.METRICS.items()))
    methods = compare.methods_of(compared)
    default_methods = [m for m in ("place-baseline", "margin-weighted", "raw-weighted", "global-auto") if m in methods]
    ss["w_compare_methods"] = [m for m in ss.get("w_compare_methods", default_methods) if m in methods]
    keys = c[1].multiselect("methods", methods, key="w_compare_methods", format_func=lambda k: METHODS_BY_KEY[k].label)
    _to_link()
    if metrics and keys:
        rows = compare.metric_table(compared, metrics, methods=keys, reference=ref)
        texts = [_texts(row) for row in compare.metric_stats(compared, metrics, methods=keys, reference=ref)]
        reference = next(x for x in compared if x.id == ref)
        wide = {r.name: st.column_config.NumberColumn(r.name, width=RUN_WIDTH, help=r.name) for r in compared}
        wide.update({(c := compare.difference_column(r, reference)): st.column_config.NumberColumn(
            c, width=DIFF_WIDTH, help=c) for r in compared if r.id != ref})
        st.dataframe(_table(rows, texts), hide_index=True, key="compare_table", width="stretch", placeholder=MISSING,
                     column_config={"key": None, "method": st.column_config.TextColumn("method", width=140),
                                    "metric": st.column_config.TextColumn("metric", width=80), **wide})
        st.caption("Each run: mean ± std over its splits (ddof 1) [the 95% Student-t interval of the mean]; the "
                   "precision–recall numbers (AUC, R@100P, R@99P, max F1) are pooled over the splits: one number. "
                   "Each difference (run − reference): on the same splits (same dataset, places, runs and seed) the "
                   "mean of the per-split differences with their 95% interval and the paired t-test's p; otherwise "
                   "Welch's interval and test, marked 'splits differ'. Rates and areas in [0, 1]; +0.050 is 5 points. "
                   "'—': the run has no such number (e.g. a closed-set protocol has no unknown-place rejection; a "
                   "run without precision–recall no AUC).")
        for line in compare.splits_note(compared, ref):
            st.caption(line)
        _method_difference(compared, metrics, methods)

    with_pr = [m for m in methods if any(p.key == m for r in compared for p in r.evaluation.pr)]
    if with_pr:
        default = "margin-weighted" if "margin-weighted" in with_pr else with_pr[0]
        if st.session_state.get("w_compare_pr_method") not in with_pr:
            st.session_state["w_compare_pr_method"] = default
        method = st.selectbox("precision–recall curves of", with_pr, format_func=lambda k: METHODS_BY_KEY[k].label,
                              key="w_compare_pr_method")
        st.plotly_chart(compare_plots.pr_overlay(compared, method), key="compare_pr", width="stretch")
    else:
        st.caption("No compared run has precision–recall curves: turn precision–recall on above and press **Run**.")
    if any(r.evaluation.tradeoff for r in compared):
        c = st.columns(2)
        series = c[0].selectbox("trade-off curve", compare_plots.TRADEOFF_SERIES, key="w_compare_series")
        rule = c[1].radio("rule", ["margin", "raw"], horizontal=True, key="w_compare_rule",
                          disabled=series == "global θ")
        st.plotly_chart(compare_plots.tradeoff_overlay(compared, series, rule), key="compare_tradeoff",
                        width="stretch")
    else:
        st.caption("The open-set trade-off curves are overlaid here once an open-set run is compared.")

    stem = compare.export_stem(compared)
    d1, d2 = st.columns(2)
    d1.download_button("Download runs (CSV)", compare.runs_csv(compared), file_name=f"{stem}.csv", mime="text/csv",
                       key="w_runs_csv", help="One row per run and method: every setting in columns, every metric.")
    d2.download_button("Download runs (JSON)", compare.runs_json(compared, metrics or compare.DEFAULT_METRICS,
                                                                 reference=ref),
                       file_name=f"{stem}.json", mime="application/json", key="w_runs_json",
                       help="Every run's settings and whole evaluation, and the comparison table.")
