"""Dataset loading: both layouts, real GardensPoint and Nordland, and bad folders."""

import numpy as np
import pytest
from PIL import Image

from vpr_explorer.data.traversals import load_dataset, traversal_roles
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import PlaceSpec, make_places


def _img(path, value=0):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.full((8, 8, 3), value, np.uint8)).save(path)


def test_traversal_folders_natural_order(tmp_path):
    for t in ("b_night", "a_day"):
        for f in (1, 2, 10):
            _img(tmp_path / t / f"img{f}.png")
    ds = load_dataset(tmp_path)
    assert ds.traversals == ("a_day", "b_night")
    assert [p.name for p in ds.paths[0]] == ["img1.png", "img2.png", "img10.png"]
    assert ds.image_index("b_night", 2) == 5
    assert ds.image_traversal.tolist() == [0, 0, 0, 1, 1, 1]
    assert ds.image_frame.tolist() == [0, 1, 2, 0, 1, 2]


def test_prepared_place_names(tmp_path):
    for place in (3, 7, 9):
        for cond in (0, 1):
            for g in range(2):
                _img(tmp_path / f"Place{place:04d}_Cond{cond:02d}_G{g:02d}.png")
    ds = load_dataset(tmp_path)
    assert ds.traversals == ("Cond00", "Cond01")
    assert ds.prepared_places.tolist() == [0, 0, 1, 1, 2, 2]
    places = make_places(ds, None)
    assert places.n_places == 3 and places.spec is None
    assert places.images_per_place.tolist() == [4, 4, 4]


def test_prepared_names_missing_frame(tmp_path):
    for cond in (0, 1):
        for place in range(2):
            _img(tmp_path / f"Place{place:04d}_Cond{cond:02d}_G00.png")
    (tmp_path / "Place0001_Cond01_G00.png").unlink()
    with pytest.raises(VPRInputError, match="condition 01 does not have the same places"):
        load_dataset(tmp_path)


def test_missing_folder(tmp_path):
    with pytest.raises(VPRInputError, match="does not exist"):
        load_dataset(tmp_path / "nope")


def test_empty_folder(tmp_path):
    with pytest.raises(VPRInputError, match="no traversal found"):
        load_dataset(tmp_path)
    (tmp_path / "day").mkdir()
    with pytest.raises(VPRInputError, match="no traversal found"):
        load_dataset(tmp_path)


def test_named_traversal_without_images(tmp_path):
    _img(tmp_path / "day" / "0.png")
    (tmp_path / "night").mkdir()
    with pytest.raises(VPRInputError, match="night: the traversal folder holds no images"):
        load_dataset(tmp_path, traversals=["day", "night"])
    with pytest.raises(VPRInputError, match="no traversal folder 'dusk'"):
        load_dataset(tmp_path, traversals=["dusk"])


def test_different_lengths(tmp_path):
    for f in range(3):
        _img(tmp_path / "day" / f"{f}.png")
    for f in range(2):
        _img(tmp_path / "night" / f"{f}.png")
    with pytest.raises(VPRInputError, match=r"different numbers of frames \(day: 3, night: 2\)"):
        load_dataset(tmp_path)


def test_empty_image_file_is_named(tmp_path):
    _img(tmp_path / "day" / "0.png")
    (tmp_path / "day" / "1.png").write_bytes(b"")
    with pytest.raises(VPRInputError, match=r"1\.png: the image file is empty"):
        load_dataset(tmp_path)


def test_bad_positions_file(tmp_path):
    for f in range(3):
        _img(tmp_path / "day" / f"{f}.png")
    (tmp_path / "positions.csv").write_text("x,y\n0,0\n1,1\n")
    with pytest.raises(VPRInputError, match="2 positions for 3 frames"):
        load_dataset(tmp_path)
    (tmp_path / "positions.csv").write_text("x,y\n0,0\n1,a\n2,2\n")
    with pytest.raises(VPRInputError, match="cannot read route positions"):
        load_dataset(tmp_path)


@pytest.mark.realdata
def test_gardens_point_mini(gardens_point):
    assert gardens_point.traversals == ("day_left", "day_right", "night_right")
    assert gardens_point.n_frames == 200 and gardens_point.n_images == 600
    assert gardens_point.positions.shape == (200, 2)
    places = make_places(gardens_point, PlaceSpec(3, 10))
    assert places.n_places == 20
    assert places.images_per_place.tolist() == [9] * 20
    assert make_places(gardens_point, PlaceSpec(3, 10, "skip")).n_places == 16


@pytest.mark.realdata
def test_nordland_layout(data_root):
    ds = load_dataset(data_root / "Nordland_64x32")
    assert ds.traversals == ("summer", "winter")
    assert ds.n_frames == 3576
    assert ds.paths[0][0].name == ds.paths[1][0].name == "images-00010.png"
    assert make_places(ds, PlaceSpec(3, 3)).n_places == 1192


@pytest.mark.parametrize("names, database, query, by_name", [
    (("query", "ref"), ("ref",), "query", True),  # folder order alone would query with ref
    (("Reference", "Live"), ("Reference",), "Live", True),
    (("db", "q", "x"), ("db",), "q", True),
    (("map", "run1", "run2"), ("map",), "run2", True),
    (("database", "day", "night"), ("database",), "night", True),
    (("queries", "summer", "winter"), ("summer",), "queries", True),
    (("day_left", "day_right", "night_right"), ("day_left",), "night_right", False),
    (("summer", "winter"), ("summer",), "winter", False),
    (("query", "queries"), ("query",), "queries", False),  # two query names: no telling, folder order
])
def test_traversal_roles_from_names_else_folder_order(names, database, query, by_name):
    roles = traversal_roles(names)
    assert tuple(names[t] for t in roles.database) == database
    assert names[roles.query] == query and roles.by_name is by_name


def test_a_dataset_with_query_and_ref_folders(tmp_path):
    for name in ("query", "ref"):
        (tmp_path / name).mkdir()
        for i in range(3):
            _img(tmp_path / name / f"{i}.png")
    ds = load_dataset(tmp_path)
    assert ds.traversals == ("query", "ref")
    roles = ds.default_roles()
    assert ds.traversals[roles.query] == "query" and [ds.traversals[t] for t in roles.database] == ["ref"]
    assert roles.describe(ds.traversals) == "query against ref (recognised from the traversal names)"
