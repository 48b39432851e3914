"""Dataset page: pick the route and the descriptor, compute descriptors, see the traversals."""

import pandas  # noqa: F401  # before plotly: plotly.py#2433
from pathlib import Path

import numpy as np
import streamlit as st

from vpr_explorer import settings
from vpr_explorer.app import DESCRIPTORS_ENV, descriptor_files
from vpr_explorer.descriptors import available_extractors
from vpr_explorer.descriptors.custom import MODELS_ENV
from vpr_explorer.errors import VPRInputError
from vpr_explorer.pipeline import DEMO

from vpr_explorer.app.ui import cache, state
from vpr_explorer.app.ui.current import current
from vpr_explorer.app.ui.feedback import show_error, show_rejected
from vpr_explorer.app.ui.routing import ensure_routed

ensure_routed(__file__)

OTHER = "__folder__"
STRIP = 8  # thumbnails per traversal

st.title("VPR Threshold Explorer")
st.markdown(
    "Why is a query accepted or rejected? Trinh & Lyons fit, for every place, a Gaussian mixture to the "
    "similarities between its images and **other** places (the *negative* scores), and set a per-place "
    "threshold θ_p from it. Pick a route and a descriptor here; the other pages show the places, the "
    "thresholds, single queries and the evaluation protocols."
)
show_rejected()
v = state.view()


def found_datasets() -> list[str]:
    """Dataset folders under ``VPR_EXPLORER_DATA`` (its direct sub-folders)."""
    root = settings.data_root()
    if root is None or not root.is_dir():
        return []
    return [str(p) for p in sorted(root.iterdir()) if p.is_dir() and not p.name.startswith(".")]


def check_folder(path: object) -> None:
    if not str(path).strip():
        raise VPRInputError("folder path: type the path of a dataset folder (one sub-folder per traversal)")
    cache.dataset(str(path).strip())


def descriptor_status() -> dict[str, str | None]:
    """Extractors and why any cannot run, then the descriptor files the app was started with.

    A broken models settings file is shown, not raised.
    """
    try:
        status = available_extractors()
    except VPRInputError as exc:
        show_error(exc, hint=f"Fix the file or unset {MODELS_ENV}; the built-in descriptors still work.")
        status = {name: None for name in ("pixels", "efficientnet-lite0")}
    return {**status, **{name: None for name in descriptor_files()}}


def check_descriptor(name: object) -> None:
    reason = descriptor_status().get(str(name))
    if reason is not None:
        raise VPRInputError(f"descriptor {name!r} is unavailable here: {reason}")


col_data, col_desc = st.columns([3, 2], gap="large")
with col_data:
    st.subheader("Route")
    options = [DEMO, *found_datasets(), OTHER]
    folder_mode = v.source not in options or st.session_state.get("folder_mode", False)
    labels = {DEMO: "Built-in demo route (drawn street, 3 conditions)", OTHER: "A folder path…"}
    st.session_state["w_source"] = OTHER if folder_mode else v.source

    def pick_source() -> None:
        choice = st.session_state["w_source"]
        st.session_state["folder_mode"] = choice == OTHER
        if choice != OTHER:
            state.commit(source=choice, validate=lambda: check_folder(choice))

    st.selectbox(
        "Dataset", options, key="w_source", on_change=pick_source,
        format_func=lambda o: labels.get(o, f"{Path(o).name}  (under {settings.DATA_ENV})"),
        help=f"Datasets found under {settings.DATA_ENV}={settings.data_root() or '(unset)'}, the demo route, "
             "or any folder: one sub-folder per traversal (frame i = same spot), or Place####_Cond##_G## images.",
    )
    if folder_mode:
        # Not bound to the view: a path that fails to open stays in the box, to be corrected.
        st.session_state.setdefault("w_folder", v.source if v.source not in options else "")

        def open_folder() -> None:
            path = st.session_state["w_folder"].strip()
            state.commit(source=path, validate=lambda: check_folder(path))

        st.text_input("Folder path", key="w_folder", on_change=open_folder, placeholder="/data/GardensPointWalking",
                      help="Press Enter to open it. The folder is checked before it replaces the current route.")

with col_desc:
    st.subheader("Descriptor")
    status = descriptor_status()
    files = descriptor_files()
    st.radio("Global image descriptor", list(status),
             captions=[(f"from {files[name].name}" if name in files else "available" if reason is None
                        else f"unavailable: {reason.split(':')[0].split(';')[0]}")
                       for name, reason in status.items()],
             help="pixels: a downsampled, normalised image (instant; fine on the demo route). "
                  "efficientnet-lite0: a learned descriptor (about a minute for 600 images on 2 CPU cores, then cached on disk). "
                  f"Descriptors computed elsewhere: `vpr-explorer app --descriptors FILE` ({DESCRIPTORS_ENV}).",
             **state.bind("w_descriptor", "descriptor", v.descriptor, validate=check_descriptor))
    missing = {name: reason for name, reason in status.items() if reason is not None}
    if missing:
        with st.expander(f"Why {len(missing)} descriptor(s) cannot run here"):
            for name, reason in missing.items():
                st.caption(f"**{name}**: {reason}")

st.divider()
disk_problem = cache.disk_cache_problem()
if disk_problem is not None:
    st.warning(
        f"**The cache folder is not writable: nothing will be cached.** Descriptors are kept in memory only "
        f"(computed again after the app restarts) and the demo route is drawn in the temporary folder.\n\n"
        f"{disk_problem}",
        icon=":material/warning:",
    )
try:
    ds = cache.dataset(v.source)
except VPRInputError as exc:
    show_error(exc, hint="Pick another route above; the rest of the app uses it once it opens.")
    st.stop()

st.subheader(f"{'demo route' if v.source == DEMO else ds.name}: {ds.n_traversals} traversals × {ds.n_frames} frames")
facts = [f"{ds.n_images} images", f"traversals: {', '.join(ds.traversals)}",
         "route positions: " + ("yes" if ds.positions is not None else "none"),
         "places fixed by file names (Place####_Cond##_G##)" if ds.prepared_places is not None else "places: group/step"]
st.caption(" · ".join(facts) + f"  \nfolder: `{ds.root}`")
for note in ds.notes:
    st.caption(f"note: {note}")

try:
    cur = current()
    kept = (f"read from {files[v.descriptor]}" if v.descriptor in files
            else "cached on disk" if disk_problem is None else "in memory only")
    st.success(f"{v.descriptor} descriptors ready: {cur.data.descriptors.shape[0]} × {cur.data.descriptors.shape[1]} "
               f"({kept}; regrouping never recomputes them). Next: **Places**.", icon=":material/check_circle:")
    for note in cur.data.notes:
        st.caption(f"{v.descriptor}: {note}")
except VPRInputError as exc:
    show_error(exc, hint="Fix or remove the file named above, or pick another route or descriptor.")

st.subheader("Traversals")
frames = np.unique(np.linspace(0, ds.n_frames - 1, min(STRIP, ds.n_frames)).round().astype(int))
for t, name in enumerate(ds.traversals):
    st.caption(f"**{name}**: frames {', '.join(map(str, frames))} of {ds.n_frames}")
    cols = st.columns(len(frames))
    for col, f in zip(cols, frames):
        col.image(cache.thumbnail(ds.paths[t][f]), caption=f"{f}", width="stretch")

with st.expander("Memory and disk caches"):
    where = (f"cached on disk under `{settings.descriptor_folder()}`" if disk_problem is None
             else f"not cached on disk (`{settings.cache_root()}` is not writable; set {settings.CACHE_ENV})")
    st.caption(f"Descriptors are {where}, keyed by image content. "
               "Forgetting the in-memory results re-reads the folders (after you changed files).")
    if st.button("Forget in-memory results", key="w_clear"):
        cache.clear_all()
        st.rerun()
