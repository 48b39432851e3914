"""Closed-form negative statistics equal the plain pairwise computation (DESIGN.md §2)."""

import numpy as np
import pytest

from reference import pairwise_negative_stats, unit_rows
from vpr_explorer.errors import VPRInputError
from vpr_explorer.places import PlaceSpec, make_places
from vpr_explorer.stats import (
    mixture_moments,
    mixture_pdf,
    negative_stats,
    positive_means,
    within_place_sq,
)


@pytest.mark.parametrize("n, dim, places, seed", [(60, 8, 5, 0), (300, 64, 37, 1), (500, 128, 2, 2)])
def test_closed_form_equals_pairwise_random(n, dim, places, seed):
    rng = np.random.default_rng(seed)
    d = unit_rows(rng, n, dim).astype(np.float32)
    labels = rng.integers(0, places, n)
    st = negative_stats(d, labels)
    mu, sigma = pairwise_negative_stats(d, labels)
    np.testing.assert_allclose(st.mu, mu, atol=1e-6)
    np.testing.assert_allclose(st.sigma, sigma, atol=1e-6)
    assert np.array_equal(st.n_neg, n - np.bincount(labels)[labels])


def test_closed_form_small_blocks_same_answer():
    rng = np.random.default_rng(3)
    d = unit_rows(rng, 250, 16)
    labels = rng.integers(0, 9, 250)
    a, b = negative_stats(d, labels), negative_stats(d, labels, block=7)
    np.testing.assert_allclose(a.mu, b.mu, atol=1e-12)
    np.testing.assert_allclose(a.sigma, b.sigma, atol=1e-12)


def test_hand_computed_tiny_case():
    # place 0: e1, e2; place 1: e1 (a duplicate of image 0), (e1+e2)/√2
    r = 1 / np.sqrt(2)
    d = np.array([[1, 0], [0, 1], [1, 0], [r, r]])
    st = negative_stats(d, np.array([0, 0, 1, 1]))
    # image 0 (e1) vs place 1: scores 1 and r -> mean (1+r)/2, std (1-r)/2
    # image 1 (e2) vs place 1: scores 0 and r -> mean r/2, std r/2
    # image 2 (e1) vs place 0: 1, 0 -> 0.5, 0.5;  image 3 vs place 0: r, r -> r, 0
    np.testing.assert_allclose(st.mu, [(1 + r) / 2, r / 2, 0.5, r], atol=1e-12)
    np.testing.assert_allclose(st.sigma, [(1 - r) / 2, r / 2, 0.5, 0], atol=1e-7)
    np.testing.assert_allclose(st.weights, [0.5, 0.5, 0.5, 0.5])


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


@pytest.mark.realdata
@pytest.mark.parametrize("fixture", ["gp_pixels", "gp_effnet"])
def test_closed_form_equals_pairwise_on_real_descriptors(request, fixture, gardens_point):
    d = request.getfixturevalue(fixture)
    places = make_places(gardens_point, PlaceSpec(3, 10))
    keep = places.image_place >= 0
    st = negative_stats(d[keep], places.image_place[keep])
    mu, sigma = pairwise_negative_stats(d[keep], places.image_place[keep])
    np.testing.assert_allclose(st.mu, mu, atol=1e-6)
    np.testing.assert_allclose(st.sigma, sigma, atol=1e-6)
    # All 600 images, every frame its own place (the hardest case for the within-place term).
    frames = gardens_point.image_frame
    st = negative_stats(d, frames)
    mu, sigma = pairwise_negative_stats(d, frames)
    np.testing.assert_allclose(st.mu, mu, atol=1e-6)
    np.testing.assert_allclose(st.sigma, sigma, atol=1e-6)
