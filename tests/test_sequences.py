"""SeqSLAM (``method.sequences``) against a plain-loop reference of OpenSeqSLAM's definition,
hand cases, boundaries, the order check, and GardensPoint night_right vs day_right."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from vpr_explorer.data.layouts import Layout
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.sequences import (
    SeqSLAMResult,
    check_sequence,
    contrast_enhance,
    seqslam,
    sequence_place_scores,
    sequence_scores,
    sequence_similarity,
    trajectory_offsets,
    uniqueness,
)

V = (0.8, 0.9, 1.0, 1.1, 1.2)


# --------------------------------------------------------------------------- the plain-loop reference
# Written from OpenSeqSLAM's doContrastEnhancement.m / doFindMatches.m, transposed to
# (n_queries, n_database), one query, one start, one velocity at a time.


def ref_enhance(d, r=10):
    nq, nd = d.shape
    e = np.zeros((nq, nd))
    for q in range(nq):
        for j in range(nd):
            w = d[q, max(0, j - r // 2):min(nd - 1, j + r // 2) + 1]
            sd = np.std(w, ddof=1)
            flat = sd <= 1e-9 * (1 + abs(np.mean(w)))
            e[q, j] = 0.0 if flat else (d[q, j] - np.mean(w)) / sd
    return e - e.min()


def ref_trajectory(e, q, s, v, ds):
    """Sum of e along the trajectory of velocity v starting at database image s, centred on query q."""
    total = 0.0
    for k in range(ds + 1):
        row = s + math.floor(k * v + 1e-9)
        if row >= e.shape[1]:
            return math.inf, total
        total += e[q - ds // 2 + k, row]
    return total, None


def ref_scores(e, ds=10, velocities=V, values=None):
    """S[q, j] (start j - ds/2), the best velocity index, and the mean of ``values`` along it."""
    nq, nd = e.shape
    h = ds // 2
    scores = np.full((nq, nd), np.inf)
    vel = np.full((nq, nd), -1)
    mean = np.full((nq, nd), -np.inf)
    for q in range(h, nq - h):
        for j in range(h, nd):
            s = j - h
            for i, v in enumerate(velocities):
                total, _ = ref_trajectory(e, q, s, v, ds)
                if total < scores[q, j]:
                    scores[q, j], vel[q, j] = total, i
                    if values is not None:
                        mean[q, j] = np.mean([values[q - h + k, s + math.floor(k * v + 1e-9)] for k in range(ds + 1)])
    return scores, vel, mean


def ref_match(row, w=10):
    """Best index (lowest within 1e-5), its score and the ratio, for one query's scores."""
    best = min(row)
    if math.isinf(best):
        return -1, math.nan, math.nan
    j = next(i for i, x in enumerate(row) if x <= best + 1e-5)
    outside = [x for i, x in enumerate(row) if abs(i - j) > w // 2]
    second = min(outside) if outside else math.inf
    return j, best, 1.0 if second == 0 else best / second


def ref_seqslam(d, ds=10, r=10, w=10, velocities=V):
    scores, vel, _ = ref_scores(ref_enhance(d, r), ds, velocities)
    out = [ref_match(list(row), w) for row in scores]
    return np.array([o[0] for o in out]), np.array([o[1] for o in out]), np.array([o[2] for o in out]), scores, vel


# --------------------------------------------------------------------------- against the reference


def test_contrast_enhancement_equals_the_loop():
    d = np.random.default_rng(0).random((7, 30))
    d[2, 10:25] = 0.3  # a flat stretch: windows with std 0 (to rounding) give 0
    np.testing.assert_allclose(contrast_enhance(d), ref_enhance(d), rtol=0, atol=1e-12)
    far = d + 1e3  # an offset changes nothing but rounding (at 1e3 · eps · window size)
    np.testing.assert_allclose(contrast_enhance(far), contrast_enhance(d), rtol=0, atol=1e-10)
    np.testing.assert_allclose(contrast_enhance(d, 4), ref_enhance(d, 4), rtol=0, atol=1e-12)
    assert contrast_enhance(d).min() == 0.0


def test_trajectory_offsets_are_openseqslam_moves():
    off = trajectory_offsets()
    assert off.tolist() == [
        [0, 0, 1, 2, 3, 4, 4, 5, 6, 7, 8],
        [0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9],
        list(range(11)),
        [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 11],
        [0, 1, 2, 3, 4, 6, 7, 8, 9, 10, 12],
    ]
    # the same as OpenSeqSLAM's integer moves vmin*ds : vmax*ds over ds
    assert (off == (np.arange(11)[None, :] * np.arange(8, 13)[:, None]) // 10).all()


@pytest.mark.parametrize("seed, shape, ds", [(1, (25, 40), 10), (2, (16, 23), 4), (3, (30, 60), 6)])
def test_scores_equal_the_loop_exactly(seed, shape, ds):
    d = np.random.default_rng(seed).random(shape)
    scores, vel = sequence_scores(d, ds=ds)
    ref, ref_vel, _ = ref_scores(contrast_enhance(d), ds)
    np.testing.assert_array_equal(scores, ref)  # the same additions in the same order
    np.testing.assert_array_equal(vel, ref_vel)


@pytest.mark.parametrize("seed", [4, 5])
def test_seqslam_equals_the_loop(seed):
    d = np.random.default_rng(seed).random((30, 45))
    r = seqslam(d)
    match, score, ratio, _, vel = ref_seqslam(d)
    np.testing.assert_array_equal(r.match, match)
    np.testing.assert_allclose(r.score, score, rtol=1e-12)
    np.testing.assert_allclose(r.ratio, ratio, rtol=1e-12)
    rows = np.flatnonzero(match >= 0)
    np.testing.assert_array_equal(r.velocity[rows], np.asarray(V)[vel[rows, match[rows]]])


def test_unusual_velocities_and_blocks(monkeypatch):
    """Duplicate and unsorted velocities, and blocks of a few rows, change nothing."""
    import vpr_explorer.method.sequences as seq

    d = np.random.default_rng(6).random((22, 35))
    vs = (1.2, 0.7, 1.0, 0.7, 1.5)
    ref, ref_vel, _ = ref_scores(contrast_enhance(d), 10, vs)
    monkeypatch.setattr(seq, "_BLOCK_BYTES", 8 * 60 * 14)
    scores, vel = sequence_scores(d, velocities=vs)
    np.testing.assert_array_equal(scores, ref)
    np.testing.assert_array_equal(vel, ref_vel)  # a tie goes to the first velocity listed


def test_sequence_similarity_is_the_mean_along_the_best_trajectory():
    s = np.random.default_rng(7).random((24, 40)).astype(np.float32)
    got = sequence_similarity(s)
    _, _, ref = ref_scores(contrast_enhance(1.0 - s.astype(np.float64)), 10, V, values=s.astype(np.float64))
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)
    places = np.arange(40) // 4
    raw, best = sequence_place_scores(s, places, 10)
    np.testing.assert_allclose(raw, got.reshape(24, 10, 4).max(axis=2), rtol=0, atol=0)
    assert (best[:5] == -1).all() and (best[-5:] == -1).all()
    assert np.isneginf(raw[:5]).all() and np.isneginf(raw[-5:]).all()
    rows = np.arange(5, 19)
    np.testing.assert_array_equal(got[rows[:, None], best[rows]], raw[rows])


def ramp_rows(seed, shape, every=3):
    """Random similarities whose every ``every``-th row is an exact ramp: there E is 0 away from the
    ends (each window's mean is its centre, exactly), so trajectories that differ only on those rows
    tie exactly, while the similarities along them differ."""
    s = np.random.default_rng(seed).random(shape).astype(np.float32)
    s[::every] = ((np.arange(shape[1])[None, :] + 3 * np.arange(0, shape[0], every)[:, None]) / 4096).astype(np.float32)
    return s


@pytest.mark.parametrize("velocities, every", [(V, 2), ((1.2, 0.7, 1.0, 0.7, 1.5), 1)])
def test_exact_ties_go_to_the_first_velocity(velocities, every):
    """On an exact tie of S the first velocity listed wins, for the velocity, the match's velocity and the values
    (unsorted velocities reach the fold out of list order)."""
    s = ramp_rows(11, (30, 60), every)
    e = contrast_enhance(1.0 - s.astype(np.float64))
    ref, ref_vel, ref_mean = ref_scores(e, 10, velocities, values=s.astype(np.float64))
    ties = 0
    for q, j in zip(*np.nonzero(np.isfinite(ref))):
        sums = [ref_trajectory(e, q, j - 5, v, 10)[0] for v in velocities]
        ties += len({v for v, x in zip(velocities, sums) if x == ref[q, j]}) > 1
    assert ties > 50  # the case has many exact ties between different velocities

    scores, vel = sequence_scores(1.0 - s.astype(np.float64), velocities=velocities)
    np.testing.assert_array_equal(scores, ref)
    np.testing.assert_array_equal(vel, ref_vel)
    got = sequence_similarity(s, velocities=velocities)
    np.testing.assert_allclose(got, ref_mean, rtol=0, atol=1e-12)  # a wrong pick is off by ≥ 1/4096/11
    r = seqslam(s, kind="similarity", velocities=velocities)
    m = r.matched
    np.testing.assert_array_equal(r.velocity[m], np.asarray(velocities)[ref_vel[m, r.match[m]]])


@pytest.mark.parametrize("velocities", [V, (1.0, 0.8, 1.1), (1.2, 0.7, 1.0, 0.7, 1.5), (0.9, 0.5, 0.8)])
def test_the_fold_over_velocities_on_whole_number_costs(monkeypatch, velocities):
    """Costs of 0, 1 or 2 make exact ties between any velocities: S, the first velocity attaining it, the values
    along it and the velocity at the match equal the loop's, whatever order the trajectories are folded in."""
    import vpr_explorer.method.sequences as seq

    rng = np.random.default_rng(13)
    e = rng.integers(0, 3, (26, 48)).astype(np.float64)
    x = rng.random((26, 48))
    ref, ref_vel, ref_mean = ref_scores(e, 10, velocities, values=x)
    offsets = trajectory_offsets(10, velocities)
    monkeypatch.setattr(seq, "_BLOCK_BYTES", 8 * 61 * 14)  # a few blocks
    t = seq._trajectories(e, 0.0, 10, offsets, velocity=True, values=x, ratio_window=10)
    np.testing.assert_array_equal(t.scores, ref)
    np.testing.assert_array_equal(t.velocity, ref_vel)
    np.testing.assert_allclose(t.mean, ref_mean, rtol=0, atol=1e-12)
    m = t.match >= 0
    at = seq._velocity_at(e, 0.0, 10, offsets, t.match, t.score)
    np.testing.assert_array_equal(at[m], ref_vel[m, t.match[m]])
    assert (at[~m] == -1).all()
    means = seq._trajectories(e, 0.0, 10, offsets, scores=False, values=x).mean  # the values alone
    np.testing.assert_array_equal(means, t.mean)


def test_blocks_and_threads_change_no_bit(monkeypatch):
    """Blocks of a few rows, on one thread or several, give the same numbers as one block."""
    import vpr_explorer.method.sequences as seq

    s = ramp_rows(12, (40, 70), every=4)
    s[7, 20:40] = 0.25  # a flat stretch in one block only
    d = 1.0 - s.astype(np.float64)

    def run():
        r = seqslam(s, kind="similarity")
        return (r.match, r.score, r.ratio, r.velocity, r.scores, *sequence_scores(d),
                sequence_similarity(s), contrast_enhance(d))

    whole = run()
    for block_bytes, workers in ((8 * 90 * 14, 1), (8 * 90 * 14, 3), (8 * 90 * 11, 2)):
        monkeypatch.setattr(seq, "_BLOCK_BYTES", block_bytes)
        monkeypatch.setattr(seq, "default_workers", lambda: workers)
        for a, b in zip(whole, run()):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)


# --------------------------------------------------------------------------- hand cases


def test_a_diagonal_of_slope_1_1_is_found_exactly():
    rng = np.random.default_rng(8)
    nq, nd, a = 61, 120, 12
    d = rng.uniform(0.5, 1.0, (nq, nd))
    line = a + np.floor(1.1 * np.arange(nq) + 1e-9).astype(int)
    d[np.arange(nq), line] = 0.0
    r = seqslam(d)
    for n in (5, 15, 25, 35, 45, 55):  # 1.1·(n − 5) whole: the trajectory lies on the line
        start = line[n - 5]
        assert r.match[n] == start + 5
        assert r.velocity[n] == 1.1
        assert r.ratio[n] < 0.5
        on_line = sum(contrast_enhance(d)[n - 5 + k, start + int(np.floor(1.1 * k + 1e-9))] for k in range(11))
        assert r.score[n] == pytest.approx(on_line, abs=1e-12)
    matched = r.matched
    # elsewhere the best trajectory follows the line up to the floor's rounding, and its start + 5
    # (what OpenSeqSLAM reports) lies within one image of the line at the query
    assert np.abs(r.match[matched] - line[matched]).max() <= 1


def test_queries_at_either_end_are_not_matched():
    r = seqslam(np.random.default_rng(9).random((30, 40)), ds=6)
    assert (r.match[:3] == -1).all() and (r.match[-3:] == -1).all()
    assert (r.match[3:-3] >= 0).all()
    assert np.isnan(r.ratio[:3]).all() and np.isnan(r.score[-3:]).all() and np.isnan(r.velocity[:3]).all()
    assert not r.accepted(1.0)[:3].any() and r.accepted(1.0)[3:-3].all()
    assert np.isinf(r.scores[:3]).all() and np.isinf(r.scores[:, :3]).all()


def test_similarity_and_difference_give_the_same_matches():
    s = np.random.default_rng(10).random((25, 40))
    a, b, c = seqslam(s, kind="similarity"), seqslam(1 - s), seqslam(2 - 2 * s, kind="difference")
    np.testing.assert_array_equal(a.match, b.match)
    np.testing.assert_array_equal(a.match, c.match)
    np.testing.assert_allclose(a.ratio, c.ratio, rtol=1e-9)


def test_ratio_window_and_boundary():
    inf = np.inf
    scores = np.array([
        [inf, 9.0, 3.0, 3.5, 3.8, 4.0, 8.0],   # W=4: image 4 (2 away) inside, image 5 (3 away) outside -> 3/4
        [inf, 6.0, 4.0, 3.0, 5.0, 4.0, 6.0],   # W=2: window 2..4; second best 4 at image 5 -> 0.75
        [2.0, 2.0, 9.0, 9.0, 9.0, 9.0, 1e9],   # tie: the lower index; its neighbour is inside
        [5.0, 5.000004, 9.0, 9.0, 9.0, 8.0, 9.0],  # within 1e-5: the lower index wins
        [0.0, 9.0, 9.0, 9.0, 0.0, 9.0, 9.0],   # second best 0: ratio 1
        [inf] * 7,                              # no trajectory: no match
    ])
    given = scores.copy()
    given.setflags(write=False)
    uniqueness(given, 4)  # a read-only matrix is read, never written
    np.testing.assert_array_equal(given, scores)
    m4, s4, r4 = uniqueness(scores[:1], 4)
    assert m4[0] == 2 and s4[0] == 3.0 and r4[0] == 0.75
    match, score, ratio = uniqueness(scores[1:], 2)
    assert match.tolist() == [3, 0, 0, 0, -1]
    assert ratio[0] == 0.75
    assert ratio[1] == 2.0 / 9.0
    assert ratio[2] == pytest.approx(5.0 / 8.0)
    assert ratio[3] == 1.0
    assert np.isnan(ratio[4]) and np.isnan(score[4])
    result = SeqSLAMResult(match=match, score=score, ratio=ratio, velocity=np.ones(5), scores=scores[1:])
    assert result.accepted(0.75)[0]                     # exactly at the threshold: accepted
    assert not result.accepted(np.nextafter(0.75, 0))[0]
    assert not result.accepted(1.0)[4]                  # unmatched: never accepted
    with pytest.raises(VPRInputError, match="threshold"):
        result.accepted(float("nan"))


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("kwargs, word", [
    ({"ds": 9}, "ds"), ({"ds": 0}, "ds"), ({"contrast_window": 5}, "contrast_window"),
    ({"ratio_window": 3}, "ratio_window"), ({"velocities": (0.4, 1.0)}, "velocities"),
    ({"velocities": ()}, "velocities"), ({"velocities": (1.0, float("nan"))}, "velocities"),
    ({"kind": "distance"}, "kind"), ({"ds": True}, "ds"),
])
def test_bad_parameters_are_named(kwargs, word):
    with pytest.raises(VPRInputError, match=word):
        seqslam(np.random.default_rng(0).random((30, 40)), **kwargs)


def test_bad_matrices_are_refused():
    d = np.random.default_rng(0).random((30, 40))
    bad = d.copy()
    bad[3, 4] = np.nan
    with pytest.raises(VPRInputError, match="NaN"):
        seqslam(bad)
    with pytest.raises(VPRInputError, match="2-D"):
        seqslam(d[0])
    with pytest.raises(VPRInputError, match="queries"):
        seqslam(d[:10])
    with pytest.raises(VPRInputError, match="database images"):
        seqslam(d[:, :19])
    assert seqslam(d[:, :20]).matched.sum() == 20  # the smallest database allowed
    with pytest.raises(VPRInputError, match="queries"):
        sequence_similarity(d[:10])


# --------------------------------------------------------------------------- the order check


def test_check_sequence_refuses_an_unordered_value(demo):
    from vpr_explorer.data.aligned import database_queries

    one = database_queries(demo, demo.traversals[-1], database=[demo.traversals[0]])
    check_sequence(one)  # one database traversal, queries in frame order
    two = database_queries(demo)
    with pytest.raises(VPRInputError, match=f"{demo.name!r}.*not one ordered route"):
        check_sequence(two)
    with pytest.raises(VPRInputError, match="database-queries"):
        check_sequence(replace(one, layout=Layout.DATABASE_QUERIES, ordered=False))
    with pytest.raises(VPRInputError, match="queries .* 2 traversals"):
        check_sequence(replace(one, query_traversal=np.r_[np.zeros(30, int), np.ones(one.n_queries - 30, int)]))
    with pytest.raises(VPRInputError, match="queries .* not in frame order"):
        check_sequence(replace(one, query_frame=one.query_frame[::-1].copy()))
    with pytest.raises(VPRInputError, match="database .* not in frame order"):
        check_sequence(replace(one, database_frame=np.roll(one.database_frame, 1)))


# --------------------------------------------------------------------------- real data


@pytest.mark.realdata
def test_gardens_point_night_against_day(gardens_point, gp_pixels):
    from vpr_explorer.data.aligned import database_queries, value_rows
    from vpr_explorer.data.groundtruth import GroundTruth
    from vpr_explorer.method.retrieval import similarity

    v = database_queries(gardens_point, "night_right", database=["day_right"])
    check_sequence(v)
    rows = value_rows(v)
    d = gp_pixels if rows is None else gp_pixels[rows]
    sims = similarity(d[v.n_database:], d[:v.n_database])
    r = seqslam(sims, kind="similarity")
    match, score, ratio, _, _ = ref_seqslam(1.0 - sims.astype(np.float64))
    np.testing.assert_array_equal(r.match, match)
    np.testing.assert_allclose(r.ratio, ratio, rtol=1e-9)
    np.testing.assert_allclose(r.score, score, rtol=1e-9)

    n, m = v.n_queries, r.matched
    single = sims.argmax(axis=1)
    recall = {}
    for tolerance in (0, 2):
        right = GroundTruth.from_frames(v.query_frame, v.database_frame, tolerance).dense()
        seq_right = right[np.arange(n), np.maximum(r.match, 0)] & m
        single_right = right[np.arange(n), single]
        recall[tolerance] = seq_right[m].mean(), single_right[m].mean()
        print(f"\nGardensPoint night_right -> day_right, pixels, right within {tolerance} frames: Recall@1 "
              f"SeqSLAM {seq_right[m].mean():.3f} vs single-image {single_right[m].mean():.3f} over the "
              f"{m.sum()} matched queries; over all {n}: {seq_right.mean():.3f} vs {single_right.mean():.3f}")
    assert recall[0][0] > recall[0][1]


def test_sequence_place_scores_refuse_an_image_between_places():
    """A ``-1`` label (an image between places) is refused by name, never written into a place's column."""
    rng = np.random.default_rng(3)
    s = rng.uniform(-1, 1, size=(30, 40))
    with pytest.raises(VPRInputError, match="db_places"):
        sequence_place_scores(s, np.r_[np.full(20, -1), np.arange(20) // 4], 5)
    with pytest.raises(VPRInputError, match="db_places"):
        sequence_place_scores(s, np.arange(40) // 4, 5)  # labels up to 9 for 5 places
