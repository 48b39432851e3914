"""The field's benchmark layouts: a database and queries, with ground truth as a relation.

Where ``datasets`` reads traversals whose frame indices line up, this module reads the
layouts VPR benchmarks are distributed in, each into a ``RetrievalDataset`` (database
images, query images, positions where the layout has them, and a ``GroundTruth``):

| layout | on disk | right database images |
|---|---|---|
| ``database-queries`` | ``database/`` and ``queries/`` (also under ``images/test/``), the position in every file name as ``@UTM_east@UTM_north@zone@letter@…`` (VPR datasets downloader: St Lucia, Pittsburgh, Tokyo 24/7, MSLS, SF-XL) | within ``radius`` metres (25) |
| ``vpr-bench`` | ``ref/``, ``query/`` and ``ground_truth_new.npy``, one row ``[query index, [reference indices]]`` per query | the listed ones |
| ``traversal-positions`` | traversal folders with ``positions.csv`` in each (``x,y`` in metres, or ``lat,lon``), frames need not line up | within ``radius`` metres |
| ``manifest`` | a CSV ``path,role[,x,y][,place]`` (role ``database``/``query``), for everything else | within ``radius`` metres, or the same place id |

Images are listed in natural order of their path below the folder (what ``vpr-explorer
list`` prints): database first, then queries. Inconsistent input (a name without a
position, a ground-truth row pointing past the reference images, mixed UTM zones) raises
one ``VPRInputError`` naming the file and line.
"""

from __future__ import annotations

import csv
import os
from dataclasses import dataclass
from enum import StrEnum
from functools import cached_property
from pathlib import Path

import numpy as np

from vpr_explorer.datasets import IMAGE_SUFFIXES, images_in, natural_key, traversal_roles
from vpr_explorer.errors import VPRInputError
from vpr_explorer.groundtruth import DEFAULT_RADIUS, GroundTruth


class Layout(StrEnum):
    """How a dataset folder is laid out (``--layout``)."""

    AUTO = "auto"
    TRAVERSALS = "traversals"
    PREPARED = "prepared"
    DATABASE_QUERIES = "database-queries"
    VPR_BENCH = "vpr-bench"
    TRAVERSAL_POSITIONS = "traversal-positions"
    MANIFEST = "manifest"


#: Layouts read into a ``RetrievalDataset`` (the others are ``datasets.Dataset``).
RETRIEVAL_LAYOUTS = frozenset({Layout.DATABASE_QUERIES, Layout.VPR_BENCH, Layout.TRAVERSAL_POSITIONS, Layout.MANIFEST})
VPR_BENCH_GT = "ground_truth_new.npy"
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
        database_place: ``(n_database,)`` place ids given by the layout (a manifest's
            ``place`` column), or ``None`` when places come from group/step.
        database_traversal, query_traversal: traversal of each image (indices into ``traversals``).
        traversals: traversal names (``("database", "queries")`` when the layout has none).
        ordered: the database is one route in order (positions along it make sense).
        notes: what the loader decided (e.g. which traversal queries).
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

    def __post_init__(self) -> None:
        for a in (self.database_xy, self.query_xy, self.database_traversal, self.query_traversal, self.database_place):
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
    """Every image below ``folder`` (recursively), in natural order of the relative path."""
    found = [p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
             and not any(part.startswith(".") for part in p.relative_to(folder).parts)]
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
    if not (np.isfinite(east) and np.isfinite(north)):
        raise VPRInputError(f"{path}: the position in the file name is not finite")
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


def _load_vpr_bench_rows(path: Path, n_q: int, n_db: int) -> list[np.ndarray]:
    try:
        rows = np.load(path, allow_pickle=True)
    except (OSError, ValueError, EOFError) as exc:
        raise VPRInputError(f"{path}: cannot read the ground truth ({exc}); it should be VPR-Bench's "
                            "array of [query index, [reference indices]] rows") from exc
    lists: list[np.ndarray | None] = [None] * n_q
    for line, row in enumerate(rows, start=1):
        try:
            qi = int(row[0])
            refs = np.asarray(row[1], dtype=np.int64).reshape(-1)
        except (TypeError, ValueError, IndexError):
            raise VPRInputError(f"{path}: row {line} is not [query index, [reference indices]]") from None
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


def _read_xy_csv(path: Path) -> np.ndarray:
    """``(n, 2)`` metres from a CSV with a header ``x,y`` (metres) or ``lat,lon`` (degrees → UTM)."""
    with path.open(newline="") as fh:
        rows = [r for r in csv.reader(fh) if r and not r[0].strip().startswith("#")]
    if not rows:
        raise VPRInputError(f"{path}: empty; it needs a header 'x,y' (metres) or 'lat,lon' and one row per frame")
    header = [h.strip().lower() for h in rows[0]]
    if {"x", "y"} <= set(header):
        cols, latlon = (header.index("x"), header.index("y")), False
    elif {"lat", "lon"} <= set(header):
        cols, latlon = (header.index("lat"), header.index("lon")), True
    else:
        raise VPRInputError(f"{path}: line 1 must name the columns: 'x,y' (metres) or 'lat,lon' (degrees)")
    values = np.empty((len(rows) - 1, 2))
    for line, row in enumerate(rows[1:], start=2):
        try:
            values[line - 2] = float(row[cols[0]]), float(row[cols[1]])
        except (ValueError, IndexError):
            raise VPRInputError(f"{path}: line {line} has no numbers in columns {rows[0][cols[0]]}, "
                                f"{rows[0][cols[1]]}") from None
        if not np.isfinite(values[line - 2]).all():
            raise VPRInputError(f"{path}: line {line}: the position is not finite")
    if latlon:
        values = _latlon_to_utm(values, path)
    return values


def _latlon_to_utm(latlon: np.ndarray, path: Path) -> np.ndarray:
    import utm

    try:
        east, north, zone, letter = utm.from_latlon(latlon[:, 0], latlon[:, 1])
    except Exception as exc:  # utm raises OutOfRangeError / ValueError for bad or mixed input
        raise VPRInputError(f"{path}: cannot convert lat/lon to UTM ({exc}); positions must lie in one UTM "
                            "zone, latitude −80…84") from exc
    return np.column_stack([east, north])


def load_traversal_positions(root: Path, radius: float = DEFAULT_RADIUS, database: list[str] | None = None,
                             queries: str | None = None) -> RetrievalDataset:
    """Traversal folders, each with a ``positions.csv`` (one row per frame); positives within ``radius`` m.

    The query traversal and the database traversals are ``queries``/``database`` when given,
    else recognised from the names (``ref``/``query`` …), else the last against the others.
    """
    subs = sorted((p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")),
                  key=lambda p: natural_key(p.name))
    listed = [(sub, images_in(sub)) for sub in subs]
    listed = [(sub, paths) for sub, paths in listed if paths]
    if len(listed) < 2:
        raise VPRInputError(f"{root}: traversal-positions needs at least 2 traversal folders of images")
    names = tuple(sub.name for sub, _ in listed)
    frames, xy = [], []
    for sub, paths in listed:
        pos_file = sub / POSITIONS_FILE
        if not pos_file.is_file():
            raise VPRInputError(f"{pos_file}: missing; every traversal folder needs its {POSITIONS_FILE} "
                                "(header 'x,y' or 'lat,lon', one row per frame)")
        pos = _read_xy_csv(pos_file)
        if len(pos) != len(paths):
            raise VPRInputError(f"{pos_file}: {len(pos)} positions for {len(paths)} frames; one row per frame")
        _check_nonempty(paths, sub)
        frames.append(paths)
        xy.append(pos)
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
        notes=(f"queries {names[q]} against {', '.join(names[t] for t in db)} ({how})",),
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


def load_manifest(path: Path, radius: float = DEFAULT_RADIUS) -> RetrievalDataset:
    """A CSV ``path,role[,x,y][,place]``: image paths relative to the CSV's folder."""
    root = path.parent
    with path.open(newline="") as fh:
        rows = [r for r in csv.reader(fh) if r and not r[0].strip().startswith("#")]
    if not rows:
        raise VPRInputError(f"{path}: empty; it needs a header 'path,role,x,y' or 'path,role,place'")
    header = [h.strip().lower() for h in rows[0]]
    if "path" not in header or "role" not in header:
        raise VPRInputError(f"{path}: line 1 must name the columns path and role, and x,y or place")
    has_xy, has_place = {"x", "y"} <= set(header), "place" in header
    if not (has_xy or has_place):
        raise VPRInputError(f"{path}: line 1 names neither x,y nor place: the ground truth needs one of them")
    col = {h: i for i, h in enumerate(header)}
    sides: dict[str, list] = {"database": [], "query": []}
    missing = _missing_files(root, [row[col["path"]].strip() if len(row) > col["path"] else "" for row in rows[1:]])
    for line, row in enumerate(rows[1:], start=2):
        try:
            rel, role = row[col["path"]].strip(), row[col["role"]].strip().lower()
            role = {"db": "database", "ref": "database", "reference": "database", "queries": "query"}.get(role, role)
            xy = (float(row[col["x"]]), float(row[col["y"]])) if has_xy else (np.nan, np.nan)
            place = row[col["place"]].strip() if has_place else ""
        except (IndexError, ValueError):
            raise VPRInputError(f"{path}: line {line} does not fill the columns {', '.join(rows[0])}") from None
        if role not in sides:
            raise VPRInputError(f"{path}: line {line}: role {role!r} must be database or query")
        image = (root / rel)
        if line - 2 in missing:
            raise VPRInputError(f"{path}: line {line}: {image} does not exist")
        if has_xy and not np.isfinite(xy).all():
            raise VPRInputError(f"{path}: line {line}: the position is not finite")
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
    positions when every traversal folder has a ``positions.csv``, else traversals/prepared."""
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
    subs = [p for p in path.iterdir() if p.is_dir() and not p.name.startswith(".")]
    if len(subs) >= 2 and all((p / POSITIONS_FILE).is_file() for p in subs):
        return Layout.TRAVERSAL_POSITIONS
    return Layout.TRAVERSALS


def load_retrieval(path: Path, layout: Layout, *, radius: float = DEFAULT_RADIUS, database: list[str] | None = None,
                   queries: str | None = None) -> RetrievalDataset:
    """Read one of ``RETRIEVAL_LAYOUTS``."""
    if layout is Layout.DATABASE_QUERIES:
        return load_database_queries(path, radius)
    if layout is Layout.VPR_BENCH:
        return load_vpr_bench(path)
    if layout is Layout.TRAVERSAL_POSITIONS:
        return load_traversal_positions(path, radius, database, queries)
    if layout is Layout.MANIFEST:
        manifest = path if path.is_file() else next(path / m for m in MANIFEST_NAMES if (path / m).is_file())
        return load_manifest(manifest, radius)
    raise VPRInputError(f"layout {layout.value!r} is not a database/queries layout")
