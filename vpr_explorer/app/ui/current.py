"""What the pages after the Dataset page start from: the view resolved into data and settings."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pandas as pd  # before plotly: plotly.py#2433
import streamlit as st
from streamlit.runtime.scriptrunner import get_script_run_ctx

from vpr_explorer.errors import VPRInputError
from vpr_explorer.data.layouts import RetrievalDataset
from vpr_explorer.method.places import MetricPlaceSpec, PlaceGeometry, PlaceSpec
from vpr_explorer.views.database_queries import DEFAULT_GROUP_M, DEFAULT_STEP_M, RetrievalPlaces, check_geometry
from vpr_explorer.views.traversal import default_step, split_traversals

from vpr_explorer.app.ui import cache, state
from vpr_explorer.app.ui.feedback import DATASET_HINT, PLACES_HINT, FixOn, fixed_on
from vpr_explorer.app.ui.state import DEFAULT_GROUP, View

RETRIEVAL_PAGES = ("home", "places", "inspector", "evaluation")
"""Pages that open a database/queries dataset; the others show aligned traversals only and say so."""


@dataclass(frozen=True, eq=False)
class Current:
    """The view with its defaults resolved against the loaded dataset.

    Attributes:
        data: dataset and descriptors.
        spec: group/step (``None`` for a prepared-places dataset, whose file names fix the places;
            for a database/queries dataset, its frames geometry's group/step or ``None``).
        database, query: traversal names of the database/traversal model (of a database/queries
            dataset: its database side and its query side).
        places: for a database/queries dataset, how its database images become places; else ``None``.
    """

    view: View
    data: cache.Loaded
    spec: PlaceSpec | None
    database: tuple[str, ...]
    query: str
    places: RetrievalPlaces | None = None

    @property
    def retrieval(self) -> RetrievalDataset | None:
        """The database/queries dataset, or ``None`` for aligned traversals."""
        ds = self.data.dataset
        return ds if isinstance(ds, RetrievalDataset) else None


def effective_spec(view: View, n_frames: int, prepared: bool) -> PlaceSpec | None:
    """The view's group/step with the dataset's defaults filled in."""
    if prepared:
        return None
    group = view.group or DEFAULT_GROUP
    step = view.step or max(group, default_step(n_frames))
    return PlaceSpec(group, step, view.reading)


def effective_places(view: View, dataset: RetrievalDataset) -> RetrievalPlaces:
    """The view's geometry and group/step (frames or metres) with the dataset's defaults filled in."""
    geometry = check_geometry(dataset, view.geometry)
    if geometry is None:
        return RetrievalPlaces(None)
    if geometry is PlaceGeometry.FRAMES:
        return RetrievalPlaces(geometry, spec=effective_spec(view, dataset.n_database, False))
    group = view.group_m or DEFAULT_GROUP_M
    step = view.step_m or max(group, DEFAULT_STEP_M)
    return RetrievalPlaces(geometry, metric=MetricPlaceSpec(group, step, view.reading, geometry))


def running_page() -> str | None:
    """The page script running now, by name (``"thresholds"``), or ``None`` where Streamlit does not say."""
    ctx = get_script_run_ctx()
    if ctx is None:
        return None
    try:
        pages = ctx.pages_manager.get_pages()
        info = pages.get(ctx.pages_manager.current_page_script_hash) or {}
    except AttributeError:  # another Streamlit version: do not guess
        return None
    path = info.get("script_path")
    return Path(path).stem if path else None


def current() -> Current:
    """Load (or fetch from memory) everything the view names.

    A query traversal the dataset does not have (an old link) is replaced by the default,
    with a warning saying so. A database/queries dataset opens on the pages of
    ``RETRIEVAL_PAGES``; the others say where to see it.

    Raises:
        ``feedback.FixOn`` (a ``VPRInputError``) naming the page where the input at fault is set.
    """
    v = state.view()
    with fixed_on(DATASET_HINT):
        data = cache.load(v.source, v.descriptor, layout=v.layout, radius=v.radius, file=v.descriptors)
    ds = data.dataset
    if isinstance(ds, RetrievalDataset):
        return _retrieval_current(v, data, ds)
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


def _retrieval_current(v: View, data: cache.Loaded, ds: RetrievalDataset) -> Current:
    page = running_page()
    if page is not None and page not in RETRIEVAL_PAGES:
        raise FixOn(VPRInputError(
            f"{ds.name!r} is read as a {ds.layout.value} layout (database and query images with ground truth): this "
            "page shows aligned traversal folders. The **Places**, **Query inspector** and **Evaluation** pages "
            "open it."), DATASET_HINT)
    try:
        places = effective_places(v, ds)
    except VPRInputError as exc:  # a geometry the dataset does not offer (an old link): the default instead
        st.warning(f"{exc}: using the dataset's default instead.", icon=":material/warning:")
        state.update(geometry=None)
        places = effective_places(state.view(), ds)
    database = tuple(ds.traversals[int(t)] for t in pd.unique(ds.database_traversal))  # in order; 1M images: 5 ms
    query = ds.traversals[int(ds.query_traversal[0])]
    return Current(v, data, places.spec, database, query, places)
