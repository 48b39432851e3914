"""Negative similarity statistics of each training image, in closed form (DESIGN.md §2).

For training image i of place p, its negative scores are S⁻ᵢ = { dᵢ·dⱼ : j in a place r ≠ p }.
A normal N(μᵢ, σᵢ²) is fitted to them (maximum likelihood, so σᵢ is the population
standard deviation), and the place's negative Gaussian mixture is
M(p) = Σᵢ wᵢ N(μᵢ, σᵢ²) with wᵢ = |S⁻ᵢ| / Σⱼ |S⁻ⱼ| over p's images.

No N×N similarity matrix is formed. With T = Σⱼ dⱼ, T_p = Σ_{j∈p} dⱼ, C = Σⱼ dⱼdⱼᵀ and n⁻ᵢ the
number of negatives:

    μᵢ     = dᵢ·(T − T_p) / n⁻ᵢ
    E[s²]ᵢ = (dᵢᵀ C dᵢ − Σ_{j∈p} (dᵢ·dⱼ)²) / n⁻ᵢ,     σᵢ² = E[s²]ᵢ − μᵢ²

which is O(N·D²) instead of O(N²·D). Sums are accumulated in float64.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse

from vpr_explorer.errors import VPRInputError

#: σ below this is treated as this when a weight 1/σ² or a density is needed: a place
#: whose image has a single negative score (σ = 0) would otherwise divide by zero.
SIGMA_FLOOR = 1e-6


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
    """Return ``descriptors`` as a 2-D float array; raise on NaN, inf or zero rows."""
    d = np.asarray(descriptors)
    if d.ndim != 2 or d.shape[0] == 0 or d.shape[1] == 0:
        raise VPRInputError(f"{what}: expected a non-empty (n_images, dim) array, got shape {d.shape}")
    if not np.issubdtype(d.dtype, np.floating):
        d = d.astype(np.float32)
    bad = ~np.isfinite(d).all(axis=1)
    if bad.any():
        raise VPRInputError(
            f"{what}: rows {_first(bad)} contain NaN or inf; recompute the descriptors (clear the cache) "
            "or remove those images"
        )
    zero = np.einsum("ij,ij->i", d, d, dtype=np.float64) < 1e-24
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


def negative_stats(
    descriptors: np.ndarray, labels: np.ndarray, n_places: int | None = None, *, block: int = 8192
) -> NegativeStats:
    """μᵢ, σᵢ of every training image's negative scores, in closed form.

    Args:
        descriptors: ``(n, D)`` L2-normalised descriptors of the training images.
        labels: ``(n,)`` place id of each image (``>= 0``).
        n_places: number of place ids; defaults to ``labels.max() + 1``.
        block: rows processed at a time (bounds memory at Nordland scale).
    """
    d = validate_descriptors(descriptors, "training descriptors")
    n, dim = d.shape
    labels, n_places = _check_labels(labels, n, n_places)
    counts = np.bincount(labels, minlength=n_places)
    n_neg = n - counts[labels]

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
    var = second / n_neg - mu**2
    # Cancellation can leave -1e-17 where the true variance is 0 (all negatives equal).
    sigma = np.sqrt(np.clip(var, 0.0, None))
    return NegativeStats(mu=mu, sigma=sigma, n_neg=n_neg.astype(np.int64), labels=labels, n_places=n_places)


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


def positive_means(descriptors: np.ndarray, labels: np.ndarray, n_places: int) -> np.ndarray:
    """``(n_places,)`` mean same-place score over pairs i ≠ j; NaN where a place has < 2 images.

    Σ_{i≠j∈p} dᵢ·dⱼ = ‖T_p‖² − Σ_{i∈p} ‖dᵢ‖², so no pairwise matrix is needed.
    """
    d = np.asarray(descriptors, dtype=np.float64)
    counts = np.bincount(labels, minlength=n_places).astype(np.float64)
    sums = sparse.csr_matrix((np.ones(len(labels)), (labels, np.arange(len(labels)))), shape=(n_places, len(labels))) @ d
    norms = np.bincount(labels, weights=np.einsum("ij,ij->i", d, d), minlength=n_places)
    pairs = counts * (counts - 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (np.einsum("ij,ij->i", sums, sums) - norms) / pairs
    out[pairs == 0] = np.nan
    return out
