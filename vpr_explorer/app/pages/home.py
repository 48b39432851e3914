"""Dataset page: pick the route (and its layout) and the descriptor (or a file of them), see the images."""

import pandas  # noqa: F401  # before plotly: plotly.py#2433
from pathlib import Path

import numpy as np
import streamlit as st

from vpr_explorer import settings
from vpr_explorer.app import (
    DATA_ROOT_ENV,
    DATA_ROOT_HINT,
    DESCRIPTORS_ENV,
    OutsideDataRoot,
    data_root,
    descriptor_files,
    under_data_root,
)
from vpr_explorer.descriptors import available_extractors
from vpr_explorer.descriptors.custom import MODELS_ENV
from vpr_explorer.errors import VPRInputError
from vpr_explorer.data.groundtruth import DEFAULT_RADIUS
from vpr_explorer.data.layouts import Layout, RetrievalDataset
from vpr_explorer.pipeline import DEMO
from vpr_explorer.views.numbers import THUMBNAIL_CHARS, radius_of

from vpr_explorer.app.ui import cache, state
from vpr_explorer.app.ui.current import current
from vpr_explorer.app.ui.feedback import show_error, show_rejected
from vpr_explorer.app.ui.fetch_panel import fetch_panel
from vpr_explorer.app.ui.routing import ensure_routed

ensure_routed(__file__)

OTHER = "__folder__"
FILE = "__file__"  # the descriptor radio's "a file of descriptors" choice
STRIP = 8  # thumbnails per traversal
RADIUS_RANGE = (0.1, 10_000.0)  # the radius box's range in metres (a bare string here: Streamlit would draw it)
LAYOUT_LABELS = {
    Layout.TRAVERSALS: "traversals: one sub-folder per traversal, frame i = the same spot",
    Layout.PREPARED: "prepared: Place####_Cond##_G## images",
    Layout.DATABASE_QUERIES: "database-queries: database/ and queries/, @UTM_east@UTM_north@ in the names",
    Layout.VPR_BENCH: "vpr-bench: ref/, query/ and ground_truth_new.npy",
    Layout.TRAVERSAL_POSITIONS: "traversal-positions: traversal folders, each with positions.csv",
    Layout.MANIFEST: "manifest: a CSV of path, role (database/query), x,y or place",
}

st.title("VPR Threshold Explorer")
st.markdown(
    "Why is a query accepted or rejected? Trinh & Lyons fit, for every place, a Gaussian mixture to the "
    "similarities between its images and **other** places (the *negative* scores), and set a per-place "
    "threshold θ_p from it. Pick a route and a descriptor here; the other pages show the places, the "
    "thresholds, single queries and the evaluation protocols."
)
show_rejected()
outside = st.session_state.pop("outside_root", None)  # a typed path the data root refused: nothing of it read
if outside:
    st.warning(f"{outside}\n\nThe previous value is kept.", icon=":material/warning:")
v = state.view()
root = data_root()


def found_datasets() -> list[str]:
    """The data root's sub-folders (not hidden ones, nor links that lead out of it), resolved."""
    try:
        entries = sorted(root.iterdir())
    except OSError:
        return []
    found = []
    for entry in entries:
        if entry.name.startswith("."):
            continue
        try:
            path = under_data_root(entry, root)  # before is_dir: a link out of the root is not even stat'ed
        except VPRInputError:
            continue
        if path.is_dir() and str(path) not in found:
            found.append(str(path))
    return found


def confined(path: str, what: str) -> str | None:
    """A typed path under the data root, resolved; ``None`` (and a warning kept for the next run) outside it."""
    if not path or (what == "folder" and path == DEMO):
        return path
    try:
        return str(under_data_root(path, root, what=what))
    except OutsideDataRoot as exc:
        st.session_state["outside_root"] = str(exc)
        return None


def check_folder(path: object) -> None:
    if not str(path).strip():
        raise VPRInputError("folder path: type the path of a dataset folder (one sub-folder per traversal)")
    cache.dataset(str(path).strip(), v.layout, v.radius)


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
        if choice != OTHER and state.commit(source=choice, validate=lambda: check_folder(choice)):
            st.session_state["file_mode"] = False  # a new dataset drops the descriptor file of the old one

    st.selectbox(
        "Dataset", options, key="w_source", on_change=pick_source,
        format_func=lambda o: labels.get(o, f"{Path(o).name}  (under the data root)"),
        help=f"The folders in the app's data root {root} ({DATA_ROOT_ENV}), the demo route, or a folder path under "
             "that root: one sub-folder per traversal (frame i = same spot), or Place####_Cond##_G## images. "
             f"Nothing outside the data root is opened: {DATA_ROOT_HINT}.",
    )
    if folder_mode:
        # Not bound to the view: a path that fails to open stays in the box, to be corrected.
        st.session_state.setdefault("w_folder", v.source if v.source not in options else "")

        def open_folder() -> None:
            path = confined(st.session_state["w_folder"].strip(), "folder")
            if path is not None and state.commit(source=path, validate=lambda: check_folder(path)):
                st.session_state["file_mode"] = False

        st.text_input("Folder path", key="w_folder", on_change=open_folder,
                      placeholder=str(root / "GardensPointWalking"),
                      help="Press Enter to open it. The folder is checked before it replaces the current route. "
                           "A manifest is a .csv file: type its path. Absolute, or relative to the data root "
                           f"{root}; nothing outside that root is opened.")

    try:
        detected = cache.layout_of(v.source).value
    except VPRInputError:
        detected = "unknown"
    layouts = [x.value for x in Layout]
    st.selectbox(
        "Layout", layouts,
        format_func=lambda x: f"auto (detected: {detected})" if x == Layout.AUTO.value else LAYOUT_LABELS[Layout(x)],
        help="How the folder is read: detected from what it holds, or named (as `--layout` on the command line). "
             "Database/queries layouts carry their ground truth: positions (a query's right database images lie "
             "within the radius) or lists.",
        **state.bind("w_layout", "layout", v.layout, validate=lambda x: cache.dataset(v.source, str(x), v.radius)),
    )

with col_desc:
    st.subheader("Descriptor")
    status = descriptor_status()
    files = descriptor_files()
    file_mode = v.descriptors is not None or st.session_state.get("file_mode", False)
    st.session_state["w_descriptor"] = FILE if file_mode else v.descriptor

    def pick_descriptor() -> None:
        choice = st.session_state["w_descriptor"]
        st.session_state["file_mode"] = choice == FILE
        if choice != FILE:
            state.commit(descriptor=choice, descriptors=None, validate=lambda: check_descriptor(choice))

    captions = [(f"from {files[name].name}" if name in files else "available" if reason is None
                 else f"unavailable: {reason.split(':')[0].split(';')[0]}") for name, reason in status.items()]
    st.radio("Global image descriptor", [*status, FILE], key="w_descriptor", on_change=pick_descriptor,
             format_func=lambda name: "A descriptor file…" if name == FILE else name,
             captions=[*captions, "computed elsewhere: .npz, .npy (+ names), hloc .h5, a VPR-methods-evaluation run"],
             help="pixels: a downsampled, normalised image (instant; fine on the demo route). "
                  "efficientnet-lite0: a learned descriptor (about a minute for 600 images on 2 CPU cores, then cached on disk). "
                  "Descriptors computed elsewhere (NetVLAD, CosPlace, MixVPR, …): type the file's path, or start the app "
                  f"with `vpr-explorer app --descriptors FILE` ({DESCRIPTORS_ENV}). A file is named by its stem.")
    if file_mode:
        # Not bound to the view: a path that fails its checks stays in the box, to be corrected.
        st.session_state.setdefault("w_descriptor_file", v.descriptors or "")

        def open_file() -> None:
            path = confined(st.session_state["w_descriptor_file"].strip(), "descriptor file")
            if path is not None:
                state.commit(descriptors=path, validate=lambda: cache.check_descriptor_file(path))

        st.text_input("Descriptor file path", key="w_descriptor_file", on_change=open_file,
                      placeholder=str(root / "netvlad.npz"),
                      help="Press Enter to read it. .npz: arrays `names` (paths relative to the dataset folder) and "
                           "`descriptors`; .npy: rows in the order `vpr-explorer list --dataset PATH` prints (names "
                           "in <stem>.txt beside it, optional); .h5: hloc's `<image name>/global_descriptor`. Its "
                           "images must be the dataset's: missing and extra ones are listed. A folder: a "
                           "VPR-methods-evaluation log folder (`database_descriptors.npy`, `queries_descriptors.npy`, "
                           "rows in VME's order) for a database-queries dataset, named by the folder's stem.")
    missing = {name: reason for name, reason in status.items() if reason is not None}
    if missing:
        with st.expander(f"Why {len(missing)} descriptor(s) cannot run here"):
            for name, reason in missing.items():
                st.caption(f"**{name}**: {reason}")

fetch_panel(root)
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
    ds = cache.dataset(v.source, v.layout, v.radius)
except VPRInputError as exc:
    show_error(exc, hint="Pick another route or layout above; the rest of the app uses it once it opens.")
    st.stop()


def show_retrieval(ds: RetrievalDataset) -> None:
    """The facts, the radius and a strip of database and query images of a database/queries dataset."""
    gt = ds.ground_truth
    st.subheader(f"{ds.name}: {ds.n_database:,} database and {ds.n_queries:,} query images ({ds.layout.value})")
    facts = [f"right database images: {gt.description}",
             f"{gt.n_unknown:,} of {ds.n_queries:,} queries with no right database image (unknown places)",
             "positions: " + ("yes (UTM or metres)" if ds.database_xy is not None else "none"),
             "places given by the layout" if ds.database_place is not None else "places: group/step (Places page)"]
    st.caption(" · ".join(facts) + f"  \nfolder: `{ds.root}`")
    for note in ds.notes:
        st.caption(f"note: {note}")
    if radius_of(ds) is not None:
        st.number_input(
            "radius (m): a database image within it is right for a query", *RADIUS_RANGE,
            step=5.0, format="%g", help=f"The field's convention is {DEFAULT_RADIUS:g} m (VPR datasets downloader, most "
                                         "papers). The ground truth, every table and the map follow it.",
            **state.bind("w_radius", "radius", float(v.radius or DEFAULT_RADIUS)))
    show_descriptors()
    for label, paths in (("database", ds.database_paths), ("queries", ds.query_paths)):
        shown = np.unique(np.linspace(0, len(paths) - 1, min(STRIP, len(paths))).round().astype(int))
        st.caption(f"**{label}**: images {', '.join(map(str, shown))} of {len(paths):,}")
        for col, i in zip(st.columns(len(shown)), shown):
            name = Path(paths[i]).name  # "@east@north@…@.jpg" names do not fit: the index, as the caption above
            col.image(cache.thumbnail(paths[i]), caption=name if len(name) <= THUMBNAIL_CHARS else f"image {i}",
                      width="stretch")


def show_descriptors() -> None:
    try:
        cur = current()
        kept = (f"read from {cache.descriptor_path(v.descriptor, v.descriptors)}"
                if v.descriptors is not None or v.descriptor in files
                else "cached on disk" if disk_problem is None else "in memory only")
        st.success(f"{cur.data.descriptor} descriptors ready: {cur.data.descriptors.shape[0]} × "
                   f"{cur.data.descriptors.shape[1]} ({kept}; regrouping never recomputes them). Next: **Places**.",
                   icon=":material/check_circle:")
        for note in cur.data.notes:
            st.caption(f"{cur.data.descriptor}: {note}")
    except VPRInputError as exc:
        show_error(exc, hint="Fix or remove the file named above, or pick another route or descriptor.")
        if v.descriptors is not None and st.button("Read the file again", key="w_reread",
                                                   help="After you fixed the file; an edited file is never served "
                                                        "from memory anyway (it is keyed by its size and time)."):
            st.rerun()


def show_traversals(ds) -> None:
    """The facts and a strip of frames of every traversal of an aligned-traversals dataset."""
    st.subheader(f"{'demo route' if v.source == DEMO else ds.name}: {ds.n_traversals} traversals × {ds.n_frames} frames")
    facts = [f"{ds.n_images} images", f"traversals: {', '.join(ds.traversals)}",
             "route positions: " + ("yes" if ds.positions is not None else "none"),
             "places fixed by file names (Place####_Cond##_G##)" if ds.prepared_places is not None
             else "places: group/step"]
    st.caption(" · ".join(facts) + f"  \nfolder: `{ds.root}`")
    for note in ds.notes:
        st.caption(f"note: {note}")

    show_descriptors()

    st.subheader("Traversals")
    frames = np.unique(np.linspace(0, ds.n_frames - 1, min(STRIP, ds.n_frames)).round().astype(int))
    for t, name in enumerate(ds.traversals):
        st.caption(f"**{name}**: frames {', '.join(map(str, frames))} of {ds.n_frames}")
        cols = st.columns(len(frames))
        for col, f in zip(cols, frames):
            col.image(cache.thumbnail(ds.paths[t][f]), caption=f"{f}", width="stretch")


if isinstance(ds, RetrievalDataset):
    show_retrieval(ds)
else:
    show_traversals(ds)

with st.expander("Memory and disk caches"):
    where = (f"cached on disk under `{settings.descriptor_folder()}`" if disk_problem is None
             else f"not cached on disk (`{settings.cache_root()}` is not writable; set {settings.CACHE_ENV})")
    st.caption(f"Descriptors are {where}, keyed by image content. "
               "Forgetting the in-memory results re-reads the folders (after you changed files).")
    if st.button("Forget in-memory results", key="w_clear"):
        cache.clear_all()
        st.rerun()
