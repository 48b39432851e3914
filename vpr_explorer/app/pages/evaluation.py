"""Evaluation page: the paper, traversal and open-set protocols; Recall@K, the trade-off, the similarity matrix."""

import pandas as pd  # before plotly: plotly.py#2433
import streamlit as st

from vpr_explorer import plots
from vpr_explorer.evaluation import PROTOCOL_LABELS, Protocol
from vpr_explorer.places import make_places
from vpr_explorer.report import method_csv
from vpr_explorer.views import AUTO_RUN_PAIRS, evaluation_json, evaluation_rows, protocol_pairs

from vpr_explorer.app.ui import cache, state
from vpr_explorer.app.ui.current import current
from vpr_explorer.app.ui.feedback import PLACES_HINT, stop_on_input_error
from vpr_explorer.app.ui.routing import ensure_routed, page_file

ensure_routed(__file__)

INSPECTOR = page_file("inspector")

if st.session_state.pop("goto_inspector", False):
    st.switch_page(INSPECTOR)

st.title("Evaluation")
with stop_on_input_error():
    cur = current()
ds = cur.data.dataset
v = state.view()


with st.form("protocol_form"):
    protocol = st.radio("Protocol", [p.value for p in Protocol], format_func=lambda p: PROTOCOL_LABELS[Protocol(p)],
                        key="w_protocol")
    c = st.columns(4)
    runs = c[0].slider("runs (paper: 50)", 1, 50, 20, key="w_runs", help="paper and open-set protocols")
    seed = c[1].number_input("seed", 0, 10_000, 0, key="w_seed")
    cross = c[2].checkbox("cross-condition", key="w_cross",
                          help="score each query only against database images of other traversals")
    share = c[3].slider("unknown share (open set)", 0.1, 0.6, 0.3, step=0.05, key="w_share")
    c = st.columns(3)
    database = c[0].multiselect("database traversals (traversal protocol)", list(ds.traversals),
                                default=list(cur.database), key="w_database")
    query = c[1].selectbox("query traversal (traversal protocol)", list(ds.traversals),
                           index=ds.traversals.index(cur.query), key="w_eval_query")
    tolerance = c[2].number_input("tolerance ± frames (traversal protocol)", 0, 20, 0, key="w_tolerance")
    submitted = st.form_submit_button("Run", type="primary")

with stop_on_input_error(hint=PLACES_HINT):
    places = make_places(ds, cur.spec)
first_visit = "eval_request" not in st.session_state
cost = protocol_pairs(protocol, places, ds, runs=int(runs), database=database, unknown_share=float(share))
if first_visit and not submitted and cost > AUTO_RUN_PAIRS:
    st.info(f"{ds.n_images:,} images: the {PROTOCOL_LABELS[Protocol(protocol)]} scores about {cost:.1e} image pairs "
            "(minutes on a laptop), so it does not start by itself. Choose the settings and press **Run**; a "
            "progress bar shows how far it is, and the result stays in memory for this dataset.",
            icon=":material/timer:")
elif submitted or first_visit:
    options = {"user_theta": v.theta}
    if protocol == Protocol.TRAVERSAL:
        options.update(database=list(database), queries=query, tolerance=int(tolerance))
    else:
        options.update(runs=int(runs), seed=int(seed), cross_condition=bool(cross))
        if protocol == Protocol.OPEN_SET:
            options["unknown_share"] = float(share)
    st.session_state["eval_request"] = (protocol, options)


def show_results() -> None:
    protocol_run, options = st.session_state["eval_request"]
    with stop_on_input_error(hint="Change the protocol settings above, or group/step on the **Places** page."):
        ev = cache.evaluation(cur.data, cur.spec, protocol_run, **options)

    st.subheader(f"{PROTOCOL_LABELS[ev.protocol]}")
    shown = {k: val for k, val in ev.settings.items() if k not in ("k_grid", "group", "step", "reading") and val is not None}
    st.caption(", ".join(f"{k}: {val}" for k, val in shown.items()) + f" · {ev.seconds:.1f} s")
    for note in ev.notes:
        st.caption(f"note: {note}")
    st.caption("The image-level baseline ranks images (the authors' 'Baseline'); the place-level baseline ranks places "
               "with no threshold. The gap between them is the change of level, not the threshold.")
    table = pd.DataFrame(evaluation_rows(ev))
    st.dataframe(table, hide_index=True, key="results", column_config={
        col: st.column_config.NumberColumn(col, format="%.1f") for col in table.columns if col not in ("method", "source")
    })
    st.plotly_chart(plots.recall_figure(ev), key="recall", width="stretch")
    d1, d2 = st.columns(2)
    stem = f"{ds.name}_{cur.data.descriptor}_{ev.protocol.value}"
    d1.download_button("Download CSV", method_csv(ev), file_name=f"{stem}.csv", mime="text/csv", key="w_csv")
    d2.download_button("Download JSON", evaluation_json(ev), file_name=f"{stem}.json", mime="application/json", key="w_json")

    if ev.protocol is Protocol.OPEN_SET:
        rule = st.radio("filter rule of the θ_p(k) curves", ["margin", "raw"], horizontal=True, key="w_rule")
        st.plotly_chart(plots.tradeoff_figure(ev, rule), key="tradeoff", width="stretch")
        st.caption("k = 0 (circled) is the paper: it sits near zero rejection, because θ_p lies in the centre of the "
                   "negative scores. Raising k trades known-place recall for rejection of unknown places; the grey "
                   "line is one global θ for every place, the stars its automatic and oracle values.")
    else:
        st.caption("Run the open-set protocol to see the trade-off between rejecting unknown places and Recall@1.")


if "eval_request" in st.session_state:
    show_results()

st.subheader("Similarity matrix: click a cell to open that query in the inspector")


def open_pair() -> None:
    points = st.session_state["simgrid"].selection.points
    pair = plots.selected_pair(points[0]) if points else None
    if pair is None:
        return
    q_image, db_image = pair
    st.session_state["picked_pair"] = (q_image, db_image)
    state.update(query=ds.traversals[ds.image_traversal[q_image]], frame=int(ds.image_frame[q_image]))
    st.session_state["goto_inspector"] = True


with stop_on_input_error(hint="Pick the query traversal on the **Places** page."):
    grid = cache.grid(cur.data, cur.database, cur.query)
if grid.sampled:
    st.caption(f"{ds.n_frames:,} frames: each row is one query frame (the centre of its block of {grid.block}) against "
               "every database frame, each column the best of its block; computing every block's rows too would "
               f"take {ds.n_frames:,}² × {len(cur.database)} similarities.")
picked = st.session_state.get("picked_pair")
marked = (int(ds.image_frame[picked[0]]), int(ds.image_frame[picked[1]])) if picked else None
st.plotly_chart(plots.similarity_heatmap(grid, query=cur.query, database=cur.database, marked=marked),
                key="simgrid", on_select=open_pair, selection_mode="points", width="stretch")
