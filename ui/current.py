"""What the pages after the Dataset page start from: the view resolved into data and settings."""

from __future__ import annotations

from dataclasses import dataclass

from vpr_explorer.errors import VPRInputError
from vpr_explorer.places import PlaceSpec
from vpr_explorer.views import default_step, split_traversals

from ui import cache, state
from ui.state import DEFAULT_GROUP, View


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
    """Load (or fetch from memory) everything the view names; raises ``VPRInputError`` on bad input."""
    v = state.view()
    data = cache.load(v.source, v.descriptor)
    ds = data.dataset
    spec = effective_spec(v, ds.n_frames, ds.prepared_places is not None)
    if v.query is not None and v.query not in ds.traversals:
        raise VPRInputError(f"query traversal {v.query!r} is not in {ds.name!r}: choose one of {', '.join(ds.traversals)}")
    database, query = split_traversals(ds, v.query)
    return Current(v, data, spec, database, query)
