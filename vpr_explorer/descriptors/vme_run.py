"""A VPR-methods-evaluation run folder as a descriptor source.

gmberton/VPR-methods-evaluation (VME) evaluates a model on a database folder and a queries
folder; ``main.py --save_descriptors`` writes two arrays into its log folder
(``logs/<log_dir>/<YYYY-MM-DD_HH-MM-SS>/``, the *run folder*):

* :data:`DATABASE_FILE` ``database_descriptors.npy``: ``(n_database, D)`` float32, row ``i``
  for the ``i``-th image of ``--database_folder``;
* :data:`QUERIES_FILE` ``queries_descriptors.npy``: ``(n_queries, D)``, row ``i`` for the
  ``i``-th image of ``--queries_folder``.

The ``i``-th image is in VME's reader order (``test_dataset.read_images_paths``), per folder:

* the lines of ``<folder>_images_paths.txt`` when that file exists: the folder's path with
  :data:`PATHS_SUFFIX` appended, so ``…/database_images_paths.txt`` *beside* ``database/``;
  each line a path relative to the folder (``./`` and a leading ``/`` allowed);
* else every file below the folder whose extension is ``.jpg``, ``.jpeg`` or ``.png`` (any
  case), hidden entries left out, sorted by plain string comparison of the paths
  (``sorted(glob(folder/**/*, recursive=True))``). That is not the explorer's natural order
  (``seq10/`` sorts before ``seq2/``), so rows are moved to the dataset's images by name.

A run folder is read against a database/queries dataset (``layouts.Layout.DATABASE_QUERIES``):
its ``database/`` and ``queries/`` folders (at the dataset's root, else under
``images/test/``, as the layout reads them) are the folders VME was given, and the
dataset's images are the ones VME's glob finds (both leave out hidden entries). Every other
layout is refused by name: its images are not VME's two folders.

Checks, each fault one :class:`~vpr_explorer.errors.VPRInputError` naming the file: a
missing ``.npy``; a file that is not a ``.npy`` of a 2-D real matrix, or whose header claims
more than the file holds (``imported.read_npy_rows``: ``allow_pickle=False``, the header
checked against the file's size before anything is mapped; a pickled object array is
refused, never run); a names file beside a ``.npy`` (``<stem>.txt``), which would reorder
its rows; without an ``_images_paths.txt``, images of the dataset that VME's glob does not
read (``.bmp``, ``.webp``, …: VME computed no row for them); rows against images (``n`` rows
for ``m`` images of the folder, or of the ``_images_paths.txt``); the two files' descriptor
lengths; in an ``_images_paths.txt``, a blank line, a repeated image, a line that is no
image of the folder, and images of the folder it leaves out (the first few of each); rows
that are NaN, infinite, zero or of a norm below ``MIN_NORM``. Then rows are L2-normalised
as ``imported.load_descriptor_file`` does (unit rows kept as stored), database rows first,
in the dataset's order; VME's models output unit rows, whose faiss L2 order is the
explorer's cosine order.

Name: the run folder's stem, as a descriptor file is named by its stem (VME's timestamp
folders, ``2024-05-01_12-30-00``, have no suffix: their whole name); rename or link the
folder to give the run another name. Key: ``imported.content_key`` over both ``.npy``
files' bytes and every ``_images_paths.txt`` read, the dtype and the dataset's image names,
so an edited file never serves a stale cache; a file that changes while it is read is refused.

What VME and the explorer count alike: a database image within 25 m of a query is a
positive (VME: sklearn ``radius_neighbors``, distance ≤ radius; here
``GroundTruth.from_positions``, distance ≤ radius), and a query counts at Recall@N when one
of its first N database images is one. VME divides by every query; the explorer's image
level by the queries with a positive (a query with none is an unknown place): the two
agree when every query has a positive.
"""

from __future__ import annotations

import hashlib
import os
import posixpath
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vpr_explorer.data.layouts import Layout, RetrievalDataset
from vpr_explorer.descriptors.cache import check_dtype
from vpr_explorer.descriptors.imported import (
    UNIT_TOLERANCE,
    DescriptorFormat,
    ImportedDescriptors,
    content_key,
    file_digests,
    file_stamp,
    read_npy_rows,
    relative_names,
    unit_rows_joined,
)
from vpr_explorer.errors import VPRInputError

DATABASE_FILE = "database_descriptors.npy"
QUERIES_FILE = "queries_descriptors.npy"
PATHS_SUFFIX = "_images_paths.txt"
"""Appended to a folder's path, the file VME reads that folder's image order from when it exists."""
VME_SUFFIXES = (".jpg", ".jpeg", ".png")
"""The extensions VME's glob keeps (compared in lower case)."""
NAMED = 5
KEY_DTYPE = "vme-run-{dtype}"
"""The dtype part of the content key: a run's key never equals a single file's."""


@dataclass(frozen=True, eq=False)
class VMESide:
    """One of a run's two files, matched to one folder of the dataset.

    Attributes:
        npy: the ``.npy`` file.
        folder: the dataset folder its rows describe (``database/`` or ``queries/``).
        order: ``(n_images,)`` the file's row of each of the folder's images, in the dataset's order.
        paths_file: the ``_images_paths.txt`` the rows follow, or ``None`` (VME's sorted glob).
        rows: the ``(n_rows, D)`` read-only memory map, as stored.
        names: the folder's images (paths relative to the dataset root), in the dataset's order.
    """

    npy: Path
    folder: Path
    order: np.ndarray
    paths_file: Path | None
    rows: np.ndarray
    names: tuple[str, ...]


@dataclass(frozen=True, eq=False)
class VMERunDescriptors(ImportedDescriptors):
    """``ImportedDescriptors`` read from a run folder (``path``); ``files``: the files read, digests alike."""

    files: tuple[Path, ...] = field(default=())

    def settings(self) -> dict[str, str]:
        """The run folder's absolute path, and each file read with its sha256 (flat keys)."""
        out = {"descriptors_file": os.path.abspath(self.path)}
        for f, digest in zip(self.files, self.digests):
            label = f.name.removesuffix(".npy").removesuffix(".txt")
            out[label] = os.path.abspath(f)
            out[f"{label}_sha256"] = digest
        return out


def is_run_folder(path: Path) -> bool:
    """Whether ``path`` is a folder (what the descriptor sources read as a VME run, :func:`load_vme_run`)."""
    return Path(path).expanduser().is_dir()


def check_run_folder(folder: Path) -> Path:
    """``folder`` when it holds both of VME's ``.npy`` files; nothing of them is read.

    Raises:
        VPRInputError: naming the folder and the file it lacks.
    """
    folder = Path(folder).expanduser()
    if not folder.is_dir():
        raise VPRInputError(f"{folder}: not a folder; give a VPR-methods-evaluation log folder holding "
                            f"{DATABASE_FILE} and {QUERIES_FILE}")
    for name in (DATABASE_FILE, QUERIES_FILE):
        if not (folder / name).is_file():
            raise VPRInputError(
                f"{folder / name}: missing; a VPR-methods-evaluation run folder holds {DATABASE_FILE} and "
                f"{QUERIES_FILE}, written by its main.py with --save_descriptors"
            )
    return folder


def run_folders(dataset: RetrievalDataset) -> tuple[Path, Path]:
    """The database and queries folders VME was given for ``dataset``: ``database/`` and ``queries/`` at its root,
    else under ``images/test/`` (the layout's rule), the folder every one of their images lies below.

    Raises:
        VPRInputError: ``dataset`` is not a database/queries dataset (named, with what to do).
    """
    if not isinstance(dataset, RetrievalDataset) or dataset.layout is not Layout.DATABASE_QUERIES:
        what = (f"a {dataset.layout.value} layout" if isinstance(dataset, RetrievalDataset)
                else "aligned traversal folders")
        raise VPRInputError(
            f"{getattr(dataset, 'name', dataset)} is {what}, not {Layout.DATABASE_QUERIES.value}: a "
            "VPR-methods-evaluation run describes a database/ and a queries/ folder of @UTM@-named images; open "
            f"the folder VME ran on (--layout {Layout.DATABASE_QUERIES.value}), or give this dataset's descriptors "
            "as one file (.npz with names, .npy with a names file, hloc .h5)"
        )
    root = Path(dataset.root)
    first = dataset.database_paths[0].relative_to(root).parts
    base = root if first[0] == "database" else root / "images" / "test"
    return base / "database", base / "queries"


def paths_file(folder: Path) -> Path:
    """The file VME reads ``folder``'s image order from when it exists: ``<folder>_images_paths.txt``, beside it."""
    return Path(os.fspath(folder) + PATHS_SUFFIX)


def run_stamp(folder: Path, dataset: RetrievalDataset) -> str:
    """Changes when a file the run is read from may have changed: size and mtime of its two ``.npy`` files and of
    the dataset's ``_images_paths.txt`` files (or their absence); nothing is read but the files' status."""
    folder = Path(folder).expanduser()
    files = [folder / DATABASE_FILE, folder / QUERIES_FILE, *map(paths_file, run_folders(dataset))]
    parts = []
    for f in files:
        try:
            s = f.stat()
            parts.append(f"{f}:{s.st_size}:{s.st_mtime_ns}")
        except OSError:
            parts.append(f"{f}:absent")
    return hashlib.sha256("|".join(parts).encode()).hexdigest()


def vme_order(names: Sequence[str]) -> list[str]:
    """VME's order of a folder's images without an ``_images_paths.txt``: plain string order of the paths.

    Args:
        names: the images' paths relative to the folder, ``/``-separated.
    """
    return sorted(names)


def load_vme_run(folder: Path, dataset: RetrievalDataset, *, names_file: Path | None = None,
                 dtype: str = "float32") -> VMERunDescriptors:
    """``(n_images, D)`` L2-normalised descriptors of ``dataset`` from a VME run folder, database rows first.

    Args:
        folder: the run folder, holding ``database_descriptors.npy`` and ``queries_descriptors.npy``.
        dataset: the database/queries dataset VME ran on.
        names_file: refused: a run's rows follow VME's order (module docstring).
        dtype: ``"float32"`` (default) or ``"float16"``.

    Returns:
        :class:`VMERunDescriptors`; its ``descriptors`` are read-only, row ``i`` for
        ``dataset.image_paths[i]``.

    Raises:
        VPRInputError: one per fault, naming the file and what to do (module docstring).
    """
    folder = Path(folder).expanduser()
    dtype = check_dtype(dtype)
    if names_file is not None:
        raise VPRInputError(
            f"names file {names_file}: a VPR-methods-evaluation run folder's rows follow VME's order (sorted image "
            f"paths, or <folder>{PATHS_SUFFIX} beside the dataset's folders); drop the names file"
        )
    database_folder, queries_folder = run_folders(dataset)
    check_run_folder(folder)
    files = (folder / DATABASE_FILE, folder / QUERIES_FILE)
    before = [file_stamp(f) for f in files]
    image_names = relative_names(dataset.image_paths, dataset.root)
    sides = (
        _side(files[0], database_folder, dataset.database_paths, image_names[:dataset.n_database]),
        _side(files[1], queries_folder, dataset.query_paths, image_names[dataset.n_database:]),
    )
    db, q = sides
    if db.rows.shape[1] != q.rows.shape[1]:
        raise VPRInputError(
            f"{q.npy}: descriptors of length {q.rows.shape[1]:,}, but {db.npy.name}'s are of length "
            f"{db.rows.shape[1]:,}; both files of a run come from one model: write them again in one run"
        )
    read = (*files, *(s.paths_file for s in sides if s.paths_file is not None))
    digests = file_digests(read)
    key = content_key(read, KEY_DTYPE.format(dtype=dtype), image_names, digests=digests)
    if [file_stamp(f) for f in files] != before:
        raise VPRInputError(f"{folder}: a descriptor file changed while it was read; open the run again once VME "
                            "has finished writing it")
    descriptors, rescaled = unit_rows_joined([(s.npy, s.rows, s.order, s.names) for s in sides], dtype,
                                             source=folder)
    descriptors.setflags(write=False)
    notes = [_side_note(s) for s in sides]
    total = sum(rescaled)
    notes.append(
        "L2-normalised after the checks: "
        + (f"{total:,} of {dataset.n_images:,} rows were rescaled to unit length; the others already were"
           if total else f"every row was already unit length (within {UNIT_TOLERANCE:g}) and is kept as stored")
    )
    return VMERunDescriptors(
        descriptors=descriptors, name=folder.stem, key=key, source=DescriptorFormat.VME_RUN, path=folder,
        notes=tuple(notes), digests=digests, files=read,
    )


# --- one side of the run ------------------------------------------------------------------


def _side(npy: Path, folder: Path, image_paths: Sequence[Path], names: Sequence[str]) -> VMESide:
    """One ``.npy`` matched to one folder's images: its rows, and the row of each image (module docstring)."""
    read = read_npy_rows(npy, None)
    if read.names_file is not None:
        raise VPRInputError(
            f"{read.names_file}: a names file beside {npy.name} would reorder its rows, but a VME run's rows follow "
            f"VME's order; remove {read.names_file.name} from the run folder"
        )
    relative = _below(folder, image_paths)
    listed_file = paths_file(folder)
    if listed_file.is_file():
        listed = _listed(listed_file, relative, folder)
        how = f"{listed_file.name}"
    else:
        others = [n for n in relative if posixpath.splitext(n)[1].lower() not in VME_SUFFIXES]
        if others:
            raise VPRInputError(
                f"{npy}: {folder} holds {len(others):,} image{'s' * (len(others) != 1)} VME's glob does not read "
                f"({_listing(others)}; it "
                f"reads {', '.join(VME_SUFFIXES)}), so the run has no descriptor for them; convert them, or move "
                "them out of the folder"
            )
        listed_file, listed = None, vme_order(relative)
        how = f"VME's sorted glob of {folder.name}/"
    rows = read.rows
    if len(rows) != len(listed):
        held = f"{listed_file} lists" if listed_file is not None else f"{folder} holds"
        raise VPRInputError(
            f"{npy}: {len(rows):,} rows, but {held} {len(listed):,} images; VME writes one row per image of "
            f"{folder.name}/ ({how}): open the dataset this run was made for, or run VME again on this one"
        )
    row_of = {name: r for r, name in enumerate(listed)}
    order = np.fromiter((row_of[name] for name in relative), dtype=np.int64, count=len(relative))
    return VMESide(npy=npy, folder=folder, order=order, paths_file=listed_file, rows=rows, names=tuple(names))


def _below(folder: Path, image_paths: Sequence[Path]) -> list[str]:
    """Each image's path relative to ``folder``, ``/``-separated (a string prefix: fast at a million images)."""
    prefix = os.fspath(folder).rstrip(os.sep) + os.sep
    out = []
    for p in image_paths:
        text = os.fspath(p)
        if not text.startswith(prefix):
            raise VPRInputError(f"{p}: not below {folder}, the folder VME read; open the dataset at its root")
        out.append(text[len(prefix):].replace(os.sep, "/"))
    return out


def _listed(listed_file: Path, relative: Sequence[str], folder: Path) -> list[str]:
    """The images ``<folder>_images_paths.txt`` lists, in its order, each an image of the folder and listed once,
    every image of the folder listed (VME computed descriptors for the listed ones only)."""
    try:
        text = listed_file.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise VPRInputError(f"{listed_file}: cannot read it ({exc}); it must be UTF-8 text, one image path "
                            f"relative to {folder} per line") from None
    lines = text.splitlines()
    blank = [i for i, line in enumerate(lines, start=1) if not line.strip()]
    if blank:
        raise VPRInputError(f"{listed_file}: line {blank[0]} is blank; VME reads every line as an image path "
                            f"relative to {folder}: remove blank lines")
    listed = [posixpath.normpath(line.lstrip("/")) for line in lines]
    repeated = [n for n, c in Counter(listed).items() if c > 1]
    if repeated:
        raise VPRInputError(f"{listed_file}: {len(repeated):,} images listed more than once ({_listing(repeated)}); "
                            "list each image once")
    images = set(relative)
    strangers = [(i, n) for i, n in enumerate(listed, start=1) if n not in images]
    if strangers:
        line, name = strangers[0]
        raise VPRInputError(
            f"{listed_file}: line {line}: {name} is not an image of {folder} ({len(strangers):,} such lines: "
            f"{_listing([n for _, n in strangers])}); list paths relative to {folder}, or open the dataset the "
            "run was made for"
        )
    left_out = sorted(images - set(listed))
    if left_out:
        raise VPRInputError(
            f"{listed_file}: lists {len(listed):,} of the {len(images):,} images of {folder}, so VME computed no "
            f"descriptor for {len(left_out):,} ({_listing(left_out)}); list every image, or move the others out "
            "of the folder"
        )
    return listed


def _side_note(side: VMESide) -> str:
    how = (f"rows in the order of {side.paths_file.name}" if side.paths_file is not None
           else f"rows in VME's order (sorted paths below {side.folder.name}/)")
    moved = int((side.order != np.arange(len(side.order))).sum())
    return (f"{side.npy.name}: {side.rows.shape[0]:,} descriptors of length {side.rows.shape[1]:,}, stored as "
            f"{side.rows.dtype}, {how}; {moved:,} of them moved to the dataset's image order")


def _listing(items: Sequence[str]) -> str:
    shown = ", ".join(str(x) for x in items[:NAMED])
    more = len(items) - NAMED
    return f"{shown} and {more:,} more" if more > 0 else shown
