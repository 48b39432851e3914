"""Shared fixtures: the real datasets (through VPR_EXPLORER_DATA), the demo route and an isolated cache.

Real-data tests skip with a clear reason when ``VPR_EXPLORER_DATA`` is unset (or fail, with
``--require-data``). ``.ci/run`` sets it and fails the run when any test is skipped, so CI
never skips them.

The app's data root (``VPR_EXPLORER_DATA_ROOT``) is, for the session, the nearest folder that
holds both pytest's temporary folders (where tests write datasets) and the real datasets:
the app tests open both. The tests of the data root itself (``test_app_data_root.py``) set
their own.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from vpr_explorer.app import DATA_ROOT_ENV
from vpr_explorer.settings import CACHE_ENV, DATA_ENV


def pytest_addoption(parser):
    parser.addoption("--require-data", action="store_true",
                     help="fail (do not skip) tests that need VPR_EXPLORER_DATA")


def pytest_configure(config):
    config.addinivalue_line("markers", "realdata: needs VPR_EXPLORER_DATA")


@contextmanager
def _environment(name: str, value: str) -> Iterator[None]:
    """``os.environ[name] = value`` inside, and what it was (or its absence) after."""
    old = os.environ.get(name)
    os.environ[name] = value
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = old


@pytest.fixture(scope="session", autouse=True)
def isolated_cache(tmp_path_factory) -> Path:
    """One descriptor cache for the whole session, never the user's ~/.cache.

    Set in the environment so that streamlit servers the tests start share it.
    """
    root = tmp_path_factory.mktemp("vpr_cache")
    with _environment(CACHE_ENV, str(root)):
        yield root


#: The torch device the device-path tests run on. Unset: the CPU, where the device code runs on
#: CPU tensors; ``benchmarks/gpu_check.py`` sets it to the GPU on a machine with one.
TEST_DEVICE_ENV = "VPR_EXPLORER_TEST_DEVICE"


@pytest.fixture(scope="session")
def device_under_test() -> str:
    """The device-path tests' torch device: ``$VPR_EXPLORER_TEST_DEVICE``, else ``"cpu"``."""
    return os.environ.get(TEST_DEVICE_ENV, "cpu")


#: rerun 0.41 (``re_analytics``) collects no usage data, and prints no first-run notice, while this
#: variable is set, to any value
RERUN_ANALYTICS_OFF = "CI"


@pytest.fixture(scope="session", autouse=True)
def rerun_analytics_off() -> Iterator[None]:
    """rerun's analytics off for the session: no first-run notice, nothing written under ~/.config/rerun.

    Set in the environment, so that the recordings the tests make, the commands they run and
    the Streamlit servers they start (which inherit it) see it; a value already set is kept.
    """
    with _environment(RERUN_ANALYTICS_OFF, os.environ.get(RERUN_ANALYTICS_OFF, "1")):
        yield


@pytest.fixture(scope="session", autouse=True)
def app_data_root(tmp_path_factory) -> Path:
    """The app's data root for the session: the nearest folder holding pytest's temporary folders and the real data.

    Set in the environment, so that AppTest sessions and the servers the tests start (which
    inherit it) open the datasets the tests write and the real ones alike.
    """
    folders = [tmp_path_factory.getbasetemp().resolve()]
    if os.environ.get(DATA_ENV):
        folders.append(Path(os.environ[DATA_ENV]).expanduser().resolve())
    root = Path(os.path.commonpath(folders))
    with _environment(DATA_ROOT_ENV, str(root)):
        yield root


@pytest.fixture(scope="session")
def data_root(request) -> Path:
    """The real-datasets folder; skips (or fails under --require-data) when it is not set."""
    value = os.environ.get(DATA_ENV)
    if not value:
        msg = f"{DATA_ENV} is not set: point it at the shared datasets folder (e.g. ../shared/datasets) to run real-data tests"
        if request.config.getoption("--require-data"):
            pytest.fail(msg)
        pytest.skip(msg)
    root = Path(value).expanduser().resolve()
    if not (root / "GardensPointWalking").is_dir():
        pytest.fail(f"{DATA_ENV}={root} holds no GardensPointWalking/ folder")
    # CI gives a relative path (../shared/datasets): servers and commands the tests start in
    # other folders must see the same one
    os.environ[DATA_ENV] = str(root)
    return root


@pytest.fixture(scope="session")
def gardens_point(data_root):
    from vpr_explorer.data.traversals import load_dataset

    return load_dataset(data_root / "GardensPointWalking")


@pytest.fixture(scope="session")
def gp_pixels(gardens_point):
    """``(600, 2048)`` pixel descriptors of GardensPoint (cached for the session)."""
    from vpr_explorer.pipeline import dataset_descriptors

    return dataset_descriptors(gardens_point, "pixels")


@pytest.fixture(scope="session")
def gp_effnet(gardens_point):
    """``(600, 1280)`` efficientnet-lite0 descriptors of GardensPoint (cached for the session)."""
    from vpr_explorer.pipeline import dataset_descriptors

    return dataset_descriptors(gardens_point, "efficientnet-lite0")


@pytest.fixture(scope="session")
def demo():
    """The built-in procedural route: 3 traversals (day, night, snow) x 60 frames."""
    from vpr_explorer.pipeline import resolve_dataset

    return resolve_dataset("demo")


@pytest.fixture(scope="session")
def demo_pixels(demo):
    """``(180, 2048)`` pixel descriptors of the demo route."""
    from vpr_explorer.pipeline import dataset_descriptors

    return dataset_descriptors(demo, "pixels")
