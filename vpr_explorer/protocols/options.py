"""How a protocol run is set up: ``ProtocolOptions``, one value checked once, whichever protocol reads it.

Every protocol (``evaluation.paper_protocol``, ``open_set_protocol``, ``retrieval_protocol``,
``scale.fast_paper_protocol``) and every caller of them (``pipeline.run_protocol``, the
command line, the app, a sweep's cells) takes its settings as one ``ProtocolOptions``; a
protocol reads the fields it needs and leaves the others. The defaults below are the
paper's where it has one (50 random splits, Recall@1/3/5/10) and the command line's help
states them from here.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import MAX_FRAMES
from vpr_explorer.method.stats import thread_count, torch_device

#: Random splits of the paper and open-set protocols: the paper's R.
RUNS = 50
#: The most random splits a run takes: each split keeps its own thresholds and outcomes, so
#: memory and time grow with runs.
MAX_RUNS = 1000
#: Seed of the splits (and of the automatic θ's pooled sample).
SEED = 0
MAX_SEED = 2**63 - 1
#: Share of places the open set holds out of the database in each split (the authors' later work).
UNKNOWN_SHARE = 0.3
#: The K of Recall@K (the paper's).
KS = (1, 3, 5, 10)
#: The k of θ_p(k) = θ_p + k·s_p the open set's trade-off sweeps (k = 0 is the paper's θ_p).
K_GRID = (-1.0, -0.5, 0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0)
#: Rows per block of the fast paper protocol's pass: a 4,096 × 4,096 float32 block is 64 MiB.
BLOCK_ROWS = 4096
#: The most rows per block the pass takes.
MOST_BLOCK_ROWS = 40_000
#: Bytes of the pass's top-2 table kept in RAM; beyond, entries go to a temporary file.
TABLE_MEMORY = 2 * 1024**3
#: The most threads the pass takes when none are asked for (one per usable CPU up to it).
MOST_THREADS = 32


def check_whole(name: str, value: object, *, low: int, high: int, why: str = "") -> int:
    """``value`` as an ``int`` in ``[low, high]``, or a ``VPRInputError`` naming ``name`` and the limit."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise VPRInputError(f"{name}={value!r}: must be a whole number from {low:,} to {high:,}")
    if not low <= value <= high:
        limit = f"{low:,} or more" if value < low else f"{high:,} or less"
        raise VPRInputError(f"{name}={value}: must be {limit}{why}")
    return int(value)


def check_finite(name: str, value: object, *, low: float | None = None, high: float | None = None,
                 example: str = "") -> float:
    """``value`` as a finite ``float`` strictly inside ``(low, high)`` where given, or a ``VPRInputError``."""
    ok = not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating))
    if ok and not np.isfinite(value):
        ok = False
    what = "a finite number" + (f" between {low:g} and {high:g}" if low is not None and high is not None else "")
    if ok and ((low is not None and value <= low) or (high is not None and value >= high)):
        ok = False
    if not ok:
        raise VPRInputError(f"{name}={value!r}: must be {what}{f' (e.g. {example})' if example else ''}")
    return float(value)


def _numbers(name: str, values: object, example: str) -> tuple:
    """``values`` as a tuple (one value alone is a tuple of one), refused when empty."""
    items = tuple(values) if isinstance(values, Sequence | np.ndarray) and not isinstance(values, str) else (values,)
    if not items:
        raise VPRInputError(f"{name}: give at least one value, e.g. {example}")
    return items


@dataclass(frozen=True)
class ProtocolOptions:
    """The settings of one protocol run, checked when made; read back, each in its normal form.

    Attributes:
        runs: paper and open set: random splits, 1 to ``MAX_RUNS``.
        seed: paper and open set: seed of the splits and of the automatic θ's sample, 0 to ``MAX_SEED``.
        cross_condition: paper and open set: score each query only against training images of
            other traversals.
        unknown_share: open set: share of places held out of the database in each split, in (0, 1).
        k_grid: open set: the k of θ_p + k·s_p its trade-off sweeps (finite; a tuple of floats).
        ks: the K of Recall@K (whole numbers, 1 or more; a tuple of ints).
        user_theta: a global θ of the user's, scored beside the automatic one (finite), or None.
        tolerance: frames of slack (0 to ``places.MAX_FRAMES``): a place holding a frame within
            this many frames of the query's is right too; the authors count 2.
        database: traversal protocol: the database traversals' names (a tuple), or None for the
            dataset's default roles (``traversals.Dataset.default_roles``).
        queries: traversal protocol: the query traversal's name, or None likewise.
        pr: also the precision–recall rows and curves.
        block: fast paper protocol (``scale``): rows per block of its pass, 1 to ``MOST_BLOCK_ROWS``;
            its buffers take about 4·block·(``blocked_pass.PANEL_ROWS`` + 76) bytes per thread.
        table_memory: fast paper protocol: bytes of its top-2 table kept in RAM before spilling to a file.
        spill_dir: fast paper protocol: folder for that file (None: the system's temporary folder).
        threads: fast paper protocol: panels of its pass run side by side, each GEMM in one BLAS
            thread; None is one per usable CPU, at most ``MOST_THREADS``. Read back, a whole number.
        device: fast paper protocol: None (numpy on the CPU) or a torch device ("cpu", "cuda") on
            which its full-set float64 sums run (``scale.full_sums.device_set_sums``) and each panel
            of its pass, its product and bookkeeping (``scale.device_panel``); read back, a
            ``torch.device``.

    No number depends on ``block`` … ``device``: they trade memory and threads for time.

    Raises:
        VPRInputError: naming the field, its value and the limit or the fix.
    """

    runs: int = RUNS
    seed: int = SEED
    cross_condition: bool = False
    unknown_share: float = UNKNOWN_SHARE
    k_grid: tuple[float, ...] = K_GRID
    ks: tuple[int, ...] = KS
    user_theta: float | None = None
    tolerance: int = 0
    database: tuple[str, ...] | None = None
    queries: str | None = None
    pr: bool = False
    block: int = BLOCK_ROWS
    table_memory: int = TABLE_MEMORY
    spill_dir: str | os.PathLike | None = None
    threads: int | None = None
    device: object | None = None

    def __post_init__(self) -> None:
        put = lambda name, value: object.__setattr__(self, name, value)  # noqa: E731 (frozen: set once, here)
        put("runs", check_whole("runs", self.runs, low=1, high=MAX_RUNS,
                                why=" (random splits: each keeps its own thresholds and scores, so memory and time "
                                    f"grow with runs; the paper uses {RUNS})"))
        put("seed", check_whole("seed", self.seed, low=0, high=MAX_SEED))
        put("unknown_share", check_finite("unknown_share", self.unknown_share, low=0, high=1,
                                          example=f"{UNKNOWN_SHARE:g}"))
        put("k_grid", tuple(check_finite("k", k, example="-1 0 0.5 1 2")
                            for k in _numbers("k", self.k_grid, "-1 0 0.5 1 2 for θ_p + k·s_p")))
        put("ks", tuple(check_whole("ks", k, low=1, high=MAX_FRAMES, why=" (Recall@K needs K >= 1)")
                        for k in _numbers("ks", self.ks, "1 5 10")))
        if self.user_theta is not None:
            put("user_theta", check_finite("theta", self.user_theta, example="0.5, a cosine similarity"))
        put("tolerance", check_whole("tolerance", self.tolerance, low=0, high=MAX_FRAMES,
                                     why=" (frames of slack; the authors use 2)"))
        if self.database is not None:
            put("database", _numbers("database", self.database, "day"))
        put("cross_condition", bool(self.cross_condition))
        put("pr", bool(self.pr))
        put("block", check_whole("block", self.block, low=1, high=MOST_BLOCK_ROWS,
                                 why=" (rows per block of the pass, e.g. 4096)"))
        put("threads", thread_count(self.threads, MOST_THREADS))
        if self.device is not None:
            put("device", torch_device(self.device))
