"""The view a session is looking at, kept in ``st.session_state`` and mirrored into the URL.

One frozen ``View`` holds every choice that more than one page reads: the dataset (its
layout, and the positive radius of a position-tagged one), the descriptor (an extractor, or
a file of descriptors computed elsewhere), group/step and their reading (in frames, or in
metres along a route or over a lattice), the query traversal, the selected place and query
(a query traversal's frame, or a query image of a database/queries dataset). It lives in
``st.session_state["view"]``; ``sync_url`` writes it into ``st.query_params`` on every run,
so the address bar always holds a link that reopens the same view, and a fresh session
starts from the URL it was opened with. A link's dataset (``source=``) and descriptor file
(``descriptors=``) are resolved against the app's data root (``app.under_data_root``) and
kept resolved; outside it they are ignored with the other refused parameters (one warning),
and nothing of them is read.

Widgets edit it through ``bind``: the widget's own state is set from the view before it
is drawn and copied back in its ``on_change`` callback, so the view is the one source
of truth even when another page (or a click on a figure) changes it.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import streamlit as st

from vpr_explorer.app import OutsideDataRoot, outside_reason, started_view, under_data_root
from vpr_explorer.errors import VPRInputError
from vpr_explorer.data.groundtruth import DEFAULT_RADIUS, check_radius
from vpr_explorer.data.layouts import Layout
from vpr_explorer.method.places import MetricPlaceSpec, PlaceGeometry, PlaceSpec, Reading
from vpr_explorer.pipeline import DEMO
from vpr_explorer.views.numbers import DEFAULT_GROUP_M

DEFAULT_DESCRIPTOR = "pixels"
"""Always available and instant; efficientnet-lite0 is the learned choice, one click away."""
DEFAULT_GROUP = 3
K_RANGE = (-1.0, 3.0)
"""The k sliders' range."""
THETA_RANGE = (-1.0, 1.0)
"""A user's global θ: a cosine similarity."""

_KEY = "view"
_PAGE_KEY = "page_params"
_INT_FIELDS = ("group", "step", "place", "frame")
_FLOAT_FIELDS = ("k", "theta")
_METRE_FIELDS = ("radius", "group_m", "step_m")
# Changing one of these makes the fields after it meaningless: they are reset.
_PLACES = ("group", "step", "geometry", "group_m", "step_m", "query", "place", "frame")
_RESETS = {
    "source": (*_PLACES, "descriptors"),  # a descriptor file describes one dataset's images
    "layout": _PLACES,
    "radius": ("place",),
    "group": ("place",),
    "step": ("place",),
    "reading": ("place",),
    "geometry": ("place",),
    "group_m": ("place",),
    "step_m": ("place",),
}


@dataclass(frozen=True)
class View:
    """Everything that identifies what the app shows; ``None`` means "the dataset's default"."""

    source: str = DEMO
    descriptor: str = DEFAULT_DESCRIPTOR
    group: int | None = None
    step: int | None = None
    reading: str = Reading.STRIDE.value
    query: str | None = None
    place: int | None = None
    frame: int | None = None
    k: float = 0.0
    theta: float | None = None
    layout: str = Layout.AUTO.value
    radius: float | None = None
    geometry: str | None = None
    group_m: float | None = None
    step_m: float | None = None
    descriptors: str | None = None  # a descriptor file typed on the Dataset page; ``descriptor`` is its stem

    def to_params(self) -> dict[str, str]:
        """Query parameters for the fields that differ from the defaults."""
        default = View()
        return {f.name: str(getattr(self, f.name)) for f in dataclasses.fields(self)
                if getattr(self, f.name) != getattr(default, f.name) and getattr(self, f.name) is not None}

    @classmethod
    def from_params(cls, params: dict[str, str]) -> tuple[View, list[str]]:
        """A view from query parameters, and the parameters that had to be ignored.

        Each ignored one is said as "name='value': why; using what instead".
        """
        values: dict[str, object] = {}
        ignored = []
        names = {f.name for f in dataclasses.fields(cls)}
        for name, text in params.items():
            if name not in names:
                continue
            try:
                values[name] = _parse(name, text)
            except ValueError as exc:
                ignored.append(f"{name}={text!r}: {exc}; using {_INSTEAD[name]}")
        # step against group: only the pair can say whether places would overlap
        if "step" in values:
            try:
                PlaceSpec(values.get("group", DEFAULT_GROUP), values["step"], values.get("reading", Reading.STRIDE))
            except VPRInputError as exc:
                ignored.append(f"step={params['step']!r}: {exc}; using {_INSTEAD['step']}")
                del values["step"]
        if "step_m" in values:
            try:
                MetricPlaceSpec(values.get("group_m", DEFAULT_GROUP_M), values["step_m"],
                                values.get("reading", Reading.STRIDE))
            except VPRInputError as exc:
                ignored.append(f"step_m={params['step_m']!r}: {exc}; using {_INSTEAD['step_m']}")
                del values["step_m"]
        if "descriptors" in values:  # a descriptor file is named by its stem, everywhere
            values["descriptor"] = Path(values["descriptors"]).expanduser().stem
        elif "descriptors" in params and values.get("descriptor") == Path(params["descriptors"]).stem:
            del values["descriptor"]  # the refused file's stem names no descriptor of this server
        return cls(**values), ignored


_INSTEAD = {
    "source": "the demo route",
    "group": f"the default ({DEFAULT_GROUP})",
    "step": "the dataset's default step",
    "reading": f"the {Reading.STRIDE.value} reading",
    "place": "the default place",
    "frame": "the default frame",
    "k": "k = 0 (the paper's thresholds)",
    "theta": "no global θ of your own",
    "layout": "the detected layout",
    "radius": f"the field's {DEFAULT_RADIUS:g} m",
    "geometry": "the dataset's default geometry",
    "group_m": "the default group in metres",
    "step_m": "the default step in metres",
    "descriptors": f"the descriptor named by descriptor, else {DEFAULT_DESCRIPTOR}",
    "descriptor": f"the default descriptor ({DEFAULT_DESCRIPTOR})",
}
"""What the app uses when a link's parameter is refused."""


def _parse(name: str, text: str) -> object:
    """One query parameter's value; ``ValueError`` saying why it cannot be used."""
    if name in _INT_FIELDS:
        try:
            value = int(text)
        except ValueError:
            raise ValueError("not a whole number") from None
        if name in ("group", "step"):
            try:  # the library's own limits and message (the skip reading checks each on its own)
                PlaceSpec(value, 1, Reading.SKIP) if name == "group" else PlaceSpec(1, value, Reading.SKIP)
            except VPRInputError as exc:
                raise ValueError(str(exc)) from None
        elif value < 0:
            raise ValueError("must be 0 or more")
        return value
    if name in _FLOAT_FIELDS:
        try:
            value = float(text)
        except ValueError:
            raise ValueError("not a number") from None
        low, high = K_RANGE if name == "k" else THETA_RANGE
        if not math.isfinite(value):
            raise ValueError("not a finite number")
        if not low <= value <= high:
            raise ValueError(f"outside {low:g} to {high:g}")
        return value
    if name in _METRE_FIELDS:
        try:
            value = float(text)
        except ValueError:
            raise ValueError("not a distance in metres") from None
        if not math.isfinite(value) or value <= 0:
            raise ValueError("must be a positive distance in metres, e.g. 25")
        if name == "radius":
            try:  # the library's own limit and message
                check_radius(value)
            except VPRInputError as exc:
                raise ValueError(str(exc).split(": ", 1)[-1]) from None
        else:
            try:  # the library's own limits and message
                MetricPlaceSpec(value, value, Reading.SKIP)
            except VPRInputError as exc:
                raise ValueError(str(exc).split(": ", 1)[-1]) from None
        return value
    if name == "reading" and text not in {r.value for r in Reading}:
        raise ValueError(f"choose {' or '.join(r.value for r in Reading)}")
    if name == "layout" and text not in {x.value for x in Layout}:
        raise ValueError(f"choose one of {', '.join(x.value for x in Layout)}")
    if name == "geometry" and text not in {g.value for g in PlaceGeometry}:
        raise ValueError(f"choose {' or '.join(g.value for g in PlaceGeometry)}")
    if name == "descriptor" and text.strip().startswith("hub:"):
        raise ValueError("a hub:DIR descriptor runs the repository's code, which a link never does; name the model "
                         "in the app's VPR_EXPLORER_MODELS settings file and choose it by that name")
    if name == "descriptors" and not text.strip():
        raise ValueError("empty: give the path of a .npz, .npy or hloc .h5 file")
    if name == "source" and not text.strip():
        raise ValueError("empty: give a dataset folder under the app's data root")
    if name == "descriptors" or (name == "source" and text != DEMO):  # the first look at a session's path
        try:
            return str(under_data_root(text, what=name))
        except OutsideDataRoot as exc:
            raise ValueError(outside_reason(exc.root)) from None
        except VPRInputError as exc:
            raise ValueError(str(exc).split(": ", 1)[-1]) from None
    return text


def view() -> View:
    """The session's view; on the first run of a session, read from the URL.

    What the URL leaves out comes from what the app was started on (``vpr-explorer app
    --dataset``), else from ``View``'s defaults.
    """
    if _KEY not in st.session_state:
        params = {k: st.query_params[k] for k in st.query_params}
        v, ignored = View.from_params({**started_view(), **params})
        st.session_state[_KEY] = v
        fields = {f.name for f in dataclasses.fields(View)}
        st.session_state[_PAGE_KEY] = {k: text for k, text in params.items() if k not in fields}
        if ignored:
            st.session_state["url_ignored"] = ignored
    return st.session_state[_KEY]


def update(**changes: object) -> View:
    """Replace fields of the view (resetting those that depend on a changed one)."""
    old = view()
    for name in list(changes):
        if changes[name] != getattr(old, name):
            for dependent in _RESETS.get(name, ()):
                changes.setdefault(dependent, None)
    if changes.get("descriptors") is not None:
        changes["descriptor"] = Path(str(changes["descriptors"])).expanduser().stem
    elif "descriptors" in changes and old.descriptors is not None and "descriptor" not in changes:
        changes["descriptor"] = DEFAULT_DESCRIPTOR  # the file's stem names no extractor
    new = dataclasses.replace(old, **changes)
    st.session_state[_KEY] = new
    return new


def page_params() -> dict[str, str]:
    """One page's own settings kept in the URL beside the view (e.g. the Evaluation page's protocol).

    A read-only copy of the raw text values: on a session's first run they come from the
    link it was opened with; a page parses them itself (refusing bad ones with a warning)
    and writes them back with ``set_page_params``. Names must not be ``View`` fields;
    prefix them with the page (``eval_runs``).
    """
    view()
    return dict(st.session_state.get(_PAGE_KEY, {}))


def set_page_params(**values: object) -> None:
    """Keep page settings in the URL (``None`` removes one); written by ``sync_url`` with the view."""
    fields = {f.name for f in dataclasses.fields(View)}
    current = dict(st.session_state.get(_PAGE_KEY, {}))
    for name, value in values.items():
        if name in fields:
            raise ValueError(f"{name!r} is a View field: change it with update()")
        if value is None:
            current.pop(name, None)
        else:
            current[name] = str(value)
    st.session_state[_PAGE_KEY] = current


_DATASET_FIELDS = ("source", "layout", "radius", "descriptor", "descriptors")
_PLACE_FIELDS = ("group", "step", "reading", "geometry", "group_m", "step_m", "query")
PAGE_FIELDS: dict[str, tuple[str, ...]] = {
    "home": _DATASET_FIELDS,
    "places": (*_DATASET_FIELDS, *_PLACE_FIELDS, "frame"),
    "thresholds": (*_DATASET_FIELDS, *_PLACE_FIELDS, "place", "k", "theta"),
    "inspector": (*_DATASET_FIELDS, *_PLACE_FIELDS, "place", "frame", "k", "theta"),
    "evaluation": (*_DATASET_FIELDS, *_PLACE_FIELDS, "theta"),
    "playback": (*_DATASET_FIELDS, *_PLACE_FIELDS, "frame", "k"),
    "sweep": (*_DATASET_FIELDS, *_PLACE_FIELDS, "k", "theta"),
}
"""The view's fields each page reads (by page name): its link carries these and no others."""
PAGE_PREFIXES: dict[str, str] = {"evaluation": "eval_", "inspector": "inspector_", "sweep": "sweep_",
                                 "thresholds": "thresholds_"}
"""The prefix of each page's own settings (``set_page_params``); a page's link carries only its own."""


def url_params(page: str | None) -> dict[str, str]:
    """The query parameters of page ``page``'s link: the view fields it reads and its own settings.

    Every page's settings stay in the session (going back to a page restores them); only its
    own are in its link. ``None`` (a page of no name known here): the whole view and every setting.
    """
    params = view().to_params()
    own = st.session_state.get(_PAGE_KEY, {})
    if page not in PAGE_FIELDS:
        return {**own, **params}
    prefix = PAGE_PREFIXES.get(page)
    return {**{k: v for k, v in own.items() if prefix is not None and k.startswith(prefix)},
            **{k: v for k, v in params.items() if k in PAGE_FIELDS[page]}}


def sync_url(page: str | None = None) -> None:
    """Write page ``page``'s link (``url_params``) into ``st.query_params`` (only when it changed,
    to avoid needless history entries)."""
    wanted = url_params(page)
    current = {k: st.query_params[k] for k in st.query_params}
    if current != wanted:
        st.query_params.from_dict(wanted)


def bind(widget_key: str, field: str, value: object, *, validate: Callable[[object], None] | None = None,
         then: Callable[[object], None] | None = None) -> dict:
    """Keyword arguments that make a widget edit one field of the view.

    ``value`` is the field's effective value (the default resolved). The widget's state is
    set to it before the widget is drawn; on change the new value is committed to the
    view, unless ``validate`` raises, in which case the view is unchanged and the error
    is kept for ``feedback.show_rejected`` to display. ``then(value)`` runs after a commit
    (the user's change only, in the widget's callback).
    """
    st.session_state[widget_key] = value
    return dict(key=widget_key, on_change=_commit, args=(widget_key, field, validate, then))


def _commit(widget_key: str, field: str, validate: Callable[[object], None] | None,
            then: Callable[[object], None] | None = None) -> None:
    value = st.session_state[widget_key]
    if commit(**{field: value}, validate=None if validate is None else (lambda: validate(value))) and then:
        then(value)


def commit(*, validate: Callable[[], None] | None = None, **changes: object) -> bool:
    """Update the view if ``validate()`` passes; else keep it and remember the error for ``show_rejected``."""
    if validate is not None:
        from vpr_explorer.errors import VPRInputError

        try:
            validate()
        except VPRInputError as exc:
            st.session_state["rejected_input"] = str(exc)
            return False
    update(**changes)
    return True
