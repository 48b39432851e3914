"""A real browser runs a group/step sweep on GardensPoint and picks a cell: Debian's Chromium against ``streamlit run``.

Opens the sweep page from a link carrying the sweep's settings, runs a small sweep from
the form (pixel descriptors, the traversal protocol: one run a cell), switches the
metric, clicks a heatmap cell of the skip reading, and checks that group/step and the
reading moved into the URL and onto the Places page. Then the same on GardensPoint as a
database/queries layout, whose sweep is of metres along its route. Saves ``sweep.png`` (the README's
screenshot with ``VPR_EXPLORER_SCREENSHOTS=docs``, as ``tests/test_browser.py``).
"""

from __future__ import annotations

import re
from urllib.parse import quote

import pytest

from streamlit_server import streamlit_server
from test_browser import (  # noqa: F401  (browser: the fixture)
    WIDTH,
    assert_no_exception,
    browser,
    click_plot_point,
    go,
    metric,
    settle,
    shoot,
)

pytestmark = [pytest.mark.browser, pytest.mark.realdata]


def shown(page, text: str, timeout: int = 120_000) -> None:
    """Wait until ``text`` is on the page (a fresh server's first link re-routes through the entry script
    before the page runs, so one quiet moment is not the end), then for the run to settle."""
    page.get_by_text(text).first.wait_for(timeout=timeout)
    settle(page)


def param(page, name: str) -> str | None:
    found = re.search(rf"[?&]{name}=([^&]*)", page.url)
    return found.group(1) if found else None


def test_sweep_click_sets_group_and_step_everywhere(browser, data_root, gp_pixels):
    gp = str(data_root / "GardensPointWalking")
    with streamlit_server("app.py", extra_args=("--client.toolbarMode", "viewer")) as url:
        page = browser.new_page(viewport={"width": WIDTH, "height": 1100})
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))

        # a shared link with the sweep's settings: a small sweep starts by itself
        page.goto(f"{url}/sweep?source={quote(gp)}&sweep_groups=2+3&sweep_steps=5&sweep_protocol=traversal")
        shown(page, "In use: group 3, step 10 (stride)")
        assert_no_exception(page, "sweep from a link")
        assert page.get_by_text("4 cells, 4 with valid places, 4 protocol runs").count() == 1  # both readings
        assert len(page.locator('[data-testid="stPlotlyChart"]').all()) == 2  # stride and skip

        # run a sweep from the form
        page.get_by_role("textbox", name="groups (frames per place)").fill("1 2 3")
        page.get_by_role("textbox", name="steps (frames)").fill("3 6 10")
        page.get_by_role("button", name="Run sweep").click()
        shown(page, "18 cells, 18 with valid places")
        assert_no_exception(page, "sweep run from the form")
        assert param(page, "sweep_groups") == "1+2+3" and param(page, "sweep_steps") == "3+6+10"
        assert param(page, "sweep_protocol") == "traversal"
        assert page.get_by_text("18 cells, 18 with valid places").count() == 1
        page.get_by_text("gain in R@1 over the place level").click()
        settle(page)
        assert param(page, "sweep_metric") == "gain"
        shoot(page, "sweep")

        # a click on the skip reading's cell group 3, step 6 uses it on every page
        skip = page.locator('[data-testid="stPlotlyChart"]').nth(1)
        click_plot_point(page, skip, 1, 2)  # category axes: step 6 is column 1, group 3 row 2
        settle(page)
        assert_no_exception(page, "sweep after a cell click")
        assert param(page, "group") == "3" and param(page, "step") == "6" and param(page, "reading") == "skip"
        assert page.get_by_text("group 3, step 6 (skip reading) is now in use on every page").count() == 1
        assert param(page, "sweep_groups") == "1+2+3"  # the sweep's own settings stay

        go(page, "Places")
        assert metric(page, "places") == str((200 - 3) // 9 + 1)  # skip 3/6: a place every 9 frames
        assert page.get_by_text("— in use").count() == 1
        assert param(page, "group") == "3" and param(page, "step") == "6" and param(page, "reading") == "skip"
        assert not errors, errors


def test_sweep_of_metres_on_a_database_queries_layout_sets_metres(browser, data_root, tmp_path):
    """GardensPoint as database/ + queries/ with positions: the sweep runs the database/queries protocol over
    group/step in metres along the route (the layout's default geometry), and a click sets group_m/step_m."""
    from vpr_explorer.data.example_layouts import write_gardens_point_layouts

    source = write_gardens_point_layouts(data_root / "GardensPointWalking", tmp_path)["database-queries"]
    with streamlit_server("app.py") as url:
        page = browser.new_page(viewport={"width": WIDTH, "height": 1100})
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(f"{url}/sweep?source={quote(str(source))}&descriptor=pixels&sweep_groups=25+50"
                  "&sweep_steps=100+200&sweep_readings=stride")
        shown(page, "In use: group 25 m, step 100 m (stride)")
        assert_no_exception(page, "sweep of metres from a link")
        assert page.get_by_text("4 cells, 4 with valid places, 4 protocol runs").count() == 1
        chart = page.locator('[data-testid="stPlotlyChart"]').first
        click_plot_point(page, chart, 1, 1)  # category axes: step 200 is column 1, group 50 row 1
        settle(page)
        assert_no_exception(page, "sweep of metres after a cell click")
        assert float(param(page, "group_m")) == 50 and float(param(page, "step_m")) == 200
        assert param(page, "reading") is None and param(page, "sweep_groups") == "25+50"  # stride: the default
        assert page.get_by_text("group 50 m, step 200 m (stride reading) is now in use on every page").count() == 1
        assert not errors, errors
