"""Ground truth as a sparse relation: hand cases and a brute-force reference."""

import numpy as np
import pytest

from vpr_explorer.errors import VPRInputError
from vpr_explorer.data.groundtruth import GroundTruth


def test_from_frames_hand_case():
    gt = GroundTruth.from_frames(np.array([0, 5, 9]), np.array([0, 1, 2, 3, 4, 5, 6, 7]), tolerance=1)
    assert [gt.positives(q).tolist() for q in range(3)] == [[0, 1], [4, 5, 6], []]
    assert gt.known.tolist() == [True, True, False] and gt.n_unknown == 1
    assert gt.description == "within ±1 frames"
    exact = GroundTruth.from_frames(np.array([3]), np.array([3, 3, 4]), tolerance=0)
    assert exact.positives(0).tolist() == [0, 1]


def test_from_positions_equals_brute_force():
    rng = np.random.default_rng(0)
    q, db = rng.uniform(0, 200, (50, 2)), rng.uniform(0, 200, (300, 2))
    gt = GroundTruth.from_positions(q, db, radius=25)
    dist = np.linalg.norm(q[:, None] - db[None], axis=2)
    np.testing.assert_array_equal(gt.dense(), dist <= 25)
    assert gt.description == "within 25 m"
    soft = GroundTruth.from_positions(q, db, radius=10, soft_radius=25)
    assert all(set(soft.positives(i)) <= set(soft.soft_positives(i)) for i in range(50))


def test_places_of_the_positives():
    gt = GroundTruth.from_lists([[0, 3], [], [2]], 4, "given")
    places = gt.places(np.array([1, -1, 0, 1]), 2)
    assert places.tolist() == [[False, True], [False, False], [True, False]]
    assert gt.places(np.array([1, -1, 0, 1]), 2, queries=np.array([2])).tolist() == [[True, False]]


def test_bad_relations_are_named():
    with pytest.raises(VPRInputError, match="query 1 lists database image 7, outside 0..3"):
        GroundTruth.from_lists([[0], [7]], 4, "given")
    with pytest.raises(VPRInputError, match="radius"):
        GroundTruth.from_positions(np.zeros((1, 2)), np.zeros((1, 2)), radius=-1)
    with pytest.raises(VPRInputError, match="finite"):
        GroundTruth.from_positions(np.array([[np.nan, 0]]), np.zeros((1, 2)))
    assert GroundTruth.from_lists([[2, 0, 2]], 3, "given").positives(0).tolist() == [0, 2]


@pytest.mark.parametrize("tolerance", [0, 1, 2, 5])
def test_the_frame_rule_of_aligned_traversals_is_this_relation(tolerance):
    from vpr_explorer.protocols.evaluation import query_truth
    from vpr_explorer.method.places import PlaceSpec, frame_places

    frame_place = frame_places(60, PlaceSpec(3, 7))
    queries = np.arange(60)
    gt = GroundTruth.from_frames(queries, np.arange(60), tolerance)
    np.testing.assert_array_equal(gt.places(frame_place, int(frame_place.max()) + 1),
                                  query_truth(queries, frame_place, tolerance))
