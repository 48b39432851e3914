"""The Query inspector's "Every acceptance rule" section under AppTest: on demand, every rule's reasons and figures
as ``views.reasons`` gives them from the bench, another query at once, another value on demand again, bad input as
an error, and every layout of GardensPoint."""

from __future__ import annotations

import numpy as np
import pytest

from test_app import DEMO_SPEC, app, assert_clean, figure, fresh_caches, navigation_mode, page, trace  # noqa: F401
from test_app_every_layout import LAYOUTS, opened, sources  # noqa: F401
from vpr_explorer.data.aligned import database_queries, value_rows
from vpr_explorer.method.places import retrieval_places
from vpr_explorer.protocols import acceptance
from vpr_explorer.protocols.acceptance import RULES, acceptance_report
from vpr_explorer.app.ui.reasons import OPEN
from vpr_explorer.views import reasons as why
from vpr_explorer.views.numbers import thumbnail_label

CHARTS = ("reasons_patch", "reasons_seqslam", "reasons_graph", "reasons_sue")


def charts(at) -> list[str]:
    return [key for key in CHARTS if any(c.proto.id.endswith(f"-{key}") for c in at.get("plotly_chart"))]


def rule_lines(at) -> dict[str, str]:
    """Rule label -> its sentence, from the section's lines ("<mark> **label**: sentence")."""
    labels = {r.label for r in RULES}
    out = {}
    for md in at.markdown:
        head, _, sentence = md.value.partition("**: ")
        label = head.rpartition("**")[2]
        if label in labels and sentence:
            out[label] = sentence
    return out


@pytest.fixture(scope="module")
def demo_bench(demo, demo_pixels):
    """The library's bench on what the section runs by default: snow's frames against day, right within ±2."""
    value = database_queries(demo, "snow", database=["day"], tolerance=2)
    d = demo_pixels[value_rows(value)]
    report = acceptance_report(value, d, labels=retrieval_places(value, DEMO_SPEC)[0])
    return value, d, report


def library_reasons(demo_bench, q):
    value, d, report = demo_bench
    nb = why.neighbourhood(d, value.n_database, *why.reason_rows(report, q))
    return nb, why.rule_reasons(report, q, nb.row(q), value.ground_truth.positives(q))


def inspector(app):
    """The inspector with the section's expander open."""
    at = page(app.run(), "inspector")
    at.session_state[OPEN] = True
    return at.run()


def test_the_closed_section_runs_nothing(app):
    at = page(app.run(), "inspector")
    assert "Every acceptance rule" in [e.label for e in at.expander]
    assert "w_reasons_run" not in [b.key for b in at.button]
    assert "w_reasons_database" not in [b.key for b in at.selectbox]


def test_the_bench_runs_on_demand_and_every_rule_gives_its_reasons(app, demo_bench):
    at = inspector(app)
    at.slider(key="w_frame").set_value(30).run()
    assert not charts(at) and not rule_lines(at)
    assert any("Press the button" in c.value for c in at.caption)
    at.button(key="w_reasons_run").click().run()
    assert_clean(at)
    nb, reasons = library_reasons(demo_bench, 30)
    lines = rule_lines(at)
    assert lines == {r.label: r.sentence for r in reasons}
    assert any("SUE" in i.value and "not metres" in i.value for i in at.info)  # the demo route's unit square
    assert charts(at) == ["reasons_patch", "reasons_seqslam", "reasons_graph"]
    value, d, report = demo_bench
    qt = report.closed.decisions["per-query"].result
    patch = figure(at, "reasons_patch")
    assert trace(patch, "threshold")["x"][0] == pytest.approx(qt.threshold[30])
    assert trace(patch, "score")["x"][0] == pytest.approx(qt.top_score[30])
    res = report.closed.decisions["seqslam"].result
    best = trace(figure(at, "reasons_seqslam"), "best trajectory")
    assert best["y"].tolist() == list(range(25, 36))
    assert best["x"].tolist() == why.seqslam_trajectories(nb, res, 30, ds=10)[0].columns.tolist()
    match = report.closed.decisions["per-query-graph"].result[0]
    assert trace(figure(at, "reasons_graph"), "path")["x"].tolist() == match.path[20:41].tolist()
    # the images beside the lines: one per rule that weighed one
    captions = [c for element in at.image for c in element.captions if c.endswith(("(right)", "(wrong)"))]
    assert captions[:-2] == [f"{thumbnail_label(value, r.image)} ({'right' if r.right else 'wrong'})" for r in reasons
                             if r.image >= 0]
    # the PA-ratio's two nearest images
    two = why.nearest_two(nb.row(30))
    for caption, name, image, d in zip(captions[-2:], ("d₁", "d₂"), two.images, two.distances):
        assert caption.startswith(f"{name} = {d:.4f}") and f"): {thumbnail_label(value, int(image))} (" in caption


def test_another_query_is_explained_at_once_and_an_end_query_says_why_seqslam_has_no_figure(app, demo_bench):
    at = inspector(app)
    at.button(key="w_reasons_run").click().run()
    at.slider(key="w_frame").set_value(2).run()  # no button: the bench is the same
    assert_clean(at)
    _, reasons = library_reasons(demo_bench, 2)
    assert rule_lines(at) == {r.label: r.sentence for r in reasons}
    assert "reasons_seqslam" not in charts(at)
    assert any("query 2 has no centred trajectory" in i.value for i in at.info)


def test_another_database_traversal_asks_for_the_button_again(app):
    at = inspector(app)
    at.button(key="w_reasons_run").click().run()
    assert rule_lines(at)
    at.selectbox(key="w_reasons_database").set_value("night").run()
    assert_clean(at)
    assert not rule_lines(at) and any("Press the button" in c.value for c in at.caption)
    at.button(key="w_reasons_run").click().run()
    assert_clean(at)
    assert rule_lines(at)
    assert any("60 queries × 60 database images (within ±2 frames)" in c.value for c in at.caption)
    at.number_input(key="w_reasons_tolerance").set_value(0).run()
    assert not rule_lines(at)


def test_a_bench_the_library_refuses_is_an_error_and_the_page_stays(app, monkeypatch):
    monkeypatch.setattr(acceptance, "BENCH_PAIRS", 100)
    at = inspector(app)
    at.button(key="w_reasons_run").click().run()
    assert_clean(at, errors=True)
    assert len(at.error) == 1 and "pairs" in at.error[0].value and "at most 100" in at.error[0].value
    assert not rule_lines(at)
    assert figure(at, "bars_margin-weighted")  # the page above the section is whole


@pytest.mark.realdata
@pytest.mark.parametrize("layout", LAYOUTS)
def test_every_layout_of_gardens_point_explains_its_rules(sources, layout):
    at = page(opened(sources[layout]), "inspector")
    at.session_state[OPEN] = True
    at.slider(key="w_frame").set_value(100).run()
    at.button(key="w_reasons_run").click().run()
    assert_clean(at)
    lines = rule_lines(at)
    assert set(lines) == {r.label for r in RULES}
    said = " ".join(i.value for i in at.info)
    if layout in ("database-queries", "manifest"):  # not one route: the sequence rules and their figures say why
        assert lines["SeqSLAM, uniqueness ratio"].startswith("left out: ") and "no database route in order" in said
        assert charts(at) == (["reasons_sue"] if "reasons_sue" in charts(at) else [])
    else:
        assert {"reasons_patch", "reasons_seqslam", "reasons_graph"} <= set(charts(at))
    if "reasons_sue" in charts(at):
        spec = figure(at, "reasons_sue")
        assert len(trace(spec, "top-K")["x"]) == 10
        assert np.isclose(np.sum(np.asarray(trace(spec, "top-K")["customdata"])[:, 1]), 1.0)
    else:
        assert lines["SUE"].startswith("left out: ")
