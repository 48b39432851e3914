"""A real browser walks the app on GardensPoint: Debian's Chromium, driven by Playwright, against ``streamlit run``.

Walks every page with efficientnet-lite0 descriptors (computed once per session by the
``gp_effnet`` fixture into the session cache, which the server shares), moves the
group/step sliders, clicks while pages are still running, picks a place in the
overview, opens a similarity-matrix cell and a rejected query in the inspector, and
finds no exception anywhere. It saves screenshots of every page: to the test's temporary
folder, or to the README's ``docs/screenshots/`` when ``VPR_EXPLORER_SCREENSHOTS=docs``
(so a test run never edits the source tree unless asked to). ``shoot(..., for_docs=False)``
keeps a picture that no page of the docs shows in the temporary folder either way.
"""

from __future__ import annotations

import os
import re
import tempfile
import time
from pathlib import Path
from urllib.parse import quote

import pytest

from streamlit_server import ROOT, streamlit_server

pytestmark = [pytest.mark.browser, pytest.mark.realdata]

SCRATCH = Path(tempfile.mkdtemp(prefix="vpr_screenshots_"))
"""Screenshots no page of the docs shows, and every screenshot unless ``VPR_EXPLORER_SCREENSHOTS=docs``."""
SCREENSHOTS = ROOT / "docs" / "screenshots" if os.environ.get("VPR_EXPLORER_SCREENSHOTS") == "docs" else SCRATCH
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
WIDTH = 1440
RUN_TIMEOUT_MS = 300_000


# --------------------------------------------------------------------------- helpers


def settle(page, timeout: int = RUN_TIMEOUT_MS) -> None:
    """Wait until the script run is over and every Plotly chart has drawn."""
    try:  # a rerun may not have started yet when the action returns
        page.wait_for_selector('[data-testid="stApp"][data-test-script-state="running"]', timeout=1500)
    except Exception:  # noqa: BLE001  (playwright's TimeoutError: the run was quicker than the poll)
        pass
    page.wait_for_selector('[data-testid="stApp"][data-test-script-state="notRunning"]', timeout=timeout)
    page.wait_for_function(
        """() => Array.from(document.querySelectorAll('[data-testid="stPlotlyChart"]'))
                  .every(c => c.querySelector('.main-svg'))
              && document.querySelectorAll('[data-testid="stSkeleton"]').length === 0""",
        timeout=60_000,
    )
    time.sleep(0.3)


def assert_no_exception(page, where: str) -> None:
    boxes = page.locator('[data-testid="stException"]')
    assert boxes.count() == 0, f"{where}: {boxes.first.inner_text()[:2000]}"
    assert "Traceback (most recent call last)" not in page.locator("body").inner_text(), where


def go(page, title: str) -> None:
    """Click a page in the sidebar navigation and wait for it."""
    page.locator('[data-testid="stSidebarNav"] a', has_text=title).first.click()
    settle(page)
    assert_no_exception(page, title)


def metric(page, label: str) -> str:
    box = page.locator('[data-testid="stMetric"]', has_text=label).first
    return box.locator('[data-testid="stMetricValue"]').inner_text().strip()


def slider(page, label: str):
    return page.locator('[data-testid="stSlider"]', has_text=label).first.get_by_role("slider")


def press(page, thumb, key: str, times: int = 1) -> None:
    for _ in range(times):
        thumb.focus()
        thumb.press(key)
        settle(page)


def shoot(page, name: str, *, for_docs: bool = True) -> Path:
    """Save a screenshot of the whole page (the viewport grown to the content's height) as ``name.png``.

    It goes to ``SCREENSHOTS``, or with ``for_docs=False`` (a picture no page of the docs shows) to
    ``SCRATCH``."""
    height = page.evaluate("""() => {
        const main = document.querySelector('[data-testid="stMainBlockContainer"]');
        return main ? Math.ceil(main.getBoundingClientRect().top + main.scrollHeight) + 40 : 1200; }""")
    page.mouse.move(5, 5)  # no tooltip or hover label in the picture
    page.set_viewport_size({"width": WIDTH, "height": int(min(max(height, 900), 4000))})
    time.sleep(0.8)  # charts re-layout to the new size
    folder = SCREENSHOTS if for_docs else SCRATCH
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.png"
    page.screenshot(path=str(path))
    page.set_viewport_size({"width": WIDTH, "height": 1100})
    return path


def click_plot_point(page, chart, x, y) -> None:
    """Click a Plotly chart at data coordinates (x, y); ``y=None``: just above the bottom of the y axis."""
    chart.scroll_into_view_if_needed()
    plot = chart.locator(".js-plotly-plot").first
    px, py = plot.evaluate(
        """(gd, xy) => { const L = gd._fullLayout;
            const y = xy[1] === null ? 0.9 * L.yaxis._length : L.yaxis.d2p(xy[1]);
            return [L.xaxis._offset + L.xaxis.d2p(xy[0]), L.yaxis._offset + y]; }""",
        [x, y],
    )
    box = plot.bounding_box()
    page.mouse.move(box["x"] + px, box["y"] + py)
    time.sleep(0.3)
    page.mouse.click(box["x"] + px, box["y"] + py)


# --------------------------------------------------------------------------- the walk


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()


def test_walk_gardens_point_in_a_real_browser(browser, data_root, gp_effnet):
    gp = str(data_root / "GardensPointWalking")
    with streamlit_server("app.py", extra_args=("--client.toolbarMode", "viewer")) as url:
        page = browser.new_page(viewport={"width": WIDTH, "height": 1100})
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))

        # Dataset page, opened from a shared link on a server that has not run any page yet.
        page.goto(f"{url}/?source={quote(gp)}&descriptor=efficientnet-lite0")
        settle(page)
        assert_no_exception(page, "home")
        assert page.get_by_text("efficientnet-lite0 descriptors ready: 600 × 1280").count() == 1
        assert page.get_by_text("GardensPointWalking: 3 traversals × 200 frames").count() == 1
        shoot(page, "home")

        # Places: the paper's group 3 / step 10 gives 20 places; move both sliders and back.
        go(page, "Places")
        assert metric(page, "places") == "20" and metric(page, "database images per place") == "6"
        press(page, slider(page, "group: frames per place"), "ArrowRight")  # group 4
        press(page, slider(page, "step: frames from one place"), "ArrowLeft", 2)  # step 8
        assert_no_exception(page, "places after slider moves")
        assert metric(page, "places") == str((200 - 4) // 8 + 1)
        assert "group=4" in page.url and "step=8" in page.url
        press(page, slider(page, "group: frames per place"), "ArrowLeft")
        press(page, slider(page, "step: frames from one place"), "ArrowRight", 2)
        assert metric(page, "places") == "20"
        assert "recomputed in" in page.locator("body").inner_text().lower()
        shoot(page, "places")

        # Click while the page is still running: move a slider and leave at once.
        thumb = slider(page, "step: frames from one place")
        thumb.focus()
        thumb.press("ArrowRight")
        page.locator('[data-testid="stSidebarNav"] a', has_text="Thresholds").first.click()
        settle(page)
        assert_no_exception(page, "thresholds after leaving places mid-run")
        assert "/thresholds" in page.url

        # Thresholds: back to step 10 through the URL, then pick a place by clicking its bar.
        page.goto(f"{url}/thresholds?source={quote(gp)}&descriptor=efficientnet-lite0")
        settle(page)
        assert_no_exception(page, "thresholds")
        overview = page.locator('[data-testid="stPlotlyChart"]').first
        click_plot_point(page, overview, "P12", None)  # category axis: the bar of place 12
        settle(page)
        assert_no_exception(page, "thresholds after a bar click")
        assert "place=12" in page.url
        assert page.get_by_text("P12: negative mixture, scores and thresholds").count() >= 1
        shoot(page, "thresholds")

        # Evaluation: click elsewhere while the protocol runs, come back, run the open-set protocol.
        page.locator('[data-testid="stSidebarNav"] a', has_text="Evaluation").first.click()
        page.wait_for_selector('[data-testid="stApp"][data-test-script-state="running"]', timeout=10_000)
        page.locator('[data-testid="stSidebarNav"] a', has_text="Query inspector").first.click()
        settle(page)
        assert_no_exception(page, "inspector after leaving evaluation mid-run")
        go(page, "Evaluation")
        page.get_by_text("open set: a share of places held out").click()
        page.get_by_role("button", name="Run", exact=True).click()
        settle(page)
        assert_no_exception(page, "open-set evaluation")
        assert page.get_by_text("Open set: unknown places rejected vs known-place Recall@1").count() >= 1
        shoot(page, "evaluation")

        # A click on a similarity-matrix cell opens that query in the inspector.
        heatmap = page.locator('[data-testid="stPlotlyChart"]').last
        click_plot_point(page, heatmap, 150, 150)
        settle(page)
        assert_no_exception(page, "inspector from the similarity matrix")
        assert "/inspector" in page.url
        frame = int(re.search(r"frame=(\d+)", page.url).group(1))
        assert abs(frame - 150) <= 1
        # The click reruns the Evaluation page, which then switches to the inspector: settle can
        # land between the two runs, so wait for the inspector's caption itself.
        opened = page.get_by_text("Opened from the similarity matrix")
        opened.wait_for(timeout=RUN_TIMEOUT_MS)
        assert opened.count() == 1

        # Open a rejected query: the inspector's finder, margin rule with the weighted θ (the default).
        page.get_by_role("button", name="next ▶").click()
        settle(page)
        assert_no_exception(page, "inspector, next rejected query")
        body = page.locator("body").inner_text()
        assert "margin, weighted θ: rejected: the best place" in body.replace("\n", " ")
        shoot(page, "inspector")

        for title in ("Dataset", "Places", "Thresholds", "Evaluation", "Query inspector"):
            go(page, title)
        assert not errors, errors
        page.close()
