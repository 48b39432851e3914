"""Images -> L2-normalised descriptors, through the cache, decoding in parallel with the model.

Decoding is PIL's in worker threads (``decode="cpu"``), or, for a torch extractor with a
:class:`~vpr_explorer.descriptors.device_decode.DeviceRecipe`, JPEGs decoded and resized on
the model's device while the threads only read file bytes (``decode="device"``, the
default on a GPU: :mod:`~vpr_explorer.descriptors.device_decode`).
"""

from __future__ import annotations

import contextlib
import hashlib
import time
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np

from vpr_explorer.descriptors.base import Extractor, forward_by_shape
from vpr_explorer.descriptors.cache import DescriptorCache, check_dtype, hash_file
from vpr_explorer.descriptors.device_decode import device_inputs, forward_tensors, read_source, use_device
from vpr_explorer.errors import VPRInputError
from vpr_explorer.settings import default_workers

# Batches decoded (or, decoding on the device, read) ahead of the one in the model. When
# the model runs on the CPU it shares the cores with the decoders: one batch ahead hides
# decoding, and more only lets the decoders steal more from the forward pass. A GPU leaves
# the cores to the decoders, which then should never wait. Memory stays at a few batches
# (a 224x224 float32 image is 0.6 MB, a 960x540 JPEG's bytes ~50 kB).
PREFETCH_BATCHES = 1
PREFETCH_BATCHES_GPU = 3
# New vectors are cached as the run goes, so that an interrupted run resumes where it
# stopped: a shard is written when this many wait, or when the oldest has waited
# FLUSH_SECONDS (a kill loses at most that much work; a Ctrl-C or an error loses only
# the batch in flight, the finished ones are written before it propagates). Only
# vectors that passed the checks are written, keyed by content, so they are right
# whatever happens later in the run.
SHARD_SIZE = 4096
FLUSH_SECONDS = 10.0
#: A row whose norm is below this is all zero: its direction, and so its cosine similarity, is undefined.
MIN_NORM = 1e-12
#: ``MIN_NORM`` squared (1e-24): the same test on a row's squared norm.
MIN_SQUARED_NORM = MIN_NORM * MIN_NORM
# Cache hits are brought back to unit length this many bytes of float32 at a time: the
# temporaries stay ~1 MiB (~200 rows at 1280-d) however many hits there are.
RENORMALISE_BYTES = 1 << 20
NAMED_IN_ERRORS = 3
HASH_CHUNK = 256


class ExtractionInterrupted(KeyboardInterrupt):
    """Ctrl-C during extraction, raised once the finished batches are in the cache.

    A ``KeyboardInterrupt``, so whatever stops on Ctrl-C still does; its message is the
    one line to show, e.g. ``"160 of 600 descriptors cached; run the same command again
    to resume"``.

    Attributes:
        cached: images of the run whose descriptors are now in the cache (hits included).
        total: images of the run.
    """

    def __init__(self, cached: int, total: int, *, with_cache: bool = True) -> None:
        self.cached = cached
        self.total = total
        if with_cache:
            message = f"{cached} of {total} descriptors cached; run the same command again to resume"
        else:
            message = f"stopped before all {total} descriptors were computed; no cache was used, nothing is kept"
        super().__init__(message)


class _Pending:
    """New vectors not yet in the cache; written as shards while the run goes on.

    Rows are dropped once stored, so a write cut short (Ctrl-C inside it) is simply
    retried by the next :meth:`flush`.
    """

    def __init__(self, cache: DescriptorCache, cache_key: str) -> None:
        self.cache = cache
        self.cache_key = cache_key
        self.hashes: list[str] = []
        self.images: list[int] = []  # how many of the run's images each hash stands for
        self.vectors: list[np.ndarray] = []
        self.saved_images = 0
        self.broken = False  # a write failed: never try again in this run
        self.since = time.monotonic()

    def add(self, hashes: list[str], images: list[int], vectors: np.ndarray) -> None:
        if not self.hashes:
            self.since = time.monotonic()
        self.hashes.extend(hashes)
        self.images.extend(images)
        self.vectors.append(vectors)
        if len(self.hashes) >= SHARD_SIZE or time.monotonic() - self.since >= FLUSH_SECONDS:
            self.flush()

    def flush(self) -> None:
        if self.broken or not self.hashes:
            return
        rows = np.concatenate(self.vectors) if len(self.vectors) > 1 else self.vectors[0]
        self.vectors = [rows]
        while self.hashes:
            n = min(SHARD_SIZE, len(self.hashes))
            try:
                self.cache.store(self.cache_key, self.hashes[:n], rows[:n])
            except VPRInputError:
                self.broken = True
                raise
            self.saved_images += sum(self.images[:n])
            del self.hashes[:n], self.images[:n]
            rows = rows[n:]
            self.vectors = [rows]
        self.vectors = []


def fingerprint(descriptors: np.ndarray) -> str:
    """sha256 hex of an array's shape, dtype and bytes: a content key for caching results."""
    array = np.ascontiguousarray(descriptors)
    digest = hashlib.sha256(f"{array.shape}|{array.dtype.str}|".encode())
    digest.update(memoryview(array).cast("B") if array.size else b"")
    return digest.hexdigest()


def _name_files(paths: Sequence[Path]) -> str:
    shown = ", ".join(str(p) for p in paths[:NAMED_IN_ERRORS])
    more = len(paths) - NAMED_IN_ERRORS
    return f"{shown} and {more} more" if more > 0 else shown


def _check_options(paths: Sequence[Path], batch_size: int, workers: int) -> None:
    if len(paths) == 0:
        raise VPRInputError("paths: no images given; choose a dataset or traversal that holds images")
    if not isinstance(batch_size, int) or batch_size < 1:
        raise VPRInputError(f"batch_size={batch_size!r}: must be a whole number >= 1")
    if not isinstance(workers, int) or workers < 1:
        raise VPRInputError(f"workers={workers!r}: must be a whole number >= 1")


def normalise_rows(raw: np.ndarray, paths: Sequence[Path], extractor: Extractor) -> np.ndarray:
    """``(B, D)`` model output -> unit rows; raises naming the images whose row is zero or not finite."""
    if raw.shape != (len(paths), extractor.dim):
        raise VPRInputError(
            f"descriptor {extractor.name!r}: forward() returned shape {raw.shape} for {len(paths)} images, "
            f"expected ({len(paths)}, {extractor.dim}); fix the extractor"
        )
    # float64 norms: float32 squares overflow for rows with entries above ~1e19.
    norms = np.linalg.norm(raw.astype(np.float64), axis=1)
    bad = ~np.isfinite(raw).all(axis=1) | ~(norms >= MIN_NORM)
    if bad.any():
        culprits = [p for p, b in zip(paths, bad) if b]
        raise VPRInputError(
            f"{len(culprits)} image(s) get a zero or NaN descriptor from {extractor.name!r}: "
            f"{_name_files(culprits)}; the image is blank or the extractor failed on it: "
            "remove the image or choose another descriptor"
        )
    return (raw / norms[:, None]).astype(np.float32)


def hash_paths(paths: Sequence[Path], pool: ThreadPoolExecutor) -> list[str]:
    """Content hashes (:func:`hash_file`) of ``paths``, in order, ``HASH_CHUNK`` files per task of ``pool``.

    Raises:
        VPRInputError: naming the first file that is missing or unreadable.
    """
    chunks = [paths[lo : lo + HASH_CHUNK] for lo in range(0, len(paths), HASH_CHUNK)]
    return [h for part in pool.map(lambda chunk: [hash_file(p) for p in chunk], chunks) for h in part]


def renormalise_in_place(vectors: np.ndarray) -> None:
    """Divide the rows of ``vectors`` that are off unit length by more than 1e-6 by their norm.

    For cache hits: float16 shards come back a little off unit length; rows within 1e-6
    (every row of a float32 shard) are left bit-exact, so a cached run equals the run
    that filled the cache. Norms and divisions are float32, ``RENORMALISE_BYTES`` of
    rows at a time, so no temporary the size of ``vectors`` is made.

    Args:
        vectors: ``(N, D)`` float32 or float16, writable; changed in place.
    """
    step = max(1, RENORMALISE_BYTES // (4 * max(vectors.shape[1], 1)))
    for lo in range(0, len(vectors), step):
        chunk = np.asarray(vectors[lo : lo + step], dtype=np.float32)  # a view when float32
        norms = np.linalg.norm(chunk, axis=1)
        off = np.flatnonzero(np.abs(norms - 1) > 1e-6)
        if len(off):
            vectors[lo + off] = chunk[off] / norms[off, None]


def forward_images(images: list[np.ndarray], extractor: Extractor) -> np.ndarray:
    """``extractor.forward`` on loaded images, one call per distinct image shape (:func:`forward_by_shape`)."""
    return forward_by_shape(images, lambda group: extractor.forward(np.stack(group)), extractor.dim)


def extract_descriptors(
    paths: Sequence[Path],
    extractor: Extractor,
    *,
    cache: DescriptorCache | None = None,
    batch_size: int = 32,
    workers: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    dtype: str = "float32",
    decode: str = "auto",
) -> np.ndarray:
    """Descriptors of ``paths``, one L2-normalised row per image.

    Images whose content is cached for ``extractor.cache_key`` are not decoded; images
    with identical bytes are computed once. The others are decoded by ``workers``
    threads (PIL releases the GIL) up to ``PREFETCH_BATCHES`` batches
    (``PREFETCH_BATCHES_GPU`` for a model on a GPU) ahead of the forward pass, which
    runs in the calling thread, ``batch_size`` images at a time (split by image shape
    when an extractor keeps the aspect ratio). With ``decode="device"`` the threads read
    the JPEGs' bytes instead, and one more thread decodes, resizes and normalises each
    batch on the extractor's device, in order, up to the same number of batches ahead
    (:func:`~vpr_explorer.descriptors.device_decode.device_inputs`); other files are
    loaded by the threads as with ``"cpu"``. Either way the descriptors go to the same
    cache key: the two paths agree to a cosine above 0.9999.

    With a cache, the cache folder is checked first (before any image is read), then
    cleared of what killed writers left in it (:meth:`DescriptorCache.remove_stale`).
    New vectors reach it as the run goes: a shard every ``SHARD_SIZE`` vectors or
    ``FLUSH_SECONDS``, and the finished batches before any error or interruption
    propagates, so running again computes only what is missing. Only vectors that
    passed the checks are cached.

    New vectors are normalised in float32 and then stored in the result as ``dtype``;
    what reaches the cache is the float32 vectors (the cache's own ``dtype`` decides how
    they are stored). Cache hits are read straight into the result in ``dtype``: when
    every image is a hit the lookup's array is the result, so a float16 run never holds
    a float32 copy of it. float32 hits from float16 shards are brought back to unit
    length (:func:`renormalise_in_place`). float16 hits are not: rounded back to float16,
    renormalised rows come out as they went in (~1e-5 off unit length either way), and
    leaving them keeps a cached float16 run equal to the run that filled the cache,
    whatever the cache's storage dtype.

    Args:
        paths: image files; repeats allowed.
        workers: decoding threads; default ``settings.default_workers()``.
        progress: ``progress(done, total)`` in images. The first call's ``done`` is the
            number of images found in the cache (not computed in this run).
        dtype: ``"float32"`` (default) or ``"float16"``: the result's dtype. float16
            halves its memory, at ~1e-3 relative error in the entries.
        decode: ``"cpu"``: PIL in the decoding threads; ``"device"``: JPEGs on the
            extractor's device (a CPU device too), for torch extractors with a recipe;
            ``"auto"`` (default): ``"device"`` when the extractor has a recipe and runs
            on CUDA, else ``"cpu"``.

    Returns:
        ``(len(paths), extractor.dim)`` in ``dtype``, read-only, unit rows (to float16
        precision for float16).

    Raises:
        VPRInputError: no paths, a bad option (named, ``dtype`` and ``decode`` included;
            ``decode="device"`` for an extractor without a recipe), a cache folder
            that cannot be written (named, before any work), an unreadable image
            (named), or images whose descriptor is zero or not finite (named).
        ExtractionInterrupted: on Ctrl-C, saying how many descriptors are cached.
    """
    if isinstance(paths, (str, Path)):
        raise VPRInputError(f"paths={str(paths)!r}: give a list of image files, not a single path")
    paths = [Path(p) for p in paths]
    workers = default_workers() if workers is None else workers
    _check_options(paths, batch_size, workers)
    dtype = check_dtype(dtype)
    on_device = use_device(decode, extractor)
    if cache is not None:
        cache.check_writable()
        cache.remove_stale(extractor.cache_key)
    total = len(paths)
    out: np.ndarray | None = None

    with (ThreadPoolExecutor(max_workers=workers, thread_name_prefix="vpr-decode") as pool,
          ThreadPoolExecutor(max_workers=1, thread_name_prefix="vpr-device-feed") as feeder):
        if cache is not None:
            # Files are hashed HASH_CHUNK per task: one task per file costs more in thread
            # hand-offs than hashing a small image (110k Nordland-size PNGs: 10 s -> ~2 s).
            hashes = hash_paths(paths, pool)
        else:
            # Without a cache there is nothing to key, so skip reading every file twice;
            # the path stands in for the content.
            hashes = [str(p) for p in paths]
        # unique content -> the images that have it
        groups: dict[str, list[int]] = {}
        for i, h in enumerate(hashes):
            groups.setdefault(h, []).append(i)

        done = 0
        if cache is not None:
            # Every path, repeats included, so that when all are hits the lookup's array
            # (in path order) is the result, with no second copy.
            index, vectors = cache.lookup(extractor.cache_key, hashes, extractor.dim, dtype=dtype)
            if len(index):
                if dtype == "float32":
                    renormalise_in_place(vectors)
                if len(index) == total:
                    out = vectors
                else:
                    out = np.empty((total, extractor.dim), dtype=dtype)
                    out[index] = vectors
                del vectors
                # A hash's images are all hits or all misses.
                for i in index.tolist():
                    groups.pop(hashes[i], None)
                done = len(index)
        if out is None:
            out = np.empty((total, extractor.dim), dtype=dtype)

        todo = list(groups)  # content still to compute, first image of each stands for it
        batches = [todo[i : i + batch_size] for i in range(0, len(todo), batch_size)]
        pending: deque[list[Future[np.ndarray]]] = deque()
        unsaved = _Pending(cache, extractor.cache_key) if cache is not None else None
        hits = done

        submitted = 0
        # On the device path the threads read bytes (or load what is not a JPEG), and the
        # feeder turns each batch, in order, into inputs on the device.
        load = (lambda path: read_source(path, extractor)) if on_device else extractor.load
        fed: deque[Future[list]] = deque()

        def feed(reads: list[Future], batch_paths: list[Path]) -> list:
            return device_inputs([f.result() for f in reads], batch_paths, extractor)

        def submit_up_to(end: int) -> None:
            nonlocal submitted
            for batch in batches[submitted:end]:
                reads = [pool.submit(load, paths[groups[h][0]]) for h in batch]
                pending.append(reads)
                if on_device:
                    fed.append(feeder.submit(feed, reads, [paths[groups[h][0]] for h in batch]))
            submitted = max(submitted, min(end, len(batches)))

        on_gpu = str(getattr(extractor, "device", "cpu")).startswith("cuda")
        ahead = PREFETCH_BATCHES_GPU if on_gpu else PREFETCH_BATCHES
        try:
            if progress is not None:
                progress(done, total)
            for b, batch in enumerate(batches):
                # Batches b+1 .. b+ahead decode while this one is forwarded.
                submit_up_to(b + 1 + ahead)
                futures = pending.popleft()
                batch_paths = [paths[groups[h][0]] for h in batch]
                if on_device:
                    raw = forward_tensors(fed.popleft().result(), extractor)
                else:
                    raw = forward_images([f.result() for f in futures], extractor)
                vectors = normalise_rows(raw, batch_paths, extractor)
                for h, v in zip(batch, vectors):
                    out[groups[h]] = v
                    done += len(groups[h])
                if unsaved is not None:
                    unsaved.add(batch, [len(groups[h]) for h in batch], vectors)
                if progress is not None:
                    progress(done, total)
            if unsaved is not None:
                unsaved.flush()
        except BaseException as exc:
            # Stop decoding what no one will use; the pools' exits wait for running loads.
            for f in fed:
                f.cancel()
            for futures in pending:
                for f in futures:
                    f.cancel()
            if unsaved is not None:
                # The finished batches, so that a new run starts after them. Should the
                # write fail too, the error that stopped the run is still the one to report.
                with contextlib.suppress(VPRInputError):
                    unsaved.flush()
            if isinstance(exc, KeyboardInterrupt) and not isinstance(exc, ExtractionInterrupted):
                cached = hits + unsaved.saved_images if unsaved is not None else 0
                raise ExtractionInterrupted(cached, total, with_cache=unsaved is not None) from None
            raise

    out.setflags(write=False)
    return out
