"""Places page: how database images become places, both readings of step side by side, the live consequences.

One body for every layout: the place controls the dataset offers (``ui.group_step``), the
query traversal of aligned traversals, both readings of group/step in frames, the queries
decided under every method, and the map where the layout has positions (``ui.place_map``).
Beside group/step, the places discovered online along the route (``ui.bench.discovery_section``)
where the database is one route in order, and the reason where it is not.
"""

import pandas  # noqa: F401  # before plotly: plotly.py#2433
import numpy as np
import streamlit as st

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import PlaceSpec, Reading, frame_places, retrieval_places
from vpr_explorer.views import plots
from vpr_explorer.views.numbers import LIVE_METHODS

from vpr_explorer.app.ui import bench as bench_ui, cache, group_step, place_map, state
from vpr_explorer.app.ui.current import current
from vpr_explorer.app.ui.feedback import show_rejected, stop_on_input_error
from vpr_explorer.app.ui.routing import ensure_routed

ensure_routed(__file__)

st.title("Places: group and step")
show_rejected()
with stop_on_input_error():
    cur = current()
ds = cur.dataset
st.markdown(
    "A **place** is a set of database images; queries are decided against places, a query's right places being "
    "those that hold one of its right database images. The paper's text and its code read `step` differently, so "
    "both readings are shown side by side. Descriptors belong to images, so a move here only relabels images and "
    "refits the closed-form statistics: nothing is re-extracted."
)
st.caption(f"{ds.describe()}.")
group_step.place_controls(ds, cur.places)
if cur.aligned is not None:
    st.selectbox("Query traversal (the database is every other traversal)", list(cur.aligned.traversals),
                 **state.bind("w_query", "query", cur.query))

if cur.spec is not None:
    spec, n, unit = cur.spec, ds.n_frames or ds.n_database, group_step.frame_unit(ds)
    strips = list(cur.aligned.traversals) if cur.aligned is not None else ["database"]
    st.subheader(f"Both readings of group {spec.group}, step {spec.step}")
    for col, reading in zip(st.columns(2), Reading):
        with col:
            in_use = reading is spec.reading
            st.markdown(f"{group_step.reading_label(reading, unit)}{' — **in use**' if in_use else ''}")
            try:
                alt = PlaceSpec(spec.group, spec.step, reading)
                n_places = retrieval_places(ds, alt)[1]
            except VPRInputError as exc:
                st.warning(f"{exc}", icon=":material/warning:")
                continue
            frame_place = frame_places(n, alt)
            (st.success if in_use else st.info)(f"{n_places} places ({alt.describe()}); "
                                                f"{int((frame_place < 0).sum())} of {n:,} {unit} skipped")
            st.plotly_chart(plots.route_figure(frame_place, strips), key=f"route_{reading.value}", width="stretch")

bench_ui.discovery_section(cur)

with stop_on_input_error(hint="Change group or step above."):
    fitted = cache.fitted(cur.data, cur.places)
    ov, seconds = cache.overview_timed(cur.data, cur.places)

st.subheader("Live consequences")
decided = (f"a seeded random sample of **{len(ov.queries):,} of the {ov.n_queries:,} queries** is decided (the "
           "Query inspector decides any query you pick)" if ov.sampled else f"all {ov.n_queries:,} queries are decided")
st.caption(f"{fitted.describe()}. Thresholds from the database images in places only; {decided}: "
           f"{ov.n_scored:,} have a right place and are scored, {ov.n_unknown:,} have no right database image "
           f"at all (unknown places: rejecting them is right), the others' right images lie between places. "
           f"Recomputed in {1000 * seconds:.0f} ms for these places (then cached), descriptors untouched.")
per = np.bincount(fitted.model.places, minlength=fitted.n_places)
m = st.columns(6 if ov.n_unknown else 5)
m[0].metric("places", fitted.n_places)
m[1].metric("database images per place", f"{per.min()}" if per.min() == per.max() else f"{per.min()}–{per.max()}")
m[2].metric("place-level R@1", f"{ov.recall1['place-baseline']:.0%}")
for col, key, label in ((m[3], "margin-weighted", "margin"), (m[4], "raw-weighted", "raw")):
    col.metric(f"{label}, weighted θ R@1", f"{ov.recall1[key]:.0%}",
               delta=f"{100 * (ov.recall1[key] - ov.recall1['place-baseline']):+.0f} pts")
if ov.n_unknown:
    m[5].metric("unknown rejected", f"{ov.unknown_rejected['margin-weighted']:.0%}",
                help=f"Share of the {ov.n_unknown:,} unknown-place queries (no right database image: the open set) "
                     "that the paper's method (margin, weighted θ) rejects.")
left, right = st.columns(2)
left.plotly_chart(plots.theta_histogram(fitted.model.theta, fitted.model.auto), key="theta_hist", width="stretch")
right.plotly_chart(plots.recall_bars({k: ov.recall1[k] for k in LIVE_METHODS},
                                     rejected={k: ov.rejected[k] for k in LIVE_METHODS},
                                     title="Recall@1 of the queries with a right place"),
                   key="recall_live", width="stretch")
st.caption("One place's negative mixture, its scores and every threshold: the **Thresholds** page.")
if ds.database_xy is not None and ds.query_xy is not None:
    place_map.render(cur, fitted)
else:
    st.info(f"The {ds.layout.value} layout of {ds.name!r} has no positions: there is no map. The Query inspector "
            "shows any query with its right places.", icon=":material/info:")
