"""The sidebar every page shares: what is being looked at, and a link that reopens it."""

from __future__ import annotations

import streamlit as st

from vpr_explorer.app.ui import state


def render() -> None:
    """Show the current view (dataset, descriptor, places, query traversal) under the navigation."""
    v = state.view()
    with st.sidebar:
        st.caption("**Looking at**")
        source = "built-in demo route" if v.source == "demo" else v.source
        places = (f"group {v.group or 'default'}, step {v.step or 'default'}, {v.reading} reading")
        st.caption(f"dataset: `{source}`  \ndescriptor: `{v.descriptor}`  \nplaces: {places}  \n"
                   f"queries: `{v.query or 'default'}`")
        st.caption("The address bar holds this view: copy it to share it.")
        ignored = st.session_state.pop("url_ignored", None)
        if ignored:
            st.warning("Ignored in the link:\n\n" + "\n".join(f"- {why}" for why in ignored), icon=":material/warning:")
