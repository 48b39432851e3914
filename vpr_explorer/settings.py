"""Where things live on disk (the cache, the demo route, the real datasets), and how many threads work by default.

Read from the environment so that tests, CI and users can redirect them:

* ``VPR_EXPLORER_CACHE``: cache folder (default ``~/.cache/vpr_explorer``); the command
  line's ``--cache-dir`` names the same kind of folder. Either way it is the cache
  *root*: descriptors live under ``<root>/descriptors/`` and the demo route under
  ``<root>/demo/``, so one folder is always one cache.
* ``VPR_EXPLORER_DATA``: folder holding real datasets (e.g. ``../shared/datasets``).
* ``VPR_EXPLORER_DEVICE``: where a database fit's two N·D² products run
  (:func:`vpr_explorer.method.stats.fit_device` reads it):
  unset or ``numpy`` (the default), ``auto`` (the GPU when torch sees one, else numpy), or a
  torch device (``cpu``, ``cuda``, ``cuda:N``).

Threads: every pool whose size the caller leaves open takes :func:`default_workers`.
"""

from __future__ import annotations

import os
import re
import socket
import tempfile
import uuid
from pathlib import Path

from vpr_explorer.errors import VPRInputError

MAX_DEFAULT_WORKERS = 8
"""The most threads a pool takes when none are asked for (:func:`default_workers`): on a small CPU
they share the cores with the work they feed; beside a GPU they are what feeds it."""

CACHE_ENV = "VPR_EXPLORER_CACHE"
DATA_ENV = "VPR_EXPLORER_DATA"
DEVICE_ENV = "VPR_EXPLORER_DEVICE"
DESCRIPTORS_FOLDER = "descriptors"
# ``.<name>.<host>.<pid>.<32 hex>.tmp``: who writes a temporary is in its name, so a
# cleaner can tell a dead writer's leftovers from a live writer's file.
_TEMPORARY = re.compile(r"^\.(?P<name>.+)\.(?P<host>[A-Za-z0-9-]{1,32})\.(?P<pid>[0-9]{1,10})\.[0-9a-f]{32}\.tmp$")


def cache_root() -> Path:
    """The cache folder; created on first use by whoever writes to it."""
    value = os.environ.get(CACHE_ENV)
    return Path(value).expanduser() if value else Path.home() / ".cache" / "vpr_explorer"


def descriptor_folder(root: str | os.PathLike[str] | None = None) -> Path:
    """Where descriptor shards live: ``<root>/descriptors``, ``root`` defaulting to :func:`cache_root`."""
    base = Path(root).expanduser() if root is not None else cache_root()
    return base / DESCRIPTORS_FOLDER


def host_tag() -> str:
    """This machine's name as it appears in temporary file names: letters, digits and ``-``, at most 32."""
    return re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname())[:32] or "host"


def temporary_name(name: str) -> str:
    """A hidden, unique name to write ``name``'s bytes under before renaming them into place.

    ``.<name>.<host>.<pid>.<random>.tmp``: the writer is named, see :func:`temporary_owner`.
    """
    return f".{name}.{host_tag()}.{os.getpid()}.{uuid.uuid4().hex}.tmp"


def temporary_owner(file_name: str) -> tuple[str, int] | None:
    """``(host, pid)`` of the process that made a :func:`temporary_name`; ``None`` for other names."""
    match = _TEMPORARY.match(file_name)
    return (match["host"], int(match["pid"])) if match else None


def check_cache_root(root: str | os.PathLike[str] | None = None) -> Path:
    """The cache folder (``root``, else :func:`cache_root`), once it is sure the cache can be written there.

    Creates nothing: finds the nearest part of ``<root>/descriptors`` that exists, which
    must be a folder, and creates (and at once drops) an unnamed temporary file in it,
    the same permission ``mkdir`` and the shard writes will need. Permissions, a
    read-only file system, or a file standing where a folder should be all show up here,
    before any work whose result would be lost. Cheap enough to call at the start of
    every command.

    Returns:
        The cache root, as given (``~`` expanded).

    Raises:
        VPRInputError: naming the folder, why it cannot be written, and the fix.
    """
    base = Path(root).expanduser() if root is not None else cache_root()
    existing = descriptor_folder(base).absolute()
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent  # exists() is False under a file (ENOTDIR) too
    why = None
    if not existing.is_dir():
        why = f"{existing} is a file, where a folder is needed"
    else:
        try:
            # O_TMPFILE where the OS has it: a file without a name, so nothing is ever left behind.
            with tempfile.TemporaryFile(dir=existing):
                pass
        except OSError as exc:
            why = f"cannot create a file in {existing}: {exc.strerror or type(exc).__name__}"
    if why is not None:
        raise VPRInputError(
            f"cache folder {base}: cannot write there ({why}); choose a writable folder with --cache-dir "
            f"(command line) or {CACHE_ENV}"
        )
    return base


def data_root() -> Path | None:
    """The real-datasets folder, or ``None`` when ``VPR_EXPLORER_DATA`` is unset."""
    value = os.environ.get(DATA_ENV)
    return Path(value).expanduser() if value else None


def usable_cpus() -> int:
    """The CPUs this process may run on: its affinity where the OS tells it, else the machine's count; at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def default_workers(cap: int = MAX_DEFAULT_WORKERS) -> int:
    """Threads for a pool when none are asked for: one per usable CPU (:func:`usable_cpus`), at most ``cap``.

    Args:
        cap: the most threads, at least 1.

    Returns:
        A whole number of threads in ``1..cap``.
    """
    return max(1, min(usable_cpus(), cap))
