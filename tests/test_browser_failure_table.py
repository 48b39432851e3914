"""The failure table in a real browser (Chromium against ``streamlit run``), on GardensPoint with pixel descriptors.

The Evaluation page, opened from a link (traversal protocol, night_right queries against the
day_right database, group 3 step 10), shows the table with its picture columns drawn; its CSV
download is the library's (``views.failures.table_csv`` of ``find_failures``' rows); ticking a
row's box opens that query in the Query inspector, its finder on the row's kind and method,
and the inspector's own "Failures" section lists the same kind of rows. No exception anywhere.
It saves ``failure_table.png`` (to a temporary folder, or ``docs/screenshots/`` with
``VPR_EXPLORER_SCREENSHOTS=docs``).
"""

from __future__ import annotations

import re
from urllib.parse import parse_qs, quote, urlparse

import pytest

from streamlit_server import streamlit_server
from test_browser import ROOT, SCREENSHOTS, WIDTH, assert_no_exception, browser, settle  # noqa: F401  (browser: the fixture)
from test_failures import fitted_gp
from vpr_explorer.app.ui import failure_table as ft
from vpr_explorer.views import failures as vf

pytestmark = [pytest.mark.browser, pytest.mark.realdata]


def table_box(page, column: str):
    """The dataframe whose headers include ``column`` (glide's accessible table names the columns in view)."""
    frames = page.locator('[data-testid="stDataFrame"]')
    for i in range(frames.count()):
        frame = frames.nth(i)
        heads = frame.evaluate("""d => Array.from(d.querySelectorAll('[role="columnheader"]'))
                                  .map(h => h.textContent.trim())""")
        if column in heads:
            return frame, heads
    raise AssertionError(f"no dataframe with a {column!r} column")


def selected(page, label: str) -> str:
    return page.get_by_role("combobox", name=label, exact=True).input_value()


def test_the_failure_table_downloads_and_opens_a_row_in_the_inspector(browser, data_root, gardens_point, tmp_path):
    fitted, desc = fitted_gp(gardens_point, 0)
    result = vf.find_failures(fitted, desc, "margin-weighted", top=1, queries=vf.failure_queries(fitted))
    rows = vf.table_rows(fitted, result)
    gp = quote(str(data_root / "GardensPointWalking"))
    link = (f"/evaluation?source={gp}&descriptor=pixels&eval_protocol=traversal&eval_database=day_right"
            "&eval_query=night_right")
    with streamlit_server("app.py", extra_args=("--client.toolbarMode", "viewer")) as url:
        page = browser.new_page(viewport={"width": WIDTH, "height": 1100}, accept_downloads=True)
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(url + link)
        page.get_by_role("heading", name="Failures: every query a method got wrong").first.wait_for(timeout=180_000)
        settle(page)
        assert_no_exception(page, "evaluation from a link")
        frame, heads = table_box(page, "true match")  # glide names the columns in view: the first ones
        for column in ("query", "#", "kind", "answer", "answered", "true match", "true place", "score", "θ"):
            assert column in heads, heads
        frame.scroll_into_view_if_needed()
        body = page.locator("body").inner_text()
        assert f"{len(rows)} rows. Select a row" in body
        SCREENSHOTS.mkdir(parents=True, exist_ok=True)
        frame.screenshot(path=str(SCREENSHOTS / "failure_table.png"))

        # the CSV is the library's rows, in the table's order
        with page.expect_download() as download:
            page.get_by_role("button", name="Download failures (CSV)").click()
        saved = tmp_path / "failures.csv"
        download.value.save_as(saved)
        assert saved.read_bytes() == vf.table_csv(rows).encode("utf-8")

        # tick the third row's box: its query opens in the inspector
        row = 2
        want = rows[row]["query"]
        box = frame.bounding_box()
        header = 36  # glide's header row, Streamlit's default
        page.mouse.click(box["x"] + 16, box["y"] + header + ft.ROW_HEIGHT * row + ft.ROW_HEIGHT / 2)
        page.wait_for_function("() => window.location.pathname.endsWith('/inspector')", timeout=120_000)
        page.get_by_role("heading", name="Query inspector").first.wait_for(timeout=120_000)
        settle(page)
        assert_no_exception(page, "inspector from the failure table")
        params = parse_qs(urlparse(page.url).query)
        assert params["frame"] == [str(want)] and params["inspector_find"] == ["wrong answer"], page.url
        assert selected(page, "Find a query that was") == "a wrong answer (accepted, wrong place)"
        assert selected(page, "under") == "margin, weighted θ"
        assert re.search(rf"query {want}\b", page.locator("body").inner_text())

        # the inspector's own section: closed, then the same failures of its value
        page.get_by_text("Failures: every query a method got wrong").first.click()
        settle(page)
        assert_no_exception(page, "inspector's failures")
        _, heads = table_box(page, "true match")
        assert "answered" in heads
        assert not errors, errors


#: The failure pictures the README and the Results page show: ``vpr-explorer failures`` on GardensPoint, night_right
#: against day_right, pixels, raw-weighted, three candidates (the command they show beside them).
README_FAILURES = ("071-wrong-answer.png",)
RESULTS_FAILURES = ("071-wrong-answer.png", "000-wrong-answer.png", "index.png")


def test_the_failure_pictures_and_their_index_in_a_browser(browser, gardens_point, tmp_path):
    """The command's index.html in Chromium: every picture loads, each row links its PNG; the README and the Results
    page show the PNGs and the index as the command draws them (saved to ``docs/screenshots/failures/`` with
    ``VPR_EXPLORER_SCREENSHOTS=docs``)."""
    import shutil

    from PIL import Image

    from test_failures import GP_PAIR
    from vpr_explorer.cli import main

    out = tmp_path / "failures"
    assert main(["failures", "--dataset", str(gardens_point.root), *GP_PAIR, "--method", "raw-weighted", "--top", "3",
                 "--out", str(out)]) == 0
    pngs = sorted(p.name for p in out.glob("*.png"))
    page = browser.new_page(viewport={"width": WIDTH, "height": 900})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto((out / "index.html").as_uri())
    page.wait_for_load_state("load")
    loaded = page.evaluate("() => Array.from(document.images).map(i => i.complete && i.naturalWidth > 0)")
    assert len(loaded) == len(pngs) and all(loaded)
    hrefs = page.evaluate("() => Array.from(document.querySelectorAll('a[href$=\".png\"]')).map(a => a.getAttribute('href'))")
    assert sorted(set(hrefs)) == pngs and not errors
    shots = SCREENSHOTS / "failures"
    shots.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(shots / "index.png"), clip={"x": 0, "y": 0, "width": WIDTH, "height": 900})
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    results = (ROOT / "docs" / "results.md").read_text(encoding="utf-8")
    assert all(f"docs/screenshots/failures/{name}" in readme for name in README_FAILURES)
    assert all(f"screenshots/failures/{name}" in results for name in RESULTS_FAILURES)
    for name in RESULTS_FAILURES[:-1]:
        assert name in pngs
        shutil.copyfile(out / name, shots / name)
        committed = ROOT / "docs" / "screenshots" / "failures" / name
        with Image.open(out / name) as drawn, Image.open(committed) as shown:
            assert shown.size == drawn.size  # the picture shown is this command's, at its size
