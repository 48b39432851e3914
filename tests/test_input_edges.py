"""Dataset input at its edges: positions out of range, lat/lon across a UTM zone boundary, a
missing manifest, ``--radius`` where it is bad or does not apply, symbolic links to nothing,
entries that cannot be read, CSVs with a byte-order mark, manifest rows that are folders, and
the radius boundary and ``@east@north@…`` parsing checked by value.

Datasets are small folders of real PNG files written here; refusals run ``main`` in this
process, and a few run ``python -m vpr_explorer.cli`` in a subprocess, as a user would.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from cli_run import assert_one_error_line, refused, run
from images import write_random_png
from vpr_explorer.errors import VPRInputError
from vpr_explorer.data.groundtruth import GroundTruth
from vpr_explorer.data.layouts import Layout, load_database_queries, load_manifest
from vpr_explorer.pipeline import open_dataset

ZONE = "55@H"
BOUND = 1e9  # groundtruth.MAX_METRES: the largest |x|, |y| of a position and the largest radius


def png(path: Path, seed: int = 0) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_random_png(path, seed, (8, 6))


def database_queries(root: Path, database: list[tuple[str, str]], queries: list[tuple[str, str]]) -> Path:
    """``database/`` and ``queries/`` with ``@east@north@55@H@…`` names (east, north as written)."""
    for side, positions in (("database", database), ("queries", queries)):
        for i, (east, north) in enumerate(positions):
            png(root / side / f"@{east}@{north}@{ZONE}@{i:04d}@.png", i)
    return root


def manifest(root: Path, header: str, rows: list[str], *, bom: bool = False, name: str = "manifest.csv") -> Path:
    """A manifest CSV beside images ``a.png``, ``b.png``, ``c.png``, ``d.png`` (written here)."""
    for i, n in enumerate("abcd"):
        png(root / f"{n}.png", i)
    path = root / name
    path.write_text(("\ufeff" if bom else "") + "\n".join([header, *rows]) + "\n", encoding="utf-8")
    return path


def traversal_positions(root: Path, positions: dict[str, list[str]], header: str = "x,y", bom: bool = False) -> Path:
    """Traversal folders, each with one PNG per row of its ``positions.csv``."""
    for t, (name, rows) in enumerate(positions.items()):
        for f in range(len(rows)):
            png(root / name / f"{f:03d}.png", 100 * t + f)
        (root / name / "positions.csv").write_text(("\ufeff" if bom else "") + "\n".join([header, *rows]) + "\n",
                                                   encoding="utf-8")
    return root


def vpr_bench(root: Path) -> Path:
    """VPR-Bench: ``ref/``, ``query/`` and a ground truth of 2-D integer rows (query i: reference i)."""
    for side in ("ref", "query"):
        for i in range(3):
            png(root / side / f"{i}.png", i)
    np.save(root / "ground_truth_new.npy", np.array([[0, 0], [1, 1], [2, 2]], dtype=np.int64))
    return root


def aligned(root: Path) -> Path:
    for t in ("day", "night"):
        for f in range(4):
            png(root / t / f"{f}.png", f)
    return root


# --------------------------------------------------------------------------- positions out of range


@pytest.mark.parametrize("value", ["1e300", "1000000001", "-1e10"])
def test_a_position_out_of_range_in_a_file_name_is_refused_by_name(tmp_path, value):
    root = database_queries(tmp_path / "dq", [(value, "6960000"), ("500000", "6960000")], [("500000", "6960000")])
    with pytest.raises(VPRInputError, match=rf"database/@{value}@6960000@55@H@0000@\.png: in the file name, the "
                                            r"position \(.*\) is out of range: positions are metres"):
        open_dataset(root)


def test_a_manifest_x_of_1e300_is_refused_naming_the_line(tmp_path):
    path = manifest(tmp_path / "m", "path,role,x,y", ["a.png,database,0,0", "b.png,database,1e300,0",
                                                      "c.png,query,0,0"])
    with pytest.raises(VPRInputError, match=r"manifest\.csv: line 3: the position \(1e\+300, 0\) is out of range"):
        load_manifest(path)


def test_a_positions_csv_of_1e300_is_refused_naming_the_line(tmp_path):
    root = traversal_positions(tmp_path / "tp", {"ref": ["0,0", "10,0"], "query": ["0,0", "0,1e300"]})
    with pytest.raises(VPRInputError, match=r"query/positions\.csv: line 3: the position \(0, 1e\+300\) is out of "
                                            "range"):
        open_dataset(root, "traversal-positions")


def test_positions_out_of_range_through_the_command_line(tmp_path, capsys):
    root = database_queries(tmp_path / "dq", [("1e300", "6960000")], [("500000", "6960000")])
    r = run("list", "--dataset", str(root))
    assert_one_error_line(r, "@1e300@6960000@55@H@0000@.png: in the file name", "out of range")
    m = manifest(tmp_path / "m", "path,role,x,y", ["a.png,database,0,0", "c.png,query,-1e300,5"])
    r = run("evaluate", "--dataset", str(m), "--descriptor", "pixels", "--cache-dir", str(tmp_path / "cache"))
    assert_one_error_line(r, "manifest.csv: line 3: the position (-1e+300, 5) is out of range")
    tp = traversal_positions(tmp_path / "tp", {"ref": ["1e300,0"], "query": ["0,0"]})
    assert_one_error_line(refused(capsys, "list", "--dataset", str(tp)), "ref/positions.csv: line 2", "out of range")


def test_positions_up_to_the_bound_are_measured_and_beyond_it_refused():
    far = GroundTruth.from_positions(np.array([[BOUND, -BOUND]]),
                                     np.array([[-BOUND, BOUND], [BOUND, -BOUND + 25]]), 25)
    assert far.positives(0).tolist() == [1]
    for bad in (np.nextafter(BOUND, np.inf), -np.inf, np.nan):
        with pytest.raises(VPRInputError, match="positions: database image 1: the position"):
            GroundTruth.from_positions(np.zeros((1, 2)), np.array([[0.0, 0.0], [0.0, bad]]))
    with pytest.raises(VPRInputError, match="radius=1e\\+300: must be at most 1,000,000,000 metres"):
        GroundTruth.from_positions(np.zeros((1, 2)), np.zeros((1, 2)), radius=1e300)


# --------------------------------------------------------------------------- lat/lon across a UTM zone boundary


def test_lat_lon_on_both_sides_of_a_zone_boundary_are_measured_in_one_zone(tmp_path):
    # nine spots 1 mm of longitude apart (about 72 m at 50° N) across 6° E, the boundary of zones 31 and 32:
    # four west of it (zone 31), five on or east of it (zone 32); the reference traversal runs west to east
    # (its first row in zone 31), the query traversal east to west (its first row in zone 32)
    spots = [f"50.0,{5.996 + 0.001 * k:.3f}" for k in range(9)]
    root = traversal_positions(tmp_path / "tp", {"ref": spots, "query": spots[::-1]}, header="lat,lon")
    ds = open_dataset(root, radius=25)
    assert ds.layout is Layout.TRAVERSAL_POSITIONS and ds.n_database == ds.n_queries == 9
    for q in range(9):
        spot = 8 - q
        assert ds.ground_truth.positives(q).tolist() == [spot]
        assert np.hypot(*(ds.query_xy[q] - ds.database_xy[spot])) < 1e-6
    assert any("UTM zone 32 (north)" in note and "8 of 18 positions lie outside it (zone 31)" in note
               for note in ds.notes), ds.notes


def test_lat_lon_in_one_zone_say_which_zone(tmp_path):
    spots = [f"-27.47,{153.02 + 0.001 * k:.3f}" for k in range(3)]
    ds = open_dataset(traversal_positions(tmp_path / "tp", {"ref": spots, "query": spots}, header="lat,lon"))
    assert ds.ground_truth.positives(0).tolist() == [0]
    zone_notes = [n for n in ds.notes if "UTM zone" in n]
    assert zone_notes == ["lat/lon converted to UTM zone 56 (south), the zone of most positions, for every "
                          "traversal"]


def test_positions_in_metres_beside_lat_lon_are_refused(tmp_path):
    root = tmp_path / "tp"
    traversal_positions(root, {"ref": ["0,0", "10,0"]})
    traversal_positions(root, {"query": ["50.0,6.0", "50.0,6.001"]}, header="lat,lon")
    with pytest.raises(VPRInputError, match=r"ref/positions\.csv: gives x,y \(metres\), but .*query/positions"
                                            r"\.csv gives lat,lon \(degrees\)"):
        open_dataset(root, "traversal-positions")


# --------------------------------------------------------------------------- a manifest layout without a manifest


def test_layout_manifest_on_a_folder_without_one_is_named(tmp_path, capsys):
    aligned(tmp_path / "route")
    with pytest.raises(VPRInputError, match=r"route: --layout manifest needs a manifest\.csv in the folder"):
        open_dataset(tmp_path / "route", "manifest")
    assert_one_error_line(refused(capsys, "list", "--dataset", str(tmp_path / "route"), "--layout", "manifest"),
                          "needs a manifest.csv")


# --------------------------------------------------------------------------- --radius


@pytest.mark.parametrize("value, fragment", [
    ("-5", "radius=-5.0: must be a positive distance in metres"),
    ("0", "radius=0.0: must be a positive distance in metres"),
    ("nan", "radius=nan: must be a positive distance in metres"),
    ("inf", "radius=inf: must be a positive distance in metres"),
    ("1e300", "radius=1e+300: must be at most 1,000,000,000 metres"),
])
@pytest.mark.parametrize("layout", ["vpr-bench", "manifest-places", "manifest-positions", "traversals"])
def test_a_bad_radius_is_refused_whatever_the_layout(tmp_path, capsys, layout, value, fragment):
    source = {
        "vpr-bench": lambda: vpr_bench(tmp_path / "vb"),
        "manifest-places": lambda: manifest(tmp_path / "m", "path,role,place", ["a.png,database,1", "b.png,query,1"]),
        "manifest-positions": lambda: manifest(tmp_path / "m", "path,role,x,y", ["a.png,database,0,0",
                                                                                 "b.png,query,0,0"]),
        "traversals": lambda: aligned(tmp_path / "route"),
    }[layout]()
    for command in ("list", "evaluate"):
        extra = [] if command == "list" else ["--descriptor", "pixels", "--cache-dir", str(tmp_path / "cache")]
        assert_one_error_line(refused(capsys, command, "--dataset", str(source), "--radius", value, *extra), fragment)


@pytest.mark.parametrize("command", ["sweep", "record"])
@pytest.mark.parametrize("value, fragment", [
    ("-5", "radius=-5.0: must be a positive distance"),
    ("nan", "radius=nan: must be a positive distance"),
    ("30", "--radius applies to database/queries layouts"),
])
def test_sweep_and_record_refuse_radius(tmp_path, capsys, command, value, fragment):
    extra = (["--database", "day", "--queries", "night", "--out", str(tmp_path / "run.rrd")]
             if command == "record" else ["--groups", "2", "--steps", "4"])
    r = refused(capsys, command, "--dataset", "demo", "--descriptor", "pixels", "--cache-dir", str(tmp_path / "c"),
                "--radius", value, *extra)
    assert_one_error_line(r, fragment)
    assert not (tmp_path / "run.rrd").exists()


@pytest.mark.parametrize("layout", ["vpr-bench", "database-queries", "manifest", "prepared"])
def test_record_refuses_a_layout_the_dataset_is_not_in(tmp_path, capsys, layout):
    r = refused(capsys, "record", "--dataset", "demo", "--descriptor", "pixels", "--cache-dir", str(tmp_path / "c"),
                "--layout", layout, "--database", "day", "--queries", "night", "--out", str(tmp_path / "run.rrd"))
    assert_one_error_line(r, f"--layout {layout}: the demo route is traversal folders")
    assert not (tmp_path / "run.rrd").exists()


@pytest.mark.parametrize("layout, says", [
    ("vpr-bench", "is vpr-bench, which takes its ground truth from ground_truth_new.npy: drop --radius"),
    ("manifest-places", "is manifest, which takes its ground truth from its place column (the same place id)"),
])
def test_a_radius_for_a_layout_that_lists_its_ground_truth_is_refused_by_name(tmp_path, capsys, layout, says):
    source = (vpr_bench(tmp_path / "vb") if layout == "vpr-bench" else
              manifest(tmp_path / "m", "path,role,x,y,place", ["a.png,database,0,0,1", "b.png,query,0,0,1"]))
    for command in ("list", "evaluate"):
        extra = [] if command == "list" else ["--descriptor", "pixels", "--cache-dir", str(tmp_path / "cache")]
        r = refused(capsys, command, "--dataset", str(source), "--radius", "30", *extra)
        assert_one_error_line(r, "--radius applies to position-tagged layouts", says)
    # without --radius they open, and a position-tagged layout takes it
    assert refused(capsys, "list", "--dataset", str(source)).returncode == 0
    m = manifest(tmp_path / "xy", "path,role,x,y", ["a.png,database,0,0", "b.png,query,29,0"])
    r = refused(capsys, "list", "--dataset", str(m), "--radius", "30")
    assert r.returncode == 0 and r.stdout.split() == ["a.png", "b.png"]


def test_the_app_warns_of_a_radius_it_cannot_use():
    from vpr_explorer.app.ui.state import View

    for text, why in (("-5", "must be a positive distance in metres"), ("nan", "must be a positive distance"),
                      ("1e300", "must be at most 1,000,000,000 metres")):
        v, ignored = View.from_params({"radius": text})
        assert v.radius is None
        assert len(ignored) == 1 and ignored[0].startswith(f"radius={text!r}: ") and why in ignored[0], ignored


# --------------------------------------------------------------------------- symbolic links to nothing


def test_a_dangling_image_link_in_traversal_folders_is_refused_by_name(tmp_path, capsys):
    root = aligned(tmp_path / "route")
    (root / "night" / "4.png").symlink_to(tmp_path / "gone.png")
    (root / "day" / "4.png").symlink_to(tmp_path / "there.png")
    png(tmp_path / "there.png")
    with pytest.raises(VPRInputError, match=rf"night/4\.png: a symbolic link to {tmp_path}/gone\.png, which does "
                                            "not exist; remove or fix it"):
        open_dataset(root)
    assert_one_error_line(refused(capsys, "list", "--dataset", str(root)), "night/4.png: a symbolic link to")


def test_a_dangling_link_or_a_loop_in_a_database_folder_is_refused_by_name(tmp_path):
    root = database_queries(tmp_path / "dq", [("500000", "6960000")], [("500000", "6960000")])
    sub = root / "database" / "more"
    sub.mkdir()
    link = sub / "@500000@6960000@55@H@x@.png"
    link.symlink_to("nowhere.png")
    with pytest.raises(VPRInputError, match=r"more/@500000@6960000@55@H@x@\.png: a symbolic link to nowhere\.png, "
                                            "which does not exist"):
        open_dataset(root)
    link.unlink()
    (sub / "a.jpg").symlink_to("b.jpg")
    (sub / "b.jpg").symlink_to("a.jpg")
    with pytest.raises(VPRInputError, match=r"more/[ab]\.jpg: a symbolic link to [ab]\.jpg in a loop of links"):
        open_dataset(root)


def test_a_manifest_row_that_is_a_folder_or_a_dangling_link_says_so(tmp_path):
    folder = tmp_path / "elsewhere"
    folder.mkdir()
    path = manifest(tmp_path / "m", "path,role,place", ["a.png,database,1", f"{folder},query,1"])
    with pytest.raises(VPRInputError, match=rf"manifest\.csv: line 3: {folder} is a folder, not an image file"):
        load_manifest(path)
    (tmp_path / "m" / "link.png").symlink_to(tmp_path / "gone.png")
    path = manifest(tmp_path / "m", "path,role,place", ["a.png,database,1", "link.png,query,1"])
    with pytest.raises(VPRInputError, match=r"line 3: .*link\.png: a symbolic link to .*gone\.png, which does not "
                                            "exist"):
        load_manifest(path)
    # an absolute path to an image is used as given
    path = manifest(tmp_path / "m", "path,role,place", ["a.png,database,1", f"{tmp_path / 'm' / 'b.png'},query,1"])
    assert load_manifest(path).query_paths == (tmp_path / "m" / "b.png",)


# --------------------------------------------------------------------------- entries that cannot be read


def unreadable_link(path: Path) -> Path:
    """A symbolic link whose target's name is too long to look up: ``stat`` fails (ENAMETOOLONG), even for root."""
    path.symlink_to("/" + "x" * 300)
    with pytest.raises(OSError):
        os.stat(path)
    return path


@pytest.mark.parametrize("where", ["route/day/9.png", "route/extra", "dq/queries/sub/9.png"])
def test_an_entry_that_cannot_be_read_is_refused_by_name(tmp_path, capsys, where):
    aligned(tmp_path / "route")
    database_queries(tmp_path / "dq", [("500000", "6960000")], [("500000", "6960000")])
    (tmp_path / where).parent.mkdir(parents=True, exist_ok=True)
    unreadable_link(tmp_path / where)
    root = tmp_path / where.split("/")[0]
    with pytest.raises(VPRInputError, match=rf"{where}: cannot be read \(File name too long\)"):
        open_dataset(root)
    assert_one_error_line(refused(capsys, "list", "--dataset", str(root)), f"{where}: cannot be read")


def test_list_of_a_system_folder_is_one_line_not_a_traceback():
    r = run("list", "--dataset", "/proc")
    assert_one_error_line(r)


# --------------------------------------------------------------------------- a byte-order mark in a CSV header


def test_a_byte_order_mark_before_a_csv_header_is_read(tmp_path):
    m = load_manifest(manifest(tmp_path / "m", "path,role,x,y", ["a.png,database,0,0", "b.png,query,3,4"], bom=True))
    assert m.query_xy.tolist() == [[3.0, 4.0]] and m.ground_truth.positives(0).tolist() == [0]
    tp = open_dataset(traversal_positions(tmp_path / "tp", {"ref": ["0,0", "100,0"], "query": ["100,0"]}, bom=True))
    assert tp.ground_truth.positives(0).tolist() == [1]
    spots = ["50.0,6.001"]
    ll = open_dataset(traversal_positions(tmp_path / "ll", {"ref": spots, "query": spots}, header="lat,lon", bom=True))
    assert ll.ground_truth.positives(0).tolist() == [0]


def test_a_manifest_that_is_not_utf8_is_named(tmp_path):
    path = manifest(tmp_path / "m", "path,role,place", ["a.png,database,1", "b.png,query,1"])
    path.write_bytes(b"path,role,place\n\xff\xfea.png,database,1\n")
    with pytest.raises(VPRInputError, match=r"manifest\.csv: not UTF-8 text"):
        load_manifest(path)


# --------------------------------------------------------------------------- the radius boundary, names by value


def test_a_database_image_exactly_at_the_radius_is_a_positive():
    beyond = np.nextafter(25.0, np.inf)
    db = np.array([[25.0, 0.0], [15.0, 20.0], [beyond, 0.0], [0.0, -beyond], [-20.0, -15.0], [0.0, -25.0]])
    gt = GroundTruth.from_positions(np.zeros((1, 2)), db, radius=25.0)
    assert gt.positives(0).tolist() == [0, 1, 4, 5]
    # the same far from the origin, as UTM coordinates are: (15, 20) is exactly 25 m
    east, north = 500_000.0, 6_960_000.0
    far = np.array([[east + 25, north], [east + 15, north + 20], [np.nextafter(east + 25, np.inf), north]])
    assert GroundTruth.from_positions(np.array([[east, north]]), far, 25.0).positives(0).tolist() == [0, 1]
    soft = GroundTruth.from_positions(np.zeros((1, 2)), db, radius=10.0, soft_radius=25.0)
    assert soft.positives(0).tolist() == [] and soft.soft_positives(0).tolist() == [0, 1, 4, 5]


def test_file_names_give_east_then_north_by_value(tmp_path):
    root = database_queries(tmp_path / "dq", [("500123.5", "5400321.25"), ("500100", "5400300.75")],
                            [("500123.5", "5400345.25")])
    ds = load_database_queries(root)  # listed in natural order of the names: @500100@… before @500123.5@…
    assert ds.database_xy.tolist() == [[500100.0, 5400300.75], [500123.5, 5400321.25]]
    assert ds.query_xy.tolist() == [[500123.5, 5400345.25]]
    assert ds.ground_truth.positives(0).tolist() == [1]  # 24 m north of @500123.5@…; @500100@… is 50 m away
