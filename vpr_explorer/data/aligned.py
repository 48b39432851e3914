"""Aligned traversals as a database/queries dataset: the one value every page and protocol reads.

Aligned traversals (``traversals.Dataset``: frame ``f`` of every traversal is the same spot)
are one layout of ``layouts.RetrievalDataset``:

* database: the chosen database traversals (default: every traversal but the query), each in
  frame order, traversal after traversal;
* queries: the frames of the query traversal, in order (query ``q`` is frame ``q``);
* ground truth: the database images within ``tolerance`` frames of the query's frame
  (``GroundTruth.from_frames``; tolerance 0: the same frame);
* what it knows of each image: its traversal, its frame (``database_frame``, ``query_frame``),
  and its position where the dataset has a positions file (``frame_xy``);
* places: group/step over frames (``method.places.retrieval_places``), or the prepared
  places' own ids, or metres along the route where positions exist.

The descriptors of the value are the traversals' rows in the value's order (``rows``):
the database rows, then the query rows; when the query traversal is the last and the
database every other one, that is the traversals' own order and no row moves.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from vpr_explorer.data.groundtruth import GroundTruth
from vpr_explorer.data.layouts import Layout, RetrievalDataset
from vpr_explorer.data.traversals import Dataset
from vpr_explorer.errors import VPRInputError


def split_traversals(dataset: Dataset, query: str | int | None = None) -> tuple[tuple[str, ...], str]:
    """Database traversals (every one but the query) and the query traversal (default: the last).

    Raises:
        VPRInputError: the dataset has one traversal, or ``query`` is not one of them.
    """
    if dataset.n_traversals < 2:
        raise VPRInputError(
            f"{dataset.name!r} has one traversal: the explorer needs a second one to query with; "
            "add a traversal folder or pick another dataset"
        )
    q = dataset.n_traversals - 1 if query is None else dataset.traversal_index(query)
    database = tuple(t for i, t in enumerate(dataset.traversals) if i != q)
    return database, dataset.traversals[q]


def rows(dataset: Dataset, database: Sequence[str | int], query: str | int) -> np.ndarray:
    """``(n_database + n_frames,)`` rows of the traversals' descriptors in the value's order."""
    n = dataset.n_frames
    order = [dataset.traversal_index(t) for t in database] + [dataset.traversal_index(query)]
    return (np.asarray(order, dtype=np.int64)[:, None] * n + np.arange(n)).reshape(-1)


def database_queries(dataset: Dataset, query: str | int | None = None, database: Sequence[str | int] | None = None,
                     tolerance: int = 0) -> RetrievalDataset:
    """The aligned traversals ``dataset`` as a database/queries dataset (see the module's docstring).

    Args:
        dataset: aligned traversals (two or more).
        query: the query traversal, by name or index (default: the last).
        database: the database traversals (default: every one but the query); none of them the query.
        tolerance: frames either side of a query's frame whose database images are right for it.

    Returns:
        The value; its ``aligned`` is ``dataset``, its layout ``traversals`` (``prepared`` for
        prepared places, whose ids become ``database_place``).

    Raises:
        VPRInputError: one traversal, an unknown traversal, the query among the database, a
            negative tolerance.
    """
    default_db, query_name = split_traversals(dataset, query)
    db = default_db if database is None else tuple(dataset.traversals[dataset.traversal_index(t)] for t in database)
    if not db:
        raise VPRInputError("database: choose at least one database traversal")
    if query_name in db:
        raise VPRInputError(f"traversal {query_name!r} is both the query and in the database: choose another query")
    n = dataset.n_frames
    t_db = np.repeat(np.asarray([dataset.traversal_index(t) for t in db], dtype=np.int64), n)
    db_frame = np.tile(np.arange(n, dtype=np.int64), len(db))
    q_frame = np.arange(n, dtype=np.int64)
    q_index = dataset.traversal_index(query_name)
    xy = dataset.positions
    prepared = dataset.prepared_places
    return RetrievalDataset(
        name=dataset.name, root=dataset.root, layout=Layout.PREPARED if prepared is not None else Layout.TRAVERSALS,
        database_paths=tuple(dataset.paths[int(t)][int(f)] for t, f in zip(t_db, db_frame)),
        query_paths=tuple(dataset.paths[q_index]),
        database_xy=None if xy is None else np.asarray(xy, dtype=np.float64)[db_frame],
        query_xy=None if xy is None else np.asarray(xy, dtype=np.float64)[q_frame],
        ground_truth=GroundTruth.from_frames(q_frame, db_frame, tolerance),
        database_traversal=t_db, query_traversal=np.full(n, q_index, dtype=np.int64),
        traversals=dataset.traversals, ordered=len(db) == 1,
        database_place=None if prepared is None else np.asarray(prepared, dtype=np.int64)[db_frame],
        notes=dataset.notes, database_frame=db_frame, query_frame=q_frame, n_frames=n,
        frame_xy=None if xy is None else np.asarray(xy, dtype=np.float64), aligned=dataset,
    )


def value_rows(value: RetrievalDataset) -> np.ndarray | None:
    """Rows of the aligned traversals' descriptors in ``value``'s order; ``None`` when it is their own order
    (or ``value`` is not made of aligned traversals)."""
    ds = value.aligned
    if ds is None:
        return None
    first = np.sort(np.unique(value.database_traversal, return_index=True)[1])  # each traversal's first image
    r = rows(ds, [int(t) for t in value.database_traversal[first]], int(value.query_traversal[0]))
    return None if len(r) == ds.n_images and np.array_equal(r, np.arange(ds.n_images)) else r
