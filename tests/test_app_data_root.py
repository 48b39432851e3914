"""The app serves one data root: a link or a typed path opens only what lies under it, and nothing else is read.

Every refusal is checked by what the app did, not only by what it said: a process-wide audit
hook (``sys.addaudithook``, armed around each AppTest run) records every file the process
opens and every folder it lists, and a path outside the root must appear in neither. A
dataset and a descriptor file the app could open perfectly well lie just outside the root,
so an app that forgot the check would read them. The launcher (``vpr-explorer app``) is
checked by the root it plans, by what it refuses, and by one real server on every
interface, whose warning names the root.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from streamlit.testing.v1 import AppTest

from images import write_random_route
from streamlit_server import free_port, serving
from test_app import TIMEOUT, assert_clean
from test_app import fresh_caches, navigation_mode  # noqa: F401  (autouse fixtures: every AppTest here needs them)

from vpr_explorer.app import ENTRY
from vpr_explorer.data.traversals import load_dataset
from vpr_explorer.descriptors.imported import write_descriptor_file

ROOT_ENV = "VPR_EXPLORER_DATA_ROOT"  # spelled out: the app reads this variable (checked against the package below)
FRAMES = 12

# --------------------------------------------------------------------------- what the process touches

_touched: list[tuple[str, str]] | None = None


def _audit(event: str, args: tuple) -> None:
    """Record ``open`` and folder listings while armed (``touching``); every thread of the process reports here."""
    if _touched is None or event not in ("open", "os.listdir", "os.scandir"):
        return
    path = args[0] if args else None
    if path is None and event != "open":
        path = "."
    if isinstance(path, (str, bytes, os.PathLike)):
        _touched.append((event, os.path.abspath(os.fsdecode(path))))


sys.addaudithook(_audit)  # cannot be removed; disarmed it returns at once


@contextmanager
def touching() -> Iterator[list[tuple[str, str]]]:
    """The files opened and folders listed by this process (AppTest's script thread included) inside the block."""
    global _touched
    _touched = found = []
    try:
        yield found
    finally:
        _touched = None


def under(path: str, folder: Path) -> bool:
    """``path`` is ``folder`` or inside it, by name (nothing is looked up)."""
    return path == str(folder) or path.startswith(str(folder).rstrip("/") + "/")


def reached(found: list[tuple[str, str]], folder: Path, *, but: Path | None = None) -> list[tuple[str, str]]:
    """What was opened or listed in ``folder`` (outside ``but``), by the path it was reached through or the real one
    (a symbolic link out of ``but`` leads into ``folder``)."""
    real = [(event, os.path.realpath(path)) for event, path in found]
    return [(event, path) for event, path in {*found, *real} if under(path, folder) and not (but and under(path, but))]


# --------------------------------------------------------------------------- a root, and data just outside it


@pytest.fixture
def served(tmp_path: Path, monkeypatch) -> dict[str, Path]:
    """``root`` (the app's data root, holding ``route``) inside ``tmp_path``; beside it ``outside``, a route of its
    own with ``outside.npz``, its descriptors; ``root/escape`` a symbolic link to it and ``root/alias`` one to
    ``route``. The process runs in the root, so that a relative path means the same folder to an app without the
    check."""
    root = tmp_path / "data" / "root"
    route = write_random_route(root / "route", FRAMES, (64, 32))
    outside = write_random_route(tmp_path / "outside", FRAMES, (64, 32))
    ds = load_dataset(outside)
    d = np.random.default_rng(0).standard_normal((ds.n_images, 8)).astype(np.float32)
    npz = tmp_path / "outside.npz"
    write_descriptor_file(npz, d / np.linalg.norm(d, axis=1, keepdims=True), ds.image_paths, ds.root)
    (root / "escape").symlink_to(outside, target_is_directory=True)
    (root / "alias").symlink_to(route, target_is_directory=True)
    monkeypatch.setenv(ROOT_ENV, str(root))
    monkeypatch.chdir(root)
    return {"tmp": tmp_path, "root": root, "route": route, "outside": outside, "npz": npz}


def opened(**params: str) -> tuple[AppTest, list[tuple[str, str]]]:
    """The app on a link with ``params``, and what the process touched meanwhile."""
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT)
    at.query_params.update(params)
    with touching() as found:
        at.run()
    return at, found


def refused_once(at: AppTest, text: str, root: Path) -> None:
    """No exception, no error, one warning naming the path, the root and how to serve another folder."""
    assert_clean(at)
    assert len(at.warning) == 1, [w.value for w in at.warning]
    said = at.warning[0].value
    assert repr(text) in said and str(root) in said and "vpr-explorer app --data-root DIR" in said, said


# --------------------------------------------------------------------------- links outside the root


@pytest.mark.parametrize("source", ["/", "/etc", "../..", "escape", "{root}/escape", "{root}/../../outside"])
def test_a_link_outside_the_data_root_is_refused_and_nothing_of_it_is_read(served, source):
    text = source.format(root=served["root"])
    at, found = opened(source=text)
    assert not reached(found, served["tmp"], but=served["root"])  # ../.. and the outside route: nothing opened
    listed = [path for event, path in found if event != "open"]
    assert "/" not in listed and not [p for p in listed if under(p, Path("/etc"))], listed
    refused_once(at, text, served["root"])
    assert at.session_state["view"].source == "demo" and "source" not in at.query_params  # the default
    assert any("descriptors ready: 180 × 2048" in s.value for s in at.success)  # the demo route instead
    body = " ".join(c.value for c in at.caption)
    assert str(served["outside"]) not in body and "/etc" not in body


def test_a_descriptor_file_outside_the_data_root_is_refused_unread(served):
    npz = served["npz"]
    at, found = opened(source=str(served["route"]), descriptors=str(npz), descriptor=npz.stem)
    assert not [path for _, path in found if path == str(npz)]
    refused_once(at, str(npz), served["root"])
    v = at.session_state["view"]
    assert v.source == str(served["route"]) and v.descriptors is None and v.descriptor == "pixels"
    assert "descriptors" not in at.query_params
    assert any(f"pixels descriptors ready: {2 * FRAMES} × 2048" in s.value for s in at.success)


def test_descriptors_naming_a_system_file_are_refused_unread(served):
    at, found = opened(descriptors="/etc/passwd.npy")
    assert not [path for _, path in found if path.startswith("/etc/passwd")]
    refused_once(at, "/etc/passwd.npy", served["root"])
    assert at.session_state["view"].descriptors is None


# --------------------------------------------------------------------------- what lies under it


@pytest.mark.parametrize("source", ["route", "{root}/route", "alias", "{root}/route/../route"])
def test_a_link_under_the_data_root_opens_it(served, source):
    at, found = opened(source=source.format(root=served["root"]))
    assert_clean(at)
    assert not at.warning, [w.value for w in at.warning]
    route = str(served["route"])
    assert at.session_state["view"].source == route and at.query_params["source"] == route  # resolved
    assert any(f"pixels descriptors ready: {2 * FRAMES} × 2048" in s.value for s in at.success)
    assert any(s.value.startswith("route: 2 traversals") for s in at.subheader)
    assert reached(found, served["route"])  # it was read: the audit sees the app's reads
    assert not reached(found, served["outside"])


@pytest.mark.parametrize("escape", ["../../outside/day/frame_00.png", "{outside}/day/frame_00.png"])
def test_a_manifest_under_the_root_naming_images_outside_it_is_refused_unread(served, escape):
    root, outside = served["root"], served["outside"]
    rows = ["path,role,place"]
    rows += [f"route/day/frame_{f:02d}.png,database,{f}" for f in range(FRAMES)]
    rows += [f"route/night/frame_{f:02d}.png,query,{f}" for f in range(FRAMES - 1)]
    rows.append(f"{escape.format(outside=outside)},query,3")
    (root / "manifest.csv").write_text("\n".join(rows) + "\n")
    at, found = opened(source=str(root / "manifest.csv"))
    assert not reached(found, served["tmp"], but=root)  # the outside image is not even looked at
    assert not at.exception and len(at.error) == 1, [e.value for e in at.error]
    said = at.error[0].value
    assert f"manifest.csv: line {FRAMES * 2 + 1}:" in said and f"is not under {root}" in said, said

    # the same manifest with every image inside the root opens
    (root / "manifest.csv").write_text("\n".join(rows[:-1]) + "\n")
    at, _ = opened(source=str(root / "manifest.csv"))
    assert_clean(at)


def test_the_demo_route_opens_wherever_the_root_is(served):
    at, _ = opened(source="demo")
    assert_clean(at)
    assert not at.warning and at.session_state["view"].source == "demo"
    assert any("descriptors ready: 180 × 2048" in s.value for s in at.success)


def test_the_dataset_page_lists_only_what_lies_under_the_root(served):
    (served["root"] / ".hidden").mkdir()
    at, found = opened()
    assert_clean(at)
    options = at.selectbox(key="w_source").options
    # the route once (its alias resolves to it), not the link out of the root, not a hidden folder
    assert options == ["Built-in demo route (drawn street, 3 conditions)", "route  (under the data root)",
                       "A folder path…"], options
    assert not reached(found, served["outside"])


@pytest.mark.parametrize("typed", ["/etc", "../../outside", "escape"])
def test_a_typed_folder_outside_the_root_is_refused_unread(served, typed):
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT).run()
    at.selectbox(key="w_source").set_value("__folder__").run()
    with touching() as found:
        at.text_input(key="w_folder").input(typed).run()
    assert not reached(found, served["tmp"], but=served["root"])
    assert not [path for event, path in found if event != "open" and under(path, Path("/etc"))]
    assert_clean(at)
    assert len(at.warning) == 1 and typed in at.warning[0].value and str(served["root"]) in at.warning[0].value
    assert at.session_state["view"].source == "demo"
    at.text_input(key="w_folder").input("route").run()  # relative to the root
    assert_clean(at)
    assert not at.warning and at.session_state["view"].source == str(served["route"])


def test_a_typed_descriptor_file_outside_the_root_is_refused_unread(served):
    npz = served["npz"]
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT).run()
    at.radio(key="w_descriptor").set_value("__file__").run()
    with touching() as found:
        at.text_input(key="w_descriptor_file").input(str(npz)).run()
    assert not [path for _, path in found if path == str(npz)]
    assert_clean(at)
    assert len(at.warning) == 1 and str(npz) in at.warning[0].value
    assert at.session_state["view"].descriptors is None


def test_the_root_comes_from_its_variable_else_the_data_folder_else_here(tmp_path, monkeypatch):
    from vpr_explorer.app import DATA_ROOT_ENV, data_root
    from vpr_explorer.settings import DATA_ENV

    assert DATA_ROOT_ENV == ROOT_ENV
    a, b = tmp_path / "a", tmp_path / "b"
    monkeypatch.chdir(tmp_path)
    assert data_root({DATA_ROOT_ENV: "a", DATA_ENV: str(b)}) == a
    assert data_root({DATA_ENV: str(b)}) == b
    assert data_root({DATA_ROOT_ENV: " ", DATA_ENV: ""}) == tmp_path


def test_the_root_check_at_its_boundaries(tmp_path):
    from vpr_explorer.app import OutsideDataRoot, under_data_root
    from vpr_explorer.errors import VPRInputError

    root = tmp_path / "data"
    (root / "x").mkdir(parents=True)
    (tmp_path / "data2").mkdir()  # shares the root's name as a prefix
    (root / "loop").symlink_to(root / "loop")
    assert under_data_root(root, root) == root  # the root itself
    assert under_data_root("x/../x", root) == root / "x"
    assert under_data_root("not-there-yet", root) == root / "not-there-yet"  # refusal does not depend on existence
    for outside in (tmp_path / "data2", "../data2", "..", tmp_path / "data" / ".." / "data2"):
        with pytest.raises(OutsideDataRoot, match="not under the app's data root"):
            under_data_root(outside, root)
    with pytest.raises(VPRInputError, match="a loop of symbolic links"):
        under_data_root("loop", root)
    with pytest.raises(VPRInputError, match="NUL"):
        under_data_root("x\x00", root)


# --------------------------------------------------------------------------- the launcher


def test_the_launcher_serves_the_folder_holding_the_dataset(tmp_path, monkeypatch):
    from vpr_explorer.app.launch import plan
    from vpr_explorer.settings import DATA_ENV

    route = write_random_route(tmp_path / "data" / "route", 2, (16, 8))
    manifest = tmp_path / "data" / "m" / "manifest.csv"
    manifest.parent.mkdir()
    manifest.write_text("path,role,place\n")
    assert plan(dataset=str(route)).data_root == tmp_path / "data"  # a folder: its neighbours open too
    assert plan(dataset=str(manifest)).data_root == manifest.parent  # a manifest: its own folder
    assert plan(dataset="/tmp").data_root == Path("/tmp").resolve()  # its parent is / : the folder itself
    launch = plan(dataset=str(route), data_root=str(route))  # given: the root itself may be the dataset
    assert launch.data_root == route and launch.env[ROOT_ENV] == str(route)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv(DATA_ENV, str(route))
    assert plan(dataset="demo").data_root == route and plan().data_root == route
    monkeypatch.delenv(DATA_ENV)
    assert plan().data_root == tmp_path and plan(data_root="data").data_root == tmp_path / "data"


@pytest.mark.parametrize("case, says", [
    ("outside", "--dataset {outside}: not under --data-root {root}"),
    ("escape", "--dataset {outside}: not under --data-root {root}"),  # a link out of the root, resolved
    ("missing root", "--data-root {tmp}/nope: no such folder"),
])
def test_a_dataset_outside_the_given_root_is_refused_by_name(tmp_path, case, says):
    from vpr_explorer.app.launch import plan
    from vpr_explorer.errors import VPRInputError

    root = tmp_path / "root"
    root.mkdir()
    outside = write_random_route(tmp_path / "outside", 2, (16, 8))
    (root / "escape").symlink_to(outside, target_is_directory=True)
    dataset = {"outside": outside, "escape": root / "escape", "missing root": outside}[case]
    given = tmp_path / "nope" if case == "missing root" else root
    with pytest.raises(VPRInputError, match=says.format(outside=outside, root=root, tmp=tmp_path)):
        plan(dataset=str(dataset), data_root=given)


def test_only_loopback_addresses_go_without_a_warning(tmp_path):
    from vpr_explorer.app.launch import exposure_warning, plan

    for address in ("127.0.0.1", "127.255.0.9", "::1", "[::1]", "localhost"):
        assert exposure_warning(address, 8501, tmp_path) is None, address
        assert plan(address=address, data_root=tmp_path).warning is None
    for address in ("0.0.0.0", "", "::", "192.168.1.7", "128.0.0.1", "example.org"):
        said = exposure_warning(address, 8501, tmp_path)
        assert said is not None and "anyone who can reach port 8501 can browse the data root" in said, address
        assert str(tmp_path) in said
    assert plan(address="0.0.0.0", port=9001, data_root=tmp_path).warning == exposure_warning("0.0.0.0", 9001, tmp_path)


def test_a_server_on_every_interface_prints_who_can_browse_the_root(tmp_path):
    port = free_port()
    command = [sys.executable, "-m", "vpr_explorer.cli", "app", "--address", "0.0.0.0", "--headless",
               "--port", str(port), "--data-root", str(tmp_path)]
    with serving(command, port, cwd=tmp_path) as output:
        lines = output().splitlines()
    assert f"  data root: {tmp_path} (a link opens only datasets and descriptor files under it; --data-root)" in lines
    warning = [line for line in lines if line.startswith("warning: --address 0.0.0.0")]
    assert warning == [f"warning: --address 0.0.0.0 is not loopback: anyone who can reach port {port} can browse the "
                       f"data root {tmp_path} (every dataset and descriptor file under it); the default 127.0.0.1 "
                       "serves this machine only"], lines
