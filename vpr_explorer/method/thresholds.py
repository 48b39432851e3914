"""Per-place thresholds θ_p from negative statistics, the threshold family, global thresholds.

* simple:   θ_p = (1/n_p) Σᵢ μᵢ
* weighted: θ_p = Σᵢ (wᵢτᵢ² / Σⱼ wⱼτⱼ²) μᵢ with τ = 1/σ (paper eq. 4, weights normalised
  as the authors' code does; read literally, eq. 4 with wᵢ = 1/n is not a weighted mean)
* family:   θ_p(k) = θ_p + k·s_p, s_p the standard deviation of the mixture M(p); k = 0 is
  the paper
* automatic global (VPR_Tutorial, after Schubert et al. "Beyond ANN"):
  θ = median(S) + Φ⁻¹(1 − 10⁻⁶)·MAD(S)/0.675 over the training similarity matrix, or a
  sample of it (``training_pair_scores``; a protocol's splits share one: ``pooled_pair_sample``)
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from scipy.stats import norm

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.stats import SIGMA_FLOOR, NegativeStats, as_float32, mixture_moments, one_blas_thread
from vpr_explorer.settings import default_workers

#: Φ⁻¹(1 − 10⁻⁶) ≈ 4.753, the automatic threshold's multiple of the robust spread.
AUTO_Z = float(norm.ppf(1 - 1e-6))
#: The MAD of normal scores in units of their σ (Φ⁻¹(0.75) ≈ 0.6745, as the automatic rule rounds it):
#: ``MAD / MAD_PER_SIGMA`` is the automatic threshold's robust spread.
MAD_PER_SIGMA = 0.675
#: Pairs used for the automatic global threshold when the training set has more.
AUTO_MAX_PAIRS = 2_000_000
#: How a training set with more pairs than ``AUTO_MAX_PAIRS`` is sampled (``training_pair_scores``).
AUTO_SAMPLES = ("tiles", "pairs")
#: Images the tile sample reads at most (2¹⁷, above the largest training sets of the protocols and
#: the app's 110k route, whose samples it leaves whole): a larger training set's tiles are drawn
#: over a seeded subset of this many, so at 500,000 images they are 8,590 GEMMs of groups of 15
#: over 131,072 gathered rows, not 125,000 GEMMs of groups of 4 over all 500,000
#: (``benchmarks/bench_auto_sample.py`` compares the θ and its spread over seeds with the
#: independent pairs').
AUTO_TILE_IMAGES = 1 << 17
#: Rows gathered at a time by the tile sample (2,048 × 2,048 float32: 16 MiB): at 33,108 × 2,048
#: (the app at 110k images) 17 chunks share the threads evenly, and each chunk fits in memory
#: that the allocator reuses for the next instead of mapping fresh pages.
TILE_ROWS = 2048
#: Independent pairs (``sample="pairs"``) scored per task.
PAIR_BLOCK = 4096
#: Threads scoring the sample's tiles or pair blocks.
PAIR_WORKERS = default_workers(4)


class ThresholdMethod(StrEnum):
    """How μᵢ of a place's images combine into θ_p."""

    SIMPLE = "simple"
    WEIGHTED = "weighted"


THRESHOLD_LABELS = {
    ThresholdMethod.SIMPLE: "simple: mean of the place's μᵢ",
    ThresholdMethod.WEIGHTED: "weighted (eq. 4, normalised): Σ wᵢτᵢ²μᵢ / Σ wⱼτⱼ², τ = 1/σ",
}


def _simple(stats: NegativeStats) -> np.ndarray:
    return np.bincount(stats.labels, weights=stats.mu, minlength=stats.n_places) / stats.counts


def _weighted(stats: NegativeStats) -> np.ndarray:
    tau2 = 1.0 / np.maximum(stats.sigma, SIGMA_FLOOR) ** 2
    v = stats.weights * tau2
    return np.bincount(stats.labels, weights=v * stats.mu, minlength=stats.n_places) / np.bincount(
        stats.labels, weights=v, minlength=stats.n_places
    )


_THRESHOLDS = {ThresholdMethod.SIMPLE: _simple, ThresholdMethod.WEIGHTED: _weighted}


def place_thresholds(stats: NegativeStats, method: ThresholdMethod | str = ThresholdMethod.WEIGHTED) -> np.ndarray:
    """``(n_places,)`` θ_p; NaN for places without training images."""
    try:
        fn = _THRESHOLDS[ThresholdMethod(method)]
    except ValueError:
        raise VPRInputError(
            f"threshold method {method!r}: choose one of {', '.join(m.value for m in ThresholdMethod)}"
        ) from None
    with np.errstate(invalid="ignore", divide="ignore"):
        theta = fn(stats)
    theta[stats.counts == 0] = np.nan
    return theta


def threshold_family(theta: np.ndarray, spread: np.ndarray, k: float) -> np.ndarray:
    """θ_p(k) = θ_p + k·s_p, each ``(n_places,)``."""
    if not np.isfinite(k):
        raise VPRInputError(f"k={k!r}: must be a finite number of mixture standard deviations")
    return theta + k * spread


def mixture_spread(stats: NegativeStats) -> np.ndarray:
    """``(n_places,)`` s_p, the standard deviation of each place's negative mixture M(p)."""
    return mixture_moments(stats)[1]


def adaptive_k(positive_mean: np.ndarray, negative_mean: np.ndarray, negative_std: np.ndarray) -> np.ndarray:
    """Per-place k = clip((μ⁺ − μ⁻) / (2σ⁻), 1, 2), from the authors' later work.

    μ⁺ is the mean same-place score, μ⁻ and σ⁻ the mixture's mean and standard deviation.
    A place without a same-place pair (μ⁺ NaN) gets k = 1.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        k = (positive_mean - negative_mean) / (2 * np.maximum(negative_std, SIGMA_FLOOR))
    return np.clip(np.nan_to_num(k, nan=1.0), 1.0, 2.0)


def training_pair_scores(
    descriptors: np.ndarray, *, max_pairs: int = AUTO_MAX_PAIRS, seed: int = 0, rows: np.ndarray | None = None,
    sample: str = "tiles", block: int = PAIR_BLOCK, workers: int = PAIR_WORKERS, images: int = AUTO_TILE_IMAGES,
) -> np.ndarray:
    """Similarities of distinct training pairs: all of them (i < j), or a seeded sample of about ``max_pairs``.

    Args:
        descriptors: ``(n, D)`` training descriptors, or the rows ``rows`` of a larger array
            (then the result is exactly that of ``descriptors[rows]``, without copying it).
        sample: above ``max_pairs`` pairs, which sample (docs/method.md, "Retrieval: baselines and filter-then-rank"):

            * ``"tiles"`` (default): a seeded permutation of the n images, of which the first
              m = min(n, ``images``) are cut into g = ⌈m²/max_pairs⌉ (≥ 3) groups of ⌊m/g⌋ or
              ⌈m/g⌉ images, and every pair between group a and group a + 1 (mod g): g dense
              tiles of about (max_pairs/m)² scores, each one float32 GEMM of gathered rows.
              About m²/g ≤ max_pairs pairs, all distinct, no image with itself, and every image
              of the m in the same number of them to within 2 (balanced, as in the full set,
              where each is in n − 1). Up to ``images`` training images (``AUTO_TILE_IMAGES``)
              the m are all of them; above, a uniform seeded subset, so the tiles stay GEMMs of
              about max_pairs/``images`` images a side and only m rows are read, however large
              the training set. Pairs in one tile share rows and columns, and a subset's pairs
              share its images, so they are not independent: ``tests/test_thresholds.py`` and
              ``benchmarks/bench_auto_sample.py`` show that the automatic θ from them agrees
              with the independent-pairs θ within its sampling error, with the subset too.
            * ``"pairs"``: ``max_pairs`` independent uniform pairs (i, j ≠ i), scored ``block``
              at a time by ``workers`` threads (each gathers 2·block rows: memory-bound).
        images: the most images the ``"tiles"`` sample reads (above, a seeded subset of this
            many); it must leave more than ``max_pairs`` pairs.

    Each score is the same float32 value whatever ``block``, ``workers`` or the BLAS thread count.
    """
    if sample not in AUTO_SAMPLES:
        raise VPRInputError(f"sample={sample!r}: choose one of {', '.join(AUTO_SAMPLES)}")
    if rows is not None:
        rows = np.asarray(rows, dtype=np.int64)
    n = len(descriptors) if rows is None else len(rows)
    total = n * (n - 1) // 2
    if total == 0:
        raise VPRInputError("the automatic global threshold needs at least 2 training images")

    def gather(idx: np.ndarray) -> np.ndarray:
        """float32 rows ``idx`` of the training set."""
        return as_float32(descriptors[idx if rows is None else rows[idx]])

    if total <= max_pairs:
        d = np.asarray(descriptors if rows is None else descriptors[rows], dtype=np.float32)
        iu = np.triu_indices(n, k=1)
        # one BLAS thread: OpenBLAS's Haswell kernel splits this product's sums between its
        # threads, and a caller beside another thread's limiter would get either count
        with one_blas_thread():
            return (d @ d.T)[iu]
    rng = np.random.default_rng(seed)
    if sample == "tiles":
        if n > images and images * (images - 1) // 2 <= max_pairs:
            raise VPRInputError(f"images={images}: a subset of the tile sample needs more than max_pairs="
                                f"{max_pairs} pairs")
        perm = rng.permutation(n)[:images]  # the first ``images`` of one permutation: every image when n <= images
        return _tile_scores(gather, perm, *tile_groups(len(perm), max_pairs), max(1, workers))
    i = rng.integers(0, n, size=max_pairs)
    j = rng.integers(0, n - 1, size=max_pairs)
    j = j + (j >= i)  # uniform over j != i
    out = np.empty(max_pairs, dtype=np.float32)

    def score(lo: int) -> None:
        hi = lo + block
        out[lo:hi] = np.einsum("ij,ij->i", gather(i[lo:hi]), gather(j[lo:hi]))

    with ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="vpr-pairs") as pool:
        list(pool.map(score, range(0, max_pairs, block)))
    return out


def tile_groups(n: int, max_pairs: int) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """Group edges ``(g + 1,)`` of n permuted images in g = ⌈n²/max_pairs⌉ (at least 3) near-equal
    groups, and the tiles (a, a + 1 mod g) whose pairs are scored."""
    g = min(n, max(3, -(-n * n // max_pairs)))
    edges = np.arange(g + 1) * n // g
    return edges, [(a, (a + 1) % g) for a in range(g)]


def _tile_scores(gather, perm: np.ndarray, edges: np.ndarray, tiles: list[tuple[int, int]], workers: int) -> np.ndarray:
    """The ``"tiles"`` sample: scores of every pair between permuted groups a and a + 1, tile by tile.

    ``gather(perm[lo:hi])`` gives the float32 rows of permuted positions lo..hi; ``edges`` and
    ``tiles`` as ``tile_groups`` gives them.

    Groups are read ``TILE_ROWS`` rows at a time (with the next group, and group 0 for the
    last tile), so each image is gathered about once and memory stays at ~2·TILE_ROWS·D floats
    per worker. A tile's scores are ``x_a @ x_bᵀ``: one GEMM of fixed shape, whichever chunk
    or thread computes it.
    """
    sizes = np.diff(edges)
    counts = np.array([sizes[a] * sizes[b] for a, b in tiles], dtype=np.int64)
    offsets = np.r_[0, np.cumsum(counts)]
    out = np.empty(int(offsets[-1]), dtype=np.float32)
    per_chunk = max(1, TILE_ROWS // (int(sizes.max()) + 1))
    chunks = [range(lo, min(lo + per_chunk, len(tiles))) for lo in range(0, len(tiles), per_chunk)]

    def score(chunk: range) -> None:
        first = tiles[chunk[0]][0]
        last = max(max(tiles[k]) for k in chunk)  # groups first..last are read together (0 apart)
        lo, hi = int(edges[first]), int(edges[last + 1])
        x = gather(perm[lo:hi])
        x0 = None
        for k in chunk:
            a, b = tiles[k]
            xa = x[edges[a] - lo : edges[a + 1] - lo]
            if b == 0:  # the last tile wraps to group 0
                x0 = gather(perm[: edges[1]]) if x0 is None else x0
                xb = x0
            else:
                xb = x[edges[b] - lo : edges[b + 1] - lo]
            np.matmul(xa, xb.T, out=out[offsets[k] : offsets[k + 1]].reshape(len(xa), len(xb)))

    with one_blas_thread(), ThreadPoolExecutor(max_workers=workers, thread_name_prefix="vpr-tiles") as pool:
        list(pool.map(score, chunks))
    return out


def _tile_pairs(perm: np.ndarray, edges: np.ndarray, tiles: list[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray]:
    """``(m,)`` row and column images of every score ``_tile_scores`` gives, in its order."""
    sizes = np.diff(edges)
    a = np.array([t[0] for t in tiles], dtype=np.int64)
    b = np.array([t[1] for t in tiles], dtype=np.int64)
    counts = sizes[a] * sizes[b]
    k = np.repeat(np.arange(len(tiles)), counts)
    local = np.arange(int(counts.sum())) - np.repeat(np.r_[0, np.cumsum(counts)[:-1]], counts)
    width = sizes[b][k]
    return perm[edges[a][k] + local // width], perm[edges[b][k] + local % width]


@dataclass(frozen=True, eq=False)
class PooledPairSample:
    """The automatic θ's training pairs for every split of one protocol run, sampled once.

    Built by ``pooled_pair_sample``. Split r's scores (``scores(r)``) are every distinct pair
    of its training images (``trains[r]``) when they have at most ``max_pairs`` pairs, as
    ``training_pair_scores`` gives them; above, the pooled tiles' pairs whose two images
    both train in split r (``pooled``, sorted, the scores of images ``image_a`` × ``image_b``).
    """

    descriptors: np.ndarray
    trains: tuple[np.ndarray, ...]
    max_pairs: int
    pooled: np.ndarray  # (m,) float32 scores of the pooled tiles, ascending (empty when no split samples)
    image_a: np.ndarray  # (m,) each score's row image, an index into ``descriptors``
    image_b: np.ndarray  # (m,) its column image

    def _sampled(self, r: int) -> bool:
        n = len(self.trains[r])
        return n * (n - 1) // 2 > self.max_pairs

    def scores(self, r: int) -> np.ndarray:
        """Split r's training pair scores, float32 (sampled: ascending)."""
        train = self.trains[r]
        if not self._sampled(r):
            return training_pair_scores(self.descriptors, rows=train, max_pairs=self.max_pairs)
        inside = np.zeros(len(self.descriptors), dtype=bool)
        inside[train] = True
        return self.pooled[inside[self.image_a] & inside[self.image_b]]

    def theta(self, r: int) -> float:
        """Split r's automatic global θ: ``auto_global_threshold(scores(r))``, the same float.

        A sampled split's scores come sorted, so its median and MAD are read off them
        (``_sorted_auto_threshold``) instead of partitioning 2·10⁶ values twice.
        """
        s = self.scores(r)
        return _sorted_auto_threshold(s) if self._sampled(r) else auto_global_threshold(s)


def _kth_of_two(a: np.ndarray, b: np.ndarray, k: int) -> float:
    """The k-th smallest (0-based) of the values of two ascending arrays together."""
    lo, hi = max(0, k + 1 - len(b)), min(k + 1, len(a))
    while lo < hi:  # i values from a and k + 1 − i from b are the k + 1 smallest
        i = (lo + hi) // 2
        if a[i] < b[k - i]:
            lo = i + 1
        else:
            hi = i
    j = k + 1 - lo
    return float(max(a[lo - 1] if lo > 0 else -np.inf, b[j - 1] if j > 0 else -np.inf))


def _middle(kth, n: int) -> float:
    # np.median's value: the middle element, or the mean of the two middle ones as np.mean forms it
    return kth(n // 2) if n % 2 else (kth(n // 2 - 1) + kth(n // 2)) / 2


def _sorted_auto_threshold(s: np.ndarray) -> float:
    """``auto_global_threshold`` of ascending scores ``s``, the same float, in O(n) cheap steps.

    The median is read off the sorted values; the deviations |s − med| are two ascending
    runs (med − s below the median, reversed, and s − med above: the same float64 values
    ``np.abs(s - med)`` holds), so their median is found by bisection across the two.
    """
    n = len(s)
    if n == 0:
        raise VPRInputError("the automatic global threshold needs at least one training score")
    med = _middle(lambda k: float(s[k]), n)
    split = int(np.searchsorted(s, med, side="right"))
    below = med - np.asarray(s[:split][::-1], dtype=np.float64)
    above = np.asarray(s[split:], dtype=np.float64) - med
    mad = _middle(lambda k: _kth_of_two(below, above, k), n)
    return float(med + AUTO_Z * mad / MAD_PER_SIGMA)


def pooled_pair_sample(
    descriptors: np.ndarray, trains, *, max_pairs: int = AUTO_MAX_PAIRS, seed: int = 0, workers: int = PAIR_WORKERS,
) -> PooledPairSample:
    """One tile sample for the automatic θ of all of a protocol run's splits.

    ``training_pair_scores`` per split draws a tile sample of the split's own training images,
    one set of small GEMMs per split. Here one seeded tile sample is drawn over the images
    that train in any split whose training set has more than ``max_pairs`` pairs (their
    union U: for the paper protocol every image in a place), and each such split keeps the
    pooled pairs whose two images both train in it, dropping the rows and columns of its
    queries (and, in the open set, of its held-out places' images).

    The tiles are those of ``training_pair_scores`` (a seeded permutation of U in g groups,
    every pair between group a and a + 1 mod g), with g = ⌈n_min²/max_pairs⌉ (at least 3)
    for n_min the smallest such training set, so each split keeps about
    (n_train/|U|)²·|U|²/g ≤ max_pairs·(n_train/n_min)² pairs: about ``max_pairs``. A split's
    kept pairs are a block sample of its training pairs, all distinct, no image with
    itself; every pooled image is in the same number of pooled pairs (to within 2), and a
    training image keeps those whose partner also trains (a binomial share). Splits with
    at most ``max_pairs`` training pairs score all of them, as ``training_pair_scores`` does.

    Args:
        descriptors: ``(n_images, D)``, any float dtype (a memory map is read in row chunks).
        trains: per split, the indices of its training images.
    """
    trains = tuple(np.asarray(t, dtype=np.int64) for t in trains)
    sampled = [t for t in trains if len(t) * (len(t) - 1) // 2 > max_pairs]
    empty = np.empty(0, dtype=np.int64)
    if not sampled:
        return PooledPairSample(descriptors, trains, max_pairs, np.empty(0, dtype=np.float32), empty, empty)
    member = np.zeros(len(descriptors), dtype=bool)  # the union, ascending (np.unique's result, without its sort)
    for t in sampled:
        member[t] = True
    images = np.flatnonzero(member)
    n_min = min(len(t) for t in sampled)
    n = len(images)
    g = min(n, max(3, -(-n_min * n_min // max_pairs)))
    edges = np.arange(g + 1) * n // g
    tiles = [(a, (a + 1) % g) for a in range(g)]
    perm = images[np.random.default_rng(seed).permutation(n)]

    def gather(idx: np.ndarray) -> np.ndarray:
        return as_float32(descriptors[idx])

    pooled = _tile_scores(gather, perm, edges, tiles, max(1, workers))
    image_a, image_b = _tile_pairs(perm, edges, tiles)
    order = np.argsort(pooled, kind="stable")
    return PooledPairSample(descriptors, trains, max_pairs, pooled[order], image_a[order], image_b[order])


def auto_global_threshold(scores: np.ndarray) -> float:
    """θ = median(S) + Φ⁻¹(1 − 10⁻⁶)·MAD(S)/0.675 over flat training similarity scores ``S``."""
    s = np.asarray(scores, dtype=np.float64).ravel()
    if s.size == 0:
        raise VPRInputError("the automatic global threshold needs at least one training score")
    med = np.median(s)
    mad = np.median(np.abs(s - med))
    return float(med + AUTO_Z * mad / MAD_PER_SIGMA)
