"""Query inspector: one query of the dataset value, its candidate places under every method, and the answer in words.

A query is picked by its index (slider or number: for aligned traversals the query
traversal's frame), by its file name, or by the finder: ◀ previous / next ▶ move to the
nearest query of a kind (``numbers.FindKind``: rejected, wrongly rejected, a wrong answer,
an accepted unknown-place query, any wrong answer, right) under one method, wrapping round
at either end (the note says so) and skipping the queries between places, whose number the
page gives. The kind and the method are kept in the URL (``inspector_find``,
``inspector_method``; defaults left out), so a shared link finds the same queries.
Its right places are those holding one of its right database images (the ground truth);
a query with none in a place lies between places (not scored), and one with no right image
at all is an unknown-place query (rejecting it is right, accepting it a false positive).
The field's image-level answer (its most similar database image, over every one) is shown
beside the place-level methods. The section "Every acceptance rule" runs the acceptance bench
on demand and gives each of its rules' own reasons for the query (``ui.reasons``). The section
"Failures" lists every query a chosen method got wrong (``ui.failure_table``), at the page's k
and global θ; a selected row opens its query here.
"""

from pathlib import Path

import pandas  # noqa: F401  # before plotly: plotly.py#2433
import streamlit as st

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.retrieval import METHODS_BY_KEY
from vpr_explorer.views.numbers import (
    BETWEEN,
    FIND_KINDS,
    LIVE_METHODS,
    UNKNOWN,
    Direction,
    FindKind,
    database_label,
    describe_answer,
    find_query_by_name,
    query_label,
    search_order,
    thumbnail_label,
    top_candidates,
    walked,
)

from vpr_explorer.app.ui import cache, failure_table, state
from vpr_explorer.app.ui.candidates import show_candidates
from vpr_explorer.app.ui.controls import threshold_controls
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

# --------------------------------------------------------------------------- the finder

#: The finder's kinds as its selectbox says them (``numbers.FindKind``: the definitions).
KIND_LABELS = {
    FindKind.REJECTED: "rejected (any)",
    FindKind.WRONGLY_REJECTED: "wrongly rejected (its right place was there)",
    FindKind.WRONG_ANSWER: "a wrong answer (accepted, wrong place)",
    FindKind.ACCEPTED_UNKNOWN: "accepted unknown (an unknown-place query accepted)",
    FindKind.ANSWERED_WRONG: "answered wrong (any of the three above)",
    FindKind.RIGHT: "right",
}
#: "no query was …": each kind in the finder's sentences.
KIND_WORDS = {
    FindKind.REJECTED: "rejected",
    FindKind.WRONGLY_REJECTED: "wrongly rejected",
    FindKind.WRONG_ANSWER: "answered with a wrong place",
    FindKind.ACCEPTED_UNKNOWN: "accepted though of an unknown place",
    FindKind.ANSWERED_WRONG: "answered wrong",
    FindKind.RIGHT: "answered right",
}
#: The finder's settings in the URL (the page's own parameters, ``state.page_params``) and their defaults.
FIND_PARAMS = {"inspector_find": FindKind.REJECTED.value, "inspector_method": "margin-weighted"}


def finder_settings() -> dict[str, str]:
    """The finder's kind and method from the URL; a refused one is said, dropped from the URL and its default used."""
    given = {**FIND_PARAMS, **{k: v for k, v in state.page_params().items() if k in FIND_PARAMS}}
    kind, method = given["inspector_find"], given["inspector_method"]
    if kind not in FIND_KINDS:
        st.warning(f"inspector_find={kind!r}: choose one of {', '.join(FIND_KINDS)}; finding "
                   f"{FIND_PARAMS['inspector_find']} queries instead.", icon=":material/warning:")
        given["inspector_find"] = FIND_PARAMS["inspector_find"]
        state.set_page_params(inspector_find=None)
    if method not in methods:
        why = ("your own global θ is off (tick \"also compare a global θ of my own\" above)"
               if method == "global-user" else f"choose one of {', '.join(methods)}")
        st.warning(f"inspector_method={method!r}: {why}; finding under "
                   f"{METHODS_BY_KEY[FIND_PARAMS['inspector_method']].label} instead.", icon=":material/warning:")
        given["inspector_method"] = FIND_PARAMS["inspector_method"]
        state.set_page_params(inspector_method=None)
    return given


def keep(name: str, widget: str) -> None:
    """A finder widget's value into the URL (its default: left out)."""
    value = st.session_state[widget]
    state.set_page_params(**{name: None if value == FIND_PARAMS[name] else value})


def jump(direction: str) -> None:
    """Move to the first query of the chosen kind under the chosen method, walking ``direction`` from this one."""
    kind, under = st.session_state["w_find_kind"], st.session_state["w_find_method"]
    try:
        found, last = cache.find(cur.data, cur.places, after=query, kind=kind, method=under, direction=direction,
                                 k=k, user_theta=user_theta)
        wrapped, skipped = walked(fitted, query, last, direction)
    except VPRInputError as exc:
        st.session_state["find_note"] = str(exc)
        return
    st.session_state["find_note"] = found_note(found, last, wrapped, skipped, direction=direction,
                                               words=KIND_WORDS[FindKind(kind)], label=METHODS_BY_KEY[under].label)
    if found is not None or last != query:  # out of budget: move on, so that the next press searches on
        state.update(frame=found if found is not None else last)


def found_note(found: int | None, last: int, wrapped: bool, skipped: int, *, direction: str, words: str,
               label: str) -> str:
    """What a press of ◀ / ▶ found in a sentence: the query, whether the walk wrapped round, the queries skipped."""
    forward = direction == Direction.NEXT
    passed = (f" ({skipped} {'query' if skipped == 1 else 'queries'} between places skipped on the way)" if skipped
              else "")
    if found is None and last == query:
        return f"no query was {words} under {label}{passed}; try raising k or another method"
    if found is None:
        return (f"no query {words} under {label} from query {search_order(ds.n_queries, query, direction)[0]} to "
                f"{last}{passed}; moved to query {last}, press {direction} again to search on")
    if found == query:
        return f"query {query} is the only query {words} under {label}{passed}"
    if not wrapped:
        return f"query {found}: the {direction} query {words} under {label}{passed}"
    if forward:
        return (f"no later one after query {query}: wrapped round to the start, query {found} is the first query "
                f"{words} under {label}{passed}")
    return (f"no earlier one before query {query}: wrapped round to the end, query {found} is the last query "
            f"{words} under {label}{passed}")


settings = finder_settings()
st.session_state["w_find_kind"], st.session_state["w_find_method"] = settings["inspector_find"], \
    settings["inspector_method"]
finder = st.columns([3, 3, 1, 1], vertical_alignment="bottom")
finder[0].selectbox("Find a query that was", list(FIND_KINDS), format_func=lambda kind: KIND_LABELS[FindKind(kind)],
                    key="w_find_kind", on_change=keep, args=("inspector_find", "w_find_kind"))
finder[1].selectbox("under", methods, format_func=lambda key: METHODS_BY_KEY[key].label, key="w_find_method",
                    on_change=keep, args=("inspector_method", "w_find_method"))
finder[2].button("◀ previous", key="w_find_previous", on_click=jump, args=(Direction.PREVIOUS.value,),
                 help="The nearest such query before this one (after query 0: from the last query back)")
finder[3].button("next ▶", key="w_find_next", on_click=jump, args=(Direction.NEXT.value,),
                 help="The nearest such query after this one (after the last query: from query 0 on)")
n_between = int(fitted.between.sum())
st.caption("The finder walks the queries in order, wrapping round at either end"
           + (f", and skips the {n_between} of {ds.n_queries} whose right database images all lie between places "
              "(not scored)." if n_between else f"; none of the {ds.n_queries} queries lies between places."))
note = st.session_state.pop("find_note", None)
if note:
    st.info(note, icon=":material/search:")

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

show_candidates(dec, methods, cands, describe, query_image=ds.query_paths[query],
                query_caption=f"query: {thumbnail_label(ds, query, query=True)}",
                database_image=lambda i: (ds.database_paths[int(model.images[i])],
                                          thumbnail_label(ds, int(model.images[i]))))

show_reasons(cur, query)

failures_box = st.expander("Failures: every query a method got wrong", key=failure_table.OPEN, on_change="rerun")
with failures_box:
    if failures_box.open:  # nothing of it runs while it is closed
        failure_table.show(cur.data, cur.places, key="inspector_failures", k=k, user_theta=user_theta, opens="here")
