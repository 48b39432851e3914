"""Thresholds page: one place's negative Gaussian mixture, its scores and every threshold."""

import pandas  # noqa: F401  # before plotly: plotly.py#2433
import numpy as np
import streamlit as st

from vpr_explorer.method.thresholds import THRESHOLD_LABELS, ThresholdMethod
from vpr_explorer.views import plots
from vpr_explorer.views.numbers import database_label, query_label

from vpr_explorer.app.ui import cache, state
from vpr_explorer.app.ui.controls import threshold_controls
from vpr_explorer.app.ui.current import current
from vpr_explorer.app.ui.feedback import PLACES_HINT, stop_on_input_error
from vpr_explorer.app.ui.routing import ensure_routed

ensure_routed(__file__)

# images shown per row (one row per database traversal, one for the queries); a bigger place says how many more
THUMBNAILS = 8


def share(x: float) -> str:
    """A share in %, "—" when there is nothing to count (NaN), never "nan%"."""
    return "—" if not np.isfinite(x) else f"{x:.0%}"


def number(x: float, fmt: str = ".3f") -> str:
    """A value, "—" when it is missing (NaN), never "nan" or "None"."""
    return "—" if not np.isfinite(x) else f"{x:{fmt}}"


# the figure bins the place's negative scores (millions on a large database): built once per setting
@st.cache_resource(show_spinner=False, max_entries=8)
def mixture(key: str, places: tuple, place: int, k: float, method: str, user_theta, _detail):
    return plots.mixture_figure(_detail, k=k, method=method, user_theta=user_theta)


st.title("Thresholds: where θ_p sits")
with stop_on_input_error():
    cur = current()
with stop_on_input_error(hint=PLACES_HINT):
    fitted = cache.fitted(cur.data, cur.places)
ds, model = cur.dataset, fitted.model
theta_w = model.theta["weighted"]
order = np.argsort(theta_w, kind="stable")
v = state.view()
place = v.place if v.place is not None and 0 <= v.place < model.n_places else int(order[len(order) // 2])
if v.place is not None and v.place != place:
    st.warning(f"place={v.place} is not a place here ({model.n_places} places, 0 to {model.n_places - 1}): showing "
               f"place {place} instead.", icon=":material/warning:")
    state.update(place=None)


def pick_from_overview() -> None:
    points = st.session_state["overview"].selection.points
    if points and isinstance(points[0].get("customdata"), (int, float)):
        state.update(place=int(points[0]["customdata"]))


controls, overview = st.columns([1, 3])
with controls:
    st.selectbox("Place", list(range(model.n_places)),
                 format_func=lambda p: f"place {p} (θ_p {number(theta_w[p])})",
                 help="A place is a set of database images (Places page). Its threshold θ_p is fitted on the "
                      "database images only, from their scores against every other place; the list shows each "
                      "place's weighted θ_p. You can also click a place in the overview.",
                 **state.bind("w_place", "place", place))
    st.radio("θ_p(k) built on", [m.value for m in ThresholdMethod], index=1, horizontal=True, key="w_method",
             format_func=lambda m: f"θ_p {m}",
             help="Which θ_p the family θ_p(k) = θ_p + k·s_p starts from: **simple** is the plain mean of the "
                  "place's negative means μᵢ; **weighted** (the paper's eq. 4, normalised) weights each μᵢ by "
                  "wᵢτᵢ², τᵢ = 1/σᵢ, so images with tight negative scores count more.")
    k, user_theta = threshold_controls()
with overview:
    st.plotly_chart(plots.places_overview(theta_w, model.positive_mean, model.negative_mean, selected=place),
                    key="overview", on_select=pick_from_overview, selection_mode="points", width="stretch")

with stop_on_input_error(hint=PLACES_HINT):
    d = cache.detail(cur.data, cur.places, place)
method = st.session_state.get("w_method", ThresholdMethod.WEIGHTED.value)
theta_k = d.theta_k(k, method)

fig_col, img_col = st.columns([5, 3])
with fig_col:
    st.plotly_chart(mixture(cur.data.key, cache.places_key(cur.places), place, k, method, user_theta, d),
                    key="mixture", width="stretch")
with img_col:
    st.markdown(f"**Place {place}**: {len(d.images)} database images and {len(d.query_images)} queries whose right "
                "places include it (raw_p: the query's best score against the place)")
    raw_of = dict(zip(d.query_images.tolist(), d.query_raw.tolist()))
    rows = [d.images[ds.database_traversal[d.images] == t] for t in np.unique(ds.database_traversal[d.images])]
    if len(d.query_images):
        rows.append(d.query_images)
    for row in rows:
        for col, i in zip(st.columns(min(len(row), THUMBNAILS)), row[:THUMBNAILS]):
            i = int(i)
            caption = (f"{database_label(ds, i)} (database)" if i < ds.n_database else
                       f"{query_label(ds, i - ds.n_database)} (query, raw_p {number(raw_of[i])})")
            col.image(cache.thumbnail(ds.image_paths[i]), width="stretch", caption=caption)
        if len(row) > THUMBNAILS:
            st.caption(f"… and {len(row) - THUMBNAILS:,} more of this row.")

st.subheader("The teaching point")
m = st.columns(4)
NONE = " Shown as — when there is nothing to count."
m[0].metric("negative scores ≥ θ_p weighted", share(d.share_negatives_above(d.theta['weighted'])),
            help="A negative score is s(i, j) between a database image i of this place and a database image j of "
                 "another place; this is the share of them at or above the weighted θ_p, i.e. how much of the "
                 "other places' evidence the threshold alone would keep." + NONE)
m[1].metric(f"negative scores ≥ θ_p(k={k:g})", share(d.share_negatives_above(theta_k)),
            help=f"The same share at θ_p(k) = θ_p + k·s_p with k = {k:g} (s_p: the standard deviation of the "
                 "place's negative mixture): raising k moves the threshold up through the negatives." + NONE)
m[2].metric("same-place scores < θ_p weighted", share(d.share_positives_below(d.theta['weighted'])),
            help="A same-place score is s(i, j) between two database images of this place (other traversals of the "
                 "same spot, or neighbours); this is the share of those pairs below the weighted θ_p, i.e. right "
                 "matches the threshold would drop. A place with one database image has no pair." + NONE)
m[3].metric(f"own queries dropped at θ_p(k={k:g})", share(d.share_queries_below(theta_k)),
            help="raw_p of a query is its best score against this place's database images; this is the share of "
                 "the queries whose right places include this place (for aligned traversals: the query "
                 "traversal's frames in it) whose raw_p is below θ_p(k), for which the right place is dropped "
                 "(a wrong reject or a wrong answer)." + NONE)
st.markdown(
    f"θ_p is a weighted **mean of the negative means μᵢ**: it sits in the *centre* of the scores against other "
    f"places (here {share(d.share_negatives_above(d.theta['weighted']))} of them lie above it), not above them. On its "
    "own it therefore drops few places and rejects almost no query of an unknown place; what it mostly does is "
    f"shift each place's margin raw_p − θ_p. Moving k up (θ_p + k·s_p, s_p = {number(d.spread)} here; this place's "
    f"adaptive k = {number(d.k_adaptive, '.2f')}) pushes the threshold into the gap between negatives and same-place "
    "scores: that is where rejection starts to pay, at the price of dropping some right places."
)
st.info(
    f"**{THRESHOLD_LABELS[ThresholdMethod.SIMPLE]}** (here {number(d.theta['simple'], '.4f')}).  \n"
    f"**{THRESHOLD_LABELS[ThresholdMethod.WEIGHTED]}** (here {number(d.theta['weighted'], '.4f')}).  \n"
    "The weighted form is the *normalised* one: read literally, the paper's eq. 4 divides by Σ τⱼ² but not by the "
    "weights, so with wᵢ = 1/n the weights sum to 1/n and θ_p would shrink with the number of images instead of "
    "being a weighted mean of the μᵢ. The authors' code normalises by Σ wⱼτⱼ², which is what is computed here: "
    "images whose negative scores are tight (small σᵢ) count more.",
    icon=":material/info:",
)
