"""The map of a dataset with positions: database images coloured by place, the queries, one query's answer.

Database images are drawn coloured by place (grey between places), the queries as markers,
and one query (``view.frame``) with its positive radius, its positives and its candidate
places; the view opens on that query's neighbourhood (``maps.neighbourhood``). A click on a
query selects it (the Query inspector then opens on it), and so does a click on a database
dot that a query's cross lies on (``maps.picked_query``). For aligned
traversals with positions the database images are the frames of the database traversals
(one dot per traversal at each frame's position).
"""

from __future__ import annotations

import numpy as np
import streamlit as st

from vpr_explorer.views import maps
from vpr_explorer.views.numbers import RetrievalFitted, query_label, radius_of
from vpr_explorer.views.numbers import top_candidates

from vpr_explorer.app.ui import cache, state
from vpr_explorer.app.ui.current import Current
from vpr_explorer.app.ui.feedback import stop_on_input_error
from vpr_explorer.app.ui.routing import page_file

MAP_CANDIDATES = 5
"""Candidate places outlined on the map: the selected query's best by raw_p."""
MAP_METHOD = "margin-weighted"
"""The method whose answer the map marks: the paper's."""
MAP_DATABASE = 20_000
"""Database images the map draws at most: beyond, those nearest the selected query (and its candidate places')."""


def map_window(ds, fitted: RetrievalFitted, query: int, places: np.ndarray) -> np.ndarray | None:
    """Database positions the map draws: all (``None``) up to ``MAP_DATABASE``, else the ``MAP_DATABASE`` nearest
    the selected query plus the images of ``places`` (its candidates and answer), ascending."""
    if ds.n_database <= MAP_DATABASE:
        return None
    dist = np.hypot(*(ds.database_xy - ds.query_xy[query]).T)
    near = np.argpartition(dist, MAP_DATABASE - 1)[:MAP_DATABASE]
    return np.union1d(near, np.flatnonzero(np.isin(fitted.database_place, places)))


# a resource (never mutated: st.plotly_chart serialises a copy): the figure of 20,000 database images and
# every query is built once per (places, query, candidates), not on every rerun of the page
@st.cache_resource(show_spinner=False, max_entries=4)
def _map_figure(key: str, places: tuple, q: int, candidates: tuple, answer: int, _ds, _fitted):
    """The map's figure, the database positions it draws (``map_window``; ``None``: all) and its origin."""
    ds, fitted = _ds, _fitted
    positives = ds.ground_truth.positives(q)
    shown = map_window(ds, fitted, q, np.r_[candidates, [answer] if answer >= 0 else []].astype(np.int64))
    db_xy, db_place = ((ds.database_xy, fitted.database_place) if shown is None
                       else (ds.database_xy[shown], fitted.database_place[shown]))
    radius = radius_of(ds)
    fig = maps.layout_map(db_xy, db_place, ds.query_xy, selected=q, radius=radius,
                          positives=positives if shown is None else np.searchsorted(shown, positives),
                          candidates=list(candidates), answer=answer,
                          title=f"{fitted.n_places} places; query {q}{' with its radius' if radius else ''} and its "
                                f"{len(candidates)} best candidate places (outlined)")
    return fig, shown, maps.map_origin(db_xy, ds.query_xy)


def render(cur: Current, fitted: RetrievalFitted) -> None:
    """The map of positions, with the selected query (``view.frame``) and its radius and candidates."""
    ds = cur.dataset
    v = state.view()
    q = v.frame if v.frame is not None and 0 <= v.frame < ds.n_queries else 0
    st.subheader("The map: database images by place, and the queries")
    c1, c2 = st.columns([1, 3])
    c1.number_input("selected query", 0, ds.n_queries - 1, step=1, help="Or click a query (×) on the map.",
                    **state.bind("w_map_query", "frame", q))
    with stop_on_input_error(hint="Change group or step above."):
        dec = cache.decision(cur.data, cur.places, q, k=v.k, user_theta=v.theta)
    candidates = top_candidates(dec, MAP_CANDIDATES)[:MAP_CANDIDATES]
    answer = dec.answer(MAP_METHOD)
    positives = ds.ground_truth.positives(q)
    right = ", ".join(f"P{p}" for p in dec.true_places) or "none"
    c2.markdown(f"**{query_label(ds, q)}** (query {q}): {len(positives)} positive database image(s) "
                f"({ds.ground_truth.description}); right place(s): {right} ({fitted.query_status(q)}); the paper's "
                f"method ({MAP_METHOD}) answers {'P' + str(answer) if answer >= 0 else 'nothing (rejected)'}.")

    fig, shown, origin = _map_figure(cur.data.key, cache.places_key(cur.places), q,
                                     tuple(int(c) for c in candidates), int(answer), ds, fitted)

    def pick() -> None:
        picked = maps.picked_query(st.session_state["layout_map"].selection.points, ds.query_xy, origin,
                                   near=radius_of(ds))
        if picked is not None and 0 <= picked < ds.n_queries:
            state.update(frame=picked)

    st.plotly_chart(fig, key="layout_map", on_select=pick, selection_mode="points", width="stretch")
    st.caption("Coloured dots: database images, one colour per place (colours repeat); grey: database images "
               "between places (skipped by group/step); ×: queries; ★: the selected query, the dashed circle its "
               "radius, green rings its positives (for aligned traversals: the database frames at its frame); black outlines: its "
               "best candidate places by raw_p; red outline: the place the paper's method answered. Plain metres, no "
               "map tiles. The view opens on the selected query's neighbourhood: zoom out, or double-click the map, "
               "for all of it. A click on a ×, or on a dot under one, selects that query."
               + ("" if shown is None else f" Of the {ds.n_database:,} database images the map draws the "
                  f"{MAP_DATABASE:,} nearest the selected query and its candidate places' ({len(shown):,} in all); "
                  "choose another query to move the window."))
    if st.button("Open this query in the Query inspector", key="w_map_inspect", icon=":material/search:"):
        st.switch_page(page_file("inspector"))
