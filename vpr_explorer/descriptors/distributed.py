"""Descriptor extraction on a Ray cluster, into the same content-keyed cache as the local extractor.

Ray is an optional extra (``pip install ".[ray]"``): this module imports it inside its
functions only, and nothing else in the package imports this module at import time.

The job, for the images of a dataset:

1. the driver hashes every file (:func:`~.extract.hash_paths`, the key of the cache);
   images with identical bytes are computed once. When the cache holds shards of the
   descriptor (of any version or precision), a worker meanwhile builds the extractor and
   answers with its cache key (:func:`_describe`), and the driver asks the cache which
   contents it holds already under that key (:meth:`DescriptorCache.contains`, manifests
   only). When it holds none, every content is to compute: the job goes on at once, and
   the actors' answers carry the key;
2. the paths (and content hashes) of the rest become a Ray Dataset (``ray.data.from_items``),
   in blocks of ``shard_images``;
3. a pool of actors (``map_batches`` with a class), one model each, decodes and forwards
   each block as the local extractor does (:func:`~.extract.extract_descriptors`: decoding
   threads one batch ahead of the forward pass), so only paths travel and decoded pixels
   never cross the object store. One actor per GPU (``num_gpus=1``) when the cluster has
   GPUs, else one per node holding the node's CPUs (:func:`_pool_shape`). Each actor
   writes every block it finishes as one shard of the cache (:meth:`DescriptorCache.store`:
   temporary, fsync, rename; the manifest last), so a killed job keeps every shard written
   before the kill, and running it again computes only what is missing. Several jobs may
   write one cache at once: shards are immutable, and equal contents in two shards are
   equal rows.

Every node must see the images and the cache folder at the same paths (a shared file
system): the driver leaves a probe file in the cache folder, and an actor that cannot
see it stops the job with an error naming the folder and the node.
"""

from __future__ import annotations

import functools
import logging
import os
import re
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vpr_explorer import settings
from vpr_explorer.descriptors.cache import DescriptorCache, check_dtype, is_stale
from vpr_explorer.descriptors.extract import ExtractionInterrupted, extract_descriptors, hash_paths
from vpr_explorer.errors import VPRInputError

RAY_EXTRA = 'pip install ".[ray]"'
#: ``--ray local``: a Ray instance of this machine, started for the job and stopped after it.
LOCAL = "local"
# Images per shard: what one actor call decodes and forwards (in batches of ``batch_size``)
# and then writes as one shard. A kill loses at most one such call per actor; fewer images per
# shard mean more files (1.6 million images: 6,250 shards of 256).
SHARD_IMAGES = 256
# The name of the empty file the driver leaves in the cache folder for the actors to find
# (a temporary's name: the next job removes a killed driver's).
PROBE = "ray-probe"
# Seconds to wait for a cluster's address to accept a connection before saying it is
# unreachable (ray.init itself retries for minutes).
CONNECT_TIMEOUT_S = 5.0
# Seconds to wait, once connected, for the address to answer as a Ray head does: its GCS is
# a gRPC server, which answers the HTTP/2 client preface with a SETTINGS frame at once.
PROBE_TIMEOUT_S = 3.0
# Seconds ray.init may take to join a cluster whose address answered as HTTP/2 (a GCS that
# does not take the join, another gRPC server, an SSH tunnel Ray does not go through: ray.init
# retries for minutes, deaf to Ctrl-C meanwhile).
JOIN_TIMEOUT_S = 10.0
# What a client sends first on an HTTP/2 connection: the preface and an empty SETTINGS frame.
_H2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])
_HEAD_WHAT = ("give the address that `ray start --head` prints (HOST:6379 by default; ray://HOST:10001 for Ray "
              f"Client), or use --ray {LOCAL}")
# Environment variables the workers need to build the same extractor as the driver
# (users' models, weights); the cache and dataset are passed as absolute paths instead.
_PASSED_ENV_PREFIX = "VPR_EXPLORER_"
_NOT_PASSED_ENV = (settings.CACHE_ENV, settings.DATA_ENV)
# How a worker's VPRInputError reads in the traceback text Ray brings back.
_RAISED_IN_WORKER = re.compile(r"^vpr_explorer\.errors\.VPRInputError: (.+)$", re.MULTILINE)


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
        cpus: logical CPUs each actor reserved (it decodes, and a CPU actor runs its
            model, on as many threads).
        cache_key: the extractor's cache key (its folder under ``<cache>/descriptors``).
    """

    total: int
    cached: int
    computed: int
    seconds: float
    actors: int
    gpus: bool
    cpus: float
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
    """Fail at once, naming ``address``, when nothing accepts a connection there or what answers is no Ray head.

    A Ray head's GCS (and a Ray Client server) is a gRPC server: it answers the HTTP/2 client
    preface with a SETTINGS frame. Anything else (an HTTP/1 server, silence, a closed
    connection, other bytes) is named in the error; ray.init would retry it for minutes.
    """
    target = address.removeprefix("ray://")
    host, sep, port = target.rpartition(":")
    if not sep or not port.isdigit() or not host:
        raise VPRInputError(
            f"--ray {address}: not a cluster address; give HOST:PORT (the head's address that "
            f"`ray start --head` prints, e.g. 10.0.0.5:6379), 'auto' for the cluster this machine joined, "
            f"or '{LOCAL}'"
        )
    host = host.strip("[]")
    try:
        with socket.create_connection((host, int(port)), timeout=CONNECT_TIMEOUT_S) as sock:
            if _uses_tls():
                return  # a TLS head answers a TLS handshake, not the plain preface
            answer, ended = _answer_to_preface(sock)
    except OSError as exc:
        raise VPRInputError(
            f"--ray {address}: the Ray cluster is unreachable ({exc.strerror or type(exc).__name__} within "
            f"{CONNECT_TIMEOUT_S:g} s); check that `ray start --head` runs there and the port is open, "
            f"or use --ray {LOCAL}"
        ) from None
    if _is_h2_settings(answer):
        return
    raise VPRInputError(f"--ray {address}: not a Ray cluster: {_what_answered(host, int(port), answer, ended)}; a "
                        f"Ray head answers as a gRPC (HTTP/2) server: {_HEAD_WHAT}")


def _uses_tls() -> bool:
    """Whether Ray is told to speak TLS to the cluster (``RAY_USE_TLS``)."""
    return os.environ.get("RAY_USE_TLS", "0").strip().lower() in ("1", "true", "yes")


def _read_some(sock: socket.socket, seconds: float, enough: Callable[[bytes], bool]) -> tuple[bytes, bool]:
    """Bytes read from ``sock`` until they are ``enough``, the peer closes, or ``seconds`` pass.

    Returns the bytes and whether the peer closed the connection.
    """
    deadline = time.monotonic() + seconds
    data = b""
    while not enough(data):
        left = deadline - time.monotonic()
        if left <= 0:
            return data, False
        sock.settimeout(left)
        try:
            chunk = sock.recv(4096)
        except TimeoutError:
            return data, False
        except ConnectionResetError:
            return data, True
        if not chunk:
            return data, True
        data += chunk
    return data, False


def _http_head_read(data: bytes) -> bool:
    """Whether ``data`` holds an HTTP/1 response's whole head (or as much as is worth reading)."""
    return b"\r\n\r\n" in data or len(data) >= 4096


def _answer_to_preface(sock: socket.socket) -> tuple[bytes, bool]:
    """What the peer sends back to the HTTP/2 client preface within ``PROBE_TIMEOUT_S``, and whether it closed.

    A frame header's 9 bytes are enough, unless the answer is an HTTP/1 response: then its head.
    """
    try:
        sock.sendall(_H2_PREFACE)
    except OSError:
        return b"", True
    return _read_some(sock, PROBE_TIMEOUT_S,
                      lambda data: _http_head_read(data) if data.startswith(b"HTTP/") else len(data) >= 9)


def _is_h2_settings(data: bytes) -> bool:
    """Whether ``data`` starts with an HTTP/2 SETTINGS frame's header (type 4, stream 0)."""
    return len(data) >= 9 and data[3] == 0x4 and data[5:9] == bytes(4) and int.from_bytes(data[:3], "big") % 6 == 0


def _http_status(data: bytes) -> str | None:
    """``"HTTP/1.0 200 OK, Server: …"`` of an HTTP/1 response's head in ``data``; ``None`` if it is not one."""
    if not data.startswith(b"HTTP/"):
        return None
    lines = data.split(b"\r\n\r\n", 1)[0].decode("latin-1").splitlines()
    server = next((line.split(":", 1)[1].strip() for line in lines[1:] if line.lower().startswith("server:")), None)
    return lines[0].strip()[:80] + (f", Server: {server[:80]}" if server else "")


def _what_answered(host: str, port: int, answer: bytes, ended: bool) -> str:
    """Says what answered the preface ``answer`` (``ended``: then closed), asking again as HTTP/1 if unclear."""
    status = _http_status(answer)
    if status is None and answer and answer[:1] in (b"\x15", b"\x16") and answer[1:2] == b"\x03":
        return ("a TLS server answered there (for a Ray head started with TLS, set RAY_USE_TLS=1 and its "
                "RAY_TLS_* certificate variables here)")
    if status is None and answer:
        # An HTTP/1 server may answer the preface with a bare error page: a plain request names it.
        try:
            with socket.create_connection((host, port), timeout=PROBE_TIMEOUT_S) as sock:
                sock.sendall(f"HEAD / HTTP/1.0\r\nHost: {host}\r\n\r\n".encode())
                status = _http_status(_read_some(sock, PROBE_TIMEOUT_S, _http_head_read)[0])
        except OSError:
            status = None
    if status is not None:
        return f"an HTTP server answered there ({status})"
    if not answer:
        return ("it accepted the connection and closed it without a word" if ended else
                f"it accepted the connection but said nothing within {PROBE_TIMEOUT_S:g} s")
    return f"it answered {answer[:40]!r}"


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
        VPRInputError: Ray not installed, the address unreachable, answered by something
            other than a Ray head, or not joined within ``JOIN_TIMEOUT_S`` (named).
        KeyboardInterrupt: Ctrl-C while joining, at once.
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
    token = (f"check its token (copy the head's ~/.ray/auth_token here, or set RAY_AUTH_MODE as the cluster was "
             f"started), or use --ray {LOCAL}")
    try:
        joined = _init_within(ray, JOIN_TIMEOUT_S, address=address, **kwargs)
    except ConnectionError as exc:
        raise VPRInputError(f"--ray {address}: cannot connect to a Ray cluster ({exc}); {token}") from None
    if not joined:
        if address == "auto":
            what, check = "", "check that `ray start` joined this machine to a running cluster"
        else:
            what = ": it answers as an HTTP/2 server, but Ray's join did not complete"
            check = "check that it is the head's address that `ray start --head` prints"
        raise VPRInputError(f"--ray {address}: no Ray cluster joined within {JOIN_TIMEOUT_S:g} s{what}; {check}, "
                            f"and {token}")
    return True


class _DropRecord:
    """A logging filter dropping the records whose message starts with ``prefix``."""

    def __init__(self, prefix: str) -> None:
        self.prefix = prefix

    def filter(self, record) -> bool:
        return not str(record.msg).startswith(self.prefix)


def _init_within(ray, seconds: float, **init) -> bool:
    """``ray.init(**init)``, waited for ``seconds`` at most and stopped by Ctrl-C; whether it returned in time.

    ray.init retries a GCS that does not take the join for minutes, in C++ code that Python's
    signal handler only reaches between tries (a Ctrl-C took 23 s), so it runs in a thread
    of its own while this one waits. A join given up on (the time was up, or Ctrl-C) that
    completes later is undone there, so that the process is never left joined after it
    was told otherwise. What ray.init raises is raised here.
    """
    lock = threading.Lock()
    finished = threading.Event()
    state: dict = {"abandoned": False, "error": None}

    def join() -> None:
        try:
            ray.init(**init)
        except BaseException as exc:  # raised in the waiting thread below
            state["error"] = exc
        with lock:
            finished.set()
            late = state["abandoned"] and state["error"] is None
        if late:
            ray.shutdown()

    # ray.init sets this SIGTERM handler (SystemExit, so that atexit disconnects) from the main thread only,
    # and warns when it runs in another.
    quiet = _DropRecord("SIGTERM handler is not set")
    worker_log = logging.getLogger("ray._private.worker")
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(signum))
    worker_log.addFilter(quiet)
    try:
        threading.Thread(target=join, name="vpr-ray-init", daemon=True).start()
        finished.wait(seconds)
    finally:
        with lock:
            state["abandoned"] = not finished.is_set()
        if not state["abandoned"]:  # else ray.init goes on, and may yet warn
            worker_log.removeFilter(quiet)
    if state["abandoned"]:
        return False
    if state["error"] is not None:
        raise state["error"]
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


class _Embed:
    """A Ray actor: one model; decodes and forwards each call's images, and writes them as one shard.

    A call is the local extractor on the call's paths (:func:`~.extract.extract_descriptors`
    without a cache: ``threads`` decoding threads one batch ahead of the forward pass),
    so only paths reach the actor and decoded pixels never cross the object store.
    """

    def __init__(self, descriptor: str, options: tuple, cache_root: str, dtype: str, batch_size: int,
                 probe: str, threads: int) -> None:
        if not Path(probe).is_file():
            raise VPRInputError(
                f"cache folder {cache_root}: node {socket.gethostname()} does not see the driver's cache folder; put "
                "the cache on a file system every node mounts at the same path and give it with --cache-dir"
            )
        self.threads = max(1, int(threads))
        self.extractor = _worker_extractor(descriptor, options)
        if "torch" in sys.modules:  # a torch model (pixels has none)
            import torch

            # Ray sets OMP_NUM_THREADS to the actor's whole CPUs; threads says otherwise.
            torch.set_num_threads(self.threads)
        self.cache = DescriptorCache(Path(cache_root), dtype=dtype)
        self.cache.remove_stale(self.extractor.cache_key)  # dead writers of this node
        self.batch_size = batch_size

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        paths = [Path(p) for p in batch["path"]]
        vectors = extract_descriptors(paths, self.extractor, batch_size=self.batch_size, workers=self.threads)
        key = self.extractor.cache_key
        self.cache.store(key, [str(h) for h in batch["hash"]], vectors)
        return {"hash": batch["hash"], "key": np.full(len(paths), key)}


def _describe(descriptor: str, options: tuple) -> tuple[str, int]:
    """A Ray task: ``(cache key, dim)`` of the extractor as a worker builds it, or why it cannot."""
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


@dataclass(frozen=True)
class _Pool:
    """The model actors of a job: how many, and what each reserves and runs on.

    Attributes:
        actors: actors in the pool.
        cpus: logical CPUs each reserves (Ray's scheduling token).
        gpus: whether each reserves a GPU (``num_gpus=1``).
        threads: its decoding threads and its torch model's threads.
    """

    actors: int
    cpus: float
    gpus: bool
    threads: int

    def remote_args(self) -> dict[str, float]:
        return {"num_cpus": self.cpus, "num_gpus": 1 if self.gpus else 0}


def _whole(cpus: float) -> float:
    """Whole CPUs from one up, else hundredths (Ray's fractional resources)."""
    return float(int(cpus)) if cpus >= 1 else int(cpus * 100) / 100


def _pool_shape(nodes: Sequence[dict], actors: int | None = None, threads: int | None = None) -> _Pool:
    """The model actors for a cluster whose live nodes have the resources ``nodes`` (``ray.nodes()``'s).

    With GPUs: one actor per GPU (at most ``actors``), each reserving its GPU and its
    share of its node's CPUs (those of the leanest GPU node), on which it decodes. Without:
    one actor per node, each reserving as many CPUs as the smallest node has, so that it
    decodes and runs its model on that many threads, as the local extractor does, and no
    other work of the cluster is put on its cores meanwhile; nodes with several times as
    many CPUs hold several actors. ``actors`` asks for another number: each then
    reserves the most whole CPUs that lets that many fit on the nodes. ``threads``
    overrides the threads of each (decoding and the model's).

    Raises:
        VPRInputError: a bad ``actors`` or ``threads``, or a cluster without CPUs or GPUs.
    """
    for name, value in (("actors", actors), ("torch_threads", threads)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise VPRInputError(f"{name}={value!r}: must be a whole number >= 1")
    gpu_nodes = [r for r in nodes if r.get("GPU", 0) >= 1]
    cpus = [float(r["CPU"]) for r in nodes if r.get("CPU", 0) > 0]
    if gpu_nodes:
        n_gpus = sum(int(r["GPU"]) for r in gpu_nodes)
        share = _whole(min(r.get("CPU", 0) / int(r["GPU"]) for r in gpu_nodes))
        return _Pool(min(actors, n_gpus) if actors is not None else n_gpus, share, True, threads or max(1, int(share)))
    if not cpus:
        raise VPRInputError("the Ray cluster has no node with CPUs or GPUs: join one with "
                            "`ray start --address HEAD:PORT`")
    if actors is None:
        share = _whole(min(cpus))
        n = sum(int(c // share) for c in cpus)
    else:
        n = actors
        share = _whole(min(min(cpus), sum(cpus) / n))
        while share > 1 and sum(int(c // share) for c in cpus) < n:
            share -= 1
    return _Pool(n, share, False, threads or max(1, int(share)))


def _key_of(ray, described) -> str:
    """The cache key the :func:`_describe` task answered, or the error it raised."""
    try:
        return ray.get(described)[0]
    except Exception as exc:
        raise _user_error(exc) or exc from None


def _holds_shards_of(cache: DescriptorCache, descriptor: str) -> bool:
    """Whether the cache holds a shard of any version or precision of ``descriptor`` (its keys are ``<name>-...``)."""
    from vpr_explorer.descriptors.registry import cache_name

    shards = (p for p in cache.folder.glob(f"{cache_name(descriptor)}-*/*.json") if not p.name.startswith("."))
    return next(shards, None) is not None


class _InterruptSeen:
    """Within ``with``: notes a Ctrl-C (SIGINT) in :attr:`seen`, then raises ``KeyboardInterrupt`` as usual.

    Ray Data's iterator waits on a queue in the calling thread; a ``KeyboardInterrupt``
    raised while it releases the queue's lock surfaces as ``RuntimeError: release unlocked
    lock``, which the flag tells apart from a failed job. Off the main thread (where no
    signal handler can be set) it does nothing.
    """

    def __init__(self) -> None:
        self.seen = False
        self._installed = False
        self._previous = None

    def _handle(self, signum, frame) -> None:
        self.seen = True
        raise KeyboardInterrupt

    def __enter__(self) -> _InterruptSeen:
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
            self._installed = True
        return self

    def __exit__(self, *exc) -> None:
        if self._installed:
            # None: a handler not set from Python; Python's own is the usual one
            signal.signal(signal.SIGINT, self._previous if self._previous is not None else signal.default_int_handler)
            self._installed = False


def _held_now(cache: DescriptorCache, cache_key: str | None, descriptor: str, unique: list[str]) -> np.ndarray:
    """Which of ``unique`` the cache holds for ``cache_key``.

    Before an actor has told the key (``None``): for any key of ``descriptor``; the job
    found no shard of it when it started, so those it holds now are this job's.
    """
    from vpr_explorer.descriptors.registry import cache_name

    keys = [cache_key] if cache_key else sorted(f.name for f in cache.folder.glob(f"{cache_name(descriptor)}-*")
                                                if f.is_dir())
    held = np.zeros(len(unique), dtype=bool)
    for key in keys:
        held |= cache.contains(key, unique)
    return held


def _write_probe(cache: DescriptorCache) -> Path:
    """An empty file in the cache folder that every actor must see; probes of dead drivers removed first."""
    cache.folder.mkdir(parents=True, exist_ok=True)
    now = time.time()
    for old in cache.folder.glob(f".{PROBE}.*.tmp"):
        if is_stale(old, settings.temporary_owner(old.name), now):
            old.unlink(missing_ok=True)
    probe = cache.folder / settings.temporary_name(PROBE)
    probe.write_bytes(b"")
    return probe


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
        actors: model actors (default: one per GPU, else one per node; see
            :func:`_pool_shape`).
        torch_threads: decoding threads of each actor, and its torch model's threads
            (default: as many as the CPUs it reserves).
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
    cache = DescriptorCache(cache_root, dtype=dtype)
    cache.check_writable()
    root = cache.root.absolute()

    owns = connect(address)
    ray = import_ray()
    probe: Path | None = None
    try:
        start = time.perf_counter()
        shape = _pool_shape([n.get("Resources", {}) for n in ray.nodes() if n.get("Alive")], actors, torch_threads)
        described = None
        if _holds_shards_of(cache, descriptor):
            # What is missing depends on the key as the actors will see it (precision, device,
            # weights): asked of a worker while the driver hashes the files (which also says
            # why the extractor cannot run there, if it cannot).
            described = ray.remote(_describe).options(num_cpus=0, num_gpus=1 if shape.gpus else 0).remote(
                descriptor, model_options)
        with ThreadPoolExecutor(max_workers=settings.default_workers(), thread_name_prefix="vpr-hash") as pool:
            hashes = hash_paths(paths, pool)
        groups: dict[str, list[int]] = {}
        for i, h in enumerate(hashes):
            groups.setdefault(h, []).append(i)
        unique = list(groups)
        total = len(paths)
        cache_key: str | None = None
        if described is not None:
            cache_key = _key_of(ray, described)
            cache.remove_stale(cache_key)
            todo = [h for h, hit in zip(unique, cache.contains(cache_key, unique)) if not hit]
        else:
            # No shard of the descriptor, whatever its key: every content is to compute, the
            # actors start at once, and their answers carry the key.
            todo = unique
        cached = total - sum(len(groups[h]) for h in todo)
        done = cached
        if progress is not None:
            progress(done, total)
        if todo:
            probe = _write_probe(cache)
            items = [{"path": str(paths[groups[h][0]]), "hash": h} for h in todo]
            # Blocks of at most shard_images paths (and hashes), each one actor call as it is.
            ds = ray.data.from_items(items, override_num_blocks=-(-len(items) // shard_images))
            ds = ds.map_batches(
                _Embed,
                batch_size=None,
                compute=ray.data.ActorPoolStrategy(size=shape.actors),
                fn_constructor_kwargs={"descriptor": descriptor, "options": model_options, "cache_root": str(root),
                                       "dtype": dtype, "batch_size": batch_size, "probe": str(probe),
                                       "threads": shape.threads},
                **shape.remote_args(),
            )
            interrupted = _InterruptSeen()
            try:
                with interrupted:
                    for out in ds.iter_batches(batch_size=None, batch_format="numpy"):
                        if len(out["key"]):
                            cache_key = str(out["key"][0])
                        done += sum(len(groups[str(h)]) for h in out["hash"])
                        if progress is not None:
                            progress(done, total)
            except Exception as exc:
                # A Ctrl-C that lands inside a lock of Ray Data's comes out as another error.
                if not interrupted.seen:
                    raise _user_error(exc) or exc from None
            except KeyboardInterrupt:
                interrupted.seen = True
            if interrupted.seen:
                # What the actors wrote before the interrupt is kept: count it from the cache.
                now = _held_now(cache, cache_key, descriptor, unique)
                raise ExtractionInterrupted(sum(len(groups[h]) for h, hit in zip(unique, now) if hit), total)
        return RayExtraction(total=total, cached=cached, computed=len(todo), seconds=time.perf_counter() - start,
                             actors=shape.actors, gpus=shape.gpus, cpus=shape.cpus, cache_key=cache_key)
    finally:
        if probe is not None:
            probe.unlink(missing_ok=True)
        if owns:
            disconnect()
