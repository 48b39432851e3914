"""The field's layouts built from the real GardensPoint images, read back, and evaluated.

Each layout is written in a temporary folder (symbolic links to the shared images, so the
content-keyed descriptor cache serves the same vectors); every recall is checked against
a plain loop over the ground-truth relation, and where a layout is the same data as the
aligned traversal folders, the numbers must be the same.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from vpr_explorer.errors import VPRInputError
from vpr_explorer.data.example_layouts import utm_name, write_gardens_point_layouts
from vpr_explorer.protocols.evaluation import retrieval_protocol
from vpr_explorer.protocols.options import ProtocolOptions
from vpr_explorer.data.groundtruth import GroundTruth
from vpr_explorer.data.layouts import Layout, detect_layout, load_manifest
from vpr_explorer.pipeline import dataset_descriptors, evaluate_retrieval, open_dataset, retrieval_places, run_protocol
from vpr_explorer.method.places import MetricPlaceSpec, PlaceSpec, make_places

pytestmark = pytest.mark.realdata

SPACING = 10.0  # metres between consecutive frames on a straight line


def _link(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.symlink_to(src.resolve())


def database_queries(root: Path, gp: Path, *, under_images_test=False) -> Path:
    base = root / "images" / "test" if under_images_test else root
    for side, trav in (("database", "day_right"), ("queries", "night_right")):
        for f in range(200):
            _link(gp / trav / f"Image{f:03d}.jpg", base / side / utm_name(500000 + SPACING * f, 6960000.0, f))
    return root


def loop_recall(sims: np.ndarray, gt: GroundTruth, ks=(1, 3, 5, 10)) -> dict[int, float]:
    """The field's Recall@K by a plain loop: a query counts when a positive is among its top K (ties against)."""
    hits = {k: 0 for k in ks}
    n = 0
    for q in range(gt.n_queries):
        pos = set(gt.positives(q).tolist())
        if not pos:
            continue
        n += 1
        best = max(sims[q, j] for j in pos)
        rank = 1 + sum(1 for j in range(sims.shape[1]) if j not in pos and sims[q, j] >= best - 1e-5)
        for k in ks:
            hits[k] += rank <= k
    return {k: hits[k] / n for k in ks}


@pytest.fixture(scope="module")
def gp_traversal(data_root, gardens_point, gp_pixels):
    """The traversal protocol on the aligned folders: day_right database, night_right queries, g3s10."""
    places = make_places(gardens_point, PlaceSpec(3, 10))

    def run(tolerance):
        return run_protocol("traversal", gardens_point, places, gp_pixels,
                            ProtocolOptions(database=["day_right"], queries="night_right", tolerance=tolerance))
    return run


def assert_place_rows_equal(a, b):
    rows_a = {r.key: r for r in a.rows if r.key != "image-baseline"}
    rows_b = {r.key: r for r in b.rows if r.key != "image-baseline"}
    assert set(rows_a) == set(rows_b)
    for key, ra in rows_a.items():
        rb = rows_b[key]
        np.testing.assert_equal(ra.recall, rb.recall, err_msg=key)
        np.testing.assert_equal((ra.accepted, ra.precision), (rb.accepted, rb.precision), err_msg=key)  # NaN == NaN


@pytest.mark.parametrize("radius, tolerance", [(5.0, 0), (25.0, 2)])
def test_database_queries_equals_the_aligned_traversals(tmp_path, data_root, gp_traversal, radius, tolerance):
    ds = open_dataset(database_queries(tmp_path / "gp", data_root / "GardensPointWalking"), radius=radius)
    assert ds.layout is Layout.DATABASE_QUERIES and ds.n_database == ds.n_queries == 200
    assert ds.ground_truth.counts.tolist() == [min(f, tolerance) + min(199 - f, tolerance) + 1 for f in range(200)]
    d = dataset_descriptors(ds, "pixels")
    ev = evaluate_retrieval(ds, d, spec=PlaceSpec(3, 10))
    assert ev.same_numbers(gp_traversal(tolerance))  # every row, the image level's too: one protocol
    # the image level counts as the field does: every database image, every query with a positive
    sims = d[200:].astype(np.float32) @ d[:200].astype(np.float32).T
    want = loop_recall(sims.astype(np.float64), ds.ground_truth)
    assert {k: v[0] for k, v in ev.row("image-baseline").recall.items()} == pytest.approx(want, abs=1e-12)
    assert ev.row("image-baseline").accepted[0] == 1.0  # the image level always answers, in a place or not
    # group/step in metres along the route give the same places as frames here (10 m a frame)
    same = evaluate_retrieval(ds, d, metric=MetricPlaceSpec(30, 100))
    assert_place_rows_equal(same, ev)


def test_database_queries_under_images_test_and_bad_names(tmp_path, data_root):
    root = database_queries(tmp_path / "gp", data_root / "GardensPointWalking", under_images_test=True)
    assert detect_layout(root) is Layout.DATABASE_QUERIES
    bad = root / "images" / "test" / "queries" / "no-position.jpg"
    _link(data_root / "GardensPointWalking" / "day_left" / "Image000.jpg", bad)
    with pytest.raises(VPRInputError, match="no-position.jpg: the file name carries no position"):
        open_dataset(root)
    bad.unlink()
    other = root / "images" / "test" / "queries" / "@500000.00@6960000.00@56@J@x@.jpg"
    _link(data_root / "GardensPointWalking" / "day_left" / "Image001.jpg", other)
    with pytest.raises(VPRInputError, match="UTM zone 56J differs"):
        open_dataset(root)


def vpr_bench(root: Path, gp: Path, rows) -> Path:
    for side, trav in (("ref", "day_right"), ("query", "night_right")):
        for f in range(200):
            _link(gp / trav / f"Image{f:03d}.jpg", root / side / f"{f}.jpg")
    gt = np.empty((len(rows), 2), dtype=object)
    for i, (q, refs) in enumerate(rows):
        gt[i, 0], gt[i, 1] = q, list(refs)
    np.save(root / "ground_truth_new.npy", gt)
    return root


def test_vpr_bench_equals_the_aligned_traversals(tmp_path, data_root, gp_traversal):
    rows = [(q, range(max(0, q - 2), min(200, q + 3))) for q in range(200)]
    root = vpr_bench(tmp_path / "vb", data_root / "GardensPointWalking", rows)
    ds = open_dataset(root)
    assert ds.layout is Layout.VPR_BENCH and ds.query_paths[10].name == "10.jpg"  # natural order, not 10 < 2
    d = dataset_descriptors(ds, "pixels")
    ev = evaluate_retrieval(ds, d, spec=PlaceSpec(3, 10))
    assert ev.same_numbers(gp_traversal(2))
    sims = (d[200:].astype(np.float32) @ d[:200].astype(np.float32).T).astype(np.float64)
    want = loop_recall(sims, ds.ground_truth)
    assert {k: v[0] for k, v in ev.row("image-baseline").recall.items()} == pytest.approx(want, abs=1e-12)


def test_vpr_bench_rows_that_do_not_fit_are_named(tmp_path, data_root):
    root = vpr_bench(tmp_path / "vb", data_root / "GardensPointWalking", [(0, [0]), (1, [1, 250])])
    with pytest.raises(VPRInputError, match=r"ground_truth_new.npy: row 2 points at reference 250, past the 200"):
        open_dataset(root)
    vpr_bench(tmp_path / "vb2", data_root / "GardensPointWalking", [(0, [0]), (300, [1])])
    with pytest.raises(VPRInputError, match="row 2 names query 300"):
        open_dataset(tmp_path / "vb2")


def test_unknown_place_queries_are_counted_apart(tmp_path, data_root):
    # queries 100..199 have no right reference: the open set, present in the data itself
    rows = [(q, [q]) for q in range(100)]
    ds = open_dataset(vpr_bench(tmp_path / "vb", data_root / "GardensPointWalking", rows))
    assert ds.ground_truth.n_unknown == 100
    d = dataset_descriptors(ds, "pixels")
    ev = evaluate_retrieval(ds, d, ProtocolOptions(user_theta=0.99), spec=PlaceSpec(3, 10))
    assert ev.settings["queries_without_positive"] == 100
    user = ev.row("global-user")
    assert user.unknown_rejection is not None and user.unknown_rejection[0] > 0.9  # θ 0.99 rejects nearly all
    assert ev.row("place-baseline").unknown_rejection[0] == 0.0  # no threshold rejects nothing


def test_traversal_positions_from_gp_pos(tmp_path, data_root):
    gp = data_root / "GardensPointWalking"
    with (gp / "gp_pos.csv").open() as fh:
        pos = np.array([[float(r[0]), float(r[1])] for r in csv.reader(fh) if r and r[0][0] in "0123456789.-"])
    assert pos.shape == (200, 2)
    root = tmp_path / "gpt"
    for trav in ("day_right", "night_right"):
        for f in range(200):
            _link(gp / trav / f"Image{f:03d}.jpg", root / trav / f"Image{f:03d}.jpg")
        np.savetxt(root / trav / "positions.csv", pos * 1000, delimiter=",", header="x,y", comments="")
    assert detect_layout(root) is Layout.TRAVERSAL_POSITIONS
    ds = open_dataset(root, radius=25)
    assert [p.parent.name for p in ds.query_paths[:1]] == ["night_right"]
    dist = np.linalg.norm(pos[:, None] * 1000 - pos[None] * 1000, axis=2)
    np.testing.assert_array_equal(ds.ground_truth.dense(), dist <= 25)
    d = dataset_descriptors(ds, "pixels")
    ev = evaluate_retrieval(ds, d, metric=MetricPlaceSpec(20, 60))
    sims = (d[200:].astype(np.float32) @ d[:200].astype(np.float32).T).astype(np.float64)
    assert ev.row("image-baseline").recall[1][0] == pytest.approx(loop_recall(sims, ds.ground_truth)[1], abs=1e-12)
    lattice = evaluate_retrieval(ds, d, metric=MetricPlaceSpec(40, 60, geometry="lattice"))
    assert lattice.settings["places"] != ev.settings["places"]


def test_manifest_with_place_ids_and_with_positions(tmp_path, data_root, gp_traversal):
    gp = data_root / "GardensPointWalking"
    places = (np.arange(200) // 10)  # frames [10k, 10k+3) are place k below; the rest are skipped
    in_place = np.arange(200) % 10 < 3
    path = tmp_path / "m.csv"
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["path", "role", "place"])
        for f in range(200):
            w.writerow([str(gp / "day_right" / f"Image{f:03d}.jpg"), "database", places[f] if in_place[f] else ""])
        for f in range(200):
            w.writerow([str(gp / "night_right" / f"Image{f:03d}.jpg"), "query", places[f] if in_place[f] else ""])
    ds = load_manifest(path)
    assert ds.layout is Layout.MANIFEST and retrieval_places(ds)[1] == 20
    d = dataset_descriptors(ds, "pixels")
    ev = evaluate_retrieval(ds, d)
    # place ids only on the frames in places: the same right places as the aligned traversals (tolerance 0);
    # frames between places have no positive here, so they are unknown-place queries
    assert ev.settings["queries_without_positive"] == 140
    ref = gp_traversal(0)
    for key in ("place-baseline", "margin-weighted", "raw-simple"):
        np.testing.assert_equal(ev.row(key).recall, ref.row(key).recall)  # a one-run std is NaN on both sides
    with path.open("a") as fh:
        fh.write("missing.jpg,query,3\n")
    with pytest.raises(VPRInputError, match=r"m.csv: line 402: .*missing.jpg does not exist"):
        load_manifest(path)


def test_retrieval_protocol_checks_its_inputs():
    gt = GroundTruth.from_lists([[0], [1]], 3, "given")
    d = np.eye(3)
    with pytest.raises(VPRInputError, match="ground truth of 2 × 3 for 3 queries"):
        retrieval_protocol(d, d, np.array([0, 1, 1]), 2, gt)
    with pytest.raises(VPRInputError, match="fewer than 2 places"):
        retrieval_protocol(d, d[:2], np.array([0, 0, -1]), 1, gt)


def test_cli_evaluates_and_lists_a_database_queries_dataset(tmp_path, data_root, capsys):
    from vpr_explorer.cli import main

    root = database_queries(tmp_path / "gp", data_root / "GardensPointWalking")
    out_json = tmp_path / "r.json"
    assert main(["evaluate", "--dataset", str(root), "--descriptor", "pixels", "--group", "30", "--step", "100",
                 "--geometry", "route", "--json", str(out_json)]) == 0
    out = capsys.readouterr().out
    assert "database-queries" in out and "200 database and 200 query images; right: within 25 m" in out
    assert "group 30 m, step 100 m (route, stride reading)" in out
    assert main(["evaluate", "--dataset", str(root), "--descriptor", "pixels", "--group", "30", "--step", "100"]) == 0
    assert "(lattice, stride reading)" in capsys.readouterr().out  # unordered images: a lattice by default
    import json

    data = json.loads(out_json.read_text())
    assert data["protocol"] == "database-queries" and data["settings"]["ground_truth"] == "within 25 m"
    # the same through frames: 10 m a frame, so group 3, step 10 frames are the same places
    assert main(["evaluate", "--dataset", str(root), "--descriptor", "pixels", "--geometry", "frames",
                 "--json", str(tmp_path / "f.json")]) == 0
    capsys.readouterr()
    frames = json.loads((tmp_path / "f.json").read_text())
    assert [m["recall"] for m in frames["methods"]] == [m["recall"] for m in data["methods"]]
    assert main(["list", "--dataset", str(root)]) == 0
    listed = capsys.readouterr().out.splitlines()
    assert len(listed) == 400 and listed[0].startswith("database/@500000.00@") and listed[200].startswith("queries/")
    for bad, said in ((["--protocol", "paper"], "use --protocol database-queries"),
                      (["--tolerance", "2"], "--radius"), (["--runs", "3"], "--runs applies to")):
        assert main(["evaluate", "--dataset", str(root), "--descriptor", "pixels", *bad]) == 2
        assert said in capsys.readouterr().err
    assert main(["evaluate", "--dataset", "demo", "--descriptor", "pixels", "--protocol", "database-queries"]) == 2
    assert "needs a database/queries layout" in capsys.readouterr().err
    assert main(["evaluate", "--dataset", "demo", "--descriptor", "pixels", "--radius", "5"]) == 2
    assert "--radius applies to database/queries layouts" in capsys.readouterr().err


def test_the_readmes_worked_examples_open_in_every_layout(tmp_path, data_root):
    paths = write_gardens_point_layouts(data_root / "GardensPointWalking", tmp_path / "gp")
    tables = {}
    for name, path in paths.items():
        ds = open_dataset(path)
        assert ds.layout.value == name and ds.n_database == ds.n_queries == 200
        d = dataset_descriptors(ds, "pixels")
        spec = MetricPlaceSpec(30, 100) if name == "database-queries" else None
        tables[name] = evaluate_retrieval(ds, d, spec=None if spec else PlaceSpec(3, 10), metric=spec)
    # the same ground truth (±2 frames = 25 m at 10 m a frame) and the same places: the same table
    assert tables["database-queries"].same_numbers(tables["vpr-bench"])
    assert tables["manifest"].settings["queries_without_positive"] == 140
