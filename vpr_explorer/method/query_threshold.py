"""Per-query adaptive threshold (Vysotska et al., ICRA 2025): patch, KS test, mixture, Kalman filter.

For each query q of a sequence, in order:

1. **Patch.** Its best match m_q = the lowest-index database image within ``TIE_TOLERANCE``
   of the row's top score s_q (the answer rule of ``retrieval``). The patch is the p × p
   block of the ``(n_queries, n_database)`` similarity matrix S with its bottom-right corner
   at (q, m_q): queries q−p+1..q × database images m_q−p+1..m_q (``Placement.TRAILING``,
   default), so a query's threshold uses only queries already seen, and a match on a
   sequence shows as a diagonal of high values across the block. ``Placement.CENTRED`` puts
   (q, m_q) at row and column p//2 of the block instead (queries q−p//2..q−p//2+p−1). A block
   reaching past an edge of S is cut there, not shifted: it then has fewer than p² values.
2. **Unimodality test.** A one-sample two-sided Kolmogorov–Smirnov test of the patch's
   values against the normal with the patch's own mean and population standard deviation
   (ddof 0): D = max over the sorted values x₍ᵢ₎ of max(i/n − Φ(z₍ᵢ₎), Φ(z₍ᵢ₎) − (i−1)/n),
   p-value ``scipy.stats.kstwo.sf(D, n)`` (what ``scipy.stats.kstest`` reports for n ≤ 10⁴,
   clipped to [0, 1]). The patch is **bimodal** when p < α (α = 0.05), decided as
   D > ``kstwo.isf(α, n)``, the critical distance, computed once per distinct n (the exact
   p-value costs up to ~0.3 ms a patch; ``ks_pvalue`` gives it). Patches of fewer than
   ``MIN_TEST_VALUES`` (5) values or with σ < ``MIN_SIGMA`` (1e-8) are not tested (statistic
   and critical distance NaN) and count as unimodal.
3. **Mixture.** A bimodal patch with at least ``MIN_MIXTURE_VALUES`` (10) values gets a
   two-component 1-D Gaussian mixture by EM: initialised by splitting the sorted values at
   the middle (lower ⌊n/2⌋ and the rest: each half's mean, population variance and share
   n_half/n); each iteration an E-step (log-sum-exp responsibilities and the mean
   log-likelihood ℓ per value) then an M-step; it stops when ℓ changes by less than
   ``tol`` (1e-6 nats per value) between two E-steps, or after ``max_iter`` (300) M-steps.
   EM on similarity patches converges slowly: on Nordland winter-vs-summer pixels the median
   mixture meets 1e-6 in ~50 steps and 300 stops 22 of 1,117 early; against running to
   1e-10 the boundary moves by a median 4e-4 (95th percentile 0.011).
   Every variance gets ``variance_floor`` (1e-6, scikit-learn's ``reg_covar``) added, and
   every component weight 10·eps (scikit-learn's guard against an empty component).
   Component 0 is the lower mean.
4. **Raw threshold** θ̂_q: where π₀g₀(x) = π₁g₁(x) between the means μ₀ ≤ x ≤ μ₁, the root
   of the quadratic

       (1/σ₁² − 1/σ₀²)/2 · x² + (μ₀/σ₀² − μ₁/σ₁²) · x
           + μ₁²/(2σ₁²) − μ₀²/(2σ₀²) + ln(π₀σ₁ / (π₁σ₀)) = 0,

   solved in the cancellation-free form (roots t/a and c/t, t = −(b + sign(b)√(b²−4ac))/2,
   so equal variances give the linear root); of the roots in [μ₀, μ₁] the one nearest the
   midpoint, and the midpoint (μ₀+μ₁)/2 when none lies there.
5. **Unimodal patches give no measurement** (θ̂_q NaN): "no path detected", the threshold
   is held. Before the first measurement of the sequence, the smoothed threshold of a query
   is its own patch's mean.
6. **Kalman filter** over the measurements in query order, a constant state with process
   noise Q = 1e-3 and measurement noise R = 1e-2: the first measurement sets the state x
   (its variance stays P₀ = 1); each later one predicts P ← P + Q, gains K = P/(P + R),
   updates x ← x + K(θ̂ − x), P ← (1 − K)P. A query's smoothed threshold θ_q is the state
   after the last measurement at or before it (step 5 otherwise).
7. **Decision**: accept the top-1 answer when s_q ≥ θ_q (exact comparison, as every
   threshold in ``retrieval``).

What the paper leaves open follows the public reimplementation in NickTrinh/VPR_Tutorial
(``experiments/vysotska_threshold.py``, the code behind the per-query-threshold numbers of
the authors' follow-up): the trailing patch cut at the edges, KS against the fitted normal
at α = 0.05, the minimum patch sizes, the midpoint fallback, holding the state on unimodal
patches, the patch mean before the first measurement, and Q, R, P₀. The EM differs from
that code's scikit-learn ``GaussianMixture`` (k-means start, three restarts, tol 1e-3): a
deterministic median split and one run, so the result does not depend on a seed.

Everything is vectorised across queries: the patches are gathered as one ``(n, p²)`` array
(cut blocks padded and masked), the KS statistic uses sorted patches and ``scipy.special.ndtr``,
and EM runs on all mixtures at once, each row frozen once it converges. The Kalman gains do
not depend on the measurements: a scalar recursion runs until the gain reaches its steady
state (a few dozen steps for the defaults), the updates of that transient run one by one,
and the rest is one constant-coefficient ``scipy.signal.lfilter``.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from functools import lru_cache

import numpy as np
from scipy import signal, special, stats

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.retrieval import TIE_TOLERANCE

#: Side of the square patch, p (the paper's value).
PATCH = 20
#: Significance level of the KS test: p < α means bimodal.
KS_ALPHA = 0.05
#: Fewest values a patch needs to be tested; fewer count as unimodal.
MIN_TEST_VALUES = 5
#: Fewest values a bimodal patch needs for a mixture; fewer count as unimodal.
MIN_MIXTURE_VALUES = 10
#: A patch whose standard deviation is below this is not tested (unimodal).
MIN_SIGMA = 1e-8
#: EM: most M-steps, and the change of mean log-likelihood per value that stops it.
EM_MAX_ITER = 300
EM_TOL = 1e-6
#: EM: added to every component variance (scikit-learn's ``reg_covar``).
VARIANCE_FLOOR = 1e-6
#: Kalman filter: process noise Q, measurement noise R, the state's variance after the first measurement P₀.
PROCESS_NOISE = 1e-3
MEASUREMENT_NOISE = 1e-2
INITIAL_VARIANCE = 1.0
#: The gain is at its steady state once one step changes it by less than this (relative).
GAIN_STEADY = 1e-15
#: Most steps of the gain recursion before the rest of the sequence is filtered with the last gain.
MAX_GAIN_STEPS = 100_000

_WEIGHT_GUARD = 10 * np.finfo(np.float64).eps


class Placement(StrEnum):
    """Where (query, best match) sits in its patch."""

    TRAILING = "trailing"
    CENTRED = "centred"


@dataclass(frozen=True)
class QueryThresholdSpec:
    """The settings of the per-query threshold; validates itself (module doc for each)."""

    patch: int = PATCH
    placement: str = Placement.TRAILING
    alpha: float = KS_ALPHA
    max_iter: int = EM_MAX_ITER
    tol: float = EM_TOL
    variance_floor: float = VARIANCE_FLOOR
    process_noise: float = PROCESS_NOISE
    measurement_noise: float = MEASUREMENT_NOISE
    initial_variance: float = INITIAL_VARIANCE

    def __post_init__(self) -> None:
        for name, low in (("patch", 2), ("max_iter", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
                raise VPRInputError(f"{name}={value!r}: must be a whole number, {low} or more")
        if self.patch > 1000:
            raise VPRInputError(f"patch={self.patch}: at most 1000 (a patch of p² values per query); lower it")
        if self.placement not in {p.value for p in Placement}:
            raise VPRInputError(f"placement={self.placement!r}: choose {' or '.join(p.value for p in Placement)}")
        for name in ("alpha", "tol", "variance_floor", "process_noise", "measurement_noise", "initial_variance"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
                    or not np.isfinite(value) or value <= 0:
                raise VPRInputError(f"{name}={value!r}: must be a finite number above 0")
        if self.alpha >= 1:
            raise VPRInputError(f"alpha={self.alpha!r}: a significance level, between 0 and 1 (e.g. 0.05)")


@dataclass(frozen=True, eq=False)
class QueryThresholds:
    """Every query's patch test, mixture, thresholds and decision, in query order.

    Attributes:
        best_match: ``(n,)`` database index of each query's top-1 answer, m_q.
        top_score: ``(n,)`` its similarity s_q.
        patch_rows: ``(n, 2)`` first and last+1 query index of the patch (cut at the edges).
        patch_cols: ``(n, 2)`` first and last+1 database index of the patch.
        n_values: ``(n,)`` values in the patch.
        patch_mean: ``(n,)`` and ``patch_std``: their mean and population standard deviation.
        ks_statistic: ``(n,)`` KS distance D to the fitted normal (NaN: not tested).
        ks_critical: ``(n,)`` the critical distance at level α for the patch's n (NaN: not tested);
            D > it ⇔ p < α (``ks_pvalue`` gives p).
        bimodal: ``(n,)`` the patch was found bimodal and got a mixture.
        weights: ``(n, 2)`` mixture weights π₀, π₁ (NaN where no mixture); component 0 has the lower mean.
        means: ``(n, 2)`` component means μ₀ ≤ μ₁.
        stds: ``(n, 2)`` component standard deviations σ₀, σ₁.
        em_iterations: ``(n,)`` M-steps EM took (0 where no mixture).
        em_converged: ``(n,)`` EM stopped on the tolerance, not on ``max_iter``.
        raw_threshold: ``(n,)`` θ̂_q, the mixture boundary (NaN where no measurement).
        threshold: ``(n,)`` θ_q, smoothed along the sequence.
        accepted: ``(n,)`` s_q ≥ θ_q.
        spec: the settings.
    """

    best_match: np.ndarray
    top_score: np.ndarray
    patch_rows: np.ndarray
    patch_cols: np.ndarray
    n_values: np.ndarray
    patch_mean: np.ndarray
    patch_std: np.ndarray
    ks_statistic: np.ndarray
    ks_critical: np.ndarray
    bimodal: np.ndarray
    weights: np.ndarray
    means: np.ndarray
    stds: np.ndarray
    em_iterations: np.ndarray
    em_converged: np.ndarray
    raw_threshold: np.ndarray
    threshold: np.ndarray
    accepted: np.ndarray
    spec: QueryThresholdSpec

    def __post_init__(self) -> None:
        for value in vars(self).values():
            if isinstance(value, np.ndarray):
                value.setflags(write=False)


@dataclass(frozen=True, eq=False)
class Mixtures:
    """Two-component 1-D Gaussian mixtures fitted by EM, one per row (component 0: lower mean).

    Attributes:
        weights: ``(m, 2)`` π₀, π₁.
        means: ``(m, 2)`` μ₀ ≤ μ₁.
        variances: ``(m, 2)`` σ₀², σ₁² (floor included).
        iterations: ``(m,)`` M-steps taken.
        converged: ``(m,)`` stopped on the tolerance.
        log_likelihood: ``(m,)`` mean log-likelihood per value at the last E-step.
    """

    weights: np.ndarray
    means: np.ndarray
    variances: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    log_likelihood: np.ndarray

    def __post_init__(self) -> None:
        for value in vars(self).values():
            value.setflags(write=False)


def best_matches(similarity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each query's top-1 answer and score: the lowest index within ``TIE_TOLERANCE`` of the row's maximum.

    Args:
        similarity: ``(n_queries, n_database)``.
    Returns:
        ``(n_queries,)`` database indices and ``(n_queries,)`` top scores (the row maxima).
    """
    top = similarity.max(axis=1)
    match = np.argmax(similarity >= (top - TIE_TOLERANCE)[:, None], axis=1)
    return match, top


def patch_bounds(centre: np.ndarray, size: int, patch: int, placement: str) -> tuple[np.ndarray, np.ndarray]:
    """First and last+1 index of each patch along one axis, cut to ``0..size``.

    Args:
        centre: ``(n,)`` the anchor index (the query along rows, its best match along columns).
        size: length of the axis.
        patch: p.
        placement: a ``Placement`` value.
    Returns:
        ``(n,)`` starts and ``(n,)`` stops.
    """
    offset = patch - 1 if placement == Placement.TRAILING else patch // 2
    start = np.asarray(centre, dtype=np.int64) - offset
    return np.maximum(start, 0), np.minimum(start + patch, size)


def gather_patches(similarity: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                   patch: int) -> tuple[np.ndarray, np.ndarray]:
    """Each query's patch as one row of p² values, float64, with a mask of the values inside S.

    Args:
        similarity: ``(n_queries, n_database)``.
        rows: ``(n, 2)`` start and stop of each patch's queries.
        cols: ``(n, 2)`` start and stop of each patch's database images.
        patch: p.
    Returns:
        ``(n, p²)`` values (0 outside the cut block) and ``(n, p²)`` mask (row-major within the block).
    """
    o = np.arange(patch)
    r = rows[:, :1] + o
    c = cols[:, :1] + o
    rv = r < rows[:, 1:]
    cv = c < cols[:, 1:]
    r = np.minimum(r, similarity.shape[0] - 1)
    c = np.minimum(c, similarity.shape[1] - 1)
    values = similarity[r[:, :, None], c[:, None, :]].astype(np.float64)
    mask = rv[:, :, None] & cv[:, None, :]
    n = len(rows)
    values = values.reshape(n, patch * patch)
    mask = mask.reshape(n, patch * patch)
    values[~mask] = 0.0
    return values, mask


def ks_normal(values: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """KS distance of each row's values to the normal with their mean and population standard deviation.

    D = max over the sorted values x₍ᵢ₎ (i = 1..n) of max(i/n − Φ(z₍ᵢ₎), Φ(z₍ᵢ₎) − (i−1)/n),
    z = (x − mean)/std: ``scipy.stats.kstest(x, "norm", args=(mean, std)).statistic``, all rows at once.

    Args:
        values: ``(m, L)`` rows of values.
        mask: ``(m, L)`` which are present.
    Returns:
        ``(m,)`` each: n, mean, std (ddof 0) and D (NaN where n < ``MIN_TEST_VALUES`` or std < ``MIN_SIGMA``).
    """
    n = mask.sum(axis=1)
    safe_n = np.maximum(n, 1)
    mean = np.where(mask, values, 0.0).sum(axis=1) / safe_n
    std = np.sqrt(np.where(mask, (values - mean[:, None]) ** 2, 0.0).sum(axis=1) / safe_n)
    tested = (n >= MIN_TEST_VALUES) & (std >= MIN_SIGMA)
    xs = np.sort(np.where(mask, values, np.inf), axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cdf = special.ndtr((xs - mean[:, None]) / np.where(tested, std, 1.0)[:, None])
    i = np.arange(1, values.shape[1] + 1, dtype=np.float64)
    present = i[None, :] <= n[:, None]
    d_plus = np.where(present, i / safe_n[:, None] - cdf, -np.inf).max(axis=1)
    d_minus = np.where(present, cdf - (i - 1) / safe_n[:, None], -np.inf).max(axis=1)
    return n, mean, std, np.where(tested, np.maximum(d_plus, d_minus), np.nan)


@lru_cache(maxsize=4096)
def ks_critical_value(alpha: float, n: int) -> float:
    """The D above which a two-sided one-sample KS test of n values rejects at level α: ``kstwo.isf(α, n)``."""
    return float(stats.kstwo.isf(alpha, n))


def ks_critical_values(alpha: float, n: np.ndarray) -> np.ndarray:
    """``ks_critical_value`` of every count in ``n`` (``(m,)``), computed once per distinct count."""
    counts, inverse = np.unique(np.asarray(n, dtype=np.int64), return_inverse=True)
    return np.array([ks_critical_value(float(alpha), int(c)) for c in counts], dtype=np.float64)[inverse]


def ks_pvalue(statistic: np.ndarray, n: np.ndarray) -> np.ndarray:
    """The exact two-sided p-value of KS distances D over n values, as ``scipy.stats.kstest`` reports it.

    Costs up to ~0.3 ms a value for large D: ``query_thresholds`` compares D with the critical
    value instead (D > D_crit ⇔ p < α) and leaves p-values to whoever shows one.
    """
    return np.clip(stats.kstwo.sf(statistic, n), 0.0, 1.0)


def fit_two_gaussians(values: np.ndarray, mask: np.ndarray, *, max_iter: int = EM_MAX_ITER, tol: float = EM_TOL,
                      variance_floor: float = VARIANCE_FLOOR) -> Mixtures:
    """Fit a two-component 1-D Gaussian mixture to each row by EM, all rows at once (module doc, step 3).

    Rows leave the working arrays as they converge, so each iteration costs only the rows still running.

    Args:
        values: ``(m, L)`` rows of values.
        mask: ``(m, L)`` which are present (each row at least 2).
        max_iter: most M-steps.
        tol: stop when the mean log-likelihood per value changes by less than this.
        variance_floor: added to every variance.
    Returns:
        The mixtures, component 0 the lower mean.
    """
    m, width = values.shape
    n = mask.sum(axis=1).astype(np.float64)
    # a mixture's likelihood does not depend on the order of its values: sort once, so the
    # present values come first in every row and the start's lower half is a prefix
    x = np.sort(np.where(mask, values, np.inf), axis=1)
    position = np.arange(width)[None, :]
    present = (position < n[:, None]).astype(np.float64)
    x = np.where(present > 0, x, 0.0)
    x2 = x * x
    sum_x = np.einsum("ij,ij->i", present, x)
    sum_x2 = np.einsum("ij,ij->i", present, x2)
    lower = (position < (n // 2)[:, None]).astype(np.float64)
    params = np.stack(_m_step(lower, present, x, x2, n, sum_x, sum_x2, variance_floor), axis=1)  # (m, 6)
    iterations = np.zeros(m, dtype=np.int64)
    converged = np.zeros(m, dtype=bool)
    ll = np.full(m, np.nan)
    active = np.arange(m)
    # working copies of the rows still running
    wx, wx2, wp, wn, wsx, wsx2 = x, x2, present, n, sum_x, sum_x2
    prev = np.full(m, np.nan)
    for it in range(max_iter + 1):
        w0, w1, mu0, mu1, var0, var1 = params[active].T
        l0 = _log_density(wx, w0, mu0, var0)
        diff = _log_density(wx, w1, mu1, var1)
        diff -= l0
        cur = (np.einsum("ij,ij->i", wp, l0) + np.einsum("ij,ij->i", wp, np.logaddexp(0.0, diff))) / wn
        ll[active] = cur
        done = np.abs(cur - prev) < tol if it > 0 else np.zeros(len(active), dtype=bool)
        converged[active[done]] = True
        if it == max_iter:
            break
        if done.any():
            keep = ~done
            active, diff, cur = active[keep], diff[keep], cur[keep]
            wx, wx2, wp, wn, wsx, wsx2 = wx[keep], wx2[keep], wp[keep], wn[keep], wsx[keep], wsx2[keep]
            if not len(active):
                break
        r1 = special.expit(diff, out=diff)
        params[active] = np.stack(_m_step(r1, wp, wx, wx2, wn, wsx, wsx2, variance_floor, second=True), axis=1)
        prev = cur
        iterations[active] += 1
    w, mu, var = params[:, :2], params[:, 2:4], params[:, 4:]
    order = np.argsort(mu, axis=1, kind="stable")
    w, mu, var = (np.ascontiguousarray(np.take_along_axis(a, order, axis=1)) for a in (w, mu, var))
    return Mixtures(w, mu, var, iterations, converged, ll)


def _log_density(x: np.ndarray, w: np.ndarray, mu: np.ndarray, var: np.ndarray) -> np.ndarray:
    """``(a, L)`` log π + log N(x | μ, σ²) of one component, row parameters ``(a,)``."""
    z = x - mu[:, None]
    z *= z
    z *= (-0.5 / var)[:, None]
    z += (np.log(w) - 0.5 * np.log(2 * np.pi * var))[:, None]
    return z


def _m_step(r: np.ndarray, present: np.ndarray, x: np.ndarray, x2: np.ndarray, n: np.ndarray, sum_x: np.ndarray,
            sum_x2: np.ndarray, variance_floor: float, *, second: bool = False) -> tuple[np.ndarray, ...]:
    """π₀, π₁, μ₀, μ₁, σ₀², σ₁² from one component's responsibilities ``r`` (``(a, L)``).

    ``r`` belongs to component 1 when ``second``, else to component 0; the other's is
    ``present − r``, so its sums come from the row totals. Variances come from raw moments:
    similarities are at most 1 in size, and E[x²] − μ² then loses ~1e-16/σ² relative,
    nothing next to the floor.
    """
    r = r * present
    nk = np.einsum("ij->i", r)
    sx = np.einsum("ij,ij->i", r, x)
    sx2 = np.einsum("ij,ij->i", r, x2)
    nk_o, sx_o, sx2_o = n - nk, sum_x - sx, sum_x2 - sx2
    if second:
        nk, sx, sx2, nk_o, sx_o, sx2_o = nk_o, sx_o, sx2_o, nk, sx, sx2
    nk = nk + _WEIGHT_GUARD
    nk_o = nk_o + _WEIGHT_GUARD
    mu, mu_o = sx / nk, sx_o / nk_o
    var = np.maximum(sx2 / nk - mu * mu, 0.0) + variance_floor
    var_o = np.maximum(sx2_o / nk_o - mu_o * mu_o, 0.0) + variance_floor
    total = nk + nk_o
    return nk / total, nk_o / total, mu, mu_o, var, var_o


def mixture_boundary(weights: np.ndarray, means: np.ndarray, stds: np.ndarray) -> np.ndarray:
    """Where π₀g₀(x) = π₁g₁(x) between the means (module doc, step 4), row by row.

    Args:
        weights: ``(m, 2)`` π₀, π₁.
        means: ``(m, 2)`` μ₀ ≤ μ₁.
        stds: ``(m, 2)`` σ₀, σ₁ (above 0).
    Returns:
        ``(m,)`` the root in [μ₀, μ₁] nearest the midpoint, else the midpoint.
    """
    w0, w1 = weights[:, 0], weights[:, 1]
    m0, m1 = means[:, 0], means[:, 1]
    v0, v1 = stds[:, 0] ** 2, stds[:, 1] ** 2
    a = 0.5 * (1 / v1 - 1 / v0)
    b = m0 / v0 - m1 / v1
    c = 0.5 * (m1 ** 2 / v1 - m0 ** 2 / v0) + np.log(w0 * stds[:, 1] / (w1 * stds[:, 0]))
    mid = 0.5 * (m0 + m1)
    with np.errstate(invalid="ignore", divide="ignore"):
        disc = b * b - 4 * a * c
        t = -0.5 * (b + np.where(b >= 0, 1.0, -1.0) * np.sqrt(disc))
        roots = np.stack([t / a, c / t], axis=1)
    inside = np.isfinite(roots) & (roots >= m0[:, None]) & (roots <= m1[:, None])
    dist = np.where(inside, np.abs(roots - mid[:, None]), np.inf)
    pick = np.argmin(dist, axis=1)
    best = np.take_along_axis(roots, pick[:, None], axis=1)[:, 0]
    return np.where(inside.any(axis=1), best, mid)


def kalman_gains(n_updates: int, *, process_noise: float = PROCESS_NOISE, measurement_noise: float = MEASUREMENT_NOISE,
                 initial_variance: float = INITIAL_VARIANCE) -> np.ndarray:
    """The gain of each measurement: 1 for the first (it sets the state), then P/(P + R) of the recursion.

    Args:
        n_updates: number of measurements.
        process_noise: Q.
        measurement_noise: R.
        initial_variance: P₀, the state's variance after the first measurement.
    Returns:
        ``(n_updates,)`` gains; once a step changes the gain by less than ``GAIN_STEADY``
        (relative), the rest repeat it.
    """
    gains = np.ones(n_updates)
    p = initial_variance
    prev = np.nan
    for j in range(1, min(n_updates, MAX_GAIN_STEPS)):
        p_pred = p + process_noise
        k = p_pred / (p_pred + measurement_noise)
        p = (1 - k) * p_pred
        gains[j] = k
        if abs(k - prev) <= GAIN_STEADY * k:
            gains[j + 1:] = k
            break
        prev = k
    else:
        if n_updates > MAX_GAIN_STEPS:
            gains[MAX_GAIN_STEPS:] = gains[MAX_GAIN_STEPS - 1]
    return gains


def kalman_smooth(measurements: np.ndarray, *, process_noise: float = PROCESS_NOISE,
                  measurement_noise: float = MEASUREMENT_NOISE,
                  initial_variance: float = INITIAL_VARIANCE) -> np.ndarray:
    """The filter's state after each measurement (module doc, step 6).

    Args:
        measurements: ``(M,)`` in sequence order, all finite.
        process_noise: Q.
        measurement_noise: R.
        initial_variance: P₀.
    Returns:
        ``(M,)`` states x_j.
    """
    z = np.asarray(measurements, dtype=np.float64)
    out = np.empty_like(z)
    if not len(z):
        return out
    k = kalman_gains(len(z), process_noise=process_noise, measurement_noise=measurement_noise,
                     initial_variance=initial_variance)
    steady = np.flatnonzero(k[1:] == k[-1])
    first_steady = int(steady[0]) + 1 if len(steady) else len(z)
    x = z[0]
    out[0] = x
    for j in range(1, first_steady):  # the transient: gains still changing
        x = x + k[j] * (z[j] - x)
        out[j] = x
    if first_steady < len(z):
        ks = k[-1]
        out[first_steady:], _ = signal.lfilter([ks], [1.0, ks - 1.0], z[first_steady:], zi=[(1.0 - ks) * x])
    return out


def query_thresholds(similarity: np.ndarray, spec: QueryThresholdSpec | None = None, *,
                     ordered: bool = True) -> QueryThresholds:
    """Every query's per-query adaptive threshold and decision (module doc).

    Args:
        similarity: ``(n_queries, n_database)`` similarities, queries and database images each in route order.
        spec: the settings (defaults: ``QueryThresholdSpec()``).
        ordered: whether the database is one route in order (a dataset value's ``ordered``); the patch
            follows the sequence, so an unordered database is refused.
    Returns:
        The per-query results.
    Raises:
        VPRInputError: an unordered database, a matrix that is not 2-D and non-empty, or non-finite values.
    """
    spec = QueryThresholdSpec() if spec is None else spec
    if not ordered:
        raise VPRInputError("ordered=False: the per-query threshold reads its patch along the route, so the database "
                            "must be one traversal in order; choose a dataset with one database traversal")
    s = np.asarray(similarity)
    if s.ndim != 2 or 0 in s.shape:
        raise VPRInputError(f"similarity has shape {s.shape}: give a non-empty (n_queries, n_database) matrix")
    if not np.issubdtype(s.dtype, np.floating) and not np.issubdtype(s.dtype, np.integer):
        raise VPRInputError(f"similarity has dtype {s.dtype}: give numbers")
    if not np.isfinite(s).all():
        raise VPRInputError("similarity holds NaN or infinite values: recompute it from finite descriptors")
    nq, nd = s.shape
    match, top = best_matches(s)
    r0, r1 = patch_bounds(np.arange(nq), nq, spec.patch, spec.placement)
    c0, c1 = patch_bounds(match, nd, spec.patch, spec.placement)
    rows = np.stack([r0, r1], axis=1)
    cols = np.stack([c0, c1], axis=1)
    values, mask = gather_patches(s, rows, cols, spec.patch)
    n, mean, std, d = ks_normal(values, mask)
    tested = np.isfinite(d)
    critical = np.full(nq, np.nan)
    critical[tested] = ks_critical_values(spec.alpha, n[tested])
    bimodal = (d > critical) & (n >= MIN_MIXTURE_VALUES)  # NaN (not tested) compares False
    weights = np.full((nq, 2), np.nan)
    means = np.full((nq, 2), np.nan)
    stds = np.full((nq, 2), np.nan)
    iterations = np.zeros(nq, dtype=np.int64)
    converged = np.zeros(nq, dtype=bool)
    raw = np.full(nq, np.nan)
    idx = np.flatnonzero(bimodal)
    if len(idx):
        mix = fit_two_gaussians(values[idx], mask[idx], max_iter=spec.max_iter, tol=spec.tol,
                                variance_floor=spec.variance_floor)
        weights[idx], means[idx], stds[idx] = mix.weights, mix.means, np.sqrt(mix.variances)
        iterations[idx], converged[idx] = mix.iterations, mix.converged
        raw[idx] = mixture_boundary(mix.weights, mix.means, stds[idx])
    states = kalman_smooth(raw[idx], process_noise=spec.process_noise, measurement_noise=spec.measurement_noise,
                           initial_variance=spec.initial_variance)
    latest = np.cumsum(bimodal) - 1  # the last measurement at or before each query; -1: none yet
    smoothed = mean.copy()
    smoothed[latest >= 0] = states[latest[latest >= 0]]
    return QueryThresholds(
        best_match=match, top_score=top.astype(np.float64), patch_rows=rows, patch_cols=cols, n_values=n,
        patch_mean=mean, patch_std=std, ks_statistic=d, ks_critical=critical, bimodal=bimodal, weights=weights,
        means=means, stds=stds, em_iterations=iterations, em_converged=converged, raw_threshold=raw, threshold=smoothed,
        accepted=top >= smoothed, spec=spec)
