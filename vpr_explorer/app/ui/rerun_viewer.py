"""rerun's web viewer as a Streamlit component that reports its time cursor to the page.

The viewer is rerun-notebook's (``rerun-sdk[notebook]``, the same version as rerun-sdk):
its ``static/`` folder holds ``widget.js`` (an anywidget module), ``widget.css`` and
``re_viewer_bg.wasm``, which ``widget.js`` fetches from beside itself. Our own
``app/static/rerun_viewer/index.html`` starts it and speaks Streamlit's component protocol
(its comment says how). rerun-notebook is found, never imported (its import starts
anywidget and reaches for the network).

Streamlit serves a component's files only from inside its folder (a symlink that leads out
is refused), so the four files are gathered under the cache (``settings.cache_root()``):
``<cache>/rerun_viewer/<rerun-notebook version>-<12 hex of index.html's SHA-256>/``:
rerun-notebook's files each a hard link to its source, or a copy where a link cannot be made
(another file system); the page a copy (a link would change with an edit of the package's
file, under the name of its former contents). The
folder is built under a temporary name (``settings.temporary_name``) and renamed into place
whole, so it is written once, two processes racing both end with the one that won, and a
writer killed mid-way leaves only a temporary, never used and removed once stale
(``descriptors.cache.is_stale``). A folder in place whose files are not all there at their
sources' sizes is replaced the same way.

``viewer`` draws it and returns the latest ``Cursor`` the viewer sent (``None`` before the
first); ``on_cursor`` is called with each cursor it sends, at the start of the rerun it causes,
before any widget is drawn.

The other way, the page moves the cursor with ``request_seek``, called from the ``on_change``
callback of the widget the user edits (the Playback page's query box): the next draw sends a
``Seek`` (a token and the position) with the component's arguments, and the viewer puts its
cursor there, paused, once per token. Every draw sends the latest seek again, so the reruns
the cursor itself causes while it plays or is dragged (the page redrawn with the cursor's own
earlier positions) carry no new token and move nothing. A request that comes in the same rerun
as a cursor is not sought (``next_seek``): the browser can send a rerun with the widget's value
from before it drew the cursor's last position, and that value is the cursor's own earlier
position coming back; ``on_cursor`` is then called again with the cursor, so that the page
ends the rerun where the cursor is. The seek, the request and the mark of a cursor live in
``st.session_state`` under the viewer's key with the suffixes ``SEEK``, ``REQUESTED`` and ``MOVED``.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import importlib.util
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import streamlit as st
import streamlit.components.v1 as components

from vpr_explorer.descriptors.cache import is_stale
from vpr_explorer.errors import VPRInputError
from vpr_explorer.settings import cache_root, temporary_name, temporary_owner

INDEX = Path(__file__).resolve().parents[1] / "static" / "rerun_viewer" / "index.html"
"""The component's page (package data)."""
ASSETS = ("widget.js", "widget.css", "re_viewer_bg.wasm")
"""rerun-notebook's files the page loads, from its ``static/`` folder."""
FOLDER = "rerun_viewer"
"""The cache's folder of component folders, one per rerun-notebook version and page."""
SEEK = ":seek"
"""Suffix of the viewer's key in ``st.session_state``: the latest ``Seek`` sent (``None`` before the first)."""
REQUESTED = ":seek_requested"
"""Suffix of the viewer's key in ``st.session_state``: the position ``request_seek`` asked for, until drawn."""
MOVED = ":cursor_moved"
"""Suffix of the viewer's key in ``st.session_state``: a cursor came in this rerun, until drawn."""
NOTEBOOK = "rerun-notebook"
INSTALL = "pip install 'rerun-sdk[notebook]>=0.41,<0.42'"


@dataclass(frozen=True)
class Cursor:
    """Where the viewer's time cursor is: a recording, its active timeline (``None``: not said yet) and the time."""

    recording_id: str
    timeline: str | None
    time: float

    @classmethod
    def from_value(cls, value: object) -> Cursor | None:
        """The component's value as a cursor; ``None`` for anything else (no value yet, a malformed one)."""
        if not isinstance(value, dict):
            return None
        rid, timeline, t = value.get("recording_id"), value.get("timeline"), value.get("time")
        if not isinstance(rid, str) or not (timeline is None or isinstance(timeline, str)):
            return None
        if isinstance(t, bool) or not isinstance(t, (int, float)):
            return None
        return cls(rid, timeline, float(t))

    def position(self, recording_id: str, timeline: str, n: int) -> int | None:
        """The position on ``timeline`` of ``recording_id`` (``0..n-1``, the nearest end outside it); else ``None``.

        A cursor whose timeline is not said yet counts as ``timeline``: the recording's
        blueprint opens the viewer on it.
        """
        if self.recording_id != recording_id or self.timeline not in (None, timeline) or n < 1:
            return None
        if self.time != self.time:  # NaN
            return None
        return int(min(max(round(self.time), 0), n - 1))


@dataclass(frozen=True)
class Seek:
    """The page's request that the viewer put its cursor at ``sequence`` on its timeline, paused.

    The viewer applies a seek once: when its ``token`` differs from the last one it applied
    (or saw on its first draw, when ``sequence`` already holds the position).
    """

    token: int
    sequence: int

    def to_arg(self) -> list[int]:
        """The component's ``seek`` argument: ``[token, sequence]``."""
        return [self.token, self.sequence]


def next_seek(last: Seek | None, requested: int | None, cursor_moved: bool) -> Seek | None:
    """The seek a draw sends: a fresh one (``last``'s token + 1, from 1) at ``requested``, else ``last`` again.

    Args:
        last: the seek the previous draw sent (``None``: none yet).
        requested: the position ``request_seek`` asked for since that draw (``None``: none).
        cursor_moved: whether the viewer sent a cursor since that draw; a request then is not
            sought (``last`` again), since it is the cursor's own earlier position echoed by
            the widget (see the module docstring).

    Raises:
        VPRInputError: ``requested`` is negative.
    """
    if requested is None or cursor_moved:
        return last
    if requested < 0:
        raise VPRInputError(f"seek: position {requested} is before the timeline's start; give a position of 0 or more")
    return Seek(1 if last is None else last.token + 1, int(requested))


def request_seek(key: str, sequence: int) -> None:
    """Ask the viewer drawn under ``key`` to put its cursor at ``sequence`` (paused) when it is next drawn.

    For the ``on_change`` callback of a widget that shows the cursor's position: a callback
    runs on the user's change only, before the rerun's script draws the viewer.
    """
    st.session_state[key + REQUESTED] = int(sequence)


def notebook_static() -> Path:
    """rerun-notebook's ``static/`` folder, with every file of ``ASSETS`` in it.

    Raises:
        VPRInputError: rerun-notebook is not installed, or not at rerun-sdk's version, or a file is missing.
    """
    spec = importlib.util.find_spec("rerun_notebook")
    if spec is None or not spec.submodule_search_locations:
        raise VPRInputError(f"rerun-notebook is not installed: {INSTALL}")
    ours, theirs = importlib.metadata.version(NOTEBOOK), importlib.metadata.version("rerun-sdk")
    if ours.split(".")[:2] != theirs.split(".")[:2]:
        raise VPRInputError(f"rerun-notebook {ours} does not match rerun-sdk {theirs}: {INSTALL}")
    static = Path(list(spec.submodule_search_locations)[0]) / "static"
    missing = [name for name in ASSETS if not (static / name).is_file()]
    if missing:
        raise VPRInputError(f"rerun-notebook's {static} lacks {', '.join(missing)}: reinstall it ({INSTALL})")
    return static


def _sources(static: Path, index: Path) -> dict[str, Path]:
    return {"index.html": index, **{name: static / name for name in ASSETS}}


def _complete(folder: Path, sources: dict[str, Path]) -> bool:
    try:
        return all((folder / name).stat().st_size == src.stat().st_size for name, src in sources.items())
    except OSError:
        return False


def _place(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:  # another file system, or links not allowed: a copy
        shutil.copyfile(src, dst)


def _remove_stale(parent: Path) -> None:
    now = time.time()
    for leftover in parent.iterdir():
        owner = temporary_owner(leftover.name)
        if owner is not None and is_stale(leftover, owner, now):
            shutil.rmtree(leftover, ignore_errors=True)


def component_folder(static: Path | None = None, *, root: Path | None = None, index: Path = INDEX) -> Path:
    """The component's folder under the cache, built once (see the module docstring).

    Args:
        static: rerun-notebook's ``static/`` folder; default ``notebook_static()``.
        root: the cache root; default ``settings.cache_root()``.
        index: the component's page.

    Raises:
        VPRInputError: rerun-notebook is unusable (``notebook_static``), or the folder cannot be written.
    """
    static = notebook_static() if static is None else static
    sources = _sources(static, index)
    digest = hashlib.sha256(index.read_bytes()).hexdigest()[:12]
    parent = (cache_root() if root is None else root) / FOLDER
    folder = parent / f"{importlib.metadata.version(NOTEBOOK)}-{digest}"
    if _complete(folder, sources):
        return folder
    try:
        parent.mkdir(parents=True, exist_ok=True)
        _remove_stale(parent)
        staging = parent / temporary_name(folder.name)
        staging.mkdir()
        try:
            for name, src in sources.items():
                if name == "index.html":
                    shutil.copyfile(src, staging / name)
                else:
                    _place(src, staging / name)
            try:
                staging.rename(folder)
            except OSError:
                if _complete(folder, sources):
                    return folder  # another process won the race
                # an incomplete folder in place (its files removed by hand): moved aside, then replaced
                aside = parent / temporary_name(folder.name)
                folder.rename(aside)
                shutil.rmtree(aside, ignore_errors=True)
                staging.rename(folder)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
    except OSError as exc:
        raise VPRInputError(f"cannot gather rerun's viewer in {parent} ({exc.strerror or exc}): choose a "
                            "writable cache folder with VPR_EXPLORER_CACHE") from exc
    return folder


@st.cache_resource(show_spinner=False)
def _component() -> Callable[..., object]:
    """The component, declared on its folder once per server (a refusal is not kept: the next run tries again)."""
    return components.declare_component("rerun_viewer", path=str(component_folder()))


def viewer(grpc_url: str, recording_id: str, *, timeline: str, height: int, key: str, sequence: int | None = None,
           on_cursor: Callable[[Cursor], None] | None = None) -> Cursor | None:
    """Draw rerun's viewer connected to ``grpc_url`` and showing ``recording_id``; its latest cursor on ``timeline``.

    Args:
        grpc_url: the gRPC server's ``rerun+http://…/proxy`` URL (``recording.ViewerServers.grpc_url``).
        recording_id: the recording to show first (the viewer lists every recording of the server).
        timeline: the timeline whose cursor is reported.
        sequence: where the cursor starts on ``timeline`` (paused) once the viewer shows the recording;
            ``None`` leaves it where the viewer puts it (the end). Read when the recording first shows,
            ignored on later reruns; ``request_seek`` moves the cursor after that.
        height: pixels.
        key: the widget key; one viewer iframe lives as long as the key is drawn.
        on_cursor: called with each cursor the viewer sends, before the rerun it causes draws anything,
            and again while drawing when a seek requested in the same rerun is not sought (``next_seek``).

    Raises:
        VPRInputError: the viewer cannot be gathered (``component_folder``); the page then shows rerun's
            own web viewer.
    """
    draw = _component()

    def changed() -> None:
        cursor = Cursor.from_value(st.session_state.get(key))
        if cursor is not None:
            st.session_state[key + MOVED] = True
            if on_cursor is not None:
                on_cursor(cursor)

    requested = st.session_state.pop(key + REQUESTED, None)
    moved = bool(st.session_state.pop(key + MOVED, False))
    seek = next_seek(st.session_state.get(key + SEEK), requested, moved)
    st.session_state[key + SEEK] = seek
    if requested is not None and moved and on_cursor is not None:
        cursor = Cursor.from_value(st.session_state.get(key))
        if cursor is not None:  # the widget's echo may have been committed after the cursor: the cursor holds
            on_cursor(cursor)
    value = draw(grpc_url=grpc_url, recording_id=recording_id, timeline=timeline, height=int(height),
                 sequence=None if sequence is None else int(sequence), seek=None if seek is None else seek.to_arg(),
                 key=key, default=None, on_change=changed)
    return Cursor.from_value(value)
