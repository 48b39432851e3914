"""A real browser on the Playback page: record, find rerun's viewer showing the recording, the frame box and its cursor together.

Drives Debian's Chromium (never a downloaded one) against a real ``streamlit run app.py``
with the pixel descriptor: on the built-in demo route (aligned traversals, no dataset
download), and on GardensPoint written as a VPR-Bench layout (its queries against its
references, in order). The viewer is the page's component (``app/ui/rerun_viewer.py``):
its frame exposes ``window.rerunViewer`` (``app/static/rerun_viewer/index.html``), through
which the test moves and plays the viewer's time cursor the way rerun-notebook's Python side
does (a ``time_ctrl`` message to the widget), reads where the viewer says its cursor is
(``cursor``), and reads the page's seeks it applied (``seeks``). The GardensPoint case saves
``playback.png`` (to a temporary folder, or ``docs/screenshots/`` with
``VPR_EXPLORER_SCREENSHOTS=docs``).
"""

from __future__ import annotations

import os
import re
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import pytest

from streamlit_server import ROOT, streamlit_server

pytestmark = pytest.mark.browser
sync_api = pytest.importorskip("playwright.sync_api")

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
        "--disable-component-update", "--disable-sync"]
TIMEOUT_MS = 120_000
DEMO_LINK = "source=demo&descriptor=pixels&group=2&step=2&query=night"
SCREENSHOTS = (ROOT / "docs" / "screenshots" if os.environ.get("VPR_EXPLORER_SCREENSHOTS") == "docs"
               else Path(tempfile.mkdtemp(prefix="vpr_screenshots_")))
COMPONENT = "iframe[src*='/component/vpr_explorer.app.ui.rerun_viewer.rerun_viewer/index.html']"


def _record(page, url: str, link: str) -> str:
    """Open the Playback page at ``link``, press Record and play; the recording's id."""
    page.goto(f"{url}/playback?{link}", timeout=TIMEOUT_MS)
    record = page.get_by_role("button", name="Record and play")
    record.wait_for(timeout=TIMEOUT_MS)
    record.click()
    caption = page.get_by_text(re.compile(r"Recording [0-9a-f]{32}"))
    caption.wait_for(timeout=TIMEOUT_MS)
    return re.search(r"Recording ([0-9a-f]{32})", caption.inner_text()).group(1)


def _viewer(page, recording_id: str):
    """The component's frame, once its viewer shows ``recording_id`` (opened, and its cursor where the page put it)."""
    frame = page.wait_for_selector(COMPONENT, timeout=TIMEOUT_MS).content_frame()
    frame.wait_for_function("rid => window.rerunViewer !== undefined && window.rerunViewer.shown === rid",
                            arg=recording_id, timeout=TIMEOUT_MS)
    return frame


def _launch(pw):
    return pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)


@pytest.mark.parametrize("layout, heading, file_name", [
    ("demo", "demo: night against day, snow", "demo_night_vs_day+snow.rrd"),
    pytest.param("vpr-bench", "vpr-bench: query against ref", "vpr-bench_query_vs_ref.rrd",
                 marks=pytest.mark.realdata),
])
def test_playback_page_records_and_shows_the_recording_in_the_viewer(tmp_path, request, layout, heading, file_name):
    link = DEMO_LINK
    if layout != "demo":
        from urllib.parse import quote

        from vpr_explorer.data.example_layouts import write_gardens_point_layouts

        written = write_gardens_point_layouts(request.getfixturevalue("data_root") / "GardensPointWalking", tmp_path)
        link = f"source={quote(str(written[layout]))}&descriptor=pixels&group=2&step=5"
    with streamlit_server("app.py") as url, sync_api.sync_playwright() as pw:
        browser = _launch(pw)
        try:
            page = browser.new_page(viewport={"width": 1500, "height": 1100}, accept_downloads=True)
            errors: list[str] = []
            page.on("pageerror", lambda exc: errors.append(f"page: {exc}"))
            recording_id = _record(page, url, link)
            assert page.get_by_text(heading).is_visible()
            assert page.get_by_text("Looking at").is_visible()  # routed through app.py
            assert page.get_by_text("box below the viewer follows its time cursor").is_visible()

            viewer = _viewer(page, recording_id)
            canvas = viewer.locator("canvas")
            assert canvas.count() == 1 and canvas.is_visible()
            box = canvas.bounding_box()
            assert box is not None and box["width"] > 600 and box["height"] > 400
            # The viewer opened our recording from the gRPC server and reports its cursor on it.
            events = viewer.evaluate("() => window.rerunViewer.events")
            assert any(e["type"] == "recording_open" and e["recording_id"] == recording_id for e in events)
            assert viewer.locator(".rerun-fail-message, #failure").count() == 0
            # It started where the box stands, and has sent nothing the page already knew.
            frame_box = page.locator('[data-testid="stNumberInput"] input').first
            start = int(frame_box.input_value())
            viewer.wait_for_function(
                "([rid, t]) => window.rerunViewer.events.some(e => e.recording_id === rid && e.time === t)",
                arg=[recording_id, start], timeout=TIMEOUT_MS)
            assert viewer.evaluate("() => window.rerunViewer.sent") == []
            if layout != "demo":  # the documentation's picture: GardensPoint's queries in the viewer
                page.mouse.move(5, 5)
                page.set_viewport_size({"width": 1500, "height": 1950})  # the page down to the query box under the viewer
                time.sleep(3)  # the viewer draws the cursor's images at the new size
                page.screenshot(path=str(SCREENSHOTS / "playback.png"))

            with page.expect_download(timeout=TIMEOUT_MS) as download:
                page.get_by_role("button", name="Download the .rrd").click()
            saved = tmp_path / "playback.rrd"
            download.value.save_as(saved)
            assert saved.read_bytes()[:4] == b"RRF2"
            assert download.value.suggested_filename == file_name

            assert page.locator('[data-testid="stException"]').count() == 0
            assert page.locator('[data-testid="stAlertContentError"]').count() == 0
            assert errors == []
        finally:
            browser.close()


def _move_cursor(page, viewer, frame: int) -> float:
    """Move the viewer's cursor to query ``frame`` (paused); seconds until the box, caption and button show it."""
    began = time.monotonic()
    viewer.evaluate("q => window.rerunViewer.custom({type: 'time_ctrl', timeline: 'query', sequence: String(q), "
                    "play: false})", frame)
    page.get_by_role("button", name=f"Open frame {frame} in the Query inspector").wait_for(timeout=TIMEOUT_MS)
    return time.monotonic() - began


@contextmanager
def _demo_playback():
    """A browser on the demo route's Playback page, recorded: ``(page, viewer frame, recording id, frame box)``.

    On leaving, no exception is shown on the page and no script error was raised in it.
    """
    with streamlit_server("app.py") as url, sync_api.sync_playwright() as pw:
        browser = _launch(pw)
        try:
            page = browser.new_page(viewport={"width": 1500, "height": 1100})
            errors: list[str] = []
            page.on("pageerror", lambda exc: errors.append(f"page: {exc}"))
            recording_id = _record(page, url, DEMO_LINK)
            yield page, _viewer(page, recording_id), recording_id, page.get_by_label("frame", exact=True)
            assert page.locator('[data-testid="stException"]').count() == 0
            assert errors == []
        finally:
            browser.close()


def test_the_frame_box_follows_the_viewers_time_cursor():
    with _demo_playback() as (page, viewer, recording_id, box):
        caption = page.locator('[data-testid="stMarkdownContainer"]', has_text="paper (margin")
        for frame in (17, 5):
            assert int(box.input_value()) != frame
            seconds = _move_cursor(page, viewer, frame)
            assert box.input_value() == str(frame), seconds
            assert caption.inner_text().startswith(f"night · frame {frame}:")
            assert "frame=" + str(frame) in page.url  # the view's frame, kept in the link
            sent = viewer.evaluate("() => window.rerunViewer.sent")[-1]
            assert (sent["recording_id"], sent["timeline"], sent["time"]) == (recording_id, "query", frame)


def _cursor_at(viewer, recording_id: str, frame: int) -> None:
    """Wait until the viewer says its cursor stands at query ``frame`` of ``recording_id``."""
    viewer.wait_for_function(
        "([rid, q]) => { const c = window.rerunViewer.cursor; "
        "return c !== null && c.recording_id === rid && c.timeline !== 'log_time' && c.time === q; }",
        arg=[recording_id, frame], timeout=TIMEOUT_MS)


def test_the_viewers_time_cursor_follows_the_frame_box():
    with _demo_playback() as (page, viewer, recording_id, box):
        assert viewer.evaluate("() => window.rerunViewer.seeks") == []  # the viewer started where the box stood

        # A number typed into the box, then one more by its stepper: the cursor goes there, paused.
        box.fill("40")
        box.press("Enter")
        page.get_by_role("button", name="Open frame 40 in the Query inspector").wait_for(timeout=TIMEOUT_MS)
        _cursor_at(viewer, recording_id, 40)
        page.locator('[data-testid="stNumberInputStepUp"]').click()
        page.get_by_role("button", name="Open frame 41 in the Query inspector").wait_for(timeout=TIMEOUT_MS)
        _cursor_at(viewer, recording_id, 41)
        assert viewer.evaluate("() => window.rerunViewer.seeks") == [[1, 40], [2, 41]]
        assert viewer.evaluate("() => window.rerunViewer.sent") == []  # the page knew: nothing sent back

        # The viewer's side moves it: the box follows, and the typed number does not pull the cursor back.
        _move_cursor(page, viewer, 23)
        assert box.input_value() == "23"
        _cursor_at(viewer, recording_id, 23)
        # Played from the start to the end, past 41: every rerun it causes repeats the seek's token.
        start = len(viewer.evaluate("() => window.rerunViewer.events"))
        viewer.evaluate("() => window.rerunViewer.custom({type: 'time_ctrl', timeline: 'query', sequence: '0', "
                        "play: true})")
        page.get_by_role("button", name="Open frame 59 in the Query inspector").wait_for(timeout=TIMEOUT_MS)
        _cursor_at(viewer, recording_id, 59)
        times = [e["time"] for e in viewer.evaluate("() => window.rerunViewer.events")[start:]
                 if e["type"] == "time_update" and e["recording_id"] == recording_id]
        top = times.index(max(times))  # the viewer may report one step past the last query, then the last
        assert times[0] in (0, 23) and times[:top + 1] == sorted(times[:top + 1]), times
        assert min(times[top:]) >= 59 and times[-1] == 59, times
        sent = [s["time"] for s in viewer.evaluate("() => window.rerunViewer.sent")]
        assert len(sent) >= 3 and sent[-1] == 59, sent  # the box followed the play: several reruns
        assert viewer.evaluate("() => window.rerunViewer.seeks") == [[1, 40], [2, 41]]
        assert box.input_value() == "59"

        # After the play the box moves the cursor again.
        box.fill("12")
        box.press("Enter")
        _cursor_at(viewer, recording_id, 12)
        assert viewer.evaluate("() => window.rerunViewer.seeks")[-1] == [3, 12]
