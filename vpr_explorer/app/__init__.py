"""The explorer app, shipped in the package: ``vpr-explorer app`` serves it from any directory.

The one Streamlit leaf of the tree: the library never imports streamlit, only this
sub-package does (and only its modules that run inside the server).

* ``explorer.py``: the entry script (what ``streamlit run`` is pointed at): page
  config, the view read from the URL, ``st.navigation`` over ``pages/``, the sidebar.
* ``pages/``: one script per page, one body for every layout; a page is widgets → one
  library call → render.
* ``ui/``: what the pages share: ``state`` (the view, mirrored into the URL), ``current``
  (the view resolved into one dataset value and its places), ``cache`` (every Streamlit
  cache), ``controls``, ``candidates``, ``group_step``, ``place_map``, ``runs``,
  ``feedback``, ``routing``, ``sidebar``.
* ``launch``: the command line's ``app`` sub-command; imports no streamlit.

A checkout's top-level ``app.py`` and ``pages/`` (for ``streamlit run app.py``) only hand
over to these.

The app serves one data root (``DATA_ROOT_ENV``, set by ``vpr-explorer app --data-root``;
unset: ``VPR_EXPLORER_DATA``, else the current directory). Every path that comes from a
session (a link's ``source=`` and ``descriptors=``, the Dataset page's path boxes and its
folder list) goes through ``under_data_root`` first: a path that does not lie under the root
once symbolic links and ``..`` are resolved is refused with ``OutsideDataRoot``, before
anything of it is read, listed or stat'ed beyond that check. The built-in ``demo`` route
opens wherever the root is. The files the operator names at start (``DESCRIPTORS_ENV``,
``vpr-explorer app --descriptors``) are read wherever they lie: a link can only pick one by
name, never by path. This module and ``launch`` import no streamlit.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

from vpr_explorer.errors import VPRInputError
from vpr_explorer.settings import DATA_ENV

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
named by its file's stem (a VPR-methods-evaluation run folder by its folder's), and the first is
the descriptor a session opens when its link names none (``vpr-explorer app --descriptors``)."""
DATA_ROOT_ENV = "VPR_EXPLORER_DATA_ROOT"
"""The app's data root (``vpr-explorer app --data-root``): a session opens only folders and files under it.
Unset: ``VPR_EXPLORER_DATA``, else the current directory (``data_root``)."""
DATA_ROOT_HINT = "start the app with `vpr-explorer app --data-root DIR` to serve another folder"


def descriptor_files(environ: Mapping[str, str] = os.environ) -> dict[str, Path]:
    """The files (or VPR-methods-evaluation run folders) ``DESCRIPTORS_ENV`` names, by descriptor name (the
    file's stem), in its order."""
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


class OutsideDataRoot(VPRInputError):
    """A path from a session (a link, a path box) that does not lie under the data root: nothing of it is read.

    Attributes:
        path: the path as it was given.
        root: the data root, resolved.
    """

    def __init__(self, what: str, path: str, root: Path) -> None:
        super().__init__(f"{what} {path}: {outside_reason(root)}")
        self.path = path
        self.root = root


def outside_reason(root: Path) -> str:
    """Why a path outside ``root`` is refused, and how to serve another folder."""
    return (f"not under the app's data root {root}; a link or a typed path opens only folders and files under it "
            f"({DATA_ROOT_HINT})")


def data_root(environ: Mapping[str, str] = os.environ) -> Path:
    """The app's data root, resolved: ``DATA_ROOT_ENV``, else ``VPR_EXPLORER_DATA``, else the current directory."""
    for variable in (DATA_ROOT_ENV, DATA_ENV):
        value = environ.get(variable, "").strip()
        if value:
            return Path(value).expanduser().resolve()
    return Path.cwd().resolve()


def under_data_root(path: str | os.PathLike[str], root: Path | None = None, *, what: str = "path") -> Path:
    """``path`` resolved (symbolic links and ``..`` followed), when it lies under the data root.

    A relative path is taken relative to the root; ``~`` and ``~/…`` are the home folder.
    Only the path's own components are looked at (to resolve it): nothing in it is read or
    listed, and the refusal says the same whether it exists or not.

    Args:
        root: the data root; default ``data_root()``.
        what: how the path is named in the message (``"source"``, ``"descriptor file"``).

    Raises:
        OutsideDataRoot: the resolved path is not the root or under it.
        VPRInputError: a path holding a NUL character, or a loop of symbolic links.
    """
    text = os.fspath(path)
    root = (data_root() if root is None else Path(root)).resolve()
    if "\x00" in text:
        raise VPRInputError(f"{what} {text!r}: holds a NUL character; give a path")
    given = Path.home() / text[2:] if text == "~" or text.startswith("~/") else Path(text)
    candidate = given if given.is_absolute() else root / given
    try:
        resolved = candidate.resolve()
    except (RuntimeError, OSError):  # a loop of symbolic links, or a component that cannot be looked at
        if not Path(os.path.normpath(candidate)).is_relative_to(root):
            raise OutsideDataRoot(what, text, root) from None
        raise VPRInputError(f"{what} {text}: a loop of symbolic links; give the path of a folder or file") from None
    if not resolved.is_relative_to(root):
        raise OutsideDataRoot(what, text, root)
    return resolved
