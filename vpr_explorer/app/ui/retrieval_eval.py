"""The Evaluation page of a database/queries dataset: the database/queries protocol, as the field counts it.

Recall@K of every method on the dataset's own queries (``pipeline.evaluate_retrieval``):
image level, a query counts at K when one of its top K database images is right; place
level, when the top K places hold one. The table states the ground truth (the radius of a
position-tagged layout) and how many queries have no right database image (unknown places,
counted apart: their rejection rate, never as misses).
"""

from __future__ import annotations

import pandas as pd  # before plotly: plotly.py#2433
import streamlit as st

from vpr_explorer.views import plots
from vpr_explorer.views.report import method_csv
from vpr_explorer.views.traversal import AUTO_RUN_PAIRS, evaluation_json, evaluation_rows

from vpr_explorer.app.ui import cache, state
from vpr_explorer.app.ui.current import Current
from vpr_explorer.app.ui.feedback import stop_on_input_error


def render(cur: Current) -> None:
    """The Evaluation page body for a database/queries dataset (the page stops after it)."""
    ds = cur.retrieval
    v = state.view()
    st.caption(f"{ds.describe()}. The database/queries protocol: thresholds from the database images in places "
               f"({cur.places.describe()}, set on the **Places** page), every query decided once.")
    cost = ds.n_queries * ds.n_database
    if (cost > AUTO_RUN_PAIRS and not cache.retrieval_evaluated(cur.data, cur.places, user_theta=v.theta)
            and not st.button("Run", type="primary", key="w_retrieval_run")):
        st.info(f"{ds.n_queries:,} queries × {ds.n_database:,} database images: about {cost:.1e} similarities "
                "(minutes on a laptop), so the protocol does not start by itself. Press **Run**; a progress bar "
                "shows how far it is, and the result stays in memory for these places.", icon=":material/timer:")
        return
    with stop_on_input_error(hint="Change group or step on the **Places** page, or your global θ on the "
                                  "**Query inspector** page."):
        ev = cache.retrieval_evaluation(cur.data, cur.places, user_theta=v.theta)
    s = ev.settings
    st.subheader("Database/queries protocol")
    st.caption(f"ground truth: {s['ground_truth']} · {s['queries']:,} queries, **{s['queries_without_positive']:,} "
               f"with no right database image** (unknown places: counted apart, as their rejection rate) · "
               f"{s['queries_between_places']:,} whose right images all lie between places (left out of the "
               f"place-level rows) · {s['database_images_in_places']:,} of {s['database_images']:,} database images "
               f"in {s['places']} · {ev.seconds:.1f} s")
    for note in ev.notes:
        st.caption(f"note: {note}")
    table = pd.DataFrame(evaluation_rows(ev))
    st.dataframe(table, hide_index=True, key="results", placeholder="—", column_config={
        col: st.column_config.NumberColumn(col, format="%.1f") for col in table.columns if col not in ("method", "source")
    })
    st.plotly_chart(plots.recall_figure(ev), key="recall", width="stretch")
    d1, d2 = st.columns(2)
    stem = f"{ds.name}_{cur.data.descriptor}_{ev.protocol.value}"
    d1.download_button("Download CSV", method_csv(ev), file_name=f"{stem}.csv", mime="text/csv", key="w_csv")
    d2.download_button("Download JSON", evaluation_json(ev), file_name=f"{stem}.json", mime="application/json",
                       key="w_json")
    st.caption("Open a query that a method rejected or got wrong on the **Query inspector** page (its “next ▶”).")
