"""Datasets of route traversals: folders of frames where the same index is the same spot.

Two layouts are read:

* **traversal folders** (GardensPoint, Nordland): ``ROOT/<traversal>/<frames>``, one
  sub-folder per traversal (condition), frames ordered by natural sort of their names;
  every traversal must hold the same number of frames, and frame ``f`` of every
  traversal shows the same spot.
* **prepared places** (the paper's naming): ``ROOT/Place####_Cond##_G##.<ext>``; each
  condition becomes a traversal and the place of every frame is given by the name, so
  group/step do not apply.

Loading lists files only; decoding happens at descriptor extraction, which names any
unreadable file.
"""

from __future__ import annotations

import csv
import errno
import os
import re
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from vpr_explorer.errors import VPRInputError

IMAGE_SUFFIXES = frozenset({".jpg", ".jpeg", ".png", ".bmp", ".ppm", ".pgm", ".tif", ".tiff", ".webp"})
PREPARED_NAME = re.compile(r"^Place(\d+)_Cond(\d+)_G(\d+)$", re.IGNORECASE)
POSITION_FILES = ("positions.csv", "gp_pos.csv")


DATABASE_NAMES = frozenset({"ref", "reference", "database", "db", "map"})
QUERY_NAMES = frozenset({"query", "queries", "q", "live"})
"""Traversal (folder) names, case-insensitive, that say which side a traversal is on."""


def natural_key(name: str) -> tuple:
    """Sort key that orders ``Image2`` before ``Image10``."""
    return tuple(int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name))


@dataclass(frozen=True)
class TraversalRoles:
    """Which traversals are the database and which one queries, and how that was decided.

    Attributes:
        database: traversal indices of the database.
        query: traversal index of the queries.
        by_name: ``True`` when the traversal names decided it (e.g. ``ref/`` and ``query/``),
            ``False`` for folder order (the first traversal against the last).
    """

    database: tuple[int, ...]
    query: int
    by_name: bool

    def describe(self, traversals: tuple[str, ...]) -> str:
        """E.g. "query against ref (recognised from the traversal names)"."""
        db = ", ".join(traversals[t] for t in self.database)
        how = ("recognised from the traversal names" if self.by_name
               else "by folder order: the first traversal against the last")
        return f"{traversals[self.query]} against {db} ({how})"


def traversal_roles(traversals: tuple[str, ...] | list[str]) -> TraversalRoles:
    """The default database and query traversals of a dataset.

    Names decide first: a traversal called ``query``/``queries``/``q``/``live`` is the query
    and one called ``ref``/``reference``/``database``/``db``/``map`` the database
    (case-insensitive). Otherwise folder order: the last traversal queries the first, as
    in GardensPoint (``day_left`` … ``night_right``) and Nordland (``summer``, ``winter``).
    """
    names = [t.lower() for t in traversals]
    n = len(names)
    if n < 2:
        raise VPRInputError(f"{n} traversal(s): a database and a query traversal need at least 2")
    named_q = [i for i, t in enumerate(names) if t in QUERY_NAMES]
    named_db = [i for i, t in enumerate(names) if t in DATABASE_NAMES]
    if len(named_q) == 1:
        q = named_q[0]
    elif named_db and not named_q:
        q = max(i for i in range(n) if i not in named_db) if len(named_db) < n else None
    else:
        q = None
    if q is None:  # nothing (or nothing unambiguous) recognised: folder order
        return TraversalRoles(database=(0,), query=n - 1, by_name=False)
    database = tuple(i for i in named_db if i != q) or (next(i for i in range(n) if i != q),)
    return TraversalRoles(database=database, query=q, by_name=True)


@dataclass(frozen=True, eq=False)
class Dataset:
    """Traversals of one route; image ``i`` is frame ``i % n_frames`` of traversal ``i // n_frames``.

    Attributes:
        name: display name (the folder name, or ``demo``).
        root: the folder the dataset was read from.
        traversals: traversal (condition) names, in order.
        paths: ``paths[t][f]`` is the file of frame ``f`` in traversal ``t``.
        prepared_places: ``(n_frames,)`` place id of each frame when the layout fixes the
            places (``Place####_Cond##_G##``), else ``None``.
        positions: ``(n_frames, 2)`` route positions ``x, y`` when a ``positions.csv`` or
            ``gp_pos.csv`` with one row per frame sits in the root, else ``None``.
    """

    name: str
    root: Path
    traversals: tuple[str, ...]
    paths: tuple[tuple[Path, ...], ...]
    prepared_places: np.ndarray | None = None
    positions: np.ndarray | None = None
    notes: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        for array in (self.prepared_places, self.positions):
            if array is not None:
                array.setflags(write=False)

    @property
    def n_traversals(self) -> int:
        return len(self.traversals)

    @property
    def n_frames(self) -> int:
        return len(self.paths[0])

    @property
    def n_images(self) -> int:
        return self.n_traversals * self.n_frames

    @cached_property
    def image_paths(self) -> tuple[Path, ...]:
        """All images in image order (traversal-major)."""
        return tuple(p for frames in self.paths for p in frames)

    @cached_property
    def image_traversal(self) -> np.ndarray:
        """``(n_images,)`` traversal index of each image."""
        out = np.repeat(np.arange(self.n_traversals), self.n_frames)
        out.setflags(write=False)
        return out

    @cached_property
    def image_frame(self) -> np.ndarray:
        """``(n_images,)`` frame index of each image."""
        out = np.tile(np.arange(self.n_frames), self.n_traversals)
        out.setflags(write=False)
        return out

    def traversal_index(self, traversal: str | int) -> int:
        """Index of a traversal given by name or index; raises naming the choices."""
        if isinstance(traversal, (int, np.integer)):
            if 0 <= traversal < self.n_traversals:
                return int(traversal)
        elif traversal in self.traversals:
            return self.traversals.index(traversal)
        raise VPRInputError(
            f"traversal {traversal!r} is not in dataset {self.name!r}: "
            f"choose one of {', '.join(self.traversals)}"
        )

    def default_roles(self) -> TraversalRoles:
        """The database and query traversals to use when none are given (see ``traversal_roles``)."""
        return traversal_roles(self.traversals)

    def image_index(self, traversal: str | int, frame: int) -> int:
        """Index of frame ``frame`` of ``traversal`` in image order."""
        t = self.traversal_index(traversal)
        if not 0 <= frame < self.n_frames:
            raise VPRInputError(f"frame {frame} is out of range: {self.name!r} has frames 0..{self.n_frames - 1}")
        return t * self.n_frames + int(frame)


def unusable(path: Path, exc: OSError) -> str:
    """Why ``path`` cannot be read, for a message: a broken symbolic link names its target."""
    if os.path.islink(path) and exc.errno in (errno.ENOENT, errno.ENOTDIR, errno.ELOOP):
        try:
            target = os.readlink(path)
        except OSError:
            target = "?"
        if exc.errno == errno.ELOOP:
            return f"{path}: a symbolic link to {target} in a loop of links that never reaches a file; remove or fix it"
        return f"{path}: a symbolic link to {target}, which does not exist; remove or fix it"
    return (f"{path}: cannot be read ({exc.strerror or exc}); fix it or its permissions, or remove it from the "
            "dataset folder")


def entries(folder: Path) -> list[Path]:
    """The entries of ``folder``; a folder that cannot be listed raises ``VPRInputError`` naming it."""
    try:
        return list(folder.iterdir())
    except OSError as exc:
        raise VPRInputError(unusable(folder, exc)) from exc


def kind(path: Path) -> str:
    """What ``path`` is once symbolic links are followed: ``"file"``, ``"folder"`` or ``"other"`` (a device …).

    Raises:
        VPRInputError: naming ``path`` when it is a symbolic link to nothing (its target
            missing, or a loop of links), or cannot be read.
    """
    try:
        mode = os.stat(path).st_mode
    except OSError as exc:
        raise VPRInputError(unusable(path, exc)) from exc
    return "file" if stat.S_ISREG(mode) else "folder" if stat.S_ISDIR(mode) else "other"


@contextmanager
def reading(path: Path) -> Iterator[None]:
    """Turn an ``OSError`` met while reading the dataset at ``path`` into one ``VPRInputError`` naming the file."""
    try:
        yield
    except OSError as exc:
        where = Path(exc.filename) if exc.filename else path
        if where == path and not os.path.islink(path):
            raise VPRInputError(f"{path}: cannot be read ({exc.strerror or exc}); check the path and its "
                                "permissions") from exc
        raise VPRInputError(unusable(where, exc)) from exc


def images_in(folder: Path) -> list[Path]:
    """The images directly in ``folder`` (no hidden files), in natural order of their names.

    Raises:
        VPRInputError: the folder cannot be listed, or an entry named as an image is a
            symbolic link to nothing or cannot be read (it is named, never skipped unsaid).
    """
    return sorted(
        (p for p in entries(folder)
         if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".") and kind(p) == "file"),
        key=lambda p: natural_key(p.name),
    )


def _read_positions(root: Path, n_frames: int) -> np.ndarray | None:
    for name in POSITION_FILES:
        path = root / name
        if not path.is_file():
            continue
        try:
            with path.open(newline="", encoding="utf-8-sig") as fh:
                rows = [row for row in csv.reader(fh) if row and not row[0].strip().startswith("#")]
            if rows and not _is_number(rows[0][0]):
                rows = rows[1:]  # header line
            xy = np.array([[float(row[0]), float(row[1])] for row in rows], dtype=np.float64)
        except (ValueError, IndexError) as exc:
            raise VPRInputError(f"{path}: cannot read route positions ({exc}); fix or remove the file") from exc
        if len(xy) != n_frames:
            raise VPRInputError(
                f"{path}: {len(xy)} positions for {n_frames} frames; it needs one 'x,y' row per frame, or remove it"
            )
        return xy
    return None


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _check_nonempty_files(paths: list[Path]) -> None:
    for p in paths:
        if p.stat().st_size == 0:
            raise VPRInputError(f"{p}: the image file is empty (0 bytes); replace or remove it")


def load_traversal_folders(root: Path, traversals: list[str] | None = None) -> Dataset:
    """Read ``ROOT/<traversal>/<frames>``; ``traversals`` picks and orders sub-folders."""
    subdirs = sorted((p for p in entries(root) if not p.name.startswith(".") and kind(p) == "folder"),
                     key=lambda p: natural_key(p.name))
    if traversals is not None:
        by_name = {p.name: p for p in subdirs}
        missing = [t for t in traversals if t not in by_name]
        if missing:
            raise VPRInputError(
                f"{root}: no traversal folder {', '.join(map(repr, missing))}; found {', '.join(by_name) or 'none'}"
            )
        subdirs = [by_name[t] for t in traversals]
    found: list[tuple[str, list[Path]]] = []
    notes = []
    for sub in subdirs:
        frames = images_in(sub)
        if frames:
            found.append((sub.name, frames))
        elif traversals is not None:
            raise VPRInputError(f"{sub}: the traversal folder holds no images ({', '.join(sorted(IMAGE_SUFFIXES))})")
        else:
            notes.append(f"skipped {sub.name}/: no images")
    if not found:
        raise VPRInputError(
            f"{root}: no traversal found: put each traversal's frames in its own sub-folder "
            f"(e.g. {root}/day/0001.jpg), or name images Place####_Cond##_G##"
        )
    lengths = {name: len(frames) for name, frames in found}
    if len(set(lengths.values())) > 1:
        listing = ", ".join(f"{n}: {c}" for n, c in lengths.items())
        raise VPRInputError(
            f"{root}: traversals have different numbers of frames ({listing}); frame i must show the same spot "
            "in every traversal, so give them equal lengths or pick matching traversals"
        )
    for _, frames in found:
        _check_nonempty_files(frames)
    n_frames = len(found[0][1])
    return Dataset(
        name=root.name,
        root=root,
        traversals=tuple(name for name, _ in found),
        paths=tuple(tuple(frames) for _, frames in found),
        positions=_read_positions(root, n_frames),
        notes=tuple(notes),
    )


def load_prepared_places(root: Path) -> Dataset:
    """Read ``ROOT/Place####_Cond##_G##.<ext>``: conditions become traversals, places are fixed."""
    entries: dict[int, dict[tuple[int, int], Path]] = {}
    for p in images_in(root):
        m = PREPARED_NAME.match(p.stem)
        if m is None:
            raise VPRInputError(
                f"{p}: mixes with Place####_Cond##_G## images but is not named that way; rename or move it"
            )
        place, cond, g = (int(x) for x in m.groups())
        entries.setdefault(cond, {})[(place, g)] = p
    if not entries:
        raise VPRInputError(f"{root}: no Place####_Cond##_G## images found")
    conds = sorted(entries)
    keys = sorted(entries[conds[0]])
    for c in conds[1:]:
        if sorted(entries[c]) != keys:
            diff = sorted(set(entries[c]) ^ set(keys))[:3]
            raise VPRInputError(
                f"{root}: condition {c:02d} does not have the same places and frames as condition "
                f"{conds[0]:02d} (e.g. Place{diff[0][0]:04d}_G{diff[0][1]:02d}); every condition needs every frame"
            )
    place_ids = sorted({place for place, _ in keys})
    rank = {pid: i for i, pid in enumerate(place_ids)}
    paths = tuple(tuple(entries[c][k] for k in keys) for c in conds)
    for frames in paths:
        _check_nonempty_files(list(frames))
    return Dataset(
        name=root.name,
        root=root,
        traversals=tuple(f"Cond{c:02d}" for c in conds),
        paths=paths,
        prepared_places=np.array([rank[place] for place, _ in keys], dtype=np.int64),
        positions=_read_positions(root, len(keys)),
    )


def load_dataset(path: str | Path, traversals: list[str] | None = None) -> Dataset:
    """Load a dataset folder in either layout (see the module docstring).

    An entry that cannot be read (no permission, a symbolic link to nothing) is refused by
    name with a ``VPRInputError``, never skipped unsaid.
    """
    root = Path(path).expanduser()
    with reading(root):
        if not root.exists():
            raise VPRInputError(f"{root}: the dataset folder does not exist; check the path")
        if not root.is_dir():
            raise VPRInputError(f"{root}: is a file, not a dataset folder; give the folder that holds the traversals")
        flat = images_in(root)
        if flat and any(PREPARED_NAME.match(p.stem) for p in flat):
            return load_prepared_places(root)
        return load_traversal_folders(root, traversals)
