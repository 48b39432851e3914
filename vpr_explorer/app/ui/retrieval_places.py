"""The Places page of a database/queries dataset: places from frames or metres, their consequences, the map.

Group/step count database images in listed order (``frames``), or metres along the database
route (``route``) or over a square lattice (``lattice``) where the layout has positions; a
manifest with a ``place`` column fixes its places. The map draws the database images
coloured by place (grey between places), the queries, and one query with its positive
radius, its positives and its candidate places; a click on a query selects it (the Query
inspector then opens on it).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import streamlit as st

from vpr_explorer.views import maps
from vpr_explorer.views import plots
from vpr_explorer.views import database_queries as retrieval_views
from vpr_explorer.method.places import READING_LABELS, PlaceGeometry, Reading, retrieval_places
from vpr_explorer.views.database_queries import geometries, geometry_label, query_label, radius_of
from vpr_explorer.views.traversal import LIVE_METHODS, top_candidates

from vpr_explorer.app.ui import cache, group_step, state
from vpr_explorer.app.ui.current import Current, effective_places
from vpr_explorer.app.ui.feedback import stop_on_input_error
from vpr_explorer.app.ui.routing import page_file

MAP_CANDIDATES = 5
"""Candidate places outlined on the map: the selected query's best by raw_p."""
MAP_METHOD = "margin-weighted"
"""The method whose answer the map marks: the paper's."""
MAP_DATABASE = 20_000
"""Database images the map draws at most: beyond, those nearest the selected query (and its candidate places')."""


def map_window(ds, fitted, query: int, places: np.ndarray) -> np.ndarray | None:
    """Database positions the map draws: all (``None``) up to ``MAP_DATABASE``, else the ``MAP_DATABASE`` nearest
    the selected query plus the images of ``places`` (its candidates and answer), ascending."""
    if ds.n_database <= MAP_DATABASE:
        return None
    dist = np.hypot(*(ds.database_xy - ds.query_xy[query]).T)
    near = np.argpartition(dist, MAP_DATABASE - 1)[:MAP_DATABASE]
    return np.union1d(near, np.flatnonzero(np.isin(fitted.database_place, places)))


# a resource (returned as is, never mutated): its negative scores are n_p × the database images in
# places (millions of floats on a large database), which st.cache_data would copy on every rerun
@st.cache_resource(show_spinner="Scoring the place's images…", max_entries=8)
def _place_detail(key: str, places: tuple, place: int, _data, _fitted):
    return retrieval_views.place_detail(_fitted, _data.descriptors, place)


# the figure bins the place's negative scores (n_p × the database images in places: millions): built once
@st.cache_resource(show_spinner=False, max_entries=8)
def _mixture_figure(key: str, places: tuple, place: int, k: float, user_theta, _detail):
    return plots.mixture_figure(_detail, k=k, user_theta=user_theta)


def _one_place(cur: Current, fitted) -> None:
    """One place: its negative mixture, its images' negative scores (their own rows only) and its thresholds."""
    v = state.view()
    model = fitted.model
    place = v.place if v.place is not None and 0 <= v.place < fitted.n_places else int(np.median(model.places))
    st.subheader("One place: its negative mixture and thresholds")
    c1, c2 = st.columns([1, 3])
    c1.number_input("place", 0, fitted.n_places - 1, step=1,
                    help="A place's θ_p comes from the scores of its database images against the database images "
                         "of every other place; only this place's rows are scored here.",
                    **state.bind("w_place_one", "place", place))
    with stop_on_input_error(hint="Choose another place."):
        detail = _place_detail(cur.data.key, cache.places_key(cur.places), int(place), cur.data, fitted)
    c2.markdown(f"**P{place}**: {len(detail.images)} database image(s), {detail.negatives.size:,} negative scores "
                f"(against the {len(model.images) - len(detail.images):,} database images of other places); "
                f"θ_p simple {detail.theta['simple']:.4f}, weighted {detail.theta['weighted']:.4f}, spread "
                f"s_p {detail.spread:.4f}; automatic global θ {detail.auto:.4f}.")
    st.plotly_chart(_mixture_figure(cur.data.key, cache.places_key(cur.places), int(place), v.k, v.theta, detail),
                    key="place_mixture", width="stretch")


def _controls(cur: Current) -> None:
    """Geometry, group/step (frames or metres) and reading, each checked before it replaces the view's."""
    ds, places = cur.retrieval, cur.places
    offered = geometries(ds)
    if not offered:
        st.info(f"{ds.name!r} names the place of every database image ({ds.layout.value}'s place column): "
                "group/step do not apply.", icon=":material/info:")
        return
    if len(offered) > 1:
        st.radio("places from", [g.value for g in offered], format_func=lambda g: geometry_label(PlaceGeometry(g)),
                 horizontal=False, help="Frames: the database images in listed order (what `vpr-explorer list` "
                                        "prints). Route: metres along the database in its listed order. Lattice: "
                                        "square cells over the plane (unordered data such as Pittsburgh, SF-XL).",
                 **state.bind("w_geometry", "geometry", places.geometry.value,
                              validate=lambda g: _check(ds, geometry=g)))
    c1, c2, c3 = st.columns([2, 2, 3])
    if places.spec is not None:
        spec = places.spec

        def check_group(g) -> None:
            group_step.refuse_overlap(lambda: _check(ds, group=g), group_field="group", step_field="step",
                                      group=g, step=spec.step, stride=spec.reading is Reading.STRIDE)

        group_step.offer_fix(lambda g: _check(ds, group=g, step=g))
        c1.slider("group: database images per place", 1, group_step.group_slider_top(spec.group, ds.n_database),
                  **state.bind("w_group", "group", spec.group, validate=check_group))
        c2.slider("step: database images from one place to the next", 1,
                  group_step.step_slider_top(spec.step, ds.n_database),
                  **state.bind("w_step", "step", spec.step, validate=lambda x: _check(ds, step=x)))
        reading = spec.reading
    else:
        metric = places.metric

        def check_group_m(g) -> None:
            group_step.refuse_overlap(lambda: _check(ds, group_m=g), group_field="group_m",
                                      step_field="step_m", group=g, step=metric.step,
                                      stride=metric.reading is Reading.STRIDE, unit=" m")

        group_step.offer_fix(lambda g: _check(ds, group_m=g, step_m=g))
        c1.number_input("group (m): metres per place", *group_step.GROUP_M_RANGE, step=5.0, format="%g",
                        **state.bind("w_group_m", "group_m", float(metric.group), validate=check_group_m))
        c2.number_input("step (m): metres from one place to the next", *group_step.STEP_M_RANGE,
                        step=5.0, format="%g",
                        **state.bind("w_step_m", "step_m", float(metric.step),
                                     validate=lambda x: _check(ds, step_m=x)))
        reading = metric.reading
    c3.radio("reading of step", [r.value for r in Reading], format_func=lambda r: READING_LABELS[Reading(r)],
             **state.bind("w_reading", "reading", reading.value,
                          validate=lambda r: _check(ds, reading=r)))


def _check(ds, **changes) -> None:
    """The places of ``ds`` if the view's fields changed so (``VPRInputError`` when they overlap or leave fewer than 2)."""
    p = effective_places(dataclasses.replace(state.view(), **changes), ds)
    retrieval_places(ds, p.spec, p.metric)


# a resource (never mutated: st.plotly_chart serialises a copy): the figure of 20,000 database images and
# every query is built once per (places, query, candidates), not on every rerun of the page
@st.cache_resource(show_spinner=False, max_entries=4)
def _map_figure(key: str, places: tuple, q: int, candidates: tuple, answer: int, _ds, _fitted):
    """The map's figure and the database positions it draws (``map_window``; ``None``: all)."""
    ds, fitted = _ds, _fitted
    positives = ds.ground_truth.positives(q)
    shown = map_window(ds, fitted, q, np.r_[candidates, [answer] if answer >= 0 else []].astype(np.int64))
    db_xy, db_place = ((ds.database_xy, fitted.database_place) if shown is None
                       else (ds.database_xy[shown], fitted.database_place[shown]))
    fig = maps.layout_map(db_xy, db_place, ds.query_xy, selected=q, radius=radius_of(ds),
                          positives=positives if shown is None else np.searchsorted(shown, positives),
                          candidates=list(candidates), answer=answer,
                          title=f"{fitted.n_places} places; query {q} with its radius and its {len(candidates)} best "
                                "candidate places (outlined)")
    return fig, shown


def _map(cur: Current, fitted) -> None:
    """The map of positions, with the selected query (``view.frame``) and its radius and candidates."""
    ds = cur.retrieval
    v = state.view()
    q = v.frame if v.frame is not None and 0 <= v.frame < ds.n_queries else 0
    st.subheader("The map: database images by place, and the queries")
    c1, c2 = st.columns([1, 3])
    c1.number_input("selected query", 0, ds.n_queries - 1, step=1, help="Or click a query (×) on the map.",
                    **state.bind("w_map_query", "frame", q))
    with stop_on_input_error(hint="Change group or step above."):
        dec = cache.retrieval_decision(cur.data, cur.places, q, k=v.k, user_theta=v.theta)
    candidates = top_candidates(dec, MAP_CANDIDATES)[:MAP_CANDIDATES]
    answer = dec.answer(MAP_METHOD)
    positives = ds.ground_truth.positives(q)
    status = fitted.query_status(q)
    right = ", ".join(f"P{p}" for p in dec.true_places) or "none"
    c2.markdown(f"**{query_label(ds, q)}** (query {q}): {len(positives)} positive database image(s) "
                f"({ds.ground_truth.description}); right place(s): {right} ({status}); the paper's method "
                f"({MAP_METHOD}) answers {'P' + str(answer) if answer >= 0 else 'nothing (rejected)'}.")

    def pick() -> None:
        points = st.session_state["layout_map"].selection.points
        picked = [p.get("customdata") for p in points if isinstance(p.get("customdata"), (int, float))]
        if picked:
            state.update(frame=int(picked[0]))

    fig, shown = _map_figure(cur.data.key, cache.places_key(cur.places), q, tuple(int(c) for c in candidates),
                             int(answer), ds, fitted)
    st.plotly_chart(fig, key="layout_map", on_select=pick, selection_mode="points", width="stretch")
    st.caption("Coloured dots: database images, one colour per place (colours repeat); grey: database images between "
               "places (skipped by group/step); ×: queries; ★: the selected query, the dashed circle its radius, green "
               "rings its positives; black outlines: its best candidate places by raw_p; red outline: the place the "
               "paper's method answered. Plain metres, no map tiles."
               + ("" if shown is None else f" Of the {ds.n_database:,} database images the map draws the "
                  f"{MAP_DATABASE:,} nearest the selected query and its candidate places' ({len(shown):,} in all); "
                  "choose another query to move the window."))
    if st.button("Open this query in the Query inspector", key="w_map_inspect", icon=":material/search:"):
        st.switch_page(page_file("inspector"))


def render(cur: Current) -> None:
    """The Places page body for a database/queries dataset."""
    ds = cur.retrieval
    st.caption(f"{ds.describe()}. A place is made of **database** images; queries are decided against them, a "
               "query's right places being those that hold one of its right database images.")
    _controls(cur)
    with stop_on_input_error(hint="Change group or step above."):
        fitted = cache.retrieval_fitted(cur.data, cur.places)
        ov, seconds = cache.retrieval_overview_timed(cur.data, cur.places)

    st.subheader("Live consequences")
    decided = (f"a seeded random sample of **{len(ov.queries):,} of the {ov.n_queries:,} queries** is decided (the "
               "Query inspector decides any query you pick)" if ov.sampled else f"all {ov.n_queries:,} queries are decided")
    st.caption(f"{fitted.describe()}. Thresholds from the database images in places only; {decided}: "
               f"{ov.n_scored:,} have a right place and are scored, {ov.n_unknown:,} have no right database image "
               f"at all (unknown places: rejecting them is right), the others' right images lie between places. "
               f"Recomputed in {1000 * seconds:.0f} ms for these places (then cached), descriptors untouched.")
    per = np.bincount(fitted.model.places, minlength=fitted.n_places)
    m = st.columns(5)
    m[0].metric("places", fitted.n_places)
    m[1].metric("database images per place", f"{per.min()}" if per.min() == per.max() else f"{per.min()}–{per.max()}")
    m[2].metric("place-level R@1", f"{ov.recall1['place-baseline']:.0%}")
    m[3].metric("margin, weighted θ R@1", f"{ov.recall1['margin-weighted']:.0%}",
                delta=f"{100 * (ov.recall1['margin-weighted'] - ov.recall1['place-baseline']):+.0f} pts")
    unknown = ov.unknown_rejected["margin-weighted"]
    m[4].metric("unknown rejected", "—" if np.isnan(unknown) else f"{unknown:.0%}",
                help=f"Share of the {ov.n_unknown:,} unknown-place queries (no right database image: the open set) "
                     "that the paper's method (margin, weighted θ) rejects; — when there is none.")
    left, right = st.columns(2)
    left.plotly_chart(plots.theta_histogram(fitted.model.theta, fitted.model.auto), key="theta_hist", width="stretch")
    right.plotly_chart(plots.recall_bars({k: ov.recall1[k] for k in LIVE_METHODS},
                                         rejected={k: ov.rejected[k] for k in LIVE_METHODS},
                                         title="Recall@1 of the queries with a right place"),
                       key="recall_live", width="stretch")
    _one_place(cur, fitted)
    if ds.database_xy is not None and ds.query_xy is not None:
        _map(cur, fitted)
    else:
        st.info(f"The {ds.layout.value} layout has no positions: there is no map. The Query inspector shows any "
                "query with its right places.", icon=":material/info:")

