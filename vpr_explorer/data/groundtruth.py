"""Ground truth as a value: which database images are right for which query.

A sparse relation between ``n_queries`` queries and ``n_database`` database images, built
the way each kind of data defines it:

* **frames** (aligned traversals): a database image is right for a query when its frame is
  within ``tolerance`` frames of the query's (tolerance 0: the same frame);
* **positions** (position-tagged data): within ``radius`` metres (the field's 25 m);
* **lists** (VPR-Bench's ``ground_truth_new.npy``, a manifest's place ids): given.

Hard positives decide Recall@K; soft positives, where a layout has them, are kept
beside them for display. A query with no hard positive is an *unknown-place* query: the
open-set case, counted apart (rejected share), never as a miss.

Rows are stored as CSR (``indptr``, ``indices``), so a million queries with a handful of
positives each take megabytes, never an ``n_queries × n_database`` matrix; dense blocks are
made on demand, a few rows at a time.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from vpr_explorer.errors import VPRInputError

#: The field's positive radius in metres (VPR datasets downloader, most papers).
DEFAULT_RADIUS = 25.0
#: The largest ``|x|`` or ``|y|`` of a position, and the largest radius, in metres: UTM coordinates
#: stay below 10⁷, and squared distances between positions this far out are still finite and exact
#: enough to compare with a radius.
MAX_METRES = 1e9


def _csr(lists: Sequence[np.ndarray], n_database: int, what: str) -> tuple[np.ndarray, np.ndarray]:
    """CSR rows (ascending, duplicates dropped) from one array of database positions per query."""
    rows = [np.unique(np.asarray(x, dtype=np.int64).reshape(-1)) for x in lists]
    for q, row in enumerate(rows):
        if row.size and (row[0] < 0 or row[-1] >= n_database):
            bad = int(row[0] if row[0] < 0 else row[-1])
            raise VPRInputError(f"{what}: query {q} lists database image {bad}, outside 0..{n_database - 1}")
    lengths = np.fromiter((len(x) for x in rows), dtype=np.int64, count=len(rows))
    indptr = np.r_[0, np.cumsum(lengths)].astype(np.int64)
    indices = np.concatenate(rows) if rows else np.empty(0, np.int64)
    return indptr, indices


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """Hard (and optionally soft) positives of every query, as CSR rows.

    Attributes:
        indptr: ``(n_queries + 1,)`` row starts into ``indices``.
        indices: ascending database image positions (``0..n_database-1``) per row.
        n_database: number of database images.
        description: how the relation was made, e.g. ``"within 25 m"``.
        soft_indptr, soft_indices: the soft positives in the same form, or ``None``.
    """

    indptr: np.ndarray
    indices: np.ndarray
    n_database: int
    description: str
    soft_indptr: np.ndarray | None = None
    soft_indices: np.ndarray | None = None

    def __post_init__(self) -> None:
        for a in (self.indptr, self.indices, self.soft_indptr, self.soft_indices):
            if a is not None:
                a.setflags(write=False)

    # ------------------------------------------------------------------ constructors

    @classmethod
    def from_lists(cls, lists: Sequence[Sequence[int]], n_database: int, description: str,
                   soft: Sequence[Sequence[int]] | None = None, *, what: str = "ground truth") -> GroundTruth:
        """From one list of positive database positions per query."""
        indptr, indices = _csr([np.asarray(x, dtype=np.int64).reshape(-1) for x in lists], n_database, what)
        sp = si = None
        if soft is not None:
            if len(soft) != len(lists):
                raise VPRInputError(f"{what}: {len(soft)} soft rows for {len(lists)} queries")
            sp, si = _csr([np.asarray(x, dtype=np.int64).reshape(-1) for x in soft], n_database, what)
        return cls(indptr, indices, int(n_database), description, sp, si)

    @classmethod
    def from_positions(cls, query_xy: np.ndarray, database_xy: np.ndarray, radius: float = DEFAULT_RADIUS,
                       soft_radius: float | None = None) -> GroundTruth:
        """Database images within ``radius`` metres of each query (UTM or any metric plane).

        Within means distance ≤ ``radius``: an image exactly at the radius is right.

        Raises:
            VPRInputError: a radius that ``check_radius`` refuses, or a position that is not
                finite or lies beyond ``MAX_METRES`` (``POSITION_RULE``).
        """
        from scipy.spatial import cKDTree

        radius = check_radius(radius, "radius")
        q = np.asarray(query_xy, dtype=np.float64).reshape(-1, 2)
        db = np.asarray(database_xy, dtype=np.float64).reshape(-1, 2)
        for side, xy in (("query", q), ("database image", db)):
            bad = np.flatnonzero(~(np.abs(xy) <= MAX_METRES).all(axis=1))  # NaN and ±inf fail too
            if bad.size:
                raise VPRInputError(f"positions: {side} {bad[0]}: {position_problem(*xy[bad[0]])}")
        tree = cKDTree(db)  # its radius search counts distance ≤ radius, as the field does
        hard = tree.query_ball_point(q, r=radius)
        soft = tree.query_ball_point(q, r=check_radius(soft_radius, "soft radius")) if soft_radius else None
        return cls.from_lists(hard, len(db), f"within {radius:g} m", soft)

    @classmethod
    def from_frames(cls, query_frames: np.ndarray, database_frames: np.ndarray, tolerance: int = 0) -> GroundTruth:
        """Database images whose frame is within ``tolerance`` of the query's frame (aligned traversals)."""
        if isinstance(tolerance, bool) or not isinstance(tolerance, (int, np.integer)) or tolerance < 0:
            raise VPRInputError(f"tolerance={tolerance!r}: must be a whole number of frames, 0 or more")
        qf = np.asarray(query_frames, dtype=np.int64)
        dbf = np.asarray(database_frames, dtype=np.int64)
        order = np.argsort(dbf, kind="stable")
        lo = np.searchsorted(dbf[order], qf - tolerance, side="left")
        hi = np.searchsorted(dbf[order], qf + tolerance, side="right")
        lists = [np.sort(order[a:b]) for a, b in zip(lo, hi)]
        what = "same frame" if tolerance == 0 else f"within ±{tolerance} frames"
        return cls.from_lists(lists, len(dbf), what)

    # ------------------------------------------------------------------ reading

    @property
    def n_queries(self) -> int:
        return len(self.indptr) - 1

    def positives(self, query: int) -> np.ndarray:
        """Hard positives of one query (database positions, ascending)."""
        return np.asarray(self.indices[self.indptr[query]:self.indptr[query + 1]])

    def soft_positives(self, query: int) -> np.ndarray:
        """Soft positives of one query (its hard ones when the layout has no soft ground truth)."""
        if self.soft_indptr is None:
            return self.positives(query)
        return np.asarray(self.soft_indices[self.soft_indptr[query]:self.soft_indptr[query + 1]])

    @property
    def counts(self) -> np.ndarray:
        """``(n_queries,)`` hard positives per query."""
        return np.diff(self.indptr)

    @property
    def known(self) -> np.ndarray:
        """``(n_queries,)`` bool: the query has a right database image."""
        return self.counts > 0

    @property
    def n_unknown(self) -> int:
        """Queries with no right database image (the open set)."""
        return int((~self.known).sum())

    def _pairs(self, queries: np.ndarray | slice | None) -> tuple[int, np.ndarray, np.ndarray]:
        """Row count, and (row within the block, database position) of every positive of some queries."""
        rows = np.arange(self.n_queries)[queries] if queries is not None else np.arange(self.n_queries)
        starts, counts = self.indptr[rows], self.indptr[rows + 1] - self.indptr[rows]
        offset = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
        return len(rows), np.repeat(np.arange(len(rows)), counts), self.indices[np.repeat(starts, counts) + offset]

    def dense(self, queries: np.ndarray | slice | None = None) -> np.ndarray:
        """``(n_rows, n_database)`` bool positives of some queries (a block; never all of a big set)."""
        n, r, j = self._pairs(queries)
        out = np.zeros((n, self.n_database), dtype=bool)
        out[r, j] = True
        return out

    def places(self, database_place: np.ndarray, n_places: int,
               queries: np.ndarray | slice | None = None) -> np.ndarray:
        """``(n_rows, n_places)`` bool: the places holding a positive of each query.

        Database images outside every place (``database_place`` −1) make no place right.
        """
        database_place = np.asarray(database_place, dtype=np.int64)
        if database_place.shape != (self.n_database,):
            raise VPRInputError(f"{len(database_place)} database place labels for {self.n_database} database images")
        n, r, j = self._pairs(queries)
        p = database_place[j]
        out = np.zeros((n, n_places), dtype=bool)
        out[r[p >= 0], p[p >= 0]] = True
        return out

    def subset(self, queries: np.ndarray) -> GroundTruth:
        """The rows of some queries (e.g. a sample), in the order given."""
        queries = np.asarray(queries, dtype=np.int64)
        return GroundTruth.from_lists([self.positives(q) for q in queries], self.n_database, self.description,
                                      None if self.soft_indptr is None else [self.soft_positives(q) for q in queries])


POSITION_RULE = (f"positions are metres (UTM east/north, or x/y in a local plane) with |x| and |y| at most "
                 f"{MAX_METRES:,.0f}")
"""What a position must be, for messages that refuse one."""


def position_text(xy) -> str:
    """A position as a message shows it, e.g. ``(1e+300, 6960000)``."""
    return "(" + ", ".join(f"{float(v):g}" for v in xy) + ")"


def position_problem(x: float, y: float) -> str | None:
    """Why ``(x, y)`` cannot be a position (not finite, or beyond ``MAX_METRES``), or ``None``."""
    if not (math.isfinite(x) and math.isfinite(y)):
        return f"the position {position_text((x, y))} is not finite"
    if abs(x) > MAX_METRES or abs(y) > MAX_METRES:
        return f"the position {position_text((x, y))} is out of range: {POSITION_RULE}"
    return None


def check_radius(value, name: str = "radius") -> float:
    """``value`` as a radius in metres: a finite number above 0 and at most ``MAX_METRES``.

    Raises:
        VPRInputError: naming ``name`` and the value.
    """
    try:
        r = float(value)
    except (TypeError, ValueError):
        raise VPRInputError(f"{name}={value!r}: must be a distance in metres, e.g. 25") from None
    if not np.isfinite(r) or r <= 0:
        raise VPRInputError(f"{name}={value!r}: must be a positive distance in metres, e.g. 25")
    if r > MAX_METRES:
        raise VPRInputError(f"{name}={value!r}: must be at most {MAX_METRES:,.0f} metres, e.g. 25")
    return r
