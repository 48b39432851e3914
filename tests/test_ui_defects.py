"""Defects a walk through the app found on the Thresholds page, the inspector's bars, the map and Nordland.

- Thresholds: every symbol the page uses (μ⁻, s_p, μ⁺, θ_p(k), adaptive k) is defined on the
  page with the place's values, adaptive k with its formula and its clip; the mixture's
  density axis has no tick below 0; the "drawn on one another" note stands above the plot
  area, where no threshold line reaches; a place is "P7" everywhere on the page; the
  database images a place's θ_p is fitted on are shown apart from its queries.
- Inspector: a margin label stands on the side of its dot away from the θ tick.
- Map (database/queries): the view opens on the selected query's neighbourhood; a click on a
  database dot under a query's cross selects that query; the readings of step speak of
  metres in metres; thumbnails are never captioned with a cut-off "@east@north@…" name.
- Nordland at group 1, step 1 (3,576 places): the overview is the same figure whichever
  place is picked (the browser redraws nothing; ``test_browser_ui_defects``), a rank slider
  walks the places in θ_p order; the route strips have no legend to sit on their axis title.

Expected values come from the library (``fit_retrieval``, ``place_detail``,
``explain_query``) and plain references written here.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from streamlit.testing.v1 import AppTest

# the autouse fixtures of test_app (fresh caches, navigation mode) apply here too
from test_app import assert_clean, figure, fitted_value, fresh_caches, navigation_mode, page, trace  # noqa: F401
from vpr_explorer.app import ENTRY
from vpr_explorer.data.example_layouts import write_gardens_point_layouts
from vpr_explorer.method.places import MetricPlaceSpec, PlaceGeometry, PlaceSpec, frame_places
from vpr_explorer.method.stats import SIGMA_FLOOR
from vpr_explorer.pipeline import dataset_descriptors, open_dataset
from vpr_explorer.views import maps, plots
from vpr_explorer.views.numbers import (
    DEFAULT_GROUP_M,
    DEFAULT_STEP_M,
    LIVE_METHODS,
    THUMBNAIL_CHARS,
    RetrievalPlaces,
    explain_query,
    fit_retrieval,
    place_detail,
    thumbnail_label,
    top_candidates,
)

pytestmark = pytest.mark.realdata

TIMEOUT = 180
GP_SPEC = PlaceSpec(3, 10)  # the app's default on GardensPoint
ONE = PlaceSpec(1, 1)  # every frame a place: Nordland's 3,576 places
PLACE_WORDS = re.compile(r"\b[Pp]lace \d")  # "place 7" / "Place 7": the page says "P7"


def opened(**params) -> AppTest:
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT)
    at.query_params.update(descriptor="pixels", **{k: str(v) for k, v in params.items()})
    return at.run()


def texts(at: AppTest) -> list[str]:
    """Every text the page shows in its body: titles, markdown, captions, notes, metric and widget labels."""
    found = [e.value for kind in ("title", "subheader", "markdown", "caption", "info", "warning", "success")
             for e in at.get(kind)]
    found += [m.label for m in at.metric] + [w.label for kind in ("selectbox", "slider", "radio") for w in at.get(kind)]
    return found


def figure_texts(spec: dict) -> list[str]:
    """A Plotly spec's title, axis titles, annotations, trace names, hover templates and hover texts."""
    layout = spec["layout"]
    found = [layout.get("title", {}).get("text", "")]
    found += [layout.get(a, {}).get("title", {}).get("text", "") for a in ("xaxis", "yaxis")]
    found += [a.get("text", "") for a in layout.get("annotations", [])]
    for t in spec["data"]:
        found += [t.get("name", ""), t.get("hovertemplate", "")]
        found += [x for x in (t.get("text") or []) if isinstance(x, str)] if isinstance(t.get("text"), list) else []
    return [f for f in found if f]


def captions(at: AppTest) -> list[str]:
    return [img.caption for element in at.image for img in element.proto.imgs]


@pytest.fixture(scope="module")
def gp(gardens_point, gp_pixels):
    """GardensPoint as the app reads it by default: ``(fitted, descriptors)`` at group 3, step 10."""
    return fitted_value(gardens_point, gp_pixels, GP_SPEC)


@pytest.fixture(scope="module")
def nordland_one(data_root):
    """Nordland 64x32 with pixels, every frame a place: ``(dataset, fitted, descriptors)``."""
    from vpr_explorer.data.traversals import load_dataset

    ds = load_dataset(data_root / "Nordland_64x32")
    f, d = fitted_value(ds, dataset_descriptors(ds, "pixels"), ONE)
    assert f.n_places == 3576
    return ds, f, d


@pytest.fixture(scope="module")
def dq(data_root, tmp_path_factory):
    """GardensPoint written as a database/queries layout (UTM file names, 25 m radius) and its pixel descriptors."""
    path = write_gardens_point_layouts(data_root / "GardensPointWalking",
                                       tmp_path_factory.mktemp("ui_layouts"))["database-queries"]
    ds = open_dataset(path)
    return path, ds, np.asarray(dataset_descriptors(ds, "pixels"))


# --------------------------------------------------------------------------- thresholds: the figure


@pytest.mark.parametrize("top, ticks", [(6.9, [0, 2, 4, 6]), (1.15, [0, 0.5, 1.0]), (10.0, [0, 2, 4, 6, 8, 10]),
                                        (0.042, [0, 0.01, 0.02, 0.03, 0.04]), (0.0, [0]), (float("nan"), [0])])
def test_density_ticks_by_hand(top, ticks):
    np.testing.assert_allclose(plots.density_ticks(top), ticks)


def test_the_mixture_has_no_negative_density_tick_and_keeps_its_rugs(gp):
    f, d = gp
    for p in range(f.n_places):
        detail = place_detail(f, d, p)
        fig = plots.mixture_figure(detail, k=1.0)
        y = fig.layout.yaxis
        ticks = np.asarray(y.tickvals, dtype=float)
        assert y.tickmode == "array" and ticks[0] == 0 and np.all(np.diff(ticks) > 0), (p, ticks)
        assert ticks[-1] <= y.range[1] < ticks[-1] + 2 * (ticks[1] - ticks[0]), (p, ticks, y.range)
        rugs = [t for t in fig.data if t.meta in ("positives", "query_raw")]
        assert rugs and all(y.range[0] < min(t.y) < 0 for t in rugs)  # the rugs still show, under 0


def test_the_drawn_on_one_another_note_stands_above_every_threshold_line(gp):
    f, d = gp
    detail = place_detail(f, d, 7)
    fig = plots.mixture_figure(detail, k=0.0)  # θ_p(k=0) is θ_p weighted: drawn on it
    notes = [a for a in fig.layout.annotations if a.name == "coincident"]
    assert len(notes) == 1 and "θ_p weighted" in notes[0].text and "θ_p(k)" in notes[0].text
    note = notes[0]
    # above the plot area (paper y = 1, anchored at its bottom), where the lines stop (their top is the axis top)
    assert (note.yref, note.y, note.yanchor) == ("paper", 1, "bottom")
    lines = [t for t in fig.data if t.meta in plots.LINE_COLOURS or t.meta == "θ_p(k)"]
    assert lines and all(max(t.y) <= fig.layout.yaxis.range[1] for t in lines)
    assert fig.layout.margin.t >= 40 + plots.NOTE_PX * len(notes)  # room for the note under the pinned title
    assert fig.layout.title.yref == "container" and fig.layout.title.yanchor == "top"
    assert fig.layout.title.text.startswith("P7: ")
    apart = plots.mixture_figure(detail, k=1.0)  # θ_p(k) apart; θ_p simple and weighted may still coincide
    kept = [a for a in apart.layout.annotations if a.name == "coincident"]
    assert not any("θ_p(k)" in a.text for a in kept)
    assert apart.layout.margin.t == 40 + plots.NOTE_PX * len(kept)


def test_the_theta_histogram_note_stands_above_its_plot_too(gp):
    f, _ = gp
    fig = plots.theta_histogram(f.model.theta, f.model.auto, user_theta=f.model.auto)  # the user's θ on the auto one
    notes = [a for a in fig.layout.annotations if a.name == "coincident"]
    assert len(notes) == 1 and (notes[0].y, notes[0].yanchor) == (1, "bottom")
    assert fig.layout.margin.t >= 40 + plots.NOTE_PX


# --------------------------------------------------------------------------- thresholds: the page


def test_the_thresholds_page_says_p7_and_defines_every_symbol(gardens_point, gp):
    f, d = gp
    model = f.model
    # the place whose adaptive k the clip changes most: the page must say it was clipped
    gap = (model.positive_mean - model.negative_mean) / (2 * np.maximum(model.spread, SIGMA_FLOOR))
    p = int(np.nanargmax(np.abs(gap - np.clip(gap, 1.0, 2.0))))
    at = page(opened(source=gardens_point.root, place=p), "thresholds")
    assert_clean(at)
    detail = place_detail(f, d, p)
    assert at.selectbox(key="w_place").value == p
    assert at.selectbox(key="w_place").format_func(p) == f"P{p} (θ_p {model.theta['weighted'][p]:.3f})"
    shown = texts(at) + figure_texts(figure(at, "mixture")) + figure_texts(figure(at, "overview"))
    assert not [t for t in shown if PLACE_WORDS.search(t)], [t for t in shown if PLACE_WORDS.search(t)]
    assert figure(at, "mixture")["layout"]["title"]["text"].startswith(f"P{p}: ")
    symbols = next(m.value for m in at.markdown if m.value.startswith(f"**The symbols, with P{p}'s values.**"))
    for line in ("**μ⁻**", "**s_p**", "**μ⁺**", "**θ_p(k) = θ_p + k·s_p**", "**adaptive k = clip((μ⁺ − μ⁻) / (2·s_p), 1, 2)**"):
        assert f"- {line}" in symbols, line
    mu_pos, mu_neg, s_p = model.positive_mean[p], model.negative_mean[p], model.spread[p]
    assert f"Here {mu_neg:.3f}." in symbols and f"Here {s_p:.3f}." in symbols and f"Here {mu_pos:.3f}." in symbols
    raw_k = (mu_pos - mu_neg) / (2 * max(s_p, SIGMA_FLOOR))  # before the clip
    assert 1.0 <= detail.k_adaptive <= 2.0 and (raw_k < 1.0 or raw_k > 2.0)
    assert f"(μ⁺ − μ⁻) / (2·s_p) = {raw_k:.2f}, clipped to {detail.k_adaptive:.2f}" in symbols
    assert f"θ_p(adaptive k) weighted = {detail.theta_k(detail.k_adaptive):.3f}" in symbols
    teaching = next(m.value for m in at.markdown if m.value.startswith("θ_p is a weighted"))
    assert f"adaptive k = {detail.k_adaptive:.2f}, both told below" in teaching


def test_the_thresholds_page_shows_the_fitted_database_images_apart_from_the_queries(gardens_point, gp):
    f, d = gp
    at = page(opened(source=gardens_point.root, place=4), "thresholds")
    assert_clean(at)
    detail = place_detail(f, d, 4)
    n_db, n_q = len(detail.images), len(detail.query_images)
    assert (n_db, n_q) == (6, 3)  # 3 frames × the 2 database traversals; the query traversal's 3 frames
    said = [c.value for c in at.caption]
    assert f"**The {n_db} database images of P4**: the mixture, θ_p and the same-place scores are fitted on these " \
           "alone." in said
    assert any(c.startswith(f"**The {n_q} queries whose right places include P4**: not part of the fit") for c in said)
    shown = captions(at)
    assert [c.endswith("(database)") for c in shown] == [True] * n_db + [False] * n_q
    assert all("(query, raw_p " in c for c in shown[n_db:])
    assert len(detail.mu) == n_db  # the mixture has one component per database image, no query among them


def test_a_rank_slider_walks_the_places_in_theta_order(gardens_point, gp):
    f, _ = gp
    order = np.argsort(f.model.theta["weighted"], kind="stable")
    at = page(opened(source=gardens_point.root), "thresholds")
    for rank in (1, 20, 7):
        at.slider(key="w_place_rank").set_value(rank).run()
        assert_clean(at)
        assert at.session_state["view"].place == order[rank - 1]
        assert at.selectbox(key="w_place").value == order[rank - 1]
        assert f"P{order[rank - 1]} ranks {rank} of 20 by weighted θ_p" in " ".join(c.value for c in at.caption)


# --------------------------------------------------------------------------- inspector: margin labels


def test_margin_labels_stand_away_from_the_theta_ticks(gp):
    f, d = gp
    checked = below = 0
    for q in range(0, f.dataset.n_queries, 7):
        dec = explain_query(f, d, q)
        cands = top_candidates(dec)
        for key in LIVE_METHODS:
            fig = plots.candidate_bars(dec, key, cands)
            dots = next(t for t in fig.data if t.meta == "raw_p")
            ticks = [t for t in fig.data if t.meta == "theta"]
            if not ticks:
                assert set(dots.textposition) == {"top center"}
                continue
            lo = fig.layout.yaxis.range[0]
            for raw, theta, where in zip(dots.y, ticks[0].y, dots.textposition):
                # plain rule: the label goes where the tick is not
                assert where == ("bottom center" if theta >= raw else "top center"), (q, key, raw, theta, where)
                below += where == "bottom center"
                checked += 1
            span = fig.layout.yaxis.range[1] - lo
            if "bottom center" in dots.textposition:  # room under the lowest dot for its label
                assert min(dots.y) - lo >= 0.1 * span
    assert checked > 100 and below > 0


# --------------------------------------------------------------------------- the map


def test_the_neighbourhood_by_hand():
    assert maps.neighbourhood((10.0, 20.0), 25.0) == ([-90.0, 110.0], [-80.0, 120.0])  # 4 radii
    assert maps.neighbourhood((0.0, 0.0), None) == ([-50.0, 50.0], [-50.0, 50.0])  # at least 50 m
    assert maps.neighbourhood((0.0, 0.0), 5.0) == ([-50.0, 50.0], [-50.0, 50.0])
    xr, yr = maps.neighbourhood((0.0, 0.0), 25.0, np.array([[130.0, 0.0], [0.0, -10.0]]))
    assert xr == [-155.0, 155.0] and yr == [-155.0, 155.0]  # the farthest positive, a radius to spare


def test_picked_query_by_hand():
    q_xy = np.array([[1000.0, 2000.0], [1010.0, 2000.0], [1100.0, 2000.0], [1010.0, 2000.0]])
    origin = (1000.0, 2000.0)
    assert maps.picked_query([{"customdata": 2, "x": 0.0, "y": 0.0}], q_xy, origin) == 2  # a cross
    assert maps.picked_query([{"x": 10.0, "y": 0.0}], q_xy, origin) == 1  # a dot under queries 1 and 3: the first
    assert maps.picked_query([{"x": 97.0, "y": 4.0}], q_xy, origin) == 2  # 5 m away
    assert maps.picked_query([{"x": 97.0, "y": 4.0}], q_xy, origin, near=4.0) is None
    assert maps.picked_query([{"x": 55.0, "y": 40.0}], q_xy, origin) is None  # no query within 25 m
    assert maps.picked_query([{"customdata": True, "x": 0.0, "y": 0.0}], q_xy, origin) == 0  # a flag is no index
    assert maps.picked_query([], q_xy, origin) is None


def test_the_map_opens_on_the_query_and_a_dot_under_its_cross_selects_it(dq):
    path, ds, d = dq
    at = page(opened(source=path, frame=60), "places")
    assert_clean(at)
    spec = figure(at, "layout_map")
    centre = trace(spec, "selected query")
    cx, cy = centre["x"][0], centre["y"][0]
    xr, yr = spec["layout"]["xaxis"]["range"], spec["layout"]["yaxis"]["range"]
    assert (xr, yr) == maps.neighbourhood((cx, cy), 25.0, np.stack([trace(spec, "positives")["x"],
                                                                    trace(spec, "positives")["y"]], axis=1))
    ring = trace(spec, "radius")
    assert xr[0] < ring["x"].min() and ring["x"].max() < xr[1] and yr[0] < ring["y"].min() and ring["y"].max() < yr[1]
    assert xr[1] - xr[0] <= 8 * 25.0 + 2 * 25.0  # not the 2 km route: the circle is not a dot under the star
    # query 62 lies on database image 62 (same UTM position): plotly hands a click there to the database dot
    origin = ds.query_xy[60] - (cx, cy)
    dots = {m: trace(spec, m) for m in ("database places", "database, between places")}
    assert all("customdata" not in t for t in dots.values())  # a click there names no query by itself
    hit = [{"curve_number": 0, "point_index": i, "x": float(t["x"][i]), "y": float(t["y"][i])}
           for t in dots.values() for i in range(len(t["x"]))
           if np.allclose((t["x"][i], t["y"][i]), ds.query_xy[62] - origin)]
    assert len(hit) == 1
    assert maps.picked_query(hit, ds.query_xy, origin, near=25.0) == 62


def test_the_readings_of_step_speak_of_the_unit_in_use(dq):
    path, _, _ = dq
    at = page(opened(source=path), "places")
    assert at.radio(key="w_geometry").value == "lattice"  # metres
    labels = list(at.radio(key="w_reading").options)  # as the page words them
    assert all("metres" in label and "frames" not in label for label in labels), labels
    at.radio(key="w_geometry").set_value("frames").run()  # group/step count database images in listed order
    assert_clean(at)
    labels = list(at.radio(key="w_reading").options)  # as the page words them
    assert all("database images" in label and "frames" not in label for label in labels), labels
    assert [m.value for m in at.markdown if m.value.startswith(("stride:", "skip:"))][0].startswith(
        "stride: a place starts every `step` database images")


def test_gardens_point_frames_still_say_frames(gardens_point):
    at = page(opened(source=gardens_point.root), "places")
    labels = list(at.radio(key="w_reading").options)  # as the page words them
    assert labels == ["stride: a place starts every `step` frames (authors' code, paper's numbers)",
                      "skip: take `group` frames, skip the next `step` (paper's text)"]


def test_thumbnails_of_utm_named_images_are_not_cut_off_names(dq):
    path, ds, d = dq
    at = page(opened(source=path, place=7), "thresholds")
    assert_clean(at)
    f = fit_retrieval(d, ds, RetrievalPlaces(PlaceGeometry.LATTICE, metric=MetricPlaceSpec(
        DEFAULT_GROUP_M, DEFAULT_STEP_M, "stride", PlaceGeometry.LATTICE)))
    detail = place_detail(f, d, 7)
    assert all(len(Path(ds.database_paths[i]).name) > 40 for i in detail.images)  # "@500700.00@6960000.00@…@.jpg"
    assert captions(at) == ([f"database image {i}" for i in detail.images] +
                            [f"query {i - ds.n_database} (raw_p {r:.3f})"
                             for i, r in zip(detail.query_images, detail.query_raw)])


def test_the_inspector_and_its_reasons_name_utm_images_by_index(dq):
    """The candidates' thumbnails and the bench's reason pictures: "database image N", never a name cut short."""
    path, ds, _ = dq
    at = page(opened(source=path, frame=5), "inspector")
    assert_clean(at)
    shown = captions(at)
    assert "query: query 5" in shown
    names = {Path(p).name for p in (*ds.database_paths, *ds.query_paths)}
    for caption in shown:
        if any(name in caption for name in names):
            continue  # the query's own picture, full width, names its file whole
        assert "@" not in caption and all(len(word) <= THUMBNAIL_CHARS for word in caption.split()), caption
    assert any(re.search(r"database image \d+", c) for c in shown)
    assert thumbnail_label(ds, 3) == "database image 3" and thumbnail_label(ds, 4, query=True) == "query 4"


def test_the_dataset_page_strips_are_not_captioned_with_cut_off_names(dq):
    path, ds, _ = dq
    at = opened(source=path)
    assert_clean(at)
    said = [c.value for c in at.caption if c.value.startswith(("**database**: images", "**queries**: images"))]
    assert len(said) == 2
    shown = [[int(i) for i in re.findall(r"\d+", s.split(": images ")[1].split(" of ")[0])] for s in said]
    assert captions(at) == [f"image {i}" for strip in shown for i in strip]  # the names are 57 characters


# --------------------------------------------------------------------------- Nordland's 3,576 places


def test_the_nordland_overview_is_one_figure_whichever_place_is_picked(nordland_one):
    _, f, _ = nordland_one
    model = f.model
    theta = model.theta["weighted"]
    figs = [plots.places_overview(theta, model.positive_mean, model.negative_mean, selected=p) for p in (None, 5, 3000)]
    assert len({fig.to_json() for fig in figs}) == 1
    fig = figs[1]
    dots = next(t for t in fig.data if t.meta == "theta")
    assert dots.type == "scattergl"
    order = np.argsort(theta, kind="stable")
    np.testing.assert_array_equal(dots.customdata, order)  # a click on a dot names its place
    np.testing.assert_allclose(dots.y, theta[order])
    assert all(h.startswith(f"P{p}:") for p, h in zip(order, dots.text))
    assert {t.meta: t.mode for t in fig.data if t.meta != "theta"} == {"positive_mean": "lines",
                                                                     "negative_mean": "lines"}
    assert dots.unselected.marker.opacity == 1  # a click restyles nothing either


def test_nordland_places_are_picked_without_redrawing_the_overview(data_root, nordland_one):
    _, f, _ = nordland_one
    order = np.argsort(f.model.theta["weighted"], kind="stable")
    at = page(opened(source=data_root / "Nordland_64x32", group=1, step=1), "thresholds")
    assert_clean(at)
    before = figure(at, "overview")
    assert at.selectbox(key="w_place").format_func(1234) == f"P1234 (θ_p {f.model.theta['weighted'][1234]:.3f})"
    at.selectbox(key="w_place").set_value(1234).run()
    assert_clean(at)
    assert at.session_state["view"].place == 1234
    at.slider(key="w_place_rank").set_value(100).run()
    assert_clean(at)
    assert at.session_state["view"].place == order[99]
    assert figure(at, "mixture")["layout"]["title"]["text"].startswith(f"P{order[99]}: ")
    assert figure(at, "overview") == before  # the same spec: the browser has nothing to redraw


def test_the_route_strips_have_no_legend_on_their_axis_title(nordland_one):
    ds, _, _ = nordland_one
    fig = plots.route_figure(frame_places(ds.n_frames, ONE), ["winter", "summer"])
    assert fig.layout.showlegend is False
    assert "grey ticks: skipped frames" in fig.layout.xaxis.title.text
    skipped = frame_places(ds.n_frames, PlaceSpec(1, 2))  # every other frame skipped
    fig = plots.route_figure(skipped, ["winter", "summer"])
    assert fig.layout.showlegend is False
    np.testing.assert_array_equal(next(t for t in fig.data if t.meta == "skipped winter").x,
                                  np.flatnonzero(skipped[:plots.ROUTE_FRAMES_SHOWN] < 0))
