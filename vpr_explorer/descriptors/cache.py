"""On-disk descriptor cache, keyed by extractor and image content.

Layout: ``ROOT/<cache_key>/<shard>.npy`` + ``<shard>.json``. A shard is one write: an
``(N, D)`` matrix and a manifest holding the N images' content hashes (sha256 of the file
bytes) in row order, the dtype, the shape and the sha256 of the ``.npy`` bytes. Keying by
content means renaming, reordering or regrouping images never recomputes, and an edited
image always does.

Why it is safe with several readers and writers (Streamlit sessions, a CLI run):

* shards are immutable; a write never touches an existing file;
* each file is written to a hidden temporary in the same folder, fsynced, then
  ``os.replace``d into place (atomic on POSIX); the manifest goes last, and readers only
  look at manifests, so a half-written shard is invisible;
* two writers of the same images make two shards with equal rows; either is right.

A shard that fails any check (manifest unreadable, ``.npy`` missing, truncated, of
another shape or dtype, checksum mismatch) is reported with ``warnings.warn``
(:class:`DescriptorCacheWarning`) naming its file, deleted, and treated as a miss, so its
vectors are recomputed, never trusted. The checksum is verified for every shard a lookup
reads rows from.

Compaction (many small shards -> one) can be added without a format change: write the
merged shard, then delete the old manifests, then their ``.npy`` files.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
import uuid
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from vpr_explorer import settings
from vpr_explorer.errors import VPRInputError

FORMAT = 1
DTYPES = ("float32", "float16")
_KEY = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+-]*$")
_HASH = re.compile(r"^[0-9a-f]{64}$")
# Rows are copied out of a shard this many bytes at a time, so a lookup's only large
# allocation is its result (no temporary the size of a shard, let alone of the result).
GATHER_BYTES = 1 << 20


class DescriptorCacheWarning(UserWarning):
    """A damaged cache shard was found and deleted; its vectors will be recomputed."""


class CacheHits(NamedTuple):
    """What a lookup found (a tuple, so ``index, vectors = cache.lookup(...)`` works).

    Attributes:
        index: ``(n_hits,)`` int64, ascending positions into the hashes asked for.
        vectors: ``(n_hits, D)`` in the dtype the lookup asked for (float32 by default,
            or float16), row ``k`` belongs to ``hashes[index[k]]``; writable, owns its data.
    """

    index: np.ndarray
    vectors: np.ndarray


class _Damaged(Exception):
    """A shard failed a check; the message says which."""


def check_dtype(dtype, name: str = "dtype", what: str = "descriptor dtype") -> str:
    """``dtype``'s name when it is one of :data:`DTYPES`.

    Args:
        dtype: anything ``np.dtype`` takes: ``"float16"``, ``np.float32``, ...
        name, what: the parameter and what it is, for the error message.

    Raises:
        VPRInputError: naming ``name`` for anything else.
    """
    try:
        dtype_name = str(np.dtype(dtype))
    except (TypeError, ValueError):
        dtype_name = ""
    if dtype_name not in DTYPES:
        raise VPRInputError(
            f"{name}={dtype!r} is not a {what}: choose one of {', '.join(DTYPES)} "
            "(float16 halves memory and disk, at ~1e-3 relative error)"
        )
    return dtype_name


def hash_file(path: Path) -> str:
    """sha256 hex digest of the file's bytes: the image's identity in the cache.

    Raises:
        VPRInputError: naming ``path`` when it is missing or unreadable.
    """
    try:
        with open(path, "rb") as fh:
            return hashlib.file_digest(fh, "sha256").hexdigest()
    except FileNotFoundError as exc:
        raise VPRInputError(f"{path}: the image file does not exist; check the dataset folder") from exc
    except OSError as exc:
        raise VPRInputError(f"{path}: cannot read the file ({exc}); check its permissions or remove it") from exc


def _atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see all of it or nothing."""
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _fsync_dir(folder: Path) -> None:
    # Makes the renames durable: without it a crash can lose the directory entries.
    if os.name != "posix":
        return  # directories cannot be opened for fsync elsewhere
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class DescriptorCache:
    """Descriptor vectors by ``(cache_key, image content hash)``, in immutable shards.

    Args:
        root: cache folder; default ``settings.cache_root() / "descriptors"``, created
            on first write.
        dtype: storage dtype of the shards this cache writes, ``"float32"`` (exact) or
            ``"float16"`` (half the disk, ~1e-3 relative error). It does not decide what
            :meth:`lookup` returns (its own ``dtype``, float32 by default). A float16 cache
            reads shards of either dtype; a float32 cache only float32 ones, so exact
            vectors are never replaced by rounded ones.
    """

    def __init__(self, root: Path | None = None, *, dtype: str = "float32") -> None:
        self.dtype = check_dtype(dtype, "dtype", "cache storage type")
        self.root = Path(root).expanduser() if root is not None else settings.cache_root() / "descriptors"

    def __repr__(self) -> str:
        return f"DescriptorCache(root={str(self.root)!r}, dtype={self.dtype!r})"

    hash_file = staticmethod(hash_file)

    # ---------------------------------------------------------------- writing

    def store(self, cache_key: str, hashes: Sequence[str], vectors: np.ndarray) -> Path | None:
        """Write one shard: ``vectors[k]`` is the descriptor of the image with ``hashes[k]``.

        Args:
            vectors: ``(N, D)`` finite floats; stored as this cache's ``dtype``.

        Returns:
            The new shard's manifest path, or ``None`` when ``hashes`` is empty.
        """
        folder = self._folder(cache_key)
        hashes = list(hashes)
        vectors = np.asarray(vectors)
        if vectors.ndim != 2 or len(vectors) != len(hashes):
            raise VPRInputError(
                f"vectors: shape {vectors.shape} does not match {len(hashes)} hashes; give one row per hash"
            )
        bad = [h for h in hashes if not isinstance(h, str) or not _HASH.match(h)]
        if bad:
            raise VPRInputError(f"hashes: {bad[0]!r} is not a sha256 hex digest; use DescriptorCache.hash_file")
        if not np.isfinite(vectors).all():
            raise VPRInputError("vectors: contain NaN or inf; only valid descriptors may be cached")
        if not hashes:
            return None
        data = np.ascontiguousarray(vectors, dtype=self.dtype)
        buffer = io.BytesIO()
        np.save(buffer, data, allow_pickle=False)
        npy_bytes = buffer.getvalue()
        manifest = {
            "format": FORMAT,
            "cache_key": cache_key,
            "hashes": hashes,
            "dtype": self.dtype,
            "shape": list(data.shape),
            "sha256": hashlib.sha256(npy_bytes).hexdigest(),
        }
        folder.mkdir(parents=True, exist_ok=True)
        shard = uuid.uuid4().hex
        _atomic_write(folder / f"{shard}.npy", npy_bytes)
        # The manifest is what makes a shard visible, so it goes last.
        _atomic_write(folder / f"{shard}.json", json.dumps(manifest).encode())
        _fsync_dir(folder)
        return folder / f"{shard}.json"

    # ---------------------------------------------------------------- reading

    def lookup(
        self, cache_key: str, hashes: Sequence[str], dim: int | None = None, *, dtype: str = "float32"
    ) -> CacheHits:
        """Cached vectors for those of ``hashes`` that are cached.

        The result is allocated once, in ``dtype``, and filled shard by shard a
        ``GATHER_BYTES`` slice at a time, so a float16 lookup of float16 shards never
        holds a float32 copy of anything, and a lookup never holds two copies of its
        result.

        Args:
            hashes: content hashes (``hash_file``); repeats are allowed (each gets its row).
            dim: expected descriptor length; shards of another length count as damaged.
                Default: the length of the first shard read.
            dtype: ``"float32"`` or ``"float16"``, the dtype of the vectors returned.
                Which shards are read depends on the cache's own storage ``dtype``: a
                float32 cache reads float32 shards only (its vectors are exact; float16
                shards count as misses), a float16 cache reads both. float16 shards'
                values come back exactly in either dtype; float32 shards' are rounded to
                float16 when ``dtype`` is float16.

        Returns:
            :class:`CacheHits` (``index`` into ``hashes``, ``(n_hits, D)`` in ``dtype``).

        Raises:
            VPRInputError: a bad ``cache_key`` or ``dtype``.
        """
        out_dtype = check_dtype(dtype)
        folder = self._folder(cache_key)
        wanted: dict[str, list[int]] = {}
        for i, h in enumerate(hashes):
            wanted.setdefault(h, []).append(i)
        n_asked = len(hashes)
        width = dim
        # One row per hash asked for, filled where found; compacted to the hits at the end.
        # Only the rows written are touched, so misses cost address space, not memory.
        vectors: np.ndarray | None = None
        found = np.zeros(n_asked, dtype=bool)
        for manifest_path in self._manifests(folder):
            if not wanted:
                break
            try:
                manifest = self._read_manifest(manifest_path)
                if width is not None and manifest["shape"][1] != width:
                    raise _Damaged(f"its vectors are {manifest['shape'][1]}-d, expected {width}-d")
                if self.dtype == "float32" and manifest["dtype"] != "float32":
                    continue  # an exact (float32) cache never serves float16-rounded vectors
                rows = [row for row, h in enumerate(manifest["hashes"]) if h in wanted]
                if not rows:
                    continue  # nothing asked for here: no need to read (or verify) its vectors
                matrix = self._read_vectors(manifest_path, manifest)
            except _Damaged as exc:
                # Its hashes stay wanted, so a later healthy shard may still serve them.
                self._discard(manifest_path, str(exc))
                continue
            positions: list[int] = []
            repeated_rows: list[int] = []
            for row in rows:
                found_at = wanted.pop(manifest["hashes"][row], None)
                if found_at is not None:  # None: a repeat within this shard, already taken
                    positions.extend(found_at)
                    repeated_rows.extend([row] * len(found_at))
            if vectors is None:
                width = manifest["shape"][1]
                vectors = np.empty((n_asked, width), dtype=out_dtype)
            dest = np.asarray(positions, dtype=np.int64)
            source = np.asarray(repeated_rows, dtype=np.int64)
            step = max(1, GATHER_BYTES // (width * matrix.dtype.itemsize))
            for lo in range(0, len(dest), step):
                # Reads only these rows of the memory-mapped shard; casts on assignment.
                vectors[dest[lo : lo + step]] = matrix[source[lo : lo + step]]
            found[dest] = True
            del matrix  # unmaps the shard before the next one is read
        if vectors is None:
            return CacheHits(np.zeros(0, dtype=np.int64), np.zeros((0, width or 0), dtype=out_dtype))
        index = np.flatnonzero(found)
        if len(index) < n_asked:
            # Move the hits to the front, in place: index[k] >= k, so a slice never reads a
            # row that an earlier slice has overwritten.
            step = max(1, GATHER_BYTES // (width * vectors.dtype.itemsize))
            for lo in range(0, len(index), step):
                part = index[lo : lo + step]
                vectors[lo : lo + len(part)] = vectors[part]
            vectors.resize((len(index), width), refcheck=False)  # no view of it exists
        return CacheHits(index, vectors)

    # ---------------------------------------------------------------- housekeeping

    def clear(self, cache_key: str | None = None) -> None:
        """Delete the shards of ``cache_key``, or of every key when ``None``.

        Deletes only files the cache writes (``*.npy``, ``*.json``, temporaries), so a
        mistaken ``root`` cannot wipe unrelated files.
        """
        folders = [self._folder(cache_key)] if cache_key is not None else self._key_folders()
        for folder in folders:
            if not folder.is_dir():
                continue
            # Manifests first, so concurrent readers stop seeing a shard before its
            # vectors go.
            for path in sorted(folder.iterdir(), key=lambda p: p.suffix != ".json"):
                if path.is_file() and (path.suffix in (".npy", ".json") or path.name.endswith(".tmp")):
                    path.unlink(missing_ok=True)
            try:
                folder.rmdir()
            except OSError:
                pass  # not empty: holds files the cache did not write; leave them

    def stats(self, cache_key: str | None = None) -> dict[str, int]:
        """``{"shards", "vectors", "bytes"}`` over ``cache_key`` or all keys (manifests only, unverified)."""
        folders = [self._folder(cache_key)] if cache_key is not None else self._key_folders()
        shards = vectors = size = 0
        for folder in folders:
            if not folder.is_dir():
                continue
            for path in folder.iterdir():
                if path.suffix not in (".npy", ".json") or path.name.startswith("."):
                    continue
                try:
                    size += path.stat().st_size
                    if path.suffix == ".json":
                        manifest = self._read_manifest(path)
                        shards += 1
                        vectors += manifest["shape"][0]
                except (OSError, _Damaged):
                    continue  # damaged or deleted meanwhile: lookup reports it
        return {"shards": shards, "vectors": vectors, "bytes": size}

    # ---------------------------------------------------------------- private

    def _folder(self, cache_key: str) -> Path:
        if not isinstance(cache_key, str) or not _KEY.match(cache_key):
            raise VPRInputError(
                f"cache_key={cache_key!r} is not a valid cache key: use letters, digits and . _ + - "
                "(Extractor.cache_key is)"
            )
        return self.root / cache_key

    def _key_folders(self) -> list[Path]:
        if not self.root.is_dir():
            return []
        return sorted(p for p in self.root.iterdir() if p.is_dir() and _KEY.match(p.name))

    @staticmethod
    def _manifests(folder: Path) -> list[Path]:
        if not folder.is_dir():
            return []
        # Sorted so every reader resolves duplicate hashes the same way.
        return sorted(p for p in folder.glob("*.json") if not p.name.startswith("."))

    @staticmethod
    def _read_manifest(path: Path) -> dict:
        try:
            manifest = json.loads(path.read_text())
        except FileNotFoundError as exc:
            raise _Damaged("the manifest disappeared") from exc
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise _Damaged(f"unreadable manifest ({exc})") from exc
        ok = (
            isinstance(manifest, dict)
            and manifest.get("format") == FORMAT
            and manifest.get("dtype") in DTYPES
            and isinstance(manifest.get("sha256"), str)
            and isinstance(manifest.get("hashes"), list)
            and isinstance(manifest.get("shape"), list)
            and len(manifest["shape"]) == 2
            and all(isinstance(n, int) and n > 0 for n in manifest["shape"])
            and manifest["shape"][0] == len(manifest["hashes"])
            and all(isinstance(h, str) and _HASH.match(h) for h in manifest["hashes"])
        )
        if not ok:
            raise _Damaged("the manifest is not a valid shard manifest")
        return manifest

    @staticmethod
    def _read_vectors(manifest_path: Path, manifest: dict) -> np.ndarray:
        """The shard's ``(N, D)`` matrix, memory-mapped, after checking its bytes."""
        npy = manifest_path.with_suffix(".npy")
        try:
            with open(npy, "rb") as fh:
                digest = hashlib.file_digest(fh, "sha256").hexdigest()
            if digest != manifest["sha256"]:
                raise _Damaged(f"{npy.name} does not match its checksum (truncated or altered)")
            # mmap: at 100k images only the rows asked for are read from disk.
            matrix = np.load(npy, mmap_mode="r", allow_pickle=False)
        except FileNotFoundError as exc:
            raise _Damaged(f"{npy.name} is missing") from exc
        except (OSError, ValueError) as exc:
            raise _Damaged(f"{npy.name} is unreadable ({exc})") from exc
        if matrix.shape != tuple(manifest["shape"]) or str(matrix.dtype) != manifest["dtype"]:
            raise _Damaged(
                f"{npy.name} holds {matrix.dtype} {matrix.shape}, the manifest says "
                f"{manifest['dtype']} {tuple(manifest['shape'])}"
            )
        return matrix

    @staticmethod
    def _discard(manifest_path: Path, why: str) -> None:
        warnings.warn(
            f"{manifest_path}: damaged descriptor cache shard: {why}; deleted it, its vectors will be recomputed",
            DescriptorCacheWarning,
            stacklevel=3,  # the caller of lookup()
        )
        # Manifest first: from that moment no other reader looks at the .npy.
        manifest_path.unlink(missing_ok=True)
        manifest_path.with_suffix(".npy").unlink(missing_ok=True)
