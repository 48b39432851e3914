"""Shared links under AppTest: each page's link carries the view fields it reads and its own settings, nothing of
the other pages; a page's settings stay in the session when another page is shown; "θ_p(k) built on" is in the
Thresholds page's link.
"""

from __future__ import annotations

from streamlit.testing.v1 import AppTest

from test_app import app, assert_clean, fresh_caches, navigation_mode, page  # noqa: F401  (fixtures)
from vpr_explorer.app import ENTRY
from vpr_explorer.app.ui.state import PAGE_FIELDS, PAGE_PREFIXES, View




VIEW_FIELDS = {f for f in View.__dataclass_fields__}


def own_and_view(params: dict) -> tuple[set[str], set[str]]:
    return {k for k in params if k not in VIEW_FIELDS}, {k for k in params if k in VIEW_FIELDS}


def test_every_page_lists_fields_of_the_view():
    assert set(PAGE_FIELDS) == {"home", "places", "thresholds", "inspector", "evaluation", "playback", "sweep"}
    for page_name, fields in PAGE_FIELDS.items():
        assert set(fields) <= VIEW_FIELDS, page_name
        assert {"source", "descriptor", "descriptors"} <= set(fields)  # every page shows a dataset's descriptors
    assert set(PAGE_FIELDS["inspector"]) == VIEW_FIELDS


def test_each_link_carries_only_its_own_page(app):
    at = page(app.run(), "inspector")
    at.slider(key="w_frame").set_value(31).run()
    at.slider(key="w_k").set_value(1.5).run()
    at.selectbox(key="w_find_kind").set_value("wrong answer").run()
    assert_clean(at)
    inspector = dict(at.query_params)
    assert inspector["frame"] == "31" and inspector["k"] == "1.5" and inspector["inspector_find"] == "wrong answer"

    at = page(at, "home")
    own, fields = own_and_view(dict(at.query_params))
    assert own == set() and fields <= set(PAGE_FIELDS["home"])  # no frame, no k, no finder
    assert "frame" not in at.query_params and "k" not in at.query_params

    at = page(at, "evaluation")
    assert_clean(at)
    own, fields = own_and_view(dict(at.query_params))
    assert own and all(k.startswith(PAGE_PREFIXES["evaluation"]) for k in own)
    assert "frame" not in fields and "k" not in fields

    at = page(at, "playback")
    assert at.query_params["frame"] == "31" and at.query_params["k"] == "1.5"
    assert not own_and_view(dict(at.query_params))[0]

    at = page(at, "inspector")  # back: the page's own settings come back with it
    assert dict(at.query_params) == inspector
    assert at.selectbox(key="w_find_kind").value == "wrong answer"


def test_a_link_to_one_page_sets_no_other_pages_settings(app):
    app.query_params.update({"frame": "12", "eval_protocol": "traversal"})
    at = page(app.run(), "thresholds")
    assert "eval_protocol" not in at.query_params and "frame" not in at.query_params
    at = page(at, "evaluation")  # the link's settings of this page were kept in the session
    assert at.query_params["eval_protocol"] == "traversal"
    assert at.radio(key="w_protocol").value == "traversal"


def test_threshold_method_is_in_the_link(app):
    at = page(app.run(), "thresholds")
    assert at.radio(key="w_method").value == "weighted" and "thresholds_method" not in at.query_params
    at.radio(key="w_method").set_value("simple").run()
    assert at.query_params["thresholds_method"] == "simple"
    at = page(at, "places")
    assert "thresholds_method" not in at.query_params
    at = page(at, "thresholds")
    assert at.radio(key="w_method").value == "simple" and at.query_params["thresholds_method"] == "simple"

    fresh = AppTest.from_file(str(ENTRY), default_timeout=60)
    fresh.query_params.update({"thresholds_method": "simple"})
    fresh = page(fresh.run(), "thresholds")
    assert_clean(fresh)
    assert fresh.radio(key="w_method").value == "simple"


def test_a_bad_threshold_method_in_a_link_is_said_and_dropped(app):
    app.query_params.update({"thresholds_method": "median"})
    at = page(app.run(), "thresholds")
    assert any("thresholds_method='median'" in w.value for w in at.warning)
    assert at.radio(key="w_method").value == "weighted" and "thresholds_method" not in at.query_params


def test_a_link_never_names_a_hub_repository(app, tmp_path):
    """A hub:DIR descriptor runs the repository's hubconf.py: a link naming one is refused before anything is read."""
    repo = tmp_path / "gmberton_MegaLoc_main"
    repo.mkdir()
    marker = tmp_path / "ran"
    (repo / "hubconf.py").write_text(f"open({str(marker)!r}, 'w').close()\ndef get_trained_model():\n    pass\n")
    app.query_params.update({"descriptor": f"hub:{repo}"})
    at = app.run()
    assert any("descriptor='hub:" in w.value and "a link never does" in w.value for w in at.warning)
    at = page(at, "places")
    assert_clean(at)
    assert not marker.exists() and "descriptor" not in at.query_params
