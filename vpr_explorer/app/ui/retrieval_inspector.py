"""The Query inspector of a database/queries dataset: one query image decided under every method.

A query is picked by its index (slider or number), by its file name, or as the next one a
method rejected or got wrong. Its right places come from the ground truth: the places that
hold one of its positives. A query with no positive at all is an *unknown-place* query:
rejecting it is right, and accepting it is a false positive. The field's image-level answer
(its most similar database image, over every one) is shown beside the place-level methods.
"""

from __future__ import annotations

import re
from pathlib import Path

import streamlit as st

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.retrieval import METHODS_BY_KEY
from vpr_explorer.views.database_queries import BETWEEN, UNKNOWN, database_label, find_query_by_name, query_label
from vpr_explorer.views.traversal import FIND_KINDS, LIVE_METHODS, top_candidates

from vpr_explorer.app.ui import cache, state
from vpr_explorer.app.ui.candidates import show_candidates
from vpr_explorer.app.ui.controls import jump_to_next, threshold_controls
from vpr_explorer.app.ui.current import Current
from vpr_explorer.app.ui.feedback import PLACES_HINT, stop_on_input_error

SHOWN_CANDIDATES = 8
SHOWN_POSITIVES = 6


def _select(cur: Current, fitted) -> int:
    """The query controls; returns the query shown (``view.frame``, checked)."""
    ds = cur.retrieval
    v = state.view()
    query = v.frame if v.frame is not None and 0 <= v.frame < ds.n_queries else 0
    if v.frame is not None and v.frame != query:
        st.warning(f"frame={v.frame} is not a query of {ds.name!r} (0 to {ds.n_queries - 1}): showing query {query} "
                   "instead.", icon=":material/warning:")
        state.update(frame=None)
    top = st.columns([3, 1, 3, 2], vertical_alignment="bottom")
    if ds.n_queries > 1:
        top[0].slider("Query image", 0, ds.n_queries - 1, **state.bind("w_query_image", "frame", query))
    top[1].number_input("query", 0, ds.n_queries - 1, step=1, help="Type a query index (the slider moves along)",
                        **state.bind("w_query_number", "frame", query))

    def by_name() -> None:
        try:
            state.update(frame=find_query_by_name(ds, st.session_state["w_query_name"]))
        except VPRInputError as exc:
            st.session_state["query_name_error"] = str(exc)

    top[2].text_input("…or its file name", key="w_query_name", on_change=by_name,
                      placeholder=Path(ds.query_paths[0]).name[:40],
                      help="The query image's file name (or its path below the dataset folder); press Enter.")
    problem = st.session_state.pop("query_name_error", None)
    if problem:
        st.error(problem, icon=":material/error:")
    return query


def _finder(cur: Current, query: int, methods: list[str], k: float, user_theta: float | None) -> None:
    finder = st.columns([2, 2, 1, 3])
    kind = finder[0].selectbox("Find queries that were", list(FIND_KINDS), key="w_find_kind")
    under = finder[1].selectbox("under", methods, index=methods.index("margin-weighted"), key="w_find_method",
                                format_func=lambda key: METHODS_BY_KEY[key].label)
    n = cur.retrieval.n_queries

    def jump() -> None:
        jump_to_next(lambda: cache.retrieval_find(cur.data, cur.places, after=query, kind=kind, method=under, k=k,
                                                  user_theta=user_theta),
                     query, n, kind=kind, label=METHODS_BY_KEY[under].label, unit="query", short="query")

    finder[2].button("next ▶", key="w_find_next", on_click=jump,
                     help="Jump to the next such query (an accepted unknown-place query counts as answered wrong)")
    note = st.session_state.pop("find_none", None)
    if note:
        finder[3].info(note)


def render(cur: Current) -> None:
    """The Query inspector body for a database/queries dataset."""
    ds = cur.retrieval
    gt = ds.ground_truth
    with stop_on_input_error(hint=PLACES_HINT):
        fitted = cache.retrieval_fitted(cur.data, cur.places)
    query = _select(cur, fitted)
    with st.expander("k and your own global θ", expanded=state.view().k != 0 or state.view().theta is not None):
        k, user_theta = threshold_controls()
    methods = [*LIVE_METHODS, *(["global-user"] if user_theta is not None else [])]
    _finder(cur, query, methods, k, user_theta)

    with stop_on_input_error(hint="Change k or your global θ above, or group/step on the **Places** page."):
        dec = cache.retrieval_decision(cur.data, cur.places, query, k=k, user_theta=user_theta)
        top_image = cache.retrieval_image_answer(cur.data, query)
    cands = top_candidates(dec, SHOWN_CANDIDATES)
    model = fitted.model
    status = fitted.query_status(query)
    positives = gt.positives(query)
    name = query_label(ds, query)

    def describe(key: str) -> str:
        """``dec.describe`` naming the image-level answer by its file name, and an unknown place as such."""
        text = re.sub(r"accepted as image (\d+) →",
                      lambda m: f"accepted as {database_label(ds, int(model.images[int(m.group(1))]))} →",
                      dec.describe(key))
        if status == BETWEEN:
            text = re.sub(r"\((right|wrong): the query's place is not in the database\)",
                          "(not scored: its right database images lie between places)", text)
        elif status == UNKNOWN:
            text = text.replace("(wrong: the query's place is not in the database)",
                                "(wrong: an unknown-place query accepted: a false positive)")
            text = text.replace("(right: the query's place is not in the database)",
                                "(right: an unknown-place query rejected)")
        return text

    def mark(key: str) -> str:
        if status == BETWEEN:
            return ":grey[:material/remove_circle_outline:]"
        return ":green[:material/check_circle:]" if dec.is_right(key) else ":red[:material/cancel:]"

    left, right = st.columns([1, 2])
    with left:
        st.image(cache.thumbnail(ds.query_paths[query], 240), width="stretch",
                 caption=f"query {query}: {name}")
        if status == UNKNOWN:
            st.markdown(f"**Unknown-place query:** no database image is right for it ({gt.description}). The right "
                        "answer is to reject it; **accepting it is a false positive**.")
        elif status == BETWEEN:
            st.markdown(f"**Its {len(positives)} right database image(s) lie between places** (skipped by "
                        "group/step): no place is right, so, as the protocol does, it is **not scored**; each "
                        "method's answer is shown unmarked.")
        else:
            st.markdown(f"**Right place(s):** {', '.join(f'P{p}' for p in dec.true_places)}, holding its right "
                        f"database images ({gt.description}).")
        if len(positives):
            shown = ", ".join(database_label(ds, int(i)) for i in positives[:SHOWN_POSITIVES])
            more = f" and {len(positives) - SHOWN_POSITIVES} more" if len(positives) > SHOWN_POSITIVES else ""
            st.caption(f"Right database images: {shown}{more}.")
        where = "" if top_image.distance is None else f", {top_image.distance:.0f} m away"
        verdict = "a right image" if top_image.positive else "not a right image"
        st.caption(f"Image level (the field's R@1): its most similar database image is "
                   f"{database_label(ds, top_image.image)} (similarity {top_image.score:.3f}{where}): {verdict}.")
    with right:
        st.markdown("**The answer under each method**")
        lines = []
        for key in methods:
            lines.append(f"- {mark(key)} **{METHODS_BY_KEY[key].label}**: {describe(key)}")
        st.markdown("\n".join(lines))

    show_candidates(dec, methods, cands, describe, query_image=ds.query_paths[query],
                    query_caption=f"query: {name[:40]}", star="a right place",
                    database_image=lambda i: (ds.database_paths[int(model.images[i])],
                                              database_label(ds, int(model.images[i]))[:40]))
