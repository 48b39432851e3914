"""Negative similarity statistics of each training image, in closed form.

For training image i of place p, its negative scores are S⁻ᵢ = { dᵢ·dⱼ : j in a place r ≠ p }.
A normal N(μᵢ, σᵢ²) is fitted to them (maximum likelihood, so σᵢ is the population
standard deviation), and the place's negative Gaussian mixture is
M(p) = Σᵢ wᵢ N(μᵢ, σᵢ²) with wᵢ = |S⁻ᵢ| / Σⱼ |S⁻ⱼ| over p's images.

No N×N similarity matrix is formed. With T = Σⱼ dⱼ, T_p = Σ_{j∈p} dⱼ, C = Σⱼ dⱼdⱼᵀ and n⁻ᵢ the
number of negatives:

    μᵢ     = dᵢ·(T − T_p) / n⁻ᵢ
    E[s²]ᵢ = (dᵢᵀ C dᵢ − Σ_{j∈p} (dᵢ·dⱼ)²) / n⁻ᵢ,     σᵢ² = E[s²]ᵢ − μᵢ²

which is O(N·D²) instead of O(N²·D). ``precision="float64"`` computes exactly this in float64.

Float32 products (the default)
------------------------------
The two N·D² products, the Gram and the quadratic forms, are float32 GEMMs; all else is
float64. Taken as above, σᵢ² = E[s²]ᵢ − μᵢ² would cancel: descriptors with a shared
component score ≈ 0.8 everywhere while σ ≈ 0.01, and a float32 error relative to s² ≈ 0.64
is ~5e-4 of σ² (|Δσ| ≈ 2.5e-6 measured). So the descriptors are centred before the products. With
m a float32 vector near the mean descriptor (``_centre``), eⱼ = dⱼ − m, E = Σⱼ eⱼeⱼᵀ and the
per-image centre score aᵢ = dᵢ·m, for any m exactly:

    Σ_{all j} (sᵢⱼ − aᵢ)²  = dᵢᵀ E dᵢ                      (sᵢⱼ − aᵢ = dᵢ·eⱼ)
    n⁻ᵢ E⁻[(s − aᵢ)²]      = dᵢᵀ E dᵢ − Σ_{j∈p} (sᵢⱼ − aᵢ)²
    σᵢ²                    = E⁻[(s − aᵢ)²] − (μᵢ − aᵢ)²

so the float32 error is relative to |dᵢ|·|eⱼ|, not to |sᵢⱼ|, and the last line does not
cancel (μᵢ − aᵢ is the gap between the negatives' mean and the all-image mean). μᵢ, aᵢ, dᵢ·T
and the same-place terms are float64 products (``_place_terms``): μ is exact to float64
rounding. Three passes: E (``_centred_gram``), the float64 terms place by place
(``_place_terms``), dᵢᵀEdᵢ (``_quadratic_forms``, (1 + 1/8)·N·D² flops by symmetry).

**Error bound.** u = 2⁻²⁴, γ_k = k·u/(1 − k·u), |·| elementwise, L = min(block, N) the rows
of one float32 Gram, S = Σⱼ |eⱼ||eⱼ|ᵀ. To first order in u:

1. ẽⱼ = fl32(dⱼ − m) = eⱼ ∘ (1 + δ), |δ| ≤ u: |ẽⱼẽⱼᵀ − eⱼeⱼᵀ| ≤ 2u·|eⱼ||eⱼ|ᵀ;
2. a block's float32 Gram, inner products of depth L in any order, errs by at most
   γ_L·Σ_{j∈block} |ẽⱼ||ẽⱼ|ᵀ; summing blocks in float64 adds O(2⁻⁵³): |Ê − E| ≤ (γ_L + 2u)·S;
3. rounding Ê to float32 (doubling its off-diagonal blocks is exact) adds u·S;
4. the float32 GEMM dᵢW, depth ≤ D, errs by at most γ_D·|dᵢ||W|, so the quadratic form by
   γ_D·|dᵢ|ᵀ S |dᵢ| (the row sums ŷ·dᵢ are float64); rounding float64 input to float32 adds 2u.

Hence, with Bᵢ = |dᵢ|ᵀ S |dᵢ| = Σⱼ (|dᵢ|·|eⱼ|)² ≤ ‖dᵢ‖²·Σⱼ ‖eⱼ‖² and ε = γ_L + γ_D + 5u,

    |σ̂ᵢ² − σᵢ²| ≤ ε·Bᵢ / n⁻ᵢ,     |σ̂ᵢ − σᵢ| ≤ min(√(ε·Bᵢ/n⁻ᵢ), ε·Bᵢ / (n⁻ᵢ·σᵢ)),

plus float64 rounding (~1e-16 · dᵢᵀEdᵢ / n⁻ᵢ); ``sigma_sq_error_bound`` evaluates it per image.
It holds for every order of summing the products, hence for every BLAS kernel (OpenBLAS,
MKL: none uses Strassen-type products) and thread count: two runs differ by at most twice
it, and the elementwise parts are cut the same whatever ``threads``.
``device=`` ("cpu", "cuda", "cuda:1", a ``torch.device``) runs the two N·D² products as
torch float32 matmuls on that device (full E, no triangle; float64 sums on the device; TF32
off), and the rest as above: the same bound holds, since it holds for any summation order.
It is a worst case: rounding errors of both signs add like √k, and measured |σ̂² − σ²| is
1e-6 to 1e-2 of it (tests/test_stats.py): |Δσ| ≈ 1e-9 at N = 100,000, D = 1,280, and
2e-9 to 5e-8 on small or shared-component sets (σ ≈ 0.01 with all scores near 0.8).
"""

from __future__ import annotations

import contextlib
import functools
import os
import threading
import warnings
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from enum import StrEnum
from typing import NamedTuple

import numpy as np
from scipy import sparse

from vpr_explorer.errors import VPRInputError
from vpr_explorer.settings import DEVICE_ENV, MAX_DEFAULT_WORKERS, default_workers

#: σ below this is treated as this when a weight 1/σ² or a density is needed: a place
#: whose image has a single negative score (σ = 0) would otherwise divide by zero.
SIGMA_FLOOR = 1e-6

#: rows per block in ``negative_stats``: 4,096 rows × 1,280 floats keep the float32 GEMMs
#: near peak rate (fewer rows lose rate, more only lengthen the float32 sums of the bound)
BLOCK = 4096
_CENTRE_ROWS = 4096  # rows averaged for the centre m
_BIG_PLACE = 1024  # places with more images get their same-place scores a band of rows at a time
_PART = 512  # rows per part of the elementwise work shared out to threads (fixed: see ``_parts``)
_MEAN_ROWS = 8192  # rows converted to float64 at a time by ``positive_means``
_TRI_BLOCKS = 8  # column blocks of W: the quadratic forms take (1 + 1/8)·N·D² flops instead of 2·N·D²
_GRAM_LANES = 4  # float64 sums of E that blocks of rows are dealt to in turn (``_centred_gram``)
_QUAD_ROWS = 1024  # rows per pool task of ``_quadratic_forms``

#: A row whose squared norm is below this is all zero: the bound ``descriptors.extract`` normalises
#: with (``MIN_SQUARED_NORM``), written here so that the statistics do not import the extractors.
ZERO_SQUARED_NORM = 1e-24


@dataclass(frozen=True, eq=False)
class NegativeStats:
    """Per training image: the normal fitted to its negative scores.

    Attributes:
        mu: ``(n,)`` mean of each image's negative scores, μᵢ.
        sigma: ``(n,)`` population standard deviation of them, σᵢ.
        n_neg: ``(n,)`` number of negative scores, |S⁻ᵢ|.
        labels: ``(n,)`` place of each training image, in ``0..n_places-1``.
        n_places: number of place ids (places without training images have no stats).
    """

    mu: np.ndarray
    sigma: np.ndarray
    n_neg: np.ndarray
    labels: np.ndarray
    n_places: int

    def __post_init__(self) -> None:
        for a in (self.mu, self.sigma, self.n_neg, self.labels):
            a.setflags(write=False)

    @property
    def counts(self) -> np.ndarray:
        """``(n_places,)`` training images per place."""
        return np.bincount(self.labels, minlength=self.n_places)

    @property
    def weights(self) -> np.ndarray:
        """``(n,)`` mixture weight wᵢ = |S⁻ᵢ| / Σ_{j∈p} |S⁻ⱼ| of each image within its place."""
        totals = np.bincount(self.labels, weights=self.n_neg, minlength=self.n_places)
        return self.n_neg / totals[self.labels]

    def components(self, place: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(mu, sigma, weight)`` of the mixture components of ``place``, each ``(n_p,)``."""
        idx = np.flatnonzero(self.labels == place)
        return self.mu[idx], self.sigma[idx], self.weights[idx]


def validate_descriptors(descriptors: np.ndarray, what: str = "descriptors") -> np.ndarray:
    """Return ``descriptors`` as a 2-D float array; raise on NaN, inf or zero rows.

    Checked ``CHECK_ELEMS`` entries at a time, so a memory-mapped float16 matrix (a million
    rows) is never converted whole: the result is ``descriptors`` itself (a memmap stays one).
    """
    d = descriptors if isinstance(descriptors, np.ndarray) else np.asarray(descriptors)
    if d.ndim != 2 or d.shape[0] == 0 or d.shape[1] == 0:
        raise VPRInputError(f"{what}: expected a non-empty (n_images, dim) array, got shape {d.shape}")
    if not np.issubdtype(d.dtype, np.floating):
        d = d.astype(np.float32)
    # One pass: a NaN or inf makes the row's sum of squares NaN or inf (so does overflow, which
    # the second look at those rows tells apart). A full isfinite pass cost as much as the stats.
    sq = np.empty(len(d), dtype=np.promote_types(d.dtype, np.float32))
    step = max(1, CHECK_ELEMS // d.shape[1])
    for lo in range(0, len(d), step):
        x = d[lo : lo + step]
        sq[lo : lo + len(x)] = np.einsum("ij,ij->i", x, x, dtype=sq.dtype)
    bad = ~np.isfinite(sq)
    suspects = np.flatnonzero(bad)
    for lo in range(0, len(suspects), step):
        part = suspects[lo : lo + step]
        bad[part] = ~np.isfinite(d[part]).all(axis=1)
    if bad.any():
        raise VPRInputError(
            f"{what}: rows {_first(bad)} contain NaN or inf; recompute the descriptors (clear the cache) "
            "or remove those images"
        )
    zero = sq < ZERO_SQUARED_NORM
    if zero.any():
        raise VPRInputError(
            f"{what}: rows {_first(zero)} are all zero, so cosine similarity is undefined; "
            "remove those images or choose another descriptor"
        )
    return d


def _first(mask: np.ndarray, n: int = 5) -> str:
    idx = np.flatnonzero(mask)
    text = ", ".join(map(str, idx[:n]))
    return text + (f" (and {len(idx) - n} more)" if len(idx) > n else "")


def _check_labels(labels: np.ndarray, n: int, n_places: int | None) -> tuple[np.ndarray, int]:
    labels = np.asarray(labels)
    if labels.shape != (n,) or not np.issubdtype(labels.dtype, np.integer):
        raise VPRInputError(f"labels: expected {n} integer place ids, got shape {labels.shape} dtype {labels.dtype}")
    if n and labels.min() < 0:
        raise VPRInputError("labels: place ids must be >= 0 (drop skipped frames, labelled -1, first)")
    if n_places is None:
        n_places = int(labels.max()) + 1
    elif labels.max() >= n_places:
        raise VPRInputError(f"labels: place id {labels.max()} >= n_places={n_places}")
    present = np.count_nonzero(np.bincount(labels, minlength=n_places))
    if present < 2:
        raise VPRInputError(
            f"only {present} place has training images: negative scores need at least 2 places; "
            "lower group/step or add traversals"
        )
    return labels.astype(np.int64), int(n_places)


def thread_count(threads: int | None, cap: int = MAX_DEFAULT_WORKERS) -> int:
    """``threads`` checked, or ``settings.default_workers(cap)`` for ``None``.

    Raises:
        VPRInputError: ``threads`` is not a whole number, 1 or more.
    """
    if threads is None:
        return default_workers(cap)
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
        raise VPRInputError(f"threads={threads!r}: must be a whole number, 1 or more (or unset: one per CPU)")
    return int(threads)


def _block_and_threads(block: int, threads: int | None) -> tuple[int, int]:
    """The closed form's ``block`` (rows at a time, 1 or more) and ``threads`` (``thread_count``), checked."""
    if isinstance(block, bool) or not isinstance(block, (int, np.integer)) or block < 1:
        raise VPRInputError(f"block: expected a positive number of rows, got {block!r}")
    return int(block), thread_count(threads)


def within_place_sq(d: np.ndarray, labels: np.ndarray, *, block_elems: int = 2**24) -> np.ndarray:
    """``(n,)`` Σ_{j∈p(i)} (dᵢ·dⱼ)², the squared same-place scores of each image, i itself included.

    Places are padded to the largest place size and processed in blocks, so the work is
    Σ_p n_p² · D and memory stays under ``block_elems`` floats per block.
    """
    n = len(labels)
    order = np.argsort(labels, kind="stable")
    sorted_labels = labels[order]
    starts = np.flatnonzero(np.r_[True, sorted_labels[1:] != sorted_labels[:-1]])
    sizes = np.diff(np.r_[starts, n])
    m = int(sizes.max())
    slot = np.arange(n) - np.repeat(starts, sizes)  # position of each sorted image in its place
    out_sorted = np.empty(n, dtype=np.float64)
    dim = d.shape[1]
    places_per_block = max(1, block_elems // (m * dim))
    for b in range(0, len(starts), places_per_block):
        pb = slice(b, b + places_per_block)
        lo, hi = starts[pb][0], starts[pb][-1] + sizes[pb][-1]
        padded = np.zeros((len(starts[pb]), m, dim), dtype=np.float64)
        padded[np.repeat(np.arange(len(starts[pb])), sizes[pb]), slot[lo:hi]] = d[order[lo:hi]]
        gram = np.einsum("pmd,pkd->pmk", padded, padded)
        sq = np.einsum("pmk,pmk->pm", gram, gram)
        out_sorted[lo:hi] = sq[np.repeat(np.arange(len(starts[pb])), sizes[pb]), slot[lo:hi]]
    out = np.empty(n, dtype=np.float64)
    out[order] = out_sorted
    return out


class Precision(StrEnum):
    """Arithmetic of the O(N·D²) products in ``negative_stats`` (module docstring)."""

    FLOAT32 = "float32"  # float32 GEMMs of centred descriptors, float64 sums: the default
    FLOAT64 = "float64"  # everything in float64: the reference the float32 products are checked against


def negative_stats(
    descriptors: np.ndarray,
    labels: np.ndarray,
    n_places: int | None = None,
    *,
    block: int = BLOCK,
    precision: Precision | str = Precision.FLOAT32,
    threads: int | None = None,
    device: object | None = None,
) -> NegativeStats:
    """μᵢ, σᵢ of every training image's negative scores, in closed form.

    Args:
        descriptors: ``(n, D)`` L2-normalised descriptors of the training images.
        labels: ``(n,)`` place id of each image (``>= 0``).
        n_places: number of place ids; defaults to ``labels.max() + 1``.
        block: rows processed at a time (bounds memory at Nordland scale; with float32 also
            the depth L of the float32 Gram sums in the error bound).
        precision: ``"float32"``: μ to float64 rounding, σ² within ``sigma_sq_error_bound``
            (module docstring); ``"float64"``: both to float64 rounding, about 4× the time
            at N = 100,000, D = 1,280 (benchmarks/bench_negative_stats.py).
        threads: threads for the elementwise work of the float32 path (default: one per usable
            CPU, at most ``settings.MAX_DEFAULT_WORKERS``; BLAS keeps its own). The work is cut
            into the same parts whatever the count, so the result does not depend on it.
        device: ``None`` (numpy, the default) or a torch device ("cpu", "cuda", …): the float32
            products as torch matmuls there (module docstring); within the same error bound.
            Only with ``precision="float32"``.

    Returns:
        μᵢ, σᵢ and n⁻ᵢ of every image, ``(n,)`` each.

    Raises:
        VPRInputError: bad descriptors, labels, ``block``, ``threads``, ``precision`` or ``device``.
    """
    d = validate_descriptors(descriptors, "training descriptors")
    n, dim = d.shape
    labels, n_places = _check_labels(labels, n, n_places)
    block, threads = _block_and_threads(block, threads)
    try:
        closed_form = _CLOSED_FORMS[Precision(precision)]
    except ValueError:
        choices = ", ".join(repr(p.value) for p in Precision)
        raise VPRInputError(f"precision: expected one of {choices}, got {precision!r}") from None
    counts = np.bincount(labels, minlength=n_places)
    n_neg = n - counts[labels]
    if device is not None:
        if Precision(precision) is not Precision.FLOAT32:
            raise VPRInputError(f"device={device!r}: the torch path computes precision='float32' only")
        dev = torch_device(device)
        closed_form = functools.partial(_closed_form_torch, device=dev)
    fit = closed_form(d, labels, counts, n_neg, block, threads)
    # Cancellation can leave -1e-17 where the true variance is 0 (all negatives equal).
    sigma = np.sqrt(np.clip(fit.var, 0.0, None))
    return NegativeStats(mu=fit.mu, sigma=sigma, n_neg=n_neg.astype(np.int64), labels=labels, n_places=n_places)


class _PlaceTerms(NamedTuple):
    """The float64 terms of each image against its own place, T and m (``_place_terms``), each ``(n,)``."""

    dot_total: np.ndarray  # dᵢ·T
    centre_score: np.ndarray  # aᵢ = dᵢ·m
    same: np.ndarray  # Σ_{j∈p} sᵢⱼ
    same_sq: np.ndarray  # Σ_{j∈p} (sᵢⱼ − aᵢ)²
    own: np.ndarray  # sᵢᵢ = ‖dᵢ‖²


class _Moments(NamedTuple):
    """What a closed form returns: μᵢ and σᵢ² (before clipping at 0), each ``(n,)``, and the place
    terms it took on the way (``None`` where it took none: the float64 form)."""

    mu: np.ndarray
    var: np.ndarray
    terms: _PlaceTerms | None


def _closed_form_float64(
    d: np.ndarray, labels: np.ndarray, counts: np.ndarray, n_neg: np.ndarray, block: int, threads: int
) -> _Moments:
    """μ and σ², C and dᵢᵀCdᵢ in float64: the reference the float32 products are checked against."""
    n, dim = d.shape
    n_places = len(counts)
    total = np.zeros(dim)
    place_sums = np.zeros((n_places, dim))
    gram = np.zeros((dim, dim))
    indicator = sparse.csr_matrix((np.ones(n), (labels, np.arange(n))), shape=(n_places, n))
    for lo in range(0, n, block):
        x = d[lo : lo + block].astype(np.float64)
        total += x.sum(axis=0)
        place_sums += indicator[:, lo : lo + block] @ x
        gram += x.T @ x

    mu = np.empty(n)
    second = np.empty(n)
    for lo in range(0, n, block):
        x = d[lo : lo + block].astype(np.float64)
        lab = labels[lo : lo + block]
        mu[lo : lo + block] = np.einsum("ij,ij->i", x, total - place_sums[lab])
        second[lo : lo + block] = np.einsum("ij,ij->i", x @ gram, x)
    second -= within_place_sq(d, labels)
    mu /= n_neg
    return _Moments(mu, second / n_neg - mu**2, None)


def _closed_form_float32(
    d: np.ndarray, labels: np.ndarray, counts: np.ndarray, n_neg: np.ndarray, block: int, threads: int
) -> _Moments:
    """μ and σ²: E and dᵢᵀEdᵢ as float32 GEMMs of centred rows, the rest float64.

    Three passes (module docstring): the centred Gram E, the float64 terms place by place,
    the quadratic forms. Elementwise work runs in ``threads`` threads over fixed parts. The
    place terms come back too (their Σ_{j∈p} sᵢⱼ and sᵢᵢ give ``_positive_from_terms``).
    """
    centre = _centre(d)
    # BLAS in one thread throughout when the products run side by side (entered once: each
    # entry asks threadpoolctl for the loaded libraries)
    with ThreadPoolExecutor(threads) as pool, one_blas_thread() if threads > 1 else contextlib.nullcontext():
        gram, total = _centred_gram(d, centre, block, pool, threads)
        terms = _place_terms(d, labels, counts, np.stack([total, centre]), pool)
        quad = _quadratic_forms(d, gram, pool, threads > 1)
    return _moments(terms, quad, n_neg)


def _moments(terms: _PlaceTerms, quad: np.ndarray, n_neg: np.ndarray) -> _Moments:
    """μᵢ and σᵢ² from the place terms and the quadratic forms dᵢᵀEdᵢ ``(n,)`` (module docstring)."""
    mu = (terms.dot_total - terms.same) / n_neg  # Σ_{j∉p} sᵢⱼ / n⁻ᵢ
    # E⁻[(s − aᵢ)²]: Σ_all (sᵢⱼ − aᵢ)² = dᵢᵀEdᵢ, less the same-place terms
    return _Moments(mu, (quad - terms.same_sq) / n_neg - (mu - terms.centre_score) ** 2, terms)


def _centred_gram(
    d: np.ndarray, centre: np.ndarray, block: int, pool: ThreadPoolExecutor, threads: int
) -> tuple[np.ndarray, np.ndarray]:
    """E = Σⱼ (dⱼ − m)(dⱼ − m)ᵀ ``(D, D)`` and T = Σⱼ dⱼ ``(D,)``, both float64.

    Per block of ``block`` rows (read in order, in this thread: a ``_FirstPass`` reads the next
    one meanwhile): the centred rows, each rounded once from dⱼ − m itself (so the error is
    relative to |dⱼ − m|, not |dⱼ|), then the block's float32 Gram (one syrk of depth L), added
    to a float64 sum. Block k goes to lane k mod ``_GRAM_LANES``, one task per block of
    ``pool`` (``threads`` workers) with BLAS in one thread when ``threads`` > 1, in turn in this
    thread otherwise; a lane's sum takes its blocks in order (block k
    waits for block k − lanes), and E is the lanes' sums added in lane order. So E is the same
    numbers for any thread count, the syrks run whole and side by side (the rate of one
    single-threaded syrk per thread: numpy's one syrk in two BLAS threads ran them at about
    70% and mirrored the triangle in one; tiles of it lost as much on task overhead), and at
    most ``threads`` blocks are in flight. Each entry is one inner product of depth L
    rounded to float32, so the error bound is that of the module docstring for any
    order of the sums (``tests/test_stats.py`` checks it, and on OpenBLAS's SkylakeX kernel
    the numbers of one syrk per block summed lane by lane, bit for bit).
    """
    n, dim = d.shape
    m = centre if d.dtype == np.float32 else centre.astype(np.float64)  # float32 − float32: one rounding
    lanes = [np.zeros((dim, dim)) for _ in range(min(_GRAM_LANES, -(-n // block)))]
    parts: dict[int, np.ndarray] = {}  # row -> the float64 sum of the part of ``_PART`` rows from it
    buffers = threading.local()  # each thread's centred rows and float32 Gram, reused across its blocks

    def task(lane: int, lo: int, x: np.ndarray) -> None:
        if not hasattr(buffers, "e"):
            buffers.e = np.empty((min(block, n), dim), dtype=np.float32)
            buffers.g = np.empty((dim, dim), dtype=np.float32)
        eb = buffers.e[: len(x)]
        for p in range(0, len(x), _PART):
            sl = slice(p, min(p + _PART, len(x)))
            np.subtract(x[sl], m, out=eb[sl], casting="same_kind")
            parts[lo + p] = x[sl].sum(axis=0, dtype=np.float64)
        np.matmul(eb.T, eb, out=buffers.g)  # eᵢᵀeᵢ: numpy hands Xᵀ X to syrk (and mirrors it)
        np.add(lanes[lane], buffers.g, out=lanes[lane])

    run_in_lanes(pool, ((lo, d[lo : lo + block]) for lo in range(0, n, block)), len(lanes),
                 lambda lane, item: task(lane, *item), in_flight=threads if threads > 1 else None)
    gram = lanes[0]
    for lane in lanes[1:]:
        gram += lane
    # in part order: the same sum whatever the thread count
    return gram, np.sum([parts[lo] for lo in sorted(parts)], axis=0)


def run_in_lanes(pool: ThreadPoolExecutor, items: Iterable, n_lanes: int, task: Callable[[int, object], None],
                 in_flight: int | None) -> None:
    """``task(lane, item)`` for every item in order, item k on lane k mod ``n_lanes``.

    With ``in_flight`` (the pool's worker count, as its caller made it), as pool tasks with
    BLAS in one thread; with ``None``, in turn in this thread (BLAS in its own threads). Items
    are drawn from ``items`` in this thread, one ahead of the tasks; item k starts once item
    k − ``n_lanes`` (its lane's last) has finished and fewer than ``in_flight`` are in flight.
    So a float64 sum per lane takes its items in order, and the lanes added in lane order
    are the same numbers for any thread count.
    """
    side_by_side = in_flight is not None
    threads = max(1, in_flight) if side_by_side else 1
    futures: dict[int, object] = {}
    with one_blas_thread() if side_by_side else contextlib.nullcontext():
        for k, item in enumerate(items):
            for wait in (k - n_lanes, k - threads):  # the lane's last item; at most ``threads`` in flight
                if wait in futures:
                    futures.pop(wait).result()
            if side_by_side:
                futures[k] = pool.submit(task, k % n_lanes, item)
            else:
                task(k % n_lanes, item)
        for future in futures.values():
            future.result()


def _side_by_side(pool: ThreadPoolExecutor, tasks: tuple[Callable[[], None], ...], parallel: bool) -> None:
    """Run BLAS-bound ``tasks`` as pool tasks with BLAS in one thread each (in the order given, as
    threads free up), or in turn with BLAS's own threads.

    Either way each product gives the same numbers: a GEMM or syrk splits rows and columns
    between threads, never an inner product.
    """
    if not parallel:
        for task in tasks:
            task()
        return
    with one_blas_thread():
        for future in [pool.submit(task) for task in tasks]:
            future.result()


def _place_terms(
    d: np.ndarray, labels: np.ndarray, counts: np.ndarray, proj: np.ndarray, pool: ThreadPoolExecutor
) -> _PlaceTerms:
    """dᵢ·T, aᵢ = dᵢ·m, Σ_{j∈p} sᵢⱼ, Σ_{j∈p} (sᵢⱼ − aᵢ)² and sᵢᵢ = ‖dᵢ‖², each ``(n,)``, in float64.

    Parts hold whole places of one size k (``_place_slabs``): each is one batched product of
    small matrices ``(P, k, D) @ (P, D, k + 2)`` (the place's k images, then T and m), which
    BLAS runs single-threaded, so the parts run side by side.

    Args:
        proj: ``(2, D)`` float64 T and m.
    """
    n, dim = d.shape
    order, slabs = _place_slabs(labels, counts, _PART)
    out = np.empty((5, n))

    def part(slab: tuple[int, int, int]) -> None:
        lo, hi, k = slab
        x = np.empty(((hi - lo) // k, k + 2, dim))
        x[:, :k] = d[order[lo:hi]].reshape(-1, k, dim)
        x[:, k:] = proj
        if k <= _BIG_PLACE:
            out[:, order[lo:hi]] = _terms(x[:, :k] @ x.transpose(0, 2, 1), k)
        else:  # one large place: a band of rows at a time keeps k × k out of memory
            rows = max(1, _BIG_PLACE**2 // k)
            for r in range(0, k, rows):
                band = slice(r, min(r + rows, k))
                out[:, order[lo:hi][band]] = _terms(x[0, band] @ x[0].T, k, band.start)

    list(pool.map(part, slabs))
    return _PlaceTerms(*out)


def _terms(g: np.ndarray, k: int, first: int = 0) -> np.ndarray:
    """``(5, m)`` dᵢ·T, aᵢ, Σ_{j∈p} sᵢⱼ, Σ_{j∈p} (sᵢⱼ − aᵢ)², sᵢᵢ from ``(..., r, k + 2)`` scores of r
    of a place's images (the place's from image ``first`` on) against its k images, T and m
    (leading axes flattened to m rows)."""
    r = np.arange(g.shape[-2])
    own = g[..., r, first + r].reshape(-1)
    g = g.reshape(-1, k + 2)
    a = g[:, k + 1]
    return np.stack([g[:, k], a, g[:, :k].sum(axis=1), ((g[:, :k] - a[:, None]) ** 2).sum(axis=1), own])


def _positive_from_terms(same: np.ndarray, own: np.ndarray, labels: np.ndarray, n_places: int) -> np.ndarray:
    """``(n_places,)`` ``positive_means`` from the place terms: Σ_{i≠j∈p} sᵢⱼ = Σ_{i∈p} (Σ_{j∈p} sᵢⱼ − sᵢᵢ),
    the float64 scores the closed form took of each place's images anyway (the same value as
    ‖T_p‖² − Σ‖dᵢ‖² to float64 rounding, summed otherwise); NaN for a place of one image."""
    counts = np.bincount(labels, minlength=n_places).astype(np.float64)
    return _mean_over_pairs(np.bincount(labels, weights=same, minlength=n_places)
                            - np.bincount(labels, weights=own, minlength=n_places), counts)


def _mean_over_pairs(pair_sums: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """``pair_sums / (n(n − 1))`` per place of ``counts`` n images; NaN for a place with fewer than two."""
    pairs = counts * (counts - 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = pair_sums / pairs
    out[pairs == 0] = np.nan
    return out


def _quadratic_forms(
    d: np.ndarray, gram: np.ndarray, pool: ThreadPoolExecutor, side_by_side: bool = True
) -> np.ndarray:
    """``(n,)`` dᵢᵀ E dᵢ: float32 GEMMs with E as float32, float64 row sums.

    E is symmetric, so dᵀEd = dᵀWd with W block upper triangular (``_TRI_BLOCKS`` column
    blocks: 2·E_IJ above the diagonal blocks, E_JJ on them, exact in float32): column block
    J of dW is d[:, :J_end] @ W[:J_end, J], (1 + 1/8)·N·D² flops instead of 2·N·D².

    Each pool task takes ``_QUAD_ROWS`` rows through every column block and their row sums,
    with BLAS in one thread when ``side_by_side``: the tasks are equal, so the threads stay
    busy to the end, with no wait between blocks of rows. A GEMM splits rows between calls
    as it splits them between threads, never an inner product, so each dᵢᵀWdᵢ is the same
    float32 products and float64 sum whatever rows share its call, as in one GEMM per block
    of ``BLOCK`` rows (``tests/test_stats.py``; products so small that OpenBLAS takes its
    small-matrix kernel, a few hundred rows of a W a few dozen columns wide, round
    otherwise, within the error bound). The memory is a task's rows per thread.
    """
    n, dim = d.shape
    cols, w = triangular_blocks(gram, np.float32)
    quad = np.empty(n)
    buffers = threading.local()  # each thread's products (and float32 rows), reused across its tasks

    def rows(lo: int) -> None:
        x = d[lo : lo + _QUAD_ROWS]
        if not hasattr(buffers, "y"):
            buffers.y = np.empty((min(_QUAD_ROWS, n), dim), dtype=np.float32)
            buffers.x = None if x.dtype == np.float32 else np.empty_like(buffers.y)
        if buffers.x is not None:  # float64 input rounded once (float16 converts exactly)
            np.copyto(buffers.x[: len(x)], x, casting="same_kind")
            x = buffers.x[: len(x)]
        quad[lo : lo + len(x)] = triangular_quadratic_forms(x, cols, w, buffers.y)

    _side_by_side(pool, tuple(functools.partial(rows, lo) for lo in range(0, n, _QUAD_ROWS)), side_by_side)
    return quad


def triangular_blocks(gram: np.ndarray, dtype) -> tuple[list[tuple[int, int]], list[np.ndarray]]:
    """W, block upper triangular with dᵀWd = dᵀEd for a symmetric ``(D, D)`` E, in ``dtype``:
    ``_TRI_BLOCKS`` column blocks (c0, c1), block J the rows ``:c1`` of E's columns ``c0:c1``
    with those above the diagonal block doubled (exact in any binary float). Column block J
    of dW is then d[:, :c1] @ W_J: (1 + 1/``_TRI_BLOCKS``)·N·D² flops instead of 2·N·D²."""
    dim = gram.shape[0]
    edges = np.linspace(0, dim, min(_TRI_BLOCKS, dim) + 1).round().astype(int)
    cols = list(zip(edges[:-1].tolist(), edges[1:].tolist()))
    w = [np.array(gram[:hi, lo:hi], dtype=dtype) for lo, hi in cols]
    for wj, (lo, _) in zip(w, cols):
        wj[:lo] *= 2
    return cols, w


def triangular_quadratic_forms(x: np.ndarray, cols: list[tuple[int, int]], w: list[np.ndarray],
                               y: np.ndarray) -> np.ndarray:
    """``(n,)`` xᵢᵀWxᵢ of the rows ``x`` through ``triangular_blocks``' W: each column block of xW
    into ``y`` (a buffer of W's dtype, at least x's shape), then the float64 row sums of (xW)∘x."""
    y = y[: len(x)]
    for (c0, c1), wj in zip(cols, w):
        np.matmul(x[:, :c1], wj, out=y[:, c0:c1])
    return np.einsum("ij,ij->i", y, x, dtype=np.float64)


def fit_device() -> str | None:
    """Where a database fit's products run (``numbers.fit_retrieval``): ``VPR_EXPLORER_DEVICE`` read.

    Returns:
        ``None`` for numpy (the variable unset, empty or ``numpy``; ``auto`` without a GPU), else
        the torch device's name (``auto`` with a GPU: ``"cuda"``).

    Raises:
        VPRInputError: naming the variable, for a value that is not ``numpy``, ``auto``, ``cpu``,
            ``cuda`` or ``cuda:N``, or a GPU torch cannot see.
    """
    value = os.environ.get(DEVICE_ENV, "").strip()
    if value in ("", "numpy"):
        return None
    import torch

    if value == "auto":
        return "cuda" if torch.cuda.is_available() else None
    try:
        return str(torch_device(value))
    except VPRInputError as exc:  # its reason, then what this variable takes
        reason = str(exc).split(": ", 1)[-1].split(";", 1)[0]
        raise VPRInputError(f"{DEVICE_ENV}={value}: {reason}; set it to numpy (the default), auto, cpu, "
                            "cuda or cuda:N") from None


def torch_device(device: object):
    """``torch.device(device)``, checked usable here; a ``VPRInputError`` naming ``device=`` otherwise."""
    try:
        import torch
    except ImportError:  # pragma: no cover (torch is a dependency)
        raise VPRInputError(f"device={device!r}: needs torch (pip install torch); or leave device unset") from None
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise VPRInputError(f"device={device!r}: not a torch device; use e.g. 'cpu' or 'cuda'") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise VPRInputError(f"device={device!r}: no CUDA device is available here; use device='cpu' or leave it unset")
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise VPRInputError(f"device={device!r}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    if dev.type not in ("cpu", "cuda"):
        raise VPRInputError(f"device={device!r}: only 'cpu' and 'cuda' devices are supported")
    return dev


class ieee_float32:
    """Context: torch float32 matmuls in full float32 (no TF32 on CUDA), restored on exit."""

    def __enter__(self):
        import torch

        self.torch = torch
        self.saved = torch.get_float32_matmul_precision()
        torch.set_float32_matmul_precision("highest")
        return self

    def __exit__(self, *exc) -> None:
        self.torch.set_float32_matmul_precision(self.saved)


def _closed_form_torch(
    d: np.ndarray, labels: np.ndarray, counts: np.ndarray, n_neg: np.ndarray, block: int, threads: int, *, device
) -> _Moments:
    """μ and σ² as ``_closed_form_float32``, the two N·D² products as torch matmuls on ``device``.

    Blocks of rows go to the device once per pass; E is summed there in float64, and the
    quadratic forms use the whole E (2·N·D² flops: simpler than the triangle, and a GPU has
    them to spare). The per-place float64 terms stay on the CPU (O(N·k·D)).
    """
    import torch

    n, dim = d.shape
    centre = _centre(d)
    dtype32 = d.dtype == np.float32
    m = torch.from_numpy(centre if dtype32 else centre.astype(np.float64)).to(device)

    def rows(lo: int):
        return torch.from_numpy(np.ascontiguousarray(d[lo : lo + block])).to(device)

    with ieee_float32():
        gram = torch.zeros((dim, dim), dtype=torch.float64, device=device)
        total = torch.zeros(dim, dtype=torch.float64, device=device)
        for lo in range(0, n, block):
            x = rows(lo)
            e = (x - m).to(torch.float32)  # float32 − float32, or float64 − float64 then one rounding
            gram += (e.T @ e).to(torch.float64)
            total += x.sum(dim=0, dtype=torch.float64)
        gram32 = gram.to(torch.float32)
        quad = torch.empty(n, dtype=torch.float64, device=device)
        for lo in range(0, n, block):
            x = rows(lo).to(torch.float32)
            quad[lo : lo + len(x)] = ((x @ gram32).to(torch.float64) * x.to(torch.float64)).sum(dim=1)
        quad, total = quad.cpu().numpy(), total.cpu().numpy()
    with ThreadPoolExecutor(threads) as pool:
        terms = _place_terms(d, labels, counts, np.stack([total, centre]), pool)
    return _moments(terms, quad, n_neg)


_CLOSED_FORMS = {Precision.FLOAT32: _closed_form_float32, Precision.FLOAT64: _closed_form_float64}


def _parts(pool: ThreadPoolExecutor, fn: Callable[[slice], object], n: int) -> list:
    """``fn`` on consecutive slices of ``_PART`` rows of ``range(n)``, in the pool (numpy frees the GIL).

    The slices do not depend on the number of threads, so neither does any result.
    """
    return list(pool.map(fn, [slice(lo, min(lo + _PART, n)) for lo in range(0, n, _PART)]))


_BLAS_LOCK = threading.Lock()
_BLAS_USERS = [0, None]  # callers inside ``one_blas_thread``, and the limiter they share


@contextlib.contextmanager
def one_blas_thread():
    """BLAS in one thread while inside, for callers whose own threads parallelise: the closed
    form's halves (``_side_by_side``), ``thresholds``' tiles (a multithreaded GEMM of 80 ×
    2,048 × 80 waits more on its threads than it computes: 15× slower on a loaded machine) and
    ``views.numbers.decide_queries``' pieces of places.

    Process-wide (OpenBLAS has one setting): nested and concurrent callers share one limiter,
    the last to leave restores the count. On OpenBLAS's SkylakeX kernel the GEMMs used here
    give the same value per element whatever the thread count (they split rows and columns
    between threads, never the sum); its Haswell kernel splits the sum of some shapes (a
    (64 × 2,048) @ (2,048 × 50) product) between threads, so callers that promise the same
    numbers for any number of their own threads keep BLAS in one thread throughout.
    Without threadpoolctl, nothing is changed.
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover
        yield
        return
    with _BLAS_LOCK:
        if _BLAS_USERS[0] == 0:
            _take_blas_control()
            _BLAS_USERS[1] = threadpool_limits(limits=1, user_api="blas")
        _BLAS_USERS[0] += 1
    try:
        yield
    finally:
        with _BLAS_LOCK:
            _BLAS_USERS[0] -= 1
            if _BLAS_USERS[0] == 0:
                _take_blas_control()
                _BLAS_USERS[1].restore_original_limits()
                _BLAS_USERS[1] = None


def _take_blas_control() -> None:
    """Let this thread set OpenBLAS's thread count (under ``_BLAS_LOCK``, the one limiter's lock).

    threadpoolctl (3.8) ignores limits set on a pthreads OpenBLAS from any thread but the first
    that set one while that thread lives: once the main thread has entered ``one_blas_thread``
    (a library call before the app, as in ``benchmarks/bench_million.py``), the limits of the
    app's script threads would be dropped, and each pool thread's GEMMs would run with all of
    BLAS's threads. The limiter is process-wide by design, so whichever thread sets or
    restores it takes control first.
    """
    from threadpoolctl import OpenBLASController

    clear = getattr(OpenBLASController, "clear_controlling_thread", None)  # none before threadpoolctl 3.8
    if clear is not None:
        clear(force=True)


def _centre(d: np.ndarray) -> np.ndarray:
    """``(D,)`` m: the mean of up to ``_CENTRE_ROWS`` evenly spaced rows, rounded to float32.

    Any m gives the exact identity; one near the mean keeps |dⱼ − m|, hence the error, small.
    """
    step = max(1, len(d) // _CENTRE_ROWS)
    return d[::step].mean(axis=0, dtype=np.float64).astype(np.float32)


def _place_slabs(labels: np.ndarray, counts: np.ndarray, rows: int) -> tuple[np.ndarray, list[tuple[int, int, int]]]:
    """Images ordered by place size, then place; and slabs ``(lo, hi, k)`` of that order.

    A slab holds whole places of one size k, at most ``rows`` rows (or one place, if larger),
    so its same-place scores are one batched product ``(P, k, D) @ (P, D, k + 2)``, no padding.
    """
    size = counts[labels]
    order = np.lexsort((labels, size))
    sorted_size = size[order]
    slabs = []
    lo = 0
    while lo < len(order):
        k = int(sorted_size[lo])
        end = int(np.searchsorted(sorted_size, k, side="right"))
        step = max(1, rows // k) * k
        slabs += [(s, min(s + step, end), k) for s in range(lo, end, step)]
        lo = end
    return order, slabs


def sigma_sq_error_bound(
    descriptors: np.ndarray, labels: np.ndarray, n_places: int | None = None, *, block: int = BLOCK
) -> np.ndarray:
    """``(n,)`` bound on |σ̂ᵢ² − σᵢ²| of ``negative_stats(..., precision="float32")``: ε·Bᵢ/n⁻ᵢ.

    Bᵢ = Σⱼ (|dᵢ|·|dⱼ − m|)² over all n images and ε = γ_L + γ_D + 5u (module docstring),
    L = min(block, n). Float64 rounding (about 1e-16 · n/n⁻ᵢ) comes on top. O(n·D²) in
    float64: for tests and benchmarks.
    """
    d = validate_descriptors(descriptors, "training descriptors")
    n, dim = d.shape
    labels, n_places = _check_labels(labels, n, n_places)
    n_neg = n - np.bincount(labels, minlength=n_places)[labels]
    e = np.abs(d.astype(np.float64) - _centre(d))
    x = np.abs(d.astype(np.float64))
    b = np.einsum("ij,ij->i", x @ (e.T @ e), x)  # |dᵢ|ᵀ (Σⱼ |eⱼ||eⱼ|ᵀ) |dᵢ|
    return _epsilon(min(block, n), dim) * b / n_neg


def _epsilon(depth: int, dim: int) -> float:
    """ε = γ_L + γ_D + 5u, with u = 2⁻²⁴ (float32) and γ_k = k·u / (1 − k·u)."""
    u = 2.0**-24
    return sum(k * u / (1 - k * u) for k in (depth, dim)) + 5 * u


def mixture_moments(stats: NegativeStats) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation of each place's mixture M(p), each ``(n_places,)``.

    Mean Σ wᵢμᵢ; variance Σ wᵢ(σᵢ² + μᵢ²) − mean². NaN for places without training images.
    """
    w = stats.weights
    mean = np.bincount(stats.labels, weights=w * stats.mu, minlength=stats.n_places)
    second = np.bincount(stats.labels, weights=w * (stats.sigma**2 + stats.mu**2), minlength=stats.n_places)
    absent = stats.counts == 0
    var = np.clip(second - mean**2, 0.0, None)
    mean[absent] = np.nan
    var[absent] = np.nan
    return mean, np.sqrt(var)


def mixture_pdf(x: np.ndarray, mu: np.ndarray, sigma: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Density of Σ wᵢ N(μᵢ, σᵢ²) at ``x``.

    Args:
        x: ``(m,)`` scores.
        mu, sigma, weights: ``(k,)`` components (weights summing to 1).
    Returns:
        ``(m,)`` density; each component alone is ``weights[i] * N(x; μᵢ, σᵢ²)``, so passing
        one component with its weight gives that component's share of the curve.
    """
    x = np.asarray(x, dtype=np.float64)[:, None]
    s = np.maximum(np.asarray(sigma, dtype=np.float64), SIGMA_FLOOR)[None, :]
    z = (x - np.asarray(mu, dtype=np.float64)[None, :]) / s
    dens = np.exp(-0.5 * z**2) / (s * np.sqrt(2 * np.pi))
    return dens @ np.asarray(weights, dtype=np.float64)


def _mean_positive(sums: np.ndarray, sq: np.ndarray, labels: np.ndarray, counts: np.ndarray,
                   n_places: int) -> np.ndarray:
    """``(n_places,)`` mean same-place score from each place's descriptor sum and each image's squared norm:
    (‖Σ d‖² − Σ ‖d‖²) / (n(n − 1)); NaN for a place with fewer than two images."""
    norms = np.bincount(labels, weights=sq, minlength=n_places)
    return _mean_over_pairs(np.einsum("ij,ij->i", sums, sums) - norms, counts)


def positive_means(
    descriptors: np.ndarray, labels: np.ndarray, n_places: int, *, threads: int | None = None
) -> np.ndarray:
    """``(n_places,)`` mean same-place score over pairs i ≠ j; NaN where a place has < 2 images.

    Σ_{i≠j∈p} dᵢ·dⱼ = ‖T_p‖² − Σ_{i∈p} ‖dᵢ‖², so no pairwise matrix is needed. Rows are
    converted to float64 ``_MEAN_ROWS`` at a time into one buffer (no float64 copy of the whole
    database); up to that many rows the sums are a single product. ``threads`` (default: one
    per usable CPU, at most ``settings.MAX_DEFAULT_WORKERS``) share the conversion and ‖dᵢ‖² by rows and the place sums by bands of places:
    each number comes from the same operations in the same order whatever their count.
    """
    d = np.asarray(descriptors)
    n = len(labels)
    counts = np.bincount(labels, minlength=n_places).astype(np.float64)
    sums = np.zeros((n_places, d.shape[1]))
    sq = np.empty(n)
    buf = np.empty((min(_MEAN_ROWS, n), d.shape[1]))
    threads = thread_count(threads)
    bands = [slice(lo, min(lo + -(-n_places // threads), n_places)) for lo in range(0, n_places, -(-n_places // threads))]
    with ThreadPoolExecutor(threads) as pool:
        for lo in range(0, n, _MEAN_ROWS):
            x = buf[: min(_MEAN_ROWS, n - lo)]

            def convert(sl: slice, lo: int = lo, x: np.ndarray = x) -> None:
                np.copyto(x[sl], d[lo + sl.start : lo + sl.stop], casting="same_kind")  # float32/float16 to float64: exact
                sq[lo + sl.start : lo + sl.stop] = np.einsum("ij,ij->i", x[sl], x[sl])

            _parts(pool, convert, len(x))
            part = sparse.csr_matrix((np.ones(len(x)), (labels[lo : lo + len(x)], np.arange(len(x)))),
                                     shape=(n_places, len(x)))

            def band_sums(band: slice, part: sparse.csr_matrix = part, x: np.ndarray = x) -> None:
                sums[band] += part[band] @ x  # each place's row of the product is computed alone

            list(pool.map(band_sums, bands))
    return _mean_positive(sums, sq, labels, counts, n_places)


# --------------------------------------------------------------------------- rows of a large (memory-mapped) matrix

#: entries per chunk of ``validate_descriptors`` and of the row views below: 16 M floats, 64 MB as float32
CHECK_ELEMS = 1 << 24


@functools.cache
def _torch():
    """torch, imported on first use, its one warning about read-only arrays spent: torch warns once per
    process that it could write to one, and ``as_float32`` only reads them (a memory map's rows)."""
    import torch

    spent = np.zeros(1, dtype=np.float16)
    spent.flags.writeable = False
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        torch.from_numpy(spent)
    return torch


_TORCH_PREPARED = threading.Event()  # ``prepare_float16_reads`` started the import


def prepare_float16_reads() -> None:
    """Import torch for ``as_float32`` in a background thread now (about 1 s), not in the first pass
    over a float16 map: the app calls this when it loads a float16 database. (Two callers at once
    may both start a thread: importing twice is harmless.)"""
    if not _TORCH_PREPARED.is_set():
        _TORCH_PREPARED.set()
        threading.Thread(target=_torch, name="vpr-import-torch", daemon=True).start()


def as_float32(block: np.ndarray) -> np.ndarray:
    """``np.asarray(block, dtype=np.float32)``, a float16 block converted by torch's vectorised cast.

    The same numbers (every float16 is a float32; a NaN stays NaN, a signalling one quieted), and
    faster: numpy's float16 cast is not vectorised, and every pass over a million-image route's
    float16 map pays it again. Any other dtype is numpy's ``asarray`` (a
    float32 block is returned as is). ``RowsOf`` reads every float16 block through it, so the
    fits, scores and decisions of a mapped database do, and the automatic θ's tile sample.
    """
    if block.dtype != np.float16:  # a byte-swapped float16 too: numpy's cast
        return np.asarray(block, dtype=np.float32)
    torch = _torch()
    out = np.empty(block.shape, dtype=np.float32)
    torch.from_numpy(out).copy_(torch.from_numpy(np.ascontiguousarray(block)))
    return out


class RowsOf:
    """Rows ``rows`` of a matrix, read a block at a time: ``descriptors[rows]`` never formed.

    What the closed form needs of its input (``shape``, ``dtype``, ``len`` and indexing by a
    slice or an index array), so ``negative_stats_rows`` runs on the database images in places
    of a memory-mapped float16 database (``descriptors.store``) without gathering them: each
    block is gathered (and converted) when the pass reaches it. A slice whose rows are one
    ascending run is a view of the matrix (a memmap reads only those pages).
    """

    def __init__(self, base: np.ndarray, rows: np.ndarray | None = None) -> None:
        self.base = base
        self.rows = None if rows is None else np.asarray(rows, dtype=np.int64)
        n = len(base) if rows is None else len(self.rows)
        self.shape = (n, base.shape[1])
        # float16 blocks come out as float32 (exactly): the closed form then centres them in
        # float32, one rounding of the exact difference as the float64 route gives, without
        # float16 → float64 arithmetic; the result is that of the float32 copy, bit for bit
        self.dtype = np.dtype(np.float32) if base.dtype == np.float16 else base.dtype

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, key) -> np.ndarray:
        if self.rows is None:
            block = self.base[key]
        else:
            idx = self.rows[key]
            if isinstance(key, slice) and len(idx) and idx[-1] - idx[0] + 1 == len(idx) and (key.step or 1) == 1:
                block = self.base[idx[0] : idx[-1] + 1]
            else:
                block = self.base[idx]
        return as_float32(block) if self.dtype == np.float32 else np.asarray(block, dtype=self.dtype)


def validate_rows(view: RowsOf, what: str = "descriptors") -> None:
    """``validate_descriptors`` on the rows of a ``RowsOf``, a block at a time (rows named by their index in it)."""
    step = max(1, CHECK_ELEMS // view.shape[1])
    for lo in range(0, len(view), step):
        try:
            validate_descriptors(view[lo : lo + step], what)
        except VPRInputError as exc:  # rows of the block -> rows of the view
            raise VPRInputError(f"{exc} (counting from row {lo:,})") from None


def negative_stats_rows(
    descriptors: np.ndarray, rows: np.ndarray | None, labels: np.ndarray, n_places: int | None = None, *,
    block: int = BLOCK, threads: int | None = None,
) -> NegativeStats:
    """``negative_stats(descriptors[rows], labels, n_places)`` (float32 products) without forming ``descriptors[rows]``.

    ``descriptors`` may be a memory-mapped float16 ``(N, D)`` matrix: the three passes of the
    closed form read it a block of ``block`` rows at a time, each converted to float32 and
    dropped, so the memory beyond the D×D Gram is a few blocks (``tests/test_million.py``
    bounds it). The operations are those of ``negative_stats`` on the gathered rows (as float32
    when stored as float16), in the same order: the result is bit-identical to it.
    """
    view = RowsOf(descriptors, rows)
    if view.shape[0] == 0 or view.shape[1] == 0:
        raise VPRInputError(f"training descriptors: expected a non-empty (n_images, dim) array, got {view.shape}")
    validate_rows(view, "training descriptors")
    n = len(view)
    labels, n_places = _check_labels(labels, n, n_places)
    block, threads = _block_and_threads(block, threads)
    counts = np.bincount(labels, minlength=n_places)
    n_neg = n - counts[labels]
    fit = _closed_form_float32(view, labels, counts, n_neg, block, threads)
    sigma = np.sqrt(np.clip(fit.var, 0.0, None))
    return NegativeStats(mu=fit.mu, sigma=sigma, n_neg=n_neg.astype(np.int64), labels=labels, n_places=n_places)


class _FirstPass(RowsOf):
    """A ``RowsOf`` that hands every block the closed form's first pass reads (consecutive slices from row 0,
    ``_centred_gram``) to ``consumers`` as well: the checks ride on the Gram's reading and conversion of
    each block instead of a pass of their own. Other reads (the centre's sample, the
    place terms' gathers) are served as by ``RowsOf``; ``complete`` tells whether every row went by, in order.

    With ``ahead`` (a one-thread executor), a slice read starts reading (and consuming) the next slice of the
    same length in that thread: the reading, conversion and checks of block k + 1 overlap block k's GEMMs.
    A read-ahead that is not asked for next (the pass read otherwise) leaves the view incomplete.
    Once every row went by (or the order broke), reads are ``RowsOf``'s, from any thread.
    """

    def __init__(self, base: np.ndarray, rows: np.ndarray | None, consumers: list[Callable[[int, np.ndarray], None]],
                 ahead: ThreadPoolExecutor | None = None):
        super().__init__(base, rows)
        self.consumers = consumers
        self.next = 0  # rows handed (or being handed) to the consumers, in order
        self.broken = False
        self.ahead = ahead
        self.pending = None  # (start, stop, future, consumed) of the read-ahead
        self.lock = threading.Lock()

    @property
    def complete(self) -> bool:
        return self.next == len(self) and not self.broken

    def _read(self, start: int, stop: int, consume: bool) -> np.ndarray:
        block = RowsOf.__getitem__(self, slice(start, stop))
        if consume:
            for hand in self.consumers:
                hand(start, block)
        return block

    def close(self) -> None:
        """Wait for a read-ahead nobody asked for; one that was consumed leaves the view incomplete
        (its errors, and the sums, are then the fallback's)."""
        if self.pending is not None:
            _, _, future, consumed = self.pending
            self.pending = None
            future.exception()  # waits
            self.broken |= consumed

    def __getitem__(self, key) -> np.ndarray:
        if (not (isinstance(key, slice) and key.step in (None, 1) and key.start is not None)
                or (self.pending is None and (self.broken or self.next == len(self)))):
            return super().__getitem__(key)  # stateless: the later passes read in the pool's threads
        with self.lock:
            return self._in_order(key)

    def _in_order(self, key: slice) -> np.ndarray:
        start, stop, _ = key.indices(len(self))
        if self.pending is not None and self.pending[:2] == (start, stop):
            future = self.pending[2]
            self.pending = None
            block = future.result()
        else:
            self.close()
            consume = not self.broken and start == self.next < len(self) and stop > start
            if consume:
                self.next = stop
            block = self._read(start, stop, consume)
        ahead = min(stop + (stop - start), len(self))
        if self.ahead is not None and start < stop < len(self):
            consume = not self.broken and self.next == stop
            if consume:
                self.next = ahead
            self.pending = (stop, ahead, self.ahead.submit(self._read, stop, ahead, consume), consume)
        return block


def stats_rows(descriptors: np.ndarray, rows: np.ndarray | None, labels: np.ndarray, n_places: int | None = None, *,
               block: int = BLOCK, threads: int | None = None,
               device: object | None = None) -> tuple[NegativeStats, np.ndarray]:
    """``negative_stats_rows`` and the positive means of the same rows, reading each block once for the checks.

    The closed form's first pass (the Gram) reads the rows in consecutive blocks; each block,
    converted once, is also checked (``validate_descriptors``: a bad row stops the fit with the
    message of ``validate_rows``, before any product of it). The next block is read, converted
    and checked in a thread of its own while the current one's products run (``_FirstPass``).
    The statistics are those of ``negative_stats_rows`` bit for bit (the same operations on the
    same float32 blocks); should the first pass read otherwise, the checks run on their own.
    The positive means come from the place terms' float64 same-place scores
    (``_positive_from_terms``): ``positive_means`` to float64 rounding, with no pass of their own.

    With ``device`` (a torch device, as ``negative_stats`` takes it) the two N·D² products run
    as torch matmuls there (``_closed_form_torch``, whose first pass reads the blocks in the
    same order, so they are checked as it reads them): the statistics of
    ``negative_stats(..., device=device)`` on the same rows, within the same error bound as
    the numpy path.
    """
    base = RowsOf(descriptors, rows)
    if base.shape[0] == 0 or base.shape[1] == 0:
        raise VPRInputError(f"training descriptors: expected a non-empty (n_images, dim) array, got {base.shape}")
    n = len(base)
    labels, n_places = _check_labels(labels, n, n_places)

    def check(lo: int, x: np.ndarray) -> None:
        try:
            validate_descriptors(x, "training descriptors")
        except VPRInputError as exc:
            raise VPRInputError(f"{exc} (counting from row {lo:,})") from None

    block, threads = _block_and_threads(block, threads)
    counts = np.bincount(labels, minlength=n_places)
    n_neg = n - counts[labels]
    closed_form = (_closed_form_float32 if device is None
                   else functools.partial(_closed_form_torch, device=torch_device(device)))
    with ThreadPoolExecutor(1, thread_name_prefix="vpr-read-ahead") as ahead:
        view = _FirstPass(descriptors, rows, [check], ahead if threads > 1 else None)
        try:
            fit = closed_form(view, labels, counts, n_neg, block, threads)
        finally:
            view.close()
    if not view.complete:  # the first pass read otherwise: the checks on their own
        validate_rows(base, "training descriptors")
    sigma = np.sqrt(np.clip(fit.var, 0.0, None))
    stats = NegativeStats(mu=fit.mu, sigma=sigma, n_neg=n_neg.astype(np.int64), labels=labels, n_places=n_places)
    return stats, _positive_from_terms(fit.terms.same, fit.terms.own, labels, n_places)
