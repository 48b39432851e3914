"""The Query inspector's "Every acceptance rule" section: each rule of the bench on the query, and why.

The acceptance bench (``protocols.acceptance`` through ``cache.bench``, its closed set) runs
on the whole similarity matrix and takes seconds on Nordland, so it runs when the button is
pressed; while the value and its places stay the same, every query's reasons then come from
the cache at once. For aligned traversals the bench's value has one database traversal
(picked here: the sequence rules need one route in order) and right images within ±
tolerance frames (default ``TOLERANCE``, the paper's code's ±2); the query traversal is the
page's, so query q is the same query. For the other layouts the bench runs on the page's
value. Each rule gets a line (``views.reasons.rule_reasons``) beside the image it answered or
rejected, then a figure per rule that has one, drawn from a few similarity rows around the
query (``views.reasons.neighbourhood``); where a rule was left out, its figure's place says why.
The section runs only while its expander is open.
"""

from __future__ import annotations

import streamlit as st

from vpr_explorer.errors import VPRInputError
from vpr_explorer.protocols.acceptance import AcceptanceReport, BenchOptions, metres_positions
from vpr_explorer.views import reasons as why
from vpr_explorer.views.numbers import thumbnail_label

from vpr_explorer.app.ui import cache
from vpr_explorer.app.ui.current import Current
from vpr_explorer.app.ui.feedback import show_error

#: Right database images within ± this many frames of the query (aligned traversals).
TOLERANCE = 2
TOLERANCE_RANGE = (0, 20)
THUMBNAIL = 96
#: Session key of the bench the button asked for: (value key, places key).
_ASKED = "reasons_bench"
#: Widget key of the section's expander (its open state).
OPEN = "w_reasons_open"
_MARK = {why.Status.ACCEPTED: ":green[:material/check_circle:]", why.Status.REJECTED: ":red[:material/block:]",
         why.Status.LEFT_OUT: ":gray[:material/remove:]"}
_FIGURES = (("per-query", "per-query threshold"), ("seqslam", "SeqSLAM"), ("per-query-graph", "graph matcher"),
            ("pa-ratio", "PA-ratio"), ("sue", "SUE"))


def _bench_value(cur: Current) -> cache.Loaded:
    """The value the bench runs on: one database traversal of aligned traversals (picked here), else the page's."""
    if cur.aligned is None:
        return cur.data
    others = [t for t in cur.aligned.traversals if t != cur.query]
    left, right = st.columns(2)
    one = left.selectbox("Database traversal (one route: the sequence rules need it)", others,
                         key="w_reasons_database")
    tolerance = right.number_input("right within ± frames", *TOLERANCE_RANGE, value=TOLERANCE, step=1,
                                   key="w_reasons_tolerance",
                                   help="A database image is right for a query within this many frames of it")
    return cache.value(cur.source, cur.query, database=(one,), tolerance=int(tolerance))


def show_reasons(cur: Current, query: int) -> None:
    """The section: the value's controls, the button, then every rule's decision on ``query`` and its figures.

    A stateful expander (``OPEN``): nothing of it runs while it is closed, and it stays open across the reruns
    its own widgets cause.
    """
    box = st.expander("Every acceptance rule", key=OPEN, on_change="rerun")
    with box:
        if not box.open:
            return
        st.caption("Every acceptance rule of the bench on the whole database (its closed set): accepted or "
                   "rejected, the image it answered or weighed, and the rule's own numbers. A rule marked "
                   "*oracle* has no threshold of its own: it runs at the τ with the best F1 on these very "
                   "queries, a bound on what it can do rather than a rule you could run.")
        try:
            data = _bench_value(cur)
        except VPRInputError as exc:
            show_error(exc, hint="Pick another database traversal or tolerance.")
            return
        asked = (data.key, cache.places_key(cur.places))
        if st.button("Run every acceptance rule", key="w_reasons_run",
                     help="Runs the bench on the whole similarity matrix once (seconds on a large route); "
                          "every query's reasons then show at once"):
            st.session_state[_ASKED] = asked
        if st.session_state.get(_ASKED) != asked:
            st.caption("Press the button to run the bench on this value.")
            return
        try:
            report = cache.bench(data, cur.places, BenchOptions())
            _show(report, data, query)
        except VPRInputError as exc:
            show_error(exc)


def _show(report: AcceptanceReport, data: cache.Loaded, query: int) -> None:
    ds = data.dataset
    if not 0 <= query < ds.n_queries:
        raise VPRInputError(f"query {query}: the bench's value has queries 0 to {ds.n_queries - 1}")
    first, stop = why.reason_rows(report, query)
    nb = why.neighbourhood(data.descriptors, ds.n_database, first, stop)
    reasons = why.rule_reasons(report, query, nb.row(query), ds.ground_truth.positives(query))
    places = report.settings.get("group/step")
    st.caption(f"The bench's value: {ds.n_queries:,} queries × {ds.n_database:,} database images "
               f"({ds.ground_truth.description}). Places P… are the bench's own on this database"
               + (f" ({places})." if places else "."))
    if not report.closed.genuine[query]:
        st.info("This query has no right image in this database: the closed set does not count it, and every "
                "acceptance of it is wrong.", icon=":material/info:")
    for r in reasons:
        picture, words = st.columns([1, 6], vertical_alignment="center")
        if r.image >= 0:
            picture.image(cache.thumbnail(ds.database_paths[r.image], THUMBNAIL), width="stretch",
                          caption=f"{thumbnail_label(ds, r.image)} ({'right' if r.right else 'wrong'})")
        words.markdown(f"{_MARK[r.status]} **{r.label}**: {r.sentence}")
    tabs = st.tabs([label for _, label in _FIGURES])
    for (key, label), tab in zip(_FIGURES, tabs):
        with tab:
            if key not in report.closed.decisions:
                st.info(f"{label}: {why.left_out_reason(report, key) if key in report.closed.left_out else 'not run'}",
                        icon=":material/info:")
                continue
            try:
                _FIGURE[key](report, data, nb, query)
            except VPRInputError as exc:
                show_error(exc)


def _per_query(report: AcceptanceReport, data: cache.Loaded, nb: why.Neighbourhood, query: int) -> None:
    qt = report.closed.decisions["per-query"].result
    st.plotly_chart(why.patch_figure(nb, qt, query), key="reasons_patch", width="stretch")


def _seqslam(report: AcceptanceReport, data: cache.Loaded, nb: why.Neighbourhood, query: int) -> None:
    res = report.closed.decisions["seqslam"].result
    if res.match[query] < 0:
        st.info(f"SeqSLAM: query {query} has no centred trajectory: it matches none of the first and last "
                f"ds/2 = {int(report.settings['ds']) // 2} queries.", icon=":material/info:")
        return
    best, competitor = why.seqslam_trajectories(nb, res, query, ds=int(report.settings["ds"]))
    st.plotly_chart(why.seqslam_figure(nb, best, competitor, query), key="reasons_seqslam", width="stretch")


def _graph(report: AcceptanceReport, data: cache.Loaded, nb: why.Neighbourhood, query: int) -> None:
    match, _ = report.closed.decisions["per-query-graph"].result
    st.plotly_chart(why.graph_figure(nb, match, query), key="reasons_graph", width="stretch")


def _pa_ratio(report: AcceptanceReport, data: cache.Loaded, nb: why.Neighbourhood, query: int) -> None:
    ds = data.dataset
    two = why.nearest_two(nb.row(query))
    u = report.closed.decisions["pa-ratio"].detail["score"][query]
    cols = st.columns(3)
    cols[0].image(cache.thumbnail(ds.query_paths[query], 160), width="stretch", caption=f"query {query}")
    positives = ds.ground_truth.positives(query)
    for col, name, image, s, d in zip(cols[1:], ("d₁", "d₂"), two.images, two.similarities, two.distances):
        right = "right" if int(image) in set(positives.tolist()) else "wrong"
        col.image(cache.thumbnail(ds.database_paths[int(image)], 160), width="stretch",
                  caption=f"{name} = {d:.4f} (s = {s:.4f}): {thumbnail_label(ds, int(image))} "
                          f"({right})")
    st.caption(f"PA-ratio u = d₁/d₂ = {u:.4f}" + (" (the two tie: u = 1)" if two.tie else "") + ".")


def _sue(report: AcceptanceReport, data: cache.Loaded, nb: why.Neighbourhood, query: int) -> None:
    ds = data.dataset
    xy, note = metres_positions(ds)
    if xy is None:
        st.info(f"SUE: {note}", icon=":material/info:")
        return
    weights = why.sue_weights(nb.row(query), xy)
    st.plotly_chart(why.sue_map(ds, report.closed.places, query, weights), key="reasons_sue", width="stretch")


_FIGURE = {"per-query": _per_query, "seqslam": _seqslam, "per-query-graph": _graph, "pa-ratio": _pa_ratio,
           "sue": _sue}
