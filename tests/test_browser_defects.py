"""Two defects a walk-through found, walked in Debian's Chromium against ``streamlit run app.py``.

- Nordland 64x32, winter frame 0: the margin rule answers a place far down the raw_p
  order; every method's chart in the Query inspector must still carry its answer
  (outlined) and the right place (starred). Expected from ``numbers.explain_query``
  on the dataset value directly.
- Playback: a recorded frame opens in the Query inspector on the same query traversal
  and frame.
"""

from __future__ import annotations

import re
from urllib.parse import quote

import numpy as np
import pytest

from streamlit_server import streamlit_server
from test_browser import assert_no_exception, browser, settle  # noqa: F401  (browser: the fixture)

from vpr_explorer.data.aligned import database_queries, value_rows
from vpr_explorer.method.places import PlaceGeometry, PlaceSpec
from vpr_explorer.method.retrieval import METHODS_BY_KEY
from vpr_explorer.views.numbers import RetrievalPlaces, explain_query, fit_retrieval
from vpr_explorer.views.numbers import LIVE_METHODS

pytestmark = [pytest.mark.browser, pytest.mark.realdata]
sync_api = pytest.importorskip("playwright.sync_api")

TIMEOUT_MS = 180_000


@pytest.fixture(scope="module")
def nordland_pixels(data_root):
    """Nordland's pixel descriptors, into the session cache the server shares (so it does not extract them)."""
    from vpr_explorer.data.traversals import load_dataset
    from vpr_explorer.pipeline import dataset_descriptors

    ds = load_dataset(data_root / "Nordland_64x32")
    return ds, dataset_descriptors(ds, "pixels")


def charts(page) -> dict[str, dict]:
    """Every drawn Plotly chart's title (tags stripped) -> its first trace's x labels, places and outlines."""
    found = page.evaluate("""() => Object.fromEntries(Array.from(document.querySelectorAll('.js-plotly-plot'))
        .filter(gd => gd.layout && gd.layout.title && gd.data && gd.data.length)
        .map(gd => [gd.layout.title.text.replace(/<[^>]*>/g, ''), {
                    outline: gd.data[0].marker && gd.data[0].marker.line ? gd.data[0].marker.line.color : null,
                    labels: Array.from(gd.data[0].x || [])}]))""")
    for chart in found.values():  # labels are "P12" or "★ P12" (a right place)
        chart["places"] = [int(label.rsplit("P", 1)[1]) for label in chart["labels"]]
    return found


def test_nordland_inspector_bars_carry_every_answer(browser, data_root, nordland_pixels):
    ds, d = nordland_pixels
    value = database_queries(ds, "winter")  # the app's value: summer against winter, query q is winter frame q
    rows = value_rows(value)
    d = d if rows is None else d[rows]
    f = fit_retrieval(d, value, RetrievalPlaces(PlaceGeometry.FRAMES, spec=PlaceSpec(3, 10)))
    dec = explain_query(f, d, 0)
    assert dec.answer("margin-weighted") not in np.argsort(-dec.raw, kind="stable")[:8]  # the case at issue
    source = quote(str(data_root / "Nordland_64x32"))
    with streamlit_server("app.py") as url:
        page = browser.new_page(viewport={"width": 1440, "height": 1100})
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(f"{url}/inspector?source={source}&descriptor=pixels&query=winter&frame=0", timeout=TIMEOUT_MS)
        page.get_by_text("Candidate places: raw_p, threshold and margin").wait_for(timeout=TIMEOUT_MS)
        page.wait_for_function(f"""() => Array.from(document.querySelectorAll('.js-plotly-plot'))
            .filter(gd => gd.data && gd.data.length).length >= {len(LIVE_METHODS)}""", timeout=TIMEOUT_MS)
        settle(page)
        assert_no_exception(page, "inspector on Nordland winter frame 0")
        shown = charts(page)
        for key in LIVE_METHODS:
            assert METHODS_BY_KEY[key].label in shown, list(shown)
            chart = shown[METHODS_BY_KEY[key].label]
            answer = dec.answer(key)
            outlined = [p for p, c in zip(chart["places"], chart["outline"]) if c == "#000"]
            assert outlined == ([answer] if answer >= 0 else []), (key, chart)
            for p in dec.true_places:
                assert f"★ P{p}" in chart["labels"], (key, chart["labels"])
        assert f"accepted as place {dec.answer('margin-weighted')}" in page.locator("body").inner_text()
        assert errors == []
        page.close()


def test_a_playback_frame_opens_in_the_inspector(browser):
    with streamlit_server("app.py") as url:
        page = browser.new_page(viewport={"width": 1440, "height": 1100})
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        # rerun's web viewer (a large wasm app in the iframe) is not under test here: not loading it keeps
        # the test short; tests/test_playback_browser.py checks the viewer itself.
        page.route(re.compile(r"^http://127\.0\.0\.1:\d+/"),
                   lambda route: route.continue_() if route.request.url.startswith(url) else route.abort())
        page.goto(f"{url}/playback?source=demo&descriptor=pixels&group=2&step=2&query=night", timeout=TIMEOUT_MS)
        page.get_by_role("button", name="Record and play").click()
        page.get_by_text(re.compile(r"Recording [0-9a-f]{32}")).wait_for(timeout=TIMEOUT_MS)
        settle(page)
        box = page.get_by_label("frame", exact=True)
        box.fill("17")
        box.press("Enter")
        settle(page)
        page.get_by_role("button", name="Open frame 17 in the Query inspector").click()
        page.wait_for_url(re.compile(r".*/inspector\?.*"), timeout=TIMEOUT_MS)
        settle(page)
        assert_no_exception(page, "inspector opened from playback")
        assert "frame=17" in page.url and "query=night" in page.url
        assert page.get_by_text("query: night · frame 17").count() >= 1
        assert page.get_by_role("heading", name="Query inspector").count() == 1
        assert errors == []
        page.close()
