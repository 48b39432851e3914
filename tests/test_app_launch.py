"""The packaged app: what ``vpr-explorer app`` starts, the view it opens, the checkout's thin entry points.

The launcher is checked by the command it plans (no server here; ``test_installed_app``
starts one from an installed wheel); the app by AppTest on the packaged entry script, as
it runs under the environment the launcher gives it.
"""

from __future__ import annotations

import ast
import sys
import tomllib
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import numpy as np
import pytest
from streamlit.testing.v1 import AppTest

from images import write_random_route
from test_app import ROOT, TIMEOUT, assert_clean, metric, page
from test_app import fresh_caches, navigation_mode  # noqa: F401  (autouse fixtures: every AppTest here needs them)

from vpr_explorer.app import DATA_ROOT_ENV, DATASET_ENV, DESCRIPTORS_ENV, ENTRY, PAGES, started_view
from vpr_explorer.app.launch import SETTINGS, plan
from vpr_explorer.data.traversals import load_dataset
from vpr_explorer.descriptors.imported import write_descriptor_file
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import make_places

FRAMES = 24


@pytest.fixture
def route(tmp_path: Path) -> Path:
    """A two-traversal dataset folder of small random PNGs."""
    return write_random_route(tmp_path / "route", FRAMES, (64, 32))


@pytest.fixture
def mine(route: Path, tmp_path: Path) -> Path:
    """``mine.npz``: random 16-D descriptors of ``route``'s images, as if computed elsewhere."""
    ds = load_dataset(route)
    d = np.random.default_rng(0).standard_normal((ds.n_images, 16)).astype(np.float32)
    path = tmp_path / "mine.npz"
    write_descriptor_file(path, d / np.linalg.norm(d, axis=1, keepdims=True), ds.image_paths, ds.root)
    return path


def flags(argv) -> dict[str, str]:
    """``--name value`` pairs after ``streamlit run SCRIPT``."""
    rest = list(argv[5:])
    return dict(zip(rest[::2], rest[1::2], strict=True))


# --------------------------------------------------------------------------- the launcher


def test_the_launcher_serves_the_packaged_entry_on_this_machine_only(route):
    launch = plan(dataset=str(route), port=8765)
    assert launch.argv[:5] == (sys.executable, "-m", "streamlit", "run", str(ENTRY))
    assert ENTRY.is_file() and ENTRY.parent.parent.name == "vpr_explorer"
    f = flags(launch.argv)
    assert f["--server.address"] == "127.0.0.1" and f["--server.port"] == "8765"
    assert "--server.headless" not in f  # Streamlit opens a browser unless asked not to
    assert flags(plan(headless=True).argv)["--server.headless"] == "true"
    assert launch.env == {DATASET_ENV: str(route), DATA_ROOT_ENV: str(route.parent)}  # its neighbours open too
    url = urlsplit(launch.url)
    assert (url.scheme, url.netloc, url.path, parse_qs(url.query)) == ("http", "127.0.0.1:8765", "/",
                                                                       {"source": [str(route)]})
    assert plan().url == "http://127.0.0.1:8501/" and set(plan().env) == {DATA_ROOT_ENV}


def test_the_link_holds_the_started_view_and_a_reachable_host(route, mine, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    launch = plan(dataset="route", descriptors=Path("mine.npz"), address="0.0.0.0")
    assert launch.env == {DATASET_ENV: str(route), DESCRIPTORS_ENV: str(mine),  # absolute: any directory
                          DATA_ROOT_ENV: str(tmp_path)}
    url = urlsplit(launch.url)
    assert url.netloc == "127.0.0.1:8501"  # every interface: this machine's is one of them
    assert {k: v[0] for k, v in parse_qs(url.query).items()} == {"source": str(route), "descriptor": "mine"}
    assert started_view(launch.env) == {"source": str(route), "descriptor": "mine"}
    assert urlsplit(plan(address="::1", port=9000).url).netloc == "[::1]:9000"
    assert flags(plan(dataset="demo").argv) and plan(dataset="demo").env == {DATASET_ENV: "demo",
                                                                             DATA_ROOT_ENV: str(plan().data_root)}


def toml_flag(value) -> str:
    """A config.toml value as Streamlit's command line writes it (``true``, ``none``, ``8501``)."""
    return str(value).lower() if isinstance(value, bool) else str(value)


def test_the_checkouts_streamlit_settings_travel_as_flags():
    """``.streamlit/config.toml`` is read from the current directory only: the launcher passes the same settings.

    Both ways: ``streamlit run app.py`` in a checkout gets every setting ``vpr-explorer app``
    passes (no file watcher among them), and the launcher passes every one the file sets.
    """
    config = tomllib.loads((ROOT / ".streamlit" / "config.toml").read_text())
    in_file = {f"{section}.{name}": toml_flag(value) for section, values in config.items()
               for name, value in values.items()}
    assert in_file == SETTINGS
    assert in_file["server.fileWatcherType"] == "none"
    f = flags(plan().argv)
    assert all(f[f"--{name}"] == value for name, value in SETTINGS.items())


@pytest.mark.parametrize("options, says", [
    (dict(dataset="no/such/folder"), "--dataset no/such/folder: no such folder"),
    (dict(dataset="demo", descriptors=Path("missing.npz")), "--descriptors missing.npz: no such file"),
    (dict(dataset="demo", descriptors=Path("table.csv")), "unknown descriptor file extension '.csv'"),
    (dict(dataset="demo", descriptors=Path("pixels.npz")), "'pixels' names a built-in descriptor; rename the file"),
    (dict(descriptors=Path("pixels.npz")), "--descriptors pixels.npz: give the --dataset its rows describe too"),
    (dict(port=0), "--port 0: choose a port from 1 to 65535"),
])
def test_bad_options_are_refused_naming_them(tmp_path, monkeypatch, options, says):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pixels.npz").write_bytes(b"")
    with pytest.raises(VPRInputError, match=says.replace("(", r"\(").replace(".", r"\.")):
        plan(**options)


# --------------------------------------------------------------------------- the app it starts


def test_the_app_opens_the_dataset_and_descriptor_file_it_was_started_on(route, mine, monkeypatch):
    for name, value in plan(dataset=str(route), descriptors=mine).env.items():
        monkeypatch.setenv(name, value)
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT).run()
    assert_clean(at)
    assert at.selectbox(key="w_source").value == str(route)  # listed: the data root is the folder holding it
    assert at.radio(key="w_descriptor").value == "mine" and "pixels" in at.radio(key="w_descriptor").options
    assert any(f"mine descriptors ready: {2 * FRAMES} × 16 (read from {mine}" in s.value for s in at.success)
    assert at.query_params["source"] == str(route) and at.query_params["descriptor"] == "mine"
    page(at, "places")
    assert_clean(at)
    ds = load_dataset(route)
    assert metric(at, "places") == str(make_places(ds, None if ds.prepared_places else _spec(at)).n_places)

    # A link naming another view wins over the one the app was started on.
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT)
    at.query_params.update(source="demo", descriptor="pixels")
    at.run()
    assert_clean(at)
    assert at.selectbox(key="w_source").value == "demo" and at.radio(key="w_descriptor").value == "pixels"


def _spec(at: AppTest):
    from vpr_explorer.method.places import PlaceSpec

    return PlaceSpec(at.slider(key="w_group").value, at.slider(key="w_step").value)


def test_a_descriptor_file_for_other_images_is_an_error_not_a_crash(route, mine, monkeypatch):
    monkeypatch.setenv(DESCRIPTORS_ENV, str(mine))  # the demo route: none of its images are in the file
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT).run()
    assert_clean(at, errors=True)
    assert at.selectbox(key="w_source").value == "demo" and at.radio(key="w_descriptor").value == "mine"
    assert any("mine.npz" in e.value for e in at.error)


# --------------------------------------------------------------------------- the checkout's entry points


def test_the_checkouts_app_py_runs_the_packaged_app():
    at = AppTest.from_file(str(ROOT / "app.py"), default_timeout=TIMEOUT).run()
    assert_clean(at)
    assert any("descriptors ready: 180 × 2048" in s.value for s in at.success)
    assert "Looking at" in " ".join(c.value for c in at.sidebar.caption)
    for name in ("places", "evaluation", "home"):
        page(at, name)
        assert_clean(at)
        assert at.title[0].value


def _body(path: Path) -> list[ast.stmt]:
    body = ast.parse(path.read_text()).body
    return body[1:] if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) else body


def test_the_checkouts_app_py_and_pages_are_thin():
    """Nothing the app needs lives outside the package: the checkout's files only hand over to it."""
    from vpr_explorer.app import explorer

    packaged = sorted(p.stem for p in PAGES.glob("*.py"))
    assert packaged == sorted(name for name, _, _ in explorer.PAGES)
    assert sorted(p.stem for p in (ROOT / "pages").glob("*.py")) == packaged
    for path in [ROOT / "app.py", *(ROOT / "pages").glob("*.py")]:
        body = _body(path)
        assert len(body) == 2 and isinstance(body[0], ast.ImportFrom), path  # one import, one call
        assert body[0].module.startswith("vpr_explorer.app"), path
    assert not (ROOT / "ui").exists()


def test_only_the_app_imports_streamlit():
    """The library never imports streamlit; the app's launcher neither (the command line imports it)."""
    package = ROOT / "vpr_explorer"
    app = package / "app"
    for path in package.rglob("*.py"):
        if app in path.parents and path not in (app / "__init__.py", app / "launch.py"):
            continue
        names = [a.name for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, ast.Import) for a in n.names]
        names += [n.module or "" for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, ast.ImportFrom)]
        assert not any(name.split(".")[0] == "streamlit" for name in names), path
