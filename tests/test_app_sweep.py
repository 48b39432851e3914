"""The Group/step sweep page under Streamlit's AppTest: a link's settings, a refused one, bad form input, a
large dataset that waits for the button, and the database/queries layouts GardensPoint is written in (frames,
metres along the route, places the layout names) (``tests/test_browser_sweep.py`` clicks a cell in Chromium)."""

from __future__ import annotations

import json

import pytest
import streamlit as st
from streamlit.testing.v1 import AppTest

from test_app import decode, downloads  # noqa: F401  (a fixture)
from vpr_explorer.app import ENTRY, PAGES
from vpr_explorer.method.places import MetricPlaceSpec, PlaceGeometry, PlaceSpec

pytestmark = pytest.mark.realdata

TIMEOUT = 120


@pytest.fixture(autouse=True)
def fresh(monkeypatch):
    """Empty Streamlit caches, and every run routed through the entry script's ``st.navigation`` (as
    ``tests/test_app.py`` does: AppTest would otherwise run the page in the old multipage mode)."""
    from streamlit.runtime.pages_manager import PagesManager

    st.cache_data.clear()
    st.cache_resource.clear()
    init = PagesManager.__init__

    def init_after_navigation(self, *args, **kwargs):
        init(self, *args, **kwargs)
        PagesManager.uses_pages_directory = False

    monkeypatch.setattr(PagesManager, "__init__", init_after_navigation)


def sweep_page(params: dict) -> AppTest:
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT)
    at.query_params.update(params)
    return at.switch_page(str(PAGES / "sweep.py")).run()


def chart(at: AppTest, key: str):
    found = [c for c in at.get("plotly_chart") if c.proto.id.endswith(f"-{key}")]
    assert len(found) == 1, [c.proto.id for c in at.get("plotly_chart")]
    return found[0]


def test_a_link_runs_its_sweep_and_keeps_it_in_the_url(data_root, gp_pixels):
    gp = str(data_root / "GardensPointWalking")
    at = sweep_page({"source": gp, "sweep_groups": "3 2", "sweep_steps": "5", "sweep_protocol": "traversal",
                     "sweep_metric": "auc"})
    assert not at.exception and not at.error, [e.value for e in at.exception]
    spec = json.loads(chart(at, "sweep_skip").proto.spec)
    heat = next(t for t in spec["data"] if t.get("meta") == "values")
    assert heat["y"] == ["2", "3"] and heat["x"] == ["5"]
    for name, value in (("sweep_groups", "2 3"), ("sweep_protocol", "traversal"), ("sweep_metric", "auc"),
                        ("sweep_readings", "stride skip")):
        got = at.query_params[name]
        assert (got[0] if isinstance(got, list) else got) == value
    assert any("4 cells, 4 with valid places" in c.value for c in at.caption)
    assert any("no unknown places" in c.value for c in at.caption)  # why the rejection grid is empty
    # the form: a bad group is refused by name and the sweep in use is kept
    at.text_input(key="w_sweep_groups").set_value("2 x")
    at.button[0].click().run()
    assert any("groups '2 x'" in e.value for e in at.error)
    got = at.query_params["sweep_groups"]
    assert (got[0] if isinstance(got, list) else got) == "2 3"


def test_a_refused_link_setting_falls_back_alone(data_root, gp_pixels):
    gp = str(data_root / "GardensPointWalking")
    at = sweep_page({"source": gp, "sweep_groups": "2", "sweep_steps": "0 5", "sweep_protocol": "traversal",
                     "sweep_readings": "skip"})
    assert not at.exception
    assert any("sweep_steps='0 5'" in w.value and "steps=0" in w.value for w in at.warning)
    got = at.query_params["sweep_protocol"]
    assert (got[0] if isinstance(got, list) else got) == "traversal"  # the others are kept
    assert [c.proto.id.rsplit("-", 1)[-1] for c in at.get("plotly_chart")] == ["sweep_skip"]


def test_a_large_sweep_states_its_cost_and_waits_for_the_button(data_root):
    at = sweep_page({"source": str(data_root / "Nordland_64x32"), "sweep_groups": "3", "sweep_steps": "10",
                     "sweep_protocol": "traversal", "sweep_readings": "stride"})
    assert not at.exception and not at.error
    assert any("does not start by itself" in w.value and "image pairs" in w.value for w in at.warning)
    assert any("1 cell, 1 with valid places, 1 protocol run to do on 7,152 images" in c.value for c in at.caption)
    assert not at.get("plotly_chart")  # nothing ran


# --------------------------------------------------------------------------- the layouts GardensPoint is written in


@pytest.fixture(scope="module")
def layouts(data_root, tmp_path_factory):
    from vpr_explorer.data.example_layouts import write_gardens_point_layouts

    return write_gardens_point_layouts(data_root / "GardensPointWalking", tmp_path_factory.mktemp("sweep_page"))


def heat(at: AppTest, reading: str) -> dict:
    spec = json.loads(chart(at, f"sweep_{reading}").proto.spec)
    return {"values": next(t for t in spec["data"] if t.get("meta") == "values"), "layout": spec["layout"]}


@pytest.mark.parametrize("layout, params, places", [
    ("vpr-bench", {"sweep_groups": "3 2", "sweep_steps": "5 10"}, lambda g, s: {"spec": PlaceSpec(g, s)}),
    ("database-queries", {"sweep_groups": "25 50.5", "sweep_steps": "100"},
     lambda g, s: {"metric": MetricPlaceSpec(g, s, "stride", "route")}),
])
def test_a_database_queries_layout_sweeps_the_database_queries_protocol(layouts, layout, params, places):
    """Frames where the layout has no positions, metres along the route (its default geometry) where it has:
    every heatmap cell is the database/queries protocol's R@1 of those places."""
    from vpr_explorer.pipeline import dataset_descriptors, evaluate_retrieval, open_dataset

    at = sweep_page({"source": str(layouts[layout]), "descriptor": "pixels", "sweep_readings": "stride", **params})
    assert not at.exception and not at.error, [e.value for e in at.exception]
    assert at.radio(key="w_sweep_protocol").value == "database-queries"
    assert len(at.radio(key="w_sweep_protocol").options) == 1
    assert any("no unknown-place query" in c.value for c in at.caption)  # why the rejection grid is empty
    value = open_dataset(layouts[layout])
    d = dataset_descriptors(value, "pixels")
    shown = heat(at, "stride")
    unit = "frames" if "spec" in places(1, 1) else "m"
    assert shown["layout"]["xaxis"]["title"]["text"] == f"step ({unit})"
    z = decode(shown["values"]["z"])
    for i, g in enumerate(shown["values"]["y"]):
        for j, s in enumerate(shown["values"]["x"]):
            g_, s_ = (float(x) if "." in x else int(x) for x in (g, s))
            ev = evaluate_retrieval(value, d, **places(g_, s_))
            assert z[i][j] == pytest.approx(100 * ev.row("place-baseline").recall[1][0], abs=1e-9), (g, s)


def test_a_link_to_a_protocol_of_aligned_traversals_is_refused_by_name(layouts):
    at = sweep_page({"source": str(layouts["vpr-bench"]), "descriptor": "pixels", "sweep_groups": "2",
                     "sweep_steps": "5", "sweep_protocol": "paper", "sweep_readings": "stride"})
    assert not at.exception and not at.error
    assert any("sweep_protocol='paper'" in w.value and "it needs aligned traversals" in w.value for w in at.warning)
    got = at.query_params["sweep_protocol"]
    assert (got[0] if isinstance(got, list) else got) == "database-queries"
    assert len(at.get("plotly_chart")) == 1


def test_places_the_layout_names_leave_nothing_to_sweep(layouts):
    at = sweep_page({"source": str(layouts["manifest"]), "descriptor": "pixels"})
    assert not at.exception and not at.error
    assert any("Group/step do not apply: the layout names its places" in i.value for i in at.info)
    assert not at.get("plotly_chart")


# --------------------------------------------------------------------------- protocols, spreads, one colour scale


def test_the_page_says_which_protocol_a_cell_runs_and_where_the_places_numbers_come_from(data_root, gp_pixels):
    gp = str(data_root / "GardensPointWalking")
    at = sweep_page({"source": gp, "sweep_groups": "3", "sweep_steps": "5 10", "sweep_runs": "3"})
    assert not at.exception and not at.error, [e.value for e in at.exception]
    assert at.radio(key="w_sweep_protocol").value == "paper"  # the default
    note = next(i.value for i in at.info if "Each cell runs" in i.value)
    assert "paper protocol: 3 random splits" in note and "The **Places** page shows another protocol" in note
    assert "the traversal protocol, the query traversal night_right against the database day_left + day_right" in note
    # the method list shows labels, not keys
    method = at.selectbox(key="w_sweep_method")
    assert method.value == "margin-weighted" and "margin, weighted θ" in method.options
    assert "margin-weighted" not in method.options
    # both readings on one colour scale, said in a caption; the hover gives mean ± std and the interval
    stride, skip = heat(at, "stride")["values"], heat(at, "skip")["values"]
    assert (stride["zmin"], stride["zmax"]) == (skip["zmin"], skip["zmax"])
    assert any(c.value.startswith("One colour scale: both readings share it") for c in at.caption)
    spec = json.loads(chart(at, "sweep_stride").proto.spec)
    hover = next(t for t in spec["data"] if t.get("meta") == "cells")["text"]
    assert all(" ± " in h and "[95% " in h and "3 splits" in h for h in hover)
    assert any(c.value.startswith("In use, over the splits: place-level baseline R@1 (%)") for c in at.caption)


def test_traversal_cells_are_the_places_pages_numbers(data_root, gardens_point, gp_pixels, downloads):
    from vpr_explorer.data.aligned import database_queries, value_rows
    from vpr_explorer.method.places import make_places
    from vpr_explorer.pipeline import run_protocol
    from vpr_explorer.views import numbers as views

    gp = str(data_root / "GardensPointWalking")
    at = sweep_page({"source": gp, "sweep_groups": "2 3", "sweep_steps": "10", "sweep_protocol": "traversal",
                     "sweep_readings": "stride", "sweep_metric": "gain"})
    assert not at.exception and not at.error, [e.value for e in at.exception]
    assert any("Method: margin, weighted θ." in c.value for c in at.caption)  # its label, not its key
    note = next(i.value for i in at.info if "Each cell runs" in i.value)
    assert "on the **Places** page's traversals: night_right queried against day_left + day_right" in note
    z = decode(heat(at, "stride")["values"]["z"])
    value = database_queries(gardens_point, query=2, database=[0, 1])  # what the Places page decides
    rows = value_rows(value)
    d = gp_pixels if rows is None else gp_pixels[rows]
    for i, g in enumerate((2, 3)):
        spec = PlaceSpec(g, 10)
        ev = run_protocol("traversal", gardens_point, make_places(gardens_point, spec), gp_pixels,
                          database=["day_left", "day_right"], queries="night_right")
        places = views.RetrievalPlaces(PlaceGeometry.FRAMES, spec=spec)
        overview = views.overview(views.fit_retrieval(d, value, places), d)
        gain = ev.row("margin-weighted").recall[1][0] - ev.row("place-baseline").recall[1][0]
        assert z[i][0] == pytest.approx(100 * gain, abs=1e-9)
        assert ev.row("place-baseline").recall[1][0] == pytest.approx(overview.recall1["place-baseline"])
    button = next(b for b in at.get("download_button") if b.proto.label == "Download CSV")
    text = downloads(button).decode()
    header = text.splitlines()[0].split(",")
    for name in ("n_splits", "r1_std", "r1_ci95_low", "r1_ci95_high", "gain_p", "gain_test"):
        assert name in header, name
    assert "night_right" in text and "day_left day_right" in text  # the traversals the cells ran
