"""The Evaluation page in a real browser (Chromium against ``streamlit run``), on GardensPoint and Nordland.

* precision–recall curves drawn; runs (paper and traversal with pixels, traversal and open
  set with efficientnet-lite0) compared: a table with a difference column, overlaid PR and
  trade-off curves; the open-set table's last column visible; why the automatic θ rejects
  everything;
* the walk-through's defect: traversal → Run → Dataset page → descriptor → Evaluation must
  show the traversal protocol above the traversal's results;
* a link with the Evaluation settings, opened in a new session, restores the controls and
  the same numbers;
* a cold Nordland load shows the controls while the protocol is still running.

It saves ``pr_curves.png`` and ``compare.png``: to a temporary folder, or to the README's
``docs/screenshots/`` with ``VPR_EXPLORER_SCREENSHOTS=docs`` (see the README's app section).
"""

from __future__ import annotations

import time
from urllib.parse import parse_qs, quote, urlparse

import pytest

from streamlit_server import streamlit_server
from test_browser import SCREENSHOTS, WIDTH, assert_no_exception, browser, go, settle  # noqa: F401  (browser: the fixture)

pytestmark = [pytest.mark.browser, pytest.mark.realdata]


def charts(page) -> list[dict]:
    """Every Plotly chart on the page: its title, its traces' names and ``meta``, and its y values."""
    return page.evaluate("""() => Array.from(document.querySelectorAll('.js-plotly-plot')).map(g => ({
        title: String((g.layout.title && (g.layout.title.text || g.layout.title)) || '').replace(/<[^>]*>/g, ''),
        names: g.data.map(t => t.name || ''), metas: g.data.map(t => t.meta || ''),
        y: g.data.map(t => Array.from(t.y || []))}))""")


def chart(page, title_start: str) -> dict:
    found = [c for c in charts(page) if str(c["title"]).startswith(title_start)]
    assert len(found) == 1, f"{title_start!r} in {[c['title'] for c in charts(page)]}"
    return found[0]


def headers(page) -> list[list[str]]:
    """Column headers of every dataframe (glide's accessible table)."""
    return page.evaluate("""() => Array.from(document.querySelectorAll('[data-testid="stDataFrame"]')).map(d =>
        Array.from(d.querySelectorAll('[role="columnheader"]')).map(h => h.textContent.trim()))""")


def open_url(page, url: str) -> None:
    """Open a link in a new session and wait for its first run (a cold server takes a while to start one)."""
    page.goto(url)
    page.get_by_role("heading", name="Evaluation").first.wait_for(timeout=120_000)
    settle(page)
    assert_no_exception(page, url)


def run(page) -> None:
    page.get_by_role("button", name="Run", exact=True).click()
    settle(page)
    assert_no_exception(page, "evaluation after Run")


def shoot_between(page, first: str, last_chart_title: str, name: str) -> None:
    """A screenshot from the heading ``first`` to the bottom of the chart titled ``last_chart_title``."""
    page.set_viewport_size({"width": WIDTH, "height": 4000})
    time.sleep(0.8)
    top = page.get_by_role("heading", name=first).first.bounding_box()["y"] - 10
    bottom = page.evaluate("""(t) => { const g = Array.from(document.querySelectorAll('.js-plotly-plot'))
        .find(g => String((g.layout.title && g.layout.title.text) || '').replace(/<[^>]*>/g, '').startsWith(t));
        return g.getBoundingClientRect().bottom + window.scrollY; }""", last_chart_title) + 10
    page.mouse.move(5, 5)
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SCREENSHOTS / f"{name}.png"), full_page=True,
                    clip={"x": 0, "y": top, "width": WIDTH, "height": bottom - top})
    page.set_viewport_size({"width": WIDTH, "height": 1100})
    time.sleep(0.5)


def test_evaluation_settings_runs_and_links_on_gardens_point(browser, data_root, gp_effnet):
    gp = str(data_root / "GardensPointWalking")
    with streamlit_server("app.py", extra_args=("--client.toolbarMode", "viewer")) as url:
        page = browser.new_page(viewport={"width": WIDTH, "height": 1100})
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))

        # The paper protocol runs by itself on GardensPoint, precision–recall included.
        open_url(page, f"{url}/evaluation?source={quote(gp)}")
        pr = chart(page, "Precision–recall, pooled over runs")
        assert any("queries with no true match" in n for n in pr["names"])
        assert any(m.startswith("own ") for m in pr["metas"])
        body = page.locator("body").inner_text()
        assert "an accepted query of an unknown place (no true match in the database) is a false positive" in body
        page.get_by_role("heading", name="Precision–recall").first.scroll_into_view_if_needed()
        shoot_between(page, "Precision–recall", "Precision–recall, pooled over runs", "pr_curves")

        # Traversal → Run → Dataset page → another descriptor → Evaluation: the traversal, with its results.
        page.get_by_text("traversal: a database traversal against a query traversal").click()
        run(page)
        assert page.get_by_role("heading", name="traversal: a database traversal").count() == 1
        assert chart(page, "Recall@K")["title"] == "Recall@K (one run)"
        go(page, "Dataset")
        page.get_by_text("efficientnet-lite0", exact=False).first.click()
        settle(page)
        go(page, "Evaluation")
        checked = page.locator('[data-testid="stRadio"] input[type="radio"]:checked').first
        assert checked.evaluate("e => e.closest('label').textContent").startswith("traversal")
        assert page.get_by_role("heading", name="traversal: a database traversal").count() == 1
        assert page.get_by_text("descriptor: efficientnet-lite0", exact=False).count() >= 1
        # efficientnet-lite0's automatic θ (1.02) rejects every query: said beside the table
        assert page.get_by_text("rejects every query", exact=False).count() >= 1

        # Three runs kept (paper; traversal with pixels, with efficientnet-lite0): differences, overlaid curves.
        tables = headers(page)
        compare = [h for h in tables if "metric" in h]
        assert compare and any(h.startswith("Δ ") for h in compare[0]), tables
        overlay = chart(page, "Precision–recall of")
        assert sum(m.startswith("pr run") for m in overlay["metas"]) == 3
        recall_before = chart(page, "Recall@K")["y"]

        # A link with the settings reopens them, with the same numbers, in a new session.
        link = page.url
        params = parse_qs(urlparse(link).query)
        assert params["eval_protocol"] == ["traversal"] and params["descriptor"] == ["efficientnet-lite0"]
        fresh = browser.new_page(viewport={"width": WIDTH, "height": 1100})
        open_url(fresh, link)
        checked = fresh.locator('[data-testid="stRadio"] input[type="radio"]:checked').first
        assert checked.evaluate("e => e.closest('label').textContent").startswith("traversal")
        assert chart(fresh, "Recall@K")["y"] == recall_before
        fresh.close()

        # The open set: its widest table keeps the last column in view; the trade-off curves overlay.
        page.get_by_text("open set: a share of places held out").click()
        run(page)
        width = page.evaluate("""() => { const s = document.querySelector('[data-testid="stDataFrame"] .dvn-scroller');
            return [s.scrollWidth, s.clientWidth]; }""")
        assert width[0] <= width[1] + 1, f"the results table scrolls sideways: {width}"
        assert sum(m.startswith("tradeoff run") for m in chart(page, "Open set, run by run")["metas"]) == 1
        assert sum(m.startswith("pr run") for m in chart(page, "Precision–recall of")["metas"]) == 4
        page.get_by_role("heading", name="Runs side by side").first.scroll_into_view_if_needed()
        shoot_between(page, "Runs side by side", "Precision–recall of", "compare")
        assert not errors, errors


def test_a_cold_nordland_load_shows_the_controls_before_the_results(browser, data_root):
    """The form shows while the protocol still runs, not only once it is done."""
    nordland = str(data_root / "Nordland_64x32")
    with streamlit_server("app.py") as url:
        page = browser.new_page(viewport={"width": WIDTH, "height": 1100})
        page.goto(f"{url}/evaluation?source={quote(nordland)}")
        page.get_by_role("button", name="Run", exact=True).wait_for(timeout=300_000)
        state = page.locator('[data-testid="stApp"]').get_attribute("data-test-script-state")
        results = page.get_by_role("heading", name="paper: R random splits").count()
        assert state == "running" and results == 0, (state, results)
        settle(page)
        assert_no_exception(page, "nordland evaluation")
        assert page.get_by_role("heading", name="paper: R random splits").count() == 1
