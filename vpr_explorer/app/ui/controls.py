"""Widgets that several pages share: the threshold family's k and the user's global θ."""

from __future__ import annotations

import streamlit as st

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

