"""Traversal playback: read the written .rrd back and check it against the library's decisions.

Every expectation below is computed from ``decide_traversal`` and the dataset directly,
not from the recording module's own helpers, so a wrong entity, frame, answer, score,
level or image fails here.
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
from vpr_explorer.method.database import decide_traversal, fit_database
from vpr_explorer.data.traversals import load_dataset
from vpr_explorer.errors import VPRInputError
from vpr_explorer.pipeline import dataset_descriptors, resolve_dataset
from vpr_explorer.method.places import PlaceSpec, make_places
from vpr_explorer.recording import (
    check_output,
    new_recording,
    record_dataset,
    record_playback,
    record_traversal,
    save_traversal,
    viewer_servers,
)

TEMPORAL = {
    "/query", "/match/paper", "/match/baseline", "/decision/paper", "/decision/baseline",
    "/scores/paper/raw", "/scores/paper/theta", "/scores/paper/margin",
    "/scores/baseline/raw", "/scores/baseline/theta", "/scores/baseline/margin",
    "/place/true", "/place/paper", "/place/baseline", "/route/query", "/route/paper", "/route/baseline",
}
SERIES = {e for e in TEMPORAL if e.startswith(("/scores/", "/place/"))}  # static style + temporal values
STATIC = {"/summary", "/thresholds/weighted", "/thresholds/simple", "/route/path", "/route/places"} | SERIES
EVERY_FRAME = TEMPORAL - {"/place/true", "/place/paper", "/place/baseline"}
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
    """``(temporal, static)``: entity -> frame -> component -> value, and entity -> component -> value."""
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
                frame = int(batch.column("frame")[i].as_py())
                temporal.setdefault(chunk.entity_path, {}).setdefault(frame, {}).update(row)
    return temporal, static


# --------------------------------------------------------------------------- the check


def check_recording(path, dataset, places, model, decisions, positions) -> None:
    """Every logged frame of ``path`` equals the library's decision for that frame."""
    temporal, static = read_rrd(path)
    assert set(temporal) == TEMPORAL
    assert set(static) == STATIC
    for entity in SERIES:
        assert set(static[entity]) & {"SeriesLines:names", "SeriesPoints:names"}, entity
    qi = decisions.query_images
    n = len(qi)
    frames = dataset.image_frame[qi]
    for entity in EVERY_FRAME:
        assert sorted(temporal[entity]) == list(frames), entity
    assert len(RrdReader(path).blueprints()) == 1

    theta = np.asarray(decisions.thresholds["weighted"], dtype=np.float64)
    np.testing.assert_array_equal(static["/thresholds/weighted"]["BarChart:values"][0]["buffer"], theta)
    np.testing.assert_array_equal(static["/thresholds/simple"]["BarChart:values"][0]["buffer"],
                                  np.asarray(decisions.thresholds["simple"], dtype=np.float64))
    np.testing.assert_array_equal(np.array(static["/route/path"]["LineStrips2D:strips"][0]),
                                  positions.astype(np.float32))
    centres = [positions[round(np.flatnonzero(places.frame_place == p).mean())] for p in range(places.n_places)]
    np.testing.assert_array_equal(np.array(static["/route/places"]["Points2D:positions"]),
                                  np.array(centres, dtype=np.float32))

    known = decisions.truth.any(axis=1)
    truth_rows = {int(f): np.flatnonzero(decisions.truth[i]) for i, f in enumerate(frames)}
    assert sorted(temporal["/place/true"]) == sorted(int(f) for f in frames[known])
    for f, row in temporal["/place/true"].items():
        assert row["Scalars:scalars"] == [float(truth_rows[f][0])]

    for short, key in METHODS.items():
        o = decisions.outcomes[key]
        answered = {int(frames[i]) for i in range(n) if o.answer_place[i] >= 0}
        assert set(temporal[f"/place/{short}"]) == answered
        for i in range(n):
            f = int(frames[i])
            place = int(o.answer_place[i])
            accepted = place >= 0
            # the answer, as a text log with the level that marks its kind
            log = temporal[f"/decision/{short}"][f]
            (text,) = log["TextLog:text"]
            if not known[i]:
                level = "DEBUG"
            elif accepted and o.rank[i] == 1:
                level = "INFO"
            else:
                level = "ERROR" if accepted else "WARN"
            assert log["TextLog:level"] == [level], (short, f, text)
            m = re.search(r": (accepted as place (\d+)|rejected)", text)
            assert m is not None, text
            assert (int(m.group(2)) if m.group(2) else -1) == place, text
            if known[i]:
                assert ("(right)" in text) == (level == "INFO"), text
            else:
                assert "not scored" in text, text
            if accepted:
                assert temporal[f"/place/{short}"][f]["Scalars:scalars"] == [float(place)]
            # the best place's scores
            best = place if accepted else int(np.argmax(np.where(np.isfinite(decisions.raw[i] - theta),
                                                                 decisions.raw[i] - theta, -np.inf)))
            raw = decisions.raw[i, best]
            assert temporal[f"/scores/{short}/raw"][f]["Scalars:scalars"] == [raw]
            assert temporal[f"/scores/{short}/theta"][f]["Scalars:scalars"] == [theta[best]]
            assert temporal[f"/scores/{short}/margin"][f]["Scalars:scalars"] == [raw - theta[best]]
            # the database image behind the answer, and where it lies on the route
            match = temporal[f"/match/{short}"][f]
            route = temporal[f"/route/{short}"][f]
            if accepted:
                image = model.images[o.answer_image[i]]
                assert match["EncodedImage:blob"] == dataset.image_paths[image].read_bytes()
                assert np.allclose(route["Points2D:positions"], [positions[dataset.image_frame[image]]])
            else:
                assert "EncodedImage:blob" not in match and match["Clear:is_recursive"] == [False]
                assert route.get("Points2D:positions", []) == []
    for i in range(n):
        f = int(frames[i])
        assert temporal["/query"][f]["EncodedImage:blob"] == dataset.image_paths[qi[i]].read_bytes()
        assert np.allclose(temporal["/route/query"][f]["Points2D:positions"], [positions[f]])


def fitted(dataset, descriptors, spec, database):
    places = make_places(dataset, spec)
    return places, fit_database(descriptors, dataset, places, database)


# --------------------------------------------------------------------------- real data


@pytest.mark.realdata
def test_gardens_point_night_against_day_matches_the_library(gardens_point, gp_pixels, tmp_path):
    places, model = fitted(gardens_point, gp_pixels, PlaceSpec(3, 10), ["day_right"])
    expected = decide_traversal(model, gp_pixels, gardens_point, places, "night_right")
    playback = save_traversal(tmp_path / "gp.rrd", gardens_point, places, gp_pixels, model, "night_right",
                              descriptor="pixels")
    assert playback.n_frames == 200 and playback.query == "night_right" and playback.database == ("day_right",)
    for key, outcome in expected.outcomes.items():
        np.testing.assert_array_equal(playback.decisions.outcomes[key].answer_place, outcome.answer_place)
    check_recording(playback.rrd, gardens_point, places, model, expected, gardens_point.positions)
    counts = playback.counts()["margin-weighted"]
    assert sum(counts.values()) == 200 and counts["between places"] == 140


@pytest.mark.realdata
def test_gardens_point_with_contiguous_places_and_k(gardens_point, gp_pixels, tmp_path):
    """Every frame in a place, thresholds raised by k: wrong rejects appear and are logged as such."""
    places, model = fitted(gardens_point, gp_pixels, PlaceSpec(2, 2), ["day_left", "day_right"])
    expected = decide_traversal(model, gp_pixels, gardens_point, places, "night_right", k=2.0)
    assert (~expected.outcomes["margin-weighted"].accepted).any()
    playback = save_traversal(tmp_path / "k.rrd", gardens_point, places, gp_pixels, model, "night_right", k=2.0)
    check_recording(playback.rrd, gardens_point, places, model, expected, gardens_point.positions)


@pytest.mark.realdata
def test_cli_record_on_gardens_point(data_root, gardens_point, gp_pixels, tmp_path, capsys):
    out = tmp_path / "run.rrd"
    rc = main(["record", "--dataset", str(data_root / "GardensPointWalking"), "--database", "day_right",
               "--queries", "night_right", "--descriptor", "pixels", "--group", "3", "--step", "10",
               "--out", str(out)])
    assert rc == 0
    assert f"wrote {out}" in capsys.readouterr().out
    places, model = fitted(gardens_point, gp_pixels, PlaceSpec(3, 10), ["day_right"])
    expected = decide_traversal(model, gp_pixels, gardens_point, places, "night_right")
    # The command reads only the two traversals it needs: image indices differ, frames do not.
    sub = resolve_dataset(data_root / "GardensPointWalking")
    sub = dataclasses.replace(sub, traversals=("day_right", "night_right"), paths=sub.paths[1:])
    sub_desc = gp_pixels[200:]
    sub_places, sub_model = fitted(sub, sub_desc, PlaceSpec(3, 10), ["day_right"])
    sub_expected = decide_traversal(sub_model, sub_desc, sub, sub_places, "night_right")
    np.testing.assert_array_equal(sub_expected.raw, expected.raw)
    check_recording(out, sub, sub_places, sub_model, sub_expected, sub.positions)


# --------------------------------------------------------------------------- demo route


@pytest.fixture(scope="module")
def demo():
    dataset = resolve_dataset("demo")
    return dataset, dataset_descriptors(dataset, "pixels")


def test_demo_record_dataset_matches_the_library(demo, tmp_path):
    dataset, desc = demo
    playback = record_dataset("demo", PlaceSpec(2, 2), "pixels", database=["day"], queries="snow",
                              out=tmp_path / "demo.rrd")
    places, model = fitted(dataset, desc, PlaceSpec(2, 2), ["day"])
    expected = decide_traversal(model, desc, dataset, places, "snow")
    assert playback.n_frames == dataset.n_frames
    check_recording(playback.rrd, dataset, places, model, expected, dataset.positions)
    assert "snow against day" in playback.describe()


def test_demo_without_positions_draws_a_line_of_frames(demo, tmp_path):
    dataset, desc = demo
    dataset = dataclasses.replace(dataset, positions=None)
    places, model = fitted(dataset, desc, PlaceSpec(3, 5), ["day", "snow"])
    expected = decide_traversal(model, desc, dataset, places, "night")
    playback = save_traversal(tmp_path / "line.rrd", dataset, places, desc, model, "night")
    line = np.stack([np.arange(dataset.n_frames), np.zeros(dataset.n_frames)], axis=1)
    check_recording(playback.rrd, dataset, places, model, expected, line)


def test_record_traversal_logs_to_the_given_recording_only(demo, tmp_path):
    dataset, desc = demo
    places, model = fitted(dataset, desc, PlaceSpec(2, 2), ["day"])
    a, b = new_recording("a"), new_recording("b")
    a.save(tmp_path / "a.rrd")
    b.save(tmp_path / "b.rrd")
    record_traversal(dataset, places, desc, model, "night", recording=a)
    a.disconnect()
    b.disconnect()
    assert len(read_rrd(tmp_path / "a.rrd")[0]["/query"]) == dataset.n_frames
    assert read_rrd(tmp_path / "b.rrd") == ({}, {})


def test_progress_reports_every_frame(demo, tmp_path):
    dataset, desc = demo
    places, model = fitted(dataset, desc, PlaceSpec(2, 2), ["day"])
    calls = []
    save_traversal(tmp_path / "p.rrd", dataset, places, desc, model, "night", progress=lambda d, t: calls.append((d, t)))
    assert calls == [(i, dataset.n_frames) for i in range(1, dataset.n_frames + 1)]


def test_served_recording_reaches_the_viewer_servers(demo, tmp_path):
    dataset, desc = demo
    places, model = fitted(dataset, desc, PlaceSpec(2, 2), ["day"])
    playback = save_traversal(tmp_path / "s.rrd", dataset, places, desc, model, "night", serve=True)
    servers = viewer_servers()
    assert viewer_servers() is servers  # once per process
    assert playback.viewer_url == servers.viewer_url
    assert playback.viewer_url.startswith("http://127.0.0.1:") and "rerun%2Bhttp%3A%2F%2F127.0.0.1%3A" in playback.viewer_url
    with urllib.request.urlopen(playback.viewer_url, timeout=10) as page:
        assert b"Rerun Viewer" in page.read()
    assert len(read_rrd(playback.rrd)[0]["/query"]) == dataset.n_frames


# --------------------------------------------------------------------------- an existing .rrd: replaced whole or kept


def _ctrl_c_at(frame: int):
    """A progress callback that presses Ctrl-C once ``frame`` frames are logged."""
    def progress(done: int, total: int) -> None:
        if done == frame:
            raise KeyboardInterrupt
    return progress


def test_an_interrupted_record_keeps_the_existing_rrd_byte_for_byte(demo, tmp_path):
    dataset, _ = demo
    out = tmp_path / "run.rrd"
    record_dataset("demo", PlaceSpec(2, 2), "pixels", database=["day"], queries="snow", out=out)
    before = out.read_bytes()
    with pytest.raises(KeyboardInterrupt):
        record_dataset("demo", PlaceSpec(3, 5), "pixels", database=["day"], queries="night", out=out,
                       progress=_ctrl_c_at(10))
    assert out.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["run.rrd"]  # no partial file left behind
    # a complete run replaces it
    record_dataset("demo", PlaceSpec(3, 5), "pixels", database=["day"], queries="night", out=out)
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
    desc = dataset_descriptors(dataset, "pixels")
    out = tmp_path / "out" / "run.rrd"
    out.parent.mkdir()
    out.write_bytes(b"a complete recording from yesterday")
    (route / "night" / "007.png").unlink()  # a query image vanishes while the recording runs
    for target in (out, out.with_name("new.rrd")):
        with pytest.raises(VPRInputError, match="007.png: cannot read the image"):
            record_playback(dataset, desc, PlaceSpec(2, 3), database=["day"], queries="night", out=target)
    assert out.read_bytes() == b"a complete recording from yesterday"
    assert [p.name for p in out.parent.iterdir()] == ["run.rrd"]


# --------------------------------------------------------------------------- bad input


def test_unknown_traversal_is_named(demo, tmp_path):
    dataset, desc = demo
    places, model = fitted(dataset, desc, PlaceSpec(2, 2), ["day"])
    with pytest.raises(VPRInputError, match="traversal 'dusk' is not in dataset 'demo'.*day, night, snow"):
        save_traversal(tmp_path / "x.rrd", dataset, places, desc, model, "dusk")
    with pytest.raises(VPRInputError, match="'dusk'"):
        record_dataset("demo", PlaceSpec(2, 2), "pixels", database=["dusk"], queries="night", out=tmp_path / "x.rrd")
    with pytest.raises(VPRInputError, match="also a database traversal"):
        record_dataset("demo", PlaceSpec(2, 2), "pixels", database=["day"], queries="day", out=tmp_path / "x.rrd")
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
    places, model = fitted(dataset, desc, PlaceSpec(2, 2), ["day"])
    rec = new_recording()
    with pytest.raises(VPRInputError, match="descriptors for 180 images"):
        record_traversal(dataset, places, desc[:100], model, "night", recording=rec)
    other_places, other_model = fitted(dataset, desc, PlaceSpec(3, 10), ["day"])
    with pytest.raises(VPRInputError, match="fitted on other places"):
        record_traversal(dataset, places, desc, other_model, "night", recording=rec)


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
