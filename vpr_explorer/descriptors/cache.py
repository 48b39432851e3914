"""On-disk descriptor cache, keyed by extractor and image content.

Layout: ``ROOT/descriptors/<cache_key>/<shard>.npy`` + ``<shard>.json``, where ``ROOT`` is
the cache folder (``--cache-dir`` or ``VPR_EXPLORER_CACHE``: the same folder is the same
cache whichever names it). A shard is one write: an
``(N, D)`` matrix and a manifest holding the N images' content hashes (sha256 of the file
bytes) in row order, the dtype, the shape and the sha256 of the ``.npy`` bytes. Keying by
content means renaming, reordering or regrouping images never recomputes, and an edited
image always does.

Why it is safe with several readers and writers (Streamlit sessions, a CLI run):

* shards are immutable; a write never touches an existing file;
* each file is written to a hidden temporary in the same folder, fsynced, then
  ``os.replace``d into place (atomic on POSIX); the manifest goes last, and readers only
  look at manifests, so a half-written shard is invisible;
* two writers of the same images make two shards with equal rows; either is right;
* a writer killed mid-write (SIGKILL, power loss) leaves a temporary, or a ``.npy``
  whose manifest never came; both carry the writer's host and pid in their names, and
  :meth:`DescriptorCache.remove_stale` deletes them once that process is gone (or, for
  another machine's files, after ``STALE_AFTER_S``). A live writer's files are never
  touched.

A shard that fails any check (manifest unreadable, ``.npy`` missing, truncated, of
another shape or dtype, checksum mismatch) is reported with ``warnings.warn``
(:class:`DescriptorCacheWarning`) naming its file, deleted, and treated as a miss, so its
vectors are recomputed, never trusted. The checksum is verified for every shard a lookup
reads rows from.

Compaction (many small shards -> one) can be added without a format change: write the
merged shard, then delete the old manifests, then their ``.npy`` files.

**Dataset views** (:meth:`DescriptorCache.dataset_view`, for a million-image database): one
float16 ``.npy`` holding a dataset's rows in its image order, written once from the shards
(each shard's checksum verified as it is read) into ``<cache_key>/views/``, atomically (a
temporary, fsync, rename; its manifest last), then memory-mapped. Its manifest records the
sha256 of the whole file, computed when it is written, and its size and mtime. A 4 GB file
is not hashed whole on every open: each open checks the size and mtime and re-hashes
``VIEW_SPOTS`` blocks of ``VIEW_SPOT_BYTES`` spread over the file (the header, the last
block, evenly between; their hashes are in the manifest); ``verify="full"`` re-hashes it
all. A view that fails a check is reported (``DescriptorCacheWarning``), deleted and written
again from the shards. Views are never read by :meth:`lookup`: the shards stay the source.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
import time
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
# A leftover whose writer is known dead is removed once this old: a margin for a
# writer in another pid namespace that shares this host name (containers).
DEAD_WRITER_GRACE_S = 60
# A leftover whose writer cannot be checked (another machine, an older version's name)
# is removed once this old: writing a shard takes seconds.
STALE_AFTER_S = 3600
# Shard file stems: ``<32 hex>.<host>.<pid>`` (older versions: ``<32 hex>``).
_SHARD_STEM = re.compile(r"^[0-9a-f]{32}\.(?P<host>[A-Za-z0-9-]{1,32})\.(?P<pid>[0-9]{1,10})$")


VIEW_FOLDER = "views"
VIEW_SPOTS = 16
VIEW_SPOT_BYTES = 1 << 16
VIEW_KIND = "dataset-view"


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
    tmp = path.with_name(settings.temporary_name(path.name))
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _writer_gone(host: str, pid: int) -> bool | None:
    """True when process ``pid`` of this machine has exited, False while it runs, None when unknown."""
    if host != settings.host_tag():
        return None  # another machine's process: its pid means nothing here
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)  # signal 0: only asks whether the process exists
    except ProcessLookupError:
        return True
    except PermissionError:
        return False  # exists, owned by another user
    except (OSError, OverflowError):
        return None
    return False


def is_stale(path: Path, owner: tuple[str, int] | None, now: float) -> bool:
    """Whether a leftover of an unfinished write may be deleted (see the module docstring).

    Args:
        path: the leftover file.
        owner: ``(host, pid)`` of the process that wrote it, from its name; None when the
            name carries none.
        now: the current time, seconds since the epoch.

    Returns:
        False for a live writer's file, whatever its age; else whether it is older than
        ``DEAD_WRITER_GRACE_S`` (its writer is gone) or ``STALE_AFTER_S`` (unknown writer).
    """
    gone = _writer_gone(*owner) if owner is not None else None
    if gone is False:
        return False  # a live writer's file, whatever its age
    try:
        age = now - path.stat().st_mtime
    except OSError:
        return False  # already gone
    return age >= (DEAD_WRITER_GRACE_S if gone else STALE_AFTER_S)


def _shard_owner(stem: str) -> tuple[str, int] | None:
    match = _SHARD_STEM.match(stem)
    return (match["host"], int(match["pid"])) if match else None


def _fsync_dir(folder: Path) -> None:
    # Makes the renames durable: without it a crash can lose the directory entries.
    if os.name != "posix":
        return  # directories cannot be opened for fsync elsewhere
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _file_sha256(path: Path) -> str:
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


def _spot_hashes(path: Path, size: int) -> list[str]:
    """sha256 of ``VIEW_SPOTS`` blocks of ``VIEW_SPOT_BYTES``: the first, the last, evenly between."""
    starts = np.unique(np.linspace(0, max(0, size - VIEW_SPOT_BYTES), VIEW_SPOTS).astype(np.int64))
    out = []
    with open(path, "rb") as fh:
        for start in starts:
            fh.seek(int(start))
            out.append(hashlib.sha256(fh.read(VIEW_SPOT_BYTES)).hexdigest())
    return out


class DescriptorCache:
    """Descriptor vectors by ``(cache_key, image content hash)``, in immutable shards.

    Args:
        root: the cache folder, default ``settings.cache_root()``; shards live under
            ``root/descriptors/`` (:attr:`folder`), created on first write.
        dtype: storage dtype of the shards this cache writes, ``"float32"`` (exact) or
            ``"float16"`` (half the disk, ~1e-3 relative error). It does not decide what
            :meth:`lookup` returns (its own ``dtype``, float32 by default). A float16 cache
            reads shards of either dtype; a float32 cache only float32 ones, so exact
            vectors are never replaced by rounded ones.
    """

    def __init__(self, root: Path | None = None, *, dtype: str = "float32") -> None:
        self.dtype = check_dtype(dtype, "dtype", "cache storage type")
        self.root = Path(root).expanduser() if root is not None else settings.cache_root()
        self.folder = settings.descriptor_folder(self.root)

    def __repr__(self) -> str:
        return f"DescriptorCache(root={str(self.root)!r}, dtype={self.dtype!r})"

    hash_file = staticmethod(hash_file)

    def check_writable(self) -> None:
        """Make sure shards can be written here (:func:`settings.check_cache_root`).

        Raises:
            VPRInputError: naming the folder and the fix (``--cache-dir``, ``VPR_EXPLORER_CACHE``).
        """
        settings.check_cache_root(self.root)

    # ---------------------------------------------------------------- writing

    def store(self, cache_key: str, hashes: Sequence[str], vectors: np.ndarray) -> Path | None:
        """Write one shard: ``vectors[k]`` is the descriptor of the image with ``hashes[k]``.

        Args:
            vectors: ``(N, D)`` finite floats; stored as this cache's ``dtype``.

        Returns:
            The new shard's manifest path, or ``None`` when ``hashes`` is empty.

        Raises:
            VPRInputError: bad arguments, or the folder cannot be written (disk full,
                permissions), naming it.
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
        # The writer in the name: a .npy whose manifest never came is cleaned up once it is gone.
        shard = f"{uuid.uuid4().hex}.{settings.host_tag()}.{os.getpid()}"
        try:
            folder.mkdir(parents=True, exist_ok=True)
            _atomic_write(folder / f"{shard}.npy", npy_bytes)
            # The manifest is what makes a shard visible, so it goes last.
            _atomic_write(folder / f"{shard}.json", json.dumps(manifest).encode())
            _fsync_dir(folder)
        except OSError as exc:
            raise VPRInputError(
                f"cache folder {self.root}: cannot write a descriptor shard ({exc.strerror or exc}); free space, "
                f"or choose a writable folder with --cache-dir (command line) or {settings.CACHE_ENV}"
            ) from exc
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

    def dataset_view(self, cache_key: str, hashes: Sequence[str], *, verify: str = "spots") -> np.ndarray | None:
        """The rows of ``hashes``, in that order, as one read-only float16 memmap ``(len(hashes), D)``.

        Written once per (``cache_key``, hashes in order) from the shards this cache reads
        (as :meth:`lookup` reads them: a float32 cache only float32 shards), rounded to
        float16, atomically; opened with ``np.load(mmap_mode="r")`` (module docstring).

        Args:
            verify: on opening an existing view, ``"spots"`` (size, mtime and the hashes of
                ``VIEW_SPOTS`` blocks) or ``"full"`` (the whole file's sha256).

        Returns:
            The memmap, or ``None`` when some hash is not cached (extract those first).

        Raises:
            VPRInputError: a bad ``cache_key`` or ``verify``, or the folder cannot be written.
        """
        if verify not in ("spots", "full"):
            raise VPRInputError(f"verify={verify!r}: choose 'spots' or 'full'")
        hashes = list(hashes)
        if not hashes:
            raise VPRInputError("hashes: no images given; a dataset view needs at least one")
        folder = self._folder(cache_key) / VIEW_FOLDER
        digest = hashlib.sha256(f"{cache_key}|{self.dtype}|".encode())
        digest.update("\n".join(hashes).encode())
        stem = digest.hexdigest()[:40]
        manifest_path = folder / f"{stem}.json"
        if manifest_path.is_file():
            try:
                return self._open_view(manifest_path, len(hashes), verify)
            except _Damaged as exc:
                warnings.warn(f"{manifest_path}: damaged dataset view: {exc}; deleted it, it is written again "
                              "from the shards", DescriptorCacheWarning, stacklevel=2)
                manifest_path.unlink(missing_ok=True)
                manifest_path.with_suffix(".npy").unlink(missing_ok=True)
        if not self._write_view(cache_key, hashes, manifest_path):
            return None
        try:
            return self._open_view(manifest_path, len(hashes), "spots")
        except _Damaged as exc:  # pragma: no cover (written and checked just now)
            raise VPRInputError(f"{manifest_path}: the dataset view just written fails its check ({exc})") from None

    def _write_view(self, cache_key: str, hashes: list[str], manifest_path: Path) -> bool:
        """Compaction: the rows of ``hashes`` from the shards into one float16 file; False if one is missing."""
        wanted: dict[str, list[int]] = {}
        for i, h in enumerate(hashes):
            wanted.setdefault(h, []).append(i)
        folder = manifest_path.parent
        npy = manifest_path.with_suffix(".npy")
        tmp = npy.with_name(settings.temporary_name(npy.name))
        out = None
        try:
            folder.mkdir(parents=True, exist_ok=True)
            now = time.time()
            for leftover in folder.glob(".*.tmp"):  # a killed compaction's temporary, once its writer is gone
                if is_stale(leftover, settings.temporary_owner(leftover.name), now):
                    leftover.unlink(missing_ok=True)
            for shard in self._manifests(self._folder(cache_key)):
                if not wanted:
                    break
                try:
                    manifest = self._read_manifest(shard)
                    if self.dtype == "float32" and manifest["dtype"] != "float32":
                        continue
                    rows = [row for row, h in enumerate(manifest["hashes"]) if h in wanted]
                    if not rows:
                        continue
                    if out is not None and manifest["shape"][1] != out.shape[1]:
                        raise _Damaged(f"its vectors are {manifest['shape'][1]}-d, expected {out.shape[1]}-d")
                    matrix = self._read_vectors(shard, manifest)
                except _Damaged as exc:
                    self._discard(shard, str(exc))
                    continue
                if out is None:
                    out = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.float16,
                                                    shape=(len(hashes), manifest["shape"][1]))
                dest, source = [], []
                for row in rows:
                    for i in wanted.pop(manifest["hashes"][row], ()):
                        dest.append(i)
                        source.append(row)
                dest_a, source_a = np.asarray(dest, dtype=np.int64), np.asarray(source, dtype=np.int64)
                step = max(1, GATHER_BYTES // (out.shape[1] * matrix.dtype.itemsize))
                for lo in range(0, len(dest_a), step):
                    out[dest_a[lo : lo + step]] = matrix[source_a[lo : lo + step]]
                del matrix
            if wanted or out is None:
                return False
            out.flush()
            del out
            out = None
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
            whole = _file_sha256(tmp)
            os.replace(tmp, npy)
            st = npy.stat()
            view = {"format": FORMAT, "kind": VIEW_KIND, "cache_key": cache_key, "n": len(hashes),
                    "dtype": "float16", "sha256": whole, "size": st.st_size, "mtime_ns": st.st_mtime_ns,
                    "spots": _spot_hashes(npy, st.st_size)}
            _atomic_write(manifest_path, json.dumps(view).encode())
            _fsync_dir(folder)
            return True
        except OSError as exc:
            raise VPRInputError(
                f"cache folder {self.root}: cannot write a dataset view ({exc.strerror or exc}); free space "
                f"(it takes {len(hashes):,} × D × 2 bytes), or choose another folder with --cache-dir or "
                f"{settings.CACHE_ENV}"
            ) from exc
        finally:
            del out
            tmp.unlink(missing_ok=True)

    @staticmethod
    def _open_view(manifest_path: Path, n: int, verify: str) -> np.ndarray:
        """The view's memmap after its checks (size, mtime, spot hashes; or the whole sha256)."""
        npy = manifest_path.with_suffix(".npy")
        try:
            view = json.loads(manifest_path.read_text())
            ok = isinstance(view, dict) and view.get("kind") == VIEW_KIND and view.get("n") == n \
                and isinstance(view.get("spots"), list) and isinstance(view.get("sha256"), str)
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise _Damaged(f"unreadable manifest ({exc})") from exc
        if not ok:
            raise _Damaged("the manifest is not a dataset view's")
        try:
            st = npy.stat()
        except FileNotFoundError as exc:
            raise _Damaged(f"{npy.name} is missing") from exc
        if st.st_size != view.get("size"):
            raise _Damaged(f"{npy.name} is {st.st_size:,} bytes, the manifest says {view.get('size'):,}")
        if st.st_mtime_ns != view.get("mtime_ns"):
            raise _Damaged(f"{npy.name} was modified after it was written")
        if verify == "full":
            if _file_sha256(npy) != view["sha256"]:
                raise _Damaged(f"{npy.name} does not match its checksum")
        elif _spot_hashes(npy, st.st_size) != view["spots"]:
            raise _Damaged(f"{npy.name} does not match the checksums of its sampled blocks")
        try:
            matrix = np.load(npy, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise _Damaged(f"{npy.name} is unreadable ({exc})") from exc
        if matrix.dtype != np.float16 or matrix.ndim != 2 or len(matrix) != n:
            raise _Damaged(f"{npy.name} holds {matrix.dtype} {matrix.shape}, expected float16 with {n} rows")
        return matrix

    def contains(self, cache_key: str, hashes: Sequence[str]) -> np.ndarray:
        """``(len(hashes),)`` bool: whether a shard this cache would read lists each hash.

        Reads manifests only, so it is cheap at millions of hashes (no vectors are read,
        no checksum verified): what a job uses to decide what is left to compute. A shard
        found damaged later is still caught by :meth:`lookup`, which then recomputes it.
        Shards of another storage dtype count as :meth:`lookup` counts them.

        Raises:
            VPRInputError: a bad ``cache_key``.
        """
        folder = self._folder(cache_key)
        wanted = set(hashes)
        seen: set[str] = set()
        for manifest_path in self._manifests(folder):
            if len(seen) == len(wanted):
                break
            try:
                manifest = self._read_manifest(manifest_path)
            except _Damaged:
                continue  # lookup reports and deletes it
            if self.dtype == "float32" and manifest["dtype"] != "float32":
                continue
            seen.update(h for h in manifest["hashes"] if h in wanted)
        return np.fromiter((h in seen for h in hashes), dtype=bool, count=len(hashes))

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
            views = folder / VIEW_FOLDER
            if views.is_dir():  # dataset views: manifests first, as below
                for path in sorted(views.iterdir(), key=lambda p: p.suffix != ".json"):
                    if path.is_file() and (path.suffix in (".npy", ".json") or path.name.endswith(".tmp")):
                        path.unlink(missing_ok=True)
                try:
                    views.rmdir()
                except OSError:
                    pass
            # Manifests first, so concurrent readers stop seeing a shard before its
            # vectors go.
            for path in sorted(folder.iterdir(), key=lambda p: p.suffix != ".json"):
                if path.is_file() and (path.suffix in (".npy", ".json") or path.name.endswith(".tmp")):
                    path.unlink(missing_ok=True)
            try:
                folder.rmdir()
            except OSError:
                pass  # not empty: holds files the cache did not write; leave them

    def remove_stale(self, cache_key: str | None = None) -> int:
        """Delete what killed writers left behind in ``cache_key``'s folder (all keys when ``None``).

        That is hidden temporaries (``.*.tmp``) and ``.npy`` files without a manifest.
        One is stale when its writer, named in the file name, is a process of this
        machine that has exited (and the file is ``DEAD_WRITER_GRACE_S`` old); when the
        writer cannot be checked (another machine, an older version's file name), when
        it is ``STALE_AFTER_S`` old. A running writer's files are never deleted.

        Returns:
            How many files were deleted.
        """
        folders = [self._folder(cache_key)] if cache_key is not None else self._key_folders()
        now = time.time()
        removed = 0
        for folder in folders:
            try:
                names = {entry.name for entry in os.scandir(folder) if entry.is_file(follow_symlinks=False)}
            except OSError:
                continue  # missing or unreadable: nothing of ours to clean
            for name in names:
                path = folder / name
                if name.startswith(".") and name.endswith(".tmp"):
                    owner = settings.temporary_owner(name)
                elif not name.startswith(".") and name.endswith(".npy") and f"{name[:-4]}.json" not in names:
                    owner = _shard_owner(name[:-4])
                else:
                    continue
                if is_stale(path, owner, now):
                    try:
                        path.unlink()
                        removed += 1
                    except OSError:
                        pass  # another cleaner was first, or a read-only cache: lookups never read it anyway
        return removed

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
        return self.folder / cache_key

    def _key_folders(self) -> list[Path]:
        if not self.folder.is_dir():
            return []
        return sorted(p for p in self.folder.iterdir() if p.is_dir() and _KEY.match(p.name))

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
