"""VPR Threshold Explorer's entry script: ``vpr-explorer app`` (or ``streamlit run`` on this file).

The entry point only routes: it restores the view from the URL, registers the pages
with ``st.navigation``, shows what is being looked at in the sidebar, and runs the page.
A checkout's ``app.py`` calls ``run`` too, so both start the same app.
"""

import pandas  # noqa: F401  # before plotly, on every page: plotly.py#2433
import streamlit as st

from vpr_explorer.app.ui import routing, sidebar, state

PAGES = (  # (script under pages/, title, icon); the first is the default page
    ("home", "Dataset", ":material/folder_open:"),
    ("places", "Places (group/step)", ":material/place:"),
    ("thresholds", "Thresholds", ":material/show_chart:"),
    ("inspector", "Query inspector", ":material/search:"),
    ("evaluation", "Evaluation", ":material/bar_chart:"),
    # Pages owned by other modules are added below this line, one entry each.
    ("playback", "Playback (rerun)", ":material/play_circle:"),
    ("sweep", "Group/step sweep", ":material/grid_on:"),
)


def run() -> None:
    """One script run of the app: route to the page the URL asks for and run it."""
    st.set_page_config(page_title="VPR Threshold Explorer", page_icon=":material/explore:", layout="wide")

    state.view()  # first run of a session: read the view from the URL

    pages = {name: st.Page(routing.page_file(name), title=title, icon=icon, default=i == 0)
             for i, (name, title, icon) in enumerate(PAGES)}
    page = st.navigation(list(pages.values()))
    goto = routing.pending_page()
    if goto in pages:
        st.switch_page(pages[goto], query_params={k: st.query_params[k] for k in st.query_params})
    name = next((n for n, p in pages.items() if p is page), None)
    sidebar.render()
    state.sync_url(name)
    st.session_state[routing.ROUTED] = True
    try:
        page.run()
    finally:
        st.session_state[routing.ROUTED] = False
        state.sync_url(name)  # the page may have changed the view (a click, a slider)


if __name__ == "__main__":  # Streamlit runs the entry script as __main__, on every rerun
    run()
