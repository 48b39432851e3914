"""The walk-through's defects that only a browser shows, in Debian's Chromium against ``streamlit run app.py``.

- Nordland at group 1, step 1 (3,576 places): picking another place (list, overview click,
  rank slider) leaves the overview as it is drawn (no Plotly redraw, the same element), and
  the page shows the new place; the time of each pick is printed (``-s``).
- Thresholds (GardensPoint): the "drawn on one another" note lies above the plot area, clear
  of every threshold line, and no density tick is negative.
- Inspector (GardensPoint): no margin label overlaps a red θ tick.
- Map (GardensPoint as database/queries, 25 m radius): the view opens with the radius circle
  tens of pixels wide, and a click on a query's cross that lies on a database dot selects
  that query.

Pixel descriptors, so nothing is extracted; expectations from the library where a number
is checked.
"""

from __future__ import annotations

import re
from urllib.parse import quote

import pytest

from streamlit_server import streamlit_server
from test_browser import assert_no_exception, browser, click_plot_point, settle, slider  # noqa: F401  (the fixture)

from vpr_explorer.data.example_layouts import write_gardens_point_layouts
from vpr_explorer.method.places import PlaceSpec
from vpr_explorer.views.numbers import explain_query, top_candidates

pytestmark = [pytest.mark.browser, pytest.mark.realdata]
sync_api = pytest.importorskip("playwright.sync_api")

TIMEOUT_MS = 180_000

# The Plotly figure whose title starts with the given text, and its plot area in page pixels.
FIND = """(start) => Array.from(document.querySelectorAll('.js-plotly-plot'))
    .find(gd => gd.layout && gd.layout.title && (gd.layout.title.text || '').replace(/<[^>]*>/g, '').startsWith(start))"""


def plot_by_title(page, start: str):
    handle = page.evaluate_handle(FIND, start)
    assert page.evaluate("gd => !!gd", handle), f"no chart titled {start!r}…"
    return handle


def wait_for_text(page, text: str) -> float:
    """Seconds until ``text`` shows, the script run is over and a frame is painted (-1: not in 2 minutes).

    Call it right after the action, with a ``text`` the page did not show before it.
    """
    return page.evaluate("""async (needle) => { const t0 = performance.now();
        const done = () => document.querySelector('[data-testid="stApp"]').getAttribute('data-test-script-state')
            === 'notRunning' && document.body.innerText.includes(needle);
        while (!done()) { if (performance.now() - t0 > 120000) return -1; await new Promise(r => setTimeout(r, 20)); }
        await new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)));
        return (performance.now() - t0) / 1000; }""", text)


@pytest.fixture(scope="module")
def served(data_root, gp_pixels):
    """One server for the module (the session's descriptor cache: pixels of GardensPoint are there)."""
    with streamlit_server("app.py") as url:
        yield url


def test_nordland_picks_leave_the_overview_drawn(browser, served, data_root):
    from vpr_explorer.data.traversals import load_dataset
    from vpr_explorer.pipeline import dataset_descriptors

    dataset_descriptors(load_dataset(data_root / "Nordland_64x32"), "pixels")  # into the cache the server reads
    source = quote(str(data_root / "Nordland_64x32"))
    page = browser.new_page(viewport={"width": 1440, "height": 1100})
    page.goto(f"{served}/thresholds?source={source}&descriptor=pixels&group=1&step=1", timeout=TIMEOUT_MS)
    page.get_by_text("All 3576 places, sorted by θ_p").first.wait_for(timeout=TIMEOUT_MS)
    settle(page)
    # the first session of a cold server draws its overview once more on its first pick (its first run computed
    # the places, descriptors and figures); a second session, on the server's caches, is what a pick looks like
    page.reload(timeout=TIMEOUT_MS)
    page.get_by_text("All 3576 places, sorted by θ_p").first.wait_for(timeout=TIMEOUT_MS)
    settle(page)
    assert_no_exception(page, "thresholds, Nordland at group 1, step 1")
    overview = plot_by_title(page, "All 3576 places")
    page.evaluate("gd => { gd.__probe = true; gd.__redraws = 0; gd.on('plotly_afterplot', () => gd.__redraws++); }",
                  overview)
    order = page.evaluate("gd => Array.from(gd._fullData[0].customdata)", overview)  # places in θ_p order
    assert len(order) == 3576

    def untouched() -> bool:
        gd = plot_by_title(page, "All 3576 places")
        return page.evaluate("gd => gd.__probe === true && gd.__redraws === 0", gd)

    def rank_said() -> tuple[int, int]:
        """The place and rank the page says: "P<place> ranks <rank> of 3,576"."""
        found = re.search(r"P(\d+) ranks ([\d,]+) of 3,576", page.locator("body").inner_text())
        return int(found.group(1)), int(found.group(2).replace(",", ""))

    seconds = []
    box = page.locator('[data-testid="stSelectbox"]').filter(has_text="Place").first
    box.locator("input").click()
    page.keyboard.type("P1234 (")
    page.wait_for_timeout(500)
    page.keyboard.press("Enter")
    seconds.append(wait_for_text(page, "P1234 ranks"))
    assert untouched(), "the overview was drawn again for a pick from the list"
    assert page.get_by_text("P1234: negative mixture").count() >= 1

    # a click on the dot of rank 101 (dots a fifth of a pixel apart: it picks one of its neighbours at worst)
    chart = page.locator('[data-testid="stPlotlyChart"]').filter(has_text="All 3576 places").first
    click_plot_point(page, chart, 100, page.evaluate("gd => gd._fullData[0].y[100]", overview))
    seconds.append(page.evaluate("""async () => { const t0 = performance.now();
        while (/P1234 ranks/.test(document.body.innerText) ||
               document.querySelector('[data-testid="stApp"]').getAttribute('data-test-script-state') !== 'notRunning') {
            if (performance.now() - t0 > 120000) return -1; await new Promise(r => setTimeout(r, 20)); }
        await new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)));
        return (performance.now() - t0) / 1000; }"""))
    place, rank = rank_said()
    assert place == order[rank - 1] and abs(rank - 101) <= 3, (place, rank)
    assert untouched(), "the overview was drawn again for a click on it"

    thumb = slider(page, "θ_p rank of the place")
    thumb.focus()
    thumb.press("ArrowRight")
    seconds.append(wait_for_text(page, f"P{order[rank]} ranks {rank + 1} of 3,576"))
    assert untouched(), "the overview was drawn again for a step of the rank slider"
    settle(page)
    assert_no_exception(page, "thresholds after three picks")
    assert all(s >= 0 for s in seconds), seconds
    print(f"Nordland 3,576 places, seconds per pick (list, overview click, rank slider): {seconds}")


def test_thresholds_note_clear_of_the_lines_and_no_negative_density_tick(browser, served, data_root):
    gp = quote(str(data_root / "GardensPointWalking"))
    page = browser.new_page(viewport={"width": 1440, "height": 1100})
    page.goto(f"{served}/thresholds?source={gp}&descriptor=pixels&place=11&k=0", timeout=TIMEOUT_MS)
    page.get_by_text("P11: negative mixture").first.wait_for(timeout=TIMEOUT_MS)
    settle(page)
    assert_no_exception(page, "thresholds")
    gd = plot_by_title(page, "P11: negative mixture")
    found = page.evaluate("""gd => {
        const area = gd.querySelector('.nsewdrag').getBoundingClientRect();
        const notes = Array.from(gd.querySelectorAll('.annotation')).filter(a => a.textContent.startsWith('drawn on'))
            .map(a => a.getBoundingClientRect());
        const lines = Array.from(gd.querySelectorAll('.scatterlayer .trace'))
            .filter((t, i) => /^(θ|global)/.test(gd.data[i].meta || ''))
            .map(t => t.getBoundingClientRect());
        const ticks = Array.from(gd.querySelectorAll('.ytick text')).map(t => t.textContent);
        return {area: [area.top, area.bottom], notes: notes.map(n => [n.top, n.bottom, n.left, n.right]),
                lines: lines.map(l => [l.top, l.bottom, l.left, l.right]), ticks}; }""", gd)
    assert found["notes"], "no 'drawn on one another' note at k = 0"
    assert found["lines"]
    for top, bottom, left, right in found["notes"]:
        assert bottom <= found["area"][0] + 1, (found["notes"], found["area"])  # above the plot area
        for l_top, _, l_left, l_right in found["lines"]:
            assert bottom <= l_top + 1 or right < l_left or l_right < left, ("a line crosses the note", found)
    values = [float(t.replace("−", "-")) for t in found["ticks"]]
    assert values and min(values) == 0, found["ticks"]


def test_inspector_margin_labels_clear_of_the_theta_ticks(browser, served, data_root, gardens_point, gp_pixels):
    from test_app import fitted_value

    f, d = fitted_value(gardens_point, gp_pixels, PlaceSpec(3, 10))

    def close_above(q: int) -> bool:
        """Some candidate's θ lies just above its raw_p: a label over the dot would sit on the tick."""
        dec = explain_query(f, d, q)
        gap = dec.thresholds["weighted"][top_candidates(dec)] - dec.raw[top_candidates(dec)]
        return bool(((gap >= 0) & (gap < 0.02)).any())

    frame = next(q for q in range(f.dataset.n_queries) if close_above(q))
    gp = quote(str(data_root / "GardensPointWalking"))
    page = browser.new_page(viewport={"width": 1440, "height": 1100})
    page.goto(f"{served}/inspector?source={gp}&descriptor=pixels&frame={frame}", timeout=TIMEOUT_MS)
    page.get_by_text("Candidate places: raw_p, threshold and margin").wait_for(timeout=TIMEOUT_MS)
    settle(page)
    assert_no_exception(page, f"inspector, frame {frame}")
    overlaps = page.evaluate("""() => Array.from(document.querySelectorAll('.js-plotly-plot'))
        .filter(gd => gd.data && gd.data.length > 1 && gd.data[1].meta === 'theta')
        .map(gd => {
            const traces = gd.querySelectorAll('.scatterlayer .trace');
            const labels = Array.from(traces[0].querySelectorAll('.textpoint text')).map(t => t.getBoundingClientRect());
            const ticks = Array.from(traces[1].querySelectorAll('.point')).map(t => t.getBoundingClientRect());
            const hit = (a, b) => a.left < b.right && b.left < a.right && a.top < b.bottom && b.top < a.bottom;
            return {title: gd.layout.title.text, labels: labels.length,
                    overlaps: labels.filter(l => ticks.some(t => hit(l, t))).length}; })""")
    assert overlaps and all(o["labels"] > 0 for o in overlaps), overlaps
    assert not [o for o in overlaps if o["overlaps"]], overlaps


def test_the_map_opens_on_the_query_and_a_cross_on_a_dot_selects_it(browser, served, data_root, tmp_path_factory):
    path = write_gardens_point_layouts(data_root / "GardensPointWalking",
                                       tmp_path_factory.mktemp("map_layouts"))["database-queries"]
    page = browser.new_page(viewport={"width": 1440, "height": 1100})
    page.goto(f"{served}/places?source={quote(str(path))}&descriptor=pixels&frame=60", timeout=TIMEOUT_MS)
    page.get_by_text("query 60 with its radius").first.wait_for(timeout=TIMEOUT_MS)
    settle(page)
    assert_no_exception(page, "places, database/queries")
    gd = plot_by_title(page, "20 places; query 60")
    size = page.evaluate("""gd => { const L = gd._fullLayout;
        const ring = gd._fullData.find(t => t.meta === 'radius');
        const xs = Array.from(ring.x).map(x => L.xaxis.d2p(x)), ys = Array.from(ring.y).map(y => L.yaxis.d2p(y));
        return [Math.max(...xs) - Math.min(...xs), Math.max(...ys) - Math.min(...ys)]; }""", gd)
    assert min(size) >= 40, f"the 25 m circle is {size} pixels wide: a dot under the star"
    q62 = page.evaluate("""gd => { const q = gd._fullData.find(t => t.meta === 'queries'); return [q.x[62], q.y[62]];
        }""", gd)
    dots = page.evaluate("""([gd, xy]) => gd._fullData.filter(t => (t.meta || '').startsWith('database'))
        .some(t => Array.from(t.x).some((x, i) => x === xy[0] && t.y[i] === xy[1]))""", [gd, q62])
    assert dots, "query 62's cross does not lie on a database dot here"
    chart = page.locator('[data-testid="stPlotlyChart"]').filter(has_text="20 places; query 60").first
    click_plot_point(page, chart, q62[0], q62[1])
    assert wait_for_text(page, "(query 62)") >= 0, "the click on query 62's cross selected nothing"
    settle(page)
    assert "frame=62" in page.url
    assert_no_exception(page, "places after the click")
