"""Playback of a dataset value's queries: read the written .rrd back and check it against the library's decisions.

Every expectation below is computed from ``numbers.explain_query`` (the Query
inspector's decision of one query) and the dataset directly, not from the recording
module's own helpers, so a wrong entity, query, order, answer, score, level or image fails
here. Aligned traversals are one value (``data.aligned.database_queries``: query q is frame
q of the query traversal); the database/queries layouts GardensPoint is written in are
recorded the same way, one entry per query in their order.
"""

from __future__ import annotations

import dataclasses
import re
import shutil
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from rerun.chunk import RrdReader

from images import write_random_png

from vpr_explorer.cli import main
from vpr_explorer.data.aligned import database_queries, value_rows
from vpr_explorer.data.traversals import load_dataset
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import MetricPlaceSpec, PlaceGeometry, PlaceSpec
from vpr_explorer.pipeline import dataset_descriptors, open_dataset, resolve_dataset
from vpr_explorer.recording import (
    check_output,
    decide_every_query,
    load_traversals,
    log_queries,
    new_recording,
    record_dataset,
    record_playback,
    viewer_servers,
)
from vpr_explorer.views.numbers import BETWEEN, UNKNOWN, RetrievalPlaces, explain_query, fit_retrieval

ROUTE = {"/route/query", "/route/paper", "/route/baseline"}
TEMPORAL = {
    "/query", "/match/paper", "/match/baseline", "/decision/paper", "/decision/baseline",
    "/scores/paper/raw", "/scores/paper/theta", "/scores/paper/margin",
    "/scores/baseline/raw", "/scores/baseline/theta", "/scores/baseline/margin",
    "/place/true", "/place/paper", "/place/baseline", *ROUTE,
}
SERIES = {e for e in TEMPORAL if e.startswith(("/scores/", "/place/"))}  # static style + temporal values
STATIC = {"/summary", "/thresholds/weighted", "/thresholds/simple", "/route/path", "/route/places"} | SERIES
EVERY_QUERY = TEMPORAL - {"/place/true", "/place/paper", "/place/baseline"}
METHODS = {"paper": "margin-weighted", "baseline": "place-baseline"}


# --------------------------------------------------------------------------- reading an .rrd


def _cell(column, i):
    """One row's component batch as a Python list (``None`` when the row does not hold it)."""
    cell = column[i]
    return cell.as_py() if cell.is_valid else None


def _blob(column, i) -> bytes | None:
    cell = column[i]
    if not cell.is_valid or len(cell) == 0:
        return None
    return cell.values.flatten().to_numpy(zero_copy_only=False).astype(np.uint8).tobytes()


def read_rrd(path: Path) -> tuple[dict[str, dict[int, dict]], dict[str, dict]]:
    """``(temporal, static)``: entity -> query -> component -> value, and entity -> component -> value."""
    temporal: dict[str, dict[int, dict]] = {}
    static: dict[str, dict] = {}
    for chunk in RrdReader(path).stream().collect().stream().to_chunks():
        if chunk.entity_path == "/__properties":
            continue
        batch = chunk.to_record_batch()
        names = [n for n in batch.schema.names if ":" in n]
        for i in range(batch.num_rows):
            row = {}
            for name in names:
                col = batch.column(name)
                row[name] = _blob(col, i) if name.endswith(":blob") else _cell(col, i)
            row = {k: v for k, v in row.items() if v is not None}
            if chunk.is_static:
                static.setdefault(chunk.entity_path, {}).update(row)
            else:
                query = int(batch.column("query")[i].as_py())
                temporal.setdefault(chunk.entity_path, {}).setdefault(query, {}).update(row)
    return temporal, static


# --------------------------------------------------------------------------- the check


def check_recording(path, fitted, descriptors, *, k: float = 0.0, positions=None) -> dict[str, list[str]]:
    """Every logged query of ``path`` equals the inspector's decision of that query, in query order.

    Args:
        positions: ``(database_xy, query_xy, path)`` of the route, or ``None`` when the layout has none.

    Returns:
        Method short name -> the level of each query's decision.
    """
    temporal, static = read_rrd(path)
    ds, model = fitted.dataset, fitted.model
    n = ds.n_queries
    assert set(temporal) == (TEMPORAL if positions is not None else TEMPORAL - ROUTE)
    assert set(static) == (STATIC if positions is not None else STATIC - {"/route/path", "/route/places"})
    for entity in SERIES:
        assert set(static[entity]) & {"SeriesLines:names", "SeriesPoints:names"}, entity
    for entity in set(temporal) & EVERY_QUERY:
        assert sorted(temporal[entity]) == list(range(n)), entity  # one entry per query, in order
    assert len(RrdReader(path).blueprints()) == 1

    theta = model.theta["weighted"] + k * model.spread
    np.testing.assert_array_equal(static["/thresholds/weighted"]["BarChart:values"][0]["buffer"], theta)
    np.testing.assert_array_equal(static["/thresholds/simple"]["BarChart:values"][0]["buffer"],
                                  model.theta["simple"] + k * model.spread)
    if positions is not None:
        database_xy, query_xy, route = positions
        strip = static["/route/path"].get("LineStrips2D:strips")
        np.testing.assert_allclose(np.array(strip[0] if strip else static["/route/path"]["Points2D:positions"]),
                                   route.astype(np.float32))
        centres = [database_xy[fitted.database_place == p].mean(axis=0) for p in range(fitted.n_places)]
        np.testing.assert_allclose(np.array(static["/route/places"]["Points2D:positions"]),
                                   np.array(centres, dtype=np.float32), rtol=1e-6)

    levels: dict[str, list[str]] = {short: [] for short in METHODS}
    for q in range(n):
        dec = explain_query(fitted, descriptors, q, k=k)
        status = fitted.query_status(q)
        if len(dec.true_places):
            true = int(dec.true_places[np.argmax(dec.raw[dec.true_places])])
            assert temporal["/place/true"][q]["Scalars:scalars"] == [float(true)]
        else:
            assert q not in temporal["/place/true"]
        assert temporal["/query"][q]["EncodedImage:blob"] == ds.query_paths[q].read_bytes()
        if positions is not None:
            assert np.allclose(temporal["/route/query"][q]["Points2D:positions"], [positions[1][q]])
        for short, key in METHODS.items():
            o = dec.outcomes[key]
            place, accepted = int(o.answer_place[0]), bool(o.accepted[0])
            log = temporal[f"/decision/{short}"][q]
            (text,) = log["TextLog:text"]
            if status == BETWEEN:
                level = "DEBUG"
            elif status == UNKNOWN:
                level = "ERROR" if accepted else "INFO"
            elif accepted and o.rank[0] == 1:
                level = "INFO"
            else:
                level = "ERROR" if accepted else "WARN"
            assert log["TextLog:level"] == [level], (short, q, text)
            levels[short].append(level)
            m = re.search(r"^query (\d+) · .*?: (accepted as place (\d+)|rejected)", text)
            assert m is not None and int(m.group(1)) == q, text
            assert (int(m.group(3)) if m.group(3) else -1) == place, text
            if status == BETWEEN:
                assert "not scored" in text, text
            elif status == UNKNOWN:
                assert "the query's place is not in the database" in text, text
            else:
                assert ("(right)" in text) == (level == "INFO"), text
            assert (q in temporal[f"/place/{short}"]) == accepted
            if accepted:
                assert temporal[f"/place/{short}"][q]["Scalars:scalars"] == [float(place)]
            # the best place's scores: the answer, or the place the paper's rule came nearest to accepting
            ranking = dec.raw - theta if key == "margin-weighted" else dec.raw
            best = place if accepted else int(np.argmax(np.where(np.isfinite(ranking), ranking, -np.inf)))
            raw = temporal[f"/scores/{short}/raw"][q]["Scalars:scalars"][0]
            assert raw == pytest.approx(dec.raw[best], abs=1e-6)
            assert temporal[f"/scores/{short}/theta"][q]["Scalars:scalars"] == [theta[best]]
            assert temporal[f"/scores/{short}/margin"][q]["Scalars:scalars"][0] == pytest.approx(raw - theta[best])
            # the database image behind the answer, and where it lies
            match = temporal[f"/match/{short}"][q]
            if accepted:
                image = int(model.images[o.answer_image[0]])
                assert match["EncodedImage:blob"] == ds.database_paths[image].read_bytes()
                if positions is not None:
                    assert np.allclose(temporal[f"/route/{short}"][q]["Points2D:positions"], [positions[0][image]])
            else:
                assert "EncodedImage:blob" not in match and match["Clear:is_recursive"] == [False]
                if positions is not None:
                    assert temporal[f"/route/{short}"][q].get("Points2D:positions", []) == []
    return levels


def aligned_value(dataset, descriptors, query, database, spec=PlaceSpec(3, 10), tolerance=0):
    """The value of aligned traversals, its descriptors in its order, and its fitted places."""
    value = database_queries(dataset, query, database, tolerance)
    rows = value_rows(value)
    d = descriptors if rows is None else descriptors[rows]
    return value, d, fit_retrieval(d, value, RetrievalPlaces(PlaceGeometry.FRAMES, spec=spec))


def frame_route(value):
    """Positions of the database images, the queries and the route of aligned traversals with positions."""
    xy = np.asarray(value.frame_xy)
    return xy[value.database_frame], xy[value.query_frame], xy


# --------------------------------------------------------------------------- real data


@pytest.mark.realdata
def test_gardens_point_night_against_day_matches_the_library(gardens_point, gp_pixels, tmp_path):
    value, d, fitted = aligned_value(gardens_point, gp_pixels, "night_right", ["day_right"])
    playback = record_playback(fitted, d, out=tmp_path / "gp.rrd", descriptor="pixels")
    assert playback.n_queries == 200 and playback.query == "night_right" and playback.database == ("day_right",)
    check_recording(playback.rrd, fitted, d, positions=frame_route(value))
    counts = playback.counts()["margin-weighted"]
    assert sum(counts.values()) == 200 and counts["between places"] == 140


@pytest.mark.realdata
def test_gardens_point_with_contiguous_places_and_k(gardens_point, gp_pixels, tmp_path):
    """Every query in a place, thresholds raised by k: wrong rejects appear and are logged as such."""
    value, d, fitted = aligned_value(gardens_point, gp_pixels, "night_right", ["day_left", "day_right"],
                                     PlaceSpec(2, 2))
    playback = record_playback(fitted, d, out=tmp_path / "k.rrd", k=2.0)
    levels = check_recording(playback.rrd, fitted, d, k=2.0, positions=frame_route(value))
    assert "WARN" in levels["paper"]


@pytest.mark.realdata
def test_cli_record_on_gardens_point(data_root, gardens_point, gp_pixels, tmp_path, capsys):
    out = tmp_path / "run.rrd"
    rc = main(["record", "--dataset", str(data_root / "GardensPointWalking"), "--database", "day_right",
               "--queries", "night_right", "--descriptor", "pixels", "--group", "3", "--step", "10",
               "--out", str(out)])
    assert rc == 0
    assert f"wrote {out}" in capsys.readouterr().out
    # The command reads only the two traversals it needs: the value is the same.
    value, d, fitted = aligned_value(gardens_point, gp_pixels, "night_right", ["day_right"])
    check_recording(out, fitted, d, positions=frame_route(value))


@pytest.fixture(scope="module")
def layouts(data_root, tmp_path_factory):
    from vpr_explorer.data.example_layouts import write_gardens_point_layouts

    return write_gardens_point_layouts(data_root / "GardensPointWalking", tmp_path_factory.mktemp("record_layouts"))


def _pixels_of(value, gardens_point, gp_pixels):
    rows = {p.resolve(): i for i, p in enumerate(gardens_point.image_paths)}
    return gp_pixels[[rows[p.resolve()] for p in value.image_paths]]


@pytest.mark.realdata
@pytest.mark.parametrize("layout, places", [
    ("database-queries", RetrievalPlaces(PlaceGeometry.ROUTE, metric=MetricPlaceSpec(25, 100))),
    ("vpr-bench", RetrievalPlaces(PlaceGeometry.FRAMES, spec=PlaceSpec(2, 5))),
    ("manifest", RetrievalPlaces(None)),
])
def test_a_database_queries_layout_plays_back_its_queries_in_order(layouts, gardens_point, gp_pixels, tmp_path,
                                                                   layout, places):
    value = open_dataset(layouts[layout])
    d = _pixels_of(value, gardens_point, gp_pixels)
    fitted = fit_retrieval(d, value, places)
    calls = []
    playback = record_playback(fitted, d, out=tmp_path / f"{layout}.rrd", descriptor="pixels",
                               progress=lambda done, total: calls.append((done, total)))
    assert calls == [(i, 200) for i in range(1, 201)]
    positions = None if value.database_xy is None else (value.database_xy, value.query_xy, value.database_xy)
    levels = check_recording(playback.rrd, fitted, d, positions=positions)
    statuses = {fitted.query_status(q) for q in range(value.n_queries)}
    if layout == "manifest":  # queries between the manifest's places have no positive: unknown places
        assert UNKNOWN in statuses and sum(playback.counts()["margin-weighted"].values()) == 200
    if layout == "database-queries":  # 25 m every 100 m: most queries' positives lie between places
        assert BETWEEN in statuses and "DEBUG" in levels["paper"]
    summary = read_rrd(playback.rrd)[1]["/summary"]["TextDocument:text"][0]
    assert f"# {value.name}: " in summary and "200 queries in their order" in summary


@pytest.mark.realdata
def test_cli_record_on_a_database_queries_layout(layouts, gardens_point, gp_pixels, tmp_path, capsys):
    out = tmp_path / "vb.rrd"
    rc = main(["record", "--dataset", str(layouts["vpr-bench"]), "--descriptor", "pixels", "--group", "2",
               "--step", "5", "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    assert "200 queries of query against ref (vpr-bench)" in capsys.readouterr().out
    value = open_dataset(layouts["vpr-bench"])
    d = _pixels_of(value, gardens_point, gp_pixels)
    check_recording(out, fit_retrieval(d, value, RetrievalPlaces(PlaceGeometry.FRAMES, spec=PlaceSpec(2, 5))), d)
    rc = main(["record", "--dataset", str(layouts["vpr-bench"]), "--descriptor", "pixels", "--tolerance", "2",
               "--out", str(out)])
    assert rc == 2 and "its queries and ground truth are set when it is opened" in capsys.readouterr().err


# --------------------------------------------------------------------------- demo route


@pytest.fixture(scope="module")
def demo():
    dataset = resolve_dataset("demo")
    return dataset, dataset_descriptors(dataset, "pixels")


def test_demo_record_dataset_matches_the_library(demo, tmp_path):
    dataset, desc = demo
    playback = record_dataset(load_traversals("demo", ["day"], "snow"), "pixels", query="snow", database=["day"],
                              group=2, step=2, out=tmp_path / "demo.rrd")
    value, d, fitted = aligned_value(dataset, desc, "snow", ["day"], PlaceSpec(2, 2))
    assert playback.n_queries == dataset.n_frames
    check_recording(playback.rrd, fitted, d, positions=frame_route(value))
    assert "snow against day" in playback.describe()


def test_demo_without_positions_draws_a_line_of_frames(demo, tmp_path):
    dataset, desc = demo
    dataset = dataclasses.replace(dataset, positions=None)
    value, d, fitted = aligned_value(dataset, desc, "night", ["day", "snow"], PlaceSpec(3, 5))
    playback = record_playback(fitted, d, out=tmp_path / "line.rrd")
    line = np.stack([np.arange(dataset.n_frames), np.zeros(dataset.n_frames)], axis=1)
    check_recording(playback.rrd, fitted, d, positions=(line[value.database_frame], line, line))


def test_log_queries_logs_to_the_given_recording_only(demo, tmp_path):
    dataset, desc = demo
    _, d, fitted = aligned_value(dataset, desc, "night", ["day"], PlaceSpec(2, 2))
    a, b = new_recording("a"), new_recording("b")
    a.save(tmp_path / "a.rrd")
    b.save(tmp_path / "b.rrd")
    log_queries(a, decide_every_query(fitted, d))
    a.disconnect()
    b.disconnect()
    assert len(read_rrd(tmp_path / "a.rrd")[0]["/query"]) == dataset.n_frames
    assert read_rrd(tmp_path / "b.rrd") == ({}, {})


def test_served_recording_reaches_the_viewer_servers(demo, tmp_path):
    dataset, desc = demo
    _, d, fitted = aligned_value(dataset, desc, "night", ["day"], PlaceSpec(2, 2))
    playback = record_playback(fitted, d, out=tmp_path / "s.rrd", serve=True)
    servers = viewer_servers()
    assert viewer_servers() is servers  # once per process
    assert playback.viewer_url == servers.viewer_url
    assert playback.viewer_url.startswith("http://127.0.0.1:")
    assert "rerun%2Bhttp%3A%2F%2F127.0.0.1%3A" in playback.viewer_url
    with urllib.request.urlopen(playback.viewer_url, timeout=10) as page:
        assert b"Rerun Viewer" in page.read()
    assert len(read_rrd(playback.rrd)[0]["/query"]) == dataset.n_frames


# --------------------------------------------------------------------------- an existing .rrd: replaced whole or kept


def _ctrl_c_at(query: int):
    """A progress callback that presses Ctrl-C once ``query`` queries are logged."""
    def progress(done: int, total: int) -> None:
        if done == query:
            raise KeyboardInterrupt
    return progress


def test_an_interrupted_record_keeps_the_existing_rrd_byte_for_byte(demo, tmp_path):
    out = tmp_path / "run.rrd"
    record_dataset(load_traversals("demo"), "pixels", query="snow", database=["day"], group=2, step=2, out=out)
    before = out.read_bytes()
    with pytest.raises(KeyboardInterrupt):
        record_dataset(load_traversals("demo"), "pixels", query="night", database=["day"], group=3, step=5, out=out,
                       progress=_ctrl_c_at(10))
    assert out.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["run.rrd"]  # no partial file left behind
    # a complete run replaces it
    record_dataset(load_traversals("demo"), "pixels", query="night", database=["day"], group=3, step=5, out=out)
    assert out.read_bytes() != before
    assert "night against day" in read_rrd(out)[1]["/summary"]["TextDocument:text"][0]
    assert [p.name for p in tmp_path.iterdir()] == ["run.rrd"]


def test_a_record_failing_midway_keeps_the_existing_rrd_and_writes_no_new_one(tmp_path):
    route = tmp_path / "route"
    for t, name in enumerate(("day", "night")):
        (route / name).mkdir(parents=True)
        for f in range(12):
            write_random_png(route / name / f"{f:03d}.png", seed=100 * t + f, size=(32, 24))
    dataset = load_dataset(route)
    _, d, fitted = aligned_value(dataset, dataset_descriptors(dataset, "pixels"), "night", ["day"], PlaceSpec(2, 3))
    out = tmp_path / "out" / "run.rrd"
    out.parent.mkdir()
    out.write_bytes(b"a complete recording from yesterday")
    (route / "night" / "007.png").unlink()  # a query image vanishes while the recording runs
    for target in (out, out.with_name("new.rrd")):
        with pytest.raises(VPRInputError, match="007.png: cannot read the image"):
            record_playback(fitted, d, out=target)
    assert out.read_bytes() == b"a complete recording from yesterday"
    assert [p.name for p in out.parent.iterdir()] == ["run.rrd"]


# --------------------------------------------------------------------------- bad input


def test_unknown_traversal_is_named(demo, tmp_path):
    dataset, _ = demo
    with pytest.raises(VPRInputError, match="traversal 'dusk' is not in dataset 'demo'.*day, night, snow"):
        record_dataset(dataset, "pixels", query="dusk", out=tmp_path / "x.rrd")
    with pytest.raises(VPRInputError, match="'dusk'"):
        load_traversals("demo", ["dusk"], "night")
    with pytest.raises(VPRInputError, match="also a database traversal"):
        load_traversals(tmp_path, ["day"], "day")
    with pytest.raises(VPRInputError, match="is both the query and in the database"):
        record_dataset(dataset, "pixels", query="day", database=["day"], out=tmp_path / "x.rrd")
    assert not (tmp_path / "x.rrd").exists()


def test_cli_unknown_traversal_exits_2(tmp_path, capsys):
    rc = main(["record", "--dataset", "demo", "--database", "day", "--queries", "dusk", "--descriptor", "pixels",
               "--out", str(tmp_path / "x.rrd")])
    assert rc == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "traversal 'dusk' is not in dataset 'demo'" in err
    assert not (tmp_path / "x.rrd").exists()


def test_mismatched_inputs_are_refused(demo, tmp_path):
    dataset, desc = demo
    _, d, fitted = aligned_value(dataset, desc, "night", ["day"], PlaceSpec(2, 2))
    with pytest.raises(VPRInputError, match="100 descriptors for 120 images"):
        record_playback(fitted, d[:100], out=tmp_path / "x.rrd")
    with pytest.raises(VPRInputError, match="k=nan"):
        record_playback(fitted, d, out=tmp_path / "x.rrd", k=float("nan"))
    assert not (tmp_path / "x.rrd").exists()


def _frames(folder: Path, n: int, source: Path) -> None:
    folder.mkdir(parents=True)
    for i in range(n):
        shutil.copy(source / f"Image{i:03d}.jpg", folder / f"Image{i:03d}.jpg")


@pytest.mark.realdata
def test_traversals_of_different_lengths_get_a_clear_message(data_root, tmp_path, capsys):
    gp = data_root / "GardensPointWalking"
    root = tmp_path / "uneven"
    _frames(root / "day", 30, gp / "day_right")
    _frames(root / "night", 30, gp / "night_right")
    _frames(root / "dusk", 20, gp / "day_left")
    args = ["record", "--dataset", str(root), "--descriptor", "pixels", "--group", "2", "--step", "5"]
    rc = main([*args, "--database", "day", "--queries", "dusk", "--out", str(tmp_path / "a.rrd")])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith("error: ") and "different numbers of frames" in err and "dusk: 20" in err
    # Only the chosen traversals need equal lengths.
    rc = main([*args, "--database", "day", "--queries", "night", "--out", str(tmp_path / "b.rrd")])
    assert rc == 0 and (tmp_path / "b.rrd").stat().st_size > 0


@pytest.mark.parametrize(
    ("out", "message"),
    [
        ("missing/run.rrd", "the folder .*missing does not exist"),
        ("folder.rrd", "is a folder"),
        ("file.txt/run.rrd", "is a file, not a folder"),
        ("run.txt", "needs the .rrd suffix"),
        ("/proc/run.rrd", "cannot write the recording"),
    ],
)
def test_unwritable_output_is_refused(tmp_path, out, message):
    (tmp_path / "folder.rrd").mkdir()
    (tmp_path / "file.txt").write_text("")
    path = Path(out) if out.startswith("/") else tmp_path / out
    with pytest.raises(VPRInputError, match=message):
        check_output(path)


def test_cli_unwritable_output_exits_2_before_any_work(tmp_path, capsys):
    rc = main(["record", "--dataset", "demo", "--database", "day", "--queries", "night",
               "--descriptor", "pixels", "--out", "/proc/run.rrd"])
    assert rc == 2
    err = capsys.readouterr().err
    assert err.startswith("error: /proc/run.rrd: cannot write the recording")
    assert "descriptors" not in err  # refused before extracting anything
