"""``pip install`` gives a working explorer: the wheel, installed away from the checkout, serves the app from anywhere.

Builds the wheel (``pip wheel --no-deps``) from a copy of the checkout's package sources,
so that the run leaves the checkout untouched; installs it with ``pip install --no-deps
--target`` (the tests' interpreter already holds the dependencies; a ``venv
--system-site-packages`` made from inside a venv would see the base interpreter's
packages, not this venv's) and runs its ``vpr-explorer app`` console script from an empty
directory with ``PYTHONPATH`` on the installed copy. That copy, not the checkout, is what
the server imports (checked). Debian's Chromium then opens the printed link's server and
finds GardensPoint on the Dataset page, with the descriptor file it was started with.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import numpy as np
import pytest

from streamlit_server import ROOT, free_port, serving
from test_browser import CHROMIUM, CHROMIUM_ARGS, WIDTH, assert_no_exception, go, metric, settle

pytestmark = [pytest.mark.browser, pytest.mark.realdata]

PIP = (sys.executable, "-m", "pip", "--disable-pip-version-check", "--no-input")


def _run(*cmd: str, cwd: Path | None = None, env: dict | None = None) -> str:
    done = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, f"{' '.join(cmd)} exited {done.returncode}:\n{done.stdout}\n{done.stderr}"
    return done.stdout


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> dict[str, Path]:
    """The wheel built from the checkout, installed under a folder of its own: ``{"site", "script", "wheel"}``."""
    tmp = tmp_path_factory.mktemp("installed")
    src = tmp / "src"
    shutil.copytree(ROOT / "vpr_explorer", src / "vpr_explorer", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    _run(*PIP, "wheel", "--no-deps", "-q", "-w", str(tmp / "wheels"), ".", cwd=src)
    (wheel,) = (tmp / "wheels").glob("vpr_explorer-*.whl")
    site = tmp / "site"
    _run(*PIP, "install", "--no-deps", "--no-index", "-q", "--target", str(site), str(wheel))
    return {"site": site, "script": site / "bin" / "vpr-explorer", "wheel": wheel}


def test_installed_wheel_serves_the_explorer_from_any_directory(installed, data_root, gardens_point, tmp_path):
    # The wheel holds the whole app: entry script, pages, helpers, launcher; nothing beside the package.
    names = zipfile.ZipFile(installed["wheel"]).namelist()
    app = {n for n in names if n.startswith("vpr_explorer/app/")}
    for name in ("home", "places", "thresholds", "inspector", "evaluation", "playback"):
        assert f"vpr_explorer/app/pages/{name}.py" in app
    assert {"vpr_explorer/app/explorer.py", "vpr_explorer/app/launch.py", "vpr_explorer/app/ui/state.py"} <= app
    assert all(n.startswith(("vpr_explorer/", "vpr_explorer-")) for n in names), names

    # Run from an empty folder, with the installed copy first on the path: no checkout in sight.
    here = tmp_path / "anywhere"
    here.mkdir()
    env = {"PYTHONPATH": str(installed["site"])}  # replaces the tests' own, if any
    imported = _run(sys.executable, "-c", "import vpr_explorer, vpr_explorer.app.launch as a; "
                    "print(vpr_explorer.__file__); print(a.__file__)", cwd=here, env={**os.environ, **env}).split()
    for where in map(Path, imported):
        assert where.is_relative_to(installed["site"]) and not where.is_relative_to(ROOT), where

    # Descriptors computed "elsewhere": random ones, so that nothing is extracted while the test waits.
    d = np.random.default_rng(0).standard_normal((gardens_point.n_images, 32)).astype(np.float32)
    from vpr_explorer.descriptors.imported import write_descriptor_file

    mine = here / "elsewhere.npz"
    write_descriptor_file(mine, d / np.linalg.norm(d, axis=1, keepdims=True), gardens_point.image_paths,
                          gardens_point.root)

    gp = data_root / "GardensPointWalking"
    port = free_port()
    command = [str(installed["script"]), "app", "--dataset", str(gp), "--descriptors", mine.name, "--headless",
               "--port", str(port)]
    with serving(command, port, cwd=here, env=env) as output:
        printed = output()
        link = urlsplit(re.search(r"^VPR Threshold Explorer: (\S+)$", printed, re.M).group(1))
        serves = Path(re.search(r"^  \(serving (.+)\)$", printed, re.M).group(1))
        assert serves.is_relative_to(installed["site"]), serves  # the installed app, not the checkout's
        assert link.netloc == f"127.0.0.1:{port}"
        assert parse_qs(link.query) == {"source": [str(gp)], "descriptor": ["elsewhere"]}

        from playwright.sync_api import sync_playwright

        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            try:
                page = browser.new_page(viewport={"width": WIDTH, "height": 1100})
                errors: list[str] = []
                page.on("pageerror", lambda exc: errors.append(str(exc)))
                # A page's bare address on the fresh server (its first run: routed through the
                # packaged entry script), then the app's: the server opens the dataset it was started on.
                page.goto(f"http://127.0.0.1:{port}/places")
                settle(page, timeout=60_000)
                assert_no_exception(page, "installed: Places page, first visit")
                assert "/places" in page.url and metric(page, "places") == "20"  # the paper's group 3 / step 10
                page.goto(f"http://127.0.0.1:{port}/")
                settle(page, timeout=60_000)
                assert_no_exception(page, "installed: Dataset page")
                body = page.locator("body").inner_text()
                assert "GardensPointWalking: 3 traversals × 200 frames" in body
                assert "600 images" in body
                assert "elsewhere descriptors ready: 600 × 32" in body
                assert "source=" in page.url and "descriptor=elsewhere" in page.url  # the view went into the URL
                go(page, "Thresholds")
                assert "/thresholds" in page.url
                assert not errors, errors
            finally:
                browser.close()
