"""The top-2 table that the pass files and the scoring reads (package doc, step 2).

Per (layout row, place index) at or above the row's floor: the best and second-best score
over the place's images and the slots reaching them (``Entries``, in RAM, then a temporary
file); every slot score where two of them are within the tie tolerance (``NearSlots``); and,
per row, the places where two or more images reach the row's own best score (``Records``).
"""

from __future__ import annotations

import os
import tempfile

import numpy as np

from vpr_explorer.method.retrieval import TIE_TOLERANCE
from vpr_explorer.protocols.scale.layout import Layout

#: Ties (``retrieval.TIE_TOLERANCE``): scores within it of each other tie.
TIE = TIE_TOLERANCE
#: One table entry: layout row, place index, best score and its slot, second best and its
#: slot, and whether two slots are within the tie tolerance: 4 + 4 + 4 + 1 + 4 + 1 + 1 = 19 bytes.
ENTRY = (("row", np.int32), ("place", np.int32), ("t1", np.float32), ("a1", np.uint8), ("t2", np.float32),
         ("a2", np.uint8), ("near", np.uint8))


def round_down32(x: np.ndarray) -> np.ndarray:
    """The largest float32 values ≤ x (the scores are float32: compared with them, nothing is lost)."""
    x32 = x.astype(np.float32)
    return np.where(x32.astype(np.float64) > x, np.nextafter(x32, np.float32(-np.inf)), x32)


def top2_rows(vals: np.ndarray) -> dict[str, np.ndarray]:
    """Best and second-best of each row of ``vals`` ``(n, m)``, the first slots reaching them,
    and whether two slots could tie.

    a1 is the first slot of the best value; with the best twice, t2 = t1 and a2 is the next
    such slot (argmax returns the first maximum). ``near`` marks rows where the best or, with
    the best held out, the second has another slot within the tie tolerance (t2 ≥ t1 − tie
    or t3 ≥ t2 − tie): only there can the image behind raw_p (the lowest slot within the
    tolerance) differ from a1/a2, and those rows keep all their slot scores (``NearSlots``).

    Returns:
        ``t1``, ``a1``, ``t2``, ``a2`` and ``near``, each ``(n,)``.
    """
    at = np.arange(len(vals))
    a1 = np.argmax(vals, axis=1)
    rest = vals.copy()
    rest[at, a1] = -np.inf
    a2 = np.argmax(rest, axis=1)
    t1, t2 = vals[at, a1], rest[at, a2]
    rest[at, a2] = -np.inf
    t3 = rest.max(axis=1)
    with np.errstate(invalid="ignore"):
        near = ((t2 >= t1 - TIE) & np.isfinite(t2)) | ((t3 >= t2 - TIE) & np.isfinite(t3))
    return {"t1": t1, "a1": a1.astype(np.uint8), "t2": t2, "a2": a2.astype(np.uint8), "near": near.astype(np.uint8)}


class NearSlots:
    """Every slot score of the table entries marked ``near`` (rare: near-duplicate images).

    Keyed by (layout row, place index); ``lookup`` returns the ``(n, m)`` scores of the
    given keys, all of which must have been added.
    """

    def __init__(self, n_places: int):
        self.n_places = n_places
        self.keys: list[np.ndarray] = []
        self.vals: list[np.ndarray] = []
        self._sorted: tuple[np.ndarray, np.ndarray] | None = None

    def add(self, rows: np.ndarray, places: np.ndarray, vals: np.ndarray) -> None:
        if len(rows):
            self.keys.append(rows.astype(np.int64) * self.n_places + places)
            self.vals.append(np.array(vals, dtype=np.float32))
            self._sorted = None

    def lookup(self, rows: np.ndarray, places: np.ndarray) -> np.ndarray:
        if self._sorted is None:
            keys = np.concatenate(self.keys) if self.keys else np.empty(0, np.int64)
            vals = np.concatenate(self.vals) if self.vals else np.empty((0, 0), np.float32)
            order = np.argsort(keys, kind="stable")
            self._sorted = (keys[order], vals[order])
        keys, vals = self._sorted
        want = rows.astype(np.int64) * self.n_places + places
        pos = np.minimum(np.searchsorted(keys, want), max(len(keys) - 1, 0))
        if len(want) and (len(keys) == 0 or not np.array_equal(keys[pos], want)):
            raise RuntimeError("internal error: a near-tie entry without its slot scores")  # pragma: no cover
        return vals[pos]


class Entries:
    """Top-2 table entries (``ENTRY``), filed by the block of their row.

    In RAM up to ``limit`` bytes, then appended to a temporary file that is deleted on
    ``close`` (or by the OS if the process dies). ``get`` returns a row block's entries
    sorted by (row, place) with a CSR row pointer.
    """

    def __init__(self, lay: Layout, limit: int, spill_dir: str | os.PathLike | None):
        self.lay, self.limit, self.spill_dir = lay, limit, spill_dir
        self.in_ram = 0
        self.file = None
        self.offset = 0
        self.chunks: dict[int, list] = {}

    def put(self, row_block: int, parts: dict[str, np.ndarray]) -> None:
        n = len(parts["row"])
        if n == 0:
            return
        arrays = {k: np.ascontiguousarray(parts[k], dtype=t) for k, t in ENTRY}
        size = sum(a.nbytes for a in arrays.values())
        if self.in_ram + size <= self.limit:
            self.in_ram += size
            self.chunks.setdefault(row_block, []).append(arrays)
            return
        if self.file is None:
            self.file = tempfile.TemporaryFile(prefix="vpr_top2_", dir=self.spill_dir)
        self.file.seek(self.offset)
        for k, _ in ENTRY:
            self.file.write(arrays[k].tobytes())
        self.chunks.setdefault(row_block, []).append((self.offset, n))
        self.offset += size

    def get(self, row_block: int) -> dict[str, np.ndarray]:
        parts = []
        for chunk in self.chunks.get(row_block, []):
            if isinstance(chunk, dict):
                parts.append(chunk)
                continue
            offset, n = chunk
            self.file.seek(offset)
            parts.append({k: np.fromfile(self.file, dtype=t, count=n) for k, t in ENTRY})
        out = {k: np.concatenate([p[k] for p in parts]) if parts else np.empty(0, t) for k, t in ENTRY}
        order = np.lexsort((out["place"], out["row"]))
        out = {k: v[order] for k, v in out.items()}
        rows = self.lay.rows(row_block)
        out["ptr"] = np.r_[0, np.cumsum(np.bincount(out["row"], minlength=rows.stop - rows.start))]
        return out

    def close(self) -> None:
        if self.file is not None:
            self.file.close()


class Records:
    """Per layout row, up to ``cap`` (place, slots ≥ b) records for the image-level count.

    A record is kept where two or more images of a wrong place reach the row's own best
    score b; the packed slot mask says which. Such a place adds at least one wrong image
    above b in any split, so ``cap`` records already put the rank beyond ``cap``: ``n``
    counts every such place of a row, kept or not.
    """

    def __init__(self, n_rows: int, slots: int, cap: int):
        self.cap = cap
        self.n = np.zeros(n_rows, dtype=np.int64)
        self.place = np.full((n_rows, cap), -1, dtype=np.int64)
        self.bits = np.zeros((n_rows, cap, (slots + 7) // 8), dtype=np.uint8)

    def add(self, rows: np.ndarray, places: np.ndarray, ge: np.ndarray) -> None:
        """``rows``, ``places`` ``(n,)``; ``ge`` ``(n, slots)`` bool, which slots reach b."""
        if len(rows) == 0:
            return
        order = np.argsort(rows, kind="stable")
        rows, places, ge = rows[order], places[order], ge[order]
        first = np.r_[True, rows[1:] != rows[:-1]]
        run_start = np.maximum.accumulate(np.where(first, np.arange(len(rows)), 0))
        pos = self.n[rows] + (np.arange(len(rows)) - run_start)
        keep = pos < self.cap
        self.place[rows[keep], pos[keep]] = places[keep]
        self.bits[rows[keep], pos[keep]] = np.packbits(ge[keep], axis=1, bitorder="little")
        np.add.at(self.n, rows, 1)
