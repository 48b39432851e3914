"""Scores shared by every protocol run on one set of descriptors, and a split's negative statistics from them.

A group/step sweep runs one protocol per cell on the same descriptors. What depends on
group and step is which images train a split (the places, the query drawn from each, the
held-out places); what does not is every image pair's score. ``SharedScores`` holds those
scores, computed once and kept for as long as the caller keeps it:

* ``full()``: the float32 similarity of all images, ``retrieval.similarity(d, d)``
  (``(n_images, n_images)``, 4·n² bytes), from which the protocols take their queries' scores;
* ``gram()``: a float64 Gram ``d64 @ d64ᵀ`` over the distinct descriptors of all images
  (8 bytes × their number²) with each row's mean score cᵢ, whatever the places. Images
  with identical descriptors share one row: a GEMM's rounding can depend on where a row
  sits, and identical images must get identical statistics.

From a Gram, ``Negatives`` gives a split's ``stats.NegativeStats`` pairwise instead of in
closed form (``stats.negative_stats``). For the members M of one protocol run (the images in a place)
and each member i, once per run (masked matrix–vector products over row blocks):

    Aᵢ = Σ_{j∈M} (sᵢⱼ − cᵢ),   Bᵢ = Σ_{j∈M} (sᵢⱼ − cᵢ)²

then per split, with training images T ⊆ M, the removed columns R = M \\ T (the queries, the
held-out places; a (distinct rows of T) × (distinct rows of R) block, never |T| × |T|) and
the same-place pairs within T (Σ_p n_p² pairs):

    Σ⁻ᵢ  = Aᵢ − Σ_{j∈R} (sᵢⱼ − cᵢ) − Σ_{j∈T, p(j)=p(i)} (sᵢⱼ − cᵢ)    (Σ²⁻ᵢ likewise from Bᵢ)
    μᵢ   = cᵢ + Σ⁻ᵢ / n⁻ᵢ,        σᵢ² = Σ²⁻ᵢ / n⁻ᵢ − (μᵢ − cᵢ)²   (clipped at 0)

Every sum is float64 about cᵢ, so σ² does not cancel as E[s²] − μ² does with all scores
near 0.8 (``stats``' module doc): it agrees with ``negative_stats(..., precision="float64")``
to ~1e-14 and with the loop reference to ~1e-16 (tests/test_shared_scores.py). Each sum runs
over columns that do not depend on i (M and R weighted by how many images share a row, a
place's pairs in the order of their rows) in a loop that does not depend on where i sits
(einsum and bincount, not a BLAS gemv, whose rounding does): images with identical
descriptors in identical places get identical statistics, and identical places tie exactly.

Memory decides where this is used: ``SHARED_LIMIT`` = 8,000 images, i.e. the float32 and
float64 matrices, 12 bytes × n² = 768 MB at the limit. Above it the protocols keep the closed form and score each split
against its training images (O(n·D²) per split, no n² memory).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.retrieval import similarity
from vpr_explorer.method.stats import NegativeStats, validate_descriptors

#: the most images whose n × n float32 similarity and float64 Gram are kept (12 bytes × n²)
SHARED_LIMIT = 8000
_ROWS = 512  # rows of the Gram per masked product (512 × 8,000 float64: 33 MB)
_PAIRS = 1 << 22  # same-place pairs gathered at a time


@dataclass(frozen=True, eq=False)
class Gram:
    """A float64 Gram over some images' distinct descriptors, and each row's centre.

    Rows are the distinct descriptors, not the images: an image's scores are its
    descriptor's row, so images with identical descriptors have identical rows bit for bit
    (a GEMM's rounding can depend on where a row sits in the matrix).

    Attributes:
        images: ``(m,)`` sorted image indices (into the descriptors) that it covers.
        row: ``(m,)`` the row (distinct descriptor) of each of those images.
        values: ``(u, u)`` float64 sᵢⱼ = dᵢ·dⱼ over the u distinct descriptors.
        centre: ``(u,)`` float64 cᵢ, the mean of row i: a value near its negative scores.
    """

    images: np.ndarray
    row: np.ndarray
    values: np.ndarray
    centre: np.ndarray

    def __post_init__(self) -> None:
        for a in (self.images, self.row, self.values, self.centre):
            a.setflags(write=False)

    def rows_of(self, images: np.ndarray) -> np.ndarray:
        """``(k,)`` Gram row of each image index in ``images``; every one must be covered."""
        images = np.asarray(images, dtype=np.int64)
        pos = np.searchsorted(self.images, images)
        if len(images) and (pos.max() >= len(self.images) or not np.array_equal(self.images[pos], images)):
            raise VPRInputError("shared scores: an image is not in the Gram these statistics were asked of")
        return self.row[pos]


class SharedScores:
    """The scores of one set of descriptors that every protocol run on them can share (module doc).

    Built cheaply: each matrix is computed on first use and kept. ``descriptors`` is kept by
    reference, so a run can check (``check``) that it is handed the scores of its own
    descriptors. Thread-safe.
    """

    def __init__(self, descriptors: np.ndarray):
        self.source = descriptors
        self.descriptors = validate_descriptors(descriptors)
        self.shape = self.descriptors.shape
        self._full: np.ndarray | None = None
        self._gram: Gram | None = None
        self._lock = threading.Lock()

    def belongs_to(self, descriptors: object) -> bool:
        """Whether these are the scores of ``descriptors``: the array they were built from (or a view
        of the same memory with the same shape, strides and type, as ``np.asarray`` of a memmap gives)."""
        return any(descriptors is a or _same_memory(descriptors, a) for a in (self.source, self.descriptors))

    def check(self, descriptors: object) -> None:
        """Raise ``VPRInputError`` unless these are the scores of ``descriptors`` (``belongs_to``)."""
        if not self.belongs_to(descriptors):
            shape = getattr(descriptors, "shape", None)
            raise VPRInputError(f"shared scores were built from other descriptors ({self.shape[0]:,} × "
                                f"{self.shape[1]:,}) than the {shape} array given: build SharedScores from these")

    def full(self) -> np.ndarray:
        """``(n, n)`` float32 ``retrieval.similarity(d, d)`` of every image (read-only)."""
        with self._lock:
            if self._full is None:
                _check_size(self.shape[0])
                full = similarity(self.descriptors, self.descriptors)
                full.setflags(write=False)
                self._full = full
            return self._full

    def gram(self) -> Gram:
        """The float64 ``Gram`` of every image, computed once."""
        with self._lock:
            if self._gram is None:
                _check_size(self.shape[0])
                x = np.ascontiguousarray(self.descriptors)
                rows = x.view(np.dtype((np.void, x.shape[1] * x.dtype.itemsize))).ravel()
                _, first, row = np.unique(rows, return_index=True, return_inverse=True)
                u = np.asarray(x[first], dtype=np.float64)
                values = u @ u.T
                self._gram = Gram(np.arange(self.shape[0]), row.reshape(-1).astype(np.int64), values,
                                  values.mean(axis=1))
            return self._gram


def _same_memory(a: object, b: object) -> bool:
    if not isinstance(a, np.ndarray) or not isinstance(b, np.ndarray):
        return False
    ia, ib = a.__array_interface__, b.__array_interface__
    return all(ia.get(k) == ib.get(k) for k in ("data", "shape", "strides", "typestr"))


def _check_size(n: int) -> None:
    if n > SHARED_LIMIT:
        raise VPRInputError(f"shared scores of {n:,} images: at most {SHARED_LIMIT:,} (12 bytes × n² of memory); "
                            "the protocols use the closed form above it")


def resolve(shared: SharedScores | None, descriptors: object, n_images: int) -> SharedScores | None:
    """The shared scores a run on ``descriptors`` should use: ``shared`` (checked) or a new one;
    ``None`` when more than ``SHARED_LIMIT`` images take part (``n_images``): the closed form then.
    """
    if shared is not None and not isinstance(shared, SharedScores):
        raise VPRInputError(f"shared: expected a SharedScores, got {type(shared).__name__}")
    if shared is not None:
        shared.check(descriptors)
    if n_images > SHARED_LIMIT:
        return None
    return SharedScores(descriptors) if shared is None else shared


def _weighted_rows(e: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``(b,)`` Σⱼ wⱼ eᵢⱼ, each row in the same order wherever it sits (einsum's loop; a BLAS gemv is not)."""
    return np.einsum("ij,j->i", e, w)


class Negatives:
    """Per-member sums of one protocol run, from which each split's ``NegativeStats`` follow (module doc).

    Args:
        gram: the ``Gram`` covering every member.
        members: image indices of the images in a place (every split trains on some of them).
    """

    def __init__(self, gram: Gram, members: np.ndarray):
        self.gram = gram
        self.members = np.unique(np.asarray(members, dtype=np.int64))
        self._rows = gram.rows_of(self.members)
        u = len(gram.values)
        weight = np.bincount(self._rows, minlength=u).astype(np.float64)  # members per distinct descriptor
        self._sum = np.full(u, np.nan)
        self._sq = np.full(u, np.nan)
        present = np.flatnonzero(weight)
        for lo in range(0, len(present), _ROWS):
            r = present[lo:lo + _ROWS]
            e = gram.values[r] - gram.centre[r, None]  # (b, u): scores about each row's centre
            self._sum[r] = _weighted_rows(e, weight)
            np.multiply(e, e, out=e)
            self._sq[r] = _weighted_rows(e, weight)

    def stats(self, train: np.ndarray, labels: np.ndarray, n_places: int) -> NegativeStats:
        """``NegativeStats`` of the training images ``train`` (among the members) with places ``labels``.

        Equal to ``stats.negative_stats(d[train], labels, n_places)`` to float64 rounding.
        """
        train = np.asarray(train, dtype=np.int64)
        labels = np.asarray(labels, dtype=np.int64)
        if labels.shape != train.shape or len(np.unique(train)) != len(train):
            raise VPRInputError("shared scores: give distinct training images, one place label each")
        counts = np.bincount(labels, minlength=n_places)
        if np.count_nonzero(counts) < 2:
            raise VPRInputError(f"only {np.count_nonzero(counts)} place has training images: negative scores need "
                                "at least 2 places; lower group/step or add traversals")
        at = np.searchsorted(self.members, train)
        if len(train) and (at.max() >= len(self.members) or not np.array_equal(self.members[at], train)):
            raise VPRInputError("shared scores: a training image is not among this run's members")
        g = self.gram
        rows = self._rows[at]
        c = g.centre[rows]
        total, total_sq = self._sum[rows], self._sq[rows]
        removed = np.ones(len(self.members), dtype=bool)
        removed[at] = False
        if removed.any():  # the queries and held-out places: (distinct training rows) × (distinct removed rows)
            cols, weight = np.unique(self._rows[removed], return_counts=True)
            weight = weight.astype(np.float64)
            distinct, back = np.unique(rows, return_inverse=True)
            down, down_sq = np.empty(len(distinct)), np.empty(len(distinct))
            for lo in range(0, len(distinct), _ROWS):
                r = distinct[lo:lo + _ROWS]
                e = g.values[np.ix_(r, cols)] - g.centre[r, None]
                down[lo:lo + len(r)] = _weighted_rows(e, weight)
                np.multiply(e, e, out=e)
                down_sq[lo:lo + len(r)] = _weighted_rows(e, weight)
            total = total - down[back.reshape(-1)]
            total_sq = total_sq - down_sq[back.reshape(-1)]
        same, same_sq = _same_place_sums(g, rows, c, labels)
        n_neg = len(train) - counts[labels]
        gap = (total - same) / n_neg  # μᵢ − cᵢ
        var = (total_sq - same_sq) / n_neg - gap**2
        # as stats.negative_stats: rounding can leave -1e-17 where the true variance is 0
        sigma = np.sqrt(np.clip(var, 0.0, None))
        return NegativeStats(mu=c + gap, sigma=sigma, n_neg=n_neg.astype(np.int64), labels=labels,
                             n_places=int(n_places))


def _same_place_sums(g: Gram, rows: np.ndarray, c: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Σ_{j∈T, p(j)=p(i)} (sᵢⱼ − cᵢ) and its squares, each ``(n,)``, i itself included.

    Each place's pairs in the order of their Gram rows, added in that order (``bincount``
    adds in order): places of identical descriptors give identical sums, whatever the
    images' indices.
    """
    n = len(rows)
    order = np.lexsort((rows, labels))
    lab = labels[order]
    sizes = np.bincount(lab)
    starts = np.cumsum(sizes) - sizes
    rep = sizes[lab]  # partners of each sorted image
    ends = np.cumsum(rep)
    same = np.zeros(n)
    same_sq = np.zeros(n)
    lo = 0
    while lo < n:  # chunks of sorted images holding at most _PAIRS pairs (one image at least)
        base = int(ends[lo - 1]) if lo else 0
        hi = max(lo + 1, int(np.searchsorted(ends, base + _PAIRS, side="right")))
        k = np.repeat(np.arange(lo, hi), rep[lo:hi])
        offset = np.arange(len(k)) - np.repeat(ends[lo:hi] - rep[lo:hi] - base, rep[lo:hi])
        partner = starts[lab[k]] + offset
        e = g.values[rows[order[k]], rows[order[partner]]] - c[order[k]]
        same[order[lo:hi]] = np.bincount(k - lo, weights=e, minlength=hi - lo)
        same_sq[order[lo:hi]] = np.bincount(k - lo, weights=e * e, minlength=hi - lo)
        lo = hi
    return same, same_sq
