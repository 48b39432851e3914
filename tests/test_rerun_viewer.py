"""The Playback page's viewer component (``app/ui/rerun_viewer.py``): its folder of files and the cursor it reports.

The folder is checked on stand-in files (a fake rerun-notebook ``static/`` folder) and on
the installed rerun-notebook: hard links where possible, a copy otherwise, one folder per
rerun-notebook version and page, built once, a crashed writer's partial folder never used,
a racing writer's folder taken as it is. The cursor is checked on hand-written values, the
seeks on hand-written requests and a plain loop that counts their tokens, and the Playback
page (AppTest) on what it embeds: the component with the recording's arguments (a number put
in the query box sent once as a seek), or, without rerun-notebook, rerun's own web viewer and
the reason.
"""

from __future__ import annotations

import hashlib
import json
import importlib.metadata
import importlib.util
import os
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from test_app import app, fresh_caches, navigation_mode  # noqa: F401  (fixtures)
from vpr_explorer.app.ui import rerun_viewer
from vpr_explorer.app.ui.rerun_viewer import (ASSETS, FOLDER, INDEX, Cursor, Seek, component_folder, next_seek,
                                              notebook_static)
from vpr_explorer.errors import VPRInputError
from vpr_explorer.settings import host_tag, temporary_name

VERSION = importlib.metadata.version("rerun-notebook")
NAMES = ("index.html", *ASSETS)


@pytest.fixture
def static(tmp_path) -> Path:
    """A stand-in for rerun-notebook's ``static/``: the three files, with distinct contents."""
    folder = tmp_path / "static"
    folder.mkdir()
    for i, name in enumerate(ASSETS):
        (folder / name).write_bytes(f"{name} {i}\n".encode() * (i + 1))
    return folder


@pytest.fixture
def index(tmp_path) -> Path:
    page = tmp_path / "index.html"
    page.write_text("<!doctype html><p>viewer</p>\n")
    return page


def _key(index: Path) -> str:
    return f"{VERSION}-{hashlib.sha256(index.read_bytes()).hexdigest()[:12]}"


def _sources(static: Path, index: Path) -> dict[str, Path]:
    return {"index.html": index, **{name: static / name for name in ASSETS}}


def test_the_folder_holds_hard_links_named_by_version_and_page(tmp_path, static, index):
    root = tmp_path / "cache"
    folder = component_folder(static, root=root, index=index)
    assert folder == root / FOLDER / _key(index)
    assert sorted(p.name for p in folder.iterdir()) == sorted(NAMES)
    for name, src in _sources(static, index).items():
        assert (folder / name).read_bytes() == src.read_bytes()
        # rerun-notebook's files hard links (no second copy of the 66 MB wasm); the page a copy
        assert os.path.samefile(folder / name, src) == (name != "index.html")
    assert [p.name for p in (root / FOLDER).iterdir()] == [folder.name]  # no temporary left


def test_a_copy_where_a_link_cannot_be_made(tmp_path, static, index, monkeypatch):
    def refuse(src, dst):
        raise OSError(18, "Invalid cross-device link")

    monkeypatch.setattr(os, "link", refuse)
    folder = component_folder(static, root=tmp_path / "cache", index=index)
    for name, src in _sources(static, index).items():
        assert (folder / name).read_bytes() == src.read_bytes()
        assert not os.path.samefile(folder / name, src)


def test_built_once_then_reused_as_it_is(tmp_path, static, index, monkeypatch):
    root = tmp_path / "cache"
    first = component_folder(static, root=root, index=index)
    before = {name: (first / name).stat().st_ino for name in NAMES}
    calls = []
    monkeypatch.setattr(rerun_viewer, "_place", lambda src, dst: calls.append(dst))
    monkeypatch.setattr(rerun_viewer.shutil, "copyfile", lambda src, dst: calls.append(dst))
    assert component_folder(static, root=root, index=index) == first
    assert calls == []
    assert {name: (first / name).stat().st_ino for name in NAMES} == before


def test_another_page_or_version_is_another_folder(tmp_path, static, index, monkeypatch):
    root = tmp_path / "cache"
    first = component_folder(static, root=root, index=index)
    index.write_text("<!doctype html><p>viewer, changed</p>\n")
    second = component_folder(static, root=root, index=index)
    assert second != first and second.name == _key(index)
    assert (second / "index.html").read_text().endswith("changed</p>\n")
    assert (first / "index.html").read_text().endswith("viewer</p>\n")  # the older one left as it was

    real = importlib.metadata.version
    monkeypatch.setattr(importlib.metadata, "version", lambda name: "9.9.9" if name == "rerun-notebook" else real(name))
    third = component_folder(static, root=root, index=index)
    assert third.name.startswith("9.9.9-") and third.parent == first.parent


def test_a_crashed_writers_partial_folder_is_never_used_and_goes_once_stale(tmp_path, static, index):
    root = tmp_path / "cache"
    parent = root / FOLDER
    parent.mkdir(parents=True)
    # A writer killed mid-way: its temporary holds only the page. Its pid is of a process that has exited.
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    pid = int(dead.stdout)
    partial = parent / f".{_key(index)}.{host_tag()}.{pid}.{'0' * 32}.tmp"
    partial.mkdir()
    (partial / "index.html").write_bytes(index.read_bytes())
    old = time.time() - 3600
    os.utime(partial, (old, old))
    # A live writer's temporary (this process) is kept, whatever its age.
    live = parent / temporary_name(_key(index))
    live.mkdir()
    os.utime(live, (old, old))

    folder = component_folder(static, root=root, index=index)
    assert folder == parent / _key(index)
    assert sorted(p.name for p in folder.iterdir()) == sorted(NAMES)
    assert not partial.exists()
    assert live.exists()


def test_an_incomplete_folder_in_place_is_replaced(tmp_path, static, index):
    root = tmp_path / "cache"
    folder = component_folder(static, root=root, index=index)
    (folder / "re_viewer_bg.wasm").unlink()
    (folder / "widget.js").write_bytes(b"cut")
    again = component_folder(static, root=root, index=index)
    assert again == folder
    for name, src in _sources(static, index).items():
        assert (folder / name).read_bytes() == src.read_bytes()
    assert [p.name for p in (root / FOLDER).iterdir()] == [folder.name]


def test_a_racing_writer_that_wins_is_taken_as_it_is(tmp_path, static, index, monkeypatch):
    root = tmp_path / "cache"
    place = rerun_viewer._place
    winner = {}

    def race(src, dst):
        if not winner:  # the other process finishes first, while this one is still linking
            monkeypatch.setattr(rerun_viewer, "_place", place)
            winner["folder"] = component_folder(static, root=root, index=index)
            winner["inodes"] = {n: (winner["folder"] / n).stat().st_ino for n in NAMES}
            monkeypatch.setattr(rerun_viewer, "_place", race)
        place(src, dst)

    monkeypatch.setattr(rerun_viewer, "_place", race)
    folder = component_folder(static, root=root, index=index)
    assert folder == winner["folder"]
    assert {n: (folder / n).stat().st_ino for n in NAMES} == winner["inodes"]  # not written over
    assert [p.name for p in (root / FOLDER).iterdir()] == [folder.name]


def test_processes_racing_all_end_with_one_complete_folder(tmp_path):
    root = tmp_path / "cache"
    code = ("import sys; from pathlib import Path; from vpr_explorer.app.ui.rerun_viewer import component_folder; "
            "print(component_folder(root=Path(sys.argv[1])))")
    procs = [subprocess.Popen([sys.executable, "-c", code, str(root)], stdout=subprocess.PIPE, text=True)
             for _ in range(4)]
    outs = {p.communicate(timeout=120)[0].strip() for p in procs}
    assert all(p.returncode == 0 for p in procs)
    (folder,) = map(Path, outs)
    static = notebook_static()
    for name, src in _sources(static, INDEX).items():
        assert (folder / name).stat().st_size == src.stat().st_size
    assert [p.name for p in (root / FOLDER).iterdir()] == [folder.name]


def test_the_installed_rerun_notebook_gives_every_asset():
    static = notebook_static()
    assert static == Path(importlib.util.find_spec("rerun_notebook").submodule_search_locations[0]) / "static"
    assert (static / "re_viewer_bg.wasm").stat().st_size > 10_000_000
    assert "export" in (static / "widget.js").read_text()[-200:]
    assert importlib.metadata.version("rerun-notebook") == importlib.metadata.version("rerun-sdk")


def test_no_rerun_notebook_is_an_input_error_naming_the_install(monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "rerun_notebook" else real(name, *a))
    with pytest.raises(VPRInputError, match=r"rerun-notebook is not installed: pip install 'rerun-sdk\[notebook\]"):
        notebook_static()


def test_missing_assets_are_an_input_error_naming_them(tmp_path, monkeypatch):
    package = tmp_path / "rerun_notebook"
    (package / "static").mkdir(parents=True)
    (package / "static" / "widget.js").write_text("export default {}")

    class Spec:
        submodule_search_locations = [str(package)]

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: Spec() if name == "rerun_notebook" else real(name, *a))
    with pytest.raises(VPRInputError, match="lacks widget.css, re_viewer_bg.wasm"):
        notebook_static()


def test_the_page_is_package_data_beside_the_app():
    assert INDEX.is_file()
    text = INDEX.read_text()
    for needed in ("streamlit:componentReady", "streamlit:render", "streamlit:setComponentValue",
                   "streamlit:setFrameHeight", "./widget.js", "./widget.css"):
        assert needed in text


RID = "0123456789abcdef0123456789abcdef"


@pytest.mark.parametrize("value", [
    None, "17", [17], {}, {"recording_id": RID, "timeline": "query"}, {"recording_id": 3, "timeline": "query", "time": 1},
    {"recording_id": RID, "timeline": 4, "time": 1}, {"recording_id": RID, "timeline": "query", "time": "1"},
    {"recording_id": RID, "timeline": "query", "time": True},
])
def test_anything_but_a_cursor_value_is_no_cursor(value):
    assert Cursor.from_value(value) is None


def test_a_cursor_value_and_its_position_on_the_recording():
    value = {"recording_id": RID, "timeline": "query", "time": 17, "id": "ab12:3"}
    cursor = Cursor.from_value(value)
    assert cursor == Cursor(RID, "query", 17.0)
    assert cursor.position(RID, "query", 60) == 17
    assert cursor.position("another", "query", 60) is None  # another recording picked in the viewer
    assert Cursor(RID, "log_time", 17.0).position(RID, "query", 60) is None  # another timeline
    assert Cursor(RID, None, 17.0).position(RID, "query", 60) == 17  # not said yet: the blueprint's
    assert Cursor(RID, "query", 16.6).position(RID, "query", 60) == 17
    assert Cursor(RID, "query", 59.0).position(RID, "query", 60) == 59  # the last query
    assert Cursor(RID, "query", 75.0).position(RID, "query", 60) == 59  # past the end: the nearest end
    assert Cursor(RID, "query", -2.0).position(RID, "query", 60) == 0
    assert Cursor(RID, "query", float("nan")).position(RID, "query", 60) is None
    assert Cursor(RID, "query", 0.0).position(RID, "query", 0) is None  # an empty recording


def test_a_request_is_a_fresh_seek_unless_a_cursor_came_with_it():
    assert next_seek(None, None, False) is None  # nothing asked: no seek
    assert next_seek(None, None, True) is None
    first = next_seek(None, 17, False)
    assert first == Seek(1, 17) and first.to_arg() == [1, 17]
    assert next_seek(first, None, False) is first  # a rerun asking nothing sends the same token: no move
    assert next_seek(first, None, True) is first  # the cursor's own reruns (playing, dragging): no move
    assert next_seek(first, 17, False) == Seek(2, 17)  # the same number asked again is a fresh seek
    assert next_seek(Seek(7, 3), 0, False) == Seek(8, 0)  # the timeline's start
    assert next_seek(first, 5, True) is first  # asked with a cursor: the cursor's echo, not sought
    assert next_seek(None, 5, True) is None
    with pytest.raises(VPRInputError, match=r"seek: position -1 .* 0 or more"):
        next_seek(first, -1, False)


def test_tokens_count_up_one_per_request():
    """The tokens of a run of requests, against a plain loop: one more per request not echoed."""
    asked = [(None, False), (4, False), (None, True), (9, True), (9, False), (None, False), (0, False), (2, True)]
    seek, token, sent = None, 0, []
    for requested, moved in asked:
        seek = next_seek(seek, requested, moved)
        if requested is not None and not moved:
            token += 1
        sent.append(None if seek is None else seek.to_arg())
        assert seek is None or seek.token == token
    assert sent == [None, [1, 4], [1, 4], [1, 4], [2, 9], [2, 9], [3, 0], [3, 0]]


def test_the_viewer_sends_a_request_once_and_a_cursor_holds_over_its_echo(monkeypatch):
    """``viewer``'s wiring, on a stand-in session state and component: what each draw sends, and who wins."""
    session: dict[str, object] = {}
    drawn: list[dict] = []

    def draw(**kwargs):
        drawn.append(kwargs)
        return session.get(kwargs["key"])

    monkeypatch.setattr(rerun_viewer, "st", SimpleNamespace(session_state=session))
    monkeypatch.setattr(rerun_viewer, "_component", lambda: draw)
    frames: list[int] = []

    def show() -> None:
        rerun_viewer.viewer("rerun+http://127.0.0.1:1/proxy", RID, timeline="query", height=600, key="v",
                            sequence=9, on_cursor=lambda c: frames.append(c.position(RID, "query", 60)))

    show()
    assert drawn[-1]["seek"] is None and drawn[-1]["sequence"] == 9
    rerun_viewer.request_seek("v", 40)  # the user typed 40 into the box
    show()
    assert drawn[-1]["seek"] == [1, 40] and frames == []
    show()  # a rerun asking nothing
    assert drawn[-1]["seek"] == [1, 40]
    # A cursor comes (23) with the box's stale value in the same rerun: no seek, the cursor told twice.
    session["v"] = {"recording_id": RID, "timeline": "query", "time": 23, "id": "ab:1"}
    drawn[-1]["on_change"]()
    rerun_viewer.request_seek("v", 9)
    show()
    assert drawn[-1]["seek"] == [1, 40] and frames == [23, 23]
    session["v"] = {"recording_id": RID, "timeline": "query", "time": 30, "id": "ab:2"}
    drawn[-1]["on_change"]()  # playing on: reruns with no request
    show()
    assert drawn[-1]["seek"] == [1, 40] and frames == [23, 23, 30]
    rerun_viewer.request_seek("v", 12)  # the next rerun holds only the user's number: sought
    show()
    assert drawn[-1]["seek"] == [2, 12] and frames == [23, 23, 30]
    assert set(session) == {"v", "v" + rerun_viewer.SEEK}  # the request and the cursor's mark are spent


# --------------------------------------------------------------------------- the page without the component (AppTest)


def _playback(at):
    from vpr_explorer.app import PAGES

    at = at.switch_page(str(PAGES / "playback.py")).run()
    at.button[0].click().run()
    assert not at.exception
    return at


def test_the_page_embeds_the_component_with_the_recording(app):
    at = _playback(app.run())
    (component,) = at.get("component_instance")
    assert not at.get("iframe")
    args = json.loads(component.proto.json_args)
    playback = at.session_state["playback"]
    assert args["recording_id"] == playback.recording_id and args["timeline"] == "query"
    assert args["grpc_url"].startswith("rerun+http://127.0.0.1:") and args["grpc_url"].endswith("/proxy")
    assert args["sequence"] == at.number_input(key="w_playback_frame").value  # the viewer starts at the box
    assert args["seek"] is None  # nothing asked of the cursor yet


def test_a_number_put_in_the_box_is_sent_to_the_viewer_once_as_a_seek(app):
    at = _playback(app.run())
    at.number_input(key="w_playback_frame").set_value(17).run()
    (component,) = at.get("component_instance")
    assert json.loads(component.proto.json_args)["seek"] == [1, 17]
    assert at.session_state["view"].frame == 17
    at.run()  # a rerun that asks nothing repeats the token: the viewer does not move
    (component,) = at.get("component_instance")
    assert json.loads(component.proto.json_args)["seek"] == [1, 17]
    at.number_input(key="w_playback_frame").increment().run()  # the stepper seeks too
    (component,) = at.get("component_instance")
    assert json.loads(component.proto.json_args)["seek"] == [2, 18]
    assert at.session_state["view"].frame == 18 and not at.exception


def test_without_rerun_notebook_the_page_shows_rerun_s_own_viewer_and_says_why(app, monkeypatch):
    def missing() -> Path:
        raise VPRInputError("rerun-notebook is not installed: pip install 'rerun-sdk[notebook]>=0.41,<0.42'")

    monkeypatch.setattr(rerun_viewer, "notebook_static", missing)
    at = _playback(app.run())
    assert not at.get("component_instance")
    (iframe,) = at.get("iframe")
    assert iframe.proto.src == at.session_state["playback"].viewer_url
    told = " ".join(c.value for c in at.caption)
    assert "rerun-notebook is not installed" in told and "does not follow the cursor" in told
    assert at.get("download_button")
