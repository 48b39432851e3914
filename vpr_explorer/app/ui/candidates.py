"""The Query inspector's candidate places: one chart per method, then the best candidates' images.

Each chart shows raw_p against the method's threshold, the answer outlined and the right
places starred; the images beside the query's are the best candidates' best database images.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import streamlit as st

from vpr_explorer.views import plots
from vpr_explorer.method.retrieval import QueryDecision

from vpr_explorer.app.ui import cache

PER_ROW = 3
"""Method charts per row."""
BEST_IMAGES = 4
"""Best candidate places shown as images beside the query."""


def show_candidates(dec: QueryDecision, methods: Sequence[str], cands: np.ndarray, describe: Callable[[str], str], *,
                    query_image: Path, query_caption: str, database_image: Callable[[int], tuple[Path, str]]) -> None:
    """The method charts and the best candidates' images.

    ``database_image(i)`` gives the path and the label of database image ``i`` (an index of
    the decision's model images).
    """
    st.subheader("Candidate places: raw_p, threshold and margin")
    st.caption("Dots: raw_p, the query's best score against the place's database images; green = kept, grey = "
               "dropped by the method's threshold (red tick); black outline = the answer; ★ = a right place; labels "
               "= margin raw_p − θ (or raw_p where there is no threshold).")
    for row in range(0, len(methods), PER_ROW):
        for col, key in zip(st.columns(PER_ROW), methods[row:row + PER_ROW]):
            with col:
                st.plotly_chart(plots.candidate_bars(dec, key, cands), key=f"bars_{key}", width="stretch")
                st.caption(describe(key))

    st.subheader("Best candidates beside the query")
    cols = st.columns(BEST_IMAGES + 1)
    cols[0].image(cache.thumbnail(query_image, 160), caption=query_caption, width="stretch")
    for col, p in zip(cols[1:], cands[:BEST_IMAGES]):
        path, label = database_image(int(dec.best_image[p]))
        verdict = "right place" if p in dec.true_places else "other place"
        col.image(cache.thumbnail(path, 160), width="stretch",
                  caption=f"P{p}, {label}: raw_p {dec.raw[p]:.3f} ({verdict})")
