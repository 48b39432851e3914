"""The Dataset page's "Fetch a public dataset" expander: the catalogue, and a button that fetches into the data root.

Widgets → one library call (``data.fetch.fetch``) → render: a ``download`` dataset is fetched
into the app's data root with an ``st.progress`` bar (bytes of the file being downloaded);
a failure is one ``st.error`` naming the URL or file and what to do, never a traceback; a
dataset served over rsync, by a script or on request shows what to do instead of a button.
``VPR_EXPLORER_MIRROR`` (``data.fetch.MIRROR_ENV``), when set, serves every file, as it does
for ``vpr-explorer fetch``.
"""

from __future__ import annotations

import os
from pathlib import Path

import streamlit as st

from vpr_explorer.data.catalogue import BY_NAME, CATALOGUE, Access
from vpr_explorer.data.fetch import MIRROR_ENV, fetch
from vpr_explorer.errors import VPRInputError

from vpr_explorer.app.ui.feedback import show_error


def fetch_panel(root: Path) -> None:
    """The expander: pick a catalogue dataset, read its facts, fetch it into ``root``."""
    with st.expander("Fetch a public dataset"):
        name = st.selectbox("Public dataset", [d.name for d in CATALOGUE], key="w_fetch_name",
                            format_func=lambda n: f"{BY_NAME[n].title}  ({BY_NAME[n].access.value})",
                            help="The datasets `vpr-explorer datasets` lists; `download` ones are fetched here.")
        dataset = BY_NAME[name]
        st.caption(f"[home]({dataset.home}) · licence: {dataset.licence} · size: {dataset.size} · opens as "
                   f"{dataset.layout.value} · sha256: {dataset.checksums} · folder: `{root / dataset.folder}`")
        if dataset.access is not Access.DOWNLOAD:
            st.info(f"Not fetched here ({dataset.access.value}): {dataset.how}", icon=":material/info:")
            return
        if not st.button(f"Fetch into {root}", key="w_fetch"):
            return
        bar = st.progress(0.0, text=f"{dataset.title}: connecting…")

        def progress(done: int, total: int, file_name: str) -> None:
            share = min(done / total, 1.0) if total > 0 else 0.0
            size = f"{done / 1e6:,.1f} of {total / 1e6:,.1f} MB" if total > 0 else f"{done / 1e6:,.1f} MB"
            bar.progress(share, text=f"{file_name}: {size}")

        try:
            result = fetch(dataset, root, mirror=os.environ.get(MIRROR_ENV, "").strip() or None, progress=progress)
        except VPRInputError as exc:
            bar.empty()
            show_error(exc, hint="Nothing half-written was kept; press the button again to resume the download.")
            return
        bar.empty()
        if result.skipped:
            st.info(f"`{result.path}` exists already: not fetched again. Pick it in the Dataset box above.",
                    icon=":material/info:")
            return
        unverified = [d.file_name for d in result.digests if not d.checked]
        st.success(f"{dataset.title} is ready at `{result.path}` ({dataset.layout.value}): pick it in the Dataset box "
                   "above." + (f" Not verified (no published sha256): {', '.join(unverified)}." if unverified else ""),
                   icon=":material/check_circle:")
