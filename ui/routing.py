"""Keep every page behind ``app.py``'s router, even on a freshly started server.

Streamlit treats an app with a ``pages/`` folder as an old-style multipage app until
``st.navigation`` has run once: on a fresh server, the first visit to ``/places`` runs
``pages/places.py`` on its own, without ``app.py`` (no page config, no sidebar, no URL
sync). ``ensure_routed`` notices that (``app.py`` marks the runs it routes) and hands
the request to ``app.py``, which then switches to the page that was asked for, with the
URL's query parameters.
"""

from __future__ import annotations

from pathlib import Path

import streamlit as st

ROUTED = "_routed_by_app"
GOTO = "_goto_page"


def ensure_routed(page_file: str) -> None:
    """Call first in every page: re-enter through ``app.py`` when the page was run on its own."""
    if st.session_state.get(ROUTED):
        return
    st.session_state[GOTO] = f"pages/{Path(page_file).name}"
    st.switch_page("app.py", query_params={k: st.query_params[k] for k in st.query_params})


def pending_page() -> str | None:
    """The page a standalone run asked for (see ``ensure_routed``), once."""
    return st.session_state.pop(GOTO, None)
