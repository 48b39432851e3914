"""A real browser opens GardensPoint in the database-queries layout with a descriptor file: Chromium against ``streamlit run``.

The layout is written in a temporary folder from the real images (``example_layouts``), the
project's efficientnet-lite0 descriptors saved as an ``.npz`` (a file "computed elsewhere").
The walk: the link opens the dataset and the file, the Places page draws the map and
regroups in metres, the Query inspector opens the next rejected query and names its right
place (checked against the library), and bad input (a descriptor path that does not exist,
a file with missing images, a radius of -1 in the link) shows one message naming it, never
a traceback.
"""

from __future__ import annotations

from urllib.parse import quote

import numpy as np
import pytest

from streamlit_server import streamlit_server
from test_browser import WIDTH, assert_no_exception, browser, go, metric, settle, shoot  # noqa: F401
from vpr_explorer.descriptors.imported import write_descriptor_file
from vpr_explorer.data.example_layouts import write_gardens_point_layouts
from vpr_explorer.pipeline import dataset_descriptors, open_dataset
from vpr_explorer.method.places import MetricPlaceSpec, PlaceGeometry
from vpr_explorer.views.numbers import RetrievalPlaces, find_query, fit_retrieval

pytestmark = [pytest.mark.browser, pytest.mark.realdata]


def number(page, label: str, value: float, url_has: str) -> None:
    """Type ``value`` into the number input labelled ``label``; wait until the URL holds ``url_has`` and the rerun ends.

    Waiting for the URL, not only for the run state: on a loaded machine the rerun may start
    after ``settle``'s first look.
    """
    box = page.locator('[data-testid="stNumberInput"]', has_text=label).first.locator("input")
    box.fill(f"{value:g}")
    box.press("Enter")
    page.wait_for_function("s => window.location.href.includes(s)", arg=url_has, timeout=120_000)
    settle(page)


def body(page) -> str:
    return page.locator("body").inner_text().replace("\n", " ")


def test_a_database_queries_layout_with_a_descriptor_file_in_a_real_browser(browser, data_root, gp_effnet,
                                                                            tmp_path):
    dq_root = write_gardens_point_layouts(data_root / "GardensPointWalking", tmp_path / "layouts")["database-queries"]
    dq = open_dataset(dq_root)
    d = np.asarray(dataset_descriptors(dq, "efficientnet-lite0"))  # the session's cache: same image content
    npz = tmp_path / "effnet_gp.npz"
    write_descriptor_file(npz, d, dq.image_paths, dq.root)
    short = tmp_path / "short.npz"
    write_descriptor_file(short, d[:390], dq.image_paths[:390], dq.root)
    link = f"?source={quote(str(dq_root))}&descriptors={quote(str(npz))}"

    with streamlit_server("app.py", extra_args=("--client.toolbarMode", "viewer")) as url:
        page = browser.new_page(viewport={"width": WIDTH, "height": 1100})
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))

        page.goto(f"{url}/{link}")
        settle(page)
        assert_no_exception(page, "home")
        assert "effnet_gp descriptors ready: 400 × 1280" in body(page)
        assert "200 database and 200 query images (database-queries)" in body(page)

        # Places: the map is drawn (every database image and query a marker), then regroup in metres.
        go(page, "Places")
        assert metric(page, "places") == "20"
        chart = page.locator('[data-testid="stPlotlyChart"]', has_text="with its radius").first
        assert chart.locator(".scatterlayer .point").count() >= 400
        assert "east (m from 500,000)" in chart.inner_text()
        shoot(page, "layout_places")
        number(page, "step (m)", 50, "step_m=50.0")
        number(page, "group (m)", 35, "group_m=35.0")
        assert_no_exception(page, "places after regrouping in metres")
        assert metric(page, "places") == "40" and metric(page, "database images per place") == "4"
        assert "group_m=35.0" in page.url and "step_m=50.0" in page.url

        # Query inspector: the next rejected query, with its right place from the ground truth.
        go(page, "Query inspector")
        page.get_by_role("button", name="next ▶").click()
        page.wait_for_function("() => window.location.href.includes('frame=')", timeout=120_000)
        settle(page)
        assert_no_exception(page, "inspector, next rejected query")
        f = fit_retrieval(d, dq, RetrievalPlaces(PlaceGeometry.LATTICE,
                                                 metric=MetricPlaceSpec(35.0, 50.0, "stride", "lattice")))
        found, _ = find_query(f, d, after=0, kind="rejected", method="margin-weighted")
        assert f"frame={found}" in page.url
        right = ", ".join(f"P{p}" for p in np.flatnonzero(f.right_places([found])[0]))
        text = body(page)
        assert f"Right place(s): {right}, holding its right database images (within 25 m)" in text
        assert "margin, weighted θ: rejected: the best place" in text
        shoot(page, "layout_inspector")

        go(page, "Evaluation")
        assert "ground truth: within 25 m" in body(page) and "0 with no right database image" in body(page)
        go(page, "Thresholds")  # one place's mixture, its database images and the queries right in it
        assert_no_exception(page, "thresholds")
        assert "negative mixture, scores and thresholds" in body(page) and "(raw_p " in body(page)

        # Bad input: one message naming it, the app still usable.
        page.goto(f"{url}/?source={quote(str(dq_root))}&descriptors={quote(str(tmp_path / 'nope.npz'))}")
        settle(page)
        assert_no_exception(page, "a descriptor file that does not exist")
        assert page.locator('[data-testid="stAlertContentError"]', has_text="nope.npz: no such file").count() == 1
        page.goto(f"{url}/?source={quote(str(dq_root))}&descriptors={quote(str(short))}")
        settle(page)
        assert_no_exception(page, "a descriptor file with missing images")
        assert page.locator('[data-testid="stAlertContentError"]',
                            has_text="10 of the dataset's 400 images have no descriptor").count() == 1
        page.goto(f"{url}/{link}&radius=-1")
        settle(page)
        assert_no_exception(page, "radius=-1 in the link")
        assert "radius='-1': must be a positive distance in metres" in body(page)
        assert "within 25 m" in body(page)
        assert not errors, errors
        page.close()
