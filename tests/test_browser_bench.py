"""The acceptance bench and discovered places in a real browser (Chromium against ``streamlit run``), on GardensPoint.

The Evaluation page's bench section opens, **Run the bench** draws the authors' table (every
rule that ran, in ``RULES`` order, with its column headers) and the precision–recall figure
(one curve and one operating point per rule); the toggle redraws it for the natural open set.
The Places page draws the discovered places beside group/step. No exception anywhere. It saves
``bench.png`` (to a temporary folder, or ``docs/screenshots/`` with ``VPR_EXPLORER_SCREENSHOTS=docs``)
and ``places_discovered.png`` (to a temporary folder: no page of the docs shows it).
"""

from __future__ import annotations

import time
from urllib.parse import quote

import pytest

from streamlit_server import streamlit_server
from test_browser import SCREENSHOTS, WIDTH, assert_no_exception, browser, go, settle, shoot  # noqa: F401  (browser: the fixture)
from test_browser_evaluation import chart, charts, headers
from vpr_explorer.protocols.acceptance import RULES

pytestmark = [pytest.mark.browser, pytest.mark.realdata]

#: Rules that need database positions in metres: GardensPoint's route is drawn in the unit square.
POSITIONS = {r.key for r in RULES if r.needs == "positions"}


def shoot_section(page, expander: str, name: str) -> None:
    """A screenshot of one expander, in a viewport tall enough that every part of it is drawn."""
    page.set_viewport_size({"width": WIDTH, "height": 4000})
    time.sleep(0.8)  # charts and the table re-layout to the new size
    page.mouse.move(5, 5)
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    page.locator('[data-testid="stExpander"]', has_text=expander).first.screenshot(path=str(SCREENSHOTS / f"{name}.png"))
    page.set_viewport_size({"width": WIDTH, "height": 1100})
    time.sleep(0.5)


def test_the_bench_renders_its_table_and_figures_on_gardens_point(browser, data_root, gp_pixels):
    gp = str(data_root / "GardensPointWalking")
    with streamlit_server("app.py", extra_args=("--client.toolbarMode", "viewer")) as url:
        page = browser.new_page(viewport={"width": WIDTH, "height": 1100})
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(f"{url}/evaluation?source={quote(gp)}&descriptor=pixels")
        page.get_by_role("heading", name="Evaluation").first.wait_for(timeout=120_000)
        settle(page)
        assert_no_exception(page, "evaluation")

        page.get_by_text("Acceptance bench: every acceptance rule on the same queries").click()
        button = page.get_by_role("button", name="Run the bench")
        button.scroll_into_view_if_needed()
        button.click()
        settle(page)
        assert_no_exception(page, "evaluation after Run the bench")

        table = [h for h in headers(page) if "closed F1" in h]
        assert len(table) == 1, headers(page)
        assert {"rule", "R@1", "R@5", "open F1 (70%)", "rejection", "AUC-PR", "τ", "τ from"} <= set(table[0])
        grid = page.locator('[data-testid="stDataFrame"]', has_text="closed F1").first
        width = grid.evaluate("g => { const s = g.querySelector('.dvn-scroller'); return [s.scrollWidth, s.clientWidth]; }")
        assert width[0] <= width[1] + 1, f"the bench's table scrolls sideways: {width}"
        ran = [r for r in RULES if r.key not in POSITIONS]
        rows = grid.evaluate("g => Array.from(g.querySelectorAll('[role=\"row\"]')).length")
        assert rows == len(ran) + 1, rows  # a header row and one row per rule that ran
        body = page.locator("body").inner_text()
        assert "Rules left out" in body and "not metres" in body  # SUE: the unit square is not metres

        closed = chart(page, "Every rule's precision–recall, closed set")
        assert [m for m in closed["metas"] if not m.startswith("own ")] == [r.key for r in ran]
        assert sorted(m for m in closed["metas"] if m.startswith("own ")) == sorted(f"own {r.key}" for r in ran)
        tutorial = chart(page, "VPR_Tutorial's precision–recall")
        assert sorted(tutorial["metas"]) == ["multi", "single"]
        assert all(any(w in n for w in ("single-best-match", "multi-match")) for n in tutorial["names"])

        shoot_section(page, "Acceptance bench", "bench")

        page.get_by_text("natural open set (first 70% of the route)").click()
        settle(page)
        assert_no_exception(page, "the natural open set's curves")
        natural = chart(page, "Every rule's precision–recall, natural open set")
        assert natural["y"] != closed["y"]
        assert not [c for c in charts(page) if c["title"].startswith("Every rule's precision–recall, closed set")]

        go(page, "Places")
        discovered = chart(page, "day_left: 200 database images in route order")
        assert "places discovered" in discovered["metas"] and "score" in discovered["metas"]
        assert "**discovered**" not in page.locator("body").inner_text()  # markdown rendered, not shown raw
        shoot(page, "places_discovered", for_docs=False)
        assert not errors, errors
