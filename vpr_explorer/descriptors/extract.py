"""Images -> L2-normalised descriptors, through the cache, decoding in parallel with the model."""

from __future__ import annotations

import hashlib
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np

from vpr_explorer.descriptors.base import Extractor
from vpr_explorer.descriptors.cache import DescriptorCache, hash_file
from vpr_explorer.errors import VPRInputError

# Batches decoded ahead of the one in the model: enough to keep the model fed while the
# decoders work, few enough that memory stays at a few batches (a 224x224 float32 image
# is 0.6 MB).
PREFETCH_BATCHES = 2
# New vectors are written in shards of this many once the whole run has succeeded:
# nothing is cached from a failed run (issue: a failed run must never leave state behind).
SHARD_SIZE = 4096
MIN_NORM = 1e-12
NAMED_IN_ERRORS = 3


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


def _normalise_rows(raw: np.ndarray, paths: Sequence[Path], extractor: Extractor) -> np.ndarray:
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


def extract_descriptors(
    paths: Sequence[Path],
    extractor: Extractor,
    *,
    cache: DescriptorCache | None = None,
    batch_size: int = 32,
    workers: int = 2,
    progress: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """Descriptors of ``paths``, one L2-normalised row per image.

    Images whose content is cached for ``extractor.cache_key`` are not decoded; images
    with identical bytes are computed once. The others are decoded by ``workers``
    threads (PIL releases the GIL) up to ``PREFETCH_BATCHES`` batches ahead of the
    forward pass, which runs in the calling thread, ``batch_size`` images at a time.
    New vectors reach the cache only after every batch passed the checks, in shards of
    ``SHARD_SIZE``; a failing run writes nothing.

    Args:
        paths: image files; repeats allowed.
        progress: ``progress(done, total)`` in images; cache hits count as done at once.

    Returns:
        ``(len(paths), extractor.dim)`` float32, read-only, unit rows.

    Raises:
        VPRInputError: no paths, a bad option, an unreadable image (named), or images
            whose descriptor is zero or not finite (named).
    """
    if isinstance(paths, (str, Path)):
        raise VPRInputError(f"paths={str(paths)!r}: give a list of image files, not a single path")
    paths = [Path(p) for p in paths]
    _check_options(paths, batch_size, workers)
    total = len(paths)
    out = np.empty((total, extractor.dim), dtype=np.float32)

    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="vpr-decode") as pool:
        if cache is not None:
            hashes = list(pool.map(hash_file, paths))
        else:
            # Without a cache there is nothing to key, so skip reading every file twice;
            # the path stands in for the content.
            hashes = [str(p) for p in paths]
        # unique content -> the images that have it
        groups: dict[str, list[int]] = {}
        for i, h in enumerate(hashes):
            groups.setdefault(h, []).append(i)
        unique = list(groups)

        done = 0
        if cache is not None:
            hits = cache.lookup(extractor.cache_key, unique, extractor.dim)
            if len(hits.index):
                vectors = hits.vectors
                # float16 shards come back a little off unit length; float32 ones are left
                # bit-exact so a cached run equals the run that filled the cache.
                norms = np.linalg.norm(vectors, axis=1, keepdims=True)
                vectors = np.where(np.abs(norms - 1) > 1e-6, vectors / norms, vectors).astype(np.float32)
                for k, u in enumerate(hits.index):
                    rows = groups.pop(unique[u])
                    out[rows] = vectors[k]
                    done += len(rows)
        if progress is not None:
            progress(done, total)

        todo = list(groups)  # content still to compute, first image of each stands for it
        batches = [todo[i : i + batch_size] for i in range(0, len(todo), batch_size)]
        pending: deque[list[Future[np.ndarray]]] = deque()
        unsaved_hashes: list[str] = []
        unsaved_vectors: list[np.ndarray] = []

        def submit(batch: list[str]) -> None:
            pending.append([pool.submit(extractor.load, paths[groups[h][0]]) for h in batch])

        try:
            for batch in batches[:PREFETCH_BATCHES]:
                submit(batch)
            for b, batch in enumerate(batches):
                futures = pending.popleft()
                if b + PREFETCH_BATCHES < len(batches):
                    submit(batches[b + PREFETCH_BATCHES])
                images = np.stack([f.result() for f in futures])
                batch_paths = [paths[groups[h][0]] for h in batch]
                vectors = _normalise_rows(np.asarray(extractor.forward(images)), batch_paths, extractor)
                for h, v in zip(batch, vectors):
                    out[groups[h]] = v
                    done += len(groups[h])
                if cache is not None:
                    unsaved_hashes.extend(batch)
                    unsaved_vectors.append(vectors)
                if progress is not None:
                    progress(done, total)
        except BaseException:
            # Stop decoding what no one will use; the pool's exit waits for running loads.
            for futures in pending:
                for f in futures:
                    f.cancel()
            raise
        if cache is not None and unsaved_hashes:
            new = np.concatenate(unsaved_vectors)
            for lo in range(0, len(unsaved_hashes), SHARD_SIZE):
                cache.store(extractor.cache_key, unsaved_hashes[lo : lo + SHARD_SIZE], new[lo : lo + SHARD_SIZE])

    out.setflags(write=False)
    return out
