"""Keep every page behind the entry script's router, even on a freshly started server.

Streamlit treats an app with a ``pages/`` folder beside its entry script (``app.py`` in a
checkout, ``explorer.py`` in the package) as an old-style multipage app until
``st.navigation`` has run once: on a fresh server, the first visit to ``/places`` runs
``pages/places.py`` on its own, without the entry script (no page config, no sidebar, no
URL sync). ``ensure_routed`` notices that (the entry script marks the runs it routes) and
hands the request to the entry script, which then switches to the page that was asked
for, with the URL's query parameters.

Pages are named by their script's stem (``"inspector"``); ``page_file`` gives the packaged
script, which is what ``st.navigation`` registers whichever entry script runs it.
"""

from __future__ import annotations

from pathlib import Path

import streamlit as st
from streamlit.runtime.scriptrunner import get_script_run_ctx

from vpr_explorer.app import PAGES

ROUTED = "_routed_by_app"
GOTO = "_goto_page"


def page_file(name: str) -> str:
    """The packaged script of page ``name`` (e.g. ``"inspector"``), for ``st.Page`` and ``st.switch_page``."""
    return str(PAGES / f"{name}.py")


def ensure_routed(page_script: str) -> None:
    """Call first in every page: re-enter through the entry script when the page was run on its own."""
    if st.session_state.get(ROUTED):
        return
    st.session_state[GOTO] = Path(page_script).stem
    entry = Path(get_script_run_ctx().main_script_path).name  # app.py or explorer.py, whichever was started
    st.switch_page(entry, query_params={k: st.query_params[k] for k in st.query_params})


def pending_page() -> str | None:
    """The page (its name) a standalone run asked for (see ``ensure_routed``), once."""
    return st.session_state.pop(GOTO, None)
