"""Query inspector: one query, its candidate places under every method, and the answer in words.

A database/queries dataset (``layouts.RetrievalDataset``) gets its own page body
(``ui.retrieval_inspector``): any query image, its right places from the ground truth.
"""

import pandas  # noqa: F401  # before plotly: plotly.py#2433
import streamlit as st

from vpr_explorer.method.database import Verdict, between_note, describe_query, query_verdict
from vpr_explorer.method.retrieval import METHODS_BY_KEY
from vpr_explorer.views.traversal import FIND_KINDS, LIVE_METHODS, top_candidates

from vpr_explorer.app.ui import cache, retrieval_inspector, state
from vpr_explorer.app.ui.candidates import show_candidates
from vpr_explorer.app.ui.controls import jump_to_next, threshold_controls
from vpr_explorer.app.ui.current import current
from vpr_explorer.app.ui.feedback import PLACES_HINT, stop_on_input_error
from vpr_explorer.app.ui.routing import ensure_routed

ensure_routed(__file__)

SHOWN_CANDIDATES = 8

st.title("Query inspector")
with stop_on_input_error():
    cur = current()
if cur.retrieval is not None:
    retrieval_inspector.render(cur)
    st.stop()
with stop_on_input_error(hint=PLACES_HINT):
    r = cache.fitted(cur.data, cur.spec, cur.query)
ds, model = cur.data.dataset, r.model
v = state.view()
frame = v.frame if v.frame is not None and 0 <= v.frame < ds.n_frames else r.first_scored_frame()
if v.frame is not None and v.frame != frame:
    st.warning(f"frame={v.frame} is not a frame of {ds.name!r} (0 to {ds.n_frames - 1}): showing frame {frame} "
               "instead.", icon=":material/warning:")
    state.update(frame=None)

top = st.columns([2, 3, 2])
top[0].selectbox("Query traversal (database: every other one)", list(ds.traversals),
                 **state.bind("w_query", "query", cur.query))
slide, enter = top[1].columns([4, 1], vertical_alignment="bottom")
slide.slider("Query frame", 0, ds.n_frames - 1, **state.bind("w_frame", "frame", frame))
enter.number_input("frame", 0, ds.n_frames - 1, step=1, help="Type a frame number (the slider moves along)",
                   **state.bind("w_frame_number", "frame", frame))
with top[2]:
    k, user_theta = threshold_controls()

methods = [*LIVE_METHODS, *(["global-user"] if user_theta is not None else [])]
finder = st.columns([2, 2, 1, 3])
kind = finder[0].selectbox("Find queries that were", list(FIND_KINDS), key="w_find_kind")
under = finder[1].selectbox("under", methods, index=methods.index("margin-weighted"), key="w_find_method",
                            format_func=lambda key: METHODS_BY_KEY[key].label)


def jump() -> None:
    """Move to the next query frame (after the current one, wrapping) that ``under`` rejected / got wrong."""
    jump_to_next(lambda: cache.find(cur.data, cur.spec, cur.query, after=frame, kind=kind, method=under, k=k,
                                    user_theta=user_theta),
                 frame, ds.n_frames, kind=kind, label=METHODS_BY_KEY[under].label, unit="query frame", short="frame")


finder[2].button("next ▶", key="w_find_next", on_click=jump, help="Jump to the next such query frame")
note = st.session_state.pop("find_none", None)
if note:
    finder[3].info(note)

image = ds.image_index(cur.query, frame)
with stop_on_input_error(hint="Change k or your global θ above, or group/step on the **Places** page."):
    dec = cache.decision(cur.data, cur.spec, cur.query, image, k=k, user_theta=user_theta)
cands = top_candidates(dec, SHOWN_CANDIDATES)


def image_name(i: int) -> str:
    """A dataset image as "<traversal> · frame N"."""
    return f"{ds.traversals[ds.image_traversal[i]]} · frame {ds.image_frame[i]}"


def describe(key: str) -> str:
    """The decision in words: images by traversal and frame, a frame between places not scored."""
    return describe_query(dec, key, model, ds)


left, right = st.columns([1, 2])
with left:
    st.image(cache.thumbnail(ds.image_paths[image], 240), width="stretch",
             caption=f"query: {cur.query} · frame {frame}")
    if len(dec.true_places):
        st.markdown(f"**Right place:** {', '.join(f'P{p}' for p in dec.true_places)} (frame {frame} is in it).")
    else:
        st.markdown(between_note(frame))
    pair = st.session_state.get("picked_pair")
    if pair and pair[0] == image:
        db = pair[1]
        db_place = int(r.places.image_place[db])
        st.caption(f"Opened from the similarity matrix: database image {image_name(db)} "
                   f"({'place P' + str(db_place) if db_place >= 0 else 'between places'}).")
with right:
    st.markdown("**The answer under each method**")
    lines = []
    for key in ["image-baseline", *methods]:
        ok = {Verdict.RIGHT: ":green[:material/check_circle:]", Verdict.BETWEEN: ":gray[:material/remove:]"}.get(
            query_verdict(dec, key), ":red[:material/cancel:]")
        lines.append(f"- {ok} **{METHODS_BY_KEY[key].label}**: {describe(key)}")
    st.markdown("\n".join(lines))

show_candidates(dec, methods, cands, describe, query_image=ds.image_paths[image],
                query_caption=f"query: {image_name(image)}",
                database_image=lambda i: (ds.image_paths[int(model.images[i])], image_name(int(model.images[i]))))
