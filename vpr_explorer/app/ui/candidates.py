"""The Query inspector's candidate places: one chart per method, then the best candidates' images.

Each chart shows raw_p against the method's threshold, the answer outlined and the right
places starred; the images beside the query's are the ``BEST_IMAGES`` best candidates' best
database images (by raw_p), and the true place's best image (``numbers.true_place_rank``) after
them, labelled with its rank, when it is not among them: the true place is always shown.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import streamlit as st

from vpr_explorer.views import plots
from vpr_explorer.views.numbers import true_place_rank
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
    shown = [int(p) for p in cands[:BEST_IMAGES]]
    true = true_place_rank(dec)
    extra = true if true is not None and true[0] not in shown else None
    if extra is not None:
        st.caption(f"The {BEST_IMAGES} best places by raw_p, then the true place's best image: it ranks "
                   f"{ordinal(extra[1])} of {dec.n_places}.")
    cols = st.columns(BEST_IMAGES + 2 if extra is not None else BEST_IMAGES + 1)
    cols[0].image(cache.thumbnail(query_image, 160), caption=query_caption, width="stretch")
    tiles = [(p, "right place" if p in dec.true_places else "other place") for p in shown]
    if extra is not None:
        tiles.append((extra[0], f"true place, ranked {ordinal(extra[1])}"))
    for col, (p, verdict) in zip(cols[1:], tiles):
        path, label = database_image(int(dec.best_image[p]))
        col.image(cache.thumbnail(path, 160), width="stretch",
                  caption=f"P{p}, {label}: raw_p {dec.raw[p]:.3f} ({verdict})")


def ordinal(n: int) -> str:
    """1st, 2nd, 3rd, 4th, …, 11th, 12th, 13th, …, 21st, 22nd, …"""
    suffix = "th" if n % 100 in (11, 12, 13) else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"
