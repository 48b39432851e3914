"""What the pages after the Dataset page start from: the view resolved into one dataset value and its places.

Every dataset, whatever its layout, reaches the pages as one value: a database/queries
dataset (``layouts.RetrievalDataset``) with its descriptors in its own order. Aligned
traversals become one (``data.aligned.database_queries``): the database is every
traversal but the query traversal, the queries are the query traversal's frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import pandas as pd  # before plotly: plotly.py#2433
import streamlit as st

from vpr_explorer.data.aligned import split_traversals
from vpr_explorer.data.layouts import RetrievalDataset
from vpr_explorer.data.traversals import Dataset
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import MetricPlaceSpec, PlaceGeometry, PlaceSpec
from vpr_explorer.views.numbers import DEFAULT_GROUP_M, DEFAULT_STEP_M, RetrievalPlaces, check_geometry
from vpr_explorer.views.numbers import default_step

from vpr_explorer.app.ui import cache, state
from vpr_explorer.app.ui.feedback import DATASET_HINT, PLACES_HINT, fixed_on
from vpr_explorer.app.ui.state import DEFAULT_GROUP, View


@dataclass(frozen=True, eq=False)
class Current:
    """The view with its defaults resolved against the loaded dataset.

    Attributes:
        view: the view it was resolved from.
        data: the dataset value (``data.dataset``, a ``RetrievalDataset``) and its descriptors
            in the value's order (database rows, then query rows).
        places: how the database images become places (the layout's ids, frames, or metres).
        database, query: traversal names of the database side and the query side.
        source: the dataset as loaded: aligned traversals (``Dataset``) and their descriptors in
            traversal order, or the same as ``data``.
    """

    view: View
    data: cache.Loaded
    places: RetrievalPlaces
    database: tuple[str, ...]
    query: str
    source: cache.Loaded

    @property
    def dataset(self) -> RetrievalDataset:
        """The dataset value every page reads."""
        return self.data.dataset

    @property
    def spec(self) -> PlaceSpec | None:
        """Group/step in frames (``None`` for places fixed by the layout, or in metres)."""
        return self.places.spec

    @property
    def aligned(self) -> Dataset | None:
        """The aligned traversals the value was made from, or ``None`` for the other layouts."""
        return self.dataset.aligned


def effective_spec(view: View, n_frames: int, prepared: bool) -> PlaceSpec | None:
    """The view's group/step with the dataset's defaults filled in."""
    if prepared:
        return None
    group = view.group or DEFAULT_GROUP
    step = view.step or max(group, default_step(n_frames))
    return PlaceSpec(group, step, view.reading)


def effective_places(view: View, dataset: RetrievalDataset) -> RetrievalPlaces:
    """The view's geometry and group/step (frames or metres) with the dataset's defaults filled in.

    Raises:
        VPRInputError: a geometry the dataset does not offer, or group/step that make no places.
    """
    geometry = check_geometry(dataset, view.geometry)
    if geometry is None:
        return RetrievalPlaces(None)
    if geometry is PlaceGeometry.FRAMES:
        return RetrievalPlaces(geometry, spec=effective_spec(view, dataset.n_frames or dataset.n_database, False))
    group = view.group_m or DEFAULT_GROUP_M
    step = view.step_m or max(group, DEFAULT_STEP_M)
    return RetrievalPlaces(geometry, metric=MetricPlaceSpec(group, step, view.reading, geometry))


def _query_traversal(v: View, ds: Dataset) -> str:
    """The view's query traversal, or the default (with a warning) when the dataset has no such traversal."""
    with fixed_on(DATASET_HINT):
        split_traversals(ds)  # one traversal: raises, saying what to add
    default = ds.traversals[ds.default_roles().query]
    if v.query is not None and v.query not in ds.traversals:
        st.warning(f"query={v.query!r} is not a traversal of {ds.name!r} ({', '.join(ds.traversals)}): using "
                   f"{default!r} instead. Pick the query traversal on the **Places** page.", icon=":material/warning:")
        state.update(query=None)
        return default
    return v.query or default


def _places(v: View, ds: RetrievalDataset) -> RetrievalPlaces:
    """The view's places; a geometry the dataset does not offer (an old link) falls back to the default."""
    try:
        check_geometry(ds, v.geometry)
    except VPRInputError as exc:
        st.warning(f"{exc}: using the dataset's default instead.", icon=":material/warning:")
        state.update(geometry=None)
        v = state.view()
    with fixed_on(PLACES_HINT):
        return effective_places(v, ds)


def current() -> Current:
    """Load (or fetch from memory) everything the view names, as one dataset value.

    A query traversal the dataset does not have (an old link) is replaced by the default,
    with a warning saying so; so is a place geometry it does not offer.

    Raises:
        ``feedback.FixOn`` (a ``VPRInputError``) naming the page where the input at fault is set.
    """
    v = state.view()
    with fixed_on(DATASET_HINT):
        source = cache.load(v.source, v.descriptor, layout=v.layout, radius=v.radius, file=v.descriptors)
    if isinstance(source.dataset, Dataset):
        query = _query_traversal(v, source.dataset)
        with fixed_on(DATASET_HINT):
            data = cache.value(source, query)
    else:
        data = source
    ds = data.dataset
    places = _places(state.view(), ds)
    database = tuple(ds.traversals[int(t)] for t in pd.unique(ds.database_traversal))  # in order; 1M images: 5 ms
    query = ds.traversals[int(ds.query_traversal[0])]
    return Current(v, data, places, database, query, source)
