"""The built-in demo route: deterministic, loadable, a street a camera drives along, crash-safe."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from vpr_explorer.data import demo
from vpr_explorer.data.traversals import load_dataset
from vpr_explorer.data.demo import (
    DEMO_FRAMES,
    DEMO_SEED,
    DEMO_TRAVERSALS,
    DEMO_VERSION,
    FRAME_SIZE,
    MARKER,
    demo_dataset,
    demo_root,
    render_frames,
    route_is_complete,
    write_demo_route,
)
from vpr_explorer.errors import VPRInputError
from vpr_explorer.settings import CACHE_ENV, cache_root

SMALL = 12  # frames in the routes the file-handling tests write


@pytest.fixture(autouse=True)
def _cache_in_tmp(tmp_path, monkeypatch):
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))


def _files(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _thumb(image: np.ndarray) -> np.ndarray:
    """Greyscale 64x32 thumbnail, zero mean, unit norm: NCC is then a dot product."""
    g = np.asarray(Image.fromarray(image).convert("L").resize((64, 32), Image.Resampling.BILINEAR), np.float64)
    g = g.ravel() - g.mean()
    return g / np.linalg.norm(g)


@pytest.fixture(scope="module")
def thumbs() -> dict[str, np.ndarray]:
    """``{traversal: (n_frames, 2048)}`` thumbnails of the default route."""
    out: dict[str, list[np.ndarray]] = {t: [] for t in DEMO_TRAVERSALS}
    for traversal, _, image in render_frames(DEMO_SEED, DEMO_FRAMES):
        out[traversal].append(_thumb(image))
    return {t: np.stack(v) for t, v in out.items()}


# --------------------------------------------------------------------------- determinism


def test_same_seed_writes_identical_bytes_and_another_seed_other_images(tmp_path):
    a = _files(write_demo_route(tmp_path / "a", seed=3, n_frames=SMALL))
    b = _files(write_demo_route(tmp_path / "b", seed=3, n_frames=SMALL))
    c = _files(write_demo_route(tmp_path / "c", seed=4, n_frames=SMALL))
    assert len(a) == len(DEMO_TRAVERSALS) * SMALL + 3  # frames, positions.csv, README.txt, route.json
    assert a == b
    frames = [name for name in a if name.endswith(".png")]
    assert set(frames) == {name for name in c if name.endswith(".png")}
    differing = [n for n in frames if a[n] != c[n]]
    assert len(differing) == len(frames)
    pa = np.asarray(Image.open(tmp_path / "a" / "day" / "frame_005.png"), np.int16)
    pc = np.asarray(Image.open(tmp_path / "c" / "day" / "frame_005.png"), np.int16)
    assert np.abs(pa - pc).mean() > 10


def test_files_hold_exactly_the_rendered_pixels(tmp_path):
    root = write_demo_route(tmp_path / "r", seed=1, n_frames=SMALL)
    for traversal, f, image in render_frames(1, SMALL):
        with Image.open(root / traversal / f"frame_{f:03d}.png") as im:
            assert im.mode == "RGB" and im.size == FRAME_SIZE
            np.testing.assert_array_equal(np.asarray(im), image)


def test_conditions_are_not_pixel_copies_of_each_other():
    frames = {t: image for t, f, image in render_frames(0, 10) if f == 4}
    day = frames["day"].astype(np.int16)
    for other in ("night", "snow"):
        assert np.abs(frames[other].astype(np.int16) - day).mean() > 20


# --------------------------------------------------------------------------- layout


def test_route_loads_as_a_dataset(tmp_path):
    root = write_demo_route(tmp_path / "route", n_frames=SMALL)
    ds = load_dataset(root)
    assert ds.traversals == DEMO_TRAVERSALS
    assert ds.n_frames == SMALL and ds.n_images == 3 * SMALL
    assert [p.name for p in ds.paths[0][:3]] == ["frame_000.png", "frame_001.png", "frame_002.png"]
    assert ds.positions.shape == (SMALL, 2)
    assert ((ds.positions >= 0) & (ds.positions <= 1)).all()
    steps = np.linalg.norm(np.diff(ds.positions, axis=0), axis=1)
    assert steps.min() > 0 and steps.max() < 3 * steps.min()  # a route, evenly driven
    assert (root / "positions.csv").read_text().splitlines()[0] == "x,y"
    assert "not a benchmark" in (root / "README.txt").read_text()


def test_demo_dataset_is_named_demo_and_lives_in_the_cache():
    ds = demo_dataset(n_frames=SMALL)
    assert ds.name == "demo"
    assert ds.root == cache_root() / "demo" / f"route-s{DEMO_SEED}-n{SMALL}-v{DEMO_VERSION}" == demo_root(n_frames=SMALL)
    assert ds.n_traversals == 3 and ds.n_frames == SMALL
    assert ds.positions.shape == (SMALL, 2)


# --------------------------------------------------------------------------- a street a camera drives along


def test_consecutive_frames_overlap_and_distant_frames_do_not(thumbs):
    n = DEMO_FRAMES
    for traversal, t in thumbs.items():
        near = float(np.mean([t[f] @ t[f + 1] for f in range(n - 1)]))
        far = float(np.mean([t[f] @ t[f + 15] for f in range(n - 15)]))
        print(f"{traversal}: NCC(f, f+1) = {near:.3f}, NCC(f, f+15) = {far:.3f}")
        assert near > far + 0.1


@pytest.mark.parametrize("query", ["night", "snow"])
def test_place_recognition_against_day_is_possible_but_not_trivial(thumbs, query):
    n = DEMO_FRAMES
    sim = thumbs[query] @ thumbs["day"].T  # (n_queries, n_database)
    same = float(np.mean(np.diag(sim)))
    far = float(np.mean([sim[f, (f + n // 2) % n] for f in range(n)]))
    recall = float(np.mean(np.abs(sim.argmax(axis=1) - np.arange(n)) <= 1))
    print(f"{query}->day: NCC same frame {same:.3f}, far frame {far:.3f}, Recall@1 (+-1 frame) {recall:.0%}")
    assert same > far + 0.05
    assert 0.3 <= recall < 0.97


# --------------------------------------------------------------------------- damaged routes and crashes


def _damage_marker(root: Path) -> None:
    (root / MARKER).unlink()


def _damage_frame(root: Path) -> None:
    (root / "night" / "frame_007.png").unlink()


def _damage_truncate(root: Path) -> None:
    path = root / "snow" / "frame_003.png"
    path.write_bytes(path.read_bytes()[:100])


@pytest.mark.parametrize("damage", [_damage_marker, _damage_frame, _damage_truncate])
def test_demo_dataset_rewrites_a_damaged_route(damage):
    root = demo_dataset(n_frames=SMALL).root
    good = _files(root)
    damage(root)
    assert not route_is_complete(root, seed=DEMO_SEED, n_frames=SMALL)
    ds = demo_dataset(n_frames=SMALL)
    assert route_is_complete(root, seed=DEMO_SEED, n_frames=SMALL)
    assert _files(root) == good
    assert ds.n_frames == SMALL
    assert sorted(p.name for p in root.parent.iterdir()) == [root.name]  # no temporary folders left


def test_demo_dataset_reuses_a_complete_route():
    root = demo_dataset(n_frames=SMALL).root
    before = os.stat(root / MARKER)
    demo_dataset(n_frames=SMALL)
    after = os.stat(root / MARKER)
    assert (before.st_ino, before.st_mtime_ns) == (after.st_ino, after.st_mtime_ns)


def test_a_crash_while_writing_leaves_no_route(tmp_path, monkeypatch):
    calls = []
    real_save = demo._save_png

    def failing_save(image, path):
        calls.append(path)
        if len(calls) == 5:
            raise OSError("disk full")
        real_save(image, path)

    monkeypatch.setattr(demo, "_save_png", failing_save)
    with pytest.raises(OSError, match="disk full"):
        write_demo_route(tmp_path / "route", n_frames=SMALL)
    assert list(tmp_path.iterdir()) == []


def test_write_replaces_a_damaged_route_but_not_a_foreign_folder(tmp_path):
    root = write_demo_route(tmp_path / "route", n_frames=SMALL)
    _damage_frame(root)
    write_demo_route(root, n_frames=SMALL)
    assert route_is_complete(root, seed=DEMO_SEED, n_frames=SMALL)

    foreign = tmp_path / "photos"
    (foreign / "day").mkdir(parents=True)
    (foreign / "day" / "holiday.jpg").write_bytes(b"not ours")
    with pytest.raises(VPRInputError, match="photos"):
        write_demo_route(foreign, n_frames=SMALL)
    assert (foreign / "day" / "holiday.jpg").read_bytes() == b"not ours"


def test_a_marker_for_other_parameters_is_not_complete(tmp_path):
    root = write_demo_route(tmp_path / "route", seed=2, n_frames=SMALL)
    assert route_is_complete(root, seed=2, n_frames=SMALL)
    assert not route_is_complete(root, seed=3, n_frames=SMALL)
    assert not route_is_complete(root, seed=2, n_frames=SMALL + 1)


# --------------------------------------------------------------------------- bad parameters


BAD = [
    ("seed", {"seed": -1}),
    ("seed", {"seed": 1.5}),
    ("seed", {"seed": "0"}),
    ("seed", {"seed": True}),
    ("n_frames", {"n_frames": 9}),
    ("n_frames", {"n_frames": 10.0}),
    ("n_frames", {"n_frames": "60"}),
    ("n_frames", {"n_frames": demo.DEMO_MAX_FRAMES + 1}),
]


@pytest.mark.parametrize(("name", "kwargs"), BAD)
def test_bad_parameters_raise_naming_the_parameter(tmp_path, name, kwargs):
    with pytest.raises(VPRInputError, match=name):
        write_demo_route(tmp_path / "route", **kwargs)
    with pytest.raises(VPRInputError, match=name):
        demo_dataset(**kwargs)
    with pytest.raises(VPRInputError, match=name):
        demo_root(**kwargs)
    with pytest.raises(VPRInputError, match=name):
        next(render_frames(**kwargs))
    assert not (tmp_path / "route").exists()
    assert not (tmp_path / "cache").exists()


def test_stale_temporaries_of_killed_writers_are_removed(tmp_path):
    stale = tmp_path / ".route.tmp-dead"
    fresh = tmp_path / ".route.tmp-busy"
    for folder in (stale, fresh):
        (folder / "day").mkdir(parents=True)
    os.utime(stale, (0, 0))
    write_demo_route(tmp_path / "route", n_frames=SMALL)
    assert not stale.exists()
    assert fresh.exists()  # may belong to a writer still at work
