"""Query inspector: one query of the dataset value, its candidate places under every method, and the answer in words.

A query is picked by its index (slider or number: for aligned traversals the query
traversal's frame), by its file name, or as the next one a method rejected or got wrong.
Its right places are those holding one of its right database images (the ground truth);
a query with none in a place lies between places (not scored), and one with no right image
at all is an unknown-place query (rejecting it is right, accepting it a false positive).
The field's image-level answer (its most similar database image, over every one) is shown
beside the place-level methods. The section "Every acceptance rule" runs the acceptance bench
on demand and gives each of its rules' own reasons for the query (``ui.reasons``).
"""

from pathlib import Path

import pandas  # noqa: F401  # before plotly: plotly.py#2433
import streamlit as st

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.retrieval import METHODS_BY_KEY
from vpr_explorer.views.numbers import (
    BETWEEN,
    UNKNOWN,
    database_label,
    describe_answer,
    find_query_by_name,
    query_label,
)
from vpr_explorer.views.numbers import FIND_KINDS, LIVE_METHODS, top_candidates

from vpr_explorer.app.ui import cache, state
from vpr_explorer.app.ui.candidates import show_candidates
from vpr_explorer.app.ui.controls import jump_to_next, threshold_controls
from vpr_explorer.app.ui.current import current
from vpr_explorer.app.ui.feedback import PLACES_HINT, stop_on_input_error
from vpr_explorer.app.ui.reasons import show_reasons
from vpr_explorer.app.ui.routing import ensure_routed

ensure_routed(__file__)

SHOWN_CANDIDATES = 8
SHOWN_POSITIVES = 6
RIGHT, WRONG, UNMARKED = ":green[:material/check_circle:]", ":red[:material/cancel:]", ":gray[:material/remove:]"

st.title("Query inspector")
with stop_on_input_error():
    cur = current()
ds = cur.dataset
gt = ds.ground_truth
with stop_on_input_error(hint=PLACES_HINT):
    fitted = cache.fitted(cur.data, cur.places)
model = fitted.model

# --------------------------------------------------------------------------- which query

v = state.view()
query = v.frame if v.frame is not None and 0 <= v.frame < ds.n_queries else 0
if v.frame is not None and v.frame != query:
    st.warning(f"frame={v.frame} is not a query of {ds.name!r} (0 to {ds.n_queries - 1}): showing query {query} "
               "instead.", icon=":material/warning:")
    state.update(frame=None)


def by_name() -> None:
    """The file-name box: the query of that name, or the error kept for this run to show."""
    try:
        state.update(frame=find_query_by_name(ds, st.session_state["w_query_name"]))
    except VPRInputError as exc:
        st.session_state["query_name_error"] = str(exc)


top = st.columns([2, 4, 1, 3][cur.aligned is None:], vertical_alignment="bottom")  # a query traversal: aligned only
slide, enter, named = top[-3:]
if cur.aligned is not None:
    top[0].selectbox("Query traversal (database: every other one)", list(cur.aligned.traversals),
                     **state.bind("w_query", "query", cur.query))
if ds.n_queries > 1:
    slide.slider("Query", 0, ds.n_queries - 1, **state.bind("w_frame", "frame", query),
                 help="The query's index (for aligned traversals: its frame in the query traversal)")
enter.number_input("query", 0, ds.n_queries - 1, step=1, help="Type a query index (the slider moves along)",
                   **state.bind("w_frame_number", "frame", query))
named.text_input("…or its file name", key="w_query_name", on_change=by_name,
                 placeholder=Path(ds.query_paths[0]).name[:40],
                 help="The query image's file name (or its path below the dataset folder); press Enter.")
problem = st.session_state.pop("query_name_error", None)
if problem:
    st.error(problem, icon=":material/error:")
with st.expander("k and your own global θ", expanded=v.k != 0 or v.theta is not None):
    k, user_theta = threshold_controls()
methods = [*LIVE_METHODS, *(["global-user"] if user_theta is not None else [])]

finder = st.columns([2, 2, 1, 3])
kind = finder[0].selectbox("Find queries that were", list(FIND_KINDS), key="w_find_kind")
under = finder[1].selectbox("under", methods, index=methods.index("margin-weighted"), key="w_find_method",
                            format_func=lambda key: METHODS_BY_KEY[key].label)


def jump() -> None:
    """Move to the next query (after the current one, wrapping) that ``under`` rejected / got wrong."""
    jump_to_next(lambda: cache.find(cur.data, cur.places, after=query, kind=kind, method=under, k=k,
                                    user_theta=user_theta),
                 query, ds.n_queries, kind=kind, label=METHODS_BY_KEY[under].label)


finder[2].button("next ▶", key="w_find_next", on_click=jump,
                 help="Jump to the next such query (an accepted unknown-place query counts as answered wrong)")
note = st.session_state.pop("find_none", None)
if note:
    finder[3].info(note)

# --------------------------------------------------------------------------- its decision

with stop_on_input_error(hint="Change k or your global θ above, or group/step on the **Places** page."):
    dec = cache.decision(cur.data, cur.places, query, k=k, user_theta=user_theta)
    top_image = cache.image_answer(cur.data, query)
cands = top_candidates(dec, SHOWN_CANDIDATES)
status = fitted.query_status(query)
positives = gt.positives(query)
name = query_label(ds, query)


def describe(key: str) -> str:
    """``describe_answer`` of this query."""
    return describe_answer(fitted, dec, key, query)


def mark(key: str) -> str:
    if status == BETWEEN:
        return UNMARKED
    return RIGHT if dec.is_right(key) else WRONG


left, right = st.columns([1, 2])
with left:
    st.image(cache.thumbnail(ds.query_paths[query], 240), width="stretch", caption=f"query {query}: {name}")
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
    pair = st.session_state.get("picked_pair")
    if pair and pair[0] == query and 0 <= pair[1] < ds.n_database:
        place = int(fitted.database_place[pair[1]])
        st.caption(f"Opened from the similarity matrix: database image {database_label(ds, pair[1])} "
                   f"({f'place P{place}' if place >= 0 else 'between places'}).")
with right:
    st.markdown("**The answer under each method**")
    where = "" if top_image.distance is None else f", {top_image.distance:.0f} m away"
    lines = [f"- {RIGHT if top_image.positive else WRONG} **image level** (the field's R@1, over every database "
             f"image): its most similar database image is {database_label(ds, top_image.image)} (similarity "
             f"{top_image.score:.3f}{where}): {'a right image' if top_image.positive else 'not a right image'}"]
    lines += [f"- {mark(key)} **{METHODS_BY_KEY[key].label}**: {describe(key)}" for key in methods]
    st.markdown("\n".join(lines))

show_candidates(dec, methods, cands, describe, query_image=ds.query_paths[query], query_caption=f"query: {name[:40]}",
                database_image=lambda i: (ds.database_paths[int(model.images[i])],
                                          database_label(ds, int(model.images[i]))[:40]))

show_reasons(cur, query)
