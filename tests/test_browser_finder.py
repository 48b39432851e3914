"""The Query inspector's finder and best candidates in a real browser (Chromium, ``streamlit run``), on GardensPoint.

Opened from a link that names the finder's kind and method, the page shows them; ◀ previous and
next ▶ move the URL's frame to the library's finds (``numbers.find_query``), past the queries
between places, and say how many they skipped and when they wrapped round; a kind picked in
the page goes into the URL, and that link opened afresh shows it again. A query whose true place
ranks below the best candidates shows the true place's image with its rank. No exception
anywhere. It saves ``inspector_finder.png`` to a temporary folder (no page of the docs shows it).
"""

from __future__ import annotations

import re
from urllib.parse import quote, unquote_plus

import pytest

from streamlit_server import streamlit_server
from test_app import fitted_value
from test_browser import WIDTH, assert_no_exception, browser, settle, shoot  # noqa: F401  (browser: the fixture)
from vpr_explorer.app.ui.candidates import BEST_IMAGES, ordinal
from vpr_explorer.method.places import PlaceSpec
from vpr_explorer.views.numbers import explain_query, find_query, true_place_rank, walked

pytestmark = [pytest.mark.browser, pytest.mark.realdata]


def body(page) -> str:
    return page.locator("body").inner_text().replace("\n", " ")


def frame(page) -> int:
    return int(re.search(r"[?&]frame=(\d+)", page.url).group(1))


def press(page, name: str) -> None:
    before = page.url
    page.get_by_role("button", name=name).click()
    page.wait_for_function("(before) => window.location.href !== before", arg=before, timeout=120_000)
    settle(page)
    assert_no_exception(page, f"inspector after {name}")


def selected(page, label: str) -> str:
    """The value a selectbox shows."""
    return page.get_by_role("combobox", name=label, exact=True).input_value()


def choose(page, label: str, option: str) -> None:
    page.get_by_role("combobox", name=label, exact=True).click()
    page.get_by_role("option", name=option, exact=True).click()
    settle(page)


def test_the_finder_walks_wraps_and_keeps_its_settings_in_the_link(browser, data_root, gardens_point, gp_pixels):
    gp = str(data_root / "GardensPointWalking")
    f, d = fitted_value(gardens_point, gp_pixels, PlaceSpec(3, 10))  # the app's value: night_right, group 3 step 10
    hits = [q for q in range(200)
            if find_query(f, d, after=(q - 1) % 200, kind="rejected", method="global-auto")[0] == q]
    assert hits and 83 not in hits
    with streamlit_server("app.py", extra_args=("--client.toolbarMode", "viewer")) as url:
        page = browser.new_page(viewport={"width": WIDTH, "height": 1100})
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(f"{url}/inspector?source={quote(gp)}&descriptor=pixels&frame=82&inspector_method=global-auto")
        page.get_by_role("heading", name="Query inspector").first.wait_for(timeout=120_000)
        settle(page)
        assert_no_exception(page, "inspector from a link")
        assert selected(page, "Find a query that was") == "rejected (any)"
        assert selected(page, "under") == "global θ, automatic"
        assert "skips the 140 of 200 whose right database images all lie between places" in body(page)

        # next ▶ and ◀ previous: the library's finds, the frames between places skipped and counted
        found, _ = find_query(f, d, after=82, kind="rejected", method="global-auto")
        press(page, "next ▶")
        assert frame(page) == found and found % 10 < 3
        _, skipped = walked(f, 82, found, "next")
        said = body(page)
        assert f"query {found}: the next query rejected under global θ, automatic" in said
        assert f"({skipped} queries between places skipped on the way)" in said
        back, _ = find_query(f, d, after=found, kind="rejected", method="global-auto", direction="previous")
        press(page, "◀ previous")
        assert frame(page) == back

        # round the start: no earlier one
        page.goto(f"{url}/inspector?source={quote(gp)}&descriptor=pixels&frame={hits[0]}"
                  "&inspector_method=global-auto")
        settle(page)
        press(page, "◀ previous")
        assert frame(page) == hits[-1]
        assert f"no earlier one before query {hits[0]}: wrapped round to the end, query {hits[-1]}" in body(page)

        # a kind picked in the page goes into the link; the link opened afresh shows it
        choose(page, "Find a query that was", "a wrong answer (accepted, wrong place)")
        assert "inspector_find=wrong" in page.url
        params = dict(p.split("=", 1) for p in page.url.split("?", 1)[1].split("&"))
        assert unquote_plus(params["inspector_find"]) == "wrong answer"
        assert params["inspector_method"] == "global-auto"
        shared = page.url
        again = browser.new_page(viewport={"width": WIDTH, "height": 1100})
        again.goto(shared)
        again.get_by_role("heading", name="Query inspector").first.wait_for(timeout=120_000)
        settle(again)
        assert_no_exception(again, "inspector from the shared link")
        assert selected(again, "Find a query that was") == "a wrong answer (accepted, wrong place)"
        assert selected(again, "under") == "global θ, automatic"
        again.close()

        # best candidates: a true place ranked below them joins them with its rank
        far = next(q for q in range(0, 200, 10) if true_place_rank(explain_query(f, d, q))[1] > BEST_IMAGES)
        place, rank = true_place_rank(explain_query(f, d, far))
        page.goto(f"{url}/inspector?source={quote(gp)}&descriptor=pixels&frame={far}")
        settle(page)
        assert_no_exception(page, "inspector, a true place ranked low")
        said = body(page)
        assert f"(true place, ranked {ordinal(rank)})" in said and f"P{place}, " in said
        shoot(page, "inspector_finder", for_docs=False)
        assert not errors, errors
        page.close()
