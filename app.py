"""VPR Threshold Explorer from a checkout: ``streamlit run app.py``.

The app ships in the package (``vpr_explorer/app/``, what ``vpr-explorer app`` serves
from any directory); this file only runs its entry script's ``run``.
"""

from vpr_explorer.app.explorer import run

run()
