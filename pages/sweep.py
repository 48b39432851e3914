"""Group/step sweep page: it lives in the package (``vpr_explorer/app/pages/sweep.py``).

``st.navigation`` in ``app.py`` registers the packaged page; Streamlit runs this file
only for a direct visit to ``/sweep`` on a fresh server, which it hands to ``app.py``.
"""

from vpr_explorer.app.ui.routing import ensure_routed

ensure_routed(__file__)
