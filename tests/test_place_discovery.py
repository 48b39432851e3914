"""Online place discovery (``method.place_discovery``) against a plain reference and hand cases.

The reference below is written straight from the authors' ``OnlinePlaceDiscovery``
(NickTrinh/VPR_Tutorial, ``experiments/online_place_discovery.py``): frame by frame, lists
of frames per place, every mean similarity taken over explicit index lists of a Gram
matrix, and statistics recomputed from lists of values with ``np.mean``/``np.std`` rather
than running sums.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.place_discovery import discover, discovered_places
from vpr_explorer.method.places import PlaceSpec, frame_places


# --------------------------------------------------------------------------- reference


def reference_places(descriptors, alpha=1.5, min_size=2, hysteresis=2, cap=10) -> tuple[np.ndarray, list, list]:
    """The authors' algorithm as a plain loop: ``(place, scores, thetas)`` (online frames only)."""
    x = np.asarray(descriptors, dtype=np.float64)
    x = x / np.linalg.norm(x, axis=1, keepdims=True)
    sim = x @ x.T
    n = len(x)

    def mean_sim(t, frames):
        return float(np.mean(sim[t, frames]))

    def std_or(values, fallback):
        return float(np.std(values)) if len(values) >= 2 else fallback

    places = [[0]]
    phase = "p0"
    consec = []
    neg_values, pos_values = [], []
    pending = []
    scores, thetas = [], []

    def open_stats(p):
        others = [f for q, fr in enumerate(places) if q != p for f in fr]
        neg = [mean_sim(t, others) for t in places[p]]
        pos = []
        if len(places[p]) >= 2:
            for t in places[p]:
                pos.append(mean_sim(t, [f for f in places[p] if f != t]))
        return neg, pos

    for t in range(1, n):
        if phase == "p0":
            consec.append(float(sim[t - 1, t]))
            dip = False
            if len(consec) >= min_size + 1:
                prev = np.array(consec[:-1])
                base_std = prev.std() if len(prev) > 2 else 0.1
                dip = consec[-1] < prev.mean() - alpha * base_std
            if dip:
                places.append([t])
                phase = "p1"
            else:
                places[0].append(t)
            continue
        if phase == "p1":
            places[1].append(t)
            if len(places[1]) >= min_size:
                neg_values, pos_values = open_stats(1)
                phase = "online"
            continue
        cur = len(places) - 1
        score = mean_sim(t, places[cur])
        mu_neg = float(np.mean(neg_values))
        sd_neg = std_or(neg_values, 0.1)
        mu_pos = float(np.mean(pos_values)) if pos_values else 0.0
        k = 1.0 if sd_neg < 1e-8 else float(np.floor((mu_pos - mu_neg) / sd_neg))
        k = max(min(k, cap), 0)
        theta = mu_neg + k * sd_neg
        scores.append(score)
        thetas.append(theta)
        if score <= theta:
            pending.append(t)
            if len(pending) >= hysteresis:
                places.append(pending)
                pending = []
                neg_values, pos_values = open_stats(len(places) - 1)
            continue
        places[cur].extend(pending)
        pending = []
        places[cur].append(t)
        pos_values.append(mean_sim(t, places[cur]))
        others = [f for fr in places[:cur] for f in fr]
        neg_values.append(mean_sim(t, others))

    place = np.full(n, -1, dtype=np.int64)
    for p, frames in enumerate(places):
        place[frames] = p
    return place, scores, thetas


def assert_same_as_reference(d, **params):
    found = discover(d, **params)
    place, scores, thetas = reference_places(d, **params)
    np.testing.assert_array_equal(found.place, place)
    online = ~np.isnan(found.score)
    np.testing.assert_allclose(found.score[online], scores, atol=1e-9)
    np.testing.assert_allclose(found.theta[online], thetas, atol=1e-9)
    return found


# --------------------------------------------------------------------------- streams


def segments(*spec: tuple[int, int], dim: int = 8) -> np.ndarray:
    """Identical images per segment: ``(direction, length)`` pairs, one-hot rows (similarities exactly 0 or 1)."""
    eye = np.eye(dim, dtype=np.float32)
    return np.concatenate([np.repeat(eye[k : k + 1], length, axis=0) for k, length in spec])


def route(seed: int, n: int = 160, dim: int = 32, noise: float = 0.35) -> np.ndarray:
    """A synthetic route: segments of random length around random directions, with noise."""
    rng = np.random.default_rng(seed)
    rows = []
    while len(rows) < n:
        base = rng.normal(size=dim)
        for _ in range(int(rng.integers(1, 15))):
            rows.append(base + noise * np.linalg.norm(base) / np.sqrt(dim) * rng.normal(size=dim))
    d = np.asarray(rows[:n], dtype=np.float32)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


# --------------------------------------------------------------------------- hand cases


def test_three_segments_of_identical_images_are_three_places():
    d = segments((0, 5), (1, 5), (2, 5))
    found = assert_same_as_reference(d)
    np.testing.assert_array_equal(found.place, np.repeat([0, 1, 2], 5))
    assert found.n_places == 3
    np.testing.assert_array_equal(found.sizes, [5, 5, 5])
    # dip at frame 5 (consecutive 0 < mean 1 − 1.5·0); place 1 = frames 5, 6; online from 7
    assert found.online_from == 7
    place, n = discovered_places(d)
    assert n == 3 and place.dtype == np.int64 and place.flags.writeable


def test_score_exactly_at_threshold_counts_as_below():
    # negatives of place 1 are all 0 -> σ⁻ = 0 -> n = 1, θ = 0; a new segment scores exactly 0 = θ
    found = discover(segments((0, 5), (1, 5), (2, 5)))
    assert found.theta[10] == 0.0 and found.score[10] == 0.0
    assert found.place[10] == 2


def test_single_outlier_frame_does_not_start_a_place():
    d = segments((0, 6), (1, 5), (2, 1), (1, 5))
    found = assert_same_as_reference(d)
    np.testing.assert_array_equal(found.place, np.repeat([0, 1], [6, 11]))
    # it was pending (at or below θ), then merged back into the current place
    assert found.score[11] <= found.theta[11]


def test_segment_shorter_than_hysteresis_is_merged_one_as_long_becomes_a_place():
    short = segments((0, 6), (1, 5), (2, 2), (1, 5))
    np.testing.assert_array_equal(discover(short, hysteresis=3).place, np.repeat([0, 1], [6, 12]))
    np.testing.assert_array_equal(discover(short, hysteresis=2).place, np.repeat([0, 1, 2, 3], [6, 5, 2, 5]))
    for h in (1, 2, 3):
        assert_same_as_reference(short, hysteresis=h)


def test_segment_before_frame_m_plus_1_is_merged_into_place_0():
    # the bootstrap looks for a dip only from frame m + 1 = 3: a change at frame 2 is not seen,
    # and with it in the baseline later changes are not dips either
    d = segments((0, 2), (1, 10))
    found = assert_same_as_reference(d)
    assert found.n_places == 1 and (found.place == 0).all()
    with pytest.raises(VPRInputError, match="found 1 place"):
        discovered_places(d)
    # with m = 1 the change at frame 2 is a dip (baseline [1], fallback std 0.1)
    np.testing.assert_array_equal(discover(d, min_size=1).place, np.repeat([0, 1], [2, 10]))


def test_place_1_takes_at_least_two_frames():
    # m = 1: the authors' code checks place 1's size from the frame after the dip, so it holds 2
    d = segments((0, 4), (1, 1), (2, 5))
    found = assert_same_as_reference(d, min_size=1)
    np.testing.assert_array_equal(found.place, np.repeat([0, 1], [4, 6]))


def test_constant_stream_is_one_place_consecutive_equal_to_mean_is_no_dip():
    d = segments((3, 20))
    found = discover(d, alpha=0.0)
    assert found.n_places == 1 and found.online_from == 20 and np.isnan(found.score).all()


def test_trailing_pending_frames_belong_to_no_place():
    d = segments((0, 6), (1, 5), (2, 1))
    found = assert_same_as_reference(d)
    np.testing.assert_array_equal(found.place, np.r_[np.repeat([0, 1], [6, 5]), -1])
    assert found.n_places == 2
    place, n = discovered_places(d)
    assert n == 2 and place[-1] == -1


def test_stream_ending_inside_the_bootstrap():
    np.testing.assert_array_equal(discover(segments((0, 1))).place, [0])
    np.testing.assert_array_equal(discover(segments((0, 5), (1, 1))).place, np.repeat([0, 1], [5, 1]))
    np.testing.assert_array_equal(discover(segments((0, 5), (1, 2))).place, np.repeat([0, 1], [5, 2]))


def test_rows_are_normalised():
    d = segments((0, 5), (1, 5), (2, 5))
    np.testing.assert_array_equal(discover(d * 3.0).place, discover(d).place)


# --------------------------------------------------------------------------- against the reference


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize(
    ("alpha", "min_size", "hysteresis", "cap"),
    [(1.5, 2, 2, 10), (0.5, 1, 1, 10), (1.0, 3, 3, 2), (2.5, 2, 2, 0)],
)
def test_random_routes_match_reference(seed, alpha, min_size, hysteresis, cap):
    d = route(seed)
    found = assert_same_as_reference(d, alpha=alpha, min_size=min_size, hysteresis=hysteresis, cap=cap)
    assigned = found.place[found.place >= 0]
    # contiguous runs in route order, ids 0..P-1, -1 only at the end
    np.testing.assert_array_equal(np.unique(assigned), np.arange(found.n_places))
    assert (np.diff(assigned) >= 0).all() and (np.diff(assigned) <= 1).all()
    assert (found.place[len(assigned):] == -1).all() and len(found.place) - len(assigned) < hysteresis


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"alpha": -0.1}, "alpha"),
        ({"alpha": float("nan")}, "alpha"),
        ({"alpha": True}, "alpha"),
        ({"min_size": 0}, "min_size"),
        ({"min_size": 1.5}, "min_size"),
        ({"hysteresis": 0}, "hysteresis"),
        ({"hysteresis": True}, "hysteresis"),
        ({"cap": -1}, "cap"),
        ({"cap": float("inf")}, "cap"),
    ],
)
def test_bad_parameters(kwargs, match):
    with pytest.raises(VPRInputError, match=match):
        discover(segments((0, 5), (1, 5)), **kwargs)


def test_bad_descriptors():
    good = segments((0, 5), (1, 5))
    nan = good.copy()
    nan[3, 0] = np.nan
    zero = good.copy()
    zero[4] = 0
    for bad, match in [(good[0], "shape"), (good[:0], "shape"), (nan, "NaN"), (zero, "all zero")]:
        with pytest.raises(VPRInputError, match=match):
            discover(bad)


# --------------------------------------------------------------------------- real data


@pytest.mark.realdata
def test_gardens_point_day_right_pixels(gardens_point, gp_pixels):
    i = gardens_point.traversal_index("day_right")
    d = gp_pixels[i * gardens_point.n_frames : (i + 1) * gardens_point.n_frames]
    t0 = time.perf_counter()
    place, n = discovered_places(d)
    seconds = time.perf_counter() - t0
    found = assert_same_as_reference(d)
    np.testing.assert_array_equal(found.place, place)
    grid = frame_places(len(d), PlaceSpec(3, 10))
    sizes = np.bincount(place[place >= 0])
    print(f"\nGardensPoint day_right pixels: {n} places discovered in {seconds * 1e3:.1f} ms, sizes "
          f"{sizes.tolist()}, {np.count_nonzero(place < 0)} left out; group 3/step 10: "
          f"{grid.max() + 1} places × 3 frames")
    assert n >= 2


@pytest.mark.realdata
def test_nordland_summer_pixels(data_root):
    from vpr_explorer.pipeline import dataset_descriptors, resolve_dataset

    nordland = resolve_dataset(data_root / "Nordland_64x32")
    i = nordland.traversal_index("summer")
    d = dataset_descriptors(nordland, "pixels")[i * nordland.n_frames : (i + 1) * nordland.n_frames]
    t0 = time.perf_counter()
    place, n = discovered_places(d)
    seconds = time.perf_counter() - t0
    found = assert_same_as_reference(d)
    np.testing.assert_array_equal(found.place, place)
    sizes = np.bincount(place[place >= 0])
    print(f"\nNordland summer pixels ({len(d)} images): {n} places in {seconds * 1e3:.1f} ms, sizes "
          f"min {sizes.min()} median {np.median(sizes):g} max {sizes.max()}, {np.count_nonzero(place < 0)} left out")
