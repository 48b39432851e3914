"""A real browser on the Playback page: record, then find rerun's viewer loaded with the recording.

Drives Debian's Chromium (never a downloaded one) against a real ``streamlit run app.py``
with the pixel descriptor: on the built-in demo route (aligned traversals, no dataset
download), and on GardensPoint written as a VPR-Bench layout (its queries against its
references, in order).
"""

from __future__ import annotations

import re

import pytest

from streamlit_server import streamlit_server

pytestmark = pytest.mark.browser
sync_api = pytest.importorskip("playwright.sync_api")

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
        "--disable-component-update", "--disable-sync"]
TIMEOUT_MS = 120_000
VIEWER_URL = re.compile(r"^http://127\.0\.0\.1:\d+/\?url=rerun%2Bhttp%3A%2F%2F127\.0\.0\.1%3A\d+%2Fproxy")


def _viewer_state(frame) -> str:
    """The viewer's own report of what it shows (a protobuf message), as text."""
    return frame.evaluate("() => new TextDecoder('latin1').decode(window._handle.viewer_state())")


@pytest.mark.parametrize("layout, heading, file_name", [
    ("demo", "demo: night against day, snow", "demo_night_vs_day+snow.rrd"),
    pytest.param("vpr-bench", "vpr-bench: query against ref", "vpr-bench_query_vs_ref.rrd",
                 marks=pytest.mark.realdata),
])
def test_playback_page_records_and_shows_the_recording_in_the_viewer(tmp_path, request, layout, heading, file_name):
    link = "source=demo&descriptor=pixels&group=2&step=2&query=night"
    if layout != "demo":
        from urllib.parse import quote

        from vpr_explorer.data.example_layouts import write_gardens_point_layouts

        written = write_gardens_point_layouts(request.getfixturevalue("data_root") / "GardensPointWalking", tmp_path)
        link = f"source={quote(str(written[layout]))}&descriptor=pixels&group=2&step=5"
    with streamlit_server("app.py") as url, sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        try:
            page = browser.new_page(viewport={"width": 1500, "height": 1100}, accept_downloads=True)
            errors: list[str] = []
            page.on("pageerror", lambda exc: errors.append(f"page: {exc}"))
            page.goto(f"{url}/playback?{link}", timeout=TIMEOUT_MS)
            record = page.get_by_role("button", name="Record and play")
            record.wait_for(timeout=TIMEOUT_MS)
            record.click()

            caption = page.get_by_text(re.compile(r"Recording [0-9a-f]{32}"))
            caption.wait_for(timeout=TIMEOUT_MS)
            recording_id = re.search(r"Recording ([0-9a-f]{32})", caption.inner_text()).group(1)
            assert page.get_by_text(heading).is_visible()
            assert page.get_by_text("Looking at").is_visible()  # routed through app.py

            page.locator("iframe").first.wait_for(timeout=TIMEOUT_MS)
            viewer = next(f for f in page.frames if VIEWER_URL.match(f.url))
            viewer.wait_for_function("() => window._handle !== undefined", timeout=TIMEOUT_MS)
            canvas = viewer.locator("canvas#the_canvas_id")
            assert canvas.is_visible()
            box = canvas.bounding_box()
            assert box is not None and box["width"] > 600 and box["height"] > 400
            # The viewer has our recording, as the active one, laid out by our blueprint.
            viewer.wait_for_function(
                "rid => new TextDecoder('latin1').decode(window._handle.viewer_state())"
                ".includes('recording_id=' + rid)", arg=recording_id, timeout=TIMEOUT_MS)
            state = _viewer_state(viewer)
            active = re.search(r"about:recording\?app_id=vpr_explorer&recording_id=([0-9a-f]+)", state)
            assert active is not None and active.group(1) == recording_id
            assert "paper's answer" in state and "place: true (grey)" in state
            assert not viewer.evaluate("() => window._handle.has_panicked()")
            assert viewer.locator("#center_text").inner_text().strip() == ""

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
