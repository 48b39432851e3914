"""VPR Threshold Explorer: ``streamlit run app.py``.

The entry point only routes: it restores the view from the URL, registers the pages
with ``st.navigation``, shows what is being looked at in the sidebar, and runs the page.
"""

import pandas  # noqa: F401  # before plotly, on every page: plotly.py#2433
import streamlit as st

from ui import routing, sidebar, state

st.set_page_config(page_title="VPR Threshold Explorer", page_icon=":material/explore:", layout="wide")

state.view()  # first run of a session: read the view from the URL

PAGES = [
    st.Page("pages/home.py", title="Dataset", icon=":material/folder_open:", default=True),
    st.Page("pages/places.py", title="Places (group/step)", icon=":material/place:"),
    st.Page("pages/thresholds.py", title="Thresholds", icon=":material/show_chart:"),
    st.Page("pages/inspector.py", title="Query inspector", icon=":material/search:"),
    st.Page("pages/evaluation.py", title="Evaluation", icon=":material/bar_chart:"),
    # Pages owned by other modules are added below this line, one st.Page(...) each.
    st.Page("pages/playback.py", title="Playback (rerun)", icon=":material/play_circle:"),
]

page = st.navigation(PAGES)
goto = routing.pending_page()
if goto:
    st.switch_page(goto, query_params={k: st.query_params[k] for k in st.query_params})
sidebar.render()
state.sync_url()
st.session_state[routing.ROUTED] = True
try:
    page.run()
finally:
    st.session_state[routing.ROUTED] = False
    state.sync_url()  # the page may have changed the view (a click, a slider)
