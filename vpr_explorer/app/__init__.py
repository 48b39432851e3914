"""The explorer app, shipped in the package: ``vpr-explorer app`` serves it from any directory.

The one Streamlit leaf of the tree: the library never imports streamlit, only this
sub-package does (and only its modules that run inside the server).

* ``explorer.py``: the entry script (what ``streamlit run`` is pointed at): page
  config, the view read from the URL, ``st.navigation`` over ``pages/``, the sidebar.
* ``pages/``: one script per page; a page is widgets → one library call → render.
* ``ui/``: what the pages share: ``state`` (the view, mirrored into the URL), ``cache``
  (every Streamlit cache), ``current``, ``controls``, ``feedback``, ``routing``,
  ``sidebar``, ``group_step``; and the bodies the Places, Query inspector and Evaluation
  pages use for a database/queries dataset (``retrieval_places``, ``retrieval_inspector``,
  ``retrieval_eval``).
* ``launch``: the command line's ``app`` sub-command; imports no streamlit.

A checkout's top-level ``app.py`` and ``pages/`` (for ``streamlit run app.py``) only hand
over to these.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

HERE = Path(__file__).resolve().parent
ENTRY = HERE / "explorer.py"
"""The entry script ``vpr-explorer app`` runs."""
PAGES = HERE / "pages"
"""The page scripts, one per page, named as the page's URL path (``places.py`` is ``/places``)."""

DATASET_ENV = "VPR_EXPLORER_DATASET"
"""The dataset a session opens when its link names none (``vpr-explorer app --dataset``)."""
LAYOUT_ENV = "VPR_EXPLORER_LAYOUT"
"""The layout the dataset is read in (``vpr-explorer app --layout``); unset: detected."""
RADIUS_ENV = "VPR_EXPLORER_RADIUS"
"""The positive radius in metres of a position-tagged layout (``vpr-explorer app --radius``)."""
DESCRIPTORS_ENV = "VPR_EXPLORER_DESCRIPTORS"
"""Descriptor files the app offers beside its extractors, separated by ``os.pathsep``; each is
named by its file's stem, and the first is the descriptor a session opens when its link names
none (``vpr-explorer app --descriptors``)."""


def descriptor_files(environ: Mapping[str, str] = os.environ) -> dict[str, Path]:
    """The files ``DESCRIPTORS_ENV`` names, by descriptor name (the file's stem), in its order."""
    files = [Path(p).expanduser() for p in environ.get(DESCRIPTORS_ENV, "").split(os.pathsep) if p.strip()]
    return {p.stem: p for p in files}


def started_view(environ: Mapping[str, str] = os.environ) -> dict[str, str]:
    """The view the app was started on (``DATASET_ENV``, its layout and radius, the first descriptor
    file), as query parameters.

    A session's link overrides it; with neither, the app opens the demo route.
    """
    view = {}
    if environ.get(DATASET_ENV, "").strip():
        view["source"] = environ[DATASET_ENV].strip()
    for name, variable in (("layout", LAYOUT_ENV), ("radius", RADIUS_ENV)):
        if environ.get(variable, "").strip():
            view[name] = environ[variable].strip()
    files = descriptor_files(environ)
    if files:
        view["descriptor"] = next(iter(files))
    return view
