"""Descriptors of a million images as a float16 memory map: never a dense float32 copy.

1,000,000 × 2,048 float16 descriptors are 4 GB; as float32 in memory they would be 8 GB, and
every product over them another copy. Here they stay in one file, dataset-ordered, opened
with ``np.load(mmap_mode="r")``: the operating system pages in what a pass reads, and every
consumer (``stats.negative_stats_rows``, ``thresholds.training_pair_scores(rows=…)``,
``numbers.score_rows`` and the protocol ``numbers.evaluate_fitted``) reads a
block of rows, converts it to float32, uses it and drops it.

Two sources give such a file:

* a descriptor ``.npy`` (float16 or float32) whose rows follow the dataset's image order (no
  names file, or one listing exactly that order): :func:`open_npy` maps it as it is;
* the descriptor cache: :meth:`DescriptorCache.dataset_view` writes the dataset's rows once,
  in its order, as one float16 file beside the shards (compaction; atomic like every cache
  write) and maps it (``pipeline.dataset_descriptors(..., mmap=True)``).

Whether to map: ``mmap="auto"`` maps once the float32 copy would reach
``mmap_min_bytes()`` (``MMAP_MIN_BYTES``, 1 GiB, or the ``VPR_EXPLORER_MMAP_BYTES``
variable): smaller descriptor sets are read into memory, as they are below that size.

Checks run chunk-wise (:func:`check_rows`): a NaN, infinite or all-zero row, or one off unit
length by more than ``UNIT_TOLERANCE_F16`` (a float16 file cannot be normalised in place),
raises one ``VPRInputError`` naming its images.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from vpr_explorer.descriptors.extract import MIN_SQUARED_NORM
from vpr_explorer.errors import VPRInputError

MMAP_ENV = "VPR_EXPLORER_MMAP_BYTES"
MMAP_MIN_BYTES = 1 << 30
"""Descriptors whose float32 copy would take this many bytes or more are memory-mapped (``mmap="auto"``)."""
CHUNK_ELEMS = 1 << 24
"""Entries checked at a time (64 MB as float32)."""
UNIT_TOLERANCE_F16 = 2e-3
"""|‖row‖ − 1| allowed in a mapped file: float16 rounding of a unit row moves its norm by ~1e-4 at most."""
NAMED = 5


def mmap_min_bytes() -> int:
    """``MMAP_MIN_BYTES``, or the ``VPR_EXPLORER_MMAP_BYTES`` variable when set (0 maps everything)."""
    raw = os.environ.get(MMAP_ENV)
    if raw is None or not raw.strip():
        return MMAP_MIN_BYTES
    try:
        value = int(raw)
    except ValueError:
        raise VPRInputError(f"{MMAP_ENV}={raw!r}: must be a whole number of bytes (0 maps every descriptor set)") \
            from None
    if value < 0:
        raise VPRInputError(f"{MMAP_ENV}={raw!r}: must be 0 or more bytes")
    return value


def check_mmap(mmap) -> str:
    """``mmap`` as ``"auto"``, ``"on"`` or ``"off"`` (``True``/``False`` are on/off)."""
    value = {True: "on", False: "off"}.get(mmap, mmap) if isinstance(mmap, bool) else mmap
    if value not in ("auto", "on", "off"):
        raise VPRInputError(f"mmap={mmap!r}: choose 'auto', True or False")
    return value


def wants_mmap(mmap, n: int, dim: int) -> bool:
    """Whether ``n × dim`` descriptors are mapped under ``mmap`` ("auto": once their float32 copy would reach
    ``mmap_min_bytes()``)."""
    mode = check_mmap(mmap)
    return mode == "on" or (mode == "auto" and n * dim * 4 >= mmap_min_bytes())


def check_rows(rows: np.ndarray, names: Sequence[str], what: str, *, tolerance: float = UNIT_TOLERANCE_F16) -> None:
    """Every row finite, non-zero and of unit length within ``tolerance``, checked ``CHUNK_ELEMS`` at a time.

    Raises:
        VPRInputError: naming ``what`` and the first images of each fault.
    """
    step = max(1, CHUNK_ELEMS // rows.shape[1])
    not_finite: list[int] = []
    zero: list[int] = []
    off: list[int] = []
    for lo in range(0, len(rows), step):
        x = np.asarray(rows[lo : lo + step], dtype=np.float32)
        with np.errstate(over="ignore", invalid="ignore"):
            sq = np.einsum("ij,ij->i", x, x, dtype=np.float64)
        bad = ~np.isfinite(sq)
        if bad.any():
            bad[bad] = ~np.isfinite(x[bad]).all(axis=1)
            not_finite.extend((lo + np.flatnonzero(bad)).tolist())
        small = np.isfinite(sq) & (sq < MIN_SQUARED_NORM)
        zero.extend((lo + np.flatnonzero(small)).tolist())
        norm_off = np.isfinite(sq) & ~small & (np.abs(np.sqrt(np.where(np.isfinite(sq), sq, 1.0)) - 1.0) > tolerance)
        off.extend((lo + np.flatnonzero(norm_off)).tolist())
    faults = []
    for rows_, text in ((not_finite, "are NaN or infinite"), (zero, "are all zero"),
                        (off, f"are not of unit length (|‖d‖ − 1| > {tolerance:g})")):
        if rows_:
            shown = ", ".join(str(names[i]) for i in rows_[:NAMED])
            more = f" and {len(rows_) - NAMED:,} more" if len(rows_) > NAMED else ""
            faults.append(f"{len(rows_):,} {text} ({shown}{more})")
    if faults:
        raise VPRInputError(
            f"{what}: of the descriptors, {' and '.join(faults)}; a memory-mapped file is used as stored, so "
            "recompute those images' descriptors (L2-normalised rows), or remove the images from the dataset"
        )


def _relative_names(image_paths: Sequence[Path], root: Path) -> tuple[str, ...]:
    """``imported.relative_names``, by string prefix when every path lies below ``root`` (a million
    ``Path.relative_to`` calls take seconds); otherwise that function itself."""
    prefix = Path(root).as_posix().rstrip("/") + "/"
    names = [Path(p).as_posix() for p in image_paths] if os.sep != "/" else [str(p) for p in image_paths]
    if all(n.startswith(prefix) for n in names):
        rel = tuple(n[len(prefix):] for n in names)
        if len(set(rel)) == len(rel):
            return rel
    from vpr_explorer.descriptors.imported import relative_names

    return relative_names(image_paths, root)


def open_npy(path: Path, image_paths: Sequence[Path], root: Path, *, names_file: Path | None = None):
    """A descriptor ``.npy`` in the dataset's image order, memory-mapped as stored (float16 or float32).

    Returns:
        ``ImportedDescriptors`` whose ``descriptors`` is the read-only memmap (no copy), or
        ``None`` when the file cannot be mapped as it is (rows in another order than the
        dataset's, another dtype): ``load_descriptor_file`` then reads it into memory.

    Raises:
        VPRInputError: what ``load_descriptor_file`` raises for the file, and rows that are
            NaN, infinite, zero or not unit length (named, :func:`check_rows`).
    """
    from vpr_explorer.descriptors import imported as imp

    path = Path(path).expanduser()
    if imp.descriptor_format(path) is not imp.DescriptorFormat.NPY or not path.is_file():
        return None
    image_names = _relative_names(image_paths, root)
    before = imp.file_stamp(path)
    read = imp.read_npy_rows(path, None if names_file is None else Path(names_file).expanduser())
    rows = read.rows
    if rows.dtype not in (np.float16, np.float32) or not rows.flags.c_contiguous:
        return None
    if read.names is not None:
        if tuple(imp.clean_name(n) for n in read.names) != image_names:
            return None  # matched by name, in another order: read into memory in the dataset's order
    elif len(rows) != len(image_names):
        return None  # load_descriptor_file names the count mismatch
    check_rows(rows, image_names, str(path))
    files = (path,) if read.names_file is None else (path, read.names_file)
    digests = imp.file_digests(files)
    key = imp.content_key(files, f"mmap-{rows.dtype}", image_names, digests=digests)
    if imp.file_stamp(path) != before:
        raise VPRInputError(f"{path}: the file changed while it was read; open it again once it is fully written")
    notes = (*read.notes, f"memory-mapped as stored ({rows.dtype}, {rows.nbytes / 2**30:.2f} GiB): read a block of "
             "rows at a time, never copied whole; every row checked finite and of unit length")
    return imp.ImportedDescriptors(descriptors=rows, name=path.stem, key=key, source=imp.DescriptorFormat.NPY,
                                   path=path, names_file=read.names_file, notes=notes, digests=digests)
