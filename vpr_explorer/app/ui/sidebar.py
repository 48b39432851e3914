"""The sidebar every page shares: what is being looked at, and a link that reopens it."""

from __future__ import annotations

import streamlit as st

from vpr_explorer.data.groundtruth import DEFAULT_RADIUS
from vpr_explorer.data.layouts import Layout

from vpr_explorer.app.ui import state


def _places(v: state.View) -> str:
    """The view's places in words: metres where a geometry in metres is chosen, else frames."""
    if all(x is None for x in (v.group, v.step, v.geometry, v.group_m, v.step_m)):
        return f"the dataset's default, {v.reading} reading"
    if v.geometry in ("route", "lattice") or (v.geometry is None and (v.group_m or v.step_m)):
        return (f"group {v.group_m or 'default'} m, step {v.step_m or 'default'} m"
                f"{f' ({v.geometry})' if v.geometry else ''}, {v.reading} reading")
    return f"group {v.group or 'default'}, step {v.step or 'default'}, {v.reading} reading"


def render() -> None:
    """Show the current view (dataset, layout, descriptor, places, queries) under the navigation."""
    v = state.view()
    with st.sidebar:
        st.caption("**Looking at**")
        source = "built-in demo route" if v.source == "demo" else v.source
        layout = "" if v.layout == Layout.AUTO.value else f"  \nlayout: {v.layout}"
        radius = "" if v.radius is None else f"  \nradius: {v.radius:g} m (default {DEFAULT_RADIUS:g})"
        descriptor = f"`{v.descriptor}`" + ("" if v.descriptors is None else f" (file `{v.descriptors}`)")
        st.caption(f"dataset: `{source}`{layout}{radius}  \ndescriptor: {descriptor}  \nplaces: {_places(v)}  \n"
                   f"queries: `{v.query or 'default'}`")
        st.caption("The address bar holds this page's view: copy it to share it.")
        ignored = st.session_state.pop("url_ignored", None)
        if ignored:
            st.warning("Ignored in the link:\n\n" + "\n".join(f"- {why}" for why in ignored), icon=":material/warning:")
