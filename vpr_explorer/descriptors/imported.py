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
extension, an unreadable or truncated file, a shape claimed by a ``.npy`` header, a
``.npz`` entry's header or an HDF5 dataset that the file does not hold or that exceeds
this machine's memory (checked from the headers and the archive's or HDF5's own record
of what is stored, before anything is allocated), HDF5 values kept in other files,
arrays of the wrong kind or shape, descriptors of different lengths, a row count that
does not fit, duplicate names, images the file lacks and names that are not images of
the dataset (the first few of each, and how many), and rows that are NaN, infinite,
zero or of a norm below ``MIN_NORM`` (naming their images). Only then are rows
L2-normalised; rows already within ``UNIT_TOLERANCE`` of unit length are kept as
stored, so the project's own descriptors come back bit for bit, and a finite row too
large to square in float64 (entries near 1e300) is scaled by its largest entry first.

:attr:`ImportedDescriptors.key` is a sha256 over the file's bytes (read in chunks; a
``.npy``'s names file too), the dtype and the dataset's image names, so caches keyed by
it never serve an edited file's old results; a file that changes while it is read is
refused.

:func:`write_descriptor_file` writes the same formats: how this project's descriptors
are exported for use elsewhere (e.g. hloc's ``pairs_from_retrieval`` reads the ``.h5``).
"""

from __future__ import annotations

import functools
import hashlib
import math
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
    """The kind of descriptor file, from its extension (a folder: a VPR-methods-evaluation run, ``vme_run``)."""

    NPZ = "npz"
    NPY = "npy"
    HLOC = "hloc-h5"
    VME_RUN = "vme-run"


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
        digests: sha256 hex of the file's bytes, then of the names file's when there is one.
    """

    descriptors: np.ndarray
    name: str
    key: str
    source: DescriptorFormat
    path: Path
    names_file: Path | None = None
    notes: tuple[str, ...] = field(default=())
    digests: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        self.descriptors.setflags(write=False)

    def settings(self) -> dict[str, str]:
        """What an evaluation's settings record of the file: its absolute path and sha256, and its names file's.

        Flat keys (``descriptors_file``, ``descriptors_sha256``, then ``names_file`` and
        ``names_sha256``), so that a run on a file whose stem is a built-in extractor's name
        (``pixels.npz``) is never mistaken for that extractor's run.
        """
        out = {"descriptors_file": os.path.abspath(self.path)}
        if self.digests:
            out["descriptors_sha256"] = self.digests[0]
        if self.names_file is not None:
            out["names_file"] = os.path.abspath(self.names_file)
            if len(self.digests) > 1:
                out["names_sha256"] = self.digests[1]
        return out

    @property
    def n_images(self) -> int:
        return self.descriptors.shape[0]

    @property
    def dim(self) -> int:
        return self.descriptors.shape[1]


@dataclass(frozen=True, eq=False)
class ReadRows:
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
        raise VPRInputError(f"{path}: {what}; give the descriptor file ({', '.join(FORMATS)}), or open a "
                            "VPR-methods-evaluation run folder with its dataset (pipeline.imported_descriptors)")
    if names_file is not None and fmt is not DescriptorFormat.NPY:
        raise VPRInputError(
            f"names_file={str(names_file)!r}: only a .npy takes a names file; {path.name} carries its own names"
        )

    before = file_stamp(path)
    read = _READERS[fmt](path, None if names_file is None else Path(names_file).expanduser())
    files = (path,) if read.names_file is None else (path, read.names_file)
    digests = file_digests(files)
    key = content_key(files, dtype, image_names, digests=digests)
    if file_stamp(path) != before:
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

    needed = _nbytes((len(order), read.rows.shape[1]), np.dtype(dtype))
    _check_memory(path, f"its {len(order):,} descriptors of length {read.rows.shape[1]:,} take {_size_text(needed)} "
                        f"as {dtype}", needed, "read them as float16 (dtype), or on a machine with more memory")
    descriptors, rescaled = _unit_rows(read.rows, order, image_names, path, dtype)
    notes.append(
        "L2-normalised after the checks: "
        + (f"{rescaled:,} of {len(order):,} rows were rescaled to unit length; the others already were"
           if rescaled else f"every row was already unit length (within {UNIT_TOLERANCE:g}) and is kept as stored")
    )
    return ImportedDescriptors(
        descriptors=descriptors, name=path.stem, key=key, source=fmt, path=path,
        names_file=read.names_file, notes=tuple(notes), digests=digests,
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


def _read_npz(path: Path, names_file: Path | None) -> ReadRows:
    # Checked first: np.load takes a file without the zip signature for a pickle.
    if not _starts(path).startswith(ZIP_MAGIC) or not zipfile.is_zipfile(path):
        raise _unreadable(path, "not a zip archive: truncated, or not written by np.savez")
    _check_npz_claims(path)
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
    return ReadRows(rows=rows, names=decoded, notes=(f"{path.name}: {_shape_note(rows)} with names",))


def read_npy_rows(path: Path, names_file: Path | None) -> ReadRows:
    """The rows of a ``.npy`` descriptor file, memory-mapped as stored, and their names when a names file is found.

    Args:
        path: the ``.npy`` file.
        names_file: a text file of one image name per row; None: the file beside ``path``
            when there is one (:func:`_find_names_file`), else rows in the dataset's order.

    Returns:
        ``rows``: the ``(n_rows, D)`` read-only memmap in the stored dtype; ``names``: one
        per row, or None.

    Raises:
        VPRInputError: not a ``.npy`` file, a header that claims more than the file holds,
            not a 2-D real matrix, or a names file that cannot be read or does not list one
            name per row.
    """
    magic = _starts(path)
    if magic.startswith(ZIP_MAGIC):
        raise VPRInputError(f"{path}: this is an .npz archive, not a single array: rename it {path.stem}.npz")
    if magic != NPY_MAGIC:
        raise _unreadable(path, "it does not start with NumPy's .npy header")
    npy_header(path)  # the header's claim against the file's size, before anything is mapped
    try:
        # Memory-mapped: rows are copied once, straight into the result in the dataset's order.
        rows = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError, SyntaxError, tokenize.TokenError, OverflowError) as exc:
        raise _unreadable(path, exc) from None
    _check_matrix(rows, path, "the array")
    names_file = _find_names_file(path, names_file)
    note = f"{path.name}: {_shape_note(rows)}"
    if names_file is None:
        return ReadRows(rows=rows, names=None, notes=(note,))
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
    return ReadRows(rows=rows, names=names, names_file=names_file,
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


def _read_hloc(path: Path, names_file: Path | None) -> ReadRows:
    import h5py

    found: list[str] = []
    vectors: list[np.ndarray] = []
    file_size = file_stamp(path)[0]
    claimed = 0
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
                claimed += _hloc_claim(path, name, dataset, file_size, h5py)
                _check_memory(path, f"its {HLOC_KEY!r} datasets claim {_size_text(claimed)} up to {name}", claimed,
                              "the file is damaged or not one dataset's global descriptors: write it again")
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
    return ReadRows(rows=rows, names=names, notes=(f"{path.name}: hloc global features, {_shape_note(rows)}",))


def _hloc_claim(path: Path, name: str, dataset, file_size: int, h5py) -> int:
    """The bytes an HDF5 dataset claims, refused at once when its storage says the file does not hold them.

    A contiguous dataset must have all of its bytes stored in the file; a chunked one
    (compressed or not) must have every chunk written, or HDF5 would make up fill values
    for the rest. Values kept in other files (external or virtual datasets) are not read.
    """
    shape = dataset.shape or ()
    nbytes = _nbytes(shape, dataset.dtype)
    offset = dataset.get_offset()  # an address in this file only for contiguous values stored in it (hloc's)
    if offset is not None and dataset.get_storage_size() == nbytes and offset + nbytes <= file_size:
        return nbytes
    dcpl = dataset.get_create_plist()
    layout = dcpl.get_layout()
    if layout == h5py.h5d.VIRTUAL or dcpl.get_external_count():
        kind = "virtual" if layout == h5py.h5d.VIRTUAL else "external"
        raise VPRInputError(
            f"{path}: {name} keeps its values in other files (an HDF5 {kind} dataset), which are not read; write "
            "the descriptors into the file itself, as hloc does"
        )
    claim = f"{name} claims shape {shape} of {dataset.dtype} ({_size_text(nbytes)})"
    if layout == h5py.h5d.CONTIGUOUS:
        stored = dataset.get_storage_size()
        if stored != nbytes or nbytes > file_size:
            raise VPRInputError(
                f"{path}: {claim}, but the file stores {_size_text(stored)} for it ({_size_text(file_size)} in "
                "all); the dataset was never written or the file is damaged: write the descriptors again"
            )
    elif layout == h5py.h5d.CHUNKED:
        needed = math.prod(-(-n // c) for n, c in zip(shape, dcpl.get_chunk()))
        written = dataset.get_num_chunks()
        if written < needed:
            raise VPRInputError(
                f"{path}: {claim}, but only {written:,} of its {needed:,} chunks are written (HDF5 would fill the "
                "rest with a constant); the dataset was never fully written or the file is damaged: write the "
                "descriptors again"
            )
    return nbytes


def _dataset_leaves(fd, h5py) -> set[str]:
    """The last part of the name of every dataset in an HDF5 file (what it holds instead)."""
    leaves: set[str] = set()
    fd.visititems(lambda name, obj: leaves.add(name.rsplit("/", 1)[-1]) if isinstance(obj, h5py.Dataset) else None)
    return leaves


_READERS = {
    DescriptorFormat.NPZ: _read_npz,
    DescriptorFormat.NPY: read_npy_rows,
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


def clean_name(name: str) -> str:
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
    clean = [clean_name(n) for n in names]
    repeated = [n for n, c in Counter(clean).items() if c > 1]
    if repeated:
        raise VPRInputError(
            f"{path}: {len(repeated):,} names appear more than once ({_listing(repeated)}); give each image "
            "one row"
        )
    index = {clean_name(n): i for i, n in enumerate(image_names)}  # cleaned alike: an absolute name loses its '/'
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
    rows: np.ndarray, order: np.ndarray, image_names: Sequence[str], path: Path, dtype: str, *,
    out: np.ndarray | None = None,
) -> tuple[np.ndarray, int]:
    """``rows[order]`` as unit rows in ``dtype`` (written into ``out`` when given), and how many were rescaled.

    Norms are float64 (float32 squares overflow above ~1e19). Rows within
    ``UNIT_TOLERANCE`` of unit length are cast, not divided, so float32 unit rows come
    back bit-exact; the others are divided in float64, as extraction does. A finite row
    whose float64 norm overflows (entries near 1e300) is divided by its largest
    magnitude first: it has a direction like any other row.

    Raises:
        VPRInputError: naming the images whose row is NaN/infinite, all zero, or of a norm
            below ``MIN_NORM``.
    """
    n, d = len(order), rows.shape[1]
    out = np.empty((n, d), dtype=dtype) if out is None else out
    step = max(1, CHUNK_BYTES // (8 * d))
    not_finite: list[int] = []
    zero: list[int] = []
    tiny: list[int] = []
    rescaled = 0
    for lo in range(0, n, step):
        block = np.asarray(rows[order[lo : lo + step]])
        wide = block.astype(np.float64)
        finite = np.isfinite(wide).all(axis=1)
        with np.errstate(over="ignore", invalid="ignore"):
            norms = np.linalg.norm(np.where(finite[:, None], wide, 0.0), axis=1)
        small = finite & ~(norms >= MIN_NORM)
        if not finite.all() or small.any():
            all_zero = small & ~np.any(wide != 0, axis=1)
            not_finite.extend((lo + np.flatnonzero(~finite)).tolist())
            zero.extend((lo + np.flatnonzero(all_zero)).tolist())
            tiny.extend((lo + np.flatnonzero(small & ~all_zero)).tolist())
            continue
        if not_finite or zero or tiny:
            continue  # an error is coming: only collect the culprits
        off = np.flatnonzero(np.abs(norms - 1.0) > UNIT_TOLERANCE)
        with np.errstate(over="ignore"):  # rows too large for ``dtype`` are off unit length: replaced below
            out[lo : lo + len(block)] = block
        if len(off):
            huge = off[np.isinf(norms[off])]
            out[lo + off] = wide[off] / norms[off, None]
            if len(huge):
                scaled = wide[huge] / np.abs(wide[huge]).max(axis=1, keepdims=True)
                out[lo + huge] = scaled / np.linalg.norm(scaled, axis=1, keepdims=True)
            rescaled += len(off)
    if not_finite or zero or tiny:
        faults = []
        if not_finite:
            faults.append(f"{len(not_finite):,} are NaN or infinite ({_listing([image_names[i] for i in not_finite])})")
        if zero:
            faults.append(f"{len(zero):,} are all zero ({_listing([image_names[i] for i in zero])})")
        if tiny:
            faults.append(f"{len(tiny):,} have a norm below {MIN_NORM:g}, too close to zero to trust their direction "
                          f"({_listing([image_names[i] for i in tiny])})")
        raise VPRInputError(
            f"{path}: of the descriptors, {' and '.join(faults)}; such a row has no direction to compare: "
            "recompute those images' descriptors, or remove the images from the dataset"
        )
    return out, rescaled


def unit_rows_joined(
    parts: Sequence[tuple[Path, np.ndarray, np.ndarray, Sequence[str]]], dtype: str, *, source: Path
) -> tuple[np.ndarray, tuple[int, ...]]:
    """Several files' rows, checked and L2-normalised as :func:`load_descriptor_file` does, into one array.

    Args:
        parts: ``(path, rows, order, image_names)`` per file, in output order: ``rows[order]``
            (``order[i]`` the file's row of ``image_names[i]``) fill the next ``len(order)`` rows of
            the result; every part's rows have the same length ``D``.
        dtype: ``"float32"`` or ``"float16"``.
        source: what the memory check names (e.g. the folder holding the files).

    Returns:
        The read-write ``(sum of len(order), D)`` array, allocated once after the memory check,
        and per part how many of its rows were rescaled to unit length.

    Raises:
        VPRInputError: more than this machine's memory, or rows that are NaN, infinite, zero or
            of a norm below ``MIN_NORM`` (naming the part's file and images).
    """
    n, d = sum(len(order) for _, _, order, _ in parts), parts[0][1].shape[1]
    needed = _nbytes((n, d), np.dtype(dtype))
    _check_memory(source, f"its {n:,} descriptors of length {d:,} take {_size_text(needed)} as {dtype}", needed,
                  "read them as float16 (dtype), or on a machine with more memory")
    out = np.empty((n, d), dtype=dtype)
    rescaled, lo = [], 0
    for path, rows, order, names in parts:
        rescaled.append(_unit_rows(rows, order, names, path, dtype, out=out[lo : lo + len(order)])[1])
        lo += len(order)
    return out, tuple(rescaled)


# --- claimed sizes, checked before anything is allocated ---------------------------------


def npy_header(path: Path) -> tuple[tuple[int, ...], np.dtype]:
    """The shape and dtype a ``.npy`` file's header declares, once the file holds exactly that array.

    Only the header is read: a header whose shape and dtype do not come to the bytes
    after it (a truncated file, or a few bytes claiming ``(10**15, 10**6)``) is refused
    before anything is mapped or allocated.

    Raises:
        VPRInputError: naming the file, the claimed shape and what to do.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            shape, dtype, offset = _array_header(fh, path, "the file")
    except OSError as exc:
        raise VPRInputError(f"{path}: cannot read the file ({exc}); check that it is readable") from None
    if not dtype.hasobject:  # an object array is refused by np.load (allow_pickle=False) with its own message
        nbytes = _nbytes(shape, dtype)
        if nbytes != size - offset:
            raise _unreadable(
                path, f"its header claims shape {shape} of {dtype}, {_size_text(nbytes)}, but "
                      f"{_size_text(size - offset)} follow the header"
            )
    return shape, dtype


def _array_header(fh, path: Path, where: str) -> tuple[tuple[int, ...], np.dtype, int]:
    """``(shape, dtype, header length)`` of the ``.npy`` at ``fh``'s start; nothing after the header is read."""
    from numpy.lib import format as npy_format

    try:
        version = npy_format.read_magic(fh)
        if version == (1, 0):
            shape, _, dtype = npy_format.read_array_header_1_0(fh)
        elif version == (2, 0):
            shape, _, dtype = npy_format.read_array_header_2_0(fh)
        else:
            raise ValueError(f".npy format version {version[0]}.{version[1]} is not read")
        offset = fh.tell()
    except (ValueError, EOFError, SyntaxError, tokenize.TokenError) as exc:
        raise _unreadable(path, f"{where}: {exc}") from None
    if any(n < 0 for n in shape):
        raise _unreadable(path, f"{where}: its header claims shape {shape}")
    return tuple(shape), dtype, offset


def _check_npz_claims(path: Path) -> None:
    """Each array the reader takes from a ``.npz`` is a ``.npy`` entry whose header fits the entry and memory.

    The archive's directory gives each entry's uncompressed size: a header claiming
    another size, or more than this machine's memory, is refused before ``np.load``
    allocates the array or inflates more than the header.
    """
    try:
        with zipfile.ZipFile(path) as archive:
            entries = set(archive.namelist())
            for key in (NPZ_NAMES, NPZ_DESCRIPTORS):
                if key in entries:  # np.load would return such an entry's raw bytes
                    raise _unreadable(path, f"the archive's entry {key!r} is not a .npy array (np.savez writes "
                                            f"{key}.npy)")
                if f"{key}.npy" not in entries:
                    continue  # the missing array is named once the archive is open
                info = archive.getinfo(f"{key}.npy")
                where = f"{info.filename} in the archive"
                with archive.open(info) as fh:  # the header alone is inflated
                    shape, dtype, offset = _array_header(fh, path, where)
                if dtype.hasobject:
                    continue  # np.load (allow_pickle=False) refuses it with its own message
                nbytes = _nbytes(shape, dtype)
                if offset + nbytes != info.file_size:
                    raise _unreadable(
                        path, f"{where} claims shape {shape} of {dtype}, {_size_text(nbytes)}, but the entry "
                              f"holds {_size_text(max(info.file_size - offset, 0))} after its header"
                    )
                _check_memory(path, f"{where} claims shape {shape} of {dtype}, {_size_text(nbytes)}", nbytes,
                              "the file is damaged or holds more than one dataset's descriptors: write this "
                              "dataset's descriptors again with np.savez")
    except (OSError, EOFError, zipfile.BadZipFile, zlib.error, RuntimeError, NotImplementedError) as exc:
        # RuntimeError, NotImplementedError: an encrypted entry, or a compression zipfile does not read
        raise _unreadable(path, exc) from None


def _check_memory(path: Path, claim: str, nbytes: int, fix: str) -> None:
    """Refuse ``nbytes`` (what ``claim`` says the file needs) when it exceeds this machine's memory."""
    memory = _memory_bytes()
    if memory is not None and nbytes > memory:
        raise VPRInputError(f"{path}: {claim}, more than this machine's memory ({_size_text(memory)}); {fix}")


@functools.cache
def _memory_bytes() -> int | None:
    """This machine's physical memory in bytes, or ``None`` where the system does not say."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None


def _nbytes(shape: Sequence[int], dtype: np.dtype) -> int:
    """Bytes of an array of ``shape`` and ``dtype``, in Python integers (never overflows)."""
    return math.prod(int(n) for n in shape) * np.dtype(dtype).itemsize


def _size_text(nbytes: int) -> str:
    """``nbytes`` for a reader: ``64 bytes``, ``3.4 KiB`` … ``3.4 ZiB``."""
    if nbytes < 1024:
        return f"{nbytes:,} bytes"
    value, unit = float(nbytes), "bytes"
    for unit in ("KiB", "MiB", "GiB", "TiB", "PiB", "EiB", "ZiB", "YiB"):
        value /= 1024
        if value < 1024:
            break
    return f"{value:,.1f} {unit}"


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


def file_stamp(path: Path) -> tuple[int, int]:
    """``(size in bytes, modification time in ns)`` of ``path``: compared before and after a read to see it unchanged.

    Raises:
        VPRInputError: the file cannot be stat'ed.
    """
    try:
        st = path.stat()
    except OSError as exc:
        raise VPRInputError(f"{path}: cannot read the file ({exc}); check that it exists and is readable") from None
    return st.st_size, st.st_mtime_ns


def file_digests(files: Sequence[Path]) -> tuple[str, ...]:
    """sha256 hex of each file's bytes, read in chunks."""
    out = []
    for f in files:
        try:
            with open(f, "rb") as fh:
                out.append(hashlib.file_digest(fh, "sha256").hexdigest())
        except OSError as exc:
            raise VPRInputError(f"{f}: cannot read the file ({exc}); check that it exists and is readable") from None
    return tuple(out)


def content_key(files: Sequence[Path], dtype: str, image_names: Sequence[str], *,
                digests: Sequence[str] | None = None) -> str:
    """sha256 over the files' bytes (their ``digests`` when already computed), the dtype and the image order."""
    digest = hashlib.sha256(KEY_VERSION.encode())
    for f, file_hash in zip(files, file_digests(files) if digests is None else digests):
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
