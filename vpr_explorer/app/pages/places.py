"""Places page: group/step sliders, both readings side by side, and the live consequences.

A database/queries dataset (``layouts.RetrievalDataset``) gets its own page body
(``ui.retrieval_places``): places from frames or metres, and the map of its positions.
"""

import pandas  # noqa: F401  # before plotly: plotly.py#2433

import streamlit as st

from vpr_explorer.views import plots
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import READING_LABELS, PlaceSpec, Reading, make_places
from vpr_explorer.views.traversal import LIVE_METHODS

from vpr_explorer.app.ui import cache, group_step, retrieval_places, state
from vpr_explorer.app.ui.current import current
from vpr_explorer.app.ui.feedback import show_rejected, stop_on_input_error
from vpr_explorer.app.ui.routing import ensure_routed

ensure_routed(__file__)

st.title("Places: group and step")
show_rejected()
with stop_on_input_error():
    cur = current()
if cur.retrieval is not None:
    retrieval_places.render(cur)
    st.stop()
st.markdown(
    "A **place** is `group` consecutive frames of every traversal; the paper's text and its code read `step` "
    "differently, so both readings are shown side by side. Descriptors belong to images, so a move here only "
    "relabels images and refits the closed-form statistics: nothing is re-extracted."
)
ds = cur.data.dataset

if cur.spec is None:
    st.info("This dataset names its places in its file names (Place####_Cond##_G##): group/step do not apply.")
    spec = None
else:
    spec = cur.spec

    def check(**change) -> None:
        make_places(ds, PlaceSpec(**{"group": spec.group, "step": spec.step, "reading": spec.reading, **change}))

    def check_group(g) -> None:
        group_step.refuse_overlap(lambda: check(group=g), group_field="group", step_field="step", group=g,
                                  step=spec.step, stride=spec.reading is Reading.STRIDE)

    group_step.offer_fix(lambda g: check(group=g, step=g))
    c1, c2, c3 = st.columns([2, 2, 3])
    c1.slider("group: frames per place", 1, group_step.group_slider_top(spec.group, ds.n_frames),
              **state.bind("w_group", "group", spec.group, validate=check_group))
    c2.slider("step: frames from one place to the next", 1, group_step.step_slider_top(spec.step, ds.n_frames),
              **state.bind("w_step", "step", spec.step, validate=lambda s: check(step=s)))
    c3.radio("reading of step", [r.value for r in Reading], format_func=lambda r: READING_LABELS[Reading(r)],
             **state.bind("w_reading", "reading", spec.reading.value, validate=lambda r: check(reading=r)))

st.selectbox("Query traversal (the database is every other traversal)", list(ds.traversals),
             **state.bind("w_query", "query", cur.query))

if spec is not None:
    st.subheader(f"Both readings of group {spec.group}, step {spec.step}")
    for col, reading in zip(st.columns(2), Reading):
        with col:
            in_use = reading is spec.reading
            st.markdown(f"{READING_LABELS[reading]}{' — **in use**' if in_use else ''}")
            try:
                alt = make_places(ds, PlaceSpec(spec.group, spec.step, reading))
            except VPRInputError as exc:
                st.warning(f"{exc}", icon=":material/warning:")
                continue
            (st.success if in_use else st.info)(f"{alt.describe()}; {int((alt.frame_place < 0).sum())} of "
                                                f"{ds.n_frames} frames skipped")
            st.plotly_chart(plots.route_figure(alt.frame_place, ds.traversals), key=f"route_{reading.value}",
                            width="stretch")

with stop_on_input_error(hint="Change group or step above."):
    r, seconds = cache.regrouped_timed(cur.data, spec, cur.query)

st.subheader("Live consequences")
decided = (f"a seeded random sample of **{len(r.frames):,} of the {r.n_frames:,} frames** of **{r.query}** is decided "
           f"(deciding all would take {r.n_frames:,} × {len(r.model.images):,} similarities; the Query inspector "
           "decides any frame you pick)" if r.sampled else f"every frame of **{r.query}** is a query")
st.caption(
    f"Database/traversal model: thresholds from **{' + '.join(r.database)}** only; {decided} "
    f"({r.n_scored:,} fall in a place and are scored; frames between places are left out). "
    f"Recomputed in {1000 * seconds:.0f} ms for this group/step (then cached), descriptors untouched."
)
m = st.columns(5)
m[0].metric("places", r.places.n_places)
m[1].metric("images per place", int(r.places.images_per_place.max()))
m[2].metric("place-level R@1", f"{r.recall1['place-baseline']:.0%}")
m[3].metric("margin, weighted θ R@1", f"{r.recall1['margin-weighted']:.0%}",
            delta=f"{100 * (r.recall1['margin-weighted'] - r.recall1['place-baseline']):+.0f} pts")
m[4].metric("raw, weighted θ R@1", f"{r.recall1['raw-weighted']:.0%}",
            delta=f"{100 * (r.recall1['raw-weighted'] - r.recall1['place-baseline']):+.0f} pts")
left, right = st.columns(2)
left.plotly_chart(plots.theta_histogram(r.model.theta, r.model.auto), key="theta_hist", width="stretch")
right.plotly_chart(plots.recall_bars({k: r.recall1[k] for k in LIVE_METHODS},
                                     rejected={k: r.rejected[k] for k in LIVE_METHODS}),
                   key="recall_live", width="stretch")
if ds.positions is not None:
    st.plotly_chart(plots.route_figure(r.places.frame_place, [r.query], ds.positions,
                                       title="The places on the route map"), key="route_map", width="stretch")
