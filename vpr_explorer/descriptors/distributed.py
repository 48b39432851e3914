"""Descriptor extraction on a Ray cluster, into the same content-keyed cache as the local extractor.

Ray is an optional extra (``pip install ".[ray]"``): this module imports it inside its
functions only, and nothing else in the package imports this module at import time.

The job, for the images of a dataset:

1. the driver hashes every file (:func:`~.extract.hash_paths`, the key of the cache) and
   asks the cache which contents it already holds (:meth:`DescriptorCache.contains`,
   manifests only); images with identical bytes are computed once;
2. the paths of the rest become a Ray Dataset (``ray.data.from_items``); decoding runs in
   Ray tasks (``map_batches`` with a function: the extractor's own ``load``, the recipe of
   the local extractor);
3. the model runs in a pool of actors, one model per actor (``map_batches`` with a class):
   one actor per GPU, each with ``num_gpus=1``, when the cluster has GPUs, else one per
   node. Each actor writes every batch it finishes as one shard of the cache
   (:meth:`DescriptorCache.store`: temporary, fsync, rename; the manifest last), so a
   killed job keeps every shard written before the kill, and running it again computes
   only what is missing. Several jobs may write one cache at once: shards are immutable,
   and equal contents in two shards are equal rows.

Every node must see the images and the cache folder at the same paths (a shared file
system): the driver leaves a probe file in the cache folder, and an actor that cannot
see it stops the job with an error naming the folder and the node.
"""

from __future__ import annotations

import functools
import os
import re
import socket
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vpr_explorer import settings
from vpr_explorer.descriptors.cache import DescriptorCache, check_dtype
from vpr_explorer.descriptors.extract import (
    ExtractionInterrupted,
    default_workers,
    forward_images,
    hash_paths,
    normalise_rows,
)
from vpr_explorer.errors import VPRInputError

RAY_EXTRA = 'pip install ".[ray]"'
#: ``--ray local``: a Ray instance of this machine, started for the job and stopped after it.
LOCAL = "local"
# Images per shard: what one actor call forwards (in batches of ``batch_size``) and then
# writes as one shard. A kill loses at most one such call per actor; fewer images per
# shard mean more files (1.6 million images: 6,250 shards of 256).
SHARD_IMAGES = 256
# Logical CPUs a decoding task and a model actor reserve (Ray's scheduling tokens, not
# limits). They differ so that Ray Data never fuses decoding into the actors (it fuses
# stages of equal resources). The actor's half CPU leaves room for decoding beside it on
# the smallest machine and for two jobs sharing a cluster (their actors never hold every
# CPU while their decoding waits); a CPU actor's model runs on as many threads as its
# node has cores. One CPU per decoding task keeps decoding just ahead of the model
# instead of racing through every image first: on 2 busy CPUs, EfficientNet-Lite0 ran
# 600 GardensPoint images at 0.96 of the local extractor's rate against 0.7 with
# half-CPU decoding tasks (three at once, fighting the model's threads).
DECODE_CPUS = 1.0
ACTOR_CPUS = 0.5
# Seconds to wait for a cluster's address to accept a connection before saying it is
# unreachable (ray.init itself retries for minutes).
CONNECT_TIMEOUT_S = 5.0
# Environment variables the workers need to build the same extractor as the driver
# (users' models, weights); the cache and dataset are passed as absolute paths instead.
_PASSED_ENV_PREFIX = "VPR_EXPLORER_"
_NOT_PASSED_ENV = (settings.CACHE_ENV, settings.DATA_ENV)
# How a worker's VPRInputError reads in the traceback text Ray brings back.
_RAISED_IN_WORKER = re.compile(r"^vpr_explorer\.errors\.VPRInputError: (.+)$", re.MULTILINE)
# Options that say where and how the model runs: decoding never needs them.
_RUNTIME_OPTIONS = ("device", "precision")


@dataclass(frozen=True)
class RayExtraction:
    """What a job did.

    Attributes:
        total: images asked for (repeats included).
        cached: of them, images whose descriptors were in the cache when the job started.
        computed: distinct image contents computed by this job (one per group of
            byte-identical images).
        seconds: wall time of the job after connecting to the cluster (hashing included).
        actors: model actors of the pool.
        gpus: whether each actor had a GPU (``num_gpus=1``).
        cache_key: the extractor's cache key (its folder under ``<cache>/descriptors``).
    """

    total: int
    cached: int
    computed: int
    seconds: float
    actors: int
    gpus: bool
    cache_key: str

    @property
    def images_per_second(self) -> float:
        """Images not cached when the job started, over :attr:`seconds`."""
        return (self.total - self.cached) / self.seconds if self.seconds > 0 else 0.0

    def describe(self) -> str:
        """The final line: images/s, and how many were cached already."""
        where = f"{self.actors} GPU actor(s)" if self.gpus else f"{self.actors} CPU actor(s)"
        todo = self.total - self.cached
        distinct = f", {self.computed} distinct" if self.computed != todo else ""
        return (
            f"{self.total} images: {self.cached} already cached, {todo} computed on Ray "
            f"({where}{distinct}) in {self.seconds:.1f} s, {self.images_per_second:.1f} images/s"
        )


def import_ray():
    """The ``ray`` module with Ray Data, or a ``VPRInputError`` saying how to install it."""
    try:
        import ray
        import ray.data  # noqa: F401  (Ray Data needs pyarrow: the extra pulls ray[data])
    except ImportError as exc:
        raise VPRInputError(
            f"--ray needs Ray, which is not installed here ({exc}): {RAY_EXTRA}, "
            "or leave out --ray to extract with local threads"
        ) from None
    return ray


def _check_reachable(address: str) -> None:
    """Fail at once, naming ``address``, when nothing accepts a connection there."""
    target = address.removeprefix("ray://")
    host, sep, port = target.rpartition(":")
    if not sep or not port.isdigit() or not host:
        raise VPRInputError(
            f"--ray {address}: not a cluster address; give HOST:PORT (the head's address that "
            f"`ray start --head` prints, e.g. 10.0.0.5:6379), 'auto' for the cluster this machine joined, "
            f"or '{LOCAL}'"
        )
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=CONNECT_TIMEOUT_S):
            pass
    except OSError as exc:
        raise VPRInputError(
            f"--ray {address}: the Ray cluster is unreachable ({exc.strerror or type(exc).__name__} within "
            f"{CONNECT_TIMEOUT_S:g} s); check that `ray start --head` runs there and the port is open, "
            f"or use --ray {LOCAL}"
        ) from None


def _job_env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k.startswith(_PASSED_ENV_PREFIX) and k not in _NOT_PASSED_ENV}


def _send_token_if_any() -> None:
    """Have Ray send this user's cluster token when there is one and nothing says otherwise.

    Clusters started by Ray 2.5x (``ray start --head``, ``ray.init()``) require the token
    it saved in ``~/.ray/auth_token``, but a driver joining one sends it only when
    ``RAY_AUTH_MODE=token``; without it the join is refused after 20 s of retries. A
    cluster started with ``RAY_AUTH_MODE=disabled`` needs the same setting here (a driver
    in token mode cannot take its calls): an explicit ``RAY_AUTH_MODE`` is left as it is.
    """
    if "RAY_AUTH_MODE" in os.environ:
        return
    if os.environ.get("RAY_AUTH_TOKEN") or os.environ.get("RAY_AUTH_TOKEN_PATH") or (
        Path.home() / ".ray" / "auth_token"
    ).is_file():
        os.environ["RAY_AUTH_MODE"] = "token"


def connect(address: str | None, *, num_cpus: int | None = None) -> bool:
    """Connect this process to Ray; whether it did (and so should :func:`disconnect` after).

    Args:
        address: ``None`` to use the connection this process already has (a test's, a
            notebook's), else ``"local"`` (start an instance of this machine), ``"auto"``
            (the cluster this machine joined with ``ray start``) or ``HOST:PORT``
            (``ray://HOST:PORT`` for Ray Client).
        num_cpus: with ``"local"``, the CPUs the instance may use (default: all).

    Raises:
        VPRInputError: Ray not installed, or the address unreachable (named).
    """
    if address not in (None, LOCAL, "auto"):
        _check_reachable(address)
        _send_token_if_any()  # before Ray is imported: it reads RAY_AUTH_MODE then
    ray = import_ray()
    if address is None:
        if ray.is_initialized():
            return False
        address = LOCAL
    elif ray.is_initialized():
        raise VPRInputError(f"--ray {address}: this process is already connected to a Ray cluster; drop --ray")
    env = _job_env()
    kwargs = {"runtime_env": {"env_vars": env}} if env else {}
    if address == LOCAL:
        ray.init(address=LOCAL, num_cpus=num_cpus, include_dashboard=False, **kwargs)
        return True
    try:
        ray.init(address=address, **kwargs)
    except ConnectionError as exc:
        raise VPRInputError(f"--ray {address}: cannot connect to a Ray cluster ({exc}); check its token (copy the "
                            f"head's ~/.ray/auth_token here, or set RAY_AUTH_MODE as the cluster was started), "
                            f"or use --ray {LOCAL}") from None
    return True


def disconnect() -> None:
    """Leave the cluster (a ``"local"`` instance stops)."""
    import ray

    ray.shutdown()


# ------------------------------------------------------------------ in the workers


@functools.lru_cache(maxsize=4)
def _worker_extractor(descriptor: str, options: tuple[tuple[str, object], ...]):
    """The extractor, built once per worker process (``get_extractor`` shares models too)."""
    from vpr_explorer.descriptors.registry import get_extractor

    return get_extractor(descriptor, **dict(options))


def _decode(batch: dict[str, np.ndarray], descriptor: str, options: tuple) -> dict[str, np.ndarray]:
    """A Ray task: the extractor's ``load`` on each path; ``image`` ``(B, C, H, W)`` (ragged when shapes differ)."""
    extractor = _worker_extractor(descriptor, options)
    images = [extractor.load(Path(p)) for p in batch["path"]]
    if len({image.shape for image in images}) == 1:
        column = np.stack(images)
    else:  # extractors that keep the aspect ratio: one array per image
        column = np.empty(len(images), dtype=object)
        column[:] = images
    return {"hash": batch["hash"], "path": batch["path"], "image": column}


class _Embed:
    """A Ray actor: one model; forwards each call's images and writes them as one shard."""

    def __init__(self, descriptor: str, options: tuple, cache_root: str, dtype: str, batch_size: int,
                 probe: str, torch_threads: int | None) -> None:
        if not Path(probe).is_file():
            raise VPRInputError(
                f"cache folder {cache_root}: node {socket.gethostname()} does not see the driver's cache folder; put "
                "the cache on a file system every node mounts at the same path and give it with --cache-dir"
            )
        self.extractor = _worker_extractor(descriptor, options)
        if "torch" in sys.modules:  # a torch model (pixels has none)
            import ray
            import torch

            if torch_threads is None and not ray.get_gpu_ids():
                # Ray gives an actor of less than one CPU one thread; decoding runs in other processes.
                torch_threads = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
            if torch_threads is not None:
                torch.set_num_threads(max(1, int(torch_threads)))
        self.cache = DescriptorCache(Path(cache_root), dtype=dtype)
        self.cache.remove_stale(self.extractor.cache_key)  # dead writers of this node
        self.batch_size = batch_size

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        images = list(batch["image"])
        paths = [Path(p) for p in batch["path"]]
        parts = []
        for lo in range(0, len(images), self.batch_size):
            raw = forward_images(images[lo : lo + self.batch_size], self.extractor)
            parts.append(normalise_rows(raw, paths[lo : lo + self.batch_size], self.extractor))
        vectors = np.concatenate(parts)
        self.cache.store(self.extractor.cache_key, [str(h) for h in batch["hash"]], vectors)
        return {"hash": batch["hash"]}


def _describe(descriptor: str, options: tuple) -> tuple[str, int]:
    extractor = _worker_extractor(descriptor, options)
    return extractor.cache_key, extractor.dim


# ------------------------------------------------------------------ the driver


def _user_error(exc: BaseException) -> VPRInputError | None:
    """The ``VPRInputError`` a worker raised, found in the chain Ray wraps it in; ``None`` if none."""
    from ray.exceptions import RayTaskError

    seen: set[int] = set()
    stack = [exc]
    while stack:
        e = stack.pop()
        if e is None or id(e) in seen:
            continue
        seen.add(id(e))
        if isinstance(e, VPRInputError) and not isinstance(e, RayTaskError):
            return e
        stack.extend([getattr(e, "cause", None), e.__cause__, e.__context__])
    # Ray Data wraps a failing stage's exception in a UserCodeException and sends only its
    # traceback's text back to the driver: the error's one-line message is its last line.
    found = _RAISED_IN_WORKER.findall(str(exc))
    return VPRInputError(found[-1].strip()) if found else None


def _pool_shape(ray, actors: int | None) -> tuple[int, bool]:
    """``(actors, gpus)``: one actor per GPU when the cluster has GPUs, else one per node (or ``actors``)."""
    resources = ray.cluster_resources()
    n_gpus = int(resources.get("GPU", 0))
    if actors is not None:
        if isinstance(actors, bool) or not isinstance(actors, int) or actors < 1:
            raise VPRInputError(f"actors={actors!r}: must be a whole number >= 1")
        return (min(actors, n_gpus) if n_gpus else actors), n_gpus > 0
    if n_gpus:
        return n_gpus, True
    nodes = sum(1 for node in ray.nodes() if node.get("Alive") and node.get("Resources", {}).get("CPU", 0) > 0)
    return max(1, nodes), False


def extract_on_ray(
    paths: Sequence[Path],
    descriptor: str,
    *,
    options: dict | None = None,
    cache_root: Path | None = None,
    dtype: str = "float32",
    address: str | None = None,
    batch_size: int = 32,
    shard_images: int = SHARD_IMAGES,
    actors: int | None = None,
    torch_threads: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> RayExtraction:
    """Fill the descriptor cache with ``descriptor``'s vectors of ``paths``, on Ray.

    What is cached already is not recomputed; what this job computes is cached shard by
    shard as the actors finish it, so an interrupted or killed job loses at most one call
    per actor, and :func:`~.extract.extract_descriptors` afterwards (or ``vpr-explorer
    evaluate``) finds everything cached. The vectors are those of the local extractor
    (same ``load``, forward and normalisation), up to the float rounding of another batch
    split or thread count.

    Args:
        paths: image files, seen by every node at these paths; repeats allowed.
        descriptor: an extractor name (``get_extractor``); ``options`` its options
            (``precision``, ...). The model runs on the actor's GPU when it has one.
        cache_root: the cache folder (default ``settings.cache_root()``), seen by every
            node at this path.
        dtype: storage dtype of new shards, as ``DescriptorCache(dtype=...)``.
        address: see :func:`connect`; ``None`` uses this process's connection, or starts
            a local instance when there is none.
        batch_size: images per forward pass.
        shard_images: images per actor call, written as one shard.
        actors: model actors (default: one per GPU, else one per node).
        torch_threads: intra-op threads of each actor's model (default: a CPU actor
            takes as many as its node has cores; a GPU actor keeps Ray's setting).
        progress: ``progress(done, total)`` in images; the first call's ``done`` counts
            the images found in the cache.

    Returns:
        :class:`RayExtraction`.

    Raises:
        VPRInputError: Ray missing, an unreachable cluster, a bad option, an unwritable
            cache folder, or what a worker raised (an unreadable image, a zero descriptor),
            named.
        ExtractionInterrupted: on Ctrl-C, saying how many descriptors are cached.
    """
    from vpr_explorer.descriptors.registry import extractor_options

    if isinstance(paths, (str, Path)):
        raise VPRInputError(f"paths={str(paths)!r}: give a list of image files, not a single path")
    paths = [Path(p).expanduser().absolute() for p in paths]
    if not paths:
        raise VPRInputError("paths: no images given; choose a dataset or traversal that holds images")
    for name, value in (("batch_size", batch_size), ("shard_images", shard_images)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise VPRInputError(f"{name}={value!r}: must be a whole number >= 1")
    dtype = check_dtype(dtype, "dtype", "cache storage type")
    options = dict(options or {})
    accepted = extractor_options(descriptor)
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        raise VPRInputError(f"descriptor {descriptor!r} has no option {', '.join(unknown)}: it accepts "
                            f"{', '.join(accepted) or 'none'}")
    model_options = tuple(sorted(options.items()))
    # Decoding needs the recipe, not the model's device: build it on the CPU.
    decode_options = {k: v for k, v in options.items() if k not in _RUNTIME_OPTIONS}
    if "device" in accepted:
        decode_options["device"] = "cpu"
    decode_options = tuple(sorted(decode_options.items()))
    cache = DescriptorCache(cache_root, dtype=dtype)
    cache.check_writable()
    root = cache.root.absolute()

    owns = connect(address)
    ray = import_ray()
    probe: Path | None = None
    try:
        start = time.perf_counter()
        n_actors, gpus = _pool_shape(ray, actors)
        actor_resources = {"num_cpus": ACTOR_CPUS, "num_gpus": 1 if gpus else 0}
        # The key as the actors will see it (precision, device, weights), and any reason the
        # extractor cannot run there, asked of a worker while the driver hashes the files
        # (that worker, its modules imported, then serves decoding tasks).
        described = ray.remote(_describe).options(**actor_resources).remote(descriptor, model_options)
        with ThreadPoolExecutor(max_workers=default_workers(), thread_name_prefix="vpr-hash") as pool:
            hashes = hash_paths(paths, pool)
        try:
            cache_key, _dim = ray.get(described)
        except Exception as exc:
            raise _user_error(exc) or exc from None
        cache.remove_stale(cache_key)
        groups: dict[str, list[int]] = {}
        for i, h in enumerate(hashes):
            groups.setdefault(h, []).append(i)
        unique = list(groups)
        todo = [h for h, hit in zip(unique, cache.contains(cache_key, unique)) if not hit]
        total = len(paths)
        cached = total - sum(len(groups[h]) for h in todo)
        done = cached
        if progress is not None:
            progress(done, total)
        if todo:
            folder = cache.folder / cache_key
            folder.mkdir(parents=True, exist_ok=True)
            # A temporary's name: should the driver be killed, remove_stale deletes it.
            probe = folder / settings.temporary_name("ray-probe")
            probe.write_bytes(b"")
            items = [{"path": str(paths[groups[h][0]]), "hash": h} for h in todo]
            ds = ray.data.from_items(items, override_num_blocks=max(1, len(items) // batch_size))
            ds = ds.map_batches(_decode, batch_size=batch_size, num_cpus=DECODE_CPUS,
                                fn_kwargs={"descriptor": descriptor, "options": decode_options})
            ds = ds.map_batches(
                _Embed,
                batch_size=shard_images,
                compute=ray.data.ActorPoolStrategy(size=n_actors),
                fn_constructor_kwargs={"descriptor": descriptor, "options": model_options, "cache_root": str(root),
                                       "dtype": dtype, "batch_size": batch_size, "probe": str(probe),
                                       "torch_threads": torch_threads},
                **actor_resources,
            )
            try:
                for out in ds.iter_batches(batch_size=None, batch_format="numpy"):
                    done += sum(len(groups[str(h)]) for h in out["hash"])
                    if progress is not None:
                        progress(done, total)
            except KeyboardInterrupt:
                # What the actors wrote before the interrupt is kept: count it from the cache.
                now = cache.contains(cache_key, unique)
                raise ExtractionInterrupted(sum(len(groups[h]) for h, hit in zip(unique, now) if hit), total) from None
            except Exception as exc:
                raise _user_error(exc) or exc from None
        return RayExtraction(total=total, cached=cached, computed=len(todo), seconds=time.perf_counter() - start,
                             actors=n_actors, gpus=gpus, cache_key=cache_key)
    finally:
        if probe is not None:
            probe.unlink(missing_ok=True)
        if owns:
            disconnect()
