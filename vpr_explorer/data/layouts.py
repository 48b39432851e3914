"""The field's benchmark layouts: a database and queries, with ground truth as a relation.

Where ``data.traversals`` reads traversals whose frame indices line up, this module reads the
layouts VPR benchmarks are distributed in, each into a ``RetrievalDataset`` (database
images, query images, positions where the layout has them, and a ``GroundTruth``):

| layout | on disk | right database images |
|---|---|---|
| ``database-queries`` | ``database/`` and ``queries/`` (also under ``images/test/``), the position in every file name as ``@UTM_east@UTM_north@zone@letter@…`` (VPR datasets downloader: St Lucia, Pittsburgh, Tokyo 24/7, MSLS, SF-XL) | within ``radius`` metres (25) |
| ``vpr-bench`` | ``ref/``, ``query/`` and ``ground_truth_new.npy``, one row ``[query index, [reference indices]]`` per query (read by ``safe_npy``: nothing pickled in it is run) | the listed ones |
| ``traversal-positions`` | traversal folders with ``positions.csv`` in each (``x,y`` in metres, or ``lat,lon``), frames need not line up | within ``radius`` metres |
| ``manifest`` | a CSV ``path,role[,x,y][,place]`` (role ``database``/``query``), for everything else | within ``radius`` metres, or the same place id |

Images are listed in natural order of their path below the folder (what ``vpr-explorer
list`` prints): database first, then queries. Inconsistent input (a name without a
position, a position that is not finite or lies beyond ``groundtruth.MAX_METRES``, a
ground-truth row pointing past the reference images, mixed UTM zones, an image that is a
symbolic link to nothing or cannot be read) raises one ``VPRInputError`` naming the file
and line. Lat/lon positions are converted to UTM in one zone for every traversal (the zone
most frames lie in; ``RetrievalDataset.notes`` says which), so that distances between
traversals are distances on the ground. CSV files may start with a UTF-8 byte-order mark.
"""

from __future__ import annotations

import csv
import os
from dataclasses import dataclass
from enum import StrEnum
from functools import cached_property
from pathlib import Path

import numpy as np

from vpr_explorer.data.traversals import (
    Dataset,
    IMAGE_SUFFIXES,
    entries,
    images_in,
    kind,
    natural_key,
    reading,
    traversal_roles,
    unusable,
)
from vpr_explorer.errors import VPRInputError
from vpr_explorer.data.groundtruth import DEFAULT_RADIUS, GroundTruth, check_radius, position_problem
from vpr_explorer.data.safe_npy import as_indices, read_npy


class Layout(StrEnum):
    """How a dataset folder is laid out (``--layout``)."""

    AUTO = "auto"
    TRAVERSALS = "traversals"
    PREPARED = "prepared"
    DATABASE_QUERIES = "database-queries"
    VPR_BENCH = "vpr-bench"
    TRAVERSAL_POSITIONS = "traversal-positions"
    MANIFEST = "manifest"


#: Layouts read into a ``RetrievalDataset`` (the others are ``traversals.Dataset``).
RETRIEVAL_LAYOUTS = frozenset({Layout.DATABASE_QUERIES, Layout.VPR_BENCH, Layout.TRAVERSAL_POSITIONS, Layout.MANIFEST})
VPR_BENCH_GT = "ground_truth_new.npy"
#: The reference index VPR-Bench writes for a query with no right reference (``[-1]``).
NO_REFERENCE = -1
MANIFEST_NAMES = ("manifest.csv",)
POSITIONS_FILE = "positions.csv"


@dataclass(frozen=True, eq=False)
class RetrievalDataset:
    """Database images and query images with the ground truth between them.

    Attributes:
        name, root: display name and folder.
        layout: which layout it was read from.
        database_paths, query_paths: the images, in listed order.
        database_xy, query_xy: ``(n, 2)`` positions in metres (UTM or a local plane), or ``None``.
        ground_truth: which database images are right for each query.
        database_traversal, query_traversal: traversal of each image (indices into ``traversals``).
        traversals: traversal names (``("database", "queries")`` when the layout has none).
        ordered: the database is one route in order (positions along it make sense).
        database_place: ``(n_database,)`` place ids given by the layout (a manifest's
            ``place`` column, prepared places' file names), or ``None`` when places come from group/step.
        notes: what the loader decided (e.g. which traversal queries).
        database_frame, query_frame: ``(n,)`` frame index of each image along the route, for aligned
            traversals (``data.aligned``: frame ``f`` of every traversal is the same spot); ``None`` for
            the other layouts, where group/step in frames count database images in listed order.
        n_frames: frames along the route of aligned traversals (``0`` for the other layouts).
        frame_xy: ``(n_frames, 2)`` position of each frame in metres for aligned traversals with a
            positions file, else ``None``.
        aligned: the aligned traversals this value was made from (``data.aligned.database_queries``),
            for what needs every traversal of every frame (the paper's random split, the open-set
            protocol); ``None`` for the other layouts.
    """

    name: str
    root: Path
    layout: Layout
    database_paths: tuple[Path, ...]
    query_paths: tuple[Path, ...]
    database_xy: np.ndarray | None
    query_xy: np.ndarray | None
    ground_truth: GroundTruth
    database_traversal: np.ndarray
    query_traversal: np.ndarray
    traversals: tuple[str, ...]
    ordered: bool = True
    database_place: np.ndarray | None = None
    notes: tuple[str, ...] = ()
    database_frame: np.ndarray | None = None
    query_frame: np.ndarray | None = None
    n_frames: int = 0
    frame_xy: np.ndarray | None = None
    aligned: Dataset | None = None

    def __post_init__(self) -> None:
        for a in (self.database_xy, self.query_xy, self.database_traversal, self.query_traversal, self.database_place,
                  self.database_frame, self.query_frame, self.frame_xy):
            if a is not None:
                a.setflags(write=False)

    @property
    def n_database(self) -> int:
        return len(self.database_paths)

    @property
    def n_queries(self) -> int:
        return len(self.query_paths)

    @property
    def n_images(self) -> int:
        return self.n_database + self.n_queries

    @cached_property
    def image_paths(self) -> tuple[Path, ...]:
        """Database images, then query images: the order descriptors are computed and listed in."""
        return self.database_paths + self.query_paths

    def describe(self) -> str:
        gt = self.ground_truth
        return (f"{self.name} ({self.layout.value}): {self.n_database:,} database and {self.n_queries:,} query images; "
                f"right: {gt.description}; {gt.n_unknown:,} queries with no right database image")


# --------------------------------------------------------------------------- helpers


def _images_below(folder: Path) -> list[Path]:
    """Every image below ``folder`` (recursively), in natural order of the relative path.

    Hidden files and folders are left out and symbolic links to folders are not followed; a
    folder that cannot be listed, or an entry named as an image that is a symbolic link to
    nothing or cannot be read, raises ``VPRInputError`` naming it.
    """
    found: list[Path] = []
    todo = [folder]
    while todo:
        here = todo.pop()
        try:
            with os.scandir(here) as listing:
                listed = list(listing)
        except OSError as exc:
            raise VPRInputError(unusable(here, exc)) from exc
        for entry in listed:
            if entry.name.startswith("."):
                continue
            path = here / entry.name
            if entry.is_dir(follow_symlinks=False):
                todo.append(path)
            elif path.suffix.lower() in IMAGE_SUFFIXES and kind(path) == "file":
                found.append(path)
    return sorted(found, key=lambda p: natural_key(p.relative_to(folder).as_posix()))


def _utm_from_name(path: Path) -> tuple[float, float, str]:
    """East, north and zone (e.g. ``"55H"``) from a ``@east@north@zone@letter@…`` file name."""
    parts = path.name.split("@")
    try:
        east, north = float(parts[1]), float(parts[2])
    except (IndexError, ValueError):
        raise VPRInputError(
            f"{path}: the file name carries no position; database-queries layouts name images "
            "'@UTM_east@UTM_north@zone@letter@…' (VPR datasets downloader), or use a manifest CSV"
        ) from None
    problem = position_problem(east, north)
    if problem is not None:
        raise VPRInputError(f"{path}: in the file name, {problem}")
    zone = "".join(parts[3:5]) if len(parts) > 4 else ""
    return east, north, zone


def _positions_from_names(paths: list[Path]) -> np.ndarray:
    xy = np.empty((len(paths), 2))
    zones: dict[str, Path] = {}
    for i, p in enumerate(paths):
        east, north, zone = _utm_from_name(p)
        xy[i] = east, north
        zones.setdefault(zone, p)
    if len(zones) > 1:
        (z1, p1), (z2, p2) = list(zones.items())[:2]
        raise VPRInputError(
            f"{p2}: UTM zone {z2 or '(none)'} differs from {p1}'s zone {z1 or '(none)'}; distances across "
            "UTM zones are meaningless: split the dataset by zone"
        )
    return xy


def _check_nonempty(paths: list[Path], folder: Path) -> None:
    if not paths:
        raise VPRInputError(f"{folder}: holds no images ({', '.join(sorted(IMAGE_SUFFIXES))})")
    for p in paths:
        if p.stat().st_size == 0:
            raise VPRInputError(f"{p}: the image file is empty (0 bytes); replace or remove it")


def _two_sides(n_db: int, n_q: int) -> tuple[np.ndarray, np.ndarray, tuple[str, str]]:
    return np.zeros(n_db, dtype=np.int64), np.ones(n_q, dtype=np.int64), ("database", "queries")


# --------------------------------------------------------------------------- the layouts


def _database_queries_root(root: Path) -> Path | None:
    for base in (root, root / "images" / "test"):
        if (base / "database").is_dir() and (base / "queries").is_dir():
            return base
    return None


def load_database_queries(root: Path, radius: float = DEFAULT_RADIUS) -> RetrievalDataset:
    """``database/`` and ``queries/`` with ``@east@north@…`` names; positives within ``radius`` m."""
    base = _database_queries_root(root)
    if base is None:
        raise VPRInputError(f"{root}: no database/ and queries/ folders (nor images/test/database and …/queries)")
    db, q = _images_below(base / "database"), _images_below(base / "queries")
    _check_nonempty(db, base / "database")
    _check_nonempty(q, base / "queries")
    both = _positions_from_names(db + q)
    db_xy, q_xy = both[:len(db)], both[len(db):]
    dt, qt, names = _two_sides(len(db), len(q))
    return RetrievalDataset(
        name=root.name, root=root, layout=Layout.DATABASE_QUERIES, database_paths=tuple(db), query_paths=tuple(q),
        database_xy=db_xy, query_xy=q_xy, ground_truth=GroundTruth.from_positions(q_xy, db_xy, radius),
        database_traversal=dt, query_traversal=qt, traversals=names, ordered=False,
    )


def _is_vpr_bench_row(item) -> bool:
    return isinstance(item, list | tuple) and len(item) == 2 and isinstance(item[1], list | tuple | np.ndarray)


def _load_vpr_bench_rows(path: Path, n_q: int, n_db: int) -> list[np.ndarray]:
    """Each query's right reference indices from ``ground_truth_new.npy``; nothing in the file is run.

    ``safe_npy`` reads the file. Three forms: VPR-Bench's object array of rows ``[query
    index, [reference indices]]`` (``(n, 2)``, or ``(n,)`` of such pairs); an object array
    of ``n_q`` reference-index lists or arrays, the ``i``-th for query ``i``; a 2-D integer
    array of ``n_q`` rows, row ``i`` the reference indices of query ``i`` (so an ``(n_q, 2)``
    integer array is two references per query, not ``[query, reference]`` pairs). Every
    index must be an integer: 0.9, 2.0 or NaN is refused as found, never rounded. A row
    whose only reference is ``-1`` (``NO_REFERENCE``) is a query with no right reference, as
    VPR-Bench marks the true negatives of its ``*_TN`` sets (its recall finds no retrieved
    image in ``[-1]``); ``-1`` beside real references, or any other negative index, is refused.
    """
    data = read_npy(path)
    expected = "VPR-Bench's array of [query index, [reference indices]] rows"
    per_query = None
    if data.ndim == 0:
        raise VPRInputError(f"{path}: holds one {type(data.item()).__name__} (a 0-d array), not {expected}")
    if data.dtype != object and data.ndim == 2:
        if data.dtype.kind in "fc":  # refused below; name the first row with a fractional value or NaN, if any
            first = int(np.argmin((np.isfinite(data) & (data == np.round(data))).all(axis=1)))
            as_indices(data[first], path=path, where=f"row {first + 1}", what="reference")
        per_query = list(data)
    elif data.dtype != object:
        raise VPRInputError(f"{path}: holds an array of {data.dtype}, shape {data.shape}, not {expected} "
                            "nor a 2-D array of reference indices (row i for query i)")
    elif data.ndim == 2 and data.shape[1] == 2:
        rows = [(row[0], row[1]) for row in data]
    elif data.ndim == 1 and len(data) and all(_is_vpr_bench_row(item) for item in data):
        rows = [(item[0], item[1]) for item in data]
    elif data.ndim == 1:
        per_query = list(data)
    else:
        raise VPRInputError(f"{path}: holds an object array of shape {data.shape}, not {expected}")
    if per_query is not None:
        if len(per_query) != n_q:
            raise VPRInputError(f"{path}: {len(per_query)} rows of reference indices, but query/ holds {n_q} images; "
                                f"row i lists the references of query i (or write {expected})")
        rows = list(enumerate(per_query))
    lists: list[np.ndarray | None] = [None] * n_q
    for line, (query, references) in enumerate(rows, start=1):
        query_index = as_indices(query, path=path, where=f"row {line}", what="query index")
        if query_index.size != 1:
            raise VPRInputError(f"{path}: row {line} is not [query index, [reference indices]]")
        qi, refs = int(query_index[0]), as_indices(references, path=path, where=f"row {line}", what="reference")
        if refs.size and (refs == NO_REFERENCE).all():
            refs = refs[:0]  # VPR-Bench's true-negative query: no reference is right
        if not 0 <= qi < n_q:
            raise VPRInputError(f"{path}: row {line} names query {qi}, but query/ holds {n_q} images (0..{n_q - 1})")
        if refs.size and (refs.min() < 0 or refs.max() >= n_db):
            bad = int(refs[(refs < 0) | (refs >= n_db)][0])
            raise VPRInputError(f"{path}: row {line} points at reference {bad}, past the {n_db} images of ref/ "
                                f"(0..{n_db - 1})")
        if lists[qi] is not None:
            raise VPRInputError(f"{path}: row {line} repeats query {qi}")
        lists[qi] = refs
    return [np.empty(0, np.int64) if x is None else x for x in lists]


def load_vpr_bench(root: Path) -> RetrievalDataset:
    """VPR-Bench: ``ref/``, ``query/`` and ``ground_truth_new.npy``."""
    gt_path = root / VPR_BENCH_GT
    if not gt_path.is_file() or not (root / "ref").is_dir() or not (root / "query").is_dir():
        raise VPRInputError(f"{root}: VPR-Bench needs ref/, query/ and {VPR_BENCH_GT}")
    db, q = _images_below(root / "ref"), _images_below(root / "query")
    _check_nonempty(db, root / "ref")
    _check_nonempty(q, root / "query")
    lists = _load_vpr_bench_rows(gt_path, len(q), len(db))
    dt, qt, names = _two_sides(len(db), len(q))
    return RetrievalDataset(
        name=root.name, root=root, layout=Layout.VPR_BENCH, database_paths=tuple(db), query_paths=tuple(q),
        database_xy=None, query_xy=None,
        ground_truth=GroundTruth.from_lists(lists, len(db), f"listed in {VPR_BENCH_GT}", what=str(gt_path)),
        database_traversal=dt, query_traversal=qt, traversals=("ref", "query"), ordered=True,
    )


def _csv_rows(path: Path, wants: str) -> list[tuple[int, list[str]]]:
    """The rows of a CSV (UTF-8, a byte-order mark allowed) with their line numbers; blank and ``#`` lines left out.

    ``wants`` says what the file should hold, for the message when it is empty.
    """
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh)
            rows = [(reader.line_num, r) for r in reader if r and not r[0].strip().startswith("#")]
    except UnicodeDecodeError as exc:
        raise VPRInputError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start}); save it as UTF-8 "
                            "CSV") from None
    except csv.Error as exc:
        raise VPRInputError(f"{path}: not a readable CSV ({exc})") from None
    if not rows:
        raise VPRInputError(f"{path}: empty; it needs {wants}")
    return rows


def _read_xy_csv(path: Path) -> tuple[np.ndarray, bool, np.ndarray]:
    """Positions from a CSV with a header ``x,y`` (metres) or ``lat,lon`` (degrees).

    Returns ``(n, 2)`` values as written, whether they are lat/lon, and the line of each.
    """
    rows = _csv_rows(path, "a header 'x,y' (metres) or 'lat,lon' and one row per frame")
    header_line, header_row = rows[0]
    header = [h.strip().lower() for h in header_row]
    if {"x", "y"} <= set(header):
        cols, latlon = (header.index("x"), header.index("y")), False
    elif {"lat", "lon"} <= set(header):
        cols, latlon = (header.index("lat"), header.index("lon")), True
    else:
        raise VPRInputError(f"{path}: line {header_line} must name the columns: 'x,y' (metres) or 'lat,lon' "
                            f"(degrees), not {', '.join(header_row)}")
    values = np.empty((len(rows) - 1, 2))
    lines = np.array([line for line, _ in rows[1:]], dtype=np.int64)
    for i, (line, row) in enumerate(rows[1:]):
        try:
            values[i] = float(row[cols[0]]), float(row[cols[1]])
        except (ValueError, IndexError):
            raise VPRInputError(f"{path}: line {line} has no numbers in columns {header_row[cols[0]]}, "
                                f"{header_row[cols[1]]}") from None
        if not np.isfinite(values[i]).all():
            raise VPRInputError(f"{path}: line {line}: the position is not finite")
        problem = None if latlon else position_problem(*values[i])
        if problem is not None:
            raise VPRInputError(f"{path}: line {line}: {problem}")
    return values, latlon, lines


def _latlon_to_utm(files: list[tuple[Path, np.ndarray, np.ndarray]]) -> tuple[list[np.ndarray], str]:
    """Every file's lat/lon as metres of ONE UTM zone, and a note saying which.

    ``files`` holds ``(path, (n, 2) lat/lon, line of each row)``. The zone (and hemisphere)
    is the one most positions lie in, ties to the first file's: converted each in its own
    zone, traversals on either side of a zone boundary would land hundreds of kilometres
    apart. UTM is accurate to well under 1 % a zone or two beyond its own.
    """
    import utm

    for path, values, lines in files:
        lat, lon = values[:, 0], values[:, 1]
        bad = np.flatnonzero(~((lat >= -80) & (lat <= 84) & (lon >= -180) & (lon <= 180)))
        if bad.size:
            i = bad[0]
            raise VPRInputError(f"{path}: line {lines[i]}: lat {lat[i]:g}, lon {lon[i]:g} is not a position UTM "
                                "covers (latitude −80…84, longitude −180…180)")
    everything = np.concatenate([values for _, values, _ in files])
    zones = np.array([utm.latlon_to_zone_number(lat, lon) for lat, lon in everything.tolist()], dtype=np.int64)
    numbers, first, counts = np.unique(zones, return_index=True, return_counts=True)
    zone = int(numbers[max(range(len(numbers)), key=lambda i: (counts[i], -first[i]))])
    north = everything[:, 0] >= 0
    northern = bool(2 * north.sum() > len(north) or (2 * north.sum() == len(north) and north[0]))
    converted = []
    for _, values, _ in files:
        east, northing, _, _ = utm.from_latlon(values[:, 0], values[:, 1], force_zone_number=zone,
                                               force_northern=northern)
        converted.append(np.column_stack([east, northing]))
    note = (f"lat/lon converted to UTM zone {zone} ({'north' if northern else 'south'}), the zone of most "
            "positions, for every traversal")
    away = (zones != zone) | (north != northern)
    if away.any():
        where = [*(f"zone {z}" for z in sorted({int(z) for z in zones[zones != zone]})),
                 *(["across the equator"] if (north != northern).any() else [])]
        note += (f"; {int(away.sum()):,} of {len(zones):,} positions lie outside it ({', '.join(where)}) and are "
                 "measured in it too")
    return converted, note


def load_traversal_positions(root: Path, radius: float = DEFAULT_RADIUS, database: list[str] | None = None,
                             queries: str | None = None) -> RetrievalDataset:
    """Traversal folders, each with a ``positions.csv`` (one row per frame); positives within ``radius`` m.

    The query traversal and the database traversals are ``queries``/``database`` when given,
    else recognised from the names (``ref``/``query`` …), else the last against the others.
    Every ``positions.csv`` gives ``x,y`` metres, or every one ``lat,lon``; lat/lon are
    converted in one UTM zone for all traversals (``_latlon_to_utm``, stated in ``notes``).
    """
    subs = sorted((p for p in entries(root) if not p.name.startswith(".") and kind(p) == "folder"),
                  key=lambda p: natural_key(p.name))
    listed = [(sub, images_in(sub)) for sub in subs]
    listed = [(sub, paths) for sub, paths in listed if paths]
    if len(listed) < 2:
        raise VPRInputError(f"{root}: traversal-positions needs at least 2 traversal folders of images")
    names = tuple(sub.name for sub, _ in listed)
    frames, read = [], []
    for sub, paths in listed:
        pos_file = sub / POSITIONS_FILE
        if not pos_file.is_file():
            raise VPRInputError(f"{pos_file}: missing; every traversal folder needs its {POSITIONS_FILE} "
                                "(header 'x,y' or 'lat,lon', one row per frame)")
        pos, latlon, lines = _read_xy_csv(pos_file)
        if len(pos) != len(paths):
            raise VPRInputError(f"{pos_file}: {len(pos)} positions for {len(paths)} frames; one row per frame")
        if read and latlon != read[0][3]:
            first, kinds = read[0][0], {True: "lat,lon (degrees)", False: "x,y (metres)"}
            raise VPRInputError(f"{pos_file}: gives {kinds[latlon]}, but {first} gives {kinds[not latlon]}; "
                                f"give every traversal's {POSITIONS_FILE} the same columns")
        _check_nonempty(paths, sub)
        frames.append(paths)
        read.append((pos_file, pos, lines, latlon))
    if read[0][3]:
        xy, zone_note = _latlon_to_utm([(path, pos, lines) for path, pos, lines, _ in read])
        extra: tuple[str, ...] = (zone_note,)
    else:
        xy, extra = [pos for _, pos, _, _ in read], ()
    if queries is not None or database:
        index = {n: i for i, n in enumerate(names)}
        for n in [*(database or []), *([queries] if queries else [])]:
            if n not in index:
                raise VPRInputError(f"traversal {n!r} is not in {root}: choose one of {', '.join(names)}")
        q = index[queries] if queries is not None else len(names) - 1
        db = [index[n] for n in database] if database else [i for i in range(len(names)) if i != q]
        how = "as given"
    else:
        roles = traversal_roles(names)
        q = roles.query
        db = list(roles.database) if roles.by_name else [i for i in range(len(names)) if i != q]
        how = "recognised from the names" if roles.by_name else "the last traversal against the others"
    if q in db:
        raise VPRInputError(f"queries={names[q]!r} is also a database traversal; pick another")
    db_paths = [p for t in db for p in frames[t]]
    db_xy = np.concatenate([xy[t] for t in db])
    db_trav = np.concatenate([np.full(len(frames[t]), t) for t in db]).astype(np.int64)
    q_xy = xy[q]
    return RetrievalDataset(
        name=root.name, root=root, layout=Layout.TRAVERSAL_POSITIONS, database_paths=tuple(db_paths),
        query_paths=tuple(frames[q]), database_xy=db_xy, query_xy=q_xy,
        ground_truth=GroundTruth.from_positions(q_xy, db_xy, radius), database_traversal=db_trav,
        query_traversal=np.full(len(frames[q]), q, dtype=np.int64), traversals=names, ordered=len(db) == 1,
        notes=(f"queries {names[q]} against {', '.join(names[t] for t in db)} ({how})", *extra),
    )


def _missing_files(root: Path, names: list[str], threads: int = 4) -> set[int]:
    """Indices of ``names`` (relative to ``root``, or absolute) that are not files: ``os.stat`` on strings in a few
    threads (it frees the GIL), 10× faster than ``Path.is_file`` at a million manifest lines."""
    from concurrent.futures import ThreadPoolExecutor

    base = os.fspath(root)

    def part(lo: int) -> list[int]:
        return [i for i in range(lo, min(lo + 65_536, len(names)))
                if not os.path.isfile(os.path.join(base, names[i]))]

    with ThreadPoolExecutor(threads) as pool:
        return {i for found in pool.map(part, range(0, len(names), 65_536)) for i in found}


def _not_an_image_file(image: Path) -> str:
    """Why a manifest row's ``image`` is not a file to read: missing, a folder, a broken link, unreadable."""
    if not os.path.lexists(image):
        return f"{image} does not exist"
    try:
        what = kind(image)
    except VPRInputError as exc:  # a symbolic link to nothing, or no permission: the message names it
        return str(exc)
    if what == "folder":
        return f"{image} is a folder, not an image file"
    return f"{image} is not a regular file" if what == "other" else f"{image} cannot be read"


def _outside(path: Path, line: int, image: str, within: Path) -> VPRInputError | None:
    """The refusal of a manifest row whose image does not lie under ``within`` (by its path's text, nothing looked at)."""
    if Path(os.path.normpath(image)).is_relative_to(within):
        return None
    return VPRInputError(f"{path}: line {line}: {image} is not under {within}, the only folder this reader may "
                         "open; give the images' paths inside it")


def load_manifest(path: Path, radius: float = DEFAULT_RADIUS, *, within: Path | None = None) -> RetrievalDataset:
    """A CSV ``path,role[,x,y][,place]``; the ground truth is the same ``place`` id when that column is there,
    else positions within ``radius`` metres.

    An image path is relative to the CSV's folder, or absolute (used as given). The file is
    UTF-8 (a byte-order mark allowed); blank lines and lines starting with ``#`` are left out.
    With ``within`` (the app's data root), a row whose path, ``..`` taken out, does not lie
    under that folder is refused before any image is looked at.
    """
    root = path.parent
    rows = _csv_rows(path, "a header 'path,role,x,y' or 'path,role,place'")
    header_line, header_row = rows[0]
    header = [h.strip().lower() for h in header_row]
    if "path" not in header or "role" not in header:
        raise VPRInputError(f"{path}: line {header_line} must name the columns path and role, and x,y or place, "
                            f"not {', '.join(header_row)}")
    has_xy, has_place = {"x", "y"} <= set(header), "place" in header
    if not (has_xy or has_place):
        raise VPRInputError(f"{path}: line {header_line} names neither x,y nor place: the ground truth needs one "
                            "of them")
    col = {h: i for i, h in enumerate(header)}
    sides: dict[str, list] = {"database": [], "query": []}
    relative = [row[col["path"]].strip() if len(row) > col["path"] else "" for _, row in rows[1:]]
    if within is not None:
        for (line, _), rel in zip(rows[1:], relative):
            refusal = _outside(path, line, os.path.join(root, rel), Path(within))
            if refusal is not None:
                raise refusal
    missing = _missing_files(root, relative)
    for i, (line, row) in enumerate(rows[1:]):
        try:
            rel, role = row[col["path"]].strip(), row[col["role"]].strip().lower()
            role = {"db": "database", "ref": "database", "reference": "database", "queries": "query"}.get(role, role)
            xy = (float(row[col["x"]]), float(row[col["y"]])) if has_xy else (np.nan, np.nan)
            place = row[col["place"]].strip() if has_place else ""
        except (IndexError, ValueError):
            raise VPRInputError(f"{path}: line {line} does not fill the columns {', '.join(header_row)}") from None
        if role not in sides:
            raise VPRInputError(f"{path}: line {line}: role {role!r} must be database or query")
        image = (root / rel)
        if not rel:
            raise VPRInputError(f"{path}: line {line}: the path column is empty; give the image's path")
        if i in missing:
            raise VPRInputError(f"{path}: line {line}: {_not_an_image_file(image)}")
        problem = position_problem(*xy) if has_xy else None
        if problem is not None:
            raise VPRInputError(f"{path}: line {line}: {problem}")
        sides[role].append((image, xy, place))
    db, q = sides["database"], sides["query"]
    if not db or not q:
        raise VPRInputError(f"{path}: it needs both database and query rows ({len(db)} and {len(q)} found)")
    db_xy = np.array([x for _, x, _ in db]) if has_xy else None
    q_xy = np.array([x for _, x, _ in q]) if has_xy else None
    database_place = None
    if has_place:
        ids = {p: i for i, p in enumerate(sorted({p for _, _, p in db if p}, key=natural_key))}
        database_place = np.array([ids.get(p, -1) for _, _, p in db], dtype=np.int64)
        gt = GroundTruth.from_lists([np.flatnonzero(database_place == ids[p]) if p in ids else [] for _, _, p in q],
                                    len(db), "the same place id", what=str(path))
    else:
        gt = GroundTruth.from_positions(q_xy, db_xy, radius)
    dt, qt, names = _two_sides(len(db), len(q))
    return RetrievalDataset(
        name=root.name if path.name in MANIFEST_NAMES else path.stem, root=root, layout=Layout.MANIFEST,
        database_paths=tuple(p for p, _, _ in db), query_paths=tuple(p for p, _, _ in q),
        database_xy=db_xy, query_xy=q_xy, ground_truth=gt, database_traversal=dt, query_traversal=qt,
        traversals=names, ordered=False, database_place=database_place,
    )


def detect_layout(path: Path) -> Layout:
    """The layout of a dataset path (module doc): a CSV file is a manifest; a folder is
    VPR-Bench with its ground-truth file, database-queries with those folders, traversal
    positions when every traversal folder has a ``positions.csv``, else traversals/prepared.

    Raises:
        VPRInputError: naming an entry that cannot be read (no permission, a symbolic link to nothing).
    """
    with reading(path):
        if path.is_file():
            if path.suffix.lower() == ".csv":
                return Layout.MANIFEST
            raise VPRInputError(f"{path}: a dataset is a folder, or a manifest .csv file")
        if any((path / m).is_file() for m in MANIFEST_NAMES):
            return Layout.MANIFEST
        if (path / VPR_BENCH_GT).is_file():
            return Layout.VPR_BENCH
        if _database_queries_root(path) is not None:
            return Layout.DATABASE_QUERIES
        subs = [p for p in entries(path) if not p.name.startswith(".") and kind(p) == "folder"]
        if len(subs) >= 2 and all((p / POSITIONS_FILE).is_file() for p in subs):
            return Layout.TRAVERSAL_POSITIONS
        return Layout.TRAVERSALS


def load_retrieval(path: Path, layout: Layout, *, radius: float = DEFAULT_RADIUS, database: list[str] | None = None,
                   queries: str | None = None, within: Path | None = None) -> RetrievalDataset:
    """Read one of ``RETRIEVAL_LAYOUTS``.

    ``radius`` (metres, checked by ``groundtruth.check_radius`` whatever the layout) makes
    the ground truth of position-tagged data; VPR-Bench and a manifest's place ids list
    theirs, and do not read it (``radius_applies`` says which). ``within``: a manifest may
    name images only under this folder (``load_manifest``); the other layouts list images
    below the dataset's own folder.

    Raises:
        VPRInputError: naming the file, line or option at fault; a file or folder that
            cannot be read is named, never a traceback.
    """
    radius = check_radius(radius, "radius")
    with reading(path):
        if layout is Layout.DATABASE_QUERIES:
            return load_database_queries(path, radius)
        if layout is Layout.VPR_BENCH:
            return load_vpr_bench(path)
        if layout is Layout.TRAVERSAL_POSITIONS:
            return load_traversal_positions(path, radius, database, queries)
        if layout is Layout.MANIFEST:
            if path.is_file():
                return load_manifest(path, radius, within=within)
            manifest = next((path / m for m in MANIFEST_NAMES if (path / m).is_file()), None)
            if manifest is None:
                raise VPRInputError(f"{path}: --layout manifest needs a {' or '.join(MANIFEST_NAMES)} in the folder, "
                                    "or the path of a manifest .csv file (header path,role and x,y or place)")
            return load_manifest(manifest, radius, within=within)
    raise VPRInputError(f"layout {layout.value!r} is not a database/queries layout")


def radius_applies(dataset: RetrievalDataset) -> bool:
    """Whether ``dataset``'s ground truth is the database images within a radius of each query's position.

    ``False`` for VPR-Bench (its ground-truth file lists them) and a manifest with a ``place``
    column (the same place id), whose ground truth no radius changes.
    """
    return dataset.database_xy is not None and dataset.database_place is None
