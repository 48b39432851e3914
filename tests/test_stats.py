"""Closed-form negative statistics equal the plain pairwise computation.

Both precisions are checked against ``reference.pairwise_negative_stats`` (float64, full
matrix); the float32 path also against its stated error bound (``sigma_sq_error_bound``).
"""

import numpy as np
import pytest

from reference import pairwise_negative_stats, unit_rows
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import PlaceSpec, make_places
from vpr_explorer.method.stats import (
    Precision,
    mixture_moments,
    mixture_pdf,
    negative_stats,
    positive_means,
    sigma_sq_error_bound,
    validate_descriptors,
    within_place_sq,
)

FLOAT64_SLACK = 1e-13  # float64 rounding of the closed form and of the reference, beside the bound


def shared_component(rng, n, dim, places, share=0.8):
    """Unit descriptors √share·u + √(1−share)·rᵢ with one shared u: every score sits near ``share``.

    rᵢ is a place centre plus noise, orthogonal to u, so σ ≈ 0.01 while μ ≈ 0.8: the case
    where E[s²] − μ² cancels.
    """
    u = unit_rows(rng, 1, dim)[0]
    labels = rng.integers(0, places, n)
    r = unit_rows(rng, places, dim)[labels] + 0.5 * unit_rows(rng, n, dim)
    r -= np.outer(r @ u, u)
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    return (np.sqrt(share) * u + np.sqrt(1 - share) * r).astype(np.float32), labels


def assert_within_bound(st, mu, sigma, d, labels, **kw):
    """μ to float64 rounding; σ² within the float32 bound; σ within 1e-6 (the accuracy the fit promises)."""
    bound = sigma_sq_error_bound(d, labels, **kw)
    np.testing.assert_allclose(st.mu, mu, rtol=0, atol=1e-12)
    excess = np.abs(st.sigma**2 - sigma**2) - bound - FLOAT64_SLACK
    assert excess.max() <= 0, f"σ² off its bound by {excess.max():.2e} at image {excess.argmax()}"
    np.testing.assert_allclose(st.sigma, sigma, rtol=0, atol=1e-6)
    return bound


@pytest.mark.parametrize("precision", list(Precision))
@pytest.mark.parametrize("n, dim, places, seed", [(60, 8, 5, 0), (300, 64, 37, 1), (500, 128, 2, 2)])
def test_closed_form_equals_pairwise_random(n, dim, places, seed, precision):
    rng = np.random.default_rng(seed)
    d = unit_rows(rng, n, dim).astype(np.float32)
    labels = rng.integers(0, places, n)
    st = negative_stats(d, labels, precision=precision)
    mu, sigma = pairwise_negative_stats(d, labels)
    np.testing.assert_allclose(st.mu, mu, atol=1e-6)
    np.testing.assert_allclose(st.sigma, sigma, atol=1e-6)
    assert np.array_equal(st.n_neg, n - np.bincount(labels)[labels])
    if precision == "float32":
        assert_within_bound(st, mu, sigma, d, labels)


def test_float32_shared_component_sigma_small_against_mu():
    rng = np.random.default_rng(8)
    d, labels = shared_component(rng, 3000, 256, 400)
    mu, sigma = pairwise_negative_stats(d, labels)
    assert 0.79 < mu.min() and mu.max() < 0.81 and sigma.max() < 0.02  # the hard case, as intended
    st = negative_stats(d, labels)
    bound = assert_within_bound(st, mu, sigma, d, labels)
    assert np.abs(st.sigma - sigma).max() < 1e-7  # measured: 4e-9, far inside the worst case
    assert np.abs(st.sigma**2 - sigma**2).max() < 1e-2 * bound.max()
    # Without centring, float32 products err relative to s² ≈ 0.64, not to (s − a)²: the
    # data above is hard enough that this misses the 1e-6 goal, which centring meets.
    gram = (d.T @ d).astype(np.float32)
    quad = np.einsum("ij,ij->i", d @ gram, d, dtype=np.float64)
    naive = (quad - within_place_sq(d, labels)) / st.n_neg - mu**2
    assert np.abs(np.sqrt(np.clip(naive, 0, None)) - sigma).max() > 1e-6


@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.float16])
@pytest.mark.parametrize("block", [4096, 100, 7])
def test_float32_bound_holds_for_every_block_and_dtype_with_a_large_place(dtype, block):
    # one place of 1,500 images (banded same-place scores) beside 199 small ones
    rng = np.random.default_rng(1)
    d = unit_rows(rng, 3000, 24).astype(dtype)
    labels = np.r_[np.zeros(1500, int), rng.integers(1, 200, 1500)]
    mu, sigma = pairwise_negative_stats(d.astype(np.float64), labels)
    assert_within_bound(negative_stats(d, labels, block=block), mu, sigma, d, labels, block=block)


_THREADS_SCRIPT = """
import sys
import numpy as np
sys.path.insert(0, sys.argv[1])
from test_stats import shared_component
from vpr_explorer.method.stats import negative_stats
d, labels = shared_component(np.random.default_rng(9), 6000, 384, 700)
st = negative_stats(d, labels, threads=int(sys.argv[2]))
np.save(sys.argv[3], np.stack([st.mu, st.sigma]))
"""


def _with_blas_threads(blas_threads, threads, tmp_path):
    """``(mu, sigma)`` of the thread test's data, BLAS limited to ``blas_threads``.

    With threadpoolctl, in this process; without it (it is no dependency), in a subprocess
    whose OpenBLAS/OpenMP/MKL thread variables say so.
    """
    d, labels = shared_component(np.random.default_rng(9), 6000, 384, 700)
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        import os
        import subprocess
        import sys
        from pathlib import Path

        out = tmp_path / f"blas{blas_threads}_threads{threads}.npy"
        env = dict(os.environ, **{v: str(blas_threads) for v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS",
                                                                  "MKL_NUM_THREADS")})
        subprocess.run([sys.executable, "-c", _THREADS_SCRIPT, str(Path(__file__).parent), str(threads), str(out)],
                       env=env, check=True, timeout=300)
        return tuple(np.load(out))
    with threadpool_limits(limits=blas_threads, user_api="blas"):
        st = negative_stats(d, labels, threads=threads)
    return st.mu, st.sigma


def test_float32_does_not_depend_on_threads(tmp_path):
    d, labels = shared_component(np.random.default_rng(9), 6000, 384, 700)
    mu1, sigma1 = _with_blas_threads(1, 1, tmp_path)
    mu2, sigma2 = _with_blas_threads(2, 2, tmp_path)
    mu3, sigma3 = _with_blas_threads(2, 3, tmp_path)
    # the elementwise parts are cut the same whatever ``threads``: bit for bit
    assert np.array_equal(mu2, mu3) and np.array_equal(sigma2, sigma3)
    # BLAS threads may reorder the float32 sums: within twice the bound (OpenBLAS: bit for bit)
    np.testing.assert_allclose(mu1, mu2, rtol=0, atol=1e-15)
    bound = sigma_sq_error_bound(d, labels)
    assert (np.abs(sigma1**2 - sigma2**2) <= 2 * bound + FLOAT64_SLACK).all()


def openblas_skylakex() -> bool:
    """Whether numpy's BLAS is OpenBLAS on its SkylakeX kernel, which cuts a product's depth
    alike whatever its shape and threads: there the tiled products below equal whole ones bit
    for bit. Its Haswell kernel (``OPENBLAS_CORETYPE=Haswell``) rounds by shape and threads,
    within the same error bound."""
    from threadpoolctl import threadpool_info

    blas = [i for i in threadpool_info() if i.get("user_api") == "blas"]
    return bool(blas) and all(i.get("internal_api") == "openblas" and i.get("architecture") == "SkylakeX"
                              for i in blas)


def float32_product_bound(a, b):
    """``(m, n)`` bound on |fl32(AᵀB) − AᵀB| for float32 inputs: γ_L·|A|ᵀ|B| with L the depth
    (Higham's bound for any order of the sums), taken in float64."""
    depth = a.shape[0]
    u = np.finfo(np.float32).eps / 2
    return depth * u / (1 - depth * u) * (np.abs(a.astype(np.float64)).T @ np.abs(b.astype(np.float64)))


@pytest.mark.parametrize("dim", [96, 130, 256])
def test_centred_gram_in_lanes_is_one_syrk_per_block_within_its_bound(dim):
    # each block's Gram is one syrk, run side by side (BLAS in one thread each) and added to
    # lane k mod _GRAM_LANES, the last partial block's too: within the float32 bound of the
    # exact Gram per block, the same numbers for 1, 2 and 3 threads, and on OpenBLAS's SkylakeX
    # kernel the numbers of one syrk per block summed lane by lane, bit for bit
    from concurrent.futures import ThreadPoolExecutor

    from vpr_explorer.method.stats import _GRAM_LANES, _centre, _centred_gram

    block = 1000
    rng = np.random.default_rng(4)
    d = unit_rows(rng, 6 * block + 123, dim).astype(np.float32)
    m = _centre(d)
    lanes = [np.zeros((dim, dim)) for _ in range(_GRAM_LANES)]
    exact, bound = np.zeros((dim, dim)), np.zeros((dim, dim))
    for k, lo in enumerate(range(0, len(d), block)):
        e = d[lo : lo + block] - m
        lanes[k % _GRAM_LANES] += np.matmul(e.T, e)
        exact += e.T.astype(np.float64) @ e.astype(np.float64)
        bound += float32_product_bound(e, e)
    expected = lanes[0] + lanes[1] + lanes[2] + lanes[3]
    got = {}
    for threads in (1, 2, 3):
        with ThreadPoolExecutor(threads) as pool:
            gram, total = got[threads] = _centred_gram(d, m, block, pool, threads)
        assert (np.abs(gram - exact) <= bound + 1e-12).all()
        if openblas_skylakex():
            np.testing.assert_array_equal(gram, expected)
        np.testing.assert_array_equal(gram, gram.T)
        np.testing.assert_allclose(total, d.sum(axis=0, dtype=np.float64), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(got[3][0], got[2][0])  # one BLAS thread per syrk in both
    np.testing.assert_array_equal(got[3][1], got[1][1])  # T: the same parts in the same order


def _quadratic_forms_by_block(d, gram, block):
    """``_quadratic_forms`` one block of rows at a time: per block, every column block of W,
    then the row sums."""
    from vpr_explorer.method.stats import _TRI_BLOCKS

    edges = np.linspace(0, d.shape[1], _TRI_BLOCKS + 1).round().astype(int)
    w = [np.asarray(gram[:hi, lo:hi], dtype=np.float32) for lo, hi in zip(edges[:-1], edges[1:])]
    for wj, lo in zip(w, edges[:-1]):
        wj[:lo] *= 2
    quad = np.empty(len(d))
    for lo in range(0, len(d), block):
        x = np.asarray(d[lo : lo + block], dtype=np.float32)
        y = np.empty_like(x)
        for (c0, c1), wj in zip(zip(edges[:-1], edges[1:]), w):
            y[:, c0:c1] = x[:, :c1] @ wj
        quad[lo : lo + len(x)] = np.einsum("ij,ij->i", y, x, dtype=np.float64)
    return quad


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.float16])
def test_quadratic_forms_in_row_tasks_are_the_block_products(monkeypatch, dtype):
    # dᵢᵀWdᵢ from tasks of ``_QUAD_ROWS`` rows, any thread count: within the float32 bound of
    # the exact forms, and on OpenBLAS's SkylakeX kernel the products of whole blocks of 4,096
    # rows bit for bit (a GEMM's rows are cut between calls as between threads, never a sum)
    from concurrent.futures import ThreadPoolExecutor

    from vpr_explorer.method import stats
    from vpr_explorer.method.stats import BLOCK, _centre, _centred_gram, _quadratic_forms

    rng = np.random.default_rng(11)
    # 260 columns: W's 8 column blocks 32 or 33 wide (uneven); narrower ones (16 at D = 130) send
    # the tasks' products to OpenBLAS's small-matrix kernel, which rounds otherwise (within the bound)
    d = unit_rows(rng, BLOCK + 1500, 260).astype(dtype)
    with ThreadPoolExecutor(2) as pool:
        gram, _ = _centred_gram(d, _centre(d), BLOCK, pool, 2)
    expected = _quadratic_forms_by_block(d, gram, BLOCK)
    # (tasks of a few hundred rows of so narrow a W go to OpenBLAS's small-matrix kernel, which
    # rounds otherwise: 333 rows here; within the bound, which holds for any order of the sums)
    x = np.asarray(d, dtype=np.float64)
    exact = np.einsum("ij,ij->i", x @ gram, x)
    # W rounded to float32 once, the rows to float32 (float64 input), then each yⱼ = Σₖ xₖW'ₖⱼ
    # a float32 sum of depth ≤ D; |x|ᵀ|W'||x| = |x|ᵀ|C||x| (W' holds C's upper triangle twice)
    u = np.finfo(np.float32).eps / 2
    dim = d.shape[1]
    bound = (3 * u + dim * u / (1 - dim * u)) * np.einsum("ij,ij->i", np.abs(x) @ np.abs(gram), np.abs(x))
    for rows, threads in ((1024, 1), (1024, 2), (1024, 3), (2048, 3), (4096, 2)):
        monkeypatch.setattr(stats, "_QUAD_ROWS", rows)
        with ThreadPoolExecutor(threads) as pool:
            got = _quadratic_forms(d, gram, pool, threads > 1)
        assert (np.abs(got - exact) <= bound + 1e-12).all(), (rows, threads)
        if openblas_skylakex():
            np.testing.assert_array_equal(got, expected)


def test_float32_and_float64_side_by_side():
    rng = np.random.default_rng(10)
    d, labels = shared_component(rng, 2000, 128, 300)
    a = negative_stats(d, labels, precision="float32")
    b = negative_stats(d, labels, precision=Precision.FLOAT64)
    np.testing.assert_allclose(a.mu, b.mu, rtol=0, atol=1e-14)
    assert (np.abs(a.sigma**2 - b.sigma**2) <= sigma_sq_error_bound(d, labels) + FLOAT64_SLACK).all()
    np.testing.assert_allclose(a.sigma, b.sigma, rtol=0, atol=1e-7)


def test_closed_form_small_blocks_same_answer():
    rng = np.random.default_rng(3)
    d = unit_rows(rng, 250, 16)
    labels = rng.integers(0, 9, 250)
    a = negative_stats(d, labels, precision="float64")
    b = negative_stats(d, labels, block=7, precision="float64")
    np.testing.assert_allclose(a.mu, b.mu, atol=1e-12)
    np.testing.assert_allclose(a.sigma, b.sigma, atol=1e-12)
    # float32: the block is the depth of the float32 Gram sums, so σ moves, within both bounds
    c, e = negative_stats(d, labels), negative_stats(d, labels, block=7)
    np.testing.assert_allclose(c.mu, e.mu, rtol=0, atol=1e-15)
    bound = sigma_sq_error_bound(d, labels) + sigma_sq_error_bound(d, labels, block=7)
    assert (np.abs(c.sigma**2 - e.sigma**2) <= bound + FLOAT64_SLACK).all()


def test_hand_computed_tiny_case():
    # place 0: e1, e2; place 1: e1 (a duplicate of image 0), (e1+e2)/√2
    r = 1 / np.sqrt(2)
    d = np.array([[1, 0], [0, 1], [1, 0], [r, r]])
    labels = np.array([0, 0, 1, 1])
    # image 0 (e1) vs place 1: scores 1 and r -> mean (1+r)/2, std (1-r)/2
    # image 1 (e2) vs place 1: scores 0 and r -> mean r/2, std r/2
    # image 2 (e1) vs place 0: 1, 0 -> 0.5, 0.5;  image 3 vs place 0: r, r -> r, 0
    mu, sigma = [(1 + r) / 2, r / 2, 0.5, r], np.array([(1 - r) / 2, r / 2, 0.5, 0])
    st = negative_stats(d, labels, precision="float64")
    np.testing.assert_allclose(st.mu, mu, atol=1e-12)
    np.testing.assert_allclose(st.sigma, sigma, atol=1e-7)
    np.testing.assert_allclose(st.weights, [0.5, 0.5, 0.5, 0.5])
    # float32: μ as exact; σ² within the bound, so a σ of 0 comes out as up to √bound (~7e-4
    # here, 1.6e-4 measured): what SIGMA_FLOOR-weighted thresholds then see
    st = negative_stats(d, labels)
    np.testing.assert_allclose(st.mu, mu, atol=1e-12)
    assert (np.abs(st.sigma**2 - sigma**2) <= sigma_sq_error_bound(d, labels) + FLOAT64_SLACK).all()


def test_within_place_sq_matches_loops():
    rng = np.random.default_rng(4)
    d = unit_rows(rng, 90, 12)
    labels = rng.integers(0, 11, 90)
    s = d @ d.T
    ref = [sum(s[i, j] ** 2 for j in range(90) if labels[j] == labels[i]) for i in range(90)]
    np.testing.assert_allclose(within_place_sq(d, labels, block_elems=500), ref, atol=1e-12)


def test_places_without_training_images_and_unequal_sizes():
    rng = np.random.default_rng(5)
    d = unit_rows(rng, 40, 6)
    labels = np.r_[np.zeros(30, int), np.full(9, 3), [5]]  # places 1, 2, 4 empty; place 5 single image
    st = negative_stats(d, labels, n_places=7)
    mu, sigma = pairwise_negative_stats(d, labels)
    np.testing.assert_allclose(st.mu, mu, atol=1e-12)
    np.testing.assert_allclose(st.sigma, sigma, atol=1e-7)
    mean, std = mixture_moments(st)
    assert np.isnan(mean[[1, 2, 4, 6]]).all() and np.isfinite(mean[[0, 3, 5]]).all()


def test_mixture_moments_match_sampling_free_formula():
    rng = np.random.default_rng(6)
    d = unit_rows(rng, 50, 5)
    labels = np.repeat(np.arange(5), 10)
    st = negative_stats(d, labels)
    mean, std = mixture_moments(st)
    # The mixture of place 2 on a fine grid: its numeric mean and std equal the closed form.
    mu, sig, w = st.components(2)
    x = np.linspace(-3, 3, 200_001)
    pdf = mixture_pdf(x, mu, sig, w)
    dx = x[1] - x[0]
    assert abs(pdf.sum() * dx - 1) < 1e-6
    m = (x * pdf).sum() * dx
    assert abs(m - mean[2]) < 1e-6
    assert abs(np.sqrt(((x - m) ** 2 * pdf).sum() * dx) - std[2]) < 1e-6


def test_positive_means_against_pairs():
    rng = np.random.default_rng(7)
    d = unit_rows(rng, 30, 4)
    labels = np.r_[np.zeros(10, int), np.ones(19, int), [2]]
    s = d @ d.T
    pm = positive_means(d, labels, 3)
    for p in (0, 1):
        idx = np.flatnonzero(labels == p)
        sub = s[np.ix_(idx, idx)]
        assert abs(pm[p] - sub[~np.eye(len(idx), dtype=bool)].mean()) < 1e-12
    assert np.isnan(pm[2])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_fits_positive_means_from_the_place_terms_against_pairs(monkeypatch, dtype):
    # stats_rows takes them from the place terms' float64 same-place scores: places of 1 (NaN),
    # 2, 7 and one past _BIG_PLACE (scored a band of rows at a time), in shuffled row order
    from vpr_explorer.method import stats

    monkeypatch.setattr(stats, "_BIG_PLACE", 16)
    rng = np.random.default_rng(12)
    labels = np.r_[[0], [1, 1], np.full(7, 2), np.full(40, 3), np.repeat(np.arange(4, 30), 5)]
    labels = labels[rng.permutation(len(labels))]
    d = (unit_rows(rng, len(labels), 24) * 0.3 + rng.standard_normal(24)).astype(dtype)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    _, pm = stats.stats_rows(d, None, labels, 30, threads=2)
    s = d.astype(np.float64) @ d.astype(np.float64).T
    assert np.isnan(pm[0])
    for p in range(1, 30):
        idx = np.flatnonzero(labels == p)
        sub = s[np.ix_(idx, idx)]
        assert abs(pm[p] - sub[~np.eye(len(idx), dtype=bool)].mean()) < 1e-13, p
    np.testing.assert_allclose(pm, positive_means(d, labels, 30), rtol=0, atol=1e-13)


def _positive_means_one_product(d, labels, n_places, rows):
    """``positive_means`` in one thread: one sparse indicator product per block."""
    from scipy import sparse

    sums, sq = np.zeros((n_places, d.shape[1])), np.empty(len(labels))
    for lo in range(0, len(labels), rows):
        x = np.asarray(d[lo : lo + rows], dtype=np.float64)
        part = sparse.csr_matrix((np.ones(len(x)), (labels[lo : lo + len(x)], np.arange(len(x)))),
                                 shape=(n_places, len(x)))
        sums += part @ x
        sq[lo : lo + len(x)] = np.einsum("ij,ij->i", x, x)
    counts = np.bincount(labels, minlength=n_places).astype(np.float64)
    pairs = counts * (counts - 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (np.einsum("ij,ij->i", sums, sums) - np.bincount(labels, weights=sq, minlength=n_places)) / pairs
    out[pairs == 0] = np.nan
    return out


@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.float16])
def test_positive_means_are_the_same_sums_whatever_the_threads(monkeypatch, dtype):
    # float64 rows make the order of the sums visible in the last bits (float32 sums are exact)
    from vpr_explorer.method import stats

    monkeypatch.setattr(stats, "_MEAN_ROWS", 97)  # several blocks, places split across them
    rng = np.random.default_rng(3)
    labels = rng.integers(0, 23, 700)
    labels[labels == 5] = 6  # a place without images
    d = (rng.standard_normal((700, 33)) * np.exp(rng.uniform(-8, 8, (700, 1)))).astype(dtype)
    expected = _positive_means_one_product(d, labels, 24, 97)
    for threads in (1, 2, 3, 8):
        np.testing.assert_array_equal(positive_means(d, labels, 24, threads=threads), expected)
    assert np.isnan(expected[5]) and np.isfinite(expected[6])


@pytest.mark.parametrize(
    "d, labels, fragment",
    [
        (np.array([[1.0, 0], [np.nan, 1], [0, 1]]), [0, 1, 1], "rows 1 contain NaN"),
        (np.array([[1.0, 0], [0, 0], [0, 1]]), [0, 1, 1], "rows 1 are all zero"),
        (np.array([[1.0, 0], [0, 1]]), [0, 0], "only 1 place"),
        (np.array([[1.0, 0], [0, 1]]), [0, -1], "must be >= 0"),
        (np.zeros((0, 3)), [], "non-empty"),
    ],
)
def test_bad_descriptors_and_labels(d, labels, fragment):
    with pytest.raises(VPRInputError, match=fragment):
        negative_stats(d, np.array(labels, dtype=np.int64))


def test_rows_whose_squares_overflow_are_not_called_nan():
    # the NaN/inf check looks at row sums of squares first: an overflow there is no NaN
    for d in (np.array([[1e300, 1e300], [0, 1]]), np.array([[3e19, 1], [np.inf, 0], [0, 1]], dtype=np.float32)):
        if np.isfinite(d).all():
            assert validate_descriptors(d) is d
        else:
            with pytest.raises(VPRInputError, match="rows 1 contain NaN or inf"):
                validate_descriptors(d)


@pytest.mark.parametrize("kw, fragment", [({"precision": "half"}, "precision: expected one of 'float32', 'float64'"),
                                          ({"block": 0}, "block: expected a positive"),
                                          ({"block": 2.5}, "block: expected a positive"),
                                          ({"threads": 0}, "threads=0: must be a whole number"),
                                          ({"threads": True}, "threads=True: must be a whole number")])
def test_bad_settings(kw, fragment):
    # every entry point of the closed form checks block and threads alike
    from vpr_explorer.method.stats import negative_stats_rows, stats_rows

    rng = np.random.default_rng(0)
    d, labels = unit_rows(rng, 10, 4), np.arange(10) % 3
    with pytest.raises(VPRInputError, match=fragment):
        negative_stats(d, labels, **kw)
    if "precision" not in kw:
        for fit in (negative_stats_rows, stats_rows):
            with pytest.raises(VPRInputError, match=fragment):
                fit(d, None, labels, **kw)


@pytest.mark.realdata
@pytest.mark.parametrize("precision", list(Precision))
@pytest.mark.parametrize("fixture", ["gp_pixels", "gp_effnet"])
def test_closed_form_equals_pairwise_on_real_descriptors(request, fixture, gardens_point, precision):
    # pixel descriptors share a large component (scores far from 0): the float32 cancellation case
    d = request.getfixturevalue(fixture)
    places = make_places(gardens_point, PlaceSpec(3, 10))
    keep = places.image_place >= 0
    st = negative_stats(d[keep], places.image_place[keep], precision=precision)
    mu, sigma = pairwise_negative_stats(d[keep], places.image_place[keep])
    np.testing.assert_allclose(st.mu, mu, atol=1e-6)
    np.testing.assert_allclose(st.sigma, sigma, atol=1e-6)
    if precision == "float32":
        assert_within_bound(st, mu, sigma, d[keep], places.image_place[keep])
    # All 600 images, every frame its own place (the hardest case for the within-place term).
    frames = gardens_point.image_frame
    st = negative_stats(d, frames, precision=precision)
    mu, sigma = pairwise_negative_stats(d, frames)
    np.testing.assert_allclose(st.mu, mu, atol=1e-6)
    np.testing.assert_allclose(st.sigma, sigma, atol=1e-6)
    if precision == "float32":
        assert_within_bound(st, mu, sigma, d, frames)


# --------------------------------------------------------------------------- device= (torch)


@pytest.mark.parametrize("dtype, block", [(np.float32, 4096), (np.float64, 100), (np.float16, 7)])
def test_torch_device_within_the_same_bound(dtype, block, device_under_test):
    # The torch path (on CPU tensors here; on a GPU, the same code, under benchmarks/gpu_check.py)
    # keeps μ exact to float64 rounding and σ² within the float32 bound, on the hard
    # shared-component data.
    rng = np.random.default_rng(3)
    d, labels = shared_component(rng, 1200, 64, 150)
    d = d.astype(dtype)
    mu, sigma = pairwise_negative_stats(d.astype(np.float64), labels)
    st = negative_stats(d, labels, block=block, device=device_under_test)
    assert_within_bound(st, mu, sigma, d, labels, block=block)
    np.testing.assert_array_equal(st.n_neg, negative_stats(d, labels).n_neg)
    np.testing.assert_allclose(st.sigma, negative_stats(d, labels, block=block).sigma, rtol=0, atol=1e-7)


@pytest.mark.parametrize("block", [4096, 333])
def test_a_database_fit_on_a_device_reads_the_rows_in_places_within_the_bound(block, device_under_test):
    # stats_rows (the fit of a database's images in places, from a float16 map) on the device:
    # the rows gathered block by block, the pairwise reference's μ to float64 rounding and σ²
    # within the float32 bound; n⁻ and the positive means as the numpy path gives them.
    from vpr_explorer.method.stats import stats_rows

    rng = np.random.default_rng(8)
    d, labels = shared_component(rng, 1500, 48, 120)
    d16 = d.astype(np.float16)
    rows = np.flatnonzero(np.arange(1500) % 5 != 2)  # gaps between runs of rows
    got, pm = stats_rows(d16, rows, labels[rows], block=block, device=device_under_test)
    gathered = d16[rows].astype(np.float32)
    mu, sigma = pairwise_negative_stats(gathered.astype(np.float64), labels[rows])
    assert_within_bound(got, mu, sigma, gathered, labels[rows], block=block)
    want, want_pm = stats_rows(d16, rows, labels[rows], block=block)
    np.testing.assert_array_equal(got.n_neg, want.n_neg)
    np.testing.assert_allclose(pm, want_pm, rtol=0, atol=1e-13)
    bad = d16.copy()
    bad[rows[700]] = np.nan  # stops the fit, naming the row among those in places, before any product
    with pytest.raises(VPRInputError, match=r"rows 700 contain NaN or inf"):
        stats_rows(bad, rows, labels[rows], device=device_under_test)


@pytest.mark.parametrize("value, want", [(None, None), ("", None), ("numpy", None), ("cpu", "cpu"), ("auto", "auto")])
def test_the_fit_device_setting(monkeypatch, value, want):
    import torch

    from vpr_explorer.method.stats import fit_device
    from vpr_explorer.settings import DEVICE_ENV

    if value is None:
        monkeypatch.delenv(DEVICE_ENV, raising=False)
    else:
        monkeypatch.setenv(DEVICE_ENV, value)
    if want == "auto":
        want = "cuda" if torch.cuda.is_available() else None
    assert fit_device() == want


@pytest.mark.parametrize("value, fragment", [("tpu", "not a torch device"), ("gpu0", "not a torch device"),
                                             ("cuda:7", "CUDA device")])
def test_a_bad_fit_device_setting_names_the_variable(monkeypatch, value, fragment):
    import torch

    from vpr_explorer.method.stats import fit_device
    from vpr_explorer.settings import DEVICE_ENV

    monkeypatch.setenv(DEVICE_ENV, value)
    if value == "cuda:7" and torch.cuda.device_count() > 7:
        pytest.skip("this machine has a cuda:7")
    with pytest.raises(VPRInputError, match=f"VPR_EXPLORER_DEVICE={value}: [^;]*{fragment}[^;]*; set it to numpy"):
        fit_device()


@pytest.mark.parametrize("kw, fragment", [({"device": "tpu"}, "device='tpu'"),
                                          ({"device": "cpu", "precision": "float64"}, "precision='float32' only")])
def test_bad_device(kw, fragment):
    rng = np.random.default_rng(0)
    with pytest.raises(VPRInputError, match=fragment):
        negative_stats(unit_rows(rng, 10, 4), np.arange(10) % 3, **kw)


def test_cuda_device_runs_or_says_why():
    import torch

    rng = np.random.default_rng(4)
    d, labels = unit_rows(rng, 300, 32).astype(np.float32), rng.integers(0, 30, 300)
    if not torch.cuda.is_available():
        with pytest.raises(VPRInputError, match="no CUDA device is available here"):
            negative_stats(d, labels, device="cuda")
        return
    mu, sigma = pairwise_negative_stats(d.astype(np.float64), labels)
    assert_within_bound(negative_stats(d, labels, device="cuda"), mu, sigma, d, labels)


def test_one_blas_thread_holds_in_any_thread():
    # threadpoolctl (3.8) keeps OpenBLAS's limits to the first thread that set one while it
    # lives: after the main thread used ``one_blas_thread`` (a library call before the app),
    # the app's script threads' limits were silently dropped and each pool thread's GEMMs ran
    # with every BLAS thread. Whichever thread enters it must get one BLAS thread, and leave
    # the count as it found it.
    import threading

    from threadpoolctl import threadpool_info

    from vpr_explorer.method.stats import one_blas_thread

    def blas_threads():
        return [i["num_threads"] for i in threadpool_info() if i.get("user_api") == "blas"]

    before = blas_threads()
    seen = {}

    def probe(tag):
        with one_blas_thread():
            seen[tag] = blas_threads()
        seen[tag + " after"] = blas_threads()

    probe("main")
    worker = threading.Thread(target=probe, args=("other",))
    worker.start()
    worker.join()
    assert seen["main"] and all(n == 1 for n in seen["main"])
    assert all(n == 1 for n in seen["other"]), seen
    assert seen["main after"] == before and seen["other after"] == before and blas_threads() == before


def test_the_all_zero_row_bound_is_the_extractors():
    """The statistics refuse as all zero exactly the rows the extractors cannot normalise."""
    from vpr_explorer.descriptors.extract import MIN_SQUARED_NORM
    from vpr_explorer.method.stats import ZERO_SQUARED_NORM

    assert ZERO_SQUARED_NORM == MIN_SQUARED_NORM
