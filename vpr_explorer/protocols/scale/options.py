"""How a run of the blocked pass is set up: ``PassOptions``, checked once for every entry point.

None of these options changes a number: they trade memory and threads for time.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.stats import thread_count, torch_device

#: Default rows per block of the pass: a 4,096 × 4,096 float32 block is 64 MiB.
BLOCK_ROWS = 4096
#: The most rows per block ``PassOptions`` takes.
MOST_BLOCK_ROWS = 40_000
#: Bytes of top-2 table entries kept in RAM; beyond, entries go to a temporary file.
TABLE_MEMORY = 2 * 1024**3
#: The most threads the pass takes when none are asked for (one per usable CPU up to it).
MOST_THREADS = 32


@dataclass(frozen=True)
class PassOptions:
    """The settings of one run of the pass, checked when made.

    Attributes:
        block: rows per block of the pass, 1 to ``MOST_BLOCK_ROWS``; its buffers take about
            4·block·(``blocked_pass.PANEL_ROWS`` + 76) bytes per thread (25 MiB at 4,096).
        table_memory: bytes of top-2 table entries kept in RAM before spilling to a file.
        spill_dir: folder for that temporary file (``None``: the system's temporary folder).
        threads: panels of the pass run side by side, each GEMM in one BLAS thread; ``None``
            is one per usable CPU, at most ``MOST_THREADS``. Read back, always a whole number.
        device: ``None`` (numpy) or a torch device ("cpu", "cuda") for the pass's block
            products; read back, a ``torch.device``.

    Raises:
        VPRInputError: a ``block`` or ``threads`` that is not a whole number in range, or a
            device torch cannot use here.
    """

    block: int = BLOCK_ROWS
    table_memory: int = TABLE_MEMORY
    spill_dir: str | os.PathLike | None = None
    threads: int | None = None
    device: object | None = None

    def __post_init__(self) -> None:
        block = self.block
        if isinstance(block, bool) or not isinstance(block, (int, np.integer)) or not 1 <= block <= MOST_BLOCK_ROWS:
            raise VPRInputError(
                f"block={block!r}: rows per block must be a whole number from 1 to {MOST_BLOCK_ROWS:,} (e.g. 4096)"
            )
        object.__setattr__(self, "block", int(block))
        object.__setattr__(self, "threads", thread_count(self.threads, MOST_THREADS))
        if self.device is not None:
            object.__setattr__(self, "device", torch_device(self.device))
