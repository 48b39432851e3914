"""Widgets that several pages share: the threshold family's k, the user's global θ, the inspector's "next"."""

from __future__ import annotations

from collections.abc import Callable

import streamlit as st

from vpr_explorer.errors import VPRInputError

from vpr_explorer.app.ui import state
from vpr_explorer.app.ui.state import K_RANGE, THETA_RANGE


def threshold_controls(container=st) -> tuple[float, float | None]:
    """A k slider for θ_p(k) = θ_p + k·s_p and an optional user global θ; returns ``(k, user_theta)``."""
    v = state.view()
    container.slider("k: θ_p(k) = θ_p + k·s_p (k = 0 is the paper)", K_RANGE[0], K_RANGE[1], step=0.25,
                     help="s_p is the standard deviation of the place's negative mixture. Raising k moves every "
                          "place's threshold out of its negative scores: more rejections, fewer wrong accepts.",
                     **state.bind("w_k", "k", float(min(max(v.k, K_RANGE[0]), K_RANGE[1]))))

    def toggle_user() -> None:
        state.update(theta=0.5 if st.session_state["w_user_on"] else None)

    st.session_state["w_user_on"] = v.theta is not None
    container.checkbox("also compare a global θ of my own", key="w_user_on", on_change=toggle_user)
    if v.theta is not None:
        container.number_input("my global θ", THETA_RANGE[0], THETA_RANGE[1], step=0.01, format="%.3f",
                               **state.bind("w_user_theta", "theta", float(v.theta)))
    v = state.view()
    return v.k, v.theta


def jump_to_next(search: Callable[[], tuple[int | None, int]], current: int, n: int, *, kind: str,
                 label: str) -> None:
    """The Query inspector's "next ▶": move the view's ``frame`` to the query ``search()`` found after ``current``.

    ``search`` returns ``(found, last)`` as ``numbers.find_query`` does (``last``: where
    a search that ran out of budget stopped); ``n`` queries in all. What could not be found is
    kept for the page to show (``st.session_state["find_none"]``).
    """
    try:
        found, last = search()
    except VPRInputError as exc:
        st.session_state["find_none"] = str(exc)
        return
    if found is not None:
        state.update(frame=found)
    elif last == current:
        st.session_state["find_none"] = f"no query was {kind} under {label}; try raising k or another method"
    else:  # the search budget ran out: move on, so that the next press searches on
        state.update(frame=last)
        st.session_state["find_none"] = (f"no query {kind} under {label} from query {(current + 1) % n} to {last}; "
                                         f"moved to query {last}, press next again to search on")
