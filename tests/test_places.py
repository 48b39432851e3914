"""Group-and-step (DESIGN.md §1): both readings, edge cases, bad parameters."""

import numpy as np
import pytest

from vpr_explorer.data.traversals import Dataset
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import PlaceSpec, Reading, frame_places, make_places


def _fake_dataset(tmp_path, n_frames, n_trav=2):
    paths = tuple(tuple(tmp_path / f"t{t}_{f}.png" for f in range(n_frames)) for t in range(n_trav))
    return Dataset(name="x", root=tmp_path, traversals=tuple(f"t{t}" for t in range(n_trav)), paths=paths)


def test_stride_reading_gardens_point_mini():
    fp = frame_places(200, PlaceSpec(3, 10))
    assert fp.max() + 1 == 20
    assert list(np.flatnonzero(fp == 0)) == [0, 1, 2]
    assert list(np.flatnonzero(fp == 1)) == [10, 11, 12]
    assert list(np.flatnonzero(fp == 19)) == [190, 191, 192]
    assert (fp >= 0).sum() == 60


def test_skip_reading_gives_sixteen_places():
    fp = frame_places(200, PlaceSpec(3, 10, Reading.SKIP))
    assert fp.max() + 1 == 16  # 200 // 13 = 15 full periods, plus frames 195..197
    assert list(np.flatnonzero(fp == 1)) == [13, 14, 15]
    assert list(np.flatnonzero(fp == 15)) == [195, 196, 197]


def test_contiguous_places_nordland_counts():
    # Nordland's 27,592 frames: g2s2 -> 13,796 places, g3s3 -> 9,197 (DESIGN.md §1)
    assert frame_places(27_592, PlaceSpec(2, 2)).max() + 1 == 13_796
    assert frame_places(27_592, PlaceSpec(3, 3)).max() + 1 == 9_197


def test_trailing_incomplete_place_is_dropped():
    fp = frame_places(11, PlaceSpec(3, 5))  # places at 0, 5; a place at 10 would need 10..12
    assert fp.tolist() == [0, 0, 0, -1, -1, 1, 1, 1, -1, -1, -1]


@pytest.mark.parametrize(
    "group, step, reading, fragment",
    [(0, 3, "stride", "group=0"), (3, 0, "skip", "step=0"), (3, 2, "stride", "step=2 < group=3"),
     (2.5, 3, "stride", "group=2.5"), (True, 3, "stride", "group=True")],
)
def test_bad_parameters_name_the_parameter(group, step, reading, fragment):
    with pytest.raises(VPRInputError, match=fragment.replace("(", r"\(")):
        PlaceSpec(group, step, reading)


def test_skip_reading_allows_step_below_group():
    assert PlaceSpec(3, 1, "skip").period == 4


def test_fewer_than_two_places_is_an_error(tmp_path):
    ds = _fake_dataset(tmp_path, 12)
    with pytest.raises(VPRInputError, match="at least 2 places"):
        make_places(ds, PlaceSpec(10, 10))
    assert make_places(ds, PlaceSpec(3, 6)).n_places == 2


def test_images_take_their_frames_place(tmp_path):
    ds = _fake_dataset(tmp_path, 20, n_trav=3)
    pl = make_places(ds, PlaceSpec(2, 5))
    assert pl.n_places == 4
    assert pl.image_place.shape == (60,)
    assert np.array_equal(pl.image_place[20:40], pl.frame_place)
    assert pl.images_per_place.tolist() == [6, 6, 6, 6]
    assert pl.describe().startswith("4 places × 6 images")


@pytest.mark.parametrize("group, step, reading, fragment", [
    (99999999999999999999, 10, "stride", "group=99999999999999999999: at most 10,000,000 frames"),
    (3, 99999999999999999999, "stride", "step=99999999999999999999: at most 10,000,000 frames"),
    (99999999999999999999, 1, "skip", "group=99999999999999999999: at most 10,000,000 frames"),
    (3, 10, "diagonal", "reading='diagonal': choose stride or skip"),
])
def test_out_of_range_parameters_name_the_limit(group, step, reading, fragment):
    with pytest.raises(VPRInputError, match=fragment):
        PlaceSpec(group, step, reading)


def test_the_largest_allowed_group_still_labels_frames():
    assert frame_places(10, PlaceSpec(10_000_000, 10_000_000)).tolist() == [-1] * 10


def test_describe_counts_only_the_given_images(tmp_path):
    ds = _fake_dataset(tmp_path, 20, n_trav=3)
    pl = make_places(ds, PlaceSpec(2, 5))
    first = np.flatnonzero(ds.image_traversal == 0)
    assert pl.describe(images=first, what="database images").startswith("4 places × 2 database images")
