"""Thresholds page: one place's negative Gaussian mixture, its scores and every threshold.

A place is named ``P<id>`` everywhere on the page, as on the others. It is picked from a
searchable list, by its rank of θ_p on a slider (the overview's x order), or by a click in
the overview. Beside the mixture: the place's database images (what θ_p is fitted on) and,
apart, the queries whose right places include it (not in the fit). Under the figures, every
symbol the page uses (μ⁻, s_p, μ⁺, θ_p(k), adaptive k) with this place's values.
"""

import pandas  # noqa: F401  # before plotly: plotly.py#2433
import numpy as np
import streamlit as st

from vpr_explorer.data.layouts import RetrievalDataset
from vpr_explorer.method.stats import SIGMA_FLOOR
from vpr_explorer.method.thresholds import THRESHOLD_LABELS, ThresholdMethod
from vpr_explorer.views import plots
from vpr_explorer.views.numbers import thumbnail_label

from vpr_explorer.app.ui import cache, state
from vpr_explorer.app.ui.controls import threshold_controls
from vpr_explorer.app.ui.current import current
from vpr_explorer.app.ui.feedback import PLACES_HINT, stop_on_input_error
from vpr_explorer.app.ui.routing import ensure_routed

ensure_routed(__file__)

# images shown per row (one row per database traversal, one for the queries); a bigger place says how many more
THUMBNAILS = 8
# a word longer than this cannot wrap under a thumbnail and is cut off (e.g. "@east@north@…@.jpg"): the index instead


def share(x: float) -> str:
    """A share in %, "—" when there is nothing to count (NaN), never "nan%"."""
    return "—" if not np.isfinite(x) else f"{x:.0%}"


def number(x: float, fmt: str = ".3f") -> str:
    """A value, "—" when it is missing (NaN), never "nan" or "None"."""
    return "—" if not np.isfinite(x) else f"{x:{fmt}}"


def count(n: int, one: str, many: str) -> str:
    """``"1 query"``, ``"3 queries"``."""
    return f"{n:,} {one if n == 1 else many}"


def image_caption(dataset: RetrievalDataset, image: int, raw: float = float("nan")) -> str:
    """A thumbnail's caption for dataset image ``image`` (database positions first, then ``n_database`` + query).

    ``thumbnail_label`` with "(database)", or "(query, raw_p R)" for a query: "<traversal> ·
    frame N (database)", "<file name> (database)", or "database image N" / "query N (raw_p R)"
    where the name would be cut off under the thumbnail.
    """
    if image < dataset.n_database:
        label = thumbnail_label(dataset, image)
        return label if label.startswith("database image") else f"{label} (database)"
    q = image - dataset.n_database
    label = thumbnail_label(dataset, q, query=True)
    return f"{label} (raw_p {number(raw)})" if label == f"query {q}" else f"{label} (query, raw_p {number(raw)})"


# the figure bins the place's negative scores (millions on a large database): built once per setting
@st.cache_resource(show_spinner=False, max_entries=8)
def mixture(key: str, places: tuple, place: int, k: float, method: str, user_theta, _detail):
    return plots.mixture_figure(_detail, k=k, method=method, user_theta=user_theta)


# every place's dots and hover texts (thousands on Nordland at group 1): built once per places and selected place
@st.cache_resource(show_spinner=False, max_entries=8)
def overview_figure(key: str, places: tuple, selected: int | None, _model):
    return plots.places_overview(_model.theta["weighted"], _model.positive_mean, _model.negative_mean,
                                 selected=selected)


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
    st.warning(f"place={v.place} is not a place here ({model.n_places} places, P0 to P{model.n_places - 1}): "
               f"showing P{place} instead.", icon=":material/warning:")
    state.update(place=None)
rank = int(np.flatnonzero(order == place)[0])


def pick_from_overview() -> None:
    points = st.session_state["overview"].selection.points
    if points and isinstance(points[0].get("customdata"), (int, float)):
        state.update(place=int(points[0]["customdata"]))


METHOD_CHOICES = [m.value for m in ThresholdMethod]
#: "θ_p(k) built on" in the URL (the page's own parameter), left out at its default
METHOD_PARAM, METHOD_DEFAULT = "thresholds_method", ThresholdMethod.WEIGHTED.value


def method_from_url() -> str:
    """The link's ``thresholds_method`` on a session's first look at the page; a refused one is said and dropped."""
    given = state.page_params().get(METHOD_PARAM, METHOD_DEFAULT)
    if given not in METHOD_CHOICES:
        st.warning(f"{METHOD_PARAM}={given!r}: choose {' or '.join(METHOD_CHOICES)}; using {METHOD_DEFAULT}.",
                   icon=":material/warning:")
        state.set_page_params(**{METHOD_PARAM: None})
        return METHOD_DEFAULT
    return given


def keep_method() -> None:
    value = st.session_state["w_method"]
    state.set_page_params(**{METHOD_PARAM: None if value == METHOD_DEFAULT else value})


if "w_method" not in st.session_state:
    st.session_state["w_method"] = method_from_url()


def pick_by_rank() -> None:
    state.update(place=int(order[st.session_state["w_place_rank"] - 1]))


controls, overview = st.columns([1, 3])
with controls:
    st.selectbox("Place", list(range(model.n_places)),
                 format_func=lambda p: f"P{p} (θ_p {number(theta_w[p])})",
                 help="A place is a set of database images (Places page). Its threshold θ_p is fitted on the "
                      "database images only, from their scores against every other place; the list shows each "
                      "place's weighted θ_p. Type a place's number to find it, walk the places in θ_p order with "
                      "the rank slider under the overview, or click a place in the overview.",
                 **state.bind("w_place", "place", place))
    st.radio("θ_p(k) built on", METHOD_CHOICES, horizontal=True, key="w_method", on_change=keep_method,
             format_func=lambda m: f"θ_p {m}",
             help="Which θ_p the family θ_p(k) = θ_p + k·s_p starts from: **simple** is the plain mean of the "
                  "place's negative means μᵢ; **weighted** (the paper's eq. 4, normalised) weights each μᵢ by "
                  "wᵢτᵢ², τᵢ = 1/σᵢ, so images with tight negative scores count more.")
    k, user_theta = threshold_controls()
with overview:
    # above OVERVIEW_WEBGL_PLACES the figure is the same for every place: built once, and the browser redraws nothing
    many = model.n_places > plots.OVERVIEW_WEBGL_PLACES
    st.plotly_chart(overview_figure(cur.data.key, cache.places_key(cur.places), None if many else place, model),
                    key="overview", on_select=pick_from_overview, selection_mode="points", width="stretch")
    st.session_state["w_place_rank"] = rank + 1
    st.slider("θ_p rank of the place (1: the lowest θ_p)", 1, max(model.n_places, 2), key="w_place_rank",
              on_change=pick_by_rank, disabled=model.n_places < 2,
              help="Drag to walk the places in the overview's order, from the lowest θ_p to the highest.")
    st.caption(f"P{place} ranks {rank + 1:,} of {model.n_places:,} by weighted θ_p"
               + ("" if many else " (tinted in the overview)") + ".")

with stop_on_input_error(hint=PLACES_HINT):
    d = cache.detail(cur.data, cur.places, place)
method = st.session_state["w_method"]
theta_k = d.theta_k(k, method)

fig_col, img_col = st.columns([5, 3])
with fig_col:
    st.plotly_chart(mixture(cur.data.key, cache.places_key(cur.places), place, k, method, user_theta, d),
                    key="mixture", width="stretch")
with img_col:
    st.markdown(f"**P{place}**: {count(len(d.images), 'database image', 'database images')} and "
                f"{count(len(d.query_images), 'query', 'queries')} whose right places include it (raw_p: the "
                "query's best score against the place)")
    raw_of = dict(zip(d.query_images.tolist(), d.query_raw.tolist()))
    rows = [d.images[ds.database_traversal[d.images] == t] for t in np.unique(ds.database_traversal[d.images])]
    groups = [(f"**The {count(len(d.images), 'database image', 'database images')} of P{place}**: the mixture, "
               "θ_p and the same-place scores are fitted on these alone.", rows)]
    if len(d.query_images):
        groups.append((f"**The {count(len(d.query_images), 'query', 'queries')} whose right places include "
                       f"P{place}**: not part of the fit; each one's raw_p is a triangle under the mixture.",
                       [d.query_images]))
    for said, group in groups:
        st.caption(said)
        for row in group:
            for col, i in zip(st.columns(min(len(row), THUMBNAILS)), row[:THUMBNAILS]):
                i = int(i)
                col.image(cache.thumbnail(ds.image_paths[i]), width="stretch",
                          caption=image_caption(ds, i, raw_of.get(i, float("nan"))))
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
    f"adaptive k = {number(d.k_adaptive, '.2f')}, both told below) pushes the threshold into the gap between negatives "
    "and same-place scores: that is where rejection starts to pay, at the price of dropping some right places."
)
mu_pos, mu_neg = float(model.positive_mean[place]), float(model.negative_mean[place])
gap = (mu_pos - mu_neg) / (2 * max(d.spread, SIGMA_FLOOR))  # adaptive_k before its clip (NaN: no same-place pair)
clipped = ("no same-place pair, so k = 1" if not np.isfinite(gap) else
           f"clipped to {d.k_adaptive:.2f}" if not 1.0 <= gap <= 2.0 else f"so k = {d.k_adaptive:.2f}")
st.markdown(
    f"**The symbols, with P{place}'s values.**\n"
    f"- **μ⁻** ({'the blue line' if many else 'rings'} in the overview): the mean of the place's negative mixture "
    f"M(p) = Σ wᵢ N(μᵢ, σᵢ²), where the scores of its database images against other places centre. "
    f"Here {number(mu_neg)}.\n"
    f"- **s_p**: the standard deviation of that mixture, how wide the negatives spread. Here {number(d.spread)}.\n"
    f"- **μ⁺** ({'the red line' if many else 'diamonds'} in the overview): the mean same-place score, over the pairs "
    f"of the place's own database images (none for a place of one image). Here {number(mu_pos)}.\n"
    f"- **θ_p(k) = θ_p + k·s_p**: the threshold the k slider moves, k standard deviations of the negatives above "
    f"θ_p. Here θ_p(k={k:g}) {method} = {number(theta_k)}.\n"
    f"- **adaptive k = clip((μ⁺ − μ⁻) / (2·s_p), 1, 2)**: one k per place, from the authors' later work: half the "
    f"gap between the same-place and the negative means, counted in s_p and kept between 1 and 2 (1 for a place "
    f"with no same-place pair). Here (μ⁺ − μ⁻) / (2·s_p) = {number(gap, '.2f')}, {clipped}, and θ_p(adaptive k) "
    f"{method} = {number(d.theta_k(d.k_adaptive, method))}. The Evaluation page's trade-off marks adaptive k with a "
    "diamond."
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
