"""The cache folder: checked before any work, one layout whoever names it, the app without one.

Tests run as root, for whom permissions never refuse a write; an unusable folder is
made the way a user meets one: a file standing where the folder (or its parent)
should be, or a path under ``/proc``.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from images import write_random_route
from streamlit.testing.v1 import AppTest
from test_app import ROOT, TIMEOUT, assert_clean, page
from test_app import fresh_caches, navigation_mode  # noqa: F401  (autouse fixtures: every AppTest here needs them)

from vpr_explorer import settings
from vpr_explorer.data.traversals import load_dataset
from vpr_explorer.descriptors import DescriptorCache, extract_descriptors
from vpr_explorer.descriptors.pixels import PixelsExtractor
from vpr_explorer.errors import VPRInputError
from vpr_explorer.pipeline import dataset_descriptors

FRAMES = 12


class CountingPixels(PixelsExtractor):
    """The pixels descriptor, recording the images it decoded."""

    def __init__(self) -> None:
        self.loaded: list[Path] = []

    def load(self, path: Path):
        self.loaded.append(Path(path))
        return super().load(path)


@pytest.fixture
def route(tmp_path: Path) -> Path:
    """A two-traversal dataset folder of small random PNGs (frame f of each is spot f)."""
    return write_random_route(tmp_path / "route", FRAMES, (96, 48))


def unusable_folders(tmp_path: Path) -> dict[str, Path]:
    a_file = tmp_path / "a-file"
    a_file.write_text("not a folder")
    return {"file as parent": a_file / "cache", "file in place": a_file, "under /proc": Path("/proc/vpr-cache")}


def cli(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vpr_explorer.cli", *args], capture_output=True, text=True,
                          timeout=300, env={**os.environ, **(env or {})})


# ------------------------------------------------------------------ checked up front


def test_check_cache_root_accepts_new_and_existing_folders_and_creates_nothing(tmp_path):
    root = tmp_path / "new" / "cache"
    assert settings.check_cache_root(root) == root
    assert list(tmp_path.iterdir()) == []  # a check, not a setup: refused runs leave nothing behind
    (root / "descriptors").mkdir(parents=True)
    assert settings.check_cache_root(root) == root
    assert list(root.rglob("*")) == [root / "descriptors"]


@pytest.mark.parametrize("kind", ["file as parent", "file in place", "under /proc"])
def test_check_cache_root_names_the_folder_and_the_fix(tmp_path, kind):
    bad = unusable_folders(tmp_path)[kind]
    with pytest.raises(VPRInputError) as caught:
        settings.check_cache_root(bad)
    message = str(caught.value)
    assert message.startswith(f"cache folder {bad}: cannot write there (")
    assert "--cache-dir" in message and settings.CACHE_ENV in message


@pytest.mark.parametrize("kind", ["file as parent", "file in place", "under /proc"])
def test_unwritable_cache_fails_before_any_image_is_decoded(route, tmp_path, kind):
    bad = unusable_folders(tmp_path)[kind]
    counting = CountingPixels()
    with pytest.raises(VPRInputError, match=rf"cache folder {bad}: cannot write there"):
        extract_descriptors(sorted(route.rglob("*.png")), counting, cache=DescriptorCache(bad))
    assert counting.loaded == []


@pytest.mark.parametrize("how", ["--cache-dir", "environment"])
def test_cli_unwritable_cache_is_one_error_line(route, tmp_path, how):
    bad = unusable_folders(tmp_path)["file as parent"]
    args = ["evaluate", "--dataset", str(route), "--descriptor", "pixels", "--group", "2", "--step", "4",
            "--runs", "2"]
    if how == "--cache-dir":
        r = cli(*args, "--cache-dir", str(bad))
    else:
        r = cli(*args, env={settings.CACHE_ENV: str(bad)})
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    (line,) = [line for line in r.stderr.splitlines() if line.strip()]
    assert line.startswith(f"error: cache folder {bad}: cannot write there")
    assert "--cache-dir" in line and settings.CACHE_ENV in line


# ------------------------------------------------------------------ one layout


def test_one_folder_is_one_cache_whether_named_by_the_option_or_the_environment(route, tmp_path, monkeypatch):
    dataset = load_dataset(route)
    n = dataset.n_images
    explicit = tmp_path / "explicit"
    first = dataset_descriptors(dataset, "pixels", cache_root=explicit)  # what --cache-dir does
    written = sorted(p.relative_to(explicit) for p in explicit.rglob("*") if p.is_file())
    assert written and all(p.parts[:2] == ("descriptors", PixelsExtractor().cache_key) for p in written)

    # The environment variable naming the same folder finds every vector there ...
    monkeypatch.setenv(settings.CACHE_ENV, str(explicit))
    calls: list[tuple[int, int]] = []
    again = dataset_descriptors(dataset, "pixels", progress=lambda done, total: calls.append((done, total)))
    assert calls == [(n, n)]
    assert (again == first).all()
    assert sorted(p.relative_to(explicit) for p in explicit.rglob("*") if p.is_file()) == written

    # ... and, naming an empty folder, lays it out the same way.
    by_env = tmp_path / "by-env"
    monkeypatch.setenv(settings.CACHE_ENV, str(by_env))
    dataset_descriptors(dataset, "pixels")
    layout = {p.relative_to(by_env).parent for p in by_env.rglob("*") if p.is_file()}
    assert layout == {p.parent for p in written}


# ------------------------------------------------------------------ the app without a cache folder


def test_app_runs_in_memory_with_a_warning_when_the_cache_folder_is_unwritable(tmp_path, monkeypatch):
    bad = unusable_folders(tmp_path)["file as parent"]
    monkeypatch.setenv(settings.CACHE_ENV, str(bad))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))  # where the demo route is drawn instead
    (tmp_path / "tmp").mkdir()
    at = AppTest.from_file(str(ROOT / "app.py"), default_timeout=TIMEOUT).run()
    assert_clean(at)
    (warning,) = [w.value for w in at.warning]
    assert "The cache folder is not writable: nothing will be cached" in warning
    assert "in memory only" in warning and str(bad) in warning
    assert any("descriptors ready: 180 × 2048 (in memory only" in s.value for s in at.success)
    assert not (tmp_path / "a-file").is_dir()
    page(at, "places")
    assert_clean(at)
