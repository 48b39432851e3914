"""The labelled images place by place, slot-padded, in blocks of whole places; and their float32 copy.

``make_layout`` orders the rows; ``as_layout32`` gathers the descriptors into that order as
float32, the rows the pass multiplies (and the full-set sums read).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from vpr_explorer.errors import VPRInputError
from vpr_explorer.protocols.evaluation import place_members

#: Most rows a block may have: flat indices into a block's scores are int32 (46,000² < 2³¹).
MAX_BLOCK_ROWS = 46_000
#: Descriptor rows gathered (and converted) at a time outside the pass.
GATHER_ROWS = 8192


@dataclass(frozen=True, eq=False)
class Layout:
    """Labelled images reordered place by place, each place padded to ``slots`` rows, in blocks.

    Inside a block of G places rows run slot-major: row = first_row + slot·G + (place − first),
    so a block's similarity viewed as ``(rows, slots, G)`` or ``(slots, G, cols)`` reduces over
    a place's images along a middle axis. Padding rows are zero descriptors, masked to −inf.

    Attributes:
        places: ``(P,)`` place ids that have images, ascending; "place index" c means places[c].
        slots: the largest place size m; slot k of a place is its k-th image by index.
        block_start: ``(n_blocks + 1,)`` first place index of each block.
        image_of_row: ``(n_rows,)`` image of each layout row, ``-1`` for padding.
        row_of_image: ``(n_images,)`` layout row of each image, ``-1`` for unlabelled frames.
        sizes: ``(P,)`` images per place.
        place_of_row, slot_of_row: ``(n_rows,)`` place index and slot of every row.
    """

    places: np.ndarray
    slots: int
    block_start: np.ndarray
    image_of_row: np.ndarray
    row_of_image: np.ndarray
    sizes: np.ndarray
    place_of_row: np.ndarray
    slot_of_row: np.ndarray

    @property
    def n_blocks(self) -> int:
        return len(self.block_start) - 1

    @property
    def n_rows(self) -> int:
        return len(self.image_of_row)

    @property
    def full_rows(self) -> int:
        """Rows of every block but the last (which may be shorter)."""
        return self.slots * int(self.block_start[1] - self.block_start[0])

    def rows(self, b: int) -> slice:
        """The layout rows of block b."""
        return slice(int(self.block_start[b]) * self.slots, int(self.block_start[b + 1]) * self.slots)

    def place_range(self, b: int) -> slice:
        """The place indices of block b."""
        return slice(int(self.block_start[b]), int(self.block_start[b + 1]))

    def row_of(self, c: np.ndarray, slot: np.ndarray) -> np.ndarray:
        """Layout row of (place index, slot)."""
        return _row_of(self.block_start, self.slots, c, slot)


def _row_of(block_start: np.ndarray, slots: int, c: np.ndarray, slot: np.ndarray) -> np.ndarray:
    blk = np.searchsorted(block_start, c, side="right") - 1
    first = block_start[blk]
    return first * slots + slot * (block_start[blk + 1] - first) + (c - first)


def make_layout(image_place: np.ndarray, n_places: int, block_rows: int) -> Layout:
    """The place-major, slot-padded, blocked layout of the labelled images.

    Blocks hold whole places and about ``block_rows`` rows; all but the last hold the same
    number of places (so a row's block is row // full_rows).

    Args:
        image_place: ``(n_images,)`` place of each image, ``-1`` for a skipped frame.
        n_places: number of place ids.
        block_rows: rows per block, as ``ProtocolOptions.block`` checks it.

    Raises:
        VPRInputError: when the largest place makes a block longer than ``MAX_BLOCK_ROWS``.
    """
    order, starts, sizes = place_members(image_place, n_places)
    places = np.flatnonzero(sizes > 0)
    psize = sizes[places]
    m = int(psize.max())
    n_p = len(places)
    wanted = max(1, -(-n_p * m // int(block_rows)))  # blocks of about block_rows rows
    per_block = -(-n_p // wanted)  # places per block; the last block may hold fewer
    block_start = np.r_[np.arange(0, n_p, per_block), n_p].astype(np.int64)
    n_blocks = len(block_start) - 1
    if m * per_block > MAX_BLOCK_ROWS:
        raise VPRInputError(f"places of {m} images: a block would exceed {MAX_BLOCK_ROWS:,} rows; lower block=")
    place_idx = np.repeat(np.arange(n_p), psize)
    slot = np.arange(len(order)) - np.repeat(starts[places], psize)
    rows = _row_of(block_start, m, place_idx, slot)
    image_of_row = np.full(n_p * m, -1, dtype=np.int64)
    image_of_row[rows] = order
    row_of_image = np.full(len(image_place), -1, dtype=np.int64)
    row_of_image[order] = rows
    width = np.diff(block_start)
    place_of_row = np.concatenate([np.tile(np.arange(block_start[b], block_start[b + 1]), m) for b in range(n_blocks)])
    slot_of_row = np.concatenate([np.repeat(np.arange(m), width[b]) for b in range(n_blocks)])
    return Layout(places, m, block_start, image_of_row, row_of_image, psize, place_of_row, slot_of_row)


def as_layout32(d: np.ndarray, lay: Layout, threads: int = 1) -> np.ndarray:
    """``(n_rows, D)`` float32 descriptors in layout order, zero rows for padding.

    Gathered ``GATHER_ROWS`` rows at a time by ``threads`` threads (numpy's gather and
    conversion release the GIL; each chunk writes its own rows, so the result does not
    depend on them).
    """
    x = np.empty((lay.n_rows, d.shape[1]), dtype=np.float32)
    img = lay.image_of_row

    def chunk(lo: int) -> None:
        part = img[lo : lo + GATHER_ROWS]
        x[lo : lo + len(part)] = d[np.maximum(part, 0)]
        x[lo + np.flatnonzero(part < 0)] = 0.0  # padding

    if threads > 1:
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(chunk, range(0, lay.n_rows, GATHER_ROWS)))
    else:
        for lo in range(0, lay.n_rows, GATHER_ROWS):
            chunk(lo)
    return x
