"""Group-and-step: frames (or database images, or metres along a route) become places.

Two readings of the paper are offered side by side:

* ``stride`` (default; the authors' code and the paper's numbers): place k covers frames
  ``[k*step, k*step + group)``, so ``step - group`` frames are skipped between places.
  GardensPoint (200 frames), group 3, step 10 -> 20 places.
* ``skip`` (the paper's text, "take 3, skip the next 10"): place k covers frames
  ``[k*(group+step), k*(group+step) + group)``. GardensPoint, 3/10 -> 16 places.

A trailing place with fewer than ``group`` frames is dropped, so every place holds the
same number of frames. Changing group/step only relabels images: descriptors are per
image and are never recomputed.

A database/queries dataset's places (``retrieval_places``) come from the layout's own place
ids, from group/step over its frames (aligned traversals) or its database images in listed
order (``frame_places``), or from
group/step in metres along the route or on a square lattice (``MetricPlaceSpec``,
``metric_places``) where the layout has positions.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from vpr_explorer.data.traversals import Dataset
from vpr_explorer.errors import VPRInputError



class Reading(StrEnum):
    """How ``step`` is read."""

    STRIDE = "stride"
    SKIP = "skip"


MAX_FRAMES = 10_000_000
"""The most frames ``group`` or ``step`` may span: far beyond any route (Nordland has 27,592 frames)."""
MAX_PLACE_METRES = 1e7
"""The most metres ``group`` or ``step`` of a ``MetricPlaceSpec`` may span (10,000 km)."""

READING_LABELS = {
    Reading.STRIDE: "stride: a place starts every `step` frames (authors' code, paper's numbers)",
    Reading.SKIP: "skip: take `group` frames, skip the next `step` (paper's text)",
}


@dataclass(frozen=True)
class PlaceSpec:
    """``group`` consecutive frames make a place; ``step`` spaces places (see ``Reading``)."""

    group: int
    step: int
    reading: Reading = Reading.STRIDE

    def __post_init__(self) -> None:
        for name in ("group", "step"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise VPRInputError(f"{name}={value!r}: must be a whole number of frames, 1 or more")
            if value > MAX_FRAMES:
                raise VPRInputError(
                    f"{name}={value}: at most {MAX_FRAMES:,} frames (longer than any route: no place would fit); "
                    "lower it"
                )
        if self.reading not in {r.value for r in Reading}:
            raise VPRInputError(f"reading={self.reading!r}: choose {' or '.join(r.value for r in Reading)}")
        object.__setattr__(self, "reading", Reading(self.reading))
        if self.reading is Reading.SKIP and self.step < 1:
            raise VPRInputError(f"step={self.step}: must be 1 or more")
        if self.reading is Reading.STRIDE and self.step < self.group:
            raise VPRInputError(
                f"step={self.step} < group={self.group}: in the stride reading places would overlap; "
                f"set step >= {self.group}, or use the skip reading"
            )

    @property
    def period(self) -> int:
        """Frames from the start of one place to the start of the next."""
        return self.step if self.reading is Reading.STRIDE else self.group + self.step

    def describe(self) -> str:
        return f"group {self.group}, step {self.step} ({self.reading.value} reading)"


def frame_places(n_frames: int, spec: PlaceSpec) -> np.ndarray:
    """``(n_frames,)`` place id of each frame, ``-1`` for frames between places."""
    frames = np.arange(n_frames)
    k, offset = np.divmod(frames, spec.period)
    complete = k * spec.period + spec.group <= n_frames
    return np.where((offset < spec.group) & complete, k, -1).astype(np.int64)


@dataclass(frozen=True, eq=False)
class Places:
    """The place of every frame and image of a dataset.

    Attributes:
        frame_place: ``(n_frames,)`` place id, ``-1`` where a frame is skipped.
        image_place: ``(n_images,)`` place id of each image (its frame's), ``-1`` if skipped.
        n_places: number of places (ids ``0..n_places-1``).
        spec: the group/step that made them; ``None`` for prepared places.
    """

    frame_place: np.ndarray
    image_place: np.ndarray
    n_places: int
    spec: PlaceSpec | None

    def __post_init__(self) -> None:
        self.frame_place.setflags(write=False)
        self.image_place.setflags(write=False)

    @property
    def images_per_place(self) -> np.ndarray:
        """``(n_places,)`` image count of each place."""
        return np.bincount(self.image_place[self.image_place >= 0], minlength=self.n_places)

    def frames_of(self, place: int) -> np.ndarray:
        return np.flatnonzero(self.frame_place == place)

    def images_of(self, place: int) -> np.ndarray:
        return np.flatnonzero(self.image_place == place)

    def describe(self, images: np.ndarray | None = None, what: str = "images") -> str:
        """E.g. "20 places × 9 images (group 3, step 10 (stride reading))".

        Args:
            images: count only these image indices (e.g. a traversal protocol's database);
                default every image.
            what: what the images are called, e.g. "database images".
        """
        how = self.spec.describe() if self.spec else "places fixed by file names"
        if images is None:
            per_place = self.images_per_place
        else:
            labels = self.image_place[np.asarray(images, dtype=np.int64)]
            per_place = np.bincount(labels[labels >= 0], minlength=self.n_places)
        counts = np.unique(per_place)
        per = str(counts[0]) if len(counts) == 1 else f"{counts.min()}-{counts.max()}"
        return f"{self.n_places} places × {per} {what} ({how})"


BETWEEN_PLACES_RULE = (
    "A query frame belongs to every place holding a frame within `tolerance` frames of it (tolerance 0: its "
    "own frame's place); a frame with no such place lies between places, has no right answer, and is left out "
    "of scoring on every page, protocol and recording (shown as \"between places, not scored\")."
)
"""The between-place rule in one sentence (docs/method.md, "Rules that hold everywhere"; the pages quote it)."""


def right_places(query_frames: np.ndarray, frame_place: np.ndarray, tolerance: int = 0) -> np.ndarray:
    """``(n_queries, n_places)`` bool: the right places of each query frame (``BETWEEN_PLACES_RULE``).

    The one rule every page, protocol and recording applies: a place is right for a query
    frame when it holds a frame within ``tolerance`` frames of it; a row with no right
    place (``between_places``) is a frame between places, left out of scoring. The
    aligned-traversal case of the ground-truth relation, vectorised over offsets: the same
    as ``GroundTruth.from_frames(query_frames, frames, tolerance).places(frame_place)``
    (``tests/test_groundtruth.py`` checks they agree).

    Args:
        query_frames: ``(n_queries,)`` frame number of each query.
        frame_place: ``(n_frames,)`` place of each frame, ``-1`` between places.
    """
    query_frames = np.asarray(query_frames, dtype=np.int64)
    frame_place = np.asarray(frame_place)
    truth = np.zeros((len(query_frames), max(0, int(frame_place.max(initial=-1)) + 1)), dtype=bool)
    for off in range(-int(tolerance), int(tolerance) + 1) if len(frame_place) else ():
        f = query_frames + off
        ok = (f >= 0) & (f < len(frame_place))
        p = np.where(ok, frame_place[np.clip(f, 0, len(frame_place) - 1)], -1)
        has = p >= 0
        truth[np.flatnonzero(has), p[has]] = True
    return truth


def between_places(truth: np.ndarray) -> np.ndarray:
    """``(n_queries,)`` bool: the query frames of ``right_places`` rows with no right place (not scored)."""
    return ~np.asarray(truth, dtype=bool).any(axis=-1)


def make_places(dataset: Dataset, spec: PlaceSpec | None) -> Places:
    """Label every image of ``dataset`` with its place.

    ``spec`` is ignored (may be ``None``) for prepared datasets, whose names fix the places.
    Raises ``VPRInputError`` when fewer than two places result: negative statistics need
    at least one other place.
    """
    if dataset.prepared_places is not None:
        frame_place = np.asarray(dataset.prepared_places, dtype=np.int64).copy()
        spec = None
    else:
        if spec is None:
            raise VPRInputError("group/step missing: give a PlaceSpec(group, step) for a traversal-folder dataset")
        frame_place = frame_places(dataset.n_frames, spec)
    n_places = int(frame_place.max()) + 1 if (frame_place >= 0).any() else 0
    if n_places < 2:
        what = spec.describe() if spec else "the file names"
        raise VPRInputError(
            f"{what} leaves {n_places} place(s) in {dataset.n_frames} frames of {dataset.name!r}: "
            "negative statistics need at least 2 places; lower group or step"
        )
    image_place = np.tile(frame_place, dataset.n_traversals)
    return Places(frame_place=frame_place, image_place=image_place, n_places=n_places, spec=spec)


# --------------------------------------------------------------------------- places in metres


class PlaceGeometry(StrEnum):
    """How positions become places when group/step are metres."""

    FRAMES = "frames"  # database images in listed order, group/step in images
    ROUTE = "route"  # distance along the database route, in its listed order
    LATTICE = "lattice"  # cells of a square lattice over the plane


GEOMETRY_LABELS = {
    PlaceGeometry.FRAMES: "frames: group/step count database images in listed order",
    PlaceGeometry.ROUTE: "route: group/step are metres along the database route",
    PlaceGeometry.LATTICE: "lattice: group/step are metres of a square lattice over the plane",
}


@dataclass(frozen=True)
class MetricPlaceSpec:
    """Places of a database with positions: ``group`` metres make a place, one every ``step``.

    In the stride reading place k covers ``[k·step, k·step + group)`` (along the route, or
    per axis of the lattice); in the skip reading ``[k·(group+step), k·(group+step) + group)``.
    """

    group: float
    step: float
    reading: Reading = Reading.STRIDE
    geometry: PlaceGeometry = PlaceGeometry.ROUTE

    def __post_init__(self) -> None:
        for name in ("group", "step"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
                    or not np.isfinite(value) or value <= 0 or value > MAX_PLACE_METRES:
                raise VPRInputError(f"{name}={value!r}: must be a distance in metres above 0 "
                                    f"(at most {MAX_PLACE_METRES / 1000:,.0f} km)")
        if self.reading not in {r.value for r in Reading}:
            raise VPRInputError(f"reading={self.reading!r}: choose {' or '.join(r.value for r in Reading)}")
        object.__setattr__(self, "reading", Reading(self.reading))
        if self.geometry not in {g.value for g in PlaceGeometry} or self.geometry == PlaceGeometry.FRAMES:
            raise VPRInputError(f"geometry={self.geometry!r}: choose route or lattice")
        object.__setattr__(self, "geometry", PlaceGeometry(self.geometry))
        if self.reading is Reading.STRIDE and self.step < self.group:
            raise VPRInputError(f"step={self.step:g} m < group={self.group:g} m: in the stride reading places would "
                                f"overlap; set step >= {self.group:g}, or use the skip reading")

    @property
    def period(self) -> float:
        return self.step if self.reading is Reading.STRIDE else self.group + self.step

    def describe(self) -> str:
        return f"group {self.group:g} m, step {self.step:g} m ({self.geometry.value}, {self.reading.value} reading)"


def _bins(v: np.ndarray, spec: MetricPlaceSpec) -> tuple[np.ndarray, np.ndarray]:
    """Bin of each value and whether it falls inside the bin's first ``group`` metres."""
    k = np.floor(v / spec.period).astype(np.int64)
    return k, (v - k * spec.period) < spec.group


def metric_places(xy: np.ndarray, spec: MetricPlaceSpec) -> tuple[np.ndarray, int]:
    """``(n,)`` place of each database image (``-1`` outside every place) and the number of places.

    Route: the distance along the database in its listed order (0 at the first image).
    Lattice: cells over the plane from the lowest x and y; cells are numbered in row-major
    order of (y, x), empty cells get no id.
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if spec.geometry is PlaceGeometry.ROUTE:
        along = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))]
        k, inside = _bins(along, spec)
        place = np.where(inside, k, -1)
    else:
        origin = xy.min(axis=0)
        kx, in_x = _bins(xy[:, 0] - origin[0], spec)
        ky, in_y = _bins(xy[:, 1] - origin[1], spec)
        place = np.where(in_x & in_y, ky * (int(kx.max()) + 1) + kx, -1)
    used = np.unique(place[place >= 0])
    out = np.full(len(place), -1, dtype=np.int64)
    out[place >= 0] = np.searchsorted(used, place[place >= 0])
    return out, len(used)


def retrieval_places(dataset, spec: PlaceSpec | None = None,
                     metric: MetricPlaceSpec | None = None) -> tuple[np.ndarray, int]:
    """``(n_database,)`` place of each database image and the number of places.

    The layout's own place ids (a manifest's ``place`` column) when it has them; else
    ``metric`` (a ``MetricPlaceSpec``: metres along the route or a lattice) when the layout
    has positions; else ``spec`` (group/step counting frames along the route for aligned
    traversals, database images in listed order for the other layouts).

    Args:
        dataset: a database/queries dataset (``data.layouts.RetrievalDataset``); its
            ``database_place``, ``database_xy``, ``database_frame``, ``frame_xy``, ``n_frames``,
            ``n_database``, ``layout`` and ``name`` are read.
        spec: group/step in frames (database images without frames), used when the layout has no place ids and
            ``metric`` is None.
        metric: group/step in metres, used when the layout has no place ids.

    Returns:
        ``(place, n_places)``: ``(n_database,)`` int64 place of each database image, ``-1``
        for an image between places, and the number of places.

    Raises:
        VPRInputError: ``metric`` on a layout without positions, neither ``spec`` nor
            ``metric`` given, or fewer than 2 places.
    """
    if dataset.database_place is not None:
        return dataset.database_place, int(dataset.database_place.max()) + 1
    frames = dataset.database_frame
    if metric is not None:
        if dataset.database_xy is None:
            raise VPRInputError(f"{dataset.name}: the {dataset.layout.value} layout has no positions: group/step in "
                                "metres need them; use --geometry frames (group/step in images)")
        if dataset.frame_xy is not None:  # aligned traversals: metres along the route of frames
            frame_place, n = metric_places(dataset.frame_xy, metric)
            place = frame_place[frames]
        else:
            place, n = metric_places(dataset.database_xy, metric)
    else:
        if spec is None:
            raise VPRInputError("group/step missing: give a PlaceSpec(group, step) or a MetricPlaceSpec")
        if frames is None:
            place = frame_places(dataset.n_database, spec)
        else:
            place = frame_places(dataset.n_frames, spec)[frames]
        n = int(place.max()) + 1 if (place >= 0).any() else 0
    if n < 2:
        what = metric.describe() if metric is not None else spec.describe()
        where = (f"{dataset.n_frames} frames" if frames is not None
                 else f"the {dataset.n_database} database images")
        raise VPRInputError(f"{what} leaves {n} place(s) in {where} of {dataset.name!r}: negative statistics need at "
                            "least 2 places; lower group or step")
    return place, n
