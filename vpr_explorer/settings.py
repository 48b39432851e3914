"""Where things live on disk: the descriptor cache, the demo route, the real datasets.

Read from the environment so that tests, CI and users can redirect them:

* ``VPR_EXPLORER_CACHE``: cache folder (default ``~/.cache/vpr_explorer``).
* ``VPR_EXPLORER_DATA``: folder holding real datasets (e.g. ``../shared/datasets``).
"""

from __future__ import annotations

import os
from pathlib import Path

CACHE_ENV = "VPR_EXPLORER_CACHE"
DATA_ENV = "VPR_EXPLORER_DATA"


def cache_root() -> Path:
    """The cache folder; created on first use by whoever writes to it."""
    value = os.environ.get(CACHE_ENV)
    return Path(value).expanduser() if value else Path.home() / ".cache" / "vpr_explorer"


def data_root() -> Path | None:
    """The real-datasets folder, or ``None`` when ``VPR_EXPLORER_DATA`` is unset."""
    value = os.environ.get(DATA_ENV)
    return Path(value).expanduser() if value else None
