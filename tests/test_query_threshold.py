"""The per-query adaptive threshold: a plain per-query loop written from its definition, hand cases, real data."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method import query_threshold as qt
from vpr_explorer.method.query_threshold import QueryThresholdSpec, query_thresholds
from vpr_explorer.method.retrieval import similarity

# ---------------------------------------------------------------------------------------------
# The reference: one query at a time, slices, scipy.stats.kstest, EM and a Kalman filter in loops.


def ref_patch(s: np.ndarray, q: int, m: int, p: int, placement: str) -> np.ndarray:
    off = p - 1 if placement == "trailing" else p // 2
    r0, c0 = max(q - off, 0), max(m - off, 0)
    r1, c1 = min(q - off + p, s.shape[0]), min(m - off + p, s.shape[1])
    return s[r0:r1, c0:c1].astype(np.float64).ravel()


def ref_em(x: np.ndarray, max_iter: int, tol: float, floor: float):
    """Two-component EM on one patch, written out plainly (start: the sorted values split at the middle)."""
    x = np.sort(x)
    n = len(x)
    halves = [x[: n // 2], x[n // 2:]]
    w = [len(h) / n for h in halves]
    mu = [h.mean() for h in halves]
    var = [h.var() + floor for h in halves]
    guard = 10 * np.finfo(float).eps
    prev = None
    iterations = 0
    converged = False
    for it in range(max_iter + 1):
        logp = np.stack([math.log(w[k]) - 0.5 * math.log(2 * math.pi * var[k]) - (x - mu[k]) ** 2 / (2 * var[k])
                         for k in range(2)])
        lse = np.logaddexp(logp[0], logp[1])
        ll = lse.mean()
        if prev is not None and abs(ll - prev) < tol:
            converged = True
            break
        if it == max_iter:
            break
        resp = np.exp(logp - lse)
        nk = [resp[k].sum() + guard for k in range(2)]
        w = [nk[k] / (nk[0] + nk[1]) for k in range(2)]
        mu = [(resp[k] * x).sum() / nk[k] for k in range(2)]
        var = [(resp[k] * (x - mu[k]) ** 2).sum() / nk[k] + floor for k in range(2)]
        prev = ll
        iterations += 1
    order = np.argsort(mu, kind="stable")
    return (np.array(w)[order], np.array(mu)[order], np.sqrt(np.array(var)[order]), iterations, converged)


def ref_boundary(w, mu, sd) -> float:
    """The root of log π₀g₀ − log π₁g₁ in [μ₀, μ₁] nearest the midpoint (np.roots); else the midpoint."""
    a = -1 / (2 * sd[0] ** 2) + 1 / (2 * sd[1] ** 2)
    b = mu[0] / sd[0] ** 2 - mu[1] / sd[1] ** 2
    c = -mu[0] ** 2 / (2 * sd[0] ** 2) + mu[1] ** 2 / (2 * sd[1] ** 2) + math.log(w[0] * sd[1] / (w[1] * sd[0]))
    mid = (mu[0] + mu[1]) / 2
    roots = [r.real for r in np.roots([a, b, c]) if abs(r.imag) < 1e-12 and mu[0] <= r.real <= mu[1]]
    return min(roots, key=lambda r: abs(r - mid)) if roots else mid


class RefKalman:
    def __init__(self, q: float, r: float, p0: float):
        self.q, self.r, self.p, self.x = q, r, p0, None

    def update(self, z: float) -> float:
        if self.x is None:
            self.x = z
            return z
        p_pred = self.p + self.q
        k = p_pred / (p_pred + self.r)
        self.x = self.x + k * (z - self.x)
        self.p = (1 - k) * p_pred
        return self.x


def reference(s: np.ndarray, spec: QueryThresholdSpec = QueryThresholdSpec(), n_queries: int | None = None) -> dict:
    nq = s.shape[0] if n_queries is None else n_queries
    kf = RefKalman(spec.process_noise, spec.measurement_noise, spec.initial_variance)
    out = {k: [] for k in ("match", "top", "pvalue", "bimodal", "weights", "means", "stds", "iterations", "raw",
                           "threshold", "accepted")}
    for q in range(nq):
        row = s[q]
        top = row.max()
        m = int(np.flatnonzero(row >= top - 1e-5)[0])
        x = ref_patch(s, q, m, spec.patch, spec.placement)
        pvalue = np.nan
        if len(x) >= 5 and x.std() >= 1e-8:
            pvalue = stats.kstest(x, "norm", args=(x.mean(), x.std())).pvalue
        bimodal = bool(pvalue < spec.alpha and len(x) >= 10)
        w = mu = sd = np.full(2, np.nan)
        iterations = 0
        raw = np.nan
        if bimodal:
            w, mu, sd, iterations, _ = ref_em(x, spec.max_iter, spec.tol, spec.variance_floor)
            raw = ref_boundary(w, mu, sd)
            theta = kf.update(raw)
        else:
            theta = kf.x if kf.x is not None else x.mean()
        for key, value in zip(out, (m, top, pvalue, bimodal, w, mu, sd, iterations, raw, theta, top >= theta)):
            out[key].append(value)
    return {k: np.array(v) for k, v in out.items()}


def assert_agrees(fast: qt.QueryThresholds, ref: dict, *, boundary_tol: float = 1e-6) -> None:
    n = len(ref["match"])
    np.testing.assert_array_equal(fast.best_match[:n], ref["match"])
    np.testing.assert_array_equal(fast.top_score[:n], ref["top"])
    # the KS decision: D against the critical value, p against α; only a p within 1e-9 of α may disagree
    near = np.abs(ref["pvalue"] - fast.spec.alpha) < 1e-9
    assert not near.any(), "a p-value at α: the comparison would be a rounding question"
    np.testing.assert_array_equal(fast.bimodal[:n], ref["bimodal"])
    np.testing.assert_allclose(qt.ks_pvalue(fast.ks_statistic[:n], fast.n_values[:n]), ref["pvalue"], rtol=1e-9,
                               atol=1e-12)
    b = ref["bimodal"]
    np.testing.assert_array_equal(fast.em_iterations[:n], ref["iterations"])
    np.testing.assert_allclose(fast.means[:n][b], ref["means"][b], atol=boundary_tol)
    np.testing.assert_allclose(fast.stds[:n][b], ref["stds"][b], atol=boundary_tol)
    np.testing.assert_allclose(fast.weights[:n][b], ref["weights"][b], atol=boundary_tol)
    np.testing.assert_allclose(fast.raw_threshold[:n], ref["raw"], atol=boundary_tol, equal_nan=True)
    np.testing.assert_allclose(fast.threshold[:n], ref["threshold"], atol=boundary_tol)
    close = np.abs(ref["top"] - ref["threshold"]) <= boundary_tol
    np.testing.assert_array_equal(fast.accepted[:n][~close], ref["accepted"][~close])


# ---------------------------------------------------------------------------------------------
# Hand cases


def _true_boundary(w0, m0, s0, w1, m1, s1) -> float:
    """Where w0·N(m0, s0²) = w1·N(m1, s1²) between the means, by bisection on the densities (no quadratic)."""
    f = lambda t: w0 * stats.norm.pdf(t, m0, s0) - w1 * stats.norm.pdf(t, m1, s1)  # noqa: E731
    lo, hi = m0, m1
    for _ in range(100):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if f(mid) > 0 else (lo, mid)
    return lo


def test_bimodal_patch_boundary_matches_the_analytic_one():
    rng = np.random.default_rng(0)
    truth = _true_boundary(0.75, 0.10, 0.02, 0.25, 0.60, 0.03)
    assert 0.29 < truth < 0.31
    x = np.concatenate([rng.normal(0.10, 0.02, 300), rng.normal(0.60, 0.03, 100)])  # one 20 × 20 patch
    rng.shuffle(x)
    values, mask = x[None, :], np.ones((1, 400), dtype=bool)
    n, mean, std, d = qt.ks_normal(values, mask)
    assert d[0] > qt.ks_critical_value(0.05, 400)
    assert stats.kstest(x, "norm", args=(x.mean(), x.std())).pvalue < 1e-10
    mix = qt.fit_two_gaussians(values, mask)
    assert mix.converged[0]
    np.testing.assert_allclose(mix.weights[0], [0.75, 0.25], atol=0.01)
    np.testing.assert_allclose(mix.means[0], [0.10, 0.60], atol=0.005)
    np.testing.assert_allclose(np.sqrt(mix.variances[0]), [0.02, 0.03], atol=0.004)
    sd = np.sqrt(mix.variances)
    found = qt.mixture_boundary(mix.weights, mix.means, sd)[0]
    # exactly the fitted mixture's boundary; the true one within what 400 samples allow (the
    # boundary sits in both tails, so σ's sampling error moves it)
    assert found == pytest.approx(_true_boundary(*mix.weights[0][:1], mix.means[0, 0], sd[0, 0],
                                                 mix.weights[0, 1], mix.means[0, 1], sd[0, 1]), abs=1e-9)
    assert abs(found - truth) < 0.02
    # many values: the fit, and so the boundary, close in on the truth
    big = np.concatenate([rng.normal(0.10, 0.02, 30000), rng.normal(0.60, 0.03, 10000)])
    mix = qt.fit_two_gaussians(big[None, :], np.ones((1, big.size), dtype=bool))
    assert abs(qt.mixture_boundary(mix.weights, mix.means, np.sqrt(mix.variances))[0] - truth) < 0.003


def test_unimodal_patch_is_not_rejected():
    rng = np.random.default_rng(1)
    x = rng.normal(0.3, 0.05, 400)
    n, mean, std, d = qt.ks_normal(x[None, :], np.ones((1, 400), dtype=bool))
    ref = stats.kstest(x, "norm", args=(x.mean(), x.std()))
    assert d[0] == pytest.approx(ref.statistic, abs=1e-12)
    assert ref.pvalue > 0.05
    assert d[0] < qt.ks_critical_value(0.05, 400)


def test_ks_matches_scipy_on_rows_of_different_lengths():
    rng = np.random.default_rng(2)
    lengths = [3, 5, 7, 10, 50, 199, 400]
    values = np.zeros((len(lengths), 400))
    mask = np.zeros((len(lengths), 400), dtype=bool)
    for i, k in enumerate(lengths):
        values[i, :k] = rng.gamma(2.0, 0.1, k)
        mask[i, :k] = True
    perm = rng.permutation(400)  # present values need not come first
    n, mean, std, d = qt.ks_normal(values[:, perm], mask[:, perm])
    for i, k in enumerate(lengths):
        x = values[i, :k]
        assert n[i] == k and mean[i] == pytest.approx(x.mean()) and std[i] == pytest.approx(x.std())
        if k < qt.MIN_TEST_VALUES:
            assert np.isnan(d[i])
            continue
        ref = stats.kstest(x, "norm", args=(x.mean(), x.std()))
        assert d[i] == pytest.approx(ref.statistic, abs=1e-12)
        assert qt.ks_pvalue(d[i:i + 1], n[i:i + 1])[0] == pytest.approx(ref.pvalue, rel=1e-9, abs=1e-15)
        assert (d[i] > qt.ks_critical_value(0.05, k)) == (ref.pvalue < 0.05)


def test_em_matches_the_loop_on_rows_of_different_lengths():
    rng = np.random.default_rng(3)
    rows, masks, xs = [], [], []
    for k in (10, 37, 400, 400, 250):
        x = np.concatenate([rng.normal(0.1, 0.03, k - k // 4), rng.normal(0.4, 0.05, k // 4)])
        v, mk = np.zeros(400), np.zeros(400, dtype=bool)
        where = rng.choice(400, k, replace=False)
        v[where], mk[where] = x, True
        rows.append(v)
        masks.append(mk)
        xs.append(x)
    mix = qt.fit_two_gaussians(np.array(rows), np.array(masks), max_iter=300, tol=1e-6, variance_floor=1e-6)
    for i, x in enumerate(xs):
        w, mu, sd, iterations, converged = ref_em(x, 300, 1e-6, 1e-6)
        assert mix.iterations[i] == iterations and mix.converged[i] == converged
        np.testing.assert_allclose(mix.weights[i], w, atol=1e-9)
        np.testing.assert_allclose(mix.means[i], mu, atol=1e-9)
        np.testing.assert_allclose(np.sqrt(mix.variances[i]), sd, atol=1e-9)


def test_em_stops_at_max_iter():
    x = np.linspace(0, 1, 400) ** 3
    mix = qt.fit_two_gaussians(x[None, :], np.ones((1, 400), dtype=bool), max_iter=3, tol=1e-12)
    assert mix.iterations[0] == 3 and not mix.converged[0]
    w, mu, sd, iterations, converged = ref_em(x, 3, 1e-12, 1e-6)
    np.testing.assert_allclose(mix.means[0], mu, atol=1e-12)


def test_boundary_closed_forms():
    # equal variances: the linear root μ̄ + σ² ln(π₀/π₁)/(μ₁ − μ₀); equal weights too: the midpoint
    w = np.array([[0.5, 0.5], [0.8, 0.2]])
    mu = np.array([[0.0, 1.0], [0.0, 1.0]])
    sd = np.full((2, 2), 0.2)
    got = qt.mixture_boundary(w, mu, sd)
    assert got[0] == pytest.approx(0.5, abs=1e-12)
    assert got[1] == pytest.approx(0.5 + 0.04 * math.log(4.0), abs=1e-12)
    # unequal variances: both roots real, only one between the means; and against np.roots
    w = np.array([[0.6, 0.4], [0.3, 0.7], [0.999999, 1e-6]])
    mu = np.array([[0.1, 0.5], [0.2, 0.3], [0.0, 0.1]])
    sd = np.array([[0.05, 0.2], [0.01, 0.05], [0.5, 0.01]])
    got = qt.mixture_boundary(w, mu, sd)
    for i in range(3):
        assert got[i] == pytest.approx(ref_boundary(w[i], mu[i], sd[i]), abs=1e-12)
    # the last: the weak, narrow upper component never wins between the means: the midpoint
    assert got[2] == pytest.approx(0.05)


def test_kalman_step_input_first_values():
    # z = 0, 1, 1, 1 …, Q = 1e-3, R = 1e-2, P₀ = 1
    # x₀ = 0; P⁻ = 1.001, K₁ = 1.001/1.011, x₁ = K₁; P₁ = (1 − K₁)·1.001 = 1.001·0.01/1.011
    # P⁻ = P₁ + 0.001, K₂ = P⁻/(P⁻ + 0.01), x₂ = x₁ + K₂(1 − x₁)
    k1 = 1.001 / 1.011
    p1 = 1.001 * 0.01 / 1.011
    k2 = (p1 + 0.001) / (p1 + 0.011)
    x1 = k1
    x2 = x1 + k2 * (1 - x1)
    assert k1 == pytest.approx(0.990108803, abs=1e-9)
    assert k2 == pytest.approx(0.521556, abs=1e-6)
    out = qt.kalman_smooth(np.r_[0.0, np.ones(9)])
    assert out[0] == 0.0
    assert out[1] == pytest.approx(x1, abs=1e-15)
    assert out[2] == pytest.approx(x2, abs=1e-15)
    assert out[2] == pytest.approx(0.995267, abs=1e-6)
    assert np.all(np.diff(out) > 0) and out[-1] < 1


def test_kalman_steady_gain_and_long_inputs_match_the_loop():
    q, r = 1e-3, 1e-2
    pp = (q + math.sqrt(q * q + 4 * q * r)) / 2  # the predicted variance at steady state (scalar Riccati)
    gains = qt.kalman_gains(500)
    assert gains[0] == 1.0
    assert gains[-1] == pytest.approx(pp / (pp + r), rel=1e-12)
    rng = np.random.default_rng(4)
    for q_, n in ((1e-3, 5000), (1e-9, 3000), (0.5, 50)):  # short and long transients
        z = rng.normal(0.2, 0.05, n)
        kf = RefKalman(q_, 1e-2, 1.0)
        ref = np.array([kf.update(v) for v in z])
        np.testing.assert_allclose(qt.kalman_smooth(z, process_noise=q_), ref, atol=1e-12)
    assert qt.kalman_smooth(np.array([])).shape == (0,)
    assert qt.kalman_smooth(np.array([0.3]))[0] == 0.3


def test_constant_matrix_every_tie_and_a_score_exactly_at_the_threshold():
    s = np.full((30, 40), 0.5, dtype=np.float32)
    r = query_thresholds(s)
    assert (r.best_match == 0).all()  # ties go to the lowest index
    assert not r.bimodal.any() and np.isnan(r.ks_statistic).all()  # σ = 0: not tested
    np.testing.assert_array_equal(r.threshold, 0.5)  # no measurement yet: the patch mean
    assert r.accepted.all()  # s_q = θ_q is accepted


def test_best_match_ties_within_tolerance():
    s = np.array([[0.3, 0.9, 0.9 + 5e-6, 0.2], [0.9, 0.91, 0.1, 0.0]])
    match, top = qt.best_matches(s)
    assert list(match) == [1, 1]
    assert top[0] == 0.9 + 5e-6


def sequence_matrix(n: int = 120, nd: int = 150, seed: int = 5) -> np.ndarray:
    """A route: noise with a diagonal of matches, a stretch where the route leaves the map."""
    rng = np.random.default_rng(seed)
    s = rng.normal(0.1, 0.03, (n, nd))
    for q in range(n):
        if not 60 <= q < 80:
            s[q, (q + 10) % nd] = 0.6 + rng.normal(0, 0.02)
    return s.astype(np.float32)


@pytest.mark.parametrize("placement", ["trailing", "centred"])
def test_synthetic_sequence_matches_the_loop(placement):
    s = sequence_matrix()
    spec = QueryThresholdSpec(placement=placement)
    fast = query_thresholds(s, spec)
    assert_agrees(fast, reference(s, spec))
    assert fast.bimodal.sum() > 50
    on_route = np.r_[30:60, 90:120]
    assert fast.accepted[on_route].all()
    # off the map: the threshold is held from the route, and the noise's best stays under it
    assert not fast.accepted[65:80].any()


def test_result_fields_and_readonly():
    r = query_thresholds(sequence_matrix())
    n = 120
    for name in ("best_match", "top_score", "n_values", "ks_statistic", "bimodal", "raw_threshold", "threshold",
                 "accepted"):
        assert getattr(r, name).shape == (n,)
        assert not getattr(r, name).flags.writeable
    assert r.means.shape == r.stds.shape == r.weights.shape == (n, 2)
    b = r.bimodal
    assert (r.means[b, 0] <= r.means[b, 1]).all()
    assert np.isnan(r.raw_threshold[~b]).all() and np.isfinite(r.raw_threshold[b]).all()
    assert ((r.raw_threshold[b] >= r.means[b, 0]) & (r.raw_threshold[b] <= r.means[b, 1])).all()
    np.testing.assert_allclose(r.weights[b].sum(axis=1), 1.0)
    # the trailing patch at query 0, match m: one row, columns m−19..m
    assert tuple(r.patch_rows[0]) == (0, 1) and r.patch_cols[0, 1] == r.best_match[0] + 1
    assert r.n_values[0] == r.patch_cols[0, 1] - r.patch_cols[0, 0]


@pytest.mark.parametrize("kwargs", [
    {"patch": 1}, {"patch": 2.5}, {"patch": True}, {"patch": 5000}, {"placement": "middle"}, {"alpha": 1.5},
    {"alpha": 0}, {"tol": float("nan")}, {"max_iter": 0}, {"process_noise": 0.0}, {"measurement_noise": -1.0},
    {"initial_variance": float("inf")}, {"variance_floor": "1e-6"},
])
def test_bad_settings(kwargs):
    with pytest.raises(VPRInputError, match=next(iter(kwargs))):
        QueryThresholdSpec(**kwargs)


def test_bad_input():
    with pytest.raises(VPRInputError, match="shape"):
        query_thresholds(np.zeros(5))
    with pytest.raises(VPRInputError, match="shape"):
        query_thresholds(np.zeros((0, 5)))
    s = sequence_matrix()
    s[3, 4] = np.nan
    with pytest.raises(VPRInputError, match="NaN"):
        query_thresholds(s)
    with pytest.raises(VPRInputError, match="ordered"):
        query_thresholds(sequence_matrix(), ordered=False)
    with pytest.raises(VPRInputError, match="dtype"):
        query_thresholds(np.array([["a", "b"]]))


def test_small_matrices():
    r = query_thresholds(np.array([[0.4]], dtype=np.float32))
    assert r.threshold[0] == pytest.approx(0.4) and r.accepted[0]
    s = sequence_matrix(8, 6)
    assert_agrees(query_thresholds(s), reference(s))


# ---------------------------------------------------------------------------------------------
# Real data


def _sims(dataset, descriptors, query: str, database: str) -> tuple[np.ndarray, bool]:
    from vpr_explorer.data.aligned import database_queries, value_rows

    v = database_queries(dataset, query, database=[database])
    rows = value_rows(v)
    d = descriptors if rows is None else descriptors[rows]
    nd = len(v.database_frame)
    return similarity(d[nd:], d[:nd]), v.ordered


@pytest.mark.realdata
def test_gardens_point_night_vs_day_matches_the_loop(gardens_point, gp_pixels):
    s, ordered = _sims(gardens_point, gp_pixels, "night_right", "day_right")
    assert ordered and s.shape == (200, 200)
    fast = query_thresholds(s, ordered=ordered)
    assert_agrees(fast, reference(s))
    assert fast.bimodal.any() and (~fast.bimodal).any()


@pytest.mark.realdata
def test_nordland_prefix_matches_the_loop(data_root):
    from vpr_explorer.pipeline import dataset_descriptors, resolve_dataset

    ds = resolve_dataset(data_root / "Nordland_64x32")
    s, ordered = _sims(ds, dataset_descriptors(ds, "pixels"), "winter", "summer")
    fast = query_thresholds(s, ordered=ordered)
    # the trailing patch and the filter only look back: the first queries' results are the loop's on them alone
    assert_agrees(fast, reference(s, n_queries=150))
