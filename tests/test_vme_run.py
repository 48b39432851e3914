"""A VPR-methods-evaluation run folder read as descriptors (``descriptors.vme_run``), against VME's own definitions.

VME's definitions, as its public code states them (gmberton/VPR-methods-evaluation,
``test_dataset.read_images_paths`` and ``main.py``), re-written here as plain loops: a
folder's images are the lines of ``<folder>_images_paths.txt`` (paths relative to the
folder) or else the sorted recursive glob of ``.jpg``/``.jpeg``/``.png`` files; a database
image is a positive of a query within 25 m (sklearn ``radius_neighbors``: distance ≤
radius), positions read from the path split on ``@``; predictions are the database images
by increasing L2 distance (faiss ``IndexFlatL2``); Recall@N counts a query when one of its
first N predictions is a positive, over every query. Runs are written in that order by the
tests, from descriptors whose image is known, and read back through the explorer.
"""

from __future__ import annotations

import json
import os
import pickle
import zlib
from glob import glob
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from streamlit.testing.v1 import AppTest

# the autouse fixtures of test_app (fresh caches, navigation mode) apply here too
from test_app import assert_clean, fresh_caches, navigation_mode  # noqa: F401
from cli_run import assert_one_error_line, refused, run
from vpr_explorer.app import DATA_ROOT_ENV, ENTRY
from vpr_explorer.data.example_layouts import utm_name
from vpr_explorer.descriptors.vme_run import DATABASE_FILE, QUERIES_FILE, VMERunDescriptors, load_vme_run, run_stamp
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import PlaceSpec
from vpr_explorer.pipeline import dataset_descriptors, evaluate_retrieval, imported_descriptors, open_dataset

TIMEOUT = 120
AUTOUSE = (fresh_caches, navigation_mode)  # test_app's autouse fixtures, imported to apply here
DIM = 16
RUN = "2024-05-01_12-30-00"  # VME's log folder: logs/<log_dir>/<start time>


# --------------------------------------------------------------------------- VME's definitions, as plain loops


def vme_images(folder: Path) -> list[str]:
    """``read_images_paths(folder)``: the ``_images_paths.txt`` lines, else the sorted glob of images."""
    listed = f"{folder}_images_paths.txt"
    if os.path.exists(listed):
        with open(listed) as fh:
            return [f"{folder}/{line}" for line in fh.read().splitlines()]
    paths = sorted(glob(f"{folder}/**/*", recursive=True))
    return [p for p in paths if os.path.isfile(p) and os.path.splitext(p)[1].lower() in (".jpg", ".jpeg", ".png")]


def vme_utm(paths: list[str]) -> list[tuple[float, float]]:
    return [(float(p.split("@")[1]), float(p.split("@")[2])) for p in paths]


def vme_positives(db_utm, q_utm, radius: float = 25.0) -> list[set[int]]:
    """Database images within ``radius`` metres of each query, distance ≤ radius counting."""
    return [{j for j, (e, n) in enumerate(db_utm) if ((qe - e) ** 2 + (qn - n) ** 2) ** 0.5 <= radius}
            for qe, qn in q_utm]


def vme_recall(run_folder: Path, database: Path, queries: Path, ns=(1, 5, 10)) -> dict[int, float]:
    """VME's Recall@N (a fraction of every query) of the run's files as stored."""
    db_desc = np.load(run_folder / DATABASE_FILE).astype(np.float64)
    q_desc = np.load(run_folder / QUERIES_FILE).astype(np.float64)
    positives = vme_positives(vme_utm(vme_images(database)), vme_utm(vme_images(queries)))
    hits = {n: 0 for n in ns}
    for q, row in enumerate(q_desc):
        distances = [float(((row - d) ** 2).sum()) for d in db_desc]
        predictions = sorted(range(len(db_desc)), key=lambda j: distances[j])[:max(ns)]
        for n in ns:
            hits[n] += any(p in positives[q] for p in predictions[:n])
    return {n: hits[n] / len(q_desc) for n in ns}


def write_run(run_folder: Path, dataset, descriptors: np.ndarray, *, dtype=np.float32) -> Path:
    """The run VME would write for ``dataset``: each folder's rows in ``vme_images`` order."""
    run_folder.mkdir(parents=True, exist_ok=True)
    index = {str(p): i for i, p in enumerate(dataset.image_paths)}
    for name, side in ((DATABASE_FILE, "database"), (QUERIES_FILE, "queries")):
        folder = dataset.database_paths[0].parent if side == "database" else dataset.query_paths[0].parent
        while folder.name != side:
            folder = folder.parent
        rows = [index[os.path.normpath(p)] for p in vme_images(folder)]
        np.save(run_folder / name, descriptors[rows].astype(dtype))
    return run_folder


# --------------------------------------------------------------------------- a small dataset written here


def descriptor_of(name: str) -> np.ndarray:
    """A unit ``(DIM,)`` float32 vector drawn from the image's file name: each image's own."""
    v = np.random.default_rng(zlib.crc32(name.encode())).standard_normal(DIM)
    return (v / np.linalg.norm(v)).astype(np.float32)


def noise(seed: int) -> Image.Image:
    """A small image of random pixels (the app's default pixels descriptor of a flat image is zero)."""
    return Image.fromarray(np.random.default_rng(seed).integers(0, 256, (12, 16, 3), dtype=np.uint8))


def write_small(root: Path) -> Path:
    """40 database images in ``seq2/`` and ``seq10/`` (VME's plain order puts seq10 first, the natural order
    seq2), 20 queries in ``part9/`` and ``part10/``, 10 m apart along a line, each query 15 m off it, so that the
    database images two steps along lie exactly 25.0 m away; mixed-case extensions, and a hidden image and a
    text file that neither reader takes."""
    for i in range(40):
        sub = "seq2" if i < 20 else "seq10"
        ext = (".jpg", ".JPG", ".png", ".jpeg")[i % 4]
        path = root / "database" / sub / utm_name(500000 + 10 * i, 6960000.0, i).replace(".jpg", ext)
        path.parent.mkdir(parents=True, exist_ok=True)
        noise(i).save(path, format="PNG" if ext == ".png" else "JPEG")
    for i in range(20):
        sub = "part9" if i < 10 else "part10"
        path = root / "queries" / sub / utm_name(500000 + 20 * i, 6960015.0, 100 + i)
        path.parent.mkdir(parents=True, exist_ok=True)
        noise(100 + i).save(path)
    Image.new("RGB", (4, 4)).save(root / "database" / "seq2" / ".hidden.jpg")
    (root / "database" / "notes.txt").write_text("not an image\n")
    return root


@pytest.fixture
def small(tmp_path):
    """``(dataset, its descriptors from descriptor_of, the run written in VME's order)``."""
    ds = open_dataset(write_small(tmp_path / "data" / "small"))
    d = np.stack([descriptor_of(p.name) for p in ds.image_paths])
    return ds, d, write_run(tmp_path / "data" / "logs" / "default" / RUN, ds, d)


# --------------------------------------------------------------------------- (a) recall, VME's definition


@pytest.mark.realdata
def test_recall_on_gardens_point_equals_vmes_loop(tmp_path, data_root):
    """GardensPoint day_right as the database, night_right as queries 15 m off the route: every query's images
    two frames away lie at exactly 25.0 m, and count; pixel descriptors written in VME's order."""
    gp = data_root / "GardensPointWalking"
    root = tmp_path / "gp"
    for f in range(200):
        for side, trav, sub, north in (("database", "day_right", "seq2" if f < 100 else "seq10", 6960000.0),
                                       ("queries", "night_right", "part9" if f < 100 else "part10", 6960015.0)):
            link = root / side / sub / utm_name(500000 + 10.0 * f, north, f)
            link.parent.mkdir(parents=True, exist_ok=True)
            link.symlink_to((gp / trav / f"Image{f:03d}.jpg").resolve())
    ds = open_dataset(root)
    d = np.asarray(dataset_descriptors(ds, "pixels"))
    logdir = write_run(tmp_path / "logs" / "gp" / RUN, ds, d)
    assert [str(p) for p in ds.database_paths] != vme_images(root / "database")  # the orders differ

    imp = imported_descriptors(ds, logdir)
    assert isinstance(imp, VMERunDescriptors) and imp.name == RUN
    np.testing.assert_array_equal(imp.descriptors, d)  # unit float32 rows come back bit for bit, in place

    # the ground truth is VME's, the 25.0 m images included
    vme_db, vme_q = vme_images(root / "database"), vme_images(root / "queries")
    positives = vme_positives(vme_utm(vme_db), vme_utm(vme_q))
    vme_query = {path: i for i, path in enumerate(vme_q)}
    at_25 = 0
    for q in range(ds.n_queries):
        mine = {str(ds.database_paths[j]) for j in ds.ground_truth.positives(q)}
        assert mine == {vme_db[j] for j in positives[vme_query[str(ds.query_paths[q])]]}
        at_25 += sum(1 for j in ds.ground_truth.positives(q)
                     if np.hypot(*(ds.database_xy[j] - ds.query_xy[q])) == 25.0)
    assert at_25 == 2 * 200 - 4  # frames f ± 2, where they exist
    assert ds.ground_truth.n_unknown == 0  # every query has a positive: VME's and the explorer's R@N agree

    ev = evaluate_retrieval(ds, imp.descriptors, spec=PlaceSpec(3, 10))
    got = {k: v[0] for k, v in ev.row("image-baseline").recall.items()}
    want = vme_recall(logdir, root / "database", root / "queries")
    assert {k: got[k] for k in (1, 5, 10)} == pytest.approx(want, abs=1e-12)
    assert 0.05 < want[1] < 0.95  # neither nothing nor everything: the comparison means something


def hand_dataset(root: Path) -> Path:
    """Four database images at 0, 25, 200, 225 m along a line; query 0 at 50 m (database image 1, exactly 25.0 m
    away, is its one positive), query 1 at 250.5 m (25.5 m from the nearest: no positive)."""
    for i, east in enumerate((0.0, 25.0, 200.0, 225.0)):
        path = root / "database" / utm_name(500000 + east, 6960000.0, i)
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.new("RGB", (8, 8), (i * 40, 0, 0)).save(path)
    for i, east in enumerate((50.0, 250.5)):
        path = root / "queries" / utm_name(500000 + east, 6960000.0, 10 + i)
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.new("RGB", (8, 8), (0, i * 40, 0)).save(path)
    return root


def test_a_hand_computed_run_at_exactly_25_m_and_a_query_without_positive(tmp_path):
    """Four database images 0, 25, 200, 225 m along a line; query 0 at 50 m (database image 1 at exactly
    25.0 m is its positive and its nearest descriptor), query 1 at 250.5 m (the nearest image 25.5 m away: no
    positive). VME: R@1 = 1/2 (every query counts); the explorer's image level: 1/1 (over the queries with a
    positive, query 1 an unknown place)."""
    root = hand_dataset(tmp_path / "hand")
    ds = open_dataset(root)
    eye = np.eye(4, dtype=np.float32)
    q = np.array([eye[1] + 0.1 * eye[0], eye[3] + 0.2 * eye[2]], dtype=np.float32)
    d = np.vstack([eye, q / np.linalg.norm(q, axis=1, keepdims=True)])
    logdir = write_run(tmp_path / "logs" / RUN, ds, d)
    assert vme_recall(logdir, root / "database", root / "queries") == {1: 0.5, 5: 0.5, 10: 0.5}
    assert [ds.ground_truth.positives(q).tolist() for q in range(2)] == [[1], []]
    ev = evaluate_retrieval(ds, imported_descriptors(ds, logdir).descriptors, spec=PlaceSpec(1, 1))
    assert {k: v[0] for k, v in ev.row("image-baseline").recall.items()} == {1: 1.0, 3: 1.0, 5: 1.0, 10: 1.0}
    assert ev.settings["queries_without_positive"] == 1


# --------------------------------------------------------------------------- (b) rows land on their images


def test_rows_come_back_on_their_own_images(small):
    ds, d, logdir = small
    relative = [p.relative_to(ds.root / "database").as_posix() for p in ds.database_paths]
    assert relative[0].startswith("seq2/") and relative != sorted(relative)  # VME's order is another one
    assert ".hidden.jpg" not in "".join(relative) and len(relative) == 40
    imp = load_vme_run(logdir, ds)
    for i, p in enumerate(ds.image_paths):
        np.testing.assert_array_equal(imp.descriptors[i], descriptor_of(p.name), err_msg=str(p))
    assert imp.descriptors.shape == (60, DIM) and not imp.descriptors.flags.writeable
    assert imp.source.value == "vme-run" and imp.path == logdir
    assert any("VME's order (sorted paths below database/)" in n for n in imp.notes)
    # the settings name the folder and both files with their sha256
    s = imp.settings()
    assert s["descriptors_file"] == str(logdir) and len(s["queries_descriptors_sha256"]) == 64


def test_the_key_is_the_files_content(small):
    ds, d, logdir = small
    key = load_vme_run(logdir, ds).key
    stamp = run_stamp(logdir, ds)
    queries = np.load(logdir / QUERIES_FILE)
    np.save(logdir / QUERIES_FILE, queries)  # the same bytes again: the same key
    assert load_vme_run(logdir, ds).key == key
    queries[[0, 1]] = queries[[1, 0]]
    np.save(logdir / QUERIES_FILE, queries)  # two rows swapped: same size, another key
    assert load_vme_run(logdir, ds).key != key and run_stamp(logdir, ds) != stamp
    assert load_vme_run(logdir, ds, dtype="float16").key != load_vme_run(logdir, ds).key


# --------------------------------------------------------------------------- (c) <folder>_images_paths.txt


def test_an_images_paths_file_sets_the_order(small):
    ds, d, logdir = small
    names = [p.relative_to(ds.root / "database").as_posix() for p in ds.database_paths]
    shuffled = [names[i] for i in np.random.default_rng(3).permutation(len(names))]
    lines = [("./" + n if k % 3 == 0 else n) for k, n in enumerate(shuffled)]  # VME joins folder + "/" + line
    (ds.root / "database_images_paths.txt").write_text("\n".join(lines) + "\n")
    vme = vme_images(ds.root / "database")
    assert [os.path.normpath(p) for p in vme] == [str(ds.root / "database" / n) for n in shuffled]
    write_run(logdir, ds, d)  # VME's rows in the file's order
    imp = load_vme_run(logdir, ds)
    for i, p in enumerate(ds.image_paths):
        np.testing.assert_array_equal(imp.descriptors[i], descriptor_of(p.name), err_msg=str(p))
    assert any("rows in the order of database_images_paths.txt" in n for n in imp.notes)
    files = [Path(f).name for k, f in imp.settings().items() if not k.endswith("sha256")]
    assert "database_images_paths.txt" in files  # read, so hashed into the key and recorded

    listed = ds.root / "database_images_paths.txt"
    for text, says in (
        ("\n".join(lines[:-1]) + "\n", "lists 39 of the 40 images"),
        ("\n".join([*lines[:-1], "seq2/elsewhere.jpg"]) + "\n", "line 40: seq2/elsewhere.jpg is not an image of"),
        ("\n".join([*lines[:5], "", *lines[5:]]) + "\n", "line 6 is blank"),
        ("\n".join([*lines, lines[1]]) + "\n", "listed more than once"),
    ):
        listed.write_text(text)
        with pytest.raises(VPRInputError) as err:
            load_vme_run(logdir, ds)
        assert str(listed) in str(err.value) and says in str(err.value), str(err.value)


# --------------------------------------------------------------------------- (d) what does not fit


class RunsCode:
    """An object whose unpickling would create a folder: it must never be unpickled."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.mkdir, (str(self.marker),)


@pytest.mark.parametrize("fault", ["count", "dim", "missing", "pickled", "raw-pickle", "names-beside", "bmp"])
def test_a_run_that_does_not_fit_is_one_error_naming_the_file(small, tmp_path, fault):
    ds, d, logdir = small
    queries = logdir / QUERIES_FILE
    marker = tmp_path / "unpickled"
    named, says = queries, ""
    if fault == "count":
        np.save(queries, np.load(queries)[:19])
        says = f"19 rows, but {ds.root / 'queries'} holds 20 images"
    elif fault == "dim":
        np.save(queries, np.load(queries)[:, :8])
        says = "descriptors of length 8, but database_descriptors.npy's are of length 16"
    elif fault == "missing":
        queries.unlink()
        says = "missing"
    elif fault == "pickled":
        np.save(queries, np.array([RunsCode(marker)] * 20, dtype=object), allow_pickle=True)
        says = "cannot read it as a .npy descriptor file"
    elif fault == "raw-pickle":
        queries.write_bytes(pickle.dumps(RunsCode(marker)))
        says = "does not start with NumPy's .npy header"
    elif fault == "names-beside":
        named = logdir / "database_descriptors.txt"
        named.write_text("anything\n" * 40)
        says = "would reorder its rows"
    else:  # an image the explorer lists and VME's glob (.jpg, .jpeg, .png) does not
        noise(7).save(ds.root / "queries" / "part9" / utm_name(500000, 6960015.0, 999).replace(".jpg", ".bmp"))
        ds = open_dataset(ds.root)
        says = "holds 1 image VME's glob does not read (part9/@500000.00@"
    with pytest.raises(VPRInputError) as err:
        imported_descriptors(ds, logdir)
    assert str(named) in str(err.value) and says in str(err.value), str(err.value)
    assert not marker.exists()  # nothing in the file was run


def test_a_layout_other_than_database_queries_is_refused_by_name(small, demo, tmp_path):
    ds, d, logdir = small
    with pytest.raises(VPRInputError, match="demo is aligned traversal folders, not database-queries"):
        imported_descriptors(demo, logdir)
    manifest = tmp_path / "m.csv"
    manifest.write_text("path,role,x,y\n" + "".join(
        f"{p},{'database' if i < 40 else 'query'},{ds.image_paths[i].name.split('@')[1]},6960000\n"
        for i, p in enumerate(ds.image_paths)))
    with pytest.raises(VPRInputError, match="is a manifest layout, not database-queries: .*--layout database-queries"):
        imported_descriptors(open_dataset(manifest), logdir)
    with pytest.raises(VPRInputError, match="names file .*: a VPR-methods-evaluation run folder's rows follow"):
        imported_descriptors(ds, logdir, names_file=tmp_path / "n.txt")


# --------------------------------------------------------------------------- (e) the command line


def test_the_cli_evaluates_a_run_folder(small, tmp_path, capsys):
    ds, d, logdir = small
    out = tmp_path / "r.json"
    r = run("evaluate", "--dataset", str(ds.root), "--descriptors", str(logdir), "--json", str(out))
    assert r.returncode == 0, r.stderr[-2000:]
    assert f"{logdir.name}: database_descriptors.npy: 40 descriptors of length 16" in r.stdout
    assert "40 database and 20 query images; right: within 25 m; 0 queries with no right database image" in r.stdout
    data = json.loads(out.read_text())
    assert data["settings"]["descriptor"] == RUN and data["settings"]["descriptors_file"] == str(logdir)
    image = next(m for m in data["methods"] if m["key"] == "image-baseline")
    want = vme_recall(logdir, ds.root / "database", ds.root / "queries")
    got = {int(k): v for k, v in image["recall"].items()}
    assert {k: got[k]["mean"] for k in (1, 5, 10)} == pytest.approx(want, abs=1e-12)

    err = assert_one_error_line(refused(capsys, "evaluate", "--dataset", "demo", "--descriptors", str(logdir)),
                                "aligned traversal folders", "database-queries")
    assert "Traceback" not in err
    (logdir / DATABASE_FILE).unlink()
    assert_one_error_line(refused(capsys, "evaluate", "--dataset", str(ds.root), "--descriptors", str(logdir)),
                          str(logdir / DATABASE_FILE), "missing")


# --------------------------------------------------------------------------- (f) the app


@pytest.fixture
def served(small, tmp_path, monkeypatch):
    """The app's data root is ``tmp_path/data`` (the dataset and the run); a second run lies outside it."""
    monkeypatch.setenv(DATA_ROOT_ENV, str(tmp_path / "data"))
    ds, d, logdir = small
    outside = write_run(tmp_path / "outside" / RUN, ds, d)
    return ds, logdir, outside


def dataset_page(ds) -> AppTest:
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT)
    at.query_params.update(source=str(ds.root))
    at.run()
    at.radio(key="w_descriptor").set_value("__file__").run()
    return at


def test_the_app_reads_a_run_folder_typed_in_the_box_and_from_the_link(served):
    ds, logdir, _ = served
    at = dataset_page(ds)
    at.text_input(key="w_descriptor_file").input(str(logdir)).run()
    assert_clean(at)
    assert at.query_params["descriptors"] == str(logdir) and at.query_params["descriptor"] == RUN
    assert at.session_state["view"].descriptor == RUN
    assert any(f"{RUN} descriptors ready: 60 × {DIM} (read from {logdir}" in s.value for s in at.success)

    link = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT)
    link.query_params.update(source=str(ds.root), descriptors=str(logdir))
    link.run()
    assert_clean(link)
    assert link.radio(key="w_descriptor").value == "__file__"
    assert any(f"{RUN} descriptors ready: 60 × {DIM}" in s.value for s in link.success)


def test_the_app_refuses_a_run_folder_outside_its_data_root_and_a_broken_one(served):
    ds, logdir, outside = served
    at = dataset_page(ds)
    at.text_input(key="w_descriptor_file").input(str(outside)).run()
    assert_clean(at)  # outside the data root: a warning, nothing of it read, the previous descriptor kept
    assert len(at.warning) == 1 and str(outside) in at.warning[0].value
    assert at.session_state["view"].descriptors is None

    (logdir / QUERIES_FILE).unlink()
    at.text_input(key="w_descriptor_file").input(str(logdir)).run()
    assert_clean(at, errors=True)
    said = "\n".join(e.value for e in at.error)
    assert f"{logdir / QUERIES_FILE}: missing" in said
    assert at.session_state["view"].descriptors is None
