"""What the pages after the Dataset page start from: the view resolved into data and settings."""

from __future__ import annotations

from dataclasses import dataclass

import streamlit as st

from vpr_explorer.places import PlaceSpec
from vpr_explorer.views import default_step, split_traversals

from vpr_explorer.app.ui import cache, state
from vpr_explorer.app.ui.feedback import DATASET_HINT, PLACES_HINT, fixed_on
from vpr_explorer.app.ui.state import DEFAULT_GROUP, View


@dataclass(frozen=True, eq=False)
class Current:
    """The view with its defaults resolved against the loaded dataset.

    Attributes:
        data: dataset and descriptors.
        spec: group/step (``None`` for a prepared-places dataset, whose file names fix the places).
        database, query: traversal names of the database/traversal model.
    """

    view: View
    data: cache.Loaded
    spec: PlaceSpec | None
    database: tuple[str, ...]
    query: str


def effective_spec(view: View, n_frames: int, prepared: bool) -> PlaceSpec | None:
    """The view's group/step with the dataset's defaults filled in."""
    if prepared:
        return None
    group = view.group or DEFAULT_GROUP
    step = view.step or max(group, default_step(n_frames))
    return PlaceSpec(group, step, view.reading)


def current() -> Current:
    """Load (or fetch from memory) everything the view names.

    A query traversal the dataset does not have (an old link) is replaced by the default,
    with a warning saying so.

    Raises:
        ``feedback.FixOn`` (a ``VPRInputError``) naming the page where the input at fault is set.
    """
    v = state.view()
    with fixed_on(DATASET_HINT):
        data = cache.load(v.source, v.descriptor)
    ds = data.dataset
    with fixed_on(PLACES_HINT):
        spec = effective_spec(v, ds.n_frames, ds.prepared_places is not None)
    with fixed_on(DATASET_HINT):
        split_traversals(ds)  # one traversal: raises, saying what to add
        wanted = v.query if v.query in ds.traversals else ds.traversals[ds.default_roles().query]
        database, query = split_traversals(ds, wanted)
    if v.query is not None and v.query != query:
        st.warning(f"query={v.query!r} is not a traversal of {ds.name!r} ({', '.join(ds.traversals)}): using "
                   f"{query!r} instead. Pick the query traversal on the **Places** page.", icon=":material/warning:")
        state.update(query=None)
    return Current(v, data, spec, database, query)
