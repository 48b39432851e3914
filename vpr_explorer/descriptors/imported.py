"""Descriptors computed elsewhere (NetVLAD, CosPlace, MixVPR, SALAD, ...) read from a file.

"Bring your own descriptors": compute global descriptors on a GPU machine with any
model, copy one file here, and every table, threshold and view treats them like a
built-in descriptor named after the file (its stem: ``netvlad.h5`` -> ``netvlad``).

Three formats, chosen by the file's extension (:data:`FORMATS`):

* ``.npz``: arrays ``names`` (strings, each image's path relative to the dataset folder,
  e.g. ``day_left/Image000.jpg``) and ``descriptors`` ``(n, D)``, row ``i`` for
  ``names[i]``::

      np.savez("netvlad.npz", names=np.array(names), descriptors=vectors)

* ``.npy``: ``(n, D)``; without names, rows follow the dataset's image order
  (traversal-major: every frame of the first traversal, then the second, ...). With a
  names file (one relative path per line, row order) the rows are matched by name: the
  ``names_file`` argument, else ``<stem>.txt`` or ``<stem>_names.txt`` beside the
  ``.npy``.
* ``.h5`` / ``.hdf5``: hloc's global features (``hloc.extract_features`` with a global
  model, e.g. ``netvlad``, ``openibl``, ``cosplace``, ``eigenplaces``): one group per
  image name holding a dataset ``global_descriptor`` of shape ``(D,)``. A name with
  folders is nested groups: ``day_left/Image000.jpg`` is read from
  ``day_left/Image000.jpg/global_descriptor``. hloc stores float16 by default; that is
  read too.

Names are matched to the dataset's images by their path relative to the dataset folder
(POSIX separators; ``\\`` and a leading ``./`` or ``/`` are tolerated): the lines
``vpr-explorer list`` prints, and :func:`relative_names` returns. Two fallbacks,
each reported in :attr:`ImportedDescriptors.notes`: a name carrying extra leading folders
(relative to a parent folder, or absolute on the machine that wrote it) matches on its
longest trailing part that is an image's relative path; a name that still matches
nothing matches on its file name alone when exactly one image of the dataset has that
file name.

Everything is checked before any descriptor is used, each fault as one
:class:`~vpr_explorer.errors.VPRInputError` naming the file and the fix: an unknown
extension, an unreadable or truncated file, arrays of the wrong kind or shape,
descriptors of different lengths, a row count that does not fit, duplicate names,
images the file lacks and names that are not images of the dataset (the first few of
each, and how many), and rows that are NaN, infinite or zero (naming their images).
Only then are rows L2-normalised; rows already within ``UNIT_TOLERANCE`` of unit length
are kept as stored, so the project's own descriptors come back bit for bit.

:attr:`ImportedDescriptors.key` is a sha256 over the file's bytes (read in chunks; a
``.npy``'s names file too), the dtype and the dataset's image names, so caches keyed by
it never serve an edited file's old results; a file that changes while it is read is
refused.

:func:`write_descriptor_file` writes the same formats: how this project's descriptors
are exported for use elsewhere (e.g. hloc's ``pairs_from_retrieval`` reads the ``.h5``).
"""

from __future__ import annotations

import hashlib
import os
import tokenize
import zipfile
import zlib
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path, PurePosixPath

import numpy as np

from vpr_explorer import settings
from vpr_explorer.descriptors.cache import check_dtype
from vpr_explorer.descriptors.extract import MIN_NORM
from vpr_explorer.errors import VPRInputError

HLOC_KEY = "global_descriptor"
"""The dataset hloc writes in each image's group for a global descriptor."""
NPZ_NAMES = "names"
NPZ_DESCRIPTORS = "descriptors"
UNIT_TOLERANCE = 1e-6
"""Rows whose norm is within this of 1 are kept as stored (the cache's rule, :func:`renormalise_in_place`)."""
NAMED_IN_ERRORS = 5
# Rows are checked and normalised this many bytes of float64 at a time, so the only
# large allocation is the result (~8 MiB temporaries; 110,000 x 1,280 float32 is 563 MB).
CHUNK_BYTES = 1 << 23
KEY_VERSION = "imported-1"
NPY_MAGIC = b"\x93NUMPY"
ZIP_MAGIC = b"PK\x03\x04"


class DescriptorFormat(StrEnum):
    """The kind of descriptor file, from its extension."""

    NPZ = "npz"
    NPY = "npy"
    HLOC = "hloc-h5"


FORMATS: dict[str, DescriptorFormat] = {
    ".npz": DescriptorFormat.NPZ,
    ".npy": DescriptorFormat.NPY,
    ".h5": DescriptorFormat.HLOC,
    ".hdf5": DescriptorFormat.HLOC,
}
"""Extension (lower case) -> format."""


@dataclass(frozen=True, eq=False)
class ImportedDescriptors:
    """Descriptors read from a file, in the dataset's image order.

    Attributes:
        descriptors: ``(n_images, D)`` float32 (or float16), L2-normalised rows, read-only;
            row ``i`` belongs to ``image_paths[i]``.
        name: the descriptor's name in every table: the file's stem.
        key: sha256 hex over everything the array depends on: the file's bytes (and the
            names file's), the dtype and the dataset's image names in order. Equal keys
            mean equal arrays, and an edited file always gets a new key, so callers key
            caches by it.
        source: the file's format.
        path: the descriptor file.
        names_file: the names file a ``.npy``'s rows were matched by, else ``None``.
        notes: what the reader decided on the way (format details, fallback name
            matches, normalisation), one sentence each, for the UI and the CLI.
    """

    descriptors: np.ndarray
    name: str
    key: str
    source: DescriptorFormat
    path: Path
    names_file: Path | None = None
    notes: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        self.descriptors.setflags(write=False)

    @property
    def n_images(self) -> int:
        return self.descriptors.shape[0]

    @property
    def dim(self) -> int:
        return self.descriptors.shape[1]


@dataclass(frozen=True, eq=False)
class _Read:
    """What a format's reader found: rows as stored, and their names when the file has them."""

    rows: np.ndarray  # (n_rows, D), any real dtype; a read-only memmap for .npy
    names: tuple[str, ...] | None
    names_file: Path | None = None
    notes: tuple[str, ...] = ()


# --- public helpers ---------------------------------------------------------------------


def descriptor_format(path: Path) -> DescriptorFormat:
    """The format of a descriptor file from its extension.

    Raises:
        VPRInputError: naming the file and the extensions that are read.
    """
    path = Path(path)
    fmt = FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise VPRInputError(
            f"{path}: unknown descriptor file extension {path.suffix or '(none)'!r}: "
            f"give a {', '.join(FORMATS)} file (.npz with 'names' and 'descriptors', a .npy in the "
            "dataset's image order, or hloc's global-feature .h5)"
        )
    return fmt


def relative_names(image_paths: Sequence[Path], root: Path) -> tuple[str, ...]:
    """Each image's name in a descriptor file: its path relative to ``root``, with ``/`` separators.

    An image outside ``root`` (a manifest may list one) is named by its whole path. These
    are the lines ``vpr-explorer list`` prints.

    Raises:
        VPRInputError: an image listed twice.
    """
    if isinstance(image_paths, (str, Path)):
        raise VPRInputError(f"image_paths={str(image_paths)!r}: give the dataset's list of image files, not one path")
    root = Path(root)
    names = []
    for p in map(Path, image_paths):
        try:
            names.append(p.relative_to(root).as_posix())
        except ValueError:
            names.append(p.as_posix())
    repeated = [n for n, c in Counter(names).items() if c > 1]
    if repeated:
        raise VPRInputError(
            f"image_paths: {_listing(repeated)} listed more than once; a descriptor file has one row per image, "
            "so give each image once"
        )
    return tuple(names)


def load_descriptor_file(
    path: Path,
    image_paths: Sequence[Path],
    root: Path,
    *,
    names_file: Path | None = None,
    dtype: str = "float32",
) -> ImportedDescriptors:
    """``(n_images, D)`` L2-normalised descriptors from a file, in the order of ``image_paths``.

    Args:
        path: a ``.npz``, ``.npy`` or hloc ``.h5``/``.hdf5`` file (see the module docstring).
        image_paths: the dataset's images in image order (``Dataset.image_paths``).
        root: the dataset folder; names in the file are paths relative to it.
        names_file: for a ``.npy`` only: one name per line, in row order. Default:
            ``<stem>.txt`` or ``<stem>_names.txt`` beside the file when there is one; with
            none, rows are taken in the dataset's image order.
        dtype: ``"float32"`` (default) or ``"float16"``.

    Returns:
        :class:`ImportedDescriptors`; its ``descriptors`` are read-only.

    Raises:
        VPRInputError: one per fault, naming the file and what to do (module docstring).
    """
    path = Path(path).expanduser()
    fmt = descriptor_format(path)
    dtype = check_dtype(dtype)
    image_names = relative_names(image_paths, root)
    root = Path(root)
    if not image_names:
        raise VPRInputError("image_paths: no images given; choose a dataset that holds images")
    if not path.is_file():
        what = "is a folder, not a descriptor file" if path.is_dir() else "does not exist"
        raise VPRInputError(f"{path}: {what}; give the descriptor file ({', '.join(FORMATS)})")
    if names_file is not None and fmt is not DescriptorFormat.NPY:
        raise VPRInputError(
            f"names_file={str(names_file)!r}: only a .npy takes a names file; {path.name} carries its own names"
        )

    before = _stamp(path)
    read = _READERS[fmt](path, None if names_file is None else Path(names_file).expanduser())
    files = (path,) if read.names_file is None else (path, read.names_file)
    key = _content_key(files, dtype, image_names)
    if _stamp(path) != before:
        raise VPRInputError(f"{path}: the file changed while it was read; open it again once it is fully written")

    notes = list(read.notes)
    if read.names is None:
        if len(read.rows) != len(image_names):
            raise VPRInputError(
                f"{path}: {len(read.rows):,} rows for the dataset's {len(image_names):,} images; a .npy without "
                "names needs one row per image in the dataset's image order (traversal by traversal, frames in "
                f"order), or put a names file beside it ({path.stem}.txt, one path relative to {root} per line)"
            )
        order = np.arange(len(image_names))
        notes.append(f"no names: rows taken in the dataset's image order ({image_names[0]} first)")
    else:
        order, match_notes = _match_names(read.names, image_names, path, root)
        notes.extend(match_notes)

    descriptors, rescaled = _unit_rows(read.rows, order, image_names, path, dtype)
    notes.append(
        "L2-normalised after the checks: "
        + (f"{rescaled:,} of {len(order):,} rows were rescaled to unit length; the others already were"
           if rescaled else f"every row was already unit length (within {UNIT_TOLERANCE:g}) and is kept as stored")
    )
    return ImportedDescriptors(
        descriptors=descriptors, name=path.stem, key=key, source=fmt, path=path,
        names_file=read.names_file, notes=tuple(notes),
    )


def write_descriptor_file(
    path: Path,
    descriptors: np.ndarray,
    image_paths: Sequence[Path],
    root: Path,
    *,
    with_names: bool = True,
) -> tuple[Path, ...]:
    """Write ``(n_images, D)`` descriptors in one of the formats :func:`load_descriptor_file` reads.

    How this project's descriptors are exported for use elsewhere: the ``.h5`` is hloc's
    global-feature layout (``pairs_from_retrieval`` reads it), the ``.npz`` and ``.npy``
    load with plain NumPy. Names are the images' paths relative to ``root``. Each file is
    written under a temporary name and renamed into place, so a reader never sees half
    of it. Rows are written as given (dtype included).

    Args:
        path: the file to write; its extension picks the format.
        descriptors: ``(n_images, D)``, row ``i`` for ``image_paths[i]``.
        with_names: for a ``.npy``: also write ``<stem>.txt`` beside it, one name per line
            in row order (default; the two files are replaced one after the other, not
            together). Without it, the rows must be in the dataset's image order.

    Returns:
        The files written (the ``.npy`` and its names file, or the one file).

    Raises:
        VPRInputError: an unknown extension, a shape or dtype that does not fit, another names
            file beside a ``.npy`` (the loader would read it), or a file that cannot be written
            (named).
    """
    path = Path(path).expanduser()
    fmt = descriptor_format(path)
    names = relative_names(image_paths, root)
    rows = np.asarray(descriptors)
    if rows.ndim != 2 or rows.shape[0] != len(names) or rows.shape[1] == 0:
        raise VPRInputError(
            f"descriptors: shape {rows.shape} for {len(names):,} images; give (n_images, D), one row per image"
        )
    if rows.dtype.kind not in "fiu":
        raise VPRInputError(f"descriptors: {rows.dtype} values; descriptors are real numbers")
    if fmt is DescriptorFormat.NPZ:
        arrays = {NPZ_NAMES: np.array(names, dtype=str), NPZ_DESCRIPTORS: rows}
        _atomic(path, lambda tmp: _with_open(tmp, lambda fh: np.savez(fh, **arrays)))
        return (path,)
    if fmt is DescriptorFormat.NPY:
        names_path = path.with_suffix(".txt")
        # The loader reads whichever names file sits beside the .npy: one left from before would reorder the rows.
        stale = [p for p in (names_path, path.with_name(f"{path.stem}_names.txt"))
                 if p.is_file() and not (with_names and p == names_path)]
        if stale:
            raise VPRInputError(
                f"{stale[0]}: a names file is already beside {path.name}, and would be read with it; remove it first"
            )
        _atomic(path, lambda tmp: _with_open(tmp, lambda fh: np.save(fh, rows, allow_pickle=False)))
        if not with_names:
            return (path,)
        _atomic(names_path, lambda tmp: tmp.write_text("\n".join(names) + "\n", encoding="utf-8"))
        return (path, names_path)

    def write_hloc(tmp: Path) -> None:
        import h5py

        # create_group makes the intermediate groups of a name with folders, as hloc's writer does.
        with h5py.File(tmp, "w") as fd:
            for name, row in zip(names, rows):
                fd.create_group(name).create_dataset(HLOC_KEY, data=row)

    _atomic(path, write_hloc)
    return (path,)


# --- readers, one per format ------------------------------------------------------------


def _read_npz(path: Path, names_file: Path | None) -> _Read:
    # Checked first: np.load takes a file without the zip signature for a pickle.
    if not _starts(path).startswith(ZIP_MAGIC) or not zipfile.is_zipfile(path):
        raise _unreadable(path, "not a zip archive: truncated, or not written by np.savez")
    try:
        archive = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
        raise _unreadable(path, exc) from None
    with archive:
        try:
            keys = list(archive.files)
            if NPZ_NAMES not in keys or NPZ_DESCRIPTORS not in keys:
                names = rows = None
            else:
                names = archive[NPZ_NAMES]
                rows = archive[NPZ_DESCRIPTORS]
        except ValueError as exc:
            if "allow_pickle" in str(exc):
                raise VPRInputError(
                    f"{path}: an array holds Python objects, which are not read (they could run code); "
                    f"save names as strings: np.savez(path, {NPZ_NAMES}=np.array(names, dtype=str), "
                    f"{NPZ_DESCRIPTORS}=vectors)"
                ) from None
            raise _unreadable(path, exc) from None
        except (OSError, EOFError, SyntaxError, tokenize.TokenError, zipfile.BadZipFile, zlib.error) as exc:
            # SyntaxError, TokenError: numpy parsing a damaged .npy header inside the archive
            raise _unreadable(path, exc) from None
    if names is None:
        raise VPRInputError(
            f"{path}: the .npz holds {', '.join(map(repr, keys)) or 'no arrays'}, not {NPZ_NAMES!r} and "
            f"{NPZ_DESCRIPTORS!r}; save it as np.savez(path, {NPZ_NAMES}=np.array(names, dtype=str), "
            f"{NPZ_DESCRIPTORS}=vectors)"
        )
    _check_matrix(rows, path, f"{NPZ_DESCRIPTORS!r}")
    if names.ndim != 1 or names.dtype.kind not in "US":
        raise VPRInputError(
            f"{path}: {NPZ_NAMES!r} is {names.dtype} of shape {names.shape}; it must be a list of strings, "
            f"one image path (relative to the dataset folder) per row of {NPZ_DESCRIPTORS!r}"
        )
    if len(names) != len(rows):
        raise VPRInputError(
            f"{path}: {len(names):,} names but {len(rows):,} rows in {NPZ_DESCRIPTORS!r}; "
            "give one name per row, in row order"
        )
    decoded = tuple(_decode(n, path) for n in names.tolist())
    return _Read(rows=rows, names=decoded, notes=(f"{path.name}: {_shape_note(rows)} with names",))


def _read_npy(path: Path, names_file: Path | None) -> _Read:
    magic = _starts(path)
    if magic.startswith(ZIP_MAGIC):
        raise VPRInputError(f"{path}: this is an .npz archive, not a single array: rename it {path.stem}.npz")
    if magic != NPY_MAGIC:
        raise _unreadable(path, "it does not start with NumPy's .npy header")
    try:
        # Memory-mapped: rows are copied once, straight into the result in the dataset's order.
        rows = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError, SyntaxError, tokenize.TokenError) as exc:
        raise _unreadable(path, exc) from None
    _check_matrix(rows, path, "the array")
    names_file = _find_names_file(path, names_file)
    note = f"{path.name}: {_shape_note(rows)}"
    if names_file is None:
        return _Read(rows=rows, names=None, notes=(note,))
    try:
        text = names_file.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise VPRInputError(
            f"{names_file}: cannot read the names file ({exc}); it must be UTF-8 text, one name per line"
        ) from None
    names = tuple(line.strip() for line in text.splitlines() if line.strip())
    if len(names) != len(rows):
        raise VPRInputError(
            f"{path}: {len(rows):,} rows but {names_file.name} lists {len(names):,} names; give one name per "
            "row, in row order (or remove the names file to take rows in the dataset's image order)"
        )
    return _Read(rows=rows, names=names, names_file=names_file,
                 notes=(f"{note}, rows matched by the names in {names_file.name}",))


def _find_names_file(path: Path, given: Path | None) -> Path | None:
    """The names file of a ``.npy``: ``given``, else the one of ``<stem>.txt``/``<stem>_names.txt`` that exists."""
    if given is not None:
        if not given.is_file():
            raise VPRInputError(f"{given}: the names file does not exist; give a text file with one name per line")
        return given
    found = [p for p in (path.with_suffix(".txt"), path.with_name(f"{path.stem}_names.txt")) if p.is_file()]
    if len(found) > 1:
        raise VPRInputError(
            f"{path}: two names files beside it ({found[0].name} and {found[1].name}); remove one or name the "
            "right one (names_file)"
        )
    return found[0] if found else None


def _read_hloc(path: Path, names_file: Path | None) -> _Read:
    import h5py

    found: list[str] = []
    vectors: list[np.ndarray] = []
    try:
        with h5py.File(path, "r") as fd:
            fd.visit(lambda name: found.append(name) if name.rsplit("/", 1)[-1] == HLOC_KEY else None)
            # Low-level reads: about a third of the time of fd[name][()] (40,000 images: 4.5 s against 15 s).
            for name in found:
                dataset = h5py.h5d.open(fd.id, name.encode())
                if dataset.dtype.kind not in "fiu":
                    raise VPRInputError(
                        f"{path}: {name} holds {dataset.dtype} values; descriptors must be real numbers"
                    )
                vector = np.empty(dataset.shape, dtype=dataset.dtype)
                dataset.read(h5py.h5s.ALL, h5py.h5s.ALL, vector)
                vectors.append(vector)
            others = sorted(_dataset_leaves(fd, h5py)) if not found else []
    except VPRInputError:
        raise
    except (OSError, RuntimeError, KeyError, ValueError, TypeError) as exc:
        raise _unreadable(path, exc) from None
    if not found:
        held = f" (it holds {', '.join(map(repr, others[:8]))})" if others else " (it holds no datasets)"
        raise VPRInputError(
            f"{path}: no {HLOC_KEY!r} dataset in the HDF5 file{held}; expected hloc's global features (one group "
            f"per image name holding {HLOC_KEY!r}, from hloc.extract_features with a global model such as "
            "netvlad); local features (keypoints, descriptors) are not global descriptors"
        )
    # hloc's name of an image is its group's path (list_h5_names: obj.parent.name.strip("/")).
    names = tuple(n.rsplit("/", 1)[0] if "/" in n else "" for n in found)
    bad_shape = [(n, v.shape) for n, v in zip(names, vectors) if not (v.ndim == 1 or (v.ndim == 2 and v.shape[0] == 1))]
    if bad_shape:
        name, shape = bad_shape[0]
        raise VPRInputError(
            f"{path}: {len(bad_shape):,} {HLOC_KEY!r} datasets are not vectors, e.g. {name!r} of shape {shape}; "
            "each image needs one (D,) global descriptor"
        )
    vectors = [v.reshape(-1) for v in vectors]
    lengths = Counter(len(v) for v in vectors)
    if len(lengths) > 1:
        common = lengths.most_common(1)[0][0]
        odd = [n for n, v in zip(names, vectors) if len(v) != common]
        others_listing = ", ".join(f"{d:,} for {c:,}" for d, c in lengths.most_common()[1:])
        raise VPRInputError(
            f"{path}: descriptors of different lengths: {common:,} for {lengths[common]:,} images, {others_listing} "
            f"({_listing(odd)}); every image needs a descriptor of the same length: compute them with one model"
        )
    rows = np.stack(vectors)
    _check_matrix(rows, path, f"the {HLOC_KEY!r} datasets")
    return _Read(rows=rows, names=names, notes=(f"{path.name}: hloc global features, {_shape_note(rows)}",))


def _dataset_leaves(fd, h5py) -> set[str]:
    """The last part of the name of every dataset in an HDF5 file (what it holds instead)."""
    leaves: set[str] = set()
    fd.visititems(lambda name, obj: leaves.add(name.rsplit("/", 1)[-1]) if isinstance(obj, h5py.Dataset) else None)
    return leaves


_READERS = {
    DescriptorFormat.NPZ: _read_npz,
    DescriptorFormat.NPY: _read_npy,
    DescriptorFormat.HLOC: _read_hloc,
}


# --- checks -----------------------------------------------------------------------------


def _check_matrix(rows: np.ndarray, path: Path, what: str) -> None:
    if rows.dtype.kind not in "fiu":
        raise VPRInputError(f"{path}: {what} holds {rows.dtype} values; descriptors must be real numbers")
    if rows.ndim != 2 or rows.shape[0] == 0 or rows.shape[1] == 0:
        raise VPRInputError(
            f"{path}: {what} has shape {rows.shape}; expected (n_images, D): one descriptor of length D >= 1 "
            "per image"
        )


def _clean(name: str) -> str:
    """A file's name for an image, with ``/`` separators and no leading ``./`` or ``/``."""
    parts = PurePosixPath(name.strip().replace("\\", "/")).parts
    return "/".join(p for p in parts if p != "/")


def _match_names(
    names: Sequence[str], image_names: Sequence[str], path: Path, root: Path
) -> tuple[np.ndarray, list[str]]:
    """``(n_images,)`` the file row of each image, matching names by relative path (then the fallbacks).

    Raises:
        VPRInputError: duplicate names, images without a row, names that are no image.
    """
    clean = [_clean(n) for n in names]
    repeated = [n for n, c in Counter(clean).items() if c > 1]
    if repeated:
        raise VPRInputError(
            f"{path}: {len(repeated):,} names appear more than once ({_listing(repeated)}); give each image "
            "one row"
        )
    index = {_clean(n): i for i, n in enumerate(image_names)}  # cleaned alike: an absolute name loses its '/'
    row_of = np.full(len(image_names), -1, dtype=np.int64)
    claimed_by: dict[int, str] = {}
    unmatched: list[int] = []
    for r, name in enumerate(clean):
        i = index.get(name)
        if i is None:
            unmatched.append(r)
        else:
            row_of[i], claimed_by[i] = r, names[r]
    notes = []

    def claim(r: int, i: int) -> None:
        if i in claimed_by:
            raise VPRInputError(
                f"{path}: names {claimed_by[i]!r} and {names[r]!r} both match the image {image_names[i]}; give "
                f"each image one row, named by its path relative to {root}"
            )
        row_of[i], claimed_by[i] = r, names[r]

    # Names written relative to a parent folder (or absolute elsewhere): the longest trailing part that is an image.
    by_suffix = []
    for r in unmatched:
        parts = clean[r].split("/")
        i = next((index[s] for s in ("/".join(parts[k:]) for k in range(1, len(parts))) if s in index), None)
        if i is not None:
            claim(r, i)
            by_suffix.append(r)
    if by_suffix:
        r = by_suffix[0]
        notes.append(
            f"{len(by_suffix):,} names matched by dropping leading folders (e.g. {names[r]!r} -> "
            f"{image_names[int(np.flatnonzero(row_of == r)[0])]!r})"
        )
    done = set(by_suffix)
    unmatched = [r for r in unmatched if r not in done]

    # A bare file name, when exactly one image of the dataset (and one leftover name) has it
    # and no other name has matched that image.
    if unmatched:
        image_files = Counter(n.rsplit("/", 1)[-1] for n in image_names)
        first_with = {}
        for i, n in enumerate(image_names):
            first_with.setdefault(n.rsplit("/", 1)[-1], i)
        leftover_files = Counter(clean[r].rsplit("/", 1)[-1] for r in unmatched)
        by_file = []
        for r in unmatched:
            file = clean[r].rsplit("/", 1)[-1]
            if image_files[file] == 1 and leftover_files[file] == 1 and first_with[file] not in claimed_by:
                claim(r, first_with[file])
                by_file.append(r)
        if by_file:
            r = by_file[0]
            notes.append(
                f"{len(by_file):,} names matched on the file name alone, each unique in the dataset (e.g. "
                f"{names[r]!r} -> {image_names[int(np.flatnonzero(row_of == r)[0])]!r})"
            )
            done = set(by_file)
            unmatched = [r for r in unmatched if r not in done]

    missing = [image_names[i] for i in np.flatnonzero(row_of < 0)]
    extra = [names[r] for r in unmatched]
    example = f"names are matched as paths relative to {root}, like {image_names[0]!r}"
    if missing and extra:
        raise VPRInputError(
            f"{path}: {len(missing):,} of the dataset's {len(image_names):,} images have no descriptor in the file "
            f"({_listing(missing)}) and {len(extra):,} names in the file are not images of the dataset "
            f"({_listing(extra)}); {example}: write the file with such names, or open the dataset it was made for"
        )
    if missing:
        raise VPRInputError(
            f"{path}: {len(missing):,} of the dataset's {len(image_names):,} images have no descriptor in the file: "
            f"{_listing(missing)}; compute descriptors for every image of the dataset ({example}), or open the "
            "dataset the file was made for"
        )
    if extra:
        raise VPRInputError(
            f"{path}: {len(extra):,} names in the file are not images of the dataset: {_listing(extra)}; {example}: "
            "remove those rows, or open the dataset they belong to"
        )
    return row_of, notes


def _unit_rows(
    rows: np.ndarray, order: np.ndarray, image_names: Sequence[str], path: Path, dtype: str
) -> tuple[np.ndarray, int]:
    """``rows[order]`` as unit rows in ``dtype``, and how many were rescaled.

    Norms are float64 (float32 squares overflow above ~1e19). Rows within
    ``UNIT_TOLERANCE`` of unit length are cast, not divided, so float32 unit rows come
    back bit-exact; the others are divided in float64, as extraction does.

    Raises:
        VPRInputError: naming the images whose row is NaN/infinite or zero.
    """
    n, d = len(order), rows.shape[1]
    out = np.empty((n, d), dtype=dtype)
    step = max(1, CHUNK_BYTES // (8 * d))
    not_finite: list[int] = []
    zero: list[int] = []
    rescaled = 0
    for lo in range(0, n, step):
        block = np.asarray(rows[order[lo : lo + step]])
        wide = block.astype(np.float64)
        finite = np.isfinite(wide).all(axis=1)
        with np.errstate(over="ignore", invalid="ignore"):
            norms = np.linalg.norm(np.where(finite[:, None], wide, 0.0), axis=1)
        small = finite & ~(norms >= MIN_NORM)
        if not finite.all() or small.any():
            not_finite.extend((lo + np.flatnonzero(~finite)).tolist())
            zero.extend((lo + np.flatnonzero(small)).tolist())
            continue
        if not_finite or zero:
            continue  # an error is coming: only collect the culprits
        off = np.flatnonzero(np.abs(norms - 1.0) > UNIT_TOLERANCE)
        out[lo : lo + len(block)] = block
        if len(off):
            out[lo + off] = wide[off] / norms[off, None]
            rescaled += len(off)
    if not_finite or zero:
        faults = []
        if not_finite:
            faults.append(f"{len(not_finite):,} are NaN or infinite ({_listing([image_names[i] for i in not_finite])})")
        if zero:
            faults.append(f"{len(zero):,} are all zero ({_listing([image_names[i] for i in zero])})")
        raise VPRInputError(
            f"{path}: of the descriptors, {' and '.join(faults)}; such a row has no direction to compare: "
            "recompute those images' descriptors, or remove the images from the dataset"
        )
    return out, rescaled


# --- small helpers ----------------------------------------------------------------------


def _listing(items: Sequence[str]) -> str:
    shown = ", ".join(str(x) for x in items[:NAMED_IN_ERRORS])
    more = len(items) - NAMED_IN_ERRORS
    return f"{shown} and {more:,} more" if more > 0 else shown


def _starts(path: Path) -> bytes:
    """The file's first bytes, to tell formats apart before a parser guesses."""
    try:
        with open(path, "rb") as fh:
            return fh.read(len(NPY_MAGIC))
    except OSError as exc:
        raise VPRInputError(f"{path}: cannot read the file ({exc}); check that it is readable") from None


def _shape_note(rows: np.ndarray) -> str:
    return f"{rows.shape[0]:,} descriptors of length {rows.shape[1]:,}, stored as {rows.dtype}"


def _decode(name: str | bytes, path: Path) -> str:
    if isinstance(name, str):
        return name
    try:
        return name.decode("utf-8")
    except UnicodeDecodeError:
        raise VPRInputError(f"{path}: the name {name!r} is not UTF-8; write names as text") from None


def _unreadable(path: Path, why: object) -> VPRInputError:
    return VPRInputError(
        f"{path}: cannot read it as a {path.suffix} descriptor file ({why}); the file is truncated, damaged or "
        "not of that format: copy or write it again"
    )


def _stamp(path: Path) -> tuple[int, int]:
    try:
        st = path.stat()
    except OSError as exc:
        raise VPRInputError(f"{path}: cannot read the file ({exc}); check that it exists and is readable") from None
    return st.st_size, st.st_mtime_ns


def _content_key(files: Sequence[Path], dtype: str, image_names: Sequence[str]) -> str:
    """sha256 over the files' bytes (read in chunks), the dtype and the image order."""
    digest = hashlib.sha256(KEY_VERSION.encode())
    for f in files:
        try:
            with open(f, "rb") as fh:
                file_hash = hashlib.file_digest(fh, "sha256").hexdigest()
        except OSError as exc:
            raise VPRInputError(f"{f}: cannot read the file ({exc}); check that it exists and is readable") from None
        digest.update(f"|{f.suffix}:{file_hash}".encode())
    digest.update(f"|{dtype}|".encode())
    digest.update(hashlib.sha256("\n".join(image_names).encode()).digest())
    return digest.hexdigest()


def _with_open(path: Path, write) -> None:
    with open(path, "wb") as fh:
        write(fh)


def _atomic(path: Path, write) -> None:
    """Call ``write(tmp)`` for a temporary file beside ``path``, then rename it into place."""
    tmp = path.with_name(settings.temporary_name(path.name))
    try:
        write(tmp)
        os.replace(tmp, path)
    except OSError as exc:
        raise VPRInputError(f"{path}: cannot write the file ({exc}); check the folder exists and is writable") from None
    finally:
        tmp.unlink(missing_ok=True)
